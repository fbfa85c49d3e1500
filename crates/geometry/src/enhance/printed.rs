//! The enhancement in printed millimetres: how far the surface moved once the model is
//! scaled to its printed height, set against what the machine can draw (its line width
//! and layer height). A displacement in the model's own units says nothing about whether
//! the print changes; one in mm next to the nozzle does.
//!
//! Figures are area-weighted (each vertex stands for a third of the area of its
//! triangles), so a densely meshed ear does not count for more than a flat back.
//! [`Displacements`] is computed once per enhanced mesh and summarised for each machine
//! ([`Displacements::summary`]), because the printed size is the job's but the nozzle is
//! the machine's.

use crate::mesh::Mesh;
use serde::{Deserialize, Serialize};

/// The fraction of the line width a displacement must exceed to count as one the
/// printer draws: a quarter (0.1 mm on a 0.4 mm nozzle). Slicers place walls to a few
/// hundredths of a millimetre, so a smaller move is lost in their rounding.
pub const LINE_WIDTH_FRACTION: f64 = 0.25;

/// The line width crispen asks of both slicers, from the nozzle: CuraEngine's line widths
/// are set to the nozzle diameter; PrusaSlicer's external perimeter is 1.05–1.125 times
/// it, which the quarter-width threshold does not distinguish.
pub fn line_width_mm(nozzle_mm: f64) -> f64 {
    nozzle_mm
}

/// What the printer draws with: its nozzle and layer height, mm.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct PrintResolution {
    pub nozzle_mm: f64,
    pub layer_height_mm: f64,
}

/// The enhancement at the printed size, mm.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct PrintedDisplacement {
    /// The printed height these figures are for.
    pub height_mm: f64,
    /// Model units → printed mm.
    pub scale: f64,
    /// Largest, 95th and 99th percentile and mean displacement (area-weighted), mm.
    pub max_mm: f64,
    pub p95_mm: f64,
    /// 99th percentile (the print-aware mode's bound is on it), mm.
    #[serde(default)]
    pub p99_mm: f64,
    pub mean_mm: f64,
    /// The machine's nozzle and layer height, when the figures are for a machine.
    pub nozzle_mm: Option<f64>,
    pub layer_height_mm: Option<f64>,
    pub line_width_mm: Option<f64>,
    /// A quarter of the line width, and the share of the surface (area, 0–1) moved by
    /// more than it.
    pub threshold_mm: Option<f64>,
    pub share_above_threshold: Option<f64>,
}

/// Per-vertex displacements of one enhancement, sorted, with the area each stands for.
#[derive(Clone, Debug, Default)]
pub struct Displacements {
    /// (distance moved in model units, vertex area), ascending by distance.
    sorted: Vec<(f64, f64)>,
    total_area: f64,
}

impl Displacements {
    /// Pairs `before` and `after` (the same faces, moved vertices) vertex by vertex.
    /// `None` when they do not have the same vertices, or the surface has no area.
    pub fn between(before: &Mesh, after: &Mesh) -> Option<Displacements> {
        let n = before.vertices.len();
        if after.vertices.len() != n || n == 0 {
            return None;
        }
        let mut area = vec![0.0f64; n];
        for f in &before.faces {
            let [a, b, c] = f.map(|i| i as usize);
            if a >= n || b >= n || c >= n {
                return None;
            }
            let (p, q, r) = (before.vertices[a], before.vertices[b], before.vertices[c]);
            let third = triangle_area(p, q, r) / 3.0;
            if third.is_finite() {
                area[a] += third;
                area[b] += third;
                area[c] += third;
            }
        }
        let pairs = before
            .vertices
            .iter()
            .zip(&after.vertices)
            .zip(area)
            .map(|((p, q), a)| {
                let d =
                    ((p[0] - q[0]).powi(2) + (p[1] - q[1]).powi(2) + (p[2] - q[2]).powi(2)).sqrt();
                (d, a)
            })
            .collect();
        Displacements::from_pairs(pairs)
    }

    /// From (distance moved, area) per vertex; `None` when the areas sum to nothing. A
    /// distance that is not a number counts as infinitely far.
    pub(crate) fn from_pairs(mut sorted: Vec<(f64, f64)>) -> Option<Displacements> {
        for pair in &mut sorted {
            if !pair.0.is_finite() {
                pair.0 = f64::INFINITY;
            }
        }
        sorted.sort_by(|x, y| x.0.total_cmp(&y.0));
        let total_area: f64 = sorted.iter().map(|x| x.1).sum();
        (total_area > 0.0 && total_area.is_finite()).then_some(Displacements { sorted, total_area })
    }

    /// The largest distance moved, model units.
    pub(crate) fn max(&self) -> f64 {
        self.sorted.last().map_or(0.0, |x| x.0)
    }

    /// The figures at `scale` (model units → mm) for a print `height_mm` tall, and for a
    /// machine when `printer` is given.
    pub fn summary(
        &self,
        scale: f64,
        height_mm: f64,
        printer: Option<PrintResolution>,
    ) -> PrintedDisplacement {
        let mean = self.sorted.iter().map(|(d, a)| d * a).sum::<f64>() / self.total_area;
        let max = self.max();
        let line_width = printer.map(|p| line_width_mm(p.nozzle_mm));
        let threshold = line_width.map(|w| w * LINE_WIDTH_FRACTION);
        PrintedDisplacement {
            height_mm,
            scale,
            max_mm: max * scale,
            p95_mm: self.quantile(0.95) * scale,
            p99_mm: self.quantile(0.99) * scale,
            mean_mm: mean * scale,
            nozzle_mm: printer.map(|p| p.nozzle_mm),
            layer_height_mm: printer.map(|p| p.layer_height_mm),
            line_width_mm: line_width,
            threshold_mm: threshold,
            share_above_threshold: threshold.map(|t| self.share_above(t / scale)),
        }
    }

