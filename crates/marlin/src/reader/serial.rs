//! What each firmware's serial input does with a line before its parser sees it: where the
//! line ends, which number it is taken for, what of it is stored. The host sends every job
//! line as `N<n> <line>*<checksum>\n`; [`check`] refuses a line for which the firmware would
//! do anything but take exactly that, as line n, and hand `<line>` to its parser. Each rule
//! is written from the firmware's source (Marlin 2.1.2.1's `GCodeQueue::get_serial_commands`
//! and `process_stream_char` in `Marlin/src/gcode/queue.cpp`, its emergency parser in
//! `Marlin/src/feature/e_parser.h`; Ultimaker2Marlin 8698fb6's `get_command` in
//! `Marlin/Marlin_main.cpp`), with its file and line in the reason, and listed in
//! docs/gcode-policy.md. The tests compare it with an independent transcription of both
//! queues (`transcribed::marlin2_queue`, `transcribed::ultimaker2_queue`).
//!
//! The host's load check cuts a line's comment (`;`) before anything reads it; a `;` that
//! reached [`check`] would be refused with what the firmware does with it.

use crate::firmware::Firmware;

/// Bytes the host adds around a command: `N<number> ` before and `*<checksum>` after.
/// Numbers up to 9 digits cover any job; the checksum is at most 3 digits.
pub(crate) const FRAMING_BYTES: usize = 1 + 9 + 1 + 1 + 3;

/// Codes a Marlin 2 built with EMERGENCY_PARSER acts on as soon as their bytes arrive
/// (`EmergencyParser::update`, e_parser.h): the command's first letters after `N<n> `, so
/// `M1080` is taken for `M108` too.
const EMERGENCY: [&str; 5] = ["M108", "M112", "M410", "M524", "M876"];

/// Refuses `code` (a line as the host sends it after `N<n> `: trimmed, its comment cut)
/// when the firmware's serial input would not take it whole, as one line with the host's
/// number, and hand it to the parser as written.
/// The reason says what the firmware would do instead, with its source line.
pub(crate) fn check(firmware: Firmware, code: &str) -> Result<(), String> {
    let marlin = firmware.is_marlin2();
    let max = firmware.max_line_bytes() - FRAMING_BYTES;
    if code.len() > max {
        return Err(format!(
            "is {} bytes long: with the host's line number and checksum it would not fit the \
             firmware's line buffer of {} bytes, which cuts it ({}), checksum and all; at \
             most {max} bytes",
            code.len(),
            firmware.max_line_bytes(),
            if marlin {
                "queue.cpp:372-374"
            } else {
                "Marlin_main.cpp:540"
            }
        ));
    }
    if let Some(c) = code.chars().find(|&c| c.is_ascii_control() && c != '\t') {
        return Err(control(marlin, c));
    }
    if code.contains('*') {
        return Err(if marlin {
            "holds `*`, where the host's checksum begins: Marlin 2 checks a line up to its \
             last `*` (queue.cpp:481-489) and its parser ends the command at the first \
             (parser.cpp:141-146), so it would run less than the file says, or refuse the \
             line again and again"
                .into()
        } else {
            "holds `*`, where the host's checksum begins: Ultimaker2Marlin checks a line \
             only up to its first `*` (Marlin_main.cpp:564-571), so it would refuse the line \
             again and again"
                .into()
        });
    }
    if code.contains(';') {
        // The host's load check cuts comments before anything reads a line; a caller that
        // did not is told what the firmware would do.
        return Err(if marlin {
            "holds `;`, where Marlin 2's serial input drops the rest of the line, the host's \
             checksum with it (queue.cpp:355-358), and would refuse the line again and again"
                .into()
        } else {
            "holds `;`, after which Ultimaker2Marlin keeps nothing, and drops the whole line \
             and the next one unanswered (Marlin_main.cpp:547, 641-642)"
                .into()
        });
    }
    if let Some(at) = code.find("M110") {
        return Err(m110(marlin, code, at));
    }
    if !marlin && code.contains(':') {
        return Err(
            "holds `:`, where Ultimaker2Marlin ends a line (Marlin_main.cpp:539): the text \
             after it would arrive as a line of its own and the rest fail its checksum"
                .into(),
        );
    }
    if marlin && code.contains('\\') {
        return Err(
            "holds `\\`, which Marlin 2's serial input drops, taking the character after it \
             as it is (queue.cpp:337-343): the line would no longer match its checksum and \
             be refused again and again"
                .into(),
        );
    }
    if marlin {
        if let Some(open) = code.find('(') {
            if !code[open..].contains(')') {
                return Err(
                    "holds `(` with no `)` after it: a Marlin 2 built with PAREN_COMMENTS \
                     (stock builds are not) drops the rest of the line from it, the host's \
                     checksum too (queue.cpp:330-334, 360-365), and would refuse the line \
                     again and again"
                        .into(),
                );
            }
        }
        // A longer code that begins with one (`M4100`, which a machine could allow) is
        // taken for it too.
        let word = code.split(' ').next().unwrap_or(code);
        if EMERGENCY.iter().any(|e| word.starts_with(e)) {
            return Err(emergency(word));
        }
    }
    Ok(())
}

