//! The rasteriser: triangles into a supersampled z-buffer of (face, barycentric) samples,
//! then one shading pass over the visible samples only (deferred, so overdraw costs a
//! depth test, not a lighting computation), then a 2×2 box filter down to the picture.
//! One rasterisation serves several paints of the same geometry (the after picture and
//! its heat map). Both passes split the picture into bands of rows across threads.

use super::{normalize, Camera, Image, Lighting, Paint};
use crispen_geometry::mesh::Mesh;
use rayon::prelude::*;

/// Samples per pixel along each axis.
pub(super) const SUPERSAMPLE: usize = 2;

/// Picture rows per band handed to a thread.
pub(super) const BAND_ROWS: usize = 32;

/// cos 30°: the largest bend between a face and its vertex normals that is shaded smooth.
const CREASE_COS: f32 = 0.866;

/// The visible surface at one sample: which face, and where on it.
#[derive(Clone, Copy)]
struct Sample {
    depth: f32,
    face: u32,
    /// Barycentric weights of the face's second and third corners.
    b1: f32,
    b2: f32,
}

const EMPTY: Sample = Sample {
    depth: f32::INFINITY,
    face: u32::MAX,
    b1: 0.0,
    b2: 0.0,
};

/// Renders `mesh` as `camera` sees it, painted with `paint`, under the pictures' key light
/// ([`Lighting::key`]).
pub fn render(mesh: &Mesh, camera: &Camera, paint: Paint) -> Image {
    render_lit(mesh, camera, paint, &Lighting::key(camera))
}

/// [`render`] under another light.
pub fn render_lit(mesh: &Mesh, camera: &Camera, paint: Paint, lighting: &Lighting) -> Image {
    render_paints(mesh, camera, &[paint], lighting).remove(0)
}

/// Renders `mesh` once per paint, rasterising it only once. Faces that index outside the
/// vertices are skipped (a mesh from the readers never has them).
pub(crate) fn render_paints(
    mesh: &Mesh,
    camera: &Camera,
    paints: &[Paint],
    lighting: &Lighting,
) -> Vec<Image> {
    let (w, h) = (
        camera.width as usize * SUPERSAMPLE,
        camera.height as usize * SUPERSAMPLE,
    );
    let ss = SUPERSAMPLE as f64;
    let projected: Vec<[f64; 3]> = mesh
        .vertices
        .iter()
        .map(|&v| {
            let [x, y, z] = camera.project(v);
            [x * ss, y * ss, z]
        })
        .collect();
    let faces: Vec<(u32, [[f64; 3]; 3])> = mesh
        .faces
        .iter()
        .enumerate()
        .filter(|(_, f)| f.iter().all(|&i| (i as usize) < projected.len()))
        .map(|(index, f)| (index as u32, f.map(|i| projected[i as usize])))
        .collect();

    let mut samples = vec![EMPTY; w * h];
    let band_samples = BAND_ROWS * SUPERSAMPLE * w;
    samples
        .par_chunks_mut(band_samples)
        .enumerate()
        .for_each(|(band, chunk)| {
            let y0 = band * BAND_ROWS * SUPERSAMPLE;
            let y1 = y0 + chunk.len() / w;
            for &(index, [a, b, c]) in &faces {
                rasterize_triangle(index, a, b, c, w, (y0, y1), chunk);
            }
        });

    let normals = Normals::of(mesh);
    paints
        .iter()
        .map(|&paint| shade_and_filter(mesh, camera, paint, lighting, &normals, &samples))
        .collect()
}

