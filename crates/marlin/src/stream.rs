//! Streaming a G-code program to a printer: the async driver that joins the pure protocol
//! state machine ([`super::protocol::Host`]) to the serial link ([`super::transport`]),
//! to a control channel (pause/resume/cancel) and to a progress watch. The daemon's
//! printer supervisors and `crispen print` both use [`Connection`].
//!
//! Beside it: why a print failed ([`PrintError`], in `error.rs`) and the idle printer
//! between jobs ([`Idle`] and the watch that reads its temperatures, in `idle.rs`).

use super::firmware::Firmware;
use super::gcode::{GcodeCommands, GcodeProgram};
use super::motion::Motion;
use super::pause::{find_pauses, heaters_off_lines, park_lines, resume_lines, FilePause};
use super::plate::{JobLines, PartFilter};
use super::protocol::reply::HostAction;
use super::protocol::{Event, HeatWaitEstimate, Host, ProtocolOptions};
use super::reader;
use super::transport::{LinkEvent, Transport};
use serde::Serialize;
use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::time::{Duration, Instant};
use tokio::sync::{mpsc, watch};

mod error;
mod idle;

pub use super::pause::PauseSettings;
pub use super::protocol::{FirmwareInfo, Temp, Temperatures};
pub use error::{PrintError, StopOutcome};
pub use idle::Idle;

use idle::IdleWatch;

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
    /// How the pauses a file asks for are made (park, heaters-off time). None: a file with
    /// one is refused before anything is sent (there is no operator to resume it).
    pub pause: Option<PauseSettings>,
}

