//! Deadlines, probes and timeouts: when the host must act next, and what it does when a
//! line goes unanswered (an `M105` probe for a lost `ok`), the printer falls silent, a
//! long command or a heat wait outlasts its limit, or the holds of a resend run out. The
//! clocks themselves are [`Timers`](super::timers::Timers).

use super::event::{Event, Failure};
use super::line::{is_code, Kind, LONG_COMMANDS, UNNUMBERED_PROBE};
use super::phase::{Phase, Stop};
use super::Host;
use std::time::{Duration, Instant};

/// How long no line may be answered, with no room for a numbered probe, before an `M105`
/// without a number asks (see `probe`): well past a move that keeps a printer from
/// reading its ring (Ultimaker2Marlin's 3-second prime, seen at 5.8 s with probes behind
/// it), well inside the limit of progress (`no_progress_timeout`, 180 s by default).
const STUCK: Duration = Duration::from_secs(10);

impl Host {
    /// The earliest time [`Host::tick`] must be called, if any.
    pub fn next_deadline(&self) -> Option<Instant> {
        match &self.phase {
            Phase::Finished | Phase::Idle => None,
            Phase::Boot { saw_start } => {
                let quiet = if *saw_start {
                    self.opts.quiet_period.min(Duration::from_millis(300))
                } else {
                    self.opts.quiet_period
                };
                Some(self.timers.last_rx.max(self.timers.opened_at) + quiet)
            }
            Phase::Greeting => Some(self.timers.greeting_sent_at + self.opts.answer_timeout),
            Phase::Job(_) => {
                let mut deadline: Option<Instant> = None;
                let mut at = |t: Instant| {
                    deadline = Some(deadline.map_or(t, |d: Instant| d.min(t)));
                };
                if !self.autoreport() && self.accepting_job_lines() {
                    at(self.timers.next_poll);
                }
                if let Some((_, decide)) = &self.pending_error {
                    at(*decide);
                }
                if let Some(hold) = self.recovery.resend_hold {
                    at(hold);
                }
                if let Some(t) = self.recovery.replay_after {
                    at(t);
                }
                if let Some((_, t)) = self.recovery.probe_replay {
                    at(t);
                }
                if let Some(settle) = &self.recovery.settle {
                    at(settle.deadline());
                }
                if let Some(stop) = self.stopping() {
                    at(self.stop_gives_up(stop));
                }
                if let Some(t) = self.owed_probe_at() {
                    at(t);
                }
                if let Some(deadline) = self.thermal.deadline(self.opts.heat_timeout) {
                    at(deadline);
                }
                if let Some(front) = self.front_line() {
                    at(self.next_probe_at());
                    if self.heat_at_front() {
                        // The heat wait has its own limit, but a waiting printer reports
                        // every second: silence means it is gone.
                        at(self.timers.last_rx + self.opts.silence_fail);
                    } else if is_code(&front.command, &LONG_COMMANDS) {
                        at(self.timers.last_rx + self.opts.long_command_timeout);
                    } else {
                        at(self.timers.last_rx + self.opts.silence_fail);
                        at(self.timers.last_ack + self.opts.no_progress_timeout);
                    }
                }
                deadline
            }
        }
    }

    /// Handle timeouts due at `now`.
    pub fn tick(&mut self, now: Instant) {
        match &self.phase {
            Phase::Finished | Phase::Idle => {}
            Phase::Boot { .. } => {
                if self.next_deadline().is_some_and(|d| now >= d) {
                    self.send_greeting(now);
                }
            }
            Phase::Greeting => {
                if now >= self.timers.greeting_sent_at + self.opts.answer_timeout {
                    if self.greeting_attempts >= 3 {
                        let waited = now - self.timers.opened_at;
                        self.fail(Failure::NoAnswer { waited });
                    } else {
                        self.send_greeting(now);
                    }
                }
            }
            Phase::Job(_) => self.tick_job(now),
        }
        self.pump(now);
    }

