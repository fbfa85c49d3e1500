//! G-code files as the host sends them: comments and blank lines stripped, one command per
//! entry, each remembered with its source line so errors can point at `file:line`.
//!
//! Over-long commands are refused here, before anything is sent: the printer would reject
//! them (MAX_CMD_SIZE) and a job that fails half-way is worse than one that never starts.

use super::firmware::Firmware;
use std::fs::File;
use std::io::{BufRead, BufReader, Read};
use std::path::{Path, PathBuf};
use std::sync::Arc;

pub(crate) use super::reader::serial::FRAMING_BYTES;

/// The largest G-code file crispen takes: checked when a pre-sliced file is prepared and
/// again when a job is loaded. A day-long print sliced finely is well under 200 MiB; the
/// shared farm's database keeps files of up to 1 GiB.
pub const MAX_GCODE_BYTES: u64 = 512 << 20;

/// The longest line, comment included, read before a file is refused. Slicers write
/// thumbnails and settings in comment lines of a few KiB at most.
pub const MAX_RAW_LINE_BYTES: u64 = 1 << 20;

/// The commands that wait for a temperature (nozzle, bed, every heater): the printer
/// answers them only once it is reached. The one list for every layer: the protocol gives
/// them the heat timeout instead of the silence probe, and the daemon holds a print's
/// heating permit until the last of them in the program's opening is answered.
pub const HEAT_WAITS: [&str; 3] = ["M109", "M190", "M116"];

/// Whether a command (its first word, in any case) is one of [`HEAT_WAITS`].
pub fn is_heat_wait(command: &str) -> bool {
    let code = command.split_whitespace().next().unwrap_or("");
    HEAT_WAITS.iter().any(|c| c.eq_ignore_ascii_case(code))
}

pub use super::reader::FILE_PAUSES;

#[derive(Debug, thiserror::Error)]
pub enum GcodeError {
    #[error("cannot read G-code file {path}: {source}")]
    Io {
        path: PathBuf,
        #[source]
        source: std::io::Error,
    },
    #[error(
        "{file}:{line}: command is {len} bytes, but {firmware} accepts at most {max} bytes per \
         command once the line number and checksum are added; shorten it (e.g. an M117 message)"
    )]
    LineTooLong {
        file: String,
        line: usize,
        len: usize,
        max: usize,
        firmware: Firmware,
    },
    #[error(
        "{file}:{line}: command contains `*`, which the printer would read as a checksum; \
         remove it"
    )]
    Asterisk { file: String, line: usize },
    #[error(
        "{file}:{line}: command contains `:`, where {firmware} ends a line, so it would never \
         pass its checksum; remove the colon (e.g. `M117 ETA 01:23` -> `M117 ETA 01h23`)"
    )]
    Colon {
        file: String,
        line: usize,
        firmware: Firmware,
    },
    #[error(
        "{file}:{line}: command contains `\\`, which Marlin drops (taking the character after \
         it as it is), so the printer would refuse the line again and again; remove it"
    )]
    Backslash { file: String, line: usize },
    #[error("{file}:{line}: command `{command}` {reason}; {firmware} cannot be sent it")]
    Serial {
        file: String,
        line: usize,
        command: String,
        reason: String,
        firmware: Firmware,
    },
    #[error("{file}:{line}: command is not valid text (UTF-8)")]
    NotText { file: String, line: usize },
    #[error("{file}: no G-code commands in the file (only comments or blank lines)")]
    Empty { file: String },
    #[error(
        "{file}: too large: crispen streams G-code files of at most {} MiB (split the job)",
        MAX_GCODE_BYTES >> 20
    )]
    TooLarge { file: String },
    #[error(
        "{file}:{line}: line longer than {} KiB; not G-code a printer can take",
        MAX_RAW_LINE_BYTES >> 10
    )]
    HugeLine { file: String, line: usize },
}

impl GcodeError {
    /// A reading error of [`scan`] (which knows the file by name only) with the file's path.
    fn at(self, path: &Path) -> Self {
        match self {
            GcodeError::Io { source, .. } => GcodeError::Io {
                path: path.to_path_buf(),
                source,
            },
            other => other,
        }
    }
}

