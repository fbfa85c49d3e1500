//! Asking a printer what it is: open its port, wait out the reset that opening causes on
//! most boards, send `M110 N0` and `M115` (numbered, with checksums) and keep the firmware's
//! answer as it wrote it (`FIRMWARE_NAME:…`, `Cap:…` lines).
//!
//! [`Probe`] is the conversation without I/O: bytes and the time go in, bytes to send and
//! the next deadline come out. [`probe`] drives it over a real serial link.

use crate::marlin::protocol::frame;
use crate::marlin::transport::{LinkEvent, Transport, TransportError};
use std::path::{Path, PathBuf};
use std::time::{Duration, Instant};

/// After opening, greet once the printer has said nothing for this long. A board reset by
/// the open stays silent in its bootloader for about a second, then prints `start` and its
/// settings; if `start` comes after the greeting, the greeting starts over.
pub(crate) const QUIET: Duration = Duration::from_millis(1500);
/// Greet after this long even if the printer never goes quiet (temperature reports that
/// a previous host switched on with `M155 S1` keep coming every second).
pub(crate) const BOOT_LIMIT: Duration = Duration::from_secs(6);
/// A greeting line unanswered this long is sent again.
pub(crate) const ANSWER_TIMEOUT: Duration = Duration::from_secs(3);
/// Greetings tried before giving up (the caller's overall timeout may end it sooner).
pub(crate) const MAX_GREETINGS: u32 = 3;
/// Lines kept from the answer; Marlin prints a few dozen `Cap:` lines.
const MAX_ANSWER_LINES: usize = 200;
/// A line longer than this is noise, not firmware output.
const MAX_LINE_BYTES: usize = 1024;

#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Phase {
    /// Waiting for the printer to be quiet after opening or a reset.
    Boot,
    /// `N0 M110 N0` sent.
    Numbering,
    /// `N1 M115` sent; the lines up to its `ok` are the answer.
    Asking,
    Answered,
    GaveUp,
}

/// One probe conversation.
#[derive(Debug)]
pub(crate) struct Probe {
    phase: Phase,
    /// When the current phase's timer started (last byte in Boot, the send otherwise).
    since: Instant,
    /// When the current Boot phase began (the open, or a `start` during the greeting).
    boot_began: Instant,
    partial: Vec<u8>,
    out: Vec<u8>,
    answer: Vec<String>,
    greetings: u32,
    /// An error or resend request arrived since the last greeting: its `ok` does not count.
    rejected: bool,
    saw_start: bool,
    bytes_received: usize,
    lines_received: usize,
}

impl Probe {
    /// A probe for a port opened at `now`.
    pub(crate) fn new(now: Instant) -> Probe {
        Probe {
            phase: Phase::Boot,
            since: now,
            boot_began: now,
            partial: Vec::new(),
            out: Vec::new(),
            answer: Vec::new(),
            greetings: 0,
            rejected: false,
            saw_start: false,
            bytes_received: 0,
            lines_received: 0,
        }
    }

    /// Bytes from the printer.
    pub(crate) fn feed(&mut self, bytes: &[u8], now: Instant) {
        self.bytes_received += bytes.len();
        if self.phase == Phase::Boot {
            self.since = now;
        }
        for &b in bytes {
            if b == b'\n' || b == b'\r' {
                let line = std::mem::take(&mut self.partial);
                self.handle_line(&line, now);
            } else if self.partial.len() < MAX_LINE_BYTES {
                self.partial.push(b);
            }
        }
    }

    /// Time passed: greet after the quiet period, greet again after an unanswered one.
    pub(crate) fn tick(&mut self, now: Instant) {
        let waited = now.saturating_duration_since(self.since);
        match self.phase {
            Phase::Boot if waited >= QUIET || now >= self.boot_began + BOOT_LIMIT => {
                self.greet(now)
            }
            Phase::Numbering | Phase::Asking if waited >= ANSWER_TIMEOUT => self.greet_again(now),
            _ => {}
        }
    }

    /// When [`Probe::tick`] next has something to do.
    pub(crate) fn next_deadline(&self) -> Option<Instant> {
        match self.phase {
            Phase::Boot => Some((self.since + QUIET).min(self.boot_began + BOOT_LIMIT)),
            Phase::Numbering | Phase::Asking => Some(self.since + ANSWER_TIMEOUT),
            Phase::Answered | Phase::GaveUp => None,
        }
    }

