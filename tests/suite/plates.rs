//! Plates through the daemon: a folder's `per_plate` copies sliced as one plate by the real
//! PrusaSlicer, a part cancelled mid-print with `crispen cancel JOB --part` (the printer
//! executes exactly what the host's filter predicts from where the store says it was
//! dropped, and the job ends done; status shows the time left and what it rests on), and
//! parts cancelled before the print (a missing part
//! named with the plate's parts, the last part left cancelling the job).

use crate::common;
use common::daemon::{ctl, drop_model, recorded, state_of, wait_for, Daemon};
use common::{job_by_file, printer};

use crispen::marlin::firmware::Firmware;
use crispen::marlin::gcode::GcodeProgram;
use serde_json::Value;
use std::path::Path;
use std::time::Duration;

/// A farm of one simulated Marlin 2 printer recording what it executes, and a folder that
/// puts `per_plate` copies of each model on one plate, unenhanced.
fn farm(root: &Path, per_plate: u32, time_scale: f64) -> std::path::PathBuf {
    std::fs::create_dir_all(root.join("hot")).unwrap();
    let config = root.join("crispen.toml");
    std::fs::write(
        &config,
        format!(
            "[spool]\ndir = \"spool\"\n[control]\nsocket = \"c.sock\"\n\
             [farm]\nsettle_s = 0.3\n\
             [[printer]]\nname = \"p\"\nfirmware = \"marlin2\"\n\
             [printer.simulate]\ntime_scale = {time_scale}\nrecord = \"{}\"\n\
             [[folder]]\npath = \"hot\"\nheight_mm = 10\nstrength = \"off\"\n\
             per_plate = {per_plate}\nprinters = [\"p\"]\n",
            root.join("p.rec").display()
        ),
    )
    .unwrap();
    config
}

fn spot() -> Vec<u8> {
    std::fs::read(common::model("spot.obj")).unwrap()
}

/// The job's whole record, as the spool keeps it.
fn record(root: &Path, id: &str) -> Value {
    let path = root.join("spool/jobs").join(id).join("job.json");
    serde_json::from_slice(&std::fs::read(path).unwrap()).unwrap()
}

#[test]
fn a_part_cancelled_mid_print_is_dropped_and_the_others_print_exactly() {
    let tmp = tempfile::tempdir().unwrap();
    let root = tmp.path();
    let config = farm(root, 3, 0.01);
    let log = root.join("daemon.log");
    let _daemon = Daemon::start(&config, &log);
    drop_model(&root.join("hot"), "spot.obj", &spot());

    let progress = |s: &Value| {
        let p = &printer(s, "p")["progress"];
        (
            p["lines_acked"].as_u64().unwrap_or(0),
            p["lines_total"].as_u64().unwrap_or(u64::MAX),
        )
    };
    let s = wait_for(
        &config,
        &log,
        Duration::from_secs(180),
        "a third printed",
        |s| {
            let (acked, total) = progress(s);
            printer(s, "p")["state"] == "printing" && acked * 3 > total
        },
    );
    let job = job_by_file(&s, "spot.obj").unwrap();
    let id = job["id"].as_str().unwrap().to_string();
    assert_eq!(job["parts"]["total"], 3, "{job:#}");
    // The time left is the planner's over the commands not yet acknowledged, at the pace
    // of a printer that has no finished print yet.
    let left = &printer(&s, "p")["progress"]["time_left"];
    assert!(left["planned_s"].as_f64().unwrap() > 1.0, "{left}");
    assert_eq!(
        left["pace"],
        serde_json::json!({"factor": 1.0, "prints": 0}),
        "{left}"
    );
    assert_eq!(left["heating"], false, "{left}");
    let names: Vec<String> = record(root, &id)["slice_report"]["parts"]
        .as_array()
        .unwrap()
        .iter()
        .map(|p| p["name"].as_str().unwrap().to_string())
        .collect();
    assert_eq!(names.len(), 3, "{names:?}");

    let (ok, out) = ctl(&config, &["cancel", &id, "--part", "2"]);
    assert!(ok, "{out}");
    assert!(
        out.contains(&names[1]) && out.contains("others print on"),
        "{out}"
    );
    let s = wait_for(&config, &log, Duration::from_secs(300), "done", |s| {
        state_of(s, "spot.obj") == "done"
    });
    let job = job_by_file(&s, "spot.obj").unwrap();
    assert_eq!(
        job["parts"]["cancelled"],
        serde_json::json!([names[1]]),
        "{job:#}"
    );
    let (_, text) = ctl(&config, &["status"]);
    assert!(text.contains("2 of 3 parts on the plate"), "{text}");

    // The store says where the part was dropped; the printer executed exactly what the
    // host's filter sends from there.
    // A print with a part dropped says nothing of its printer's pace.
    assert!(record(root, &id)["print_report"]["pace"].is_null());
    let cancels = record(root, &id)["parts_cancelled"].clone();
    assert_eq!(cancels.as_array().unwrap().len(), 1, "{cancels:#}");
    let dropped = &cancels[0]["dropped"];
    let from = dropped["command"].as_u64().unwrap() as usize;
    assert!(dropped["layer"].as_u64().unwrap() > 1, "{dropped}");
    let gcode = root
        .join("spool/jobs")
        .join(&id)
        .join("spot.obj.marlin-175.gcode");
    let program = GcodeProgram::load_for(&gcode, Firmware::Marlin2).unwrap();
    let part = program.marks().unwrap().find(&names[1]).unwrap();
    let expected: Vec<String> = crispen::marlin::plate::sent_lines(&program, &[(part, from)])
        .filter_map(|(_, line)| line.map(|l| l.into_owned()))
        .collect();
    let executed = recorded(&root.join("p.rec"));
    assert!(expected.len() < program.len(), "the filter dropped moves");
    assert_eq!(executed.len(), expected.len(), "commands executed");
    if let Some(i) = (0..expected.len()).find(|&i| executed[i] != expected[i]) {
        panic!(
            "executed command {i} is {:?}, the host's filter sent {:?}",
            executed[i], expected[i]
        );
    }
}

