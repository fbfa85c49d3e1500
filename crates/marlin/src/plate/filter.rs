//! What the host sends of a plate once parts of it are cancelled: a pure transducer that
//! takes the job's commands one at a time, in order, and says for each whether it goes
//! as it is, rewritten, or not at all. The host asks it for each line as it is about to
//! send it, so a cancel takes effect from the next line not yet decided.
//!
//! In a cancelled part's lines (from the cancel on):
//! - its extruding moves are not sent: in absolute positioning, each stretch of the part's
//!   moves (up to the part's end, or a command that depends on where the head is: `G92` of
//!   X/Y/Z, `G28`, `G90`/`G91`, a tool change...) becomes one travel, at its last move, to
//!   where the stretch ends, written with the file's own numbers for each axis it named
//!   (so the firmware's 32-bit position is the one the file's moves would have left), at
//!   the feed rate in force after it in the file; in relative positioning each move is sent
//!   without its extrusion, so the firmware adds the same numbers;
//! - what is no extrusion still runs: retractions and the pushes that undo them (an
//!   `E`-only move, a wipe's retraction, sent as a move of `E` alone), `G92 E`, firmware
//!   retraction (`G10`/`G11`), temperatures, fans, Z and every other command;
//! - in absolute extrusion (`M82`), the filament not pushed leaves the firmware's `E`
//!   behind the file's: every later `E` the host sends is the file's less that difference,
//!   computed exactly on the file's decimals, until a `G92 E` sets both alike again.
//!
//! The other parts' lines are therefore the file's own, and the head is where the file
//! would have left it whenever a line of theirs is sent.

use crate::firmware::Firmware;
use crate::gcode::GcodeCommands;
use crate::labels::Marks;
use crate::motion::{Command, Motion};
use crate::reader;
use std::borrow::Cow;
use std::sync::Arc;

/// What the host sends for one command.
#[derive(Clone, Debug, PartialEq, Eq)]
pub enum Decision<'a> {
    /// The command as the file writes it.
    Send(&'a str),
    /// Another line in its place.
    Rewrite(String),
    /// Nothing.
    Skip,
}

impl<'a> Decision<'a> {
    /// The line sent, if any.
    pub fn line(self) -> Option<Cow<'a, str>> {
        match self {
            Decision::Send(s) => Some(Cow::Borrowed(s)),
            Decision::Rewrite(s) => Some(Cow::Owned(s)),
            Decision::Skip => None,
        }
    }
}

/// Filament positions in units of 10⁻⁹ mm: a file's `E` decimals (PrusaSlicer and Cura
/// write five) add and subtract exactly.
type Nano = i128;
const NANO: f64 = 1e9;

/// A stretch of a cancelled part's lines sent as one travel.
#[derive(Clone, Debug)]
struct Stretch {
    /// The first command after it.
    end: usize,
    /// Its last move that changes where the head is: the travel goes in its place.
    target: Option<usize>,
    /// The file's number for X, Y, Z as the stretch last names each.
    axes: [Option<String>; 3],
}

/// The host's filter of a plate's lines (see the module's comment).
#[derive(Clone, Debug)]
pub struct PartFilter {
    marks: Arc<Marks>,
    /// Per part: the command it is dropped from.
    cancelled: Vec<Option<usize>>,
    /// The next command to decide.
    next: usize,
    /// The file followed as written: its modes.
    original: Motion,
    /// The feed rate in force in the file, and in what the host sent, as written.
    feed: Option<String>,
    sent_feed: Option<String>,
    /// The file's `E` and the one the host has sent, in absolute terms.
    file_e: Nano,
    sent_e: Nano,
    stretch: Option<Stretch>,
    /// Filament each part's lines pushed that was not sent, mm.
    dropped: Vec<Nano>,
}

impl PartFilter {
    pub fn new(marks: Arc<Marks>, firmware: Firmware) -> PartFilter {
        let parts = marks.names().len();
        PartFilter {
            marks,
            cancelled: vec![None; parts],
            next: 0,
            original: Motion::new(firmware),
            feed: None,
            sent_feed: None,
            file_e: 0,
            sent_e: 0,
            stretch: None,
            dropped: vec![0; parts],
        }
    }