    /// Bytes to write to the port now.
    pub(crate) fn take_outgoing(&mut self) -> Vec<u8> {
        std::mem::take(&mut self.out)
    }

    /// The M115 answer, once its `ok` arrived.
    pub(crate) fn answer(&self) -> Option<&[String]> {
        (self.phase == Phase::Answered).then_some(&self.answer[..])
    }

    /// Every greeting went unanswered.
    pub(crate) fn gave_up(&self) -> bool {
        self.phase == Phase::GaveUp
    }

    /// The printer printed `start` (it was reset, most likely by the open).
    pub(crate) fn saw_start(&self) -> bool {
        self.saw_start
    }

    pub(crate) fn bytes_received(&self) -> usize {
        self.bytes_received
    }

    /// Lines of printable text received (none with bytes received: likely a wrong baud rate).
    pub(crate) fn lines_received(&self) -> usize {
        self.lines_received
    }

    fn greet_again(&mut self, now: Instant) {
        if self.greetings >= MAX_GREETINGS {
            self.phase = Phase::GaveUp;
        } else {
            self.greet(now);
        }
    }

    fn greet(&mut self, now: Instant) {
        self.greetings += 1;
        self.rejected = false;
        self.answer.clear();
        self.phase = Phase::Numbering;
        self.since = now;
        // M110 skips the line-number check, so this works whatever number the printer
        // last saw (a printer that was not reset remembers the previous host's).
        self.out.extend_from_slice(frame(0, "M110 N0").as_bytes());
    }

    fn handle_line(&mut self, raw: &[u8], now: Instant) {
        let text = String::from_utf8_lossy(raw);
        let line = text.trim_matches(|c: char| c.is_whitespace() || c == '\0');
        if line.is_empty() {
            return;
        }
        // At a wrong baud rate bytes still arrive, as noise; a line counts only if it is text.
        if !line.chars().any(char::is_control) && !line.contains('\u{fffd}') {
            self.lines_received += 1;
        }
        let lower = line.to_ascii_lowercase();
        if lower == "start" {
            self.saw_start = true;
            if matches!(self.phase, Phase::Numbering | Phase::Asking) {
                // It rebooted under the greeting: wait for it to settle, then greet again.
                self.phase = Phase::Boot;
                self.since = now;
                self.boot_began = now;
            }
            return;
        }
        match self.phase {
            Phase::Numbering | Phase::Asking => {}
            _ => return,
        }
        if lower.starts_with("error:") || lower.starts_with("resend:") || lower.starts_with("rs ") {
            self.rejected = true;
            return;
        }
        if lower.starts_with("ok") {
            if self.rejected {
                // A garbled line: start the greeting over (bounded like a timeout).
                self.greet_again(now);
            } else if self.phase == Phase::Numbering {
                self.phase = Phase::Asking;
                self.since = now;
                self.out.extend_from_slice(frame(1, "M115").as_bytes());
            } else {
                self.phase = Phase::Answered;
            }
            return;
        }
        let chatter = lower.starts_with("echo:busy")
            || lower.starts_with("busy:")
            || lower.starts_with("t:")
            || lower == "wait";
        if self.phase == Phase::Asking && !chatter && self.answer.len() < MAX_ANSWER_LINES {
            self.answer.push(line.to_string());
        }
    }
}

/// What a successful probe found.
#[derive(Debug, Clone)]
pub struct ProbeReport {
    /// The M115 answer lines, as the firmware wrote them.
    pub answer: Vec<String>,
    /// The printer printed `start` (opening the port reset it).
    pub saw_start: bool,
    pub waited: Duration,
}

