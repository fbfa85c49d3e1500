//! The Marlin host protocol as a pure state machine: bytes from the printer and the current
//! time go in; lines to send, events and the next deadline come out. No ports, no clocks,
//! so every corner (resend storms, lost `ok`s, garbage, resets) is unit-tested directly and
//! the async driver in [`super::stream`] stays thin.
//!
//! Exactly-once delivery rests on the printer's own line-number check: it executes line
//! `N` only if it follows the last one it accepted, and asks for the rest again otherwise.
//! The host therefore never skips or re-orders; it replays everything from a requested line.
//! `ok` counting only drives flow control and progress, and it heals itself: an `ok`
//! carrying a temperature report answers an `M105`, which the printer processes after every
//! earlier line, so it acknowledges everything up to that `M105`. A job only counts as done
//! after such a final `M105` is answered.

use super::firmware::Firmware;
use super::gcode::GcodeCommands;
use serde::Serialize;
use std::collections::{BTreeMap, VecDeque};
use std::time::{Duration, Instant};

/// XOR of every byte, as Marlin checks it.
pub fn checksum(bytes: &[u8]) -> u8 {
    bytes.iter().fold(0, |acc, b| acc ^ b)
}

/// `N<number> <command>*<checksum>\n`.
pub fn frame(number: u64, command: &str) -> String {
    let body = format!("N{number} {command}");
    let cs = checksum(body.as_bytes());
    format!("{body}*{cs}\n")
}

/// Upper bound of `frame(number, command).len()` without building the line: `N`, the
/// number, a space, the command, `*`, a checksum of at most three digits and `\n`.
fn wire_len_bound(number: u64, command: &str) -> usize {
    let digits = number.checked_ilog10().map_or(1, |d| d as usize + 1);
    1 + digits + 1 + command.len() + 1 + 3 + 1
}

/// Tunables; [`ProtocolOptions::for_firmware`] gives sensible values.
#[derive(Debug, Clone)]
pub struct ProtocolOptions {
    pub firmware: Firmware,
    /// Keep several lines in flight within the printer's receive buffer (false: one line in
    /// flight, as OctoPrint and Printrun do).
    pub send_ahead: bool,
    /// After opening, proceed when the printer has been quiet this long (no `start` seen).
    pub quiet_period: Duration,
    /// During the handshake, retry when a line gets no answer for this long.
    pub answer_timeout: Duration,
    /// No byte from the printer for this long while a short command is unacknowledged:
    /// probe with `M105`.
    pub silence_probe: Duration,
    /// No byte at all for this long while waiting on a short command: fail the job.
    pub silence_fail: Duration,
    /// No byte at all for this long while a long command (G28, G29, M400, G4) runs.
    pub long_command_timeout: Duration,
    /// M109/M190 not finished after this long: stop safely and fail the job.
    pub heat_timeout: Duration,
    /// Interval of temperature reports (autoreport) or polls.
    pub temperature_interval: Duration,
    /// How many times the same line may be requested again before the job fails.
    pub resend_limit: u32,
    /// Lines kept for resends. Marlin only ever asks for a line it has not acknowledged
    /// (those are always kept), so this needs to cover the send-ahead window, not the job.
    pub history_lines: usize,
}

impl ProtocolOptions {
    pub fn for_firmware(firmware: Firmware) -> Self {
        ProtocolOptions {
            firmware,
            send_ahead: true,
            quiet_period: Duration::from_millis(1500),
            answer_timeout: Duration::from_secs(3),
            silence_probe: Duration::from_secs(3),
            silence_fail: Duration::from_secs(30),
            long_command_timeout: Duration::from_secs(900),
            heat_timeout: Duration::from_secs(1200),
            temperature_interval: Duration::from_secs(2),
            resend_limit: 10,
            // Each kept line is a copy of its command: a whole job's worth costs MBs per printer.
            history_lines: 1024,
        }
    }
}

/// One heater's reading.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Default)]
pub struct Temp {
    pub current: f64,
    pub target: Option<f64>,
}

#[derive(Debug, Clone, Copy, PartialEq, Serialize, Default)]
pub struct Temperatures {
    pub hotend: Option<Temp>,
    pub bed: Option<Temp>,
}

/// What the printer said about itself in answer to `M115`.
#[derive(Debug, Clone, PartialEq, Serialize, Default)]
pub struct FirmwareInfo {
    pub name: Option<String>,
    pub protocol_version: Option<String>,
    pub machine_type: Option<String>,
    pub extruder_count: Option<u32>,
    /// `Cap:NAME:0|1` lines (empty on firmware without them, e.g. Ultimaker2Marlin).
    pub capabilities: BTreeMap<String, bool>,
}

impl FirmwareInfo {
    pub fn capability(&self, name: &str) -> Option<bool> {
        self.capabilities.get(name).copied()
    }
}

