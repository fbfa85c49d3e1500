//! What the host tells its driver: the [`Event`]s, why a job failed ([`Failure`]), what it
//! cost ([`JobSummary`]), and what the printer said about itself ([`FirmwareInfo`]).

use super::reply::HostAction;
use super::temperature::{HeatWaitEstimate, Temperatures};
use serde::Serialize;
use std::collections::BTreeMap;
use std::time::Duration;

/// What the printer said about itself in answer to `M115`.
#[derive(Debug, Clone, PartialEq, Serialize, Default)]
pub struct FirmwareInfo {
    pub name: Option<String>,
    pub protocol_version: Option<String>,
    pub machine_type: Option<String>,
    pub extruder_count: Option<u32>,
    /// `Cap:NAME:0|1` lines (empty on firmware without them, e.g. Ultimaker2Marlin), at
    /// most [`MAX_CAPABILITIES`] names.
    pub capabilities: BTreeMap<String, bool>,
}

impl FirmwareInfo {
    pub(crate) fn capability(&self, name: &str) -> Option<bool> {
        self.capabilities.get(name).copied()
    }

    /// Take a `Cap:NAME:0|1` line.
    pub(super) fn note_capability(&mut self, name: String, value: bool) {
        // Marlin 2.1 lists about 40; a printer (or noise) writing endless new
        // names must not grow the map without bound.
        let known = self.capabilities.contains_key(&name);
        if known || self.capabilities.len() < MAX_CAPABILITIES {
            self.capabilities.insert(name, value);
        }
    }

    /// Take the `FIRMWARE_NAME:` line of the answer to `M115`.
    pub(super) fn read_m115_line(&mut self, line: &str) {
        const KEYS: [&str; 4] = [
            "FIRMWARE_NAME:",
            "PROTOCOL_VERSION:",
            "MACHINE_TYPE:",
            "EXTRUDER_COUNT:",
        ];
        for (i, key) in KEYS.iter().enumerate() {
            let Some(start) = line.find(key) else {
                continue;
            };
            let value_start = start + key.len();
            let rest = &line[value_start..];
            // A value runs until the next known key (names contain spaces).
            let end = KEYS
                .iter()
                .filter_map(|k| rest.find(&format!(" {k}")))
                .min()
                .unwrap_or(rest.len());
            let value = rest[..end].trim().to_string();
            match i {
                0 => self.name = Some(value),
                1 => self.protocol_version = Some(value),
                2 => self.machine_type = Some(value),
                _ => {
                    self.extruder_count =
                        value.split_whitespace().next().and_then(|v| v.parse().ok())
                }
            }
        }
    }
}

/// The most `Cap:` names kept from one printer.
pub const MAX_CAPABILITIES: usize = 128;

/// Why a connection or job ended without success. `last_acked` counts job commands the
/// printer acknowledged (commands 1..=last_acked are done).
#[derive(Debug, Clone, PartialEq)]
pub enum Failure {
    NoAnswer {
        waited: Duration,
    },
    PrinterReset {
        last_acked: usize,
    },
    Fatal {
        message: String,
        last_acked: usize,
    },
    ResendLimit {
        line: u64,
        times: u32,
        last_acked: usize,
    },
    LineGone {
        line: u64,
        oldest_kept: u64,
        last_acked: usize,
    },
    /// The printer no longer counts lines as the host does (a line it ran set its count, as
    /// `M110` inside a message does on Marlin 2): it refuses the host's lines or asks for
    /// ones it had acknowledged. Sending on would print nothing, or print twice.
    LostNumbering {
        what: Numbering,
        last_acked: usize,
    },
    /// The printer asked for a line it had already confirmed (an answered `M105`, an
    /// `ok N`): it lost its state (a reset without `start`, a power dip); replaying on top
    /// of a half-printed layer would be guessing.
    LostState {
        line: u64,
        confirmed: u64,
        last_acked: usize,
    },
    Silent {
        waited: Duration,
        last_acked: usize,
    },
    /// The printer kept talking but acknowledged nothing for this long.
    NoProgress {
        waited: Duration,
        last_acked: usize,
    },
    HeatTimeout {
        command: String,
        waited: Duration,
        temperatures: Temperatures,
        last_acked: usize,
    },
    Cancelled {
        last_acked: usize,
    },
    LineTooLong {
        command: String,
        len: usize,
        max: usize,
    },
    /// The firmware reported an error that is neither a line error (those come with a
    /// `Resend:`) nor a halt (a halted printer has switched its heaters off): a failed
    /// probing, a refused command. The printer no longer does what the file says.
    FirmwareError {
        message: String,
        last_acked: usize,
    },
}

