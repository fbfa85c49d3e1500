//! The printers' cameras as the rest of the daemon sees them: each printer's feed (shared
//! by the printers that name the same camera) and how its picture is made; the pictures
//! made last are kept so that many viewers cost one encoding per frame.

use super::feed::{CameraFault, CameraFeed, CameraState, Frame};
use super::picture::{self, PictureError};
use crate::daemon::config::camera::{CameraSettings, CameraSource, CameraTransform};
use crate::daemon::config::Config;
use bytes::Bytes;
use serde::{Deserialize, Serialize};
use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::sync::Mutex;
use tokio::sync::watch;

/// One printer's camera.
pub struct PrinterCamera {
    /// The camera's URL as written (one camera may serve several printers).
    pub source: String,
    feed: watch::Receiver<CameraFeed>,
    transform: CameraTransform,
    /// The last picture made: (frame number, picture).
    made: Mutex<Option<(u64, Bytes)>>,
}

/// A printer's picture.
#[derive(Debug, Clone)]
pub struct Picture {
    pub jpeg: Bytes,
    /// The frame's number at its camera.
    pub seq: u64,
    /// Unix seconds when the camera sent it.
    pub at: f64,
}

/// A printer's camera as shown (status, API, metrics).
#[derive(Debug, Clone, Serialize)]
pub struct CameraStatus {
    pub printer: String,
    pub source: String,
    pub state: CameraState,
    pub error: Option<String>,
    /// Unix seconds of the latest frame.
    pub frame_at: Option<f64>,
    pub frames: u64,
    pub failures: u64,
}

/// The farm's cameras: made once at start from the config (`[camera]`, `[printer.camera]`).
pub struct Cameras {
    printers: BTreeMap<String, PrinterCamera>,
    pub settings: CameraSettings,
    /// Where the jobs' snapshots and timelapses are kept: `<spool>/camera/<job>/`.
    root: PathBuf,
}

/// A source to fetch: its name (URL), where it comes from, and its feed's sending end.
pub type Source = (String, CameraSource, watch::Sender<CameraFeed>);

impl Cameras {
    /// The cameras of `config`, and the sources their tasks are to fetch (each camera once,
    /// whatever number of printers name it).
    pub fn new(config: &Config) -> (Cameras, Vec<Source>) {
        let mut sources: Vec<Source> = Vec::new();
        let mut printers = BTreeMap::new();
        for p in &config.printers {
            let Some(cam) = &p.camera else { continue };
            let name = cam.source.url().text.clone();
            let feed = match sources
                .iter()
                .find(|(n, s, _)| *n == name && *s == cam.source)
            {
                Some((_, _, tx)) => tx.subscribe(),
                None => {
                    let (tx, rx) = watch::channel(CameraFeed::starting());
                    sources.push((name.clone(), cam.source.clone(), tx));
                    rx
                }
            };
            printers.insert(
                p.name.clone(),
                PrinterCamera {
                    source: name,
                    feed,
                    transform: cam.transform,
                    made: Mutex::new(None),
                },
            );
        }
        let cameras = Cameras {
            printers,
            settings: config.camera.clone(),
            root: config.spool_dir.join("camera"),
        };
        (cameras, sources)
    }

    pub fn root(&self) -> &Path {
        &self.root
    }

    /// The printers that have a camera.
    pub fn printers(&self) -> impl Iterator<Item = &str> {
        self.printers.keys().map(String::as_str)
    }

    pub fn has(&self, printer: &str) -> bool {
        self.printers.contains_key(printer)
    }

    /// Follows a printer's camera (a new frame, a change of state).
    pub fn watch(&self, printer: &str) -> Option<watch::Receiver<CameraFeed>> {
        self.printers.get(printer).map(|c| c.feed.clone())
    }

