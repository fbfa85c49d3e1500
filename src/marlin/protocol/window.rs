//! Numbering and the send window: each line gets its number when it is sent (so numbers
//! always match the order on the wire), is kept for resends, and goes out only while the
//! bytes in flight fit the printer's receive buffer.

use super::{code_of, is_code, HeatWait};
use super::{frame, Failure, Host, InFlight, Kind, Line, Phase};
use crate::marlin::gcode::is_heat_wait;
use std::time::Instant;

/// Bytes of the printer's receive ring kept free for a probe: `N<number> M105*<cs>\n` with
/// up to eight digits of line number.
const PROBE_RESERVE: usize = 1 + 8 + 1 + 4 + 1 + 3 + 1;

/// Upper bound of `frame(number, command).len()` without building the line: `N`, the
/// number, a space, the command, `*`, a checksum of at most three digits and `\n`.
fn wire_len_bound(number: u64, command: &str) -> usize {
    let digits = number.checked_ilog10().map_or(1, |d| d as usize + 1);
    1 + digits + 1 + command.len() + 1 + 3 + 1
}

impl Host {
    pub(super) fn history_line(&self, number: u64) -> Option<&Line> {
        let first = self.history.front()?.number;
        self.history.get(number.checked_sub(first)? as usize)
    }

    pub(super) fn reset_numbering(&mut self) {
        self.history.clear();
        self.in_flight.clear();
        self.in_flight_bytes = 0;
        self.pending.clear();
        self.next_number = 0;
        self.send_cursor = 0;
        self.swallow_oks = 0;
        self.duplicate_budget = None;
        self.repeated = None;
        self.replay_after = None;
        self.probe_replay = None;
        self.settle = None;
        self.ok_may_follow = None;
        self.resend_hold = None;
        self.cautious_until = 0;
        self.confirmed = None;
    }

    pub(super) fn discard_unsent_job_lines(&mut self) {
        let Some(first) = self.history.front().map(|l| l.number) else {
            return;
        };
        if self.send_cursor >= self.next_number {
            return;
        }
        let keep = (self.send_cursor - first) as usize;
        let dropped: Vec<Line> = self.history.drain(keep..).collect();
        self.next_number = self.send_cursor;
        for line in dropped.into_iter().rev() {
            if line.kind == Kind::SafeStop {
                self.pending.push_front((line.kind, line.command));
            }
        }
    }

    /// Give the next line a number and remember it for resends.
    pub(super) fn new_line(&mut self, kind: Kind, command: String) -> u64 {
        let number = self.next_number;
        self.next_number += 1;
        let command = if self.opts.uncuttable_lines && self.opts.firmware.checksum_to_first_star() {
            uncuttable(number, command)
        } else {
            command
        };
        // A job's own `M110 N<k>` would move the printer's counter away from the host's:
        // it is sent as `M110 N<its own number>`, which keeps both in step.
        let command = if matches!(kind, Kind::Job(_)) && is_code(&command, &["M110"]) {
            format!("M110 N{number}")
        } else {
            command
        };
        self.history.push_back(Line {
            number,
            kind,
            command,
        });
        // Keep history bounded, but never drop lines that are not yet acknowledged.
        let oldest_needed = self
            .in_flight
            .front()
            .map_or(self.send_cursor, |f| f.number.min(self.send_cursor));
        while self.history.len() > self.opts.history_lines
            && self
                .history
                .front()
                .is_some_and(|l| l.number < oldest_needed)
        {
            self.history.pop_front();
        }
        number
    }

