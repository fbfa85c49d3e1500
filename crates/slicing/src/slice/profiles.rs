//! Slicer profiles and command lines.
//!
//! The built-in profiles (`config/`) and the shared Marlin start/end code (`gcode/`) are
//! compiled into the binary, so an installed `crispen` needs no data files; `--profile`
//! replaces the profile. Per job, crispen fills the start/end code's placeholders
//! (`{BED_TEMP}`, `{NOZZLE_TEMP}`, `{PRESENT_Z}`) itself, so both slicers get the same
//! literal code, and maps [`SliceSettings`] onto each slicer's keys:
//!
//! | setting      | PrusaSlicer                                   | CuraEngine                                   |
//! |--------------|-----------------------------------------------|----------------------------------------------|
//! | layer_height | `layer_height`                                | `layer_height` (+ infill/support thickness)  |
//! | infill       | `fill_density`                                | `infill_sparse_density` + `infill_line_distance` |
//! | supports     | `support_material`, `support_material_auto`   | `support_enable`                             |
//! | nozzle_temp  | `temperature`, `first_layer_temperature`      | `material_print_temperature` (all variants)  |
//! | bed_temp     | `bed_temperature`, `first_layer_bed_temperature` | `material_bed_temperature` (+ `_layer_0`) |
//! | material     | temperatures above + `filament_type`, `filament_density` | temperatures above            |

//!
//! The machine ([`crate::machine`]) overrides the profile's bed size and height, nozzle and
//! filament diameter and heated bed, and brings its start and end code, so one profile
//! serves every machine.
//!
//! What varies between slicers lives behind [`SlicerProfile`], one file per slicer
//! (`prusa.rs` and `cura.rs`, which build on this one); `slice::load_profile` picks it.

use super::{SliceError, SliceSettings};
use crate::machine::Machine;
use std::ffi::OsString;
use std::path::Path;

pub(crate) const PRUSA_PROFILE: &str =
    include_str!("../../../../config/prusaslicer-ultimaker2.ini");
pub(crate) const CURA_PROFILE: &str = include_str!("../../../../config/cura-ultimaker2.toml");
pub(crate) const START_GCODE: &str = include_str!("../../../../gcode/start.gcode");
pub(crate) const END_GCODE: &str = include_str!("../../../../gcode/end.gcode");

/// A slicer with its profile loaded, ready to slice jobs.
pub trait SlicerProfile: std::fmt::Debug + Send + Sync {
    /// The slicer's command line for one job of the meshes `stls` (each a part of the
    /// plate, placed where it goes, or one model the slicer duplicates
    /// `job.copies` times); files it needs are written into `workdir`.
    fn invocation(
        &self,
        job: &JobParams,
        workdir: &Path,
        stls: &[std::path::PathBuf],
        gcode: &Path,
    ) -> Result<Invocation, SliceError>;
}

/// The per-job values the command line is built from.
#[derive(Clone, Debug)]
pub struct JobParams<'a> {
    pub settings: &'a SliceSettings,
    /// Bed, nozzle, filament and start/end code come from the machine, over the profile.
    pub machine: &'a Machine,
    pub nozzle_temp_c: f64,
    pub bed_temp_c: f64,
    pub height_mm: f64,
    /// Copies of the one mesh the slicer lays out itself (PrusaSlicer's `--duplicate`);
    /// 1 where crispen placed each part.
    pub copies: u32,
}

/// Arguments and extra environment for the slicer program.
#[derive(Clone, Debug, Default)]
pub struct Invocation {
    pub args: Vec<OsString>,
    pub env: Vec<(OsString, OsString)>,
}

/// The machine's start and end code with this job's values filled in. A machine without
/// a heated bed loses the lines that heat it.
pub(crate) fn start_end_gcode(job: &JobParams) -> (String, String) {
    let m = job.machine;
    let present_z = (job.height_mm + 50.0).min(m.bed_mm[2] - 5.0);
    let start = m.start_gcode.as_deref().unwrap_or(START_GCODE);
    let end = m.end_gcode.as_deref().unwrap_or(END_GCODE);
    let start: String = start
        .lines()
        .filter(|l| m.heated_bed || !l.contains("{BED_TEMP}"))
        .map(|l| format!("{l}\n"))
        .collect();
    let start = start
        .replace("{BED_TEMP}", &fmt_num(job.bed_temp_c))
        .replace("{NOZZLE_TEMP}", &fmt_num(job.nozzle_temp_c));
    let end = end.replace("{PRESENT_Z}", &fmt_num(present_z));
    (start, end)
}

/// A number as the slicers' configs want it: at most three decimals, no trailing zeros.
pub(super) fn fmt_num(v: f64) -> String {
    let r = (v * 1000.0).round() / 1000.0;
    format!("{r}")
}

/// The machine's bed centre as `x,y` in mm.
pub(super) fn bed_centre(machine: &Machine) -> String {
    format!(
        "{},{}",
        fmt_num(machine.bed_mm[0] / 2.0),
        fmt_num(machine.bed_mm[1] / 2.0)
    )
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn start_and_end_code_get_the_job_values_and_keep_no_placeholders() {
        let settings = SliceSettings::default();
        let machine = Machine::builtin("ultimaker2").unwrap();
        let job = JobParams {
            settings: &settings,
            machine: &machine,
            nozzle_temp_c: 215.0,
            bed_temp_c: 65.0,
            height_mm: 40.0,
            copies: 1,
        };
        let (start, end) = start_end_gcode(&job);
        assert!(
            start.contains("M190 S65") && start.contains("M109 S215"),
            "{start}"
        );
        assert!(end.contains("G1 Z90 "), "{end}");
        assert!(!start.contains('{') && !end.contains('{'));

        let cold = Machine {
            heated_bed: false,
            ..machine.clone()
        };
        let (start, _) = start_end_gcode(&JobParams {
            machine: &cold,
            ..job
        });
        assert!(
            !start.contains("M190") && !start.contains("M140"),
            "{start}"
        );
        assert!(start.contains("M109 S215"), "{start}");
    }
}
