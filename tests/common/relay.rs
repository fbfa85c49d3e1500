//! A fault-injecting serial relay between a host and the real printer firmware, for the
//! tests that run crispen against the firmware itself (`CRISPEN_FIRMWARE_DIR`).
//!
//! The firmware is served on a pty by the scripts that come with it (`serve-marlin VARIANT
//! LINK`, `serve-ultimaker2 LINK`); the relay opens that pty like a host would (which boots
//! the firmware, as DTR resets a board), and offers the host a pty of its own. Everything
//! crossing it goes through seeded faults: corrupted bytes and whole lines lost on the way
//! to the printer, bursts of consecutive corrupted lines, lost `ok`s and garbled answers on
//! the way back, a delay each way, and a port that closes in the middle of a job. The
//! firmware's own answers are recorded before any fault touches them, so a test reads the
//! printer's real final `M114` position, whatever the host saw.
#![allow(dead_code)] // each test binary uses its own part of this module

use crispen::marlin::gcode::GcodeProgram;
use crispen::marlin::stream::{Connection, PrintError, PrintProgress, PrintReport, StreamOptions};
use nix::fcntl::{fcntl, FcntlArg, OFlag};
use nix::poll::{poll, PollFd, PollFlags, PollTimeout};
use nix::sys::termios;
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use std::collections::VecDeque;
use std::fs::File;
use std::io::Read;
use std::os::fd::{AsFd, OwnedFd};
use std::os::unix::process::CommandExt;
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, Mutex};
use std::thread::JoinHandle;
use std::time::{Duration, Instant};
use tokio::sync::{mpsc, watch};

/// The real firmware this machine has, from `CRISPEN_FIRMWARE_DIR`. The tests that call
/// this are `ignore`d where the variable was unset at build time (`build.rs` sets the
/// `crispen_firmware` cfg), so this is reached without it only through `--ignored`.
pub fn firmware_dir() -> PathBuf {
    let dir = std::env::var_os("CRISPEN_FIRMWARE_DIR")
        .filter(|dir| !dir.is_empty())
        .map(PathBuf::from)
        .expect(
            "set CRISPEN_FIRMWARE_DIR to the folder with the real firmware \
             (serve-marlin, ultimaker2/serve-ultimaker2) to run this test",
        );
    assert!(
        dir.join("serve-marlin").exists(),
        "CRISPEN_FIRMWARE_DIR={} has no serve-marlin",
        dir.display()
    );
    dir
}

/// Which real firmware to serve.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Build {
    /// Marlin 2.1.2.1, stock (no ADVANCED_OK).
    Default,
    /// Marlin 2.1.2.1 with ADVANCED_OK.
    AdvOk,
    /// Marlin 2.1.2.1 with NO_TIMEOUTS: says `wait` when idle.
    Wait,
    /// Ultimaker2Marlin in the AVR emulator, at the board's own pace.
    Ultimaker2,
}

impl Build {
    pub const ALL: [Build; 4] = [Build::Default, Build::AdvOk, Build::Wait, Build::Ultimaker2];
    pub const MARLIN: [Build; 3] = [Build::Default, Build::AdvOk, Build::Wait];

    pub fn name(self) -> &'static str {
        match self {
            Build::Default => "marlin-2.1.2.1-default",
            Build::AdvOk => "marlin-2.1.2.1-advok",
            Build::Wait => "marlin-2.1.2.1-wait",
            Build::Ultimaker2 => "ultimaker2marlin",
        }
    }
}

