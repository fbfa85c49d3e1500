//! The Marlin host protocol as a pure state machine: bytes from the printer and the current
//! time go in; lines to send, events and the next deadline come out. No ports, no clocks,
//! so every corner (resend storms, lost `ok`s, garbage, resets) is unit-tested directly and
//! the async driver above it (`stream.rs`) stays thin.
//!
//! Exactly-once delivery rests on the printer's own line-number check: it executes line
//! `N` only if it follows the last one it accepted, and asks for the rest again otherwise.
//! The host therefore never skips or re-orders; it replays everything from a requested line.
//! `ok` counting only drives flow control and progress, and it heals itself: an `ok`
//! carrying a temperature report answers an `M105`, which the printer processes after every
//! earlier line, so it acknowledges everything up to that `M105`. A job only counts as done
//! after such a final `M105` is answered.
//!
//! This file holds the [`Host`] (its state, and what its driver calls: start a job, feed
//! bytes, pause, cancel). Around it, two kinds of children:
//!
//! - what it is made of, which knows nothing of the `Host`: [`reply`] (each printer line
//!   classified into a pure [`Reply`] first), `options`, `event`, `framing` (lines on the
//!   wire), `line` and `phase` (what is sent, and where the host is), and the parts of its
//!   state with rules of their own: `timers` (clocks and latencies), `recovery` (what is
//!   kept between resend requests) and `temperature` (readings and heat waits);
//! - the host's own steps, each an `impl Host` of its own: `receive.rs` (acting on each
//!   reply), `resend.rs` (a `Resend:` request), `window.rs` (numbering and the send
//!   window), `timeouts.rs` (deadlines, probes and timeouts) and `stop.rs` (how a job
//!   ends: done, paused, or stopped safely).

mod event;
mod framing;
mod line;
mod options;
mod phase;
mod receive;
mod recovery;
pub mod reply;
mod resend;
mod stop;
mod temperature;
mod timeouts;
mod timers;
mod window;

pub use event::{Event, Failure, FirmwareInfo, JobSummary, Numbering, MAX_CAPABILITIES};
pub use framing::{canonical, checksum, frame};
pub use options::ProtocolOptions;
pub use temperature::{HeatWaitEstimate, Temp, Temperatures};

use super::gcode::is_heat_wait;
use super::plate::JobLines;
use event::Stats;
use line::{InFlight, Kind, Line, Owed};
use phase::{JobPhase, Phase, Stop};
use recovery::Recovery;
use reply::Reply;
use std::collections::VecDeque;
use std::time::Instant;
use temperature::Thermal;
use timers::Timers;

/// The host side of one printer connection.
pub struct Host {
    opts: ProtocolOptions,
    phase: Phase,
    info: FirmwareInfo,
    rx_partial: Vec<u8>,
    outgoing: Vec<u8>,
    events: VecDeque<Event>,

    /// The job's lines, taken one at a time as they are sent (a plate's filter decides
    /// each then: see `plate::JobLines`).
    job: JobLines,
    next_job: usize,
    acked_job: usize,
    pending: VecDeque<(Kind, String)>,
    history: VecDeque<Line>,
    next_number: u64,
    /// The first line number of the safe stop being made: an `M105` sent before it is
    /// never taken for lost while stopping, so its late answer cannot confirm the stop.
    stop_from: u64,
    send_cursor: u64,
    in_flight: VecDeque<InFlight>,
    in_flight_bytes: usize,
    /// `M105`s taken for answered by an answer that may have been an earlier one's (one a
    /// probe took for lost: see `handle_ok`), oldest first: each may still wait unread in
    /// the printer's ring, its answer to come.
    unsettled_m105s: VecDeque<u64>,
    /// Answers owed by lines outside the current count, oldest first (see [`Owed`]): their
    /// `ok`s are not taken for the count's lines, nor an `M105`'s report for the stop's
    /// (the printer runs the stop's lines after them), and the send window counts their
    /// bytes: a stop begun while the printer's ring is full must not overrun it.
    owed: VecDeque<Owed>,
    /// An `M105` sent without a number is unanswered: the numbers below this were sent
    /// before it, and its answer settles them (see `probe`): it confirms them where it was
    /// a probe while the host's `M110` waited to run (`true`), and says only that the
    /// printer read them where it asked after a long wait without answers (`false`).
    unnumbered_probe: Option<(u64, Instant, bool)>,
    /// One line in flight until this line number is reached (after a resend).
    cautious_until: u64,
    /// `ok N<n> P<p> B<b>` seen: `ok`s are matched to lines by number.
    advanced_ok: bool,
    /// The highest line number the printer has certainly accepted.
    confirmed: Option<u64>,
    /// Between resend requests: holds on the replay, duplicates to expect, what follows
    /// `Resend:` on this firmware.
    recovery: Recovery,

