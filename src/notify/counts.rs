//! What became of notification attempts, per receiver, for `crispen_notifications_total`.
//! Receivers are the config's (at most `MAX_RECEIVERS`), so the labels stay bounded. The
//! counts are the run's: they start at zero with each run, as Prometheus counters do.
//! Each receiver's tally is published by its tasks (its sender, and the observer when it
//! cannot queue an event) as a `watch`, and read through [`Counts`] by `/metrics`.

use std::sync::Arc;
use tokio::sync::watch;

/// What became of one attempt or event.
#[derive(Debug, Clone, Copy, PartialEq, Eq, PartialOrd, Ord)]
pub(crate) enum Outcome {
    /// The receiver took it (a 2xx answer).
    Delivered,
    /// An attempt failed (no answer, or an error answer); the event is retried.
    Error,
    /// The event was given up: refused for good, too old, too many attempts, or pushed
    /// out of a full queue.
    Dropped,
}

impl Outcome {
    pub(crate) const ALL: [Outcome; 3] = [Outcome::Delivered, Outcome::Error, Outcome::Dropped];

    pub(crate) fn name(self) -> &'static str {
        match self {
            Outcome::Delivered => "delivered",
            Outcome::Error => "error",
            Outcome::Dropped => "dropped",
        }
    }
}

/// One receiver's counts, by outcome (in [`Outcome::ALL`]'s order).
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub(crate) struct Tally([u64; 3]);

impl Tally {
    /// Counts one `outcome` on `tally`.
    pub(crate) fn count(tally: &watch::Sender<Tally>, outcome: Outcome) {
        tally.send_modify(|t| t.0[outcome as usize] += 1);
    }
}

/// Every receiver's counts, as `/metrics` reads them: each one's name and its tally (from
/// zero before its first event, so its series exist from the start).
#[derive(Debug, Clone, Default)]
pub struct Counts(Arc<Vec<(String, watch::Receiver<Tally>)>>);

impl Counts {
    pub(crate) fn new(receivers: Vec<(String, watch::Receiver<Tally>)>) -> Counts {
        Counts(Arc::new(receivers))
    }

    /// Every (receiver, outcome, count), by receiver.
    pub(crate) fn all(&self) -> Vec<(String, Outcome, u64)> {
        self.0
            .iter()
            .flat_map(|(name, tally)| {
                let tally = *tally.borrow();
                Outcome::ALL.map(|o| (name.clone(), o, tally.0[o as usize]))
            })
            .collect()
    }
}
