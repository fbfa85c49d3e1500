//! Machines: what slicing depends on. A [`Machine`] is a kind of printer (bed size and
//! height, nozzle and filament diameter, heated bed or not, firmware flavour, slicer
//! profiles, start and end code); a printer in the config is one machine, and a job is
//! sliced once per machine among the printers that may take it.
//!
//! The built-in machines are data ([`BUILTIN`]), compiled into the binary together with
//! the profiles and start/end code they use; a farm defines others with `[[machine]]`
//! tables ([`MachineSpec`], checked by [`MachineSpec::check`]).
//!
//! A machine names its firmware flavour ([`Firmware`]), which is the host protocol's to
//! define: this module builds on `marlin`, never the other way round, and `slice` builds
//! on this one.

mod code;
pub(crate) mod commands;
pub mod eject;

use code::read_code;

use crispen_marlin::firmware::Firmware;
use serde::{Deserialize, Serialize};
use std::path::{Path, PathBuf};

/// A kind of printer, as the slicer and the placement see it.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Machine {
    /// The name printers and job records use (`ultimaker2`, or a config's own).
    pub name: String,
    /// The firmware the printer runs (the G-code flavour and the serial protocol).
    pub firmware: Firmware,
    /// Usable build volume, mm (X, Y, Z).
    pub bed_mm: [f64; 3],
    pub nozzle_mm: f64,
    /// Nozzles this machine may be fitted with (a printer may name one, `nozzle_mm`).
    pub nozzle_range_mm: [f64; 2],
    pub filament_mm: f64,
    pub heated_bed: bool,
    /// A PrusaSlicer `.ini` replacing the built-in profile (None: built-in).
    pub prusa_profile: Option<PathBuf>,
    /// A CuraEngine `.toml` replacing the built-in profile (None: built-in).
    pub cura_profile: Option<PathBuf>,
    /// Start code replacing crispen's (None: `gcode/start.gcode`); the placeholders
    /// `{BED_TEMP}` and `{NOZZLE_TEMP}` are filled per job.
    pub start_gcode: Option<String>,
    /// End code replacing crispen's (None: `gcode/end.gcode`); `{PRESENT_Z}` is filled.
    pub end_gcode: Option<String>,
    /// Park code replacing crispen's at a pause the file asks for (None: lift 10 mm, move to
    /// X 0 and the largest Y); sent in absolute positioning once the head has stopped.
    pub pause_gcode: Option<String>,
    /// Code sent when the operator resumes, before crispen returns the head and restores
    /// the file's modes, E and feed rate (a purge, a fan); None: nothing more.
    pub resume_gcode: Option<String>,
    /// The highest hotend temperature a file may ask for, °C (see the G-code policy, `policy` in `slice`).
    pub max_hotend_c: f64,
    /// The highest bed temperature a file may ask for, °C.
    pub max_bed_c: f64,
    /// Extruders (tools `T0` .. `T<n-1>`).
    pub extruders: u8,
    /// Commands the G-code policy refuses that this machine allows in files (`M500`).
    pub allow: Vec<String>,
    /// How its printers push a finished print off the bed (`[machine.eject]`), if they can.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub eject: Option<eject::Eject>,
}

/// Room kept free around the model on each side, for the skirt the profiles print.
pub(crate) const SKIRT_MARGIN_MM: f64 = 5.0;

impl Machine {
    /// The box a model must fit in on this bed (X, Y, Z), keeping room for the skirt.
    pub fn fits_mm(&self) -> [f64; 3] {
        [
            self.bed_mm[0] - 2.0 * SKIRT_MARGIN_MM,
            self.bed_mm[1] - 2.0 * SKIRT_MARGIN_MM,
            self.bed_mm[2],
        ]
    }

    /// The built-in machine of this name.
    pub fn builtin(name: &str) -> Option<Machine> {
        BUILTIN
            .iter()
            .find(|b| b.name == name)
            .map(Builtin::machine)
    }

