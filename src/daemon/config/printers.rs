//! `[[printer]]`: each printer's table checked: its name, the machine it is (and so its
//! firmware and nozzle), its serial settings and timeouts, and where it is reached, a
//! serial device or a simulated printer.

use super::check::{number, Context};
use super::checked::{PrinterConfig, PrinterPort};
use super::error::ConfigError;
use super::pause;
use super::raw::{RawPrinter, RawSimulate};
use crate::daemon::bed::ClearBy;
use crate::daemon::filament::routing::check_asks;
use crate::machine::Machine;
use crate::marlin::firmware::Firmware;
use std::collections::BTreeSet;
use std::path::PathBuf;
use std::time::Duration;

/// At most this many printers (and so heating permits) in one farm.
pub(crate) const MAX_PRINTERS: usize = 256;

/// Checks the `[[printer]]` tables in order, each name once; `machines` are the
/// `[[machine]]` tables, checked.
pub(super) fn check(
    raw: Vec<RawPrinter>,
    machines: &[Machine],
    cx: &Context,
    warnings: &mut Vec<String>,
) -> Result<Vec<PrinterConfig>, ConfigError> {
    let Context { invalid, .. } = *cx;
    if raw.len() > MAX_PRINTERS {
        return Err(invalid(
            "[[printer]]".into(),
            "name",
            format!("at most {MAX_PRINTERS} printers, got {}", raw.len()),
        ));
    }
    let mut printers = Vec::new();
    let mut names = BTreeSet::new();
    for (i, p) in raw.into_iter().enumerate() {
        let section = format!("[[printer]] #{} (name {:?})", i + 1, p.name);
        if p.name.is_empty()
            || !p
                .name
                .chars()
                .all(|c| c.is_ascii_alphanumeric() || c == '-' || c == '_' || c == '.')
        {
            return Err(invalid(
                section,
                "name",
                "must be non-empty and use only letters, digits, `-`, `_`, `.`".into(),
            ));
        }
        if !names.insert(p.name.clone()) {
            return Err(invalid(
                section,
                "name",
                "is used by another printer".into(),
            ));
        }
        printers.push(check_printer(section, p, machines, cx, warnings)?);
    }
    Ok(printers)
}

/// One `[[printer]]` table, whose name is checked; `section` names it in errors.
fn check_printer(
    section: String,
    p: RawPrinter,
    machines: &[Machine],
    cx: &Context,
    warnings: &mut Vec<String>,
) -> Result<PrinterConfig, ConfigError> {
    let Context { invalid, .. } = *cx;
    let machine = machine_of(section.clone(), &p, machines, cx)?;
    let firmware = machine.firmware;
    let baud = match p.baud {
        None => firmware.default_baud(),
        Some(b) if (300..=4_000_000).contains(&b) => b as u32,
        Some(b) => {
            return Err(invalid(
                section,
                "baud",
                format!("must be between 300 and 4000000, got {b}"),
            ))
        }
    };
    let heat_timeout = match p.heat_timeout_s {
        None => Duration::from_secs(1200),
        Some(s) if (10..=86_400).contains(&s) => Duration::from_secs(s as u64),
        Some(s) => {
            return Err(invalid(
                section,
                "heat_timeout_s",
                format!("must be between 10 and 86400 seconds, got {s}"),
            ))
        }
    };
    let pause_heaters_off = pause::heaters_off_after(p.pause_heaters_off_s)
        .map_err(|m| invalid(section.clone(), "pause_heaters_off_s", m))?;
    let camera = match p.camera {
        None => None,
        Some(c) => Some(
            super::camera::check_printer(c)
                .map_err(|(key, m)| invalid(format!("{section}.camera"), key, m))?,
        ),
    };
    check_asks(
        p.material.as_deref(),
        p.colour.as_deref(),
        None,
        p.tags.as_deref(),
        None,
    )
    .map_err(|(key, m)| invalid(section.clone(), key, m))?;
    let hardened = match p.nozzle.as_deref() {
        None | Some("brass") => false,
        Some("hardened") => true,
        Some(other) => {
            return Err(invalid(
                section,
                "nozzle",
                format!("\"brass\" or \"hardened\", got {other:?}"),
            ))
        }
    };
    let filament = p
        .material
        .as_deref()
        .map(|m| crate::daemon::filament::Filament {
            material: m.trim().to_ascii_uppercase(),
            colour: p
                .colour
                .as_deref()
                .unwrap_or("unknown")
                .trim()
                .to_ascii_lowercase(),
            colour_hex: None,
            brand: None,
            diameter_mm: machine.filament_mm,
            density_g_cm3: crate::slice::density_of(m),
            price_per_kg: None,
        });
    if p.colour.is_some() && filament.is_none() {
        return Err(invalid(
            section,
            "colour",
            "needs `material` beside it (the filament the printer holds)".into(),
        ));
    }
    let tags = p.tags.unwrap_or_default();
    let (eject, bed_clear) = clearing_of(
        &section,
        p.eject,
        p.bed_clear.as_deref(),
        &machine,
        camera.is_some(),
        cx,
    )?;
    let power = match p.power {
        None => None,
        Some(raw) => Some(
            super::power::check(raw, cx.anchor)
                .map_err(|(key, m)| invalid(format!("{section}.power"), key, m))?,
        ),
    };
    let port = port_of(section, &p.name, p.port, p.simulate, cx, warnings)?;
    Ok(PrinterConfig {
        power,
        eject,
        bed_clear,
        filament,
        hardened,
        tags,
        name: p.name,
        port,
        firmware,
        machine,
        baud,
        heat_timeout,
        pause_heaters_off,
        camera,
    })
}

