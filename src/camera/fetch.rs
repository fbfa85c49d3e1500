//! Asking a camera server for frames over HTTP: one JPEG from a snapshot URL, or the
//! frames of an MJPEG stream as they come. Each wait has the camera's time limit and each
//! frame its size limit; what a camera answers instead (an error page, HTML, a stream with
//! no boundary) is an error that says what came.

use super::mjpeg::{boundary_of, check_jpeg, megabytes, FrameFault, MjpegError, MjpegReader, Part};
use crate::outbound::HttpUrl;
use bytes::Bytes;
use http_body_util::{BodyExt, Empty};
use hyper::body::Incoming;
use hyper_util::rt::TokioIo;
use serde::{Deserialize, Serialize};
use std::time::Duration;

/// Why a camera gave no frame, as data: the status and the job page word it, and a job's
/// `camera.json` keeps it (the details, an OS's or a library's words, are the log's).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(tag = "kind", rename_all = "snake_case")]
pub enum CameraFault {
    /// The connection was refused or could not be made.
    Connect,
    /// No answer within the time limit.
    Timeout { seconds: f64 },
    /// An MJPEG stream gave no part within the time limit.
    NoFrame { seconds: f64 },
    /// An HTTP status other than success.
    Status { code: u16 },
    /// Something other than a JPEG (an error page).
    NotJpeg,
    /// A frame over `[camera] frame_max_mb`.
    TooLarge { max_bytes: usize },
    /// Not an MJPEG stream where one was configured.
    NotStream,
    /// A stream without its boundary.
    NoBoundary { max_bytes: usize },
    /// The stream or the connection ended.
    Closed,
    /// The HTTP exchange failed otherwise.
    Http,
    /// A frame that is not a whole JPEG.
    Refused { frame: FrameFault },
}

