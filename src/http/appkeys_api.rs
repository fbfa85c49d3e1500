//! The application-key endpoints: OctoPrint's plugin flow a client follows to get a key
//! (probe, request, poll; no key needed, the client has none yet) and the operator's list
//! and decisions. Apart from the keys themselves ([`super::appkeys`]), which the
//! listener's state holds, so the keeper does not depend on the state that holds it.

use super::appkeys::{KeysView, Poll, Scope};
use super::error::quoted;
use super::{ApiError, AppState};
use axum::extract::{Path, Query, State};
use axum::http::{header, HeaderMap, StatusCode};
use axum::response::{IntoResponse, Response};
use axum::Json;
use serde::Deserialize;
use std::time::Instant;

// ---- OctoPrint's plugin endpoints (no key needed: the client has none yet) ----

/// `GET plugin/appkeys/probe`: the flow is supported.
pub(crate) async fn probe() -> StatusCode {
    StatusCode::NO_CONTENT
}

#[derive(Debug, Deserialize)]
pub(crate) struct RequestBody {
    app: String,
    // OctoPrint's optional `user`; crispen has no users.
    #[serde(default)]
    #[allow(dead_code)]
    user: Option<String>,
}

/// `POST plugin/appkeys/request` with `{"app": "Name"}`: `201` with the poll address in
/// `Location` and `app_token`.
pub(crate) async fn request(
    State(state): State<AppState>,
    client: Option<axum::Extension<super::serve::ClientAddr>>,
    uri: axum::http::Uri,
    headers: HeaderMap,
    body: axum::body::Bytes,
) -> Result<Response, ApiError> {
    let body: RequestBody = serde_json::from_slice(&body).map_err(|e| {
        ApiError::bad_request(format!(
            "the key request's body must be JSON like {{\"app\": \"Name\"}}: {e}"
        ))
    })?;
    let source = match client.and_then(|c| c.0 .0) {
        Some(ip) => ip.to_string(),
        None => "control socket".to_string(),
    };
    let instance = instance_of(uri.path());
    let token = state
        .appkeys
        .request(&body.app, source, instance, Instant::now())?;
    let location = format!(
        "{}{}/{token}",
        origin(&headers),
        uri.path().trim_end_matches('/')
    );
    tracing::info!(app = %body.app, "http: an application asks for a key");
    Ok((
        StatusCode::CREATED,
        [(header::LOCATION, location)],
        Json(serde_json::json!({ "app_token": token })),
    )
        .into_response())
}

/// `GET plugin/appkeys/request/<token>`: `202` while undecided, `200` with `api_key`
/// once allowed, `404` when denied, expired, abandoned or unknown.
pub(crate) async fn poll(
    State(state): State<AppState>,
    Path(params): Path<Vec<(String, String)>>,
) -> Result<Response, ApiError> {
    let token = params
        .iter()
        .find(|(k, _)| k == "token")
        .map(|(_, v)| v.as_str())
        .unwrap_or("");
    match state.appkeys.poll(token, Instant::now()) {
        Poll::Waiting => Ok((StatusCode::ACCEPTED, Json(serde_json::json!({}))).into_response()),
        Poll::Granted(key) => Ok(Json(serde_json::json!({ "api_key": key })).into_response()),
        Poll::Gone => Err(ApiError::not_found(
            "no such key request: it was denied, or has expired, or was not polled for a minute, or its key was fetched already",
        )),
    }
}

/// The OctoPrint instance a path under it names: `/` or `/octoprint/<folder>/`.
fn instance_of(path: &str) -> String {
    match path.strip_prefix("/octoprint/") {
        Some(rest) => format!(
            "/octoprint/{}/",
            crate::daemon::hotfolder::printable(rest.split('/').next().unwrap_or(""))
        ),
        None => "/".to_string(),
    }
}

/// `http://host` as the client addressed the server (its `Host`), for absolute
/// `Location`s as OctoPrint gives them; empty (a relative address) without one.
pub(crate) fn origin(headers: &HeaderMap) -> String {
    match headers.get(header::HOST).and_then(|h| h.to_str().ok()) {
        Some(host)
            if !host.is_empty()
                && host
                    .bytes()
                    .all(|b| b.is_ascii_alphanumeric() || b".-:[]_".contains(&b)) =>
        {
            format!("http://{host}")
        }
        _ => String::new(),
    }
}

// ---- the operator's side (`/api/v1/appkeys`), for the dashboard and `crispen keys` ----

/// `GET /api/v1/appkeys`: pending requests and keys (never their secrets).
pub(crate) async fn list(State(state): State<AppState>) -> Json<KeysView> {
    Json(state.appkeys.view(Instant::now()))
}

/// The scope an allow gives: `?control=true&everywhere=true` (each absent: false).
#[derive(Debug, Default, Deserialize)]
pub(crate) struct ScopeQuery {
    #[serde(default)]
    control: Option<String>,
    #[serde(default)]
    everywhere: Option<String>,
}

impl ScopeQuery {
    fn scope(&self) -> Result<Scope, ApiError> {
        let flag = |name: &str, v: &Option<String>| match v.as_deref() {
            None => Ok(false),
            Some(v) => match v.to_ascii_lowercase().as_str() {
                "" | "1" | "true" | "yes" => Ok(true),
                "0" | "false" | "no" => Ok(false),
                _ => Err(ApiError::bad_request(format!(
                    "{name} must be true or false, got {}",
                    quoted(v)
                ))),
            },
        };
        Ok(Scope {
            control: flag("control", &self.control)?,
            everywhere: flag("everywhere", &self.everywhere)?,
        })
    }
}

/// `POST /api/v1/appkeys/requests/{id}/allow[?control=true][&everywhere=true]`,
/// `…/requests/{id}/deny`, `/api/v1/appkeys/keys/{id}/allow[?…]` (sets an existing key's
/// scope to exactly what the query says) and `/api/v1/appkeys/keys/{id}/revoke`.
pub(crate) async fn act(
    State(state): State<AppState>,
    Path((kind, id, action)): Path<(String, String, String)>,
    Query(query): Query<ScopeQuery>,
) -> Result<Json<serde_json::Value>, ApiError> {
    let scope = query.scope()?;
    let keys = state.appkeys.clone();
    let done = tokio::task::spawn_blocking(move || match (kind.as_str(), action.as_str()) {
        ("requests", "allow") => keys.decide(&id, Some(scope), Instant::now()),
        ("requests", "deny") => keys.decide(&id, None, Instant::now()),
        ("keys", "allow") => keys.set_scope(&id, scope),
        ("keys", "revoke") => keys.revoke(&id),
        _ => Err(ApiError::not_found(format!(
            "no such action {}: the actions are requests/ID/allow, requests/ID/deny, keys/ID/allow, keys/ID/revoke",
            quoted(&format!("{kind}/{id}/{action}"))
        ))),
    })
    .await
    .map_err(ApiError::from)??;
    tracing::info!(message = %done, "http: application keys");
    Ok(Json(serde_json::json!({ "ok": true, "message": done })))
}
