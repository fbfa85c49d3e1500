//! The print as the printer will lay it, drawn from the G-code crispen sends rather than
//! from the mesh: the lines of filament that can be seen from outside, each drawn as a
//! bead (a tube of the line's width and the layer's height, with a rounded cross-section),
//! under a low, grazing light, so the layer lines and a wall the enhancement moved by a
//! tenth of a millimetre show as light and shadow. [`preview_picture`] puts the model,
//! the plain print and the enhanced one side by side from one camera, and below them the
//! prints at the size they will be printed.
//!
//! The G-code is followed as the walls' measure follows it
//! ([`crate::slice::walls::extruding_moves`]: Marlin's reading and motion), and a file that
//! marks no kinds of line is drawn whole. Every input is bounded: moves beyond the walls'
//! [`COORD_LIMIT_MM`] or not finite are dropped, and a print of more than
//! [`MAX_SEGMENTS`] visible lines is sampled (every k-th layer, drawn k layers tall so the
//! surface stays closed) rather than refused.
//!
//! Each bead is ray-cast rather than tessellated: per sample, the nearest crossing of the
//! view ray with the bead's elliptic cylinder (or the ellipsoids that round its ends),
//! which gives an exact normal per pixel for the price of a quadratic; beads are drawn
//! front to back, so a hidden one costs a depth comparison.

use super::raster::{self, Shader, SUPERSAMPLE};
use super::scene::dot;
use super::{normalize, sub, Camera, Image, Lighting, Paint, MODEL_COLOR};
use crate::mesh::place::UpAxis;
use crate::mesh::Mesh;
use crate::slice::walls::COORD_LIMIT_MM;
use rayon::prelude::*;
use std::collections::BTreeMap;
use std::io::BufRead;
use std::path::{Path, PathBuf};

/// The name of the picture in a job's directory (and in `crispen slice --preview DIR`).
pub const PREVIEW_PNG: &str = "preview.png";

/// At most this many lines are kept from one file (a 20 mm bunny has about 10^5; 100 mm
/// of it about 2 million): beyond, the print is sampled by layers.
pub const MAX_SEGMENTS: usize = 1_500_000;

/// Side of each panel of the preview, pixels.
pub const PANEL_PX: u32 = 400;
/// The scale of the strip at the size printed: 4 px per mm, about 100 dpi, a screen's.
pub const ACTUAL_PX_PER_MM: f64 = 4.0;
/// The light's height above the horizon: low enough for a layer's ridge to cast its
/// shading, high enough to light the top surfaces.
const LIGHT_ELEVATION_DEG: f64 = 20.0;
const GAP_PX: u32 = 8;

/// Bounds of a bead's cross-section, mm: a line narrower or wider than a nozzle could
/// draw, or a layer step outside these (a Z hop, a first layer at Z 0) is not believed.
const LINE_WIDTH_MM: std::ops::RangeInclusive<f64> = 0.1..=2.0;
const MIN_LAYER_MM: f64 = 0.04;
const MAX_LAYER_MM: f64 = 1.0;

/// Whether a `;TYPE:` comment starts lines that can be seen from outside the print. The
/// outer walls are most of what shows (PrusaSlicer `External perimeter`, `Overhang
/// perimeter`; CuraEngine `WALL-OUTER`); the inner walls show on every slope, where each
/// layer's step lays bare the walls inside it, and around a top surface; the top and
/// bottom skins are the top and the bottom (PrusaSlicer `Top`/`Bottom solid infill`,
/// `Ironing`, `Gap fill` between walls; CuraEngine `SKIN`). Sparse and internal solid
/// infill are hidden by the skins and walls around them (and are most of the lines);
/// support, skirt, brim and prime towers are removed from the print, and would only hide
/// it.
fn is_visible(kind: &str) -> bool {
    const SEEN: [&str; 10] = [
        "External perimeter",
        "Overhang perimeter",
        "Perimeter",
        "Top solid infill",
        "Bottom solid infill",
        "Ironing",
        "Gap fill",
        "WALL-OUTER",
        "WALL-INNER",
        "SKIN",
    ];
    let kind = kind.trim();
    SEEN.iter().any(|s| kind.eq_ignore_ascii_case(s))
}

/// A line in the XY plane, mm (f32: a bed is well under 10 m, and f32 keeps a µm there).
type Line = [[f32; 2]; 2];

/// One layer of visible lines.
#[derive(Clone, Debug, PartialEq)]
struct Layer {
    /// The order in which the file reached this Z (0 for the first layer with a visible
    /// line): sampling keeps the layers whose index is a multiple of the stride.
    index: usize,
    lines: Vec<Line>,
}

