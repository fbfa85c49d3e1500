//! A second, independent reading of a line for the tests and the fuzz target: each
//! firmware's serial input and parser walked the way its C source walks them, over the
//! bytes the host actually sends (`N<n> ` before the line, `*<checksum>` and a line end
//! after it), byte by byte and pointer by pointer, with the C library's number readers.
//! The readers of [`super::marlin2`], [`super::ultimaker2`] and [`super::serial`] are
//! compared with this on random lines: a disagreement is a bug in one of them.

use super::view::View;

/// A line as the host frames it: `N<n> <text>*<checksum>\n`, the checksum the XOR of every
/// byte before the `*`.
fn frame(n: u64, text: &str) -> String {
    let body = format!("N{n} {text}");
    let sum = body.bytes().fold(0u8, |a, b| a ^ b);
    format!("{body}*{sum}\n")
}

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

/// What a firmware's serial input made of the bytes it read: the lines it put in its
/// command queue (as stored: number and checksum still in them), the errors it answered, the
/// line number it counts from afterwards, and what it acted on while reading.
#[derive(Debug, Default, Clone, PartialEq)]
pub struct Queue {
    pub queued: Vec<Vec<u8>>,
    pub errors: Vec<&'static str>,
    pub last_n: i64,
    /// Marlin 2 without EMERGENCY_PARSER acts on an unnumbered `M108`, `M112` or `M410`
    /// when it reads it (queue.cpp:524-531); with it, on those codes as their bytes arrive
    /// (e_parser.h), numbered or not.
    pub early: Vec<&'static str>,
}

/// C's `strtol(s, NULL, 10)` on a NUL-terminated buffer (a 64-bit `long`, as on the Linux
/// build; saturating).
fn strtol(b: &[u8]) -> i64 {
    let mut i = 0;
    while matches!(b[i], b' ' | b'\t' | b'\n' | 0x0b | 0x0c | b'\r') {
        i += 1;
    }
    let negative = b[i] == b'-';
    if matches!(b[i], b'+' | b'-') {
        i += 1;
    }
    let mut v: i64 = 0;
    while b[i].is_ascii_digit() {
        v = v.saturating_mul(10).saturating_add(i64::from(b[i] - b'0'));
        i += 1;
    }
    if negative {
        -v
    } else {
        v
    }
}

/// C's `strchr` / `strstr` from `at` on a NUL-terminated buffer.
fn strchr(b: &[u8], at: usize, c: u8) -> Option<usize> {
    (at..b.len())
        .take_while(|&i| b[i] != 0)
        .find(|&i| b[i] == c)
}
fn strstr(b: &[u8], at: usize, needle: &[u8]) -> bool {
    let end = (at..b.len()).find(|&i| b[i] == 0).unwrap_or(b.len());
    b[at..end].windows(needle.len()).any(|w| w == needle)
}

