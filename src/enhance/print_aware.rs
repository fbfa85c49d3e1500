//! The print-aware variant of the enhancement (`--mode print-aware`): the paper's
//! operators, bands, weight W and combination, with the bands and the strength chosen for
//! the printer instead of fixed in the unit sphere. `docs/method.md` ("The enhancement,
//! as printed") has the study that judges it against the paper's method.
//!
//! - **Bands.** An implicit step (M − δL) damps a surface wave of wavelength ℓ (unit
//!   sphere) by 1 / (1 + δ(2π/ℓ)²), half at ℓ = 2π√δ. The printer draws features down to
//!   about its resolution s = max(line width, 2 × layer height) at the printed size; those
//!   from 2s to 8s are drawn, but rounded and shallowed by the nozzle. δ1 and δ2 put the
//!   mid band Δ2 on those wavelengths (at the bounding radius in mm, r·scale); δ3 = 10·δ2 as
//!   in the paper, for W.
//! - **Strength.** λ2 lifts the band's typical feature (its area-weighted 90th percentile
//!   amplitude A, mm) by what the printer loses: a quarter of the line width w (the
//!   slicer's rounding) or half a layer height h (relief shallower falls between layers),
//!   whichever is more: (λ2 − 1)·A = max(w/4, h/2); then it is lowered, if needed, until the largest displacement
//!   relative to the bounding radius is no more than the paper's strong setting (λ2 = 40)
//!   gives on the same mesh.
//! - **Combination.** Ṽ = V_δ2 + λ2·W·Δ2 + Δ1: λ1 = 1 keeps the detail finer than the
//!   band as it is (below the printer's resolution there is nothing to gain by removing
//!   it), so the only change is (λ2·W − 1)·Δ2. λ2·W > 0, so no feature of the band is
//!   inverted: a bump stays a bump, and where W holds back thin parts the band is at most
//!   flattened.

use super::{Bands, EnhanceError, EnhanceOptions, EnhanceReport, Phase, PrintResolution, Solver};
use crate::mesh::Mesh;
use serde::{Deserialize, Serialize};
use std::time::Instant;

/// How the enhancement's bands and strength are chosen.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum Mode {
    /// The paper's: bands fixed in the unit sphere, λ2 from the height table.
    #[default]
    Paper,
    /// Bands and λ2 from the machine's line width and layer height at the printed size.
    PrintAware,
}

impl std::str::FromStr for Mode {
    type Err = String;
    fn from_str(s: &str) -> Result<Self, String> {
        match s {
            "paper" => Ok(Mode::Paper),
            "print-aware" | "print_aware" => Ok(Mode::PrintAware),
            _ => Err(format!("unknown mode {s:?}; use paper or print-aware")),
        }
    }
}

impl std::fmt::Display for Mode {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(match self {
            Mode::Paper => "paper",
            Mode::PrintAware => "print-aware",
        })
    }
}

/// The band's wavelengths, in units of the printer's resolution s.
pub(crate) const BAND_WAVELENGTHS: [f64; 2] = [2.0, 8.0];
/// The strength the largest displacement is capped by: the paper's strong setting.
pub(crate) const PAPER_STRONG_LAMBDA2: f64 = 40.0;
/// λ2 is never above this.
pub(crate) const MAX_LAMBDA2: f64 = 200.0;

/// What the print-aware mode chose, and why.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct PrintAwareReport {
    pub nozzle_mm: f64,
    pub layer_height_mm: f64,
    /// max(line width, 2 × layer height), mm.
    pub resolution_mm: f64,
    /// The mid band's wavelengths at the printed size, mm.
    pub band_mm: [f64; 2],
    pub deltas: [f64; 3],
    /// The band's area-weighted 90th percentile amplitude, mm.
    pub band_amplitude_mm: f64,
    /// What the band is lifted by, max(w/4, h/2), mm.
    pub lift_mm: f64,
    /// λ2 that lifts it so, and the λ2 used.
    pub lambda2_target: f64,
    pub lambda2: f64,
    /// Largest displacement / bounding radius: the paper's strong setting's (the cap) and
    /// this enhancement's.
    pub cap_ratio: f64,
    pub max_ratio: f64,
    /// Whether the cap lowered λ2.
    pub capped: bool,
}

/// The δ for a band of wavelengths `band_mm` on a mesh of bounding radius `radius_mm`.
pub(crate) fn deltas_for(band_mm: [f64; 2], radius_mm: f64) -> [f64; 3] {
    let delta = |l: f64| (l / (2.0 * std::f64::consts::PI * radius_mm)).powi(2);
    let (d1, d2) = (delta(band_mm[0]), delta(band_mm[1]));
    [d1, d2, 10.0 * d2].map(|d| d.clamp(1e-9, 10.0))
}

