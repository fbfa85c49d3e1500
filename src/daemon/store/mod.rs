//! The job store as one owner: a single task ([`start`]) owns the store (the embedded
//! [`spool::Spool`] today, a database tomorrow) and is the only place a job or a bed gate
//! changes. Everyone else holds a cheap, cloneable [`StoreHandle`] and sends it requests
//! (an mpsc message with a oneshot reply). The task runs each batch of requests on a
//! blocking thread (`spawn_blocking`): the store's disk writes never hold up the async
//! runtime, and no lock is held across them, because nothing else can reach the store.
//! The daemon runs the task in its supervised set: a panic (in the store, or in a
//! request's edit) is not caught, so the daemon stops rather than go on with a change
//! done halfway.
//!
//! What follows from a job's change is the task's too: its `job state` log line, the
//! counts by state and the metrics' tally, published in the same snapshot as the change
//! ([`Snapshot::counts`], [`Snapshot::tally`]). They are worked out from the difference
//! between each job's record and the one published before, so a change another host
//! made (taken in by a resync) is counted like one of this host's.
//!
//! Readers do not queue behind writes: after every batch the task publishes an immutable
//! [`Snapshot`] (a `watch` of an `Arc`), which status, HTTP, metrics and the printers'
//! glances read for free. A reply is sent only after the snapshot holding its change is
//! published, so a caller always reads its own writes.
//!
//! Checks that must not be split from their change (claiming a ready job, cancelling a job
//! that has not started printing, clearing a bed, a late sidecar) are single requests, so
//! no other change can come between. Legal state changes stay one table,
//! [`JobState::can_go_to`], applied by [`Job::apply_transition`] inside the store.
//!
//! Finished jobs leave the live snapshot for the [`history`]: beyond `live_jobs` at the
//! change that made one too many, older than `live_for` at a round every
//! [`RETIRE_EVERY`]; the task retires them in batches on its blocking thread, so what
//! every reader pays for follows the jobs at work, not the farm's past. The snapshot also
//! keeps what would otherwise be looked up on disk at every glance (which pictures a job
//! has), worked out once when the job changes.
//!
//! [`postgres`] is the second store: the farm's queue in PostgreSQL, shared by several
//! hosts. Other hosts change jobs too, so its store reloads them on [`StoreHandle::resync`]
//! and the snapshot is rebuilt; a state check (`from`) is made inside the store, where the
//! database row is locked, never against a snapshot that may be stale.

pub mod history;
pub mod pending;
pub mod postgres;
pub mod spool;
pub mod stats;

pub use history::Retention;

use super::job::{ForMachine, Job, JobState, PrinterGate, StoreError};
use serde::{Deserialize, Serialize};
use std::collections::{BTreeMap, HashMap};
use std::path::{Path, PathBuf};
use std::sync::Arc;
use tokio::sync::{mpsc, oneshot, watch};

/// A change to a job's other fields, made in the same write as its state change.
pub type JobEdit = Box<dyn FnOnce(&mut Job) + Send>;

/// Where jobs are kept. Every method may block (disk, network): the store's task calls
/// them on a blocking thread, one at a time. Opening (and taking whatever lock keeps two
/// daemons apart) is each implementation's own constructor.
pub trait JobStore: Send + 'static {
    /// The local directory holding one directory per job (model, sidecar, G-code, report).
    fn jobs_dir(&self) -> PathBuf;
    /// Every job, oldest first.
    fn jobs(&self) -> Vec<Job>;
    fn job(&self, id: &str) -> Option<Job>;
    fn gates(&self) -> BTreeMap<String, PrinterGate>;
    /// Restart rules: preparing → queued, printing → interrupted (and its bed not cleared).
    /// Returns the ids changed.
    fn recover(&mut self) -> Result<Vec<String>, StoreError>;
    /// Makes a complete file of a hot folder a queued job, or leaves it where it was.
    /// `printers` is the folder's rule, for stores whose other hosts lack the folder.
    fn admit(
        &mut self,
        source: &Path,
        folder: &Path,
        printers: &[String],
    ) -> Result<Job, StoreError>;
    /// Takes a sidecar that arrived after its model: as the job's sidecar when `applies`,
    /// else kept aside. Returns `applies`.
    fn late_sidecar(&mut self, id: &str, sidecar: &Path, applies: bool)
        -> Result<bool, StoreError>;
    /// Changes a job's state (checked against the table, and first against `from`, the
    /// states it must be in now) with `also`'s changes, persisted.
    fn transition_with(
        &mut self,
        id: &str,
        from: Option<StateFilter>,
        state: JobState,
        reason: Option<String>,
        also: JobEdit,
    ) -> Result<Job, StoreError>;
    /// A state change that has already happened (a print ended): kept even when it cannot
    /// be persisted now, and persisted by [`JobStore::write_pending`] later.
    fn record_outcome(
        &mut self,
        id: &str,
        state: JobState,
        reason: Option<String>,
        also: JobEdit,
    ) -> Result<Job, StoreError>;
    /// Changes a job's other fields; never its state.
    fn update(&mut self, id: &str, change: JobEdit) -> Result<Job, StoreError>;
    /// Puts a failed, cancelled or interrupted job back (ready if its G-code is kept).
    fn retry(&mut self, id: &str) -> Result<Job, StoreError>;
    fn set_gate(&mut self, printer: &str, gate: PrinterGate) -> Result<(), StoreError>;
    /// Persists what [`JobStore::record_outcome`] and [`JobStore::set_gate`] could not;
    /// returns how many remain.
    fn write_pending(&mut self) -> usize;
    /// How many recorded outcomes (and bed gates) wait to be persisted.
    fn unwritten(&self) -> usize;
    /// Takes in changes made elsewhere (other hosts of a shared store); true when it did,
    /// so the snapshot must be rebuilt. A store only this daemon changes has none.
    fn resync(&mut self) -> bool {
        false
    }
    /// Moves the finished jobs `retention` no longer keeps live (by
    /// [`history::to_retire`]) to the history; returns their ids, at most
    /// [`history::BATCH`]. `now`: seconds since the epoch.
    fn retire(&mut self, retention: &Retention, now: f64) -> Result<Vec<String>, StoreError>;
    /// A job in the history; None when there is no such retired job.
    fn retired(&self, id: &str) -> Result<Option<RetiredJob>, StoreError>;
    /// A page of the history, newest first, of jobs with a sequence number below `before`
    /// that `filter` takes.
    fn history(
        &self,
        before: Option<u64>,
        limit: usize,
        filter: &history::Filter,
    ) -> Result<history::Page, StoreError>;
    /// Forgets the jobs the history has kept longer than `keep_for` before `now` (their
    /// records and files); returns how many. See [`Retention::keep_for`].
    fn prune(&mut self, keep_for: std::time::Duration, now: f64) -> Result<usize, StoreError>;
    /// Every job retired at or after `since` (seconds since the epoch), in no particular
    /// order; a job may come twice (the statistics count it once).
    fn each_retired(
        &self,
        since: f64,
        visit: &mut dyn FnMut(history::Retired),
    ) -> Result<(), StoreError>;
}

