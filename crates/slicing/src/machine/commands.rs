//! Every command the supported firmwares know, classified for the G-code policy (the
//! `policy` module of `slice`): what a file may send as it is, what the checks follow,
//! what the host intercepts, and what is refused, with why. A command missing from the
//! table is refused unless a machine allows it by name (`allow = ["M9001"]` in its
//! `[[machine]]` table), as are the commands marked [`Class::Guarded`]: a list of what to
//! refuse would always miss the next command, so the policy lists what may pass.
//!
//! Kept here, with the machine, because a machine's `allow` is checked against it.

use crispen_marlin::firmware::Firmware;

/// What the policy does with a command.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub(crate) enum Class {
    /// Sent as written: it changes nothing a job's checks need, nothing beyond the job.
    Allowed,
    /// Sent once the checks pass: moves and positions (followed), temperatures and tools
    /// (against the machine's limits), and the conditions the policy names.
    Checked,
    /// Never sent: a pause the file asks for, which the host carries out itself.
    Intercepted,
    /// Refused unless the machine's `allow` names it: it changes the printer beyond the
    /// job, or moves the head where the follower cannot follow.
    Guarded(&'static str),
    /// Refused on every machine: it belongs to the host's conversation with the printer,
    /// or nothing crispen drives has the hardware.
    Refused(&'static str),
}

use Class::{Allowed, Checked, Guarded, Intercepted, Refused};

const NO_HARDWARE: &str =
    "drives hardware no machine crispen prints on has (laser, spindle, coolant, valves, mixing)";
const SD_FILE: &str = "runs or changes a file on the printer's SD card, which no check has read";
const WORKSPACES: &str = "selects a workspace coordinate system: off in stock Marlin, kept in EEPROM where on (so offsets would shift later jobs), its moves not followed for certain";
const UNFOLLOWED: &str = "moves the head where the motion checks cannot follow it";

/// Marlin 2.1's commands (its `GcodeSuite::process_parsed_command`), each with its class.
/// Marlin 2.0 knows a subset; a command it lacks is answered `Unknown command`.
pub(crate) const MARLIN2: &[(&str, Class)] = &[
    ("G0", Checked),
    ("G1", Checked),
    ("G2", Checked),
    ("G3", Checked),
    ("G4", Allowed),
    ("G5", Checked),
    ("G6", Refused("moves steppers directly, which the motion checks cannot follow")),
    ("G10", Checked),
    ("G11", Allowed),
    ("G12", Guarded("runs the nozzle-cleaning pattern at the positions set in the firmware, which the motion checks cannot follow")),
    ("G17", Allowed),
    ("G18", Refused("selects the ZX plane for arcs, which the motion checks do not follow")),
    ("G19", Refused("selects the YZ plane for arcs, which the motion checks do not follow")),
    ("G20", Refused("switches to inches, which the motion checks do not follow")),
    ("G21", Allowed),
    ("G26", Guarded("prints the mesh validation pattern: heats to its own temperatures (H, B) and moves the head where the motion checks cannot follow")),
    ("G27", Guarded("parks the head at the position set in the firmware, which the motion checks cannot follow")),
    ("G28", Checked),
    ("G29", Guarded("probes the bed and rewrites the bed mesh (G29 S3 and the like set mesh points by hand)")),
    ("G30", Guarded(UNFOLLOWED)),
    ("G31", Guarded("docks the probe sled")),
    ("G32", Guarded("undocks the probe sled")),
    ("G33", Guarded("calibrates a delta's geometry, changing it until reset (for good with M500)")),
    ("G34", Guarded("aligns the Z steppers, moving them independently")),
    ("G35", Guarded(UNFOLLOWED)),
    ("G38", Guarded(UNFOLLOWED)),
    ("G42", Guarded("moves the head to a mesh point, which the motion checks cannot follow")),
    ("G53", Refused(WORKSPACES)),
    ("G54", Refused(WORKSPACES)),
    ("G55", Refused(WORKSPACES)),
    ("G56", Refused(WORKSPACES)),
    ("G57", Refused(WORKSPACES)),
    ("G58", Refused(WORKSPACES)),
    ("G59", Refused(WORKSPACES)),
    ("G60", Checked),
    ("G61", Checked),
    ("G76", Guarded("calibrates the probe's temperature compensation: heats and probes")),
    ("G80", Allowed),
    ("G90", Checked),
    ("G91", Checked),
    ("G92", Checked),
    ("G425", Guarded("calibrates backlash by touching a conductive object, changing settings until reset")),
    ("M0", Intercepted),
    ("M1", Intercepted),
    ("M3", Refused(NO_HARDWARE)),
    ("M4", Refused(NO_HARDWARE)),
    ("M5", Refused(NO_HARDWARE)),
    ("M7", Refused(NO_HARDWARE)),
    ("M8", Refused(NO_HARDWARE)),
    ("M9", Refused(NO_HARDWARE)),
    ("M10", Refused(NO_HARDWARE)),
    ("M11", Refused(NO_HARDWARE)),
    ("M16", Guarded("halts the printer when its name differs from the one given")),
    ("M17", Allowed),
    ("M18", Allowed),
    ("M20", Allowed),
    ("M21", Guarded("mounts the SD card")),
    ("M22", Guarded("releases the SD card")),
    ("M23", Refused(SD_FILE)),
    ("M24", Refused(SD_FILE)),
    ("M25", Intercepted),
    ("M26", Refused(SD_FILE)),
    ("M27", Allowed),
    ("M28", Refused("makes the printer write every later line to its SD card instead of running it (Marlin queue.cpp:654-679, Ultimaker2Marlin Marlin_main.cpp:492-503), until an M29")),
    ("M29", Guarded("ends writing a file to the SD card")),
    ("M30", Guarded("deletes a file from the printer's SD card")),
    ("M31", Allowed),
    ("M32", Refused(SD_FILE)),
    ("M33", Allowed),
    ("M34", Guarded("changes the SD card's sorting")),
    ("M42", Guarded("sets a pin of the controller directly, outside the firmware's safety checks")),
    ("M43", Guarded("toggles the controller's pins for debugging")),
    ("M48", Guarded("probes the bed repeatedly, moving the head where the motion checks cannot follow")),
    ("M73", Allowed),
    ("M75", Allowed),
    ("M76", Allowed),
    ("M77", Allowed),
    ("M78", Allowed),
    ("M80", Allowed),
    ("M81", Guarded("switches the printer's power supply off, so the host loses the printer")),
    ("M82", Checked),
    ("M83", Checked),
    ("M84", Allowed),
    ("M85", Guarded("sets an inactivity timeout that halts the printer")),
    ("M86", Allowed),
    ("M87", Allowed),
    ("M92", Guarded("changes the steps per mm, scaling every later move")),
    ("M100", Allowed),
    ("M102", Guarded("changes the bed probe's mode")),
    ("M104", Checked),
    ("M105", Allowed),
    ("M106", Allowed),
    ("M107", Allowed),
    ("M108", Refused("breaks a heat wait: a Marlin 2 built with EMERGENCY_PARSER acts on it as soon as it arrives (feature/e_parser.h), ending the file's own M109/M190 before the lines sent ahead of it")),
    ("M109", Checked),
    ("M110", Refused("sets the line number, which belongs to the host: the next line would be refused and resent")),
    ("M111", Refused("changes the firmware's debug flags, and with them what it prints and whether it heats or extrudes at all (dry run)")),
    ("M112", Guarded("halts the printer (emergency stop); a file has no business halting it")),
    ("M113", Refused("changes the busy keepalive the host relies on to tell a long command from a lost printer")),
    ("M114", Allowed),
    ("M115", Allowed),
    ("M117", Allowed),
    ("M118", Checked),
    ("M119", Allowed),
    ("M120", Allowed),
    ("M121", Guarded("switches the endstops off")),
    ("M122", Allowed),
    ("M123", Allowed),
    ("M125", Intercepted),
    ("M126", Refused(NO_HARDWARE)),
    ("M127", Refused(NO_HARDWARE)),
    ("M128", Refused(NO_HARDWARE)),
    ("M129", Refused(NO_HARDWARE)),
    ("M140", Checked),
    ("M141", Checked),
    ("M143", Refused(NO_HARDWARE)),
    ("M145", Checked),
    ("M149", Checked),
    ("M150", Allowed),
    ("M154", Refused("makes the printer report its position by itself, answers that belong to the host")),
    ("M155", Refused("changes the temperature reports the host relies on to watch the printer")),
    ("M163", Refused(NO_HARDWARE)),
    ("M164", Refused(NO_HARDWARE)),
    ("M165", Refused(NO_HARDWARE)),
    ("M166", Refused(NO_HARDWARE)),
    ("M190", Checked),
    ("M191", Checked),
    ("M192", Allowed),
    ("M193", Refused(NO_HARDWARE)),
    ("M200", Allowed),
    ("M201", Allowed),
    ("M202", Allowed),
    ("M203", Allowed),
    ("M204", Allowed),
    ("M205", Allowed),
    ("M206", Guarded("changes the home offsets, shifting every later job")),
    ("M207", Allowed),
    ("M208", Allowed),
    ("M209", Allowed),
    ("M211", Guarded("with S0 switches the software endstops off, so moves may run into the frame")),
    ("M217", Guarded("changes the tool-change settings")),
    ("M218", Guarded("changes a hotend's offset")),
    ("M220", Allowed),
    ("M221", Allowed),
    ("M226", Intercepted),
    ("M240", Allowed),
    ("M250", Allowed),
    ("M255", Allowed),
    ("M256", Allowed),
    ("M260", Guarded("sends bytes on the controller's I2C bus")),
    ("M261", Guarded("reads the controller's I2C bus")),
    ("M280", Guarded("moves a servo (a probe's, a tool changer's)")),
    ("M281", Guarded("changes a servo's angles")),
    ("M282", Guarded("detaches a servo")),
    ("M290", Refused("babysteps the head (Z into the bed, by any amount), which the motion checks cannot follow")),
    ("M300", Allowed),
    ("M301", Guarded("changes the hotend's PID values")),
    ("M302", Guarded("with P or S allows cold extrusion, grinding filament through a cold nozzle")),
    ("M303", Guarded("runs a PID autotune: heats with no print (to its S target) and changes the PID values")),
    ("M304", Guarded("changes the bed's PID values")),
    ("M305", Guarded("changes a thermistor's parameters, so temperatures read wrong")),
    ("M306", Guarded("changes or autotunes the hotend's model-predictive control")),
    ("M350", Guarded("changes the microstepping, scaling every later move")),
    ("M351", Guarded("sets the microstepping pins directly")),
    ("M355", Allowed),
    ("M360", Refused(NO_HARDWARE)),
    ("M361", Refused(NO_HARDWARE)),
    ("M362", Refused(NO_HARDWARE)),
    ("M363", Refused(NO_HARDWARE)),
    ("M364", Refused(NO_HARDWARE)),
    ("M380", Refused(NO_HARDWARE)),
    ("M381", Refused(NO_HARDWARE)),
    ("M400", Allowed),
    ("M401", Guarded("deploys the bed probe")),
    ("M402", Guarded("stows the bed probe")),
    ("M403", Allowed),
    ("M404", Guarded("changes the nominal filament width, scaling every extrusion")),
    ("M405", Guarded("turns on filament width compensation, scaling every extrusion")),
    ("M406", Allowed),
    ("M407", Allowed),
    ("M410", Refused("stops every move at once, so the printer no longer knows where the head is")),
    ("M412", Allowed),
    ("M413", Guarded("switches power-loss recovery on or off, a setting kept with M500")),
    ("M420", Allowed),
    ("M421", Refused("edits a point of the bed mesh, shifting the nozzle's height where the motion checks cannot see")),
    ("M422", Guarded("changes the Z stepper alignment points")),
    ("M423", Guarded("changes the X-twist compensation")),
    ("M425", Guarded("changes the backlash compensation")),
    ("M428", Guarded("sets the home offsets from the head's position, shifting every later job")),
    ("M430", Allowed),
    ("M486", Allowed),
    ("M500", Guarded("saves the printer's settings to EEPROM, so whatever the file changed outlives every job")),
    ("M501", Guarded("reloads the settings from EEPROM, dropping what the operator set since")),
    ("M502", Guarded("resets every setting to the firmware's defaults (calibrated steps, PID, offsets; for good with M500)")),
    ("M503", Allowed),
    ("M504", Allowed),
    ("M510", Guarded("locks the machine until it is unlocked with a passcode")),
    ("M511", Guarded("unlocks the machine")),
    ("M512", Guarded("sets the machine's passcode")),
    ("M524", Refused(SD_FILE)),
    ("M540", Guarded("changes whether an endstop hit aborts the print")),
    ("M552", Guarded("changes the printer's network address")),
    ("M553", Guarded("changes the printer's network mask")),
    ("M554", Guarded("changes the printer's network gateway")),
    ("M569", Guarded("changes the stepper drivers' mode")),
    ("M575", Guarded("changes the serial port's baud rate, so the host loses the printer")),
    ("M592", Allowed),
    ("M593", Allowed),
    ("M600", Intercepted),
    ("M601", Intercepted),
    ("M602", Guarded("resumes a print paused on the printer")),
    ("M603", Guarded("changes the filament-change lengths")),
    ("M605", Guarded("changes the dual-nozzle mode")),
    ("M665", Guarded("changes a delta's geometry")),
    ("M666", Guarded("changes the endstop adjustments")),
    ("M672", Guarded("changes the Duet smart effector's sensitivity")),
    ("M701", Guarded("loads filament: extrudes its own length, parking where the firmware is set to")),
    ("M702", Guarded("unloads filament: retracts its own length, parking where the firmware is set to")),
    ("M710", Allowed),
    ("M808", Guarded("repeats a part of a file printed from the SD card")),
    ("M810", Refused("runs or sets a G-code macro, whose lines no check has read")),
    ("M811", Refused("runs or sets a G-code macro, whose lines no check has read")),
    ("M812", Refused("runs or sets a G-code macro, whose lines no check has read")),
    ("M813", Refused("runs or sets a G-code macro, whose lines no check has read")),
    ("M814", Refused("runs or sets a G-code macro, whose lines no check has read")),
    ("M815", Refused("runs or sets a G-code macro, whose lines no check has read")),
    ("M816", Refused("runs or sets a G-code macro, whose lines no check has read")),
    ("M817", Refused("runs or sets a G-code macro, whose lines no check has read")),
    ("M818", Refused("runs or sets a G-code macro, whose lines no check has read")),
    ("M819", Refused("runs or sets a G-code macro, whose lines no check has read")),
    ("M851", Guarded("changes the probe's offset, the nozzle's distance to the bed")),
    ("M852", Guarded("changes the bed skew compensation")),
    ("M860", Guarded("changes the I2C position encoders")),
    ("M861", Guarded("changes the I2C position encoders")),
    ("M862", Guarded("changes the I2C position encoders")),
    ("M863", Guarded("changes the I2C position encoders")),
    ("M864", Guarded("changes the I2C position encoders")),
    ("M865", Guarded("changes the I2C position encoders")),
    ("M866", Guarded("changes the I2C position encoders")),
    ("M867", Guarded("changes the I2C position encoders")),
    ("M868", Guarded("changes the I2C position encoders")),
    ("M869", Guarded("changes the I2C position encoders")),
    ("M871", Guarded("changes the probe temperature compensation")),
    ("M876", Refused("answers a host prompt, which belongs to the host")),
    ("M900", Allowed),
    ("M906", Guarded("changes the stepper motor currents (too high overheats drivers and motors)")),
    ("M907", Guarded("changes the stepper motor currents (too high overheats drivers and motors)")),
    ("M908", Guarded("changes a digital potentiometer's motor current")),
    ("M909", Guarded("changes the stepper drivers' settings")),
    ("M910", Guarded("changes the stepper drivers' settings")),
    ("M911", Allowed),
    ("M912", Guarded("changes the stepper drivers' settings")),
    ("M913", Guarded("changes the stepper drivers' hybrid thresholds")),
    ("M914", Guarded("changes the sensorless homing thresholds, so homing may drive into the frame")),
    ("M915", Guarded("drives the Z axis into its end to align it")),
    ("M916", Guarded("tunes the stepper drivers' thermal limits")),
    ("M917", Guarded("changes the stepper motor currents (too high overheats drivers and motors)")),
    ("M918", Guarded("changes the stepper drivers' settings")),
    ("M919", Guarded("changes the stepper drivers' settings")),
    ("M928", Guarded("starts logging to a file on the SD card")),
    ("M951", Guarded("changes the magnetic parking extruder's settings")),
    ("M993", Guarded("backs up the SPI flash to the SD card")),
    ("M994", Guarded("restores the SPI flash from the SD card")),
    ("M995", Guarded("calibrates the touch screen")),
    ("M997", Guarded("starts a firmware update")),
    ("M999", Refused("resets the printer's line count (Ultimaker2Marlin Marlin_main.cpp:2329-2333) or asks the host to resend from its last line (Marlin M999.cpp:44), which belongs to the host")),
    ("T0", Checked),
];

/// Ultimaker2Marlin's commands where it differs from Marlin 2 (its `process_command`):
/// its own `M605`/`M606` (store and recall the print settings) and `M923` (start an SD
/// file); its display commands `M10000`-`M10010` are past the numbers read alike, so the
/// reader refuses them. The rest it shares, or answers `Unknown command`.
pub(crate) const ULTIMAKER2: &[(&str, Class)] = &[
    (
        "M605",
        Guarded("stores the print settings, which the next M606 restores"),
    ),
    (
        "M606",
        Guarded("restores print settings stored before the job"),
    ),
    ("M923", Refused(SD_FILE)),
];

/// The class of `code` (`G1`, `M104`, `T3`) on `firmware`; `None` for a command the table
/// does not know.
pub(crate) fn classify(firmware: Firmware, code: &str) -> Option<Class> {
    if code.starts_with('T') {
        return Some(Checked);
    }
    if firmware == Firmware::Ultimaker2 {
        if let Some((_, class)) = ULTIMAKER2.iter().find(|(c, _)| *c == code) {
            return Some(*class);
        }
    }
    MARLIN2
        .iter()
        .find(|(c, _)| *c == code)
        .map(|(_, class)| *class)
}

/// Whether `code` (upper case) is a command a machine may allow: one the table guards,
/// or one it does not know (a vendor's own command).
pub(crate) fn allowable(code: &str) -> bool {
    let plain = code.len() > 1
        && matches!(code.as_bytes()[0], b'G' | b'M')
        && code[1..].bytes().all(|b| b.is_ascii_digit())
        && !code[1..].starts_with('0');
    plain
        && Firmware::ALL
            .iter()
            .all(|&fw| matches!(classify(fw, code), None | Some(Class::Guarded(_))))
}

/// The commands the table guards, for messages.
pub(crate) fn guarded() -> impl Iterator<Item = &'static str> {
    MARLIN2
        .iter()
        .chain(ULTIMAKER2)
        .filter(|(_, class)| matches!(class, Class::Guarded(_)))
        .map(|(code, _)| *code)
}

