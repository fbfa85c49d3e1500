//! What an OctoPrint instance says about its printer and job, for a hot folder that
//! several printers print from. OctoPrint has one printer per instance; a folder has a
//! list. So each answer is about the folder's *focus printer*, chosen in this order:
//! 1. a printer of the folder busy with one of this folder's jobs (printing, paused, or
//!    waiting to heat), the one furthest along;
//! 2. else the first of the folder's printers that is idle;
//! 3. else the first printer in the folder's list.
//!
//! `api/printer`: the focus printer's temperatures (`tool0`, `bed`; `null` while not
//! known) and its state as OctoPrint's flags; `crispen.printers` lists every printer of
//! the folder with its state. `api/job`: the focus printer's job when it prints one of
//! this folder's, else the folder's next job waiting for a printer (state `Operational`,
//! no progress), else no job. `api/printerprofiles`: the focus printer's machine.
//! Always `200`: a folder whose printers are all offline says so in its flags
//! (`closedOrError`), where OctoPrint would answer `409`.
//!
//! `POST api/job` (pause, resume, cancel, start) acts on the folder's print, for the
//! operator's key and application keys with `control` in their scope ([`job_command`]).

use super::Instance;
use crate::daemon::control::{self, Command, JobStatus};
use crate::daemon::farm::{PrinterState, PrinterStatus};
use crate::daemon::job::JobState;
use crate::http::appkeys::Who;
use crate::http::error::quoted;
use crate::http::{ApiError, AppState};
use axum::extract::State;
use axum::Json;
use serde_json::{json, Value};

/// A folder's printers and jobs, as one status snapshot has them.
struct FolderView {
    name: String,
    printers: Vec<PrinterStatus>,
    jobs: Vec<JobStatus>,
    /// Index into `printers`, if the folder has any printer the farm knows.
    focus: Option<usize>,
}

fn busy(state: PrinterState) -> bool {
    matches!(
        state,
        PrinterState::Printing | PrinterState::Paused | PrinterState::WaitingToHeat
    )
}

fn view(state: &AppState, instance: &Instance) -> Result<FolderView, ApiError> {
    let config = state.farm.config();
    let folder = instance.some_folder(&config)?;
    let status = control::status(&state.farm);
    let printers: Vec<PrinterStatus> = folder
        .printers
        .iter()
        .filter_map(|name| status.printers.iter().find(|p| &p.name == name).cloned())
        .collect();
    let jobs: Vec<JobStatus> = status
        .jobs
        .into_iter()
        .filter(|j| j.folder == folder.path)
        .collect();
    let ours = |p: &PrinterStatus| {
        p.job
            .as_ref()
            .is_some_and(|id| jobs.iter().any(|j| &j.id == id))
    };
    let progress = |p: &PrinterStatus| {
        p.progress
            .as_ref()
            .map_or(0.0, |g| g.lines_acked as f64 / g.lines_total.max(1) as f64)
    };
    let focus = printers
        .iter()
        .enumerate()
        .filter(|(_, p)| busy(p.state) && ours(p))
        .max_by(|(_, a), (_, b)| progress(a).total_cmp(&progress(b)))
        .map(|(i, _)| i)
        .or_else(|| printers.iter().position(|p| p.state == PrinterState::Idle))
        .or(if printers.is_empty() { None } else { Some(0) });
    Ok(FolderView {
        name: super::upload::folder_name(folder),
        printers,
        jobs,
        focus,
    })
}

/// OctoPrint's state text for a printer's state (Cura maps `Printing…`, `Paused`,
/// `Operational`, `Offline…`, `Error…`, `Connecting`, `Starting…`).
fn state_text(p: Option<&PrinterStatus>) -> String {
    let Some(p) = p else {
        return "Offline (no printer)".to_string();
    };
    match p.state {
        PrinterState::Printing => "Printing".to_string(),
        PrinterState::Paused | PrinterState::WaitingForOperator => "Paused".to_string(),
        PrinterState::WaitingToHeat => "Starting".to_string(),
        // A finished print still on the bed: the printer is there, it takes no job until
        // the operator clears it (`crispen.printers` says so).
        PrinterState::Idle
        | PrinterState::BedNotCleared
        | PrinterState::CheckingBed
        | PrinterState::Maintenance => "Operational".to_string(),
        // The eject sequence moves the printer: busy, as while it prints.
        PrinterState::Ejecting => "Printing".to_string(),
        PrinterState::Connecting => "Connecting".to_string(),
        PrinterState::Disconnected | PrinterState::Off => "Offline".to_string(),
        PrinterState::Stopped | PrinterState::Halted => format!(
            "Error: {}",
            p.detail.as_deref().unwrap_or("the printer stopped")
        ),
    }
}

