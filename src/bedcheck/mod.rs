//! The camera's bed check: is the bed as empty as in the picture a person confirmed
//! (the reference)? A fresh frame is compared with the reference over the bed's region,
//! in a way that holds under another light (a room at night and in the morning, daylight
//! from a window, a lamp), camera noise and JPEG artefacts, and a small shift of the
//! camera, but finds what a print leaves behind: a part, a purge line, a blob, a
//! spaghetti nest. No I/O and no clock: pictures in, a [`Verdict`] out.
//!
//! How, in order (each step is one module or function, the pixels' work done by the
//! `image` and `imageproc` crates where they have it):
//! 1. Both pictures are cropped to the region and brought to a working size whose longer
//!    side is at most [`WORK_MAX`] pixels (area averages: the noise halves with each
//!    halving of the size). The reference's part is done once ([`Reference::prepare`]).
//! 2. The camera's shift is found by correlating the two pictures' gradient magnitudes
//!    (edges move with the camera; their strength does not depend much on the light), at
//!    half size and then at the working size ([`align`]); up to [`MAX_SHIFT`] working
//!    pixels each way.
//! 3. The light is the frame's brightness over the reference's, per colour channel, as a
//!    smooth field over the region: a robust quadratic surface of the blocks' ratios with
//!    what it leaves out smoothed by a median of neighbouring blocks, so a lamp's
//!    fall-off or a window's gradient is followed but a part (a few blocks) is not
//!    ([`light`]). The frame is divided by it.
//! 4. Each frame pixel is compared with the reference's 3 × 3 pixels around its place (the
//!    smallest difference counts, so an edge that moved by a pixel is no difference), in
//!    each colour channel, and also by its gradient (an edge the reference lacks: a part
//!    of the bed's own colour shows by its sides and shadow).
//! 5. The thresholds, of brightness and of colour, are the picture's own noise: the spread
//!    of the plain differences over the whole region (a part is a small share of it),
//!    times a factor, with a floor for JPEG's artefacts. Pixels above them seed patches;
//!    pixels above half of them grow them (hysteresis), closed by a pixel so a spaghetti's
//!    strands make one nest. A picture whose noise puts the threshold of brightness over
//!    [`MAX_THRESHOLD`] is too dark to tell: never "clear".
//! 6. A patch with at least [`MIN_PATCH_PX`] pixels and [`MIN_SEED_PX`] seeds makes the bed
//!    not clear. The figures: the share of the region's pixels in patches, each patch's
//!    box in the picture's pixels, and its size in mm when the bed's size is known (the
//!    region's width taken as the bed's).
//!
//! The measured rates on the bed pictures in `tests/data/bed` and the time of one check
//! are in `benches/bedcheck.rs`; `tests/suite/bedcheck.rs` pins them.

mod align;
mod light;
mod mark;
mod planes;

pub use align::MAX_SHIFT;
pub use mark::marked_jpeg;
use planes::Planes;

use image::{GenericImageView, RgbImage};
use serde::{Deserialize, Serialize};

/// The working picture's longer side, pixels.
pub const WORK_MAX: u32 = 400;
/// A patch smaller than this many working pixels is noise, not an object.
pub const MIN_PATCH_PX: usize = 12;
/// Pixels over the full threshold a patch must hold.
pub const MIN_SEED_PX: usize = 4;
/// A frame or reference larger than this many pixels is not decoded (a lying header).
const MAX_PIXELS: u64 = 64 * 1024 * 1024;
/// The smallest region compared, working pixels each way.
const MIN_SIDE: u32 = 32;

/// The bed's region in the printer's picture, pixels: left, top, width, height.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
pub struct Region {
    pub x: u32,
    pub y: u32,
    pub w: u32,
    pub h: u32,
}

impl Region {
    /// `X,Y,W,H` as the command line writes it.
    pub fn parse(text: &str) -> Result<Region, String> {
        let parts: Vec<&str> = text.split(',').map(str::trim).collect();
        let numbers: Result<Vec<u32>, _> = parts.iter().map(|p| p.parse::<u32>()).collect();
        match numbers.as_deref() {
            Ok(&[x, y, w, h]) if w > 0 && h > 0 => Ok(Region { x, y, w, h }),
            _ => Err(format!(
                "{text:?}: give the region as X,Y,W,H in pixels (four whole numbers, W and H above 0)"
            )),
        }
    }

