//! End-to-end tests of `crispen run`: the real binary, simulated printers on real ptys
//! (declared in the config, or separate `crispen sim` processes), the real PrusaSlicer,
//! real files dropped into a hot folder. They check pick-up (rename-in, slow copy,
//! sidecar), failure of a corrupt model, the bed-clear gate, exactly-once delivery of
//! every done job's G-code, recovery after `kill -9` in the middle of a print or of a
//! slicing (whose slicer must not outlive the daemon), print
//! controls (pause, resume, cancel, retry), a safe stop at SIGTERM, an unplugged printer
//! and its reconnection, printers added and removed by SIGHUP, a reload's policy per key,
//! and a spool whose filesystem fills up.

use crate::common;
use common::daemon::{
    ctl, drop_model, job_gcode, passed_over, recorded, state_of, status, wait_for, Daemon, Killed,
    BIN,
};
use common::{job_by_file, printer};

use crispen::marlin::firmware::Firmware;
use crispen::marlin::gcode::GcodeProgram;
use serde_json::Value;
use std::io::Write;
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};

#[test]
fn farm_end_to_end_with_restart() {
    let tmp = tempfile::tempdir().unwrap();
    let root = tmp.path();
    let hot = root.join("hot/25mm");
    std::fs::create_dir_all(&hot).unwrap();
    let config = root.join("crispen.toml");
    let log = root.join("daemon.log");
    let rec_a = root.join("a.rec");
    let rec_b = root.join("b.rec");
    std::fs::write(
        &config,
        format!(
            r#"
[spool]
dir = "spool"
[control]
socket = "crispen.sock"
[farm]
max_heating = 1
settle_s = 1.0
rescan_s = 2
[[printer]]
name = "a"
firmware = "marlin2"
[printer.simulate]
time_scale = 0.01
record = "{}"
[[printer]]
name = "b"
firmware = "ultimaker2"
[printer.simulate]
time_scale = 0.01
record = "{}"
[[folder]]
path = "hot/25mm"
height_mm = 25
printers = ["a", "b"]
"#,
            rec_a.display(),
            rec_b.display()
        ),
    )
    .unwrap();
    // One printer of each firmware: `a` answers ADVANCED_OK and sends the host ahead into
    // its 128-byte receive buffer, `b` speaks the older Ultimaker 2 dialect.
    let model = std::fs::read(concat!(env!("CARGO_MANIFEST_DIR"), "/tests/data/spot.obj")).unwrap();

    let mut daemon = Daemon::start(&config, &log);
    wait_for(
        &config,
        &log,
        Duration::from_secs(20),
        "the daemon to answer",
        |s| s["printers"].as_array().is_some_and(|p| p.len() == 2),
    );

    // 1. Renamed in: complete at once.
    std::fs::write(hot.join("first.obj.part"), &model).unwrap();
    std::fs::rename(hot.join("first.obj.part"), hot.join("first.obj")).unwrap();
    // 2. A corrupt model.
    std::fs::write(
        hot.join("broken.stl"),
        b"solid broken\nfacet normal 0 0 this is not an stl\n",
    )
    .unwrap();
    // 3. A sidecar turning enhancement off (sidecar first, as a user would copy both).
    std::fs::write(hot.join("igea.obj.toml"), "enhance = false\n").unwrap();
    std::fs::write(hot.join("igea.obj"), &model).unwrap();
    // 4. Copied slowly, in chunks, with pauses shorter than the settle time. It must not
    // be taken half-copied: its job is checked below to begin after the copy ended.
    let copied = {
        let mut f = std::fs::File::create(hot.join("slow.obj")).unwrap();
        for chunk in model.chunks(model.len() / 8 + 1) {
            f.write_all(chunk).unwrap();
            f.flush().unwrap();
            std::thread::sleep(Duration::from_millis(300));
        }
        drop(f);
        std::time::SystemTime::now()
            .duration_since(std::time::UNIX_EPOCH)
            .unwrap()
            .as_secs_f64()
    };
    let dropped = ["first.obj", "broken.stl", "igea.obj", "slow.obj"];

    let s = wait_for(
        &config,
        &log,
        Duration::from_secs(120),
        "the corrupt model to fail",
        |s| state_of(s, "broken.stl") == "failed",
    );
    let reason = job_by_file(&s, "broken.stl").unwrap()["reason"]
        .as_str()
        .unwrap_or("")
        .to_string();
    assert!(
        reason.contains("broken.stl"),
        "failure reason names the file: {reason}"
    );
    // The slow copy became a job only after its last byte was written.
    let slow = wait_for(
        &config,
        &log,
        Duration::from_secs(120),
        "the slow copy picked up",
        |s| job_by_file(s, "slow.obj").is_some(),
    );
    let slow_dir = root.join("spool/jobs").join(
        job_by_file(&slow, "slow.obj").unwrap()["id"]
            .as_str()
            .unwrap(),
    );
    let state: Value =
        serde_json::from_slice(&std::fs::read(slow_dir.join("job.json")).unwrap()).unwrap();
    let queued_at = state["history"][0][1].as_f64().unwrap();
    assert!(
        queued_at >= copied,
        "picked up {:.3} s before its copy ended",
        copied - queued_at
    );
    assert_eq!(std::fs::read(slow_dir.join("slow.obj")).unwrap(), model);

    // Two printers, three good jobs: two get printed, then both printers wait for their
    // beds to be cleared and the third job stays ready.
    let s = wait_for(
        &config,
        &log,
        Duration::from_secs(240),
        "two prints done",
        |s| {
            ["first.obj", "igea.obj", "slow.obj"]
                .iter()
                .filter(|f| state_of(s, f) == "done")
                .count()
                == 2
                && printer(s, "a")["state"] == "bed_not_cleared"
                && printer(s, "b")["state"] == "bed_not_cleared"
        },
    );
    let waiting: String = ["first.obj", "igea.obj", "slow.obj"]
        .iter()
        .find(|f| state_of(&s, f) != "done")
        .unwrap()
        .to_string();
    // Once the third job is ready, both printers could take it at once: the bed gate
    // must hold it, seen once both have looked for a job since it was ready.
    let ready = wait_for(
        &config,
        &log,
        Duration::from_secs(120),
        "the third job ready",
        |s| state_of(s, &waiting) == "ready",
    );
    let s = passed_over(
        &config,
        &log,
        &ready,
        &["a", "b"],
        "both printers looked for a job since it was ready",
    );
    for p in ["a", "b"] {
        assert_eq!(printer(&s, p)["state"], "bed_not_cleared", "{s:#}");
    }
    assert_eq!(
        state_of(&s, &waiting),
        "ready",
        "held by the bed gates: {s:#}"
    );
    let igea = job_by_file(&s, "igea.obj").unwrap();
    assert!(igea["state"] != "failed", "{igea}");

    // Clear printer a: it takes the waiting job. Kill the daemon mid-print.
    assert_eq!(printer(&s, "a")["bed_cleared"], false);
    let (ok, out) = ctl(&config, &["clear", "a"]);
    assert!(ok, "{out}");
    wait_for(
        &config,
        &log,
        Duration::from_secs(60),
        "the third job printing",
        |s| {
            let p = printer(s, "a");
            p["state"] == "printing" && p["progress"]["lines_acked"].as_u64().unwrap_or(0) > 200
        },
    );
    daemon.kill9();
    let before: Value = {
        let spool = root.join("spool/jobs");
        let mut states = serde_json::Map::new();
        for e in std::fs::read_dir(&spool).unwrap() {
            let j: Value =
                serde_json::from_slice(&std::fs::read(e.unwrap().path().join("job.json")).unwrap())
                    .unwrap();
            states.insert(j["file"].as_str().unwrap().to_string(), j["state"].clone());
        }
        Value::Object(states)
    };
    assert_eq!(before[&waiting], "printing");

    let mut daemon = Daemon::start(&config, &log);
    let s = wait_for(
        &config,
        &log,
        Duration::from_secs(30),
        "the restarted daemon's printers",
        |s| {
            s["printers"]
                .as_array()
                .is_some_and(|p| p.len() == 2 && p.iter().all(|p| p["state"] != "connecting"))
        },
    );
    assert_eq!(state_of(&s, &waiting), "interrupted");
    assert_eq!(printer(&s, "a")["state"], "bed_not_cleared");
    assert_eq!(printer(&s, "a")["bed_cleared"], false);
    for f in dropped {
        if f != waiting {
            assert_eq!(
                before[f],
                state_of(&s, f),
                "{f} kept its state across the restart"
            );
        }
    }

    // No dropped file is missing: each is in its job directory, none left in the folder.
    for f in dropped {
        let job = job_by_file(&s, f).unwrap_or_else(|| panic!("{f} has a job"));
        let id = job["id"].as_str().unwrap();
        assert!(
            root.join("spool/jobs").join(id).join(f).is_file(),
            "{f} kept in the spool"
        );
    }
    assert!(root
        .join("spool/jobs")
        .join(job_by_file(&s, "igea.obj").unwrap()["id"].as_str().unwrap())
        .join("igea.obj.toml")
        .is_file());

    // Every done job's G-code was executed exactly once, in order, by its printer.
    for (name, rec, fw, machine) in [
        ("a", &rec_a, Firmware::Marlin2, "marlin-175"),
        ("b", &rec_b, Firmware::Ultimaker2, "ultimaker2"),
    ] {
        let executed = recorded(rec);
        let mut expected: Vec<String> = Vec::new();
        for f in ["first.obj", "igea.obj", "slow.obj"] {
            let job = job_by_file(&s, f).unwrap();
            if job["printer"] == name && job["state"] == "done" {
                let gcode: PathBuf = root
                    .join("spool/jobs")
                    .join(job["id"].as_str().unwrap())
                    .join(format!("{f}.{machine}.gcode"));
                expected.extend(
                    GcodeProgram::load_for(&gcode, fw)
                        .unwrap()
                        .iter()
                        // As the printer reads it: Ultimaker2Marlin's lines may be sent
                        // with an extra space or zero (the cut-line guard).
                        .map(crispen::marlin::protocol::canonical),
                );
            }
        }
        assert!(!expected.is_empty(), "printer {name} printed a job");
        assert!(
            executed.len() >= expected.len(),
            "printer {name} executed everything"
        );
        if let Some(i) = (0..expected.len()).find(|&i| executed[i] != expected[i]) {
            panic!(
                "printer {name} did not execute its done jobs exactly once, in order: first difference at command {i}: executed {:?}, expected {:?}",
                &executed[i.saturating_sub(2)..(i + 3).min(executed.len())],
                &expected[i.saturating_sub(2)..(i + 3).min(expected.len())]
            );
        }
        if name == "b" {
            assert_eq!(executed.len(), expected.len(), "nothing else ran on b");
        }
    }

    // The enhancement was off for the sidecar's job and on for the others.
    let report = |f: &str| -> Value {
        let id = job_by_file(&s, f).unwrap()["id"]
            .as_str()
            .unwrap()
            .to_string();
        serde_json::from_slice(
            &std::fs::read(root.join("spool/jobs").join(id).join("job.json")).unwrap(),
        )
        .unwrap()
    };
    assert_eq!(
        report("igea.obj")["slice_report"]["enhancement"]["mode"],
        "unmodified"
    );
    assert_eq!(
        report("first.obj")["slice_report"]["enhancement"]["mode"],
        "enhanced"
    );

    // SIGHUP with a broken config: refused, the daemon carries on with the old one.
    let good = std::fs::read_to_string(&config).unwrap();
    std::fs::write(&config, good.replace("height_mm = 25", "height_mm = -1")).unwrap();
    let pid = nix::unistd::Pid::from_raw(daemon.child.id() as i32);
    nix::sys::signal::kill(pid, nix::sys::signal::Signal::SIGHUP).unwrap();
    // The good file goes back only once the daemon has read the bad one.
    let started = Instant::now();
    let refusal = loop {
        let log_text = std::fs::read_to_string(&log).unwrap();
        if let Some(line) = log_text.lines().find(|l| l.contains("new config refused")) {
            break line.to_string();
        }
        assert!(
            started.elapsed() < Duration::from_secs(20),
            "the refusal is logged"
        );
        std::thread::sleep(Duration::from_millis(100));
    };
    std::fs::write(&config, &good).unwrap();
    assert!(refusal.contains("height_mm"), "the refusal names the key");
    assert!(
        daemon.child.try_wait().unwrap().is_none(),
        "still running after a bad reload"
    );
    assert!(
        status(&config).is_some(),
        "still answering after a bad reload"
    );

    // SIGTERM with nothing printing: a clean exit, socket removed.
    nix::sys::signal::kill(pid, nix::sys::signal::Signal::SIGTERM).unwrap();
    let started = Instant::now();
    let code = loop {
        if let Some(code) = daemon.child.try_wait().unwrap() {
            break code;
        }
        assert!(
            started.elapsed() < Duration::from_secs(20),
            "daemon did not stop on SIGTERM"
        );
        std::thread::sleep(Duration::from_millis(100));
    };
    assert!(code.success(), "{code:?}");
    assert!(!root.join("crispen.sock").exists());
}

