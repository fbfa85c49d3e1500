//! The rasteriser: triangles into a supersampled z-buffer of (face, barycentric) samples,
//! then one shading pass over the visible samples only (deferred, so overdraw costs a
//! depth test, not a lighting computation), then a 2×2 box filter down to the picture.

use super::{normalize, Camera, Image, Paint};
use crate::mesh::Mesh;

/// Samples per pixel along each axis.
const SUPERSAMPLE: u32 = 2;

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

/// Renders `mesh` as `camera` sees it. Faces that index outside the vertices are skipped
/// (a mesh from the readers never has them).
pub fn render(mesh: &Mesh, camera: &Camera, paint: Paint) -> Image {
    let (w, h) = (camera.width * SUPERSAMPLE, camera.height * SUPERSAMPLE);
    let mut samples = vec![EMPTY; w as usize * h as usize];
    let ss = f64::from(SUPERSAMPLE);
    let projected: Vec<[f64; 3]> = mesh
        .vertices
        .iter()
        .map(|&v| {
            let [x, y, z] = camera.project(v);
            [x * ss, y * ss, z]
        })
        .collect();
    let n = projected.len();
    for (index, face) in mesh.faces.iter().enumerate() {
        if face.iter().any(|&i| i as usize >= n) {
            continue;
        }
        let [a, b, c] = face.map(|i| projected[i as usize]);
        rasterize_triangle(index as u32, a, b, c, w, h, &mut samples);
    }
    let normals = vertex_normals(mesh);
    shade_and_filter(mesh, camera, paint, &normals, &samples)
}

