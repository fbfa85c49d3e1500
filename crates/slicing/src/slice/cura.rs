//! CuraEngine: the profile is a TOML table of settings, each passed as `-s key=value`
//! together with Ultimaker's printer definitions; crispen computes the values Cura's
//! front end would derive with Python formulas.

use super::profiles::{fmt_num, start_end_gcode, Invocation, JobParams, SlicerProfile};
use super::{SliceError, SliceSettings};
use std::ffi::OsString;
use std::path::{Path, PathBuf};

/// Default place of Ultimaker's definitions (scripts/setup puts them there); the
/// environment variable CRISPEN_CURA_RESOURCES overrides it.
pub(crate) const DEFAULT_CURA_RESOURCES: &str = "/usr/local/share/crispen/cura";

/// CuraEngine with its settings and the folder holding `definitions/` and `extruders/`.
#[derive(Clone, Debug)]
pub(crate) struct CuraProfile {
    settings: Vec<(String, String)>,
    resources: PathBuf,
}

impl CuraProfile {
    /// Reads the profile text (`shown` names it in errors) and checks Ultimaker's
    /// definitions are installed.
    pub(crate) fn load(text: &str, shown: &Path) -> Result<CuraProfile, SliceError> {
        let settings = parse_cura_toml(text).map_err(|reason| SliceError::BadProfile {
            path: shown.to_path_buf(),
            reason,
        })?;
        let resources = cura_resources();
        let machine = resources.join("definitions").join("ultimaker2.def.json");
        if !machine.is_file() {
            return Err(SliceError::CuraResourcesMissing { path: machine });
        }
        Ok(CuraProfile {
            settings,
            resources,
        })
    }
}

impl SlicerProfile for CuraProfile {
    fn invocation(
        &self,
        job: &JobParams,
        _workdir: &Path,
        stls: &[PathBuf],
        gcode: &Path,
    ) -> Result<Invocation, SliceError> {
        let (start, end) = start_end_gcode(job);
        let s = job.settings;
        let (settings, resources) = (&self.settings, &self.resources);
        let mut map: Vec<(String, String)> = settings.clone();
        let mut put = |k: &str, v: String| {
            map.retain(|(key, _)| key != k);
            map.push((k.to_string(), v));
        };
        if let Some(lh) = s.layer_height_mm {
            put("layer_height", fmt_num(lh));
        }
        if let Some(p) = s.infill_percent {
            put("infill_sparse_density", fmt_num(p));
        }
        if let Some(on) = s.supports {
            put("support_enable", on.to_string());
        }
        for k in [
            "material_print_temperature",
            "material_print_temperature_layer_0",
            "material_initial_print_temperature",
            "material_final_print_temperature",
            "default_material_print_temperature",
        ] {
            put(k, fmt_num(job.nozzle_temp_c));
        }
        for k in [
            "material_bed_temperature",
            "material_bed_temperature_layer_0",
            "default_material_bed_temperature",
        ] {
            put(k, fmt_num(job.bed_temp_c));
        }
        let m = job.machine;
        put("machine_width", fmt_num(m.bed_mm[0]));
        put("machine_depth", fmt_num(m.bed_mm[1]));
        put("machine_height", fmt_num(m.bed_mm[2]));
        put("machine_nozzle_size", fmt_num(m.nozzle_mm));
        put("material_diameter", fmt_num(m.filament_mm));
        put("machine_heated_bed", m.heated_bed.to_string());
        // Cura derives line widths from the nozzle with formulas the engine cannot
        // evaluate on the command line; a profile that sets them keeps its own.
        for k in [
            "line_width",
            "wall_line_width",
            "wall_line_width_0",
            "wall_line_width_x",
            "skin_line_width",
            "infill_line_width",
            "skirt_brim_line_width",
            "support_line_width",
        ] {
            if !settings.iter().any(|(key, _)| key == k) || k == "line_width" {
                put(k, fmt_num(m.nozzle_mm));
            }
        }
        put("machine_start_gcode", start);
        put("machine_end_gcode", end);
        derive_cura_formulas(&mut map, s);

        let definitions = resources.join("definitions");
        let extruders = resources.join("extruders");
        let mut args: Vec<OsString> = vec![
            "slice".into(),
            // -v logs the real print time estimate (the G-code header has placeholders).
            "-v".into(),
            "-j".into(),
            definitions.join("ultimaker2.def.json").into(),
        ];
        for (k, v) in &map {
            args.push("-s".into());
            args.push(format!("{k}={v}").into());
        }
        args.extend(["-o".into(), gcode.as_os_str().to_owned()]);
        // One mesh per part of the plate, each where crispen placed it; CuraEngine labels
        // each by its file's name (`;MESH:NAME`).
        for stl in stls {
            args.extend(["-l".into(), stl.as_os_str().to_owned()]);
        }
        let mut search = OsString::from(definitions);
        search.push(":");
        search.push(extruders);
        Ok(Invocation {
            args,
            env: vec![("CURA_ENGINE_SEARCH_PATH".into(), search)],
        })
    }
}

