//! Notifications: the farm tells the operator what needs them (a bed to clear, a failed
//! job, a printer offline or waiting) by HTTP to the `[[notify]]` receivers, in the
//! shape each one reads (a JSON webhook, ntfy, Slack, Discord), optionally signed.
//!
//! - [`observe`]: events derived from the farm's published state, without I/O.
//! - [`outbox`]: each receiver's queue of pending events, files in the spool, so what
//!   was seen survives a restart.
//! - [`wire`]: one attempt to send one event (body, signature, HTTP with a time limit).
//! - [`deliver`]: the tasks: one observes and queues, one per receiver sends, retrying
//!   with backoff (bounded in time and count) with the same event id.
//! - [`counts`]: what became of the attempts, for `/metrics`.
//!
//! A slow or dead receiver delays nothing else: the observer only writes small files and
//! wakes the receivers' tasks, each attempt has a time limit, and each queue is bounded.

pub(crate) mod counts;
pub(crate) mod deliver;
pub(crate) mod event;
pub(crate) mod observe;
pub(crate) mod outbox;
pub mod wire;

pub use counts::Counts;
pub use deliver::run;
pub use event::{Event, EventKind};
