//! An idle printer between jobs: what it says is logged, and its temperatures are read
//! with `M105`s that never touch the next job's line numbering.

use super::error::describe_temps;
use crate::protocol::reply::{Reply, Report};
use crate::protocol::{ProtocolOptions, Temp, Temperatures};
use std::path::Path;
use std::time::Duration;

/// What `Connection::idle_for` saw.
#[derive(Debug, Clone, PartialEq)]
pub enum Idle {
    /// Nothing that needs acting on (reports and messages are logged).
    Quiet,
    /// The printer said `start`: it was reset or power-cycled. The next job begins with a
    /// fresh handshake and line numbering.
    Rebooted,
    /// A temperature report: the hotend and bed as read now (a heater the report left out
    /// keeps its last reading).
    Temperatures(Temperatures),
    /// No temperature report for [`IdleWatch::stale_after`] although the printer was
    /// asked: the last figures are no longer current.
    Silent,
    /// The firmware said it halted (`Error:Printer halted. kill() called!`, a thermal
    /// error): it takes nothing more until it is reset.
    Halted(String),
}

/// Reading an idle printer between jobs. Its temperatures are asked for with an `M105`
/// every `temperature_interval`, sent without a line number: Marlin checks nothing on a
/// line without `N` and does not count it, so the line numbering of the next job is not
/// touched, and every firmware crispen speaks (Ultimaker2Marlin has no `M155`) answers it
/// with `ok T:.. /.. B:.. /..`. One is in flight at a time; an `ok` answers the oldest
/// unanswered one. Its `ok` must never be taken for a job line's: a job begins only after
/// the sync line's answer (see [`sync_line`]), which comes after every earlier one.
#[derive(Debug)]
pub(super) struct IdleWatch {
    /// An unfinished line of what the printer said.
    pub(super) partial: Vec<u8>,
    /// `M105`s sent whose `ok` has not come.
    pub(super) unanswered: u32,
    pub(super) last_sent: Option<tokio::time::Instant>,
    pub(super) next_poll: tokio::time::Instant,
    /// The last busy keep-alive or heat-wait report: the printer is inside a long command
    /// of its own (from its menu) and answers later.
    pub(super) alive_at: Option<tokio::time::Instant>,
    pub(super) temperatures: Temperatures,
    pub(super) last_report: Option<tokio::time::Instant>,
    /// [`Idle::Silent`] was returned since the last report.
    pub(super) silent: bool,
    /// The planner's settings as the printer last reported them (`M503`, or its boot
    /// banner), one line per command (`M203 X300.00 ...`), the latest of each.
    pub(super) settings: Vec<String>,
    /// The sync line on its way, if any.
    sync: Option<Sync>,
    /// The number the next sync line carries.
    next_token: u32,
}

/// A sync line sent and not yet answered.
#[derive(Debug)]
struct Sync {
    token: u32,
    sent: tokio::time::Instant,
    /// Its echo came: the next `ok` is its own.
    echoed: bool,
}

/// A line that no Marlin takes for a command (no `G`, `M` or `T` word, no `N`, `*`, `:` or
/// `;`, all lower case): every firmware crispen speaks answers it `echo:Unknown command:
/// "crispen sync 7"` and `ok` (seen on Marlin 2.1.2.1 and Ultimaker2Marlin), after the
/// answers to every command sent before it, as it answers every command that is not a
/// move in order. Its echo names it, which no count of `ok`s can: an idle `M105` or
/// `M503` answered later than the host waited was taken for lost, and its `ok` then for
/// the job's first line's (and every later `ok` for the line before its own).
pub(super) fn sync_line(token: u32) -> String {
    format!("crispen sync {token}")
}

/// What a chunk of idle talk held.
#[derive(Debug, Default)]
pub(super) struct Heard {
    pub(super) rebooted: bool,
    pub(super) report: bool,
    /// The firmware's halt message.
    pub(super) halted: Option<String>,
    /// The sync line was answered: nothing sent before it is still to be answered.
    pub(super) synced: bool,
}

impl IdleWatch {
    pub(super) fn new() -> IdleWatch {
        IdleWatch {
            partial: Vec::new(),
            unanswered: 0,
            last_sent: None,
            next_poll: tokio::time::Instant::now(),
            alive_at: None,
            temperatures: Temperatures::default(),
            last_report: None,
            silent: false,
            settings: Vec::new(),
            sync: None,
            next_token: 1,
        }
    }

