//! `crispen::slice` and `crispen slice` against the real slicers (PrusaSlicer and
//! CuraEngine, installed by scripts/setup) and real failing programs (shell scripts
//! standing in for a slicer that crashes, hangs or writes nonsense).
//!
//! Each G-code job is re-read here independently of the library's own check, so a bug in
//! the check cannot hide a bad job.

use crispen::daemon::prepare::steps::{prepare, prepare_one, SliceRequest, Step, Target};
use crispen::enhance::Strength;
use crispen::machine::Machine;
use crispen::slice::{SliceError, SliceReport, SliceSettings, SlicerKind};
use std::path::{Path, PathBuf};
use std::time::{Duration, Instant};

use crate::common;

fn machine(name: &str) -> Machine {
    Machine::builtin(name).expect("a built-in machine")
}

/// Prepares a model for an Ultimaker 2 into `out`.
fn slice(
    req: &SliceRequest,
    out: &Path,
    progress: &mut dyn FnMut(Step),
) -> Result<SliceReport, SliceError> {
    slice_for(req, "ultimaker2", out, progress)
}

fn slice_for(
    req: &SliceRequest,
    machine_name: &str,
    out: &Path,
    progress: &mut dyn FnMut(Step),
) -> Result<SliceReport, SliceError> {
    let target = Target {
        machine: machine(machine_name),
        output: out.to_path_buf(),
        keep_mesh: None,
    };
    prepare_one(req, target, progress)
}

fn spot() -> PathBuf {
    common::model("spot.obj")
}

fn bunny() -> PathBuf {
    common::model("bunny.obj")
}

/// Facts read straight from a G-code file.
#[derive(Debug)]
struct Job {
    text: String,
    /// Line numbers (1-based) of the first M190, M109 and extrusion with XY movement.
    first_bed_wait: usize,
    first_nozzle_wait: usize,
    first_extrusion: usize,
    min_xy: [f64; 2],
    max_xy: [f64; 2],
    top_z: f64,
    layers: usize,
}

fn read_job(path: &Path) -> Job {
    let text = std::fs::read_to_string(path).expect("G-code written");
    let (mut x, mut y, mut z, mut e) = (0.0f64, 0.0f64, 0.0f64, 0.0f64);
    let mut job = Job {
        text: String::new(),
        first_bed_wait: 0,
        first_nozzle_wait: 0,
        first_extrusion: 0,
        min_xy: [f64::MAX; 2],
        max_xy: [f64::MIN; 2],
        top_z: 0.0,
        layers: 0,
    };
    let mut zs: Vec<f64> = Vec::new();
    for (i, line) in text.lines().enumerate() {
        let code = line.split(';').next().unwrap().trim();
        let mut words = code.split_whitespace();
        match words.next() {
            Some("M190") if job.first_bed_wait == 0 => job.first_bed_wait = i + 1,
            Some("M109") if job.first_nozzle_wait == 0 => job.first_nozzle_wait = i + 1,
            Some("G92") => {
                for w in words {
                    if let Some(v) = w.strip_prefix('E') {
                        e = v.parse().unwrap();
                    }
                }
            }
            Some("G0") | Some("G1") => {
                let (mut nx, mut ny, mut nz, mut ne) = (x, y, z, e);
                for w in words {
                    let v = || w[1..].parse::<f64>().unwrap();
                    match &w[..1] {
                        "X" => nx = v(),
                        "Y" => ny = v(),
                        "Z" => nz = v(),
                        "E" => ne = v(),
                        _ => {}
                    }
                }
                if ne > e && (nx != x || ny != y) && code.starts_with("G1") {
                    if job.first_extrusion == 0 {
                        job.first_extrusion = i + 1;
                    }
                    job.min_xy = [job.min_xy[0].min(nx), job.min_xy[1].min(ny)];
                    job.max_xy = [job.max_xy[0].max(nx), job.max_xy[1].max(ny)];
                    job.top_z = job.top_z.max(nz);
                    if !zs.iter().any(|q| (q - nz).abs() < 1e-6) {
                        zs.push(nz);
                    }
                }
                (x, y, z, e) = (nx, ny, nz, ne);
            }
            Some("G91") => break, // the end code; the print itself is absolute
            _ => {}
        }
    }
    job.layers = zs.len();
    job.text = text;
    job
}