/// Why a connection or job ended without success. `last_acked` counts job commands the
/// printer acknowledged (commands 1..=last_acked are done).
#[derive(Debug, Clone, PartialEq)]
pub enum Failure {
    NoAnswer {
        waited: Duration,
    },
    PrinterReset {
        last_acked: usize,
    },
    Fatal {
        message: String,
        last_acked: usize,
    },
    ResendLimit {
        line: u64,
        times: u32,
        last_acked: usize,
    },
    LineGone {
        line: u64,
        oldest_kept: u64,
        last_acked: usize,
    },
    Silent {
        waited: Duration,
        last_acked: usize,
    },
    HeatTimeout {
        command: String,
        waited: Duration,
        temperatures: Temperatures,
        last_acked: usize,
    },
    Cancelled {
        last_acked: usize,
    },
    LineTooLong {
        command: String,
        len: usize,
        max: usize,
    },
}

#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct JobSummary {
    pub lines_total: usize,
    pub lines_sent: u64,
    pub resends: u64,
    pub probes: u64,
}

#[derive(Debug, Clone, PartialEq)]
pub enum Event {
    /// Handshake finished.
    Connected(FirmwareInfo),
    Progress {
        acked: usize,
        total: usize,
    },
    Temperatures(Temperatures),
    /// `busy:`/`wait` keep-alive.
    Busy(String),
    /// The printer asked for `line` again; `replay` lines will be sent again.
    Resend {
        line: u64,
        replay: u64,
    },
    /// The printer was silent; an `M105` probe went out.
    Probe,
    /// Informational printer output (`echo:`, non-fatal `Error:`) worth logging.
    Message(String),
    Paused,
    Resumed,
    Done(JobSummary),
    Failed(Failure),
}

#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Kind {
    /// Job command by index.
    Job(usize),
    /// M110 / M115 at connect or job start.
    Setup,
    /// M105 polls, probes and the final sync; M155, M73.
    Housekeeping,
    /// M108 and the heaters/fan/motors-off lines.
    SafeStop,
}

#[derive(Debug, Clone)]
struct Line {
    number: u64,
    kind: Kind,
    command: String,
}

#[derive(Debug, Clone, Copy)]
struct InFlight {
    number: u64,
    bytes: usize,
    is_m105: bool,
}

#[derive(Debug, Clone, Copy, PartialEq)]
enum Phase {
    /// Port just opened: wait for `start` or a quiet period.
    Boot {
        saw_start: bool,
    },
    /// M110 + M115 sent, waiting for their answers.
    Greeting,
    Idle,
    Job,
    Finished,
}

#[derive(Debug, Clone, Copy, PartialEq)]
enum StopReason {
    Cancel,
    Heat,
}

/// The host side of one printer connection.
pub struct Host {
    opts: ProtocolOptions,
    phase: Phase,
    info: FirmwareInfo,
    rx_partial: Vec<u8>,
    outgoing: Vec<u8>,
    events: VecDeque<Event>,

    job: GcodeCommands,
    next_job: usize,
    acked_job: usize,
    pending: VecDeque<(Kind, String)>,
    history: VecDeque<Line>,
    next_number: u64,
    send_cursor: u64,
    in_flight: VecDeque<InFlight>,
    in_flight_bytes: usize,
    swallow_oks: u32,
    duplicate_budget: Option<(u64, u64)>,
    repeated: Option<(u64, u32)>,

    opened_at: Instant,
    last_rx: Instant,
    front_since: Instant,
    last_probe: Option<Instant>,
    /// Last `ok`, resend request or busy keep-alive: temperature reports alone do not
    /// prove that commands are moving.
    last_progress: Instant,
    greeting_sent_at: Instant,
    greeting_attempts: u32,
    next_poll: Instant,
    temps: Temperatures,
    recent_errors: Vec<String>,
    paused: bool,
    paused_reported: bool,
    stopping: Option<StopReason>,
    heat_failure: Option<(String, Duration)>,
    sync_queued: bool,
    last_m73: Option<usize>,

    lines_sent: u64,
    resends: u64,
    probes: u64,
}

const LONG_COMMANDS: [&str; 4] = ["G28", "G29", "M400", "G4"];
const HEAT_COMMANDS: [&str; 2] = ["M109", "M190"];
const SAFE_STOP: [&str; 4] = ["M104 S0", "M140 S0", "M107", "M84"];
const MAX_PARTIAL: usize = 4096;

fn code_of(command: &str) -> &str {
    command.split_whitespace().next().unwrap_or("")
}

fn is_code(command: &str, codes: &[&str]) -> bool {
    let code = code_of(command);
    codes.iter().any(|c| c.eq_ignore_ascii_case(code))
}

