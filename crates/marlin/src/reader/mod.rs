//! How a line of G-code is read: once as written ([`read`]), and once the way each
//! firmware's own parser reads the bytes the host sends ([`marlin2`], [`ultimaker2`]).
//! Every reader of G-code in crispen (the G-code policy, the motion follower, the host's
//! pauses, the slicer-output checks) takes its commands from here.
//!
//! A line is accepted only when it is written plainly (a command `G1`, `M104`, `T0`, then
//! parameters: an upper-case letter and an optional number `[+-]digits[.digits]`, each
//! letter once) and, for [`read_for`], the firmware finds exactly that command with exactly
//! those parameters and values. Anything else is [`Unreadable`], with why: a firmware
//! reads past junk (`M104 @S400` sets 400 °C on Marlin 2), takes a number with an exponent
//! (`S2.7E2` is 270 on Ultimaker2Marlin), finds a `G` anywhere in a line (Ultimaker2Marlin
//! runs `M400 G92 Z50` as `G92 Z50`), or takes the first of two values where another takes
//! the last. A check that read such a line its own way would judge a command the printer
//! never runs. Before the parser comes the serial input ([`serial`]): where a line ends,
//! which number it is taken for (`M117 M110 N999` renumbers Marlin 2's count), what of it
//! is kept.

pub mod marlin2;
pub(crate) mod serial;
#[cfg(any(test, fuzzing))]
pub mod transcribed;
pub mod ultimaker2;
mod view;

use crate::firmware::Firmware;

pub use view::View;

/// The commands with which a file asks for a pause: wait for the user (`M0`, `M1`), pause
/// the print (`M25`, `M601`), park (`M125`), wait for a pin (`M226`), change the filament
/// (`M600`). On a printer with no one in front of it, each stops the printer until someone
/// presses its knob (or does nothing at all where the firmware lacks it, and the pause the
/// file wanted is lost). The host therefore never sends them: it pauses the printer itself
/// at that point and waits for the operator (see `crate::pause`).
pub const FILE_PAUSES: [&str; 7] = ["M0", "M1", "M25", "M125", "M226", "M601", "M600"];

/// One parameter of a command: its letter (upper case) and number, if it has one.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Word<'a> {
    pub letter: char,
    pub value: Option<f64>,
    /// The number as written (`-2.5`): each firmware reads it into a 32-bit float of its
    /// own ([`firmware_float`]).
    pub text: Option<&'a str>,
}

/// One command of a line, as every firmware reads it.
#[derive(Clone, Debug, PartialEq)]
pub struct Command<'a> {
    /// `G1`, `M104`, `T1`: letter and number (leading zeros dropped: `G01` is `G1`).
    pub code: String,
    pub words: Vec<Word<'a>>,
    /// The text after the code: the message of `M117`, the file of `M23`, the words of a
    /// pause (which the host intercepts, so its text is never sent).
    pub rest: &'a str,
}

impl Command<'_> {
    /// The number given for `letter`, if any.
    pub fn get(&self, letter: char) -> Option<f64> {
        self.words
            .iter()
            .find(|w| w.letter == letter)
            .and_then(|w| w.value)
    }

    /// The number given for `letter` as `firmware` reads it ([`firmware_float`]).
    pub fn get_f32(&self, letter: char, firmware: Firmware) -> Option<f32> {
        let text = self.words.iter().find(|w| w.letter == letter)?.text?;
        Some(firmware_float(firmware, text))
    }

    /// Whether `letter` is given (with or without a number).
    pub fn has(&self, letter: char) -> bool {
        self.words.iter().any(|w| w.letter == letter)
    }

    /// The command's letter: `G`, `M` or `T`.
    pub(crate) fn letter(&self) -> char {
        self.code.as_bytes()[0] as char
    }

    /// The command's number (`104` for `M104`).
    pub fn number(&self) -> u32 {
        self.code[1..].parse().unwrap_or(u32::MAX)
    }
}

/// A plain number (`[+-]digits[.digits]`) as `firmware` reads it: Marlin 2 with `strtof`,
/// rounded to the nearest float (glibc, and Rust's parser likewise); Ultimaker2Marlin with
/// avr-libc's `strtod`, which can land one float away ([`ultimaker2::strtod`]).
pub fn firmware_float(firmware: Firmware, text: &str) -> f32 {
    match firmware {
        Firmware::Marlin2 | Firmware::Marlin20 => marlin2::value_float(text.as_bytes()) as f32,
        Firmware::Ultimaker2 => ultimaker2::strtod(text.as_bytes()).0 as f32,
    }
}

/// Why a line cannot be taken as exactly one command with known parameters.
#[derive(Clone, Debug, PartialEq, thiserror::Error)]
#[error("{0}")]
pub struct Unreadable(pub String);

/// The highest command number read (Marlin keeps it in 16 bits; Ultimaker2Marlin in an
/// AVR `int`, so numbers past 32767 wrap): beyond, numbers are not read alike.
pub(crate) const MAX_CODE: u32 = 9999;

