//! `[history]`: how long, and how many, finished jobs stay in the live queue before they
//! move to the history, and how long the history keeps them.

use super::check::Bounds;
use super::checked::HistoryConfig;
use super::raw::RawHistory;
use std::time::Duration;

/// Bounds of `[history] live_days` (0: a finished job leaves the queue at once).
pub(crate) const LIVE_DAYS: Bounds = 0.0..=3650.0;
/// Bounds of `[history] keep_days`: at least a day; absent, the history keeps everything.
pub(crate) const KEEP_DAYS: Bounds = 1.0..=36_500.0;
/// Bounds of `[history] live_jobs`: the live queue stays small whatever the history holds.
pub(crate) const LIVE_JOBS: std::ops::RangeInclusive<i64> = 0..=10_000;

/// Checks `[history]`; the error names the key.
pub(super) fn check(h: RawHistory) -> Result<HistoryConfig, (&'static str, String)> {
    let days = h.live_days.unwrap_or(7.0);
    if !LIVE_DAYS.contains(&days) {
        let (lo, hi) = (LIVE_DAYS.start(), LIVE_DAYS.end());
        return Err((
            "live_days",
            format!("must be between {lo} and {hi} days, got {days}"),
        ));
    }
    let jobs = h.live_jobs.unwrap_or(200);
    if !LIVE_JOBS.contains(&jobs) {
        let (lo, hi) = (LIVE_JOBS.start(), LIVE_JOBS.end());
        return Err((
            "live_jobs",
            format!("must be between {lo} and {hi}, got {jobs}"),
        ));
    }
    let keep_for = match h.keep_days {
        None => None,
        Some(keep) if KEEP_DAYS.contains(&keep) => Some(Duration::from_secs_f64(keep * 86_400.0)),
        Some(keep) => {
            let (lo, hi) = (KEEP_DAYS.start(), KEEP_DAYS.end());
            return Err((
                "keep_days",
                format!("must be between {lo} and {hi} days (leave it out to keep for good), got {keep}"),
            ));
        }
    };
    Ok(HistoryConfig {
        live_for: Duration::from_secs_f64(days * 86_400.0),
        live_jobs: jobs as usize,
        keep_for,
    })
}