#[test]
fn parts_cancelled_before_the_print_and_the_last_one_cancels_the_job() {
    let tmp = tempfile::tempdir().unwrap();
    let root = tmp.path();
    let config = farm(root, 2, 0.01);
    let log = root.join("daemon.log");
    let _daemon = Daemon::start(&config, &log);
    std::fs::write(root.join("hot/spot.obj.toml"), "hold = true\n").unwrap();
    drop_model(&root.join("hot"), "spot.obj", &spot());
    let s = wait_for(&config, &log, Duration::from_secs(180), "ready", |s| {
        state_of(s, "spot.obj") == "ready"
    });
    let id = job_by_file(&s, "spot.obj").unwrap()["id"]
        .as_str()
        .unwrap()
        .to_string();

    let (ok, out) = ctl(&config, &["cancel", &id, "--part", "no such part"]);
    assert!(!ok, "{out}");
    assert!(
        out.contains("no part \"no such part\"") && out.contains("1 \""),
        "{out}"
    );

    let (ok, out) = ctl(&config, &["cancel", &id, "--part", "1"]);
    assert!(ok && out.contains("will not be printed"), "{out}");
    let s = wait_for(
        &config,
        &log,
        Duration::from_secs(10),
        "one part cancelled",
        |s| {
            job_by_file(s, "spot.obj").unwrap()["parts"]["cancelled"]
                .as_array()
                .is_some_and(|c| c.len() == 1)
        },
    );
    assert_eq!(state_of(&s, "spot.obj"), "ready");

    let (ok, out) = ctl(&config, &["cancel", &id, "--part", "2"]);
    assert!(ok && out.contains("the job is cancelled"), "{out}");
    wait_for(&config, &log, Duration::from_secs(10), "cancelled", |s| {
        state_of(s, "spot.obj") == "cancelled"
    });
    assert_eq!(
        record(root, &id)["parts_cancelled"]
            .as_array()
            .unwrap()
            .len(),
        2
    );
}

/// Spot, and a box half its height standing beside it.
fn spot_and_a_box() -> (crispen::mesh::Mesh, crispen::mesh::Mesh) {
    let spot = crispen::mesh::load(&common::model("spot.obj"))
        .unwrap()
        .mesh;
    let (lo, hi) = spot.bounds().unwrap();
    let height = hi[2] - lo[2];
    let side = block([hi[0] + height, lo[1], lo[2]], height / 2.0);
    (spot, side)
}

