//! `[[printer]] pause_heaters_off_s`: how long a pause the G-code file asked for (`M0`,
//! `M600`, ...) may wait for the operator before the printer's heaters are turned off (the
//! job keeps waiting; the resume heats up again first). Checked apart from the rest of the
//! printer's table so the bounds and the default live in one place.

use std::time::Duration;

/// Bounds of `pause_heaters_off_s`: at least 10 s (tests and impatient farms), at most a day
/// (a hot nozzle left alone longer is a fire risk nobody asked for).
pub(crate) const PAUSE_HEATERS_OFF_S: std::ops::RangeInclusive<i64> = 10..=86_400;

/// The default: half an hour, time for someone to come to the printer.
pub(crate) const DEFAULT_PAUSE_HEATERS_OFF_S: u64 = 30 * 60;

/// The value in force, or why the given one is refused.
pub(super) fn heaters_off_after(raw: Option<i64>) -> Result<Duration, String> {
    match raw {
        None => Ok(Duration::from_secs(DEFAULT_PAUSE_HEATERS_OFF_S)),
        Some(s) if PAUSE_HEATERS_OFF_S.contains(&s) => Ok(Duration::from_secs(s as u64)),
        Some(s) => Err(format!(
            "must be between {} and {} seconds, got {s}",
            PAUSE_HEATERS_OFF_S.start(),
            PAUSE_HEATERS_OFF_S.end()
        )),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn bounded_with_a_default() {
        assert_eq!(heaters_off_after(None), Ok(Duration::from_secs(1800)));
        assert_eq!(heaters_off_after(Some(10)), Ok(Duration::from_secs(10)));
        let err = heaters_off_after(Some(9)).unwrap_err();
        assert!(
            err.contains("between 10 and 86400") && err.contains("9"),
            "{err}"
        );
        assert!(heaters_off_after(Some(86_401)).is_err());
    }
}
