//! A farm of different machines, end to end with the real binary, simulated printers on
//! real ptys and the real PrusaSlicer: an Ultimaker 2 and a 1.75 mm Marlin machine share
//! one hot folder; each printer receives G-code made for its own machine (checked in what
//! each simulator executed: filament pushed, bed centre); a pre-sliced file prints exactly
//! as written; one made for another machine, and binary G-code, are refused with the reason.

use crate::common;
use common::daemon::{ctl, drop_model, recorded, state_of, wait_for, Daemon, BIN};
use common::{job_by_file, printer};

use crispen::sim::is_housekeeping;
use serde_json::Value;
use std::path::{Path, PathBuf};
use std::process::Command;
use std::time::Duration;

/// Generous: the machine is shared and slicing runs twice per model.
const LIMIT: Duration = Duration::from_secs(600);

/// A G-code file's commands as a printer must execute them: comments, blank lines and
/// trailing space gone (written here, apart from the host's own reader).
fn commands_of(path: &Path) -> Vec<String> {
    std::fs::read_to_string(path)
        .unwrap()
        .lines()
        .map(|l| l.split(';').next().unwrap().trim().to_string())
        .filter(|l| !l.is_empty() && !is_housekeeping(l))
        .collect()
}

/// Filament pushed by extruding moves (moves in X/Y: not primes or unretractions) and the
/// middle of their X/Y extent.
fn extrusion_and_middle(commands: &[String]) -> (f64, [f64; 2]) {
    let (mut e, mut total, mut x, mut y) = (0.0f64, 0.0f64, 0.0f64, 0.0f64);
    let (mut lo, mut hi) = ([f64::MAX; 2], [f64::MIN; 2]);
    for c in commands {
        let mut words = c.split_whitespace();
        let cmd = words.next();
        let (mut ne, mut moves_xy) = (e, false);
        for w in words {
            let v = w[1..].parse::<f64>().unwrap_or(0.0);
            match (cmd, &w[..1]) {
                (Some("G92"), "E") => {
                    e = v;
                    ne = v;
                }
                (Some("G0" | "G1"), "E") => ne = v,
                (Some("G0" | "G1"), "X") => (x, moves_xy) = (v, true),
                (Some("G0" | "G1"), "Y") => (y, moves_xy) = (v, true),
                _ => {}
            }
        }
        if cmd == Some("G1") && moves_xy && ne > e {
            total += ne - e;
            lo = [lo[0].min(x), lo[1].min(y)];
            hi = [hi[0].max(x), hi[1].max(y)];
        }
        e = ne;
    }
    (total, [(lo[0] + hi[0]) / 2.0, (lo[1] + hi[1]) / 2.0])
}

/// `crispen slice` for a machine (one of the config's or a built-in), unenhanced.
fn slice_for(config: &Path, machine: &str, out: &Path) {
    let output = Command::new(BIN)
        .arg("slice")
        .arg(common::model("spot.obj"))
        .arg("-o")
        .arg(out)
        .args([
            "--height",
            "12",
            "--no-enhance",
            "--machine",
            machine,
            "--config",
        ])
        .arg(config)
        .output()
        .unwrap();
    assert!(
        output.status.success(),
        "{}",
        String::from_utf8_lossy(&output.stderr)
    );
}

