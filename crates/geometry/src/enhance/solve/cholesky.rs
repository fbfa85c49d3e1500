//! Spec step 3 by sparse Cholesky (faer): one symbolic analysis of the pattern the three
//! matrices `M − δL` share, then per δ a numeric factorisation and a solve with the three
//! coordinates as right-hand sides. The factor is computed in single precision and the
//! solution refined in double against the exact matrix; if that does not reach the
//! residual, the δ is factorised again in double.

#[cfg(test)]
use super::DELTAS;
use super::MAX_RELATIVE_RESIDUAL;
use super::{ordering, relative_residual, residual_too_large, Problem, Solutions};
use crate::enhance::{EnhanceError, Phase, PhaseTimings};
use faer::dyn_stack::{MemBuffer, MemStack};
use faer::perm::PermRef;
use faer::sparse::linalg::cholesky::{
    factorize_symbolic_cholesky, CholeskySymbolicParams, SymbolicCholesky, SymmetricOrdering,
};
use faer::sparse::linalg::SymbolicSupernodalParams;
use faer::sparse::{SparseColMatRef, SymbolicSparseColMatRef};
use faer::traits::ComplexField;
use faer::{Conj, Mat, Par, Side};
use std::borrow::Cow;
use std::sync::atomic::{AtomicUsize, Ordering};
use std::sync::mpsc;
use std::time::Instant;

/// From this many vertices the pattern is ordered by nested dissection, not AMD
/// (measured at 0.8 M vertices: symbolic analysis 2.5 s → 0.7 s, and no more fill).
const ND_MIN_VERTICES: usize = 100_000;

/// Supernode amalgamation: faer's default (CHOLMOD's) with the two larger-supernode
/// thresholds doubled, allowing a little more explicit fill for fewer, larger dense blocks
/// (measured 10 % faster factorisation for 2 % more factor entries at 0.8 M vertices).
const SUPERNODE_RELAXATION: &[(usize, f64)] = &[(4, 1.0), (16, 0.8), (48, 0.2), (usize::MAX, 0.1)];

/// Iterative-refinement steps after the first solve. Single precision gains about
/// five digits per step on these matrices (first solve ~1e-5, then 1e-10, 1e-15).
const MAX_REFINEMENTS: usize = 4;

/// Solves the three systems.
///
/// The δ are independent once the pattern is analysed, so they run on up to three
/// threads, each factorising sequentially. On 2 cores two concurrent factorisations take
/// 0.6× the time of two in a row, where faer's parallel factorisation of one matrix
/// measured no faster than its sequential one (0.8 M vertices).
pub(super) fn solve(
    problem: Problem,
    timings: &mut PhaseTimings,
    progress: &mut dyn FnMut(Phase),
) -> Result<Solutions, EnhanceError> {
    progress(Phase::Factorize);
    let deltas = problem.deltas;
    let t = Instant::now();
    let system = System::analyse(problem)?;
    timings.symbolic_s = t.elapsed().as_secs_f64();
    timings.factorize_s += timings.symbolic_s;
    let workers = std::thread::available_parallelism()
        .map_or(1, |n| n.get())
        .min(deltas.len());
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
                if k >= deltas.len() || sender.send((k, system.solve(deltas[k]))).is_err() {
                    break;
                }
            });
        }
        drop(sender);
        let mut finished = 0;
        for (k, result) in receiver {
            // Stop the workers from starting another δ; the scope waits for running ones.
            let solution = result.inspect_err(|_| next.store(deltas.len(), Ordering::Relaxed))?;
            timings.factorize_s += solution.factorize_s;
            timings.solve_s += solution.solve_s;
            solved[k] = Some(solution);
            finished += 1;
            if finished < deltas.len() {
                progress(Phase::Solve(finished));
            }
        }
        Ok::<_, EnhanceError>(())
    })?;
    let solved = solved.map(|s| s.expect("every δ solved or an error returned"));
    Ok(Solutions {
        residuals: std::array::from_fn(|k| solved[k].residual),
        v: solved.map(|s| s.x),
    })
}

/// The three systems: their shared pattern (a view of the operators' own) and its
/// symbolic analysis, done once.
struct System<'a> {
    problem: Problem<'a>,
    pattern: SymbolicSparseColMatRef<'a, usize>,
    symbolic: SymbolicCholesky<usize>,
}

