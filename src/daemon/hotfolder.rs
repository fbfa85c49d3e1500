//! Hot-folder pick-up: deciding when a file dropped into a watched folder is complete.
//!
//! A file counts as complete when it was renamed into the folder (inotify MOVED_TO), when
//! it was closed after writing (CLOSE_WRITE), or when its size and mtime stayed unchanged
//! for the settle time (for copies over network shares, where events are unreliable).
//! Temporary names (`*.part`, `*~`, dot-files) are never taken; sidecars (`*.toml`) are
//! reported like models, for the pick-up to match with their model. Models and G-code
//! sliced elsewhere (`*.gcode`, printed as it is) are taken alike; what a file is, is the
//! preparation's to find out.
//! A name with control or bidi characters is refused (set aside in [`SET_ASIDE_DIR`]) by
//! the check every operator-given name goes through ([`crate::names::problem`]), and
//! names are shown through [`printable`] wherever they are printed.
//! A folder directly in a hot folder is a plate of several models (see
//! `daemon::plate_folder`); it is complete when nothing in it changed for the settle
//! time, or when it was renamed in whole.
//! [`SettleTracker`] is the pure decision; [`watch`] drives it with `notify` events, a
//! periodic rescan (in case an event was missed) and a short tick.

use notify::event::{AccessKind, AccessMode, ModifyKind, RenameMode};
use notify::{EventKind, RecursiveMode, Watcher};
use std::collections::HashMap;
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Arc;
use std::time::{Duration, Instant, SystemTime};
use tokio::sync::mpsc;

/// What a file is, by its name's extension (any case): the one classifier the pick-up, the
/// preparation and the upload share.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(crate) enum FileKind {
    /// A model for the pipeline (`.stl`, `.obj`, `.3mf`).
    Model,
    /// G-code sliced elsewhere, printed as it is (`.gcode`, `.gco`, `.g`), or binary G-code
    /// (`.bgcode`), which the preparation refuses with the reason.
    Gcode,
}

/// Model formats the pipeline takes.
const MODEL_EXTENSIONS: [&str; 3] = ["stl", "obj", "3mf"];
/// G-code sliced elsewhere.
const GCODE_EXTENSIONS: [&str; 4] = ["gcode", "gco", "g", "bgcode"];

/// The kind of file `name` is, or None when its extension is neither a model's nor
/// G-code's.
pub(crate) fn file_kind(name: &str) -> Option<FileKind> {
    let (_, extension) = name.rsplit_once('.')?;
    let extension = extension.to_ascii_lowercase();
    if MODEL_EXTENSIONS.contains(&extension.as_str()) {
        Some(FileKind::Model)
    } else if GCODE_EXTENSIONS.contains(&extension.as_str()) {
        Some(FileKind::Gcode)
    } else {
        None
    }
}

/// Whether a file name may be a model: not hidden, not a partial download, not a backup,
/// not a sidecar.
pub(crate) fn is_candidate_name(name: &str) -> bool {
    !(name.starts_with('.')
        || name.ends_with(".part")
        || name.ends_with('~')
        || name.ends_with(".toml")
        || name.ends_with(".tmp")
        || name.ends_with(".crdownload"))
}

/// The folder inside a hot folder where the pick-up sets aside files it refuses (a name
/// with control or bidi characters, a sidecar whose model never came). The watcher takes
/// only files directly in the hot folder, never from here.
pub(crate) const SET_ASIDE_DIR: &str = "set-aside";

/// A sidecar whose model has not arrived within this many settle times (10 minutes at
/// the default `settle_s = 5`) is set aside.
pub(crate) const ORPHAN_SIDECAR_SETTLES: u32 = 120;

/// Moves `path` (a file or a plate folder) into `folder/`[`SET_ASIDE_DIR`] under its own
/// name (`.1`, `.2`, … added if that is taken), never replacing a file. Returns where it
/// went.
pub(crate) fn set_aside(path: &Path, folder: &Path) -> std::io::Result<PathBuf> {
    let dir = folder.join(SET_ASIDE_DIR);
    std::fs::create_dir_all(&dir)?;
    let name = path.file_name().unwrap_or_default();
    for n in 0..1000 {
        let mut to_name = name.to_os_string();
        if n > 0 {
            to_name.push(format!(".{n}"));
        }
        let to = dir.join(to_name);
        match move_no_replace(path, &to) {
            Ok(()) => return Ok(to),
            Err(e) if e.kind() == std::io::ErrorKind::AlreadyExists => continue,
            Err(e) => return Err(e),
        }
    }
    Err(std::io::Error::new(
        std::io::ErrorKind::AlreadyExists,
        "1000 files of this name are set aside already",
    ))
}

