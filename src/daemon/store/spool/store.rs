//! The spool as the store's task drives it ([`JobStore`]): what it holds in memory is read
//! in place, and every call that touches its disk runs on a blocking thread, the spool
//! moved there and back. The task makes one call at a time, so nothing else needs the
//! spool meanwhile, and no lock is taken.

use super::super::history::{self, HistoryFiles, Retention, Retired};
use super::super::{blocking, InventoryEdit, JobEdit, JobStore, RetiredJob, StateFilter};
use super::Spool;
use crate::daemon::filament::Inventory;
use crate::daemon::job::{Job, JobState, PrinterGate, StoreError};
use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

/// The embedded store: a [`Spool`] whose disk work is kept off the runtime.
pub(crate) struct SpoolStore {
    /// Away only during a call, on its blocking thread.
    spool: Option<Box<Spool>>,
}

impl From<Spool> for SpoolStore {
    fn from(spool: Spool) -> SpoolStore {
        SpoolStore {
            spool: Some(Box::new(spool)),
        }
    }
}

impl SpoolStore {
    /// Opens the spool at `root` (blocking: for tests, whose stores are small).
    #[cfg(test)]
    pub(crate) fn open(root: &Path) -> Result<SpoolStore, StoreError> {
        Spool::open(root).map(SpoolStore::from)
    }

    fn spool(&self) -> &Spool {
        // Only a call whose future was dropped halfway (the task itself ending) leaves it
        // away, and nothing calls the store after that.
        self.spool
            .as_deref()
            .expect("the spool is back after each call")
    }

    /// Runs `work` on the spool on a blocking thread.
    async fn on_disk<T: Send + 'static>(
        &mut self,
        work: impl FnOnce(&mut Spool) -> T + Send + 'static,
    ) -> T {
        let mut spool = self
            .spool
            .take()
            .expect("the spool is back after each call");
        let (spool, out) = blocking(move || {
            let out = work(&mut spool);
            (spool, out)
        })
        .await;
        self.spool = Some(spool);
        out
    }
}

#[async_trait::async_trait]
impl JobStore for SpoolStore {
    fn jobs_dir(&self) -> PathBuf {
        self.spool().jobs_dir()
    }
    fn jobs(&self) -> Vec<Job> {
        self.spool().jobs().cloned().collect()
    }
    fn job(&self, id: &str) -> Option<Job> {
        self.spool().get(id).cloned()
    }
    fn gates(&self) -> BTreeMap<String, PrinterGate> {
        self.spool().gates.clone()
    }
    fn inventory(&self) -> Inventory {
        self.spool().inventory.clone()
    }
    async fn edit_inventory(
        &mut self,
        edit: &mut InventoryEdit<'_>,
    ) -> Result<Inventory, StoreError> {
        // The edit borrows its caller's state: applied here, only the write goes away.
        let mut changed = self.spool().inventory.clone();
        edit(&mut changed)?;
        self.on_disk(move |s| s.set_inventory(changed)).await
    }
    async fn recover(&mut self) -> Result<Vec<String>, StoreError> {
        self.on_disk(Spool::recover).await
    }
    async fn make_copies(&mut self, id: &str) -> Result<Vec<String>, StoreError> {
        let id = id.to_string();
        self.on_disk(move |s| s.make_copies(&id)).await
    }
    async fn admit(
        &mut self,
        source: &Path,
        folder: &Path,
        _printers: &[String],
    ) -> Result<Job, StoreError> {
        let (source, folder) = (source.to_path_buf(), folder.to_path_buf());
        self.on_disk(move |s| s.admit(&source, &folder)).await
    }
    async fn late_sidecar(
        &mut self,
        id: &str,
        sidecar: &Path,
        applies: bool,
    ) -> Result<bool, StoreError> {
        let (id, sidecar) = (id.to_string(), sidecar.to_path_buf());
        self.on_disk(move |s| s.late_sidecar(&id, &sidecar, applies))
            .await
    }
    async fn transition_with(
        &mut self,
        id: &str,
        from: Option<StateFilter>,
        state: JobState,
        reason: Option<String>,
        also: JobEdit,
    ) -> Result<Job, StoreError> {
        let id = id.to_string();
        self.on_disk(move |s| s.transition_from(&id, from, state, reason, also))
            .await
    }
    async fn record_outcome(
        &mut self,
        id: &str,
        state: JobState,
        reason: Option<String>,
        also: JobEdit,
    ) -> Result<Job, StoreError> {
        let id = id.to_string();
        self.on_disk(move |s| s.record_outcome(&id, state, reason, also))
            .await
    }
    async fn update(&mut self, id: &str, change: JobEdit) -> Result<Job, StoreError> {
        let id = id.to_string();
        self.on_disk(move |s| s.update(&id, change)).await
    }
    async fn retry(&mut self, id: &str) -> Result<Job, StoreError> {
        let id = id.to_string();
        self.on_disk(move |s| s.retry(&id)).await
    }
    async fn set_gate(&mut self, printer: &str, gate: PrinterGate) -> Result<(), StoreError> {
        let printer = printer.to_string();
        self.on_disk(move |s| s.set_gate(&printer, gate)).await
    }
    async fn write_pending(&mut self) -> usize {
        self.on_disk(Spool::write_pending).await
    }
    fn unwritten(&self) -> usize {
        self.spool().unwritten()
    }
    async fn retire(&mut self, retention: &Retention, now: f64) -> Result<Vec<String>, StoreError> {
        let retention = *retention;
        self.on_disk(move |s| s.retire(&retention, now)).await
    }
    async fn retired(&mut self, id: &str) -> Result<Option<RetiredJob>, StoreError> {
        let id = id.to_string();
        self.on_disk(move |s| s.retired_job(&id)).await
    }
    async fn history(
        &mut self,
        before: Option<u64>,
        limit: usize,
        filter: &history::Filter,
    ) -> Result<history::Page, StoreError> {
        let filter = filter.clone();
        self.on_disk(move |s| s.history_page(before, limit, &filter))
            .await
    }
    async fn prune(
        &mut self,
        keep_for: std::time::Duration,
        now: f64,
    ) -> Result<usize, StoreError> {
        self.on_disk(move |s| s.prune(keep_for, now)).await
    }
    async fn each_retired(
        &mut self,
        since: f64,
        visit: &mut (dyn FnMut(Retired) + Send),
    ) -> Result<(), StoreError> {
        // A month at a time: the visitor borrows its caller's state, so it runs here, and
        // never the whole history is in memory at once.
        let months = self.on_disk(move |s| s.history.months_since(since)).await?;
        for month in months {
            blocking(move || HistoryFiles::month_records(&month).collect::<Vec<_>>())
                .await
                .into_iter()
                .for_each(&mut *visit);
        }
        Ok(())
    }
}
