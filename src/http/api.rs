//! The JSON API under `/api/v1/`. Reads come from the farm's status snapshot
//! (`daemon::control::status`) and the job store; actions are the farm's own commands
//! (`daemon::control::execute`), the same for the CLI (on the control socket), the
//! dashboard and any other client.

use super::error::quoted;
use super::upload;
use super::{ApiError, AppState};
use crate::daemon::control::{self, Command, JobStatus};
use crate::daemon::farm::{Farm, PrinterStatus};
use crate::daemon::job::{Job, JobState};
// The pictures served are those the store knows a job's directory may hold.
use crate::daemon::store::{history, stats, PICTURES};
use crate::enhance::Strength;
use axum::body::Body;
use axum::extract::{Path, State};
use axum::http::{header, StatusCode};
use axum::response::{IntoResponse, Response};
use axum::Json;
use serde::Serialize;

/// A job in the queue, with what it will be made as.
#[derive(Debug, Serialize)]
pub(crate) struct JobView {
    #[serde(flatten)]
    pub status: JobStatus,
    /// The hot folder's name (see `upload::folder_name`).
    pub folder_name: String,
    /// The printed height and enhancement strength from the folder and the job's sidecar
    /// (None when the folder has left the config or the sidecar is broken).
    pub height_mm: Option<f64>,
    pub strength: Option<Strength>,
    /// The printers that may print it.
    pub machines: Vec<String>,
    /// The pictures in the job's directory (see `crate::preview`).
    pub pictures: Vec<&'static str>,
    /// Where its wall comparison is (measured after it is ready), so that a page showing
    /// the job knows when to show it again.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub comparison: Option<crate::daemon::job::Comparison>,
}

#[derive(Debug, Serialize)]
pub(crate) struct FolderView {
    pub name: String,
    pub height_mm: f64,
    pub strength: Strength,
    pub printers: Vec<String>,
    /// Jobs from this folder that have not reached a printer yet.
    pub queued: usize,
}

#[derive(Debug, Serialize)]
pub(crate) struct StatusView {
    pub printers: Vec<PrinterStatus>,
    pub jobs: Vec<JobView>,
    pub folders: Vec<FolderView>,
    /// The hosts of a farm shared through `[store]`.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub farm: Option<control::FarmStatus>,
    /// See [`control::Status::version`].
    pub version: u64,
}

/// The whole farm: printers, jobs (newest last) and hot folders.
pub(crate) fn snapshot(farm: &Farm) -> StatusView {
    let status = control::status(farm);
    let config = farm.config();
    let store = farm.store();
    let printers = farm.printer_machines();
    let jobs = status
        .jobs
        .into_iter()
        .map(|j| job_view(&config, &store, &printers, j))
        .collect();
    drop(store);
    let folders = config
        .folders
        .iter()
        .map(|f| FolderView {
            name: upload::folder_name(f),
            height_mm: f.height_mm,
            strength: f.strength,
            printers: f.printers.clone(),
            queued: 0,
        })
        .collect::<Vec<_>>();
    let mut view = StatusView {
        printers: status.printers,
        jobs,
        folders,
        farm: status.farm,
        version: status.version,
    };
    for job in &view.jobs {
        let waiting = matches!(
            job.status.state,
            crate::daemon::job::JobState::Queued
                | crate::daemon::job::JobState::Preparing
                | crate::daemon::job::JobState::Ready
        );
        if let Some(f) = view.folders.iter_mut().find(|f| f.name == job.folder_name) {
            f.queued += usize::from(waiting);
        }
    }
    view
}

/// One job's entry: its status with what it will be made as. Which pictures it has comes
/// from the store's snapshot (looked at once when the job changed, not at every glance).
fn job_view(
    config: &crate::daemon::config::Config,
    store: &crate::daemon::store::Snapshot,
    printers: &[(String, crate::machine::Machine)],
    j: JobStatus,
) -> JobView {
    let dir = store.job_dir(&j.id);
    let folder = config.folder(&j.folder);
    let job = store.get(&j.id);
    let sidecar = job.and_then(|job| job.sidecar.as_ref());
    let task = folder.and_then(|f| {
        crate::daemon::prepare::resolve_task(&j.id, &dir, &j.file, f, printers, sidecar).ok()
    });
    JobView {
        folder_name: folder
            .map(upload::folder_name)
            .unwrap_or_else(|| j.folder.display().to_string()),
        height_mm: task.as_ref().map(|t| t.height_mm),
        strength: task.as_ref().map(|t| t.strength),
        machines: folder.map(|f| f.printers.clone()).unwrap_or_default(),
        pictures: store.pictures(&j.id),
        comparison: job.and_then(|job| job.comparison.clone()),
        status: j,
    }
}

