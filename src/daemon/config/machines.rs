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
        if let Some(eject) = &machine.eject {
            eject_fits(eject, &machine)
                .map_err(|m| invalid(format!("{section}.eject"), "gcode", m))?;
        }
        machines.push(machine);
    }
    Ok(machines)
}

/// A machine's pause or resume code is sent by the host in the middle of a job: it must
/// load as any job's lines do (text, length, characters), pass the machine's G-code
/// policy, and ask for no pause itself.
fn pause_code_fits(code: &str, machine: &crate::machine::Machine) -> Result<(), String> {
    code_fits(code, machine, "the code runs at one")
}

/// An eject sequence is streamed as a short job of its own after a print: it must load
/// and pass the policy as a job's lines do, with the commands it is allowed (a plate
/// changer's) beside the machine's, and ask for no pause (nobody is there).
pub(super) fn eject_fits(
    eject: &crate::machine::eject::Eject,
    machine: &crate::machine::Machine,
) -> Result<(), String> {
    let mut allowed = machine.clone();
    for code in &eject.allow {
        if !allowed.allow.contains(code) {
            allowed.allow.push(code.clone());
        }
    }
    code_fits(
        &eject.gcode,
        &allowed,
        "the sequence runs with nobody there",
    )
}

/// `code` loads as a job's lines for `machine`'s firmware, passes its policy and asks for
/// no pause (`why_not`: why a pause is refused).
fn code_fits(code: &str, machine: &crate::machine::Machine, why_not: &str) -> Result<(), String> {
    crate::marlin::gcode::GcodeProgram::read(code.as_bytes(), "the code", machine.firmware)
        .map_err(|e| e.to_string())?;
    let verdict = crate::slice::policy::check(code.as_bytes(), machine)
        .map_err(|e| format!("cannot read the code: {e}"))?;
    if !verdict.passed() {
        return Err(verdict.summary());
    }
    match verdict.pauses.first() {
        Some(p) => Err(format!(
            "line {}: `{}` asks for a pause; {why_not}",
            p.line, p.command
        )),
        None => Ok(()),
    }
}
