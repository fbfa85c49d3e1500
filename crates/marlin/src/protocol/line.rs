//! The lines the host sends: what each is for, and what is known of one in flight.

use std::time::Instant;

#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(super) enum Kind {
    /// Job command by index.
    Job(usize),
    /// M110 / M115 at connect or job start.
    Setup,
    /// M105 polls and probes; M155, M73.
    Housekeeping,
    /// The `M105` that ends a job or a stop: only its own answer (`ok T:`, or an `ok N`
    /// past it) acknowledges it, never a plain `ok` that may belong to something else.
    Sync,
    /// The heaters/fan/motors-off lines.
    SafeStop,
}

#[derive(Debug, Clone)]
pub(super) struct Line {
    pub(super) number: u64,
    pub(super) kind: Kind,
    pub(super) command: String,
}

#[derive(Debug, Clone, Copy)]
pub(super) struct InFlight {
    pub(super) number: u64,
    pub(super) bytes: usize,
    /// Awaiting an `M105`'s answer (a probe may take its answer for lost: see `probe`).
    pub(super) is_m105: bool,
    /// An `M105`, whatever became of `is_m105`.
    pub(super) m105: bool,
    pub(super) sync: bool,
    /// A heat wait (M109/M190/M116): nothing is sent behind it until it is answered.
    pub(super) heat: bool,
    pub(super) sent: Instant,
}

/// An `M105` without number or checksum: the printer runs it whatever line it expects.
pub(super) const UNNUMBERED_PROBE: &[u8] = b"M105\n";

/// A line whose answer names no line of the current count: one sent before a stop began,
/// or one without a number (a stop's heaters off, its probe). Until answered it may still
/// sit in the printer's receive ring.
#[derive(Debug, Clone, Copy)]
pub(super) struct Owed {
    pub(super) bytes: usize,
    pub(super) what: OwedLine,
}

#[derive(Debug, Clone, Copy, PartialEq)]
pub(super) enum OwedLine {
    /// A numbered line of the count before: `ok` (with that number on ADVANCED_OK).
    Before,
    /// A line without a number: `ok` (without a number on ADVANCED_OK).
    Unnumbered,
    /// An `M105`, numbered or not: answered with its report, after every line before it.
    M105,
}

/// Commands that keep the printer busy for long without a word: silence is no sign of
/// trouble while one runs.
pub(super) const LONG_COMMANDS: [&str; 4] = ["G28", "G29", "M400", "G4"];
/// Heaters, fan and motors off.
pub(super) const SAFE_STOP: [&str; 4] = ["M104 S0", "M140 S0", "M107", "M84"];
/// Heaters off, sent at once without a number when a stop begins: no `N` and no `*` in them
/// (Ultimaker2Marlin takes a line with an `N` anywhere for a numbered one).
pub(super) const HEATERS_OFF: [&str; 2] = ["M104 S0", "M140 S0"];

/// A command's code (`G1`, `M105`): its first word.
pub(super) fn code_of(command: &str) -> &str {
    command.split_whitespace().next().unwrap_or("")
}

/// Whether `command`'s code is one of `codes`.
pub(super) fn is_code(command: &str, codes: &[&str]) -> bool {
    let code = code_of(command);
    codes.iter().any(|c| c.eq_ignore_ascii_case(code))
}
