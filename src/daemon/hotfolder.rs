//! Hot-folder pick-up: deciding when a file dropped into a watched folder is complete.
//!
//! A file counts as complete when it was renamed into the folder (inotify MOVED_TO), when
//! it was closed after writing (CLOSE_WRITE), or when its size and mtime stayed unchanged
//! for the settle time (for copies over network shares, where events are unreliable).
//! Temporary names (`*.part`, `*~`, dot-files) are never taken; sidecars (`*.toml`) are
//! reported like models, for the pick-up to match with their model. Models and G-code
//! sliced elsewhere (`*.gcode`, printed as it is) are taken alike; what a file is, is the
//! preparation's to find out.
//! [`SettleTracker`] is the pure decision; [`watch`] drives it with `notify` events, a
//! periodic rescan (in case an event was missed) and a short tick.

use notify::event::{AccessKind, AccessMode, ModifyKind, RenameMode};
use notify::{EventKind, RecursiveMode, Watcher};
use std::collections::HashMap;
use std::path::{Path, PathBuf};
use std::time::{Duration, Instant, SystemTime};
use tokio::sync::mpsc;

/// Whether a file name may be a model: not hidden, not a partial download, not a backup,
/// not a sidecar.
pub fn is_candidate_name(name: &str) -> bool {
    !(name.starts_with('.')
        || name.ends_with(".part")
        || name.ends_with('~')
        || name.ends_with(".toml")
        || name.ends_with(".tmp")
        || name.ends_with(".crdownload"))
}

/// Whether a file name is a model's sidecar (`model.stl.toml`). Sidecars are tracked too,
/// so one that arrives after its model can still be matched with it.
pub fn is_sidecar_name(name: &str) -> bool {
    !name.starts_with('.') && name.len() > ".toml".len() && name.ends_with(".toml")
}

#[derive(Debug)]
struct Seen {
    size: u64,
    mtime: Option<SystemTime>,
    unchanged_since: Instant,
    /// A CLOSE_WRITE or MOVED_TO event said the writer is done.
    finished_by_event: bool,
}

/// Tracks files in hot folders until they are complete. Pure apart from reading metadata.
#[derive(Debug)]
pub struct SettleTracker {
    settle: Duration,
    seen: HashMap<PathBuf, Seen>,
}

impl SettleTracker {
    pub fn new(settle: Duration) -> Self {
        SettleTracker {
            settle,
            seen: HashMap::new(),
        }
    }

    /// Starts tracking a path (idempotent). `finished` marks a close-after-write or
    /// rename-in event.
    pub fn note(&mut self, path: &Path, finished: bool) {
        let name = match path.file_name() {
            Some(n) => n.to_string_lossy(),
            None => return,
        };
        if !is_candidate_name(&name) && !is_sidecar_name(&name) {
            return;
        }
        let entry = self.seen.entry(path.to_path_buf()).or_insert(Seen {
            size: u64::MAX,
            mtime: None,
            unchanged_since: Instant::now(),
            finished_by_event: false,
        });
        if finished {
            entry.finished_by_event = true;
        }
    }

    /// Lists a folder and tracks every regular file in it.
    pub fn scan_dir(&mut self, dir: &Path) {
        let Ok(entries) = std::fs::read_dir(dir) else {
            return;
        };
        for entry in entries.flatten() {
            if entry.file_type().map(|t| t.is_file()).unwrap_or(false) {
                self.note(&entry.path(), false);
            }
        }
    }

    /// Returns the files that are complete now and stops tracking them (and files that
    /// vanished).
    pub fn take_complete(&mut self, now: Instant) -> Vec<PathBuf> {
        let mut done = Vec::new();
        let settle = self.settle;
        self.seen.retain(|path, seen| {
            // Not followed: a link could lead out of the folder to any file.
            let Ok(meta) = std::fs::symlink_metadata(path) else {
                return false;
            };
            if !meta.is_file() {
                if meta.is_symlink() {
                    tracing::warn!(file = %path.display(), "a symbolic link in a hot folder is not picked up");
                }
                return false;
            }
            let mtime = meta.modified().ok();
            if meta.len() != seen.size || mtime != seen.mtime {
                seen.size = meta.len();
                seen.mtime = mtime;
                seen.unchanged_since = now;
                if !seen.finished_by_event {
                    return true;
                }
            }
            if seen.finished_by_event || now.duration_since(seen.unchanged_since) >= settle {
                done.push(path.clone());
                return false;
            }
            true
        });
        done.sort();
        done
    }
}

