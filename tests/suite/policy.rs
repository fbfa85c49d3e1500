//! The G-code policy end to end: the real daemon, simulated printers of every firmware
//! flavour on real ptys. A file asking for more heat than the machine takes, resetting and
//! saving its settings, updating its firmware or sweeping an arc off the bed fails at
//! preparation, naming the command, and no printer receives a line of it (each simulator's
//! own record says what it executed); a machine that allows `M500` prints a file saving
//! its settings; a clean file prints, its verdict in the job's report.

use crate::common;
use common::daemon::{ctl, drop_model, recorded, state_of, wait_for, Daemon};
use common::job_by_file;

use std::time::Duration;

const LIMIT: Duration = Duration::from_secs(240);

/// An `M117` of 125 bytes: more than MAX_CMD_SIZE (96) less the host's framing.
const LONG_LINE: &str = "M117 xxxxxxxxxxxxxxxxxxxxxxxxxxxxxxxxxxxxxxxxxxxxxxxxxxxxxxxxxxxxxxxxxxxxxxxxxxxxxxxxxxxxxxxxxxxxxxxxxxxxxxxxxxxxxxxxxxxxxxxx\n";

/// A small print any of the machines here may take: heat, home, a marker the simulator
/// records (`M118 <marker>`), `body`, a few extruding moves in the middle of the bed.
fn gcode(marker: &str, body: &str) -> String {
    format!(
        "M104 S200\nM140 S50\nG28\nM109 S200\nM190 S50\nG90\nM82\nG92 E0\nG1 Z0.3 F600\n\
         M118 {marker}\n{body}G1 X60 Y60 F3000\nG1 X100 Y60 E2\nG1 X100 Y100 E4\n\
         G1 Z10\nM104 S0\nM140 S0\n"
    )
}

