//! `GET /api/v1/events`: server-sent events carrying the farm's state. Each `status`
//! event holds the same JSON as `GET /api/v1/status`; one is sent at once, then whenever
//! anything changes: on every change the farm announces, and at least every second while
//! printers report progress and temperatures (which change without an announcement).
//! Unchanged states are not sent again; a comment every 15 s keeps proxies from closing
//! an idle stream.

use super::AppState;
use axum::extract::State;
use axum::response::sse::{Event, KeepAlive, Sse};
use futures_util::Stream;
use std::convert::Infallible;
use std::time::Duration;

/// How often live figures (progress, temperatures) are looked at.
const POLL: Duration = Duration::from_secs(1);

pub async fn events(
    State(state): State<AppState>,
) -> Sse<impl Stream<Item = Result<Event, Infallible>>> {
    let farm = state.farm.clone();
    let wake = farm.subscribe();
    let stream = futures_util::stream::unfold(
        (farm, wake, String::new(), true),
        |(farm, mut wake, last, mut first)| async move {
            loop {
                if !std::mem::take(&mut first) {
                    tokio::select! {
                        _ = wake.changed() => {}
                        _ = tokio::time::sleep(POLL) => {}
                        _ = farm.shutdown.cancelled() => return None,
                    }
                }
                let snapshot = {
                    let farm = farm.clone();
                    tokio::task::spawn_blocking(move || super::api::snapshot(&farm)).await
                };
                let Ok(snapshot) = snapshot else { return None };
                let text = serde_json::to_string(&snapshot).unwrap_or_default();
                if text != last {
                    let event = Event::default().event("status").data(text.clone());
                    return Some((Ok(event), (farm, wake, text, false)));
                }
            }
        },
    );
    Sse::new(stream).keep_alive(KeepAlive::new().interval(Duration::from_secs(15)))
}