/// Moves a file or a folder to `to`, failing rather than replacing what is there (the hot
/// folder and its set-aside folder are on one file system).
fn move_no_replace(from: &Path, to: &Path) -> std::io::Result<()> {
    use nix::fcntl::{renameat2, RenameFlags, AT_FDCWD};
    renameat2(AT_FDCWD, from, AT_FDCWD, to, RenameFlags::RENAME_NOREPLACE)
        .map_err(std::io::Error::from)
}

// A name is shown through the one function for every name an operator gives.
pub use crate::names::{escaped, printable};

/// Whether a file name is a model's sidecar (`model.stl.toml`). Sidecars are tracked too,
/// so one that arrives after its model can still be matched with it.
pub(crate) fn is_sidecar_name(name: &str) -> bool {
    !name.starts_with('.') && name.len() > ".toml".len() && name.ends_with(".toml")
}

/// A file name in its one spelling, Unicode NFC: `café` typed on one machine may arrive
/// composed (U+00E9) and on another decomposed (`e` and U+0301, as macOS writes names);
/// the two look alike everywhere they are shown, so they are one name to the farm. A job's
/// name, an upload's name and every comparison of names go through this.
pub fn normal_name(name: &str) -> std::borrow::Cow<'_, str> {
    use unicode_normalization::UnicodeNormalization;
    match unicode_normalization::is_nfc(name) {
        true => std::borrow::Cow::Borrowed(name),
        false => std::borrow::Cow::Owned(name.nfc().collect()),
    }
}

/// Whether two file names are one name, perhaps spelt differently (see [`normal_name`]).
pub fn same_name(a: &str, b: &str) -> bool {
    a == b || normal_name(a) == normal_name(b)
}

/// What is directly in `folder` under `name` in any of its spellings (a file, a directory,
/// a link: not followed): `folder/name` itself when it is there, else the first entry whose
/// name is [`same_name`] as it. None when neither is there or the folder cannot be listed.
/// Blocking: one `lstat`, and a listing of the folder only when that finds nothing.
pub(crate) fn find_named(folder: &Path, name: &str) -> Option<PathBuf> {
    let exact = folder.join(name);
    if std::fs::symlink_metadata(&exact).is_ok() {
        return Some(exact);
    }
    let wanted = normal_name(name);
    std::fs::read_dir(folder)
        .ok()?
        .flatten()
        .find(|e| {
            e.file_name()
                .to_str()
                .is_some_and(|n| normal_name(n) == wanted)
        })
        .map(|e| e.path())
}

#[derive(Debug)]
struct Seen {
    /// What a look found last: a file's size, or a folder's files and bytes.
    size: (u64, u64),
    mtime: Option<SystemTime>,
    unchanged_since: Instant,
    /// A CLOSE_WRITE or MOVED_TO event said the writer is done.
    finished_by_event: bool,
}

/// What a look at a tracked path found (read on a blocking thread: see [`look`]).
#[derive(Debug, Clone, PartialEq)]
pub(crate) enum Found {
    /// Nothing is there any more (or it cannot be read).
    Gone,
    /// A symbolic link: never followed, since it could lead out of the folder to any file.
    Symlink,
    /// A device, a FIFO: nothing to take.
    NotAFile,
    File {
        size: u64,
        mtime: Option<SystemTime>,
    },
    /// A folder (a plate of models): the files directly in it, their bytes, and the
    /// latest change to it or to any of them.
    Folder {
        files: u64,
        bytes: u64,
        mtime: Option<SystemTime>,
    },
}

