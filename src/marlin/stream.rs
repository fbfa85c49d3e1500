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

/// What became of the safe stop (heaters, fan and motors off) that follows a failure while
/// the printer still answers, or a cancel. Part of the job's error, so whoever reads why a
/// job failed also reads whether the printer was left hot.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize)]
pub enum StopOutcome {
    /// The printer acknowledged the heaters-off lines (an answered `M105` after them).
    Confirmed,
    /// The host gave up before the printer confirmed them: it may still be hot.
    NotConfirmed,
    /// No stop was needed or possible (a reset or halted printer has switched its heaters
    /// off; nothing was sent yet).
    None,
}

impl std::fmt::Display for StopOutcome {
    /// Written after the error's own text.
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            StopOutcome::Confirmed => f.write_str("; heaters, fan and motors confirmed off"),
            StopOutcome::NotConfirmed => {
                f.write_str("; heaters NOT confirmed off: check the printer now")
            }
            StopOutcome::None => Ok(()),
        }
    }
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
         cable and baud rate), last acknowledged line {last_acked}{stop}"
    )]
    ResendLimit {
        port: PathBuf,
        line: u64,
        times: u32,
        last_acked: usize,
        stop: StopOutcome,
    },
    #[error(
        "printer on {port} asked for line {line}, which is no longer kept (oldest kept: \
         {oldest_kept}); stopping rather than guessing, last acknowledged line \
         {last_acked}{stop}"
    )]
    LineGone {
        port: PathBuf,
        line: u64,
        oldest_kept: u64,
        last_acked: usize,
        stop: StopOutcome,
    },
    #[error(
        "printer on {port} asked for line {line} again although it had confirmed line \
         {confirmed}: it lost its state (reset or power dip?); stopped rather than \
         replaying onto a half-printed part, last acknowledged line {last_acked}{stop}"
    )]
    LostState {
        port: PathBuf,
        line: u64,
        confirmed: u64,
        last_acked: usize,
        stop: StopOutcome,
    },
    #[error(
        "printer on {port} kept talking but acknowledged no line for {waited_s:.0} s; \
         stopped, last acknowledged line {last_acked}{stop}"
    )]
    NoProgress {
        port: PathBuf,
        waited_s: f64,
        last_acked: usize,
        stop: StopOutcome,
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
         {waited_s:.0} s in all, now {temperatures}); last acknowledged line \
         {last_acked}{stop}"
    )]
    HeatTimeout {
        port: PathBuf,
        command: String,
        waited_s: f64,
        temperatures: String,
        last_acked: usize,
        stop: StopOutcome,
    },
    #[error("job on {port} cancelled, last acknowledged line {last_acked}{stop}")]
    Cancelled {
        port: PathBuf,
        last_acked: usize,
        stop: StopOutcome,
    },
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
        "printer on {port} reported `{message}`, which the job cannot go on after, last \
         acknowledged line {last_acked}{stop}"
    )]
    FirmwareError {
        port: PathBuf,
        message: String,
        last_acked: usize,
        stop: StopOutcome,
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

    /// Whether the safe stop after the failure was confirmed, where one was made.
    pub fn stop_outcome(&self) -> StopOutcome {
        match self {
            PrintError::ResendLimit { stop, .. }
            | PrintError::LineGone { stop, .. }
            | PrintError::LostState { stop, .. }
            | PrintError::NoProgress { stop, .. }
            | PrintError::HeatTimeout { stop, .. }
            | PrintError::Cancelled { stop, .. }
            | PrintError::FirmwareError { stop, .. } => *stop,
            _ => StopOutcome::None,
        }
    }

    /// `stop`: what the protocol reported of its safe stop ([`Event::SafeStop`]) before the
    /// failure.
    fn from_failure(port: &Path, failure: Failure, stop: StopOutcome) -> Self {
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
                stop,
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
                stop,
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
                stop,
            },
            Failure::NoProgress { waited, last_acked } => PrintError::NoProgress {
                port,
                waited_s: waited.as_secs_f64(),
                last_acked,
                stop,
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
                stop,
            },
            Failure::Cancelled { last_acked } => PrintError::Cancelled {
                port,
                last_acked,
                stop,
            },
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
                stop,
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
    /// Between jobs: what the printer says, and the `M105`s that read its temperatures.
    idle: IdleWatch,
    /// The printer said `start` since the last job: it rebooted, so the next job begins
    /// with a fresh handshake.
    rebooted: bool,
}

