//! The model of the eye, from the literature and with its published constants only
//! (docs/method.md, "The observer", lists each with its source): how sensitive a person
//! is to a pattern of a given spatial frequency at a given luminance and field size
//! (Barten's contrast sensitivity function), how a strong pattern raises the threshold
//! of another in its band (Daly's masking), and how the chance of seeing several
//! differences adds up (probability summation with the psychometric function's slope).
//! Pure functions of numbers: the pictures are the comparison's.

/// Barten's contrast sensitivity (P. G. J. Barten, "Formula for the contrast sensitivity
/// of the human eye", Proc. SPIE 5294, 2004, 231–238: the closed form of his 1999 model
/// for photopic foveal vision, binocular, with natural pupils): the reciprocal of the
/// modulation of a sine grating at its detection threshold.
///
/// `u` is the spatial frequency in cycles per degree, `luminance` the adapting luminance
/// in cd/m², `field_deg` the angular size X0 of the object (a square field of that side;
/// for another shape, the side of the square of the same area).
pub(crate) fn barten_csf(u: f64, luminance: f64, field_deg: f64) -> f64 {
    let (a, b, c, d, e) = BARTEN;
    let u2 = u * u;
    let l = luminance.max(MIN_LUMINANCE);
    let x0 = field_deg.max(MIN_FIELD_DEG);
    let numerator = a * (-b * u2 * (1.0 + 100.0 / l).powf(0.08)).exp();
    // 1 / (1 − e^(−0.02 u²)), the lateral inhibition term, grows without bound at u → 0.
    let inhibition = 1.0 / (1.0 - (-e * u2).exp()).max(f64::MIN_POSITIVE);
    let denominator = ((1.0 + 144.0 / (x0 * x0) + c * u2) * (d / l.powf(0.83) + inhibition)).sqrt();
    numerator / denominator
}

/// The constants of Barten's 2004 formula, in its order: 5200 (the scale), 0.0016 (the
/// optical blur's exponent), 0.64 (the spatial extent of the neural noise), 63 (the
/// photon noise at luminance L^0.83) and 0.02 (the lateral inhibition). The exponents
/// 0.08 and 0.83 and the 100 and 144 are written where they are used.
const BARTEN: (f64, f64, f64, f64, f64) = (5200.0, 0.0016, 0.64, 63.0, 0.02);

/// Below these the formula is used at these: the cloth's shadow is not darker than the
/// dimmest a room is lit, and an object is never smaller than the fovea's 1° in the
/// formula's field term (Barten fits it from about that size).
const MIN_LUMINANCE: f64 = 0.01;
const MIN_FIELD_DEG: f64 = 0.5;

/// Daly's threshold elevation by masking (S. Daly, "The visible differences predictor: an
/// algorithm for the assessment of image fidelity", in A. B. Watson (ed.), Digital Images
/// and Human Vision, MIT Press 1993, 179–206): by how many times a mask of `mask` (the
/// mask's contrast in its band, in multiples of its own detection threshold, as H. Yee's
/// perceptual metric applies it, ACM TOG/J. Graphics Tools 2004) raises the threshold of
/// a pattern in the same band. 1 for no mask; about mask^0.7 for a strong one.
pub(crate) fn daly_elevation(mask: f64) -> f64 {
    let (k1, k2, s, b) = DALY;
    let m = mask.abs();
    (1.0 + (k1 * (k2 * m).powf(s)).powf(b)).powf(1.0 / b)
}

/// Daly's k1, k2, the learning slope s (0.65–1 in his paper; 0.7 is the value the
/// perceptual metrics that use his function take) and b.
const DALY: (f64, f64, f64, f64) = (0.0153, 392.498, 0.7, 4.0);

/// The slope β of the psychometric function P(c) = 1 − exp(−(c/threshold)^β) (the Weibull
/// form), which is also the exponent of probability summation over bands and places
/// (Quick 1974; Watson 1979): 3.5, the value of Daly's VDP and of Mantiuk et al.'s
/// HDR-VDP-2 (ACM TOG 30(4), 2011).
pub(crate) const BETA: f64 = 3.5;

/// [`barten_csf`] tabulated over the adapting luminance for one frequency and field: one
/// band of one picture looks it up per pixel, so the formula's powers and exponentials are
/// paid 256 times instead of per pixel. Linear in log10(luminance) between knots, which
/// are 0.0234 decades apart: the sensitivity changes by less than 1 % between two.
pub(crate) struct CsfTable {
    log_lo: f64,
    step: f64,
    values: Vec<f32>,
}

