//! The daemon's [`JobStore`] over the farm database: each call awaits the async client,
//! and what it does with this host's files (the hot folder's, the job directories') runs
//! on a blocking thread.
//!
//! It keeps what the snapshot needs in memory (every job, every bed gate), so glances never
//! reach the database; [`JobStore::resync`] takes in what other hosts changed. A job's
//! files live in the database and are copied into this host's `<spool>/jobs/<id>/` when
//! it prepares or prints the job; preparation's G-code goes to the database with the
//! change that makes the job ready.
//!
//! While the database is unreachable, an outcome that has happened (a print ended) and a
//! bed gate are kept here and written by [`JobStore::write_pending`] once it is back, if the
//! farm has not moved the job on meanwhile; everything else fails with
//! [`StoreError::Database`], so nothing new is claimed.

use super::{Change, FileBody, PgError, PgStore, MAX_FILE_BYTES};
use crate::daemon::filament::Inventory;
use crate::daemon::job::{Job, JobState, PrinterGate, StoreError};
use crate::daemon::store::history::{self, Retention, Retired};
use crate::daemon::store::pending::{Attempt, Kept, Pending, Written};
use crate::daemon::store::rules::io_err;
use crate::daemon::store::spool::{
    late_sidecar_name, lock_dir, model_name, move_file, regular_file_size, sidecar_of,
};
use crate::daemon::store::{blocking, InventoryEdit, JobEdit, JobStore, RetiredJob, StateFilter};
use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

/// Jobs changed this long before the last resync are read again: a transaction's
/// `updated_at` is its start, and it may commit a little after a resync that missed it.
const RESYNC_OVERLAP_S: f64 = 30.0;
/// Retired jobs read from the farm database at a time by a filtered history page or the
/// statistics (each read loads whole jobs, so not all at once).
const HISTORY_CHUNK: usize = 500;

pub struct PgJobStore {
    db: PgStore,
    _lock: nix::fcntl::Flock<std::fs::File>,
    jobs_dir: PathBuf,
    jobs: BTreeMap<String, Job>,
    gates: BTreeMap<String, PrinterGate>,
    /// The farm's spools as last read or written.
    inventory: Inventory,
    /// Outcomes recorded, and bed gates set, while the database was unreachable.
    pending: Pending,
    /// The database's time of the last resync.
    synced_to: f64,
    /// The last call found the database unreachable: until a resync reaches it again,
    /// changes fail at once and outcomes are kept at once, rather than each waiting out
    /// the connection timeout while the store's other requests queue behind it.
    unreachable: Option<String>,
}

/// `[state]` as a filter.
fn only(state: JobState) -> StateFilter {
    static EACH: [[JobState; 1]; 8] = [
        [JobState::Queued],
        [JobState::Preparing],
        [JobState::Ready],
        [JobState::Printing],
        [JobState::Done],
        [JobState::Failed],
        [JobState::Cancelled],
        [JobState::Interrupted],
    ];
    let i = JobState::ALL.iter().position(|s| *s == state).unwrap_or(0);
    &EACH[i]
}

impl PgJobStore {
    /// Opens the store for this host: its local directory `spool_dir` (locked, as a spool
    /// is) and every job and gate of the farm.
    pub async fn open(db: PgStore, spool_dir: &Path) -> Result<PgJobStore, StoreError> {
        let dir = spool_dir.to_path_buf();
        let lock = blocking(move || lock_dir(&dir)).await?;
        let changes = db.jobs_since(f64::NEG_INFINITY).await?;
        let (jobs, synced_to) = (changes.jobs, changes.now);
        let gates = db.gates().await?;
        let inventory = db.inventory().await?;
        Ok(PgJobStore {
            inventory,
            _lock: lock,
            jobs_dir: spool_dir.join("jobs"),
            jobs: jobs.into_iter().map(|j| (j.id.clone(), j)).collect(),
            gates,
            pending: Pending::default(),
            synced_to,
            unreachable: None,
            db,
        })
    }

    fn job_dir(&self, id: &str) -> PathBuf {
        self.jobs_dir.join(id)
    }

    /// Takes the database's record of a job after a refused change (another host moved it).
    async fn reread(&mut self, id: &str) {
        if let Ok(job) = self.db.job(id).await {
            self.jobs.insert(id.to_string(), job);
        }
    }

