//! Preparing a job: read its sidecar, work out the folder's settings with the sidecar's
//! overrides, then enhance and slice the model into `<job dir>/<file>.gcode`, keeping the
//! enhanced mesh that was sliced as `<job dir>/<file>.enhanced.stl`.
//!
//! The work runs in a child process (`crispen prepare-job`, [`run_child`]) rather than on a
//! thread: loading, cleaning and enhancing a model are long computations with nowhere to
//! stop, so a hostile or merely huge file could otherwise hold a preparation slot for as
//! long as it likes. A child can be killed at once, whatever it is doing, when the job is
//! cancelled, the daemon stops, or the configured time limit passes, and its memory goes
//! back to the system when it ends. The child speaks [`ChildMessage`] JSON lines on stdout.

use super::config::{parse_strength, FolderConfig};
use super::job::Sidecar;
use crate::enhance::Strength;
use crate::slice::{SliceReport, SlicerKind, UpAxis};
use serde::{Deserialize, Serialize};
use std::collections::VecDeque;
use std::io::Read;
use std::path::{Path, PathBuf};
use std::time::Duration;
use tokio::io::{AsyncBufReadExt, AsyncWriteExt};
use tokio_util::sync::CancellationToken;

/// Everything one preparation needs, resolved from the folder config and the sidecar.
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct PrepareTask {
    pub job: String,
    pub model: PathBuf,
    pub output: PathBuf,
    /// Where the enhanced, placed mesh that was sliced is kept.
    pub enhanced_mesh: PathBuf,
    pub height_mm: f64,
    pub strength: Strength,
    pub slicer: SlicerKind,
    pub up: UpAxis,
    pub profile: Option<PathBuf>,
    pub settings: crate::slice::SliceSettings,
    /// The whole preparation (load, enhance, slice) is stopped after this long.
    pub timeout: Duration,
}

/// What the preparation child writes on stdout, one JSON object per line.
#[derive(Debug, Clone, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum ChildMessage {
    /// The step it is on (shown by `crispen status`).
    Step(String),
    Done(Box<SliceReport>),
    /// The job failed; the reason is for the operator.
    Failed(String),
}

/// Why a preparation did not produce G-code.
#[derive(Debug, thiserror::Error)]
pub enum PrepareError {
    /// The model, its settings or the slicer failed; the message says which and why.
    #[error("{0}")]
    Failed(String),
    #[error("preparation took longer than {after:?} and was stopped (hint: raise the folder's `timeout_s`, or print a smaller model)")]
    TimedOut { after: Duration },
    #[error("preparation was stopped (the job was cancelled or the daemon is stopping)")]
    Cancelled,
    #[error("cannot start the preparation process {program}: {source}")]
    Spawn {
        program: PathBuf,
        #[source]
        source: std::io::Error,
    },
    #[error("the preparation process ended without an answer ({status}); its last output:\n{stderr_tail}")]
    Crashed { status: String, stderr_tail: String },
}

/// Stderr lines of the child kept for an error message.
const STDERR_TAIL_LINES: usize = 20;