    /// The machine a printer has when its config names none: what crispen always sliced
    /// for (`ultimaker2`) for Ultimaker2Marlin, and [`DEFAULT_MARLIN_MACHINE`] for Marlin 2.
    pub fn default_for(firmware: Firmware) -> Machine {
        let name = match firmware {
            Firmware::Ultimaker2 => "ultimaker2",
            Firmware::Marlin2 | Firmware::Marlin20 => DEFAULT_MARLIN_MACHINE,
        };
        let mut machine = Machine::builtin(name).expect("the default machines are built in");
        machine.firmware = firmware;
        machine
    }

    /// This machine fitted with another nozzle: a machine of its own (sliced apart),
    /// named `<name>-<nozzle>mm`.
    pub fn with_nozzle(&self, nozzle_mm: f64) -> Result<Machine, String> {
        let [lo, hi] = self.nozzle_range_mm;
        if !(nozzle_mm.is_finite() && (lo..=hi).contains(&nozzle_mm)) {
            return Err(format!(
                "the {} takes nozzles from {lo} to {hi} mm, got {nozzle_mm}",
                self.name
            ));
        }
        if nozzle_mm == self.nozzle_mm {
            return Ok(self.clone());
        }
        Ok(Machine {
            name: format!("{}-{nozzle_mm}mm", self.name),
            nozzle_mm,
            ..self.clone()
        })
    }
}

/// The machine of a `marlin2`/`marlin20` printer whose config names none: a common
/// 1.75 mm bed-slinger (220 x 220 x 250 mm, 0.4 mm nozzle, heated bed).
pub const DEFAULT_MARLIN_MACHINE: &str = "marlin-175";

/// A built-in machine as data.
#[derive(Debug, Clone, Copy)]
pub struct Builtin {
    pub name: &'static str,
    pub description: &'static str,
    pub firmware: Firmware,
    pub bed_mm: [f64; 3],
    pub nozzle_mm: f64,
    pub nozzle_range_mm: [f64; 2],
    pub filament_mm: f64,
    pub heated_bed: bool,
    pub max_hotend_c: f64,
    pub max_bed_c: f64,
}

impl Builtin {
    pub(crate) fn machine(&self) -> Machine {
        Machine {
            name: self.name.to_string(),
            firmware: self.firmware,
            bed_mm: self.bed_mm,
            nozzle_mm: self.nozzle_mm,
            nozzle_range_mm: self.nozzle_range_mm,
            filament_mm: self.filament_mm,
            heated_bed: self.heated_bed,
            prusa_profile: None,
            cura_profile: None,
            start_gcode: None,
            end_gcode: None,
            pause_gcode: None,
            resume_gcode: None,
            max_hotend_c: self.max_hotend_c,
            max_bed_c: self.max_bed_c,
            extruders: 1,
            allow: Vec::new(),
            eject: None,
        }
    }
}

