//! What has happened but could not be persisted yet (a full disk, a database outage): the
//! one rule both stores keep. An outcome (a print ended) is worked out on the store's own
//! record first ([`outcome`]), so it stands at once: it is shown, the job is never offered
//! again, and it is written by [`Pending::write`] once the store can. A bed that needs
//! clearing must still need it after the outage, so a bed gate is kept the same way.

use crate::daemon::job::{Job, JobState, PrinterGate, StoreError};
use std::collections::BTreeMap;

/// Works out an outcome on `job` (the table checked): the state it was in, and the job
/// after it.
pub(crate) fn outcome(
    job: &Job,
    state: JobState,
    reason: Option<String>,
    also: impl FnOnce(&mut Job),
) -> Result<(JobState, Job), StoreError> {
    let mut after = job.clone();
    let from = after.state;
    after.apply_transition(state, reason, also)?;
    Ok((from, after))
}

/// Outcomes and bed gates kept until they can be written.
#[derive(Debug, Default)]
pub(crate) struct Pending {
    /// By job: the state it was in before the outcome, and the job after it.
    outcomes: BTreeMap<String, (JobState, Job)>,
    gates: BTreeMap<String, PrinterGate>,
}

/// How one attempt to write something kept went.
#[derive(Debug)]
pub(crate) enum Attempt {
    /// Written; with the store's record of the job afterwards, when it has one.
    Written(Option<Box<Job>>),
    /// Not this one, now; the others may still be written (a job's own directory).
    Failed,
    /// The store cannot be reached: the rest is not tried either, rather than each
    /// waiting out the same failure.
    Unreachable,
    /// Refused for good (the farm moved the job on, its directory is gone): forgotten.
    Dropped,
}

/// What [`Pending::write`] did.
#[derive(Debug, Default)]
pub(crate) struct Written {
    /// The jobs' records after their outcomes were written.
    pub jobs: Vec<Job>,
    /// Jobs whose outcome was dropped: the store's record of them is to be read again.
    pub dropped: Vec<String>,
    /// The store was found unreachable.
    pub unreachable: bool,
}

impl Pending {
    /// Keeps an outcome (`from`: the state the job was in) to be written later.
    pub(crate) fn keep_outcome(&mut self, from: JobState, job: Job) {
        self.outcomes.insert(job.id.clone(), (from, job));
    }

    /// A later change of the job was written, so its kept outcome was too.
    pub(crate) fn written(&mut self, id: &str) {
        self.outcomes.remove(id);
    }

    pub(crate) fn has_outcome(&self, id: &str) -> bool {
        self.outcomes.contains_key(id)
    }

    pub(crate) fn keep_gate(&mut self, printer: &str, gate: PrinterGate) {
        self.gates.insert(printer.to_string(), gate);
    }

    /// A later gate of the printer was written.
    pub(crate) fn gate_written(&mut self, printer: &str) {
        self.gates.remove(printer);
    }

    /// The gates kept, by printer.
    pub(crate) fn gates(&self) -> impl Iterator<Item = (&String, &PrinterGate)> {
        self.gates.iter()
    }

    /// How many outcomes and gates wait.
    pub(crate) fn len(&self) -> usize {
        self.outcomes.len() + self.gates.len()
    }

    #[cfg(test)]
    pub(crate) fn is_empty(&self) -> bool {
        self.len() == 0
    }

    /// Everything kept, outcomes first, each to be tried in turn and handed back to
    /// [`Pending::settle`] with how it went (see [`Pending::write`]).
    pub(crate) fn take(&mut self) -> Vec<Kept> {
        let outcomes = std::mem::take(&mut self.outcomes)
            .into_iter()
            .map(|(id, (from, job))| Kept::Outcome {
                id,
                from,
                job: Box::new(job),
            });
        let gates = std::mem::take(&mut self.gates)
            .into_iter()
            .map(|(printer, gate)| Kept::Gate { printer, gate });
        outcomes.chain(gates).collect()
    }

