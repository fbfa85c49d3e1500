//! Preparing a job: read its sidecar, work out the folder's settings with the sidecar's
//! overrides, then enhance and slice the model into `<job dir>/<file>.gcode`. The daemon
//! calls [`Preparer::prepare`] on a blocking thread (bounded by a semaphore of the core
//! count); [`SlicePreparer`] is the real one, built on `crispen::slice`.

use super::config::{parse_strength, FolderConfig};
use super::job::Sidecar;
use crate::enhance::Strength;
use crate::slice::{SlicerKind, UpAxis};
use std::io::Read;
use std::path::{Path, PathBuf};
use std::sync::atomic::AtomicBool;
use std::sync::Arc;
use std::time::Duration;

/// Everything one preparation needs, resolved from the folder config and the sidecar.
#[derive(Debug, Clone)]
pub struct PrepareTask {
    pub job: String,
    pub model: PathBuf,
    pub output: PathBuf,
    pub height_mm: f64,
    pub strength: Strength,
    pub slicer: SlicerKind,
    pub up: UpAxis,
    pub profile: Option<PathBuf>,
    pub settings: crate::slice::SliceSettings,
    pub timeout: Duration,
    /// Set when the job is cancelled while being prepared.
    pub cancel: Arc<AtomicBool>,
}

/// Turns a model into G-code. Returns a JSON report kept in the job, or the reason the
/// job failed (operator-readable).
pub trait Preparer: Send + Sync + 'static {
    fn prepare(
        &self,
        task: &PrepareTask,
        progress: &mut dyn FnMut(&str),
    ) -> Result<serde_json::Value, String>;
}

/// Reads a sidecar file (`model.stl.toml`); unknown keys are an error.
pub fn read_sidecar(path: &Path) -> Result<Option<Sidecar>, String> {
    let file = match std::fs::File::open(path) {
        Ok(f) => f,
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => return Ok(None),
        Err(e) => return Err(format!("sidecar {}: cannot read: {e}", path.display())),
    };
    parse_sidecar(file, path).map(Some)
}

/// Parses a sidecar from any reader; `path` names it in errors.
pub fn parse_sidecar(mut reader: impl Read, path: &Path) -> Result<Sidecar, String> {
    let mut text = String::new();
    reader
        .read_to_string(&mut text)
        .map_err(|e| format!("sidecar {}: cannot read: {e}", path.display()))?;
    let sidecar: Sidecar = toml::from_str(&text).map_err(|e| {
        format!(
            "sidecar {}: {} (allowed keys: height_mm, enhance, strength, up, copies, printer)",
            path.display(),
            e.message().trim()
        )
    })?;
    if let Some(h) = sidecar.height_mm {
        if !(h.is_finite() && h > 0.0 && h <= 1000.0) {
            return Err(format!(
                "sidecar {}: key `height_mm`: must be > 0 and at most 1000, got {h}",
                path.display()
            ));
        }
    }
    if sidecar.copies == Some(0) {
        return Err(format!(
            "sidecar {}: key `copies`: must be at least 1",
            path.display()
        ));
    }
    if let Some(s) = &sidecar.strength {
        parse_strength(s)
            .map_err(|m| format!("sidecar {}: key `strength`: {m}", path.display()))?;
    }
    Ok(sidecar)
}

/// Combines a folder's settings with a sidecar's overrides into a task.
pub fn resolve_task(
    job: &str,
    job_dir: &Path,
    file: &str,
    folder: &FolderConfig,
    sidecar: Option<&Sidecar>,
) -> Result<PrepareTask, String> {
    let mut strength = folder.strength;
    let mut height_mm = folder.height_mm;
    let mut up = folder.up;
    if let Some(s) = sidecar {
        if let Some(h) = s.height_mm {
            height_mm = h;
        }
        if let Some(axis) = s.up {
            up = axis;
        }
        if let Some(v) = &s.strength {
            strength = parse_strength(v)?;
        }
        if s.enhance == Some(false) {
            strength = Strength::Off;
        } else if s.enhance == Some(true) && strength == Strength::Off {
            strength = Strength::Auto;
        }
        if let Some(p) = &s.printer {
            if !folder.printers.contains(p) {
                return Err(format!(
                    "sidecar {file}.toml: key `printer`: {p:?} does not serve folder {} (it is served by {})",
                    folder.path.display(),
                    folder.printers.join(", ")
                ));
            }
        }
    }
    Ok(PrepareTask {
        job: job.to_string(),
        model: job_dir.join(file),
        output: job_dir.join(format!("{file}.gcode")),
        height_mm,
        strength,
        slicer: folder.slicer,
        up,
        profile: folder.profile.clone(),
        settings: folder.settings.clone(),
        timeout: folder.timeout,
        cancel: Arc::default(),
    })
}

