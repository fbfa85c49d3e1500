//! The config's first stage: the file's text read (a page, in UTF-8) and parsed into the
//! `Raw*` structs that mirror the file, unknown keys rejected and every parse error located
//! by line and table. Apart from the checked types, which the daemon uses, and from the
//! checks, which turn the one into the other section by section.

use super::checked::OnShutdown;
use super::error::ConfigError;
use super::notify;
use crate::mesh::place::UpAxis;
use crate::slice::SlicerKind;
use serde::Deserialize;
use std::io::Read;
use std::path::{Path, PathBuf};

#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
pub(super) struct RawConfig {
    pub(super) spool: RawSpool,
    #[serde(default)]
    pub(super) control: Option<RawControl>,
    #[serde(default)]
    pub(super) farm: Option<RawFarm>,
    #[serde(default, rename = "machine")]
    pub(super) machines: Vec<crate::machine::MachineSpec>,
    #[serde(default, rename = "printer")]
    pub(super) printers: Vec<RawPrinter>,
    #[serde(default, rename = "folder")]
    pub(super) folders: Vec<RawFolder>,
    #[serde(default)]
    pub(super) http: Option<RawHttp>,
    #[serde(default)]
    pub(super) store: Option<RawStore>,
    #[serde(default)]
    pub(super) history: Option<RawHistory>,
    #[serde(default, rename = "notify")]
    pub(super) notify: Vec<notify::RawNotify>,
    #[serde(default)]
    pub(super) camera: Option<super::camera::RawCamera>,
    #[serde(default)]
    pub(super) spoolman: Option<super::spoolman::RawSpoolman>,
    #[serde(default)]
    pub(super) enhancement: Option<RawEnhancement>,
    #[serde(default, rename = "maintenance")]
    pub(super) maintenance: Vec<RawMaintenance>,
}

/// `[[maintenance]]`: see `maintenance.rs`.
#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
pub(super) struct RawMaintenance {
    pub(super) name: String,
    pub(super) printers: Option<Vec<String>>,
    pub(super) tags: Option<Vec<String>>,
    pub(super) every_print_hours: Option<f64>,
    pub(super) every_kg: Option<f64>,
    pub(super) every_abrasive_kg: Option<f64>,
    pub(super) every_jobs: Option<f64>,
    pub(super) every_days: Option<f64>,
    pub(super) block: Option<bool>,
}

/// `[enhancement]`: see `enhancement.rs`.
#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
pub(super) struct RawEnhancement {
    pub(super) reference_height_mm: Option<f64>,
    pub(super) observe_timeout_s: Option<f64>,
}

#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
pub(super) struct RawHistory {
    pub(super) live_days: Option<f64>,
    pub(super) live_jobs: Option<i64>,
    pub(super) keep_days: Option<f64>,
}

#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
pub(super) struct RawStore {
    pub(super) postgres: String,
    pub(super) password_file: Option<PathBuf>,
    pub(super) lease_s: Option<f64>,
}

#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
pub(super) struct RawHttp {
    pub(super) listen: String,
    pub(super) api_key_file: PathBuf,
    pub(super) read_only_without_key: Option<bool>,
    pub(super) upload_max_mb: Option<i64>,
    /// The dashboard's address as operators reach it (notifications link to it).
    pub(super) public_url: Option<String>,
    pub(super) announce: Option<bool>,
    pub(super) default_folder: Option<String>,
}

#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
pub(super) struct RawSpool {
    pub(super) dir: PathBuf,
}

#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
pub(super) struct RawControl {
    pub(super) socket: PathBuf,
}

#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
pub(super) struct RawFarm {
    pub(super) max_heating: Option<i64>,
    pub(super) on_shutdown: Option<OnShutdown>,
    pub(super) settle_s: Option<f64>,
    pub(super) rescan_s: Option<f64>,
    pub(super) finish_timeout_s: Option<f64>,
    pub(super) host: Option<String>,
    /// A spool left with less than this after a print sends `spool_low`.
    pub(super) spool_low_g: Option<f64>,
}

