//! `POST api/files/local`: a slicer's upload into the instance's hot folder (a model
//! through the normal pipeline, G-code as pre-sliced), and `POST api/files/local/<path>`
//! with `{"command": "select", "print": true}`, which releases the job a held upload
//! became.
//!
//! The whole form is read before anything is decided, as OctoPrint does: the file is
//! received into a hidden temporary file in the folder it will most likely go to (the
//! `path` given before it, else the instance's folder, else the first folder), and moved
//! if a `path` after it names another folder. Then:
//! - `print` true ("Upload and print"): the file prints once ready, as every file in a hot
//!   folder does (`true`, `yes`, `y`, `1` are true, as in OctoPrint).
//! - else ("Upload"; `select` alone too): the job is held: prepared as usual, then kept
//!   from the printers until released (the select-and-print command here, `crispen
//!   release JOB`, `POST /api/v1/jobs/{id}/release`, the dashboard's Print button). The
//!   hold travels as the model's sidecar `<file>.toml` with `hold = true`, received whole
//!   and linked into the hot folder right before the model itself, so the pick-up finds
//!   it with the model. A sidecar of that name already there is not replaced: the upload
//!   is refused.
//! - `path`: on a folder's instance empty or that folder's name; on the root a folder's
//!   name, or empty for the default folder (`[http] default_folder`, else the only one);
//!   anything else is refused with the folders' names.
//!
//! The select command is never lost: a held upload is remembered with a token of its
//! own (`crate::http::pending`), and its select-and-print releases that upload's job whenever
//! it comes, before the hot folder has even taken the file.
//!
//! The answer is OctoPrint's: `201`, the file's address in `Location` (under the
//! instance's base, which is where Cura sends its select-and-print command), and the body
//! with `files.local`, `done`, `effectiveSelect`, `effectivePrint`.

use super::form::{FormReader, Step};
use super::{upload, Instance};
use crate::daemon::config::{Config, FolderConfig};
use crate::daemon::control::{self, Command};
use crate::daemon::job::JobState;
use crate::http::appkeys::{Grant, Who};
use crate::http::{ApiError, AppState, UPLOAD_IDLE_TIMEOUT};
use axum::extract::State;
use axum::http::header::{CONTENT_TYPE, LOCATION};
use axum::http::{HeaderMap, StatusCode};
use axum::response::{IntoResponse, Response};
use axum::Json;
use futures_util::StreamExt;
use std::time::Duration;

/// Waits for the next piece of the body (at most [`UPLOAD_IDLE_TIMEOUT`]) and pushes it.
async fn pull(
    reader: &mut FormReader,
    body: &mut axum::body::BodyDataStream,
) -> Result<(), String> {
    match tokio::time::timeout(UPLOAD_IDLE_TIMEOUT, body.next()).await {
        Err(_) => Err(format!(
            "the upload stalled for {} s",
            UPLOAD_IDLE_TIMEOUT.as_secs()
        )),
        Ok(Some(Ok(piece))) => {
            reader.push(&piece);
            Ok(())
        }
        Ok(Some(Err(e))) => Err(format!("the upload broke off: {e}")),
        Ok(None) => {
            reader.finish();
            Ok(())
        }
    }
}

/// The hot folder an upload's `path` names on `instance`.
fn folder_for<'a>(
    config: &'a Config,
    instance: &Instance,
    path: Option<&str>,
) -> Result<&'a FolderConfig, ApiError> {
    let name = path.unwrap_or("").trim().trim_matches('/');
    match (&instance.folder, name) {
        (Some(_), "") | (None, "") => instance.some_folder(config),
        (Some(own), name) if name == own => instance.some_folder(config),
        (Some(own), name) => Err(ApiError::bad_request(format!(
            "path {}: this is hot folder {}'s instance, which has no subfolders; upload without a path (or to another folder's own instance)",
            super::super::error::quoted(name),
            super::super::error::quoted(own)
        ))),
        (None, name) => upload::find_folder(config, name),
    }
}

