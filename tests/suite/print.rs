//! The host streamer against the simulated printer over real ptys: one test per fault
//! class and their combination. Each proves what the printer executed (its own record),
//! not what the host believes: the job exactly once and in order, or an exact prefix and
//! the right error. The last tests run the real `crispen sim` and `crispen print` binaries.

use crate::common;
use common::daemon::{self, Reaper};

use crispen::marlin::firmware::Firmware;
use crispen::marlin::gcode::GcodeProgram;
use crispen::marlin::protocol::canonical;
use crispen::marlin::stream::{
    Connection, PrintError, PrintProgress, PrintReport, StopOutcome, StreamControl, StreamOptions,
};
use crispen::sim::{self, Faults, SimConfig, SimHandle};
use std::process::{Command, Stdio};
use std::time::Duration;
use tokio::sync::{mpsc, watch};

/// A plausible small job: heat, home, many short moves (a tessellated curve), cool down.
fn job_text(moves: usize) -> String {
    let mut s = String::from(
        "; generated test job\nM140 S60\nM104 S200\nM190 S60\nM109 S200 ; wait\nG28\nG92 E0\n",
    );
    for i in 0..moves {
        let a = i as f64 * 0.05;
        // Written as a printer reads it (`canonical`: no trailing zeros), so that the
        // record of what the simulated printer ran compares with the file.
        s.push_str(&canonical(&format!(
            "G1 X{:.3} Y{:.3} E{:.4} F1800",
            100.0 + 20.0 * a.cos(),
            100.0 + 20.0 * a.sin(),
            i as f64 * 0.01
        )));
        s.push('\n');
        if i % 50 == 0 {
            s.push_str(&format!(";LAYER:{}\n\n", i / 50));
        }
    }
    s.push_str("M400\nM104 S0\nM140 S0\nM84\n");
    s
}

fn program(fw: Firmware, moves: usize) -> GcodeProgram {
    GcodeProgram::read(job_text(moves).as_bytes(), "test.gcode", fw).unwrap()
}

fn start_sim(fw: Firmware, faults: Faults, seed: u64) -> SimHandle {
    let mut cfg = SimConfig::new(fw);
    cfg.faults = faults;
    cfg.seed = seed;
    sim::spawn(cfg).expect("simulator starts")
}

/// Short timeouts so fault tests take seconds, not minutes.
fn options(fw: Firmware) -> StreamOptions {
    let mut o = StreamOptions::for_firmware(fw);
    o.protocol.quiet_period = Duration::from_millis(300);
    o.protocol.silence_probe = Duration::from_millis(400);
    o.protocol.silence_fail = Duration::from_secs(4);
    o.connect_timeout = Duration::from_secs(10);
    o
}

/// What the printer executed of the job: housekeeping (M105, M110, M155, M73...) removed.
fn job_executed(sim: &SimHandle) -> Vec<String> {
    sim.executed()
        .into_iter()
        .filter(|c| !sim::is_housekeeping(c))
        .collect()
}

async fn stream(
    sim: &SimHandle,
    opts: &StreamOptions,
    program: &GcodeProgram,
) -> Result<PrintReport, PrintError> {
    let mut conn = Connection::open(sim.device_path(), opts).await?;
    let (_control, control_rx) = mpsc::channel(1);
    let (progress, _) = watch::channel(PrintProgress::default());
    tokio::time::timeout(
        Duration::from_secs(120),
        conn.print(program, control_rx, progress),
    )
    .await
    .unwrap_or_else(|_| {
        // Where it stood, for a wedge seen once under CI's load and never here.
        let done = sim.executed();
        panic!(
            "job ends within two minutes: {} commands executed, the last {:?}",
            done.len(),
            &done[done.len().saturating_sub(5)..]
        )
    })
}

async fn exactly_once(fw: Firmware, faults: Faults, seed: u64, moves: usize) -> PrintReport {
    let sim = start_sim(fw, faults.clone(), seed);
    let program = program(fw, moves);
    let report = stream(&sim, &options(fw), &program)
        .await
        .unwrap_or_else(|e| panic!("{fw} {faults:?}: {e}"));
    assert_eq!(
        job_executed(&sim),
        program.to_vec(),
        "{fw} {faults:?}: executed sequence differs from the file"
    );
    assert_eq!(report.lines_acked, program.len());
    sim.shutdown();
    report
}

/// Issue 45: the time left is planned with the printer's own settings, read with an
/// unnumbered `M503` at connect (as the simulator answers it, line for line as the real
/// firmware does); a setting a job changed is what the next connection reads, and the
/// job's numbering is untouched by the query (the job runs exactly once).
#[tokio::test]
async fn the_printers_own_settings_are_read_at_connect() {
    use crispen::daemon::time_left::Settings;
    use crispen::marlin::estimate::{estimate_with, Limits};
    for fw in Firmware::ALL {
        let sim = start_sim(fw, Faults::default(), 3);
        let opts = options(fw);
        let conn = Connection::open(sim.device_path(), &opts).await.unwrap();
        assert_eq!(
            Settings::limits(fw, conn.settings()),
            (Limits::of(fw), Settings::Printer),
            "{fw}"
        );
        drop(conn);
        let job = GcodeProgram::read(&b"M203 X50 Y40\nG1 X10 F6000\n"[..], "t.gcode", fw).unwrap();
        stream(&sim, &opts, &job).await.unwrap();
        assert_eq!(job_executed(&sim), job.to_vec(), "{fw}");
        let conn = Connection::open(sim.device_path(), &opts).await.unwrap();
        let (limits, whose) = Settings::limits(fw, conn.settings());
        assert_eq!(
            (limits.max_feedrate[0], limits.max_feedrate[1], whose),
            (50.0, 40.0, Settings::Printer),
            "{fw}"
        );
        // 100 mm asked at 100 mm/s runs at this printer's 50.
        let planned = estimate_with(["G1 X100 F6000"], limits).total_seconds;
        assert!(planned > 2.0 && planned < 2.1, "{fw}: {planned}");
        drop(conn);
        sim.shutdown();
    }
}