/// How a printer's bed is cleared: its eject sequence (`[printer.eject]`, else its
/// machine's), checked against the machine's G-code policy, and `bed_clear`, which needs
/// a sequence (and a camera, to check).
fn clearing_of(
    section: &str,
    spec: Option<crate::machine::eject::EjectSpec>,
    bed_clear: Option<&str>,
    machine: &Machine,
    has_camera: bool,
    cx: &Context,
) -> Result<(Option<crate::machine::eject::Eject>, ClearBy), ConfigError> {
    let Context { invalid, anchor } = *cx;
    let eject_section = format!("{section}.eject");
    let eject = match spec {
        Some(spec) => {
            // A sequence the policy refuses is named by the key that gave it.
            let code_key = if spec.file.is_some() { "file" } else { "gcode" };
            let eject = spec
                .check(machine.bed_mm[2], &anchor(std::path::Path::new(".")))
                .map_err(|(key, m)| invalid(eject_section.clone(), key, m))?;
            super::machines::eject_fits(&eject, machine)
                .map_err(|m| invalid(eject_section.clone(), code_key, m))?;
            Some(eject)
        }
        None => machine.eject.clone(),
    };
    let bed_clear = match bed_clear {
        None => ClearBy::Person,
        Some(text) => {
            ClearBy::parse(text).map_err(|m| invalid(section.to_string(), "bed_clear", m))?
        }
    };
    needs_for(bed_clear, eject.is_some(), has_camera)
        .map_err(|m| invalid(section.to_string(), "bed_clear", m))?;
    Ok((eject, bed_clear))
}

/// What `bed_clear` needs of a printer: an eject sequence, and a camera to check with.
pub(super) fn needs_for(clear: ClearBy, has_eject: bool, has_camera: bool) -> Result<(), String> {
    if clear != ClearBy::Person && !has_eject {
        return Err(format!(
            "{:?} needs an eject sequence: a [printer.eject] table, or one in the machine's [machine.eject]",
            clear.name()
        ));
    }
    if clear == ClearBy::EjectAndCheck && !has_camera {
        return Err(format!(
            "{:?} needs a camera to check the bed with: a [printer.camera] table",
            clear.name()
        ));
    }
    Ok(())
}

/// The machine a printer is: the one its `machine` names, else the default for its
/// `firmware`, with the nozzle `nozzle_mm` fits; a `firmware` given beside `machine` must
/// be the machine's.
fn machine_of(
    section: String,
    p: &RawPrinter,
    machines: &[Machine],
    cx: &Context,
) -> Result<Machine, ConfigError> {
    let Context { invalid, .. } = *cx;
    let find_machine = |name: &str| {
        machines
            .iter()
            .find(|m| m.name == name)
            .cloned()
            .or_else(|| crate::machine::Machine::builtin(name))
    };
    let stated: Option<Firmware> = p
        .firmware
        .as_deref()
        .map(str::parse)
        .transpose()
        .map_err(|m: String| invalid(section.clone(), "firmware", m))?;
    let mut machine = match (&p.machine, stated) {
        (Some(name), _) => find_machine(name).ok_or_else(|| {
            invalid(
                section.clone(),
                "machine",
                format!(
                    "no machine is named {name:?} (built-in: {}; or define it in a [[machine]] table)",
                    crate::machine::BUILTIN
                        .iter()
                        .map(|b| b.name)
                        .collect::<Vec<_>>()
                        .join(", ")
                ),
            )
        })?,
        (None, Some(firmware)) => crate::machine::Machine::default_for(firmware),
        (None, None) => {
            return Err(invalid(
                section,
                "machine",
                "missing (give `machine`, e.g. \"ultimaker2\", or at least `firmware`)"
                    .into(),
            ))
        }
    };
    if let Some(f) = stated.filter(|f| *f != machine.firmware) {
        return Err(invalid(
            section,
            "firmware",
            format!(
                "is {f}, but machine {:?} runs {}; leave `firmware` out (it comes from the machine)",
                machine.name, machine.firmware
            ),
        ));
    }
    if let Some(nozzle) = p.nozzle_mm {
        machine = machine
            .with_nozzle(nozzle)
            .map_err(|m| invalid(section.clone(), "nozzle_mm", m))?;
        if machines.iter().any(|m| m.name == machine.name) {
            return Err(invalid(
                section,
                "nozzle_mm",
                format!(
                    "this nozzle makes a machine named {:?}, which a [[machine]] table already names",
                    machine.name
                ),
            ));
        }
    }
    Ok(machine)
}