    /// The region inside a `width` × `height` picture: cut at its edges; an error when it
    /// lies outside or leaves too little.
    fn within(self, width: u32, height: u32) -> Result<Region, BedCheckError> {
        if self.x >= width || self.y >= height {
            return Err(BedCheckError::RegionOutside {
                region: self,
                width,
                height,
            });
        }
        let r = Region {
            w: self.w.min(width - self.x),
            h: self.h.min(height - self.y),
            ..self
        };
        if r.w < MIN_SIDE || r.h < MIN_SIDE {
            return Err(BedCheckError::RegionTooSmall(r));
        }
        Ok(r)
    }
}

impl std::fmt::Display for Region {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "{},{},{},{}", self.x, self.y, self.w, self.h)
    }
}

/// Why two pictures could not be compared.
#[derive(Debug, thiserror::Error)]
pub enum BedCheckError {
    #[error("the {what} is not a readable JPEG: {message}")]
    Decode { what: &'static str, message: String },
    #[error("the region {region} lies outside the {width}x{height} picture")]
    RegionOutside {
        region: Region,
        width: u32,
        height: u32,
    },
    #[error("the region {0} is too small to compare (at least {MIN_SIDE}x{MIN_SIDE} pixels)")]
    RegionTooSmall(Region),
    #[error(
        "the frame is {}x{}, the reference {}x{}: the camera's resolution or crop changed; take a new reference (`crispen clear PRINTER --reference` on an empty bed)",
        frame.0, frame.1, reference.0, reference.1
    )]
    SizeChanged {
        reference: (u32, u32),
        frame: (u32, u32),
    },
}

/// A patch of the bed that differs from the reference.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Patch {
    /// Its box in the picture's pixels.
    pub x: u32,
    pub y: u32,
    pub w: u32,
    pub h: u32,
    /// Its differing pixels, in the picture's pixels (about).
    pub area_px: u64,
    /// Its box's width and height in mm, when the bed's size is known.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub size_mm: Option<[f64; 2]>,
    /// How far it stands above the threshold: its largest difference over the threshold.
    pub strength: f64,
}

/// The check's answer, with its figures.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Verdict {
    pub clear: bool,
    /// The share of the region that differs (its pixels in patches), %.
    pub differs_percent: f64,
    /// The patches found, the largest first (empty when clear).
    pub patches: Vec<Patch>,
    /// The region compared, as cut to the picture.
    pub region: Region,
    /// The camera's shift found, picture pixels (x, y).
    pub shift_px: [f64; 2],
    /// The frame's light over the reference's (the median of the field).
    pub light: f64,
    /// The threshold of brightness, in 8-bit levels of difference after the light is
    /// corrected: the picture's noise times a factor.
    pub threshold: f64,
    /// The picture is too noisy (too dark) to tell: not clear, whatever was found (its
    /// threshold is above [`MAX_THRESHOLD`]).
    #[serde(default)]
    pub unsure: bool,
    /// How many mm one picture pixel is across the region (None: the bed's size unknown).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub mm_per_px: Option<f64>,
}

impl Verdict {
    /// The decision and its figures in one line ("clear: 0.3 % of the bed differs",
    /// "not clear: 6.1 % of the bed differs, largest patch 14 × 9 mm").
    pub fn summary(&self) -> String {
        if self.unsure && self.patches.is_empty() {
            return format!(
                "not clear: cannot tell, the picture is too dark or noisy (its noise threshold is {:.0} levels, at most {MAX_THRESHOLD:.0}): more light on the bed",
                self.threshold
            );
        }
        let word = if self.clear { "clear" } else { "not clear" };
        let mut text = format!("{word}: {:.1} % of the bed differs", self.differs_percent);
        if let Some(p) = self.patches.first() {
            match p.size_mm {
                Some([w, h]) => text += &format!(", largest patch {w:.0} × {h:.0} mm"),
                None => text += &format!(", largest patch {} × {} px", p.w, p.h),
            }
            if self.patches.len() > 1 {
                text += &format!(" ({} patches)", self.patches.len());
            }
        }
        text
    }
}

