//! The job spool: one directory per job under `<spool>/jobs/`, holding the dropped model
//! (moved in, never deleted), its sidecar, the prepared G-code and `job.json`, the job's
//! state. `job.json` is written atomically (temporary file, fsync, rename, fsync of the
//! directory) so a crash or power cut leaves either the old or the new state, never a torn
//! one. The printers' bed gates live in `<spool>/printers.json`, written the same way.
//! [`Spool::open`] rebuilds everything from disk; [`Spool::recover`] applies the
//! restart rules (preparing → queued, printing → interrupted).
//!
//! Finished jobs move to the history after a while (see [`super::history`]): their
//! directories stay under `<spool>/jobs/`, and `<spool>/history/` says which ones are
//! retired, so opening the spool never reads their state.
//!
//! The embedded, single-host implementation of [`JobStore`]: the default.

use super::history::{self, HistoryFiles, Retention, Retired};
use super::pending::{Attempt, Pending};
use super::rules::io_err;
use super::{JobEdit, JobStore, RetiredJob, StateFilter};
use crate::daemon::hotfolder::{find_named, normal_name};
use crate::daemon::job::{now_s, Job, JobState, PrinterGate, StoreError};
use serde::{Deserialize, Serialize};
use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

/// The spool on disk plus its in-memory index. Not synchronised: only the store's task
/// uses it (see [`super::spawn`]). Holds the spool's lock (`<spool>/lock`, an flock) while
/// open, so two daemons never share a spool.
pub struct Spool {
    _lock: nix::fcntl::Flock<std::fs::File>,
    root: PathBuf,
    jobs: BTreeMap<String, Job>,
    gates: BTreeMap<String, PrinterGate>,
    next_seq: u64,
    /// Outcomes newer in memory than on disk (see [`Spool::record_outcome`]), and bed
    /// gates newer than `printers.json` (a full disk): a bed that needs clearing must
    /// still need it after a restart, so they are written again.
    pending: Pending,
    history: HistoryFiles,
    /// The jobs in the history (their directories stay in `jobs/`).
    retired: std::collections::HashSet<String>,
}

/// Creates `root/jobs` and takes `root/lock`, so two daemons never share a directory.
pub(super) fn lock_dir(root: &Path) -> Result<nix::fcntl::Flock<std::fs::File>, StoreError> {
    let jobs_dir = root.join("jobs");
    std::fs::create_dir_all(&jobs_dir).map_err(io_err(&jobs_dir, "create"))?;
    let lock_path = root.join("lock");
    let lock_file = std::fs::OpenOptions::new()
        .create(true)
        .truncate(false)
        .write(true)
        .open(&lock_path)
        .map_err(io_err(&lock_path, "open"))?;
    nix::fcntl::Flock::lock(lock_file, nix::fcntl::FlockArg::LockExclusiveNonblock).map_err(
        |(_, errno)| match errno {
            nix::errno::Errno::EWOULDBLOCK => StoreError::Locked {
                path: root.to_path_buf(),
            },
            e => io_err(&lock_path, "lock")(e.into()),
        },
    )
}

/// Writes `bytes` to `path` atomically and durably (see [`crate::fsutil`]).
pub(super) fn write_atomic(path: &Path, bytes: &[u8]) -> Result<(), StoreError> {
    Ok(crate::fsutil::write_atomic(path, bytes)?)
}

impl Spool {
    /// Opens (creating if needed) the spool at `root`, takes its lock, and loads every job
    /// in it. A job whose state cannot be read is loaded as failed, never stopping the
    /// others; a directory that is not a job of this spool (a copy of one, a stray
    /// folder) is left alone and logged.
    pub fn open(root: &Path) -> Result<Spool, StoreError> {
        let jobs_dir = root.join("jobs");
        let lock = lock_dir(root)?;
        let (history, retired) = HistoryFiles::open(root)?;
        let mut jobs = BTreeMap::new();
        let mut next_seq = 1;
        for entry in std::fs::read_dir(&jobs_dir).map_err(io_err(&jobs_dir, "list"))? {
            let entry = entry.map_err(io_err(&jobs_dir, "list"))?;
            let dir = entry.path();
            let name = entry.file_name().to_string_lossy().into_owned();
            if !entry.file_type().is_ok_and(|t| t.is_dir()) {
                continue;
            }
            let Some(seq) = seq_of_id(&name) else {
                tracing::warn!(dir = %dir.display(), "not a job directory (its name is not a job id); left alone");
                continue;
            };
            next_seq = next_seq.max(seq + 1);
            if retired.contains(&name) {
                continue;
            }
            let job = match load_job(&dir) {
                // A job directory without state: created by a pick-up interrupted before
                // the state was written. Its files stay; the pick-up is redone below.
                Ok(None) => continue,
                Ok(Some(job)) if job.id != name => {
                    tracing::warn!(dir = %dir.display(), job = %job.id, "a copy of another job's directory; not a job, left alone");
                    continue;
                }
                Ok(Some(job)) => job,
                Err(e) => {
                    tracing::error!(job = %name, error = %e, "job state unreadable; the job is marked failed");
                    unreadable_job(root, &dir, &name, seq, &e)
                }
            };
            jobs.insert(job.id.clone(), job);
        }
        let gates_file = root.join("printers.json");
        let gates = match std::fs::read(&gates_file) {
            Ok(t) => serde_json::from_slice(&t).map_err(|e| StoreError::Corrupt {
                path: gates_file.clone(),
                message: e.to_string(),
            })?,
            Err(e) if e.kind() == std::io::ErrorKind::NotFound => BTreeMap::new(),
            Err(e) => return Err(io_err(&gates_file, "read")(e)),
        };
        let mut store = Spool {
            _lock: lock,
            root: root.to_path_buf(),
            jobs,
            gates,
            next_seq,
            pending: Pending::default(),
            history,
            retired,
        };
        store.adopt_orphans()?;
        Ok(store)
    }

    /// Job directories whose model was moved in but whose state was never written (a crash
    /// between the two steps) become queued jobs, so no dropped file is ever lost. Only a
    /// directory whose `origin.json` names it is adopted: a copy of one is not a new job.
    fn adopt_orphans(&mut self) -> Result<(), StoreError> {
        let jobs_dir = self.root.join("jobs");
        let mut orphans = Vec::new();
        for entry in std::fs::read_dir(&jobs_dir).map_err(io_err(&jobs_dir, "list"))? {
            let entry = entry.map_err(io_err(&jobs_dir, "list"))?;
            let id = entry.file_name().to_string_lossy().into_owned();
            if self.jobs.contains_key(&id)
                || self.retired.contains(&id)
                || seq_of_id(&id).is_none()
                || !entry.path().is_dir()
            {
                continue;
            }
            orphans.push((id, entry.path()));
        }
        for (id, dir) in orphans {
            let Some(origin) = read_origin(&dir) else {
                continue;
            };
            if origin.id != id {
                tracing::warn!(dir = %dir.display(), job = %origin.id, "a copy of another job's directory; not a job, left alone");
                continue;
            }
            if !dir.join(&origin.file).exists() {
                continue;
            }
            let seq = self.next_seq;
            self.next_seq += 1;
            let job = Job::queued(id.clone(), seq, origin.file, origin.folder);
            self.save(&job)?;
            self.jobs.insert(id, job);
        }
        Ok(())
    }