    /// How a printer's camera is doing; `printing`: its printer prints now (a camera that
    /// repeats one picture then is frozen).
    pub fn status(&self, printer: &str, printing: bool) -> Option<CameraStatus> {
        let cam = self.printers.get(printer)?;
        let feed = cam.feed.borrow();
        let frozen = printing
            && feed.state == CameraState::Online
            && feed.same_since.elapsed() >= self.settings.frozen_after;
        Some(CameraStatus {
            printer: printer.to_string(),
            source: cam.source.clone(),
            state: if frozen {
                CameraState::Frozen
            } else {
                feed.state
            },
            error: if frozen {
                Some(format!(
                    "the same picture for {} s while the printer prints",
                    feed.same_since.elapsed().as_secs()
                ))
            } else {
                feed.error.clone()
            },
            frame_at: feed.frame.as_ref().map(|f| f.at),
            frames: feed.frames,
            failures: feed.failures,
        })
    }

    /// The printer's latest picture (blocking: it may decode and encode a frame), however
    /// old; None when it has no camera or no frame came yet.
    pub fn picture(&self, printer: &str) -> Option<Result<Picture, PictureError>> {
        let cam = self.printers.get(printer)?;
        let frame = cam.feed.borrow().frame.clone()?;
        Some(made(cam, &frame))
    }

    /// The printer's picture as the print is now (blocking, as [`Cameras::picture`]): a
    /// frame of a camera online now, no older than a few refreshes (a job's snapshot must
    /// show the print as it is, not as it was when the camera died); why there is none
    /// otherwise. None when the printer has no camera.
    pub fn fresh_picture(&self, printer: &str) -> Option<Result<Picture, NoFrame>> {
        let cam = self.printers.get(printer)?;
        let frame = {
            let feed = cam.feed.borrow();
            match (feed.state, &feed.frame) {
                (CameraState::Offline, _) => {
                    return Some(Err(NoFrame::Offline {
                        fault: feed.fault,
                        since: feed.offline_since,
                    }))
                }
                (CameraState::Starting, _) | (_, None) => return Some(Err(NoFrame::Starting)),
                (_, Some(frame)) => Arc::clone(frame),
            }
        };
        let max_age = (self.settings.refresh * 3).max(std::time::Duration::from_secs(15));
        let age = super::feed::unix_now() - frame.at;
        if age > max_age.as_secs_f64() {
            return Some(Err(NoFrame::Stale { age_s: age }));
        }
        Some(made(cam, &frame).map_err(|e| {
            tracing::warn!(printer, error = %e, "camera: no picture");
            NoFrame::Picture
        }))
    }
}

/// Why there was no picture of the print when one was wanted (a snapshot, a timelapse
/// frame), as data: a job's `camera.json` keeps it and the job page words it.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(tag = "kind", rename_all = "snake_case")]
pub enum NoFrame {
    /// The camera has given no frame yet.
    Starting,
    /// The camera is offline: its last failure, and since when (Unix seconds).
    Offline {
        fault: Option<CameraFault>,
        since: Option<f64>,
    },
    /// Its latest frame is this old (seconds), too old to show the print as it is.
    Stale { age_s: f64 },
    /// The frame could not be made into the printer's picture (cut and turned).
    Picture,
    /// The picture could not be written to the job's camera folder.
    Disk,
}

impl NoFrame {
    /// Whether `self` and `other` have the same cause (a run of layers without a frame
    /// is one entry while it does).
    pub fn same_cause(&self, other: &NoFrame) -> bool {
        use std::mem::discriminant;
        match (self, other) {
            (NoFrame::Offline { fault: a, .. }, NoFrame::Offline { fault: b, .. }) => {
                a.as_ref().map(discriminant) == b.as_ref().map(discriminant)
            }
            _ => discriminant(self) == discriminant(other),
        }
    }
}

