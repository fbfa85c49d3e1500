//! Adaptive unsharp masking of geometry (Herholz et al. 2017), exactly as
//! `docs/method.md` specifies: exaggerate a mesh's mid-scale
//! features so a small print keeps the look of the large original.
//!
//! No I/O and no async: the CLI and the slicing pipeline load a [`Mesh`] with
//! [`crate::mesh`], call [`enhance`] (or [`Bands`] for several strengths of one mesh),
//! then scale and write it. [`StrengthTable`] turns a printed height into λ2.

mod bands;
pub mod operators;
pub mod print_aware;
pub(crate) mod printed;
mod solve;
mod strength;
mod terms;

pub use bands::{Bands, Combined};
pub use operators::COT_BOUND;
pub use print_aware::Mode;
pub use printed::{line_width_mm, LINE_WIDTH_FRACTION};
pub use printed::{Displacements, PrintResolution, PrintedDisplacement};
pub use solve::{Solver, CG_MAX_VERTICES, DELTAS, MAX_RELATIVE_RESIDUAL};
pub use strength::{Strength, StrengthTable};
pub use terms::{EnhanceError, EnhanceOptions, EnhanceReport, Phase, PhaseTimings};

use crate::mesh::Mesh;
use std::time::Instant;

/// Enhances `mesh` (spec steps 1–7): same faces, moved vertices, in the input's units.
/// `progress` is called as each phase starts.
pub fn enhance(
    mesh: &Mesh,
    opts: &EnhanceOptions,
    progress: &mut dyn FnMut(Phase),
) -> Result<(Mesh, EnhanceReport), EnhanceError> {
    opts.validate()?;
    let bands = Bands::compute(mesh, progress)?;
    progress(Phase::Combine);
    let t = Instant::now();
    let combined = bands.combine(opts)?;
    Ok(finish(
        mesh,
        &bands,
        combined,
        opts.lambda1,
        opts.lambda2,
        t,
    ))
}

/// The enhanced mesh and its report, once the bands are combined (`combine_started`: when
/// combining began, for the timings).
pub fn finish(
    mesh: &Mesh,
    bands: &Bands,
    combined: Combined,
    lambda1: f64,
    lambda2: f64,
    combine_started: Instant,
) -> (Mesh, EnhanceReport) {
    let mut timings = bands.timings.clone();
    timings.combine_s = combine_started.elapsed().as_secs_f64();
    let report = EnhanceReport {
        vertices: mesh.vertices.len(),
        faces: mesh.faces.len(),
        lambda1,
        lambda2,
        mu: combined.mu,
        w_min: combined.w_min,
        w_mean: combined.w_mean,
        max_displacement: combined.max_displacement,
        mean_displacement: combined.mean_displacement,
        max_solve_residual: bands.residuals.iter().copied().fold(0.0, f64::max),
        center: bands.center,
        radius: bands.radius,
        clamped_cotangents: bands.clamped_cotangents,
        timings,
    };
    let out = Mesh {
        vertices: combined.vertices,
        faces: mesh.faces.clone(),
    };
    (out, report)
}
