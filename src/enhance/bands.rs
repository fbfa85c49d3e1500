//! Spec steps 1–7 split the way the spec's "interactive use" asks: [`Bands::compute`]
//! does the expensive, mesh-only part once (normalise, operators, three sparse Cholesky
//! solves sharing one symbolic analysis, bands); [`Bands::combine`] is a few vector
//! operations per vertex for any λ1, λ2 and μ.

use super::operators::Operators;
use super::{cg, ordering};
use super::{EnhanceError, EnhanceOptions, Phase, PhaseTimings};
use crate::mesh::Mesh;
use faer::dyn_stack::{MemBuffer, MemStack};
use faer::perm::PermRef;
use faer::sparse::linalg::cholesky::{
    factorize_symbolic_cholesky, CholeskySymbolicParams, SymbolicCholesky, SymmetricOrdering,
};
use faer::sparse::linalg::SymbolicSupernodalParams;
use faer::sparse::{SparseColMatRef, SymbolicSparseColMat, SymbolicSparseColMatRef};
use faer::traits::ComplexField;
use faer::{Conj, Mat, Par, Side};
use rayon::prelude::*;
use std::sync::atomic::{AtomicUsize, Ordering};
use std::sync::mpsc;
use std::time::Instant;

/// How to solve the three systems of spec step 3.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub enum Solver {
    /// Conjugate gradients below [`CG_MAX_VERTICES`] vertices (falling back to
    /// Cholesky if they do not converge), Cholesky from there on. CG's iteration count
    /// grows with the mesh's resolution, Cholesky's cost does not depend on δ. Measured
    /// with benches/enhance.rs (2 cores), CG over Cholesky time: 0.4× on the bunny (35 k
    /// vertices), 0.8× on Nefertiti (50 k), 0.6× on the bunny subdivided to 139 k, 1.1×
    /// and 1.3× on Nefertiti and Homer subdivided to 200 k and 216 k.
    #[default]
    Auto,
    /// Sparse Cholesky (faer), one symbolic analysis for the three δ.
    Cholesky,
    /// Jacobi-preconditioned conjugate gradients, warm-started.
    ConjugateGradient,
}

/// Below this many vertices [`Solver::Auto`] uses conjugate gradients.
pub const CG_MAX_VERTICES: usize = 150_000;

/// The smoothing steps of spec step 3, in unit-sphere units.
pub const DELTAS: [f64; 3] = [0.5e-5, 1e-5, 1e-4];

