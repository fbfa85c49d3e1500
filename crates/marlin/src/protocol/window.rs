//! Numbering and the send window: each line gets its number when it is sent (so numbers
//! always match the order on the wire), is kept for resends, and goes out only while the
//! bytes in flight fit the printer's receive buffer.

use super::event::Failure;
use super::framing::{frame, uncuttable, wire_len_bound};
use super::line::{code_of, is_code, InFlight, Kind, Line, OwedLine, UNNUMBERED_PROBE};
use super::phase::Phase;
use super::temperature::HeatWait;
use super::Host;
use crate::gcode::is_heat_wait;
use std::time::Instant;

/// Bytes of the printer's receive ring kept free: for a probe, `N<number> M105*<cs>\n` with
/// up to eight digits of line number (19), and for what a stop sends at once, unnumbered,
/// whatever the ring holds: `M108`, the heaters off and one `M105` (26; see `owed_probe_at`);
/// and beside them the `M105` without a number that numbered probes leave room for (5; see
/// `probe_fits`), so that they fit as often as before it had room of its own.
pub(super) const PROBE_RESERVE: usize = 26 + UNNUMBERED_PROBE.len();

impl Host {
    pub(super) fn history_line(&self, number: u64) -> Option<&Line> {
        let first = self.history.front()?.number;
        self.history.get(number.checked_sub(first)? as usize)
    }

