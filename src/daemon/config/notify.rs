//! The `[[notify]]` tables: where the farm's events (a job done, failed, cancelled; a
//! printer offline, back, waiting, in error; a host of a shared farm lost) are sent, in
//! which shape, signed with which secret, and how long a receiver that does not answer is
//! retried. Checked here in the two stages of the config (the shape, then the secret file
//! in `resolve`), each error naming the table by its number and name, and the key.

use super::check::{seconds_in, Bounds};
use super::error::ConfigError;
use super::secret::read_secret;
use crate::outbound::HttpUrl;
use serde::Deserialize;
use std::path::{Path, PathBuf};
use std::time::Duration;

/// One `[[notify]]` table as written.
#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
pub(super) struct RawNotify {
    name: String,
    url: String,
    events: Option<Vec<String>>,
    format: Option<String>,
    secret_file: Option<PathBuf>,
    timeout_s: Option<f64>,
    retry_for_s: Option<f64>,
    max_attempts: Option<i64>,
    backoff_max_s: Option<f64>,
}

/// The events a receiver may ask for, by name (the `event` field of what is sent).
pub(crate) const EVENT_NAMES: [&str; 13] = [
    "job_done",
    "job_failed",
    "job_cancelled",
    "job_interrupted",
    "printer_error",
    "printer_offline",
    "printer_online",
    "printer_waiting",
    "host_lost",
    "spool_low",
    "bed_not_clear",
    "maintenance_due",
    "test",
];

/// The shape of what is sent.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum NotifyFormat {
    /// The event as JSON (a webhook, Home Assistant).
    Json,
    /// A message for an ntfy topic URL: text body, title, tags, priority and click link as
    /// headers (ntfy.sh or a self-hosted server; a phone subscribes to the topic).
    Ntfy,
    /// A Slack incoming webhook: `{"text": ...}`.
    Slack,
    /// A Discord webhook: `{"content": ...}` (at most 2000 characters).
    Discord,
}

impl NotifyFormat {
    pub(crate) const NAMES: [&'static str; 4] = ["json", "ntfy", "slack", "discord"];

    fn parse(name: &str) -> Option<NotifyFormat> {
        match name {
            "json" => Some(NotifyFormat::Json),
            "ntfy" => Some(NotifyFormat::Ntfy),
            "slack" => Some(NotifyFormat::Slack),
            "discord" => Some(NotifyFormat::Discord),
            _ => None,
        }
    }
}

/// A secret; never shown in logs or debug output.
#[derive(Clone, PartialEq, Eq)]
pub struct NotifySecret(pub Vec<u8>);

impl std::fmt::Debug for NotifySecret {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str("NotifySecret(..)")
    }
}

/// One checked `[[notify]]` table.
#[derive(Debug, Clone, PartialEq)]
pub struct Receiver {
    /// Its label: in logs, metrics (`receiver`) and the name of its queue on disk.
    pub name: String,
    pub url: HttpUrl,
    /// The event names it gets (all of [`EVENT_NAMES`] by default).
    pub events: Vec<String>,
    pub format: NotifyFormat,
    pub secret_file: Option<PathBuf>,
    /// Read from `secret_file` by `resolve` (None before, and without a secret file).
    pub secret: Option<NotifySecret>,
    /// One attempt (connect, send, answer) takes at most this long.
    pub timeout: Duration,
    /// An event not delivered this long after it happened is dropped (logged).
    pub retry_for: Duration,
    /// An event is dropped (logged) after this many failed attempts in one run.
    pub max_attempts: u32,
    /// The longest wait between attempts while the receiver is down.
    pub backoff_max: Duration,
}

impl Receiver {
    pub(crate) fn wants(&self, event: &str) -> bool {
        self.events.iter().any(|e| e == event)
    }
}

/// The checked notification settings.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct NotifyConfig {
    pub receivers: Vec<Receiver>,
    /// `[http] public_url`: the dashboard's address as the operator reaches it, put in
    /// every event as its link.
    pub dashboard: Option<String>,
}

/// Bounds of `timeout_s`.
pub(crate) const TIMEOUT_S: Bounds = 0.1..=120.0;
/// Bounds of `retry_for_s` (up to a week).
pub(crate) const RETRY_FOR_S: Bounds = 1.0..=7.0 * 86_400.0;
/// Bounds of `backoff_max_s`.
pub(crate) const BACKOFF_MAX_S: Bounds = 0.1..=3600.0;
/// Bounds of `max_attempts`.
pub(crate) const MAX_ATTEMPTS: std::ops::RangeInclusive<i64> = 1..=10_000;
/// Most receivers.
pub(crate) const MAX_RECEIVERS: usize = 32;
/// Longest receiver name; its characters are letters, digits, `-` and `_` (it names a
/// directory of the spool and a metrics label).
pub(crate) const MAX_NAME_CHARS: usize = 64;

