//! G-code sliced elsewhere: what a file says about the machine it was made for, and
//! whether it may be printed as it is on a given machine.
//!
//! [`read_target`] reads what the slicer wrote where it writes it: PrusaSlicer's config
//! block at the end (`; filament_diameter = 2.85`, `; nozzle_diameter`, `; printer_model`,
//! `; bed_shape`, `; max_print_height`, `; filament_type = PLA`), CuraEngine's header
//! (`;FLAVOR:`, `;NOZZLE_DIAMETER:`, and in the header Cura puts at the top of a Griffin
//! file, `;EXTRUDER_TRAIN.0.MATERIAL.GUID:`) and Cura's settings block
//! (`;SETTING_3 ...definition = ultimaker2...`), and follows the moves as Marlin would
//! ([`crispen_marlin::motion`]) for their extent, arcs included. A file's material is
//! only what its slicer wrote as one, never guessed from its temperatures; CuraEngine's
//! Marlin flavour names none, and UltiGCode's `;MATERIAL:` is a volume, not a name. [`check_for`] compares that with
//! a [`Machine`]: a file made for another filament or nozzle, another known printer, the
//! SD-card-only UltiGCode flavour, or whose moves leave the machine's bed is refused with
//! the reason. Binary G-code (PrusaSlicer's `.bgcode`) is refused by [`read_target`].
//! Pure functions over a reader; no slicer is run.

use crate::machine::Machine;
use crispen_marlin::motion::Motion;
use std::io::BufRead;

/// The first bytes of a binary G-code file (PrusaSlicer 2.7's `.bgcode`).
pub(crate) const BINARY_MAGIC: &[u8; 4] = b"GCDE";

/// Allowance for rounding at the edges of the bed, mm.
const EDGE_MM: f64 = 0.5;
/// Filament diameters closer than this are the same filament (1.75 vs 1.73 slicer presets).
const FILAMENT_TOLERANCE_MM: f64 = 0.1;
const NOZZLE_TOLERANCE_MM: f64 = 0.01;

/// What a G-code file says about its target, and what its moves do.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct GcodeTarget {
    /// `PrusaSlicer 2.5.0`, `Cura_SteamEngine 4.13.0`.
    pub slicer: Option<String>,
    /// Cura's `;FLAVOR:` or PrusaSlicer's `gcode_flavor`.
    pub flavor: Option<String>,
    /// PrusaSlicer's `printer_model`, or the Cura definition's id.
    pub printer_model: Option<String>,
    pub filament_mm: Option<f64>,
    /// The material it was sliced for, as the slicer names it (`PLA`, PrusaSlicer's
    /// `FLEX`), unchecked: the job's asks check it.
    pub material: Option<String>,
    pub nozzle_mm: Option<f64>,
    /// The bed the slicer was told of (PrusaSlicer's `bed_shape` and `max_print_height`).
    pub stated_bed_mm: Option<[f64; 3]>,
    /// Lowest and highest X, Y, Z any move goes to: [[min x, max x], [min y, max y], [min z, max z]].
    pub extent_mm: Option<[[f64; 2]; 3]>,
    /// Net filament pushed, mm (a retraction counts back until it is pushed again).
    pub extruded_mm: f64,
    /// Line of the first extruding move, when it comes before any nozzle heating.
    pub extrudes_cold_at: Option<usize>,
    pub lines: usize,
}

/// Why a file cannot be read as G-code at all.
#[derive(Debug, thiserror::Error)]
pub enum PreslicedError {
    #[error(
        "binary G-code (PrusaSlicer .bgcode) cannot be streamed to a printer over USB; export \
         plain G-code (PrusaSlicer: Print Settings > Output options, untick \"Binary G-code\")"
    )]
    Binary,
    #[error("not G-code: {0}")]
    NotGcode(String),
    #[error("cannot read the G-code: {0}")]
    Read(#[from] std::io::Error),
}

