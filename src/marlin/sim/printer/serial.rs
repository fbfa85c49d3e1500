//! Serial line assembly, as Marlin's `get_serial_commands` does it: bytes enter a 128-byte
//! receive ring (bytes beyond it are lost), an emergency parser sees M108/M112 on arrival,
//! and complete lines move into the command slots once their line number and checksum
//! pass; a bad line flushes the ring and asks for a resend. Kept apart from the command
//! execution because this is where the firmware flavours differ most on the wire.

use super::super::recorder::Recorder;
use super::motion::is_move;
use super::state::{Printer, Queued, Status, Wait};
use crate::marlin::firmware::Firmware;
use std::time::Instant;

impl Printer {
    /// Bytes from the host. They enter the receive ring; bytes that do not fit are lost,
    /// as on a real board whose host sent more than the ring holds (the line they belonged
    /// to then fails its checksum and is resent).
    ///
    /// The pty hands over in one go what a UART delivers byte by byte, and a board's main
    /// loop empties its ring far faster than 115200 baud fills it; so the main loop gets
    /// to run whenever the ring is full (and, on Marlin 2.1, after each line as it
    /// completes), and bytes are lost only when it cannot take lines (all command slots
    /// full, or stuck in a blocking command such as M109). On Marlin 2.1, reading each line
    /// as it comes is what makes a line error's flush take only the bytes that had arrived
    /// before it: every line behind a bad one, still on its way, draws its own
    /// `Error:`/`Resend:`/`ok` block (as on the real Marlin 2.1.2.1), while lines waiting
    /// in a ring the main loop could not empty (a replay among them) are lost with the
    /// flush. Ultimaker2Marlin keeps reading a whole write before it runs a command (its
    /// moves sent behind an `M109` are taken into the queue, and acknowledged, before the
    /// heat wait ends); whether it too answers each line on its way was not checked, nor
    /// for Marlin 2.0 (no real build of it here), which keeps the old model too.
    pub(crate) fn receive(&mut self, bytes: &[u8], now: Instant, recorder: &mut Recorder) {
        let mut lost = 0usize;
        if matches!(self.status, Status::Booting(_)) {
            return; // the bootloader does not listen to the firmware's protocol
        }
        for &b in bytes {
            if self.status != Status::Running {
                return;
            }
            if self.fw.emergency_parser() {
                self.emergency_byte(b);
                if self.status != Status::Running {
                    return;
                }
            }
            if self.rx.len() >= self.fw.rx_buffer_bytes() {
                self.advance(now, recorder);
            }
            if self.rx.len() < self.fw.rx_buffer_bytes() {
                self.rx.push_back(b);
            } else {
                lost += 1;
            }
            if b == b'\n' && self.fw == Firmware::Marlin2 {
                self.advance(now, recorder);
            }
        }
        if lost > 0 {
            tracing::debug!(lost, "receive buffer overrun: bytes lost");
        }
    }

    /// Marlin's EMERGENCY_PARSER: acts on M108/M112 as they arrive, even while the main
    /// loop is stuck in a heat wait.
    fn emergency_byte(&mut self, b: u8) {
        if b != b'\n' && b != b'\r' {
            if self.emergency.len() < 128 {
                self.emergency.push(b);
            }
            return;
        }
        let line = String::from_utf8_lossy(&self.emergency).into_owned();
        self.emergency.clear();
        let cmd = strip_number_and_checksum(&line);
        let word = cmd
            .split_whitespace()
            .next()
            .unwrap_or("")
            .to_ascii_uppercase();
        match word.as_str() {
            "M112" => {
                tracing::warn!("M112: emergency stop");
                self.say("Error:Printer halted. kill() called!");
                self.status = Status::Halted;
            }
            "M108" => {
                // Only a heat wait in progress is broken; a stray M108 must not cut the
                // next one short.
                let heating = self
                    .active
                    .as_ref()
                    .is_some_and(|a| matches!(a.wait, Wait::Heat { .. }));
                self.heat_break = heating;
            }
            _ => {}
        }
    }

