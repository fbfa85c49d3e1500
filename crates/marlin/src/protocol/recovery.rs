//! What the host keeps between a printer's resend requests: holds on the replay (the
//! printer may still be sending error blocks, or be in a storm), duplicate requests to
//! expect, and what this firmware does after `Resend:`. The handling itself is in
//! `resend.rs`.

use std::time::{Duration, Instant};

/// The quiet after an error block that ends a [`Settle`]: at least this, or twice the
/// usual answer time.
const SETTLE_QUIET: Duration = Duration::from_millis(5);
pub(super) const SETTLE_QUIET_MAX: Duration = Duration::from_millis(50);
/// The longest a replay waits for error blocks.
pub(super) const SETTLE_MAX: Duration = Duration::from_millis(150);
/// After a repeated error block that may have eaten a replay: probe this soon if the
/// replayed line is still unanswered (its answer would have come at once).
pub(super) const REPLAY_PROBE: Duration = Duration::from_millis(30);

/// Unexplained answers (see [`Recovery::unexplained`]) with no line answered between them
/// that stop a job: one may be noise whose `ok`, taken for the refusal's, was a line's own
/// (its line then waits for a probe's answer); three, each standing for another line the
/// host sent, is a printer refusing each line it gets.
pub(super) const UNEXPLAINED_LIMIT: u32 = 3;

/// What the line after a `Resend:` or a fragment's `Unknown command` may be.
#[derive(Debug, Clone, Copy)]
pub(super) struct OkFollow {
    /// A plain `ok` there is theirs, not a line's.
    pub(super) swallow: bool,
    /// Nothing else awaits an `ok`: whether one comes tells this firmware's way.
    pub(super) learn: bool,
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
pub(super) struct Settle {
    pub(super) line: u64,
    /// Blocks still expected.
    pub(super) remaining: u64,
    /// Quiet until then: no more blocks are coming.
    pub(super) quiet_until: Instant,
    pub(super) give_up: Instant,
}

impl Settle {
    pub(super) fn deadline(&self) -> Instant {
        self.quiet_until.min(self.give_up)
    }

    /// How long the printer must be quiet after an error block before the replay goes,
    /// given how long a line usually waits for its answer.
    pub(super) fn quiet(ack_wait: Duration) -> Duration {
        (ack_wait * 2).clamp(SETTLE_QUIET, SETTLE_QUIET_MAX)
    }
}

/// Whether this firmware sends an `ok` after `Resend:`, learnt from unambiguous cases (a
/// resend with nothing else awaiting an `ok`): Marlin 2.1 and Ultimaker2Marlin do, Marlin
/// 2.0 does not, Marlin 1.1 sometimes. Until two observations agree, the firmware profile's
/// value stands in where a case is ambiguous.
#[derive(Debug, Clone, Copy, Default)]
pub(super) struct ResendOk {
    pub(super) seen_ok: u32,
    pub(super) seen_none: u32,
}

impl ResendOk {
    pub(super) fn known(&self) -> Option<bool> {
        (self.seen_ok + self.seen_none >= 2 && self.seen_ok != self.seen_none)
            .then_some(self.seen_ok > self.seen_none)
    }
}

/// The resend state of one connection (see the module's documentation).
#[derive(Debug, Default)]
pub(super) struct Recovery {
    /// The line just read asks for an `ok` right behind it: a `Resend:` (Marlin 2.1 and
    /// Ultimaker2Marlin print `ok` in the same breath) or a fragment's `Unknown command`.
    /// Only the very next line can be that `ok`; a guess never outlives it, so it cannot eat
    /// the `ok` of a later line.
    pub(super) ok_may_follow: Option<OkFollow>,
    /// While it is not known whether an `ok` follows `Resend:` and nothing else awaits an
    /// `ok`, the replay waits for the next line (or this time) to tell.
    pub(super) resend_hold: Option<Instant>,
    /// Duplicate resend requests to ignore: (line, how many). Lines already on their way
    /// when the replay began each cause one, always as a line-number error (Marlin checks
    /// the number first); a request after a checksum error is the replay itself corrupted
    /// again, a new request.
    pub(super) duplicate_budget: Option<(u64, u64)>,
    /// The `Error:` before the next `Resend:` was a line-number error.
    pub(super) number_error: bool,
    /// Its `Last Line: <k>`.
    pub(super) error_last_line: Option<u64>,
    /// The line requested again, how often, and since when.
    pub(super) repeated: Option<(u64, u32, Instant)>,
    /// Replays wait until then (a resend storm, a safe stop inside a noise burst).
    pub(super) replay_after: Option<Instant>,
    /// Probe then if the replayed line is still unanswered: a repeated error block came
    /// after the replay went out, and Marlin may have thrown the replay away with it.
    pub(super) probe_replay: Option<(u64, Instant)>,
    /// After a `Resend:`, the replay waits for the error blocks of the lines that were
    /// already on their way (see [`Settle`]).
    pub(super) settle: Option<Settle>,
    pub(super) resend_ok: ResendOk,
    /// Answers since the last acknowledged line that the host cannot explain: requests
    /// for lines beyond any it sent without an error naming the line before, `ok N` for a
    /// line never sent; never more than the lines still owed an answer (a printer that
    /// counts from elsewhere answers each line it gets so; noise beyond them follows no
    /// line of the host's). [`UNEXPLAINED_LIMIT`] mean the printer counts from elsewhere.
    pub(super) unexplained: u32,
}

impl Recovery {
    /// Nothing goes out now: the host waits to learn whether an `ok` follows a `Resend:`,
    /// for the error blocks of lines on their way, or for a paced replay.
    pub(super) fn holding(&self, now: Instant) -> bool {
        self.resend_hold.is_some()
            || self.settle.is_some()
            || self.replay_after.is_some_and(|t| now < t)
    }

    /// A new numbering: what was kept about the last one's resends is void (what was
    /// learnt about the firmware stays).
    pub(super) fn clear_episode(&mut self) {
        self.duplicate_budget = None;
        self.repeated = None;
        self.replay_after = None;
        self.probe_replay = None;
        self.settle = None;
        self.ok_may_follow = None;
        self.resend_hold = None;
        self.unexplained = 0;
    }
}
