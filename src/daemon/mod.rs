//! The print-farm daemon behind `crispen run`: hot folders feed a job spool, jobs are
//! prepared (enhanced and sliced) off the async runtime, and each printer's supervisor
//! prints ready jobs one at a time, waiting for its bed to be cleared in between.
//!
//! - [`config`]: the TOML configuration, checked in two stages.
//! - [`job`]: a job, its states and the one table of legal changes.
//! - [`store`]: the task that owns the jobs (the embedded spool by default), its handle
//!   and the snapshot readers glance at.
//! - [`hotfolder`]: deciding when a dropped file is complete.
//! - [`prepare`]: a job's preparation (sidecars, machines, the steps) and its queue.
//! - [`printer`]: printer supervisors and staggered heat-ups.
//! - [`control`]: the operator's commands and the control socket, which serves the HTTP
//!   API (`crate::http`) like the TCP listener.
//! - [`reload`]: SIGHUP, and when each config key's change takes effect.
//! - [`farm`]: the state all of these share.
//!
//! [`run`] wires them together; I/O endpoints (printer ports, the preparer) are resolved
//! here, at startup and on a reload, so no other part knows whether a printer is simulated.

pub mod config;
pub mod control;
pub mod farm;
pub mod hotfolder;
pub mod job;
pub mod prepare;
pub mod printer;
pub mod reload;
pub mod shared;
pub mod store;

mod fleet;