#[derive(Debug, thiserror::Error)]
pub enum ProbeError {
    #[error(transparent)]
    Open(#[from] TransportError),
    #[error("{port}: no answer to M115 within {waited_s:.1} s; {hint}")]
    NoAnswer {
        port: PathBuf,
        waited_s: f64,
        hint: String,
    },
    #[error("{port}: the port closed during the probe ({reason})")]
    Closed { port: PathBuf, reason: String },
}

/// Opens `port` at `baud` and asks the printer for its M115 answer, giving up after
/// `timeout` in all.
pub async fn probe(port: &Path, baud: u32, timeout: Duration) -> Result<ProbeReport, ProbeError> {
    let mut link = Transport::open(port, baud).await?;
    let started = Instant::now();
    let give_up = started + timeout;
    let mut probe = Probe::new(started);
    loop {
        let out = probe.take_outgoing();
        if !out.is_empty() {
            link.send(out);
        }
        if let Some(answer) = probe.answer() {
            return Ok(ProbeReport {
                answer: answer.to_vec(),
                saw_start: probe.saw_start(),
                waited: started.elapsed(),
            });
        }
        let now = Instant::now();
        if probe.gave_up() || now >= give_up {
            return Err(ProbeError::NoAnswer {
                port: port.to_path_buf(),
                waited_s: now.duration_since(started).as_secs_f64(),
                hint: no_answer_hint(&probe, baud),
            });
        }
        let deadline = probe.next_deadline().unwrap_or(give_up).min(give_up);
        tokio::select! {
            event = link.recv() => match event {
                LinkEvent::Data(bytes) => probe.feed(&bytes, Instant::now()),
                LinkEvent::Closed(reason) => {
                    return Err(ProbeError::Closed { port: port.to_path_buf(), reason });
                }
            },
            _ = tokio::time::sleep_until(tokio::time::Instant::from_std(deadline)) => {
                probe.tick(Instant::now());
            }
        }
    }
}

fn no_answer_hint(probe: &Probe, baud: u32) -> String {
    if probe.bytes_received() == 0 {
        "nothing at all was received (is the printer switched on, and is this its port?)"
            .to_string()
    } else if probe.lines_received() == 0 {
        format!(
            "{} bytes arrived but no readable line: the baud rate {baud} is probably wrong \
             (try --baud 115200 or --baud 250000)",
            probe.bytes_received()
        )
    } else {
        format!(
            "{} lines arrived but none answered M115 (is this a Marlin printer?)",
            probe.lines_received()
        )
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Feeds `text` split at every possible byte position and checks each run ends the same.
    fn conversation(replies: &[&str]) -> Vec<Probe> {
        let whole: String = replies.concat();
        (0..=whole.len())
            .map(|split| {
                let t0 = Instant::now();
                let mut p = Probe::new(t0);
                p.tick(t0 + QUIET);
                assert_eq!(p.take_outgoing(), frame(0, "M110 N0").into_bytes());
                let t = t0 + QUIET + Duration::from_millis(10);
                let (a, b) = whole.as_bytes().split_at(split);
                p.feed(a, t);
                p.feed(b, t);
                p
            })
            .collect()
    }

    #[test]
    fn waits_for_quiet_then_numbers_then_asks() {
        let t0 = Instant::now();
        let mut p = Probe::new(t0);
        p.tick(t0 + QUIET / 2);
        assert!(
            p.take_outgoing().is_empty(),
            "greeted before the quiet period"
        );
        // The boot banner restarts the quiet period.
        p.feed(b"start\necho:Marlin 2.1.2\n", t0 + QUIET / 2);
        p.tick(t0 + QUIET);
        assert!(p.take_outgoing().is_empty(), "greeted during the banner");
        p.tick(t0 + QUIET / 2 + QUIET);
        assert_eq!(p.take_outgoing(), b"N0 M110 N0*125\n");
        let t = t0 + 2 * QUIET;
        p.feed(b"ok\n", t);
        assert_eq!(p.take_outgoing(), frame(1, "M115").into_bytes());
        p.feed(
            b"FIRMWARE_NAME:Marlin 2.1.2 SOURCE_CODE_URL:x UUID:1\r\nCap:EEPROM:1\nok\n",
            t,
        );
        assert_eq!(
            p.answer().unwrap(),
            [
                "FIRMWARE_NAME:Marlin 2.1.2 SOURCE_CODE_URL:x UUID:1",
                "Cap:EEPROM:1"
            ]
        );
        assert!(p.saw_start());
    }

    #[test]
    fn answer_is_the_same_whatever_the_byte_split() {
        let replies = [
            "echo:Unknown command: \"M110 N0\"\n", // Ultimaker2Marlin has no M110
            "ok\n",
            "T:20.0 /0.0 B:20.0 /0.0 @:0 B@:0\n", // autoreport left on by another host
            "FIRMWARE_NAME:Marlin Ultimaker2; Sprinter/grbl mashup for gen6 EXTRUDER_COUNT:1\n",
            "echo:busy: processing\n",
            "ok N1 P15 B3\n",
        ];
        for p in conversation(&replies) {
            assert_eq!(
                p.answer().unwrap(),
                ["FIRMWARE_NAME:Marlin Ultimaker2; Sprinter/grbl mashup for gen6 EXTRUDER_COUNT:1"]
            );
        }
    }

    #[test]
    fn a_printer_that_never_goes_quiet_is_greeted_after_the_boot_limit() {
        let t0 = Instant::now();
        let mut p = Probe::new(t0);
        let report = b"T:21.3 /0.0 B:20.9 /0.0 @:0 B@:0\n";
        let mut t = t0;
        while p.take_outgoing().is_empty() {
            assert!(
                t < t0 + BOOT_LIMIT + Duration::from_secs(1),
                "never greeted"
            );
            t += Duration::from_secs(1);
            p.feed(report, t);
            p.tick(t);
        }
        assert!(t >= t0 + BOOT_LIMIT);
        p.feed(report, t);
        p.feed(b"ok\n", t);
        assert_eq!(p.take_outgoing(), frame(1, "M115").into_bytes());
        p.feed(report, t);
        p.feed(b"FIRMWARE_NAME:Marlin 2.1.2\nok\n", t);
        assert_eq!(p.answer().unwrap(), ["FIRMWARE_NAME:Marlin 2.1.2"]);
    }

    #[test]
    fn a_rejected_greeting_is_sent_again() {
        let t0 = Instant::now();
        let mut p = Probe::new(t0);
        p.tick(t0 + QUIET);
        p.take_outgoing();
        let t = t0 + QUIET;
        p.feed(b"Error:checksum mismatch, Last Line: 7\nResend: 8\nok\n", t);
        assert_eq!(p.take_outgoing(), frame(0, "M110 N0").into_bytes());
        assert!(p.answer().is_none());
        p.feed(b"ok\n", t);
        assert_eq!(p.take_outgoing(), frame(1, "M115").into_bytes());
    }

    #[test]
    fn a_reset_during_the_greeting_waits_and_greets_again() {
        let t0 = Instant::now();
        let mut p = Probe::new(t0);
        p.tick(t0 + QUIET);
        p.take_outgoing();
        let t = t0 + QUIET + Duration::from_millis(200);
        p.feed(b"start\n", t);
        p.tick(t + QUIET / 2);
        assert!(p.take_outgoing().is_empty());
        p.tick(t + QUIET);
        assert_eq!(p.take_outgoing(), frame(0, "M110 N0").into_bytes());
    }

    #[test]
    fn silence_gives_up_after_the_bounded_greetings() {
        let t0 = Instant::now();
        let mut p = Probe::new(t0);
        let mut t = t0 + QUIET;
        p.tick(t);
        assert_eq!(p.take_outgoing(), frame(0, "M110 N0").into_bytes());
        for _ in 1..MAX_GREETINGS {
            t += ANSWER_TIMEOUT;
            p.tick(t);
            assert_eq!(p.take_outgoing(), frame(0, "M110 N0").into_bytes());
        }
        assert!(!p.gave_up());
        t += ANSWER_TIMEOUT;
        p.tick(t);
        assert!(p.gave_up() && p.take_outgoing().is_empty() && p.next_deadline().is_none());
    }

    #[test]
    fn noise_is_told_apart_from_text() {
        let t0 = Instant::now();
        let mut p = Probe::new(t0);
        p.feed(&[0xf0, 0x80, b'\n', 0x1b, 0x9c, 0xfe, b'\n'], t0);
        assert_eq!((p.bytes_received(), p.lines_received()), (7, 0));
        assert!(no_answer_hint(&p, 250_000).contains("baud rate 250000 is probably wrong"));
        // Endless noise without a newline is bounded.
        p.feed(&vec![b'x'; 10 * MAX_LINE_BYTES], t0);
        assert!(p.partial.len() <= MAX_LINE_BYTES);
    }
}
