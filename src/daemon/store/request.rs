//! The requests the store's task serves, each an mpsc message with a oneshot reply, and
//! how each is carried out against the store. Apart from
//! the task's loop (which batches them) and the handle (which sends them).

use super::change::{InventoryChange, JobChange};
use super::clients::for_clients;
use super::history::{self, Retention};
use super::job_store::{JobStore, RetiredJob};
use super::retiring::round;
use super::rules::StateFilter;
use super::snapshot::Snapshot;
use super::stats;
use crate::daemon::bed::{Bed, CheckRecord, Clearing};
use crate::daemon::filament::Inventory;
use crate::daemon::job::{Job, JobState, PrinterGate, StoreError};
use std::path::PathBuf;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Arc;
use tokio::sync::oneshot;

pub(super) type Reply<T> = oneshot::Sender<Result<T, StoreError>>;

/// The messages the store's task serves.
pub(super) enum Request {
    Admit {
        source: PathBuf,
        folder: PathBuf,
        printers: Vec<String>,
        reply: Reply<Job>,
    },
    LateSidecar {
        folder: PathBuf,
        file: String,
        sidecar: PathBuf,
        reply: Reply<Option<LateSidecar>>,
    },
    Transition {
        id: String,
        from: Option<StateFilter>,
        to: JobState,
        reason: Option<String>,
        also: JobChange,
        reply: Reply<Job>,
    },
    Outcome {
        id: String,
        to: JobState,
        reason: Option<String>,
        also: JobChange,
        reply: Reply<Job>,
    },
    Update {
        id: String,
        change: JobChange,
        reply: Reply<Updated>,
    },
    Retry {
        id: String,
        reply: Reply<Job>,
    },
    Claim {
        printer: String,
        eligible: Box<dyn Fn(&Job) -> bool + Send>,
        reply: Reply<Option<Job>>,
    },
    /// A change of a printer's bed, checked against [`Bed::can_go_to`] and its `from`.
    ///
    /// [`Bed::can_go_to`]: crate::daemon::bed::Bed::can_go_to
    Bed {
        printer: String,
        /// Boxed: a check's record is large beside the other requests.
        change: Box<BedChange>,
        reply: Reply<PrinterGate>,
    },
    WritePending {
        reply: Reply<usize>,
    },
    Resync {
        reply: Reply<bool>,
    },
    Retire {
        now: f64,
        reply: Reply<Vec<String>>,
    },
    Retired {
        id: String,
        reply: Reply<Option<RetiredJob>>,
    },
    History {
        before: Option<u64>,
        limit: usize,
        filter: history::Filter,
        reply: Reply<history::Page>,
    },
    EditInventory {
        change: InventoryChange,
        reply: Reply<Inventory>,
    },
    Stats {
        period: stats::Period,
        printers: Vec<String>,
        folders: Vec<String>,
        now: f64,
        reply: Reply<stats::Stats>,
    },
}

/// A change of a printer's bed (see [`Request::Bed`]).
pub(crate) struct BedChange {
    /// The names of the states the bed must be in now ([`Bed::name`]); None: any the
    /// table allows to go to `to`.
    pub from: Option<&'static [&'static str]>,
    pub to: Bed,
    /// A print of this job just ended on it: it becomes the gate's last job.
    pub printed: Option<String>,
    /// The camera's check that led to it, kept as the gate's last.
    pub check: Option<CheckRecord>,
    /// A step of clearing the last job's print, added to that job's record.
    pub record: Option<Clearing>,
}

/// What became of a sidecar that arrived after its model had become a job.
#[derive(Debug, Clone, PartialEq)]
pub(crate) struct LateSidecar {
    pub job: String,
    /// The job's state when the sidecar arrived.
    pub state: JobState,
    /// Taken as the job's sidecar (it had not started preparing); else kept aside.
    pub applies: bool,
}

/// An updated job, and whether the change applied (see [`JobChange::apply`]).
#[derive(Debug)]
pub(crate) struct Updated {
    pub(crate) job: Job,
    pub(crate) applied: bool,
}

/// A typed change as the stores' edit.
fn edit(change: JobChange) -> super::job_store::JobEdit {
    Box::new(move |j| {
        change.apply(j);
    })
}

/// A reply waiting for the snapshot that shows its change to be published.
pub(super) type Delivery = Box<dyn FnOnce() + Send>;

fn deliver<T: Send + 'static>(reply: Reply<T>, result: Result<T, StoreError>) -> Delivery {
    Box::new(move || {
        let _ = reply.send(result);
    })
}

