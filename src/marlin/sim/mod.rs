//! A simulated Marlin printer on a real pty.
//!
//! [`spawn`] opens a pseudo-terminal, runs the printer on its own thread and returns at once
//! with the device path a host opens like a USB serial port. The printer side of the
//! protocol (line numbers, checksums, resends, `ok` timing, the receive buffer, heating,
//! M115 per firmware profile) lives in the I/O-free [`printer`] core; this file only moves
//! bytes between the pty and that core and sleeps until the core's next deadline, so an
//! idle simulator costs no CPU (the daemon's soak benchmark runs twenty of them). Bytes
//! cross a link model on the way ([`SimConfig::link_latency`], [`SimConfig::baud`]): queues
//! of timestamped batches whose arrival times are just more deadlines for that sleep.
//!
//! Faults (corrupted host bytes, lost `ok`s, spurious resends, busy periods, garbage,
//! reset/unplug/silence/fatal after N lines) are drawn from a seeded ChaCha generator so a
//! test with a fixed seed sees the same faults every run. Every command the printer
//! executes is recorded ([`SimHandle::executed`], and optionally a file) so tests can prove
//! that a host delivered a job exactly once and in order.

#[cfg(test)]
mod cosim;
mod printer;

use crate::marlin::firmware::Firmware;
use crate::marlin::protocol::canonical;
use nix::fcntl::{fcntl, FcntlArg, OFlag};
use nix::poll::{poll, PollFd, PollFlags, PollTimeout};
use nix::sys::termios;
use printer::{Printer, Status};
use std::collections::VecDeque;
use std::fs::File;
use std::io::{self, Write};
use std::os::fd::{AsFd, OwnedFd};
use std::path::{Path, PathBuf};
use std::sync::{Arc, Mutex};
use std::thread::JoinHandle;
use std::time::{Duration, Instant};

/// Faults to inject. Probabilities are per received line (host side) or per emitted line
/// (printer side); `*_after_lines` fire once, right after the printer starts executing its
/// N-th numbered line (so exactly N numbered lines have been executed, and the N-th one's
/// `ok` is never sent). `Default` injects nothing.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct Faults {
    /// Probability per received line that one of its bytes arrives corrupted, which the
    /// printer detects (checksum / line number) and answers with a resend request.
    pub corrupt_host_bytes: f64,
    /// Probability per received numbered line that one of its `.` arrives as `*`: Marlin 2
    /// then fails the checksum (it takes the last `*`), Ultimaker2Marlin checks only up to
    /// the first `*` and may run the cut line (seen on the real firmware).
    pub star_for_dot: f64,
    /// Probability that the `ok` for a command is never sent (M105's answer is exempt, so
    /// a host's M105 probe always recovers).
    pub drop_ok: f64,
    /// Probability that a good numbered line is answered as if it had been corrupted.
    pub spurious_resend: f64,
    /// Probability per received numbered line that it is lost whole (a noisy cable, a
    /// relay): the printer first sees the next line's number and answers it, as the real
    /// Marlin 2.1.2.1 does, with `Error:Line Number is not Last Line Number+1, Last Line:
    /// N`, `Resend: N+1` and `ok`, and so every line behind it already on its way.
    pub lose_line: f64,
    /// Probability that a command triggers a busy period with `echo:busy: processing`
    /// keep-alives before its `ok` (firmware with the busy protocol only).
    pub busy: f64,
    /// Probability per emitted line of garbage: a corrupted `ok` (`okk`, or an `ok` lost
    /// in binary noise), a garbled temperature report, a non-UTF-8 noise line, or the
    /// `Resend:12` spelling. Never a resend request for a different line.
    pub garbage: f64,
    /// Reboot (`start`, state forgotten, line numbers back to 0) after N numbered lines.
    pub reset_after_lines: Option<usize>,
    /// Close the pty after N numbered lines: the host sees a hang-up and the device vanishes.
    pub unplug_after_lines: Option<usize>,
    /// Stop answering anything after N numbered lines.
    pub silence_after_lines: Option<usize>,
    /// Halt with `Error:...` / `Error:Printer halted. kill() called!` after N numbered lines.
    pub fatal_after_lines: Option<usize>,
    /// Host actions (`//action:NAME`) to send after N numbered lines, as when someone
    /// presses Stop, Pause or Resume on the printer's screen: `(N, "pause")`.
    pub actions: Vec<(usize, String)>,
    /// Firmware errors that are not a halt (`Error:TEXT`, e.g. a failed probing) to report
    /// after N numbered lines: `(N, "Probing Failed")`.
    pub errors: Vec<(usize, String)>,
}

