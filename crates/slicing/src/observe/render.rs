//! The print as light: each visible line of its G-code ([`Print::layers`]) is a bead, a
//! tube of the line's width and the layer's height with an elliptic cross-section and
//! rounded ends, and each sample of the picture is the nearest crossing of its view ray
//! with a bead (an exact quadric, so each sample has its own normal and the layer lines
//! are ridges). The surface is white PLA taken as a Lambertian reflector lit by the
//! scene's lights ([`Lighting`]); what no bead covers is the cloth it stands on. The
//! result is luminance in cd/m², per pixel the mean of 2 × 2 samples, and the share of
//! each pixel the print covers.
//!
//! Orthographic: at 40 cm a print seen whole spans a few degrees to a few tens, and the
//! small and the large print are compared in one framing, so perspective is left out.
//! The picture is drawn in bands of rows, each band on a thread with its own small depth
//! buffer; beads are sorted front to back so a hidden one costs a depth comparison.

use super::pyramid::Plane;
use crate::preview::print::Print;
use crate::preview::{dot, sub};
use rayon::prelude::*;

/// An orthographic camera: the point at the picture's centre, its basis (unit vectors to
/// the picture's right and up, and into it), and its scale.
#[derive(Clone, Copy, Debug, PartialEq)]
pub(crate) struct Camera {
    pub(crate) centre: [f64; 3],
    pub(crate) right: [f64; 3],
    pub(crate) up: [f64; 3],
    pub(crate) forward: [f64; 3],
    pub(crate) px_per_mm: f64,
    pub(crate) width: usize,
    pub(crate) height: usize,
}

/// A distant light: the unit vector towards it and the illuminance it gives a surface
/// facing it, lux.
#[derive(Clone, Copy, Debug, PartialEq)]
pub(crate) struct Light {
    pub(crate) towards: [f64; 3],
    pub(crate) lux: f64,
}

/// The lights of a scene: distant lamps and a uniform sky (the room's light from above:
/// a surface facing up gets all of `sky_lux`, one facing down none).
#[derive(Clone, Debug, PartialEq)]
pub(crate) struct Lighting {
    pub(crate) lamps: Vec<Light>,
    pub(crate) sky_lux: f64,
}

impl Lighting {
    /// The luminance of a Lambertian surface of `albedo` with unit normal `n`, cd/m².
    pub(crate) fn luminance(&self, albedo: f64, n: [f64; 3]) -> f64 {
        let lamps: f64 = self
            .lamps
            .iter()
            .map(|l| l.lux * dot(n, l.towards).max(0.0))
            .sum();
        albedo / std::f64::consts::PI * (lamps + self.sky_lux * 0.5 * (1.0 + n[2]))
    }
}

/// What a picture of a print holds: luminance (cd/m²) and the share of each pixel the
/// print covers (0 to 1).
pub(crate) struct Rendered {
    pub(crate) luminance: Plane,
    pub(crate) coverage: Plane,
}

/// Samples per pixel along each side.
const SS: usize = 2;
/// Rows of pixels per band (one task for the threads).
const BAND_ROWS: usize = 16;

/// One bead, ready to intersect: its axis from `a` (world, mm) along the horizontal unit
/// vector `u` for `len`, its half width and half height, and where it is on the
/// supersampled screen.
struct Bead {
    a: [f64; 3],
    u: [f64; 2],
    len: f64,
    half_w: f64,
    half_h: f64,
    /// The nearest depth any of it can have: the sort key, and a quick reject.
    near: f64,
    /// Its axis's ends on the supersampled screen, and a radius that surely holds it.
    sa: [f64; 2],
    sb: [f64; 2],
    radius: f64,
    /// Supersampled rows it may cover, inclusive.
    rows: [i64; 2],
}