/// A box of `size` with its low corner at `at`.
fn block(at: [f64; 3], size: f64) -> crispen::mesh::Mesh {
    let vertices = (0..8)
        .map(|i| [0, 1, 2].map(|k| at[k] + if i >> k & 1 == 1 { size } else { 0.0 }))
        .collect();
    // Outward faces of the unit cube, corners numbered by their bits (x 1, y 2, z 4).
    let faces = vec![
        [0, 2, 1],
        [1, 2, 3],
        [4, 5, 6],
        [5, 7, 6],
        [0, 1, 4],
        [1, 5, 4],
        [2, 6, 3],
        [3, 6, 7],
        [0, 4, 2],
        [2, 4, 6],
        [1, 3, 5],
        [3, 7, 5],
    ];
    crispen::mesh::Mesh { vertices, faces }
}

/// A 3MF whose build places Spot and a box half its height is one plate of two models:
/// the box prints half as tall (the set keeps its proportions), the G-code labels each
/// by the object's name, the box cancelled before the print leaves the booking and the
/// print, and the printer executes exactly the plate without it.
#[test]
fn a_3mf_of_several_objects_prints_as_one_plate_of_its_models() {
    let tmp = tempfile::tempdir().unwrap();
    let root = tmp.path();
    let config = farm(root, 1, 0.01);
    let log = root.join("daemon.log");
    let _daemon = Daemon::start(&config, &log);
    let (spot, side) = spot_and_a_box();
    std::fs::write(root.join("hot/set.3mf.toml"), "hold = true\n").unwrap();
    drop_model(
        &root.join("hot"),
        "set.3mf",
        &crispen::mesh::write_3mf(
            std::io::Cursor::new(Vec::new()),
            &[("Block", &side), ("Spot", &spot)],
        )
        .unwrap()
        .into_inner(),
    );
    let s = wait_for(&config, &log, Duration::from_secs(180), "ready", |s| {
        state_of(s, "set.3mf") == "ready"
    });
    let job = job_by_file(&s, "set.3mf").unwrap();
    let id = job["id"].as_str().unwrap().to_string();
    // In grams where the material is known, else metres.
    let booked = |job: &Value| job["need_g"].as_f64().or(job["need_m"].as_f64()).unwrap();
    let need = booked(job);
    let report = record(root, &id)["slice_report"].clone();
    let parts = report["parts"].as_array().unwrap();
    assert_eq!(parts.len(), 2, "{report:#}");
    // PrusaSlicer labels each object by the file crispen gave it, named after the object.
    let part = |name: &str| {
        parts
            .iter()
            .find(|p| {
                p["name"]
                    .as_str()
                    .unwrap()
                    .starts_with(&format!("{name}.stl"))
            })
            .unwrap_or_else(|| panic!("no part {name}: {report:#}"))
    };
    let block = part("Block")["name"].as_str().unwrap().to_string();
    let top = |name: &str| part(name)["z_mm"][1].as_f64().unwrap();
    // The tallest at the folder's 10 mm; the box at half, to a layer.
    assert!((top("Spot") - 10.0).abs() <= 0.3, "{report:#}");
    assert!((top("Block") - 5.0).abs() <= 0.3, "{report:#}");

    let (ok, out) = ctl(&config, &["cancel", &id, "--part", &block]);
    assert!(ok && out.contains("will not be printed"), "{out}");
    let s = wait_for(
        &config,
        &log,
        Duration::from_secs(10),
        "Block cancelled",
        |s| job_by_file(s, "set.3mf").unwrap()["parts"]["cancelled"] == serde_json::json!([block]),
    );
    // The booking leaves the box's share out.
    let share =
        part("Block")["extruded_mm"].as_f64().unwrap() / report["filament_mm"].as_f64().unwrap();
    let left = booked(job_by_file(&s, "set.3mf").unwrap());
    assert!(share > 0.01, "{report:#}");
    assert!(
        (left - need * (1.0 - share)).abs() < 1e-3,
        "{left} of {need}"
    );

    let (ok, out) = ctl(&config, &["release", &id]);
    assert!(ok, "{out}");
    wait_for(&config, &log, Duration::from_secs(300), "done", |s| {
        state_of(s, "set.3mf") == "done"
    });
    let gcode = root
        .join("spool/jobs")
        .join(&id)
        .join("set.3mf.marlin-175.gcode");
    let program = GcodeProgram::load_for(&gcode, Firmware::Marlin2).unwrap();
    let dropped = program.marks().unwrap().find(&block).unwrap();
    let expected: Vec<String> = crispen::marlin::plate::sent_lines(&program, &[(dropped, 0)])
        .filter_map(|(_, line)| line.map(|l| l.into_owned()))
        .collect();
    let executed = recorded(&root.join("p.rec"));
    assert!(expected.len() < program.len(), "the filter dropped the box");
    assert_eq!(executed, expected, "commands executed");
}

