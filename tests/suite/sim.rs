//! The simulated printer, driven directly over its pty with raw bytes (no host code): the
//! firmware behaviour per profile, the record of executed commands, every fault, and the
//! `crispen sim` command.

use crispen::marlin::firmware::Firmware;
use crispen::sim::{self, is_housekeeping, Faults, SimConfig, SimHandle};
use nix::poll::{poll, PollFd, PollFlags, PollTimeout};
use nix::sys::termios;
use std::fs::File;
use std::io::{Read, Write};
use std::os::fd::AsFd;
use std::os::unix::fs::OpenOptionsExt;
use std::path::Path;
use std::time::{Duration, Instant};

const WAIT: Duration = Duration::from_secs(5);

/// A raw host end of the pty.
struct Port {
    file: File,
    pending: Vec<u8>,
    /// Every line read so far, for failure messages.
    seen: Vec<String>,
}

impl Port {
    fn open(path: &Path) -> Port {
        let file = std::fs::OpenOptions::new()
            .read(true)
            .write(true)
            .custom_flags(nix::libc::O_NOCTTY | nix::libc::O_NONBLOCK)
            .open(path)
            .unwrap_or_else(|e| panic!("open {}: {e}", path.display()));
        let mut attrs = termios::tcgetattr(&file).unwrap();
        termios::cfmakeraw(&mut attrs);
        termios::tcsetattr(&file, termios::SetArg::TCSANOW, &attrs).unwrap();
        Port {
            file,
            pending: Vec::new(),
            seen: Vec::new(),
        }
    }

    fn send_raw(&mut self, bytes: &[u8]) {
        let mut rest = bytes;
        while !rest.is_empty() {
            match self.file.write(rest) {
                Ok(n) => rest = &rest[n..],
                Err(e) if e.kind() == std::io::ErrorKind::WouldBlock => {
                    std::thread::sleep(Duration::from_millis(1))
                }
                Err(e) => panic!("write: {e}"),
            }
        }
    }

    fn send(&mut self, line: &str) {
        self.send_raw(format!("{line}\n").as_bytes());
    }

    /// Send `cmd` as line `n` with a correct checksum.
    fn send_numbered(&mut self, n: u64, cmd: &str) {
        let line = numbered(n, cmd);
        self.send(&line);
    }

    /// The next line as bytes, or None after `timeout`. Err on hang-up/EIO.
    fn line_bytes(&mut self, timeout: Duration) -> Result<Option<Vec<u8>>, std::io::Error> {
        let deadline = Instant::now() + timeout;
        loop {
            if let Some(at) = self.pending.iter().position(|&b| b == b'\n') {
                let mut line: Vec<u8> = self.pending.drain(..=at).collect();
                line.pop();
                self.seen.push(String::from_utf8_lossy(&line).into_owned());
                return Ok(Some(line));
            }
            let left = deadline.saturating_duration_since(Instant::now());
            if left.is_zero() {
                return Ok(None);
            }
            let mut fds = [PollFd::new(self.file.as_fd(), PollFlags::POLLIN)];
            let ms = PollTimeout::try_from(left.as_millis().max(1) as i32).unwrap();
            poll(&mut fds, ms).map_err(std::io::Error::from)?;
            let mut buf = [0u8; 1024];
            match self.file.read(&mut buf) {
                Ok(0) => return Err(std::io::ErrorKind::UnexpectedEof.into()),
                Ok(n) => self.pending.extend_from_slice(&buf[..n]),
                Err(e) if e.kind() == std::io::ErrorKind::WouldBlock => {}
                Err(e) => return Err(e),
            }
        }
    }

    fn line(&mut self, timeout: Duration) -> Option<String> {
        self.line_bytes(timeout)
            .expect("port closed")
            .map(|l| String::from_utf8_lossy(&l).into_owned())
    }

    /// Read lines until one starts with `prefix`; returns the lines before it and the line.
    fn until(&mut self, prefix: &str) -> (Vec<String>, String) {
        let mut before = Vec::new();
        let deadline = Instant::now() + WAIT;
        while let Some(line) = self.line(deadline.saturating_duration_since(Instant::now())) {
            if line.starts_with(prefix) {
                return (before, line);
            }
            before.push(line);
        }
        panic!("no line starting with {prefix:?}; saw {:#?}", self.seen);
    }

    /// Lines that arrive within `quiet` (used to prove something is NOT sent).
    fn drain(&mut self, quiet: Duration) -> Vec<String> {
        let mut lines = Vec::new();
        while let Some(line) = self.line(quiet) {
            lines.push(line);
        }
        lines
    }

    /// Reset line numbers the way a host does on connect.
    /// Like a host, it tries again when the line gets no answer (Marlin 2.1 ignores a
    /// corrupted `N0` line silently: it takes it for a duplicate).
    fn handshake(&mut self) {
        for _ in 0..10 {
            self.send_numbered(0, "M110 N0");
            while let Some(line) = self.line(Duration::from_secs(1)) {
                if line.starts_with("ok") {
                    return;
                }
            }
        }
        panic!("no answer to M110; saw {:#?}", self.seen);
    }
}

fn numbered(n: u64, cmd: &str) -> String {
    let body = format!("N{n} {cmd}");
    let sum = body.bytes().fold(0u8, |a, b| a ^ b);
    format!("{body}*{sum}")
}

fn start(cfg: SimConfig) -> (SimHandle, Port) {
    let sim = sim::spawn(cfg).expect("spawn simulator");
    let port = Port::open(sim.device_path());
    (sim, port)
}

fn job_commands(sim: &SimHandle) -> Vec<String> {
    sim.executed()
        .into_iter()
        .filter(|c| !is_housekeeping(c))
        .collect()
}

