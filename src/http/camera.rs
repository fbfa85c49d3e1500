//! The cameras through crispen itself (the browser never needs the camera's own address,
//! usually on another network): each printer's latest picture and a live view of it, the
//! cameras' states, and the snapshots and timelapse kept with each job. Behind the same
//! read rules as the rest of the API.

use super::auth::Keyed;
use super::error::quoted;
use super::serve::ClientAddr;
use super::{ApiError, AppState};
use crate::camera::hub::{CameraStatus, Picture};
use crate::camera::recorder::{JobCamera, MANIFEST};
use axum::body::Body;
use axum::extract::{Path, Query, State};
use axum::http::{header, StatusCode};
use axum::response::{IntoResponse, Response};
use axum::{Extension, Json};
use std::time::Duration;

/// Whether a print is under way on a printer (a camera showing one picture then is frozen).
pub(super) fn prints(farm: &crate::daemon::farm::Farm, printer: &str) -> bool {
    farm.printer(printer)
        .is_some_and(|h| h.live.borrow().state.has_print_under_way())
}

/// `GET /api/v1/cameras`: each printer's camera and how it is doing.
pub(crate) async fn cameras(State(state): State<AppState>) -> Json<Vec<CameraStatus>> {
    let list = state
        .cameras
        .printers()
        .filter_map(|p| state.cameras.status(p, prints(&state.farm, p)))
        .collect();
    Json(list)
}

async fn latest(state: &AppState, printer: &str) -> Result<Picture, ApiError> {
    if !state.cameras.has(printer) {
        return Err(ApiError::not_found(format!(
            "printer {} has no camera (hint: a [printer.camera] table with `snapshot` or `stream`)",
            quoted(printer)
        )));
    }
    let (cameras, name) = (state.cameras.clone(), printer.to_string());
    let made = tokio::task::spawn_blocking(move || cameras.picture(&name))
        .await
        .map_err(ApiError::from)?;
    match made {
        Some(Ok(p)) => Ok(p),
        Some(Err(e)) => Err(ApiError::new(
            StatusCode::SERVICE_UNAVAILABLE,
            format!("printer {}: {e}", quoted(printer)),
        )),
        None => {
            let why = state
                .cameras
                .status(printer, false)
                .and_then(|s| s.error)
                .unwrap_or_else(|| "no frame yet".into());
            Err(ApiError::new(
                StatusCode::SERVICE_UNAVAILABLE,
                format!("printer {}'s camera has no picture: {why}", quoted(printer)),
            ))
        }
    }
}

/// `GET /api/v1/printers/{name}/snapshot`: the printer's latest picture, as a JPEG.
pub(crate) async fn snapshot(
    State(state): State<AppState>,
    Path(name): Path<String>,
) -> Result<Response, ApiError> {
    let p = latest(&state, &name).await?;
    Ok((
        [
            (header::CONTENT_TYPE, "image/jpeg".to_string()),
            (header::CACHE_CONTROL, "no-store".to_string()),
            (
                header::HeaderName::from_static("x-frame-time"),
                format!("{:.3}", p.at),
            ),
        ],
        Body::from(p.jpeg),
    )
        .into_response())
}

/// The boundary of the live view's parts.
const BOUNDARY: &str = "crispenframe";

/// `GET /api/v1/printers/{name}/stream`: the printer's pictures as an MJPEG stream, a new
/// part for each new frame (capped like the event streams, since it holds a connection);
/// with `?action=snapshot`, one picture.
pub(crate) async fn stream(
    State(state): State<AppState>,
    Path(name): Path<String>,
    Query(query): Query<std::collections::HashMap<String, String>>,
    client: Option<Extension<ClientAddr>>,
    keyed: Option<Extension<Keyed>>,
) -> Result<Response, ApiError> {
    // A still, as mjpg-streamer answers `?action=snapshot` (Home Assistant asks so).
    if query.get("action").is_some_and(|a| a == "snapshot") {
        return snapshot(State(state), Path(name)).await;
    }
    let client = client.and_then(|Extension(ClientAddr(a))| a);
    let keyed = keyed.is_some_and(|Extension(Keyed(k))| k);
    let Some(feed) = state.cameras.watch(&name) else {
        return Err(latest(&state, &name).await.err().unwrap_or_else(|| {
            ApiError::not_found(format!("printer {} has no camera", quoted(&name)))
        }));
    };
    let place = state.streams.open(client, keyed)?;
    let frames = futures_util::stream::unfold(
        (state, name, feed, 0u64, place),
        |(state, name, mut feed, last, place)| async move {
            loop {
                if feed
                    .borrow_and_update()
                    .frame
                    .as_ref()
                    .is_some_and(|f| f.seq != last)
                {
                    if let Ok(p) = latest(&state, &name).await {
                        let mut part = format!(
                            "--{BOUNDARY}\r\nContent-Type: image/jpeg\r\nContent-Length: {}\r\n\r\n",
                            p.jpeg.len()
                        )
                        .into_bytes();
                        part.extend_from_slice(&p.jpeg);
                        part.extend_from_slice(b"\r\n");
                        let seq = p.seq;
                        return Some((
                            Ok::<_, std::convert::Infallible>(part),
                            (state, name, feed, seq, place),
                        ));
                    }
                }
                tokio::select! {
                    r = feed.changed() => if r.is_err() { return None },
                    _ = state.farm.shutdown.cancelled() => return None,
                    // A camera that stopped: the stream stays, quiet.
                    _ = tokio::time::sleep(Duration::from_secs(30)) => {}
                }
            }
        },
    );
    Ok((
        [
            (
                header::CONTENT_TYPE,
                format!("multipart/x-mixed-replace; boundary={BOUNDARY}"),
            ),
            (header::CACHE_CONTROL, "no-store".to_string()),
        ],
        Body::from_stream(frames),
    )
        .into_response())
}

