//! Talking to Marlin printers.
//!
//! - [`firmware`]: what each supported firmware can do (buffer sizes, optional features).
//! - `gcode`, `motion`, `pause`: G-code as the firmware reads it: a job's commands, the
//!   one follower of where its moves take the head, and the pauses a file asks for.
//! - `protocol`: the host state machine. Pure: bytes and the current time go in, lines to
//!   send, events and deadlines come out. No ports, no clocks.
//! - `estimate`: how long a job takes as the firmware's planner moves it.
//! - `labels`: which part of a plate each command is, as the file labels it (read as a job
//!   is loaded).
//! - `plate`: a plate's parts, as its file labels them, and the host's filter that drops
//!   a cancelled part's lines.
//! - `transport` / `stream`: the serial port and the async driver around the state machine.
//!
//! The simulated printer that speaks the other side is the crate `crispen-sim`.

#![warn(unreachable_pub)]

pub mod estimate;
pub mod firmware;
pub mod gcode;
pub mod labels;
pub mod motion;
pub mod pause;
pub mod plate;
pub mod protocol;
pub mod reader;
pub mod stream;
pub mod transport;
