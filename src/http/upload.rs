//! Files uploaded into a hot folder: the folder is named by the last component of its
//! path, the file name is checked to be one plain name of a model, a sidecar or G-code, the bytes are streamed to a
//! hidden temporary file in that folder (which the hot-folder watcher never takes), and
//! the finished file is hard-linked to its name, which fails rather than replace a file
//! already there. Nothing is ever written outside a configured hot folder. A held upload
//! (see the `octoprint` module) links its sidecar right before its model.

use super::{ApiError, UPLOAD_IDLE_TIMEOUT};
use crate::daemon::config::{Config, FolderConfig};
use axum::body::Bytes;
use axum::http::StatusCode;
use futures_util::{Stream, StreamExt};
use std::path::{Path, PathBuf};
use tokio::io::AsyncWriteExt;

/// Longest file name accepted (the usual file system limit).
const MAX_NAME_BYTES: usize = 200;

/// A hot folder's name as the API shows it: the last component of its path.
pub(crate) fn folder_name(folder: &FolderConfig) -> String {
    folder
        .path
        .file_name()
        .map(|n| n.to_string_lossy().into_owned())
        .unwrap_or_else(|| folder.path.display().to_string())
}

/// The hot folder called `name`.
pub(crate) fn find_folder<'a>(
    config: &'a Config,
    name: &str,
) -> Result<&'a FolderConfig, ApiError> {
    let names = || {
        config
            .folders
            .iter()
            .map(folder_name)
            .collect::<Vec<_>>()
            .join(", ")
    };
    let mut found = config.folders.iter().filter(|f| folder_name(f) == name);
    match (found.next(), found.next()) {
        (Some(f), None) => Ok(f),
        (Some(_), Some(_)) => Err(ApiError::conflict(format!(
            "two hot folders are called {}; rename one of them so uploads can tell them apart",
            super::error::quoted(name)
        ))),
        (None, _) => Err(ApiError::not_found(format!(
            "no hot folder called {} (the folders are: {})",
            super::error::quoted(name),
            names()
        ))),
    }
}

/// What kind of file an upload is, by its name.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Upload {
    Model,
    Sidecar,
    Gcode,
}

/// An uploaded file's name as the farm keeps it: in its one spelling (NFC, see
/// [`crate::daemon::hotfolder::normal_name`]), then checked by [`check_name`]. Every way
/// an upload's name arrives goes through this, so `café.gcode` composed and decomposed
/// land on one file name, and a second one is refused as a second identical name is.
pub fn upload_name(name: &str) -> Result<(String, Upload), ApiError> {
    let name = crate::daemon::hotfolder::normal_name(name).into_owned();
    let kind = check_name(&name)?;
    Ok((name, kind))
}

/// Checks an uploaded file's name: exactly one plain path component (no directories, not
/// `.` or `..`, not hidden, not a temporary name the watcher skips), at most
/// [`MAX_NAME_BYTES`], without control or bidi characters, of a model, G-code, or the
/// sidecar of one. Every upload passes this whatever its other fields say, and
/// [`receive`] checks again before it writes anything.
pub fn check_name(name: &str) -> Result<Upload, ApiError> {
    let bad = |why: &str| {
        ApiError::bad_request(format!(
            "file name \"{}\": {why}",
            crate::daemon::hotfolder::printable(name)
        ))
    };
    // A sidecar's name is its model's and `.toml`.
    let limit = match crate::daemon::hotfolder::is_sidecar_name(name) {
        true => MAX_NAME_BYTES + ".toml".len(),
        false => MAX_NAME_BYTES,
    };
    if name.is_empty() || name.len() > limit {
        return Err(bad(&format!(
            "must be 1 to {limit} bytes long (it is {})",
            name.len()
        )));
    }
    if name.contains(['/', '\\', '\0']) || name == "." || name == ".." {
        return Err(bad("must be a plain file name, without folders"));
    }
    if let Some(problem) = crate::names::problem(name) {
        return Err(bad(&format!("{problem}; rename the file")));
    }
    let mut components = Path::new(name).components();
    if !matches!(
        (components.next(), components.next()),
        (Some(std::path::Component::Normal(one)), None) if one == name
    ) {
        return Err(bad("must be a plain file name, without folders"));
    }
    if crate::daemon::hotfolder::is_sidecar_name(name) {
        // A sidecar belongs to a model or G-code whose name passes too.
        let model = &name[..name.len() - ".toml".len()];
        return match check_name(model) {
            Ok(Upload::Sidecar) | Err(_) => Err(bad(
                "a sidecar is named after its model: the model's name and .toml (part.stl.toml)",
            )),
            Ok(_) => Ok(Upload::Sidecar),
        };
    }
    if !crate::daemon::hotfolder::is_candidate_name(name) {
        return Err(bad(
            "is a hidden or temporary name that the hot folder never takes",
        ));
    }
    use crate::daemon::hotfolder::{file_kind, FileKind};
    match file_kind(name) {
        Some(FileKind::Model) => Ok(Upload::Model),
        // Pre-sliced G-code, which a hot folder prints as it is (what a slicer sends after
        // slicing itself); binary G-code is refused with the reason at preparation, as a
        // dropped one is.
        Some(FileKind::Gcode) => Ok(Upload::Gcode),
        None => Err(bad(
            "must end in .stl, .obj or .3mf (a model), .toml (its sidecar) or .gcode (pre-sliced)",
        )),
    }
}