/// A job that heats before printing, prints on the bed, centred, up to the asked height
/// (within three layers: slicers drop pointed tips narrower than the nozzle).
fn assert_good_job(job: &Job, height: f64, layer: f64) {
    assert!(job.first_extrusion > 0, "no extrusion");
    assert!(
        job.first_bed_wait > 0 && job.first_bed_wait < job.first_extrusion,
        "bed not heated before printing: {job:?}"
    );
    assert!(job.first_nozzle_wait > 0 && job.first_nozzle_wait < job.first_extrusion);
    for k in 0..2 {
        assert!(job.min_xy[k] >= 0.0 && job.max_xy[k] <= 223.0, "{job:?}");
        // Centred: the print's middle is within a few mm of the bed's (the skirt is
        // symmetric around the model).
        let mid = (job.min_xy[k] + job.max_xy[k]) / 2.0;
        assert!((mid - 111.5).abs() < 3.0, "not centred: {mid} in {job:?}");
    }
    assert!(
        (job.top_z - height).abs() <= 3.0 * layer + 1e-6,
        "top at {} for height {height}",
        job.top_z
    );
    let expected_layers = height / layer;
    assert!(
        (job.layers as f64 - expected_layers).abs() <= 4.0,
        "{} layers, expected about {expected_layers}",
        job.layers
    );
    assert!(
        job.text.contains("M84"),
        "the end code turns the motors off"
    );
}

fn write_script(dir: &Path, name: &str, body: &str) -> PathBuf {
    use std::os::unix::fs::PermissionsExt;
    let path = dir.join(name);
    std::fs::write(&path, format!("#!/bin/sh\n{body}\n")).unwrap();
    std::fs::set_permissions(&path, std::fs::Permissions::from_mode(0o755)).unwrap();
    path
}

#[test]
fn prusaslicer_slices_spot_and_the_enhanced_job_differs_from_the_unmodified_one() {
    let dir = tempfile::tempdir().unwrap();
    let enhanced_out = dir.path().join("spot.gcode");
    let mut steps = Vec::new();
    let out_path = PathBuf::from(&enhanced_out);
    let mut req = SliceRequest::new(spot(), 30.0);
    req.strength = Strength::Lambda2(20.0);
    let report =
        slice(&req, &out_path, &mut |s| steps.push(s.describe())).expect("PrusaSlicer slices spot");
    assert_eq!(report.slicer, SlicerKind::Prusa);
    assert!(report
        .slicer_version
        .as_deref()
        .is_some_and(|v| v.starts_with("PrusaSlicer 2.")));
    assert_eq!(report.enhancement.lambda2, Some(20.0));
    assert!(report.enhancement.report.is_some());
    assert!(report.estimated_print_time_s.is_some_and(|t| t > 60.0));
    assert!(report.filament_mm.is_some_and(|mm| mm > 10.0));
    assert!(report.filament_g.is_some_and(|g| g > 0.0));
    assert!((report.model_size_mm[2] - 30.0).abs() < 1e-6);
    assert_eq!(steps.first(), Some(&"loading".to_string()));
    assert!(steps.iter().any(|s| s.starts_with("enhancing")));
    assert_eq!(steps.last().unwrap(), "checking the G-code for ultimaker2");
    let job = read_job(&enhanced_out);
    assert_good_job(&job, 30.0, 0.2);
    assert_eq!(report.layer_count, job.layers);
    assert!(job.text.contains("M109 S210") && job.text.contains("M190 S60"));

    let plain_out = dir.path().join("spot-plain.gcode");
    let out_path = PathBuf::from(&plain_out);
    let mut req = SliceRequest::new(spot(), 30.0);
    req.strength = Strength::Off;
    let plain = slice(&req, &out_path, &mut |_| {}).expect("unmodified spot slices");
    assert_eq!(plain.enhancement.lambda2, None);
    assert_eq!(plain.enhancement.mode, "unmodified");
    let plain_job = read_job(&plain_out);
    assert_good_job(&plain_job, 30.0, 0.2);
    // Compare only the moves: the header has a timestamp.
    let moves = |t: &str| -> Vec<String> {
        t.lines()
            .filter(|l| l.starts_with("G1 "))
            .map(str::to_string)
            .collect()
    };
    assert_ne!(moves(&job.text), moves(&plain_job.text));
}