/// What to do wrong, per line. Probabilities are per line crossing in that direction.
#[derive(Debug, Clone, Default)]
pub struct RelayFaults {
    pub seed: u64,
    /// A numbered host line arrives with one byte changed (never into a line ending).
    pub corrupt_line: f64,
    /// A numbered host line has one of its `.` turned into `*` (what Ultimaker2Marlin's
    /// first-`*` checksum can let through as a cut line).
    pub star_for_dot: f64,
    /// A numbered host line is lost whole: the printer sees the next one's number first and
    /// asks for it again (a resend the host did not cause).
    pub drop_line: f64,
    /// From the N-th numbered host line on, this many consecutive numbered lines arrive
    /// corrupted: `(N, count)`.
    pub burst: Option<(u64, u64)>,
    /// An `ok` from the printer is lost.
    pub lose_ok: f64,
    /// A line from the printer arrives with one byte changed.
    pub garble_reply: f64,
    /// Each line takes this long each way, plus up to `jitter` more (order is kept).
    pub delay: Duration,
    pub jitter: Duration,
    /// Close the host's port after this many numbered host lines (an unplugged cable).
    pub close_after: Option<u64>,
    /// Once a host line containing the first text crosses, the second is sent to the
    /// printer right behind it, once: a line slipped in between the host's (a second
    /// writer on the port), e.g. one with `M110` in it that renumbers Marlin.
    pub inject: Option<(String, String)>,
    /// Once a host line containing the text crosses, what the printer says within the
    /// given time after reaches the host only then (in order): a printer that answers late,
    /// as one busy with a command of its own or an emulator starved of the CPU does.
    pub hold_replies: Option<(String, Duration)>,
}

/// What the relay saw.
#[derive(Debug, Default, Clone)]
pub struct RelayLog {
    /// Every line the firmware wrote, before any fault.
    pub printer_lines: Vec<String>,
    /// Numbered host lines that crossed (before faults).
    pub host_lines: u64,
    pub corrupted: u64,
    pub dropped: u64,
    pub lost_oks: u64,
    pub garbled: u64,
    /// The host's port was closed by the `close_after` fault.
    pub closed: bool,
    /// Every line each way with its time since the relay started, as it crossed (after
    /// faults): `>` to the printer, `<` to the host.
    pub wire: Vec<(f64, char, String)>,
    /// How many lines the firmware had written when the first `M114` crossed to it: its
    /// answer comes after them (the job asks for the position once).
    pub m114_at: Option<usize>,
}

impl RelayLog {
    /// The firmware's answer to the last `M114` that crossed to it, once it has come.
    pub fn answered_position(&self) -> Option<[f64; 3]> {
        self.printer_lines[self.m114_at?..]
            .iter()
            .find_map(|l| parse_position(l))
    }

    /// The last `X:… Y:… Z:…` position the firmware reported (its answer to `M114`).
    pub fn last_position(&self) -> Option<[f64; 3]> {
        self.printer_lines
            .iter()
            .rev()
            .find_map(|l| parse_position(l))
    }
}

/// `X:1.00 Y:0.00 Z:0.00 E:0.00 Count X:80 …` (Marlin) or `X:101.00Y:98.00Z:10.00E:0.00
/// Count …` (Ultimaker2Marlin).
pub fn parse_position(line: &str) -> Option<[f64; 3]> {
    let [x, y, z, _] = parse_position_e(line)?;
    Some([x, y, z])
}

/// [`parse_position`] with the extruder's position (`E:`) too.
pub fn parse_position_e(line: &str) -> Option<[f64; 4]> {
    let head = line.split("Count").next()?;
    if !head.starts_with("X:") {
        return None;
    }
    let mut out = [0.0; 4];
    for (i, axis) in ["X:", "Y:", "Z:", "E:"].iter().enumerate() {
        let at = head.find(axis)? + 2;
        let rest = &head[at..];
        let end = rest
            .find(|c: char| !(c.is_ascii_digit() || c == '.' || c == '-'))
            .unwrap_or(rest.len());
        out[i] = rest[..end].parse().ok()?;
    }
    Some(out)
}

/// A served firmware behind a fault-injecting relay. Dropping it stops both.
pub struct Relay {
    device: PathBuf,
    log: Arc<Mutex<RelayLog>>,
    /// Lines the test itself sends to the firmware (see [`Relay::ask`]).
    direct: Arc<Mutex<Vec<u8>>>,
    stop: Arc<AtomicBool>,
    thread: Option<JoinHandle<()>>,
    server: Child,
    dir: tempfile::TempDir,
    _slot: Slot,
}