/// Watches `folders` and sends each complete file (with its folder) on `out`, until `out`
/// is closed. Rescans every `rescan` and at start.
pub async fn watch(
    folders: Vec<PathBuf>,
    settle: Duration,
    rescan: Duration,
    out: mpsc::Sender<(PathBuf, PathBuf)>,
) {
    let (event_tx, mut event_rx) = mpsc::unbounded_channel::<(PathBuf, bool)>();
    let watcher = notify::recommended_watcher(move |res: notify::Result<notify::Event>| {
        let Ok(event) = res else { return };
        let finished = matches!(
            event.kind,
            EventKind::Access(AccessKind::Close(AccessMode::Write))
                | EventKind::Modify(ModifyKind::Name(RenameMode::To))
        );
        for path in event.paths {
            let _ = event_tx.send((path, finished));
        }
    });
    let mut watcher = match watcher {
        Ok(w) => Some(w),
        Err(e) => {
            tracing::warn!(error = %e, "cannot watch hot folders; relying on periodic rescans");
            None
        }
    };
    for folder in &folders {
        if let Err(e) = std::fs::create_dir_all(folder) {
            tracing::error!(folder = %folder.display(), error = %e, "cannot create hot folder");
        }
        if let Some(w) = watcher.as_mut() {
            if let Err(e) = w.watch(folder, RecursiveMode::NonRecursive) {
                tracing::warn!(folder = %folder.display(), error = %e, "cannot watch hot folder; relying on rescans");
            }
        }
    }
    let mut tracker = SettleTracker::new(settle);
    for folder in &folders {
        tracker.scan_dir(folder);
    }
    let tick = (settle / 4).clamp(Duration::from_millis(50), Duration::from_millis(500));
    let mut ticker = tokio::time::interval(tick);
    let mut rescan_timer = tokio::time::interval(rescan);
    rescan_timer.tick().await;
    loop {
        tokio::select! {
            _ = out.closed() => break,
            Some((path, finished)) = event_rx.recv() => {
                if path.parent().is_some_and(|p| folders.iter().any(|f| f == p)) {
                    tracker.note(&path, finished);
                }
            }
            _ = rescan_timer.tick() => {
                for folder in &folders {
                    tracker.scan_dir(folder);
                }
            }
            _ = ticker.tick() => {
                for path in tracker.take_complete(Instant::now()) {
                    let folder = path.parent().map(Path::to_path_buf).unwrap_or_default();
                    if out.send((path, folder)).await.is_err() {
                        return;
                    }
                }
            }
        }
    }
    drop(watcher);
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::io::Write;

    #[test]
    fn names_that_are_never_taken() {
        for name in [".hidden.stl", "x.stl.part", "x.stl~", "x.stl.toml", "x.tmp"] {
            assert!(!is_candidate_name(name), "{name}");
        }
        // Pre-sliced G-code is taken too (printed as it is); binary G-code is taken so
        // that its job fails with the reason rather than the file lying there unnoticed.
        for name in [
            "x.stl",
            "bust.OBJ",
            "a b.3mf",
            "noext",
            "part.gcode",
            "part.bgcode",
        ] {
            assert!(is_candidate_name(name), "{name}");
        }
    }

    #[test]
    fn growing_file_waits_for_settle_and_event_completes_at_once() {
        let tmp = tempfile::tempdir().unwrap();
        let mut tracker = SettleTracker::new(Duration::from_millis(200));
        let growing = tmp.path().join("grow.stl");
        let mut f = std::fs::File::create(&growing).unwrap();
        f.write_all(b"part one").unwrap();
        tracker.scan_dir(tmp.path());
        let t0 = Instant::now();
        assert!(tracker.take_complete(t0).is_empty());
        f.write_all(b" and more").unwrap();
        f.flush().unwrap();
        // Size changed: the settle clock restarts.
        assert!(tracker
            .take_complete(t0 + Duration::from_millis(150))
            .is_empty());
        assert!(tracker
            .take_complete(t0 + Duration::from_millis(300))
            .is_empty());
        assert_eq!(
            tracker.take_complete(t0 + Duration::from_millis(400)),
            vec![growing.clone()]
        );
        // Taken once only.
        assert!(tracker
            .take_complete(t0 + Duration::from_secs(5))
            .is_empty());

        let renamed = tmp.path().join("in.stl");
        std::fs::write(&renamed, b"x").unwrap();
        tracker.note(&renamed, true);
        assert_eq!(tracker.take_complete(Instant::now()), vec![renamed]);

        let part = tmp.path().join("big.stl.part");
        std::fs::write(&part, b"x").unwrap();
        tracker.note(&part, true);
        assert!(tracker
            .take_complete(Instant::now() + Duration::from_secs(9))
            .is_empty());
    }

    /// A link is never taken, even when an event says it is complete: it could lead out
    /// of the folder to any file the daemon may read.
    #[test]
    fn symbolic_links_are_never_taken() {
        let tmp = tempfile::tempdir().unwrap();
        let target = tmp.path().join("elsewhere.stl");
        std::fs::write(&target, b"x").unwrap();
        let hot = tmp.path().join("hot");
        std::fs::create_dir(&hot).unwrap();
        let link = hot.join("link.stl");
        std::os::unix::fs::symlink(&target, &link).unwrap();
        let mut tracker = SettleTracker::new(Duration::from_millis(10));
        tracker.note(&link, true);
        tracker.scan_dir(&hot);
        assert!(tracker
            .take_complete(Instant::now() + Duration::from_secs(1))
            .is_empty());
    }
}