struct DeltaSolution {
    x: Vec<[f64; 3]>,
    residual: f64,
    factorize_s: f64,
    solve_s: f64,
}

impl<'a> System<'a> {
    /// The symbolic analysis: fill-reducing ordering, elimination tree, supernodes.
    fn analyse(problem: Problem<'a>) -> Result<Self, EnhanceError> {
        let ops = problem.ops;
        let n = ops.n;
        let pattern = SymbolicSparseColMatRef::new_checked(n, n, &ops.col_ptr, None, &ops.row_idx);
        // Large meshes: geometric nested dissection (see ordering.rs); small ones: AMD.
        let (forward, inverse) = if n >= ND_MIN_VERTICES {
            let forward = ordering::nested_dissection(problem.v0, &ops.col_ptr, &ops.row_idx);
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
        let symbolic =
            factorize_symbolic_cholesky(pattern, Side::Lower, order, params).map_err(|e| {
                EnhanceError::Solver {
                    delta: None,
                    message: format!("symbolic analysis failed: {e:?}"),
                }
            })?;
        tracing::debug!(
            vertices = n,
            factor_entries = symbolic.len_val(),
            "symbolic analysis"
        );
        Ok(System {
            problem,
            pattern,
            symbolic,
        })
    }

    /// Solve for one δ: factorise in single precision and refine in double, which
    /// halves the factor's memory and takes 0.65× the time; if single precision breaks
    /// down or refinement stalls (badly conditioned geometry), factorise in double.
    fn solve(&self, delta: f64) -> Result<DeltaSolution, EnhanceError> {
        let values = self.problem.ops.system_values(delta);
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
            return Err(residual_too_large(
                delta,
                solution.residual,
                "the double-precision Cholesky solve",
            ));
        }
        Ok(solution)
    }

    /// Factorise `M − δL` (stored lower triangle `values`) in precision `T`, solve in `T`
    /// and refine the solution against the double-precision matrix until its residual is
    /// far below the spec's bound.
    fn factorize_and_solve<T: FactorScalar>(
        &self,
        delta: f64,
        values: &[f64],
    ) -> Result<DeltaSolution, EnhanceError> {
        let t = Instant::now();
        let values_t = T::from_f64_slice(values);
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
                SparseColMatRef::new(self.pattern, &values_t[..]),
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
        let (ops, rhs) = (self.problem.ops, self.problem.rhs);
        let mut x = solve(rhs);
        let mut residual = relative_residual(ops, values, &x, rhs);
        for _ in 0..MAX_REFINEMENTS {
            if residual.relative <= MAX_RELATIVE_RESIDUAL * 1e-2 {
                break;
            }
            let correction = solve(&residual.vector);
            for (xi, ci) in x.iter_mut().zip(&correction) {
                for c in 0..3 {
                    xi[c] += ci[c];
                }
            }
            let before = residual.relative;
            residual = relative_residual(ops, values, &x, rhs);
            if !(residual.relative < before * 0.5) {
                break; // stalled: more steps will not help
            }
        }
        tracing::debug!(
            delta,
            precision = T::NAME,
            residual = residual.relative,
            "Cholesky solve"
        );
        Ok(DeltaSolution {
            x,
            residual: residual.relative,
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
    /// The matrix values in this precision: a copy for f32, the values themselves for f64.
    fn from_f64_slice(values: &[f64]) -> Cow<'_, [Self]>;
}

impl FactorScalar for f32 {
    const NAME: &'static str = "single";
    fn from_f64(value: f64) -> Self {
        value as f32
    }
    fn to_f64(self) -> f64 {
        self as f64
    }
    fn from_f64_slice(values: &[f64]) -> Cow<'_, [Self]> {
        values.iter().map(|&v| v as f32).collect()
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
    fn from_f64_slice(values: &[f64]) -> Cow<'_, [Self]> {
        Cow::Borrowed(values)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::enhance::operators::Operators;

    /// The bunny scaled to about the unit sphere (its radius is ~0.1), its operators and
    /// the right-hand side `M V0`.
    fn bunny_system() -> (Operators, Vec<[f64; 3]>, Vec<[f64; 3]>) {
        let path =
            std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("../../tests/data/bunny.obj.gz");
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
        let system = System::analyse(Problem {
            ops: &ops,
            v0: &v0,
            rhs: &rhs,
            deltas: DELTAS,
        })
        .unwrap();
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