    /// The area-weighted `q` quantile of the displacement, model units.
    pub(crate) fn quantile(&self, q: f64) -> f64 {
        let target = q.clamp(0.0, 1.0) * self.total_area;
        let mut acc = 0.0;
        for &(d, a) in &self.sorted {
            acc += a;
            if acc >= target {
                return d;
            }
        }
        self.sorted.last().map_or(0.0, |x| x.0)
    }

    /// The share of the area (0–1) moved by more than `limit` model units.
    pub(crate) fn share_above(&self, limit: f64) -> f64 {
        let first = self.sorted.partition_point(|x| x.0 <= limit);
        // A float sum starts at -0.0; the share of nothing is 0.
        (0.0 + self.sorted[first..].iter().map(|x| x.1).sum::<f64>()) / self.total_area
    }
}

fn triangle_area(p: [f64; 3], q: [f64; 3], r: [f64; 3]) -> f64 {
    let u = [q[0] - p[0], q[1] - p[1], q[2] - p[2]];
    let v = [r[0] - p[0], r[1] - p[1], r[2] - p[2]];
    let c = [
        u[1] * v[2] - u[2] * v[1],
        u[2] * v[0] - u[0] * v[2],
        u[0] * v[1] - u[1] * v[0],
    ];
    0.5 * (c[0] * c[0] + c[1] * c[1] + c[2] * c[2]).sqrt()
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Two triangles of a unit square (area 1) with a third, tiny triangle far away.
    fn square() -> Mesh {
        Mesh {
            vertices: vec![
                [0.0, 0.0, 0.0],
                [1.0, 0.0, 0.0],
                [1.0, 1.0, 0.0],
                [0.0, 1.0, 0.0],
            ],
            faces: vec![[0, 1, 2], [0, 2, 3]],
        }
    }

    #[test]
    fn figures_are_area_weighted_and_scaled_to_mm() {
        let before = square();
        let mut after = before.clone();
        // Vertex 0 and 2 stand for 1/3 of the area each, 1 and 3 for 1/6 each.
        after.vertices[0][2] = 0.1;
        after.vertices[1][2] = 0.4;
        let d = Displacements::between(&before, &after).unwrap();
        let printer = PrintResolution {
            nozzle_mm: 0.4,
            layer_height_mm: 0.2,
        };
        let s = d.summary(2.0, 20.0, Some(printer));
        assert!((s.max_mm - 0.8).abs() < 1e-12);
        // Mean: (0.1·1/3 + 0.4·1/6) · 2 mm.
        assert!(
            (s.mean_mm - 2.0 * (0.1 / 3.0 + 0.4 / 6.0)).abs() < 1e-12,
            "{s:?}"
        );
        // The 95th percentile of the area is the largest move (vertex 1 holds 1/6).
        assert!((s.p95_mm - 0.8).abs() < 1e-12);
        assert_eq!(s.threshold_mm, Some(0.1));
        // Moved more than 0.1 mm (0.05 model units): vertices 0 (0.2 mm) and 1 (0.8 mm).
        let share = s.share_above_threshold.unwrap();
        assert!((share - 0.5).abs() < 1e-12, "{share}");
        assert_eq!(s.nozzle_mm, Some(0.4));
        // Without a machine: millimetres, no threshold.
        let bare = d.summary(2.0, 20.0, None);
        assert_eq!(bare.share_above_threshold, None);
        assert_eq!(bare.max_mm, s.max_mm);
    }

    #[test]
    fn a_wider_nozzle_counts_fewer_moves() {
        let before = square();
        let mut after = before.clone();
        for (k, v) in after.vertices.iter_mut().enumerate() {
            v[2] = 0.04 * (k + 1) as f64;
        }
        let d = Displacements::between(&before, &after).unwrap();
        let share = |nozzle_mm| {
            d.summary(
                1.0,
                10.0,
                Some(PrintResolution {
                    nozzle_mm,
                    layer_height_mm: 0.2,
                }),
            )
            .share_above_threshold
            .unwrap()
        };
        assert!(share(0.25) > share(0.4) && share(0.4) > share(0.8));
        assert_eq!(share(0.8), 0.0);
    }

    #[test]
    fn mismatched_or_empty_meshes_give_none() {
        let before = square();
        let mut fewer = before.clone();
        fewer.vertices.pop();
        assert!(Displacements::between(&before, &fewer).is_none());
        let flat = Mesh {
            vertices: vec![[0.0; 3]; 3],
            faces: vec![[0, 1, 2]],
        };
        assert!(Displacements::between(&flat, &flat).is_none());
        let bad_index = Mesh {
            vertices: vec![[0.0; 3]; 3],
            faces: vec![[0, 1, 7]],
        };
        assert!(Displacements::between(&bad_index, &bad_index).is_none());
    }
}
