//! Acting on what the printer says: each line, once classified into a [`Reply`], moves
//! the host on. An `ok` acknowledges lines (and teaches the host how long answers take),
//! a temperature report updates the heaters, an error waits a moment to show whether it
//! belongs to a resend or a halt, and a `Resend:` goes to `resend.rs`.

use super::event::{Event, Failure, Numbering};
use super::framing::{canonical, strip_framing};
use super::line::{is_code, InFlight, Kind, OwedLine, LONG_COMMANDS};
use super::phase::Phase;
use super::recovery::OkFollow;
use super::reply::{HostAction, OkReply, Reply, Report};
use super::stop::STOP_WAIT_EVERY;
use super::temperature::Temp;
use super::Host;
use crate::gcode::is_heat_wait;
use std::time::{Duration, Instant};

impl Host {
    pub(super) fn handle(&mut self, reply: Reply, now: Instant) {
        self.recovery.resend_hold = None;
        let quiet = self.settle_quiet();
        if let Some(settle) = &mut self.recovery.settle {
            // The printer is still talking: more blocks may follow.
            settle.quiet_until = now + quiet;
        }
        if self.is_owed_ok(&reply) {
            return; // the `ok` printed with the `Resend:` or the fragment's answer
        }
        if let Some((message, _)) = self.pending_error.take() {
            match reply {
                Reply::Resend(_) | Reply::LineError(_) | Reply::Fatal(_) | Reply::Error(_) => {
                    // Part of a resend or a halt, or followed by another error (which then
                    // decides: a halt's reason often comes in several lines).
                }
                _ => self.firmware_error(message, now),
            }
        }
        match reply {
            Reply::Start => self.on_start(),
            Reply::Fatal(line) => {
                let mut parts = std::mem::take(&mut self.recent_errors);
                parts.push(line);
                let message = parts.join(" / ");
                let last_acked = self.acked_job;
                self.fail(Failure::Fatal {
                    message,
                    last_acked,
                });
            }
            Reply::LineError(line) => {
                // Its `Resend:` follows on its own line.
                let lower = line.to_ascii_lowercase();
                self.recovery.number_error = lower.contains("line number is not");
                self.recovery.error_last_line = lower
                    .rsplit_once("last line:")
                    .and_then(|(_, k)| k.trim().parse().ok());
            }
            Reply::Error(line) => self.on_error(line, now),
            Reply::Resend(n) => self.handle_resend(n, now),
            Reply::Ok(ok) => {
                if let Some(report) = ok.report {
                    self.take_report(report, now);
                }
                self.handle_ok(&ok, now);
            }
            Reply::Busy(line) => {
                self.timers.last_progress = now;
                self.events.push_back(Event::Busy(line));
            }
            Reply::Wait if matches!(self.phase, Phase::Boot { .. }) => {
                // Up and idle (a NO_TIMEOUTS build says so all the time, so the link would
                // never fall quiet): greet it now.
                self.send_greeting(now);
            }
            Reply::Wait => self.on_wait(now),
            Reply::UnknownCommand(text) => self.on_unknown_command(text),
            Reply::Temperatures(report) => self.take_report(report, now),
            Reply::FirmwareName(line) => self.info.read_m115_line(&line),
            Reply::Capability(name, value) => {
                if name == "ADVANCED_OK" && value {
                    self.advanced_ok = true;
                }
                self.info.note_capability(name, value);
            }
            Reply::Action(action) => {
                self.events.push_back(Event::HostAction(action.clone()));
                match action {
                    HostAction::Cancel => self.cancel(now),
                    HostAction::Pause => self.pause(now),
                    HostAction::Resume => self.resume(now),
                    HostAction::Other(_) => {}
                }
            }
            // Settings the boot banner lists: read between jobs, where `M503` asks for them
            // (`stream::idle`); here only logged.
            Reply::Setting(line) | Reply::Other(line) => {
                self.events.push_back(Event::Message(line))
            }
        }
    }