/// Reads a G-code file's target and the extent of its moves.
pub fn read_target(mut reader: impl BufRead) -> Result<GcodeTarget, PreslicedError> {
    if reader.fill_buf()?.starts_with(BINARY_MAGIC) {
        return Err(PreslicedError::Binary);
    }
    let mut t = GcodeTarget::default();
    let mut motion = Motion::default();
    let mut heated = false;
    let mut extent: Option<[[f64; 2]; 3]> = None;
    let mut bed_xy: Option<[f64; 2]> = None;
    let mut bed_z: Option<f64> = None;
    let mut commands = 0usize;
    let mut line = Vec::new();
    loop {
        line.clear();
        if reader.read_until(b'\n', &mut line)? == 0 {
            break;
        }
        t.lines += 1;
        if line.contains(&0) {
            return Err(PreslicedError::NotGcode(format!(
                "line {} holds binary data",
                t.lines
            )));
        }
        let text = String::from_utf8_lossy(&line);
        let (code, comment) = match text.find(';') {
            Some(i) => (&text[..i], Some(text[i + 1..].trim())),
            None => (&text[..], None),
        };
        if let Some(c) = comment {
            read_comment(c, &mut t, &mut bed_xy, &mut bed_z);
        }
        let Ok(Some(cmd)) = crispen_marlin::reader::read(code) else {
            continue;
        };
        commands += 1;
        if matches!(cmd.code.as_str(), "M104" | "M109") && cmd.get('S').is_some_and(|s| s > 0.0) {
            heated = true;
        }
        // What cannot be followed is the policy's to refuse, naming the line; the extent
        // here is of what can.
        if let Ok(Some(m)) = motion.apply(&cmd) {
            let de = m.extruded();
            t.extruded_mm += de;
            if de > 0.0 && !heated && t.extrudes_cold_at.is_none() {
                t.extrudes_cold_at = Some(t.lines);
            }
            if m.moves_xyz() {
                let e = extent.get_or_insert([[f64::INFINITY, f64::NEG_INFINITY]; 3]);
                for (k, [lo, hi]) in e.iter_mut().enumerate() {
                    // As the file writes it: an extent is reported, the bed is the
                    // policy's to judge in both readings.
                    *lo = lo.min(m.written.0[k]);
                    *hi = hi.max(m.written.1[k]);
                }
            }
        }
    }
    if commands == 0 {
        return Err(PreslicedError::NotGcode("it holds no commands".into()));
    }
    t.extent_mm = extent;
    if let (Some([x, y]), Some(z)) = (bed_xy, bed_z) {
        t.stated_bed_mm = Some([x, y, z]);
    }
    Ok(t)
}

/// One comment: PrusaSlicer's `key = value` config lines, Cura's `KEY:value` header lines,
/// Cura's settings block (`SETTING_3 ...`, escaped newlines).
fn read_comment(
    c: &str,
    t: &mut GcodeTarget,
    bed_xy: &mut Option<[f64; 2]>,
    bed_z: &mut Option<f64>,
) {
    let num = |v: &str| {
        v.split(',')
            .next()
            .and_then(|v| v.trim().parse::<f64>().ok())
            .filter(|v| v.is_finite())
    };
    if let Some(rest) = c.strip_prefix("generated by ") {
        t.slicer = Some(rest.split(" on ").next().unwrap_or(rest).trim().to_string());
    } else if let Some(rest) = c.strip_prefix("Generated with ") {
        t.slicer = Some(rest.trim().to_string());
    } else if let Some(v) = c.strip_prefix("FLAVOR:") {
        t.flavor = Some(v.trim().to_string());
    } else if let Some(v) = c.strip_prefix("NOZZLE_DIAMETER:") {
        t.nozzle_mm = t.nozzle_mm.or(num(v));
    } else if let Some(guid) = c.strip_prefix("EXTRUDER_TRAIN.0.MATERIAL.GUID:") {
        if let Some(m) = cura_material(guid) {
            t.material = Some(m.into());
        }
    } else if let Some(blob) = c.strip_prefix("SETTING_3 ") {
        // Cura's front end: its profile as JSON text, newlines escaped (`\\n` in the file).
        let blob = blob.replace("\\\\n", "\n").replace("\\n", "\n");
        for entry in blob.lines() {
            let Some((k, v)) = entry.split_once(" = ") else {
                continue;
            };
            match k.trim() {
                "definition" => t.printer_model = Some(v.trim().to_string()),
                "material_diameter" => t.filament_mm = num(v).or(t.filament_mm),
                "machine_nozzle_size" => t.nozzle_mm = num(v).or(t.nozzle_mm),
                _ => {}
            }
        }
    } else if let Some((k, v)) = c.split_once(" = ") {
        let v = v.trim();
        match k.trim() {
            "filament_diameter" => t.filament_mm = num(v),
            "nozzle_diameter" => t.nozzle_mm = num(v),
            // One per extruder (`PLA;PETG`): the first extruder's, the one a
            // single-extruder printer has.
            "filament_type" => {
                t.material = v
                    .split(';')
                    .next()
                    .map(str::trim)
                    .filter(|m| !m.is_empty())
                    .map(String::from)
            }
            "printer_model" if !v.is_empty() => t.printer_model = Some(v.to_string()),
            "gcode_flavor" => t.flavor = Some(v.to_string()),
            "max_print_height" => *bed_z = num(v),
            "bed_shape" => {
                // Corners `0x0,223x0,223x223,0x223`: the bed is their extent.
                let corners: Vec<[f64; 2]> = v
                    .split(',')
                    .filter_map(|p| {
                        let (x, y) = p.split_once('x')?;
                        Some([x.trim().parse().ok()?, y.trim().parse().ok()?])
                    })
                    .collect();
                if corners.len() >= 3 {
                    let span = |k: usize| {
                        let lo = corners.iter().map(|c| c[k]).fold(f64::INFINITY, f64::min);
                        let hi = corners
                            .iter()
                            .map(|c| c[k])
                            .fold(f64::NEG_INFINITY, f64::max);
                        hi - lo
                    };
                    *bed_xy = Some([span(0), span(1)]);
                }
            }
            _ => {}
        }
    }
}