/// A job's commands stored back to back in one shared buffer, with the length of each.
///
/// A sliced job has tens of thousands of short commands (a file of tiny moves, millions);
/// one `String` each costs ~80 bytes with its heap block, and even a 4-byte end offset per
/// command is twice the text of a `G1 X1` job. Packed, a command costs its own bytes plus
/// one for its length ([`SmallSeq`]), and a clone is two reference counts.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct GcodeCommands {
    text: Arc<String>,
    lens: Arc<SmallSeq>,
    /// The commands of `lens` this handle covers: `first..first + count` (a part of a job
    /// shares its buffers, see [`GcodeCommands::part`]).
    first: usize,
    count: usize,
    /// The text offset of command `first`.
    first_byte: usize,
}

impl GcodeCommands {
    /// Pack commands; `None` if they hold more than [`MAX_GCODE_BYTES`] of text.
    pub(crate) fn pack<S: AsRef<str>>(commands: impl IntoIterator<Item = S>) -> Option<Self> {
        let mut text = String::new();
        let mut lens = SmallSeq::default();
        for command in commands {
            text.push_str(command.as_ref());
            lens.push(command.as_ref().len() as u64);
            if text.len() as u64 > MAX_GCODE_BYTES {
                return None;
            }
        }
        Some(GcodeCommands::from_parts(text, lens))
    }

    fn from_parts(mut text: String, mut lens: SmallSeq) -> Self {
        text.shrink_to_fit();
        lens.shrink_to_fit();
        // `Arc<String>`, not `Arc<str>`: converting would copy the whole text once more.
        let count = lens.len();
        GcodeCommands {
            text: Arc::new(text),
            lens: Arc::new(lens),
            first: 0,
            count,
            first_byte: 0,
        }
    }

    /// Commands `range` of these, sharing the same buffers (no copy): the parts of a job
    /// between the pauses its file asks for are streamed one after the other.
    pub(crate) fn part(&self, range: std::ops::Range<usize>) -> GcodeCommands {
        let end = range.end.min(self.count);
        let start = range.start.min(end);
        let first = self.first + start;
        let first_byte = if first < self.lens.len() {
            self.lens.sum_before(first) as usize
        } else {
            self.text.len()
        };
        GcodeCommands {
            text: Arc::clone(&self.text),
            lens: Arc::clone(&self.lens),
            first,
            count: end - start,
            first_byte,
        }
    }

    pub(crate) fn len(&self) -> usize {
        self.count
    }
    pub(crate) fn is_empty(&self) -> bool {
        self.count == 0
    }
    /// Command `index` (0-based), or `None` past the end.
    pub(crate) fn get(&self, index: usize) -> Option<&str> {
        if index >= self.len() {
            return None;
        }
        let at = self.first + index;
        let start = self.lens.sum_before(at) as usize;
        let end = start + self.lens.get(at) as usize;
        Some(&self.text[start..end])
    }
    pub(crate) fn iter(&self) -> impl ExactSizeIterator<Item = &str> + '_ {
        let mut start = self.first_byte;
        (self.first..self.first + self.count).map(move |i| {
            let end = start + self.lens.get(i) as usize;
            let command = &self.text[start..end];
            start = end;
            command
        })
    }
    /// Owned copies of all commands (tests and small jobs only: this undoes the packing).
    pub(crate) fn to_vec(&self) -> Vec<String> {
        self.iter().map(str::to_owned).collect()
    }
}

impl std::ops::Index<usize> for GcodeCommands {
    type Output = str;
    fn index(&self, index: usize) -> &str {
        match self.get(index) {
            Some(command) => command,
            None => panic!("command {index} out of range (job has {})", self.len()),
        }
    }
}

impl Default for GcodeCommands {
    fn default() -> Self {
        GcodeCommands::from_parts(String::new(), SmallSeq::default())
    }
}

/// For generated jobs held in memory (tests, benchmarks); a real file goes through
/// [`GcodeProgram::read`], which reports an oversized job as an error instead.
impl From<Vec<String>> for GcodeCommands {
    fn from(commands: Vec<String>) -> Self {
        GcodeCommands::pack(commands).expect("in-memory job within MAX_GCODE_BYTES")
    }
}

/// Non-negative integers that are nearly always small (command lengths, the gap between
/// two commands' source lines): one byte each, a side list for the rare larger value, and
/// the running total every [`SmallSeq::BLOCK`] entries, so a prefix sum costs at most
/// `BLOCK` additions.
#[derive(Debug, Clone, Default, PartialEq, Eq)]
struct SmallSeq {
    bytes: Vec<u8>,
    /// `(index, value)` of each entry whose byte is `u8::MAX`, in index order.
    wide: Vec<(usize, u64)>,
    /// `totals[k]`: the sum of the entries before `k * BLOCK`.
    totals: Vec<u64>,
    sum: u64,
}

