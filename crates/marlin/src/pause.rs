//! Pauses a G-code file asks for (`M0`, `M1`, `M25`, `M125`, `M226`, `M601`, `M600`: see
//! [`FILE_PAUSES`]): where they are, what the operator is told, and
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

use super::gcode::{GcodeCommands, FILE_PAUSES};
use super::motion::{Command, Motion};
use super::protocol::Temperatures;
use super::reader;

/// A pause the file asks for.
#[derive(Debug, Clone, PartialEq)]
pub struct FilePause {
    /// Index of the pause command among the job's commands (it is never sent).
    pub index: usize,
    /// The command as written, e.g. `M0 Insert magnets`.
    pub command: String,
    /// What the operator is told: see [`pause_message`].
    pub message: String,
}

/// Finds the pauses of a job, in order.
pub fn find_pauses(commands: &GcodeCommands) -> Vec<FilePause> {
    let mut shown = None;
    let mut pauses = Vec::new();
    for (index, command) in commands.iter().enumerate() {
        let Ok(Some(cmd)) = reader::read(command) else {
            continue;
        };
        if let Some(message) = pause_message(&cmd, &mut shown) {
            pauses.push(FilePause {
                index,
                command: command.to_string(),
                message,
            });
        }
    }
    pauses
}

/// Read in file order: follows the display's message (`M117`, kept in `shown`), and for a
/// pause the file asks for ([`FILE_PAUSES`]) says what the operator is told: the command's
/// own text (`M0 Insert magnets`), or else the last message shown before it, or else what
/// the command is for. `None` for any other command. The host's pauses and the G-code
/// policy's verdict both read pauses with this, so they name the same ones.
pub fn pause_message(cmd: &Command, shown: &mut Option<String>) -> Option<String> {
    if cmd.code == "M117" {
        // An empty M117 clears the display.
        *shown = (!cmd.rest.is_empty()).then(|| cmd.rest.to_string());
        return None;
    }
    if !FILE_PAUSES.contains(&cmd.code.as_str()) {
        return None;
    }
    Some(match (own_text(cmd), shown.as_ref()) {
        (Some(own), _) => own.to_string(),
        (None, Some(shown)) => shown.clone(),
        (None, None) => format!(
            "{} ({})",
            format!("{} {}", cmd.code, cmd.rest).trim_end(),
            purpose(&cmd.code)
        ),
    })
}

/// The message of `M0 Insert magnets` or `M1 S5 Turn the part` (after any `P<ms>` or
/// `S<s>` time); only M0/M1 carry a free message, the others' words are parameters.
fn own_text<'a>(cmd: &Command<'a>) -> Option<&'a str> {
    if !matches!(cmd.code.as_str(), "M0" | "M1") {
        return None;
    }
    let mut rest = cmd.rest;
    while let Some(word) = rest.split_whitespace().next() {
        let timed = word.len() > 1
            && word.starts_with(['P', 'S', 'p', 's'])
            && word[1..].parse::<f64>().is_ok();
        if !timed {
            break;
        }
        rest = rest[word.len()..].trim_start();
    }
    (!rest.is_empty()).then_some(rest.trim_end())
}

fn purpose(code: &str) -> &'static str {
    match code {
        "M600" => "filament change",
        "M0" | "M1" => "wait for the user",
        "M125" => "park the head",
        "M226" => "wait for a pin",
        _ => "pause the print",
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
    /// The machine's own park code, replacing the lift and move (`[[machine]] pause_gcode`).
    pub park_gcode: Option<String>,
    /// The machine's code sent on resuming, before the head returns (`resume_gcode`).
    pub resume_gcode: Option<String>,
}

impl PauseSettings {
    /// The lift, and where the head parks: X at its minimum, Y at its maximum (a bed-slinger
    /// brings the print forward to the operator; the head is clear of it either way).
    pub(crate) const DEFAULT_LIFT_MM: f64 = 10.0;
    pub(crate) const DEFAULT_HEATERS_OFF_AFTER: std::time::Duration =
        std::time::Duration::from_secs(30 * 60);