    /// Restart rules: preparation is redone, a print that was running is interrupted and its
    /// printer must have its bed cleared by a person. Returns the ids changed.
    pub fn recover(&mut self) -> Result<Vec<String>, StoreError> {
        let mut changed = Vec::new();
        let ids: Vec<String> = self.jobs.keys().cloned().collect();
        for id in ids {
            let job = &self.jobs[&id];
            match job.state {
                JobState::Preparing => {
                    self.transition(&id, JobState::Queued, None)?;
                    changed.push(id);
                }
                JobState::Printing => {
                    let printer = job.printer.clone();
                    self.transition(
                        &id,
                        JobState::Interrupted,
                        Some("the daemon stopped while this job was printing; \
                              check the printer, clear its bed, then `crispen retry` the job if wanted"
                            .into()),
                    )?;
                    if let Some(p) = printer {
                        self.set_gate(
                            &p,
                            PrinterGate {
                                bed_not_cleared: true,
                                last_job: Some(id.clone()),
                            },
                        )?;
                    }
                    changed.push(id);
                }
                _ => {}
            }
        }
        Ok(changed)
    }

    pub fn root(&self) -> &Path {
        &self.root
    }

    pub fn job_dir(&self, id: &str) -> PathBuf {
        self.root.join("jobs").join(id)
    }

    pub fn get(&self, id: &str) -> Option<&Job> {
        self.jobs.get(id)
    }

    /// Jobs oldest first.
    pub fn jobs(&self) -> impl Iterator<Item = &Job> {
        let mut all: Vec<&Job> = self.jobs.values().collect();
        all.sort_by_key(|j| j.seq);
        all.into_iter()
    }

    pub fn gate(&self, printer: &str) -> PrinterGate {
        self.gates.get(printer).cloned().unwrap_or_default()
    }

    pub fn set_gate(&mut self, printer: &str, gate: PrinterGate) -> Result<(), StoreError> {
        self.gates.insert(printer.to_string(), gate.clone());
        let written = self.save_gates();
        match &written {
            // One file holds every gate: all kept ones are written with it.
            Ok(()) => self.pending.gate_written(printer),
            Err(_) => self.pending.keep_gate(printer, gate),
        }
        written
    }

    fn save_gates(&self) -> Result<(), StoreError> {
        let bytes = serde_json::to_vec_pretty(&self.gates).expect("gates serialise");
        write_atomic(&self.root.join("printers.json"), &bytes)
    }

    /// Creates a job by moving `source` (a complete file in a hot folder) into a new job
    /// directory. The file is renamed, not copied, when spool and folder share a filesystem;
    /// otherwise it is copied, synced, and only then removed from the folder.
    pub fn admit(&mut self, source: &Path, folder: &Path) -> Result<Job, StoreError> {
        // Never follow a link out of the hot folder: only the folder's own files are taken.
        regular_file_size(source)?;
        let file = model_name(source);
        let seq = self.next_seq;
        self.next_seq += 1;
        let id = Job::make_id(seq, &file);
        let dir = self.job_dir(&id);
        let sidecar = sidecar_of(source);
        let job = Job::queued(id.clone(), seq, file, folder.to_path_buf());
        // A pick-up that cannot be completed (a full disk) is undone: the files go back to
        // the hot folder and no half job is left behind.
        let mut moved = Vec::new();
        if let Err(e) = self.admit_into(&job, source, &sidecar, &mut moved) {
            let mut undone = true;
            for (from, to) in moved.iter().rev() {
                undone &= move_file(to, from).is_ok();
            }
            if undone {
                let _ = std::fs::remove_dir_all(&dir);
            } else {
                tracing::error!(job = %id, dir = %dir.display(), "a failed pick-up could not be undone; its files stay in the job directory");
            }
            return Err(e);
        }
        self.jobs.insert(id, job.clone());
        Ok(job)
    }

    /// The steps of [`Spool::admit`]; each file moved is recorded in `moved` as
    /// (from, to) so that a failure can be undone.
    fn admit_into(
        &self,
        job: &Job,
        source: &Path,
        sidecar: &Path,
        moved: &mut Vec<(PathBuf, PathBuf)>,
    ) -> Result<(), StoreError> {
        let dir = self.job_dir(&job.id);
        std::fs::create_dir_all(&dir).map_err(io_err(&dir, "create job directory"))?;
        // Written before the move so a crash between the move and job.json still leaves
        // enough to rebuild the job (see adopt_orphans).
        let origin = serde_json::to_vec(&Origin {
            id: job.id.clone(),
            file: job.file.clone(),
            folder: job.folder.clone(),
        })
        .expect("origin serialises");
        write_atomic(&dir.join("origin.json"), &origin)?;
        let model = dir.join(&job.file);
        move_file(source, &model)?;
        moved.push((source.to_path_buf(), model));
        // The sidecar travels with its model.
        if std::fs::symlink_metadata(sidecar).is_ok_and(|m| m.is_file()) {
            let to = dir.join(format!("{}.toml", job.file));
            move_file(sidecar, &to)?;
            moved.push((sidecar.to_path_buf(), to));
        }
        self.save(job)
    }

    /// Moves a sidecar that arrived after its model into the job's directory: as the
    /// job's sidecar when `applies` (the job has not started preparing), else aside as
    /// `<file>.toml.late`, kept but not used. Returns `applies`.
    pub fn late_sidecar(
        &mut self,
        id: &str,
        sidecar: &Path,
        applies: bool,
    ) -> Result<bool, StoreError> {
        let job = self
            .jobs
            .get(id)
            .ok_or_else(|| StoreError::NoSuchJob(id.to_string()))?;
        regular_file_size(sidecar)?;
        let name = late_sidecar_name(&job.file, applies);
        move_file(sidecar, &self.job_dir(id).join(name))?;
        Ok(applies)
    }

    fn save(&self, job: &Job) -> Result<(), StoreError> {
        let bytes = serde_json::to_vec_pretty(job).expect("job serialises");
        write_atomic(&self.job_dir(&job.id).join("job.json"), &bytes)
    }

    /// Changes a job's state (with a reason for failed/cancelled/interrupted) and persists it.
    pub fn transition(
        &mut self,
        id: &str,
        state: JobState,
        reason: Option<String>,
    ) -> Result<Job, StoreError> {
        self.transition_with(id, state, reason, |_| {})
    }

    /// [`Spool::transition`] with other fields changed in the same write (the printer
    /// that claimed the job, the preparation's report).
    pub fn transition_with(
        &mut self,
        id: &str,
        state: JobState,
        reason: Option<String>,
        also: impl FnOnce(&mut Job),
    ) -> Result<Job, StoreError> {
        self.change(id, |job| job.apply_transition(state, reason, also))
    }