/// What [`Connection::idle_for`] saw.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Idle {
    /// Nothing that needs acting on (reports and messages are logged).
    Quiet,
    /// The printer said `start`: it was reset or power-cycled. The next job begins with a
    /// fresh handshake and line numbering.
    Rebooted,
    /// A temperature report: the hotend and bed as read now (a heater the report left out
    /// keeps its last reading).
    Temperatures(Temperatures),
    /// No temperature report for [`IdleWatch::stale_after`] although the printer was
    /// asked: the last figures are no longer current.
    Silent,
}

/// Reading an idle printer between jobs. Its temperatures are asked for with an `M105`
/// every `temperature_interval`, sent without a line number: Marlin checks nothing on a
/// line without `N` and does not count it, so the line numbering of the next job is not
/// touched, and every firmware crispen speaks (Ultimaker2Marlin has no `M155`) answers it
/// with `ok T:.. /.. B:.. /..`. One is in flight at a time; an `ok` answers the oldest
/// unanswered one. Its `ok` must never be taken for a job line's: a job begins only once
/// every such answer is in ([`Connection::print`]), or is known lost.
#[derive(Debug)]
struct IdleWatch {
    /// An unfinished line of what the printer said.
    partial: Vec<u8>,
    /// `M105`s sent whose `ok` has not come.
    unanswered: u32,
    last_sent: Option<tokio::time::Instant>,
    next_poll: tokio::time::Instant,
    /// The last busy keep-alive or heat-wait report: the printer is inside a long command
    /// of its own (from its menu) and answers later.
    alive_at: Option<tokio::time::Instant>,
    temperatures: Temperatures,
    last_report: Option<tokio::time::Instant>,
    /// [`Idle::Silent`] was returned since the last report.
    silent: bool,
}

/// What a chunk of idle talk held.
#[derive(Debug, Default)]
struct Heard {
    rebooted: bool,
    report: bool,
}

impl IdleWatch {
    fn new() -> IdleWatch {
        IdleWatch {
            partial: Vec::new(),
            unanswered: 0,
            last_sent: None,
            next_poll: tokio::time::Instant::now(),
            alive_at: None,
            temperatures: Temperatures::default(),
            last_report: None,
            silent: false,
        }
    }

    /// After this, an `M105` still unanswered is taken as lost: an idle printer answers at
    /// once, and one busy with a command of its own says so (`busy:` every 2 s, or heat
    /// reports every second).
    fn answer_deadline(&self, wait: Duration) -> Option<tokio::time::Instant> {
        let since = self.last_sent.max(self.alive_at)?;
        (self.unanswered > 0).then_some(since + wait)
    }

    /// Figures older than this (since the last report) are not shown as current.
    fn stale_after(opts: &ProtocolOptions) -> Duration {
        opts.temperature_interval * 3 + opts.silence_probe
    }