    pub fn marks(&self) -> &Marks {
        &self.marks
    }

    /// The next command to decide: where a cancel now takes effect.
    pub fn next(&self) -> usize {
        self.next
    }

    /// Drops `part` from the next command not yet decided on; a part already cancelled
    /// keeps its first cancel. Returns the command it is dropped from, None for no such
    /// part.
    pub fn cancel(&mut self, part: u16) -> Option<usize> {
        let next = self.next;
        self.cancel_from(part, next)
    }

    /// Drops `part` from command `from` on (not before the next one to decide): a cancel
    /// made while printing, replayed (to measure what a print pushed).
    pub fn cancel_from(&mut self, part: u16, from: usize) -> Option<usize> {
        let slot = self.cancelled.get_mut(usize::from(part))?;
        Some(*slot.get_or_insert(from.max(self.next)))
    }

    /// The command each part is dropped from (None: not cancelled).
    pub fn cancelled(&self) -> &[Option<usize>] {
        &self.cancelled
    }

    /// Whether every part is cancelled.
    pub fn all_cancelled(&self) -> bool {
        self.cancelled.iter().all(Option::is_some)
    }

    /// Filament `part`'s lines would have pushed after its cancel and were not sent, mm.
    pub fn dropped_mm(&self, part: u16) -> f64 {
        self.dropped
            .get(usize::from(part))
            .map_or(0.0, |&n| n as f64 / NANO)
    }

