//! The store's task, the one owner of the store: it takes the waiting requests in
//! batches, serves them one after another, publishes the new snapshot and then sends the
//! replies; `start` opens it with its handle. Apart from the requests (what each does) and
//! the handle (how callers reach it): this is the loop and its timing.

use super::handle::StoreHandle;
use super::history::{self, Retention};
use super::job_store::JobStore;
use super::request::Request;
use super::retiring::{catch_up_ledgers, retire_beyond_limit, round};
use super::snapshot::Snapshot;
use std::sync::Arc;
use tokio::sync::{mpsc, watch};

/// How often the store's task makes its round ([`round`]): finished jobs older than
/// `live_for` cannot wait on a change to be retired (at once after starting, and again at
/// once while a batch was full). Jobs beyond `live_jobs` do not wait for it.
const RETIRE_EVERY: std::time::Duration = std::time::Duration::from_secs(600);

/// How often the store's task tries again to write the outcomes kept while the farm
/// database was unreachable (only while some are).
pub(super) const WRITE_PENDING_EVERY: std::time::Duration = std::time::Duration::from_secs(5);

/// The store's task, to be run in the daemon's supervised set: it ends only when the
/// last handle is dropped, and a panic (in the store, or in a request's edit) is the
/// task's, so the daemon stops rather than go on with a change done halfway.
pub type StoreTask = std::pin::Pin<Box<dyn std::future::Future<Output = ()> + Send>>;

/// Opens the store's task with finished jobs kept live as `retention` says: its handle,
/// and the task itself for the caller to run (the service, in its supervised set).
pub fn start(store: impl JobStore, retention: Retention) -> (StoreHandle, StoreTask) {
    let store: Box<dyn JobStore> = Box::new(store);
    let view = Snapshot::of(&*store, None);
    let (snapshots, snapshot) = watch::channel(Arc::new(view.clone()));
    let (tx, rx) = mpsc::channel(256);
    let task = Box::pin(serve(store, view, rx, snapshots, retention));
    (StoreHandle { tx, snapshot }, task)
}

/// [`start`] with the default [`Retention`], its task spawned on the current runtime
/// unsupervised: for tests and tools, not the daemon.
pub fn spawn(store: impl JobStore) -> StoreHandle {
    spawn_with(store, Retention::default())
}

/// [`spawn`] with finished jobs kept live as `retention` says.
pub fn spawn_with(store: impl JobStore, retention: Retention) -> StoreHandle {
    let (handle, task) = start(store, retention);
    tokio::spawn(task);
    handle
}

/// What the store's task does next.
enum Work {
    Requests(Vec<Request>),
    Retire,
    WritePending,
}

/// The store's task: takes whatever requests are waiting, serves them in order (each
/// store keeps its own blocking work off the runtime), retires finished jobs beyond
/// `live_jobs`, publishes the new snapshot, then sends the replies. Every [`RETIRE_EVERY`] it makes its [`round`] the
/// same way, and every [`WRITE_PENDING_EVERY`] while outcomes wait to be written, it
/// tries them (one try at a time, as everything here).
async fn serve(
    mut store: Box<dyn JobStore>,
    mut view: Snapshot,
    mut requests: mpsc::Receiver<Request>,
    snapshots: watch::Sender<Arc<Snapshot>>,
    retention: Retention,
) {
    const BATCH: usize = 64;
    let mut retiring = tokio::time::interval(RETIRE_EVERY);
    retiring.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Delay);
    let mut writing = tokio::time::interval(WRITE_PENDING_EVERY);
    writing.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Delay);
    // The first snapshot, made as the task was opened, has not looked at the jobs'
    // pictures (that is disk work): it is published again once they are known.
    if view.look().await {
        snapshots.send_replace(Arc::new(view.clone()));
    }
    loop {
        let work = tokio::select! {
            // Requests first: retiring can always wait a little.
            biased;
            first = requests.recv() => {
                let Some(first) = first else { break };
                let mut batch = vec![first];
                while batch.len() < BATCH {
                    match requests.try_recv() {
                        Ok(r) => batch.push(r),
                        Err(_) => break,
                    }
                }
                Work::Requests(batch)
            }
            _ = retiring.tick() => Work::Retire,
            _ = writing.tick(), if view.unwritten > 0 => Work::WritePending,
        };
        let mut deliveries = Vec::new();
        let (mut changed, mut full) = (false, false);
        match work {
            Work::Requests(batch) => {
                // A panic here (in the store, or in a request's edit) is not caught: the
                // change it left halfway is unknown, so the task ends with it and the
                // daemon stops; every reply not sent yet says `Stopped`.
                for request in batch {
                    let (delivery, change) =
                        request.serve(&mut *store, &mut view, &retention).await;
                    deliveries.push(delivery);
                    changed |= change;
                }
                changed |= super::copies::tend(&mut *store, &mut view).await;
                changed |= catch_up_ledgers(&mut *store, &mut view)
                    .await
                    .unwrap_or(false);
                changed |= retire_beyond_limit(&mut *store, &mut view, &retention).await;
            }
            Work::WritePending => {
                changed = super::request::write_pending(&mut *store, &mut view)
                    .await
                    .1
            }
            Work::Retire => {
                changed |= super::copies::tend(&mut *store, &mut view).await;
                let now = crate::daemon::job::now_s();
                match round(&mut *store, &mut view, &retention, now).await {
                    Ok(ids) => {
                        changed |= !ids.is_empty();
                        full = ids.len() >= history::BATCH;
                    }
                    Err(e) => {
                        tracing::error!(error = %e, "cannot move finished jobs to the history; they stay live and it is tried again later")
                    }
                }
            }
        }
        // What the changed jobs' directories hold, before anyone reads the change.
        view.look().await;
        if full {
            retiring.reset_immediately();
        }
        // A batch that changed nothing wakes no follower.
        if changed {
            view.version += 1;
            snapshots.send_replace(Arc::new(view.clone()));
        }
        for delivery in deliveries {
            delivery();
        }
    }
}