/// The real preparation: `crispen::slice` (enhance, scale, slice with a real slicer).
pub struct SlicePreparer;

impl Preparer for SlicePreparer {
    fn prepare(
        &self,
        task: &PrepareTask,
        progress: &mut dyn FnMut(&str),
    ) -> Result<serde_json::Value, String> {
        real_slice(task, progress)
    }
}

fn real_slice(
    task: &PrepareTask,
    progress: &mut dyn FnMut(&str),
) -> Result<serde_json::Value, String> {
    use crate::enhance::Phase;
    use crate::slice::{SliceRequest, SliceStep};
    let mut req = SliceRequest::new(&task.model, &task.output, task.height_mm);
    req.slicer = task.slicer;
    req.strength = task.strength;
    req.up = task.up;
    req.settings = task.settings.clone();
    req.profile = task.profile.clone();
    req.timeout = task.timeout;
    req.cancel = Some(task.cancel.clone());
    let report = crate::slice::slice(&req, &mut |step| {
        let name = match step {
            SliceStep::Loading => "loading".to_string(),
            SliceStep::Enhancing(Phase::Operators) => "enhancing: operators".into(),
            SliceStep::Enhancing(Phase::Factorize) => "enhancing: factorizing".into(),
            SliceStep::Enhancing(Phase::Solve(i)) => format!("enhancing: solve {i}"),
            SliceStep::Enhancing(Phase::Combine) => "enhancing: combining".into(),
            SliceStep::Slicing => "slicing".into(),
            SliceStep::Checking => "checking the G-code".into(),
        };
        progress(&name);
    })
    .map_err(|e| e.to_string())?;
    Ok(serde_json::to_value(&report).unwrap_or_default())
}

#[cfg(test)]
mod tests {
    use super::*;

    fn folder() -> FolderConfig {
        FolderConfig {
            path: "/hot".into(),
            height_mm: 50.0,
            printers: vec!["a".into(), "b".into()],
            strength: Strength::Auto,
            slicer: SlicerKind::Prusa,
            up: UpAxis::Z,
            profile: None,
            timeout: Duration::from_secs(60),
            settings: Default::default(),
        }
    }

    #[test]
    fn sidecar_overrides_and_rejects_unknown_keys() {
        let s = parse_sidecar(
            &b"enhance = false\nheight_mm = 20\nup = \"y\"\n"[..],
            Path::new("m.stl.toml"),
        )
        .unwrap();
        let t = resolve_task("j", Path::new("/s/j"), "m.stl", &folder(), Some(&s)).unwrap();
        assert_eq!(t.strength, Strength::Off);
        assert_eq!(t.height_mm, 20.0);
        assert_eq!(t.up, UpAxis::Y);
        assert_eq!(t.output, PathBuf::from("/s/j/m.stl.gcode"));

        let err = parse_sidecar(&b"enhanse = false\n"[..], Path::new("m.stl.toml")).unwrap_err();
        assert!(
            err.contains("m.stl.toml") && err.contains("enhanse"),
            "{err}"
        );
        let err = parse_sidecar(&b"height_mm = -1\n"[..], Path::new("m.stl.toml")).unwrap_err();
        assert!(err.contains("height_mm"), "{err}");

        let s = parse_sidecar(&b"printer = \"zz\"\n"[..], Path::new("m.stl.toml")).unwrap();
        let err = resolve_task("j", Path::new("/s/j"), "m.stl", &folder(), Some(&s)).unwrap_err();
        assert!(err.contains("\"zz\""), "{err}");
    }
}