    /// Decides command [`PartFilter::next`] of `commands` (the whole job's) and moves on.
    pub fn decide<'c>(&mut self, commands: &'c GcodeCommands) -> Option<Decision<'c>> {
        let index = self.next;
        let text = commands.get(index)?;
        self.next += 1;
        if self.stretch.as_ref().is_some_and(|s| s.end <= index) {
            self.stretch = None;
        }
        let cmd = match reader::read(text) {
            Ok(Some(cmd)) => cmd,
            // What the follower cannot read goes as it is (the G-code policy refuses it
            // before a job is printed).
            _ => return Some(Decision::Send(text)),
        };
        let dropping = self
            .marks
            .part_at(index)
            .filter(|&p| self.cancelled[usize::from(p)].is_some_and(|from| from <= index));
        let decision = match dropping {
            Some(part) => self.drop(commands, index, text, &cmd, part),
            None => self.keep(text, &cmd),
        };
        if is_move(&cmd) {
            if let Some(f) = word_text(&cmd, 'F') {
                self.feed = Some(f.to_string());
            }
        }
        let sent_feed = match &decision {
            Decision::Send(_) => is_move(&cmd).then(|| word_text(&cmd, 'F')).flatten(),
            Decision::Rewrite(line) => line
                .split(' ')
                .find_map(|w| w.strip_prefix('F'))
                .filter(|_| line.starts_with('G')),
            Decision::Skip => None,
        };
        if let Some(f) = sent_feed {
            self.sent_feed = Some(f.to_string());
        }
        let _ = self.original.apply(&cmd);
        Some(decision)
    }

    /// A command of a part still printed, or outside every part: sent as written, with its
    /// `E` shifted in absolute extrusion where filament was not pushed, and the file's feed
    /// rate where dropped moves set it and the host did not send them.
    fn keep<'c>(&mut self, text: &'c str, cmd: &Command) -> Decision<'c> {
        if cmd.code == "G92" {
            if let Some(e) = word_text(cmd, 'E').and_then(nano) {
                self.file_e = e;
                self.sent_e = e;
            }
            return Decision::Send(text);
        }
        if !is_move(cmd) {
            return Decision::Send(text);
        }
        let mut changes: Vec<(char, Option<String>)> = Vec::new();
        if let Some(e) = word_text(cmd, 'E').and_then(nano) {
            if self.original.e_relative() {
                self.file_e += e;
                self.sent_e += e;
            } else {
                let behind = self.file_e - self.sent_e;
                self.file_e = e;
                self.sent_e = e - behind;
                if behind != 0 {
                    changes.push(('E', Some(decimal(e - behind))));
                }
            }
        }
        let mut line = if changes.is_empty() {
            Cow::Borrowed(text)
        } else {
            Cow::Owned(rewrite(cmd, &changes))
        };
        if !cmd.has('F') && self.feed != self.sent_feed {
            if let Some(f) = &self.feed {
                line = Cow::Owned(format!("{line} F{f}"));
            }
        }
        match line {
            Cow::Borrowed(text) => Decision::Send(text),
            Cow::Owned(line) => Decision::Rewrite(line),
        }
    }

    /// A command of a cancelled part.
    fn drop<'c>(
        &mut self,
        commands: &GcodeCommands,
        index: usize,
        text: &'c str,
        cmd: &Command,
        part: u16,
    ) -> Decision<'c> {
        if !is_move(cmd) {
            return self.keep(text, cmd);
        }
        let positions =
            ['X', 'Y', 'Z'].iter().any(|l| cmd.has(*l)) || cmd.code != "G0" && cmd.code != "G1";
        if !positions {
            // Only E (a retraction or its undoing) or only F: no extrusion on the part.
            return self.keep(text, cmd);
        }
        // What its E would push, and the E sent for a retraction (a wipe's).
        let relative_e = self.original.e_relative();
        let e = word_text(cmd, 'E').and_then(nano);
        let (push, retract) = match e {
            None => (0, None),
            Some(e) => {
                let delta = if relative_e { e } else { e - self.file_e };
                if delta > 0 {
                    self.file_e += delta;
                    (delta, None)
                } else {
                    let behind = self.file_e - self.sent_e;
                    self.file_e += delta;
                    self.sent_e += delta;
                    let sent = if relative_e { e } else { e - behind };
                    (0, Some(decimal(sent)))
                }
            }
        };
        self.dropped[usize::from(part)] += push;
        if self.original.xyz_relative() {
            // Each move as the firmware adds it, without the extrusion.
            return Decision::Rewrite(rewrite(cmd, &[('E', retract)]));
        }
        if self.stretch.is_none() {
            self.stretch = Some(self.stretch_from(commands, index));
        }
        let feed = word_text(cmd, 'F')
            .map(str::to_string)
            .or(self.feed.clone());
        let stretch = self.stretch.as_ref().expect("just set");
        if stretch.target != Some(index) {
            return match retract {
                Some(e) => {
                    Decision::Rewrite(match feed.filter(|f| Some(f) != self.sent_feed.as_ref()) {
                        Some(f) => format!("G1 E{e} F{f}"),
                        None => format!("G1 E{e}"),
                    })
                }
                None => Decision::Skip,
            };
        }
        let mut line = String::from("G1");
        for (letter, value) in ['X', 'Y', 'Z'].iter().zip(&stretch.axes) {
            if let Some(v) = value {
                line += &format!(" {letter}{v}");
            }
        }
        if let Some(e) = retract {
            line += &format!(" E{e}");
        }
        if let Some(f) = feed {
            line += &format!(" F{f}");
        }
        Decision::Rewrite(line)
    }

    /// The stretch of dropped lines that begins at `start`, in absolute positioning: up
    /// to the part's next mark or the first command that depends on where the head is.
    fn stretch_from(&self, commands: &GcodeCommands, start: usize) -> Stretch {
        let limit = self
            .marks
            .next_mark_after(start)
            .unwrap_or(usize::MAX)
            .min(commands.len());
        let mut stretch = Stretch {
            end: limit,
            target: None,
            axes: [None, None, None],
        };
        for j in start..limit {
            let cmd = match commands.get(j).map(reader::read) {
                Some(Ok(Some(cmd))) => cmd,
                Some(Ok(None)) => continue,
                _ => {
                    stretch.end = j;
                    break;
                }
            };
            if is_barrier(&cmd) {
                stretch.end = j;
                break;
            }
            if !is_move(&cmd) {
                continue;
            }
            let named: Vec<(usize, &str)> = ['X', 'Y', 'Z']
                .iter()
                .enumerate()
                .filter_map(|(k, l)| word_text(&cmd, *l).map(|t| (k, t)))
                .collect();
            if named.is_empty() && (cmd.code == "G0" || cmd.code == "G1") {
                continue;
            }
            stretch.target = Some(j);
            for (k, t) in named {
                stretch.axes[k] = Some(t.to_string());
            }
        }
        stretch
    }
}

