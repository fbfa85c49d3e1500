//! What a store is: the [`JobStore`] trait the store's task drives (the spool, the farm
//! database), the edit a change carries, and a retired job as the history gives it back.
//! Apart from the task so each store implements it without depending on the task that
//! calls it.

use super::history::{self, Retention};
use super::rules::StateFilter;
use crate::daemon::filament::Inventory;
use crate::daemon::job::{Job, JobState, PrinterGate, StoreError};
use serde::{Deserialize, Serialize};
use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

/// A change to a job's other fields, made in the same write as its state change.
pub(crate) type JobEdit = Box<dyn FnOnce(&mut Job) + Send>;

/// A change to the inventory; may be applied more than once (a shared store applies it
/// again to a newer inventory), so it must not count on its first attempt's result.
pub(crate) type InventoryEdit<'a> =
    dyn FnMut(&mut Inventory) -> Result<(), crate::daemon::filament::FilamentError> + Send + 'a;

/// Where jobs are kept. The store's task calls it, one call at a time. What reads the
/// store's memory only is a plain method; what reaches its disk or its database is async,
/// and each store keeps its blocking work off the runtime's threads (the spool's on a
/// blocking thread, the farm database's over its async client). Opening (and taking
/// whatever lock keeps two daemons apart) is each implementation's own constructor.
#[async_trait::async_trait]
pub trait JobStore: Send + 'static {
    /// The local directory holding one directory per job (model, sidecar, G-code, report).
    fn jobs_dir(&self) -> PathBuf;
    /// Every job, oldest first.
    fn jobs(&self) -> Vec<Job>;
    fn job(&self, id: &str) -> Option<Job>;
    fn gates(&self) -> BTreeMap<String, PrinterGate>;
    /// The farm's spools and which printer holds which.
    fn inventory(&self) -> Inventory;
    /// Changes the inventory by `edit` and persists it; a refused edit changes nothing.
    /// Farm-wide in a shared store: the edit applies to the inventory as the database
    /// holds it, under a lock, so hosts' changes never overwrite each other.
    async fn edit_inventory(
        &mut self,
        edit: &mut InventoryEdit<'_>,
    ) -> Result<Inventory, StoreError>;
    /// Restart rules: preparing → queued, printing → interrupted (and its bed not cleared).
    /// Returns the ids changed.
    async fn recover(&mut self) -> Result<Vec<String>, StoreError>;
    /// Makes a complete file of a hot folder a queued job, or leaves it where it was.
    /// `printers` is the folder's rule, for stores whose other hosts lack the folder.
    async fn admit(
        &mut self,
        source: &Path,
        folder: &Path,
        printers: &[String],
    ) -> Result<Job, StoreError>;
    /// Takes a sidecar that arrived after its model: as the job's sidecar when `applies`,
    /// else kept aside. Returns `applies`.
    async fn late_sidecar(
        &mut self,
        id: &str,
        sidecar: &Path,
        applies: bool,
    ) -> Result<bool, StoreError>;
    /// Changes a job's state (checked against the table, and first against `from`, the
    /// states it must be in now) with `also`'s changes, persisted.
    async fn transition_with(
        &mut self,
        id: &str,
        from: Option<StateFilter>,
        state: JobState,
        reason: Option<String>,
        also: JobEdit,
    ) -> Result<Job, StoreError>;
    /// A state change that has already happened (a print ended): kept even when it cannot
    /// be persisted now, and persisted by [`JobStore::write_pending`] later.
    async fn record_outcome(
        &mut self,
        id: &str,
        state: JobState,
        reason: Option<String>,
        also: JobEdit,
    ) -> Result<Job, StoreError>;
    /// Makes the copies due of job `id` ([`Job::copies_due`]), each a ready job with the
    /// job's G-code, and marks them made, all or nothing: copies are made once whichever
    /// host sees the job first. Returns the copies' ids (none when none were due).
    async fn make_copies(&mut self, id: &str) -> Result<Vec<String>, StoreError>;
    /// Changes a job's other fields; never its state.
    async fn update(&mut self, id: &str, change: JobEdit) -> Result<Job, StoreError>;
    /// Puts a failed, cancelled or interrupted job back (ready if its G-code is kept).
    async fn retry(&mut self, id: &str) -> Result<Job, StoreError>;
    /// Sets a printer's bed gate. When it cannot be persisted now (a full disk, an
    /// outage), a closed gate (a print ended) is kept and persisted by
    /// [`JobStore::write_pending`], so the bed still needs clearing afterwards; a clear is
    /// not done (the gate stays as it was) and is an error.
    async fn set_gate(&mut self, printer: &str, gate: PrinterGate) -> Result<(), StoreError>;
    /// Persists what [`JobStore::record_outcome`] and [`JobStore::set_gate`] could not;
    /// returns how many remain.
    async fn write_pending(&mut self) -> usize;
    /// How many recorded outcomes (and bed gates) wait to be persisted.
    fn unwritten(&self) -> usize;
    /// Takes in changes made elsewhere (other hosts of a shared store); true when it did,
    /// so the snapshot must be rebuilt. A store only this daemon changes has none.
    async fn resync(&mut self) -> bool {
        false
    }
    /// Moves the finished jobs `retention` no longer keeps live (by
    /// [`history::to_retire`]) to the history; returns their ids, at most
    /// [`history::BATCH`]. `now`: seconds since the epoch.
    async fn retire(&mut self, retention: &Retention, now: f64) -> Result<Vec<String>, StoreError>;
    /// A job in the history; None when there is no such retired job.
    async fn retired(&mut self, id: &str) -> Result<Option<RetiredJob>, StoreError>;
    /// A page of the history, newest first, of jobs with a sequence number below `before`
    /// that `filter` takes.
    async fn history(
        &mut self,
        before: Option<u64>,
        limit: usize,
        filter: &history::Filter,
    ) -> Result<history::Page, StoreError>;
    /// Forgets the jobs the history has kept longer than `keep_for` before `now` (their
    /// records and files); returns how many. See [`Retention::keep_for`].
    async fn prune(&mut self, keep_for: std::time::Duration, now: f64)
        -> Result<usize, StoreError>;
    /// Every job retired at or after `since` (seconds since the epoch), in no particular
    /// order; a job may come twice (the statistics count it once).
    async fn each_retired(
        &mut self,
        since: f64,
        visit: &mut (dyn FnMut(history::Retired) + Send),
    ) -> Result<(), StoreError>;
}

/// A job in the history: its record, and its whole state where it can still be read.
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct RetiredJob {
    pub record: history::Retired,
    pub job: Option<Job>,
}
