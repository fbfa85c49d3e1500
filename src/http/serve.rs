//! The connection loop under both listeners (the control socket and TCP): HTTP/1.1 by
//! hyper, with the bounds a daemon facing any client needs. At most
//! [`Limits::max_connections`] connections at once; a connection that has sent no
//! complete request head (a slow or idle client) holds its place only until a new
//! connection needs it: at the limit, the one that has waited longest for a head is
//! closed. So a slowloris (many connections sending a byte now and then) cannot keep out
//! a client that sends its request at once, such as one with the key; the clients that
//! do hold a connection for long, event streams, are capped by the `events` module. A
//! request's head must arrive within [`Limits::header_timeout`], which also closes a
//! connection left idle between requests; a head larger than [`MAX_HEAD_BYTES`] is refused;
//! a response the client stops reading for [`Limits::write_stall`] ends its connection; and
//! when accepting fails (out of file descriptors) the loop waits a little longer each time
//! instead of spinning. Request bodies and handler times are bounded in the router.

use axum::Router;
use hyper_util::rt::{TokioIo, TokioTimer};
use std::collections::HashMap;
use std::future::Future;
use std::io;
use std::net::IpAddr;
use std::pin::Pin;
use std::sync::{Arc, Mutex};
use std::task::{Context, Poll};
use std::time::{Duration, Instant};
use tokio::io::{AsyncRead, AsyncWrite, ReadBuf};
use tokio_util::sync::CancellationToken;

/// Largest request head (request line, headers and the blank line that ends them): one
/// byte more is answered 431. hyper counts the head as its parser reads it, whole; its
/// read buffer bound (`max_buf_size`) is no limit on the head, since one read may take
/// a whole head larger than it (a 70,000-byte header was read and answered 200).
pub(crate) const MAX_HEAD_BYTES: usize = 64 * 1024;

/// The bounds of one listener.
#[derive(Debug, Clone, Copy)]
pub(crate) struct Limits {
    pub max_connections: usize,
    pub header_timeout: Duration,
    pub write_stall: Duration,
}

impl Default for Limits {
    fn default() -> Limits {
        Limits {
            // Well under the service's 1024 file descriptors; event streams are capped at
            // a quarter of it (`streams::MAX_STREAMS`).
            max_connections: 256,
            header_timeout: Duration::from_secs(10),
            write_stall: Duration::from_secs(60),
        }
    }
}

/// The address a request came from (TCP; none on the control socket), for the per-client
/// caps of the handlers.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(crate) struct ClientAddr(pub Option<IpAddr>);

/// A listening socket: TCP or unix.
pub(crate) trait Incoming: Send + 'static {
    type Io: AsyncRead + AsyncWrite + Unpin + Send + 'static;
    fn accept_io(&self) -> impl Future<Output = io::Result<(Self::Io, ClientAddr)>> + Send;
}

impl Incoming for tokio::net::TcpListener {
    type Io = tokio::net::TcpStream;
    async fn accept_io(&self) -> io::Result<(Self::Io, ClientAddr)> {
        let (stream, peer) = self.accept().await?;
        let _ = stream.set_nodelay(true);
        Ok((stream, ClientAddr(Some(peer.ip()))))
    }
}

impl Incoming for tokio::net::UnixListener {
    type Io = tokio::net::UnixStream;
    async fn accept_io(&self) -> io::Result<(Self::Io, ClientAddr)> {
        Ok((self.accept().await?.0, ClientAddr(None)))
    }
}

/// One open connection as the loop sees it.
struct Conn {
    /// Requests being answered (the answer's body not yet sent whole).
    busy: usize,
    /// Since when it has waited for a request head, when not busy.
    waiting_since: Instant,
    close: CancellationToken,
}

/// The open connections of one listener.
#[derive(Default)]
struct Conns {
    next: u64,
    open: HashMap<u64, Conn>,
}

impl Conns {
    /// Makes room for one more connection below `max`: closes the connection that has
    /// waited longest for a request head. False when every connection is busy.
    fn make_room(&mut self, max: usize) -> bool {
        if self.open.len() < max {
            return true;
        }
        let victim = self
            .open
            .iter()
            .filter(|(_, c)| c.busy == 0)
            .min_by_key(|(_, c)| c.waiting_since)
            .map(|(id, _)| *id);
        match victim.and_then(|id| self.open.remove(&id)) {
            Some(conn) => {
                conn.close.cancel();
                true
            }
            None => false,
        }
    }
}

