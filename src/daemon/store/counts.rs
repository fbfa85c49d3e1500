//! What follows from a job's state change besides the change itself: its `job state` log
//! line, the counts by state and the metrics' tally. Apart from the snapshot that
//! publishes them: they are worked out from one job's records, before and after.

use super::stats;
use crate::daemon::job::{Job, JobState};

/// How many jobs reached each state since the store's task started (by [`JobState::ALL`]'s
/// order): `/metrics`, and `--exit-when-idle` (which needs a job to have finished).
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct JobCounts([u64; JobState::ALL.len()]);

impl JobCounts {
    fn count(&mut self, state: JobState) {
        if let Some(i) = JobState::ALL.iter().position(|s| *s == state) {
            self.0[i] += 1;
        }
    }

    /// Changes into `state`.
    pub fn entered(&self, state: JobState) -> u64 {
        JobState::ALL
            .iter()
            .position(|s| *s == state)
            .map_or(0, |i| self.0[i])
    }

    /// Changes into a state without work ahead (a job finished, for now or for good).
    pub fn finished(&self) -> u64 {
        JobState::ALL
            .iter()
            .filter(|s| !s.is_active())
            .map(|s| self.entered(*s))
            .sum()
    }
}

/// What follows from a job's state change besides the change itself: its log line, the
/// counts and the metrics' tally. Kept by the store's task alone and published in its
/// snapshot with the change, so a reader never sees one without the other. Counted from
/// the difference between a job's record and the one published before (its new entries in
/// `history`), whoever made the change: a request of this host, or another host of a
/// shared farm whose change a resync took in.
#[derive(Debug, Clone, Default)]
pub(super) struct Counted {
    pub(super) states: JobCounts,
    pub(super) tally: stats::Tally,
    /// The beds' ejects and checks by (printer, kind, result): counted as this host's
    /// changes of its beds are served.
    pub(super) beds: std::collections::BTreeMap<(String, &'static str, &'static str), u64>,
}

impl Counted {
    /// Announces the state changes `job` made since `before` (the record last published;
    /// None: a job new to the snapshot, whose every change is new here).
    pub(super) fn changes(&mut self, before: Option<&Job>, job: &Job) {
        let seen = before.map_or(0, |b| b.history.len());
        let n = job.history.len();
        for k in seen..n {
            let state = job.history[k].0;
            // The job's reason is that of its latest change only.
            let reason = (k + 1 == n).then_some(job.reason.as_deref()).flatten();
            tracing::info!(
                job = %job.id,
                printer = job.printer.as_deref(),
                state = state.name(),
                reason,
                "job state"
            );
            self.states.count(state);
            self.tally.count(job, k);
        }
    }
}