impl Host {
    /// A host for a port opened at `now`; it starts with the handshake.
    pub fn new(opts: ProtocolOptions, now: Instant) -> Self {
        Host {
            opts,
            phase: Phase::Boot { saw_start: false },
            info: FirmwareInfo::default(),
            rx_partial: Vec::new(),
            outgoing: Vec::new(),
            events: VecDeque::new(),
            job: GcodeCommands::default(),
            next_job: 0,
            acked_job: 0,
            pending: VecDeque::new(),
            history: VecDeque::new(),
            next_number: 0,
            send_cursor: 0,
            in_flight: VecDeque::new(),
            in_flight_bytes: 0,
            swallow_oks: 0,
            duplicate_budget: None,
            repeated: None,
            opened_at: now,
            last_rx: now,
            front_since: now,
            last_probe: None,
            last_progress: now,
            greeting_sent_at: now,
            greeting_attempts: 0,
            next_poll: now,
            temps: Temperatures::default(),
            recent_errors: Vec::new(),
            paused: false,
            paused_reported: false,
            stopping: None,
            heat_failure: None,
            sync_queued: false,
            last_m73: None,
            lines_sent: 0,
            resends: 0,
            probes: 0,
        }
    }

    pub fn options(&self) -> &ProtocolOptions {
        &self.opts
    }
    pub fn firmware_info(&self) -> &FirmwareInfo {
        &self.info
    }
    /// Handshake done and no job running.
    pub fn is_idle(&self) -> bool {
        self.phase == Phase::Idle
    }
    /// A failure or the end of a job was reported; nothing more will be sent.
    pub fn is_finished(&self) -> bool {
        self.phase == Phase::Finished
    }
    /// For a new job on a link that was greeted before: skip the handshake.
    pub fn mark_connected(&mut self, info: FirmwareInfo) {
        self.info = info;
        self.phase = Phase::Idle;
    }
    /// The printer is working on M109/M190.
    pub fn heating(&self) -> bool {
        self.front_line()
            .is_some_and(|l| is_code(&l.command, &HEAT_COMMANDS))
    }
    pub fn acked_job_lines(&self) -> usize {
        self.acked_job
    }
    pub fn temperatures(&self) -> Temperatures {
        self.temps
    }
    pub fn lines_sent(&self) -> u64 {
        self.lines_sent
    }
    pub fn resends(&self) -> u64 {
        self.resends
    }

    /// Bytes to write to the port now.
    pub fn take_outgoing(&mut self) -> Vec<u8> {
        std::mem::take(&mut self.outgoing)
    }
    pub fn poll_event(&mut self) -> Option<Event> {
        self.events.pop_front()
    }

    /// Start streaming `commands` (already stripped of comments) after the handshake.
    /// Returns false when the host is not idle. Pass a shared handle (e.g.
    /// [`GcodeProgram::shared_commands`](super::gcode::GcodeProgram::shared_commands)) so a
    /// long job is not held in memory twice.
    pub fn start_job(&mut self, commands: impl Into<GcodeCommands>, now: Instant) -> bool {
        if self.phase != Phase::Idle {
            return false;
        }
        self.phase = Phase::Job;
        self.job = commands.into();
        self.next_job = 0;
        self.acked_job = 0;
        self.reset_numbering();
        self.pending.push_back((Kind::Setup, "M110 N0".into()));
        if self.autoreport() {
            let secs = self.opts.temperature_interval.as_secs().max(1);
            self.pending
                .push_back((Kind::Housekeeping, format!("M155 S{secs}")));
        }
        self.next_poll = now;
        self.front_since = now;
        self.last_rx = now;
        self.last_progress = now;
        self.last_probe = None;
        self.paused = false;
        self.stopping = None;
        self.sync_queued = false;
        self.last_m73 = None;
        self.lines_sent = 0;
        self.resends = 0;
        self.probes = 0;
        self.pump(now);
        true
    }

    /// Stop the job safely: no more job lines; break heat waits where the firmware can;
    /// then heaters, fan and motors off as ordinary numbered lines.
    pub fn cancel(&mut self, now: Instant) {
        if self.phase == Phase::Job && self.stopping.is_none() {
            self.begin_stop(StopReason::Cancel, now);
        }
    }

    /// Stop sending job lines; [`Event::Paused`] follows once the printer drained them.
    pub fn pause(&mut self, now: Instant) {
        if self.phase == Phase::Job && self.stopping.is_none() && !self.paused {
            self.paused = true;
            self.paused_reported = false;
            self.pump(now);
        }
    }

    pub fn resume(&mut self, now: Instant) {
        if self.phase == Phase::Job && self.paused {
            self.paused = false;
            self.events.push_back(Event::Resumed);
            self.pump(now);
        }
    }