    /// A new sync line to send (see [`sync_line`]), with a number of its own: the answer to
    /// an earlier one, if it comes after all, is passed over.
    pub(super) fn begin_sync(&mut self, now: tokio::time::Instant) -> Vec<u8> {
        let token = self.next_token;
        self.next_token = self.next_token.wrapping_add(1);
        self.sync = Some(Sync {
            token,
            sent: now,
            echoed: false,
        });
        format!("{}\n", sync_line(token)).into_bytes()
    }

    /// When the sync line on its way is taken as lost, as an `M105` is (see
    /// [`IdleWatch::answer_deadline`]).
    pub(super) fn sync_deadline(&self, wait: Duration) -> Option<tokio::time::Instant> {
        let sync = self.sync.as_ref()?;
        Some(Some(sync.sent).max(self.alive_at)? + wait)
    }

    /// After this, an `M105` still unanswered is taken as lost: an idle printer answers at
    /// once, and one busy with a command of its own says so (`busy:` every 2 s, or heat
    /// reports every second).
    pub(super) fn answer_deadline(&self, wait: Duration) -> Option<tokio::time::Instant> {
        let since = self.last_sent.max(self.alive_at)?;
        (self.unanswered > 0).then_some(since + wait)
    }

    /// Figures older than this (since the last report) are not shown as current.
    pub(super) fn stale_after(opts: &ProtocolOptions) -> Duration {
        opts.temperature_interval * 3 + opts.silence_probe
    }

    /// Splits `bytes` into lines (keeping an unfinished one), logs each, and takes the
    /// answers and reports among them.
    pub(super) fn hear(&mut self, port: &Path, bytes: &[u8], now: tokio::time::Instant) -> Heard {
        let mut heard = Heard::default();
        for &b in bytes {
            if b != b'\n' {
                if self.partial.len() < 4096 {
                    self.partial.push(b);
                }
                continue;
            }
            let Some(reply) = Reply::parse(&std::mem::take(&mut self.partial)) else {
                continue;
            };
            match reply {
                Reply::Start => {
                    heard.rebooted = true;
                    // A reset forgets what it was asked.
                    self.unanswered = 0;
                    tracing::warn!(port = %port.display(), "printer rebooted while idle (it said `start`)");
                }
                Reply::Ok(_) if self.sync.as_ref().is_some_and(|s| s.echoed) => {
                    self.sync = None;
                    self.unanswered = 0;
                    heard.synced = true;
                }
                Reply::UnknownCommand(text) => match &mut self.sync {
                    Some(sync) if text == sync_line(sync.token) => sync.echoed = true,
                    // An earlier sync line's echo, or a command of someone else's.
                    _ => {
                        tracing::info!(port = %port.display(), "idle printer: unknown command {text:?}")
                    }
                },
                Reply::Ok(ok) => {
                    self.unanswered = self.unanswered.saturating_sub(1);
                    if let Some(report) = ok.report {
                        self.take(report, now);
                        heard.report = true;
                    }
                }
                Reply::Temperatures(report) => {
                    if report.waiting {
                        self.alive_at = Some(now);
                    }
                    self.take(report, now);
                    heard.report = true;
                }
                Reply::Busy(line) => {
                    self.alive_at = Some(now);
                    tracing::debug!(port = %port.display(), "idle printer: {line}");
                }
                Reply::Setting(line) => {
                    tracing::debug!(port = %port.display(), "idle printer's setting: {line}");
                    let code = line.split_whitespace().next().unwrap_or("").to_string();
                    self.settings
                        .retain(|s| s.split_whitespace().next() != Some(code.as_str()));
                    self.settings.push(line);
                }
                Reply::Fatal(line) => {
                    tracing::error!(port = %port.display(), "idle printer halted: {line}");
                    heard.halted = Some(line);
                }
                Reply::Error(line) => {
                    tracing::warn!(port = %port.display(), "idle printer: {line}")
                }
                Reply::Action(action) => {
                    // No job to act on: the printer's own menu was used between jobs.
                    tracing::info!(port = %port.display(), ?action, "idle printer asked the host to act; no job is running")
                }
                // NO_TIMEOUTS builds say `wait` every few seconds while idle.
                Reply::Wait => tracing::trace!(port = %port.display(), "idle printer: wait"),
                other => tracing::info!(port = %port.display(), "idle printer: {other:?}"),
            }
        }
        if heard.report {
            tracing::debug!(port = %port.display(), "idle printer: {}", describe_temps(&self.temperatures));
        }
        heard
    }

