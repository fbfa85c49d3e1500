//! Lines as they go on the wire: `N<number> <command>*<checksum>`, written so that a byte
//! corrupted into `*` cannot leave a cut line that passes, and read back as the printer
//! reads them.

/// XOR of every byte, as Marlin checks it.
pub fn checksum(bytes: &[u8]) -> u8 {
    bytes.iter().fold(0, |acc, b| acc ^ b)
}

/// `N<number> <command>*<checksum>\n`.
pub fn frame(number: u64, command: &str) -> String {
    let body = format!("N{number} {command}");
    let cs = checksum(body.as_bytes());
    format!("{body}*{cs}\n")
}

/// Upper bound of `frame(number, command).len()` without building the line: `N`, the
/// number, a space, the command, `*`, a checksum of at most three digits and `\n`.
pub(super) fn wire_len_bound(number: u64, command: &str) -> usize {
    let digits = number.checked_ilog10().map_or(1, |d| d as usize + 1);
    1 + digits + 1 + command.len() + 1 + 3 + 1
}

/// A command as a printer reads it, whatever way it was written: one space between words,
/// numbers without trailing zeros after a decimal point (nor a bare point). Undoes what
/// [`uncuttable`] does to a line, so a record of what a printer ran compares with the file.
pub fn canonical(command: &str) -> String {
    command
        .split_whitespace()
        .map(|word| {
            let b = word.as_bytes();
            let numeric = b.len() > 1
                && b[0].is_ascii_alphabetic()
                && word[1..].contains('.')
                && word[1..]
                    .bytes()
                    .all(|c| c.is_ascii_digit() || c == b'.' || c == b'-');
            if numeric {
                word.trim_end_matches('0').trim_end_matches('.')
            } else {
                word
            }
        })
        .collect::<Vec<_>>()
        .join(" ")
}

/// Where a byte of `N<number> <command>` corrupted into `*` would leave a line that still
/// passes a checksum taken up to the first `*`: the XOR of what comes before equals the
/// number the firmware reads after it (`strtol`, 0 where no digit follows). Positions
/// before `from` are not looked at.
pub(super) fn cut_that_passes(body: &[u8], from: usize) -> Option<usize> {
    (from.max(1)..body.len()).find(|&i| {
        let prefix = checksum(&body[..i]) as u64;
        let digits: Vec<u8> = body[i + 1..]
            .iter()
            .copied()
            .take_while(u8::is_ascii_digit)
            .take(4)
            .collect();
        let read = std::str::from_utf8(&digits)
            .ok()
            .and_then(|d| d.parse::<u64>().ok())
            .unwrap_or(0);
        prefix == read
    })
}

/// Ultimaker2Marlin checks a line's checksum only up to its first `*`: a `.` corrupted into
/// `*` in `N472 G1 X0.03 Y0.05` runs `G1 X0.03 Y0` when the prefix's XOR happens to be 5,
/// which in G-code is far likelier than 1 in 128 (about one line in ten of a sliced file is
/// at risk). Such a line is written differently with the same meaning: trailing zeros on a
/// number (`Y0.050`, `F6000.0`) or an extra space before a word, which change the prefixes'
/// XORs and what the firmware would read after a cut; one or two such edits, the first
/// variant without a passing cut is taken. Cuts inside `N<number>` itself cannot be written
/// away, nor can a few lines in a thousand whose risky prefix no edit reaches; they are left.
pub(super) fn uncuttable(number: u64, command: String) -> String {
    let from = format!("N{number} ").len();
    let passes = |c: &str| cut_that_passes(format!("N{number} {c}").as_bytes(), from).is_some();
    if !passes(&command) {
        return command;
    }
    let words: Vec<&str> = command.split(' ').collect();
    // (word, zeros to append; 0 means an extra space before it)
    let mut edits = vec![(0, 0)];
    for (k, word) in words.iter().enumerate().skip(1) {
        let numeric = word.len() > 1
            && word.as_bytes()[0].is_ascii_alphabetic()
            && word[1..]
                .bytes()
                .all(|b| b.is_ascii_digit() || b == b'.' || b == b'-')
            && word[1..].bytes().any(|b| b.is_ascii_digit());
        if numeric {
            edits.extend([(k, 1), (k, 2), (k, 3)]);
        }
        edits.push((k, 0));
    }
    let apply = |words: &mut Vec<String>, (k, zeros): (usize, usize)| {
        let word = &mut words[k];
        if zeros == 0 {
            word.insert(0, ' ');
        } else {
            if !word.contains('.') {
                word.push('.');
            }
            word.push_str(&"0".repeat(zeros));
        }
    };
    let base: Vec<String> = words.iter().map(|w| w.to_string()).collect();
    for &edit in &edits {
        let mut w = base.clone();
        apply(&mut w, edit);
        let candidate = w.join(" ");
        if !passes(&candidate) {
            return candidate;
        }
    }
    for &a in &edits {
        for &b in edits.iter().filter(|b| b.0 > a.0) {
            let mut w = base.clone();
            apply(&mut w, a);
            apply(&mut w, b);
            let candidate = w.join(" ");
            if !passes(&candidate) {
                return candidate;
            }
        }
    }
    command
}

/// `N12 G1 X5*34` -> `G1 X5`; text without a number or checksum stays as it is.
pub(super) fn strip_framing(text: &str) -> &str {
    let mut s = text.trim();
    if let Some(rest) = s.strip_prefix('N') {
        if let Some((number, command)) = rest.split_once(' ') {
            if !number.is_empty() && number.bytes().all(|b| b.is_ascii_digit()) {
                s = command;
                if let Some((body, cs)) = s.rsplit_once('*') {
                    if cs.bytes().all(|b| b.is_ascii_digit()) {
                        s = body;
                    }
                }
            }
        }
    }
    s.trim()
}
