//! Which part of a plate each line belongs to, as the slicers and firmwares label it:
//!
//! | who                            | a part starts                    | it ends                  |
//! |--------------------------------|----------------------------------|--------------------------|
//! | PrusaSlicer (`gcode_label_objects`, OctoPrint style) | `; printing object NAME` | `; stop printing object NAME` |
//! | CuraEngine                     | `;MESH:NAME`                     | `;MESH:NONMESH` or the next `;MESH:` |
//! | Klipper (`EXCLUDE_OBJECT`)     | `EXCLUDE_OBJECT_START NAME=NAME` | `EXCLUDE_OBJECT_END`     |
//! | Marlin (`CANCEL_OBJECTS`)      | `M486 S<i>` (named by `M486 A`)  | `M486 S-1`               |
//!
//! The comments cost nothing to send, since the host strips them; the label commands are
//! never sent: Klipper's are no Marlin command (Marlin answers `Unknown command`, and a
//! `POLYGON` is longer than a line may be), and `M486` is the firmware's own object
//! cancel, which the host does itself on every firmware (see the plate's `filter`). A file
//! labelled two ways (a post-processor adding `M486` to a Cura file) is read by the first
//! way seen, so that one region never belongs to two parts.
//!
//! The reader keeps, per part, its name, and the index of the first command (among the
//! commands the host sends) where each part starts or stops: [`Marks`].

use std::collections::BTreeMap;

/// The most parts one plate may have: a bed of 300 × 300 mm holds no more 20 mm parts.
pub const MAX_PARTS: usize = 250;
/// The longest part name kept (longer ones are cut, at a character boundary).
pub const MAX_NAME_CHARS: usize = 100;

/// What a line of a file is to the plate.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub(crate) enum LineLabel {
    /// Not a label.
    No,
    /// A comment that labels (the host strips comments anyway).
    Comment,
    /// A label command the host does not send.
    Command,
}

/// The ways of labelling (see the module's table).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
enum Scheme {
    Prusa,
    Cura,
    Klipper,
    M486,
}

/// Where each part of a plate starts and stops among a job's commands.
#[derive(Clone, Debug, Default, PartialEq, Eq)]
pub struct Marks {
    names: Vec<String>,
    /// `(index, part)`: from the command at `index` on, the lines are `part`'s (None: no
    /// part's); in file order, indices never decreasing.
    marks: Vec<(usize, Option<u16>)>,
}

impl Marks {
    /// The parts' names, in the order the file first names them.
    pub fn names(&self) -> &[String] {
        &self.names
    }

    /// The part that command `index` belongs to.
    pub fn part_at(&self, index: usize) -> Option<u16> {
        let after = self.marks.partition_point(|(at, _)| *at <= index);
        after.checked_sub(1).and_then(|i| self.marks[i].1)
    }

    /// The index of the first mark after command `index` (where the part it is in may end).
    pub(crate) fn next_mark_after(&self, index: usize) -> Option<usize> {
        let after = self.marks.partition_point(|(at, _)| *at <= index);
        self.marks.get(after).map(|(at, _)| *at)
    }

    /// Each run of commands of one part: `(first..end, part)`, in file order, empty ones
    /// left out.
    pub fn runs(
        &self,
        commands: usize,
    ) -> impl Iterator<Item = (std::ops::Range<usize>, u16)> + '_ {
        self.marks
            .iter()
            .enumerate()
            .filter_map(move |(i, &(at, part))| {
                let end = self
                    .marks
                    .get(i + 1)
                    .map_or(commands, |m| m.0)
                    .min(commands);
                let part = part?;
                (at < end).then_some((at..end, part))
            })
    }

    /// The part named `name` (exactly, or its number from 1 in [`Marks::names`]' order).
    pub fn find(&self, name: &str) -> Option<u16> {
        if let Some(i) = self.names.iter().position(|n| n == name) {
            return Some(i as u16);
        }
        let n: usize = name.trim().parse().ok()?;
        (1..=self.names.len()).contains(&n).then(|| (n - 1) as u16)
    }
}

/// Reads a file's labels line by line, as the host loads it.
#[derive(Debug, Default)]
pub(crate) struct LabelReader {
    scheme: Option<Scheme>,
    marks: Marks,
    /// Marlin's objects by their `M486` number, and the one selected last.
    m486: BTreeMap<i64, u16>,
    selected: Option<i64>,
    /// Names past [`MAX_PARTS`] were seen: the file is no plate crispen can cancel parts of.
    too_many: bool,
}

