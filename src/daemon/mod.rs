//! The print-farm daemon behind `crispen run`: hot folders feed a job spool, jobs are
//! prepared (enhanced and sliced) off the async runtime, and each printer's supervisor
//! prints ready jobs one at a time, waiting for its bed to be cleared in between.
//!
//! - [`config`]: the TOML configuration, checked in two stages.
//! - [`job`]: a job, its states and the one table of legal changes.
//! - [`bed`]: a printer's bed between prints (cleared by a person, ejected by the printer,
//!   checked by its camera) and its table of legal changes; `printer::eject`: running the eject.
//! - [`store`]: the task that owns the jobs (the embedded spool by default), its handle
//!   and the snapshot readers glance at.
//! - [`hotfolder`]: deciding when a dropped file is complete; [`pickup`] admits them.
//! - [`prepare`]: a job's preparation (sidecars, machines, the steps) and its queue.
//! - [`printer`]: printer supervisors and staggered heat-ups; [`fleet`]: the set of them.
//! - [`care`]: a printer's care by use: its counts, its `[[maintenance]]` tasks falling
//!   due, the work recorded, a printer held out of the queue by hand.
//! - [`control`]: the farm's operations (status and the operator's commands), served by
//!   the `http` module on the control socket and on TCP; [`done`]: what a command did.
//! - [`reload`]: SIGHUP, and when each config key's change takes effect.
//! - [`farm`]: the handles to each piece of the farm's state and its owner.
//! - [`shared`]: this host's part in a farm shared through PostgreSQL.
//! - [`error`]: [`DaemonError`], what starting the daemon's pieces can fail with.
//!
//! The `service` module wires them together with the HTTP listeners and supervises them; the
//! daemon does not know of `http`.

pub mod bed;
pub mod care;
pub mod command;
pub mod config;
pub mod control;
pub mod done;
pub(crate) mod error;
pub mod farm;
pub mod filament;
pub mod fleet;
pub mod hotfolder;
pub mod job;
pub(crate) mod plate_folder;
pub mod prepare;
pub(crate) mod printer;
pub mod reload;
pub mod shared;
pub mod spools;
pub mod store;
pub mod time_left;
pub(crate) mod usage;

#[cfg(test)]
pub(crate) mod doubles;
#[cfg(test)]
mod supervision_tests;

pub(crate) use error::DaemonError;

use config::Config;
use farm::Farm;
use job::JobState;
use std::collections::HashMap;
use std::path::PathBuf;
use std::sync::Arc;
use std::time::Duration;
use tokio::sync::mpsc;

/// What [`open_store`] opened.
pub(crate) struct Opened {
    pub farm: Arc<Farm>,
    /// The owners of the farm's other state, for the service to hand out.
    pub owners: farm::Owners,
    /// The job store's task, which nothing answers until the caller runs it (the service,
    /// in its supervised set).
    pub store: store::StoreTask,
    /// A shared farm's database and lease, for [`shared::run`].
    pub shared: Option<(store::postgres::PgStore, Duration)>,
}

/// Opens the job store the config names, applies the restart rules to what this host left
/// mid-flight, and builds the farm around it.
pub(crate) async fn open_store(config: &Config) -> Result<Opened, DaemonError> {
    let mid_flight = |id: &str, state: JobState| {
        tracing::warn!(job = %id, state = state.name(), "job found mid-flight after a restart");
    };
    let Some(shared) = &config.store else {
        let dir = config.spool_dir.clone();
        let (spool, recovered) = store::blocking(move || -> Result<_, job::StoreError> {
            let mut spool = store::spool::Spool::open(&dir)?;
            let recovered: Vec<(String, JobState)> = spool
                .recover()?
                .into_iter()
                .filter_map(|id| Some((id.clone(), spool.get(&id)?.state)))
                .collect();
            Ok((spool, recovered))
        })
        .await?;
        for (id, state) in recovered {
            mid_flight(&id, state);
        }
        let store = store::spool::SpoolStore::from(spool);
        let (farm, owners, store) = Farm::new(config.clone(), store);
        return Ok(Opened {
            farm,
            owners,
            store,
            shared: None,
        });
    };
    let db = store::postgres::PgStore::connect(&shared.postgres, &config.farm.host, shared.lease)
        .await
        .map_err(|e| match e {
            store::postgres::PgError::HostInUse { .. } => DaemonError::HostInUse(e),
            e => DaemonError::Database(e),
        })?;
    let recovered = db.recover_own().await?;
    let store = store::postgres::store::PgJobStore::open(db.clone(), &config.spool_dir).await?;
    let (farm, owners, store) = Farm::new(config.clone(), store);
    for id in recovered {
        if let Some(job) = farm.store().get(&id) {
            mid_flight(&id, job.state);
        }
    }
    let _ = farm.db.set(db.clone());
    Ok(Opened {
        farm,
        owners,
        store,
        shared: Some((db, shared.lease)),
    })
}

