//! The farm's shared state: the config in force, the job store's handle, each printer's live status,
//! live progress of jobs, and a generation counter that wakes every task when anything
//! changes (a job became ready, a bed was cleared, shutdown began). One `Arc<Farm>` is
//! handed to the pick-up, preparation, printer and control tasks.

use super::config::Config;
use super::job::{Job, JobState, StoreError};
use super::store::{JobStore, Snapshot, StateFilter, StoreHandle};
use serde::{Deserialize, Serialize};
use std::collections::{BTreeMap, HashMap};
use std::sync::{Arc, Mutex, RwLock};
use tokio::sync::{mpsc, watch};
use tokio_util::sync::CancellationToken;

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

/// A printer's hotend and bed (°C, current and target) as read now: from the job's
/// reports while it prints, from an `M105` every few seconds between jobs.
#[derive(Debug, Clone, Copy, Default, PartialEq, Serialize, Deserialize)]
pub struct PrinterTemperatures {
    pub hotend_c: Option<f64>,
    pub hotend_target_c: Option<f64>,
    pub bed_c: Option<f64>,
    pub bed_target_c: Option<f64>,
}

#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct PrinterStatus {
    pub name: String,
    pub state: PrinterState,
    pub firmware: String,
    pub port: String,
    pub job: Option<String>,
    pub progress: Option<LiveProgress>,
    /// None while not known now: not connected, or the printer stopped answering (stale
    /// figures are never shown as current).
    #[serde(default)]
    pub temperatures: Option<PrinterTemperatures>,
    /// Why the printer is in its state (e.g. the last connection error).
    pub detail: Option<String>,
    /// False from the end of a print until `crispen clear`, whatever the connection
    /// does meanwhile: an offline printer can still have a finished print on its bed.
    pub bed_cleared: bool,
    /// The host it is attached to, in a farm shared through `[store]`.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub host: Option<String>,
    /// Its host stopped renewing its lease: what is shown is as of then.
    #[serde(default)]
    pub offline: bool,
}

/// What a control command asks of a print in progress. Between hosts of a shared farm it
/// travels as a word in the database's `commands` table ([`PrintCommand::word`],
/// [`PrintCommand::parse`]: the one place a word becomes a command).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum PrintCommand {
    Pause,
    Resume,
    Cancel,
}

impl PrintCommand {
    /// The word that stands for it in the farm database.
    pub fn word(self) -> &'static str {
        match self {
            PrintCommand::Pause => "pause",
            PrintCommand::Resume => "resume",
            PrintCommand::Cancel => "cancel",
        }
    }

    /// The command a word read from the farm database stands for. Anything else (a newer
    /// host's command, a hand-written row) is an error: it must never be taken for a
    /// cancel, which would stop a print.
    pub fn parse(word: &str) -> Result<PrintCommand, UnknownCommand> {
        match word {
            "pause" => Ok(PrintCommand::Pause),
            "resume" => Ok(PrintCommand::Resume),
            "cancel" => Ok(PrintCommand::Cancel),
            _ => Err(UnknownCommand::new(word)),
        }
    }
}

/// A command word that is not one of [`PrintCommand`]'s; it keeps the text shortened (the
/// database does not bound it), and shows it escaped.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
#[error("unknown command {text:?}")]
pub struct UnknownCommand {
    /// At most [`UnknownCommand::SHOWN`] characters of the word, `…` after a longer one.
    pub text: String,
}

impl UnknownCommand {
    const SHOWN: usize = 40;

    fn new(word: &str) -> UnknownCommand {
        let mut text: String = word.chars().take(Self::SHOWN).collect();
        if word.chars().nth(Self::SHOWN).is_some() {
            text.push('…');
        }
        UnknownCommand { text }
    }
}

/// One printer's leave to heat up; handed back when dropped.
pub struct HeatingPermit {
    farm: Arc<Farm>,
}

impl Drop for HeatingPermit {
    fn drop(&mut self) {
        *self.farm.heating.lock().unwrap_or_else(|e| e.into_inner()) -= 1;
        self.farm.bump();
    }
}

/// A preparation in progress.
pub struct Preparation {
    pub step: String,
    /// Fired by `crispen cancel` (and by shutdown, of which it is a child): the
    /// preparation's process is killed at once.
    pub cancel: CancellationToken,
}

