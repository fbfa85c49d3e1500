//! The host's clocks: when the printer last said something, last made progress and last
//! answered a line, when the next poll and probe are due, and how long its answers usually
//! take (which paces the probes for lost `ok`s). The deadlines and timeouts acting on them
//! are in `timeouts.rs`.

use std::time::{Duration, Instant};

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

/// The times and latencies of one connection.
#[derive(Debug)]
pub(super) struct Timers {
    pub(super) opened_at: Instant,
    pub(super) last_rx: Instant,
    pub(super) front_since: Instant,
    pub(super) last_probe: Option<Instant>,
    /// Last `ok`, resend request or busy keep-alive: temperature reports and `wait` alone
    /// do not prove that commands are moving.
    pub(super) last_progress: Instant,
    /// Last time a line was acknowledged.
    pub(super) last_ack: Instant,
    /// How long the oldest line typically waits for its answer (a moving average): a
    /// printer that answers in milliseconds and then says nothing for many times that has
    /// lost an `ok`, and is probed long before `silence_probe`.
    pub(super) ack_wait: Duration,
    /// How long a line typically takes from being sent to its answer (a moving average;
    /// None until one was answered): no probe counts as lost sooner than twice that, so
    /// on a slow link a probe's answer is never taken for a later probe's.
    pub(super) latency: Option<Duration>,
    /// The same for `M105`s alone.
    pub(super) m105_latency: Option<Duration>,
    pub(super) greeting_sent_at: Instant,
    pub(super) next_poll: Instant,
    /// When a stop last sent an unnumbered `M108`.
    pub(super) last_m108: Option<Instant>,
    /// When a stop that waits for a heat-up last said how long it may take.
    pub(super) last_stop_wait: Option<Instant>,
}

impl Timers {
    /// The clocks of a port opened at `now`.
    pub(super) fn new(now: Instant) -> Self {
        Timers {
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
            next_poll: now,
            last_m108: None,
            last_stop_wait: None,
        }
    }

    /// How long an `M105` may go unanswered before its answer counts as lost (four times
    /// the usual, at least [`M105_PATIENCE`]).
    pub(super) fn m105_patience(&self, silence_probe: Duration) -> Duration {
        self.m105_latency
            .map_or(silence_probe, |l| (l * 4).max(M105_PATIENCE))
            // A printer that answers each probe while earlier M105s seem to wait is
            // losing answers, not slow: the backlog is cleared within a few probes.
            .min(silence_probe * 3)
    }

    /// How long nothing may move before a probe goes out.
    pub(super) fn probe_interval(&self, silence_probe: Duration) -> Duration {
        // Quiet for many times the usual wait for an answer: an `ok` was lost. Never sooner
        // than twice a line's usual round trip nor than `QUICK_PROBE` (a probe costs a
        // line), never later than `silence_probe`.
        match self.latency {
            Some(latency) => (self.ack_wait * 8).max(latency * 2).max(QUICK_PROBE),
            // Nothing answered yet: the link's round trip is unknown.
            None => FIRST_PROBE,
        }
        .min(silence_probe)
    }

    /// Learn from a line answered by its own answer: `waited` at the front of the line
    /// queue, `sample` since it was sent. `ambiguous`: an `M105` answered while a later
    /// `M105` is in flight; `long`: a long command or a heat wait.
    pub(super) fn learn(
        &mut self,
        waited: Duration,
        sample: Duration,
        is_m105: bool,
        ambiguous: bool,
        long: bool,
    ) {
        // The round trip follows a slower printer at once (a full planner: each `ok`
        // waits for a move to end) and a faster one slowly, so a probe's answer
        // queued behind moves is not taken for lost. Long commands say nothing about it.
        let follow =
            |l: Option<Duration>| Some(l.map_or(sample, |l| ((l * 7 + sample) / 8).max(sample)));
        if !ambiguous {
            self.ack_wait = (self.ack_wait * 7 + waited) / 8;
            if !long {
                self.latency = follow(self.latency);
            }
        }
        if is_m105 && (!ambiguous || self.m105_latency.is_none()) {
            self.m105_latency = follow(self.m105_latency);
        }
    }
}