/// Draws `print` (placed on the bed, mm) as `camera` sees it under `lighting`: its beads
/// of `albedo`, on a background of `background` cd/m².
pub(crate) fn render(
    print: &Print,
    camera: &Camera,
    lighting: &Lighting,
    albedo: f64,
    background: f32,
) -> Rendered {
    let (w, h) = (camera.width * SS, camera.height * SS);
    let scale = camera.px_per_mm * SS as f64;
    let screen = |p: [f64; 3]| {
        let d = sub(p, camera.centre);
        [
            0.5 * w as f64 + dot(d, camera.right) * scale,
            0.5 * h as f64 - dot(d, camera.up) * scale,
        ]
    };
    let half_w = 0.5 * print.line_width_mm;
    let mut beads: Vec<Bead> = Vec::new();
    for (z_top, layer_h, lines) in print.layers() {
        let zc = z_top - 0.5 * layer_h;
        let half_h = 0.5 * layer_h;
        for line in lines {
            let a = [f64::from(line[0][0]), f64::from(line[0][1]), zc];
            let b = [f64::from(line[1][0]), f64::from(line[1][1]), zc];
            let (dx, dy) = (b[0] - a[0], b[1] - a[1]);
            let len = dx.hypot(dy);
            if !(len.is_finite() && len > 0.0) {
                continue;
            }
            let (sa, sb) = (screen(a), screen(b));
            let radius = half_w.max(half_h) * scale + 1.0;
            let top = (sa[1].min(sb[1]) - radius).floor().max(0.0);
            let bottom = (sa[1].max(sb[1]) + radius).ceil().min(h as f64 - 1.0);
            let left = sa[0].min(sb[0]) - radius;
            let right = sa[0].max(sb[0]) + radius;
            if !(top <= bottom && right >= 0.0 && left <= w as f64) {
                continue;
            }
            let near = (dot(sub(a, camera.centre), camera.forward))
                .min(dot(sub(b, camera.centre), camera.forward))
                - half_w.max(half_h);
            beads.push(Bead {
                a,
                u: [dx / len, dy / len],
                len,
                half_w,
                half_h,
                near,
                sa,
                sb,
                radius,
                rows: [top as i64, bottom as i64],
            });
        }
    }
    // Front to back: most samples are settled by the first beads that reach them.
    beads.sort_unstable_by(|x, y| x.near.total_cmp(&y.near));

    let bands = camera.height.div_ceil(BAND_ROWS);
    let mut per_band: Vec<Vec<u32>> = vec![Vec::new(); bands];
    let band_ss = (BAND_ROWS * SS) as i64;
    for (i, b) in beads.iter().enumerate() {
        for band in (b.rows[0] / band_ss)..=(b.rows[1] / band_ss) {
            if let Some(list) = per_band.get_mut(band as usize) {
                list.push(i as u32);
            }
        }
    }

    let background_lum = background;
    let mut luminance = vec![background_lum; camera.width * camera.height];
    let mut coverage = vec![0.0f32; camera.width * camera.height];
    luminance
        .par_chunks_mut(camera.width * BAND_ROWS)
        .zip(coverage.par_chunks_mut(camera.width * BAND_ROWS))
        .enumerate()
        .for_each(|(band, (lum, cov))| {
            let rows = lum.len() / camera.width;
            let y0 = band as i64 * band_ss;
            let y1 = y0 + (rows * SS) as i64;
            let mut depth = vec![f32::INFINITY; w * rows * SS];
            let mut normal = vec![[0.0f32; 3]; w * rows * SS];
            for &i in &per_band[band] {
                draw(
                    &beads[i as usize],
                    camera,
                    scale,
                    w,
                    h,
                    (y0, y1),
                    &mut depth,
                    &mut normal,
                );
            }
            // Shade each sample, then average the 2 × 2 samples of each pixel.
            let share = 1.0 / (SS * SS) as f32;
            for r in 0..rows {
                for x in 0..camera.width {
                    let (mut sum, mut hits) = (0.0f32, 0usize);
                    for sy in 0..SS {
                        for sx in 0..SS {
                            let s = (r * SS + sy) * w + x * SS + sx;
                            if depth[s].is_finite() {
                                let n = normal[s].map(f64::from);
                                sum += lighting.luminance(albedo, n) as f32;
                                hits += 1;
                            } else {
                                sum += background_lum;
                            }
                        }
                    }
                    lum[r * camera.width + x] = sum * share;
                    cov[r * camera.width + x] = hits as f32 * share;
                }
            }
        });
    Rendered {
        luminance: Plane {
            width: camera.width,
            height: camera.height,
            data: luminance,
        },
        coverage: Plane {
            width: camera.width,
            height: camera.height,
            data: coverage,
        },
    }
}

