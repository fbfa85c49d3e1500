//! Spec steps 1–7 split the way the spec's "interactive use" asks: [`Bands::compute`]
//! does the expensive, mesh-only part once (normalise, operators, the three solves of
//! [`super::solve`], bands); [`Bands::combine`] is a few vector operations per vertex for
//! any λ1, λ2 and μ.

use super::operators::Operators;
use super::solve::{self, Problem, Solver};
use super::{EnhanceError, EnhanceOptions, Phase, PhaseTimings};
use crate::mesh::Mesh;
use rayon::prelude::*;
use std::time::Instant;

/// The frequency bands of one mesh, in unit-sphere units.
#[derive(Clone, Debug)]
pub struct Bands {
    /// Normalisation: V0 = (V − center) / radius.
    pub center: [f64; 3],
    pub radius: f64,
    v0: Vec<[f64; 3]>,
    v_delta2: Vec<[f64; 3]>,
    delta1: Vec<[f64; 3]>,
    delta2: Vec<[f64; 3]>,
    /// ‖Δ3_i‖² per vertex, and its maximum (the μ rule's denominator).
    delta3_sq: Vec<f64>,
    max_delta3_sq: f64,
    /// Each vertex's lumped (Voronoi-mixed) area, unit-sphere units.
    area: Vec<f64>,
    /// The three δ the bands were made with.
    pub deltas: [f64; 3],
    /// Relative residual ‖(M − δL)V − MV0‖ / ‖MV0‖ of each solve (worst of x, y, z).
    pub residuals: [f64; 3],
    /// Cotangents that hit [`super::operators::COT_BOUND`].
    pub clamped_cotangents: usize,
    /// Seconds spent in operators, factorisation (symbolic + numeric) and solves.
    pub timings: PhaseTimings,
}

/// A combination of the bands, mapped back to input units.
#[derive(Clone, Debug)]
pub struct Combined {
    pub vertices: Vec<[f64; 3]>,
    pub mu: f64,
    pub w_min: f64,
    pub w_mean: f64,
    /// Distance each vertex moved, in input units: largest and mean.
    pub max_displacement: f64,
    pub mean_displacement: f64,
    /// Distance each vertex moved, input units.
    pub(crate) moved: Vec<f64>,
}

impl Bands {
    /// Spec steps 1–4. Fails on a mesh the method cannot run on (no faces, bad indices,
    /// non-finite coordinates, zero size) or when the solver fails.
    pub fn compute(mesh: &Mesh, progress: &mut dyn FnMut(Phase)) -> Result<Bands, EnhanceError> {
        Self::compute_with(mesh, Solver::Auto, progress)
    }

    /// [`Bands::compute`] with a chosen solver.
    pub fn compute_with(
        mesh: &Mesh,
        solver: Solver,
        progress: &mut dyn FnMut(Phase),
    ) -> Result<Bands, EnhanceError> {
        Self::compute_with_deltas(mesh, solver, solve::DELTAS, progress)
    }

    /// [`Bands::compute_with`] with other smoothing steps than the paper's (ascending,
    /// unit-sphere units): the print-aware mode places them by the printer's resolution.
    pub fn compute_with_deltas(
        mesh: &Mesh,
        solver: Solver,
        deltas: [f64; 3],
        progress: &mut dyn FnMut(Phase),
    ) -> Result<Bands, EnhanceError> {
        validate(mesh)?;
        if !(deltas.iter().all(|d| d.is_finite() && *d > 0.0)
            && deltas[0] < deltas[1]
            && deltas[1] < deltas[2])
        {
            return Err(EnhanceError::InvalidOption {
                name: "delta",
                value: deltas[0],
            });
        }
        let mut timings = PhaseTimings::default();

        // Step 1: normalise into the unit sphere around the bounding box centre.
        let (lo, hi) = mesh.bounds().ok_or(EnhanceError::NoFaces)?;
        let center: [f64; 3] = std::array::from_fn(|k| (lo[k] + hi[k]) / 2.0);
        let radius = mesh
            .vertices
            .iter()
            .map(|v| dist_sq(*v, center))
            .fold(0.0, f64::max)
            .sqrt();
        if !(radius > 0.0 && radius.is_finite()) {
            return Err(EnhanceError::ZeroSize);
        }
        let v0: Vec<[f64; 3]> = mesh
            .vertices
            .par_iter()
            .map(|v| std::array::from_fn(|k| (v[k] - center[k]) / radius))
            .collect();

        // Step 2.
        progress(Phase::Operators);
        let t = Instant::now();
        let ops = Operators::build(&v0, &mesh.faces);
        let rhs: Vec<[f64; 3]> = v0
            .iter()
            .zip(&ops.mass)
            .map(|(v, m)| v.map(|c| c * m))
            .collect();
        timings.operators_s = t.elapsed().as_secs_f64();

        // Step 3.
        let problem = Problem {
            ops: &ops,
            v0: &v0,
            rhs: &rhs,
            deltas,
        };
        let solved = solve::solve(problem, solver, &mut timings, progress)?;
        // Step 4: bands.
        let [v1, v2, v3] = solved.v;
        let diff = |a: &[[f64; 3]], b: &[[f64; 3]]| -> Vec<[f64; 3]> {
            a.par_iter()
                .zip(b)
                .map(|(p, q)| std::array::from_fn(|c| p[c] - q[c]))
                .collect()
        };
        let delta1 = diff(&v0, &v1);
        let delta2 = diff(&v1, &v2);
        let delta3_sq: Vec<f64> = v2.iter().zip(&v3).map(|(p, q)| dist_sq(*p, *q)).collect();
        let max_delta3_sq = delta3_sq.iter().copied().fold(0.0, f64::max);
        Ok(Bands {
            center,
            radius,
            v0,
            v_delta2: v2,
            delta1,
            delta2,
            delta3_sq,
            max_delta3_sq,
            area: ops.mass.clone(),
            deltas,
            residuals: solved.residuals,
            clamped_cotangents: ops.clamped_cotangents,
            timings,
        })
    }

