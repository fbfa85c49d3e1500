//! The printers' cameras, the way farms already run them (ustreamer, mjpg-streamer,
//! crowsnest: a snapshot URL or an MJPEG stream), kept off the printing path.
//!
//! - `mjpeg`: an MJPEG stream read into frames, no I/O.
//! - `fetch`: a snapshot or a stream asked for over HTTP, with time and size limits.
//! - `feed`: one camera's task, which alone publishes its latest frame and state.
//! - `picture`: a printer's picture cut and turned from its camera's frame.
//! - `hub`: [`Cameras`], each printer's camera as the dashboard, the API and the
//!   recorder see it.
//! - `recorder`: the snapshots and timelapse of each job, from its printer's state.
//! - `bedwatch`: the picture of each empty bed, and the bed checks the store says are due.
//! - `timelapse`: the MP4 made by ffmpeg, and the cameras' disk limit.

pub mod bedwatch;
pub mod feed;
pub mod fetch;
pub mod hub;
pub mod mjpeg;
pub mod picture;
pub mod recorder;
pub mod timelapse;

pub use hub::Cameras;

use crate::daemon::farm::Farm;
use std::sync::Arc;
use tokio_util::sync::CancellationToken;

/// Fetches every camera and records every printer's jobs until `stop` (and waits for it
/// when there is no camera).
pub(crate) async fn run(
    farm: Arc<Farm>,
    cameras: Arc<Cameras>,
    sources: Vec<hub::Source>,
    stop: CancellationToken,
) {
    let mut tasks = tokio::task::JoinSet::new();
    // The timelapses being encoded: waited for at the stop, up to `ENCODE_AT_STOP`.
    let encodes = tokio_util::task::TaskTracker::new();
    for (name, source, feed) in sources {
        tasks.spawn(feed::run(
            name,
            source,
            cameras.settings.clone(),
            feed,
            stop.clone(),
        ));
    }
    {
        let root = cameras.root().to_path_buf();
        encodes.spawn(async move { recorder::encode_leftovers(&root).await });
    }
    for printer in cameras.printers() {
        tasks.spawn(bedwatch::watch(
            Arc::clone(&farm),
            Arc::clone(&cameras),
            printer.to_string(),
            stop.clone(),
        ));
        tasks.spawn(recorder::record(
            Arc::clone(&farm),
            Arc::clone(&cameras),
            printer.to_string(),
            encodes.clone(),
            stop.clone(),
        ));
    }
    while let Some(ended) = tasks.join_next().await {
        // A panic is the service's to see (it stops the daemon with the task's name).
        if let Err(e) = ended {
            if e.is_panic() {
                std::panic::resume_unwind(e.into_panic());
            }
        }
    }
    // No camera at all, or every task ended at the stop: this one ends with the stop, as
    // the service expects of a task that runs as long as it does.
    stop.cancelled().await;
    // The timelapses of the prints that just ended are made before the daemon exits (a
    // single job's `--exit-when-idle` run wants its video); one still encoding after
    // `ENCODE_AT_STOP` is left to the next start (`recorder::encode_leftovers`).
    encodes.close();
    if tokio::time::timeout(ENCODE_AT_STOP, encodes.wait())
        .await
        .is_err()
    {
        tracing::warn!("camera: a timelapse is still encoding; it is made at the next start");
    }
}

/// The longest the stop waits for timelapses being encoded.
const ENCODE_AT_STOP: std::time::Duration = std::time::Duration::from_secs(60);