    /// [`Spool::transition_with`] for an outcome that has already happened (a print
    /// ended): it is recorded in memory even when it cannot be written (a full disk), and
    /// written by [`Spool::write_pending`] once it can, so a finished print is never
    /// taken for an unfinished one and offered again.
    pub fn record_outcome(
        &mut self,
        id: &str,
        state: JobState,
        reason: Option<String>,
        also: impl FnOnce(&mut Job),
    ) -> Result<Job, StoreError> {
        let current = self
            .jobs
            .get(id)
            .ok_or_else(|| StoreError::NoSuchJob(id.to_string()))?;
        let (from, job) = super::pending::outcome(current, state, reason, also)?;
        self.jobs.insert(id.to_string(), job.clone());
        if let Err(e) = self.save(&job) {
            tracing::error!(job = id, error = %e, "cannot write the job's state; kept in memory and written again when possible");
            self.pending.keep_outcome(from, job.clone());
        }
        Ok(job)
    }

    /// Writes the outcomes and gates that could not be written before; returns how many
    /// remain.
    pub fn write_pending(&mut self) -> usize {
        let mut pending = std::mem::take(&mut self.pending);
        pending.write(
            |id, _, job| match self.save(job) {
                Ok(()) => Attempt::Written(None),
                // Removed by hand: there is nowhere to write it.
                Err(_) if !self.job_dir(id).is_dir() => Attempt::Dropped,
                Err(_) => Attempt::Failed,
            },
            |_, _| match self.save_gates() {
                Ok(()) => Attempt::Written(None),
                Err(_) => Attempt::Failed,
            },
        );
        self.pending = pending;
        self.pending.len()
    }

    /// Applies `change` to a job's other fields and persists it; its state stays (only
    /// [`Spool::transition`] changes that).
    pub fn update(&mut self, id: &str, change: impl FnOnce(&mut Job)) -> Result<Job, StoreError> {
        self.change(id, |job| {
            let state = job.state;
            change(job);
            job.state = state;
            Ok(())
        })
    }

    fn change(
        &mut self,
        id: &str,
        change: impl FnOnce(&mut Job) -> Result<(), StoreError>,
    ) -> Result<Job, StoreError> {
        let mut job = self
            .jobs
            .get(id)
            .cloned()
            .ok_or_else(|| StoreError::NoSuchJob(id.to_string()))?;
        change(&mut job)?;
        if let Err(e) = self.save(&job).inspect(|_| self.pending.written(id)) {
            let dir = self.job_dir(id);
            if dir.is_dir() {
                return Err(e);
            }
            // Removed by hand: nothing of the job is left to go on with. It fails (in
            // memory; there is nowhere to write it) so the queue moves past it.
            let mut failed = self.jobs[id].clone();
            if failed.state.can_go_to(JobState::Failed) {
                failed.state = JobState::Failed;
                failed.history.push((JobState::Failed, now_s()));
                // Named relative to the spool: the reason is shown to clients.
                failed.reason = Some(format!(
                    "its directory {} was removed",
                    super::spool_relative(&dir.display().to_string(), &self.root)
                ));
                self.jobs.insert(id.to_string(), failed);
            }
            return Err(StoreError::DirectoryGone {
                id: id.to_string(),
                dir,
            });
        }
        self.jobs.insert(id.to_string(), job.clone());
        Ok(job)
    }

    /// Puts a failed, cancelled or interrupted job back in the queue.
    pub fn retry(&mut self, id: &str) -> Result<Job, StoreError> {
        if let Some(retired) = self.retired_job(id)? {
            return Err(super::retired_refusal(id, retired.record.state, "retry"));
        }
        let job = self
            .jobs
            .get(id)
            .ok_or_else(|| StoreError::NoSuchJob(id.to_string()))?;
        // Finished jobs the table lets back into the queue (done is final).
        if job.state.is_active() || !job.state.can_go_to(JobState::Queued) {
            return Err(StoreError::WrongState {
                id: id.to_string(),
                state: job.state,
                action: "retry",
                allowed: "failed, cancelled or interrupted",
            });
        }
        // A job that was prepared keeps its G-code: printing it again is what a retry
        // after a cancelled or interrupted print means, and slicing again would give a
        // slightly different program (PrusaSlicer's output varies from run to run).
        let dir = self.job_dir(id);
        let prepared = super::prepared(job, |name| dir.join(name).is_file());
        let state = if prepared {
            JobState::Ready
        } else {
            JobState::Queued
        };
        self.transition_with(id, state, None, |j| j.printer = None)
    }
}

impl Spool {
    /// Moves the finished jobs `retention` no longer keeps live to the history: their
    /// records are appended and synced first, then they leave the live jobs. Returns
    /// their ids (at most [`history::BATCH`]).
    pub fn retire(&mut self, retention: &Retention, now: f64) -> Result<Vec<String>, StoreError> {
        let pending = &self.pending;
        let ids = history::to_retire(self.jobs.values(), retention, now, &|id| {
            pending.has_outcome(id)
        });
        if ids.is_empty() {
            return Ok(ids);
        }
        let records: Vec<Retired> = ids
            .iter()
            .map(|id| Retired::of(&self.jobs[id], self.job_dir(id), now))
            .collect();
        self.history.append(&records, now)?;
        for id in &ids {
            self.jobs.remove(id);
            self.retired.insert(id.clone());
        }
        Ok(ids)
    }

    /// Forgets the history's months wholly older than `keep_for` before `now`: each job's
    /// directory first, then the month's file (a crash in between leaves the file, whose
    /// remaining directories go next time). Returns how many jobs went.
    pub fn prune(&mut self, keep_for: std::time::Duration, now: f64) -> Result<usize, StoreError> {
        let cutoff = now - keep_for.as_secs_f64();
        let mut gone = 0;
        for file in self.history.months_before(cutoff)? {
            for record in HistoryFiles::records_of(&file)? {
                // Only a retired job's own directory: never a live job's.
                if self.jobs.contains_key(&record.id) {
                    continue;
                }
                let dir = self.job_dir(&record.id);
                match std::fs::remove_dir_all(&dir) {
                    Ok(()) => {}
                    Err(e) if e.kind() == std::io::ErrorKind::NotFound => {}
                    Err(e) => return Err(io_err(&dir, "remove")(e)),
                }
                self.retired.remove(&record.id);
                gone += 1;
            }
            self.history.remove_month(&file)?;
            tracing::info!(file = %file.display(), "history month older than [history] keep_days removed, with its jobs' directories");
        }
        Ok(gone)
    }

    /// A retired job: its history record, and its whole state from its directory.
    pub fn retired_job(&self, id: &str) -> Result<Option<RetiredJob>, StoreError> {
        if !self.retired.contains(id) {
            return Ok(None);
        }
        let Some(record) = self.history.find(id)? else {
            return Ok(None);
        };
        let job = load_job(&self.job_dir(id)).ok().flatten();
        Ok(Some(RetiredJob { record, job }))
    }
}

