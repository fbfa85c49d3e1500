//! The serial link to a printer, for async code: a `serialport` port (real USB serial or a
//! simulator's pty) switched to non-blocking mode and driven by tokio's reactor, so a
//! printer's answer wakes its task directly and a write never blocks the runtime. (Two
//! threads per port, one reading with a poll timeout and one writing, cost the daemon three
//! thread wake-ups per line; with 20 printers streaming that was most of its CPU.)
//!
//! Opening must not reset the printer: HUPCL is cleared so closing the port leaves DTR
//! alone, and the baud rate is best-effort (a pty ignores it). End of file, EIO or the
//! device vanishing all surface as [`LinkEvent::Closed`].

use nix::errno::Errno;
use nix::fcntl::{fcntl, FcntlArg, OFlag};
use nix::sys::termios::{self, ControlFlags, SetArg};
use std::os::fd::{AsFd, AsRawFd, BorrowedFd, RawFd};
use std::path::{Path, PathBuf};
use std::time::Duration;
use tokio::io::unix::AsyncFd;
use tokio::io::Interest;

#[derive(Debug, thiserror::Error)]
pub enum TransportError {
    #[error(
        "cannot open printer port {port}: {message}; check the path, that the printer is \
         plugged in, and that you may use the device (e.g. the dialout group)"
    )]
    Open { port: PathBuf, message: String },
    #[error(
        "cannot open printer port {port}: another program has it open (crispen waited \
         {waited_s:.1} s for it; hint: stop the other host using it, e.g. OctoPrint or a \
         serial terminal)"
    )]
    Busy { port: PathBuf, waited_s: f64 },
}

/// How long an open waits for a port another holder has locked. A process this one starts
/// (a slicer, ffmpeg) holds a copy of every descriptor between its fork and its exec, and
/// with it the port's lock, even though close-on-exec is set: a port closed and reopened in
/// that moment is briefly busy. Another program keeps it busy past this.
pub const BUSY_WAIT: Duration = Duration::from_secs(3);
/// Between two tries at a busy port.
const BUSY_RETRY: Duration = Duration::from_millis(25);

/// What the port delivered.
#[derive(Debug)]
pub enum LinkEvent {
    Data(Vec<u8>),
    /// The port is gone (EOF, EIO, unplugged); carries the reason.
    Closed(String),
}

/// An open serial link. Must be opened and used inside a tokio runtime with I/O enabled.
pub struct Transport {
    fd: AsyncFd<Port>,
    /// Bytes queued for the printer that the port has not taken yet (its output buffer is
    /// full when the printer stops reading).
    outgoing: Vec<u8>,
    /// A write failed: reported by the next `recv`.
    failed: Option<String>,
}

/// Bytes read at once; a printer's answers are short.
const READ_CHUNK: usize = 4096;

impl Transport {
    /// Opens the port, waiting up to [`BUSY_WAIT`] while another holder has it locked.
    pub async fn open(port: &Path, baud: u32) -> Result<Transport, TransportError> {
        let started = tokio::time::Instant::now();
        loop {
            match Transport::open_once(port, baud) {
                Err(Opened::Busy) if started.elapsed() < BUSY_WAIT => {
                    tokio::time::sleep(BUSY_RETRY).await;
                }
                Err(Opened::Busy) => {
                    return Err(TransportError::Busy {
                        port: port.to_path_buf(),
                        waited_s: started.elapsed().as_secs_f64(),
                    })
                }
                Err(Opened::Failed(e)) => return Err(e),
                Ok(transport) => return Ok(transport),
            }
        }
    }

    fn open_once(port: &Path, baud: u32) -> Result<Transport, Opened> {
        let open_err = |message: String| {
            Opened::Failed(TransportError::Open {
                port: port.to_path_buf(),
                message,
            })
        };
        let path = port.to_string_lossy().into_owned();
        let native = serialport::new(&path, baud)
            .dtr_on_open(true)
            .open_native()
            .or_else(|e| match e.kind() {
                serialport::ErrorKind::NoDevice => Err(e),
                // Some pty drivers refuse custom baud rates; the rate means nothing there.
                _ => serialport::new(&path, 0).open_native(),
            })
            .map_err(|e| match e.kind() {
                // serialport's kind for a port locked by another opener (its exclusive
                // flock, or TIOCEXCL's EBUSY).
                serialport::ErrorKind::NoDevice => Opened::Busy,
                _ => open_err(e.to_string()),
            })?;
        let native = Port(native);
        clear_hupcl(&native);
        // serialport opens blocking; its own read and write also poll with a timeout first.
        // The fd is read and written directly instead, without blocking.
        let flags = fcntl(&native, FcntlArg::F_GETFL).map_err(|e| open_err(e.to_string()))?;
        fcntl(
            &native,
            FcntlArg::F_SETFL(OFlag::from_bits_truncate(flags) | OFlag::O_NONBLOCK),
        )
        .map_err(|e| open_err(e.to_string()))?;
        // SAFETY: `Port` owns its fd, open until the port is dropped with the `AsyncFd`, and
        // always returns that same fd.
        let fd = unsafe {
            AsyncFd::register_with_interest(native, Interest::READABLE | Interest::WRITABLE)
        }
        .map_err(|e| open_err(e.to_string()))?;
        Ok(Transport {
            fd,
            outgoing: Vec::new(),
            failed: None,
        })
    }

