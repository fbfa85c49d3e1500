//! What the store's task publishes after every change: an immutable [`Snapshot`] of the
//! live jobs and bed gates, with what is known of each job's pictures and what the jobs did
//! (the counts and the tally). Apart from the task so the readers' side (status, HTTP,
//! metrics, the printers' glances) is one file, and the task only builds and sends it.

use super::counts::{Counted, JobCounts};
use super::history;
use super::job_store::JobStore;
use super::stats;
use crate::daemon::filament::Inventory;
use crate::daemon::job::{Job, PrinterGate};
use std::collections::{BTreeMap, HashMap};
use std::path::{Path, PathBuf};
use std::sync::Arc;

/// An immutable picture of every live job and bed gate, as of the store's last change.
/// Cheap to publish: each job is shared (`Arc`), and the index is shared until a job
/// comes or goes.
#[derive(Clone, Debug, Default)]
pub struct Snapshot {
    /// Oldest first.
    jobs: Vec<Arc<Live>>,
    index: Arc<HashMap<String, usize>>,
    pub(super) gates: BTreeMap<String, PrinterGate>,
    /// The farm's spools and which printer holds which.
    pub(super) inventory: Arc<Inventory>,
    jobs_dir: PathBuf,
    /// Outcomes recorded but not yet persisted (a full disk).
    pub(super) unwritten: usize,
    /// What jobs did since the task started, counted as each change is published.
    counted: Arc<Counted>,
    /// How many snapshots the task has published since it started (see [`Snapshot::version`]).
    pub(super) version: u64,
}

/// A live job and what is known of its files.
#[derive(Clone, Debug)]
struct Live {
    job: Job,
    /// Which of [`PICTURES`] its directory holds (bit i for `PICTURES[i]`); None until the
    /// task has looked ([`Snapshot::look`]), which it does before it publishes.
    pictures: Option<u8>,
}

/// The pictures a job's directory may hold (see `crate::preview`); at most 8, one bit of
/// [`Live::pictures`] each.
pub const PICTURES: [&str; 6] = [
    crate::preview::BEFORE_PNG,
    crate::preview::AFTER_PNG,
    crate::preview::DISPLACEMENT_PNG,
    crate::preview::walls::WALLS_PNG,
    crate::preview::PREVIEW_PNG,
    crate::observation::OBSERVED_PNG,
];
const _: () = assert!(PICTURES.len() <= u8::BITS as usize);

impl Live {
    /// The job, with the pictures `before` knew (the job as last seen, when the whole
    /// snapshot is rebuilt after other hosts' changes) if it is the same job in the same
    /// state: pictures are made while a job prepares, so a job whose history has not moved
    /// has the ones it had. Else they are to be looked at.
    fn of(job: Job, before: Option<&Live>) -> Live {
        let pictures = before
            .filter(|b| b.job.history.len() == job.history.len() && b.job.state == job.state)
            .and_then(|b| b.pictures);
        Live { job, pictures }
    }
}

/// Which of [`PICTURES`] the job directory `dir` holds (a few `stat`s: on a blocking
/// thread).
fn pictures_in(dir: &Path) -> u8 {
    PICTURES
        .iter()
        .enumerate()
        .filter(|(_, name)| dir.join(name).is_file())
        .fold(0, |bits, (i, _)| bits | 1 << i)
}

impl Snapshot {
    /// The store's jobs as they are now. `before`: the snapshot published last (None: the
    /// first, when the task starts: nothing is a change yet); what changed since is counted.
    /// The pictures of the jobs that moved are looked at by [`Snapshot::look`].
    pub(super) fn of(store: &dyn JobStore, before: Option<&Snapshot>) -> Snapshot {
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
                Arc::new(Live::of(j, old))
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
            inventory: Arc::new(store.inventory()),
            jobs_dir,
            unwritten: store.unwritten(),
            counted,
            version: before.map_or(0, |b| b.version),
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
    pub(crate) fn pictures(&self, id: &str) -> Vec<&'static str> {
        let bits = self.live(id).and_then(|l| l.pictures).unwrap_or(0);
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

    /// The farm's spools and which printer holds which.
    pub fn inventory(&self) -> &Inventory {
        &self.inventory
    }

    pub fn job_dir(&self, id: &str) -> PathBuf {
        self.jobs_dir.join(id)
    }

    /// How many changes the store's task has published since it started, this one
    /// included: a reader that acted on version `n` acted on every change up to it (a
    /// printer's supervisor says which version it last looked for a job in).
    pub fn version(&self) -> u64 {
        self.version
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

    /// The beds' ejects and checks since the store's task started: (printer, `ejects` or
    /// `checks`, result) and how many.
    pub fn bed_counts(&self) -> &BTreeMap<(String, &'static str, &'static str), u64> {
        &self.counted.beds
    }

    /// Counts a change of `printer`'s bed (see [`crate::daemon::bed::Bed::counted`]).
    pub(super) fn count_bed(&mut self, printer: &str, kind: &'static str, result: &'static str) {
        *Arc::make_mut(&mut self.counted)
            .beds
            .entry((printer.to_string(), kind, result))
            .or_default() += 1;
    }

    /// No job has work ahead of it.
    pub(crate) fn idle(&self) -> bool {
        !self.jobs().any(|j| j.state.is_active())
    }

    /// Finished jobs (done, failed, cancelled) still live.
    pub(crate) fn finished_live(&self) -> usize {
        self.jobs()
            .filter(|j| history::is_finished(j.state))
            .count()
    }

    /// Takes the store's current record of `id` (after a change, successful or not: a
    /// failed change may still have failed the job, e.g. when its directory is gone), and
    /// announces what it changed.
    pub(super) fn refresh(&mut self, store: &dyn JobStore, id: &str) {
        let Some(job) = store.job(id) else { return };
        let before = self.index.get(id).map(|&i| Arc::clone(&self.jobs[i]));
        Arc::make_mut(&mut self.counted).changes(before.as_ref().map(|l| &l.job), &job);
        match self.index.get(id) {
            // Looked at again at every change: a few stats per change, none per glance.
            Some(&i) => self.jobs[i] = Arc::new(Live::of(job, None)),
            // New jobs have the highest sequence number: appending keeps the order.
            None => {
                Arc::make_mut(&mut self.index).insert(job.id.clone(), self.jobs.len());
                self.jobs.push(Arc::new(Live::of(job, None)));
            }
        }
    }

    /// Looks at the pictures of the jobs not looked at since they changed, all at once on
    /// a blocking thread; the task does it before it publishes. Says whether any job has
    /// a picture (what a reader would see differently).
    pub(super) async fn look(&mut self) -> bool {
        let unlooked: Vec<(usize, PathBuf)> = (self.jobs.iter().enumerate())
            .filter(|(_, l)| l.pictures.is_none())
            .map(|(i, l)| (i, self.jobs_dir.join(&l.job.id)))
            .collect();
        if unlooked.is_empty() {
            return false;
        }
        let looked = super::blocking(move || {
            unlooked
                .into_iter()
                .map(|(i, dir)| (i, pictures_in(&dir)))
                .collect::<Vec<_>>()
        })
        .await;
        let mut any = false;
        for (i, bits) in looked {
            Arc::make_mut(&mut self.jobs[i]).pictures = Some(bits);
            any |= bits != 0;
        }
        any
    }

    /// Drops jobs that moved to the history.
    pub(super) fn remove(&mut self, ids: &[String]) {
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
