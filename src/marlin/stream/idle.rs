//! An idle printer between jobs: what it says is logged, and its temperatures are read
//! with `M105`s that never touch the next job's line numbering.

use super::error::describe_temps;
use crate::marlin::protocol::reply::{Reply, Report};
use crate::marlin::protocol::{ProtocolOptions, Temp, Temperatures};
use std::path::Path;
use std::time::Duration;

/// What `Connection::idle_for` saw.
#[derive(Debug, Clone, PartialEq)]
pub(crate) enum Idle {
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
/// unanswered one. Its `ok` must never be taken for a job line's: a job begins only once
/// every such answer is in (`Connection::print` waits for them), or is known lost.
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
}

/// What a chunk of idle talk held.
#[derive(Debug, Default)]
pub(super) struct Heard {
    pub(super) rebooted: bool,
    pub(super) report: bool,
    /// The firmware's halt message.
    pub(super) halted: Option<String>,
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
        }
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