/// A farm whose slicer never finishes, with a model dropped in: the daemon running, the
/// job preparing and the stand-in slicer's process started.
struct StuckSlicing {
    config: PathBuf,
    log: PathBuf,
    daemon: Daemon,
    job: String,
    slicer_proc: PathBuf,
}

fn start_stuck_slicing(root: &Path) -> StuckSlicing {
    let hot = root.join("hot");
    std::fs::create_dir_all(&hot).unwrap();
    // A stand-in slicer that never finishes and says which process it is.
    let pid_file = root.join("slicer.pid");
    let slicer = root.join("endless-slicer");
    std::fs::write(
        &slicer,
        format!(
            "#!/bin/sh\necho $$ > {}\nexec sleep 600\n",
            pid_file.display()
        ),
    )
    .unwrap();
    Command::new("chmod")
        .arg("755")
        .arg(&slicer)
        .status()
        .unwrap();
    let config = root.join("crispen.toml");
    std::fs::write(
        &config,
        format!(
            "[spool]\ndir = \"{spool}\"\n[control]\nsocket = \"{sock}\"\n[farm]\nsettle_s = 0.5\n\
             [[printer]]\nname = \"p\"\nfirmware = \"marlin2\"\n[printer.simulate]\ntime_scale = 0.0\n\
             [[folder]]\npath = \"{hot}\"\nheight_mm = 30\nprinters = [\"p\"]\n",
            spool = root.join("spool").display(),
            sock = root.join("c.sock").display(),
            hot = hot.display(),
        ),
    )
    .unwrap();
    let log = root.join("daemon.log");
    let log_file = std::fs::File::create(&log).unwrap();
    let daemon = Daemon {
        child: Command::new(BIN)
            .args(["run", "--config"])
            .arg(&config)
            .env("CRISPEN_PRUSA_SLICER", &slicer)
            .stdout(Stdio::null())
            .stderr(log_file)
            .spawn()
            .unwrap(),
    };

    let model = Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/data/spot.obj");
    std::fs::copy(&model, hot.join("spot.obj.part")).unwrap();
    std::fs::rename(hot.join("spot.obj.part"), hot.join("spot.obj")).unwrap();

    let s = wait_for(&config, &log, Duration::from_secs(30), "preparing", |s| {
        state_of(s, "spot.obj") == "preparing"
    });
    let job = job_by_file(&s, "spot.obj").unwrap()["id"]
        .as_str()
        .unwrap()
        .to_string();
    // The shell creates the file before it writes the number: wait for a whole line.
    let start = Instant::now();
    let pid: u32 = loop {
        let text = std::fs::read_to_string(&pid_file).unwrap_or_default();
        if let Some(pid) = text.strip_suffix('\n').and_then(|t| t.parse().ok()) {
            break pid;
        }
        assert!(
            start.elapsed() < Duration::from_secs(30),
            "the slicer never started"
        );
        std::thread::sleep(Duration::from_millis(50));
    };
    let slicer_proc = PathBuf::from(format!("/proc/{pid}"));
    assert!(slicer_proc.exists(), "the slicer should be running");
    StuckSlicing {
        config,
        log,
        daemon,
        job,
        slicer_proc,
    }
}

fn assert_gone_soon(proc_dir: &Path, log: &Path, after: &str) {
    let start = Instant::now();
    while proc_dir.exists() {
        assert!(
            start.elapsed() < Duration::from_secs(10),
            "the slicer ({}) is still running after {after}\nlog:\n{}",
            proc_dir.display(),
            std::fs::read_to_string(log).unwrap_or_default()
        );
        std::thread::sleep(Duration::from_millis(50));
    }
}

/// Cancelling a job while its model is being sliced stops the slicer: its process is
/// killed rather than left to finish work nobody wants, and the job ends cancelled with
/// its model still in the spool.
#[test]
fn cancel_during_preparation_kills_the_slicer() {
    let dir = tempfile::tempdir().unwrap();
    let root = dir.path();
    let farm = start_stuck_slicing(root);
    let (ok, text) = ctl(&farm.config, &["cancel", &farm.job]);
    assert!(ok, "{text}");
    wait_for(
        &farm.config,
        &farm.log,
        Duration::from_secs(10),
        "cancelled",
        |s| state_of(s, "spot.obj") == "cancelled",
    );
    assert_gone_soon(&farm.slicer_proc, &farm.log, "the cancel");
    // The dropped model is still accounted for.
    assert!(root
        .join("spool/jobs")
        .join(&farm.job)
        .join("spot.obj")
        .exists());
}

/// `kill -9` of the daemon while a model is being sliced: the kernel takes the slicer
/// down with it, and the restarted daemon prepares the job again (with the real slicer
/// this time) and prints it.
#[test]
fn daemon_killed_during_preparation_resumes_the_job() {
    let dir = tempfile::tempdir().unwrap();
    let root = dir.path();
    let mut farm = start_stuck_slicing(root);
    farm.daemon.kill9();
    assert_gone_soon(&farm.slicer_proc, &farm.log, "the daemon was killed");
    let stored: Value = serde_json::from_slice(
        &std::fs::read(root.join("spool/jobs").join(&farm.job).join("job.json")).unwrap(),
    )
    .unwrap();
    assert_eq!(stored["state"], "preparing", "{stored}");

    let _daemon = Daemon::start(&farm.config, &farm.log);
    let s = wait_for(
        &farm.config,
        &farm.log,
        Duration::from_secs(120),
        "done",
        |s| state_of(s, "spot.obj") == "done",
    );
    assert_eq!(
        job_by_file(&s, "spot.obj").unwrap()["id"],
        farm.job.as_str()
    );
}

/// Asserts the recorded commands are a prefix of the job followed by the safe-stop lines
/// (heaters, fan, motors off), after the unnumbered stop lines.
#[track_caller]
fn assert_prefix_then_safe_stop(recorded: &[String], job: &[String]) {
    let safe_stop = ["M104 S0", "M140 S0", "M107", "M84"].map(String::from);
    let tail = &recorded[recorded.len().saturating_sub(8)..];
    assert!(
        recorded.ends_with(&safe_stop),
        "the print must end with the safe-stop lines: {tail:?}"
    );
    // Before the numbered stop, the lines that work whatever line number the printer
    // expects: `M108` where it breaks a wait, heaters off unnumbered, the count reset.
    let mut prefix = &recorded[..recorded.len() - safe_stop.len()];
    while prefix.last().is_some_and(|c| {
        ["M108", "M104 S0", "M140 S0"].contains(&c.as_str()) || c.starts_with("M110")
    }) {
        prefix = &prefix[..prefix.len() - 1];
    }
    assert!(
        prefix.len() < job.len(),
        "the job was stopped before its end: {tail:?}"
    );
    if let Some(i) = (0..prefix.len()).find(|&i| prefix[i] != job[i]) {
        panic!(
            "executed command {i} is {:?}, the job's is {:?}",
            prefix[i], job[i]
        );
    }
}

/// Pause, resume and cancel reach a print through the daemon; a cancelled job can be
/// retried once the bed is cleared; and with `on_shutdown = "stop"` a SIGTERM stops the
/// print safely, leaves its job interrupted, and the restarted daemon keeps the bed gate.
#[test]
fn print_controls_and_stop_at_shutdown() {
    let tmp = tempfile::tempdir().unwrap();
    let root = tmp.path();
    let hot = root.join("hot");
    std::fs::create_dir_all(&hot).unwrap();
    let config = root.join("crispen.toml");
    let log = root.join("daemon.log");
    let rec = root.join("p.rec");
    std::fs::write(
        &config,
        format!(
            "[spool]\ndir = \"spool\"\n[control]\nsocket = \"c.sock\"\n\
             [farm]\nsettle_s = 0.5\non_shutdown = \"stop\"\n\
             [[printer]]\nname = \"p\"\nfirmware = \"marlin2\"\n\
             [printer.simulate]\ntime_scale = 0.02\nrecord = \"{}\"\n\
             [[folder]]\npath = \"hot\"\nheight_mm = 25\nprinters = [\"p\"]\n",
            rec.display()
        ),
    )
    .unwrap();
    let model = Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/data/spot.obj");
    let mut daemon = Daemon::start(&config, &log);
    std::fs::copy(&model, hot.join("spot.obj.part")).unwrap();
    std::fs::rename(hot.join("spot.obj.part"), hot.join("spot.obj")).unwrap();

    let acked = |s: &Value| {
        printer(s, "p")["progress"]["lines_acked"]
            .as_u64()
            .unwrap_or(0)
    };
    let s = wait_for(&config, &log, Duration::from_secs(120), "printing", |s| {
        printer(s, "p")["state"] == "printing" && acked(s) > 100
    });
    let id = job_by_file(&s, "spot.obj").unwrap()["id"]
        .as_str()
        .unwrap()
        .to_string();

    // Pause: no more lines are acknowledged while paused. The print shows itself again
    // each time it reads a temperature report (the printer sends one every period): a
    // line it sent at one report would be answered before the printer's report after
    // next, so three showings later nothing was sent at the first.
    let (ok, out) = ctl(&config, &["pause", "p"]);
    assert!(ok, "{out}");
    let paused = wait_for(&config, &log, Duration::from_secs(20), "paused", |s| {
        printer(s, "p")["state"] == "paused"
    });
    let shown_at = |s: &Value| {
        printer(s, "p")["progress"]["elapsed_s"]
            .as_f64()
            .unwrap_or(0.0)
    };
    let mut s = paused.clone();
    for turn in 1..=3 {
        let before = shown_at(&s);
        s = wait_for(
            &config,
            &log,
            Duration::from_secs(20),
            &format!("the paused print shown again ({turn})"),
            |s| shown_at(s) > before,
        );
        assert_eq!(printer(&s, "p")["state"], "paused", "{s:#}");
        assert_eq!(
            acked(&s),
            acked(&paused),
            "a line acknowledged while paused"
        );
    }

    // Resume: lines flow again.
    let (ok, out) = ctl(&config, &["resume", "p"]);
    assert!(ok, "{out}");
    let before = acked(&s);
    wait_for(&config, &log, Duration::from_secs(20), "resumed", |s| {
        printer(s, "p")["state"] == "printing" && acked(s) > before + 50
    });

    // Cancel: the job ends cancelled, the printer ran the safe-stop lines, and the bed
    // gate holds the printer.
    let (ok, out) = ctl(&config, &["cancel", &id]);
    assert!(ok, "{out}");
    let s = wait_for(&config, &log, Duration::from_secs(30), "cancelled", |s| {
        state_of(s, "spot.obj") == "cancelled" && printer(s, "p")["state"] == "bed_not_cleared"
    });
    assert_eq!(printer(&s, "p")["bed_cleared"], false);
    let job = job_gcode(root, &id, "spot.obj");
    assert_prefix_then_safe_stop(&recorded(&rec), &job);

    // Retry: the job waits for the bed, then prints again from its first line.
    let (ok, out) = ctl(&config, &["retry", &id]);
    assert!(ok, "{out}");
    let ready = wait_for(
        &config,
        &log,
        Duration::from_secs(120),
        "the retried job ready",
        |s| state_of(s, "spot.obj") == "ready",
    );
    let s = passed_over(
        &config,
        &log,
        &ready,
        &["p"],
        "the printer looked for a job since the retried one was ready",
    );
    assert_eq!(
        state_of(&s, "spot.obj"),
        "ready",
        "held by the bed gate: {s:#}"
    );
    assert_eq!(printer(&s, "p")["state"], "bed_not_cleared");
    let executed_before_retry = recorded(&rec).len();
    let (ok, out) = ctl(&config, &["clear", "p"]);
    assert!(ok, "{out}");
    wait_for(
        &config,
        &log,
        Duration::from_secs(60),
        "printing again",
        |s| state_of(s, "spot.obj") == "printing" && acked(s) > 100,
    );

    // SIGTERM with on_shutdown = "stop": the print stops safely and the daemon exits.
    nix::sys::signal::kill(
        nix::unistd::Pid::from_raw(daemon.child.id() as i32),
        nix::sys::signal::Signal::SIGTERM,
    )
    .unwrap();
    let start = Instant::now();
    let exit = loop {
        if let Some(exit) = daemon.child.try_wait().unwrap() {
            break exit;
        }
        assert!(
            start.elapsed() < Duration::from_secs(30),
            "the daemon did not exit after SIGTERM\nlog:\n{}",
            std::fs::read_to_string(&log).unwrap_or_default()
        );
        std::thread::sleep(Duration::from_millis(100));
    };
    assert!(exit.success(), "{exit:?}");
    let retried = recorded(&rec)[executed_before_retry..].to_vec();
    assert_prefix_then_safe_stop(&retried, &job);
    let stored: Value = serde_json::from_slice(
        &std::fs::read(root.join("spool/jobs").join(&id).join("job.json")).unwrap(),
    )
    .unwrap();
    assert_eq!(stored["state"], "interrupted", "{stored}");
    assert!(
        stored["reason"].as_str().unwrap_or("").contains("shutdown"),
        "{stored}"
    );

    // After a restart the job is still interrupted and the bed still needs clearing.
    let _daemon = Daemon::start(&config, &log);
    let s = wait_for(&config, &log, Duration::from_secs(30), "restarted", |s| {
        s["printers"].as_array().is_some_and(|p| p.len() == 1)
    });
    assert_eq!(state_of(&s, "spot.obj"), "interrupted");
    assert_eq!(printer(&s, "p")["bed_cleared"], false);
    assert!(root.join("spool/jobs").join(&id).join("spot.obj").is_file());
}

