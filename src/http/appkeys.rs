//! Application keys, as OctoPrint's `appkeys` plugin hands them out: a client (Cura's
//! OctoPrint connection) asks for a key of its own (`POST plugin/appkeys/request` with its
//! name), polls the address it was given, and the operator allows or denies the request on
//! the dashboard (or `crispen keys`). An allowed client gets a random key that it alone
//! holds, listed by its application's name and revocable one by one, so no slicer ever
//! needs the farm's `[http]` key.
//!
//! An application key opens the OctoPrint emulation only (`/api/...` outside `/api/v1/`,
//! `/octoprint/...`), never the farm's operator API, and within it only what its
//! [`Scope`] says, which the operator chose when allowing it (and may change):
//! - **where**: the OctoPrint instance it was asked on (`/octoprint/<folder>/`, or the
//!   root `/`, which then uploads to the root's default folder only), or, with
//!   `everywhere`, every instance of the farm;
//! - **what**: `upload` (the default) reads the instance's state, uploads, and prints its
//!   own uploads: "upload and print", and the select-and-print of a file it uploaded
//!   without `print`; `control` adds `POST api/job` (pause, resume, cancel the
//!   instance's print).
//!
//! No application key ever releases a job that a sidecar or the operator held: the
//! sidecar of an upload held for its select-and-print carries a mark (see
//! [`AppKeys::hold_mark`]) that only the key which uploaded it can produce, and the
//! select-and-print of an application key releases only a job whose sidecar has its mark.
//! Keys stored before scopes existed have none in the file: they load with the narrowest
//! one (upload, on their own instance).
//!
//! Keys are kept in `appkeys.json` in the spool directory (mode 0600, written with
//! `fsutil::write_atomic_with`). Pending requests live in memory only, and a request
//! leaves the list as soon as it no longer waits: decided (an allowed one's key waits,
//! outside the list, for its client to fetch it), expired ([`PENDING_FOR`]), or abandoned
//! by its client (not polled for [`ABANDONED_AFTER`], as OctoPrint forgets them). At most
//! [`MAX_PENDING`] wait at once, [`MAX_PENDING_PER_SOURCE`] from one address.
//!
//! One owner: the state is behind one lock, held for a lookup or a change and the
//! synchronous write of the file (on a blocking thread), never across an await.

use super::error::quoted;
use super::instance::Instance;
use super::ApiError;
use crate::daemon::config::{Config, FolderConfig};
use axum::http::StatusCode;
use serde::{Deserialize, Serialize};
use std::path::PathBuf;
use std::sync::Mutex;
use std::time::{Duration, Instant};

/// Requests waiting for the operator's decision at once.
pub(crate) const MAX_PENDING: usize = 16;
/// Requests from one address waiting at once: one client cannot take every place, and a
/// client needs one (two: a retry while the first is still listed).
pub(crate) const MAX_PENDING_PER_SOURCE: usize = 2;
/// A request not decided within this is forgotten; an allowed key not fetched within
/// this after the decision is not told any more (the key stays, revocable).
pub(crate) const PENDING_FOR: Duration = Duration::from_secs(10 * 60);
/// A request whose client has not polled for this long is forgotten: the client gave up
/// (Cura polls every second; OctoPrint forgets a request after 5 s without a poll).
pub(crate) const ABANDONED_AFTER: Duration = Duration::from_secs(60);
/// Application keys kept at most; revoke one to make room.
pub(crate) const MAX_KEYS: usize = 64;
/// Longest application name kept (longer ones are cut).
const MAX_APP_CHARS: usize = 64;
/// The file in the spool directory.
pub(crate) const FILE_NAME: &str = "appkeys.json";
/// Largest key file read.
const MAX_FILE_BYTES: u64 = 1024 * 1024;
/// How the hold mark starts its line in a held upload's sidecar (a TOML comment: the
/// sidecar's keys stay what they are).
pub(crate) const HOLD_MARK_PREFIX: &str =
    "# held for the select-and-print of an OctoPrint upload: ";

/// What an application key may do, and where; chosen by the operator when allowing it.
/// The default (also for keys stored before scopes existed) is the narrowest: upload,
/// on the instance it was asked on.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub(crate) struct Scope {
    /// Also `POST api/job`: pause, resume, cancel the instance's print.
    pub control: bool,
    /// Every instance of the farm, not just the one it was asked on.
    pub everywhere: bool,
}

impl Scope {
    /// `upload` or `upload, control`, then where: as listings show it.
    pub(crate) fn describe(&self, instance: &str) -> String {
        format!(
            "{} {}",
            if self.control {
                "upload, control"
            } else {
                "upload"
            },
            if self.everywhere {
                "everywhere".to_string()
            } else {
                format!("on {instance}")
            }
        )
    }
}

