//! A `Resend: n` from the printer, step by step: which line it really asks for (a rejected
//! `M110` names a line of the old count), whether it can be honoured at all (a line it had
//! confirmed, one never sent, one no longer kept), whether it is a duplicate caused by a
//! line already on its way, how often it came (a storm is paced, and fails in the end),
//! and then the replay: what the printer dropped, the error blocks to wait for, the `ok`
//! that may follow, and the rewind of the send cursor. What is kept between requests is
//! [`Recovery`](super::recovery::Recovery).

use super::event::{Event, Failure, Numbering};
use super::line::{is_code, Kind};
use super::phase::Phase;
use super::recovery::{OkFollow, Settle, REPLAY_PROBE, SETTLE_MAX, UNEXPLAINED_LIMIT};
use super::Host;
use std::time::{Duration, Instant};

/// Acknowledged lines a request may disown before the host takes the printer's count for
/// gone back: an `ok` taken for a line's may have been a fragment's (the firmware ran the
/// tail of a cut line) or a line's whose corrupted `N` made it run unchecked. Four: the
/// real Ultimaker2Marlin behind the noisy relay once disowned four such answers in one
/// window (`Resend: 86` after `ok`s taken for 86 to 89); a count that really went back
/// (a restart, an `M110` slipped in) lands far below the lines in flight.
const WENT_BACK_SLACK: u64 = 4;

impl Host {
    pub(super) fn handle_resend(&mut self, n: u64, now: Instant) {
        self.timers.last_progress = now;
        let expect_ok = self.expect_ok_after_resend();
        let first = self.history.front().map_or(self.next_number, |l| l.number);
        if self.phase == Phase::Greeting && (n < first || n >= self.next_number) {
            // The printer's counter is from an earlier session; M110 resets it.
            self.send_greeting(now);
            return;
        }
        let last_line = self.recovery.error_last_line;
        let n = self.requested_line(n, first);
        if self.refuse_resend(n, first, last_line, expect_ok, now) {
            return;
        }
        self.free_ring_before(n);
        if self.skip_duplicate_resend(n, expect_ok, now) {
            return;
        }
        if self.count_repeated_resend(n, now) {
            return;
        }
        self.drop_lines_from(n, now);
        self.listen_for_ok_after_resend(expect_ok, now);
        self.rewind_to(n);
    }

    /// Whether an `ok` follows this `Resend:` (plain `ok`s are ignored anyway where
    /// ADVANCED_OK numbers them).
    fn expect_ok_after_resend(&self) -> bool {
        !self.advanced_ok
            && self
                .recovery
                .resend_ok
                .known()
                .unwrap_or(self.opts.firmware.ok_after_resend())
    }

    /// The line a request for `n` really asks for, `first` being the oldest line kept.
    fn requested_line(&mut self, n: u64, first: u64) -> u64 {
        let never_sent = n >= self.next_number || n > self.send_cursor;
        let counter_reset_pending = self.in_flight.front().is_some_and(|f| f.number == first)
            && self
                .history_line(first)
                .is_some_and(|l| l.kind == Kind::Setup && is_code(&l.command, &["M110"]));
        // A request for a line we never sent, after an error that names the line before it,
        // while our `M110` is unanswered: the printer rejected the `M110` (its counter still
        // runs from before). Send it again. A garbled number never matches its error.
        let consistent = std::mem::take(&mut self.recovery.error_last_line) == n.checked_sub(1);
        let stop_first = self.stopping().map(|_| first);
        if never_sent && counter_reset_pending && consistent {
            first
        } else if let Some(first) = stop_first.filter(|&f| n < f) {
            // The printer still counts from before the stop: it rejected our M110. The
            // safe-stop lines are harmless to run twice, so replaying from it is safe.
            // Whatever answer seemed to confirm a line of the stop's count (an M105's,
            // after a refusal taken for a duplicate) did not: the printer took none.
            self.confirmed = self.confirmed.filter(|&c| c < first);
            first
        } else {
            n
        }
    }