impl LabelReader {
    /// Reads one line as written (comment included); `next_command` is the index the next
    /// command sent will have.
    pub(crate) fn line(&mut self, line: &str, next_command: usize) -> LineLabel {
        let text = line.trim();
        if let Some(comment) = text.strip_prefix(';') {
            let comment = comment.trim_end();
            if let Some(name) = comment.strip_prefix("MESH:") {
                if self.takes(Scheme::Cura) {
                    if name.trim() == "NONMESH" {
                        self.stop(next_command);
                    } else {
                        // CuraEngine names a mesh by the file it was given, folders and all.
                        let name = name.rsplit(['/', '\\']).next().unwrap_or(name);
                        self.start(name, next_command);
                    }
                }
                return LineLabel::Comment;
            }
            let comment = comment.trim_start();
            if let Some(name) = comment.strip_prefix("printing object ") {
                if self.takes(Scheme::Prusa) {
                    self.start(name, next_command);
                }
                return LineLabel::Comment;
            }
            if comment.starts_with("stop printing object") {
                if self.takes(Scheme::Prusa) {
                    self.stop(next_command);
                }
                return LineLabel::Comment;
            }
            return LineLabel::No;
        }
        // A label command is never sent, with or without a comment after it.
        let code = text.split(';').next().unwrap_or_default().trim();
        if let Some(rest) = strip_word(code, "EXCLUDE_OBJECT_DEFINE") {
            if let Some(name) = klipper_name(rest) {
                if self.takes(Scheme::Klipper) {
                    self.part(name);
                }
            }
            return LineLabel::Command;
        }
        if let Some(rest) = strip_word(code, "EXCLUDE_OBJECT_START") {
            if self.takes(Scheme::Klipper) {
                match klipper_name(rest) {
                    Some(name) => self.start(name, next_command),
                    None => self.stop(next_command),
                }
            }
            return LineLabel::Command;
        }
        if strip_word(code, "EXCLUDE_OBJECT_END").is_some() {
            if self.takes(Scheme::Klipper) {
                self.stop(next_command);
            }
            return LineLabel::Command;
        }
        if let Some(rest) = strip_word(code, "M486") {
            if self.takes(Scheme::M486) {
                self.m486(rest, next_command);
            }
            return LineLabel::Command;
        }
        LineLabel::No
    }

    /// The marks read from a file of `commands` commands, if it labels at least one of
    /// them as a part's.
    pub(crate) fn finish(self, commands: usize) -> Option<Marks> {
        if self.too_many {
            tracing::warn!(
                "the file labels more than {MAX_PARTS} parts: its parts cannot be cancelled"
            );
            return None;
        }
        let any = self.marks.runs(commands).next().is_some();
        any.then_some(self.marks)
    }

    /// Whether labels of `scheme` count: the first scheme seen is the file's.
    fn takes(&mut self, scheme: Scheme) -> bool {
        *self.scheme.get_or_insert(scheme) == scheme
    }

    /// The part named `name`, added if new.
    fn part(&mut self, name: &str) -> Option<u16> {
        let name = clean_name(name);
        if let Some(i) = self.marks.names.iter().position(|n| *n == name) {
            return Some(i as u16);
        }
        if self.marks.names.len() >= MAX_PARTS {
            self.too_many = true;
            return None;
        }
        self.marks.names.push(name);
        Some((self.marks.names.len() - 1) as u16)
    }

    fn start(&mut self, name: &str, at: usize) {
        let part = self.part(name);
        self.mark(at, part);
    }

    fn stop(&mut self, at: usize) {
        self.mark(at, None);
    }

    fn mark(&mut self, at: usize, part: Option<u16>) {
        let marks = &mut self.marks.marks;
        match marks.last_mut() {
            // Nothing between two marks: the later one stands.
            Some(last) if last.0 == at => last.1 = part,
            Some(last) if last.1 == part => {}
            None if part.is_none() => {}
            _ => marks.push((at, part)),
        }
    }

    /// `M486 T<count>`, `S<i>` (select; -1: none), `A<name>` (name the selected one), and
    /// the firmware's own cancels (`P`, `U`, `C`), which only a firmware acts on.
    fn m486(&mut self, rest: &str, at: usize) {
        let rest = rest.trim();
        let (letter, value) = match rest.chars().next() {
            Some(c) => (c.to_ascii_uppercase(), rest[c.len_utf8()..].trim()),
            None => return,
        };
        match letter {
            'S' => {
                // `S<i>` may carry its name after it (RepRapFirmware's `S0 A"name"`).
                let (number, name) = match value.find(['A', 'a']) {
                    Some(i) => (value[..i].trim(), Some(value[i + 1..].trim())),
                    None => (value, None),
                };
                let Ok(i) = number.parse::<i64>() else { return };
                if i < 0 {
                    self.selected = None;
                    self.stop(at);
                    return;
                }
                self.selected = Some(i);
                if let Some(name) = name {
                    self.name_m486(i, name);
                }
                let part = match self.m486.get(&i) {
                    Some(&p) => Some(p),
                    None => {
                        let p = self.part(&format!("object {i}"));
                        if let Some(p) = p {
                            self.m486.insert(i, p);
                        }
                        p
                    }
                };
                self.mark(at, part);
            }
            'A' => {
                if let Some(i) = self.selected {
                    self.name_m486(i, value);
                }
            }
            _ => {}
        }
    }