#[test]
fn curaengine_slices_the_bunny_with_overrides_through_the_cli() {
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("bunny.gcode");
    let output = std::process::Command::new(env!("CARGO_BIN_EXE_crispen"))
        .args([
            "slice",
            bunny().to_str().unwrap(),
            "-o",
            out.to_str().unwrap(),
        ])
        .args(["--height", "25", "--slicer", "cura", "--json", "--up", "y"])
        .args(["--set", "layer_height=0.15", "--set", "infill=10"])
        .args(["--set", "nozzle_temp=215", "--set", "material=petg"])
        .output()
        .expect("crispen runs");
    assert!(
        output.status.success(),
        "{}",
        String::from_utf8_lossy(&output.stderr)
    );
    let report: serde_json::Value = serde_json::from_slice(&output.stdout).expect("JSON report");
    assert_eq!(report["slicer"], "cura");
    assert!(report["slicer_version"]
        .as_str()
        .unwrap()
        .starts_with("CuraEngine 4."));
    assert_eq!(report["material"], "petg");
    assert_eq!(report["up"], "y");
    // Standing up, the bunny is taller than deep; lying on its side (Z up) it is not.
    let size = &report["model_size_mm"];
    assert!(size[1].as_f64().unwrap() < 25.0, "{size}");
    assert_eq!(report["nozzle_temp_c"], 215.0);
    assert_eq!(report["bed_temp_c"], 85.0);
    assert_eq!(report["layer_height_mm"], 0.15);
    assert_eq!(report["enhancement"]["mode"], "enhanced");
    assert!(report["estimated_print_time_s"].as_f64().unwrap() > 60.0);
    assert!(report["filament_mm"].as_f64().unwrap() > 10.0);
    let job = read_job(&out);
    assert_good_job(&job, 25.0, 0.15);
    assert_eq!(report["layer_count"].as_u64().unwrap() as usize, job.layers);
    assert!(job.text.contains("M109 S215") && job.text.contains("M190 S85"));
    assert!(job.text.contains(";FLAVOR:Marlin"));
}

#[test]
fn a_slicer_exiting_non_zero_is_reported_with_its_status_and_output() {
    let dir = tempfile::tempdir().unwrap();
    let fake = write_script(
        dir.path(),
        "crashing-slicer",
        "echo 'Slicing...'\necho 'error: the mesh exploded' >&2\nexit 3",
    );
    let out = dir.path().join("out.gcode");
    let out_path = PathBuf::from(&out);
    let mut req = SliceRequest::new(spot(), 20.0);
    req.strength = Strength::Off;
    req.slicer_program = Some(fake);
    let err = slice(&req, &out_path, &mut |_| {}).unwrap_err();
    assert!(matches!(err, SliceError::SlicerFailed { .. }), "{err:?}");
    let msg = err.to_string();
    assert!(msg.contains("PrusaSlicer"), "{msg}");
    assert!(msg.contains("exit status: 3"), "{msg}");
    assert!(msg.contains("the mesh exploded"), "{msg}");
    assert!(msg.contains("spot.obj"), "{msg}");
    assert!(!out.exists());
}

