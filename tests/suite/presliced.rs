//! `crispen::slice::presliced` on real slicer output: G-code written by the real
//! PrusaSlicer and CuraEngine for one machine is accepted for it and refused, with the
//! reason, for machines it does not fit (filament, nozzle, bed, flavour).

use crispen::daemon::prepare::steps::{prepare_one, SliceRequest, Target};
use crispen::enhance::Strength;
use crispen::machine::Machine;
use crispen::slice::presliced::{check_for, read_target, GcodeTarget};
use crispen::slice::SlicerKind;
use std::path::Path;

use crate::common;

fn machine(name: &str) -> Machine {
    Machine::builtin(name).unwrap()
}

/// Slices spot, 10 mm tall and unenhanced, for `machine` with crispen's own steps.
fn sliced_for(machine: Machine, slicer: SlicerKind, out: &Path) -> GcodeTarget {
    sliced_in(machine, slicer, None, out)
}

/// [`sliced_for`], for `material` (a preset's name) where given.
fn sliced_in(
    machine: Machine,
    slicer: SlicerKind,
    material: Option<&str>,
    out: &Path,
) -> GcodeTarget {
    let mut req = SliceRequest::new(common::model("spot.obj"), 10.0);
    req.strength = Strength::Off;
    req.slicer = slicer;
    req.settings.material = material.map(String::from);
    let target = Target {
        machine,
        output: out.to_path_buf(),
        keep_mesh: None,
    };
    prepare_one(&req, target, &mut |_| {}).expect("sliced");
    read_target(std::io::BufReader::new(std::fs::File::open(out).unwrap())).unwrap()
}

#[test]
fn prusaslicer_output_is_for_its_machine_only() {
    let dir = tempfile::tempdir().unwrap();
    let t = sliced_for(
        machine("marlin-175"),
        SlicerKind::Prusa,
        &dir.path().join("a.gcode"),
    );
    assert!(t.slicer.as_deref().unwrap().starts_with("PrusaSlicer 2."));
    assert_eq!((t.filament_mm, t.nozzle_mm), (Some(1.75), Some(0.4)));
    assert_eq!(t.stated_bed_mm, Some([220.0, 220.0, 250.0]));
    check_for(&t, &machine("marlin-175")).unwrap();
    let e = check_for(&t, &machine("ultimaker2")).unwrap_err();
    assert!(
        e.contains("1.75 mm filament, the ultimaker2 takes 2.85"),
        "{e}"
    );

    // A 0.6 mm nozzle on an Ultimaker 2+: not for the same machine with a 0.4 mm one.
    let plus = machine("ultimaker2plus");
    let t = sliced_for(
        plus.with_nozzle(0.6).unwrap(),
        SlicerKind::Prusa,
        &dir.path().join("b.gcode"),
    );
    let e = check_for(&t, &plus).unwrap_err();
    assert!(e.contains("0.6 mm nozzle"), "{e}");

    // Centred on a 500 mm bed, the print lies beyond the Original+'s 205 mm.
    let big = Machine {
        name: "big-285".into(),
        bed_mm: [500.0, 500.0, 300.0],
        ..machine("ultimaker2")
    };
    let t = sliced_for(big, SlicerKind::Prusa, &dir.path().join("c.gcode"));
    let e = check_for(&t, &machine("ultimaker-original-plus")).unwrap_err();
    assert!(
        e.contains("its moves go to X")
            && e.contains("outside the ultimaker-original-plus's bed (0 .. 205 mm)"),
        "{e}"
    );
}

