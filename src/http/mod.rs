//! The operator's window: one HTTP API (JSON under `/api/v1/`, server-sent events), the
//! web dashboard at `/`, Prometheus metrics at `/metrics`, and the part of OctoPrint's API
//! that slicers use to "Send to printer". Served on two listeners: always on the control
//! socket (whose file mode decides who may use it; the CLI speaks to it), and on TCP when
//! `[http] listen` is configured (where the API key decides).
//!
//! - [`serve`]: the connection loop: connection limit, timeouts, accept back-off.
//! - [`auth`]: the API key, body limits and time limits every request passes through.
//! - [`error`]: every error as JSON that names what is wrong.
//! - [`api`]: status, printers, jobs and their pictures, folders, and the actions, which
//!   are the farm's own operations (`daemon::control::execute`).
//! - [`upload`]: files streamed into a hot folder under a temporary name, then linked in.
//! - [`multipart`]: an upload's `multipart/form-data` body read as it arrives, bounded.
//! - [`camera`]: the printers' pictures and live views, the jobs' snapshots and timelapses.
//! - [`events`]: live state, progress and temperatures as server-sent events.
//! - [`metrics`]: the farm in Prometheus' text format.
//! - [`octoprint`]: OctoPrint's API for slicers and other clients, one instance per hot
//!   folder under `/octoprint/<folder>/` and one at the root.
//! - [`appkeys`]: OctoPrint's application-key flow: keys of their own for clients.
//! - [`zeroconf`]: each folder's instance announced as `_octoprint._tcp`.
//! - [`assets`]: the dashboard's page, script and style, built into the binary.

mod api;
pub(crate) mod appkeys;
mod appkeys_api;
mod assets;
mod auth;
mod camera;
mod care;
mod counters;
mod error;
mod events;
mod instance;
mod limits;
mod metrics;
mod multipart;
mod octoprint;
pub(crate) mod pending;
pub(crate) mod serve;
mod spools;
mod state;
mod streams;
mod upload;
pub(crate) mod zeroconf;

use crate::daemon::config::HttpConfig;
use crate::daemon::farm::Farm;
use axum::routing::{get, post, put};
use axum::Router;
use std::sync::Arc;

pub(crate) use appkeys::AppKeys;
pub(crate) use counters::Counters;
pub(crate) use error::ApiError;
pub(crate) use limits::{
    DEFAULT_UPLOAD_MAX_BYTES, MAX_BODY_BYTES, REQUEST_TIMEOUT, UPLOAD_IDLE_TIMEOUT, UPLOAD_TIMEOUT,
};
pub use state::{Access, AppState};

// The reading of an upload's form and the check of its file's name are exported for the
// fuzz targets.
pub use octoprint::{read_form as read_upload_form, truthy, Form as UploadForm};
pub use upload::{check_name as check_upload_name, upload_name, Upload};

/// The whole application: pages, API, metrics and the OctoPrint subset.
pub(crate) fn router(state: AppState) -> Router {
    let (octoprint_uploads, octoprint_api, octoprint_open) = octoprint::routes();
    let uploads = Router::new()
        .route("/api/v1/folders/{folder}/files/{file}", put(api::upload))
        .merge(octoprint_uploads)
        .layer(axum::extract::DefaultBodyLimit::max(
            usize::try_from(state.upload_max_bytes).unwrap_or(usize::MAX),
        ))
        .route_layer(axum::middleware::from_fn(auth::upload_time_limit));
    let api = Router::new()
        .route("/api/v1/status", get(api::status))
        .route("/api/v1/printers", get(api::printers))
        .route("/api/v1/printers/{name}", get(api::printer))
        .route(
            "/api/v1/printers/{name}/{action}",
            post(api::printer_action),
        )
        .route("/api/v1/printers/{name}/load", post(spools::load))
        .route("/api/v1/printers/{name}/power/{switch}", post(api::power))
        .route("/api/v1/printers/{name}/maintenance", get(care::record))
        .route(
            "/api/v1/printers/{name}/maintenance/{action}",
            post(care::action),
        )
        .route("/api/v1/spools", get(spools::list).post(spools::add))
        .route("/api/v1/jobs", get(api::jobs))
        .route("/api/v1/jobs/{id}", get(api::job))
        .route("/api/v1/history", get(api::history))
        .route("/api/v1/stats", get(api::stats))
        .route("/api/v1/jobs/{id}/{action}", post(api::job_action))
        .route(
            "/api/v1/jobs/{id}/parts/{part}/cancel",
            post(api::cancel_part),
        )
        .route("/api/v1/jobs/{id}/pictures/{picture}", get(api::picture))
        .route("/api/v1/jobs/{id}/camera/{file}", get(camera::job_file))
        .route("/api/v1/cameras", get(camera::cameras))
        .route("/api/v1/printers/{name}/snapshot", get(camera::snapshot))
        .route("/api/v1/printers/{name}/bed/{file}", get(camera::bed_file))
        .route("/api/v1/folders", get(api::folders))
        .route("/metrics", get(metrics::metrics))
        // The application keys, as the dashboard and `crispen keys` manage them.
        .route("/api/v1/appkeys", get(appkeys_api::list))
        .route(
            "/api/v1/appkeys/{kind}/{id}/{action}",
            post(appkeys_api::act),
        )
        .merge(octoprint_api)
        .layer(axum::extract::DefaultBodyLimit::max(MAX_BODY_BYTES))
        .route_layer(axum::middleware::from_fn(auth::time_limit))
        // The event stream outlives any request time limit by design.
        .route("/api/v1/events", get(events::events))
        .route("/api/v1/printers/{name}/stream", get(camera::stream));
    // A client asks for its key before it has one.
    let open = octoprint_open
        .layer(axum::extract::DefaultBodyLimit::max(MAX_BODY_BYTES))
        .route_layer(axum::middleware::from_fn(auth::time_limit));
    let pages = Router::new()
        .route("/", get(assets::index))
        .route("/appkeys.js", get(assets::appkeys_script))
        .route("/app.js", get(assets::script))
        .route("/style.css", get(assets::style))
        .route("/stats", get(assets::stats_page))
        .route("/stats.js", get(assets::stats_script));
    Router::new()
        .merge(uploads)
        .merge(api)
        .route_layer(axum::middleware::from_fn_with_state(
            state.clone(),
            auth::require_key,
        ))
        .merge(pages)
        .merge(open)
        .fallback(error::not_found)
        .method_not_allowed_fallback(error::method_not_allowed)
        .with_state(state)
}

