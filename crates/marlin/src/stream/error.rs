//! Why a print failed, as the operator reads it: each protocol [`Failure`] with the port,
//! the last acknowledged line and what became of the safe stop.

use crate::protocol::{Failure, Numbering, Temp, Temperatures};
use crate::transport::TransportError;
use serde::Serialize;
use std::path::{Path, PathBuf};

/// What became of the safe stop (heaters, fan and motors off) that follows a failure while
/// the printer still answers, or a cancel. Part of the job's error, so whoever reads why a
/// job failed also reads whether the printer was left hot.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize)]
pub enum StopOutcome {
    /// The printer acknowledged the heaters-off lines (an answered `M105` after them).
    Confirmed,
    /// The host gave up before the printer confirmed them: it may still be hot.
    NotConfirmed,
    /// The host gave up on the stop's numbered lines (fan and motors), but the printer's
    /// own temperature report, after the heaters-off lines, showed both targets at 0.
    HeatersOff,
    /// No stop was needed or possible (a reset or halted printer has switched its heaters
    /// off; nothing was sent yet).
    None,
}

impl std::fmt::Display for StopOutcome {
    /// Written after the error's own text.
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            StopOutcome::Confirmed => f.write_str("; heaters, fan and motors confirmed off"),
            StopOutcome::NotConfirmed => {
                f.write_str("; heaters NOT confirmed off: check the printer now")
            }
            StopOutcome::HeatersOff => f.write_str(
                "; heaters confirmed off by the printer's report (fan and motors not confirmed)",
            ),
            StopOutcome::None => Ok(()),
        }
    }
}

#[derive(Debug, thiserror::Error)]
pub enum PrintError {
    #[error(transparent)]
    Open(#[from] TransportError),
    #[error(
        "no answer from the printer on {port} after {waited_s:.1} s; check the baud rate \
         (--baud) and the firmware profile (--firmware)"
    )]
    NoAnswer { port: PathBuf, waited_s: f64 },
    #[error(
        "interrupted: printer on {port} disconnected ({reason}), last acknowledged line \
         {last_acked}"
    )]
    Disconnected {
        port: PathBuf,
        reason: String,
        last_acked: usize,
    },
    #[error(
        "printer on {port} reset itself (it said `start`) in the middle of the job; the print \
         is lost, last acknowledged line {last_acked}"
    )]
    PrinterReset { port: PathBuf, last_acked: usize },
    #[error(
        "printer on {port} stopped with a fatal error: {message}; last acknowledged line \
         {last_acked} (the printer needs a reset or M999)"
    )]
    Fatal {
        port: PathBuf,
        message: String,
        last_acked: usize,
    },
    #[error(
        "printer on {port} asked for line {line} again {times} times; giving up (check the \
         cable and baud rate), last acknowledged line {last_acked}{stop}"
    )]
    ResendLimit {
        port: PathBuf,
        line: u64,
        times: u32,
        last_acked: usize,
        stop: StopOutcome,
    },
    #[error(
        "printer on {port} asked for line {line}, which is no longer kept (oldest kept: \
         {oldest_kept}); stopping rather than guessing, last acknowledged line \
         {last_acked}{stop}"
    )]
    LineGone {
        port: PathBuf,
        line: u64,
        oldest_kept: u64,
        last_acked: usize,
        stop: StopOutcome,
    },
    #[error(
        "printer on {port} asked for line {line} again although it had confirmed line \
         {confirmed}: its line count went back (a line it ran set it, or it was reset without \
         saying so, a power dip); stopped rather than replaying onto a half-printed part, \
         last acknowledged line {last_acked}{stop}"
    )]
    LostState {
        port: PathBuf,
        line: u64,
        confirmed: u64,
        last_acked: usize,
        stop: StopOutcome,
    },
    #[error(
        "printer on {port} no longer counts lines as the host does: {what}; the job was \
         stopped, the printer's count reset and the printer stopped, last acknowledged line \
         {last_acked}{stop}"
    )]
    LostNumbering {
        port: PathBuf,
        what: Numbering,
        last_acked: usize,
        stop: StopOutcome,
    },
    #[error(
        "printer on {port} kept talking but acknowledged no line for {waited_s:.0} s; \
         stopped, last acknowledged line {last_acked}{stop}"
    )]
    NoProgress {
        port: PathBuf,
        waited_s: f64,
        last_acked: usize,
        stop: StopOutcome,
    },
    #[error(
        "printer on {port} went silent for {waited_s:.1} s and did not answer M105 probes; \
         last acknowledged line {last_acked}"
    )]
    Silent {
        port: PathBuf,
        waited_s: f64,
        last_acked: usize,
    },
    #[error(
        "printer on {port}: `{command}` stopped coming closer to its temperature (waited \
         {waited_s:.0} s in all, now {temperatures}); last acknowledged line \
         {last_acked}{stop}"
    )]
    HeatTimeout {
        port: PathBuf,
        command: String,
        waited_s: f64,
        temperatures: String,
        last_acked: usize,
        stop: StopOutcome,
    },
    #[error("job on {port} cancelled, last acknowledged line {last_acked}{stop}")]
    Cancelled {
        port: PathBuf,
        last_acked: usize,
        stop: StopOutcome,
    },
    #[error(
        "line `{command}` is {len} bytes with its line number and checksum, more than the \
         printer's limit of {max}; nothing was sent for it"
    )]
    LineTooLong {
        command: String,
        len: usize,
        max: usize,
    },
    #[error(
        "printer on {port} reported `{message}`, which the job cannot go on after, last \
         acknowledged line {last_acked}{stop}"
    )]
    FirmwareError {
        port: PathBuf,
        message: String,
        last_acked: usize,
        stop: StopOutcome,
    },
    #[error("printer on {port} is busy with another job")]
    Busy { port: PathBuf },
    #[error(
        "{file}:{line}: the file asks for a pause (`{command}`), which needs an operator to \
         resume it; this way of printing has none (print it through the daemon, whose \
         printers pause and wait for `crispen resume`, or remove the pause); nothing was sent"
    )]
    PauseWithoutOperator {
        file: String,
        line: usize,
        command: String,
    },
}

