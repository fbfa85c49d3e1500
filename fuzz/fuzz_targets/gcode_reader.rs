//! Any text as one line of G-code: crispen's reading of it for each firmware (the one the
//! G-code policy decides on) must equal an independent transcription of that firmware's
//! C parser, and a line it accepts must be taken whole, as the host's numbered line, by a
//! transcription of that firmware's serial input (`marlin::reader::transcribed`); any
//! disagreement is a failure.
#![no_main]

use crispen::marlin::reader::transcribed::disagreement;
use libfuzzer_sys::fuzz_target;

fuzz_target!(|data: &[u8]| {
    let text = String::from_utf8_lossy(data);
    // One line as the host's load check reads a file: up to its newline, the comment cut.
    // Carriage returns, `*`, NUL and the rest stay: the reader must refuse what the
    // firmware's serial input would not take whole.
    let line = text.split(['\n', ';']).next().unwrap_or("");
    if let Some(d) = disagreement(line.trim()) {
        panic!("{d}");
    }
});
