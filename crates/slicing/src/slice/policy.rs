//! The G-code policy: what a file may ask of a printer, checked once when a job is
//! prepared, before any printer claims it. Anyone who may upload decides what every printer
//! of a folder executes, so every G-code crispen streams (pre-sliced files, uploads, its own
//! slicers' output: a custom profile's start code is G-code too) passes through [`check`]:
//!
//! - temperatures above the machine's limits (`max_hotend_c`, `max_bed_c`; a chamber the
//!   machine does not have), temperature units it cannot follow (`M149 F`/`K`), tools the
//!   machine does not have (`T1` on one extruder) are refused;
//! - each line is read as the machine's firmware reads it ([`crispen_marlin::reader`]); a
//!   line it cannot take as exactly one command with known parameters is refused;
//! - every command is classified ([`crate::machine::commands`]): commands that change a
//!   printer beyond the job (EEPROM, firmware update, settings that outlive the job,
//!   SD-card writes, endstops off, cold extrusion, halts), or move the head where the
//!   follower cannot, and every command the table does not know, are refused unless the
//!   machine allows the command by name (`allow = ["M500"]`); commands that belong to the
//!   host or to hardware no machine has are refused always;
//! - every move is followed ([`crispen_marlin::motion`]) and must stay on the bed, arcs included;
//!   what cannot be followed is refused;
//! - pauses the file asks for ([`FILE_PAUSES`](crispen_marlin::reader::FILE_PAUSES)) are not refused: the host intercepts them;
//!   the verdict lists them with the message the host will show
//!   ([`crispen_marlin::pause::pause_message`]).
//!
//! [`check`] is pure over a reader; [`check_file`] adds the host's own load-time checks
//! ([`crispen_marlin::gcode::GcodeProgram`]: text, line length, characters the firmware
//! cannot take), so a file that cannot be streamed fails here too. Every refusal names the
//! file's line, the command and why.

use crate::machine::commands::{classify, Class};
use crate::machine::Machine;
use crispen_marlin::motion::{Bounds, Command, Motion};
use crispen_marlin::pause::pause_message;
use crispen_marlin::protocol::reply::Reply;
use crispen_marlin::reader;
use serde::{Deserialize, Serialize};
use std::io::{BufRead, Read};
use std::path::Path;

/// The most refusals and pauses a verdict lists (it counts them all).
pub const MAX_LISTED: usize = 20;
/// Allowance at the bed's edges for rounding, mm (as the other checks).
const EDGE_MM: f64 = 0.5;
/// The longest command text quoted in a message.
const QUOTED_CHARS: usize = 60;

/// Why a file may not be printed on a machine, at one line.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Refusal {
    pub line: usize,
    /// The command as written (cut to a readable length).
    pub command: String,
    pub reason: String,
}

impl std::fmt::Display for Refusal {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "line {}: `{}` {}", self.line, self.command, self.reason)
    }
}

/// A pause the file asks for (intercepted by the host, not refused).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Pause {
    pub line: usize,
    pub command: String,
    /// The operator's message: the command's own text, else the last `M117` before it.
    pub message: String,
}

/// What the policy found in one file for one machine.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct Verdict {
    /// The first [`MAX_LISTED`] refusals.
    pub refusals: Vec<Refusal>,
    pub refusals_total: usize,
    /// The first [`MAX_LISTED`] pauses.
    pub pauses: Vec<Pause>,
    pub pauses_total: usize,
    /// Commands the machine's `allow` let through, with their count.
    #[serde(default)]
    pub allowed: Vec<(String, usize)>,
    pub lines: usize,
}

impl Verdict {
    pub fn passed(&self) -> bool {
        self.refusals_total == 0
    }

