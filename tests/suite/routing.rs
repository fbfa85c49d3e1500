//! Where a pre-sliced job goes and what it waits for, on a farm of simulated printers
//! running the real daemon, with files the real PrusaSlicer sliced:
//!
//! - a Bowden file's need is what it pushes net (its retractions pushed back count once),
//!   from the follower that books what its print took: the need shown before the print
//!   is the weight booked after it, and a spool holding more than that takes it;
//! - a file's own material (PrusaSlicer's `; filament_type`) is what it asks unless its
//!   folder or sidecar says otherwise: a PLA file goes to the printer holding PLA, never to
//!   one holding TPU, and waits with the reason where only TPU is loaded;
//! - the reason names every printer left out, a printer whose machine cannot print the
//!   file included, in grams of the material asked, and `crispen status` shows it.

use crate::common;
use crate::presliced::net_and_forward_mm;

use common::daemon::{ctl, recorded, status, wait_for, Daemon};
use common::farm::{drop_file, state_of};
use crispen::daemon::prepare::steps::{prepare_one, SliceRequest, Target};
use crispen::enhance::Strength;
use crispen::machine::Machine;
use crispen::marlin::firmware::Firmware;
use crispen::marlin::motion::extruded_mm;
use serde_json::Value;
use std::path::{Path, PathBuf};
use std::time::{Duration, Instant};

/// Grams per mm of 1.75 mm filament at `density` (PLA 1.24, TPU 1.21 in crispen's table).
fn grams_per_mm(density: f64) -> f64 {
    let r_cm = 1.75 / 20.0;
    std::f64::consts::PI * r_cm * r_cm * 0.1 * density
}

/// Spot, 30 mm tall, unenhanced, sliced by the real PrusaSlicer for the generic Marlin
/// machine the simulated printers are, with crispen's profile (a Bowden Ultimaker 2's:
/// 6 mm retractions, absolute E, `G92 E0` at each layer) changed by `profile_lines`.
fn sliced(dir: &Path, name: &str, profile_lines: &str) -> PathBuf {
    let mut req = SliceRequest::new(common::model("spot.obj"), 30.0);
    req.strength = Strength::Off;
    if !profile_lines.is_empty() {
        let base = std::fs::read_to_string(concat!(
            env!("CARGO_MANIFEST_DIR"),
            "/config/prusaslicer-ultimaker2.ini"
        ))
        .unwrap();
        // Each line given replaces the profile's own (PrusaSlicer refuses a key twice).
        let key = |l: &str| l.split('=').next().unwrap_or_default().trim().to_string();
        let given: Vec<String> = profile_lines.lines().map(key).collect();
        let kept: Vec<&str> = base.lines().filter(|l| !given.contains(&key(l))).collect();
        let profile = dir.join(format!("{name}.ini"));
        std::fs::write(&profile, format!("{}\n{profile_lines}\n", kept.join("\n"))).unwrap();
        req.profile = Some(profile);
    }
    let output = dir.join(name);
    let target = Target {
        machine: Machine::builtin("marlin-175").unwrap(),
        output: output.clone(),
        keep_mesh: None,
    };
    prepare_one(&req, target, &mut |_| {}).expect("sliced");
    output
}

/// Grams told as the daemon tells them.
fn told(g: f64) -> String {
    if g < 10.0 {
        format!("{g:.1} g")
    } else {
        format!("{g:.0} g")
    }
}

fn job<'a>(s: &'a Value, file: &str) -> &'a Value {
    common::job_by_file(s, file).unwrap_or_else(|| panic!("no job {file}: {s}"))
}

/// A farm config: `printers` (name, extra keys) simulated instantly and recorded, every
/// bed not cleared at the start (so that every job is ready, and its need and reason
/// can be read, before any printer takes one); `folders` as given.
fn farm(root: &Path, printers: &[(&str, &str)], folders: &str) -> (PathBuf, PathBuf) {
    std::fs::create_dir_all(root.join("spool")).unwrap();
    let gates: Vec<String> = printers
        .iter()
        .map(|(p, _)| format!("\"{p}\": {{\"bed_not_cleared\": true, \"last_job\": null}}"))
        .collect();
    std::fs::write(
        root.join("spool/printers.json"),
        format!("{{{}}}", gates.join(", ")),
    )
    .unwrap();
    let mut text = "[spool]\ndir = \"spool\"\n[control]\nsocket = \"c.sock\"\n\
                    [farm]\nsettle_s = 0.3\nmax_heating = 4\n"
        .to_string();
    for (name, extra) in printers {
        text += &format!(
            "[[printer]]\nname = \"{name}\"\n{extra}\n[printer.simulate]\ntime_scale = 0.0\nrecord = \"{name}.rec\"\n"
        );
    }
    text += folders;
    let config = root.join("crispen.toml");
    std::fs::write(&config, text).unwrap();
    (config, root.join("daemon.log"))
}

