//! Strength from printed height (the spec's "Strength from target height"): the smaller
//! the print relative to its ~10–15 cm reference size, the stronger the enhancement,
//! interpolated linearly in log(height), capped at the paper's preferred range.

use serde::{Deserialize, Serialize};

/// How strongly to enhance: from the height table, not at all (models whose surface
/// detail reads as defects, like the paper's Igea), a fixed λ2, or as the observer
/// chooses among a few (`crate::observe`, the daemon's preparation).
#[derive(Clone, Copy, Debug, Serialize, Deserialize, PartialEq)]
#[serde(rename_all = "lowercase")]
pub enum Strength {
    Auto,
    Off,
    Lambda2(f64),
    Observed,
}

/// Height → λ2. `points` are (printed height in mm, λ2) in ascending height; below the
/// first point its λ2 applies; at and above `unmodified_from_mm` the model is printed
/// unmodified; between points λ2 is linear in ln(height), and between the last point
/// and `unmodified_from_mm` it continues towards `λ2_at_unmodified`.
#[derive(Clone, Debug, Serialize, Deserialize, PartialEq)]
#[serde(deny_unknown_fields)]
pub struct StrengthTable {
    pub points: Vec<(f64, f64)>,
    pub unmodified_from_mm: f64,
    /// λ2 just below `unmodified_from_mm` (the spec: 1).
    pub lambda2_at_unmodified: f64,
}

impl Default for StrengthTable {
    /// The spec's table: ≤25 mm → 20, 50 mm → 15, 100 mm → 6, rising from 1 just below
    /// 150 mm, unmodified from 150 mm.
    fn default() -> Self {
        StrengthTable {
            points: vec![(25.0, 20.0), (50.0, 15.0), (100.0, 6.0)],
            unmodified_from_mm: 150.0,
            lambda2_at_unmodified: 1.0,
        }
    }
}

impl StrengthTable {
    /// Checks a table from a config file: finite, positive heights in ascending order
    /// below `unmodified_from_mm`, finite non-negative λ2.
    #[cfg(test)]
    pub fn validate(&self) -> Result<(), String> {
        if self.points.is_empty() {
            return Err("the strength table needs at least one (height, lambda2) point".into());
        }
        let mut previous = 0.0;
        for &(h, l) in &self.points {
            if !(h.is_finite() && h > previous) {
                return Err(format!(
                    "heights must be positive and ascending; {h} follows {previous}"
                ));
            }
            if !(l.is_finite() && l >= 0.0) {
                return Err(format!("lambda2 {l} at {h} mm must be a finite number ≥ 0"));
            }
            previous = h;
        }
        if !(self.unmodified_from_mm.is_finite() && self.unmodified_from_mm > previous) {
            return Err(format!(
                "unmodified_from_mm ({}) must be above the last height ({previous})",
                self.unmodified_from_mm
            ));
        }
        if !(self.lambda2_at_unmodified.is_finite() && self.lambda2_at_unmodified >= 0.0) {
            return Err("lambda2_at_unmodified must be a finite number ≥ 0".into());
        }
        Ok(())
    }

    /// λ2 for a print `height_mm` tall; `None` means print it unmodified (at or above
    /// the top of the table, or a height that is not a positive number).
    pub fn lambda2_for_height(&self, height_mm: f64) -> Option<f64> {
        if !(height_mm.is_finite() && height_mm > 0.0) || height_mm >= self.unmodified_from_mm {
            return None;
        }
        let first = *self.points.first()?;
        if height_mm <= first.0 {
            return Some(first.1);
        }
        let mut knots = self.points.clone();
        knots.push((self.unmodified_from_mm, self.lambda2_at_unmodified));
        for pair in knots.windows(2) {
            let ((h0, l0), (h1, l1)) = (pair[0], pair[1]);
            if height_mm <= h1 {
                let t = (height_mm.ln() - h0.ln()) / (h1.ln() - h0.ln());
                return Some(l0 + t * (l1 - l0));
            }
        }
        None
    }

    /// λ2 for `strength` at an optional printed height; `None` = unmodified. `Auto`
    /// without a height cannot choose and leaves the model unmodified. `Observed` is
    /// settled by the preparation before it enhances; here, where the observer has not
    /// chosen, it is the table's, the default it falls back to.
    pub fn resolve(&self, strength: Strength, height_mm: Option<f64>) -> Option<f64> {
        match strength {
            Strength::Off => None,
            Strength::Lambda2(l) => Some(l),
            Strength::Auto | Strength::Observed => {
                height_mm.and_then(|h| self.lambda2_for_height(h))
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn default_table_matches_the_spec() {
        let t = StrengthTable::default();
        t.validate().unwrap();
        let at = |h: f64| t.lambda2_for_height(h);
        assert_eq!(at(10.0), Some(20.0));
        assert_eq!(at(25.0), Some(20.0));
        assert!((at(50.0).unwrap() - 15.0).abs() < 1e-12);
        assert!((at(100.0).unwrap() - 6.0).abs() < 1e-12);
        assert_eq!(at(150.0), None);
        assert_eq!(at(300.0), None);
        assert!((at(149.999).unwrap() - 1.0).abs() < 1e-3);
        // Linear in log(height): the geometric mean of 25 and 50 gets the midpoint.
        assert!((at((25.0f64 * 50.0).sqrt()).unwrap() - 17.5).abs() < 1e-12);
        // Monotone, never above 20.
        let mut previous = f64::INFINITY;
        for h in (1..150).map(f64::from) {
            let l = at(h).unwrap();
            assert!(l <= previous && l <= 20.0, "{h} mm -> {l}");
            previous = l;
        }
        assert_eq!(at(f64::NAN), None);
        assert_eq!(at(-5.0), None);
    }

    #[test]
    fn resolve_and_override() {
        let t = StrengthTable::default();
        assert_eq!(t.resolve(Strength::Off, Some(30.0)), None);
        assert_eq!(t.resolve(Strength::Lambda2(7.0), None), Some(7.0));
        assert_eq!(t.resolve(Strength::Auto, None), None);
        assert_eq!(t.resolve(Strength::Auto, Some(20.0)), Some(20.0));
        let custom: StrengthTable = serde_json::from_str(
            r#"{"points": [[40, 10]], "unmodified_from_mm": 80, "lambda2_at_unmodified": 0}"#,
        )
        .unwrap();
        custom.validate().unwrap();
        assert_eq!(custom.lambda2_for_height(30.0), Some(10.0));
        assert_eq!(custom.lambda2_for_height(80.0), None);
        let bad = StrengthTable {
            points: vec![(50.0, 10.0), (40.0, 5.0)],
            ..StrengthTable::default()
        };
        assert!(bad.validate().is_err());
    }
}