/// The built-in machines. Build volumes are the usable ones Ultimaker's own slicer (Cura's
/// machine definitions) uses, which are what a slicer may fill: the Ultimaker Original+
/// is sold as 210 x 210 x 205 mm, of which Cura uses 205 x 205 x 200.
pub const BUILTIN: &[Builtin] = &[
    Builtin {
        name: "ultimaker2",
        description: "Ultimaker 2",
        firmware: Firmware::Ultimaker2,
        bed_mm: [223.0, 223.0, 205.0],
        nozzle_mm: 0.4,
        nozzle_range_mm: [0.4, 0.4],
        filament_mm: 2.85,
        heated_bed: true,
        // Ultimaker2Marlin (Configuration.h) trips at HEATER_0_MAXTEMP 275 °C and lets a
        // target reach 15 °C below it, 260 °C, which is also the top of the nozzle range
        // Ultimaker publishes for the UM2 family (PTFE coupler); the bed's published range
        // ends at 100 °C (the firmware's BED_MAXTEMP of 200 protects nothing below that).
        max_hotend_c: 260.0,
        max_bed_c: 100.0,
    },
    Builtin {
        name: "ultimaker2-extended",
        description: "Ultimaker 2 Extended",
        firmware: Firmware::Ultimaker2,
        bed_mm: [223.0, 223.0, 305.0],
        nozzle_mm: 0.4,
        nozzle_range_mm: [0.4, 0.4],
        filament_mm: 2.85,
        heated_bed: true,
        // Ultimaker2Marlin (Configuration.h) trips at HEATER_0_MAXTEMP 275 °C and lets a
        // target reach 15 °C below it, 260 °C, which is also the top of the nozzle range
        // Ultimaker publishes for the UM2 family (PTFE coupler); the bed's published range
        // ends at 100 °C (the firmware's BED_MAXTEMP of 200 protects nothing below that).
        max_hotend_c: 260.0,
        max_bed_c: 100.0,
    },
    Builtin {
        // Swappable nozzles: Ultimaker sells 0.25, 0.4, 0.6 and 0.8 mm.
        name: "ultimaker2plus",
        description: "Ultimaker 2+",
        firmware: Firmware::Ultimaker2,
        bed_mm: [223.0, 223.0, 205.0],
        nozzle_mm: 0.4,
        nozzle_range_mm: [0.25, 0.8],
        filament_mm: 2.85,
        heated_bed: true,
        // Ultimaker2Marlin (Configuration.h) trips at HEATER_0_MAXTEMP 275 °C and lets a
        // target reach 15 °C below it, 260 °C, which is also the top of the nozzle range
        // Ultimaker publishes for the UM2 family (PTFE coupler); the bed's published range
        // ends at 100 °C (the firmware's BED_MAXTEMP of 200 protects nothing below that).
        max_hotend_c: 260.0,
        max_bed_c: 100.0,
    },
    Builtin {
        // Ultimaker's Marlin 1 fork at 250000 baud, the same lineage and serial
        // behaviour as Ultimaker2Marlin.
        name: "ultimaker-original-plus",
        description: "Ultimaker Original+ (heated build plate)",
        firmware: Firmware::Ultimaker2,
        bed_mm: [205.0, 205.0, 200.0],
        nozzle_mm: 0.4,
        nozzle_range_mm: [0.4, 0.4],
        filament_mm: 2.85,
        heated_bed: true,
        // Ultimaker's Marlin of the same lineage, with the Ultimaker 2's limits
        // (HEATER_0_MAXTEMP 275, targets to 260 °C) and a heated plate taken as the
        // Ultimaker 2's (100 °C).
        max_hotend_c: 260.0,
        max_bed_c: 100.0,
    },
    Builtin {
        name: DEFAULT_MARLIN_MACHINE,
        description: "a generic Marlin 2 printer for 1.75 mm filament",
        firmware: Firmware::Marlin2,
        bed_mm: [220.0, 220.0, 250.0],
        nozzle_mm: 0.4,
        nozzle_range_mm: [0.2, 1.0],
        filament_mm: 1.75,
        heated_bed: true,
        // Marlin's stock Configuration.h: HEATER_0_MAXTEMP 275 with HOTEND_OVERSHOOT 15
        // (the highest target it accepts: 260 °C); BED_MAXTEMP 150 with BED_OVERSHOOT 10
        // would allow 140, but a common bed-slinger's bed is sold for at most 100-110 °C:
        // 110.
        max_hotend_c: 260.0,
        max_bed_c: 110.0,
    },
];

/// Bounds of a machine's values.
pub(crate) const BED_MM: std::ops::RangeInclusive<f64> = 20.0..=2000.0;
pub(crate) const NOZZLE_MM: std::ops::RangeInclusive<f64> = 0.1..=2.0;
pub(crate) const FILAMENT_MM: std::ops::RangeInclusive<f64> = 1.0..=3.5;
/// Bounds of the temperature limits, °C: no hotend crispen drives takes more than 450,
/// no bed more than 200 (0: files may not heat it).
pub(crate) const HOTEND_C: std::ops::RangeInclusive<f64> = 100.0..=450.0;
pub(crate) const BED_C: std::ops::RangeInclusive<f64> = 0.0..=200.0;
pub(crate) const EXTRUDERS: std::ops::RangeInclusive<u8> = 1..=8;
/// At most this many machines in one config.
pub const MAX_MACHINES: usize = 64;

