//! The dashboard's files, built into the binary: one page, one script, one style sheet;
//! no framework, nothing from another server.

use axum::http::header;
use axum::response::IntoResponse;

const INDEX: &str = include_str!("assets/index.html");
const SCRIPT: &str = include_str!("assets/app.js");
const STYLE: &str = include_str!("assets/style.css");
const STATS_PAGE: &str = include_str!("assets/stats.html");
const STATS_SCRIPT: &str = include_str!("assets/stats.js");
const APPKEYS: &str = include_str!("assets/appkeys.js");

/// Only this page's own files; nothing framed elsewhere.
const POLICY: &str =
    "default-src 'self'; img-src 'self' blob:; media-src 'self' blob:; frame-ancestors 'none'; base-uri 'none'";

pub(crate) async fn index() -> impl IntoResponse {
    (
        [
            (header::CONTENT_TYPE, "text/html; charset=utf-8"),
            (header::CONTENT_SECURITY_POLICY, POLICY),
        ],
        INDEX,
    )
}

pub(crate) async fn script() -> impl IntoResponse {
    (
        [(header::CONTENT_TYPE, "text/javascript; charset=utf-8")],
        SCRIPT,
    )
}

pub(crate) async fn style() -> impl IntoResponse {
    ([(header::CONTENT_TYPE, "text/css; charset=utf-8")], STYLE)
}

/// The statistics page (`/stats`): its own page and script, the dashboard's style.
pub(crate) async fn stats_page() -> impl IntoResponse {
    (
        [
            (header::CONTENT_TYPE, "text/html; charset=utf-8"),
            (header::CONTENT_SECURITY_POLICY, POLICY),
        ],
        STATS_PAGE,
    )
}

pub(crate) async fn stats_script() -> impl IntoResponse {
    (
        [(header::CONTENT_TYPE, "text/javascript; charset=utf-8")],
        STATS_SCRIPT,
    )
}

/// The application-key requests panel (its own file; see `super::appkeys`).
pub(crate) async fn appkeys_script() -> impl IntoResponse {
    (
        [(header::CONTENT_TYPE, "text/javascript; charset=utf-8")],
        APPKEYS,
    )
}