    fn tick_job(&mut self, now: Instant) {
        if let Some((message, _)) = self.pending_error.take_if(|(_, decide)| now >= *decide) {
            self.firmware_error(message, now);
            return;
        }
        if let Some(stop) = self.stopping() {
            if now >= self.stop_gives_up(stop)
                || now - self.timers.last_rx >= self.opts.silence_fail
            {
                self.finish_stop(false);
                return;
            }
        }
        if self.owed_probe_at().is_some_and(|t| now >= t) {
            self.probe_owed(now);
        }
        if self.recovery.replay_after.is_some_and(|t| now >= t) {
            self.recovery.replay_after = None;
        }
        if self.recovery.settle.is_some_and(|s| now >= s.deadline()) {
            // Quiet: whatever error blocks were coming have come.
            self.recovery.settle = None;
        }
        if let Some((line, _)) = self.recovery.probe_replay.take_if(|(_, t)| now >= *t) {
            if self.in_flight.front().is_some_and(|f| f.number == line) {
                self.probe(now);
            }
        }
        if !self.autoreport() && self.accepting_job_lines() && now >= self.timers.next_poll {
            self.timers.next_poll = now + self.opts.temperature_interval;
            if !self.in_flight.iter().any(|f| f.is_m105)
                && !self.pending.iter().any(|(_, c)| c == "M105")
            {
                self.pending.push_back((Kind::Housekeeping, "M105".into()));
            }
        }
        if self.recovery.resend_hold.is_some_and(|hold| now >= hold) {
            // Nothing came after the `Resend:`: this firmware sends no `ok` there.
            self.recovery.resend_hold = None;
            if self.recovery.ok_may_follow.take().is_some() {
                self.recovery.resend_ok.seen_none += 1;
            }
        }
        let last_acked = self.acked_job;
        if self
            .thermal
            .deadline(self.opts.heat_timeout)
            .is_some_and(|d| now >= d)
        {
            if self.stopping().is_some() {
                // The stop waited for the heat-up (see `stop_gives_up`) as long as it could.
                self.thermal.heat = None;
                self.finish_stop(false);
                return;
            }
            let heat = self
                .thermal
                .heat
                .take()
                .expect("a deadline means a heat wait");
            let temperatures = self.thermal.temps;
            self.fail_safely(
                Failure::HeatTimeout {
                    command: heat.command,
                    waited: now - heat.since,
                    temperatures,
                    last_acked,
                },
                now,
            );
            return;
        }
        let Some(front) = self.front_line().cloned() else {
            return;
        };
        if self.heat_at_front() {
            // Inside a heat wait: its own limit applies; but every firmware reports the
            // temperature each second while it waits, so silence means it is gone.
            if now - self.timers.last_rx >= self.opts.silence_fail {
                self.fail(Failure::Silent {
                    waited: now - self.timers.last_rx,
                    last_acked,
                });
            }
        } else if is_code(&front.command, &LONG_COMMANDS) {
            if now - self.timers.last_rx >= self.opts.long_command_timeout {
                self.fail(Failure::Silent {
                    waited: now - self.timers.last_rx,
                    last_acked,
                });
            }
        } else if now - self.timers.last_rx >= self.opts.silence_fail {
            self.fail(Failure::Silent {
                waited: now - self.timers.last_rx,
                last_acked,
            });
        } else if now - self.timers.last_ack >= self.opts.no_progress_timeout {
            self.fail_safely(
                Failure::NoProgress {
                    waited: now - self.timers.last_ack,
                    last_acked,
                },
                now,
            );
            return;
        }
        if self.in_job() && now >= self.next_probe_at() {
            self.probe(now);
        }
    }

    /// When a stop is given up unconfirmed: at its own limit, or, while the printer waits for
    /// a heater and reads nothing until it is there (Ultimaker2Marlin), when that wait times
    /// out: its heaters-off lines run only then.
    fn stop_gives_up(&self, stop: &Stop) -> Instant {
        let give_up = stop.give_up();
        match self.thermal.deadline(self.opts.heat_timeout) {
            Some(heat) if !self.breaks_heat_wait() && self.heating() => give_up.max(heat),
            _ => give_up,
        }
    }

