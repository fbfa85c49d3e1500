//! A second, independent reading of a line for the tests and the fuzz target: each
//! firmware's parser walked the way its C source walks it, over the bytes the host actually
//! sends (`N<n> ` before the line, `*<checksum>` after it, a NUL at the end), pointer by
//! pointer, with the C library's number readers. The readers of [`super::marlin2`] and
//! [`super::ultimaker2`] are compared with this on random lines: a disagreement is a bug in
//! one of them.

use super::view::View;
use crate::marlin::protocol::frame;

/// The bytes on the wire for line number 7 of `text`, NUL-terminated, without the newline.
fn wire(text: &str) -> Vec<u8> {
    let mut b = frame(7, text).trim_end_matches('\n').as_bytes().to_vec();
    b.push(0);
    b
}

fn numeric_signed(c: u8) -> bool {
    c.is_ascii_digit() || c == b'-'
}

/// glibc's `strtof` for the texts Marlin hands it (they start `[+-]?.?[0-9]`).
fn strtof(b: &[u8]) -> f64 {
    let mut end = 0;
    if matches!(b[end], b'+' | b'-') {
        end += 1;
    }
    while b[end].is_ascii_digit() {
        end += 1;
    }
    if b[end] == b'.' {
        end += 1;
        while b[end].is_ascii_digit() {
            end += 1;
        }
    }
    std::str::from_utf8(&b[..end])
        .ok()
        .and_then(|t| t.parse::<f32>().ok())
        .map_or(0.0, f64::from)
}

/// Marlin 2.1.2.1's `GCodeParser::parse` and `value_float` on the wire bytes.
pub(crate) fn marlin2(text: &str) -> View {
    let mut buf = wire(text);
    let mut view = View::new();
    // queue.cpp hands the parser the line with the checksum; the parser cuts at the first
    // `*` and the spaces before it.
    if let Some(star) = buf.iter().position(|&c| c == b'*') {
        let mut s = star;
        while s > 0 && buf[s - 1] == b' ' {
            s -= 1;
        }
        buf[s] = 0;
    }
    let mut p = 0usize;
    while buf[p] == b' ' {
        p += 1;
    }
    if buf[p] == b'N' && numeric_signed(buf[p + 1]) {
        while buf[p] != 0 && buf[p] != b' ' {
            p += 1;
        }
        while buf[p] == b' ' {
            p += 1;
        }
    }
    let letter = buf[p];
    match letter {
        b'G' | b'M' | b'T' => {
            p += 1;
            while buf[p] == b' ' {
                p += 1;
            }
            if !buf[p].is_ascii_digit() {
                return view;
            }
            let mut codenum: u16 = 0;
            loop {
                codenum = codenum
                    .wrapping_mul(10)
                    .wrapping_add(u16::from(buf[p] - b'0'));
                p += 1;
                if !buf[p].is_ascii_digit() {
                    break;
                }
            }
            while buf[p] == b' ' {
                p += 1;
            }
            view.command = Some((letter as char, u32::from(codenum)));
            if letter == b'M' && matches!(codenum, 23 | 28 | 30 | 117 | 118 | 928) {
                view.string = true;
                return view;
            }
        }
        _ => return view,
    }
    loop {
        let param = buf[p];
        p += 1;
        if param == 0 {
            break;
        }
        if param == b'!' && view.command == Some(('M', 32)) {
            view.string = true;
            return view;
        }
        if param.is_ascii_uppercase() {
            while buf[p] == b' ' {
                p += 1;
            }
            let signless = |q: usize| {
                buf[q].is_ascii_digit() || (buf[q] == b'.' && buf[q + 1].is_ascii_digit())
            };
            let has_val = signless(p) || (matches!(buf[p], b'-' | b'+') && signless(p + 1));
            let value = has_val.then(|| {
                // value_float: cut at the first E/e/X/x before a space or the end.
                let mut e = p;
                while buf[e] != 0 && buf[e] != b' ' {
                    if matches!(buf[e], b'E' | b'e' | b'X' | b'x') {
                        break;
                    }
                    e += 1;
                }
                let mut cut = buf[p..=e].to_vec();
                *cut.last_mut().expect("one byte at least") = 0;
                strtof(&cut)
            });
            view.params[usize::from(param - b'A')] = Some(value);
        }
        if !buf[p].is_ascii_uppercase() {
            while buf[p].is_ascii_digit() || matches!(buf[p], b'.' | b'+' | b'-') {
                p += 1;
            }
            while buf[p] == b' ' {
                p += 1;
            }
        }
    }
    view
}

