//! Streaming a G-code program to a printer: the async driver that joins the pure protocol
//! state machine ([`super::protocol::Host`]) to the serial link ([`super::transport`]),
//! to a control channel (pause/resume/cancel) and to a progress watch. The daemon's
//! printer supervisors and `crispen print` both use [`Connection`].

use super::firmware::Firmware;
use super::gcode::GcodeProgram;
use super::protocol::reply::{HostAction, Reply};
use super::protocol::{Event, Failure, Host, ProtocolOptions};
use super::transport::{LinkEvent, Transport, TransportError};
use serde::Serialize;
use std::path::{Path, PathBuf};
use std::time::{Duration, Instant};
use tokio::sync::{mpsc, watch};

pub use super::protocol::{FirmwareInfo, Temp, Temperatures};

/// How to talk to one printer.
#[derive(Debug, Clone)]
pub struct StreamOptions {
    pub firmware: Firmware,
    pub baud: u32,
    /// Keep several lines in flight (false: one line in flight).
    pub send_ahead: bool,
    /// Give up the handshake after this long.
    pub connect_timeout: Duration,
    /// Everything the protocol core needs (silence, heat and resend limits, ...).
    pub protocol: ProtocolOptions,
}

impl StreamOptions {
    pub fn for_firmware(firmware: Firmware) -> Self {
        StreamOptions {
            firmware,
            baud: firmware.default_baud(),
            send_ahead: true,
            connect_timeout: Duration::from_secs(20),
            protocol: ProtocolOptions::for_firmware(firmware),
        }
    }
    fn protocol_options(&self) -> ProtocolOptions {
        let mut p = self.protocol.clone();
        p.firmware = self.firmware;
        p.send_ahead = self.send_ahead;
        p
    }
}

#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum StreamControl {
    Pause,
    Resume,
    Cancel,
}

#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Default)]
#[serde(rename_all = "lowercase")]
pub enum PrintState {
    #[default]
    Connecting,
    Heating,
    Printing,
    Pausing,
    Paused,
    Cancelling,
    Done,
    Failed,
}

#[derive(Debug, Clone, Serialize, Default)]
pub struct PrintProgress {
    pub lines_acked: usize,
    pub lines_total: usize,
    pub hotend: Option<Temp>,
    pub bed: Option<Temp>,
    pub state: PrintState,
    pub elapsed_s: f64,
    /// Estimated from the acknowledgement rate so far.
    pub remaining_s: Option<f64>,
}

#[derive(Debug, Clone, Serialize)]
pub struct PrintReport {
    pub port: PathBuf,
    pub lines_total: usize,
    pub lines_acked: usize,
    /// Lines written, including housekeeping and replays.
    pub lines_sent: u64,
    pub resends: u64,
    pub silence_probes: u64,
    /// Pieces of lines the printer answered on their own after a receive-buffer flush.
    pub fragments: u64,
    pub duration_s: f64,
}

