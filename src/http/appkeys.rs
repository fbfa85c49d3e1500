//! Application keys, as OctoPrint's `appkeys` plugin hands them out: a client (Cura's
//! OctoPrint connection) asks for a key of its own (`POST plugin/appkeys/request` with its
//! name), polls the address it was given, and the operator allows or denies the request on
//! the dashboard (or `crispen keys`). An allowed client gets a random key that it alone
//! holds, listed by its application's name and revocable one by one, so no slicer ever
//! needs the farm's `[http]` key.
//!
//! An application key opens the OctoPrint emulation only (`/api/...` outside `/api/v1/`,
//! `/octoprint/...`): a slicer may read the printers' state and upload, never act on the
//! farm's operator API. Keys are kept in `appkeys.json` in the spool directory (mode 0600,
//! written with `fsutil::write_atomic_with`); pending requests live in memory only, at
//! most [`MAX_PENDING`] at once ([`MAX_PENDING_PER_SOURCE`] from one address), each for
//! at most [`PENDING_FOR`]: a request nobody
//! decides on goes away, and a client that stopped polling is forgotten.
//!
//! One owner: the state is behind one lock, held for a lookup or a change and the
//! synchronous write of the file (on a blocking thread), never across an await.

use super::error::quoted;
use super::{ApiError, AppState};
use axum::extract::{Path, State};
use axum::http::{header, HeaderMap, StatusCode};
use axum::response::{IntoResponse, Response};
use axum::Json;
use serde::{Deserialize, Serialize};
use std::path::PathBuf;
use std::sync::Mutex;
use std::time::{Duration, Instant};

/// Requests waiting for a decision (or for their client to fetch the key) at once.
pub const MAX_PENDING: usize = 16;
/// Requests from one address waiting at once: one client cannot take every place.
pub const MAX_PENDING_PER_SOURCE: usize = 4;
/// A request not decided and fetched within this is forgotten.
pub const PENDING_FOR: Duration = Duration::from_secs(10 * 60);
/// Application keys kept at most; revoke one to make room.
pub const MAX_KEYS: usize = 64;
/// Longest application name kept (longer ones are cut).
const MAX_APP_CHARS: usize = 64;
/// The file in the spool directory.
pub const FILE_NAME: &str = "appkeys.json";
/// Largest key file read.
const MAX_FILE_BYTES: u64 = 1024 * 1024;

/// Who a request's key is: the operator (`[http]` key, or the control socket) or an
/// application that was given a key of its own.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum Who {
    Operator,
    App(String),
}

/// A key handed to an application.
#[derive(Debug, Clone, Serialize, Deserialize, PartialEq)]
#[serde(deny_unknown_fields)]
pub struct AppKey {
    /// Names the key in lists and for revoking; not the key.
    pub id: String,
    pub app: String,
    /// Where the request came from.
    pub source: String,
    /// The OctoPrint instance it was asked on (`/` or `/octoprint/<folder>/`).
    pub instance: String,
    /// When it was granted, seconds since the Unix epoch.
    pub created_s: u64,
    /// The secret; only ever shown to the client that asked, once.
    #[serde(rename = "key")]
    secret: String,
}

#[derive(Debug, Default, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
struct KeyFile {
    keys: Vec<AppKey>,
}

#[derive(Debug, Clone, PartialEq)]
enum Decision {
    Pending,
    Allowed(String),
    Denied,
}

#[derive(Debug)]
struct Pending {
    id: String,
    /// The poll address's secret part; never listed.
    token: String,
    app: String,
    source: String,
    instance: String,
    since: Instant,
    decision: Decision,
}

/// What a poll finds.
#[derive(Debug, PartialEq)]
pub enum Poll {
    Waiting,
    Granted(String),
    /// Denied, expired, fetched already, or never asked.
    Gone,
}

/// A pending request as the dashboard lists it.
#[derive(Debug, Serialize)]
pub struct PendingView {
    pub id: String,
    pub app: String,
    pub source: String,
    pub instance: String,
    pub age_s: u64,
    /// "pending", or "allowed"/"denied" until the client has fetched the answer.
    pub decision: &'static str,
}