/// Marlin 2.1.2.1's `GCodeQueue::get_serial_commands` and `process_stream_char`
/// (queue.cpp:326-545) as the stock build has them (no PAREN_COMMENTS, no
/// GCODE_QUOTED_STRINGS, no SDSUPPORT), with a free command slot for every line, over
/// `bytes` arriving at once while the firmware's count stands at `last_n`; and, when
/// `emergency_parser`, `EmergencyParser::update` (e_parser.h) over the same bytes.
pub fn marlin2_queue(bytes: &[u8], last_n: i64, emergency_parser: bool) -> Queue {
    const PS_NORMAL: u8 = 0;
    const PS_EOL: u8 = 1;
    const PS_ESC: u8 = 4;
    const MAX_CMD_SIZE: usize = 96;
    let mut q = Queue {
        last_n,
        ..Queue::default()
    };
    if emergency_parser {
        q.early = emergency_parser_walk(bytes);
    }
    let mut buff = [0u8; MAX_CMD_SIZE + 1];
    let mut ind = 0usize;
    let mut sis = PS_NORMAL;
    for &c in bytes {
        if c == b'\n' || c == b'\r' {
            // process_line_done
            sis = PS_NORMAL;
            buff[ind] = 0;
            if ind == 0 {
                continue;
            }
            ind = 0;
            let mut command = 0;
            while buff[command] == b' ' {
                command += 1;
            }
            if buff[command] == b'N' {
                let m110 = strstr(&buff, command, b"M110");
                let mut npos = command;
                if m110 {
                    if let Some(n2) = strchr(&buff, command + 4, b'N') {
                        npos = n2;
                    }
                }
                let gcode_n = strtol(&buff[npos + 1..]);
                if gcode_n != q.last_n + 1 && !m110 {
                    if (q.last_n - 1..=q.last_n).contains(&gcode_n) {
                        continue;
                    }
                    // gcode_line_error reads the receive buffer empty: the rest is gone.
                    q.errors.push("Line Number is not Last Line Number+1");
                    return q;
                }
                let end = (command..buff.len()).find(|&i| buff[i] == 0).unwrap();
                match (command..end).rev().find(|&i| buff[i] == b'*') {
                    Some(apos) => {
                        let checksum = buff[command..apos].iter().fold(0u8, |a, b| a ^ b);
                        if strtol(&buff[apos + 1..]) != i64::from(checksum) {
                            q.errors.push("checksum mismatch");
                            return q;
                        }
                    }
                    None => {
                        q.errors.push("No Checksum with line number");
                        return q;
                    }
                }
                q.last_n = gcode_n;
            } else if !emergency_parser && buff[command] == b'M' {
                match (buff[command + 1], buff[command + 2], buff[command + 3]) {
                    (b'1', b'0', b'8') => q.early.push("M108"),
                    (b'1', b'1', b'2') => q.early.push("M112"),
                    (b'4', b'1', b'0') => q.early.push("M410"),
                    _ => {}
                }
            }
            let len = buff.iter().position(|&b| b == 0).unwrap();
            q.queued.push(buff[..len].to_vec());
        } else {
            // process_stream_char
            if sis == PS_EOL {
                continue;
            } else if sis >= PS_ESC {
                sis -= PS_ESC;
            } else if c == b'\\' {
                sis += PS_ESC;
                if sis == PS_ESC {
                    continue;
                }
            } else if c == b';' {
                sis = PS_EOL;
                continue;
            }
            if c == 0x08 {
                if ind > 0 {
                    ind -= 1;
                    buff[ind] = 0;
                }
            } else {
                buff[ind] = c;
                ind += 1;
                if ind >= MAX_CMD_SIZE - 1 {
                    sis = PS_EOL;
                }
            }
        }
    }
    q
}

/// `EmergencyParser::update` (e_parser.h) as a stock-plus-EMERGENCY_PARSER build has it
/// (no SD card, no host prompts): the codes it acts on in `bytes`.
fn emergency_parser_walk(bytes: &[u8]) -> Vec<&'static str> {
    #[derive(Clone, Copy, PartialEq)]
    enum S {
        Reset,
        N,
        M,
        M1,
        M10,
        M108,
        M11,
        M112,
        M4,
        M41,
        M410,
        Ignore,
    }
    let mut acted = Vec::new();
    let mut state = S::Reset;
    for &c in bytes {
        let eol = c == b'\n' || c == b'\r';
        state = match state {
            S::Reset => match c {
                b' ' | b'\n' | b'\r' => S::Reset,
                b'N' => S::N,
                b'M' => S::M,
                _ => S::Ignore,
            },
            S::N => match c {
                b'0'..=b'9' | b'-' | b' ' => S::N,
                b'M' => S::M,
                _ => S::Ignore,
            },
            S::M => match c {
                b' ' => S::M,
                b'1' => S::M1,
                b'4' => S::M4,
                _ => S::Ignore,
            },
            S::M1 => match c {
                b'0' => S::M10,
                b'1' => S::M11,
                _ => S::Ignore,
            },
            S::M10 if c == b'8' => S::M108,
            S::M11 if c == b'2' => S::M112,
            S::M4 if c == b'1' => S::M41,
            S::M41 if c == b'0' => S::M410,
            S::M10 | S::M11 | S::M4 | S::M41 => S::Ignore,
            S::Ignore if eol => S::Reset,
            S::Ignore => S::Ignore,
            done @ (S::M108 | S::M112 | S::M410) => {
                if eol {
                    acted.push(match done {
                        S::M108 => "M108",
                        S::M112 => "M112",
                        _ => "M410",
                    });
                    S::Reset
                } else {
                    done
                }
            }
        };
    }
    acted
}