/// The gradient magnitude of a plane (Sobel, by imageproc), as f32.
fn gradient(plane: &[f32], w: usize, h: usize) -> Vec<f32> {
    let gray = image::GrayImage::from_fn(w as u32, h as u32, |x, y| {
        image::Luma([plane[y as usize * w + x as usize].clamp(0.0, 255.0) as u8])
    });
    imageproc::gradients::sobel_gradients(&gray)
        .into_raw()
        .into_iter()
        .map(f32::from)
        .collect()
}

/// The largest value of `plane` in each pixel's 3 × 3 neighbourhood.
fn max3(plane: &[f32], w: usize, h: usize) -> Vec<f32> {
    let mut out = vec![0f32; plane.len()];
    for y in 0..h {
        for x in 0..w {
            let mut m = f32::MIN;
            for yy in y.saturating_sub(1)..(y + 2).min(h) {
                for xx in x.saturating_sub(1)..(x + 2).min(w) {
                    m = m.max(plane[yy * w + xx]);
                }
            }
            out[y * w + x] = m;
        }
    }
    out
}

/// The empty bed as a person confirmed it, prepared once for every check against it.
#[derive(Debug, Clone)]
pub struct Reference {
    /// The whole picture's size.
    size: (u32, u32),
    region: Region,
    planes: Planes,
    /// Its gradient magnitude (of brightness), which the alignment correlates.
    grad: Vec<f32>,
    /// The largest gradient of brightness and of each colour difference in each pixel's
    /// 3 × 3 neighbourhood: where the picture has an edge, a difference of up to a pixel's
    /// worth of it is the edge moved, not something new.
    edges: [Vec<f32>; 3],
    bed_mm: Option<[f64; 2]>,
}

/// Decodes a JPEG (bounded in size) into RGB.
fn decode(jpeg: &[u8], what: &'static str) -> Result<RgbImage, BedCheckError> {
    let mut reader =
        image::ImageReader::with_format(std::io::Cursor::new(jpeg), image::ImageFormat::Jpeg);
    let mut limits = image::Limits::default();
    limits.max_alloc = Some(MAX_PIXELS * 4);
    reader.limits(limits);
    reader
        .decode()
        .map(|p| p.to_rgb8())
        .map_err(|e| BedCheckError::Decode {
            what,
            message: e.to_string(),
        })
}

/// The working size of a region: its longer side at most [`WORK_MAX`].
fn working_size(region: Region) -> (u32, u32) {
    let longer = region.w.max(region.h);
    if longer <= WORK_MAX {
        return (region.w, region.h);
    }
    let s = f64::from(WORK_MAX) / f64::from(longer);
    (
        ((f64::from(region.w) * s).round() as u32).max(1),
        ((f64::from(region.h) * s).round() as u32).max(1),
    )
}

impl Reference {
    /// The reference picture (a JPEG) prepared for checks over `region` (None: the whole
    /// picture). `bed_mm`: the bed's width and depth, for patch sizes in mm.
    pub fn prepare(
        jpeg: &[u8],
        region: Option<Region>,
        bed_mm: Option<[f64; 2]>,
    ) -> Result<Reference, BedCheckError> {
        Reference::of(&decode(jpeg, "reference")?, region, bed_mm)
    }

    /// [`Reference::prepare`] of a decoded picture.
    pub fn of(
        picture: &RgbImage,
        region: Option<Region>,
        bed_mm: Option<[f64; 2]>,
    ) -> Result<Reference, BedCheckError> {
        let (width, height) = picture.dimensions();
        let region = region
            .unwrap_or(Region {
                x: 0,
                y: 0,
                w: width,
                h: height,
            })
            .within(width, height)?;
        let (w, h) = working_size(region);
        let planes = Planes::of(&picture.view(region.x, region.y, region.w, region.h), w, h);
        let grad = gradient(&planes.luma, planes.w, planes.h);
        let n = planes.w * planes.h;
        let colour = |k: usize| -> Vec<f32> {
            // A colour difference brought to 0..255 for the gradient (it spans ±255).
            let plane: Vec<f32> = (0..n)
                .map(|i| {
                    128.0 + 0.5 * ycc([planes.rgb[0][i], planes.rgb[1][i], planes.rgb[2][i]])[k]
                })
                .collect();
            max3(&gradient(&plane, planes.w, planes.h), planes.w, planes.h)
                .into_iter()
                .map(|g| 2.0 * g)
                .collect()
        };
        let edges = [max3(&grad, planes.w, planes.h), colour(1), colour(2)];
        Ok(Reference {
            size: (width, height),
            region,
            planes,
            grad,
            edges,
            bed_mm,
        })
    }

