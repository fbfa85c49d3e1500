//! What became of notification attempts, per receiver, for `crispen_notifications_total`.
//! Receivers are the config's (at most `MAX_RECEIVERS`), so the labels stay bounded. The
//! counts are the process's: they start at zero with each run, as Prometheus counters do.

use std::collections::BTreeMap;
use std::sync::Mutex;

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

static COUNTS: Mutex<BTreeMap<(String, Outcome), u64>> = Mutex::new(BTreeMap::new());

fn counts() -> std::sync::MutexGuard<'static, BTreeMap<(String, Outcome), u64>> {
    COUNTS.lock().unwrap_or_else(|e| e.into_inner())
}

/// Shows `receiver`'s counters from zero (a series that exists before its first event).
pub(crate) fn register(receiver: &str) {
    let mut c = counts();
    for o in Outcome::ALL {
        c.entry((receiver.to_string(), o)).or_insert(0);
    }
}

pub(crate) fn count(receiver: &str, outcome: Outcome) {
    *counts().entry((receiver.to_string(), outcome)).or_insert(0) += 1;
}

/// Every (receiver, outcome, count), by receiver.
pub(crate) fn all() -> Vec<(String, Outcome, u64)> {
    counts()
        .iter()
        .map(|((r, o), n)| (r.clone(), *o, *n))
        .collect()
}