/// Runs one preparation in a child process: `program prepare-job`, the task as JSON on its
/// stdin. `on_step` hears each step. The child is killed (and with it any slicer it runs,
/// which dies with its parent) when `cancel` fires or `task.timeout` passes.
pub async fn run_child(
    program: &Path,
    task: &PrepareTask,
    cancel: &CancellationToken,
    mut on_step: impl FnMut(String),
) -> Result<SliceReport, PrepareError> {
    let mut cmd = tokio::process::Command::new(program);
    cmd.arg("prepare-job")
        .stdin(std::process::Stdio::piped())
        .stdout(std::process::Stdio::piped())
        .stderr(std::process::Stdio::piped())
        .kill_on_drop(true);
    // The child (and the slicer it runs, in turn) dies with the daemon.
    crate::slice::process::die_with_this_process(cmd.as_std_mut());
    let mut child = cmd.spawn().map_err(|source| PrepareError::Spawn {
        program: program.to_path_buf(),
        source,
    })?;
    let input = serde_json::to_vec(task).expect("a task serialises");
    let mut stdin = child.stdin.take().expect("stdin is piped");
    let mut stdout =
        tokio::io::BufReader::new(child.stdout.take().expect("stdout is piped")).lines();
    let mut stderr =
        tokio::io::BufReader::new(child.stderr.take().expect("stderr is piped")).lines();
    let feed = async move {
        let _ = stdin.write_all(&input).await;
        // stdin dropped here: the child sees the end of the task.
    };
    let deadline = tokio::time::sleep(task.timeout);
    tokio::pin!(feed, deadline);
    let mut fed = false;
    let mut answer = None;
    let mut stdout_open = true;
    let mut stderr_open = true;
    let mut tail = VecDeque::with_capacity(STDERR_TAIL_LINES);
    while stdout_open || stderr_open {
        tokio::select! {
            _ = &mut feed, if !fed => fed = true,
            line = stdout.next_line(), if stdout_open => match line {
                Ok(Some(line)) => match serde_json::from_str::<ChildMessage>(&line) {
                    Ok(ChildMessage::Step(step)) => on_step(step),
                    Ok(end) => answer = Some(end),
                    Err(_) => push_tail(&mut tail, line),
                },
                _ => stdout_open = false,
            },
            line = stderr.next_line(), if stderr_open => match line {
                Ok(Some(line)) => {
                    tracing::debug!(child = %line, "preparation output");
                    push_tail(&mut tail, line);
                }
                _ => stderr_open = false,
            },
            _ = cancel.cancelled() => {
                let _ = child.start_kill();
                let _ = child.wait().await;
                return Err(PrepareError::Cancelled);
            }
            _ = &mut deadline => {
                let _ = child.start_kill();
                let _ = child.wait().await;
                return Err(PrepareError::TimedOut { after: task.timeout });
            }
        }
    }
    let status = tokio::select! {
        status = child.wait() => status,
        _ = cancel.cancelled() => {
            let _ = child.start_kill();
            return Err(PrepareError::Cancelled);
        }
    };
    match answer {
        Some(ChildMessage::Done(report)) => Ok(*report),
        Some(ChildMessage::Failed(reason)) => Err(PrepareError::Failed(reason)),
        _ => Err(PrepareError::Crashed {
            status: status.map_or_else(|e| e.to_string(), |s| s.to_string()),
            stderr_tail: Vec::from(tail).join("\n"),
        }),
    }
}

fn push_tail(tail: &mut VecDeque<String>, line: String) {
    if tail.len() == STDERR_TAIL_LINES {
        tail.pop_front();
    }
    tail.push_back(line.chars().take(400).collect());
}

/// Reads a sidecar file (`model.stl.toml`); unknown keys are an error.
pub fn read_sidecar(path: &Path) -> Result<Option<Sidecar>, String> {
    let file = match std::fs::File::open(path) {
        Ok(f) => f,
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => return Ok(None),
        Err(e) => return Err(format!("sidecar {}: cannot read: {e}", path.display())),
    };
    parse_sidecar(file, path).map(Some)
}

/// Copies of one model a sidecar may ask for.
pub const MAX_COPIES: u32 = 100;

/// A sidecar holds a handful of short keys; anything bigger is not one.
pub const MAX_SIDECAR_BYTES: u64 = 16 * 1024;

/// Parses a sidecar from any reader; `path` names it in errors.
pub fn parse_sidecar(reader: impl Read, path: &Path) -> Result<Sidecar, String> {
    let mut text = String::new();
    reader
        .take(MAX_SIDECAR_BYTES + 1)
        .read_to_string(&mut text)
        .map_err(|e| format!("sidecar {}: cannot read: {e}", path.display()))?;
    if text.len() as u64 > MAX_SIDECAR_BYTES {
        return Err(format!(
            "sidecar {}: larger than {MAX_SIDECAR_BYTES} bytes; a sidecar holds a few keys",
            path.display()
        ));
    }
    let sidecar: Sidecar = toml::from_str(&text).map_err(|e| {
        format!(
            "sidecar {}: {} (allowed keys: height_mm, enhance, strength, up, copies, printer)",
            path.display(),
            e.message().trim()
        )
    })?;
    if let Some(h) = sidecar.height_mm {
        super::config::check_height(h)
            .map_err(|m| format!("sidecar {}: key `height_mm`: {m}", path.display()))?;
    }
    if let Some(n) = sidecar.copies {
        if !(1..=MAX_COPIES).contains(&n) {
            return Err(format!(
                "sidecar {}: key `copies`: must be from 1 to {MAX_COPIES}, got {n}",
                path.display()
            ));
        }
    }
    if let Some(s) = &sidecar.strength {
        parse_strength(s)
            .map_err(|m| format!("sidecar {}: key `strength`: {m}", path.display()))?;
    }
    Ok(sidecar)
}