    /// The region it is compared over.
    pub fn region(&self) -> Region {
        self.region
    }

    /// Working pixels per picture pixel.
    fn scale(&self) -> f64 {
        self.planes.w as f64 / f64::from(self.region.w)
    }

    /// Compares a frame (a JPEG of the same camera, crop and size) with the empty bed.
    pub fn check(&self, jpeg: &[u8]) -> Result<Verdict, BedCheckError> {
        self.check_picture(&decode(jpeg, "frame")?)
    }

    /// [`Reference::check`] of a decoded frame.
    pub fn check_picture(&self, frame: &RgbImage) -> Result<Verdict, BedCheckError> {
        if frame.dimensions() != self.size {
            return Err(BedCheckError::SizeChanged {
                reference: self.size,
                frame: frame.dimensions(),
            });
        }
        let reference = &self.planes;
        let (w, h) = (reference.w, reference.h);
        let planes = Planes::of(
            &frame.view(self.region.x, self.region.y, self.region.w, self.region.h),
            w as u32,
            h as u32,
        );
        let grad = gradient(&planes.luma, w, h);
        let shift = align::shift(&self.grad, &grad, w, h);
        let aligned = align::apply(&planes, &grad, shift);
        let field = light::field(reference, &aligned);
        let diff = difference(self, &aligned, &field);
        let scale = self.scale();
        let mm_per_px = self.bed_mm.map(|[bw, _]| bw / f64::from(self.region.w));
        let found = patches(&diff, w, h);
        let compared = diff.compared.max(1) as f64;
        let differing: usize = found.iter().map(|p| p.area).sum();
        let mut patches: Vec<Patch> = found
            .iter()
            .map(|p| {
                let to_px = |v: usize| (v as f64 / scale).round() as u32;
                let (x0, y0) = (to_px(p.x0), to_px(p.y0));
                let (x1, y1) = (to_px(p.x1 + 1), to_px(p.y1 + 1));
                let (pw, ph) = (x1.saturating_sub(x0).max(1), y1.saturating_sub(y0).max(1));
                Patch {
                    x: self.region.x + x0,
                    y: self.region.y + y0,
                    w: pw,
                    h: ph,
                    area_px: (p.area as f64 / (scale * scale)).round() as u64,
                    size_mm: mm_per_px.map(|m| [f64::from(pw) * m, f64::from(ph) * m]),
                    strength: f64::from(p.peak),
                }
            })
            .collect();
        patches.sort_by_key(|p| std::cmp::Reverse(p.area_px));
        let unsure = diff.threshold > MAX_THRESHOLD;
        Ok(Verdict {
            clear: patches.is_empty() && !unsure,
            unsure,
            differs_percent: 100.0 * differing as f64 / compared,
            patches,
            region: self.region,
            shift_px: [f64::from(shift.0) / scale, f64::from(shift.1) / scale],
            light: f64::from(field.median),
            threshold: f64::from(diff.threshold),
            mm_per_px,
        })
    }
}

/// Each working pixel's difference, in units of the threshold (above 1: a seed).
struct Difference {
    /// Per pixel; NaN where the frame has no pixel for it (the border a shift leaves).
    score: Vec<f32>,
    /// Pixels compared.
    compared: usize,
    /// The threshold in levels (see [`Verdict::threshold`]).
    threshold: f32,
}