/// A move: `G0`-`G3`, `G5`.
fn is_move(cmd: &Command) -> bool {
    matches!(cmd.code.as_str(), "G0" | "G1" | "G2" | "G3" | "G5")
}

/// A command after which the head's place or the file's coordinates may differ from what
/// the moves before it say: a stretch of dropped moves ends before it.
fn is_barrier(cmd: &Command) -> bool {
    match cmd.letter() {
        'T' => true,
        'G' => match cmd.code.as_str() {
            "G0" | "G1" | "G2" | "G3" | "G5" | "G4" | "G10" | "G11" | "G21" => false,
            "G92" => ['X', 'Y', 'Z'].iter().any(|l| cmd.has(*l)),
            _ => true,
        },
        _ => matches!(cmd.code.as_str(), "M206" | "M428"),
    }
}

/// The number `letter` is written with.
fn word_text<'a>(cmd: &Command<'a>, letter: char) -> Option<&'a str> {
    cmd.words.iter().find(|w| w.letter == letter)?.text
}

/// `cmd` written again with some words changed: `(letter, Some(text))` replaces the
/// number, `(letter, None)` leaves the word out.
fn rewrite(cmd: &Command, changes: &[(char, Option<String>)]) -> String {
    let mut line = cmd.code.clone();
    for w in &cmd.words {
        let text = match changes.iter().find(|(l, _)| *l == w.letter) {
            Some((_, None)) => continue,
            Some((_, Some(t))) => Some(t.as_str()),
            None => w.text,
        };
        line.push(' ');
        line.push(w.letter);
        if let Some(t) = text {
            line += t;
        }
    }
    line
}

/// A plain number (`[+-]digits[.digits]`, as the reader takes them) in units of 10⁻⁹,
/// rounded to the nearest beyond nine decimals.
fn nano(text: &str) -> Option<Nano> {
    let (negative, digits) = match text.as_bytes().first()? {
        b'-' => (true, &text[1..]),
        b'+' => (false, &text[1..]),
        _ => (false, text),
    };
    let (whole, fraction) = digits.split_once('.').unwrap_or((digits, ""));
    let mut value: Nano = 0;
    for b in whole.bytes() {
        let d = b.checked_sub(b'0').filter(|d| *d < 10)?;
        value = value.checked_mul(10)?.checked_add(Nano::from(d))?;
    }
    let mut scale: Nano = 1_000_000_000;
    let mut frac: Nano = 0;
    for (i, b) in fraction.bytes().enumerate() {
        let d = Nano::from(b.checked_sub(b'0').filter(|d| *d < 10)?);
        if i < 9 {
            scale /= 10;
            frac += d * scale;
        } else if i == 9 && d >= 5 {
            frac += 1;
        }
    }
    let value = value.checked_mul(1_000_000_000)?.checked_add(frac)?;
    Some(if negative { -value } else { value })
}

/// A [`Nano`] written as a plain number, without trailing zeros.
fn decimal(v: Nano) -> String {
    let sign = if v < 0 { "-" } else { "" };
    let a = v.unsigned_abs();
    let (whole, frac) = (a / 1_000_000_000, a % 1_000_000_000);
    if frac == 0 {
        return format!("{sign}{whole}");
    }
    let frac = format!("{frac:09}");
    format!("{sign}{whole}.{}", frac.trim_end_matches('0'))
}

#[cfg(test)]
mod tests;