#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
pub(super) struct RawPrinter {
    pub(super) name: String,
    pub(super) port: Option<PathBuf>,
    pub(super) firmware: Option<String>,
    /// A machine's name (built-in or `[[machine]]`); the firmware then comes from it.
    pub(super) machine: Option<String>,
    /// The nozzle fitted, for machines that take several (e.g. the Ultimaker 2+).
    pub(super) nozzle_mm: Option<f64>,
    pub(super) baud: Option<i64>,
    pub(super) heat_timeout_s: Option<i64>,
    /// See `pause.rs`.
    pub(super) pause_heaters_off_s: Option<i64>,
    pub(super) simulate: Option<RawSimulate>,
    pub(super) camera: Option<super::camera::RawPrinterCamera>,
    /// The filament it holds until a spool is loaded (see `crate::daemon::filament`).
    pub(super) material: Option<String>,
    pub(super) colour: Option<String>,
    /// `brass` or `hardened`.
    pub(super) nozzle: Option<String>,
    /// Its groups: a job asking for tags goes only to printers carrying all of them.
    pub(super) tags: Option<Vec<String>>,
    /// Its eject sequence (`[printer.eject]`), replacing its machine's.
    pub(super) eject: Option<crate::machine::eject::EjectSpec>,
    /// How its bed is cleared after a good print: "person", "eject", "eject-and-check".
    pub(super) bed_clear: Option<String>,
    /// Its power switch (`[printer.power]`).
    pub(super) power: Option<super::power::RawPower>,
}

#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
pub(super) struct RawSimulate {
    /// A number (how many times faster than real time) or "instant".
    pub(super) speed: Option<toml::Value>,
    /// Replaced by `speed`, its inverse; still read, with a warning.
    pub(super) time_scale: Option<f64>,
    pub(super) seed: Option<u64>,
    pub(super) record: Option<PathBuf>,
}

#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
pub(super) struct RawFolder {
    pub(super) path: PathBuf,
    pub(super) height_mm: f64,
    pub(super) printers: Vec<String>,
    pub(super) strength: Option<toml::Value>,
    pub(super) enhance: Option<bool>,
    /// How the enhancement chooses its bands and strength (`print-aware` or `paper`).
    pub(super) enhancement: Option<crate::enhance::Mode>,
    pub(super) slicer: Option<SlicerKind>,
    pub(super) up: Option<UpAxis>,
    pub(super) profile: Option<PathBuf>,
    pub(super) timeout_s: Option<f64>,
    /// Copies of each model side by side on one bed (a plate).
    pub(super) per_plate: Option<u32>,
    /// Copies of each model, each printed on its own printer at once.
    pub(super) copies: Option<u32>,
    pub(super) settings: Option<toml::Table>,
    /// What its jobs ask of their printer (a sidecar may override each).
    pub(super) material: Option<String>,
    pub(super) colour: Option<String>,
    pub(super) nozzle_mm: Option<f64>,
    pub(super) tags: Option<Vec<String>>,
    pub(super) priority: Option<i32>,
    /// How the beds of its jobs' printers are cleared, replacing the printers' own.
    pub(super) bed_clear: Option<String>,
}

/// The largest config file read.
pub(super) const MAX_CONFIG_BYTES: u64 = 1 << 20;

/// The text of a config file, refused beyond [`MAX_CONFIG_BYTES`] (a config is a page,
/// not a stream) or when it is not UTF-8.
pub(super) fn read_text(path: &Path) -> Result<String, ConfigError> {
    let read = |source| ConfigError::Read {
        file: path.to_path_buf(),
        source,
    };
    let mut bytes = Vec::new();
    std::fs::File::open(path)
        .and_then(|f| f.take(MAX_CONFIG_BYTES + 1).read_to_end(&mut bytes))
        .map_err(read)?;
    if bytes.len() as u64 > MAX_CONFIG_BYTES {
        return Err(read(std::io::Error::new(
            std::io::ErrorKind::InvalidData,
            format!(
                "larger than {} MiB: not a crispen config",
                MAX_CONFIG_BYTES >> 20
            ),
        )));
    }
    String::from_utf8(bytes).map_err(|_| {
        read(std::io::Error::new(
            std::io::ErrorKind::InvalidData,
            "not UTF-8 text",
        ))
    })
}