pub(crate) async fn upload(
    State(state): State<AppState>,
    instance: Instance,
    who: Option<axum::Extension<Who>>,
    headers: HeaderMap,
    body: axum::body::Body,
) -> Result<Response, ApiError> {
    let grant = match who.map(|w| w.0) {
        Some(Who::App(grant)) => Some(grant),
        _ => None,
    };
    let content_type = headers
        .get(CONTENT_TYPE)
        .and_then(|v| v.to_str().ok())
        .unwrap_or("");
    let mut reader = FormReader::new(content_type)?;
    let mut body = body.into_data_stream();
    let (file_name, kind) = loop {
        match reader.step()? {
            Step::More => pull(&mut reader, &mut body)
                .await
                .map_err(ApiError::bad_request)?,
            Step::File { name, kind } => break (name, kind),
            Step::Data(_) | Step::FileEnd | Step::End => {
                unreachable!("no file data or end before the file")
            }
        }
    };
    let config = state.farm.config();
    // Where the file is received: the folder the fields so far name (a wrong `path`
    // before the file is final: refused before the file is read), else the instance's,
    // else any: a `path` may still come after the file.
    let early = reader.form().clone();
    let staging = match early.path {
        Some(_) => {
            let folder = folder_for(&config, &instance, early.path.as_deref())?;
            if let Some(grant) = &grant {
                grant.check_folder(&config, &instance, folder)?;
            }
            folder
        }
        None => match instance.folder(&config)? {
            Some(folder) => folder,
            None => config.folders.first().ok_or_else(|| {
                ApiError::new(StatusCode::CONFLICT, "this farm has no hot folder")
            })?,
        },
    };
    let data = futures_util::stream::unfold(
        (&mut reader, &mut body, false),
        |(reader, body, failed)| async move {
            if failed {
                return None;
            }
            loop {
                match reader.step() {
                    Ok(Step::Data(data)) => return Some((Ok(data), (reader, body, false))),
                    Ok(Step::FileEnd) => return None,
                    Ok(Step::More) => {
                        if let Err(e) = pull(reader, body).await {
                            return Some((Err(e), (reader, body, true)));
                        }
                    }
                    Ok(Step::File { .. } | Step::End) => unreachable!("one file, then its end"),
                    Err(e) => return Some((Err(e.message), (reader, body, true))),
                }
            }
        },
    );
    let received = upload::receive(&staging.path, &file_name, data, state.upload_max_bytes).await?;
    // The rest of the form: fields after the file.
    loop {
        match reader.step()? {
            Step::More => pull(&mut reader, &mut body)
                .await
                .map_err(ApiError::bad_request)?,
            Step::End => break,
            Step::File { .. } | Step::Data(_) | Step::FileEnd => {
                unreachable!("the form reader refuses a second file")
            }
        }
    }
    let form = reader.form().clone();
    let folder = folder_for(&config, &instance, form.path.as_deref())?;
    if let Some(grant) = &grant {
        grant.check_folder(&config, &instance, folder)?;
    }
    let received = match folder.path == staging.path {
        true => received,
        false => received.relocate(&folder.path).await?,
    };
    let size = received.size;
    // A sidecar is no job of its own: nothing to hold. `select` alone (OctoPrint: load
    // the file, do not start it) holds, as no `print` does.
    let hold = !form.print && kind != upload::Upload::Sidecar;
    // An application key's hold carries its mark: that key (and the operator) may
    // release the job; the operator's hold has none.
    let mark = match (&grant, hold) {
        (Some(grant), true) => Some(state.appkeys.hold_mark(grant, &folder.path).ok_or_else(
            || ApiError::new(StatusCode::FORBIDDEN, "the application key was revoked"),
        )?),
        _ => None,
    };
    // The upload's own token (see `crate::http::pending`): its select-and-print finds this
    // upload's job by it, whenever the command comes.
    let token = hold.then(crate::http::pending::token);
    let sidecar = match &token {
        Some(token) => Some(receive_hold(&folder.path, &file_name, token, mark.as_deref()).await?),
        None => None,
    };
    let stored = upload::place_with_sidecar(received, sidecar).await?;
    if let Some(token) = &token {
        state.pending.remember(
            &folder.path,
            &file_name,
            token,
            grant.as_ref().map(|g| g.id.as_str()),
        );
    }
    let folder_name = upload::folder_name(folder);
    tracing::info!(
        file = %stored.display(), size, print = form.print, folder = %folder_name,
        instance = %instance.base, "octoprint upload into a hot folder"
    );
    let shown = crate::daemon::hotfolder::printable(&file_name);
    let message = if !hold {
        format!("{shown} is in hot folder {folder_name}; it prints once ready")
    } else {
        format!(
            "{shown} is in hot folder {folder_name}; it is prepared and then held \
             until released (select and print it, `crispen release JOB` or the dashboard's Print button)"
        )
    };
    // The file's path within the instance's storage: the root's storage is all folders.
    let path = match instance.folder {
        Some(_) => file_name.clone(),
        None => format!("{folder_name}/{file_name}"),
    };
    let encoded = path
        .split('/')
        .map(crate::percent::percent_encode)
        .collect::<Vec<_>>()
        .join("/");
    let location = format!(
        "{}{}api/files/local/{encoded}",
        crate::http::appkeys_api::origin(&headers),
        instance.base
    );
    let body = serde_json::json!({
        "done": true,
        "effectivePrint": !hold,
        "effectiveSelect": form.select || form.print,
        "message": message,
        "files": { "local": {
            "name": file_name,
            "display": file_name,
            "path": path,
            "origin": "local",
            "refs": { "resource": location, "download": location },
        }},
    });
    Ok((StatusCode::CREATED, [(LOCATION, location)], Json(body)).into_response())
}

