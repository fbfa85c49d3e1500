//! `[store]`: the farm database a shared farm keeps its queue in: its connection string
//! (the one rule for the config check and the store's connection), its password file and
//! its lease.

use super::check::{seconds_in, Bounds, Context};
use super::checked::{PgSettings, StoreConfig};
use super::error::ConfigError;
use super::raw::RawStore;
use super::secret::read_secret;
use std::path::Path;

/// Why a `[store] postgres` connection string is refused.
#[derive(Debug, Clone, PartialEq)]
pub(crate) enum ConninfoError {
    /// It holds a password, which belongs in `password_file` or `PGPASSWORD`.
    Password,
    /// It is too long, does not parse or names no server; the reason.
    Bad(String),
}

/// A `[store] postgres` connection string checked and parsed, the one rule for both the
/// config check and the store's connection: at most 4096 characters, it parses, names the
/// server (there is no default to fall back on), and holds no password.
pub(crate) fn parse_conninfo(conninfo: &str) -> Result<tokio_postgres::Config, ConninfoError> {
    if conninfo.len() > 4096 {
        return Err(ConninfoError::Bad(format!(
            "{} characters: too long for a connection string",
            conninfo.len()
        )));
    }
    let config: tokio_postgres::Config = conninfo.parse().map_err(|e: tokio_postgres::Error| {
        // The parser's reason (e.g. the unknown option) is the error's source.
        let reason = std::error::Error::source(&e).map(|s| format!(": {s}"));
        ConninfoError::Bad(format!("{e}{}", reason.unwrap_or_default()))
    })?;
    if config.get_hosts().is_empty() && config.get_hostaddrs().is_empty() {
        return Err(ConninfoError::Bad(format!(
            "{conninfo:?} names no server (hint: \"host=/run/postgresql dbname=crispen\", or host=NAME for one on another machine)"
        )));
    }
    if config.get_password().is_some() {
        return Err(ConninfoError::Password);
    }
    Ok(config)
}

/// Bounds of `[store] lease_s`: long enough for a busy host's heartbeat, short enough that
/// a dead host's printers are seen offline the same minute.
pub(crate) const LEASE_S: Bounds = 3.0..=600.0;

/// Checks `[store]` (stage two: its password file is not read yet).
pub(super) fn check(
    raw: Option<RawStore>,
    cx: &Context,
) -> Result<Option<StoreConfig>, ConfigError> {
    let Context { invalid, anchor } = *cx;
    let store = match raw {
        None => None,
        Some(s) => {
            let invalid = |key, m| invalid("[store]".into(), key, m);
            parse_conninfo(&s.postgres).map_err(|e| {
                invalid(
                    "postgres",
                    match e {
                        ConninfoError::Password => "the connection string holds a password (hint: put the password in [store] password_file or PGPASSWORD)".into(),
                        ConninfoError::Bad(m) => m,
                    },
                )
            })?;
            if s.password_file
                .as_ref()
                .is_some_and(|p| p.as_os_str().is_empty())
            {
                return Err(invalid("password_file", "must not be empty".into()));
            }
            Some(StoreConfig {
                postgres: PgSettings {
                    conninfo: s.postgres,
                    password_file: s.password_file.map(|p| anchor(&p)),
                },
                lease: seconds_in(s.lease_s.unwrap_or(15.0), &LEASE_S)
                    .map_err(|m| invalid("lease_s", m))?,
            })
        }
    };
    Ok(store)
}

/// Reads the password file (stage three), as the store will read it; a warning when others
/// can read it.
pub(super) fn resolve(
    store: Option<&StoreConfig>,
    file: &Path,
    warnings: &mut Vec<String>,
) -> Result<(), ConfigError> {
    if let Some(path) = store.and_then(|s| s.postgres.password_file.as_ref()) {
        let (_, warning) = read_secret(path).map_err(|m| ConfigError::Invalid {
            file: file.to_path_buf(),
            section: "[store]".into(),
            key: "password_file".into(),
            message: m,
        })?;
        if let Some(w) = warning {
            warnings.push(format!("[store] key `password_file`: {w}"));
        }
    }
    Ok(())
}