    fn take(&mut self, report: Report, now: tokio::time::Instant) {
        let merge = |old: Option<Temp>, new: Option<Temp>| match (old, new) {
            (Some(old), Some(new)) => Some(Temp {
                current: new.current,
                target: new.target.or(old.target),
            }),
            (old, new) => new.or(old),
        };
        let t = report.temperatures;
        self.temperatures = Temperatures {
            hotend: merge(self.temperatures.hotend, t.hotend),
            bed: merge(self.temperatures.bed, t.bed),
        };
        self.last_report = Some(now);
        self.silent = false;
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::reader;

    /// What a starved printer says once it gets to answer: a late `M503` (its settings and
    /// `ok`), the first sync line (given up on), then the second.
    const LATE: &[u8] = b"echo:  M203 X300.00 Y300.00 Z40.00 E45.00\nok\n\
        echo:Unknown command: \"crispen sync 1\"\nok\n\
        echo:Unknown command: \"crispen sync 2\"\nok\n";

    fn hear_all(watch: &mut IdleWatch, chunks: &[&[u8]]) -> Vec<bool> {
        let now = tokio::time::Instant::now();
        chunks
            .iter()
            .map(|c| watch.hear(Path::new("/dev/test"), c, now).synced)
            .collect()
    }

    #[test]
    fn only_the_latest_sync_lines_own_ok_syncs_whatever_the_split() {
        for cut in 0..=LATE.len() {
            for second_cut in cut..=LATE.len() {
                let mut watch = IdleWatch::new();
                let now = tokio::time::Instant::now();
                watch.begin_sync(now);
                watch.begin_sync(now);
                let (a, rest) = LATE.split_at(cut);
                let (b, c) = rest.split_at(second_cut - cut);
                let synced = hear_all(&mut watch, &[a, b, c]);
                // Synced by the chunk holding the last byte, and by no earlier one.
                let last = if !c.is_empty() {
                    2
                } else if !b.is_empty() {
                    1
                } else {
                    0
                };
                let expected: Vec<bool> = (0..3).map(|i| i == last).collect();
                assert_eq!(synced, expected, "cut at {cut} and {second_cut}");
                assert_eq!(watch.settings, ["M203 X300.00 Y300.00 Z40.00 E45.00"]);
            }
        }
    }

    #[test]
    fn an_ok_before_the_echo_or_after_a_garbled_one_does_not_sync() {
        let mut watch = IdleWatch::new();
        watch.begin_sync(tokio::time::Instant::now());
        let heard = hear_all(
            &mut watch,
            &[
                b"ok T:20.0 /0.0 B:20.0 /0.0\n",
                b"echo:Unknown command: \"crispen synd 1\"\nok\n",
                b"echo:Unknown command: \"crispen sync 11\"\nok\n",
                b"echo:Unknown command: \"crispen sync 1\"\n",
                b"ok\n",
                b"ok\n",
            ],
        );
        assert_eq!(heard, [false, false, false, false, true, false]);
    }

    #[test]
    fn a_sync_line_is_no_command_to_either_firmware() {
        for token in [0, 1, 7, 4_294_967_295] {
            let line = sync_line(token);
            assert_eq!(reader::marlin2::read(&line).command, None, "{line}");
            assert_eq!(reader::ultimaker2::read(&line).command, None, "{line}");
        }
    }

    #[test]
    fn a_busy_printer_extends_the_wait_for_the_sync_line() {
        let mut watch = IdleWatch::new();
        let sent = tokio::time::Instant::now();
        let wait = Duration::from_secs(3);
        assert_eq!(watch.sync_deadline(wait), None);
        watch.begin_sync(sent);
        assert_eq!(watch.sync_deadline(wait), Some(sent + wait));
        let later = sent + Duration::from_secs(2);
        watch.hear(Path::new("/dev/test"), b"echo:busy: processing\n", later);
        assert_eq!(watch.sync_deadline(wait), Some(later + wait));
    }
}