/// How the host found that the printer's line count is no longer its own.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize)]
#[serde(tag = "kind", rename_all = "snake_case")]
pub enum Numbering {
    /// It asked for line `requested`, which the host never sent (it had sent lines up to
    /// `sent`), after an error naming `last_line` as the last it took: e.g. `Last Line:
    /// 999`, `Resend: 1000` when the host had sent 13.
    AheadOfHost {
        requested: u64,
        last_line: Option<u64>,
        sent: u64,
    },
    /// It asked again for line `requested` after acknowledging every line up to
    /// `acknowledged` in order: its count went back.
    WentBack { requested: u64, acknowledged: u64 },
    /// Its answers advanced nothing: `refusals` answers in a row asked for lines the host
    /// never sent (it had sent lines up to `sent`), each with its `ok`.
    NoAdvance { refusals: u32, sent: u64 },
}

impl std::fmt::Display for Numbering {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            Numbering::AheadOfHost {
                requested,
                last_line,
                sent,
            } => {
                write!(f, "it asked for line {requested}")?;
                if let Some(last) = last_line {
                    write!(f, " (its last line {last})")?;
                }
                write!(
                    f,
                    ", but the host had sent lines only up to {sent}: a line it ran set its \
                     count (as `M110` anywhere in a line does on Marlin)"
                )
            }
            Numbering::WentBack {
                requested,
                acknowledged,
            } => write!(
                f,
                "it asked for line {requested} again after acknowledging every line up to \
                 {acknowledged}: its count went back (a line it ran set it, or it restarted \
                 without saying so)"
            ),
            Numbering::NoAdvance { refusals, sent } => write!(
                f,
                "it refused {refusals} lines in a row, each time asking for a line the host \
                 never sent (it had sent lines up to {sent}), and acknowledged none"
            ),
        }
    }
}

#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct JobSummary {
    pub lines_total: usize,
    pub lines_sent: u64,
    pub resends: u64,
    pub probes: u64,
    /// Pieces of lines the printer answered on their own (the tail of a line cut by a
    /// receive-buffer flush): seen as `Unknown command` or as an `ok` without a line number.
    pub fragments: u64,
}

#[derive(Debug, Clone, PartialEq)]
pub enum Event {
    /// Handshake finished.
    Connected(FirmwareInfo),
    Progress {
        acked: usize,
        total: usize,
    },
    Temperatures(Temperatures),
    /// `busy:` keep-alive.
    Busy(String),
    /// The printer asked for `line` again; `replay` lines will be sent again.
    Resend {
        line: u64,
        replay: u64,
    },
    /// The printer was silent, or said `wait` with lines in flight; an `M105` probe went out.
    Probe,
    /// The printer answered a piece of a line on its own (see [`JobSummary::fragments`]).
    Fragment(String),
    /// `//action:cancel|pause|resume` from the printer's own menu; the host acts on it.
    HostAction(HostAction),
    /// Informational printer output (`echo:`, non-fatal `Error:`) worth logging.
    Message(String),
    Paused,
    Resumed,
    /// A failure stopped the printer: heaters, fan and motors off. `confirmed`: the printer
    /// acknowledged those lines (an answered `M105` after them).
    SafeStop {
        confirmed: bool,
    },
    /// During a stop, the printer's own answer to an `M105` sent after the stop's
    /// unnumbered heaters-off lines shows both targets at 0: whatever becomes of the
    /// stop's numbered lines (a noisy link may keep refusing them), the heaters are off,
    /// and nothing the host sends after can turn them on.
    HeatersOff,
    /// A stop was asked for while the printer waits for a heater, and its firmware reads
    /// nothing until the wait is over (Ultimaker2Marlin): the heaters go off only then.
    StopWaitsForHeat(HeatWaitEstimate),
    Done(JobSummary),
    Failed(Failure),
}

/// What a job has cost so far, for its [`JobSummary`].
#[derive(Debug, Clone, Copy, Default)]
pub(super) struct Stats {
    pub(super) lines_sent: u64,
    pub(super) resends: u64,
    pub(super) probes: u64,
    pub(super) fragments: u64,
}

impl Stats {
    pub(super) fn summary(&self, lines_total: usize) -> JobSummary {
        JobSummary {
            lines_total,
            lines_sent: self.lines_sent,
            resends: self.resends,
            probes: self.probes,
            fragments: self.fragments,
        }
    }
}