/// Combines a folder's settings with a sidecar's overrides into a task.
pub fn resolve_task(
    job: &str,
    job_dir: &Path,
    file: &str,
    folder: &FolderConfig,
    sidecar: Option<&Sidecar>,
) -> Result<PrepareTask, String> {
    let mut strength = folder.strength;
    let mut height_mm = folder.height_mm;
    let mut up = folder.up;
    if let Some(s) = sidecar {
        if let Some(h) = s.height_mm {
            height_mm = h;
        }
        if let Some(axis) = s.up {
            up = axis;
        }
        if let Some(v) = &s.strength {
            strength = parse_strength(v)?;
        }
        if s.enhance == Some(false) {
            strength = Strength::Off;
        } else if s.enhance == Some(true) && strength == Strength::Off {
            strength = Strength::Auto;
        }
        if let Some(p) = &s.printer {
            if !folder.printers.contains(p) {
                return Err(format!(
                    "sidecar {file}.toml: key `printer`: {p:?} does not serve folder {} (it is served by {})",
                    folder.path.display(),
                    folder.printers.join(", ")
                ));
            }
        }
    }
    Ok(PrepareTask {
        job: job.to_string(),
        model: job_dir.join(file),
        output: job_dir.join(format!("{file}.gcode")),
        enhanced_mesh: job_dir.join(format!("{file}.enhanced.stl")),
        height_mm,
        strength,
        slicer: folder.slicer,
        up,
        profile: folder.profile.clone(),
        settings: folder.settings.clone(),
        timeout: folder.timeout,
    })
}

/// The preparation itself, as the child runs it: `crispen::slice` (load, enhance, place,
/// slice with a real slicer). `progress` hears each step's name. Blocking.
pub fn prepare(
    task: &PrepareTask,
    progress: &mut dyn FnMut(String),
) -> Result<SliceReport, crate::slice::SliceError> {
    use crate::enhance::Phase;
    use crate::slice::{SliceRequest, SliceStep};
    let mut req = SliceRequest::new(&task.model, &task.output, task.height_mm);
    req.slicer = task.slicer;
    req.strength = task.strength;
    req.up = task.up;
    req.settings = task.settings.clone();
    req.profile = task.profile.clone();
    req.timeout = task.timeout;
    req.keep_mesh = Some(task.enhanced_mesh.clone());
    // Pictures and thumbnails go next to the G-code, in the job's directory.
    req.pictures = task.output.parent().map(Path::to_path_buf);
    crate::slice::slice(&req, &mut |step| {
        progress(match step {
            SliceStep::Loading => "loading".to_string(),
            SliceStep::Enhancing(Phase::Operators) => "enhancing: operators".into(),
            SliceStep::Enhancing(Phase::Factorize) => "enhancing: factorizing".into(),
            SliceStep::Enhancing(Phase::Solve(i)) => format!("enhancing: solve {i}"),
            SliceStep::Enhancing(Phase::Combine) => "enhancing: combining".into(),
            SliceStep::Slicing => "slicing".into(),
            SliceStep::Checking => "checking the G-code".into(),
        })
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    fn folder() -> FolderConfig {
        FolderConfig {
            path: "/hot".into(),
            height_mm: 50.0,
            printers: vec!["a".into(), "b".into()],
            strength: Strength::Auto,
            slicer: SlicerKind::Prusa,
            up: UpAxis::Z,
            profile: None,
            timeout: Duration::from_secs(60),
            settings: Default::default(),
        }
    }

    #[test]
    fn sidecar_overrides_and_rejects_unknown_keys() {
        let s = parse_sidecar(
            &b"enhance = false\nheight_mm = 20\nup = \"y\"\n"[..],
            Path::new("m.stl.toml"),
        )
        .unwrap();
        let t = resolve_task("j", Path::new("/s/j"), "m.stl", &folder(), Some(&s)).unwrap();
        assert_eq!(t.strength, Strength::Off);
        assert_eq!(t.height_mm, 20.0);
        assert_eq!(t.up, UpAxis::Y);
        assert_eq!(t.output, PathBuf::from("/s/j/m.stl.gcode"));

        let err = parse_sidecar(&b"enhanse = false\n"[..], Path::new("m.stl.toml")).unwrap_err();
        assert!(
            err.contains("m.stl.toml") && err.contains("enhanse"),
            "{err}"
        );
        let err = parse_sidecar(&b"height_mm = -1\n"[..], Path::new("m.stl.toml")).unwrap_err();
        assert!(err.contains("height_mm"), "{err}");

        let s = parse_sidecar(&b"printer = \"zz\"\n"[..], Path::new("m.stl.toml")).unwrap();
        let err = resolve_task("j", Path::new("/s/j"), "m.stl", &folder(), Some(&s)).unwrap_err();
        assert!(err.contains("\"zz\""), "{err}");
    }
}