/// Intersects the view rays of the samples of rows `y0..y1` (supersampled) that `b` may
/// cover with it, keeping each sample's nearest hit in `depth` and `normal`.
#[allow(clippy::too_many_arguments)]
fn draw(
    b: &Bead,
    camera: &Camera,
    scale: f64,
    w: usize,
    h: usize,
    (y0, y1): (i64, i64),
    depth: &mut [f32],
    normal: &mut [[f32; 3]],
) {
    let f = camera.forward;
    let (u, n) = ([b.u[0], b.u[1], 0.0], [-b.u[1], b.u[0], 0.0]);
    let (a2, c2) = (b.half_w * b.half_w, b.half_h * b.half_h);
    // Along a ray, the cross-section coordinates (p across, q up, s along) change by these
    // per unit of depth.
    let (fp, fq, fs) = (dot(f, n), f[2], dot(f, u));
    let alpha_tube = fp * fp / a2 + fq * fq / c2;
    let alpha_cap = (f[0] * f[0] + f[1] * f[1]) / a2 + fq * fq / c2;
    let base = sub(camera.centre, b.a);
    let seg = [b.sb[0] - b.sa[0], b.sb[1] - b.sa[1]];
    for y in b.rows[0].max(y0)..=b.rows[1].min(y1 - 1) {
        let py = y as f64 + 0.5;
        // The part of the axis within `radius` of this row, widened by the radius.
        let (t0, t1) = if seg[1].abs() > 1e-9 {
            let ta = (py - b.radius - b.sa[1]) / seg[1];
            let tb = (py + b.radius - b.sa[1]) / seg[1];
            (ta.min(tb).max(0.0), ta.max(tb).min(1.0))
        } else if (py - b.sa[1]).abs() <= b.radius {
            (0.0, 1.0)
        } else {
            continue;
        };
        if t0 > t1 {
            continue;
        }
        let xa = b.sa[0] + t0 * seg[0];
        let xb = b.sa[0] + t1 * seg[0];
        let x_lo = (xa.min(xb) - b.radius).floor().max(0.0) as usize;
        let x_hi = ((xa.max(xb) + b.radius).ceil() as i64).min(w as i64 - 1);
        if x_hi < x_lo as i64 {
            continue;
        }
        let sy = (0.5 * h as f64 - py) / scale;
        let row = ((y - y0) as usize) * w;
        for x in x_lo..=x_hi as usize {
            let s = row + x;
            if f64::from(depth[s]) <= b.near {
                continue;
            }
            let sx = (x as f64 + 0.5 - 0.5 * w as f64) / scale;
            // The ray's point on the picture plane, relative to the bead's start.
            let e: [f64; 3] =
                std::array::from_fn(|k| base[k] + sx * camera.right[k] + sy * camera.up[k]);
            let (p0, q0, s0) = (dot(e, n), e[2], dot(e, u));
            // The elliptic cylinder (p/a)² + (q/c)² = 1: α t² + 2 β t + γ = 0.
            let beta = p0 * fp / a2 + q0 * fq / c2;
            let gamma = p0 * p0 / a2 + q0 * q0 / c2 - 1.0;
            let disc = beta * beta - alpha_tube * gamma;
            // Missing the cylinder is missing the bead: its rounded ends lie inside it.
            if disc < 0.0 {
                continue;
            }
            let t = (-beta - disc.sqrt()) / alpha_tube;
            let along = s0 + t * fs;
            let hit = if (0.0..=b.len).contains(&along) {
                let (p, q) = (p0 + t * fp, q0 + t * fq);
                Some((t, [p / a2 * n[0], p / a2 * n[1], q / c2]))
            } else {
                // Past an end: the half-ellipsoid that rounds that end.
                let end = if along < 0.0 { 0.0 } else { b.len };
                let c = [e[0] - end * u[0], e[1] - end * u[1], e[2]];
                let beta = (c[0] * f[0] + c[1] * f[1]) / a2 + c[2] * fq / c2;
                let gamma = (c[0] * c[0] + c[1] * c[1]) / a2 + c[2] * c[2] / c2 - 1.0;
                let disc = beta * beta - alpha_cap * gamma;
                (disc >= 0.0).then(|| {
                    let t = (-beta - disc.sqrt()) / alpha_cap;
                    let p: [f64; 3] = std::array::from_fn(|k| c[k] + t * f[k]);
                    (t, [p[0] / a2, p[1] / a2, p[2] / c2])
                })
            };
            if let Some((t, nrm)) = hit {
                if (t as f32) < depth[s] {
                    depth[s] = t as f32;
                    let len = dot(nrm, nrm).sqrt();
                    normal[s] = nrm.map(|c| (c / len) as f32);
                }
            }
        }
    }
}