/// A bad checksum on line 1 followed at once by line 2. Marlin 2.1 reads each line as it
/// comes (as the real Marlin 2.1.2.1 does through the relay in `tests/firmware.rs`): line
/// 2 draws its own line-number error and resend request. The other flavours have line 2
/// in their receive buffer already and flush it with the bad line. Either way only the resend
/// of 1 and then 2 again execute.
#[test]
fn checksum_error_asks_for_resend_then_ok_and_each_line_behind_it_too() {
    for fw in Firmware::ALL {
        let (sim, mut port) = start(SimConfig::new(fw));
        port.handshake();
        port.send_raw(format!("N1 G1 X1*0\n{}\n", numbered(2, "G1 X2")).as_bytes());
        let mut errors = vec!["Error:checksum mismatch, Last Line: 0"];
        if fw == Firmware::Marlin2 {
            errors.push("Error:Line Number is not Last Line Number+1, Last Line: 0");
        }
        for error in errors {
            let (_, err) = port.until("Error:");
            assert_eq!(err, error, "{fw}");
            assert_eq!(port.line(WAIT).as_deref(), Some("Resend: 1"), "{fw}");
            // Marlin 2.0 sends no `ok` after `Resend:`.
            if fw.ok_after_resend() {
                assert!(port.line(WAIT).unwrap().starts_with("ok"), "{fw}");
            }
        }
        assert!(port.drain(Duration::from_millis(200)).is_empty(), "{fw}");
        port.send_numbered(1, "G1 X1");
        let (_, ok) = port.until("ok");
        if fw.advanced_ok() {
            assert!(ok.starts_with("ok N1 P"), "{ok}");
        } else {
            assert_eq!(ok, "ok");
        }
        port.send_numbered(2, "G1 X2");
        port.until("ok");
        assert_eq!(job_commands(&sim), ["G1 X1", "G1 X2"], "{fw}");
    }
}

#[test]
fn wrong_line_number_and_missing_checksum_ask_for_resend() {
    let (sim, mut port) = start(SimConfig::new(Firmware::Marlin2));
    port.handshake();
    port.send_numbered(1, "G1 X1");
    port.until("ok");
    port.send_numbered(3, "G1 X3");
    let (_, err) = port.until("Error:");
    assert_eq!(
        err,
        "Error:Line Number is not Last Line Number+1, Last Line: 1"
    );
    assert_eq!(port.line(WAIT).as_deref(), Some("Resend: 2"));
    port.until("ok");
    port.send("N2 G1 X2");
    let (_, err) = port.until("Error:");
    assert_eq!(err, "Error:No Checksum with line number, Last Line: 1");
    assert_eq!(port.line(WAIT).as_deref(), Some("Resend: 2"));
    port.until("ok");
    // Un-numbered commands are accepted as Marlin does.
    port.send("G1 X9");
    port.until("ok");
    assert_eq!(job_commands(&sim), ["G1 X1", "G1 X9"]);
}

#[test]
fn m110_sets_the_line_number_last_n_wins() {
    let (sim, mut port) = start(SimConfig::new(Firmware::Marlin2));
    port.send_numbered(101, "M110 N100");
    port.until("ok");
    port.send_numbered(101, "G1 X1");
    let (_, ok) = port.until("ok");
    assert!(ok.starts_with("ok N101 "), "{ok}");
    port.send_numbered(0, "M110 N0");
    port.until("ok");
    port.send_numbered(1, "G1 X2");
    port.until("ok");
    assert_eq!(
        sim.executed(),
        ["M110 N100", "G1 X1", "M110 N0", "G1 X2"],
        "executed() strips N and checksum"
    );
}

#[test]
fn m115_answers_per_profile() {
    let (_sim, mut port) = start(SimConfig::new(Firmware::Marlin2));
    port.send_numbered(1, "M115");
    let (lines, _) = port.until("ok");
    assert!(
        lines[0].starts_with("FIRMWARE_NAME:Marlin 2.1.2"),
        "{lines:?}"
    );
    assert!(lines[0].contains("PROTOCOL_VERSION:1.0") && lines[0].contains("EXTRUDER_COUNT:1"));
    for cap in [
        "Cap:AUTOREPORT_TEMP:1",
        "Cap:BUSY_PROTOCOL:1",
        "Cap:EMERGENCY_PARSER:1",
        "Cap:ADVANCED_OK:1",
    ] {
        assert!(
            lines.iter().any(|l| l == cap),
            "{cap} missing from {lines:?}"
        );
    }

    let (_sim, mut port) = start(SimConfig::new(Firmware::Ultimaker2));
    port.send_numbered(1, "M115");
    let (lines, ok) = port.until("ok");
    assert_eq!(ok, "ok");
    assert_eq!(lines.len(), 1, "{lines:?}");
    assert!(lines[0].starts_with("FIRMWARE_NAME:Marlin Ultimaker2;"));
    assert!(lines[0].contains("MACHINE_TYPE:Ultimaker EXTRUDER_COUNT:1"));
}

#[test]
fn m105_reports_temperatures_with_the_ok_and_unknown_commands_per_profile() {
    let (_sim, mut port) = start(SimConfig::new(Firmware::Marlin2));
    port.send_numbered(1, "M105");
    let (_, ok) = port.until("ok");
    assert_eq!(ok, "ok T:21.00 /0.00 B:21.00 /0.00 @:0 B@:0");
    port.send_numbered(2, "M9999 X");
    let (lines, _) = port.until("ok");
    assert_eq!(lines, ["echo:Unknown command: \"M9999 X\""]);

    let (_sim, mut port) = start(SimConfig::new(Firmware::Ultimaker2));
    port.send_numbered(1, "M9999 X");
    let (lines, ok) = port.until("ok");
    assert!(lines.is_empty() && ok == "ok", "{lines:?} {ok}");
    // No autoreport on the Ultimaker 2: M155 is acknowledged and nothing follows.
    port.send_numbered(2, "M155 S1");
    port.until("ok");
    assert!(port.drain(Duration::from_millis(300)).is_empty());
}

