//! The way to the store's task: a cheap, cloneable [`StoreHandle`] that reads the
//! published snapshot for free and sends every change as a request. Apart from the task so
//! what callers see (one method per request) is one file.

use super::change::{InventoryChange, JobChange};
use super::history;
use super::job_store::RetiredJob;
use super::request::{BedChange, LateSidecar, Reply, Request, Updated};
use super::rules::StateFilter;
use super::snapshot::Snapshot;
use super::stats;
use crate::daemon::filament::Inventory;
use crate::daemon::job::{Job, JobState, PrinterGate, StoreError};
use std::path::Path;
use std::sync::Arc;
use tokio::sync::{mpsc, oneshot, watch};

/// A cheap, cloneable way to the store's task.
#[derive(Clone)]
pub struct StoreHandle {
    pub(super) tx: mpsc::Sender<Request>,
    pub(super) snapshot: watch::Receiver<Arc<Snapshot>>,
}

impl StoreHandle {
    /// The jobs and gates as of the last change; no round trip.
    pub fn snapshot(&self) -> Arc<Snapshot> {
        self.snapshot.borrow().clone()
    }

    /// Follows the snapshot: `changed()` resolves once a change after this call is
    /// published (the way tasks wait for jobs and bed gates).
    pub(crate) fn subscribe(&self) -> watch::Receiver<Arc<Snapshot>> {
        let mut follower = self.snapshot.clone();
        follower.mark_unchanged();
        follower
    }

    async fn ask<T>(&self, request: impl FnOnce(Reply<T>) -> Request) -> Result<T, StoreError> {
        let (reply, answer) = oneshot::channel();
        self.tx
            .send(request(reply))
            .await
            .map_err(|_| StoreError::Stopped)?;
        answer.await.map_err(|_| StoreError::Stopped)?
    }

    pub async fn admit(
        &self,
        source: &Path,
        folder: &Path,
        printers: &[String],
    ) -> Result<Job, StoreError> {
        let (source, folder) = (source.to_path_buf(), folder.to_path_buf());
        let printers = printers.to_vec();
        self.ask(|reply| Request::Admit {
            source,
            folder,
            printers,
            reply,
        })
        .await
    }

    /// Gives a sidecar that arrived late to the newest job of its model `file` from
    /// `folder`; `None` when there is no such job (yet).
    pub(crate) async fn late_sidecar(
        &self,
        folder: &Path,
        file: &str,
        sidecar: &Path,
    ) -> Result<Option<LateSidecar>, StoreError> {
        let (folder, file, sidecar) = (folder.to_path_buf(), file.to_string(), sidecar.into());
        self.ask(|reply| Request::LateSidecar {
            folder,
            file,
            sidecar,
            reply,
        })
        .await
    }

    pub async fn transition(
        &self,
        id: &str,
        state: JobState,
        reason: Option<String>,
    ) -> Result<Job, StoreError> {
        self.change(id, None, state, reason, JobChange::Nothing)
            .await
    }

    /// [`StoreHandle::transition`] with other fields changed in the same write.
    #[cfg(test)]
    pub(crate) async fn transition_with(
        &self,
        id: &str,
        state: JobState,
        reason: Option<String>,
        also: JobChange,
    ) -> Result<Job, StoreError> {
        self.change(id, None, state, reason, also).await
    }

    /// [`StoreHandle::transition`] with other fields changed in the same write (`also`),
    /// only if the job is in one of the states `from` (else [`StoreError::StateChanged`]),
    /// checked and changed as one step.
    pub async fn transition_from(
        &self,
        id: &str,
        from: StateFilter,
        state: JobState,
        reason: Option<String>,
        also: JobChange,
    ) -> Result<Job, StoreError> {
        self.change(id, Some(from), state, reason, also).await
    }

    async fn change(
        &self,
        id: &str,
        from: Option<StateFilter>,
        to: JobState,
        reason: Option<String>,
        also: JobChange,
    ) -> Result<Job, StoreError> {
        let id = id.to_string();
        self.ask(|reply| Request::Transition {
            id,
            from,
            to,
            reason,
            also,
            reply,
        })
        .await
    }

    /// See [`JobStore::record_outcome`].
    ///
    /// [`JobStore::record_outcome`]: super::job_store::JobStore::record_outcome
    pub async fn record_outcome(
        &self,
        id: &str,
        state: JobState,
        reason: Option<String>,
        also: JobChange,
    ) -> Result<Job, StoreError> {
        let id = id.to_string();
        self.ask(|reply| Request::Outcome {
            id,
            to: state,
            reason,
            also,
            reply,
        })
        .await
    }

    /// Changes a job's fields as `change` says, checked and changed as one step.
    pub(crate) async fn update(&self, id: &str, change: JobChange) -> Result<Updated, StoreError> {
        let id = id.to_string();
        self.ask(|reply| Request::Update { id, change, reply })
            .await
    }

