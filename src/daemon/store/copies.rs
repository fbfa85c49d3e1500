//! Copies at once: a job whose sidecar asks for `copies = N` prints as N jobs, itself and
//! N−1 copies made when it is ready ([`Job::copies_due`](crate::daemon::job::Job::copies_due)),
//! each claimed, printed, booked and retried on its own, so as many fitting printers as
//! are free print them at the same time. The store's task makes the copies due after each
//! batch of changes and at each round (a job made ready by a run or a host that stopped
//! before its copies were made gets them then), and gives the copies their first job's
//! wall comparison once it is made (the same G-code, measured once).

use super::job_store::JobStore;
use super::snapshot::Snapshot;

/// Makes the copies due of every job in `view`, and shares the wall comparisons made;
/// whether anything changed. A job whose copies cannot be made now (a full disk, the
/// database away) keeps them due and is tried again after the next change.
pub(super) async fn tend(store: &mut dyn JobStore, view: &mut Snapshot) -> bool {
    let due: Vec<String> = view
        .jobs()
        .filter(|j| !j.copies_due().is_empty())
        .map(|j| j.id.clone())
        .collect();
    let mut changed = false;
    for id in due {
        match store.make_copies(&id).await {
            Ok(made) => {
                if !made.is_empty() {
                    tracing::info!(job = %id, copies = made.len(), "copies made, each printed on its own");
                }
                for copy in &made {
                    view.refresh(store, copy);
                }
                view.refresh(store, &id);
                changed = true;
            }
            Err(e) => {
                tracing::error!(job = %id, error = %e, "cannot make the job's copies now; tried again after the next change")
            }
        }
    }
    changed | share_comparisons(store, view).await
}

/// Gives each copy whose wall comparison waits the first job's, once that is made: its
/// comparison and its slicing report (the figures of the same G-code).
async fn share_comparisons(store: &mut dyn JobStore, view: &mut Snapshot) -> bool {
    use crate::daemon::job::Comparison;
    let waiting: Vec<(String, Comparison, Option<crate::slice::SliceReport>)> = view
        .jobs()
        .filter(|j| matches!(j.comparison, Some(Comparison::Pending { .. })))
        .filter_map(|j| {
            let first = view.get(&j.copy.as_ref()?.job)?;
            let made = first
                .comparison
                .clone()
                .filter(|c| !matches!(c, Comparison::Pending { .. }))?;
            Some((j.id.clone(), made, first.slice_report.clone()))
        })
        .collect();
    let mut changed = false;
    for (id, comparison, report) in waiting {
        let shared = store
            .update(
                &id,
                Box::new(move |j| {
                    j.comparison = Some(comparison);
                    j.slice_report = report;
                }),
            )
            .await;
        match shared {
            Ok(_) => {
                view.refresh(store, &id);
                changed = true;
            }
            Err(e) => {
                tracing::warn!(job = %id, error = %e, "cannot give the copy its first job's wall comparison now; tried again after the next change")
            }
        }
    }
    changed
}
