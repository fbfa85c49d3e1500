//! The light: how much brighter the frame is than the reference, per colour channel, as a
//! smooth field over the region. The region is cut into blocks; each block's ratio of
//! means (in logarithms) is fitted by a quadratic surface, robustly (iteratively
//! reweighted least squares with Tukey's weights, solved by faer's QR), so the blocks a
//! part covers count for nothing; what the surface leaves out of a lamp's fall-off is
//! added back as the median of the 5 × 5 neighbouring blocks' residuals, which a part of a
//! few blocks does not move. Each pixel's gain is the field interpolated between the
//! blocks' centres.

use super::align::Aligned;
use super::planes::Planes;
use faer::linalg::solvers::SolveLstsq;
use faer::Mat;

/// A block's side, working pixels.
const BLOCK: usize = 24;
/// A block darker than this in the reference (levels) says nothing of the light: its
/// ratio is noise.
const DARK: f64 = 8.0;
/// Tukey's constant (95 % efficiency at the normal).
const TUKEY: f64 = 4.685;

/// Each working pixel's gain per channel (frame over reference).
pub(super) struct Field {
    gains: [Vec<f32>; 3],
    /// The median gain of the blocks (luminance), the frame's light over the reference's.
    pub median: f32,
}

impl Field {
    pub(super) fn at(&self, i: usize) -> [f32; 3] {
        [self.gains[0][i], self.gains[1][i], self.gains[2][i]]
    }
}

fn median(values: &mut [f64]) -> f64 {
    if values.is_empty() {
        return 0.0;
    }
    let k = values.len() / 2;
    *values.select_nth_unstable_by(k, f64::total_cmp).1
}

/// The quadratic surface's terms at (u, v), both in [-1, 1].
fn terms(u: f64, v: f64) -> [f64; 6] {
    [1.0, u, v, u * u, u * v, v * v]
}

/// A robust quadratic fit of `values` (None: no data) at the blocks' places `at`.
fn robust_quadratic(values: &[Option<f64>], at: &[(f64, f64)]) -> Vec<f64> {
    let known: Vec<usize> = (0..values.len()).filter(|&i| values[i].is_some()).collect();
    if known.len() < 12 {
        // Too few blocks for a surface: one gain for all.
        let mut v: Vec<f64> = known.iter().filter_map(|&i| values[i]).collect();
        let m = median(&mut v);
        return vec![m; values.len()];
    }
    let mut weights = vec![1.0; known.len()];
    let mut coef = [0.0; 6];
    for _ in 0..6 {
        let a = Mat::<f64>::from_fn(known.len(), 6, |r, c| {
            let (u, v) = at[known[r]];
            terms(u, v)[c] * weights[r]
        });
        let b = Mat::<f64>::from_fn(known.len(), 1, |r, _| {
            values[known[r]].unwrap_or(0.0) * weights[r]
        });
        let x = a.qr().solve_lstsq(&b);
        for (c, v) in coef.iter_mut().enumerate() {
            *v = x[(c, 0)];
        }
        let residuals: Vec<f64> = known
            .iter()
            .map(|&i| {
                let (u, v) = at[i];
                let fit: f64 = terms(u, v).iter().zip(&coef).map(|(t, c)| t * c).sum();
                values[i].unwrap_or(0.0) - fit
            })
            .collect();
        let mut abs: Vec<f64> = residuals.iter().map(|r| r.abs()).collect();
        let scale = (1.4826 * median(&mut abs)).max(0.01);
        for (w, r) in weights.iter_mut().zip(&residuals) {
            let t = r / (TUKEY * scale);
            // The square root of Tukey's weight: the rows are scaled by it.
            *w = if t.abs() < 1.0 { 1.0 - t * t } else { 0.0 };
        }
    }
    at.iter()
        .map(|&(u, v)| terms(u, v).iter().zip(&coef).map(|(t, c)| t * c).sum())
        .collect()
}

