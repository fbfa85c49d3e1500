//! A computational observer: how much a small print looks like the same model printed at
//! a reference size, as a person would see both on a table (docs/method.md, "The
//! observer", gives the model, its sources and every constant).
//!
//! - [`render`]: each print drawn from its G-code (the beads crispen's preview reads,
//!   [`crate::preview::print::Print`]) as luminance, at its real size as seen from the
//!   viewing distance, in pixels per degree of visual angle, from several views around
//!   it under the scene's lights: white PLA on a dark cloth.
//! - [`eye`]: Barten's contrast sensitivity, Daly's masking, probability summation; only
//!   published constants.
//! - [`compare`]: Peli's band-limited contrast in threshold units, and the differences
//!   between two prints band by band and place by place, lost and added.
//!
//! The small print and the reference are framed alike (the object at the same place of
//! each picture, scaled), the small one's picture 2^m times coarser than the reference's
//! with m chosen so that both are drawn at no fewer than [`Conditions::pixels_per_degree`]:
//! so their pyramids share levels pixel for pixel, a level of each standing for the same
//! part of the object at the same scale of the object, while each is weighted by the
//! eye's sensitivity at the frequency it has on the retina.

mod compare;
mod eye;
mod pyramid;
mod render;

use crate::preview::print::Print;
use crate::preview::Image;
use crate::preview::{cross, dot, normalize, sub};
use render::{Camera, Light, Lighting};

pub use crate::observation::{
    BandDifference, Conditions, Resemblance, DISTANCE_MM, ELEVATION_DEG, PIXELS_PER_DEGREE, VIEWS,
};

impl Conditions {
    /// Checks each value against its bounds; the error names the value.
    pub fn check(&self) -> Result<(), ObserveError> {
        let bad = |what: &'static str, value: String, range: String| {
            Err(ObserveError::Condition { what, value, range })
        };
        if !(self.distance_mm.is_finite() && DISTANCE_MM.contains(&self.distance_mm)) {
            return bad(
                "viewing distance (mm)",
                self.distance_mm.to_string(),
                format!("{DISTANCE_MM:?}"),
            );
        }
        if !(self.pixels_per_degree.is_finite()
            && PIXELS_PER_DEGREE.contains(&self.pixels_per_degree))
        {
            return bad(
                "pixels per degree",
                self.pixels_per_degree.to_string(),
                format!("{PIXELS_PER_DEGREE:?}"),
            );
        }
        if !(self.elevation_deg.is_finite() && ELEVATION_DEG.contains(&self.elevation_deg)) {
            return bad(
                "elevation (degrees)",
                self.elevation_deg.to_string(),
                format!("{ELEVATION_DEG:?}"),
            );
        }
        if !VIEWS.contains(&self.views) {
            return bad("views", self.views.to_string(), format!("{VIEWS:?}"));
        }
        Ok(())
    }

    /// Millimetres of the print per degree of visual angle at its centre.
    fn mm_per_degree(&self) -> f64 {
        self.distance_mm * 1f64.to_radians().tan()
    }

    /// The view `k`: the camera's basis (right, up, forward) and the lights, which keep
    /// their place relative to the viewer as the print is turned.
    fn view(&self, k: usize) -> ([f64; 3], [f64; 3], [f64; 3], Lighting) {
        let azimuth = VIEW_START_DEG + 360.0 * k as f64 / self.views as f64;
        let towards = |az: f64, el: f64| {
            let (az, el) = (az.to_radians(), el.to_radians());
            [el.cos() * az.sin(), -el.cos() * az.cos(), el.sin()]
        };
        let forward = towards(azimuth, self.elevation_deg).map(|c| -c);
        let right = normalize(cross(forward, [0.0, 0.0, 1.0]));
        let up = cross(right, forward);
        let lamps = LAMPS
            .iter()
            .map(|&(az, el, lux)| Light {
                towards: towards(azimuth + az, el),
                lux,
            })
            .collect();
        (
            right,
            up,
            forward,
            Lighting {
                lamps,
                sky_lux: SKY_LUX,
            },
        )
    }
}