/// Clears the bed of each of `printers` that waits for it, until `done` holds.
fn clear_until(
    config: &Path,
    log: &Path,
    printers: &[&str],
    what: &str,
    done: impl Fn(&Value) -> bool,
) -> Value {
    let started = Instant::now();
    loop {
        let s = status(config).unwrap_or(Value::Null);
        if s.is_object() && done(&s) {
            return s;
        }
        for p in printers {
            let waiting = s["printers"]
                .as_array()
                .into_iter()
                .flatten()
                .any(|x| x["name"] == *p && x["bed_cleared"] == false);
            if waiting {
                ctl(config, &["clear", p]);
            }
        }
        assert!(
            started.elapsed() < Duration::from_secs(180),
            "timed out waiting for {what}\nstatus: {s}\nlog:\n{}",
            std::fs::read_to_string(log).unwrap_or_default()
        );
        std::thread::sleep(Duration::from_millis(150));
    }
}

fn load(config: &Path, printer: &str, material: &str, colour: &str, grams: f64) {
    let grams = format!("{grams:.3}");
    let (ok, out) = ctl(
        config,
        &[
            "load",
            printer,
            "--material",
            material,
            "--colour",
            colour,
            "--grams",
            &grams,
        ],
    );
    assert!(ok && out.contains("loaded"), "{out}");
}

/// Three Bowden files, each on its own printer: absolute E (crispen's profile; its start
/// code resets E with `G92 E0`), relative E (reset at each layer, as PrusaSlicer demands),
/// and firmware retraction (`G10`/`G11`). Each needs what
/// it pushes net: short of that, it waits with the figure; given a spool that holds more
/// than that but less than its forward moves add up to, it prints, and what the print
/// took is the need shown before it, and what the printer executed.
#[test]
fn a_bowden_file_needs_what_it_pushes_net() {
    let tmp = tempfile::tempdir().unwrap();
    let root = tmp.path();
    let files = [
        ("a", "absolute.gcode", ""),
        (
            "b",
            "relative.gcode",
            "use_relative_e_distances = 1\nlayer_gcode = G92 E0",
        ),
        ("c", "firmware.gcode", "use_firmware_retraction = 1"),
    ];
    let sliced: Vec<(&str, &str, PathBuf)> = files
        .iter()
        .map(|(p, name, lines)| (*p, *name, sliced(root, name, lines)))
        .collect();
    let text = |f: &Path| std::fs::read_to_string(f).unwrap();
    assert!(text(&sliced[0].2).contains("\nM82"), "absolute E");
    assert!(text(&sliced[1].2).contains("\nM83"), "relative E");
    assert!(text(&sliced[2].2).contains("\nG10"), "firmware retraction");
    let per_mm = grams_per_mm(1.24);
    let figures: Vec<(f64, f64)> = sliced
        .iter()
        .map(|(_, _, f)| net_and_forward_mm(f))
        .collect();
    for ((_, name, _), (net, forward)) in sliced.iter().zip(&figures) {
        eprintln!(
            "{name}: pushes {:.3} g net; its forward moves add up to {:.3} g",
            net * per_mm,
            forward * per_mm
        );
    }
    // The E-axis retractions make the difference the spools are sized in.
    for (net, forward) in &figures[..2] {
        assert!(*forward > net * 1.2, "{forward} mm forward, {net} mm net");
    }

    let (config, log) = farm(
        root,
        &[
            ("a", "firmware = \"marlin2\""),
            ("b", "firmware = \"marlin2\""),
            ("c", "firmware = \"marlin2\""),
        ],
        "[[folder]]\npath = \"hot\"\nheight_mm = 30\nprinters = [\"a\", \"b\", \"c\"]\n",
    );
    std::fs::create_dir_all(root.join("hot")).unwrap();
    let _daemon = Daemon::start(&config, &log);
    wait_for(
        &config,
        &log,
        Duration::from_secs(30),
        "the printers",
        |s| s["printers"].as_array().is_some_and(|p| p.len() == 3),
    );
    // Short spools first: half the net need.
    for ((printer, _, _), (net, _)) in sliced.iter().zip(&figures) {
        load(&config, printer, "PLA", "white", net * per_mm / 2.0);
    }
    let hot = root.join("hot");
    for (printer, name, file) in &sliced {
        drop_file(
            &hot,
            &format!("{name}.toml"),
            format!("printer = \"{printer}\"\n").as_bytes(),
        );
        drop_file(&hot, name, &std::fs::read(file).unwrap());
    }
    let s = wait_for(
        &config,
        &log,
        Duration::from_secs(120),
        "every job ready",
        |s| files.iter().all(|(_, n, _)| state_of(s, n) == "ready"),
    );
    for ((printer, name, _), (net, _)) in sliced.iter().zip(&figures) {
        let j = job(&s, name);
        let need_g = j["need_g"].as_f64().unwrap();
        assert!(
            (need_g - net * per_mm).abs() < 1e-9,
            "{name}: needs {need_g} g, pushes {} g net",
            net * per_mm
        );
        // The reason tells the need as the status does, and what is left alike.
        let why = j["waiting"].as_str().unwrap_or_default();
        let expected = format!(
            "waiting for {} of PLA (the file's material): {printer} has {}",
            told(need_g),
            told(net * per_mm / 2.0)
        );
        assert_eq!(why, expected, "{name}");
    }
    // Spools that hold more than the net need, less than the forward moves: enough.
    for ((printer, _, _), (net, forward)) in sliced.iter().zip(&figures) {
        let grams = if forward > &(net * 1.2) {
            (net + forward) / 2.0 * per_mm
        } else {
            net * 1.05 * per_mm
        };
        load(&config, printer, "PLA", "white", grams);
    }
    let s = wait_for(
        &config,
        &log,
        Duration::from_secs(30),
        "no job waiting",
        |s| files.iter().all(|(_, n, _)| job(s, n)["waiting"].is_null()),
    );
    let needs: Vec<f64> = files
        .iter()
        .map(|(_, n, _)| job(&s, n)["need_g"].as_f64().unwrap())
        .collect();
    let s = clear_until(&config, &log, &["a", "b", "c"], "every job done", |s| {
        files.iter().all(|(_, n, _)| state_of(s, n) == "done")
    });
    for (((printer, name, _), need_g), (net, _)) in sliced.iter().zip(&needs).zip(&figures) {
        let j = job(&s, name);
        assert_eq!(j["printer"], *printer, "{name}");
        let used = j["used_g"].as_f64().unwrap();
        assert!(
            (used - need_g).abs() < 1e-9,
            "{name}: needed {need_g} g, its print took {used} g"
        );
        let executed = extruded_mm(
            recorded(&root.join(format!("{printer}.rec")))
                .iter()
                .map(String::as_str),
            Firmware::Marlin2,
        );
        assert!(
            (executed - net).abs() < 1e-6,
            "{name}: {printer} executed {executed} mm, the file pushes {net} mm net"
        );
    }
}

