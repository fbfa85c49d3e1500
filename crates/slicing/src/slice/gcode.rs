//! Checking a slicer's G-code before it becomes a job, and reading its figures.
//!
//! The check follows the moves as Marlin would ([`crispen_marlin::motion`]: G90/G91, M82/M83, G92,
//! G28, arcs, offsets) and demands:
//! some extruding moves; every move inside the machine (X, Y within the bed, Z within the
//! height, with a 0.5 mm allowance for rounding: the start code's purge and the skirt are
//! on the bed, so nothing legitimately leaves it); the top printed layer at the asked
//! height (within a layer, plus two for pointed tops the slicer drops); no run of empty
//! layers (which would leave the rest printed in the air); and both heaters switched on
//! (M104/M109 and M140/M190) before the first extrusion. It also counts layers and reads the slicer's estimates.

use crispen_marlin::firmware::Firmware;
use crispen_marlin::motion::{self, Motion};
use std::io::BufRead;

/// What the job must satisfy.
#[derive(Clone, Debug)]
pub(crate) struct Expectations {
    pub bed_mm: [f64; 3],
    /// Printed height of the model.
    pub height_mm: f64,
    /// The requested layer height, if any; otherwise it is read from the G-code.
    pub layer_height_mm: Option<f64>,
    /// Whether the machine has a heated bed (then it must be heated before extruding).
    pub heated_bed: bool,
    /// How the moves are followed (arcs, home offsets differ).
    pub firmware: Firmware,
}

/// Figures read from a G-code file that passed the check.
#[derive(Clone, Debug, Default, PartialEq)]
pub(crate) struct GcodeStats {
    pub lines: usize,
    /// Distinct heights at which the model is printed (extruding moves in X/Y).
    pub layer_count: usize,
    pub layer_height_mm: Option<f64>,
    pub top_z_mm: f64,
    /// Net filament pushed by all moves, mm (from the E axis).
    pub extruded_mm: f64,
    pub estimated_time_s: Option<f64>,
    pub filament_mm: Option<f64>,
    pub filament_g: Option<f64>,
    pub slicer_version: Option<String>,
}

/// How many layers below the model's top the last printed layer may be.
pub(crate) const TOP_LAYERS_ALLOWED: f64 = 3.0;

/// Allowance for rounding at the edges of the machine.
const EDGE_MM: f64 = 0.5;

/// Parses `1d 2h 3m 4s`, `21m 14s` or `45s` into seconds.
pub(crate) fn parse_duration_words(text: &str) -> Option<f64> {
    let mut total = 0.0;
    let mut any = false;
    for word in text.split_whitespace() {
        let (num, unit) = word.split_at(word.find(|c: char| c.is_alphabetic())?);
        let n: f64 = num.parse().ok()?;
        total += n * match unit {
            "d" => 86400.0,
            "h" => 3600.0,
            "m" => 60.0,
            "s" => 1.0,
            _ => return None,
        };
        any = true;
    }
    any.then_some(total)
}

/// CuraEngine's `-v` log line `Print time (s): 2637`.
pub(crate) fn parse_cura_log_time(line: &str) -> Option<f64> {
    line.trim()
        .strip_prefix("Print time (s):")
        .and_then(|v| v.trim().parse().ok())
}

fn comment_value<'a>(comment: &'a str, key: &str) -> Option<&'a str> {
    let rest = comment.trim_start().strip_prefix(key)?;
    Some(rest.trim_start().strip_prefix('=').unwrap_or(rest).trim())
}

