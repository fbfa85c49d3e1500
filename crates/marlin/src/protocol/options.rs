//! The host's tunables: limits, timeouts and pacing, with sensible values per firmware.

use crate::firmware::Firmware;
use std::time::Duration;

/// Tunables; [`ProtocolOptions::for_firmware`] gives sensible values.
#[derive(Debug, Clone)]
pub struct ProtocolOptions {
    pub firmware: Firmware,
    /// Keep several lines in flight within the printer's receive buffer (false: one line in
    /// flight, as OctoPrint and Printrun do).
    pub send_ahead: bool,
    /// After opening, proceed when the printer has been quiet this long (no `start` seen).
    pub quiet_period: Duration,
    /// During the handshake, retry when a line gets no answer for this long.
    pub answer_timeout: Duration,
    /// No byte from the printer for this long while a short command is unacknowledged:
    /// probe with `M105`.
    pub silence_probe: Duration,
    /// No byte at all for this long while waiting on a short command: fail the job.
    pub silence_fail: Duration,
    /// No byte at all for this long while a long command (G28, G29, M400, G4) runs.
    pub long_command_timeout: Duration,
    /// M109/M190 whose temperature has not come closer to its target for this long: stop
    /// safely and fail the job. A wait that still makes progress never times out.
    pub heat_timeout: Duration,
    /// No line acknowledged for this long while the printer keeps talking (outside heat
    /// waits and long commands): stop safely and fail the job.
    pub no_progress_timeout: Duration,
    /// After a `Resend:` while it is not yet known whether this firmware sends an `ok`
    /// after it (Marlin 2.1 and Ultimaker2Marlin do, Marlin 2.0 does not), wait this long
    /// for one before replaying.
    pub resend_ok_wait: Duration,
    /// After a resend, this many further lines go one at a time: a burst right after a
    /// receive-buffer flush is what cuts lines into fragments the firmware may execute.
    pub cautious_lines: u64,
    /// Interval of temperature reports (autoreport) or polls.
    pub temperature_interval: Duration,
    /// How many times the same line may be requested again at once; past that, replays are
    /// paced (`storm_pause`) and the job fails only when the storm outlasts `storm_timeout`.
    /// A printer that keeps asking for the same line is usually behind a noisy cable.
    pub resend_limit: u32,
    pub storm_pause: Duration,
    pub storm_timeout: Duration,
    /// A safe stop after a failure keeps trying this long while the printer keeps talking
    /// (it ends sooner when the printer falls silent for `silence_fail`), one replay every
    /// `stop_pause`: giving up leaves a printer hot.
    pub stop_timeout: Duration,
    pub stop_pause: Duration,
    /// On firmware that checks a checksum only up to the first `*` (Ultimaker2Marlin),
    /// write each line so that no byte corrupted into `*` leaves a cut line that passes
    /// (see `framing::uncuttable`): numbers may gain trailing zeros and words an extra space,
    /// which change the text sent but not what the printer does. On by default; Marlin 2
    /// takes the last `*`, so nothing changes there.
    pub uncuttable_lines: bool,
    /// Lines kept for resends. Marlin only ever asks for a line it has not acknowledged
    /// (those are always kept), so this needs to cover the send-ahead window, not the job.
    pub history_lines: usize,
}

impl ProtocolOptions {
    pub fn for_firmware(firmware: Firmware) -> Self {
        ProtocolOptions {
            firmware,
            send_ahead: true,
            quiet_period: Duration::from_millis(1500),
            answer_timeout: Duration::from_secs(3),
            silence_probe: Duration::from_secs(3),
            silence_fail: Duration::from_secs(30),
            long_command_timeout: Duration::from_secs(900),
            heat_timeout: Duration::from_secs(1200),
            no_progress_timeout: Duration::from_secs(180),
            resend_ok_wait: Duration::from_millis(250),
            cautious_lines: 8,
            temperature_interval: Duration::from_secs(2),
            resend_limit: 10,
            storm_pause: Duration::from_millis(100),
            storm_timeout: Duration::from_secs(30),
            stop_timeout: Duration::from_secs(180),
            stop_pause: Duration::from_millis(200),
            uncuttable_lines: true,
            // Each kept line is a copy of its command: a whole job's worth costs MBs per printer.
            history_lines: 1024,
        }
    }
}