/// Watches the hot folders and admits complete files as jobs, until dropped (a reload
/// starts it anew with the new folders) or shutdown.
pub(crate) fn pickup(
    farm: &Arc<Farm>,
    config: &Config,
) -> impl std::future::Future<Output = ()> + Send + 'static {
    let folders: Vec<PathBuf> = config.folders.iter().map(|f| f.path.clone()).collect();
    let (tx, mut rx) = mpsc::channel(64);
    let farm = Arc::clone(farm);
    let settle = config.farm.settle;
    let rescan = config.farm.rescan;
    async move {
        // Plate folders a kill left half packed go back, or go, before anything is watched.
        let staged = folders.clone();
        hotfolder::blocking(move || staged.iter().for_each(|f| drop(plate_folder::recover(f))))
            .await;
        // The watcher goes with the pick-up, however it ends.
        let _watcher = tokio_util::task::AbortOnDropHandle::new(tokio::spawn(hotfolder::watch(
            folders, settle, rescan, tx,
        )));
        let mut at = Pickup {
            waiting: HashMap::new(),
            retries: hotfolder::Retries::default(),
            orphan_after: settle * hotfolder::ORPHAN_SIDECAR_SETTLES,
        };
        loop {
            let due = at.retries.next_due().map(tokio::time::Instant::from_std);
            let offered = tokio::select! {
                offered = rx.recv() => match offered {
                    Some(offered) => vec![offered],
                    None => break,
                },
                () = sleep_until(due) => at.retries.due(std::time::Instant::now()),
            };
            for (path, folder) in offered {
                if farm.stopping() {
                    // Shutdown stops this task; until then nothing more is admitted.
                    return std::future::pending().await;
                }
                // Offered again by the events its failed pick-up made: it waits its turn.
                if at.retries.waits(&path, std::time::Instant::now()) {
                    continue;
                }
                pick_up(&farm, &path, &folder, &mut at).await;
            }
        }
    }
}

/// Sleeps until `deadline`; for ever without one.
async fn sleep_until(deadline: Option<tokio::time::Instant>) {
    match deadline {
        Some(deadline) => tokio::time::sleep_until(deadline).await,
        None => std::future::pending().await,
    }
}

/// What the pick-up keeps from one file to the next.
struct Pickup {
    /// When each sidecar without a model, and each plate folder not whole yet, was first
    /// seen.
    waiting: HashMap<PathBuf, std::time::Instant>,
    /// The files whose pick-up failed, and when each is tried again.
    retries: hotfolder::Retries,
    /// How long a sidecar waits for its model, and a plate folder for its sidecar and
    /// models, before it is set aside.
    orphan_after: Duration,
}