pub struct Farm {
    pub config: RwLock<Arc<Config>>,
    /// The job store's task (see [`super::store`]): the only way a job changes.
    pub jobs: StoreHandle,
    pub printers: Mutex<BTreeMap<String, PrinterStatus>>,
    /// Jobs being prepared: their current step, and the flag that stops their slicer.
    pub preparing: Mutex<HashMap<String, Preparation>>,
    /// Control channel into each printer's running print.
    pub print_controls: Mutex<HashMap<String, mpsc::Sender<PrintCommand>>>,
    /// Bumped on every change that may let a task make progress.
    generation: watch::Sender<u64>,
    /// Cancelled once SIGTERM arrived: no new work is taken, waits end.
    pub shutdown: CancellationToken,
    /// Printers holding a heating permit now (see [`Farm::heating_permit`]).
    heating: Mutex<usize>,
    /// Jobs that reached a final state during this run (for --exit-when-idle).
    pub finished_this_run: std::sync::atomic::AtomicUsize,
    /// The farm database, when `[store] postgres` shares the farm with other hosts.
    pub db: std::sync::OnceLock<crate::daemon::store::postgres::PgStore>,
    /// The rest of a shared farm as last read from its database (see `super::shared`).
    pub shared: Mutex<Option<super::shared::FarmView>>,
}

impl Farm {
    /// Starts the store's task on the current runtime and builds the farm around it.
    pub fn new(config: Config, store: impl JobStore, shutdown: CancellationToken) -> Arc<Farm> {
        let retention = super::store::Retention {
            live_for: config.history.live_for,
            live_jobs: config.history.live_jobs,
        };
        Arc::new(Farm {
            config: RwLock::new(Arc::new(config)),
            jobs: super::store::spawn_with(store, retention),
            printers: Mutex::new(BTreeMap::new()),
            preparing: Mutex::new(HashMap::new()),
            print_controls: Mutex::new(HashMap::new()),
            generation: watch::channel(0).0,
            shutdown,
            heating: Mutex::new(0),
            finished_this_run: Default::default(),
            db: Default::default(),
            shared: Mutex::new(None),
        })
    }

    pub fn config(&self) -> Arc<Config> {
        self.config
            .read()
            .unwrap_or_else(|e| e.into_inner())
            .clone()
    }

    /// The jobs and bed gates as of the store's last change (a glance: no round trip).
    pub fn store(&self) -> Arc<Snapshot> {
        self.jobs.snapshot()
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
        self.shutdown.is_cancelled()
    }

    pub fn begin_stop(&self) {
        self.shutdown.cancel();
        self.bump();
    }

    /// Waits for one of the `[farm] max_heating` heating permits. The limit is read from
    /// the config in force at each try, so a reload applies to the next permit (a lower
    /// limit lets permits already held run out). Not raced with shutdown here: the caller
    /// does that.
    pub async fn heating_permit(self: &Arc<Self>) -> HeatingPermit {
        loop {
            let mut wake = self.subscribe();
            {
                let mut in_use = self.heating.lock().unwrap_or_else(|e| e.into_inner());
                if *in_use < self.config().farm.max_heating {
                    *in_use += 1;
                    return HeatingPermit {
                        farm: Arc::clone(self),
                    };
                }
            }
            let _ = wake.changed().await;
        }
    }

    /// Changes a job's state, logs it, counts final states, and wakes the tasks.
    pub async fn transition(
        &self,
        id: &str,
        state: JobState,
        reason: Option<String>,
    ) -> Result<Job, StoreError> {
        self.transition_with(id, state, reason, |_| {}).await
    }

    /// [`Farm::transition`] with other fields of the job changed in the same write.
    pub async fn transition_with(
        &self,
        id: &str,
        state: JobState,
        reason: Option<String>,
        also: impl FnOnce(&mut Job) + Send + 'static,
    ) -> Result<Job, StoreError> {
        let job = self
            .jobs
            .transition_with(id, state, reason.clone(), also)
            .await?;
        self.announce(id, state, &reason);
        Ok(job)
    }

    /// [`Farm::transition_with`] only if the job is in one of the states `from`, checked
    /// and changed as one step of the store (a cancel that a claim must not overtake).
    pub async fn transition_from(
        &self,
        id: &str,
        from: StateFilter,
        state: JobState,
        reason: Option<String>,
        also: impl FnOnce(&mut Job) + Send + 'static,
    ) -> Result<Job, StoreError> {
        let job = self
            .jobs
            .transition_from(id, from, state, reason.clone(), also)
            .await?;
        self.announce(id, state, &reason);
        Ok(job)
    }

    /// Takes the oldest ready job `eligible` allows for `printer` (see
    /// [`StoreHandle::claim`]).
    pub async fn claim(
        &self,
        printer: &str,
        eligible: impl Fn(&Job) -> bool + Send + 'static,
    ) -> Result<Option<Job>, StoreError> {
        let job = self.jobs.claim(printer, eligible).await?;
        if let Some(job) = &job {
            self.announce(&job.id, job.state, &None);
        }
        Ok(job)
    }