/// Streams `body` into `folder/name`, at most `max` bytes. Returns the path and the size.
pub(crate) async fn store<S, E>(
    folder: &Path,
    name: &str,
    body: S,
    max: u64,
) -> Result<(PathBuf, u64), ApiError>
where
    S: Stream<Item = Result<Bytes, E>>,
    E: std::fmt::Display,
{
    let received = receive(folder, name, body, max).await?;
    let size = received.size;
    Ok((received.place().await?, size))
}

/// An upload received whole into its hidden temporary file in the hot folder, not yet
/// under its name; the temporary file is removed when this is dropped.
pub(crate) struct Received {
    temp: PathBuf,
    target: PathBuf,
    pub size: u64,
}

impl Drop for Received {
    fn drop(&mut self) {
        let _ = std::fs::remove_file(&self.temp);
    }
}

impl Received {
    /// Links the file to its name, which fails rather than replace a file already there.
    pub(crate) async fn place(self) -> Result<PathBuf, ApiError> {
        place_with_sidecar(self, None).await
    }

    /// Moves the received file to another hot folder (an OctoPrint form whose `path`
    /// came after its file): linked to a new temporary name there, or copied (and
    /// synced) when the folders are on different file systems.
    pub(crate) async fn relocate(self, folder: &Path) -> Result<Received, ApiError> {
        let name = self
            .target
            .file_name()
            .map(|n| n.to_string_lossy().into_owned())
            .unwrap_or_default();
        let target = folder.join(&name);
        let temp = folder.join(format!(".{name}.{:016x}.upload", rand::random::<u64>()));
        let moved = Received {
            temp,
            target,
            size: self.size,
        };
        tokio::task::spawn_blocking(move || {
            let linked = std::fs::hard_link(&self.temp, &moved.temp).or_else(|_| {
                std::fs::copy(&self.temp, &moved.temp)
                    .and_then(|_| std::fs::File::open(&moved.temp)?.sync_all())
            });
            // `self` goes now, and its temporary file with it.
            linked
                .map(|_| moved)
                .map_err(|e| io_error(&self.target, "cannot move the upload to its folder", e))
        })
        .await
        .map_err(ApiError::from)?
    }

    /// A link, not `fsutil::write_atomic`'s rename: a rename would replace a file of the
    /// same name that the hot folder already holds. Made durable like it (the file was
    /// synced as it was received; the folder's entry is synced here). The name spelt
    /// otherwise (a file dropped by hand under its decomposed spelling) is taken as well.
    fn link(&self) -> Result<PathBuf, ApiError> {
        if self.taken_otherwise() {
            return Err(self.taken());
        }
        match std::fs::hard_link(&self.temp, &self.target) {
            Ok(()) => {
                if let Some(folder) = self.target.parent() {
                    crate::fsutil::sync_dir(folder).map_err(|e| {
                        io_error(&self.target, "cannot make the upload durable", e.source)
                    })?;
                }
                Ok(self.target.clone())
            }
            Err(e) if e.kind() == std::io::ErrorKind::AlreadyExists => Err(self.taken()),
            Err(e) => Err(io_error(&self.target, "cannot put the upload in place", e)),
        }
    }

