//! Marlin 2's reading of a line (`GCodeParser::parse` in `src/gcode/parser.cpp`, and
//! `parser.h`'s value readers), as the stock 2.1.2.1 configuration builds it:
//! `FASTER_GCODE_PARSER` on, `GCODE_CASE_INSENSITIVE`, `GCODE_QUOTED_STRINGS`,
//! `PAREN_COMMENTS`, `GCODE_MOTION_MODES` and sub-codes off. Checked against the real
//! firmware by `tests/firmware.rs`.
//!
//! What the parser does, step by step:
//! - spaces are skipped; the command letter must be `G`, `M` or `T` (upper case), then
//!   optional spaces and the digits of its number (a 16-bit integer);
//! - `M23`, `M28`, `M30`, `M117`, `M118`, `M928` take the rest of the line as a string;
//! - otherwise each character in turn is a parameter's letter if it is `A`-`Z`, and is
//!   skipped otherwise; after a letter, spaces are skipped and a value is there if the
//!   text starts `[+-]?.?[0-9]`. If the next character is no letter, the characters
//!   `0-9 . + -` and then spaces are skipped. So junk before a letter hides nothing: in
//!   `M104 @S400` the `@` is skipped and `S400` read;
//! - a letter given twice keeps its last position (`M104 S100 S400` is 400);
//! - a value is read with `strtof` up to the first `E` or `X` (either case), so there are
//!   no exponents and no hexadecimal: `S1.5E2` is 1.5 (and `E2` another parameter).

use super::view::View;

/// What Marlin 2 finds in `text` (a line's code, as the host sends it after its `N<n> `).
pub fn read(text: &str) -> View {
    let b = text.as_bytes();
    let at = |i: usize| b.get(i).copied().unwrap_or(0);
    let mut view = View::new();
    let mut p = 0;
    while at(p) == b' ' {
        p += 1;
    }
    let letter = at(p);
    if !matches!(letter, b'G' | b'M' | b'T') {
        return view;
    }
    p += 1;
    while at(p) == b' ' {
        p += 1;
    }
    if !at(p).is_ascii_digit() {
        return view;
    }
    let mut number: u16 = 0;
    while at(p).is_ascii_digit() {
        number = number
            .wrapping_mul(10)
            .wrapping_add(u16::from(at(p) - b'0'));
        p += 1;
    }
    view.command = Some((letter as char, u32::from(number)));
    while at(p) == b' ' {
        p += 1;
    }
    if letter == b'M' && matches!(number, 23 | 28 | 30 | 117 | 118 | 928) {
        view.string = true;
        return view;
    }
    loop {
        let param = at(p);
        if param == 0 {
            break;
        }
        p += 1;
        if param == b'!' && letter == b'M' && number == 32 {
            // M32's file name runs to the end.
            view.string = true;
            return view;
        }
        if param.is_ascii_uppercase() {
            while at(p) == b' ' {
                p += 1;
            }
            let value = valid_float(&b[p.min(b.len())..]).then(|| value_float(&b[p..]));
            view.params[(param - b'A') as usize] = Some(value);
        }
        if !at(p).is_ascii_uppercase() {
            while matches!(at(p), b'0'..=b'9' | b'.' | b'+' | b'-') {
                p += 1;
            }
            while at(p) == b' ' {
                p += 1;
            }
        }
    }
    view
}

/// `[+-]?.?[0-9]`: the parser's test for a value.
fn valid_float(b: &[u8]) -> bool {
    let signless = |s: &[u8]| {
        s.first().is_some_and(u8::is_ascii_digit)
            || (s.first() == Some(&b'.') && s.get(1).is_some_and(u8::is_ascii_digit))
    };
    signless(b) || (matches!(b.first(), Some(b'+' | b'-')) && signless(&b[1..]))
}

/// `value_float()`: `strtof` over the text up to the first `E`, `e`, `X` or `x` (before a
/// space or the end). What `strtof` takes of a text starting `[+-]?.?[0-9]`, with no
/// exponent left, is a sign, digits and one point.
pub(super) fn value_float(b: &[u8]) -> f64 {
    let end = b
        .iter()
        .position(|&c| c == b' ' || matches!(c, b'E' | b'e' | b'X' | b'x'))
        .unwrap_or(b.len());
    let b = &b[..end];
    let mut i = usize::from(matches!(b.first(), Some(b'+' | b'-')));
    while b.get(i).is_some_and(u8::is_ascii_digit) {
        i += 1;
    }
    if b.get(i) == Some(&b'.') {
        i += 1;
        while b.get(i).is_some_and(u8::is_ascii_digit) {
            i += 1;
        }
    }
    let text = std::str::from_utf8(&b[..i]).unwrap_or("0");
    // "+.5", "-5.": Rust's parser takes these as strtof does.
    f64::from(text.parse::<f32>().unwrap_or(0.0))
}