    /// Runs `work` against the database unless it is known to be unreachable, noting an
    /// outage when the call meets one.
    async fn reach<T>(
        &mut self,
        work: impl std::future::Future<Output = Result<T, PgError>>,
    ) -> Result<T, PgError> {
        if let Some(e) = &self.unreachable {
            return Err(PgError::Unreachable(e.clone()));
        }
        let result = work.await;
        if let Err(e) = &result {
            if e.is_outage() {
                self.unreachable = Some(e.to_string());
            }
        }
        result
    }

    async fn modify(&mut self, id: &str, change: Change<'_>) -> Result<Job, StoreError> {
        let db = self.db.clone();
        let result = self.reach(db.modify(id, change)).await;
        match result {
            Ok(job) => {
                self.jobs.insert(id.to_string(), job.clone());
                Ok(job)
            }
            Err(e) => {
                if !e.is_outage() {
                    self.reread(id).await;
                }
                Err(e.into())
            }
        }
    }

    fn cached(&self, id: &str) -> Result<&Job, StoreError> {
        self.jobs
            .get(id)
            .ok_or_else(|| StoreError::NoSuchJob(id.to_string()))
    }
}

/// The dropped file itself, as every host sharing its hot folder sees it: the folder, its
/// name, inode, size and modification time (the same file seen by two hosts is one pick-up;
/// a file dropped again is another, even under the same name).
fn pickup_of(source: &Path, folder: &str, file: &str) -> Result<String, StoreError> {
    use std::os::unix::fs::MetadataExt;
    let m = std::fs::metadata(source).map_err(io_err(source, "read"))?;
    Ok(format!(
        "{}:{}:{}.{:09}:{folder}/{file}",
        m.ino(),
        m.size(),
        m.mtime(),
        m.mtime_nsec()
    ))
}

/// An edit that gives a job the fields of `after` (a change worked out beforehand), keeping
/// its state and history for the transition to move on.
fn becomes(after: Job) -> JobEdit {
    Box::new(move |job: &mut Job| {
        let history = std::mem::take(&mut job.history);
        let (state, origin) = (job.state, job.origin.take());
        *job = after;
        job.history = history;
        job.state = state;
        job.origin = origin;
    })
}

#[async_trait::async_trait]
impl JobStore for PgJobStore {
    fn jobs_dir(&self) -> PathBuf {
        self.jobs_dir.clone()
    }

    fn jobs(&self) -> Vec<Job> {
        let mut jobs: Vec<Job> = self.jobs.values().cloned().collect();
        jobs.sort_by_key(|j| j.seq);
        jobs
    }

    fn job(&self, id: &str) -> Option<Job> {
        self.jobs.get(id).cloned()
    }

    fn gates(&self) -> BTreeMap<String, PrinterGate> {
        self.gates.clone()
    }

    fn inventory(&self) -> Inventory {
        self.inventory.clone()
    }

    async fn edit_inventory(
        &mut self,
        edit: &mut InventoryEdit<'_>,
    ) -> Result<Inventory, StoreError> {
        let db = self.db.clone();
        let inventory = self.reach(db.edit_inventory(edit)).await?;
        self.inventory = inventory.clone();
        Ok(inventory)
    }

    async fn recover(&mut self) -> Result<Vec<String>, StoreError> {
        let ids = self.db.recover_own().await?;
        self.resync().await;
        Ok(ids)
    }

