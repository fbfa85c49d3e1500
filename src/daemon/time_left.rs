//! A print's time left, and what it rests on: the planner's estimate of the commands not
//! yet acknowledged (`marlin::estimate`, with the printer's own settings where it reported
//! them), corrected by the printer's own pace on its earlier prints (what its stepper took
//! per step beyond the planner's time), with the heat-up apart (a heater's time is the
//! heater's, not the planner's).
//!
//! Why per step and not a factor on the time: what a printer's stepper adds to its
//! planner goes by the interrupts it runs, one a step. Marlin 2.1.2.1's Linux build, whose
//! step timer is re-armed after each interrupt has run (HAL/LINUX/hardware/Timer.cpp,
//! `Timer::setCompare`: only an interrupt shorter than 1 µs is discounted), ran long fast
//! travels 6 % to 18 % slower than planned (by the machine's load) and Spot 3 %: the same
//! 6 to 20 µs a step. A factor taken from one kind of print is wrong for the other.

use serde::{Deserialize, Serialize};

/// Earlier prints a printer's pace is taken from (its most recent).
pub(crate) const PACE_PRINTS: usize = 5;

/// Prints whose took / planned falls outside these say more about the print (a long
/// pause, a printer slowed by hand) than about the printer: such a print is not counted.
const PACE_RANGE: std::ops::RangeInclusive<f64> = 0.5..=3.0;

/// Fewer step events than this say too little of a stepper to be counted.
const MIN_STEPS: f64 = 1000.0;

/// A finished print's motion as planned and as it went: from the end of its heat-up to
/// its last acknowledgement, without pauses or cancelled parts (such prints keep none).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct PaceSample {
    pub planned_s: f64,
    pub took_s: f64,
    /// The step events of its moves as planned (0 in records made before they were
    /// counted: those are not counted for the pace).
    #[serde(default)]
    pub steps: f64,
}

/// How a printer keeps to its planner: the seconds its stepper takes per step event
/// beyond the planner's time, the median over its recent prints of
/// `(took - planned) / steps` (0 with none; below 0 where it runs ahead of the planner).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct Pace {
    pub per_step_s: f64,
    /// The prints it rests on.
    pub prints: u32,
}

impl Default for Pace {
    fn default() -> Self {
        Pace {
            per_step_s: 0.0,
            prints: 0,
        }
    }
}

impl Pace {
    /// The pace from a printer's prints, oldest first (the last [`PACE_PRINTS`] count).
    pub fn of(samples: impl IntoIterator<Item = PaceSample>) -> Pace {
        let mut per_step: Vec<f64> = samples
            .into_iter()
            .filter(|s| s.planned_s >= 1.0 && s.took_s.is_finite() && s.steps >= MIN_STEPS)
            .filter(|s| PACE_RANGE.contains(&(s.took_s / s.planned_s)))
            .map(|s| (s.took_s - s.planned_s) / s.steps)
            .filter(|d| d.is_finite())
            .collect();
        let mut recent = per_step.split_off(per_step.len().saturating_sub(PACE_PRINTS));
        if recent.is_empty() {
            return Pace::default();
        }
        recent.sort_by(f64::total_cmp);
        let mid = recent.len() / 2;
        let per_step_s = if recent.len() % 2 == 1 {
            recent[mid]
        } else {
            (recent[mid - 1] + recent[mid]) / 2.0
        };
        Pace {
            per_step_s,
            prints: recent.len() as u32,
        }
    }
}

/// Whose settings the planner's estimate was made with.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Settings {
    /// The printer's own, as it reported them in answer to `M503` at connect.
    Printer,
    /// The machine's stock values: the printer reported none (no `M503`).
    #[default]
    Stock,
}

impl Settings {
    /// The planner's settings for a printer on `firmware` that reported `reported` (the
    /// `M503` lines of [`Connection::settings`](crate::marlin::stream::Connection::settings)),
    /// and whose they are.
    pub fn limits(
        firmware: crate::marlin::firmware::Firmware,
        reported: &[String],
    ) -> (crate::marlin::estimate::Limits, Settings) {
        let mut limits = crate::marlin::estimate::Limits::of(firmware);
        let taken = limits.apply_m503(&reported.join("\n"));
        let whose = if taken.is_empty() {
            Settings::Stock
        } else {
            Settings::Printer
        };
        (limits, whose)
    }
}