fn flags(p: Option<&PrinterStatus>) -> Value {
    let state = p.map(|p| p.state);
    let is = |s: PrinterState| state == Some(s);
    let operational = matches!(
        state,
        Some(
            PrinterState::Idle
                | PrinterState::WaitingToHeat
                | PrinterState::Printing
                | PrinterState::Paused
                | PrinterState::WaitingForOperator
                | PrinterState::BedNotCleared
                | PrinterState::Ejecting
                | PrinterState::CheckingBed
                | PrinterState::Maintenance
        )
    );
    json!({
        "operational": operational,
        "printing": is(PrinterState::Printing) || is(PrinterState::WaitingToHeat),
        "paused": is(PrinterState::Paused) || is(PrinterState::WaitingForOperator),
        "pausing": false,
        "cancelling": false,
        "resuming": false,
        "finishing": false,
        "sdReady": false,
        "error": is(PrinterState::Stopped) || is(PrinterState::Halted),
        "ready": is(PrinterState::Idle),
        "closedOrError": !operational,
    })
}

fn temperature(actual: Option<f64>, target: Option<f64>) -> Value {
    json!({ "actual": actual, "target": target, "offset": 0 })
}

/// `GET api/printer` (`exclude`, `history` and `limit` are accepted and ignored: there is
/// no temperature history).
pub(crate) async fn printer(
    State(state): State<AppState>,
    instance: Instance,
) -> Result<Json<Value>, ApiError> {
    let v = view(&state, &instance)?;
    let focus = v.focus.map(|i| &v.printers[i]);
    let t = focus
        .and_then(|p| {
            p.temperatures.or_else(|| {
                p.progress
                    .as_ref()
                    .map(|g| crate::daemon::farm::PrinterTemperatures {
                        hotend_c: g.hotend_c,
                        hotend_target_c: g.hotend_target_c,
                        bed_c: g.bed_c,
                        bed_target_c: g.bed_target_c,
                    })
            })
        })
        .unwrap_or_default();
    Ok(Json(json!({
        "temperature": {
            "tool0": temperature(t.hotend_c, t.hotend_target_c),
            "bed": temperature(t.bed_c, t.bed_target_c),
        },
        "sd": { "ready": false },
        "state": { "text": state_text(focus), "flags": flags(focus) },
        "crispen": {
            "folder": v.name,
            "printer": focus.map(|p| p.name.clone()),
            "printers": v.printers.iter().map(|p| json!({
                "name": p.name,
                "state": p.state,
                "job": p.job,
                "bed_cleared": p.bed_cleared,
            })).collect::<Vec<_>>(),
        },
    })))
}