async fn blocking<T: Send + 'static>(
    state: &AppState,
    work: impl FnOnce(&Farm) -> T + Send + 'static,
) -> Result<T, ApiError> {
    let farm = state.farm.clone();
    tokio::task::spawn_blocking(move || work(&farm))
        .await
        .map_err(ApiError::from)
}

pub(crate) async fn status(State(state): State<AppState>) -> Result<Json<StatusView>, ApiError> {
    blocking(&state, snapshot).await.map(Json)
}

pub(crate) async fn printers(State(state): State<AppState>) -> Json<Vec<PrinterStatus>> {
    Json(control::status(&state.farm).printers)
}

pub(crate) async fn printer(
    State(state): State<AppState>,
    Path(name): Path<String>,
) -> Result<Json<PrinterStatus>, ApiError> {
    control::status(&state.farm)
        .printers
        .into_iter()
        .find(|p| p.name == name)
        .map(Json)
        .ok_or_else(|| no_printer(&state.farm, &name))
}

pub(crate) async fn jobs(State(state): State<AppState>) -> Result<Json<Vec<JobView>>, ApiError> {
    blocking(&state, |farm| snapshot(farm).jobs).await.map(Json)
}

/// One job: its queue entry and everything stored about it (slice and print reports,
/// history, reason).
#[derive(Debug, Serialize)]
pub(crate) struct JobDetail {
    #[serde(flatten)]
    pub view: JobView,
    pub job: Job,
    /// Its printer's snapshots and timelapse, once it has printed with a camera.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub camera: Option<crate::camera::recorder::JobCamera>,
}

/// `GET /api/v1/jobs/{id}`: a live job's entry and record (without building every other
/// job's entry), or a job in the history: its history record and its whole record with
/// `"retired": true`.
pub(crate) async fn job(
    State(state): State<AppState>,
    Path(id): Path<String>,
) -> Result<Response, ApiError> {
    let wanted = id.clone();
    let camera_root = state.cameras.root().to_path_buf();
    let found = blocking(&state, move |farm| {
        let store = farm.store();
        let job = store.get(&wanted).cloned()?;
        let status = control::status(farm)
            .jobs
            .into_iter()
            .find(|j| j.id == wanted)?;
        let view = job_view(&farm.config(), &store, &farm.printer_machines(), status);
        let camera = super::camera::manifest(&camera_root, &wanted);
        Some(JobDetail { view, job, camera })
    })
    .await?;
    if let Some(detail) = found {
        return Ok(Json(detail).into_response());
    }
    match state.farm.jobs().retired(&id).await {
        Ok(Some(retired)) => {
            let mut answer = said(&retired.record);
            // A record from before the figures were kept: its job's report has them.
            let report = retired.job.as_ref().and_then(|j| j.slice_report.as_ref());
            if let (None, Some(report)) = (&retired.record.moved, report) {
                answer["moved"] = report.moved().to_string().into();
            }
            answer["retired"] = serde_json::Value::Bool(true);
            let root = state.cameras.root().to_path_buf();
            let wanted = id.clone();
            if let Ok(Some(camera)) =
                tokio::task::spawn_blocking(move || super::camera::manifest(&root, &wanted)).await
            {
                answer["camera"] = serde_json::to_value(camera).unwrap_or_default();
            }
            answer["job"] = serde_json::to_value(&retired.job).unwrap_or_default();
            Ok(Json(answer).into_response())
        }
        Ok(None) => Err(ApiError::not_found(
            "no such job (hint: GET /api/v1/jobs lists them, GET /api/v1/history the finished ones)",
        )),
        Err(e) => Err(store_unavailable(&state.farm, e)),
    }
}

/// A history record as the API shows it: what the enhancement moved in words, made here
/// from the record's figures.
fn said(record: &history::Retired) -> serde_json::Value {
    let mut answer = serde_json::to_value(record).unwrap_or_default();
    if let Some(moved) = &record.moved {
        answer["moved"] = moved.to_string().into();
    }
    answer
}

