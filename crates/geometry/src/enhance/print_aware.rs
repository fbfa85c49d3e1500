//! The print-aware variant of the enhancement (`--mode print-aware`, a folder's
//! `enhancement = "print-aware"`): the paper's operators, bands, weight W and combination,
//! with the bands and the strength chosen for the printer instead of fixed in the unit
//! sphere. `docs/method.md` ("The enhancement, as printed") has the study that judges it
//! against the paper's method.
//!
//! - **Bands.** An implicit step (M − δL) damps a surface wave of wavelength ℓ (unit
//!   sphere) by 1 / (1 + δ(2π/ℓ)²), half at ℓ = 2π√δ. The printer draws features down to
//!   about its resolution s = max(line width, 2 × layer height) at the printed size; those
//!   from 2s to 8s are drawn, but rounded and shallowed by the nozzle. δ1 and δ2 put the
//!   mid band Δ2 on those wavelengths (at the bounding radius in mm, r·scale); δ3 = 10·δ2 as
//!   in the paper, for W.
//! - **Strength.** λ2 is the smallest that moves a target share of the surface by more
//!   than a quarter line width (what the slicer's rounding hides). The target follows the
//!   paper's strength: [`TARGET_SHARE`] at the paper's medium λ2 = 20 (the height table's
//!   value at 25 mm and below), in proportion to λ2 − 1 otherwise, so it falls with the
//!   printed height to nothing at the table's top (150 mm) and a folder's `strength` still
//!   scales it. Two bounds keep it moderate, whatever the target: the 99th percentile of
//!   the displacement (area-weighted, so a few vertices cannot set it) within the paper's
//!   strong setting's (λ2 = 40) on the same mesh, and the largest displacement within
//!   [`CEILING_LINE_WIDTHS`] line widths at the printed size.
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
/// The paper's strong setting: its displacement's 99th percentile bounds this one's.
pub(crate) const PAPER_STRONG_LAMBDA2: f64 = 40.0;
/// The paper's medium setting (the height table's λ2 at 25 mm and below), at which the
/// target share is [`TARGET_SHARE`].
pub(crate) const PAPER_MEDIUM_LAMBDA2: f64 = 20.0;
/// The share of the surface (area) to move by more than a quarter line width at the
/// paper's medium strength.
pub const TARGET_SHARE: f64 = 0.25;
/// The quantile of the displacement bounded by the paper's strong setting's.
pub(crate) const CAP_QUANTILE: f64 = 0.99;
/// No point moves more than this many line widths at the printed size.
pub const CEILING_LINE_WIDTHS: f64 = 1.0;
/// λ2 is never above this.
pub(crate) const MAX_LAMBDA2: f64 = 200.0;
/// Bisection steps for λ2 (to 200 / 2^30, far below what changes a print).
const BISECTION_STEPS: usize = 30;

/// What bound λ2 below its target.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Limit {
    /// The 99th percentile reached the paper's strong setting's.
    StrongP99,
    /// The largest displacement reached the ceiling in line widths.
    Ceiling,
}

/// What the print-aware mode chose, and why. Millimetres are at the printed size.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct PrintAwareReport {
    pub nozzle_mm: f64,
    pub layer_height_mm: f64,
    /// max(line width, 2 × layer height), mm.
    pub resolution_mm: f64,
    /// The mid band's wavelengths at the printed size, mm.
    pub band_mm: [f64; 2],
    pub deltas: [f64; 3],
    /// The paper's λ2 for this job (height table or fixed), which sets the target.
    pub paper_lambda2: f64,
    /// The share of the surface to move by more than a quarter line width, and the share
    /// moved.
    pub target_share: f64,
    pub share: f64,
    /// A quarter line width, mm.
    pub threshold_mm: f64,
    /// The λ2 used.
    pub lambda2: f64,
    /// 99th percentile of the displacement: this one's, and the paper's strong setting's
    /// (its bound), mm.
    pub p99_mm: f64,
    pub strong_p99_mm: f64,
    /// Largest displacement and its ceiling, mm.
    pub max_mm: f64,
    pub ceiling_mm: f64,
    /// What kept λ2 below the target's, if anything.
    pub limited_by: Option<Limit>,
}

/// The δ for a band of wavelengths `band_mm` on a mesh of bounding radius `radius_mm`.
pub(crate) fn deltas_for(band_mm: [f64; 2], radius_mm: f64) -> [f64; 3] {
    let delta = |l: f64| (l / (2.0 * std::f64::consts::PI * radius_mm)).powi(2);
    let (d1, d2) = (delta(band_mm[0]), delta(band_mm[1]));
    [d1, d2, 10.0 * d2].map(|d| d.clamp(1e-9, 10.0))
}

/// The share of the surface to move by more than a quarter line width when the paper's
/// method would use `paper_lambda2`.
pub(crate) fn target_share(paper_lambda2: f64) -> f64 {
    let relative = (paper_lambda2 - 1.0) / (PAPER_MEDIUM_LAMBDA2 - 1.0);
    if relative.is_finite() {
        (TARGET_SHARE * relative).clamp(0.0, 1.0)
    } else {
        0.0
    }
}

