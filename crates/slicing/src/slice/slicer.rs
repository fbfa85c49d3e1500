//! Which slicer runs, and how slicing fails: the definitions every slicer's module (and
//! the profiles and settings they read) shares, apart from the root that runs them.

use crate::machine::SKIRT_MARGIN_MM;
use crispen_geometry::enhance::EnhanceError;
use crispen_geometry::mesh::MeshError;
use serde::{Deserialize, Serialize};
use std::path::{Path, PathBuf};
use std::time::Duration;

/// Which slicer turns the mesh into G-code.
#[derive(Clone, Copy, Debug, Serialize, Deserialize, PartialEq, Eq, Default)]
#[serde(rename_all = "lowercase")]
pub enum SlicerKind {
    /// PrusaSlicer (Debian package `prusa-slicer`), the default.
    #[default]
    Prusa,
    /// CuraEngine (Debian package `cura-engine`) with Ultimaker's definitions.
    Cura,
}

impl SlicerKind {
    /// The program run when no other is configured.
    pub fn default_program(self) -> &'static str {
        match self {
            SlicerKind::Prusa => "prusa-slicer",
            SlicerKind::Cura => "CuraEngine",
        }
    }

    /// The Debian package that provides the slicer.
    pub(crate) fn package(self) -> &'static str {
        match self {
            SlicerKind::Prusa => "prusa-slicer",
            SlicerKind::Cura => "cura-engine",
        }
    }

    /// Environment variable naming another program to run (e.g. a wrapper script).
    pub(crate) fn program_env(self) -> &'static str {
        match self {
            SlicerKind::Prusa => "CRISPEN_PRUSA_SLICER",
            SlicerKind::Cura => "CRISPEN_CURA_ENGINE",
        }
    }
}

impl std::fmt::Display for SlicerKind {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(match self {
            SlicerKind::Prusa => "PrusaSlicer",
            SlicerKind::Cura => "CuraEngine",
        })
    }
}

impl std::str::FromStr for SlicerKind {
    type Err = String;
    fn from_str(s: &str) -> Result<Self, String> {
        match s.to_ascii_lowercase().as_str() {
            "prusa" | "prusaslicer" | "prusa-slicer" => Ok(SlicerKind::Prusa),
            "cura" | "curaengine" | "cura-engine" => Ok(SlicerKind::Cura),
            _ => Err(format!("unknown slicer {s:?}; use prusa or cura")),
        }
    }
}

/// Why a job failed. Messages name the model, slicer, exit status and the end of the
/// slicer's output, and end with what the user can do.
#[derive(Debug, thiserror::Error)]
pub enum SliceError {
    #[error(transparent)]
    Mesh(#[from] MeshError),
    #[error("{model}: {source}")]
    Enhance {
        model: PathBuf,
        #[source]
        source: EnhanceError,
    },
    #[error(
        "{model}: at {height_mm} mm tall the model is {size_mm:.1?} mm (X, Y, Z), which does not fit \
         the {machine}'s {max_mm:?} mm (keeping {SKIRT_MARGIN_MM} mm around it for the skirt); \
         print it smaller"
    )]
    TooBig {
        model: PathBuf,
        machine: String,
        height_mm: f64,
        size_mm: [f64; 3],
        max_mm: [f64; 3],
    },
    #[error(
        "{model}: {asked} parts of {footprints} do not fit the {machine}'s {area_mm:?} mm \
         together (keeping {} mm between them and {SKIRT_MARGIN_MM} mm around them); at most \
         {fit} do: ask for fewer per plate, or print them smaller",
        crate::slice::plate::GAP_MM
    )]
    PlateTooBig {
        model: PathBuf,
        machine: String,
        asked: usize,
        /// The parts' footprints, in words.
        footprints: String,
        area_mm: [f64; 2],
        fit: usize,
    },
    #[error("{model}: the model has no volume to print (empty or flat mesh)")]
    EmptyModel { model: PathBuf },
    #[error("bad setting {key}={value}: {hint}")]
    BadSetting {
        key: String,
        value: String,
        hint: String,
    },
    #[error("cannot read profile {path}: {reason}")]
    BadProfile { path: PathBuf, reason: String },
    #[error(
        "{slicer} not found (tried to run {program}); install Debian's {package} package \
         (`sudo apt-get install {package}`, or run scripts/setup), or set {env} to the program"
    )]
    SlicerMissing {
        slicer: SlicerKind,
        program: PathBuf,
        package: &'static str,
        env: &'static str,
    },
    #[error(
        "CuraEngine needs Ultimaker's printer definitions, but {path} does not exist; run \
         scripts/setup, or set CRISPEN_CURA_RESOURCES to the folder holding definitions/ and extruders/"
    )]
    CuraResourcesMissing { path: PathBuf },
    #[error(
        "{slicer} failed on {model} ({status}); end of its output:\n{output_tail}\nhint: the \
         slicer's last lines above say why; check the profile (--profile) and the model"
    )]
    SlicerFailed {
        slicer: SlicerKind,
        model: PathBuf,
        status: String,
        output_tail: String,
    },
    #[error(
        "{slicer} took longer than {after:?} on {model} and was stopped; end of its output:\n\
         {output_tail}\nhint: raise the timeout (--timeout SECS) for big models"
    )]
    Timeout {
        slicer: SlicerKind,
        model: PathBuf,
        after: Duration,
        output_tail: String,
    },
    #[error("slicing {model} was cancelled")]
    Cancelled { model: PathBuf },
    #[error(
        "{slicer} wrote unusable G-code for {model}: {reason}; the job was not written. End of \
         the slicer's output:\n{output_tail}"
    )]
    BadOutput {
        slicer: SlicerKind,
        model: PathBuf,
        reason: String,
        output_tail: String,
    },
    #[error("{context} {path}: {source}")]
    Io {
        context: &'static str,
        path: PathBuf,
        #[source]
        source: std::io::Error,
    },
}

impl SliceError {
    pub fn io<'a>(
        context: &'static str,
        path: &'a Path,
    ) -> impl FnOnce(std::io::Error) -> SliceError + 'a {
        move |source| SliceError::Io {
            context,
            path: path.to_path_buf(),
            source,
        }
    }
}