/// A folder of models with a `plate.toml` naming them, dropped into a hot folder, is one
/// job: a plate of its models, each a part named after its file, with the sidecar's other
/// keys; the folder leaves the hot folder, and nothing is left in its staging. A folder
/// holding a file its `plate.toml` does not name is set aside whole, untouched.
#[test]
fn a_folder_of_models_dropped_as_one_job_is_a_plate_of_them() {
    let tmp = tempfile::tempdir().unwrap();
    let root = tmp.path();
    let config = farm(root, 1, 0.01);
    let log = root.join("daemon.log");
    let _daemon = Daemon::start(&config, &log);
    let (_, side) = spot_and_a_box();
    // Each folder is made beside the hot folder and renamed in whole, as a file manager
    // moving it does.
    let make = |name: &str, sidecar: &str| {
        let dir = root.join(name);
        std::fs::create_dir(&dir).unwrap();
        std::fs::copy(common::model("spot.obj"), dir.join("spot.obj")).unwrap();
        crispen::mesh::save(&dir.join("box.stl"), &side).unwrap();
        std::fs::write(dir.join("plate.toml"), sidecar).unwrap();
        std::fs::rename(&dir, root.join("hot").join(name)).unwrap();
    };
    make("bad", "models = [\"spot.obj\"]\n");
    make("set", "models = [\"spot.obj\", \"box.stl\"]\nhold = true\n");

    let s = wait_for(&config, &log, Duration::from_secs(180), "ready", |s| {
        state_of(s, "set.3mf") == "ready"
    });
    let id = job_by_file(&s, "set.3mf").unwrap()["id"]
        .as_str()
        .unwrap()
        .to_string();
    let report = record(root, &id)["slice_report"].clone();
    let mut names: Vec<&str> = report["parts"]
        .as_array()
        .unwrap()
        .iter()
        .map(|p| p["name"].as_str().unwrap())
        .collect();
    names.sort();
    assert!(
        names.len() == 2 && names[0].starts_with("box.") && names[1].starts_with("spot."),
        "{report:#}"
    );
    // The sidecar's other keys came with it.
    assert_eq!(
        record(root, &id)["sidecar"]["hold"],
        true,
        "{:#}",
        record(root, &id)
    );
    // The job keeps the packed plate; the folder left the hot folder.
    assert!(root.join("spool/jobs").join(&id).join("set.3mf").is_file());
    let staging: Vec<_> = std::fs::read_dir(root.join("hot/.crispen-plates"))
        .unwrap()
        .collect();
    assert!(staging.is_empty(), "{staging:?}");
    assert!(!root.join("hot/set").exists());

    // The refused folder is set aside whole, named in the log with the reason.
    let aside = root.join("hot/set-aside/bad");
    let start = std::time::Instant::now();
    while !aside.join("box.stl").exists() {
        assert!(
            start.elapsed() < Duration::from_secs(60),
            "bad was not set aside"
        );
        std::thread::sleep(Duration::from_millis(100));
    }
    let mut held: Vec<String> = std::fs::read_dir(&aside)
        .unwrap()
        .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
        .collect();
    held.sort();
    assert_eq!(held, ["box.stl", "plate.toml", "spot.obj"]);
    let text = std::fs::read_to_string(&log).unwrap();
    assert!(
        text.contains("box.stl is in the folder but is not a model named in plate.toml"),
        "{text}"
    );
}