/// The gain field of `frame` (aligned) over `reference`.
pub(super) fn field(reference: &Planes, frame: &Aligned) -> Field {
    let (w, h) = (reference.w, reference.h);
    let (gw, gh) = (w.div_ceil(BLOCK), h.div_ceil(BLOCK));
    let nb = gw * gh;
    // Block sums of both pictures over the pixels the frame has.
    let mut sums = vec![[0.0f64; 7]; nb];
    for y in 0..h {
        for x in 0..w {
            let i = y * w + x;
            if !frame.valid[i] {
                continue;
            }
            let s = &mut sums[(y / BLOCK) * gw + x / BLOCK];
            for c in 0..3 {
                s[c] += f64::from(reference.rgb[c][i]);
                s[3 + c] += f64::from(frame.planes.rgb[c][i]);
            }
            s[6] += 1.0;
        }
    }
    let at: Vec<(f64, f64)> = (0..nb)
        .map(|b| {
            let (bx, by) = (b % gw, b / gw);
            let u = if gw > 1 {
                2.0 * bx as f64 / (gw - 1) as f64 - 1.0
            } else {
                0.0
            };
            let v = if gh > 1 {
                2.0 * by as f64 / (gh - 1) as f64 - 1.0
            } else {
                0.0
            };
            (u, v)
        })
        .collect();
    let mut logs: [Vec<f64>; 3] = Default::default();
    for c in 0..3 {
        let ratios: Vec<Option<f64>> = sums
            .iter()
            .map(|s| {
                let (frame, reference) = (s[3 + c] / s[6].max(1.0), s[c] / s[6].max(1.0));
                (s[6] >= (BLOCK * BLOCK / 4) as f64 && reference >= DARK && frame > 0.0)
                    .then(|| (frame / reference).ln())
            })
            .collect();
        let surface = robust_quadratic(&ratios, &at);
        // What the surface leaves out, as the neighbours' median.
        let residual: Vec<Option<f64>> = ratios
            .iter()
            .zip(&surface)
            .map(|(r, s)| r.map(|r| r - s))
            .collect();
        logs[c] = (0..nb)
            .map(|b| {
                let (bx, by) = ((b % gw) as i64, (b / gw) as i64);
                let mut near: Vec<f64> = Vec::with_capacity(25);
                for ny in (by - 2).max(0)..(by + 3).min(gh as i64) {
                    for nx in (bx - 2).max(0)..(bx + 3).min(gw as i64) {
                        if let Some(r) = residual[ny as usize * gw + nx as usize] {
                            near.push(r);
                        }
                    }
                }
                surface[b] + median(&mut near)
            })
            .collect();
    }
    let mut lumas: Vec<f64> = (0..nb)
        .map(|b| (0.299 * logs[0][b] + 0.587 * logs[1][b] + 0.114 * logs[2][b]).exp())
        .collect();
    let median_gain = median(&mut lumas) as f32;
    // Each pixel between the four nearest blocks' centres.
    let gains = std::array::from_fn(|c| {
        let block: Vec<f32> = logs[c].iter().map(|l| l.exp() as f32).collect();
        let mut out = vec![1f32; w * h];
        for y in 0..h {
            let fy = ((y as f32 + 0.5) / BLOCK as f32 - 0.5).clamp(0.0, (gh - 1) as f32);
            let (y0, ty) = (fy.floor() as usize, fy.fract());
            let y1 = (y0 + 1).min(gh - 1);
            for x in 0..w {
                let fx = ((x as f32 + 0.5) / BLOCK as f32 - 0.5).clamp(0.0, (gw - 1) as f32);
                let (x0, tx) = (fx.floor() as usize, fx.fract());
                let x1 = (x0 + 1).min(gw - 1);
                let top = block[y0 * gw + x0] * (1.0 - tx) + block[y0 * gw + x1] * tx;
                let bottom = block[y1 * gw + x0] * (1.0 - tx) + block[y1 * gw + x1] * tx;
                out[y * w + x] = top * (1.0 - ty) + bottom * ty;
            }
        }
        out
    });
    Field {
        gains,
        median: median_gain,
    }
}
