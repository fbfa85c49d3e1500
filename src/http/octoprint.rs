//! The part of OctoPrint's REST API that slicers' "Send to printer" uses (PrusaSlicer,
//! OrcaSlicer, Cura's OctoPrint connection): `GET /api/version` to test the connection and
//! `POST /api/files/local` to upload. The upload is multipart with the fields `path` (here:
//! the hot folder's name), `print`, `select` and `file`; the file goes into the hot folder:
//! a model through the normal pipeline, G-code (what a slicer sends after slicing itself)
//! as pre-sliced. Slicers send the key in `X-Api-Key`, as here.
//!
//! `print`: with `print=true` ("Upload and print") the file prints once ready, as every
//! file in a hot folder does. Without it ("Upload"; OctoPrint's default is false) the job
//! is held: prepared as usual, then kept from the printers until the operator releases it
//! (`crispen release JOB`, `POST /api/v1/jobs/{id}/release`, the dashboard's Print
//! button). The hold travels as the model's sidecar `<file>.toml` with `hold = true`,
//! received whole and linked into the hot folder right before the model itself, so the
//! pick-up finds it with the model. A sidecar of that name already there is not
//! replaced: the upload is refused.

use super::upload;
use super::{ApiError, AppState};
use axum::extract::multipart::{Multipart, MultipartRejection};
use axum::extract::State;
use axum::http::StatusCode;
use axum::Json;

/// The OctoPrint API version whose answers these are.
const API_VERSION: &str = "0.1";
/// The OctoPrint server version reported; clients only check that it is recent enough.
const SERVER_VERSION: &str = "1.10.0";

pub async fn version() -> Json<serde_json::Value> {
    Json(serde_json::json!({
        "api": API_VERSION,
        "server": SERVER_VERSION,
        "text": format!("OctoPrint (crispen {})", env!("CARGO_PKG_VERSION")),
    }))
}

pub async fn upload(
    State(state): State<AppState>,
    multipart: Result<Multipart, MultipartRejection>,
) -> Result<(StatusCode, Json<serde_json::Value>), ApiError> {
    let mut multipart = multipart.map_err(|e| {
        ApiError::bad_request(format!(
            "POST /api/files/local needs a multipart/form-data body with a `file` field: {e}"
        ))
    })?;
    let config = state.farm.config();
    let mut path: Option<String> = None;
    let mut print = false;
    loop {
        let field = multipart.next_field().await.map_err(|e| {
            ApiError::new(
                e.status(),
                format!("the multipart body is broken: {}", e.body_text()),
            )
        })?;
        let Some(field) = field else { break };
        let name = field.name().unwrap_or("").to_string();
        match name.as_str() {
            "path" | "print" | "select" => {
                let value = field.text().await.map_err(|e| {
                    ApiError::bad_request(format!("field `{name}`: {}", e.body_text()))
                })?;
                if value.len() > 1024 {
                    return Err(ApiError::bad_request(format!("field `{name}` is too long")));
                }
                match name.as_str() {
                    "path" => path = Some(value),
                    "print" => print = value.trim().eq_ignore_ascii_case("true"),
                    _ => {}
                }
            }
            "file" => {
                let file_name = field.file_name().unwrap_or("").to_string();
                let folder = folder_for(&config, path.as_deref())?;
                // A sidecar is no job of its own: nothing to hold.
                let hold = !print && upload::check_name(&file_name)? != upload::Upload::Sidecar;
                let received =
                    upload::receive(&folder.path, &file_name, field, state.upload_max_bytes)
                        .await?;
                let size = received.size;
                let sidecar = match hold {
                    true => Some(receive_hold(&folder.path, &file_name).await?),
                    false => None,
                };
                let stored = upload::place_with_sidecar(received, sidecar).await?;
                tracing::info!(file = %stored.display(), size, print, "octoprint upload into a hot folder");
                let folder_name = upload::folder_name(folder);
                let message = if !hold {
                    format!("{file_name} is in hot folder {folder_name}; it prints once ready")
                } else {
                    format!(
                        "{file_name} is in hot folder {folder_name}; it is prepared and then held \
                         until released (`crispen release JOB` or the dashboard's Print button)"
                    )
                };
                return Ok((
                    StatusCode::CREATED,
                    Json(serde_json::json!({
                        "done": true,
                        "effectivePrint": !hold,
                        "message": message,
                        "effectiveSelect": false,
                        "files": { "local": {
                            "name": file_name,
                            "path": format!("{folder_name}/{file_name}"),
                            "origin": "local",
                        }},
                    })),
                ));
            }
            // OctoPrint ignores fields it does not know; so do we.
            _ => {}
        }
    }
    Err(ApiError::bad_request(
        "the multipart body has no `file` field (hint: the slicer sends the file as `file`)",
    ))
}

/// The sidecar that holds `file_name`, received into `folder` under a temporary name.
async fn receive_hold(
    folder: &std::path::Path,
    file_name: &str,
) -> Result<upload::Received, ApiError> {
    let text = futures_util::stream::iter([Ok::<_, std::convert::Infallible>(
        axum::body::Bytes::from_static(HOLD_SIDECAR.as_bytes()),
    )]);
    let sidecar = format!("{file_name}.toml");
    upload::receive(folder, &sidecar, text, HOLD_SIDECAR.len() as u64).await
}

/// The sidecar of an upload without `print`.
const HOLD_SIDECAR: &str =
    "# an upload without \"print\": prepared, then held until released\nhold = true\n";

/// The hot folder a slicer's `path` names; with no path, the only folder there is.
fn folder_for<'a>(
    config: &'a crate::daemon::config::Config,
    path: Option<&str>,
) -> Result<&'a crate::daemon::config::FolderConfig, ApiError> {
    let name = path.unwrap_or("").trim().trim_matches('/');
    if name.is_empty() {
        return match config.folders.as_slice() {
            [only] => Ok(only),
            _ => Err(ApiError::bad_request(format!(
                "which hot folder? give its name as the upload path (in the slicer's physical printer settings); the folders are: {}",
                config
                    .folders
                    .iter()
                    .map(upload::folder_name)
                    .collect::<Vec<_>>()
                    .join(", ")
            ))),
        };
    }
    upload::find_folder(config, name)
}