impl PrintError {
    /// Job commands the printer acknowledged before the failure, where known.
    pub fn last_acked(&self) -> Option<usize> {
        match self {
            PrintError::Disconnected { last_acked, .. }
            | PrintError::PrinterReset { last_acked, .. }
            | PrintError::Fatal { last_acked, .. }
            | PrintError::ResendLimit { last_acked, .. }
            | PrintError::LineGone { last_acked, .. }
            | PrintError::Silent { last_acked, .. }
            | PrintError::LostState { last_acked, .. }
            | PrintError::LostNumbering { last_acked, .. }
            | PrintError::NoProgress { last_acked, .. }
            | PrintError::HeatTimeout { last_acked, .. }
            | PrintError::Cancelled { last_acked, .. }
            | PrintError::FirmwareError { last_acked, .. } => Some(*last_acked),
            _ => None,
        }
    }

    /// Counts of this error (acknowledged lines) made for a part of the job that began at
    /// job command `offset`: `job_lines` says whether the part was the job's own lines
    /// (their count is added) or host lines of a pause (the job's count stays at `offset`).
    pub(super) fn in_part(mut self, offset: usize, job_lines: bool) -> Self {
        match &mut self {
            PrintError::Disconnected { last_acked, .. }
            | PrintError::PrinterReset { last_acked, .. }
            | PrintError::Fatal { last_acked, .. }
            | PrintError::ResendLimit { last_acked, .. }
            | PrintError::LineGone { last_acked, .. }
            | PrintError::Silent { last_acked, .. }
            | PrintError::LostState { last_acked, .. }
            | PrintError::LostNumbering { last_acked, .. }
            | PrintError::NoProgress { last_acked, .. }
            | PrintError::HeatTimeout { last_acked, .. }
            | PrintError::Cancelled { last_acked, .. }
            | PrintError::FirmwareError { last_acked, .. } => {
                *last_acked = if job_lines {
                    *last_acked + offset
                } else {
                    offset
                };
            }
            _ => {}
        }
        self
    }

    /// Whether the safe stop after the failure was confirmed, where one was made.
    pub fn stop_outcome(&self) -> StopOutcome {
        match self {
            PrintError::ResendLimit { stop, .. }
            | PrintError::LineGone { stop, .. }
            | PrintError::LostState { stop, .. }
            | PrintError::LostNumbering { stop, .. }
            | PrintError::NoProgress { stop, .. }
            | PrintError::HeatTimeout { stop, .. }
            | PrintError::Cancelled { stop, .. }
            | PrintError::FirmwareError { stop, .. } => *stop,
            _ => StopOutcome::None,
        }
    }