/// Draws one triangle into the rows `y0..y1` of the sample buffer, which `band` holds.
fn rasterize_triangle(
    face: u32,
    a: [f64; 3],
    b: [f64; 3],
    c: [f64; 3],
    w: usize,
    (y0, y1): (usize, usize),
    band: &mut [Sample],
) {
    let min_y = a[1].min(b[1]).min(c[1]).floor().max(y0 as f64);
    let max_y = a[1].max(b[1]).max(c[1]).ceil().min(y1 as f64);
    if !(min_y < max_y) {
        return;
    }
    let area = edge(a, b, c);
    if !area.is_finite() || area.abs() < 1e-12 {
        return;
    }
    let min_x = a[0].min(b[0]).min(c[0]).floor().max(0.0);
    let max_x = a[0].max(b[0]).max(c[0]).ceil().min(w as f64);
    if !(min_x < max_x) {
        return;
    }
    let inv_area = 1.0 / area;
    for y in min_y as usize..max_y as usize {
        let py = y as f64 + 0.5;
        let row = &mut band[(y - y0) * w..][..w];
        for x in min_x as usize..max_x as usize {
            let p = [x as f64 + 0.5, py, 0.0];
            // Normalised by the signed area, the weights are positive inside whichever way
            // the triangle winds (both sides of a surface are drawn).
            let w0 = edge(b, c, p) * inv_area;
            let w1 = edge(c, a, p) * inv_area;
            let w2 = edge(a, b, p) * inv_area;
            if w0 < 0.0 || w1 < 0.0 || w2 < 0.0 {
                continue;
            }
            let depth = (w0 * a[2] + w1 * b[2] + w2 * c[2]) as f32;
            let s = &mut row[x];
            if depth < s.depth {
                *s = Sample {
                    depth,
                    face,
                    b1: w1 as f32,
                    b2: w2 as f32,
                };
            }
        }
    }
}

/// Twice the signed area of the screen triangle (a, b, p).
fn edge(a: [f64; 3], b: [f64; 3], p: [f64; 3]) -> f64 {
    (b[0] - a[0]) * (p[1] - a[1]) - (b[1] - a[1]) * (p[0] - a[0])
}

/// Unit normals per face and per vertex.
struct Normals {
    face: Vec<[f32; 3]>,
    /// Weighted by the angle of each face at the vertex, so they do not depend on how the
    /// surface happens to be split into triangles; zero for a vertex on no proper face.
    vertex: Vec<[f32; 3]>,
}

impl Normals {
    fn of(mesh: &Mesh) -> Normals {
        let v = &mesh.vertices;
        let mut sum = vec![[0.0f64; 3]; v.len()];
        let mut face = Vec::with_capacity(mesh.faces.len());
        for f in &mesh.faces {
            if f.iter().any(|&i| i as usize >= v.len()) {
                face.push([0.0; 3]);
                continue;
            }
            let n = normalize(crispen_geometry::mesh::triangle_normal(v, *f));
            face.push(n.map(|c| c as f32));
            for corner in 0..3 {
                let [a, b, c] = [0, 1, 2].map(|k| v[f[(corner + k) % 3] as usize]);
                let e1 = normalize(std::array::from_fn(|k| b[k] - a[k]));
                let e2 = normalize(std::array::from_fn(|k| c[k] - a[k]));
                let angle = (e1[0] * e2[0] + e1[1] * e2[1] + e1[2] * e2[2])
                    .clamp(-1.0, 1.0)
                    .acos();
                let i = f[corner] as usize;
                for k in 0..3 {
                    sum[i][k] += angle * n[k];
                }
            }
        }
        let vertex = sum
            .into_iter()
            .map(|n| normalize(n).map(|c| c as f32))
            .collect();
        Normals { face, vertex }
    }
}

fn shade_and_filter(
    mesh: &Mesh,
    camera: &Camera,
    paint: Paint,
    lighting: &Lighting,
    normals: &Normals,
    samples: &[Sample],
) -> Image {
    // A heat map keeps more ambient light and no highlight: its colours are the message,
    // and white would read as a value on the ramp.
    let lighting = match paint {
        Paint::Uniform(_) => *lighting,
        Paint::PerVertex(_) => Lighting {
            ambient: 0.5,
            shininess: 0.0,
            ..*lighting
        },
    };
    let shader = Shader::new(camera, &lighting);

    let shade = |s: &Sample| -> [f32; 3] {
        let f = mesh.faces[s.face as usize].map(|i| i as usize);
        let weights = [1.0 - s.b1 - s.b2, s.b1, s.b2];
        // Smooth across gentle bends, sharp at creases: a corner whose vertex normal is
        // more than 30° from the face's own takes the face's (a box stays a box).
        let face_normal = normals.face[s.face as usize];
        let mut n = [0.0f32; 3];
        for (&corner, wgt) in f.iter().zip(weights) {
            let vn = normals.vertex[corner];
            let corner_normal = if dot3(vn, face_normal) > CREASE_COS {
                vn
            } else {
                face_normal
            };
            for k in 0..3 {
                n[k] += wgt * corner_normal[k];
            }
        }
        let len = dot3(n, n).sqrt();
        if len > 0.0 {
            n = n.map(|c| c / len);
        }
        // Two-sided: the inside of a hole (the bunny's base) is lit like the outside.
        if dot3(n, shader.to_viewer) < 0.0 {
            n = n.map(|c| -c);
        }
        let base = match paint {
            Paint::Uniform(color) => color,
            Paint::PerVertex(colors) => {
                let mut c = [0.0f32; 3];
                for (&corner, wgt) in f.iter().zip(weights) {
                    let v = colors.get(corner).copied().unwrap_or([0.5; 3]);
                    for k in 0..3 {
                        c[k] += wgt * v[k];
                    }
                }
                c
            }
        };
        shader.shade(base, n)
    };
    resolve(camera, |i| {
        let s = &samples[i];
        (s.face != u32::MAX).then(|| shade(s))
    })
}