    /// Splits `bytes` into lines (keeping an unfinished one), logs each, and takes the
    /// answers and reports among them.
    fn hear(&mut self, port: &Path, bytes: &[u8], now: tokio::time::Instant) -> Heard {
        let mut heard = Heard::default();
        for &b in bytes {
            if b != b'\n' {
                if self.partial.len() < 4096 {
                    self.partial.push(b);
                }
                continue;
            }
            let Some(reply) = Reply::parse(&std::mem::take(&mut self.partial)) else {
                continue;
            };
            match reply {
                Reply::Start => {
                    heard.rebooted = true;
                    // A reset forgets what it was asked.
                    self.unanswered = 0;
                    tracing::warn!(port = %port.display(), "printer rebooted while idle (it said `start`)");
                }
                Reply::Ok(ok) => {
                    self.unanswered = self.unanswered.saturating_sub(1);
                    if let Some(report) = ok.report {
                        self.take(report, now);
                        heard.report = true;
                    }
                }
                Reply::Temperatures(report) => {
                    if report.waiting {
                        self.alive_at = Some(now);
                    }
                    self.take(report, now);
                    heard.report = true;
                }
                Reply::Busy(line) => {
                    self.alive_at = Some(now);
                    tracing::debug!(port = %port.display(), "idle printer: {line}");
                }
                Reply::Fatal(line) | Reply::Error(line) => {
                    tracing::warn!(port = %port.display(), "idle printer: {line}")
                }
                Reply::Action(action) => {
                    // No job to act on: the printer's own menu was used between jobs.
                    tracing::info!(port = %port.display(), ?action, "idle printer asked the host to act; no job is running")
                }
                // NO_TIMEOUTS builds say `wait` every few seconds while idle.
                Reply::Wait => tracing::trace!(port = %port.display(), "idle printer: wait"),
                other => tracing::info!(port = %port.display(), "idle printer: {other:?}"),
            }
        }
        if heard.report {
            tracing::debug!(port = %port.display(), "idle printer: {}", describe_temps(&self.temperatures));
        }
        heard
    }

    fn take(&mut self, report: super::protocol::reply::Report, now: tokio::time::Instant) {
        let merge = |old: Option<Temp>, new: Option<Temp>| match (old, new) {
            (Some(old), Some(new)) => Some(Temp {
                current: new.current,
                target: new.target.or(old.target),
            }),
            (old, new) => new.or(old),
        };
        let t = report.temperatures;
        self.temperatures = Temperatures {
            hotend: merge(self.temperatures.hotend, t.hotend),
            bed: merge(self.temperatures.bed, t.bed),
        };
        self.last_report = Some(now);
        self.silent = false;
    }
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
            idle: IdleWatch::new(),
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
    /// a power cycle, host actions, messages) for up to `duration`, asking for its
    /// temperatures every `temperature_interval` (see [`IdleWatch`]). Returns early with
    /// [`Idle::Rebooted`] when the printer says `start`, with [`Idle::Temperatures`] on a
    /// report, with [`Idle::Silent`] once reports stop, and with an error if the link
    /// closes. Cancel-safe: the daemon races it against a bed being cleared.
    pub async fn idle_for(&mut self, duration: Duration) -> Result<Idle, PrintError> {
        let until = tokio::time::Instant::now() + duration;
        let interval = self.opts.protocol.temperature_interval;
        let answer_wait = self.opts.protocol.silence_probe;
        let stale_after = IdleWatch::stale_after(&self.opts.protocol);
        loop {
            let now = tokio::time::Instant::now();
            let idle = &mut self.idle;
            if idle.answer_deadline(answer_wait).is_some_and(|d| now >= d) {
                tracing::debug!(port = %self.port.display(), "an idle M105 went unanswered; taken as lost");
                idle.unanswered = 0;
            }
            if idle.unanswered == 0 && now >= idle.next_poll {
                self.transport.send(b"M105\n".to_vec());
                idle.unanswered = 1;
                idle.last_sent = Some(now);
                idle.next_poll = now + interval;
            }
            let stale_at = idle
                .last_report
                .filter(|_| !idle.silent)
                .map(|t| t + stale_after);
            if stale_at.is_some_and(|t| now >= t) {
                idle.silent = true;
                tracing::warn!(port = %self.port.display(), waited_s = stale_after.as_secs_f64(), "the idle printer stopped reporting its temperatures");
                return Ok(Idle::Silent);
            }
            let wake = [
                Some(until),
                idle.answer_deadline(answer_wait),
                (idle.unanswered == 0).then_some(idle.next_poll),
                stale_at,
            ]
            .into_iter()
            .flatten()
            .min()
            .unwrap_or(until);
            tokio::select! {
                link = self.transport.recv() => match link {
                    LinkEvent::Data(bytes) => {
                        let heard = self.idle.hear(&self.port, &bytes, tokio::time::Instant::now());
                        if heard.rebooted {
                            self.rebooted = true;
                            return Ok(Idle::Rebooted);
                        }
                        if heard.report {
                            return Ok(Idle::Temperatures(self.idle.temperatures));
                        }
                    }
                    LinkEvent::Closed(reason) => {
                        return Err(PrintError::Disconnected { port: self.port.clone(), reason, last_acked: 0 });
                    }
                },
                _ = tokio::time::sleep_until(wake) => {
                    if tokio::time::Instant::now() >= until {
                        return Ok(Idle::Quiet);
                    }
                }
            }
        }
    }

