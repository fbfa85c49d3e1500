//! Pictures of numbers and the octave pyramid the eye model reads them through: each
//! level half the previous one's resolution ([`reduce`]: the binomial low-pass
//! [1 5 10 10 5 1]/32, of even length so that a pixel of level j+1 is centred on the
//! 2 × 2 block of level j it stands for, and long enough to keep most of the band above
//! the new level's Nyquist frequency out of it), and back ([`expand`]: bilinear). A picture whose sides are multiples of 2^k has k levels
//! whose pixels tile it exactly, so two pictures of one framing at resolutions 2^m apart
//! share their levels pixel for pixel: level j of the finer is level j − m of the coarser.

use rayon::prelude::*;

/// A picture of `f32`, rows top to bottom.
#[derive(Clone, Debug, PartialEq)]
pub(crate) struct Plane {
    pub(crate) width: usize,
    pub(crate) height: usize,
    pub(crate) data: Vec<f32>,
}

impl Plane {
    pub(crate) fn filled(width: usize, height: usize, value: f32) -> Plane {
        Plane {
            width,
            height,
            data: vec![value; width * height],
        }
    }

    pub(crate) fn at(&self, x: usize, y: usize) -> f32 {
        self.data[y * self.width + x]
    }
}

/// Rows of this many pixels are one unit of work for the threads.
const ROWS_PER_TASK: usize = 16;

/// Half the resolution (each side rounded up), low-passed by [1 5 10 10 5 1]/32 in each
/// direction (its response cos⁵(πf): a quarter of what passes at f = 0.2 cycles per
/// pixel is left at 0.3, where it would fold back): sample i of the result is centred
/// between samples 2i and 2i + 1. Edges are extended by repeating the last sample.
pub(crate) fn reduce(p: &Plane) -> Plane {
    let (w, h) = (p.width, p.height);
    let (w2, h2) = (w.div_ceil(2), h.div_ceil(2));
    const K: [f32; 6] = [
        1.0 / 32.0,
        5.0 / 32.0,
        10.0 / 32.0,
        10.0 / 32.0,
        5.0 / 32.0,
        1.0 / 32.0,
    ];
    // Along rows first.
    let mut rows = vec![0.0f32; w2 * h];
    rows.par_chunks_mut(w2 * ROWS_PER_TASK)
        .enumerate()
        .for_each(|(task, out)| {
            for (r, out_row) in out.chunks_mut(w2).enumerate() {
                let row = &p.data[(task * ROWS_PER_TASK + r) * w..][..w];
                for (i, o) in out_row.iter_mut().enumerate() {
                    let at = |k: isize| row[(2 * i as isize + k).clamp(0, w as isize - 1) as usize];
                    *o = (0..6).map(|k| K[k] * at(k as isize - 2)).sum();
                }
            }
        });
    let mut out = vec![0.0f32; w2 * h2];
    out.par_chunks_mut(w2 * ROWS_PER_TASK)
        .enumerate()
        .for_each(|(task, chunk)| {
            for (r, out_row) in chunk.chunks_mut(w2).enumerate() {
                let y = task * ROWS_PER_TASK + r;
                let row = |k: isize| {
                    let yy = (2 * y as isize + k).clamp(0, h as isize - 1) as usize;
                    &rows[yy * w2..][..w2]
                };
                let taps: [&[f32]; 6] = std::array::from_fn(|k| row(k as isize - 2));
                for i in 0..w2 {
                    out_row[i] = (0..6).map(|k| K[k] * taps[k][i]).sum();
                }
            }
        });
    Plane {
        width: w2,
        height: h2,
        data: out,
    }
}

/// `p` brought up to `width` × `height` (twice its size, or one less where a side was
/// odd), bilinear: a sample of the result is 3/4 of the coarse sample it lies in and 1/4
/// of its nearer neighbour.
pub(crate) fn expand(p: &Plane, width: usize, height: usize) -> Plane {
    let (w, h) = (p.width, p.height);
    let tap = |i: usize, n: usize| -> (usize, usize) {
        let coarse = i / 2;
        let near = if i % 2 == 0 {
            coarse.saturating_sub(1)
        } else {
            (coarse + 1).min(n - 1)
        };
        (coarse, near)
    };
    let mut rows = vec![0.0f32; width * h];
    rows.par_chunks_mut(width * ROWS_PER_TASK)
        .enumerate()
        .for_each(|(task, out)| {
            for (r, out_row) in out.chunks_mut(width).enumerate() {
                let row = &p.data[(task * ROWS_PER_TASK + r) * w..][..w];
                for (x, o) in out_row.iter_mut().enumerate() {
                    let (c, n) = tap(x, w);
                    *o = 0.75 * row[c] + 0.25 * row[n];
                }
            }
        });
    let mut out = vec![0.0f32; width * height];
    out.par_chunks_mut(width * ROWS_PER_TASK)
        .enumerate()
        .for_each(|(task, chunk)| {
            for (r, out_row) in chunk.chunks_mut(width).enumerate() {
                let y = task * ROWS_PER_TASK + r;
                let (c, n) = tap(y, h);
                let (a, b) = (&rows[c * width..][..width], &rows[n * width..][..width]);
                for x in 0..width {
                    out_row[x] = 0.75 * a[x] + 0.25 * b[x];
                }
            }
        });
    Plane {
        width,
        height,
        data: out,
    }
}

