//! Any text as one line of G-code: crispen's reading of it for each firmware (the one the
//! G-code policy decides on) must equal an independent transcription of that firmware's
//! C parser (`marlin::reader::transcribed`); any disagreement is a failure.
#![no_main]

use crispen::marlin::reader::transcribed::disagreement;
use libfuzzer_sys::fuzz_target;

fuzz_target!(|data: &[u8]| {
    let text = String::from_utf8_lossy(data);
    // One line as the host sends it: no newline, the comment cut, no `*` (the host's load
    // check refuses it), at most a firmware's line length.
    let line = text.split(['\n', '\r', ';']).next().unwrap_or("");
    if line.contains('*') || line.contains('\0') || line.len() > 96 {
        return;
    }
    if let Some(d) = disagreement(line.trim()) {
        panic!("{d}");
    }
});