    /// Records the outcome of a print, which has happened whether or not it can be
    /// written now (see [`JobStore::record_outcome`]).
    pub async fn record_outcome(
        &self,
        id: &str,
        state: JobState,
        reason: Option<String>,
        also: impl FnOnce(&mut Job) + Send + 'static,
    ) -> Result<Job, StoreError> {
        let job = self
            .jobs
            .record_outcome(id, state, reason.clone(), also)
            .await?;
        self.announce(id, state, &reason);
        Ok(job)
    }

    /// Logs a state change, counts final states, and wakes the tasks.
    fn announce(&self, id: &str, state: JobState, reason: &Option<String>) {
        match reason {
            Some(r) => tracing::info!(job = id, state = state.name(), reason = %r, "job state"),
            None => tracing::info!(job = id, state = state.name(), "job state"),
        }
        if !state.is_active() {
            self.finished_this_run
                .fetch_add(1, std::sync::atomic::Ordering::SeqCst);
        }
        self.bump();
    }

    pub fn set_printer(&self, name: &str, change: impl FnOnce(&mut PrinterStatus)) {
        let mut printers = self.printers.lock().unwrap_or_else(|e| e.into_inner());
        if let Some(p) = printers.get_mut(name) {
            change(p);
        }
    }

    /// Every printer that may take a job, by name, with its machine: this host's, and in a
    /// shared farm the other hosts' as they registered them.
    pub fn printer_machines(&self) -> Vec<(String, crate::machine::Machine)> {
        let mut all: Vec<(String, crate::machine::Machine)> = self
            .config()
            .printers
            .iter()
            .map(|p| (p.name.clone(), p.machine.clone()))
            .collect();
        if let Some(view) = &*self.shared.lock().unwrap_or_else(|e| e.into_inner()) {
            for (name, machine) in &view.machines {
                if !all.iter().any(|(n, _)| n == name) {
                    all.push((name.clone(), machine.clone()));
                }
            }
        }
        all
    }

    /// No job has work ahead of it.
    pub fn idle(&self) -> bool {
        !self.store().jobs().any(|j| j.state.is_active())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Every command reads back as itself; any other word is refused, never a cancel
    /// (it once fell through to cancel and stopped the print).
    #[test]
    fn print_commands_parse_in_one_place() {
        for c in [
            PrintCommand::Pause,
            PrintCommand::Resume,
            PrintCommand::Cancel,
        ] {
            assert_eq!(PrintCommand::parse(c.word()), Ok(c));
        }
        for word in ["stop", "", "Cancel", "cancel ", "abort"] {
            assert!(PrintCommand::parse(word).is_err(), "{word:?}");
        }
        let long = format!("x\n\u{1b}[2J{}", "y".repeat(500));
        let e = PrintCommand::parse(&long).unwrap_err();
        assert_eq!(e.text.chars().count(), UnknownCommand::SHOWN + 1);
        assert!(e.text.ends_with('…'));
        let shown = e.to_string();
        assert!(
            !shown.contains('\n') && !shown.contains('\u{1b}'),
            "{shown}"
        );
        assert!(
            shown.contains("\\n") && shown.contains("\\u{1b}"),
            "{shown}"
        );
    }

    fn farm(max_heating: usize, spool: &std::path::Path) -> Arc<Farm> {
        let text = format!("[spool]\ndir = \"spool\"\n[farm]\nmax_heating = {max_heating}\n");
        let config = Config::parse(&text, &spool.join("crispen.toml")).unwrap();
        let store = super::super::store::spool::Spool::open(&spool.join("spool")).unwrap();
        Farm::new(config, store, CancellationToken::new())
    }

    /// `max_heating` applies on reload: raising it lets a waiting printer heat at once
    /// (the permits were once a semaphore sized at startup).
    #[tokio::test]
    async fn max_heating_applies_on_reload() {
        let tmp = tempfile::tempdir().unwrap();
        let farm = farm(1, tmp.path());
        let first = farm.heating_permit().await;
        let waiting = tokio::spawn({
            let farm = Arc::clone(&farm);
            async move { farm.heating_permit().await }
        });
        tokio::task::yield_now().await;
        assert!(!waiting.is_finished(), "one permit only");
        let mut raised = (*farm.config()).clone();
        raised.farm.max_heating = 2;
        *farm.config.write().unwrap() = Arc::new(raised);
        farm.bump();
        let second = tokio::time::timeout(std::time::Duration::from_secs(30), waiting)
            .await
            .expect("the raised limit lets the waiting printer heat")
            .unwrap();
        drop((first, second));
        assert_eq!(*farm.heating.lock().unwrap(), 0, "permits are handed back");
    }
}
