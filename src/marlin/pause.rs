//! Pauses a G-code file asks for (`M0`, `M1`, `M25`, `M125`, `M226`, `M601`, `M600`: see
//! [`FILE_PAUSES`](super::gcode::FILE_PAUSES)): where they are, what the operator is told, and
//! the G-code the host sends to park the printer and to take up the print again. Pure: no
//! I/O and no clock; the stream driver (`stream.rs`) drives it.
//!
//! Why the host and not the firmware: each of these commands stops a printer until someone
//! presses its knob (`M0` waits with `busy: paused for user`, and a host waiting for its `ok`
//! takes the silence for a stuck printer), or is unknown to the firmware and the pause the file
//! wanted is silently lost (a stock Marlin 2 without a display answers all of them with
//! `Unknown command`). crispen never sends them: it stops streaming at that point, parks the
//! head, waits for the operator (`crispen resume`, the API or the dashboard) and goes on.
//!
//! Where the head goes back to is followed by the host from the file itself ([`Motion`]), not
//! saved by the firmware with `G60`/`G61`: those need `SAVED_POSITIONS`, which stock Marlin 2
//! builds leave out and Ultimaker2Marlin does not have, and a firmware that lacks them answers
//! `Unknown command` and would send the head to a wrong place on resume.

use super::gcode::{display_message, is_file_pause, GcodeCommands};
use super::protocol::Temperatures;

/// A pause the file asks for.
#[derive(Debug, Clone, PartialEq)]
pub struct FilePause {
    /// Index of the pause command among the job's commands (it is never sent).
    pub index: usize,
    /// The command as written, e.g. `M0 Insert magnets`.
    pub command: String,
    /// What the operator is told: the command's own text, or else the last `M117` message
    /// before it, or else what the command is for.
    pub message: String,
}

/// Finds the pauses of a job, in order.
pub fn find_pauses(commands: &GcodeCommands) -> Vec<FilePause> {
    let mut shown: Option<String> = None;
    let mut pauses = Vec::new();
    for (index, command) in commands.iter().enumerate() {
        if let Some(text) = display_message(command) {
            // An empty M117 clears the display.
            shown = (!text.is_empty()).then(|| text.to_string());
            continue;
        }
        if !is_file_pause(command) {
            continue;
        }
        let own = own_text(command);
        let message = match (own, &shown) {
            (Some(own), _) => own.to_string(),
            (None, Some(shown)) => shown.clone(),
            (None, None) => format!("{} ({})", command.trim(), purpose(command)),
        };
        pauses.push(FilePause {
            index,
            command: command.to_string(),
            message,
        });
    }
    pauses
}

/// The text of `M0 Insert magnets` (after the code and any `P<ms>`/`S<s>` word).
fn own_text(command: &str) -> Option<&str> {
    let code = command.split_whitespace().next()?;
    let mut rest = command[code.len()..].trim_start();
    // M0/M1 take an optional time before their message.
    while let Some(word) = rest.split_whitespace().next() {
        let timed = word.len() > 1
            && word.starts_with(['P', 'S', 'p', 's'])
            && word[1..].parse::<f64>().is_ok();
        if !timed {
            break;
        }
        rest = rest[word.len()..].trim_start();
    }
    let code_no = code[1..].parse::<u32>().ok()?;
    // Only M0/M1 carry a free message; the others' words are parameters.
    (matches!(code_no, 0 | 1) && !rest.is_empty()).then_some(rest.trim_end())
}

fn purpose(command: &str) -> &'static str {
    let code = command.split_whitespace().next().unwrap_or("");
    match code.get(1..).and_then(|n| n.parse::<u32>().ok()) {
        Some(600) => "filament change",
        Some(0 | 1) => "wait for the user",
        Some(125) => "park the head",
        Some(226) => "wait for a pin",
        _ => "pause the print",
    }
}