/// A job in the history: its record, and its whole state where it can still be read.
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct RetiredJob {
    pub record: history::Retired,
    pub job: Option<Job>,
}

/// What a change of a retired job meets: the history is not the queue.
pub fn retired_refusal(id: &str, state: JobState, action: &'static str) -> StoreError {
    StoreError::WrongState {
        id: id.to_string(),
        state,
        action,
        allowed: "still in the queue (it has moved to the history, `crispen history`; drop its model into a hot folder again to print it again)",
    }
}

/// The names of the G-code files preparation made for a job: one per machine, or, for a
/// job prepared before machines existed (sliced for an Ultimaker 2), `<file>.gcode`.
pub fn gcode_files(job: &Job) -> Vec<String> {
    if job.machines.is_empty() {
        return vec![format!("{}.gcode", job.file)];
    }
    job.machines
        .values()
        .filter_map(|m| match m {
            ForMachine::Gcode(file) => Some(file.clone()),
            ForMachine::Refused(_) => None,
        })
        .collect()
}

/// Whether a job that is retried keeps its G-code (and goes back to ready) or is prepared
/// again: it was prepared, and one of its G-code files is still there (`has`: in its
/// directory, or in the farm database). The one rule of both stores.
pub fn prepared(job: &Job, has: impl Fn(&str) -> bool) -> bool {
    job.slice_report.is_some() && gcode_files(job).iter().any(|f| has(f))
}

impl From<crate::fsutil::WriteError> for StoreError {
    fn from(e: crate::fsutil::WriteError) -> StoreError {
        StoreError::Io {
            path: e.path,
            action: e.step,
            source: e.source,
        }
    }
}

/// Checks that a job is in one of the states `from` (when given).
pub fn check_from(job: &Job, from: Option<StateFilter>) -> Result<(), StoreError> {
    match from {
        Some(from) if !from.contains(&job.state) => Err(StoreError::StateChanged {
            id: job.id.clone(),
            state: job.state,
            expected: names(from),
        }),
        _ => Ok(()),
    }
}

/// An immutable picture of every live job and bed gate, as of the store's last change.
/// Cheap to publish: each job is shared (`Arc`), and the index is shared until a job
/// comes or goes.
#[derive(Clone, Debug, Default)]
pub struct Snapshot {
    /// Oldest first.
    jobs: Vec<Arc<Live>>,
    index: Arc<HashMap<String, usize>>,
    gates: BTreeMap<String, PrinterGate>,
    jobs_dir: PathBuf,
    /// Outcomes recorded but not yet persisted (a full disk).
    unwritten: usize,
    /// What jobs did since the task started, counted as each change is published.
    counted: Arc<Counted>,
}

/// How many jobs reached each state since the store's task started (by [`JobState::ALL`]'s
/// order): `/metrics`, and `--exit-when-idle` (which needs a job to have finished).
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct JobCounts([u64; JobState::ALL.len()]);

impl JobCounts {
    fn count(&mut self, state: JobState) {
        if let Some(i) = JobState::ALL.iter().position(|s| *s == state) {
            self.0[i] += 1;
        }
    }

    /// Changes into `state`.
    pub fn into_state(&self, state: JobState) -> u64 {
        JobState::ALL
            .iter()
            .position(|s| *s == state)
            .map_or(0, |i| self.0[i])
    }

    /// Changes into a state without work ahead (a job finished, for now or for good).
    pub fn finished(&self) -> u64 {
        JobState::ALL
            .iter()
            .filter(|s| !s.is_active())
            .map(|s| self.into_state(*s))
            .sum()
    }
}

/// What follows from a job's state change besides the change itself: its log line, the
/// counts and the metrics' tally. Kept by the store's task alone and published in its
/// snapshot with the change, so a reader never sees one without the other. Counted from
/// the difference between a job's record and the one published before (its new entries in
/// `history`), whoever made the change: a request of this host, or another host of a
/// shared farm whose change a resync took in.
#[derive(Debug, Clone, Default)]
struct Counted {
    states: JobCounts,
    tally: stats::Tally,
}

impl Counted {
    /// Announces the state changes `job` made since `before` (the record last published;
    /// None: a job new to the snapshot, whose every change is new here).
    fn changes(&mut self, before: Option<&Job>, job: &Job) {
        let seen = before.map_or(0, |b| b.history.len());
        let n = job.history.len();
        for k in seen..n {
            let state = job.history[k].0;
            // The job's reason is that of its latest change only.
            let reason = (k + 1 == n).then_some(job.reason.as_deref()).flatten();
            tracing::info!(
                job = %job.id,
                printer = job.printer.as_deref(),
                state = state.name(),
                reason,
                "job state"
            );
            self.states.count(state);
            self.tally.count(job, k);
        }
    }
}

/// A live job and what is known of its files.
#[derive(Debug)]
struct Live {
    job: Job,
    /// Which of [`PICTURES`] its directory holds (bit i for `PICTURES[i]`).
    pictures: u8,
}

/// The pictures a job's directory may hold (see `crate::preview`).
pub const PICTURES: [&str; 4] = [
    crate::preview::BEFORE_PNG,
    crate::preview::AFTER_PNG,
    crate::preview::DISPLACEMENT_PNG,
    crate::preview::walls::WALLS_PNG,
];

