//! The daemon's preparation queue: queued jobs are prepared oldest first, at most one per
//! core at a time, each in its own child process ([`super::process::run_child`]); the
//! outcome (G-code per machine, or the reason none can print it) is recorded in the job.
//!
//! An enhanced job is ready with its comparison pending ([`Comparison`]). Comparisons are
//! the queue's low-priority work: one at a time, started only while no job is being
//! prepared or waits to be (a job that arrives meanwhile is prepared at once, beside it:
//! the comparison's process runs at the lowest CPU priority), each in a child process of
//! its own ([`super::process::run_compare_child`]). Its figures go into the job's report
//! through the store; a comparison that fails leaves the job as it was, marked not
//! measured. Each start is counted in the job, so one that the daemon's stops keep cutting
//! short is given up after [`COMPARE_TRIES`] rather than redone at every start.
//!
//! The comparison also draws the enhanced job's preview of the print (`preview.png`,
//! [`crate::preview::print`]). A job printed unmodified or pre-sliced has no comparison;
//! its preview (a pre-sliced one's without a model beside it) is drawn as the same
//! low-priority work ([`preview_one`]), once per job and G-code: a preview that fails is
//! logged and the job stands.

use super::process::{run_child, run_compare_child, PrepareError};
use super::task::{resolve_task, PrepareTask, Prepared, TaskMachine};
use crate::daemon::farm::{Farm, PreparingOwner};
use crate::daemon::job::{Comparison, JobState, StoreError};
use crate::daemon::store::{JobChange, PreparedJob, StateFilter};
use crate::slice::moved::WallsState;
use std::collections::HashSet;
use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::time::{Duration, Instant};
use tokio_util::sync::CancellationToken;
use tracing::Instrument;

