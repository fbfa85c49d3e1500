//! Moving finished jobs out of the live snapshot to the history: at a change that left
//! too many live, and in the task's periodic round. Apart because both a request (an
//! operator's `retire`) and the task's own timer make the round.

use super::history::Retention;
use super::job_store::JobStore;
use super::snapshot::Snapshot;
use crate::daemon::job::StoreError;

/// Moves what `retention` no longer keeps live to the history and out of the snapshot,
/// one batch.
fn retire(
    store: &mut dyn JobStore,
    view: &mut Snapshot,
    retention: &Retention,
    now: f64,
) -> Result<Vec<String>, StoreError> {
    let ids = store.retire(retention, now)?;
    if !ids.is_empty() {
        tracing::info!(jobs = ids.len(), first = %ids[0], "finished jobs moved to the history");
    }
    view.remove(&ids);
    Ok(ids)
}

/// The periodic round: retires what has been live longer than `live_for` (and anything
/// else [`history::to_retire`] picks), and forgets what the history keeps no longer.
///
/// [`history::to_retire`]: super::history::to_retire
pub(super) fn round(
    store: &mut dyn JobStore,
    view: &mut Snapshot,
    retention: &Retention,
    now: f64,
) -> Result<Vec<String>, StoreError> {
    let ids = retire(store, view, retention, now)?;
    if let Some(keep_for) = retention.keep_for {
        match store.prune(keep_for, now) {
            Ok(0) => {}
            Ok(n) => tracing::info!(jobs = n, "jobs older than [history] keep_days forgotten"),
            Err(e) => {
                tracing::error!(error = %e, "cannot forget the history's old jobs; tried again later")
            }
        }
    }
    Ok(ids)
}

/// Retires the oldest finished jobs beyond `live_jobs` as soon as a batch of requests
/// leaves more than that live, so a burst of finished jobs never makes every reader pay
/// for all of them until the next round. Says whether any moved.
pub(super) fn retire_beyond_limit(
    store: &mut dyn JobStore,
    view: &mut Snapshot,
    retention: &Retention,
) -> bool {
    let mut moved = false;
    while view.finished_live() > retention.live_jobs {
        match retire(store, view, retention, crate::daemon::job::now_s()) {
            Ok(ids) if !ids.is_empty() => moved = true,
            // What is left must stay for now (an outcome not yet written).
            Ok(_) => break,
            Err(e) => {
                tracing::error!(error = %e, "cannot move finished jobs beyond [history] live_jobs to the history; they stay live and it is tried again at the next change");
                break;
            }
        }
    }
    moved
}