/// Ultimaker2Marlin 8698fb6's `get_command` (Marlin_main.cpp:533-644) with room in its
/// queue for every line, over `bytes` arriving at once while its count stands at
/// `last_n`.
pub fn ultimaker2_queue(bytes: &[u8], last_n: i64) -> Queue {
    const MAX_CMD_SIZE: usize = 96;
    let mut q = Queue {
        last_n,
        ..Queue::default()
    };
    let mut cmdbuffer = [0u8; MAX_CMD_SIZE + 1];
    let mut serial_count = 0usize;
    let mut comment_mode = false;
    for &serial_char in bytes {
        if serial_char == b'\n'
            || serial_char == b'\r'
            || (serial_char == b':' && !comment_mode)
            || serial_count >= MAX_CMD_SIZE - 1
        {
            if serial_count == 0 {
                comment_mode = false;
                continue; // `return`: the next call reads on
            }
            cmdbuffer[serial_count] = 0;
            if !comment_mode {
                if let Some(npos) = strchr(&cmdbuffer, 0, b'N') {
                    let gcode_n = strtol(&cmdbuffer[npos + 1..]);
                    if gcode_n != q.last_n + 1 && !strstr(&cmdbuffer, 0, b"M110") {
                        // FlushSerialRequestResend empties the receive buffer.
                        q.errors.push("Line Number is not Last Line Number+1");
                        return q;
                    }
                    match strchr(&cmdbuffer, 0, b'*') {
                        Some(star) => {
                            let checksum = cmdbuffer[..star].iter().fold(0u8, |a, b| a ^ b);
                            let end = (star..cmdbuffer.len())
                                .find(|&i| cmdbuffer[i] == 0)
                                .unwrap();
                            let (v, _) = super::ultimaker2::strtod(&cmdbuffer[star + 1..end]);
                            let read = if v.is_finite() { v as i64 } else { -1 };
                            if read != i64::from(checksum) {
                                q.errors.push("checksum mismatch");
                                return q;
                            }
                        }
                        None => {
                            q.errors.push("No Checksum with line number");
                            return q;
                        }
                    }
                    q.last_n = gcode_n;
                } else if strchr(&cmdbuffer, 0, b'*').is_some() {
                    // No flush: the rest stays in the receive buffer.
                    q.errors.push("No Line Number with checksum");
                    serial_count = 0;
                    continue;
                }
                q.queued.push(cmdbuffer[..serial_count].to_vec());
            }
            serial_count = 0;
        } else {
            if serial_char == b';' {
                comment_mode = true;
            }
            if !comment_mode {
                cmdbuffer[serial_count] = serial_char;
                serial_count += 1;
            }
        }
    }
    q
}

/// Where the firmware's serial input would not take `line`, framed as the host sends it as
/// line `n` while the firmware expects it, whole as that one line.
fn queue_disagreement(fw: crate::firmware::Firmware, line: &str) -> Option<String> {
    for n in [7u64, 1234] {
        let framed = frame(n, line);
        let q = if fw.is_marlin2() {
            marlin2_queue(framed.as_bytes(), n as i64 - 1, true)
        } else {
            ultimaker2_queue(framed.as_bytes(), n as i64 - 1)
        };
        let whole = framed.trim_end_matches('\n').as_bytes();
        let taken = q.errors.is_empty()
            && q.early.is_empty()
            && q.last_n == n as i64
            && q.queued.len() == 1
            && q.queued[0] == whole;
        if !taken {
            return Some(format!(
                "{fw} {line:?} as line {n}: accepted, but queued as {q:?}"
            ));
        }
    }
    None
}

/// Where crispen's readers and the transcriptions disagree on `line`, if they do: each
/// firmware reader against its transcription on every line that reaches a parser whole,
/// and on every line [`super::read_for`] accepts, its command and values against the
/// transcribed parser and the whole line against the transcribed serial input.
pub fn disagreement(line: &str) -> Option<String> {
    use super::{read_for, STRING_COMMANDS};
    use crate::firmware::Firmware;
    // What a parser never sees whole: its serial input splits or cuts it first.
    let whole = !line.contains(['*', '\0', '\r', '\n']);
    let pairs = [
        (Firmware::Marlin2, super::marlin2::read(line), marlin2(line)),
        (
            Firmware::Ultimaker2,
            super::ultimaker2::read(line),
            ultimaker2(line),
        ),
    ];
    for (fw, ours, theirs) in pairs {
        if let Ok(Some(_)) = read_for(fw, line) {
            if let Some(d) = queue_disagreement(fw, line) {
                return Some(d);
            }
        }
        if !whole {
            continue;
        }
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
