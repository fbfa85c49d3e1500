//! The control API: JSON lines over a unix socket (mode 0660, so the service user's group
//! may use it). Each request line gets one response line. [`serve`] runs in the daemon;
//! [`request`] is the client used by `crispen status|clear|cancel|pause|resume|retry`.
//!
//! Requests: `{"cmd":"status"}`, `{"cmd":"clear","printer":"a"}`, `{"cmd":"cancel","job":"0001-x"}`,
//! `{"cmd":"pause","printer":"a"}`, `{"cmd":"resume","printer":"a"}`, `{"cmd":"retry","job":"..."}`.
//! Responses: `{"ok":true,"message":...,"status":{...}}` or `{"ok":false,"error":"..."}`.

use super::farm::{Farm, LiveProgress, PrintCommand, PrinterStatus};
use super::job::{JobState, StoreError};
use serde::{Deserialize, Serialize};
use std::collections::HashMap;
use std::io::{BufRead, BufReader, Write};
use std::os::unix::fs::PermissionsExt;
use std::path::{Path, PathBuf};
use std::sync::Arc;
use tokio::io::{AsyncBufReadExt, AsyncReadExt, AsyncWriteExt};

#[derive(Debug, Clone, Serialize, Deserialize, PartialEq)]
#[serde(tag = "cmd", rename_all = "lowercase", deny_unknown_fields)]
pub enum Request {
    Status,
    Clear { printer: String },
    Cancel { job: String },
    Pause { printer: String },
    Resume { printer: String },
    Retry { job: String },
}

#[derive(Debug, Clone, Serialize, Deserialize, Default)]
pub struct Response {
    pub ok: bool,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub error: Option<String>,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub message: Option<String>,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub status: Option<Status>,
}

#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct Status {
    pub printers: Vec<PrinterStatus>,
    pub jobs: Vec<JobStatus>,
}

#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct JobStatus {
    pub id: String,
    pub file: String,
    pub folder: PathBuf,
    pub state: JobState,
    pub printer: Option<String>,
    pub reason: Option<String>,
    /// Preparation step, while preparing.
    pub step: Option<String>,
    /// Print progress, while printing.
    pub progress: Option<LiveProgress>,
    pub copies_done: u32,
    pub copies: u32,
    pub updated: f64,
}