    async fn admit(
        &mut self,
        source: &Path,
        folder: &Path,
        printers: &[String],
    ) -> Result<Job, StoreError> {
        let folder_name = folder.to_string_lossy().into_owned();
        // A hot folder may be on a network share: even a look at the file is made off
        // the runtime.
        let (file, sidecar, has_sidecar, pickup) = {
            let (source, folder_name) = (source.to_path_buf(), folder_name.clone());
            blocking(move || -> Result<_, StoreError> {
                let size = regular_file_size(&source)?;
                if size > MAX_FILE_BYTES {
                    return Err(io_err(&source, "read")(std::io::Error::other(format!(
                        "{size} bytes, more than the farm database keeps in one file ({MAX_FILE_BYTES})"
                    ))));
                }
                let file = model_name(&source);
                let sidecar = sidecar_of(&source);
                let has_sidecar = std::fs::symlink_metadata(&sidecar).is_ok_and(|m| m.is_file());
                let pickup = pickup_of(&source, &folder_name, &file)?;
                Ok((file, sidecar, has_sidecar, pickup))
            })
            .await?
        };
        let sidecar_name = format!("{file}.toml");
        // Read as they are stored, never whole in memory (a model may be large).
        let mut files = vec![(file.as_str(), FileBody::Path(source))];
        if has_sidecar {
            files.push((&sidecar_name, FileBody::Path(&sidecar)));
        }
        let db = self.db.clone();
        let job = self
            .reach(db.admit(&file, &folder_name, printers, &files, Some(&pickup)))
            .await?;
        // The job is in the farm now: its files leave the hot folder for this host's copy,
        // which preparation here reads. A file that cannot be moved is removed, so it is
        // never picked up twice.
        let dir = self.job_dir(&job.id);
        let mut moves = vec![(source.to_path_buf(), dir.join(&file))];
        if has_sidecar {
            moves.push((sidecar, dir.join(&sidecar_name)));
        }
        let id = job.id.clone();
        blocking(move || {
            let _ = std::fs::create_dir_all(&dir);
            for (from, to) in moves {
                if let Err(e) = move_file(&from, &to) {
                    tracing::warn!(job = %id, error = %e, "cannot keep a local copy; the farm database has the file");
                    if let Err(e) = std::fs::remove_file(&from) {
                        tracing::error!(job = %id, file = %from.display(), error = %e, "cannot remove a picked-up file from its hot folder: remove it by hand, or it is picked up again");
                    }
                }
            }
        })
        .await;
        self.jobs.insert(job.id.clone(), job.clone());
        Ok(job)
    }

    async fn late_sidecar(
        &mut self,
        id: &str,
        sidecar: &Path,
        applies: bool,
    ) -> Result<bool, StoreError> {
        let name = late_sidecar_name(&self.cached(id)?.file, applies);
        let from = sidecar.to_path_buf();
        let bytes = blocking(move || {
            regular_file_size(&from)?;
            std::fs::read(&from).map_err(io_err(&from, "read"))
        })
        .await?;
        self.db.put_file(id, &name, &bytes).await?;
        let (dir, from) = (self.job_dir(id), sidecar.to_path_buf());
        blocking(move || {
            let _ = std::fs::create_dir_all(&dir);
            move_file(&from, &dir.join(name))
        })
        .await?;
        Ok(applies)
    }

    async fn transition_with(
        &mut self,
        id: &str,
        from: Option<StateFilter>,
        state: JobState,
        reason: Option<String>,
        also: JobEdit,
    ) -> Result<Job, StoreError> {
        let dir = self.job_dir(id);
        let was = self.jobs.get(id).map(|j| j.state);
        let change = Change {
            from,
            to: Some(state),
            reason,
            edit: also,
            // Preparation made its G-code here; the other hosts' printers need it.
            upload_from: (state == JobState::Ready && was == Some(JobState::Preparing))
                .then_some(dir.as_path()),
            download_to: match state {
                JobState::Preparing => Some((dir.as_path(), false)),
                JobState::Printing => Some((dir.as_path(), true)),
                _ => None,
            },
        };
        self.modify(id, change).await
    }

    async fn record_outcome(
        &mut self,
        id: &str,
        state: JobState,
        reason: Option<String>,
        also: JobEdit,
    ) -> Result<Job, StoreError> {
        // Worked out here first: the outcome stands even if the database cannot take it now.
        let (from, after) =
            crate::daemon::store::pending::outcome(self.cached(id)?, state, reason.clone(), also)?;
        let change = Change {
            from: Some(only(from)),
            to: Some(state),
            reason,
            edit: becomes(after.clone()),
            upload_from: None,
            download_to: None,
        };
        let db = self.db.clone();
        match self.reach(db.modify(id, change)).await {
            Ok(job) => {
                self.jobs.insert(id.to_string(), job.clone());
                Ok(job)
            }
            Err(e) if e.is_outage() => {
                tracing::error!(job = id, error = %e, "cannot record the outcome in the farm database; kept here and written once it is back");
                self.pending.keep_outcome(from, after.clone());
                self.jobs.insert(id.to_string(), after.clone());
                Ok(after)
            }
            Err(e) => {
                self.reread(id).await;
                Err(e.into())
            }
        }
    }

