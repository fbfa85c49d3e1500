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
    #[error("{file}:{line}: command is not valid text (UTF-8)")]
    NotText { file: String, line: usize },
    #[error("{file}: no G-code commands in the file (only comments or blank lines)")]
    Empty { file: String },
}

/// A parsed job: the commands to send, in order, exactly as they will reach the printer
/// (after the host adds its line number and checksum).
///
/// The commands are shared, not copied: the protocol core streaming a job holds a clone of
/// the same `Arc`, so a printing job keeps its G-code in memory once.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct GcodeProgram {
    name: String,
    commands: Arc<[String]>,
    source_lines: Vec<usize>,
}

impl GcodeProgram {
    /// Load a file, checking line lengths against the strictest supported firmware.
    pub fn load(path: &Path) -> Result<Self, GcodeError> {
        let strictest = Firmware::ALL
            .into_iter()
            .min_by_key(|f| f.max_line_bytes())
            .unwrap_or(Firmware::Marlin2);
        Self::load_for(path, strictest)
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
        let mut commands = Vec::new();
        let mut source_lines = Vec::new();
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
            if code.len() > max {
                return Err(GcodeError::LineTooLong {
                    file: name.to_string(),
                    line: line_no,
                    len: code.len(),
                    max,
                    firmware,
                });
            }
            commands.push(code.to_string());
            source_lines.push(line_no);
        }
        if commands.is_empty() {
            return Err(GcodeError::Empty {
                file: name.to_string(),
            });
        }
        Ok(GcodeProgram {
            name: name.to_string(),
            commands: commands.into(),
            source_lines,
        })
    }

    /// Build a program from commands already in memory (benchmarks, generated jobs).
    pub fn from_commands(name: &str, commands: Vec<String>) -> Self {
        let source_lines = (1..=commands.len()).collect();
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
    pub fn commands(&self) -> &[String] {
        &self.commands
    }
    /// The commands as a shared handle (no copy), for the protocol core.
    pub fn shared_commands(&self) -> Arc<[String]> {
        Arc::clone(&self.commands)
    }
    /// The 1-based line in the source file of command `index` (0-based).
    pub fn source_line(&self, index: usize) -> Option<usize> {
        self.source_lines.get(index).copied()
    }
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
        assert_eq!(p.commands(), ["G28", "G1 X1 Y2", "M104 S0"]);
        assert_eq!(p.source_line(0), Some(3));
        assert_eq!(p.source_line(1), Some(4));
        assert_eq!(p.source_line(2), Some(6));
        assert_eq!(p.len(), 3);
    }

    #[test]
    fn non_utf8_in_comments_is_fine_but_not_in_commands() {
        assert_eq!(parse(b"G1 X1 ; \xff\xfe\n").unwrap().commands(), ["G1 X1"]);
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
    fn load_reports_the_path() {
        let err = GcodeProgram::load(Path::new("/nonexistent/x.gcode")).unwrap_err();
        assert!(err.to_string().contains("/nonexistent/x.gcode"), "{err}");
    }
}
