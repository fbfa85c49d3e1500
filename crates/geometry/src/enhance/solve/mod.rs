//! Spec step 3: the three systems `(M − δL) V_δ = M V0`, one per δ of [`DELTAS`], solved
//! by sparse Cholesky ([`cholesky`]) or by conjugate gradients ([`cg`]). Whatever precision
//! or iteration produced an answer, it is accepted only when [`relative_residual`],
//! computed the same way for both against the double-precision matrix, is within
//! [`MAX_RELATIVE_RESIDUAL`].

mod cg;
mod cholesky;
mod choose;
mod ordering;

pub(in crate::enhance) use choose::solve;

use super::operators::Operators;
use super::EnhanceError;

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

/// The systems to solve, as views of what the caller owns: the operators, the normalised
/// vertices V0 and the right-hand side M V0 shared by the three δ.
#[derive(Clone, Copy)]
pub(super) struct Problem<'a> {
    pub ops: &'a Operators,
    pub v0: &'a [[f64; 3]],
    pub rhs: &'a [[f64; 3]],
    /// The three δ, ascending ([`DELTAS`] for the paper's method).
    pub deltas: [f64; 3],
}

/// V_δ for each δ of [`DELTAS`], and each one's relative residual.
pub(super) struct Solutions {
    pub v: [Vec<[f64; 3]>; 3],
    pub residuals: [f64; 3],
}

/// How far `x` is from solving `A x = b`, for the symmetric `A` whose stored lower
/// triangle is `values` (see [`Operators::system_values`]).
pub(super) struct Residual {
    /// The worst column's ‖b − Ax‖ / ‖b‖ (‖b − Ax‖ where that column of b is 0).
    pub relative: f64,
    /// b − Ax itself, the right-hand side of a refinement step.
    pub vector: Vec<[f64; 3]>,
}

pub(super) fn relative_residual(
    ops: &Operators,
    values: &[f64],
    x: &[[f64; 3]],
    b: &[[f64; 3]],
) -> Residual {
    let mut vector = vec![[0.0; 3]; x.len()];
    ops.sym_matvec(values, x, &mut vector);
    for (ri, bi) in vector.iter_mut().zip(b) {
        *ri = std::array::from_fn(|c| bi[c] - ri[c]);
    }
    let norm = |v: &[[f64; 3]], c: usize| v.iter().map(|p| p[c] * p[c]).sum::<f64>().sqrt();
    let relative = (0..3)
        .map(|c| {
            let (rn, bn) = (norm(&vector, c), norm(b, c));
            if bn > 0.0 {
                rn / bn
            } else {
                rn
            }
        })
        .fold(0.0, f64::max);
    Residual { relative, vector }
}

/// The error for a solve whose best answer missed [`MAX_RELATIVE_RESIDUAL`].
fn residual_too_large(delta: f64, residual: f64, how: &str) -> EnhanceError {
    EnhanceError::Solver {
        delta: Some(delta),
        message: format!(
            "{how} reached a relative residual of only {residual:.3e} (needs \
             {MAX_RELATIVE_RESIDUAL:e})"
        ),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// An equilateral triangle: M has a third of the area on each corner.
    fn triangle() -> (Operators, Vec<[f64; 3]>) {
        let h = 3f64.sqrt() / 2.0;
        let v = vec![[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.5, h, 0.0]];
        (Operators::build(&v, &[[0, 1, 2]]), v)
    }

    #[test]
    fn the_residual_is_relative_per_column_and_takes_the_worst() {
        let (ops, v) = triangle();
        // δ = 0: A = M, so x = V solves A x = M V exactly.
        let values = ops.system_values(0.0);
        let b: Vec<[f64; 3]> = v
            .iter()
            .zip(&ops.mass)
            .map(|(p, m)| p.map(|c| c * m))
            .collect();
        assert!(relative_residual(&ops, &values, &v, &b).relative < 1e-15);
        // x = 0 leaves all of b: relative residual 1 in every column that has one.
        let zero = vec![[0.0; 3]; 3];
        let r = relative_residual(&ops, &values, &zero, &b);
        assert!((r.relative - 1.0).abs() < 1e-15, "{}", r.relative);
        assert_eq!(r.vector, b);
        // x off in z only, where b is 0: the absolute residual counts, and it is the worst.
        let lifted: Vec<[f64; 3]> = v.iter().map(|p| [p[0], p[1], 10.0]).collect();
        let r = relative_residual(&ops, &values, &lifted, &b);
        let expected = 10.0 * ops.mass.iter().map(|m| m * m).sum::<f64>().sqrt();
        assert!((r.relative - expected).abs() < 1e-12, "{}", r.relative);
    }
}