/// The sidecar that holds `file_name`, received into `folder` under a temporary name;
/// with the upload's token and the hold mark of the application key that uploaded it, if
/// one did.
async fn receive_hold(
    folder: &std::path::Path,
    file_name: &str,
    token: &str,
    mark: Option<&str>,
) -> Result<upload::Received, ApiError> {
    let content = format!(
        "{HOLD_SIDECAR}{}{}",
        crate::http::pending::sidecar_line(token),
        mark.unwrap_or("")
    );
    let size = content.len() as u64;
    let text = futures_util::stream::iter([Ok::<_, std::convert::Infallible>(
        axum::body::Bytes::from(content),
    )]);
    let sidecar = format!("{file_name}.toml");
    upload::receive(folder, &sidecar, text, size).await
}

/// The sidecar of an upload without `print`.
const HOLD_SIDECAR: &str =
    "# an upload without \"print\": prepared, then held until released\nhold = true\n";

/// How long the select command waits for its upload to become a job (the hot folder
/// takes a file once it has settled); within the request's own time limit.
const PICKUP_WAIT: Duration = Duration::from_secs(20);

#[derive(Debug, serde::Deserialize)]
struct FileCommand {
    command: String,
    #[serde(default)]
    print: serde_json::Value,
}

/// `POST api/files/local/<path>`: `select` (the held job stays held) or `select` with
/// `print` (the held job is released and prints, once). Other commands (slice, copy,
/// move) are refused. `204` as OctoPrint answers.
pub(crate) async fn command(
    State(state): State<AppState>,
    instance: Instance,
    who: Option<axum::Extension<Who>>,
    body: axum::body::Bytes,
) -> Result<StatusCode, ApiError> {
    let grant = match who.map(|w| w.0) {
        Some(Who::App(grant)) => Some(grant),
        _ => None,
    };
    let command: FileCommand = serde_json::from_slice(&body).map_err(|e| {
        ApiError::bad_request(format!(
            "a file command is JSON like {{\"command\": \"select\", \"print\": true}}: {e}"
        ))
    })?;
    if command.command != "select" {
        return Err(ApiError::bad_request(format!(
            "file command {}: only \"select\" (with \"print\": true to print) is supported; crispen slices itself",
            super::super::error::quoted(&command.command)
        )));
    }
    let print = match &command.print {
        serde_json::Value::Bool(b) => *b,
        serde_json::Value::String(s) => super::truthy(s),
        serde_json::Value::Null => false,
        other => {
            return Err(ApiError::bad_request(format!(
                "\"print\" must be true or false, got {other}"
            )))
        }
    };
    let path = instance
        .rest
        .strip_prefix("api/files/local/")
        .unwrap_or("")
        .to_string();
    let path = crate::percent::percent_decode(&path);
    let (folder_part, file) = match path.rsplit_once('/') {
        Some((folder, file)) => (Some(folder), file),
        None => (None, path.as_str()),
    };
    let config = state.farm.config();
    let folder = folder_for(&config, &instance, folder_part)?;
    if let Some(grant) = &grant {
        grant.check_folder(&config, &instance, folder)?;
    }
    // The job is found by its name in either spelling (jobs made before names were
    // normalised keep theirs).
    let (file, _) = upload::upload_name(file)?;
    let folder_path = folder.path.clone();
    let shown = crate::daemon::hotfolder::printable(&file);
    let folder_name = upload::folder_name(folder);
    drop(config);
    // An upload of this name remembered (see `crate::http::pending`): the command is its own,
    // taken now whatever the upload's job is (not there yet, preparing, ready).
    if let Some((token, key)) = state.pending.newest(&folder_path, &file) {
        let may = match (&grant, &key) {
            (None, _) => true,
            (Some(grant), Some(key)) => &grant.id == key,
            (Some(_), None) => false,
        };
        if !print {
            // Selected, not printed: it stays held (harmless for any key).
            return Ok(StatusCode::NO_CONTENT);
        }
        if !may {
            if let Some(grant) = &grant {
                return Err(grant.refuse_release("(not a job yet)", &shown));
            }
        }
        let outcome = state
            .pending
            .print(&state.farm, &token)
            .await
            .map_err(|e| ApiError::conflict(e.to_string()))?;
        tracing::info!(file = %shown, folder = %folder_name, ?outcome, "octoprint: select and print");
        return Ok(StatusCode::NO_CONTENT);
    }
    let deadline = tokio::time::Instant::now() + PICKUP_WAIT;
    loop {
        let jobs: Vec<control::JobStatus> = control::status(&state.farm)
            .jobs
            .into_iter()
            .filter(|j| {
                j.folder == folder_path && crate::daemon::hotfolder::same_name(&j.file, &file)
            })
            .collect();
        let live = |j: &&control::JobStatus| {
            matches!(
                j.state,
                JobState::Queued | JobState::Preparing | JobState::Ready | JobState::Printing
            )
        };
        let held: Vec<&control::JobStatus> = jobs.iter().filter(live).filter(|j| j.held).collect();
        // An application key prints only a job its own upload held; the operator's key
        // any held job.
        let held = match (&grant, print) {
            (Some(grant), true) if !held.is_empty() => {
                let own = own_holds(&state, grant, &held).await;
                match newest(held.iter().copied().filter(|j| own.contains(&j.id))) {
                    Some(job) => Some(job),
                    None => {
                        let job = newest(held.iter().copied()).map_or("", |j| j.id.as_str());
                        return Err(grant.refuse_release(job, &shown));
                    }
                }
            }
            _ => newest(held),
        };
        // A job not prepared yet shows no hold: its sidecar is read by the preparation.
        // Its release is taken now and kept (`control::execute`'s release reads the
        // sidecar in the job's directory); one that holds nothing is left alone.
        if held.is_none() && print {
            let unprepared: Vec<&control::JobStatus> = jobs
                .iter()
                .filter(|j| matches!(j.state, JobState::Queued | JobState::Preparing))
                .collect();
            let mine = match &grant {
                Some(grant) if !unprepared.is_empty() => {
                    let own = own_holds(&state, grant, &unprepared).await;
                    unprepared
                        .into_iter()
                        .filter(|j| own.contains(&j.id))
                        .collect()
                }
                _ => unprepared,
            };
            if let Some(job) = newest(mine) {
                match control::execute(
                    &state.farm,
                    Command::Release {
                        job: job.id.clone(),
                    },
                )
                .await
                {
                    Ok(message) => {
                        tracing::info!(job = %job.id, %message, "octoprint: select and print released a job not prepared yet");
                        return Ok(StatusCode::NO_CONTENT);
                    }
                    Err(control::CommandError::NotHeld(_)) => {}
                    Err(e) => return Err(ApiError::conflict(e.to_string())),
                }
            }
        }
        match held {
            Some(job) if print => {
                let message = control::execute(
                    &state.farm,
                    Command::Release {
                        job: job.id.clone(),
                    },
                )
                .await
                .map_err(|e| ApiError::conflict(e.to_string()))?;
                tracing::info!(job = %job.id, %message, "octoprint: select and print released a held job");
                return Ok(StatusCode::NO_CONTENT);
            }
            // Selected, not printed: it stays held.
            Some(_) => return Ok(StatusCode::NO_CONTENT),
            None if jobs.iter().any(|j| live(&j)) => {
                // Not held: it prints (or printed) once anyway; select changes nothing.
                return Ok(StatusCode::NO_CONTENT);
            }
            None => {}
        }
        if tokio::time::Instant::now() >= deadline {
            let finished = !jobs.is_empty();
            return Err(match finished {
                true => ApiError::conflict(format!(
                    "{shown} in hot folder {folder_name} has finished; upload it again to print it again"
                )),
                false => ApiError::not_found(format!(
                    "no job from {shown} in hot folder {folder_name} (it did not become a job within {} s)",
                    PICKUP_WAIT.as_secs()
                )),
            });
        }
        tokio::time::sleep(Duration::from_millis(200)).await;
    }
}