/// A `[[machine]]` table as written in the config.
#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct MachineSpec {
    pub name: String,
    /// Start from this machine (built-in or defined earlier) and change what is given.
    pub based_on: Option<String>,
    pub firmware: Option<String>,
    pub bed_mm: Option<Vec<f64>>,
    pub nozzle_mm: Option<f64>,
    pub filament_mm: Option<f64>,
    pub heated_bed: Option<bool>,
    pub prusa_profile: Option<PathBuf>,
    pub cura_profile: Option<PathBuf>,
    /// A file of start code (placeholders `{BED_TEMP}`, `{NOZZLE_TEMP}`).
    pub start_gcode: Option<PathBuf>,
    /// A file of end code (placeholder `{PRESENT_Z}`).
    pub end_gcode: Option<PathBuf>,
    /// A file of park code for a file's pauses.
    pub pause_gcode: Option<PathBuf>,
    /// A file of code sent on resuming a file's pause.
    pub resume_gcode: Option<PathBuf>,
    /// The highest hotend temperature a file may ask for, °C.
    pub max_hotend_c: Option<f64>,
    /// The highest bed temperature a file may ask for, °C.
    pub max_bed_c: Option<f64>,
    pub extruders: Option<u8>,
    /// Commands the G-code policy guards or does not know that this machine allows in files
    /// ([`commands::allowable`]).
    pub allow: Option<Vec<String>>,
    /// How its printers push a print off the bed (see [`eject`]).
    pub eject: Option<eject::EjectSpec>,
}

/// Whether a name may name a machine (it becomes part of G-code file names).
pub(crate) fn valid_name(name: &str) -> bool {
    !name.is_empty()
        && name.len() <= 64
        && name
            .chars()
            .all(|c| c.is_ascii_alphanumeric() || c == '-' || c == '_' || c == '.')
}

