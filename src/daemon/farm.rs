//! The farm's state, each piece with one owner that alone changes it and publishes it as a
//! `watch` the tasks that follow it wait on (there is no global wake-up):
//!
//! - jobs and bed gates: the job store's task ([`super::store`]), published as its
//!   snapshot; changed by requests through its handle ([`Farm::jobs`]). The task alone
//!   logs and counts each change, in the snapshot that publishes it.
//! - a printer's live status (state, job, progress, temperatures): that printer's
//!   supervisor (the `printer` module), one watch per printer; which printers there are:
//!   the fleet (the `fleet` module). Whether its bed is cleared is not part of it: that is
//!   the store's gate, and [`Farm::local_printers`] derives it in one place.
//! - the config in force: the reload path ([`ConfigOwner`]).
//! - heating permits: [`HeatingPermits`].
//! - preparations in progress: the preparation queue.
//! - the rest of a shared farm: the shared-farm task (`super::shared`).
//!
//! One `Arc<Farm>` of handles is given to the pick-up, preparation, printer, shared-farm
//! and control tasks; [`FarmWatch`] follows all of it (the event stream does). `Farm`
//! reads and follows; it sends nothing. The senders of the config, the printers, the
//! preparations and the shared view are [`Owners`], made with the farm and handed each to
//! its one owner, which alone can change that piece.

use super::config::Config;
use super::job::StoreError;
use super::store::{JobStore, Snapshot, StoreHandle, StoreTask};
use serde::{Deserialize, Serialize};
use std::collections::{BTreeMap, HashMap};
use std::sync::Arc;
use tokio::sync::{mpsc, watch};
use tokio_util::sync::CancellationToken;

pub(crate) use super::command::{PrintCommand, UnknownCommand};

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
    /// At a pause the G-code file asked for (`M0`, `M600`, ...): parked, waiting for the
    /// operator's resume; the progress's `pause` says why.
    WaitingForOperator,
    /// The firmware halted (`M112`, a `kill()`, a thermal runaway, ...): it takes no job
    /// until the printer was reset (its boot banner seen on the link, or a new connection
    /// that completes the handshake, which a halted firmware never answers).
    Halted,
    BedNotCleared,
    /// Its eject sequence runs (or waits for the bed to cool): a short job of its own
    /// that pushes the print off (see `daemon::bed`).
    Ejecting,
    /// Its camera checks the bed against the picture of it empty.
    CheckingBed,
    /// Out of the queue for its care: held by hand, or a blocking `[[maintenance]]` task
    /// is due (see `daemon::care`); the detail says which.
    Maintenance,
    /// Switched off by its power switch (`[printer.power]`): idle and cool for long enough,
    /// or by hand; switched on again when it has work. The detail says why, and what the
    /// switch answered.
    Off,
    Disconnected,
    Stopped,
}

