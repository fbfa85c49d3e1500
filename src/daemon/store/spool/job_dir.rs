//! What a job directory of the spool holds and how its files are named, read and moved:
//! the model's name in the job, its sidecar, a late sidecar's place, the job's state
//! (`job.json`) and where its model came from (`origin.json`). Apart from the `Spool`
//! itself because the farm database's store keeps a local job directory the same way.

use super::super::rules::io_err;
use crate::daemon::hotfolder::{find_named, normal_name};
use crate::daemon::job::{now_s, Job, JobState, StoreError};
use serde::{Deserialize, Serialize};
use std::path::{Path, PathBuf};

/// What a job directory says about where its model came from (written before the model
/// is moved in, so an interrupted pick-up can be completed).
#[derive(Debug, Serialize, Deserialize)]
pub(super) struct Origin {
    /// The directory's own name: a copy of the directory under another name is not a job.
    pub(super) id: String,
    pub(super) file: String,
    pub(super) folder: PathBuf,
}

pub(super) fn read_origin(dir: &Path) -> Option<Origin> {
    let bytes = std::fs::read(dir.join("origin.json")).ok()?;
    serde_json::from_slice(&bytes).ok()
}

/// Names of the files crispen keeps in a job directory besides the model's own.
/// The size of `path` if it is a regular file (never a link out of the hot folder).
pub(crate) fn regular_file_size(path: &Path) -> Result<u64, StoreError> {
    match std::fs::symlink_metadata(path) {
        Ok(meta) if meta.file_type().is_file() => Ok(meta.len()),
        Ok(_) => Err(StoreError::NotAFile {
            path: path.to_path_buf(),
        }),
        Err(e) => Err(io_err(path, "read")(e)),
    }
}

/// The name a dropped file is kept under in its job: its own in its one spelling (NFC:
/// two spellings of a name are one job name, see [`normal_name`]), unless it is named like
/// one of the job's own files, so neither overwrites the other. The file in the hot folder
/// is not renamed; its copy in the job directory is under this name.
pub(crate) fn model_name(source: &Path) -> String {
    let dropped = source
        .file_name()
        .map(|n| normal_name(&n.to_string_lossy()).into_owned())
        .unwrap_or_else(|| "model".into());
    if is_reserved_name(&dropped) {
        format!("model-{dropped}")
    } else {
        dropped
    }
}

/// The sidecar of a dropped model: `<model>.toml`, or the same name spelt otherwise (a
/// decomposed `café.gcode.toml` is the sidecar of a composed `café.gcode`). A path that
/// is not there when there is none.
pub(crate) fn sidecar_of(source: &Path) -> PathBuf {
    let mut exact = source.as_os_str().to_owned();
    exact.push(".toml");
    let exact = PathBuf::from(exact);
    let (Some(folder), Some(name)) = (source.parent(), source.file_name()) else {
        return exact;
    };
    let Some(name) = name.to_str() else {
        return exact;
    };
    find_named(folder, &format!("{name}.toml")).unwrap_or(exact)
}

/// Where a late sidecar of model `file` goes: the job's sidecar when it `applies`, else
/// aside, kept but not used.
pub(crate) fn late_sidecar_name(file: &str, applies: bool) -> String {
    if applies {
        format!("{file}.toml")
    } else {
        format!("{file}.toml.late")
    }
}

/// Whether a file of a job's directory is one a copy of it shares (see
/// [`link_files`]): its model, sidecar, G-code and previews; not its state, nor what its
/// own print left (the camera's pictures, a timelapse, the picture of the print).
pub(crate) fn copy_shares(name: &str) -> bool {
    !is_reserved_name(name)
        && !name.ends_with(".jpg")
        && !name.ends_with(".mp4")
        && name != crate::observation::OBSERVED_PNG
}

