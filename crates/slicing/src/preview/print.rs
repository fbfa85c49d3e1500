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
//! which gives an exact normal per pixel for the price of a quadratic. Beads are drawn
//! nearest first, and a sample whose surface is in front of every bead still to come is
//! passed over from then on, so a hidden bead costs a look per row it crosses; the rays
//! per sample and the rows all beads cross are capped ([`render_print_counted`]), so a
//! picture costs at most a bound that follows from its size and the file's lines, whatever
//! lines the file stacks on one spot.

use super::raster::{self, Shader, SUPERSAMPLE};
use super::scene::dot;
use super::{normalize, sub, Camera, Image, Lighting, Paint, MODEL_COLOR};
use crate::slice::walls::COORD_LIMIT_MM;
use crispen_geometry::mesh::place::UpAxis;
use crispen_geometry::mesh::Mesh;
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
    /// Its rows on the supersampled screen, first and last (inclusive of partial samples).
    rows: [i64; 2],
    /// Its axis on screen (supersampled): the samples within `radius` of it are its own.
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

/// At most this many beads cast a ray at one sample; the sample then keeps the nearest
/// surface they found. In a print, a sample is settled long before (the beads are drawn
/// nearest first, and one whose nearest point is behind a sample's surface passes it by);
/// only lines stacked on one spot, each reaching in front of the others (a purge or
/// calibration pattern, or a file crafted so), reach the cap.
pub const MAX_RAYS_PER_SAMPLE: u8 = 32;

/// The rows of samples the beads of one picture may cross together, per sample of the
/// picture and per bead: a bead looks at each row it crosses once. A print's beads cross
/// a few rows each at a panel's size, and only their share of the picture when it is
/// close up; only long lines stacked on one another cross this many, and past it the
/// farthest beads are left out (each one's nearest point is behind those drawn).
const ROWS_PER_SAMPLE: u64 = 8;
const ROWS_PER_BEAD: u64 = 8;

/// What drawing a print cost, counted: the bound it keeps ([`DrawWork::bound`]), which
/// follows from the picture's size and the number of lines alone, is checked against
/// these, not against a clock.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct DrawWork {
    /// Samples of the picture (supersampled pixels).
    pub samples: u64,
    /// Beads on the picture, and those left out past the rows' budget.
    pub beads: u64,
    pub beads_left_out: u64,
    /// Rows of samples a bead crossed (each finds the bead's span on its row once).
    pub bead_rows: u64,
    /// Samples visited: a ray cast, or a depth comparison that settles the sample.
    pub visits: u64,
    /// Rays cast at a bead.
    pub rays: u64,
    /// Samples that reached [`MAX_RAYS_PER_SAMPLE`] unsettled.
    pub capped: u64,
}

impl DrawWork {
    fn add(self, o: DrawWork) -> DrawWork {
        DrawWork {
            samples: self.samples + o.samples,
            beads: self.beads + o.beads,
            beads_left_out: self.beads_left_out + o.beads_left_out,
            bead_rows: self.bead_rows + o.bead_rows,
            visits: self.visits + o.visits,
            rays: self.rays + o.rays,
            capped: self.capped + o.capped,
        }
    }

    /// The most work drawing may do, from the picture's samples and its beads alone: the
    /// rows the beads cross together, and the samples visited (each at most
    /// [`MAX_RAYS_PER_SAMPLE`] times: a ray each, the last settling it, or a depth
    /// comparison that settles it sooner).
    pub fn bound(&self) -> (u64, u64) {
        (
            rows_budget(self.samples, self.beads),
            self.samples * u64::from(MAX_RAYS_PER_SAMPLE),
        )
    }
}

fn rows_budget(samples: u64, beads: u64) -> u64 {
    ROWS_PER_SAMPLE * samples + ROWS_PER_BEAD * beads
}

/// Draws `print` as `camera` sees it, under `lighting`.
pub fn render_print(print: &Print, camera: &Camera, lighting: &Lighting) -> Image {
    render_print_counted(print, camera, lighting).0
}