impl Live {
    /// Looks at the job's pictures, unless `before` (the job as last seen, when the whole
    /// snapshot is rebuilt after other hosts' changes) is the same job in the same state:
    /// pictures are made while a job prepares, so a job whose history has not moved has
    /// the ones it had.
    fn of(job: Job, dir: &Path, before: Option<&Live>) -> Live {
        let pictures = match before {
            Some(b) if b.job.history.len() == job.history.len() && b.job.state == job.state => {
                b.pictures
            }
            _ => PICTURES
                .iter()
                .enumerate()
                .filter(|(_, name)| dir.join(name).is_file())
                .fold(0, |bits, (i, _)| bits | 1 << i),
        };
        Live { job, pictures }
    }
}

impl Snapshot {
    /// The store's jobs as they are now. `before`: the snapshot published last (None: the
    /// first, when the task starts: nothing is a change yet); what changed since is counted.
    fn of(store: &dyn JobStore, before: Option<&Snapshot>) -> Snapshot {
        let jobs_dir = store.jobs_dir();
        let mut counted = before.map(|b| Arc::clone(&b.counted)).unwrap_or_default();
        let jobs: Vec<Arc<Live>> = store
            .jobs()
            .into_iter()
            .map(|j| {
                let old = before.and_then(|b| b.live(&j.id));
                if before.is_some() {
                    Arc::make_mut(&mut counted).changes(old.map(|l| &l.job), &j);
                }
                let dir = jobs_dir.join(&j.id);
                Arc::new(Live::of(j, &dir, old))
            })
            .collect();
        let index = jobs
            .iter()
            .enumerate()
            .map(|(i, j)| (j.job.id.clone(), i))
            .collect();
        Snapshot {
            jobs,
            index: Arc::new(index),
            gates: store.gates(),
            jobs_dir,
            unwritten: store.unwritten(),
            counted,
        }
    }

    fn live(&self, id: &str) -> Option<&Live> {
        self.index.get(id).map(|&i| &*self.jobs[i])
    }

    pub fn get(&self, id: &str) -> Option<&Job> {
        self.live(id).map(|l| &l.job)
    }

    /// Jobs oldest first.
    pub fn jobs(&self) -> impl Iterator<Item = &Job> {
        self.jobs.iter().map(|j| &j.job)
    }

    /// The pictures job `id`'s directory holds, of [`PICTURES`] (as of its last change).
    pub fn pictures(&self, id: &str) -> Vec<&'static str> {
        let bits = self.live(id).map_or(0, |l| l.pictures);
        PICTURES
            .iter()
            .enumerate()
            .filter(|(i, _)| bits & (1 << i) != 0)
            .map(|(_, p)| *p)
            .collect()
    }

    pub fn gate(&self, printer: &str) -> PrinterGate {
        self.gates.get(printer).cloned().unwrap_or_default()
    }

    pub fn job_dir(&self, id: &str) -> PathBuf {
        self.jobs_dir.join(id)
    }

    /// Outcomes that happened but could not be persisted yet.
    pub fn unwritten(&self) -> usize {
        self.unwritten
    }

    /// How many jobs reached each state since the store's task started.
    pub fn counts(&self) -> JobCounts {
        self.counted.states
    }

    /// The metrics' counters by printer since the store's task started.
    pub fn tally(&self) -> &stats::Tally {
        &self.counted.tally
    }

    /// No job has work ahead of it.
    pub fn idle(&self) -> bool {
        !self.jobs().any(|j| j.state.is_active())
    }

    /// Finished jobs (done, failed, cancelled) still live.
    pub fn finished_live(&self) -> usize {
        self.jobs()
            .filter(|j| history::is_finished(j.state))
            .count()
    }

    /// Takes the store's current record of `id` (after a change, successful or not: a
    /// failed change may still have failed the job, e.g. when its directory is gone), and
    /// announces what it changed.
    fn refresh(&mut self, store: &dyn JobStore, id: &str) {
        let Some(job) = store.job(id) else { return };
        let before = self.index.get(id).map(|&i| Arc::clone(&self.jobs[i]));
        Arc::make_mut(&mut self.counted).changes(before.as_ref().map(|l| &l.job), &job);
        let dir = self.job_dir(id);
        match self.index.get(id) {
            // Looked at again at every change: a few stats per change, none per glance.
            Some(&i) => self.jobs[i] = Arc::new(Live::of(job, &dir, None)),
            // New jobs have the highest sequence number: appending keeps the order.
            None => {
                Arc::make_mut(&mut self.index).insert(job.id.clone(), self.jobs.len());
                self.jobs.push(Arc::new(Live::of(job, &dir, None)));
            }
        }
    }

    /// Drops jobs that moved to the history.
    fn remove(&mut self, ids: &[String]) {
        if ids.is_empty() {
            return;
        }
        let gone: std::collections::HashSet<&str> = ids.iter().map(String::as_str).collect();
        self.jobs.retain(|l| !gone.contains(l.job.id.as_str()));
        self.index = Arc::new(
            self.jobs
                .iter()
                .enumerate()
                .map(|(i, l)| (l.job.id.clone(), i))
                .collect(),
        );
    }
}

type Reply<T> = oneshot::Sender<Result<T, StoreError>>;

/// What a job must be in for a change to go ahead; checked inside the store's task, so
/// nothing can change the job between the check and the change.
pub type StateFilter = &'static [JobState];

