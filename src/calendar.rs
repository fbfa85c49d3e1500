//! Calendar dates of the farm's times (seconds since the epoch, as jobs keep them), in
//! UTC, through `jiff`: the history's monthly files and CSV, the statistics' days, the
//! CLI's tables. A time outside the years 1970 to 9999 is shown as the nearest of them.

use jiff::civil::{Date, DateTime};
use jiff::tz::Offset;
use jiff::Timestamp;

/// The UTC date and time of `t`, to the second.
fn utc(t: f64) -> DateTime {
    let last = Timestamp::MAX.as_second();
    let second = if t.is_nan() {
        0
    } else {
        t.floor().clamp(0.0, last as f64) as i64
    };
    let at = Timestamp::from_second(second).unwrap_or(Timestamp::UNIX_EPOCH);
    Offset::UTC.to_datetime(at)
}

/// `YYYY-MM-DDTHH:MM:SSZ`.
pub fn iso_utc(t: f64) -> String {
    utc(t).strftime("%Y-%m-%dT%H:%M:%SZ").to_string()
}

/// `YYYY-MM-DD HH:MM`.
pub fn utc_minute(t: f64) -> String {
    utc(t).strftime("%Y-%m-%d %H:%M").to_string()
}

/// `YYYY-MM-DD`.
pub fn date_of(t: f64) -> String {
    utc(t).strftime("%Y-%m-%d").to_string()
}

/// `YYYY-MM`.
pub fn month_of(t: f64) -> String {
    utc(t).strftime("%Y-%m").to_string()
}

/// The time of a UTC date's midnight, written `YYYY-MM-DD` (1970 to 9999); None for
/// anything else, a day the month does not have among them.
pub fn midnight_of(text: &str) -> Option<f64> {
    let date: Date = text.parse().ok()?;
    // jiff also reads a longer form (`2026-02-01T…`); only the date itself is one here.
    if text.len() != 10 || !(1970..=9999).contains(&date.year()) {
        return None;
    }
    let at = Offset::UTC
        .to_timestamp(date.to_datetime(jiff::civil::Time::midnight()))
        .ok()?;
    Some(at.as_second() as f64)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn times_are_written_as_utc_dates() {
        // 2024-02-29T12:00:00Z, a leap day.
        let t = 1_709_208_000.0;
        assert_eq!(iso_utc(t), "2024-02-29T12:00:00Z");
        assert_eq!(iso_utc(t + 0.9), "2024-02-29T12:00:00Z");
        assert_eq!(utc_minute(t + 59.0), "2024-02-29 12:00");
        assert_eq!(date_of(t), "2024-02-29");
        assert_eq!(month_of(t), "2024-02");
        assert_eq!(month_of(0.0), "1970-01");
        assert_eq!(month_of(1_796_220_000.0), "2026-12");
        // Out of range, nonsense: the nearest date shown.
        assert_eq!(iso_utc(-5.0), "1970-01-01T00:00:00Z");
        assert_eq!(iso_utc(f64::NAN), "1970-01-01T00:00:00Z");
        // jiff's last instant is late on 9999-12-30 UTC (its offsets reach a day either way).
        assert_eq!(date_of(f64::INFINITY), "9999-12-30");
    }

    #[test]
    fn dates_are_read_as_their_midnight() {
        assert_eq!(midnight_of("2024-02-29"), Some(1_709_164_800.0));
        assert_eq!(midnight_of("1970-01-01"), Some(0.0));
        for bad in [
            "2026-02-31",
            "2026-13-01",
            "1969-12-31",
            "2024-2-29",
            "2024-02-29T00:00",
            "x",
            "",
        ] {
            assert_eq!(midnight_of(bad), None, "{bad}");
        }
        // Every day of a leap year and the year after reads back as itself.
        let start = midnight_of("2024-01-01").unwrap();
        for day in 0..731 {
            let t = start + f64::from(day) * 86_400.0;
            assert_eq!(midnight_of(&date_of(t)), Some(t));
        }
    }
}
