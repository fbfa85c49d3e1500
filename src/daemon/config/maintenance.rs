//! `[[maintenance]]`: the care each printer needs by use (see `crate::daemon::care`): a
//! task's name, the printers or tags it applies to, its intervals (print hours, kg of
//! filament, kg of abrasive filament, prints, days; due when any is reached) and whether a
//! due task keeps its printer out of the queue.

use super::check::number;
use super::checked::PrinterConfig;
use super::raw::RawMaintenance;
use crate::daemon::care::{Measure, Task};
use std::collections::BTreeSet;

/// At most this many tasks.
pub(crate) const MAX_TASKS: usize = 100;
/// The bounds of an interval in `measure`.
fn bounds(measure: Measure) -> std::ops::RangeInclusive<f64> {
    match measure {
        Measure::PrintHours => 0.1..=100_000.0,
        Measure::Kg | Measure::AbrasiveKg => 0.01..=10_000.0,
        Measure::Jobs => 1.0..=1_000_000.0,
        Measure::Days => 0.01..=3650.0,
    }
}
/// The longest task name, in characters.
const NAME_CHARS: usize = 64;

/// Checks every `[[maintenance]]` table against the printers; the error names the table
/// (by its place and name) and the key.
pub(super) fn check(
    raw: Vec<RawMaintenance>,
    printers: &[PrinterConfig],
) -> Result<Vec<Task>, (String, &'static str, String)> {
    if raw.len() > MAX_TASKS {
        return Err((
            "[[maintenance]]".into(),
            "name",
            format!("at most {MAX_TASKS} tasks, got {}", raw.len()),
        ));
    }
    let mut names = BTreeSet::new();
    let mut tasks = Vec::new();
    for (i, m) in raw.into_iter().enumerate() {
        let section = format!("[[maintenance]] #{} (name {:?})", i + 1, m.name);
        let err = |key: &'static str, message: String| (section.clone(), key, message);
        let bad_name = m.name.trim().is_empty()
            || m.name.chars().count() > NAME_CHARS
            || m.name.contains('/')
            || crate::names::problem(&m.name).is_some();
        if bad_name {
            return Err(err(
                "name",
                format!("must be 1 to {NAME_CHARS} characters, without `/`, control characters or bidi controls"),
            ));
        }
        if !names.insert(m.name.clone()) {
            return Err(err("name", "is used by another task".into()));
        }
        let listed = m.printers.unwrap_or_default();
        if let Some(p) = listed
            .iter()
            .find(|p| !printers.iter().any(|c| &c.name == *p))
        {
            return Err(err("printers", format!("no [[printer]] is named {p:?}")));
        }
        let tags = m.tags.unwrap_or_default();
        if let Some(t) = tags
            .iter()
            .find(|t| !printers.iter().any(|c| c.tags.contains(t)))
        {
            return Err(err("tags", format!("no [[printer]] has the tag {t:?}")));
        }
        let mut every = Vec::new();
        for (measure, value) in [
            (Measure::PrintHours, m.every_print_hours),
            (Measure::Kg, m.every_kg),
            (Measure::AbrasiveKg, m.every_abrasive_kg),
            (Measure::Jobs, m.every_jobs),
            (Measure::Days, m.every_days),
        ] {
            let Some(v) = value else { continue };
            let range = bounds(measure);
            // Prints are counted whole.
            let whole = measure != Measure::Jobs || v.fract() == 0.0;
            if !(v.is_finite() && range.contains(&v) && whole) {
                let what = if measure == Measure::Jobs {
                    "a whole number"
                } else {
                    "a number"
                };
                return Err(err(
                    measure.key(),
                    format!(
                        "must be {what} from {} to {}, got {}",
                        number(*range.start()),
                        number(*range.end()),
                        number(v)
                    ),
                ));
            }
            every.push((measure, v));
        }
        if every.is_empty() {
            let keys: Vec<&str> = Measure::ALL.iter().map(|m| m.key()).collect();
            return Err(err(
                Measure::PrintHours.key(),
                format!("a task needs an interval: one of {}", keys.join(", ")),
            ));
        }
        tasks.push(Task {
            name: m.name,
            printers: listed,
            tags,
            every,
            block: m.block.unwrap_or(false),
        });
    }
    Ok(tasks)
}