#[test]
fn m109_heats_at_a_realistic_rate_reporting_and_keeping_alive() {
    let mut cfg = SimConfig::new(Firmware::Marlin2);
    cfg.time_scale = 0.01; // 2.5 °C per simulated second: 21 → 100 °C in ~32 s = ~0.32 s
    let (_sim, mut port) = start(cfg);
    port.send_numbered(1, "M109 S100");
    let (lines, ok) = port.until("ok");
    assert!(ok.starts_with("ok N1 "), "{ok}");
    let reports: Vec<f64> = lines
        .iter()
        .filter_map(|l| l.strip_prefix("T:"))
        .map(|l| l.split(' ').next().unwrap().parse().unwrap())
        .collect();
    assert!(reports.len() >= 3, "too few reports: {lines:?}");
    assert!(reports.windows(2).all(|w| w[0] <= w[1]), "{reports:?}");
    assert!(reports[0] < 80.0, "heated too fast: {reports:?}");
    assert!(
        lines.iter().any(|l| l == "echo:busy: processing"),
        "{lines:?}"
    );
    port.send_numbered(2, "M105");
    let (_, ok) = port.until("ok");
    assert!(
        ok.starts_with("ok T:99.") || ok.starts_with("ok T:100."),
        "{ok}"
    );
}

#[test]
fn m108_breaks_a_heat_wait_and_m112_halts() {
    let mut cfg = SimConfig::new(Firmware::Marlin2);
    cfg.time_scale = 1.0; // the bed would take minutes
    let (_sim, mut port) = start(cfg);
    port.send_numbered(1, "M190 S100");
    assert!(port
        .drain(Duration::from_millis(300))
        .iter()
        .all(|l| !l.starts_with("ok")));
    port.send("M108");
    port.until("ok N1");
    port.send_numbered(2, "M112");
    port.until("Error:Printer halted. kill() called!");
    port.send_numbered(3, "M105");
    assert!(port.drain(Duration::from_millis(300)).is_empty());
}

#[test]
fn moves_are_acknowledged_on_entering_the_planner_which_drains_at_their_speed() {
    let mut cfg = SimConfig::new(Firmware::Marlin2);
    cfg.time_scale = 1.0;
    let (sim, mut port) = start(cfg);
    // Each move is 10 mm at 600 mm/min = 1 s. Sixteen fit in the planner at once.
    for n in 1..=17 {
        let x = if n % 2 == 1 { 10 } else { 0 };
        port.send_numbered(n, &format!("G1 X{x} F600"));
    }
    for n in 1..=16u64 {
        let (_, ok) = port.until("ok");
        let free = 16 - n;
        assert!(ok.starts_with(&format!("ok N{n} P{free} ")), "{ok}");
    }
    // The 17th waits for the first move to finish (about 1 s after it started).
    assert!(port.drain(Duration::from_millis(300)).is_empty());
    let (_, ok) = port.until("ok");
    assert!(ok.starts_with("ok N17 "), "{ok}");
    assert_eq!(job_commands(&sim).len(), 17);
}

#[test]
fn record_file_gets_every_executed_command() {
    let dir = tempfile::tempdir().unwrap();
    let record = dir.path().join("executed.txt");
    let mut cfg = SimConfig::new(Firmware::Ultimaker2);
    cfg.record = Some(record.clone());
    let (sim, mut port) = start(cfg);
    port.handshake();
    port.send_numbered(1, "G28");
    port.until("ok");
    port.send_numbered(2, "M104 S200");
    port.until("ok");
    let text = std::fs::read_to_string(&record).unwrap();
    assert_eq!(text, "M110 N0\nG28\nM104 S200\n");
    assert_eq!(sim.executed(), ["M110 N0", "G28", "M104 S200"]);
}

/// A minimal one-line-in-flight host: resends from the requested line, probes with M105
/// when an ok does not come. Good enough to prove faults are survivable.
fn ping_pong(port: &mut Port, job: &[String]) -> usize {
    let mut resends = 0;
    let mut next = 1usize;
    port.handshake();
    while next <= job.len() {
        port.send_numbered(next as u64, &job[next - 1]);
        let mut acked = false;
        while !acked {
            // Long enough that a loaded machine never probes needlessly (a probe is a line
            // too, and would change which lines the seeded corruption hits).
            let Some(line) = port.line(Duration::from_secs(2)) else {
                port.send("M105"); // lost ok: probe
                continue;
            };
            if let Some(n) = line.strip_prefix("Resend:") {
                next = n.trim().parse().unwrap();
                resends += 1;
                // Marlin follows the request with an ok; swallow it.
                port.until("ok");
                acked = true;
                next -= 1;
            } else if line.starts_with("ok") {
                acked = true;
            }
        }
        next += 1;
    }
    resends
}

#[test]
fn corrupted_host_bytes_are_caught_and_resent_reproducibly() {
    let job: Vec<String> = (0..40)
        .map(|i| format!("G1 X{i} Y{} F3000", i * 2))
        .collect();
    let mut outcomes = Vec::new();
    for _ in 0..2 {
        let mut cfg = SimConfig::new(Firmware::Marlin2);
        cfg.seed = 7;
        cfg.faults.corrupt_host_bytes = 0.25;
        let (sim, mut port) = start(cfg);
        let resends = ping_pong(&mut port, &job);
        assert!(resends >= 3, "only {resends} resends at 25% corruption");
        assert_eq!(job_commands(&sim), job);
        outcomes.push(resends);
    }
    assert_eq!(outcomes[0], outcomes[1], "same seed, same faults");
}

