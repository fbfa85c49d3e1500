//! The rules every store keeps alike (the spool and the farm database): the states a
//! change must find, what a retired job answers to a change, what counts as prepared, and
//! how a store's file error is told. Apart from the store's task and the `JobStore` trait
//! because the history and both stores use them too, and none of those may depend on the
//! task that drives them.

use crate::daemon::job::{ForMachine, Job, JobState, StoreError};
use std::path::Path;

/// What a job must be in for a change to go ahead; checked inside the store's task, so
/// nothing can change the job between the check and the change.
pub(crate) type StateFilter = &'static [JobState];

/// What a change of a retired job meets: the history is not the queue.
pub(crate) fn retired_refusal(id: &str, state: JobState, action: &'static str) -> StoreError {
    StoreError::WrongState {
        id: id.to_string(),
        state,
        action,
        allowed: "still in the queue (it has moved to the history, `crispen history`; drop its model into a hot folder again to print it again)",
    }
}

/// The names of the G-code files preparation made for a job: one per machine, or, for a
/// job prepared before machines existed (sliced for an Ultimaker 2), `<file>.gcode`.
pub(crate) fn gcode_files(job: &Job) -> Vec<String> {
    if job.machines.is_empty() {
        return vec![format!("{}.gcode", job.file)];
    }
    job.machines
        .values()
        .filter_map(|m| match m {
            ForMachine::Gcode(file) => Some(file.clone()),
            ForMachine::Refused(_) => None,
        })
        .collect()
}

/// Whether a job that is retried keeps its G-code (and goes back to ready) or is prepared
/// again: it was prepared, and one of its G-code files is still there (`has`: in its
/// directory, or in the farm database). The one rule of both stores.
pub(crate) fn prepared(job: &Job, has: impl Fn(&str) -> bool) -> bool {
    job.slice_report.is_some() && gcode_files(job).iter().any(|f| has(f))
}

impl From<crate::fsutil::WriteError> for StoreError {
    fn from(e: crate::fsutil::WriteError) -> StoreError {
        StoreError::Io {
            path: e.path,
            action: e.step,
            source: e.source,
        }
    }
}

/// Checks that a job is in one of the states `from` (when given).
pub(crate) fn check_from(job: &Job, from: Option<StateFilter>) -> Result<(), StoreError> {
    match from {
        Some(from) if !from.contains(&job.state) => Err(StoreError::StateChanged {
            id: job.id.clone(),
            state: job.state,
            expected: names(from),
        }),
        _ => Ok(()),
    }
}

fn names(states: StateFilter) -> String {
    let names: Vec<&str> = states.iter().map(|s| s.name()).collect();
    names.join(" or ")
}

/// The error of a file operation of a store on `path`: what was done and why it failed.
pub(super) fn io_err(
    path: &Path,
    action: &'static str,
) -> impl FnOnce(std::io::Error) -> StoreError {
    let path = path.to_path_buf();
    move |source| StoreError::Io {
        path,
        action,
        source,
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The rule both stores use on retry; a job prepared before machines existed keeps its
    /// `<file>.gcode` (the PostgreSQL store took it for unprepared).
    #[test]
    fn what_counts_as_prepared() {
        let mut job = Job::queued("0001-a_stl".into(), 1, "a.stl".into(), "/hot".into());
        let has = |names: &'static [&'static str]| move |n: &str| names.contains(&n);
        assert!(!prepared(&job, has(&["a.stl.gcode"])), "never sliced");
        job.slice_report = Some(Default::default());
        assert!(prepared(&job, has(&["a.stl.gcode"])), "legacy G-code");
        assert!(!prepared(&job, has(&[])));
        job.machines
            .insert("m1".into(), ForMachine::Refused("too big".into()));
        job.machines
            .insert("m2".into(), ForMachine::Gcode("a.stl.m2.gcode".into()));
        assert!(prepared(&job, has(&["a.stl.m2.gcode"])));
        assert!(!prepared(&job, has(&["a.stl.gcode"])), "not this job's now");
    }
}