impl PrinterState {
    /// A print is under way on the printer: printing, paused, or at a pause its file asked
    /// for (what a camera watches, and where one repeating picture means it is frozen).
    pub(crate) fn has_print_under_way(self) -> bool {
        matches!(
            self,
            PrinterState::Printing | PrinterState::Paused | PrinterState::WaitingForOperator
        )
    }
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
    /// What [`time_left`](Self::time_left) comes to, seconds.
    pub remaining_s: Option<f64>,
    /// What the time left rests on.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub time_left: Option<super::time_left::TimeLeft>,
    /// The program's heat-up part is done (see `printer` on staggered heat-ups).
    pub heated: bool,
    pub paused: bool,
    /// Set while the print waits at a pause its file asked for.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub pause: Option<crate::marlin::stream::PauseInfo>,
    /// The parts of its plate dropped so far, each with where (its `print` is the
    /// supervisor's to fill in).
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub parts_cancelled: Vec<super::job::PartCancel>,
    /// Set while a stop waits for the printer's heat-up to end (its firmware reads nothing
    /// until then): which heater, where it is and must get to, how long that may take.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub stop_wait: Option<crate::marlin::stream::StopWait>,
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

/// What a printer's supervisor publishes about it, and only it changes.
#[derive(Debug, Clone, PartialEq)]
pub(crate) struct PrinterLive {
    pub state: PrinterState,
    pub firmware: String,
    pub port: String,
    pub job: Option<String>,
    pub progress: Option<LiveProgress>,
    /// None while not known now: not connected, or the printer stopped answering (stale
    /// figures are never shown as current).
    pub temperatures: Option<PrinterTemperatures>,
    /// Why the printer is in its state (e.g. the last connection error).
    pub detail: Option<String>,
}

impl PrinterLive {
    /// A printer whose supervisor has not connected yet.
    pub(crate) fn connecting(firmware: &str, port: &str) -> PrinterLive {
        PrinterLive {
            state: PrinterState::Connecting,
            firmware: firmware.to_string(),
            port: port.to_string(),
            job: None,
            progress: None,
            temperatures: None,
            detail: None,
        }
    }
}

/// A printer as shown (status, API, the farm database): its supervisor's live status, and
/// its bed gate from the store.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
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
    /// Its filament, spool and nozzle.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub holds: Option<super::filament::routing::Holding>,
    /// Its bed between prints (cleared by a person, ejected, checked by the camera) and
    /// the camera's last check of it.
    #[serde(default)]
    pub bed: super::bed::Bed,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub last_check: Option<super::bed::CheckRecord>,
    /// The job store's version (the status's `version`) in which this printer last looked
    /// for a job and took none (its bed waits to be cleared, or no ready job is for it):
    /// every job ready by then was passed over by it. 0 until it first looks.
    #[serde(default)]
    pub looked_at: u64,
    /// Its `[[maintenance]]` tasks, and where each stands (see `daemon::care`).
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub maintenance: Vec<super::care::TaskStatus>,
    /// What it has done since its counting began.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub care: Option<super::care::Counts>,
    /// Put into maintenance by hand: by whom, when, why.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub held: Option<super::care::Work>,
    /// It has a power switch (`[printer.power]`) its host switches.
    #[serde(default)]
    pub switchable: bool,
}

/// What the fleet keeps of a printer in the farm: the receiving ends of what its
/// supervisor owns.
#[derive(Clone)]
pub(crate) struct PrinterHandle {
    pub live: watch::Receiver<PrinterLive>,
    /// See [`PrinterStatus::looked_at`]; nobody waits on it.
    pub looked: watch::Receiver<u64>,
    /// The control channel into the print in progress; None between prints.
    pub print: watch::Receiver<Option<mpsc::Sender<PrintCommand>>>,
    /// Operators' switching of its power, to its supervisor.
    pub power: mpsc::Sender<PowerRequest>,
}

/// The owning ends of a printer's [`PrinterHandle`], held by its supervisor.
pub(crate) struct PrinterOwner {
    pub live: watch::Sender<PrinterLive>,
    pub looked: watch::Sender<u64>,
    pub print: watch::Sender<Option<mpsc::Sender<PrintCommand>>>,
    /// Operators' switching of its power; the supervisor alone takes them (the lock is
    /// never contended: it only lets the supervisor's shared reference receive).
    pub power: tokio::sync::Mutex<mpsc::Receiver<PowerRequest>>,
}

/// An operator's switching of a printer's power (`crispen power`, the dashboard), for its
/// supervisor, which carries it out between prints only.
#[derive(Debug)]
pub(crate) struct PowerRequest {
    pub on: bool,
    /// Off even though a finished print is still on its bed (never while it is hot).
    pub force: bool,
    /// A request its supervisor takes later than [`POWER_ANSWER`] after this is refused:
    /// its asker has been told it was not done.
    pub asked: std::time::Instant,
    pub reply: PowerReply,
}

/// The answer to a [`PowerRequest`]: whether the switch changed (false: it was already
/// so), or why it was not done.
pub(crate) type PowerReply = tokio::sync::oneshot::Sender<Result<bool, String>>;

/// How long an operator's power request waits for its supervisor.
pub(crate) const POWER_ANSWER: std::time::Duration = std::time::Duration::from_secs(15);

/// A new printer's owner (for its supervisor) and handle (for the farm).
pub(crate) fn printer_channels(initial: PrinterLive) -> (PrinterOwner, PrinterHandle) {
    let (live, live_rx) = watch::channel(initial);
    let (looked, looked_rx) = watch::channel(0);
    let (print, print_rx) = watch::channel(None);
    let (power, power_rx) = mpsc::channel(4);
    (
        PrinterOwner {
            live,
            looked,
            print,
            power: tokio::sync::Mutex::new(power_rx),
        },
        PrinterHandle {
            live: live_rx,
            looked: looked_rx,
            print: print_rx,
            power,
        },
    )
}