/// A port another opener has locked is waited for, as it is for the moment a child process
/// of this one holds it between fork and exec: released while the open waits, it opens;
/// held past the wait, the error says the port is in use. (The first case under load once
/// failed the settings test above: a reopen right after a close met the lock.)
#[tokio::test]
async fn a_locked_port_is_waited_for_then_named_in_use() {
    use crispen::marlin::transport::{Transport, TransportError, BUSY_WAIT};
    let sim = start_sim(Firmware::Marlin2, Faults::default(), 3);
    let path = sim.device_path().to_path_buf();
    let holder = serialport::new(path.to_string_lossy(), 0)
        .open_native()
        .unwrap();
    let mut opening = Box::pin(Transport::open(&path, 115_200));
    // A zero timeout polls the open once: it met the lock and waits.
    assert!(tokio::time::timeout(Duration::ZERO, &mut opening)
        .await
        .is_err());
    drop(holder);
    opening.await.expect("opens once the holder let go");

    let holder = serialport::new(path.to_string_lossy(), 0)
        .open_native()
        .unwrap();
    match Transport::open(&path, 115_200).await {
        Err(e @ TransportError::Busy { waited_s, .. }) => {
            assert!(waited_s >= BUSY_WAIT.as_secs_f64(), "{e}");
            assert!(e.to_string().contains("another program has it open"), "{e}");
        }
        Err(e) => panic!("not named busy: {e}"),
        Ok(_) => panic!("opened a port another opener holds"),
    }
    drop(holder);
    sim.shutdown();
}

#[tokio::test]
async fn clean_link_delivers_the_file_exactly_once() {
    for fw in Firmware::ALL {
        let report = exactly_once(fw, Faults::default(), 1, 400).await;
        assert_eq!(report.resends, 0, "{fw}");
    }
}

#[tokio::test]
async fn corrupted_host_bytes_are_resent_exactly_once() {
    for fw in Firmware::ALL {
        let faults = Faults {
            corrupt_host_bytes: 0.05,
            ..Faults::default()
        };
        let report = exactly_once(fw, faults, 7, 600).await;
        assert!(report.resends > 0, "{fw}: the fault was injected");
    }
}

#[tokio::test]
async fn spurious_resends_are_handled() {
    let faults = Faults {
        spurious_resend: 0.05,
        ..Faults::default()
    };
    for fw in Firmware::ALL {
        let report = exactly_once(fw, faults.clone(), 11, 500).await;
        assert!(report.resends > 0, "{fw}");
    }
}

#[tokio::test]
async fn lost_oks_are_recovered_by_probes() {
    let faults = Faults {
        drop_ok: 0.03,
        ..Faults::default()
    };
    for fw in Firmware::ALL {
        // A seed whose dropped `ok`s include one a probe must recover on every flavour
        // (with ADVANCED_OK, a later `ok N` covers most of them); the `M503` at connect
        // draws from the same faults, so the seed moved from 3 when it came.
        let report = exactly_once(fw, faults.clone(), 12, 300).await;
        assert!(report.silence_probes > 0, "{fw}");
    }
}

#[tokio::test]
async fn busy_periods_and_garbage_are_tolerated() {
    let faults = Faults {
        busy: 0.02,
        garbage: 0.05,
        ..Faults::default()
    };
    for fw in Firmware::ALL {
        exactly_once(fw, faults.clone(), 5, 500).await;
    }
}

#[tokio::test]
async fn all_faults_at_once_still_deliver_exactly_once() {
    let faults = Faults {
        corrupt_host_bytes: 0.03,
        drop_ok: 0.02,
        spurious_resend: 0.02,
        busy: 0.01,
        garbage: 0.03,
        ..Faults::default()
    };
    for fw in Firmware::ALL {
        for seed in [21, 22] {
            exactly_once(fw, faults.clone(), seed, 500).await;
        }
    }
}

#[tokio::test]
async fn unplug_leaves_an_exact_prefix_and_a_disconnect_error() {
    for fw in Firmware::ALL {
        let faults = Faults {
            unplug_after_lines: Some(120),
            ..Faults::default()
        };
        let sim = start_sim(fw, faults, 1);
        let program = program(fw, 400);
        let err = stream(&sim, &options(fw), &program).await.unwrap_err();
        let executed = job_executed(&sim);
        assert!(
            matches!(err, PrintError::Disconnected { .. }),
            "{fw}: {err}"
        );
        let msg = err.to_string();
        assert!(
            msg.contains("disconnected") && msg.contains("last acknowledged line"),
            "{msg}"
        );
        assert!(!executed.is_empty() && executed.len() < program.len());
        assert_eq!(
            executed,
            program.to_vec()[..executed.len()],
            "{fw}: a prefix"
        );
        let acked = err.last_acked().unwrap();
        assert!(
            acked <= executed.len(),
            "{fw}: acked {acked} > executed {}",
            executed.len()
        );
        assert!(
            acked + 8 >= executed.len(),
            "{fw}: acked {acked} far behind {}",
            executed.len()
        );
    }
}

#[tokio::test]
async fn a_printer_reset_fails_the_job_with_its_reason() {
    for fw in Firmware::ALL {
        let faults = Faults {
            reset_after_lines: Some(100),
            ..Faults::default()
        };
        let sim = start_sim(fw, faults, 1);
        let program = program(fw, 300);
        let err = stream(&sim, &options(fw), &program).await.unwrap_err();
        assert!(
            matches!(err, PrintError::PrinterReset { .. }),
            "{fw}: {err}"
        );
        assert!(err.to_string().contains("reset"), "{err}");
        let executed = job_executed(&sim);
        assert_eq!(
            executed,
            program.to_vec()[..executed.len()],
            "{fw}: a prefix"
        );
    }
}

#[tokio::test]
async fn a_fatal_error_fails_the_job_with_the_printer_message() {
    for fw in Firmware::ALL {
        let faults = Faults {
            fatal_after_lines: Some(80),
            ..Faults::default()
        };
        let sim = start_sim(fw, faults, 1);
        let program = program(fw, 300);
        let err = stream(&sim, &options(fw), &program).await.unwrap_err();
        match &err {
            PrintError::Fatal { message, .. } => {
                assert!(
                    message.contains("kill()") || message.contains("stopped"),
                    "{message}"
                )
            }
            other => panic!("{fw}: {other}"),
        }
    }
}