impl JobStore for Spool {
    fn jobs_dir(&self) -> PathBuf {
        self.root.join("jobs")
    }
    fn jobs(&self) -> Vec<Job> {
        Spool::jobs(self).cloned().collect()
    }
    fn job(&self, id: &str) -> Option<Job> {
        self.get(id).cloned()
    }
    fn gates(&self) -> BTreeMap<String, PrinterGate> {
        self.gates.clone()
    }
    fn recover(&mut self) -> Result<Vec<String>, StoreError> {
        Spool::recover(self)
    }
    fn admit(
        &mut self,
        source: &Path,
        folder: &Path,
        _printers: &[String],
    ) -> Result<Job, StoreError> {
        Spool::admit(self, source, folder)
    }
    fn late_sidecar(
        &mut self,
        id: &str,
        sidecar: &Path,
        applies: bool,
    ) -> Result<bool, StoreError> {
        Spool::late_sidecar(self, id, sidecar, applies)
    }
    fn transition_with(
        &mut self,
        id: &str,
        from: Option<StateFilter>,
        state: JobState,
        reason: Option<String>,
        also: JobEdit,
    ) -> Result<Job, StoreError> {
        self.change(id, |job| {
            super::check_from(job, from)?;
            job.apply_transition(state, reason, also)
        })
    }
    fn record_outcome(
        &mut self,
        id: &str,
        state: JobState,
        reason: Option<String>,
        also: JobEdit,
    ) -> Result<Job, StoreError> {
        Spool::record_outcome(self, id, state, reason, also)
    }
    fn update(&mut self, id: &str, change: JobEdit) -> Result<Job, StoreError> {
        Spool::update(self, id, change)
    }
    fn retry(&mut self, id: &str) -> Result<Job, StoreError> {
        Spool::retry(self, id)
    }
    fn set_gate(&mut self, printer: &str, gate: PrinterGate) -> Result<(), StoreError> {
        Spool::set_gate(self, printer, gate)
    }
    fn write_pending(&mut self) -> usize {
        Spool::write_pending(self)
    }
    fn unwritten(&self) -> usize {
        self.pending.len()
    }
    fn retire(&mut self, retention: &Retention, now: f64) -> Result<Vec<String>, StoreError> {
        Spool::retire(self, retention, now)
    }
    fn retired(&self, id: &str) -> Result<Option<RetiredJob>, StoreError> {
        self.retired_job(id)
    }
    fn history(
        &self,
        before: Option<u64>,
        limit: usize,
        filter: &history::Filter,
    ) -> Result<history::Page, StoreError> {
        Ok(history::page_of(
            self.history.records()?,
            before,
            limit,
            filter,
        ))
    }
    fn prune(&mut self, keep_for: std::time::Duration, now: f64) -> Result<usize, StoreError> {
        Spool::prune(self, keep_for, now)
    }
    fn each_retired(&self, since: f64, visit: &mut dyn FnMut(Retired)) -> Result<(), StoreError> {
        self.history.records_since(since)?.for_each(visit);
        Ok(())
    }
}

/// What a job directory says about where its model came from (written before the model
/// is moved in, so an interrupted pick-up can be completed).
#[derive(Debug, Serialize, Deserialize)]
struct Origin {
    /// The directory's own name: a copy of the directory under another name is not a job.
    id: String,
    file: String,
    folder: PathBuf,
}

fn read_origin(dir: &Path) -> Option<Origin> {
    let bytes = std::fs::read(dir.join("origin.json")).ok()?;
    serde_json::from_slice(&bytes).ok()
}

/// Names of the files crispen keeps in a job directory besides the model's own.
/// The size of `path` if it is a regular file (never a link out of the hot folder).
pub(super) fn regular_file_size(path: &Path) -> Result<u64, StoreError> {
    match std::fs::symlink_metadata(path) {
        Ok(meta) if meta.file_type().is_file() => Ok(meta.len()),
        Ok(_) => Err(StoreError::NotAFile {
            path: path.to_path_buf(),
        }),
        Err(e) => Err(io_err(path, "read")(e)),
    }
}

/// The name a dropped file is kept under in its job: its own in its one spelling (NFC:
/// two spellings of a name are one job name, see [`normal_name`]), unless it is named like
/// one of the job's own files, so neither overwrites the other. The file in the hot folder
/// is not renamed; its copy in the job directory is under this name.
pub(super) fn model_name(source: &Path) -> String {
    let dropped = source
        .file_name()
        .map(|n| normal_name(&n.to_string_lossy()).into_owned())
        .unwrap_or_else(|| "model".into());
    if is_reserved_name(&dropped) {
        format!("model-{dropped}")
    } else {
        dropped
    }
}

/// The sidecar of a dropped model: `<model>.toml`, or the same name spelt otherwise (a
/// decomposed `café.gcode.toml` is the sidecar of a composed `café.gcode`). A path that
/// is not there when there is none.
pub(super) fn sidecar_of(source: &Path) -> PathBuf {
    let mut exact = source.as_os_str().to_owned();
    exact.push(".toml");
    let exact = PathBuf::from(exact);
    let (Some(folder), Some(name)) = (source.parent(), source.file_name()) else {
        return exact;
    };
    let Some(name) = name.to_str() else {
        return exact;
    };
    find_named(folder, &format!("{name}.toml")).unwrap_or(exact)
}

/// Where a late sidecar of model `file` goes: the job's sidecar when it `applies`, else
/// aside, kept but not used.
pub(super) fn late_sidecar_name(file: &str, applies: bool) -> String {
    if applies {
        format!("{file}.toml")
    } else {
        format!("{file}.toml.late")
    }
}

fn is_reserved_name(name: &str) -> bool {
    matches!(name, "job.json" | "origin.json") || name.starts_with(".crispen-")
}

/// The sequence number of a well-formed job id (`<digits>-<letters, digits, -, _>`), as
/// [`Spool::admit`] makes them; `None` for anything else.
pub fn seq_of_id(id: &str) -> Option<u64> {
    let (seq, stem) = id.split_once('-')?;
    let stem_ok = stem.len() <= 40
        && stem
            .chars()
            .all(|c| c.is_ascii_alphanumeric() || c == '-' || c == '_');
    if seq.len() < 4 || seq.len() > 12 || !seq.chars().all(|c| c.is_ascii_digit()) || !stem_ok {
        return None;
    }
    seq.parse().ok()
}

/// Reads a job's state; `Ok(None)` when it has none yet. State files are small: a bigger
/// one is not a job's.
fn load_job(dir: &Path) -> Result<Option<Job>, StoreError> {
    const MAX_STATE_BYTES: u64 = 1 << 20;
    let path = dir.join("job.json");
    let file = match std::fs::File::open(&path) {
        Ok(f) => f,
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => return Ok(None),
        Err(e) => return Err(io_err(&path, "read")(e)),
    };
    let mut text = Vec::new();
    std::io::Read::read_to_end(
        &mut std::io::Read::take(file, MAX_STATE_BYTES + 1),
        &mut text,
    )
    .map_err(io_err(&path, "read"))?;
    if text.len() as u64 > MAX_STATE_BYTES {
        return Err(StoreError::Corrupt {
            path,
            message: format!("larger than {MAX_STATE_BYTES} bytes"),
        });
    }
    let job: Job = serde_json::from_slice(&text).map_err(|e| StoreError::Corrupt {
        path: path.clone(),
        message: e.to_string(),
    })?;
    if seq_of_id(&job.id).is_none() {
        return Err(StoreError::Corrupt {
            path,
            message: format!("{:?} is not a job id", job.id),
        });
    }
    Ok(Some(job))
}