/// The rest of a shared farm as this host last read it from its database; written by
/// the shared-farm task only.
#[derive(Debug, Clone, Default, PartialEq)]
pub(crate) struct FarmView {
    /// None while the database answers; else why it does not.
    pub database: Option<String>,
    pub hosts: Vec<super::store::postgres::FarmHost>,
    /// Other hosts' printers, as their hosts last published them.
    pub printers: Vec<PrinterStatus>,
    /// Other hosts' printers' machines, for preparing their jobs here.
    pub machines: Vec<(String, crate::machine::Machine)>,
}

/// The `[farm] max_heating` permits: how many are held, owned here and changed only by
/// taking one ([`HeatingPermits::acquire`]) and dropping it.
#[derive(Clone, Default)]
pub struct HeatingPermits {
    in_use: Arc<watch::Sender<usize>>,
}

/// One printer's leave to heat up; handed back when dropped.
pub(crate) struct HeatingPermit {
    in_use: Arc<watch::Sender<usize>>,
}

impl Drop for HeatingPermit {
    fn drop(&mut self) {
        self.in_use.send_modify(|n| *n -= 1);
    }
}

impl HeatingPermits {
    /// Waits for a permit. The limit is read from the config in force at each try, so a
    /// reload applies to the next permit (a lower limit lets permits already held run
    /// out). Not raced with shutdown here: the caller does that.
    pub(crate) async fn acquire(&self, mut config: watch::Receiver<Arc<Config>>) -> HeatingPermit {
        let mut released = self.in_use.subscribe();
        loop {
            let limit = config.borrow_and_update().farm.max_heating;
            released.borrow_and_update();
            let taken = self.in_use.send_if_modified(|n| {
                let free = *n < limit;
                if free {
                    *n += 1;
                }
                free
            });
            if taken {
                return HeatingPermit {
                    in_use: Arc::clone(&self.in_use),
                };
            }
            tokio::select! {
                _ = released.changed() => {}
                _ = config.changed() => {}
            }
        }
    }

    /// Permits held now.
    #[cfg(test)]
    pub(crate) fn in_use(&self) -> usize {
        *self.in_use.borrow()
    }
}

/// A preparation in progress.
#[derive(Clone)]
pub(crate) struct Preparation {
    pub step: String,
    /// Fired by `crispen cancel` (and by shutdown, of which it is a child): the
    /// preparation's process is killed at once.
    pub cancel: CancellationToken,
}

pub struct Farm {
    /// The config in force; its sender here is never sent on (see [`ConfigOwner`]), as for
    /// the printers, the preparations and the shared view below.
    config: watch::Sender<Arc<Config>>,
    /// The job store's task: the only way a job changes ([`Farm::jobs`]).
    jobs: StoreHandle,
    /// The printers of this host; the fleet adds and removes them ([`PrintersOwner`]).
    printers: watch::Sender<BTreeMap<String, PrinterHandle>>,
    /// Jobs being prepared; the preparation queue adds, steps and removes them
    /// ([`PreparingOwner`]).
    preparing: watch::Sender<BTreeMap<String, Preparation>>,
    pub heating: HeatingPermits,
    /// The rest of a shared farm; the shared-farm task writes it ([`SharedOwner`]).
    shared: watch::Sender<Option<FarmView>>,
    /// Cancelled once SIGTERM arrived: no new work is taken, waits end.
    pub(crate) shutdown: Stop,
    /// Cancelled when the prints in progress are to stop safely (heaters off): at once
    /// with `on_shutdown = "stop"`; with "finish", at a second SIGTERM or when
    /// `finish_timeout_s` ran out ([`StopOwner::stop_prints`]).
    pub(crate) stop_prints: Stop,
    /// The farm database, when `[store] postgres` shares the farm with other hosts.
    pub db: std::sync::OnceLock<crate::daemon::store::postgres::PgStore>,
}

