//! How a job ends: drained to done (after a final `M105` is answered) or to a pause, and
//! the safe stop (heaters, fan and motors off) after a cancel or a failure while the
//! printer still answers.

use super::event::{Event, Failure};
use super::line::{is_code, Kind, Owed, OwedLine, HEATERS_OFF, SAFE_STOP, UNNUMBERED_PROBE};
use super::phase::{JobPhase, Phase, Stop};
use super::Host;
use std::time::{Duration, Instant};

/// How often a stop that waits for a heat-up says again how long it may take.
pub(super) const STOP_WAIT_EVERY: Duration = Duration::from_secs(5);

impl Host {
    /// Stops the job safely, whatever line the printer expects next. First, at once and
    /// without a number: an `M108` where the firmware can break a heat wait with it, then
    /// the heaters off. Marlin 2 and Ultimaker2Marlin run a line with neither `N` nor `*`
    /// unchecked (queue.cpp:458-461; Marlin_main.cpp:594-604), so these pass even when the
    /// printer's count is no longer the host's (a line that renumbered it, a lost count).
    /// Then a new count, `N<k> M110 N<k>` with `k` above any number the printer has seen
    /// from the host (a line with `M110` in it passes whatever number the printer expects:
    /// queue.cpp:463-473, Marlin_main.cpp:554), and, once that is answered, the safe-stop
    /// lines numbered from there and an `M105` whose answered report confirms them all.
    pub(super) fn begin_stop(&mut self, stop: Stop, now: Instant) {
        let cancel = matches!(stop, Stop::Cancel { .. });
        self.phase = Phase::Job(JobPhase::Stopping(stop));
        // A new episode with numbers of its own: a request for an older number then means
        // the printer rejected the M110 (see `requested_line`).
        let first = self.next_number;
        // After a cancel the printer reads the lines still in flight, in order, before the
        // stop's (Ultimaker2Marlin behind a queue of moves it works off at their speed):
        // they hold room in its ring, and their `ok`s come first. After a failure they
        // are presumed refused (flushed with an error, or counted elsewhere); waiting for
        // them could hold the stop back for good. An `M105` among them is answered either
        // way, and its answer says nothing of the stop's lines.
        let mut owed = std::mem::take(&mut self.owed);
        for f in &self.in_flight {
            let m105 = self
                .history_line(f.number)
                .is_some_and(|l| is_code(&l.command, &["M105"]));
            if cancel || m105 {
                owed.push_back(Owed {
                    bytes: if cancel { f.bytes } else { 0 },
                    what: if m105 {
                        OwedLine::M105
                    } else {
                        OwedLine::Before
                    },
                });
            }
        }
        if self.unnumbered_probe.is_some() {
            owed.push_back(Owed {
                bytes: if cancel { UNNUMBERED_PROBE.len() } else { 0 },
                what: OwedLine::M105,
            });
        }
        self.reset_numbering();
        self.owed = owed;
        self.next_number = first;
        self.send_cursor = first;
        self.stop_from = first;
        self.cautious_until = first + 2;
        let breaks = self.breaks_heat_wait();
        if breaks {
            self.send_unnumbered("M108", now);
        }
        for cmd in HEATERS_OFF {
            self.send_unnumbered(cmd, now);
        }
        self.timers.last_stop_wait = None;
        if !breaks && self.heating() {
            // Ultimaker2Marlin reads nothing while it waits for a heater: the stop runs
            // when the wait is over. Say so, and how long that may be.
            self.say_stop_waits(now);
        }
        self.pending
            .push_back((Kind::Setup, format!("M110 N{first}")));
        for cmd in SAFE_STOP {
            self.pending.push_back((Kind::SafeStop, cmd.into()));
        }
        if self.autoreport() {
            self.pending.push_back((Kind::SafeStop, "M155 S0".into()));
        }
        self.pending.push_back((Kind::Sync, "M105".into()));
        // What the last episode left in flight is gone.
        self.timers.last_progress = now;
        self.timers.last_ack = now;
        self.timers.front_since = now;
        self.pump(now);
    }

    /// A line without number or checksum, outside the send window (it is a few bytes, and
    /// the firmware takes it whatever line it expects). Its `ok`, anonymous, is not a
    /// numbered line's.
    pub(super) fn send_unnumbered(&mut self, cmd: &str, now: Instant) {
        self.outgoing.extend_from_slice(cmd.as_bytes());
        self.outgoing.push(b'\n');
        self.owed.push_back(Owed {
            bytes: cmd.len() + 1,
            what: OwedLine::Unnumbered,
        });
        if cmd == "M108" {
            self.timers.last_m108 = Some(now);
        }
    }

    /// When the stop's numbered lines, waiting for room in the ring that lines sent before
    /// them may still hold, ask with an unnumbered `M105` whether those were read (their
    /// `ok`s may have been lost, and its answer comes after all of theirs): once the
    /// printer has been quiet for a probe's interval, and again each interval while one
    /// more fits the ring.
    pub(super) fn owed_probe_at(&self) -> Option<Instant> {
        let waiting = self.stopping().is_some()
            && self.in_flight.is_empty()
            && !self.pending.is_empty()
            && !self.owed.is_empty()
            && self.probe_fits_unnumbered();
        let since = match self.timers.last_probe {
            Some(p) => p.max(self.timers.last_progress),
            None => self.timers.last_progress,
        };
        waiting.then(|| since + self.opts.silence_probe)
    }

