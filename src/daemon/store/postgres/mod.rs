//! The farm's queue in PostgreSQL, shared by several hosts (issue 12's store). Hosts share
//! nothing but the database: jobs with their history, reports and files, printers with
//! their bed gates, and each host's lease.
//!
//! Every change of a job is one transaction on its locked row ([`PgStore::modify`]),
//! checked against [`JobState::can_go_to`], the same table as the spool's, and against who
//! holds the job: a job preparing or printing belongs to the host that claimed it, and
//! only that host records what became of it. Claims of the oldest waiting job
//! ([`PgStore::claim_preparation`], [`PgStore::claim_print`]) use `FOR UPDATE SKIP LOCKED`,
//! so hosts claiming at once never wait on each other and a job goes to one printer once.
//! A host that stops renewing its lease loses its work by the rules of
//! [`PgStore::expire_hosts`]: preparing jobs go back to the queue, printing jobs become
//! `interrupted` (never reprinted on their own), and its printers show as offline with the
//! time they were last seen.
//!
//! A host's name is held by one run of crispen at a time: each run draws a random token
//! and takes the host's row with it ([`PgStore::connect`]), which it may only do once the
//! lease of the run before has run out ([`PgError::HostInUse`] otherwise: a cloned machine
//! keeps the hostname, the default `[farm] host`). Every change a run makes checks, in its
//! transaction, that the row still holds its token; a run whose token was replaced (its
//! lease lapsed during an outage and a new run took the name) is [`PgError::Displaced`]
//! and acts for the host no more.
//!
//! - [`schema`]: the versioned schema and its migrations.
//! - [`store`]: the daemon's [`super::JobStore`] over it: a local copy of each job's files,
//!   and outcomes kept while the database is unreachable.
//!
//! [`JobState::can_go_to`]: crate::daemon::job::JobState::can_go_to

pub mod schema;
pub mod store;

mod commands;
mod copy;
mod error;
mod filament;
mod history;
mod jobs;
mod lease;
mod printers;
mod rows;

pub use copy::{FileBody, MAX_FILE_BYTES};
pub use error::PgError;
pub(crate) use jobs::{Change, Changes};
pub use lease::{Expired, FarmHost, PgStore};
