//! The enhancement as the nozzle draws it: two G-code files of one model (plain and
//! enhanced, same slicer and settings) compared by their outer walls, layer by layer.
//!
//! The outer wall is what a viewer sees of a print, and slicers mark it: PrusaSlicer
//! `;TYPE:External perimeter`, CuraEngine `;TYPE:WALL-OUTER`. [`outer_walls`] follows the
//! moves as Marlin would ([`crispen_marlin::motion`]) and keeps every extruding move of that
//! type as a segment of its layer (layers keyed by Z to the micrometre). [`compare`]
//! samples the enhanced walls every [`SAMPLE_SPACING_MM`] and measures each sample's
//! distance to the nearest segment of the plain wall of the same layer (a grid of cells
//! finds it without scanning the layer).
//!
//! Every input is bounded, since G-code may be anything: coordinates beyond
//! [`COORD_LIMIT_MM`] and non-finite numbers are dropped, distances are capped at
//! [`MAX_DISTANCE_MM`] (a wall moved that far is not a detail, and the cap bounds the
//! search), and a wall longer than [`MAX_SAMPLES`] samples is sampled more coarsely.

use crispen_marlin::motion::Motion;
use serde::{Deserialize, Serialize};
use std::collections::BTreeMap;
use std::io::BufRead;

/// Distance between samples along the enhanced wall, mm.
pub(crate) const SAMPLE_SPACING_MM: f64 = 0.05;
/// Distances are capped here, mm.
pub const MAX_DISTANCE_MM: f64 = 5.0;
/// Coordinates beyond ±this are not a printer's, mm; such moves are dropped.
pub(crate) const COORD_LIMIT_MM: f64 = 10_000.0;
/// At most this many samples in one comparison (Spot 100 mm tall has 1.6 million; a
/// taller print is sampled more coarsely, which changes its figures little, as the
/// samples only weight the wall by length).
pub(crate) const MAX_SAMPLES: usize = 2_000_000;
/// At most this many wall segments are kept from one file (Spot 100 mm tall has 40,000).
pub(crate) const MAX_SEGMENTS: usize = 5_000_000;
/// The shares reported: wall moved more than these, mm.
pub(crate) const THRESHOLDS_MM: [f64; 3] = [0.05, 0.1, 0.2];

/// Histogram bin for the percentile, mm (the p95 is exact to this).
const BIN_MM: f64 = 0.0005;

/// A wall segment in the XY plane, mm.
pub(crate) type Segment = [[f64; 2]; 2];

/// The outer walls of one G-code file: per layer (Z in µm), the segments drawn.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct OuterWalls {
    pub layers: BTreeMap<i64, Vec<Segment>>,
}

impl OuterWalls {
    pub fn segment_count(&self) -> usize {
        self.layers.values().map(Vec::len).sum()
    }
}

/// Whether a `;TYPE:` comment starts an outer wall (PrusaSlicer or CuraEngine).
fn is_outer_wall(kind: &str) -> bool {
    let kind = kind.trim();
    kind.eq_ignore_ascii_case("External perimeter") || kind.eq_ignore_ascii_case("WALL-OUTER")
}

/// Reads the outer walls from G-code. Fails only when the reader fails.
pub fn outer_walls(reader: impl BufRead) -> std::io::Result<OuterWalls> {
    let mut walls = OuterWalls::default();
    let mut kept = 0usize;
    // A file that marks no outer wall has none to compare.
    extruding_moves(
        reader,
        |k| k.is_some_and(is_outer_wall),
        |m| {
            let (pos, target) = (m.from, m.to);
            let sane = |p: &[f64; 4]| p[..3].iter().all(|c| c.abs() <= COORD_LIMIT_MM);
            if sane(&pos)
                && sane(&target)
                && (target[0] != pos[0] || target[1] != pos[1])
                && kept < MAX_SEGMENTS
            {
                let z = (target[2] * 1000.0).round() as i64;
                walls
                    .layers
                    .entry(z)
                    .or_default()
                    .push([[pos[0], pos[1]], [target[0], target[1]]]);
                kept += 1;
            }
        },
    )?;
    Ok(walls)
}