    /// Whether `reply` is the plain `ok` the line before asked for right behind it (see
    /// [`Recovery::ok_may_follow`](super::recovery::Recovery::ok_may_follow)); learns from
    /// it, or from its absence, whether this firmware sends one after `Resend:`.
    fn is_owed_ok(&mut self, reply: &Reply) -> bool {
        let Some(follow) = self.recovery.ok_may_follow.take() else {
            return false;
        };
        let plain_ok =
            matches!(reply, Reply::Ok(ok) if !ok.text && ok.line.is_none() && !ok.advanced);
        if follow.learn {
            if plain_ok {
                self.recovery.resend_ok.seen_ok += 1;
            } else {
                self.recovery.resend_ok.seen_none += 1;
            }
        }
        plain_ok && (follow.swallow || follow.learn)
    }

    /// `start`: the board has booted.
    fn on_start(&mut self) {
        match &self.phase {
            Phase::Boot { .. } => self.phase = Phase::Boot { saw_start: true },
            Phase::Greeting => {
                // Rebooted while we greeted it: start over once it settles.
                self.reset_numbering();
                self.phase = Phase::Boot { saw_start: true };
            }
            _ => {
                // A reset switches the heaters off; the print is lost.
                let last_acked = self.acked_job;
                self.fail(Failure::PrinterReset { last_acked });
            }
        }
    }

    /// An `Error:` that is no line error by its words.
    fn on_error(&mut self, line: String, now: Instant) {
        self.recent_errors.push(line.clone());
        if self.recent_errors.len() > 4 {
            self.recent_errors.remove(0);
        }
        if line
            .to_ascii_lowercase()
            .contains("no line number with checksum")
        {
            // Ultimaker2Marlin on the tail of a line cut by a buffer flush (it has
            // a `*` but no `N`): neither `Resend:` nor `ok` follows.
            self.stats.fragments += 1;
            self.events.push_back(Event::Fragment(line));
        } else if self.in_job() && self.stopping().is_none() {
            // Decided by the next line, or after a moment of silence.
            self.pending_error = Some((line, now + self.opts.resend_ok_wait));
        } else {
            self.events.push_back(Event::Message(line));
        }
    }

    /// `wait`: the printer's queue is empty. Lines still believed in flight had their
    /// `ok`s lost (or are still on the wire): probe at once, never treat it as a sign of
    /// life.
    fn on_wait(&mut self, now: Instant) {
        // At most one probe a second: `wait` comes often, and a probe's answer
        // takes a moment.
        let spacing = (self.opts.silence_probe / 2).min(Duration::from_secs(1));
        let recent_probe = self
            .timers
            .last_probe
            .is_some_and(|p| now.saturating_duration_since(p) < spacing);
        if self.in_job() && !self.in_flight.is_empty() && !recent_probe {
            self.probe(now);
        }
    }

    /// `Unknown command: "..."`: a line of ours the firmware does not know, or the piece of
    /// a line cut by a buffer flush.
    fn on_unknown_command(&mut self, text: String) {
        // Some firmware quotes the whole line, number and checksum included.
        let command = strip_framing(&text);
        // Compared as the printer reads them: the cut-line guard may have
        // written the line with an extra space or trailing zeros.
        let command = canonical(command);
        let ours = self.in_flight.iter().any(|f| {
            self.history_line(f.number)
                .is_some_and(|l| canonical(&l.command).eq_ignore_ascii_case(&command))
        });
        if ours {
            self.events
                .push_back(Event::Message(format!("Unknown command: \"{text}\"")));
        } else {
            // Not a line we sent: the piece of a line cut by a buffer flush. Its
            // `ok` (plain in builds without ADVANCED_OK) answers no line of ours.
            self.stats.fragments += 1;
            if !self.advanced_ok {
                self.recovery.ok_may_follow = Some(OkFollow {
                    swallow: true,
                    learn: false,
                });
            }
            self.events.push_back(Event::Fragment(text));
        }
    }

