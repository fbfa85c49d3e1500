//! The farm's shared state: the config in force, the job store, each printer's live status,
//! live progress of jobs, and a generation counter that wakes every task when anything
//! changes (a job became ready, a bed was cleared, shutdown began). One `Arc<Farm>` is
//! handed to the pick-up, preparation, printer and control tasks.

use super::config::Config;
use super::job::{Job, JobState, JobStore, StoreError};
use serde::{Deserialize, Serialize};
use std::collections::{BTreeMap, HashMap};
use std::sync::{Arc, Mutex, RwLock};
use tokio::sync::{mpsc, watch, Semaphore};

/// A printer's state as shown by `crispen status` (lower case in JSON).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum PrinterState {
    Connecting,
    Idle,
    /// Holding a job's start until a heating permit is free (staggered heat-ups).
    WaitingToHeat,
    Printing,
    Paused,
    BedNotCleared,
    Disconnected,
    Stopped,
}

/// Live figures of a print (from the streamer).
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct LiveProgress {
    pub lines_acked: usize,
    pub lines_total: usize,
    pub hotend_c: Option<f64>,
    pub hotend_target_c: Option<f64>,
    pub bed_c: Option<f64>,
    pub bed_target_c: Option<f64>,
    pub elapsed_s: f64,
    pub remaining_s: Option<f64>,
    /// The program's heat-up part is done (see `printer` on staggered heat-ups).
    pub heated: bool,
    pub paused: bool,
}

#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct PrinterStatus {
    pub name: String,
    pub state: PrinterState,
    pub firmware: String,
    pub port: String,
    pub job: Option<String>,
    pub progress: Option<LiveProgress>,
    /// Why the printer is in its state (e.g. the last connection error).
    pub detail: Option<String>,
    /// False from the end of a print until `crispen clear`, whatever the connection
    /// does meanwhile: an offline printer can still have a finished print on its bed.
    pub bed_cleared: bool,
}

/// What a control command asks of a print in progress.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum PrintCommand {
    Pause,
    Resume,
    Cancel,
}

/// A preparation in progress.
pub struct Preparation {
    pub step: String,
    /// Set by `crispen cancel`; the slicer's child process is killed when it is seen.
    pub cancel: Arc<std::sync::atomic::AtomicBool>,
}

pub struct Farm {
    pub config: RwLock<Arc<Config>>,
    pub store: Mutex<JobStore>,
    pub printers: Mutex<BTreeMap<String, PrinterStatus>>,
    /// Jobs being prepared: their current step, and the flag that stops their slicer.
    pub preparing: Mutex<HashMap<String, Preparation>>,
    /// Control channel into each printer's running print.
    pub print_controls: Mutex<HashMap<String, mpsc::Sender<PrintCommand>>>,
    /// Bumped on every change that may let a task make progress.
    generation: watch::Sender<u64>,
    /// Set once SIGTERM arrived: no new work is taken.
    stopping: watch::Sender<bool>,
    pub heating: Arc<Semaphore>,
    /// Jobs that reached a final state during this run (for --exit-when-idle).
    pub finished_this_run: std::sync::atomic::AtomicUsize,
}

impl Farm {
    pub fn new(config: Config, store: JobStore) -> Arc<Farm> {
        let heating = Arc::new(Semaphore::new(config.farm.max_heating));
        Arc::new(Farm {
            config: RwLock::new(Arc::new(config)),
            store: Mutex::new(store),
            printers: Mutex::new(BTreeMap::new()),
            preparing: Mutex::new(HashMap::new()),
            print_controls: Mutex::new(HashMap::new()),
            generation: watch::channel(0).0,
            stopping: watch::channel(false).0,
            heating,
            finished_this_run: Default::default(),
        })
    }

    pub fn config(&self) -> Arc<Config> {
        self.config
            .read()
            .unwrap_or_else(|e| e.into_inner())
            .clone()
    }

    pub fn store(&self) -> std::sync::MutexGuard<'_, JobStore> {
        self.store.lock().unwrap_or_else(|e| e.into_inner())
    }

    /// Wakes every task waiting in [`Farm::changed`].
    pub fn bump(&self) {
        self.generation.send_modify(|g| *g += 1);
    }

    /// A receiver that resolves `changed()` on the next bump.
    pub fn subscribe(&self) -> watch::Receiver<u64> {
        self.generation.subscribe()
    }

    pub fn stopping(&self) -> bool {
        *self.stopping.borrow()
    }

    pub fn subscribe_stopping(&self) -> watch::Receiver<bool> {
        self.stopping.subscribe()
    }

    pub fn begin_stop(&self) {
        self.stopping.send_replace(true);
        self.bump();
    }

    /// Changes a job's state, logs it, counts final states, and wakes the tasks.
    pub fn transition(
        &self,
        id: &str,
        state: JobState,
        reason: Option<String>,
    ) -> Result<Job, StoreError> {
        self.transition_in(&mut self.store(), id, state, reason)
    }

    /// [`Farm::transition`] with the store already locked, for a caller whose check and
    /// change must not be split by another task (claiming a job).
    pub fn transition_in(
        &self,
        store: &mut JobStore,
        id: &str,
        state: JobState,
        reason: Option<String>,
    ) -> Result<Job, StoreError> {
        let job = store.transition(id, state, reason.clone())?;
        match &reason {
            Some(r) => tracing::info!(job = id, state = state.name(), reason = %r, "job state"),
            None => tracing::info!(job = id, state = state.name(), "job state"),
        }
        if !state.is_active() {
            self.finished_this_run
                .fetch_add(1, std::sync::atomic::Ordering::SeqCst);
        }
        self.bump();
        Ok(job)
    }

    pub fn set_printer(&self, name: &str, change: impl FnOnce(&mut PrinterStatus)) {
        let mut printers = self.printers.lock().unwrap_or_else(|e| e.into_inner());
        if let Some(p) = printers.get_mut(name) {
            change(p);
        }
    }

    /// No job has work ahead of it.
    pub fn idle(&self) -> bool {
        !self.store().jobs().any(|j| j.state.is_active())
    }
}