    /// Feed bytes read from the port.
    pub fn feed(&mut self, bytes: &[u8], now: Instant) {
        if self.phase == Phase::Finished {
            return;
        }
        if !bytes.is_empty() {
            self.last_rx = now;
        }
        let mut rest = bytes;
        while let Some(pos) = rest.iter().position(|&b| b == b'\n') {
            let mut line = std::mem::take(&mut self.rx_partial);
            line.extend_from_slice(&rest[..pos]);
            rest = &rest[pos + 1..];
            self.handle_line(&line, now);
            if self.phase == Phase::Finished {
                return;
            }
        }
        self.rx_partial.extend_from_slice(rest);
        if self.rx_partial.len() > MAX_PARTIAL {
            // Binary noise without newlines: keep only the tail, a real line may follow.
            let cut = self.rx_partial.len() - MAX_PARTIAL / 2;
            self.rx_partial.drain(..cut);
        }
        self.pump(now);
    }

    /// The earliest time [`Host::tick`] must be called, if any.
    pub fn next_deadline(&self) -> Option<Instant> {
        match self.phase {
            Phase::Finished | Phase::Idle => None,
            Phase::Boot { saw_start } => {
                let quiet = if saw_start {
                    self.opts.quiet_period.min(Duration::from_millis(300))
                } else {
                    self.opts.quiet_period
                };
                Some(self.last_rx.max(self.opened_at) + quiet)
            }
            Phase::Greeting => Some(self.greeting_sent_at + self.opts.answer_timeout),
            Phase::Job => {
                let mut deadline: Option<Instant> = None;
                let mut at = |t: Instant| {
                    deadline = Some(deadline.map_or(t, |d: Instant| d.min(t)));
                };
                if !self.autoreport() && self.accepting_job_lines() {
                    at(self.next_poll);
                }
                if let Some(front) = self.front_line() {
                    at(self.next_probe_at());
                    if is_code(&front.command, &HEAT_COMMANDS) {
                        at(self.front_since + self.opts.heat_timeout);
                    } else if is_code(&front.command, &LONG_COMMANDS) {
                        at(self.last_rx + self.opts.long_command_timeout);
                    } else {
                        at(self.last_rx + self.opts.silence_fail);
                    }
                }
                deadline
            }
        }
    }

    /// Handle timeouts due at `now`.
    pub fn tick(&mut self, now: Instant) {
        match self.phase {
            Phase::Finished | Phase::Idle => {}
            Phase::Boot { .. } => {
                if self.next_deadline().is_some_and(|d| now >= d) {
                    self.send_greeting(now);
                }
            }
            Phase::Greeting => {
                if now >= self.greeting_sent_at + self.opts.answer_timeout {
                    if self.greeting_attempts >= 3 {
                        let waited = now - self.opened_at;
                        self.fail(Failure::NoAnswer { waited });
                    } else {
                        self.send_greeting(now);
                    }
                }
            }
            Phase::Job => self.tick_job(now),
        }
        self.pump(now);
    }

    fn tick_job(&mut self, now: Instant) {
        if !self.autoreport() && self.accepting_job_lines() && now >= self.next_poll {
            self.next_poll = now + self.opts.temperature_interval;
            if !self.in_flight.iter().any(|f| f.is_m105)
                && !self.pending.iter().any(|(_, c)| c == "M105")
            {
                self.pending.push_back((Kind::Housekeeping, "M105".into()));
            }
        }
        let Some(front) = self.front_line().cloned() else {
            return;
        };
        let last_acked = self.acked_job;
        if is_code(&front.command, &HEAT_COMMANDS) {
            let waited = now - self.front_since;
            if waited >= self.opts.heat_timeout {
                if self.stopping.is_some() {
                    // Even the safe stop is stuck behind the heat wait (no M108 here).
                    let temperatures = self.temps;
                    self.fail(Failure::HeatTimeout {
                        command: front.command,
                        waited,
                        temperatures,
                        last_acked,
                    });
                } else {
                    self.heat_failure = Some((front.command.clone(), waited));
                    self.begin_stop(StopReason::Heat, now);
                    // Give the safe stop its own full period before giving up.
                    self.front_since = now;
                }
            }
        } else if is_code(&front.command, &LONG_COMMANDS) {
            if now - self.last_rx >= self.opts.long_command_timeout {
                self.fail(Failure::Silent {
                    waited: now - self.last_rx,
                    last_acked,
                });
            }
        } else if now - self.last_rx >= self.opts.silence_fail {
            self.fail(Failure::Silent {
                waited: now - self.last_rx,
                last_acked,
            });
        }
        if self.phase == Phase::Job && now >= self.next_probe_at() {
            self.last_probe = Some(now);
            self.probes += 1;
            self.events.push_back(Event::Probe);
            // The probe bypasses the send window: the printer is most likely idle and
            // the window only looks full because an `ok` was lost.
            if self.send_cursor < self.next_number {
                // A replay is waiting: the line the printer asked for is the probe.
                self.transmit(self.send_cursor, now);
            } else {
                let number = self.new_line(Kind::Housekeeping, "M105".into());
                self.transmit(number, now);
            }
        }
    }