/// Admits one complete file of a hot folder: a model becomes a job (with its sidecar if
/// that is there already); a sidecar whose model was picked up before it arrived joins its
/// job if the job has not started preparing, and is otherwise reported and kept aside.
/// A file whose name has control or bidi characters, and a sidecar whose model has not
/// come within `orphan_after` (it is looked at again on each rescan), are set aside
/// ([`hotfolder::set_aside`]) with a log line naming them. A model whose pick-up fails
/// (the spool's disk full) stays in its folder and is tried again after a wait that grows
/// with each failure ([`hotfolder::Retries`]). A folder is a plate of models
/// ([`pick_up_plate`]).
async fn pick_up(farm: &Farm, path: &std::path::Path, folder: &std::path::Path, at: &mut Pickup) {
    let Pickup {
        waiting: lone_sidecars,
        retries,
        orphan_after,
    } = at;
    let orphan_after = *orphan_after;
    let raw_name = path.file_name().unwrap_or_default();
    let name = raw_name.to_string_lossy().into_owned();
    let problem = match raw_name.to_str() {
        None => Some("is not valid UTF-8"),
        Some(name) => crate::names::problem(name),
    };
    if let Some(problem) = problem {
        set_aside(path, folder, &format!("its name {problem}"));
        return;
    }
    if std::fs::symlink_metadata(path).is_ok_and(|m| m.is_dir()) {
        return pick_up_plate(farm, path, folder, at).await;
    }
    if !hotfolder::is_sidecar_name(&name) {
        let printers = farm
            .config()
            .folder(folder)
            .map(|f| f.printers.clone())
            .unwrap_or_default();
        match farm.jobs().admit(path, folder, &printers).await {
            Ok(job) => {
                retries.forget(path);
                tracing::info!(job = %job.id, file = %path.display(), "picked up")
            }
            // Another host sharing the folder took it first: it moves it away.
            Err(e @ crate::daemon::job::StoreError::TakenElsewhere { .. }) => {
                retries.forget(path);
                tracing::info!(file = %path.display(), reason = %e, "not picked up here")
            }
            // Taken away meanwhile: nothing to try again.
            Err(e) if !path.exists() => {
                retries.forget(path);
                tracing::warn!(file = %path.display(), error = %e, "cannot pick up: the file is gone")
            }
            Err(e) => {
                let wait = retries.failed(path, folder, std::time::Instant::now());
                tracing::error!(file = %path.display(), error = %e, retry_in_s = wait.as_secs(), "cannot pick up; the file stays in its folder and is tried again");
            }
        }
        return;
    }
    let model = name.strip_suffix(".toml").unwrap_or(&name);
    // The model may be spelt otherwise than its sidecar (one composed, one decomposed): it
    // is its model all the same, as the pick-up of the model finds it.
    if !path.exists() || hotfolder::find_named(folder, model).is_some_and(|m| m.exists()) {
        // Taken with its model already, or its model is still arriving.
        lone_sidecars.remove(path);
        return;
    }
    match farm.jobs().late_sidecar(folder, model, path).await {
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

/// Admits a plate folder as one job of its models ([`plate_folder`]): packed into one 3MF,
/// which is admitted, then the folder removed. A folder refused for what it holds is set
/// aside with the reason; one without its sidecar or a model it names may still be
/// arriving and is looked at again on each rescan until the sidecars' wait is over; one
/// whose pick-up fails for the machine's sake (a full disk) is tried again as a model is.
async fn pick_up_plate(
    farm: &Farm,
    dir: &std::path::Path,
    folder: &std::path::Path,
    at: &mut Pickup,
) {
    let (d, f) = (dir.to_path_buf(), folder.to_path_buf());
    let Some(staged) = hotfolder::blocking(move || plate_folder::stage(&d, &f)).await else {
        return;
    };
    let staged = match staged {
        Ok(staged) => staged,
        Err(e) if e.may_be_arriving() => {
            let since = *at
                .waiting
                .entry(dir.to_path_buf())
                .or_insert_with(std::time::Instant::now);
            if since.elapsed() >= at.orphan_after {
                at.waiting.remove(dir);
                set_aside(dir, folder, &format!("a plate folder: {e}"));
            } else {
                tracing::debug!(folder = %dir.display(), reason = %e, "a plate folder not whole yet");
            }
            return;
        }
        Err(e) if e.is_the_folders() => {
            at.waiting.remove(dir);
            set_aside(dir, folder, &format!("a plate folder: {e}"));
            return;
        }
        Err(e) => {
            let wait = at.retries.failed(dir, folder, std::time::Instant::now());
            tracing::error!(folder = %dir.display(), error = %e, retry_in_s = wait.as_secs(), "cannot pack a plate folder; it stays in its hot folder and is tried again");
            return;
        }
    };
    at.waiting.remove(dir);
    let printers = farm
        .config()
        .folder(folder)
        .map(|f| f.printers.clone())
        .unwrap_or_default();
    let admitted = farm.jobs().admit(&staged.model, folder, &printers).await;
    let dir_back = dir.to_path_buf();
    let (finished, job) = match admitted {
        Ok(job) => {
            at.retries.forget(dir);
            tracing::info!(job = %job.id, folder = %dir.display(), "picked up a plate folder as one job of its models");
            (
                hotfolder::blocking(move || staged.admitted()).await,
                Some(job.id),
            )
        }
        Err(e) => {
            let wait = at.retries.failed(dir, folder, std::time::Instant::now());
            tracing::error!(folder = %dir.display(), error = %e, retry_in_s = wait.as_secs(), "cannot pick up a plate folder; it goes back to its hot folder and is tried again");
            (
                hotfolder::blocking(move || staged.undo(&dir_back)).await,
                None,
            )
        }
    };
    if let Some(Err(e)) = finished {
        tracing::error!(job = ?job, folder = %dir.display(), error = %e, "cannot finish with a plate folder in its hot folder's {}/ (the next start finishes it)", plate_folder::STAGING_DIR)
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
