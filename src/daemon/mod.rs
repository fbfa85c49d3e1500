//! The print-farm daemon behind `crispen run`: hot folders feed a job spool, jobs are
//! prepared (enhanced and sliced) off the async runtime, and each printer's supervisor
//! prints ready jobs one at a time, waiting for its bed to be cleared in between.
//!
//! - [`config`]: the TOML configuration, checked in two stages.
//! - [`job`]: the spool of job directories and their atomically written state.
//! - [`postgres`]: the farm's queue in PostgreSQL, shared by several hosts (not wired in yet).
//! - [`hotfolder`]: deciding when a dropped file is complete.
//! - [`prepare`]: sidecars and the slicer step.
//! - [`printer`]: printer supervisors and staggered heat-ups.
//! - [`control`]: the JSON-lines control socket and its client.
//! - [`farm`]: the state all of these share.
//!
//! [`run`] wires them together; I/O endpoints (printer ports, the preparer) are resolved
//! here, at startup and on a reload, so no other part knows whether a printer is simulated.

pub mod config;
pub mod control;
pub mod farm;
pub mod hotfolder;
pub mod job;
pub mod ports;
pub mod postgres;
pub mod prepare;
pub mod printer;

use config::{Config, PrinterConfig, PrinterPort};
use farm::{Farm, PrinterState, PrinterStatus};
use job::{JobState, JobStore};
use std::collections::BTreeMap;
use std::path::PathBuf;
use std::sync::Arc;
use std::time::Duration;
use tokio::sync::{mpsc, watch};
use tokio_util::sync::CancellationToken;
use tracing::Instrument;