#[test]
fn spurious_resend_and_dropped_ok() {
    let mut cfg = SimConfig::new(Firmware::Marlin2);
    cfg.faults.spurious_resend = 1.0;
    let (sim, mut port) = start(cfg);
    port.send_numbered(1, "G1 X1");
    let (_, err) = port.until("Error:");
    assert_eq!(err, "Error:checksum mismatch, Last Line: 0");
    assert_eq!(port.line(WAIT).as_deref(), Some("Resend: 1"));
    assert!(sim.executed().is_empty());

    let mut cfg = SimConfig::new(Firmware::Ultimaker2);
    cfg.faults.drop_ok = 1.0;
    let (sim, mut port) = start(cfg);
    port.send_numbered(1, "G1 X1");
    assert!(
        port.drain(Duration::from_millis(300)).is_empty(),
        "ok not dropped"
    );
    port.send("M105");
    let (_, ok) = port.until("ok");
    assert!(ok.starts_with("ok T:"), "the M105 probe recovers: {ok}");
    assert_eq!(sim.executed(), ["G1 X1", "M105"]);
}

#[test]
fn busy_fault_sends_keepalives_before_the_ok() {
    let mut cfg = SimConfig::new(Firmware::Marlin2);
    cfg.faults.busy = 1.0;
    let (_sim, mut port) = start(cfg);
    port.send_numbered(1, "G1 X1");
    let (lines, ok) = port.until("ok");
    assert!(ok.starts_with("ok N1"));
    assert!(lines.len() >= 2, "{lines:?}");
    assert!(
        lines.iter().all(|l| l == "echo:busy: processing"),
        "{lines:?}"
    );
}

#[test]
fn garbage_fault_garbles_answers_but_never_misdirects_a_resend() {
    let mut cfg = SimConfig::new(Firmware::Marlin2);
    cfg.faults.garbage = 1.0;
    cfg.seed = 3;
    let (_sim, mut port) = start(cfg);
    let mut raw = Vec::new();
    for n in 1..=6 {
        port.send_numbered(n, "G1 X1");
        while let Ok(Some(line)) = port.line_bytes(Duration::from_millis(150)) {
            raw.push(line);
        }
    }
    assert!(!raw.is_empty());
    assert!(
        raw.iter().all(|l| !l.starts_with(b"ok N")),
        "every ok garbled: {:?}",
        port.seen
    );
    assert!(raw.iter().any(|l| l.starts_with(b"okk N")));
    assert!(raw.iter().any(|l| std::str::from_utf8(l).is_err()));
    port.send_numbered(9, "G1 X1");
    let (_, err) = port.until("Error:");
    assert!(err.starts_with("Error:Line Number"), "{err}");
    let (_, resend) = port.until("Resend:");
    assert_eq!(resend, "Resend:7");
}

#[test]
fn reset_after_lines_reboots_and_forgets_line_numbers() {
    let mut cfg = SimConfig::new(Firmware::Marlin2);
    cfg.faults.reset_after_lines = Some(3);
    let (sim, mut port) = start(cfg);
    port.handshake(); // line 1 (N0)
    port.send_numbered(1, "M104 S200");
    port.until("ok");
    port.send_numbered(2, "G1 X1"); // third numbered line: executed, then reset
    let (before, _) = port.until("start");
    assert!(
        before.is_empty(),
        "no ok for the line that triggered the reset: {before:?}"
    );
    port.send_numbered(1, "M105");
    let (_, ok) = port.until("ok");
    assert_eq!(
        ok, "ok T:21.00 /0.00 B:21.00 /0.00 @:0 B@:0",
        "targets forgotten"
    );
    assert_eq!(sim.executed(), ["M110 N0", "M104 S200", "G1 X1", "M105"]);
}

#[test]
fn unplug_after_lines_hangs_up_and_the_device_vanishes() {
    let dir = tempfile::tempdir().unwrap();
    let link = dir.path().join("printer");
    let mut cfg = SimConfig::new(Firmware::Marlin2);
    cfg.faults.unplug_after_lines = Some(2);
    cfg.link = Some(link.clone());
    let (sim, mut port) = start(cfg);
    port.handshake();
    port.send_numbered(1, "G1 X1");
    // The printer may already be gone: a write to a hung-up pty fails with EIO.
    let _ = port
        .file
        .write(format!("{}\n", numbered(2, "G1 X2")).as_bytes());
    let deadline = Instant::now() + WAIT;
    loop {
        match port.line_bytes(Duration::from_millis(100)) {
            Err(_) => break,
            Ok(Some(line)) => assert!(line.is_empty() || line == b"ok", "{line:?}"),
            Ok(None) => assert!(Instant::now() < deadline, "no hang-up"),
        }
    }
    assert_eq!(sim.executed(), ["M110 N0", "G1 X1"]);
    // The pty node vanishes with the master, but parallel tests reuse pty numbers at
    // once, so only the link (ours alone) is checked.
    drop(port);
    let deadline = Instant::now() + WAIT;
    while std::fs::symlink_metadata(&link).is_ok() {
        assert!(Instant::now() < deadline, "link not removed");
        std::thread::sleep(Duration::from_millis(10));
    }
}

#[test]
fn silence_and_fatal_after_lines() {
    let mut cfg = SimConfig::new(Firmware::Ultimaker2);
    cfg.faults.silence_after_lines = Some(2);
    let (sim, mut port) = start(cfg);
    port.handshake();
    port.send_numbered(1, "G1 X1");
    port.send_numbered(2, "M105");
    port.send("M105");
    // Ultimaker2Marlin acknowledges the move as it enters the queue, before it runs; after
    // that nothing.
    let said = port.drain(Duration::from_millis(300));
    assert!(
        said.len() <= 1 && said.iter().all(|l| l == "ok"),
        "{said:?}"
    );
    assert_eq!(sim.executed(), ["M110 N0", "G1 X1"]);

    let mut cfg = SimConfig::new(Firmware::Marlin2);
    cfg.faults.fatal_after_lines = Some(2);
    let (sim, mut port) = start(cfg);
    port.handshake();
    port.send_numbered(1, "G1 X1");
    let (_, first) = port.until("Error:");
    let second = port.line(WAIT).unwrap();
    assert!(first.starts_with("Error:") && second == "Error:Printer halted. kill() called!");
    port.send_numbered(2, "M105");
    assert!(port.drain(Duration::from_millis(300)).is_empty());
    assert_eq!(sim.executed(), ["M110 N0", "G1 X1"]);
}