/// A daemon printing `spot.obj` with `on_shutdown = "finish"` and `finish_timeout_s`,
/// whose systemd notifications go to a datagram socket the test reads (as systemd's
/// `NOTIFY_SOCKET`).
struct Finishing {
    _tmp: tempfile::TempDir,
    root: PathBuf,
    config: PathBuf,
    log: PathBuf,
    rec: PathBuf,
    notify: std::os::unix::net::UnixDatagram,
    daemon: Daemon,
    job: String,
}

impl Finishing {
    /// Started, and printing past its heat-up.
    fn printing(finish_timeout_s: u32) -> Finishing {
        let tmp = tempfile::tempdir().unwrap();
        let root = tmp.path().to_path_buf();
        let hot = root.join("hot");
        std::fs::create_dir_all(&hot).unwrap();
        let (config, log, rec) = (
            root.join("crispen.toml"),
            root.join("daemon.log"),
            root.join("p.rec"),
        );
        std::fs::write(
            &config,
            format!(
                "[spool]\ndir = \"spool\"\n[control]\nsocket = \"c.sock\"\n\
                 [farm]\nsettle_s = 0.5\non_shutdown = \"finish\"\nfinish_timeout_s = {finish_timeout_s}\n\
                 [[printer]]\nname = \"p\"\nfirmware = \"marlin2\"\n\
                 [printer.simulate]\nspeed = 10\nrecord = \"{}\"\n\
                 [[folder]]\npath = \"hot\"\nheight_mm = 25\nprinters = [\"p\"]\n",
                rec.display()
            ),
        )
        .unwrap();
        let socket = root.join("notify.sock");
        let notify = std::os::unix::net::UnixDatagram::bind(&socket).unwrap();
        notify.set_nonblocking(true).unwrap();
        let mut launcher = Command::new(BIN);
        launcher.env("NOTIFY_SOCKET", &socket);
        let daemon = Daemon::start_by(launcher, &config, &log);
        drop_model(&hot, "spot.obj", &spot());
        let s = wait_for(&config, &log, Duration::from_secs(120), "printing", |s| {
            printer(s, "p")["state"] == "printing"
                && printer(s, "p")["progress"]["lines_acked"].as_u64() > Some(100)
        });
        let job = job_by_file(&s, "spot.obj").unwrap()["id"]
            .as_str()
            .unwrap()
            .to_string();
        Finishing {
            _tmp: tmp,
            root,
            config,
            log,
            rec,
            notify,
            daemon,
            job,
        }
    }

    fn signal(&self, signal: nix::sys::signal::Signal) {
        let pid = nix::unistd::Pid::from_raw(self.daemon.child.id() as i32);
        nix::sys::signal::kill(pid, signal).unwrap();
    }

    /// Waits for the daemon to exit (successfully), then checks the print ended with the
    /// safe stop (heaters off) and its job interrupted.
    fn exits_after_a_safe_stop(&mut self, limit: Duration) {
        let start = Instant::now();
        let exit = loop {
            if let Some(exit) = self.daemon.child.try_wait().unwrap() {
                break exit;
            }
            assert!(
                start.elapsed() < limit,
                "the daemon did not exit\nlog:\n{}",
                std::fs::read_to_string(&self.log).unwrap_or_default()
            );
            std::thread::sleep(Duration::from_millis(100));
        };
        assert!(exit.success(), "{exit:?}");
        let job = job_gcode(&self.root, &self.job, "spot.obj");
        assert_prefix_then_safe_stop(&recorded(&self.rec), &job);
        let stored: Value = serde_json::from_slice(
            &std::fs::read(
                self.root
                    .join("spool/jobs")
                    .join(&self.job)
                    .join("job.json"),
            )
            .unwrap(),
        )
        .unwrap();
        assert_eq!(stored["state"], "interrupted", "{stored}");
    }

    /// The time asked of systemd so far, in microseconds, in order.
    fn extensions(&self) -> Vec<u64> {
        let mut asked = Vec::new();
        let mut buf = [0u8; 4096];
        while let Ok(n) = self.notify.recv(&mut buf) {
            for line in String::from_utf8_lossy(&buf[..n]).lines() {
                if let Some(usec) = line.strip_prefix("EXTEND_TIMEOUT_USEC=") {
                    asked.push(usec.parse().unwrap());
                }
            }
        }
        asked
    }
}

/// With `on_shutdown = "finish"`, a SIGTERM lets the print run on while the daemon asks
/// systemd for more time, and a second SIGTERM stops it safely, heaters off (before, it
/// did nothing: systemd killed the daemon at its stop timeout with the heaters on).
#[test]
fn a_second_sigterm_stops_a_finishing_print_safely() {
    let mut farm = Finishing::printing(3600);
    farm.signal(nix::sys::signal::Signal::SIGTERM);
    let acked = |s: &Value| printer(s, "p")["progress"]["lines_acked"].as_u64();
    let before = acked(&status(&farm.config).unwrap());
    wait_for(
        &farm.config,
        &farm.log,
        Duration::from_secs(20),
        "the print going on after the first SIGTERM",
        |s| printer(s, "p")["state"] == "printing" && acked(s) > before.map(|n| n + 20),
    );
    assert!(farm.daemon.child.try_wait().unwrap().is_none());
    farm.signal(nix::sys::signal::Signal::SIGTERM);
    farm.exits_after_a_safe_stop(Duration::from_secs(60));
    let asked = farm.extensions();
    assert!(!asked.is_empty(), "no EXTEND_TIMEOUT_USEC");
    let log = std::fs::read_to_string(&farm.log).unwrap();
    assert!(
        log.contains("second SIGTERM: stopping the prints safely"),
        "{log}"
    );
}

/// A print still running when `finish_timeout_s` runs out is stopped safely; until then
/// the daemon renews its request for time, never asking beyond the bound and the safe
/// stop's grace (60 s).
#[test]
fn a_finishing_print_is_stopped_safely_at_the_bound() {
    let mut farm = Finishing::printing(5);
    farm.signal(nix::sys::signal::Signal::SIGTERM);
    let start = Instant::now();
    // Within the bound and the safe stop's grace, with room for a loaded machine (the
    // whole suite at once once took more than 40 s here).
    farm.exits_after_a_safe_stop(Duration::from_secs(5 + 60 + 30));
    let took = start.elapsed();
    assert!(
        took >= Duration::from_secs(4),
        "stopped after {took:?}, before the bound"
    );
    let asked = farm.extensions();
    assert!(asked.len() >= 2, "the request for time renewed: {asked:?}");
    assert!(
        asked.iter().all(|&usec| usec > 0 && usec <= 65_000_000),
        "{asked:?}"
    );
    let log = std::fs::read_to_string(&farm.log).unwrap();
    assert!(
        log.contains("finish_timeout_s ran out: stopping the prints safely"),
        "{log}"
    );
}

/// A `crispen sim` process of its own (not one the daemon starts), so the test can pull
/// its plug and put a new one in its place.
struct SimProcess {
    process: Killed,
}

impl SimProcess {
    /// A `marlin2` simulator at `time_scale` behind `link`, with `faults` (its flags).
    fn start(link: &Path, record: &Path, time_scale: &str, faults: &[&str]) -> SimProcess {
        let _ = std::fs::remove_file(link);
        let child = Command::new(BIN)
            .args([
                "sim",
                "--firmware",
                "marlin2",
                "--time-scale",
                time_scale,
                "--link",
            ])
            .arg(link)
            .arg("--record")
            .arg(record)
            .args(faults)
            .stdout(Stdio::null())
            .stderr(Stdio::null())
            .spawn()
            .unwrap();
        let start = Instant::now();
        while std::fs::read_link(link).is_err() {
            assert!(
                start.elapsed() < Duration::from_secs(10),
                "sim link never appeared"
            );
            std::thread::sleep(Duration::from_millis(20));
        }
        SimProcess {
            process: Killed(child),
        }
    }
}