/// The material of one of Cura's generic material profiles, by its GUID (from Ultimaker's
/// `fdm_materials`: `generic_pla.xml.fdm_material` and its siblings), for the materials
/// crispen knows. Any other profile (a brand's) is not guessed at.
fn cura_material(guid: &str) -> Option<&'static str> {
    const GENERIC: &[(&str, &str)] = &[
        ("506c9f0d-e3aa-4bd4-b2d2-23e2425b1aa9", "PLA"),
        ("1cbfaeb3-1906-4b26-b2e7-6f777a8c197a", "PETG"),
        ("60636bb4-518f-42e7-8237-fe77b194ebe0", "ABS"),
        ("1d52b2be-a3a2-41de-a8b1-3bcdb5618695", "TPU"),
    ];
    let guid = guid.trim();
    GENERIC
        .iter()
        .find(|(g, _)| g.eq_ignore_ascii_case(guid))
        .map(|(_, m)| *m)
}

/// The built-in machine a slicer's printer model names (Cura definition ids), if known.
fn known_model(model: &str) -> Option<&'static str> {
    let id = model.trim().to_ascii_lowercase().replace([' ', '+'], "_");
    Some(match id.as_str() {
        "ultimaker2" | "ultimaker_2" => "ultimaker2",
        "ultimaker2_extended" | "ultimaker_2_extended" => "ultimaker2-extended",
        "ultimaker2_plus" | "ultimaker_2_" => "ultimaker2plus",
        "ultimaker_original_plus" | "ultimaker_original_" => "ultimaker-original-plus",
        _ => return None,
    })
}

/// The built-in machine a machine is, itself or with another nozzle (`ultimaker2plus-0.6mm`).
fn builtin_base(name: &str) -> Option<&'static str> {
    crate::machine::BUILTIN.iter().map(|b| b.name).find(|b| {
        name == *b
            || name
                .strip_prefix(b)
                .and_then(|r| r.strip_prefix('-'))
                .and_then(|r| r.strip_suffix("mm"))
                .is_some_and(|n| n.parse::<f64>().is_ok())
    })
}