#[tokio::test]
async fn a_silent_printer_fails_the_job_within_seconds() {
    let faults = Faults {
        silence_after_lines: Some(60),
        ..Faults::default()
    };
    let sim = start_sim(Firmware::Marlin2, faults, 1);
    let program = program(Firmware::Marlin2, 300);
    let started = std::time::Instant::now();
    let err = stream(&sim, &options(Firmware::Marlin2), &program)
        .await
        .unwrap_err();
    assert!(matches!(err, PrintError::Silent { .. }), "{err}");
    assert!(started.elapsed() < Duration::from_secs(30));
}

#[tokio::test]
async fn cancel_runs_the_safe_stop_lines() {
    for fw in Firmware::ALL {
        let mut cfg = SimConfig::new(fw);
        // Real timing, so the job is still running when we cancel.
        cfg.time_scale = 1.0;
        let sim = sim::spawn(cfg).unwrap();
        // Ultimaker2Marlin acknowledges moves as they enter its queue: after a cancel it
        // says nothing while it works off up to 8 queued moves at real speed.
        let mut opts = options(fw);
        opts.protocol.silence_fail = Duration::from_secs(15);
        let text = (0..400)
            .map(|i| format!("G1 X{} Y{} F6000\n", 10 + (i % 2) * 50, 10 + (i % 3) * 20))
            .collect::<String>();
        let program = GcodeProgram::read(text.as_bytes(), "moves.gcode", fw).unwrap();
        let mut conn = Connection::open(sim.device_path(), &opts).await.unwrap();
        let (control, control_rx) = mpsc::channel(1);
        let (progress, mut progress_rx) = watch::channel(PrintProgress::default());
        let canceller = tokio::spawn(async move {
            while progress_rx.changed().await.is_ok() {
                if progress_rx.borrow().lines_acked >= 20 {
                    control.send(StreamControl::Cancel).await.unwrap();
                    return;
                }
            }
        });
        let err = tokio::time::timeout(
            Duration::from_secs(60),
            conn.print(&program, control_rx, progress),
        )
        .await
        .unwrap()
        .unwrap_err();
        canceller.await.unwrap();
        assert!(matches!(err, PrintError::Cancelled { .. }), "{fw}: {err}");
        let (prefix, stop) = split_at_the_stop(&job_executed(&sim), &program.to_vec());
        assert!(prefix > 20 && prefix < 400, "{fw}: {prefix}");
        assert_the_stop(&stop, fw);
    }
}

/// The job's lines the printer ran before a stop (how many, a prefix of `program`), and
/// what it ran after them.
fn split_at_the_stop(executed: &[String], program: &[String]) -> (usize, Vec<String>) {
    let prefix = executed
        .iter()
        .zip(program)
        .take_while(|(a, b)| a == b)
        .count();
    (prefix, executed[prefix..].to_vec())
}

/// A stop as the printer ran it: an `M108` where it breaks a heat wait, the heaters off at
/// once without a number, then heaters, fan and motors off after a new count; nothing else.
fn assert_the_stop(stop: &[String], fw: Firmware) {
    let unnumbered: &[&str] = if fw == Firmware::Ultimaker2 {
        &["M104 S0", "M140 S0"]
    } else {
        &["M108", "M104 S0", "M140 S0"]
    };
    let numbered = ["M104 S0", "M140 S0", "M107", "M84"];
    let expected: Vec<&str> = unnumbered.iter().copied().chain(numbered).collect();
    assert_eq!(stop, expected, "{fw}");
}

/// A line a relay (or a second writer on the port) slips between the host's: numbered and
/// checksummed, so the printer takes it.
fn foreign_line(body: &str) -> String {
    let sum = body.bytes().fold(0u8, |a, b| a ^ b);
    format!("{body}*{sum}")
}

/// Issue 42 on the simulator: a line with `M110` in it, slipped into the stream after the
/// 40th line (the G-code policy refuses it in a file), renumbers the printer as the real
/// Marlin 2.1.2.1 does (higher, lower, to 0) or Ultimaker2Marlin (by the line's own
/// number). The job fails saying what happened, no refused line counts as progress, and
/// the printer confirms its heaters off. Before, the job showed 100 % and stayed printing
/// with the heaters held.
#[tokio::test]
async fn a_printer_renumbered_mid_job_is_stopped_and_its_heaters_confirmed_off() {
    use crispen::marlin::protocol::Numbering;
    for (fw, advanced_ok, line, ahead) in [
        (Firmware::Marlin2, false, "N0 M117 M110 N999", Some(1000)),
        (Firmware::Marlin2, true, "N0 M117 M110 N999", Some(1000)),
        (Firmware::Marlin2, false, "N0 M117 M110 N5", None),
        (Firmware::Marlin2, true, "N0 M117 M110 N5", None),
        (Firmware::Marlin2, false, "N0 M117 M110 N0", None),
        (Firmware::Marlin20, false, "N0 M117 M110 N999", Some(1000)),
        (Firmware::Ultimaker2, false, "N999 M117 M110", Some(1000)),
    ] {
        let mut cfg = SimConfig::new(fw);
        cfg.faults.receive = vec![(40, foreign_line(line))];
        // The real Marlin 2.1.2.1 is built without ADVANCED_OK.
        cfg.advanced_ok = Some(advanced_ok);
        let sim = sim::spawn(cfg).unwrap();
        let program = program(fw, 300);
        let err = stream(&sim, &options(fw), &program).await.unwrap_err();
        match (&err, ahead) {
            (
                PrintError::LostNumbering {
                    what: Numbering::AheadOfHost { requested, .. },
                    ..
                },
                Some(n),
            ) => assert_eq!(*requested, n, "{fw} {line}"),
            (
                PrintError::LostNumbering {
                    what: Numbering::WentBack { .. },
                    ..
                },
                None,
            ) => {}
            // An answered `M105` or `ok N<n>` had confirmed the lines it asks for again:
            // the same stop, named so.
            (PrintError::LostState { .. }, None) => {}
            _ => panic!("{fw} {line}: {err}"),
        }
        assert_eq!(
            err.stop_outcome(),
            StopOutcome::Confirmed,
            "{fw} {line}: {err}"
        );
        assert!(
            err.to_string().contains("no longer counts lines")
                || err.to_string().contains("line count went back"),
            "{err}"
        );
        // What the printer ran of the job, of the line slipped in, of the stop.
        let executed: Vec<String> = job_executed(&sim)
            .into_iter()
            .filter(|c| c != "M117 M110 N999" && !c.starts_with("M117 M110"))
            .collect();
        let (prefix, stop) = split_at_the_stop(&executed, &program.to_vec());
        assert!(
            prefix < 60,
            "{fw} {line}: the job stopped at once ({prefix})"
        );
        assert_the_stop(&stop, fw);
        // No progress for what the printer refused. (The slipped-in line's own `ok` is
        // one the host cannot tell from its oldest line's: one more at most.)
        assert!(
            err.last_acked().unwrap() <= prefix + 1,
            "{fw} {line}: {err}; ran {prefix} of the job, then {stop:?}"
        );
        sim.shutdown();
    }
}