/// Each solve must reach this relative residual (spec step 3).
pub const MAX_RELATIVE_RESIDUAL: f64 = 1e-10;

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
        validate(mesh)?;
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
        let n = ops.n;
        let rhs: Vec<[f64; 3]> = v0
            .iter()
            .zip(&ops.mass)
            .map(|(v, m)| v.map(|c| c * m))
            .collect();
        timings.operators_s = t.elapsed().as_secs_f64();

        // Step 3.
        let (mut solutions, residuals) = match solver {
            Solver::Auto if n < CG_MAX_VERTICES => {
                match solve_cg(&ops, &v0, &rhs, &mut timings, progress) {
                    Ok(solved) => solved,
                    Err(e) => {
                        // Badly shaped triangles can make CG crawl; Cholesky does not care.
                        tracing::debug!(error = %e, "conjugate gradients failed; using Cholesky");
                        solve_cholesky(&ops, &v0, &rhs, &mut timings, progress)?
                    }
                }
            }
            Solver::ConjugateGradient => solve_cg(&ops, &v0, &rhs, &mut timings, progress)?,
            Solver::Auto | Solver::Cholesky => {
                solve_cholesky(&ops, &v0, &rhs, &mut timings, progress)?
            }
        };
        // Step 4: bands.
        let v3 = solutions.pop().expect("three solutions");
        let v2 = solutions.pop().expect("three solutions");
        let v1 = solutions.pop().expect("three solutions");
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
            residuals,
            clamped_cotangents: ops.clamped_cotangents,
            timings,
        })
    }

    /// Spec step 5's default: μ = 0.1·λ2 / max‖Δ3_i‖² (0 when every Δ3_i is 0).
    pub fn default_mu(&self, lambda2: f64) -> f64 {
        if self.max_delta3_sq > 0.0 {
            0.1 * lambda2 / self.max_delta3_sq
        } else {
            0.0
        }
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
        };
        for (v, w, moved) in per_vertex {
            combined.vertices.push(v);
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

/// The three solutions V_δ and each one's relative residual.
type Solved = (Vec<Vec<[f64; 3]>>, [f64; 3]);

/// Spec step 3 by sparse Cholesky: one symbolic analysis, then per δ a numeric
/// factorisation and a solve with the three coordinates as right-hand sides.
///
/// The δ are independent once the pattern is analysed, so they run on up to three
/// threads, each factorising sequentially. On 2 cores two concurrent factorisations take
/// 0.6× the time of two in a row, where faer's parallel factorisation of one matrix
/// measured no faster than its sequential one (0.8 M vertices).
fn solve_cholesky(
    ops: &Operators,
    positions: &[[f64; 3]],
    rhs: &[[f64; 3]],
    timings: &mut PhaseTimings,
    progress: &mut dyn FnMut(Phase),
) -> Result<Solved, EnhanceError> {
    // One symbolic analysis (fill-reducing ordering, elimination tree,
    // supernodes) serves all three δ, whose matrices share the pattern.
    progress(Phase::Factorize);
    let t = Instant::now();
    let (pattern, symbolic) = analyse(ops, positions)?;
    timings.symbolic_s = t.elapsed().as_secs_f64();
    timings.factorize_s += timings.symbolic_s;
    let system = System {
        ops,
        pattern: pattern.as_ref(),
        symbolic: &symbolic,
        rhs,
    };
    let workers = std::thread::available_parallelism()
        .map_or(1, |n| n.get())
        .min(DELTAS.len());
    let next = AtomicUsize::new(0);
    let mut solved: [Option<DeltaSolution>; 3] = Default::default();
    progress(Phase::Solve(0));
    std::thread::scope(|scope| {
        let (sender, receiver) = mpsc::channel();
        for _ in 0..workers {
            let sender = sender.clone();
            let (system, next) = (&system, &next);
            scope.spawn(move || loop {
                let k = next.fetch_add(1, Ordering::Relaxed);
                if k >= DELTAS.len() || sender.send((k, system.solve(DELTAS[k]))).is_err() {
                    break;
                }
            });
        }
        drop(sender);
        let mut finished = 0;
        for (k, result) in receiver {
            // Stop the workers from starting another δ; the scope waits for running ones.
            let solution = result.inspect_err(|_| next.store(DELTAS.len(), Ordering::Relaxed))?;
            timings.factorize_s += solution.factorize_s;
            timings.solve_s += solution.solve_s;
            solved[k] = Some(solution);
            finished += 1;
            if finished < DELTAS.len() {
                progress(Phase::Solve(finished));
            }
        }
        Ok::<_, EnhanceError>(())
    })?;

    let mut residuals = [0.0; 3];
    let mut solutions = Vec::with_capacity(3);
    for (k, solution) in solved.into_iter().enumerate() {
        let solution = solution.expect("every δ solved or an error returned");
        residuals[k] = solution.residual;
        solutions.push(solution.x);
    }
    Ok((solutions, residuals))
}

/// The pattern of `M − δL` and its symbolic Cholesky analysis.
fn analyse(
    ops: &Operators,
    positions: &[[f64; 3]],
) -> Result<(SymbolicSparseColMat<usize>, SymbolicCholesky<usize>), EnhanceError> {
    let n = ops.n;
    let pattern = SymbolicSparseColMat::<usize>::new_checked(
        n,
        n,
        ops.col_ptr.clone(),
        None,
        ops.row_idx.clone(),
    );
    // Large meshes: geometric nested dissection (see ordering.rs); small ones: AMD.
    let (forward, inverse) = if n >= ND_MIN_VERTICES {
        let forward = ordering::nested_dissection(positions, &ops.col_ptr, &ops.row_idx);
        let mut inverse = vec![0usize; n];
        for (k, &v) in forward.iter().enumerate() {
            inverse[v] = k;
        }
        (forward, inverse)
    } else {
        (Vec::new(), Vec::new())
    };
    let order = if forward.is_empty() {
        SymmetricOrdering::Amd
    } else {
        SymmetricOrdering::Custom(PermRef::new_checked(&forward, &inverse, n))
    };
    let params = CholeskySymbolicParams {
        supernodal_params: SymbolicSupernodalParams {
            relax: Some(SUPERNODE_RELAXATION),
        },
        ..Default::default()
    };
    let symbolic = factorize_symbolic_cholesky(pattern.as_ref(), Side::Lower, order, params)
        .map_err(|e| EnhanceError::Solver {
            delta: None,
            message: format!("symbolic analysis failed: {e:?}"),
        })?;
    tracing::debug!(
        vertices = n,
        factor_entries = symbolic.len_val(),
        "symbolic analysis"
    );
    Ok((pattern, symbolic))
}

/// Supernode amalgamation: faer's default (CHOLMOD's) with the two larger-supernode
/// thresholds doubled, allowing a little more explicit fill for fewer, larger dense blocks
/// (measured 10 % faster factorisation for 2 % more factor entries at 0.8 M vertices).
const SUPERNODE_RELAXATION: &[(usize, f64)] = &[(4, 1.0), (16, 0.8), (48, 0.2), (usize::MAX, 0.1)];

/// Iterative-refinement steps after the first solve. Single precision gains about
/// five digits per step on these matrices (first solve ~1e-5, then 1e-10, 1e-15).
const MAX_REFINEMENTS: usize = 4;

/// One of the three systems `(M − δL) V = M V0`, sharing pattern, analysis and
/// right-hand side with the other two.
struct System<'a> {
    ops: &'a Operators,
    pattern: SymbolicSparseColMatRef<'a, usize>,
    symbolic: &'a SymbolicCholesky<usize>,
    rhs: &'a [[f64; 3]],
}