#[test]
fn a_farm_of_two_machines_prints_each_its_own_gcode() {
    let tmp = tempfile::tempdir().unwrap();
    let root = tmp.path();
    for d in ["hot/shared", "hot/only-175"] {
        std::fs::create_dir_all(root.join(d)).unwrap();
    }
    let config = root.join("crispen.toml");
    let log = root.join("daemon.log");
    let rec = |p: &str| root.join(format!("{p}.rec"));
    std::fs::write(
        &config,
        format!(
            r#"
[spool]
dir = "spool"
[control]
socket = "crispen.sock"
[farm]
max_heating = 2
settle_s = 0.5
rescan_s = 2
[[machine]]
name = "small-175"
firmware = "marlin2"
bed_mm = [180, 180, 180]
nozzle_mm = 0.4
filament_mm = 1.75
heated_bed = true
max_hotend_c = 260
max_bed_c = 110
[[printer]]
name = "um2"
machine = "ultimaker2"
[printer.simulate]
time_scale = 0.0
record = "{}"
[[printer]]
name = "mk"
machine = "small-175"
[printer.simulate]
time_scale = 0.0
record = "{}"
[[folder]]
path = "hot/shared"
height_mm = 12
printers = ["um2", "mk"]
enhance = false
[[folder]]
path = "hot/only-175"
height_mm = 12
printers = ["mk"]
"#,
            rec("um2").display(),
            rec("mk").display()
        ),
    )
    .unwrap();
    let _daemon = Daemon::start(&config, &log);
    wait_for(&config, &log, LIMIT, "the daemon to answer", |s| {
        s["printers"].as_array().is_some_and(|p| p.len() == 2)
    });

    // Two models into the shared folder: each is prepared for both machines, and each
    // printer takes one (then waits for its bed to be cleared).
    let spot = std::fs::read(common::model("spot.obj")).unwrap();
    drop_model(&root.join("hot/shared"), "one.obj", &spot);
    drop_model(&root.join("hot/shared"), "two.obj", &spot);
    let s = wait_for(&config, &log, LIMIT, "both models printed", |s| {
        state_of(s, "one.obj") == "done" && state_of(s, "two.obj") == "done"
    });
    let printed_by = |p: &str| {
        ["one.obj", "two.obj"]
            .into_iter()
            .find(|f| job_by_file(&s, f).unwrap()["printer"] == p)
            .unwrap_or_else(|| panic!("{p} printed neither model: {s}"))
    };
    let job_dir = |s: &Value, f: &str| -> PathBuf {
        root.join("spool/jobs")
            .join(job_by_file(s, f).unwrap()["id"].as_str().unwrap())
    };
    let mut figures = Vec::new();
    for (p, machine) in [("um2", "ultimaker2"), ("mk", "small-175")] {
        let file = printed_by(p);
        let gcode = job_dir(&s, file).join(format!("{file}.{machine}.gcode"));
        let executed = recorded(&rec(p));
        assert_eq!(
            executed,
            commands_of(&gcode),
            "{p} executed the G-code made for its machine {machine}, all of it, once"
        );
        let text = std::fs::read_to_string(&gcode).unwrap();
        let diameter = if p == "um2" { "2.85" } else { "1.75" };
        assert!(text.contains(&format!("; filament_diameter = {diameter}")));
        figures.push(extrusion_and_middle(&executed));
    }
    // Same model, same height: the 1.75 mm machine pushes (2.85 / 1.75)² = 2.65 times the
    // filament length; each print is centred on its own bed (223 mm and 180 mm).
    let ratio = figures[1].0 / figures[0].0;
    assert!((2.3..3.0).contains(&ratio), "filament ratio {ratio}");
    assert!((figures[0].1[0] - 111.5).abs() < 3.0, "{:?}", figures[0]);
    assert!((figures[1].1[0] - 90.0).abs() < 3.0, "{:?}", figures[1]);

    // Pre-sliced G-code: one made for the 1.75 mm machine, dropped into the shared folder,
    // is printed by that machine's printer exactly as written; the Ultimaker 2 refuses it.
    for p in ["um2", "mk"] {
        let (ok, out) = ctl(&config, &["clear", p]);
        assert!(ok, "{out}");
    }
    let presliced = root.join("made-for-175.gcode");
    slice_for(&config, "small-175", &presliced);
    let um2_gcode = root.join("made-for-um2.gcode");
    slice_for(&config, "ultimaker2", &um2_gcode);
    let before_mk = recorded(&rec("mk")).len();
    let before_um2 = recorded(&rec("um2")).len();
    drop_model(
        &root.join("hot/shared"),
        "pre.gcode",
        &std::fs::read(&presliced).unwrap(),
    );
    // And into the folder only the 1.75 mm machine serves: one sliced for the Ultimaker 2,
    // and a binary G-code file.
    drop_model(
        &root.join("hot/only-175"),
        "for-um2.gcode",
        &std::fs::read(&um2_gcode).unwrap(),
    );
    drop_model(
        &root.join("hot/only-175"),
        "part.bgcode",
        b"GCDE\x01\x00\x00\x00\x01\x00\x00\x00",
    );
    let s = wait_for(&config, &log, LIMIT, "the pre-sliced files handled", |s| {
        state_of(s, "pre.gcode") == "done"
            && state_of(s, "for-um2.gcode") == "failed"
            && state_of(s, "part.bgcode") == "failed"
    });
    assert_eq!(job_by_file(&s, "pre.gcode").unwrap()["printer"], "mk");
    let executed = recorded(&rec("mk"))[before_mk..].to_vec();
    assert_eq!(
        executed,
        commands_of(&presliced),
        "the pre-sliced file printed exactly as written"
    );
    assert_eq!(
        recorded(&rec("um2")).len(),
        before_um2,
        "um2 printed nothing more"
    );
    let reason = |f: &str| {
        job_by_file(&s, f).unwrap()["reason"]
            .as_str()
            .unwrap_or("")
            .to_string()
    };
    let r = reason("for-um2.gcode");
    assert!(
        r.contains("for-um2.gcode is not for the small-175")
            && r.contains("2.85 mm filament")
            && r.contains("1.75"),
        "{r}"
    );
    assert!(
        reason("part.bgcode").contains("binary G-code"),
        "{}",
        reason("part.bgcode")
    );
    // The Ultimaker 2's refusal of pre.gcode is on the job's record.
    let record: Value =
        serde_json::from_slice(&std::fs::read(job_dir(&s, "pre.gcode").join("job.json")).unwrap())
            .unwrap();
    assert_eq!(record["machines"]["small-175"]["gcode"], "pre.gcode");
    let refused = record["machines"]["ultimaker2"]["refused"]
        .as_str()
        .unwrap();
    assert!(refused.contains("1.75 mm filament"), "{refused}");
    assert_eq!(printer(&s, "um2")["state"], "idle");
}