/// A cancel while the printer heats: where an unnumbered `M108` ends the wait (Marlin 2,
/// with an emergency parser or without one, whose queue reads it during the wait), the
/// heaters go off at once, long before the target; Ultimaker2Marlin reads nothing while
/// it heats, so the stop waits for the heat-up, and the printer's progress says so with
/// how long it may take. Once a second SIGTERM turned the heaters off 44 s later, at full
/// temperature.
#[tokio::test]
async fn a_stop_during_a_heat_wait_breaks_it_where_the_firmware_can() {
    for (fw, emergency_parser) in [
        (Firmware::Marlin2, Some(false)),
        (Firmware::Marlin2, Some(true)),
        (Firmware::Ultimaker2, None),
    ] {
        let mut cfg = SimConfig::new(fw);
        cfg.time_scale = 0.1;
        cfg.emergency_parser = emergency_parser;
        let sim = sim::spawn(cfg).unwrap();
        let text = "M104 S150\nM109 S150\nG1 X10 F3000\nG1 X20\n";
        let program = GcodeProgram::read(text.as_bytes(), "hot.gcode", fw).unwrap();
        let mut conn = Connection::open(sim.device_path(), &options(fw))
            .await
            .unwrap();
        let (control, control_rx) = mpsc::channel(1);
        let (progress, mut progress_rx) = watch::channel(PrintProgress::default());
        let watcher = tokio::spawn(async move {
            let mut cancelled = false;
            let mut stop_wait = None;
            let mut last = PrintProgress::default();
            let mut hottest: f64 = 0.0;
            while progress_rx.changed().await.is_ok() {
                last = progress_rx.borrow().clone();
                hottest = hottest.max(last.hotend.map_or(0.0, |t| t.current));
                let hot = last.hotend.is_some_and(|t| t.current >= 40.0);
                if hot && !cancelled {
                    cancelled = true;
                    control.send(StreamControl::Cancel).await.unwrap();
                }
                if let Some(w) = &last.stop_wait {
                    stop_wait = Some(w.clone());
                }
            }
            (stop_wait, last, hottest)
        });
        let err = tokio::time::timeout(
            Duration::from_secs(60),
            conn.print(&program, control_rx, progress),
        )
        .await
        .unwrap()
        .unwrap_err();
        drop(conn);
        let (stop_wait, last, hottest) = watcher.await.unwrap();
        assert!(matches!(err, PrintError::Cancelled { .. }), "{fw}: {err}");
        assert_eq!(err.stop_outcome(), StopOutcome::Confirmed, "{fw}: {err}");
        let hotend = last.hotend.unwrap();
        assert_eq!(hotend.target, Some(0.0), "{fw}");
        let (prefix, stop) = split_at_the_stop(&job_executed(&sim), &program.to_vec());
        assert_eq!(prefix, 2, "{fw}: no move after the heat wait");
        assert_the_stop(&stop, fw);
        if fw == Firmware::Ultimaker2 {
            let w = stop_wait.expect("the progress said the stop waits for the heat-up");
            assert_eq!(w.command.as_deref(), Some("M109 S150"));
            assert_eq!(w.target_c, Some(150.0));
            assert!(w.remaining_s.is_some() && w.limit_s > 0.0, "{w:?}");
            // It ran its heat-up out.
            assert!(hottest >= 148.0, "{hottest}");
        } else {
            assert!(stop_wait.is_none(), "{fw}");
            // Broken off well below the target.
            assert!(hottest < 100.0, "{fw}: {hottest}");
        }
        sim.shutdown();
    }
}

/// The real binaries: `crispen sim` in its own process, `crispen print` streaming to it.
#[test]
fn crispen_print_streams_to_crispen_sim() {
    let dir = tempfile::tempdir().unwrap();
    let record = dir.path().join("executed.txt");
    let gcode = dir.path().join("job.gcode");
    std::fs::write(&gcode, job_text(300)).unwrap();
    let exe = env!("CARGO_BIN_EXE_crispen");

    let (mut sim, device) = daemon::spawn_sim(
        Command::new(exe)
            .args([
                "sim",
                "--time-scale",
                "0",
                "--corrupt",
                "0.02",
                "--seed",
                "4",
                "--record",
            ])
            .arg(&record),
    );

    let out = Command::new(exe)
        .args(["print"])
        .arg(&gcode)
        .arg("--port")
        .arg(&device)
        .output()
        .unwrap();
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert!(out.status.success(), "{stderr}");
    assert!(stderr.contains("done: "), "{stderr}");

    // A file that cannot be sent fails before anything is sent, naming file and line.
    std::fs::write(&gcode, format!("G28\nM117 {}\n", "x".repeat(100))).unwrap();
    let out = Command::new(exe)
        .args(["print"])
        .arg(&gcode)
        .arg("--port")
        .arg(&device)
        .output()
        .unwrap();
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert!(!out.status.success());
    assert!(stderr.contains("job.gcode:2:"), "{stderr}");

    // The G-code policy, as the daemon applies it: a file over the machine's limits is
    // refused before anything is sent, naming the line, the command and the machine.
    std::fs::write(&gcode, "G28\nM104 S300\nG1 X10 Y10\n").unwrap();
    let print = |extra: &[&str]| {
        let out = Command::new(exe)
            .args(["print"])
            .arg(&gcode)
            .arg("--port")
            .arg(&device)
            .args(extra)
            .output()
            .unwrap();
        (
            out.status.success(),
            String::from_utf8_lossy(&out.stderr).into_owned(),
        )
    };
    let (ok, stderr) = print(&[]);
    assert!(!ok);
    assert!(
        stderr.contains("line 2: `M104 S300`") && stderr.contains("\"marlin-175\""),
        "{stderr}"
    );
    let (ok, stderr) = print(&["--machine", "ultimaker2", "--firmware", "marlin2"]);
    assert!(!ok && stderr.contains("runs ultimaker2"), "{stderr}");
    let (ok, stderr) = print(&["--machine", "prusa-mk9"]);
    assert!(!ok && stderr.contains("one of: ultimaker2"), "{stderr}");

    let _ = nix::sys::signal::kill(
        nix::unistd::Pid::from_raw(sim.id() as i32),
        nix::sys::signal::Signal::SIGTERM,
    );
    let _ = sim.wait();
    let executed = daemon::recorded(&record);
    let expected = program(Firmware::Marlin2, 300);
    assert_eq!(executed, expected.to_vec());
}

