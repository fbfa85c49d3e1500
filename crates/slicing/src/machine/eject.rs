//! How a machine's bed is cleared by the printer itself: its eject sequence (`[machine.eject]`,
//! or `[printer.eject]` for one printer), the G-code a farm writes to push a finished print
//! off a cold bed or to drive a plate changer. Read and bounded here; the daemon's config
//! checks it against the machine's G-code policy as it checks a job's lines.

use serde::{Deserialize, Serialize};
use std::path::{Component, Path, PathBuf};

/// `[machine.eject]` or `[printer.eject]` as written.
#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct EjectSpec {
    /// The sequence itself, inline.
    pub gcode: Option<String>,
    /// Or a file holding it, under the config's folder.
    pub file: Option<PathBuf>,
    /// The bed temperature to wait for before the sequence runs, °C (parts come off a
    /// cold PEI sheet).
    pub release_bed_c: Option<f64>,
    /// The tallest print the sequence may push off, mm; a taller one waits for a person.
    pub max_height_mm: Option<f64>,
    /// Commands of a plate changer (or others the G-code policy refuses) the sequence may
    /// use.
    pub allow: Option<Vec<String>>,
}

/// An eject sequence, read and bounded.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Eject {
    /// The G-code sent after a good print, as written.
    pub gcode: String,
    /// Wait for the bed to cool to this first, °C (None: no wait).
    pub release_bed_c: Option<f64>,
    /// The tallest print it may push off, mm.
    pub max_height_mm: f64,
    /// Commands it may use that the policy refuses in files (upper case).
    pub allow: Vec<String>,
}

/// The coolest release temperature asked (a bed does not cool below the room) and the
/// warmest (above this nothing comes off).
pub const RELEASE_BED_C: std::ops::RangeInclusive<f64> = 15.0..=80.0;

impl EjectSpec {
    /// Checks the table for `machine` (whose height bounds `max_height_mm`); `config_dir`
    /// is the config's folder, which `file` must be under. Errors name the key.
    pub fn check(
        self,
        machine_z_mm: f64,
        config_dir: &Path,
    ) -> Result<Eject, (&'static str, String)> {
        let gcode = match (self.gcode, self.file) {
            (Some(g), None) => {
                if g.len() as u64 > super::code::MAX_CODE_BYTES {
                    return Err((
                        "gcode",
                        format!(
                            "larger than {} bytes; an eject sequence is a few lines",
                            super::code::MAX_CODE_BYTES
                        ),
                    ));
                }
                g
            }
            (None, Some(f)) => {
                let under = f.is_relative()
                    && f.components()
                        .all(|c| matches!(c, Component::Normal(_) | Component::CurDir));
                if !under || f.as_os_str().is_empty() {
                    return Err((
                        "file",
                        format!(
                            "{}: must be a file under the config's folder (a relative path without `..`)",
                            f.display()
                        ),
                    ));
                }
                super::code::read_code(&config_dir.join(&f)).map_err(|m| ("file", m))?
            }
            (Some(_), Some(_)) => {
                return Err((
                    "file",
                    "give `gcode` (the sequence) or `file`, not both".into(),
                ))
            }
            (None, None) => {
                return Err((
                    "gcode",
                    "missing: give the sequence as `gcode` or a `file` under the config's folder"
                        .into(),
                ))
            }
        };
        if gcode.trim().is_empty() {
            return Err(("gcode", "the sequence is empty".into()));
        }
        let release_bed_c = match self.release_bed_c {
            None => None,
            Some(c) if c.is_finite() && RELEASE_BED_C.contains(&c) => Some(c),
            Some(c) => {
                return Err((
                    "release_bed_c",
                    format!(
                        "must be from {} to {} °C, got {c}",
                        RELEASE_BED_C.start(),
                        RELEASE_BED_C.end()
                    ),
                ))
            }
        };
        let max_height_mm = match self.max_height_mm {
            Some(h) if h.is_finite() && (1.0..=machine_z_mm).contains(&h) => h,
            Some(h) => {
                return Err((
                    "max_height_mm",
                    format!("must be from 1 mm to the machine's height ({machine_z_mm} mm), got {h}"),
                ))
            }
            None => {
                return Err((
                    "max_height_mm",
                    "missing: the tallest print the sequence may push off, mm (a taller one waits for a person)".into(),
                ))
            }
        };
        let mut allow = Vec::new();
        for word in self.allow.unwrap_or_default() {
            let code = word.trim().to_ascii_uppercase();
            if !super::commands::allowable(&code) {
                return Err((
                    "allow",
                    format!(
                        "{word:?} is not a command a sequence may be allowed: only those the G-code policy guards or does not know (a plate changer's own); see docs/gcode-policy.md"
                    ),
                ));
            }
            if !allow.contains(&code) {
                allow.push(code);
            }
        }
        Ok(Eject {
            gcode,
            release_bed_c,
            max_height_mm,
            allow,
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn spec(text: &str) -> EjectSpec {
        toml::from_str(text).unwrap()
    }

    #[test]
    fn an_eject_is_bounded_and_read_from_under_the_config() {
        let dir = tempfile::tempdir().unwrap();
        std::fs::write(dir.path().join("push.gcode"), "G28\nG1 Y220\n").unwrap();
        let e = spec(
            "file = \"push.gcode\"\nrelease_bed_c = 30\nmax_height_mm = 60\nallow = [\"m1234\"]",
        )
        .check(205.0, dir.path())
        .unwrap();
        assert_eq!(e.gcode, "G28\nG1 Y220\n");
        assert_eq!((e.release_bed_c, e.max_height_mm), (Some(30.0), 60.0));
        assert_eq!(e.allow, ["M1234"]);
        for (text, key) in [
            ("file = \"../push.gcode\"\nmax_height_mm = 60", "file"),
            ("file = \"/etc/push.gcode\"\nmax_height_mm = 60", "file"),
            (
                "gcode = \"G28\"\nfile = \"push.gcode\"\nmax_height_mm = 60",
                "file",
            ),
            ("max_height_mm = 60", "gcode"),
            ("gcode = \"G28\"", "max_height_mm"),
            ("gcode = \"G28\"\nmax_height_mm = 300", "max_height_mm"),
            (
                "gcode = \"G28\"\nmax_height_mm = 60\nrelease_bed_c = 95",
                "release_bed_c",
            ),
            (
                "gcode = \"G28\"\nmax_height_mm = 60\nallow = [\"G1\"]",
                "allow",
            ),
            ("gcode = \"  \"\nmax_height_mm = 60", "gcode"),
        ] {
            assert_eq!(
                spec(text).check(205.0, dir.path()).unwrap_err().0,
                key,
                "{text}"
            );
        }
    }
}