/// Who a request's key is: the operator (`[http]` key, or the control socket) or an
/// application that was given a key of its own.
#[derive(Debug, Clone, PartialEq, Eq)]
pub(crate) enum Who {
    Operator,
    App(Grant),
}

/// An application key as a request presents it: whose it is and what it opens.
#[derive(Debug, Clone, PartialEq, Eq)]
pub(crate) struct Grant {
    /// The key's id (not its secret).
    pub id: String,
    pub app: String,
    /// The instance it was asked on (`/` or `/octoprint/<folder>/`).
    pub instance: String,
    pub scope: Scope,
}

/// Why a key may not do something: the client's `403`, and one log line naming the key.
fn refuse(grant: &Grant, what: &str, hint: String) -> ApiError {
    tracing::warn!(
        app = %grant.app, key = %grant.id, scope = %grant.scope.describe(&grant.instance),
        refused = %what, "http: application key refused"
    );
    ApiError::new(
        StatusCode::FORBIDDEN,
        format!(
            "the application key of {} (id {}, scope: {}) may not {what}; {hint}",
            grant.app,
            grant.id,
            grant.scope.describe(&grant.instance)
        ),
    )
}

impl Grant {
    /// The folder the key's own instance names (None: the root instance).
    fn own_folder(&self) -> Option<String> {
        Instance::parse(&self.instance).folder
    }

    /// Whether the key opens the instance `path` addresses; refused with the way to
    /// widen it.
    pub(crate) fn check_instance(&self, path: &str) -> Result<(), ApiError> {
        let asked = Instance::parse(path);
        if self.scope.everywhere || asked.folder == self.own_folder() {
            return Ok(());
        }
        Err(refuse(
            self,
            &format!("use the OctoPrint instance {}", asked.base),
            format!(
                "it was allowed on {} only (the operator lets it use every instance with `crispen keys allow {} --everywhere`, or the dashboard)",
                self.instance, self.id
            ),
        ))
    }

    /// Whether the key may put a file into `folder` through `instance` (which
    /// [`Grant::check_instance`] let through): on the root instance, a key of the root's
    /// own uploads into its default folder only (the root's `path` names any folder).
    pub(crate) fn check_folder(
        &self,
        config: &Config,
        instance: &Instance,
        folder: &FolderConfig,
    ) -> Result<(), ApiError> {
        if self.scope.everywhere || instance.folder.is_some() {
            return Ok(());
        }
        let default = super::instance::default_folder(config).map(|f| &f.path);
        if default == Some(&folder.path) {
            return Ok(());
        }
        Err(refuse(
            self,
            &format!(
                "upload into hot folder {} through the root instance",
                super::upload::folder_name(folder)
            ),
            format!(
                "on the root it uploads into the default folder only (the operator lets it use every folder with `crispen keys allow {} --everywhere`)",
                self.id
            ),
        ))
    }

    /// Whether the key may control prints (`POST api/job`).
    pub(crate) fn check_control(&self, what: &str) -> Result<(), ApiError> {
        if self.scope.control {
            return Ok(());
        }
        Err(refuse(
            self,
            what,
            format!(
                "its scope is upload only (the operator gives it control with `crispen keys allow {} --control`, or the dashboard's \"Allow with control\")",
                self.id
            ),
        ))
    }

    /// Refuses releasing job `job`, which a sidecar or the operator held.
    pub(crate) fn refuse_release(&self, job: &str, file: &str) -> ApiError {
        refuse(
            self,
            &format!("print job {job} ({file})"),
            "that job is held by its sidecar or by the operator, not by an upload of this key; only the operator releases it (the dashboard's Print button, `crispen release JOB`)".to_string(),
        )
    }
}

/// A key handed to an application.
#[derive(Debug, Clone, Serialize, Deserialize, PartialEq)]
#[serde(deny_unknown_fields)]
pub(crate) struct AppKey {
    /// Names the key in lists and for revoking; not the key.
    pub id: String,
    pub app: String,
    /// Where the request came from.
    pub source: String,
    /// The OctoPrint instance it was asked on (`/` or `/octoprint/<folder>/`).
    pub instance: String,
    /// When it was granted, seconds since the Unix epoch.
    pub created_s: u64,
    /// What it opens; absent in keys stored before scopes existed: the narrowest.
    #[serde(default)]
    pub scope: Scope,
    /// The secret; only ever shown to the client that asked, once.
    #[serde(rename = "key")]
    secret: String,
}

