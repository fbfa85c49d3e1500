//! The connection loop under both listeners (the control socket and TCP): HTTP/1.1 by
//! hyper, with the bounds a daemon facing any client needs. At most
//! [`Limits::max_connections`] connections at once (more wait in the kernel's backlog);
//! a request's head must arrive within [`Limits::header_timeout`], which also closes a
//! connection left idle between requests; a head larger than [`MAX_HEAD_BYTES`] is refused;
//! a response the client stops reading for [`Limits::write_stall`] ends its connection; and
//! when accepting fails (out of file descriptors) the loop waits a little longer each time
//! instead of spinning. Request bodies and handler times are bounded in the router.

use axum::Router;
use hyper_util::rt::{TokioIo, TokioTimer};
use hyper_util::service::TowerToHyperService;
use std::future::Future;
use std::io;
use std::pin::Pin;
use std::sync::Arc;
use std::task::{Context, Poll};
use std::time::Duration;
use tokio::io::{AsyncRead, AsyncWrite, ReadBuf};
use tokio_util::sync::CancellationToken;

/// Largest request head (request line and headers) read into memory.
pub const MAX_HEAD_BYTES: usize = 64 * 1024;

/// The bounds of one listener.
#[derive(Debug, Clone, Copy)]
pub struct Limits {
    pub max_connections: usize,
    pub header_timeout: Duration,
    pub write_stall: Duration,
}

impl Default for Limits {
    fn default() -> Limits {
        Limits {
            max_connections: 64,
            header_timeout: Duration::from_secs(10),
            write_stall: Duration::from_secs(60),
        }
    }
}

/// A listening socket: TCP or unix.
pub trait Incoming: Send + 'static {
    type Io: AsyncRead + AsyncWrite + Unpin + Send + 'static;
    fn accept_io(&self) -> impl Future<Output = io::Result<Self::Io>> + Send;
}

impl Incoming for tokio::net::TcpListener {
    type Io = tokio::net::TcpStream;
    async fn accept_io(&self) -> io::Result<Self::Io> {
        let (stream, _) = self.accept().await?;
        let _ = stream.set_nodelay(true);
        Ok(stream)
    }
}

impl Incoming for tokio::net::UnixListener {
    type Io = tokio::net::UnixStream;
    async fn accept_io(&self) -> io::Result<Self::Io> {
        Ok(self.accept().await?.0)
    }
}

/// Serves `app` on `listener` until `stop` fires; connections still open then are asked
/// to finish their current response (a few seconds at most) and closed.
pub async fn serve<L: Incoming>(
    listener: L,
    app: Router,
    limits: Limits,
    stop: CancellationToken,
    name: &'static str,
) {
    let slots = Arc::new(tokio::sync::Semaphore::new(limits.max_connections));
    let mut backoff = Duration::from_millis(10);
    loop {
        let slot = tokio::select! {
            slot = Arc::clone(&slots).acquire_owned() => slot.expect("the semaphore is never closed"),
            _ = stop.cancelled() => return,
        };
        let io = tokio::select! {
            accepted = listener.accept_io() => match accepted {
                Ok(io) => io,
                Err(e) => {
                    tracing::warn!(listener = name, error = %e, retry_in_ms = backoff.as_millis() as u64, "http: cannot accept a connection");
                    tokio::select! {
                        _ = tokio::time::sleep(backoff) => {}
                        _ = stop.cancelled() => return,
                    }
                    backoff = (backoff * 2).min(Duration::from_secs(1));
                    continue;
                }
            },
            _ = stop.cancelled() => return,
        };
        backoff = Duration::from_millis(10);
        let service = TowerToHyperService::new(app.clone());
        let stop = stop.clone();
        tokio::spawn(async move {
            let _slot = slot;
            let io = TokioIo::new(StallGuard::new(io, limits.write_stall));
            let mut builder = hyper::server::conn::http1::Builder::new();
            builder
                .timer(TokioTimer::new())
                .header_read_timeout(limits.header_timeout)
                .max_buf_size(MAX_HEAD_BYTES);
            let connection = builder.serve_connection(io, service);
            tokio::pin!(connection);
            let result = tokio::select! {
                result = connection.as_mut() => result,
                _ = stop.cancelled() => {
                    connection.as_mut().graceful_shutdown();
                    match tokio::time::timeout(Duration::from_secs(5), connection).await {
                        Ok(result) => result,
                        Err(_) => return,
                    }
                }
            };
            if let Err(e) = result {
                tracing::debug!(listener = name, error = %e, "http: connection ended");
            }
        });
    }
}

/// A connection whose writes may stall at most `limit`: a client that stops reading
/// (an event stream left open in a frozen tab, or on purpose) cannot hold a connection
/// slot for ever.
struct StallGuard<T> {
    io: T,
    limit: Duration,
    stalled: Option<Pin<Box<tokio::time::Sleep>>>,
}

impl<T> StallGuard<T> {
    fn new(io: T, limit: Duration) -> StallGuard<T> {
        StallGuard {
            io,
            limit,
            stalled: None,
        }
    }

    /// Passes a write's outcome on; a write still pending after `limit` fails.
    fn watch<R>(
        &mut self,
        cx: &mut Context<'_>,
        polled: Poll<io::Result<R>>,
    ) -> Poll<io::Result<R>> {
        match polled {
            Poll::Ready(r) => {
                self.stalled = None;
                Poll::Ready(r)
            }
            Poll::Pending => {
                let limit = self.limit;
                let timer = self
                    .stalled
                    .get_or_insert_with(|| Box::pin(tokio::time::sleep(limit)));
                match timer.as_mut().poll(cx) {
                    Poll::Ready(()) => Poll::Ready(Err(io::Error::new(
                        io::ErrorKind::TimedOut,
                        format!("the client read nothing for {} s", limit.as_secs()),
                    ))),
                    Poll::Pending => Poll::Pending,
                }
            }
        }
    }
}

