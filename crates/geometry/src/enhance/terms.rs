//! What an enhancement is asked and what it answers: the options, the phases and their
//! timings, the report and the errors. Apart from the root, which runs the steps, so the
//! steps (bands, solve) use these without depending on what runs them.

use serde::{Deserialize, Serialize};

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

/// What `enhance` did, in the input's units.
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
