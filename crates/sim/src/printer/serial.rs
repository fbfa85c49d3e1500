//! Serial line assembly, as Marlin's `get_serial_commands` does it: bytes enter a 128-byte
//! receive ring (bytes beyond it are lost), an emergency parser sees M108/M112 on arrival,
//! and complete lines move into the command slots once their line number and checksum
//! pass; a bad line flushes the ring and asks for a resend. Kept apart from the command
//! execution because this is where the firmware flavours differ most on the wire.

use super::super::recorder::Recorder;
use super::motion::is_move;
use super::state::{Printer, Queued, Status, Wait};
use crispen_marlin::firmware::Firmware;
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
            if self.emergency_parser {
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
            if (b == b'\n' || b == b'\r') && self.fw == Firmware::Marlin2 {
                self.advance(now, recorder);
            }
        }
        if lost > 0 {
            tracing::debug!(lost, "receive buffer overrun: bytes lost");
        }
    }

    /// Marlin's EMERGENCY_PARSER (`EmergencyParser::update`, e_parser.h): acts on `M108`,
    /// `M112` and `M410` as their bytes arrive, numbered or not, even while the main loop is
    /// stuck in a heat wait. It looks only at a line's first command: `N12 M1080` is taken
    /// for `M108`, `M117 M108` is nothing.
    fn emergency_byte(&mut self, b: u8) {
        if b != b'\n' && b != b'\r' {
            if self.emergency.len() < 128 {
                self.emergency.push(b);
            }
            return;
        }
        let line = std::mem::take(&mut self.emergency);
        if let Some(code) = emergency_code(&line) {
            self.act_at_once(code);
        }
    }

    /// `M108`, `M112` or `M410` acted on before its turn in the queue: by the emergency
    /// parser, or by Marlin's queue as it reads an unnumbered one (queue.cpp:524-531).
    fn act_at_once(&mut self, code: &str) {
        match code {
            "M112" => {
                tracing::warn!("M112: emergency stop");
                self.say("Error:Printer halted. kill() called!");
                self.status = Status::Halted;
            }
            "M410" => self.planner.clear(),
            _ => {
                // It clears `wait_for_heatup`, which a heat wait sets when it starts
                // (temperature.cpp:4097): only a wait in progress is broken.
                let heating = self
                    .active
                    .as_ref()
                    .is_some_and(|a| matches!(a.wait, Wait::Heat { .. }));
                self.heat_break = heating;
            }
        }
    }

    /// Move complete lines from the ring into free command slots, reading them as the
    /// firmware's serial input does. Marlin counts the command being run as holding its
    /// slot (the ring's read index moves on only after it).
    pub(super) fn fill_slots(&mut self) {
        while self.status == Status::Running
            && self.slots.len() + usize::from(self.active.is_some()) < self.fw.command_slots()
        {
            let Some(b) = self.rx.pop_front() else { return };
            if self.fw.is_marlin2() {
                self.marlin_byte(b);
            } else {
                self.ultimaker2_byte(b);
            }
        }
    }

    /// One byte through Marlin 2's `get_serial_commands` and `process_stream_char`
    /// (queue.cpp:326-376, 450-541): a line ends at `\n` or `\r`; from `;` on nothing is
    /// kept, nor past the 95th byte; `\` is dropped and the byte after it kept as it is;
    /// a backspace erases the byte before it.
    fn marlin_byte(&mut self, b: u8) {
        if b == b'\n' || b == b'\r' {
            self.in_comment = false;
            self.escaped = false;
            let raw = std::mem::take(&mut self.assembling);
            if raw.iter().all(|c| c.is_ascii_whitespace()) {
                return;
            }
            return self.accept_line(raw);
        }
        if self.in_comment {
            return;
        }
        if self.escaped {
            self.escaped = false;
        } else if b == b'\\' {
            self.escaped = true;
            return;
        } else if b == b';' {
            self.in_comment = true;
            return;
        }
        if b == 0x08 {
            self.assembling.pop();
            return;
        }
        self.assembling.push(b);
        if self.assembling.len() >= self.fw.max_line_bytes() - 1 {
            self.in_comment = true; // PS_EOL: the rest of an overlong line is skipped
        }
    }

    /// One byte through Ultimaker2Marlin's `get_command` (Marlin_main.cpp:533-644): a line
    /// ends at `\n`, `\r`, a `:` outside a comment, or when 95 bytes are stored (the byte
    /// that ends it is lost); after a `;` nothing is stored, the line is dropped, and so is
    /// the next one (`comment_mode` is cleared only by an empty line).
    fn ultimaker2_byte(&mut self, b: u8) {
        let ends = b == b'\n'
            || b == b'\r'
            || (b == b':' && !self.in_comment)
            || self.assembling.len() >= self.fw.max_line_bytes() - 1;
        if ends {
            if self.assembling.is_empty() {
                self.in_comment = false;
                return;
            }
            let raw = std::mem::take(&mut self.assembling);
            if self.in_comment {
                tracing::debug!("Ultimaker2Marlin drops a line with a comment in it");
                return;
            }
            return self.accept_line(raw);
        }
        if b == b';' {
            self.in_comment = true;
        }
        if !self.in_comment {
            self.assembling.push(b);
        }
    }

    fn accept_line(&mut self, mut raw: Vec<u8>) {
        if self.lose_line(&raw) {
            return;
        }
        self.corrupt_received(&mut raw);
        self.star_for_dot(&mut raw);
        let line = String::from_utf8_lossy(&raw).into_owned();
        if self.fw.is_marlin2() {
            self.accept_marlin(&line);
        } else {
            self.accept_ultimaker2(&line);
        }
    }

    /// Marlin 2.1.2.1's checks of a complete line (queue.cpp:456-538).
    fn accept_marlin(&mut self, line: &str) {
        let command = line.trim_start_matches(' ');
        if !command.starts_with('N') {
            // Only a line that starts with `N` is checked; the rest runs unchecked (its
            // checksum, if any, is cut by the parser). Without an emergency parser the
            // queue acts on an unnumbered M108, M112 or M410 as it reads it (it compares
            // the second to fourth bytes only).
            if !self.emergency_parser {
                let b = command.as_bytes();
                let early = match (b.first(), b.get(1..4)) {
                    (Some(b'M'), Some(b"108")) => Some("M108"),
                    (Some(b'M'), Some(b"112")) => Some("M112"),
                    (Some(b'M'), Some(b"410")) => Some("M410"),
                    _ => None,
                };
                if let Some(early) = early {
                    self.act_at_once(early);
                    if self.status != Status::Running {
                        return;
                    }
                }
            }
            let cmd = strip_number_and_checksum(command).to_string();
            return self.enqueue(None, cmd);
        }
        // `M110` anywhere: no sequence check, and the number after the first `N` past the
        // line's fifth byte (queue.cpp:463-470): `N12 M117 M110 N999` counts on from 999.
        let m110 = command.contains("M110");
        let npos = if m110 {
            command
                .get(4..)
                .and_then(|t| t.find('N'))
                .map_or(0, |i| i + 4)
        } else {
            0
        };
        let n = strtol(&command[npos + 1..]);
        let last = self.last_n as i64;
        if n != last + 1 && !m110 {
            if self.fw.ignores_duplicate_lines() && (last - 1..=last).contains(&n) {
                tracing::debug!(line = n, "duplicate line ignored");
                return;
            }
            return self.line_error("Line Number is not Last Line Number+1");
        }
        // Marlin 2 takes the last `*`.
        let Some(star) = command.rfind('*') else {
            return self.line_error("No Checksum with line number");
        };
        let sum = command.as_bytes()[..star].iter().fold(0u8, |a, &b| a ^ b);
        if strtol(&command[star + 1..]) != i64::from(sum) {
            return self.line_error("checksum mismatch");
        }
        if self.spurious_resend() {
            return self.line_error("checksum mismatch");
        }
        self.last_n = n.max(0) as u64;
        let cmd = strip_number_and_checksum(command).to_string();
        // ADVANCED_OK answers with the number the line starts with.
        let line_n = leading_int(&command[1..]).map(|v| v.max(0) as u64);
        self.enqueue(line_n, cmd);
    }

    /// Ultimaker2Marlin's checks of a complete line (Marlin_main.cpp:547-604): the first
    /// `N` anywhere is its number (so `M117 DONE` without one is a numbered line), `M110`
    /// anywhere skips the sequence check, the checksum covers the line up to its first `*`.
    fn accept_ultimaker2(&mut self, line: &str) {
        let Some(npos) = line.find('N') else {
            if line.contains('*') {
                // An error, and neither `Resend:` nor `ok`.
                self.say("Error:No Line Number with checksum");
            } else {
                let cmd = line.trim().to_string();
                self.enqueue(None, cmd);
            }
            return;
        };
        let n = strtol(&line[npos + 1..]);
        if n != self.last_n as i64 + 1 && !line.contains("M110") {
            return self.line_error("Line Number is not Last Line Number+1");
        }
        // Only up to the first `*`: a `.` turned into `*` may leave a cut line whose
        // checksum passes, and the cut line runs.
        let Some(star) = line.find('*') else {
            return self.line_error("No Checksum with line number");
        };
        let sum = line.as_bytes()[..star].iter().fold(0u8, |a, &b| a ^ b);
        let (read, _) = crispen_marlin::reader::ultimaker2::strtod(&line.as_bytes()[star + 1..]);
        if !read.is_finite() || read as i64 != i64::from(sum) {
            return self.line_error("checksum mismatch");
        }
        if self.spurious_resend() {
            return self.line_error("checksum mismatch");
        }
        self.last_n = n.max(0) as u64;
        let cmd = strip_number_and_checksum(&line[..=star]).to_string();
        self.enqueue(Some(self.last_n), cmd);
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

/// The code an emergency parser takes a line for (e_parser.h): after spaces and an optional
/// `N` with digits, `-` and spaces, an `M`, spaces, then `108`, `112` or `410`; whatever
/// follows up to the line's end does not matter.
fn emergency_code(line: &[u8]) -> Option<&'static str> {
    let at = |i: usize| line.get(i).copied().unwrap_or(0);
    let mut i = 0;
    while at(i) == b' ' {
        i += 1;
    }
    if at(i) == b'N' {
        i += 1;
        while matches!(at(i), b'0'..=b'9' | b'-' | b' ') {
            i += 1;
        }
    }
    if at(i) != b'M' {
        return None;
    }
    i += 1;
    while at(i) == b' ' {
        i += 1;
    }
    match (at(i), at(i + 1), at(i + 2)) {
        (b'1', b'0', b'8') => Some("M108"),
        (b'1', b'1', b'2') => Some("M112"),
        (b'4', b'1', b'0') => Some("M410"),
        _ => None,
    }
}