/// Something to make a running simulated printer do now, as a person at the printer would
/// ([`SimHandle::poke`], and `crispen sim --stdin`).
#[derive(Debug, Clone, PartialEq)]
pub enum Poke {
    /// Press reset or cycle the power: `start`, line numbers and settings forgotten.
    Reset,
    /// Use the printer's own menu: `//action:NAME` (cancel, pause, resume).
    Action(String),
    /// Report a firmware error that is not a halt: `Error:TEXT`.
    Error(String),
}

impl std::str::FromStr for Poke {
    type Err = String;
    /// `reset`, `action NAME`, `error TEXT`.
    fn from_str(text: &str) -> Result<Poke, String> {
        let text = text.trim();
        let (word, rest) = text.split_once(' ').unwrap_or((text, ""));
        let rest = rest.trim();
        match word {
            "reset" if rest.is_empty() => Ok(Poke::Reset),
            "action"
                if !rest.is_empty()
                    && rest.bytes().all(|b| b.is_ascii_alphanumeric() || b == b'_') =>
            {
                Ok(Poke::Action(rest.to_string()))
            }
            "error" if !rest.is_empty() && !rest.contains(['\n', '\r']) => {
                Ok(Poke::Error(rest.to_string()))
            }
            _ => Err(format!(
                "`{text}`: expected `reset`, `action NAME` (cancel, pause, resume) or `error TEXT`"
            )),
        }
    }
}

/// Sends [`Poke`]s to a running simulated printer; cheap to clone, usable from any thread.
#[derive(Clone)]
pub struct Poker {
    pokes: std::sync::mpsc::Sender<Poke>,
    /// Written to wake the printer thread. (Closing the handle's other pipe is shutdown.)
    doorbell: Arc<OwnedFd>,
}

impl Poker {
    /// Make the printer act now. False if it no longer runs.
    pub fn poke(&self, poke: Poke) -> bool {
        self.pokes.send(poke).is_ok() && nix::unistd::write(&*self.doorbell, b"!").is_ok()
    }
}

/// The largest speed-up factor taken; faster than that is "instant".
pub const MAX_SPEED: f64 = 1_000_000.0;

/// A simulated printer's speed as operators give it (`crispen sim --speed`,
/// `[printer.simulate] speed`): how many times faster than the real printer, higher is
/// faster (1 = real timing, 20 = twenty times faster), from 0.01 to [`MAX_SPEED`], or
/// "instant" (moves, heating and homing take no time). Returned as
/// [`SimConfig::time_scale`], its inverse. Operators once gave that inverse, which read as
/// a speed: 20 made a demo twenty times slower, and it looked hung.
pub fn time_scale_of_speed(speed: &str) -> Result<f64, String> {
    if speed.trim() == "instant" {
        return Ok(0.0);
    }
    match speed.trim().parse::<f64>() {
        Ok(x) if (0.01..=MAX_SPEED).contains(&x) => Ok(1.0 / x),
        _ => Err(format!(
            "speed {speed:?}: give how many times faster than real time, from 0.01 to {MAX_SPEED} (1 = real time, 20 = twenty times faster), or \"instant\""
        )),
    }
}

/// The speed an old time scale (real seconds per simulated second) is, as `speed` is
/// written: for the warning that names its replacement.
pub fn speed_of_time_scale(time_scale: f64) -> String {
    if time_scale == 0.0 {
        "instant".into()
    } else {
        (1.0 / time_scale).to_string()
    }
}

