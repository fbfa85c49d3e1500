//! Ultimaker2Marlin's reading of a line (`process_command`, `code_seen` and `code_value`
//! in `Marlin/Marlin_main.cpp`, commit 8698fb6), which has no parser of its own:
//!
//! - the command is a `G` found anywhere in the line (`strchr`), else an `M`, else a `T`,
//!   and its number is `(int)strtod(...)` of the text after that letter. So `M400 G92 Z50`
//!   runs `G92 Z50`, and `M117 Going` runs `G0`;
//! - a parameter is the first occurrence of its (upper-case) letter anywhere in the line,
//!   the command's text included, and its value is `strtod` of what follows: leading white
//!   space skipped, exponents taken (`S2.7E2` is 270), `inf` and `nan` too; no number at all
//!   reads as 0, which the command handlers use as given (`G1 Z` moves Z to 0);
//! - lower-case letters are never found.
//!
//! The host's `N<n> ` before the line and `*<checksum>` after it add no letter but `N`.

use super::view::View;

/// What Ultimaker2Marlin finds in `text`.
pub(crate) fn read(text: &str) -> View {
    let b = text.as_bytes();
    let mut view = View::new();
    // Where each upper-case letter first occurs (what `strchr` finds), in one pass.
    let mut first: [Option<usize>; 26] = [None; 26];
    for (i, &c) in b.iter().enumerate() {
        if c.is_ascii_uppercase() {
            first[usize::from(c - b'A')].get_or_insert(i);
        }
    }
    // `code_seen('G')`, else `M`, else `T`: the first letter found is the command,
    // whatever number follows it.
    if let Some((letter, i)) = [b'G', b'M', b'T']
        .into_iter()
        .find_map(|letter| Some((letter, first[usize::from(letter - b'A')]?)))
    {
        let (v, _) = strtod(&b[i + 1..]);
        // `(int)` of an AVR float: out of range (or nan) is undefined; no such command.
        if v.is_finite() && (0.0..32768.0).contains(&v) {
            view.command = Some((letter as char, v.trunc() as u32));
        }
    }
    for (param, at) in view.params.iter_mut().zip(first) {
        if let Some(i) = at {
            *param = Some(Some(strtod(&b[i + 1..]).0));
        }
    }
    view
}

/// avr-libc's `strtod` (on a 32-bit `double`): the value and how many bytes it took (0 and
/// 0 when no number starts the text).
pub(crate) fn strtod(b: &[u8]) -> (f64, usize) {
    let mut i = 0;
    while b
        .get(i)
        .is_some_and(|c| matches!(c, b' ' | b'\t' | b'\n' | b'\x0b' | b'\x0c' | b'\r'))
    {
        i += 1;
    }
    let negative = b.get(i) == Some(&b'-');
    if matches!(b.get(i), Some(b'+' | b'-')) {
        i += 1;
    }
    let sign = if negative { -1.0 } else { 1.0 };
    let word = |w: &[u8], at: usize| {
        b.len() >= at + w.len() && b[at..at + w.len()].eq_ignore_ascii_case(w)
    };
    if word(b"infinity", i) {
        return (sign * f64::INFINITY, i + 8);
    }
    if word(b"inf", i) {
        return (sign * f64::INFINITY, i + 3);
    }
    if word(b"nan", i) {
        return (f64::NAN, i + 3);
    }
    let start = i;
    let int = b[i..].iter().take_while(|c| c.is_ascii_digit()).count();
    i += int;
    let mut frac = 0;
    if b.get(i) == Some(&b'.') {
        frac = b[i + 1..].iter().take_while(|c| c.is_ascii_digit()).count();
        i += 1 + frac;
    }
    if int + frac == 0 {
        return (0.0, 0);
    }
    let mantissa_end = i;
    if matches!(b.get(i), Some(b'e' | b'E')) {
        let mut j = i + 1;
        if matches!(b.get(j), Some(b'+' | b'-')) {
            j += 1;
        }
        let digits = b[j..].iter().take_while(|c| c.is_ascii_digit()).count();
        if digits > 0 {
            i = j + digits;
        }
    }
    let text = std::str::from_utf8(&b[start..i]).unwrap_or("0");
    let mut v: f64 = text.parse().unwrap_or_else(|_| {
        std::str::from_utf8(&b[start..mantissa_end])
            .ok()
            .and_then(|t| t.parse().ok())
            .unwrap_or(0.0)
    });
    // A 32-bit double: overflow is infinity.
    v = f64::from(v as f32);
    (sign * v, i)
}