impl Farm {
    /// Builds the farm around the store's task, which is returned for the caller to run
    /// (the service runs it in its supervised set; see [`super::store::start`]), with the
    /// owners of the farm's other state, for the caller to hand each to its owner.
    pub(crate) fn new(config: Config, store: impl JobStore) -> (Arc<Farm>, Owners, StoreTask) {
        let retention = super::store::Retention {
            live_for: config.history.live_for,
            live_jobs: config.history.live_jobs,
            keep_for: config.history.keep_for,
        };
        let (jobs, task) = super::store::start(store, retention);
        let (shutdown, stop_prints) = (CancellationToken::new(), CancellationToken::new());
        let farm = Arc::new(Farm {
            config: watch::channel(Arc::new(config)).0,
            jobs,
            printers: watch::channel(BTreeMap::new()).0,
            preparing: watch::channel(BTreeMap::new()).0,
            heating: HeatingPermits::default(),
            shared: watch::channel(None).0,
            shutdown: Stop(shutdown.clone()),
            stop_prints: Stop(stop_prints.clone()),
            db: Default::default(),
        });
        let owners = Owners {
            config: ConfigOwner(farm.config.clone()),
            printers: PrintersOwner(farm.printers.clone()),
            preparing: PreparingOwner(farm.preparing.clone()),
            shared: SharedOwner(farm.shared.clone()),
            stop: StopOwner {
                shutdown,
                stop_prints,
                config: farm.config.subscribe(),
            },
        };
        (farm, owners, task)
    }

    pub(crate) fn config(&self) -> Arc<Config> {
        self.config.borrow().clone()
    }

    /// Follows the config in force.
    pub(crate) fn watch_config(&self) -> watch::Receiver<Arc<Config>> {
        self.config.subscribe()
    }

    /// The job store's task: every change of a job or a bed gate is a request to it, and
    /// it alone logs and counts what changed.
    pub(crate) fn jobs(&self) -> &StoreHandle {
        &self.jobs
    }

    /// The jobs and bed gates as of the store's last change (a glance: no round trip).
    pub(crate) fn store(&self) -> Arc<Snapshot> {
        self.jobs.snapshot()
    }

    /// Follows the jobs and bed gates.
    pub(crate) fn watch_jobs(&self) -> watch::Receiver<Arc<Snapshot>> {
        self.jobs.subscribe()
    }

    pub(crate) fn stopping(&self) -> bool {
        self.shutdown.is_cancelled()
    }

    /// Waits for one of the `[farm] max_heating` heating permits (see
    /// [`HeatingPermits::acquire`]).
    pub(crate) async fn heating_permit(&self) -> HeatingPermit {
        self.heating.acquire(self.watch_config()).await
    }

    /// The statistics of `period`, with every configured printer and folder listed.
    pub(crate) async fn stats(
        &self,
        period: super::store::stats::Period,
    ) -> Result<super::store::stats::Stats, StoreError> {
        let config = self.config();
        let printers = config.printers.iter().map(|p| p.name.clone()).collect();
        let folders = config
            .folders
            .iter()
            .map(|f| {
                f.path.file_name().map_or_else(
                    || f.path.display().to_string(),
                    |n| n.to_string_lossy().into_owned(),
                )
            })
            .collect();
        let now = super::job::now_s();
        self.jobs.stats(period, printers, folders, now).await
    }

    // Printers (the fleet's: see [`PrintersOwner`]).

    /// The handle of this host's printer `name`.
    pub(crate) fn printer(&self, name: &str) -> Option<PrinterHandle> {
        self.printers.borrow().get(name).cloned()
    }

    /// Follows which printers this host has.
    pub(crate) fn watch_printers(&self) -> watch::Receiver<BTreeMap<String, PrinterHandle>> {
        self.printers.subscribe()
    }

    /// This host's printers as shown: each supervisor's live status with the bed gate
    /// from the store (the one place `bed_cleared` is made).
    pub(crate) fn local_printers(&self) -> Vec<PrinterStatus> {
        let store = self.store();
        let config = self.config();
        let host = config.store.as_ref().map(|_| config.farm.host.clone());
        let names: Vec<String> = self.printers.borrow().keys().cloned().collect();
        let names: Vec<&str> = names.iter().map(String::as_str).collect();
        let offers = offers(&config, &store, &names);
        let now = super::job::now_s();
        self.printers
            .borrow()
            .iter()
            .map(|(name, handle)| {
                let live = handle.live.borrow().clone();
                let gate = store.gate(name);
                let care = store.inventory().care.get(name);
                let holds = offers
                    .iter()
                    .find(|o| o.printer == name)
                    .map(super::filament::routing::Holding::of);
                PrinterStatus {
                    holds,
                    name: name.clone(),
                    state: live.state,
                    firmware: live.firmware,
                    port: live.port,
                    job: live.job,
                    progress: live.progress,
                    temperatures: live.temperatures,
                    detail: live.detail,
                    bed_cleared: !gate.bed_not_cleared(),
                    bed: gate.bed,
                    last_check: gate.last_check,
                    host: host.clone(),
                    offline: false,
                    looked_at: *handle.looked.borrow(),
                    maintenance: super::care::status(config.tasks_of(name), care, now),
                    care: care.map(|c| c.counts.clone()),
                    held: care.and_then(|c| c.held.clone()),
                    switchable: config
                        .printers
                        .iter()
                        .any(|p| &p.name == name && p.power.is_some()),
                }
            })
            .collect()
    }

