//! A print's time left, and what it rests on: the planner's estimate of the commands not
//! yet acknowledged (`marlin::estimate`, with the printer's own settings where it reported
//! them to `M503`), scaled by the printer's own pace on its earlier
//! prints (what each took against what the planner said), with the heat-up apart (a
//! heater's time is the heater's, not the planner's).

use serde::{Deserialize, Serialize};

/// Earlier prints a printer's pace is taken from (its most recent).
pub(crate) const PACE_PRINTS: usize = 5;

/// Paces beyond these say more about the print (a long pause, a printer slowed by hand)
/// than about the printer: such a print is not counted.
const PACE_RANGE: std::ops::RangeInclusive<f64> = 0.5..=3.0;

/// A finished print's motion as planned and as it went: from the end of its heat-up to
/// its last acknowledgement, without pauses or cancelled parts (such prints keep none).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct PaceSample {
    pub planned_s: f64,
    pub took_s: f64,
}

/// How a printer keeps to its planner's estimate: the median of its recent prints'
/// `took / planned` (1 with none).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct Pace {
    pub factor: f64,
    /// The prints it rests on.
    pub prints: u32,
}

impl Default for Pace {
    fn default() -> Self {
        Pace {
            factor: 1.0,
            prints: 0,
        }
    }
}

impl Pace {
    /// The pace from a printer's prints, oldest first (the last [`PACE_PRINTS`] count).
    pub fn of(samples: impl IntoIterator<Item = PaceSample>) -> Pace {
        let mut ratios: Vec<f64> = samples
            .into_iter()
            .filter(|s| s.planned_s >= 1.0 && s.took_s.is_finite())
            .map(|s| s.took_s / s.planned_s)
            .filter(|r| PACE_RANGE.contains(r))
            .collect();
        let mut recent = ratios.split_off(ratios.len().saturating_sub(PACE_PRINTS));
        if recent.is_empty() {
            return Pace::default();
        }
        recent.sort_by(f64::total_cmp);
        let mid = recent.len() / 2;
        let factor = if recent.len() % 2 == 1 {
            recent[mid]
        } else {
            (recent[mid - 1] + recent[mid]) / 2.0
        };
        Pace {
            factor,
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

/// What a print's time left rests on (its `remaining_s` is `planned_s × pace`).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct TimeLeft {
    /// The planner's seconds for the commands not yet acknowledged.
    pub planned_s: f64,
    pub pace: Pace,
    /// Still heating up: the heat-up's own time comes on top.
    pub heating: bool,
    /// Whose settings the planner used.
    #[serde(default)]
    pub settings: Settings,
}

impl TimeLeft {
    pub fn seconds(&self) -> f64 {
        self.planned_s * self.pace.factor
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn sample(planned_s: f64, took_s: f64) -> PaceSample {
        PaceSample { planned_s, took_s }
    }

    #[test]
    fn a_printers_pace_is_the_median_of_its_recent_prints() {
        assert_eq!(Pace::of([]), Pace::default());
        let pace = Pace::of([sample(100.0, 110.0)]);
        assert_eq!((pace.factor, pace.prints), (1.1, 1));
        // Median of the last five; a print outside the sane range is not counted.
        let pace = Pace::of([
            sample(100.0, 300.0),
            sample(100.0, 101.0),
            sample(100.0, 102.0),
            sample(100.0, 104.0),
            sample(100.0, 103.0),
            sample(100.0, 900.0),
            sample(100.0, 105.0),
        ]);
        assert_eq!(pace.prints, 5);
        assert!((pace.factor - 1.03).abs() < 1e-12, "{pace:?}");
        let even = Pace::of([sample(100.0, 100.0), sample(100.0, 110.0)]);
        assert!((even.factor - 1.05).abs() < 1e-12);
        // A print too short to say anything, or with no figure, is not counted.
        assert_eq!(
            Pace::of([sample(0.5, 1.0), sample(10.0, f64::NAN)]).prints,
            0
        );
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