/// Gives the directory `to` the files of `from` a copy shares ([`copy_shares`]): hard
/// links, so the copies of a big G-code take no more room, or copies where links cannot be
/// made (another filesystem).
pub(super) fn link_files(from: &Path, to: &Path) -> Result<(), StoreError> {
    for entry in std::fs::read_dir(from).map_err(io_err(from, "list"))? {
        let entry = entry.map_err(io_err(from, "list"))?;
        let name = entry.file_name().to_string_lossy().into_owned();
        if !entry.file_type().is_ok_and(|t| t.is_file()) || !copy_shares(&name) {
            continue;
        }
        let (source, target) = (entry.path(), to.join(&name));
        if std::fs::hard_link(&source, &target).is_err() {
            std::fs::copy(&source, &target)
                .map_err(io_err(&target, "copy a job's file for its copy"))?;
        }
    }
    Ok(())
}

fn is_reserved_name(name: &str) -> bool {
    matches!(name, "job.json" | "origin.json") || name.starts_with(".crispen-")
}

/// The sequence number of a well-formed job id (`<digits>-<letters, digits, -, _>`), as
/// `Spool::admit` makes them; `None` for anything else.
pub(crate) fn seq_of_id(id: &str) -> Option<u64> {
    let (seq, stem) = id.split_once('-')?;
    let stem_ok = stem.len() <= 40
        && stem
            .chars()
            .all(|c| c.is_ascii_alphanumeric() || c == '-' || c == '_');
    if seq.len() < 4 || seq.len() > 12 || !seq.chars().all(|c| c.is_ascii_digit()) || !stem_ok {
        return None;
    }
    seq.parse().ok()
}

/// Reads a job's state; `Ok(None)` when it has none yet. State files are small: a bigger
/// one is not a job's.
pub(super) fn load_job(dir: &Path) -> Result<Option<Job>, StoreError> {
    const MAX_STATE_BYTES: u64 = 1 << 20;
    let path = dir.join("job.json");
    let file = match std::fs::File::open(&path) {
        Ok(f) => f,
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => return Ok(None),
        Err(e) => return Err(io_err(&path, "read")(e)),
    };
    let mut text = Vec::new();
    std::io::Read::read_to_end(
        &mut std::io::Read::take(file, MAX_STATE_BYTES + 1),
        &mut text,
    )
    .map_err(io_err(&path, "read"))?;
    if text.len() as u64 > MAX_STATE_BYTES {
        return Err(StoreError::Corrupt {
            path,
            message: format!("larger than {MAX_STATE_BYTES} bytes"),
        });
    }
    let job: Job = serde_json::from_slice(&text).map_err(|e| StoreError::Corrupt {
        path: path.clone(),
        message: e.to_string(),
    })?;
    if seq_of_id(&job.id).is_none() {
        return Err(StoreError::Corrupt {
            path,
            message: format!("{:?} is not a job id", job.id),
        });
    }
    Ok(Some(job))
}

/// A failed stand-in for a job whose state could not be read; the directory is kept as it
/// is for the operator to look at. Its reason names the files relative to the spool `root`
/// (`jobs/<id>/job.json`): clients see it (the log has the whole path).
pub(super) fn unreadable_job(
    root: &Path,
    dir: &Path,
    id: &str,
    seq: u64,
    error: &StoreError,
) -> Job {
    let (file, folder) = match read_origin(dir) {
        Some(o) => (o.file, o.folder),
        None => (String::new(), PathBuf::new()),
    };
    let mut job = Job::queued(id.to_string(), seq, file, folder);
    job.state = JobState::Failed;
    job.history.push((JobState::Failed, now_s()));
    let reason = format!("{error}; the directory {} is kept as it was", dir.display());
    job.reason = Some(super::super::spool_relative(&reason, root));
    job
}

/// Moves a file, copying it when `from` and `to` are on different filesystems. A copy
/// goes to a temporary name first and is renamed into place only once whole and synced,
/// so a copy cut short (a full disk) never passes for the file.
pub(crate) fn move_file(from: &Path, to: &Path) -> Result<(), StoreError> {
    match std::fs::rename(from, to) {
        Ok(()) => Ok(()),
        Err(e) if e.raw_os_error() == Some(nix::libc::EXDEV) => {
            let mut source = std::fs::File::open(from).map_err(io_err(from, "read"))?;
            crate::fsutil::write_atomic_with(to, |file| {
                std::io::copy(&mut source, file).map(|_| ())
            })?;
            std::fs::remove_file(from).map_err(io_err(from, "remove after copying"))
        }
        Err(e) => Err(io_err(from, "move")(e)),
    }
}