/// What a folder holds, for [`Found::Folder`].
fn look_into(dir: &Path, own_mtime: Option<SystemTime>) -> Found {
    let (mut files, mut bytes, mut mtime) = (0u64, 0u64, own_mtime);
    for meta in std::fs::read_dir(dir)
        .into_iter()
        .flatten()
        .flatten()
        .filter_map(|e| e.metadata().ok())
    {
        files += 1;
        bytes = bytes.saturating_add(meta.len());
        mtime = mtime.max(meta.modified().ok());
    }
    Found::Folder {
        files,
        bytes,
        mtime,
    }
}

/// Looks at each path, not following links. Blocking, one `lstat` per path: run it on a
/// blocking thread, never on the async worker (a hot folder on NFS may take seconds).
pub(crate) fn look(paths: Vec<PathBuf>) -> Vec<(PathBuf, Found)> {
    paths
        .into_iter()
        .map(|path| {
            let found = match std::fs::symlink_metadata(&path) {
                Err(_) => Found::Gone,
                Ok(meta) if meta.is_file() => Found::File {
                    size: meta.len(),
                    mtime: meta.modified().ok(),
                },
                Ok(meta) if meta.is_symlink() => Found::Symlink,
                Ok(meta) if meta.is_dir() => look_into(&path, meta.modified().ok()),
                Ok(_) => Found::NotAFile,
            };
            (path, found)
        })
        .collect()
}

/// The regular files and folders directly in `dir` (none when it cannot be listed).
/// Blocking, like [`look`].
pub(crate) fn list_files(dir: &Path) -> Vec<PathBuf> {
    let Ok(entries) = std::fs::read_dir(dir) else {
        return Vec::new();
    };
    entries
        .flatten()
        .filter(|e| {
            e.file_type()
                .map(|t| t.is_file() || t.is_dir())
                .unwrap_or(false)
        })
        .map(|e| e.path())
        .collect()
}

/// Tracks files in hot folders until they are complete. The decision ([`Self::complete`])
/// is pure: what the file system holds comes in from [`look`] and [`list_files`].
#[derive(Debug)]
pub(crate) struct SettleTracker {
    settle: Duration,
    seen: HashMap<PathBuf, Seen>,
}

impl SettleTracker {
    pub(crate) fn new(settle: Duration) -> Self {
        SettleTracker {
            settle,
            seen: HashMap::new(),
        }
    }

    /// Starts tracking a path (idempotent). `finished` marks a close-after-write or
    /// rename-in event.
    pub(crate) fn note(&mut self, path: &Path, finished: bool) {
        let name = match path.file_name() {
            Some(n) => n.to_string_lossy(),
            None => return,
        };
        if !is_candidate_name(&name) && !is_sidecar_name(&name) || name == SET_ASIDE_DIR {
            return;
        }
        let entry = self.seen.entry(path.to_path_buf()).or_insert(Seen {
            size: (u64::MAX, u64::MAX),
            mtime: None,
            unchanged_since: Instant::now(),
            finished_by_event: false,
        });
        if finished {
            entry.finished_by_event = true;
        }
    }

    /// The paths tracked, for [`look`].
    pub(crate) fn tracked(&self) -> Vec<PathBuf> {
        self.seen.keys().cloned().collect()
    }

    /// Lists a folder and tracks every regular file in it. Blocking (see [`list_files`]).
    #[cfg(test)]
    pub(crate) fn scan_dir(&mut self, dir: &Path) {
        for path in list_files(dir) {
            self.note(&path, false);
        }
    }

    /// Looks at every tracked file and returns those complete now (see
    /// [`Self::complete`]). Blocking (see [`look`]).
    #[cfg(test)]
    pub(crate) fn take_complete(&mut self, now: Instant) -> Vec<PathBuf> {
        let found = look(self.tracked());
        self.complete(found, now)
    }

