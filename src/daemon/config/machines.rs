//! `[[machine]]`: the farm's own machines, each built-in one's or an earlier table's
//! variant, with the pause and resume code the host sends mid-job checked as a job's lines.

use super::check::Context;
use super::error::ConfigError;

/// Checks the `[[machine]]` tables in order (one may be `based_on` an earlier one).
pub(super) fn check(
    specs: Vec<crate::machine::MachineSpec>,
    cx: &Context,
) -> Result<Vec<crate::machine::Machine>, ConfigError> {
    let Context { invalid, anchor } = *cx;
    use crate::machine::{Machine, MAX_MACHINES};
    if specs.len() > MAX_MACHINES {
        return Err(invalid(
            "[[machine]]".into(),
            "name",
            format!("at most {MAX_MACHINES} machines, got {}", specs.len()),
        ));
    }
    let mut machines: Vec<Machine> = Vec::new();
    for (i, spec) in specs.into_iter().enumerate() {
        let section = format!("[[machine]] #{} (name {:?})", i + 1, spec.name);
        let known = |name: &str| {
            machines
                .iter()
                .find(|m| m.name == name)
                .cloned()
                .or_else(|| Machine::builtin(name))
        };
        let machine = spec
            .check(&known, anchor)
            .map_err(|(key, m)| invalid(section.clone(), key, m))?;
        for (key, code) in [
            ("pause_gcode", &machine.pause_gcode),
            ("resume_gcode", &machine.resume_gcode),
        ] {
            if let Some(code) = code {
                pause_code_fits(code, &machine).map_err(|m| invalid(section.clone(), key, m))?;
            }
        }
        machines.push(machine);
    }
    Ok(machines)
}

/// A machine's pause or resume code is sent by the host in the middle of a job: it must
/// load as any job's lines do (text, length, characters), pass the machine's G-code
/// policy, and ask for no pause itself.
fn pause_code_fits(code: &str, machine: &crate::machine::Machine) -> Result<(), String> {
    crate::marlin::gcode::GcodeProgram::read(code.as_bytes(), "the code", machine.firmware)
        .map_err(|e| e.to_string())?;
    let verdict = crate::slice::policy::check(code.as_bytes(), machine)
        .map_err(|e| format!("cannot read the code: {e}"))?;
    if !verdict.passed() {
        return Err(verdict.summary());
    }
    match verdict.pauses.first() {
        Some(p) => Err(format!(
            "line {}: `{}` asks for a pause; the code runs at one",
            p.line, p.command
        )),
        None => Ok(()),
    }
}
