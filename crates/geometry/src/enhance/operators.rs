//! Spec step 2: the cotangent Laplacian L and the Voronoi-mixed lumped mass M, on the
//! normalised vertices, stored the way the solver wants them: the lower triangle
//! (diagonal first in each column, rows ascending) of the shared sparsity pattern of
//! `M − δL`, with the off-diagonal cotangent weights kept separately so the matrix for
//! any δ is one pass over the values.
//!
//! Cotangents are clamped to ±[`COT_BOUND`]: a cotangent of 1e5 means an angle of
//! about 1e-5 rad (0.0006°), far thinner than any triangle a printer can resolve, and
//! the bound keeps `M − δL` well enough conditioned for a Cholesky factorisation in
//! f64 (δ·1e5 ≤ 10 against masses of order 1/n). Non-degenerate meshes never hit it;
//! the bunny's largest |cot| is about 60.

use rayon::prelude::*;

/// Bound on |cot θ| (see the module documentation).
pub const COT_BOUND: f64 = 1e5;

/// The operators of one mesh. `L_ij = weight` for i ≠ j (the sum of the halved
/// cotangents of the angles opposite edge ij), `L_ii = −weight_sum[i]`.
pub struct Operators {
    pub n: usize,
    /// CSC lower-triangular pattern of `M − δL`: column j holds j itself, then its
    /// neighbours i > j in ascending order.
    pub col_ptr: Vec<usize>,
    pub row_idx: Vec<usize>,
    /// Off-diagonal `L_ij` per stored entry (0 for the diagonal entries).
    pub weight: Vec<f64>,
    /// `Σ_j L_ij` over i's neighbours, i.e. `−L_ii`.
    pub weight_sum: Vec<f64>,
    /// Diagonal of M.
    pub mass: Vec<f64>,
    /// Number of cotangents that hit the bound.
    pub clamped_cotangents: usize,
}

/// Per-face terms: the halved cotangent opposite each corner's edge and each corner's
/// mixed Voronoi area.
struct FaceTerms {
    half_cot: [f64; 3],
    area: [f64; 3],
    clamped: u8,
}

fn sub(a: [f64; 3], b: [f64; 3]) -> [f64; 3] {
    [a[0] - b[0], a[1] - b[1], a[2] - b[2]]
}
fn dot(a: [f64; 3], b: [f64; 3]) -> f64 {
    a[0] * b[0] + a[1] * b[1] + a[2] * b[2]
}
fn cross_norm(a: [f64; 3], b: [f64; 3]) -> f64 {
    let c = [
        a[1] * b[2] - a[2] * b[1],
        a[2] * b[0] - a[0] * b[2],
        a[0] * b[1] - a[1] * b[0],
    ];
    dot(c, c).sqrt()
}

fn face_terms(p: [[f64; 3]; 3]) -> FaceTerms {
    // Corner k's angle is between the edges to the other two corners; the edge opposite
    // corner k joins corners k+1 and k+2.
    let mut cot = [0.0; 3];
    let mut edge_sq = [0.0; 3]; // squared length of the edge opposite corner k
    let mut corner_dot = [0.0; 3];
    let double_area = cross_norm(sub(p[1], p[0]), sub(p[2], p[0]));
    let mut clamped = 0u8;
    for k in 0..3 {
        let a = sub(p[(k + 1) % 3], p[k]);
        let b = sub(p[(k + 2) % 3], p[k]);
        corner_dot[k] = dot(a, b);
        let e = sub(p[(k + 2) % 3], p[(k + 1) % 3]);
        edge_sq[k] = dot(e, e);
        // cot θ = cos/sin = (a·b) / |a×b|; |a×b| is the same for every corner.
        let c = corner_dot[k] / double_area;
        cot[k] = if c.is_nan() {
            0.0
        } else if c.abs() > COT_BOUND {
            clamped += 1;
            COT_BOUND.copysign(c)
        } else {
            c
        };
    }
    let area = double_area / 2.0;
    let obtuse = (0..3).find(|&k| corner_dot[k] < 0.0);
    let corner_area = match obtuse {
        Some(o) => std::array::from_fn(|k| if k == o { area / 2.0 } else { area / 4.0 }),
        // Voronoi area of corner k: its two edges are opposite corners k+1 and k+2.
        None => std::array::from_fn(|k| {
            let (j, l) = ((k + 1) % 3, (k + 2) % 3);
            (edge_sq[j] * cot[j] + edge_sq[l] * cot[l]) / 8.0
        }),
    };
    FaceTerms {
        half_cot: cot.map(|c| c / 2.0),
        area: corner_area,
        clamped,
    }
}