/// Commands whose text after the code is a string, not parameters, on Marlin 2
/// (`GCodeParser::parse` stops at them). Ultimaker2Marlin has no such notion: it looks for
/// its letters in the whole line, which [`ultimaker2`] models.
pub(crate) const STRING_COMMANDS: [&str; 6] = ["M23", "M28", "M30", "M117", "M118", "M928"];

/// A line's code (its comment already cut at `;`) as written: `None` for a blank line.
/// This is the reading every firmware agrees with for the lines it accepts; [`read_for`]
/// also checks that the firmware does.
pub fn read(code: &str) -> Result<Option<Command<'_>>, Unreadable> {
    let text = code.trim();
    if text.is_empty() {
        return Ok(None);
    }
    let bytes = text.as_bytes();
    let letter = bytes[0] as char;
    if letter == 'N'
        && bytes
            .get(1)
            .is_some_and(|b| b.is_ascii_digit() || *b == b'-')
    {
        return Err(Unreadable(
            "carries a line number of its own: the host numbers every line, so Marlin 2 \
             answers `Unknown command` while Ultimaker2Marlin runs the command"
                .into(),
        ));
    }
    if !matches!(letter, 'G' | 'M' | 'T') {
        return Err(Unreadable(if matches!(letter, 'g' | 'm' | 't') {
            "is written in lower case: stock Marlin answers `Unknown command`, a build with \
             GCODE_CASE_INSENSITIVE runs it"
                .into()
        } else {
            "is no G-code command (a command starts with G, M or T and its number)".into()
        }));
    }
    let digits = bytes[1..].iter().take_while(|b| b.is_ascii_digit()).count();
    if digits == 0 {
        return Err(Unreadable(format!(
            "has no number after `{letter}`: firmwares read such a line differently"
        )));
    }
    let number_text = &text[1..1 + digits];
    let number: u32 = number_text.trim_start_matches('0').parse().unwrap_or(
        if number_text.trim_start_matches('0').is_empty() {
            0
        } else {
            u32::MAX
        },
    );
    if number > MAX_CODE {
        return Err(Unreadable(format!(
            "has the command number {number_text}, beyond what firmwares read alike"
        )));
    }
    let code = format!("{letter}{number}");
    let after = &text[1 + digits..];
    if after.starts_with('.') {
        return Err(Unreadable(format!(
            "has a sub-code (`{code}{}`): stock Marlin reads it as `{code}` and the rest as \
             parameters, a build with sub-codes runs another command",
            after.split(' ').next().unwrap_or("")
        )));
    }
    if !after.is_empty() && !after.starts_with(' ') {
        // `G1X5` is read alike; `M104@S400` is not a plain parameter.
        if !after.as_bytes()[0].is_ascii_uppercase() {
            return Err(junk(after, 0));
        }
    }
    let rest = after.trim();
    if STRING_COMMANDS.contains(&code.as_str()) || FILE_PAUSES.contains(&code.as_str()) {
        // A string command's text is its argument; a pause is intercepted by the host and
        // never sent, so its words are only its message.
        return Ok(Some(Command {
            code,
            words: Vec::new(),
            rest,
        }));
    }
    let words = parameters(after, letter)?;
    Ok(Some(Command { code, words, rest }))
}

/// [`read`], and the firmware's own reading of the same line must find the same command
/// with the same parameters: otherwise the line is [`Unreadable`], naming the firmware and
/// what it would read. Before its parser, the firmware's serial input must take the line
/// whole, as the one line the host numbered ([`serial::check`]).
pub fn read_for(firmware: Firmware, code: &str) -> Result<Option<Command<'_>>, Unreadable> {
    let text = code.trim();
    if !text.is_empty() {
        serial::check(firmware, text).map_err(Unreadable)?;
    }
    let plain = read(text)?;
    let Some(cmd) = plain else {
        return Ok(None);
    };
    let view = match firmware {
        Firmware::Marlin2 | Firmware::Marlin20 => marlin2::read(text),
        Firmware::Ultimaker2 => ultimaker2::read(text),
    };
    agree(firmware, &cmd, &view)?;
    Ok(Some(cmd))
}