/// How to run a simulated printer.
#[derive(Debug, Clone)]
pub struct SimConfig {
    pub firmware: Firmware,
    /// Seed of the fault generator: the same seed and input give the same faults.
    pub seed: u64,
    /// Simulated seconds → real seconds. 0.0 makes moves, heating and homing instant;
    /// 1.0 is real timing.
    pub time_scale: f64,
    pub faults: Faults,
    /// Append each executed command to this file, one per line, flushed at once.
    pub record: Option<PathBuf>,
    /// Keep every executed command in memory for [`SimHandle::executed`] (tests do). A
    /// long-running simulated printer (the daemon's, `crispen sim`) must not: a job of
    /// millions of lines would keep them all.
    pub keep_executed: bool,
    /// Make a symlink to the pty device here (an existing symlink is replaced).
    pub link: Option<PathBuf>,
    /// One-way delay of the link, applied in both directions: bytes the printer sends reach
    /// the host no earlier than this after the printer produced them, and bytes the host
    /// writes reach the printer no earlier than this after they were written. A pty has no
    /// latency of its own, but a USB serial link does (1 ms full-speed frames; an FTDI
    /// adapter holds short answers up to its 16 ms latency timer), and that round trip is
    /// what a host with one line in flight pays per line. Zero by default so tests and the
    /// fault simulation stay fast and exact; benchmarks set it to compare hosts fairly.
    pub link_latency: Duration,
    /// Line speed in bits per second (10 bits per byte, 8N1) in both directions, or `None`
    /// for no limit. A pty moves bytes as fast as memory; at 115200 baud a 30-byte G1 line
    /// takes 2.6 ms on the wire.
    pub baud: Option<u32>,
    /// NO_TIMEOUTS: say `wait` this often while the command queue is empty.
    pub wait_when_idle: Option<Duration>,
    /// Opening the port resets the board (DTR): input is lost for this bootloader delay,
    /// then the firmware boots and says `start`.
    pub reset_on_open: Option<Duration>,
    /// ADVANCED_OK on or off, whatever the firmware profile says (`None`: the profile's).
    /// The real Marlin 2.1.2.1 ships with it off.
    pub advanced_ok: Option<bool>,
    /// How temperature reports are spaced around `/`.
    pub report_style: ReportStyle,
    /// Marlin 2 built with ADVANCED_PAUSE_FEATURE: `M600` parks and waits for the user
    /// (`busy: paused for user`, no `ok` until the knob). Off, as in stock Marlin 2.1, whose
    /// answer is `Unknown command`. (Ultimaker2Marlin answers `M600` with `ok` either way.)
    pub advanced_pause: bool,
}

/// The spacing of a temperature report: printers differ, and a host must read them all.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub enum ReportStyle {
    /// Marlin's and Ultimaker2Marlin's `T:24.99 /0.00`.
    #[default]
    Marlin,
    /// OctoPrint's virtual printer's `T:24.99/ 0.00`.
    SlashFirst,
    /// `T:24.99/0.00`, no space at all.
    Tight,
}

impl SimConfig {
    /// A fault-free printer with instant timing and seed 0.
    pub fn new(firmware: Firmware) -> Self {
        SimConfig {
            firmware,
            seed: 0,
            time_scale: 0.0,
            faults: Faults::default(),
            record: None,
            keep_executed: true,
            link: None,
            link_latency: Duration::ZERO,
            baud: None,
            wait_when_idle: None,
            reset_on_open: None,
            advanced_ok: None,
            report_style: ReportStyle::Marlin,
            advanced_pause: false,
        }
    }
}

/// Commands a host sends on its own account (not from the job): tests filter these out of
/// [`SimHandle::executed`] before comparing with the job file.
pub fn is_housekeeping(cmd: &str) -> bool {
    let word = cmd.split_whitespace().next().unwrap_or("");
    matches!(
        word.to_ascii_uppercase().as_str(),
        "M105" | "M110" | "M115" | "M155" | "M114" | "M27" | "M73"
    )
}

/// A running simulated printer. Dropping it stops the printer like [`SimHandle::shutdown`].
pub struct SimHandle {
    device: PathBuf,
    link: Option<PathBuf>,
    executed: Arc<Mutex<Vec<String>>>,
    wake: Option<OwnedFd>,
    poker: Poker,
    thread: Option<JoinHandle<()>>,
}

impl SimHandle {
    /// The pty device (e.g. `/dev/pts/7`) a host opens.
    pub fn device_path(&self) -> &Path {
        &self.device
    }

