//! `[spool]`, `[control]` and `[farm]`: where the farm keeps its jobs and is reached, and
//! how it runs (heat-ups at once, stops, the hot folders' timing, this host's name).

use super::check::{seconds_in, shorten, Bounds, Context};
use super::checked::{FarmConfig, OnShutdown};
use super::error::ConfigError;
use super::printers::MAX_PRINTERS;
use super::raw::{RawConfig, RawFarm};
use std::path::{Path, PathBuf};

/// Settle time of a dropped file: long enough to see a write, short enough to notice.
const SETTLE_S: Bounds = 0.05..=3600.0;
/// Rescan period of the hot folders.
const RESCAN_S: Bounds = 0.5..=86_400.0;
/// How long prints may take to finish at a stop: from a second (tests) to two days.
pub(crate) const FINISH_TIMEOUT_S: Bounds = 1.0..=2.0 * 86_400.0;
/// Two hours, what the service unit once waited for a stop before it killed the daemon.
pub(crate) const DEFAULT_FINISH_TIMEOUT_S: f64 = 2.0 * 3600.0;

/// A spool with less than this left after a print is low: about one more small print.
pub(crate) const DEFAULT_SPOOL_LOW_G: f64 = 100.0;

/// Checks `[farm]` (all of it optional).
pub(super) fn check(raw: Option<RawFarm>, cx: &Context) -> Result<FarmConfig, ConfigError> {
    let Context { invalid, .. } = *cx;
    let raw_farm = raw.unwrap_or(RawFarm {
        max_heating: None,
        on_shutdown: None,
        settle_s: None,
        rescan_s: None,
        finish_timeout_s: None,
        host: None,
        spool_low_g: None,
    });
    let max_heating = match raw_farm.max_heating {
        None => 2,
        Some(n) if (1..=MAX_PRINTERS as i64).contains(&n) => n as usize,
        Some(n) => {
            return Err(invalid(
                "[farm]".into(),
                "max_heating",
                format!("must be between 1 and {MAX_PRINTERS}, got {n}"),
            ))
        }
    };
    let seconds = |key: &str, value: Option<f64>, default: f64, range: &Bounds| {
        seconds_in(value.unwrap_or(default), range).map_err(|m| invalid("[farm]".into(), key, m))
    };
    Ok(FarmConfig {
        max_heating,
        on_shutdown: raw_farm.on_shutdown.unwrap_or(OnShutdown::Finish),
        settle: seconds("settle_s", raw_farm.settle_s, 5.0, &SETTLE_S)?,
        rescan: seconds("rescan_s", raw_farm.rescan_s, 30.0, &RESCAN_S)?,
        finish_timeout: seconds(
            "finish_timeout_s",
            raw_farm.finish_timeout_s,
            DEFAULT_FINISH_TIMEOUT_S,
            &FINISH_TIMEOUT_S,
        )?,
        spool_low_g: match raw_farm.spool_low_g.unwrap_or(DEFAULT_SPOOL_LOW_G) {
            g if (0.0..=crate::daemon::filament::MAX_SPOOL_G).contains(&g) => g,
            g => {
                return Err(invalid(
                    "[farm]".into(),
                    "spool_low_g",
                    format!(
                        "must be between 0 and {} g, got {g}",
                        crate::daemon::filament::MAX_SPOOL_G
                    ),
                ))
            }
        },
        host: match raw_farm.host {
            None => this_hostname(),
            Some(h) => check_host_name(&h).map_err(|m| invalid("[farm]".into(), "host", m))?,
        },
    })
}

/// `[spool] dir` and the control socket (`[control] socket`, else `crispen.sock` in the
/// spool), made absolute: the one rule for the daemon and for the commands that reach it.
pub(super) fn spool_and_socket(
    raw: &RawConfig,
    file: &Path,
    base: &Path,
) -> Result<(PathBuf, PathBuf), ConfigError> {
    let invalid = |section: &str, key: &str| ConfigError::Invalid {
        file: file.to_path_buf(),
        section: section.into(),
        key: key.into(),
        message: "must not be empty".into(),
    };
    if raw.spool.dir.as_os_str().is_empty() {
        return Err(invalid("[spool]", "dir"));
    }
    // `join` keeps an absolute path as it is.
    let spool_dir = base.join(&raw.spool.dir);
    let socket = match &raw.control {
        Some(c) if c.socket.as_os_str().is_empty() => return Err(invalid("[control]", "socket")),
        Some(c) => base.join(&c.socket),
        None => spool_dir.join("crispen.sock"),
    };
    Ok((spool_dir, socket))
}

/// A host name as `[farm] host` takes it: it names the host in the farm database, the
/// logs and job reasons. 1 to 64 ASCII letters, digits, `.`, `_` and `-`, starting with a
/// letter, digit or `_` (so never `.`, `..` or an option-like `-x`).
fn check_host_name(name: &str) -> Result<String, String> {
    let ok = (1..=64).contains(&name.len())
        && name
            .chars()
            .all(|c| c.is_ascii_alphanumeric() || matches!(c, '.' | '_' | '-'))
        && !name.starts_with(['.', '-']);
    if ok {
        Ok(name.to_string())
    } else {
        Err(format!(
            "{}: use 1 to 64 letters, digits, '.', '_' or '-', not starting with '.' or '-'",
            shorten(&format!("{name:?}"))
        ))
    }
}

/// The system's host name (the default `[farm] host`), made to fit [`check_host_name`].
/// From uname(2), not /proc/sys (which the service unit's `ProcSubset=pid` hides).
fn this_hostname() -> String {
    let raw = nix::unistd::gethostname()
        .map(|h| h.to_string_lossy().into_owned())
        .unwrap_or_default();
    let name: String = raw
        .trim()
        .trim_start_matches(['.', '-'])
        .chars()
        .map(|c| {
            if c.is_ascii_alphanumeric() || matches!(c, '.' | '_' | '-') {
                c
            } else {
                '-'
            }
        })
        .take(64)
        .collect();
    if name.is_empty() {
        "localhost".into()
    } else {
        name
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A host name is a plain word of the farm: no `.`/`..`, nothing option-like, bounded.
    #[test]
    fn host_names() {
        for good in ["rack-1", "a", "_x", "host.example.org", &"h".repeat(64)] {
            assert_eq!(check_host_name(good).as_deref(), Ok(good), "{good}");
        }
        for bad in [
            "",
            ".",
            "..",
            "-",
            "-x",
            ".hidden",
            "a/b",
            "a b",
            "é",
            &"h".repeat(65),
        ] {
            assert!(check_host_name(bad).is_err(), "{bad:?}");
        }
        let long = check_host_name(&"/".repeat(4000)).unwrap_err();
        assert!(long.len() < 300, "{long}");
        assert!(check_host_name(&this_hostname()).is_ok());
    }
}
