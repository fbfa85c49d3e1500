//! The thermal model: heaters approach their targets at fixed rates, and the reports
//! each firmware prints about them.
use super::super::config::ReportStyle;
use super::state::{Heater, Printer};
use crispen_marlin::firmware::Firmware;
use std::time::Instant;

/// The room's temperature: where heaters without a target settle.
pub(super) const AMBIENT: f64 = 21.0;

const HOTEND_HEAT_RATE: f64 = 2.5; // °C per simulated second
const HOTEND_COOL_RATE: f64 = 1.0;
const BED_HEAT_RATE: f64 = 0.8;
const BED_COOL_RATE: f64 = 0.3;

impl Printer {
    pub(super) fn update_temperatures(&mut self, now: Instant) {
        let real = now.saturating_duration_since(self.temps_at).as_secs_f64();
        self.temps_at = now;
        let sim = if self.time_scale == 0.0 {
            f64::INFINITY
        } else {
            real / self.time_scale
        };
        for (t, heat, cool) in [
            (&mut self.hotend, HOTEND_HEAT_RATE, HOTEND_COOL_RATE),
            (&mut self.bed, BED_HEAT_RATE, BED_COOL_RATE),
        ] {
            let goal = t.target.max(AMBIENT);
            if t.current < goal {
                t.current = (t.current + heat * sim).min(goal);
            } else if t.current > goal {
                t.current = (t.current - cool * sim).max(goal);
            }
        }
    }

    pub(super) fn temperature_report(&self) -> String {
        let slash = match self.report_style {
            ReportStyle::Marlin => " /",
            ReportStyle::SlashFirst => "/ ",
            ReportStyle::Tight => "/",
        };
        format!(
            "T:{:.2}{slash}{:.2} B:{:.2}{slash}{:.2} @:0 B@:0",
            self.hotend.current, self.hotend.target, self.bed.current, self.bed.target
        )
    }

    /// The report printed every second inside M109/M190: Marlin's with a `W:` residency
    /// countdown, Ultimaker2Marlin's without the target (`T:210.0 E:0 W:?`).
    pub(super) fn heat_wait_report(&self, heater: Heater) -> String {
        match (self.fw, heater) {
            (Firmware::Ultimaker2, Heater::Hotend) => {
                format!("T:{:.1} E:0 W:?", self.hotend.current)
            }
            (Firmware::Ultimaker2, Heater::Bed) => {
                format!("T:{:.1} E:0 B:{:.1}", self.hotend.current, self.bed.current)
            }
            _ => format!("{} W:?", self.temperature_report()),
        }
    }
}
