//! `[[folder]]`: each hot folder's table checked: its path (apart from the spool and the
//! other folders), the height its models are printed at, the printers it feeds, and how its
//! jobs are enhanced and sliced. The height and strength rules are also a sidecar's.

use super::check::{number, seconds_in, Bounds, Context};
use super::checked::{FolderConfig, PrinterConfig};
use super::error::ConfigError;
use super::raw::RawFolder;
use crate::daemon::filament::routing::check_asks;
use crate::enhance::Strength;
use std::path::{Path, PathBuf};

/// Time limit of one preparation (enhance and slice).
pub(crate) const PREPARE_TIMEOUT_S: Bounds = 0.1..=7.0 * 86_400.0;

/// Checks the `[[folder]]` tables in order, each path once. `printers` are the
/// `[[printer]]` tables, checked; in a `shared` farm, a folder may name other hosts'
/// printers too. No folder may contain the spool (`spool_dir`) or be inside it.
pub(super) fn check(
    raw: Vec<RawFolder>,
    printers: &[PrinterConfig],
    shared: bool,
    spool_dir: &Path,
    cx: &Context,
) -> Result<Vec<FolderConfig>, ConfigError> {
    let Context { invalid, anchor } = *cx;
    let mut folders: Vec<FolderConfig> = Vec::new();
    for (i, f) in raw.into_iter().enumerate() {
        let section = format!(
            "[[folder]] #{} (path {:?})",
            i + 1,
            f.path.display().to_string()
        );
        if f.path.as_os_str().is_empty() {
            return Err(invalid(section, "path", "must not be empty".into()));
        }
        // Its name is the folder's name in the API, the dashboard and uploads.
        if let Some(problem) = crate::names::problem(&f.path.to_string_lossy()) {
            return Err(invalid(section, "path", problem.into()));
        }
        let path = anchor(&f.path);
        if folders.iter().any(|o| o.path == path) {
            return Err(invalid(section, "path", "is configured twice".into()));
        }
        // A folder in a hot folder is a plate of models, packed and removed when taken.
        let inside = |a: &Path, b: &Path| normalise(a).starts_with(normalise(b));
        if let Some(o) = folders
            .iter()
            .find(|o| inside(&path, &o.path) || inside(&o.path, &path))
        {
            return Err(invalid(
                section,
                "path",
                format!(
                    "the hot folders {} and {} must not contain each other (a folder inside a hot folder is taken as a plate of models)",
                    o.path.display(),
                    path.display()
                ),
            ));
        }
        folders.push(check_folder(
            section, path, f, printers, shared, spool_dir, cx,
        )?);
    }
    Ok(folders)
}

/// One `[[folder]]` table, its path (`path`, made absolute) taken by no other folder;
/// `section` names it in errors.
fn check_folder(
    section: String,
    path: PathBuf,
    f: RawFolder,
    printers: &[PrinterConfig],
    shared: bool,
    spool_dir: &Path,
    cx: &Context,
) -> Result<FolderConfig, ConfigError> {
    let Context { invalid, anchor } = *cx;
    check_height(f.height_mm).map_err(|m| invalid(section.clone(), "height_mm", m))?;
    // A height no machine of the folder can build would fail every job.
    let tallest = printers
        .iter()
        .filter(|p| f.printers.contains(&p.name))
        .map(|p| p.machine.bed_mm[2])
        .fold(0.0, f64::max);
    if !f.printers.is_empty() && tallest > 0.0 && f.height_mm > tallest {
        return Err(invalid(
            section,
            "height_mm",
            format!(
                "{} mm is taller than any of its printers' machines builds ({tallest} mm)",
                f.height_mm
            ),
        ));
    }
    let inside = |a: &Path, b: &Path| normalise(a).starts_with(normalise(b));
    if inside(&path, spool_dir) || inside(spool_dir, &path) {
        return Err(invalid(
            section,
            "path",
            format!(
                "the hot folder and the spool ({}) must not contain each other",
                spool_dir.display()
            ),
        ));
    }
    if f.printers.is_empty() {
        return Err(invalid(
            section,
            "printers",
            "must name at least one printer".into(),
        ));
    }
    for name in &f.printers {
        // In a shared farm, a folder may name other hosts' printers.
        if !printers.iter().any(|p| p.name == *name) && !shared {
            return Err(invalid(
                section,
                "printers",
                format!("no [[printer]] is named {name:?}"),
            ));
        }
    }
    let strength = match (&f.strength, f.enhance) {
        (_, Some(false)) => Strength::Off,
        (None, _) => Strength::Auto,
        (Some(v), _) => parse_strength(v).map_err(|m| invalid(section.clone(), "strength", m))?,
    };
    let timeout = seconds_in(f.timeout_s.unwrap_or(600.0), &PREPARE_TIMEOUT_S)
        .map_err(|m| invalid(section.clone(), "timeout_s", m))?;
    let per_plate = f.per_plate.unwrap_or(1);
    check_per_plate(per_plate).map_err(|m| invalid(section.clone(), "per_plate", m))?;
    let copies = f.copies.unwrap_or(1);
    check_copies(copies).map_err(|m| invalid(section.clone(), "copies", m))?;
    let settings = match f.settings {
        None => crate::slice::SliceSettings::default(),
        Some(table) => {
            let settings: crate::slice::SliceSettings = toml::Value::Table(table)
                .try_into()
                .map_err(|e: toml::de::Error| {
                    invalid(section.clone(), "settings", e.message().trim().to_string())
                })?;
            settings
                .validate()
                .map_err(|e| invalid(section.clone(), "settings", e.to_string()))?;
            settings
        }
    };
    check_asks(
        f.material.as_deref(),
        f.colour.as_deref(),
        f.nozzle_mm,
        f.tags.as_deref(),
        f.priority,
    )
    .map_err(|(key, m)| invalid(section.clone(), key, m))?;
    let mut settings = settings;
    // `material` is what the jobs ask of their printer, and what they are sliced for.
    if let Some(m) = &f.material {
        let preset = m.trim().to_ascii_lowercase();
        match &settings.material {
            Some(s) if *s != preset => {
                return Err(invalid(
                    section,
                    "material",
                    format!("{m:?} differs from settings.material {s:?}; give one"),
                ))
            }
            _ => {}
        }
        if crate::slice::MATERIALS.iter().any(|p| p.name == preset) {
            settings.material = Some(preset);
        }
    }
    let asks = crate::daemon::filament::Asks {
        material: f
            .material
            .or_else(|| settings.material.clone())
            .map(|m| m.trim().to_ascii_uppercase()),
        colour: f.colour.map(|c| c.trim().to_ascii_lowercase()),
        nozzle_mm: f.nozzle_mm,
        tags: f.tags.unwrap_or_default(),
        priority: f.priority.unwrap_or(0),
        ..Default::default()
    };
    let bed_clear = match f.bed_clear.as_deref() {
        None => None,
        Some(text) => {
            let clear = crate::daemon::bed::ClearBy::parse(text)
                .map_err(|m| invalid(section.clone(), "bed_clear", m))?;
            for p in printers.iter().filter(|p| f.printers.contains(&p.name)) {
                super::printers::needs_for(clear, p.eject.is_some(), p.camera.is_some()).map_err(
                    |m| {
                        invalid(
                            section.clone(),
                            "bed_clear",
                            format!("printer {:?}: {m}", p.name),
                        )
                    },
                )?;
            }
            Some(clear)
        }
    };
    Ok(FolderConfig {
        bed_clear,
        asks,
        path,
        height_mm: f.height_mm,
        printers: f.printers,
        strength,
        mode: f.enhancement.unwrap_or_default(),
        slicer: f.slicer.unwrap_or_default(),
        up: f.up.unwrap_or_default(),
        profile: f.profile.map(|p| anchor(&p)),
        timeout,
        settings,
        per_plate,
        copies,
    })
}