impl AppKey {
    fn grant(&self) -> Grant {
        Grant {
            id: self.id.clone(),
            app: self.app.clone(),
            instance: self.instance.clone(),
            scope: self.scope,
        }
    }
}

#[derive(Debug, Default, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
struct KeyFile {
    keys: Vec<AppKey>,
}

/// A request waiting for the operator's decision.
#[derive(Debug)]
struct Pending {
    id: String,
    /// The poll address's secret part; never listed.
    token: String,
    app: String,
    source: String,
    instance: String,
    since: Instant,
    /// The client's last poll (or its request).
    polled: Instant,
}

impl Pending {
    /// Still waiting at `now`: neither expired nor abandoned by its client.
    fn live(&self, now: Instant) -> bool {
        now.saturating_duration_since(self.since) < PENDING_FOR
            && now.saturating_duration_since(self.polled) < ABANDONED_AFTER
    }

    /// When it stops waiting unless decided or polled.
    fn ends_in(&self, now: Instant) -> Duration {
        let expiry = PENDING_FOR.saturating_sub(now.saturating_duration_since(self.since));
        let abandoned = ABANDONED_AFTER.saturating_sub(now.saturating_duration_since(self.polled));
        expiry.min(abandoned)
    }
}

/// An allowed request's key, waiting for its client's next poll (outside the pending
/// list: it takes no place there).
#[derive(Debug)]
struct Answer {
    token: String,
    secret: String,
    since: Instant,
}

/// What a poll finds.
#[derive(Debug, PartialEq)]
pub(crate) enum Poll {
    Waiting,
    Granted(String),
    /// Denied, expired, abandoned, fetched already, or never asked.
    Gone,
}

/// A pending request as the dashboard lists it.
#[derive(Debug, Serialize)]
pub(crate) struct PendingView {
    pub id: String,
    pub app: String,
    pub source: String,
    pub instance: String,
    pub age_s: u64,
    /// Always "pending": a decided request leaves the list (kept for older dashboards).
    pub decision: &'static str,
}

/// Everything the dashboard shows: requests and keys (without their secrets).
#[derive(Debug, Serialize)]
pub(crate) struct KeysView {
    pub pending: Vec<PendingView>,
    pub keys: Vec<KeyView>,
}

/// A key as listed: everything but its secret.
#[derive(Debug, Serialize)]
pub(crate) struct KeyView {
    pub id: String,
    pub app: String,
    pub source: String,
    pub instance: String,
    pub created_s: u64,
    pub scope: Scope,
    /// The scope in words: "upload on /octoprint/gc/", "upload, control everywhere".
    pub scope_text: String,
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
    answers: Vec<Answer>,
}

impl Keys {
    /// Drops what no longer waits.
    fn prune(&mut self, now: Instant) {
        self.pending.retain(|p| p.live(now));
        self.answers
            .retain(|a| now.saturating_duration_since(a.since) < PENDING_FOR);
    }
}

fn random_text(bytes: usize) -> String {
    use base64::Engine;
    let raw: Vec<u8> = (0..bytes).map(|_| rand::random::<u8>()).collect();
    base64::engine::general_purpose::URL_SAFE_NO_PAD.encode(raw)
}

/// An id for a request or key: eight lower-case letters and digits, so that it never
/// reads as an option on a command line (`crispen keys allow ID`; a base64 id may start
/// with `-`) nor needs quoting.
fn random_id() -> String {
    const ALPHABET: &[u8] = b"abcdefghijkmnpqrstuvwxyz23456789";
    (0..8)
        .map(|_| ALPHABET[usize::from(rand::random::<u8>()) % ALPHABET.len()] as char)
        .collect()
}

/// Compares in time independent of where the texts differ.
fn same(given: &[u8], key: &[u8]) -> bool {
    subtle::ConstantTimeEq::ct_eq(given, key).into()
}

/// The signature in a hold mark: only the key's secret makes it, for this key, this
/// upload (`nonce`) and this hot folder. (Not the file's name: the job's name is the
/// upload's as the spool spells it, and the job is found by that name anyway.)
fn hold_signature(secret: &str, key_id: &str, nonce: &str, folder: &std::path::Path) -> String {
    use std::os::unix::ffi::OsStrExt;
    let mut text = b"crispen octoprint hold\0".to_vec();
    for part in [
        key_id.as_bytes(),
        nonce.as_bytes(),
        folder.as_os_str().as_bytes(),
    ] {
        text.extend_from_slice(part);
        text.push(0);
    }
    crate::notify::wire::sign(secret.as_bytes(), &text)
}

