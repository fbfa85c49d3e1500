//! Preparing a job: read its sidecar, work out the folder's settings with the sidecar's
//! overrides and the machines that may print it (the distinct machines of the printers
//! serving its folder), then enhance the model once and slice it once per machine into
//! `<job dir>/<file>.<machine>.gcode` ([`steps`]), keeping the enhanced mesh that was
//! sliced as `<job dir>/<file>.enhanced.stl`. A dropped `.gcode` file is not sliced: it is
//! checked against each machine ([`crate::slice::presliced`]) and printed as it is. Every
//! G-code, dropped or sliced, passes the host's load checks and the G-code policy
//! ([`crate::slice::policy`]) here, before a printer may claim it; the verdict is in the
//! job's report.
//! [`queue`] is the daemon's loop that takes queued jobs through this.
//!
//! An enhanced job is ready as soon as its own G-code is checked. Whether the enhancement
//! reaches the nozzle (its outer walls against the unmodified model's, sliced the same
//! way: [`crate::slice::walls`]) is measured afterwards by a task of its own
//! ([`PrepareTask::compare`]), which the queue runs only while no job is being prepared or
//! waits to be, in a child process at the lowest CPU priority: the measurement used to
//! nearly double every job's preparation.
//!
//! The work runs in a child process (`crispen prepare-job`, [`run_child`]) rather than on a
//! thread: loading, cleaning and enhancing a model are long computations with nowhere to
//! stop, so a hostile or merely huge file could otherwise hold a preparation slot for as
//! long as it likes. A child can be killed at once, whatever it is doing, when the job is
//! cancelled, the daemon stops, or the configured time limit passes, and its memory goes
//! back to the system when it ends. The child speaks [`ChildMessage`] JSON lines on stdout.
//!
//! - [`task`]: what one preparation is, as the daemon hands it to the child, and what the
//!   child answers.
//! - [`process`]: the daemon's side, running the child; [`work`]: the child's side.
//! - [`steps`]: enhancing and slicing a model; [`queue`]: the daemon's loop.

pub(crate) mod process;
pub mod queue;
pub mod steps;
pub(crate) mod task;
pub(crate) mod work;

pub use process::{run_child, run_compare_child, PrepareError};
pub use task::{is_presliced, resolve_task, ChildMessage, PrepareTask, Prepared, TaskMachine};
pub use work::{answer, run_task};
