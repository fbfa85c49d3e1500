//! The simulated printer's state: the [`Printer`] and the parts it is made of (the command
//! at the head of the queue, the queued lines, the heaters). Kept apart from the main loop
//! in the root so that the root and the seams beside it (serial, motion, thermal, dialect,
//! faults) share it without depending on each other.

use super::super::config::{Faults, ReportStyle};
use crispen_marlin::firmware::Firmware;
use rand_chacha::ChaCha8Rng;
use std::collections::VecDeque;
use std::time::{Duration, Instant};

#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(crate) enum Status {
    Running,
    /// After M112 or a fatal error: reads and discards input, says nothing.
    Halted,
    /// The silence fault: alive but mute.
    Silent,
    /// The unplug fault: the pty must be closed.
    Unplugged,
    /// Held in reset by the bootloader after the host opened the port (DTR): input is
    /// lost until the firmware starts and says `start`.
    Booting(Instant),
}

#[derive(Debug, Clone, Copy, PartialEq)]
pub(super) enum Heater {
    Hotend,
    Bed,
}

#[derive(Debug, Clone, Copy)]
pub(super) struct Temperature {
    pub(super) current: f64,
    pub(super) target: f64,
}

/// What the command at the head of the queue waits for before it can finish.
#[derive(Debug, Clone)]
pub(super) enum Wait {
    /// A move waits for a free planner slot.
    PlannerSlot {
        seconds: f64,
    },
    /// M400, and the synchronisation before G28/G4.
    Drain {
        then: Option<Box<Wait>>,
    },
    Until(Instant),
    /// A `Until` that starts only when it is reached (after a drain).
    For(f64),
    Heat {
        heater: Heater,
        cooling_too: bool,
    },
    /// `M0`/`M1` (and `M600` with ADVANCED_PAUSE_FEATURE): until someone presses the knob,
    /// which no test does: a host that sends one waits for an `ok` that never comes.
    User,
}

pub(super) struct Active {
    pub(super) wait: Wait,
    /// Line number for ADVANCED_OK.
    pub(super) n: Option<u64>,
    /// Its `ok` was sent when it entered the queue.
    pub(super) answered: bool,
    /// Sends `echo:busy: processing` while it waits (long commands, busy fault).
    pub(super) busy: bool,
    pub(super) next_heat_report: Option<Instant>,
}

pub(super) struct Queued {
    pub(super) n: Option<u64>,
    pub(super) cmd: String,
    /// Already acknowledged on entering the queue (Ultimaker2Marlin's moves).
    pub(super) acked: bool,
}

pub(crate) struct Printer {
    pub(super) fw: Firmware,
    pub(super) time_scale: f64,
    pub(super) faults: Faults,
    pub(super) rng: ChaCha8Rng,
    pub(super) status: Status,
    pub(super) rx: VecDeque<u8>,
    pub(super) assembling: Vec<u8>,
    pub(super) emergency: Vec<u8>,
    pub(super) slots: VecDeque<Queued>,
    pub(super) last_n: u64,
    pub(super) active: Option<Active>,
    pub(super) planner: VecDeque<Duration>,
    pub(super) planner_head_end: Option<Instant>,
    pub(super) position: [f64; 4],
    pub(super) relative: bool,
    pub(super) relative_e: bool,
    pub(super) feedrate: f64,
    /// The planner's settings: the firmware's stock values, changed by `M92`, `M201`,
    /// `M203`, `M204`, `M205` until a reset (no EEPROM), reported by `M503`.
    pub(super) settings: crispen_marlin::estimate::Limits,
    pub(super) hotend: Temperature,
    pub(super) bed: Temperature,
    pub(super) temps_at: Instant,
    pub(super) autoreport: Option<Duration>,
    pub(super) next_autoreport: Option<Instant>,
    pub(super) keepalive: f64,
    pub(super) next_keepalive: Option<Instant>,
    pub(super) heat_break: bool,
    pub(super) numbered_executed: usize,
    /// A `;` was seen on the line being assembled: Marlin 2 keeps nothing more of the line;
    /// Ultimaker2Marlin's `comment_mode`, which drops the line and the next one and stops
    /// its `:` rule.
    pub(super) in_comment: bool,
    /// Marlin 2 read a `\\`: the next character is kept as it is (queue.cpp:337-343).
    pub(super) escaped: bool,
    /// EMERGENCY_PARSER (see [`SimConfig::emergency_parser`](super::super::config::SimConfig::emergency_parser)).
    pub(super) emergency_parser: bool,
    /// The command being finished was acknowledged on entry: its `ok` is not sent again.
    pub(super) answered: bool,
    /// NO_TIMEOUTS: say `wait` this often while the command queue is empty.
    pub(super) wait_when_idle: Option<Duration>,
    pub(super) next_wait: Option<Instant>,
    /// `ok N<n> P<p> B<b>` (ADVANCED_OK).
    pub(super) advanced_ok: bool,
    /// ADVANCED_PAUSE_FEATURE (see [`SimConfig::advanced_pause`](super::super::config::SimConfig::advanced_pause)).
    pub(super) advanced_pause: bool,
    pub(super) report_style: ReportStyle,
    pub(super) out: Vec<u8>,
}
