//! One camera source (a snapshot URL or an MJPEG stream), fetched by a task of its own that
//! alone publishes what it has: the latest frame, whether the camera answers, and counts.
//! Nothing on the printing path waits on it: readers glance at the published feed.

use super::fetch::{self, FetchError};
use crate::daemon::config::camera::{CameraSettings, CameraSource};
use bytes::Bytes;
use serde::Serialize;
use std::sync::Arc;
use std::time::{Duration, Instant};
use tokio::sync::watch;
use tokio_util::sync::CancellationToken;

/// Whether a camera gives frames.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize)]
#[serde(rename_all = "lowercase")]
pub enum CameraState {
    /// No answer yet.
    Starting,
    Online,
    /// Its last fetch failed (the feed's `error` says why).
    Offline,
    /// It answers, but with the same picture for `[camera] frozen_after_s` while its
    /// printer prints (decided per printer, see `hub`).
    Frozen,
}

/// A frame as the camera sent it.
#[derive(Debug)]
pub struct Frame {
    pub jpeg: Bytes,
    /// Counts the frames of this source: a new number is a new frame.
    pub seq: u64,
    /// Unix seconds when it came.
    pub at: f64,
}

/// What a source's task publishes.
#[derive(Debug, Clone)]
pub struct CameraFeed {
    pub state: CameraState,
    pub frame: Option<Arc<Frame>>,
    pub error: Option<String>,
    pub frames: u64,
    pub failures: u64,
    /// Since when (monotonic) the frames have been the same picture, byte for byte.
    pub same_since: Instant,
}

impl CameraFeed {
    pub fn starting() -> CameraFeed {
        CameraFeed {
            state: CameraState::Starting,
            frame: None,
            error: None,
            frames: 0,
            failures: 0,
            same_since: Instant::now(),
        }
    }
}

/// Unix seconds now.
pub(crate) fn unix_now() -> f64 {
    std::time::SystemTime::now()
        .duration_since(std::time::UNIX_EPOCH)
        .map_or(0.0, |d| d.as_secs_f64())
}

/// A stream's frames are published at most this often; the rest are skipped unread.
const STREAM_PACE: Duration = Duration::from_millis(250);
/// The longest wait before a failed camera is tried again.
const RETRY_MAX: Duration = Duration::from_secs(60);

/// Fetches `source` until `stop`, publishing into `feed`. `name` names it in logs (its URL).
pub async fn run(
    name: String,
    source: CameraSource,
    settings: CameraSettings,
    feed: watch::Sender<CameraFeed>,
    stop: CancellationToken,
) {
    let mut publisher = Publisher {
        name,
        feed,
        last_digest: None,
    };
    let mut retry = settings.refresh;
    loop {
        let result = match &source {
            CameraSource::Snapshot(url) => {
                let got = tokio::select! {
                    got = fetch::snapshot(url, settings.timeout, settings.frame_max_bytes) => got,
                    _ = stop.cancelled() => return,
                };
                got.map(|jpeg| publisher.frame(jpeg))
            }
            CameraSource::Stream(url) => tokio::select! {
                r = stream(url, &settings, &mut publisher) => r,
                _ = stop.cancelled() => return,
            },
        };
        let pause = match result {
            Ok(()) => {
                retry = settings.refresh;
                settings.refresh
            }
            Err(e) => {
                publisher.failed(&e);
                let pause = retry;
                retry = (retry * 2).min(RETRY_MAX.max(settings.refresh));
                pause
            }
        };
        tokio::select! {
            _ = tokio::time::sleep(pause) => {}
            _ = stop.cancelled() => return,
        }
    }
}

/// Reads a stream until it fails, publishing a frame per [`STREAM_PACE`] at most.
async fn stream(
    url: &crate::daemon::config::notify::ReceiverUrl,
    settings: &CameraSettings,
    publisher: &mut Publisher,
) -> Result<(), FetchError> {
    let mut stream = fetch::Stream::open(url, settings.timeout, settings.frame_max_bytes).await?;
    let mut last = None::<Instant>;
    loop {
        let jpeg = stream.next().await?;
        if last.is_none_or(|t| t.elapsed() >= STREAM_PACE) {
            last = Some(Instant::now());
            publisher.frame(jpeg);
        }
    }
}

struct Publisher {
    name: String,
    feed: watch::Sender<CameraFeed>,
    last_digest: Option<u64>,
}

impl Publisher {
    fn frame(&mut self, jpeg: Vec<u8>) {
        let digest = {
            use std::hash::{Hash, Hasher};
            let mut h = std::collections::hash_map::DefaultHasher::new();
            jpeg.hash(&mut h);
            h.finish()
        };
        let same = self.last_digest == Some(digest);
        self.last_digest = Some(digest);
        let name = &self.name;
        self.feed.send_modify(|f| {
            if f.state != CameraState::Online && f.state != CameraState::Frozen {
                tracing::info!(camera = %name, "camera online");
            }
            f.frames += 1;
            f.frame = Some(Arc::new(Frame {
                jpeg: Bytes::from(jpeg),
                seq: f.frames,
                at: unix_now(),
            }));
            f.state = CameraState::Online;
            f.error = None;
            if !same {
                f.same_since = Instant::now();
            }
        });
    }

    /// A failed fetch: logged when the camera goes offline or fails otherwise than before.
    fn failed(&mut self, e: &FetchError) {
        let text = e.to_string();
        let name = &self.name;
        self.feed.send_modify(|f| {
            f.failures += 1;
            if f.state != CameraState::Offline || f.error.as_deref() != Some(&text) {
                tracing::warn!(camera = %name, error = %text, "camera offline; the prints go on without it");
            }
            f.state = CameraState::Offline;
            f.error = Some(text);
        });
    }
}