/// Half the resolution, each pixel the largest of the 2 × 2 block it stands for: which
/// places of a level hold any of the object.
pub(crate) fn reduce_max(p: &Plane) -> Plane {
    let (w2, h2) = (p.width.div_ceil(2), p.height.div_ceil(2));
    let mut data = vec![0.0f32; w2 * h2];
    for y in 0..h2 {
        for x in 0..w2 {
            let mut m = f32::NEG_INFINITY;
            for (dx, dy) in [(0, 0), (1, 0), (0, 1), (1, 1)] {
                let (xx, yy) = (
                    (2 * x + dx).min(p.width - 1),
                    (2 * y + dy).min(p.height - 1),
                );
                m = m.max(p.at(xx, yy));
            }
            data[y * w2 + x] = m;
        }
    }
    Plane {
        width: w2,
        height: h2,
        data,
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn plane(w: usize, h: usize, f: impl Fn(usize, usize) -> f32) -> Plane {
        Plane {
            width: w,
            height: h,
            data: (0..w * h).map(|i| f(i % w, i / w)).collect(),
        }
    }

    #[test]
    fn a_constant_stays_constant_and_a_ramp_stays_a_ramp() {
        let c = plane(64, 40, |_, _| 3.5);
        let r = reduce(&c);
        assert_eq!((r.width, r.height), (32, 20));
        assert!(r.data.iter().all(|v| (v - 3.5).abs() < 1e-6));
        let e = expand(&r, 64, 40);
        assert!(e.data.iter().all(|v| (v - 3.5).abs() < 1e-6));
        // A ramp in x: level-1 pixel i stands for x = 2i + 0.5, and expanding back gives
        // the ramp again away from the edges (where the edge is repeated).
        let ramp = plane(64, 8, |x, _| x as f32);
        let r = reduce(&ramp);
        for i in 2..30 {
            assert!((r.at(i, 3) - (2.0 * i as f32 + 0.5)).abs() < 1e-4, "{i}");
        }
        let e = expand(&r, 64, 8);
        for x in 4..60 {
            assert!((e.at(x, 3) - x as f32).abs() < 1e-4, "{x}: {}", e.at(x, 3));
        }
    }

    /// Two framings 2^m apart share their levels: a picture drawn at twice the resolution
    /// (each coarse pixel's value in its 2 × 2 block) reduces onto the coarse one,
    /// where the pattern is smooth.
    #[test]
    fn levels_of_two_resolutions_line_up() {
        let f = |x: f32, y: f32| (0.05 * x).sin() + (0.03 * y).cos();
        let coarse = plane(64, 64, |x, y| f(x as f32 + 0.5, y as f32 + 0.5));
        let fine = plane(128, 128, |x, y| {
            f((x as f32 + 0.5) / 2.0, (y as f32 + 0.5) / 2.0)
        });
        let (a, b) = (reduce(&reduce(&fine)), reduce(&coarse));
        for y in 4..28 {
            for x in 4..28 {
                assert!((a.at(x, y) - b.at(x, y)).abs() < 0.01, "({x}, {y})");
            }
        }
    }

    #[test]
    fn odd_sides_and_tiny_planes() {
        let p = plane(5, 3, |x, y| (x + y) as f32);
        let r = reduce(&p);
        assert_eq!((r.width, r.height), (3, 2));
        let e = expand(&r, 5, 3);
        assert_eq!(e.data.len(), 15);
        let one = plane(1, 1, |_, _| 2.0);
        assert_eq!(reduce(&one).data, vec![2.0]);
        assert_eq!(expand(&one, 2, 2).data, vec![2.0; 4]);
        let m = reduce_max(&plane(4, 2, |x, _| if x == 3 { 1.0 } else { 0.0 }));
        assert_eq!(m.data, vec![0.0, 1.0]);
    }
}