    /// The commands executed so far, in order, without `N<n> ` and `*<checksum>`, as the
    /// printer read them ([`canonical`]).
    pub fn executed(&self) -> Vec<String> {
        self.executed
            .lock()
            .unwrap_or_else(|e| e.into_inner())
            .clone()
    }

    /// Make the printer act now (reset, a host action, an error), as a person would.
    pub fn poke(&self, poke: Poke) -> bool {
        self.poker.poke(poke)
    }

    /// A handle for [`SimHandle::poke`] that another thread can own.
    pub fn poker(&self) -> Poker {
        self.poker.clone()
    }

    /// Stop the printer, close the pty and remove the link (if it still points to us).
    pub fn shutdown(mut self) {
        self.stop();
    }

    fn stop(&mut self) {
        // Closing the write end of the wake pipe makes the printer thread's poll return.
        self.wake.take();
        if let Some(thread) = self.thread.take() {
            let _ = thread.join();
        }
        if let Some(link) = self.link.take() {
            if std::fs::read_link(&link).ok().as_deref() == Some(self.device.as_path()) {
                let _ = std::fs::remove_file(&link);
            }
        }
    }
}

impl Drop for SimHandle {
    fn drop(&mut self) {
        self.stop();
    }
}

/// A pty's two ends, both closed on exec: a child process started meanwhile (a slicer, a
/// test's firmware) must not keep either open, or closing the master would not hang up
/// the host's side (seen in the test suite: a closed port taken for a silent printer).
pub struct Pty {
    pub master: OwnedFd,
    pub slave: OwnedFd,
}

/// Opens a pty whose descriptors are never inherited (`openpty` leaves them inheritable
/// until set otherwise, a race with any thread that starts a process meanwhile).
pub fn open_pty() -> nix::Result<Pty> {
    use nix::pty::{grantpt, posix_openpt, ptsname_r, unlockpt};
    use std::os::fd::{FromRawFd, IntoRawFd};
    let master = posix_openpt(OFlag::O_RDWR | OFlag::O_NOCTTY | OFlag::O_CLOEXEC)?;
    grantpt(&master)?;
    unlockpt(&master)?;
    let name = ptsname_r(&master)?;
    let slave = nix::fcntl::open(
        name.as_str(),
        OFlag::O_RDWR | OFlag::O_NOCTTY | OFlag::O_CLOEXEC,
        nix::sys::stat::Mode::empty(),
    )?;
    // SAFETY: the descriptor was just taken from `master`, which no longer owns it.
    let master = unsafe { OwnedFd::from_raw_fd(master.into_raw_fd()) };
    Ok(Pty { master, slave })
}

