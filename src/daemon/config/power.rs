//! `[printer.power]`: the switch in front of a printer (see `crate::power`) and when the
//! farm uses it: on when the printer has work, off after `off_after_idle_min` idle with its
//! hotend below `safe_hotend_c`.

use crate::outbound::HttpUrl;
use crate::power::Switch;
use std::time::Duration;

/// `[printer.power]` as written.
#[derive(Debug, serde::Deserialize)]
#[serde(deny_unknown_fields)]
pub(super) struct RawPower {
    pub(super) kind: String,
    pub(super) url: Option<String>,
    pub(super) entity: Option<String>,
    pub(super) token_file: Option<std::path::PathBuf>,
    pub(super) on_url: Option<String>,
    pub(super) off_url: Option<String>,
    pub(super) off_after_idle_min: Option<f64>,
    pub(super) safe_hotend_c: Option<f64>,
    pub(super) boot_s: Option<f64>,
}

/// `[printer.power]`, checked.
#[derive(Debug, Clone, PartialEq)]
pub struct PowerConfig {
    pub switch: Switch,
    /// Switched off once idle this long, cool, its bed clear; None: only by hand.
    pub off_after_idle: Option<Duration>,
    /// The hotend must be below this to be switched off (its fan cools it above).
    pub safe_hotend_c: f64,
    /// How long a printer switched on may take to appear and answer.
    pub boot: Duration,
}

/// Bounds: minutes idle before off, the hotend's safe temperature, the boot's wait.
const IDLE_MIN: std::ops::RangeInclusive<f64> = 0.01..=10_080.0;
const SAFE_C: std::ops::RangeInclusive<f64> = 25.0..=80.0;
const BOOT_S: std::ops::RangeInclusive<f64> = 1.0..=600.0;

/// Checks `[printer.power]`; the error names the key.
pub(super) fn check(
    raw: RawPower,
    anchor: &dyn Fn(&std::path::Path) -> std::path::PathBuf,
) -> Result<PowerConfig, (&'static str, String)> {
    let url =
        |key: &'static str, text: Option<String>| -> Result<HttpUrl, (&'static str, String)> {
            let text = text.ok_or((key, format!("kind {:?} needs `{key}`", raw.kind)))?;
            HttpUrl::parse(&text).map_err(|e| (key, e))
        };
    let only = |key: &'static str, set: bool, kinds: &str| {
        if set {
            Err((key, format!("goes with kind {kinds} only")))
        } else {
            Ok(())
        }
    };
    let switch = match raw.kind.as_str() {
        "tasmota" | "shelly" | "shelly-rpc" => {
            only("entity", raw.entity.is_some(), "\"homeassistant\"")?;
            only("token_file", raw.token_file.is_some(), "\"homeassistant\"")?;
            only("on_url", raw.on_url.is_some() || raw.off_url.is_some(), "\"http\"")?;
            let u = url("url", raw.url.clone())?;
            match raw.kind.as_str() {
                "tasmota" => Switch::Tasmota(u),
                "shelly" => Switch::ShellyGen1(u),
                _ => Switch::ShellyRpc(u),
            }
        }
        "homeassistant" => {
            only("on_url", raw.on_url.is_some() || raw.off_url.is_some(), "\"http\"")?;
            let entity = raw
                .entity
                .clone()
                .ok_or(("entity", "kind \"homeassistant\" needs `entity` (switch.NAME)".to_string()))?;
            let ok = entity.strip_prefix("switch.").is_some_and(|n| {
                !n.is_empty() && n.chars().all(|c| c.is_ascii_alphanumeric() || c == '_')
            });
            if !ok {
                return Err(("entity", format!("must be a switch entity (switch.NAME, letters, digits and _), got {entity:?}")));
            }
            let token_file = raw
                .token_file
                .as_deref()
                .ok_or(("token_file", "kind \"homeassistant\" needs `token_file` (a long-lived access token)".to_string()))?;
            Switch::HomeAssistant {
                url: url("url", raw.url.clone())?,
                entity,
                token_file: anchor(token_file),
            }
        }
        "http" => {
            only("url", raw.url.is_some(), "tasmota, shelly, shelly-rpc or homeassistant")?;
            Switch::Http {
                on: url("on_url", raw.on_url.clone())?,
                off: url("off_url", raw.off_url.clone())?,
            }
        }
        other => {
            return Err((
                "kind",
                format!("\"tasmota\", \"shelly\", \"shelly-rpc\", \"homeassistant\" or \"http\", got {other:?}"),
            ))
        }
    };
    let within = |key: &'static str, v: f64, range: std::ops::RangeInclusive<f64>| {
        if v.is_finite() && range.contains(&v) {
            Ok(v)
        } else {
            Err((
                key,
                format!(
                    "must be from {} to {}, got {}",
                    range.start(),
                    range.end(),
                    super::check::number(v)
                ),
            ))
        }
    };
    let off_after_idle = match raw.off_after_idle_min {
        None => None,
        Some(m) => Some(Duration::from_secs_f64(
            within("off_after_idle_min", m, IDLE_MIN)? * 60.0,
        )),
    };
    Ok(PowerConfig {
        switch,
        off_after_idle,
        safe_hotend_c: within("safe_hotend_c", raw.safe_hotend_c.unwrap_or(50.0), SAFE_C)?,
        boot: Duration::from_secs_f64(within("boot_s", raw.boot_s.unwrap_or(120.0), BOOT_S)?),
    })
}
