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
pub fn read(text: &str) -> View {
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

/// avr-libc's `strtod` (avr-libc 2.0 and 2.1, `libc/stdlib/strtod.c`, which Debian's and
/// Arduino's AVR toolchains ship; `double` is 32-bit there): the value and how many bytes
/// it took (0 and 0 when no number starts the text). It is not rounded as a decimal is
/// rounded to the nearest float: the digits are gathered into a 32-bit integer (lines
/// 137-163: past 429496728 further digits only count in the exponent), converted to a
/// float (line 197, `__floatunsisf`, to nearest), then multiplied by float powers of ten
/// from the largest (`1e32f`, `1e16f`, ... `1e1f`, or their inverses; lines 201-219), each
/// product rounded to nearest. `150.3` is the nearest float to 150.3 that way, but a value
/// with more digits can land one float away from glibc's `strtof`.
pub fn strtod(b: &[u8]) -> (f64, usize) {
    const P10: [f32; 6] = [1e1, 1e2, 1e4, 1e8, 1e16, 1e32];
    const M10: [f32; 6] = [1e-1, 1e-2, 1e-4, 1e-8, 1e-16, 1e-32];
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
    let (mut mantissa, mut exp, mut any, mut dot, mut full) = (0u32, 0i32, false, false, false);
    while let Some(&c) = b.get(i) {
        if c.is_ascii_digit() {
            any = true;
            if full {
                exp += i32::from(!dot);
            } else {
                exp -= i32::from(dot);
                mantissa = mantissa.wrapping_mul(10).wrapping_add(u32::from(c - b'0'));
                full = mantissa >= (u32::MAX - 9) / 10;
            }
        } else if c == b'.' && !dot {
            dot = true;
        } else {
            break;
        }
        i += 1;
    }
    if !any {
        return (0.0, 0);
    }
    if matches!(b.get(i), Some(b'e' | b'E')) {
        let mut j = i + 1;
        let minus = b.get(j) == Some(&b'-');
        if matches!(b.get(j), Some(b'+' | b'-')) {
            j += 1;
        }
        if b.get(j).is_some_and(u8::is_ascii_digit) {
            let mut e = 0i32;
            while let Some(d) = b.get(j).filter(|d| d.is_ascii_digit()) {
                if e < 3200 {
                    e = e * 10 + i32::from(d - b'0');
                }
                j += 1;
            }
            exp += if minus { -e } else { e };
            i = j;
        }
    }
    let mut x = mantissa as f32;
    if x != 0.0 {
        let (powers, mut left) = if exp < 0 { (M10, -exp) } else { (P10, exp) };
        for k in (0..6).rev() {
            while left >= 1 << k {
                x *= powers[k];
                left -= 1 << k;
            }
        }
    }
    (sign * f64::from(x), i)
}
