//! Firmware profiles: the facts about a printer's firmware that both the host and the
//! simulator must agree on. Values come from Marlin's and Ultimaker2Marlin's defaults
//! (see docs/host-protocol.md and docs/firmware.md).

use serde::{Deserialize, Serialize};
use std::fmt;
use std::str::FromStr;

#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Firmware {
    /// Marlin 2.x with the usual options: ADVANCED_OK, busy protocol, autoreport, M112/M108.
    Marlin2,
    /// Ultimaker2Marlin: 250000 baud, 128-byte RX buffer, 8 command slots, none of the
    /// optional protocol features, and `Resend:` is always followed by `ok`.
    Ultimaker2,
}

impl Firmware {
    pub const ALL: [Firmware; 2] = [Firmware::Marlin2, Firmware::Ultimaker2];

    pub fn name(self) -> &'static str {
        match self {
            Firmware::Marlin2 => "marlin2",
            Firmware::Ultimaker2 => "ultimaker2",
        }
    }
    pub fn default_baud(self) -> u32 {
        match self {
            Firmware::Marlin2 => 115_200,
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
            Firmware::Marlin2 => 4,
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
        matches!(self, Firmware::Marlin2)
    }
    /// `echo:busy: processing` keep-alives (M113).
    pub fn busy_protocol(self) -> bool {
        matches!(self, Firmware::Marlin2)
    }
    /// `Cap:` lines in the M115 answer.
    pub fn reports_capabilities(self) -> bool {
        matches!(self, Firmware::Marlin2)
    }
    /// M112 emergency stop and M108 break-out of heat waits (EMERGENCY_PARSER).
    pub fn emergency_parser(self) -> bool {
        matches!(self, Firmware::Marlin2)
    }
    /// M73 progress display.
    pub fn progress_m73(self) -> bool {
        matches!(self, Firmware::Marlin2)
    }
    /// Whether a `Resend:` request is followed by an `ok` for the rejected line.
    pub fn ok_after_resend(self) -> bool {
        true
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
            .ok_or_else(|| format!("unknown firmware `{s}` (expected marlin2 or ultimaker2)"))
    }
}