    pub async fn retry(&self, id: &str) -> Result<Job, StoreError> {
        let id = id.to_string();
        self.ask(|reply| Request::Retry { id, reply }).await
    }

    /// Takes the oldest ready job that `eligible` allows for `printer`, marking it
    /// printing by that printer, as one step: two printers never take the same job.
    pub async fn claim(
        &self,
        printer: &str,
        eligible: impl Fn(&Job) -> bool + Send + 'static,
    ) -> Result<Option<Job>, StoreError> {
        let (printer, eligible) = (printer.to_string(), Box::new(eligible));
        self.ask(|reply| Request::Claim {
            printer,
            eligible,
            reply,
        })
        .await
    }

    /// Changes a printer's bed (see [`BedChange`]), checked against the bed's table of
    /// legal changes in the same step; returns the gate as it was.
    pub(crate) async fn change_bed(
        &self,
        printer: &str,
        change: BedChange,
    ) -> Result<PrinterGate, StoreError> {
        let printer = printer.to_string();
        self.ask(|reply| Request::Bed {
            printer,
            change: Box::new(change),
            reply,
        })
        .await
    }

    /// The gate after a print of `job` on `printer`: its bed waits for a person (what a
    /// print that did not end well leaves; the printers' supervisors decide the rest, see
    /// `daemon::printer`).
    pub async fn close_gate(&self, printer: &str, job: &str) -> Result<(), StoreError> {
        let change = BedChange {
            from: None,
            to: crate::daemon::bed::Bed::Waiting { why: None },
            printed: Some(job.to_string()),
            check: None,
            record: None,
        };
        self.change_bed(printer, change).await.map(|_| ())
    }

    /// A person says the printer's bed is clear; false when it was clear already.
    pub(crate) async fn clear_gate(&self, printer: &str) -> Result<bool, StoreError> {
        let change = BedChange {
            from: None,
            to: crate::daemon::bed::Bed::Clear {
                by: crate::daemon::bed::ClearedBy::Person,
                at_s: crate::daemon::job::now_s(),
            },
            printed: None,
            check: None,
            record: None,
        };
        self.change_bed(printer, change)
            .await
            .map(|before| before.bed_not_cleared())
    }

    /// Persists outcomes that could not be written before; returns how many remain.
    pub async fn write_pending(&self) -> Result<usize, StoreError> {
        self.ask(|reply| Request::WritePending { reply }).await
    }

    /// Takes in what other hosts changed (see [`JobStore::resync`]); true when anything had.
    ///
    /// [`JobStore::resync`]: super::job_store::JobStore::resync
    pub async fn resync(&self) -> Result<bool, StoreError> {
        self.ask(|reply| Request::Resync { reply }).await
    }

    /// Moves the finished jobs the retention no longer keeps live to the history now, as
    /// of `now` (seconds since the epoch), one batch; the task also does this on its own.
    pub async fn retire(&self, now: f64) -> Result<Vec<String>, StoreError> {
        self.ask(|reply| Request::Retire { now, reply }).await
    }

    /// A job that has moved to the history (None: no such retired job).
    pub async fn retired(&self, id: &str) -> Result<Option<RetiredJob>, StoreError> {
        let id = id.to_string();
        self.ask(|reply| Request::Retired { id, reply }).await
    }

    /// A page of the history, newest first: jobs below sequence number `before`, at most
    /// `limit` (bounded by [`history::PAGE_LIMIT`]).
    pub async fn history(
        &self,
        before: Option<u64>,
        limit: usize,
    ) -> Result<history::Page, StoreError> {
        self.history_where(before, limit, history::Filter::default())
            .await
    }

    /// [`StoreHandle::history`] of the jobs `filter` takes.
    pub async fn history_where(
        &self,
        before: Option<u64>,
        limit: usize,
        filter: history::Filter,
    ) -> Result<history::Page, StoreError> {
        let limit = limit.clamp(*history::PAGE_LIMIT.start(), *history::PAGE_LIMIT.end());
        self.ask(|reply| Request::History {
            before,
            limit,
            filter,
            reply,
        })
        .await
    }

    /// The statistics of `period` over the history and the live jobs (see [`stats`]);
    /// `printers` and `folders` are listed even when they did nothing.
    /// Changes the farm's spools or a printer's care (see
    /// [`JobStore::edit_inventory`](super::job_store::JobStore::edit_inventory)); the
    /// inventory as written.
    pub async fn edit_inventory(&self, change: InventoryChange) -> Result<Inventory, StoreError> {
        self.ask(|reply| Request::EditInventory { change, reply })
            .await
    }

    pub async fn stats(
        &self,
        period: stats::Period,
        printers: Vec<String>,
        folders: Vec<String>,
        now: f64,
    ) -> Result<stats::Stats, StoreError> {
        self.ask(|reply| Request::Stats {
            period,
            printers,
            folders,
            now,
            reply,
        })
        .await
    }
}