struct DeltaSolution {
    x: Vec<[f64; 3]>,
    residual: f64,
    factorize_s: f64,
    solve_s: f64,
}

impl System<'_> {
    /// Solve for one δ: factorise in single precision and refine in double, which
    /// halves the factor's memory and takes 0.65× the time; if single precision breaks
    /// down or refinement stalls (badly conditioned geometry), factorise in double.
    fn solve(&self, delta: f64) -> Result<DeltaSolution, EnhanceError> {
        let values = self.ops.system_values(delta);
        match self.factorize_and_solve::<f32>(delta, &values) {
            Ok(solution) if solution.residual <= MAX_RELATIVE_RESIDUAL => return Ok(solution),
            Ok(solution) => tracing::debug!(
                delta,
                residual = solution.residual,
                "single-precision factor did not converge; factorising in double"
            ),
            Err(error) => {
                tracing::debug!(delta, %error, "single-precision factorisation failed; factorising in double")
            }
        }
        let solution = self.factorize_and_solve::<f64>(delta, &values)?;
        if !(solution.residual <= MAX_RELATIVE_RESIDUAL) {
            return Err(EnhanceError::Solver {
                delta: Some(delta),
                message: format!(
                    "the solve reached a relative residual of only {:.3e} (needs {:e})",
                    solution.residual, MAX_RELATIVE_RESIDUAL
                ),
            });
        }
        Ok(solution)
    }

    /// Factorise `M − δL` in precision `T`, solve in `T` and refine the solution against
    /// the double-precision matrix until its residual is far below the spec's bound.
    fn factorize_and_solve<T: FactorScalar>(
        &self,
        delta: f64,
        values: &[f64],
    ) -> Result<DeltaSolution, EnhanceError> {
        let t = Instant::now();
        let values_t: Vec<T> = values.iter().map(|&v| T::from_f64(v)).collect();
        let mut factor_values = vec![T::from_f64(0.0); self.symbolic.len_val()];
        let mut scratch = MemBuffer::new(
            self.symbolic
                .factorize_numeric_llt_scratch::<T>(Par::Seq, Default::default())
                .or(self.symbolic.solve_in_place_scratch::<T>(3, Par::Seq)),
        );
        let llt = self
            .symbolic
            .factorize_numeric_llt(
                &mut factor_values,
                SparseColMatRef::new(self.pattern, &values_t),
                Side::Lower,
                Default::default(),
                Par::Seq,
                MemStack::new(&mut scratch),
                Default::default(),
            )
            .map_err(|e| EnhanceError::Solver {
                delta: Some(delta),
                message: format!(
                    "Cholesky factorisation failed ({e:?}): the matrix is not positive \
                     definite, which points at badly broken geometry"
                ),
            })?;
        let factorize_s = t.elapsed().as_secs_f64();

        let t = Instant::now();
        // Solves A·c = b for a right-hand side scaled to unit size first: refinement
        // residuals shrink towards 1e-25 and would underflow single precision otherwise.
        let mut solve = |b: &[[f64; 3]]| -> Vec<[f64; 3]> {
            let scale = b.iter().flatten().fold(0.0f64, |m, v| m.max(v.abs()));
            if scale == 0.0 {
                return vec![[0.0; 3]; b.len()];
            }
            let mut x = Mat::from_fn(b.len(), 3, |i, c| T::from_f64(b[i][c] / scale));
            llt.solve_in_place_with_conj(
                Conj::No,
                x.as_mut(),
                Par::Seq,
                MemStack::new(&mut scratch),
            );
            (0..b.len())
                .map(|i| std::array::from_fn(|c| x[(i, c)].to_f64() * scale))
                .collect()
        };
        let mut x = solve(self.rhs);
        let mut residual = relative_residual(self.ops, values, &x, self.rhs);
        for _ in 0..MAX_REFINEMENTS {
            if residual.0 <= MAX_RELATIVE_RESIDUAL * 1e-2 {
                break;
            }
            let correction = solve(&residual.1);
            for (xi, ci) in x.iter_mut().zip(&correction) {
                for c in 0..3 {
                    xi[c] += ci[c];
                }
            }
            let before = residual.0;
            residual = relative_residual(self.ops, values, &x, self.rhs);
            if !(residual.0 < before * 0.5) {
                break; // stalled: more steps will not help
            }
        }
        tracing::debug!(
            delta,
            precision = T::NAME,
            residual = residual.0,
            "Cholesky solve"
        );
        Ok(DeltaSolution {
            x,
            residual: residual.0,
            factorize_s,
            solve_s: t.elapsed().as_secs_f64(),
        })
    }
}

