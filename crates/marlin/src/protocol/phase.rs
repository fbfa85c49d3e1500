//! Where the host is: booting, greeting, idle, in a job (and where in it), finished.

use super::event::Failure;
use std::time::Instant;

#[derive(Debug, Clone, PartialEq)]
pub(super) enum Phase {
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
pub(super) enum JobPhase {
    /// Sending the job's lines.
    Streaming,
    /// Every job line answered: autoreport off and a final `M105` queued, whose answer
    /// ends the job done (only it proves every earlier line was accepted in order).
    Closing,
    /// No job lines go out. `synced`: an `M105` after the last job line was queued (with
    /// Ultimaker2Marlin, all `ok`s in does not mean the queued moves ran); `reported`:
    /// [`Event::Paused`](super::event::Event::Paused) went out, once that `M105` was answered.
    Paused { synced: bool, reported: bool },
    /// Heaters, fan and motors off on their way; the job ends once they are answered.
    Stopping(Stop),
}

/// Why a job stops sending its lines.
#[derive(Debug, Clone, PartialEq)]
pub(super) enum Stop {
    /// On request. Given up, unconfirmed, at `give_up` (as a failure's stop).
    Cancel { give_up: Instant },
    /// A failure while the printer still answers: the safe-stop lines go out (as for a
    /// cancel), and the failure is reported once an `M105` after them is answered or
    /// `give_up` passes.
    Failure { failure: Failure, give_up: Instant },
}

impl Stop {
    /// When the stop is given up unconfirmed, while the printer keeps talking.
    pub(super) fn give_up(&self) -> Instant {
        match self {
            Stop::Cancel { give_up } | Stop::Failure { give_up, .. } => *give_up,
        }
    }
}