#[derive(Debug, thiserror::Error)]
pub enum PrintError {
    #[error(transparent)]
    Open(#[from] TransportError),
    #[error(
        "no answer from the printer on {port} after {waited_s:.1} s; check the baud rate \
         (--baud) and the firmware profile (--firmware)"
    )]
    NoAnswer { port: PathBuf, waited_s: f64 },
    #[error(
        "interrupted: printer on {port} disconnected ({reason}), last acknowledged line \
         {last_acked}"
    )]
    Disconnected {
        port: PathBuf,
        reason: String,
        last_acked: usize,
    },
    #[error(
        "printer on {port} reset itself (it said `start`) in the middle of the job; the print \
         is lost, last acknowledged line {last_acked}"
    )]
    PrinterReset { port: PathBuf, last_acked: usize },
    #[error(
        "printer on {port} stopped with a fatal error: {message}; last acknowledged line \
         {last_acked} (the printer needs a reset or M999)"
    )]
    Fatal {
        port: PathBuf,
        message: String,
        last_acked: usize,
    },
    #[error(
        "printer on {port} asked for line {line} again {times} times; giving up (check the \
         cable and baud rate), last acknowledged line {last_acked}"
    )]
    ResendLimit {
        port: PathBuf,
        line: u64,
        times: u32,
        last_acked: usize,
    },
    #[error(
        "printer on {port} asked for line {line}, which is no longer kept (oldest kept: \
         {oldest_kept}); stopping rather than guessing, last acknowledged line {last_acked}"
    )]
    LineGone {
        port: PathBuf,
        line: u64,
        oldest_kept: u64,
        last_acked: usize,
    },
    #[error(
        "printer on {port} asked for line {line} again although it had confirmed line \
         {confirmed}: it lost its state (reset or power dip?); stopped safely rather than \
         replaying onto a half-printed part, last acknowledged line {last_acked}"
    )]
    LostState {
        port: PathBuf,
        line: u64,
        confirmed: u64,
        last_acked: usize,
    },
    #[error(
        "printer on {port} kept talking but acknowledged no line for {waited_s:.0} s; \
         stopped safely, last acknowledged line {last_acked}"
    )]
    NoProgress {
        port: PathBuf,
        waited_s: f64,
        last_acked: usize,
    },
    #[error(
        "printer on {port} went silent for {waited_s:.1} s and did not answer M105 probes; \
         last acknowledged line {last_acked}"
    )]
    Silent {
        port: PathBuf,
        waited_s: f64,
        last_acked: usize,
    },
    #[error(
        "printer on {port}: `{command}` stopped coming closer to its temperature (waited \
         {waited_s:.0} s in all, now {temperatures}); heaters were switched off, last \
         acknowledged line {last_acked}"
    )]
    HeatTimeout {
        port: PathBuf,
        command: String,
        waited_s: f64,
        temperatures: String,
        last_acked: usize,
    },
    #[error("job on {port} cancelled; heaters, fan and motors switched off, last acknowledged line {last_acked}")]
    Cancelled { port: PathBuf, last_acked: usize },
    #[error(
        "line `{command}` is {len} bytes with its line number and checksum, more than the \
         printer's limit of {max}; nothing was sent for it"
    )]
    LineTooLong {
        command: String,
        len: usize,
        max: usize,
    },
    #[error(
        "printer on {port} reported `{message}`, which the job cannot go on after; heaters, \
         fan and motors were switched off, last acknowledged line {last_acked}"
    )]
    FirmwareError {
        port: PathBuf,
        message: String,
        last_acked: usize,
    },
    #[error("printer on {port} is busy with another job")]
    Busy { port: PathBuf },
}

impl PrintError {
    /// Job commands the printer acknowledged before the failure, where known.
    pub fn last_acked(&self) -> Option<usize> {
        match self {
            PrintError::Disconnected { last_acked, .. }
            | PrintError::PrinterReset { last_acked, .. }
            | PrintError::Fatal { last_acked, .. }
            | PrintError::ResendLimit { last_acked, .. }
            | PrintError::LineGone { last_acked, .. }
            | PrintError::Silent { last_acked, .. }
            | PrintError::LostState { last_acked, .. }
            | PrintError::NoProgress { last_acked, .. }
            | PrintError::HeatTimeout { last_acked, .. }
            | PrintError::Cancelled { last_acked, .. }
            | PrintError::FirmwareError { last_acked, .. } => Some(*last_acked),
            _ => None,
        }
    }

