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
pub mod printed;
mod solve;
mod strength;

pub use bands::{Bands, Combined};
pub use operators::COT_BOUND;
pub use print_aware::Mode;
pub use printed::{Displacements, PrintResolution, PrintedDisplacement};
pub use solve::{Solver, CG_MAX_VERTICES, DELTAS, MAX_RELATIVE_RESIDUAL};
pub use strength::{Strength, StrengthTable};

use crate::mesh::Mesh;
use serde::{Deserialize, Serialize};
use std::time::Instant;

/// How to combine the bands (spec step 6).
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct EnhanceOptions {
    /// Weight of the finest band; 0 (the paper's choice for printing) avoids amplifying
    /// scan noise.
    pub lambda1: f64,
    /// Strength: weight of the mid band.
    pub lambda2: f64,
    /// Weight falloff; `None` = the spec's rule 0.1·λ2 / max‖Δ3_i‖².
    pub mu: Option<f64>,
}

impl EnhanceOptions {
    /// The spec's defaults (λ1 = 0, μ by rule) at strength `lambda2`.
    pub fn with_lambda2(lambda2: f64) -> Self {
        EnhanceOptions {
            lambda1: 0.0,
            lambda2,
            mu: None,
        }
    }

    pub fn validate(&self) -> Result<(), EnhanceError> {
        let bad = |name: &'static str, value: f64| EnhanceError::InvalidOption { name, value };
        if !self.lambda1.is_finite() {
            return Err(bad("lambda1", self.lambda1));
        }
        if !self.lambda2.is_finite() {
            return Err(bad("lambda2", self.lambda2));
        }
        if let Some(mu) = self.mu {
            if !(mu.is_finite() && mu >= 0.0) {
                return Err(bad("mu", mu));
            }
        }
        Ok(())
    }
}

/// Where enhancement is, for progress displays.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Phase {
    /// Building the cotangent Laplacian and mass matrix.
    Operators,
    /// Symbolic analysis of the shared sparsity pattern.
    Factorize,
    /// Factorising and solving for δ number 0, 1 or 2.
    Solve(usize),
    /// Weights and combination.
    Combine,
}

/// Seconds per phase. `factorize_s` includes the symbolic analysis and the three
/// numeric factorisations; `solve_s` the triangular solves and residual checks. The
/// Cholesky path works on the three δ concurrently, so its two figures add up the time
/// of each δ and can together exceed the wall time they took.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct PhaseTimings {
    pub operators_s: f64,
    pub factorize_s: f64,
    /// The symbolic analysis alone (fill-reducing ordering and structure), part of
    /// `factorize_s`.
    pub symbolic_s: f64,
    pub solve_s: f64,
    pub combine_s: f64,
}

/// What [`enhance`] did, in the input's units.
#[derive(Clone, Debug, Default, Serialize, Deserialize)]
pub struct EnhanceReport {
    pub vertices: usize,
    pub faces: usize,
    pub lambda1: f64,
    pub lambda2: f64,
    pub mu: f64,
    pub w_min: f64,
    pub w_mean: f64,
    pub max_displacement: f64,
    pub mean_displacement: f64,
    pub max_solve_residual: f64,
    pub center: [f64; 3],
    pub radius: f64,
    pub clamped_cotangents: usize,
    pub timings: PhaseTimings,
}

/// Why a mesh could not be enhanced. Meshes from [`crate::mesh::load`] are already
/// cleaned and validated, so from there only `Solver` and `ZeroSize` can occur.
#[derive(Debug, thiserror::Error)]
pub enum EnhanceError {
    #[error("the mesh has no faces")]
    NoFaces,
    #[error("face {face} refers to vertex {index}, but the mesh has {vertices} vertices")]
    BadIndex {
        face: usize,
        index: u32,
        vertices: usize,
    },
    #[error("vertex {vertex} has a NaN or infinite coordinate")]
    NonFinite { vertex: usize },
    #[error("the mesh has zero size (all vertices coincide)")]
    ZeroSize,
    #[error("invalid option {name} = {value} (hint: it must be a finite number; mu must be ≥ 0)")]
    InvalidOption { name: &'static str, value: f64 },
    #[error(
        "the sparse solver failed{}: {message} (hint: repair the mesh, e.g. remove \
         self-intersecting or sliver triangles, or print it unenhanced)",
        delta.map(|d| format!(" for delta = {d:e}")).unwrap_or_default()
    )]
    Solver { delta: Option<f64>, message: String },
}

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
pub(crate) fn finish(
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