#[test]
fn overrunning_the_receive_buffer_loses_bytes_and_asks_for_a_resend() {
    let mut cfg = SimConfig::new(Firmware::Marlin2);
    cfg.time_scale = 1.0;
    let (sim, mut port) = start(cfg);
    port.handshake();
    // Stall the main loop in a heat wait, then send far more than the 128-byte ring holds.
    port.send_numbered(1, "M109 S200");
    let deadline = Instant::now() + WAIT;
    while !sim.executed().iter().any(|c| c == "M109 S200") {
        assert!(Instant::now() < deadline, "the heat wait never began");
        std::thread::sleep(Duration::from_millis(10));
    }
    let job: Vec<String> = (2..40)
        .map(|n| numbered(n, &format!("G1 X{n}.125 Y{n}.5 E0.0123 F1800")))
        .collect();
    port.send_raw((job.join("\n") + "\n").as_bytes());
    // The pty keeps the bytes in order: the job's reach the ring (and overflow it) before
    // M108's. The emergency parser still sees M108 although its bytes find no room in the ring.
    port.send("M108");
    port.until("ok N1 ");
    // The ring held the first lines and a fragment; the next line completes the fragment,
    // which fails its check, and the printer asks for the first line it lost.
    port.send_numbered(40, "G1 X0");
    let (_, err) = port.until("Error:");
    let (_, resend) = port.until("Resend:");
    let first_lost: usize = resend["Resend: ".len()..].parse().unwrap();
    assert!(
        err.ends_with(&format!("Last Line: {}", first_lost - 1)),
        "{err}"
    );
    let moves: Vec<String> = sim
        .executed()
        .into_iter()
        .filter(|c| c.starts_with("G1"))
        .collect();
    // M109 holds the main loop, but Marlin reads lines into its three free command slots
    // while it waits (temperature.cpp:4122 `idle()`, MarlinCore.cpp:412, as the real
    // 2.1.2.1 does); then only the 128-byte ring takes lines (3 of 35 bytes).
    assert_eq!(moves.len(), 6, "{moves:?}");
    assert_eq!(moves.len(), first_lost - 2, "an exact prefix: {moves:?}");
    assert!(!sim.executed().contains(&"M108".to_string()));
}

#[test]
fn crispen_sim_prints_its_device_and_manages_its_link() {
    let dir = tempfile::tempdir().unwrap();
    let link = dir.path().join("ttyCRISPEN");
    let mut child = std::process::Command::new(env!("CARGO_BIN_EXE_crispen"))
        .args([
            "sim",
            "--firmware",
            "ultimaker2",
            "--time-scale",
            "0",
            "--link",
        ])
        .arg(&link)
        .stdout(std::process::Stdio::piped())
        .stderr(std::process::Stdio::null())
        .spawn()
        .unwrap();
    let mut stdout = std::io::BufReader::new(child.stdout.take().unwrap());
    let mut first = String::new();
    std::io::BufRead::read_line(&mut stdout, &mut first).unwrap();
    let device = first
        .trim_end()
        .strip_prefix("crispen sim: listening on ")
        .unwrap_or_else(|| panic!("first line: {first:?}"));
    assert_eq!(std::fs::read_link(&link).unwrap(), Path::new(device));
    let mut port = Port::open(&link);
    port.send_numbered(1, "M115");
    let (lines, _) = port.until("ok");
    assert!(lines[0].contains("Ultimaker2"));
    drop(port);
    nix::sys::signal::kill(
        nix::unistd::Pid::from_raw(child.id() as i32),
        nix::sys::signal::Signal::SIGTERM,
    )
    .unwrap();
    let status = child.wait().unwrap();
    assert!(status.success(), "{status}");
    assert!(
        std::fs::symlink_metadata(&link).is_err(),
        "link left behind"
    );
}

/// How long a `crispen sim` started with `speed_args` takes (real time) over a 4-second
/// dwell (`G4 S4`), and what it said on stderr.
fn dwell_with(speed_args: &[&str]) -> (Duration, String) {
    let dir = tempfile::tempdir().unwrap();
    let link = dir.path().join("ttyCRISPEN");
    let mut child = std::process::Command::new(env!("CARGO_BIN_EXE_crispen"))
        .args(["sim", "--firmware", "ultimaker2"])
        .args(speed_args)
        .arg("--link")
        .arg(&link)
        .stdout(std::process::Stdio::piped())
        .stderr(std::process::Stdio::piped())
        .spawn()
        .unwrap();
    let mut stdout = std::io::BufReader::new(child.stdout.take().unwrap());
    let mut first = String::new();
    std::io::BufRead::read_line(&mut stdout, &mut first).unwrap();
    let mut port = Port::open(&link);
    let start = Instant::now();
    port.send_numbered(1, "G4 S4");
    port.until("ok");
    let took = start.elapsed();
    drop(port);
    nix::sys::signal::kill(
        nix::unistd::Pid::from_raw(child.id() as i32),
        nix::sys::signal::Signal::SIGTERM,
    )
    .unwrap();
    let out = child.wait_with_output().unwrap();
    (took, String::from_utf8_lossy(&out.stderr).into_owned())
}