    /// One line for the job's report: "passed, 2 pauses (line 40: M0 ...)" or the refusals.
    pub fn summary(&self) -> String {
        if !self.passed() {
            let listed: Vec<String> = self.refusals.iter().map(ToString::to_string).collect();
            let more = self.refusals_total - self.refusals.len();
            return format!(
                "refused by the G-code policy: {}{}",
                listed.join("; "),
                if more > 0 {
                    format!("; and {more} more")
                } else {
                    String::new()
                }
            );
        }
        let mut s = match self.pauses_total {
            0 => "passed the G-code policy, no pauses".to_string(),
            1 => "passed the G-code policy, 1 pause".to_string(),
            n => format!("passed the G-code policy, {n} pauses"),
        };
        if !self.pauses.is_empty() {
            let listed: Vec<String> = self
                .pauses
                .iter()
                .map(|p| format!("line {}: {} {:?}", p.line, p.command, p.message))
                .collect();
            s += &format!(" ({})", listed.join("; "));
        }
        if !self.allowed.is_empty() {
            let listed: Vec<String> = self
                .allowed
                .iter()
                .map(|(c, n)| format!("{c} x{n}"))
                .collect();
            s += &format!("; allowed by the machine: {}", listed.join(", "));
        }
        s
    }

    fn refuse(&mut self, line: usize, command: &str, reason: String) {
        self.refusals_total += 1;
        if self.refusals.len() < MAX_LISTED {
            self.refusals.push(Refusal {
                line,
                command: quote(command),
                reason,
            });
        }
    }
}

/// The command as shown in a refusal: shortened, and a control character written out
/// (`\r`), so that a line end inside a line cannot break the report's lines.
fn quote(command: &str) -> String {
    let c = command.trim();
    let shown = |c: char| -> String {
        if c.is_control() {
            c.escape_default().to_string()
        } else {
            c.to_string()
        }
    };
    let text: String = c.chars().take(QUOTED_CHARS).map(shown).collect();
    if c.chars().count() > QUOTED_CHARS {
        format!("{text}...")
    } else {
        text
    }
}

/// Whether a guarded command, with these parameters, is refused unless allowed: `M211`
/// only switching the endstops off (`S0`), `M302` only allowing cold extrusion (`P`, `S`);
/// every other guarded command always.
fn guard_applies(cmd: &Command) -> bool {
    match cmd.code.as_str() {
        "M211" => cmd.has('S') && cmd.get('S') != Some(1.0),
        "M302" => cmd.has('P') || cmd.has('S'),
        _ => true,
    }
}

/// Reads the file's commands as the machine's firmware reads them and judges them for
/// `machine`. Fails only when the reader fails.
pub fn check(reader: impl BufRead, machine: &Machine) -> std::io::Result<Verdict> {
    let mut v = Verdict::default();
    let mut motion = Motion::new(machine.firmware);
    let mut shown = None;
    let mut allowed: Vec<(String, usize)> = Vec::new();
    let mut raw = Vec::new();
    let mut reader = reader;
    let mut number = 0usize;
    loop {
        raw.clear();
        // Lines are bounded by the host's load check; here a long one is read whole only
        // up to a limit, and the rest of it skipped.
        let n = reader
            .by_ref()
            .take(crispen_marlin::gcode::MAX_RAW_LINE_BYTES)
            .read_until(b'\n', &mut raw)?;
        if n == 0 {
            break;
        }
        number += 1;
        if raw.last() != Some(&b'\n') && n as u64 == crispen_marlin::gcode::MAX_RAW_LINE_BYTES {
            v.refuse(number, "", "is longer than a printer can take".into());
            let mut sink = Vec::new();
            reader.read_until(b'\n', &mut sink)?;
            continue;
        }
        let code = match raw.iter().position(|&b| b == b';') {
            Some(i) => &raw[..i],
            None => &raw[..],
        };
        let Ok(code) = std::str::from_utf8(code) else {
            v.refuse(number, "", "is not text (UTF-8)".into());
            continue;
        };
        // A plate's labels are read by the host, which never sends them.
        if crispen_marlin::labels::is_label_command(code) {
            continue;
        }
        let cmd = match reader::read_for(machine.firmware, code) {
            Ok(Some(cmd)) => cmd,
            Ok(None) => continue,
            Err(why) => {
                v.refuse(
                    number,
                    code,
                    format!("{why}; refused on the {}", machine.name),
                );
                continue;
            }
        };
        judge(
            &cmd,
            code,
            number,
            machine,
            &mut motion,
            &mut v,
            &mut allowed,
            &mut shown,
        );
    }
    v.lines = number;
    v.allowed = allowed;
    Ok(v)
}