/// The visible lines of one G-code file, per layer, ready to draw.
#[derive(Clone, Debug, PartialEq)]
pub struct Print {
    /// Per layer (Z of its top in µm), its lines.
    layers: BTreeMap<i64, Layer>,
    /// Every `stride`-th layer is kept (1: all).
    pub stride: usize,
    /// The lines' width, mm.
    pub line_width_mm: f64,
    /// Extruding moves dropped as no printer's (out of bounds, not finite).
    pub dropped: usize,
}

impl Print {
    pub fn segment_count(&self) -> usize {
        self.layers.values().map(|l| l.lines.len()).sum()
    }

    pub fn layer_count(&self) -> usize {
        self.layers.len()
    }

    /// Per layer, bottom to top: the Z of its top and its height, mm. A layer is as tall
    /// as the step from the layer below it (so a sampled print, its layers k apart, stays
    /// closed); the first from the bed.
    fn layer_heights(&self) -> impl Iterator<Item = (f64, f64, &Layer)> + '_ {
        let stride = self.stride.max(1) as f64;
        let mut below: Option<f64> = None;
        self.layers.iter().map(move |(&z_um, layer)| {
            let z = z_um as f64 / 1000.0;
            let step = match below {
                Some(b) => z - b,
                None => z,
            };
            let h = step.clamp(MIN_LAYER_MM, MAX_LAYER_MM * stride);
            below = Some(z);
            (z, h, layer)
        })
    }

    /// The layers as drawn, bottom to top: the Z of each layer's top and its height (as
    /// [`Print::layer_heights`] settles them), and its lines in XY, mm. The observer
    /// (`crate::observe`) draws its own pictures of the beads from these.
    pub fn layers(&self) -> impl Iterator<Item = (f64, f64, &[[[f32; 2]; 2]])> + '_ {
        self.layer_heights()
            .map(|(z, h, layer)| (z, h, layer.lines.as_slice()))
    }

    /// The box the beads fill, mm; None for a print with no visible line.
    pub fn bounds(&self) -> Option<([f64; 3], [f64; 3])> {
        let r = 0.5 * self.line_width_mm;
        let mut lo = [f64::INFINITY; 3];
        let mut hi = [f64::NEG_INFINITY; 3];
        for (z, h, layer) in self.layer_heights() {
            for p in layer.lines.iter().flatten() {
                for k in 0..2 {
                    lo[k] = lo[k].min(f64::from(p[k]) - r);
                    hi[k] = hi[k].max(f64::from(p[k]) + r);
                }
                lo[2] = lo[2].min(z - h);
                hi[2] = hi[2].max(z);
            }
        }
        (lo[0] <= hi[0]).then_some((lo, hi))
    }
}

/// Reads the visible lines of G-code (see [`is_visible`]), keeping at most `max_segments`
/// (sampling layers beyond), drawn `line_width_mm` wide (clamped to what a nozzle draws).
/// Fails only when the reader fails.
pub fn read_print(
    reader: impl BufRead,
    line_width_mm: f64,
    max_segments: usize,
) -> std::io::Result<Print> {
    let line_width_mm = if line_width_mm.is_finite() {
        line_width_mm.clamp(*LINE_WIDTH_MM.start(), *LINE_WIDTH_MM.end())
    } else {
        0.4
    };
    let mut print = Print {
        layers: BTreeMap::new(),
        stride: 1,
        line_width_mm,
        dropped: 0,
    };
    let max_segments = max_segments.max(1);
    let mut kept = 0usize;
    // The layer being read: its Z (µm) and its index.
    let mut current: Option<(i64, usize)> = None;
    // A file that marks no kinds (another slicer's, or written by hand) is drawn whole.
    crate::slice::walls::extruding_moves(
        reader,
        |k| k.is_none_or(is_visible),
        |m| {
            if !m.moves_xy() {
                return;
            }
            let sane = |p: &[f64; 4]| p[..3].iter().all(|c| c.abs() <= COORD_LIMIT_MM);
            if !(sane(&m.from) && sane(&m.to)) {
                print.dropped += 1;
                return;
            }
            let z_um = (m.to[2] * 1000.0).round() as i64;
            let index = match current {
                Some((z, i)) if z == z_um => i,
                Some((_, i)) => i + 1,
                None => 0,
            };
            current = Some((z_um, index));
            if kept >= max_segments {
                // Sample: keep every other layer of those kept, until there is room (one
                // layer alone beyond the cap keeps what it has).
                while kept >= max_segments && print.layers.len() > 1 {
                    print.stride = print.stride.saturating_mul(2);
                    let stride = print.stride;
                    print.layers.retain(|_, l| l.index % stride == 0);
                    kept = print.segment_count();
                }
                if kept >= max_segments {
                    return;
                }
            }
            let layer = match print.layers.get_mut(&z_um) {
                Some(layer) => layer,
                // A later layer, or one the sampling passes over.
                None if index % print.stride != 0 => return,
                None => print.layers.entry(z_um).or_insert(Layer {
                    index,
                    lines: Vec::new(),
                }),
            };
            layer.lines.push([
                [m.from[0] as f32, m.from[1] as f32],
                [m.to[0] as f32, m.to[1] as f32],
            ]);
            kept += 1;
        },
    )?;
    Ok(print)
}