#[derive(Debug, thiserror::Error)]
pub enum DaemonError {
    #[error(transparent)]
    Config(#[from] config::ConfigError),
    #[error(transparent)]
    Store(#[from] job::StoreError),
    #[error(transparent)]
    Control(#[from] control::ControlError),
    #[error("printer {printer}: cannot start its simulator: {message}")]
    Simulator { printer: String, message: String },
    #[error("cannot install signal handlers: {0}")]
    Signals(std::io::Error),
    #[error("cannot find this program to run preparations with: {0}")]
    PrepareProgram(std::io::Error),
    #[error("[http] listen = \"{listen}\": cannot listen: {source} (hint: is another program on this port? Under systemd, install config/crispen-http.conf as a drop-in so the unit allows TCP)")]
    Http {
        listen: std::net::SocketAddr,
        #[source]
        source: std::io::Error,
    },
}

/// How `crispen run` was asked to behave.
#[derive(Debug, Clone, Default)]
pub struct RunOptions {
    /// The config file to re-read on SIGHUP (None: the built-in default, not reloadable).
    pub config_path: Option<PathBuf>,
    /// Exit once no job has work left and at least one job finished during this run.
    pub exit_when_idle: bool,
    /// The `crispen` program whose `prepare-job` prepares a job (None: this program).
    pub prepare_program: Option<PathBuf>,
}

/// The printer supervisors, one per configured printer, and how a reload changes them:
/// a printer added to the config starts at once; one removed or changed retires when it
/// is not printing (a print in progress is never cut short by a reload), and a changed
/// one then starts again with its new settings.
struct Fleet {
    running: BTreeMap<String, Supervised>,
    /// Retired supervisors still finishing a print.
    retiring: Vec<Supervised>,
    /// New settings for printers whose old supervisor is still retiring.
    waiting: Vec<PrinterConfig>,
}

struct Supervised {
    spec: PrinterConfig,
    task: tokio::task::JoinHandle<()>,
    retire: watch::Sender<bool>,
    /// Keeps a simulated printer alive as long as its supervisor.
    _simulator: Option<crate::marlin::sim::SimHandle>,
}

impl Fleet {
    fn start_all(farm: &Arc<Farm>, printers: &[PrinterConfig]) -> Result<Fleet, DaemonError> {
        let mut fleet = Fleet {
            running: BTreeMap::new(),
            retiring: Vec::new(),
            waiting: Vec::new(),
        };
        for spec in printers {
            fleet.start(farm, spec.clone())?;
        }
        Ok(fleet)
    }

    /// Resolves the printer's port (starting its simulator if it has one), shows it in
    /// the status and starts its supervisor.
    fn start(&mut self, farm: &Arc<Farm>, spec: PrinterConfig) -> Result<(), DaemonError> {
        let (port, simulator) = match &spec.port {
            PrinterPort::Serial(path) => (path.clone(), None),
            PrinterPort::Simulated {
                time_scale,
                seed,
                record,
            } => {
                let mut sim = crate::marlin::sim::SimConfig::new(spec.firmware);
                sim.time_scale = *time_scale;
                sim.seed = *seed;
                sim.record = record.clone();
                let handle =
                    crate::marlin::sim::spawn(sim).map_err(|e| DaemonError::Simulator {
                        printer: spec.name.clone(),
                        message: e.to_string(),
                    })?;
                let device = handle.device_path().to_path_buf();
                tracing::info!(printer = %spec.name, device = %device.display(), time_scale, "simulated printer started");
                (device, Some(handle))
            }
        };
        farm.printers
            .lock()
            .unwrap_or_else(|e| e.into_inner())
            .insert(
                spec.name.clone(),
                PrinterStatus {
                    name: spec.name.clone(),
                    state: PrinterState::Connecting,
                    firmware: spec.firmware.name().to_string(),
                    port: port.display().to_string(),
                    job: None,
                    progress: None,
                    detail: None,
                    bed_cleared: true,
                },
            );
        let connector = Box::new(printer::MarlinConnector {
            port,
            firmware: spec.firmware,
            baud: spec.baud,
            heat_timeout: spec.heat_timeout,
        });
        let (retire, retired) = watch::channel(false);
        let task = tokio::spawn(printer::supervise(
            Arc::clone(farm),
            spec.name.clone(),
            connector,
            retired,
        ));
        self.running.insert(
            spec.name.clone(),
            Supervised {
                spec,
                task,
                retire,
                _simulator: simulator,
            },
        );
        Ok(())
    }

    /// Applies a reloaded config's printers.
    fn apply(&mut self, farm: &Arc<Farm>, printers: &[PrinterConfig]) {
        let names: Vec<String> = self.running.keys().cloned().collect();
        for name in names {
            let spec = &self.running[&name].spec;
            match printers.iter().find(|p| p.name == name) {
                Some(new) if new == spec => {}
                new => {
                    let old = self.running.remove(&name).expect("listed above");
                    old.retire.send_replace(true);
                    tracing::info!(printer = %name, "config reload: retiring the printer's supervisor");
                    self.retiring.push(old);
                    if let Some(new) = new {
                        self.waiting.push(new.clone());
                    }
                }
            }
        }
        self.waiting
            .retain(|w| printers.iter().any(|p| p.name == w.name));
        for new in printers {
            if !self.running.contains_key(&new.name)
                && !self.waiting.iter().any(|w| w.name == new.name)
            {
                self.waiting.push(new.clone());
            }
        }
        self.settle(farm);
    }

    /// Lets go of retired supervisors that have finished and starts the waiting printers
    /// whose names are free again.
    fn settle(&mut self, farm: &Arc<Farm>) {
        self.retiring.retain(|s| !s.task.is_finished());
        let waiting = std::mem::take(&mut self.waiting);
        for spec in waiting {
            if self.retiring.iter().any(|s| s.spec.name == spec.name) {
                self.waiting.push(spec);
                continue;
            }
            let name = spec.name.clone();
            if let Err(e) = self.start(farm, spec) {
                tracing::error!(printer = %name, error = %e, "config reload: cannot start the printer");
            }
        }
    }

    /// Waits for every supervisor to end (after [`Farm::begin_stop`]).
    async fn join(self) {
        for s in self.running.into_values().chain(self.retiring) {
            let _ = s.task.await;
        }
    }
}

/// Runs the daemon until SIGTERM/SIGINT (or until idle with `exit_when_idle`). The
/// shutdown token made here is handed down to every task; each races it at its waits.
pub async fn run(config: Config, options: RunOptions) -> Result<(), DaemonError> {
    use tokio::signal::unix::{signal, SignalKind};
    let prepare_program = match &options.prepare_program {
        Some(p) => p.clone(),
        None => std::env::current_exe().map_err(DaemonError::PrepareProgram)?,
    };
    let mut sigterm = signal(SignalKind::terminate()).map_err(DaemonError::Signals)?;
    let mut sigint = signal(SignalKind::interrupt()).map_err(DaemonError::Signals)?;
    let mut sighup = signal(SignalKind::hangup()).map_err(DaemonError::Signals)?;

    let mut store = JobStore::open(&config.spool_dir)?;
    for id in store.recover()? {
        let job = store.get(&id).expect("recovered job exists");
        tracing::warn!(job = %id, state = job.state.name(), "job found mid-flight after a restart");
    }
    let listener = control::bind(&config.socket)?;
    let http_listener = match &config.http {
        None => None,
        Some(http) => {
            let bound = crate::http::bind(http)
                .await
                .map_err(|source| DaemonError::Http {
                    listen: http.listen,
                    source,
                })?;
            let address = bound
                .local_addr()
                .map_or_else(|_| http.listen.to_string(), |a| a.to_string());
            tracing::info!(address = %address, dashboard = %format!("http://{address}/"), "http: listening");
            Some((bound, http.clone()))
        }
    };
    tracing::info!(
        config = %config.source.display(),
        spool = %config.spool_dir.display(),
        socket = %config.socket.display(),
        printers = config.printers.len(),
        folders = config.folders.len(),
        "crispen daemon starting"
    );
    let shutdown = CancellationToken::new();
    let farm = Farm::new(config.clone(), store, shutdown.clone());
    let mut fleet = Fleet::start_all(&farm, &config.printers)?;
    let control_task = tokio::spawn(control::serve(Arc::clone(&farm), listener));
    let http_task = http_listener
        .map(|(bound, http)| tokio::spawn(crate::http::serve(Arc::clone(&farm), http, bound)));
    let mut pickup = spawn_pickup(&farm, &config);
    let prepare_task = tokio::spawn(prepare_loop(Arc::clone(&farm), prepare_program));

    let _ = sd_notify::notify(false, &[sd_notify::NotifyState::Ready]);
    let mut watchdog_usec = 0u64;
    let watchdog = sd_notify::watchdog_enabled(false, &mut watchdog_usec);
    let tick = if watchdog {
        Duration::from_micros(watchdog_usec / 2).max(Duration::from_millis(100))
    } else {
        Duration::from_secs(5)
    };
    let mut ticker = tokio::time::interval(tick);
    let mut wake = farm.subscribe();
    loop {
        tokio::select! {
            _ = sigterm.recv() => { tracing::info!("SIGTERM: stopping"); break; }
            _ = sigint.recv() => { tracing::info!("SIGINT: stopping"); break; }
            _ = sighup.recv() => {
                reload(&farm, &options, &mut pickup, &mut fleet);
            }
            _ = ticker.tick() => {
                fleet.settle(&farm);
                let pending = Arc::clone(&farm);
                tokio::task::spawn_blocking(move || pending.store().write_pending());
                if watchdog {
                    let _ = sd_notify::notify(false, &[sd_notify::NotifyState::Watchdog]);
                }
                let summary = summary(&farm);
                let _ = sd_notify::notify(false, &[sd_notify::NotifyState::Status(&summary)]);
            }
            _ = wake.changed() => {
                if options.exit_when_idle
                    && farm.finished_this_run.load(std::sync::atomic::Ordering::SeqCst) > 0
                    && farm.idle()
                {
                    tracing::info!("no work left: exiting (--exit-when-idle)");
                    break;
                }
            }
        }
    }

    // Shutdown: take no new work; preparation in progress is stopped (its job goes back to
    // the queue); prints finish or stop per config.
    let _ = sd_notify::notify(false, &[sd_notify::NotifyState::Stopping]);
    farm.begin_stop();
    pickup.abort();
    let _ = prepare_task.await;
    fleet.join().await;
    control_task.abort();
    if let Some(task) = http_task {
        task.abort();
    }
    let _ = std::fs::remove_file(&farm.config().socket);
    tracing::info!("crispen daemon stopped");
    Ok(())
}

fn summary(farm: &Farm) -> String {
    let printers = farm.printers.lock().unwrap_or_else(|e| e.into_inner());
    let printing = printers
        .values()
        .filter(|p| p.state == PrinterState::Printing)
        .count();
    let total = printers.len();
    drop(printers);
    let store = farm.store();
    let count = |s: JobState| store.jobs().filter(|j| j.state == s).count();
    format!(
        "{printing}/{total} printers printing; jobs: {} queued, {} preparing, {} ready, {} failed",
        count(JobState::Queued),
        count(JobState::Preparing),
        count(JobState::Ready),
        count(JobState::Failed)
    )
}

/// SIGHUP: re-read the config file. A bad file is refused and the old config kept. Folder,
/// farm and printer changes take effect (printers as [`Fleet::apply`] says); the spool and
/// the control socket need a restart.
fn reload(
    farm: &Arc<Farm>,
    options: &RunOptions,
    pickup: &mut tokio::task::JoinHandle<()>,
    fleet: &mut Fleet,
) {
    let Some(path) = &options.config_path else {
        tracing::warn!("SIGHUP: running on the built-in default config; nothing to reload");
        return;
    };
    match Config::load(path) {
        Err(e) => tracing::error!(error = %e, "SIGHUP: new config refused; keeping the old one"),
        Ok(new) => {
            let old = farm.config();
            let http_changed = new.http.as_ref().map(|h| (h.listen, &h.api_key))
                != old.http.as_ref().map(|h| (h.listen, &h.api_key));
            if new.spool_dir != old.spool_dir || new.socket != old.socket || http_changed {
                tracing::warn!(
                    "SIGHUP: [spool], [control] and [http] changes need a restart; ignored"
                );
            }
            let mut merged = new;
            merged.spool_dir = old.spool_dir.clone();
            merged.socket = old.socket.clone();
            merged.http = old.http.clone();
            pickup.abort();
            *farm.config.write().unwrap_or_else(|e| e.into_inner()) = Arc::new(merged.clone());
            fleet.apply(farm, &merged.printers);
            *pickup = spawn_pickup(farm, &merged);
            farm.bump();
            tracing::info!("SIGHUP: config reloaded");
        }
    }
}

/// Starts watching the hot folders and admitting complete files as jobs.
fn spawn_pickup(farm: &Arc<Farm>, config: &Config) -> tokio::task::JoinHandle<()> {
    let folders: Vec<PathBuf> = config.folders.iter().map(|f| f.path.clone()).collect();
    let (tx, mut rx) = mpsc::channel(64);
    let farm = Arc::clone(farm);
    let settle = config.farm.settle;
    let rescan = config.farm.rescan;
    tokio::spawn(async move {
        let watcher = tokio::spawn(hotfolder::watch(folders, settle, rescan, tx));
        while let Some((path, folder)) = rx.recv().await {
            if farm.stopping() {
                break;
            }
            let farm = Arc::clone(&farm);
            let _ = tokio::task::spawn_blocking(move || pick_up(&farm, &path, &folder)).await;
        }
        watcher.abort();
    })
}

/// Admits one complete file of a hot folder: a model becomes a job (with its sidecar if
/// that is there already); a sidecar whose model was picked up before it arrived joins its
/// job if the job has not started preparing, and is otherwise reported and kept aside.
fn pick_up(farm: &Farm, path: &std::path::Path, folder: &std::path::Path) {
    let name = path
        .file_name()
        .map(|n| n.to_string_lossy().into_owned())
        .unwrap_or_default();
    if !hotfolder::is_sidecar_name(&name) {
        match farm.store().admit(path, folder) {
            Ok(job) => {
                tracing::info!(job = %job.id, file = %path.display(), "picked up");
                farm.bump();
            }
            Err(e) => tracing::error!(file = %path.display(), error = %e, "cannot pick up"),
        }
        return;
    }
    let model = name.strip_suffix(".toml").unwrap_or(&name);
    if !path.exists() || folder.join(model).exists() {
        // Taken with its model already, or its model is still arriving.
        return;
    }
    let mut store = farm.store();
    let job = store
        .jobs()
        .filter(|j| j.folder == folder && j.file == model)
        .last()
        .map(|j| (j.id.clone(), j.state));
    let Some((id, state)) = job else {
        tracing::debug!(file = %path.display(), "a sidecar without its model yet");
        return;
    };
    match store.late_sidecar(&id, path, state == JobState::Queued) {
        Ok(true) => {
            tracing::info!(job = %id, file = %path.display(), "sidecar arrived after its model; it applies")
        }
        Ok(false) => tracing::warn!(
            job = %id,
            file = %path.display(),
            state = state.name(),
            "sidecar arrived after its model's job had started; NOT applied, kept in the job directory as {model}.toml.late (hint: put the sidecar in first, or `crispen cancel` and drop both again)"
        ),
        Err(e) => {
            tracing::error!(job = %id, file = %path.display(), error = %e, "cannot take the late sidecar")
        }
    }
}

/// Prepares queued jobs, oldest first, at most one per core at a time, each in its own
/// child process under a token of its own (a child of the shutdown token).
async fn prepare_loop(farm: Arc<Farm>, program: PathBuf) {
    let cores = std::thread::available_parallelism()
        .map(|n| n.get())
        .unwrap_or(1);
    let mut running = tokio::task::JoinSet::new();
    loop {
        let mut wake = farm.subscribe();
        if farm.stopping() {
            break;
        }
        // A job just picked up waits the settle time, so a sidecar that arrives shortly
        // after its model still applies.
        let settle = farm.config().farm.settle.as_secs_f64();
        let mut wait_s: Option<f64> = None;
        while running.len() < cores {
            let now = job::now_s();
            let next = farm
                .store()
                .jobs()
                .filter(|j| j.state == JobState::Queued)
                .find(|j| {
                    let fresh = j.history.len() == 1;
                    let left = j.history[0].1 + settle - now;
                    if fresh && left > 0.0 {
                        wait_s = Some(wait_s.map_or(left, |w| w.min(left)));
                        return false;
                    }
                    true
                })
                .map(|j| j.id.clone());
            let Some(id) = next else { break };
            if let Err(e) = farm.transition(&id, JobState::Preparing, None) {
                tracing::error!(job = %id, error = %e, "cannot start preparing");
                // A job that failed for it (its directory is gone) is passed over; one
                // still queued (the disk is full) waits for the next change.
                let still_queued = farm.store().get(&id).map(|j| j.state) == Some(JobState::Queued);
                if still_queued {
                    break;
                }
                continue;
            }
            let cancel = farm.shutdown.child_token();
            farm.preparing
                .lock()
                .unwrap_or_else(|e| e.into_inner())
                .insert(
                    id.clone(),
                    farm::Preparation {
                        step: "starting".into(),
                        cancel: cancel.clone(),
                    },
                );
            let span = tracing::info_span!("job", job = %id);
            running.spawn(
                prepare_one(Arc::clone(&farm), id, program.clone(), cancel).instrument(span),
            );
        }
        let grace = Duration::from_secs_f64(wait_s.unwrap_or(0.0).clamp(0.0, 3600.0));
        tokio::select! {
            _ = wake.changed() => {}
            Some(_) = running.join_next() => {}
            _ = farm.shutdown.cancelled() => {}
            _ = tokio::time::sleep(grace), if wait_s.is_some() => {}
        }
    }
    // The shutdown token has stopped every preparation's child; wait for their jobs to be
    // put back in the queue.
    while running.join_next().await.is_some() {}
}

/// Prepares one job and records the outcome.
async fn prepare_one(farm: Arc<Farm>, id: String, program: PathBuf, cancel: CancellationToken) {
    let resolved = {
        let (farm, id) = (Arc::clone(&farm), id.clone());
        tokio::task::spawn_blocking(move || resolve(&farm, &id))
            .await
            .unwrap_or_else(|e| Err(format!("preparation crashed: {e}")))
    };
    let result = match resolved {
        Err(reason) => Err(prepare::PrepareError::Failed(reason)),
        Ok((task, sidecar)) => {
            tracing::info!(
                model = %task.model.display(),
                height_mm = task.height_mm,
                strength = ?task.strength,
                "preparing"
            );
            let on_step = |step: String| {
                if let Some(p) = farm
                    .preparing
                    .lock()
                    .unwrap_or_else(|e| e.into_inner())
                    .get_mut(&id)
                {
                    p.step = step;
                }
            };
            prepare::run_child(&program, &task, &cancel, on_step)
                .await
                .map(|report| (report, sidecar))
        }
    };
    let farm2 = Arc::clone(&farm);
    let _ = tokio::task::spawn_blocking(move || finish_preparation(&farm2, &id, result)).await;
}

/// Reads the job's sidecar and works out its task.
fn resolve(farm: &Farm, id: &str) -> Result<(prepare::PrepareTask, Option<job::Sidecar>), String> {
    let (job, dir) = {
        let store = farm.store();
        let job = store.get(id).cloned().ok_or("job vanished")?;
        (job, store.job_dir(id))
    };
    let config = farm.config();
    let folder = config.folder(&job.folder).ok_or_else(|| {
        format!(
            "folder {} is no longer in the config (hint: add it back and `crispen retry` the job)",
            job.folder.display()
        )
    })?;
    let sidecar = prepare::read_sidecar(&dir.join(format!("{}.toml", job.file)))?;
    let task = prepare::resolve_task(id, &dir, &job.file, folder, sidecar.as_ref())?;
    Ok((task, sidecar))
}

fn finish_preparation(
    farm: &Farm,
    id: &str,
    result: Result<(crate::slice::SliceReport, Option<job::Sidecar>), prepare::PrepareError>,
) {
    farm.preparing
        .lock()
        .unwrap_or_else(|e| e.into_inner())
        .remove(id);
    // Cancelled (or otherwise moved on) while being prepared: the result is not wanted.
    // Checked and recorded under one hold of the lock, so a cancel cannot slip between.
    let mut store = farm.store();
    if store.get(id).map(|j| j.state) != Some(JobState::Preparing) {
        return;
    }
    let outcome = match result {
        Ok((report, sidecar)) => farm.transition_with(&mut store, id, JobState::Ready, None, |j| {
            j.slice_report = Some(report);
            j.sidecar = sidecar;
        }),
        // Still preparing, so not cancelled by the operator: the daemon is stopping, and
        // the job is prepared again at the next start.
        Err(prepare::PrepareError::Cancelled) => {
            farm.transition_in(&mut store, id, JobState::Queued, None)
        }
        Err(e) => farm.transition_in(&mut store, id, JobState::Failed, Some(e.to_string())),
    };
    drop(store);
    if let Err(e) = outcome {
        tracing::error!(job = id, error = %e, "cannot record the preparation's outcome");
    }
}
