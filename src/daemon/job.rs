//! The job spool: one directory per job under `<spool>/jobs/`, holding the dropped model
//! (moved in, never deleted), its sidecar, the prepared G-code and `job.json`, the job's
//! state. `job.json` is written atomically (temporary file, fsync, rename, fsync of the
//! directory) so a crash or power cut leaves either the old or the new state, never a torn
//! one. The printers' bed gates live in `<spool>/printers.json`, written the same way.
//! [`JobStore::open`] rebuilds everything from disk; [`JobStore::recover`] applies the
//! restart rules (preparing → queued, printing → interrupted).

use serde::{Deserialize, Serialize};
use std::collections::BTreeMap;
use std::io::Write;
use std::path::{Path, PathBuf};
use std::time::{SystemTime, UNIX_EPOCH};

#[derive(Debug, thiserror::Error)]
pub enum StoreError {
    #[error("spool {path}: {action}: {source}")]
    Io {
        path: PathBuf,
        action: &'static str,
        #[source]
        source: std::io::Error,
    },
    #[error("spool {path}: unreadable job state: {message} (hint: the job directory is kept; fix or move it away and restart)")]
    Corrupt { path: PathBuf, message: String },
    #[error("no job {0:?} (hint: `crispen status` lists the jobs)")]
    NoSuchJob(String),
    #[error("job {id} is {state}; {action} needs it to be {allowed}")]
    WrongState {
        id: String,
        state: JobState,
        action: &'static str,
        allowed: &'static str,
    },
}

#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum JobState {
    Queued,
    Preparing,
    Ready,
    Printing,
    Done,
    Failed,
    Cancelled,
    Interrupted,
}

impl JobState {
    pub fn name(self) -> &'static str {
        match self {
            JobState::Queued => "queued",
            JobState::Preparing => "preparing",
            JobState::Ready => "ready",
            JobState::Printing => "printing",
            JobState::Done => "done",
            JobState::Failed => "failed",
            JobState::Cancelled => "cancelled",
            JobState::Interrupted => "interrupted",
        }
    }
    /// Still has work ahead of it (the daemon is not idle while any job is active).
    pub fn is_active(self) -> bool {
        matches!(
            self,
            JobState::Queued | JobState::Preparing | JobState::Ready | JobState::Printing
        )
    }
}

impl std::fmt::Display for JobState {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(self.name())
    }
}

/// What a sidecar (`model.stl.toml`) may override for one model.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Sidecar {
    pub height_mm: Option<f64>,
    pub enhance: Option<bool>,
    pub strength: Option<toml::Value>,
    pub copies: Option<u32>,
    pub printer: Option<String>,
    /// Which of the model's axes points up: "z" or "y".
    pub up: Option<crate::slice::UpAxis>,
}

/// One job as persisted in `job.json`.
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct Job {
    pub id: String,
    /// Sequence number: the order jobs were picked up in (oldest first).
    pub seq: u64,
    /// The dropped file's name; the model is `<job dir>/<file>`.
    pub file: String,
    /// The hot folder it was dropped into.
    pub folder: PathBuf,
    pub state: JobState,
    /// Seconds since the epoch of each state change: (state, time).
    pub history: Vec<(JobState, f64)>,
    pub printer: Option<String>,
    pub reason: Option<String>,
    pub sidecar: Option<Sidecar>,
    /// Copies printed so far (a sidecar may ask for more than one).
    #[serde(default)]
    pub copies_done: u32,
    pub slice_report: Option<serde_json::Value>,
    pub print_report: Option<serde_json::Value>,
}

impl Job {
    /// A job just picked up: queued, with nothing prepared or printed yet.
    fn queued(id: String, seq: u64, file: String, folder: PathBuf) -> Job {
        Job {
            id,
            seq,
            file,
            folder,
            state: JobState::Queued,
            history: vec![(JobState::Queued, now_s())],
            printer: None,
            reason: None,
            sidecar: None,
            copies_done: 0,
            slice_report: None,
            print_report: None,
        }
    }
}