    pub(super) fn transmit(&mut self, number: u64, now: Instant) {
        let Some(line) = self.history_line(number) else {
            return;
        };
        let wire = frame(number, &line.command);
        let is_m105 = code_of(&line.command).eq_ignore_ascii_case("M105");
        let sync = line.kind == Kind::Sync;
        let is_heat = is_heat_wait(&line.command);
        if wire.len() - 1 > self.opts.firmware.max_line_bytes() {
            let failure = Failure::LineTooLong {
                command: line.command.clone(),
                len: wire.len() - 1,
                max: self.opts.firmware.max_line_bytes(),
            };
            self.fail_safely(failure, now);
            return;
        }
        if is_heat {
            let command = line.command.clone();
            let words: Vec<&str> = command.split_whitespace().collect();
            let target = words[1..]
                .iter()
                .find_map(|w| w.strip_prefix(['S', 'R', 's', 'r']))
                .and_then(|v| v.parse::<f64>().ok());
            self.heat = Some(HeatWait {
                number,
                bed: is_code(&command, &["M190"]),
                command,
                target,
                since: now,
                best: None,
            });
        }
        if self.in_flight.is_empty() {
            self.front_since = now;
        }
        self.outgoing.extend_from_slice(wire.as_bytes());
        self.in_flight.push_back(InFlight {
            number,
            bytes: wire.len(),
            is_m105,
            sync,
            sent: now,
        });
        self.in_flight_bytes += wire.len();
        self.send_cursor = number + 1;
        self.lines_sent += 1;
    }

    pub(super) fn window_allows(&self, number: u64, bytes: usize) -> bool {
        if self.in_flight.is_empty() {
            return true;
        }
        // Lines the printer took off its ring (see `handle_resend`) no longer count here.
        let in_ring = self.in_flight.iter().any(|f| f.bytes > 0);
        if in_ring && (!self.opts.send_ahead || number < self.cautious_until) {
            return false;
        }
        // Every unacknowledged line may still sit in the printer's receive ring: while the
        // firmware is blocked (planner full, M109, G28...) its loop does not move lines into
        // command slots, so free slots announced by ADVANCED_OK (`B`) are no room for more
        // bytes. Bytes beyond the ring are lost and two lines merge into one whose checksum
        // may even pass; so the bytes in flight never exceed the ring. One byte of margin
        // (`<`): Marlin's ring tells full from empty by leaving one cell unused. The last
        // `PROBE_RESERVE` bytes are kept for one probe (see `probe_fits`).
        self.in_flight_bytes + bytes + PROBE_RESERVE < self.opts.firmware.rx_buffer_bytes()
    }

    /// Whether a probe (or a replayed line sent as one) still fits the printer's receive
    /// ring: the window leaves room for one, so the first probe always goes out, and a
    /// further one only once lines have been answered. A probe beyond the ring would be
    /// lost in part while the printer is blocked (a homing or a heat wait of minutes,
    /// during which Ultimaker2Marlin reads nothing), and its remains would merge with the
    /// next line.
    pub(super) fn probe_fits(&self, number: u64, command: &str) -> bool {
        self.in_flight_bytes + wire_len_bound(number, command)
            < self.opts.firmware.rx_buffer_bytes()
    }

    /// Send whatever the window allows. A line gets its number only when it is sent, so
    /// numbers always match the order on the wire.
    pub(super) fn pump(&mut self, now: Instant) {
        loop {
            if matches!(
                self.phase,
                Phase::Finished | Phase::Idle | Phase::Boot { .. }
            ) || self.resend_hold.is_some()
                || self.settle.is_some()
                || self.replay_after.is_some_and(|t| now < t)
            {
                return;
            }
            if self.send_cursor < self.next_number {
                // Replaying after a resend request.
                let number = self.send_cursor;
                let Some(line) = self.history_line(number) else {
                    break;
                };
                if !self.window_allows(number, wire_len_bound(number, &line.command)) {
                    break;
                }
                self.transmit(number, now);
                continue;
            }
            let candidate_len = if let Some((_, command)) = self.pending.front() {
                command.len()
            } else if self.accepting_job_lines() && self.next_job < self.job.len() {
                self.job[self.next_job].len()
            } else {
                break;
            };
            let number = self.next_number;
            if !self.window_allows(number, candidate_len + wire_len_bound(number, "")) {
                break;
            }
            let number = if let Some((kind, command)) = self.pending.pop_front() {
                self.new_line(kind, command)
            } else {
                let idx = self.next_job;
                self.next_job += 1;
                let command = self.job[idx].to_owned();
                self.new_line(Kind::Job(idx), command)
            };
            self.transmit(number, now);
        }
        self.check_progress(now);
    }
}