/// How many times the noise a difference must be to count (the noise measured as the
/// spread of the plain differences: most of a bed is unchanged).
const NOISE_FACTOR: f32 = 4.5;
/// The least threshold of brightness, levels: JPEG's ringing at the bed's edges and the
/// grain of its sheet under a changed light stay below it.
const FLOOR: f32 = 10.0;
/// The least threshold of colour (each of the two colour differences), levels.
const COLOUR_FLOOR: f32 = 8.0;
/// Bands of the reference's brightness with a noise of their own (64 levels each).
const BANDS: usize = 4;
/// A band with fewer pixels than this takes the region's threshold.
const BAND_PIXELS: usize = 2000;
/// Sobel's magnitude of a ramp is 8 times its slope a pixel: a difference up to an
/// eighth of the reference's gradient nearby is its edge moved by a pixel.
const EDGE_SLACK: f32 = 1.0 / 8.0;
/// Above this threshold of brightness the picture is too noisy (too dark) to see a small
/// dark part on a dark bed: the check answers "not clear", unsure, rather than "clear".
pub const MAX_THRESHOLD: f32 = 24.0;
/// An edge must be this much stronger than the reference's strongest nearby to count.
const EDGE_FACTOR: f32 = 1.6;
/// A channel at or above this level is clipped: what it would be is not known.
const CLIPPED: f32 = 250.0;
/// Pixels this near the region's edge are not compared (the gradient there is the
/// crop's, not the picture's).
const MARGIN: usize = 2;

/// The spread of `values` as a normal's standard deviation (1.4826 × the median of the
/// absolute values: robust to the few pixels a part covers).
fn spread(values: &mut [f32]) -> f32 {
    if values.is_empty() {
        return 0.0;
    }
    let k = values.len() / 2;
    1.4826 * *values.select_nth_unstable_by(k, f32::total_cmp).1
}

/// Brightness and the two colour differences of an RGB pixel.
fn ycc([r, g, b]: [f32; 3]) -> [f32; 3] {
    let y = 0.299 * r + 0.587 * g + 0.114 * b;
    [y, b - y, r - y]
}

/// The frame's pixel `f` against the reference's `r` brought to the frame's light
/// (`gain`), in brightness and colour, in the reference's levels; a channel the light
/// clips in both is taken as equal.
fn apart(f: [f32; 3], r: [f32; 3], gain: [f32; 3], luma_gain: f32) -> [f32; 3] {
    let predicted: [f32; 3] = std::array::from_fn(|c| {
        let p = (r[c] * gain[c]).min(255.0);
        if f[c] >= CLIPPED && p >= CLIPPED {
            f[c]
        } else {
            p
        }
    });
    let (a, b) = (ycc(f), ycc(predicted));
    std::array::from_fn(|k| (a[k] - b[k]).abs() / luma_gain)
}

