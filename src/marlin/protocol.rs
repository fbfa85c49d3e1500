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
//! - [`reply`]: each printer line classified into a pure [`Reply`] first.
//! - this file: numbering, the send window and the host state machine acting on replies.

pub mod reply;
mod window;

pub use window::canonical;

use super::firmware::Firmware;
use super::gcode::{is_heat_wait, GcodeCommands};
use reply::{HostAction, OkReply, Reply, Report};
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
    /// M109/M190 whose temperature has not come closer to its target for this long: stop
    /// safely and fail the job. A wait that still makes progress never times out.
    pub heat_timeout: Duration,
    /// No line acknowledged for this long while the printer keeps talking (outside heat
    /// waits and long commands): stop safely and fail the job.
    pub no_progress_timeout: Duration,
    /// After a `Resend:` while it is not yet known whether this firmware sends an `ok`
    /// after it (Marlin 2.1 and Ultimaker2Marlin do, Marlin 2.0 does not), wait this long
    /// for one before replaying.
    pub resend_ok_wait: Duration,
    /// After a resend, this many further lines go one at a time: a burst right after a
    /// receive-buffer flush is what cuts lines into fragments the firmware may execute.
    pub cautious_lines: u64,
    /// Interval of temperature reports (autoreport) or polls.
    pub temperature_interval: Duration,
    /// How many times the same line may be requested again at once; past that, replays are
    /// paced (`storm_pause`) and the job fails only when the storm outlasts `storm_timeout`.
    /// A printer that keeps asking for the same line is usually behind a noisy cable.
    pub resend_limit: u32,
    pub storm_pause: Duration,
    pub storm_timeout: Duration,
    /// A safe stop after a failure keeps trying this long while the printer keeps talking
    /// (it ends sooner when the printer falls silent for `silence_fail`), one replay every
    /// `stop_pause`: giving up leaves a printer hot.
    pub stop_timeout: Duration,
    pub stop_pause: Duration,
    /// On firmware that checks a checksum only up to the first `*` (Ultimaker2Marlin),
    /// write each line so that no byte corrupted into `*` leaves a cut line that passes
    /// (see `window::uncuttable`): numbers may gain trailing zeros and words an extra space,
    /// which change the text sent but not what the printer does. On by default; Marlin 2
    /// takes the last `*`, so nothing changes there.
    pub uncuttable_lines: bool,
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
            no_progress_timeout: Duration::from_secs(180),
            resend_ok_wait: Duration::from_millis(250),
            cautious_lines: 8,
            temperature_interval: Duration::from_secs(2),
            resend_limit: 10,
            storm_pause: Duration::from_millis(100),
            storm_timeout: Duration::from_secs(30),
            stop_timeout: Duration::from_secs(180),
            stop_pause: Duration::from_millis(200),
            uncuttable_lines: true,
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
    /// `Cap:NAME:0|1` lines (empty on firmware without them, e.g. Ultimaker2Marlin), at
    /// most [`MAX_CAPABILITIES`] names.
    pub capabilities: BTreeMap<String, bool>,
}

impl FirmwareInfo {
    pub fn capability(&self, name: &str) -> Option<bool> {
        self.capabilities.get(name).copied()
    }
}

/// The most `Cap:` names kept from one printer.
pub const MAX_CAPABILITIES: usize = 128;

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
    /// The printer asked for a line it had already confirmed (an answered `M105`, an
    /// `ok N`): it lost its state (a reset without `start`, a power dip); replaying on top
    /// of a half-printed layer would be guessing.
    LostState {
        line: u64,
        confirmed: u64,
        last_acked: usize,
    },
    Silent {
        waited: Duration,
        last_acked: usize,
    },
    /// The printer kept talking but acknowledged nothing for this long.
    NoProgress {
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
    /// The firmware reported an error that is neither a line error (those come with a
    /// `Resend:`) nor a halt (a halted printer has switched its heaters off): a failed
    /// probing, a refused command. The printer no longer does what the file says.
    FirmwareError {
        message: String,
        last_acked: usize,
    },
}

#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct JobSummary {
    pub lines_total: usize,
    pub lines_sent: u64,
    pub resends: u64,
    pub probes: u64,
    /// Pieces of lines the printer answered on their own (the tail of a line cut by a
    /// receive-buffer flush): seen as `Unknown command` or as an `ok` without a line number.
    pub fragments: u64,
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
    /// `busy:` keep-alive.
    Busy(String),
    /// The printer asked for `line` again; `replay` lines will be sent again.
    Resend {
        line: u64,
        replay: u64,
    },
    /// The printer was silent, or said `wait` with lines in flight; an `M105` probe went out.
    Probe,
    /// The printer answered a piece of a line on its own (see [`JobSummary::fragments`]).
    Fragment(String),
    /// `//action:cancel|pause|resume` from the printer's own menu; the host acts on it.
    HostAction(HostAction),
    /// Informational printer output (`echo:`, non-fatal `Error:`) worth logging.
    Message(String),
    Paused,
    Resumed,
    /// A failure stopped the printer: heaters, fan and motors off. `confirmed`: the printer
    /// acknowledged those lines (an answered `M105` after them).
    SafeStop {
        confirmed: bool,
    },
    Done(JobSummary),
    Failed(Failure),
}

#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Kind {
    /// Job command by index.
    Job(usize),
    /// M110 / M115 at connect or job start.
    Setup,
    /// M105 polls and probes; M155, M73.
    Housekeeping,
    /// The `M105` that ends a job or a stop: only its own answer (`ok T:`, or an `ok N`
    /// past it) acknowledges it, never a plain `ok` that may belong to something else.
    Sync,
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
    sync: bool,
    sent: Instant,
}

#[derive(Debug, Clone, PartialEq)]
enum Phase {
    /// Port just opened: wait for `start` or a quiet period.
    Boot {
        saw_start: bool,
    },
    /// M110 + M115 sent, waiting for their answers.
    Greeting,
    Idle,
    Job(JobPhase),
    Finished,
}

/// Where a running job is. Each stage carries what only it needs, so combinations that
/// make no sense (paused while stopping, a final sync on a cancelled job) cannot be built.
#[derive(Debug, Clone, PartialEq)]
enum JobPhase {
    /// Sending the job's lines.
    Streaming,
    /// Every job line answered: autoreport off and a final `M105` queued, whose answer
    /// ends the job done (only it proves every earlier line was accepted in order).
    Closing,
    /// No job lines go out. `synced`: an `M105` after the last job line was queued (with
    /// Ultimaker2Marlin, all `ok`s in does not mean the queued moves ran); `reported`:
    /// [`Event::Paused`] went out, once that `M105` was answered.
    Paused { synced: bool, reported: bool },
    /// Heaters, fan and motors off on their way; the job ends once they are answered.
    Stopping(Stop),
}