/// Where a printer is reached: its serial `port`, or the simulated printer its
/// `[printer.simulate]` table describes (one of the two). `name` is the printer's.
fn port_of(
    section: String,
    name: &str,
    port: Option<PathBuf>,
    simulate: Option<RawSimulate>,
    cx: &Context,
    warnings: &mut Vec<String>,
) -> Result<PrinterPort, ConfigError> {
    let Context { invalid, anchor } = *cx;
    let port = match (port, simulate) {
        (Some(_), Some(_)) => {
            return Err(invalid(
                section,
                "simulate",
                "give either `port` or a `[printer.simulate]` table, not both".into(),
            ))
        }
        (None, None) => {
            return Err(invalid(
                section,
                "port",
                "missing (hint: a serial device such as /dev/ttyUSB0, or a \
                 [printer.simulate] table for a simulated printer)"
                    .into(),
            ))
        }
        (Some(port), None) => PrinterPort::Serial(anchor(&port)),
        (None, Some(sim)) => {
            let sim_section = format!("{section}.simulate");
            let time_scale = simulate_time_scale(sim.speed, sim.time_scale, &sim_section, warnings)
                .map_err(|(key, m)| invalid(sim_section, key, m))?;
            PrinterPort::Simulated {
                time_scale,
                // From the name, not the position: removing another printer
                // must not change this one (a reload would restart it).
                seed: sim.seed.unwrap_or_else(|| name_seed(name)),
                record: sim.record.map(|r| anchor(&r)),
            }
        }
    };
    Ok(port)
}

/// `[printer.simulate] speed` (see [`crate::sim::time_scale_of_speed`]), or the
/// old `time_scale`, its inverse, read as before with a warning in `warnings` that names
/// `speed`: the simulator's time scale. An error names its key.
fn simulate_time_scale(
    speed: Option<toml::Value>,
    time_scale: Option<f64>,
    section: &str,
    warnings: &mut Vec<String>,
) -> Result<f64, (&'static str, String)> {
    use crate::sim::{speed_of_time_scale, time_scale_of_speed};
    match (speed, time_scale) {
        (Some(_), Some(_)) => Err((
            "time_scale",
            "give `speed` alone (`time_scale` is its old, inverse form)".into(),
        )),
        (Some(speed), None) => {
            let text = match speed {
                toml::Value::String(s) => s,
                other => other.to_string(),
            };
            time_scale_of_speed(&text).map_err(|m| ("speed", m))
        }
        (None, Some(old)) => {
            if !(old.is_finite() && (0.0..=100.0).contains(&old)) {
                return Err((
                    "time_scale",
                    format!(
                        "must be between 0 (instant) and 100, got {} (hint: use `speed`, how many times faster than real time)",
                        number(old)
                    ),
                ));
            }
            let speed = match speed_of_time_scale(old) {
                word if old == 0.0 => format!("{word:?}"),
                factor => factor,
            };
            warnings.push(format!(
                "{section} key `time_scale`: replaced by `speed`, a speed-up factor (higher is faster); time_scale = {} is speed = {speed}",
                number(old)
            ));
            Ok(old)
        }
        (None, None) => Ok(1.0),
    }
}

/// A stable seed from a printer's name (FNV-1a), the same on every run and reload.
fn name_seed(name: &str) -> u64 {
    name.bytes().fold(0xcbf2_9ce4_8422_2325, |h, b| {
        (h ^ u64::from(b)).wrapping_mul(0x0100_0000_01b3)
    })
}