    /// When to probe with M105 if nothing moves. Long commands are probed too: the M105
    /// waits in the printer's queue behind them, harmlessly, and its answer recovers an
    /// `ok` lost at their end. One probe at a time, unless its answer seems lost too.
    fn next_probe_at(&self) -> Instant {
        let probe = self.opts.silence_probe;
        let base = self.last_progress.max(self.front_since) + probe;
        let long_front = self.front_line().is_some_and(|l| {
            is_code(&l.command, &HEAT_COMMANDS) || is_code(&l.command, &LONG_COMMANDS)
        });
        if long_front && self.in_flight.iter().any(|f| f.is_m105) {
            // It waits behind the long command; more probes would only fill the buffer.
            return base.max(self.front_since + self.opts.long_command_timeout);
        }
        match self.last_probe {
            Some(p) if self.in_flight.iter().any(|f| f.is_m105) => base.max(p + probe * 3),
            Some(p) => base.max(p + probe),
            None => base,
        }
    }

    fn autoreport(&self) -> bool {
        match self.info.capability("AUTOREPORT_TEMP") {
            Some(cap) => cap,
            None => self.info.capabilities.is_empty() && self.opts.firmware.autoreport_temp(),
        }
    }

    fn emergency_parser(&self) -> bool {
        match self.info.capability("EMERGENCY_PARSER") {
            Some(cap) => cap,
            None => self.opts.firmware.emergency_parser(),
        }
    }

    fn accepting_job_lines(&self) -> bool {
        self.phase == Phase::Job && !self.paused && self.stopping.is_none()
    }

    fn front_line(&self) -> Option<&Line> {
        let front = self.in_flight.front()?;
        self.history_line(front.number)
    }

    fn history_line(&self, number: u64) -> Option<&Line> {
        let first = self.history.front()?.number;
        self.history.get(number.checked_sub(first)? as usize)
    }

    fn reset_numbering(&mut self) {
        self.history.clear();
        self.in_flight.clear();
        self.in_flight_bytes = 0;
        self.pending.clear();
        self.next_number = 0;
        self.send_cursor = 0;
        self.duplicate_budget = None;
        self.repeated = None;
    }

    fn send_greeting(&mut self, now: Instant) {
        self.phase = Phase::Greeting;
        self.greeting_attempts += 1;
        self.greeting_sent_at = now;
        self.reset_numbering();
        self.pending.push_back((Kind::Setup, "M110 N0".into()));
        self.pending.push_back((Kind::Setup, "M115".into()));
    }

    fn begin_stop(&mut self, reason: StopReason, now: Instant) {
        self.stopping = Some(reason);
        self.paused = false;
        // Job lines waiting to be (re)sent are never sent now; the printer expects the
        // first of them next, so the safe-stop lines take over their numbers.
        self.discard_unsent_job_lines();
        self.pending.retain(|(kind, _)| *kind == Kind::SafeStop);
        if self.emergency_parser() {
            // Numbered, outside the window: the emergency parser acts on it on arrival
            // (breaking an M109/M190 wait), and the queue then acknowledges it in order.
            let number = self.new_line(Kind::SafeStop, "M108".into());
            if self.send_cursor == number {
                self.transmit(number, now);
            }
        }
        for cmd in SAFE_STOP {
            self.pending.push_back((Kind::SafeStop, cmd.into()));
        }
    }

    fn discard_unsent_job_lines(&mut self) {
        let Some(first) = self.history.front().map(|l| l.number) else {
            return;
        };
        if self.send_cursor >= self.next_number {
            return;
        }
        let keep = (self.send_cursor - first) as usize;
        let dropped: Vec<Line> = self.history.drain(keep..).collect();
        self.next_number = self.send_cursor;
        for line in dropped.into_iter().rev() {
            if line.kind == Kind::SafeStop {
                self.pending.push_front((line.kind, line.command));
            }
        }
    }

    fn fail(&mut self, failure: Failure) {
        if self.phase != Phase::Finished {
            self.phase = Phase::Finished;
            self.events.push_back(Event::Failed(failure));
        }
    }

    /// Give the next line a number and remember it for resends.
    fn new_line(&mut self, kind: Kind, command: String) -> u64 {
        let number = self.next_number;
        self.next_number += 1;
        self.history.push_back(Line {
            number,
            kind,
            command,
        });
        // Keep history bounded, but never drop lines that are not yet acknowledged.
        let oldest_needed = self
            .in_flight
            .front()
            .map_or(self.send_cursor, |f| f.number.min(self.send_cursor));
        while self.history.len() > self.opts.history_lines
            && self
                .history
                .front()
                .is_some_and(|l| l.number < oldest_needed)
        {
            self.history.pop_front();
        }
        number
    }