    /// Take a temperature report: a reading without a target (Ultimaker2Marlin's
    /// `T:210.0 E:0 W:?`) keeps the target known before. During a heat wait, note when the
    /// temperature last came closer to its target.
    fn take_report(&mut self, report: Report, now: Instant) {
        self.thermal.take(report.temperatures, report.waiting, now);
        self.events
            .push_back(Event::Temperatures(self.thermal.temps));
        // A stop that said it waits for the heat-up (`begin_stop`) says so again.
        let said = self.timers.last_stop_wait;
        if self.stopping().is_some()
            && self.heating()
            && said.is_some_and(|t| now.saturating_duration_since(t) >= STOP_WAIT_EVERY)
        {
            self.say_stop_waits(now);
        }
        if report.waiting && self.stopping().is_some() && self.breaks_heat_wait() {
            // A heat wait began after the stop's M108 was read (it waited behind another
            // command): an M108 read before the wait starts is lost, as the wait sets its
            // flag anew (temperature.cpp:4097). Break this one too, once a second at most.
            let due = self
                .timers
                .last_m108
                .is_none_or(|t| now.saturating_duration_since(t) >= Duration::from_secs(1));
            if due {
                self.send_unnumbered("M108", now);
            }
        }
    }

    fn handle_ok(&mut self, ok: &OkReply, now: Instant) {
        self.timers.last_progress = now;
        // Any `ok` ends a heat wait's reports: the printer reads commands again.
        if std::mem::take(&mut self.thermal.heat_reported) {
            // The first `ok` after the in-wait reports: the printer read nothing while it
            // waited, so this is the heat command's own.
            self.thermal.heat = None;
        }
        if ok.text && self.settle_owed_m105() {
            // The answer of an M105 sent before the stop's count began: it says nothing of
            // the stop's lines, which the printer runs after it.
            return;
        }
        if ok.text {
            if let Some((before, _, confirms)) = self.unnumbered_probe.take() {
                // The answer of the M105 sent without a number: the printer ran it after
                // every line sent before it, and only those.
                self.owed.clear();
                match before.checked_sub(1) {
                    Some(last) if confirms => {
                        self.confirm_through(last);
                        self.ack_through(last, now);
                    }
                    Some(last) => {
                        // Asked after a long wait without answers: the printer read those
                        // lines, but may have refused some (their resend requests lost
                        // too), so none is confirmed. Their bytes are off its ring, and
                        // their `M105`s are answered no more: a numbered probe now fits,
                        // and its answer, or a resend request, tells the rest.
                        self.read_through(last);
                        for f in self.in_flight.iter_mut().filter(|f| f.number <= last) {
                            f.is_m105 = false;
                        }
                    }
                    None => {}
                }
                // During a stop, after the stop's own unnumbered heaters-off lines too (a
                // probe from before the stop is answered as a stale one, above).
                let off = |t: Option<Temp>| t.is_some_and(|t| t.target == Some(0.0));
                let heaters_off = ok
                    .report
                    .as_ref()
                    .is_some_and(|r| off(r.temperatures.hotend) && off(r.temperatures.bed));
                if self.stopping().is_some() && heaters_off {
                    self.events.push_back(Event::HeatersOff);
                }
                return;
            }
            // The answer of an M105 (only it carries text, whether or not the temperatures
            // in it could be read): the printer processed it after every earlier line.
            // Printers run M105s in the order sent, so it is the oldest unanswered one's,
            // or a later one's where an earlier answer was lost. It is taken for the
            // oldest one's still awaited, skipping those a probe took for lost (else,
            // after one lost answer, each answer would settle the M105 before its own and
            // the job would never move again). But the printer has certainly run only the
            // oldest M105 whose answer may still come: only that far are lines confirmed.
            // Ultimaker2Marlin, blocked by a long move, answers probes taken for lost
            // seconds later: taken for a later probe's answer, one confirmed that probe
            // while it still waited unread in the ring, and a resend request for it was
            // taken for a printer that had lost its state (issue 48).
            let oldest = self.oldest_m105();
            if let Some(pos) = self.in_flight.iter().position(|f| f.is_m105) {
                let number = self.in_flight[pos].number;
                // Every `ok` owed by an earlier `Resend:` or fragment came before this one:
                // a debt still open was a guess that went wrong.
                self.owed.clear();
                self.confirm_through(oldest.unwrap_or(number).min(number));
                self.ack_through(number, now);
                return;
            }
            // No M105 awaits an answer: this is the late answer of one a probe took for
            // lost. Taken for a move's `ok`, it counted a line out of the printer's ring
            // that was still in it (issue 48: a clean link overran Ultimaker2Marlin's).
            if let Some(oldest) = oldest {
                self.confirm_through(oldest);
                if let Some(pos) = self.in_flight.iter().position(|f| f.number == oldest) {
                    let f = self.in_flight.remove(pos).expect("position is valid");
                    self.in_flight_bytes -= f.bytes;
                    self.acknowledged(f, now, false);
                }
            }
            return;
        }
        if let Some(n) = ok.line {
            self.advanced_ok = true;
            if self.stopping().is_some() && n < self.stop_from {
                // A line sent before the stop's count began.
                self.settle_owed_ok(&[OwedLine::Before]);
            }
            if n < self.next_number {
                self.confirm_through(n);
                self.ack_through(n, now);
            } else if self.stopping().is_none() && self.in_job() {
                // An answer for a line the host never sent: the printer counts from
                // elsewhere (a line that set its count was answered with its own number).
                if self.unexplained_answer() {
                    let what = Numbering::NoAdvance {
                        refusals: self.recovery.unexplained,
                        sent: self.next_number.saturating_sub(1),
                    };
                    self.numbering_lost(what, now);
                }
            }
            return;
        }
        if ok.advanced && self.settle_owed_ok(&[OwedLine::Unnumbered]) {
            // A line of the host's own without a number (a stop's heaters off).
            return;
        }
        if ok.advanced {
            // ADVANCED_OK answer without a number: it answered a line that had none, the
            // tail of a line cut by a receive-buffer flush, which the firmware executed.
            self.stats.fragments += 1;
            self.events.push_back(Event::Fragment(
                "a line without a number was executed".into(),
            ));
            return;
        }
        if self.advanced_ok {
            // A plain `ok` in an ADVANCED_OK build is the one after `Resend:`.
            return;
        }
        if self.settle_owed_ok(&[OwedLine::Before, OwedLine::Unnumbered]) {
            // A line sent before the stop's count began, or one without a number.
            return;
        }
        // A plain `ok` answers the oldest line, but never an `M105`: its answer carries the
        // temperatures. Ultimaker2Marlin answers moves as they enter its queue and an
        // `M105` only when it runs, so the `ok`s of moves sent after an `M105` come before
        // its answer; taken for the `M105`'s, they left its answer to be taken for a later
        // `M105`'s, which the printer may never have received (a corrupted line), and the
        // resend that followed looked like a printer that had lost its state. There, too,
        // an `M105` a probe took for lost is still owed its answer, which comes only when
        // it runs; where `ok`s come in line order, a later line's says it came and went.
        let in_order = !self.opts.firmware.acks_moves_on_entry();
        if let Some(pos) = self
            .in_flight
            .iter()
            .position(|f| !f.sync && !f.is_m105 && (in_order || !f.m105))
        {
            let f = self.in_flight.remove(pos).expect("position is valid");
            self.in_flight_bytes -= f.bytes;
            self.acknowledged(f, now, true);
        } else if let Some(f) = self.in_flight.pop_front() {
            // Only `M105`s are waiting: this `ok` is the oldest one's, whatever became of its
            // text (a firmware that answers a bare `ok`, a report garbled on the wire).
            // Progress never waits on reading the optional part of a reply.
            self.in_flight_bytes -= f.bytes;
            self.acknowledged(f, now, true);
        }
    }

