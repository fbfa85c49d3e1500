//! What goes wrong with the farm database: [`PgError`], and how it reaches the store's
//! callers as a [`StoreError`]. Apart so the schema's migrations, the lease and the jobs'
//! transactions share it without depending on each other.

use crate::daemon::job::StoreError;
use std::path::PathBuf;

#[derive(Debug, thiserror::Error)]
pub enum PgError {
    #[error("[store] postgres: {0} (hint: put the password in [store] password_file or the PGPASSWORD environment variable, never in the connection string)")]
    PasswordInConnectionString(&'static str),
    #[error("[store] postgres: {0}")]
    BadConnectionString(String),
    #[error("[store] password_file {path}: {source}")]
    PasswordFile {
        path: PathBuf,
        source: std::io::Error,
    },
    #[error("[farm] host {host:?} is in use: another run of crispen holds this host's lease in the farm database for {remaining_s:.0} s more, and renews it while it runs (hint: give each machine its own [farm] host (the default is the hostname, which a cloned machine keeps); after a crash, start again once the lease has run out)")]
    HostInUse { host: String, remaining_s: f64 },
    #[error("[farm] host {host:?} was taken over by another run of crispen after this run's lease ran out: this run no longer acts for it (takes no work, records no outcome, publishes nothing) (hint: stop this run; give each machine its own [farm] host)")]
    Displaced { host: String },
    #[error("the farm database has schema version {found}, newer than this crispen knows ({known}) (hint: upgrade crispen on this host to the version the other hosts run)")]
    SchemaTooNew { found: i32, known: i32 },
    #[error("migrating the farm database to schema version {version}: {source}")]
    Migration {
        version: i32,
        source: tokio_postgres::Error,
    },
    #[error("the farm database is unreachable: {0}")]
    Pool(#[from] deadpool_postgres::PoolError),
    /// An earlier call found it unreachable (what that call met), and it has not been
    /// reached since.
    #[error("{0}")]
    Unreachable(String),
    #[error("the farm database: {0}")]
    Db(#[from] tokio_postgres::Error),
    /// What the job's rules refused (no such job, a change the table forbids, a claim lost).
    #[error(transparent)]
    Job(#[from] StoreError),
    #[error("job {id}: file {name}: {source}")]
    File {
        id: String,
        name: String,
        source: std::io::Error,
    },
    #[error(
        "job {id}: the farm database holds a value this crispen cannot read ({what}): {message}"
    )]
    Corrupt {
        id: String,
        what: &'static str,
        message: String,
    },
}

impl From<PgError> for StoreError {
    fn from(e: PgError) -> StoreError {
        match e {
            PgError::Job(e) => e,
            other => StoreError::Database {
                failure: if other.is_outage() {
                    crate::daemon::job::DatabaseFailure::Outage
                } else {
                    crate::daemon::job::DatabaseFailure::Other
                },
                message: other.to_string(),
            },
        }
    }
}

impl PgError {
    /// The database could not be reached or answered with a failure of its own (as opposed
    /// to refusing the change by the job's rules).
    pub(crate) fn is_outage(&self) -> bool {
        matches!(
            self,
            PgError::Pool(_) | PgError::Db(_) | PgError::Unreachable(_)
        )
    }
}