/// The position and modes of the printer as the file has set them so far: where the head
/// goes back to after a pause, and the modes the resume restores (the park changes them).
/// An axis is `None` while its position is not known from the file (before its first move
/// or `G92`, and after it was homed: the firmware's home position is not in the file).
#[derive(Debug, Clone, Default, PartialEq)]
pub struct Motion {
    /// `G91` is in force (X, Y, Z and, unless `M82` followed, E are relative).
    pub relative: bool,
    /// E is relative (`M83`, or `G91` without a later `M82`).
    pub relative_e: bool,
    /// X, Y, Z, E in the file's coordinates.
    pub position: [Option<f64>; 4],
    /// The last feed rate (mm/min) a move gave.
    pub feed: Option<f64>,
}

const AXES: [char; 4] = ['X', 'Y', 'Z', 'E'];

/// `G1 X10.5Y-2` into its letters and numbers (letters in upper case; a letter without a
/// number gets `None`).
fn words(command: &str) -> Vec<(char, Option<f64>)> {
    let mut out = Vec::new();
    let bytes = command.as_bytes();
    let mut i = 0;
    while i < bytes.len() {
        let c = bytes[i] as char;
        if !c.is_ascii_alphabetic() {
            i += 1;
            continue;
        }
        let start = i + 1;
        let mut end = start;
        while end < bytes.len() && matches!(bytes[end], b'0'..=b'9' | b'.' | b'-' | b'+') {
            end += 1;
        }
        out.push((
            c.to_ascii_uppercase(),
            command[start..end].parse::<f64>().ok(),
        ));
        i = end.max(start);
    }
    out
}

impl Motion {
    /// Follows one command.
    pub fn follow(&mut self, command: &str) {
        let w = words(command);
        let Some(&(letter, Some(code))) = w.first() else {
            return;
        };
        // `G1.5` and the like are no command this follows.
        if code.fract() != 0.0 || !(0.0..=10_000.0).contains(&code) {
            return;
        }
        let code = code as u32;
        let value = |axis: char| {
            w.iter()
                .skip(1)
                .find(|(l, _)| *l == axis)
                .and_then(|(_, v)| *v)
        };
        let named = |axis: char| w.iter().skip(1).any(|(l, _)| *l == axis);
        match (letter, code) {
            ('G', 0..=3) => {
                for (i, axis) in AXES.into_iter().enumerate() {
                    let Some(v) = value(axis) else { continue };
                    let relative = if axis == 'E' {
                        self.relative_e
                    } else {
                        self.relative
                    };
                    self.position[i] = if relative {
                        self.position[i].map(|p| p + v)
                    } else {
                        Some(v)
                    };
                }
                if let Some(f) = value('F') {
                    self.feed = Some(f);
                }
            }
            ('G', 28) => {
                let all = !['X', 'Y', 'Z'].into_iter().any(named);
                for (i, axis) in ['X', 'Y', 'Z'].into_iter().enumerate() {
                    if all || named(axis) {
                        self.position[i] = None;
                    }
                }
            }
            ('G', 90) => {
                self.relative = false;
                self.relative_e = false;
            }
            ('G', 91) => {
                self.relative = true;
                self.relative_e = true;
            }
            ('G', 92) => {
                let all = !AXES.into_iter().any(named);
                for (i, axis) in AXES.into_iter().enumerate() {
                    if all {
                        self.position[i] = Some(0.0);
                    } else if named(axis) {
                        self.position[i] = Some(value(axis).unwrap_or(0.0));
                    }
                }
            }
            ('M', 82) => self.relative_e = false,
            ('M', 83) => self.relative_e = true,
            _ => {}
        }
    }
}

/// How the host parks a printer at a file's pause and takes the print up again.
#[derive(Debug, Clone, PartialEq)]
pub struct PauseSettings {
    /// The machine's build volume (X, Y, Z, mm from the origin): the park stays inside it.
    pub volume_mm: [f64; 3],
    /// How far the head is lifted (less near the top of the volume).
    pub lift_mm: f64,
    /// A pause nobody resumes for this long turns the heaters off (the job keeps waiting;
    /// the resume heats up again first).
    pub heaters_off_after: std::time::Duration,
}