    /// Send an `M105` at once, in the room the send window keeps for it: the printer is most
    /// likely idle and the window only looks full because an `ok` was lost. Its answer
    /// acknowledges every earlier line.
    pub(super) fn probe(&mut self, now: Instant) {
        if self.recovery.holding(now) {
            return;
        }
        self.timers.last_probe = Some(now);
        if self.counter_reset_in_flight() {
            // The host's `M110` waits to run (behind a long command, or moves): a numbered
            // line read before it runs is counted again from the M110's number when it
            // does (M110.cpp:31-32), and the printer would refuse the next one. An M105
            // without a number asks all the same.
            // Only the M110 is in flight, so a late answer of an earlier one settles the
            // same line: one taken for lost is simply asked again.
            self.probe_unnumbered(now, true);
            return;
        }
        let replay = self
            .history_line(self.send_cursor)
            .filter(|_| self.send_cursor < self.next_number)
            .map(|l| l.command.clone());
        let fits = match &replay {
            Some(command) => self.probe_fits(self.send_cursor, command),
            None => self.probe_fits(self.next_number, "M105"),
        };
        if !fits {
            // Earlier probes fill the room kept for one: the printer has not read them yet
            // (blocked), or their answers were lost. A printer that reports its
            // temperatures unasked is never silent, so silence cannot tell which: after
            // [`STUCK`] without an answer, an `M105` without a number asks (it fits where
            // a numbered line does not). Its answer says the printer read every line sent
            // before it; a lost burst of answers otherwise held the job until it failed
            // for want of progress (issue 48, `tests/noisy.rs`).
            if now.saturating_duration_since(self.timers.last_ack) >= STUCK
                && self.probe_fits_unnumbered()
            {
                self.probe_unnumbered(now, false);
            }
            return;
        }
        self.stats.probes += 1;
        self.events.push_back(Event::Probe);
        // An ignored duplicate resend request may have been a real one: after a probe, a
        // repeated request is always new.
        self.recovery.duplicate_budget = None;
        if replay.is_some() {
            // A replay is waiting: the line the printer asked for is the probe.
            self.transmit(self.send_cursor, now);
        } else {
            // M105s still in flight while the printer is otherwise quiet had their answers
            // lost (garbled), since a printer answers an M105 as soon as it reaches it. The
            // probe's answer must settle them too: taken for theirs, each answer would
            // settle only the oldest, every probe would add one more, and the job would
            // never move again (each probe answered, none settling the lines behind them).
            // Only those older than any M105 was seen to take: Ultimaker2Marlin answers an
            // M105 only once the moves before it have left its queue, seconds after their
            // own `ok`s; taken for lost, its late answer would confirm a later M105 the
            // printer never got.
            let patience = self.timers.m105_patience(self.opts.silence_probe);
            // While stopping, an M105 sent before the stop lines keeps its place whatever
            // its age: Ultimaker2Marlin answers it only after the moves queued before it,
            // and that answer, taken for the stop's own M105, would confirm heaters off
            // that had not run yet (seen on a loaded machine: a cancel reported as
            // confirmed before the printer had executed `M104 S0`).
            let keep_below = if self.stopping().is_some() {
                self.stop_from
            } else {
                0
            };
            // And only those the printer has certainly read (see `confirm_through`): one
            // still in its ring was not lost, it waits (Ultimaker2Marlin reads nothing
            // while a move waits for a planner block); taken for lost, its answer came
            // seconds later and was taken for a later probe's (issue 48).
            for f in self.in_flight.iter_mut() {
                if f.number >= keep_below
                    && f.bytes == 0
                    && now.saturating_duration_since(f.sent) >= patience
                {
                    f.is_m105 = false;
                }
            }
            let number = self.new_line(Kind::Housekeeping, "M105".into());
            self.transmit(number, now);
        }
    }

    /// Sends an `M105` without a number, unless one sent less than an `M105`'s patience ago
    /// still waits for its answer; `confirms`: its answer confirms the lines before it
    /// (see `Host::unnumbered_probe`).
    fn probe_unnumbered(&mut self, now: Instant, confirms: bool) {
        let patience = self.timers.m105_patience(self.opts.silence_probe);
        let due = self
            .unnumbered_probe
            .is_none_or(|(_, sent, _)| now.saturating_duration_since(sent) >= patience);
        if due {
            self.stats.probes += 1;
            self.events.push_back(Event::Probe);
            self.outgoing.extend_from_slice(UNNUMBERED_PROBE);
            // It follows the lines sent so far, not those waiting to be replayed.
            self.unnumbered_probe = Some((self.send_cursor, now, confirms));
        }
    }

    /// The host's own `M110` is the oldest line unanswered: nothing numbered goes out
    /// until it has run.
    fn counter_reset_in_flight(&self) -> bool {
        self.front_line()
            .is_some_and(|l| l.kind == Kind::Setup && is_code(&l.command, &["M110"]))
    }

    /// When to probe with M105 if nothing moves. Long commands are probed too: the M105
    /// waits in the printer's queue behind them, harmlessly, and its answer recovers an
    /// `ok` lost at their end. One probe at a time, unless its answer seems lost too.
    fn next_probe_at(&self) -> Instant {
        let probe = self.timers.probe_interval(self.opts.silence_probe);
        let mut base = self.timers.last_progress.max(self.timers.front_since) + probe;
        // A probe waits for the host's own holds (it would be held back until then).
        for t in [self.recovery.replay_after, self.recovery.resend_hold]
            .into_iter()
            .flatten()
        {
            base = base.max(t);
        }
        if let Some(settle) = &self.recovery.settle {
            base = base.max(settle.deadline());
        }
        let long_front = self.heat_at_front()
            || self
                .front_line()
                .is_some_and(|l| is_code(&l.command, &LONG_COMMANDS));
        if long_front && self.in_flight.iter().any(|f| f.is_m105) {
            // It waits behind the long command; more probes would only fill the buffer.
            return base.max(self.timers.front_since + self.opts.long_command_timeout);
        }
        match self.timers.last_probe {
            // An `M105` still waits after the last probe: its answer was lost, or taken
            // for an earlier one's whose own was lost. Once an `M105`'s usual time is
            // known, the next probe goes when that one counts as lost (see `probe`), so
            // its answer settles it: sooner, each answer would be taken for its
            // predecessor's and the newest probe would wait on; later only costs time.
            // Before, a quick probe learns it.
            Some(p) if self.in_flight.iter().any(|f| f.is_m105) => base.max(
                p + match self.timers.m105_latency {
                    Some(_) => self
                        .timers
                        .m105_patience(self.opts.silence_probe)
                        .max(probe),
                    None => probe * 3,
                },
            ),
            Some(p) => base.max(p + probe),
            None => base,
        }
    }
}
