//! The operator's window: one HTTP API (JSON under `/api/v1/`, server-sent events), the
//! web dashboard at `/`, Prometheus metrics at `/metrics`, and the part of OctoPrint's API
//! that slicers use to "Send to printer". Served on TCP when `[http] listen` is configured.
//!
//! - [`auth`]: the API key, body limits and time limits every request passes through.
//! - [`error`]: every error as JSON that names what is wrong.
//! - [`api`]: status, printers, jobs and their pictures, folders, and the actions, which
//!   are the control socket's own operations (`daemon::control::handle`).
//! - [`upload`]: files streamed into a hot folder under a temporary name, then linked in.
//! - [`events`]: live state, progress and temperatures as server-sent events.
//! - [`metrics`]: the farm in Prometheus' text format.
//! - [`octoprint`]: `GET /api/version` and `POST /api/files/local`.
//! - [`assets`]: the dashboard's page, script and style, built into the binary.

mod api;
mod assets;
mod auth;
mod error;
mod events;
mod metrics;
mod octoprint;
mod upload;

use crate::daemon::config::HttpConfig;
use crate::daemon::farm::Farm;
use axum::routing::{get, post, put};
use axum::Router;
use std::sync::Arc;
use std::time::Duration;

pub use error::ApiError;

/// What every handler needs.
#[derive(Clone)]
pub struct AppState {
    pub farm: Arc<Farm>,
    pub http: Arc<HttpConfig>,
}

/// Largest body of any request but an upload: actions carry no body or a few fields.
pub const MAX_BODY_BYTES: usize = 64 * 1024;
/// A request (other than an upload or the event stream) is answered within this or gets 503.
pub const REQUEST_TIMEOUT: Duration = Duration::from_secs(30);
/// An upload may take this long in all…
pub const UPLOAD_TIMEOUT: Duration = Duration::from_secs(3600);
/// …but no more than this between two pieces of it.
pub const UPLOAD_IDLE_TIMEOUT: Duration = Duration::from_secs(60);

/// The whole application: pages, API, metrics and the OctoPrint subset.
pub fn router(state: AppState) -> Router {
    let uploads = Router::new()
        .route("/api/v1/folders/{folder}/files/{file}", put(api::upload))
        .route("/api/files/local", post(octoprint::upload))
        .layer(axum::extract::DefaultBodyLimit::max(
            usize::try_from(state.http.upload_max_bytes).unwrap_or(usize::MAX),
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
        .route("/api/v1/jobs", get(api::jobs))
        .route("/api/v1/jobs/{id}", get(api::job))
        .route("/api/v1/jobs/{id}/{action}", post(api::job_action))
        .route("/api/v1/jobs/{id}/pictures/{picture}", get(api::picture))
        .route("/api/v1/folders", get(api::folders))
        .route("/metrics", get(metrics::metrics))
        .route("/api/version", get(octoprint::version))
        .layer(axum::extract::DefaultBodyLimit::max(MAX_BODY_BYTES))
        .route_layer(axum::middleware::from_fn(auth::time_limit))
        // The event stream outlives any request time limit by design.
        .route("/api/v1/events", get(events::events));
    let pages = Router::new()
        .route("/", get(assets::index))
        .route("/app.js", get(assets::script))
        .route("/style.css", get(assets::style));
    Router::new()
        .merge(uploads)
        .merge(api)
        .route_layer(axum::middleware::from_fn_with_state(
            state.clone(),
            auth::require_key,
        ))
        .merge(pages)
        .fallback(error::not_found)
        .method_not_allowed_fallback(error::method_not_allowed)
        .with_state(state)
}

/// Binds the TCP listener of `[http] listen`.
pub async fn bind(http: &HttpConfig) -> std::io::Result<tokio::net::TcpListener> {
    tokio::net::TcpListener::bind(http.listen).await
}

/// Serves the application on `listener` until the farm's shutdown token fires.
pub async fn serve(farm: Arc<Farm>, http: HttpConfig, listener: tokio::net::TcpListener) {
    let shutdown = farm.shutdown.clone();
    let app = router(AppState {
        farm,
        http: Arc::new(http),
    });
    let served = axum::serve(listener, app)
        .with_graceful_shutdown(async move { shutdown.cancelled().await })
        .await;
    if let Err(e) = served {
        tracing::error!(error = %e, "http: the listener failed");
    }
}