/// The table as Markdown, as docs/gcode-policy.md shows it (a test keeps the two equal).
#[cfg(test)]
pub(crate) fn markdown() -> String {
    let mut out =
        String::from("| Command | Marlin 2 | Ultimaker2Marlin | Why |\n|---|---|---|---|\n");
    let name = |class: Option<Class>| match class {
        Some(Allowed) => "allowed",
        Some(Checked) => "checked",
        Some(Intercepted) => "intercepted",
        Some(Guarded(_)) => "refused unless allowed",
        Some(Refused(_)) => "refused",
        None => "refused unless allowed (unknown)",
    };
    let why = |class: Option<Class>| match class {
        Some(Guarded(w) | Refused(w)) => w,
        _ => "",
    };
    // Marlin 2's commands, then Ultimaker2Marlin's own (M605 is in both: once).
    let mut seen = Vec::new();
    for &(code, _) in MARLIN2.iter().chain(ULTIMAKER2) {
        if seen.contains(&code) {
            continue;
        }
        seen.push(code);
        let (m, u) = (
            classify(Firmware::Marlin2, code),
            classify(Firmware::Ultimaker2, code),
        );
        let code_shown = if code == "T0" { "T<n>" } else { code };
        let reason = if why(m) == why(u) || why(u).is_empty() {
            why(m).to_string()
        } else if why(m).is_empty() {
            why(u).to_string()
        } else {
            format!("Marlin 2: {}; Ultimaker2Marlin: {}", why(m), why(u))
        };
        out += &format!(
            "| `{code_shown}` | {} | {} | {reason} |\n",
            name(m),
            name(u)
        );
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn each_command_is_listed_once_with_a_reason_where_refused() {
        for table in [MARLIN2, ULTIMAKER2] {
            for (i, (code, class)) in table.iter().enumerate() {
                assert!(
                    !table[..i].iter().any(|(c, _)| c == code),
                    "{code} listed twice"
                );
                if let Class::Guarded(why) | Class::Refused(why) = class {
                    assert!(why.len() > 10, "{code}");
                }
            }
        }
    }

    /// docs/gcode-policy.md shows the table as it is.
    #[test]
    fn the_documented_table_is_the_table() {
        let doc = include_str!("../../../../docs/gcode-policy.md");
        assert!(
            doc.contains(&markdown()),
            "docs/gcode-policy.md's command table differs from the code; its text is:\n{}",
            markdown()
        );
    }

    #[test]
    fn unknown_and_guarded_commands_may_be_allowed_nothing_else() {
        assert!(allowable("M500") && allowable("M211") && allowable("G29"));
        assert!(allowable("M1234"), "a vendor's own command");
        for code in [
            "M104", "G1", "M110", "M118", "M290", "M923", "T0", "M0500", "X1", "M",
        ] {
            assert!(!allowable(code), "{code}");
        }
        assert_eq!(classify(Firmware::Marlin2, "T7"), Some(Class::Checked));
        assert_eq!(classify(Firmware::Marlin2, "M1234"), None);
        assert!(matches!(
            classify(Firmware::Ultimaker2, "M605"),
            Some(Class::Guarded(_))
        ));
    }
}