/// Follows G-code as Marlin would ([`crispen_marlin::motion`]) and hands `each` every move
/// that pushes filament (E increasing) within a `;TYPE:` section whose kind `kind` accepts
/// (a layer change ends a section); `kind(None)` says whether to take the moves of a file
/// that has marked none so far (one from another slicer, or written by hand). Arcs come as
/// their chords: the slicers here write none (arc fitting is off in the built-in
/// profiles), and a chord only shortens a line. The outer walls and the preview of the
/// print (`crate::preview::print`) read G-code so. Fails only when the reader fails.
pub(crate) fn extruding_moves(
    reader: impl BufRead,
    kind: impl Fn(Option<&str>) -> bool,
    mut each: impl FnMut(crispen_marlin::motion::Move),
) -> std::io::Result<()> {
    let mut motion = Motion::default();
    let mut marked = false;
    let mut in_kind = kind(None);
    for line in reader.split(b'\n') {
        let line = line?;
        let line = String::from_utf8_lossy(&line);
        let (code, comment) = match line.find(';') {
            Some(i) => (&line[..i], Some(&line[i + 1..])),
            None => (&line[..], None),
        };
        if let Some(c) = comment {
            let c = c.trim();
            if let Some(k) = c.strip_prefix("TYPE:") {
                marked = true;
                in_kind = kind(Some(k));
            } else if (c.starts_with("LAYER:") || c == "LAYER_CHANGE") && marked {
                in_kind = false;
            }
        }
        let Ok(Some(cmd)) = crispen_marlin::reader::read(code) else {
            continue;
        };
        // A command that cannot be followed leaves the position as it was: a file the
        // policy refuses is never printed anyway.
        let Ok(Some(m)) = motion.apply(&cmd) else {
            continue;
        };
        if in_kind && m.to[3] > m.from[3] {
            each(m);
        }
    }
    Ok(())
}

/// One layer's figures.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct LayerFigures {
    pub z_mm: f64,
    pub mean_mm: f64,
    /// Share of this layer's enhanced wall moved more than 0.1 mm.
    pub share_over_0_1_mm: f64,
}

/// How far the enhanced outer wall lies from the plain one.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct WallComparison {
    /// Layers with an outer wall in both files (the figures are over these).
    pub layers: usize,
    /// Layers with an outer wall in only one of the files.
    pub layers_unmatched: usize,
    /// Length of the enhanced outer wall measured, mm.
    pub wall_mm: f64,
    pub samples: usize,
    /// The spacing used (more than [`SAMPLE_SPACING_MM`] only for very long walls), mm.
    pub spacing_mm: f64,
    /// Distance from the enhanced wall to the plain one, over the wall's length, mm.
    pub mean_mm: f64,
    pub p95_mm: f64,
    /// What all but 1 % of the wall is within (the largest is often a contour that a
    /// tiny change in Z moved far, not a move of the wall), mm.
    #[serde(default)]
    pub p99_mm: f64,
    pub max_mm: f64,
    /// Share (0–1) of the enhanced wall's length moved more than 0.05, 0.1, 0.2 mm.
    pub share_over_0_05_mm: f64,
    pub share_over_0_1_mm: f64,
    pub share_over_0_2_mm: f64,
    /// A quarter of the machine's line width (the threshold a printer's rounding hides a
    /// move under, `crispen_geometry::enhance::printed`), mm, and the share of the wall moved more.
    #[serde(default)]
    pub quarter_line_mm: f64,
    #[serde(default)]
    pub share_over_quarter_line: f64,
    /// Per compared layer, bottom to top (not kept in reports: a figure per layer).
    #[serde(skip)]
    pub per_layer: Vec<LayerFigures>,
}