/// A pre-sliced file labelled the Klipper way (`EXCLUDE_OBJECT_DEFINE`/`_START`/`_END`,
/// as OrcaSlicer and PrusaSlicer write for Klipper) or with Marlin's `M486`: the daemon
/// reads its parts as for a plate it sliced (names, outlines on the bed), which the job
/// page draws.
#[test]
fn a_labelled_pre_sliced_file_shows_its_parts() {
    use crispen::daemon::prepare::steps::{prepare_one, SliceRequest, Target};
    let tmp = tempfile::tempdir().unwrap();
    let root = tmp.path();
    let mut req = SliceRequest::new(common::model("spot.obj"), 10.0);
    req.strength = crispen::enhance::Strength::Off;
    req.per_plate = 2;
    let sliced = root.join("sliced.gcode");
    let target = Target {
        machine: crispen::machine::Machine::builtin("marlin-175").unwrap(),
        output: sliced.clone(),
        keep_mesh: None,
    };
    prepare_one(&req, target, &mut |_| {}).expect("sliced");
    let text = std::fs::read_to_string(&sliced).unwrap();
    // PrusaSlicer's labels, rewritten as the other two schemes write them.
    let relabel = |start: &dyn Fn(usize) -> String, end: &dyn Fn(usize) -> String| {
        let mut names: Vec<String> = Vec::new();
        let mut out = String::new();
        for line in text.lines() {
            let (name, open) = match (
                line.strip_prefix("; printing object "),
                line.strip_prefix("; stop printing object "),
            ) {
                (Some(n), _) => (n, true),
                (_, Some(n)) => (n, false),
                _ => {
                    out.push_str(line);
                    out.push('\n');
                    continue;
                }
            };
            let i = names.iter().position(|n| n == name).unwrap_or_else(|| {
                names.push(name.to_string());
                names.len() - 1
            });
            out.push_str(&if open { start(i) } else { end(i) });
            out.push('\n');
        }
        assert_eq!(names.len(), 2, "PrusaSlicer labelled two copies");
        out
    };
    let klipper = relabel(
        &|i| format!("EXCLUDE_OBJECT_START NAME=spot_{}", i + 1),
        &|i| format!("EXCLUDE_OBJECT_END NAME=spot_{}", i + 1),
    );
    let klipper =
        format!("EXCLUDE_OBJECT_DEFINE NAME=spot_1\nEXCLUDE_OBJECT_DEFINE NAME=spot_2\n{klipper}");
    let marlin = relabel(&|i| format!("M486 S{i}\nM486 Aspot {}", i + 1), &|_| {
        "M486 S-1".into()
    });
    let marlin = format!("M486 T2\n{marlin}");

    let config = farm(root, 1, 0.01);
    std::fs::write(root.join("hot/klipper.gcode.toml"), "hold = true\n").unwrap();
    std::fs::write(root.join("hot/marlin.gcode.toml"), "hold = true\n").unwrap();
    let log = root.join("daemon.log");
    let _daemon = Daemon::start(&config, &log);
    drop_model(&root.join("hot"), "klipper.gcode", klipper.as_bytes());
    drop_model(&root.join("hot"), "marlin.gcode", marlin.as_bytes());
    let s = wait_for(&config, &log, Duration::from_secs(60), "both ready", |s| {
        state_of(s, "klipper.gcode") == "ready" && state_of(s, "marlin.gcode") == "ready"
    });
    for (file, names) in [
        ("klipper.gcode", ["spot_1", "spot_2"]),
        ("marlin.gcode", ["spot 1", "spot 2"]),
    ] {
        let job = job_by_file(&s, file).unwrap();
        assert_eq!(job["parts"]["total"], 2, "{job:#}");
        let report = record(root, job["id"].as_str().unwrap())["slice_report"].clone();
        let parts = report["parts"].as_array().unwrap();
        let got: Vec<&str> = parts.iter().map(|p| p["name"].as_str().unwrap()).collect();
        assert_eq!(got, names, "{file}");
        for p in parts {
            // An outline of the part's extrusions, on the bed.
            let outline = p["outline"].as_array().unwrap();
            assert!(outline.len() >= 3, "{file}: {p}");
            assert!(p["extruded_mm"].as_f64().unwrap() > 10.0, "{file}: {p}");
        }
    }
}