    /// Log what arrived between jobs and is not read yet; notes a reboot.
    fn drain_idle_input(&mut self) -> Result<(), PrintError> {
        while let Some(link) = self.transport.try_recv() {
            match link {
                LinkEvent::Data(bytes) => {
                    let now = tokio::time::Instant::now();
                    self.rebooted |= self.idle.hear(&self.port, &bytes, now).rebooted;
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

    /// Waits until every `M105` sent between jobs is answered (or known lost): an answer
    /// arriving after the job's `M110 N0` would be taken for its `ok`, and every later
    /// `ok` for the line before its own.
    async fn await_idle_answers(&mut self) -> Result<(), PrintError> {
        let answer_wait = self.opts.protocol.silence_probe;
        while let Some(deadline) = self.idle.answer_deadline(answer_wait) {
            tracing::debug!(port = %self.port.display(), "waiting for the answer to an idle M105 before the job starts");
            tokio::select! {
                link = self.transport.recv() => match link {
                    LinkEvent::Data(bytes) => {
                        let now = tokio::time::Instant::now();
                        self.rebooted |= self.idle.hear(&self.port, &bytes, now).rebooted;
                    }
                    LinkEvent::Closed(reason) => {
                        return Err(PrintError::Disconnected { port: self.port.clone(), reason, last_acked: 0 });
                    }
                },
                _ = tokio::time::sleep_until(deadline) => {
                    tracing::warn!(port = %self.port.display(), "an idle M105 went unanswered; starting the job as if it was lost");
                    self.idle.unanswered = 0;
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
        self.await_idle_answers().await?;
        self.idle.partial.clear();
        // Reports from before the job say nothing about after it: the watch starts afresh,
        // as on a new connection (the first look after a job longer than `stale_after`
        // found them stale and warned that the printer stopped reporting).
        self.idle.last_report = None;
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
        let mut stop = StopOutcome::None;
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
            flush(&mut self.host, &mut self.transport);
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
                        let err = PrintError::from_failure(&port, f, stop);
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
                        stop = StopOutcome::Confirmed;
                        tracing::info!(port = %port.display(), gcode = program.name(), "printer stopped safely: heaters, fan and motors off")
                    }
                    Event::SafeStop { confirmed: false } => {
                        stop = StopOutcome::NotConfirmed;
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
                Event::Failed(f) => {
                    return Err(PrintError::from_failure(port, f, StopOutcome::None))
                }
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

async fn sleep_until_opt(deadline: Option<tokio::time::Instant>) {
    match deadline {
        Some(d) => tokio::time::sleep_until(d).await,
        None => std::future::pending().await,
    }
}

fn flush(host: &mut Host, transport: &mut Transport) {
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
            StopOutcome::None,
        );
        let msg = err.to_string();
        assert!(msg.contains("/dev/ttyUSB3") && msg.contains("41"), "{msg}");
        assert_eq!(err.last_acked(), Some(41));
        // Whether the heaters were confirmed off is part of the error itself.
        let failure = Failure::ResendLimit {
            line: 7,
            times: 10,
            last_acked: 6,
        };
        let err = |stop| PrintError::from_failure(Path::new("/dev/ttyUSB3"), failure.clone(), stop);
        let confirmed = err(StopOutcome::Confirmed).to_string();
        assert!(
            confirmed.ends_with("; heaters, fan and motors confirmed off"),
            "{confirmed}"
        );
        let not = err(StopOutcome::NotConfirmed);
        assert!(
            not.to_string()
                .ends_with("heaters NOT confirmed off: check the printer now"),
            "{not}"
        );
        assert_eq!(not.stop_outcome(), StopOutcome::NotConfirmed);
    }

    /// An idle `M105` whose answer is still on its way when a job starts: the job waits
    /// for it, so its `ok` is never taken for the job's `M110` (and every later `ok` for
    /// the line before its own). Checked on a link with a real round trip (300 ms each
    /// way), for every firmware flavour: the host never counts a job line acknowledged
    /// before the printer has executed it, no line is resent, and each runs exactly once.
    #[tokio::test]
    async fn an_idle_m105_in_flight_when_a_job_starts_is_not_taken_for_its_answers() {
        use crate::marlin::sim::{is_housekeeping, spawn, SimConfig};
        // Ten lines: an answer taken for the wrong line shows at the first ones, and each
        // line costs two 300 ms link delays.
        let commands: Vec<String> = (0..10)
            .map(|i| match i % 2 {
                0 => format!("M106 S{}", i * 8),
                _ => "M107".to_string(),
            })
            .collect();
        let program = GcodeProgram::from_commands("fans.gcode", commands.clone());
        for firmware in [Firmware::Marlin20, Firmware::Ultimaker2, Firmware::Marlin2] {
            let mut sim = SimConfig::new(firmware);
            sim.link_latency = Duration::from_millis(300);
            let printer = spawn(sim).unwrap();
            let opts = StreamOptions::for_firmware(firmware);
            let mut conn = Connection::open(printer.device_path(), &opts)
                .await
                .unwrap();
            // The first poll goes at once; the watch is cut short (as the daemon's is when
            // a job arrives) long before its answer can be back.
            let watched = tokio::time::timeout(
                Duration::from_millis(50),
                conn.idle_for(Duration::from_secs(60)),
            )
            .await;
            assert!(watched.is_err(), "{firmware:?}: nothing came back in 50 ms");
            assert_eq!(conn.idle.unanswered, 1, "{firmware:?}: an M105 in flight");

            let (progress_tx, mut progress_rx) = watch::channel(PrintProgress::default());
            let (_control, control_rx) = mpsc::channel(1);
            let print = conn.print(&program, control_rx, progress_tx);
            tokio::pin!(print);
            let executed_job_lines = || {
                printer
                    .executed()
                    .iter()
                    .filter(|c| !is_housekeeping(c))
                    .count()
            };
            let mut ahead = None;
            let report = loop {
                tokio::select! {
                    report = &mut print => break report,
                    Ok(()) = progress_rx.changed() => {
                        let acked = progress_rx.borrow_and_update().lines_acked;
                        // Read after the figure: the printer's count can only have grown.
                        let executed = executed_job_lines();
                        if acked > executed {
                            ahead.get_or_insert((acked, executed));
                        }
                    }
                }
            };
            let report = report.unwrap_or_else(|e| panic!("{firmware:?}: {e}"));
            assert_eq!(
                ahead, None,
                "{firmware:?}: (lines the host counted acknowledged, lines the printer had run)"
            );
            assert_eq!(report.resends, 0, "{firmware:?}");
            let job: Vec<String> = printer
                .executed()
                .into_iter()
                .filter(|c| !is_housekeeping(c))
                .collect();
            assert_eq!(job, commands, "{firmware:?}: every line once, in order");
        }
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