    /// Every printer that may take a job, by name, with its machine: this host's, and in a
    /// shared farm the other hosts' as they registered them.
    pub(crate) fn printer_machines(&self) -> Vec<(String, crate::machine::Machine)> {
        let mut all: Vec<(String, crate::machine::Machine)> = self
            .config()
            .printers
            .iter()
            .map(|p| (p.name.clone(), p.machine.clone()))
            .collect();
        if let Some(view) = &*self.shared.borrow() {
            for (name, machine) in &view.machines {
                if !all.iter().any(|(n, _)| n == name) {
                    all.push((name.clone(), machine.clone()));
                }
            }
        }
        all
    }

    // Preparations (the preparation queue's: see [`PreparingOwner`]).

    /// Stops a job's preparation in progress, if any.
    pub(crate) fn cancel_preparation(&self, id: &str) {
        if let Some(p) = self.preparing.borrow().get(id) {
            p.cancel.cancel();
        }
    }

    /// Each preparation's current step, by job.
    pub(crate) fn preparation_steps(&self) -> HashMap<String, String> {
        self.preparing
            .borrow()
            .iter()
            .map(|(id, p)| (id.clone(), p.step.clone()))
            .collect()
    }

    // The rest of a shared farm (the shared-farm task's: see [`SharedOwner`]).

    /// The rest of the farm as last read (None: not shared, or not read yet).
    pub(crate) fn shared(&self) -> Option<FarmView> {
        self.shared.borrow().clone()
    }

    /// Follows the rest of a shared farm.
    pub(crate) fn watch_shared(&self) -> watch::Receiver<Option<FarmView>> {
        self.shared.subscribe()
    }

    /// Follows everything shown of the farm.
    pub(crate) fn watch(&self) -> FarmWatch {
        let mut watch = FarmWatch {
            jobs: self.watch_jobs(),
            config: self.watch_config(),
            printers: self.watch_printers(),
            preparing: self.preparing.subscribe(),
            shared: self.watch_shared(),
            lives: BTreeMap::new(),
        };
        watch.follow_printers();
        watch
    }
}

/// The senders of the farm's state besides the store's, each for its one owner: the
/// reload path, the fleet, the preparation queue, the shared-farm task. Whoever builds the
/// farm hands them out; nothing else can change these pieces.
pub(crate) struct Owners {
    pub(crate) config: ConfigOwner,
    pub(crate) printers: PrintersOwner,
    pub(crate) preparing: PreparingOwner,
    pub(crate) shared: SharedOwner,
    pub(crate) stop: StopOwner,
}

/// A stop the service decides, as the farm's tasks see it: whether it came, a wait for
/// it, and tokens of their own that end with it (cancelling one never reaches it).
#[derive(Clone)]
pub(crate) struct Stop(CancellationToken);

impl Stop {
    pub(crate) fn is_cancelled(&self) -> bool {
        self.0.is_cancelled()
    }

    pub(crate) fn cancelled(&self) -> tokio_util::sync::WaitForCancellationFuture<'_> {
        self.0.cancelled()
    }

    pub(crate) fn child_token(&self) -> CancellationToken {
        self.0.child_token()
    }
}

/// Stops the farm (the service's, at a signal).
pub(crate) struct StopOwner {
    shutdown: CancellationToken,
    stop_prints: CancellationToken,
    config: watch::Receiver<Arc<Config>>,
}