/// [`render_print`], and what it cost.
///
/// The beads are drawn nearest first into a buffer of the nearest surface per sample. Once
/// a sample's surface is nearer than the nearest point of the bead being drawn, no later
/// bead can be in front of it: the sample is settled and skipped from then on (each row
/// keeps, per sample, the next one not settled, with paths halved as they are followed),
/// so a bead behind the picture's surface costs a look at each of its rows, not at each of
/// its samples. Two caps bound the rest, whatever the file (both stated with their
/// constants): a sample still unsettled after [`MAX_RAYS_PER_SAMPLE`] rays keeps the
/// nearest surface they found, and the beads past a budget of rows crossed are left out,
/// farthest first.
pub fn render_print_counted(
    print: &Print,
    camera: &Camera,
    lighting: &Lighting,
) -> (Image, DrawWork) {
    let ss = SUPERSAMPLE as f64;
    let (w, h) = (
        camera.width as usize * SUPERSAMPLE,
        camera.height as usize * SUPERSAMPLE,
    );
    let scale = camera.scale * ss;
    let mut beads = beads_of(print, camera, scale, (w, h));
    let samples = (w * h) as u64;
    let on_picture = beads.len() as u64;
    let mut rows_left = rows_budget(samples, on_picture);
    let kept = beads
        .iter()
        .take_while(|b| {
            let rows = (b.rows[1] - b.rows[0] + 1) as u64;
            let fits = rows <= rows_left;
            rows_left = rows_left.saturating_sub(rows);
            fits
        })
        .count();
    beads.truncate(kept);

    let mut hits = vec![MISS; w * h];
    let band_rows = raster::BAND_ROWS * SUPERSAMPLE;
    let work = hits
        .par_chunks_mut((band_rows * w).max(1))
        .enumerate()
        .map(|(band, chunk)| {
            let y0 = (band * band_rows) as i64;
            let y1 = y0 + (chunk.len() / w) as i64;
            let mut band = Band::new(chunk, w, y0);
            for b in &beads {
                if b.rows[1] < y0 || b.rows[0] >= y1 {
                    continue;
                }
                band.draw(b, camera, scale, h);
            }
            band.work
        })
        .reduce(DrawWork::default, DrawWork::add);
    let work = DrawWork {
        beads: on_picture,
        beads_left_out: on_picture - kept as u64,
        ..work
    };

    let shader = Shader::new(camera, lighting);
    let image = raster::resolve(camera, |i| {
        let hit = &hits[i];
        hit.depth
            .is_finite()
            .then(|| shader.shade(MODEL_COLOR, hit.normal))
    });
    (image, work)
}

/// The beads of `print` on the picture (`scale` samples per mm, `w` × `h` samples), the
/// nearest first (in the file's order where they are as near: the first keeps a sample
/// whose surfaces tie).
fn beads_of(print: &Print, camera: &Camera, scale: f64, (w, h): (usize, usize)) -> Vec<Bead> {
    let half_w = 0.5 * print.line_width_mm;
    // A quarter of a sample: no picture tells a path from its chord closer than that.
    let tolerance = 0.25 / scale;
    let mut chords = Vec::new();
    let mut beads: Vec<Bead> = Vec::new();
    for (z, layer_h, layer) in print.layer_heights() {
        let zc = z - 0.5 * layer_h;
        let p = |q: [f32; 2]| sub([q[0].into(), q[1].into(), zc], camera.center);
        chords.clear();
        joined_chords(&layer.lines, tolerance, &mut chords);
        beads.extend(chords.iter().filter_map(|l| {
            bead(
                p(l[0]),
                p(l[1]),
                half_w,
                0.5 * layer_h,
                camera,
                scale,
                (w, h),
            )
        }));
    }
    // What settles a sample (see `render_print_counted`) holds for every later bead.
    beads.sort_by(|a, b| a.near.total_cmp(&b.near));
    beads
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
    // Its cross-section lies within an ellipsoid of its half width across and its half
    // height up: this far towards the camera at most.
    let f = camera.forward;
    let towards =
        (half_w * half_w * (f[0] * f[0] + f[1] * f[1]) + half_h * half_h * f[2] * f[2]).sqrt();
    let near = dot(a, f).min(dot(b, f)) - towards;
    Some(Bead {
        a,
        u,
        len,
        half_w,
        half_h,
        near,
        rows: [y0 as i64, y1 as i64],
        sa,
        sb,
        radius,
    })
}

