//! The camera's part in clearing beds: the picture of each printer's empty bed (the
//! reference, taken when a person confirms the bed is clear), and the check of a bed the
//! store says is due for one (after an eject, or before a job on a bed the camera found
//! clear a while ago). Like the recorder it follows the published state and never touches
//! a printer: a check answers with the bed's next state, through the store, with the
//! frame marked where it differs, kept with the job whose print was on the bed.
//!
//! A check waits for a frame the camera took after the moment it is due (plus
//! [`SETTLE_S`]: the last moves' answer may come a little before the camera's next
//! frame shows them), at most [`frame_wait`]; a camera that is offline, frozen or has no
//! reference sends the bed to a person with that reason. A daemon killed during a check
//! finds it due again at its next start, and makes it again: it moves nothing.

use super::hub::{Cameras, NoFrame};
use crate::bedcheck::{Reference, Region};
use crate::daemon::bed::{Bed, CameraProblem, CheckRecord, ClearedBy, Clearing, Why};
use crate::daemon::farm::Farm;
use crate::daemon::job::now_s;
use crate::daemon::store::BedChange;
use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::time::Duration;
use tokio_util::sync::CancellationToken;
use tracing::Instrument;

/// A frame for a check must be this much newer than the moment the check was due.
pub const SETTLE_S: f64 = 1.0;

/// The reference's file for `printer` under the spool.
pub fn reference_path(spool: &Path, printer: &str) -> PathBuf {
    spool.join("bed").join(printer).join("reference.jpg")
}

/// How long a check waits for a frame newer than its moment: a few of the camera's
/// refreshes and its time limit, at least 20 s.
fn frame_wait(cameras: &Cameras) -> Duration {
    (cameras.settings.refresh * 3 + cameras.settings.timeout).max(Duration::from_secs(20))
}

/// Why a reference could not be taken, for the person who asked.
#[derive(Debug, thiserror::Error)]
pub enum ReferenceError {
    #[error("printer {0} has no camera")]
    NoCamera(String),
    #[error("its camera has no fresh picture ({0})")]
    NoPicture(String),
    #[error("cannot keep the picture: {0}")]
    Write(String),
}

/// Takes the printer's picture now as the picture of its empty bed (blocking: it may
/// decode a frame and writes a file).
pub fn take_reference(
    cameras: &Cameras,
    spool: &Path,
    printer: &str,
) -> Result<(), ReferenceError> {
    if !cameras.has(printer) {
        return Err(ReferenceError::NoCamera(printer.to_string()));
    }
    let picture = match cameras.fresh_picture(printer) {
        Some(Ok(p)) => p,
        Some(Err(NoFrame::Picture)) => {
            return Err(ReferenceError::NoPicture(
                "the camera's frame could not be made into the printer's picture".into(),
            ))
        }
        _ => {
            let why = cameras
                .status(printer, false)
                .and_then(|s| s.error)
                .unwrap_or_else(|| "no frame lately".into());
            return Err(ReferenceError::NoPicture(why));
        }
    };
    let path = reference_path(spool, printer);
    let write = || -> std::io::Result<()> {
        std::fs::create_dir_all(path.parent().unwrap_or(spool))?;
        Ok(crate::fsutil::write_atomic(&path, &picture.jpeg)?)
    };
    write().map_err(|e| ReferenceError::Write(e.to_string()))?;
    tracing::info!(printer, file = %path.display(), "the picture of the empty bed taken as the reference");
    Ok(())
}

/// Checks `printer`'s bed whenever the store says a check is due, until `stop`.
pub(crate) async fn watch(
    farm: Arc<Farm>,
    cameras: Arc<Cameras>,
    printer: String,
    stop: CancellationToken,
) {
    let mut beds = farm.watch_jobs();
    let mut reference: Option<(std::time::SystemTime, Arc<Reference>)> = None;
    loop {
        let due = match farm.store().gate(&printer).bed {
            Bed::CheckDue { after_s, .. } => Some(after_s),
            _ => None,
        };
        if let Some(after_s) = due {
            let span = tracing::info_span!("bed check", printer = %printer);
            let checked =
                check(&farm, &cameras, &printer, after_s, &mut reference).instrument(span);
            let answer = tokio::select! {
                a = checked => a,
                _ = stop.cancelled() => return,
            };
            let (to, record) = answer;
            let job = farm.store().gate(&printer).last_job;
            let check = record.clone();
            let change = BedChange {
                from: Some(&["check_due"]),
                to,
                printed: None,
                check: check.clone(),
                record: check.map(|check| Clearing::Check {
                    printer: printer.clone(),
                    check,
                }),
            };
            match farm.jobs().change_bed(&printer, change).await {
                Ok(_) => {
                    tracing::info!(printer = %printer, job = job.as_deref().unwrap_or("-"), "bed checked")
                }
                Err(e) => {
                    tracing::warn!(printer = %printer, error = %e, "the bed check's answer came too late")
                }
            }
            continue;
        }
        tokio::select! {
            r = beds.changed() => if r.is_err() { return },
            _ = stop.cancelled() => return,
        }
    }
}