/// Why a job stops sending its lines.
#[derive(Debug, Clone, PartialEq)]
enum Stop {
    /// On request: the safe-stop lines follow the job's numbering.
    Cancel,
    /// A failure while the printer still answers: the line counter is reset with `M110`
    /// (the printer's idea of the next line is not to be trusted), the safe-stop lines go
    /// out, and the failure is reported once an `M105` after them is answered or `give_up`
    /// passes.
    Failure { failure: Failure, give_up: Instant },
}

/// An M109/M190 the printer may still be working on. Tracked apart from the order of `ok`s,
/// which Ultimaker2Marlin does not keep (it acknowledges moves queued behind the heat
/// command before the heat command ends).
#[derive(Debug, Clone)]
struct HeatWait {
    number: u64,
    command: String,
    bed: bool,
    /// `S`/`R` of the command.
    target: Option<f64>,
    since: Instant,
    /// The closest distance to the target seen so far, and when.
    best: Option<(f64, Instant)>,
}

/// What the line after a `Resend:` or a fragment's `Unknown command` may be.
#[derive(Debug, Clone, Copy)]
struct OkFollow {
    /// A plain `ok` there is theirs, not a line's.
    swallow: bool,
    /// Nothing else awaits an `ok`: whether one comes tells this firmware's way.
    learn: bool,
}

/// The replay after a `Resend: n` held back until the lines sent after n have drawn their
/// own error blocks. Stock Marlin answers every line that reaches it after a bad one with
/// `Error:`/`Resend: n`/`ok`, and each such block flushes its receive ring: a replay that
/// arrived by then is thrown away with it and never answered (seen on the real Marlin
/// 2.1.2.1: most of its recovery time went into finding such lost replays). The blocks
/// come within a millisecond or two, so the wait is short: it ends when one block per line
/// sent after n has come, or when the printer has been quiet for a moment (lines the first
/// flush caught draw no block), and never lasts more than [`SETTLE_MAX`].
#[derive(Debug, Clone, Copy)]
struct Settle {
    line: u64,
    /// Blocks still expected.
    remaining: u64,
    /// Quiet until then: no more blocks are coming.
    quiet_until: Instant,
    give_up: Instant,
}

impl Settle {
    fn deadline(&self) -> Instant {
        self.quiet_until.min(self.give_up)
    }
}

/// Whether this firmware sends an `ok` after `Resend:`, learnt from unambiguous cases (a
/// resend with nothing else awaiting an `ok`): Marlin 2.1 and Ultimaker2Marlin do, Marlin
/// 2.0 does not, Marlin 1.1 sometimes. Until two observations agree, the firmware profile's
/// value stands in where a case is ambiguous.
#[derive(Debug, Clone, Copy, Default)]
struct ResendOk {
    seen_ok: u32,
    seen_none: u32,
}

impl ResendOk {
    fn known(&self) -> Option<bool> {
        (self.seen_ok + self.seen_none >= 2 && self.seen_ok != self.seen_none)
            .then_some(self.seen_ok > self.seen_none)
    }
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
    /// The first line number of the safe stop being made: an `M105` sent before it is
    /// never taken for lost while stopping, so its late answer cannot confirm the stop.
    stop_from: u64,
    send_cursor: u64,
    in_flight: VecDeque<InFlight>,
    in_flight_bytes: usize,
    /// `ok`s to ignore: the unnumbered `M108`'s (answered when the queue reaches it).
    swallow_oks: u32,
    /// The line just read asks for an `ok` right behind it: a `Resend:` (Marlin 2.1 and
    /// Ultimaker2Marlin print `ok` in the same breath) or a fragment's `Unknown command`.
    /// Only the very next line can be that `ok`; a guess never outlives it, so it cannot eat
    /// the `ok` of a later line.
    ok_may_follow: Option<OkFollow>,
    /// While it is not known whether an `ok` follows `Resend:` and nothing else awaits an
    /// `ok`, the replay waits for the next line (or this time) to tell.
    resend_hold: Option<Instant>,
    /// Duplicate resend requests to ignore: (line, how many). Lines already on their way
    /// when the replay began each cause one, always as a line-number error (Marlin checks
    /// the number first); a request after a checksum error is the replay itself corrupted
    /// again, a new request.
    duplicate_budget: Option<(u64, u64)>,
    /// The `Error:` before the next `Resend:` was a line-number error.
    number_error: bool,
    /// Its `Last Line: <k>`.
    error_last_line: Option<u64>,
    /// The line requested again, how often, and since when.
    repeated: Option<(u64, u32, Instant)>,
    /// Replays wait until then (a resend storm, a safe stop inside a noise burst).
    replay_after: Option<Instant>,
    /// Probe then if the replayed line is still unanswered: a repeated error block came
    /// after the replay went out, and Marlin may have thrown the replay away with it.
    probe_replay: Option<(u64, Instant)>,
    /// After a `Resend:`, the replay waits for the error blocks of the lines that were
    /// already on their way (see [`Settle`]).
    settle: Option<Settle>,
    resend_ok: ResendOk,
    /// One line in flight until this line number is reached (after a resend).
    cautious_until: u64,
    /// `ok N<n> P<p> B<b>` seen: `ok`s are matched to lines by number.
    advanced_ok: bool,
    /// The highest line number the printer has certainly accepted.
    confirmed: Option<u64>,
    fragments: u64,

    opened_at: Instant,
    last_rx: Instant,
    front_since: Instant,
    last_probe: Option<Instant>,
    /// Last `ok`, resend request or busy keep-alive: temperature reports and `wait` alone
    /// do not prove that commands are moving.
    last_progress: Instant,
    /// Last time a line was acknowledged.
    last_ack: Instant,
    /// How long the oldest line typically waits for its answer (a moving average): a
    /// printer that answers in milliseconds and then says nothing for many times that has
    /// lost an `ok`, and is probed long before `silence_probe`.
    ack_wait: Duration,
    /// How long a line typically takes from being sent to its answer (a moving average;
    /// None until one was answered): no probe counts as lost sooner than twice that, so
    /// on a slow link a probe's answer is never taken for a later probe's.
    latency: Option<Duration>,
    /// The same for `M105`s alone.
    m105_latency: Option<Duration>,
    greeting_sent_at: Instant,
    greeting_attempts: u32,
    next_poll: Instant,
    temps: Temperatures,
    /// The printer reports `W:` (inside an M109/M190 wait) and has not answered since.
    heat_reported: bool,
    heat: Option<HeatWait>,
    recent_errors: Vec<String>,
    /// An `Error:` that is no line error by its words, and when to act on it: it may yet
    /// prove part of a resend (a `Resend:` follows) or of a halt (a `kill()` line follows).
    pending_error: Option<(String, Instant)>,
    last_m73: Option<usize>,

    lines_sent: u64,
    resends: u64,
    probes: u64,
}