/// The job store could not answer a reading (its history unreadable, the farm database
/// down): 503, with the spool's files named relative to it (the log has the whole path).
fn store_unavailable(farm: &Farm, e: crate::daemon::job::StoreError) -> ApiError {
    tracing::error!(error = %e, "http: the job store could not answer");
    let spool = &farm.config().spool_dir;
    let message = crate::daemon::store::spool_relative(&e.to_string(), spool);
    ApiError::new(StatusCode::SERVICE_UNAVAILABLE, message)
}

/// `GET /api/v1/history?limit=N&before=SEQ` and the filters: `printer`, `folder` (name or
/// path), `state` (done, failed, cancelled), `since` and `until` (when it ended: seconds
/// since the epoch or a UTC date `YYYY-MM-DD`), and `format` (`json`, `csv`).
#[derive(Debug, serde::Deserialize)]
#[serde(deny_unknown_fields)]
pub(crate) struct HistoryQuery {
    pub limit: Option<usize>,
    pub before: Option<u64>,
    pub printer: Option<String>,
    pub folder: Option<String>,
    pub state: Option<String>,
    pub since: Option<String>,
    pub until: Option<String>,
    pub format: Option<String>,
}

/// A query string that cannot be read, as the API's JSON error.
pub(super) fn bad_query(e: axum::extract::rejection::QueryRejection) -> ApiError {
    ApiError::bad_request(format!(
        "{} (see README: History and statistics)",
        e.body_text()
    ))
}

fn time_param(key: &str, value: Option<&str>) -> Result<Option<f64>, ApiError> {
    value
        .map(|v| stats::parse_time(v).map_err(|e| ApiError::bad_request(format!("{key}: {e}"))))
        .transpose()
}

impl HistoryQuery {
    fn filter(&self) -> Result<history::Filter, ApiError> {
        let state = match self.state.as_deref() {
            None => None,
            Some(name) => Some(
                [JobState::Done, JobState::Failed, JobState::Cancelled]
                    .into_iter()
                    .find(|s| s.name() == name)
                    .ok_or_else(|| {
                        ApiError::bad_request(format!(
                            "state {}: the history holds done, failed and cancelled jobs",
                            quoted(name)
                        ))
                    })?,
            ),
        };
        Ok(history::Filter {
            printer: self.printer.clone(),
            folder: self.folder.clone(),
            state,
            since: time_param("since", self.since.as_deref())?,
            until: time_param("until", self.until.as_deref())?,
        })
    }
}

/// `GET /api/v1/history`: finished jobs that have left the queue, newest first, a page at
/// a time (`limit`, 1 to 1000, default 50; `before`: the `next` of the page before), or
/// with `format=csv` every job the filters take, as CSV.
pub(crate) async fn history(
    State(state): State<AppState>,
    query: Result<axum::extract::Query<HistoryQuery>, axum::extract::rejection::QueryRejection>,
) -> Result<Response, ApiError> {
    let query = query.map_err(bad_query)?.0;
    let filter = query.filter()?;
    let unavailable = |e| store_unavailable(&state.farm, e);
    let csv = match query.format.as_deref() {
        None | Some("json") => false,
        Some("csv") => true,
        Some(other) => {
            return Err(ApiError::bad_request(format!(
                "format {}: json or csv",
                quoted(other)
            )))
        }
    };
    let bounds = history::PAGE_LIMIT;
    let limit = query.limit.unwrap_or(if csv { *bounds.end() } else { 50 });
    if !bounds.contains(&limit) {
        return Err(ApiError::new(
            StatusCode::BAD_REQUEST,
            format!(
                "limit {limit}: must be between {} and {}",
                bounds.start(),
                bounds.end()
            ),
        ));
    }
    if !csv {
        let page = state
            .farm
            .jobs()
            .history_where(query.before, limit, filter)
            .await
            .map_err(unavailable)?;
        let jobs: Vec<serde_json::Value> = page.jobs.iter().map(said).collect();
        return Ok(Json(serde_json::json!({ "jobs": jobs, "next": page.next })).into_response());
    }
    // The export: page after page until the history (or CSV_MAX_ROWS) ends; `limit`
    // is the size of each read.
    let mut csv = history::Csv::new();
    let (mut before, mut rows) = (query.before, 0usize);
    loop {
        let page = state
            .farm
            .jobs()
            .history_where(before, limit, filter.clone())
            .await
            .map_err(unavailable)?;
        for r in &page.jobs {
            csv.push(r);
        }
        rows += page.jobs.len();
        match page.next {
            Some(next) if rows < CSV_MAX_ROWS => before = Some(next),
            _ => break,
        }
    }
    Ok((
        [
            (
                header::CONTENT_TYPE,
                "text/csv; charset=utf-8; header=present",
            ),
            (
                header::CONTENT_DISPOSITION,
                "attachment; filename=\"crispen-history.csv\"",
            ),
        ],
        csv.into_bytes(),
    )
        .into_response())
}

