//! How a job ends: drained to done (after a final `M105` is answered) or to a pause, and
//! the safe stop (heaters, fan and motors off) after a cancel or a failure while the
//! printer still answers.

use super::event::{Event, Failure};
use super::line::{Kind, SAFE_STOP};
use super::phase::{JobPhase, Phase, Stop};
use super::Host;
use std::time::Instant;

impl Host {
    /// M108 (breaking a heat wait where the firmware can), then heaters, fan and motors off,
    /// autoreport off, and an `M105` whose answer confirms them all.
    pub(super) fn queue_safe_stop(&mut self, now: Instant) {
        self.stop_from = self.next_number;
        self.pending
            .retain(|(kind, _)| matches!(kind, Kind::SafeStop | Kind::Setup));
        let failure = matches!(self.stopping(), Some(Stop::Failure { .. }));
        if self.emergency_parser() && !failure {
            if self.pending.is_empty() {
                // Numbered, outside the window: the emergency parser acts on it on arrival
                // (breaking an M109/M190 wait), and the queue then acknowledges it in order.
                let number = self.new_line(Kind::SafeStop, "M108".into());
                if self.send_cursor == number {
                    self.transmit(number, now);
                }
            } else {
                self.pending.push_back((Kind::SafeStop, "M108".into()));
            }
        }
        for cmd in SAFE_STOP {
            self.pending.push_back((Kind::SafeStop, cmd.into()));
        }
        if self.autoreport() {
            self.pending.push_back((Kind::SafeStop, "M155 S0".into()));
        }
        self.pending.push_back((Kind::Sync, "M105".into()));
    }

    /// A failure while the printer still answers: never leave it hot. The printer's line
    /// counter is reset (`M110`), whatever it expected, and the safe-stop lines follow.
    pub(super) fn fail_safely(&mut self, failure: Failure, now: Instant) {
        match &self.phase {
            Phase::Job(JobPhase::Stopping(Stop::Failure { .. })) => self.finish_stop(false),
            Phase::Job(_) => {
                let give_up = now + self.opts.stop_timeout;
                self.phase = Phase::Job(JobPhase::Stopping(Stop::Failure { failure, give_up }));
                // A new episode with numbers of its own, above any the printer has seen:
                // `N<k> M110 N<k>` passes whatever it expects, and a request for an older
                // number then means it rejected the M110 (see `handle_resend`).
                let first = self.next_number;
                self.reset_numbering();
                self.next_number = first;
                self.send_cursor = first;
                self.cautious_until = first + 2;
                self.pending
                    .push_back((Kind::Setup, format!("M110 N{first}")));
                if self.emergency_parser() {
                    // Break a heat wait the printer may be stuck in; without a number, so it
                    // needs no place in the sequence (the emergency parser acts on arrival;
                    // the queue later runs it as an unnumbered command and says `ok`).
                    self.outgoing.extend_from_slice(b"M108\n");
                    if !self.advanced_ok {
                        self.swallow_oks += 1;
                    }
                }
                // A new episode: what the last one left in flight is gone.
                self.timers.last_progress = now;
                self.timers.last_ack = now;
                self.timers.front_since = now;
                self.queue_safe_stop(now);
                self.pump(now);
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
        let drained = self.in_flight.is_empty()
            && self.send_cursor >= self.next_number
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