/// Firmware instances running at once in this test process, at most one per core
/// (`CRISPEN_FIRMWARE_AT_ONCE` overrides). Each keeps its printer's real time only with
/// its share of a core (the AVR emulator alone takes about 40 % of one): a starved
/// firmware boots and answers slower than any real printer, and the host rightly gives up
/// on it, which would test the machine's load rather than the host.
static RUNNING: (Mutex<usize>, std::sync::Condvar) = (Mutex::new(0), std::sync::Condvar::new());

/// One firmware's place among [`RUNNING`], given back when dropped: held by each relay,
/// and by a test that runs a firmware itself.
pub struct Slot;

impl Slot {
    pub fn take() -> Slot {
        let limit = std::env::var("CRISPEN_FIRMWARE_AT_ONCE")
            .ok()
            .and_then(|v| v.parse::<usize>().ok())
            .unwrap_or_else(|| std::thread::available_parallelism().map_or(2, |n| n.get()))
            .max(1);
        let (running, freed) = &RUNNING;
        let mut n = running.lock().unwrap_or_else(|e| e.into_inner());
        while *n >= limit {
            n = freed.wait(n).unwrap_or_else(|e| e.into_inner());
        }
        *n += 1;
        Slot
    }
}

impl Drop for Slot {
    fn drop(&mut self) {
        let (running, freed) = &RUNNING;
        *running.lock().unwrap_or_else(|e| e.into_inner()) -= 1;
        freed.notify_one();
    }
}

impl Relay {
    /// Serve `build` from `firmware` and put the relay in front of it. The firmware boots
    /// when the host opens [`Relay::device_path`].
    pub fn start(firmware: &Path, build: Build, faults: RelayFaults) -> Relay {
        let slot = Slot::take();
        let dir = tempfile::tempdir().unwrap();
        let link = dir.path().join("printer");
        let mut cmd = match build {
            Build::Ultimaker2 => {
                let mut c = Command::new(firmware.join("ultimaker2/serve-ultimaker2"));
                // The emulator's own log of the wire (see `Relay::ring_overruns`).
                c.arg(&link).arg("--tap").arg(dir.path().join(TAP));
                c
            }
            _ => {
                let variant = match build {
                    Build::Default => "default",
                    Build::AdvOk => "advok",
                    _ => "wait",
                };
                let mut c = Command::new(firmware.join("serve-marlin"));
                c.arg(variant).arg(&link);
                c
            }
        };
        // A process group of its own, so the script, socat and the firmware end together.
        let server = cmd
            .process_group(0)
            .stdin(Stdio::null())
            .stdout(Stdio::null())
            .stderr(Stdio::inherit())
            .spawn()
            .unwrap_or_else(|e| panic!("starting {}: {e}", build.name()));
        let deadline = Instant::now() + Duration::from_secs(20);
        while !link.exists() {
            assert!(
                Instant::now() < deadline,
                "{}: no pty at {}",
                build.name(),
                link.display()
            );
            std::thread::sleep(Duration::from_millis(20));
        }

        let pty = crispen::sim::open_pty().expect("a pty for the host side");
        let mut attrs = termios::tcgetattr(&pty.slave).unwrap();
        termios::cfmakeraw(&mut attrs);
        termios::tcsetattr(&pty.slave, termios::SetArg::TCSANOW, &attrs).unwrap();
        let device = nix::unistd::ttyname(&pty.slave).unwrap();
        // Without our slave descriptor the master reports a hang-up until the host opens it.
        drop(pty.slave);
        set_nonblocking(&pty.master);

        let log = Arc::new(Mutex::new(RelayLog::default()));
        let stop = Arc::new(AtomicBool::new(false));
        let direct = Arc::new(Mutex::new(Vec::new()));
        let thread = {
            let log = log.clone();
            let stop = stop.clone();
            let direct = direct.clone();
            let master = pty.master;
            std::thread::spawn(move || run(master, link, faults, log, stop, direct))
        };
        Relay {
            device,
            log,
            direct,
            stop,
            thread: Some(thread),
            server,
            dir,
            _slot: slot,
        }
    }

    pub fn device_path(&self) -> &Path {
        &self.device
    }