/// Open a pty and start the printer on its own thread. Returns at once.
pub fn spawn(cfg: SimConfig) -> io::Result<SimHandle> {
    let pty = open_pty().map_err(|e| {
        with_context(
            e,
            "cannot open a pty (is /dev/pts mounted and /dev/ptmx usable?)",
        )
    })?;
    // Raw mode on the slave side: no echo, no line editing, no CR/LF translation, exactly
    // like a USB serial port. The settings live with the pty, so they survive the host's
    // open/close.
    let mut attrs = termios::tcgetattr(&pty.slave)
        .map_err(|e| with_context(e, "cannot read the pty's terminal settings"))?;
    termios::cfmakeraw(&mut attrs);
    termios::tcsetattr(&pty.slave, termios::SetArg::TCSANOW, &attrs)
        .map_err(|e| with_context(e, "cannot put the pty in raw mode"))?;
    let device = nix::unistd::ttyname(&pty.slave)
        .map_err(|e| with_context(e, "cannot find the pty's device path"))?;
    // We close our slave descriptor so the master reports a hang-up while no host has the
    // port open; output is then discarded, as on a cable nobody listens to.
    drop(pty.slave);
    let master = pty.master;
    let flags = fcntl(&master, FcntlArg::F_GETFL).map_err(io::Error::from)?;
    fcntl(
        &master,
        FcntlArg::F_SETFL(OFlag::from_bits_truncate(flags) | OFlag::O_NONBLOCK),
    )
    .map_err(io::Error::from)?;

    if let Some(link) = &cfg.link {
        if let Ok(meta) = std::fs::symlink_metadata(link) {
            if meta.file_type().is_symlink() {
                std::fs::remove_file(link).map_err(|e| {
                    io::Error::new(
                        e.kind(),
                        format!("cannot replace the old link {}: {e}", link.display()),
                    )
                })?;
            } else {
                return Err(io::Error::new(
                    io::ErrorKind::AlreadyExists,
                    format!(
                        "{} exists and is not a symlink; refusing to replace it",
                        link.display()
                    ),
                ));
            }
        }
        std::os::unix::fs::symlink(&device, link).map_err(|e| {
            io::Error::new(
                e.kind(),
                format!(
                    "cannot link {} to {}: {e} (does the folder exist and is it writable?)",
                    link.display(),
                    device.display()
                ),
            )
        })?;
    }
    let record = match &cfg.record {
        Some(path) => Some(
            std::fs::OpenOptions::new()
                .create(true)
                .append(true)
                .open(path)
                .map_err(|e| {
                    io::Error::new(e.kind(), format!("record file {}: {e}", path.display()))
                })?,
        ),
        None => None,
    };
    let (wake_rx, wake_tx) = nix::unistd::pipe()
        .map_err(|e| with_context(e, "cannot create the simulator's wake-up pipe"))?;
    let (doorbell_rx, doorbell_tx) = nix::unistd::pipe()
        .map_err(|e| with_context(e, "cannot create the simulator's poke pipe"))?;
    let (poke_tx, poke_rx) = std::sync::mpsc::channel();
    let executed = Arc::new(Mutex::new(Vec::new()));
    let printer = Printer::new(&cfg, Instant::now());
    let reset_on_open = cfg.reset_on_open;
    let wire = Wire {
        latency: cfg.link_latency,
        byte_time: cfg
            .baud
            .filter(|&b| b > 0)
            .map(|b| Duration::from_secs_f64(10.0 / b as f64)),
    };
    let recorder = Recorder {
        executed: cfg.keep_executed.then(|| executed.clone()),
        file: record,
    };
    let name = device.display().to_string();
    let link_for_thread = cfg.link.clone();
    let device_for_thread = device.clone();
    let thread = std::thread::Builder::new()
        .name(format!("sim {name}"))
        .spawn(move || {
            let _span = tracing::info_span!("sim", printer = %name).entered();
            let pokes = Pokes {
                doorbell: doorbell_rx,
                pokes: poke_rx,
            };
            run(
                master,
                wake_rx,
                pokes,
                printer,
                recorder,
                wire,
                reset_on_open,
            );
            // The pty is closed now (unplug or shutdown): an unplugged device disappears,
            // and so does its udev-style link.
            if let Some(link) = link_for_thread {
                if std::fs::read_link(&link).ok().as_deref() == Some(device_for_thread.as_path()) {
                    let _ = std::fs::remove_file(&link);
                }
            }
        })?;
    Ok(SimHandle {
        device,
        link: cfg.link.clone(),
        executed,
        wake: Some(wake_tx),
        poker: Poker {
            pokes: poke_tx,
            doorbell: Arc::new(doorbell_tx),
        },
        thread: Some(thread),
    })
}

fn with_context(err: nix::errno::Errno, what: &str) -> io::Error {
    let err = io::Error::from(err);
    io::Error::new(err.kind(), format!("{what}: {err}"))
}

/// Where executed commands go: the shared list, and the record file if any.
pub(crate) struct Recorder {
    executed: Option<Arc<Mutex<Vec<String>>>>,
    file: Option<File>,
}

impl Recorder {
    /// Records what the printer ran as it reads it ([`canonical`]: a host may write the
    /// same command with an extra space or trailing zeros, e.g. crispen's cut-line guard).
    pub(crate) fn push(&mut self, cmd: &str) {
        let cmd = &canonical(cmd);
        if let Some(executed) = &self.executed {
            executed
                .lock()
                .unwrap_or_else(|e| e.into_inner())
                .push(cmd.to_string());
        }
        if let Some(file) = &mut self.file {
            if let Err(err) = writeln!(file, "{cmd}").and_then(|_| file.flush()) {
                tracing::warn!(%err, "cannot append to the record file; recording stopped");
                self.file = None;
            }
        }
    }
}

const MAX_OUTPUT_BACKLOG: usize = 64 * 1024;