#[test]
fn a_hanging_slicer_is_killed_at_the_timeout() {
    let dir = tempfile::tempdir().unwrap();
    let fake = write_script(
        dir.path(),
        "hanging-slicer",
        "echo 'thinking hard'\nsleep 60",
    );
    let out_path = dir.path().join("out.gcode");
    let mut req = SliceRequest::new(spot(), 20.0);
    req.strength = Strength::Off;
    req.slicer = SlicerKind::Cura;
    req.slicer_program = Some(fake);
    req.timeout = Duration::from_millis(500);
    let started = Instant::now();
    let err = slice(&req, &out_path, &mut |_| {}).unwrap_err();
    assert!(matches!(err, SliceError::Timeout { .. }), "{err:?}");
    let msg = err.to_string();
    assert!(
        msg.contains("CuraEngine") && msg.contains("thinking hard"),
        "{msg}"
    );
    // Well before the script's own 60 s: it and its `sleep` were killed.
    assert!(started.elapsed() < Duration::from_secs(30));
}

#[test]
fn a_model_too_tall_or_too_wide_fails_before_any_slicer_runs() {
    let dir = tempfile::tempdir().unwrap();
    let marker = dir.path().join("slicer-ran");
    let fake = write_script(
        dir.path(),
        "recording-slicer",
        &format!("touch '{}'", marker.display()),
    );
    let out_path = dir.path().join("out.gcode");
    let mut req = SliceRequest::new(spot(), 210.0);
    req.strength = Strength::Off;
    req.slicer_program = Some(fake.clone());
    let err = slice(&req, &out_path, &mut |_| {}).unwrap_err();
    assert!(matches!(err, SliceError::TooBig { .. }), "{err:?}");
    assert!(err.to_string().contains("does not fit"), "{err}");

    // The bunny is 1.3 times as wide as it is tall: at 180 mm it fits in height, not on
    // the bed.
    req.model = bunny();
    req.height_mm = 180.0;
    let err = slice(&req, &out_path, &mut |_| {}).unwrap_err();
    assert!(matches!(err, SliceError::TooBig { .. }), "{err:?}");
    assert!(
        !marker.exists(),
        "the slicer must not run for a model that does not fit"
    );
}

#[test]
fn a_missing_slicer_names_the_package_to_install() {
    for (kind, package) in [
        (SlicerKind::Prusa, "prusa-slicer"),
        (SlicerKind::Cura, "cura-engine"),
    ] {
        let out_path = PathBuf::from("/tmp/never-written.gcode");
        let mut req = SliceRequest::new(spot(), 20.0);
        req.strength = Strength::Off;
        req.slicer = kind;
        req.slicer_program = Some("/nonexistent/crispen-test/slicer".into());
        let err = slice(&req, &out_path, &mut |_| {}).unwrap_err();
        assert!(matches!(err, SliceError::SlicerMissing { .. }), "{err:?}");
        assert!(
            err.to_string()
                .contains(&format!("apt-get install {package}")),
            "{err}"
        );
    }
}

#[test]
fn nonsense_gcode_is_refused_and_the_existing_job_is_kept() {
    let dir = tempfile::tempdir().unwrap();
    // Writes heating and travel moves but never extrudes, to whatever --output names.
    let fake = write_script(
        dir.path(),
        "lazy-slicer",
        "while [ $# -gt 0 ]; do [ \"$1\" = --output ] && out=$2; shift; done\n\
         printf 'M190 S60\\nM109 S210\\nG1 X10 Y10 Z0.2\\n' > \"$out\"",
    );
    let out = dir.path().join("job.gcode");
    std::fs::write(&out, "; the previous, good job\n").unwrap();
    let out_path = PathBuf::from(&out);
    let mut req = SliceRequest::new(spot(), 20.0);
    req.strength = Strength::Off;
    req.slicer_program = Some(fake);
    let err = slice(&req, &out_path, &mut |_| {}).unwrap_err();
    assert!(matches!(err, SliceError::BadOutput { .. }), "{err:?}");
    assert!(err.to_string().contains("no extruding moves"), "{err}");
    assert_eq!(
        std::fs::read_to_string(&out).unwrap(),
        "; the previous, good job\n"
    );
}

