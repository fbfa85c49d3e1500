//! PrusaSlicer: the profile is an `.ini` config passed with `--load`, followed by a second
//! config of this job's values (temperatures, settings, start/end code).

use super::profiles::{bed_centre, fmt_num, start_end_gcode, Invocation, JobParams, SlicerProfile};
use super::SliceError;
use std::ffi::OsString;
use std::path::Path;

/// PrusaSlicer with its `.ini` profile.
#[derive(Clone, Debug)]
pub(crate) struct PrusaProfile {
    ini: String,
}

impl PrusaProfile {
    /// Checks the profile text (`shown` names it in errors).
    pub(crate) fn load(ini: String, shown: &Path) -> Result<PrusaProfile, SliceError> {
        check_prusa_ini(&ini).map_err(|reason| SliceError::BadProfile {
            path: shown.to_path_buf(),
            reason,
        })?;
        Ok(PrusaProfile { ini })
    }
}

impl SlicerProfile for PrusaProfile {
    fn invocation(
        &self,
        job: &JobParams,
        workdir: &Path,
        stls: &[std::path::PathBuf],
        gcode: &Path,
    ) -> Result<Invocation, SliceError> {
        let (start, end) = start_end_gcode(job);
        let s = job.settings;
        let material = s.material_preset()?;
        let ini = &self.ini;
        let mut job_ini = String::from("# written by crispen for this job\n");
        let mut put = |k: &str, v: String| job_ini.push_str(&format!("{k} = {v}\n"));
        if let Some(lh) = s.layer_height_mm {
            put("layer_height", fmt_num(lh));
            put("first_layer_height", fmt_num(lh.max(0.2)));
        }
        if let Some(p) = s.infill_percent {
            put("fill_density", format!("{}%", fmt_num(p)));
        }
        if let Some(on) = s.supports {
            put("support_material", u8::from(on).to_string());
            put("support_material_auto", "1".into());
        }
        put("temperature", fmt_num(job.nozzle_temp_c));
        put("first_layer_temperature", fmt_num(job.nozzle_temp_c));
        put("bed_temperature", fmt_num(job.bed_temp_c));
        put("first_layer_bed_temperature", fmt_num(job.bed_temp_c));
        put("filament_type", material.name.to_ascii_uppercase());
        put("filament_density", fmt_num(material.density_g_cm3));
        let m = job.machine;
        let [x, y, z] = m.bed_mm.map(fmt_num);
        put("bed_shape", format!("0x0,{x}x0,{x}x{y},0x{y}"));
        put("max_print_height", z);
        put("nozzle_diameter", fmt_num(m.nozzle_mm));
        put("filament_diameter", fmt_num(m.filament_mm));
        // Each object labelled (`; printing object NAME`), so a part of a plate can be
        // cancelled while the others print on.
        put("gcode_label_objects", "1".into());
        put("start_gcode", prusa_escape(&start));
        put("end_gcode", prusa_escape(&end));
        let profile_path = workdir.join("profile.ini");
        let job_path = workdir.join("job.ini");
        for (path, text) in [(&profile_path, ini.as_str()), (&job_path, job_ini.as_str())] {
            std::fs::write(path, text).map_err(|source| SliceError::Io {
                context: "cannot write slicer config",
                path: path.clone(),
                source,
            })?;
        }
        let centre = bed_centre(job.machine);
        let mut args: Vec<OsString> = vec![
            "--export-gcode".into(),
            "--load".into(),
            profile_path.into(),
            "--load".into(),
            job_path.into(),
        ];
        // Several objects or copies are arranged on the bed by PrusaSlicer itself, the
        // whole centred on the bed.
        if job.copies > 1 {
            args.extend(["--duplicate".into(), job.copies.to_string().into()]);
        }
        // Without `--merge` PrusaSlicer slices each input file alone, each over the same
        // output, leaving the last; with it, one plate of them all, arranged.
        if stls.len() > 1 {
            args.push("--merge".into());
        }
        args.extend([
            "--center".into(),
            centre.into(),
            "--output".into(),
            gcode.into(),
        ]);
        args.extend(stls.iter().map(|s| s.as_os_str().to_owned()));
        Ok(Invocation { args, env: vec![] })
    }
}

/// A PrusaSlicer config is `key = value` lines, comments and blank lines; catching other
/// text here gives a clearer message than the slicer's.
fn check_prusa_ini(text: &str) -> Result<(), String> {
    for (i, line) in text.lines().enumerate() {
        let t = line.trim();
        if t.is_empty() || t.starts_with('#') || t.starts_with(';') {
            continue;
        }
        if t.starts_with('[') {
            return Err(format!(
                "line {}: sections ({t}) are PrusaSlicer bundles, not a config; export one \
                 printer/print/filament config with PrusaSlicer's File > Export > Export Config",
                i + 1
            ));
        }
        if !t.contains('=') {
            return Err(format!(
                "line {}: expected `key = value`, found {t:?}",
                i + 1
            ));
        }
    }
    Ok(())
}

/// PrusaSlicer config values are single-line; newlines and backslashes are escaped.
fn prusa_escape(text: &str) -> String {
    text.replace('\\', "\\\\").replace('\n', "\\n")
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn builtin_profile_parses_and_bad_ones_name_the_line() {
        check_prusa_ini(super::super::profiles::PRUSA_PROFILE).unwrap();
        let e = check_prusa_ini("layer_height = 0.2\n[printer:Ultimaker 2]\n").unwrap_err();
        assert!(e.contains("line 2"), "{e}");
    }
}