/// The boundary of `holds` in [lo, hi], where it holds at `lo` and not at `hi`: the last
/// value found to hold and the first found not to.
fn bisect(
    mut lo: f64,
    mut hi: f64,
    holds: impl Fn(f64) -> Result<bool, EnhanceError>,
) -> Result<(f64, f64), EnhanceError> {
    for _ in 0..BISECTION_STEPS {
        let mid = 0.5 * (lo + hi);
        if holds(mid)? {
            lo = mid;
        } else {
            hi = mid;
        }
    }
    Ok((lo, hi))
}

/// One combination's figures, model units.
struct Trial {
    share: f64,
    p99: f64,
    max: f64,
}

/// Enhances `mesh` for a printer: `scale` is printed mm per model unit, `paper_lambda2`
/// the λ2 the paper's method would use for this job. Returns the mesh (input units), the
/// usual report and what was chosen.
pub fn enhance(
    mesh: &Mesh,
    scale: f64,
    printer: PrintResolution,
    paper_lambda2: f64,
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
    if !(paper_lambda2.is_finite() && paper_lambda2 >= 0.0) {
        return Err(bad("paper_lambda2", paper_lambda2));
    }
    // The bound: the paper's strong setting on this mesh.
    let paper = Bands::compute(mesh, progress)?;
    let strong = paper.combine(&EnhanceOptions::with_lambda2(PAPER_STRONG_LAMBDA2))?;
    let strong_p99 = paper
        .displacements(&strong)
        .map_or(0.0, |d| d.quantile(CAP_QUANTILE));
    drop((paper, strong));

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
    let threshold = super::printed::LINE_WIDTH_FRACTION * width / scale;
    let ceiling = CEILING_LINE_WIDTHS * width / scale;
    let target = target_share(paper_lambda2);
    let opts = |lambda2| EnhanceOptions {
        lambda1: 1.0,
        lambda2,
        mu: None,
    };
    let trial = |lambda2| -> Result<Trial, EnhanceError> {
        let combined = bands.combine(&opts(lambda2))?;
        Ok(match bands.displacements(&combined) {
            Some(d) => Trial {
                share: d.share_above(threshold),
                p99: d.quantile(CAP_QUANTILE),
                max: d.max(),
            },
            None => Trial {
                share: 0.0,
                p99: 0.0,
                max: 0.0,
            },
        })
    };
    let limit = |t: &Trial| {
        if t.p99 > strong_p99 {
            Some(Limit::StrongP99)
        } else if t.max > ceiling {
            Some(Limit::Ceiling)
        } else {
            None
        }
    };
    // Each figure grows with λ2 (W's falloff grows with it too, but only where the band is
    // held back), so the largest λ2 within the bounds and the smallest reaching the
    // target are found by bisection; λ2 = 1 changes the band only where W holds it back.
    let reaches = |lambda2| -> Result<bool, EnhanceError> { Ok(trial(lambda2)?.share >= target) };
    let bound = limit(&trial(MAX_LAMBDA2)?);
    let highest = match bound {
        None => MAX_LAMBDA2,
        Some(_) => bisect(1.0, MAX_LAMBDA2, |l| Ok(limit(&trial(l)?).is_none()))?.0,
    };
    let (lambda2, limited_by) = if !reaches(highest)? {
        (highest, bound)
    } else if reaches(1.0)? {
        (1.0, None)
    } else {
        (bisect(1.0, highest, |l| Ok(!reaches(l)?))?.1, None)
    };
    let combined = bands.combine(&opts(lambda2))?;
    let chosen_trial = trial(lambda2)?;
    let chosen = PrintAwareReport {
        nozzle_mm: printer.nozzle_mm,
        layer_height_mm: printer.layer_height_mm,
        resolution_mm: resolution,
        band_mm,
        deltas,
        paper_lambda2,
        target_share: target,
        share: chosen_trial.share,
        threshold_mm: threshold * scale,
        lambda2,
        p99_mm: chosen_trial.p99 * scale,
        strong_p99_mm: strong_p99 * scale,
        max_mm: chosen_trial.max * scale,
        ceiling_mm: ceiling * scale,
        limited_by,
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

    #[test]
    fn the_target_follows_the_papers_strength_and_falls_to_nothing_at_150_mm() {
        let table = super::super::StrengthTable::default();
        let at = |height: f64| table.lambda2_for_height(height).map_or(0.0, target_share);
        assert_eq!(at(15.0), TARGET_SHARE);
        assert_eq!(at(25.0), TARGET_SHARE);
        assert!((at(100.0) - TARGET_SHARE * 5.0 / 19.0).abs() < 1e-12);
        assert!(at(149.0) < 0.01 * TARGET_SHARE);
        assert_eq!(at(150.0), 0.0);
        let heights = [15.0, 30.0, 50.0, 75.0, 100.0, 125.0, 149.9];
        assert!(heights.windows(2).all(|h| at(h[0]) >= at(h[1])));
        // A folder's strength scales it, within 0..=1; nonsense is no enhancement.
        assert_eq!(target_share(40.0), TARGET_SHARE * 39.0 / 19.0);
        assert_eq!(target_share(1000.0), 1.0);
        assert_eq!(target_share(0.5), 0.0);
        assert_eq!(target_share(f64::NAN), 0.0);
    }
}