impl SmallSeq {
    const BLOCK: usize = 64;

    fn with_capacity(entries: usize) -> Self {
        SmallSeq {
            bytes: Vec::with_capacity(entries),
            totals: Vec::with_capacity(entries / Self::BLOCK + 1),
            ..SmallSeq::default()
        }
    }

    fn push(&mut self, value: u64) {
        if self.bytes.len() % Self::BLOCK == 0 {
            self.totals.push(self.sum);
        }
        match u8::try_from(value) {
            Ok(byte) if byte < u8::MAX => self.bytes.push(byte),
            _ => {
                self.wide.push((self.bytes.len(), value));
                self.bytes.push(u8::MAX);
            }
        }
        self.sum += value;
    }
    fn len(&self) -> usize {
        self.bytes.len()
    }
    /// Entry `index`; the caller keeps `index < len()`.
    fn get(&self, index: usize) -> u64 {
        match self.bytes[index] {
            u8::MAX => {
                let at = self.wide.partition_point(|&(i, _)| i < index);
                self.wide[at].1
            }
            byte => u64::from(byte),
        }
    }
    /// The sum of the entries before `index`; the caller keeps `index < len()`.
    fn sum_before(&self, index: usize) -> u64 {
        let block = index / Self::BLOCK;
        let within: u64 = (block * Self::BLOCK..index).map(|i| self.get(i)).sum();
        self.totals[block] + within
    }
    fn shrink_to_fit(&mut self) {
        self.bytes.shrink_to_fit();
        self.wide.shrink_to_fit();
        self.totals.shrink_to_fit();
    }
}

/// A parsed job: the commands to send, in order, exactly as they will reach the printer
/// (after the host adds its line number and checksum).
///
/// The commands are packed and shared, not copied: the protocol core streaming a job holds a
/// clone of the same buffers, so a printing job keeps its G-code in memory once.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct GcodeProgram {
    name: String,
    commands: GcodeCommands,
    /// The gap between each command's source line and the previous one's.
    source_lines: Arc<SmallSeq>,
    /// The firmware it was read for.
    firmware: Firmware,
    /// Which part of a plate each command belongs to, where the file labels its parts
    /// ([`crate::labels`]); label commands are not among the commands.
    marks: Option<Arc<crate::labels::Marks>>,
}

impl GcodeProgram {
    /// Load a file that must suit every supported firmware.
    #[cfg(test)]
    pub(crate) fn load(path: &Path) -> Result<Self, GcodeError> {
        let mut program = None;
        for firmware in Firmware::ALL {
            program = Some(Self::load_for(path, firmware)?);
        }
        Ok(program.expect("at least one firmware"))
    }

    /// Load a file for one firmware.
    pub fn load_for(path: &Path, firmware: Firmware) -> Result<Self, GcodeError> {
        let (file, size) = open_job(path)?;
        let size = usize::try_from(size).unwrap_or(0);
        // The buffers are reserved for the most the file can hold (every command at least
        // two bytes with its line end) rather than grown by doubling: growing copies a
        // buffer while the old one is still held, which for a large job would double the
        // daemon's peak memory; reserved pages never written cost no memory.
        let mut program = Loading::with_capacity(size);
        let marks = scan(file, &path.display().to_string(), firmware, |code, line| {
            program.push(code, line)
        })
        .map_err(|e| e.at(path))?;
        program.finish(&path.display().to_string(), firmware, marks)
    }

    /// Parse G-code from any reader; `name` is used in error messages.
    pub fn read(reader: impl Read, name: &str, firmware: Firmware) -> Result<Self, GcodeError> {
        let mut program = Loading::with_capacity(0);
        let marks = scan(reader, name, firmware, |code, line| {
            program.push(code, line)
        })?;
        program.finish(name, firmware, marks)
    }

    /// Build a program from commands already in memory (benchmarks, generated jobs).
    pub fn from_commands(name: &str, commands: Vec<String>) -> Self {
        let mut source_lines = SmallSeq::default();
        for _ in &commands {
            source_lines.push(1);
        }
        GcodeProgram {
            name: name.to_string(),
            commands: commands.into(),
            source_lines: Arc::new(source_lines),
            firmware: Firmware::Marlin2,
            marks: None,
        }
    }

