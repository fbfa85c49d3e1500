//! The integration tests as one binary: each module is what was once a test binary of its
//! own. One binary links the crate once (each link carries faer) and runs every test on
//! one pool of threads, so a daemon test waiting on its simulated printer overlaps with
//! the slicer and enhancement tests instead of waiting for them in a queue of binaries.
//! `tests/firmware.rs` stays a binary of its own: it runs at the real printers' pace and
//! is counted apart.
//!
//! Run one module with a filter: `cargo test --test suite daemon::`.

#[path = "../common/mod.rs"]
mod common;

mod bedcheck;
mod camera;
mod copies;
mod daemon;
mod enhance;
mod farm;
mod filament;
mod history;
mod http;
mod layers;
mod machines;
mod maintenance;
mod mesh_io;
mod night;
mod notify;
mod observe;
mod octoprint;
mod pauses;
mod plates;
mod policy;
mod ports;
mod postgres;
mod power;
mod presliced;
mod preview;
mod print;
mod routing;
mod service;
mod sim;
mod slice;
mod spoolman;