/// [`read_print`] of a file, with the default cap.
pub fn read_print_file(path: &Path, line_width_mm: f64) -> std::io::Result<Print> {
    let file = std::fs::File::open(path)?;
    read_print(
        std::io::BufReader::with_capacity(1 << 16, file),
        line_width_mm,
        MAX_SEGMENTS,
    )
}

/// One bead, ready to cast rays at: its axis from `a` to `b` (relative to the camera's
/// centre, at mid-height of its layer), its half width and half height.
struct Bead {
    a: [f64; 3],
    /// Unit vector along the axis (horizontal), and its length.
    u: [f64; 3],
    len: f64,
    half_w: f64,
    half_h: f64,
    /// The nearest depth any of it can have (its sort key).
    near: f64,
    /// Its box on the supersampled screen: x0, x1, y0, y1 (inclusive of partial samples).
    screen: [i64; 4],
    /// Its axis on screen (supersampled), for the quick reject.
    sa: [f64; 2],
    sb: [f64; 2],
    /// Screen radius that surely holds it, in samples.
    radius: f64,
}

/// A sample's nearest surface: depth and unit normal.
#[derive(Clone, Copy)]
struct Hit {
    depth: f32,
    normal: [f32; 3],
}

const MISS: Hit = Hit {
    depth: f32::INFINITY,
    normal: [0.0; 3],
};

/// Draws `print` as `camera` sees it, under `lighting`.
pub fn render_print(print: &Print, camera: &Camera, lighting: &Lighting) -> Image {
    let ss = SUPERSAMPLE as f64;
    let (w, h) = (
        camera.width as usize * SUPERSAMPLE,
        camera.height as usize * SUPERSAMPLE,
    );
    let scale = camera.scale * ss;
    let half_w = 0.5 * print.line_width_mm;
    let mut beads: Vec<Bead> = print
        .layer_heights()
        .flat_map(|(z, layer_h, layer)| {
            let zc = z - 0.5 * layer_h;
            layer.lines.iter().filter_map(move |l| {
                let p = |q: [f32; 2]| sub([q[0].into(), q[1].into(), zc], camera.center);
                bead(
                    p(l[0]),
                    p(l[1]),
                    half_w,
                    0.5 * layer_h,
                    camera,
                    scale,
                    (w, h),
                )
            })
        })
        .collect();
    // Front to back: most samples are settled by the first beads, and a bead behind them
    // costs a depth comparison per sample.
    beads.sort_unstable_by(|a, b| a.near.total_cmp(&b.near));

    let mut hits = vec![MISS; w * h];
    let band_rows = raster::BAND_ROWS * SUPERSAMPLE;
    hits.par_chunks_mut((band_rows * w).max(1))
        .enumerate()
        .for_each(|(band, chunk)| {
            let y0 = (band * band_rows) as i64;
            let y1 = y0 + (chunk.len() / w) as i64;
            for b in &beads {
                if b.screen[3] < y0 || b.screen[2] >= y1 {
                    continue;
                }
                cast(b, camera, scale, (w, h), (y0, y1), chunk);
            }
        });

    let shader = Shader::new(camera, lighting);
    raster::resolve(camera, |i| {
        let hit = &hits[i];
        hit.depth
            .is_finite()
            .then(|| shader.shade(MODEL_COLOR, hit.normal))
    })
}

/// The bead from `a` to `b` (relative to the camera's centre), or None when it is no line
/// or wholly off the picture.
fn bead(
    a: [f64; 3],
    b: [f64; 3],
    half_w: f64,
    half_h: f64,
    camera: &Camera,
    scale: f64,
    (w, h): (usize, usize),
) -> Option<Bead> {
    let d = sub(b, a);
    let len = d[0].hypot(d[1]);
    if !(len.is_finite() && len > 0.0) {
        return None;
    }
    let u = [d[0] / len, d[1] / len, 0.0];
    let screen = |p: [f64; 3]| {
        [
            0.5 * w as f64 + dot(p, camera.right) * scale,
            0.5 * h as f64 - dot(p, camera.up) * scale,
        ]
    };
    let (sa, sb) = (screen(a), screen(b));
    let reach = half_w.max(half_h);
    let radius = reach * scale + 1.0;
    let x0 = (sa[0].min(sb[0]) - radius).floor().max(0.0);
    let x1 = (sa[0].max(sb[0]) + radius).ceil().min(w as f64 - 1.0);
    let y0 = (sa[1].min(sb[1]) - radius).floor().max(0.0);
    let y1 = (sa[1].max(sb[1]) + radius).ceil().min(h as f64 - 1.0);
    if !(x0 <= x1 && y0 <= y1) {
        return None;
    }
    let near = dot(a, camera.forward).min(dot(b, camera.forward)) - reach;
    Some(Bead {
        a,
        u,
        len,
        half_w,
        half_h,
        near,
        screen: [x0 as i64, x1 as i64, y0 as i64, y1 as i64],
        sa,
        sb,
        radius,
    })
}

