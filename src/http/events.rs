//! `GET /api/v1/events`: server-sent events carrying the farm's state. Each `status`
//! event holds the same JSON as `GET /api/v1/status`; one is sent at once, then whenever
//! anything changes: the stream follows every piece of the farm's state (jobs, each
//! printer's live status, preparations, config, the rest of a shared farm), at most one
//! event per [`SPACING`]. Unchanged states are not sent again; a comment every 15 s keeps
//! proxies from closing an idle stream.
//!
//! A stream holds its connection for as long as the client wants, so streams are
//! capped: without the key at most [`MAX_STREAMS_PER_CLIENT`] per client address and
//! [`MAX_STREAMS_WITHOUT_KEY`] in all, with it [`MAX_STREAMS`] in all; one more is refused
//! with 503. Requests with the key thus always find a connection (see `serve`).

use super::auth::Keyed;
use super::serve::ClientAddr;
use super::{ApiError, AppState};
use axum::extract::State;
use axum::http::StatusCode;
use axum::response::sse::{Event, KeepAlive, Sse};
use axum::Extension;
use futures_util::Stream;
use std::collections::HashMap;
use std::convert::Infallible;
use std::net::IpAddr;
use std::sync::{Arc, Mutex};
use std::time::Duration;

/// Streams without the key from one client address.
pub const MAX_STREAMS_PER_CLIENT: usize = 8;
/// Streams without the key in all.
pub const MAX_STREAMS_WITHOUT_KEY: usize = 32;
/// Streams in all (a quarter of a listener's connections).
pub const MAX_STREAMS: usize = 64;

/// The open event streams of one listener.
#[derive(Debug, Default)]
pub struct Streams(Mutex<Counts>);

#[derive(Debug, Default)]
struct Counts {
    all: usize,
    without_key: usize,
    by_client: HashMap<Option<IpAddr>, usize>,
}

/// One open stream; closing it (dropping this) frees its place.
pub struct StreamPlace {
    streams: Arc<Streams>,
    client: Option<Option<IpAddr>>,
}

impl Drop for StreamPlace {
    fn drop(&mut self) {
        let mut counts = self.streams.0.lock().unwrap_or_else(|e| e.into_inner());
        counts.all -= 1;
        if let Some(client) = self.client {
            counts.without_key -= 1;
            if let Some(n) = counts.by_client.get_mut(&client) {
                *n -= 1;
                if *n == 0 {
                    counts.by_client.remove(&client);
                }
            }
        }
    }
}

impl Streams {
    /// A place for one more stream from `client`, if the caps allow it.
    pub fn open(
        self: &Arc<Self>,
        client: Option<IpAddr>,
        keyed: bool,
    ) -> Result<StreamPlace, ApiError> {
        let mut counts = self.0.lock().unwrap_or_else(|e| e.into_inner());
        let refuse = |what: String| {
            Err(ApiError::new(
                StatusCode::SERVICE_UNAVAILABLE,
                format!("too many event streams {what}; close a dashboard tab or try again later"),
            ))
        };
        if counts.all >= MAX_STREAMS {
            return refuse(format!("(at most {MAX_STREAMS})"));
        }
        if !keyed {
            if counts.without_key >= MAX_STREAMS_WITHOUT_KEY {
                return refuse(format!(
                    "without the key (at most {MAX_STREAMS_WITHOUT_KEY}; with the key in X-Api-Key there is room)"
                ));
            }
            let mine = counts.by_client.entry(client).or_default();
            if *mine >= MAX_STREAMS_PER_CLIENT {
                return refuse(format!(
                    "without the key from this address (at most {MAX_STREAMS_PER_CLIENT})"
                ));
            }
            *mine += 1;
            counts.without_key += 1;
        }
        counts.all += 1;
        Ok(StreamPlace {
            streams: Arc::clone(self),
            client: (!keyed).then_some(client),
        })
    }
}

/// Events are at most this often: a change soon after one sent waits for the rest of it,
/// and what changed meanwhile goes in one event (progress changes several times a second).
const SPACING: Duration = Duration::from_millis(500);

pub async fn events(
    State(state): State<AppState>,
    client: Option<Extension<ClientAddr>>,
    keyed: Option<Extension<Keyed>>,
) -> Result<Sse<impl Stream<Item = Result<Event, Infallible>>>, ApiError> {
    let client = client.and_then(|Extension(ClientAddr(a))| a);
    let keyed = keyed.is_some_and(|Extension(Keyed(k))| k);
    let place = state.streams.open(client, keyed)?;
    let farm = state.farm.clone();
    let wake = farm.watch();
    let stream = futures_util::stream::unfold(
        (farm, wake, String::new(), true, place),
        |(farm, mut wake, last, mut first, place)| async move {
            loop {
                if !std::mem::take(&mut first) {
                    tokio::select! {
                        () = wake.changed() => {}
                        _ = farm.shutdown.cancelled() => return None,
                    }
                    tokio::time::sleep(SPACING).await;
                }
                let snapshot = {
                    let farm = farm.clone();
                    tokio::task::spawn_blocking(move || super::api::snapshot(&farm)).await
                };
                let Ok(snapshot) = snapshot else { return None };
                let text = serde_json::to_string(&snapshot).unwrap_or_default();
                if text != last {
                    let event = Event::default().event("status").data(text.clone());
                    return Some((Ok(event), (farm, wake, text, false, place)));
                }
            }
        },
    );
    Ok(Sse::new(stream).keep_alive(KeepAlive::new().interval(Duration::from_secs(15))))
}
