//! OctoPrint's held uploads waiting for their select-and-print, so that the command is never lost
//! whenever it arrives: before the hot folder has taken the file (it has not become a job
//! yet), while its job is prepared, or once it is ready.
//!
//! Each held upload gets a token, written into its sidecar (a TOML comment line,
//! [`TOKEN_PREFIX`]) and remembered here with its folder, file name and the key that
//! uploaded it. The token, not the file name, finds the job: a client that uploads the
//! same name again and again (Cura sends its job name) must release *this* upload's job,
//! not the previous one still printing. A select-and-print marks the upload wanted; a
//! job from it that exists is released at once, else the sweeper ([`sweep`], one task of
//! the service) looks for it each time the jobs change, until it appears (then releases
//! it) or [`MAX_WAIT`] has passed (then it logs that it gave up). The list is the run's
//! ([`Pending`], made by the service and shared by the listeners and the sweeper).
//!
//! Bounded: at most [`MAX_PENDING`] uploads are remembered (the oldest forgotten first),
//! none longer than [`MAX_WAIT`]. Memory only: after a restart a select-and-print finds
//! a job that exists by its name, as before (`octoprint::files::command`).

use crate::daemon::control::{self, Command, CommandError, JobStatus};
use crate::daemon::farm::Farm;
use crate::daemon::job::JobState;
use std::path::{Path, PathBuf};
use std::sync::{Arc, Mutex, MutexGuard};
use std::time::{Duration, Instant};
use tokio::sync::Notify;
use tokio_util::sync::CancellationToken;

/// How the token's line starts in a held upload's sidecar.
pub(crate) const TOKEN_PREFIX: &str = "# octoprint upload: ";
/// Uploads remembered at most.
pub(crate) const MAX_PENDING: usize = 1024;
/// How long an upload is remembered, and a wanted one looked for: far longer than a hot
/// folder takes to settle a file (a sidecar whose model never came is dropped after ten
/// settle times).
pub(crate) const MAX_WAIT: Duration = Duration::from_secs(30 * 60);

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

/// The held uploads of a run, and the sweeper's wake-up.
#[derive(Debug, Default)]
pub(crate) struct Pending {
    entries: Mutex<Vec<Entry>>,
    /// A select-and-print marked an upload wanted whose job is not there yet.
    wanted: Notify,
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

impl Pending {
    fn entries(&self) -> MutexGuard<'_, Vec<Entry>> {
        self.entries.lock().unwrap_or_else(|e| e.into_inner())
    }

    /// Remembers a held upload of `file` into `folder` by the key `key` (None: the operator).
    pub(crate) fn remember(&self, folder: &Path, file: &str, token: &str, key: Option<&str>) {
        let mut p = self.entries();
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
    pub(crate) fn newest(&self, folder: &Path, file: &str) -> Option<(String, Option<String>)> {
        self.entries()
            .iter()
            .rev()
            .find(|e| e.folder == folder && crate::daemon::hotfolder::same_name(&e.file, file))
            .map(|e| (e.token.clone(), e.key.clone()))
    }

    /// The remembered uploads into `folder` not asked to print yet, newest first, that `key`
    /// may start (its own; the operator's key, None, any): (token, file).
    pub(crate) fn unwanted(&self, folder: &Path, key: Option<&str>) -> Vec<(String, String)> {
        self.entries()
            .iter()
            .rev()
            .filter(|e| {
                e.folder == folder && !e.wanted && (key.is_none() || e.key.as_deref() == key)
            })
            .map(|e| (e.token.clone(), e.file.clone()))
            .collect()
    }

    fn forget(&self, token: &str) {
        self.entries().retain(|e| e.token != token);
    }

    /// A select-and-print for the upload `token`: released now if its job exists, else
    /// marked wanted for the sweeper. Errors: the farm refused the release (the job was
    /// cancelled meanwhile, say).
    pub(crate) async fn print(
        &self,
        farm: &Arc<Farm>,
        token: &str,
    ) -> Result<Outcome, CommandError> {
        let entry = {
            let mut p = self.entries();
            let Some(e) = p.iter_mut().find(|e| e.token == token) else {
                return Ok(Outcome::Waiting);
            };
            e.wanted = true;
            e.clone()
        };
        match try_release(farm, &entry).await? {
            Some(outcome) => {
                self.forget(token);
                Ok(outcome)
            }
            None => {
                self.wanted.notify_one();
                Ok(Outcome::Waiting)
            }
        }
    }

    /// Forgets the uploads older than [`MAX_WAIT`] (saying so of a wanted one); the
    /// wanted ones left, and when the oldest left is to be forgotten.
    fn expire(&self, now: Instant) -> (Vec<Entry>, Option<Instant>) {
        let mut p = self.entries();
        p.retain(|e| {
            let fresh = now.duration_since(e.since) < MAX_WAIT;
            if !fresh && e.wanted {
                tracing::warn!(file = %e.file, folder = %e.folder.display(), "octoprint: a select-and-print's upload did not become a job in time; given up");
            }
            fresh
        });
        let wanted = p.iter().filter(|e| e.wanted).cloned().collect();
        (wanted, p.iter().map(|e| e.since + MAX_WAIT).min())
    }
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

/// The sweeper, until `stop`: each time the jobs change or a select-and-print marks an
/// upload wanted, releases the wanted uploads' jobs that exist now; forgets uploads older
/// than [`MAX_WAIT`] when they are.
pub(crate) async fn sweep(farm: Arc<Farm>, pending: Arc<Pending>, stop: CancellationToken) {
    let mut jobs = farm.watch_jobs();
    loop {
        let (wanted, expiry) = pending.expire(Instant::now());
        for entry in &wanted {
            let released = tokio::select! {
                () = stop.cancelled() => return,
                released = try_release(&farm, entry) => released,
            };
            match released {
                Ok(None) => {}
                Ok(Some(_)) => pending.forget(&entry.token),
                Err(e) => {
                    tracing::warn!(file = %entry.file, error = %e, "octoprint: a select-and-print could not release the upload's job");
                    pending.forget(&entry.token);
                }
            }
        }
        let expiry = async {
            match expiry {
                Some(at) => tokio::time::sleep_until(at.into()).await,
                None => std::future::pending().await,
            }
        };
        tokio::select! {
            () = stop.cancelled() => return,
            () = pending.wanted.notified() => {}
            changed = jobs.changed() => {
                if changed.is_err() {
                    // The store has ended: the daemon is stopping.
                    stop.cancelled().await;
                    return;
                }
            }
            () = expiry => {}
        }
    }
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
        let pending = Pending::default();
        pending.remember(folder, "a.gcode", "t1", None);
        pending.remember(folder, "a.gcode", "t2", Some("k"));
        assert_eq!(
            pending.newest(folder, "a.gcode"),
            Some(("t2".to_string(), Some("k".to_string())))
        );
        assert_eq!(pending.unwanted(folder, Some("k")).len(), 1);
        for i in 0..MAX_PENDING + 5 {
            pending.remember(folder, "b.gcode", &format!("x{i}"), None);
        }
        assert_eq!(pending.entries().len(), MAX_PENDING);
    }
}