    pub fn log(&self) -> RelayLog {
        self.log.lock().unwrap().clone()
    }

    /// Ultimaker2Marlin's own record of its receive ring overflowing: each line of its tap
    /// (`um2sim --tap`) that lost bytes, with the bytes lost. The emulator notes the loss
    /// on the line the surviving bytes make up, so a loss shows once a later line arrived
    /// whole (a job's final `M114` does). Empty for the Linux builds, which have no tap.
    pub fn ring_overruns(&self) -> Vec<String> {
        std::fs::read_to_string(self.dir.path().join(TAP))
            .unwrap_or_default()
            .lines()
            .filter(|l| l.contains("dropped: RX ring full"))
            .map(str::to_string)
            .collect()
    }

    /// Asks the firmware itself, past the host: sends `line` (unnumbered) and returns the
    /// first line it writes afterwards that starts with `answer`, waiting up to `limit`.
    /// The host's port must still be open (the relay ends the firmware's with it).
    pub fn ask(&self, line: &str, answer: &str, limit: Duration) -> Option<String> {
        let from = self.log().printer_lines.len();
        self.direct
            .lock()
            .unwrap()
            .extend_from_slice(format!("{line}\n").as_bytes());
        let deadline = Instant::now() + limit;
        loop {
            let log = self.log();
            if let Some(l) = log.printer_lines[from..]
                .iter()
                .find(|l| l.starts_with(answer))
            {
                return Some(l.clone());
            }
            if Instant::now() >= deadline {
                return None;
            }
            std::thread::sleep(Duration::from_millis(10));
        }
    }

    /// Waits (up to `limit`) for the firmware's own answer to the last `M114` sent to it
    /// (after an `M400`, it is the position once every move ran), and returns the log
    /// with it; the log as it is when no answer came.
    pub fn wait_position(&self, limit: Duration) -> RelayLog {
        self.wait_until(limit, |log| log.answered_position().is_some())
    }

    /// Waits (up to `limit`) until the log shows `done`, and returns it; the log as it is
    /// when it never did.
    pub fn wait_until(&self, limit: Duration, done: impl Fn(&RelayLog) -> bool) -> RelayLog {
        let deadline = Instant::now() + limit;
        loop {
            let log = self.log();
            if done(&log) || Instant::now() >= deadline {
                return log;
            }
            std::thread::sleep(Duration::from_millis(10));
        }
    }
}

impl Drop for Relay {
    fn drop(&mut self) {
        self.stop.store(true, Ordering::SeqCst);
        if let Some(t) = self.thread.take() {
            let _ = t.join();
        }
        // The whole group this relay started: the serve script, socat or um2sim, firmware.
        let pgid = nix::unistd::Pid::from_raw(self.server.id() as i32);
        let _ = nix::sys::signal::killpg(pgid, nix::sys::signal::Signal::SIGTERM);
        let _ = self.server.wait();
    }
}

/// The file in the relay's folder where the Ultimaker 2 emulator logs the wire.
const TAP: &str = "tap.txt";

fn set_nonblocking(fd: &OwnedFd) {
    let flags = fcntl(fd, FcntlArg::F_GETFL).unwrap();
    fcntl(
        fd,
        FcntlArg::F_SETFL(OFlag::from_bits_truncate(flags) | OFlag::O_NONBLOCK),
    )
    .unwrap();
}

/// One direction: bytes gathered into lines, each due at a time of its own.
struct Lane {
    partial: Vec<u8>,
    queue: VecDeque<(Instant, Vec<u8>)>,
}

impl Lane {
    fn new() -> Self {
        Lane {
            partial: Vec::new(),
            queue: VecDeque::new(),
        }
    }

    fn lines(&mut self, bytes: &[u8]) -> Vec<Vec<u8>> {
        let mut out = Vec::new();
        for &b in bytes {
            self.partial.push(b);
            if b == b'\n' {
                out.push(std::mem::take(&mut self.partial));
            }
        }
        out
    }

    fn push(&mut self, due: Instant, line: Vec<u8>) {
        // Never overtake the line before it.
        let due = self.queue.back().map_or(due, |(d, _)| due.max(*d));
        self.queue.push_back((due, line));
    }