/// Everything the dashboard shows: requests and keys (without their secrets).
#[derive(Debug, Serialize)]
pub struct KeysView {
    pub pending: Vec<PendingView>,
    pub keys: Vec<KeyView>,
}

/// A key as listed: everything but its secret.
#[derive(Debug, Serialize)]
pub struct KeyView {
    pub id: String,
    pub app: String,
    pub source: String,
    pub instance: String,
    pub created_s: u64,
}

/// The key file is broken or cannot be read.
#[derive(Debug, thiserror::Error)]
#[error(
    "application keys {path}: {message} (hint: fix or remove the file; its clients then ask again)"
)]
pub struct AppKeysError {
    pub path: PathBuf,
    pub message: String,
}

/// The application keys and pending requests of one daemon.
#[derive(Debug)]
pub struct AppKeys {
    path: PathBuf,
    state: Mutex<Keys>,
}

#[derive(Debug, Default)]
struct Keys {
    keys: Vec<AppKey>,
    pending: Vec<Pending>,
}

fn random_text(bytes: usize) -> String {
    use base64::Engine;
    let raw: Vec<u8> = (0..bytes).map(|_| rand::random::<u8>()).collect();
    base64::engine::general_purpose::URL_SAFE_NO_PAD.encode(raw)
}

/// Compares in time independent of where the texts differ.
fn same(given: &[u8], key: &[u8]) -> bool {
    given.len() == key.len() && given.iter().zip(key).fold(0u8, |acc, (a, b)| acc | (a ^ b)) == 0
}

impl AppKeys {
    /// Reads `spool_dir/appkeys.json` (none: no keys yet).
    pub fn open(spool_dir: &std::path::Path) -> Result<AppKeys, AppKeysError> {
        let path = spool_dir.join(FILE_NAME);
        let failed = |message: String| AppKeysError {
            path: path.clone(),
            message,
        };
        let keys = match std::fs::metadata(&path) {
            Err(e) if e.kind() == std::io::ErrorKind::NotFound => Vec::new(),
            Err(e) => return Err(failed(e.to_string())),
            Ok(m) if m.len() > MAX_FILE_BYTES => {
                return Err(failed(format!("larger than {MAX_FILE_BYTES} bytes")))
            }
            Ok(_) => {
                let text = std::fs::read(&path).map_err(|e| failed(e.to_string()))?;
                let file: KeyFile =
                    serde_json::from_slice(&text).map_err(|e| failed(e.to_string()))?;
                if file.keys.len() > MAX_KEYS {
                    return Err(failed(format!("more than {MAX_KEYS} keys")));
                }
                file.keys
            }
        };
        Ok(AppKeys {
            path,
            state: Mutex::new(Keys {
                keys,
                pending: Vec::new(),
            }),
        })
    }

