//! A job's timelapse frames encoded to an MP4 that plays in a browser (H.264, yuv420p, its
//! index at the front), by `ffmpeg` on one thread so a busy host's prints keep their
//! cores; and the cameras' disk limit, which removes the oldest jobs' pictures first and
//! never those of a job being recorded.

use std::path::Path;
use std::time::Duration;
use tokio::io::AsyncReadExt;

/// Frames per second of a timelapse.
const FPS: u32 = 10;

/// Where frame `frame` (from 0) is in an encoded timelapse, seconds.
pub(crate) fn seconds_at(frame: u32) -> f64 {
    f64::from(frame) / f64::from(FPS)
}
/// The longest an encoding may take.
const ENCODE_TIMEOUT: Duration = Duration::from_secs(600);
/// What is kept of ffmpeg's complaints.
const STDERR_KEPT: usize = 4096;

/// Encodes `frames/00001.jpg...` into `out`; its size in bytes, or why not.
pub async fn encode(frames: &Path, out: &Path) -> Result<u64, String> {
    let partial = out.with_extension("partial.mp4");
    let mut child = tokio::process::Command::new("ffmpeg")
        .args(["-hide_banner", "-loglevel", "error", "-nostdin", "-y"])
        .args(["-framerate", &FPS.to_string()])
        .arg("-i")
        .arg(frames.join("%05d.jpg"))
        .args([
            "-vf",
            "scale=trunc(iw/2)*2:trunc(ih/2)*2,format=yuv420p",
            "-c:v",
            "libx264",
            "-preset",
            "veryfast",
            "-threads",
            "1",
            "-movflags",
            "+faststart",
        ])
        .arg(&partial)
        .stdin(std::process::Stdio::null())
        .stdout(std::process::Stdio::null())
        .stderr(std::process::Stdio::piped())
        .kill_on_drop(true)
        .spawn()
        .map_err(|e| format!("cannot run ffmpeg: {e} (hint: install Debian's ffmpeg package)"))?;
    let mut stderr = child.stderr.take();
    let run = async {
        let mut kept = Vec::new();
        if let Some(err) = stderr.as_mut() {
            let mut buf = [0u8; 1024];
            while let Ok(n) = err.read(&mut buf).await {
                if n == 0 {
                    break;
                }
                let room = STDERR_KEPT.saturating_sub(kept.len());
                kept.extend_from_slice(&buf[..n.min(room)]);
            }
        }
        (child.wait().await, kept)
    };
    let (status, stderr) = tokio::time::timeout(ENCODE_TIMEOUT, run)
        .await
        .map_err(|_| {
            format!(
                "ffmpeg took more than {} s; stopped",
                ENCODE_TIMEOUT.as_secs()
            )
        })?;
    let status = status.map_err(|e| format!("ffmpeg: {e}"))?;
    if !status.success() {
        let _ = tokio::fs::remove_file(&partial).await;
        return Err(format!(
            "ffmpeg failed ({status}): {}",
            String::from_utf8_lossy(&stderr).trim()
        ));
    }
    tokio::fs::rename(&partial, out)
        .await
        .map_err(|e| format!("cannot keep {}: {e}", out.display()))?;
    let bytes = tokio::fs::metadata(out).await.map(|m| m.len()).unwrap_or(0);
    Ok(bytes)
}

/// Removes whole job folders under `root`, oldest first, until all of them together take
/// at most `limit` bytes; never `keep`'s nor a folder changed in the last minute (a job
/// being recorded writes to its folder at least that often while its camera answers).
pub async fn enforce_limit(root: &Path, limit: u64, keep: &str) {
    let (root, keep) = (root.to_path_buf(), keep.to_string());
    let _ = tokio::task::spawn_blocking(move || enforce_limit_now(&root, limit, &keep)).await;
}

fn enforce_limit_now(root: &Path, limit: u64, keep: &str) {
    let Ok(entries) = std::fs::read_dir(root) else {
        return;
    };
    let mut folders: Vec<(std::time::SystemTime, u64, std::path::PathBuf, bool)> = entries
        .flatten()
        .filter(|e| e.file_type().is_ok_and(|t| t.is_dir()))
        .map(|e| {
            let path = e.path();
            let (size, newest) = folder_size(&path);
            let busy = e.file_name() == keep
                || newest
                    .elapsed()
                    .is_ok_and(|age| age < Duration::from_secs(60));
            (newest, size, path, busy)
        })
        .collect();
    let mut total: u64 = folders.iter().map(|f| f.1).sum();
    folders.sort_by_key(|f| f.0);
    for (_, size, path, busy) in folders {
        if total <= limit {
            break;
        }
        if busy {
            continue;
        }
        match std::fs::remove_dir_all(&path) {
            Ok(()) => {
                total -= size;
                tracing::info!(folder = %path.display(), bytes = size, "camera: removed an old job's pictures ([camera] disk_limit_mb)");
            }
            Err(e) => {
                tracing::warn!(folder = %path.display(), error = %e, "camera: cannot remove an old job's pictures")
            }
        }
    }
}

/// The bytes under a folder and its newest modification.
fn folder_size(dir: &Path) -> (u64, std::time::SystemTime) {
    let mut size = 0;
    let mut newest = std::time::UNIX_EPOCH;
    let mut stack = vec![dir.to_path_buf()];
    while let Some(d) = stack.pop() {
        let Ok(entries) = std::fs::read_dir(&d) else {
            continue;
        };
        for e in entries.flatten() {
            let Ok(meta) = e.metadata() else { continue };
            if let Ok(m) = meta.modified() {
                newest = newest.max(m);
            }
            if meta.is_dir() {
                stack.push(e.path());
            } else {
                size += meta.len();
            }
        }
    }
    (size, newest)
}

/// The bytes the jobs' pictures take together (for `/metrics`).
pub(crate) fn total_bytes(root: &Path) -> u64 {
    folder_size(root).0
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_oldest_jobs_go_first_and_never_the_one_kept() {
        let root = tempfile::tempdir().unwrap();
        let old = std::time::SystemTime::now() - Duration::from_secs(3600);
        for (i, job) in ["a", "b", "c", "d"].iter().enumerate() {
            let dir = root.path().join(job);
            std::fs::create_dir(&dir).unwrap();
            let f = dir.join("x.jpg");
            std::fs::write(&f, vec![0u8; 1000]).unwrap();
            let t = old + Duration::from_secs(i as u64 * 60);
            std::fs::File::options()
                .write(true)
                .open(&f)
                .unwrap()
                .set_modified(t)
                .unwrap();
            std::fs::File::open(&dir).unwrap().set_modified(t).unwrap();
        }
        // "a" is the oldest but kept; "b" and "c" go, "d" brings it under 2,000 bytes.
        enforce_limit_now(root.path(), 2000, "a");
        let left: Vec<bool> = ["a", "b", "c", "d"]
            .iter()
            .map(|j| root.path().join(j).exists())
            .collect();
        assert_eq!(left, [true, false, false, true]);
        assert_eq!(total_bytes(root.path()), 2000);
    }
}