    async fn make_copies(&mut self, id: &str) -> Result<Vec<String>, StoreError> {
        let db = self.db.clone();
        let made = self.reach(db.make_copies(id)).await?;
        // The job's record says they are made: read it back, as the copies.
        self.reread(id).await;
        let ids = made.iter().map(|j| j.id.clone()).collect();
        for copy in made {
            self.jobs.insert(copy.id.clone(), copy);
        }
        Ok(ids)
    }

    async fn update(&mut self, id: &str, change: JobEdit) -> Result<Job, StoreError> {
        let change = Change {
            from: None,
            to: None,
            reason: None,
            edit: change,
            upload_from: None,
            download_to: None,
        };
        self.modify(id, change).await
    }

    async fn retry(&mut self, id: &str) -> Result<Job, StoreError> {
        const FINISHED: StateFilter =
            &[JobState::Failed, JobState::Cancelled, JobState::Interrupted];
        if !self.jobs.contains_key(id) {
            if let Some(retired) = self.retired(id).await? {
                return Err(crate::daemon::store::retired_refusal(
                    id,
                    retired.record.state,
                    "retry",
                ));
            }
        }
        let job = self.cached(id)?.clone();
        if !FINISHED.contains(&job.state) {
            return Err(StoreError::WrongState {
                id: id.to_string(),
                state: job.state,
                action: "retry",
                allowed: "failed, cancelled or interrupted",
            });
        }
        // As in the spool: a prepared job keeps its G-code and is printed again as it was.
        let names = self.db.file_names(&job).await?;
        let prepared = super::super::prepared(&job, |name| names.iter().any(|n| n == name));
        let state = if prepared {
            JobState::Ready
        } else {
            JobState::Queued
        };
        let mut change = Change::to(state);
        change.from = Some(FINISHED);
        change.edit = Box::new(|j| j.printer = None);
        self.modify(id, change).await
    }

    async fn set_gate(&mut self, printer: &str, gate: PrinterGate) -> Result<(), StoreError> {
        let db = self.db.clone();
        match self.reach(db.set_gate(printer, &gate)).await {
            Ok(()) => {
                self.pending.gate_written(printer);
                self.gates.insert(printer.to_string(), gate);
                Ok(())
            }
            Err(e) if e.is_outage() && gate.bed_not_cleared() => {
                // A print ended: its bed must still need clearing after the outage.
                tracing::error!(printer, error = %e, "cannot record the bed gate in the farm database; kept here and written once it is back");
                self.pending.keep_gate(printer, gate.clone());
                self.gates.insert(printer.to_string(), gate);
                Ok(())
            }
            Err(e) => Err(e.into()),
        }
    }

    async fn write_pending(&mut self) -> usize {
        // Tried whatever the last call found: this is how an outage is found to be over.
        let mut written = Written::default();
        for kept in self.pending.take() {
            let attempt = match &kept {
                _ if written.unreachable => Attempt::Unreachable,
                Kept::Outcome { from, job, .. } => match self.db.write_outcome(job, *from).await {
                    Ok(record) => Attempt::Written(Some(Box::new(record))),
                    Err(e) if e.is_outage() => Attempt::Unreachable,
                    Err(e) => {
                        tracing::warn!(job = %job.id, error = %e, "the farm moved the job on during the outage");
                        Attempt::Dropped
                    }
                },
                Kept::Gate { printer, gate } => match self.db.set_gate(printer, gate).await {
                    Ok(()) => Attempt::Written(None),
                    Err(e) if e.is_outage() => Attempt::Unreachable,
                    Err(_) => Attempt::Dropped,
                },
            };
            self.pending.settle(kept, attempt, &mut written);
        }
        for job in written.jobs {
            self.jobs.insert(job.id.clone(), job);
        }
        for id in written.dropped {
            self.reread(&id).await;
        }
        if !written.unreachable {
            self.unreachable = None;
        }
        self.unwritten()
    }

    fn unwritten(&self) -> usize {
        self.pending.len()
    }

    async fn retire(&mut self, retention: &Retention, now: f64) -> Result<Vec<String>, StoreError> {
        let pending = &self.pending;
        let wanted = history::to_retire(self.jobs.values(), retention, now, &|id| {
            pending.has_outcome(id)
        });
        if wanted.is_empty() {
            return Ok(wanted);
        }
        let db = self.db.clone();
        let retired = self.reach(db.retire(&wanted)).await?;
        for id in &retired {
            self.jobs.remove(id);
        }
        Ok(retired)
    }

