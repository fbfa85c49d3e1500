//! The cap on a listener's open event streams: without the key at most
//! [`MAX_STREAMS_PER_CLIENT`] per client address and [`MAX_STREAMS_WITHOUT_KEY`] in all,
//! with it [`MAX_STREAMS`] in all. Apart from the stream itself (`events`) because
//! the listener's state holds the count that the stream's handler takes.

use super::ApiError;
use axum::http::StatusCode;
use std::collections::HashMap;
use std::net::IpAddr;
use std::sync::{Arc, Mutex};

/// Streams without the key from one client address.
pub(crate) const MAX_STREAMS_PER_CLIENT: usize = 8;
/// Streams without the key in all.
pub(crate) const MAX_STREAMS_WITHOUT_KEY: usize = 32;
/// Streams in all (a quarter of a listener's connections).
pub(crate) const MAX_STREAMS: usize = 64;

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
pub(crate) struct StreamPlace {
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
    pub(crate) fn open(
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
