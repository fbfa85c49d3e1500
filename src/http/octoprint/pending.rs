//! Held uploads waiting for their select-and-print, so that the command is never lost
//! whenever it arrives: before the hot folder has taken the file (it has not become a job
//! yet), while its job is prepared, or once it is ready.
//!
//! Each held upload gets a token, written into its sidecar (a TOML comment line,
//! [`TOKEN_PREFIX`]) and remembered here with its folder, file name and the key that
//! uploaded it. The token, not the file name, finds the job: a client that uploads the
//! same name again and again (Cura sends its job name) must release *this* upload's job,
//! not the previous one still printing. A select-and-print marks the upload wanted; a
//! job from it that exists is released at once, else one sweeper task looks for it every
//! [`SWEEP`] until it appears (then releases it) or [`MAX_WAIT`] has passed (then it logs
//! that it gave up).
//!
//! Bounded: at most [`MAX_PENDING`] uploads are remembered (the oldest forgotten first),
//! none longer than [`MAX_WAIT`]. Memory only: after a restart a select-and-print finds
//! a job that exists by its name, as before (`super::files::command`).

use crate::daemon::control::{self, Command, CommandError, JobStatus};
use crate::daemon::farm::Farm;
use crate::daemon::job::JobState;
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, Mutex, MutexGuard};
use std::time::{Duration, Instant};

/// How the token's line starts in a held upload's sidecar.
pub(crate) const TOKEN_PREFIX: &str = "# octoprint upload: ";
/// Uploads remembered at most.
pub(crate) const MAX_PENDING: usize = 1024;
/// How long an upload is remembered, and a wanted one looked for: far longer than a hot
/// folder takes to settle a file (a sidecar whose model never came is dropped after ten
/// settle times).
pub(crate) const MAX_WAIT: Duration = Duration::from_secs(30 * 60);
/// How often the sweeper looks for the jobs of wanted uploads.
pub(crate) const SWEEP: Duration = Duration::from_millis(200);

/// One held upload.
#[derive(Debug, Clone)]
struct Entry {
    folder: PathBuf,
    file: String,
    token: String,
    /// The application key that uploaded it (None: the operator's key).
    key: Option<String>,
    /// A select-and-print asked for it.
    wanted: bool,
    since: Instant,
}

static PENDING: Mutex<Vec<Entry>> = Mutex::new(Vec::new());
/// Whether the sweeper task runs.
static SWEEPING: AtomicBool = AtomicBool::new(false);

fn pending() -> MutexGuard<'static, Vec<Entry>> {
    PENDING.lock().unwrap_or_else(|e| e.into_inner())
}

/// A fresh token: 128 random bits in hex.
pub(crate) fn token() -> String {
    let mut bytes = [0u8; 16];
    rand::fill(&mut bytes[..]);
    bytes.iter().map(|b| format!("{b:02x}")).collect()
}

/// The sidecar line that carries `token`.
pub(crate) fn sidecar_line(token: &str) -> String {
    format!("{TOKEN_PREFIX}{token}\n")
}

/// The token in a sidecar's text, if any.
fn token_in(sidecar: &str) -> Option<&str> {
    sidecar
        .lines()
        .find_map(|l| l.strip_prefix(TOKEN_PREFIX))
        .map(str::trim)
}

/// Remembers a held upload of `file` into `folder` by the key `key` (None: the operator).
pub(crate) fn remember(folder: &Path, file: &str, token: &str, key: Option<&str>) {
    let mut p = pending();
    let now = Instant::now();
    p.retain(|e| now.duration_since(e.since) < MAX_WAIT);
    if p.len() >= MAX_PENDING {
        p.remove(0);
    }
    p.push(Entry {
        folder: folder.to_path_buf(),
        file: file.to_string(),
        token: token.to_string(),
        key: key.map(str::to_string),
        wanted: false,
        since: now,
    });
}

/// The newest remembered upload of `file` into `folder`: (token, its key).
pub(crate) fn newest(folder: &Path, file: &str) -> Option<(String, Option<String>)> {
    pending()
        .iter()
        .rev()
        .find(|e| e.folder == folder && crate::daemon::hotfolder::same_name(&e.file, file))
        .map(|e| (e.token.clone(), e.key.clone()))
}

/// The remembered uploads into `folder` not asked to print yet, newest first, that `key`
/// may start (its own; the operator's key, None, any): (token, file).
pub(crate) fn unwanted(folder: &Path, key: Option<&str>) -> Vec<(String, String)> {
    pending()
        .iter()
        .rev()
        .filter(|e| e.folder == folder && !e.wanted && (key.is_none() || e.key.as_deref() == key))
        .map(|e| (e.token.clone(), e.file.clone()))
        .collect()
}

fn forget(token: &str) {
    pending().retain(|e| e.token != token);
}

/// What became of a wanted upload's select-and-print.
#[derive(Debug, Clone, PartialEq, Eq)]
pub(crate) enum Outcome {
    /// Its job was released now.
    Released(String),
    /// Its job exists and is not held (released already): nothing to do.
    AlreadyFree(String),
    /// No job from it yet: remembered; the sweeper releases it once it appears.
    Waiting,
}