impl StreamOptions {
    pub fn for_firmware(firmware: Firmware) -> Self {
        StreamOptions {
            firmware,
            baud: firmware.default_baud(),
            send_ahead: true,
            connect_timeout: Duration::from_secs(20),
            protocol: ProtocolOptions::for_firmware(firmware),
            pause: None,
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
    /// Stop printing this part of the plate (its number in the file's
    /// [`Marks`](super::plate::Marks)) from the next line not sent; the last part cancels
    /// the print.
    CancelPart(u16),
}

/// A part of a plate the host stopped printing.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, serde::Deserialize)]
pub struct CancelledPart {
    /// Its number in the file's [`Marks`](super::plate::Marks), and its name.
    pub part: u16,
    pub name: String,
    /// The job's command (0-based) it was dropped from: every line before it was sent as
    /// the file has it.
    pub from: usize,
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
    /// At a pause the file asks for: parked, waiting for the operator to resume
    /// ([`PrintProgress::pause`] says why).
    WaitingForOperator,
    Cancelling,
    Done,
    Failed,
}

/// A pause the file asked for, as shown while the printer waits at it.
#[derive(Debug, Clone, Serialize, serde::Deserialize, PartialEq)]
pub struct PauseInfo {
    /// What the operator is told (the command's text or the last `M117` message).
    pub message: String,
    /// The pause command as written, and its line in the file.
    pub command: String,
    pub line: Option<usize>,
    /// The head was parked (false: its position was not known from the file, so it was
    /// not moved).
    pub parked: bool,
    /// Nobody resumed in time: the heaters were turned off; the resume heats up first.
    pub heaters_off: bool,
}

#[derive(Debug, Clone, Serialize, Default)]
pub struct PrintProgress {
    pub lines_acked: usize,
    pub lines_total: usize,
    pub hotend: Option<Temp>,
    pub bed: Option<Temp>,
    pub state: PrintState,
    pub elapsed_s: f64,
    /// Set while the print waits at a pause the file asked for.
    pub pause: Option<PauseInfo>,
    /// The parts of the plate cancelled so far, in order.
    pub cancelled_parts: Vec<CancelledPart>,
    /// Set while a stop waits for the printer's heat-up to end.
    pub stop_wait: Option<StopWait>,
}

/// A stop (a cancel, a failure, a shutdown) that waits for the printer's heat-up to end: its
/// firmware reads nothing while it waits for a heater (Ultimaker2Marlin), so the heaters go
/// off only then. Figures, for the log and the printer's status.
#[derive(Debug, Clone, Serialize, serde::Deserialize, PartialEq)]
pub struct StopWait {
    /// The heat wait the printer is in (`M109 S210`), where the host sent it.
    pub command: Option<String>,
    /// The bed's heater, else the hotend's.
    pub bed: bool,
    pub current_c: Option<f64>,
    pub target_c: Option<f64>,
    /// At the rate the heater has closed in on its target so far.
    pub remaining_s: Option<f64>,
    /// The longest the host waits: until the heater has not come closer to its target for
    /// the heat timeout.
    pub limit_s: f64,
}

impl From<HeatWaitEstimate> for StopWait {
    fn from(e: HeatWaitEstimate) -> Self {
        StopWait {
            command: e.command,
            bed: e.bed,
            current_c: e.current,
            target_c: e.target,
            remaining_s: e.remaining.map(|d| d.as_secs_f64()),
            limit_s: e.limit.as_secs_f64(),
        }
    }
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

impl Connection {
    /// Open the port and run the handshake (wait for `start` or quiet, M110, M115).
    pub async fn open(port: &Path, opts: &StreamOptions) -> Result<Connection, PrintError> {
        let mut transport = Transport::open(port, opts.baud).await?;
        let (host, info) = greet(&mut transport, port, opts).await?;
        tracing::info!(port = %port.display(), firmware = ?info.name, "printer connected");
        let mut connection = Connection {
            transport,
            host,
            port: port.to_path_buf(),
            opts: opts.clone(),
            info,
            idle: IdleWatch::new(),
            rebooted: false,
        };
        connection.ask_settings().await?;
        Ok(connection)
    }

    pub fn firmware_info(&self) -> &FirmwareInfo {
        &self.info
    }

    /// The planner's settings as the printer reported them in answer to `M503` (or in a
    /// boot banner since), one command a line (`M203 X300.00 Y300.00 Z5.00 E25.00`); empty
    /// where it reported none.
    pub fn settings(&self) -> &[String] {
        &self.idle.settings
    }

    /// Asks the greeted printer for its planner's settings with an `M503` sent without a
    /// line number, as the idle `M105`s are (the next job's numbering is not touched), and
    /// waits until it is answered. A firmware without `M503` answers `Unknown command` and
    /// `ok`: no settings, and the estimate rests on the machine's stock values.
    async fn ask_settings(&mut self) -> Result<(), PrintError> {
        self.transport.send(b"M503\n".to_vec());
        self.synchronize().await
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
                        if let Some(message) = heard.halted {
                            return Ok(Idle::Halted(message));
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

    /// Makes sure every answer to what was sent between jobs is in before a job's first
    /// line goes: sends the sync line (see [`idle::sync_line`]) and waits for its echo and
    /// `ok`. Each wait is `silence_probe`, longer while the printer says it is busy; then a
    /// new sync line goes, with a number of its own. A printer that answers none within
    /// `connect_timeout` is not answering.
    async fn synchronize(&mut self) -> Result<(), PrintError> {
        let started = tokio::time::Instant::now();
        let give_up = started + self.opts.connect_timeout;
        let wait = self.opts.protocol.silence_probe;
        self.transport.send(self.idle.begin_sync(started));
        loop {
            let deadline = self
                .idle
                .sync_deadline(wait)
                .unwrap_or(give_up)
                .min(give_up);
            tokio::select! {
                link = self.transport.recv() => match link {
                    LinkEvent::Data(bytes) => {
                        let heard = self.idle.hear(&self.port, &bytes, tokio::time::Instant::now());
                        self.rebooted |= heard.rebooted;
                        if heard.synced {
                            return Ok(());
                        }
                    }
                    LinkEvent::Closed(reason) => {
                        return Err(PrintError::Disconnected { port: self.port.clone(), reason, last_acked: 0 });
                    }
                },
                _ = tokio::time::sleep_until(deadline) => {
                    let now = tokio::time::Instant::now();
                    if now >= give_up {
                        return Err(PrintError::NoAnswer { port: self.port.clone(), waited_s: (now - started).as_secs_f64() });
                    }
                    tracing::debug!(port = %self.port.display(), "the sync line is not answered yet; sending another");
                    self.transport.send(self.idle.begin_sync(now));
                }
            }
        }
    }

    /// Begin the next job on a clean link: what the printer said between jobs is logged,
    /// not taken for answers to this job; after a reboot the handshake runs again (the
    /// firmware may even have changed), which lets the boot banner through first.
    async fn clean_link(&mut self) -> Result<(), PrintError> {
        self.drain_idle_input()?;
        self.synchronize().await?;
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
            self.ask_settings().await?;
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
    ///
    /// A pause the file asks for ([`FILE_PAUSES`](super::gcode::FILE_PAUSES)) is never sent:
    /// the job is streamed in parts between its pauses. At each pause the part before it has
    /// ended (every line answered, and an `M105` after them, so the printer has taken them
    /// all), the head is parked, and the print waits for [`StreamControl::Resume`]; see
    /// [`super::pause`]. Without [`StreamOptions::pause`] such a file is refused before
    /// anything is sent.
    pub async fn print(
        &mut self,
        program: &GcodeProgram,
        control: mpsc::Receiver<StreamControl>,
        progress: watch::Sender<PrintProgress>,
    ) -> Result<PrintReport, PrintError> {
        self.print_plate(program, &[], control, progress).await
    }

    /// [`Connection::print`], with parts of the plate cancelled before it starts (their
    /// numbers in the file's [`Marks`](super::plate::Marks)): they are dropped from its
    /// first line. A program whose file labels no parts has nothing to cancel.
    pub async fn print_plate(
        &mut self,
        program: &GcodeProgram,
        cancelled: &[u16],
        mut control: mpsc::Receiver<StreamControl>,
        progress: watch::Sender<PrintProgress>,
    ) -> Result<PrintReport, PrintError> {
        let pauses = find_pauses(program.commands());
        if let (Some(first), None) = (pauses.first(), &self.opts.pause) {
            return Err(PrintError::PauseWithoutOperator {
                file: program.name().to_string(),
                line: program.source_line(first.index).unwrap_or(0),
                command: first.command.clone(),
            });
        }
        let mut run = Run {
            started: Instant::now(),
            total: program.len(),
            port: self.port.clone(),
            name: program.name().to_string(),
            progress,
            pause: None,
            stop_wait: None,
            control_open: true,
            sent: Sent::default(),
            filter: program
                .marks()
                .map(|marks| PartFilter::new(Arc::clone(marks), program.firmware())),
            cancelled: Vec::new(),
            all: program.shared_commands(),
        };
        for &part in cancelled {
            run.cancel_part(None, part);
        }
        if run.filter.as_ref().is_some_and(PartFilter::all_cancelled) {
            return Err(PrintError::Cancelled {
                port: run.port.clone(),
                last_acked: 0,
                stop: StopOutcome::None,
            });
        }
        let commands = program.shared_commands();
        let mut motion = Motion::new(self.opts.firmware);
        let mut from = 0;
        for pause in &pauses {
            let part = commands.part(from..pause.index);
            if !part.is_empty() {
                self.stream_part(&mut run, &mut control, part.clone(), from, Part::Job)
                    .await?;
            }
            for command in part.iter().filter_map(|c| reader::read(c).ok().flatten()) {
                // What cannot be followed was refused at preparation (the G-code policy;
                // only the daemon streams files with pauses).
                let _ = motion.apply(&command);
            }
            let line = program.source_line(pause.index);
            self.wait_for_operator(&mut run, &mut control, pause, line, &motion)
                .await?;
            from = pause.index + 1;
        }
        let rest = commands.part(from..commands.len());
        if !rest.is_empty() || pauses.is_empty() {
            self.stream_part(&mut run, &mut control, rest, from, Part::Job)
                .await?;
        }
        run.publish(run.total, self.host.temperatures(), PrintState::Done);
        tracing::info!(port = %run.port.display(), gcode = run.name, lines = run.total, "print finished");
        Ok(PrintReport {
            port: run.port.clone(),
            lines_total: run.total,
            lines_acked: run.total,
            lines_sent: run.sent.lines_sent,
            resends: run.sent.resends,
            silence_probes: run.sent.probes,
            fragments: run.sent.fragments,
            duration_s: run.started.elapsed().as_secs_f64(),
        })
    }

    /// At a pause the file asks for (the part before it has ended): park, wait for the
    /// operator (turning the heaters off once [`PauseSettings::heaters_off_after`] has
    /// passed), then heat up again if needed and return to the print. A cancel meanwhile
    /// stops the printer safely; a reset or a lost link fails the job.
    async fn wait_for_operator(
        &mut self,
        run: &mut Run,
        control: &mut mpsc::Receiver<StreamControl>,
        pause: &FilePause,
        line: Option<usize>,
        motion: &Motion,
    ) -> Result<(), PrintError> {
        let settings = self
            .opts
            .pause
            .clone()
            .expect("a file with pauses is refused without pause settings");
        let at = pause.index;
        // The targets in force before the pause: what a resume after heaters-off restores.
        let before = self.host.temperatures();
        let park = park_lines(&settings, motion);
        run.pause = Some(PauseInfo {
            message: pause.message.clone(),
            command: pause.command.clone(),
            line,
            parked: park.is_some(),
            heaters_off: false,
        });
        tracing::info!(port = %run.port.display(), gcode = run.name, line, command = pause.command, message = pause.message, "the file asks for a pause; parking and waiting for the operator");
        match park {
            Some(lines) => {
                self.stream_part(run, control, GcodeCommands::from(lines), at, Part::Park)
                    .await?
            }
            None => {
                tracing::warn!(port = %run.port.display(), gcode = run.name, "the head's position is not known from the file (homed, or not moved yet): not parked")
            }
        }
        let mut shown = before;
        run.publish(at, shown, PrintState::WaitingForOperator);
        let heaters_off_at = tokio::time::Instant::now() + settings.heaters_off_after;
        let mut heaters_off = false;
        enum Woke {
            Idle(Result<Idle, PrintError>),
            Control(Option<StreamControl>),
            HeatersOff,
        }
        loop {
            let woke = tokio::select! {
                idle = self.idle_for(Duration::from_secs(3600)) => Woke::Idle(idle),
                cmd = control.recv(), if run.control_open => Woke::Control(cmd),
                _ = tokio::time::sleep_until(heaters_off_at), if !heaters_off => Woke::HeatersOff,
            };
            match woke {
                Woke::Idle(Ok(Idle::Temperatures(t))) => {
                    shown = t;
                    run.publish(at, shown, PrintState::WaitingForOperator);
                }
                Woke::Idle(Ok(Idle::Rebooted)) => {
                    run.publish(at, shown, PrintState::Failed);
                    return Err(PrintError::PrinterReset {
                        port: run.port.clone(),
                        last_acked: at,
                    });
                }
                Woke::Idle(Ok(Idle::Quiet | Idle::Silent)) => {}
                Woke::Idle(Ok(Idle::Halted(message))) => {
                    run.publish(at, shown, PrintState::Failed);
                    return Err(PrintError::Fatal {
                        port: run.port.clone(),
                        message,
                        last_acked: at,
                    });
                }
                Woke::Idle(Err(e)) => {
                    run.publish(at, shown, PrintState::Failed);
                    return Err(e.in_part(at, false));
                }
                Woke::Control(None) => run.control_open = false,
                Woke::Control(Some(StreamControl::Resume)) => break,
                Woke::Control(Some(StreamControl::Pause)) => {}
                Woke::Control(Some(StreamControl::CancelPart(part)))
                    if !run.cancel_part(None, part) =>
                {
                    run.publish(at, shown, PrintState::WaitingForOperator);
                }
                Woke::Control(Some(StreamControl::Cancel | StreamControl::CancelPart(_))) => {
                    run.publish(at, shown, PrintState::Cancelling);
                    let stop = GcodeCommands::from(
                        ["M104 S0", "M140 S0", "M107", "M84"]
                            .map(String::from)
                            .to_vec(),
                    );
                    let confirmed = self.stream_part(run, control, stop, at, Part::Stop).await;
                    let stop = match confirmed {
                        Ok(()) => StopOutcome::Confirmed,
                        Err(e) => {
                            tracing::error!(port = %run.port.display(), gcode = run.name, "the printer did not confirm heaters off: {e}");
                            StopOutcome::NotConfirmed
                        }
                    };
                    run.publish(at, shown, PrintState::Failed);
                    return Err(PrintError::Cancelled {
                        port: run.port.clone(),
                        last_acked: at,
                        stop,
                    });
                }
                Woke::HeatersOff => {
                    tracing::warn!(port = %run.port.display(), gcode = run.name, waited_s = settings.heaters_off_after.as_secs_f64(), "nobody resumed the pause; heaters off (the job keeps waiting)");
                    let off = GcodeCommands::from(heaters_off_lines());
                    self.stream_part(run, control, off, at, Part::Waiting)
                        .await?;
                    heaters_off = true;
                    if let Some(p) = &mut run.pause {
                        p.heaters_off = true;
                    }
                    shown = self.host.temperatures();
                    run.publish(at, shown, PrintState::WaitingForOperator);
                }
            }
        }
        tracing::info!(port = %run.port.display(), gcode = run.name, heaters_off, "the operator resumed the pause");
        let lines = resume_lines(
            &settings,
            motion,
            run.pause.as_ref().is_some_and(|p| p.parked),
            heaters_off.then_some(&before),
        );
        run.pause = None;
        self.stream_part(run, control, GcodeCommands::from(lines), at, Part::Resume)
            .await
    }

    /// Streams one part: job lines from job command `offset` on, or host lines of a pause.
    /// Returns when every line was answered (and an `M105` after them).
    async fn stream_part(
        &mut self,
        run: &mut Run,
        control: &mut mpsc::Receiver<StreamControl>,
        commands: GcodeCommands,
        offset: usize,
        part: Part,
    ) -> Result<(), PrintError> {
        self.clean_link().await?;
        let port = self.port.clone();
        let job_lines = part == Part::Job;
        let acked = |host: &Host| {
            if job_lines {
                offset + host.acked_job_lines()
            } else {
                offset
            }
        };
        let mut state = part.state();
        let mut stop = StopOutcome::None;
        let lines = match run.filter.take().filter(|_| job_lines) {
            Some(filter) => JobLines::filtered(commands, run.all.clone(), offset, filter),
            None => JobLines::from(commands),
        };
        self.host.start_job(lines, Instant::now());
        // The printer's report showed its heaters off during a stop (`Event::HeatersOff`).
        let mut heaters_off = false;
        run.publish(acked(&self.host), self.host.temperatures(), state);
        let mut last_publish = Instant::now();
        loop {
            flush(&mut self.host, &mut self.transport);
            let mut changed = false;
            // State changes are published at once; counters at most every 100 ms.
            let mut state_changed = false;
            while let Some(event) = self.host.poll_event() {
                match event {
                    Event::Done(summary) => {
                        if let Some(filter) = self.host.job_lines().take_filter() {
                            run.filter = Some(filter);
                        }
                        run.sent.lines_sent += summary.lines_sent;
                        run.sent.resends += summary.resends;
                        run.sent.probes += summary.probes;
                        run.sent.fragments += summary.fragments;
                        run.publish(acked(&self.host), self.host.temperatures(), state);
                        return Ok(());
                    }
                    Event::Failed(f) => {
                        run.publish(
                            acked(&self.host),
                            self.host.temperatures(),
                            PrintState::Failed,
                        );
                        let err =
                            PrintError::from_failure(&port, f, stop).in_part(offset, job_lines);
                        tracing::warn!(port = %port.display(), gcode = run.name, "print failed: {err}");
                        return Err(err);
                    }
                    Event::Progress { .. } | Event::Temperatures(_) => changed = true,
                    Event::Paused => {
                        state = PrintState::Paused;
                        state_changed = true;
                    }
                    Event::Resumed => {
                        state = part.state();
                        state_changed = true;
                    }
                    Event::Resend { line, replay } => {
                        tracing::debug!(port = %port.display(), gcode = run.name, line, replay, "printer asked for a resend")
                    }
                    Event::Probe => {
                        tracing::debug!(port = %port.display(), gcode = run.name, "printer silent; probing with M105")
                    }
                    Event::Busy(_) => {}
                    Event::Message(m) => {
                        tracing::debug!(port = %port.display(), gcode = run.name, "printer: {m}")
                    }
                    Event::Fragment(text) => {
                        tracing::warn!(port = %port.display(), gcode = run.name, "printer answered a piece of a line on its own: {text}")
                    }
                    Event::HostAction(action) => {
                        tracing::info!(port = %port.display(), gcode = run.name, ?action, "printer asked the host to act");
                        match action {
                            HostAction::Cancel => state = PrintState::Cancelling,
                            HostAction::Pause => state = PrintState::Pausing,
                            HostAction::Resume | HostAction::Other(_) => {}
                        }
                        state_changed = true;
                    }
                    Event::SafeStop { confirmed: true } => {
                        stop = StopOutcome::Confirmed;
                        tracing::info!(port = %port.display(), gcode = run.name, "printer stopped safely: heaters, fan and motors off")
                    }
                    Event::SafeStop { confirmed: false } if heaters_off => {
                        stop = StopOutcome::HeatersOff;
                        tracing::warn!(port = %port.display(), gcode = run.name, "the printer did not take the stop's numbered lines (fan and motors), but its report shows its heaters off")
                    }
                    Event::SafeStop { confirmed: false } => {
                        stop = StopOutcome::NotConfirmed;
                        tracing::error!(port = %port.display(), gcode = run.name, "the printer did not confirm heaters off; check it now")
                    }
                    Event::HeatersOff => {
                        if !heaters_off {
                            tracing::info!(port = %port.display(), gcode = run.name, "the printer's report shows its heaters off");
                        }
                        heaters_off = true;
                    }
                    Event::StopWaitsForHeat(estimate) => {
                        let wait = StopWait::from(estimate);
                        // Said again as the heater's reports come: the log has the first.
                        if run.stop_wait.is_none() {
                            tracing::warn!(
                                port = %port.display(),
                                gcode = run.name,
                                command = wait.command.as_deref().unwrap_or("?"),
                                current_c = wait.current_c,
                                target_c = wait.target_c,
                                remaining_s = wait.remaining_s,
                                limit_s = wait.limit_s,
                                "the stop waits for the heat-up: the firmware reads nothing until it ends, then the heaters go off"
                            );
                        }
                        run.stop_wait = Some(wait);
                        state_changed = true;
                    }
                    Event::Connected(_) => {}
                }
            }
            if run.stop_wait.is_some() && !self.host.heating() {
                run.stop_wait = None;
                state_changed = true;
            }
            if state_changed || (changed && last_publish.elapsed() >= Duration::from_millis(100)) {
                let shown = if state == PrintState::Printing && self.host.heating() {
                    PrintState::Heating
                } else {
                    state
                };
                run.publish(acked(&self.host), self.host.temperatures(), shown);
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
                        run.publish(acked(&self.host), self.host.temperatures(), PrintState::Failed);
                        let last_acked = acked(&self.host);
                        tracing::warn!(port = %port.display(), gcode = run.name, last_acked, "printer disconnected: {reason}");
                        return Err(PrintError::Disconnected { port: port.clone(), reason, last_acked });
                    }
                },
                cmd = control.recv(), if run.control_open => match cmd {
                    // The host's own lines of a pause are not paused: they are short, and
                    // the print is waiting for the operator around them anyway.
                    Some(StreamControl::Pause) if job_lines => {
                        state = PrintState::Pausing;
                        self.host.pause(Instant::now());
                        run.publish(acked(&self.host), self.host.temperatures(), state);
                    }
                    Some(StreamControl::Resume) if job_lines => self.host.resume(Instant::now()),
                    Some(StreamControl::Pause | StreamControl::Resume) => {
                        tracing::debug!(port = %port.display(), gcode = run.name, "pause/resume ignored while the host parks or resumes the printer");
                    }
                    Some(StreamControl::CancelPart(p)) if !run.cancel_part(Some(self.host.job_lines()), p) => {
                        tracing::info!(port = %port.display(), gcode = run.name, part = p, "a part of the plate cancelled");
                        run.publish(acked(&self.host), self.host.temperatures(), state);
                    }
                    Some(StreamControl::Cancel | StreamControl::CancelPart(_)) => {
                        state = PrintState::Cancelling;
                        self.host.cancel(Instant::now());
                        run.publish(acked(&self.host), self.host.temperatures(), state);
                    }
                    None => run.control_open = false,
                },
                _ = sleep_until_opt(deadline) => self.host.tick(Instant::now()),
            }
        }
    }
}

/// What a part of a print streams: the job's own lines, or the host's lines around a pause.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Part {
    Job,
    /// Parking at a pause.
    Park,
    /// Heaters off during a long pause.
    Waiting,
    /// Heating up again and returning to the print.
    Resume,
    /// The safe stop of a cancel during a pause.
    Stop,
}

impl Part {
    fn state(self) -> PrintState {
        match self {
            Part::Job | Part::Resume => PrintState::Printing,
            Part::Park => PrintState::Pausing,
            Part::Waiting => PrintState::WaitingForOperator,
            Part::Stop => PrintState::Cancelling,
        }
    }
}

/// One print across its parts: what is published, and the counts of the report.
struct Run {
    started: Instant,
    total: usize,
    port: PathBuf,
    name: String,
    progress: watch::Sender<PrintProgress>,
    pause: Option<PauseInfo>,
    stop_wait: Option<StopWait>,
    control_open: bool,
    sent: Sent,
    /// The plate's filter while no part of the job streams (between its parts, at a
    /// pause); a part streaming holds it in its lines.
    filter: Option<PartFilter>,
    /// The parts cancelled so far.
    cancelled: Vec<CancelledPart>,
    /// The whole job's commands, which the filter's indices count.
    all: GcodeCommands,
}

/// The report's counts, summed over the parts.
#[derive(Debug, Default)]
struct Sent {
    lines_sent: u64,
    resends: u64,
    probes: u64,
    fragments: u64,
}

impl Run {
    /// Cancels a part of the plate (in `lines`' filter while a part of the job streams,
    /// else in the run's). Returns whether every part is cancelled now: the print is then
    /// cancelled as a whole.
    fn cancel_part(&mut self, lines: Option<&mut JobLines>, part: u16) -> bool {
        let filter = match lines.and_then(JobLines::filter_mut) {
            Some(filter) => Some(filter),
            None => self.filter.as_mut(),
        };
        let Some(filter) = filter else {
            tracing::warn!(port = %self.port.display(), gcode = self.name, part, "a part cancelled, but the file labels no parts");
            return false;
        };
        let Some(from) = filter.cancel(part) else {
            tracing::warn!(port = %self.port.display(), gcode = self.name, part, "no such part to cancel");
            return false;
        };
        if !self.cancelled.iter().any(|c| c.part == part) {
            let name = filter.marks().names()[usize::from(part)].clone();
            tracing::info!(port = %self.port.display(), gcode = self.name, part = name, from, "part cancelled: its lines are dropped from here on");
            self.cancelled.push(CancelledPart { part, name, from });
        }
        filter.all_cancelled()
    }

    fn publish(&self, acked: usize, t: Temperatures, state: PrintState) {
        let elapsed = self.started.elapsed().as_secs_f64();
        let total = self.total;
        self.progress.send_replace(PrintProgress {
            lines_acked: acked,
            lines_total: total,
            hotend: t.hotend,
            bed: t.bed,
            state,
            elapsed_s: elapsed,
            pause: self.pause.clone(),
            cancelled_parts: self.cancelled.clone(),
            stop_wait: self.stop_wait.clone(),
        });
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