impl PauseSettings {
    /// The lift, and where the head parks: X at its minimum, Y at its maximum (a bed-slinger
    /// brings the print forward to the operator; the head is clear of it either way).
    pub const DEFAULT_LIFT_MM: f64 = 10.0;
    pub const DEFAULT_HEATERS_OFF_AFTER: std::time::Duration =
        std::time::Duration::from_secs(30 * 60);

    pub fn new(volume_mm: [f64; 3]) -> PauseSettings {
        PauseSettings {
            volume_mm,
            lift_mm: Self::DEFAULT_LIFT_MM,
            heaters_off_after: Self::DEFAULT_HEATERS_OFF_AFTER,
        }
    }
}

/// Travel feed rates of the park and the return (mm/min): slow in Z, which is slow on
/// every machine crispen knows, brisk in X/Y.
const Z_FEED: f64 = 600.0;
const XY_FEED: f64 = 6000.0;

fn num(v: f64) -> String {
    // Three decimals, without trailing zeros: short lines, and G-code any firmware reads.
    let s = format!("{v:.3}");
    let s = s.trim_end_matches('0').trim_end_matches('.');
    if s == "-0" {
        "0".into()
    } else {
        s.into()
    }
}

/// The lines that park the printer at a pause, with `motion` as the file left it; `None` when
/// the head's position is not known (nothing is moved then: a blind move could hit the
/// print). Ends with `M400`, so the park is over once its lines are answered.
pub fn park_lines(settings: &PauseSettings, motion: &Motion) -> Option<Vec<String>> {
    let [Some(_), Some(_), Some(z), _] = motion.position else {
        return None;
    };
    let [_, y_max, z_max] = settings.volume_mm;
    let lift = settings.lift_mm.min((z_max - z).max(0.0));
    let mut lines = vec!["M400".to_string(), "G90".to_string()];
    if lift > 0.0 {
        lines.push(format!("G1 Z{} F{}", num(z + lift), num(Z_FEED)));
    }
    lines.push(format!("G1 X0 Y{} F{}", num(y_max), num(XY_FEED)));
    lines.push("M400".to_string());
    Some(lines)
}

/// The lines that turn the heaters off during a long pause (the fan and motors stay on:
/// the motors keep the head's position for the resume).
pub fn heaters_off_lines() -> Vec<String> {
    vec!["M104 S0".to_string(), "M140 S0".to_string()]
}

