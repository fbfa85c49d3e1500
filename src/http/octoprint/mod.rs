//! OctoPrint's REST API as the clients that farm users already have speak it: Cura's
//! "OctoPrint Connection" plugin, PrusaSlicer and OrcaSlicer (physical printer, type
//! OctoPrint), `octorest`, OctoPrint's own `octoprint client`. Each hot folder is an
//! OctoPrint instance of its own under `/octoprint/<folder>/` (announced by zeroconf, see
//! `super::zeroconf`), so Cura lists "crispen: &lt;folder&gt;" and a job sent to one lands in
//! that folder; the root (`/api/...`) is one more instance, standing for `[http]
//! default_folder` (or the only folder), where uploads may name their folder in `path`.
//!
//! - [`form`]: the upload's form, read whole whatever the order of its fields.
//! - [`files`]: `POST api/files/local` (upload) and `POST api/files/local/<path>`
//!   (`select`, with `print` releasing a held upload).
//! - [`state`]: `api/printer`, `api/job`, `api/printerprofiles`, `api/connection`: a
//!   folder's printers and its current or next job, described honestly (which printer's
//!   temperatures, what the flags mean for several printers; see docs/octoprint.md).
//! - [`identity`]: each instance's UUID (`plugins.discovery.upnpUuid`, the zeroconf
//!   `uuid`), which Home Assistant takes as the device's unique id.
//! - here (the instance a request addresses is `super::instance`): `api/version`,
//!   `api/server`, `api/settings`, `api/login`, and the routes.
//!
//! What OctoPrint can do and a farm does not let a slicer do (send G-code to a printer,
//! connect or disconnect it) is refused with `409` and a message saying where the
//! operator does it. `POST api/job` (pause, resume, cancel, start) is the operator's, and
//! an application key's whose scope has `control` (see `super::appkeys`); Home
//! Assistant's buttons use it.

pub(crate) mod files;
pub(crate) mod form;
pub(crate) mod identity;
pub(crate) mod state;

use super::upload;
use super::{ApiError, AppState};
use axum::http::StatusCode;
use axum::routing::{get, post};
use axum::{Json, Router};

pub(crate) use super::instance::Instance;
pub use form::{read_form, truthy, Form};

/// The OctoPrint API version whose answers these are.
pub(crate) const API_VERSION: &str = "0.1";
/// The OctoPrint server version reported; clients only check that it is recent enough.
pub(crate) const SERVER_VERSION: &str = "1.10.0";

pub(crate) async fn version() -> Json<serde_json::Value> {
    Json(serde_json::json!({
        "api": API_VERSION,
        "server": SERVER_VERSION,
        "text": format!("OctoPrint (crispen {})", env!("CARGO_PKG_VERSION")),
    }))
}

/// `GET api/server`: OctoPrint's version, and no safe mode (crispen has no plugins to
/// leave out), as Home Assistant's `pyoctoprintapi` reads it.
pub(crate) async fn server() -> Json<serde_json::Value> {
    Json(serde_json::json!({ "version": SERVER_VERSION, "safemode": null }))
}