/// Enhances `mesh` for a printer: `scale` is printed mm per model unit. Returns the mesh
/// (input units), the usual report and what was chosen.
pub fn enhance(
    mesh: &Mesh,
    scale: f64,
    printer: PrintResolution,
    progress: &mut dyn FnMut(Phase),
) -> Result<(Mesh, EnhanceReport, PrintAwareReport), EnhanceError> {
    let bad = |name, value| EnhanceError::InvalidOption { name, value };
    if !(scale.is_finite() && scale > 0.0) {
        return Err(bad("scale", scale));
    }
    if !(printer.nozzle_mm.is_finite() && printer.nozzle_mm > 0.0) {
        return Err(bad("nozzle_mm", printer.nozzle_mm));
    }
    if !(printer.layer_height_mm.is_finite() && printer.layer_height_mm > 0.0) {
        return Err(bad("layer_height_mm", printer.layer_height_mm));
    }
    // The cap: the paper's strong setting on this mesh.
    let paper = Bands::compute(mesh, progress)?;
    let strong = paper.combine(&EnhanceOptions::with_lambda2(PAPER_STRONG_LAMBDA2))?;
    let cap_ratio = strong.max_displacement / paper.radius;
    drop(paper);

    let width = super::printed::line_width_mm(printer.nozzle_mm);
    let resolution = width.max(2.0 * printer.layer_height_mm);
    let band_mm = BAND_WAVELENGTHS.map(|k| k * resolution);
    let radius_mm = {
        let (lo, hi) = mesh.bounds().ok_or(EnhanceError::NoFaces)?;
        let c: [f64; 3] = std::array::from_fn(|k| (lo[k] + hi[k]) / 2.0);
        let r = mesh
            .vertices
            .iter()
            .map(|v| (0..3).map(|k| (v[k] - c[k]).powi(2)).sum::<f64>())
            .fold(0.0, f64::max)
            .sqrt();
        r * scale
    };
    let deltas = deltas_for(band_mm, radius_mm);
    let bands = Bands::compute_with_deltas(mesh, Solver::Auto, deltas, progress)?;
    progress(Phase::Combine);
    let t = Instant::now();
    let amplitude_mm = bands.mid_band_quantile(0.9) * bands.radius * scale;
    // What the printer loses: a quarter line width across the layers (the slicer's
    // rounding), half a layer along Z (relief shallower than that falls between layers).
    let lift_mm = (0.25 * width).max(0.5 * printer.layer_height_mm);
    let lambda2_target = if amplitude_mm > 0.0 {
        (1.0 + lift_mm / amplitude_mm).min(MAX_LAMBDA2)
    } else {
        1.0
    };
    let opts = |lambda2| EnhanceOptions {
        lambda1: 1.0,
        lambda2,
        mu: None,
    };
    let ratio = |lambda2| -> Result<f64, EnhanceError> {
        Ok(bands.combine(&opts(lambda2))?.max_displacement / bands.radius)
    };
    let mut lambda2 = lambda2_target;
    let capped = ratio(lambda2)? > cap_ratio;
    if capped {
        // The largest displacement grows with λ2 (W's falloff grows with it too, but only
        // where the band is held back): bisect for the largest λ2 within the cap.
        let (mut lo, mut hi) = (1.0, lambda2_target);
        for _ in 0..40 {
            let mid = 0.5 * (lo + hi);
            if ratio(mid)? <= cap_ratio {
                lo = mid;
            } else {
                hi = mid;
            }
        }
        lambda2 = lo;
    }
    let combined = bands.combine(&opts(lambda2))?;
    let max_ratio = combined.max_displacement / bands.radius;
    let chosen = PrintAwareReport {
        nozzle_mm: printer.nozzle_mm,
        layer_height_mm: printer.layer_height_mm,
        resolution_mm: resolution,
        band_mm,
        deltas,
        band_amplitude_mm: amplitude_mm,
        lift_mm,
        lambda2_target,
        lambda2,
        cap_ratio,
        max_ratio,
        capped,
    };
    let (out, report) = super::finish(mesh, &bands, combined, 1.0, lambda2, t);
    Ok((out, report, chosen))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn deltas_put_the_half_damping_wavelength_on_the_band() {
        let d = deltas_for([0.8, 3.2], 13.0);
        for (delta, l) in d.iter().zip([0.8, 3.2]) {
            let half = 2.0 * std::f64::consts::PI * delta.sqrt() * 13.0;
            assert!((half - l).abs() < 1e-12, "{half} vs {l}");
        }
        assert!((d[2] / d[1] - 10.0).abs() < 1e-12);
        assert_eq!("print-aware".parse::<Mode>(), Ok(Mode::PrintAware));
        assert!("fancy".parse::<Mode>().is_err());
    }
}