/// The most lines one chord stands for.
const MAX_JOINED: usize = 64;

/// The lines of a layer as a picture can tell them apart, into `out`: a run of lines each
/// starting where the one before ended (a curve, which slicers write as many short
/// lines) becomes its chord while every point of the run lies within `tolerance` (mm) of
/// it, up to [`MAX_JOINED`] lines. Projected, a point moves no farther than it is, so the
/// picture moves by less than the tolerance on screen; and a sample crossed by many tiny
/// lines of one wall is crossed by a few chords.
fn joined_chords(lines: &[Line], tolerance: f64, out: &mut Vec<Line>) {
    let mut run: Vec<[f32; 2]> = Vec::with_capacity(MAX_JOINED + 1);
    for l in lines {
        let joins = run.len() <= MAX_JOINED
            && run.last() == Some(&l[0])
            && run[1..]
                .iter()
                .all(|&p| distance_to_segment(p, [run[0], l[1]]) <= tolerance);
        if joins {
            run.push(l[1]);
        } else {
            if let [first, .., last] = run[..] {
                out.push([first, last]);
            }
            run.clear();
            run.extend(l);
        }
    }
    if let [first, .., last] = run[..] {
        out.push([first, last]);
    }
}

/// The distance from `p` to the segment `s`, mm.
fn distance_to_segment(p: [f32; 2], s: Line) -> f64 {
    let [p, a, b] = [p, s[0], s[1]].map(|q| q.map(f64::from));
    let d = [b[0] - a[0], b[1] - a[1]];
    let len2 = d[0] * d[0] + d[1] * d[1];
    let t = if len2 > 0.0 {
        (((p[0] - a[0]) * d[0] + (p[1] - a[1]) * d[1]) / len2).clamp(0.0, 1.0)
    } else {
        0.0
    };
    (p[0] - a[0] - t * d[0]).hypot(p[1] - a[1] - t * d[1])
}

/// The rows `y0..` of the nearest surfaces that one thread draws, and what it costs.
struct Band<'a> {
    hits: &'a mut [Hit],
    /// Per row, `w + 1` entries: for each sample, one at or before the next sample not
    /// settled (itself when it is not); the last is the row's end, never settled.
    next: Vec<u32>,
    rays: Vec<u8>,
    w: usize,
    y0: i64,
    work: DrawWork,
}

impl Band<'_> {
    fn new(hits: &mut [Hit], w: usize, y0: i64) -> Band<'_> {
        let rows = hits.len() / w.max(1);
        Band {
            next: (0..rows).flat_map(|_| 0..=w as u32).collect(),
            rays: vec![0; hits.len()],
            work: DrawWork {
                samples: hits.len() as u64,
                ..DrawWork::default()
            },
            hits,
            w,
            y0,
        }
    }

    /// Draws `b` into the band's rows: each sample within its screen radius not yet
    /// settled gets a ray.
    fn draw(&mut self, b: &Bead, camera: &Camera, scale: f64, h: usize) {
        let w = self.w;
        let rows = (self.hits.len() / w) as i64;
        let ray = Ray::new(b, camera, scale, (w, h));
        for y in b.rows[0].max(self.y0)..=b.rows[1].min(self.y0 + rows - 1) {
            self.work.bead_rows += 1;
            let py = y as f64 + 0.5;
            let Some((lo, hi)) = capsule_span(b.sa, b.sb, b.radius, py) else {
                continue;
            };
            // The samples whose centres lie in the span.
            let first = (lo - 0.5).ceil().max(0.0);
            let last = (hi - 0.5).floor().min(w as f64 - 1.0);
            if !(first <= last) {
                continue;
            }
            let (first, last) = (first as usize, last as usize);
            let r = (y - self.y0) as usize;
            let next = &mut self.next[r * (w + 1)..][..w + 1];
            let mut x = unsettled(next, first);
            while x <= last {
                self.work.visits += 1;
                let i = r * w + x;
                let hit = &mut self.hits[i];
                let settled = if f64::from(hit.depth) <= b.near {
                    true
                } else {
                    self.work.rays += 1;
                    if let Some((t, normal)) = ray.cast(x as f64 + 0.5, py) {
                        if (t as f32) < hit.depth {
                            *hit = Hit {
                                depth: t as f32,
                                normal: normalize(normal).map(|c| c as f32),
                            };
                        }
                    }
                    self.rays[i] += 1;
                    let capped = self.rays[i] >= MAX_RAYS_PER_SAMPLE;
                    self.work.capped += u64::from(capped);
                    capped
                };
                if settled {
                    next[x] = x as u32 + 1;
                }
                x = unsettled(next, x + 1);
            }
        }
    }
}