/// The messages the store's task serves.
enum Request {
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
        also: JobEdit,
        reply: Reply<Job>,
    },
    Outcome {
        id: String,
        to: JobState,
        reason: Option<String>,
        also: JobEdit,
        reply: Reply<Job>,
    },
    Update {
        id: String,
        change: JobEdit,
        reply: Reply<Job>,
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
    SetGate {
        printer: String,
        gate: PrinterGate,
        reply: Reply<()>,
    },
    ClearGate {
        printer: String,
        reply: Reply<bool>,
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
    Stats {
        period: stats::Period,
        printers: Vec<String>,
        folders: Vec<String>,
        now: f64,
        reply: Reply<stats::Stats>,
    },
}

/// What became of a sidecar that arrived after its model had become a job.
#[derive(Debug, Clone, PartialEq)]
pub struct LateSidecar {
    pub job: String,
    /// The job's state when the sidecar arrived.
    pub state: JobState,
    /// Taken as the job's sidecar (it had not started preparing); else kept aside.
    pub applies: bool,
}

/// A reply waiting for the snapshot that shows its change to be published.
type Delivery = Box<dyn FnOnce() + Send>;

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
    fn serve(
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
                let result = store.admit(&source, &folder, &printers);
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
            } => {
                let found = view
                    .jobs()
                    .filter(|j| {
                        j.folder == folder && crate::daemon::hotfolder::same_name(&j.file, &file)
                    })
                    .last()
                    .map(|j| (j.id.clone(), j.state));
                let result = match found {
                    None => Ok(None),
                    Some((id, state)) => store
                        .late_sidecar(&id, &sidecar, state == JobState::Queued)
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
            Request::Transition {
                id,
                from,
                to,
                reason,
                also,
                reply,
            } => {
                let reason = reason.map(|r| for_clients(&r, store));
                let result = store.transition_with(&id, from, to, reason, also);
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
                let result = store.record_outcome(&id, to, reason, also);
                view.refresh(store, &id);
                view.unwritten = store.unwritten();
                (deliver(reply, result), true)
            }
            Request::Update { id, change, reply } => {
                let result = store.update(&id, change);
                view.refresh(store, &id);
                (deliver(reply, result), true)
            }
            Request::Retry { id, reply } => {
                let result = store.retry(&id);
                view.refresh(store, &id);
                (deliver(reply, result), true)
            }
            Request::Claim {
                printer,
                eligible,
                reply,
            } => {
                let (result, tried) = claim(store, view, &printer, &*eligible);
                (deliver(reply, result), tried)
            }
            Request::SetGate {
                printer,
                gate,
                reply,
            } => {
                let result = store.set_gate(&printer, gate);
                view.gates = store.gates();
                view.unwritten = store.unwritten();
                (deliver(reply, result), true)
            }
            Request::ClearGate { printer, reply } => {
                let gate = view.gate(&printer);
                let result = if gate.bed_not_cleared {
                    let cleared = PrinterGate {
                        bed_not_cleared: false,
                        last_job: gate.last_job,
                    };
                    store.set_gate(&printer, cleared).map(|()| true)
                } else {
                    Ok(false)
                };
                if let Ok(true) = result {
                    tracing::info!(printer = %printer, "bed cleared");
                }
                view.gates = store.gates();
                view.unwritten = store.unwritten();
                let changed = !matches!(result, Ok(false));
                (deliver(reply, result), changed)
            }
            Request::Resync { reply } => {
                let changed = store.resync();
                if changed {
                    *view = Snapshot::of(store, Some(view));
                }
                (deliver(reply, Ok(changed)), changed)
            }
            Request::Retire { now, reply } => {
                let retired = round(store, view, retention, now);
                let changed = retired.as_ref().is_ok_and(|ids| !ids.is_empty());
                (deliver(reply, retired), changed)
            }
            Request::Retired { id, reply } => (deliver(reply, store.retired(&id)), false),
            Request::History {
                before,
                limit,
                filter,
                reply,
            } => (deliver(reply, store.history(before, limit, &filter)), false),
            Request::Stats {
                period,
                printers,
                folders,
                now,
                reply,
            } => {
                let mut builder = stats::Builder::new(period, &printers, &folders);
                // A job retired before the period began ended before it too.
                let result = store
                    .each_retired(period.from, &mut |r| builder.add(&r))
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
            Request::WritePending { reply } => {
                // Only the persisted copy changes: the view already shows these outcomes.
                let left = store.write_pending();
                let changed = view.unwritten != left;
                view.unwritten = left;
                (deliver(reply, Ok(left)), changed)
            }
        }
    }
}

fn names(states: StateFilter) -> String {
    let names: Vec<&str> = states.iter().map(|s| s.name()).collect();
    names.join(" or ")
}

/// Takes the oldest ready job `eligible` for `printer`, marking it printing. A job that
/// fails as it is claimed (its directory is gone), or that another host took first, is
/// passed over for the next one. Also says whether any job was tried (and may have
/// changed).
fn claim(
    store: &mut dyn JobStore,
    view: &mut Snapshot,
    printer: &str,
    eligible: &dyn Fn(&Job) -> bool,
) -> (Result<Option<Job>, StoreError>, bool) {
    let candidates: Vec<String> = view
        .jobs()
        .filter(|j| j.state == JobState::Ready && eligible(j))
        .map(|j| j.id.clone())
        .collect();
    let tried = !candidates.is_empty();
    let result = (|| {
        for id in candidates {
            let name = printer.to_string();
            let claimed = store.transition_with(
                &id,
                Some(&[JobState::Ready]),
                JobState::Printing,
                None,
                Box::new(move |j| j.printer = Some(name)),
            );
            view.refresh(store, &id);
            match claimed {
                Ok(job) => return Ok(Some(job)),
                Err(StoreError::StateChanged { .. } | StoreError::LostClaim { .. }) => continue,
                Err(_) if view.get(&id).is_some_and(|j| j.state == JobState::Failed) => continue,
                Err(e) => return Err(e),
            }
        }
        Ok(None)
    })();
    (result, tried)
}

/// Moves what `retention` no longer keeps live to the history and out of the snapshot,
/// one batch.
fn retire(
    store: &mut dyn JobStore,
    view: &mut Snapshot,
    retention: &Retention,
    now: f64,
) -> Result<Vec<String>, StoreError> {
    let ids = store.retire(retention, now)?;
    if !ids.is_empty() {
        tracing::info!(jobs = ids.len(), first = %ids[0], "finished jobs moved to the history");
    }
    view.remove(&ids);
    Ok(ids)
}

/// The periodic round: retires what has been live longer than `live_for` (and anything
/// else [`history::to_retire`] picks), and forgets what the history keeps no longer.
fn round(
    store: &mut dyn JobStore,
    view: &mut Snapshot,
    retention: &Retention,
    now: f64,
) -> Result<Vec<String>, StoreError> {
    let ids = retire(store, view, retention, now)?;
    if let Some(keep_for) = retention.keep_for {
        match store.prune(keep_for, now) {
            Ok(0) => {}
            Ok(n) => tracing::info!(jobs = n, "jobs older than [history] keep_days forgotten"),
            Err(e) => {
                tracing::error!(error = %e, "cannot forget the history's old jobs; tried again later")
            }
        }
    }
    Ok(ids)
}

/// Retires the oldest finished jobs beyond `live_jobs` as soon as a batch of requests
/// leaves more than that live, so a burst of finished jobs never makes every reader pay
/// for all of them until the next round. Says whether any moved.
fn retire_beyond_limit(
    store: &mut dyn JobStore,
    view: &mut Snapshot,
    retention: &Retention,
) -> bool {
    let mut moved = false;
    while view.finished_live() > retention.live_jobs {
        match retire(store, view, retention, crate::daemon::job::now_s()) {
            Ok(ids) if !ids.is_empty() => moved = true,
            // What is left must stay for now (an outcome not yet written).
            Ok(_) => break,
            Err(e) => {
                tracing::error!(error = %e, "cannot move finished jobs beyond [history] live_jobs to the history; they stay live and it is tried again at the next change");
                break;
            }
        }
    }
    moved
}

/// How often the store's task makes its round ([`round`]): finished jobs older than
/// `live_for` cannot wait on a change to be retired (at once after starting, and again at
/// once while a batch was full). Jobs beyond `live_jobs` do not wait for it.
const RETIRE_EVERY: std::time::Duration = std::time::Duration::from_secs(600);

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
}