    /// A request that cannot be honoured: for a line the printer had confirmed (it lost its
    /// state), for one never sent, for lines it had acknowledged in order (its count is no
    /// longer the host's), or for one no longer kept. True if it was one. `last_line`: the
    /// `Last Line:` of the error before it.
    fn refuse_resend(
        &mut self,
        n: u64,
        first: u64,
        last_line: Option<u64>,
        expect_ok: bool,
        now: Instant,
    ) -> bool {
        if let Some(confirmed) = self.confirmed.filter(|&c| n <= c) {
            let last_acked = self.acked_job;
            self.fail_safely(
                Failure::LostState {
                    line: n,
                    confirmed,
                    last_acked,
                },
                now,
            );
            return true;
        }
        // The error before a real request names the line before it (`Last Line: 999`,
        // `Resend: 1000`); a garbled number does not match its error.
        let consistent = last_line == n.checked_sub(1);
        // A stop has a count of its own, and sends its M110 again where it was rejected.
        let streaming = self.stopping().is_none();
        if n > self.next_number && streaming {
            // Beyond the next line the host would send: the printer counts from elsewhere.
            let sent = self.next_number.saturating_sub(1);
            if consistent {
                let what = Numbering::AheadOfHost {
                    requested: n,
                    last_line,
                    sent,
                };
                self.numbering_lost(what, now);
                return true;
            }
            // A garbled number, or a refusal whose error was lost: its `ok` is no line's.
            // More of them, one for each line sent and unanswered, are no accident.
            if self.unexplained_answer() {
                let refusals = self.recovery.unexplained;
                self.numbering_lost(Numbering::NoAdvance { refusals, sent }, now);
                return true;
            }
        }
        if n >= self.next_number || n > self.send_cursor {
            // Never sent (`Resend: 034497`, or Ultimaker2Marlin's answer to a fragment with
            // an `N` in it): nothing to replay. The `ok` printed with it is not a line's.
            self.recovery.ok_may_follow = Some(OkFollow {
                swallow: expect_ok,
                learn: false,
            });
            self.events.push_back(Event::Message(format!(
                "ignored resend request for line {n}"
            )));
            return true;
        }
        // Lines before the oldest one still unanswered were answered in order: a request
        // for them disowns those answers. One or two may have been another line's `ok` (a
        // fragment the firmware ran, a lost line whose number was corrupted away); more is
        // a printer whose count went back.
        let answered_front = self
            .in_flight
            .front()
            .map_or(self.send_cursor, |f| f.number);
        if streaming && consistent && n + WENT_BACK_SLACK < answered_front {
            let what = Numbering::WentBack {
                requested: n,
                acknowledged: answered_front - 1,
            };
            self.numbering_lost(what, now);
            return true;
        }
        if n < first {
            let last_acked = self.acked_job;
            self.fail_safely(
                Failure::LineGone {
                    line: n,
                    oldest_kept: first,
                    last_acked,
                },
                now,
            );
            return true;
        }
        false
    }

    /// The printer took every line before n off its receive ring into its command queue
    /// (that is what `Last Line: n-1` says): they still owe their `ok`s, but no longer
    /// take room in the ring, and a lost `ok` among them must not hold the window shut.
    fn free_ring_before(&mut self, n: u64) {
        for f in self.in_flight.iter_mut().filter(|f| f.number < n) {
            f.bytes = 0;
        }
        self.in_flight_bytes = self.in_flight.iter().map(|f| f.bytes).sum();
        self.unsettled_m105s.retain(|&m| m >= n);
    }

    /// A request caused by a line that was already on its way when the replay of `n`
    /// began: nothing more to replay. True if it was one.
    fn skip_duplicate_resend(&mut self, n: u64, expect_ok: bool, now: Instant) -> bool {
        let number_error = std::mem::take(&mut self.recovery.number_error);
        let Some((line, remaining)) = self.recovery.duplicate_budget else {
            return false;
        };
        if !(line == n && remaining > 0 && number_error) {
            return false;
        }
        self.recovery.duplicate_budget = Some((line, remaining - 1));
        if let Some(settle) = self.recovery.settle.as_mut().filter(|s| s.line == n) {
            settle.remaining = settle.remaining.saturating_sub(1);
            if settle.remaining == 0 {
                self.recovery.settle = None; // every line on its way has drawn its block
            }
        }
        self.recovery.ok_may_follow = Some(OkFollow {
            swallow: expect_ok,
            learn: false,
        });
        if self.send_cursor > n {
            // Seen on the real Marlin: each such block flushes the receive ring,
            // with our replay in it if it had arrived; it then never gets an
            // answer. Find out soon, not after a quiet probe interval.
            self.recovery.probe_replay = Some((n, now + REPLAY_PROBE));
        }
        true
    }