    fn transmit(&mut self, number: u64, now: Instant) {
        let Some(line) = self.history_line(number) else {
            return;
        };
        let wire = frame(number, &line.command);
        let is_m105 = code_of(&line.command).eq_ignore_ascii_case("M105");
        if wire.len() - 1 > self.opts.firmware.max_line_bytes() {
            let failure = Failure::LineTooLong {
                command: line.command.clone(),
                len: wire.len() - 1,
                max: self.opts.firmware.max_line_bytes(),
            };
            self.fail(failure);
            return;
        }
        if self.in_flight.is_empty() {
            self.front_since = now;
        }
        self.outgoing.extend_from_slice(wire.as_bytes());
        self.in_flight.push_back(InFlight {
            number,
            bytes: wire.len(),
            is_m105,
        });
        self.in_flight_bytes += wire.len();
        self.send_cursor = number + 1;
        self.lines_sent += 1;
    }

    fn window_allows(&self, bytes: usize) -> bool {
        if self.in_flight.is_empty() {
            return true;
        }
        if !self.opts.send_ahead {
            return false;
        }
        // Every unacknowledged line may still sit in the printer's receive ring: while the
        // firmware is blocked (planner full, M109, G28...) its loop does not move lines into
        // command slots, so free slots announced by ADVANCED_OK (`B`) are no room for more
        // bytes. Bytes beyond the ring are lost and two lines merge into one whose checksum
        // may even pass; so the bytes in flight never exceed the ring. One byte of margin:
        // Marlin's ring tells full from empty by leaving one cell unused.
        self.in_flight_bytes + bytes < self.opts.firmware.rx_buffer_bytes()
    }

    /// Send whatever the window allows. A line gets its number only when it is sent, so
    /// numbers always match the order on the wire.
    fn pump(&mut self, now: Instant) {
        loop {
            if matches!(
                self.phase,
                Phase::Finished | Phase::Idle | Phase::Boot { .. }
            ) {
                return;
            }
            if self.send_cursor < self.next_number {
                // Replaying after a resend request.
                let number = self.send_cursor;
                let Some(line) = self.history_line(number) else {
                    break;
                };
                if !self.window_allows(wire_len_bound(number, &line.command)) {
                    break;
                }
                self.transmit(number, now);
                continue;
            }
            let candidate_len = if let Some((_, command)) = self.pending.front() {
                command.len()
            } else if self.accepting_job_lines() && self.next_job < self.job.len() {
                self.job[self.next_job].len()
            } else {
                break;
            };
            if !self.window_allows(candidate_len + wire_len_bound(self.next_number, "")) {
                break;
            }
            let number = if let Some((kind, command)) = self.pending.pop_front() {
                self.new_line(kind, command)
            } else {
                let idx = self.next_job;
                self.next_job += 1;
                let command = self.job[idx].to_owned();
                self.new_line(Kind::Job(idx), command)
            };
            self.transmit(number, now);
        }
        self.check_progress(now);
    }

    fn check_progress(&mut self, _now: Instant) {
        if self.phase != Phase::Job {
            return;
        }
        let drained = self.in_flight.is_empty()
            && self.send_cursor >= self.next_number
            && self.pending.is_empty();
        if !drained {
            return;
        }
        if let Some(reason) = self.stopping {
            let last_acked = self.acked_job;
            match (reason, self.heat_failure.take()) {
                (StopReason::Heat, Some((command, waited))) => {
                    let temperatures = self.temps;
                    self.fail(Failure::HeatTimeout {
                        command,
                        waited,
                        temperatures,
                        last_acked,
                    })
                }
                _ => self.fail(Failure::Cancelled { last_acked }),
            }
            return;
        }
        if self.paused {
            if !self.paused_reported {
                self.paused_reported = true;
                self.events.push_back(Event::Paused);
            }
            return;
        }
        if self.next_job < self.job.len() {
            return;
        }
        if !self.sync_queued {
            // Only an answered M105 proves every earlier line was accepted in order.
            self.sync_queued = true;
            self.pending.push_back((Kind::Housekeeping, "M105".into()));
            self.pump(_now);
            return;
        }
        self.acked_job = self.job.len();
        self.phase = Phase::Finished;
        self.events.push_back(Event::Progress {
            acked: self.acked_job,
            total: self.job.len(),
        });
        self.events.push_back(Event::Done(JobSummary {
            lines_total: self.job.len(),
            lines_sent: self.lines_sent,
            resends: self.resends,
            probes: self.probes,
        }));
    }