#[test]
fn bad_settings_and_profiles_are_refused_before_slicing() {
    let mut s = SliceSettings::default();
    let err = s.set("infill", "lots").unwrap_err();
    assert!(err.to_string().contains("infill=lots"), "{err}");
    let err = s.set("layer_height", "0.8").unwrap_err();
    assert!(err.to_string().contains("between 0.05 and 0.32"), "{err}");
    let err = s.set("colour", "red").unwrap_err();
    assert!(err.to_string().contains("known settings"), "{err}");
    s.set("material", "PETG").unwrap();
    assert_eq!(s.temperatures().unwrap(), (235.0, 85.0));
    let job = SliceSettings {
        nozzle_temp_c: Some(240.0),
        ..Default::default()
    };
    assert_eq!(s.merge(&job).temperatures().unwrap(), (240.0, 85.0));

    let dir = tempfile::tempdir().unwrap();
    let profile = dir.path().join("bundle.ini");
    std::fs::write(&profile, "[printer:Ultimaker 2]\nnozzle_diameter = 0.4\n").unwrap();
    let out_path = dir.path().join("out.gcode");
    let mut req = SliceRequest::new(spot(), 20.0);
    req.profile = Some(profile);
    let err = slice(&req, &out_path, &mut |_| {}).unwrap_err();
    assert!(matches!(err, SliceError::BadProfile { .. }), "{err:?}");
    assert!(err.to_string().contains("bundle.ini"), "{err}");
}

/// The filament a G-code file pushes in extruding moves (moves in X/Y: not primes or
/// unretractions; absolute E, resets with G92), and the X/Y middle of those moves.
fn extrusion_and_middle(text: &str) -> (f64, [f64; 2]) {
    let (mut e, mut total) = (0.0f64, 0.0f64);
    let (mut x, mut y) = (0.0f64, 0.0f64);
    let (mut lo, mut hi) = ([f64::MAX; 2], [f64::MIN; 2]);
    for line in text.lines() {
        let code = line.split(';').next().unwrap().trim();
        let mut words = code.split_whitespace();
        let cmd = words.next();
        let (mut ne, mut moves_xy) = (e, false);
        for w in words {
            let v = || w[1..].parse::<f64>().unwrap_or(0.0);
            match (cmd, &w[..1]) {
                (Some("G92"), "E") => {
                    e = v();
                    ne = e;
                }
                (Some("G0" | "G1"), "E") => ne = v(),
                (Some("G0" | "G1"), "X") => (x, moves_xy) = (v(), true),
                (Some("G0" | "G1"), "Y") => (y, moves_xy) = (v(), true),
                _ => {}
            }
        }
        if matches!(cmd, Some("G1")) && moves_xy && ne > e {
            total += ne - e;
            lo = [lo[0].min(x), lo[1].min(y)];
            hi = [hi[0].max(x), hi[1].max(y)];
        }
        e = ne;
    }
    (total, [(lo[0] + hi[0]) / 2.0, (lo[1] + hi[1]) / 2.0])
}