/// Checks the `[[notify]]` tables and `[http] public_url` (stage two: nothing read).
pub(super) fn check(
    raw: Vec<RawNotify>,
    public_url: Option<&str>,
    file: &Path,
    anchor: &dyn Fn(&Path) -> PathBuf,
) -> Result<NotifyConfig, ConfigError> {
    let dashboard = match public_url {
        None => None,
        Some(u) => {
            HttpUrl::parse(u).map_err(|m| ConfigError::Invalid {
                file: file.to_path_buf(),
                section: "[http]".into(),
                key: "public_url".into(),
                message: m,
            })?;
            Some(u.trim_end_matches('/').to_string())
        }
    };
    if raw.len() > MAX_RECEIVERS {
        return Err(ConfigError::Invalid {
            file: file.to_path_buf(),
            section: format!("[[notify]] #{}", MAX_RECEIVERS + 1),
            key: "name".into(),
            message: format!("at most {MAX_RECEIVERS} receivers"),
        });
    }
    let mut receivers: Vec<Receiver> = Vec::new();
    for (i, r) in raw.into_iter().enumerate() {
        let receiver = check_receiver(i, r, &receivers, file, anchor)?;
        receivers.push(receiver);
    }
    Ok(NotifyConfig {
        receivers,
        dashboard,
    })
}

/// The `i`th `[[notify]]` table (from 0), named apart from the receivers `taken` before it.
fn check_receiver(
    i: usize,
    r: RawNotify,
    taken: &[Receiver],
    file: &Path,
    anchor: &dyn Fn(&Path) -> PathBuf,
) -> Result<Receiver, ConfigError> {
    let section = format!("[[notify]] #{} (name {:?})", i + 1, r.name);
    let invalid = |key: &str, message: String| ConfigError::Invalid {
        file: file.to_path_buf(),
        section: section.clone(),
        key: key.into(),
        message,
    };
    let name_ok = !r.name.is_empty()
        && r.name.chars().count() <= MAX_NAME_CHARS
        && r.name
            .chars()
            .all(|c| c.is_ascii_alphanumeric() || c == '-' || c == '_');
    if !name_ok {
        return Err(invalid(
            "name",
            format!("must be 1 to {MAX_NAME_CHARS} letters, digits, '-' or '_' (it names the receiver's queue in the spool)"),
        ));
    }
    if taken.iter().any(|o| o.name == r.name) {
        return Err(invalid(
            "name",
            "another [[notify]] table has this name".into(),
        ));
    }
    let url = HttpUrl::parse(&r.url).map_err(|m| invalid("url", m))?;
    let events = match r.events {
        None => EVENT_NAMES.iter().map(|e| e.to_string()).collect(),
        Some(list) => {
            if list.is_empty() {
                return Err(invalid(
                    "events",
                    "is empty: leave it out for every event, or remove the table".into(),
                ));
            }
            for e in &list {
                if !EVENT_NAMES.contains(&e.as_str()) {
                    return Err(invalid(
                        "events",
                        format!("unknown event {e:?}; known: {}", EVENT_NAMES.join(", ")),
                    ));
                }
            }
            let mut list = list;
            list.dedup();
            list
        }
    };
    let format = match &r.format {
        None => NotifyFormat::Json,
        Some(f) => NotifyFormat::parse(f).ok_or_else(|| {
            invalid(
                "format",
                format!(
                    "unknown format {f:?}; one of {}",
                    NotifyFormat::NAMES.join(", ")
                ),
            )
        })?,
    };
    let seconds = |key: &str, value: Option<f64>, default: f64, range: &Bounds| {
        seconds_in(value.unwrap_or(default), range).map_err(|m| invalid(key, m))
    };
    let timeout = seconds("timeout_s", r.timeout_s, 10.0, &TIMEOUT_S)?;
    let retry_for = seconds("retry_for_s", r.retry_for_s, 86_400.0, &RETRY_FOR_S)?;
    let backoff_max = seconds("backoff_max_s", r.backoff_max_s, 300.0, &BACKOFF_MAX_S)?;
    let max_attempts = r.max_attempts.unwrap_or(100);
    if !MAX_ATTEMPTS.contains(&max_attempts) {
        return Err(invalid(
            "max_attempts",
            format!(
                "must be from {} to {}, got {max_attempts}",
                MAX_ATTEMPTS.start(),
                MAX_ATTEMPTS.end()
            ),
        ));
    }
    Ok(Receiver {
        name: r.name,
        url,
        events,
        format,
        secret_file: r.secret_file.as_deref().map(anchor),
        secret: None,
        timeout,
        retry_for,
        max_attempts: max_attempts as u32,
        backoff_max,
    })
}

/// Reads each receiver's secret file (stage three); warnings for files others can read.
pub(super) fn resolve(
    notify: &mut NotifyConfig,
    file: &Path,
    warnings: &mut Vec<String>,
) -> Result<(), ConfigError> {
    for (i, r) in notify.receivers.iter_mut().enumerate() {
        let Some(path) = &r.secret_file else {
            continue;
        };
        let section = format!("[[notify]] #{} (name {:?})", i + 1, r.name);
        let invalid = |message: String| ConfigError::Invalid {
            file: file.to_path_buf(),
            section: section.clone(),
            key: "secret_file".into(),
            message,
        };
        let (text, warning) = read_secret(path).map_err(invalid)?;
        let secret = text.trim();
        if secret.len() < 16 {
            return Err(invalid(format!(
                "{} holds {} characters: a signing secret needs at least 16 (hint: head -c 32 /dev/urandom | base64 > {})",
                path.display(),
                secret.len(),
                path.display()
            )));
        }
        if let Some(w) = warning {
            warnings.push(format!("{section} key `secret_file`: {w}"));
        }
        r.secret = Some(NotifySecret(secret.as_bytes().to_vec()));
    }
    Ok(())
}
