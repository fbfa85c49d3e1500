//! Which solver answers: conjugate gradients below [`super::CG_MAX_VERTICES`] with
//! Cholesky behind them, or the one asked for. Apart from the root, which defines the
//! problem both solvers take, so neither solver depends on the choice between them.

use super::{cg, cholesky, Problem, Solutions, Solver, CG_MAX_VERTICES};
use crate::enhance::{EnhanceError, Phase, PhaseTimings};

/// Solves the three systems with `solver`; fails when no solver reaches the residual.
pub(in crate::enhance) fn solve(
    problem: Problem,
    solver: Solver,
    timings: &mut PhaseTimings,
    progress: &mut dyn FnMut(Phase),
) -> Result<Solutions, EnhanceError> {
    match solver {
        Solver::Auto if problem.ops.n < CG_MAX_VERTICES => {
            cg::solve(problem, timings, progress).or_else(|error| {
                // Badly shaped triangles can make CG crawl; Cholesky does not care.
                tracing::debug!(%error, "conjugate gradients failed; using Cholesky");
                cholesky::solve(problem, timings, progress)
            })
        }
        Solver::ConjugateGradient => cg::solve(problem, timings, progress),
        Solver::Auto | Solver::Cholesky => cholesky::solve(problem, timings, progress),
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::enhance::operators::Operators;
    use crate::enhance::solve::{relative_residual, DELTAS, MAX_RELATIVE_RESIDUAL};

    #[test]
    fn both_solvers_pass_the_same_residual_check_and_agree() {
        // A bumpy fan around a centre vertex, so every δ moves something.
        let mut v = vec![[0.0, 0.0, 0.3]];
        let mut faces = Vec::new();
        for k in 0..8u32 {
            let angle = f64::from(k) * std::f64::consts::TAU / 8.0;
            v.push([angle.cos(), angle.sin(), 0.1 * f64::from(k % 2)]);
            faces.push([0, 1 + k, 1 + (k + 1) % 8]);
        }
        let ops = Operators::build(&v, &faces);
        let rhs: Vec<[f64; 3]> = v
            .iter()
            .zip(&ops.mass)
            .map(|(p, m)| p.map(|c| c * m))
            .collect();
        let problem = Problem {
            ops: &ops,
            v0: &v,
            rhs: &rhs,
            deltas: DELTAS,
        };
        let mut timings = PhaseTimings::default();
        let chol = solve(problem, Solver::Cholesky, &mut timings, &mut |_| {}).unwrap();
        let cg = solve(
            problem,
            Solver::ConjugateGradient,
            &mut timings,
            &mut |_| {},
        )
        .unwrap();
        for (k, delta) in DELTAS.iter().enumerate() {
            let values = ops.system_values(*delta);
            for solved in [&chol, &cg] {
                let r = relative_residual(&ops, &values, &solved.v[k], &rhs).relative;
                assert!(r <= MAX_RELATIVE_RESIDUAL, "δ = {delta}: {r:e}");
                assert_eq!(solved.residuals[k], r);
            }
            let worst = chol.v[k]
                .iter()
                .zip(&cg.v[k])
                .flat_map(|(a, b)| (0..3).map(move |c| (a[c] - b[c]).abs()))
                .fold(0.0, f64::max);
            assert!(worst < 1e-9, "δ = {delta}: solvers differ by {worst:e}");
        }
    }
}