    /// Names Marlin's object `i` (renaming the placeholder it may have had).
    fn name_m486(&mut self, i: i64, name: &str) {
        let name = clean_name(name.trim_matches('"'));
        if name.is_empty() {
            return;
        }
        match self.m486.get(&i) {
            Some(&p) => {
                if !self.marks.names.contains(&name) {
                    self.marks.names[usize::from(p)] = name;
                }
            }
            None => {
                if let Some(p) = self.part(&name) {
                    self.m486.insert(i, p);
                }
            }
        }
    }
}

/// Whether a line's code (its comment cut) is a label command, which the host never sends
/// (see the module's table).
pub fn is_label_command(code: &str) -> bool {
    let code = code.trim();
    [
        "EXCLUDE_OBJECT_DEFINE",
        "EXCLUDE_OBJECT_START",
        "EXCLUDE_OBJECT_END",
        "M486",
    ]
    .iter()
    .any(|w| strip_word(code, w).is_some())
}

/// `code` starting with the word `word` (any case), and what follows it.
fn strip_word<'a>(code: &'a str, word: &str) -> Option<&'a str> {
    let head = code.get(..word.len())?;
    if !head.eq_ignore_ascii_case(word) {
        return None;
    }
    let rest = &code[word.len()..];
    (rest.is_empty() || rest.starts_with(' ')).then_some(rest)
}

/// The `NAME=` of a Klipper label, unquoted.
fn klipper_name(rest: &str) -> Option<&str> {
    let at = rest.to_ascii_uppercase().find("NAME=")?;
    let value = &rest[at + 5..];
    let value = if let Some(quoted) = value.strip_prefix('\'').or(value.strip_prefix('"')) {
        let end = quoted.find(['\'', '"']).unwrap_or(quoted.len());
        &quoted[..end]
    } else {
        value.split_whitespace().next().unwrap_or("")
    };
    (!value.is_empty()).then_some(value)
}