/// One enhancement, two machines: each G-code is made for its machine's filament (the
/// 1.75 mm machine pushes about (2.85 / 1.75)² = 2.65 times the filament length for the
/// same plastic) and centred on its bed. Fails on code that slices for an Ultimaker 2
/// whatever the printer.
#[test]
fn one_model_is_sliced_once_per_machine_for_its_filament_and_bed() {
    let dir = tempfile::tempdir().unwrap();
    let mut req = SliceRequest::new(spot(), 20.0);
    req.strength = Strength::Off;
    let targets: Vec<Target> = ["ultimaker2", "marlin-175"]
        .iter()
        .map(|m| Target {
            machine: machine(m),
            output: dir.path().join(format!("{m}.gcode")),
            keep_mesh: None,
        })
        .collect();
    let mut steps = Vec::new();
    let results = prepare(&req, &targets, &mut |s| steps.push(s.describe())).unwrap();
    assert_eq!(
        steps.iter().filter(|s| s.as_str() == "loading").count(),
        1,
        "{steps:?}"
    );
    assert!(
        steps.contains(&"slicing for marlin-175".to_string()),
        "{steps:?}"
    );
    let reports: Vec<&SliceReport> = results
        .iter()
        .map(|(m, r)| r.as_ref().unwrap_or_else(|e| panic!("{m}: {e}")))
        .collect();
    assert_eq!(reports[1].machine, "marlin-175");
    let um2 = std::fs::read_to_string(&targets[0].output).unwrap();
    let m175 = std::fs::read_to_string(&targets[1].output).unwrap();
    assert!(um2.contains("; filament_diameter = 2.85"));
    assert!(m175.contains("; filament_diameter = 1.75"));
    assert!(m175.contains("; bed_shape = 0x0,220x0,220x220,0x220"));
    let (e_um2, mid_um2) = extrusion_and_middle(&um2);
    let (e_175, mid_175) = extrusion_and_middle(&m175);
    let ratio = e_175 / e_um2;
    assert!((2.3..3.0).contains(&ratio), "filament ratio {ratio}");
    assert!((mid_um2[0] - 111.5).abs() < 3.0 && (mid_175[0] - 110.0).abs() < 3.0);
    assert!((mid_um2[1] - 111.5).abs() < 3.0 && (mid_175[1] - 110.0).abs() < 3.0);
}

/// A model too wide for one machine fails for that machine with the sizes named, and is
/// still sliced for the machine it fits (a fake slicer records that it ran).
#[test]
fn a_model_too_big_for_one_machine_goes_to_the_one_it_fits() {
    let dir = tempfile::tempdir().unwrap();
    let marker = dir.path().join("slicer-ran");
    let fake = write_script(
        dir.path(),
        "recording-slicer",
        &format!("touch '{}'; exit 1", marker.display()),
    );
    let mut req = SliceRequest::new(bunny(), 180.0);
    req.strength = Strength::Off;
    req.slicer_program = Some(fake);
    let big = Machine {
        name: "big".into(),
        bed_mm: [400.0, 400.0, 400.0],
        ..machine("marlin-175")
    };
    let targets = [machine("ultimaker2"), big].map(|m| Target {
        output: dir.path().join(format!("{}.gcode", m.name)),
        machine: m,
        keep_mesh: None,
    });
    let results = prepare(&req, &targets, &mut |_| {}).unwrap();
    let err = results[0].1.as_ref().unwrap_err();
    assert!(matches!(err, SliceError::TooBig { .. }), "{err:?}");
    let msg = err.to_string();
    assert!(
        msg.contains("the ultimaker2's [213.0, 213.0, 205.0] mm") && msg.contains("180 mm tall"),
        "{msg}"
    );
    assert!(
        matches!(results[1].1, Err(SliceError::SlicerFailed { .. })),
        "{:?}",
        results[1].1
    );
    assert!(marker.exists(), "the slicer ran for the machine it fits");
}