/// The file's own material routes it: a PLA file goes to the printer holding PLA, not
/// the one holding TPU; where only TPU is loaded it waits, saying so, and naming the
/// printer whose machine cannot print it; a folder's or a sidecar's material overrides
/// the file's (weighed at its own density); a printer whose filament nobody recorded
/// takes it. `crispen status` shows why a ready job waits.
#[test]
fn a_files_material_decides_where_it_prints() {
    let tmp = tempfile::tempdir().unwrap();
    let root = tmp.path();
    let file = sliced(root, "spot.gcode", "");
    let gcode = std::fs::read(&file).unwrap();
    assert!(
        String::from_utf8_lossy(&gcode).contains("\n; filament_type = PLA\n"),
        "PrusaSlicer writes the material in its config block"
    );
    let (net, _) = net_and_forward_mm(&file);
    let marlin = "firmware = \"marlin2\"";
    let (config, log) = farm(
        root,
        &[
            ("tpu", marlin),
            ("pla", marlin),
            ("bare", marlin),
            ("um2", "machine = \"ultimaker2\""),
        ],
        "[[folder]]\npath = \"farm\"\nheight_mm = 30\nprinters = [\"tpu\", \"pla\"]\n\
         [[folder]]\npath = \"tpu-only\"\nheight_mm = 30\nprinters = [\"tpu\", \"um2\"]\n\
         [[folder]]\npath = \"as-tpu\"\nheight_mm = 30\nprinters = [\"tpu\"]\nmaterial = \"TPU\"\n\
         [[folder]]\npath = \"bare\"\nheight_mm = 30\nprinters = [\"bare\"]\n",
    );
    for f in ["farm", "tpu-only", "as-tpu", "bare"] {
        std::fs::create_dir_all(root.join(f)).unwrap();
    }
    let _daemon = Daemon::start(&config, &log);
    wait_for(
        &config,
        &log,
        Duration::from_secs(30),
        "the printers",
        |s| s["printers"].as_array().is_some_and(|p| p.len() == 4),
    );
    load(&config, "tpu", "TPU", "red", 1000.0);
    load(&config, "pla", "PLA", "white", 1000.0);
    // The PLA file in the TPU-only folder first, and first in priority: the TPU printer
    // passes it over for the later, lower one it can print.
    let put = |folder: &str, name: &str, sidecar: &str| {
        let dir = root.join(folder);
        if !sidecar.is_empty() {
            drop_file(&dir, &format!("{name}.toml"), sidecar.as_bytes());
        }
        drop_file(&dir, name, &gcode);
    };
    put("tpu-only", "pla-file.gcode", "priority = 10\n");
    put("tpu-only", "sidecar-tpu.gcode", "material = \"TPU\"\n");
    put("farm", "to-pla.gcode", "");
    put("as-tpu", "folder-tpu.gcode", "");
    put("bare", "to-bare.gcode", "");
    let names = [
        "pla-file.gcode",
        "sidecar-tpu.gcode",
        "to-pla.gcode",
        "folder-tpu.gcode",
        "to-bare.gcode",
    ];
    let s = wait_for(
        &config,
        &log,
        Duration::from_secs(120),
        "every job ready",
        |s| names.iter().all(|n| state_of(s, n) == "ready"),
    );
    // What each asks, and its need at the density of that material.
    let asks = |n: &str| job(&s, n)["asks"].clone();
    assert_eq!(asks("to-pla.gcode")["material"], "PLA");
    assert_eq!(asks("to-pla.gcode")["material_of_file"], true);
    for n in ["sidecar-tpu.gcode", "folder-tpu.gcode"] {
        assert_eq!(asks(n)["material"], "TPU", "{n}");
        assert!(asks(n)["material_of_file"].is_null(), "{n}");
    }
    let need = |n: &str| job(&s, n)["need_g"].as_f64().unwrap();
    assert!((need("to-pla.gcode") - net * grams_per_mm(1.24)).abs() < 1e-9);
    assert!((need("sidecar-tpu.gcode") - net * grams_per_mm(1.21)).abs() < 1e-9);
    // Only the PLA file in the TPU-only folder waits, and says why: the printer holding
    // TPU, and the one whose machine cannot print a 1.75 mm file.
    for n in &names[1..] {
        assert!(
            job(&s, n)["waiting"].is_null(),
            "{n}: {}",
            job(&s, n)["waiting"]
        );
    }
    let why = job(&s, "pla-file.gcode")["waiting"]
        .as_str()
        .unwrap_or_default()
        .to_string();
    assert!(
        why.starts_with(
            "waiting for PLA (the file's material): loaded is TPU red (tpu); \
             um2 cannot print it (pla-file.gcode is not for the ultimaker2: "
        ),
        "{why}"
    );
    // The status table shows it, under the job.
    let (ok, table) = ctl(&config, &["status"]);
    assert!(ok, "{table}");
    let id = job(&s, "pla-file.gcode")["id"]
        .as_str()
        .unwrap()
        .to_string();
    let lines: Vec<&str> = table.lines().collect();
    let row = lines
        .iter()
        .position(|l| l.starts_with(&id))
        .unwrap_or_else(|| panic!("no row for {id}:\n{table}"));
    assert_eq!(lines[row + 1].trim(), why, "{table}");

    let done = [
        "sidecar-tpu.gcode",
        "to-pla.gcode",
        "folder-tpu.gcode",
        "to-bare.gcode",
    ];
    let s = clear_until(
        &config,
        &log,
        &["tpu", "pla", "bare", "um2"],
        "the printable jobs done",
        |s| done.iter().all(|n| state_of(s, n) == "done"),
    );
    for (n, printer) in [
        ("to-pla.gcode", "pla"),
        ("sidecar-tpu.gcode", "tpu"),
        ("folder-tpu.gcode", "tpu"),
        ("to-bare.gcode", "bare"),
    ] {
        assert_eq!(job(&s, n)["printer"], printer, "{n}");
    }
    // The TPU printer took two jobs while the PLA one, older and first in priority, was
    // ready: it passed it over, and it still waits.
    assert_eq!(state_of(&s, "pla-file.gcode"), "ready");
    assert!(job(&s, "pla-file.gcode")["waiting"]
        .as_str()
        .is_some_and(|w| w.starts_with("waiting for PLA (the file's material): ")));
}