impl Request {
    /// Carries out one request against the store, updating `view` with what changed;
    /// says whether anything may have (a claim that found nothing, a clear of a clear
    /// bed change nothing, and publish nothing: a task waiting for changes is not woken
    /// by its own fruitless request).
    pub(super) async fn serve(
        self,
        store: &mut dyn JobStore,
        view: &mut Snapshot,
        retention: &Retention,
    ) -> (Delivery, bool) {
        match self {
            Request::Admit {
                source,
                folder,
                printers,
                reply,
            } => {
                let result = store.admit(&source, &folder, &printers).await;
                if let Ok(job) = &result {
                    view.refresh(store, &job.id);
                }
                let changed = result.is_ok();
                (deliver(reply, result), changed)
            }
            Request::LateSidecar {
                folder,
                file,
                sidecar,
                reply,
            } => late_sidecar(store, view, folder, file, sidecar, reply).await,
            Request::Transition {
                id,
                from,
                to,
                reason,
                also,
                reply,
            } => {
                let reason = reason.map(|r| for_clients(&r, store));
                let result = store
                    .transition_with(&id, from, to, reason, edit(also))
                    .await;
                view.refresh(store, &id);
                (deliver(reply, result), true)
            }
            Request::Outcome {
                id,
                to,
                reason,
                also,
                reply,
            } => {
                let reason = reason.map(|r| for_clients(&r, store));
                let result = store.record_outcome(&id, to, reason, edit(also)).await;
                view.refresh(store, &id);
                view.unwritten = store.unwritten();
                (deliver(reply, result), true)
            }
            Request::Update { id, change, reply } => {
                // The store's edits return nothing: whether the change applied comes back
                // beside the job.
                let applied = Arc::new(AtomicBool::new(false));
                let flag = Arc::clone(&applied);
                let result = store
                    .update(
                        &id,
                        Box::new(move |j| flag.store(change.apply(j), Ordering::Relaxed)),
                    )
                    .await
                    .map(|job| Updated {
                        job,
                        applied: applied.load(Ordering::Relaxed),
                    });
                view.refresh(store, &id);
                (deliver(reply, result), true)
            }
            Request::Retry { id, reply } => {
                let result = store.retry(&id).await;
                view.refresh(store, &id);
                (deliver(reply, result), true)
            }
            Request::Claim {
                printer,
                eligible,
                reply,
            } => {
                // The order is worked out before the first await: the test of what fits
                // the printer is the caller's and goes no further.
                let candidates = claim_order(view, &*eligible);
                drop(eligible);
                let (result, tried) = claim(store, view, &printer, candidates).await;
                (deliver(reply, result), tried)
            }
            Request::Bed {
                printer,
                change,
                reply,
            } => change_bed(store, view, printer, *change, reply).await,
            Request::Resync { reply } => {
                let changed = store.resync().await;
                if changed {
                    *view = Snapshot::of(store, Some(view));
                }
                (deliver(reply, Ok(changed)), changed)
            }
            Request::Retire { now, reply } => {
                let retired = round(store, view, retention, now).await;
                let changed = retired.as_ref().is_ok_and(|ids| !ids.is_empty());
                (deliver(reply, retired), changed)
            }
            Request::Retired { id, reply } => (deliver(reply, store.retired(&id).await), false),
            Request::EditInventory { change, reply } => {
                let result = store.edit_inventory(&mut |inv| change.apply(inv)).await;
                let changed = result.as_ref().is_ok_and(|i| i != view.inventory());
                if let Ok(inventory) = &result {
                    view.inventory = std::sync::Arc::new(inventory.clone());
                }
                (deliver(reply, result), changed)
            }
            Request::History {
                before,
                limit,
                filter,
                reply,
            } => (
                deliver(reply, store.history(before, limit, &filter).await),
                false,
            ),
            Request::Stats {
                period,
                printers,
                folders,
                now,
                reply,
            } => statistics(store, view, period, printers, folders, now, reply).await,
            Request::WritePending { reply } => {
                let (left, changed) = write_pending(store, view).await;
                (deliver(reply, Ok(left)), changed)
            }
        }
    }
}

/// Writes the outcomes kept while the database was unreachable: how many are left, and
/// whether the view changed. Only the persisted copy changes: the view already shows the
/// outcomes themselves.
pub(super) async fn write_pending(store: &mut dyn JobStore, view: &mut Snapshot) -> (usize, bool) {
    let left = store.write_pending().await;
    let changed = view.unwritten != left;
    view.unwritten = left;
    (left, changed)
}

/// A sidecar that arrived after its model: given to the newest job of that model from
/// `folder`, if any (see [`Request::LateSidecar`]).
async fn late_sidecar(
    store: &mut dyn JobStore,
    view: &mut Snapshot,
    folder: PathBuf,
    file: String,
    sidecar: PathBuf,
    reply: Reply<Option<LateSidecar>>,
) -> (Delivery, bool) {
    let found = view
        .jobs()
        .filter(|j| j.folder == folder && crate::daemon::hotfolder::same_name(&j.file, &file))
        .last()
        .map(|j| (j.id.clone(), j.state));
    let result = match found {
        None => Ok(None),
        Some((id, state)) => store
            .late_sidecar(&id, &sidecar, state == JobState::Queued)
            .await
            .map(|applies| {
                Some(LateSidecar {
                    job: id,
                    state,
                    applies,
                })
            }),
    };
    let changed = !matches!(result, Ok(None));
    (deliver(reply, result), changed)
}