/// Compares the enhanced walls against the plain ones (see the module's comment), for a
/// machine drawing lines `line_width_mm` wide.
pub fn compare(plain: &OuterWalls, enhanced: &OuterWalls, line_width_mm: f64) -> WallComparison {
    let mut out = WallComparison {
        quarter_line_mm: crispen_geometry::enhance::LINE_WIDTH_FRACTION * line_width_mm,
        ..WallComparison::default()
    };
    let matched: Vec<(i64, &[Segment], &[Segment])> = enhanced
        .layers
        .iter()
        .filter_map(|(z, e)| {
            plain
                .layers
                .get(z)
                .map(|p| (*z, p.as_slice(), e.as_slice()))
        })
        .collect();
    out.layers = matched.len();
    out.layers_unmatched = plain.layers.len() + enhanced.layers.len() - 2 * matched.len();
    let length: f64 = matched
        .iter()
        .flat_map(|(_, _, e)| e.iter())
        .map(seg_len)
        .sum();
    let spacing = SAMPLE_SPACING_MM.max(length / MAX_SAMPLES as f64);
    out.spacing_mm = spacing;
    let bins = (MAX_DISTANCE_MM / BIN_MM) as usize + 1;
    let mut histogram = vec![0u64; bins];
    let mut sum = 0.0;
    let mut over = [0u64; 3];
    let mut over_quarter_line = 0u64;
    for (z, p, e) in matched {
        let grid = Grid::new(p, e);
        let (mut layer_n, mut layer_sum, mut layer_over) = (0u64, 0.0, 0u64);
        for s in e {
            let len = seg_len(s);
            out.wall_mm += len;
            let n = ((len / spacing).ceil() as usize).max(1);
            for k in 0..n {
                let t = (k as f64 + 0.5) / n as f64;
                let q = [
                    s[0][0] + t * (s[1][0] - s[0][0]),
                    s[0][1] + t * (s[1][1] - s[0][1]),
                ];
                let d = grid.nearest(q);
                histogram[((d / BIN_MM) as usize).min(bins - 1)] += 1;
                sum += d;
                out.max_mm = out.max_mm.max(d);
                for (c, t) in over.iter_mut().zip(THRESHOLDS_MM) {
                    *c += u64::from(d > t);
                }
                over_quarter_line += u64::from(d > out.quarter_line_mm);
                layer_n += 1;
                layer_sum += d;
                layer_over += u64::from(d > 0.1);
            }
        }
        out.samples += layer_n as usize;
        out.per_layer.push(LayerFigures {
            z_mm: z as f64 / 1000.0,
            mean_mm: layer_sum / layer_n.max(1) as f64,
            share_over_0_1_mm: layer_over as f64 / layer_n.max(1) as f64,
        });
    }
    if out.samples > 0 {
        let n = out.samples as f64;
        out.mean_mm = sum / n;
        let quantile = |q: f64| {
            let target = (q * n).ceil() as u64;
            let mut acc = 0u64;
            for (i, c) in histogram.iter().enumerate() {
                acc += c;
                if acc >= target {
                    return ((i + 1) as f64 * BIN_MM).min(out.max_mm);
                }
            }
            out.max_mm
        };
        out.p95_mm = quantile(0.95);
        out.p99_mm = quantile(0.99);
        out.share_over_0_05_mm = over[0] as f64 / n;
        out.share_over_0_1_mm = over[1] as f64 / n;
        out.share_over_0_2_mm = over[2] as f64 / n;
        out.share_over_quarter_line = over_quarter_line as f64 / n;
    }
    out
}

fn seg_len(s: &Segment) -> f64 {
    (s[1][0] - s[0][0]).hypot(s[1][1] - s[0][1])
}

fn point_segment(q: [f64; 2], s: &Segment) -> f64 {
    let (a, b) = (s[0], s[1]);
    let d = [b[0] - a[0], b[1] - a[1]];
    let l2 = d[0] * d[0] + d[1] * d[1];
    let t = if l2 > 0.0 {
        (((q[0] - a[0]) * d[0] + (q[1] - a[1]) * d[1]) / l2).clamp(0.0, 1.0)
    } else {
        0.0
    };
    (q[0] - a[0] - t * d[0]).hypot(q[1] - a[1] - t * d[1])
}