    fn lock(&self) -> std::sync::MutexGuard<'_, Keys> {
        self.state.lock().unwrap_or_else(|e| e.into_inner())
    }

    /// The application a key was given to, if it is one of the keys.
    pub fn app_of(&self, given: &[u8]) -> Option<String> {
        let state = self.lock();
        // Every key compared, whichever matches.
        let mut found = None;
        for k in &state.keys {
            if same(given, k.secret.as_bytes()) {
                found = Some(k.app.clone());
            }
        }
        found
    }

    /// A new request; its poll token. Expired requests are dropped first.
    pub fn request(
        &self,
        app: &str,
        source: String,
        instance: String,
        now: Instant,
    ) -> Result<String, ApiError> {
        let app: String = crate::daemon::hotfolder::printable(app.trim())
            .chars()
            .take(MAX_APP_CHARS)
            .collect();
        if app.is_empty() {
            return Err(ApiError::bad_request(
                "the request needs the application's name: {\"app\": \"Name\"}",
            ));
        }
        let mut state = self.lock();
        state
            .pending
            .retain(|p| now.saturating_duration_since(p.since) < PENDING_FOR);
        if state.pending.iter().filter(|p| p.source == source).count() >= MAX_PENDING_PER_SOURCE {
            return Err(ApiError::new(
                StatusCode::TOO_MANY_REQUESTS,
                format!(
                    "{MAX_PENDING_PER_SOURCE} key requests from {source} are waiting already; allow or deny them on the dashboard (or wait {} minutes)",
                    PENDING_FOR.as_secs() / 60
                ),
            ));
        }
        if state.pending.len() >= MAX_PENDING {
            return Err(ApiError::new(
                StatusCode::TOO_MANY_REQUESTS,
                format!(
                    "{MAX_PENDING} key requests are waiting already; allow or deny them on the dashboard (or wait {} minutes)",
                    PENDING_FOR.as_secs() / 60
                ),
            ));
        }
        let token = random_text(24);
        state.pending.push(Pending {
            id: random_text(6),
            token: token.clone(),
            app,
            source,
            instance,
            since: now,
            decision: Decision::Pending,
        });
        Ok(token)
    }

    /// What the client polling `token` is told; a final answer is told once.
    pub fn poll(&self, token: &str, now: Instant) -> Poll {
        let mut state = self.lock();
        let Some(at) = state.pending.iter().position(|p| {
            same(token.as_bytes(), p.token.as_bytes())
                && now.saturating_duration_since(p.since) < PENDING_FOR
        }) else {
            return Poll::Gone;
        };
        match state.pending[at].decision.clone() {
            Decision::Pending => Poll::Waiting,
            Decision::Allowed(key) => {
                state.pending.remove(at);
                Poll::Granted(key)
            }
            Decision::Denied => {
                state.pending.remove(at);
                Poll::Gone
            }
        }
    }

    /// Allows or denies the request `id`; an allowed one gets its key, stored durably
    /// before the client can fetch it. Blocking (writes the file).
    pub fn decide(&self, id: &str, allow: bool, now: Instant) -> Result<String, ApiError> {
        let mut state = self.lock();
        let Some(at) = state
            .pending
            .iter()
            .position(|p| p.id == id && now.saturating_duration_since(p.since) < PENDING_FOR)
        else {
            return Err(ApiError::not_found(format!(
                "no pending key request {} (hint: GET /api/v1/appkeys lists them; a request is forgotten after {} minutes)",
                quoted(id),
                PENDING_FOR.as_secs() / 60
            )));
        };
        if state.pending[at].decision != Decision::Pending {
            return Err(ApiError::conflict(format!(
                "key request {} was decided already",
                quoted(id)
            )));
        }
        let app = state.pending[at].app.clone();
        if !allow {
            state.pending[at].decision = Decision::Denied;
            return Ok(format!("denied a key to {app}"));
        }
        if state.keys.len() >= MAX_KEYS {
            return Err(ApiError::conflict(format!(
                "{MAX_KEYS} application keys exist already; revoke one first"
            )));
        }
        let secret = random_text(24);
        let key = AppKey {
            id: random_text(6),
            app: app.clone(),
            source: state.pending[at].source.clone(),
            instance: state.pending[at].instance.clone(),
            created_s: std::time::SystemTime::now()
                .duration_since(std::time::UNIX_EPOCH)
                .map_or(0, |d| d.as_secs()),
            secret: secret.clone(),
        };
        let mut keys = state.keys.clone();
        keys.push(key.clone());
        self.write(&keys)?;
        state.keys = keys;
        state.pending[at].decision = Decision::Allowed(secret);
        tracing::info!(app = %app, key = %key.id, "http: application key granted");
        Ok(format!("allowed {app} a key (id {})", key.id))
    }

    /// Revokes the key `id`. Blocking (writes the file).
    pub fn revoke(&self, id: &str) -> Result<String, ApiError> {
        let mut state = self.lock();
        let Some(at) = state.keys.iter().position(|k| k.id == id) else {
            return Err(ApiError::not_found(format!(
                "no application key {} (hint: GET /api/v1/appkeys lists them)",
                quoted(id)
            )));
        };
        let mut keys = state.keys.clone();
        let gone = keys.remove(at);
        self.write(&keys)?;
        state.keys = keys;
        tracing::info!(app = %gone.app, key = %gone.id, "http: application key revoked");
        Ok(format!("revoked the key of {} (id {})", gone.app, gone.id))
    }

    pub fn view(&self, now: Instant) -> KeysView {
        let state = self.lock();
        KeysView {
            pending: state
                .pending
                .iter()
                .filter(|p| now.saturating_duration_since(p.since) < PENDING_FOR)
                .map(|p| PendingView {
                    id: p.id.clone(),
                    app: p.app.clone(),
                    source: p.source.clone(),
                    instance: p.instance.clone(),
                    age_s: now.saturating_duration_since(p.since).as_secs(),
                    decision: match p.decision {
                        Decision::Pending => "pending",
                        Decision::Allowed(_) => "allowed",
                        Decision::Denied => "denied",
                    },
                })
                .collect(),
            keys: state
                .keys
                .iter()
                .map(|k| KeyView {
                    id: k.id.clone(),
                    app: k.app.clone(),
                    source: k.source.clone(),
                    instance: k.instance.clone(),
                    created_s: k.created_s,
                })
                .collect(),
        }
    }

    /// The key file, mode 0600 (it holds secrets), replaced atomically.
    fn write(&self, keys: &[AppKey]) -> Result<(), ApiError> {
        use std::io::Write;
        use std::os::unix::fs::PermissionsExt;
        let text = serde_json::to_vec_pretty(&serde_json::json!({ "keys": keys }))
            .expect("keys serialise");
        crate::fsutil::write_atomic_with(&self.path, |file| {
            file.set_permissions(std::fs::Permissions::from_mode(0o600))?;
            file.write_all(&text)
        })
        .map_err(|e| {
            tracing::error!(error = %e, "http: cannot store the application keys");
            ApiError::new(
                StatusCode::INTERNAL_SERVER_ERROR,
                format!("cannot store the application keys: {}", e.source.kind()),
            )
        })
    }
}

