//! One camera source (a snapshot URL or an MJPEG stream), fetched by a task of its own that
//! alone publishes what it has: the latest frame, whether the camera answers, and counts.
//! Nothing on the printing path waits on it: readers glance at the published feed.
//!
//! A frame is published only when it is a whole JPEG whose picture decodes; one that is
//! not (cut short, run into the next part, undecodable) is a failure like a refused
//! connection: counted, and the camera offline until a whole frame comes.

pub use super::fetch::CameraFault;
use super::fetch::{self, FetchError};
use super::mjpeg::{FrameFault, Part};
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
    /// Why the last fetch failed, in words (with the details) and as data.
    pub error: Option<String>,
    pub fault: Option<CameraFault>,
    /// Unix seconds of the first failure since the camera last gave a frame.
    pub offline_since: Option<f64>,
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
            fault: None,
            offline_since: None,
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
        warned: None,
        said_offline: false,
    };
    let mut retry = settings.refresh;
    loop {
        let result = match &source {
            CameraSource::Snapshot(url) => {
                let got = tokio::select! {
                    got = fetch::snapshot(url, settings.timeout, settings.frame_max_bytes) => got,
                    _ = stop.cancelled() => return,
                };
                match got {
                    Ok(jpeg) => {
                        publisher.checked_frame(jpeg).await;
                        Ok(())
                    }
                    Err(e) => Err(e),
                }
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

/// Reads a stream until it fails, publishing a frame per [`STREAM_PACE`] at most; each
/// part refused is a failure.
async fn stream(
    url: &crate::outbound::HttpUrl,
    settings: &CameraSettings,
    publisher: &mut Publisher,
) -> Result<(), FetchError> {
    let mut stream = fetch::Stream::open(url, settings.timeout, settings.frame_max_bytes).await?;
    let mut last = None::<Instant>;
    loop {
        match stream.next().await? {
            Part::Frame(jpeg) => {
                if last.is_none_or(|t| t.elapsed() >= STREAM_PACE) {
                    last = Some(Instant::now());
                    publisher.checked_frame(jpeg).await;
                }
            }
            Part::Refused(fault) => publisher.failed(&FetchError::Refused(fault)),
        }
    }
}

/// A camera failing over and over is logged at most this often (a camera whose frames
/// come cut now and then would otherwise log each one).
const WARN_EVERY: Duration = Duration::from_secs(60);

struct Publisher {
    name: String,
    feed: watch::Sender<CameraFeed>,
    last_digest: Option<u64>,
    /// When a failure was last logged.
    warned: Option<Instant>,
    /// The log said the camera went offline and has not yet said it is back: a camera
    /// whose failures were too frequent to log is not announced online at each frame.
    said_offline: bool,
}

impl Publisher {
    /// A whole frame from the camera, published when its picture decodes (off the
    /// runtime), refused otherwise.
    async fn checked_frame(&mut self, jpeg: Vec<u8>) {
        match tokio::task::spawn_blocking(move || super::picture::decodes(&jpeg).map(|()| jpeg))
            .await
        {
            Ok(Ok(jpeg)) => self.frame(jpeg),
            Ok(Err(e)) => {
                tracing::debug!(camera = %self.name, error = %e, "camera: a frame that does not decode");
                self.failed(&FetchError::Refused(FrameFault::Undecodable));
            }
            // The decoder panicked: the frame is refused with the rest.
            Err(_) => self.failed(&FetchError::Refused(FrameFault::Undecodable)),
        }
    }

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
        let said_offline = self.said_offline;
        self.feed.send_modify(|f| {
            if f.state != CameraState::Online
                && f.state != CameraState::Frozen
                && (f.frames == 0 || said_offline)
            {
                tracing::info!(camera = %name, frames = f.frames + 1, failures = f.failures, "camera online");
            }
            f.frames += 1;
            f.frame = Some(Arc::new(Frame {
                jpeg: Bytes::from(jpeg),
                seq: f.frames,
                at: unix_now(),
            }));
            f.state = CameraState::Online;
            f.error = None;
            f.fault = None;
            f.offline_since = None;
            if !same {
                f.same_since = Instant::now();
            }
        });
        self.said_offline = false;
    }

    /// A failed fetch or a frame refused: logged when the camera goes offline or fails
    /// otherwise than before, at most once per [`WARN_EVERY`].
    fn failed(&mut self, e: &FetchError) {
        let (text, fault) = (e.to_string(), e.fault());
        let name = &self.name;
        let quiet = self.warned.is_some_and(|t| t.elapsed() < WARN_EVERY);
        let mut warned = false;
        self.feed.send_modify(|f| {
            f.failures += 1;
            let changed = f.state != CameraState::Offline
                || f.fault.map(|k| std::mem::discriminant(&k))
                    != Some(std::mem::discriminant(&fault));
            if changed && !quiet {
                tracing::warn!(camera = %name, error = %text, failures = f.failures, "camera offline; the prints go on without it");
                warned = true;
            }
            if f.state != CameraState::Offline {
                f.offline_since = Some(unix_now());
            }
            f.state = CameraState::Offline;
            f.error = Some(text);
            f.fault = Some(fault);
        });
        if warned {
            self.warned = Some(Instant::now());
            self.said_offline = true;
        }
    }
}