/// A failed stand-in for a job whose state could not be read; the directory is kept as it
/// is for the operator to look at. Its reason names the files relative to the spool `root`
/// (`jobs/<id>/job.json`): clients see it (the log has the whole path).
fn unreadable_job(root: &Path, dir: &Path, id: &str, seq: u64, error: &StoreError) -> Job {
    let (file, folder) = match read_origin(dir) {
        Some(o) => (o.file, o.folder),
        None => (String::new(), PathBuf::new()),
    };
    let mut job = Job::queued(id.to_string(), seq, file, folder);
    job.state = JobState::Failed;
    job.history.push((JobState::Failed, now_s()));
    let reason = format!("{error}; the directory {} is kept as it was", dir.display());
    job.reason = Some(super::spool_relative(&reason, root));
    job
}

/// Moves a file, copying it when `from` and `to` are on different filesystems. A copy
/// goes to a temporary name first and is renamed into place only once whole and synced,
/// so a copy cut short (a full disk) never passes for the file.
pub(super) fn move_file(from: &Path, to: &Path) -> Result<(), StoreError> {
    match std::fs::rename(from, to) {
        Ok(()) => Ok(()),
        Err(e) if e.raw_os_error() == Some(nix::libc::EXDEV) => {
            let mut source = std::fs::File::open(from).map_err(io_err(from, "read"))?;
            crate::fsutil::write_atomic_with(to, |file| {
                std::io::copy(&mut source, file).map(|_| ())
            })?;
            std::fs::remove_file(from).map_err(io_err(from, "remove after copying"))
        }
        Err(e) => Err(io_err(from, "move")(e)),
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::io::Write;

    /// A temporary folder holding a hot folder `hot` and a spool `spool`, opened.
    fn open_with_hot_folder() -> (tempfile::TempDir, PathBuf, PathBuf, Spool) {
        let tmp = tempfile::tempdir().unwrap();
        let hot = tmp.path().join("hot");
        std::fs::create_dir(&hot).unwrap();
        let spool = tmp.path().join("spool");
        let store = Spool::open(&spool).unwrap();
        (tmp, hot, spool, store)
    }

    fn drop_file(dir: &Path, name: &str) -> PathBuf {
        let p = dir.join(name);
        std::fs::write(&p, b"solid x\nendsolid x\n").unwrap();
        p
    }

    #[test]
    fn admit_moves_file_and_persists_state() {
        let (_tmp, hot, spool, mut store) = open_with_hot_folder();
        let src = drop_file(&hot, "a b.stl");
        std::fs::write(hot.join("a b.stl.toml"), "enhance = false\n").unwrap();
        let job = store.admit(&src, &hot).unwrap();
        assert!(!src.exists());
        assert!(store.job_dir(&job.id).join("a b.stl").exists());
        assert!(store.job_dir(&job.id).join("a b.stl.toml").exists());
        assert!(!hot.join("a b.stl.toml").exists());
        assert_eq!(job.state, JobState::Queued);

        let err = Spool::open(&spool).err().unwrap();
        assert!(matches!(err, StoreError::Locked { .. }), "{err}");
        drop(store);
        let store2 = Spool::open(&spool).unwrap();
        let again = store2.get(&job.id).unwrap();
        assert_eq!(again.file, "a b.stl");
        assert_eq!(again.state, JobState::Queued);
    }

    /// A dropped `café.gcode` becomes a job named in the one spelling (composed), whichever
    /// spelling it was dropped under; its sidecar goes with it in the other spelling too.
    #[test]
    fn a_job_is_named_in_the_one_spelling_and_finds_its_sidecar_in_any() {
        let (_tmp, hot, spool, mut store) = open_with_hot_folder();
        let composed = "caf\u{e9}.gcode";
        let src = drop_file(&hot, "cafe\u{301}.gcode");
        std::fs::write(hot.join(format!("{composed}.toml")), "hold = true\n").unwrap();
        let job = store.admit(&src, &hot).unwrap();
        assert_eq!(job.file, composed);
        let dir = store.job_dir(&job.id);
        assert!(dir.join(composed).is_file());
        assert!(dir.join(format!("{composed}.toml")).is_file());
        assert_eq!(std::fs::read_dir(&hot).unwrap().count(), 0, "both taken");
        // Composed model, decomposed sidecar.
        let src = drop_file(&hot, composed);
        std::fs::write(hot.join("cafe\u{301}.gcode.toml"), "copies = 2\n").unwrap();
        let second = store.admit(&src, &hot).unwrap();
        assert_eq!(second.file, composed);
        assert!(store
            .job_dir(&second.id)
            .join(format!("{composed}.toml"))
            .is_file());
        assert_eq!(std::fs::read_dir(&hot).unwrap().count(), 0, "both taken");
        drop(store);
        let store = Spool::open(&spool).unwrap();
        assert_eq!(store.get(&job.id).unwrap().file, composed);
    }

    #[test]
    fn restart_rules_and_gates_survive_reopen() {
        let (_tmp, hot, spool, mut store) = open_with_hot_folder();
        let a = store.admit(&drop_file(&hot, "a.stl"), &hot).unwrap().id;
        let b = store.admit(&drop_file(&hot, "b.stl"), &hot).unwrap().id;
        let c = store.admit(&drop_file(&hot, "c.stl"), &hot).unwrap().id;
        store.transition(&a, JobState::Preparing, None).unwrap();
        for (id, path) in [
            (
                &b,
                &[JobState::Preparing, JobState::Ready, JobState::Printing][..],
            ),
            (&c, &[JobState::Preparing, JobState::Ready]),
        ] {
            for &state in path {
                store.transition(id, state, None).unwrap();
            }
        }
        store.update(&b, |j| j.printer = Some("p1".into())).unwrap();
        drop(store);

        let mut store = Spool::open(&spool).unwrap();
        let changed = store.recover().unwrap();
        assert_eq!(changed.len(), 2);
        assert_eq!(store.get(&a).unwrap().state, JobState::Queued);
        assert_eq!(store.get(&b).unwrap().state, JobState::Interrupted);
        assert!(store.get(&b).unwrap().reason.is_some());
        assert_eq!(store.get(&c).unwrap().state, JobState::Ready);
        assert!(store.gate("p1").bed_not_cleared);
        assert!(!store.gate("p2").bed_not_cleared);

        drop(store);
        let store = Spool::open(&spool).unwrap();
        assert!(store.gate("p1").bed_not_cleared);
        let order: Vec<&str> = store.jobs().map(|j| j.id.as_str()).collect();
        assert_eq!(order, vec![a.as_str(), b.as_str(), c.as_str()]);
    }

    #[test]
    fn retry_only_from_finished_states() {
        let (_tmp, hot, _, mut store) = open_with_hot_folder();
        let a = store.admit(&drop_file(&hot, "a.stl"), &hot).unwrap().id;
        let err = store.retry(&a).unwrap_err().to_string();
        assert!(err.contains("is queued"), "{err}");
        store
            .transition(&a, JobState::Failed, Some("bad mesh".into()))
            .unwrap();
        let job = store.retry(&a).unwrap();
        assert_eq!(
            job.state,
            JobState::Queued,
            "nothing prepared: prepare again"
        );
        assert_eq!(job.reason, None);
        assert!(matches!(store.retry("nope"), Err(StoreError::NoSuchJob(_))));

        // Prepared, then cancelled in print: straight back to ready with its G-code.
        std::fs::write(store.job_dir(&a).join("a.stl.gcode"), b"G28\n").unwrap();
        store
            .update(&a, |j| j.slice_report = Some(Default::default()))
            .unwrap();
        store.transition(&a, JobState::Preparing, None).unwrap();
        store.transition(&a, JobState::Ready, None).unwrap();
        store.transition(&a, JobState::Printing, None).unwrap();
        store
            .transition(&a, JobState::Cancelled, Some("cancelled".into()))
            .unwrap();
        assert_eq!(store.retry(&a).unwrap().state, JobState::Ready);
    }

    #[test]
    fn orphaned_pickup_is_adopted() {
        let tmp = tempfile::tempdir().unwrap();
        let spool = tmp.path().join("spool");
        let dir = spool.join("jobs").join("0007-x_stl");
        std::fs::create_dir_all(&dir).unwrap();
        std::fs::write(dir.join("x.stl"), b"data").unwrap();
        std::fs::write(
            dir.join("origin.json"),
            serde_json::to_vec(
                &serde_json::json!({"id": "0007-x_stl", "file": "x.stl", "folder": "/hot"}),
            )
            .unwrap(),
        )
        .unwrap();
        let store = Spool::open(&spool).unwrap();
        let job = store.get("0007-x_stl").unwrap();
        assert_eq!(job.state, JobState::Queued);
        assert_eq!(job.file, "x.stl");
    }

    /// The store refuses every change the table refuses, leaves the job as it was (in
    /// memory and on disk), and `update` can never change a state behind the table's back.
    #[test]
    fn store_enforces_the_table() {
        let (_tmp, hot, spool, mut store) = open_with_hot_folder();
        let a = store.admit(&drop_file(&hot, "a.stl"), &hot).unwrap().id;
        let err = store.transition(&a, JobState::Done, None).unwrap_err();
        assert!(
            matches!(
                err,
                StoreError::IllegalTransition {
                    from: JobState::Queued,
                    to: JobState::Done,
                    ..
                }
            ),
            "{err}"
        );
        store.update(&a, |j| j.state = JobState::Done).unwrap();
        assert_eq!(store.get(&a).unwrap().state, JobState::Queued);
        drop(store);
        let reopened = Spool::open(&spool).unwrap();
        assert_eq!(reopened.get(&a).unwrap().state, JobState::Queued);
        assert_eq!(reopened.get(&a).unwrap().history.len(), 1);
    }

    proptest::proptest! {
        #![proptest_config(proptest::prelude::ProptestConfig::with_cases(48))]
        /// Random sequences of attempted changes (legal or not) and restarts on a real
        /// spool: a change succeeds exactly when the table allows it, the state on disk
        /// always equals the one in memory, every step of the recorded history is legal,
        /// and once done a job stays done.
        #[test]
        fn random_transitions_follow_the_table(
            steps in proptest::collection::vec((0usize..9, 0usize..8), 1..40)
        ) {
            let (_tmp, hot, spool, mut store) = open_with_hot_folder();
            let id = store.admit(&drop_file(&hot, "m.stl"), &hot).unwrap().id;
            let mut done = false;
            for (op, target) in steps {
                let before = store.get(&id).unwrap().state;
                if op == 8 {
                    // A restart: reopen from disk and apply the restart rules.
                    drop(store);
                    store = Spool::open(&spool).unwrap();
                    store.recover().unwrap();
                    let after = store.get(&id).unwrap().state;
                    proptest::prop_assert!(after == before || before.can_go_to(after));
                } else {
                    let to = JobState::ALL[target];
                    let result = store.transition(&id, to, None);
                    proptest::prop_assert_eq!(result.is_ok(), before.can_go_to(to));
                    let now = store.get(&id).unwrap().state;
                    proptest::prop_assert_eq!(now, if result.is_ok() { to } else { before });
                }
                let now = store.get(&id).unwrap().state;
                proptest::prop_assert!(!done || now == JobState::Done, "done is final");
                done |= now == JobState::Done;
                let on_disk: Job = serde_json::from_slice(
                    &std::fs::read(store.job_dir(&id).join("job.json")).unwrap(),
                )
                .unwrap();
                proptest::prop_assert_eq!(on_disk.state, now);
            }
            let history = &store.get(&id).unwrap().history;
            for pair in history.windows(2) {
                proptest::prop_assert!(pair[0].0.can_go_to(pair[1].0), "{:?}", pair);
            }
        }
    }

    /// A corrupt, oversized or lying job state fails that job only: the spool still
    /// opens, the other jobs load, and the directory stays as it was.
    #[test]
    fn unreadable_job_state_fails_that_job_only() {
        let (_tmp, hot, spool, mut store) = open_with_hot_folder();
        let ids: Vec<String> = ["a.stl", "b.stl", "c.stl", "d.stl"]
            .iter()
            .map(|f| store.admit(&drop_file(&hot, f), &hot).unwrap().id)
            .collect();
        drop(store);
        let state = |id: &str| spool.join("jobs").join(id).join("job.json");
        std::fs::write(state(&ids[0]), b"{\"id\": \"0001-a_stl\", trunc").unwrap();
        let evil = std::fs::read_to_string(state(&ids[1]))
            .unwrap()
            .replace(&ids[1], "../../../etc");
        std::fs::write(state(&ids[1]), evil).unwrap();
        std::fs::write(state(&ids[2]), vec![b' '; 2 << 20]).unwrap();

        let store = Spool::open(&spool).unwrap();
        for id in &ids[..3] {
            let job = store.get(id).unwrap_or_else(|| panic!("{id} is listed"));
            assert_eq!(job.state, JobState::Failed, "{id}");
            let reason = job.reason.as_deref().unwrap();
            assert!(
                reason.contains("job.json") && reason.contains("kept"),
                "{reason}"
            );
            // Clients see the reason: the files relative to the spool, never its path.
            assert!(
                reason.contains(&format!("jobs/{id}/job.json"))
                    && reason.contains(&format!("directory jobs/{id} is kept"))
                    && !reason.contains(&*spool.to_string_lossy()),
                "{reason}"
            );
        }
        assert_eq!(
            store.get(&ids[0]).unwrap().file,
            "a.stl",
            "from origin.json"
        );
        assert_eq!(store.get(&ids[3]).unwrap().state, JobState::Queued);
        assert!(std::fs::read(state(&ids[0])).unwrap().ends_with(b"trunc"));
    }

    /// A job directory copied within the spool (under any name) is not a second job, with
    /// its state written or not yet.
    #[test]
    fn a_copied_job_directory_is_not_a_new_job() {
        let (_tmp, hot, spool, mut store) = open_with_hot_folder();
        let a = store.admit(&drop_file(&hot, "a.stl"), &hot).unwrap().id;
        drop(store);
        let jobs = spool.join("jobs");
        let copy = |to: &str| {
            let status = std::process::Command::new("cp")
                .arg("-a")
                .arg(jobs.join(&a))
                .arg(jobs.join(to))
                .status()
                .unwrap();
            assert!(status.success());
        };
        copy("0042-a_stl");
        copy("0001-a_stl copy");
        copy("0043-a_stl");
        // A copy of a pick-up that never got its state (origin.json only).
        std::fs::remove_file(jobs.join("0043-a_stl/job.json")).unwrap();
        let store = Spool::open(&spool).unwrap();
        let listed: Vec<&str> = store.jobs().map(|j| j.id.as_str()).collect();
        assert_eq!(listed, vec![a.as_str()]);
    }

    /// A dropped model named like the job's own files is kept under another name: the
    /// model and the job's state both survive.
    #[test]
    fn a_model_named_like_crispens_files_overwrites_nothing() {
        let (_tmp, hot, spool, mut store) = open_with_hot_folder();
        let mut ids = Vec::new();
        for name in ["job.json", "origin.json"] {
            let job = store.admit(&drop_file(&hot, name), &hot).unwrap();
            assert_eq!(job.file, format!("model-{name}"));
            let dir = store.job_dir(&job.id);
            assert_eq!(
                std::fs::read(dir.join(&job.file)).unwrap(),
                b"solid x\nendsolid x\n"
            );
            ids.push(job.id);
        }
        drop(store);
        let store = Spool::open(&spool).unwrap();
        for id in &ids {
            assert_eq!(store.get(id).unwrap().state, JobState::Queued);
        }
    }

    /// A link in a hot folder is not followed: neither the model nor its sidecar.
    #[test]
    fn symbolic_links_are_not_picked_up() {
        let (tmp, hot, _, mut store) = open_with_hot_folder();
        let secret = tmp.path().join("secret.stl");
        std::fs::write(&secret, b"private").unwrap();
        std::os::unix::fs::symlink(&secret, hot.join("link.stl")).unwrap();
        let err = store.admit(&hot.join("link.stl"), &hot).unwrap_err();
        assert!(matches!(err, StoreError::NotAFile { .. }), "{err}");
        assert_eq!(store.jobs().count(), 0);

        let sidecar_target = tmp.path().join("other.toml");
        std::fs::write(&sidecar_target, "enhance = false\n").unwrap();
        std::os::unix::fs::symlink(&sidecar_target, hot.join("m.stl.toml")).unwrap();
        let job = store.admit(&drop_file(&hot, "m.stl"), &hot).unwrap();
        assert!(!store.job_dir(&job.id).join("m.stl.toml").exists());
    }

    /// A job whose directory was removed by hand fails (in memory) at its next change,
    /// so whoever waits for it moves on.
    #[test]
    fn a_removed_job_directory_fails_the_job() {
        let (_tmp, hot, _, mut store) = open_with_hot_folder();
        let a = store.admit(&drop_file(&hot, "a.stl"), &hot).unwrap().id;
        std::fs::remove_dir_all(store.job_dir(&a)).unwrap();
        let err = store.transition(&a, JobState::Preparing, None).unwrap_err();
        assert!(matches!(err, StoreError::DirectoryGone { .. }), "{err}");
        let job = store.get(&a).unwrap();
        assert_eq!(job.state, JobState::Failed);
        assert!(job.reason.as_deref().unwrap().contains("removed"));
    }

    /// Makes every later write of this job's state fail, as a full disk would: the
    /// temporary file's name is taken by a directory.
    fn block_writes(store: &Spool, id: &str) -> PathBuf {
        let blocker = crate::fsutil::temp_path(&store.job_dir(id).join("job.json"));
        std::fs::create_dir_all(&blocker).unwrap();
        blocker
    }

    /// A pick-up that cannot be completed leaves the model and its sidecar in the hot
    /// folder and no half job in the spool, now or after a restart.
    #[test]
    fn a_pickup_that_cannot_be_written_is_undone() {
        let (_tmp, hot, spool, mut store) = open_with_hot_folder();
        block_writes(&store, "0001-a_stl");
        let src = drop_file(&hot, "a.stl");
        std::fs::write(hot.join("a.stl.toml"), "enhance = false\n").unwrap();
        store.admit(&src, &hot).unwrap_err();
        assert_eq!(std::fs::read(&src).unwrap(), b"solid x\nendsolid x\n");
        assert!(hot.join("a.stl.toml").is_file());
        assert!(!store.job_dir("0001-a_stl").exists(), "no half job left");
        assert_eq!(store.jobs().count(), 0);
        drop(store);
        assert_eq!(Spool::open(&spool).unwrap().jobs().count(), 0);
    }

    /// A print that finished while its state could not be written counts as done at
    /// once (never retried, never offered again) and is written once writing works.
    #[test]
    fn an_outcome_that_cannot_be_written_is_kept_and_written_later() {
        let (_tmp, hot, _, mut store) = open_with_hot_folder();
        let a = store.admit(&drop_file(&hot, "a.stl"), &hot).unwrap().id;
        for state in [JobState::Preparing, JobState::Ready, JobState::Printing] {
            store.transition(&a, state, None).unwrap();
        }
        let blocker = block_writes(&store, &a);
        let job = store
            .record_outcome(&a, JobState::Done, None, |j| j.copies_done += 1)
            .unwrap();
        assert_eq!(job.state, JobState::Done);
        assert_eq!(store.get(&a).unwrap().state, JobState::Done);
        assert!(matches!(
            store.retry(&a),
            Err(StoreError::WrongState { .. })
        ));
        let on_disk = |store: &Spool| -> Job {
            serde_json::from_slice(&std::fs::read(store.job_dir(&a).join("job.json")).unwrap())
                .unwrap()
        };
        assert_eq!(on_disk(&store).state, JobState::Printing);
        assert_eq!(store.write_pending(), 1, "still not writable");
        std::fs::remove_dir(&blocker).unwrap();
        assert_eq!(store.write_pending(), 0);
        let written = on_disk(&store);
        assert_eq!((written.state, written.copies_done), (JobState::Done, 1));
    }

    /// A spool with `n` jobs that went to `state` one after another, `gap` seconds apart
    /// ending `ago` seconds before `now`; returns their ids, oldest first.
    fn finished_jobs(store: &mut Spool, hot: &Path, n: usize, state: JobState) -> Vec<String> {
        (0..n)
            .map(|i| {
                let id = store
                    .admit(&drop_file(hot, &format!("m{i}.stl")), hot)
                    .unwrap()
                    .id;
                store.transition(&id, state, Some("over".into())).unwrap();
                id
            })
            .collect()
    }

    fn retention(days: u64, jobs: usize) -> Retention {
        Retention {
            live_for: std::time::Duration::from_secs(days * 86_400),
            live_jobs: jobs,
            keep_for: None,
        }
    }

    /// `[history] keep_days`: a month of the history wholly older than it goes, its jobs'
    /// directories first, then its file; later months stay, and a reopened spool agrees.
    #[test]
    fn the_history_forgets_months_older_than_it_keeps() {
        let (_tmp, hot, spool, mut store) = open_with_hot_folder();
        let done = finished_jobs(&mut store, &hot, 2, JobState::Cancelled);
        let now = now_s();
        let old = now - 100.0 * 86_400.0;
        // The older job moves to the history a hundred days ago, the other now.
        assert_eq!(store.retire(&retention(7, 1), old).unwrap(), done[..1]);
        assert_eq!(store.retire(&retention(7, 0), now).unwrap(), done[1..]);
        let old_month = spool
            .join("history")
            .join(format!("{}.jsonl", history::month_of(old)));
        assert!(old_month.is_file());

        let keep = std::time::Duration::from_secs(30 * 86_400);
        assert_eq!(store.prune(keep, now).unwrap(), 1);
        assert!(!old_month.exists());
        assert!(!store.job_dir(&done[0]).exists());
        assert!(store.job_dir(&done[1]).join("m1.stl").is_file());
        assert_eq!(store.prune(keep, now).unwrap(), 0);
        let listed = |store: &Spool| -> Vec<String> {
            JobStore::history(store, None, 10, &Default::default())
                .unwrap()
                .jobs
                .into_iter()
                .map(|r| r.id)
                .collect()
        };
        assert_eq!(listed(&store), done[1..]);
        assert!(store.retired_job(&done[0]).unwrap().is_none());
        drop(store);
        let store = Spool::open(&spool).unwrap();
        assert_eq!(store.jobs().count(), 0);
        assert_eq!(listed(&store), done[1..]);
    }

    /// Finished jobs beyond the count, and all of them once old enough, leave the live
    /// jobs for the history; their directories stay; after a restart they are still in
    /// the history (once each) and not live; active jobs never move.
    #[test]
    fn finished_jobs_move_to_the_history_and_stay_there() {
        let (_tmp, hot, spool, mut store) = open_with_hot_folder();
        let done = finished_jobs(&mut store, &hot, 5, JobState::Cancelled);
        let active = store
            .admit(&drop_file(&hot, "active.stl"), &hot)
            .unwrap()
            .id;
        let now = now_s();
        let moved = store.retire(&retention(7, 3), now).unwrap();
        assert_eq!(moved, done[..2].to_vec(), "the oldest beyond three");
        assert!(store.get(&done[0]).is_none() && store.get(&done[2]).is_some());
        assert!(
            store.job_dir(&done[0]).join("m0.stl").is_file(),
            "files stay"
        );
        assert!(store.retire(&retention(7, 3), now).unwrap().is_empty());

        // A week later every finished job is old enough; the active one stays.
        let moved = store
            .retire(&retention(7, 3), now + 8.0 * 86_400.0)
            .unwrap();
        assert_eq!(moved, done[2..].to_vec());
        assert_eq!(
            store.jobs().map(|j| j.id.clone()).collect::<Vec<_>>(),
            std::slice::from_ref(&active)
        );

        drop(store);
        let store = Spool::open(&spool).unwrap();
        assert_eq!(store.jobs().count(), 1);
        let page = JobStore::history(&store, None, 100, &Default::default()).unwrap();
        let mut ids: Vec<String> = page.jobs.iter().map(|r| r.id.clone()).collect();
        ids.reverse();
        assert_eq!(ids, done);
        let retired = store
            .retired_job(&done[3])
            .unwrap()
            .expect("retired job found");
        assert_eq!(retired.record.state, JobState::Cancelled);
        assert_eq!(retired.record.dir, store.job_dir(&done[3]));
        assert_eq!(retired.job.unwrap().reason.as_deref(), Some("over"));
        assert!(store.retired_job(&active).unwrap().is_none());
        // The history is not the queue.
        let mut store = store;
        let err = store.retry(&done[3]).unwrap_err();
        assert!(matches!(err, StoreError::WrongState { .. }), "{err}");
        assert!(err.to_string().contains("history"), "{err}");
        // New jobs continue the numbering past the retired ones.
        let next = store.admit(&drop_file(&hot, "next.stl"), &hot).unwrap();
        assert_eq!(next.seq, 7);
    }

    /// A crash after the history was written but before the jobs left the live ones:
    /// after the restart each job is in the history once and not live. A crash in the
    /// middle of writing a line: that job was not retired, is live, and is retired again
    /// (once).
    #[test]
    fn a_crash_while_retiring_loses_nothing_and_shows_nothing_twice() {
        let (_tmp, hot, spool, mut store) = open_with_hot_folder();
        let done = finished_jobs(&mut store, &hot, 3, JobState::Failed);
        let now = now_s();
        // Written, then "killed" before the jobs left the live ones.
        let records: Vec<Retired> = done[..2]
            .iter()
            .map(|id| Retired::of(store.get(id).unwrap(), store.job_dir(id), now))
            .collect();
        store.history.append(&records, now).unwrap();
        drop(store);
        // And a line cut short, for the third.
        let file = spool
            .join("history")
            .join(format!("{}.jsonl", history::month_of(now)));
        let third = serde_json::to_string(&Retired::of(
            &Spool::open(&spool).unwrap().get(&done[2]).unwrap().clone(),
            PathBuf::new(),
            now,
        ))
        .unwrap();
        let mut f = std::fs::OpenOptions::new()
            .append(true)
            .open(&file)
            .unwrap();
        f.write_all(&third.as_bytes()[..third.len() / 2]).unwrap();
        drop(f);

        let mut store = Spool::open(&spool).unwrap();
        let live: Vec<String> = store.jobs().map(|j| j.id.clone()).collect();
        assert_eq!(live, [done[2].clone()], "the cut line's job is live");
        assert!(std::fs::read(&file).unwrap().ends_with(b"\n"), "mended");
        assert_eq!(
            store.retire(&retention(7, 0), now).unwrap(),
            [done[2].clone()]
        );
        drop(store);
        let store = Spool::open(&spool).unwrap();
        assert_eq!(store.jobs().count(), 0);
        let page = JobStore::history(&store, None, 100, &Default::default()).unwrap();
        let ids: Vec<&str> = page.jobs.iter().map(|r| r.id.as_str()).collect();
        assert_eq!(
            ids,
            [&done[2], &done[1], &done[0]],
            "each once, newest first"
        );
    }
}