/// The reason for a control character at a line's place on the wire.
fn control(marlin: bool, c: char) -> String {
    let name = match c {
        '\r' => "a carriage return (U+000D)".to_string(),
        '\n' => "a line feed (U+000A)".to_string(),
        '\u{8}' => "a backspace (U+0008)".to_string(),
        '\0' => "a NUL byte".to_string(),
        c => format!("the control character U+{:04X}", c as u32),
    };
    match (c, marlin) {
        ('\r' | '\n', true) => format!(
            "holds {name}, where Marlin 2 ends a line (`ISEOL`, queue.cpp:450): the text \
             after it would arrive as a line of its own, without number or checksum, which \
             Marlin runs unchecked (only a line that starts with `N` is checked, \
             queue.cpp:458-461), and the first part would fail its checksum"
        ),
        ('\r' | '\n', false) => format!(
            "holds {name}, where Ultimaker2Marlin ends a line (Marlin_main.cpp:537-538): the \
             text after it would arrive as a line of its own, without number or checksum, \
             which it runs unchecked (Marlin_main.cpp:594-604), and the first part would \
             fail its checksum"
        ),
        ('\u{8}', true) => format!(
            "holds {name}, with which Marlin 2's serial input erases the character before it \
             (queue.cpp:367-370): the printer would take another line than the file's, and \
             one whose `N` is erased runs unchecked"
        ),
        ('\0', _) => format!(
            "holds {name}, which ends the line for the firmware's string functions (`strchr`, \
             `strstr`): the checksum after it would never be seen"
        ),
        _ => format!(
            "holds {name}: it reaches the printer's parser and display as it is, and no \
             line of G-code needs one"
        ),
    }
}

/// The reason for `M110` at byte `at` of a line.
fn m110(marlin: bool, code: &str, at: usize) -> String {
    let shown = &code[at..(at + 4)];
    if !marlin {
        return format!(
            "holds `{shown}`: Ultimaker2Marlin skips the check of a line's number when \
             `M110` is anywhere in it (Marlin_main.cpp:554), so a line lost before it would \
             go unnoticed"
        );
    }
    // queue.cpp:466: the first `N` after the line's fifth byte, i.e. in the line's own text
    // (the host's `N<n> ` is at least three bytes and no job line starts with `N`).
    match code.find('N') {
        Some(n) => {
            let value = strtol(&code[n + 1..]);
            format!(
                "holds `{shown}`: Marlin 2's serial input takes any numbered line with \
                 `M110` in it for a new line count (queue.cpp:463-470), skips the check of \
                 its number and counts on from the number after its next `N` ({value}): it \
                 would refuse every later line the host sends (`Line Number is not Last \
                 Line Number+1, Last Line: {value}`)"
            )
        }
        None => format!(
            "holds `{shown}`: Marlin 2 skips the check of a line's number when `M110` is \
             anywhere in it (queue.cpp:463, 473), so a line lost before it would go \
             unnoticed"
        ),
    }
}