#[tokio::test]
async fn one_connection_runs_jobs_back_to_back() {
    let fw = Firmware::Marlin2;
    let sim = start_sim(fw, Faults::default(), 2);
    let program = program(fw, 100);
    let mut conn = Connection::open(sim.device_path(), &options(fw))
        .await
        .unwrap();
    for _ in 0..2 {
        let (_control, control_rx) = mpsc::channel(1);
        let (progress, progress_rx) = watch::channel(PrintProgress::default());
        let report = conn.print(&program, control_rx, progress).await.unwrap();
        assert_eq!(report.lines_acked, program.len());
        assert_eq!(progress_rx.borrow().lines_acked, program.len());
    }
    let twice: Vec<String> = program
        .iter()
        .chain(program.iter())
        .map(str::to_owned)
        .collect();
    assert_eq!(job_executed(&sim), twice);
}

#[tokio::test]
async fn pause_holds_the_job_and_resume_finishes_it_exactly_once() {
    let fw = Firmware::Ultimaker2;
    let mut cfg = SimConfig::new(fw);
    cfg.time_scale = 1.0;
    let sim = std::sync::Arc::new(sim::spawn(cfg).unwrap());
    let text = (0..60)
        .map(|i| format!("G1 X{} Y{} F12000\n", 10 + (i % 2) * 30, 10 + (i % 3) * 20))
        .collect::<String>();
    let program = GcodeProgram::read(text.as_bytes(), "moves.gcode", fw).unwrap();
    let mut conn = Connection::open(sim.device_path(), &options(fw))
        .await
        .unwrap();
    let (control, control_rx) = mpsc::channel(1);
    let (progress, mut progress_rx) = watch::channel(PrintProgress::default());
    let watcher_sim = sim.clone();
    let driver = tokio::spawn(async move {
        while progress_rx.borrow().lines_acked < 10 {
            progress_rx.changed().await.unwrap();
        }
        control.send(StreamControl::Pause).await.unwrap();
        while progress_rx.borrow().state != crispen::marlin::stream::PrintState::Paused {
            progress_rx.changed().await.unwrap();
        }
        let at_pause = job_executed(&watcher_sim).len();
        tokio::time::sleep(Duration::from_millis(1500)).await;
        let later = job_executed(&watcher_sim).len();
        control.send(StreamControl::Resume).await.unwrap();
        (at_pause, later)
    });
    let report = tokio::time::timeout(
        Duration::from_secs(60),
        conn.print(&program, control_rx, progress),
    )
    .await
    .unwrap()
    .unwrap();
    let (at_pause, later) = driver.await.unwrap();
    assert_eq!(at_pause, later, "nothing executed while paused");
    assert!(at_pause < program.len());
    assert_eq!(report.lines_acked, program.len());
    assert_eq!(job_executed(&sim), program.to_vec());
}

// ----- real firmware behaviours (docs/firmware.md) ------------------------------------------

fn start_sim_with(cfg: SimConfig) -> SimHandle {
    sim::spawn(cfg).expect("simulator starts")
}

/// The done-when figure: under 3 % corrupted lines and 1 % lost `ok`s, for every firmware
/// flavour, the job runs exactly once and ends done.
#[tokio::test]
async fn every_flavour_delivers_exactly_once_through_3_percent_corruption_and_1_percent_lost_oks() {
    let faults = Faults {
        corrupt_host_bytes: 0.03,
        drop_ok: 0.01,
        ..Faults::default()
    };
    for fw in Firmware::ALL {
        for seed in [31, 32] {
            let report = exactly_once(fw, faults.clone(), seed, 600).await;
            assert!(
                report.resends > 0,
                "{fw} seed {seed}: the fault was injected"
            );
        }
    }
}

/// A Marlin 2.0 printer sends no `ok` after `Resend:`. Streamed one line at a time with
/// the 2.1 profile (the wrong guess), the host learns it from the first answers: no line is
/// ever left waiting for an `ok` that will not come, so no probe is needed.
#[tokio::test]
async fn marlin20_without_ok_after_resend_is_recognised_at_run_time() {
    let fw = Firmware::Marlin20;
    let faults = Faults {
        corrupt_host_bytes: 0.05,
        ..Faults::default()
    };
    let sim = start_sim(fw, faults, 9);
    let program = program(fw, 300);
    let mut opts = options(Firmware::Marlin2);
    opts.send_ahead = false;
    opts.protocol.resend_ok_wait = Duration::from_millis(300);
    let report = stream(&sim, &opts, &program).await.unwrap();
    assert_eq!(job_executed(&sim), program.to_vec());
    assert!(report.resends > 5, "{report:?}");
    // A wrong guess would leave a line waiting for an `ok` after nearly every resend, each
    // found only by a probe. (A line whose `N` itself was corrupted runs as a fragment and
    // does need one.)
    assert!(
        report.silence_probes * 4 <= report.resends,
        "ok accounting drifted: {report:?}"
    );
}

