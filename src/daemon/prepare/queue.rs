//! The daemon's preparation queue: queued jobs are prepared oldest first, at most one per
//! core at a time, each in its own child process ([`super::run_child`]); the outcome (G-code
//! per machine, or the reason none can print it) is recorded in the job.

use crate::daemon::farm::Farm;
use crate::daemon::job::{JobState, StoreError};
use crate::daemon::store::StateFilter;
use std::path::PathBuf;
use std::sync::Arc;
use std::time::Duration;
use tokio_util::sync::CancellationToken;
use tracing::Instrument;

/// Prepares queued jobs, oldest first, at most one per core at a time, each in its own
/// child process under a token of its own (a child of the shutdown token).
pub async fn prepare_loop(farm: Arc<Farm>, program: PathBuf) {
    let cores = std::thread::available_parallelism()
        .map(|n| n.get())
        .unwrap_or(1);
    let mut running = tokio::task::JoinSet::new();
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
                .transition_from(&id, &[JobState::Queued], JobState::Preparing, None, |_| {})
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
            farm.start_preparation(&id, cancel.clone());
            let span = tracing::info_span!("job", job = %id);
            running.spawn(
                prepare_one(Arc::clone(&farm), id, program.clone(), cancel).instrument(span),
            );
        }
        let grace = Duration::from_secs_f64(wait_s.unwrap_or(0.0).clamp(0.0, 3600.0));
        tokio::select! {
            Ok(()) = jobs.changed() => {}
            Ok(()) = reloads.changed() => {}
            Some(_) = running.join_next() => {}
            _ = farm.shutdown.cancelled() => {}
            _ = tokio::time::sleep(grace), if wait_s.is_some() => {}
        }
    }
    // The shutdown token has stopped every preparation's child; wait for their jobs to be
    // put back in the queue.
    while running.join_next().await.is_some() {}
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
async fn prepare_one(farm: Arc<Farm>, id: String, program: PathBuf, cancel: CancellationToken) {
    let resolved = {
        let (farm, id) = (Arc::clone(&farm), id.clone());
        tokio::task::spawn_blocking(move || resolve(&farm, &id))
            .await
            .unwrap_or_else(|e| Err(format!("preparation crashed: {e}")))
    };
    let result = match resolved {
        Err(reason) => Err(super::PrepareError::Failed(reason)),
        Ok((task, sidecar)) => {
            tracing::info!(
                model = %task.model.display(),
                height_mm = task.height_mm,
                strength = ?task.strength,
                "preparing"
            );
            let on_step = |step: String| farm.preparation_step(&id, step);
            super::run_child(&program, &task, &cancel, on_step)
                .await
                .map(|report| (report, sidecar))
        }
    };
    finish_preparation(&farm, &id, result).await;
}

/// Reads the job's sidecar and works out its task.
fn resolve(
    farm: &Farm,
    id: &str,
) -> Result<(super::PrepareTask, Option<crate::daemon::job::Sidecar>), String> {
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
    let sidecar = crate::daemon::job::read_sidecar(&dir.join(format!("{}.toml", job.file)))?;
    let task = super::resolve_task(
        id,
        &dir,
        &job.file,
        folder,
        &farm.printer_machines(),
        sidecar.as_ref(),
    )?;
    Ok((task, sidecar))
}

/// Records a preparation's outcome, unless the job was cancelled (or otherwise moved on)
/// meanwhile: the store checks that it is still preparing as one step with the change.
async fn finish_preparation(
    farm: &Farm,
    id: &str,
    result: Result<(super::Prepared, Option<crate::daemon::job::Sidecar>), super::PrepareError>,
) {
    farm.end_preparation(id);
    const STILL_PREPARING: StateFilter = &[JobState::Preparing];
    let outcome = match result {
        Ok((prepared, sidecar)) => {
            let (machines, report) = prepared.for_machines();
            match prepared.failure() {
                // No machine can print it: failed, with each machine's reason.
                Some(reason) => {
                    farm.jobs()
                        .transition_from(id, STILL_PREPARING, JobState::Failed, Some(reason), |j| {
                            j.machines = machines;
                            j.sidecar = sidecar;
                        })
                        .await
                }
                None => {
                    farm.jobs()
                        .transition_from(id, STILL_PREPARING, JobState::Ready, None, |j| {
                            j.slice_report = report;
                            j.machines = machines;
                            j.sidecar = sidecar;
                        })
                        .await
                }
            }
        }
        // Still preparing, so not cancelled by the operator: the daemon is stopping, and
        // the job is prepared again at the next start.
        Err(super::PrepareError::Cancelled) => {
            farm.jobs()
                .transition_from(id, STILL_PREPARING, JobState::Queued, None, |_| {})
                .await
        }
        Err(e) => {
            let reason = Some(e.to_string());
            farm.jobs()
                .transition_from(id, STILL_PREPARING, JobState::Failed, reason, |_| {})
                .await
        }
    };
    match outcome {
        Ok(_) | Err(StoreError::StateChanged { .. }) => {}
        Err(e) => tracing::error!(job = id, error = %e, "cannot record the preparation's outcome"),
    }
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
