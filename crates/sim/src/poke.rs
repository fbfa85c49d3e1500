//! Making a running simulated printer act now, as a person at the printer would: the
//! [`Poke`]s, and the two ends that carry them to the printer's thread.

use std::os::fd::OwnedFd;
use std::sync::Arc;

/// Something to make a running simulated printer do now, as a person at the printer would
/// (`SimHandle::poke`, and `crispen sim --stdin`).
#[derive(Debug, Clone, PartialEq)]
pub enum Poke {
    /// Press reset or cycle the power: `start`, line numbers and settings forgotten.
    Reset,
    /// Use the printer's own menu: `//action:NAME` (cancel, pause, resume).
    Action(String),
    /// Report a firmware error that is not a halt: `Error:TEXT`.
    Error(String),
    /// Receive this line as if it came over the cable between the host's lines (a relay
    /// or a second host writing to the port): `N0 M117 M110 N999*<checksum>` renumbers
    /// Marlin 2 as a message with `M110` in it does.
    Receive(String),
}

impl std::str::FromStr for Poke {
    type Err = String;
    /// `reset`, `action NAME`, `error TEXT`, `line TEXT`.
    fn from_str(text: &str) -> Result<Poke, String> {
        let text = text.trim();
        let (word, rest) = text.split_once(' ').unwrap_or((text, ""));
        let rest = rest.trim();
        match word {
            "reset" if rest.is_empty() => Ok(Poke::Reset),
            "action"
                if !rest.is_empty()
                    && rest.bytes().all(|b| b.is_ascii_alphanumeric() || b == b'_') =>
            {
                Ok(Poke::Action(rest.to_string()))
            }
            "error" if !rest.is_empty() && !rest.contains(['\n', '\r']) => {
                Ok(Poke::Error(rest.to_string()))
            }
            "line" if !rest.is_empty() && !rest.contains(['\n', '\r']) => {
                Ok(Poke::Receive(rest.to_string()))
            }
            _ => Err(format!(
                "`{text}`: expected `reset`, `action NAME` (cancel, pause, resume), `error TEXT` \
                 or `line TEXT` (received as if from the cable)"
            )),
        }
    }
}

/// Sends [`Poke`]s to a running simulated printer; cheap to clone, usable from any thread.
#[derive(Clone)]
pub struct Poker {
    pub(super) pokes: std::sync::mpsc::Sender<Poke>,
    /// Written to wake the printer thread. (Closing the handle's other pipe is shutdown.)
    pub(super) doorbell: Arc<OwnedFd>,
}

impl Poker {
    /// Make the printer act now. False if it no longer runs.
    pub fn poke(&self, poke: Poke) -> bool {
        self.pokes.send(poke).is_ok() && nix::unistd::write(&*self.doorbell, b"!").is_ok()
    }
}

/// The receiving end of a [`Poker`].
pub(super) struct Pokes {
    pub(super) doorbell: OwnedFd,
    pub(super) pokes: std::sync::mpsc::Receiver<Poke>,
}