/// What a print's time left rests on (its `remaining_s` is `planned_s` and the pace's
/// seconds for `steps_left`).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct TimeLeft {
    /// The planner's seconds for the commands not yet acknowledged.
    pub planned_s: f64,
    /// Their step events.
    #[serde(default)]
    pub steps_left: f64,
    pub pace: Pace,
    /// Still heating up: the heat-up's own time comes on top.
    pub heating: bool,
    /// Whose settings the planner used.
    #[serde(default)]
    pub settings: Settings,
}

impl TimeLeft {
    pub fn seconds(&self) -> f64 {
        // A printer ahead of its planner takes no less than half the planner's time (the
        // range its prints were counted in).
        (self.planned_s + self.steps_left * self.pace.per_step_s).max(self.planned_s / 2.0)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn sample(planned_s: f64, took_s: f64, steps: f64) -> PaceSample {
        PaceSample {
            planned_s,
            took_s,
            steps,
        }
    }

    #[test]
    fn a_printers_pace_is_the_median_of_its_recent_prints_per_step() {
        assert_eq!(Pace::of([]), Pace::default());
        let pace = Pace::of([sample(100.0, 110.0, 1e6)]);
        assert_eq!(pace.prints, 1);
        assert!((pace.per_step_s - 1e-5).abs() < 1e-15, "{pace:?}");
        // Median of the last five; a print outside the sane range is not counted.
        let pace = Pace::of([
            sample(100.0, 300.0, 1e6),
            sample(100.0, 101.0, 1e6),
            sample(100.0, 102.0, 1e6),
            sample(100.0, 104.0, 1e6),
            sample(100.0, 103.0, 1e6),
            sample(100.0, 900.0, 1e6),
            sample(100.0, 105.0, 1e6),
        ]);
        assert_eq!(pace.prints, 5);
        assert!((pace.per_step_s - 3e-6).abs() < 1e-15, "{pace:?}");
        // A print too short to say anything, with no figure, or recorded before steps
        // were counted, is not counted.
        assert_eq!(
            Pace::of([
                sample(0.5, 1.0, 1e6),
                sample(10.0, f64::NAN, 1e6),
                sample(100.0, 110.0, 0.0)
            ])
            .prints,
            0
        );
    }

    /// The stepper's cost goes by steps: a pace learned on a print of few steps a second
    /// gives a print of many steps a second its own, larger share (the Linux build's 18 %
    /// on fast travels against 3 % on Spot), where a factor on the time would not.
    #[test]
    fn the_pace_goes_by_the_steps_left() {
        let pace = Pace::of([sample(40.0, 41.2, 60_000.0)]); // 20 µs a step
        let travels = TimeLeft {
            planned_s: 180.0,
            steps_left: 1.6e6,
            pace,
            heating: false,
            settings: Settings::Printer,
        };
        assert!((travels.seconds() - 212.0).abs() < 1e-9, "{travels:?}");
        // No pace: the planner's time. Far ahead of the planner: no less than half of it.
        let plain = TimeLeft {
            pace: Pace::default(),
            ..travels
        };
        assert_eq!(plain.seconds(), 180.0);
        let ahead = TimeLeft {
            pace: Pace {
                per_step_s: -1.0,
                prints: 1,
            },
            ..travels
        };
        assert_eq!(ahead.seconds(), 90.0);
    }

    /// Where the printer reported its settings, they are its planner's; where it reported
    /// none, the machine's stock ones, and the time left says which.
    #[test]
    fn the_planner_takes_the_printers_settings_where_it_reported_them() {
        use crate::marlin::estimate::{Junction, Limits};
        use crate::marlin::firmware::Firmware;
        assert_eq!(
            Settings::limits(Firmware::Marlin2, &[]),
            (Limits::of(Firmware::Marlin2), Settings::Stock)
        );
        let reported = [
            "M203 X200.00 Y200.00 Z5.00 E25.00".to_string(),
            "M205 B20000.00 S0.00 T0.00 J0.01".to_string(),
        ];
        let (limits, whose) = Settings::limits(Firmware::Marlin2, &reported);
        assert_eq!(whose, Settings::Printer);
        assert_eq!(limits.max_feedrate, [200.0, 200.0, 5.0, 25.0]);
        // J0.01 is the stock 0.013 mm as the report rounds it: the exact value is kept.
        assert_eq!(limits.junction, Junction::Deviation { mm: 0.013 });
    }
}
