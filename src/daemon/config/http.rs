//! `[http]`: the TCP listener of the HTTP API and dashboard, checked in two stages (its
//! address and limits, then its API key file), and the key file's one reader.

use super::checked::{ApiKey, CheckedHttp, FolderConfig, HttpConfig};
use super::error::ConfigError;
use super::octoprint;
use super::raw::RawHttp;
use super::secret::read_secret;
use std::path::{Path, PathBuf};

/// Shortest API key accepted: a guessable key on a network port is no key.
pub(crate) const MIN_API_KEY_CHARS: usize = 16;
/// Bounds of `[http] upload_max_mb`.
pub(crate) const UPLOAD_MAX_MB: std::ops::RangeInclusive<i64> = 1..=4096;

/// Checks `[http]`; errors name the key. Its key file is read by [`super::Checked::resolve`],
/// so a missing or weak key stops the daemon at startup rather than leaving the port open.
pub(super) fn check(
    h: RawHttp,
    anchor: &dyn Fn(&Path) -> PathBuf,
) -> Result<CheckedHttp, (&'static str, String)> {
    let listen: std::net::SocketAddr = h.listen.parse().map_err(|_| {
        (
            "listen",
            format!(
                "{:?} is not an address and port (e.g. \"0.0.0.0:8080\" or \"127.0.0.1:8080\")",
                h.listen
            ),
        )
    })?;
    // Port 0 lets the system pick one (tests); any other port below 1024 needs a
    // capability the service unit does not grant (`CapabilityBoundingSet=` is empty).
    if (1..1024).contains(&listen.port()) {
        return Err((
            "listen",
            format!(
                "port {} is privileged (below 1024): the daemon runs without the capability to bind it (hint: use a port from 1024 up, e.g. 8080, and a reverse proxy if it must be 80 or 443)",
                listen.port()
            ),
        ));
    }
    let upload_max_mb = h.upload_max_mb.unwrap_or(512);
    if !UPLOAD_MAX_MB.contains(&upload_max_mb) {
        return Err((
            "upload_max_mb",
            format!(
                "must be from {} to {}, got {upload_max_mb}",
                UPLOAD_MAX_MB.start(),
                UPLOAD_MAX_MB.end()
            ),
        ));
    }
    Ok(CheckedHttp {
        listen,
        api_key_file: anchor(&h.api_key_file),
        read_only_without_key: h.read_only_without_key.unwrap_or(false),
        upload_max_bytes: upload_max_mb as u64 * 1024 * 1024,
        octoprint: octoprint::check(h.announce, h.default_folder)?,
    })
}

/// Reads the API key file (stage three) and checks that `default_folder` names one of the
/// `folders`; a warning when others can read the key file.
pub(super) fn resolve(
    http: Option<CheckedHttp>,
    folders: &[FolderConfig],
    file: &Path,
    warnings: &mut Vec<String>,
) -> Result<Option<HttpConfig>, ConfigError> {
    let invalid = |key: &str, message: String| ConfigError::Invalid {
        file: file.to_path_buf(),
        section: "[http]".into(),
        key: key.into(),
        message,
    };
    let Some(h) = http else {
        return Ok(None);
    };
    let paths: Vec<&Path> = folders.iter().map(|f| f.path.as_path()).collect();
    octoprint::check_folder(&h.octoprint, &paths).map_err(|(key, m)| invalid(key, m))?;
    let (api_key, warning) =
        read_api_key_warning(&h.api_key_file).map_err(|m| invalid("api_key_file", m))?;
    if let Some(w) = warning {
        warnings.push(format!("[http] key `api_key_file`: {w}"));
    }
    Ok(Some(HttpConfig {
        listen: h.listen,
        api_key,
        read_only_without_key: h.read_only_without_key,
        upload_max_bytes: h.upload_max_bytes,
        any_port_if_taken: false,
        octoprint: h.octoprint,
    }))
}

/// Reads an API key file; a missing or weak key is refused (see [`read_secret`]).
pub(crate) fn read_api_key(key_file: &Path) -> Result<ApiKey, String> {
    read_api_key_warning(key_file).map(|(key, _)| key)
}

/// [`read_api_key`], with [`read_secret`]'s warning.
fn read_api_key_warning(key_file: &Path) -> Result<(ApiKey, Option<String>), String> {
    let (text, warning) = read_secret(key_file).map_err(|e| {
        if key_file.exists() {
            e
        } else {
            format!(
                "{e} (hint: make one: (umask 077; head -c 24 /dev/urandom | base64 > {}))",
                key_file.display()
            )
        }
    })?;
    let key = text.trim();
    if key.chars().count() < MIN_API_KEY_CHARS || !key.chars().all(|c| c.is_ascii_graphic()) {
        return Err(format!(
            "{}: the key must be at least {MIN_API_KEY_CHARS} printable ASCII characters without spaces",
            key_file.display()
        ));
    }
    Ok((ApiKey(key.to_string()), warning))
}