/// `GET api/job`.
pub(crate) async fn job(
    State(state): State<AppState>,
    instance: Instance,
) -> Result<Json<Value>, ApiError> {
    let v = view(&state, &instance)?;
    let focus = v.focus.map(|i| &v.printers[i]);
    let current = focus
        .filter(|p| busy(p.state))
        .and_then(|p| p.job.as_ref())
        .and_then(|id| v.jobs.iter().find(|j| &j.id == id));
    let next = || {
        v.jobs.iter().find(|j| {
            matches!(
                j.state,
                JobState::Queued | JobState::Preparing | JobState::Ready
            )
        })
    };
    // The whole print's estimate: time printed so far and the estimate of what is left
    // (null until crispen has one, as OctoPrint's before its analysis).
    let mut estimated: Option<u64> = None;
    let (job, state_text, progress) = match current {
        Some(j) => {
            let live = focus
                .and_then(|p| p.progress.clone())
                .or(j.progress.clone());
            estimated = live.as_ref().and_then(|g| {
                g.remaining_s
                    .map(|r| (g.elapsed_s + r).max(0.0).round() as u64)
            });
            let progress = match live {
                Some(g) => json!({
                    "completion": 100.0 * g.lines_acked as f64 / g.lines_total.max(1) as f64,
                    "filepos": null,
                    "printTime": g.elapsed_s.round() as u64,
                    "printTimeLeft": g.remaining_s.map(|s| s.round() as u64),
                    "printTimeLeftOrigin": g.remaining_s.map(|_| "analysis"),
                }),
                None => no_progress(),
            };
            (Some(j), state_text(focus), progress)
        }
        None => {
            // Not printing one of ours: the printer's own state, and the next job.
            let text = match focus.map(|p| p.state) {
                Some(s) if busy(s) => "Operational".to_string(),
                _ => state_text(focus),
            };
            (next(), text, no_progress())
        }
    };
    let file = match job {
        // A copy is shown as one ("bust.stl (copy 2 of 6)"), its file as it is.
        Some(j) => json!({
            "name": j.file,
            "display": match &j.copy {
                Some(c) => format!("{} (copy {} of {})", j.file, c.n, j.copies),
                None => j.file.clone(),
            },
            "path": match instance.folder {
                Some(_) => j.file.clone(),
                None => format!("{}/{}", v.name, j.file),
            },
            "origin": "local",
            "size": null,
            "date": null,
        }),
        None => json!({ "name": null, "path": null, "origin": null, "size": null, "date": null }),
    };
    Ok(Json(json!({
        "job": {
            "file": file,
            "estimatedPrintTime": estimated,
            "lastPrintTime": null,
            "filament": null,
            "user": null,
        },
        "progress": progress,
        "state": state_text,
        "crispen": {
            "folder": v.name,
            "job": job.map(|j| json!({
                "id": j.id, "state": j.state, "held": j.held, "printer": j.printer,
                "copy": j.copy, "copies": j.copies_status,
            })),
        },
    })))
}

fn no_progress() -> Value {
    json!({
        "completion": null,
        "filepos": null,
        "printTime": null,
        "printTimeLeft": null,
        "printTimeLeftOrigin": null,
    })
}

/// `GET api/printerprofiles`: one profile, current and default: the focus printer's
/// machine (build volume, heated bed, nozzle; the filament diameter under `crispen`).
pub(crate) async fn printer_profiles(
    State(state): State<AppState>,
    instance: Instance,
) -> Result<Json<Value>, ApiError> {
    let v = view(&state, &instance)?;
    let focus = v.focus.map(|i| v.printers[i].name.clone());
    let machines = state.farm.printer_machines();
    let machine = focus
        .as_ref()
        .and_then(|name| machines.iter().find(|(n, _)| n == name))
        .map(|(_, m)| m);
    let Some(m) = machine else {
        return Ok(Json(json!({ "profiles": {} })));
    };
    let axis = |speed: u32| json!({ "speed": speed, "inverted": false });
    Ok(Json(json!({ "profiles": { "_default": {
        "id": "_default",
        "name": format!("crispen: {}", v.name),
        "model": m.name,
        "color": "default",
        "current": true,
        "default": true,
        "resource": format!("{}api/printerprofiles/_default", instance.base),
        "volume": {
            "formFactor": "rectangular",
            "origin": "lowerleft",
            "width": m.bed_mm[0],
            "depth": m.bed_mm[1],
            "height": m.bed_mm[2],
            "custom_box": false,
        },
        "heatedBed": m.heated_bed,
        "heatedChamber": false,
        "axes": { "x": axis(6000), "y": axis(6000), "z": axis(200), "e": axis(300) },
        "extruder": {
            "count": 1,
            "offsets": [[0.0, 0.0]],
            "nozzleDiameter": m.nozzle_mm,
            "sharedNozzle": false,
            "defaultExtrusionLength": 5,
        },
        "crispen": { "filament_mm": m.filament_mm, "printer": focus },
    }}})))
}

/// `GET api/connection`: the focus printer's connection. Connecting and disconnecting
/// (`POST`) are crispen's own business and refused.
pub(crate) async fn connection(
    State(state): State<AppState>,
    instance: Instance,
) -> Result<Json<Value>, ApiError> {
    let v = view(&state, &instance)?;
    let focus = v.focus.map(|i| &v.printers[i]);
    Ok(Json(json!({
        "current": {
            "state": state_text(focus),
            "port": focus.map(|p| p.port.clone()),
            "baudrate": null,
            "printerProfile": "_default",
        },
        "options": {
            "ports": v.printers.iter().map(|p| p.port.clone()).collect::<Vec<_>>(),
            "baudrates": [],
            "printerProfiles": [{ "id": "_default", "name": format!("crispen: {}", v.name) }],
            "portPreference": null,
            "baudratePreference": null,
            "printerProfilePreference": "_default",
            "autoconnect": true,
        },
    })))
}

