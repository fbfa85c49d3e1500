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