/// One check: the bed's next state, and the check's record when the camera answered.
async fn check(
    farm: &Farm,
    cameras: &Arc<Cameras>,
    printer: &str,
    after_s: f64,
    cached: &mut Option<(std::time::SystemTime, Arc<Reference>)>,
) -> (Bed, Option<CheckRecord>) {
    let no = |problem: CameraProblem| {
        tracing::warn!(printer, problem = %problem.describe(), "the bed cannot be checked; it waits for a person");
        (
            Bed::Waiting {
                why: Some(Why::NoCheck { problem }),
            },
            None,
        )
    };
    let config = farm.config();
    let Some(pc) = config.printers.iter().find(|p| p.name == printer) else {
        return no(CameraProblem::NoCamera);
    };
    let Some(mut feed) = cameras.watch(printer) else {
        return no(CameraProblem::NoCamera);
    };
    let region = pc.camera.as_ref().and_then(|c| c.bed_region);
    let bed_mm = [pc.machine.bed_mm[0], pc.machine.bed_mm[1]];
    // The reference, prepared once and again when a person takes a new one.
    let path = reference_path(&config.spool_dir, printer);
    let modified = std::fs::metadata(&path).and_then(|m| m.modified()).ok();
    let Some(modified) = modified else {
        return no(CameraProblem::NoReference);
    };
    let reference = match cached.as_ref().filter(|(t, _)| *t == modified) {
        Some((_, r)) => Arc::clone(r),
        None => match prepare(path, region, bed_mm).await {
            Ok(r) => {
                let r = Arc::new(r);
                *cached = Some((modified, Arc::clone(&r)));
                r
            }
            Err(e) => return no(CameraProblem::Unreadable { error: e }),
        },
    };
    // A frame taken after the moment the check is for.
    let fresh = |f: &super::feed::CameraFeed| {
        f.frame
            .as_ref()
            .is_some_and(|fr| fr.at >= after_s + SETTLE_S)
    };
    let waited = tokio::time::timeout(frame_wait(cameras), async {
        loop {
            if fresh(&feed.borrow_and_update()) {
                return true;
            }
            if feed.changed().await.is_err() {
                return false;
            }
        }
    })
    .await;
    if !matches!(waited, Ok(true)) {
        let error = cameras.status(printer, false).and_then(|s| s.error);
        return no(CameraProblem::Offline { error });
    }
    if let Some(status) = cameras.status(printer, true) {
        if status.state == super::feed::CameraState::Frozen {
            let seconds = feed.borrow().same_since.elapsed().as_secs();
            return no(CameraProblem::Frozen { seconds });
        }
    }
    let (cams, name) = (Arc::clone(cameras), printer.to_string());
    let picture = match tokio::task::spawn_blocking(move || cams.fresh_picture(&name)).await {
        Ok(Some(Ok(p))) => p,
        Ok(Some(Err(NoFrame::Picture))) => {
            return no(CameraProblem::Unreadable {
                error: "the camera's frame could not be made into the printer's picture".into(),
            })
        }
        _ => return no(CameraProblem::Offline { error: None }),
    };
    let job = farm.store().gate(printer).last_job;
    let count = job
        .as_deref()
        .and_then(|j| farm.store().get(j).map(|j| j.clearing.len()))
        .unwrap_or(0);
    let spool = config.spool_dir.clone();
    let camera_root = cameras.root().to_path_buf();
    let printer_name = printer.to_string();
    let at_s = picture.at;
    let compared = tokio::task::spawn_blocking(move || {
        let verdict = reference.check(&picture.jpeg).map_err(|e| e.to_string())?;
        // The marked picture: with the job whose print was on the bed, else the
        // printer's own latest.
        let (file, relative) = match &job {
            Some(job) => {
                let name = format!("bed-check-{}.jpg", count + 1);
                (camera_root.join(job).join(&name), format!("camera/{job}/{name}"))
            }
            None => (
                spool.join("bed").join(&printer_name).join("check.jpg"),
                format!("bed/{printer_name}/check.jpg"),
            ),
        };
        let kept = crate::bedcheck::marked_jpeg(&picture.jpeg, &verdict)
            .map_err(|e| e.to_string())
            .and_then(|jpeg| {
                std::fs::create_dir_all(file.parent().unwrap_or(&spool))
                    .map_err(|e| e.to_string())?;
                crate::fsutil::write_atomic(&file, &jpeg).map_err(|e| e.to_string())
            });
        let picture = match kept {
            Ok(()) => Some(relative),
            Err(e) => {
                tracing::warn!(printer = %printer_name, error = %e, "cannot keep the check's marked picture");
                None
            }
        };
        Ok::<_, String>(CheckRecord {
            at_s,
            verdict,
            picture,
        })
    })
    .await;
    let record = match compared {
        Ok(Ok(r)) => r,
        Ok(Err(e)) => return no(CameraProblem::Unreadable { error: e }),
        Err(e) => {
            return no(CameraProblem::Unreadable {
                error: e.to_string(),
            })
        }
    };
    tracing::info!(printer, summary = %record.verdict.summary(), "bed check");
    let to = if record.verdict.clear {
        Bed::Clear {
            by: ClearedBy::Camera,
            at_s: now_s(),
        }
    } else {
        Bed::Waiting {
            why: Some(Why::NotClear {
                check: Box::new(record.clone()),
            }),
        }
    };
    (to, Some(record))
}

/// Reads and prepares the reference at `path` (off the runtime).
async fn prepare(
    path: PathBuf,
    region: Option<Region>,
    bed_mm: [f64; 2],
) -> Result<Reference, String> {
    tokio::task::spawn_blocking(move || {
        let jpeg = std::fs::read(&path).map_err(|e| format!("{}: {e}", path.display()))?;
        Reference::prepare(&jpeg, region, Some(bed_mm))
            .map_err(|e| format!("the reference picture: {e}"))
    })
    .await
    .map_err(|e| e.to_string())?
}