impl<T: AsyncRead + Unpin> AsyncRead for StallGuard<T> {
    fn poll_read(
        mut self: Pin<&mut Self>,
        cx: &mut Context<'_>,
        buf: &mut ReadBuf<'_>,
    ) -> Poll<io::Result<()>> {
        Pin::new(&mut self.io).poll_read(cx, buf)
    }
}

impl<T: AsyncWrite + Unpin> AsyncWrite for StallGuard<T> {
    fn poll_write(
        mut self: Pin<&mut Self>,
        cx: &mut Context<'_>,
        buf: &[u8],
    ) -> Poll<io::Result<usize>> {
        let polled = Pin::new(&mut self.io).poll_write(cx, buf);
        self.watch(cx, polled)
    }

    fn poll_write_vectored(
        mut self: Pin<&mut Self>,
        cx: &mut Context<'_>,
        bufs: &[io::IoSlice<'_>],
    ) -> Poll<io::Result<usize>> {
        let polled = Pin::new(&mut self.io).poll_write_vectored(cx, bufs);
        self.watch(cx, polled)
    }

    fn is_write_vectored(&self) -> bool {
        self.io.is_write_vectored()
    }

    fn poll_flush(mut self: Pin<&mut Self>, cx: &mut Context<'_>) -> Poll<io::Result<()>> {
        let polled = Pin::new(&mut self.io).poll_flush(cx);
        self.watch(cx, polled)
    }

    fn poll_shutdown(mut self: Pin<&mut Self>, cx: &mut Context<'_>) -> Poll<io::Result<()>> {
        let polled = Pin::new(&mut self.io).poll_shutdown(cx);
        self.watch(cx, polled)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use tokio::io::{AsyncReadExt, AsyncWriteExt};

    async fn get(socket: &std::path::Path) -> String {
        let mut stream = tokio::net::UnixStream::connect(socket).await.unwrap();
        stream
            .write_all(b"GET / HTTP/1.1\r\nHost: x\r\nConnection: close\r\n\r\n")
            .await
            .unwrap();
        let mut answer = String::new();
        stream.read_to_string(&mut answer).await.unwrap();
        answer
    }

    /// Serves `body` at `/` on a new socket in `dir` until the test ends.
    fn start(
        dir: &std::path::Path,
        name: &str,
        body: String,
        limits: Limits,
    ) -> std::path::PathBuf {
        let socket = dir.join(name);
        let listener = tokio::net::UnixListener::bind(&socket).unwrap();
        let app = Router::new().route("/", axum::routing::get(move || async move { body }));
        tokio::spawn(serve(
            listener,
            app,
            limits,
            CancellationToken::new(),
            "test",
        ));
        socket
    }

    /// With every slot taken by an idle connection, a new request waits; it is answered
    /// once a slot frees. An idle connection is closed after the header timeout.
    #[tokio::test]
    async fn connections_are_limited_and_idle_ones_closed() {
        let dir = tempfile::tempdir().unwrap();
        let limits = Limits {
            max_connections: 2,
            header_timeout: Duration::from_secs(3600),
            write_stall: Duration::from_secs(60),
        };
        let socket = start(dir.path(), "s.sock", "hello".into(), limits);

        let idle_a = tokio::net::UnixStream::connect(&socket).await.unwrap();
        let _idle_b = tokio::net::UnixStream::connect(&socket).await.unwrap();
        let waiting = tokio::spawn({
            let socket = socket.clone();
            async move { get(&socket).await }
        });
        // Not answered while both slots are held (a slow machine only makes this wait
        // longer, never shorter).
        tokio::time::sleep(Duration::from_millis(500)).await;
        assert!(
            !waiting.is_finished(),
            "answered beyond the connection limit"
        );
        drop(idle_a);
        let answer = tokio::time::timeout(Duration::from_secs(60), waiting)
            .await
            .expect("answered once a slot was free")
            .unwrap();
        assert!(answer.ends_with("hello"), "{answer}");

        // The header timeout closes an idle connection.
        let limits = Limits {
            header_timeout: Duration::from_millis(200),
            ..Limits::default()
        };
        let socket = start(dir.path(), "t.sock", "hello".into(), limits);
        let mut idle = tokio::net::UnixStream::connect(&socket).await.unwrap();
        let mut buf = [0u8; 64];
        let read = tokio::time::timeout(Duration::from_secs(60), idle.read(&mut buf))
            .await
            .expect("closed by the server");
        assert!(matches!(read, Ok(0) | Err(_)), "{read:?}");
    }

    /// A client that never reads its answer loses the connection after the stall limit.
    #[tokio::test]
    async fn a_client_that_stops_reading_is_dropped() {
        let dir = tempfile::tempdir().unwrap();
        let limits = Limits {
            max_connections: 1,
            write_stall: Duration::from_millis(300),
            ..Limits::default()
        };
        let socket = start(dir.path(), "s.sock", "x".repeat(16 * 1024 * 1024), limits);
        let mut stuck = tokio::net::UnixStream::connect(&socket).await.unwrap();
        stuck
            .write_all(b"GET / HTTP/1.1\r\nHost: x\r\n\r\n")
            .await
            .unwrap();
        // The only slot is freed by the stall limit, so this one is answered.
        let answer = tokio::time::timeout(Duration::from_secs(60), get(&socket))
            .await
            .expect("the stalled connection was dropped");
        assert!(answer.starts_with("HTTP/1.1 200"), "{}", &answer[..40]);
        drop(stuck);
    }
}