/// The first view's azimuth, degrees clockwise from the front (−Y on the bed) seen from
/// above: the front-left corner, the three-quarter view a person takes first.
const VIEW_START_DEG: f64 = -45.0;

/// The lamps, relative to the viewer: (azimuth from the line of sight, degrees, negative
/// to the viewer's left; elevation, degrees; illuminance on a surface facing the lamp,
/// lux). A key lamp high on the left and a weaker fill low on the right; with the sky
/// light, about the 500 lux of a desk (EN 12464-1's figure for reading and writing).
const LAMPS: [(f64, f64, f64); 2] = [(-45.0, 45.0, 350.0), (60.0, 20.0, 100.0)];
const SKY_LUX: f64 = 150.0;

/// Reflectances: white PLA (diffuse, 0.8: a white plastic), the dark cloth under it (0.04,
/// black felt).
const PLA_ALBEDO: f64 = 0.8;
const CLOTH_ALBEDO: f64 = 0.04;

/// Octave levels of the reference's pyramid: at 120 pixels per degree the coarsest is
/// centred at 0.16 cycles per degree, the scale of the whole of a large print.
const LEVELS: usize = 8;

/// A print placed on the bed as sliced: the slicer centres the model's box on
/// `centre_xy` with its bottom at Z 0, and it is `height_mm` tall. A print and the
/// reference are aligned by these (the same model scaled), not by their beads.
#[derive(Clone, Copy)]
pub struct OnBed<'a> {
    pub print: &'a Print,
    pub centre_xy: [f64; 2],
    pub height_mm: f64,
}

#[derive(Debug, thiserror::Error)]
pub enum ObserveError {
    #[error("the {what} {value} is out of bounds ({range})")]
    Condition {
        what: &'static str,
        value: String,
        range: String,
    },
    #[error("the reference print has no visible line to look at")]
    EmptyReference,
    #[error("print {0} has no visible line to look at")]
    EmptyPrint(usize),
    #[error("print {index} is {height_mm} mm tall, taller than the reference ({reference_mm} mm); the observer compares smaller prints with a larger one")]
    Taller {
        index: usize,
        height_mm: f64,
        reference_mm: f64,
    },
    #[error("a print's height must be a positive number of mm, got {0}")]
    Height(f64),
    #[error("stopped")]
    Stopped,
}

/// Where each print of one view is drawn: the reference's framing, and each print's
/// picture of it.
struct Framing {
    reference: Camera,
    lighting: Lighting,
    ppd: f64,
}

/// The framing of view `k` for the reference: its picture centred on the middle of its
/// box, wide enough for the print in every direction it may reach (with a margin for a
/// print the enhancement made a little larger), each side a multiple of 2^[`LEVELS`].
fn framing(conditions: &Conditions, reference: &OnBed, k: usize) -> Option<Framing> {
    let (lo, hi) = reference.print.bounds()?;
    let (right, up, forward, lighting) = conditions.view(k);
    let centre = frame_centre(reference);
    let (mut hx, mut hy) = (0.0f64, 0.0f64);
    for i in 0..8 {
        let c: [f64; 3] = std::array::from_fn(|j| if i >> j & 1 == 1 { hi[j] } else { lo[j] });
        let d = sub(c, centre);
        hx = hx.max(dot(d, right).abs());
        hy = hy.max(dot(d, up).abs());
    }
    let ppd = conditions.pixels_per_degree;
    let px_per_mm = ppd / conditions.mm_per_degree();
    let unit = 1usize << LEVELS;
    let side = |half: f64| {
        let px = (2.0 * (half * 1.04 + 1.0) * px_per_mm).ceil() as usize;
        px.div_ceil(unit).max(1) * unit
    };
    Some(Framing {
        reference: Camera {
            centre,
            right,
            up,
            forward,
            px_per_mm,
            width: side(hx),
            height: side(hy),
        },
        lighting,
        ppd,
    })
}

/// The middle of a placed print's box: the point the framings of all prints share.
fn frame_centre(p: &OnBed) -> [f64; 3] {
    [p.centre_xy[0], p.centre_xy[1], 0.5 * p.height_mm]
}