/// Changes `printer`'s bed as `change` says if the table and its `from` allow (see
/// [`Request::Bed`]); the reply is the gate as it was.
async fn change_bed(
    store: &mut dyn JobStore,
    view: &mut Snapshot,
    printer: String,
    change: BedChange,
    reply: Reply<PrinterGate>,
) -> (Delivery, bool) {
    let before = view.gate(&printer);
    let allowed = change.from.is_none_or(|f| f.contains(&before.bed.name()))
        && before.bed.can_go_to(&change.to);
    if !allowed {
        let refused = StoreError::BedChange {
            printer,
            from: before.bed.name(),
            to: change.to.name(),
        };
        return (deliver(reply, Err(refused)), false);
    }
    let gate = PrinterGate {
        bed: change.to,
        last_job: change.printed.clone().or(before.last_job.clone()),
        last_check: change.check.or(before.last_check.clone()),
    };
    if gate == before {
        return (deliver(reply, Ok(before)), false);
    }
    let counted = before.bed.counted(&gate.bed);
    let result = store.set_gate(&printer, gate.clone()).await;
    if result.is_ok() {
        tracing::info!(printer = %printer, bed = gate.bed.name(), reason = gate.bed.describe(), "bed");
        if let Some((kind, outcome)) = counted {
            view.count_bed(&printer, kind, outcome);
        }
        if let (Some(step), Some(job)) = (change.record, &gate.last_job) {
            // The job's record is told, not asked: a job gone to the history keeps its own.
            match store
                .update(job, Box::new(move |j| j.clearing.push(step)))
                .await
            {
                Ok(_) => view.refresh(store, job),
                Err(e) => {
                    tracing::warn!(printer = %printer, job = %job, error = %e, "cannot add the bed's clearing to the job's record")
                }
            }
        }
    }
    view.gates = store.gates();
    view.unwritten = store.unwritten();
    // A change the store could not write is not done (see `JobStore::set_gate`): nothing
    // to publish.
    let changed = result.is_ok();
    (deliver(reply, result.map(|()| before)), changed)
}

/// The statistics of `period` over the history and the live jobs (see [`Request::Stats`]).
async fn statistics(
    store: &mut dyn JobStore,
    view: &Snapshot,
    period: stats::Period,
    printers: Vec<String>,
    folders: Vec<String>,
    now: f64,
    reply: Reply<stats::Stats>,
) -> (Delivery, bool) {
    let mut builder = stats::Builder::new(period, &printers, &folders);
    // A job retired before the period began ended before it too.
    let result = store
        .each_retired(period.from, &mut |r| builder.add(&r))
        .await
        .map(|()| {
            // The live jobs: finished ones not yet retired, and the printing
            // time of those under way.
            for job in view.jobs() {
                if history::is_finished(job.state)
                    || job.history.iter().any(|h| h.0 == JobState::Printing)
                {
                    let dir = view.job_dir(&job.id);
                    builder.add(&history::Retired::of(job, dir, now));
                }
            }
            builder.finish()
        });
    (deliver(reply, result), false)
}

/// The ready jobs `eligible` takes, in the order a printer claims them: higher priority
/// first; the oldest first among equals, a copy as old as the job that asked for it (the
/// jobs are oldest first, and the sort is stable).
fn claim_order(view: &Snapshot, eligible: &dyn Fn(&Job) -> bool) -> Vec<String> {
    let mut candidates: Vec<(i32, u64, String)> = view
        .jobs()
        .filter(|j| j.state == JobState::Ready && eligible(j))
        .map(|j| {
            let asked = view.get(j.group()).map_or(j.seq, |first| first.seq);
            (j.asks.priority, asked, j.id.clone())
        })
        .collect();
    candidates.sort_by_key(|(p, asked, _)| (std::cmp::Reverse(*p), *asked));
    candidates.into_iter().map(|(_, _, id)| id).collect()
}

/// Takes the first of `candidates` (see [`claim_order`]) for `printer`, marking it
/// printing. A job that fails as it is claimed (its directory is gone), or that another
/// host took first, is passed over for the next one. Also says whether any job was tried
/// (and may have changed).
async fn claim(
    store: &mut dyn JobStore,
    view: &mut Snapshot,
    printer: &str,
    candidates: Vec<String>,
) -> (Result<Option<Job>, StoreError>, bool) {
    let tried = !candidates.is_empty();
    for id in candidates {
        let name = printer.to_string();
        let claimed = store
            .transition_with(
                &id,
                Some(&[JobState::Ready]),
                JobState::Printing,
                None,
                Box::new(move |j| j.printer = Some(name)),
            )
            .await;
        view.refresh(store, &id);
        match claimed {
            Ok(job) => return (Ok(Some(job)), tried),
            Err(StoreError::StateChanged { .. } | StoreError::LostClaim { .. }) => continue,
            Err(_) if view.get(&id).is_some_and(|j| j.state == JobState::Failed) => continue,
            Err(e) => return (Err(e), tried),
        }
    }
    (Ok(None), tried)
}