/// A command as a printer reads it, whatever way it was written: one space between words,
/// numbers without trailing zeros after a decimal point (nor a bare point). Undoes what
/// [`uncuttable`] does to a line, so a record of what a printer ran compares with the file.
pub fn canonical(command: &str) -> String {
    command
        .split_whitespace()
        .map(|word| {
            let b = word.as_bytes();
            let numeric = b.len() > 1
                && b[0].is_ascii_alphabetic()
                && word[1..].contains('.')
                && word[1..]
                    .bytes()
                    .all(|c| c.is_ascii_digit() || c == b'.' || c == b'-');
            if numeric {
                word.trim_end_matches('0').trim_end_matches('.')
            } else {
                word
            }
        })
        .collect::<Vec<_>>()
        .join(" ")
}

/// Where a byte of `N<number> <command>` corrupted into `*` would leave a line that still
/// passes a checksum taken up to the first `*`: the XOR of what comes before equals the
/// number the firmware reads after it (`strtol`, 0 where no digit follows). Positions
/// before `from` are not looked at.
pub(super) fn cut_that_passes(body: &[u8], from: usize) -> Option<usize> {
    (from.max(1)..body.len()).find(|&i| {
        let prefix = super::checksum(&body[..i]) as u64;
        let digits: Vec<u8> = body[i + 1..]
            .iter()
            .copied()
            .take_while(u8::is_ascii_digit)
            .take(4)
            .collect();
        let read = std::str::from_utf8(&digits)
            .ok()
            .and_then(|d| d.parse::<u64>().ok())
            .unwrap_or(0);
        prefix == read
    })
}

/// Ultimaker2Marlin checks a line's checksum only up to its first `*`: a `.` corrupted into
/// `*` in `N472 G1 X0.03 Y0.05` runs `G1 X0.03 Y0` when the prefix's XOR happens to be 5,
/// which in G-code is far likelier than 1 in 128 (about one line in ten of a sliced file is
/// at risk). Such a line is written differently with the same meaning: trailing zeros on a
/// number (`Y0.050`, `F6000.0`) or an extra space before a word, which change the prefixes'
/// XORs and what the firmware would read after a cut; one or two such edits, the first
/// variant without a passing cut is taken. Cuts inside `N<number>` itself cannot be written
/// away, nor can a few lines in a thousand whose risky prefix no edit reaches; they are left.
pub(super) fn uncuttable(number: u64, command: String) -> String {
    let from = format!("N{number} ").len();
    let passes = |c: &str| cut_that_passes(format!("N{number} {c}").as_bytes(), from).is_some();
    if !passes(&command) {
        return command;
    }
    let words: Vec<&str> = command.split(' ').collect();
    // (word, zeros to append; 0 means an extra space before it)
    let mut edits = vec![(0, 0)];
    for (k, word) in words.iter().enumerate().skip(1) {
        let numeric = word.len() > 1
            && word.as_bytes()[0].is_ascii_alphabetic()
            && word[1..]
                .bytes()
                .all(|b| b.is_ascii_digit() || b == b'.' || b == b'-')
            && word[1..].bytes().any(|b| b.is_ascii_digit());
        if numeric {
            edits.extend([(k, 1), (k, 2), (k, 3)]);
        }
        edits.push((k, 0));
    }
    let apply = |words: &mut Vec<String>, (k, zeros): (usize, usize)| {
        let word = &mut words[k];
        if zeros == 0 {
            word.insert(0, ' ');
        } else {
            if !word.contains('.') {
                word.push('.');
            }
            word.push_str(&"0".repeat(zeros));
        }
    };
    let base: Vec<String> = words.iter().map(|w| w.to_string()).collect();
    for &edit in &edits {
        let mut w = base.clone();
        apply(&mut w, edit);
        let candidate = w.join(" ");
        if !passes(&candidate) {
            return candidate;
        }
    }
    for &a in &edits {
        for &b in edits.iter().filter(|b| b.0 > a.0) {
            let mut w = base.clone();
            apply(&mut w, a);
            apply(&mut w, b);
            let candidate = w.join(" ");
            if !passes(&candidate) {
                return candidate;
            }
        }
    }
    command
}