/// The most recently changed of `jobs`: the upload a command meant, where one name has
/// several.
pub(super) fn newest<'a>(
    jobs: impl IntoIterator<Item = &'a control::JobStatus>,
) -> Option<&'a control::JobStatus> {
    jobs.into_iter()
        .max_by(|a, b| a.updated.total_cmp(&b.updated))
}

/// Which of the `held` jobs the upload of `grant` held: their sidecars (in their job
/// directories, read on a blocking thread, each at most a sidecar's size) carry the
/// key's hold mark for their folder and file. One that cannot be read is not its own.
pub(super) async fn own_holds(
    state: &AppState,
    grant: &Grant,
    held: &[&control::JobStatus],
) -> Vec<String> {
    let store = state.farm.store();
    let files: Vec<(String, std::path::PathBuf, std::path::PathBuf)> = held
        .iter()
        .map(|j| {
            (
                j.id.clone(),
                store.job_dir(&j.id).join(format!("{}.toml", j.file)),
                j.folder.clone(),
            )
        })
        .collect();
    drop(store);
    let keys = state.appkeys.clone();
    let grant = grant.clone();
    tokio::task::spawn_blocking(move || {
        use std::io::Read;
        files
            .into_iter()
            .filter(|(_, sidecar, folder)| {
                let mut text = String::new();
                std::fs::File::open(sidecar)
                    .and_then(|f| {
                        f.take(crate::daemon::job::MAX_SIDECAR_BYTES)
                            .read_to_string(&mut text)
                    })
                    .is_ok()
                    && keys.held_by(&grant, &text, folder)
            })
            .map(|(id, ..)| id)
            .collect()
    })
    .await
    .unwrap_or_default()
}
