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
//! The embedded, single-host implementation of [`JobStore`](super::JobStore), the default,
//! is [`SpoolStore`], which makes the spool's calls that touch the disk on a blocking
//! thread.

use super::history::{self, HistoryFiles, Retention, Retired};
use super::pending::{Attempt, Pending};
use super::rules::io_err;
use super::{JobEdit, RetiredJob, StateFilter};
use crate::daemon::bed::{Bed, Why};
use crate::daemon::filament::Inventory;
use crate::daemon::job::{now_s, Job, JobState, PrinterGate, StoreError};
use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

mod job_dir;
mod store;
#[cfg(test)]
mod tests;

pub(crate) use job_dir::seq_of_id;
pub(super) use job_dir::{late_sidecar_name, model_name, move_file, regular_file_size, sidecar_of};
use job_dir::{load_job, read_origin, unreadable_job, Origin};
pub(crate) use store::SpoolStore;

/// The spool on disk plus its in-memory index. Not synchronised: only the store's task
/// uses it (see [`super::spawn`]). Holds the spool's lock (`<spool>/lock`, an flock) while
/// open, so two daemons never share a spool.
pub(crate) struct Spool {
    _lock: nix::fcntl::Flock<std::fs::File>,
    root: PathBuf,
    jobs: BTreeMap<String, Job>,
    gates: BTreeMap<String, PrinterGate>,
    /// The farm's spools, in `<spool>/filament.json`.
    inventory: Inventory,
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

/// The spools' file in the spool directory.
const INVENTORY_FILE: &str = "filament.json";

/// Writes `bytes` to `path` atomically and durably (see [`crate::fsutil`]).
pub(super) fn write_atomic(path: &Path, bytes: &[u8]) -> Result<(), StoreError> {
    Ok(crate::fsutil::write_atomic(path, bytes)?)
}

impl Spool {
    /// Opens (creating if needed) the spool at `root`, takes its lock, and loads every job
    /// in it. A job whose state cannot be read is loaded as failed, never stopping the
    /// others; a directory that is not a job of this spool (a copy of one, a stray
    /// folder) is left alone and logged.
    pub(crate) fn open(root: &Path) -> Result<Spool, StoreError> {
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
        let inventory_file = root.join(INVENTORY_FILE);
        let inventory = match std::fs::read(&inventory_file) {
            Ok(t) => serde_json::from_slice(&t).map_err(|e| StoreError::Corrupt {
                path: inventory_file.clone(),
                message: e.to_string(),
            })?,
            Err(e) if e.kind() == std::io::ErrorKind::NotFound => Inventory::default(),
            Err(e) => return Err(io_err(&inventory_file, "read")(e)),
        };
        let mut store = Spool {
            _lock: lock,
            root: root.to_path_buf(),
            jobs,
            gates,
            inventory,
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
    /// printer must have its bed cleared by a person, as must a printer whose eject
    /// sequence was running (it is never run again). Returns the ids of the jobs changed.
    pub(crate) fn recover(&mut self) -> Result<Vec<String>, StoreError> {
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
                        let gate = self
                            .gate_of(&p)
                            .after_print(&id, Bed::Waiting { why: None });
                        self.set_gate(&p, gate)?;
                    }
                    changed.push(id);
                }
                _ => {}
            }
        }
        // An eject sequence the daemon stopped in: never run again; a person looks.
        let ejecting: Vec<String> = self
            .gates
            .iter()
            .filter(|(_, g)| matches!(g.bed, Bed::Ejecting { .. }))
            .map(|(p, _)| p.clone())
            .collect();
        for p in ejecting {
            tracing::warn!(printer = %p, "the daemon stopped while the printer's eject sequence ran; its bed waits for a person");
            let gate = PrinterGate {
                bed: Bed::Waiting {
                    why: Some(Why::EjectInterrupted),
                },
                ..self.gate_of(&p)
            };
            self.set_gate(&p, gate)?;
        }
        Ok(changed)
    }

    pub(crate) fn job_dir(&self, id: &str) -> PathBuf {
        self.root.join("jobs").join(id)
    }

    pub(crate) fn get(&self, id: &str) -> Option<&Job> {
        self.jobs.get(id)
    }

    /// Jobs oldest first.
    pub(crate) fn jobs(&self) -> impl Iterator<Item = &Job> {
        let mut all: Vec<&Job> = self.jobs.values().collect();
        all.sort_by_key(|j| j.seq);
        all.into_iter()
    }

    #[cfg(test)]
    pub(crate) fn gate(&self, printer: &str) -> PrinterGate {
        self.gate_of(printer)
    }

    fn gate_of(&self, printer: &str) -> PrinterGate {
        self.gates.get(printer).cloned().unwrap_or_default()
    }

    /// Sets a printer's bed gate and writes it. When it cannot be written (a full disk),
    /// the rule of both stores: a bed that needs clearing (a print ended) is kept here and
    /// written later, so it still needs clearing after the outage; a clear is not done
    /// (the gate stays as it was, here as on disk) and the error says so.
    pub(crate) fn set_gate(&mut self, printer: &str, gate: PrinterGate) -> Result<(), StoreError> {
        let before = self.gates.insert(printer.to_string(), gate.clone());
        match self.save_gates() {
            // One file holds every gate: all kept ones are written with it.
            Ok(()) => {
                self.pending.gate_written(printer);
                Ok(())
            }
            Err(e) if gate.bed_not_cleared() => {
                tracing::error!(printer = %printer, error = %e, "cannot write the bed gate; kept here and written when possible");
                self.pending.keep_gate(printer, gate);
                Ok(())
            }
            Err(e) => {
                match before {
                    Some(before) => self.gates.insert(printer.to_string(), before),
                    None => self.gates.remove(printer),
                };
                Err(e)
            }
        }
    }

    fn save_gates(&self) -> Result<(), StoreError> {
        let bytes = serde_json::to_vec_pretty(&self.gates).expect("gates serialise");
        write_atomic(&self.root.join("printers.json"), &bytes)
    }

    /// Creates a job by moving `source` (a complete file in a hot folder) into a new job
    /// directory. The file is renamed, not copied, when spool and folder share a filesystem;
    /// otherwise it is copied, synced, and only then removed from the folder.
    pub(crate) fn admit(&mut self, source: &Path, folder: &Path) -> Result<Job, StoreError> {
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
                // Never a job: its number is the next pick-up's (the same file tried
                // again after a full disk keeps one id, not a new one each time).
                if !dir.exists() {
                    self.next_seq = seq;
                }
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
    pub(crate) fn late_sidecar(
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
    pub(crate) fn transition(
        &mut self,
        id: &str,
        state: JobState,
        reason: Option<String>,
    ) -> Result<Job, StoreError> {
        self.transition_with(id, state, reason, |_| {})
    }

    /// [`Spool::transition`] with other fields changed in the same write (the printer
    /// that claimed the job, the preparation's report).
    pub(crate) fn transition_with(
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
    pub(crate) fn record_outcome(
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
    pub(crate) fn write_pending(&mut self) -> usize {
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
    pub(crate) fn update(
        &mut self,
        id: &str,
        change: impl FnOnce(&mut Job),
    ) -> Result<Job, StoreError> {
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

    /// Makes the copies due of job `id` (see [`JobStore::make_copies`](super::JobStore::make_copies)). Each copy's
    /// directory is made whole under a name that is no job's (links to the job's files,
    /// its `job.json`), then renamed into place, so a crash leaves a copy whole or not at
    /// all; one already made (a crash before the job was marked) is not made again.
    pub(crate) fn make_copies(&mut self, id: &str) -> Result<Vec<String>, StoreError> {
        let job = self
            .jobs
            .get(id)
            .cloned()
            .ok_or_else(|| StoreError::NoSuchJob(id.to_string()))?;
        let due = job.copies_due();
        if due.is_empty() {
            return Ok(Vec::new());
        }
        let last = due.end - 1;
        let mut made = Vec::new();
        for n in due {
            let exists = self
                .jobs
                .values()
                .any(|j| j.copy.as_ref().is_some_and(|c| c.job == id && c.n == n));
            if exists {
                continue;
            }
            let seq = self.next_seq;
            let copy = job.copy_for(n, seq);
            let partial = self
                .root
                .join("jobs")
                .join(format!(".crispen-copy-{}", copy.id));
            let _ = std::fs::remove_dir_all(&partial);
            std::fs::create_dir_all(&partial)
                .map_err(io_err(&partial, "create a copy's directory"))?;
            job_dir::link_files(&self.job_dir(id), &partial)?;
            let bytes = serde_json::to_vec_pretty(&copy).expect("job serialises");
            write_atomic(&partial.join("job.json"), &bytes)?;
            let dir = self.job_dir(&copy.id);
            std::fs::rename(&partial, &dir)
                .map_err(io_err(&dir, "move a copy's directory into place"))?;
            self.next_seq += 1;
            made.push(copy.id.clone());
            self.jobs.insert(copy.id.clone(), copy);
        }
        self.update(id, |j| j.copies_made = last)?;
        Ok(made)
    }

    /// Puts a failed, cancelled or interrupted job back in the queue.
    pub(crate) fn retry(&mut self, id: &str) -> Result<Job, StoreError> {
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
    pub(crate) fn retire(
        &mut self,
        retention: &Retention,
        now: f64,
    ) -> Result<Vec<String>, StoreError> {
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
    pub(crate) fn prune(
        &mut self,
        keep_for: std::time::Duration,
        now: f64,
    ) -> Result<usize, StoreError> {
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
    pub(crate) fn retired_job(&self, id: &str) -> Result<Option<RetiredJob>, StoreError> {
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

impl Spool {
    pub(crate) fn jobs_dir(&self) -> PathBuf {
        self.root.join("jobs")
    }

    /// Makes `inventory` the spool's, written first when it differs (a refused edit of
    /// it changes nothing: see [`SpoolStore`]).
    fn set_inventory(&mut self, inventory: Inventory) -> Result<Inventory, StoreError> {
        if inventory != self.inventory {
            let bytes = serde_json::to_vec(&inventory).expect("the inventory serialises");
            write_atomic(&self.root.join(INVENTORY_FILE), &bytes)?;
            self.inventory = inventory;
        }
        Ok(self.inventory.clone())
    }

    /// [`Spool::transition_with`], first checked against `from` (the states the job must be
    /// in now), as [`JobStore::transition_with`](super::JobStore::transition_with) is.
    pub(crate) fn transition_from(
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

    pub(crate) fn unwritten(&self) -> usize {
        self.pending.len()
    }

    /// A page of the history (see [`JobStore::history`](super::JobStore::history)).
    pub(crate) fn history_page(
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
}