/// `crispen slice --machine` with a nozzle choice and CuraEngine: the machine's nozzle and
/// filament reach the slicer, and a machine without a heated bed gets no bed heating.
#[test]
fn the_cli_slices_for_a_named_machine_and_nozzle() {
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("spot.gcode");
    let run = |extra: &[&str]| {
        std::process::Command::new(env!("CARGO_BIN_EXE_crispen"))
            .args([
                "slice",
                spot().to_str().unwrap(),
                "-o",
                out.to_str().unwrap(),
            ])
            .args(["--height", "15", "--no-enhance", "--json"])
            .args(extra)
            .output()
            .expect("crispen runs")
    };
    let output = run(&["--machine", "ultimaker2plus", "--nozzle", "0.6"]);
    assert!(
        output.status.success(),
        "{}",
        String::from_utf8_lossy(&output.stderr)
    );
    let report: serde_json::Value = serde_json::from_slice(&output.stdout).unwrap();
    assert_eq!(report["machine"], "ultimaker2plus-0.6mm");
    // crispen's own output passed the G-code policy, its verdict in the report.
    assert_eq!(report["policy"]["refusals_total"], 0, "{report}");
    let text = std::fs::read_to_string(&out).unwrap();
    assert!(
        text.contains("; nozzle_diameter = 0.6"),
        "nozzle not passed on"
    );

    let output = run(&["--machine", "ultimaker2", "--nozzle", "0.6"]);
    assert!(!output.status.success());
    assert!(String::from_utf8_lossy(&output.stderr).contains("from 0.4 to 0.4"));
    let output = run(&["--machine", "prusa-mk9"]);
    assert!(String::from_utf8_lossy(&output.stderr).contains("built-in: ultimaker2, "));

    // A farm's own machine, from a config: unheated bed, 1.75 mm, CuraEngine.
    let config = dir.path().join("crispen.toml");
    std::fs::write(
        &config,
        "[spool]\ndir = \"spool\"\n[[machine]]\nname = \"cold-175\"\nfirmware = \"marlin2\"\n\
         bed_mm = [180, 180, 180]\nnozzle_mm = 0.4\nfilament_mm = 1.75\nheated_bed = false\n\
         max_hotend_c = 260\nmax_bed_c = 0\n",
    )
    .unwrap();
    let output = run(&[
        "--machine",
        "cold-175",
        "--config",
        config.to_str().unwrap(),
        "--slicer",
        "cura",
    ]);
    assert!(
        output.status.success(),
        "{}",
        String::from_utf8_lossy(&output.stderr)
    );
    let text = std::fs::read_to_string(&out).unwrap();
    assert!(
        !text.contains("M190") && !text.contains("M140 S6"),
        "the cold bed is heated"
    );
    let (_, mid) = extrusion_and_middle(&text);
    assert!(
        (mid[0] - 90.0).abs() < 3.0,
        "not centred on a 180 mm bed: {mid:?}"
    );
}

/// `crispen slice --compare`: the model is sliced unmodified with the same settings and
/// the two jobs' outer walls are compared layer by layer, with a picture of a few layers.
/// The bunny at 20 mm on a 0.4 mm nozzle is the case: a mean of a few hundredths
/// of a millimetre, a few per cent of the wall moved more than 0.1 mm.
#[test]
fn the_cli_compares_the_enhanced_outer_walls_with_the_unmodified_ones() {
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("bunny.gcode");
    let pictures = dir.path().join("pictures");
    let output = std::process::Command::new(env!("CARGO_BIN_EXE_crispen"))
        .args([
            "slice",
            bunny().to_str().unwrap(),
            "-o",
            out.to_str().unwrap(),
        ])
        .args(["--height", "20", "--up", "y", "--machine", "ultimaker2plus"])
        .args([
            "--compare",
            "--json",
            "--pictures",
            pictures.to_str().unwrap(),
        ])
        .output()
        .expect("crispen runs");
    assert!(
        output.status.success(),
        "{}",
        String::from_utf8_lossy(&output.stderr)
    );
    let report: serde_json::Value = serde_json::from_slice(&output.stdout).expect("JSON report");
    let w = &report["walls"];
    let f = |k: &str| w[k].as_f64().unwrap_or_else(|| panic!("{k} in {w}"));
    assert!(f("layers") > 80.0, "{w}");
    assert!(f("mean_mm") > 0.01 && f("mean_mm") < 0.1, "{w}");
    assert!(
        f("p95_mm") > f("mean_mm") && f("max_mm") >= f("p95_mm"),
        "{w}"
    );
    assert!(f("share_over_0_05_mm") > f("share_over_0_1_mm"), "{w}");
    assert!(
        f("share_over_0_1_mm") > 0.001 && f("share_over_0_1_mm") < 0.2,
        "{w}"
    );
    assert!(f("share_over_0_1_mm") >= f("share_over_0_2_mm"), "{w}");
    let printed = &report["enhancement"]["printed"];
    assert_eq!(printed["nozzle_mm"], 0.4);
    assert_eq!(printed["threshold_mm"], 0.1);
    // The comparison in one line, as `crispen slice` prints it.
    let moved = report["moved"].as_str().unwrap();
    assert!(
        moved.starts_with("The outer wall moves by more than a quarter line width (0.1 mm) on ")
            && moved.contains(" % of its length; at most "),
        "{moved}"
    );
    let png = std::fs::read(pictures.join("walls.png")).expect("walls.png");
    assert_eq!(&png[..8], b"\x89PNG\r\n\x1a\n");
}