impl StopOwner {
    /// Takes no new work; the prints in progress finish or stop as `[farm] on_shutdown`
    /// (in force now) says.
    pub(crate) fn begin(&self) {
        self.shutdown.cancel();
        if self.config.borrow().farm.on_shutdown == super::config::OnShutdown::Stop {
            self.stop_prints();
        }
    }

    /// Stops the prints in progress safely (heaters off; their jobs end interrupted) and
    /// takes no new work.
    pub(crate) fn stop_prints(&self) {
        self.shutdown.cancel();
        self.stop_prints.cancel();
    }
}

/// Puts a config in force (the reload path's).
pub(crate) struct ConfigOwner(watch::Sender<Arc<Config>>);

impl ConfigOwner {
    pub(crate) fn set(&self, config: Config) {
        self.0.send_replace(Arc::new(config));
    }
}

/// Which printers this host has (the fleet's).
pub(crate) struct PrintersOwner(watch::Sender<BTreeMap<String, PrinterHandle>>);

impl PrintersOwner {
    /// Adds a printer, as its supervisor starts.
    pub(crate) fn add(&self, name: &str, handle: PrinterHandle) {
        self.0.send_modify(|p| {
            p.insert(name.to_string(), handle);
        });
    }

    /// Removes a printer, once its retired supervisor has ended.
    pub(crate) fn remove(&self, name: &str) {
        self.0.send_if_modified(|p| p.remove(name).is_some());
    }
}

/// The preparations in progress (the preparation queue's; its tasks share it).
#[derive(Clone)]
pub(crate) struct PreparingOwner(watch::Sender<BTreeMap<String, Preparation>>);

impl PreparingOwner {
    /// A preparation started.
    pub(crate) fn start(&self, id: &str, cancel: CancellationToken) {
        self.0.send_modify(|p| {
            let step = "starting".into();
            p.insert(id.to_string(), Preparation { step, cancel });
        });
    }

    /// A preparation's step changed.
    pub(crate) fn step(&self, id: &str, step: String) {
        self.0.send_if_modified(|p| match p.get_mut(id) {
            Some(p) if p.step != step => {
                p.step = step;
                true
            }
            _ => false,
        });
    }

    /// A preparation ended.
    pub(crate) fn end(&self, id: &str) {
        self.0.send_if_modified(|p| p.remove(id).is_some());
    }
}

/// The view of the rest of a shared farm (the shared-farm task's).
pub(crate) struct SharedOwner(watch::Sender<Option<FarmView>>);

impl SharedOwner {
    /// Changes the view; the followers wake only when it differs.
    pub(crate) fn set(&self, change: impl FnOnce(&mut FarmView)) {
        self.0.send_if_modified(|view| {
            let before = view.clone();
            change(view.get_or_insert_with(FarmView::default));
            *view != before
        });
    }
}

/// Receivers of every piece of the farm's state: [`FarmWatch::changed`] resolves on the
/// next change of any since the last call (or since it was made).
pub(crate) struct FarmWatch {
    jobs: watch::Receiver<Arc<Snapshot>>,
    config: watch::Receiver<Arc<Config>>,
    printers: watch::Receiver<BTreeMap<String, PrinterHandle>>,
    preparing: watch::Receiver<BTreeMap<String, Preparation>>,
    shared: watch::Receiver<Option<FarmView>>,
    /// Each printer's live status, followed from when the printer was first seen here.
    lives: BTreeMap<String, watch::Receiver<PrinterLive>>,
}

impl FarmWatch {
    /// Follows the printers there are now. The set is read without marking it seen: a
    /// change of it not yet seen still ends the next wait.
    fn follow_printers(&mut self) {
        let printers = self.printers.borrow();
        self.lives.retain(|name, live| {
            printers
                .get(name)
                .is_some_and(|h| h.live.same_channel(live))
        });
        for (name, handle) in printers.iter() {
            self.lives.entry(name.clone()).or_insert_with(|| {
                let mut live = handle.live.clone();
                live.mark_unchanged();
                live
            });
        }
    }