/// The plain layer's segments bucketed into square cells covering both layers.
struct Grid<'a> {
    segments: &'a [Segment],
    origin: [f64; 2],
    cell: f64,
    dims: [usize; 2],
    /// Per cell, indices into `segments`.
    cells: Vec<Vec<u32>>,
}

/// At most this many cells a side.
const GRID_MAX: usize = 512;

impl<'a> Grid<'a> {
    fn new(segments: &'a [Segment], also: &[Segment]) -> Grid<'a> {
        let mut lo = [f64::INFINITY; 2];
        let mut hi = [f64::NEG_INFINITY; 2];
        for p in segments.iter().chain(also).flatten() {
            for k in 0..2 {
                lo[k] = lo[k].min(p[k]);
                hi[k] = hi[k].max(p[k]);
            }
        }
        let extent = (hi[0] - lo[0]).max(hi[1] - lo[1]).max(0.0);
        // Cells of at least 1 mm: a query looks at most MAX_DISTANCE_MM cells away.
        let cell = (extent / GRID_MAX as f64).max(1.0);
        let dims = [0, 1].map(|k| (((hi[k] - lo[k]) / cell) as usize + 1).min(GRID_MAX));
        let mut cells = vec![Vec::new(); dims[0] * dims[1]];
        let mut grid = Grid {
            segments,
            origin: lo,
            cell,
            dims,
            cells: Vec::new(),
        };
        let mut put = |x: usize, y: usize, i: u32| {
            let cell: &mut Vec<u32> = &mut cells[y * dims[0] + x];
            if cell.last() != Some(&i) {
                cell.push(i);
            }
        };
        for (i, s) in segments.iter().enumerate() {
            let i = i as u32;
            let a = grid.cell_of(s[0]);
            let b = grid.cell_of(s[1]);
            let (x0, x1) = (a[0].min(b[0]), a[0].max(b[0]));
            let (y0, y1) = (a[1].min(b[1]), a[1].max(b[1]));
            if (x1 - x0 + 1) * (y1 - y0 + 1) <= 16 {
                // A wall segment is short: every cell of its bounding box.
                for x in x0..=x1 {
                    for y in y0..=y1 {
                        put(x, y, i);
                    }
                }
            } else {
                // A long one (or garbage): points along it less than a cell apart, each
                // with the cells around it, which covers every cell it crosses.
                let steps =
                    ((seg_len(s) / (0.5 * grid.cell)).ceil() as usize).clamp(1, 4 * GRID_MAX);
                for k in 0..=steps {
                    let t = k as f64 / steps as f64;
                    let p = [
                        s[0][0] + t * (s[1][0] - s[0][0]),
                        s[0][1] + t * (s[1][1] - s[0][1]),
                    ];
                    let [cx, cy] = grid.cell_of(p);
                    for x in cx.saturating_sub(1)..=(cx + 1).min(dims[0] - 1) {
                        for y in cy.saturating_sub(1)..=(cy + 1).min(dims[1] - 1) {
                            put(x, y, i);
                        }
                    }
                }
            }
        }
        grid.cells = cells;
        grid
    }

    fn cell_of(&self, p: [f64; 2]) -> [usize; 2] {
        [0, 1].map(|k| {
            let c = ((p[k] - self.origin[k]) / self.cell).floor();
            if c.is_nan() || c < 0.0 {
                0
            } else {
                (c as usize).min(self.dims[k] - 1)
            }
        })
    }

    /// Distance from `q` to the nearest segment, capped at [`MAX_DISTANCE_MM`]: cells in
    /// rings around q's cell, until the nearest found is closer than any further ring.
    fn nearest(&self, q: [f64; 2]) -> f64 {
        let [cx, cy] = self.cell_of(q).map(|c| c as i64);
        let mut best = MAX_DISTANCE_MM;
        let max_ring = self.dims[0].max(self.dims[1]) as i64;
        for r in 0..=max_ring {
            for x in (cx - r)..=(cx + r) {
                for y in (cy - r)..=(cy + r) {
                    let on_ring = (x - cx).abs() == r || (y - cy).abs() == r;
                    if !on_ring || x < 0 || y < 0 {
                        continue;
                    }
                    let (x, y) = (x as usize, y as usize);
                    if x >= self.dims[0] || y >= self.dims[1] {
                        continue;
                    }
                    for &i in &self.cells[y * self.dims[0] + x] {
                        best = best.min(point_segment(q, &self.segments[i as usize]));
                    }
                }
            }
            // Anything in ring r + 1 or beyond is at least r cells away (and a distance is
            // never more than the cap).
            if best <= r as f64 * self.cell || r as f64 * self.cell >= MAX_DISTANCE_MM {
                break;
            }
        }
        best
    }
}

/// `len` bytes drawn from `alphabet` by a fixed generator (`state` its seed and its
/// state): G-code's noise, the same at every run.
#[cfg(test)]
pub(crate) fn random_bytes(state: &mut u64, alphabet: &[u8], len: usize) -> Vec<u8> {
    (0..len)
        .map(|_| {
            *state = state
                .wrapping_mul(6364136223846793005)
                .wrapping_add(1442695040888963407);
            alphabet[(*state >> 33) as usize % alphabet.len()]
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    /// `layers` layers, each: an inner perimeter, then the outer wall of `kind`, a square
    /// of half side `half` about (50, 50), then infill; E reset at each layer.
    fn square_gcode(kind: &str, half: f64, layers: usize) -> String {
        let mut g = String::from("G90\nM82\n");
        for l in 1..=layers {
            let z = 0.2 * l as f64;
            g += &format!(";LAYER_CHANGE\n;Z:{z}\nG92 E0\nG1 Z{z:.3}\n");
            g += ";TYPE:Perimeter\nG1 X0 Y0\nG1 X1 Y1 E0.1\n";
            g += &format!(";TYPE:{kind}\nG1 X{0} Y{0} F600\n", 50.0 - half);
            let mut e = 0.1;
            for (x, y) in [(1.0, -1.0), (1.0, 1.0), (-1.0, 1.0), (-1.0, -1.0)] {
                e += 0.5;
                g += &format!(
                    "G1 X{:.4} Y{:.4} E{e:.4}\n",
                    50.0 + x * half,
                    50.0 + y * half
                );
            }
            g += ";TYPE:Solid infill\nG1 X50 Y50 E100\n";
        }
        g
    }

    #[test]
    fn reads_only_the_outer_wall_of_each_layer() {
        let w = outer_walls(square_gcode("External perimeter", 10.0, 3).as_bytes()).unwrap();
        assert_eq!(
            w.layers.keys().copied().collect::<Vec<_>>(),
            [200, 400, 600]
        );
        assert!(w.layers.values().all(|s| s.len() == 4), "{w:?}");
        let cura = outer_walls(square_gcode("WALL-OUTER", 10.0, 2).as_bytes()).unwrap();
        assert_eq!(cura.segment_count(), 8);
        let none = outer_walls(square_gcode("WALL-INNER", 10.0, 2).as_bytes()).unwrap();
        assert_eq!(none.segment_count(), 0);
    }

    #[test]
    fn a_wall_moved_out_by_a_known_distance() {
        let plain = outer_walls(square_gcode("External perimeter", 10.0, 2).as_bytes()).unwrap();
        let same = compare(&plain, &plain, 0.4);
        assert_eq!(same.layers, 2);
        assert!(same.mean_mm < 1e-12, "{same:?}");
        assert_eq!(same.share_over_0_05_mm, 0.0);
        assert!((same.wall_mm - 160.0).abs() < 1e-9);
        assert!(same.samples >= 3200, "{}", same.samples);

        let grown = outer_walls(square_gcode("External perimeter", 10.15, 2).as_bytes()).unwrap();
        let c = compare(&plain, &grown, 0.4);
        // Every sample of the grown square is 0.15 mm out (the corners, further along the
        // diagonal, are nearest to the plain corner: up to 0.15·√2).
        assert!((c.mean_mm - 0.15).abs() < 2e-3, "{c:?}");
        assert!((c.p95_mm - 0.15).abs() < 2e-3, "{c:?}");
        assert!(c.p99_mm >= c.p95_mm && c.p99_mm <= c.max_mm, "{c:?}");
        assert!(c.max_mm <= 0.15 * 2f64.sqrt() + 1e-9);
        assert_eq!(c.share_over_0_05_mm, 1.0);
        assert_eq!(c.share_over_0_1_mm, 1.0);
        assert!(c.share_over_0_2_mm < 0.01, "{c:?}");
        // A quarter of a 0.4 mm line is 0.1 mm, of a 0.8 mm one 0.2 mm.
        assert_eq!(c.share_over_quarter_line, 1.0);
        assert!(compare(&plain, &grown, 0.8).share_over_quarter_line < 0.01);
        assert_eq!(c.per_layer.len(), 2);
        assert_eq!(c.per_layer[0].z_mm, 0.2);
    }

    #[test]
    fn distances_are_capped_and_unmatched_layers_counted() {
        let plain = outer_walls(square_gcode("External perimeter", 10.0, 2).as_bytes()).unwrap();
        let mut far = plain.clone();
        for s in far.layers.values_mut().flatten() {
            for p in s.iter_mut() {
                p[0] += 1000.0;
            }
        }
        far.layers.insert(999_000, vec![[[0.0, 0.0], [1.0, 0.0]]]);
        let c = compare(&plain, &far, 0.4);
        assert_eq!(c.max_mm, MAX_DISTANCE_MM);
        assert_eq!(c.layers, 2);
        assert_eq!(c.layers_unmatched, 1);
        let empty = compare(&OuterWalls::default(), &plain, 0.4);
        assert_eq!((empty.layers, empty.samples, empty.mean_mm), (0, 0, 0.0));
    }

    #[test]
    fn a_long_segment_is_found_wherever_it_passes() {
        // One diagonal segment across a 300 mm layer; samples of a parallel one 0.3 mm
        // away must all find it, along its whole length.
        let plain = OuterWalls {
            layers: [(200, vec![[[0.0, 0.0], [300.0, 290.0]]])].into(),
        };
        let off = 0.3 / (300.0f64.hypot(290.0));
        let (dx, dy) = (-290.0 * off, 300.0 * off);
        let enhanced = OuterWalls {
            layers: [(200, vec![[[dx, dy], [300.0 + dx, 290.0 + dy]]])].into(),
        };
        let c = compare(&plain, &enhanced, 0.4);
        assert!(
            (c.max_mm - 0.3).abs() < 1e-9 && (c.mean_mm - 0.3).abs() < 1e-9,
            "{c:?}"
        );
    }

    #[test]
    fn relative_moves_and_garbage_do_not_panic() {
        let g = "M83\nG91\n;TYPE:External perimeter\nG1 Z0.2\nG1 X10 E1\nG1 Y10 E1\n\
                 G1 X1e300 E1\nG1 Xnan E1\nG1 X-1e308 Y-1e308 E1\nG92 X0 Y0\nG1 X5 E-1\n\
                 ;TYPE:\n\x00\x01\u{fffd}G1 E\nG1 X Y Z\n";
        let w = outer_walls(g.as_bytes()).unwrap();
        // Lines no firmware reads alike (`X1e300`, `Xnan`) are no moves here: the G-code
        // policy refuses them before anything prints.
        assert_eq!(w.layers[&200].len(), 2, "{w:?}");
        assert_eq!(w.layers[&200][1], [[10.0, 0.0], [10.0, 10.0]]);
        let _ = compare(&w, &w, 0.4);
        // Random bytes from G-code's alphabet.
        const ALPHABET: &[u8] = b"G1XYZE0123456789.-; \nTYPE:External perimeter\nM83G92";
        let mut state = 12345u64;
        for _ in 0..200 {
            let bytes = random_bytes(&mut state, ALPHABET, 400);
            let w = outer_walls(&bytes[..]).unwrap();
            let c = compare(&w, &w, 0.4);
            assert!(c.mean_mm.is_finite() && c.max_mm <= MAX_DISTANCE_MM);
        }
    }
}