    /// Move complete lines from the ring into free command slots, checking them as
    /// Marlin's get_serial_commands does.
    pub(super) fn fill_slots(&mut self) {
        while self.status == Status::Running && self.slots.len() < self.fw.command_slots() {
            let Some(b) = self.rx.pop_front() else { return };
            if b == b';' {
                self.in_comment = true;
            }
            // Ultimaker2Marlin's reader also ends a line at a `:` outside comments.
            let colon_end = b == b':' && self.fw.colon_ends_line() && !self.in_comment;
            if b == b'\n' || b == b'\r' || colon_end {
                self.in_comment = false;
                let raw = std::mem::take(&mut self.assembling);
                let overlong = std::mem::replace(&mut self.overlong, false);
                if raw.iter().all(|c| c.is_ascii_whitespace()) && !overlong {
                    continue;
                }
                self.accept_line(raw);
                continue;
            }
            if self.assembling.len() < self.fw.max_line_bytes() {
                self.assembling.push(b);
            } else {
                self.overlong = true; // Marlin stops storing; the checksum will fail
            }
        }
    }

    fn accept_line(&mut self, mut raw: Vec<u8>) {
        // Comments are not stored (Marlin drops `;...` while reading).
        if let Some(at) = raw.iter().position(|&c| c == b';') {
            raw.truncate(at);
        }
        if self.lose_line(&raw) {
            return;
        }
        self.corrupt_received(&mut raw);
        self.star_for_dot(&mut raw);
        let line = String::from_utf8_lossy(&raw).trim().to_string();
        if line.is_empty() {
            return;
        }
        if let Some(rest) = line.strip_prefix('N') {
            let is_m110 = line.contains("M110");
            // For M110 Marlin 2 takes the last N on the line (`N101 M110 N100`);
            // Ultimaker2Marlin has no M110 handler and keeps the line's own number.
            let number_text = if is_m110 && self.fw.is_marlin2() {
                line.rfind('N').map(|i| &line[i + 1..]).unwrap_or(rest)
            } else {
                rest
            };
            let n = leading_int(number_text);
            if !is_m110 && n != Some(self.last_n as i64 + 1) {
                let last = self.last_n as i64;
                if self.fw.ignores_duplicate_lines()
                    && n.is_some_and(|n| n == last || n == last - 1)
                {
                    tracing::debug!(line = ?n, "duplicate line ignored");
                    return;
                }
                return self.line_error("Line Number is not Last Line Number+1");
            }
            // Marlin 2 takes the last `*`; Ultimaker2Marlin the first, so a `.` turned into
            // `*` may leave a cut line whose checksum passes, and the cut line runs.
            let star = if self.fw.checksum_to_first_star() {
                line.find('*')
            } else {
                line.rfind('*')
            };
            let Some(star) = star else {
                return self.line_error("No Checksum with line number");
            };
            let sum = line.as_bytes()[..star].iter().fold(0u8, |a, &b| a ^ b);
            if leading_int(&line[star + 1..]) != Some(sum as i64) {
                return self.line_error("checksum mismatch");
            }
            if self.spurious_resend() {
                return self.line_error("checksum mismatch");
            }
            let n = n.unwrap_or(0).max(0) as u64;
            self.last_n = n;
            let cmd = strip_number_and_checksum(&line[..=star]).to_string();
            let line_n = leading_int(rest).map(|v| v.max(0) as u64);
            self.enqueue(line_n, cmd);
        } else if line.contains('*') && !self.fw.is_marlin2() {
            // Ultimaker2Marlin: an error, and neither `Resend:` nor `ok`.
            self.say("Error:No Line Number with checksum");
        } else {
            // Marlin 2 checks nothing on a line without N: it runs it (a checksum, if any,
            // is cut off).
            let cmd = strip_number_and_checksum(&line).to_string();
            self.enqueue(None, cmd);
        }
    }

    pub(super) fn enqueue(&mut self, n: Option<u64>, cmd: String) {
        let acked = self.fw.acks_moves_on_entry() && is_move(self.fw, &cmd);
        if acked {
            self.ok(n);
        }
        self.slots.push_back(Queued { n, cmd, acked });
    }

    /// Marlin's gcode_line_error + flush_and_request_resend: report, drop the rest of the
    /// receive buffer, ask for the next expected line, and (per profile) ok.
    pub(super) fn line_error(&mut self, what: &str) {
        let last = self.last_n;
        tracing::debug!(error = what, last_line = last, "line rejected");
        self.say(&format!("Error:{what}, Last Line: {last}"));
        self.rx.clear();
        self.assembling.clear();
        self.overlong = false;
        self.say_noisy(&format!("Resend: {}", last + 1));
        if self.fw.ok_after_resend() {
            // Marlin prints a bare `ok` here, without the ADVANCED_OK fields.
            if !self.drop_this_ok() {
                self.say_noisy("ok");
            }
        }
    }
}