/// A printer unplugged mid-print over a noisy link (corrupt bytes, garbage answers): the
/// job ends interrupted with the last acknowledged line, having executed an exact prefix
/// of its G-code; the supervisor reconnects when a printer is back on the port, holds it
/// for the bed clear, and a retried job then prints whole, exactly once.
#[test]
fn unplugged_printer_interrupts_the_job_and_reconnects() {
    let tmp = tempfile::tempdir().unwrap();
    let root = tmp.path();
    let hot = root.join("hot");
    std::fs::create_dir_all(&hot).unwrap();
    let link = root.join("ttyUM2");
    let (rec1, rec2) = (root.join("first.rec"), root.join("second.rec"));
    let first = SimProcess::start(
        &link,
        &rec1,
        "0.02",
        &[
            "--unplug-after",
            "600",
            "--corrupt",
            "0.01",
            "--garbage",
            "0.01",
            "--seed",
            "7",
        ],
    );
    let config = root.join("crispen.toml");
    let log = root.join("daemon.log");
    std::fs::write(
        &config,
        format!(
            "[spool]\ndir = \"spool\"\n[control]\nsocket = \"c.sock\"\n[farm]\nsettle_s = 0.5\n\
             [[printer]]\nname = \"p\"\nfirmware = \"marlin2\"\nport = \"{}\"\n\
             [[folder]]\npath = \"hot\"\nheight_mm = 25\nprinters = [\"p\"]\n",
            link.display()
        ),
    )
    .unwrap();
    let _daemon = Daemon::start(&config, &log);
    let model = Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/data/spot.obj");
    std::fs::copy(&model, hot.join("spot.obj.part")).unwrap();
    std::fs::rename(hot.join("spot.obj.part"), hot.join("spot.obj")).unwrap();

    let s = wait_for(
        &config,
        &log,
        Duration::from_secs(120),
        "interrupted",
        |s| state_of(s, "spot.obj") == "interrupted",
    );
    let job = job_by_file(&s, "spot.obj").unwrap();
    let id = job["id"].as_str().unwrap().to_string();
    let reason = job["reason"].as_str().unwrap_or("");
    assert!(
        reason.contains("disconnected") && reason.contains("last acknowledged line"),
        "{reason}"
    );
    assert_eq!(printer(&s, "p")["bed_cleared"], false);
    let gcode = job_gcode(root, &id, "spot.obj");
    let executed = recorded(&rec1);
    assert!(
        executed.len() > 100 && executed.len() < gcode.len(),
        "{} of {} lines",
        executed.len(),
        gcode.len()
    );
    if let Some(i) = (0..executed.len()).find(|&i| executed[i] != gcode[i]) {
        panic!(
            "executed command {i} is {:?}, the job's is {:?}",
            executed[i], gcode[i]
        );
    }
    drop(first);

    // Plug a printer back in: the supervisor finds it and holds it for the bed clear.
    // The retried print only has to run whole, exactly once: no need to pace it.
    let _second = SimProcess::start(&link, &rec2, "0", &[]);
    wait_for(&config, &log, Duration::from_secs(60), "reconnected", |s| {
        printer(s, "p")["state"] == "bed_not_cleared"
    });
    for args in [["retry", id.as_str()], ["clear", "p"]] {
        let (ok, out) = ctl(&config, &args);
        assert!(ok, "{out}");
    }
    wait_for(&config, &log, Duration::from_secs(240), "printed", |s| {
        state_of(s, "spot.obj") == "done"
    });
    assert!(
        recorded(&rec2) == gcode,
        "the retried print ran the job exactly once"
    );
}

/// An idle printer's temperatures are read between jobs and shown while current: the
/// daemon shows the simulator's ambient reading with its heaters off (status JSON and
/// the CLI's table); when the printer hangs they go once no report came for a while, and
/// come back with its answers; when the printer goes (its pty closes) they are gone at
/// once, not shown as if still true; when a printer is back on the port they are read
/// again.
#[test]
fn idle_temperatures_are_shown_only_while_the_printer_answers() {
    let tmp = tempfile::tempdir().unwrap();
    let root = tmp.path();
    std::fs::create_dir_all(root.join("hot")).unwrap();
    let link = root.join("ttyACM0");
    let first = SimProcess::start(&link, &root.join("first.rec"), "0.02", &[]);
    let config = root.join("crispen.toml");
    let log = root.join("daemon.log");
    std::fs::write(
        &config,
        format!(
            "[spool]\ndir = \"spool\"\n[control]\nsocket = \"c.sock\"\n\
             [[printer]]\nname = \"p\"\nfirmware = \"marlin2\"\nport = \"{}\"\n\
             [[folder]]\npath = \"hot\"\nheight_mm = 25\nprinters = [\"p\"]\n",
            link.display()
        ),
    )
    .unwrap();
    let _daemon = Daemon::start(&config, &log);
    let ambient = |s: &Value| {
        let p = printer(s, "p");
        let t = &p["temperatures"];
        p["state"] == "idle"
            && t["hotend_c"]
                .as_f64()
                .is_some_and(|c| (c - 21.0).abs() < 0.5)
            && t["bed_c"].as_f64().is_some_and(|c| (c - 21.0).abs() < 0.5)
            && t["hotend_target_c"] == 0.0
            && t["bed_target_c"] == 0.0
    };
    wait_for(
        &config,
        &log,
        Duration::from_secs(60),
        "idle at 21 °C",
        ambient,
    );
    let (ok, table) = ctl(&config, &["status"]);
    let row = table.lines().find(|l| l.starts_with("p ")).unwrap_or("");
    assert!(ok && row.contains("21/0C"), "{table}");

    // A printer that hangs (its firmware stops; the port stays open): the figures go
    // once no report came for a while, and come back when it answers again.
    let signal = |s: nix::sys::signal::Signal| {
        let pid = nix::unistd::Pid::from_raw(first.process.0.id() as i32);
        nix::sys::signal::kill(pid, s).unwrap();
    };
    signal(nix::sys::signal::Signal::SIGSTOP);
    let s = wait_for(
        &config,
        &log,
        Duration::from_secs(60),
        "stale figures dropped",
        |s| printer(s, "p")["temperatures"].is_null(),
    );
    assert_eq!(printer(&s, "p")["state"], "idle");
    signal(nix::sys::signal::Signal::SIGCONT);
    wait_for(
        &config,
        &log,
        Duration::from_secs(60),
        "answering again",
        ambient,
    );

    drop(first);
    let s = wait_for(
        &config,
        &log,
        Duration::from_secs(30),
        "the printer gone",
        |s| printer(s, "p")["state"] != "idle",
    );
    assert!(
        printer(&s, "p")["temperatures"].is_null(),
        "no figures while the printer is gone: {s:#}"
    );
    let (ok, table) = ctl(&config, &["status"]);
    let row = table.lines().find(|l| l.starts_with("p ")).unwrap_or("");
    assert!(ok && !row.contains("21/0C"), "{table}");

    let _second = SimProcess::start(&link, &root.join("second.rec"), "0.02", &[]);
    wait_for(
        &config,
        &log,
        Duration::from_secs(60),
        "read again",
        ambient,
    );
}

/// SIGHUP applies printer changes: an added printer starts and takes work, a removed
/// one leaves the status; the other printers carry on untouched.
#[test]
fn reload_adds_and_retires_printers() {
    let tmp = tempfile::tempdir().unwrap();
    let root = tmp.path();
    std::fs::create_dir_all(root.join("hot")).unwrap();
    let config = root.join("crispen.toml");
    let log = root.join("daemon.log");
    let write_config = |printers: &[&str], folder_printers: &str| {
        let mut text = String::from(
            "[spool]\ndir = \"spool\"\n[control]\nsocket = \"c.sock\"\n[farm]\nsettle_s = 0.5\n",
        );
        for name in printers {
            text.push_str(&format!(
                "[[printer]]\nname = \"{name}\"\nfirmware = \"marlin2\"\n\
                 [printer.simulate]\ntime_scale = 0.0\n"
            ));
        }
        text.push_str(&format!(
            "[[folder]]\npath = \"hot\"\nheight_mm = 20\nprinters = [{folder_printers}]\n"
        ));
        std::fs::write(&config, text).unwrap();
    };
    let names = |s: &Value| -> Vec<String> {
        s["printers"]
            .as_array()
            .unwrap()
            .iter()
            .map(|p| p["name"].as_str().unwrap().to_string())
            .collect()
    };
    write_config(&["a"], "\"a\"");
    let daemon = Daemon::start(&config, &log);
    let hup = || {
        nix::sys::signal::kill(
            nix::unistd::Pid::from_raw(daemon.child.id() as i32),
            nix::sys::signal::Signal::SIGHUP,
        )
        .unwrap()
    };
    wait_for(
        &config,
        &log,
        Duration::from_secs(20),
        "printer a idle",
        |s| printer(s, "a")["state"] == "idle",
    );

    // Add b, and give the folder to b alone: b starts and prints the next job.
    write_config(&["a", "b"], "\"b\"");
    hup();
    wait_for(
        &config,
        &log,
        Duration::from_secs(20),
        "printer b idle",
        |s| names(s) == ["a", "b"] && printer(s, "b")["state"] == "idle",
    );
    let gcode = common::farm::presliced_gcode("spot", 20, 1200);
    drop_model(&root.join("hot"), "spot.gcode", gcode.as_bytes());
    let s = wait_for(
        &config,
        &log,
        Duration::from_secs(120),
        "printed on b",
        |s| state_of(s, "spot.gcode") == "done",
    );
    assert_eq!(job_by_file(&s, "spot.gcode").unwrap()["printer"], "b");
    assert_eq!(printer(&s, "a")["state"], "idle", "a was not disturbed");

    // Remove a: it leaves the status, b keeps its bed gate.
    write_config(&["b"], "\"b\"");
    hup();
    let s = wait_for(&config, &log, Duration::from_secs(20), "a retired", |s| {
        names(s) == ["b"]
    });
    assert_eq!(
        printer(&s, "b")["state"],
        "bed_not_cleared",
        "log:\n{}",
        std::fs::read_to_string(&log).unwrap_or_default()
    );
}

/// The small farm's printer starts with a finished print on its bed, so ready jobs wait
/// rather than print.
fn bed_not_cleared_at_start(root: &Path) {
    std::fs::create_dir_all(root.join("spool")).unwrap();
    std::fs::write(
        root.join("spool/printers.json"),
        r#"{"p": {"bed_not_cleared": true, "last_job": null}}"#,
    )
    .unwrap();
}

/// A config of one simulated printer `p` and the hot folder `hot`, with `extra` added to
/// the folder's table.
fn small_farm(root: &Path, folder_extra: &str) -> (PathBuf, PathBuf) {
    std::fs::create_dir_all(root.join("hot")).unwrap();
    let config = root.join("crispen.toml");
    std::fs::write(
        &config,
        format!(
            "[spool]\ndir = \"spool\"\n[control]\nsocket = \"c.sock\"\n[farm]\nsettle_s = 0.3\n\
             [[printer]]\nname = \"p\"\nfirmware = \"marlin2\"\n[printer.simulate]\ntime_scale = 0.0\n\
             [[folder]]\npath = \"hot\"\nheight_mm = 25\nprinters = [\"p\"]\n{folder_extra}\n"
        ),
    )
    .unwrap();
    (config, root.join("daemon.log"))
}