    /// From what a look found, the files that are complete now; stops tracking them and
    /// what is gone or no regular file. A tracked path the look did not cover is kept.
    pub(crate) fn complete(&mut self, found: Vec<(PathBuf, Found)>, now: Instant) -> Vec<PathBuf> {
        let mut done = Vec::new();
        for (path, found) in found {
            let Some(seen) = self.seen.get_mut(&path) else {
                continue;
            };
            let (size, mtime) = match found {
                Found::File { size, mtime } => ((size, 0), mtime),
                Found::Folder {
                    files,
                    bytes,
                    mtime,
                } => ((bytes, files), mtime),
                Found::Symlink => {
                    tracing::warn!(file = %path.display(), "a symbolic link in a hot folder is not picked up");
                    self.seen.remove(&path);
                    continue;
                }
                Found::Gone | Found::NotAFile => {
                    self.seen.remove(&path);
                    continue;
                }
            };
            if size != seen.size || mtime != seen.mtime {
                seen.size = size;
                seen.mtime = mtime;
                seen.unchanged_since = now;
                if !seen.finished_by_event {
                    continue;
                }
            }
            if seen.finished_by_event || now.duration_since(seen.unchanged_since) >= self.settle {
                self.seen.remove(&path);
                done.push(path);
            }
        }
        done.sort();
        done
    }
}

/// The first wait before a file whose pick-up failed is tried again.
const RETRY_FIRST: Duration = Duration::from_secs(1);
/// The longest wait: the wait doubles with each failure up to this.
const RETRY_MOST: Duration = Duration::from_secs(60);

/// Files whose pick-up failed (the spool's disk full): each is tried again after a wait
/// that doubles with each failure, from [`RETRY_FIRST`] to [`RETRY_MOST`], and not before,
/// however often the watcher offers it meanwhile (a failed pick-up that moves the file
/// back, or reads it, makes events of its own). The pure decision, with time passed in.
#[derive(Debug, Default)]
pub(crate) struct Retries {
    waiting: HashMap<PathBuf, Retry>,
}

#[derive(Debug)]
struct Retry {
    folder: PathBuf,
    failures: u32,
    at: Instant,
}

impl Retries {
    /// Notes that picking up `path` (of `folder`) failed at `now`; the wait until it is
    /// tried again.
    pub(crate) fn failed(&mut self, path: &Path, folder: &Path, now: Instant) -> Duration {
        let retry = self.waiting.entry(path.to_path_buf()).or_insert(Retry {
            folder: folder.to_path_buf(),
            failures: 0,
            at: now,
        });
        retry.failures = retry.failures.saturating_add(1);
        let wait = RETRY_FIRST
            .saturating_mul(1 << (retry.failures - 1).min(16))
            .min(RETRY_MOST);
        retry.at = now + wait;
        wait
    }

    /// `path` was picked up, or is gone: no more tries.
    pub(crate) fn forget(&mut self, path: &Path) {
        self.waiting.remove(path);
    }

    /// Whether `path` waits to be tried again after `now` (so an offer now is passed over).
    pub(crate) fn waits(&self, path: &Path, now: Instant) -> bool {
        self.waiting.get(path).is_some_and(|r| r.at > now)
    }

    /// When the next file is due, if any waits.
    pub(crate) fn next_due(&self) -> Option<Instant> {
        self.waiting.values().map(|r| r.at).min()
    }

    /// The files due at `now`, with their folders (they stay noted until they are
    /// picked up or forgotten).
    pub(crate) fn due(&self, now: Instant) -> Vec<(PathBuf, PathBuf)> {
        let mut due: Vec<(PathBuf, PathBuf)> = self
            .waiting
            .iter()
            .filter(|(_, r)| r.at <= now)
            .map(|(p, r)| (p.clone(), r.folder.clone()))
            .collect();
        due.sort();
        due
    }
}

/// Runs file-system work on a blocking thread, so a slow hot folder (NFS) never stalls the
/// async worker's other tasks (printer streams, the HTTP API). A panic there is the
/// watcher's own; None when the runtime is shutting down.
pub(crate) async fn blocking<R: Send + 'static>(
    work: impl FnOnce() -> R + Send + 'static,
) -> Option<R> {
    match tokio::task::spawn_blocking(work).await {
        Ok(result) => Some(result),
        Err(e) if e.is_panic() => std::panic::resume_unwind(e.into_panic()),
        Err(_) => None,
    }
}

/// Most file-system events waiting for the watcher's loop. A burst beyond it (thousands
/// of files dropped at once) is not queued: the events are dropped, the folders are
/// scanned again at the next tick, and a file whose "finished" event was dropped is taken
/// once its size and mtime stayed unchanged for the settle time, as on a network share.
const EVENT_QUEUE: usize = 1024;