#[allow(clippy::too_many_arguments)]
fn judge(
    cmd: &Command,
    text: &str,
    line: usize,
    machine: &Machine,
    motion: &mut Motion,
    v: &mut Verdict,
    allowed: &mut Vec<(String, usize)>,
    shown: &mut Option<String>,
) {
    let code = cmd.code.as_str();
    let class = classify(machine.firmware, code);
    // Every command, so that the display's message is followed for the pauses after it.
    if let Some(message) = pause_message(cmd, shown) {
        v.pauses_total += 1;
        if v.pauses.len() < MAX_LISTED {
            v.pauses.push(Pause {
                line,
                command: quote(text),
                message,
            });
        }
        return;
    }
    let guarded = match class {
        // Pauses were listed above.
        Some(Class::Intercepted) => return,
        Some(Class::Refused(what)) => {
            v.refuse(line, text, format!("{what}; refused on every machine"));
            return;
        }
        Some(Class::Guarded(what)) if guard_applies(cmd) => Some(what.to_string()),
        None => Some(format!(
            "is no command the G-code policy knows for {} firmware",
            machine.firmware
        )),
        Some(Class::Guarded(_) | Class::Allowed | Class::Checked) => None,
    };
    if let Some(what) = guarded {
        if !machine.allow.iter().any(|a| a == code) {
            v.refuse(
                line,
                text,
                format!(
                    "{what}; refused on the {} (a machine may allow it: `allow = [\"{code}\"]`)",
                    machine.name
                ),
            );
            return;
        }
        match allowed.iter_mut().find(|(c, _)| c == code) {
            Some((_, n)) => *n += 1,
            None => allowed.push((code.to_string(), 1)),
        }
    }
    if code == "M118" {
        if let Some(reason) = echo_taken_for_an_answer(cmd.rest) {
            v.refuse(line, text, reason);
            return;
        }
    }
    // Temperatures count whatever the class: an allowed G26 or M303 heats too.
    if let Some(reason) = temperature(cmd, machine) {
        v.refuse(line, text, reason);
        return;
    }
    if let Some(tool) = code.strip_prefix('T') {
        let t: u64 = tool.parse().unwrap_or(u64::MAX);
        if t >= u64::from(machine.extruders) {
            v.refuse(
                line,
                text,
                format!(
                    "selects tool {tool}, but the {} has {} extruder{}",
                    machine.name,
                    machine.extruders,
                    if machine.extruders == 1 { "" } else { "s" }
                ),
            );
        }
        return;
    }
    match motion.apply(cmd) {
        Err(e) => v.refuse(line, text, format!("cannot be followed: {e}")),
        Ok(Some(m)) => match m.bounds(machine.bed_mm, EDGE_MM) {
            Bounds::Inside => {}
            Bounds::Outside(k) => {
                let axis = ['X', 'Y', 'Z'][k];
                let past = if m.lo[k] < -EDGE_MM { m.lo[k] } else { m.hi[k] };
                v.refuse(
                    line,
                    text,
                    format!(
                        "{} {axis} to {past:.1} mm, outside the {}'s 0 .. {} mm",
                        if m.curved { "sweeps" } else { "moves" },
                        machine.name,
                        machine.bed_mm[k]
                    ),
                );
            }
            Bounds::Rounding(k) => {
                let axis = ['X', 'Y', 'Z'][k];
                v.refuse(
                    line,
                    text,
                    format!(
                        "{} {axis} to the edge of the {}'s 0 .. {} mm, inside or outside as \
                         the firmware's 32-bit floats round it ({:.6} .. {:.6} mm) or as \
                         the file writes it ({:.6} .. {:.6} mm)",
                        if m.curved { "sweeps" } else { "moves" },
                        machine.name,
                        machine.bed_mm[k],
                        m.lo[k],
                        m.hi[k],
                        m.written.0[k],
                        m.written.1[k]
                    ),
                );
            }
        },
        Ok(None) => {}
    }
}