/// Casts the rays of the bead's samples in rows `y0..y1`, which `band` holds.
fn cast(
    b: &Bead,
    camera: &Camera,
    scale: f64,
    (w, h): (usize, usize),
    (y0, y1): (i64, i64),
    band: &mut [Hit],
) {
    let half_height = 0.5 * h as f64;
    let f = camera.forward;
    let n = [-b.u[1], b.u[0], 0.0];
    let (a2, c2) = (b.half_w * b.half_w, b.half_h * b.half_h);
    // Along the ray, the cross-section coordinates change by these per unit of depth.
    let (fn_, fz, fu) = (dot(f, n), f[2], dot(f, b.u));
    let fh2 = f[0] * f[0] + f[1] * f[1];
    let alpha_tube = fn_ * fn_ / a2 + fz * fz / c2;
    let alpha_cap = fh2 / a2 + fz * fz / c2;
    let seg = [b.sb[0] - b.sa[0], b.sb[1] - b.sa[1]];
    let seg2 = seg[0] * seg[0] + seg[1] * seg[1];
    let r2 = b.radius * b.radius;
    for y in b.screen[2].max(y0)..=b.screen[3].min(y1 - 1) {
        let py = y as f64 + 0.5;
        let row = &mut band[(y - y0) as usize * w..][..w];
        for x in b.screen[0]..=b.screen[1] {
            let px = x as f64 + 0.5;
            // Quick reject: farther on screen from the axis than the bead reaches.
            let t = if seg2 > 0.0 {
                (((px - b.sa[0]) * seg[0] + (py - b.sa[1]) * seg[1]) / seg2).clamp(0.0, 1.0)
            } else {
                0.0
            };
            let (dx, dy) = (px - b.sa[0] - t * seg[0], py - b.sa[1] - t * seg[1]);
            if dx * dx + dy * dy > r2 {
                continue;
            }
            let hit = &mut row[x as usize];
            if f64::from(hit.depth) <= b.near {
                continue;
            }
            // The ray's point at depth 0, relative to the bead's start.
            let (rx, ry) = ((px - 0.5 * w as f64) / scale, (half_height - py) / scale);
            let o: [f64; 3] =
                std::array::from_fn(|k| rx * camera.right[k] + ry * camera.up[k] - b.a[k]);
            let (p0, q0, s0) = (dot(o, n), o[2], dot(o, b.u));
            // The side of the tube: (p/a)² + (q/c)² = 1.
            let beta = p0 * fn_ / a2 + q0 * fz / c2;
            let gamma = p0 * p0 / a2 + q0 * q0 / c2 - 1.0;
            let disc = beta * beta - alpha_tube * gamma;
            if disc < 0.0 {
                continue;
            }
            let t = (-beta - disc.sqrt()) / alpha_tube;
            let s = s0 + t * fu;
            let found = if (0.0..=b.len).contains(&s) {
                let (p, q) = (p0 + t * fn_, q0 + t * fz);
                Some((t, [p / a2 * n[0], p / a2 * n[1], q / c2]))
            } else {
                // Past an end: the ellipsoids that round the ends.
                [0.0, b.len]
                    .into_iter()
                    .filter_map(|end| {
                        let e = [o[0] - end * b.u[0], o[1] - end * b.u[1], o[2]];
                        let beta = (e[0] * f[0] + e[1] * f[1]) / a2 + e[2] * fz / c2;
                        let gamma = (e[0] * e[0] + e[1] * e[1]) / a2 + e[2] * e[2] / c2 - 1.0;
                        let disc = beta * beta - alpha_cap * gamma;
                        (disc >= 0.0).then(|| {
                            let t = (-beta - disc.sqrt()) / alpha_cap;
                            let p: [f64; 3] = std::array::from_fn(|k| e[k] + t * f[k]);
                            (t, [p[0] / a2, p[1] / a2, p[2] / c2])
                        })
                    })
                    .min_by(|x, y| x.0.total_cmp(&y.0))
            };
            if let Some((t, normal)) = found {
                if (t as f32) < hit.depth {
                    let normal = normalize(normal);
                    *hit = Hit {
                        depth: t as f32,
                        normal: normal.map(|c| c as f32),
                    };
                }
            }
        }
    }
}