/// The precisions a factor is computed in.
trait FactorScalar: ComplexField + Copy {
    const NAME: &'static str;
    fn from_f64(value: f64) -> Self;
    fn to_f64(self) -> f64;
}

impl FactorScalar for f32 {
    const NAME: &'static str = "single";
    fn from_f64(value: f64) -> Self {
        value as f32
    }
    fn to_f64(self) -> f64 {
        self as f64
    }
}

impl FactorScalar for f64 {
    const NAME: &'static str = "double";
    fn from_f64(value: f64) -> Self {
        value
    }
    fn to_f64(self) -> f64 {
        self
    }
}

/// Spec step 3 by preconditioned conjugate gradients, each δ warm-started from the
/// previous solution (δ1 from V0, δ2 by linear extrapolation, δ3 from V_δ2).
fn solve_cg(
    ops: &Operators,
    v0: &[[f64; 3]],
    rhs: &[[f64; 3]],
    timings: &mut PhaseTimings,
    progress: &mut dyn FnMut(Phase),
) -> Result<Solved, EnhanceError> {
    progress(Phase::Factorize);
    let t = Instant::now();
    let lap = cg::FullLaplacian::new(ops);
    timings.factorize_s += t.elapsed().as_secs_f64();
    let t = Instant::now();
    let mut solutions: Vec<Vec<[f64; 3]>> = Vec::with_capacity(3);
    let mut residuals = [0.0; 3];
    for (k, &delta) in DELTAS.iter().enumerate() {
        progress(Phase::Solve(k));
        let mut x: Vec<[f64; 3]> = match k {
            0 => v0.to_vec(),
            // V(δ) is close to linear in δ for small δ; δ2 = 2·δ1.
            1 => solutions[0]
                .iter()
                .zip(v0)
                .map(|(a, b)| std::array::from_fn(|c| 2.0 * a[c] - b[c]))
                .collect(),
            _ => solutions[1].clone(),
        };
        // Tighter than the spec's 1e-10: the bands are small differences of the
        // solutions, amplified by λ2.
        let converged = cg::solve(&lap, delta, rhs, &mut x, CG_TOLERANCE, CG_MAX_ITERATIONS);
        tracing::debug!(delta, iterations = ?converged, "conjugate gradients");
        let mut ax = vec![[0.0; 3]; x.len()];
        lap.apply(delta, &x, &mut ax);
        let residual = (0..3)
            .map(|c| {
                let rn: f64 = rhs
                    .iter()
                    .zip(&ax)
                    .map(|(b, a)| (b[c] - a[c]).powi(2))
                    .sum::<f64>()
                    .sqrt();
                let bn: f64 = rhs.iter().map(|b| b[c] * b[c]).sum::<f64>().sqrt();
                if bn > 0.0 {
                    rn / bn
                } else {
                    rn
                }
            })
            .fold(0.0, f64::max);
        if converged.is_none() || !(residual <= MAX_RELATIVE_RESIDUAL) {
            return Err(EnhanceError::Solver {
                delta: Some(delta),
                message: format!(
                    "conjugate gradients stopped at a relative residual of {residual:.3e} \
                     after {CG_MAX_ITERATIONS} iterations (needs {MAX_RELATIVE_RESIDUAL:e})"
                ),
            });
        }
        residuals[k] = residual;
        solutions.push(x);
    }
    timings.solve_s += t.elapsed().as_secs_f64();
    Ok((solutions, residuals))
}