/// `--speed` is a speed-up factor, higher is faster (`--speed 20`: a 4 s dwell in 0.2 s;
/// `--speed 2`: in 2 s). The old `--time-scale` said "simulated seconds per real second"
/// but was the inverse, so 20 made a demo twenty times slower; it still works (as it
/// always did), with a warning that names `--speed`, and the help shows only `--speed`.
#[test]
fn crispen_sim_speed_is_a_factor_and_time_scale_is_still_read() {
    let (fast, said) = dwell_with(&["--speed", "20"]);
    assert!(fast < Duration::from_millis(1500), "--speed 20: {fast:?}");
    assert!(!said.contains("warning"), "{said}");
    let (slow, _) = dwell_with(&["--speed", "2"]);
    assert!(slow >= Duration::from_millis(1900), "--speed 2: {slow:?}");
    assert!(slow > fast);
    let (old, said) = dwell_with(&["--time-scale", "0.05"]);
    assert!(
        old < Duration::from_millis(1500),
        "--time-scale 0.05: {old:?}"
    );
    assert!(
        said.contains("--time-scale is replaced by --speed")
            && said.contains("--time-scale 0.05 is --speed 20"),
        "{said}"
    );

    let run = |args: &[&str]| {
        std::process::Command::new(env!("CARGO_BIN_EXE_crispen"))
            .args(args)
            .output()
            .unwrap()
    };
    let help = String::from_utf8_lossy(&run(&["sim", "--help"]).stdout).into_owned();
    assert!(
        help.contains("--speed <FACTOR>") && help.contains("20 = twenty times faster"),
        "{help}"
    );
    assert!(!help.contains("--time-scale"), "{help}");
    for bad in [
        &["sim", "--speed", "0"][..],
        &["sim", "--speed", "fast"],
        &["sim", "--speed", "2", "--time-scale", "0.5"],
    ] {
        let out = run(bad);
        assert!(!out.status.success(), "{bad:?}");
        let said = String::from_utf8_lossy(&out.stderr);
        assert!(said.contains("speed"), "{bad:?}: {said}");
    }
}

#[test]
fn link_latency_delays_the_command_and_the_answer() {
    let latency = Duration::from_millis(40);
    let mut cfg = SimConfig::new(Firmware::Marlin2);
    cfg.link_latency = latency;
    let (_sim, mut port) = start(cfg);
    port.handshake();
    let sent = Instant::now();
    port.send_numbered(1, "M105");
    let (_, ok) = port.until("ok");
    let round_trip = sent.elapsed();
    assert_eq!(ok, "ok T:21.00 /0.00 B:21.00 /0.00 @:0 B@:0");
    // The command travels one way, the answer the other.
    assert!(
        round_trip >= latency * 2,
        "M105 answered after {round_trip:?}, sooner than two link latencies of {latency:?}"
    );
}

#[test]
fn baud_limit_paces_the_bytes_on_the_wire() {
    let baud = 1200;
    let mut cfg = SimConfig::new(Firmware::Marlin2);
    cfg.baud = Some(baud);
    let (_sim, mut port) = start(cfg);
    let line = numbered(1, "M105");
    let sent = Instant::now();
    port.send(&line);
    let (_, ok) = port.until("ok");
    let took = sent.elapsed();
    // Both lines with their newline, 10 bits per byte, one after the other.
    let bytes = (line.len() + 1 + ok.len() + 1) as f64;
    let wire = Duration::from_secs_f64(bytes * 10.0 / baud as f64);
    assert!(
        took >= wire,
        "{bytes} bytes at {baud} baud took only {took:?}"
    );
}

#[test]
fn a_fragment_that_is_no_command_is_answered_but_never_executed() {
    // What is left of `N7 G1 X300 F1800*61` when a line error flushed the receive buffer
    // mid-line and corruption took the `*`.
    let (sim, mut port) = start(SimConfig::new(Firmware::Marlin2));
    port.handshake();
    port.send("300 F1800b1");
    let (lines, _) = port.until("ok");
    assert_eq!(lines, ["echo:Unknown command: \"300 F1800b1\""]);
    port.send_numbered(1, "G1 X1");
    port.until("ok");
    assert_eq!(sim.executed(), ["M110 N0", "G1 X1"]);
}

#[test]
fn faults_default_to_none() {
    assert_eq!(Faults::default().reset_after_lines, None);
    assert_eq!(Faults::default().corrupt_host_bytes, 0.0);
    let cfg = SimConfig::new(Firmware::Marlin2);
    assert_eq!((cfg.link_latency, cfg.baud), (Duration::ZERO, None));
    assert!(is_housekeeping("M105") && is_housekeeping("M110 N0") && !is_housekeeping("G1 X1"));
}

// ----- firmware dialects (docs/firmware.md) --------------------------------------------------

/// Ultimaker2Marlin ends a line at `:`: the head fails for want of a checksum, the tail is
/// a checksum without a line number (an error with neither `Resend:` nor `ok`).
#[test]
fn ultimaker2_ends_a_line_at_a_colon_and_refuses_checksums_without_numbers() {
    let (sim, mut port) = start(SimConfig::new(Firmware::Ultimaker2));
    port.handshake();
    port.send_numbered(1, "M117 ETA 01:23");
    let (_, err) = port.until("Error:");
    assert_eq!(err, "Error:No Checksum with line number, Last Line: 0");
    assert_eq!(port.line(WAIT).as_deref(), Some("Resend: 1"));
    assert_eq!(port.line(WAIT).as_deref(), Some("ok"));
    // (The tail `23*..` went with the flush of the receive buffer.) A line with a checksum
    // but no number:
    port.send("G1 X9*12");
    assert_eq!(
        port.line(WAIT).as_deref(),
        Some("Error:No Line Number with checksum")
    );
    assert!(port.drain(Duration::from_millis(200)).is_empty(), "no ok");
    assert!(job_commands(&sim).is_empty());
    // A colon inside a comment does not end the line; but after a `;` the firmware keeps
    // nothing, drops the line, and drops the next one too (`comment_mode` is cleared only by
    // an empty line: Marlin_main.cpp:542-547, 641), as the real firmware does.
    port.send(&format!("{} ; at 01:23", numbered(1, "G1 X1")));
    port.send(&numbered(1, "G1 X1"));
    assert!(port.drain(Duration::from_millis(300)).is_empty());
    assert!(job_commands(&sim).is_empty());
    port.send(&numbered(1, "G1 X1"));
    port.until("ok");
    assert_eq!(job_commands(&sim), ["G1 X1"]);
}

