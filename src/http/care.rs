//! A printer's care through the API: recording a `[[maintenance]]` task done, putting a
//! printer into maintenance by hand and taking it out (`POST .../maintenance/{action}`),
//! and its care record with the log of work (`GET .../maintenance`). The dashboard and
//! `crispen maintenance` are its clients.

use super::api::{act, bad_query, no_printer};
use super::error::{quoted, ApiError};
use super::state::AppState;
use crate::daemon::care::{Counts, Logged, TaskStatus, Work};
use crate::daemon::control::{self, CareAsk, Command};
use axum::extract::rejection::QueryRejection;
use axum::extract::{Path, Query, State};
use axum::Json;
use serde::{Deserialize, Serialize};

/// The query of a care action.
#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
pub(crate) struct CareQuery {
    /// The task done (`done` only).
    pub task: Option<String>,
    /// Who did it (the CLI sends the user's login name; the dashboard its own name).
    pub by: Option<String>,
    pub note: Option<String>,
}

/// `POST /api/v1/printers/{name}/maintenance/{done|start|end}`.
pub(crate) async fn action(
    State(state): State<AppState>,
    Path((name, action)): Path<(String, String)>,
    query: Result<Query<CareQuery>, QueryRejection>,
) -> Result<Json<serde_json::Value>, ApiError> {
    let Query(query) = query.map_err(bad_query)?;
    if !control::printer_names(&state.farm).contains(&name) {
        return Err(no_printer(&state.farm, &name));
    }
    let what = match (action.as_str(), query.task) {
        ("done", Some(task)) => CareAsk::Done { task },
        ("done", None) => {
            return Err(ApiError::bad_request(
                "`done` needs the task: ?task=NAME".to_string(),
            ))
        }
        ("start", None) => CareAsk::Start,
        ("end", None) => CareAsk::End,
        ("start" | "end", Some(_)) => {
            return Err(ApiError::bad_request(format!(
                "`task` goes with `done` only, not {action}"
            )))
        }
        (other, _) => {
            return Err(ApiError::not_found(format!(
                "no maintenance action {}; they are done, start, end",
                quoted(other)
            )))
        }
    };
    let command = Command::Care {
        printer: name,
        what,
        by: query.by.unwrap_or_else(|| "operator".into()),
        note: query.note,
    };
    act(&state, command).await
}

/// A printer's care as `GET .../maintenance` answers it.
#[derive(Debug, Serialize)]
pub(crate) struct CareView {
    pub printer: String,
    pub tasks: Vec<TaskStatus>,
    pub counts: Counts,
    pub held: Option<Work>,
    /// Oldest first.
    pub log: Vec<Logged>,
}

/// `GET /api/v1/printers/{name}/maintenance`.
pub(crate) async fn record(
    State(state): State<AppState>,
    Path(name): Path<String>,
) -> Result<Json<CareView>, ApiError> {
    let farm = &state.farm;
    if !control::printer_names(farm).contains(&name) {
        return Err(no_printer(farm, &name));
    }
    let config = farm.config();
    let store = farm.store();
    let care = store.inventory().care.get(&name);
    let now = crate::daemon::job::now_s();
    Ok(Json(CareView {
        tasks: crate::daemon::care::status(config.tasks_of(&name), care, now),
        counts: care.map(|c| c.counts.clone()).unwrap_or_default(),
        held: care.and_then(|c| c.held.clone()),
        log: care.map(|c| c.log.clone()).unwrap_or_default(),
        printer: name,
    }))
}