impl Operators {
    /// Builds L and M for `vertices` (already normalised) and `faces` (indices valid).
    /// Vertices no face touches get mass 1 and no neighbours, so they stay where they are.
    pub fn build(vertices: &[[f64; 3]], faces: &[[u32; 3]]) -> Operators {
        let n = vertices.len();
        // The per-face trigonometry is the costly part and is independent per face.
        let terms: Vec<FaceTerms> = faces
            .par_iter()
            .with_min_len(4096)
            .map(|f| face_terms(f.map(|i| vertices[i as usize])))
            .collect();

        let mut mass = vec![0.0; n];
        let mut clamped_cotangents = 0usize;
        // Bucket each edge's weight under its smaller endpoint (its column in the lower
        // triangle): counting pass, then fill.
        let mut count = vec![0usize; n + 1];
        for f in faces {
            for k in 0..3 {
                let (a, b) = (f[(k + 1) % 3], f[(k + 2) % 3]);
                count[a.min(b) as usize + 1] += 1;
            }
        }
        for j in 0..n {
            count[j + 1] += count[j];
        }
        let mut cursor = count.clone();
        let mut bucket_row = vec![0u32; count[n]];
        let mut bucket_w = vec![0.0f64; count[n]];
        for (f, t) in faces.iter().zip(&terms) {
            clamped_cotangents += t.clamped as usize;
            for k in 0..3 {
                mass[f[k] as usize] += t.area[k];
                let (a, b) = (f[(k + 1) % 3], f[(k + 2) % 3]);
                let col = a.min(b) as usize;
                bucket_row[cursor[col]] = a.max(b);
                bucket_w[cursor[col]] = t.half_cot[k];
                cursor[col] += 1;
            }
        }
        drop(terms);
        drop(cursor);

        // Per column: sort by row, merge the two half-edges of each interior edge.
        let mut col_ptr = Vec::with_capacity(n + 1);
        let mut row_idx = Vec::with_capacity(n + count[n] / 2 + n);
        let mut weight = Vec::with_capacity(row_idx.capacity());
        let mut weight_sum = vec![0.0; n];
        let mut scratch: Vec<(u32, f64)> = Vec::new();
        col_ptr.push(0);
        for j in 0..n {
            row_idx.push(j);
            weight.push(0.0);
            scratch.clear();
            scratch.extend(
                bucket_row[count[j]..count[j + 1]]
                    .iter()
                    .copied()
                    .zip(bucket_w[count[j]..count[j + 1]].iter().copied()),
            );
            scratch.sort_unstable_by_key(|&(r, _)| r);
            let mut k = 0;
            while k < scratch.len() {
                let row = scratch[k].0;
                let mut w = 0.0;
                while k < scratch.len() && scratch[k].0 == row {
                    w += scratch[k].1;
                    k += 1;
                }
                row_idx.push(row as usize);
                weight.push(w);
                weight_sum[j] += w;
                weight_sum[row as usize] += w;
            }
            col_ptr.push(row_idx.len());
        }
        for m in &mut mass {
            if *m == 0.0 {
                *m = 1.0;
            }
        }
        Operators {
            n,
            col_ptr,
            row_idx,
            weight,
            weight_sum,
            mass,
            clamped_cotangents,
        }
    }

    /// The stored (lower-triangle) values of `M − δL`.
    pub(crate) fn system_values(&self, delta: f64) -> Vec<f64> {
        let mut values = Vec::with_capacity(self.row_idx.len());
        for j in 0..self.n {
            let range = self.col_ptr[j]..self.col_ptr[j + 1];
            values.push(self.mass[j] + delta * self.weight_sum[j]);
            values.extend(
                self.weight[range.start + 1..range.end]
                    .iter()
                    .map(|w| -delta * w),
            );
        }
        values
    }

    /// `y = A x` for the symmetric matrix whose lower triangle is `values`; `x`, `y` are
    /// n×3 row-major.
    pub(crate) fn sym_matvec(&self, values: &[f64], x: &[[f64; 3]], y: &mut [[f64; 3]]) {
        y.iter_mut().for_each(|r| *r = [0.0; 3]);
        for j in 0..self.n {
            let range = self.col_ptr[j]..self.col_ptr[j + 1];
            let d = values[range.start];
            for c in 0..3 {
                y[j][c] += d * x[j][c];
            }
            for e in range.start + 1..range.end {
                let i = self.row_idx[e];
                let a = values[e];
                for c in 0..3 {
                    y[i][c] += a * x[j][c];
                    y[j][c] += a * x[i][c];
                }
            }
        }
    }

    /// `L x` for n×3 row-major `x` (used by tests and diagnostics).
    pub fn laplacian_apply(&self, x: &[[f64; 3]]) -> Vec<[f64; 3]> {
        let mut y: Vec<[f64; 3]> = (0..self.n)
            .map(|i| x[i].map(|c| -self.weight_sum[i] * c))
            .collect();
        for j in 0..self.n {
            for e in self.col_ptr[j] + 1..self.col_ptr[j + 1] {
                let i = self.row_idx[e];
                let w = self.weight[e];
                for c in 0..3 {
                    y[i][c] += w * x[j][c];
                    y[j][c] += w * x[i][c];
                }
            }
        }
        y
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn equilateral_triangle_terms() {
        let h = 3f64.sqrt() / 2.0;
        let t = face_terms([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.5, h, 0.0]]);
        let cot60 = 1.0 / 3f64.sqrt();
        for k in 0..3 {
            assert!((t.half_cot[k] - cot60 / 2.0).abs() < 1e-15);
            // Each corner of an equilateral triangle gets a third of its area.
            assert!((t.area[k] - (h / 2.0) / 3.0).abs() < 1e-15);
        }
    }

    #[test]
    fn obtuse_triangle_gets_mixed_areas() {
        let t = face_terms([[0.0, 0.0, 0.0], [2.0, 0.0, 0.0], [1.0, 0.2, 0.0]]);
        let area = 0.2;
        assert!((t.area[2] - area / 2.0).abs() < 1e-15);
        assert!((t.area[0] - area / 4.0).abs() < 1e-15);
        assert!((t.area[1] - area / 4.0).abs() < 1e-15);
    }

    #[test]
    fn sliver_cotangents_are_clamped() {
        let t = face_terms([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.5, 1e-9, 0.0]]);
        assert_eq!(t.clamped, 3);
        assert!(t.half_cot.iter().all(|c| c.abs() <= COT_BOUND / 2.0));
    }
}
