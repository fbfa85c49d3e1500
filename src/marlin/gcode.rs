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

/// Bytes the host adds around a command: `N<number> ` before and `*<checksum>` after.
/// Numbers up to 9 digits cover any job; the checksum is at most 3 digits.
pub const FRAMING_BYTES: usize = 1 + 9 + 1 + 1 + 3;

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
        "{file}:{line}: command contains `\\` outside quotes, which Marlin drops, so the \
         printer would run something else than the file says; remove it"
    )]
    Backslash { file: String, line: usize },
    #[error("{file}:{line}: command is not valid text (UTF-8)")]
    NotText { file: String, line: usize },
    #[error("{file}: no G-code commands in the file (only comments or blank lines)")]
    Empty { file: String },
    #[error("{file}: too large: more than 4 GiB of G-code commands (split the job)")]
    TooLarge { file: String },
}

/// A job's commands stored back to back in one shared buffer, with the end offset of each.
///
/// A sliced job has tens of thousands of short commands; one `String` each costs ~80 bytes
/// with its heap block, which for a farm of printers adds up to hundreds of MB. Packed, a
/// command costs its own bytes plus 4 for its offset, and a clone is two reference counts.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct GcodeCommands {
    text: Arc<str>,
    ends: Arc<[u32]>,
}

impl GcodeCommands {
    /// Pack commands; `None` if they do not fit 32-bit offsets (more than 4 GiB).
    pub fn pack<S: AsRef<str>>(commands: impl IntoIterator<Item = S>) -> Option<Self> {
        let mut text = String::new();
        let mut ends = Vec::new();
        for command in commands {
            text.push_str(command.as_ref());
            ends.push(u32::try_from(text.len()).ok()?);
        }
        Some(GcodeCommands {
            text: text.into(),
            ends: ends.into(),
        })
    }

    pub fn len(&self) -> usize {
        self.ends.len()
    }
    pub fn is_empty(&self) -> bool {
        self.ends.is_empty()
    }
    /// Command `index` (0-based), or `None` past the end.
    pub fn get(&self, index: usize) -> Option<&str> {
        let end = *self.ends.get(index)? as usize;
        let start = match index {
            0 => 0,
            _ => self.ends[index - 1] as usize,
        };
        Some(&self.text[start..end])
    }
    pub fn iter(&self) -> impl ExactSizeIterator<Item = &str> + '_ {
        (0..self.len()).map(|i| &self[i])
    }
    /// Owned copies of all commands (tests and small jobs only: this undoes the packing).
    pub fn to_vec(&self) -> Vec<String> {
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
        GcodeCommands {
            text: Arc::from(""),
            ends: Arc::from([]),
        }
    }
}

/// For generated jobs held in memory (tests, benchmarks); a real file goes through
/// [`GcodeProgram::read`], which reports an oversized job as an error instead.
impl From<Vec<String>> for GcodeCommands {
    fn from(commands: Vec<String>) -> Self {
        GcodeCommands::pack(commands).expect("in-memory job under 4 GiB")
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
    source_lines: Arc<[u32]>,
}

impl GcodeProgram {
    /// Load a file that must suit every supported firmware.
    pub fn load(path: &Path) -> Result<Self, GcodeError> {
        let mut program = None;
        for firmware in Firmware::ALL {
            program = Some(Self::load_for(path, firmware)?);
        }
        Ok(program.expect("at least one firmware"))
    }

    /// Load a file for one firmware.
    pub fn load_for(path: &Path, firmware: Firmware) -> Result<Self, GcodeError> {
        let file = File::open(path).map_err(|source| GcodeError::Io {
            path: path.to_path_buf(),
            source,
        })?;
        Self::read(file, &path.display().to_string(), firmware).map_err(|e| match e {
            GcodeError::Io { source, .. } => GcodeError::Io {
                path: path.to_path_buf(),
                source,
            },
            other => other,
        })
    }

    /// Parse G-code from any reader; `name` is used in error messages.
    pub fn read(reader: impl Read, name: &str, firmware: Firmware) -> Result<Self, GcodeError> {
        let max = firmware.max_line_bytes().saturating_sub(FRAMING_BYTES);
        let too_large = || GcodeError::TooLarge {
            file: name.to_string(),
        };
        let mut text = String::new();
        let mut ends: Vec<u32> = Vec::new();
        let mut source_lines: Vec<u32> = Vec::new();
        let mut reader = BufReader::new(reader);
        let mut raw = Vec::new();
        let mut line_no = 0;
        loop {
            raw.clear();
            let n = reader
                .read_until(b'\n', &mut raw)
                .map_err(|source| GcodeError::Io {
                    path: PathBuf::from(name),
                    source,
                })?;
            if n == 0 {
                break;
            }
            line_no += 1;
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
            if has_unquoted_backslash(code) {
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
            text.push_str(code);
            ends.push(u32::try_from(text.len()).map_err(|_| too_large())?);
            source_lines.push(u32::try_from(line_no).map_err(|_| too_large())?);
        }
        if ends.is_empty() {
            return Err(GcodeError::Empty {
                file: name.to_string(),
            });
        }
        Ok(GcodeProgram {
            name: name.to_string(),
            commands: GcodeCommands {
                text: text.into(),
                ends: ends.into(),
            },
            source_lines: source_lines.into(),
        })
    }

    /// Build a program from commands already in memory (benchmarks, generated jobs).
    pub fn from_commands(name: &str, commands: Vec<String>) -> Self {
        let source_lines = (1..=commands.len() as u32).collect();
        GcodeProgram {
            name: name.to_string(),
            commands: commands.into(),
            source_lines,
        }
    }

    pub fn name(&self) -> &str {
        &self.name
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
    pub fn command(&self, index: usize) -> Option<&str> {
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
    pub fn shared_commands(&self) -> GcodeCommands {
        self.commands.clone()
    }
    /// The 1-based line in the source file of command `index` (0-based).
    pub fn source_line(&self, index: usize) -> Option<usize> {
        self.source_lines.get(index).map(|&line| line as usize)
    }
}

/// A `\\` outside a `"..."` string: Marlin's parser drops it.
fn has_unquoted_backslash(code: &str) -> bool {
    let mut quoted = false;
    let mut bytes = code.bytes();
    while let Some(b) = bytes.next() {
        match b {
            b'"' => quoted = !quoted,
            b'\\' if quoted => {
                bytes.next(); // an escape inside quotes
            }
            b'\\' => return true,
            _ => {}
        }
    }
    false
}

#[cfg(test)]
mod tests {
    use super::*;

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
        assert!(
            parse(b"M118 \"a\\\"b\"\n").is_ok(),
            "escapes inside quotes are kept"
        );
    }

    #[test]
    fn load_reports_the_path() {
        let err = GcodeProgram::load(Path::new("/nonexistent/x.gcode")).unwrap_err();
        assert!(err.to_string().contains("/nonexistent/x.gcode"), "{err}");
    }
}