    fn due(&mut self, now: Instant) -> Vec<u8> {
        let mut out = Vec::new();
        while self.queue.front().is_some_and(|(d, _)| *d <= now) {
            out.extend(self.queue.pop_front().unwrap().1);
        }
        out
    }
}

fn corrupt(rng: &mut ChaCha8Rng, line: &mut [u8]) {
    let body = line.len().saturating_sub(1).max(1);
    let at = rng.random_range(0..body);
    loop {
        let b: u8 = rng.random_range(1..=255);
        if b != line[at] && b != b'\n' && b != b'\r' {
            line[at] = b;
            return;
        }
    }
}

fn write_all<F: AsFd>(fd: F, mut bytes: &[u8], stop: &AtomicBool) -> bool {
    while !bytes.is_empty() {
        match nix::unistd::write(fd.as_fd(), bytes) {
            Ok(n) => bytes = &bytes[n..],
            Err(nix::errno::Errno::EAGAIN) => {
                if stop.load(Ordering::SeqCst) {
                    return false;
                }
                std::thread::sleep(Duration::from_millis(1));
            }
            Err(_) => return false,
        }
    }
    true
}

fn run(
    master: OwnedFd,
    link: PathBuf,
    faults: RelayFaults,
    log: Arc<Mutex<RelayLog>>,
    stop: Arc<AtomicBool>,
    direct: Arc<Mutex<Vec<u8>>>,
) {
    let mut rng = ChaCha8Rng::seed_from_u64(faults.seed);
    let mut inject = faults.inject.clone();
    let mut hold = faults.hold_replies.clone();
    let mut held_until: Option<Instant> = None;
    let mut master = Some(master);
    let mut printer: Option<File> = None;
    let mut to_printer = Lane::new();
    let mut to_host = Lane::new();
    let mut buf = [0u8; 4096];
    let mut numbered = 0u64;
    let born = Instant::now();
    let delay = |rng: &mut ChaCha8Rng| {
        let jitter = if faults.jitter.is_zero() {
            Duration::ZERO
        } else {
            faults.jitter.mul_f64(rng.random::<f64>())
        };
        faults.delay + jitter
    };
    while !stop.load(Ordering::SeqCst) {
        let Some(host) = master.as_ref() else {
            std::thread::sleep(Duration::from_millis(10));
            continue;
        };
        let now = Instant::now();
        let next_due = [to_printer.queue.front(), to_host.queue.front()]
            .into_iter()
            .flatten()
            .map(|(d, _)| *d)
            .min();
        let wait_ms = next_due.map_or(20, |d| {
            (d.saturating_duration_since(now).as_millis() as u64).clamp(0, 20)
        });
        let (host_events, printer_events) = {
            let mut fds = vec![PollFd::new(host.as_fd(), PollFlags::POLLIN)];
            if let Some(p) = &printer {
                fds.push(PollFd::new(p.as_fd(), PollFlags::POLLIN));
            }
            let _ = poll(&mut fds, PollTimeout::from(wait_ms as u16));
            (
                fds[0].revents().unwrap_or(PollFlags::empty()),
                fds.get(1).and_then(|f| f.revents()),
            )
        };
        let host_hup = host_events.contains(PollFlags::POLLHUP);
        if printer.is_none() {
            if host_hup {
                continue; // nobody has the port open yet
            }
            // The host opened the port: open the printer's, which boots its firmware.
            let f = std::fs::OpenOptions::new()
                .read(true)
                .write(true)
                .open(&link)
                .unwrap_or_else(|e| panic!("opening the firmware's pty {}: {e}", link.display()));
            let mut attrs = termios::tcgetattr(&f).unwrap();
            termios::cfmakeraw(&mut attrs);
            termios::tcsetattr(&f, termios::SetArg::TCSANOW, &attrs).unwrap();
            let flags = fcntl(&f, FcntlArg::F_GETFL).unwrap();
            fcntl(
                &f,
                FcntlArg::F_SETFL(OFlag::from_bits_truncate(flags) | OFlag::O_NONBLOCK),
            )
            .unwrap();
            printer = Some(f);
            continue;
        }
        if host_events.contains(PollFlags::POLLIN) {
            if let Ok(n) = nix::unistd::read(host, &mut buf) {
                let now = Instant::now();
                for mut line in to_printer.lines(&buf[..n]) {
                    let mut log = log.lock().unwrap();
                    if line.first() == Some(&b'N') {
                        numbered += 1;
                        log.host_lines = numbered;
                        let in_burst = faults.burst.is_some_and(|(from, count)| {
                            numbered >= from && numbered < from + count
                        });
                        let dots: Vec<usize> =
                            (0..line.len()).filter(|&i| line[i] == b'.').collect();
                        if !dots.is_empty() && rng.random::<f64>() < faults.star_for_dot {
                            let at = dots[rng.random_range(0..dots.len())];
                            line[at] = b'*';
                            log.corrupted += 1;
                        } else if in_burst || rng.random::<f64>() < faults.corrupt_line {
                            corrupt(&mut rng, &mut line);
                            log.corrupted += 1;
                        } else if rng.random::<f64>() < faults.drop_line {
                            log.dropped += 1;
                            continue;
                        }
                    }
                    // The first crossing: a replay after the answer (the host honouring a
                    // resend request that proves stale; the firmware refuses the line by
                    // its number) must not hide the answer.
                    if log.m114_at.is_none() && line.windows(4).any(|w| w == b"M114") {
                        log.m114_at = Some(log.printer_lines.len());
                    }
                    let due = now + delay(&mut rng);
                    let at = (now - born).as_secs_f64();
                    log.wire.push((
                        at,
                        '>',
                        String::from_utf8_lossy(&line).trim_end().to_string(),
                    ));
                    if let Some((_, held)) =
                        hold.take_if(|(after, _)| String::from_utf8_lossy(&line).contains(&**after))
                    {
                        held_until = Some(now + held);
                    }
                    let slipped = inject
                        .take_if(|(after, _)| String::from_utf8_lossy(&line).contains(&**after));
                    to_printer.push(due, line);
                    if let Some((_, extra)) = slipped {
                        log.wire.push((at, '>', format!("{extra} (slipped in)")));
                        to_printer.push(due, format!("{extra}\n").into_bytes());
                    }
                }
            }
        }
        if faults.close_after.is_some_and(|n| numbered >= n) {
            log.lock().unwrap().closed = true;
            master = None; // the host's reads and writes now fail: an unplugged cable
            printer = None;
            continue;
        }
        if host_hup && printer.is_some() && host_events.contains(PollFlags::POLLHUP) {
            // The host closed the port: end this connection (the firmware's pty closes).
            if !host_events.contains(PollFlags::POLLIN) {
                printer = None;
                master = None;
                continue;
            }
        }
        if printer_events.is_some_and(|e| e.intersects(PollFlags::POLLIN | PollFlags::POLLHUP)) {
            let p = printer.as_mut().unwrap();
            match p.read(&mut buf) {
                Ok(0) => {}
                Ok(n) => {
                    let now = Instant::now();
                    for mut line in to_host.lines(&buf[..n]) {
                        let mut log = log.lock().unwrap();
                        let text = String::from_utf8_lossy(&line).trim_end().to_string();
                        let is_ok = text.starts_with("ok");
                        log.printer_lines.push(text);
                        if is_ok && rng.random::<f64>() < faults.lose_ok {
                            log.lost_oks += 1;
                            continue;
                        }
                        if rng.random::<f64>() < faults.garble_reply {
                            corrupt(&mut rng, &mut line);
                            log.garbled += 1;
                        }
                        let due = now + delay(&mut rng);
                        let due = held_until.filter(|&u| now < u).map_or(due, |u| due.max(u));
                        let at = (now - born).as_secs_f64();
                        log.wire.push((
                            at,
                            '<',
                            String::from_utf8_lossy(&line).trim_end().to_string(),
                        ));
                        to_host.push(due, line);
                    }
                }
                Err(_) => {}
            }
        }
        let asked = std::mem::take(&mut *direct.lock().unwrap());
        if !asked.is_empty() {
            if let Some(p) = &printer {
                write_all(p, &asked, &stop);
            }
        }
        let now = Instant::now();
        let out = to_printer.due(now);
        if !out.is_empty() {
            if let Some(p) = &printer {
                write_all(p, &out, &stop);
            }
        }
        let out = to_host.due(now);
        if !out.is_empty() && !write_all(host, &out, &stop) {
            // The host is gone; what it would have read is lost with the cable.
        }
    }
}