/// The first stage: the text as the file's shape, and the directory that anchors its
/// relative paths.
pub(super) fn parse_raw(text: &str, path: &Path) -> Result<(RawConfig, PathBuf), ConfigError> {
    let raw: RawConfig = toml::from_str(text).map_err(|e| {
        let offset = e.span().map(|s| s.start).unwrap_or(0);
        let (line, mut section) = locate(text, offset);
        let mut message = e.message().trim().to_string();
        // serde speaks of fields; the file has keys.
        if let Some(key) = message.strip_prefix("missing field ") {
            message = format!("missing key {key}");
        }
        // An unknown table is reported where serde sees it, as a key of the document;
        // its header is on the error's line, so name it as what it is.
        if let Some(header) = unknown_table_header(text, offset) {
            section = "the top level".into();
            message = format!(
                "unknown table `{header}` (known tables: {})",
                KNOWN_TABLES.join(", ")
            );
        }
        ConfigError::Parse {
            file: path.to_path_buf(),
            line,
            section,
            message,
        }
    })?;
    // Every configured path is made absolute here, once: the watcher compares event
    // paths (absolute) with folder paths, and the daemon may change directory later.
    // `crispen.toml` has the parent "", which is the current directory.
    let dir = match path.parent() {
        Some(dir) if !dir.as_os_str().is_empty() => dir,
        _ => Path::new("."),
    };
    let base = std::path::absolute(dir).unwrap_or_else(|_| dir.to_path_buf());
    Ok((raw, base))
}

/// The tables as their headers are written, for an error about an unknown one. A test
/// checks it against the file's shape (`keys::tables`).
pub(super) const KNOWN_TABLES: [&str; 14] = [
    "[spool]",
    "[control]",
    "[farm]",
    "[[machine]]",
    "[[printer]]",
    "[[folder]]",
    "[http]",
    "[store]",
    "[history]",
    "[[notify]]",
    "[camera]",
    "[spoolman]",
    "[enhancement]",
    "[[maintenance]]",
];

/// The table header on the line of `offset`, when that header names no known table.
fn unknown_table_header(text: &str, offset: usize) -> Option<String> {
    let offset = offset.min(text.len());
    let start = text[..offset].rfind('\n').map_or(0, |i| i + 1);
    let line = text[start..].lines().next()?.trim();
    let name = line
        .strip_prefix("[[")
        .and_then(|l| l.split_once("]]"))
        .or_else(|| line.strip_prefix('[').and_then(|l| l.split_once(']')))?
        .0
        .trim();
    let top = name.split('.').next()?.trim().trim_matches('"');
    let known = KNOWN_TABLES
        .iter()
        .any(|h| h.trim_matches(['[', ']']) == top);
    (!known).then(|| {
        line.split_once('#')
            .map_or(line, |(h, _)| h)
            .trim()
            .to_string()
    })
}

/// Line number (1-based) of a byte offset and the table header that encloses it.
fn locate(text: &str, offset: usize) -> (usize, String) {
    let offset = offset.min(text.len());
    let before = &text[..offset];
    let line = before.matches('\n').count() + 1;
    let mut section = "the top level".to_string();
    let mut counts: std::collections::HashMap<String, usize> = Default::default();
    // Up to the end of the offset's own line: an error about a table as a whole (a missing
    // key) points at its header, which names it.
    let line_end = text[offset..].find('\n').map_or(text.len(), |i| offset + i);
    for l in text[..line_end].lines() {
        let t = l.trim();
        if t.starts_with("[[") {
            if let Some(end) = t.find("]]") {
                let name = t[2..end].trim().to_string();
                let n = counts.entry(name.clone()).or_insert(0);
                *n += 1;
                section = format!("[[{name}]] #{n}");
            }
        } else if t.starts_with('[') {
            if let Some(end) = t.find(']') {
                let name = t[1..end].trim().to_string();
                // `[printer.simulate]` belongs to the latest `[[printer]]`.
                match name.split_once('.') {
                    Some((parent, child)) if counts.contains_key(parent) => {
                        section = format!("[[{parent}]] #{}.{child}", counts[parent]);
                    }
                    _ => section = format!("[{name}]"),
                }
            }
        }
    }
    (line, section)
}