/// `POST api/job` as OctoPrint takes it: `{"command": "pause", "action":
/// "pause"|"resume"|"toggle"}` (no action: toggle, as OctoPrint), `{"command": "cancel"}`,
/// `{"command": "start"}`.
#[derive(Debug, serde::Deserialize)]
struct JobCommand {
    command: String,
    #[serde(default)]
    action: Option<String>,
}

/// Why a job command did nothing, for the answer and the counter.
struct Refusal {
    error: ApiError,
    /// `refused` (the key may not) or `failed` (nothing to act on, the farm refused).
    result: &'static str,
}

impl From<ApiError> for Refusal {
    fn from(error: ApiError) -> Refusal {
        Refusal {
            error,
            result: "failed",
        }
    }
}

/// `POST api/job`: pause, resume, cancel or start the instance's print: the print of one
/// of the folder's jobs on the folder's focus printer, through the same commands as the
/// dashboard's buttons (`control::execute`: host-side pause, safe stop). `start` prints
/// the newest held upload of this key (the operator's: any) in the folder, as its
/// select-and-print would. The operator's key may; an application key only with
/// `control` in its scope, else `409` saying how to give it (`crispen keys allow ID
/// --control`). `restart` is refused (`409`): crispen prints a job once. Nothing to act
/// on: `409`, as OctoPrint answers. `204`. Every command is logged with the key's
/// application and counted (`crispen_octoprint_control_total`).
pub(crate) async fn job_command(
    State(state): State<AppState>,
    instance: Instance,
    who: Option<axum::Extension<Who>>,
    body: axum::body::Bytes,
) -> Result<axum::http::StatusCode, ApiError> {
    let command: JobCommand = serde_json::from_slice(&body).map_err(|e| {
        ApiError::bad_request(format!(
            "a job command is JSON like {{\"command\": \"pause\", \"action\": \"pause\"}}, {{\"command\": \"cancel\"}} or {{\"command\": \"start\"}}: {e}"
        ))
    })?;
    let (action, what): (&'static str, &'static str) =
        match (command.command.as_str(), command.action.as_deref()) {
            ("pause", None | Some("toggle")) => ("toggle", "pause or resume the print"),
            ("pause", Some("pause")) => ("pause", "pause the print"),
            ("pause", Some("resume")) => ("resume", "resume the print"),
            ("cancel", _) => ("cancel", "cancel the print"),
            ("start", _) => ("start", "start the selected job"),
            ("restart", _) => {
                return Err(ApiError::conflict(
                    "job command \"restart\": crispen prints a job once; upload it again (with print) to print it again",
                ))
            }
            ("pause", Some(other)) => {
                return Err(ApiError::bad_request(format!(
                    "pause action {}: the actions are pause, resume, toggle",
                    quoted(other)
                )))
            }
            (other, _) => {
                return Err(ApiError::bad_request(format!(
                    "job command {}: the commands are pause (action pause, resume or toggle), cancel and start",
                    quoted(other)
                )))
            }
        };
    let folder = {
        let config = state.farm.config();
        let folder = instance.some_folder(&config)?;
        (folder.path.clone(), super::upload::folder_name(folder))
    };
    let who = who.map(|w| w.0);
    let by = match &who {
        Some(Who::Operator) => "the operator".to_string(),
        Some(Who::App(grant)) => grant.app.clone(),
        None => "no key".to_string(),
    };
    let done = control_job(&state, &instance, who.as_ref(), &folder.0, action, what).await;
    let result = match &done {
        Ok(_) => "done",
        Err(r) => r.result,
    };
    state
        .counters
        .count_octoprint_control(&folder.1, action, result);
    match done {
        Ok(message) => {
            tracing::info!(app = %by, folder = %folder.1, action, %message, instance = %instance.base, "octoprint: job command");
            Ok(axum::http::StatusCode::NO_CONTENT)
        }
        Err(r) => {
            tracing::info!(app = %by, folder = %folder.1, action, result, error = %r.error.message, instance = %instance.base, "octoprint: job command not done");
            Err(r.error)
        }
    }
}