/// The camera of `print` in `framing`: the reference's, scaled about the print's own
/// centre by the ratio of heights, its picture 2^m times coarser (m the largest that
/// keeps the print at or above the framing's pixels per degree). Returns it, m and the
/// print's pixels per degree.
fn print_camera(framing: &Framing, reference: &OnBed, print: &OnBed) -> (Camera, usize, f64) {
    let s = reference.height_mm / print.height_mm;
    let m = (s.log2().floor().max(0.0) as usize).min(LEVELS - 1);
    let r = &framing.reference;
    let camera = Camera {
        centre: frame_centre(print),
        px_per_mm: r.px_per_mm * s / f64::from(1u32 << m),
        width: r.width >> m,
        height: r.height >> m,
        ..*r
    };
    (camera, m, framing.ppd * s / f64::from(1u32 << m))
}

/// The luminance of the cloth, cd/m²: lit by the lamps at their elevations and the sky.
fn cloth_luminance(lighting: &Lighting) -> f32 {
    lighting.luminance(CLOTH_ALBEDO, [0.0, 0.0, 1.0]) as f32
}

/// Barten's X0 for a picture: the side of the square of the print's angular area.
fn field_deg(coverage: &pyramid::Plane, ppd: f64) -> f64 {
    let px: f64 = coverage.data.iter().map(|&c| f64::from(c)).sum();
    px.sqrt() / ppd
}

/// How alike each of `prints` looks to `reference` (docs/method.md, "The observer").
/// `stop` is asked between pictures: when it says so, the work ends with
/// [`ObserveError::Stopped`]. `progress` hears (view, print) as each is looked at (print
/// None: the reference). Blocking; uses the rayon pool.
pub fn observe(
    reference: &OnBed,
    prints: &[OnBed],
    conditions: &Conditions,
    stop: &dyn Fn() -> bool,
    progress: &mut dyn FnMut(usize, Option<usize>),
) -> Result<Vec<Resemblance>, ObserveError> {
    conditions.check()?;
    check_height(reference.height_mm)?;
    for (index, p) in prints.iter().enumerate() {
        check_height(p.height_mm)?;
        if p.height_mm > reference.height_mm * (1.0 + 1e-9) {
            return Err(ObserveError::Taller {
                index,
                height_mm: p.height_mm,
                reference_mm: reference.height_mm,
            });
        }
        if p.print.bounds().is_none() {
            return Err(ObserveError::EmptyPrint(index));
        }
    }
    // Per print, per band: the mean over the views of Σ d^β / area, lost and added.
    let mut sums = vec![vec![(0.0f64, 0.0f64); LEVELS]; prints.len()];
    let mut per_view = vec![Vec::with_capacity(conditions.views); prints.len()];
    let mut cpd = vec![vec![None; LEVELS]; prints.len()];
    let mut reference_cpd = vec![0.0; LEVELS];
    for k in 0..conditions.views {
        if stop() {
            return Err(ObserveError::Stopped);
        }
        progress(k, None);
        let framing = framing(conditions, reference, k).ok_or(ObserveError::EmptyReference)?;
        let background = cloth_luminance(&framing.lighting);
        let t = std::time::Instant::now();
        let seen = render::render(
            reference.print,
            &framing.reference,
            &framing.lighting,
            PLA_ALBEDO,
            background,
        );
        let perceived = compare::perceive(
            &seen.luminance,
            &seen.coverage,
            framing.ppd,
            field_deg(&seen.coverage, framing.ppd),
            LEVELS,
        );
        tracing::debug!(
            view = k,
            width = framing.reference.width,
            height = framing.reference.height,
            seconds = t.elapsed().as_secs_f64(),
            "the reference seen"
        );
        drop(seen);
        reference_cpd.clone_from(&perceived.cpd);
        for (i, print) in prints.iter().enumerate() {
            if stop() {
                return Err(ObserveError::Stopped);
            }
            progress(k, Some(i));
            let (camera, m, ppd) = print_camera(&framing, reference, print);
            let t = std::time::Instant::now();
            let seen = render::render(
                print.print,
                &camera,
                &framing.lighting,
                PLA_ALBEDO,
                background,
            );
            let rendered_s = t.elapsed().as_secs_f64();
            let mine = compare::perceive(
                &seen.luminance,
                &seen.coverage,
                ppd,
                field_deg(&seen.coverage, ppd),
                LEVELS - m,
            );
            let bands = compare::compare(&perceived, &mine, m);
            tracing::debug!(
                view = k,
                print = i,
                width = camera.width,
                height = camera.height,
                render_s = rendered_s,
                seconds = t.elapsed().as_secs_f64(),
                "a print seen and compared"
            );
            let mut view_total = 0.0;
            for (j, b) in bands.iter().enumerate() {
                let area = b.area.max(1.0);
                let share = 1.0 / conditions.views as f64;
                sums[i][j].0 += share * b.lost / area;
                sums[i][j].1 += share * b.added / area;
                view_total += (b.lost + b.added) / area;
                cpd[i][j] = j.checked_sub(m).and_then(|l| mine.cpd.get(l).copied());
            }
            per_view[i].push(view_total.powf(1.0 / eye::BETA));
        }
    }
    let root = |x: f64| x.powf(1.0 / eye::BETA);
    Ok(sums
        .iter()
        .enumerate()
        .map(|(i, bands)| {
            let lost: f64 = bands.iter().map(|b| b.0).sum();
            let added: f64 = bands.iter().map(|b| b.1).sum();
            let difference = root(lost + added);
            Resemblance {
                resemblance: 1.0 / (1.0 + difference),
                difference_jnd: difference,
                lost_jnd: root(lost),
                added_jnd: root(added),
                bands: bands
                    .iter()
                    .enumerate()
                    .map(|(j, b)| BandDifference {
                        reference_cpd: reference_cpd[j],
                        cpd: cpd[i][j],
                        lost_jnd: root(b.0),
                        added_jnd: root(b.1),
                    })
                    .collect(),
                views_jnd: per_view[i].clone(),
            }
        })
        .collect())
}