    pub(super) fn reset_numbering(&mut self) {
        self.history.clear();
        self.in_flight.clear();
        self.in_flight_bytes = 0;
        self.unsettled_m105s.clear();
        self.pending.clear();
        self.next_number = 0;
        self.send_cursor = 0;
        self.owed.clear();
        self.unnumbered_probe = None;
        self.recovery.clear_episode();
        self.cautious_until = 0;
        self.confirmed = None;
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
            self.thermal.heat = Some(HeatWait::new(number, line.command.clone(), now));
        }
        if self.in_flight.is_empty() {
            self.timers.front_since = now;
        }
        self.outgoing.extend_from_slice(wire.as_bytes());
        self.in_flight.push_back(InFlight {
            number,
            bytes: wire.len(),
            is_m105,
            m105: is_m105,
            sync,
            heat: is_heat,
            sent: now,
        });
        self.in_flight_bytes += wire.len();
        self.send_cursor = number + 1;
        self.stats.lines_sent += 1;
    }

    pub(super) fn window_allows(&self, number: u64, bytes: usize) -> bool {
        if self.in_flight.is_empty() && self.owed.iter().all(|o| o.bytes == 0) {
            return true;
        }
        if self.in_flight.iter().any(|f| f.heat) {
            // Nothing behind a heat wait until it is answered: a stop during the wait then
            // finds a free command slot for its unnumbered M108 (Marlin 2 reads lines into
            // free slots while it waits, and acts on an M108 as it reads it), and on
            // Ultimaker2Marlin, which reads nothing while it waits, an empty receive
            // buffer for its heaters-off lines; and no move of the job runs after a stop.
            // (Probes still go, in the room kept for one.)
            return false;
        }
        // Lines the printer took off its ring (see `handle_resend`) no longer count here.
        // Sending one line at a time, `M105`s do not either: one line may follow them (in
        // the room the ring has). An `M105`'s answer says nothing of which `M105` it
        // answers; after one answer was lost, each probe's answer was taken for the probe
        // before it, one probe always seemed unanswered, and the host sent only probes
        // (issue 48; `tests/noisy.rs`: 42 of 150 jobs failed or all but stopped).
        let in_ring = |but_m105s: bool| {
            self.in_flight
                .iter()
                .any(|f| f.bytes > 0 && !(but_m105s && f.m105))
        };
        if number < self.cautious_until && in_ring(false) || !self.opts.send_ahead && in_ring(true)
        {
            return false;
        }
        // Every unacknowledged line may still sit in the printer's receive ring: while the
        // firmware is blocked (planner full, M109, G28...) its loop does not move lines into
        // command slots, so free slots announced by ADVANCED_OK (`B`) are no room for more
        // bytes. Bytes beyond the ring are lost and two lines merge into one whose checksum
        // may even pass; so the bytes in flight never exceed the ring. One byte of margin
        // (`<`): Marlin's ring tells full from empty by leaving one cell unused. The last
        // `PROBE_RESERVE` bytes are kept for one probe (see `probe_fits`). Lines outside
        // the count still owed an answer may sit in the ring too.
        self.ring_has_room(bytes + PROBE_RESERVE)
    }

    /// Whether an unnumbered `M105` still fits the receive ring.
    pub(super) fn probe_fits_unnumbered(&self) -> bool {
        self.ring_has_room(UNNUMBERED_PROBE.len())
    }

    /// Whether `bytes` more fit the receive ring beside everything that may still sit in
    /// it (one cell is left unused: see `window_allows`).
    fn ring_has_room(&self, bytes: usize) -> bool {
        self.in_flight_bytes + self.owed_bytes() + bytes < self.opts.firmware.rx_buffer_bytes()
    }

    /// The printer has certainly read and accepted every line up to `number` (an answer
    /// that names it, or an `M105`'s, which it runs after them): they no longer take room
    /// in its receive ring.
    pub(super) fn confirm_through(&mut self, number: u64) {
        self.unsettled_m105s.retain(|&n| n > number);
        self.read_through(number);
        self.confirmed = Some(self.confirmed.map_or(number, |c| c.max(number)));
    }

    /// The printer has read every line up to `number` off its receive ring, whatever it
    /// made of them.
    pub(super) fn read_through(&mut self, number: u64) {
        for f in self.in_flight.iter_mut().filter(|f| f.number <= number) {
            self.in_flight_bytes -= f.bytes;
            f.bytes = 0;
        }
    }

    /// The oldest `M105` whose answer may still come, taken for lost or not: an `M105`'s
    /// answer is certainly its or a later one's (printers run them in the order sent).
    pub(super) fn oldest_m105(&self) -> Option<u64> {
        let in_flight = self.in_flight.iter().filter(|f| f.m105).map(|f| f.number);
        self.unsettled_m105s.iter().copied().chain(in_flight).min()
    }

    /// Bytes of the lines outside the count that may still sit in the receive ring.
    fn owed_bytes(&self) -> usize {
        self.owed.iter().map(|o| o.bytes).sum()
    }

    /// An `ok` without a report, of a line of one of these kinds: the oldest such owed
    /// line's, if one is owed.
    pub(super) fn settle_owed_ok(&mut self, kinds: &[OwedLine]) -> bool {
        let Some(pos) = self.owed.iter().position(|o| kinds.contains(&o.what)) else {
            return false;
        };
        self.owed.remove(pos);
        true
    }

    /// An `M105`'s answer: the oldest owed `M105`'s, if one is owed; the printer read every
    /// line before it, whose `ok`s, if still to come, were lost.
    pub(super) fn settle_owed_m105(&mut self) -> bool {
        let Some(pos) = self.owed.iter().position(|o| o.what == OwedLine::M105) else {
            return false;
        };
        self.owed.drain(..=pos);
        true
    }

    /// Whether a probe (or a replayed line sent as one) still fits the printer's receive
    /// ring: the window leaves room for one, so the first probe always goes out, and a
    /// further one only once lines have been answered. A probe beyond the ring would be
    /// lost in part while the printer is blocked (a homing or a heat wait of minutes,
    /// during which Ultimaker2Marlin reads nothing), and its remains would merge with the
    /// next line. Numbered probes leave room for one `M105` without a number, the last
    /// way to ask once their answers were lost (see `probe`).
    pub(super) fn probe_fits(&self, number: u64, command: &str) -> bool {
        self.ring_has_room(wire_len_bound(number, command) + UNNUMBERED_PROBE.len())
    }

    /// Send whatever the window allows. A line gets its number only when it is sent, so
    /// numbers always match the order on the wire.
    pub(super) fn pump(&mut self, now: Instant) {
        loop {
            if matches!(
                self.phase,
                Phase::Finished | Phase::Idle | Phase::Boot { .. }
            ) || self.recovery.holding(now)
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
            } else if !self.accepting_job_lines() {
                break;
            } else if let Some((_, len)) = self.job.peek(self.next_job) {
                len
            } else {
                // The lines left are none to send (a cancelled part's).
                self.next_job = self.job.len();
                break;
            };
            let number = self.next_number;
            if !self.window_allows(number, candidate_len + wire_len_bound(number, "")) {
                break;
            }
            let number = if let Some((kind, command)) = self.pending.pop_front() {
                self.new_line(kind, command)
            } else {
                let (idx, command) = self.job.take(self.next_job).expect("peeked above");
                self.next_job = idx + 1;
                self.new_line(Kind::Job(idx), command)
            };
            self.transmit(number, now);
        }
        self.check_progress(now);
    }
}