    fn from_failure(port: &Path, failure: Failure) -> Self {
        let port = port.to_path_buf();
        match failure {
            Failure::NoAnswer { waited } => PrintError::NoAnswer {
                port,
                waited_s: waited.as_secs_f64(),
            },
            Failure::PrinterReset { last_acked } => PrintError::PrinterReset { port, last_acked },
            Failure::Fatal {
                message,
                last_acked,
            } => PrintError::Fatal {
                port,
                message,
                last_acked,
            },
            Failure::ResendLimit {
                line,
                times,
                last_acked,
            } => PrintError::ResendLimit {
                port,
                line,
                times,
                last_acked,
            },
            Failure::LineGone {
                line,
                oldest_kept,
                last_acked,
            } => PrintError::LineGone {
                port,
                line,
                oldest_kept,
                last_acked,
            },
            Failure::LostState {
                line,
                confirmed,
                last_acked,
            } => PrintError::LostState {
                port,
                line,
                confirmed,
                last_acked,
            },
            Failure::NoProgress { waited, last_acked } => PrintError::NoProgress {
                port,
                waited_s: waited.as_secs_f64(),
                last_acked,
            },
            Failure::Silent { waited, last_acked } => PrintError::Silent {
                port,
                waited_s: waited.as_secs_f64(),
                last_acked,
            },
            Failure::HeatTimeout {
                command,
                waited,
                temperatures,
                last_acked,
            } => PrintError::HeatTimeout {
                port,
                command,
                waited_s: waited.as_secs_f64(),
                temperatures: describe_temps(&temperatures),
                last_acked,
            },
            Failure::Cancelled { last_acked } => PrintError::Cancelled { port, last_acked },
            Failure::LineTooLong { command, len, max } => {
                PrintError::LineTooLong { command, len, max }
            }
            Failure::FirmwareError {
                message,
                last_acked,
            } => PrintError::FirmwareError {
                port,
                message,
                last_acked,
            },
        }
    }
}

fn describe_temps(t: &Temperatures) -> String {
    let one = |name: &str, t: Option<Temp>| match t {
        Some(Temp {
            current,
            target: Some(target),
        }) => format!("{name} {current:.1}/{target:.0}°C"),
        Some(Temp { current, .. }) => format!("{name} {current:.1}°C"),
        None => format!("{name} unknown"),
    };
    format!("{}, {}", one("hotend", t.hotend), one("bed", t.bed))
}

/// An open, handshaken printer link.
pub struct Connection {
    transport: Transport,
    host: Host,
    port: PathBuf,
    opts: StreamOptions,
    info: FirmwareInfo,
    /// An unfinished line of what the printer said between jobs.
    idle_partial: Vec<u8>,
    /// The printer said `start` since the last job: it rebooted, so the next job begins
    /// with a fresh handshake.
    rebooted: bool,
}

/// What [`Connection::idle_for`] saw.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Idle {
    /// Nothing that needs acting on (reports and messages are logged).
    Quiet,
    /// The printer said `start`: it was reset or power-cycled. The next job begins with a
    /// fresh handshake and line numbering.
    Rebooted,
}

impl Connection {
    /// Open the port and run the handshake (wait for `start` or quiet, M110, M115).
    pub async fn open(port: &Path, opts: &StreamOptions) -> Result<Connection, PrintError> {
        let mut transport = Transport::open(port, opts.baud)?;
        let (host, info) = greet(&mut transport, port, opts).await?;
        tracing::info!(port = %port.display(), firmware = ?info.name, "printer connected");
        Ok(Connection {
            transport,
            host,
            port: port.to_path_buf(),
            opts: opts.clone(),
            info,
            idle_partial: Vec::new(),
            rebooted: false,
        })
    }

    pub fn firmware_info(&self) -> &FirmwareInfo {
        &self.info
    }
    pub fn port(&self) -> &Path {
        &self.port
    }
    pub fn options(&self) -> &StreamOptions {
        &self.opts
    }

    /// Read and log what the printer says between jobs (temperature reports, `start` after
    /// a power cycle, host actions, messages) for up to `duration`. Returns early with
    /// [`Idle::Rebooted`] when the printer says `start`, and with an error if the link
    /// closes. Cancel-safe: the daemon races it against a bed being cleared.
    pub async fn idle_for(&mut self, duration: Duration) -> Result<Idle, PrintError> {
        let until = tokio::time::Instant::now() + duration;
        loop {
            tokio::select! {
                link = self.transport.recv() => match link {
                    LinkEvent::Data(bytes) => {
                        if log_idle_lines(&self.port, &mut self.idle_partial, &bytes) {
                            self.rebooted = true;
                            return Ok(Idle::Rebooted);
                        }
                    }
                    LinkEvent::Closed(reason) => {
                        return Err(PrintError::Disconnected { port: self.port.clone(), reason, last_acked: 0 });
                    }
                },
                _ = tokio::time::sleep_until(until) => return Ok(Idle::Quiet),
            }
        }
    }