/// The three-quarter view of `bounds` (mm, Z up), centred on their picture: fitted to
/// fill `size` × `size`, or at `px_per_mm` in a picture just big enough (at most `size`
/// a side).
pub(crate) fn framed(bounds: ([f64; 3], [f64; 3]), size: u32, px_per_mm: Option<f64>) -> Camera {
    let base = Camera::three_quarter(bounds, UpAxis::Z, size);
    let (lo, hi) = bounds;
    let mut xs = [f64::INFINITY, f64::NEG_INFINITY];
    let mut ys = xs;
    for i in 0..8 {
        let c: [f64; 3] = std::array::from_fn(|k| if i >> k & 1 == 1 { hi[k] } else { lo[k] });
        let d = sub(c, base.center);
        let (x, y) = (dot(d, base.right), dot(d, base.up));
        xs = [xs[0].min(x), xs[1].max(x)];
        ys = [ys[0].min(y), ys[1].max(y)];
    }
    let (mx, my) = (0.5 * (xs[0] + xs[1]), 0.5 * (ys[0] + ys[1]));
    let center = std::array::from_fn(|k| base.center[k] + mx * base.right[k] + my * base.up[k]);
    let extent = [xs[1] - xs[0], ys[1] - ys[0]];
    let (scale, width, height) = match px_per_mm {
        Some(s) => {
            let px = |e: f64| ((e * s).ceil() as u32 + 4).clamp(8, size.max(8));
            (s, px(extent[0]), px(extent[1]))
        }
        None => {
            let e = extent[0].max(extent[1]);
            let s = if e > 0.0 && e.is_finite() {
                0.94 * f64::from(size) / e
            } else {
                base.scale
            };
            (s, size, size)
        }
    };
    Camera {
        center,
        scale,
        width,
        height,
        ..base
    }
}

/// The picture of a job's print (see the module's comment): in the top row the model
/// (when given: placed, in mm, Z up, as sliced), the plain print and the enhanced one
/// (when given), `panel` pixels square, from one camera fitted to both prints; below, each
/// print at [`ACTUAL_PX_PER_MM`] under its panel. None when the plain print has no
/// visible line.
pub fn preview_picture(
    mesh: Option<&Mesh>,
    plain: &Print,
    enhanced: Option<&Print>,
    panel: u32,
) -> Option<Image> {
    let panel = panel.clamp(16, 480);
    let mut bounds = plain.bounds()?;
    if let Some((lo, hi)) = enhanced.and_then(Print::bounds) {
        for k in 0..3 {
            bounds.0[k] = bounds.0[k].min(lo[k]);
            bounds.1[k] = bounds.1[k].max(hi[k]);
        }
    }
    let camera = framed(bounds, panel, None);
    let lighting = Lighting::grazing(&camera, [0.0, 0.0, 1.0], LIGHT_ELEVATION_DEG);
    let mut top: Vec<Image> = Vec::new();
    if let Some(mesh) = mesh.and_then(|m| on_print(m, bounds)) {
        top.push(super::render_lit(
            &mesh,
            &camera,
            Paint::Uniform(MODEL_COLOR),
            &lighting,
        ));
    }
    let prints: Vec<&Print> = std::iter::once(plain).chain(enhanced).collect();
    let first_print = top.len();
    for p in &prints {
        top.push(render_print(p, &camera, &lighting));
    }
    let small = framed(bounds, panel, Some(ACTUAL_PX_PER_MM));
    let small_light = Lighting::grazing(&small, [0.0, 0.0, 1.0], LIGHT_ELEVATION_DEG);
    let actual: Vec<Image> = prints
        .iter()
        .map(|p| render_print(p, &small, &small_light))
        .collect();

    let n = top.len() as u32;
    let width = n * panel + (n - 1) * GAP_PX;
    let height = panel + GAP_PX + small.height;
    let mut image = Image {
        width,
        height,
        rgba: vec![0; 4 * width as usize * height as usize],
    };
    for (k, picture) in top.iter().enumerate() {
        blit(&mut image, picture, k as u32 * (panel + GAP_PX), 0);
    }
    for (k, picture) in actual.iter().enumerate() {
        // Under its print's panel, centred.
        let x = (first_print + k) as u32 * (panel + GAP_PX) + (panel - picture.width) / 2;
        blit(&mut image, picture, x, panel + GAP_PX);
    }
    Some(image)
}

