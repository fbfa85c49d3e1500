//! The camera's shift between the reference and a frame: the translation that best
//! correlates their gradient magnitudes (normalised, so a change of light does not move
//! it), searched at half size over [`MAX_SHIFT`] and refined by a pixel at the working
//! size; and the frame moved back by it.

use super::planes::Planes;

/// The largest camera shift found, working pixels each way (2.5 % of the region's
/// longer side).
pub const MAX_SHIFT: i32 = 10;

/// Working pixels (x, y) by which the frame's content lies further than the reference's.
pub(super) type Shift = (i32, i32);

/// The frame's planes and gradient moved back by the shift, and which pixels it has.
pub(super) struct Aligned {
    pub planes: Planes,
    pub grad: Vec<f32>,
    /// The frame has a pixel here (not in the border the shift leaves).
    pub valid: Vec<bool>,
}

/// Normalised correlation of `a` at (x, y) with `b` at (x + dx, y + dy), over the pixels
/// at least `margin` from every edge of `a` (the same pixels whatever the shift), every
/// `step`-th row and column.
fn correlation(
    a: &[f32],
    b: &[f32],
    w: usize,
    h: usize,
    (dx, dy): Shift,
    margin: usize,
    step: usize,
) -> f64 {
    let (mut sa, mut sb, mut saa, mut sbb, mut sab, mut n) = (0.0, 0.0, 0.0, 0.0, 0.0, 0.0);
    for y in (margin..h.saturating_sub(margin)).step_by(step) {
        let yb = (y as i32 + dy) as usize;
        for x in (margin..w.saturating_sub(margin)).step_by(step) {
            let xb = (x as i32 + dx) as usize;
            let (va, vb) = (f64::from(a[y * w + x]), f64::from(b[yb * w + xb]));
            sa += va;
            sb += vb;
            saa += va * va;
            sbb += vb * vb;
            sab += va * vb;
            n += 1.0;
        }
    }
    if n < 1.0 {
        return 0.0;
    }
    let cov = sab - sa * sb / n;
    let var = (saa - sa * sa / n) * (sbb - sb * sb / n);
    if var <= 0.0 {
        0.0
    } else {
        cov / var.sqrt()
    }
}

/// The best of the shifts `candidates` for `a` against `b` (the first among equals).
fn best(
    a: &[f32],
    b: &[f32],
    w: usize,
    h: usize,
    candidates: impl Iterator<Item = Shift>,
    margin: usize,
    step: usize,
) -> Shift {
    let mut best = ((0, 0), f64::MIN);
    for s in candidates {
        let c = correlation(a, b, w, h, s, margin, step);
        if c > best.1 {
            best = (s, c);
        }
    }
    best.0
}

/// Halves a plane by 2 × 2 averages (a coarse look for the search).
fn half(plane: &[f32], w: usize, h: usize) -> (Vec<f32>, usize, usize) {
    let image = image::ImageBuffer::<image::Luma<f32>, Vec<f32>>::from_raw(
        w as u32,
        h as u32,
        plane.to_vec(),
    )
    .expect("a plane holds its pixels");
    let (hw, hh) = ((w / 2).max(1), (h / 2).max(1));
    let small = image::imageops::thumbnail(&image, hw as u32, hh as u32);
    (small.into_raw(), hw, hh)
}

/// The camera's shift from `reference`'s gradient to `frame`'s (same size).
pub(super) fn shift(reference: &[f32], frame: &[f32], w: usize, h: usize) -> Shift {
    let reach = MAX_SHIFT / 2;
    let (ra, hw, hh) = half(reference, w, h);
    let (fa, _, _) = half(frame, w, h);
    let around = |r: i32, c: Shift| {
        (-r..=r).flat_map(move |dy| (-r..=r).map(move |dx| (c.0 + dx, c.1 + dy)))
    };
    let coarse = best(
        &ra,
        &fa,
        hw,
        hh,
        around(reach, (0, 0)),
        reach as usize + 1,
        1,
    );
    let fine = best(
        reference,
        frame,
        w,
        h,
        around(1, (coarse.0 * 2, coarse.1 * 2)),
        MAX_SHIFT as usize + 2,
        1,
    );
    (
        fine.0.clamp(-MAX_SHIFT, MAX_SHIFT),
        fine.1.clamp(-MAX_SHIFT, MAX_SHIFT),
    )
}

/// The frame moved back by `shift`: pixel (x, y) is the frame's (x + dx, y + dy).
pub(super) fn apply(frame: &Planes, grad: &[f32], (dx, dy): Shift) -> Aligned {
    let (w, h) = (frame.w, frame.h);
    let n = w * h;
    let mut planes = Planes {
        w,
        h,
        rgb: [vec![0f32; n], vec![0f32; n], vec![0f32; n]],
        luma: vec![0f32; n],
    };
    let mut moved = vec![0f32; n];
    let mut valid = vec![false; n];
    for y in 0..h {
        let ys = y as i32 + dy;
        if ys < 0 || ys >= h as i32 {
            continue;
        }
        for x in 0..w {
            let xs = x as i32 + dx;
            if xs < 0 || xs >= w as i32 {
                continue;
            }
            let (i, j) = (y * w + x, ys as usize * w + xs as usize);
            for c in 0..3 {
                planes.rgb[c][i] = frame.rgb[c][j];
            }
            planes.luma[i] = frame.luma[j];
            moved[i] = grad[j];
            // Sobel's border and the pixel beside it are not the picture's edges.
            valid[i] = x > 0 && y > 0 && x + 1 < w && y + 1 < h;
        }
    }
    Aligned {
        planes,
        grad: moved,
        valid,
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A pattern moved by (3, -2) is found moved by (3, -2), under a light twice as bright.
    #[test]
    fn finds_a_shift_whatever_the_light() {
        let (w, h) = (120, 80);
        let pattern = |x: i32, y: i32| {
            let (x, y) = (x as f32, y as f32);
            ((x * 0.31).sin() * (y * 0.17).cos() * 40.0 + ((x + y) * 0.05).sin() * 30.0).abs()
        };
        let a: Vec<f32> = (0..h)
            .flat_map(|y| (0..w).map(move |x| pattern(x, y)))
            .collect();
        let b: Vec<f32> = (0..h)
            .flat_map(|y| (0..w).map(move |x| 2.0 * pattern(x - 3, y + 2)))
            .collect();
        assert_eq!(shift(&a, &b, w as usize, h as usize), (3, -2));
        assert_eq!(shift(&a, &a, w as usize, h as usize), (0, 0));
    }
}