/// `GET api/settings`: what clients read of OctoPrint's settings. No SD card; the webcam
/// is the camera of the folder's first printer that has one, served by crispen (Home
/// Assistant's camera entity reads `streamUrl`, and asks it `?action=snapshot` for stills,
/// as mjpg-streamer answers), else off as OctoPrint has it without one; no
/// G-code analysis (crispen prepares and estimates itself). Of the plugins only the
/// bundled Discovery plugin's settings, for its `upnpUuid`: the instance's identity (see
/// [`identity`]), which Home Assistant's setup needs; no `tracking` (anonymous usage
/// tracking is off, as OctoPrint leaves it without consent).
pub(crate) async fn settings(
    axum::extract::State(state): axum::extract::State<AppState>,
    instance: Instance,
    headers: axum::http::HeaderMap,
) -> Result<Json<serde_json::Value>, ApiError> {
    let config = state.farm.config();
    let folder_config = instance.folder(&config)?;
    let camera = folder_config.and_then(|f| f.printers.iter().find(|p| state.cameras.has(p)));
    // The address the client reached crispen by, unless the dashboard's public one is set.
    let origin = config.notify.dashboard.clone().or_else(|| {
        let host = headers.get(axum::http::header::HOST)?.to_str().ok()?;
        host.chars()
            .all(|c| c.is_ascii_alphanumeric() || ".-:[]".contains(c))
            .then(|| format!("http://{host}"))
    });
    let (stream_url, snapshot_url) = match (camera, &origin) {
        (Some(p), Some(origin)) => {
            let at = format!(
                "{origin}/api/v1/printers/{}",
                crate::percent::percent_encode(p)
            );
            (format!("{at}/stream"), format!("{at}/snapshot"))
        }
        _ => (String::new(), String::new()),
    };
    let folder = folder_config.map(upload::folder_name);
    let spool = config.spool_dir.clone();
    drop(config);
    let own = instance.folder.is_some();
    let uuid = tokio::task::spawn_blocking(move || {
        let which = match (&folder, own) {
            (Some(name), true) => identity::Which::Folder(name),
            _ => identity::Which::Root,
        };
        identity::uuid(&spool, which)
    })
    .await
    .map_err(|e| ApiError::new(StatusCode::INTERNAL_SERVER_ERROR, e.to_string()))?
    .map_err(|e| {
        tracing::error!(error = %e, "octoprint: no instance identity");
        ApiError::new(StatusCode::INTERNAL_SERVER_ERROR, e.to_string())
    })?;
    Ok(Json(serde_json::json!({
        "api": { "allowCrossOrigin": false },
        "appearance": { "name": instance.folder.as_deref().map_or("crispen".to_string(), |f| format!("crispen: {f}")) },
        "feature": {
            "sdSupport": false,
            "gcodeViewer": false,
            "temperatureGraph": false,
            "keyboardControl": false,
        },
        "folder": {},
        "gcodeAnalysis": { "runAt": "never" },
        "plugins": {
            "discovery": {
                "upnpUuid": uuid,
                "publicHost": null,
                "publicPort": null,
                "pathPrefix": null,
                "httpUsername": null,
                "httpPassword": null,
                "zeroConf": [],
                "addresses": null,
                "ignoredAddresses": null,
                "interfaces": null,
                "ignoredInterfaces": null,
            },
        },
        "serial": { "autoconnect": true },
        "temperature": { "profiles": [] },
        "webcam": {
            "webcamEnabled": !stream_url.is_empty(),
            "timelapseEnabled": false,
            "streamUrl": stream_url,
            "snapshotUrl": snapshot_url,
            "snapshotSslValidation": true,
            "flipH": false,
            "flipV": false,
            "rotate90": false,
            "bitrate": "",
            "streamRatio": "16:9",
        },
    })))
}

/// `POST api/login` with `{"passive": true}`: who the key is (an application key's
/// application, or the operator for the `[http]` key). Logging in with a user name and
/// password is refused: crispen has keys, not users.
pub(crate) async fn login(
    who: Option<axum::Extension<super::appkeys::Who>>,
    body: axum::body::Bytes,
) -> Result<Json<serde_json::Value>, ApiError> {
    let passive = serde_json::from_slice::<serde_json::Value>(&body)
        .ok()
        .and_then(|v| v.get("passive").cloned())
        .is_some_and(|p| p.as_bool() == Some(true) || p.is_string());
    if !passive {
        return Err(ApiError::new(
            StatusCode::BAD_REQUEST,
            "crispen has API keys, not users: log in with {\"passive\": true} and the key in X-Api-Key",
        ));
    }
    let name = match who.map(|w| w.0) {
        Some(super::appkeys::Who::App(grant)) => grant.app,
        _ => "crispen operator".to_string(),
    };
    Ok(Json(serde_json::json!({
        "name": name,
        "active": true,
        "admin": false,
        "user": true,
        "apikey": null,
        "groups": ["users"],
        "permissions": [],
        "needs": { "role": ["status", "files_upload", "print", "connection"] },
        "roles": ["user"],
        "session": null,
    })))
}