/// Where CuraEngine's definitions are: CRISPEN_CURA_RESOURCES or the default.
pub fn cura_resources() -> PathBuf {
    std::env::var_os("CRISPEN_CURA_RESOURCES")
        .filter(|v| !v.is_empty())
        .map(PathBuf::from)
        .unwrap_or_else(|| PathBuf::from(DEFAULT_CURA_RESOURCES))
}

/// Reads a CuraEngine settings file: a TOML table of scalar values.
pub(crate) fn parse_cura_toml(text: &str) -> Result<Vec<(String, String)>, String> {
    let table: toml::Table = toml::from_str(text).map_err(|e| e.to_string())?;
    let mut out = Vec::with_capacity(table.len());
    for (key, value) in table {
        let v = match value {
            toml::Value::String(s) => s,
            toml::Value::Integer(n) => n.to_string(),
            toml::Value::Float(f) => f.to_string(),
            toml::Value::Boolean(b) => b.to_string(),
            other => {
                return Err(format!(
                    "{key}: expected a string, number or true/false, found a {}",
                    other.type_str()
                ))
            }
        };
        out.push((key, v));
    }
    Ok(out)
}

/// Values Cura computes with Python formulas that CuraEngine cannot evaluate on the
/// command line: the infill line spacing from the density, and the infill and support
/// thickness from the layer height. Explicit values in the profile are kept unless the
/// job overrides what they derive from.
fn derive_cura_formulas(map: &mut Vec<(String, String)>, s: &SliceSettings) {
    let get = |map: &Vec<(String, String)>, k: &str| {
        map.iter().find(|(key, _)| key == k).map(|(_, v)| v.clone())
    };
    let num =
        |map: &Vec<(String, String)>, k: &str| get(map, k).and_then(|v| v.parse::<f64>().ok());
    let put = |map: &mut Vec<(String, String)>, k: &str, v: String| {
        map.retain(|(key, _)| key != k);
        map.push((k.to_string(), v));
    };
    if s.infill_percent.is_some() || get(map, "infill_line_distance").is_none() {
        if let Some(density) = num(map, "infill_sparse_density") {
            let width = num(map, "infill_line_width")
                .or_else(|| num(map, "line_width"))
                .unwrap_or(0.4);
            let pattern = get(map, "infill_pattern").unwrap_or_else(|| "grid".into());
            let lines_per_cell = match pattern.as_str() {
                "grid" | "tetrahedral" | "quarter_cubic" => 2.0,
                "triangles" | "trihexagon" | "cubic" | "cubicsubdiv" => 3.0,
                _ => 1.0,
            };
            let distance = if density <= 0.0 {
                0.0
            } else {
                width * 100.0 / density * lines_per_cell
            };
            put(map, "infill_line_distance", fmt_num(distance));
        }
    }
    if let Some(lh) = num(map, "layer_height") {
        for k in ["infill_sparse_thickness", "support_infill_sparse_thickness"] {
            if s.layer_height_mm.is_some() || get(map, k).is_none() {
                put(map, k, fmt_num(lh));
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn builtin_profile_parses_and_bad_ones_name_the_key() {
        let cura = parse_cura_toml(super::super::profiles::CURA_PROFILE).unwrap();
        assert!(cura
            .iter()
            .any(|(k, v)| k == "machine_gcode_flavor" && v == "RepRap (Marlin/Sprinter)"));
        assert!(cura
            .iter()
            .any(|(k, v)| k == "material_diameter" && v == "2.85"));
        let e = parse_cura_toml("layer_height = [1, 2]\n").unwrap_err();
        assert!(e.contains("layer_height"), "{e}");
    }

    #[test]
    fn cura_infill_spacing_follows_the_density() {
        let mut map = vec![
            ("infill_sparse_density".to_string(), "20".to_string()),
            ("infill_pattern".to_string(), "grid".to_string()),
            ("layer_height".to_string(), "0.2".to_string()),
        ];
        derive_cura_formulas(&mut map, &SliceSettings::default());
        let get = |k: &str| map.iter().find(|(key, _)| key == k).unwrap().1.clone();
        assert_eq!(get("infill_line_distance"), "4");
        assert_eq!(get("infill_sparse_thickness"), "0.2");
    }
}
