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

use super::{SliceError, SliceSettings, SlicerKind, BED_MM};
use std::ffi::OsString;
use std::path::{Path, PathBuf};

pub const PRUSA_PROFILE: &str = include_str!("../../config/prusaslicer-ultimaker2.ini");
pub const CURA_PROFILE: &str = include_str!("../../config/cura-ultimaker2.toml");
pub const START_GCODE: &str = include_str!("../../gcode/start.gcode");
pub const END_GCODE: &str = include_str!("../../gcode/end.gcode");

/// Default place of Ultimaker's definitions (scripts/setup puts them there); the
/// environment variable CRISPEN_CURA_RESOURCES overrides it.
pub const DEFAULT_CURA_RESOURCES: &str = "/usr/local/share/crispen/cura";

/// A loaded slicer profile.
#[derive(Clone, Debug)]
pub enum Profile {
    /// PrusaSlicer `.ini` text, passed with `--load`.
    Prusa { ini: String },
    /// CuraEngine settings, each passed as `-s key=value`, and the folder holding
    /// `definitions/` and `extruders/`.
    Cura {
        settings: Vec<(String, String)>,
        resources: PathBuf,
    },
}

/// The per-job values the command line is built from.
#[derive(Clone, Debug)]
pub struct JobParams<'a> {
    pub settings: &'a SliceSettings,
    pub nozzle_temp_c: f64,
    pub bed_temp_c: f64,
    pub height_mm: f64,
}

/// Arguments and extra environment for the slicer program.
#[derive(Clone, Debug, Default)]
pub struct Invocation {
    pub args: Vec<OsString>,
    pub env: Vec<(OsString, OsString)>,
}

/// Where CuraEngine's definitions are: CRISPEN_CURA_RESOURCES or the default.
pub fn cura_resources() -> PathBuf {
    std::env::var_os("CRISPEN_CURA_RESOURCES")
        .filter(|v| !v.is_empty())
        .map(PathBuf::from)
        .unwrap_or_else(|| PathBuf::from(DEFAULT_CURA_RESOURCES))
}

/// Loads `path`, or the built-in profile for the slicer.
pub fn load_profile(kind: SlicerKind, path: Option<&Path>) -> Result<Profile, SliceError> {
    let text = match path {
        Some(p) => std::fs::read_to_string(p).map_err(|e| SliceError::BadProfile {
            path: p.to_path_buf(),
            reason: e.to_string(),
        })?,
        None => match kind {
            SlicerKind::Prusa => PRUSA_PROFILE.to_string(),
            SlicerKind::Cura => CURA_PROFILE.to_string(),
        },
    };
    let shown = path.map_or_else(|| PathBuf::from("(built-in profile)"), Path::to_path_buf);
    match kind {
        SlicerKind::Prusa => {
            check_prusa_ini(&text).map_err(|reason| SliceError::BadProfile {
                path: shown,
                reason,
            })?;
            Ok(Profile::Prusa { ini: text })
        }
        SlicerKind::Cura => {
            let settings = parse_cura_toml(&text).map_err(|reason| SliceError::BadProfile {
                path: shown,
                reason,
            })?;
            let resources = cura_resources();
            let machine = resources.join("definitions").join("ultimaker2.def.json");
            if !machine.is_file() {
                return Err(SliceError::CuraResourcesMissing { path: machine });
            }
            Ok(Profile::Cura {
                settings,
                resources,
            })
        }
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

/// Reads a CuraEngine settings file: a TOML table of scalar values.
pub fn parse_cura_toml(text: &str) -> Result<Vec<(String, String)>, String> {
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

/// The start and end code with this job's values filled in.
pub fn start_end_gcode(job: &JobParams) -> (String, String) {
    let present_z = (job.height_mm + 50.0).min(BED_MM[2] - 5.0);
    let start = START_GCODE
        .replace("{BED_TEMP}", &fmt_num(job.bed_temp_c))
        .replace("{NOZZLE_TEMP}", &fmt_num(job.nozzle_temp_c));
    let end = END_GCODE.replace("{PRESENT_Z}", &fmt_num(present_z));
    (start, end)
}

fn fmt_num(v: f64) -> String {
    let r = (v * 1000.0).round() / 1000.0;
    format!("{r}")
}

/// PrusaSlicer config values are single-line; newlines and backslashes are escaped.
fn prusa_escape(text: &str) -> String {
    text.replace('\\', "\\\\").replace('\n', "\\n")
}

/// Builds the slicer's command line; writes the files it needs into `workdir`.
pub fn build_invocation(
    kind: SlicerKind,
    profile: &Profile,
    job: &JobParams,
    workdir: &Path,
    stl: &Path,
    gcode: &Path,
) -> Result<Invocation, SliceError> {
    let (start, end) = start_end_gcode(job);
    let s = job.settings;
    let material = s.material_preset()?;
    match (kind, profile) {
        (SlicerKind::Prusa, Profile::Prusa { ini }) => {
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
            let centre = format!("{},{}", fmt_num(BED_MM[0] / 2.0), fmt_num(BED_MM[1] / 2.0));
            let args: Vec<OsString> = vec![
                "--export-gcode".into(),
                "--load".into(),
                profile_path.into(),
                "--load".into(),
                job_path.into(),
                "--center".into(),
                centre.into(),
                "--output".into(),
                gcode.into(),
                stl.into(),
            ];
            Ok(Invocation { args, env: vec![] })
        }
        (
            SlicerKind::Cura,
            Profile::Cura {
                settings,
                resources,
            },
        ) => {
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
            args.extend([
                "-o".into(),
                gcode.as_os_str().to_owned(),
                "-l".into(),
                stl.as_os_str().to_owned(),
            ]);
            let mut search = OsString::from(definitions);
            search.push(":");
            search.push(extruders);
            Ok(Invocation {
                args,
                env: vec![("CURA_ENGINE_SEARCH_PATH".into(), search)],
            })
        }
        _ => unreachable!("profile loaded for another slicer"),
    }
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
    fn builtin_profiles_parse() {
        check_prusa_ini(PRUSA_PROFILE).unwrap();
        let cura = parse_cura_toml(CURA_PROFILE).unwrap();
        assert!(cura
            .iter()
            .any(|(k, v)| k == "machine_gcode_flavor" && v == "RepRap (Marlin/Sprinter)"));
        assert!(cura
            .iter()
            .any(|(k, v)| k == "material_diameter" && v == "2.85"));
    }

    #[test]
    fn start_and_end_code_get_the_job_values_and_keep_no_placeholders() {
        let settings = SliceSettings::default();
        let job = JobParams {
            settings: &settings,
            nozzle_temp_c: 215.0,
            bed_temp_c: 65.0,
            height_mm: 40.0,
        };
        let (start, end) = start_end_gcode(&job);
        assert!(
            start.contains("M190 S65") && start.contains("M109 S215"),
            "{start}"
        );
        assert!(end.contains("G1 Z90 "), "{end}");
        assert!(!start.contains('{') && !end.contains('{'));
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

    #[test]
    fn bad_profiles_are_refused_with_the_line() {
        let e = check_prusa_ini("layer_height = 0.2\n[printer:Ultimaker 2]\n").unwrap_err();
        assert!(e.contains("line 2"), "{e}");
        let e = parse_cura_toml("layer_height = [1, 2]\n").unwrap_err();
        assert!(e.contains("layer_height"), "{e}");
    }
}