    /// Waits for the next change of the farm after the last call (or since made).
    pub(crate) async fn changed(&mut self) {
        self.follow_printers();
        let lives = &mut self.lives;
        let live = async {
            let mut open: Vec<&mut watch::Receiver<PrinterLive>> = lives.values_mut().collect();
            loop {
                if open.is_empty() {
                    return std::future::pending().await;
                }
                let (changed, i) = {
                    let waits = open.iter_mut().map(|l| Box::pin(l.changed()));
                    let (changed, i, _rest) = futures_util::future::select_all(waits).await;
                    (changed, i)
                };
                match changed {
                    Ok(()) => return,
                    // Its supervisor ended: nothing more comes from it.
                    Err(_) => {
                        open.swap_remove(i);
                    }
                }
            }
        };
        // A closed channel (its owner gone) is never a change again.
        tokio::select! {
            Ok(()) = self.jobs.changed() => {}
            Ok(()) = self.config.changed() => {}
            Ok(()) = self.printers.changed() => {}
            Ok(()) = self.preparing.changed() => {}
            Ok(()) = self.shared.changed() => {}
            () = live => {}
        }
    }
}

/// What each printer of `printers` offers a job now: see [`offer`]; the filament the job
/// printing on it will take is reserved.
pub(crate) fn offers<'a>(
    config: &'a Config,
    snapshot: &'a Snapshot,
    printers: &[&str],
) -> Vec<super::filament::routing::Offer<'a>> {
    config
        .printers
        .iter()
        .filter(|p| printers.contains(&p.name.as_str()))
        .map(|p| {
            let reserved_mm = snapshot
                .jobs()
                .filter(|j| {
                    j.state == super::job::JobState::Printing
                        && j.printer.as_deref() == Some(p.name.as_str())
                })
                .filter_map(|j| j.need_on(&p.machine.name))
                .map(|n| n.mm)
                .sum();
            offer(p, snapshot.inventory(), reserved_mm)
        })
        .collect()
}

/// What `printer` offers a job: its config (nozzle, groups, default filament) with what
/// the inventory records it holds; `reserved_mm` of its spool are promised to its current
/// job. One place for the claim and the reasons shown to the operator.
pub(crate) fn offer<'a>(
    printer: &'a super::config::PrinterConfig,
    inventory: &'a super::filament::Inventory,
    reserved_mm: f64,
) -> super::filament::routing::Offer<'a> {
    let spool = inventory.spool_on(&printer.name);
    let unloaded = inventory.loaded.get(&printer.name) == Some(&super::filament::Loaded::Nothing);
    super::filament::routing::Offer {
        printer: &printer.name,
        machine: &printer.machine.name,
        spool,
        filament: match (spool, unloaded) {
            (Some(s), _) => Some(&s.filament),
            (None, true) => None,
            (None, false) => printer.filament.as_ref(),
        },
        unloaded,
        nozzle_mm: printer.machine.nozzle_mm,
        hardened: printer.hardened,
        machine_filament_mm: printer.machine.filament_mm,
        tags: &printer.tags,
        reserved_mm,
    }
}

/// The printers `job`'s folder lets print it: as the config has it, or as recorded when
/// the job came from another host of a shared farm.
pub(crate) fn folder_rule<'a>(
    config: &'a Config,
    job: &'a super::job::Job,
) -> Option<&'a Vec<String>> {
    match (&job.origin, config.folder(&job.folder)) {
        (Some(o), f) if o.host != config.farm.host || f.is_none() => Some(&o.printers),
        (_, f) => f.map(|f| &f.printers),
    }
}