    /// Whether the hot folder holds this name under another spelling (the upload's own
    /// is NFC; a file put there by other means may not be). The link itself refuses the
    /// upload's own spelling.
    fn taken_otherwise(&self) -> bool {
        let (Some(folder), Some(name)) = (self.target.parent(), self.target.file_name()) else {
            return false;
        };
        crate::daemon::hotfolder::find_named(folder, &name.to_string_lossy())
            .is_some_and(|found| found != self.target)
    }

    fn taken(&self) -> ApiError {
        ApiError::conflict(format!(
            "{}: a file of this name is already in the hot folder (hint: wait until it \
             is picked up, or upload under another name)",
            shown(&self.target)
        ))
    }
}

/// Links `sidecar`, then `model`, to their names, one right after the other on one
/// thread: the pick-up takes a file only once it has settled, so it finds the sidecar with
/// its model, never alone. Nothing is linked when the model's name is taken; a sidecar
/// linked for a model that then cannot be is removed again.
pub(crate) async fn place_with_sidecar(
    model: Received,
    sidecar: Option<Received>,
) -> Result<PathBuf, ApiError> {
    tokio::task::spawn_blocking(move || {
        let Some(sidecar) = sidecar else {
            return model.link();
        };
        if std::fs::symlink_metadata(&model.target).is_ok() || model.taken_otherwise() {
            return model.link(); // fails, naming the file that is there
        }
        let linked = sidecar.link()?;
        model.link().inspect_err(|_| {
            let _ = std::fs::remove_file(&linked);
        })
    })
    .await
    .map_err(ApiError::from)?
}

/// A file in a hot folder as an HTTP answer names it: its name alone, shortened and
/// escaped; the server's paths are none of the client's business (the log has them).
fn shown(target: &Path) -> String {
    let name = target
        .file_name()
        .map(|n| n.to_string_lossy())
        .unwrap_or_default();
    crate::daemon::hotfolder::printable(&name)
}

fn io_error(target: &Path, what: &str, e: std::io::Error) -> ApiError {
    let status = if e.raw_os_error() == Some(nix::libc::ENOSPC) {
        StatusCode::INSUFFICIENT_STORAGE
    } else {
        StatusCode::INTERNAL_SERVER_ERROR
    };
    tracing::error!(file = %target.display(), error = %e, "http: {what}");
    // The error's own text may carry the path too (an OS error does not).
    ApiError::new(status, format!("{}: {what}: {}", shown(target), e.kind()))
}

/// Streams `body` into a hidden temporary file in `folder`, at most `max` bytes, synced.
pub(crate) async fn receive<S, E>(
    folder: &Path,
    name: &str,
    body: S,
    max: u64,
) -> Result<Received, ApiError>
where
    S: Stream<Item = Result<Bytes, E>>,
    E: std::fmt::Display,
{
    // Checked here too, whatever the caller did: nothing is written under a name that
    // is not one plain file name in `folder`, nor under a name in another spelling than
    // its one (the callers normalise it first, so that they answer with the name used).
    let name = &*crate::daemon::hotfolder::normal_name(name);
    check_name(name)?;
    let target = folder.join(name);
    let temp = folder.join(format!(".{name}.{:016x}.upload", rand::random::<u64>()));
    let mut file = tokio::fs::OpenOptions::new()
        .write(true)
        .create_new(true)
        .mode(0o640)
        .open(&temp)
        .await
        .map_err(|e| io_error(&target, "cannot create the upload's temporary file", e))?;
    // From here on the temporary file goes when `received` does, whatever fails.
    let mut received = Received {
        temp,
        target,
        size: 0,
    };
    received.size = copy_body(&mut file, body, max, name).await?;
    file.sync_all()
        .await
        .map_err(|e| io_error(&received.target, "cannot write", e))?;
    Ok(received)
}