/// `N12 G1 X5*34` → `G1 X5` (also for lines without N or checksum).
pub(crate) fn strip_number_and_checksum(line: &str) -> &str {
    let mut s = line.trim();
    if let Some(star) = s.rfind('*') {
        s = &s[..star];
    }
    if let Some(rest) = s.strip_prefix('N') {
        let digits = rest
            .find(|c: char| !(c.is_ascii_digit() || c == '-'))
            .unwrap_or(rest.len());
        s = &rest[digits..];
    }
    s.trim()
}

pub(super) fn leading_int(s: &str) -> Option<i64> {
    let s = s.trim_start();
    let end = s
        .char_indices()
        .find(|&(i, c)| !(c.is_ascii_digit() || (i == 0 && c == '-')))
        .map_or(s.len(), |(i, _)| i);
    s[..end].parse().ok()
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::marlin::sim::config::SimConfig;

    /// Stock Marlin 2.1.2.1 (no ADVANCED_OK), running at real speed.
    fn stock_marlin() -> (Printer, Recorder) {
        let mut cfg = SimConfig::new(Firmware::Marlin2);
        cfg.time_scale = 1.0;
        cfg.advanced_ok = Some(false);
        let mut p = Printer::new(&cfg, Instant::now());
        p.take_output();
        let rec = Recorder {
            executed: None,
            file: None,
        };
        (p, rec)
    }

    fn numbered(n: u64, cmd: &str) -> String {
        let line = format!("N{n} {cmd}");
        let sum = line.bytes().fold(0u8, |a, b| a ^ b);
        format!("{line}*{sum}\n")
    }

    fn said(p: &mut Printer) -> Vec<String> {
        String::from_utf8_lossy(&p.take_output())
            .lines()
            .map(str::to_string)
            .collect()
    }

    /// As the real Marlin 2.1.2.1 answers through the relay (`tests/firmware.rs`): a line
    /// lost on the way is a line-number error on the next one, and every line already on
    /// its way behind it draws its own `Error:`/`Resend:`/`ok` block (the flush takes only
    /// what had arrived). The simulator once flushed every line of a write at once.
    #[test]
    fn a_lost_line_draws_a_line_number_error_for_each_line_on_its_way() {
        let (mut p, mut rec) = stock_marlin();
        let now = Instant::now();
        let write: String = [1, 3, 4, 5]
            .iter()
            .map(|&n| numbered(n, &format!("G1 X{n} F6000")))
            .collect();
        p.receive(write.as_bytes(), now, &mut rec);
        p.advance(now, &mut rec);
        let said = said(&mut p);
        let block = [
            "Error:Line Number is not Last Line Number+1, Last Line: 1",
            "Resend: 2",
            "ok",
        ];
        let expected: Vec<&str> = std::iter::once("ok")
            .chain(block.iter().copied().cycle().take(9))
            .collect();
        assert_eq!(said, expected);
    }

    /// As on the real firmware: errors are printed when a line is read, `ok`s when a
    /// command is done, so a `Resend:` comes before the `ok`s of earlier lines still
    /// waiting in the command slots.
    #[test]
    fn a_resend_comes_before_the_oks_of_earlier_queued_lines() {
        let (mut p, mut rec) = stock_marlin();
        let now = Instant::now();
        // Corrupted on the way: its checksum no longer matches.
        let bad = numbered(4, "G1 X3 F6000").replace("X3", "X9");
        let write =
            numbered(1, "G4 S1") + &numbered(2, "G1 X1 F6000") + &numbered(3, "G1 X2 F6000") + &bad;
        p.receive(write.as_bytes(), now, &mut rec);
        p.advance(now, &mut rec);
        assert!(said(&mut p).is_empty(), "the dwell holds the main loop");
        p.advance(now + std::time::Duration::from_secs(2), &mut rec);
        let said = said(&mut p);
        assert_eq!(
            said,
            [
                "ok",
                "Error:checksum mismatch, Last Line: 3",
                "Resend: 4",
                "ok",
                "ok",
                "ok"
            ]
        );
    }

    #[test]
    fn strips_number_and_checksum() {
        assert_eq!(strip_number_and_checksum("N12 G1 X5*34"), "G1 X5");
        assert_eq!(strip_number_and_checksum("N0 M110 N0*125"), "M110 N0");
        assert_eq!(strip_number_and_checksum("G28"), "G28");
    }
}