/// The first sample at or after `x` in its row that is not settled (the row's end when
/// none is), halving the path followed.
fn unsettled(next: &mut [u32], mut x: usize) -> usize {
    while next[x] as usize != x {
        let skip = next[next[x] as usize];
        next[x] = skip;
        x = skip as usize;
    }
    x
}

/// Where the row at `py` crosses the points within `r` of the segment `a`–`b` (a capsule,
/// convex, so one span): the union of its crossings of the discs at the ends and of the
/// band between them. None when it misses.
fn capsule_span(a: [f64; 2], b: [f64; 2], r: f64, py: f64) -> Option<(f64, f64)> {
    let mut span = (f64::INFINITY, f64::NEG_INFINITY);
    let mut take = |(lo, hi): (f64, f64)| {
        if lo <= hi {
            span = (span.0.min(lo), span.1.max(hi));
        }
    };
    for c in [a, b] {
        let q = r * r - (py - c[1]) * (py - c[1]);
        if q >= 0.0 {
            let s = q.sqrt();
            take((c[0] - s, c[0] + s));
        }
    }
    let d = [b[0] - a[0], b[1] - a[1]];
    let len = d[0].hypot(d[1]);
    if len > 0.0 {
        // Along the segment, 0 ≤ (p − a)·d ≤ |d|²; across it, |(p − a) × d| ≤ r |d|; each
        // linear in x along the row.
        let dy = py - a[1];
        let mut band = (f64::NEG_INFINITY, f64::INFINITY);
        let along = within(&mut band, dy * d[1], d[0], 0.0, len * len);
        let across = within(&mut band, -dy * d[0], d[1], -r * len, r * len);
        if along && across {
            take((a[0] + band.0, a[0] + band.1));
        }
    }
    (span.0 <= span.1).then_some(span)
}

/// Narrows `range` (of x, relative to the segment's start) to where `c0 + c1·x` lies in
/// `lo..=hi`; false when nowhere.
fn within(range: &mut (f64, f64), c0: f64, c1: f64, lo: f64, hi: f64) -> bool {
    if c1 == 0.0 {
        return (lo..=hi).contains(&c0);
    }
    let (p, q) = ((lo - c0) / c1, (hi - c0) / c1);
    let (p, q) = if c1 > 0.0 { (p, q) } else { (q, p) };
    *range = (range.0.max(p), range.1.min(q));
    range.0 <= range.1
}

/// A bead's ray casting: what stays the same for all its samples.
struct Ray<'a> {
    b: &'a Bead,
    camera: &'a Camera,
    scale: f64,
    half_size: [f64; 2],
    /// The bead's horizontal normal.
    n: [f64; 3],
    a2: f64,
    c2: f64,
    /// Along the ray, the cross-section coordinates change by these per unit of depth.
    fn_: f64,
    fz: f64,
    fu: f64,
    alpha_tube: f64,
    alpha_cap: f64,
}

