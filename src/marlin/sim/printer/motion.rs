//! Motion: how long moves take at their feedrate, and the planner queue that drains at
//! that pace (a move is acknowledged once it is in the planner).
use super::state::Printer;
use crate::marlin::firmware::Firmware;
use crate::marlin::reader;
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

    /// Simulated seconds a G0–G3 takes at its feedrate (F is persistent, mm/min).
    pub(super) fn move_seconds(&mut self, words: &[(char, f64)], code: i64) -> f64 {
        if let Some(f) = word(words, 'F') {
            if f > 0.0 {
                self.feedrate = f;
            }
        }
        let start = self.position;
        let mut end = start;
        for (i, axis) in ['X', 'Y', 'Z', 'E'].into_iter().enumerate() {
            if let Some(v) = word(words, axis) {
                let rel = if i == 3 {
                    // Ultimaker2Marlin: G91 makes E relative whatever M82 said.
                    self.relative_e || (self.relative && self.fw == Firmware::Ultimaker2)
                } else {
                    self.relative
                };
                end[i] = if rel { start[i] + v } else { v };
            }
        }
        self.position = end;
        let (dx, dy, dz) = (end[0] - start[0], end[1] - start[1], end[2] - start[2]);
        let mut distance = (dx * dx + dy * dy + dz * dz).sqrt();
        if code == 2 || code == 3 {
            let (i, j) = (
                word(words, 'I').unwrap_or(0.0),
                word(words, 'J').unwrap_or(0.0),
            );
            let radius = (i * i + j * j).sqrt();
            if radius > 0.0 {
                let (cx, cy) = (start[0] + i, start[1] + j);
                let a0 = (start[1] - cy).atan2(start[0] - cx);
                let a1 = (end[1] - cy).atan2(end[0] - cx);
                let mut sweep = if code == 3 { a1 - a0 } else { a0 - a1 };
                if sweep <= 1e-9 {
                    sweep += std::f64::consts::TAU;
                }
                distance = (radius * sweep).hypot(dz);
            }
        }
        if distance == 0.0 {
            distance = (end[3] - start[3]).abs();
        }
        distance / (self.feedrate / 60.0)
    }
}

/// A command as the firmware being simulated reads it (`crate::marlin::reader`'s view of
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