/// The store's task: takes whatever requests are waiting, serves them in order on a
/// blocking thread, retires finished jobs beyond `live_jobs`, publishes the new
/// snapshot, then sends the replies. Every [`RETIRE_EVERY`] it makes its [`round`] the
/// same way.
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
        };
        let work = tokio::task::spawn_blocking(move || {
            let mut deliveries = Vec::new();
            let mut changed = false;
            let mut full = false;
            match work {
                Work::Requests(batch) => {
                    // A panic here (in the store, or in a request's edit) is not caught:
                    // the change it left halfway is unknown, so the task ends with it and
                    // the daemon stops; every reply not sent yet says `Stopped`.
                    for request in batch {
                        let (delivery, change) = request.serve(&mut *store, &mut view, &retention);
                        deliveries.push(delivery);
                        changed |= change;
                    }
                    changed |= retire_beyond_limit(&mut *store, &mut view, &retention);
                }
                Work::Retire => {
                    let now = crate::daemon::job::now_s();
                    match round(&mut *store, &mut view, &retention, now) {
                        Ok(ids) => {
                            changed = !ids.is_empty();
                            full = ids.len() >= history::BATCH;
                        }
                        Err(e) => {
                            tracing::error!(error = %e, "cannot move finished jobs to the history; they stay live and it is tried again later")
                        }
                    }
                }
            }
            (store, view, deliveries, changed, full)
        });
        let (deliveries, changed, full);
        (store, view, deliveries, changed, full) = match work.await {
            Ok(done) => done,
            // The panic goes on as this task's, for the supervisor to name.
            Err(e) if e.is_panic() => std::panic::resume_unwind(e.into_panic()),
            Err(e) => {
                tracing::error!(error = %e, "the job store's thread was cancelled; the store stops");
                return;
            }
        };
        if full {
            retiring.reset_immediately();
        }
        // A batch that changed nothing wakes no follower.
        if changed {
            snapshots.send_replace(Arc::new(view.clone()));
        }
        for delivery in deliveries {
            delivery();
        }
    }
}

/// A cheap, cloneable way to the store's task.
#[derive(Clone)]
pub struct StoreHandle {
    tx: mpsc::Sender<Request>,
    snapshot: watch::Receiver<Arc<Snapshot>>,
}

impl StoreHandle {
    /// The jobs and gates as of the last change; no round trip.
    pub fn snapshot(&self) -> Arc<Snapshot> {
        self.snapshot.borrow().clone()
    }