/// The most rows one CSV export holds (narrow it with `since`/`until` for more).
pub(crate) const CSV_MAX_ROWS: usize = 200_000;

/// `GET /api/v1/stats?days=N` (the last N UTC days, today included; default 7) or
/// `?from=T&to=T` (seconds since the epoch or `YYYY-MM-DD`, `to` excluded).
#[derive(Debug, serde::Deserialize)]
#[serde(deny_unknown_fields)]
pub(crate) struct StatsQuery {
    pub days: Option<u32>,
    pub from: Option<String>,
    pub to: Option<String>,
}

/// `GET /api/v1/stats`: the statistics of a period, per printer and per folder.
pub(crate) async fn stats(
    State(state): State<AppState>,
    query: Result<axum::extract::Query<StatsQuery>, axum::extract::rejection::QueryRejection>,
) -> Result<Json<stats::Stats>, ApiError> {
    let query = query.map_err(bad_query)?.0;
    let now = crate::daemon::job::now_s();
    let period = match (query.days, query.from.as_deref(), query.to.as_deref()) {
        (days, None, None) => {
            let days = days.unwrap_or(7);
            if !(1..=stats::MAX_DAYS as u32).contains(&days) {
                return Err(ApiError::bad_request(format!(
                    "days {days}: must be between 1 and {}",
                    stats::MAX_DAYS
                )));
            }
            stats::Period::last_days(days, now)
        }
        (None, Some(from), to) => {
            let from = time_param("from", Some(from))?.unwrap_or_default();
            let to = time_param("to", to)?.unwrap_or(now);
            stats::Period::new(from, to)
        }
        (None, None, Some(_)) => return Err(ApiError::bad_request("to without from")),
        (Some(_), _, _) => return Err(ApiError::bad_request("days, or from and to; not both")),
    }
    .map_err(ApiError::bad_request)?;
    state
        .farm
        .stats(period)
        .await
        .map(Json)
        .map_err(|e| store_unavailable(&state.farm, e))
}

/// One of a job's pictures. Only the fixed names of [`PICTURES`] are served, from the
/// directory of a job the store knows, so no request can name another file.
pub(crate) async fn picture(
    State(state): State<AppState>,
    Path((id, picture)): Path<(String, String)>,
) -> Result<Response, ApiError> {
    let Some(name) = PICTURES.into_iter().find(|p| *p == picture) else {
        return Err(ApiError::not_found(format!(
            "no picture {picture:?}; a job's pictures are {}",
            PICTURES.join(", ")
        )));
    };
    let dir = {
        let store = state.farm.store();
        store.get(&id).map(|_| store.job_dir(&id))
    };
    let dir = dir.ok_or_else(|| ApiError::not_found(format!("no job {}", quoted(&id))))?;
    let path = dir.join(name);
    // Not through a link: the job directory is the daemon's, but be sure.
    let meta = tokio::fs::symlink_metadata(&path).await;
    let bytes = match meta {
        Ok(m) if m.is_file() && m.len() <= 64 * 1024 * 1024 => tokio::fs::read(&path).await.ok(),
        _ => None,
    };
    let bytes = bytes.ok_or_else(|| {
        ApiError::not_found(format!(
            "job {} has no {} (pictures are drawn once a job is prepared; the preview of the print once no job is being prepared)",
            quoted(&id),
            quoted(name)
        ))
    })?;
    Ok((
        [
            (header::CONTENT_TYPE, "image/png"),
            (header::CACHE_CONTROL, "no-cache"),
        ],
        Body::from(bytes),
    )
        .into_response())
}