impl MachineSpec {
    /// Checks the table into a machine. `known` finds a machine by name (built-in or
    /// defined earlier); `anchor` makes a path absolute. Errors name the key.
    pub fn check(
        self,
        known: &dyn Fn(&str) -> Option<Machine>,
        anchor: &dyn Fn(&Path) -> PathBuf,
    ) -> Result<Machine, (&'static str, String)> {
        if !valid_name(&self.name) {
            return Err((
                "name",
                "must be 1 to 64 letters, digits, `-`, `_`, `.`".into(),
            ));
        }
        if known(&self.name).is_some() {
            return Err((
                "name",
                format!(
                    "{:?} is already a machine (built-in: {}); give yours another name, with \
                     `based_on = {:?}` to start from it",
                    self.name,
                    BUILTIN
                        .iter()
                        .map(|b| b.name)
                        .collect::<Vec<_>>()
                        .join(", "),
                    self.name
                ),
            ));
        }
        let base = match &self.based_on {
            Some(b) => Some(known(b).ok_or_else(|| {
                (
                    "based_on",
                    format!("no machine is named {b:?} (built-in or defined above)"),
                )
            })?),
            None => None,
        };
        let need = |key: &'static str| {
            (
                key,
                "missing (give it, or `based_on` a machine to start from)".to_string(),
            )
        };
        let firmware = match (&self.firmware, &base) {
            (Some(f), _) => f.parse::<Firmware>().map_err(|m| ("firmware", m))?,
            (None, Some(b)) => b.firmware,
            (None, None) => return Err(need("firmware")),
        };
        let bed_mm = match (&self.bed_mm, &base) {
            (Some(v), _) => {
                let ok = v.len() == 3 && v.iter().all(|x| x.is_finite() && BED_MM.contains(x));
                if !ok {
                    return Err((
                        "bed_mm",
                        format!(
                            "must be [x, y, z], each from {} to {} mm, got {v:?}",
                            BED_MM.start(),
                            BED_MM.end()
                        ),
                    ));
                }
                [v[0], v[1], v[2]]
            }
            (None, Some(b)) => b.bed_mm,
            (None, None) => return Err(need("bed_mm")),
        };
        let in_range = |key: &'static str, v: f64, r: &std::ops::RangeInclusive<f64>| {
            if v.is_finite() && r.contains(&v) {
                Ok(v)
            } else {
                Err((
                    key,
                    format!("must be from {} to {} mm, got {v}", r.start(), r.end()),
                ))
            }
        };
        let nozzle_mm = match (self.nozzle_mm, &base) {
            (Some(v), _) => in_range("nozzle_mm", v, &NOZZLE_MM)?,
            (None, Some(b)) => b.nozzle_mm,
            (None, None) => return Err(need("nozzle_mm")),
        };
        let filament_mm = match (self.filament_mm, &base) {
            (Some(v), _) => in_range("filament_mm", v, &FILAMENT_MM)?,
            (None, Some(b)) => b.filament_mm,
            (None, None) => return Err(need("filament_mm")),
        };
        let heated_bed = match (self.heated_bed, &base) {
            (Some(v), _) => v,
            (None, Some(b)) => b.heated_bed,
            (None, None) => return Err(need("heated_bed")),
        };
        let celsius = |key: &'static str,
                       v: Option<f64>,
                       r: &std::ops::RangeInclusive<f64>,
                       inherited: Option<f64>| {
            match (v, inherited) {
                (Some(v), _) if v.is_finite() && r.contains(&v) => Ok(v),
                (Some(v), _) => Err((
                    key,
                    format!("must be from {} to {} °C, got {v}", r.start(), r.end()),
                )),
                (None, Some(b)) => Ok(b),
                (None, None) => Err(need(key)),
            }
        };
        let max_hotend_c = celsius(
            "max_hotend_c",
            self.max_hotend_c,
            &HOTEND_C,
            base.as_ref().map(|b| b.max_hotend_c),
        )?;
        let max_bed_c = celsius(
            "max_bed_c",
            self.max_bed_c,
            &BED_C,
            base.as_ref().map(|b| b.max_bed_c),
        )?;
        let extruders = match (self.extruders, &base) {
            (Some(n), _) if EXTRUDERS.contains(&n) => n,
            (Some(n), _) => {
                return Err((
                    "extruders",
                    format!(
                        "must be from {} to {}, got {n}",
                        EXTRUDERS.start(),
                        EXTRUDERS.end()
                    ),
                ))
            }
            (None, Some(b)) => b.extruders,
            (None, None) => 1,
        };
        let allow = match (self.allow, &base) {
            (Some(list), _) => {
                let mut out: Vec<String> = Vec::new();
                for word in list {
                    let code = word.trim().to_ascii_uppercase();
                    if !commands::allowable(&code) {
                        return Err((
                            "allow",
                            format!(
                                "{word:?} is not a command a machine may allow: only those \
                                 the G-code policy guards ({}) or does not know (a vendor's \
                                 own); see docs/gcode-policy.md",
                                commands::guarded().collect::<Vec<_>>().join(", ")
                            ),
                        ));
                    }
                    if !out.contains(&code) {
                        out.push(code);
                    }
                }
                out
            }
            (None, Some(b)) => b.allow.clone(),
            (None, None) => Vec::new(),
        };
        let file = |key: &'static str, p: &Option<PathBuf>| -> Result<Option<PathBuf>, _> {
            match p {
                None => Ok(None),
                Some(p) if p.as_os_str().is_empty() => Err((key, "must not be empty".into())),
                Some(p) => Ok(Some(anchor(p))),
            }
        };
        let code = |key: &'static str, p: &Option<PathBuf>| -> Result<Option<String>, _> {
            let Some(path) = file(key, p)? else {
                return Ok(None);
            };
            read_code(&path).map(Some).map_err(|m| (key, m))
        };
        Ok(Machine {
            name: self.name,
            firmware,
            bed_mm,
            nozzle_mm,
            // A machine defined in the config is what it says: its nozzle is given.
            nozzle_range_mm: match (&base, self.nozzle_mm) {
                (Some(b), None) => b.nozzle_range_mm,
                _ => [nozzle_mm, nozzle_mm],
            },
            filament_mm,
            heated_bed,
            prusa_profile: file("prusa_profile", &self.prusa_profile)?
                .or_else(|| base.as_ref().and_then(|b| b.prusa_profile.clone())),
            cura_profile: file("cura_profile", &self.cura_profile)?
                .or_else(|| base.as_ref().and_then(|b| b.cura_profile.clone())),
            start_gcode: code("start_gcode", &self.start_gcode)?
                .or_else(|| base.as_ref().and_then(|b| b.start_gcode.clone())),
            end_gcode: code("end_gcode", &self.end_gcode)?
                .or_else(|| base.as_ref().and_then(|b| b.end_gcode.clone())),
            pause_gcode: code("pause_gcode", &self.pause_gcode)?
                .or_else(|| base.as_ref().and_then(|b| b.pause_gcode.clone())),
            resume_gcode: code("resume_gcode", &self.resume_gcode)?
                .or_else(|| base.as_ref().and_then(|b| b.resume_gcode.clone())),
            max_hotend_c,
            max_bed_c,
            extruders,
            allow,
            eject: match self.eject {
                Some(spec) => Some(
                    spec.check(bed_mm[2], &anchor(Path::new(".")))
                        .map_err(|(key, m)| (eject_key(key), m))?,
                ),
                None => base.as_ref().and_then(|b| b.eject.clone()),
            },
        })
    }
}