    fn handle_line(&mut self, raw: &[u8], now: Instant) {
        let text = String::from_utf8_lossy(raw);
        let line = text.trim_matches(|c: char| c.is_whitespace() || c == '\0');
        if line.is_empty() {
            return;
        }
        let lower = line.to_ascii_lowercase();

        if lower == "start" {
            match self.phase {
                Phase::Boot { .. } => self.phase = Phase::Boot { saw_start: true },
                Phase::Greeting => {
                    // Rebooted while we greeted it: start over once it settles.
                    self.reset_numbering();
                    self.phase = Phase::Boot { saw_start: true };
                }
                _ => {
                    let last_acked = self.acked_job;
                    self.fail(Failure::PrinterReset { last_acked });
                }
            }
            return;
        }
        if lower.starts_with("error:") || lower.starts_with("!!") {
            if lower.contains("kill()")
                || lower.contains("printer halted")
                || lower.contains("printer stopped")
            {
                let mut parts = std::mem::take(&mut self.recent_errors);
                parts.push(line.to_string());
                let message = parts.join(" / ");
                let last_acked = self.acked_job;
                self.fail(Failure::Fatal {
                    message,
                    last_acked,
                });
                return;
            }
            if !lower.contains("last line") {
                self.recent_errors.push(line.to_string());
                if self.recent_errors.len() > 4 {
                    self.recent_errors.remove(0);
                }
                self.events.push_back(Event::Message(line.to_string()));
            }
            // A line error's `Resend:` follows on its own line.
            return;
        }
        if let Some(n) = parse_resend(&lower) {
            self.handle_resend(n, now);
            return;
        }
        if lower.starts_with("ok") {
            self.parse_temperatures(line);
            self.handle_ok(&lower, now);
            return;
        }
        if lower.contains("busy:") || lower == "wait" {
            self.last_progress = now;
            self.events.push_back(Event::Busy(line.to_string()));
            return;
        }
        if lower.starts_with("firmware_name:") || lower.contains(" firmware_name:") {
            self.parse_firmware_line(line);
            return;
        }
        if let Some(cap) = line.strip_prefix("Cap:") {
            if let Some((name, value)) = cap.rsplit_once(':') {
                self.info
                    .capabilities
                    .insert(name.trim().to_string(), value.trim() == "1");
            }
            return;
        }
        if self.parse_temperatures(line) {
            return;
        }
        self.events.push_back(Event::Message(line.to_string()));
    }

    fn parse_firmware_line(&mut self, line: &str) {
        const KEYS: [&str; 4] = [
            "FIRMWARE_NAME:",
            "PROTOCOL_VERSION:",
            "MACHINE_TYPE:",
            "EXTRUDER_COUNT:",
        ];
        for (i, key) in KEYS.iter().enumerate() {
            let Some(start) = line.find(key) else {
                continue;
            };
            let value_start = start + key.len();
            let rest = &line[value_start..];
            // A value runs until the next known key (names contain spaces).
            let end = KEYS
                .iter()
                .filter_map(|k| rest.find(&format!(" {k}")))
                .min()
                .unwrap_or(rest.len());
            let value = rest[..end].trim().to_string();
            match i {
                0 => self.info.name = Some(value),
                1 => self.info.protocol_version = Some(value),
                2 => self.info.machine_type = Some(value),
                _ => {
                    self.info.extruder_count =
                        value.split_whitespace().next().and_then(|v| v.parse().ok())
                }
            }
        }
    }

    /// Parse `T:cur /target B:cur /target`; returns whether a hotend reading was found.
    fn parse_temperatures(&mut self, line: &str) -> bool {
        let mut temps = Temperatures::default();
        let tokens: Vec<&str> = line.split_whitespace().collect();
        let mut i = 0;
        while i < tokens.len() {
            let token = tokens[i];
            let (slot, value) = if let Some(v) = token.strip_prefix("T:") {
                (&mut temps.hotend, v)
            } else if let Some(v) = token.strip_prefix("B:") {
                (&mut temps.bed, v)
            } else {
                i += 1;
                continue;
            };
            if let Ok(current) = value.parse::<f64>() {
                let target = tokens
                    .get(i + 1)
                    .and_then(|t| t.strip_prefix('/'))
                    .and_then(|t| t.parse::<f64>().ok());
                if slot.is_none() {
                    *slot = Some(Temp { current, target });
                }
            }
            i += 1;
        }
        if temps.hotend.is_none() && temps.bed.is_none() {
            return false;
        }
        if temps.hotend.is_some() {
            self.temps.hotend = temps.hotend;
        }
        if temps.bed.is_some() {
            self.temps.bed = temps.bed;
        }
        self.events.push_back(Event::Temperatures(self.temps));
        temps.hotend.is_some()
    }

