//! The serial link to a printer, for async code: a `serialport` port (real USB serial or a
//! simulator's pty) read by a blocking thread that forwards bytes over a channel, and
//! written by a second thread so a slow printer never blocks the async runtime.
//!
//! Opening must not reset the printer: HUPCL is cleared so closing the port leaves DTR
//! alone, and the baud rate is best-effort (a pty ignores it). End of file, EIO or the
//! device vanishing all surface as [`LinkEvent::Closed`].

use nix::sys::termios::{self, ControlFlags, SetArg};
use std::io::{Read, Write};
use std::os::fd::{AsRawFd, BorrowedFd};
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Arc;
use std::thread::JoinHandle;
use std::time::Duration;
use tokio::sync::mpsc;

#[derive(Debug, thiserror::Error)]
pub enum TransportError {
    #[error(
        "cannot open printer port {port}: {message}; check the path, that the printer is \
         plugged in, and that you may use the device (e.g. the dialout group)"
    )]
    Open { port: PathBuf, message: String },
}

/// What the reader thread reports.
#[derive(Debug)]
pub enum LinkEvent {
    Data(Vec<u8>),
    /// The port is gone (EOF, EIO, unplugged); carries the reason.
    Closed(String),
}

/// An open serial link. Dropping it stops both threads.
pub struct Transport {
    port: PathBuf,
    incoming: mpsc::UnboundedReceiver<LinkEvent>,
    outgoing: Option<std::sync::mpsc::Sender<Vec<u8>>>,
    stop: Arc<AtomicBool>,
    reader: Option<JoinHandle<()>>,
    writer: Option<JoinHandle<()>>,
}

const READ_POLL: Duration = Duration::from_millis(100);

impl Transport {
    pub fn open(port: &Path, baud: u32) -> Result<Transport, TransportError> {
        let open_err = |message: String| TransportError::Open {
            port: port.to_path_buf(),
            message,
        };
        let path = port.to_string_lossy().into_owned();
        let native = serialport::new(&path, baud)
            .timeout(READ_POLL)
            .dtr_on_open(true)
            .open_native()
            .or_else(|_| {
                // Some pty drivers refuse custom baud rates; the rate means nothing there.
                serialport::new(&path, 0).timeout(READ_POLL).open_native()
            })
            .map_err(|e| open_err(e.to_string()))?;
        clear_hupcl(&native);
        let mut reader_port = native
            .try_clone_native()
            .map_err(|e| open_err(e.to_string()))?;
        let mut writer_port = native;

        let stop = Arc::new(AtomicBool::new(false));
        let (in_tx, in_rx) = mpsc::unbounded_channel();
        let (out_tx, out_rx) = std::sync::mpsc::channel::<Vec<u8>>();

        let reader_stop = stop.clone();
        let reader_tx = in_tx.clone();
        let reader = std::thread::Builder::new()
            .name("crispen-serial-rx".into())
            .spawn(move || {
                let mut buf = [0u8; 4096];
                while !reader_stop.load(Ordering::Relaxed) {
                    match reader_port.read(&mut buf) {
                        Ok(0) => {
                            let _ = reader_tx.send(LinkEvent::Closed("end of file".into()));
                            return;
                        }
                        Ok(n) => {
                            if reader_tx.send(LinkEvent::Data(buf[..n].to_vec())).is_err() {
                                return;
                            }
                        }
                        Err(e) if e.kind() == std::io::ErrorKind::TimedOut => {}
                        Err(e) if e.kind() == std::io::ErrorKind::Interrupted => {}
                        Err(e) => {
                            let _ = reader_tx.send(LinkEvent::Closed(e.to_string()));
                            return;
                        }
                    }
                }
            })
            .map_err(|e| open_err(e.to_string()))?;

        let writer = std::thread::Builder::new()
            .name("crispen-serial-tx".into())
            .spawn(move || {
                while let Ok(bytes) = out_rx.recv() {
                    if let Err(e) = writer_port
                        .write_all(&bytes)
                        .and_then(|_| writer_port.flush())
                    {
                        let _ = in_tx.send(LinkEvent::Closed(format!("write failed: {e}")));
                        return;
                    }
                }
            })
            .map_err(|e| open_err(e.to_string()))?;

        Ok(Transport {
            port: port.to_path_buf(),
            incoming: in_rx,
            outgoing: Some(out_tx),
            stop,
            reader: Some(reader),
            writer: Some(writer),
        })
    }

    pub fn port(&self) -> &Path {
        &self.port
    }

    /// Queue bytes for the printer. Errors show up later as [`LinkEvent::Closed`].
    pub fn send(&self, bytes: Vec<u8>) {
        if let Some(tx) = &self.outgoing {
            let _ = tx.send(bytes);
        }
    }

    /// A chunk already received, without waiting.
    pub fn try_recv(&mut self) -> Option<LinkEvent> {
        self.incoming.try_recv().ok()
    }

    /// The next chunk from the printer, or `Closed`.
    pub async fn recv(&mut self) -> LinkEvent {
        self.incoming
            .recv()
            .await
            .unwrap_or_else(|| LinkEvent::Closed("reader stopped".into()))
    }
}

impl Drop for Transport {
    fn drop(&mut self) {
        self.stop.store(true, Ordering::Relaxed);
        self.outgoing.take();
        // The writer ends when its channel closes; it is not joined because a write to a
        // printer that stopped reading could block. The reader ends within one poll.
        self.writer.take();
        if let Some(r) = self.reader.take() {
            let _ = r.join();
        }
    }
}

/// Closing the port must not drop DTR (which resets most boards).
fn clear_hupcl(port: &serialport::TTYPort) {
    // SAFETY: the fd belongs to `port`, which outlives this borrow.
    let fd = unsafe { BorrowedFd::borrow_raw(port.as_raw_fd()) };
    if let Ok(mut attrs) = termios::tcgetattr(fd) {
        attrs.control_flags.remove(ControlFlags::HUPCL);
        let _ = termios::tcsetattr(fd, SetArg::TCSANOW, &attrs);
    }
}