/// An eject key as the machine's error names it (`eject.max_height_mm`).
fn eject_key(key: &'static str) -> &'static str {
    match key {
        "gcode" => "eject.gcode",
        "file" => "eject.file",
        "release_bed_c" => "eject.release_bed_c",
        "max_height_mm" => "eject.max_height_mm",
        "allow" => "eject.allow",
        _ => "eject",
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn spec(text: &str) -> MachineSpec {
        toml::from_str(text).unwrap()
    }

    fn check(text: &str) -> Result<Machine, (&'static str, String)> {
        spec(text).check(&Machine::builtin, &|p| p.to_path_buf())
    }

    #[test]
    fn builtins_have_their_published_build_volumes() {
        let m = |n: &str| Machine::builtin(n).unwrap();
        assert_eq!(m("ultimaker2").bed_mm, [223.0, 223.0, 205.0]);
        assert_eq!(m("ultimaker2-extended").bed_mm, [223.0, 223.0, 305.0]);
        assert_eq!(m("ultimaker2plus").nozzle_range_mm, [0.25, 0.8]);
        assert_eq!(m("ultimaker-original-plus").bed_mm, [205.0, 205.0, 200.0]);
        for b in BUILTIN {
            assert!(valid_name(b.name), "{}", b.name);
        }
        assert_eq!(m(DEFAULT_MARLIN_MACHINE).filament_mm, 1.75);
        for b in BUILTIN {
            let machine = b.machine();
            assert!(HOTEND_C.contains(&machine.max_hotend_c), "{}", b.name);
            assert!(BED_C.contains(&machine.max_bed_c), "{}", b.name);
            assert_eq!((machine.extruders, machine.allow.len()), (1, 0));
        }
        assert_eq!(m("ultimaker2").max_hotend_c, 260.0);
        assert_eq!(
            Machine::default_for(Firmware::Ultimaker2).name,
            "ultimaker2"
        );
        assert_eq!(
            Machine::default_for(Firmware::Marlin20).firmware,
            Firmware::Marlin20
        );
    }

    #[test]
    fn nozzle_choice_is_bounded_and_names_its_own_machine() {
        let plus = Machine::builtin("ultimaker2plus").unwrap();
        let m = plus.with_nozzle(0.6).unwrap();
        assert_eq!(
            (m.name.as_str(), m.nozzle_mm),
            ("ultimaker2plus-0.6mm", 0.6)
        );
        assert_eq!(plus.with_nozzle(0.4).unwrap(), plus);
        let e = plus.with_nozzle(1.0).unwrap_err();
        assert!(e.contains("0.25 to 0.8"), "{e}");
        assert!(Machine::builtin("ultimaker2")
            .unwrap()
            .with_nozzle(0.6)
            .is_err());
    }

    #[test]
    fn a_machine_table_is_checked_key_by_key() {
        let m = check(
            "name = \"generic-175\"\nfirmware = \"marlin2\"\nbed_mm = [220, 220, 250]\n\
             nozzle_mm = 0.4\nfilament_mm = 1.75\nheated_bed = true\nmax_hotend_c = 260\n\
             max_bed_c = 110\n",
        )
        .unwrap();
        assert_eq!(m.bed_mm, [220.0, 220.0, 250.0]);
        let m = check("name = \"um2-06\"\nbased_on = \"ultimaker2\"\nnozzle_mm = 0.6\n").unwrap();
        assert_eq!((m.filament_mm, m.nozzle_mm), (2.85, 0.6));
        for (text, key, says) in [
            (
                "name = \"a\"\nbased_on = \"nope\"",
                "based_on",
                "no machine",
            ),
            (
                "name = \"ultimaker2\"\nbased_on = \"ultimaker2\"",
                "name",
                "already",
            ),
            ("name = \"a b\"", "name", "letters"),
            ("name = \"a\"\nfirmware = \"marlin2\"", "bed_mm", "missing"),
            (
                "name = \"a\"\nbased_on = \"ultimaker2\"\nbed_mm = [1, 2]",
                "bed_mm",
                "[x, y, z]",
            ),
            (
                "name = \"a\"\nbased_on = \"ultimaker2\"\nbed_mm = [200, 200, 1e9]",
                "bed_mm",
                "2000",
            ),
            (
                "name = \"a\"\nbased_on = \"ultimaker2\"\nnozzle_mm = 0",
                "nozzle_mm",
                "from 0.1",
            ),
            (
                "name = \"a\"\nbased_on = \"ultimaker2\"\nfilament_mm = nan",
                "filament_mm",
                "from 1",
            ),
            (
                "name = \"a\"\nbased_on = \"ultimaker2\"\nfirmware = \"grbl\"",
                "firmware",
                "unknown",
            ),
            (
                "name = \"a\"\nbased_on = \"ultimaker2\"\nstart_gcode = \"/nonexistent\"",
                "start_gcode",
                "cannot read",
            ),
        ] {
            let (k, m) = check(text).unwrap_err();
            assert_eq!(k, key, "{text}: {m}");
            assert!(m.contains(says), "{text}: {m}");
        }
        for (text, key, says) in [
            ("max_hotend_c = 1000", "max_hotend_c", "100 to 450"),
            ("max_bed_c = -1", "max_bed_c", "0 to 200"),
            ("extruders = 0", "extruders", "1 to 8"),
            ("allow = [\"M104\"]", "allow", "M500"),
        ] {
            let (k, m) =
                check(&format!("name = \"a\"\nbased_on = \"ultimaker2\"\n{text}")).unwrap_err();
            assert_eq!(k, key, "{text}: {m}");
            assert!(m.contains(says), "{text}: {m}");
        }
        let (k, _) = check(
            "name = \"a\"\nfirmware = \"marlin2\"\nbed_mm = [220, 220, 250]\nnozzle_mm = 0.4\n\
             filament_mm = 1.75\nheated_bed = true\n",
        )
        .unwrap_err();
        assert_eq!(k, "max_hotend_c");
        let m = check(
            "name = \"a\"\nbased_on = \"ultimaker2\"\nallow = [\"m500\", \"M500\"]\nmax_bed_c = 80",
        )
        .unwrap();
        assert_eq!(
            (m.allow, m.max_bed_c, m.max_hotend_c),
            (vec!["M500".to_string()], 80.0, 260.0)
        );
        assert!(toml::from_str::<MachineSpec>("name = \"a\"\nbed = 1").is_err());
    }
}