use config::Config;
use farm::{Farm, PrinterState};
use fleet::Fleet;
use job::JobState;
use std::collections::HashMap;
use std::path::PathBuf;
use std::sync::Arc;
use std::time::Duration;
use tokio::sync::mpsc;
use tokio_util::sync::CancellationToken;

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
    #[error("[store] postgres: {0}")]
    Database(#[from] store::postgres::PgError),
    /// Another run holds this host's name in the farm ([`store::postgres::PgError::HostInUse`]).
    #[error("{0}")]
    HostInUse(store::postgres::PgError),
    #[error("cannot install signal handlers: {0}")]
    Signals(std::io::Error),
    #[error("cannot find this program to run preparations with: {0}")]
    PrepareProgram(std::io::Error),
    /// A top-level task ended or panicked while the daemon ran; the daemon stops with
    /// this error (a non-zero exit, which systemd's `Restart=on-failure` answers).
    #[error("the daemon's {task} task {how}; the daemon stops (to be restarted)")]
    TaskEnded { task: String, how: String },
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

    let shutdown = CancellationToken::new();
    let (farm, shared) = open_store(&config, &shutdown).await?;
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
    tracing::info!(
        config = %config.source.display(),
        spool = %config.spool_dir.display(),
        socket = %config.socket.display(),
        printers = config.printers.len(),
        folders = config.folders.len(),
        "crispen daemon starting"
    );
    // The lease is renewed until the last print has ended, after the shutdown token.
    let stop_shared = CancellationToken::new();
    // It ends on its own, for good, when another run took this host's name (its log and
    // the status say so); only a panic is a failure.
    let mut shared_task = Watched::new("shared farm", None).may_end();
    if let Some((db, lease)) = shared {
        tracing::info!(host = %db.host(), "sharing the farm's queue through its database");
        shared_task.handle = Some(tokio::spawn(shared::run(
            Arc::clone(&farm),
            db,
            lease,
            stop_shared.clone(),
        )));
    }
    let mut fleet = Fleet::start_all(&farm, &config.printers)?;
    // The listeners outlive the shutdown token: while prints finish at a stop, the
    // operator can still watch them and cancel one.
    let stop_listeners = CancellationToken::new();
    let mut control_task = Watched::new(
        "control socket",
        Some(tokio::spawn(crate::http::serve_socket(
            Arc::clone(&farm),
            config.http.clone(),
            listener,
            stop_listeners.clone(),
        ))),
    );
    let mut http_task = Watched::new(
        "http listener",
        http_listener.map(|(bound, http)| {
            tokio::spawn(crate::http::serve_tcp(
                Arc::clone(&farm),
                http,
                bound,
                stop_listeners.clone(),
            ))
        }),
    );
    let mut pickup = Watched::new("hot-folder pick-up", Some(spawn_pickup(&farm, &config)));
    let mut prepare_task = Watched::new(
        "preparation",
        Some(tokio::spawn(prepare::queue::prepare_loop(
            Arc::clone(&farm),
            prepare_program,
        ))),
    );

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
    // Why the daemon stops on its own: a top-level task that ended or panicked.
    let mut failure: Option<DaemonError> = None;
    loop {
        let mut reload = false;
        let mut watched = [
            &mut shared_task,
            &mut control_task,
            &mut http_task,
            &mut pickup,
            &mut prepare_task,
        ];
        tokio::select! {
            _ = sigterm.recv() => { tracing::info!("SIGTERM: stopping"); break; }
            _ = sigint.recv() => { tracing::info!("SIGINT: stopping"); break; }
            _ = sighup.recv() => reload = true,
            (task, ended) = first_end(&mut watched) => {
                if let Some(e) = task_failure(&task, ended) {
                    tracing::error!("{e}");
                    failure = Some(e);
                    break;
                }
            }
            _ = ticker.tick() => {
                if let Some(printer) = fleet.ended() {
                    let e = DaemonError::TaskEnded {
                        task: format!("printer {printer}'s supervisor"),
                        how: "ended unexpectedly".into(),
                    };
                    tracing::error!(printer = %printer, "{e}");
                    failure = Some(e);
                    break;
                }
                fleet.settle(&farm);
                if farm.store().unwritten() > 0 {
                    let jobs = farm.jobs.clone();
                    tokio::spawn(async move { jobs.write_pending().await });
                }
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
        if reload {
            on_sighup(&farm, &options, &mut pickup, &mut fleet);
        }
    }

    // Shutdown: take no new work; preparation in progress is stopped (its job goes back to
    // the queue); prints finish or stop per config.
    let _ = sd_notify::notify(false, &[sd_notify::NotifyState::Stopping]);
    farm.begin_stop();
    if let Some(task) = pickup.handle.take() {
        task.abort();
    }
    if let Some(task) = prepare_task.handle.take() {
        let _ = task.await;
    }
    fleet.join().await;
    if let Some(task) = shared_task.handle.take() {
        // Prints have ended: their outcomes are in the store.
        stop_shared.cancel();
        let _ = task.await;
        let left = farm.jobs.write_pending().await.unwrap_or(0);
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
    stop_listeners.cancel();
    for task in [control_task.handle.take(), http_task.handle.take()]
        .into_iter()
        .flatten()
    {
        let _ = task.await;
    }
    let _ = std::fs::remove_file(&farm.config().socket);
    match failure {
        Some(e) => Err(e),
        None => {
            tracing::info!("crispen daemon stopped");
            Ok(())
        }
    }
}

/// A top-level task of the daemon, watched by [`run`]'s loop: one that ends or panics
/// while the daemon runs stops the daemon ([`DaemonError::TaskEnded`]), rather than leave
/// it half alive while the systemd watchdog keeps being fed.
struct Watched {
    name: &'static str,
    /// None: not started (no such listener in the config), or already joined.
    handle: Option<tokio::task::JoinHandle<()>>,
    /// It may end on its own; only a panic is a failure.
    may_end: bool,
}

impl Watched {
    fn new(name: &'static str, handle: Option<tokio::task::JoinHandle<()>>) -> Watched {
        Watched {
            name,
            handle,
            may_end: false,
        }
    }

    fn may_end(self) -> Watched {
        Watched {
            may_end: true,
            ..self
        }
    }
}

/// Waits for the first of `tasks` to end and takes its handle out (so it is never awaited
/// again); pending for ever while none is running.
async fn first_end(tasks: &mut [&mut Watched]) -> (Watched, Result<(), tokio::task::JoinError>) {
    use std::future::Future;
    std::future::poll_fn(|cx| {
        for task in tasks.iter_mut() {
            let Some(handle) = task.handle.as_mut() else {
                continue;
            };
            if let std::task::Poll::Ready(ended) = std::pin::Pin::new(handle).poll(cx) {
                task.handle = None;
                let which = Watched {
                    name: task.name,
                    handle: None,
                    may_end: task.may_end,
                };
                return std::task::Poll::Ready((which, ended));
            }
        }
        std::task::Poll::Pending
    })
    .await
}

/// Whether a watched task's end stops the daemon, and why.
fn task_failure(task: &Watched, ended: Result<(), tokio::task::JoinError>) -> Option<DaemonError> {
    let how = match ended {
        Ok(()) if task.may_end => return None,
        Ok(()) => "ended unexpectedly".to_string(),
        Err(e) if e.is_panic() => {
            let payload = e.into_panic();
            let message = payload
                .downcast_ref::<&str>()
                .map(|s| s.to_string())
                .or_else(|| payload.downcast_ref::<String>().cloned())
                .unwrap_or_else(|| "(no message)".into());
            format!("panicked: {message}")
        }
        Err(_) => "was cancelled".to_string(),
    };
    Some(DaemonError::TaskEnded {
        task: task.name.to_string(),
        how,
    })
}

/// Opens the job store the config names, applies the restart rules to what this host left
/// mid-flight, and builds the farm around it. A shared farm also returns its database and
/// lease, for [`shared::run`].
async fn open_store(
    config: &Config,
    shutdown: &CancellationToken,
) -> Result<(Arc<Farm>, Option<(store::postgres::PgStore, Duration)>), DaemonError> {
    let mid_flight = |id: &str, state: JobState| {
        tracing::warn!(job = %id, state = state.name(), "job found mid-flight after a restart");
    };
    let Some(shared) = &config.store else {
        let mut store = store::spool::Spool::open(&config.spool_dir)?;
        for id in store.recover()? {
            mid_flight(&id, store.get(&id).expect("recovered job exists").state);
        }
        return Ok((Farm::new(config.clone(), store, shutdown.clone()), None));
    };
    let db = store::postgres::PgStore::connect(&shared.postgres, &config.farm.host, shared.lease)
        .await
        .map_err(|e| match e {
            store::postgres::PgError::HostInUse { .. } => DaemonError::HostInUse(e),
            e => DaemonError::Database(e),
        })?;
    let recovered = db.recover_own().await?;
    let store = store::postgres::store::PgJobStore::open(db.clone(), &config.spool_dir).await?;
    let farm = Farm::new(config.clone(), store, shutdown.clone());
    for id in recovered {
        if let Some(job) = farm.store().get(&id) {
            mid_flight(&id, job.state);
        }
    }
    let _ = farm.db.set(db.clone());
    Ok((farm, Some((db, shared.lease))))
}

/// Binds `[http] listen`. The built-in default's port, when taken, gives way to one the
/// system picks (the address is logged); a configured port never does.
async fn bind_http(http: &config::HttpConfig) -> Result<tokio::net::TcpListener, DaemonError> {
    let failed = |source| DaemonError::Http {
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

/// SIGHUP: re-read the config file and apply it as [`reload::POLICY`] declares; a bad
/// file is refused and the old config kept. Pick-up restarts with the new folders, and
/// the printers change as [`Fleet::apply`] says.
fn on_sighup(farm: &Arc<Farm>, options: &RunOptions, pickup: &mut Watched, fleet: &mut Fleet) {
    let Some(path) = &options.config_path else {
        tracing::warn!("SIGHUP: running on the built-in default config; nothing to reload");
        return;
    };
    if let reload::Reloaded::Applied { config, .. } = reload::reload(farm, path) {
        if let Some(old) = pickup.handle.take() {
            old.abort();
        }
        fleet.apply(farm, &config.printers);
        pickup.handle = Some(spawn_pickup(farm, &config));
        farm.bump();
        tracing::info!("SIGHUP: config reloaded");
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
        let mut lone_sidecars = HashMap::new();
        let orphan_after = settle * hotfolder::ORPHAN_SIDECAR_SETTLES;
        while let Some((path, folder)) = rx.recv().await {
            if farm.stopping() {
                break;
            }
            pick_up(&farm, &path, &folder, &mut lone_sidecars, orphan_after).await;
        }
        watcher.abort();
    })
}

/// Admits one complete file of a hot folder: a model becomes a job (with its sidecar if
/// that is there already); a sidecar whose model was picked up before it arrived joins its
/// job if the job has not started preparing, and is otherwise reported and kept aside.
/// A file whose name has control or bidi characters, and a sidecar whose model has not
/// come within `orphan_after` (it is looked at again on each rescan), are set aside
/// ([`hotfolder::set_aside`]) with a log line naming them. `lone_sidecars` holds when each
/// sidecar without a model was first seen.
async fn pick_up(
    farm: &Farm,
    path: &std::path::Path,
    folder: &std::path::Path,
    lone_sidecars: &mut HashMap<PathBuf, std::time::Instant>,
    orphan_after: Duration,
) {
    let raw_name = path.file_name().unwrap_or_default();
    let name = raw_name.to_string_lossy().into_owned();
    let problem = match raw_name.to_str() {
        None => Some("is not valid UTF-8"),
        Some(name) => hotfolder::name_problem(name),
    };
    if let Some(problem) = problem {
        set_aside(path, folder, &format!("its name {problem}"));
        return;
    }
    if !hotfolder::is_sidecar_name(&name) {
        let printers = farm
            .config()
            .folder(folder)
            .map(|f| f.printers.clone())
            .unwrap_or_default();
        match farm.jobs.admit(path, folder, &printers).await {
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
        lone_sidecars.remove(path);
        return;
    }
    match farm.jobs.late_sidecar(folder, model, path).await {
        Ok(None) => {
            let since = *lone_sidecars
                .entry(path.to_path_buf())
                .or_insert_with(std::time::Instant::now);
            if since.elapsed() >= orphan_after {
                lone_sidecars.remove(path);
                set_aside(
                    path,
                    folder,
                    &format!(
                        "a sidecar whose model {} did not arrive within {} s",
                        hotfolder::printable(model),
                        orphan_after.as_secs()
                    ),
                );
            } else {
                tracing::debug!(file = %hotfolder::printable(&name), "a sidecar without its model yet");
            }
        }
        Ok(Some(late)) if late.applies => {
            tracing::info!(job = %late.job, file = %path.display(), "sidecar arrived after its model; it applies")
        }
        Ok(Some(late)) => tracing::warn!(
            job = %late.job,
            file = %path.display(),
            state = late.state.name(),
            "sidecar arrived after its model's job had started; NOT applied, kept in the job directory as {model}.toml.late (hint: put the sidecar in first, or `crispen cancel` and drop both again)"
        ),
        Err(e) => {
            tracing::error!(file = %path.display(), error = %e, "cannot take the late sidecar")
        }
    }
}

/// Moves a file the pick-up refuses out of the way, into the hot folder's
/// [`hotfolder::SET_ASIDE_DIR`], and says so; it is kept, never deleted.
fn set_aside(path: &std::path::Path, folder: &std::path::Path, why: &str) {
    let name = path
        .file_name()
        .map(|n| n.to_string_lossy().into_owned())
        .unwrap_or_default();
    match hotfolder::set_aside(path, folder) {
        Ok(to) => tracing::warn!(
            file = %hotfolder::printable(&name),
            folder = %folder.display(),
            set_aside_as = %hotfolder::printable(&to.file_name().unwrap_or_default().to_string_lossy()),
            "not picked up: {why}; set aside in the folder's {}/ (rename it and put it back to print it)",
            hotfolder::SET_ASIDE_DIR
        ),
        Err(e) => tracing::error!(
            file = %hotfolder::printable(&name),
            folder = %folder.display(),
            error = %e,
            "not picked up: {why}; and it cannot be set aside"
        ),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A top-level task that panics is found, named, and stops the daemon with an error
    /// (before, nothing watched them: a panicked preparation left a daemon that prepared
    /// nothing while it fed the systemd watchdog).
    #[tokio::test]
    async fn a_panicking_task_stops_the_daemon_with_its_name() {
        let mut quiet = Watched::new("quiet", Some(tokio::spawn(std::future::pending())));
        let mut absent = Watched::new("absent", None);
        let mut panicking = Watched::new(
            "preparation",
            Some(tokio::spawn(async {
                tokio::task::yield_now().await;
                let history: Vec<u8> = Vec::new();
                let _ = history[0];
            })),
        );
        let (task, ended) = first_end(&mut [&mut quiet, &mut absent, &mut panicking]).await;
        assert_eq!(task.name, "preparation");
        assert!(panicking.handle.is_none(), "taken out, never awaited again");
        let e = task_failure(&task, ended).expect("a panic stops the daemon");
        let shown = e.to_string();
        assert!(
            shown.contains("preparation task panicked: index out of bounds"),
            "{shown}"
        );
        quiet.handle.take().unwrap().abort();
    }

    /// A task that returns is a failure too, except one that may end on its own (the
    /// shared farm's, when another run took this host's name).
    #[tokio::test]
    async fn a_task_that_returns_stops_the_daemon_unless_it_may() {
        let mut listener = Watched::new("control socket", Some(tokio::spawn(async {})));
        let (task, ended) = first_end(&mut [&mut listener]).await;
        let e = task_failure(&task, ended).expect("an ended listener stops the daemon");
        assert!(
            e.to_string()
                .contains("control socket task ended unexpectedly"),
            "{e}"
        );
        let mut shared = Watched::new("shared farm", Some(tokio::spawn(async {}))).may_end();
        let (task, ended) = first_end(&mut [&mut shared]).await;
        assert!(task_failure(&task, ended).is_none());
    }
}