fn check_height(h: f64) -> Result<(), ObserveError> {
    if h.is_finite() && h > 0.0 {
        Ok(())
    } else {
        Err(ObserveError::Height(h))
    }
}

/// The views of `prints` as a person sees them, for a page or a report: one row per
/// print, one column per view, each picture at `px_per_mm` (the observer's own
/// resolution is `conditions.pixels_per_degree / (distance · tan 1°)`: the print at its
/// real size on the retina), each print framed as the observer frames it against
/// `reference`. The reference is drawn in the first row at the scale of the first print,
/// so like parts sit at like places. Luminance is shown relative to the brightest white
/// PLA can be under the scene's lights, in sRGB. None when the reference has no visible
/// line.
pub fn views_picture(
    reference: &OnBed,
    prints: &[OnBed],
    conditions: &Conditions,
    px_per_mm: f64,
) -> Option<Image> {
    let first = prints.first().unwrap_or(reference);
    let rows: Vec<&OnBed> = std::iter::once(reference).chain(prints).collect();
    let mut cells: Vec<Vec<Image>> = Vec::new();
    for (r, p) in rows.iter().enumerate() {
        let mut row = Vec::new();
        for k in 0..conditions.views {
            let framing = framing(conditions, reference, k)?;
            // Each row at the first print's size: the reference scaled down into it.
            let shown = if r == 0 { first } else { p };
            let s_shown = reference.height_mm / shown.height_mm;
            let s_drawn = reference.height_mm / p.height_mm;
            let scale = px_per_mm / framing.reference.px_per_mm;
            let r_cam = &framing.reference;
            let camera = Camera {
                centre: frame_centre(p),
                px_per_mm: px_per_mm * s_drawn / s_shown,
                width: ((r_cam.width as f64 * scale / s_shown).ceil() as usize).max(1),
                height: ((r_cam.height as f64 * scale / s_shown).ceil() as usize).max(1),
                ..*r_cam
            };
            let background = cloth_luminance(&framing.lighting);
            let seen = render::render(p.print, &camera, &framing.lighting, PLA_ALBEDO, background);
            row.push(to_srgb(
                &seen.luminance,
                brightest(&framing.lighting) as f32,
            ));
        }
        cells.push(row);
    }
    Some(sheet(&cells, SHEET_GAP_PX))
}