    /// Counts a request for the same line again: past `resend_limit` (or during a safe
    /// stop) replays are paced, and a storm that outlasts `storm_timeout` fails the job.
    /// True if it did.
    fn count_repeated_resend(&mut self, n: u64, now: Instant) -> bool {
        let (times, since) = match self.recovery.repeated {
            Some((line, times, since)) if line == n => (times + 1, since),
            _ => (1, now),
        };
        self.recovery.repeated = Some((n, times, since));
        let stopping = self.stopping().is_some();
        if stopping && times > 1 {
            // The safe stop rides out the noise, paced, until `stop_timeout` (see `tick_job`).
            self.recovery.replay_after = Some(now + self.opts.stop_pause);
        } else if times > self.opts.resend_limit {
            // A storm: paced replays until it ends or outlasts `storm_timeout`.
            self.recovery.replay_after = Some(now + self.opts.storm_pause);
        }
        if !stopping && times > self.opts.resend_limit && now - since >= self.opts.storm_timeout {
            let last_acked = self.acked_job;
            self.fail_safely(
                Failure::ResendLimit {
                    line: n,
                    times: times - 1,
                    last_acked,
                },
                now,
            );
            return true;
        }
        false
    }

    /// The printer dropped line n and everything after it.
    fn drop_lines_from(&mut self, n: u64, now: Instant) {
        // An unnumbered M105 on its way answers after the lines the printer took, which
        // no longer include these: its answer confirms none of them (see `handle_ok`).
        if let Some((before, _, _)) = &mut self.unnumbered_probe {
            *before = (*before).min(n);
        }
        let mut dropped_after = 0;
        self.in_flight.retain(|f| {
            if f.number >= n {
                if f.number > n {
                    dropped_after += 1;
                }
                false
            } else {
                true
            }
        });
        self.in_flight_bytes = self.in_flight.iter().map(|f| f.bytes).sum();
        // The printer discarded its ring: lines from n on are sent again.
        self.unsettled_m105s.retain(|&m| m < n);
        self.recovery.duplicate_budget = Some((n, dropped_after));
        // Lines sent after n may still reach the printer, each drawing an error block that
        // flushes its ring: the replay waits for them (see `Settle`).
        self.recovery.settle = (dropped_after > 0).then(|| Settle {
            line: n,
            remaining: dropped_after,
            quiet_until: now + self.settle_quiet(),
            give_up: now + SETTLE_MAX,
        });
    }

    /// The replay goes out at once. Where nothing else awaits an `ok`, the next line
    /// tells whether this firmware sends one after `Resend:`.
    fn listen_for_ok_after_resend(&mut self, expect_ok: bool, now: Instant) {
        if !self.advanced_ok {
            let learn = self.in_flight.is_empty() && self.recovery.resend_ok.known().is_none();
            self.recovery.ok_may_follow = Some(OkFollow {
                swallow: expect_ok,
                learn,
            });
            if learn {
                self.recovery.resend_hold = Some(now + self.opts.resend_ok_wait);
            }
        }
    }

    /// Counts an answer the host cannot explain (see `Recovery::unexplained`); true when
    /// enough came, each standing for another line still owed an answer, to stop the job.
    pub(super) fn unexplained_answer(&mut self) -> bool {
        let owed = self.in_flight.len() + usize::from(self.unnumbered_probe.is_some());
        if (self.recovery.unexplained as usize) < owed {
            self.recovery.unexplained += 1;
        }
        self.recovery.unexplained >= UNEXPLAINED_LIMIT
    }

    /// The printer's count is no longer the host's: sending on would print nothing (every
    /// line refused) or print lines twice (replaying what it had run). Stop the job and the
    /// printer; the stop works whatever the printer counts (`begin_stop`).
    pub(super) fn numbering_lost(&mut self, what: Numbering, now: Instant) {
        let last_acked = self.acked_job;
        self.events.push_back(Event::Message(format!(
            "the printer's line count is not the host's: {what}"
        )));
        self.fail_safely(Failure::LostNumbering { what, last_acked }, now);
    }

    /// Sends again from line n: the send cursor goes back, a few lines go one at a time,
    /// and an `M105` after the replay settles whatever `ok`s were owed around the request.
    fn rewind_to(&mut self, n: u64) {
        let replay = self.send_cursor - n;
        self.cautious_until = self.send_cursor.max(n) + self.opts.cautious_lines;
        self.send_cursor = n;
        self.stats.resends += 1;
        self.events.push_back(Event::Resend { line: n, replay });
        if self.accepting_job_lines() && !self.pending.iter().any(|(_, c)| c == "M105") {
            // Whatever became of the `ok`s owed around this request (one after `Resend:` or
            // none, earlier lines' answered late, some lost), the answer of an `M105` sent
            // after the replay settles them all: the printer runs it after every earlier line.
            self.pending.push_front((Kind::Housekeeping, "M105".into()));
        }
    }

    /// How long the printer must be quiet after an error block before the replay goes.
    pub(super) fn settle_quiet(&self) -> Duration {
        Settle::quiet(self.timers.ack_wait)
    }
}