/// `GET api/system/commands`: none, as an OctoPrint whose operator configured none.
async fn system_commands() -> Json<serde_json::Value> {
    Json(serde_json::json!({ "core": [], "custom": [] }))
}

/// A farm's own ways to do what OctoPrint clients ask of one printer.
async fn refused(instance: Instance) -> ApiError {
    ApiError::conflict(format!(
        "{}: not here: crispen drives its printers itself (pause, resume and cancel on the dashboard, `crispen pause|resume|cancel`, or /api/v1/)",
        super::error::quoted(&instance.rest)
    ))
}

/// `POST api/system/commands/<source>/<action>` (Home Assistant's Shutdown System,
/// Reboot System and Restart OctoPrint buttons): the host is not OctoPrint's to stop.
async fn system_refused(instance: Instance) -> ApiError {
    ApiError::conflict(format!(
        "{}: not here: crispen does not shut down, reboot or restart its host for an OctoPrint client (the operator does, e.g. `systemctl restart crispen`)",
        super::error::quoted(&instance.rest)
    ))
}

/// Every OctoPrint route, for the root instance and each folder's: (uploads, API under
/// the key, key requests without one).
pub(crate) fn routes() -> (Router<AppState>, Router<AppState>, Router<AppState>) {
    let mut uploads = Router::new();
    let mut api = Router::new();
    let mut open = Router::new();
    for base in ["", "/octoprint/{folder}"] {
        uploads = uploads.route(&format!("{base}/api/files/local"), post(files::upload));
        api = api
            .route(&format!("{base}/api/version"), get(version))
            .route(&format!("{base}/api/server"), get(server))
            .route(&format!("{base}/api/settings"), get(settings))
            .route(&format!("{base}/api/system/commands"), get(system_commands))
            .route(
                &format!("{base}/api/system/commands/{{*command}}"),
                post(system_refused),
            )
            // pyoctoprintapi joins some addresses with a doubled slash
            // (`<base>//api/printer/bed`, `<base>//api/system/commands/...`).
            .route(
                &format!("{base}//api/system/commands/{{*command}}"),
                post(system_refused),
            )
            .route(&format!("{base}//api/printer/{{*command}}"), post(refused))
            .route(&format!("{base}/api/login"), post(login))
            .route(
                &format!("{base}/api/printerprofiles"),
                get(state::printer_profiles),
            )
            .route(&format!("{base}/api/printer"), get(state::printer))
            .route(&format!("{base}/api/printer/{{*command}}"), post(refused))
            .route(
                &format!("{base}/api/job"),
                get(state::job).post(state::job_command),
            )
            .route(
                &format!("{base}/api/connection"),
                get(state::connection).post(refused),
            )
            .route(
                &format!("{base}/api/files/local/{{*path}}"),
                post(files::command),
            );
        open = open
            .route(
                &format!("{base}/plugin/appkeys/probe"),
                get(super::appkeys_api::probe),
            )
            .route(
                &format!("{base}/plugin/appkeys/request"),
                post(super::appkeys_api::request),
            )
            .route(
                &format!("{base}/plugin/appkeys/request/{{token}}"),
                get(super::appkeys_api::poll),
            );
    }
    (uploads, api, open)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn instances_are_read_from_the_address() {
        let i = Instance::parse("/octoprint/hot%20one/api/files/local/a.gcode");
        assert_eq!(i.folder.as_deref(), Some("hot one"));
        assert_eq!(i.base, "/octoprint/hot%20one/");
        assert_eq!(i.rest, "api/files/local/a.gcode");
        let i = Instance::parse("/api/version");
        assert_eq!(
            (i.folder, i.base.as_str(), i.rest.as_str()),
            (None, "/", "api/version")
        );
        assert_eq!(crate::percent::percent_decode("a%2Fb%zz%4"), "a/b%zz%4");
    }
}