/// The reason for a line an emergency parser acts on as it arrives.
fn emergency(word: &str) -> String {
    let taken = EMERGENCY
        .iter()
        .find(|e| word.starts_with(**e))
        .copied()
        .unwrap_or("M108");
    let what = match taken {
        "M108" => "ends a heat wait or a wait for the user",
        "M112" => "halts the printer",
        "M410" => "stops every move at once",
        "M524" => "aborts an SD print",
        _ => "answers a host prompt",
    };
    format!(
        "is taken for `{taken}` by a Marlin 2 built with EMERGENCY_PARSER, which acts on it as \
         soon as its bytes arrive (feature/e_parser.h: it {what}), before the lines sent \
         ahead of it have run"
    )
}

/// C's `strtol(s, NULL, 10)` for a reason's number: leading white space, a sign, digits.
fn strtol(s: &str) -> i64 {
    let t = s.trim_start_matches([' ', '\t', '\n', '\x0b', '\x0c', '\r']);
    let (negative, t) = match t.as_bytes().first() {
        Some(b'-') => (true, &t[1..]),
        Some(b'+') => (false, &t[1..]),
        _ => (false, t),
    };
    let digits: String = t
        .chars()
        .take_while(char::is_ascii_digit)
        .take(18)
        .collect();
    let v: i64 = digits.parse().unwrap_or(0);
    if negative {
        -v
    } else {
        v
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn refused(fw: Firmware, code: &str) -> String {
        check(fw, code).unwrap_err()
    }

    #[test]
    fn a_message_with_m110_is_refused_naming_the_renumbering() {
        let why = refused(Firmware::Marlin2, "M117 M110 N999");
        assert!(
            why.contains("queue.cpp:463") && why.contains("999"),
            "{why}"
        );
        let why = refused(Firmware::Marlin2, "M117 renumber M110");
        assert!(why.contains("unnoticed"), "{why}");
        let why = refused(Firmware::Ultimaker2, "M117 M110 N999");
        assert!(why.contains("Marlin_main.cpp:554"), "{why}");
        // strstr is case-sensitive, and takes `M1100` for `M110` too.
        assert!(check(Firmware::Marlin2, "M117 m110 n999").is_ok());
        assert!(check(Firmware::Marlin2, "M1100").is_err());
    }

    #[test]
    fn line_ends_and_erasures_inside_a_line_are_refused() {
        for fw in Firmware::ALL {
            for code in [
                "M117 a\rM104 S300\rM117 b",
                "M117 a\nM104 S300",
                "M117 a\0b",
            ] {
                let why = refused(fw, code);
                assert!(
                    why.contains(".cpp") || why.contains("NUL"),
                    "{fw} {code:?}: {why}"
                );
            }
            assert!(check(fw, "M117 tab\tis fine").is_ok());
        }
        let why = refused(Firmware::Marlin2, "M117 \u{8}\u{8}\u{8}M104 S300");
        assert!(why.contains("queue.cpp:367"), "{why}");
    }

    #[test]
    fn stars_colons_backslashes_and_open_parentheses_where_the_firmware_reads_them() {
        for fw in Firmware::ALL {
            assert!(check(fw, "M117 a*b").is_err());
        }
        assert!(check(Firmware::Ultimaker2, "M117 ETA 01:23").is_err());
        assert!(check(Firmware::Marlin2, "M117 ETA 01:23").is_ok());
        assert!(check(Firmware::Marlin2, "M118 \"a\\\"b\"").is_err());
        assert!(check(Firmware::Ultimaker2, "M117 a\\b").is_ok());
        assert!(check(Firmware::Marlin2, "M117 (unclosed").is_err());
        assert!(check(Firmware::Marlin2, "M117 (closed) fine").is_ok());
    }

    #[test]
    fn what_an_emergency_parser_takes_on_arrival_is_refused_on_marlin() {
        for code in ["M108", "M112", "M1080", "M4101 S1", "M8765"] {
            let why = refused(Firmware::Marlin2, code);
            assert!(why.contains("e_parser.h"), "{code}: {why}");
        }
        assert!(check(Firmware::Marlin2, "M117 M108").is_ok());
        assert!(check(Firmware::Marlin2, "M1 M108").is_ok());
        assert!(check(Firmware::Ultimaker2, "M1080").is_ok());
    }
}