    /// Asks, at `owed_probe_at`.
    pub(super) fn probe_owed(&mut self, now: Instant) {
        self.stats.probes += 1;
        self.events.push_back(Event::Probe);
        self.timers.last_probe = Some(now);
        self.outgoing.extend_from_slice(UNNUMBERED_PROBE);
        self.owed.push_back(Owed {
            bytes: UNNUMBERED_PROBE.len(),
            what: OwedLine::M105,
        });
    }

    /// The stop waits for a heat-up the printer does not break off: how long that may take,
    /// from the readings so far. Said when the stop begins, and again as the heater's
    /// reports come (every [`STOP_WAIT_EVERY`] at most), so the figure follows the heater.
    pub(super) fn say_stop_waits(&mut self, now: Instant) {
        self.timers.last_stop_wait = Some(now);
        let estimate = self.thermal.estimate(now, self.opts.heat_timeout);
        self.events.push_back(Event::StopWaitsForHeat(estimate));
    }

    /// Whether an unnumbered `M108` ends a heat wait on this printer: where an emergency
    /// parser takes it on arrival (`Cap:EMERGENCY_PARSER:1`, e_parser.h), and on Marlin 2
    /// without one, whose queue acts on an unnumbered `M108` as it reads it
    /// (queue.cpp:524-531) and reads the serial input during a heat wait while a command
    /// slot is free (temperature.cpp:4122 `idle()`, MarlinCore.cpp:412): the host keeps
    /// one free by sending nothing behind a heat wait. Not on Ultimaker2Marlin, which reads
    /// nothing until the wait is over (Marlin_main.cpp:1419-1460, 1472-1490).
    pub(super) fn breaks_heat_wait(&self) -> bool {
        self.emergency_parser() || self.opts.firmware.reads_serial_while_heating()
    }

    /// A failure while the printer still answers: never leave it hot (see [`Host::begin_stop`]).
    pub(super) fn fail_safely(&mut self, failure: Failure, now: Instant) {
        match &self.phase {
            Phase::Job(JobPhase::Stopping(Stop::Failure { .. })) => self.finish_stop(false),
            Phase::Job(_) => {
                let give_up = now + self.opts.stop_timeout;
                self.begin_stop(Stop::Failure { failure, give_up }, now);
            }
            _ => self.fail(failure),
        }
    }

    /// Report the failure that stopped the printer, with whether the stop was confirmed.
    pub(super) fn finish_stop(&mut self, confirmed: bool) {
        let failure = match self.stopping() {
            Some(Stop::Failure { failure, .. }) => failure.clone(),
            _ => Failure::Cancelled {
                last_acked: self.acked_job,
            },
        };
        self.events.push_back(Event::SafeStop { confirmed });
        self.fail(failure);
    }

    /// A firmware error that is not part of a resend or a halt: the printer refused
    /// something or failed at it, so the job cannot go on as the file says. Stop safely.
    pub(super) fn firmware_error(&mut self, message: String, now: Instant) {
        self.events.push_back(Event::Message(message.clone()));
        if self.in_job() && self.stopping().is_none() {
            let last_acked = self.acked_job;
            self.fail_safely(
                Failure::FirmwareError {
                    message,
                    last_acked,
                },
                now,
            );
        }
    }

    pub(super) fn fail(&mut self, failure: Failure) {
        if self.phase != Phase::Finished {
            self.phase = Phase::Finished;
            self.events.push_back(Event::Failed(failure));
        }
    }

    pub(super) fn check_progress(&mut self, now: Instant) {
        let Phase::Job(job) = &self.phase else {
            return;
        };
        // The host's own M105s (polls, probes) hold nothing back once every other line is
        // answered: where an answer was lost, each later one is taken for the M105 before
        // its own (see `handle_ok`), and waiting for the newest probe's would only send
        // probe after probe.
        let drained = self.in_flight.iter().all(|f| {
            f.m105
                && self
                    .history_line(f.number)
                    .is_some_and(|l| l.kind == Kind::Housekeeping)
        }) && self.send_cursor >= self.next_number
            && self.pending.is_empty();
        if !drained {
            return;
        }
        match job {
            JobPhase::Stopping(_) => self.finish_stop(true),
            JobPhase::Paused { synced: false, .. } => {
                // Drained of `ok`s is not drained: Ultimaker2Marlin acknowledges moves as
                // they enter its queue. An answered M105 is processed after all of them.
                self.phase = Phase::Job(JobPhase::Paused {
                    synced: true,
                    reported: false,
                });
                self.pending.push_back((Kind::Sync, "M105".into()));
                self.pump(now);
            }
            JobPhase::Paused {
                synced: true,
                reported: false,
            } => {
                self.phase = Phase::Job(JobPhase::Paused {
                    synced: true,
                    reported: true,
                });
                self.events.push_back(Event::Paused);
            }
            JobPhase::Paused { .. } => {}
            JobPhase::Streaming if self.next_job < self.job.len() => {}
            JobPhase::Streaming => {
                // Only an answered M105 proves every earlier line was accepted in order.
                // The printer stays connected between jobs: its reports stop with the job.
                self.phase = Phase::Job(JobPhase::Closing);
                if self.autoreport() {
                    self.pending
                        .push_back((Kind::Housekeeping, "M155 S0".into()));
                }
                self.pending.push_back((Kind::Sync, "M105".into()));
                self.pump(now);
            }
            JobPhase::Closing => self.finish_job(),
        }
    }

    fn finish_job(&mut self) {
        self.acked_job = self.job.len();
        self.phase = Phase::Finished;
        self.events.push_back(Event::Progress {
            acked: self.acked_job,
            total: self.job.len(),
        });
        self.events
            .push_back(Event::Done(self.stats.summary(self.job.len())));
    }
}