/// The connections and a signal that one may make room now (it ended or became idle).
#[derive(Default)]
struct Table {
    conns: Mutex<Conns>,
    freed: tokio::sync::Notify,
}

/// Locks the table; a panic elsewhere while it was held leaves it usable.
fn lock(table: &Table) -> std::sync::MutexGuard<'_, Conns> {
    table.conns.lock().unwrap_or_else(|e| e.into_inner())
}

/// Marks its connection busy while it lives: from a request's head to the end of its
/// answer (it travels in the answer's body).
struct Busy {
    conns: Arc<Table>,
    id: u64,
}

impl Busy {
    fn new(conns: &Arc<Table>, id: u64) -> Busy {
        if let Some(c) = lock(conns).open.get_mut(&id) {
            c.busy += 1;
        }
        Busy {
            conns: Arc::clone(conns),
            id,
        }
    }
}

impl Drop for Busy {
    fn drop(&mut self) {
        if let Some(c) = lock(&self.conns).open.get_mut(&self.id) {
            c.busy = c.busy.saturating_sub(1);
            if c.busy == 0 {
                c.waiting_since = Instant::now();
                self.conns.freed.notify_one();
            }
        }
    }
}

/// An answer's body carrying its connection's [`Busy`] mark.
struct MarkedBody {
    inner: axum::body::Body,
    _busy: Busy,
}

impl http_body::Body for MarkedBody {
    type Data = axum::body::Bytes;
    type Error = axum::Error;

    fn poll_frame(
        mut self: Pin<&mut Self>,
        cx: &mut Context<'_>,
    ) -> Poll<Option<Result<http_body::Frame<Self::Data>, Self::Error>>> {
        Pin::new(&mut self.inner).poll_frame(cx)
    }

    fn is_end_stream(&self) -> bool {
        self.inner.is_end_stream()
    }

    fn size_hint(&self) -> http_body::SizeHint {
        self.inner.size_hint()
    }
}