    /// Every line up to `number` is acknowledged. An `M105` among them not yet confirmed
    /// may still be answered (see `handle_ok`): it is kept among the unsettled until a
    /// confirmation passes it.
    fn ack_through(&mut self, number: u64, now: Instant) {
        while self.in_flight.front().is_some_and(|f| f.number <= number) {
            let f = self.in_flight.pop_front().expect("front exists");
            self.in_flight_bytes -= f.bytes;
            if f.m105 && self.confirmed.is_none_or(|c| f.number > c) {
                self.unsettled_m105s.push_back(f.number);
            }
            let own = f.number == number;
            self.acknowledged(f, now, own);
        }
        if self
            .thermal
            .heat
            .as_ref()
            .is_some_and(|h| h.number < number)
        {
            self.thermal.heat = None; // a later line was answered: the wait is over
        }
    }

    /// `own`: by its own answer, not settled by a later line's (whose wait says nothing
    /// about this line's).
    fn acknowledged(&mut self, f: InFlight, now: Instant, own: bool) {
        let number = f.number;
        let waited = now.saturating_duration_since(self.timers.front_since);
        // A line settled by a probe's answer waited for the probe, not for the printer:
        // taken into the averages, each lost `ok` would make the next one slower to find
        // (seen on the real Marlin: probes a second apart after a few lost `ok`s).
        if own {
            // An `M105` answered while a later `M105` is in flight may have had its own
            // answer lost, and this be the later one's: its wait is then the time until the
            // next probe. It paces no probe (seen on the real Marlin: one such sample
            // doubled the round trip, and the next probe came 1.2 s after the printer had
            // answered), and tells how long an `M105` may take only while nothing else does
            // (erring long there costs a probe; short, a false confirmation).
            let ambiguous = f.is_m105 && self.in_flight.iter().any(|g| g.is_m105);
            let long = self
                .history_line(number)
                .is_some_and(|l| is_code(&l.command, &LONG_COMMANDS) || is_heat_wait(&l.command));
            let sample = now.saturating_duration_since(f.sent);
            self.timers
                .learn(waited, sample, f.is_m105, ambiguous, long);
        }
        self.timers.front_since = now;
        self.timers.last_ack = now;
        self.recovery.unexplained = 0;
        if !self.opts.firmware.acks_moves_on_entry()
            && self
                .thermal
                .heat
                .as_ref()
                .is_some_and(|h| h.number == number)
        {
            self.thermal.heat = None; // `ok`s in line order: this is the heat command's own
        }
        // A successful answer after the requested line ends a resend episode.
        if let Some((line, _, _)) = self.recovery.repeated {
            if number >= line {
                self.recovery.repeated = None;
            }
        }
        let Some(line) = self.history_line(number) else {
            return;
        };
        match (&self.phase, line.kind) {
            (_, Kind::Job(idx)) if idx + 1 > self.acked_job => {
                self.acked_job = idx + 1;
                let total = self.job.len();
                self.events.push_back(Event::Progress {
                    acked: self.acked_job,
                    total,
                });
                if self.opts.firmware.progress_m73() && self.accepting_job_lines() {
                    let percent = self.acked_job * 100 / total.max(1);
                    if self.last_m73 != Some(percent) && percent < 100 {
                        self.last_m73 = Some(percent);
                        self.pending
                            .push_back((Kind::Housekeeping, format!("M73 P{percent}")));
                    }
                }
            }
            (Phase::Greeting, Kind::Setup) if line.command == "M115" => {
                self.phase = Phase::Idle;
                self.events.push_back(Event::Connected(self.info.clone()));
            }
            _ => {}
        }
    }
}
