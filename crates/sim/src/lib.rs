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

mod config;
#[cfg(test)]
mod cosim;
mod poke;
mod printer;
mod recorder;

pub use config::{
    speed_of_time_scale, time_scale_of_speed, Faults, ReportStyle, SimConfig, MAX_SPEED,
};
pub use poke::{Poke, Poker};

use nix::fcntl::{fcntl, FcntlArg, OFlag};
use nix::poll::{poll, PollFd, PollFlags, PollTimeout};
use nix::sys::termios;
use poke::Pokes;
use printer::{Printer, Status};
use recorder::Recorder;
use std::collections::VecDeque;
use std::io;
use std::os::fd::{AsFd, OwnedFd};
use std::path::{Path, PathBuf};
use std::sync::{Arc, Mutex};
use std::thread::JoinHandle;
use std::time::{Duration, Instant};

/// Commands a host sends on its own account (not from the job): tests filter these out of
/// [`SimHandle::executed`] before comparing with the job file.
pub fn is_housekeeping(cmd: &str) -> bool {
    let word = cmd.split_whitespace().next().unwrap_or("");
    matches!(
        word.to_ascii_uppercase().as_str(),
        "M105" | "M110" | "M115" | "M155" | "M114" | "M27" | "M73" | "M503"
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
    /// printer read them ([`canonical`](crispen_marlin::protocol::canonical)).
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