/// Why `M118 <text>` is refused, if it is: the line Marlin prints for it (`echo:` before it
/// with `E1`, `//` with `A1`, as its `M118` handler takes those words off the front) is
/// read by the host's own reply parser, and anything but an inert message (an `ok`, a
/// resend request, an error, a temperature report, a busy or action line) would be taken
/// for the printer's answer.
fn echo_taken_for_an_answer(text: &str) -> Option<String> {
    let mut rest = text;
    let (mut echo, mut action) = (false, false);
    for _ in 0..3 {
        let b = rest.as_bytes();
        let word = match (b.first(), b.get(1)) {
            (Some(b'A'), Some(b'1')) => {
                action = true;
                true
            }
            (Some(b'E'), Some(b'1')) => {
                echo = true;
                true
            }
            (Some(b'P'), Some(d)) if d.is_ascii_digit() => true,
            _ => false,
        };
        if !word {
            break;
        }
        rest = rest[2..].trim_start_matches(' ');
    }
    let printed = format!(
        "{}{}{rest}",
        if echo { "echo:" } else { "" },
        if action { "//" } else { "" }
    );
    match Reply::parse(printed.as_bytes()) {
        None | Some(Reply::Other(_)) => None,
        Some(reply) => Some(format!(
            "prints `{printed}` on the serial line, which the host would read as the \
             printer's own answer ({reply:?})"
        )),
    }
}

/// Why a command's temperatures are refused on `machine`, if they are: every parameter
/// that sets a heater's target counts (`S`, `R`, `B` of `M104`/`M109`, `M145`'s presets,
/// `G26`'s pattern, an autotune's target, RepRapFirmware's tool temperatures); a preset
/// chosen by number (`I`) is refused, since the file does not say its temperature.
fn temperature(cmd: &Command, machine: &Machine) -> Option<String> {
    let hotend = ("hotend", machine.max_hotend_c);
    let bed = ("bed", machine.max_bed_c);
    let chamber = ("chamber", 0.0);
    let targets: &[(char, (&str, f64))] = match cmd.code.as_str() {
        "M104" | "M109" => &[('S', hotend), ('R', hotend), ('B', hotend)],
        "M140" | "M190" => &[('S', bed), ('R', bed)],
        "M141" | "M191" => &[('S', chamber), ('R', chamber)],
        "M145" | "G26" => &[('H', hotend), ('B', bed)],
        // M303 E-1 tunes the bed; its default target (150 °C) is under every hotend limit.
        "M303" if cmd.get('E') == Some(-1.0) => &[('S', bed)],
        "M303" => &[('S', hotend)],
        // RepRapFirmware's tool temperatures: no Marlin command, but a file made for
        // another printer may hold them.
        "M568" | "G10" => &[('S', hotend), ('R', hotend)],
        "M149" => {
            return (cmd.has('F') || cmd.has('K')).then(|| {
                "switches temperatures to Fahrenheit or Kelvin, which the limits cannot \
                 follow"
                    .to_string()
            })
        }
        _ => return None,
    };
    if matches!(cmd.code.as_str(), "M104" | "M109" | "M140" | "M190") && cmd.has('I') {
        return Some(
            "heats to a material preset chosen by number (I), whose temperature the file \
             does not say"
                .to_string(),
        );
    }
    let tool = match cmd.code.as_str() {
        "M104" | "M109" => cmd.get('T'),
        "M303" => cmd.get('E').filter(|e| *e >= 0.0),
        _ => None,
    };
    if let Some(t) = tool {
        if t < 0.0 || t >= f64::from(machine.extruders) {
            return Some(format!(
                "sets the temperature of tool {t}, but the {} has {} extruder{}",
                machine.name,
                machine.extruders,
                if machine.extruders == 1 { "" } else { "s" }
            ));
        }
    }
    for &(letter, (what, limit)) in targets {
        let Some(t) = cmd.get(letter) else { continue };
        if what == "chamber" && t > 0.0 {
            return Some(format!(
                "asks for a {t} °C chamber, but the {} has no chamber heater",
                machine.name
            ));
        }
        if t > limit {
            let given = if letter == 'S' {
                String::new()
            } else {
                format!(" (given as {letter})")
            };
            return Some(format!(
                "asks for {t} °C on the {what}{given}, above the {}'s limit of {limit} °C",
                machine.name
            ));
        }
    }
    None
}