// Jobs through the relay: what the firmware tests and the recovery benchmark run.

/// `moves` short relative moves, then the position asked for; and the position they end at.
pub fn job(moves: usize) -> (String, [f64; 3]) {
    let mut text = String::from("G92 X0 Y0 Z0\nG91\n");
    let (mut x, mut y) = (0i64, 0i64); // in hundredths of a millimetre
    for i in 0..moves {
        let dx = (i % 3 + 1) as i64;
        let dy = (i % 4 + 1) as i64;
        x += dx;
        y += dy;
        text.push_str(&format!("G1 X0.{dx:02} Y0.{dy:02} F6000\n"));
    }
    text.push_str("G90\nM400\nM114\n");
    (text, [x as f64 / 100.0, y as f64 / 100.0, 0.0])
}

pub fn firmware(build: Build) -> crispen::marlin::firmware::Firmware {
    match build {
        Build::Ultimaker2 => crispen::marlin::firmware::Firmware::Ultimaker2,
        _ => crispen::marlin::firmware::Firmware::Marlin2,
    }
}

pub struct Outcome {
    pub result: Result<PrintReport, PrintError>,
    pub log: RelayLog,
    pub took: Duration,
}

pub async fn print_through(
    dir: &std::path::Path,
    build: Build,
    faults: RelayFaults,
    moves: usize,
) -> Outcome {
    print_through_with(dir, build, faults, moves, |_| {}).await
}