    /// Log what arrived between jobs and is not read yet; notes a reboot.
    fn drain_idle_input(&mut self) -> Result<(), PrintError> {
        while let Some(link) = self.transport.try_recv() {
            match link {
                LinkEvent::Data(bytes) => {
                    self.rebooted |= log_idle_lines(&self.port, &mut self.idle_partial, &bytes);
                }
                LinkEvent::Closed(reason) => {
                    return Err(PrintError::Disconnected {
                        port: self.port.clone(),
                        reason,
                        last_acked: 0,
                    });
                }
            }
        }
        Ok(())
    }

    /// Begin the next job on a clean link: what the printer said between jobs is logged,
    /// not taken for answers to this job; after a reboot the handshake runs again (the
    /// firmware may even have changed), which lets the boot banner through first.
    async fn clean_link(&mut self) -> Result<(), PrintError> {
        self.drain_idle_input()?;
        self.idle_partial.clear();
        if std::mem::take(&mut self.rebooted) {
            tracing::info!(port = %self.port.display(), "printer rebooted since the last job; greeting it again");
            let (host, info) = greet(&mut self.transport, &self.port, &self.opts).await?;
            self.host = host;
            self.info = info;
        } else if !self.host.is_idle() {
            // A previous job ended: the protocol core is single-use per job outcome, so
            // start a fresh one on the same (already greeted) link.
            let mut host = Host::new(self.opts.protocol_options(), Instant::now());
            host.mark_connected(self.info.clone());
            self.host = host;
        }
        Ok(())
    }