/// A select-and-print for the upload `token`: released now if its job exists, else
/// marked wanted for the sweeper. Errors: the farm refused the release (the job was
/// cancelled meanwhile, say).
pub(crate) async fn print(farm: &Arc<Farm>, token: &str) -> Result<Outcome, CommandError> {
    let entry = {
        let mut p = pending();
        let Some(e) = p.iter_mut().find(|e| e.token == token) else {
            return Ok(Outcome::Waiting);
        };
        e.wanted = true;
        e.clone()
    };
    match try_release(farm, &entry).await? {
        Some(outcome) => {
            forget(token);
            Ok(outcome)
        }
        None => {
            start_sweeper(farm);
            Ok(Outcome::Waiting)
        }
    }
}

/// The job that `entry`'s upload became, if it is one yet: a live job of its folder and
/// name whose sidecar (in its job directory) carries the token.
async fn job_of(farm: &Farm, entry: &Entry, jobs: &[JobStatus]) -> Option<JobStatus> {
    let store = farm.store();
    let candidates: Vec<(JobStatus, PathBuf)> = jobs
        .iter()
        .filter(|j| {
            j.folder == entry.folder
                && crate::daemon::hotfolder::same_name(&j.file, &entry.file)
                && matches!(
                    j.state,
                    JobState::Queued | JobState::Preparing | JobState::Ready | JobState::Printing
                )
        })
        .map(|j| {
            (
                j.clone(),
                store.job_dir(&j.id).join(format!("{}.toml", j.file)),
            )
        })
        .collect();
    drop(store);
    if candidates.is_empty() {
        return None;
    }
    let token = entry.token.clone();
    tokio::task::spawn_blocking(move || {
        use std::io::Read;
        candidates.into_iter().find_map(|(job, sidecar)| {
            let mut text = String::new();
            std::fs::File::open(&sidecar)
                .and_then(|f| {
                    f.take(crate::daemon::job::MAX_SIDECAR_BYTES)
                        .read_to_string(&mut text)
                })
                .ok()?;
            (token_in(&text) == Some(token.as_str())).then_some(job)
        })
    })
    .await
    .ok()
    .flatten()
}

/// Releases `entry`'s job if it exists: Some(outcome), None while there is no job yet.
async fn try_release(farm: &Arc<Farm>, entry: &Entry) -> Result<Option<Outcome>, CommandError> {
    let jobs = control::status(farm).jobs;
    let Some(job) = job_of(farm, entry, &jobs).await else {
        return Ok(None);
    };
    match control::execute(
        farm,
        Command::Release {
            job: job.id.clone(),
        },
    )
    .await
    {
        Ok(message) => {
            tracing::info!(job = %job.id, file = %entry.file, %message, "octoprint: select and print released the upload's job");
            Ok(Some(Outcome::Released(job.id)))
        }
        Err(CommandError::NotHeld(_)) => Ok(Some(Outcome::AlreadyFree(job.id))),
        Err(e) => Err(e),
    }
}

/// Starts the sweeper unless it runs.
fn start_sweeper(farm: &Arc<Farm>) {
    if SWEEPING.swap(true, Ordering::SeqCst) {
        return;
    }
    let farm = Arc::clone(farm);
    tokio::spawn(async move {
        loop {
            let now = Instant::now();
            let wanted: Vec<Entry> = {
                let mut p = pending();
                p.retain(|e| {
                    let fresh = now.duration_since(e.since) < MAX_WAIT;
                    if !fresh && e.wanted {
                        tracing::warn!(file = %e.file, folder = %e.folder.display(), "octoprint: a select-and-print's upload did not become a job in time; given up");
                    }
                    fresh
                });
                p.iter().filter(|e| e.wanted).cloned().collect()
            };
            if wanted.is_empty() {
                SWEEPING.store(false, Ordering::SeqCst);
                // A print asked for between the look and the flag starts no sweeper of
                // its own (the flag was up): look once more.
                let more = pending().iter().any(|e| e.wanted);
                if !more || SWEEPING.swap(true, Ordering::SeqCst) {
                    return;
                }
                continue;
            }
            for entry in &wanted {
                match try_release(&farm, entry).await {
                    Ok(None) => {}
                    Ok(Some(_)) => forget(&entry.token),
                    Err(e) => {
                        tracing::warn!(file = %entry.file, error = %e, "octoprint: a select-and-print could not release the upload's job");
                        forget(&entry.token);
                    }
                }
            }
            tokio::time::sleep(SWEEP).await;
        }
    });
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn tokens_are_found_in_sidecars() {
        let t = token();
        assert_eq!(t.len(), 32);
        let text = format!("hold = true\n{}# other\n", sidecar_line(&t));
        assert_eq!(token_in(&text), Some(t.as_str()));
        assert_eq!(token_in("hold = true\n"), None);
    }

    #[test]
    fn the_newest_upload_of_a_name_is_found_and_the_list_is_bounded() {
        let folder = Path::new("/nonexistent/pending-test");
        remember(folder, "a.gcode", "t1", None);
        remember(folder, "a.gcode", "t2", Some("k"));
        assert_eq!(
            newest(folder, "a.gcode"),
            Some(("t2".to_string(), Some("k".to_string())))
        );
        assert_eq!(unwanted(folder, Some("k")).len(), 1);
        for i in 0..MAX_PENDING + 5 {
            remember(folder, "b.gcode", &format!("x{i}"), None);
        }
        assert!(pending().len() <= MAX_PENDING);
    }
}