const CG_TOLERANCE: f64 = 1e-12;
const CG_MAX_ITERATIONS: usize = 20_000;

/// From this many vertices the Cholesky path orders by nested dissection, not AMD
/// (measured at 0.8 M vertices: symbolic analysis 2.5 s → 0.7 s, and no more fill).
const ND_MIN_VERTICES: usize = 100_000;

/// Worst relative residual over the three columns, and the residual b − Ax itself.
fn relative_residual(
    ops: &Operators,
    values: &[f64],
    x: &[[f64; 3]],
    b: &[[f64; 3]],
) -> (f64, Vec<[f64; 3]>) {
    let mut ax = vec![[0.0; 3]; x.len()];
    ops.sym_matvec(values, x, &mut ax);
    let r: Vec<[f64; 3]> = b
        .iter()
        .zip(&ax)
        .map(|(bi, ai)| std::array::from_fn(|c| bi[c] - ai[c]))
        .collect();
    let worst = (0..3)
        .map(|c| {
            let rn: f64 = r.iter().map(|v| v[c] * v[c]).sum::<f64>().sqrt();
            let bn: f64 = b.iter().map(|v| v[c] * v[c]).sum::<f64>().sqrt();
            if bn > 0.0 {
                rn / bn
            } else {
                rn
            }
        })
        .fold(0.0, f64::max);
    (worst, r)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The bunny scaled to about the unit sphere (its radius is ~0.1), its operators and the right-hand side `M V0`.
    fn bunny_system() -> (Operators, Vec<[f64; 3]>, Vec<[f64; 3]>) {
        let path = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/data/bunny.obj.gz");
        let packed = std::fs::File::open(&path).unwrap();
        let mesh = crate::mesh::read(flate2::read::GzDecoder::new(packed), "bunny.obj")
            .unwrap()
            .mesh;
        let v0: Vec<[f64; 3]> = mesh.vertices.iter().map(|v| v.map(|c| c * 10.0)).collect();
        let ops = Operators::build(&v0, &mesh.faces);
        let rhs = v0
            .iter()
            .zip(&ops.mass)
            .map(|(v, m)| v.map(|c| c * m))
            .collect();
        (ops, v0, rhs)
    }

    #[test]
    fn single_precision_factor_refines_to_the_double_precision_solution() {
        let (ops, v0, rhs) = bunny_system();
        let (pattern, symbolic) = analyse(&ops, &v0).unwrap();
        let system = System {
            ops: &ops,
            pattern: pattern.as_ref(),
            symbolic: &symbolic,
            rhs: &rhs,
        };
        for delta in DELTAS {
            let values = ops.system_values(delta);
            let single = system.factorize_and_solve::<f32>(delta, &values).unwrap();
            let double = system.factorize_and_solve::<f64>(delta, &values).unwrap();
            assert!(
                single.residual <= MAX_RELATIVE_RESIDUAL * 1e-2,
                "{delta}: {}",
                single.residual
            );
            assert!(
                double.residual <= MAX_RELATIVE_RESIDUAL * 1e-2,
                "{delta}: {}",
                double.residual
            );
            let worst = single
                .x
                .iter()
                .zip(&double.x)
                .flat_map(|(a, b)| (0..3).map(move |c| (a[c] - b[c]).abs()))
                .fold(0.0, f64::max);
            assert!(worst < 1e-9, "δ = {delta}: solutions differ by {worst:e}");
        }
    }
}
