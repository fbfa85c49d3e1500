//! What the checks of every section share: how a wrong value is named in the file and a
//! relative path anchored at its directory ([`Context`]), bounded seconds, and numbers and
//! values as an error shows them. Apart from the sections so that each can use them.

use super::error::ConfigError;
use std::path::{Path, PathBuf};
use std::time::Duration;

/// What each section's check is handed by the second stage.
#[derive(Clone, Copy)]
pub(super) struct Context<'a> {
    /// The error for a wrong value: its section, its key and what is wrong with it.
    pub invalid: &'a dyn Fn(String, &str, String) -> ConfigError,
    /// A path of the file made absolute: relative paths are relative to the file's
    /// directory.
    pub anchor: &'a dyn Fn(&Path) -> PathBuf,
}

/// A range of seconds a setting may take.
pub type Bounds = std::ops::RangeInclusive<f64>;

/// A number of seconds within `range`, as a duration (never a panic for NaN, infinity or
/// a value too big for a `Duration`).
pub(super) fn seconds_in(value: f64, range: &Bounds) -> Result<Duration, String> {
    if value.is_finite() && range.contains(&value) {
        Ok(Duration::from_secs_f64(value))
    } else {
        Err(format!(
            "must be a number of seconds from {} to {}, got {}",
            range.start(),
            range.end(),
            number(value)
        ))
    }
}

pub use crate::names::number;

/// A value as an error echoes it: at most 80 characters, the rest marked as cut.
pub(super) fn shorten(text: &str) -> String {
    match text.char_indices().nth(80) {
        None => text.to_string(),
        Some((cut, _)) => format!("{}… ({} characters)", &text[..cut], text.chars().count()),
    }
}
