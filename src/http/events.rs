//! `GET /api/v1/events`: server-sent events carrying the farm's state. Each `status`
//! event holds the same JSON as `GET /api/v1/status`; one is sent at once, then whenever
//! anything changes: the stream follows every piece of the farm's state (jobs, each
//! printer's live status, preparations, config, the rest of a shared farm), at most one
//! event per [`SPACING`]. Unchanged states are not sent again; a comment every 15 s keeps
//! proxies from closing an idle stream.
//!
//! A stream holds its connection for as long as the client wants, so streams are capped
//! ([`super::streams`]); one more is refused with 503. Requests with the key thus always
//! find a connection (see `serve`).

use super::auth::Keyed;
use super::serve::ClientAddr;
use super::{ApiError, AppState};
use axum::extract::State;
use axum::response::sse::{Event, KeepAlive, Sse};
use axum::Extension;
use futures_util::Stream;
use std::convert::Infallible;
use std::time::Duration;

/// Events are at most this often: a change soon after one sent waits for the rest of it,
/// and what changed meanwhile goes in one event (progress changes several times a second).
const SPACING: Duration = Duration::from_millis(500);

pub(crate) async fn events(
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