/// The lines that take the print up again after a pause: heat up again to the targets in
/// force before the pause when `reheat` (the heaters were turned off meanwhile), return to
/// where the head was when `parked`, and restore the file's modes (positioning, extruder
/// mode and position, feed rate), which the park changed.
pub fn resume_lines(motion: &Motion, parked: bool, reheat: Option<&Temperatures>) -> Vec<String> {
    let mut lines = Vec::new();
    if let Some(t) = reheat {
        let bed = t.bed.and_then(|b| b.target).filter(|&s| s > 0.0);
        let hotend = t.hotend.and_then(|h| h.target).filter(|&s| s > 0.0);
        // Both heat at once; then wait for each.
        if let Some(s) = bed {
            lines.push(format!("M140 S{}", num(s)));
        }
        if let Some(s) = hotend {
            lines.push(format!("M104 S{}", num(s)));
        }
        if let Some(s) = bed {
            lines.push(format!("M190 S{}", num(s)));
        }
        if let Some(s) = hotend {
            lines.push(format!("M109 S{}", num(s)));
        }
    }
    if parked {
        if let [Some(x), Some(y), Some(z), _] = motion.position {
            lines.push("G90".to_string());
            lines.push(format!("G1 X{} Y{} F{}", num(x), num(y), num(XY_FEED)));
            lines.push(format!("G1 Z{} F{}", num(z), num(Z_FEED)));
        }
    }
    lines.push(if motion.relative { "G91" } else { "G90" }.to_string());
    lines.push(if motion.relative_e { "M83" } else { "M82" }.to_string());
    if let (false, Some(e)) = (motion.relative_e, motion.position[3]) {
        lines.push(format!("G92 E{}", num(e)));
    }
    if let Some(f) = motion.feed {
        lines.push(format!("G1 F{}", num(f)));
    }
    lines
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::marlin::protocol::Temp;

    fn commands(lines: &[&str]) -> GcodeCommands {
        GcodeCommands::pack(lines).unwrap()
    }

    #[test]
    fn every_pause_command_is_found_with_its_message() {
        let job = commands(&[
            "G28",
            "M117 Insert magnets now",
            "G1 X1",
            "M0",
            "M1 S5 Turn the part",
            "m600",
            "M117",
            "M25",
            "M601",
            "M125",
            "M226 P3 S1",
            "M00 old style",
            "M104 S200",
            "M1000",
            "M117 only text",
        ]);
        let found = find_pauses(&job);
        let got: Vec<(usize, &str)> = found
            .iter()
            .map(|p| (p.index, p.message.as_str()))
            .collect();
        assert_eq!(
            got,
            vec![
                (3, "Insert magnets now"),
                (4, "Turn the part"),
                (5, "Insert magnets now"),
                (7, "M25 (pause the print)"),
                (8, "M601 (pause the print)"),
                (9, "M125 (park the head)"),
                (10, "M226 P3 S1 (wait for a pin)"),
                (11, "old style"),
            ]
        );
    }

    #[test]
    fn motion_follows_modes_and_positions() {
        let mut m = Motion::default();
        for c in [
            "G28",
            "G90",
            "M83",
            "G1 Z0.2 F600",
            "G1 X10 Y20 E1 F1800",
            "G1 X12 E0.5",
        ] {
            m.follow(c);
        }
        assert_eq!(
            m.position,
            [Some(12.0), Some(20.0), Some(0.2), None],
            "E relative from an unknown start stays unknown"
        );
        assert!(!m.relative && m.relative_e);
        assert_eq!(m.feed, Some(1800.0));
        m.follow("G92 E0");
        m.follow("G1 E2");
        m.follow("G1 E1.5");
        assert_eq!(m.position[3], Some(3.5));
        m.follow("G91");
        m.follow("G1X1Y-2");
        assert_eq!(m.position[..2], [Some(13.0), Some(18.0)]);
        m.follow("G28 X");
        assert_eq!(m.position[0], None);
    }

    #[test]
    fn park_stays_in_the_volume_and_resume_restores_the_file_state() {
        let settings = PauseSettings::new([220.0, 220.0, 250.0]);
        let mut m = Motion::default();
        for c in ["G90", "M82", "G92 E0", "G1 X50 Y60 Z245 E12.5 F1500"] {
            m.follow(c);
        }
        let park = park_lines(&settings, &m).unwrap();
        assert_eq!(
            park,
            vec!["M400", "G90", "G1 Z250 F600", "G1 X0 Y220 F6000", "M400"],
            "lifted only to the top of the volume"
        );
        let temps = Temperatures {
            hotend: Some(Temp {
                current: 30.0,
                target: Some(210.0),
            }),
            bed: Some(Temp {
                current: 25.0,
                target: Some(60.0),
            }),
        };
        let resume = resume_lines(&m, true, Some(&temps));
        assert_eq!(
            resume,
            vec![
                "M140 S60",
                "M104 S210",
                "M190 S60",
                "M109 S210",
                "G90",
                "G1 X50 Y60 F6000",
                "G1 Z245 F600",
                "G90",
                "M82",
                "G92 E12.5",
                "G1 F1500"
            ]
        );
        // Unknown position: no park, and the resume moves nothing.
        let homed = Motion::default();
        assert_eq!(park_lines(&settings, &homed), None);
        assert_eq!(resume_lines(&homed, false, None), vec!["G90", "M82"]);
    }
}