#[test]
fn curaengine_output_is_checked_by_its_moves_and_flavour() {
    let dir = tempfile::tempdir().unwrap();
    // CuraEngine's own header says little (no filament diameter): the moves must fit.
    let t = sliced_for(
        machine("ultimaker2"),
        SlicerKind::Cura,
        &dir.path().join("a.gcode"),
    );
    assert!(t.slicer.as_deref().unwrap().starts_with("Cura_SteamEngine"));
    assert_eq!(t.flavor.as_deref(), Some("Marlin"));
    check_for(&t, &machine("ultimaker2")).unwrap();
    let small = Machine {
        name: "small".into(),
        bed_mm: [100.0, 100.0, 100.0],
        ..machine("ultimaker2")
    };
    let e = check_for(&t, &small).unwrap_err();
    assert!(e.contains("outside the small's bed (0 .. 100 mm)"), "{e}");

    // Cura's default for the Ultimaker 2 is UltiGCode, for its SD card: never over USB.
    let resources = crispen::slice::cura::cura_resources();
    let out = dir.path().join("ulti.gcode");
    let stl = dir.path().join("spot.stl");
    let mut mesh = crispen::mesh::load(&common::model("spot.obj"))
        .unwrap()
        .mesh;
    crispen::mesh::place::place_on_bed(&mut mesh, 10.0, [f64::INFINITY; 3]).unwrap();
    let mut bytes = Vec::new();
    crispen::mesh::write_stl(&mut bytes, &mesh).unwrap();
    std::fs::write(&stl, bytes).unwrap();
    let status = std::process::Command::new("CuraEngine")
        .arg("slice")
        .arg("-j")
        .arg(resources.join("definitions/ultimaker2.def.json"))
        .args([
            "-s",
            "infill_line_distance=4",
            "-s",
            "center_object=true",
            "-o",
        ])
        .arg(&out)
        .arg("-l")
        .arg(&stl)
        .env(
            "CURA_ENGINE_SEARCH_PATH",
            format!(
                "{}:{}",
                resources.join("definitions").display(),
                resources.join("extruders").display()
            ),
        )
        .stdout(std::process::Stdio::null())
        .stderr(std::process::Stdio::null())
        .status()
        .expect("CuraEngine runs");
    assert!(status.success());
    let t = read_target(std::io::BufReader::new(std::fs::File::open(&out).unwrap())).unwrap();
    assert_eq!(t.flavor.as_deref(), Some("UltiGCode"));
    assert_eq!(t.nozzle_mm, Some(0.4));
    let e = check_for(&t, &machine("ultimaker2")).unwrap_err();
    assert!(e.contains("UltiGCode"), "{e}");
}

/// What a file pushes net, and what its forward moves alone add up to (every
/// un-retraction counted as new filament), mm, followed as Marlin 2 follows it.
pub(crate) fn net_and_forward_mm(file: &Path) -> (f64, f64) {
    use crispen::marlin::motion::{extruded_mm, Motion};
    let text = std::fs::read_to_string(file).unwrap();
    let firmware = crispen::marlin::firmware::Firmware::Marlin2;
    let mut motion = Motion::new(firmware);
    let mut forward = 0.0;
    for line in text.lines() {
        let code = line.split(';').next().unwrap_or_default();
        if let Ok(Some(cmd)) = crispen::marlin::reader::read(code) {
            if let Ok(Some(m)) = motion.apply(&cmd) {
                forward += (m.to[3] - m.from[3]).max(0.0);
            }
        }
    }
    (extruded_mm(text.lines(), firmware), forward)
}

/// The real slicers' Bowden output (6 mm retractions): what a file pushes is counted net,
/// as the follower that books a print counts it, far below its forward moves' sum.
#[test]
fn a_slicers_retractions_count_net() {
    let dir = tempfile::tempdir().unwrap();
    for (slicer, name) in [
        (SlicerKind::Prusa, "p.gcode"),
        (SlicerKind::Cura, "c.gcode"),
    ] {
        let out = dir.path().join(name);
        let t = sliced_for(machine("marlin-175"), slicer, &out);
        let (net, forward) = net_and_forward_mm(&out);
        eprintln!("{slicer:?}: {net:.1} mm net, {forward:.1} mm forward");
        assert!(
            (t.extruded_mm - net).abs() < 1e-6,
            "{slicer:?}: {} mm, net {net} mm",
            t.extruded_mm
        );
        assert!(
            forward > net * 1.2,
            "{slicer:?}: {forward} mm forward, {net} mm net"
        );
    }
}