impl<'a> Ray<'a> {
    fn new(b: &'a Bead, camera: &'a Camera, scale: f64, (w, h): (usize, usize)) -> Ray<'a> {
        let f = camera.forward;
        let n = [-b.u[1], b.u[0], 0.0];
        let (a2, c2) = (b.half_w * b.half_w, b.half_h * b.half_h);
        let (fn_, fz, fu) = (dot(f, n), f[2], dot(f, b.u));
        let fh2 = f[0] * f[0] + f[1] * f[1];
        Ray {
            b,
            camera,
            scale,
            half_size: [0.5 * w as f64, 0.5 * h as f64],
            n,
            a2,
            c2,
            fn_,
            fz,
            fu,
            alpha_tube: fn_ * fn_ / a2 + fz * fz / c2,
            alpha_cap: fh2 / a2 + fz * fz / c2,
        }
    }

    /// The nearest crossing of the view ray through the sample at (`px`, `py`) with the
    /// bead's elliptic cylinder, or past its ends with the ellipsoids that round them: its
    /// depth and its (unnormalised) normal.
    fn cast(&self, px: f64, py: f64) -> Option<(f64, [f64; 3])> {
        let (b, f, n) = (self.b, self.camera.forward, self.n);
        let (a2, c2) = (self.a2, self.c2);
        // The ray's point at depth 0, relative to the bead's start.
        let (rx, ry) = (
            (px - self.half_size[0]) / self.scale,
            (self.half_size[1] - py) / self.scale,
        );
        let o: [f64; 3] =
            std::array::from_fn(|k| rx * self.camera.right[k] + ry * self.camera.up[k] - b.a[k]);
        let (p0, q0, s0) = (dot(o, n), o[2], dot(o, b.u));
        // The side of the tube: (p/a)² + (q/c)² = 1.
        let beta = p0 * self.fn_ / a2 + q0 * self.fz / c2;
        let gamma = p0 * p0 / a2 + q0 * q0 / c2 - 1.0;
        let disc = beta * beta - self.alpha_tube * gamma;
        if disc < 0.0 {
            return None;
        }
        let t = (-beta - disc.sqrt()) / self.alpha_tube;
        let s = s0 + t * self.fu;
        if (0.0..=b.len).contains(&s) {
            let (p, q) = (p0 + t * self.fn_, q0 + t * self.fz);
            return Some((t, [p / a2 * n[0], p / a2 * n[1], q / c2]));
        }
        // Past an end: the ellipsoids that round the ends.
        [0.0, b.len]
            .into_iter()
            .filter_map(|end| {
                let e = [o[0] - end * b.u[0], o[1] - end * b.u[1], o[2]];
                let beta = (e[0] * f[0] + e[1] * f[1]) / a2 + e[2] * self.fz / c2;
                let gamma = (e[0] * e[0] + e[1] * e[1]) / a2 + e[2] * e[2] / c2 - 1.0;
                let disc = beta * beta - self.alpha_cap * gamma;
                (disc >= 0.0).then(|| {
                    let t = (-beta - disc.sqrt()) / self.alpha_cap;
                    let p: [f64; 3] = std::array::from_fn(|k| e[k] + t * f[k]);
                    (t, [p[0] / a2, p[1] / a2, p[2] / c2])
                })
            })
            .min_by(|x, y| x.0.total_cmp(&y.0))
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

    /// Every bead (the same, in the same order) at every sample within its reach on
    /// screen, the nearest surface kept: no sample passed over, no cap. What the drawing
    /// must give wherever its caps are not reached.
    fn render_every_bead(print: &Print, camera: &Camera, lighting: &Lighting) -> Image {
        let (w, h) = (
            camera.width as usize * SUPERSAMPLE,
            camera.height as usize * SUPERSAMPLE,
        );
        let scale = camera.scale * SUPERSAMPLE as f64;
        let mut hits = vec![MISS; w * h];
        for b in beads_of(print, camera, scale, (w, h)) {
            let ray = Ray::new(&b, camera, scale, (w, h));
            let axis = [b.sb[0] - b.sa[0], b.sb[1] - b.sa[1]];
            for (i, hit) in hits.iter_mut().enumerate() {
                let p = [(i % w) as f64 + 0.5, (i / w) as f64 + 0.5];
                let d = [p[0] - b.sa[0], p[1] - b.sa[1]];
                let t = (d[0] * axis[0] + d[1] * axis[1]) / (axis[0] * axis[0] + axis[1] * axis[1]);
                let t = if t.is_finite() {
                    t.clamp(0.0, 1.0)
                } else {
                    0.0
                };
                if (d[0] - t * axis[0]).hypot(d[1] - t * axis[1]) > b.radius {
                    continue;
                }
                if let Some((t, n)) = ray.cast(p[0], p[1]) {
                    if (t as f32) < hit.depth {
                        *hit = Hit {
                            depth: t as f32,
                            normal: normalize(n).map(|c| c as f32),
                        };
                    }
                }
            }
        }
        let shader = Shader::new(camera, lighting);
        raster::resolve(camera, |i| {
            hits[i]
                .depth
                .is_finite()
                .then(|| shader.shade(MODEL_COLOR, hits[i].normal))
        })
    }

    /// A print's picture is the one every bead cast at every sample gives: passing over
    /// the samples settled changes nothing, and no cap is reached; the work stays within
    /// its bound, and far under what every bead at every sample costs.
    #[test]
    fn passing_over_settled_samples_changes_no_pixel() {
        let bulge = |l: usize| 10.0 + 2.0 * ((l as f64) / 8.0).sin();
        let print = read(&tower(60, bulge));
        let bounds = print.bounds().unwrap();
        for (eye, size) in [
            ([0.5, -0.8, 0.4], 96),
            ([0.0, 0.0, 1.0], 64),
            ([-0.3, 0.9, -0.2], 80),
            ([0.0, -1.0, 0.0], 72),
        ] {
            let camera = Camera::looking_at(bounds, eye, [0.0, 0.0, 1.0], size, size);
            let light = Lighting::grazing(&camera, [0.0, 0.0, 1.0], 20.0);
            let (image, work) = render_print_counted(&print, &camera, &light);
            let every = render_every_bead(&print, &camera, &light);
            let differ: Vec<(usize, [u8; 4], [u8; 4])> = (0..image.rgba.len() / 4)
                .filter(|&i| image.rgba[4 * i..4 * i + 4] != every.rgba[4 * i..4 * i + 4])
                .map(|i| {
                    (
                        i,
                        image.rgba[4 * i..4 * i + 4].try_into().unwrap(),
                        every.rgba[4 * i..4 * i + 4].try_into().unwrap(),
                    )
                })
                .collect();
            assert!(
                differ.is_empty(),
                "{eye:?}: {} differ: {:?} {work:?}",
                differ.len(),
                &differ[..differ.len().min(10)]
            );
            // Drawn this small (a layer a sample tall), a few samples where walls meet
            // reach the cap, and still show the nearest surface.
            assert_eq!(work.beads_left_out, 0, "{eye:?}");
            assert!(work.capped * 200 < work.samples, "{eye:?}: {work:?}");
            let (rows, visits) = work.bound();
            assert!(work.bead_rows <= rows && work.visits <= visits, "{work:?}");
            assert!(work.rays <= work.visits, "{work:?}");
        }
    }

    /// Lines stacked on one spot (a purge pattern, or a file crafted so): short ones, each
    /// bead covering most of the picture and reaching in front of the others, on one layer
    /// or a few; long ones, each crossing most of the picture's rows. The work follows
    /// from the picture and the number of lines alone (at most 32 rays a sample, 8 rows a
    /// sample and a bead), far under a ray per bead and sample; the spot is still drawn.
    #[test]
    fn lines_stacked_on_one_spot_cost_at_most_the_bound() {
        let stacked = |moves: usize, layers: usize, long: bool| {
            let mut g = String::from("G90\nM83\nG1 X20 Y20\n");
            for i in 0..moves {
                if i % (moves / layers) == 0 {
                    g += &format!("G1 Z{:.2}\n", 0.2 + 0.05 * (i / (moves / layers)) as f64);
                }
                let there = i % 2 == 0;
                let (x, y) = match (long, there) {
                    (true, _) => (20.0, if there { 170.0 } else { 20.0 }),
                    (false, _) => (
                        if there { 20.3 } else { 20.0 },
                        20.0 + 0.05 * (i % 7) as f64,
                    ),
                };
                g += &format!("G1 X{x:.3} Y{y:.3} E0.01\n");
            }
            g
        };
        for (moves, layers, long) in [
            (6000, 1, false),
            (24_000, 1, false),
            (6000, 6, false),
            (6000, 1, true),
            (40_000, 4, true),
        ] {
            let what = format!("{moves} lines on {layers} layers, long {long}");
            let print = read(&stacked(moves, layers, long));
            assert_eq!(print.segment_count(), moves, "{what}");
            let camera = framed(print.bounds().unwrap(), 120, None);
            let light = Lighting::grazing(&camera, [0.0, 0.0, 1.0], 20.0);
            let (image, work) = render_print_counted(&print, &camera, &light);
            let samples = 240 * 240;
            assert_eq!(
                (work.samples, work.beads),
                (samples, moves as u64),
                "{what}"
            );
            assert_eq!(work.bound(), (8 * (samples + moves as u64), 32 * samples));
            assert!(
                work.bead_rows <= work.bound().0
                    && work.visits <= work.bound().1
                    && work.rays <= work.visits,
                "{what}: {work:?}"
            );
            assert!(
                work.visits * 100 < moves as u64 * samples,
                "{what}: {work:?}"
            );
            if long {
                assert!(work.beads_left_out > 0, "{what}: {work:?}");
            } else {
                assert!(work.capped > samples / 4, "{what}: {work:?}");
            }
            let drawn = opaque(&image);
            assert!(
                drawn > if long { 60 } else { 120 * 120 / 8 },
                "{what}: {drawn} px"
            );
        }
    }

    /// A curve written as many short lines is drawn as chords within the tolerance of
    /// every point; lines that turn back, or do not join, stay as they are.
    #[test]
    fn short_joined_lines_become_chords_within_the_tolerance() {
        let ring: Vec<Line> = (0..2000)
            .map(|i| {
                let p = |k: usize| {
                    let a = k as f64 / 2000.0 * std::f64::consts::TAU;
                    [
                        (100.0 + 20.0 * a.cos()) as f32,
                        (100.0 + 20.0 * a.sin()) as f32,
                    ]
                };
                [p(i), p(i + 1)]
            })
            .collect();
        for tolerance in [0.001, 0.01, 0.1] {
            let mut chords = Vec::new();
            joined_chords(&ring, tolerance, &mut chords);
            // A chord of sagitta t on a circle of radius r spans about √(8rt).
            let span = (8.0 * 20.0 * tolerance).sqrt();
            let expected = (2.0 * std::f64::consts::PI * 20.0 / span).max(2000.0 / 64.0);
            assert!(
                (chords.len() as f64) < 1.6 * expected,
                "{} chords at {tolerance} mm",
                chords.len()
            );
            // Each line's end lies within the tolerance of the chord that stands for it.
            let mut next = 0;
            for c in &chords {
                assert_eq!(c[0], ring[next][0]);
                while ring[next][1] != c[1] {
                    assert!(distance_to_segment(ring[next][1], *c) <= tolerance);
                    next += 1;
                }
                next += 1;
            }
            assert_eq!(next, ring.len());
        }
        // Back and forth along one line, a zig-zag, lines that do not join.
        let there_and_back: Vec<Line> = vec![[[0.0, 0.0], [10.0, 0.0]], [[10.0, 0.0], [5.0, 0.0]]];
        let zigzag: Vec<Line> = (0..10)
            .map(|i| {
                [
                    [i as f32, (i % 2) as f32],
                    [i as f32 + 1.0, ((i + 1) % 2) as f32],
                ]
            })
            .collect();
        let apart: Vec<Line> = vec![[[0.0, 0.0], [1.0, 0.0]], [[1.5, 0.0], [3.0, 0.0]]];
        for lines in [there_and_back, zigzag, apart] {
            let mut chords = Vec::new();
            joined_chords(&lines, 0.1, &mut chords);
            assert_eq!(chords, lines);
        }
    }
}
