//! The checks every API request passes: the API key on TCP, and time limits. The key may
//! come as OctoPrint accepts it: an `X-Api-Key` header, `Authorization: Bearer KEY`, or
//! the `apikey` query parameter. The `[http]` key opens everything; an application key
//! (see `super::appkeys`) opens the OctoPrint emulation only (`/api/...` outside
//! `/api/v1/`, `/octoprint/...`), and there only the instance its scope names (checked
//! here; what it may do there is checked by the handlers, with [`Who`]). The dashboard's own files need no key: they hold no
//! data, and the page asks for the key when the API wants one.

use super::appkeys::Who;
use super::{Access, ApiError, AppState, REQUEST_TIMEOUT, UPLOAD_TIMEOUT};
use axum::extract::{Request, State};
use axum::http::{Method, StatusCode};
use axum::middleware::Next;
use axum::response::{IntoResponse, Response};

/// Lets a request through with the right key, or a read-only one without a key when
/// `[http] read_only_without_key` allows it. On the control socket the socket's file
/// mode has already decided.
pub(crate) async fn require_key(
    State(state): State<AppState>,
    mut request: Request,
    next: Next,
) -> Response {
    let (key, read_only_without_key) = match &*state.access {
        Access::Socket => {
            request.extensions_mut().insert(Keyed(true));
            request.extensions_mut().insert(Who::Operator);
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
    let given = given_key(&request);
    let read_only = matches!(*request.method(), Method::GET | Method::HEAD);
    let octoprint = is_octoprint(request.uri().path());
    match given {
        Some(key_given) if same_key(&key_given, key.0.as_bytes()) => {
            request.extensions_mut().insert(Keyed(true));
            request.extensions_mut().insert(Who::Operator);
            next.run(request).await
        }
        Some(key_given) if octoprint => match state.appkeys.grant_of(&key_given) {
            // Its instance, or every one: whatever the address, before any handler.
            Some(grant) => match grant.check_instance(request.uri().path()) {
                Ok(()) => {
                    request.extensions_mut().insert(Keyed(true));
                    request.extensions_mut().insert(Who::App(grant));
                    next.run(request).await
                }
                Err(refused) => refused.into_response(),
            },
            None => ApiError::new(
                StatusCode::FORBIDDEN,
                "the API key does not match the key in [http] api_key_file nor an application key (hint: ask for one through the application-key flow, or see `crispen keys`)",
            )
            .into_response(),
        },
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

/// The key a request carries: `X-Api-Key`, `Authorization: Bearer`, or `?apikey=`.
fn given_key(request: &Request) -> Option<Vec<u8>> {
    let headers = request.headers();
    if let Some(v) = headers.get("x-api-key") {
        return Some(v.as_bytes().to_vec());
    }
    if let Some(bearer) = headers
        .get(axum::http::header::AUTHORIZATION)
        .and_then(|v| v.as_bytes().strip_prefix(b"Bearer "))
    {
        return Some(bearer.trim_ascii().to_vec());
    }
    let query = request.uri().query()?;
    query.split('&').find_map(|pair| {
        let value = pair.strip_prefix("apikey=")?;
        Some(crate::percent::percent_decode(value).into_bytes())
    })
}

/// The OctoPrint emulation's addresses, which application keys open.
fn is_octoprint(path: &str) -> bool {
    path.starts_with("/octoprint/") || (path.starts_with("/api/") && !path.starts_with("/api/v1/"))
}

/// Whether a request came with the key (or on the control socket), for the handlers
/// whose bounds differ (event streams).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(crate) struct Keyed(pub bool);

/// Compares in time independent of where the keys differ.
fn same_key(given: &[u8], key: &[u8]) -> bool {
    subtle::ConstantTimeEq::ct_eq(given, key).into()
}

pub(crate) async fn time_limit(request: Request, next: Next) -> Response {
    limited(REQUEST_TIMEOUT, request, next).await
}

pub(crate) async fn upload_time_limit(request: Request, next: Next) -> Response {
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

    #[test]
    fn keys_come_as_octoprint_takes_them() {
        let req = |uri: &str, header: Option<(&str, &str)>| {
            let mut b = axum::http::Request::builder().uri(uri);
            if let Some((k, v)) = header {
                b = b.header(k, v);
            }
            b.body(axum::body::Body::empty()).unwrap()
        };
        let key = |r| super::given_key(&r).map(|k| String::from_utf8(k).unwrap());
        assert_eq!(
            key(req("/api/job", Some(("X-Api-Key", "k1")))).as_deref(),
            Some("k1")
        );
        assert_eq!(
            key(req("/api/job", Some(("Authorization", "Bearer k2")))).as_deref(),
            Some("k2")
        );
        assert_eq!(
            key(req("/api/job?x=1&apikey=k%33", None)).as_deref(),
            Some("k3")
        );
        assert_eq!(
            key(req("/api/job", Some(("Authorization", "Basic eA==")))),
            None
        );
        assert!(super::is_octoprint("/octoprint/hot/api/job"));
        assert!(super::is_octoprint("/api/files/local"));
        assert!(!super::is_octoprint("/api/v1/status"));
        assert!(!super::is_octoprint("/metrics"));
    }
}