/// `mesh` moved onto the print: the centre of its box over the centre of the prints', its
/// bottom on theirs. The slicer centres the part on the bed; the mesh was placed about the
/// origin. None for an empty mesh.
fn on_print(mesh: &Mesh, bounds: ([f64; 3], [f64; 3])) -> Option<Mesh> {
    let (lo, hi) = mesh.bounds()?;
    let shift = [
        0.5 * (bounds.0[0] + bounds.1[0] - lo[0] - hi[0]),
        0.5 * (bounds.0[1] + bounds.1[1] - lo[1] - hi[1]),
        bounds.0[2] - lo[2],
    ];
    let mut moved = mesh.clone();
    for v in &mut moved.vertices {
        for k in 0..3 {
            v[k] += shift[k];
        }
    }
    Some(moved)
}

/// Copies `src` into `dst` at (`x`, `y`), clipped.
fn blit(dst: &mut Image, src: &Image, x: u32, y: u32) {
    for sy in 0..src.height.min(dst.height.saturating_sub(y)) {
        let cols = src.width.min(dst.width.saturating_sub(x)) as usize;
        let from = 4 * (sy * src.width) as usize;
        let to = 4 * ((y + sy) as usize * dst.width as usize + x as usize);
        dst.rgba[to..to + 4 * cols].copy_from_slice(&src.rgba[from..from + 4 * cols]);
    }
}

/// Why a preview was not drawn. A picture is a nicety: the job stands without it.
#[derive(Debug, thiserror::Error)]
pub enum PreviewError {
    #[error("cannot read the G-code {path}: {source}")]
    Read {
        path: PathBuf,
        #[source]
        source: std::io::Error,
    },
    #[error("the G-code {0} has no visible line to draw")]
    Empty(PathBuf),
    #[error("cannot write {path}: {source}")]
    Write {
        path: PathBuf,
        #[source]
        source: std::io::Error,
    },
}