impl Job {
    pub fn copies_wanted(&self) -> u32 {
        self.sidecar
            .as_ref()
            .and_then(|s| s.copies)
            .unwrap_or(1)
            .max(1)
    }
}

pub fn now_s() -> f64 {
    SystemTime::now()
        .duration_since(UNIX_EPOCH)
        .map(|d| d.as_secs_f64())
        .unwrap_or(0.0)
}

/// Persisted per-printer state that must survive a restart.
#[derive(Debug, Clone, Default, Serialize, Deserialize, PartialEq)]
pub struct PrinterGate {
    /// A print ended (or was interrupted) and nobody has confirmed the bed is clear.
    pub bed_not_cleared: bool,
    pub last_job: Option<String>,
}

/// The spool on disk plus its in-memory index. Not synchronised: the daemon keeps it
/// behind one mutex.
pub struct JobStore {
    root: PathBuf,
    jobs: BTreeMap<String, Job>,
    gates: BTreeMap<String, PrinterGate>,
    next_seq: u64,
}

fn io_err(path: &Path, action: &'static str) -> impl FnOnce(std::io::Error) -> StoreError {
    let path = path.to_path_buf();
    move |source| StoreError::Io {
        path,
        action,
        source,
    }
}

/// Writes `bytes` to `path` atomically: temporary file, fsync, rename, fsync of the directory.
pub fn write_atomic(path: &Path, bytes: &[u8]) -> Result<(), StoreError> {
    let dir = path.parent().unwrap_or(Path::new("."));
    let tmp = path.with_extension("tmp");
    let mut f = std::fs::File::create(&tmp).map_err(io_err(&tmp, "create"))?;
    f.write_all(bytes).map_err(io_err(&tmp, "write"))?;
    f.sync_all().map_err(io_err(&tmp, "fsync"))?;
    drop(f);
    std::fs::rename(&tmp, path).map_err(io_err(path, "rename into place"))?;
    std::fs::File::open(dir)
        .and_then(|d| d.sync_all())
        .map_err(io_err(dir, "fsync directory"))?;
    Ok(())
}

