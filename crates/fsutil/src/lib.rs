//! Writing a file so that a crash or a power cut leaves either the old file or the whole
//! new one, never a torn one: [`write_atomic`] and [`write_atomic_with`]. The one place
//! crispen does this (job states, bed gates, history, meshes, G-code, pictures).
//!
//! The steps, each needed: write a temporary file in the same directory (a rename is only
//! atomic within one file system), `fsync` it (else the rename may reach the disk before
//! the data, and a power cut leaves an empty file under the final name), rename it over
//! the target, then `fsync` the directory (else the rename itself may be lost). A crate
//! of its own: it depends on nothing else of crispen.

#![warn(unreachable_pub)]

use std::io::Write;
use std::os::unix::fs::OpenOptionsExt;
use std::path::{Path, PathBuf};

/// Which step of an atomic write failed, on which path.
#[derive(Debug, thiserror::Error)]
#[error("{}: {step}: {source}", path.display())]
pub struct WriteError {
    pub path: PathBuf,
    /// "create", "write", "fsync", "rename into place", "fsync directory".
    pub step: &'static str,
    #[source]
    pub source: std::io::Error,
}

impl From<WriteError> for std::io::Error {
    /// For callers that speak `io::Error`: the kind is kept, the path and step are told.
    fn from(e: WriteError) -> std::io::Error {
        std::io::Error::new(e.source.kind(), e.to_string())
    }
}

/// The temporary name next to `path`: hidden and marked as crispen's, so hot folders and
/// job listings pass over it, and fixed, so a crash leaves at most one behind per file.
pub fn temp_path(path: &Path) -> PathBuf {
    let mut name = std::ffi::OsString::from(TEMP_PREFIX);
    name.push(path.file_name().unwrap_or_default());
    path.with_file_name(name)
}

/// How every temporary name made by [`temp_path`] starts.
pub const TEMP_PREFIX: &str = ".crispen-tmp-";

/// Writes `bytes` to `path` atomically (see the module's comment). The file is readable
/// by others (0644 before the umask), like the job's other files.
pub fn write_atomic(path: &Path, bytes: &[u8]) -> Result<(), WriteError> {
    write_atomic_with(path, |file| file.write_all(bytes))
}

/// [`write_atomic`] with the content written by `write` (a copy, a streamed answer, a
/// serialiser), so a large file never has to be whole in memory.
pub fn write_atomic_with(
    path: &Path,
    write: impl FnOnce(&mut std::fs::File) -> std::io::Result<()>,
) -> Result<(), WriteError> {
    let mut file = AtomicFile::create(path)?;
    write(file.file()).map_err(|source| WriteError {
        path: file.tmp.clone(),
        step: "write",
        source,
    })?;
    file.commit()
}

/// A file being written atomically, for writers that cannot be one closure (an async
/// stream): [`AtomicFile::file`] to write, [`AtomicFile::commit`] to put it in place.
/// Dropped without a commit, the temporary file is removed and the old file stays.
pub struct AtomicFile {
    file: Option<std::fs::File>,
    tmp: PathBuf,
    path: PathBuf,
}

impl AtomicFile {
    /// Creates the temporary file next to `path` (readable by others, 0644 before the
    /// umask, like the job's other files).
    pub fn create(path: &Path) -> Result<AtomicFile, WriteError> {
        let tmp = temp_path(path);
        let file = std::fs::OpenOptions::new()
            .write(true)
            .create(true)
            .truncate(true)
            .mode(0o644)
            .open(&tmp)
            .map_err(|source| WriteError {
                path: tmp.clone(),
                step: "create",
                source,
            })?;
        Ok(AtomicFile {
            file: Some(file),
            tmp,
            path: path.to_path_buf(),
        })
    }

    pub fn file(&mut self) -> &mut std::fs::File {
        self.file
            .as_mut()
            .expect("an atomic file is open until committed")
    }

    /// Syncs the file, renames it over the target and syncs the directory.
    pub fn commit(mut self) -> Result<(), WriteError> {
        let file = self.file.take().expect("an atomic file is committed once");
        let fail = |path: &Path, step| {
            let path = path.to_path_buf();
            move |source| WriteError { path, step, source }
        };
        file.sync_all().map_err(fail(&self.tmp, "fsync"))?;
        drop(file);
        std::fs::rename(&self.tmp, &self.path).map_err(fail(&self.path, "rename into place"))?;
        let dir = match self.path.parent() {
            Some(p) if !p.as_os_str().is_empty() => p,
            _ => Path::new("."),
        };
        sync_dir(dir)
    }
}

impl Drop for AtomicFile {
    fn drop(&mut self) {
        // Not committed (or the commit failed before the rename): the old file stays.
        if self.tmp.exists() {
            let _ = std::fs::remove_file(&self.tmp);
        }
    }
}

/// Makes a directory's entries (a rename, a new file) durable.
pub fn sync_dir(dir: &Path) -> Result<(), WriteError> {
    std::fs::File::open(dir)
        .and_then(|d| d.sync_all())
        .map_err(|source| WriteError {
            path: dir.to_path_buf(),
            step: "fsync directory",
            source,
        })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn replaces_whole_and_leaves_no_temporary_file() {
        let tmp = tempfile::tempdir().unwrap();
        let path = tmp.path().join("state.json");
        write_atomic(&path, b"old").unwrap();
        write_atomic(&path, b"new and longer").unwrap();
        assert_eq!(std::fs::read(&path).unwrap(), b"new and longer");
        let names: Vec<_> = std::fs::read_dir(tmp.path())
            .unwrap()
            .map(|e| e.unwrap().file_name())
            .collect();
        assert_eq!(names, vec![std::ffi::OsString::from("state.json")]);
    }

    /// A write that fails half way leaves the old file as it was, and no temporary file.
    #[test]
    fn a_failed_write_keeps_the_old_file() {
        let tmp = tempfile::tempdir().unwrap();
        let path = tmp.path().join("g.gcode");
        write_atomic(&path, b"G28\n").unwrap();
        let err = write_atomic_with(&path, |f| {
            f.write_all(b"G1 X")?;
            Err(std::io::Error::other("the slicer died"))
        })
        .unwrap_err();
        assert_eq!(err.step, "write");
        assert!(err.to_string().contains(".crispen-tmp-g.gcode"), "{err}");
        assert_eq!(std::fs::read(&path).unwrap(), b"G28\n");
        assert!(!temp_path(&path).exists());
    }

    /// The temporary name's place taken (by a directory) fails at "create", naming it.
    #[test]
    fn a_blocked_temporary_name_fails_cleanly() {
        let tmp = tempfile::tempdir().unwrap();
        let path = tmp.path().join("job.json");
        std::fs::create_dir(temp_path(&path)).unwrap();
        let err = write_atomic(&path, b"{}").unwrap_err();
        assert_eq!(err.step, "create");
        assert!(!path.exists());
    }
}