/// Why no frame came.
#[derive(Debug, thiserror::Error)]
pub enum FetchError {
    #[error("cannot connect to {host}:{port}: {message}")]
    Connect {
        host: String,
        port: u16,
        message: String,
    },
    #[error("no answer within {0:?}")]
    Timeout(Duration),
    #[error("no whole frame within {0:?}")]
    NoFrame(Duration),
    #[error("answered HTTP {0}")]
    Status(u16),
    #[error("answered {0}, not a JPEG")]
    NotJpeg(String),
    #[error("a frame larger than {} ([camera] frame_max_mb)", megabytes(*.0))]
    TooLarge(usize),
    #[error("answered {0}, not an MJPEG stream (multipart/x-mixed-replace with a boundary)")]
    NotStream(String),
    #[error("the stream: {0}")]
    Stream(#[from] MjpegError),
    #[error("HTTP: {0}")]
    Http(String),
    #[error("the stream ended")]
    Closed,
    /// A frame that is not a whole JPEG (cut, run into the next part, not decoding).
    #[error("{0}")]
    Refused(FrameFault),
}

impl FetchError {
    /// What went wrong, as data (the words and the details are the log's).
    pub fn fault(&self) -> CameraFault {
        match self {
            FetchError::Connect { .. } => CameraFault::Connect,
            FetchError::Timeout(d) => CameraFault::Timeout {
                seconds: d.as_secs_f64(),
            },
            FetchError::NoFrame(d) => CameraFault::NoFrame {
                seconds: d.as_secs_f64(),
            },
            FetchError::Status(code) => CameraFault::Status { code: *code },
            FetchError::NotJpeg(_) | FetchError::Stream(MjpegError::NotJpeg { .. }) => {
                CameraFault::NotJpeg
            }
            FetchError::TooLarge(max) | FetchError::Stream(MjpegError::TooLarge { max }) => {
                CameraFault::TooLarge { max_bytes: *max }
            }
            FetchError::NotStream(_) => CameraFault::NotStream,
            FetchError::Stream(MjpegError::NoBoundary { max }) => {
                CameraFault::NoBoundary { max_bytes: *max }
            }
            FetchError::Stream(MjpegError::Ended) | FetchError::Closed => CameraFault::Closed,
            FetchError::Http(_) => CameraFault::Http,
            FetchError::Refused(frame) => CameraFault::Refused { frame: *frame },
        }
    }
}

/// An answer whose body is read on; its connection is driven by a task of its own, which
/// ends with it.
struct Answer {
    response: hyper::Response<Incoming>,
    _connection: tokio_util::task::AbortOnDropHandle<()>,
}

async fn get(url: &HttpUrl, timeout: Duration) -> Result<Answer, FetchError> {
    tokio::time::timeout(timeout, get_inner(url))
        .await
        .map_err(|_| FetchError::Timeout(timeout))?
}

async fn get_inner(url: &HttpUrl) -> Result<Answer, FetchError> {
    let io = crate::outbound::connect(url)
        .await
        .map_err(|e| match e.connect_failure() {
            Some(message) => FetchError::Connect {
                host: url.host.clone(),
                port: url.port,
                message,
            },
            None => FetchError::Http(e.to_string()),
        })?;
    let request = crate::outbound::request(url, hyper::Method::GET, &url.path)
        .body(Empty::<Bytes>::new())
        .map_err(|e| FetchError::Http(e.to_string()))?;
    exchange(io, request).await
}

/// `request` on one connection, which a task of its own drives while the body is read.
async fn exchange(
    io: impl tokio::io::AsyncRead + tokio::io::AsyncWrite + Unpin + Send + 'static,
    request: hyper::Request<Empty<Bytes>>,
) -> Result<Answer, FetchError> {
    let http = |e: hyper::Error| FetchError::Http(e.to_string());
    let (mut sender, connection) = hyper::client::conn::http1::handshake(TokioIo::new(io))
        .await
        .map_err(http)?;
    let connection = drive(connection);
    let response = sender.send_request(request).await.map_err(http)?;
    Ok(Answer {
        response,
        _connection: connection,
    })
}

fn drive<F>(connection: F) -> tokio_util::task::AbortOnDropHandle<()>
where
    F: std::future::Future + Send + 'static,
{
    tokio_util::task::AbortOnDropHandle::new(tokio::spawn(async move {
        let _ = connection.await;
    }))
}

fn content_type(response: &hyper::Response<Incoming>) -> String {
    response
        .headers()
        .get(hyper::header::CONTENT_TYPE)
        .and_then(|v| v.to_str().ok())
        .unwrap_or("no Content-Type")
        .chars()
        .take(100)
        .collect()
}

fn check_status(response: &hyper::Response<Incoming>) -> Result<(), FetchError> {
    let status = response.status();
    if status.is_success() {
        Ok(())
    } else {
        Err(FetchError::Status(status.as_u16()))
    }
}

/// One JPEG from a snapshot URL, whole within `timeout`.
pub async fn snapshot(url: &HttpUrl, timeout: Duration, max: usize) -> Result<Vec<u8>, FetchError> {
    tokio::time::timeout(timeout, async {
        let answer = get(url, timeout).await?;
        check_status(&answer.response)?;
        let kind = content_type(&answer.response);
        let mut body = answer.response.into_body();
        let mut bytes = Vec::new();
        while let Some(frame) = body.frame().await {
            let frame = frame.map_err(|e| FetchError::Http(e.to_string()))?;
            if let Ok(data) = frame.into_data() {
                if bytes.len() + data.len() > max {
                    return Err(FetchError::TooLarge(max));
                }
                bytes.extend_from_slice(&data);
            }
        }
        match check_jpeg(&bytes) {
            Ok(len) => {
                bytes.truncate(len);
                Ok(bytes)
            }
            Err(FrameFault::NotJpeg { bytes: n }) => {
                Err(FetchError::NotJpeg(format!("{kind} ({n} bytes)")))
            }
            Err(fault) => Err(FetchError::Refused(fault)),
        }
    })
    .await
    .map_err(|_| FetchError::Timeout(timeout))?
}

/// The body's first bytes, up to its first line's end (at most 256 bytes).
async fn first_line(response: &mut hyper::Response<Incoming>) -> Result<Vec<u8>, FetchError> {
    let mut start = Vec::new();
    while start.len() < 256 && !start.contains(&b'\n') {
        let Some(frame) = response.body_mut().frame().await else {
            break;
        };
        let frame = frame.map_err(|e| FetchError::Http(e.to_string()))?;
        if let Ok(data) = frame.into_data() {
            start.extend_from_slice(&data);
        }
    }
    Ok(start)
}

/// An open MJPEG stream.
pub struct Stream {
    answer: Answer,
    reader: MjpegReader,
    ready: std::collections::VecDeque<Part>,
    timeout: Duration,
}

impl Stream {
    /// Opens the stream. Its boundary is the content type's, or (ffmpeg's own server says
    /// `application/octet-stream`) the first line of the body when that is one.
    pub async fn open(url: &HttpUrl, timeout: Duration, max: usize) -> Result<Stream, FetchError> {
        let mut answer = get(url, timeout).await?;
        check_status(&answer.response)?;
        let kind = content_type(&answer.response);
        let (boundary, start) = match boundary_of(&kind) {
            Some(b) => (b, Vec::new()),
            None => {
                let start = tokio::time::timeout(timeout, first_line(&mut answer.response))
                    .await
                    .map_err(|_| FetchError::NoFrame(timeout))??;
                let line = String::from_utf8_lossy(&start).into_owned();
                let boundary = line
                    .lines()
                    .next()
                    .and_then(|l| l.strip_prefix("--"))
                    .map(|b| b.trim().to_string())
                    .filter(|b| !b.is_empty() && line.contains('\n'))
                    .ok_or(FetchError::NotStream(kind))?;
                (boundary, start)
            }
        };
        let mut stream = Stream {
            answer,
            reader: MjpegReader::new(&boundary, max),
            ready: Default::default(),
            timeout,
        };
        stream.ready.extend(stream.reader.feed(&start)?);
        Ok(stream)
    }

    /// The next part: a whole frame, or one refused (the stream goes on after it); an
    /// error when none comes within the time limit (a stream that trickles bytes without
    /// a part is as dead as a silent one).
    pub async fn next(&mut self) -> Result<Part, FetchError> {
        let timeout = self.timeout;
        tokio::time::timeout(timeout, async {
            loop {
                if let Some(part) = self.ready.pop_front() {
                    return Ok(part);
                }
                let Some(frame) = self.answer.response.body_mut().frame().await else {
                    return Err(FetchError::Closed);
                };
                let frame = frame.map_err(|e| FetchError::Http(e.to_string()))?;
                if let Ok(data) = frame.into_data() {
                    self.ready.extend(self.reader.feed(&data)?);
                }
            }
        })
        .await
        .map_err(|_| FetchError::NoFrame(timeout))?
    }
}