    /// Settles one thing [`Pending::take`] gave with `attempt`: kept again unless written
    /// or dropped, and noted in `done`. Once `done` says the store is unreachable, what is
    /// left is not tried (each would wait out the same failure): it is settled as
    /// [`Attempt::Unreachable`].
    pub(crate) fn settle(&mut self, kept: Kept, attempt: Attempt, done: &mut Written) {
        match (kept, attempt) {
            (Kept::Outcome { id, .. }, Attempt::Written(record)) => {
                tracing::info!(job = %id, "job outcome written after all");
                done.jobs.extend(record.map(|j| *j));
            }
            (Kept::Outcome { id, from, job }, Attempt::Failed) => {
                self.outcomes.insert(id, (from, *job));
            }
            (Kept::Outcome { id, from, job }, Attempt::Unreachable) => {
                done.unreachable = true;
                self.outcomes.insert(id, (from, *job));
            }
            (Kept::Outcome { id, .. }, Attempt::Dropped) => {
                tracing::warn!(job = %id, "a kept outcome was not written: the job was moved on or removed meanwhile");
                done.dropped.push(id);
            }
            (Kept::Gate { printer, .. }, Attempt::Written(_)) => {
                tracing::info!(printer, "bed gate written after all")
            }
            (Kept::Gate { printer, gate }, Attempt::Failed) => {
                self.gates.insert(printer, gate);
            }
            (Kept::Gate { printer, gate }, Attempt::Unreachable) => {
                done.unreachable = true;
                self.gates.insert(printer, gate);
            }
            (Kept::Gate { .. }, Attempt::Dropped) => {}
        }
    }

    /// Tries to write what is kept (outcomes, then gates) with `outcome` and `gate`,
    /// keeping what is not written; see [`Attempt`].
    pub(crate) fn write(
        &mut self,
        mut outcome: impl FnMut(&str, JobState, &Job) -> Attempt,
        mut gate: impl FnMut(&str, &PrinterGate) -> Attempt,
    ) -> Written {
        let mut done = Written::default();
        for kept in self.take() {
            let attempt = match &kept {
                _ if done.unreachable => Attempt::Unreachable,
                Kept::Outcome { id, from, job } => outcome(id, *from, job),
                Kept::Gate { printer, gate: g } => gate(printer, g),
            };
            self.settle(kept, attempt, &mut done);
        }
        done
    }
}

/// One thing kept (see [`Pending::take`]).
#[derive(Debug)]
pub(crate) enum Kept {
    Outcome {
        id: String,
        from: JobState,
        job: Box<Job>,
    },
    Gate {
        printer: String,
        gate: PrinterGate,
    },
}

#[cfg(test)]
mod tests {
    use super::*;

    fn job(seq: u64) -> Job {
        Job::queued(
            Job::make_id(seq, "m.stl"),
            seq,
            "m.stl".into(),
            "/hot".into(),
        )
    }

    /// A failure passes to the next; an unreachable store stops the rest, which stays
    /// kept; a dropped one is forgotten and named for rereading.
    #[test]
    fn kept_outcomes_are_written_dropped_or_kept() {
        let mut pending = Pending::default();
        for seq in 1..=4 {
            pending.keep_outcome(JobState::Printing, job(seq));
        }
        pending.keep_gate(
            "p1",
            PrinterGate {
                bed: crate::daemon::bed::Bed::Waiting { why: None },
                ..Default::default()
            },
        );
        assert_eq!(pending.len(), 5);
        let mut tried = Vec::new();
        let done = pending.write(
            |id, from, _| {
                assert_eq!(from, JobState::Printing);
                tried.push(id.to_string());
                match &id[..4] {
                    "0001" => Attempt::Written(Some(Box::new(job(1)))),
                    "0002" => Attempt::Failed,
                    "0003" => Attempt::Dropped,
                    _ => Attempt::Unreachable,
                }
            },
            |_, _| panic!("not tried once the store is unreachable"),
        );
        assert_eq!(tried.len(), 4);
        assert_eq!(done.jobs.len(), 1);
        assert_eq!(done.dropped, vec![job(3).id]);
        assert!(done.unreachable);
        assert!(pending.has_outcome(&job(2).id) && pending.has_outcome(&job(4).id));
        assert_eq!(pending.len(), 3, "two outcomes and the gate stay");

        let done = pending.write(
            |_, _, _| Attempt::Written(None),
            |_, _| Attempt::Written(None),
        );
        assert!(!done.unreachable);
        assert!(pending.is_empty());
    }

    #[test]
    fn an_outcome_is_checked_against_the_table() {
        let queued = job(1);
        assert!(outcome(&queued, JobState::Done, None, |_| {}).is_err());
        let mut printing = job(2);
        printing.state = JobState::Printing;
        let (from, after) =
            outcome(&printing, JobState::Done, None, |j| j.copies_done = 1).unwrap();
        assert_eq!(
            (from, after.state, after.copies_done),
            (JobState::Printing, JobState::Done, 1)
        );
    }
}
