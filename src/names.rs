//! What an operator names (a file, a material, a colour, a brand, a spool, a hot folder, a
//! printer a sidecar asks for) may hold, and how a name is shown. A name goes to
//! terminals (`crispen status`, `crispen spools`), the log (one line per event), the
//! dashboard and notifications, so a control character (an ESC sequence, a line break)
//! or a bidi control (U+202E shows `gcode.exe` as `exe.edocg`) would let it drive a
//! terminal, forge a log line or show as another name. [`problem`] is the one check,
//! wherever a name comes in (config, sidecars, the API and the command line, Spoolman's
//! answers, hot folders and uploads); [`printable`] and [`escaped`] show any text safely
//! (what was stored before the check, a name quoted in an error); [`number`] shows a
//! number an operator gave. A leaf module.

/// Whether `c` changes the direction text is shown in: such a name looks like another.
fn is_bidi_control(c: char) -> bool {
    matches!(c, '\u{061C}' | '\u{200E}' | '\u{200F}' | '\u{202A}'..='\u{202E}' | '\u{2066}'..='\u{2069}')
}

/// Whether `c` acts on a terminal or a log rather than being shown: the C0 and C1 controls
/// (ESC, CR, LF, BEL...), and the Unicode line and paragraph separators, which break a
/// line like LF does.
fn is_control(c: char) -> bool {
    c.is_control() || matches!(c, '\u{2028}' | '\u{2029}')
}

/// Why `name` cannot be taken as a name, if it cannot: it holds a control character or a
/// bidi control. The caller says which name (its key, its file) and quotes it with
/// [`printable`].
pub fn problem(name: &str) -> Option<&'static str> {
    if name.chars().any(is_control) {
        return Some("contains control characters");
    }
    if name.chars().any(is_bidi_control) {
        return Some("contains characters that reverse the text's direction (bidi controls)");
    }
    None
}

/// `text` with control and bidi characters escaped (`\u{1b}`), whole: for what the
/// daemon reports about a job (a failure's reason may quote a name) on a terminal.
pub fn escaped(text: &str) -> String {
    text.chars().map(shown).collect()
}

/// One character as it is shown: escaped when it is a control or bidi character.
fn shown(c: char) -> String {
    match is_control(c) || is_bidi_control(c) {
        true => c.escape_unicode().to_string(),
        false => c.to_string(),
    }
}

/// Longest name shown in a message, in characters; longer ones are cut in the middle.
const SHOWN_NAME_CHARS: usize = 80;

/// A name as messages, logs and `crispen status` show it: control and bidi characters
/// escaped (`\u{1b}`), so a name cannot drive a terminal or reverse the text around it,
/// and cut to [`SHOWN_NAME_CHARS`] with `…` in the middle.
pub fn printable(name: &str) -> String {
    let escaped: Vec<String> = name.chars().map(shown).collect();
    if escaped.len() <= SHOWN_NAME_CHARS {
        return escaped.concat();
    }
    let half = SHOWN_NAME_CHARS / 2;
    format!(
        "{}…{}",
        escaped[..half].concat(),
        escaped[escaped.len() - half..].concat()
    )
}

/// A number as an error shows it: as written for ordinary values, in exponent form when
/// that would take more than 16 characters (`1e308`, not 309 digits).
pub fn number(value: f64) -> String {
    let plain = value.to_string();
    if plain.len() <= 16 {
        plain
    } else {
        format!("{value:e}")
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn names_are_printed_harmless_and_short() {
        assert_eq!(printable("bust.stl"), "bust.stl");
        assert_eq!(printable("a\u{1b}[31mb.stl"), "a\\u{1b}[31mb.stl");
        assert_eq!(printable("x\u{202e}lts.exe"), "x\\u{202e}lts.exe");
        assert_eq!(escaped("a\u{2028}b"), "a\\u{2028}b");
        let long = printable(&"é".repeat(4096));
        assert_eq!(long.chars().count(), SHOWN_NAME_CHARS + 1);
    }

    /// Every kind of character the check refuses, and what it lets through: any script,
    /// spaces, punctuation, emoji, a combining accent, a zero-width joiner.
    #[test]
    fn what_a_name_may_hold() {
        for good in [
            "a b.stl",
            "PLA+",
            "Prusament Galaxy Black",
            "ПЛА",
            "שחור",
            "黒",
            "cafe\u{301}",
            "🐙",
            "a\u{200d}b",
            "",
        ] {
            assert_eq!(problem(good), None, "{good:?}");
        }
        for control in [
            "a\u{1b}b", "\u{7}", "a\nb", "a\rb", "a\tb", "\u{85}", "\u{7f}",
        ] {
            assert_eq!(
                problem(control),
                Some("contains control characters"),
                "{control:?}"
            );
        }
        for separator in ["a\u{2028}b", "a\u{2029}b"] {
            assert!(problem(separator).is_some(), "{separator:?}");
        }
        for bidi in [
            '\u{061C}', '\u{200E}', '\u{200F}', '\u{202A}', '\u{202B}', '\u{202C}', '\u{202D}',
            '\u{202E}', '\u{2066}', '\u{2067}', '\u{2068}', '\u{2069}',
        ] {
            let name = format!("PLA{bidi}GTEP");
            assert!(
                problem(&name).is_some_and(|p| p.contains("bidi")),
                "{name:?}"
            );
            assert!(!printable(&name).contains(bidi));
        }
    }
}
