//! The commands the G-code policy (the `policy` module of `slice`) refuses in files unless a
//! machine allows them by name (`allow = ["M500"]` in its `[[machine]]` table). Kept here,
//! with the machine, because a machine's table is checked against it: only these words
//! may be allowed.

/// Commands refused in files unless the machine allows them by name, with what they do.
/// Conditions (`M211` only with `S0`...) are the policy's
/// (its `refused`).
pub const REFUSED: &[(&str, &str)] = &[
    ("M500", "saves the printer's settings to EEPROM, so whatever the file changed outlives every job"),
    ("M501", "reloads the settings from EEPROM, dropping what the operator set since"),
    ("M502", "resets every setting to the firmware's defaults (calibrated steps, PID, offsets; for good with M500)"),
    ("M997", "starts a firmware update"),
    ("M28", "writes a file to the printer's SD card"),
    ("M29", "ends writing a file to the SD card"),
    ("M30", "deletes a file from the printer's SD card"),
    ("M928", "starts logging to a file on the SD card"),
    ("M211", "with S0 switches the software endstops off, so moves may run into the frame"),
    ("M302", "with P or S allows cold extrusion, grinding filament through a cold nozzle"),
    ("M112", "halts the printer (emergency stop); a file has no business halting it"),
    ("M999", "restarts a halted printer"),
    ("M92", "changes the steps per mm until the printer is reset (for good with M500)"),
    ("M301", "changes the hotend's PID values until the printer is reset (for good with M500)"),
    ("M304", "changes the bed's PID values until the printer is reset (for good with M500)"),
    ("M303", "runs a PID autotune: heats with no print and changes the PID values"),
    ("M306", "changes or autotunes the hotend's model-predictive control (for good with M500)"),
    ("M851", "changes the probe's offset, the nozzle's distance to the bed, until reset (for good with M500)"),
    ("M206", "changes the home offsets until the printer is reset, shifting every later job (for good with M500)"),
    ("M428", "sets the home offsets from the head's position, shifting every later job"),
    ("M218", "changes a hotend's offset until the printer is reset (for good with M500)"),
    ("M665", "changes a delta's geometry until the printer is reset (for good with M500)"),
    ("M666", "changes the endstop adjustments until the printer is reset (for good with M500)"),
    ("M350", "changes the microstepping, scaling every move until reset"),
    ("M906", "changes the stepper motor currents (too high overheats drivers and motors)"),
    ("M907", "changes the stepper motor currents (too high overheats drivers and motors)"),
    ("M42", "sets a pin of the controller directly, outside the firmware's safety checks"),
    ("M43", "toggles the controller's pins for debugging"),
    ("M121", "switches the endstops off"),
    ("M575", "changes the serial port's baud rate, so the host loses the printer"),
];

/// Whether `code` (`M500`) is a command a machine may allow: one of [`REFUSED`].
pub fn allowable(code: &str) -> bool {
    REFUSED.iter().any(|(c, _)| *c == code)
}