/// [`job_command`]'s work, once the command is read: what was done, or why not.
async fn control_job(
    state: &AppState,
    instance: &Instance,
    who: Option<&Who>,
    folder: &std::path::Path,
    action: &'static str,
    what: &'static str,
) -> Result<String, Refusal> {
    let grant = match who {
        Some(Who::Operator) => None,
        Some(Who::App(grant)) => {
            // OctoPrint answers a command it may not take with 409; so does this, with the
            // way to give the key control.
            grant.check_control(what).map_err(|e| Refusal {
                error: ApiError::conflict(e.message),
                result: "refused",
            })?;
            Some(grant)
        }
        // Changes always come with a key; without one nothing is authorised.
        None => {
            return Err(Refusal {
                error: ApiError::new(
                    axum::http::StatusCode::FORBIDDEN,
                    "controlling a print needs a key",
                ),
                result: "refused",
            })
        }
    };
    if action == "start" {
        return start(state, grant, folder).await;
    }
    let v = view(state, instance)?;
    // The folder's print: a printer of the folder busy with one of its jobs.
    let controllable = |p: &&PrinterStatus| {
        (busy(p.state) || p.state == PrinterState::WaitingForOperator)
            && p.job
                .as_ref()
                .is_some_and(|id| v.jobs.iter().any(|j| &j.id == id))
    };
    let focus = v
        .focus
        .map(|i| &v.printers[i])
        .filter(controllable)
        .or_else(|| v.printers.iter().find(controllable));
    let Some(printer) = focus else {
        return Err(ApiError::conflict(format!(
            "hot folder {} has no print running to {what}",
            v.name
        ))
        .into());
    };
    let paused = matches!(
        printer.state,
        PrinterState::Paused | PrinterState::WaitingForOperator
    );
    let name = printer.name.clone();
    let act = match action {
        // The print on this printer only: of a job with copies, the copy it prints.
        "cancel" => {
            let job = printer.job.clone().unwrap_or_default();
            let copy = state.farm.store().get(&job).map(|j| j.copy_number());
            Command::Cancel { job, copy }
        }
        "resume" => Command::Resume { printer: name },
        "pause" => Command::Pause { printer: name },
        _ if paused => Command::Resume { printer: name },
        _ => Command::Pause { printer: name },
    };
    control::execute(&state.farm, act)
        .await
        .map(|done| done.to_string())
        .map_err(|e| ApiError::conflict(e.to_string()).into())
}

/// `start`: the newest held job of the folder that `grant`'s uploads held (the
/// operator's key: any held job) is released; else the newest such upload that has not
/// become a job yet is printed once it does (`crate::http::pending`).
async fn start(
    state: &AppState,
    grant: Option<&crate::http::appkeys::Grant>,
    folder: &std::path::Path,
) -> Result<String, Refusal> {
    let status = control::status(&state.farm);
    let held: Vec<&JobStatus> = status
        .jobs
        .iter()
        .filter(|j| {
            j.folder == folder
                && j.held
                && matches!(
                    j.state,
                    JobState::Queued | JobState::Preparing | JobState::Ready
                )
        })
        .collect();
    let mine: Vec<&JobStatus> = match grant {
        None => held,
        Some(grant) => {
            let own = super::files::own_holds(state, grant, &held).await;
            held.into_iter().filter(|j| own.contains(&j.id)).collect()
        }
    };
    if let Some(job) = super::files::newest(mine) {
        return control::execute(
            &state.farm,
            Command::Release {
                job: job.id.clone(),
            },
        )
        .await
        .map(|done| done.to_string())
        .map_err(|e| ApiError::conflict(e.to_string()).into());
    }
    let key = grant.map(|g| g.id.as_str());
    if let Some((token, file)) = state.pending.unwanted(folder, key).into_iter().next() {
        let outcome = state
            .pending
            .print(&state.farm, &token)
            .await
            .map_err(|e| Refusal::from(ApiError::conflict(e.to_string())))?;
        return Ok(match outcome {
            crate::http::pending::Outcome::Released(job) => format!("{file}: job {job} released"),
            crate::http::pending::Outcome::AlreadyFree(job) => {
                format!("{file}: job {job} was not held; it prints once ready")
            }
            crate::http::pending::Outcome::Waiting => {
                format!("{file}: prints as soon as the hot folder has taken it")
            }
        });
    }
    Err(ApiError::conflict(
        "nothing to start: no held upload of this key in this hot folder (crispen starts every other job itself once it is ready and a printer is free)",
    )
    .into())
}