/// Ultimaker2Marlin's `process_command` with `code_seen` (`strchr` over the whole command
/// buffer, the host's line number and checksum included: get_command keeps them) and
/// `code_value` (`strtod`).
pub(crate) fn ultimaker2(text: &str) -> View {
    let buf = wire(text);
    let strchr = |c: u8| buf.iter().take_while(|&&b| b != 0).position(|&b| b == c);
    let mut view = View::new();
    for letter in [b'G', b'M', b'T'] {
        if let Some(i) = strchr(letter) {
            let (v, _) = super::ultimaker2::strtod(&buf[i + 1..buf.len() - 1]);
            if v.is_finite() && (0.0..32768.0).contains(&v) {
                view.command = Some((letter as char, v as u32));
            }
            break;
        }
    }
    for letter in b'A'..=b'Z' {
        if let Some(i) = strchr(letter) {
            let (v, _) = super::ultimaker2::strtod(&buf[i + 1..buf.len() - 1]);
            view.params[usize::from(letter - b'A')] = Some(Some(v));
        }
    }
    view
}

/// Where crispen's readers and the transcriptions disagree on `line`, if they do: each
/// firmware reader against its transcription on every line, and [`super::read_for`]'s
/// command and values against the transcription on every line it accepts.
pub fn disagreement(line: &str) -> Option<String> {
    use super::{read_for, STRING_COMMANDS};
    use crate::marlin::firmware::Firmware;
    let pairs = [
        (Firmware::Marlin2, super::marlin2::read(line), marlin2(line)),
        (
            Firmware::Ultimaker2,
            super::ultimaker2::read(line),
            ultimaker2(line),
        ),
    ];
    for (fw, ours, theirs) in pairs {
        if ours.command != theirs.command {
            return Some(format!(
                "{fw} {line:?}: command {:?} against {:?}",
                ours.command, theirs.command
            ));
        }
        for i in 0..26 {
            if i == usize::from(b'N' - b'A') {
                continue; // the host's line number
            }
            let same = match (ours.params[i], theirs.params[i]) {
                (Some(Some(a)), Some(Some(b))) => a == b || (a.is_nan() && b.is_nan()),
                (a, b) => a == b,
            };
            if !same {
                return Some(format!(
                    "{fw} {line:?}: {} is {:?} against {:?}",
                    (b'A' + i as u8) as char,
                    ours.params[i],
                    theirs.params[i]
                ));
            }
        }
        let Ok(Some(c)) = read_for(fw, line) else {
            continue;
        };
        if theirs.command != Some((c.letter(), c.number())) {
            return Some(format!(
                "{fw} {line:?}: accepted as {}, runs {:?}",
                c.code, theirs.command
            ));
        }
        if theirs.string || STRING_COMMANDS.contains(&c.code.as_str()) {
            continue;
        }
        for w in &c.words {
            let read = theirs.param(w.letter).flatten().map(|v| v as f32);
            let written = w.text.map(|t| super::firmware_float(fw, t));
            if read != written || theirs.param(w.letter).is_none() {
                return Some(format!(
                    "{fw} {line:?}: {} accepted as {:?}, read as {:?}",
                    w.letter,
                    w.value,
                    theirs.param(w.letter)
                ));
            }
        }
    }
    None
}