    pub(crate) fn name(&self) -> &str {
        &self.name
    }
    /// The firmware it was read for.
    pub fn firmware(&self) -> Firmware {
        self.firmware
    }
    /// Which part of a plate each command belongs to, if the file labels its parts.
    pub fn marks(&self) -> Option<&Arc<crate::labels::Marks>> {
        self.marks.as_ref()
    }
    pub fn len(&self) -> usize {
        self.commands.len()
    }
    pub fn is_empty(&self) -> bool {
        self.commands.is_empty()
    }
    pub fn commands(&self) -> &GcodeCommands {
        &self.commands
    }
    /// Command `index` (0-based), or `None` past the end.
    #[cfg(test)]
    pub(crate) fn command(&self, index: usize) -> Option<&str> {
        self.commands.get(index)
    }
    pub fn iter(&self) -> impl ExactSizeIterator<Item = &str> + '_ {
        self.commands.iter()
    }
    /// Owned copies of all commands (tests and small jobs only: this undoes the packing).
    pub fn to_vec(&self) -> Vec<String> {
        self.commands.to_vec()
    }
    /// The commands as a shared handle (no copy), for the protocol core.
    pub(crate) fn shared_commands(&self) -> GcodeCommands {
        self.commands.clone()
    }
    /// The 1-based line in the source file of command `index` (0-based).
    pub fn source_line(&self, index: usize) -> Option<usize> {
        (index < self.source_lines.len())
            .then(|| (self.source_lines.sum_before(index) + self.source_lines.get(index)) as usize)
    }
}

/// Whether a line as read may be a plate's label (a comment, or a label command: see
/// [`crate::labels`]): a cheap look at its first bytes.
fn may_label(raw: &[u8]) -> bool {
    let start = raw
        .iter()
        .position(|b| !b.is_ascii_whitespace())
        .unwrap_or(raw.len());
    let head = &raw[start..];
    let starts =
        |word: &[u8]| head.len() >= word.len() && head[..word.len()].eq_ignore_ascii_case(word);
    head.first() == Some(&b';') || starts(b"M486") || starts(b"EXCLUDE_OBJECT")
}

/// Reads G-code as the host loads it for `firmware`, line by line, without holding it:
/// each command (comment cut, trimmed) goes to `each` with its line number, and the plate's
/// labels are read on the way ([`crate::labels`]; a label command is not a command
/// sent, so every reader counts commands alike). One reading,
/// so the program the host streams and every figure taken from the file agree; memory
/// stays near nothing, and no line, however long, is held whole beyond
/// [`MAX_RAW_LINE_BYTES`].
pub(crate) fn scan(
    reader: impl Read,
    name: &str,
    firmware: Firmware,
    mut each: impl FnMut(&str, usize),
) -> Result<Option<crate::labels::Marks>, GcodeError> {
    let max = firmware.max_line_bytes().saturating_sub(FRAMING_BYTES);
    let io = |source| GcodeError::Io {
        path: PathBuf::from(name),
        source,
    };
    let mut reader = BufReader::new(reader.take(MAX_GCODE_BYTES + 1));
    let mut raw = Vec::new();
    let mut line_no = 0;
    let mut total = 0u64;
    let mut labels = crate::labels::LabelReader::default();
    let mut commands = 0usize;
    loop {
        raw.clear();
        let n = (&mut reader)
            .take(MAX_RAW_LINE_BYTES)
            .read_until(b'\n', &mut raw)
            .map_err(io)?;
        if n == 0 {
            break;
        }
        line_no += 1;
        total += n as u64;
        if total > MAX_GCODE_BYTES {
            return Err(GcodeError::TooLarge {
                file: name.to_string(),
            });
        }
        if n as u64 == MAX_RAW_LINE_BYTES && raw.last() != Some(&b'\n') {
            return Err(GcodeError::HugeLine {
                file: name.to_string(),
                line: line_no,
            });
        }
        if may_label(&raw)
            && labels.line(&String::from_utf8_lossy(&raw), commands)
                == crate::labels::LineLabel::Command
        {
            continue;
        }
        // Comments may hold anything (slicers write non-UTF-8 names); cut them first.
        let code = match raw.iter().position(|&b| b == b';') {
            Some(i) => &raw[..i],
            None => &raw[..],
        };
        let code = std::str::from_utf8(code).map_err(|_| GcodeError::NotText {
            file: name.to_string(),
            line: line_no,
        })?;
        let code = code.trim();
        if code.is_empty() {
            continue;
        }
        if code.contains('*') {
            return Err(GcodeError::Asterisk {
                file: name.to_string(),
                line: line_no,
            });
        }
        if firmware.colon_ends_line() && code.contains(':') {
            return Err(GcodeError::Colon {
                file: name.to_string(),
                line: line_no,
                firmware,
            });
        }
        if code.contains('\\') {
            // Stock Marlin has no quoted strings (GCODE_QUOTED_STRINGS), so a backslash is
            // dropped wherever it stands (queue.cpp:337-343).
            return Err(GcodeError::Backslash {
                file: name.to_string(),
                line: line_no,
            });
        }
        if code.len() > max {
            return Err(GcodeError::LineTooLong {
                file: name.to_string(),
                line: line_no,
                len: code.len(),
                max,
                firmware,
            });
        }
        if let Err(why) = super::reader::serial::check(firmware, code) {
            return Err(GcodeError::Serial {
                file: name.to_string(),
                line: line_no,
                command: code
                    .chars()
                    .take(60)
                    .collect::<String>()
                    .escape_debug()
                    .to_string(),
                reason: why,
                firmware,
            });
        }
        each(code, line_no);
        commands += 1;
    }
    Ok(labels.finish(commands))
}

