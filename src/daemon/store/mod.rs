//! The job store as one owner: a single task ([`start`]) owns the store (the embedded
//! spool, [`spool::SpoolStore`], or the farm database, [`postgres::store::PgJobStore`]) and
//! is the only place a job or a bed gate changes. Everyone else holds a cheap, cloneable
//! [`StoreHandle`] and sends it requests (an mpsc message with a oneshot reply). The store's
//! trait is async ([`JobStore`]): the spool's disk work runs on a blocking thread, the
//! database's is awaited on its async client, so neither holds up the runtime, and no lock
//! is held across them, because nothing else can reach the store.
//! The daemon runs the task in its supervised set: a panic (in the store, or in a
//! request's edit) is not caught, so the daemon stops rather than go on with a change
//! done halfway.
//!
//! What follows from a job's change is the task's too: its `job state` log line, the
//! counts by state and the metrics' tally, published in the same snapshot as the change
//! ([`Snapshot::counts`], [`Snapshot::tally`]). They are worked out from the difference
//! between each job's record and the one published before, so a change another host
//! made (taken in by a resync) is counted like one of this host's.
//!
//! Readers do not queue behind writes: after every batch the task publishes an immutable
//! [`Snapshot`] (a `watch` of an `Arc`), which status, HTTP, metrics and the printers'
//! glances read for free. A reply is sent only after the snapshot holding its change is
//! published, so a caller always reads its own writes.
//!
//! Checks that must not be split from their change (claiming a ready job, cancelling a job
//! that has not started printing, clearing a bed, a late sidecar) are single requests, so
//! no other change can come between. Legal state changes stay one table,
//! [`JobState::can_go_to`], applied by [`Job::apply_transition`] inside the store.
//!
//! Finished jobs leave the live snapshot for the [`history`]: beyond `live_jobs` at the
//! change that made one too many, older than `live_for` at a round every ten minutes
//! (`task::RETIRE_EVERY`); the task retires them in batches, so what every reader pays for follows the jobs at work, not the farm's past. The snapshot also
//! keeps what would otherwise be looked up on disk at every glance (which pictures a job
//! has), worked out once when the job changes.
//!
//! [`postgres`] is the second store: the farm's queue in PostgreSQL, shared by several
//! hosts. Other hosts change jobs too, so its store reloads them on [`StoreHandle::resync`]
//! and the snapshot is rebuilt; a state check (`from`) is made inside the store, where the
//! database row is locked, never against a snapshot that may be stale.
//!
//! [`JobState::can_go_to`]: crate::daemon::job::JobState::can_go_to
//! [`Job::apply_transition`]: crate::daemon::job::Job::apply_transition

pub mod history;
pub mod pending;
pub mod postgres;
pub(crate) mod spool;
pub mod stats;

mod change;
mod clients;
mod copies;
mod counts;
mod handle;
pub(crate) mod job_store;
pub(crate) mod request;
mod retiring;
mod rules;
mod snapshot;
mod task;
#[cfg(test)]
mod task_tests;

pub use change::{InventoryChange, JobChange, PreparedJob, Use};
pub(crate) use clients::spool_relative;
pub(crate) use handle::StoreHandle;
pub use history::Retention;
pub(crate) use job_store::{InventoryEdit, JobEdit, JobStore, RetiredJob};
pub(crate) use request::BedChange;
pub(crate) use rules::{check_from, prepared, retired_refusal, StateFilter};
pub use snapshot::{Snapshot, PICTURES};
pub use task::{spawn, spawn_with, start, StoreTask};

/// Runs blocking `work` (the disk) on a blocking thread, for a store's async method; a
/// panic in it goes on as the caller's.
pub(crate) async fn blocking<T: Send + 'static>(work: impl FnOnce() -> T + Send + 'static) -> T {
    match tokio::task::spawn_blocking(work).await {
        Ok(out) => out,
        Err(e) => match e.try_into_panic() {
            Ok(panic) => std::panic::resume_unwind(panic),
            // Only a runtime shutting down cancels it, with the store's task.
            Err(e) => panic!("a job store's blocking work was cancelled: {e}"),
        },
    }
}