/// The picture of `frame` for `cam`'s printer, the last one made when it is the same frame.
fn made(cam: &PrinterCamera, frame: &Frame) -> Result<Picture, PictureError> {
    let mut made = cam.made.lock().unwrap_or_else(|e| e.into_inner());
    if let Some((seq, jpeg)) = made.as_ref().filter(|(seq, _)| *seq == frame.seq) {
        return Ok(Picture {
            jpeg: jpeg.clone(),
            seq: *seq,
            at: frame.at,
        });
    }
    let jpeg = Bytes::from(picture::make(&frame.jpeg, &cam.transform)?);
    *made = Some((frame.seq, jpeg.clone()));
    Ok(Picture {
        jpeg,
        seq: frame.seq,
        at: frame.at,
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::time::{Duration, Instant};

    fn cameras(text: &str) -> (Cameras, Vec<Source>) {
        let config = Config::parse(
            &format!("[spool]\ndir = \"spool\"\n[camera]\nfrozen_after_s = 60\n{text}"),
            Path::new("/etc/crispen/crispen.toml"),
        )
        .unwrap();
        Cameras::new(&config)
    }

    fn printer(name: &str, camera: &str) -> String {
        format!("[[printer]]\nname = \"{name}\"\nfirmware = \"marlin2\"\n[printer.simulate]\n[printer.camera]\n{camera}\n")
    }

    /// One camera on a shelf is fetched once for all the printers that name it, each with
    /// its own crop; another camera is a source of its own.
    #[test]
    fn a_shared_camera_is_one_source() {
        let shelf = "snapshot = \"http://shelf:8080/snapshot\"";
        let (cams, sources) = cameras(
            &(printer("a", &format!("{shelf}\ncrop = [0, 0, 100, 100]"))
                + &printer("b", &format!("{shelf}\ncrop = [100, 0, 100, 100]"))
                + &printer("c", "stream = \"http://shelf:8080/stream\"")
                + "[[printer]]\nname = \"blind\"\nfirmware = \"marlin2\"\n[printer.simulate]\n"),
        );
        assert_eq!(sources.len(), 2);
        assert_eq!(cams.printers().collect::<Vec<_>>(), ["a", "b", "c"]);
        assert!(!cams.has("blind"));
        // A frame from the shelf is both a's and b's.
        sources[0].2.send_modify(|f| {
            f.state = CameraState::Online;
            f.frame = Some(Arc::new(Frame {
                jpeg: Bytes::from_static(b"\xff\xd8\xff"),
                seq: 1,
                at: crate::camera::feed::unix_now(),
            }));
        });
        for p in ["a", "b"] {
            assert_eq!(cams.status(p, false).unwrap().frames, 0);
            assert!(cams.status(p, false).unwrap().frame_at.is_some());
        }
        assert!(cams.status("c", false).unwrap().frame_at.is_none());
    }

    /// The same picture for `frozen_after_s` is a frozen camera while its printer prints,
    /// and an online one while it does not (a still room gives a still picture); a frame
    /// that old is no picture for a job's snapshot.
    #[test]
    fn a_camera_repeating_one_picture_while_printing_is_frozen() {
        let (cams, sources) = cameras(&printer("p", "snapshot = \"http://cam/snapshot\""));
        sources[0].2.send_modify(|f| {
            f.state = CameraState::Online;
            f.frame = Some(Arc::new(Frame {
                jpeg: Bytes::from_static(b"\xff\xd8\xff"),
                seq: 7,
                at: crate::camera::feed::unix_now() - 61.0,
            }));
            f.same_since = Instant::now() - Duration::from_secs(61);
        });
        let printing = cams.status("p", true).unwrap();
        assert_eq!(printing.state, CameraState::Frozen);
        assert!(printing.error.unwrap().contains("the same picture"));
        assert_eq!(cams.status("p", false).unwrap().state, CameraState::Online);
        assert!(
            matches!(cams.fresh_picture("p"), Some(Err(NoFrame::Stale { age_s })) if age_s > 60.0),
            "too old for a snapshot"
        );
        let shown = cams.picture("p").unwrap().unwrap();
        assert_eq!(shown.seq, 7);
    }
}
