//! Motion: how long moves take at their feedrate, and the planner queue that drains at
//! that pace (a move is acknowledged once it is in the planner).
use super::state::Printer;
use crispen_marlin::firmware::Firmware;
use crispen_marlin::motion::{firmware_arc, ArcRun};
use crispen_marlin::reader;
use std::time::Instant;

impl Printer {
    pub(super) fn update_planner(&mut self, now: Instant) {
        while let Some(end) = self.planner_head_end {
            if now < end {
                break;
            }
            self.planner.pop_front();
            self.planner_head_end = self.planner.front().map(|d| end + *d);
        }
    }

    pub(super) fn plan(&mut self, seconds: f64, now: Instant) {
        let d = self.real(seconds);
        if self.planner.is_empty() {
            self.planner_head_end = Some(now + d);
        }
        self.planner.push_back(d);
    }

    /// Simulated seconds a G0–G3 takes at its feedrate (F is persistent, mm/min), the
    /// position moved as the firmware moves it: in its 32-bit floats, an arc run by its own
    /// arithmetic (`crispen_marlin::motion::firmware_arc`: Marlin 2's `plan_arc`,
    /// Ultimaker2Marlin's `mc_arc`), so an arc whose ends are equal in float is a whole
    /// circle here too, one Marlin 2 cannot make answers `Error:G2/G3 bad parameters`,
    /// and one the firmware skips takes no time. The position is the file's own
    /// coordinates (what `M114` reports): exact for Ultimaker2Marlin, and for Marlin 2
    /// while no `G92` shifted its workspace.
    pub(super) fn move_seconds(&mut self, words: &[(char, f64)], code: i64) -> f64 {
        if let Some(f) = word(words, 'F') {
            if f > 0.0 {
                self.feedrate = f;
            }
        }
        let start = self.position.map(|v| v as f32);
        let mut end = start;
        for (i, axis) in ['X', 'Y', 'Z', 'E'].into_iter().enumerate() {
            if let Some(v) = word(words, axis) {
                let rel = if i == 3 {
                    // Ultimaker2Marlin: G91 makes E relative whatever M82 said.
                    self.relative_e || (self.relative && self.fw == Firmware::Ultimaker2)
                } else {
                    self.relative
                };
                // The views' values are the firmware's floats already.
                end[i] = if rel { start[i] + v as f32 } else { v as f32 };
            }
        }
        let d: Vec<f64> = (0..4)
            .map(|k| f64::from(end[k]) - f64::from(start[k]))
            .collect();
        let mut distance = (d[0] * d[0] + d[1] * d[1] + d[2] * d[2]).sqrt();
        if code == 2 || code == 3 {
            let read = ['R', 'I', 'J'].map(|l| word(words, l).map(|v| v as f32));
            match firmware_arc(self.fw, code == 2, start, end, read) {
                ArcRun::Runs { radius, sweep, .. } => {
                    distance = (f64::from(radius) * f64::from(sweep)).hypot(d[2]);
                }
                ArcRun::BadParameters => {
                    self.say("Error:G2/G3 bad parameters");
                    return 0.0;
                }
                ArcRun::Skipped(_) => {
                    // Ultimaker2Marlin takes the end as reached; Marlin 2 stays.
                    if self.fw == Firmware::Ultimaker2 {
                        self.position = end.map(f64::from);
                    }
                    return 0.0;
                }
            }
        }
        self.position = end.map(f64::from);
        if distance == 0.0 {
            distance = d[3].abs();
        }
        distance / (self.feedrate / 60.0)
    }
}

/// A command as the firmware being simulated reads it (`crispen_marlin::reader`'s view of
/// Marlin 2 or Ultimaker2Marlin, so the simulator runs odd lines as the real firmware does:
/// `M104 @S400` heats to 400, `M400 G92 Z50` is a `G92` on Ultimaker2Marlin): the command's
/// letter and number first, then each parameter seen, by letter, with its value (`NaN` for
/// a letter seen without one). Empty when the firmware finds no command.
pub(super) fn parse_words(fw: Firmware, cmd: &str) -> Vec<(char, f64)> {
    let view = match fw {
        Firmware::Marlin2 | Firmware::Marlin20 => reader::marlin2::read(cmd),
        Firmware::Ultimaker2 => reader::ultimaker2::read(cmd),
    };
    let Some((letter, number)) = view.command else {
        return Vec::new();
    };
    let mut words = vec![(letter, f64::from(number))];
    for (i, param) in view.params.iter().enumerate() {
        let l = (b'A' + i as u8) as char;
        // The host's line number, and (where letters are found anywhere) the command's own.
        if l == 'N' || l == letter {
            continue;
        }
        if let Some(value) = param {
            words.push((l, value.unwrap_or(f64::NAN)));
        }
    }
    words
}

pub(super) fn word(words: &[(char, f64)], letter: char) -> Option<f64> {
    words
        .iter()
        .skip(1)
        .find(|w| w.0 == letter)
        .map(|w| w.1)
        .filter(|v| !v.is_nan())
}

pub(super) fn word_present(words: &[(char, f64)], letter: char) -> bool {
    words.iter().skip(1).any(|w| w.0 == letter)
}

/// G0–G3: the commands Ultimaker2Marlin acknowledges as they enter its queue.
pub(super) fn is_move(fw: Firmware, cmd: &str) -> bool {
    let words = parse_words(fw, cmd);
    matches!(words.first(), Some(&('G', code)) if (0.0..=3.0).contains(&code))
}