/// Serves `app` on `listener` until `stop` fires; connections still open then are asked
/// to finish their current response (a few seconds at most) and closed.
pub(crate) async fn serve<L: Incoming>(
    listener: L,
    app: Router,
    limits: Limits,
    stop: CancellationToken,
    name: &'static str,
) {
    let conns = Arc::new(Table::default());
    let mut backoff = Duration::from_millis(10);
    loop {
        let (io, client) = tokio::select! {
            accepted = listener.accept_io() => match accepted {
                Ok(accepted) => accepted,
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
        let close = CancellationToken::new();
        // Every connection busy with a request: the new one waits until one is done.
        loop {
            let freed = conns.freed.notified();
            if lock(&conns).make_room(limits.max_connections) {
                break;
            }
            tokio::select! {
                _ = freed => {}
                _ = stop.cancelled() => return,
            }
        }
        let id = {
            let mut table = lock(&conns);
            let id = table.next;
            table.next += 1;
            table.open.insert(
                id,
                Conn {
                    busy: 0,
                    waiting_since: Instant::now(),
                    close: close.clone(),
                },
            );
            id
        };
        let service = {
            let (app, conns) = (app.clone(), Arc::clone(&conns));
            hyper::service::service_fn(
                move |mut request: axum::http::Request<hyper::body::Incoming>| {
                    let busy = Busy::new(&conns, id);
                    request.extensions_mut().insert(client);
                    let answer = tower_service::Service::call(&mut app.clone(), request);
                    async move {
                        let answer = answer.await?;
                        Ok::<_, std::convert::Infallible>(
                            answer.map(|inner| MarkedBody { inner, _busy: busy }),
                        )
                    }
                },
            )
        };
        let (stop, conns) = (stop.clone(), Arc::clone(&conns));
        tokio::spawn(async move {
            let io = TokioIo::new(StallGuard::new(io, limits.write_stall));
            let mut builder = hyper::server::conn::http1::Builder::new();
            builder
                .timer(TokioTimer::new())
                .header_read_timeout(limits.header_timeout)
                .max_header_size(MAX_HEAD_BYTES)
                .max_buf_size(MAX_HEAD_BYTES);
            let connection = builder.serve_connection(io, service);
            tokio::pin!(connection);
            let result = tokio::select! {
                result = connection.as_mut() => Some(result),
                // Closed to make room: it had sent no request.
                _ = close.cancelled() => None,
                _ = stop.cancelled() => {
                    connection.as_mut().graceful_shutdown();
                    tokio::time::timeout(Duration::from_secs(5), connection).await.ok()
                }
            };
            lock(&conns).open.remove(&id);
            conns.freed.notify_one();
            if let Some(Err(e)) = result {
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

    /// With every place taken by a connection that sent no request, a new request is
    /// answered all the same: the one that waited longest for a head is closed to make
    /// room. An idle connection is closed after the header timeout.
    #[tokio::test]
    async fn idle_connections_make_room_and_are_closed() {
        let dir = tempfile::tempdir().unwrap();
        let limits = Limits {
            max_connections: 2,
            header_timeout: Duration::from_secs(3600),
            write_stall: Duration::from_secs(60),
        };
        let socket = start(dir.path(), "s.sock", "hello".into(), limits);

        let mut oldest = tokio::net::UnixStream::connect(&socket).await.unwrap();
        oldest.write_all(b"GET / HT").await.unwrap();
        // Accepted before the next one (the loop takes them in order).
        tokio::time::sleep(Duration::from_millis(100)).await;
        let _idle = tokio::net::UnixStream::connect(&socket).await.unwrap();
        let answer = tokio::time::timeout(Duration::from_secs(60), get(&socket))
            .await
            .expect("answered at the connection limit");
        assert!(answer.ends_with("hello"), "{answer}");
        let mut buf = [0u8; 64];
        let read = tokio::time::timeout(Duration::from_secs(60), oldest.read(&mut buf))
            .await
            .expect("the oldest waiting connection was closed");
        assert!(matches!(read, Ok(0) | Err(_)), "{read:?}");

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

    /// A request head of exactly `size` bytes (request line, headers, blank line).
    fn head_of(size: usize) -> Vec<u8> {
        let start = "GET / HTTP/1.1\r\nHost: x\r\nConnection: close\r\nX-Pad: ";
        let pad = size - start.len() - "\r\n\r\n".len();
        format!("{start}{}\r\n\r\n", "p".repeat(pad)).into_bytes()
    }

    /// Sends `head` in pieces of `piece` bytes and reads the answer's status line.
    async fn status_of(socket: &std::path::Path, head: &[u8], piece: usize) -> String {
        let mut stream = tokio::net::UnixStream::connect(socket).await.unwrap();
        for part in head.chunks(piece) {
            // The server may answer and close before the whole head is sent.
            if stream.write_all(part).await.is_err() {
                break;
            }
        }
        let mut answer = Vec::new();
        let _ = stream.read_to_end(&mut answer).await;
        let answer = String::from_utf8_lossy(&answer);
        answer.lines().next().unwrap_or("").to_string()
    }

    /// The head limit is the documented 64 KiB, counted as hyper's parser counts a head
    /// (request line to blank line), at the byte: one byte more is 431, however the head
    /// arrives (at once, which hyper's read buffer bound let through up to about 112 KiB,
    /// or in pieces).
    #[tokio::test]
    async fn the_head_limit_is_64_kib_at_the_byte() {
        let dir = tempfile::tempdir().unwrap();
        let socket = start(dir.path(), "s.sock", "hello".into(), Limits::default());
        for piece in [usize::MAX, 65_536, 4096, 1000] {
            for (size, status) in [
                (1024, "HTTP/1.1 200 OK"),
                (MAX_HEAD_BYTES - 1, "HTTP/1.1 200 OK"),
                (MAX_HEAD_BYTES, "HTTP/1.1 200 OK"),
                (
                    MAX_HEAD_BYTES + 1,
                    "HTTP/1.1 431 Request Header Fields Too Large",
                ),
                (70_000, "HTTP/1.1 431 Request Header Fields Too Large"),
                (112 * 1024, "HTTP/1.1 431 Request Header Fields Too Large"),
                (1 << 20, "HTTP/1.1 431 Request Header Fields Too Large"),
            ] {
                let got = status_of(&socket, &head_of(size), piece).await;
                assert_eq!(
                    got, status,
                    "a head of {size} bytes sent in pieces of {piece}"
                );
            }
        }
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