pub(crate) async fn folders(
    State(state): State<AppState>,
) -> Result<Json<Vec<FolderView>>, ApiError> {
    blocking(&state, |farm| snapshot(farm).folders)
        .await
        .map(Json)
}

pub(super) fn no_printer(farm: &Farm, name: &str) -> ApiError {
    let names = control::printer_names(farm);
    ApiError::not_found(format!(
        "no printer {} (the printers are: {})",
        quoted(name),
        names.join(", ")
    ))
}

/// `POST /api/v1/printers/{name}/clear|pause|resume|unload` (`load`: see `spools`);
/// `clear?reference=true` also takes the camera's picture as the empty bed's reference.
pub(crate) async fn printer_action(
    State(state): State<AppState>,
    Path((name, action)): Path<(String, String)>,
    query: Result<axum::extract::Query<ActionQuery>, axum::extract::rejection::QueryRejection>,
) -> Result<Json<serde_json::Value>, ApiError> {
    if !control::printer_names(&state.farm).contains(&name) {
        return Err(no_printer(&state.farm, &name));
    }
    let query = query.map_err(bad_query)?.0;
    if query.reference.is_some() && action != "clear" {
        return Err(ApiError::bad_request(
            "`reference` goes with `clear` only".to_string(),
        ));
    }
    let printer = name;
    let command = match action.as_str() {
        "clear" => return clear(&state, printer, query.reference == Some(true)).await,
        "pause" => Command::Pause { printer },
        "resume" => Command::Resume { printer },
        "unload" => Command::Unload { printer },
        other => {
            return Err(ApiError::not_found(format!(
                "no printer action {}; the printer actions are clear, pause, resume, load, unload",
                quoted(other)
            )))
        }
    };
    act(&state, command).await
}

/// The query of `POST /api/v1/printers/{name}/power/{on|off}`.
#[derive(Debug, serde::Deserialize)]
#[serde(deny_unknown_fields)]
pub(crate) struct PowerQuery {
    /// Off even with a print still on its bed.
    pub force: Option<bool>,
}

/// `POST /api/v1/printers/{name}/power/{on|off}`: switches a printer with a
/// `[printer.power]` switch, between prints.
pub(crate) async fn power(
    State(state): State<AppState>,
    Path((name, switch)): Path<(String, String)>,
    query: Result<axum::extract::Query<PowerQuery>, axum::extract::rejection::QueryRejection>,
) -> Result<Json<serde_json::Value>, ApiError> {
    let query = query.map_err(bad_query)?.0;
    if !control::printer_names(&state.farm).contains(&name) {
        return Err(no_printer(&state.farm, &name));
    }
    let on = match switch.as_str() {
        "on" => true,
        "off" => false,
        other => {
            return Err(ApiError::not_found(format!(
                "no power action {}; they are on, off",
                quoted(other)
            )))
        }
    };
    let command = Command::Power {
        printer: name,
        on,
        force: query.force == Some(true),
    };
    act(&state, command).await
}

/// The query of a printer action: `reference=true` with `clear`.
#[derive(Debug, serde::Deserialize)]
#[serde(deny_unknown_fields)]
pub(crate) struct ActionQuery {
    pub reference: Option<bool>,
}

/// A person says the printer's bed is clear. With a camera, its picture now becomes the
/// reference of the bed check (before the bed opens to a job, so the picture is of the
/// empty bed) when there is none yet or `reference` asks for a new one.
async fn clear(
    state: &AppState,
    printer: String,
    reference: bool,
) -> Result<Json<serde_json::Value>, ApiError> {
    use crate::camera::bedwatch;
    let spool = state.farm.config().spool_dir.clone();
    let mut note = String::new();
    let local = state.cameras.has(&printer);
    if local && (reference || !bedwatch::reference_path(&spool, &printer).exists()) {
        let (cameras, name) = (state.cameras.clone(), printer.clone());
        let taken =
            tokio::task::spawn_blocking(move || bedwatch::take_reference(&cameras, &spool, &name))
                .await
                .map_err(ApiError::from)?;
        note = match taken {
            Ok(()) => "; the camera's picture of it is the reference of the bed check now".into(),
            Err(e) if reference => {
                return Err(ApiError::conflict(format!(
                    "{printer}: no reference taken: {e}; the bed was not marked clear"
                )))
            }
            Err(e) => format!("; no reference of the empty bed taken: {e}"),
        };
    } else if reference {
        return Err(ApiError::conflict(format!(
            "{printer} has no camera on this host: no reference can be taken here"
        )));
    }
    let mut answer = act(state, Command::Clear { printer }).await?;
    if let Some(message) = answer.0.get_mut("message") {
        *message = serde_json::Value::String(format!("{}{note}", message.as_str().unwrap_or("")));
    }
    Ok(answer)
}

