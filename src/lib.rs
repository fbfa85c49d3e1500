//! crispen: make small 3D prints keep the features of their big originals.
//!
//! The library is layered so each part can be used and tested on its own; `mesh` and
//! `enhance` (the crate `crispen-geometry`), `marlin` (`crispen-marlin`), `sim`
//! (`crispen-sim`), `slice`, `machine`, `preview`, `observe` and `observation`
//! (`crispen-slicing`), `outbound` and `power` (`crispen-adapters`) and `fsutil`
//! (`crispen-fsutil`) are crates of their own under `crates/`, re-exported here:
//! - [`mesh`]: reading, cleaning and writing triangle meshes (STL, OBJ, 3MF). No async.
//! - [`enhance`]: adaptive unsharp masking of geometry (Herholz et al. 2017). No I/O.
//! - [`preview`]: pictures of a mesh before and after enhancement, and G-code thumbnails.
//! - [`observe`]: a model of a person looking at a print: how much a small print looks
//!   like the same model printed large, from their G-code.
//! - [`slice`](mod@slice): running a real slicer (PrusaSlicer, CuraEngine) on an enhanced mesh.
//! - [`machine`]: the kinds of printer a job is sliced for (bed, nozzle, filament, firmware).
//! - [`marlin`]: the Marlin host protocol as a pure state machine, and its serial transport.
//! - [`sim`]: the simulated printer used by tests, the quick start and the demo farm.
//! - [`ports`]: finding serial devices and asking a printer what it is (M115).
//! - [`daemon`]: the print-farm service: config, hot folders, job spool, printer
//!   supervisors, control socket.
//! - [`http`]: the HTTP API, web dashboard, metrics and OctoPrint-compatible upload,
//!   serving the farm's handles and operations.
//! - [`notify`]: notifications of the farm's events (a bed to clear, a failed job, a
//!   printer offline) to webhooks, ntfy, Slack and Discord, queued in the spool.
//! - [`bedcheck`]: the camera's bed check: a frame against the picture of the empty bed.
//!   No I/O.
//! - [`camera`]: the printers' cameras: frames fetched off the printing path, each
//!   printer's picture, and the snapshots and timelapse kept with each job.
//! - [`power`]: the printers' power switches (Tasmota, Shelly, Home Assistant, plain
//!   HTTP): the requests and answers of each, below the farm that decides.
//! - [`spoolman`]: a client for Spoolman, the filament-spool inventory server: spools, and
//!   the filament a print used booked against its spool.
//! - [`service`]: `crispen run` as one supervised service: wires `daemon` and `http`.
//! - `fsutil`: the one atomic, durable file write (`fsutil::write_atomic`).
//! - `outbound`: outbound HTTP (notifications, cameras, Spoolman), its TLS client and the
//!   URLs it is given.
//! - [`calendar`]: the calendar dates of the farm's times, in UTC.
//! - [`percent`]: names in addresses (percent-encoding), for the API, its clients and links.
//! - [`names`]: what a name an operator gives may hold, and how any name is shown.
//!
//! The `crispen` command line lives on the binary's side (`src/cli`), so the library does
//! not depend on clap, anyhow or indicatif.

// `pub(crate)` is the default: an item is `pub` only when something outside the library (the
// binary, tests/, benches/, fuzz/) names it, so the public API is what is used.
#![warn(unreachable_pub)]

pub mod bedcheck;
pub mod calendar;
pub mod camera;
pub mod daemon;
use crispen_fsutil as fsutil;
pub use crispen_geometry::enhance;
pub mod http;
pub use crispen_geometry::mesh;
pub use crispen_marlin as marlin;
pub mod names;
pub mod notify;
pub mod percent;
pub mod ports;
pub mod service;
pub use crispen_adapters::{outbound, power};
pub use crispen_sim as sim;
pub use crispen_slicing::{machine, observation, observe, preview, slice};
pub mod spoolman;