/// Reads and checks G-code; the error is the reason it is not a usable job.
pub(crate) fn check(reader: impl BufRead, expect: &Expectations) -> Result<GcodeStats, String> {
    let mut stats = GcodeStats::default();
    let mut motion = Motion::new(expect.firmware);
    let mut nozzle_heated = false;
    let mut bed_heated = !expect.heated_bed;
    let mut first_extrusion_line: Option<usize> = None;
    let mut layer_zs: Vec<f64> = Vec::new();
    let mut top_z = f64::NEG_INFINITY;
    let mut extruding_moves = 0usize;
    let mut header_layer_height: Option<f64> = None;
    let mut last_time_elapsed: Option<f64> = None;

    for (index, line) in reader.split(b'\n').enumerate() {
        let line = line.map_err(|e| format!("cannot read the G-code: {e}"))?;
        let line = String::from_utf8_lossy(&line);
        let number = index + 1;
        stats.lines = number;
        let (code, comment) = match line.find(';') {
            Some(i) => (&line[..i], Some(&line[i + 1..])),
            None => (&line[..], None),
        };
        if let Some(c) = comment {
            read_comment(
                c,
                &mut stats,
                &mut header_layer_height,
                &mut last_time_elapsed,
            );
        }
        let Ok(Some(cmd)) = crispen_marlin::reader::read(code) else {
            continue;
        };
        let get = |letter: char| cmd.get(letter);
        match cmd.code.as_str() {
            "M104" | "M109" if get('S').is_some_and(|t| t > 0.0) => nozzle_heated = true,
            "M140" | "M190" if get('S').is_some_and(|t| t > 0.0) => bed_heated = true,
            _ => {}
        }
        let Some(m) = motion
            .apply(&cmd)
            .map_err(|e| format!("line {number}: {e}"))?
        else {
            continue;
        };
        if let Some(k) = motion::outside(m.lo, m.hi, expect.bed_mm, EDGE_MM) {
            let axis = ['X', 'Y', 'Z'][k];
            let past = if m.lo[k] < -EDGE_MM { m.lo[k] } else { m.hi[k] };
            return Err(format!(
                "line {number} moves {axis} to {past:.2} mm, outside the printer's 0..{} mm",
                expect.bed_mm[k]
            ));
        }
        let de = m.extruded();
        if de > 0.0 {
            if first_extrusion_line.is_none() {
                first_extrusion_line = Some(number);
                if !(nozzle_heated && bed_heated) {
                    return Err(format!(
                        "line {number} extrudes before {} heated (M104/M109 and M140/M190 \
                         must come first)",
                        match (nozzle_heated, bed_heated) {
                            (false, false) => "the nozzle and the bed are",
                            (false, true) => "the nozzle is",
                            _ => "the bed is",
                        }
                    ));
                }
            }
            if m.moves_xy() {
                extruding_moves += 1;
                // The file's own number (the firmware's float of 0.4 is 0.40000001): a
                // layer is reported as sliced.
                let z = m.written.1[2];
                top_z = top_z.max(z);
                if !layer_zs.iter().any(|lz| (lz - z).abs() < 1e-4) {
                    layer_zs.push(z);
                }
            }
        }
        stats.extruded_mm += de;
    }

    if stats.lines == 0 {
        return Err("the G-code file is empty".into());
    }
    if extruding_moves == 0 {
        return Err("the G-code has no extruding moves (nothing would be printed)".into());
    }
    layer_zs.sort_by(f64::total_cmp);
    stats.layer_count = layer_zs.len();
    stats.top_z_mm = top_z;
    stats.layer_height_mm = expect.layer_height_mm.or(header_layer_height);
    let layer = stats
        .layer_height_mm
        .unwrap_or_else(|| median_step(&layer_zs).unwrap_or(0.3));
    // Something must be printed on the bed, and every layer must rest on one below: a run
    // of empty layers leaves everything above printed in the air.
    let first_z = layer_zs[0];
    if first_z > layer.max(0.3) + 1e-3 {
        return Err(format!(
            "the first printed layer is at Z {first_z:.3} mm, not on the bed"
        ));
    }
    if let Some(w) = layer_zs
        .windows(2)
        .find(|w| w[1] - w[0] > 2.5 * layer + 1e-3)
    {
        return Err(format!(
            "nothing is printed between Z {:.2} and {:.2} mm, so what is above would be \
             printed in the air; the model may be lying on its side (try --up y) or have parts \
             too thin to print at this height",
            w[0], w[1]
        ));
    }
    // Slicers cut at mid-layer, so the last layer lies within one layer of the top; and
    // they drop islands narrower than the nozzle, so a pointed top (an ear, a spire) loses
    // a layer or two more. A mis-scaled model misses by far more than three layers.
    if (top_z - expect.height_mm).abs() > TOP_LAYERS_ALLOWED * layer + 1e-3 {
        return Err(format!(
            "the top layer is at Z {top_z:.3} mm but the model is {:.3} mm tall (layer height \
             {layer} mm)",
            expect.height_mm
        ));
    }
    if stats.estimated_time_s.is_none() {
        stats.estimated_time_s = last_time_elapsed;
    }
    Ok(stats)
}

fn median_step(zs: &[f64]) -> Option<f64> {
    let mut steps: Vec<f64> = zs.windows(2).map(|w| w[1] - w[0]).collect();
    steps.sort_by(f64::total_cmp);
    steps.get(steps.len() / 2).copied()
}