/// The table's span, cd/m² (log10): from a dim room's shadow to sunlit white.
const TABLE_LOG_LUMINANCE: (f64, f64) = (-2.0, 4.0);
const TABLE_KNOTS: usize = 257;

impl CsfTable {
    pub(crate) fn new(u: f64, field_deg: f64) -> CsfTable {
        let (lo, hi) = TABLE_LOG_LUMINANCE;
        let step = (hi - lo) / (TABLE_KNOTS - 1) as f64;
        let values = (0..TABLE_KNOTS)
            .map(|i| barten_csf(u, 10f64.powf(lo + step * i as f64), field_deg) as f32)
            .collect();
        CsfTable {
            log_lo: lo,
            step,
            values,
        }
    }

    /// The sensitivity at `luminance` cd/m² (clamped to the table's span).
    pub(crate) fn at(&self, luminance: f32) -> f32 {
        let x = (f64::from(luminance.max(1e-6)).log10() - self.log_lo) / self.step;
        let last = (self.values.len() - 1) as f64;
        let x = x.clamp(0.0, last);
        let i = (x as usize).min(self.values.len() - 2);
        let f = (x - i as f64) as f32;
        self.values[i] * (1.0 - f) + self.values[i + 1] * f
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The formula's shape as Barten describes it: band-pass with its peak between 2 and
    /// 6 cycles per degree at office luminances, the peak rising and moving to higher
    /// frequencies with luminance, a small field losing the low frequencies, and the
    /// acuity limit (sensitivity 1) near 50–60 cycles per degree at 100 cd/m².
    #[test]
    fn barten_has_the_published_shape() {
        let peak = |l: f64, x0: f64| {
            (1..=400)
                .map(|i| 0.1 * f64::from(i))
                .map(|u| (u, barten_csf(u, l, x0)))
                .fold((0.0, 0.0), |a, b| if b.1 > a.1 { b } else { a })
        };
        let (u100, s100) = peak(100.0, 10.0);
        assert!((2.0..=6.0).contains(&u100), "peak at {u100} cpd");
        assert!((300.0..=800.0).contains(&s100), "peak sensitivity {s100}");
        let (u1, s1) = peak(1.0, 10.0);
        assert!(u1 < u100 && s1 < s100, "{u1} {s1}");
        // Field size: the low frequencies care most (its term 144/X0² stands beside
        // 0.64 u²).
        assert!(barten_csf(0.5, 100.0, 2.0) < 0.6 * barten_csf(0.5, 100.0, 20.0));
        let high = barten_csf(20.0, 100.0, 2.0) / barten_csf(20.0, 100.0, 20.0);
        assert!((0.9..1.0).contains(&high), "{high}");
        // Acuity: sensitivity 1 between 45 and 65 cycles per degree.
        let cutoff = (1..=1000)
            .map(|i| 0.1 * f64::from(i))
            .find(|&u| u > 10.0 && barten_csf(u, 100.0, 10.0) < 1.0)
            .unwrap();
        assert!((45.0..=65.0).contains(&cutoff), "cutoff {cutoff} cpd");
        // Bounded inputs give finite numbers.
        for (u, l, x) in [
            (0.0, 0.0, 0.0),
            (1e3, 1e9, 1e3),
            (f64::MIN_POSITIVE, 1.0, 1.0),
        ] {
            assert!(barten_csf(u, l, x).is_finite(), "{u} {l} {x}");
        }
    }

    #[test]
    fn daly_masking_starts_at_the_masks_threshold() {
        assert!((daly_elevation(0.0) - 1.0).abs() < 1e-12);
        assert!(daly_elevation(0.1) < 1.001);
        // k1 · k2^s = 1.0009: at the mask's own threshold the elevation is 2^(1/4).
        assert!((daly_elevation(1.0) - 2f64.powf(0.25)).abs() < 1e-3);
        // Well above, it grows as the mask to the learning slope.
        let ratio = daly_elevation(1000.0) / daly_elevation(100.0);
        assert!((ratio - 10f64.powf(0.7)).abs() < 0.01, "{ratio}");
        assert_eq!(daly_elevation(-5.0), daly_elevation(5.0));
    }

    #[test]
    fn the_table_follows_the_formula() {
        let table = CsfTable::new(8.0, 5.0);
        for l in [0.02, 0.7, 8.0, 55.0, 130.0, 900.0] {
            let exact = barten_csf(8.0, l, 5.0);
            let looked = f64::from(table.at(l as f32));
            assert!(
                (looked / exact - 1.0).abs() < 0.01,
                "{l}: {looked} vs {exact}"
            );
        }
        assert!(table.at(0.0).is_finite() && table.at(f32::INFINITY).is_finite());
        assert!(table.at(f32::NAN).is_finite());
    }
}