/// Opens a job's file for [`scan`], refusing one too large before reading a byte (`scan`
/// counts too, for files that grow meanwhile); with its size.
pub(crate) fn open_job(path: &Path) -> Result<(File, u64), GcodeError> {
    let io = |source| GcodeError::Io {
        path: path.to_path_buf(),
        source,
    };
    let file = File::open(path).map_err(io)?;
    let size = file.metadata().map_err(io)?.len();
    if size > MAX_GCODE_BYTES {
        return Err(GcodeError::TooLarge {
            file: path.display().to_string(),
        });
    }
    Ok((file, size))
}

/// Net filament the first `limit` commands of the job file at `path` push (all of them
/// with `None`), mm, followed as `firmware` follows them
/// ([`Pushed`](super::motion::Pushed)) and read as they stream by; with the number of
/// commands read. What a pre-sliced job needs, and what a print took up to its last
/// acknowledged line.
pub fn pushed_mm(
    path: &Path,
    firmware: Firmware,
    limit: Option<usize>,
) -> Result<(f64, usize), GcodeError> {
    let (file, _) = open_job(path)?;
    let mut pushed = super::motion::Pushed::new(firmware);
    let mut commands = 0usize;
    scan(file, &path.display().to_string(), firmware, |code, _| {
        if limit.is_none_or(|l| commands < l) {
            pushed.follow(code);
        }
        commands += 1;
    })?;
    Ok((pushed.mm(), commands))
}

/// A program as [`scan`] hands it over.
struct Loading {
    text: String,
    lens: SmallSeq,
    source_lines: SmallSeq,
    last_command_line: usize,
}

impl Loading {
    fn with_capacity(bytes: usize) -> Self {
        let bytes = bytes.min(usize::try_from(MAX_GCODE_BYTES).unwrap_or(usize::MAX));
        Loading {
            text: String::with_capacity(bytes),
            lens: SmallSeq::with_capacity(bytes / 2),
            source_lines: SmallSeq::with_capacity(bytes / 2),
            last_command_line: 0,
        }
    }

    fn push(&mut self, code: &str, line: usize) {
        self.text.push_str(code);
        self.lens.push(code.len() as u64);
        self.source_lines
            .push((line - self.last_command_line) as u64);
        self.last_command_line = line;
    }