/// Why a G-code file cannot be used at all.
#[derive(Debug, thiserror::Error)]
pub enum PolicyError {
    /// The host would refuse to load it (the message names the file and line).
    #[error(transparent)]
    Load(#[from] crispen_marlin::gcode::GcodeError),
    #[error("cannot read {path}: {source}")]
    Io {
        path: std::path::PathBuf,
        #[source]
        source: std::io::Error,
    },
}

/// The host's own load-time checks for a firmware ([`GcodeProgram::load_for`]: size,
/// text, line length, characters the firmware cannot take), without keeping the program.
///
/// [`GcodeProgram::load_for`]: crispen_marlin::gcode::GcodeProgram::load_for
pub(crate) fn load_check(
    path: &Path,
    firmware: crispen_marlin::firmware::Firmware,
) -> Result<(), PolicyError> {
    crispen_marlin::gcode::GcodeProgram::load_for(path, firmware)?;
    Ok(())
}

/// [`check`] on a file.
pub fn check_path(path: &Path, machine: &Machine) -> Result<Verdict, PolicyError> {
    let io = |source| PolicyError::Io {
        path: path.to_path_buf(),
        source,
    };
    let file = std::fs::File::open(path).map_err(io)?;
    check(std::io::BufReader::new(file), machine).map_err(io)
}

/// The host's load-time checks for the machine's firmware, then [`check`]: what a job
/// preparation runs on every G-code file before a printer may claim it.
pub(crate) fn check_file(path: &Path, machine: &Machine) -> Result<Verdict, PolicyError> {
    load_check(path, machine.firmware)?;
    check_path(path, machine)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn um2() -> Machine {
        Machine::builtin("ultimaker2").unwrap()
    }

    fn verdict(text: &str, machine: &Machine) -> Verdict {
        check(text.as_bytes(), machine).unwrap()
    }

    const CLEAN: &str = "M104 S210\nM140 S60\nG28\nM190 S60\nM109 S210\nG92 E0\n\
        G1 Z0.2 F600\nG1 X100 Y100\nG1 X110 Y100 E1.5\nM104 S0\nM140 S0\n";

    #[test]
    fn a_clean_file_passes() {
        let v = verdict(CLEAN, &um2());
        assert!(v.passed(), "{v:?}");
        assert_eq!(v.lines, 11);
        assert_eq!(v.summary(), "passed the G-code policy, no pauses");
    }

    #[test]
    fn temperatures_over_the_machines_limits_are_refused_with_line_and_limit() {
        let m = um2();
        for (text, says) in [
            (
                "M104 S400",
                "400 °C on the hotend, above the ultimaker2's limit of 260",
            ),
            ("M109 R300", "300 °C on the hotend"),
            ("M104S300", "300 °C"),
            (
                "M140 S150",
                "150 °C on the bed, above the ultimaker2's limit of 100",
            ),
            ("M190 S101", "101 °C on the bed"),
            ("M141 S40", "no chamber heater"),
            ("M104 T1 S200", "tool 1"),
            ("M104 Snan", "where a parameter belongs"),
            ("M149 F1", "Fahrenheit"),
            ("G10 P0 S300", "300 °C on the hotend"),
        ] {
            let v = verdict(&format!("G28\n{text}\n"), &m);
            assert_eq!(v.refusals_total, 1, "{text}: {v:?}");
            let r = &v.refusals[0];
            assert_eq!(r.line, 2, "{text}");
            assert!(r.to_string().contains(says), "{text}: {r}");
            assert!(r.to_string().contains(text), "{text}: {r}");
        }
        assert!(verdict("M104 S260\nM140 S100\nM141 S0\n", &m).passed());
    }

    /// Issue 31's findings and their kin, each refused before anything is sent, on both
    /// firmwares, with a reason naming the line.
    #[test]
    fn the_ways_around_the_policy_are_closed_on_every_firmware() {
        let marlin = Machine::builtin("marlin-175").unwrap();
        for machine in [um2(), marlin.clone()] {
            for text in [
                // Junk before a parameter hides it from a reader of its own.
                "M104 @S400",
                "M104 \"S400\"",
                "M104 (S400)",
                "M104 !S400",
                "M104 -S400",
                "M140 @S150",
                // Commands no list of refusals named.
                "M290 Z-5",
                "M421 I0 J0 Z-2",
                "G29 S3 I0 J0 Z-2",
                "M145 S0 H400",
                "M104 I0",
                "M140 I1",
                "G26 H400",
                "M908 P0 S255",
                "M917 T100",
                "M23 evil.gco",
                "M24",
                "M32 !evil.gco#",
                "M810 G28|M104 S400",
                "M81",
                "M413 S0",
                "M118 ok",
                "M118 E1 busy: processing",
                "M118 Resend: 3",
                "M118 A1 action:cancel",
                "M118 T:20 /300",
                "M110 N100",
                "M303 S400",
                "M155 S0",
                // A command the table does not know.
                "M1234 S400",
                "G7 X1",
            ] {
                let v = verdict(&format!("G28\n{text}\nG1 X10\n"), &machine);
                assert_eq!(v.refusals_total, 1, "{text} on {}: {v:?}", machine.name);
                assert_eq!(v.refusals[0].line, 2, "{text}");
                assert!(v.summary().contains("line 2"), "{text}");
            }
        }
        // Read as Ultimaker2Marlin reads them: an exponent, a G anywhere.
        for text in ["M104 S2.7E2", "M140 S1.5E2", "M400 G92 Z50", "M117 G92 Z60"] {
            let v = verdict(&format!("G28\n{text}\n"), &um2());
            assert_eq!(v.refusals_total, 1, "{text}: {v:?}");
            assert!(v.refusals[0].reason.contains("Ultimaker2Marlin"), "{v:?}");
        }
        // Marlin 2 reads them as written: S2.7 °C and a parameter E2; a message.
        for text in [
            "M104 S2.7E2",
            "M117 G92 Z60",
            "M400 G92 Z50",
            "M118 job 12 done",
        ] {
            assert!(verdict(&format!("{text}\n"), &marlin).passed(), "{text}");
        }
        // An allowed guarded command still has its temperatures checked.
        let allowing = Machine {
            allow: vec!["G26".into(), "M1234".into()],
            ..marlin.clone()
        };
        assert!(verdict("G26 H200 B60\nM1234 S1\n", &allowing).passed());
        assert_eq!(verdict("G26 H400\n", &allowing).refusals_total, 1);
    }

    /// Issue 42: lines the firmware's serial input would not take as the one line the
    /// host numbered, refused naming the firmware's source and what it would do: a message
    /// that renumbers Marlin 2 (`M110` anywhere, queue.cpp:463-470), a carriage return
    /// where both firmwares end a line, a backspace Marlin 2 erases with, codes an
    /// emergency parser acts on at once, commands that take the printer's count or its
    /// queue away from the host.
    #[test]
    fn lines_the_serial_input_would_not_take_whole_are_refused() {
        let marlin = Machine::builtin("marlin-175").unwrap();
        // The file.
        let file = "M104 S50\nM140 S35\nG28\nM109 S50\nM190 S35\nG90\nM82\nG92 E0\n\
                    G1 Z5 F600\nG1 X60 Y60 F3000\nG1 X100 Y60 E2\nM117 M110 N999\nM104 S0\n\
                    M140 S0\nG1 Z10\n";
        let v = verdict(file, &marlin);
        assert_eq!(v.refusals_total, 1, "{v:?}");
        let r = &v.refusals[0];
        assert_eq!(r.line, 12);
        assert!(
            r.reason.contains("queue.cpp:463") && r.reason.contains("999"),
            "{r}"
        );
        assert!(!verdict(file, &um2()).passed());
        for (text, says) in [
            ("M117 a\rM104 S300\rM117 b", "carriage return"),
            ("M117 x M110", "M110"),
            ("M117 \u{8}\u{8}\u{8}\u{8}\u{8}M104 S300", "backspace"),
            ("M108", "EMERGENCY_PARSER"),
            ("M4100", "e_parser.h"),
            ("M999", "line count"),
            ("M28 job.gco", "SD card"),
            ("M117 (unclosed", "PAREN_COMMENTS"),
        ] {
            let v = verdict(&format!("G28\n{text}\nG1 X10\n"), &marlin);
            assert_eq!(v.refusals_total, 1, "{text:?}: {v:?}");
            assert_eq!(v.refusals[0].line, 2, "{text:?}");
            assert!(v.refusals[0].reason.contains(says), "{text:?}: {v:?}");
            // The refusal shows a line end written out, never raw.
            assert!(!v.refusals[0].command.contains('\r'), "{text:?}");
        }
        // A colon is a line end only on Ultimaker2Marlin; a message may say `M108` after
        // its code; a backslash stands for itself there.
        assert!(verdict("M117 ETA 01:23\n", &marlin).passed());
        assert!(!verdict("M117 ETA 01:23\n", &um2()).passed());
        assert!(verdict("M117 press M108\n", &marlin).passed());
        assert!(verdict("M117 a\\b\n", &um2()).passed());
    }

    #[test]
    fn commands_that_change_a_printer_for_good_are_refused_unless_allowed() {
        let v = verdict("G28\nM502\nM500\nM997\n", &um2());
        assert_eq!(v.refusals_total, 3);
        assert_eq!(v.refusals[0].line, 2);
        assert!(v.refusals[0].reason.contains("defaults"), "{v:?}");
        assert!(v.refusals[1].reason.contains("EEPROM"), "{v:?}");
        assert!(v.refusals[2].reason.contains("firmware update"), "{v:?}");
        assert!(v
            .summary()
            .starts_with("refused by the G-code policy: line 2: `M502`"));
        for text in [
            "M211 S0",
            "M302 P1",
            "M92 E9999",
            "M303 E0 S200 C8",
            "M112",
            "M28 evil.g",
            "M30 x.g",
            "m0500",
            "M206 X-50",
            "M851 Z-5",
            "M575 B9600",
        ] {
            let v = verdict(&format!("{text}\n"), &um2());
            assert_eq!(v.refusals_total, 1, "{text}: {v:?}");
        }
        for text in [
            "M211",
            "M211 S1",
            "M302",
            "M420 S1",
            "M900 K0.05",
            "M204 S1000",
        ] {
            assert!(verdict(&format!("{text}\n"), &um2()).passed(), "{text}");
        }
        let allowing = Machine {
            allow: vec!["M500".into()],
            ..um2()
        };
        let v = verdict("G28\nM500\n", &allowing);
        assert!(v.passed(), "{v:?}");
        assert_eq!(v.allowed, [("M500".to_string(), 1)]);
        assert!(v.summary().contains("allowed by the machine: M500 x1"));
        assert!(!verdict("M502\n", &allowing).passed());
    }

    #[test]
    fn tools_the_machine_lacks_are_refused() {
        assert!(verdict("T0\n", &um2()).passed());
        let v = verdict("T1\n", &um2());
        assert!(v.refusals[0].reason.contains("1 extruder"), "{v:?}");
        let two = Machine {
            extruders: 2,
            ..um2()
        };
        assert!(verdict("T1\nM104 T1 S200\n", &two).passed());
    }

    #[test]
    fn moves_arcs_and_offsets_off_the_bed_are_refused_naming_the_line() {
        let v = verdict("G28\nG1 X1 Y50\nG2 I-100\n", &um2());
        assert_eq!(v.refusals[0].line, 3);
        assert!(v.refusals[0].reason.contains("sweeps X to -199.0"), "{v:?}");
        let v = verdict("G28\nG1 X100\nG92 X0\nG1 X200\n", &um2());
        assert!(v.refusals[0].reason.contains("moves X to 300.0"), "{v:?}");
        let v = verdict("G28\nG1 X1.2.3\n", &um2());
        assert!(
            v.refusals[0].reason.contains("where a parameter belongs"),
            "{v:?}"
        );
        let v = verdict("G28\nG92 x100\nG1 X300\n", &um2());
        assert_eq!(v.refusals[0].line, 2, "{v:?}");
        let v = verdict("G28\nG54\nG1 X10\n", &um2());
        assert!(
            v.refusals[0].reason.contains("workspace coordinate system"),
            "{v:?}"
        );
        // M206 is refused as a setting, and followed when allowed.
        let allowing = Machine {
            allow: vec!["M206".into()],
            ..um2()
        };
        let v = verdict("M206 X-100\nG28\nG1 X200\n", &allowing);
        assert!(v.refusals[0].reason.contains("moves X to 300.0"), "{v:?}");
    }

    /// Issue 42's reproduction: a sliver in 64-bit, a whole circle of 141 mm radius (off
    /// the bed) in the firmware's 32-bit floats. Refused on both firmwares, naming the
    /// line; the same arc ending a thousandth away passes.
    #[test]
    fn an_arc_whose_ends_are_equal_in_float_not_in_double_is_refused() {
        let marlin = Machine::builtin("marlin-175").unwrap();
        for machine in [marlin, um2()] {
            let v = verdict(
                "G28\nG1 X210 Y210 F6000\nG2 X210.000005 Y209.999995 I-100 J-100 F3000\n",
                &machine,
            );
            assert_eq!(v.refusals_total, 1, "{}: {v:?}", machine.name);
            assert_eq!(v.refusals[0].line, 3);
            assert!(
                v.refusals[0].reason.contains("whole circle"),
                "{}: {v:?}",
                machine.name
            );
            let v = verdict(
                "G28\nG1 X150 Y150 F6000\nG2 X150.001 Y149.999 I-50 J-50 F3000\n",
                &machine,
            );
            assert!(v.passed(), "{}: {v:?}", machine.name);
        }
        let v = verdict(
            "G28\nG1 X150 Y150\nG2 X150.000005 Y150.000005 R50\n",
            &Machine::builtin("marlin-175").unwrap(),
        );
        assert!(v.refusals[0].reason.contains("bad parameters"), "{v:?}");
        let v = verdict(
            "G28\nG1 X220.5000001 Y10\n",
            &Machine::builtin("marlin-175").unwrap(),
        );
        assert!(v.refusals[0].reason.contains("32-bit"), "{v:?}");
    }

    #[test]
    fn pauses_are_listed_with_their_message_not_refused() {
        let v = verdict(
            "G28\nM117 Insert magnets\nM601\nM0 Swap the colour\nM600\nM25\n",
            &um2(),
        );
        assert!(v.passed(), "{v:?}");
        assert_eq!(v.pauses_total, 4);
        assert_eq!(v.pauses[0].line, 3);
        assert_eq!(v.pauses[0].message, "Insert magnets");
        assert_eq!(v.pauses[1].message, "Swap the colour");
        assert!(v
            .summary()
            .starts_with("passed the G-code policy, 4 pauses (line 3"));
    }

    #[test]
    fn unreadable_lines_are_refused_and_the_list_is_bounded() {
        let v = check(&b"G28\nM104 S\xff\xfe\n"[..], &um2()).unwrap();
        assert_eq!(v.refusals[0].line, 2);
        assert!(v.refusals[0].reason.contains("UTF-8"));
        let many = "M500\n".repeat(100);
        let v = verdict(&many, &um2());
        assert_eq!((v.refusals.len(), v.refusals_total), (MAX_LISTED, 100));
        assert!(v.summary().ends_with("and 80 more"));
    }

    #[test]
    fn the_hosts_load_checks_run_too() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("a.gcode");
        std::fs::write(&path, format!("G28\nM117 {}\n", "x".repeat(200))).unwrap();
        let e = check_file(&path, &um2()).unwrap_err();
        assert!(e.to_string().contains(":2:"), "{e}");
        std::fs::write(&path, CLEAN).unwrap();
        assert!(check_file(&path, &um2()).unwrap().passed());
    }
}
