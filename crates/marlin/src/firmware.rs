//! Firmware profiles: the facts about a printer's firmware that both the host and the
//! simulator must agree on. Values come from Marlin's and Ultimaker2Marlin's defaults
//! (see docs/host-protocol.md and docs/firmware.md).

use serde::{Deserialize, Serialize};
use std::fmt;
use std::str::FromStr;

#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Firmware {
    /// Marlin 2.1 with the usual options: ADVANCED_OK, busy protocol, autoreport, M112/M108.
    Marlin2,
    /// Marlin 2.0.x as commonly built: no `ok` after `Resend:` (its
    /// `flush_and_request_resend` sends none) and no ADVANCED_OK; busy protocol, autoreport,
    /// M112/M108 as 2.1.
    Marlin20,
    /// Ultimaker2Marlin: 250000 baud, 128-byte RX buffer, 8 command slots, none of the
    /// optional protocol features, and `Resend:` is always followed by `ok`.
    Ultimaker2,
}

impl Firmware {
    pub const ALL: [Firmware; 3] = [Firmware::Marlin2, Firmware::Marlin20, Firmware::Ultimaker2];

    /// The Marlin 2 family (2.0 and 2.1).
    pub fn is_marlin2(self) -> bool {
        matches!(self, Firmware::Marlin2 | Firmware::Marlin20)
    }

    pub fn name(self) -> &'static str {
        match self {
            Firmware::Marlin2 => "marlin2",
            Firmware::Marlin20 => "marlin20",
            Firmware::Ultimaker2 => "ultimaker2",
        }
    }
    pub fn default_baud(self) -> u32 {
        match self {
            Firmware::Marlin2 | Firmware::Marlin20 => 115_200,
            Firmware::Ultimaker2 => 250_000,
        }
    }
    /// Bytes the printer's serial receive buffer holds (Marlin's RX_BUFFER_SIZE).
    pub fn rx_buffer_bytes(self) -> usize {
        128
    }
    /// Command slots (Marlin's BUFSIZE).
    pub fn command_slots(self) -> usize {
        match self {
            Firmware::Marlin2 | Firmware::Marlin20 => 4,
            Firmware::Ultimaker2 => 8,
        }
    }
    /// Longest command line the firmware accepts, newline excluded (MAX_CMD_SIZE).
    pub fn max_line_bytes(self) -> usize {
        96
    }
    /// `ok N<line> P<planner> B<buffer>` answers.
    pub fn advanced_ok(self) -> bool {
        matches!(self, Firmware::Marlin2)
    }
    /// `M155 S<s>` temperature autoreport (and `Cap:AUTOREPORT_TEMP:1`).
    pub fn autoreport_temp(self) -> bool {
        self.is_marlin2()
    }
    /// `echo:busy: processing` keep-alives (M113).
    pub fn busy_protocol(self) -> bool {
        self.is_marlin2()
    }
    /// M112 emergency stop and M108 break-out of heat waits (EMERGENCY_PARSER).
    pub fn emergency_parser(self) -> bool {
        self.is_marlin2()
    }
    /// The firmware reads its serial input during a heat wait and acts on an unnumbered
    /// `M108` as it reads it, even without an emergency parser: Marlin 2's heat waits call
    /// `idle()`, whose `manage_inactivity` reads lines into free command slots
    /// (temperature.cpp:4122, MarlinCore.cpp:412), and its queue clears `wait_for_heatup`
    /// on reading `M108` (queue.cpp:524-531). Ultimaker2Marlin's M109/M190 loops read
    /// nothing (Marlin_main.cpp:1419-1460, 1472-1490).
    pub fn reads_serial_while_heating(self) -> bool {
        self.is_marlin2()
    }
    /// M73 progress display.
    pub fn progress_m73(self) -> bool {
        self.is_marlin2()
    }
    /// Whether a `Resend:` request is followed by an `ok` for the rejected line. The host
    /// learns this at run time; this value only stands in until it knows.
    pub fn ok_after_resend(self) -> bool {
        !matches!(self, Firmware::Marlin20)
    }
    /// Ultimaker2Marlin's reader ends a line at `:` (outside comments), so a command with a
    /// colon never passes its checksum.
    pub fn colon_ends_line(self) -> bool {
        matches!(self, Firmware::Ultimaker2)
    }
    /// A line numbered like the last accepted one, or one less, is ignored without any
    /// answer (Marlin 2.1); older firmware asks for the expected line instead.
    pub fn ignores_duplicate_lines(self) -> bool {
        matches!(self, Firmware::Marlin2)
    }
    /// The checksum covers the line only up to its first `*` (Ultimaker2Marlin; Marlin 2
    /// takes the last), so a byte corrupted into `*` can cut a line that still passes.
    pub fn checksum_to_first_star(self) -> bool {
        matches!(self, Firmware::Ultimaker2)
    }
    /// Moves (G0–G3) are acknowledged when they enter the command queue, other commands
    /// when they finish, so `ok`s do not come in line order (Ultimaker2Marlin).
    pub fn acks_moves_on_entry(self) -> bool {
        matches!(self, Firmware::Ultimaker2)
    }
}

impl fmt::Display for Firmware {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(self.name())
    }
}

impl FromStr for Firmware {
    type Err = String;
    fn from_str(s: &str) -> Result<Self, Self::Err> {
        Firmware::ALL
            .into_iter()
            .find(|f| f.name() == s)
            .ok_or_else(|| {
                format!("unknown firmware `{s}` (expected marlin2, marlin20 or ultimaker2)")
            })
    }
}