/// CuraEngine marks its outer wall `;TYPE:WALL-OUTER`; the comparison reads it too.
#[test]
fn the_comparison_reads_curaengine_outer_walls() {
    let dir = tempfile::tempdir().unwrap();
    let mut req = SliceRequest::new(spot(), 20.0);
    req.slicer = SlicerKind::Cura;
    req.up = crispen::mesh::place::UpAxis::Y;
    req.strength = Strength::Lambda2(40.0);
    req.compare = true;
    let report = slice(&req, &dir.path().join("spot.gcode"), &mut |_| {}).unwrap();
    let w = report.walls.expect("a comparison");
    assert!(w.layers > 80 && w.wall_mm > 1000.0, "{w:?}");
    assert!(w.mean_mm > 0.0 && w.share_over_0_05_mm > 0.0, "{w:?}");
}

/// In print-aware mode the enhancement depends on the machine: one job for two nozzles is
/// enhanced for each (a wider band and another strength for the wider nozzle), where the
/// paper's mode enhances it once for both.
#[test]
fn print_aware_mode_enhances_a_job_for_each_machine() {
    let dir = tempfile::tempdir().unwrap();
    let um2p = machine("ultimaker2plus");
    let targets: Vec<Target> = [0.25, 0.4]
        .iter()
        .map(|&nozzle| Target {
            machine: um2p.with_nozzle(nozzle).unwrap(),
            output: dir.path().join(format!("spot-{nozzle}.gcode")),
            keep_mesh: None,
        })
        .collect();
    let mut req = SliceRequest::new(spot(), 25.0);
    req.up = crispen::mesh::place::UpAxis::Y;
    // Thin layers, so that the line width sets the printer's resolution.
    req.settings.layer_height_mm = Some(0.1);
    let lambdas = |req: &SliceRequest| -> Vec<(String, f64, f64)> {
        prepare(req, &targets, &mut |_| {})
            .unwrap()
            .into_iter()
            .map(|(_, r)| {
                let r = r.unwrap();
                let printed = r.enhancement.printed.unwrap();
                (
                    r.enhancement.mode,
                    r.enhancement.lambda2.unwrap(),
                    printed.nozzle_mm.unwrap(),
                )
            })
            .collect()
    };
    let paper = lambdas(&req);
    assert_eq!(paper[0].1, paper[1].1, "{paper:?}");
    assert_eq!(paper[0].0, "enhanced");
    req.mode = crispen::enhance::Mode::PrintAware;
    let aware = lambdas(&req);
    assert_eq!(aware[0].0, "enhanced (print-aware)");
    assert_ne!(aware[0].1, aware[1].1, "{aware:?}");
    assert_eq!((aware[0].2, aware[1].2), (0.25, 0.4));
}