#[test]
fn refused_files_fail_before_any_printer_receives_a_line() {
    let dir = tempfile::tempdir().unwrap();
    let root = dir.path();
    std::fs::create_dir_all(root.join("hot")).unwrap();
    let config = root.join("crispen.toml");
    let log = root.join("daemon.log");
    let rec = |p: &str| root.join(format!("{p}.rec"));
    // One printer per firmware flavour; the Marlin 2 one's machine allows M500.
    let printers = [
        ("um2", "machine = \"ultimaker2\""),
        ("m2", "machine = \"saves-175\""),
        ("m20", "firmware = \"marlin20\""),
    ];
    let mut text = String::from(
        "[spool]\ndir = \"spool\"\n[control]\nsocket = \"c.sock\"\n[farm]\nsettle_s = 0.3\n\
         [[machine]]\nname = \"saves-175\"\nbased_on = \"marlin-175\"\nallow = [\"M500\"]\n",
    );
    for (name, which) in printers {
        text += &format!(
            "[[printer]]\nname = \"{name}\"\n{which}\n[printer.simulate]\ntime_scale = 0.0\n\
             record = \"{}\"\n",
            rec(name).display()
        );
    }
    text += "[[folder]]\npath = \"hot\"\nheight_mm = 20\nprinters = [\"um2\", \"m2\", \"m20\"]\n";
    std::fs::write(&config, text).unwrap();
    let _daemon = Daemon::start(&config, &log);
    wait_for(&config, &log, LIMIT, "three idle printers", |s| {
        s["printers"]
            .as_array()
            .is_some_and(|p| p.len() == 3 && p.iter().all(|p| p["state"] == "idle"))
    });

    let refused = [
        (
            "hot.gcode",
            "M104 S400\n",
            "`M104 S400` asks for 400 °C on the hotend",
        ),
        ("reset.gcode", "M502\nM500\n", "`M502` resets every setting"),
        ("flash.gcode", "M997\n", "`M997` starts a firmware update"),
        (
            "arc.gcode",
            "G1 X1 Y50\nG2 I-100 E5\n",
            "`G2 I-100 E5` sweeps X to -199.0",
        ),
        // The host's own load check: longer than any of these firmwares takes.
        (
            "long.gcode",
            LONG_LINE,
            "long.gcode:11: command is 125 bytes",
        ),
    ];
    for (file, body, _) in refused {
        drop_model(&root.join("hot"), file, gcode(file, body).as_bytes());
    }
    let s = wait_for(&config, &log, LIMIT, "every refused file failed", |s| {
        refused.iter().all(|(f, _, _)| state_of(s, f) == "failed")
    });
    for (file, _, says) in refused {
        let job = job_by_file(&s, file).unwrap();
        let reason = job["reason"].as_str().unwrap_or_default();
        // Every machine's reason names the line and the command.
        for machine in ["ultimaker2", "saves-175", "marlin-175"] {
            assert!(
                reason.contains(&format!("{machine}: {file} is not for the {machine}")),
                "{file}: {reason}"
            );
        }
        assert!(reason.contains(says), "{file}: {reason}");
        assert!(job["printer"].is_null(), "{file} was claimed: {job}");
    }
    // Refused at line 11 or 12 (after the 10 lines of the prelude).
    let reason = job_by_file(&s, "reset.gcode").unwrap()["reason"].to_string();
    assert!(reason.contains("line 11: `M502`"), "{reason}");

    // A file saving the settings prints on the machine that allows it, and only there.
    drop_model(
        &root.join("hot"),
        "save.gcode",
        gcode("save", "M500\n").as_bytes(),
    );
    let s = wait_for(&config, &log, LIMIT, "save.gcode printed", |s| {
        state_of(s, "save.gcode") == "done"
    });
    let job = job_by_file(&s, "save.gcode").unwrap();
    assert_eq!(job["printer"], "m2", "{job}");

    // A clean file prints, its verdict in the report.
    let (ok, out) = ctl(&config, &["clear", "m2"]);
    assert!(ok, "{out}");
    drop_model(
        &root.join("hot"),
        "clean.gcode",
        gcode("clean", "M117 Printing clean\n").as_bytes(),
    );
    let s = wait_for(&config, &log, LIMIT, "clean.gcode printed", |s| {
        state_of(s, "clean.gcode") == "done"
    });
    let job = job_by_file(&s, "clean.gcode").unwrap();
    let printer = job["printer"].as_str().unwrap().to_string();
    assert!(
        recorded(&rec(&printer)).contains(&"M118 clean".to_string()),
        "{printer} did not print clean.gcode"
    );
    // The job's record (spool/jobs/<id>/job.json) keeps the verdict in its report.
    let record: serde_json::Value = serde_json::from_slice(
        &std::fs::read(
            root.join("spool/jobs")
                .join(job["id"].as_str().unwrap())
                .join("job.json"),
        )
        .unwrap(),
    )
    .unwrap();
    let verdict = &record["slice_report"]["policy"];
    assert_eq!(verdict["refusals_total"], 0, "{record}");
    assert_eq!(verdict["pauses_total"], 0, "{record}");
    assert_eq!(verdict["lines"], 17, "{record}");

    // No printer received a line of a refused file: no marker, no refused command.
    for (name, _) in printers {
        let executed = recorded(&rec(name));
        for (file, body, _) in refused {
            assert!(
                !executed.iter().any(|c| c == &format!("M118 {file}")),
                "{name} executed {file}"
            );
            let first = body.lines().next().unwrap();
            assert!(
                !executed.iter().any(|c| c == first),
                "{name} executed {first}"
            );
        }
        let saved = executed.iter().any(|c| c == "M500");
        assert_eq!(saved, name == "m2", "{name}: {executed:?}");
    }
}

/// Defence in depth: crispen's own slicer output passes the policy too, so a machine
/// whose start code resets and saves the settings makes no job, naming the command; the
/// same start code with the reset left out slices, its verdict in the report.
#[test]
fn a_start_code_that_resets_the_printer_fails_the_slicing() {
    use crispen::daemon::prepare::steps::{prepare_one, SliceRequest, Target};
    use crispen::machine::Machine;
    let dir = tempfile::tempdir().unwrap();
    let start = include_str!("../../gcode/start.gcode");
    let slice = |start_gcode: String, name: &str| {
        let mut req = SliceRequest::new(common::model("spot.obj"), 10.0);
        req.strength = crispen::enhance::Strength::Off;
        let target = Target {
            machine: Machine {
                name: name.into(),
                start_gcode: Some(start_gcode),
                ..Machine::builtin("marlin-175").unwrap()
            },
            output: dir.path().join(format!("{name}.gcode")),
            keep_mesh: None,
        };
        prepare_one(&req, target, &mut |_| {})
    };
    let e = slice(format!("{start}M502\nM500\n"), "resets")
        .unwrap_err()
        .to_string();
    assert!(
        e.contains("refused by the G-code policy") && e.contains("`M502` resets every setting"),
        "{e}"
    );
    assert!(!dir.path().join("resets.gcode").exists());
    let report = slice(format!("{start}M117 Magnets at 5 mm\n"), "clean").unwrap();
    let verdict = report.policy.expect("a verdict in the report");
    assert!(verdict.passed(), "{verdict:?}");
    assert!(dir.path().join("clean.gcode").exists());
}