/// Marlin 2 runs a line without `N` unchecked; 2.1 ignores a repeated line number silently,
/// 2.0 asks for the expected line.
#[test]
fn marlin2_runs_unnumbered_lines_and_21_ignores_duplicates() {
    for fw in [Firmware::Marlin2, Firmware::Marlin20] {
        let (sim, mut port) = start(SimConfig::new(fw));
        port.handshake();
        port.send("G1 X7*99");
        port.until("ok");
        port.send_numbered(1, "G1 X1");
        port.until("ok");
        port.send_numbered(1, "G1 X1");
        let said = port.drain(Duration::from_millis(300));
        if fw.ignores_duplicate_lines() {
            assert!(said.is_empty(), "{fw}: {said:?}");
        } else {
            assert!(said.iter().any(|l| l == "Resend: 2"), "{fw}: {said:?}");
        }
        assert_eq!(job_commands(&sim), ["G1 X7", "G1 X1"], "{fw}");
    }
}

/// NO_TIMEOUTS: `wait` only while the queue is empty.
#[test]
fn wait_when_idle_only_while_the_queue_is_empty() {
    let mut cfg = SimConfig::new(Firmware::Marlin2);
    cfg.time_scale = 1.0;
    cfg.wait_when_idle = Some(Duration::from_millis(100));
    let (_sim, mut port) = start(cfg);
    port.handshake();
    // Two `wait`s in a row while idle; the deadline is only a bound for a loaded machine.
    let until = Instant::now() + Duration::from_secs(10);
    let mut said = Vec::new();
    while said.iter().filter(|l| *l == "wait").count() < 2 {
        match port.line(until.saturating_duration_since(Instant::now())) {
            Some(line) => said.push(line),
            None => panic!("fewer than two `wait`s while idle: {said:?}"),
        }
    }
    assert!(said.iter().all(|l| l == "wait"), "{said:?}");
    // G4 S1 holds the queue for a second: busy keep-alives, no `wait`, until it ends.
    port.send_numbered(1, "G4 S1");
    let (before, _) = port.until("ok");
    assert!(!before.iter().any(|l| l == "wait"), "{before:?}");
}

/// The printer's own Stop/Pause menu items, on demand after N lines; and the Ultimaker 2's
/// heat-wait report without a target, with moves acknowledged as they enter the queue
/// (before the M109 ahead of them finishes).
#[test]
fn host_actions_on_demand_and_ultimaker2_heating() {
    let mut cfg = SimConfig::new(Firmware::Ultimaker2);
    cfg.time_scale = 0.05;
    // After the M110 and the M109 (counted when it starts).
    cfg.faults.actions = vec![(2, "pause".into())];
    let (_sim, mut port) = start(cfg);
    port.handshake();
    port.send_raw(
        format!(
            "{}\n{}\n",
            numbered(1, "M109 S60"),
            numbered(2, "G1 X5 F3000")
        )
        .as_bytes(),
    );
    let (before, _) = port.until("//action:pause");
    let (during, _) = port.until("T:");
    let mut lines: Vec<String> = before.into_iter().chain(during).collect();
    lines.extend(port.drain(Duration::from_secs(3)));
    let first_ok = lines.iter().position(|l| l == "ok").expect("the G1's ok");
    let report = lines
        .iter()
        .position(|l| l.ends_with("E:0 W:?"))
        .unwrap_or_else(|| panic!("no UM2 heat report: {lines:?}"));
    assert!(first_ok < report, "the move's ok came at entry: {lines:?}");
    assert!(lines[report].starts_with("T:") && !lines[report].contains('/'));
    assert_eq!(lines.iter().filter(|l| *l == "ok").count(), 2, "{lines:?}");
}

/// Opening the port resets the board: input during the bootloader delay is lost, then
/// `start`.
#[test]
fn reset_on_open_loses_input_until_start() {
    let mut cfg = SimConfig::new(Firmware::Marlin2);
    cfg.reset_on_open = Some(Duration::from_millis(800));
    let (sim, mut port) = start(cfg);
    let opened = Instant::now();
    port.send_numbered(0, "M110 N0");
    let (_, start) = port.until("start");
    assert_eq!(start, "start");
    assert!(opened.elapsed() >= Duration::from_millis(700));
    assert!(sim.executed().is_empty(), "the bootloader ran nothing");
    port.handshake();
    assert_eq!(sim.executed(), ["M110 N0"]);
}

/// The dialect switches of `crispen sim`: a Marlin 2.0 that says `wait` when idle and
/// resets on open, with host actions on demand; and clear refusals of bad values.
#[test]
fn crispen_sim_switches_for_firmware_behaviours() {
    let exe = env!("CARGO_BIN_EXE_crispen");
    let mut child = std::process::Command::new(exe)
        .args([
            "sim",
            "--firmware",
            "marlin20",
            "--time-scale",
            "0",
            "--wait-when-idle-ms",
            "100",
            "--reset-on-open-ms",
            "300",
            "--action-after",
            "1:cancel",
        ])
        .stdout(std::process::Stdio::piped())
        .stderr(std::process::Stdio::null())
        .spawn()
        .unwrap();
    let mut stdout = std::io::BufReader::new(child.stdout.take().unwrap());
    let mut first = String::new();
    std::io::BufRead::read_line(&mut stdout, &mut first).unwrap();
    let device = first
        .trim_end()
        .strip_prefix("crispen sim: listening on ")
        .unwrap_or_else(|| panic!("first line: {first:?}"))
        .to_string();
    let mut port = Port::open(Path::new(&device));
    port.until("start");
    port.until("wait");
    port.send_numbered(0, "M110 N0");
    port.until("//action:cancel");
    port.until("ok");
    port.send_numbered(1, "M115");
    let (lines, _) = port.until("ok");
    assert!(lines.iter().any(|l| l.contains("Marlin 2.0")), "{lines:?}");
    drop(port);
    nix::sys::signal::kill(
        nix::unistd::Pid::from_raw(child.id() as i32),
        nix::sys::signal::Signal::SIGTERM,
    )
    .unwrap();
    assert!(child.wait().unwrap().success());

    for (flag, value, says) in [
        ("--action-after", "pause", "expected N:NAME"),
        ("--action-after", "3:pa use", "action name"),
        ("--wait-when-idle-ms", "0", "flood"),
    ] {
        let out = std::process::Command::new(exe)
            .args(["sim", flag, value])
            .output()
            .unwrap();
        assert!(!out.status.success(), "{flag} {value}");
        let stderr = String::from_utf8_lossy(&out.stderr);
        assert!(stderr.contains(says), "{flag} {value}: {stderr}");
    }
}