/// The link's timing: latency and, with a baud limit, the time one byte occupies the wire.
#[derive(Debug, Clone, Copy)]
struct Wire {
    latency: Duration,
    byte_time: Option<Duration>,
}

/// Bytes on their way through the link in one direction, each batch with the time it
/// arrives at the far end. Batches keep their order; the poll loop sleeps until the first
/// one is due.
#[derive(Default)]
struct InFlight {
    batches: VecDeque<(Instant, Vec<u8>)>,
    /// When the wire is free again (baud limit): a batch is serialised after the one before.
    wire_free: Option<Instant>,
    bytes: usize,
}

impl InFlight {
    fn send(&mut self, wire: &Wire, now: Instant, bytes: Vec<u8>) {
        let mut sent = now;
        if let Some(byte_time) = wire.byte_time {
            let start = self.wire_free.map_or(now, |free| free.max(now));
            sent = start + byte_time * bytes.len() as u32;
            self.wire_free = Some(sent);
        }
        self.bytes += bytes.len();
        self.batches.push_back((sent + wire.latency, bytes));
    }

    fn next_due(&self) -> Option<Instant> {
        self.batches.front().map(|b| b.0)
    }

    /// The first batch if it has arrived by `now`.
    fn arrived(&mut self, now: Instant) -> Option<&mut Vec<u8>> {
        match self.batches.front_mut() {
            Some((due, bytes)) if *due <= now => Some(bytes),
            _ => None,
        }
    }

    /// Remove `n` bytes from the front of the first batch (all of it when fully delivered).
    fn consume(&mut self, n: usize) {
        if let Some((_, bytes)) = self.batches.front_mut() {
            let n = n.min(bytes.len());
            bytes.drain(..n);
            self.bytes -= n;
            if bytes.is_empty() {
                self.batches.pop_front();
            }
        }
    }

    fn clear(&mut self) {
        self.batches.clear();
        self.bytes = 0;
    }
}

/// The receiving end of a [`Poker`].
struct Pokes {
    doorbell: OwnedFd,
    pokes: std::sync::mpsc::Receiver<Poke>,
}

