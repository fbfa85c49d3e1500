//! The daemon's side of a preparation: the child process (`crispen prepare-job`) it runs
//! for a task, fed the task on stdin and heard on stdout, and killed when the job is
//! cancelled, the daemon stops or the time limit passes.

use super::task::{ChildMessage, PrepareTask, Prepared};
use crate::slice::walls::WallComparison;
use std::collections::VecDeque;
use std::path::{Path, PathBuf};
use std::time::Duration;
use tokio::io::{AsyncBufReadExt, AsyncWriteExt};
use tokio_util::sync::CancellationToken;

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
    on_step: impl FnMut(String),
) -> Result<Prepared, PrepareError> {
    match child_answer(program, task, cancel, on_step).await? {
        ChildMessage::Done(prepared) => Ok(*prepared),
        other => Err(unexpected(other)),
    }
}

/// Runs a [`PrepareTask::compare`] task in a child process, as [`run_child`] runs a
/// preparation.
pub async fn run_compare_child(
    program: &Path,
    task: &PrepareTask,
    cancel: &CancellationToken,
) -> Result<WallComparison, PrepareError> {
    match child_answer(program, task, cancel, |_| {}).await? {
        ChildMessage::Compared(comparison) => Ok(*comparison),
        other => Err(unexpected(other)),
    }
}

/// A child that answered another task's message: a crispen of another version.
fn unexpected(message: ChildMessage) -> PrepareError {
    PrepareError::Failed(format!(
        "the preparation process answered the wrong kind of task: {message:?}"
    ))
}

/// The child's last message, [`ChildMessage::Done`] or [`ChildMessage::Compared`].
async fn child_answer(
    program: &Path,
    task: &PrepareTask,
    cancel: &CancellationToken,
    mut on_step: impl FnMut(String),
) -> Result<ChildMessage, PrepareError> {
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
        Some(ChildMessage::Failed(reason)) => Err(PrepareError::Failed(reason)),
        Some(end) => Ok(end),
        None => Err(PrepareError::Crashed {
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
