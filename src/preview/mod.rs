//! Pictures of a job's mesh, made on the CPU (no GPU, no display): the model before and
//! after the enhancement from one camera, a heat map of how far each point of the surface
//! moved, the G-code thumbnails other farm tools show ([`thumbnail`]), and the outer walls
//! of a few layers, plain and enhanced ([`walls`]).
//!
//! A small z-buffer rasteriser is all this needs: orthographic projection, per-pixel
//! interpolated normals (the enhancement is a change of shading, so flat or per-vertex
//! lighting would hide what it did), 2×2 supersampling for smooth edges, and a transparent
//! background so the pictures sit on any page.

mod raster;
pub mod thumbnail;
pub mod walls;

use crate::mesh::place::UpAxis;
use crate::mesh::Mesh;
use std::path::{Path, PathBuf};

pub use raster::render;

/// An 8-bit RGBA picture, rows top to bottom.
#[derive(Clone, Debug, PartialEq)]
pub struct Image {
    pub width: u32,
    pub height: u32,
    pub rgba: Vec<u8>,
}

impl Image {
    pub fn pixel(&self, x: u32, y: u32) -> [u8; 4] {
        let i = 4 * (y as usize * self.width as usize + x as usize);
        self.rgba[i..i + 4].try_into().unwrap()
    }

    /// The picture as a PNG file's bytes.
    pub fn to_png(&self) -> Vec<u8> {
        let mut out = Vec::new();
        let mut encoder = png::Encoder::new(&mut out, self.width, self.height);
        encoder.set_color(png::ColorType::Rgba);
        encoder.set_depth(png::BitDepth::Eight);
        encoder.set_compression(png::Compression::Fast);
        // Encoding into memory cannot fail for a buffer of the right size.
        let mut writer = encoder.write_header().expect("PNG header");
        writer.write_image_data(&self.rgba).expect("PNG data");
        writer.finish().expect("PNG end");
        out
    }
}

/// An orthographic camera: where it looks from, and how model units map to pixels.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Camera {
    /// The point at the centre of the picture.
    pub center: [f64; 3],
    /// Unit vectors: into the picture, to its right, and up.
    pub forward: [f64; 3],
    pub right: [f64; 3],
    pub up: [f64; 3],
    /// Pixels per model unit.
    pub scale: f64,
    pub width: u32,
    pub height: u32,
}

impl Camera {
    /// Looks at `bounds` from `eye_direction` (from the model towards the viewer), with
    /// `up` as close to the picture's up as it can be (any other axis when looking along
    /// it), fitting the bounding sphere of
    /// `bounds` into the picture with a small margin, whatever the direction.
    pub fn looking_at(
        bounds: ([f64; 3], [f64; 3]),
        eye_direction: [f64; 3],
        up: [f64; 3],
        width: u32,
        height: u32,
    ) -> Camera {
        let (lo, hi) = bounds;
        let center = std::array::from_fn(|k| 0.5 * (lo[k] + hi[k]));
        let radius = 0.5 * norm(sub(hi, lo));
        let forward = normalize(eye_direction.map(|c| -c));
        // Looking straight along `up` leaves no picture-up: take the nearest axis instead.
        let mut right = cross(forward, up);
        if norm(right) < 1e-9 {
            let k = (0..3)
                .min_by(|&a, &b| forward[a].abs().total_cmp(&forward[b].abs()))
                .unwrap_or(0);
            right = cross(
                forward,
                std::array::from_fn(|i| f64::from(u8::from(i == k))),
            );
        }
        let right = normalize(right);
        let up = cross(right, forward);
        let scale = if radius > 0.0 {
            0.92 * 0.5 * f64::from(width.min(height)) / radius
        } else {
            1.0
        };
        Camera {
            center,
            forward,
            right,
            up,
            scale,
            width,
            height,
        }
    }

    /// The view farm tools and slicers show of a part on the bed: from the front, 30° to
    /// the right and 25° above, with the model's `up` axis up.
    pub fn three_quarter(bounds: ([f64; 3], [f64; 3]), up: UpAxis, size: u32) -> Camera {
        let (az, el) = (30f64.to_radians(), 25f64.to_radians());
        let (side, front, height) = (az.sin() * el.cos(), az.cos() * el.cos(), el.sin());
        // Z up: the front of the bed is −Y. Y up (OBJ files): the front is +Z.
        let (eye, up_vector) = match up {
            UpAxis::Z => ([side, -front, height], [0.0, 0.0, 1.0]),
            UpAxis::Y => ([side, height, front], [0.0, 1.0, 0.0]),
        };
        Camera::looking_at(bounds, eye, up_vector, size, size)
    }

    /// Where `p` lands: picture x and y in pixels, and depth (smaller is nearer).
    fn project(&self, p: [f64; 3]) -> [f64; 3] {
        let d = sub(p, self.center);
        [
            0.5 * f64::from(self.width) + dot(d, self.right) * self.scale,
            0.5 * f64::from(self.height) - dot(d, self.up) * self.scale,
            dot(d, self.forward),
        ]
    }
}

/// How a surface is coloured: one colour, or a colour per vertex.
#[derive(Clone, Copy, Debug)]
pub enum Paint<'a> {
    Uniform([f32; 3]),
    PerVertex(&'a [[f32; 3]]),
}

/// The colour of the model in the before and after pictures.
pub const MODEL_COLOR: [f32; 3] = [0.72, 0.76, 0.82];

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
    Ok(crate::fsutil::write_atomic(path, &image.to_png())?)
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

fn sub(a: [f64; 3], b: [f64; 3]) -> [f64; 3] {
    [a[0] - b[0], a[1] - b[1], a[2] - b[2]]
}

fn dot(a: [f64; 3], b: [f64; 3]) -> f64 {
    a[0] * b[0] + a[1] * b[1] + a[2] * b[2]
}

fn cross(a: [f64; 3], b: [f64; 3]) -> [f64; 3] {
    [
        a[1] * b[2] - a[2] * b[1],
        a[2] * b[0] - a[0] * b[2],
        a[0] * b[1] - a[1] * b[0],
    ]
}

fn norm(a: [f64; 3]) -> f64 {
    dot(a, a).sqrt()
}

fn normalize(a: [f64; 3]) -> [f64; 3] {
    let n = norm(a);
    if n > 0.0 {
        a.map(|c| c / n)
    } else {
        a
    }
}