/// A name as shown: control characters dropped, spaces trimmed, cut to
/// [`MAX_NAME_CHARS`].
fn clean_name(name: &str) -> String {
    name.trim()
        .chars()
        .filter(|c| !c.is_control())
        .take(MAX_NAME_CHARS)
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Reads `text` as the host loads it: commands are the lines with code that are no
    /// label; returns the marks and the commands.
    fn read(text: &str) -> (Option<Marks>, Vec<String>) {
        let mut reader = LabelReader::default();
        let mut commands = Vec::new();
        for line in text.lines() {
            match reader.line(line, commands.len()) {
                LineLabel::Command | LineLabel::Comment => {}
                LineLabel::No => {
                    let code = line.split(';').next().unwrap().trim();
                    if !code.is_empty() {
                        commands.push(code.to_string());
                    }
                }
            }
        }
        (reader.finish(commands.len()), commands)
    }

    fn runs(marks: &Marks, n: usize) -> Vec<(std::ops::Range<usize>, String)> {
        marks
            .runs(n)
            .map(|(r, p)| (r, marks.names()[usize::from(p)].clone()))
            .collect()
    }

    #[test]
    fn prusaslicer_comments_mark_each_part() {
        let (marks, commands) = read(
            "G28\n; printing object a id:0 copy 0\nG1 X1 E1\nG1 X2 E2\n\
             ; stop printing object a id:0 copy 0\n; printing object b id:0 copy 1\nG1 X3 E3\n\
             ; stop printing object b id:0 copy 1\nG1 Z1\n; printing object a id:0 copy 0\n\
             G1 X4 E4\n; stop printing object a id:0 copy 0\n",
        );
        let marks = marks.unwrap();
        assert_eq!(marks.names(), ["a id:0 copy 0", "b id:0 copy 1"]);
        assert_eq!(
            runs(&marks, commands.len()),
            [
                (1..3, "a id:0 copy 0".into()),
                (3..4, "b id:0 copy 1".into()),
                (5..6, "a id:0 copy 0".into())
            ]
        );
        assert_eq!(marks.part_at(0), None);
        assert_eq!(marks.part_at(2), Some(0));
        assert_eq!(marks.part_at(4), None);
        assert_eq!(marks.find("2"), Some(1));
        assert_eq!(marks.find("b id:0 copy 1"), Some(1));
        assert_eq!(marks.find("c"), None);
    }

    #[test]
    fn cura_meshes_end_at_the_next_mesh_or_nonmesh() {
        let (marks, commands) = read(
            ";LAYER:0\nG0 X1\n;MESH:a.stl\nG1 X2 E1\n;MESH:/tmp/x/b.stl\nG1 X3 E2\n;MESH:NONMESH\nG0 Z1\n",
        );
        let marks = marks.unwrap();
        assert_eq!(
            runs(&marks, commands.len()),
            [(1..2, "a.stl".into()), (2..3, "b.stl".into())]
        );
        assert_eq!(commands, ["G0 X1", "G1 X2 E1", "G1 X3 E2", "G0 Z1"]);
    }

    #[test]
    fn klipper_and_marlin_labels_are_read_and_never_sent() {
        let (marks, commands) = read(
            "EXCLUDE_OBJECT_DEFINE NAME='cube_1' CENTER=10,10 POLYGON=[[0,0],[1,1]]\n\
             EXCLUDE_OBJECT_DEFINE NAME=cube_2 CENTER=20,20\nG28\n\
             EXCLUDE_OBJECT_START NAME=cube_2\nG1 X1 E1\nEXCLUDE_OBJECT_END NAME=cube_2\n\
             EXCLUDE_OBJECT_START NAME='cube_1'\nG1 X2 E2\nEXCLUDE_OBJECT_END NAME='cube_1'\n",
        );
        let marks = marks.unwrap();
        assert_eq!(marks.names(), ["cube_1", "cube_2"]);
        assert_eq!(
            runs(&marks, commands.len()),
            [(1..2, "cube_2".into()), (2..3, "cube_1".into())]
        );
        assert_eq!(commands, ["G28", "G1 X1 E1", "G1 X2 E2"]);
        // PrusaSlicer's firmware labels for Marlin: a header naming each, then numbers.
        let (marks, commands) = read(
            "M486 T2\nM486 S0\nM486 A Shape-Box (Instance 1)\nM486 S-1\nM486 S1\n\
             M486 A Shape-Box (Instance 2)\nM486 S-1\nG28\nM486 S1\nG1 X1 E1\nM486 S-1\n\
             M486 S0\nG1 X2 E2\nM486 S-1 ; done\nM486 P1\n",
        );
        let marks = marks.unwrap();
        assert_eq!(
            marks.names(),
            ["Shape-Box (Instance 1)", "Shape-Box (Instance 2)"]
        );
        assert_eq!(
            runs(&marks, commands.len()),
            [
                (1..2, "Shape-Box (Instance 2)".into()),
                (2..3, "Shape-Box (Instance 1)".into())
            ]
        );
        assert_eq!(commands, ["G28", "G1 X1 E1", "G1 X2 E2"]);
        // Unnamed, and RepRapFirmware's names on the S line.
        let (marks, _) = read("M486 S3\nG1 X1 E1\nM486 S4 A\"left\"\nG1 X2 E2\nM486 S-1\n");
        assert_eq!(marks.unwrap().names(), ["object 3", "left"]);
    }

    #[test]
    fn the_first_scheme_seen_is_the_files() {
        let (marks, commands) =
            read(";MESH:a.stl\nM486 S0\nG1 X1 E1\nM486 S-1\n;MESH:NONMESH\nG1 X2\n");
        let marks = marks.unwrap();
        assert_eq!(marks.names(), ["a.stl"]);
        assert_eq!(runs(&marks, commands.len()), [(0..1, "a.stl".into())]);
        assert_eq!(commands, ["G1 X1 E1", "G1 X2"]);
    }

    #[test]
    fn files_without_labelled_commands_have_no_marks() {
        assert_eq!(read("G28\nG1 X1 E1\n").0, None);
        assert_eq!(
            read("; printing object a\n; stop printing object a\nG28\n").0,
            None
        );
        assert_eq!(read("; stop printing object a\nG28\n").0, None);
    }

    #[test]
    fn names_are_bounded_and_parts_too() {
        let long = "x".repeat(500);
        let (marks, _) = read(&format!("; printing object {long}\u{7}\nG1 X1 E1\n"));
        assert_eq!(marks.unwrap().names()[0].chars().count(), MAX_NAME_CHARS);
        let mut text = String::new();
        for i in 0..=MAX_PARTS {
            text += &format!(";MESH:m{i}\nG1 X1 E{i}\n");
        }
        assert_eq!(read(&text).0, None);
    }
}
