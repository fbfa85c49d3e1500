//! Pictures of a job's mesh, made on the CPU (no GPU, no display): the model before and
//! after the enhancement from one camera, a heat map of how far each point of the surface
//! moved, the G-code thumbnails other farm tools show ([`thumbnail`]), and the outer walls
//! of a few layers, plain and enhanced ([`walls`]), and the print as the printer will lay
//! it, drawn from the G-code ([`print`](mod@print)).
//!
//! A small z-buffer rasteriser is all this needs: orthographic projection, per-pixel
//! interpolated normals (the enhancement is a change of shading, so flat or per-vertex
//! lighting would hide what it did), 2×2 supersampling for smooth edges, and a transparent
//! background so the pictures sit on any page.

pub mod print;
mod raster;
mod scene;
pub mod thumbnail;
pub mod walls;

use crispen_geometry::mesh::place::UpAxis;
use crispen_geometry::mesh::Mesh;
use std::path::{Path, PathBuf};

pub use print::PREVIEW_PNG;
pub use raster::{render, render_lit};
pub(crate) use scene::{cross, dot};
pub use scene::{norm, normalize, sub};
pub use scene::{Camera, Image, Lighting, Paint, MODEL_COLOR};

/// The heat map's colours: dark blue (unmoved) through teal and green to yellow (moved
/// most), a perceptually ordered ramp that stays readable for colour-blind viewers.
const HEAT_RAMP: [[f32; 3]; 5] = [
    [0.27, 0.00, 0.33],
    [0.23, 0.32, 0.55],
    [0.13, 0.57, 0.55],
    [0.37, 0.79, 0.38],
    [0.99, 0.91, 0.14],
];

/// A colour on the heat ramp for `t` in 0..=1 (clamped).
pub fn heat_color(t: f64) -> [f32; 3] {
    let t = if t.is_finite() {
        t.clamp(0.0, 1.0)
    } else {
        0.0
    } as f32;
    let x = t * (HEAT_RAMP.len() - 1) as f32;
    let i = (x.floor() as usize).min(HEAT_RAMP.len() - 2);
    let f = x - i as f32;
    std::array::from_fn(|c| HEAT_RAMP[i][c] * (1.0 - f) + HEAT_RAMP[i + 1][c] * f)
}

/// Per-vertex heat colours for the distance each vertex moved from `before` to `after`
/// (same vertices in the same order). The top of the ramp is the 98th percentile of the
/// distances, so a few extreme vertices do not leave the rest of the picture dark; the
/// farther ones are drawn at the top too. Returns the colours and the largest distance.
pub fn displacement_colors(before: &Mesh, after: &Mesh) -> (Vec<[f32; 3]>, f64) {
    let moved: Vec<f64> = before
        .vertices
        .iter()
        .zip(&after.vertices)
        .map(|(a, b)| norm(sub(*b, *a)))
        .collect();
    let max = moved.iter().copied().fold(0.0, f64::max);
    let mut sorted = moved.clone();
    sorted.sort_by(f64::total_cmp);
    let top = sorted
        .get(sorted.len() * 98 / 100)
        .copied()
        .filter(|&t| t > 0.0)
        .unwrap_or(max);
    let colors = moved
        .iter()
        .map(|&d| heat_color(if top > 0.0 { d / top } else { 0.0 }))
        .collect();
    (colors, max)
}

/// The three pictures of an enhanced mesh, from one camera.
pub struct Pictures {
    pub before: Image,
    pub after: Image,
    /// `after`, coloured by how far each vertex moved.
    pub displacement: Image,
    /// The largest distance a vertex moved, in the meshes' units.
    pub max_displacement: f64,
}

/// Renders `before` and `after` (the same vertices, moved) at `size` × `size` pixels. The
/// camera is fitted to `before`, so a part that swells shows it.
pub fn pictures(before: &Mesh, after: &Mesh, up: UpAxis, size: u32) -> Option<Pictures> {
    if before.vertices.len() != after.vertices.len() {
        return None;
    }
    let camera = Camera::three_quarter(before.bounds()?, up, size);
    let (heat, max_displacement) = displacement_colors(before, after);
    let [after_image, displacement]: [Image; 2] = raster::render_paints(
        after,
        &camera,
        &[Paint::Uniform(MODEL_COLOR), Paint::PerVertex(&heat)],
        &Lighting::key(&camera),
    )
    .try_into()
    .ok()?;
    Some(Pictures {
        before: render(before, &camera, Paint::Uniform(MODEL_COLOR)),
        after: after_image,
        displacement,
        max_displacement,
    })
}

/// The names of the pictures in a job's directory (and in `crispen enhance --preview DIR`).
pub const BEFORE_PNG: &str = "before.png";
pub const AFTER_PNG: &str = "after.png";
pub const DISPLACEMENT_PNG: &str = "displacement.png";

/// Writes `image` to `path` as PNG, whole under a temporary name then renamed, readable
/// by others like the job's other files.
pub fn write_png(path: &Path, image: &Image) -> std::io::Result<()> {
    Ok(crispen_fsutil::write_atomic(path, &image.to_png())?)
}

impl Pictures {
    /// Writes the three PNGs into `dir` (each written whole under a temporary name, then
    /// renamed) and returns their paths.
    pub fn save(&self, dir: &Path) -> std::io::Result<Vec<PathBuf>> {
        [
            (BEFORE_PNG, &self.before),
            (AFTER_PNG, &self.after),
            (DISPLACEMENT_PNG, &self.displacement),
        ]
        .into_iter()
        .map(|(name, image)| {
            let path = dir.join(name);
            write_png(&path, image)?;
            Ok(path)
        })
        .collect()
    }
}