/// Draws [`PREVIEW_PNG`] into `dir` from the plain G-code and, for an enhanced job, the
/// enhanced one, beside `mesh` (placed, mm, Z up), lines `line_width_mm` wide. Returns
/// the picture's path. Blocking.
pub fn draw_preview(
    dir: &Path,
    mesh: Option<&Mesh>,
    plain_gcode: &Path,
    enhanced_gcode: Option<&Path>,
    line_width_mm: f64,
) -> Result<PathBuf, PreviewError> {
    let started = std::time::Instant::now();
    let read = |path: &Path| {
        read_print_file(path, line_width_mm).map_err(|source| PreviewError::Read {
            path: path.to_path_buf(),
            source,
        })
    };
    let plain = read(plain_gcode)?;
    let enhanced = enhanced_gcode.map(read).transpose()?;
    let image = preview_picture(mesh, &plain, enhanced.as_ref(), PANEL_PX)
        .ok_or_else(|| PreviewError::Empty(plain_gcode.to_path_buf()))?;
    let path = dir.join(PREVIEW_PNG);
    super::write_png(&path, &image).map_err(|source| PreviewError::Write {
        path: path.clone(),
        source,
    })?;
    tracing::info!(
        file = %path.display(),
        segments = plain.segment_count(),
        stride = plain.stride,
        seconds = started.elapsed().as_secs_f64(),
        "preview of the print drawn"
    );
    Ok(path)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// `layers` layers 0.2 mm tall of a square tower about (100, 100): an inner perimeter,
    /// the outer wall (half side `half(layer)`), sparse infill; E absolute, reset per layer.
    fn tower(layers: usize, half: impl Fn(usize) -> f64) -> String {
        let mut g = String::from("G90\nM82\n");
        for l in 1..=layers {
            let z = 0.2 * l as f64;
            g += &format!(";LAYER_CHANGE\n;Z:{z:.1}\nG92 E0\nG1 Z{z:.3}\n");
            let h = half(l);
            let mut e = 0.0;
            for (kind, side) in [("Perimeter", h - 0.45), ("External perimeter", h)] {
                g += &format!(
                    ";TYPE:{kind}\nG1 X{:.3} Y{:.3} F600\n",
                    100.0 - side,
                    100.0 - side
                );
                for (x, y) in [(1.0, -1.0), (1.0, 1.0), (-1.0, 1.0), (-1.0, -1.0)] {
                    e += 0.5;
                    g += &format!(
                        "G1 X{:.3} Y{:.3} E{e:.4}\n",
                        100.0 + x * side,
                        100.0 + y * side
                    );
                }
            }
            g += ";TYPE:Internal infill\nG1 X90 Y90 E100\nG1 X110 Y110 E101\n";
        }
        g
    }

    fn read(g: &str) -> Print {
        read_print(g.as_bytes(), 0.45, MAX_SEGMENTS).unwrap()
    }

    #[test]
    fn keeps_the_visible_lines_of_each_layer() {
        let p = read(&tower(3, |_| 10.0));
        assert_eq!(p.layer_count(), 3);
        // Two walls of four sides per layer; the infill is hidden.
        assert_eq!(p.segment_count(), 24);
        assert_eq!(p.stride, 1);
        let (lo, hi) = p.bounds().unwrap();
        assert!((lo[0] - (90.0 - 0.225)).abs() < 1e-4, "{lo:?}");
        assert!(
            (hi[2] - 0.6).abs() < 1e-9 && lo[2].abs() < 1e-9,
            "{lo:?} {hi:?}"
        );
        let cura = read(&tower(2, |_| 10.0).replace("External perimeter", "WALL-OUTER"));
        assert_eq!(cura.segment_count(), 16);
        let hidden = read(
            &tower(2, |_| 10.0)
                .replace("External perimeter", "Internal infill")
                .replace("Perimeter", "Internal infill"),
        );
        assert_eq!(hidden.segment_count(), 0);
        assert!(preview_picture(None, &hidden, None, 100).is_none());
        // A file that marks no kinds (another slicer's, or by hand) is drawn whole.
        let unmarked = read(
            &tower(2, |_| 10.0)
                .lines()
                .filter(|l| !l.starts_with(";TYPE:"))
                .collect::<Vec<_>>()
                .join("\n"),
        );
        // Its walls and its one infill line that moves (the other starts where it ends).
        assert_eq!(unmarked.segment_count(), 2 * (8 + 1));
    }

    #[test]
    fn split_garbage_and_huge_numbers_do_not_panic() {
        let g = "M83\nG91\n;TYPE:External perimeter\nG1 Z0.2\nG1 X10 E1\nG1 Y10 E1\n\
                 G1 X1e300 E1\nG1 Xnan E1\nG1 X-1e308 Y-1e308 E1\nG1 X20000 E1\nG92 X0 Y0\n\
                 G1 X5 E-1\n;TYPE:\n\x00\x01\u{fffd}G1 E\nG1 X Y Z\nG1 X1 E1e400\n";
        let p = read(g);
        // The two sane moves are kept; the one 20 m away is dropped.
        assert_eq!(p.segment_count(), 2, "{p:?}");
        assert_eq!(p.layers[&200].lines[1], [[10.0, 0.0], [10.0, 10.0]]);
        assert!(p.dropped >= 1);
        // A file read in pieces reads as a whole.
        let whole = tower(4, |_| 10.0);
        let chained = std::io::BufReader::with_capacity(7, whole.as_bytes());
        assert_eq!(
            read_print(chained, 0.45, MAX_SEGMENTS).unwrap(),
            read(&whole)
        );
        // Random bytes from G-code's alphabet, drawn too.
        const ALPHABET: &[u8] = b"G1XYZE0123456789.-; \nTYPE:External perimeter\nM83G92e+";
        let mut state = 12345u64;
        for _ in 0..100 {
            let bytes = crate::slice::walls::random_bytes(&mut state, ALPHABET, 400);
            let p = read_print(&bytes[..], f64::NAN, MAX_SEGMENTS).unwrap();
            if let Some(image) = preview_picture(None, &p, Some(&p), 32) {
                assert!(image.width <= 3 * 32 + 16 && image.height <= 2 * 32 + 8);
            }
        }
    }

    #[test]
    fn identical_gcode_gives_identical_panels() {
        let g = tower(30, |_| 10.0);
        let (a, b) = (read(&g), read(&g));
        let one = preview_picture(None, &a, Some(&b), 120).unwrap();
        let (left, right) = (crop(&one, 0, 120), crop(&one, 128, 120));
        assert!(opaque(&left) > 2000, "the tower is drawn");
        assert_eq!(left, right);
        assert_eq!(one, preview_picture(None, &a, Some(&b), 120).unwrap());
    }

    fn crop(image: &Image, x0: u32, size: u32) -> Image {
        let mut rgba = Vec::new();
        for y in 0..size {
            for x in x0..x0 + size {
                rgba.extend(image.pixel(x, y));
            }
        }
        Image {
            width: size,
            height: size,
            rgba,
        }
    }

    fn opaque(image: &Image) -> usize {
        image.rgba.chunks(4).filter(|p| p[3] > 0).count()
    }

    /// The outer wall of layers 20 to 29 pushed out by 0.3 mm: the enhanced panel differs
    /// from the plain one where that band projects, and nowhere far from it.
    #[test]
    fn a_wall_pushed_out_shows_where_it_moved_and_only_there() {
        let band = 20..30;
        let plain = read(&tower(50, |_| 10.0));
        let moved = read(&tower(50, |l| if band.contains(&l) { 10.3 } else { 10.0 }));
        let size = 300;
        let both = preview_picture(None, &plain, Some(&moved), size).unwrap();
        let (p, e) = (crop(&both, 0, size), crop(&both, size + GAP_PX, size));
        let camera = framed(moved.bounds().unwrap(), size, None);
        // The rows the band's box covers, from the camera the picture used.
        let mut rows = [f64::INFINITY, f64::NEG_INFINITY];
        for i in 0..8 {
            let x = if i & 1 == 1 { 110.6 } else { 89.4 };
            let y = if i & 2 == 2 { 110.6 } else { 89.4 };
            let z = if i & 4 == 4 {
                0.2 * band.end as f64
            } else {
                0.2 * band.start as f64 - 0.4
            };
            let py = camera.project([x, y, z])[1];
            rows = [rows[0].min(py), rows[1].max(py)];
        }
        let mut inside = 0;
        for y in 0..size {
            for x in 0..size {
                let (a, b) = (p.pixel(x, y), e.pixel(x, y));
                let differs = (0..4).any(|k| a[k].abs_diff(b[k]) > 8);
                if differs {
                    let near = (y as f64) >= rows[0] - 3.0 && (y as f64) <= rows[1] + 3.0;
                    assert!(near, "pixel ({x}, {y}) differs, outside rows {rows:?}");
                    inside += 1;
                }
            }
        }
        assert!(inside > 150, "only {inside} pixels differ");
    }

    /// Seen level and close up, a wall is its layers: along a column the light rises and
    /// falls once per layer, as each bead's rounded face turns from the light to the bed.
    #[test]
    fn layer_lines_show_as_ridges() {
        let p = read(&tower(50, |_| 10.0));
        let base = Camera::looking_at(
            p.bounds().unwrap(),
            [0.0, -1.0, 0.0],
            [0.0, 0.0, 1.0],
            200,
            200,
        );
        // 50 px per mm on the middle of the front wall: 4 mm, 20 layers, fill the picture.
        let camera = Camera {
            center: [100.0, 90.0, 5.0],
            scale: 50.0,
            ..base
        };
        let image = render_print(
            &p,
            &camera,
            &Lighting::grazing(&camera, [0.0, 0.0, 1.0], 20.0),
        );
        let column: Vec<f64> = (0..200)
            .map(|y| {
                let c = image.pixel(100, y);
                assert_eq!(c[3], 255, "the wall fills the picture");
                f64::from(c[0]) + f64::from(c[1]) + f64::from(c[2])
            })
            .collect();
        let mean = column.iter().sum::<f64>() / column.len() as f64;
        let rises = column
            .windows(2)
            .filter(|w| w[0] < mean && w[1] >= mean)
            .count();
        assert!(
            (19..=21).contains(&rises),
            "{rises} ridges in 20 layers: {column:?}"
        );
        let (lo, hi) = column
            .iter()
            .fold((f64::MAX, 0.0f64), |(l, h), &v| (l.min(v), h.max(v)));
        assert!(
            hi - lo > 100.0,
            "the ridges are light and shadow: {lo}..{hi}"
        );
    }

    #[test]
    fn a_print_over_the_cap_is_sampled_and_stays_closed() {
        let g = tower(200, |_| 10.0);
        let full = read(&g);
        assert_eq!(full.segment_count(), 1600);
        let sampled = read_print(g.as_bytes(), 0.45, 300).unwrap();
        assert!(
            sampled.segment_count() <= 300,
            "{}",
            sampled.segment_count()
        );
        assert!(sampled.stride >= 8, "stride {}", sampled.stride);
        // The sampled layers still span the print, each as tall as the step below it.
        let (lo, hi) = sampled.bounds().unwrap();
        assert!(lo[2].abs() < 1e-9, "{lo:?}");
        assert!(hi[2] > 40.0 - 0.2 * sampled.stride as f64 - 1e-9, "{hi:?}");
        let heights: f64 = sampled.layer_heights().map(|(_, h, _)| h).sum();
        assert!((heights - hi[2]).abs() < 1e-6, "{heights} vs {}", hi[2]);
        // Drawn, it has no gaps between layers: its silhouette is as solid as the full one's.
        let camera = framed(full.bounds().unwrap(), 100, None);
        let light = Lighting::grazing(&camera, [0.0, 0.0, 1.0], 20.0);
        let (a, b) = (
            opaque(&render_print(&full, &camera, &light)),
            opaque(&render_print(&sampled, &camera, &light)),
        );
        assert!((a as f64 - b as f64).abs() < 0.05 * a as f64, "{a} vs {b}");
    }
}