async fn copy_body<S, E>(
    file: &mut tokio::fs::File,
    body: S,
    max: u64,
    name: &str,
) -> Result<u64, ApiError>
where
    S: Stream<Item = Result<Bytes, E>>,
    E: std::fmt::Display,
{
    let name = crate::daemon::hotfolder::printable(name);
    let mut body = std::pin::pin!(body);
    let mut size = 0u64;
    loop {
        let chunk = match tokio::time::timeout(UPLOAD_IDLE_TIMEOUT, body.next()).await {
            Err(_) => {
                return Err(ApiError::new(
                    StatusCode::REQUEST_TIMEOUT,
                    format!(
                        "{name}: the upload stalled for {} s",
                        UPLOAD_IDLE_TIMEOUT.as_secs()
                    ),
                ))
            }
            Ok(None) => return Ok(size),
            Ok(Some(Err(e))) => {
                return Err(ApiError::bad_request(format!(
                    "{name}: the upload broke off: {e}"
                )))
            }
            Ok(Some(Ok(chunk))) => chunk,
        };
        size += chunk.len() as u64;
        if size > max {
            return Err(ApiError::new(
                StatusCode::PAYLOAD_TOO_LARGE,
                format!(
                    "{name}: larger than the upload limit of {} MiB ([http] upload_max_mb)",
                    max / (1024 * 1024)
                ),
            ));
        }
        file.write_all(&chunk).await.map_err(|e| {
            ApiError::new(
                if e.raw_os_error() == Some(nix::libc::ENOSPC) {
                    StatusCode::INSUFFICIENT_STORAGE
                } else {
                    StatusCode::INTERNAL_SERVER_ERROR
                },
                format!("{name}: cannot write the upload: {}", e.kind()),
            )
        })?;
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn names_are_checked() {
        assert_eq!(check_name("part.stl").unwrap(), Upload::Model);
        assert_eq!(check_name("Part.3MF").unwrap(), Upload::Model);
        assert_eq!(check_name("part.stl.toml").unwrap(), Upload::Sidecar);
        assert_eq!(check_name("part.gcode").unwrap(), Upload::Gcode);
        assert_eq!(check_name("PART.GCO").unwrap(), Upload::Gcode);
        // G-code by the same classifier as the preparation's (this list once lacked it).
        assert_eq!(check_name("part.bgcode").unwrap(), Upload::Gcode);
        for bad in [
            "",
            "../x.stl",
            "a/b.stl",
            "..",
            ".hidden.stl",
            "x.stl.part",
            ".x.gcode",
            "gcode",
            "x.txt",
            "stl",
            "a\\b.stl",
            "a\nb.stl",
            "./x.stl",
            "x.stl/",
            "a\u{1b}[2Jb.stl",
            "evil\u{202e}lts.gcode",
            "notes.txt.toml",
            "x.stl.toml.toml",
            ".x.stl.toml",
            "x.gcode.part",
        ] {
            let e = check_name(bad).unwrap_err();
            assert!(e.message.contains("file name"), "{bad}: {}", e.message);
        }
        let e = check_name(&format!("{}.gcode", "a".repeat(244))).unwrap_err();
        assert_eq!(e.status, StatusCode::BAD_REQUEST);
        assert!(e.message.contains("200 bytes"), "{}", e.message);
        assert!(
            e.message.len() < 300,
            "the name is shortened: {}",
            e.message
        );
    }

    #[tokio::test]
    async fn an_upload_lands_whole_or_not_at_all() {
        let dir = tempfile::tempdir().unwrap();
        let chunks = |n: usize| {
            futures_util::stream::iter(
                (0..n).map(|_| Ok::<_, std::io::Error>(Bytes::from_static(b"0123456789"))),
            )
        };
        let (path, size) = store(dir.path(), "a.stl", chunks(3), 100).await.unwrap();
        assert_eq!((std::fs::read(&path).unwrap().len(), size), (30, 30));
        // Never replaces a file already there.
        let e = store(dir.path(), "a.stl", chunks(1), 100)
            .await
            .unwrap_err();
        assert_eq!(e.status, StatusCode::CONFLICT);
        assert_eq!(std::fs::read(&path).unwrap().len(), 30);
        // Too large: refused, nothing left behind.
        let e = store(dir.path(), "b.stl", chunks(20), 100)
            .await
            .unwrap_err();
        assert_eq!(e.status, StatusCode::PAYLOAD_TOO_LARGE);
        let left: Vec<_> = std::fs::read_dir(dir.path()).unwrap().collect();
        assert_eq!(left.len(), 1, "only a.stl: {left:?}");
    }

    /// `café.gcode` composed and decomposed are one name: stored under the composed
    /// spelling whichever arrives, and the second refused as a second identical name is,
    /// also when the first was put in the folder by hand under the decomposed spelling.
    #[tokio::test]
    async fn two_spellings_of_a_name_are_one_name() {
        let composed = "caf\u{e9}.gcode";
        let decomposed = "cafe\u{301}.gcode";
        assert_eq!(upload_name(decomposed).unwrap().0, composed);
        assert_eq!(upload_name(composed).unwrap().0, composed);
        let one =
            || futures_util::stream::iter([Ok::<_, std::io::Error>(Bytes::from_static(b"G28\n"))]);
        let dir = tempfile::tempdir().unwrap();
        let (path, _) = store(dir.path(), decomposed, one(), 100).await.unwrap();
        assert_eq!(path, dir.path().join(composed));
        let e = store(dir.path(), composed, one(), 100).await.unwrap_err();
        assert_eq!(e.status, StatusCode::CONFLICT, "{}", e.message);
        let e = store(dir.path(), decomposed, one(), 100).await.unwrap_err();
        assert_eq!(e.status, StatusCode::CONFLICT, "{}", e.message);

        // Dropped by hand, decomposed: an upload of the name in either spelling waits.
        let dir = tempfile::tempdir().unwrap();
        std::fs::write(dir.path().join(decomposed), b"G28\n").unwrap();
        for name in [composed, decomposed] {
            let e = store(dir.path(), name, one(), 100).await.unwrap_err();
            assert_eq!(e.status, StatusCode::CONFLICT, "{name:?}: {}", e.message);
        }
        // A held upload's sidecar spelt otherwise is taken too: nothing placed.
        let dir = tempfile::tempdir().unwrap();
        std::fs::write(dir.path().join("cafe\u{301}.gcode.toml"), b"copies = 2\n").unwrap();
        let model = receive(dir.path(), composed, one(), 100).await.unwrap();
        let sidecar = receive(dir.path(), &format!("{composed}.toml"), one(), 100)
            .await
            .unwrap();
        let e = place_with_sidecar(model, Some(sidecar)).await.unwrap_err();
        assert_eq!(e.status, StatusCode::CONFLICT, "{}", e.message);
        let left: Vec<_> = std::fs::read_dir(dir.path()).unwrap().collect();
        assert_eq!(left.len(), 1, "only the sidecar there before: {left:?}");
    }

    /// A held upload's sidecar and model arrive together or not at all.
    #[tokio::test]
    async fn a_sidecar_and_its_model_are_placed_together_or_not_at_all() {
        let dir = tempfile::tempdir().unwrap();
        let one = |text: &'static [u8]| {
            futures_util::stream::iter([Ok::<_, std::io::Error>(Bytes::from_static(text))])
        };
        let names = || {
            let mut n: Vec<String> = std::fs::read_dir(dir.path())
                .unwrap()
                .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
                .collect();
            n.sort();
            n
        };
        let root = dir.path().to_path_buf();
        let pair = |model: &'static str| {
            let root = root.clone();
            async move {
                let m = receive(&root, model, one(b"model"), 100).await.unwrap();
                let sidecar = format!("{model}.toml");
                let s = receive(&root, &sidecar, one(b"hold = true\n"), 100)
                    .await
                    .unwrap();
                place_with_sidecar(m, Some(s)).await
            }
        };
        pair("a.stl").await.unwrap();
        assert_eq!(names(), ["a.stl", "a.stl.toml"]);
        // The model's name is taken: nothing placed, the sidecar there untouched.
        std::fs::remove_file(dir.path().join("a.stl.toml")).unwrap();
        let e = pair("a.stl").await.unwrap_err();
        assert_eq!(e.status, StatusCode::CONFLICT);
        assert_eq!(names(), ["a.stl"]);
        // A sidecar of that name is there already: refused, it is not replaced.
        std::fs::write(dir.path().join("b.stl.toml"), "copies = 2\n").unwrap();
        let e = pair("b.stl").await.unwrap_err();
        assert!(e.message.contains("b.stl.toml"), "{}", e.message);
        assert_eq!(names(), ["a.stl", "b.stl.toml"]);
        assert_eq!(
            std::fs::read_to_string(dir.path().join("b.stl.toml")).unwrap(),
            "copies = 2\n"
        );
    }
}