/// Why a control command was refused; the client shows the message.
#[derive(Debug, thiserror::Error)]
pub enum CommandError {
    #[error("no printer {0:?} (hint: `crispen status` lists the printers)")]
    NoPrinter(String),
    #[error("{0} is not printing")]
    NotPrinting(String),
    #[error("{0}: the print just ended")]
    PrintEnded(String),
    #[error("job {id} is {state}; only active jobs can be cancelled")]
    NotActive { id: String, state: JobState },
    #[error(transparent)]
    Store(#[from] StoreError),
}

#[derive(Debug, thiserror::Error)]
pub enum ControlError {
    #[error("cannot reach the daemon at {socket}: {source} (hint: is `crispen run` running with the same --config?)")]
    Connect {
        socket: PathBuf,
        #[source]
        source: std::io::Error,
    },
    #[error("control socket {socket}: {source}")]
    Io {
        socket: PathBuf,
        #[source]
        source: std::io::Error,
    },
    #[error("control socket {socket}: unreadable answer: {message}")]
    Protocol { socket: PathBuf, message: String },
}

/// Sends one request and waits for its answer (blocking; used by the CLI).
pub fn request(socket: &Path, req: &Request) -> Result<Response, ControlError> {
    let stream = std::os::unix::net::UnixStream::connect(socket).map_err(|source| {
        ControlError::Connect {
            socket: socket.to_path_buf(),
            source,
        }
    })?;
    let io = |source| ControlError::Io {
        socket: socket.to_path_buf(),
        source,
    };
    let mut line = serde_json::to_string(req).expect("request serialises");
    line.push('\n');
    (&stream).write_all(line.as_bytes()).map_err(io)?;
    let mut answer = String::new();
    BufReader::new(&stream).read_line(&mut answer).map_err(io)?;
    serde_json::from_str(&answer).map_err(|e| ControlError::Protocol {
        socket: socket.to_path_buf(),
        message: e.to_string(),
    })
}

/// Builds the status snapshot.
pub fn status(farm: &Farm) -> Status {
    let mut printers: Vec<PrinterStatus> = farm
        .printers
        .lock()
        .unwrap_or_else(|e| e.into_inner())
        .values()
        .cloned()
        .collect();
    let preparing: HashMap<String, String> = farm
        .preparing
        .lock()
        .unwrap_or_else(|e| e.into_inner())
        .iter()
        .map(|(id, p)| (id.clone(), p.step.clone()))
        .collect();
    let store = farm.store();
    for p in &mut printers {
        p.bed_cleared = !store.gate(&p.name).bed_not_cleared;
    }
    let jobs = store
        .jobs()
        .map(|j| JobStatus {
            id: j.id.clone(),
            file: j.file.clone(),
            folder: j.folder.clone(),
            state: j.state,
            printer: j.printer.clone(),
            reason: j.reason.clone(),
            step: (j.state == JobState::Preparing)
                .then(|| preparing.get(&j.id).cloned())
                .flatten(),
            progress: (j.state == JobState::Printing)
                .then(|| {
                    printers
                        .iter()
                        .find(|p| p.job.as_deref() == Some(j.id.as_str()))
                        .and_then(|p| p.progress.clone())
                })
                .flatten(),
            copies_done: j.copies_done,
            copies: j.copies_wanted(),
            updated: j.history.last().map(|h| h.1).unwrap_or(0.0),
        })
        .collect();
    Status { printers, jobs }
}

/// Carries out one request.
pub async fn handle(farm: &Arc<Farm>, req: Request) -> Response {
    let result: Result<Option<String>, CommandError> = match req {
        Request::Status => {
            return Response {
                ok: true,
                status: Some(status(farm)),
                ..Default::default()
            }
        }
        Request::Clear { printer } => clear(farm, &printer).await,
        Request::Pause { printer } => send_print_command(farm, &printer, PrintCommand::Pause).await,
        Request::Resume { printer } => {
            send_print_command(farm, &printer, PrintCommand::Resume).await
        }
        Request::Cancel { job } => cancel(farm, &job).await,
        Request::Retry { job } => {
            let r = farm.jobs.retry(&job).await.map_err(CommandError::from);
            r.map(|retried| {
                farm.bump();
                Some(match retried.state {
                    JobState::Ready => format!("job {job} is ready to print again"),
                    _ => format!("job {job} queued for preparation again"),
                })
            })
        }
    };
    match result {
        Ok(message) => Response {
            ok: true,
            message,
            ..Default::default()
        },
        Err(error) => Response {
            ok: false,
            error: Some(error.to_string()),
            ..Default::default()
        },
    }
}

fn known_printer(farm: &Farm, printer: &str) -> Result<(), CommandError> {
    if farm
        .printers
        .lock()
        .unwrap_or_else(|e| e.into_inner())
        .contains_key(printer)
    {
        Ok(())
    } else {
        Err(CommandError::NoPrinter(printer.to_string()))
    }
}

async fn clear(farm: &Farm, printer: &str) -> Result<Option<String>, CommandError> {
    known_printer(farm, printer)?;
    if !farm.jobs.clear_gate(printer).await? {
        return Ok(Some(format!("{printer}: bed was already clear")));
    }
    tracing::info!(printer, "bed cleared");
    farm.bump();
    Ok(Some(format!(
        "{printer}: bed cleared; it may take the next job"
    )))
}

async fn send_print_command(
    farm: &Farm,
    printer: &str,
    command: PrintCommand,
) -> Result<Option<String>, CommandError> {
    known_printer(farm, printer)?;
    let tx = farm
        .print_controls
        .lock()
        .unwrap_or_else(|e| e.into_inner())
        .get(printer)
        .cloned();
    let Some(tx) = tx else {
        return Err(CommandError::NotPrinting(printer.to_string()));
    };
    tx.send(command)
        .await
        .map_err(|_| CommandError::PrintEnded(printer.to_string()))?;
    tracing::info!(printer, ?command, "print command sent");
    Ok(Some(format!("{printer}: {command:?} sent")))
}

async fn cancel(farm: &Arc<Farm>, id: &str) -> Result<Option<String>, CommandError> {
    // Checked and changed as one step of the store: a printer claiming the job between
    // the two would otherwise print a job marked cancelled.
    const NOT_STARTED: &[JobState] = &[JobState::Queued, JobState::Preparing, JobState::Ready];
    let reason = Some("cancelled by the operator".into());
    let cancelled = farm
        .transition_from(id, NOT_STARTED, JobState::Cancelled, reason, |_| {})
        .await;
    match cancelled {
        Ok(_) => {
            // A slicer already running for it is stopped, not left to finish unwanted.
            if let Some(p) = farm
                .preparing
                .lock()
                .unwrap_or_else(|e| e.into_inner())
                .get(id)
            {
                p.cancel.cancel();
            }
            Ok(Some(format!("job {id} cancelled")))
        }
        Err(StoreError::StateChanged {
            state: JobState::Printing,
            ..
        }) => {
            let printer = farm
                .store()
                .get(id)
                .and_then(|j| j.printer.clone())
                .unwrap_or_default();
            send_print_command(farm, &printer, PrintCommand::Cancel).await?;
            Ok(Some(format!(
                "job {id}: stopping the print on {printer} (heaters off)"
            )))
        }
        Err(StoreError::StateChanged { state, .. }) => Err(CommandError::NotActive {
            id: id.to_string(),
            state,
        }),
        Err(e) => Err(e.into()),
    }
}

/// Longest request line accepted; a request is a few short fields.
pub const MAX_REQUEST_BYTES: usize = 64 * 1024;
/// A connection with no complete request for this long is closed.
pub const IDLE_TIMEOUT: std::time::Duration = std::time::Duration::from_secs(10);
/// Connections served at once; more wait in the kernel's backlog.
pub const MAX_CONNECTIONS: usize = 64;

/// Binds the control socket with mode 0660. An existing socket nobody answers on (left by
/// a daemon that was killed) is replaced; anything else at the path is left alone and
/// refused, so a mistyped `[control] socket` can never remove a file.
pub fn bind(socket: &Path) -> Result<tokio::net::UnixListener, ControlError> {
    use std::os::unix::fs::FileTypeExt;
    let io = |source| ControlError::Io {
        socket: socket.to_path_buf(),
        source,
    };
    if let Some(dir) = socket.parent() {
        std::fs::create_dir_all(dir).map_err(io)?;
    }
    match std::fs::symlink_metadata(socket) {
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => {}
        Err(e) => return Err(io(e)),
        Ok(meta) if !meta.file_type().is_socket() => {
            return Err(io(std::io::Error::new(
                std::io::ErrorKind::AlreadyExists,
                "the path exists and is not a socket; it is left alone (hint: use another [control] socket)",
            )))
        }
        Ok(_) => {
            if std::os::unix::net::UnixStream::connect(socket).is_ok() {
                return Err(io(std::io::Error::new(
                    std::io::ErrorKind::AddrInUse,
                    "another daemon is listening here (hint: stop it, or use another [control] socket)",
                )));
            }
            std::fs::remove_file(socket).map_err(io)?;
        }
    }
    let listener = tokio::net::UnixListener::bind(socket).map_err(io)?;
    std::fs::set_permissions(socket, std::fs::Permissions::from_mode(0o660)).map_err(io)?;
    Ok(listener)
}

/// Answers requests until the task is dropped: at most [`MAX_CONNECTIONS`] connections at
/// once, each closed after [`IDLE_TIMEOUT`] without a request or at a request longer than
/// [`MAX_REQUEST_BYTES`]; when accepting fails (out of file descriptors) it waits a
/// little longer each time instead of spinning.
pub async fn serve(farm: Arc<Farm>, listener: tokio::net::UnixListener) {
    let slots = Arc::new(tokio::sync::Semaphore::new(MAX_CONNECTIONS));
    let mut backoff = std::time::Duration::from_millis(10);
    loop {
        let Ok(slot) = Arc::clone(&slots).acquire_owned().await else {
            return;
        };
        let stream = tokio::select! {
            accepted = listener.accept() => match accepted {
                Ok((stream, _)) => stream,
                Err(e) => {
                    tracing::warn!(error = %e, retry_in_ms = backoff.as_millis() as u64, "control socket: cannot accept");
                    tokio::time::sleep(backoff).await;
                    backoff = (backoff * 2).min(std::time::Duration::from_secs(1));
                    continue;
                }
            },
            _ = farm.shutdown.cancelled() => return,
        };
        backoff = std::time::Duration::from_millis(10);
        let farm = Arc::clone(&farm);
        tokio::spawn(async move {
            let _slot = slot;
            serve_connection(&farm, stream).await;
        });
    }
}

/// Decodes one request line (as read, newline included or not) or says what is wrong
/// with it.
pub fn parse_request(line: &[u8]) -> Result<Request, String> {
    if line.len() > MAX_REQUEST_BYTES {
        return Err(format!(
            "bad request: longer than {MAX_REQUEST_BYTES} bytes; the connection is closed"
        ));
    }
    serde_json::from_slice(line).map_err(|e| format!("bad request: {e}"))
}

async fn serve_connection(farm: &Arc<Farm>, stream: tokio::net::UnixStream) {
    let (read, mut write) = stream.into_split();
    let mut reader = tokio::io::BufReader::new(read);
    loop {
        let mut line = Vec::new();
        let mut limited = (&mut reader).take(MAX_REQUEST_BYTES as u64 + 1);
        let read = limited.read_until(b'\n', &mut line);
        let read = tokio::select! {
            read = tokio::time::timeout(IDLE_TIMEOUT, read) => read,
            _ = farm.shutdown.cancelled() => return,
        };
        let response = match read {
            Err(_) | Ok(Err(_)) | Ok(Ok(0)) => return,
            Ok(Ok(_)) => match parse_request(&line) {
                Ok(req) => handle(farm, req).await,
                Err(error) => Response {
                    ok: false,
                    error: Some(error),
                    ..Default::default()
                },
            },
        };
        let mut out = serde_json::to_string(&response).expect("response serialises");
        out.push('\n');
        if write.write_all(out.as_bytes()).await.is_err() || line.len() > MAX_REQUEST_BYTES {
            return;
        }
    }
}