const LONG_COMMANDS: [&str; 4] = ["G28", "G29", "M400", "G4"];
const SAFE_STOP: [&str; 4] = ["M104 S0", "M140 S0", "M107", "M84"];
const MAX_PARTIAL: usize = 4096;
/// The shortest quiet after which a lost `ok` is probed for.
/// (A probe costs one `M105` line in the queue; waiting costs the whole link.)
const QUICK_PROBE: Duration = Duration::from_millis(25);
/// An `M105` is taken for lost no sooner than this (nor than four times the usual time an
/// `M105` takes): a late answer taken for a later `M105`'s would confirm lines the printer
/// may never have got (seen on the real Marlin on a busy machine: a false `LostState`).
/// An answer found lost late costs one more probe, not a wrong confirmation.
const M105_PATIENCE: Duration = Duration::from_millis(250);
/// The same before any line was answered.
const FIRST_PROBE: Duration = Duration::from_millis(200);
/// The quiet after an error block that ends a [`Settle`]: at least this, or twice the
/// usual answer time.
const SETTLE_QUIET: Duration = Duration::from_millis(5);
const SETTLE_QUIET_MAX: Duration = Duration::from_millis(50);
/// The longest a replay waits for error blocks.
const SETTLE_MAX: Duration = Duration::from_millis(150);
/// After a repeated error block that may have eaten a replay: probe this soon if the
/// replayed line is still unanswered (its answer would have come at once).
const REPLAY_PROBE: Duration = Duration::from_millis(30);

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
            stop_from: 0,
            send_cursor: 0,
            in_flight: VecDeque::new(),
            in_flight_bytes: 0,
            swallow_oks: 0,
            ok_may_follow: None,
            resend_hold: None,
            duplicate_budget: None,
            number_error: false,
            error_last_line: None,
            repeated: None,
            replay_after: None,
            probe_replay: None,
            settle: None,
            resend_ok: ResendOk::default(),
            cautious_until: 0,
            advanced_ok: false,
            confirmed: None,
            fragments: 0,
            opened_at: now,
            last_rx: now,
            front_since: now,
            last_probe: None,
            last_progress: now,
            last_ack: now,
            ack_wait: Duration::ZERO,
            latency: None,
            m105_latency: None,
            greeting_sent_at: now,
            greeting_attempts: 0,
            next_poll: now,
            temps: Temperatures::default(),
            heat_reported: false,
            heat: None,
            recent_errors: Vec::new(),
            pending_error: None,
            last_m73: None,
            lines_sent: 0,
            resends: 0,
            probes: 0,
        }
    }

    /// The state the tests look at when a run goes wrong.
    #[cfg(test)]
    pub(crate) fn debug_state(&self) -> String {
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
        self.advanced_ok = info.capability("ADVANCED_OK") == Some(true);
        self.info = info;
        self.phase = Phase::Idle;
    }
    /// The printer is inside M109/M190: it says so in its reports (`W:`), or a heat command
    /// was sent and is not known to have ended: by an `ok` right after its `W:` reports (the
    /// firmware reads nothing while it waits), by an answer confirming a later line, or,
    /// where `ok`s keep line order, by its own `ok`.
    pub fn heating(&self) -> bool {
        self.heat_reported || self.heat.is_some() || self.heat_at_front()
    }

    /// The oldest unanswered line is a heat wait (M109/M190/M116), or the printer reports that it waits: it
    /// reads nothing else meanwhile, so silence is no sign of trouble.
    fn heat_at_front(&self) -> bool {
        self.heat_reported || self.front_line().is_some_and(|l| is_heat_wait(&l.command))
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
    pub fn fragments(&self) -> u64 {
        self.fragments
    }
    /// Whether the firmware was seen to send an `ok` after `Resend:` (None: not known yet).
    pub fn ok_after_resend(&self) -> Option<bool> {
        self.resend_ok.known()
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
        self.next_poll = now;
        self.front_since = now;
        self.last_rx = now;
        self.last_progress = now;
        self.last_ack = now;
        self.last_probe = None;
        self.last_m73 = None;
        self.lines_sent = 0;
        self.resends = 0;
        self.probes = 0;
        self.fragments = 0;
        self.pump(now);
        true
    }

    /// Stop the job safely: no more job lines; break heat waits where the firmware can;
    /// then heaters, fan and motors off as ordinary numbered lines.
    pub fn cancel(&mut self, now: Instant) {
        if self.in_job() && self.stopping().is_none() {
            self.phase = Phase::Job(JobPhase::Stopping(Stop::Cancel));
            // Job lines waiting to be (re)sent are never sent now; the printer expects the
            // first of them next, so the safe-stop lines take over their numbers.
            self.discard_unsent_job_lines();
            self.queue_safe_stop(now);
            self.pump(now);
        }
    }

    /// Stop sending job lines; [`Event::Paused`] follows once the printer drained them.
    pub fn pause(&mut self, now: Instant) {
        // Once every job line is answered there is nothing left to hold back.
        if self.phase == Phase::Job(JobPhase::Streaming) {
            self.phase = Phase::Job(JobPhase::Paused {
                synced: false,
                reported: false,
            });
            self.pump(now);
        }
    }

    pub fn resume(&mut self, now: Instant) {
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
            self.last_rx = now;
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

    /// The earliest time [`Host::tick`] must be called, if any.
    pub fn next_deadline(&self) -> Option<Instant> {
        match &self.phase {
            Phase::Finished | Phase::Idle => None,
            Phase::Boot { saw_start } => {
                let quiet = if *saw_start {
                    self.opts.quiet_period.min(Duration::from_millis(300))
                } else {
                    self.opts.quiet_period
                };
                Some(self.last_rx.max(self.opened_at) + quiet)
            }
            Phase::Greeting => Some(self.greeting_sent_at + self.opts.answer_timeout),
            Phase::Job(_) => {
                let mut deadline: Option<Instant> = None;
                let mut at = |t: Instant| {
                    deadline = Some(deadline.map_or(t, |d: Instant| d.min(t)));
                };
                if !self.autoreport() && self.accepting_job_lines() {
                    at(self.next_poll);
                }
                if let Some((_, decide)) = &self.pending_error {
                    at(*decide);
                }
                if let Some(hold) = self.resend_hold {
                    at(hold);
                }
                if let Some(t) = self.replay_after {
                    at(t);
                }
                if let Some((_, t)) = self.probe_replay {
                    at(t);
                }
                if let Some(settle) = &self.settle {
                    at(settle.deadline());
                }
                if let Some(Stop::Failure { give_up, .. }) = self.stopping() {
                    at(*give_up);
                }
                if let Some(deadline) = self.heat_deadline() {
                    at(deadline);
                }
                if let Some(front) = self.front_line() {
                    at(self.next_probe_at());
                    if self.heat_at_front() {
                        // The heat wait has its own limit, but a waiting printer reports
                        // every second: silence means it is gone.
                        at(self.last_rx + self.opts.silence_fail);
                    } else if is_code(&front.command, &LONG_COMMANDS) {
                        at(self.last_rx + self.opts.long_command_timeout);
                    } else {
                        at(self.last_rx + self.opts.silence_fail);
                        at(self.last_ack + self.opts.no_progress_timeout);
                    }
                }
                deadline
            }
        }
    }

    /// Handle timeouts due at `now`.
    pub fn tick(&mut self, now: Instant) {
        match &self.phase {
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
            Phase::Job(_) => self.tick_job(now),
        }
        self.pump(now);
    }

    fn tick_job(&mut self, now: Instant) {
        if let Some((message, _)) = self.pending_error.take_if(|(_, decide)| now >= *decide) {
            self.firmware_error(message, now);
            return;
        }
        if let Some(Stop::Failure { give_up, .. }) = self.stopping() {
            if now >= *give_up || now - self.last_rx >= self.opts.silence_fail {
                self.finish_stop(false);
                return;
            }
        }
        if self.replay_after.is_some_and(|t| now >= t) {
            self.replay_after = None;
        }
        if self.settle.is_some_and(|s| now >= s.deadline()) {
            // Quiet: whatever error blocks were coming have come.
            self.settle = None;
        }
        if let Some((line, _)) = self.probe_replay.take_if(|(_, t)| now >= *t) {
            if self.in_flight.front().is_some_and(|f| f.number == line) {
                self.probe(now);
            }
        }
        if !self.autoreport() && self.accepting_job_lines() && now >= self.next_poll {
            self.next_poll = now + self.opts.temperature_interval;
            if !self.in_flight.iter().any(|f| f.is_m105)
                && !self.pending.iter().any(|(_, c)| c == "M105")
            {
                self.pending.push_back((Kind::Housekeeping, "M105".into()));
            }
        }
        if self.resend_hold.is_some_and(|hold| now >= hold) {
            // Nothing came after the `Resend:`: this firmware sends no `ok` there.
            self.resend_hold = None;
            if self.ok_may_follow.take().is_some() {
                self.resend_ok.seen_none += 1;
            }
        }
        let last_acked = self.acked_job;
        if self.heat_deadline().is_some_and(|d| now >= d) {
            let heat = self.heat.take().expect("a deadline means a heat wait");
            let temperatures = self.temps;
            self.fail_safely(
                Failure::HeatTimeout {
                    command: heat.command,
                    waited: now - heat.since,
                    temperatures,
                    last_acked,
                },
                now,
            );
            return;
        }
        let Some(front) = self.front_line().cloned() else {
            return;
        };
        if self.heat_at_front() {
            // Inside a heat wait: its own limit applies; but every firmware reports the
            // temperature each second while it waits, so silence means it is gone.
            if now - self.last_rx >= self.opts.silence_fail {
                self.fail(Failure::Silent {
                    waited: now - self.last_rx,
                    last_acked,
                });
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
        } else if now - self.last_ack >= self.opts.no_progress_timeout {
            self.fail_safely(
                Failure::NoProgress {
                    waited: now - self.last_ack,
                    last_acked,
                },
                now,
            );
            return;
        }
        if self.in_job() && now >= self.next_probe_at() {
            self.probe(now);
        }
    }

    /// Send an `M105` at once, in the room the send window keeps for it: the printer is most
    /// likely idle and the window only looks full because an `ok` was lost. Its answer
    /// acknowledges every earlier line.
    fn probe(&mut self, now: Instant) {
        if self.resend_hold.is_some()
            || self.settle.is_some()
            || self.replay_after.is_some_and(|t| now < t)
        {
            return;
        }
        self.last_probe = Some(now);
        let replay = self
            .history_line(self.send_cursor)
            .filter(|_| self.send_cursor < self.next_number)
            .map(|l| l.command.clone());
        let fits = match &replay {
            Some(command) => self.probe_fits(self.send_cursor, command),
            None => self.probe_fits(self.next_number, "M105"),
        };
        if !fits {
            // Earlier probes fill the room kept for one: the printer has not read them yet
            // (blocked), or their answers were lost, which only silence can tell now.
            return;
        }
        self.probes += 1;
        self.events.push_back(Event::Probe);
        // An ignored duplicate resend request may have been a real one: after a probe, a
        // repeated request is always new.
        self.duplicate_budget = None;
        if replay.is_some() {
            // A replay is waiting: the line the printer asked for is the probe.
            self.transmit(self.send_cursor, now);
        } else {
            // M105s still in flight while the printer is otherwise quiet had their answers
            // lost (garbled), since a printer answers an M105 as soon as it reaches it. The
            // probe's answer must settle them too: taken for theirs, each answer would
            // settle only the oldest, every probe would add one more, and the job would
            // never move again (each probe answered, none settling the lines behind them).
            // Only those older than any M105 was seen to take: Ultimaker2Marlin answers an
            // M105 only once the moves before it have left its queue, seconds after their
            // own `ok`s; taken for lost, its late answer would confirm a later M105 the
            // printer never got.
            let patience = self.m105_patience();
            // While stopping, an M105 sent before the stop lines keeps its place whatever
            // its age: Ultimaker2Marlin answers it only after the moves queued before it,
            // and that answer, taken for the stop's own M105, would confirm heaters off
            // that had not run yet (seen on a loaded machine: a cancel reported as
            // confirmed before the printer had executed `M104 S0`).
            let keep_below = if self.stopping().is_some() {
                self.stop_from
            } else {
                0
            };
            for f in self.in_flight.iter_mut() {
                if f.number >= keep_below && now.saturating_duration_since(f.sent) >= patience {
                    f.is_m105 = false;
                }
            }
            let number = self.new_line(Kind::Housekeeping, "M105".into());
            self.transmit(number, now);
        }
    }

    /// How long an `M105` may go unanswered before its answer counts as lost (four times
    /// the usual, at least [`M105_PATIENCE`]).
    fn m105_patience(&self) -> Duration {
        self.m105_latency
            .map_or(self.opts.silence_probe, |l| (l * 4).max(M105_PATIENCE))
            // A printer that answers each probe while earlier M105s seem to wait is
            // losing answers, not slow: the backlog is cleared within a few probes.
            .min(self.opts.silence_probe * 3)
    }

    /// How long the printer must be quiet after an error block before the replay goes.
    fn settle_quiet(&self) -> Duration {
        (self.ack_wait * 2).clamp(SETTLE_QUIET, SETTLE_QUIET_MAX)
    }

    /// When a heat wait times out: `heat_timeout` after it started or after its
    /// temperature last came closer to the target, whichever is later.
    fn heat_deadline(&self) -> Option<Instant> {
        let heat = self.heat.as_ref()?;
        let progress = heat.best.map_or(heat.since, |(_, at)| at.max(heat.since));
        Some(progress + self.opts.heat_timeout)
    }

    /// When to probe with M105 if nothing moves. Long commands are probed too: the M105
    /// waits in the printer's queue behind them, harmlessly, and its answer recovers an
    /// `ok` lost at their end. One probe at a time, unless its answer seems lost too.
    fn next_probe_at(&self) -> Instant {
        // Quiet for many times the usual wait for an answer: an `ok` was lost. Never sooner
        // than twice a line's usual round trip nor than `QUICK_PROBE` (a probe costs a
        // line), never later than `silence_probe`.
        let probe = match self.latency {
            Some(latency) => (self.ack_wait * 8).max(latency * 2).max(QUICK_PROBE),
            // Nothing answered yet: the link's round trip is unknown.
            None => FIRST_PROBE,
        }
        .min(self.opts.silence_probe);
        let mut base = self.last_progress.max(self.front_since) + probe;
        // A probe waits for the host's own holds (it would be held back until then).
        for t in [self.replay_after, self.resend_hold].into_iter().flatten() {
            base = base.max(t);
        }
        if let Some(settle) = &self.settle {
            base = base.max(settle.deadline());
        }
        let long_front = self.heat_at_front()
            || self
                .front_line()
                .is_some_and(|l| is_code(&l.command, &LONG_COMMANDS));
        if long_front && self.in_flight.iter().any(|f| f.is_m105) {
            // It waits behind the long command; more probes would only fill the buffer.
            return base.max(self.front_since + self.opts.long_command_timeout);
        }
        match self.last_probe {
            // An `M105` still waits after the last probe: its answer was lost, or taken
            // for an earlier one's whose own was lost. Once an `M105`'s usual time is
            // known, the next probe goes when that one counts as lost (see `probe`), so
            // its answer settles it: sooner, each answer would be taken for its
            // predecessor's and the newest probe would wait on; later only costs time.
            // Before, a quick probe learns it.
            Some(p) if self.in_flight.iter().any(|f| f.is_m105) => base.max(
                p + match self.m105_latency {
                    Some(_) => self.m105_patience().max(probe),
                    None => probe * 3,
                },
            ),
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
        self.greeting_sent_at = now;
        self.reset_numbering();
        self.pending.push_back((Kind::Setup, "M110 N0".into()));
        self.pending.push_back((Kind::Setup, "M115".into()));
    }

    /// M108 (breaking a heat wait where the firmware can), then heaters, fan and motors off,
    /// autoreport off, and an `M105` whose answer confirms them all.
    fn queue_safe_stop(&mut self, now: Instant) {
        self.stop_from = self.next_number;
        self.pending
            .retain(|(kind, _)| matches!(kind, Kind::SafeStop | Kind::Setup));
        let failure = matches!(self.stopping(), Some(Stop::Failure { .. }));
        if self.emergency_parser() && !failure {
            if self.pending.is_empty() {
                // Numbered, outside the window: the emergency parser acts on it on arrival
                // (breaking an M109/M190 wait), and the queue then acknowledges it in order.
                let number = self.new_line(Kind::SafeStop, "M108".into());
                if self.send_cursor == number {
                    self.transmit(number, now);
                }
            } else {
                self.pending.push_back((Kind::SafeStop, "M108".into()));
            }
        }
        for cmd in SAFE_STOP {
            self.pending.push_back((Kind::SafeStop, cmd.into()));
        }
        if self.autoreport() {
            self.pending.push_back((Kind::SafeStop, "M155 S0".into()));
        }
        self.pending.push_back((Kind::Sync, "M105".into()));
    }

    /// A failure while the printer still answers: never leave it hot. The printer's line
    /// counter is reset (`M110`), whatever it expected, and the safe-stop lines follow.
    fn fail_safely(&mut self, failure: Failure, now: Instant) {
        match &self.phase {
            Phase::Job(JobPhase::Stopping(Stop::Failure { .. })) => self.finish_stop(false),
            Phase::Job(_) => {
                let give_up = now + self.opts.stop_timeout;
                self.phase = Phase::Job(JobPhase::Stopping(Stop::Failure { failure, give_up }));
                // A new episode with numbers of its own, above any the printer has seen:
                // `N<k> M110 N<k>` passes whatever it expects, and a request for an older
                // number then means it rejected the M110 (see `handle_resend`).
                let first = self.next_number;
                self.reset_numbering();
                self.next_number = first;
                self.send_cursor = first;
                self.cautious_until = first + 2;
                self.pending
                    .push_back((Kind::Setup, format!("M110 N{first}")));
                if self.emergency_parser() {
                    // Break a heat wait the printer may be stuck in; without a number, so it
                    // needs no place in the sequence (the emergency parser acts on arrival;
                    // the queue later runs it as an unnumbered command and says `ok`).
                    self.outgoing.extend_from_slice(b"M108\n");
                    if !self.advanced_ok {
                        self.swallow_oks += 1;
                    }
                }
                // A new episode: what the last one left in flight is gone.
                self.last_progress = now;
                self.last_ack = now;
                self.front_since = now;
                self.queue_safe_stop(now);
                self.pump(now);
            }
            _ => self.fail(failure),
        }
    }

    /// Report the failure that stopped the printer, with whether the stop was confirmed.
    fn finish_stop(&mut self, confirmed: bool) {
        let failure = match self.stopping() {
            Some(Stop::Failure { failure, .. }) => failure.clone(),
            _ => Failure::Cancelled {
                last_acked: self.acked_job,
            },
        };
        self.events.push_back(Event::SafeStop { confirmed });
        self.fail(failure);
    }

    /// A firmware error that is not part of a resend or a halt: the printer refused
    /// something or failed at it, so the job cannot go on as the file says. Stop safely.
    fn firmware_error(&mut self, message: String, now: Instant) {
        self.events.push_back(Event::Message(message.clone()));
        if self.in_job() && self.stopping().is_none() {
            let last_acked = self.acked_job;
            self.fail_safely(
                Failure::FirmwareError {
                    message,
                    last_acked,
                },
                now,
            );
        }
    }

    fn fail(&mut self, failure: Failure) {
        if self.phase != Phase::Finished {
            self.phase = Phase::Finished;
            self.events.push_back(Event::Failed(failure));
        }
    }

    fn check_progress(&mut self, now: Instant) {
        let Phase::Job(job) = &self.phase else {
            return;
        };
        let drained = self.in_flight.is_empty()
            && self.send_cursor >= self.next_number
            && self.pending.is_empty();
        if !drained {
            return;
        }
        match job {
            JobPhase::Stopping(_) => self.finish_stop(true),
            JobPhase::Paused { synced: false, .. } => {
                // Drained of `ok`s is not drained: Ultimaker2Marlin acknowledges moves as
                // they enter its queue. An answered M105 is processed after all of them.
                self.phase = Phase::Job(JobPhase::Paused {
                    synced: true,
                    reported: false,
                });
                self.pending.push_back((Kind::Sync, "M105".into()));
                self.pump(now);
            }
            JobPhase::Paused {
                synced: true,
                reported: false,
            } => {
                self.phase = Phase::Job(JobPhase::Paused {
                    synced: true,
                    reported: true,
                });
                self.events.push_back(Event::Paused);
            }
            JobPhase::Paused { .. } => {}
            JobPhase::Streaming if self.next_job < self.job.len() => {}
            JobPhase::Streaming => {
                // Only an answered M105 proves every earlier line was accepted in order.
                // The printer stays connected between jobs: its reports stop with the job.
                self.phase = Phase::Job(JobPhase::Closing);
                if self.autoreport() {
                    self.pending
                        .push_back((Kind::Housekeeping, "M155 S0".into()));
                }
                self.pending.push_back((Kind::Sync, "M105".into()));
                self.pump(now);
            }
            JobPhase::Closing => self.finish_job(),
        }
    }

    fn finish_job(&mut self) {
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
            fragments: self.fragments,
        }));
    }

    fn handle(&mut self, reply: Reply, now: Instant) {
        self.resend_hold = None;
        let quiet = self.settle_quiet();
        if let Some(settle) = &mut self.settle {
            // The printer is still talking: more blocks may follow.
            settle.quiet_until = now + quiet;
        }
        if let Some(follow) = self.ok_may_follow.take() {
            let plain_ok =
                matches!(&reply, Reply::Ok(ok) if !ok.text && ok.line.is_none() && !ok.advanced);
            if follow.learn {
                if plain_ok {
                    self.resend_ok.seen_ok += 1;
                } else {
                    self.resend_ok.seen_none += 1;
                }
            }
            if plain_ok && (follow.swallow || follow.learn) {
                return; // the `ok` printed with the `Resend:` or the fragment's answer
            }
        }
        if let Some((message, _)) = self.pending_error.take() {
            match reply {
                Reply::Resend(_) | Reply::LineError(_) | Reply::Fatal(_) | Reply::Error(_) => {
                    // Part of a resend or a halt, or followed by another error (which then
                    // decides: a halt's reason often comes in several lines).
                }
                _ => self.firmware_error(message, now),
            }
        }
        match reply {
            Reply::Start => match &self.phase {
                Phase::Boot { .. } => self.phase = Phase::Boot { saw_start: true },
                Phase::Greeting => {
                    // Rebooted while we greeted it: start over once it settles.
                    self.reset_numbering();
                    self.phase = Phase::Boot { saw_start: true };
                }
                _ => {
                    // A reset switches the heaters off; the print is lost.
                    let last_acked = self.acked_job;
                    self.fail(Failure::PrinterReset { last_acked });
                }
            },
            Reply::Fatal(line) => {
                let mut parts = std::mem::take(&mut self.recent_errors);
                parts.push(line);
                let message = parts.join(" / ");
                let last_acked = self.acked_job;
                self.fail(Failure::Fatal {
                    message,
                    last_acked,
                });
            }
            Reply::LineError(line) => {
                // Its `Resend:` follows on its own line.
                let lower = line.to_ascii_lowercase();
                self.number_error = lower.contains("line number is not");
                self.error_last_line = lower
                    .rsplit_once("last line:")
                    .and_then(|(_, k)| k.trim().parse().ok());
            }
            Reply::Error(line) => {
                self.recent_errors.push(line.clone());
                if self.recent_errors.len() > 4 {
                    self.recent_errors.remove(0);
                }
                if line
                    .to_ascii_lowercase()
                    .contains("no line number with checksum")
                {
                    // Ultimaker2Marlin on the tail of a line cut by a buffer flush (it has
                    // a `*` but no `N`): neither `Resend:` nor `ok` follows.
                    self.fragments += 1;
                    self.events.push_back(Event::Fragment(line));
                } else if self.in_job() && self.stopping().is_none() {
                    // Decided by the next line, or after a moment of silence.
                    self.pending_error = Some((line, now + self.opts.resend_ok_wait));
                } else {
                    self.events.push_back(Event::Message(line));
                }
            }
            Reply::Resend(n) => self.handle_resend(n, now),
            Reply::Ok(ok) => {
                if let Some(report) = ok.report {
                    self.take_report(report, now);
                }
                self.handle_ok(&ok, now);
            }
            Reply::Busy(line) => {
                self.last_progress = now;
                self.events.push_back(Event::Busy(line));
            }
            Reply::Wait if matches!(self.phase, Phase::Boot { .. }) => {
                // Up and idle (a NO_TIMEOUTS build says so all the time, so the link would
                // never fall quiet): greet it now.
                self.send_greeting(now);
            }
            Reply::Wait => {
                // The printer's queue is empty. Lines still believed in flight had their
                // `ok`s lost (or are still on the wire): probe at once, never treat it as a
                // sign of life.
                // At most one probe a second: `wait` comes often, and a probe's answer
                // takes a moment.
                let spacing = (self.opts.silence_probe / 2).min(Duration::from_secs(1));
                let recent_probe = self
                    .last_probe
                    .is_some_and(|p| now.saturating_duration_since(p) < spacing);
                if self.in_job() && !self.in_flight.is_empty() && !recent_probe {
                    self.probe(now);
                }
            }
            Reply::UnknownCommand(text) => {
                // Some firmware quotes the whole line, number and checksum included.
                let command = strip_framing(&text);
                // Compared as the printer reads them: the cut-line guard may have
                // written the line with an extra space or trailing zeros.
                let command = canonical(command);
                let ours = self.in_flight.iter().any(|f| {
                    self.history_line(f.number)
                        .is_some_and(|l| canonical(&l.command).eq_ignore_ascii_case(&command))
                });
                if ours {
                    self.events
                        .push_back(Event::Message(format!("Unknown command: \"{text}\"")));
                } else {
                    // Not a line we sent: the piece of a line cut by a buffer flush. Its
                    // `ok` (plain in builds without ADVANCED_OK) answers no line of ours.
                    self.fragments += 1;
                    if !self.advanced_ok {
                        self.ok_may_follow = Some(OkFollow {
                            swallow: true,
                            learn: false,
                        });
                    }
                    self.events.push_back(Event::Fragment(text));
                }
            }
            Reply::Temperatures(report) => self.take_report(report, now),
            Reply::FirmwareName(line) => self.parse_firmware_line(&line),
            Reply::Capability(name, value) => {
                if name == "ADVANCED_OK" && value {
                    self.advanced_ok = true;
                }
                // Marlin 2.1 lists about 40; a printer (or noise) writing endless new
                // names must not grow the map without bound.
                let known = self.info.capabilities.contains_key(&name);
                if known || self.info.capabilities.len() < MAX_CAPABILITIES {
                    self.info.capabilities.insert(name, value);
                }
            }
            Reply::Action(action) => {
                self.events.push_back(Event::HostAction(action.clone()));
                match action {
                    HostAction::Cancel => self.cancel(now),
                    HostAction::Pause => self.pause(now),
                    HostAction::Resume => self.resume(now),
                    HostAction::Other(_) => {}
                }
            }
            Reply::Other(line) => self.events.push_back(Event::Message(line)),
        }
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

    /// Take a temperature report: a reading without a target (Ultimaker2Marlin's
    /// `T:210.0 E:0 W:?`) keeps the target known before. During a heat wait, note when the
    /// temperature last came closer to its target.
    fn take_report(&mut self, report: Report, now: Instant) {
        let merge = |old: Option<Temp>, new: Option<Temp>| match (old, new) {
            (Some(old), Some(new)) => Some(Temp {
                current: new.current,
                target: new.target.or(old.target),
            }),
            (old, new) => new.or(old),
        };
        self.temps.hotend = merge(self.temps.hotend, report.temperatures.hotend);
        self.temps.bed = merge(self.temps.bed, report.temperatures.bed);
        self.heat_reported = report.waiting;
        if let Some(heat) = &mut self.heat {
            let reading = if heat.bed {
                self.temps.bed
            } else {
                self.temps.hotend
            };
            if let Some(reading) = reading {
                if let Some(target) = heat.target.or(reading.target) {
                    // Progress is coming closer to the target: rising for a heat-up,
                    // falling for a cool-down (`M190 R30`).
                    let gap = (target - reading.current).abs();
                    match heat.best {
                        Some((best, _)) if gap > best - 0.5 => {}
                        _ => heat.best = Some((gap, now)),
                    }
                    if gap <= 2.0 && !report.waiting {
                        // There, and the printer no longer reports a wait.
                        self.heat = None;
                    }
                }
            }
        }
        self.events.push_back(Event::Temperatures(self.temps));
    }

    fn handle_ok(&mut self, ok: &OkReply, now: Instant) {
        self.last_progress = now;
        // Any `ok` ends a heat wait's reports: the printer reads commands again.
        if std::mem::take(&mut self.heat_reported) {
            // The first `ok` after the in-wait reports: the printer read nothing while it
            // waited, so this is the heat command's own.
            self.heat = None;
        }
        if ok.text {
            // The answer of an M105 (only it carries text, whether or not the temperatures
            // in it could be read): the printer processed it after every earlier line.
            if let Some(pos) = self.in_flight.iter().position(|f| f.is_m105) {
                let number = self.in_flight[pos].number;
                // Every `ok` owed by an earlier `Resend:` or fragment came before this one:
                // a debt still open was a guess that went wrong.
                self.swallow_oks = 0;
                self.ack_through(number, now);
                return;
            }
        }
        if let Some(n) = ok.line {
            self.advanced_ok = true;
            if n < self.next_number {
                self.ack_through(n, now);
            }
            return;
        }
        if ok.advanced {
            // ADVANCED_OK answer without a number: it answered a line that had none, the
            // tail of a line cut by a receive-buffer flush, which the firmware executed.
            self.fragments += 1;
            self.events.push_back(Event::Fragment(
                "a line without a number was executed".into(),
            ));
            return;
        }
        if self.advanced_ok {
            // A plain `ok` in an ADVANCED_OK build is the one after `Resend:`.
            return;
        }
        if self.swallow_oks > 0 {
            self.swallow_oks -= 1;
            return;
        }
        // A plain `ok` answers the oldest line, but never an `M105`: its answer carries the
        // temperatures. Ultimaker2Marlin answers moves as they enter its queue and an
        // `M105` only when it runs, so the `ok`s of moves sent after an `M105` come before
        // its answer; taken for the `M105`'s, they left its answer to be taken for a later
        // `M105`'s, which the printer may never have received (a corrupted line), and the
        // resend that followed looked like a printer that had lost its state.
        if let Some(pos) = self.in_flight.iter().position(|f| !f.sync && !f.is_m105) {
            let f = self.in_flight.remove(pos).expect("position is valid");
            self.in_flight_bytes -= f.bytes;
            self.acknowledged(f, now, true);
        } else if let Some(f) = self.in_flight.pop_front() {
            // Only `M105`s are waiting: this `ok` is the oldest one's, whatever became of its
            // text (a firmware that answers a bare `ok`, a report garbled on the wire).
            // Progress never waits on reading the optional part of a reply.
            self.in_flight_bytes -= f.bytes;
            self.acknowledged(f, now, true);
        }
    }

    /// Every line up to `number` is acknowledged (and certainly accepted by the printer).
    fn ack_through(&mut self, number: u64, now: Instant) {
        while self.in_flight.front().is_some_and(|f| f.number <= number) {
            let f = self.in_flight.pop_front().expect("front exists");
            self.in_flight_bytes -= f.bytes;
            let own = f.number == number;
            self.acknowledged(f, now, own);
        }
        self.confirmed = Some(self.confirmed.map_or(number, |c| c.max(number)));
        if self.heat.as_ref().is_some_and(|h| h.number < number) {
            self.heat = None; // a later line was answered: the wait is over
        }
    }

    /// `own`: by its own answer, not settled by a later line's (whose wait says nothing
    /// about this line's).
    fn acknowledged(&mut self, f: InFlight, now: Instant, own: bool) {
        let number = f.number;
        let waited = now.saturating_duration_since(self.front_since);
        // A line settled by a probe's answer waited for the probe, not for the printer:
        // taken into the averages, each lost `ok` would make the next one slower to find
        // (seen on the real Marlin: probes a second apart after a few lost `ok`s).
        if own {
            // An `M105` answered while a later `M105` is in flight may have had its own
            // answer lost, and this be the later one's: its wait is then the time until the
            // next probe. It paces no probe (seen on the real Marlin: one such sample
            // doubled the round trip, and the next probe came 1.2 s after the printer had
            // answered), and tells how long an `M105` may take only while nothing else does
            // (erring long there costs a probe; short, a false confirmation).
            let ambiguous = f.is_m105 && self.in_flight.iter().any(|g| g.is_m105);
            // The round trip follows a slower printer at once (a full planner: each `ok`
            // waits for a move to end) and a faster one slowly, so a probe's answer
            // queued behind moves is not taken for lost. Long commands say nothing about it.
            let long = self
                .history_line(number)
                .is_some_and(|l| is_code(&l.command, &LONG_COMMANDS) || is_heat_wait(&l.command));
            let sample = now.saturating_duration_since(f.sent);
            let follow = |l: Option<Duration>| {
                Some(l.map_or(sample, |l| ((l * 7 + sample) / 8).max(sample)))
            };
            if !ambiguous {
                self.ack_wait = (self.ack_wait * 7 + waited) / 8;
                if !long {
                    self.latency = follow(self.latency);
                }
            }
            if f.is_m105 && (!ambiguous || self.m105_latency.is_none()) {
                self.m105_latency = follow(self.m105_latency);
            }
        }
        self.front_since = now;
        self.last_ack = now;
        if !self.opts.firmware.acks_moves_on_entry()
            && self.heat.as_ref().is_some_and(|h| h.number == number)
        {
            self.heat = None; // `ok`s in line order: this is the heat command's own
        }
        // A successful answer after the requested line ends a resend episode.
        if let Some((line, _, _)) = self.repeated {
            if number >= line {
                self.repeated = None;
            }
        }
        let Some(line) = self.history_line(number) else {
            return;
        };
        match (&self.phase, line.kind) {
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
        // Whether an `ok` follows this `Resend:` (plain `ok`s are ignored anyway where
        // ADVANCED_OK numbers them).
        let expect_ok = !self.advanced_ok
            && self
                .resend_ok
                .known()
                .unwrap_or(self.opts.firmware.ok_after_resend());
        let first = self.history.front().map_or(self.next_number, |l| l.number);
        if self.phase == Phase::Greeting && (n < first || n >= self.next_number) {
            // The printer's counter is from an earlier session; M110 resets it.
            self.send_greeting(now);
            return;
        }
        let never_sent = n >= self.next_number || n > self.send_cursor;
        let counter_reset_pending = self.in_flight.front().is_some_and(|f| f.number == first)
            && self
                .history_line(first)
                .is_some_and(|l| l.kind == Kind::Setup && is_code(&l.command, &["M110"]));
        // A request for a line we never sent, after an error that names the line before it,
        // while our `M110` is unanswered: the printer rejected the `M110` (its counter still
        // runs from before). Send it again. A garbled number never matches its error.
        let consistent = std::mem::take(&mut self.error_last_line) == n.checked_sub(1);
        let stop_first = match self.stopping() {
            Some(Stop::Failure { .. }) => Some(first),
            _ => None,
        };
        let n = if never_sent && counter_reset_pending && consistent {
            first
        } else if let Some(first) = stop_first.filter(|&f| n < f) {
            // The printer still counts from before the stop: it rejected our M110. The
            // safe-stop lines are harmless to run twice, so replaying from it is safe.
            first
        } else {
            n
        };
        if let Some(confirmed) = self.confirmed.filter(|&c| n <= c) {
            let last_acked = self.acked_job;
            self.fail_safely(
                Failure::LostState {
                    line: n,
                    confirmed,
                    last_acked,
                },
                now,
            );
            return;
        }
        if n >= self.next_number || n > self.send_cursor {
            // Never sent: a garbled number (`Resend: 034497`). Nothing to replay.
            self.events.push_back(Event::Message(format!(
                "ignored resend request for line {n}"
            )));
            return;
        }
        if n < first {
            let last_acked = self.acked_job;
            self.fail_safely(
                Failure::LineGone {
                    line: n,
                    oldest_kept: first,
                    last_acked,
                },
                now,
            );
            return;
        }
        // The printer took every line before n off its receive ring into its command queue
        // (that is what `Last Line: n-1` says): they still owe their `ok`s, but no longer
        // take room in the ring, and a lost `ok` among them must not hold the window shut.
        for f in self.in_flight.iter_mut().filter(|f| f.number < n) {
            f.bytes = 0;
        }
        self.in_flight_bytes = self.in_flight.iter().map(|f| f.bytes).sum();
        let number_error = std::mem::take(&mut self.number_error);
        if let Some((line, remaining)) = self.duplicate_budget {
            if line == n && remaining > 0 && number_error {
                // Caused by a line that was already on its way when we began replaying.
                self.duplicate_budget = Some((line, remaining - 1));
                if let Some(settle) = self.settle.as_mut().filter(|s| s.line == n) {
                    settle.remaining = settle.remaining.saturating_sub(1);
                    if settle.remaining == 0 {
                        self.settle = None; // every line on its way has drawn its block
                    }
                }
                self.ok_may_follow = Some(OkFollow {
                    swallow: expect_ok,
                    learn: false,
                });
                if self.send_cursor > n {
                    // Seen on the real Marlin: each such block flushes the receive ring,
                    // with our replay in it if it had arrived; it then never gets an
                    // answer. Find out soon, not after a quiet probe interval.
                    self.probe_replay = Some((n, now + REPLAY_PROBE));
                }
                return;
            }
        }
        let (times, since) = match self.repeated {
            Some((line, times, since)) if line == n => (times + 1, since),
            _ => (1, now),
        };
        self.repeated = Some((n, times, since));
        let stopping = matches!(self.stopping(), Some(Stop::Failure { .. }));
        if stopping && times > 1 {
            // The safe stop rides out the noise, paced, until `stop_timeout` (see `tick_job`).
            self.replay_after = Some(now + self.opts.stop_pause);
        } else if times > self.opts.resend_limit {
            // A storm: paced replays until it ends or outlasts `storm_timeout`.
            self.replay_after = Some(now + self.opts.storm_pause);
        }
        if !stopping && times > self.opts.resend_limit && now - since >= self.opts.storm_timeout {
            let last_acked = self.acked_job;
            self.fail_safely(
                Failure::ResendLimit {
                    line: n,
                    times: times - 1,
                    last_acked,
                },
                now,
            );
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
        // Lines sent after n may still reach the printer, each drawing an error block that
        // flushes its ring: the replay waits for them (see `Settle`).
        self.settle = (dropped_after > 0).then(|| Settle {
            line: n,
            remaining: dropped_after,
            quiet_until: now + self.settle_quiet(),
            give_up: now + SETTLE_MAX,
        });
        if !self.advanced_ok {
            // The replay goes out at once. Where nothing else awaits an `ok`, the next line
            // tells whether this firmware sends one after `Resend:`.
            let learn = self.in_flight.is_empty() && self.resend_ok.known().is_none();
            self.ok_may_follow = Some(OkFollow {
                swallow: expect_ok,
                learn,
            });
            if learn {
                self.resend_hold = Some(now + self.opts.resend_ok_wait);
            }
        }
        let replay = self.send_cursor - n;
        self.cautious_until = self.send_cursor.max(n) + self.opts.cautious_lines;
        self.send_cursor = n;
        self.resends += 1;
        self.events.push_back(Event::Resend { line: n, replay });
        if self.accepting_job_lines() && !self.pending.iter().any(|(_, c)| c == "M105") {
            // Whatever became of the `ok`s owed around this request (one after `Resend:` or
            // none, earlier lines' answered late, some lost), the answer of an `M105` sent
            // after the replay settles them all: the printer runs it after every earlier line.
            self.pending.push_front((Kind::Housekeeping, "M105".into()));
        }
        if self.stopping() == Some(&Stop::Cancel) {
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

/// `N12 G1 X5*34` -> `G1 X5`; text without a number or checksum stays as it is.
fn strip_framing(text: &str) -> &str {
    let mut s = text.trim();
    if let Some(rest) = s.strip_prefix('N') {
        if let Some((number, command)) = rest.split_once(' ') {
            if !number.is_empty() && number.bytes().all(|b| b.is_ascii_digit()) {
                s = command;
                if let Some((body, cs)) = s.rsplit_once('*') {
                    if cs.bytes().all(|b| b.is_ascii_digit()) {
                        s = body;
                    }
                }
            }
        }
    }
    s.trim()
}

#[cfg(test)]
mod tests;
