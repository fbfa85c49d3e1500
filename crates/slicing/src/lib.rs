//! From an enhanced mesh to checked G-code and the pictures of its print.
//!
//! - [`slice`](mod@slice): running a real slicer (PrusaSlicer, CuraEngine) on a mesh, its
//!   profiles and the policy that checks what it wrote.
//! - [`machine`]: the kinds of printer a job is sliced for (bed, nozzle, filament,
//!   firmware), and their start, end and eject G-code.
//! - [`preview`]: pictures of a mesh before and after enhancement, of its print, and the
//!   G-code's thumbnails.
//! - [`observe`]: a model of a person looking at a print: how much a small print looks
//!   like the same model printed large, from their G-code; [`observation`] is what it
//!   reports.
//!
//! The farm (`crispen`) prepares its jobs with it; nothing here knows jobs or printers at
//! work.

#![warn(unreachable_pub)]

pub mod machine;
pub mod observation;
pub mod observe;
pub mod preview;
pub mod slice;