/// A bound on the luminance of white PLA under `lighting`, cd/m²: as if every lamp and
/// the whole sky lit it fully. The pictures show luminance relative to it, so nothing is
/// clipped.
fn brightest(lighting: &Lighting) -> f64 {
    let lux: f64 = lighting.lamps.iter().map(|l| l.lux).sum::<f64>() + lighting.sky_lux;
    PLA_ALBEDO / std::f64::consts::PI * lux
}

/// Luminance relative to `white`, clipped, in sRGB (opaque).
fn to_srgb(luminance: &pyramid::Plane, white: f32) -> Image {
    let encode = |v: f32| {
        let v = (v / white).clamp(0.0, 1.0);
        let s = if v <= 0.003_130_8 {
            12.92 * v
        } else {
            1.055 * v.powf(1.0 / 2.4) - 0.055
        };
        (s * 255.0).round() as u8
    };
    let mut rgba = Vec::with_capacity(4 * luminance.data.len());
    for &v in &luminance.data {
        let g = encode(v);
        rgba.extend([g, g, g, 255]);
    }
    Image {
        width: luminance.width as u32,
        height: luminance.height as u32,
        rgba,
    }
}

/// `cells` (rows of pictures) laid out on a grid with `gap` pixels between them, each
/// cell as large as the largest picture of its column and row.
fn sheet(cells: &[Vec<Image>], gap: u32) -> Image {
    let cols = cells.iter().map(Vec::len).max().unwrap_or(0);
    let col_w: Vec<u32> = (0..cols)
        .map(|c| {
            cells
                .iter()
                .filter_map(|r| r.get(c))
                .map(|i| i.width)
                .max()
                .unwrap_or(0)
        })
        .collect();
    let row_h: Vec<u32> = cells
        .iter()
        .map(|r| r.iter().map(|i| i.height).max().unwrap_or(0))
        .collect();
    let width = col_w.iter().sum::<u32>() + gap * cols.saturating_sub(1) as u32;
    let height = row_h.iter().sum::<u32>() + gap * cells.len().saturating_sub(1) as u32;
    let mut out = Image {
        width,
        height,
        rgba: vec![0; 4 * width as usize * height as usize],
    };
    let mut y = 0;
    for (r, row) in cells.iter().enumerate() {
        let mut x = 0;
        for (c, picture) in row.iter().enumerate() {
            let (ox, oy) = (
                x + (col_w[c] - picture.width) / 2,
                y + (row_h[r] - picture.height) / 2,
            );
            for py in 0..picture.height {
                let from = 4 * (py * picture.width) as usize;
                let to = 4 * ((oy + py) as usize * width as usize + ox as usize);
                let n = 4 * picture.width as usize;
                out.rgba[to..to + n].copy_from_slice(&picture.rgba[from..from + n]);
            }
            x += col_w[c] + gap;
        }
        y += row_h[r] + gap;
    }
    out
}

/// The scale, pixels per mm of `print`, at which [`views_picture`]'s row of views of it
/// (framed against `reference`) is `width` pixels across; 0 when the reference has no
/// visible line.
pub fn fit_px_per_mm(reference: &OnBed, print: &OnBed, conditions: &Conditions, width: u32) -> f64 {
    let s = reference.height_mm / print.height_mm;
    let across_mm: f64 = (0..conditions.views)
        .filter_map(|k| framing(conditions, reference, k))
        .map(|f| f.reference.width as f64 / f.reference.px_per_mm / s)
        .sum();
    let gaps = (SHEET_GAP_PX * conditions.views.saturating_sub(1) as u32) as f64;
    if across_mm > 0.0 {
        (f64::from(width) - gaps).max(1.0) / across_mm
    } else {
        0.0
    }
}

/// Pixels between the pictures of a sheet.
const SHEET_GAP_PX: u32 = 6;

/// The observer's own resolution for `conditions`, pixels per mm of the print: the scale
/// at which [`views_picture`] shows the prints at their real size on the retina.
pub fn real_size_px_per_mm(conditions: &Conditions) -> f64 {
    conditions.pixels_per_degree / conditions.mm_per_degree()
}