/// What each slicer writes of its material, read as written: PrusaSlicer's config block
/// (`; filament_type = PLA`, the material it sliced for); CuraEngine's Marlin flavour names
/// none, and UltiGCode's `;MATERIAL:` is a volume; the header Cura puts at the top of a
/// Griffin file (CuraEngine logs it after slicing, the front end writes it in place of the
/// first) names its material profile's GUID.
#[test]
fn each_slicers_material_is_read_as_it_writes_it() {
    let dir = tempfile::tempdir().unwrap();
    let t = sliced_for(
        machine("marlin-175"),
        SlicerKind::Prusa,
        &dir.path().join("a.gcode"),
    );
    assert_eq!(t.material.as_deref(), Some("PLA"));
    let t = sliced_in(
        machine("marlin-175"),
        SlicerKind::Prusa,
        Some("petg"),
        &dir.path().join("b.gcode"),
    );
    assert_eq!(t.material.as_deref(), Some("PETG"));
    let t = sliced_for(
        machine("ultimaker2"),
        SlicerKind::Cura,
        &dir.path().join("c.gcode"),
    );
    assert_eq!(
        t.material, None,
        "CuraEngine's Marlin flavour names no material"
    );

    // CuraEngine itself, Griffin flavour, for Cura's generic PETG.
    let resources = crispen::slice::cura::cura_resources();
    let stl = dir.path().join("spot.stl");
    let mut mesh = crispen::mesh::load(&common::model("spot.obj"))
        .unwrap()
        .mesh;
    crispen::mesh::place::place_on_bed(&mut mesh, 10.0, [f64::INFINITY; 3]).unwrap();
    let mut bytes = Vec::new();
    crispen::mesh::write_stl(&mut bytes, &mesh).unwrap();
    std::fs::write(&stl, bytes).unwrap();
    let cura = |flavour: &str, out: &Path| {
        let run = std::process::Command::new("CuraEngine")
            .args(["slice", "-v", "-j"])
            .arg(resources.join("definitions/ultimaker2.def.json"))
            .args(["-s", &format!("machine_gcode_flavor={flavour}")])
            .args(["-s", "material_guid=1cbfaeb3-1906-4b26-b2e7-6f777a8c197a"])
            .args([
                "-s",
                "infill_line_distance=4",
                "-s",
                "center_object=true",
                "-o",
            ])
            .arg(out)
            .arg("-l")
            .arg(&stl)
            .env(
                "CURA_ENGINE_SEARCH_PATH",
                format!(
                    "{}:{}",
                    resources.join("definitions").display(),
                    resources.join("extruders").display()
                ),
            )
            .stdout(std::process::Stdio::null())
            .output()
            .expect("CuraEngine runs");
        assert!(run.status.success());
        String::from_utf8_lossy(&run.stderr).into_owned()
    };
    let out = dir.path().join("griffin.gcode");
    let log = cura("Griffin", &out);
    let header = log
        .split("Gcode header after slicing:\n")
        .nth(1)
        .and_then(|h| h.split("End of gcode header.").next())
        .expect("CuraEngine logs the header after slicing");
    assert!(
        header.contains(";EXTRUDER_TRAIN.0.MATERIAL.GUID:1cbfaeb3"),
        "{header}"
    );
    let body = std::fs::read_to_string(&out).unwrap();
    let body = body
        .split(";END_OF_HEADER\n")
        .nth(1)
        .expect("a Griffin header");
    let t = read_target(format!("{header}{body}").as_bytes()).unwrap();
    assert_eq!(t.material.as_deref(), Some("PETG"));
    // The engine's own first header, before slicing, names none.
    let t = read_target(std::fs::read(&out).unwrap().as_slice()).unwrap();
    assert_eq!(t.material, None);

    let out = dir.path().join("ulti.gcode");
    cura("UltiGCode", &out);
    let text = std::fs::read_to_string(&out).unwrap();
    assert!(text.contains(";MATERIAL:"), "UltiGCode's header");
    assert_eq!(read_target(text.as_bytes()).unwrap().material, None);
}