// ---- OctoPrint's plugin endpoints (no key needed: the client has none yet) ----

/// `GET plugin/appkeys/probe`: the flow is supported.
pub async fn probe() -> StatusCode {
    StatusCode::NO_CONTENT
}

#[derive(Debug, Deserialize)]
pub struct RequestBody {
    app: String,
    // OctoPrint's optional `user`; crispen has no users.
    #[serde(default)]
    #[allow(dead_code)]
    user: Option<String>,
}

/// `POST plugin/appkeys/request` with `{"app": "Name"}`: `201` with the poll address in
/// `Location` and `app_token`.
pub async fn request(
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
/// once allowed, `404` when denied or unknown.
pub async fn poll(
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
            "no such key request: it was denied, or has expired, or its key was fetched already",
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
pub fn origin(headers: &HeaderMap) -> String {
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
pub async fn list(State(state): State<AppState>) -> Json<KeysView> {
    Json(state.appkeys.view(Instant::now()))
}

/// `POST /api/v1/appkeys/requests/{id}/allow|deny` and `/api/v1/appkeys/keys/{id}/revoke`.
pub async fn act(
    State(state): State<AppState>,
    Path((kind, id, action)): Path<(String, String, String)>,
) -> Result<Json<serde_json::Value>, ApiError> {
    let keys = state.appkeys.clone();
    let done = tokio::task::spawn_blocking(move || match (kind.as_str(), action.as_str()) {
        ("requests", "allow") => keys.decide(&id, true, Instant::now()),
        ("requests", "deny") => keys.decide(&id, false, Instant::now()),
        ("keys", "revoke") => keys.revoke(&id),
        _ => Err(ApiError::not_found(format!(
            "no such action {}: the actions are requests/ID/allow, requests/ID/deny, keys/ID/revoke",
            quoted(&format!("{kind}/{id}/{action}"))
        ))),
    })
    .await
    .map_err(ApiError::from)??;
    tracing::info!(message = %done, "http: application keys");
    Ok(Json(serde_json::json!({ "ok": true, "message": done })))
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The flow: asked, listed, allowed (stored), fetched once; denied; bounded; revoked;
    /// kept across a restart; expired requests forgotten.
    #[test]
    fn requests_are_decided_fetched_once_and_keys_kept() {
        let dir = tempfile::tempdir().unwrap();
        let keys = AppKeys::open(dir.path()).unwrap();
        let t0 = Instant::now();
        let token = keys
            .request("Cura", "10.0.0.5".into(), "/".into(), t0)
            .unwrap();
        assert_eq!(keys.poll(&token, t0), Poll::Waiting);
        let view = keys.view(t0);
        assert_eq!(view.pending.len(), 1);
        assert_eq!(view.pending[0].app, "Cura");
        let id = view.pending[0].id.clone();
        assert!(!serde_json::to_string(&view).unwrap().contains(&token));
        keys.decide(&id, true, t0).unwrap();
        assert!(keys.decide(&id, false, t0).is_err(), "decided once");
        let Poll::Granted(secret) = keys.poll(&token, t0) else {
            panic!("granted")
        };
        assert_eq!(keys.poll(&token, t0), Poll::Gone, "fetched once");
        assert_eq!(keys.app_of(secret.as_bytes()).as_deref(), Some("Cura"));
        assert_eq!(keys.app_of(b"nope"), None);
        // Listed without the secret... but stored, 0600, and read again.
        let listed = serde_json::to_string(&keys.view(t0).keys).unwrap();
        assert!(listed.contains("Cura") && !listed.contains(&secret));
        let file = dir.path().join(FILE_NAME);
        use std::os::unix::fs::PermissionsExt;
        assert_eq!(
            std::fs::metadata(&file).unwrap().permissions().mode() & 0o777,
            0o600
        );
        let again = AppKeys::open(dir.path()).unwrap();
        assert_eq!(again.app_of(secret.as_bytes()).as_deref(), Some("Cura"));

        let denied = keys.request("Evil", "x".into(), "/".into(), t0).unwrap();
        let id = keys.view(t0).pending[0].id.clone();
        keys.decide(&id, false, t0).unwrap();
        assert_eq!(keys.poll(&denied, t0), Poll::Gone);

        for _ in 0..MAX_PENDING_PER_SOURCE {
            keys.request("a", "x".into(), "/".into(), t0).unwrap();
        }
        let e = keys.request("a", "x".into(), "/".into(), t0).unwrap_err();
        assert_eq!(e.status, StatusCode::TOO_MANY_REQUESTS);
        assert!(e.message.contains("from x"), "{}", e.message);
        for i in MAX_PENDING_PER_SOURCE..MAX_PENDING {
            keys.request("a", format!("y{i}"), "/".into(), t0).unwrap();
        }
        let e = keys.request("a", "z".into(), "/".into(), t0).unwrap_err();
        assert_eq!(e.status, StatusCode::TOO_MANY_REQUESTS);
        // Expired ones make room.
        let later = t0 + PENDING_FOR + Duration::from_secs(1);
        keys.request("a", "x".into(), "/".into(), later).unwrap();
        assert_eq!(keys.view(later).pending.len(), 1);
        assert!(keys.request("  ", "x".into(), "/".into(), later).is_err());

        let key_id = keys.view(t0).keys[0].id.clone();
        keys.revoke(&key_id).unwrap();
        assert_eq!(keys.app_of(secret.as_bytes()), None);
        assert!(keys.revoke(&key_id).is_err());
        assert_eq!(AppKeys::open(dir.path()).unwrap().view(t0).keys.len(), 0);

        std::fs::write(&file, "{not json").unwrap();
        let e = AppKeys::open(dir.path()).unwrap_err();
        assert!(e.to_string().contains("appkeys.json"), "{e}");
    }
}