/// C's `strtol(s, NULL, 10)`: white space, a sign, digits; 0 where there are none.
fn strtol(s: &str) -> i64 {
    let t = s.trim_start_matches([' ', '\t', '\n', '\x0b', '\x0c', '\r']);
    let (negative, t) = match t.as_bytes().first() {
        Some(b'-') => (true, &t[1..]),
        Some(b'+') => (false, &t[1..]),
        _ => (false, t),
    };
    let v = t.bytes().take_while(u8::is_ascii_digit).fold(0i64, |v, d| {
        v.saturating_mul(10).saturating_add(i64::from(d - b'0'))
    });
    if negative {
        -v
    } else {
        v
    }
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
    use crate::config::SimConfig;

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

    fn printer(fw: Firmware, emergency_parser: bool) -> (Printer, Recorder) {
        let mut cfg = SimConfig::new(fw);
        cfg.time_scale = 1.0;
        cfg.advanced_ok = Some(false);
        cfg.emergency_parser = Some(emergency_parser);
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

    /// Marlin 2.1.2.1's queue takes a numbered line with `M110` anywhere in it for a new
    /// count, its number the one after the next `N` (queue.cpp:463-470): after `M117 M110
    /// N999` every later line is refused, as on the real firmware. Ultimaker2Marlin takes
    /// the line's first `N` (Marlin_main.cpp:550-554): its count stays the host's.
    #[test]
    fn a_message_with_m110_renumbers_as_each_firmware_does() {
        let (mut p, mut rec) = printer(Firmware::Marlin2, false);
        let now = Instant::now();
        let write = numbered(1, "G1 X1 F6000") + &numbered(2, "M117 M110 N999");
        p.receive(write.as_bytes(), now, &mut rec);
        p.advance(now, &mut rec);
        assert_eq!(said(&mut p), ["ok", "ok"]);
        p.receive(numbered(3, "G1 X2").as_bytes(), now, &mut rec);
        p.advance(now, &mut rec);
        assert_eq!(
            said(&mut p),
            [
                "Error:Line Number is not Last Line Number+1, Last Line: 999",
                "Resend: 1000",
                "ok"
            ]
        );
        // A line numbered 999 (or 998) is dropped unanswered; an `M110` line passes.
        p.receive(numbered(999, "G1 X3").as_bytes(), now, &mut rec);
        p.advance(now, &mut rec);
        assert!(said(&mut p).is_empty());
        p.receive(numbered(4, "M110 N4").as_bytes(), now, &mut rec);
        p.receive(numbered(5, "G1 X4").as_bytes(), now, &mut rec);
        p.advance(now, &mut rec);
        assert_eq!(said(&mut p), ["ok", "ok"]);

        let (mut p, mut rec) = printer(Firmware::Ultimaker2, false);
        p.receive(write.as_bytes(), now, &mut rec);
        p.receive(numbered(3, "G1 X2").as_bytes(), now, &mut rec);
        p.advance(now, &mut rec);
        // Moves acknowledged on entry, M117 when done: no error.
        assert!(said(&mut p).iter().all(|l| l == "ok"));
        assert_eq!(p.last_n, 3);
        // An unnumbered line with an `N` in it is a numbered one there.
        p.receive(b"M117 DONE\n", now, &mut rec);
        p.advance(now, &mut rec);
        assert_eq!(
            said(&mut p)[0],
            "Error:Line Number is not Last Line Number+1, Last Line: 3"
        );
    }

    /// A carriage return ends a line on both firmwares (queue.cpp:450, Marlin_main.cpp:538):
    /// the piece after it arrives without number or checksum and runs unchecked, as the
    /// real Marlin did when its flush had not taken it. A backspace erases on Marlin 2
    /// (queue.cpp:367-370): erased back to before its `N`, a line runs unchecked too.
    #[test]
    fn line_ends_and_erasures_inside_a_line_run_what_the_file_did_not_say() {
        let (mut p, mut rec) = printer(Firmware::Marlin2, false);
        let now = Instant::now();
        let sum = |l: &str| l.bytes().fold(0u8, |a, b| a ^ b);
        let body = "N1 M117 a\rM104 S300\rM117 b";
        // Byte by byte, as a UART delivers them.
        for b in format!("{body}*{}\n", sum(body)).bytes() {
            p.receive(&[b], now, &mut rec);
            p.advance(now, &mut rec);
        }
        assert_eq!(p.hotend.target, 300.0);
        let said = said(&mut p);
        assert_eq!(said[0], "Error:No Checksum with line number, Last Line: 0");

        let (mut p, mut rec) = printer(Firmware::Marlin2, false);
        let body = format!("N1 M117 {}M104 S280", "\u{8}".repeat(8));
        p.receive(format!("{body}*{}\n", sum(&body)).as_bytes(), now, &mut rec);
        p.advance(now, &mut rec);
        assert_eq!(p.hotend.target, 280.0);
        assert_eq!(p.last_n, 0, "the line ran as an unnumbered one");
    }

    /// Ultimaker2Marlin keeps nothing after a `;`, drops the line, and drops the next one
    /// too: `comment_mode` is cleared only by an empty line (Marlin_main.cpp:542-547, 641).
    #[test]
    fn a_comment_drops_the_line_and_the_next_on_ultimaker2marlin() {
        let (mut p, mut rec) = printer(Firmware::Ultimaker2, false);
        let now = Instant::now();
        let write = "N1 M105 ;x*1\n".to_string() + &numbered(2, "M105") + &numbered(3, "M105");
        p.receive(write.as_bytes(), now, &mut rec);
        p.advance(now, &mut rec);
        assert_eq!(
            said(&mut p)[0],
            "Error:Line Number is not Last Line Number+1, Last Line: 0"
        );
        // Marlin 2 drops only the rest of the line, its checksum with it.
        let (mut p, mut rec) = printer(Firmware::Marlin2, false);
        p.receive(write.as_bytes(), now, &mut rec);
        p.advance(now, &mut rec);
        assert_eq!(
            said(&mut p)[0],
            "Error:No Checksum with line number, Last Line: 0"
        );
    }

    /// Without an emergency parser, Marlin 2 reads lines into free command slots while it
    /// waits for a heater (temperature.cpp:4122, MarlinCore.cpp:412) and ends the wait on
    /// an unnumbered `M108` as it reads it (queue.cpp:524-531); with every slot taken, the
    /// `M108` waits in the receive buffer with the rest. Ultimaker2Marlin reads nothing.
    #[test]
    fn an_unnumbered_m108_ends_a_heat_wait_where_the_firmware_reads_it() {
        let now = Instant::now();
        for (fw, queued_behind, breaks) in [
            (Firmware::Marlin2, 0, true),
            (Firmware::Marlin2, 3, false),
            (Firmware::Marlin20, 0, true),
            (Firmware::Ultimaker2, 0, false),
        ] {
            let (mut p, mut rec) = printer(fw, false);
            let mut write = numbered(1, "M109 S200");
            for n in 0..queued_behind {
                write += &numbered(2 + n, "G4 P1");
            }
            p.receive(write.as_bytes(), now, &mut rec);
            p.advance(now, &mut rec);
            assert!(p.in_heat_wait(), "{fw}");
            p.take_output();
            let later = now + std::time::Duration::from_millis(500);
            p.receive(b"M108\n", later, &mut rec);
            p.advance(later, &mut rec);
            assert_eq!(
                !p.in_heat_wait(),
                breaks,
                "{fw} with {queued_behind} behind"
            );
            if breaks {
                assert!(p.hotend.current < 100.0);
            }
        }
        // With an emergency parser, it acts on arrival, slots full or not, numbered or not.
        let (mut p, mut rec) = printer(Firmware::Marlin2, true);
        let write = numbered(1, "M109 S200") + &numbered(2, "G4 P1") + &numbered(3, "G4 P1");
        p.receive(write.as_bytes(), now, &mut rec);
        p.advance(now, &mut rec);
        p.receive(numbered(4, "M1080").as_bytes(), now, &mut rec);
        p.advance(now, &mut rec);
        assert!(!p.in_heat_wait());
    }
}
