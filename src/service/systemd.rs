//! The daemon's messages to systemd (`sd_notify`): readiness, status, watchdog pings and
//! requests for more time at a stop. They are sent without blocking: a datagram socket
//! whose reader has stopped reading (its queue holds 10 messages by default) would
//! otherwise stop the runtime thread that sends, and with it the stop it was timing.
//! A message the queue has no room for is dropped; the next status or ping replaces it.

use sd_notify::NotifyState;
use std::io;
use std::os::unix::net::UnixDatagram;

/// The socket systemd gave in `NOTIFY_SOCKET`, or nothing outside systemd.
pub(crate) struct Systemd {
    socket: Option<UnixDatagram>,
}

impl Systemd {
    /// Connects to `NOTIFY_SOCKET` where it is set; a socket that cannot be reached is
    /// logged once and nothing is sent.
    pub(crate) fn from_env() -> Systemd {
        let Some(path) = std::env::var_os("NOTIFY_SOCKET") else {
            return Systemd { socket: None };
        };
        match connect(&path) {
            Ok(socket) => Systemd {
                socket: Some(socket),
            },
            Err(e) => {
                tracing::warn!(socket = ?path, error = %e, "systemd: cannot reach NOTIFY_SOCKET; readiness and status are not reported");
                Systemd { socket: None }
            }
        }
    }

    /// Sends `states` as one message, without waiting.
    pub(crate) fn notify(&self, states: &[NotifyState<'_>]) {
        let Some(socket) = &self.socket else {
            return;
        };
        let message: String = states.iter().map(|s| format!("{s}\n")).collect();
        match socket.send(message.as_bytes()) {
            Ok(_) => {}
            Err(e) if e.kind() == io::ErrorKind::WouldBlock => {
                tracing::debug!("systemd: its queue is full; a notification dropped");
            }
            Err(e) => tracing::debug!(error = %e, "systemd: a notification not sent"),
        }
    }
}

/// A path socket, or an abstract one (`@name`), as `sd_notify(3)` allows.
fn connect(path: &std::ffi::OsStr) -> io::Result<UnixDatagram> {
    use std::os::unix::ffi::OsStrExt;
    let socket = UnixDatagram::unbound()?;
    match path.as_bytes().strip_prefix(b"@") {
        Some(name) => {
            use std::os::linux::net::SocketAddrExt;
            socket.connect_addr(&std::os::unix::net::SocketAddr::from_abstract_name(name)?)?;
        }
        None => socket.connect(path)?,
    }
    socket.set_nonblocking(true)?;
    Ok(socket)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A reader that never reads: the sender goes on past its full queue (before, the
    /// eleventh message blocked the daemon's stop for good), and what it read first
    /// arrived whole.
    #[test]
    fn a_reader_that_does_not_read_never_blocks_the_sender() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("notify");
        let reader = UnixDatagram::bind(&path).unwrap();
        let systemd = Systemd {
            socket: Some(connect(path.as_os_str()).unwrap()),
        };
        systemd.notify(&[NotifyState::Ready, NotifyState::Status("one")]);
        for _ in 0..100 {
            systemd.notify(&[NotifyState::ExtendTimeoutUsec(20_000_000)]);
        }
        let mut buf = [0u8; 256];
        let n = reader.recv(&mut buf).unwrap();
        assert_eq!(&buf[..n], b"READY=1\nSTATUS=one\n");
    }

    /// An abstract socket (`@name`) is reached by its name.
    #[test]
    fn an_abstract_socket_is_reached() {
        use std::os::linux::net::SocketAddrExt;
        let name = format!("crispen-test-{}", std::process::id());
        let addr = std::os::unix::net::SocketAddr::from_abstract_name(name.as_bytes()).unwrap();
        let reader = UnixDatagram::bind_addr(&addr).unwrap();
        let systemd = Systemd {
            socket: Some(connect(std::ffi::OsStr::new(&format!("@{name}"))).unwrap()),
        };
        systemd.notify(&[NotifyState::Watchdog]);
        let mut buf = [0u8; 64];
        let n = reader.recv(&mut buf).unwrap();
        assert_eq!(&buf[..n], b"WATCHDOG=1\n");
    }
}