/// Marlin checks a line's number before its checksum; a line longer than MAX_CMD_SIZE is
/// cut, losing its `*cs`; Marlin 2.0 sends no `ok` after `Resend:`, 2.1 does.
#[test]
fn marlin_checks_the_number_first_cuts_long_lines_and_20_sends_no_ok_after_resend() {
    for fw in [Firmware::Marlin2, Firmware::Marlin20] {
        let (sim, mut port) = start(SimConfig::new(fw));
        port.handshake();
        port.send_numbered(1, "G1 X1");
        port.until("ok");
        // Wrong number and wrong checksum: the number is what is reported.
        port.send("N5 G1 X5*1");
        let (_, err) = port.until("Error:");
        assert!(err.starts_with("Error:Line Number is not"), "{fw}: {err}");
        assert_eq!(port.line(WAIT).as_deref(), Some("Resend: 2"), "{fw}");
        let after = port.drain(Duration::from_millis(300));
        assert_eq!(
            after.iter().any(|l| l.starts_with("ok")),
            fw.ok_after_resend(),
            "{fw}: {after:?}"
        );
        // 96 bytes and more: cut before the checksum.
        port.send_numbered(2, &format!("M117 {}", "x".repeat(95)));
        let (_, err) = port.until("Error:");
        assert!(
            err.starts_with("Error:No Checksum with line number"),
            "{fw}: {err}"
        );
        port.drain(Duration::from_millis(300));
        assert_eq!(job_commands(&sim), ["G1 X1"], "{fw}");
    }
}

/// Pokes act at once, as a person at the printer: a firmware error, the menu's host
/// actions, and the reset button (line numbers forgotten, `start` said).
#[test]
fn pokes_report_errors_send_actions_and_reset_at_once() {
    let (sim, mut port) = start(SimConfig::new(Firmware::Marlin2));
    port.handshake();
    port.send_numbered(1, "G1 X1");
    port.until("ok");
    assert!(sim.poke("error Probing Failed".parse().unwrap()));
    assert_eq!(port.until("Error:").1, "Error:Probing Failed");
    assert!(sim.poke("action pause".parse().unwrap()));
    port.until("//action:pause");
    assert!(sim.poke(sim::Poke::Reset));
    port.until("start");
    // Numbering starts over: line 1 is expected again.
    port.send_numbered(1, "G1 X2");
    port.until("ok");
    assert_eq!(job_commands(&sim), ["G1 X1", "G1 X2"]);
    assert!("bogus".parse::<sim::Poke>().is_err());
    assert!("action".parse::<sim::Poke>().is_err());
}

/// The pauses a file may ask for, as the real firmware answers them (docs/firmware.md):
/// a host that forwarded one would wait for an `ok` that only the knob brings, or lose the
/// pause to `Unknown command`.
#[test]
fn file_pauses_wait_for_the_knob_or_are_unknown_per_firmware() {
    // Marlin 2 with a display: M0 waits, saying so every keep-alive interval, and never `ok`.
    let mut cfg = SimConfig::new(Firmware::Marlin2);
    cfg.time_scale = 1.0;
    let (sim, mut port) = start(cfg.clone());
    port.handshake();
    port.send_numbered(1, "M0 Insert magnets");
    let (before, _) = port.until("echo:busy: paused for user");
    assert!(before.iter().all(|l| !l.starts_with("ok")), "{before:?}");
    assert!(port
        .drain(Duration::from_millis(300))
        .iter()
        .all(|l| !l.starts_with("ok")));
    drop((sim, port));

    // Stock Marlin 2.1 (no ADVANCED_PAUSE_FEATURE, SDSUPPORT, ...): unknown, the pause lost.
    let (_sim, mut port) = start(cfg.clone());
    port.handshake();
    for (n, cmd) in [(1, "M600"), (2, "M25"), (3, "M601"), (4, "M125")] {
        port.send_numbered(n, cmd);
        port.until(&format!("echo:Unknown command: \"{cmd}\""));
        port.until("ok");
    }

    // With ADVANCED_PAUSE_FEATURE, M600 parks and waits for the user.
    let mut advanced = cfg.clone();
    advanced.advanced_pause = true;
    let (_sim, mut port) = start(advanced);
    port.handshake();
    port.send_numbered(1, "M600");
    let (before, _) = port.until("echo:busy: paused for user");
    assert!(before.iter().all(|l| !l.starts_with("ok")), "{before:?}");

    // Ultimaker2Marlin: M0 waits in silence (no busy protocol); M600 and M25 answer `ok`.
    let mut um2 = SimConfig::new(Firmware::Ultimaker2);
    um2.time_scale = 1.0;
    let (_sim, mut port) = start(um2.clone());
    port.handshake();
    port.send_numbered(1, "M600");
    port.until("ok");
    port.send_numbered(2, "M25");
    port.until("ok");
    port.send_numbered(3, "M0");
    assert!(port.drain(Duration::from_millis(500)).is_empty());
}