/// Checks the firmware's view against the plain reading.
fn agree(firmware: Firmware, cmd: &Command, view: &View) -> Result<(), Unreadable> {
    let fw = match firmware {
        Firmware::Marlin2 | Firmware::Marlin20 => "Marlin 2",
        Firmware::Ultimaker2 => "Ultimaker2Marlin",
    };
    let written = (cmd.letter(), cmd.number());
    match view.command {
        Some(c) if c == written => {}
        Some((l, n)) => {
            return Err(Unreadable(format!(
                "is run as `{l}{n}` by {fw} (it looks for {l} anywhere in the line), not as \
                 `{}`",
                cmd.code
            )))
        }
        None => {
            return Err(Unreadable(format!(
                "is no command {fw} runs (it answers `Unknown command`)"
            )))
        }
    }
    if FILE_PAUSES.contains(&cmd.code.as_str()) {
        // Never sent: the host pauses instead.
        return Ok(());
    }
    if STRING_COMMANDS.contains(&cmd.code.as_str()) {
        // Marlin 2 reads no parameters in them; Ultimaker2Marlin's handlers of these take
        // the text only (its letters matter only as the command, checked above).
        return Ok(());
    }
    for i in 0..26u8 {
        let letter = (b'A' + i) as char;
        // The command's own letter and the host's line number are no parameters.
        if letter == cmd.letter() || letter == 'N' {
            continue;
        }
        let word = cmd.words.iter().find(|w| w.letter == letter);
        let written = word.map(|w| w.value);
        let read = view.params[i as usize];
        let same = match (written, read) {
            (None, None) => true,
            (Some(None), Some(None)) => true,
            // The firmware's value must be what it reads from the written digits.
            (Some(Some(_)), Some(Some(b))) => {
                word.and_then(|w| w.text)
                    .map(|t| firmware_float(firmware, t))
                    == Some(b as f32)
            }
            _ => false,
        };
        if !same {
            let shown = |v: Option<Option<f64>>| match v {
                None => "nothing".to_string(),
                Some(None) => format!("{letter} without a number"),
                Some(Some(x)) => format!("{letter}{x}"),
            };
            return Err(Unreadable(format!(
                "is read by {fw} with {} where it is written with {}",
                shown(read),
                shown(written)
            )));
        }
    }
    Ok(())
}

/// The parameters of a non-string command, written plainly: `X10 Y-2.5 E.4 F1800`, with or
/// without spaces between them, a space allowed between a letter and its number.
fn parameters(text: &str, command: char) -> Result<Vec<Word<'_>>, Unreadable> {
    let bytes = text.as_bytes();
    let mut words: Vec<Word> = Vec::new();
    let mut i = 0;
    while i < bytes.len() {
        let c = bytes[i];
        if c == b' ' {
            i += 1;
            continue;
        }
        if c.is_ascii_lowercase() {
            return Err(Unreadable(format!(
                "gives `{}` in lower case: stock Marlin skips it, a build with \
                 GCODE_CASE_INSENSITIVE reads it",
                c as char
            )));
        }
        if !c.is_ascii_uppercase() {
            return Err(junk(text, i));
        }
        let letter = c as char;
        if letter == 'N' {
            return Err(Unreadable(
                "gives N, which the host's line number would be confused with".into(),
            ));
        }
        if letter == command {
            return Err(Unreadable(format!(
                "gives {letter} again as a parameter: Ultimaker2Marlin reads the command's own \
                 number for it"
            )));
        }
        if words.iter().any(|w| w.letter == letter) {
            return Err(Unreadable(format!(
                "gives {letter} twice: Marlin 2 takes the last, Ultimaker2Marlin the first"
            )));
        }
        i += 1;
        let mut j = i;
        while j < bytes.len() && bytes[j] == b' ' {
            j += 1;
        }
        let len = number_len(&bytes[j..]);
        let number = (len > 0).then(|| &text[j..j + len]);
        let value = if let Some(n) = number {
            i = j + len;
            // Digits, a sign and one point parse; a value past f64 is no plain number.
            match n.parse::<f64>() {
                Ok(v) if v.is_finite() && v.abs() < 1e9 => Some(v),
                _ => {
                    return Err(Unreadable(format!(
                        "gives {letter}{n}, a number firmwares do not read alike"
                    )))
                }
            }
        } else {
            None
        };
        if let Some(&next) = bytes.get(i) {
            if next != b' ' && !next.is_ascii_uppercase() {
                return Err(junk(text, i));
            }
        }
        words.push(Word {
            letter,
            value,
            text: number,
        });
    }
    Ok(words)
}

/// The length of a plain number at the start of `bytes`: `[+-]?(digits(.digits*)?|.digits)`.
fn number_len(bytes: &[u8]) -> usize {
    let mut i = usize::from(matches!(bytes.first(), Some(b'+' | b'-')));
    let int = bytes[i..].iter().take_while(|b| b.is_ascii_digit()).count();
    i += int;
    let mut frac = 0;
    if bytes.get(i) == Some(&b'.') {
        frac = bytes[i + 1..]
            .iter()
            .take_while(|b| b.is_ascii_digit())
            .count();
        if int + frac > 0 {
            i += 1 + frac;
        }
    }
    if int + frac == 0 {
        0
    } else {
        i
    }
}

fn junk(text: &str, at: usize) -> Unreadable {
    let c = text[at..].chars().next().unwrap_or(' ');
    let shown = match c {
        '\t' => "a tab".to_string(),
        c if c.is_control() => format!("the control character U+{:04X}", c as u32),
        c => format!("`{c}`"),
    };
    Unreadable(format!(
        "holds {shown} where a parameter belongs: firmwares skip such text and read the \
         letters after it, so what runs is not what is written"
    ))
}

#[cfg(test)]
mod tests;