    /// `stop`: what the protocol reported of its safe stop ([`Event::SafeStop`](crate::protocol::Event::SafeStop)) before the
    /// failure.
    pub(super) fn from_failure(port: &Path, failure: Failure, stop: StopOutcome) -> Self {
        let port = port.to_path_buf();
        match failure {
            Failure::NoAnswer { waited } => PrintError::NoAnswer {
                port,
                waited_s: waited.as_secs_f64(),
            },
            Failure::PrinterReset { last_acked } => PrintError::PrinterReset { port, last_acked },
            Failure::Fatal {
                message,
                last_acked,
            } => PrintError::Fatal {
                port,
                message,
                last_acked,
            },
            Failure::ResendLimit {
                line,
                times,
                last_acked,
            } => PrintError::ResendLimit {
                port,
                line,
                times,
                last_acked,
                stop,
            },
            Failure::LineGone {
                line,
                oldest_kept,
                last_acked,
            } => PrintError::LineGone {
                port,
                line,
                oldest_kept,
                last_acked,
                stop,
            },
            Failure::LostState {
                line,
                confirmed,
                last_acked,
            } => PrintError::LostState {
                port,
                line,
                confirmed,
                last_acked,
                stop,
            },
            Failure::LostNumbering { what, last_acked } => PrintError::LostNumbering {
                port,
                what,
                last_acked,
                stop,
            },
            Failure::NoProgress { waited, last_acked } => PrintError::NoProgress {
                port,
                waited_s: waited.as_secs_f64(),
                last_acked,
                stop,
            },
            Failure::Silent { waited, last_acked } => PrintError::Silent {
                port,
                waited_s: waited.as_secs_f64(),
                last_acked,
            },
            Failure::HeatTimeout {
                command,
                waited,
                temperatures,
                last_acked,
            } => PrintError::HeatTimeout {
                port,
                command,
                waited_s: waited.as_secs_f64(),
                temperatures: describe_temps(&temperatures),
                last_acked,
                stop,
            },
            Failure::Cancelled { last_acked } => PrintError::Cancelled {
                port,
                last_acked,
                stop,
            },
            Failure::LineTooLong { command, len, max } => {
                PrintError::LineTooLong { command, len, max }
            }
            Failure::FirmwareError {
                message,
                last_acked,
            } => PrintError::FirmwareError {
                port,
                message,
                last_acked,
                stop,
            },
        }
    }
}

pub(super) fn describe_temps(t: &Temperatures) -> String {
    let one = |name: &str, t: Option<Temp>| match t {
        Some(Temp {
            current,
            target: Some(target),
        }) => format!("{name} {current:.1}/{target:.0}°C"),
        Some(Temp { current, .. }) => format!("{name} {current:.1}°C"),
        None => format!("{name} unknown"),
    };
    format!("{}, {}", one("hotend", t.hotend), one("bed", t.bed))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn errors_name_the_port_and_the_last_acknowledged_line() {
        let err = PrintError::from_failure(
            Path::new("/dev/ttyUSB3"),
            Failure::PrinterReset { last_acked: 41 },
            StopOutcome::None,
        );
        let msg = err.to_string();
        assert!(msg.contains("/dev/ttyUSB3") && msg.contains("41"), "{msg}");
        assert_eq!(err.last_acked(), Some(41));
        // Whether the heaters were confirmed off is part of the error itself.
        let failure = Failure::ResendLimit {
            line: 7,
            times: 10,
            last_acked: 6,
        };
        let err = |stop| PrintError::from_failure(Path::new("/dev/ttyUSB3"), failure.clone(), stop);
        let confirmed = err(StopOutcome::Confirmed).to_string();
        assert!(
            confirmed.ends_with("; heaters, fan and motors confirmed off"),
            "{confirmed}"
        );
        let not = err(StopOutcome::NotConfirmed);
        assert!(
            not.to_string()
                .ends_with("heaters NOT confirmed off: check the printer now"),
            "{not}"
        );
        assert_eq!(not.stop_outcome(), StopOutcome::NotConfirmed);
    }
}