/// NO_TIMEOUTS: the printer says `wait` while idle. With lost `ok`s the host must take it
/// as a sign that they were lost, never as a keep-alive that postpones its probe.
#[tokio::test]
async fn a_printer_that_says_wait_when_idle_never_stalls_a_job() {
    for fw in Firmware::ALL {
        let mut cfg = SimConfig::new(fw);
        cfg.seed = 5;
        cfg.faults.drop_ok = 0.02;
        cfg.wait_when_idle = Some(Duration::from_millis(100));
        let sim = start_sim_with(cfg);
        let program = program(fw, 300);
        let mut opts = options(fw);
        // Probing on silence alone would take ages: only `wait` can make it quick.
        opts.protocol.silence_probe = Duration::from_secs(20);
        opts.protocol.silence_fail = Duration::from_secs(60);
        let started = std::time::Instant::now();
        let report = stream(&sim, &opts, &program)
            .await
            .unwrap_or_else(|e| panic!("{fw}: {e}"));
        assert_eq!(job_executed(&sim), program.to_vec(), "{fw}");
        if !fw.advanced_ok() {
            // (ADVANCED_OK heals a lost `ok` with the next one, by its number.)
            assert!(report.silence_probes > 0, "{fw}: an ok was lost");
        }
        assert!(
            started.elapsed() < Duration::from_secs(20),
            "{fw}: took {:?}",
            started.elapsed()
        );
    }
}

/// Stop and Pause on the printer's own screen (`//action:cancel`, `//action:pause`).
#[tokio::test]
async fn host_actions_from_the_printer_pause_and_cancel_the_job() {
    for fw in [Firmware::Marlin2, Firmware::Marlin20] {
        // Cancel: the job ends cancelled, with the safe-stop lines run.
        let mut cfg = SimConfig::new(fw);
        cfg.faults.actions = vec![(60, "cancel".into())];
        let sim = start_sim_with(cfg);
        let program = program(fw, 300);
        let err = stream(&sim, &options(fw), &program).await.unwrap_err();
        assert!(matches!(err, PrintError::Cancelled { .. }), "{fw}: {err}");
        let executed = job_executed(&sim);
        let n = executed.len();
        assert!(n < program.len(), "{fw}: {n}");
        assert!(
            executed[n - 5..].ends_with(&[
                "M104 S0".to_string(),
                "M140 S0".into(),
                "M107".into(),
                "M84".into()
            ]),
            "{fw}: {:?}",
            &executed[n - 5..]
        );

        // Pause: the job holds (state Paused) until resumed, then finishes exactly once.
        let mut cfg = SimConfig::new(fw);
        cfg.faults.actions = vec![(60, "pause".into())];
        let sim = start_sim_with(cfg);
        let mut conn = Connection::open(sim.device_path(), &options(fw))
            .await
            .unwrap();
        let (control, control_rx) = mpsc::channel(1);
        let (progress, mut progress_rx) = watch::channel(PrintProgress::default());
        let driver = tokio::spawn(async move {
            while progress_rx.borrow().state != crispen::marlin::stream::PrintState::Paused {
                progress_rx.changed().await.unwrap();
            }
            let acked = progress_rx.borrow().lines_acked;
            control.send(StreamControl::Resume).await.unwrap();
            acked
        });
        let report = tokio::time::timeout(
            Duration::from_secs(60),
            conn.print(&program, control_rx, progress),
        )
        .await
        .unwrap()
        .unwrap();
        let acked_at_pause = driver.await.unwrap();
        assert!(acked_at_pause < program.len(), "{fw}");
        assert_eq!(report.lines_acked, program.len());
        assert_eq!(job_executed(&sim), program.to_vec(), "{fw}");
    }
}

/// Opening the port resets many boards (DTR): the bootloader ignores the first second,
/// then the firmware says `start`. The handshake gets through and the job runs once.
#[tokio::test]
async fn a_reset_on_open_with_a_bootloader_delay_is_waited_out() {
    for fw in Firmware::ALL {
        let mut cfg = SimConfig::new(fw);
        cfg.reset_on_open = Some(Duration::from_millis(1200));
        let sim = start_sim_with(cfg);
        let program = program(fw, 100);
        stream(&sim, &options(fw), &program)
            .await
            .unwrap_or_else(|e| panic!("{fw}: {e}"));
        assert_eq!(job_executed(&sim), program.to_vec(), "{fw}");
    }
}

/// Ultimaker2Marlin acknowledges moves when they enter its queue, so the moves queued
/// behind an M109 are acknowledged before it finishes. The host's heating state follows
/// what the printer reports, not the order of `ok`s: while it still heats, the job never
/// shows as printing past the heat-up (the daemon's heating permit hangs on this).
#[tokio::test]
async fn ultimaker2_heating_state_follows_the_printer_not_the_order_of_oks() {
    let fw = Firmware::Ultimaker2;
    let mut cfg = SimConfig::new(fw);
    cfg.time_scale = 0.02;
    let sim = start_sim_with(cfg);
    let text = "M104 S200\nG1 X1 F3000\nG1 X2\nM109 S200\nG1 X3\nG1 X4\nG1 X5\nG1 X6\nM104 S0\n";
    let program = GcodeProgram::read(text.as_bytes(), "heat.gcode", fw).unwrap();
    let heat_index = 3;
    let mut conn = Connection::open(sim.device_path(), &options(fw))
        .await
        .unwrap();
    let (_control, control_rx) = mpsc::channel(1);
    let (progress, mut progress_rx) = watch::channel(PrintProgress::default());
    let watcher = tokio::spawn(async move {
        let mut wrong = Vec::new();
        let mut saw_heating = false;
        while progress_rx.changed().await.is_ok() {
            let p = progress_rx.borrow().clone();
            saw_heating |= p.state == crispen::marlin::stream::PrintState::Heating;
            let hot = p.hotend.is_some_and(|t| t.current >= 195.0);
            if p.lines_acked > heat_index
                && p.state != crispen::marlin::stream::PrintState::Heating
                && p.state != crispen::marlin::stream::PrintState::Done
                && !hot
            {
                wrong.push((p.lines_acked, p.state, p.hotend));
            }
        }
        (saw_heating, wrong)
    });
    tokio::time::timeout(
        Duration::from_secs(60),
        conn.print(&program, control_rx, progress),
    )
    .await
    .unwrap()
    .unwrap();
    drop(conn);
    let (saw_heating, wrong) = watcher.await.unwrap();
    assert!(saw_heating);
    assert!(
        wrong.is_empty(),
        "shown past the heat-up while cold: {wrong:?}"
    );
    assert_eq!(job_executed(&sim), program.to_vec());
}