#[allow(clippy::too_many_arguments)]
fn rasterize_triangle(
    face: u32,
    a: [f64; 3],
    b: [f64; 3],
    c: [f64; 3],
    w: u32,
    h: u32,
    samples: &mut [Sample],
) {
    let area = edge(a, b, c);
    if !area.is_finite() || area.abs() < 1e-12 {
        return;
    }
    let min_x = a[0].min(b[0]).min(c[0]).floor().max(0.0);
    let max_x = a[0].max(b[0]).max(c[0]).ceil().min(f64::from(w));
    let min_y = a[1].min(b[1]).min(c[1]).floor().max(0.0);
    let max_y = a[1].max(b[1]).max(c[1]).ceil().min(f64::from(h));
    if min_x >= max_x || min_y >= max_y {
        return;
    }
    let inv_area = 1.0 / area;
    for y in min_y as u32..max_y as u32 {
        let py = f64::from(y) + 0.5;
        for x in min_x as u32..max_x as u32 {
            let p = [f64::from(x) + 0.5, py, 0.0];
            // Normalised by the signed area, the weights are positive inside whichever way
            // the triangle winds (both sides of a surface are drawn).
            let w0 = edge(b, c, p) * inv_area;
            let w1 = edge(c, a, p) * inv_area;
            let w2 = edge(a, b, p) * inv_area;
            if w0 < 0.0 || w1 < 0.0 || w2 < 0.0 {
                continue;
            }
            let depth = (w0 * a[2] + w1 * b[2] + w2 * c[2]) as f32;
            let s = &mut samples[y as usize * w as usize + x as usize];
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

/// Vertex normals weighted by the angle of each face at the vertex (so they do not depend
/// on how the surface happens to be split into triangles); unit length, or zero for a
/// vertex on no proper face.
fn vertex_normals(mesh: &Mesh) -> Vec<[f32; 3]> {
    let v = &mesh.vertices;
    let mut sum = vec![[0.0f64; 3]; v.len()];
    for f in &mesh.faces {
        if f.iter().any(|&i| i as usize >= v.len()) {
            continue;
        }
        let n = normalize(crate::mesh::triangle_normal(v, *f));
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
    sum.into_iter()
        .map(|n| normalize(n).map(|c| c as f32))
        .collect()
}

fn shade_and_filter(
    mesh: &Mesh,
    camera: &Camera,
    paint: Paint,
    normals: &[[f32; 3]],
    samples: &[Sample],
) -> Image {
    let to_viewer = camera.forward.map(|c| -c);
    // A key light above and to the left of the viewer; the half vector for its highlight.
    let light = normalize(std::array::from_fn(|k| {
        0.8 * to_viewer[k] + 0.55 * camera.up[k] - 0.35 * camera.right[k]
    }));
    let half = normalize(std::array::from_fn(|k| light[k] + to_viewer[k]));
    let (light, half, to_viewer) = (f32x3(light), f32x3(half), f32x3(to_viewer));

    let shade = |s: &Sample| -> [f32; 3] {
        let face = mesh.faces[s.face as usize];
        let f = face.map(|i| i as usize);
        let b0 = 1.0 - s.b1 - s.b2;
        let weights = [b0, s.b1, s.b2];
        // Smooth across gentle bends, sharp at creases: a corner whose vertex normal is
        // more than 30° from the face's own takes the face's (a box stays a box).
        let face_normal = f32x3(normalize(crate::mesh::triangle_normal(
            &mesh.vertices,
            face,
        )));
        let mut n = [0.0f32; 3];
        for (corner, wgt) in f.iter().zip(weights) {
            let vn = normals[*corner];
            let corner_normal = if dot3(vn, face_normal) > CREASE_COS {
                vn
            } else {
                face_normal
            };
            for k in 0..3 {
                n[k] += wgt * corner_normal[k];
            }
        }
        let len = (n[0] * n[0] + n[1] * n[1] + n[2] * n[2]).sqrt();
        if len > 0.0 {
            n = n.map(|c| c / len);
        }
        // Two-sided: the inside of a hole (the bunny's base) is lit like the outside.
        if dot3(n, to_viewer) < 0.0 {
            n = n.map(|c| -c);
        }
        let diffuse = dot3(n, light).max(0.0);
        // No highlight on a heat map: white would read as a value on the ramp.
        let specular = match paint {
            Paint::Uniform(_) => dot3(n, half).max(0.0).powi(32),
            Paint::PerVertex(_) => 0.0,
        };
        let base = match paint {
            Paint::Uniform(color) => color,
            Paint::PerVertex(colors) => {
                let mut c = [0.0f32; 3];
                for (corner, wgt) in f.iter().zip(weights) {
                    let v = colors.get(*corner).copied().unwrap_or([0.5; 3]);
                    for k in 0..3 {
                        c[k] += wgt * v[k];
                    }
                }
                c
            }
        };
        // A heat map keeps more ambient light: its colours are the message.
        let ambient = match paint {
            Paint::Uniform(_) => 0.3,
            Paint::PerVertex(_) => 0.5,
        };
        base.map(|c| (c * (ambient + (1.0 - ambient) * diffuse) + 0.18 * specular).clamp(0.0, 1.0))
    };

    let (w, h) = (camera.width, camera.height);
    let sw = (w * SUPERSAMPLE) as usize;
    let mut rgba = vec![0u8; 4 * w as usize * h as usize];
    for y in 0..h as usize {
        for x in 0..w as usize {
            let mut color = [0.0f32; 3];
            let mut covered = 0u32;
            for sy in 0..SUPERSAMPLE as usize {
                for sx in 0..SUPERSAMPLE as usize {
                    let s = &samples
                        [(y * SUPERSAMPLE as usize + sy) * sw + x * SUPERSAMPLE as usize + sx];
                    if s.face != u32::MAX {
                        let c = shade(s);
                        for k in 0..3 {
                            color[k] += c[k];
                        }
                        covered += 1;
                    }
                }
            }
            if covered > 0 {
                let px = &mut rgba[4 * (y * w as usize + x)..][..4];
                for k in 0..3 {
                    px[k] = (255.0 * color[k] / covered as f32).round() as u8;
                }
                px[3] = (255 * covered / (SUPERSAMPLE * SUPERSAMPLE)) as u8;
            }
        }
    }
    Image {
        width: w,
        height: h,
        rgba,
    }
}

fn f32x3(v: [f64; 3]) -> [f32; 3] {
    v.map(|c| c as f32)
}

fn dot3(a: [f32; 3], b: [f32; 3]) -> f32 {
    a[0] * b[0] + a[1] * b[1] + a[2] * b[2]
}
