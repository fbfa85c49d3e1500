//! `[enhancement]`: the farm's settings of the observer that a folder's or sidecar's
//! `strength = "observed"` asks (`crate::daemon::prepare::steps::observed`): the size the
//! small prints should look like, and how long the observer may take.

use super::check::{seconds_in, Bounds};
use super::folders::check_height;
use super::raw::RawEnhancement;
use crate::observation::{ObserveSettings, DEFAULT_OBSERVE_TIMEOUT_S};

/// Bounds of `observe_timeout_s`: long enough to slice a few prints, at most a day.
pub(crate) const OBSERVE_TIMEOUT_S: Bounds = 10.0..=86_400.0;

/// Checks `[enhancement]` (absent: the defaults); the error names the key.
pub(super) fn check(
    raw: Option<RawEnhancement>,
) -> Result<ObserveSettings, (&'static str, String)> {
    let Some(raw) = raw else {
        return Ok(ObserveSettings::default());
    };
    let mut settings = ObserveSettings::default();
    if let Some(h) = raw.reference_height_mm {
        check_height(h).map_err(|m| ("reference_height_mm", m))?;
        settings.reference_height_mm = h;
    }
    let timeout = raw
        .observe_timeout_s
        .unwrap_or(DEFAULT_OBSERVE_TIMEOUT_S as f64);
    settings.timeout =
        seconds_in(timeout, &OBSERVE_TIMEOUT_S).map_err(|m| ("observe_timeout_s", m))?;
    Ok(settings)
}
