//! What starting the daemon's pieces (its store, its printers) can fail with: a module of
//! its own, below both the daemon's root and the fleet that starts the printers, so that
//! each can name it.

use super::{config, job, store};

#[derive(Debug, thiserror::Error)]
pub enum DaemonError {
    #[error(transparent)]
    Config(#[from] config::ConfigError),
    #[error(transparent)]
    Store(#[from] job::StoreError),
    #[error(transparent)]
    Control(#[from] ControlError),
    #[error("printer {printer}: cannot start its simulator: {message}")]
    Simulator { printer: String, message: String },
    #[error("[store] postgres: {0}")]
    Database(#[from] store::postgres::PgError),
    /// Another run holds this host's name in the farm ([`store::postgres::PgError::HostInUse`]).
    #[error("{0}")]
    HostInUse(store::postgres::PgError),
}

/// The control socket cannot be set up.
#[derive(Debug, thiserror::Error)]
#[error("control socket {socket}: {source}")]
pub struct ControlError {
    pub socket: std::path::PathBuf,
    #[source]
    pub source: std::io::Error,
}