/// Prepares queued jobs, oldest first, at most one per core at a time, each in its own
/// child process under a token of its own (a child of the shutdown token); in between,
/// measures the ready jobs' comparisons (see the module's comment).
/// `owner`: the preparations in progress are this queue's to show.
pub(crate) async fn prepare_loop(farm: Arc<Farm>, owner: PreparingOwner, program: PathBuf) {
    let cores = std::thread::available_parallelism()
        .map(|n| n.get())
        .unwrap_or(1);
    let mut running = tokio::task::JoinSet::new();
    let mut measuring = tokio::task::JoinSet::new();
    // The unmodified jobs whose preview was looked at in this run, each as of its
    // history (a job prepared again has a longer one, and a new G-code to draw).
    let mut looked_at: HashSet<(String, usize)> = HashSet::new();
    loop {
        // Followed from before the look at the queue: a change while looking is not
        // missed. A reload may let a job be prepared here.
        let (mut jobs, mut reloads) = (farm.watch_jobs(), farm.watch_config());
        if farm.stopping() {
            break;
        }
        // A job just picked up waits the settle time, so a sidecar that arrives shortly
        // after its model still applies.
        let config = farm.config();
        let settle = config.farm.settle.as_secs_f64();
        let mut wait_s: Option<f64> = None;
        while running.len() < cores {
            let now = crate::daemon::job::now_s();
            let next = farm
                .store()
                .jobs()
                .filter(|j| j.state == JobState::Queued && can_prepare(&config, j))
                .find(|j| match settle_left(j, settle, now) {
                    Some(left) => {
                        wait_s = Some(wait_s.map_or(left, |w| w.min(left)));
                        false
                    }
                    None => true,
                })
                .map(|j| j.id.clone());
            let Some(id) = next else { break };
            let claimed = farm
                .jobs()
                .transition_from(
                    &id,
                    &[JobState::Queued],
                    JobState::Preparing,
                    None,
                    JobChange::Nothing,
                )
                .await;
            if let Err(e) = claimed {
                if matches!(e, StoreError::StateChanged { .. }) {
                    // Another host of the farm took it first.
                    continue;
                }
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
            owner.start(&id, cancel.clone());
            let span = tracing::info_span!("job", job = %id);
            running.spawn(
                prepare_one(
                    Arc::clone(&farm),
                    owner.clone(),
                    id,
                    program.clone(),
                    cancel,
                )
                .instrument(span),
            );
        }
        // A comparison never goes ahead of a preparation: none starts while a job is
        // being prepared or waits to be (settling included).
        let to_prepare = farm
            .store()
            .jobs()
            .any(|j| j.state == JobState::Queued && can_prepare(&config, j));
        if running.is_empty() && measuring.is_empty() && !to_prepare {
            if let Some((id, tries)) = next_comparison(&farm, &config).await {
                let span = tracing::info_span!("job", job = %id);
                measuring.spawn(
                    compare_one(Arc::clone(&farm), id, tries, program.clone()).instrument(span),
                );
            } else if let Some(id) = next_preview(&farm, &config, &mut looked_at) {
                let span = tracing::info_span!("job", job = %id);
                measuring.spawn(preview_one(Arc::clone(&farm), id).instrument(span));
            }
        }
        let grace = Duration::from_secs_f64(wait_s.unwrap_or(0.0).clamp(0.0, 3600.0));
        tokio::select! {
            Ok(()) = jobs.changed() => {}
            Ok(()) = reloads.changed() => {}
            Some(_) = running.join_next() => {}
            Some(_) = measuring.join_next() => {}
            _ = farm.shutdown.cancelled() => {}
            _ = tokio::time::sleep(grace), if wait_s.is_some() => {}
        }
    }
    // The shutdown token has stopped every preparation's child; wait for their jobs to be
    // put back in the queue (and a comparison's to stay pending).
    while running.join_next().await.is_some() {}
    while measuring.join_next().await.is_some() {}
}

/// Whether this host can prepare a job: one from its own folders (a job whose folder has
/// left the config fails, with a hint), or, in a farm shared with other hosts, one from a
/// folder this host's config also has.
/// Seconds a job just picked up still waits for the settle time, or None when it may be
/// prepared now. Only a job whose whole history is its pick-up waits; a history read from
/// disk or from the database may be anything, empty included, and must not panic here.
fn settle_left(job: &crate::daemon::job::Job, settle_s: f64, now: f64) -> Option<f64> {
    match job.history.as_slice() {
        [(_, picked_up)] => Some(picked_up + settle_s - now).filter(|left| *left > 0.0),
        _ => None,
    }
}

fn can_prepare(config: &crate::daemon::config::Config, job: &crate::daemon::job::Job) -> bool {
    match &job.origin {
        Some(origin) if origin.host != config.farm.host => config.folder(&job.folder).is_some(),
        _ => true,
    }
}

/// Prepares one job and records the outcome.
async fn prepare_one(
    farm: Arc<Farm>,
    owner: PreparingOwner,
    id: String,
    program: PathBuf,
    cancel: CancellationToken,
) {
    let resolved = {
        let (farm, id) = (Arc::clone(&farm), id.clone());
        tokio::task::spawn_blocking(move || resolve(&farm, &id))
            .await
            .unwrap_or_else(|e| Err(format!("preparation crashed: {e}")))
    };
    let result = match resolved {
        Err(reason) => Err(PrepareError::Failed(reason)),
        Ok((task, sidecar)) => {
            tracing::info!(
                model = %task.model.display(),
                height_mm = task.height_mm,
                strength = ?task.strength,
                "preparing"
            );
            let on_step = |step: String| owner.step(&id, step);
            let asks = task.asks.clone();
            run_child(&program, &task, &cancel, on_step)
                .await
                .and_then(|prepared| {
                    // The file's own material, checked here too: the child read it from
                    // a file anyone may drop.
                    let asks = asks
                        .with_file_material(prepared.file_material.as_deref())
                        .map_err(PrepareError::Failed)?;
                    Ok((prepared, sidecar, asks))
                })
        }
    };
    finish_preparation(&farm, &owner, &id, result).await;
}

/// Reads the job's sidecar and works out its task.
fn resolve(
    farm: &Farm,
    id: &str,
) -> Result<(PrepareTask, Option<crate::daemon::job::Sidecar>), String> {
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
    let mut sidecar = crate::daemon::job::read_sidecar(&dir.join(format!("{}.toml", job.file)))?;
    // The folder's copies, unless the sidecar says: kept with the job, which makes its
    // copies from what it holds once it is ready.
    if folder.copies > 1
        && sidecar
            .as_ref()
            .is_none_or(|s| s.copies.is_none() && s.printers.is_none())
    {
        sidecar.get_or_insert_with(Default::default).copies = Some(folder.copies);
    }
    let mut task = resolve_task(
        id,
        &dir,
        &job.file,
        folder,
        &farm.printer_machines(),
        sidecar.as_ref(),
    )?;
    task.observe = config.enhancement.clone();
    Ok((task, sidecar))
}

/// Records a preparation's outcome, unless the job was cancelled (or otherwise moved on)
/// meanwhile: the store checks that it is still preparing as one step with the change.
async fn finish_preparation(
    farm: &Farm,
    owner: &PreparingOwner,
    id: &str,
    result: Result<
        (
            Prepared,
            Option<crate::daemon::job::Sidecar>,
            crate::daemon::filament::Asks,
        ),
        PrepareError,
    >,
) {
    owner.end(id);
    const STILL_PREPARING: StateFilter = &[JobState::Preparing];
    let outcome = match result {
        Ok((prepared, sidecar, asks)) => {
            let (machines, mut report) = prepared.for_machines();
            let needs = prepared.needs();
            match prepared.failure() {
                // No machine can print it: failed, with each machine's reason.
                Some(reason) => {
                    let change = JobChange::Unprintable {
                        machines,
                        sidecar,
                        asks,
                    };
                    farm.jobs()
                        .transition_from(
                            id,
                            STILL_PREPARING,
                            JobState::Failed,
                            Some(reason),
                            change,
                        )
                        .await
                }
                None => {
                    // Only an enhanced model has an unmodified one to be compared with.
                    let enhanced = report
                        .as_ref()
                        .is_some_and(|r| r.enhancement.lambda2.is_some());
                    if let Some(r) = &mut report {
                        r.walls_state = if enhanced {
                            WallsState::Pending
                        } else {
                            WallsState::NotAsked
                        };
                    }
                    let change = JobChange::Prepared(Box::new(PreparedJob {
                        machines,
                        needs,
                        sidecar,
                        asks,
                        report,
                        comparison: enhanced.then_some(Comparison::Pending { tries: 0 }),
                    }));
                    farm.jobs()
                        .transition_from(id, STILL_PREPARING, JobState::Ready, None, change)
                        .await
                }
            }
        }
        // Still preparing, so not cancelled by the operator: the daemon is stopping, and
        // the job is prepared again at the next start.
        Err(PrepareError::Cancelled) => {
            farm.jobs()
                .transition_from(
                    id,
                    STILL_PREPARING,
                    JobState::Queued,
                    None,
                    JobChange::Nothing,
                )
                .await
        }
        Err(e) => {
            let reason = Some(e.to_string());
            farm.jobs()
                .transition_from(
                    id,
                    STILL_PREPARING,
                    JobState::Failed,
                    reason,
                    JobChange::Nothing,
                )
                .await
        }
    };
    match outcome {
        Ok(_) | Err(StoreError::StateChanged { .. }) => {}
        Err(e) => tracing::error!(job = id, error = %e, "cannot record the preparation's outcome"),
    }
}

/// Starts of one job's comparison after which it is given up (each start that ended
/// without an outcome was cut short by the daemon's stop or a crash).
pub(crate) const COMPARE_TRIES: u32 = 2;

/// The oldest job whose comparison is pending, with its start counted in the job (the
/// count it now has); a job whose tries are used up is marked not measured on the way.
async fn next_comparison(
    farm: &Farm,
    config: &crate::daemon::config::Config,
) -> Option<(String, u32)> {
    loop {
        let (id, tries) = farm.store().jobs().find_map(|j| match j.comparison {
            // A job prepared again gets a comparison of its own when it is ready; a copy
            // takes its first job's.
            Some(Comparison::Pending { tries })
                if !matches!(j.state, JobState::Queued | JobState::Preparing)
                    && j.copy.is_none()
                    && can_prepare(config, j) =>
            {
                Some((j.id.clone(), tries))
            }
            _ => None,
        })?;
        let next = if tries >= COMPARE_TRIES {
            tracing::warn!(job = %id, tries, "the wall comparison never ended; given up");
            Comparison::NotMeasured {
                reason: format!(
                    "started {tries} times and cut short each time (the daemon stopped); not tried again"
                ),
            }
        } else {
            Comparison::Pending { tries: tries + 1 }
        };
        let counted = farm
            .jobs()
            .update(&id, JobChange::ComparisonStarted { tries, next })
            .await;
        match counted {
            Ok(updated) => match updated.job.comparison {
                Some(Comparison::Pending { tries: now }) if now == tries + 1 => {
                    return Some((id, now))
                }
                // Given up, or changed meanwhile: look again.
                _ => {}
            },
            Err(e) => {
                // Tried again at the next change of the jobs.
                tracing::error!(job = %id, error = %e, "cannot start the wall comparison");
                return None;
            }
        }
    }
}

/// Measures one job's comparison (its `tries`-th start) and records the outcome. Cut
/// short by the daemon's stop, it stays pending, for the next start.
async fn compare_one(farm: Arc<Farm>, id: String, tries: u32, program: PathBuf) {
    let (started_s, clock) = (crate::daemon::job::now_s(), Instant::now());
    let task = {
        let (farm, id) = (Arc::clone(&farm), id.clone());
        tokio::task::spawn_blocking(move || resolve_comparison(&farm, &id))
            .await
            .unwrap_or_else(|e| Err(format!("the comparison crashed: {e}")))
    };
    let result = match task {
        Err(reason) => Err(reason),
        Ok(task) => {
            tracing::info!(machine = %task.machines[0].machine.name, tries, "comparing the outer walls with the unmodified model's");
            let cancel = farm.shutdown.child_token();
            match run_compare_child(&program, &task, &cancel).await {
                Err(PrepareError::Cancelled) => return,
                result => result.map_err(|e| e.to_string()),
            }
        }
    };
    let took_s = clock.elapsed().as_secs_f64();
    let result = result.map_err(|reason| {
        tracing::warn!(%reason, "the wall comparison was not made; the job is as it was");
        // Shown to clients: never the server's paths.
        let dir = farm.store().job_dir(&id);
        let spool = dir.ancestors().nth(2).unwrap_or(&dir);
        crate::daemon::store::spool_relative(&reason, spool)
    });
    let change = JobChange::ComparisonEnded {
        tries,
        walls: result,
        started_s,
        took_s,
    };
    let recorded = farm.jobs().update(&id, change).await;
    match recorded {
        Ok(_) => tracing::info!(seconds = took_s, "wall comparison recorded"),
        // Moved to the history meanwhile: the comparison no longer has a job to go into.
        Err(StoreError::NoSuchJob(_)) => {}
        Err(e) => tracing::error!(error = %e, "cannot record the wall comparison"),
    }
}

/// The oldest job printed unmodified or pre-sliced whose preview is missing or older
/// than its G-code. Each job's files are looked at once per state change in this run
/// (`looked_at`, by its history's length): not at every turn of the loop, under the
/// store's lock, for every job the farm has kept.
fn next_preview(
    farm: &Farm,
    config: &crate::daemon::config::Config,
    looked_at: &mut HashSet<(String, usize)>,
) -> Option<String> {
    let store = farm.store();
    for j in store.jobs() {
        let unmodified = j
            .slice_report
            .as_ref()
            .is_some_and(|r| r.enhancement.lambda2.is_none());
        let drawable = unmodified
            && j.comparison.is_none()
            && matches!(
                j.state,
                JobState::Ready | JobState::Printing | JobState::Done | JobState::Interrupted
            )
            && can_prepare(config, j);
        if !drawable || !looked_at.insert((j.id.clone(), j.history.len())) {
            continue;
        }
        let gcode = j
            .slice_report
            .as_ref()
            .and_then(|r| j.gcode_for(&r.machine));
        if gcode.is_some_and(|g| {
            let dir = store.job_dir(&j.id);
            preview_missing(&dir, &dir.join(g))
        }) {
            return Some(j.id.clone());
        }
    }
    None
}

/// Whether `dir` has no preview of the print newer than `gcode`.
fn preview_missing(dir: &Path, gcode: &Path) -> bool {
    let modified = |p: &Path| std::fs::metadata(p).and_then(|m| m.modified()).ok();
    match (
        modified(&dir.join(crate::preview::PREVIEW_PNG)),
        modified(gcode),
    ) {
        (Some(picture), Some(gcode)) => picture < gcode,
        (None, Some(_)) => true,
        // No G-code: nothing to draw.
        (_, None) => false,
    }
}

/// Draws the preview of a job printed unmodified or pre-sliced (see the module's
/// comment), in this process but on one thread at the lowest CPU priority, so that a
/// preparation that starts meanwhile has the cores. A preview that fails is logged; the
/// job is as it was.
async fn preview_one(farm: Arc<Farm>, id: String) {
    let clock = Instant::now();
    let drawn = {
        let (farm, id) = (Arc::clone(&farm), id.clone());
        tokio::task::spawn_blocking(move || -> Result<(), String> {
            let task = resolve_comparison(&farm, &id)?;
            let pool = rayon::ThreadPoolBuilder::new()
                .num_threads(1)
                .thread_name(|_| "preview".into())
                .start_handler(|_| {
                    // SAFETY: setpriority only changes this thread's scheduling (Linux
                    // nices threads one by one); it touches no memory.
                    unsafe { nix::libc::setpriority(nix::libc::PRIO_PROCESS, 0, 19) };
                })
                .build()
                .map_err(|e| format!("no thread to draw on: {e}"))?;
            pool.install(|| super::work::preview_task(&task))
        })
        .await
        .unwrap_or_else(|e| Err(format!("the preview crashed: {e}")))
    };
    match drawn {
        Ok(()) => tracing::info!(
            seconds = clock.elapsed().as_secs_f64(),
            "preview of the print done"
        ),
        Err(reason) => tracing::warn!(%reason, "no preview of the print; the job is as it was"),
    }
    // A change of the job, for its pictures to be looked at again.
    match farm.jobs().update(&id, JobChange::Nothing).await {
        Ok(_) | Err(StoreError::NoSuchJob(_)) => {}
        Err(e) => tracing::error!(error = %e, "cannot record the preview"),
    }
}

/// The comparison's task: the job's own (as it would be prepared now), for the machine of
/// its report, whose G-code it compares.
fn resolve_comparison(farm: &Farm, id: &str) -> Result<PrepareTask, String> {
    let (mut task, _) = resolve(farm, id)?;
    let job = farm.store().get(id).cloned().ok_or("job vanished")?;
    let report = job.slice_report.as_ref().ok_or("the job has no report")?;
    // Compared as it was prepared, or not at all: a measure of other settings would
    // mislead. (A pre-sliced file was made elsewhere: only its preview is drawn, from it.)
    let presliced = super::task::is_presliced(&job.file);
    if !presliced && (task.height_mm != report.height_mm || task.slicer != report.slicer) {
        return Err("the folder's settings changed since the job was prepared".into());
    }
    let gcode = job
        .gcode_for(&report.machine)
        .ok_or_else(|| format!("the job has no G-code for the {}", report.machine))?;
    let machine = task
        .machines
        .drain(..)
        .find(|m| m.machine.name == report.machine)
        .ok_or_else(|| format!("the {} no longer serves the job's folder", report.machine))?;
    let output = task.model.with_file_name(gcode);
    task.machines = vec![TaskMachine { output, ..machine }];
    task.compare = true;
    Ok(task)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::daemon::job::Job;

    /// A job whose job.json has an empty history (hand-edited, or written by a broken
    /// store) is prepared without waiting; reading `history[0]` once panicked the whole
    /// preparation task.
    #[test]
    fn a_job_with_an_empty_history_does_not_panic_preparation() {
        let tmp = tempfile::tempdir().unwrap();
        let job = Job::queued("0001-a".into(), 1, "a.stl".into(), tmp.path().into());
        let mut on_disk = serde_json::to_value(&job).unwrap();
        on_disk["history"] = serde_json::json!([]);
        let path = tmp.path().join("job.json");
        std::fs::write(&path, serde_json::to_vec(&on_disk).unwrap()).unwrap();
        let read: Job = serde_json::from_slice(&std::fs::read(&path).unwrap()).unwrap();
        assert!(read.history.is_empty());
        assert_eq!(settle_left(&read, 30.0, crate::daemon::job::now_s()), None);
    }

    fn farm(root: &std::path::Path) -> Arc<Farm> {
        let text = "[spool]\ndir = \"spool\"\n";
        let config =
            crate::daemon::config::Config::parse(text, &root.join("crispen.toml")).unwrap();
        let store = crate::daemon::store::spool::SpoolStore::open(&root.join("spool")).unwrap();
        let (farm, _owners, task) = Farm::new(config, store);
        tokio::spawn(task);
        farm
    }

    /// A ready job whose comparison is `comparison`.
    async fn ready_job(farm: &Farm, root: &std::path::Path, comparison: Comparison) -> String {
        let hot = root.join("hot");
        std::fs::create_dir_all(&hot).unwrap();
        std::fs::write(hot.join("a.stl"), b"solid x\nendsolid x\n").unwrap();
        let id = farm
            .jobs()
            .admit(&hot.join("a.stl"), &hot, &[])
            .await
            .unwrap()
            .id;
        farm.jobs()
            .transition(&id, JobState::Preparing, None)
            .await
            .unwrap();
        farm.jobs()
            .transition_with(
                &id,
                JobState::Ready,
                None,
                JobChange::Edit(Box::new(move |j| {
                    j.slice_report = Some(Default::default());
                    j.comparison = Some(comparison);
                })),
            )
            .await
            .unwrap();
        id
    }

    /// Each start of a comparison is counted in the job before it runs, so a daemon
    /// stopped (or crashed) during it measures it again at its next start, but not
    /// forever: after [`COMPARE_TRIES`] starts without an outcome it is not measured.
    #[tokio::test]
    async fn a_comparison_never_ended_is_given_up_after_its_tries() {
        let tmp = tempfile::tempdir().unwrap();
        let farm = farm(tmp.path());
        let id = ready_job(&farm, tmp.path(), Comparison::Pending { tries: 0 }).await;
        let config = farm.config();
        for tries in 1..=COMPARE_TRIES {
            assert_eq!(
                next_comparison(&farm, &config).await,
                Some((id.clone(), tries))
            );
            let kept = farm.store().get(&id).unwrap().comparison.clone();
            assert_eq!(kept, Some(Comparison::Pending { tries }));
        }
        assert_eq!(next_comparison(&farm, &config).await, None);
        let job = farm.store().get(&id).cloned().unwrap();
        assert!(
            matches!(&job.comparison, Some(Comparison::NotMeasured { reason }) if reason.contains("not tried again")),
            "{:?}",
            job.comparison
        );
        assert_eq!(job.state, JobState::Ready, "the job stays as it was");
    }

    /// A comparison that fails leaves the job ready and shows why, without the spool's
    /// paths; one whose job was prepared again meanwhile (its comparison pending afresh)
    /// is dropped rather than put over the new G-code's.
    #[tokio::test]
    async fn a_failed_or_stale_comparison_leaves_the_job_as_it_was() {
        let tmp = tempfile::tempdir().unwrap();
        let farm = farm(tmp.path());
        let id = ready_job(&farm, tmp.path(), Comparison::Pending { tries: 0 }).await;
        let config = farm.config();
        let (_, tries) = next_comparison(&farm, &config).await.unwrap();
        // The job's folder is not in the config: no task, so no comparison.
        compare_one(Arc::clone(&farm), id.clone(), tries, "/nonexistent".into()).await;
        let job = farm.store().get(&id).cloned().unwrap();
        match &job.comparison {
            Some(Comparison::NotMeasured { reason }) => {
                assert!(reason.contains("no longer in the config"), "{reason}");
                let spool = tmp.path().join("spool");
                assert!(!reason.contains(&*spool.to_string_lossy()), "{reason}");
            }
            other => panic!("{other:?}"),
        }
        assert_eq!(job.state, JobState::Ready);
        assert!(job.slice_report.unwrap().walls.is_none());

        let pending_afresh = || {
            JobChange::Edit(Box::new(|j| {
                j.comparison = Some(Comparison::Pending { tries: 0 })
            }))
        };
        farm.jobs().update(&id, pending_afresh()).await.unwrap();
        let (_, tries) = next_comparison(&farm, &config).await.unwrap();
        // Prepared again meanwhile: pending afresh.
        farm.jobs().update(&id, pending_afresh()).await.unwrap();
        compare_one(Arc::clone(&farm), id.clone(), tries, "/nonexistent".into()).await;
        let kept = farm.store().get(&id).unwrap().comparison.clone();
        assert_eq!(kept, Some(Comparison::Pending { tries: 0 }));
    }

    /// The settle time applies to a job just picked up, and only to it.
    #[test]
    fn only_a_job_just_picked_up_waits_to_settle() {
        let tmp = tempfile::tempdir().unwrap();
        let mut job = Job::queued("0001-a".into(), 1, "a.stl".into(), tmp.path().into());
        let picked_up = job.history[0].1;
        assert_eq!(settle_left(&job, 30.0, picked_up + 10.0), Some(20.0));
        assert_eq!(settle_left(&job, 30.0, picked_up + 30.0), None);
        job.history.push((JobState::Preparing, picked_up + 1.0));
        job.history.push((JobState::Queued, picked_up + 2.0));
        assert_eq!(settle_left(&job, 30.0, picked_up + 3.0), None);
    }
}