/// The query of a job action: `copy=N`, one copy of a job with copies (cancel, retry).
#[derive(Debug, serde::Deserialize)]
#[serde(deny_unknown_fields)]
pub(crate) struct JobActionQuery {
    pub copy: Option<u32>,
}

/// `POST /api/v1/jobs/{id}/cancel|retry|release[?copy=N]`: of a job with copies, every
/// copy it applies to, or copy N.
pub(crate) async fn job_action(
    State(state): State<AppState>,
    Path((id, action)): Path<(String, String)>,
    query: Result<axum::extract::Query<JobActionQuery>, axum::extract::rejection::QueryRejection>,
) -> Result<Json<serde_json::Value>, ApiError> {
    let copy = query.map_err(bad_query)?.0.copy;
    if state.farm.store().get(&id).is_none() {
        return Err(ApiError::not_found(format!(
            "no job {} (hint: GET /api/v1/jobs lists them)",
            quoted(&id)
        )));
    }
    let job = id;
    let command = match action.as_str() {
        "cancel" => Command::Cancel { job, copy },
        "retry" => Command::Retry { job, copy },
        "release" if copy.is_none() => Command::Release { job },
        "release" => {
            return Err(ApiError::bad_request(
                "release applies to every copy of a job: no `copy` with it".to_string(),
            ))
        }
        other => {
            return Err(ApiError::not_found(format!(
                "no job action {}; the job actions are cancel, retry, release",
                quoted(other)
            )))
        }
    };
    act(&state, command).await
}

/// `POST /api/v1/jobs/{id}/parts/{part}/cancel`: the part by its name or its number from 1
/// (the job's `slice_report.parts`).
pub(crate) async fn cancel_part(
    State(state): State<AppState>,
    Path((job, part)): Path<(String, String)>,
) -> Result<Json<serde_json::Value>, ApiError> {
    act(&state, Command::CancelPart { job, part }).await
}

pub(super) async fn act(
    state: &AppState,
    command: Command,
) -> Result<Json<serde_json::Value>, ApiError> {
    tracing::info!(?command, "http: action");
    match control::execute(&state.farm, command).await {
        Ok(done) => Ok(Json(
            serde_json::json!({ "ok": true, "message": done.to_string() }),
        )),
        Err(e) if e.is_not_found() => Err(ApiError::not_found(e.to_string())),
        Err(e) if e.is_unavailable() => Err(ApiError::new(
            StatusCode::SERVICE_UNAVAILABLE,
            e.to_string(),
        )),
        Err(e) => Err(ApiError::conflict(e.to_string())),
    }
}

/// `PUT /api/v1/folders/{folder}/files/{file}`: the body is the file.
pub(crate) async fn upload(
    State(state): State<AppState>,
    Path((folder, file)): Path<(String, String)>,
    body: Body,
) -> Result<(StatusCode, Json<serde_json::Value>), ApiError> {
    let config = state.farm.config();
    let folder = upload::find_folder(&config, &folder)?;
    // The name as the farm keeps it (one spelling), which the answer shows too.
    let (file, _) = upload::upload_name(&file)?;
    let (path, size) = upload::store(
        &folder.path,
        &file,
        body.into_data_stream(),
        state.upload_max_bytes,
    )
    .await?;
    tracing::info!(file = %path.display(), size, "http: uploaded into a hot folder");
    Ok((
        StatusCode::CREATED,
        Json(serde_json::json!({
            "ok": true,
            "folder": upload::folder_name(folder),
            "file": file,
            "bytes": size,
            "message": format!("{file} is in hot folder {}; it becomes a job once picked up", upload::folder_name(folder)),
        })),
    ))
}