    async fn retired(&mut self, id: &str) -> Result<Option<RetiredJob>, StoreError> {
        let found = self.db.retired_job(id).await?;
        Ok(found.map(|(job, at)| RetiredJob {
            record: Retired::of(&job, self.job_dir(id), at),
            job: Some(job),
        }))
    }

    async fn history(
        &mut self,
        before: Option<u64>,
        limit: usize,
        filter: &history::Filter,
    ) -> Result<history::Page, StoreError> {
        // Unfiltered: one read of one more than asked (whether there is a next page).
        // Filtered: older and older reads until enough match or the history ends.
        let chunk = if filter.is_empty() {
            limit + 1
        } else {
            HISTORY_CHUNK.max(limit + 1)
        };
        // A job that ended since then was retired since then too.
        let since = filter.since.unwrap_or(0.0);
        let (mut jobs, mut more, mut cursor) = (Vec::new(), false, before);
        loop {
            let read = self.db.history(cursor, chunk, since).await?;
            for (job, at) in &read {
                let record = Retired::of(job, self.job_dir(&job.id), *at);
                if filter.matches(&record) {
                    if jobs.len() == limit {
                        more = true;
                        break;
                    }
                    jobs.push(record);
                }
            }
            if more || read.len() < chunk {
                break;
            }
            cursor = read.last().map(|(j, _)| j.seq);
        }
        Ok(history::Page {
            next: if more {
                jobs.last().map(|r| r.seq)
            } else {
                None
            },
            jobs,
        })
    }

    async fn prune(
        &mut self,
        keep_for: std::time::Duration,
        now: f64,
    ) -> Result<usize, StoreError> {
        // By the database's record of when each job was retired; any host may do it.
        let gone = self.db.forget_retired(now - keep_for.as_secs_f64()).await?;
        let dirs: Vec<PathBuf> = gone.iter().map(|id| self.job_dir(id)).collect();
        blocking(move || {
            for dir in dirs {
                // This host's copy of its files, where it has one.
                let _ = std::fs::remove_dir_all(dir);
            }
        })
        .await;
        Ok(gone.len())
    }

    async fn each_retired(
        &mut self,
        since: f64,
        visit: &mut (dyn FnMut(Retired) + Send),
    ) -> Result<(), StoreError> {
        let mut cursor = None;
        loop {
            let read = self.db.history(cursor, HISTORY_CHUNK, since).await?;
            cursor = read.last().map(|(j, _)| j.seq);
            let n = read.len();
            for (job, at) in read {
                visit(Retired::of(&job, self.job_dir(&job.id), at));
            }
            if n < HISTORY_CHUNK {
                return Ok(());
            }
        }
    }

    async fn resync(&mut self) -> bool {
        let since = self.synced_to - RESYNC_OVERLAP_S;
        let read = async {
            let jobs = self.db.jobs_since(since).await?;
            let gates = self.db.gates().await?;
            let inventory = self.db.inventory().await?;
            Ok::<_, PgError>((jobs, gates, inventory))
        }
        .await;
        let (
            super::Changes {
                jobs: changed,
                retired,
                now,
            },
            mut gates,
            inventory,
        ) = match read {
            Ok(read) => read,
            Err(e) => {
                tracing::debug!(error = %e, "cannot read the farm database's changes");
                return false;
            }
        };
        self.unreachable = None;
        self.synced_to = now;
        let mut any = false;
        for id in retired {
            any |= self.jobs.remove(&id).is_some();
        }
        for job in changed {
            // An outcome not yet written stays as this host knows it.
            if self.pending.has_outcome(&job.id) {
                continue;
            }
            let known = self.jobs.get(&job.id).map(serde_json::to_value);
            if known.and_then(Result::ok) != serde_json::to_value(&job).ok() {
                any = true;
                self.jobs.insert(job.id.clone(), job);
            }
        }
        for (printer, gate) in self.pending.gates() {
            gates.insert(printer.clone(), gate.clone());
        }
        if gates != self.gates {
            any = true;
            self.gates = gates;
        }
        if inventory != self.inventory {
            any = true;
            self.inventory = inventory;
        }
        any
    }
}