fn spot() -> Vec<u8> {
    std::fs::read(Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/data/spot.obj")).unwrap()
}

fn wait_exit(daemon: &mut Daemon, limit: Duration, log: &Path) -> std::process::ExitStatus {
    let started = Instant::now();
    loop {
        if let Some(code) = daemon.child.try_wait().unwrap() {
            return code;
        }
        assert!(
            started.elapsed() < limit,
            "the daemon did not exit within {limit:?}\nlog:\n{}",
            std::fs::read_to_string(log).unwrap_or_default()
        );
        std::thread::sleep(Duration::from_millis(100));
    }
}

/// `crispen run --exit-when-idle` exits once the only job has failed at preparation. It
/// never did: a job's change is published before it is counted, the daemon looked on the
/// publication, saw the job failed but no job counted as finished, and no later change
/// came to look again. Several daemons in a row, each with one job a pre-sliced G-code
/// that extrudes nothing (refused at preparation without a slicer).
#[test]
fn exit_when_idle_exits_when_the_only_job_failed_at_preparation() {
    for round in 0..4 {
        let dir = tempfile::tempdir().unwrap();
        let root = dir.path();
        let (config, log) = small_farm(root, "");
        drop_model(
            &root.join("hot"),
            "nothing.gcode",
            b"G28\nG1 X10 Y10 F600\n",
        );
        let log_file = std::fs::File::create(&log).unwrap();
        let child = Command::new(BIN)
            .args(["run", "--exit-when-idle", "--config"])
            .arg(&config)
            .env("RUST_LOG", "info")
            .stdout(Stdio::null())
            .stderr(log_file)
            .spawn()
            .unwrap();
        let mut daemon = Daemon { child };
        let code = wait_exit(&mut daemon, Duration::from_secs(30), &log);
        assert!(code.success(), "round {round}: {code:?}");
        let text = std::fs::read_to_string(&log).unwrap();
        assert!(
            text.contains("state=\"failed\"") || text.contains("state=failed"),
            "round {round}: the job did not fail:\n{text}"
        );
        assert!(text.contains("extrudes nothing"), "round {round}:\n{text}");
    }
}

/// SIGTERM while a job is being prepared (here by a slicer that never ends) stops the
/// preparation at once: the daemon exits within seconds rather than waiting out the
/// preparation, the slicer is gone, and the job is back in the queue for the next start.
#[test]
fn sigterm_during_preparation_stops_it_within_seconds() {
    let dir = tempfile::tempdir().unwrap();
    let root = dir.path();
    let mut farm = start_stuck_slicing(root);
    let pid = nix::unistd::Pid::from_raw(farm.daemon.child.id() as i32);
    nix::sys::signal::kill(pid, nix::sys::signal::Signal::SIGTERM).unwrap();
    let code = wait_exit(&mut farm.daemon, Duration::from_secs(15), &farm.log);
    assert!(code.success(), "{code:?}");
    assert_gone_soon(&farm.slicer_proc, &farm.log, "SIGTERM");
    let stored: Value = serde_json::from_slice(
        &std::fs::read(root.join("spool/jobs").join(&farm.job).join("job.json")).unwrap(),
    )
    .unwrap();
    assert_eq!(stored["state"], "queued", "{stored}");
}

/// A closed surface (a torus) with `n * n` vertices as OBJ text: big enough that loading
/// and enhancing it take well over a second.
fn torus_obj(n: usize) -> Vec<u8> {
    use std::fmt::Write as _;
    let mut text = String::new();
    for i in 0..n {
        for j in 0..n {
            let (u, v) = (
                i as f64 / n as f64 * std::f64::consts::TAU,
                j as f64 / n as f64 * std::f64::consts::TAU,
            );
            let r = 10.0 + 4.0 * v.cos();
            writeln!(
                text,
                "v {:.5} {:.5} {:.5}",
                r * u.cos(),
                r * u.sin(),
                4.0 * v.sin()
            )
            .unwrap();
        }
    }
    let at = |i: usize, j: usize| (i % n) * n + (j % n) + 1;
    for i in 0..n {
        for j in 0..n {
            let (a, b, c, d) = (at(i, j), at(i + 1, j), at(i + 1, j + 1), at(i, j + 1));
            writeln!(text, "f {a} {b} {c}\nf {a} {c} {d}").unwrap();
        }
    }
    text.into_bytes()
}

/// A folder's time limit covers the whole preparation, enhancement included (it once
/// covered the slicer only, so a big or hostile model could hold a slot for as long as
/// its enhancement took): the job fails naming the limit, and the next job goes on.
#[test]
fn preparation_time_limit_fails_the_job_and_the_queue_goes_on() {
    let dir = tempfile::tempdir().unwrap();
    let root = dir.path();
    let (config, log) = small_farm(root, "timeout_s = 0.5");
    let mut text = std::fs::read_to_string(&config).unwrap();
    text += "[[folder]]\npath = \"hot2\"\nheight_mm = 25\nprinters = [\"p\"]\n";
    std::fs::write(&config, text).unwrap();
    std::fs::create_dir_all(root.join("hot2")).unwrap();
    let _daemon = Daemon::start(&config, &log);
    let hot = root.join("hot");
    drop_model(&hot, "torus.obj", &torus_obj(400));
    let s = wait_for(
        &config,
        &log,
        Duration::from_secs(120),
        "the big job to fail",
        |s| state_of(s, "torus.obj") == "failed",
    );
    let reason = job_by_file(&s, "torus.obj").unwrap()["reason"]
        .as_str()
        .unwrap()
        .to_string();
    assert!(
        reason.contains("longer than 500ms") && reason.contains("timeout_s"),
        "{reason}"
    );
    // The slot is free again: a job from a folder with the default limit is done.
    // Pre-sliced: it goes through preparation (the slot) without a slicer's CPU.
    let small = common::farm::presliced_gcode("small", 20, 1200);
    drop_model(&root.join("hot2"), "small.gcode", small.as_bytes());
    wait_for(
        &config,
        &log,
        Duration::from_secs(120),
        "the next job to be done",
        |s| state_of(s, "small.gcode") == "done",
    );
}

/// Two daemons on one spool would print the same jobs: the second refuses to start,
/// naming the spool, even with a control socket of its own.
#[test]
fn a_second_daemon_on_the_same_spool_refuses_to_start() {
    let dir = tempfile::tempdir().unwrap();
    let root = dir.path();
    let (config, log) = small_farm(root, "");
    let _first = Daemon::start(&config, &log);
    wait_for(
        &config,
        &log,
        Duration::from_secs(20),
        "the first daemon",
        |_| true,
    );
    let other = root.join("other.toml");
    std::fs::write(
        &other,
        std::fs::read_to_string(&config)
            .unwrap()
            .replace("c.sock", "other.sock"),
    )
    .unwrap();
    let out = Command::new(BIN)
        .args(["run", "--config"])
        .arg(&other)
        .output()
        .unwrap();
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert!(!out.status.success(), "{stderr}");
    assert!(
        stderr.contains("in use by another crispen daemon") && stderr.contains("spool"),
        "{stderr}"
    );
    assert!(status(&config).is_some(), "the first daemon still answers");
}

/// A job directory removed by hand while its job waited does not stop the queue: that
/// job fails, and the printer takes the next one. (A printer once kept trying the
/// missing job and printed nothing more.)
#[test]
fn a_removed_job_directory_does_not_stop_the_queue() {
    let dir = tempfile::tempdir().unwrap();
    let root = dir.path();
    let (config, log) = small_farm(root, "");
    bed_not_cleared_at_start(root);
    let _daemon = Daemon::start(&config, &log);
    let hot = root.join("hot");
    // Pre-sliced files: the queue is the point here, not the slicer.
    let gcode = |marker: &str| common::farm::presliced_gcode(marker, 20, 1200);
    drop_model(&hot, "first.gcode", gcode("first").as_bytes());
    let s = wait_for(
        &config,
        &log,
        Duration::from_secs(120),
        "the first job ready",
        |s| state_of(s, "first.gcode") == "ready",
    );
    drop_model(&hot, "second.gcode", gcode("second").as_bytes());
    wait_for(
        &config,
        &log,
        Duration::from_secs(120),
        "the second job ready",
        |s| state_of(s, "second.gcode") == "ready",
    );
    let first = job_by_file(&s, "first.gcode").unwrap()["id"]
        .as_str()
        .unwrap()
        .to_string();
    std::fs::remove_dir_all(root.join("spool/jobs").join(&first)).unwrap();
    let (ok, out) = ctl(&config, &["clear", "p"]);
    assert!(ok, "{out}");
    let s = wait_for(
        &config,
        &log,
        Duration::from_secs(120),
        "the second job done",
        |s| state_of(s, "second.gcode") == "done",
    );
    assert_eq!(state_of(&s, "first.gcode"), "failed");
    let reason = job_by_file(&s, "first.gcode").unwrap()["reason"]
        .as_str()
        .unwrap()
        .to_string();
    assert!(reason.contains("removed"), "{reason}");
    // A finished print shows all its lines, not the last throttled figure.
    let progress = &printer(&s, "p")["progress"];
    assert_eq!(
        progress["lines_acked"], progress["lines_total"],
        "{progress}"
    );
}

/// The control socket speaks HTTP with bounds: an endless request head gets 431 and the
/// connection is closed (a request line was once read into memory without end), an idle
/// connection is closed, and the daemon goes on answering.
#[test]
fn control_socket_limits_requests_and_idle_connections() {
    use std::io::Read;
    use std::os::unix::net::UnixStream;
    let dir = tempfile::tempdir().unwrap();
    let root = dir.path();
    let (config, log) = small_farm(root, "");
    let _daemon = Daemon::start(&config, &log);
    wait_for(&config, &log, Duration::from_secs(20), "the daemon", |_| {
        true
    });
    let socket = root.join("c.sock");

    let mut big = UnixStream::connect(&socket).unwrap();
    big.set_read_timeout(Some(Duration::from_secs(30))).unwrap();
    let _ = big.write_all(b"GET /api/v1/status HTTP/1.1\r\nX-Long: ");
    let chunk = vec![b'x'; 64 * 1024];
    for _ in 0..4 {
        if big.write_all(&chunk).is_err() {
            break;
        }
    }
    let mut answer = Vec::new();
    let _ = big.read_to_end(&mut answer);
    let answer = String::from_utf8_lossy(&answer);
    assert!(answer.starts_with("HTTP/1.1 431"), "answer: {answer:?}");

    let mut idle = UnixStream::connect(&socket).unwrap();
    idle.set_read_timeout(Some(Duration::from_secs(60)))
        .unwrap();
    let mut buf = [0u8; 16];
    let n = idle
        .read(&mut buf)
        .expect("closed by the daemon, not by our timeout");
    assert_eq!(n, 0, "the idle connection is closed");
    assert!(status(&config).is_some());
}

/// Whatever is at the control socket's path and is not a socket is never removed: the
/// daemon refuses to start and the file is intact.
#[test]
fn a_file_at_the_socket_path_is_never_removed() {
    let dir = tempfile::tempdir().unwrap();
    let root = dir.path();
    let (config, _log) = small_farm(root, "");
    std::fs::write(root.join("c.sock"), b"precious").unwrap();
    let out = Command::new(BIN)
        .args(["run", "--config"])
        .arg(&config)
        .output()
        .unwrap();
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert!(!out.status.success(), "{stderr}");
    assert!(stderr.contains("not a socket"), "{stderr}");
    assert_eq!(std::fs::read(root.join("c.sock")).unwrap(), b"precious");
}

/// `run --check` refuses what the daemon would trip over later: a hot folder inside the
/// spool (its jobs would be picked up as models), with section and key named.
#[test]
fn check_refuses_a_hot_folder_inside_the_spool() {
    let dir = tempfile::tempdir().unwrap();
    let root = dir.path();
    let (config, _log) = small_farm(root, "");
    let text = std::fs::read_to_string(&config).unwrap();
    std::fs::write(
        &config,
        text.replace("path = \"hot\"", "path = \"spool/hot\""),
    )
    .unwrap();
    let out = Command::new(BIN)
        .args(["run", "--check", "--config"])
        .arg(&config)
        .output()
        .unwrap();
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert!(!out.status.success(), "{stderr}");
    assert!(
        stderr.contains("[[folder]] #1")
            && stderr.contains("key `path`")
            && stderr.contains("must not contain each other"),
        "{stderr}"
    );
}

/// A config using every section with a secret: `[farm] host`, `[store]` with a password
/// file and `[http]` with a key file, both mode 0600. `run --check` accepts it quietly.
fn farm_config(root: &Path) -> PathBuf {
    use std::os::unix::fs::PermissionsExt;
    std::fs::create_dir_all(root.join("hot")).unwrap();
    for (name, text) in [("pw", "a-password\n"), ("key", "k-0123456789abcdef-k\n")] {
        std::fs::write(root.join(name), text).unwrap();
        std::fs::set_permissions(root.join(name), std::fs::Permissions::from_mode(0o600)).unwrap();
    }
    let config = root.join("crispen.toml");
    std::fs::write(
        &config,
        "[spool]\ndir = \"spool\"\n[control]\nsocket = \"c.sock\"\n[farm]\nhost = \"rack-1\"\n\
         [store]\npostgres = \"host=/run/postgresql dbname=crispen\"\npassword_file = \"pw\"\nlease_s = 15\n\
         [http]\nlisten = \"127.0.0.1:8080\"\napi_key_file = \"key\"\n\
         [[printer]]\nname = \"p\"\nfirmware = \"marlin2\"\n[printer.simulate]\nspeed = \"instant\"\n\
         [[folder]]\npath = \"hot\"\nheight_mm = 25\nprinters = [\"p\"]\n",
    )
    .unwrap();
    config
}

fn run_check(config: &Path) -> (bool, String) {
    let out = Command::new(BIN)
        .args(["run", "--check", "--config"])
        .arg(config)
        .output()
        .unwrap();
    (
        out.status.success(),
        String::from_utf8_lossy(&out.stderr).into_owned(),
    )
}

/// Issue 20: `run --check` refuses what the service cannot use or what is no name, each
/// error naming its section and key: a privileged port (the unit grants no capability to
/// bind one), host names `..` and `-`, an empty connection string, a password file that
/// is missing, a directory or a device (`/dev/zero` was read without end at start), an
/// API key file that is a device (whose hint once said to write the key *to*
/// /dev/urandom); `lease_s = 1e308` is shown as 1e308, not in 309 digits.
#[test]
fn check_refuses_what_the_service_cannot_use() {
    let dir = tempfile::tempdir().unwrap();
    let root = dir.path();
    let config = farm_config(root);
    let good = std::fs::read_to_string(&config).unwrap();
    let (ok, stderr) = run_check(&config);
    assert!(
        ok && stderr.is_empty(),
        "the base config passes quietly: {stderr}"
    );
    std::fs::create_dir(root.join("a-directory")).unwrap();
    let cases: &[(&str, &str, &[&str])] = &[
        (
            "\"127.0.0.1:8080\"",
            "\"0.0.0.0:22\"",
            &["[http]: key `listen`", "port 22 is privileged"],
        ),
        ("\"rack-1\"", "\"..\"", &["[farm]: key `host`", "\"..\""]),
        (
            "\"rack-1\"",
            "\"-\"",
            &["[farm]: key `host`", "not starting with"],
        ),
        ("\"rack-1\"", "\".hidden\"", &["[farm]: key `host`"]),
        (
            "\"host=/run/postgresql dbname=crispen\"",
            "\"\"",
            &["[store]: key `postgres`", "names no server"],
        ),
        (
            "lease_s = 15",
            "lease_s = 1e308",
            &["[store]: key `lease_s`", "got 1e308"],
        ),
        (
            "\"pw\"",
            "\"no-such-file\"",
            &["[store]: key `password_file`", "no-such-file"],
        ),
        (
            "\"pw\"",
            "\"a-directory\"",
            &["[store]: key `password_file`", "not a regular file"],
        ),
        (
            "\"pw\"",
            "\"/dev/zero\"",
            &[
                "[store]: key `password_file`",
                "/dev/zero is not a regular file",
            ],
        ),
        (
            "\"key\"",
            "\"/dev/urandom\"",
            &[
                "[http]: key `api_key_file`",
                "/dev/urandom is not a regular file",
            ],
        ),
        (
            "\"key\"",
            "\"no-key\"",
            &[
                "[http]: key `api_key_file`",
                "(umask 077; head -c 24 /dev/urandom | base64 > ",
            ],
        ),
    ];
    for (from, to, want) in cases {
        std::fs::write(&config, good.replacen(from, to, 1)).unwrap();
        let (ok, stderr) = run_check(&config);
        assert!(!ok, "{to} passed --check");
        for part in *want {
            assert!(stderr.contains(part), "{to}: {part:?} not in: {stderr}");
        }
        assert!(
            !stderr.contains("> /dev/urandom") && stderr.len() < 600,
            "{to}: {stderr}"
        );
    }
}

/// Issue 20: key and password files others can read are accepted, with a warning from
/// `run --check` naming the section, key and file.
#[test]
fn check_warns_about_secrets_others_can_read() {
    use std::os::unix::fs::PermissionsExt;
    let dir = tempfile::tempdir().unwrap();
    let root = dir.path();
    let config = farm_config(root);
    std::fs::set_permissions(root.join("key"), std::fs::Permissions::from_mode(0o644)).unwrap();
    std::fs::set_permissions(root.join("pw"), std::fs::Permissions::from_mode(0o640)).unwrap();
    let (ok, stderr) = run_check(&config);
    assert!(ok, "{stderr}");
    let key = root.join("key");
    let pw = root.join("pw");
    for want in [
        format!(
            "warning: [http] key `api_key_file`: {} is readable by every user (mode 0644)",
            key.display()
        ),
        format!(
            "warning: [store] key `password_file`: {} is readable by its group (mode 0640)",
            pw.display()
        ),
    ] {
        assert!(stderr.contains(&want), "{want:?} not in: {stderr}");
    }
}

/// `crispen run --check … | head -1` with the reader gone: the check ends as Unix tools do
/// (SIGPIPE), without a panic on stderr.
#[test]
fn a_check_whose_reader_is_gone_ends_quietly() {
    use std::os::unix::process::ExitStatusExt;
    let dir = tempfile::tempdir().unwrap();
    let (config, _log) = small_farm(dir.path(), "");
    let (reader, writer) = nix::unistd::pipe().unwrap();
    drop(reader);
    let output = Command::new(BIN)
        .args(["run", "--check", "--config"])
        .arg(&config)
        .stdout(std::process::Stdio::from(writer))
        .stderr(std::process::Stdio::piped())
        .output()
        .unwrap();
    let stderr = String::from_utf8_lossy(&output.stderr);
    assert!(!stderr.contains("panicked"), "{stderr}");
    assert_eq!(
        output.status.signal(),
        Some(13),
        "{:?}: {stderr}",
        output.status
    );
}

/// A sidecar that arrives shortly after its model still applies (it was once left in
/// the folder, silently ignored), and one that arrives after its job started is reported
/// in the log and kept aside in the job directory, never silently dropped.
#[test]
fn a_sidecar_arriving_after_its_model_is_honoured_or_reported() {
    let dir = tempfile::tempdir().unwrap();
    let root = dir.path();
    let (config, log) = small_farm(root, "");
    let text = std::fs::read_to_string(&config).unwrap();
    std::fs::write(&config, text.replace("settle_s = 0.3", "settle_s = 2")).unwrap();
    let _daemon = Daemon::start(&config, &log);
    let hot = root.join("hot");
    drop_model(&hot, "late.obj", &spot());
    // The sidecar comes once the model has become a job.
    let s = wait_for(&config, &log, Duration::from_secs(30), "picked up", |s| {
        job_by_file(s, "late.obj").is_some()
    });
    assert_eq!(
        state_of(&s, "late.obj"),
        "queued",
        "waiting for a late sidecar"
    );
    assert!(!hot.join("late.obj").exists());
    drop_model(&hot, "late.obj.toml", b"enhance = false\n");
    let s = wait_for(&config, &log, Duration::from_secs(120), "done", |s| {
        state_of(s, "late.obj") == "done"
    });
    let id = job_by_file(&s, "late.obj").unwrap()["id"]
        .as_str()
        .unwrap()
        .to_string();
    let job_dir = root.join("spool/jobs").join(&id);
    let stored: Value =
        serde_json::from_slice(&std::fs::read(job_dir.join("job.json")).unwrap()).unwrap();
    assert_eq!(
        stored["slice_report"]["enhancement"]["mode"], "unmodified",
        "the sidecar applied"
    );
    assert!(!hot.join("late.obj.toml").exists());
    // The mesh that was sliced is kept with the job.
    assert!(job_dir.join("late.obj.enhanced.stl").is_file());

    drop_model(&hot, "late.obj.toml", b"copies = 2\n");
    // The file is kept aside first, then the log line is written: wait for both.
    let reported = || {
        std::fs::read_to_string(&log)
            .unwrap()
            .contains("NOT applied")
    };
    let started = Instant::now();
    while !(job_dir.join("late.obj.toml.late").is_file() && reported()) {
        assert!(
            started.elapsed() < Duration::from_secs(30),
            "the late sidecar is kept aside ({}) and reported in the log ({})",
            job_dir.join("late.obj.toml.late").is_file(),
            reported()
        );
        std::thread::sleep(Duration::from_millis(100));
    }
    assert!(!hot.join("late.obj.toml").exists());
}

/// `crispen run --config crispen.toml` (a file name without a directory) anchors the
/// config's paths at the file's directory, as any other config path does: a model dropped
/// in the hot folder is found by its watch event (the rescan is set to a day, so nothing
/// else can find it), and `crispen status --config crispen.toml` from the same directory
/// reaches the daemon. The paths were once taken relative to "", and the folder's watch
/// events never matched it.
#[test]
fn a_config_named_without_a_directory_anchors_its_paths() {
    let dir = tempfile::tempdir().unwrap();
    let root = dir.path();
    let (config, log) = small_farm(root, "");
    let text = std::fs::read_to_string(&config)
        .unwrap()
        .replace("settle_s = 0.3", "settle_s = 0.3\nrescan_s = 86400");
    std::fs::write(&config, text).unwrap();
    let child = Command::new(BIN)
        .current_dir(root)
        .args(["run", "--config", "crispen.toml"])
        .env("RUST_LOG", "info")
        .stdout(Stdio::null())
        .stderr(std::fs::File::create(&log).unwrap())
        .spawn()
        .unwrap();
    let _daemon = Daemon { child };
    wait_for(&config, &log, Duration::from_secs(30), "the daemon", |s| {
        printer(s, "p")["state"] == "idle"
    });
    let gcode = common::farm::presliced_gcode("spot", 20, 1200);
    drop_model(&root.join("hot"), "spot.gcode", gcode.as_bytes());
    wait_for(
        &config,
        &log,
        Duration::from_secs(60),
        "the dropped model picked up by its watch event",
        |s| job_by_file(s, "spot.gcode").is_some(),
    );
    let out = Command::new(BIN)
        .current_dir(root)
        .args(["status", "--config", "crispen.toml"])
        .output()
        .unwrap();
    let text = String::from_utf8_lossy(&out.stdout);
    assert!(
        out.status.success() && text.contains("spot.gcode"),
        "{text}"
    );
}

/// One SIGHUP changing a key of each reload policy (see `crispen::daemon::reload`): a
/// folder added applies at once (a file dropped into it is picked up), a printer's
/// firmware applies by restarting that printer (the status shows the new firmware), and
/// a new control socket needs a daemon restart (the daemon goes on answering on the old
/// one and says so in its log). `history.keep_days` and `printer.pause_heaters_off_s`,
/// once dropped by a reload without a word, are reported too.
#[test]
fn reload_applies_each_key_as_its_policy_declares() {
    let tmp = tempfile::tempdir().unwrap();
    let root = tmp.path();
    let (config, log) = small_farm(root, "");
    std::fs::create_dir_all(root.join("hot2")).unwrap();
    // The control client reads the socket from its config: a copy keeps the old one.
    let old_config = root.join("old.toml");
    std::fs::copy(&config, &old_config).unwrap();
    let mut daemon = Daemon::start(&config, &log);
    wait_for(&config, &log, Duration::from_secs(30), "p idle", |s| {
        printer(s, "p")["state"] == "idle"
    });
    let text = std::fs::read_to_string(&config).unwrap();
    let changed = text
        .replace("socket = \"c.sock\"", "socket = \"d.sock\"")
        .replace(
            "firmware = \"marlin2\"",
            "firmware = \"ultimaker2\"\nbaud = 250000\npause_heaters_off_s = 60",
        )
        + "[[folder]]\npath = \"hot2\"\nheight_mm = 25\nprinters = [\"p\"]\n\
           [history]\nkeep_days = 30\n";
    std::fs::write(&config, changed).unwrap();
    nix::sys::signal::kill(
        nix::unistd::Pid::from_raw(daemon.child.id() as i32),
        nix::sys::signal::Signal::SIGHUP,
    )
    .unwrap();
    // Printer restart: the printer comes back with its new firmware.
    wait_for(
        &old_config,
        &log,
        Duration::from_secs(60),
        "p restarted as an ultimaker2",
        |s| {
            // Missing from the status while its supervisor restarts.
            s["printers"]
                .as_array()
                .into_iter()
                .flatten()
                .any(|p| p["name"] == "p" && p["firmware"] == "ultimaker2" && p["state"] == "idle")
        },
    );
    // Live: the new folder is watched.
    let gcode = common::farm::presliced_gcode("late", 20, 1200);
    drop_model(&root.join("hot2"), "late.gcode", gcode.as_bytes());
    wait_for(
        &old_config,
        &log,
        Duration::from_secs(60),
        "the new folder's file picked up",
        |s| job_by_file(s, "late.gcode").is_some(),
    );
    // Daemon restart: still on the old socket, never on the new one.
    assert!(root.join("c.sock").exists());
    assert!(
        !root.join("d.sock").exists(),
        "the new socket waits for a restart"
    );
    let text = std::fs::read_to_string(&log).unwrap();
    for (key, says) in [
        ("control.socket", "needs a daemon restart"),
        (
            "printer.firmware",
            "applies when the printer is not printing",
        ),
        ("folder", "applied"),
        ("history.keep_days", "needs a daemon restart"),
        (
            "printer.pause_heaters_off_s",
            "applies when the printer is not printing",
        ),
    ] {
        assert!(
            text.lines()
                .any(|l| l.contains(&format!("SIGHUP: {key} changed: {says}"))),
            "{key}: {says}\nlog:\n{text}"
        );
    }
    daemon.kill9();
}

/// A spool on a filesystem of its own: a 64 MB tmpfs mounted in a private mount
/// namespace (`unshare -m`), held open by a `sleep` so that it outlives a daemon restart.
/// The daemon runs inside it (`nsenter`); the test reaches the spool through
/// `/proc/<holder>/root`.
struct SmallDisk {
    holder: Child,
}

impl SmallDisk {
    fn mount(at: &Path) -> SmallDisk {
        std::fs::create_dir_all(at).unwrap();
        let mut holder = Command::new("unshare")
            .args(["-m", "--propagation", "private", "sh", "-c"])
            .arg("mount -t tmpfs -o size=64m crispen-test \"$0\" && echo mounted && exec sleep 100000")
            .arg(at)
            .stdout(Stdio::piped())
            .spawn()
            .expect("unshare (util-linux) runs");
        let mut line = String::new();
        std::io::BufRead::read_line(
            &mut std::io::BufReader::new(holder.stdout.take().unwrap()),
            &mut line,
        )
        .unwrap();
        assert_eq!(
            line.trim(),
            "mounted",
            "cannot mount a tmpfs in a private mount namespace (the test needs root on Linux)"
        );
        SmallDisk { holder }
    }

    /// `path` as the namespace sees it.
    fn inside(&self, path: &Path) -> PathBuf {
        Path::new(&format!("/proc/{}/root", self.holder.id())).join(path.strip_prefix("/").unwrap())
    }

    fn start_daemon(&self, config: &Path, log: &Path) -> Daemon {
        let mut nsenter = Command::new("nsenter");
        nsenter
            .arg(format!("--mount=/proc/{}/ns/mnt", self.holder.id()))
            .arg("--")
            .arg(BIN);
        Daemon::start_by(nsenter, config, log)
    }

    /// Fills the filesystem to the last byte; returns the filler to remove later.
    fn fill(&self, dir: &Path) -> PathBuf {
        let filler = self.inside(&dir.join("filler"));
        let mut file = std::fs::File::create(&filler).unwrap();
        let block = vec![0xa5u8; 64 * 1024];
        loop {
            match file.write(&block) {
                Ok(0) => break,
                Ok(_) => {}
                Err(e) if e.raw_os_error() == Some(nix::libc::ENOSPC) => break,
                Err(e) => panic!("filling the disk: {e}"),
            }
        }
        // The last bytes one at a time, so not even a small file fits.
        while file.write(&[0]).is_ok_and(|n| n == 1) {}
        filler
    }
}

impl Drop for SmallDisk {
    fn drop(&mut self) {
        let _ = self.holder.kill();
        let _ = self.holder.wait();
    }
}

/// A full disk, for real. While the spool's filesystem is full: a model whose pick-up
/// cannot be copied whole stays in the hot folder, with no half job in the spool, and is
/// tried again after 1, 2, 4 ... s under one job number (it was tried every 0.4 s, each
/// time with a new number); a print that ends is shown done at once though its state
/// cannot be written; `crispen clear` is refused, saying so without a server path, and
/// stays undone (it answered with the spool's path and then took effect once space came
/// back). Once space returns, the done state and the closed bed gate reach the disk, the
/// waiting model is picked up as the next job, and after a `kill -9` and a restart the
/// job is still done (never interrupted, so never offered for a reprint) and its bed
/// still waits to be cleared, until it is cleared.
#[test]
fn a_full_disk_loses_nothing_and_reprints_nothing() {
    let tmp = tempfile::tempdir().unwrap();
    let root = tmp.path();
    let hot = root.join("hot");
    std::fs::create_dir_all(&hot).unwrap();
    let spool = root.join("spool");
    let disk = SmallDisk::mount(&spool);
    let config = root.join("crispen.toml");
    let log = root.join("daemon.log");
    let rec = root.join("p.rec");
    std::fs::write(
        &config,
        format!(
            "[spool]\ndir = \"spool\"\n[control]\nsocket = \"c.sock\"\n\
             [farm]\nsettle_s = 0.3\nrescan_s = 1\n\
             [[printer]]\nname = \"p\"\nfirmware = \"marlin2\"\n\
             [printer.simulate]\ntime_scale = 0.01\nrecord = \"{}\"\n\
             [[folder]]\npath = \"hot\"\nheight_mm = 25\nprinters = [\"p\"]\n",
            rec.display()
        ),
    )
    .unwrap();
    let mut daemon = disk.start_daemon(&config, &log);
    drop_model(&hot, "spot.obj", &spot());
    let s = wait_for(&config, &log, Duration::from_secs(240), "printing", |s| {
        printer(s, "p")["state"] == "printing"
    });
    let id = job_by_file(&s, "spot.obj").unwrap()["id"]
        .as_str()
        .unwrap()
        .to_string();
    let (ok, out) = ctl(&config, &["pause", "p"]);
    assert!(ok, "{out}");
    wait_for(&config, &log, Duration::from_secs(120), "paused", |s| {
        printer(s, "p")["state"] == "paused"
    });
    let filler = disk.fill(&spool);

    // A pick-up that cannot be copied whole: the file stays, no half job.
    let big: Vec<u8> = (0..2_000_000u32).map(|i| (i % 251) as u8).collect();
    drop_model(&hot, "big.stl", &big);
    // Tried again after 1, 2, 4 s: three failures, each logged with its wait.
    let waits = || -> Vec<u64> {
        std::fs::read_to_string(&log)
            .unwrap()
            .lines()
            .filter(|l| l.contains("cannot pick up") && l.contains("big.stl"))
            .map(|l| {
                let at = l.find("retry_in_s=").expect("the wait is logged") + "retry_in_s=".len();
                l[at..].split_whitespace().next().unwrap().parse().unwrap()
            })
            .collect()
    };
    let started = Instant::now();
    while waits().len() < 3 {
        assert!(
            started.elapsed() < Duration::from_secs(120),
            "the failed pick-up is logged three times: {:?}",
            waits()
        );
        std::thread::sleep(Duration::from_millis(200));
    }
    assert_eq!(waits()[..3], [1, 2, 4], "a wait that doubles");
    assert_eq!(std::fs::read(hot.join("big.stl")).unwrap(), big);
    let jobs_dir = disk.inside(&spool.join("jobs"));
    let left: Vec<String> = std::fs::read_dir(&jobs_dir)
        .unwrap()
        .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
        .collect();
    assert_eq!(left, vec![id.clone()], "no half job in the spool");
    let status_now = status(&config).unwrap();
    assert!(job_by_file(&status_now, "big.stl").is_none());

    // The print ends while nothing can be written: done at once, in memory.
    let (ok, out) = ctl(&config, &["resume", "p"]);
    assert!(ok, "{out}");
    wait_for(&config, &log, Duration::from_secs(600), "done", |s| {
        state_of(s, "spot.obj") == "done"
    });
    let job_json = disk.inside(&spool.join("jobs").join(&id).join("job.json"));
    let on_disk =
        |path: &Path| -> Value { serde_json::from_slice(&std::fs::read(path).unwrap()).unwrap() };
    assert_eq!(
        on_disk(&job_json)["state"],
        "printing",
        "the disk is full: the outcome could not be written yet"
    );
    let (ok, out) = ctl(&config, &["retry", &id]);
    assert!(!ok, "a done job is not offered again: {out}");

    // A clear that cannot be written is not done, and says so: what did not happen, what
    // stays, why, what to do; the path is in the log, with the printer.
    let (ok, out) = ctl(&config, &["clear", "p"]);
    assert!(!ok, "{out}");
    for said in [
        "p: the bed is not marked clear",
        "No space left on device",
        "the printer takes no job until it is",
        "`crispen clear p` again",
    ] {
        assert!(out.contains(said), "{said:?} in {out}");
    }
    assert!(
        !out.contains(&spool.display().to_string()) && !out.contains(".crispen-tmp"),
        "a server path in the answer: {out}"
    );
    let logged = std::fs::read_to_string(&log).unwrap();
    assert!(
        logged
            .lines()
            .any(|l| l.contains("the bed is not marked clear")
                && l.contains("printer=p")
                && l.contains(".crispen-tmp-printers.json")),
        "the path is logged with the printer:\n{logged}"
    );
    assert_eq!(
        printer(&status(&config).unwrap(), "p")["state"],
        "bed_not_cleared"
    );

    // Space returns: the outcome and the bed gate are written (one after the other), the
    // model is picked up.
    std::fs::remove_file(&filler).unwrap();
    let gates = disk.inside(&spool.join("printers.json"));
    let started = Instant::now();
    while on_disk(&job_json)["state"] != "done" || !gates.exists() {
        assert!(
            started.elapsed() < Duration::from_secs(60),
            "the outcome and the bed gate are written once space returns"
        );
        std::thread::sleep(Duration::from_millis(200));
    }
    assert_eq!(
        on_disk(&gates)["p"]["bed_not_cleared"],
        true,
        "the refused clear stayed undone"
    );
    assert_eq!(
        printer(&status(&config).unwrap(), "p")["state"],
        "bed_not_cleared"
    );
    // Tried again at its next turn (a minute apart at most), under the next number.
    let s = wait_for(
        &config,
        &log,
        Duration::from_secs(150),
        "big.stl picked up",
        |s| job_by_file(s, "big.stl").is_some(),
    );
    assert_eq!(job_by_file(&s, "big.stl").unwrap()["id"], "0002-big_stl");
    assert!(!hot.join("big.stl").exists());

    // After a kill -9 and a restart: still done, the bed still to be cleared.
    daemon.kill9();
    let printed = recorded(&rec).len();
    let _daemon = disk.start_daemon(&config, &log);
    let s = wait_for(&config, &log, Duration::from_secs(60), "back", |s| {
        s["printers"].as_array().is_some_and(|p| !p.is_empty())
            && printer(s, "p")["state"] == "bed_not_cleared"
    });
    assert_eq!(state_of(&s, "spot.obj"), "done");
    let (ok, out) = ctl(&config, &["retry", &id]);
    assert!(!ok, "still not offered again after a restart: {out}");
    assert_eq!(recorded(&rec).len(), printed, "nothing printed since");
    let (ok, out) = ctl(&config, &["clear", "p"]);
    assert!(ok && out.contains("bed cleared"), "{out}");
}

/// The daemon's memory while it prints a large pre-sliced file of very short lines (10
/// million commands, 37 MB): the job's commands are held packed, once, and its simulated
/// printer does not keep what it executed. Before, the load alone peaked at about 4 times
/// the file and the simulated printer's list grew with every line (157 MB three seconds
/// in, 206 MB at 15 %). Measured as what the daemon grows by over its idle footprint: the
/// packed program is 1.3 times the file (its text, and a byte per command for its length
/// and one for its source line), and the preview of the print drawn meanwhile adds its
/// picture's buffers, about 9 MB whatever the file (1.67 times in all on this machine); a
/// second copy of the program anywhere (preparation reading the file whole, a buffer grown
/// by doubling) passes twice the file.
#[test]
fn a_large_file_of_short_lines_costs_the_daemon_little_memory() {
    let tmp = tempfile::tempdir().unwrap();
    let root = tmp.path();
    let hot = root.join("hot");
    std::fs::create_dir_all(&hot).unwrap();
    let config = root.join("crispen.toml");
    let log = root.join("daemon.log");
    std::fs::write(
        &config,
        "[spool]\ndir = \"spool\"\n[control]\nsocket = \"c.sock\"\n[farm]\nsettle_s = 0.5\n\
         [[printer]]\nname = \"p\"\nfirmware = \"marlin2\"\n[printer.simulate]\ntime_scale = 0.0\n\
         [[folder]]\npath = \"hot\"\nheight_mm = 25\nprinters = [\"p\"]\n",
    )
    .unwrap();
    let mut gcode = b"M104 S200\nM109 S200\nG28\nG92 E0\nG1 X10 Y10 Z0.2 E1 F3000\n".to_vec();
    let words: [&[u8]; 3] = [b"G4\n", b"G90\n", b"G91\n"];
    for i in 0..10_000_000 {
        gcode.extend_from_slice(words[i % 3]);
    }
    let file_kb = gcode.len() as u64 / 1024;
    let daemon = Daemon::start(&config, &log);
    let status_kb = |key: &str| -> u64 {
        std::fs::read_to_string(format!("/proc/{}/status", daemon.child.id()))
            .unwrap()
            .lines()
            .find_map(|l| l.strip_prefix(key))
            .and_then(|v| v.trim().trim_end_matches("kB").trim().parse().ok())
            .unwrap()
    };
    wait_for(&config, &log, Duration::from_secs(60), "the printer", |s| {
        s["printers"].as_array().is_some_and(|p| !p.is_empty())
    });
    let idle_kb = status_kb("VmRSS:");
    drop_model(&hot, "short.gcode", &gcode);
    drop(gcode);
    let acked = |s: &Value| {
        printer(s, "p")["progress"]["lines_acked"]
            .as_u64()
            .unwrap_or(0)
    };
    // Well into the job: loaded, and a million lines executed by the simulated printer.
    // However slow a loaded machine makes the print, the wait goes on while it advances;
    // it fails only on a print that stopped moving.
    let (mut last, mut advanced) = (0, Instant::now());
    loop {
        if let Some(s) = common::daemon::status(&config) {
            let now = acked(&s);
            if now > 1_000_000 {
                break;
            }
            if now > last {
                (last, advanced) = (now, Instant::now());
            }
        }
        assert!(
            advanced.elapsed() < Duration::from_secs(120),
            "the print stopped at {last} lines\nlog:\n{}",
            std::fs::read_to_string(&log).unwrap_or_default()
        );
        std::thread::sleep(Duration::from_millis(200));
    }
    let peak_kb = status_kb("VmHWM:");
    assert!(
        peak_kb - idle_kb < 2 * file_kb,
        "the daemon grew from {idle_kb} kB to a peak of {peak_kb} kB for a {file_kb} kB file"
    );
}

/// Issue 22: a queued job whose job.json has an empty history (hand-edited, or written by
/// a broken store) is prepared like any other; reading `history[0]` once panicked the
/// preparation task, and nothing was prepared again.
#[test]
fn a_job_with_an_empty_history_is_prepared() {
    let dir = tempfile::tempdir().unwrap();
    let root = dir.path();
    let (config, log) = small_farm(root, "");
    bed_not_cleared_at_start(root);
    let mut daemon = Daemon::start(&config, &log);
    let gcode = common::farm::presliced_gcode("empty", 20, 1200);
    drop_model(&root.join("hot"), "empty.gcode", gcode.as_bytes());
    let s = wait_for(
        &config,
        &log,
        Duration::from_secs(120),
        "the job ready",
        |s| state_of(s, "empty.gcode") == "ready",
    );
    let id = job_by_file(&s, "empty.gcode").unwrap()["id"]
        .as_str()
        .unwrap()
        .to_string();
    nix::sys::signal::kill(
        nix::unistd::Pid::from_raw(daemon.child.id() as i32),
        nix::sys::signal::Signal::SIGTERM,
    )
    .unwrap();
    assert!(wait_exit(&mut daemon, Duration::from_secs(60), &log).success());
    let job_json = root.join("spool/jobs").join(&id).join("job.json");
    let mut job: Value = serde_json::from_slice(&std::fs::read(&job_json).unwrap()).unwrap();
    job["state"] = "queued".into();
    job["history"] = serde_json::json!([]);
    std::fs::write(&job_json, serde_json::to_vec(&job).unwrap()).unwrap();
    let _daemon = Daemon::start(&config, &log);
    wait_for(
        &config,
        &log,
        Duration::from_secs(120),
        "the job with an empty history prepared",
        |s| state_of(s, "empty.gcode") == "ready",
    );
    let text = std::fs::read_to_string(&log).unwrap();
    assert!(!text.contains("panicked"), "{text}");
}

/// Issue 33: an enhanced job is ready (printable) as soon as its own G-code is checked;
/// its wall comparison is measured afterwards, never ahead of another job's preparation,
/// and the job's record (what its report and page show) gains it when it is done. Two
/// jobs dropped together: each is ready before its comparison starts, and neither
/// comparison starts before the other job's preparation has ended.
#[test]
fn the_wall_comparison_comes_after_every_preparation_and_the_job_does_not_wait_for_it() {
    let dir = tempfile::tempdir().unwrap();
    let root = dir.path();
    let (config, log) = small_farm(root, "");
    bed_not_cleared_at_start(root);
    let _daemon = Daemon::start(&config, &log);
    for name in ["first.obj", "second.obj"] {
        drop_model(&root.join("hot"), name, &spot());
    }
    let s = wait_for(
        &config,
        &log,
        Duration::from_secs(180),
        "both jobs ready",
        |s| state_of(s, "first.obj") == "ready" && state_of(s, "second.obj") == "ready",
    );
    let job_json = |file: &str| -> Value {
        let id = job_by_file(&s, file).unwrap()["id"].as_str().unwrap();
        let path = root.join("spool/jobs").join(id).join("job.json");
        serde_json::from_slice(&std::fs::read(path).unwrap()).unwrap()
    };
    // Each comparison runs at the lowest CPU priority: waited for as the job's record
    // says it is made, however long a busy machine takes.
    let measured = |file: &str| job_json(file)["comparison"]["state"] == "done";
    wait_for(
        &config,
        &log,
        Duration::from_secs(600),
        "both comparisons made",
        |_| measured("first.obj") && measured("second.obj"),
    );
    // When the job entered `state` (its last time).
    let entered = |job: &Value, state: &str| -> f64 {
        job["history"]
            .as_array()
            .unwrap()
            .iter()
            .rev()
            .find(|h| h[0] == state)
            .unwrap_or_else(|| panic!("never {state}: {job}"))[1]
            .as_f64()
            .unwrap()
    };
    let jobs = [job_json("first.obj"), job_json("second.obj")];
    let last_ready = jobs.iter().map(|j| entered(j, "ready")).fold(0.0, f64::max);
    for job in &jobs {
        let comparison = &job["comparison"];
        let compared_at = comparison["started_s"].as_f64().unwrap();
        assert!(
            entered(job, "ready") < compared_at,
            "ready before its comparison: {job}"
        );
        assert!(
            last_ready <= compared_at,
            "no comparison before every preparation has ended: {jobs:?}"
        );
        // The report gains the figures, and the job's page the walls picture.
        let walls = &job["slice_report"]["walls"];
        assert!(walls["layers"].as_u64().unwrap() > 50, "{walls}");
        assert!(walls["mean_mm"].as_f64().unwrap() > 0.0, "{walls}");
        let dir = root.join("spool/jobs").join(job["id"].as_str().unwrap());
        assert!(dir.join("walls.png").is_file(), "{}", dir.display());
        // And the preview of both prints, drawn with it.
        assert!(dir.join("preview.png").is_file(), "{}", dir.display());
        assert_eq!(job["state"], "ready", "the comparison changes no state");
    }
}

/// A job printed unmodified has no comparison, and still gets its preview of the print,
/// drawn once the queue is idle: ready first, then `preview.png` in its directory and in
/// its pictures, the job as it was. So does a pre-sliced job (its print alone).
#[test]
fn jobs_printed_unmodified_or_presliced_get_their_preview_after_they_are_ready() {
    let dir = tempfile::tempdir().unwrap();
    let root = dir.path();
    let (config, log) = small_farm(root, "strength = \"off\"");
    bed_not_cleared_at_start(root);
    let _daemon = Daemon::start(&config, &log);
    drop_model(&root.join("hot"), "plain.obj", &spot());
    let gcode = common::farm::presliced_gcode("spot", 20, 1200);
    drop_model(&root.join("hot"), "sliced.gcode", gcode.as_bytes());
    let s = wait_for(
        &config,
        &log,
        Duration::from_secs(180),
        "the jobs ready",
        |s| state_of(s, "plain.obj") == "ready" && state_of(s, "sliced.gcode") == "ready",
    );
    for file in ["plain.obj", "sliced.gcode"] {
        let id = job_by_file(&s, file).unwrap()["id"]
            .as_str()
            .unwrap()
            .to_string();
        let job_dir = root.join("spool/jobs").join(&id);
        let started = Instant::now();
        while !job_dir.join("preview.png").is_file() {
            assert!(
                started.elapsed() < Duration::from_secs(120),
                "no preview drawn for {file}\nlog:\n{}",
                std::fs::read_to_string(&log).unwrap_or_default()
            );
            std::thread::sleep(Duration::from_millis(200));
        }
        let record: Value =
            serde_json::from_slice(&std::fs::read(job_dir.join("job.json")).unwrap()).unwrap();
        assert!(record.get("comparison").is_none(), "{record}");
        assert_eq!(record["state"], "ready", "the preview changes no state");
        let png = std::fs::read(job_dir.join("preview.png")).unwrap();
        assert_eq!(&png[..8], b"\x89PNG\r\n\x1a\n");
        // Not the enhanced job's pictures: only the model and its print.
        assert!(!job_dir.join("after.png").exists());
    }
}