    pub fn new(volume_mm: [f64; 3]) -> PauseSettings {
        PauseSettings {
            volume_mm,
            lift_mm: Self::DEFAULT_LIFT_MM,
            heaters_off_after: Self::DEFAULT_HEATERS_OFF_AFTER,
            park_gcode: None,
            resume_gcode: None,
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

/// The commands of a machine's pause or resume code: comments and blank lines left out
/// (the config checked it loads and passes the G-code policy).
fn code_lines(code: &str) -> impl Iterator<Item = String> + '_ {
    code.lines()
        .map(|l| l.split(';').next().unwrap_or("").trim())
        .filter(|l| !l.is_empty())
        .map(String::from)
}

/// The lines that park the printer at a pause, with `motion` as the file left it; `None` when
/// the head's position is not known (nothing is moved then: a blind move could hit the
/// print, and the head could not be brought back). The park is the machine's `park_gcode`,
/// or else on the machine (X at its minimum, Y at its maximum, lifted), written in the
/// file's coordinates, which a `G92` in the file may have shifted. In absolute positioning,
/// after `M400`; ends with `M400`, so the park is over once its lines are answered.
pub fn park_lines(settings: &PauseSettings, motion: &Motion) -> Option<Vec<String>> {
    let [_, _, z] = motion.known_machine_position()?;
    let [_, y_max, z_max] = settings.volume_mm;
    let lift = settings.lift_mm.min((z_max - z).max(0.0));
    let mut lines = vec!["M400".to_string(), "G90".to_string()];
    if let Some(code) = &settings.park_gcode {
        lines.extend(code_lines(code));
        lines.push("M400".to_string());
        return Some(lines);
    }
    if lift > 0.0 {
        lines.push(format!(
            "G1 Z{} F{}",
            num(motion.to_file(2, z + lift)),
            num(Z_FEED)
        ));
    }
    lines.push(format!(
        "G1 X{} Y{} F{}",
        num(motion.to_file(0, 0.0)),
        num(motion.to_file(1, y_max)),
        num(XY_FEED)
    ));
    lines.push("M400".to_string());
    Some(lines)
}

/// The lines that turn the heaters off during a long pause (the fan and motors stay on:
/// the motors keep the head's position for the resume).
pub(crate) fn heaters_off_lines() -> Vec<String> {
    vec!["M104 S0".to_string(), "M140 S0".to_string()]
}

/// The lines that take the print up again after a pause: heat up again to the targets in
/// force before the pause when `reheat` (the heaters were turned off meanwhile), the
/// machine's `resume_gcode`, return to where the head was when `parked`, and restore the
/// file's modes (positioning, extruder mode and position, feed rate), which the park and
/// the machine's code may have changed.
pub fn resume_lines(
    settings: &PauseSettings,
    motion: &Motion,
    parked: bool,
    reheat: Option<&Temperatures>,
) -> Vec<String> {
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
    if let Some(code) = &settings.resume_gcode {
        lines.extend(code_lines(code));
    }
    let position = motion.file_position();
    if parked {
        if let [Some(x), Some(y), Some(z), _] = position {
            lines.push("G90".to_string());
            lines.push(format!("G1 X{} Y{} F{}", num(x), num(y), num(XY_FEED)));
            lines.push(format!("G1 Z{} F{}", num(z), num(Z_FEED)));
        }
    }
    lines.extend(motion.mode_commands().map(String::from));
    if let (false, Some(e)) = (motion.e_relative(), position[3]) {
        lines.push(format!("G92 E{}", num(e)));
    }
    if let Some(f) = motion.feed() {
        lines.push(format!("G1 F{}", num(f)));
    }
    lines
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::protocol::Temp;

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
            "m600", // stock Marlin answers `Unknown command`: no pause
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
                (7, "M25 (pause the print)"),
                (8, "M601 (pause the print)"),
                (9, "M125 (park the head)"),
                (10, "M226 P3 S1 (wait for a pin)"),
                (11, "old style"),
            ]
        );
    }

    fn followed(lines: &[&str]) -> Motion {
        let mut m = Motion::default();
        for line in lines {
            m.apply(&reader::read(line).unwrap().unwrap()).unwrap();
        }
        m
    }

    #[test]
    fn the_head_is_known_only_where_the_file_says_where_it_is() {
        let m = followed(&["G28", "G90", "M83", "G1 Z0.2 F600", "G1 X10 Y20 E1 F1800"]);
        assert_eq!(
            m.file_position(),
            // Z as the firmware holds it: 0.2 in a 32-bit float.
            [Some(10.0), Some(20.0), Some(f64::from(0.2f32)), None],
            "E relative from an unknown start stays unknown"
        );
        assert!(m.e_relative());
        assert_eq!(m.feed(), Some(1800.0));
        let m = followed(&["G28", "G1 X10 Y20 Z5", "G28 X"]);
        assert_eq!(
            m.file_position()[..2],
            [None, Some(20.0)],
            "homed: not known"
        );
        assert_eq!(m.known_machine_position(), None);
        // Relative moves from a known place stay known; Marlin 2's G91 makes E relative.
        let m = followed(&["G1 X10 Y20 Z5", "G92 E0", "G91", "G1 X1 Y-2 E2"]);
        assert_eq!(
            m.file_position(),
            [Some(11.0), Some(18.0), Some(5.0), Some(2.0)]
        );
        assert_eq!(m.mode_commands(), ["G91", "M83"]);
        // A G92 on an axis whose place is not known shifts the file's coordinates by an
        // unknown amount: its later moves do not make it known on the machine.
        let m = followed(&["G28", "G92 Z5", "G1 X1 Y1 Z6"]);
        assert_eq!(m.known_machine_position(), None);
    }

    #[test]
    fn park_stays_in_the_volume_and_resume_restores_the_file_state() {
        let settings = PauseSettings::new([220.0, 220.0, 250.0]);
        let m = followed(&["G90", "M82", "G92 E0", "G1 X50 Y60 Z245 E12.5 F1500"]);
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
        let resume = resume_lines(&settings, &m, true, Some(&temps));
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
        // Where the file shifted its coordinates (G92 X0 at machine X30), the park still
        // goes to the machine's X0: X-30 in the file's; the return is in the file's.
        let m = followed(&["G28", "G1 X30 Y40 Z2", "G92 X0", "G1 X5"]);
        assert_eq!(park_lines(&settings, &m).unwrap()[3], "G1 X-30 Y220 F6000");
        assert_eq!(
            resume_lines(&settings, &m, true, None)[1],
            "G1 X5 Y40 F6000"
        );
        // The machine's own codes: its park instead of the lift and move (still bracketed by
        // M400 in absolute positioning), its resume code before the head returns.
        let own = PauseSettings {
            park_gcode: Some("G91 ; lift\nG1 Z5\n\nG90\nG1 X200 Y0 ; aside\n".into()),
            resume_gcode: Some("M106 S255\n".into()),
            ..settings.clone()
        };
        assert_eq!(
            park_lines(&own, &m).unwrap(),
            vec!["M400", "G90", "G91", "G1 Z5", "G90", "G1 X200 Y0", "M400"]
        );
        assert_eq!(
            resume_lines(&own, &m, true, None)[..3],
            ["M106 S255", "G90", "G1 X5 Y40 F6000"]
        );
        // Unknown position: no park, and the resume moves nothing.
        let homed = Motion::default();
        assert_eq!(park_lines(&settings, &homed), None);
        assert_eq!(
            resume_lines(&settings, &homed, false, None),
            vec!["G90", "M82"]
        );
    }
}