    /// Stream `program`; returns when every line was acknowledged, or why not.
    pub async fn print(
        &mut self,
        program: &GcodeProgram,
        mut control: mpsc::Receiver<StreamControl>,
        progress: watch::Sender<PrintProgress>,
    ) -> Result<PrintReport, PrintError> {
        self.clean_link().await?;
        let started = Instant::now();
        let total = program.len();
        let port = self.port.clone();
        let mut state = PrintState::Printing;
        let mut control_open = true;
        self.host
            .start_job(program.shared_commands(), Instant::now());
        let publish = |host: &Host, state: PrintState| {
            let elapsed = started.elapsed().as_secs_f64();
            let acked = host.acked_job_lines();
            let remaining = (acked > 0 && acked < total)
                .then(|| elapsed / acked as f64 * (total - acked) as f64);
            let t = host.temperatures();
            progress.send_replace(PrintProgress {
                lines_acked: acked,
                lines_total: total,
                hotend: t.hotend,
                bed: t.bed,
                state,
                elapsed_s: elapsed,
                remaining_s: if acked >= total { Some(0.0) } else { remaining },
            });
        };
        publish(&self.host, state);
        let mut last_publish = Instant::now();
        loop {
            flush(&mut self.host, &self.transport);
            let mut changed = false;
            // State changes are published at once; counters at most every 100 ms.
            let mut state_changed = false;
            while let Some(event) = self.host.poll_event() {
                match event {
                    Event::Done(summary) => {
                        publish(&self.host, PrintState::Done);
                        tracing::info!(port = %port.display(), gcode = program.name(), lines = total, "print finished");
                        return Ok(PrintReport {
                            port: port.clone(),
                            lines_total: total,
                            lines_acked: total,
                            lines_sent: summary.lines_sent,
                            resends: summary.resends,
                            silence_probes: summary.probes,
                            fragments: summary.fragments,
                            duration_s: started.elapsed().as_secs_f64(),
                        });
                    }
                    Event::Failed(f) => {
                        publish(&self.host, PrintState::Failed);
                        let err = PrintError::from_failure(&port, f);
                        tracing::warn!(port = %port.display(), gcode = program.name(), "print failed: {err}");
                        return Err(err);
                    }
                    Event::Progress { .. } | Event::Temperatures(_) => changed = true,
                    Event::Paused => {
                        state = PrintState::Paused;
                        state_changed = true;
                    }
                    Event::Resumed => {
                        state = PrintState::Printing;
                        state_changed = true;
                    }
                    Event::Resend { line, replay } => {
                        tracing::debug!(port = %port.display(), gcode = program.name(), line, replay, "printer asked for a resend")
                    }
                    Event::Probe => {
                        tracing::debug!(port = %port.display(), gcode = program.name(), "printer silent; probing with M105")
                    }
                    Event::Busy(_) => {}
                    Event::Message(m) => {
                        tracing::debug!(port = %port.display(), gcode = program.name(), "printer: {m}")
                    }
                    Event::Fragment(text) => {
                        tracing::warn!(port = %port.display(), gcode = program.name(), "printer answered a piece of a line on its own: {text}")
                    }
                    Event::HostAction(action) => {
                        tracing::info!(port = %port.display(), gcode = program.name(), ?action, "printer asked the host to act");
                        match action {
                            HostAction::Cancel => state = PrintState::Cancelling,
                            HostAction::Pause => state = PrintState::Pausing,
                            HostAction::Resume | HostAction::Other(_) => {}
                        }
                        state_changed = true;
                    }
                    Event::SafeStop { confirmed: true } => {
                        tracing::info!(port = %port.display(), gcode = program.name(), "printer stopped safely: heaters, fan and motors off")
                    }
                    Event::SafeStop { confirmed: false } => {
                        tracing::error!(port = %port.display(), gcode = program.name(), "the printer did not confirm heaters off; check it now")
                    }
                    Event::Connected(_) => {}
                }
            }
            if state_changed || (changed && last_publish.elapsed() >= Duration::from_millis(100)) {
                let shown = if state == PrintState::Printing && self.host.heating() {
                    PrintState::Heating
                } else {
                    state
                };
                publish(&self.host, shown);
                last_publish = Instant::now();
            }
            let deadline = self
                .host
                .next_deadline()
                .map(tokio::time::Instant::from_std);
            tokio::select! {
                link = self.transport.recv() => match link {
                    LinkEvent::Data(bytes) => self.host.feed(&bytes, Instant::now()),
                    LinkEvent::Closed(reason) => {
                        publish(&self.host, PrintState::Failed);
                        let last_acked = self.host.acked_job_lines();
                        tracing::warn!(port = %port.display(), gcode = program.name(), last_acked, "printer disconnected: {reason}");
                        return Err(PrintError::Disconnected { port: port.clone(), reason, last_acked });
                    }
                },
                cmd = control.recv(), if control_open => match cmd {
                    Some(StreamControl::Pause) => {
                        state = PrintState::Pausing;
                        self.host.pause(Instant::now());
                        publish(&self.host, state);
                    }
                    Some(StreamControl::Resume) => self.host.resume(Instant::now()),
                    Some(StreamControl::Cancel) => {
                        state = PrintState::Cancelling;
                        self.host.cancel(Instant::now());
                        publish(&self.host, state);
                    }
                    None => control_open = false,
                },
                _ = sleep_until_opt(deadline) => self.host.tick(Instant::now()),
            }
        }
    }
}

/// The handshake on an open link: wait for `start` or a quiet period, then M110 and M115.
async fn greet(
    transport: &mut Transport,
    port: &Path,
    opts: &StreamOptions,
) -> Result<(Host, FirmwareInfo), PrintError> {
    let mut host = Host::new(opts.protocol_options(), Instant::now());
    let give_up = tokio::time::Instant::now() + opts.connect_timeout;
    let started = Instant::now();
    loop {
        flush(&mut host, transport);
        while let Some(event) = host.poll_event() {
            match event {
                Event::Connected(info) => return Ok((host, info)),
                Event::Failed(f) => return Err(PrintError::from_failure(port, f)),
                Event::Message(m) => tracing::debug!(port = %port.display(), "printer: {m}"),
                _ => {}
            }
        }
        let deadline = host
            .next_deadline()
            .map(tokio::time::Instant::from_std)
            .unwrap_or(give_up)
            .min(give_up);
        tokio::select! {
            link = transport.recv() => match link {
                LinkEvent::Data(bytes) => host.feed(&bytes, Instant::now()),
                LinkEvent::Closed(reason) => {
                    return Err(PrintError::Disconnected { port: port.to_path_buf(), reason, last_acked: 0 });
                }
            },
            _ = tokio::time::sleep_until(deadline) => {
                if tokio::time::Instant::now() >= give_up {
                    return Err(PrintError::NoAnswer { port: port.to_path_buf(), waited_s: started.elapsed().as_secs_f64() });
                }
                host.tick(Instant::now());
            }
        }
    }
}