    /// Queue bytes for the printer and write what the port takes now; the rest goes out
    /// from [`Transport::recv`]. Errors show up there as [`LinkEvent::Closed`].
    pub fn send(&mut self, bytes: Vec<u8>) {
        if self.failed.is_some() {
            return;
        }
        if self.outgoing.is_empty() {
            self.outgoing = bytes;
        } else {
            self.outgoing.extend_from_slice(&bytes);
        }
        write_queued(self.fd.get_ref(), &mut self.outgoing, &mut self.failed);
    }

    /// A chunk already received, without waiting.
    pub fn try_recv(&mut self) -> Option<LinkEvent> {
        if let Some(reason) = self.failed.take() {
            return Some(LinkEvent::Closed(reason));
        }
        read_once(self.fd.get_ref())
    }

    /// The next chunk from the printer, or `Closed`; writes queued bytes meanwhile.
    /// Cancel-safe: nothing is lost when another branch of a `select!` wins.
    pub async fn recv(&mut self) -> LinkEvent {
        loop {
            if let Some(reason) = self.failed.take() {
                return LinkEvent::Closed(reason);
            }
            let interest = if self.outgoing.is_empty() {
                Interest::READABLE
            } else {
                Interest::READABLE | Interest::WRITABLE
            };
            let mut guard = match self.fd.ready(interest).await {
                Ok(guard) => guard,
                Err(e) => return LinkEvent::Closed(e.to_string()),
            };
            let ready = guard.ready();
            if ready.is_writable() && !self.outgoing.is_empty() {
                // `guard` borrows only the fd field, so the queue can be written from here.
                if !write_queued(guard.get_inner(), &mut self.outgoing, &mut self.failed) {
                    guard.clear_ready_matching(tokio::io::Ready::WRITABLE);
                }
            }
            if ready.is_readable() || ready.is_read_closed() {
                match read_once(guard.get_inner()) {
                    Some(event) => return event,
                    None => guard.clear_ready_matching(tokio::io::Ready::READABLE),
                }
            }
        }
    }
}

/// Why one try at opening failed.
enum Opened {
    Busy,
    Failed(TransportError),
}

/// The open port: `serialport` configures it (and drops exclusive access on close); the
/// fd is what is read and written.
struct Port(serialport::TTYPort);

impl AsRawFd for Port {
    fn as_raw_fd(&self) -> RawFd {
        self.0.as_raw_fd()
    }
}

impl AsFd for Port {
    fn as_fd(&self) -> BorrowedFd<'_> {
        // SAFETY: the TTYPort owns the fd and keeps it open for as long as it lives.
        unsafe { BorrowedFd::borrow_raw(self.0.as_raw_fd()) }
    }
}

/// Write `queue` until the port would block; a failure empties it and is kept in `failed`.
/// Returns whether the queue is empty.
fn write_queued(port: &Port, queue: &mut Vec<u8>, failed: &mut Option<String>) -> bool {
    while !queue.is_empty() {
        match nix::unistd::write(port, queue) {
            Ok(n) => {
                queue.drain(..n);
            }
            Err(Errno::EINTR) => {}
            Err(Errno::EAGAIN) => return false,
            Err(e) => {
                *failed = Some(format!("write failed: {}", e.desc()));
                queue.clear();
            }
        }
    }
    true
}

/// One read without waiting: `None` when nothing is there.
fn read_once(port: &Port) -> Option<LinkEvent> {
    let mut buf = vec![0u8; READ_CHUNK];
    loop {
        return match nix::unistd::read(port, &mut buf) {
            Ok(0) => Some(LinkEvent::Closed("end of file".into())),
            Ok(n) => {
                buf.truncate(n);
                Some(LinkEvent::Data(buf))
            }
            Err(Errno::EINTR) => continue,
            Err(Errno::EAGAIN) => None,
            Err(e) => Some(LinkEvent::Closed(e.desc().to_string())),
        };
    }
}

/// Closing the port must not drop DTR (which resets most boards).
fn clear_hupcl(port: &Port) {
    let fd = port.as_fd();
    if let Ok(mut attrs) = termios::tcgetattr(fd) {
        attrs.control_flags.remove(ControlFlags::HUPCL);
        let _ = termios::tcsetattr(fd, SetArg::TCSANOW, &attrs);
    }
}