    /// Follows the snapshot: `changed()` resolves once a change after this call is
    /// published (the way tasks wait for jobs and bed gates).
    pub fn subscribe(&self) -> watch::Receiver<Arc<Snapshot>> {
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
    pub async fn late_sidecar(
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
        self.transition_with(id, state, reason, |_| {}).await
    }

    /// [`StoreHandle::transition`] with other fields changed in the same write.
    pub async fn transition_with(
        &self,
        id: &str,
        state: JobState,
        reason: Option<String>,
        also: impl FnOnce(&mut Job) + Send + 'static,
    ) -> Result<Job, StoreError> {
        self.change(id, None, state, reason, Box::new(also)).await
    }

    /// [`StoreHandle::transition_with`] only if the job is in one of the states `from`
    /// (else [`StoreError::StateChanged`]), checked and changed as one step.
    pub async fn transition_from(
        &self,
        id: &str,
        from: StateFilter,
        state: JobState,
        reason: Option<String>,
        also: impl FnOnce(&mut Job) + Send + 'static,
    ) -> Result<Job, StoreError> {
        self.change(id, Some(from), state, reason, Box::new(also))
            .await
    }

    async fn change(
        &self,
        id: &str,
        from: Option<StateFilter>,
        to: JobState,
        reason: Option<String>,
        also: JobEdit,
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
    pub async fn record_outcome(
        &self,
        id: &str,
        state: JobState,
        reason: Option<String>,
        also: impl FnOnce(&mut Job) + Send + 'static,
    ) -> Result<Job, StoreError> {
        let (id, also) = (id.to_string(), Box::new(also));
        self.ask(|reply| Request::Outcome {
            id,
            to: state,
            reason,
            also,
            reply,
        })
        .await
    }

    pub async fn update(
        &self,
        id: &str,
        change: impl FnOnce(&mut Job) + Send + 'static,
    ) -> Result<Job, StoreError> {
        let (id, change) = (id.to_string(), Box::new(change));
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

    pub async fn set_gate(&self, printer: &str, gate: PrinterGate) -> Result<(), StoreError> {
        let printer = printer.to_string();
        self.ask(|reply| Request::SetGate {
            printer,
            gate,
            reply,
        })
        .await
    }

    /// Closes a printer's bed gate after a print (`job`: the job on the bed).
    pub async fn close_gate(&self, printer: &str, job: &str) -> Result<(), StoreError> {
        let gate = PrinterGate {
            bed_not_cleared: true,
            last_job: Some(job.to_string()),
        };
        self.set_gate(printer, gate).await
    }

    /// Marks a printer's bed cleared; false when it was clear already.
    pub async fn clear_gate(&self, printer: &str) -> Result<bool, StoreError> {
        let printer = printer.to_string();
        self.ask(|reply| Request::ClearGate { printer, reply })
            .await
    }

    /// Persists outcomes that could not be written before; returns how many remain.
    pub async fn write_pending(&self) -> Result<usize, StoreError> {
        self.ask(|reply| Request::WritePending { reply }).await
    }

    /// Takes in what other hosts changed (see [`JobStore::resync`]); true when anything had.
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

/// A job's reason as it is kept: the API, the dashboard, the history and notifications show
/// it to clients, which are never told the server's paths (the log has them). Whoever
/// built the reason (a preparation, a printer, a policy) may have named a file by its
/// path; every path inside the spool is named relative to it here (`jobs/<id>/part.gcode`).
fn for_clients(reason: &str, store: &dyn JobStore) -> String {
    let jobs = store.jobs_dir();
    spool_relative(reason, jobs.parent().unwrap_or(&jobs))
}

/// `text` with every path inside `spool` named relative to it (`jobs/<id>/job.json`), and
/// `spool` itself as "the spool". The spool's path is matched as it is written and as it
/// resolves (a spool under a symbolic link), only where it is a whole path, not a piece of
/// a longer name (`/srv/spool` in `/srv/spool2/x` is left alone).
pub fn spool_relative(text: &str, spool: &Path) -> String {
    let mut spellings: Vec<String> = vec![spool.to_string_lossy().into_owned()];
    if let Ok(real) = spool.canonicalize() {
        spellings.push(real.to_string_lossy().into_owned());
    }
    let mut spellings: Vec<String> = spellings
        .into_iter()
        .map(|s| s.trim_end_matches('/').to_string())
        // A spool at `/` or `` would match everything: nothing to hide that way.
        .filter(|s| s.len() > 1)
        .collect();
    // The longest first, so a spelling inside another does not cut it short.
    spellings.sort_by_key(|s| std::cmp::Reverse(s.len()));
    spellings.dedup();
    let in_path = |c: char| c.is_alphanumeric() || matches!(c, '/' | '.' | '_' | '-' | '~');
    let mut out = String::with_capacity(text.len());
    let mut rest = text;
    'scan: while !rest.is_empty() {
        let before = out.chars().next_back();
        if !before.is_some_and(in_path) {
            for spelling in &spellings {
                let Some(after) = rest.strip_prefix(spelling.as_str()) else {
                    continue;
                };
                if let Some(inside) = after.strip_prefix('/') {
                    rest = inside;
                    continue 'scan;
                }
                if !after.chars().next().is_some_and(in_path) {
                    out.push_str("the spool");
                    rest = after;
                    continue 'scan;
                }
            }
        }
        let c = rest.chars().next().expect("not empty");
        out.push(c);
        rest = &rest[c.len_utf8()..];
    }
    out
}

/// The error of a file operation of a store on `path`: what was done and why it failed.
fn io_err(path: &Path, action: &'static str) -> impl FnOnce(std::io::Error) -> StoreError {
    let path = path.to_path_buf();
    move |source| StoreError::Io {
        path,
        action,
        source,
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Paths inside the spool are named relative to it, wherever they stand in a reason;
    /// a longer name that merely begins like the spool is not touched.
    #[test]
    fn reasons_name_spool_files_relative_to_it() {
        let spool = Path::new("/srv/crispen/spool");
        let cases = [
            (
                "spool /srv/crispen/spool/jobs/0001-a/job.json: unreadable job state: eof; \
                 the directory /srv/crispen/spool/jobs/0001-a is kept as it was",
                "spool jobs/0001-a/job.json: unreadable job state: eof; \
                 the directory jobs/0001-a is kept as it was",
            ),
            (
                "cannot load the G-code: \"/srv/crispen/spool/jobs/0002-b/b.gcode\":12: bad",
                "cannot load the G-code: \"jobs/0002-b/b.gcode\":12: bad",
            ),
            ("in /srv/crispen/spool: full", "in the spool: full"),
            ("/srv/crispen/spool/", ""),
            (
                "/srv/crispen/spool2/x and x/srv/crispen/spool/y and /srv/crispen/spoolx",
                "/srv/crispen/spool2/x and x/srv/crispen/spool/y and /srv/crispen/spoolx",
            ),
            ("café /srv/crispen/spool/jobs/é", "café jobs/é"),
            ("nothing to see", "nothing to see"),
        ];
        for (text, want) in cases {
            assert_eq!(spool_relative(text, spool), want, "{text}");
            // A spool named with a trailing slash is the same spool.
            assert_eq!(
                spool_relative(text, Path::new("/srv/crispen/spool/")),
                want,
                "{text}"
            );
        }
        // Under a symbolic link: both the link's path and the real one.
        let tmp = tempfile::tempdir().unwrap();
        let real = tmp.path().join("real");
        std::fs::create_dir(&real).unwrap();
        let link = tmp.path().join("link");
        std::os::unix::fs::symlink(&real, &link).unwrap();
        let real = real.canonicalize().unwrap();
        let text = format!("{}/jobs/a and {}/jobs/b", link.display(), real.display());
        assert_eq!(spool_relative(&text, &link), "jobs/a and jobs/b");
        // A spool at the root hides nothing (every path would match).
        assert_eq!(spool_relative("/etc/x", Path::new("/")), "/etc/x");
    }

    /// A reason given to the store's task is kept (and so shown in the status and the
    /// history) with the spool's paths made relative.
    #[tokio::test]
    async fn a_kept_reason_names_no_spool_path() {
        let tmp = tempfile::tempdir().unwrap();
        let hot = tmp.path().join("hot");
        std::fs::create_dir(&hot).unwrap();
        let root = tmp.path().join("spool");
        let store = spool::Spool::open(&root).unwrap();
        let handle = spawn_with(store, Retention::default());
        std::fs::write(hot.join("a.gcode"), b"G28\n").unwrap();
        let job = handle.admit(&hot.join("a.gcode"), &hot, &[]).await.unwrap();
        let model = root.join("jobs").join(&job.id).join("a.gcode");
        let reason = format!("not G-code: {}: line 1", model.display());
        handle
            .transition(&job.id, JobState::Failed, Some(reason))
            .await
            .unwrap();
        let kept = handle
            .snapshot()
            .get(&job.id)
            .unwrap()
            .reason
            .clone()
            .unwrap();
        assert_eq!(kept, format!("not G-code: jobs/{}/a.gcode: line 1", job.id));
    }

    /// Through the store's task: retired jobs leave the published snapshot (beyond
    /// `live_jobs` at the change that made one too many, older than `live_for` at a
    /// round), the history pages through them, and one is found by id; what pictures a
    /// job has is in the snapshot, looked at when the job changed.
    #[tokio::test]
    async fn the_snapshot_keeps_live_jobs_and_the_history_the_rest() {
        let tmp = tempfile::tempdir().unwrap();
        let hot = tmp.path().join("hot");
        std::fs::create_dir(&hot).unwrap();
        let store = spool::Spool::open(&tmp.path().join("spool")).unwrap();
        let retention = Retention {
            live_for: std::time::Duration::from_secs(86_400),
            live_jobs: 2,
            keep_for: None,
        };
        let handle = spawn_with(store, retention);
        let mut ids = Vec::new();
        for i in 0..4 {
            let model = hot.join(format!("m{i}.stl"));
            std::fs::write(&model, b"solid x\nendsolid x\n").unwrap();
            let job = handle.admit(&model, &hot, &[]).await.unwrap();
            ids.push(job.id);
        }
        let snapshot = handle.snapshot();
        assert!(snapshot.pictures(&ids[0]).is_empty());
        std::fs::write(
            snapshot.job_dir(&ids[0]).join(crate::preview::AFTER_PNG),
            b"png",
        )
        .unwrap();
        let cancel = |id: String| {
            let handle = handle.clone();
            async move {
                handle
                    .transition(&id, JobState::Cancelled, None)
                    .await
                    .unwrap()
            }
        };
        cancel(ids[0].clone()).await;
        assert_eq!(
            handle.snapshot().pictures(&ids[0]),
            [crate::preview::AFTER_PNG]
        );
        cancel(ids[1].clone()).await;
        assert!(handle.snapshot().get(&ids[0]).is_some(), "two finished");
        cancel(ids[2].clone()).await;
        let snapshot = handle.snapshot();
        let live: Vec<&str> = snapshot.jobs().map(|j| j.id.as_str()).collect();
        assert_eq!(
            live,
            &ids[1..],
            "the oldest of three finished retired at once"
        );

        let two_days_on = crate::daemon::job::now_s() + 2.0 * 86_400.0;
        let moved = handle.retire(two_days_on).await.unwrap();
        assert_eq!(moved, ids[1..3].to_vec());
        let snapshot = handle.snapshot();
        let live: Vec<&str> = snapshot.jobs().map(|j| j.id.as_str()).collect();
        assert_eq!(live, [ids[3].as_str()]);

        let mut paged = Vec::new();
        let mut next = None;
        loop {
            let page = handle.history(next, 1).await.unwrap();
            paged.extend(page.jobs.iter().map(|j| j.id.clone()));
            next = page.next;
            if next.is_none() {
                break;
            }
        }
        assert_eq!(paged, [&*ids[2], &ids[1], &ids[0]], "newest first");
        let retired = handle.retired(&ids[0]).await.unwrap().unwrap();
        assert_eq!(retired.record.state, JobState::Cancelled);
        assert!(handle.retired(&ids[3]).await.unwrap().is_none());
    }

    /// 3,000 jobs finishing within a minute (three bursts of 1,000, each finished as fast
    /// as the store takes them) never leave more than `live_jobs` finished jobs live, as
    /// every reply (sent after its snapshot) and the snapshot after each burst show. They
    /// once all stayed live until the next round, up to ten minutes later, and every
    /// status paid for them. The counts have every change.
    #[tokio::test]
    async fn a_burst_of_finished_jobs_never_exceeds_the_live_count() {
        use futures_util::future::join_all;
        const LIVE: usize = 50;
        const BURST: usize = 1_000;
        // 6,000 synced writes: in memory where there is a tmpfs (seconds, not minutes on
        // a busy disk); what is tested is the live count, not the disk.
        let tmp = tempfile::tempdir_in("/dev/shm")
            .or_else(|_| tempfile::tempdir())
            .unwrap();
        let hot = tmp.path().join("hot");
        std::fs::create_dir(&hot).unwrap();
        let store = spool::Spool::open(&tmp.path().join("spool")).unwrap();
        let retention = Retention {
            live_for: std::time::Duration::from_secs(86_400),
            live_jobs: LIVE,
            keep_for: None,
        };
        let handle = spawn_with(store, retention);
        let mut last = String::new();
        for burst in 1..=3 {
            let admitted = join_all((0..BURST).map(|i| {
                let (handle, hot) = (handle.clone(), hot.clone());
                async move {
                    let model = hot.join(format!("b{burst}-{i}.gcode"));
                    std::fs::write(&model, b"G28\n").unwrap();
                    handle.admit(&model, &hot, &[]).await.unwrap().id
                }
            }))
            .await;
            let finished = join_all(admitted.iter().enumerate().map(|(i, id)| {
                let handle = handle.clone();
                // Every way a job ends for good.
                let to = [JobState::Cancelled, JobState::Failed][i % 2];
                async move {
                    handle.transition(id, to, None).await.unwrap();
                    handle.snapshot().finished_live()
                }
            }))
            .await;
            let most = finished.into_iter().max().unwrap();
            assert!(most <= LIVE, "burst {burst}: {most} finished jobs live");
            let snapshot = handle.snapshot();
            assert_eq!(snapshot.finished_live(), LIVE, "burst {burst}");
            assert_eq!(snapshot.jobs().count(), LIVE, "burst {burst}: only those");
            let counts = snapshot.counts();
            assert_eq!(counts.into_state(JobState::Queued), (burst * BURST) as u64);
            assert_eq!(counts.finished(), (burst * BURST) as u64);
            last = admitted.last().unwrap().clone();
        }
        // The newest stay live; the rest are in the history.
        assert!(handle.snapshot().get(&last).is_some());
        let page = handle.history(None, 1).await.unwrap();
        assert!(page.jobs[0].seq < handle.snapshot().get(&last).unwrap().seq);
    }

    /// The embedded store with a second writer, as a shared farm has: changes queued in
    /// `elsewhere` are made behind the task's back, and taken in by the next resync.
    struct TwoHosts {
        spool: spool::Spool,
        elsewhere: Arc<std::sync::Mutex<Vec<(String, JobState)>>>,
    }

    impl JobStore for TwoHosts {
        fn jobs_dir(&self) -> PathBuf {
            self.spool.jobs_dir()
        }
        fn jobs(&self) -> Vec<Job> {
            JobStore::jobs(&self.spool)
        }
        fn job(&self, id: &str) -> Option<Job> {
            JobStore::job(&self.spool, id)
        }
        fn gates(&self) -> BTreeMap<String, PrinterGate> {
            JobStore::gates(&self.spool)
        }
        fn recover(&mut self) -> Result<Vec<String>, StoreError> {
            JobStore::recover(&mut self.spool)
        }
        fn admit(&mut self, source: &Path, folder: &Path, p: &[String]) -> Result<Job, StoreError> {
            JobStore::admit(&mut self.spool, source, folder, p)
        }
        fn late_sidecar(&mut self, id: &str, s: &Path, applies: bool) -> Result<bool, StoreError> {
            JobStore::late_sidecar(&mut self.spool, id, s, applies)
        }
        fn transition_with(
            &mut self,
            id: &str,
            from: Option<StateFilter>,
            state: JobState,
            reason: Option<String>,
            also: JobEdit,
        ) -> Result<Job, StoreError> {
            JobStore::transition_with(&mut self.spool, id, from, state, reason, also)
        }
        fn record_outcome(
            &mut self,
            id: &str,
            state: JobState,
            reason: Option<String>,
            also: JobEdit,
        ) -> Result<Job, StoreError> {
            JobStore::record_outcome(&mut self.spool, id, state, reason, also)
        }
        fn update(&mut self, id: &str, change: JobEdit) -> Result<Job, StoreError> {
            JobStore::update(&mut self.spool, id, change)
        }
        fn retry(&mut self, id: &str) -> Result<Job, StoreError> {
            JobStore::retry(&mut self.spool, id)
        }
        fn set_gate(&mut self, printer: &str, gate: PrinterGate) -> Result<(), StoreError> {
            JobStore::set_gate(&mut self.spool, printer, gate)
        }
        fn write_pending(&mut self) -> usize {
            JobStore::write_pending(&mut self.spool)
        }
        fn unwritten(&self) -> usize {
            JobStore::unwritten(&self.spool)
        }
        fn resync(&mut self) -> bool {
            let changes: Vec<_> = std::mem::take(&mut *self.elsewhere.lock().unwrap());
            for (id, state) in &changes {
                let on_p1: JobEdit = Box::new(|j| j.printer = Some("p1".into()));
                JobStore::transition_with(&mut self.spool, id, None, *state, None, on_p1).unwrap();
            }
            // Always a rebuild of the snapshot: one with nothing new must count nothing.
            true
        }
        fn retire(&mut self, r: &Retention, now: f64) -> Result<Vec<String>, StoreError> {
            JobStore::retire(&mut self.spool, r, now)
        }
        fn retired(&self, id: &str) -> Result<Option<RetiredJob>, StoreError> {
            JobStore::retired(&self.spool, id)
        }
        fn history(
            &self,
            before: Option<u64>,
            limit: usize,
            filter: &history::Filter,
        ) -> Result<history::Page, StoreError> {
            JobStore::history(&self.spool, before, limit, filter)
        }
        fn prune(&mut self, keep: std::time::Duration, now: f64) -> Result<usize, StoreError> {
            JobStore::prune(&mut self.spool, keep, now)
        }
        fn each_retired(
            &self,
            since: f64,
            visit: &mut dyn FnMut(history::Retired),
        ) -> Result<(), StoreError> {
            JobStore::each_retired(&self.spool, since, visit)
        }
    }

    /// Changes another host made are counted by the task from what a resync takes in,
    /// each once (a rebuild that brings nothing new counts nothing): the counts and the
    /// tally are the farm's, not only this host's requests (a wrapper around this host's
    /// requests once counted, and missed them).
    #[tokio::test]
    async fn changes_from_elsewhere_are_counted_once() {
        let tmp = tempfile::tempdir().unwrap();
        let hot = tmp.path().join("hot");
        std::fs::create_dir(&hot).unwrap();
        let elsewhere = Arc::new(std::sync::Mutex::new(Vec::new()));
        let store = TwoHosts {
            spool: spool::Spool::open(&tmp.path().join("spool")).unwrap(),
            elsewhere: Arc::clone(&elsewhere),
        };
        let handle = spawn(store);
        std::fs::write(hot.join("a.gcode"), b"G28\n").unwrap();
        let job = handle.admit(&hot.join("a.gcode"), &hot, &[]).await.unwrap();
        let counts = |state| handle.snapshot().counts().into_state(state);
        assert_eq!(counts(JobState::Queued), 1, "this host's own change");
        elsewhere.lock().unwrap().extend(
            [
                JobState::Preparing,
                JobState::Ready,
                JobState::Printing,
                JobState::Done,
            ]
            .map(|s| (job.id.clone(), s)),
        );
        assert!(handle.resync().await.unwrap());
        // Rebuilt again from the same jobs: nothing is counted twice.
        assert!(handle.resync().await.unwrap());
        for state in [JobState::Queued, JobState::Preparing, JobState::Ready] {
            assert_eq!(counts(state), 1, "{state}");
        }
        assert_eq!((counts(JobState::Printing), counts(JobState::Done)), (1, 1));
        let snapshot = handle.snapshot();
        assert_eq!(snapshot.counts().finished(), 1);
        let p1 = &snapshot.tally().read()["p1"];
        assert_eq!((p1.done, p1.prints), (1, 1), "the print on p1");
    }

    /// The rule both stores use on retry; a job prepared before machines existed keeps its
    /// `<file>.gcode` (the PostgreSQL store took it for unprepared).
    #[test]
    fn what_counts_as_prepared() {
        let mut job = Job::queued("0001-a_stl".into(), 1, "a.stl".into(), "/hot".into());
        let has = |names: &'static [&'static str]| move |n: &str| names.contains(&n);
        assert!(!prepared(&job, has(&["a.stl.gcode"])), "never sliced");
        job.slice_report = Some(Default::default());
        assert!(prepared(&job, has(&["a.stl.gcode"])), "legacy G-code");
        assert!(!prepared(&job, has(&[])));
        job.machines
            .insert("m1".into(), ForMachine::Refused("too big".into()));
        job.machines
            .insert("m2".into(), ForMachine::Gcode("a.stl.m2.gcode".into()));
        assert!(prepared(&job, has(&["a.stl.m2.gcode"])));
        assert!(!prepared(&job, has(&["a.stl.gcode"])), "not this job's now");
    }
}
