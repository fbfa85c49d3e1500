//! Moving finished jobs out of the live snapshot to the history: at a change that left
//! too many live, and in the task's periodic round. Apart because both a request (an
//! operator's `retire`) and the task's own timer make the round. Before any job leaves,
//! the spools' ledgers and the printers' care counts take the uses the live jobs recorded
//! ([`catch_up_ledgers`]).

use super::history::Retention;
use super::job_store::JobStore;
use super::snapshot::Snapshot;
use crate::daemon::care;
use crate::daemon::filament::routing::abrasive;
use crate::daemon::job::{JobUse, StoreError};
use std::collections::HashSet;

/// Moves what `retention` no longer keeps live to the history and out of the snapshot,
/// one batch.
async fn retire(
    store: &mut dyn JobStore,
    view: &mut Snapshot,
    retention: &Retention,
    now: f64,
) -> Result<Vec<String>, StoreError> {
    if catch_up_ledgers(store, view).await.is_err() {
        return Ok(Vec::new());
    }
    let ids = store.retire(retention, now).await?;
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
pub(super) async fn round(
    store: &mut dyn JobStore,
    view: &mut Snapshot,
    retention: &Retention,
    now: f64,
) -> Result<Vec<String>, StoreError> {
    let ids = retire(store, view, retention, now).await?;
    if let Some(keep_for) = retention.keep_for {
        match store.prune(keep_for, now).await {
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
pub(super) async fn retire_beyond_limit(
    store: &mut dyn JobStore,
    view: &mut Snapshot,
    retention: &Retention,
) -> bool {
    let mut moved = false;
    while view.finished_live() > retention.live_jobs {
        match retire(store, view, retention, crate::daemon::job::now_s()).await {
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

/// The job of a use's key (`<job>#<n>`).
fn job_of(key: &str) -> &str {
    key.rsplit_once('#').map_or(key, |(j, _)| j)
}

/// How long a counted print's key is kept once its job is no longer live here: longer
/// than any host of a shared farm can lag behind another in seeing a job (so none counts a
/// print again that another counted and then retired).
const COUNTED_KEPT_S: f64 = 86_400.0;

/// How often the counted keys of live jobs are marked seen, at the latest (see
/// `care::refresh`): a job live for weeks is still kept a day from when it left.
const COUNTED_REFRESH_S: f64 = 3600.0;

/// Brings the spools' ledgers and the printers' care counts up to date with the uses the
/// live jobs recorded with their outcomes (a use is in the job's record first, in the same
/// write as the outcome; here it reaches its spool and its printer's counts, once: both are
/// keyed by the use). Says whether anything changed. A failure (the disk, the database) is
/// logged and tried again at the next change; until it succeeds no finished job leaves the
/// live view (its use would leave with it).
pub(super) async fn catch_up_ledgers(
    store: &mut dyn JobStore,
    view: &mut Snapshot,
) -> Result<bool, ()> {
    let inventory = view.inventory();
    let uncounted = |u: &JobUse| {
        inventory
            .care
            .get(&u.printer)
            .is_none_or(|c| !c.counted.contains_key(&u.key))
    };
    let off_ledger = |u: &JobUse| {
        u.spool
            .as_ref()
            .and_then(|s| inventory.spools.get(s))
            .is_some_and(|s| !s.uses.contains_key(&u.key))
    };
    let missing: Vec<JobUse> = view
        .jobs()
        .flat_map(|j| j.uses.iter())
        .filter(|u| off_ledger(u) || uncounted(u))
        .cloned()
        .collect();
    let live_jobs: HashSet<&str> = view.jobs().map(|j| j.id.as_str()).collect();
    let live = |key: &str| live_jobs.contains(job_of(key));
    let now = crate::daemon::job::now_s();
    if missing.is_empty() && !care::stale(&inventory.care, live, now, COUNTED_REFRESH_S) {
        return Ok(false);
    }
    let result = store
        .edit_inventory(&mut |inv| {
            for u in &missing {
                let print = care::Print {
                    print_s: u.print_s,
                    failed: u.failed,
                    material: &u.material,
                    mm: u.mm,
                    g: if u.weighed() { u.grams } else { 0.0 },
                    abrasive: u.weighed() && abrasive(&u.material),
                };
                care::count(&mut inv.care, &u.printer, &u.key, u.at_s, print);
                let Some(spool) = &u.spool else { continue };
                inv.record_use(
                    spool,
                    &u.key,
                    crate::daemon::filament::Use {
                        job: job_of(&u.key).to_string(),
                        printer: u.printer.clone(),
                        grams: u.grams,
                        mm: u.mm,
                        at_s: u.at_s,
                        report: crate::daemon::filament::Report::Local,
                    },
                );
            }
            care::refresh(&mut inv.care, live, now, COUNTED_KEPT_S);
            Ok(())
        })
        .await;
    match result {
        Ok(inventory) => {
            view.inventory = std::sync::Arc::new(inventory);
            Ok(true)
        }
        Err(e) => {
            tracing::error!(error = %e, "cannot record the prints' filament on their spools and printers; tried again at the next change");
            Err(())
        }
    }
}