/// A noise burst that makes the host give up is the common failure while the printer
/// still answers: the printer must end with heaters, fan and motors off.
#[tokio::test]
async fn giving_up_on_a_noisy_link_leaves_the_printer_safe() {
    for fw in Firmware::ALL {
        let faults = Faults {
            corrupt_host_bytes: 0.6,
            ..Faults::default()
        };
        let sim = start_sim(fw, faults, 3);
        let program = program(fw, 300);
        let mut opts = options(fw);
        opts.protocol.resend_limit = 3;
        // A storm is ridden out for `storm_timeout`: make this one outlast it.
        opts.protocol.storm_timeout = Duration::from_millis(500);
        // The stop rides out the noise up to its own limit, within the test's two minutes
        // however slow a loaded machine makes the link.
        opts.protocol.stop_timeout = Duration::from_secs(60);
        let err = stream(&sim, &opts, &program).await.unwrap_err();
        assert!(matches!(err, PrintError::ResendLimit { .. }), "{fw}: {err}");
        let executed = job_executed(&sim);
        let n = executed.len();
        assert!(n >= 4, "{fw}: {executed:?}");
        let tail = &executed[n.saturating_sub(6)..];
        // The error says what became of the stop, and that is what the printer ran.
        let ran: &[&str] = match err.stop_outcome() {
            StopOutcome::Confirmed => &["M104 S0", "M140 S0", "M107", "M84"],
            StopOutcome::HeatersOff => &["M104 S0", "M140 S0"],
            StopOutcome::NotConfirmed => &[],
            StopOutcome::None => panic!("{fw}: the error says nothing of the stop: {err}"),
        };
        for line in ran {
            assert!(executed.iter().any(|c| c == line), "{fw}: {err}: {tail:?}");
        }
        if err.stop_outcome() == StopOutcome::Confirmed {
            for line in ran {
                assert!(tail.iter().any(|c| c == line), "{fw}: {tail:?}");
            }
        }
    }
}

/// A firmware error that is neither a line error nor a halt (here a failed probing) means
/// the printer no longer does what the file says: the job ends failed with the error as
/// its reason, and the printer ends with heaters, fan and motors off.
#[tokio::test]
async fn a_firmware_error_that_is_no_halt_ends_the_job_with_heaters_off() {
    for fw in Firmware::ALL {
        let mut cfg = SimConfig::new(fw);
        cfg.faults.errors = vec![(60, "Probing Failed".into())];
        let sim = start_sim_with(cfg);
        let program = program(fw, 300);
        let err = stream(&sim, &options(fw), &program).await.unwrap_err();
        match &err {
            PrintError::FirmwareError { message, .. } => {
                assert!(message.contains("Probing Failed"), "{fw}: {err}")
            }
            other => panic!("{fw}: {other}"),
        }
        // The job's error says the printer confirmed the stop, not only a log line.
        assert!(
            err.to_string()
                .ends_with("; heaters, fan and motors confirmed off"),
            "{err}"
        );
        assert_eq!(err.stop_outcome(), StopOutcome::Confirmed, "{fw}");
        let executed = job_executed(&sim);
        let n = executed.len();
        assert!(n < program.len(), "{fw}: the job stopped");
        let tail = &executed[n.saturating_sub(6)..];
        for line in ["M104 S0", "M140 S0", "M107", "M84"] {
            assert!(tail.iter().any(|c| c == line), "{fw}: {tail:?}");
        }
    }
}