impl JobStore {
    /// Opens (creating if needed) the spool at `root` and loads every job in it.
    pub fn open(root: &Path) -> Result<JobStore, StoreError> {
        let jobs_dir = root.join("jobs");
        std::fs::create_dir_all(&jobs_dir).map_err(io_err(&jobs_dir, "create"))?;
        let mut jobs = BTreeMap::new();
        let mut next_seq = 1;
        for entry in std::fs::read_dir(&jobs_dir).map_err(io_err(&jobs_dir, "list"))? {
            let entry = entry.map_err(io_err(&jobs_dir, "list"))?;
            let state_file = entry.path().join("job.json");
            let text = match std::fs::read(&state_file) {
                Ok(t) => t,
                // A job directory without state: created by a pick-up interrupted before
                // the state was written. Its files stay; the pick-up is redone below.
                Err(e) if e.kind() == std::io::ErrorKind::NotFound => continue,
                Err(e) => return Err(io_err(&state_file, "read")(e)),
            };
            let job: Job = serde_json::from_slice(&text).map_err(|e| StoreError::Corrupt {
                path: state_file.clone(),
                message: e.to_string(),
            })?;
            next_seq = next_seq.max(job.seq + 1);
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
        let mut store = JobStore {
            root: root.to_path_buf(),
            jobs,
            gates,
            next_seq,
        };
        store.adopt_orphans()?;
        Ok(store)
    }

    /// Job directories whose model was moved in but whose state was never written (a crash
    /// between the two steps) become queued jobs, so no dropped file is ever lost.
    fn adopt_orphans(&mut self) -> Result<(), StoreError> {
        let jobs_dir = self.root.join("jobs");
        let mut orphans = Vec::new();
        for entry in std::fs::read_dir(&jobs_dir).map_err(io_err(&jobs_dir, "list"))? {
            let entry = entry.map_err(io_err(&jobs_dir, "list"))?;
            let id = entry.file_name().to_string_lossy().into_owned();
            if self.jobs.contains_key(&id) || !entry.path().is_dir() {
                continue;
            }
            orphans.push((id, entry.path()));
        }
        for (id, dir) in orphans {
            let meta: Option<(String, PathBuf)> = std::fs::read(dir.join("origin.json"))
                .ok()
                .and_then(|b| serde_json::from_slice(&b).ok());
            let Some((file, folder)) = meta else { continue };
            if !dir.join(&file).exists() {
                continue;
            }
            let seq = self.next_seq;
            self.next_seq += 1;
            let job = Job::queued(id.clone(), seq, file, folder);
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
        self.gates.insert(printer.to_string(), gate);
        let bytes = serde_json::to_vec_pretty(&self.gates).expect("gates serialise");
        write_atomic(&self.root.join("printers.json"), &bytes)
    }

    /// Creates a job by moving `source` (a complete file in a hot folder) into a new job
    /// directory. The file is renamed, not copied, when spool and folder share a filesystem;
    /// otherwise it is copied, synced, and only then removed from the folder.
    pub fn admit(&mut self, source: &Path, folder: &Path) -> Result<Job, StoreError> {
        let file = source
            .file_name()
            .map(|n| n.to_string_lossy().into_owned())
            .unwrap_or_else(|| "model".into());
        let seq = self.next_seq;
        self.next_seq += 1;
        let stem: String = file
            .chars()
            .map(|c| {
                if c.is_ascii_alphanumeric() || c == '-' {
                    c
                } else {
                    '_'
                }
            })
            .take(40)
            .collect();
        let id = format!("{seq:04}-{stem}");
        let dir = self.job_dir(&id);
        std::fs::create_dir_all(&dir).map_err(io_err(&dir, "create job directory"))?;
        // Written before the move so a crash between the move and job.json still leaves
        // enough to rebuild the job (see adopt_orphans).
        let origin = serde_json::to_vec(&(&file, folder)).expect("origin serialises");
        write_atomic(&dir.join("origin.json"), &origin)?;
        move_file(source, &dir.join(&file))?;
        // The sidecar travels with its model.
        let mut sidecar_name = source.as_os_str().to_owned();
        sidecar_name.push(".toml");
        let sidecar_path = PathBuf::from(sidecar_name);
        if sidecar_path.is_file() {
            move_file(&sidecar_path, &dir.join(format!("{file}.toml")))?;
        }
        let job = Job::queued(id.clone(), seq, file, folder.to_path_buf());
        self.save(&job)?;
        self.jobs.insert(id, job.clone());
        Ok(job)
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
        self.update(id, |job| {
            job.state = state;
            job.history.push((state, now_s()));
            if reason.is_some() || state.is_active() {
                job.reason = reason;
            }
        })
    }

    /// Applies `change` to a job and persists it.
    pub fn update(&mut self, id: &str, change: impl FnOnce(&mut Job)) -> Result<Job, StoreError> {
        let mut job = self
            .jobs
            .get(id)
            .cloned()
            .ok_or_else(|| StoreError::NoSuchJob(id.to_string()))?;
        change(&mut job);
        self.save(&job)?;
        self.jobs.insert(id.to_string(), job.clone());
        Ok(job)
    }

    /// Puts a failed, cancelled or interrupted job back in the queue.
    pub fn retry(&mut self, id: &str) -> Result<Job, StoreError> {
        let job = self
            .jobs
            .get(id)
            .ok_or_else(|| StoreError::NoSuchJob(id.to_string()))?;
        if !matches!(
            job.state,
            JobState::Failed | JobState::Cancelled | JobState::Interrupted
        ) {
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
        let prepared = job.slice_report.is_some()
            && self
                .job_dir(id)
                .join(format!("{}.gcode", job.file))
                .is_file();
        let state = if prepared {
            JobState::Ready
        } else {
            JobState::Queued
        };
        self.update(id, |j| {
            j.state = state;
            j.history.push((state, now_s()));
            j.reason = None;
            j.printer = None;
        })
    }
}

fn move_file(from: &Path, to: &Path) -> Result<(), StoreError> {
    match std::fs::rename(from, to) {
        Ok(()) => Ok(()),
        Err(e) if e.raw_os_error() == Some(nix::libc::EXDEV) => {
            std::fs::copy(from, to).map_err(io_err(to, "copy model into spool"))?;
            std::fs::File::open(to)
                .and_then(|f| f.sync_all())
                .map_err(io_err(to, "fsync"))?;
            std::fs::remove_file(from).map_err(io_err(from, "remove after copying into spool"))
        }
        Err(e) => Err(io_err(from, "move into spool")(e)),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn drop_file(dir: &Path, name: &str) -> PathBuf {
        let p = dir.join(name);
        std::fs::write(&p, b"solid x\nendsolid x\n").unwrap();
        p
    }

    #[test]
    fn admit_moves_file_and_persists_state() {
        let tmp = tempfile::tempdir().unwrap();
        let hot = tmp.path().join("hot");
        std::fs::create_dir(&hot).unwrap();
        let src = drop_file(&hot, "a b.stl");
        std::fs::write(hot.join("a b.stl.toml"), "enhance = false\n").unwrap();
        let mut store = JobStore::open(&tmp.path().join("spool")).unwrap();
        let job = store.admit(&src, &hot).unwrap();
        assert!(!src.exists());
        assert!(store.job_dir(&job.id).join("a b.stl").exists());
        assert!(store.job_dir(&job.id).join("a b.stl.toml").exists());
        assert!(!hot.join("a b.stl.toml").exists());
        assert_eq!(job.state, JobState::Queued);

        let store2 = JobStore::open(&tmp.path().join("spool")).unwrap();
        let again = store2.get(&job.id).unwrap();
        assert_eq!(again.file, "a b.stl");
        assert_eq!(again.state, JobState::Queued);
    }

    #[test]
    fn restart_rules_and_gates_survive_reopen() {
        let tmp = tempfile::tempdir().unwrap();
        let hot = tmp.path().join("hot");
        std::fs::create_dir(&hot).unwrap();
        let spool = tmp.path().join("spool");
        let mut store = JobStore::open(&spool).unwrap();
        let a = store.admit(&drop_file(&hot, "a.stl"), &hot).unwrap().id;
        let b = store.admit(&drop_file(&hot, "b.stl"), &hot).unwrap().id;
        let c = store.admit(&drop_file(&hot, "c.stl"), &hot).unwrap().id;
        store.transition(&a, JobState::Preparing, None).unwrap();
        store.transition(&b, JobState::Printing, None).unwrap();
        store.update(&b, |j| j.printer = Some("p1".into())).unwrap();
        store.transition(&c, JobState::Ready, None).unwrap();
        drop(store);

        let mut store = JobStore::open(&spool).unwrap();
        let changed = store.recover().unwrap();
        assert_eq!(changed.len(), 2);
        assert_eq!(store.get(&a).unwrap().state, JobState::Queued);
        assert_eq!(store.get(&b).unwrap().state, JobState::Interrupted);
        assert!(store.get(&b).unwrap().reason.is_some());
        assert_eq!(store.get(&c).unwrap().state, JobState::Ready);
        assert!(store.gate("p1").bed_not_cleared);
        assert!(!store.gate("p2").bed_not_cleared);

        let store = JobStore::open(&spool).unwrap();
        assert!(store.gate("p1").bed_not_cleared);
        let order: Vec<&str> = store.jobs().map(|j| j.id.as_str()).collect();
        assert_eq!(order, vec![a.as_str(), b.as_str(), c.as_str()]);
    }

    #[test]
    fn retry_only_from_finished_states() {
        let tmp = tempfile::tempdir().unwrap();
        let hot = tmp.path().join("hot");
        std::fs::create_dir(&hot).unwrap();
        let mut store = JobStore::open(&tmp.path().join("spool")).unwrap();
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
            .update(&a, |j| j.slice_report = Some(serde_json::json!({})))
            .unwrap();
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
            serde_json::to_vec(&("x.stl", "/hot")).unwrap(),
        )
        .unwrap();
        let store = JobStore::open(&spool).unwrap();
        let job = store.get("0007-x_stl").unwrap();
        assert_eq!(job.state, JobState::Queued);
        assert_eq!(job.file, "x.stl");
    }
}