/// Copies of one model a folder or a sidecar may ask for.
pub(crate) const MAX_COPIES: u32 = 100;

/// Checks how many copies of a model a folder or a sidecar asks for.
pub(crate) fn check_copies(n: u32) -> Result<(), String> {
    if (1..=MAX_COPIES).contains(&n) {
        Ok(())
    } else {
        Err(format!("must be from 1 to {MAX_COPIES}, got {n}"))
    }
}

/// Checks how many copies a folder or a sidecar puts on one plate.
pub(crate) fn check_per_plate(n: u32) -> Result<(), String> {
    let max = crate::slice::plate::MAX_PER_PLATE;
    if (1..=max).contains(&n) {
        Ok(())
    } else {
        Err(format!("must be from 1 to {max}, got {n}"))
    }
}

/// A printed height in mm: what the printer can build, and enough to hold a shape.
pub(crate) fn check_height(height_mm: f64) -> Result<(), String> {
    let range = crate::slice::HEIGHT_MM;
    if height_mm.is_finite() && range.contains(&height_mm) {
        Ok(())
    } else {
        Err(format!(
            "must be from {} to {} mm, got {}",
            range.start(),
            range.end(),
            number(height_mm)
        ))
    }
}

/// `path` with `.` and `..` taken out lexically (links are not resolved: the folders may
/// not exist yet).
fn normalise(path: &Path) -> PathBuf {
    let mut out = PathBuf::new();
    for c in path.components() {
        match c {
            std::path::Component::CurDir => {}
            std::path::Component::ParentDir => {
                out.pop();
            }
            other => out.push(other),
        }
    }
    out
}

/// The strongest enhancement accepted: five times the automatic table's strongest (20),
/// beyond which a shape is distorted rather than sharpened.
pub(crate) const MAX_LAMBDA2: f64 = 100.0;

/// `strength = "auto" | "off" | "observed" | <lambda2>`.
pub(crate) fn parse_strength(value: &toml::Value) -> Result<Strength, String> {
    match value {
        toml::Value::String(s) if s == "auto" => Ok(Strength::Auto),
        toml::Value::String(s) if s == "off" => Ok(Strength::Off),
        toml::Value::String(s) if s == "observed" => Ok(Strength::Observed),
        toml::Value::Float(x) if (0.0..=MAX_LAMBDA2).contains(x) => Ok(Strength::Lambda2(*x)),
        toml::Value::Integer(x) if (0..=MAX_LAMBDA2 as i64).contains(x) => {
            Ok(Strength::Lambda2(*x as f64))
        }
        other => Err(format!(
            "must be \"auto\", \"off\", \"observed\" or a lambda2 from 0 to {MAX_LAMBDA2}, got {other}"
        )),
    }
}
