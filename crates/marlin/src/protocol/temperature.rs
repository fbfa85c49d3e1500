//! Temperatures: the printer's readings, and the heat wait (M109/M190) it may be inside,
//! with when it last came closer to its target.

use super::line::is_code;
use serde::Serialize;
use std::time::{Duration, Instant};

/// One heater's reading.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Default)]
pub struct Temp {
    pub current: f64,
    pub target: Option<f64>,
}

#[derive(Debug, Clone, Copy, PartialEq, Serialize, Default)]
pub struct Temperatures {
    pub hotend: Option<Temp>,
    pub bed: Option<Temp>,
}

/// An M109/M190 the printer may still be working on. Tracked apart from the order of `ok`s,
/// which Ultimaker2Marlin does not keep (it acknowledges moves queued behind the heat
/// command before the heat command ends).
#[derive(Debug, Clone)]
pub(super) struct HeatWait {
    pub(super) number: u64,
    pub(super) command: String,
    pub(super) bed: bool,
    /// `S`/`R` of the command.
    pub(super) target: Option<f64>,
    pub(super) since: Instant,
    /// The closest distance to the target seen so far, and when.
    pub(super) best: Option<(f64, Instant)>,
    /// The first distance to the target seen during the wait, and when: with the latest,
    /// how fast the heater closes in.
    pub(super) first: Option<(f64, Instant)>,
    /// The latest distance to the target, and when.
    pub(super) latest: Option<(f64, Instant)>,
}

/// What a stop that waits for a heat-up waits for: the heat wait, where its heater is and
/// must get to, and how long that may take. Figures, for the log and the printer's status.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct HeatWaitEstimate {
    /// The command the printer waits in (`M109 S210`), where the host sent it.
    pub command: Option<String>,
    /// The bed's heater (`M190`), else the hotend's.
    pub bed: bool,
    pub current: Option<f64>,
    pub target: Option<f64>,
    /// At the rate the heater has closed in so far; `None` before it was seen to.
    pub remaining: Option<Duration>,
    /// The longest the host waits for it: until the heater has not come closer to its
    /// target for the heat timeout.
    pub limit: Duration,
}

impl HeatWait {
    /// A heat command (`M109`/`M190`, and kin) sent as line `number` at `now`.
    pub(super) fn new(number: u64, command: String, now: Instant) -> Self {
        let words: Vec<&str> = command.split_whitespace().collect();
        let target = words[1..]
            .iter()
            .find_map(|w| w.strip_prefix(['S', 'R', 's', 'r']))
            .and_then(|v| v.parse::<f64>().ok());
        HeatWait {
            number,
            bed: is_code(&command, &["M190"]),
            command,
            target,
            since: now,
            best: None,
            first: None,
            latest: None,
        }
    }
}

/// What the host knows of the heaters: the last readings, whether the printer reports a
/// heat wait, and the heat wait a command of ours started.
#[derive(Debug, Default)]
pub(super) struct Thermal {
    pub(super) temps: Temperatures,
    /// The printer reports `W:` (inside an M109/M190 wait) and has not answered since.
    pub(super) heat_reported: bool,
    pub(super) heat: Option<HeatWait>,
}

impl Thermal {
    /// Take a temperature report: a reading without a target (Ultimaker2Marlin's
    /// `T:210.0 E:0 W:?`) keeps the target known before. During a heat wait, note when the
    /// temperature last came closer to its target. `waiting`: the report has `W:`.
    pub(super) fn take(&mut self, reading: Temperatures, waiting: bool, now: Instant) {
        let merge = |old: Option<Temp>, new: Option<Temp>| match (old, new) {
            (Some(old), Some(new)) => Some(Temp {
                current: new.current,
                target: new.target.or(old.target),
            }),
            (old, new) => new.or(old),
        };
        self.temps.hotend = merge(self.temps.hotend, reading.hotend);
        self.temps.bed = merge(self.temps.bed, reading.bed);
        self.heat_reported = waiting;
        if let Some(heat) = &mut self.heat {
            let reading = if heat.bed {
                self.temps.bed
            } else {
                self.temps.hotend
            };
            if let Some(reading) = reading {
                if let Some(target) = heat.target.or(reading.target) {
                    // Progress is coming closer to the target: rising for a heat-up,
                    // falling for a cool-down (`M190 R30`).
                    let gap = (target - reading.current).abs();
                    heat.first.get_or_insert((gap, now));
                    heat.latest = Some((gap, now));
                    match heat.best {
                        Some((best, _)) if gap > best - 0.5 => {}
                        _ => heat.best = Some((gap, now)),
                    }
                    if gap <= 2.0 && !waiting {
                        // There, and the printer no longer reports a wait.
                        self.heat = None;
                    }
                }
            }
        }
    }

    /// How long the heat wait the printer is in may last: at the rate its heater has
    /// closed in on the target so far, and at most until the host's heat timeout.
    pub(super) fn estimate(&self, now: Instant, heat_timeout: Duration) -> HeatWaitEstimate {
        let heat = self.heat.as_ref();
        let bed = heat.is_some_and(|h| h.bed);
        let reading = if bed {
            self.temps.bed
        } else {
            self.temps.hotend
        };
        let remaining = heat.and_then(|h| {
            let ((g0, t0), (g1, t1)) = (h.first?, h.latest?);
            let rate = (g0 - g1) / t1.saturating_duration_since(t0).as_secs_f64();
            (rate > 0.01).then(|| Duration::from_secs_f64((g1 / rate).min(1e6)))
        });
        let limit = self
            .deadline(heat_timeout)
            .map_or(heat_timeout, |d| d.saturating_duration_since(now));
        HeatWaitEstimate {
            command: heat.map(|h| h.command.clone()),
            bed,
            current: reading.map(|r| r.current),
            target: heat
                .and_then(|h| h.target)
                .or(reading.and_then(|r| r.target)),
            remaining,
            limit,
        }
    }

    /// When a heat wait times out: `heat_timeout` after it started or after its
    /// temperature last came closer to the target, whichever is later.
    pub(super) fn deadline(&self, heat_timeout: Duration) -> Option<Instant> {
        let heat = self.heat.as_ref()?;
        let progress = heat.best.map_or(heat.since, |(_, at)| at.max(heat.since));
        Some(progress + heat_timeout)
    }
}
