//! The service behind `crispen run`: it opens the farm, wires hot-folder pick-up,
//! preparation, the printer fleet, the shared farm and the HTTP listeners (the control
//! socket and `[http]`), and supervises them. Every top-level task runs in one
//! [`Supervised`] set: one that ends or panics while the service runs stops the service
//! with [`ServiceError::TaskEnded`] (a non-zero exit, which systemd's
//! `Restart=on-failure` answers) rather than leave it half alive while the watchdog is fed.
//!
//! The dependencies go one way: the service knows `daemon` and `http`; `http` serves the
//! farm's handles and operations the service hands it; `daemon` knows neither.

use crate::daemon::config::{self, Config};
use crate::daemon::farm::{ConfigOwner, Farm, PrinterState, StopOwner};
use crate::daemon::fleet::{self, Fleet};
use crate::daemon::job::JobState;
use crate::daemon::{control, prepare, reload, shared, DaemonError};
use std::collections::HashMap;
use std::path::PathBuf;
use std::sync::Arc;
use std::time::Duration;
use tokio::task::{AbortHandle, Id, JoinError, JoinSet};
use tokio_util::sync::CancellationToken;

mod systemd;
use sd_notify::NotifyState;
use systemd::Systemd;

#[derive(Debug, thiserror::Error)]
pub enum ServiceError {
    #[error(transparent)]
    Daemon(#[from] DaemonError),
    #[error("cannot install signal handlers: {0}")]
    Signals(std::io::Error),
    #[error("cannot find this program to run preparations with: {0}")]
    PrepareProgram(std::io::Error),
    /// A top-level task ended or panicked while the service ran; it stops with this error.
    #[error("the daemon's {task} task {how}; the daemon stops (to be restarted)")]
    TaskEnded { task: String, how: String },
    #[error("notifications: cannot open the queues in the spool: {0}")]
    Notify(std::io::Error),
    #[error(transparent)]
    AppKeys(#[from] crate::http::appkeys::AppKeysError),
    #[error("[http] listen = \"{listen}\": cannot listen: {source} (hint: is another program on this port? Under systemd, install config/crispen-http.conf as a drop-in so the unit allows TCP)")]
    Http {
        listen: std::net::SocketAddr,
        #[source]
        source: std::io::Error,
    },
}

impl From<control::ControlError> for ServiceError {
    fn from(e: control::ControlError) -> ServiceError {
        ServiceError::Daemon(e.into())
    }
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

/// The top-level tasks, each with its name: one that ends while it should run is found
/// by [`Supervised::next_end`].
#[derive(Default)]
pub(crate) struct Supervised {
    tasks: JoinSet<()>,
    names: HashMap<Id, Task>,
}

struct Task {
    name: &'static str,
    /// It may end on its own; only a panic is a failure.
    may_end: bool,
    abort: AbortHandle,
}

impl Supervised {
    /// Starts a task that must run until the service stops it.
    pub(crate) fn spawn(
        &mut self,
        name: &'static str,
        task: impl std::future::Future<Output = ()> + Send + 'static,
    ) {
        self.spawn_as(name, false, task);
    }

    /// Starts a task that may end on its own (only a panic is a failure).
    pub(crate) fn spawn_may_end(
        &mut self,
        name: &'static str,
        task: impl std::future::Future<Output = ()> + Send + 'static,
    ) {
        self.spawn_as(name, true, task);
    }

    fn spawn_as(
        &mut self,
        name: &'static str,
        may_end: bool,
        task: impl std::future::Future<Output = ()> + Send + 'static,
    ) {
        let abort = self.tasks.spawn(task);
        self.names.insert(
            abort.id(),
            Task {
                name,
                may_end,
                abort,
            },
        );
    }

    /// Stops the task `name` (to start it anew, or at shutdown); its end is no failure.
    pub(crate) fn stop(&mut self, name: &str) {
        self.names.retain(|_, t| {
            let this = t.name == name;
            if this {
                t.abort.abort();
            }
            !this
        });
    }

    /// Whether the task `name` is running.
    pub(crate) fn has(&self, name: &str) -> bool {
        self.names.values().any(|t| t.name == name)
    }

    /// Waits for a task that ended when it should not have: why it stops the service.
    /// Pending while every task runs (or none is left).
    pub(crate) async fn next_end(&mut self) -> ServiceError {
        loop {
            let Some(ended) = self.tasks.join_next_with_id().await else {
                return std::future::pending().await;
            };
            let (id, how) = match ended {
                Ok((id, ())) => (id, Ok(())),
                Err(e) => (e.id(), Err(e)),
            };
            // A task stopped on purpose is no longer named.
            let Some(task) = self.names.remove(&id) else {
                continue;
            };
            if let Some(e) = failure(task.name, task.may_end, how) {
                return e;
            }
        }
    }

    /// Waits for the task `name` to end (after its stop token fired).
    pub(crate) async fn join(&mut self, name: &str) {
        while self.has(name) {
            let Some(ended) = self.tasks.join_next_with_id().await else {
                return;
            };
            let id = match &ended {
                Ok((id, ())) => *id,
                Err(e) => e.id(),
            };
            if let Some(task) = self.names.remove(&id) {
                if let Some(e) = failure(task.name, true, ended.map(|_| ())) {
                    tracing::error!("at shutdown: {e}");
                }
            }
        }
    }
}

/// Whether a task's end stops the service, and why.
fn failure(name: &str, may_end: bool, ended: Result<(), JoinError>) -> Option<ServiceError> {
    let how = match ended {
        Ok(()) if may_end => return None,
        Ok(()) => "ended unexpectedly".to_string(),
        Err(e) if e.is_panic() => format!("panicked: {}", panic_message(e)),
        Err(_) => "was cancelled".to_string(),
    };
    Some(ServiceError::TaskEnded {
        task: name.to_string(),
        how,
    })
}

fn panic_message(e: JoinError) -> String {
    let payload = e.into_panic();
    payload
        .downcast_ref::<&str>()
        .map(|s| s.to_string())
        .or_else(|| payload.downcast_ref::<String>().cloned())
        .unwrap_or_else(|| "(no message)".into())
}

const PICKUP: &str = "hot-folder pick-up";
const PREPARATION: &str = "preparation";
const SHARED: &str = "shared farm";
const CONTROL: &str = "control socket";
const HTTP: &str = "http listener";
const NOTIFY: &str = "notifications";
const CAMERAS: &str = "cameras";
const STORE: &str = "job store";
const SPOOLMAN: &str = "Spoolman link";
const UPLOADS: &str = "OctoPrint's held uploads";

/// Runs the daemon until SIGTERM/SIGINT (or until idle with `exit_when_idle`). The
/// shutdown token made here is handed down to every task; each races it at its waits.
pub async fn run(config: Config, options: RunOptions) -> Result<(), ServiceError> {
    let mut signals = Signals::new()?;
    let mut running = Running::start(config, options).await?;
    let failure = running.serve(&mut signals).await;
    running.shut_down(&mut signals).await;
    match failure {
        Some(e) => Err(e),
        None => {
            tracing::info!("crispen daemon stopped");
            Ok(())
        }
    }
}

/// The signals the daemon answers, set up before anything starts so none is missed.
struct Signals {
    term: tokio::signal::unix::Signal,
    int: tokio::signal::unix::Signal,
    hup: tokio::signal::unix::Signal,
}

impl Signals {
    fn new() -> Result<Signals, ServiceError> {
        use tokio::signal::unix::{signal, SignalKind};
        let listen = |kind| signal(kind).map_err(ServiceError::Signals);
        Ok(Signals {
            term: listen(SignalKind::terminate())?,
            int: listen(SignalKind::interrupt())?,
            hup: listen(SignalKind::hangup())?,
        })
    }
}

/// A started daemon: its farm, its tasks and printers, and the tokens that stop each group
/// of tasks in the order a shutdown needs.
struct Running {
    farm: Arc<Farm>,
    /// A reload puts its config in force.
    config_owner: ConfigOwner,
    /// A signal stops the farm.
    stop: StopOwner,
    options: RunOptions,
    tasks: Supervised,
    fleet: Fleet,
    /// The lease is renewed until the last print has ended, after the shutdown token.
    stop_shared: CancellationToken,
    /// Notifications outlive the prints: what a stop does to them is told too.
    stop_notify: CancellationToken,
    stop_cameras: CancellationToken,
    /// The listeners outlive the shutdown token: while prints finish at a stop, the
    /// operator can still watch them and cancel one.
    stop_listeners: CancellationToken,
    /// Withdrawn when the daemon stops (dropped).
    _announced: Option<crate::http::zeroconf::Announcer>,
    systemd: Systemd,
}

impl Running {
    /// Opens the store, binds the listeners and starts every task and printer.
    async fn start(config: Config, options: RunOptions) -> Result<Running, ServiceError> {
        let prepare_program = match &options.prepare_program {
            Some(p) => p.clone(),
            None => std::env::current_exe().map_err(ServiceError::PrepareProgram)?,
        };
        let crate::daemon::Opened {
            farm,
            owners,
            store,
            shared: shared_db,
        } = crate::daemon::open_store(&config).await?;
        // Each piece of the farm's state to its one owner (the config's stays here: the
        // reload is the service's).
        let crate::daemon::farm::Owners {
            config: config_owner,
            printers: printers_owner,
            preparing: preparing_owner,
            shared: shared_owner,
            stop,
        } = owners;
        let listener = control::bind(&config.socket)?;
        let http_listener = match &config.http {
            None => None,
            Some(http) => {
                let bound = bind_http(http).await?;
                let address = bound
                    .local_addr()
                    .map_or_else(|_| http.listen.to_string(), |a| a.to_string());
                tracing::info!(address = %address, "http: listening");
                tracing::info!("dashboard: http://{address}/");
                Some((bound, http.clone()))
            }
        };
        let appkeys = Arc::new(crate::http::AppKeys::open(&config.spool_dir)?);
        // Not announcing is no reason to stop printing: the failure is logged as an error
        // and the farm runs on.
        let announced = match &http_listener {
            Some((bound, _)) => match bound.local_addr() {
                Ok(address) => crate::http::zeroconf::announce(&config, address)
                    .inspect_err(|e| tracing::error!(error = %e, "the hot folders are not announced on the network"))
                    .ok()
                    .flatten(),
                Err(_) => None,
            },
            None => None,
        };
        tracing::info!(
            config = %config.source.display(),
            spool = %config.spool_dir.display(),
            socket = %config.socket.display(),
            printers = config.printers.len(),
            folders = config.folders.len(),
            "crispen daemon starting"
        );
        let mut tasks = Supervised::default();
        // The only owner of the jobs: a panic in it stops the daemon (see `store::start`).
        tasks.spawn(STORE, store);
        let stop_shared = CancellationToken::new();
        if let Some((db, lease)) = shared_db {
            tracing::info!(host = %db.host(), "sharing the farm's queue through its database");
            // It ends on its own, for good, when another run took this host's name (its
            // log and the status say so); only a panic is a failure.
            tasks.spawn_may_end(
                SHARED,
                shared::run(
                    Arc::clone(&farm),
                    shared_owner,
                    db,
                    lease,
                    stop_shared.clone(),
                ),
            );
        }
        let stop_notify = CancellationToken::new();
        let (notifications, notify) = crate::notify::run(Arc::clone(&farm), stop_notify.clone())
            .map_err(ServiceError::Notify)?;
        let counters = Arc::new(crate::http::Counters::new(notifications));
        tasks.spawn(NOTIFY, notify);
        // Like the notifications, it outlives the prints: their last uses are told.
        tasks.spawn(
            SPOOLMAN,
            crate::spoolman::link::run(Arc::clone(&farm), stop_notify.clone()),
        );
        let (cameras, camera_sources) = crate::camera::Cameras::new(&config);
        let cameras = Arc::new(cameras);
        let stop_cameras = CancellationToken::new();
        tasks.spawn(
            CAMERAS,
            crate::camera::run(
                Arc::clone(&farm),
                Arc::clone(&cameras),
                camera_sources,
                stop_cameras.clone(),
            ),
        );
        let fleet = Fleet::start_all(
            &farm,
            printers_owner,
            &config.printers,
            fleet::marlin_ports(),
        )?;
        let stop_listeners = CancellationToken::new();
        let shared = crate::http::Shared {
            appkeys: Arc::clone(&appkeys),
            cameras: Arc::clone(&cameras),
            counters,
            pending: Arc::default(),
        };
        tasks.spawn(
            UPLOADS,
            crate::http::pending::sweep(
                Arc::clone(&farm),
                Arc::clone(&shared.pending),
                stop_listeners.clone(),
            ),
        );
        tasks.spawn(
            CONTROL,
            crate::http::serve_socket(
                Arc::clone(&farm),
                shared.clone(),
                config.http.clone(),
                listener,
                stop_listeners.clone(),
            ),
        );
        if let Some((bound, http)) = http_listener {
            tasks.spawn(
                HTTP,
                crate::http::serve_tcp(
                    Arc::clone(&farm),
                    shared,
                    http,
                    bound,
                    stop_listeners.clone(),
                ),
            );
        }
        tasks.spawn(PICKUP, crate::daemon::pickup(&farm, &config));
        tasks.spawn(
            PREPARATION,
            prepare::queue::prepare_loop(Arc::clone(&farm), preparing_owner, prepare_program),
        );
        Ok(Running {
            farm,
            config_owner,
            stop,
            options,
            tasks,
            fleet,
            stop_shared,
            stop_notify,
            stop_cameras,
            stop_listeners,
            _announced: announced,
            systemd: Systemd::from_env(),
        })
    }

    /// Tells systemd the daemon is ready and serves until a signal, an idle farm with
    /// `exit_when_idle`, or a task's end; returns the failure when it was one.
    async fn serve(&mut self, signals: &mut Signals) -> Option<ServiceError> {
        let farm = Arc::clone(&self.farm);
        self.systemd.notify(&[NotifyState::Ready]);
        let mut watchdog_usec = 0u64;
        let watchdog = sd_notify::watchdog_enabled(false, &mut watchdog_usec);
        let tick = if watchdog {
            Duration::from_micros(watchdog_usec / 2).max(Duration::from_millis(100))
        } else {
            Duration::from_secs(5)
        };
        let mut ticker = tokio::time::interval(tick);
        let mut jobs = farm.watch_jobs();
        loop {
            tokio::select! {
                _ = signals.term.recv() => { tracing::info!("SIGTERM: stopping"); return None; }
                _ = signals.int.recv() => { tracing::info!("SIGINT: stopping"); return None; }
                _ = signals.hup.recv() => on_sighup(&farm, &self.config_owner, &self.options, &mut self.tasks, &mut self.fleet),
                // A top-level task that ended or panicked stops the daemon.
                e = self.tasks.next_end() => {
                    tracing::error!("{e}");
                    return Some(e);
                }
                (printer, how) = self.fleet.next_end() => {
                    let e = failure_of_printer(&printer, how);
                    tracing::error!(printer = %printer, "{e}");
                    return Some(e);
                }
                _ = ticker.tick() => {
                    if watchdog {
                        self.systemd.notify(&[NotifyState::Watchdog]);
                    }
                    let summary = summary(&farm);
                    self.systemd.notify(&[NotifyState::Status(&summary)]);
                }
                // A change is counted in the snapshot that publishes it: one look sees both.
                Ok(()) = jobs.changed() => {
                    let store = farm.store();
                    if self.options.exit_when_idle && store.counts().finished() > 0 && store.idle() {
                        tracing::info!("no work left: exiting (--exit-when-idle)");
                        return None;
                    }
                }
            }
        }
    }

    /// Shutdown: take no new work; preparation in progress is stopped (its job goes back
    /// to the queue); prints finish or stop per config; then the shared farm's lease, the
    /// notifications and the listeners, in that order.
    async fn shut_down(self, signals: &mut Signals) {
        let Running {
            farm,
            mut tasks,
            fleet,
            stop_shared,
            stop_notify,
            stop_cameras,
            stop_listeners,
            systemd,
            stop,
            ..
        } = self;
        systemd.notify(&[NotifyState::Stopping]);
        stop.begin();
        tasks.stop(PICKUP);
        tasks.join(PREPARATION).await;
        finish_prints(
            &farm,
            &stop,
            &systemd,
            fleet,
            &mut signals.term,
            &mut signals.int,
        )
        .await;
        if tasks.has(SHARED) {
            // Prints have ended: their outcomes are in the store.
            stop_shared.cancel();
            tasks.join(SHARED).await;
            let left = farm.jobs().write_pending().await.unwrap_or(0);
            if left > 0 {
                tracing::error!(outcomes = left, "the farm database is unreachable: outcomes not written (the jobs show as interrupted once this host's lease runs out)");
            } else if let Some(db) = farm.db.get() {
                // Nothing of this run is left to record: the next run under this name may
                // start at once instead of waiting out the lease.
                if let Err(e) = db.release_host().await {
                    tracing::warn!(error = %e, "cannot give up this host's lease; the next start under this name waits for it to run out");
                }
            }
        }
        // The prints have ended: their last pictures are taken as the recorders stop.
        stop_cameras.cancel();
        tasks.join(CAMERAS).await;
        stop_notify.cancel();
        tasks.join(SPOOLMAN).await;
        tasks.join(NOTIFY).await;
        stop_listeners.cancel();
        tasks.join(CONTROL).await;
        tasks.join(HTTP).await;
        tasks.join(UPLOADS).await;
        let _ = std::fs::remove_file(&farm.config().socket);
    }
}

/// How often systemd is asked for more time while prints finish at a stop, and how much
/// each time: several renewals may be late before the time runs out.
const EXTEND_EVERY: Duration = Duration::from_secs(2);
const EXTEND_BY: Duration = Duration::from_secs(20);
/// After the prints were told to stop, the time asked for their safe stop (the stop's
/// lines and the printers' answers) before systemd may kill the daemon.
const STOP_GRACE: Duration = Duration::from_secs(60);

/// Waits for the printers' supervisors to end after [`StopOwner::begin`]. While prints
/// finish, systemd is asked for more time (`EXTEND_TIMEOUT_USEC`, renewed before it runs
/// out), so the unit's short `TimeoutStopSec` does not kill a daemon whose printers are
/// hot; but only up to `[farm] finish_timeout_s` (and the grace of the safe stop after
/// it): then the prints are stopped safely, heaters off, as a second SIGTERM or SIGINT
/// stops them at once. A daemon killed by systemd would leave the heaters on.
async fn finish_prints(
    farm: &Farm,
    stop: &StopOwner,
    systemd: &Systemd,
    fleet: Fleet,
    sigterm: &mut tokio::signal::unix::Signal,
    sigint: &mut tokio::signal::unix::Signal,
) {
    use tokio::time::Instant;
    let bound = Instant::now() + farm.config().farm.finish_timeout;
    let mut stopping = farm.stop_prints.is_cancelled();
    // Past this, no more time is asked for.
    let mut last = if stopping { Instant::now() } else { bound } + STOP_GRACE;
    let printing = farm
        .local_printers()
        .iter()
        .filter(|p| p.job.is_some())
        .count();
    if printing > 0 && !stopping {
        tracing::info!(
            prints = printing,
            "waiting for the prints to finish (at most [farm] finish_timeout_s = {} s; a second SIGTERM stops them safely)",
            farm.config().farm.finish_timeout.as_secs_f64()
        );
    }
    let mut extend = tokio::time::interval(EXTEND_EVERY);
    let ended = fleet.join();
    tokio::pin!(ended);
    loop {
        let why = tokio::select! {
            () = &mut ended => return,
            _ = sigterm.recv(), if !stopping => "second SIGTERM",
            _ = sigint.recv(), if !stopping => "SIGINT while the prints finish",
            () = tokio::time::sleep_until(bound), if !stopping => "[farm] finish_timeout_s ran out",
            _ = extend.tick() => {
                let left = last.saturating_duration_since(Instant::now()).min(EXTEND_BY);
                if !left.is_zero() {
                    let usec = u32::try_from(left.as_micros()).unwrap_or(u32::MAX);
                    systemd.notify(&[NotifyState::ExtendTimeoutUsec(usec)]);
                }
                continue;
            }
        };
        tracing::warn!("{why}: stopping the prints safely (heaters off)");
        stop.stop_prints();
        stopping = true;
        last = last.min(Instant::now() + STOP_GRACE);
    }
}

/// A printer's supervisor ended while the service ran (it panicked: it ends only once
/// retired, or at shutdown).
fn failure_of_printer(printer: &str, how: Result<(), JoinError>) -> ServiceError {
    let how = match how {
        Err(e) if e.is_panic() => format!("panicked: {}", panic_message(e)),
        _ => "ended unexpectedly".into(),
    };
    ServiceError::TaskEnded {
        task: format!("printer {printer}'s supervisor"),
        how,
    }
}

/// Binds `[http] listen`. The built-in default's port, when taken, gives way to one the
/// system picks (the address is logged); a configured port never does.
async fn bind_http(http: &config::HttpConfig) -> Result<tokio::net::TcpListener, ServiceError> {
    let failed = |source| ServiceError::Http {
        listen: http.listen,
        source,
    };
    match crate::http::bind(http).await {
        Err(e) if http.any_port_if_taken && e.kind() == std::io::ErrorKind::AddrInUse => {
            tracing::warn!(listen = %http.listen, "http: the port is taken; listening on a port the system picks");
            let any = std::net::SocketAddr::new(http.listen.ip(), 0);
            tokio::net::TcpListener::bind(any).await.map_err(failed)
        }
        bound => bound.map_err(failed),
    }
}

fn summary(farm: &Farm) -> String {
    let printers = farm.local_printers();
    let printing = printers
        .iter()
        .filter(|p| p.state == PrinterState::Printing)
        .count();
    let total = printers.len();
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

/// SIGHUP: re-read the config file and apply it as [`reload::POLICY`] declares; a bad
/// file is refused and the old config kept. Pick-up restarts with the new folders, and
/// the printers change as [`Fleet::apply`] says.
fn on_sighup(
    farm: &Arc<Farm>,
    owner: &ConfigOwner,
    options: &RunOptions,
    tasks: &mut Supervised,
    fleet: &mut Fleet,
) {
    let Some(path) = &options.config_path else {
        tracing::warn!("SIGHUP: running on the built-in default config; nothing to reload");
        return;
    };
    if let Some(config) = reload::reload(farm, owner, path) {
        tasks.stop(PICKUP);
        fleet.apply(&config.printers);
        tasks.spawn(PICKUP, crate::daemon::pickup(farm, &config));
        tracing::info!("SIGHUP: config reloaded");
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A printer's supervisor that panicked is named with the panic's message.
    #[tokio::test(start_paused = true)]
    async fn a_panicking_supervisor_is_named() {
        let panicked = tokio::spawn(async { panic!("the link broke its promise") })
            .await
            .unwrap_err();
        assert_eq!(
            failure_of_printer("bad", Err(panicked)).to_string(),
            "the daemon's printer bad's supervisor task panicked: the link broke its promise; \
             the daemon stops (to be restarted)"
        );
    }

    /// A top-level task that panics is found, named, and stops the daemon with an error
    /// (before, nothing watched them: a panicked preparation left a daemon that prepared
    /// nothing while it fed the systemd watchdog). One stopped on purpose is no failure.
    #[tokio::test(start_paused = true)]
    async fn a_panicking_task_stops_the_daemon_with_its_name() {
        let mut tasks = Supervised::default();
        tasks.spawn("quiet", std::future::pending());
        tasks.spawn("restarted", std::future::pending());
        tasks.spawn(PREPARATION, async {
            tokio::time::sleep(Duration::from_secs(3)).await;
            let history: Vec<u8> = Vec::new();
            let _ = history[0];
        });
        tasks.stop("restarted");
        let e = tasks.next_end().await;
        let shown = e.to_string();
        assert!(
            shown.contains("preparation task panicked: index out of bounds"),
            "{shown}"
        );
        assert!(tasks.has("quiet") && !tasks.has(PREPARATION) && !tasks.has("restarted"));
    }

    /// A request that panics in the job store's task (here an edit; a store's own bug
    /// alike) stops the daemon: the supervised set names the store's task with the panic,
    /// and the request's caller and every later one get `Stopped`. The task once caught
    /// the panic and served on after a change done halfway; a panic while retiring ended
    /// it unsupervised, while the watchdog was still fed.
    #[tokio::test]
    async fn a_panicking_store_request_stops_the_daemon() {
        use crate::daemon::doubles::{farm_config, ready_job};
        use crate::daemon::job::StoreError;
        let tmp = tempfile::tempdir().unwrap();
        let config = farm_config(tmp.path(), &["p1"], "");
        let store = crate::daemon::store::spool::SpoolStore::open(&config.spool_dir).unwrap();
        let (farm, _owners, task) = Farm::new(config, store);
        let mut tasks = Supervised::default();
        tasks.spawn(STORE, task);
        let job = ready_job(&farm, "a.stl", "G28\n").await;
        let asked = farm
            .jobs()
            .update(
                &job,
                crate::daemon::store::JobChange::Edit(Box::new(|_| {
                    panic!("an edit broke its promise")
                })),
            )
            .await;
        assert!(matches!(asked, Err(StoreError::Stopped)), "{asked:?}");
        let e = tokio::time::timeout(Duration::from_secs(30), tasks.next_end())
            .await
            .expect("the store's end is seen");
        assert_eq!(
            e.to_string(),
            "the daemon's job store task panicked: an edit broke its promise; \
             the daemon stops (to be restarted)"
        );
        assert!(!tasks.has(STORE));
        let after = farm
            .jobs()
            .transition(&job, JobState::Cancelled, None)
            .await;
        assert!(matches!(after, Err(StoreError::Stopped)), "{after:?}");
    }

    /// A task that returns is a failure too, except one that may end on its own (the
    /// shared farm's, when another run took this host's name).
    #[tokio::test(start_paused = true)]
    async fn a_task_that_returns_stops_the_daemon_unless_it_may() {
        let mut tasks = Supervised::default();
        tasks.spawn_may_end(SHARED, async {});
        tasks.spawn(CONTROL, async {
            tokio::time::sleep(Duration::from_secs(1)).await;
        });
        let e = tasks.next_end().await;
        assert!(
            e.to_string()
                .contains("control socket task ended unexpectedly"),
            "{e}"
        );
    }
}