/// Lighting as the shading pass applies it: unit vectors in `f32`, and the half vector
/// of the highlight.
pub(super) struct Shader {
    light: [f32; 3],
    half: [f32; 3],
    pub(super) to_viewer: [f32; 3],
    ambient: f32,
    shininess: f32,
}

impl Shader {
    pub(super) fn new(camera: &Camera, lighting: &Lighting) -> Shader {
        let to_viewer = camera.forward.map(|c| -c);
        let light = normalize(lighting.direction);
        let half = normalize(std::array::from_fn(|k| light[k] + to_viewer[k]));
        Shader {
            light: f32x3(light),
            half: f32x3(half),
            to_viewer: f32x3(to_viewer),
            ambient: lighting.ambient,
            shininess: lighting.shininess,
        }
    }

    /// `base` lit on a surface of unit normal `n` (facing the viewer).
    pub(super) fn shade(&self, base: [f32; 3], n: [f32; 3]) -> [f32; 3] {
        let diffuse = dot3(n, self.light).max(0.0);
        let specular = if self.shininess > 0.0 {
            self.shininess * dot3(n, self.half).max(0.0).powi(32)
        } else {
            0.0
        };
        base.map(|c| {
            (c * (self.ambient + (1.0 - self.ambient) * diffuse) + specular).clamp(0.0, 1.0)
        })
    }
}

/// The picture from a supersampled one: `color(i)` is the colour of sample `i` (row-major,
/// [`SUPERSAMPLE`] × the camera's size), None where nothing was drawn; each pixel is the
/// mean of its covered samples, its alpha the share covered. In bands across threads.
pub(super) fn resolve(camera: &Camera, color: impl Fn(usize) -> Option<[f32; 3]> + Sync) -> Image {
    let (w, h) = (camera.width as usize, camera.height as usize);
    let sw = w * SUPERSAMPLE;
    let mut rgba = vec![0u8; 4 * w * h];
    rgba.par_chunks_mut((4 * w * BAND_ROWS).max(1))
        .enumerate()
        .for_each(|(band, rows)| {
            for (dy, row) in rows.chunks_mut(4 * w).enumerate() {
                let y = band * BAND_ROWS + dy;
                for (x, px) in row.chunks_mut(4).enumerate() {
                    let mut sum = [0.0f32; 3];
                    let mut covered = 0u32;
                    for sy in 0..SUPERSAMPLE {
                        let line = (y * SUPERSAMPLE + sy) * sw;
                        for sx in x * SUPERSAMPLE..(x + 1) * SUPERSAMPLE {
                            if let Some(c) = color(line + sx) {
                                for k in 0..3 {
                                    sum[k] += c[k];
                                }
                                covered += 1;
                            }
                        }
                    }
                    if covered > 0 {
                        for k in 0..3 {
                            px[k] = (255.0 * sum[k] / covered as f32).round() as u8;
                        }
                        px[3] = (255 * covered / (SUPERSAMPLE * SUPERSAMPLE) as u32) as u8;
                    }
                }
            }
        });
    Image {
        width: camera.width,
        height: camera.height,
        rgba,
    }
}

pub(super) fn f32x3(v: [f64; 3]) -> [f32; 3] {
    v.map(|c| c as f32)
}

pub(super) fn dot3(a: [f32; 3], b: [f32; 3]) -> f32 {
    a[0] * b[0] + a[1] * b[1] + a[2] * b[2]
}