/// The daemon keeps its connection between jobs. While the bed waits to be cleared it
/// reads what the printer says: a reset (`start`, here the sim's reset button) is noted in
/// the printer's status and the log, and the next job begins with a fresh handshake; a
/// pulled cable is noticed and the printer reconnected before a job depends on it; each
/// job's autoreport is switched off at its end; every job runs exactly once.
#[test]
fn between_jobs_the_daemon_watches_the_printer_and_the_next_job_starts_clean() {
    use std::io::Write;
    let exe = env!("CARGO_BIN_EXE_crispen");
    let dir = tempfile::tempdir().unwrap();
    let root = dir.path();
    let link = root.join("p.tty");
    let record = root.join("p.rec");
    std::fs::create_dir(root.join("hot")).unwrap();
    // Whatever happens below, no daemon or simulator outlives the test.
    let reaper = Reaper::default();
    let start_sim = |record: &std::path::Path| {
        let (sim, _) = daemon::spawn_sim(
            Command::new(exe)
                .args([
                    "sim",
                    "--firmware",
                    "marlin2",
                    "--time-scale",
                    "0",
                    "--stdin",
                ])
                .arg("--link")
                .arg(&link)
                .arg("--record")
                .arg(record)
                .stdin(Stdio::piped()),
        );
        reaper.watch(&sim);
        sim
    };
    let mut sim = start_sim(&record);
    let mut sim_stdin = sim.stdin.take().unwrap();

    let config = root.join("crispen.toml");
    std::fs::write(
        &config,
        format!(
            "[spool]\ndir = \"spool\"\n[control]\nsocket = \"c.sock\"\n[farm]\nsettle_s = 0.3\n\
             [[printer]]\nname = \"p\"\nfirmware = \"marlin2\"\nport = {:?}\n\
             [[folder]]\npath = \"hot\"\nheight_mm = 20\nprinters = [\"p\"]\n",
            link.display().to_string()
        ),
    )
    .unwrap();
    let log = root.join("daemon.log");
    let mut farm = daemon::Daemon::start(&config, &log);
    let wait_for = |what: &str, check: &dyn Fn(&serde_json::Value) -> bool| {
        daemon::wait_for(&config, &log, Duration::from_secs(300), what, check)
    };
    let model = std::fs::read(concat!(env!("CARGO_MANIFEST_DIR"), "/tests/data/spot.obj")).unwrap();
    let drop_model = |name: &str| daemon::drop_model(&root.join("hot"), name, &model);
    let job_of = |s: &serde_json::Value, file: &str| -> serde_json::Value {
        common::job_by_file(s, file).cloned().unwrap_or_default()
    };
    let gcode_of = |s: &serde_json::Value, file: &str| -> Vec<String> {
        daemon::job_gcode(root, job_of(s, file)["id"].as_str().unwrap(), file)
    };
    let recorded = || -> Vec<String> {
        std::fs::read_to_string(&record)
            .unwrap_or_default()
            .lines()
            .map(String::from)
            .collect()
    };

    drop_model("first.obj");
    let s = wait_for("the first job done and the bed waiting", &|s| {
        job_of(s, "first.obj")["state"] == "done"
            && common::printer(s, "p")["state"] == "bed_not_cleared"
    });
    let first = gcode_of(&s, "first.obj");
    let after_first = recorded();
    // Autoreport was switched on for the job and off at its end.
    let last_m155 = after_first.iter().rev().find(|c| c.starts_with("M155"));
    assert_eq!(
        last_m155.map(String::as_str),
        Some("M155 S0"),
        "{after_first:?}"
    );

    // The reset button while the bed waits: noted at once, not only when a job starts.
    writeln!(sim_stdin, "reset").unwrap();
    wait_for("the reset noted in the printer's status", &|s| {
        common::printer(s, "p")["detail"]
            .as_str()
            .is_some_and(|d| d.contains("reset"))
    });
    let text = std::fs::read_to_string(&log).unwrap();
    assert!(
        text.contains("printer reset between jobs") && text.contains("printer"),
        "{text}"
    );

    let (ok, out) = daemon::ctl(&config, &["clear", "p"]);
    assert!(ok, "{out}");
    drop_model("second.obj");
    let s = wait_for("the second job done", &|s| {
        job_of(s, "second.obj")["state"] == "done"
    });
    let second = gcode_of(&s, "second.obj");
    wait_for("the bed waiting again", &|s| {
        common::printer(s, "p")["state"] == "bed_not_cleared"
    });

    // The cable is pulled while the bed waits: noticed at once, not when the next job
    // would fail on it, and the printer is reconnected once it is back.
    let stop = |sim: &mut std::process::Child| {
        let _ = nix::sys::signal::kill(
            nix::unistd::Pid::from_raw(sim.id() as i32),
            nix::sys::signal::Signal::SIGTERM,
        );
        let _ = sim.wait();
    };
    stop(&mut sim);
    wait_for("the lost link noticed", &|s| {
        common::printer(s, "p")["state"] == "disconnected"
    });
    let record_after = root.join("p-after.rec");
    let mut sim_after = start_sim(&record_after);
    wait_for(
        "the printer reconnected, its bed still to be cleared",
        &|s| common::printer(s, "p")["state"] == "bed_not_cleared",
    );
    assert!(daemon::ctl(&config, &["clear", "p"]).0);
    drop_model("third.obj");
    let s = wait_for("the third job done", &|s| {
        job_of(s, "third.obj")["state"] == "done"
    });
    let third = gcode_of(&s, "third.obj");
    farm.kill9();
    stop(&mut sim_after);
    let after = daemon::recorded(&record_after);
    assert!(after == third, "the third job exactly once on the new link");

    let all = recorded();
    // After the reset the printer was greeted afresh (M115) and numbered from 0 (M110 N0)
    // before the second job's first line.
    let since_reset = &all[after_first.len()..];
    let greeted = since_reset.iter().position(|c| c == "M115");
    let renumbered = since_reset.iter().position(|c| c == "M110 N0");
    let first_line = since_reset.iter().position(|c| *c == second[0]);
    assert!(
        greeted.is_some()
            && renumbered.is_some()
            && greeted < first_line
            && renumbered < first_line,
        "{:?}",
        &since_reset[..since_reset.len().min(8)]
    );
    let jobs: Vec<String> = all
        .into_iter()
        .filter(|c| !sim::is_housekeeping(c))
        .collect();
    let expected: Vec<String> = first.iter().chain(&second).cloned().collect();
    assert!(jobs == expected, "each job exactly once, in order");
}

/// Ultimaker2Marlin checks a line's checksum only up to its first `*` (seen on the real
/// firmware: `G1 X0.03 Y0.05` ran as `G1 X0.03 Y0`), and the simulator does the same. With
/// one `.` in ten lines arriving as `*`, the host's cut-line guard (on by default) leaves
/// no cut line that passes: the printer runs the file exactly. Without it, the simulated
/// printer runs a cut line, which is what this test would catch.
#[tokio::test]
async fn ultimaker2_runs_no_cut_line_with_the_default_options() {
    let fw = Firmware::Ultimaker2;
    let faults = Faults {
        star_for_dot: 0.1,
        ..Faults::default()
    };
    // Short relative moves as in the real firmware's test (`G1 X0.03 Y0.05`): small
    // numbers after a cut are what a prefix's XOR can equal.
    let mut text = String::from("G92 X0 Y0\nG91\n");
    for i in 0..1500 {
        text.push_str(&format!("G1 X0.0{} Y0.0{} F6000\n", i % 3 + 1, i % 4 + 1));
    }
    let program = GcodeProgram::read(text.as_bytes(), "cut.gcode", fw).unwrap();
    let expected: Vec<String> = program.to_vec();
    let sim = start_sim(fw, faults.clone(), 5);
    stream(&sim, &options(fw), &program)
        .await
        .unwrap_or_else(|e| panic!("{e}"));
    assert_eq!(job_executed(&sim), expected, "a cut line ran");
    drop(sim);

    let sim = start_sim(fw, faults, 5);
    let mut opts = options(fw);
    opts.protocol.uncuttable_lines = false;
    let _ = stream(&sim, &opts, &program).await;
    assert_ne!(
        job_executed(&sim),
        expected,
        "without the guard, the simulated Ultimaker2Marlin runs a cut line"
    );
}