/// A job's camera manifest, if its folder has one (blocking).
pub(crate) fn manifest(root: &std::path::Path, job: &str) -> Option<JobCamera> {
    if job.is_empty() || job.contains(['/', '\\']) || job.starts_with('.') {
        return None;
    }
    let text = std::fs::read(root.join(job).join(MANIFEST)).ok()?;
    serde_json::from_slice(&text).ok()
}

/// `GET /api/v1/jobs/{id}/camera/{file}`: one of the files a job's camera manifest lists
/// (no request can name another).
pub(crate) async fn job_file(
    State(state): State<AppState>,
    Path((id, file)): Path<(String, String)>,
) -> Result<Response, ApiError> {
    let root = state.cameras.root().to_path_buf();
    let wanted = (id.clone(), file.clone());
    let checks: Vec<String> = state
        .farm
        .store()
        .get(&id)
        .map(|j| check_pictures(&j.clearing))
        .unwrap_or_default();
    let found = tokio::task::spawn_blocking(move || {
        let (id, file) = wanted;
        // A bed check's marked picture is listed in the job's record, not its manifest.
        let checked = checks.iter().any(|c| *c == format!("camera/{id}/{file}"));
        let listed = checked
            || manifest(&root, &id).is_some_and(|m| {
                m.snapshots.iter().any(|s| s.file == file)
                    || m.timelapse.as_ref().is_some_and(|t| t.file == file)
            });
        if !listed {
            return None;
        }
        let path = root.join(&id).join(&file);
        let meta = std::fs::symlink_metadata(&path).ok()?;
        if !meta.is_file() || meta.len() > 1 << 30 {
            return None;
        }
        std::fs::read(&path).ok()
    })
    .await
    .map_err(ApiError::from)?;
    let bytes = found.ok_or_else(|| {
        ApiError::not_found(format!(
            "job {} has no camera file {} (GET /api/v1/jobs/{{id}} lists its snapshots and timelapse)",
            quoted(&id),
            quoted(&file)
        ))
    })?;
    let kind = if file.ends_with(".mp4") {
        "video/mp4"
    } else {
        "image/jpeg"
    };
    Ok((
        [
            (header::CONTENT_TYPE, kind),
            (header::CACHE_CONTROL, "no-cache"),
        ],
        Body::from(bytes),
    )
        .into_response())
}

/// The marked pictures of a job's bed checks, relative to the spool.
fn check_pictures(steps: &[crate::daemon::bed::Clearing]) -> Vec<String> {
    steps
        .iter()
        .filter_map(|s| match s {
            crate::daemon::bed::Clearing::Check { check, .. } => check.picture.clone(),
            crate::daemon::bed::Clearing::Eject { .. } => None,
        })
        .collect()
}

/// `GET /api/v1/printers/{name}/bed/{file}`: the picture of the printer's empty bed
/// (`reference.jpg`), or the marked picture of its camera's last check (as its bed names
/// it); no request can name another file.
pub(crate) async fn bed_file(
    State(state): State<AppState>,
    Path((name, file)): Path<(String, String)>,
) -> Result<Response, ApiError> {
    let spool = state.farm.config().spool_dir.clone();
    let gate = state.farm.store().gate(&name);
    let named = |picture: &Option<String>| {
        picture.clone().filter(|p| {
            std::path::Path::new(p)
                .file_name()
                .is_some_and(|n| n.to_string_lossy() == file)
        })
    };
    let relative = if file == "reference.jpg" {
        Some(format!("bed/{name}/reference.jpg"))
    } else {
        let waiting = match &gate.bed {
            crate::daemon::bed::Bed::Waiting {
                why: Some(crate::daemon::bed::Why::NotClear { check }),
            } => named(&check.picture),
            _ => None,
        };
        waiting.or_else(|| gate.last_check.as_ref().and_then(|c| named(&c.picture)))
    };
    let known = control_names(&state.farm).contains(&name);
    let found = match relative.filter(|_| known) {
        None => None,
        Some(relative) => tokio::task::spawn_blocking(move || {
            let path = spool.join(relative);
            let meta = std::fs::symlink_metadata(&path).ok()?;
            if !meta.is_file() || meta.len() > 64 << 20 {
                return None;
            }
            std::fs::read(&path).ok()
        })
        .await
        .map_err(ApiError::from)?,
    };
    let bytes = found.ok_or_else(|| {
        ApiError::not_found(format!(
            "printer {} has no bed picture {} (its reference is reference.jpg; its last check's picture is named in GET /api/v1/printers/{{name}})",
            quoted(&name),
            quoted(&file)
        ))
    })?;
    Ok((
        [
            (header::CONTENT_TYPE, "image/jpeg"),
            (header::CACHE_CONTROL, "no-cache"),
        ],
        Body::from(bytes),
    )
        .into_response())
}

fn control_names(farm: &crate::daemon::farm::Farm) -> Vec<String> {
    crate::daemon::control::printer_names(farm)
}
