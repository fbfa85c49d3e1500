//! The checks every API request passes: the API key (`X-Api-Key`, as OctoPrint clients
//! send it) on TCP, and time limits. The dashboard's own files need no key: they hold no data,
//! and the page asks for the key when the API wants one.

use super::{Access, ApiError, AppState, REQUEST_TIMEOUT, UPLOAD_TIMEOUT};
use axum::extract::{Request, State};
use axum::http::{Method, StatusCode};
use axum::middleware::Next;
use axum::response::{IntoResponse, Response};

/// Lets a request through with the right key, or a read-only one without a key when
/// `[http] read_only_without_key` allows it. On the control socket the socket's file
/// mode has already decided.
pub async fn require_key(
    State(state): State<AppState>,
    mut request: Request,
    next: Next,
) -> Response {
    let (key, read_only_without_key) = match &*state.access {
        Access::Socket => {
            request.extensions_mut().insert(Keyed(true));
            return next.run(request).await;
        }
        Access::Key {
            key,
            read_only_without_key,
        } => (key, *read_only_without_key),
    };
    // The key in force: a reload (SIGHUP) reads the key file again, so a rotated key
    // replaces the one the listener started with.
    let config = state.farm.config();
    let key = config.http.as_ref().map_or(key, |h| &h.api_key);
    let given = request
        .headers()
        .get("x-api-key")
        .map(|v| v.as_bytes().to_vec());
    let read_only = matches!(*request.method(), Method::GET | Method::HEAD);
    match given {
        Some(key_given) if same_key(&key_given, key.0.as_bytes()) => {
            request.extensions_mut().insert(Keyed(true));
            next.run(request).await
        }
        Some(_) => ApiError::new(
            StatusCode::FORBIDDEN,
            "the X-Api-Key header does not match the key in [http] api_key_file",
        )
        .into_response(),
        None if read_only && read_only_without_key => {
            request.extensions_mut().insert(Keyed(false));
            next.run(request).await
        }
        None => ApiError::new(
            StatusCode::UNAUTHORIZED,
            if read_only {
                "this needs the API key in an X-Api-Key header (the key is in the file named by [http] api_key_file)"
            } else {
                "changes need the API key in an X-Api-Key header, even with read_only_without_key (the key is in the file named by [http] api_key_file)"
            },
        )
        .into_response(),
    }
}

/// Whether a request came with the key (or on the control socket), for the handlers
/// whose bounds differ (event streams).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Keyed(pub bool);

/// Compares in time independent of where the keys differ.
fn same_key(given: &[u8], key: &[u8]) -> bool {
    given.len() == key.len() && given.iter().zip(key).fold(0u8, |acc, (a, b)| acc | (a ^ b)) == 0
}

pub async fn time_limit(request: Request, next: Next) -> Response {
    limited(REQUEST_TIMEOUT, request, next).await
}

pub async fn upload_time_limit(request: Request, next: Next) -> Response {
    limited(UPLOAD_TIMEOUT, request, next).await
}

async fn limited(limit: std::time::Duration, request: Request, next: Next) -> Response {
    let path = request.uri().path().to_string();
    match tokio::time::timeout(limit, next.run(request)).await {
        Ok(response) => response,
        Err(_) => ApiError::new(
            StatusCode::SERVICE_UNAVAILABLE,
            format!("{path}: not answered within {} s", limit.as_secs()),
        )
        .into_response(),
    }
}

#[cfg(test)]
mod tests {
    #[test]
    fn keys_compare_whole() {
        assert!(super::same_key(b"abcdefgh", b"abcdefgh"));
        assert!(!super::same_key(b"abcdefg", b"abcdefgh"));
        assert!(!super::same_key(b"abcdefgx", b"abcdefgh"));
        assert!(!super::same_key(b"", b"abcdefgh"));
    }
}