/// Compares the aligned frame with the reference brought to the frame's light (see the
/// module): each pixel's difference in brightness and colour, the smallest over the
/// reference's 3 × 3 pixels around it, over the threshold of each (its noise), and its
/// new edges.
fn difference(reference: &Reference, frame: &align::Aligned, field: &light::Field) -> Difference {
    let r = &reference.planes;
    let (w, h) = (r.w, r.h);
    let n = w * h;
    let rgb = |p: &Planes, i: usize| [p.rgb[0][i], p.rgb[1][i], p.rgb[2][i]];
    let compared = |i: usize| {
        let (x, y) = (i % w, i / w);
        frame.valid[i] && x >= MARGIN && y >= MARGIN && x + MARGIN < w && y + MARGIN < h
    };
    let luma_gain = |g: [f32; 3]| 0.299 * g[0] + 0.587 * g[1] + 0.114 * g[2];
    // The noise of each of brightness and colour, from the plain differences: over the
    // whole region, and over the pixels of each band of brightness (a camera's noise is
    // larger in the dark parts of its picture, after its gamma).
    let band = |i: usize| ((r.luma[i] / 64.0) as usize).min(BANDS - 1);
    let mut plain: [Vec<f32>; 3] = Default::default();
    let mut banded: [[Vec<f32>; 3]; BANDS] = Default::default();
    for i in (0..n).filter(|&i| compared(i)) {
        let g = field.at(i);
        let d = apart(rgb(&frame.planes, i), rgb(r, i), g, luma_gain(g));
        for k in 0..3 {
            plain[k].push(d[k]);
            banded[band(i)][k].push(d[k]);
        }
    }
    let floors = [FLOOR, COLOUR_FLOOR, COLOUR_FLOOR];
    let thresholds: [f32; 3] =
        std::array::from_fn(|k| (NOISE_FACTOR * spread(&mut plain[k])).max(floors[k]));
    // A band's own threshold where it has enough pixels to tell, never below the region's.
    let band_thresholds: [[f32; 3]; BANDS] = std::array::from_fn(|b| {
        std::array::from_fn(|k| {
            let values = &mut banded[b][k];
            if values.len() < BAND_PIXELS {
                thresholds[k]
            } else {
                (NOISE_FACTOR * spread(values)).max(thresholds[k])
            }
        })
    });
    // Sobel's magnitude of a step is 4 times its height, and on a flat, noisy bed about
    // 3.5 times the noise: an edge counts as a step of a threshold's height.
    let edge_threshold = 4.0 * thresholds[0];
    let mut score = vec![f32::NAN; n];
    let mut count = 0;
    for y in 0..h {
        for x in 0..w {
            let i = y * w + x;
            if !compared(i) {
                continue;
            }
            count += 1;
            let g = field.at(i);
            let lg = luma_gain(g);
            let f = rgb(&frame.planes, i);
            let thresholds = band_thresholds[band(i)];
            let mut best = f32::MAX;
            for yy in y - 1..=y + 1 {
                for xx in x - 1..=x + 1 {
                    let d = apart(f, rgb(r, yy * w + xx), g, lg);
                    let s = (0..3)
                        .map(|k| d[k] / (thresholds[k] + EDGE_SLACK * reference.edges[k][i]))
                        .fold(0f32, f32::max);
                    best = best.min(s);
                }
            }
            let edge = (frame.grad[i] / lg - EDGE_FACTOR * reference.edges[0][i]).max(0.0);
            score[i] = best.max(edge / edge_threshold);
        }
    }
    Difference {
        score,
        compared: count,
        threshold: thresholds[0],
    }
}

/// A patch in working pixels.
struct Found {
    x0: usize,
    y0: usize,
    x1: usize,
    y1: usize,
    area: usize,
    peak: f32,
}

/// The patches of `diff`: pixels over half the threshold, closed by one pixel and
/// labelled (imageproc), kept when big enough and seeded by pixels over the threshold.
fn patches(diff: &Difference, w: usize, h: usize) -> Vec<Found> {
    use imageproc::distance_transform::Norm;
    use imageproc::region_labelling::{connected_components, Connectivity};
    let weak = image::GrayImage::from_fn(w as u32, h as u32, |x, y| {
        let s = diff.score[y as usize * w + x as usize];
        image::Luma([if s >= 0.5 { 255 } else { 0 }])
    });
    let closed = imageproc::morphology::close(&weak, Norm::LInf, 1);
    let labels = connected_components(&closed, Connectivity::Eight, image::Luma([0u8]));
    let mut found: std::collections::HashMap<u32, (Found, usize)> = Default::default();
    for (x, y, label) in labels.enumerate_pixels() {
        let label = label.0[0];
        if label == 0 {
            continue;
        }
        let (x, y) = (x as usize, y as usize);
        let s = diff.score[y * w + x];
        let (p, seeds) = found.entry(label).or_insert((
            Found {
                x0: x,
                y0: y,
                x1: x,
                y1: y,
                area: 0,
                peak: 0.0,
            },
            0,
        ));
        p.x0 = p.x0.min(x);
        p.y0 = p.y0.min(y);
        p.x1 = p.x1.max(x);
        p.y1 = p.y1.max(y);
        if s >= 0.5 {
            p.area += 1;
        }
        if s >= 1.0 {
            *seeds += 1;
        }
        if s > p.peak {
            p.peak = s;
        }
    }
    found
        .into_values()
        .filter(|(p, seeds)| p.area >= MIN_PATCH_PX && *seeds >= MIN_SEED_PX)
        .map(|(p, _)| p)
        .collect()
}
