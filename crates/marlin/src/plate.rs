//! Plates: several parts on one bed, each labelled by the slicer that laid it out, and a
//! part dropped mid-print while the others print on, by the host on any firmware.
//!
//! - the sibling `labels`: the ways slicers and firmwares say which part a line belongs
//!   to (PrusaSlicer's `; printing object`, CuraEngine's `;MESH:`, Klipper's
//!   `EXCLUDE_OBJECT_*`, Marlin's `M486`), read as a file is loaded into [`Marks`] (apart
//!   from this module, which follows the loaded program: the loader reads labels);
//! - `map`: each part's name, outline on the bed and filament, and the plate's layers
//!   ([`PlateMap`]);
//! - `filter`: what the host sends once parts are cancelled ([`PartFilter`]), pure: a
//!   command in, the line to send (or none) out;
//! - `lines`: the job's lines as the protocol core takes them, one at a time, through the
//!   filter ([`JobLines`]).
//!
//! Where the firmware has `M486` (`CANCEL_OBJECTS`), the host could leave the cancel to
//! it; it does not: the host's filter works the same on every firmware, and a firmware's
//! own cancel would leave the host's follower (the pauses' park, the filament booked, the
//! time left) guessing what the printer skipped.

mod filter;
mod lines;
mod map;

pub use crate::labels::{Marks, MAX_NAME_CHARS, MAX_PARTS};
pub use filter::{Decision, PartFilter};
pub use lines::JobLines;
pub use map::{Layer, PartInfo, PlateMap};

use crate::gcode::GcodeProgram;
use std::borrow::Cow;
use std::sync::Arc;

/// The lines a print of `program` sent, with `cancels` (`(part, command it was dropped
/// from)`) as they were made while it printed: what the host's filter decided, replayed,
/// per command of the program (None: not sent). Without a plate, the program's own.
pub fn sent_lines<'a>(
    program: &'a GcodeProgram,
    cancels: &[(u16, usize)],
) -> Box<dyn Iterator<Item = (usize, Option<Cow<'a, str>>)> + Send + 'a> {
    let Some(marks) = program.marks() else {
        return Box::new(program.iter().map(|c| Some(Cow::Borrowed(c))).enumerate());
    };
    let mut filter = PartFilter::new(Arc::clone(marks), program.firmware());
    for &(part, from) in cancels {
        filter.cancel_from(part, from);
    }
    let commands = program.commands();
    Box::new((0..program.len()).map(move |i| (i, filter.decide(commands).and_then(Decision::line))))
}