/// The printer thread: shuttle bytes between the pty master and the printer core through
/// the link model, sleeping in poll() until input arrives, output can drain, bytes in flight
/// arrive, the core's next deadline, or shutdown.
fn run(
    master: OwnedFd,
    wake: OwnedFd,
    pokes: Pokes,
    mut printer: Printer,
    mut recorder: Recorder,
    wire: Wire,
    reset_on_open: Option<Duration>,
) {
    let mut scratch = [0u8; 4096];
    let mut host_connected = false;
    let mut to_printer = InFlight::default();
    let mut to_host = InFlight::default();
    loop {
        let now = Instant::now();
        while let Some(bytes) = to_printer.arrived(now) {
            let bytes = std::mem::take(bytes);
            to_printer.consume(bytes.len());
            printer.receive(&bytes, now, &mut recorder);
        }
        printer.advance(now, &mut recorder);
        if printer.status() == Status::Unplugged {
            tracing::info!("simulated unplug: closing the pty");
            return;
        }
        let out = printer.take_output();
        if !host_connected {
            // Nobody listens: what the printer says is lost, as on an unconnected cable.
            to_host.clear();
            to_printer.clear();
        } else if !out.is_empty() {
            to_host.send(&wire, now, out);
        }
        // A host that never reads must not make the printer hoard output without bound
        // (a real UART just sends it into the void).
        while to_host.bytes > MAX_OUTPUT_BACKLOG {
            to_host.consume(to_host.bytes - MAX_OUTPUT_BACKLOG);
        }
        // True while arrived bytes wait for the host to read (the pty is full): poll then
        // waits for POLLOUT rather than for a deadline already in the past.
        let mut out_pending = false;
        while let Some(bytes) = to_host.arrived(now) {
            match nix::unistd::write(&master, bytes) {
                Ok(n) => to_host.consume(n),
                Err(nix::errno::Errno::EAGAIN) => {
                    out_pending = true;
                    break;
                }
                Err(err) => {
                    if err != nix::errno::Errno::EIO {
                        tracing::warn!(%err, "pty write failed");
                    }
                    host_connected = false;
                    break;
                }
            }
        }
        let arrivals = [
            printer.next_deadline(),
            to_printer.next_due(),
            if out_pending {
                None
            } else {
                to_host.next_due()
            },
        ];
        let timeout = match arrivals.into_iter().flatten().min() {
            Some(t) => t.saturating_duration_since(Instant::now()),
            None => Duration::from_secs(3600),
        };
        // While no host has the port open the master reports a hang-up continuously, so
        // look again for a host only every 50 ms instead of spinning.
        let timeout = if host_connected {
            timeout
        } else {
            timeout.min(Duration::from_millis(50))
        };
        let mut master_flags = PollFlags::empty();
        if host_connected {
            master_flags |= PollFlags::POLLIN;
            if out_pending {
                master_flags |= PollFlags::POLLOUT;
            }
        }
        let mut fds = vec![
            PollFd::new(wake.as_fd(), PollFlags::POLLIN),
            PollFd::new(pokes.doorbell.as_fd(), PollFlags::POLLIN),
        ];
        // Without a host the master always reports POLLHUP, so it is left out of the poll
        // (which then only sleeps) and probed by a read afterwards.
        if host_connected {
            fds.push(PollFd::new(master.as_fd(), master_flags));
        }
        let ms = timeout.as_millis().min(i32::MAX as u128) as i32;
        // Round up so a deadline 0.4 ms away does not turn into a busy loop of 0 ms polls.
        let ms = if timeout > Duration::from_millis(ms as u64) {
            ms.saturating_add(1)
        } else {
            ms
        };
        match poll(
            &mut fds,
            PollTimeout::try_from(ms).unwrap_or(PollTimeout::MAX),
        ) {
            Ok(_) => {}
            Err(nix::errno::Errno::EINTR) => continue,
            Err(err) => {
                tracing::error!(%err, "poll failed; stopping the simulated printer");
                return;
            }
        }
        if fds[0].revents().is_some_and(|r| !r.is_empty()) {
            return; // shutdown: the handle closed the pipe
        }
        if fds[1].revents().is_some_and(|r| !r.is_empty()) {
            let _ = nix::unistd::read(&pokes.doorbell, &mut scratch);
            while let Ok(poke) = pokes.pokes.try_recv() {
                printer.poke(poke);
            }
        }
        if !host_connected {
            // Probe: a read that does not fail with EIO means a host opened the port.
            match nix::unistd::read(&master, &mut scratch) {
                Err(nix::errno::Errno::EIO) => {}
                Ok(n) => {
                    host_connected = true;
                    tracing::debug!("host opened the port");
                    if let Some(delay) = reset_on_open {
                        printer.reset_on_open(Instant::now(), delay);
                    }
                    to_printer.send(&wire, Instant::now(), scratch[..n].to_vec());
                }
                Err(_) => {
                    host_connected = true;
                    if let Some(delay) = reset_on_open {
                        printer.reset_on_open(Instant::now(), delay);
                    }
                }
            }
            continue;
        }
        let revents = fds
            .get(2)
            .and_then(|f| f.revents())
            .unwrap_or(PollFlags::empty());
        if revents.contains(PollFlags::POLLIN) {
            match nix::unistd::read(&master, &mut scratch) {
                Ok(0) | Err(nix::errno::Errno::EIO) => {
                    host_connected = false;
                    tracing::debug!("host closed the port");
                }
                Ok(n) => to_printer.send(&wire, Instant::now(), scratch[..n].to_vec()),
                Err(nix::errno::Errno::EAGAIN) => {}
                Err(err) => tracing::warn!(%err, "pty read failed"),
            }
        } else if revents.contains(PollFlags::POLLHUP) {
            host_connected = false;
            tracing::debug!("host closed the port");
        }
    }
}

#[cfg(test)]
mod pty_tests {
    use super::*;
    use nix::fcntl::FdFlag;

    /// Neither end of a pty is inherited by a process started meanwhile.
    #[test]
    fn pty_descriptors_close_on_exec() {
        let pty = open_pty().unwrap();
        for fd in [&pty.master, &pty.slave] {
            let flags = FdFlag::from_bits_truncate(fcntl(fd, FcntlArg::F_GETFD).unwrap());
            assert!(flags.contains(FdFlag::FD_CLOEXEC));
        }
    }
}