fn read_comment(
    comment: &str,
    stats: &mut GcodeStats,
    header_layer_height: &mut Option<f64>,
    last_time_elapsed: &mut Option<f64>,
) {
    let c = comment.trim();
    if let Some(v) = c.strip_prefix("generated by PrusaSlicer ") {
        stats.slicer_version = Some(format!(
            "PrusaSlicer {}",
            v.split_whitespace().next().unwrap_or("")
        ));
    } else if let Some(v) = c.strip_prefix("Generated with Cura_SteamEngine ") {
        stats.slicer_version = Some(format!("CuraEngine {}", v.trim()));
    } else if let Some(v) = comment_value(c, "estimated printing time (normal mode)") {
        stats.estimated_time_s = parse_duration_words(v);
    } else if let Some(v) = comment_value(c, "filament used [mm]") {
        stats.filament_mm = v.split(',').next().and_then(|x| x.trim().parse().ok());
    } else if let Some(v) = comment_value(c, "total filament used [g]") {
        stats.filament_g = v.parse().ok();
    } else if let Some(v) = c.strip_prefix("TIME_ELAPSED:") {
        *last_time_elapsed = v.trim().parse().ok();
    } else if let Some(v) = c.strip_prefix("Layer height:") {
        *header_layer_height = v.trim().parse().ok();
    } else if let Some(v) = comment_value(c, "layer_height") {
        *header_layer_height = v.parse().ok();
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn expect(height: f64) -> Expectations {
        Expectations {
            bed_mm: [223.0, 223.0, 205.0],
            height_mm: height,
            layer_height_mm: Some(0.2),
            heated_bed: true,
            firmware: Firmware::Ultimaker2,
        }
    }

    const HEAT: &str = "M140 S60\nM104 S210\nG28\nM190 S60\nM109 S210\nG92 E0\n";

    fn two_layers() -> String {
        format!(
            "; generated by PrusaSlicer 2.5.0 on today\n{HEAT}G1 Z0.2 F600\nG1 X100 Y100\n\
             G1 X110 Y100 E1.5\nG1 Z0.4\nG1 X100 Y100 E3\n\
             ; estimated printing time (normal mode) = 1h 2m 3s\n\
             ; filament used [mm] = 3.00\n; total filament used [g] = 0.02\n"
        )
    }

    #[test]
    fn reads_layers_and_prusaslicer_figures() {
        let s = check(two_layers().as_bytes(), &expect(0.4)).unwrap();
        assert_eq!(s.layer_count, 2);
        assert_eq!(s.top_z_mm, 0.4);
        assert_eq!(s.estimated_time_s, Some(3723.0));
        assert_eq!(s.filament_mm, Some(3.0));
        assert_eq!(s.filament_g, Some(0.02));
        assert_eq!(s.slicer_version.as_deref(), Some("PrusaSlicer 2.5.0"));
        assert!((s.extruded_mm - 3.0).abs() < 1e-9);
    }

    #[test]
    fn rejects_empty_and_non_extruding_gcode() {
        assert!(check(&b""[..], &expect(1.0)).unwrap_err().contains("empty"));
        let travel = format!("{HEAT}G1 X10 Y10 Z0.2\nG1 X20 Y20\n");
        let e = check(travel.as_bytes(), &expect(0.2)).unwrap_err();
        assert!(e.contains("no extruding moves"), "{e}");
    }

    #[test]
    fn rejects_extruding_before_heating() {
        let g = "G28\nG1 Z0.2\nG1 X10 Y10 E1\nM109 S210\nM190 S60\n";
        let e = check(g.as_bytes(), &expect(0.2)).unwrap_err();
        assert!(
            e.contains("line 3") && e.contains("nozzle and the bed"),
            "{e}"
        );
        let g = "M109 S210\nG1 Z0.2\nG1 X10 Y10 E1\n";
        let e = check(g.as_bytes(), &expect(0.2)).unwrap_err();
        assert!(e.contains("the bed is"), "{e}");
    }

    #[test]
    fn rejects_moves_off_the_bed_including_relative_ones() {
        let g = format!("{HEAT}G1 Z0.2\nG1 X230 Y10 E1\n");
        let e = check(g.as_bytes(), &expect(0.2)).unwrap_err();
        assert!(e.contains("line 8") && e.contains("X to 230.00"), "{e}");
        let g = format!("{HEAT}G1 X5 Y5 Z0.2\nG1 X10 E1\nG91\nG1 X-20\n");
        let e = check(g.as_bytes(), &expect(0.2)).unwrap_err();
        assert!(e.contains("X to -10.00"), "{e}");
    }

    #[test]
    fn rejects_missing_layers_and_a_print_that_starts_in_the_air() {
        let gap =
            format!("{HEAT}G1 Z0.2\nG1 X100 Y100\nG1 X110 Y100 E1\nG1 Z1.0\nG1 X100 Y100 E2\n");
        let e = check(gap.as_bytes(), &expect(1.0)).unwrap_err();
        assert!(e.contains("between Z 0.20 and 1.00"), "{e}");
        let high = format!("{HEAT}G1 Z0.8\nG1 X100 Y100\nG1 X110 Y100 E1\n");
        let e = check(high.as_bytes(), &expect(0.8)).unwrap_err();
        assert!(e.contains("not on the bed"), "{e}");
    }

    #[test]
    fn rejects_a_top_layer_at_the_wrong_height() {
        let e = check(two_layers().as_bytes(), &expect(5.0)).unwrap_err();
        assert!(e.contains("top layer is at Z 0.400"), "{e}");
    }

    #[test]
    fn parses_durations_and_cura_log_lines() {
        assert_eq!(parse_duration_words("21m 14s"), Some(1274.0));
        assert_eq!(parse_duration_words("1d 0h 0m 1s"), Some(86401.0));
        assert_eq!(parse_duration_words("soon"), None);
        assert_eq!(parse_cura_log_time("Print time (s): 2637"), Some(2637.0));
        assert_eq!(parse_cura_log_time("Print time (hr|min|s): 0h 43m"), None);
    }
}