    /// Spec step 5's default: μ = 0.1·λ2 / max‖Δ3_i‖² (0 when every Δ3_i is 0).
    pub(crate) fn default_mu(&self, lambda2: f64) -> f64 {
        if self.max_delta3_sq > 0.0 {
            0.1 * lambda2 / self.max_delta3_sq
        } else {
            0.0
        }
    }

    /// How far `combined`'s vertices moved, weighted by the area each stands for.
    pub(crate) fn displacements(&self, combined: &Combined) -> Option<super::Displacements> {
        super::Displacements::from_pairs(
            combined
                .moved
                .iter()
                .copied()
                .zip(self.area.iter().copied())
                .collect(),
        )
    }

    /// Band RMS in unit-sphere units: sqrt(mean ‖Δk_i‖²) for k = 1, 2, 3.
    pub fn band_rms(&self) -> [f64; 3] {
        let n = self.v0.len().max(1) as f64;
        let rms = |s: f64| (s / n).sqrt();
        [
            rms(self.delta1.iter().map(|d| dist_sq(*d, [0.0; 3])).sum()),
            rms(self.delta2.iter().map(|d| dist_sq(*d, [0.0; 3])).sum()),
            rms(self.delta3_sq.iter().sum()),
        ]
    }

    /// Spec steps 5–7: Ṽ = V_δ2 + λ2 W Δ2 + λ1 Δ1 with W_ii = exp(−μ‖Δ3_i‖²), mapped back
    /// to input units. `opts.mu = None` uses [`Bands::default_mu`].
    pub fn combine(&self, opts: &EnhanceOptions) -> Result<Combined, EnhanceError> {
        opts.validate()?;
        let mu = opts.mu.unwrap_or_else(|| self.default_mu(opts.lambda2));
        let (r, c) = (self.radius, self.center);
        let per_vertex: Vec<([f64; 3], f64, f64)> = (0..self.v0.len())
            .into_par_iter()
            .with_min_len(8192)
            .map(|i| {
                let w = (-mu * self.delta3_sq[i]).exp();
                let (base, d2, d1) = (self.v_delta2[i], self.delta2[i], self.delta1[i]);
                let enhanced: [f64; 3] = std::array::from_fn(|k| {
                    base[k] + opts.lambda2 * w * d2[k] + opts.lambda1 * d1[k]
                });
                let moved = dist_sq(enhanced, self.v0[i]).sqrt() * r;
                (std::array::from_fn(|k| enhanced[k] * r + c[k]), w, moved)
            })
            .collect();
        let n = per_vertex.len().max(1) as f64;
        let mut combined = Combined {
            vertices: Vec::with_capacity(per_vertex.len()),
            mu,
            w_min: f64::INFINITY,
            w_mean: 0.0,
            max_displacement: 0.0,
            mean_displacement: 0.0,
            moved: Vec::with_capacity(per_vertex.len()),
        };
        for (v, w, moved) in per_vertex {
            combined.vertices.push(v);
            combined.moved.push(moved);
            combined.w_min = combined.w_min.min(w);
            combined.w_mean += w / n;
            combined.max_displacement = combined.max_displacement.max(moved);
            combined.mean_displacement += moved / n;
        }
        Ok(combined)
    }
}

fn dist_sq(a: [f64; 3], b: [f64; 3]) -> f64 {
    (0..3).map(|k| (a[k] - b[k]) * (a[k] - b[k])).sum()
}

fn validate(mesh: &Mesh) -> Result<(), EnhanceError> {
    if mesh.faces.is_empty() {
        return Err(EnhanceError::NoFaces);
    }
    let n = mesh.vertices.len();
    for (face, f) in mesh.faces.iter().enumerate() {
        if let Some(&index) = f.iter().find(|&&i| i as usize >= n) {
            return Err(EnhanceError::BadIndex {
                face,
                index,
                vertices: n,
            });
        }
    }
    if let Some(vertex) = mesh
        .vertices
        .iter()
        .position(|v| !v.iter().all(|c| c.is_finite()))
    {
        return Err(EnhanceError::NonFinite { vertex });
    }
    Ok(())
}