/// The bounded queue from `notify`'s thread to the watcher's loop; it never blocks the
/// sender, and says when it dropped an event.
struct EventQueue {
    tx: mpsc::Sender<(PathBuf, bool)>,
    overflowed: Arc<AtomicBool>,
}

impl EventQueue {
    fn new(capacity: usize) -> (EventQueue, mpsc::Receiver<(PathBuf, bool)>) {
        let (tx, rx) = mpsc::channel(capacity);
        let queue = EventQueue {
            tx,
            overflowed: Arc::new(AtomicBool::new(false)),
        };
        (queue, rx)
    }

    /// Queues one event, or notes that it was dropped (queue full, or the loop is gone).
    fn offer(&self, path: PathBuf, finished: bool) {
        if self.tx.try_send((path, finished)).is_err() {
            self.overflowed.store(true, Ordering::SeqCst);
        }
    }
}

/// Watches `folders` and sends each complete file (with its folder) on `out`, until `out`
/// is closed. Rescans every `rescan` and at start.
pub(crate) async fn watch(
    folders: Vec<PathBuf>,
    settle: Duration,
    rescan: Duration,
    out: mpsc::Sender<(PathBuf, PathBuf)>,
) {
    let (events, mut event_rx) = EventQueue::new(EVENT_QUEUE);
    let overflowed = Arc::clone(&events.overflowed);
    let watcher = notify::recommended_watcher(move |res: notify::Result<notify::Event>| {
        let Ok(event) = res else { return };
        let finished = matches!(
            event.kind,
            EventKind::Access(AccessKind::Close(AccessMode::Write))
                | EventKind::Modify(ModifyKind::Name(RenameMode::To))
        );
        for path in event.paths {
            events.offer(path, finished);
        }
    });
    let mut watcher = match watcher {
        Ok(w) => Some(w),
        Err(e) => {
            tracing::warn!(error = %e, "cannot watch hot folders; relying on periodic rescans");
            None
        }
    };
    let to_create = folders.clone();
    let Some(created) = blocking(move || {
        to_create
            .iter()
            .map(|folder| std::fs::create_dir_all(folder).err())
            .collect::<Vec<_>>()
    })
    .await
    else {
        return;
    };
    for (folder, error) in folders.iter().zip(created) {
        if let Some(e) = error {
            tracing::error!(folder = %folder.display(), error = %e, "cannot create hot folder");
        }
        if let Some(w) = watcher.as_mut() {
            if let Err(e) = w.watch(folder, RecursiveMode::NonRecursive) {
                tracing::warn!(folder = %folder.display(), error = %e, "cannot watch hot folder; relying on rescans");
            }
        }
    }
    let mut tracker = SettleTracker::new(settle);
    // Every listing and look below runs on a blocking thread; the loop waits for it (events
    // meanwhile wait in their bounded queue) and decides on the async side.
    let list_all = |folders: &Vec<PathBuf>| {
        let folders = folders.clone();
        blocking(move || {
            folders
                .iter()
                .flat_map(|f| list_files(f))
                .collect::<Vec<_>>()
        })
    };
    let Some(listed) = list_all(&folders).await else {
        return;
    };
    for path in &listed {
        tracker.note(path, false);
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
                let Some(listed) = list_all(&folders).await else {
                    return;
                };
                for path in &listed {
                    tracker.note(path, false);
                }
            }
            _ = ticker.tick() => {
                // Events were dropped: list the folders now rather than at the next
                // periodic rescan, then look at every tracked file, in one trip.
                let rescan = overflowed.swap(false, Ordering::SeqCst).then(|| folders.clone());
                let tracked = tracker.tracked();
                let now = Instant::now();
                let Some((listed, found)) = blocking(move || {
                    let listed: Vec<PathBuf> =
                        rescan.iter().flatten().flat_map(|f| list_files(f)).collect();
                    // The files just listed are looked at too, as if noted before the look.
                    let mut paths = tracked;
                    paths.extend(listed.iter().cloned());
                    paths.sort();
                    paths.dedup();
                    (listed, look(paths))
                })
                .await
                else {
                    return;
                };
                for path in &listed {
                    tracker.note(path, false);
                }
                for path in tracker.complete(found, now) {
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

    /// One list of extensions for everyone: `.bgcode` is G-code to the upload as it is to
    /// the preparation (the upload's own list once lacked it).
    #[test]
    fn file_kinds() {
        for name in ["a.stl", "A.OBJ", "b.c.3mf"] {
            assert_eq!(file_kind(name), Some(FileKind::Model), "{name}");
        }
        for name in ["a.gcode", "A.GCO", "a.g", "part.bgcode", "PART.BGCODE"] {
            assert_eq!(file_kind(name), Some(FileKind::Gcode), "{name}");
        }
        for name in ["gcode", "a.ply", "a.gcode.txt", "a.", "stl", "a.xbgcode"] {
            assert_eq!(file_kind(name), None, "{name}");
        }
    }

    /// The event queue from notify's thread is bounded: a burst beyond it is dropped and
    /// noted (for a rescan at the next tick), never held in memory without limit.
    #[test]
    fn the_event_queue_is_bounded_and_says_when_it_dropped() {
        let (queue, mut rx) = EventQueue::new(2);
        for i in 0..5 {
            queue.offer(PathBuf::from(format!("f{i}.stl")), true);
        }
        assert!(queue.overflowed.load(Ordering::SeqCst));
        let mut got = Vec::new();
        while let Ok((path, _)) = rx.try_recv() {
            got.push(path);
        }
        assert_eq!(got, [PathBuf::from("f0.stl"), PathBuf::from("f1.stl")]);
    }

    /// The decision is made from what a look found, with no file system call of its own
    /// (the watcher looks on a blocking thread): these paths do not exist.
    #[test]
    fn the_decision_is_made_from_what_a_look_found() {
        let settle = Duration::from_secs(1);
        let mut tracker = SettleTracker::new(settle);
        let [a, b, c, d, e] = ["a.stl", "b.stl", "c.stl", "d.stl", "e.stl"]
            .map(|n| PathBuf::from("/nowhere/crispen").join(n));
        for path in [&a, &b, &c, &d, &e] {
            tracker.note(path, false);
        }
        tracker.note(&b, true);
        let file = |size| Found::File { size, mtime: None };
        let t0 = Instant::now();
        let found = vec![
            (a.clone(), file(10)),
            (b.clone(), file(5)),
            (c.clone(), Found::Symlink),
            (d.clone(), Found::Gone),
            (e.clone(), Found::NotAFile),
            // Not tracked (no event, no listing noted it): ignored.
            (PathBuf::from("/nowhere/crispen/f.stl"), file(1)),
        ];
        assert_eq!(tracker.complete(found, t0), vec![b.clone()]);
        assert_eq!(tracker.tracked(), vec![a.clone()]);
        // Unchanged for less than the settle time, then for the settle time.
        let half = t0 + settle / 2;
        assert!(tracker
            .complete(vec![(a.clone(), file(10))], half)
            .is_empty());
        // A change starts the wait again.
        assert!(tracker
            .complete(vec![(a.clone(), file(11))], t0 + settle)
            .is_empty());
        assert!(
            tracker.complete(vec![], t0 + settle * 3).is_empty(),
            "not looked at"
        );
        assert_eq!(
            tracker.complete(vec![(a.clone(), file(11))], t0 + settle * 2),
            vec![a]
        );
    }

    /// A file whose events were all dropped is still taken: the rescan notes it, and it
    /// is complete once unchanged for the settle time.
    #[test]
    fn a_file_without_events_is_taken_by_a_rescan() {
        let tmp = tempfile::tempdir().unwrap();
        std::fs::write(tmp.path().join("quiet.stl"), b"solid x\n").unwrap();
        let mut tracker = SettleTracker::new(Duration::from_secs(1));
        tracker.scan_dir(tmp.path());
        let later = Instant::now() + Duration::from_secs(5);
        tracker.take_complete(Instant::now());
        assert_eq!(tracker.take_complete(later), [tmp.path().join("quiet.stl")]);
    }

    /// A failed pick-up is tried again after 1, 2, 4 ... s, at most a minute apart, and
    /// never while it waits; each file on its own, until it is picked up or gone.
    #[test]
    fn failed_pickups_back_off_each_on_its_own() {
        let t0 = Instant::now();
        let (a, b, hot) = (
            Path::new("/h/a.stl"),
            Path::new("/h/b.stl"),
            Path::new("/h"),
        );
        let mut retries = Retries::default();
        assert_eq!(retries.next_due(), None);
        assert!(!retries.waits(a, t0));
        let mut now = t0;
        let mut waits = Vec::new();
        for _ in 0..10 {
            let wait = retries.failed(a, hot, now);
            waits.push(wait.as_secs());
            assert!(retries.waits(a, now));
            assert!(retries.waits(a, now + wait - Duration::from_millis(1)));
            assert!(retries
                .due(now + wait - Duration::from_millis(1))
                .is_empty());
            now += wait;
            assert!(!retries.waits(a, now));
            assert_eq!(retries.due(now), [(a.to_path_buf(), hot.to_path_buf())]);
        }
        assert_eq!(waits, [1, 2, 4, 8, 16, 32, 60, 60, 60, 60]);
        // A second file starts at the first wait; the next due is the earlier of the two.
        assert_eq!(retries.failed(b, hot, now), RETRY_FIRST);
        assert_eq!(retries.next_due(), Some(now));
        retries.forget(a);
        assert_eq!(retries.next_due(), Some(now + RETRY_FIRST));
        assert!(!retries.waits(a, now));
        // Failing for ever stays bounded (no overflow).
        for _ in 0..100 {
            assert!(retries.failed(b, hot, now) <= RETRY_MOST);
        }
        retries.forget(b);
        assert_eq!(retries.next_due(), None);
    }

    /// Two spellings of one name are one name; a name is found in a folder in either.
    #[test]
    fn two_spellings_are_one_name() {
        let composed = "caf\u{e9}.gcode";
        let decomposed = "cafe\u{301}.gcode";
        assert_ne!(composed, decomposed);
        assert_eq!(normal_name(decomposed), composed);
        assert!(matches!(
            normal_name(composed),
            std::borrow::Cow::Borrowed(_)
        ));
        assert!(same_name(composed, decomposed));
        assert!(!same_name(composed, "cafe.gcode"));
        // The Kelvin sign is K in its one spelling.
        assert_eq!(normal_name("\u{212a}.stl"), "K.stl");
        let tmp = tempfile::tempdir().unwrap();
        assert_eq!(find_named(tmp.path(), composed), None);
        std::fs::write(tmp.path().join(decomposed), b"x").unwrap();
        for name in [composed, decomposed] {
            assert_eq!(
                find_named(tmp.path(), name),
                Some(tmp.path().join(decomposed)),
                "{name:?}"
            );
        }
        assert_eq!(find_named(tmp.path(), "cafe.gcode"), None);
        assert_eq!(find_named(&tmp.path().join("none"), composed), None);
    }

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

    /// A folder (a plate of models) is complete once nothing in it changed for the settle
    /// time: a file added or grown starts the wait again. The set-aside folder and hidden
    /// ones (the plates' staging) are never taken.
    #[test]
    fn a_folder_is_complete_once_nothing_in_it_changes() {
        let tmp = tempfile::tempdir().unwrap();
        let hot = tmp.path();
        let plate = hot.join("set");
        for dir in [
            plate.clone(),
            hot.join(SET_ASIDE_DIR),
            hot.join(".crispen-plates"),
        ] {
            std::fs::create_dir(&dir).unwrap();
        }
        let settle = Duration::from_millis(200);
        let mut tracker = SettleTracker::new(settle);
        tracker.scan_dir(hot);
        assert_eq!(tracker.tracked(), std::slice::from_ref(&plate));
        let t0 = Instant::now();
        assert!(tracker.take_complete(t0).is_empty());
        std::fs::write(plate.join("a.stl"), b"solid").unwrap();
        assert!(tracker.take_complete(t0 + settle).is_empty(), "a file came");
        let mut f = std::fs::File::options()
            .append(true)
            .open(plate.join("a.stl"))
            .unwrap();
        f.write_all(b" a").unwrap();
        assert!(tracker.take_complete(t0 + settle * 2).is_empty(), "it grew");
        assert!(tracker.take_complete(t0 + settle * 5 / 2).is_empty());
        assert_eq!(tracker.take_complete(t0 + settle * 3), [plate]);
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