    /// When things last happened, and how long answers take.
    timers: Timers,
    greeting_attempts: u32,
    /// Temperatures and the heat wait the printer may be in.
    thermal: Thermal,
    recent_errors: Vec<String>,
    /// An `Error:` that is no line error by its words, and when to act on it: it may yet
    /// prove part of a resend (a `Resend:` follows) or of a halt (a `kill()` line follows).
    pending_error: Option<(String, Instant)>,
    last_m73: Option<usize>,

    stats: Stats,
}

const MAX_PARTIAL: usize = 4096;

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
            job: JobLines::default(),
            next_job: 0,
            acked_job: 0,
            pending: VecDeque::new(),
            history: VecDeque::new(),
            next_number: 0,
            stop_from: 0,
            send_cursor: 0,
            in_flight: VecDeque::new(),
            in_flight_bytes: 0,
            unsettled_m105s: VecDeque::new(),
            owed: VecDeque::new(),
            unnumbered_probe: None,
            cautious_until: 0,
            advanced_ok: false,
            confirmed: None,
            recovery: Recovery::default(),
            timers: Timers::new(now),
            greeting_attempts: 0,
            thermal: Thermal::default(),
            recent_errors: Vec::new(),
            pending_error: None,
            last_m73: None,
            stats: Stats::default(),
        }
    }

    /// The state a test prints when a run goes wrong (the co-simulation in `crispen-sim`).
    pub fn debug_state(&self) -> String {
        format!(
            "phase {:?} next_job {}/{} send_cursor {} next_number {} in_flight {:?} pending {:?} cautious_until {}",
            self.phase,
            self.next_job,
            self.job.len(),
            self.send_cursor,
            self.next_number,
            self.in_flight,
            self.pending,
            self.cautious_until
        )
    }

    #[cfg(test)]
    pub(crate) fn options(&self) -> &ProtocolOptions {
        &self.opts
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
        self.advanced_ok = info.capability("ADVANCED_OK") == Some(true);
        self.info = info;
        self.phase = Phase::Idle;
    }
    /// The printer is inside M109/M190: it says so in its reports (`W:`), or a heat command
    /// was sent and is not known to have ended: by an `ok` right after its `W:` reports (the
    /// firmware reads nothing while it waits), by an answer confirming a later line, or,
    /// where `ok`s keep line order, by its own `ok`.
    pub(crate) fn heating(&self) -> bool {
        self.thermal.heat_reported || self.thermal.heat.is_some() || self.heat_at_front()
    }

    /// The oldest unanswered line is a heat wait (M109/M190/M116), or the printer reports that it waits: it
    /// reads nothing else meanwhile, so silence is no sign of trouble.
    fn heat_at_front(&self) -> bool {
        self.thermal.heat_reported || self.front_line().is_some_and(|l| is_heat_wait(&l.command))
    }
    pub fn acked_job_lines(&self) -> usize {
        self.acked_job
    }
    /// The job's lines, for a change to those not sent yet (a plate's part cancelled).
    pub(crate) fn job_lines(&mut self) -> &mut JobLines {
        &mut self.job
    }
    pub(crate) fn temperatures(&self) -> Temperatures {
        self.thermal.temps
    }
    #[cfg(test)]
    pub(crate) fn resends(&self) -> u64 {
        self.stats.resends
    }
    #[cfg(test)]
    pub(crate) fn fragments(&self) -> u64 {
        self.stats.fragments
    }
    /// Whether the firmware was seen to send an `ok` after `Resend:` (None: not known yet).
    #[cfg(test)]
    pub(crate) fn ok_after_resend(&self) -> Option<bool> {
        self.recovery.resend_ok.known()
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
    pub fn start_job(&mut self, commands: impl Into<JobLines>, now: Instant) -> bool {
        if self.phase != Phase::Idle {
            return false;
        }
        self.phase = Phase::Job(JobPhase::Streaming);
        self.job = commands.into();
        self.next_job = 0;
        self.acked_job = 0;
        self.reset_numbering();
        // The M110 goes alone: if the printer rejects it, its request names a line of the
        // old count, and no line of the new count is on its way to be taken for it.
        self.cautious_until = 2;
        self.pending.push_back((Kind::Setup, "M110 N0".into()));
        if self.autoreport() {
            let secs = self.opts.temperature_interval.as_secs().max(1);
            self.pending
                .push_back((Kind::Housekeeping, format!("M155 S{secs}")));
        }
        self.timers.next_poll = now;
        self.timers.front_since = now;
        self.timers.last_rx = now;
        self.timers.last_progress = now;
        self.timers.last_ack = now;
        self.timers.last_probe = None;
        self.last_m73 = None;
        self.stats = Stats::default();
        self.pump(now);
        true
    }

    /// Stop the job safely: no more job lines; break a heat wait where the firmware can;
    /// heaters off at once, then a new line count and heaters, fan and motors off,
    /// confirmed by an `M105` (see `begin_stop`).
    pub(crate) fn cancel(&mut self, now: Instant) {
        if self.in_job() && self.stopping().is_none() {
            let give_up = now + self.opts.stop_timeout;
            self.begin_stop(Stop::Cancel { give_up }, now);
        }
    }

    /// Stop sending job lines; [`Event::Paused`] follows once the printer drained them.
    pub(crate) fn pause(&mut self, now: Instant) {
        // Once every job line is answered there is nothing left to hold back.
        if self.phase == Phase::Job(JobPhase::Streaming) {
            self.phase = Phase::Job(JobPhase::Paused {
                synced: false,
                reported: false,
            });
            self.pump(now);
        }
    }

    pub(crate) fn resume(&mut self, now: Instant) {
        if matches!(self.phase, Phase::Job(JobPhase::Paused { .. })) {
            self.phase = Phase::Job(JobPhase::Streaming);
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
            self.timers.last_rx = now;
        }
        let mut rest = bytes;
        while let Some(pos) = rest.iter().position(|&b| b == b'\n') {
            let mut line = std::mem::take(&mut self.rx_partial);
            line.extend_from_slice(&rest[..pos]);
            rest = &rest[pos + 1..];
            if let Some(reply) = Reply::parse(&line) {
                self.handle(reply, now);
            }
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
        matches!(
            self.phase,
            Phase::Job(JobPhase::Streaming | JobPhase::Closing)
        )
    }

    fn in_job(&self) -> bool {
        matches!(self.phase, Phase::Job(_))
    }

    fn stopping(&self) -> Option<&Stop> {
        match &self.phase {
            Phase::Job(JobPhase::Stopping(stop)) => Some(stop),
            _ => None,
        }
    }

    fn front_line(&self) -> Option<&Line> {
        let front = self.in_flight.front()?;
        self.history_line(front.number)
    }

    fn send_greeting(&mut self, now: Instant) {
        self.phase = Phase::Greeting;
        self.greeting_attempts += 1;
        self.timers.greeting_sent_at = now;
        self.reset_numbering();
        self.pending.push_back((Kind::Setup, "M110 N0".into()));
        self.pending.push_back((Kind::Setup, "M115".into()));
    }
}

#[cfg(test)]
mod tests;