impl AppKeys {
    /// Reads `spool_dir/appkeys.json` (none: no keys yet).
    pub(crate) fn open(spool_dir: &std::path::Path) -> Result<AppKeys, AppKeysError> {
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
                ..Keys::default()
            }),
        })
    }

    fn lock(&self) -> std::sync::MutexGuard<'_, Keys> {
        self.state.lock().unwrap_or_else(|e| e.into_inner())
    }

    /// The key `given` is, if it is one of the keys: who holds it and what it opens.
    pub(crate) fn grant_of(&self, given: &[u8]) -> Option<Grant> {
        let state = self.lock();
        // Every key compared, whichever matches.
        let mut found = None;
        for k in &state.keys {
            if same(given, k.secret.as_bytes()) {
                found = Some(k.grant());
            }
        }
        found
    }

    /// The application a key was given to, if it is one of the keys.
    #[cfg(test)]
    pub(crate) fn app_of(&self, given: &[u8]) -> Option<String> {
        self.grant_of(given).map(|g| g.app)
    }

    /// A new request; its poll token. Requests that no longer wait are dropped first.
    pub(crate) fn request(
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
        state.prune(now);
        // What frees a place: the operator's decision, at once; else the first of them
        // to expire (or be abandoned by its client).
        let next_free = |of: &mut dyn Iterator<Item = &Pending>| {
            of.map(|p| p.ends_in(now))
                .min()
                .unwrap_or_default()
                .as_secs()
                + 1
        };
        let mine = state.pending.iter().filter(|p| p.source == source).count();
        if mine >= MAX_PENDING_PER_SOURCE {
            let wait = next_free(&mut state.pending.iter().filter(|p| p.source == source));
            tracing::warn!(%source, app = %app, "http: key request refused: {mine} from this address wait already");
            return Err(ApiError::new(
                StatusCode::TOO_MANY_REQUESTS,
                format!(
                    "{mine} key requests from {source} are waiting for the operator's decision already (at most {MAX_PENDING_PER_SOURCE} from one address): \
                     the operator allowing or denying one (dashboard, Application keys; `crispen keys`) frees its place at once; \
                     otherwise one is forgotten in {wait} s (not polled for {} s, or {} minutes old). Keep polling the request already made rather than asking again",
                    ABANDONED_AFTER.as_secs(),
                    PENDING_FOR.as_secs() / 60
                ),
            ));
        }
        if state.pending.len() >= MAX_PENDING {
            let wait = next_free(&mut state.pending.iter());
            tracing::warn!(%source, app = %app, "http: key request refused: {MAX_PENDING} wait already");
            return Err(ApiError::new(
                StatusCode::TOO_MANY_REQUESTS,
                format!(
                    "{MAX_PENDING} key requests are waiting for the operator's decision already: \
                     the operator allowing or denying them (dashboard, Application keys; `crispen keys`) frees their places at once; \
                     otherwise one is forgotten in {wait} s"
                ),
            ));
        }
        let token = random_text(24);
        state.pending.push(Pending {
            id: random_id(),
            token: token.clone(),
            app,
            source,
            instance,
            since: now,
            polled: now,
        });
        Ok(token)
    }

    /// What the client polling `token` is told; a key is told once.
    pub(crate) fn poll(&self, token: &str, now: Instant) -> Poll {
        let mut state = self.lock();
        state.prune(now);
        // Every entry compared, whichever matches.
        let mut waiting = None;
        for (i, p) in state.pending.iter().enumerate() {
            if same(token.as_bytes(), p.token.as_bytes()) {
                waiting = Some(i);
            }
        }
        if let Some(i) = waiting {
            state.pending[i].polled = now;
            return Poll::Waiting;
        }
        let mut answered = None;
        for (i, a) in state.answers.iter().enumerate() {
            if same(token.as_bytes(), a.token.as_bytes()) {
                answered = Some(i);
            }
        }
        match answered {
            Some(i) => Poll::Granted(state.answers.remove(i).secret),
            None => Poll::Gone,
        }
    }

    /// Allows (with `scope`) or denies the request `id`; either way it leaves the pending
    /// list at once. An allowed one gets its key, stored durably before the client can
    /// fetch it. Blocking (writes the file).
    pub(crate) fn decide(
        &self,
        id: &str,
        allow: Option<Scope>,
        now: Instant,
    ) -> Result<String, ApiError> {
        let mut state = self.lock();
        state.prune(now);
        let Some(at) = state.pending.iter().position(|p| p.id == id) else {
            return Err(ApiError::not_found(format!(
                "no pending key request {} (hint: GET /api/v1/appkeys lists them; a request leaves the list once decided, after {} minutes, or when its client stops asking for {} s)",
                quoted(id),
                PENDING_FOR.as_secs() / 60,
                ABANDONED_AFTER.as_secs()
            )));
        };
        let Some(scope) = allow else {
            let gone = state.pending.remove(at);
            tracing::info!(app = %gone.app, source = %gone.source, "http: application key denied");
            return Ok(format!("denied a key to {}", gone.app));
        };
        if state.keys.len() >= MAX_KEYS {
            return Err(ApiError::conflict(format!(
                "{MAX_KEYS} application keys exist already; revoke one first"
            )));
        }
        let request = &state.pending[at];
        let key = AppKey {
            id: random_id(),
            app: request.app.clone(),
            source: request.source.clone(),
            instance: request.instance.clone(),
            created_s: std::time::SystemTime::now()
                .duration_since(std::time::UNIX_EPOCH)
                .map_or(0, |d| d.as_secs()),
            scope,
            secret: random_text(24),
        };
        let mut keys = state.keys.clone();
        keys.push(key.clone());
        self.write(&keys)?;
        state.keys = keys;
        let request = state.pending.remove(at);
        state.answers.push(Answer {
            token: request.token,
            secret: key.secret.clone(),
            since: now,
        });
        let scope = key.scope.describe(&key.instance);
        tracing::info!(app = %key.app, key = %key.id, %scope, "http: application key granted");
        Ok(format!(
            "allowed {} a key (id {}; {scope})",
            key.app, key.id
        ))
    }

    /// Sets the scope of key `id` (wider or narrower). Blocking (writes the file).
    pub(crate) fn set_scope(&self, id: &str, scope: Scope) -> Result<String, ApiError> {
        let mut state = self.lock();
        let Some(at) = state.keys.iter().position(|k| k.id == id) else {
            return Err(no_key(id));
        };
        let mut keys = state.keys.clone();
        keys[at].scope = scope;
        self.write(&keys)?;
        state.keys = keys;
        let key = &state.keys[at];
        let scope = key.scope.describe(&key.instance);
        tracing::info!(app = %key.app, key = %key.id, %scope, "http: application key's scope set");
        Ok(format!(
            "the key of {} (id {}) may now: {scope}",
            key.app, key.id
        ))
    }

    /// Revokes the key `id`. Blocking (writes the file).
    pub(crate) fn revoke(&self, id: &str) -> Result<String, ApiError> {
        let mut state = self.lock();
        let Some(at) = state.keys.iter().position(|k| k.id == id) else {
            return Err(no_key(id));
        };
        let mut keys = state.keys.clone();
        let gone = keys.remove(at);
        self.write(&keys)?;
        state.keys = keys;
        tracing::info!(app = %gone.app, key = %gone.id, "http: application key revoked");
        Ok(format!("revoked the key of {} (id {})", gone.app, gone.id))
    }

    /// The line a held upload's sidecar carries so that the key `grant` (and no other)
    /// may release the job it becomes: a fresh nonce and a signature made with the key's
    /// secret over key, nonce and hot folder. Nothing is remembered: the mark proves
    /// itself while the key exists, across restarts. None: the key is gone.
    pub(crate) fn hold_mark(&self, grant: &Grant, folder: &std::path::Path) -> Option<String> {
        let state = self.lock();
        let key = state.keys.iter().find(|k| k.id == grant.id)?;
        let nonce = random_text(12);
        let signature = hold_signature(&key.secret, &key.id, &nonce, folder);
        Some(format!(
            "{HOLD_MARK_PREFIX}{}.{nonce}.{signature}\n",
            key.id
        ))
    }

    /// Whether `sidecar` (a job's sidecar text) carries the hold mark of `grant`'s own
    /// upload into `folder`.
    pub(crate) fn held_by(&self, grant: &Grant, sidecar: &str, folder: &std::path::Path) -> bool {
        let Some(mark) = sidecar
            .lines()
            .find_map(|l| l.strip_prefix(HOLD_MARK_PREFIX))
            .map(str::trim)
        else {
            return false;
        };
        let mut parts = mark.splitn(3, '.');
        let (Some(key_id), Some(nonce), Some(signature)) =
            (parts.next(), parts.next(), parts.next())
        else {
            return false;
        };
        if key_id != grant.id {
            return false;
        }
        let state = self.lock();
        let Some(key) = state.keys.iter().find(|k| k.id == key_id) else {
            return false;
        };
        same(
            signature.as_bytes(),
            hold_signature(&key.secret, key_id, nonce, folder).as_bytes(),
        )
    }

    pub(crate) fn view(&self, now: Instant) -> KeysView {
        let mut state = self.lock();
        state.prune(now);
        KeysView {
            pending: state
                .pending
                .iter()
                .map(|p| PendingView {
                    id: p.id.clone(),
                    app: p.app.clone(),
                    source: p.source.clone(),
                    instance: p.instance.clone(),
                    age_s: now.saturating_duration_since(p.since).as_secs(),
                    decision: "pending",
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
                    scope: k.scope,
                    scope_text: k.scope.describe(&k.instance),
                })
                .collect(),
        }
    }

    /// The key file, mode 0600 (it holds secrets), replaced atomically.
    fn write(&self, keys: &[AppKey]) -> Result<(), ApiError> {
        use std::io::Write;
        use std::os::unix::fs::PermissionsExt;
        let text =
            serde_json::to_vec_pretty(&serde_json::json!({ "keys": keys })).map_err(|e| {
                ApiError::new(
                    StatusCode::INTERNAL_SERVER_ERROR,
                    format!("cannot store the application keys: {e}"),
                )
            })?;
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

fn no_key(id: &str) -> ApiError {
    ApiError::not_found(format!(
        "no application key {} (hint: GET /api/v1/appkeys lists them)",
        quoted(id)
    ))
}

#[cfg(test)]
mod tests {
    use super::*;

    fn request(keys: &AppKeys, app: &str, source: &str, instance: &str, at: Instant) -> String {
        keys.request(app, source.into(), instance.into(), at)
            .unwrap()
    }

    fn pending_id(keys: &AppKeys, app: &str, at: Instant) -> String {
        keys.view(at)
            .pending
            .iter()
            .find(|p| p.app == app)
            .unwrap()
            .id
            .clone()
    }

    /// The flow: asked, listed, allowed (stored), fetched once; kept across a restart;
    /// revoked.
    #[test]
    fn requests_are_decided_fetched_once_and_keys_kept() {
        let dir = tempfile::tempdir().unwrap();
        let keys = AppKeys::open(dir.path()).unwrap();
        let t0 = Instant::now();
        let token = request(&keys, "Cura", "10.0.0.5", "/", t0);
        assert_eq!(keys.poll(&token, t0), Poll::Waiting);
        let view = keys.view(t0);
        assert_eq!(view.pending.len(), 1);
        assert_eq!(view.pending[0].app, "Cura");
        let id = view.pending[0].id.clone();
        assert!(!serde_json::to_string(&view).unwrap().contains(&token));
        keys.decide(&id, Some(Scope::default()), t0).unwrap();
        assert!(keys.view(t0).pending.is_empty(), "decided: off the list");
        assert!(keys.decide(&id, None, t0).is_err(), "decided once");
        let Poll::Granted(secret) = keys.poll(&token, t0) else {
            panic!("granted")
        };
        assert_eq!(keys.poll(&token, t0), Poll::Gone, "fetched once");
        assert_eq!(keys.app_of(secret.as_bytes()).as_deref(), Some("Cura"));
        assert_eq!(keys.app_of(b"nope"), None);
        // Listed without the secret, with its scope... but stored, 0600, and read again.
        let view = keys.view(t0);
        let listed = serde_json::to_string(&view.keys).unwrap();
        assert!(listed.contains("Cura") && !listed.contains(&secret));
        assert_eq!(view.keys[0].scope_text, "upload on /");
        let file = dir.path().join(FILE_NAME);
        use std::os::unix::fs::PermissionsExt;
        assert_eq!(
            std::fs::metadata(&file).unwrap().permissions().mode() & 0o777,
            0o600
        );
        let again = AppKeys::open(dir.path()).unwrap();
        assert_eq!(again.app_of(secret.as_bytes()).as_deref(), Some("Cura"));

        let key_id = view.keys[0].id.clone();
        keys.revoke(&key_id).unwrap();
        assert_eq!(keys.app_of(secret.as_bytes()), None);
        assert!(keys.revoke(&key_id).is_err());
        assert_eq!(AppKeys::open(dir.path()).unwrap().view(t0).keys.len(), 0);

        std::fs::write(&file, "{not json").unwrap();
        let e = AppKeys::open(dir.path()).unwrap_err();
        assert!(e.to_string().contains("appkeys.json"), "{e}");
    }

    /// A place in the list is freed the moment a request stops waiting: denied, allowed,
    /// abandoned by its client, expired. The 429 says what frees one.
    #[test]
    fn requests_free_their_places_at_once() {
        let dir = tempfile::tempdir().unwrap();
        let keys = AppKeys::open(dir.path()).unwrap();
        let t0 = Instant::now();
        // Sixteen requests from eight addresses, all denied: sixteen places free again.
        for round in 0..3 {
            for i in 0..MAX_PENDING {
                let source = format!("10.0.0.{}", i / MAX_PENDING_PER_SOURCE);
                request(&keys, &format!("a{i}"), &source, "/", t0);
            }
            let e = keys
                .request("b", "10.9.9.9".into(), "/".into(), t0)
                .unwrap_err();
            assert_eq!(e.status, StatusCode::TOO_MANY_REQUESTS, "round {round}");
            assert!(e.message.contains("allowing or denying"), "{}", e.message);
            for p in keys.view(t0).pending {
                keys.decide(&p.id, None, t0).unwrap();
            }
            assert!(keys.view(t0).pending.is_empty());
        }
        // A denied request's poll finds nothing, at once.
        let denied = request(&keys, "Evil", "x", "/", t0);
        keys.decide(&pending_id(&keys, "Evil", t0), None, t0)
            .unwrap();
        assert_eq!(keys.poll(&denied, t0), Poll::Gone);

        // Per address: two wait at once; the third is told what helps.
        let first = request(&keys, "a", "x", "/", t0);
        request(&keys, "b", "x", "/", t0);
        let e = keys.request("c", "x".into(), "/".into(), t0).unwrap_err();
        assert_eq!(e.status, StatusCode::TOO_MANY_REQUESTS);
        assert!(e.message.contains("from x"), "{}", e.message);
        assert!(
            e.message.contains("frees its place at once"),
            "{}",
            e.message
        );
        assert!(
            e.message
                .contains(&format!("forgotten in {} s", ABANDONED_AFTER.as_secs() + 1)),
            "{}",
            e.message
        );
        // Another address is not held up by that.
        request(&keys, "d", "y", "/", t0);
        // Allowing one frees its place too (its key waits outside the list).
        keys.decide(&pending_id(&keys, "a", t0), Some(Scope::default()), t0)
            .unwrap();
        request(&keys, "c", "x", "/", t0);
        assert!(matches!(keys.poll(&first, t0), Poll::Granted(_)));

        // A client that keeps polling keeps its place; one that stopped loses it.
        let t1 = t0 + ABANDONED_AFTER / 2;
        let kept = keys.request("e", "z".into(), "/".into(), t0).unwrap();
        assert_eq!(keys.poll(&kept, t1), Poll::Waiting);
        let t2 = t0 + ABANDONED_AFTER + Duration::from_secs(1);
        let view = keys.view(t2);
        assert_eq!(
            view.pending
                .iter()
                .map(|p| p.app.as_str())
                .collect::<Vec<_>>(),
            ["e"],
            "the others were not polled"
        );
        // And expiry ends even a polled one.
        let mut t = t2;
        while t < t0 + PENDING_FOR {
            assert_eq!(keys.poll(&kept, t), Poll::Waiting);
            t += ABANDONED_AFTER / 2;
        }
        assert_eq!(keys.poll(&kept, t0 + PENDING_FOR), Poll::Gone);
        assert!(keys.view(t0 + PENDING_FOR).pending.is_empty());
        assert!(keys.request("  ", "x".into(), "/".into(), t).is_err());
    }

    /// Scopes: set when allowing, changed later, shown, and checked: the instance, the
    /// root's folder, control.
    #[test]
    fn scopes_are_given_and_checked() {
        let dir = tempfile::tempdir().unwrap();
        let keys = AppKeys::open(dir.path()).unwrap();
        let t0 = Instant::now();
        let token = request(&keys, "Cura", "a", "/octoprint/gc/", t0);
        keys.decide(&pending_id(&keys, "Cura", t0), Some(Scope::default()), t0)
            .unwrap();
        let Poll::Granted(secret) = keys.poll(&token, t0) else {
            panic!("granted")
        };
        let grant = keys.grant_of(secret.as_bytes()).unwrap();
        assert_eq!(grant.scope, Scope::default());
        assert!(
            grant.id.len() == 8 && grant.id.bytes().all(|b| b.is_ascii_alphanumeric()),
            "an id never reads as an option: {}",
            grant.id
        );
        assert!(grant
            .check_instance("/octoprint/gc/api/files/local")
            .is_ok());
        assert!(
            grant.check_instance("/octoprint/g%63/api/job").is_ok(),
            "the same folder, spelt otherwise"
        );
        let e = grant
            .check_instance("/octoprint/um/api/files/local")
            .unwrap_err();
        assert_eq!(e.status, StatusCode::FORBIDDEN);
        assert!(
            e.message
                .contains(&format!("crispen keys allow {} --everywhere", grant.id)),
            "{}",
            e.message
        );
        assert!(
            grant.check_instance("/api/files/local").is_err(),
            "nor the root"
        );
        let e = grant.check_control("pause the print").unwrap_err();
        assert!(
            e.message
                .contains(&format!("crispen keys allow {} --control", grant.id)),
            "{}",
            e.message
        );

        let both = Scope {
            control: true,
            everywhere: true,
        };
        let said = keys.set_scope(&grant.id, both).unwrap();
        assert!(said.contains("upload, control everywhere"), "{said}");
        let grant = keys.grant_of(secret.as_bytes()).unwrap();
        assert!(grant.check_instance("/octoprint/um/api/job").is_ok());
        assert!(grant.check_instance("/api/job").is_ok());
        assert!(grant.check_control("pause").is_ok());
        // Stored: read again with it.
        let again = AppKeys::open(dir.path()).unwrap();
        assert_eq!(again.grant_of(secret.as_bytes()).unwrap().scope, both);
        assert!(keys.set_scope("nope", both).is_err());

        // Allowed with control, on its instance only.
        let token = request(&keys, "HA", "b", "/", t0);
        let control = Scope {
            control: true,
            everywhere: false,
        };
        keys.decide(&pending_id(&keys, "HA", t0), Some(control), t0)
            .unwrap();
        let Poll::Granted(secret) = keys.poll(&token, t0) else {
            panic!("granted")
        };
        let grant = keys.grant_of(secret.as_bytes()).unwrap();
        assert_eq!(grant.scope, control);
        assert!(grant.check_instance("/api/job").is_ok());
        assert!(grant.check_instance("/octoprint/gc/api/job").is_err());
        let listed = keys.view(t0);
        assert_eq!(
            listed
                .keys
                .iter()
                .find(|k| k.app == "HA")
                .unwrap()
                .scope_text,
            "upload, control on /"
        );
    }

    /// Keys written before scopes existed load with the narrowest scope.
    #[test]
    fn keys_stored_without_a_scope_load_narrow() {
        let dir = tempfile::tempdir().unwrap();
        std::fs::write(
            dir.path().join(FILE_NAME),
            r#"{"keys": [{"id": "k1", "app": "Cura", "source": "10.0.0.5",
                "instance": "/octoprint/gc/", "created_s": 1700000000, "key": "s3cr3t-s3cr3t"}]}"#,
        )
        .unwrap();
        let keys = AppKeys::open(dir.path()).unwrap();
        let grant = keys.grant_of(b"s3cr3t-s3cr3t").unwrap();
        assert_eq!(
            grant.scope,
            Scope {
                control: false,
                everywhere: false
            }
        );
        assert!(grant.check_instance("/octoprint/um/api/job").is_err());
        assert_eq!(
            keys.view(Instant::now()).keys[0].scope_text,
            "upload on /octoprint/gc/"
        );
    }

    /// A hold mark releases for its own key and folder only.
    #[test]
    fn hold_marks_belong_to_one_key_and_folder() {
        let dir = tempfile::tempdir().unwrap();
        let keys = AppKeys::open(dir.path()).unwrap();
        let t0 = Instant::now();
        let mut grants = Vec::new();
        for app in ["Cura", "Orca"] {
            let token = request(&keys, app, app, "/", t0);
            keys.decide(&pending_id(&keys, app, t0), Some(Scope::default()), t0)
                .unwrap();
            let Poll::Granted(secret) = keys.poll(&token, t0) else {
                panic!("granted")
            };
            grants.push(keys.grant_of(secret.as_bytes()).unwrap());
        }
        let folder = std::path::Path::new("/farm/hot");
        let mark = keys.hold_mark(&grants[0], folder).unwrap();
        let sidecar = format!("hold = true\n{mark}");
        assert!(keys.held_by(&grants[0], &sidecar, folder));
        assert!(!keys.held_by(&grants[1], &sidecar, folder), "another key");
        assert!(!keys.held_by(&grants[0], &sidecar, std::path::Path::new("/farm/um")));
        assert!(
            !keys.held_by(&grants[0], "hold = true\n", folder),
            "the operator's hold"
        );
        let forged = sidecar.replace(&mark[mark.len() - 9..mark.len() - 1], "00000000");
        assert!(!keys.held_by(&grants[0], &forged, folder));
        // Another key's mark, made with the other key's id written in: not its secret.
        let other = keys.hold_mark(&grants[1], folder).unwrap();
        let claimed = other.replacen(&grants[1].id, &grants[0].id, 1);
        assert!(!keys.held_by(&grants[0], &format!("hold = true\n{claimed}"), folder));
        keys.revoke(&grants[0].id).unwrap();
        assert!(!keys.held_by(&grants[0], &sidecar, folder), "revoked");
    }
}