/// Binds the TCP listener of `[http] listen`.
pub(crate) async fn bind(http: &HttpConfig) -> std::io::Result<tokio::net::TcpListener> {
    tokio::net::TcpListener::bind(http.listen).await
}

/// What both listeners share, made once by the service: the application keys, the
/// cameras, the run's counters and OctoPrint's held uploads (whose sweeper is a task of
/// the service, see `pending::sweep`).
#[derive(Clone)]
pub(crate) struct Shared {
    pub(crate) appkeys: Arc<AppKeys>,
    pub(crate) cameras: Arc<crate::camera::Cameras>,
    pub(crate) counters: Arc<Counters>,
    pub(crate) pending: Arc<pending::Pending>,
}

impl Shared {
    fn state(self, farm: Arc<Farm>, access: Access, upload_max_bytes: u64) -> AppState {
        AppState {
            farm,
            access: Arc::new(access),
            upload_max_bytes,
            streams: Arc::default(),
            appkeys: self.appkeys,
            cameras: self.cameras,
            counters: self.counters,
            pending: self.pending,
        }
    }
}

/// Serves the application on the control socket until `stop` fires.
pub(crate) async fn serve_socket(
    farm: Arc<Farm>,
    shared: Shared,
    http: Option<HttpConfig>,
    listener: tokio::net::UnixListener,
    stop: tokio_util::sync::CancellationToken,
) {
    let upload_max_bytes = http.map_or(DEFAULT_UPLOAD_MAX_BYTES, |h| h.upload_max_bytes);
    let app = router(shared.state(farm, Access::Socket, upload_max_bytes));
    serve::serve(listener, app, serve::Limits::default(), stop, "socket").await;
}

/// Serves the application on the TCP listener of `[http]` until `stop` fires.
pub(crate) async fn serve_tcp(
    farm: Arc<Farm>,
    shared: Shared,
    http: HttpConfig,
    listener: tokio::net::TcpListener,
    stop: tokio_util::sync::CancellationToken,
) {
    let access = Access::Key {
        key: http.api_key,
        read_only_without_key: http.read_only_without_key,
    };
    let app = router(shared.state(farm, access, http.upload_max_bytes));
    serve::serve(listener, app, serve::Limits::default(), stop, "tcp").await;
}

/// Where the built-in default serves the dashboard.
pub(crate) const DEMO_LISTEN: &str = "127.0.0.1:8080";

/// The demo's key file cannot be made or read.
#[derive(Debug, thiserror::Error)]
#[error("dashboard key {path}: {message}")]
pub struct DemoKeyError {
    pub path: std::path::PathBuf,
    pub message: String,
}

/// `[http]` of the built-in default: the dashboard on [`DEMO_LISTEN`] (or a port the
/// system picks if that one is taken), open to look at without a key, and a key for
/// acting that is made once (random, mode 0600) in `key_file` and kept there.
pub fn demo_http(key_file: &std::path::Path) -> Result<HttpConfig, DemoKeyError> {
    use base64::Engine;
    use std::io::Write;
    use std::os::unix::fs::OpenOptionsExt;
    let failed = |message: String| DemoKeyError {
        path: key_file.to_path_buf(),
        message,
    };
    if let Some(dir) = key_file.parent() {
        std::fs::create_dir_all(dir).map_err(|e| failed(e.to_string()))?;
    }
    let created = std::fs::OpenOptions::new()
        .write(true)
        .create_new(true)
        .mode(0o600)
        .open(key_file);
    match created {
        Ok(mut file) => {
            let key =
                base64::engine::general_purpose::URL_SAFE_NO_PAD.encode(rand::random::<[u8; 24]>());
            // Created in place with `create_new`, not `fsutil::write_atomic`: a key that
            // exists is never replaced, and the file is 0600 from its first byte.
            file.write_all(format!("{key}\n").as_bytes())
                .and_then(|_| file.sync_all())
                .map_err(|e| failed(format!("cannot write: {e}")))?;
            if let Some(dir) = key_file.parent() {
                crate::fsutil::sync_dir(dir).map_err(|e| failed(e.to_string()))?;
            }
        }
        Err(e) if e.kind() == std::io::ErrorKind::AlreadyExists => {}
        Err(e) => return Err(failed(format!("cannot create: {e}"))),
    }
    let api_key = crate::daemon::config::read_api_key(key_file).map_err(failed)?;
    Ok(HttpConfig {
        listen: DEMO_LISTEN.parse().expect("a valid address"),
        api_key,
        read_only_without_key: true,
        upload_max_bytes: DEFAULT_UPLOAD_MAX_BYTES,
        any_port_if_taken: true,
        // Listening on loopback only: nothing to announce to the network.
        octoprint: crate::daemon::config::octoprint::OctoPrintConfig {
            announce: false,
            default_folder: None,
        },
    })
}