/// Why no printer can take a ready job now; None when one can (or it is not ready, or no
/// printer of this host serves it). `offers`: this host's printers' (see [`offers`]).
/// Every printer that serves it is named with why it cannot, its machine's refusal of
/// the file included.
pub(crate) fn waiting<'a>(
    config: &Config,
    job: &'a super::job::Job,
    offers: &[super::filament::routing::Offer<'a>],
) -> Option<super::filament::routing::Waiting<'a>> {
    use super::filament::routing::{refusal, Refusal, Waiting};
    if job.state != super::job::JobState::Ready || job.held() {
        return None;
    }
    let rule = folder_rule(config, job)?;
    let wanted = job.wanted_printer();
    let serving: Vec<&super::filament::routing::Offer> = offers
        .iter()
        .filter(|o| rule.iter().any(|p| p == o.printer) && wanted.is_none_or(|w| w == o.printer))
        .collect();
    if serving.is_empty() {
        return None;
    }
    let mut refused = Vec::new();
    for o in serving {
        let need = job.need_on(o.machine);
        let why = match (job.gcode_for(o.machine), job.machines.get(o.machine)) {
            (Some(_), _) => refusal(&job.asks, need, o),
            (None, Some(super::job::ForMachine::Refused(reason))) => Some(Refusal::Machine {
                machine: o.machine.to_string(),
                reason: Some(reason.clone()),
            }),
            // Not prepared for its machine (its nozzle was not the one asked, or it came
            // after): what it holds says why, if that does.
            (None, _) => Some(refusal(&job.asks, need, o).unwrap_or(Refusal::Machine {
                machine: o.machine.to_string(),
                reason: None,
            })),
        };
        refused.push((o.clone(), why?));
    }
    Some(Waiting {
        asks: &job.asks,
        refused,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    fn farm(max_heating: usize, spool: &std::path::Path) -> (Arc<Farm>, Owners) {
        let text = format!("[spool]\ndir = \"spool\"\n[farm]\nmax_heating = {max_heating}\n");
        let config = Config::parse(&text, &spool.join("crispen.toml")).unwrap();
        let store = super::super::store::spool::SpoolStore::open(&spool.join("spool")).unwrap();
        let (farm, owners, task) = Farm::new(config, store);
        tokio::spawn(task);
        (farm, owners)
    }

    /// `max_heating` applies on reload: raising it lets a waiting printer heat at once
    /// (the permits were once a semaphore sized at startup).
    #[tokio::test(start_paused = true)]
    async fn max_heating_applies_on_reload() {
        let tmp = tempfile::tempdir().unwrap();
        let (farm, owners) = farm(1, tmp.path());
        let first = farm.heating_permit().await;
        let waiting = tokio::spawn({
            let farm = Arc::clone(&farm);
            async move { farm.heating_permit().await }
        });
        tokio::task::yield_now().await;
        assert!(!waiting.is_finished(), "one permit only");
        let mut raised = (*farm.config()).clone();
        raised.farm.max_heating = 2;
        owners.config.set(raised);
        let second = tokio::time::timeout(std::time::Duration::from_secs(30), waiting)
            .await
            .expect("the raised limit lets the waiting printer heat")
            .unwrap();
        assert_eq!(farm.heating.in_use(), 2);
        drop((first, second));
        assert_eq!(farm.heating.in_use(), 0, "permits are handed back");
    }

    /// A printer's bed gate is shown from the store, as it is now: closed after a print,
    /// open after a clear. It was once a field set when the printer started and never
    /// changed, corrected where it was read, and published stale to the farm database.
    #[tokio::test]
    async fn bed_cleared_is_the_stores_gate() {
        let tmp = tempfile::tempdir().unwrap();
        let (farm, owners) = farm(1, tmp.path());
        let (_owner, handle) = printer_channels(PrinterLive::connecting("marlin2", "/dev/x"));
        owners.printers.add("p1", handle);
        let shown = |farm: &Farm| farm.local_printers()[0].bed_cleared;
        assert!(shown(&farm));
        farm.jobs().close_gate("p1", "0001-a").await.unwrap();
        assert!(!shown(&farm), "a finished print is on the bed");
        assert!(farm.jobs().clear_gate("p1").await.unwrap());
        assert!(shown(&farm), "cleared");
    }

    /// The farm's watch ends a wait on a change of a printer's live status, once, and
    /// not for a change from before it was made (it once took every earlier change for a
    /// new one, and the event stream spun).
    #[tokio::test(start_paused = true)]
    async fn the_farm_watch_wakes_once_per_change() {
        use std::time::Duration;
        let tmp = tempfile::tempdir().unwrap();
        let (farm, owners) = farm(1, tmp.path());
        let (owner, handle) = printer_channels(PrinterLive::connecting("marlin2", "/dev/x"));
        owners.printers.add("p1", handle);
        owner.live.send_modify(|p| p.state = PrinterState::Idle);
        let mut watch = farm.watch();
        let quiet = Duration::from_secs(600);
        assert!(tokio::time::timeout(quiet, watch.changed()).await.is_err());
        owner.live.send_modify(|p| p.state = PrinterState::Printing);
        tokio::time::timeout(quiet, watch.changed())
            .await
            .expect("woken by the change");
        assert!(tokio::time::timeout(quiet, watch.changed()).await.is_err());
        farm.jobs().close_gate("p1", "0001-a").await.unwrap();
        tokio::time::timeout(quiet, watch.changed())
            .await
            .expect("woken by the gate");
    }
}