    fn finish(
        self,
        name: &str,
        firmware: Firmware,
        marks: Option<crate::labels::Marks>,
    ) -> Result<GcodeProgram, GcodeError> {
        let Loading {
            text,
            lens,
            mut source_lines,
            ..
        } = self;
        if lens.len() == 0 {
            return Err(GcodeError::Empty {
                file: name.to_string(),
            });
        }
        source_lines.shrink_to_fit();
        Ok(GcodeProgram {
            name: name.to_string(),
            commands: GcodeCommands::from_parts(text, lens),
            source_lines: Arc::new(source_lines),
            firmware,
            marks: marks.map(Arc::new),
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The one list of heat waits: by the command's first word, in any case, never by a
    /// prefix of another code.
    #[test]
    fn heat_waits_are_known_by_their_code() {
        for c in ["M109 S210", "m190 S60", "M116", "M109 R200 T0"] {
            assert!(is_heat_wait(c), "{c}");
        }
        for c in ["M104 S210", "M140 S60", "M1090", "G1 X1 ; M109", ""] {
            assert!(!is_heat_wait(c), "{c}");
        }
    }

    fn parse(text: &[u8]) -> Result<GcodeProgram, GcodeError> {
        GcodeProgram::read(text, "job.gcode", Firmware::Marlin2)
    }

    #[test]
    fn strips_comments_and_blank_lines_and_keeps_source_lines() {
        let p = parse(b"; header\n\nG28 ; home\r\n  G1 X1 Y2  \n;only comment\nM104 S0").unwrap();
        assert_eq!(p.to_vec(), ["G28", "G1 X1 Y2", "M104 S0"]);
        assert_eq!(p.command(1), Some("G1 X1 Y2"));
        assert_eq!(p.command(3), None);
        assert_eq!(p.source_line(0), Some(3));
        assert_eq!(p.source_line(1), Some(4));
        assert_eq!(p.source_line(2), Some(6));
        assert_eq!(p.len(), 3);
    }

    #[test]
    fn non_utf8_in_comments_is_fine_but_not_in_commands() {
        assert_eq!(parse(b"G1 X1 ; \xff\xfe\n").unwrap().to_vec(), ["G1 X1"]);
        let err = parse(b"G28\nG1 X\xff\n").unwrap_err();
        assert!(matches!(err, GcodeError::NotText { line: 2, .. }), "{err}");
    }

    #[test]
    fn over_long_lines_are_refused_with_file_and_line() {
        let long = format!("G28\nM117 {}\n", "x".repeat(90));
        let err = parse(long.as_bytes()).unwrap_err();
        let msg = err.to_string();
        assert!(matches!(err, GcodeError::LineTooLong { line: 2, .. }));
        assert!(msg.starts_with("job.gcode:2:"), "{msg}");
        // The longest accepted command still fits the printer with framing added.
        let ok = format!("M117 {}", "x".repeat(96 - FRAMING_BYTES - 5));
        let p = parse(ok.as_bytes()).unwrap();
        assert!(p.commands()[0].len() + FRAMING_BYTES <= Firmware::Marlin2.max_line_bytes());
    }

    #[test]
    fn asterisks_and_empty_files_are_refused() {
        assert!(matches!(
            parse(b"M117 a*b\n").unwrap_err(),
            GcodeError::Asterisk { line: 1, .. }
        ));
        assert!(matches!(
            parse(b"; nothing\n\n").unwrap_err(),
            GcodeError::Empty { .. }
        ));
    }

    #[test]
    fn packed_commands_keep_boundaries_and_share_on_clone() {
        let commands = GcodeCommands::pack(["G28", "", "G1 X1"]).unwrap();
        assert_eq!(commands.len(), 3);
        assert_eq!(commands.iter().collect::<Vec<_>>(), ["G28", "", "G1 X1"]);
        assert_eq!(&commands[2], "G1 X1");
        assert_eq!(commands.get(3), None);
        let copy = commands.clone();
        assert!(Arc::ptr_eq(&copy.text, &commands.text));
        assert!(GcodeCommands::default().is_empty());
    }

    #[test]
    fn colons_for_ultimaker2_and_bare_backslashes_are_refused_naming_the_line() {
        let text = b"G28\nM117 ETA 01:23\n";
        let err = GcodeProgram::read(&text[..], "job.gcode", Firmware::Ultimaker2).unwrap_err();
        assert!(matches!(err, GcodeError::Colon { line: 2, .. }), "{err}");
        assert!(err.to_string().starts_with("job.gcode:2:"), "{err}");
        // Marlin reads colons fine; a colon in a comment is no command at all.
        assert!(GcodeProgram::read(&text[..], "job.gcode", Firmware::Marlin2).is_ok());
        assert!(GcodeProgram::read(&b"G28 ; at 01:23\n"[..], "j", Firmware::Ultimaker2).is_ok());
        for fw in Firmware::ALL {
            let err = GcodeProgram::read(&b"M117 a\\b\n"[..], "j.gcode", fw).unwrap_err();
            assert!(
                matches!(err, GcodeError::Backslash { line: 1, .. }),
                "{fw}: {err}"
            );
        }
        // Stock Marlin 2.1.2.1 has no quoted strings: the backslash is dropped there too.
        assert!(matches!(
            parse(b"M118 \"a\\\"b\"\n").unwrap_err(),
            GcodeError::Backslash { line: 1, .. }
        ));
    }

    /// Issue 42: a carriage return inside a line (where both firmwares end a line, the
    /// middle piece then running unnumbered) and a message that renumbers Marlin 2 are
    /// refused when the file is loaded, naming the line and the firmware's rule.
    #[test]
    fn lines_the_serial_input_would_split_or_renumber_are_refused_naming_the_line() {
        for fw in Firmware::ALL {
            let err = GcodeProgram::read(&b"G28\nM117 a\rM104 S300\rM117 b\n"[..], "job.gcode", fw)
                .unwrap_err();
            let msg = err.to_string();
            assert!(
                matches!(err, GcodeError::Serial { line: 2, .. }),
                "{fw}: {msg}"
            );
            assert!(msg.starts_with("job.gcode:2:"), "{msg}");
            assert!(
                msg.contains("carriage return") && msg.contains(".cpp:"),
                "{msg}"
            );
            assert!(!msg.contains('\r'), "the line end is written out: {msg:?}");
            let err =
                GcodeProgram::read(&b"G28\nM117 M110 N999\n"[..], "job.gcode", fw).unwrap_err();
            assert!(
                matches!(err, GcodeError::Serial { line: 2, .. }),
                "{fw}: {err}"
            );
        }
        // A file with CRLF line ends is fine: the CR ends the line where the host does.
        assert!(parse(b"G28\r\nG1 X1\r\n").is_ok());
    }

    #[test]
    fn small_sequences_keep_large_values_and_sums_across_blocks() {
        let values: Vec<u64> = (0..1000u64)
            .map(|i| match i % 97 {
                0 => 255 + i,
                1 => 254,
                _ => i % 7,
            })
            .collect();
        let mut seq = SmallSeq::default();
        for &v in &values {
            seq.push(v);
        }
        let mut sum = 0;
        for (i, &v) in values.iter().enumerate() {
            assert_eq!(seq.get(i), v, "entry {i}");
            assert_eq!(seq.sum_before(i), sum, "sum before {i}");
            sum += v;
        }
    }

    #[test]
    fn source_lines_survive_long_runs_of_comments() {
        let mut text = String::from("G28\n");
        text.push_str(&"; comment\n".repeat(300));
        text.push_str("G1 X1\n\n\nG1 X2\n");
        let p = parse(text.as_bytes()).unwrap();
        assert_eq!(p.to_vec(), ["G28", "G1 X1", "G1 X2"]);
        assert_eq!(p.source_line(0), Some(1));
        assert_eq!(p.source_line(1), Some(302));
        assert_eq!(p.source_line(2), Some(305));
        assert_eq!(p.source_line(3), None);
        // Indexing and iteration agree over many blocks.
        let many: Vec<String> = (0..500).map(|i| format!("G1 X{i}")).collect();
        let commands = GcodeCommands::from(many.clone());
        assert_eq!(commands.to_vec(), many);
        assert!((0..500).all(|i| commands[i] == many[i]));
    }

    #[test]
    fn huge_lines_and_files_are_refused_without_reading_them_whole() {
        let mut text = b"G28\n; ".to_vec();
        text.extend(std::iter::repeat_n(b'x', MAX_RAW_LINE_BYTES as usize));
        let err = parse(&text).unwrap_err();
        assert!(matches!(err, GcodeError::HugeLine { line: 2, .. }), "{err}");
        // A file past the limit is refused by its size, before it is read.
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("big.gcode");
        let file = File::create(&path).unwrap();
        file.set_len(MAX_GCODE_BYTES + 1).unwrap();
        let err = GcodeProgram::load_for(&path, Firmware::Marlin2).unwrap_err();
        assert!(matches!(err, GcodeError::TooLarge { .. }), "{err}");
        assert!(err.to_string().contains("512 MiB"), "{err}");
    }

    #[test]
    fn load_reports_the_path() {
        let err = GcodeProgram::load(Path::new("/nonexistent/x.gcode")).unwrap_err();
        assert!(err.to_string().contains("/nonexistent/x.gcode"), "{err}");
    }
}