/// [`print_through`] with the host's options changed by `tweak`.
pub async fn print_through_with(
    dir: &std::path::Path,
    build: Build,
    faults: RelayFaults,
    moves: usize,
    tweak: impl FnOnce(&mut StreamOptions),
) -> Outcome {
    let relay = Relay::start(dir, build, faults);
    let (text, _) = job(moves);
    let fw = firmware(build);
    let program = GcodeProgram::read(text.as_bytes(), "job.gcode", fw).unwrap();
    let mut opts = StreamOptions::for_firmware(fw);
    tweak(&mut opts);
    let started = Instant::now();
    let (result, log) = print_program(&relay, &program, &opts).await;
    let took = started.elapsed();
    Outcome { result, log, took }
}

/// Connects through `relay` and prints `program` (within 10 minutes); then the relay's
/// log with the firmware's own answer to the job's final M114 (it is recorded before any
/// fault touches it, so it comes whatever the host saw).
pub async fn print_program(
    relay: &Relay,
    program: &GcodeProgram,
    opts: &StreamOptions,
) -> (Result<PrintReport, PrintError>, RelayLog) {
    let result = async {
        let mut conn = Connection::open(relay.device_path(), opts).await?;
        let (_control, control_rx) = mpsc::channel(1);
        let (progress, _) = watch::channel(PrintProgress::default());
        conn.print(program, control_rx, progress).await
    };
    let result = tokio::time::timeout(Duration::from_secs(600), result)
        .await
        .unwrap_or_else(|_| panic!("{}: no end after 10 minutes", program.firmware().name()));
    let log = tokio::task::block_in_place(|| relay.wait_position(Duration::from_secs(10)));
    (result, log)
}

/// The noise: 2 % corrupted lines, 0.5 % lost `ok`s, 1 % lines lost whole (the
/// printer asks for them again: resends the host did not cause).
pub fn noise(seed: u64) -> RelayFaults {
    RelayFaults {
        seed,
        corrupt_line: 0.02,
        lose_ok: 0.005,
        drop_line: 0.01,
        ..RelayFaults::default()
    }
}