/// Whether the file may be printed as it is on `machine`; the error says why not.
pub fn check_for(target: &GcodeTarget, machine: &Machine) -> Result<(), String> {
    let m = machine;
    if let Some(f) = &target.flavor {
        if f.eq_ignore_ascii_case("UltiGCode") {
            return Err(
                "it is UltiGCode, made to print from an Ultimaker 2's SD card (the printer \
                 heats and sets the extrusion itself); slice it with the Marlin flavour to \
                 print it over USB"
                    .into(),
            );
        }
    }
    if let Some(d) = target.filament_mm {
        if (d - m.filament_mm).abs() > FILAMENT_TOLERANCE_MM {
            return Err(format!(
                "it was sliced for {d} mm filament, the {} takes {} mm",
                m.name, m.filament_mm
            ));
        }
    }
    if let Some(d) = target.nozzle_mm {
        if (d - m.nozzle_mm).abs() > NOZZLE_TOLERANCE_MM {
            return Err(format!(
                "it was sliced for a {d} mm nozzle, the {} has {} mm",
                m.name, m.nozzle_mm
            ));
        }
    }
    // Only a known printer model tells: a farm's own machine may be any printer.
    if let Some(model) = &target.printer_model {
        if let (Some(named), Some(this)) = (known_model(model), builtin_base(&m.name)) {
            if named != this {
                return Err(format!(
                    "it was sliced for printer model {model:?} ({named}), not the {}",
                    m.name
                ));
            }
        }
    }
    if let Some(line) = target.extrudes_cold_at {
        return Err(format!(
            "line {line} extrudes before the nozzle is heated (no M104/M109 before it); \
             a file printed over USB must heat the printer itself"
        ));
    }
    let Some(extent) = target.extent_mm else {
        return Err("it holds no moves".into());
    };
    for (k, axis) in ['X', 'Y', 'Z'].into_iter().enumerate() {
        let [lo, hi] = extent[k];
        // Written so that a coordinate that is no number counts as outside.
        if !(lo >= -EDGE_MM && hi <= m.bed_mm[k] + EDGE_MM) {
            return Err(format!(
                "its moves go to {axis} {lo:.1} .. {hi:.1} mm, outside the {}'s bed (0 .. {} mm)",
                m.name, m.bed_mm[k]
            ));
        }
    }
    if target.extruded_mm <= 0.0 {
        return Err("it extrudes nothing".into());
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    fn um2() -> Machine {
        Machine::builtin("ultimaker2").unwrap()
    }

    fn read(text: &str) -> GcodeTarget {
        read_target(text.as_bytes()).unwrap()
    }

    const MOVES: &str =
        "G28\nM104 S210\nM109 S210\nG92 E0\nG1 X10 Y10 Z0.2 F3000\nG1 X100 Y100 E5\n";

    #[test]
    fn prusaslicer_config_block_is_read() {
        let t = read(&format!(
            "; generated by PrusaSlicer 2.5.0 on 2026-12-01 at 21:24:10 UTC\n{MOVES}\
             ; bed_shape = 0x0,250x0,250x210,0x210\n; filament_diameter = 1.75\n\
             ; max_print_height = 210\n; nozzle_diameter = 0.4\n; printer_model = MK3S\n"
        ));
        assert_eq!(t.slicer.as_deref(), Some("PrusaSlicer 2.5.0"));
        assert_eq!(t.filament_mm, Some(1.75));
        assert_eq!(t.stated_bed_mm, Some([250.0, 210.0, 210.0]));
        assert_eq!(t.printer_model.as_deref(), Some("MK3S"));
        assert_eq!(
            t.extent_mm,
            // From the origin G28 left the head at.
            Some([[0.0, 100.0], [0.0, 100.0], [0.0, 0.2]])
        );
        let e = check_for(&t, &um2()).unwrap_err();
        assert!(e.contains("1.75 mm filament") && e.contains("2.85"), "{e}");
    }

    #[test]
    fn cura_settings_block_names_the_printer() {
        let t = read(&format!(
            ";FLAVOR:Marlin\n{MOVES};SETTING_3 {{\"global_quality\": \"[general]\\\\nversion = 4\\\\n\
             definition = ultimaker2_plus\\\\n[values]\\\\nmaterial_diameter = 2.85\\\\n\"}}\n"
        ));
        assert_eq!(t.printer_model.as_deref(), Some("ultimaker2_plus"));
        assert_eq!(t.filament_mm, Some(2.85));
        let e = check_for(&t, &um2()).unwrap_err();
        assert!(e.contains("ultimaker2plus"), "{e}");
        check_for(&t, &Machine::builtin("ultimaker2plus").unwrap()).unwrap();
    }

    #[test]
    fn moves_off_the_bed_cold_extrusion_and_ultigcode_are_refused() {
        check_for(&read(MOVES), &um2()).unwrap();
        let far = format!("{MOVES}G1 X230 Y100 E6\n");
        let e = check_for(&read(&far), &um2()).unwrap_err();
        assert!(e.contains("X 0.0 .. 230.0") && e.contains("223"), "{e}");
        let relative = format!("{MOVES}G91\nG1 Z250\n");
        let e = check_for(&read(&relative), &um2()).unwrap_err();
        assert!(e.contains("Z 0.0 .. 250.2"), "{e}");
        let e = check_for(&read("G28\nG1 X10 Y10 E3\n"), &um2()).unwrap_err();
        assert!(e.contains("line 2 extrudes before"), "{e}");
        let e = check_for(&read(&format!(";FLAVOR:UltiGCode\n{MOVES}")), &um2()).unwrap_err();
        assert!(e.contains("UltiGCode"), "{e}");
    }

    /// The material is what the slicer wrote as one: PrusaSlicer's `filament_type` (the
    /// first extruder's), the Cura header's generic material GUID; never UltiGCode's
    /// `;MATERIAL:` (a volume), nor a brand's GUID crispen does not know.
    #[test]
    fn the_material_is_what_the_slicer_wrote() {
        let material = |text: &str| read(&format!("{MOVES}{text}")).material;
        assert_eq!(material("; filament_type = PLA\n").as_deref(), Some("PLA"));
        assert_eq!(
            material("; filament_type = FLEX;PETG\n").as_deref(),
            Some("FLEX")
        );
        assert_eq!(material("; filament_type = \n"), None);
        assert_eq!(
            material(";EXTRUDER_TRAIN.0.MATERIAL.GUID:1CBFAEB3-1906-4b26-b2e7-6f777a8c197a\n")
                .as_deref(),
            Some("PETG")
        );
        assert_eq!(
            material(";EXTRUDER_TRAIN.0.MATERIAL.GUID:00000000-0000-0000-0000-000000000000\n"),
            None
        );
        assert_eq!(
            material(";FLAVOR:UltiGCode\n;MATERIAL:6666\n;MATERIAL2:0\n"),
            None
        );
        assert_eq!(
            material("M104 S240\nM140 S85\n"),
            None,
            "never from temperatures"
        );
    }

    /// What a file pushes is net: a retraction counts back until it is pushed again,
    /// with absolute and relative E, after `G92 E0`, and with firmware retraction
    /// (`G10`/`G11` leave the file's E where it was).
    #[test]
    fn the_filament_pushed_is_net_of_retractions() {
        let absolute = "G28\nM104 S210\nM109 S210\nM82\nG92 E0\nG1 X10 Y10 E5\n\
                        G1 E-1 F2400\nG1 X20\nG1 E5\nG1 X30 E8\nG92 E0\nG1 E-6\nG1 X40\n\
                        G1 E0\nG1 X50 E2\n";
        assert!((read(absolute).extruded_mm - 10.0).abs() < 1e-9);
        let relative = "G28\nM104 S210\nM109 S210\nM83\nG1 X10 Y10 E5\nG1 E-6.5\nG1 X20\n\
                        G1 E6.5\nG1 X30 E3\nG10\nG1 X40\nG11\nG1 X50 E2\n";
        assert!((read(relative).extruded_mm - 10.0).abs() < 1e-9);
    }

    #[test]
    fn binary_and_non_gcode_files_are_refused() {
        let e = read_target(&b"GCDE\x01\x00\x00\x00"[..]).unwrap_err();
        assert!(matches!(e, PreslicedError::Binary), "{e}");
        assert!(e.to_string().contains("Binary G-code"), "{e}");
        assert!(matches!(
            read_target(&b"; only a comment\n"[..]),
            Err(PreslicedError::NotGcode(_))
        ));
        assert!(matches!(
            read_target(&b"G1 X1\n\x00\x01\x02"[..]),
            Err(PreslicedError::NotGcode(_))
        ));
    }
}