/// Split `bytes` into lines (keeping an unfinished one in `partial`) and log each as the
/// printer's idle talk; true if one was a boot (`start`).
fn log_idle_lines(port: &Path, partial: &mut Vec<u8>, bytes: &[u8]) -> bool {
    let mut rebooted = false;
    for &b in bytes {
        if b != b'\n' {
            if partial.len() < 4096 {
                partial.push(b);
            }
            continue;
        }
        match Reply::parse(&std::mem::take(partial)) {
            Some(Reply::Start) => {
                rebooted = true;
                tracing::warn!(port = %port.display(), "printer rebooted while idle (it said `start`)");
            }
            Some(Reply::Temperatures(r)) => {
                tracing::debug!(port = %port.display(), "idle printer: {}", describe_temps(&r.temperatures))
            }
            Some(Reply::Fatal(line)) | Some(Reply::Error(line)) => {
                tracing::warn!(port = %port.display(), "idle printer: {line}")
            }
            Some(Reply::Action(action)) => {
                // No job to act on: the printer's own menu was used between jobs.
                tracing::info!(port = %port.display(), ?action, "idle printer asked the host to act; no job is running")
            }
            // NO_TIMEOUTS builds say `wait` every few seconds while idle.
            Some(Reply::Wait) => tracing::trace!(port = %port.display(), "idle printer: wait"),
            Some(other) => tracing::info!(port = %port.display(), "idle printer: {other:?}"),
            None => {}
        }
    }
    rebooted
}

async fn sleep_until_opt(deadline: Option<tokio::time::Instant>) {
    match deadline {
        Some(d) => tokio::time::sleep_until(d).await,
        None => std::future::pending().await,
    }
}

fn flush(host: &mut Host, transport: &Transport) {
    let out = host.take_outgoing();
    if !out.is_empty() {
        transport.send(out);
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The daemon runs jobs with `tokio::spawn`, which needs `Send` futures; this only has
    /// to compile.
    #[allow(dead_code)]
    fn print_future_is_send(
        conn: &mut Connection,
        program: &GcodeProgram,
        control: mpsc::Receiver<StreamControl>,
        progress: watch::Sender<PrintProgress>,
    ) {
        fn is_send<T: Send>(_: &T) {}
        let opts = StreamOptions::for_firmware(Firmware::Marlin2);
        let open = Connection::open(Path::new("/dev/null"), &opts);
        is_send(&open);
        let print = conn.print(program, control, progress);
        is_send(&print);
    }

    #[test]
    fn errors_name_the_port_and_the_last_acknowledged_line() {
        let err = PrintError::from_failure(
            Path::new("/dev/ttyUSB3"),
            Failure::PrinterReset { last_acked: 41 },
        );
        let msg = err.to_string();
        assert!(msg.contains("/dev/ttyUSB3") && msg.contains("41"), "{msg}");
        assert_eq!(err.last_acked(), Some(41));
    }

    #[tokio::test]
    async fn opening_a_missing_port_says_which_and_what_to_check() {
        let opts = StreamOptions::for_firmware(Firmware::Ultimaker2);
        let err = Connection::open(Path::new("/dev/does-not-exist-crispen"), &opts)
            .await
            .err()
            .expect("fails");
        let msg = err.to_string();
        assert!(
            msg.contains("/dev/does-not-exist-crispen") && msg.contains("plugged in"),
            "{msg}"
        );
    }
}