    fn handle_ok(&mut self, lower: &str, now: Instant) {
        self.last_progress = now;
        if self.swallow_oks > 0 {
            // The `ok` that follows a `Resend:` belongs to the rejected line.
            self.swallow_oks -= 1;
            return;
        }
        let answers_m105 = lower.contains("t:");
        let through = if answers_m105 {
            self.in_flight.iter().position(|f| f.is_m105)
        } else {
            None
        };
        let count = match through {
            Some(pos) => pos + 1,
            None if self.in_flight.is_empty() => 0,
            None => 1,
        };
        for _ in 0..count {
            if let Some(f) = self.in_flight.pop_front() {
                self.in_flight_bytes -= f.bytes;
                self.acknowledge(f.number);
            }
        }
        if count > 0 {
            self.front_since = now;
        }
        // A successful answer ends a resend episode.
        if count > 0 {
            if let Some((line, _)) = self.repeated {
                if self.in_flight.front().is_none_or(|f| f.number > line) {
                    self.repeated = None;
                }
            }
        }
    }

    fn acknowledge(&mut self, number: u64) {
        let Some(line) = self.history_line(number) else {
            return;
        };
        match (self.phase, line.kind) {
            (_, Kind::Job(idx)) if idx + 1 > self.acked_job => {
                self.acked_job = idx + 1;
                let total = self.job.len();
                self.events.push_back(Event::Progress {
                    acked: self.acked_job,
                    total,
                });
                if self.opts.firmware.progress_m73() && self.accepting_job_lines() {
                    let percent = self.acked_job * 100 / total.max(1);
                    if self.last_m73 != Some(percent) && percent < 100 {
                        self.last_m73 = Some(percent);
                        self.pending
                            .push_back((Kind::Housekeeping, format!("M73 P{percent}")));
                    }
                }
            }
            (Phase::Greeting, Kind::Setup) if line.command == "M115" => {
                self.phase = Phase::Idle;
                self.events.push_back(Event::Connected(self.info.clone()));
            }
            _ => {}
        }
    }

    fn handle_resend(&mut self, n: u64, now: Instant) {
        self.last_progress = now;
        if self.opts.firmware.ok_after_resend() {
            self.swallow_oks += 1;
        }
        let first = self.history.front().map_or(self.next_number, |l| l.number);
        if self.phase == Phase::Greeting && (n < first || n >= self.next_number) {
            // The printer's counter is from an earlier session; M110 resets it.
            self.send_greeting(now);
            return;
        }
        if n >= self.next_number || n > self.send_cursor {
            // Never sent: a garbled number (`Resend: 034497`). Nothing to replay.
            self.swallow_oks = self.swallow_oks.saturating_sub(1);
            self.events.push_back(Event::Message(format!(
                "ignored resend request for line {n}"
            )));
            return;
        }
        if n < first {
            let last_acked = self.acked_job;
            self.fail(Failure::LineGone {
                line: n,
                oldest_kept: first,
                last_acked,
            });
            return;
        }
        if let Some((line, remaining)) = self.duplicate_budget {
            if line == n && remaining > 0 {
                // Caused by a line that was already on its way when we began replaying.
                self.duplicate_budget = Some((line, remaining - 1));
                return;
            }
        }
        let times = match self.repeated {
            Some((line, times)) if line == n => times + 1,
            _ => 1,
        };
        self.repeated = Some((n, times));
        if times > self.opts.resend_limit {
            let last_acked = self.acked_job;
            self.fail(Failure::ResendLimit {
                line: n,
                times: times - 1,
                last_acked,
            });
            return;
        }
        // The printer dropped line n and everything after it.
        let mut dropped_after = 0;
        self.in_flight.retain(|f| {
            if f.number >= n {
                if f.number > n {
                    dropped_after += 1;
                }
                false
            } else {
                true
            }
        });
        self.in_flight_bytes = self.in_flight.iter().map(|f| f.bytes).sum();
        self.duplicate_budget = Some((n, dropped_after));
        let replay = self.send_cursor - n;
        self.send_cursor = n;
        self.resends += 1;
        self.events.push_back(Event::Resend { line: n, replay });
        if self.stopping.is_some() {
            // Job lines after n are not sent again during a stop; renumber the rest.
            let keep = (n - first) as usize;
            let dropped: Vec<Line> = self.history.drain(keep..).collect();
            self.next_number = n;
            for line in dropped.into_iter().rev() {
                if !matches!(line.kind, Kind::Job(_)) {
                    self.pending.push_front((line.kind, line.command));
                }
            }
        }
    }
}

/// `Resend: 12`, `Resend:12`, `rs 12`, `rs:12`.
fn parse_resend(lower: &str) -> Option<u64> {
    let rest = match lower.find("resend") {
        Some(pos) => &lower[pos + "resend".len()..],
        None => lower.strip_prefix("rs")?,
    };
    let rest = rest.trim_start_matches([':', ' ', '\t']);
    let digits: String = rest.chars().take_while(|c| c.is_ascii_digit()).collect();
    digits.parse().ok()
}

#[cfg(test)]
mod tests;
