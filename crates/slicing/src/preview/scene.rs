//! What a render takes and gives: the image, the camera, the paint of a surface, and the
//! vector arithmetic they share; apart from the root so the rasteriser, the thumbnails and
//! the walls use them without depending on the pictures made from them.

use crispen_geometry::mesh::place::UpAxis;

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
    pub(crate) fn three_quarter(bounds: ([f64; 3], [f64; 3]), up: UpAxis, size: u32) -> Camera {
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
    pub(crate) fn project(&self, p: [f64; 3]) -> [f64; 3] {
        let d = sub(p, self.center);
        [
            0.5 * f64::from(self.width) + dot(d, self.right) * self.scale,
            0.5 * f64::from(self.height) - dot(d, self.up) * self.scale,
            dot(d, self.forward),
        ]
    }
}

/// Where the light comes from, and how much of it reaches every surface.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Lighting {
    /// Towards the light (normalised where it is used).
    pub direction: [f64; 3],
    /// The share of the light every surface gets, whichever way it faces.
    pub ambient: f32,
    /// Strength of the highlight (0: none).
    pub shininess: f32,
}

impl Lighting {
    /// The mesh pictures' light: a key light above and to the left of the viewer, and a
    /// fair ambient share, so every side of the model reads.
    pub fn key(camera: &Camera) -> Lighting {
        let to_viewer = camera.forward.map(|c| -c);
        Lighting {
            direction: normalize(std::array::from_fn(|k| {
                0.8 * to_viewer[k] + 0.55 * camera.up[k] - 0.35 * camera.right[k]
            })),
            ambient: 0.3,
            shininess: 0.18,
        }
    }

    /// A grazing light, as an inspector holds a lamp to a surface: `elevation_deg` above
    /// the horizon (the plane normal to `world_up`), from the viewer's left and 60° round
    /// from the viewer, with little ambient. Flat light hides relief of a tenth of a
    /// millimetre; a low one turns each layer line and each moved wall into light and
    /// shadow.
    pub fn grazing(camera: &Camera, world_up: [f64; 3], elevation_deg: f64) -> Lighting {
        let up = normalize(world_up);
        let flat = |v: [f64; 3]| normalize(sub(v, up.map(|c| c * dot(v, up))));
        let (to_viewer, right) = (flat(camera.forward.map(|c| -c)), flat(camera.right));
        let azimuth = 60f64.to_radians();
        let horizontal = normalize(std::array::from_fn(|k| {
            azimuth.cos() * to_viewer[k] - azimuth.sin() * right[k]
        }));
        let el = elevation_deg.to_radians();
        Lighting {
            direction: normalize(std::array::from_fn(|k| {
                el.cos() * horizontal[k] + el.sin() * up[k]
            })),
            ambient: 0.18,
            shininess: 0.08,
        }
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

pub fn sub(a: [f64; 3], b: [f64; 3]) -> [f64; 3] {
    [a[0] - b[0], a[1] - b[1], a[2] - b[2]]
}

pub(crate) fn dot(a: [f64; 3], b: [f64; 3]) -> f64 {
    a[0] * b[0] + a[1] * b[1] + a[2] * b[2]
}

pub(crate) fn cross(a: [f64; 3], b: [f64; 3]) -> [f64; 3] {
    [
        a[1] * b[2] - a[2] * b[1],
        a[2] * b[0] - a[0] * b[2],
        a[0] * b[1] - a[1] * b[0],
    ]
}

pub fn norm(a: [f64; 3]) -> f64 {
    dot(a, a).sqrt()
}

pub fn normalize(a: [f64; 3]) -> [f64; 3] {
    let n = norm(a);
    if n > 0.0 {
        a.map(|c| c / n)
    } else {
        a
    }
}
