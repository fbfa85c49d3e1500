//! Slicing with real slicers: turn a mesh placed on a machine's bed into a Marlin G-code
//! job for that machine.
//!
//! [`slice_mesh`] runs PrusaSlicer or CuraEngine as a child process on a temporary STL
//! ([`process`]) with the machine's profile, and checks the G-code before calling it a job
//! ([`gcode`]). Loading, enhancing and placing the model are steps of their own
//! ([`crispen_geometry::mesh`], [`crispen_geometry::enhance`], [`crispen_geometry::mesh::place`]), composed by the daemon's
//! preparation (`crate::daemon::prepare`). The slicer profiles and the start/end G-code are
//! embedded in the binary ([`profiles`]), so an installed `crispen` needs nothing from the
//! source tree; a machine or a folder may name other profile files. G-code sliced
//! elsewhere is read by [`presliced`].
//!
//! Per-folder and per-job overrides are [`SliceSettings`]: a few named settings (layer
//! height, infill, supports, temperatures, material) that crispen maps onto each slicer's
//! own keys, so a print farm never edits the profile files. Temperatures are always
//! crispen's (from the material preset unless overridden), because the shared start code
//! heats with them.

pub mod cura;
pub(crate) mod gcode;
pub mod moved;
pub mod plate;
pub mod policy;
pub mod presliced;
pub mod process;
pub mod profiles;
pub(crate) mod prusa;
mod settings;
mod slicer;
pub mod walls;

pub use settings::{density_of, Material, SliceSettings, MATERIALS, SETTING_KEYS};
pub use slicer::{SliceError, SlicerKind};

use crate::machine::Machine;
use crispen_geometry::enhance::{EnhanceReport, PrintedDisplacement};
use crispen_geometry::mesh::place::UpAxis;
use crispen_geometry::mesh::Mesh;
use serde::{Deserialize, Serialize};
use std::path::{Path, PathBuf};
use std::sync::atomic::AtomicBool;
use std::time::{Duration, Instant};

/// Printed heights accepted, mm: from a height that still holds a shape of a few layers
/// to the tallest machine that can be described; whether a machine builds it is the
/// placement's check.
pub const HEIGHT_MM: std::ops::RangeInclusive<f64> = 1.0..=*crate::machine::BED_MM.end();

/// The layer height of the built-in profiles (`config/prusaslicer-ultimaker2.ini`,
/// `config/cura-ultimaker2.toml`), mm, when neither the job nor the G-code says.
pub const DEFAULT_LAYER_HEIGHT_MM: f64 = 0.2;

/// Loads `path`, or the built-in profile for the slicer, and checks the slicer's own
/// files are installed.
pub fn load_profile(
    kind: SlicerKind,
    path: Option<&Path>,
) -> Result<Box<dyn profiles::SlicerProfile>, SliceError> {
    let text = match path {
        Some(p) => std::fs::read_to_string(p).map_err(|e| SliceError::BadProfile {
            path: p.to_path_buf(),
            reason: e.to_string(),
        })?,
        None => match kind {
            SlicerKind::Prusa => profiles::PRUSA_PROFILE.to_string(),
            SlicerKind::Cura => profiles::CURA_PROFILE.to_string(),
        },
    };
    let shown = path.map_or_else(|| PathBuf::from("(built-in profile)"), Path::to_path_buf);
    Ok(match kind {
        SlicerKind::Prusa => Box::new(prusa::PrusaProfile::load(text, &shown)?),
        SlicerKind::Cura => Box::new(cura::CuraProfile::load(&text, &shown)?),
    })
}

/// Where a slicing is; reported through the `progress` callback of [`slice_mesh`].
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum SliceStep {
    Slicing,
    Checking,
}

/// One slicing: a mesh already enhanced and placed on the machine's bed (see
/// [`crispen_geometry::mesh::place`]), sliced for one machine into `output`.
#[derive(Clone, Debug)]
pub struct SliceJob<'a> {
    /// The model file the mesh came from (named in messages and the report).
    pub model: &'a Path,
    pub output: &'a Path,
    pub machine: &'a Machine,
    /// Printed height (the mesh's Z extent), mm.
    pub height_mm: f64,
    pub slicer: SlicerKind,
    pub settings: &'a SliceSettings,
    /// A profile replacing the machine's (PrusaSlicer `.ini` or CuraEngine `.toml`).
    pub profile: Option<&'a Path>,
    /// The slicer is killed and the slicing fails after this long.
    pub timeout: Duration,
    /// Program to run instead of the slicer's usual one (also env CRISPEN_PRUSA_SLICER /
    /// CRISPEN_CURA_ENGINE); the job wins over the environment.
    pub slicer_program: Option<&'a Path>,
    /// Set to true from another thread to stop the slicer.
    pub cancel: Option<&'a AtomicBool>,
    /// Where to keep the mesh that was sliced, as binary STL.
    pub keep_mesh: Option<&'a Path>,
    /// The G-code is only measured, never printed (the unmodified slicing a comparison is
    /// made against): a G-code failing the job's checks is kept, with a warning, because
    /// a slicer's trouble with the unmodified model (an open scan's empty layers) is no
    /// reason not to measure the enhanced one.
    pub measure_only: bool,
    /// Copies of the model side by side on one bed (1: one), each a part of the plate.
    pub per_plate: u32,
}

/// How the model was changed before slicing.
#[derive(Clone, Debug, Default, Serialize, Deserialize)]
pub struct EnhancementSummary {
    /// The λ2 used, or `None` when the model was printed unmodified.
    pub lambda2: Option<f64>,
    /// `"enhanced"` or `"unmodified"`.
    pub mode: String,
    pub report: Option<EnhanceReport>,
    /// The displacement at the printed size in mm, against this job's machine's nozzle and
    /// layer height (the report's `max_displacement` is in the model file's units).
    #[serde(default)]
    pub printed: Option<PrintedDisplacement>,
    /// In print-aware mode, what it chose for this machine (band, lift, λ2, cap).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub print_aware: Option<crispen_geometry::enhance::print_aware::PrintAwareReport>,
    /// With `strength = "observed"`: what the observer saw of each candidate and why
    /// this strength.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub observed: Option<crate::observation::Observation>,
}

/// Where the comparison of the outer walls stands when a report has none.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum WallsState {
    /// Not asked for (`crispen slice` without `--compare`; reports made before the state
    /// was kept).
    #[default]
    NotAsked,
    /// To be measured (the daemon's, after the job is ready).
    Pending,
    /// Asked for and not made (the reason is the comparison's own, shown beside it).
    NotMeasured,
}

/// Seconds spent in each step.
#[derive(Clone, Debug, Default, Serialize, Deserialize)]
pub struct StepTimings {
    pub load_s: f64,
    pub enhance_s: f64,
    pub slice_s: f64,
    pub check_s: f64,
    pub total_s: f64,
}

/// What a finished job produced.
#[derive(Clone, Debug, Default, Serialize, Deserialize)]
pub struct SliceReport {
    pub model: PathBuf,
    pub output: PathBuf,
    /// The machine the G-code is made for.
    #[serde(default)]
    pub machine: String,
    pub height_mm: f64,
    pub up: UpAxis,
    pub enhancement: EnhancementSummary,
    pub slicer: SlicerKind,
    pub slicer_version: Option<String>,
    pub material: String,
    pub nozzle_temp_c: f64,
    pub bed_temp_c: f64,
    /// Model footprint on the bed after scaling, mm (X, Y, Z).
    pub model_size_mm: [f64; 3],
    pub timings: StepTimings,
    pub layer_count: usize,
    pub layer_height_mm: Option<f64>,
    pub top_layer_z_mm: f64,
    pub estimated_print_time_s: Option<f64>,
    pub filament_mm: Option<f64>,
    pub filament_g: Option<f64>,
    pub gcode_lines: usize,
    /// The outer walls against the unmodified model's, sliced the same way (when asked
    /// for, see `SliceRequest::compare`).
    #[serde(default)]
    pub walls: Option<walls::WallComparison>,
    /// Where the comparison of the outer walls stands while `walls` is none: what the
    /// line on what the enhancement moved says of it ([`SliceReport::moved`]).
    #[serde(default)]
    pub walls_state: WallsState,
    /// What the G-code policy found (pauses, commands the machine allowed); a file it
    /// refuses makes no report.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub policy: Option<policy::Verdict>,
    /// The parts of the plate, as the G-code labels them (see `crispen_marlin::plate`):
    /// each may be cancelled while the others print on. Empty for a file that labels none.
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub parts: Vec<crispen_marlin::plate::PartInfo>,
}

/// Slices a placed mesh for one machine ([`slice_plate`] with the model as its one part,
/// `job.per_plate` times).
pub fn slice_mesh(
    mesh: &Mesh,
    job: &SliceJob,
    progress: &mut dyn FnMut(SliceStep),
) -> Result<SliceReport, SliceError> {
    let name = job
        .model
        .file_stem()
        .map_or_else(|| "model".to_string(), |s| s.to_string_lossy().into_owned());
    slice_plate(&[plate::PlatePart { name: &name, mesh }], job, progress)
}

/// Slices placed meshes as one plate for one machine (each `job.per_plate` times, each a
/// part the G-code labels: see [`plate`]), checks the G-code, and writes `job.output`
/// (only when the G-code passed the checks; an existing file is replaced atomically). The
/// report's model-side fields (`up`, `enhancement`, `model_size_mm`, load and enhance
/// timings) are the composer's to fill. Blocking.
pub fn slice_plate(
    parts: &[plate::PlatePart],
    job: &SliceJob,
    progress: &mut dyn FnMut(SliceStep),
) -> Result<SliceReport, SliceError> {
    let started = Instant::now();
    let mut timings = StepTimings::default();
    job.settings.validate()?;
    let (nozzle_temp_c, mut bed_temp_c) = job.settings.temperatures()?;
    if !job.machine.heated_bed {
        bed_temp_c = 0.0;
    }
    let material = job.settings.material_preset()?;
    let profile_path = job.profile.or(match job.slicer {
        SlicerKind::Prusa => job.machine.prusa_profile.as_deref(),
        SlicerKind::Cura => job.machine.cura_profile.as_deref(),
    });
    let profile = load_profile(job.slicer, profile_path)?;

    progress(SliceStep::Slicing);
    let t = Instant::now();
    let work = tempfile::Builder::new()
        .prefix("crispen-slice-")
        .tempdir()
        .map_err(SliceError::io(
            "cannot create a temporary folder in",
            &std::env::temp_dir(),
        ))?;
    let (stls, copies) = write_plate(parts, job, work.path())?;
    if let (Some(keep), Some(first)) = (job.keep_mesh, stls.first()) {
        persist(first, keep)?;
    }
    let gcode_path = work.path().join("job.gcode");
    let params = profiles::JobParams {
        settings: job.settings,
        machine: job.machine,
        nozzle_temp_c,
        bed_temp_c,
        height_mm: job.height_mm,
        copies,
    };
    let invocation = profile.invocation(&params, work.path(), &stls, &gcode_path)?;
    let program = job
        .slicer_program
        .map(Path::to_path_buf)
        .or_else(|| std::env::var_os(job.slicer.program_env()).map(PathBuf::from))
        .unwrap_or_else(|| PathBuf::from(job.slicer.default_program()));
    tracing::info!(slicer = %job.slicer, program = %program.display(), model = %job.model.display(), machine = %job.machine.name, "slicing");
    let run = process::run(
        &program,
        &invocation.args,
        &invocation.env,
        job.timeout,
        job.cancel,
    );
    let model = || job.model.to_path_buf();
    let outcome = match run {
        Ok(o) => o,
        Err(process::RunError::NotFound) => {
            return Err(SliceError::SlicerMissing {
                slicer: job.slicer,
                program,
                package: job.slicer.package(),
                env: job.slicer.program_env(),
            })
        }
        Err(process::RunError::Spawn(source)) => {
            return Err(SliceError::Io {
                context: "cannot start",
                path: program,
                source,
            })
        }
    };
    timings.slice_s = t.elapsed().as_secs_f64();
    let output_tail = outcome.tail_text();
    match outcome.end {
        process::End::Exited(status) if status.success() => {}
        process::End::Exited(status) => {
            return Err(SliceError::SlicerFailed {
                slicer: job.slicer,
                model: model(),
                status: status.to_string(),
                output_tail,
            })
        }
        process::End::TimedOut => {
            return Err(SliceError::Timeout {
                slicer: job.slicer,
                model: model(),
                after: job.timeout,
                output_tail,
            })
        }
        process::End::Cancelled => return Err(SliceError::Cancelled { model: model() }),
    }

    progress(SliceStep::Checking);
    let t = Instant::now();
    let bad_output = |reason: String| SliceError::BadOutput {
        slicer: job.slicer,
        model: model(),
        reason,
        output_tail: output_tail.clone(),
    };
    let file = std::fs::File::open(&gcode_path)
        .map_err(|e| bad_output(format!("no G-code file was written ({e})")))?;
    let expect = gcode::Expectations {
        bed_mm: job.machine.bed_mm,
        height_mm: job.height_mm,
        layer_height_mm: job.settings.layer_height_mm,
        heated_bed: job.machine.heated_bed,
        firmware: job.machine.firmware,
    };
    // Defence in depth: a profile's start and end code is G-code too, and crispen's own
    // output must pass what an uploaded file must. The two readings are independent and the
    // job waits for both, so they run side by side (half the wait on two cores).
    let (checked, verdict) = std::thread::scope(|scope| {
        let verdict = (!job.measure_only)
            .then(|| scope.spawn(|| policy::check_file(&gcode_path, job.machine)));
        let checked = gcode::check(std::io::BufReader::new(file), &expect);
        let verdict = verdict.map(|t| {
            t.join()
                .unwrap_or_else(|panic| std::panic::resume_unwind(panic))
        });
        (checked, verdict)
    });
    let stats = match checked {
        Ok(stats) => stats,
        Err(reason) if job.measure_only => {
            tracing::warn!(model = %job.model.display(), %reason, "the G-code measured would not pass as a job");
            gcode::GcodeStats::default()
        }
        Err(reason) => return Err(bad_output(reason)),
    };
    let verdict = verdict.transpose().map_err(|e| bad_output(e.to_string()))?;
    if let Some(verdict) = verdict.as_ref().filter(|v| !v.passed()) {
        return Err(bad_output(verdict.summary()));
    }
    timings.check_s = t.elapsed().as_secs_f64();

    // Cura's G-code header holds placeholders when run from the command line; its log has
    // the real estimate. PrusaSlicer writes real figures into the G-code.
    let estimated_print_time_s = outcome
        .lines()
        .find_map(gcode::parse_cura_log_time)
        .or(stats.estimated_time_s);
    let filament_mm = stats.filament_mm.or(Some(stats.extruded_mm));
    let filament_g = stats.filament_g.or_else(|| {
        filament_mm.map(|mm| {
            let r_cm = job.machine.filament_mm / 10.0 / 2.0;
            mm / 10.0 * std::f64::consts::PI * r_cm * r_cm * material.density_g_cm3
        })
    });

    let parts = plate_parts(&gcode_path, job.machine.firmware);
    persist(&gcode_path, job.output)?;
    timings.total_s = started.elapsed().as_secs_f64();
    Ok(SliceReport {
        model: model(),
        output: job.output.to_path_buf(),
        machine: job.machine.name.clone(),
        height_mm: job.height_mm,
        slicer: job.slicer,
        slicer_version: stats.slicer_version,
        material: material.name.to_string(),
        nozzle_temp_c,
        bed_temp_c,
        timings,
        layer_count: stats.layer_count,
        layer_height_mm: stats.layer_height_mm,
        top_layer_z_mm: stats.top_z_mm,
        estimated_print_time_s,
        filament_mm,
        filament_g,
        gcode_lines: stats.lines,
        policy: verdict,
        parts,
        ..SliceReport::default()
    })
}

/// Writes the plate's meshes into `dir` for the slicer: PrusaSlicer gets each part once
/// and lays out `per_plate` copies itself; CuraEngine gets every copy placed by crispen
/// ([`plate::arrange`]), one file each. Refused when they cannot fit the bed together.
/// Returns the files and the copies the slicer makes of each.
fn write_plate(
    parts: &[plate::PlatePart],
    job: &SliceJob,
    dir: &Path,
) -> Result<(Vec<PathBuf>, u32), SliceError> {
    let per_plate = job.per_plate.max(1);
    let fits = job.machine.fits_mm();
    let mut footprints = Vec::new();
    for part in parts {
        for _ in 0..per_plate {
            footprints.push(plate::footprint(part.mesh));
        }
    }
    let centres = plate::arrange(&footprints, [fits[0], fits[1]]).map_err(|no| {
        let sizes: Vec<String> = parts
            .iter()
            .map(|p| {
                let f = plate::footprint(p.mesh);
                format!("{:.1} x {:.1} mm", f[0], f[1])
            })
            .collect();
        SliceError::PlateTooBig {
            model: job.model.to_path_buf(),
            machine: job.machine.name.clone(),
            asked: footprints.len(),
            footprints: sizes.join(", "),
            area_mm: [fits[0], fits[1]],
            fit: no.fit,
        }
    })?;
    let write = |path: &Path, mesh: &Mesh| -> Result<(), SliceError> {
        let file = std::fs::File::create(path)
            .map_err(SliceError::io("cannot write temporary STL", path))?;
        let mut w = std::io::BufWriter::new(file);
        crispen_geometry::mesh::write_stl(&mut w, mesh)
            .and_then(|_| std::io::Write::flush(&mut w))
            .map_err(SliceError::io("cannot write temporary STL", path))
    };
    let mut stls = Vec::new();
    let mut taken: Vec<String> = Vec::new();
    let mut unique = |stem: String| {
        let mut name = stem.clone();
        let mut n = 1;
        while taken.contains(&name) {
            n += 1;
            name = format!("{stem}-{n}");
        }
        taken.push(name.clone());
        name
    };
    match job.slicer {
        SlicerKind::Prusa => {
            for part in parts {
                let path = dir.join(format!("{}.stl", unique(plate::file_stem(part.name))));
                write(&path, part.mesh)?;
                stls.push(path);
            }
            Ok((stls, per_plate))
        }
        SlicerKind::Cura => {
            let many = footprints.len() > 1;
            let mut centre = centres.iter();
            for part in parts {
                for copy in 1..=per_plate {
                    let at = *centre.next().expect("a centre per copy");
                    let stem = plate::file_stem(part.name);
                    let stem = if many && per_plate > 1 {
                        format!("{stem}-{copy}")
                    } else {
                        stem
                    };
                    let path = dir.join(format!("{}.stl", unique(stem)));
                    write(&path, &plate::moved(part.mesh, at))?;
                    stls.push(path);
                }
            }
            Ok((stls, 1))
        }
    }
}

/// The parts a G-code file labels, with their outlines (none when it labels none, or
/// cannot be read: the checks above have read it already).
pub fn plate_parts(
    gcode: &Path,
    firmware: crispen_marlin::firmware::Firmware,
) -> Vec<crispen_marlin::plate::PartInfo> {
    let program = match crispen_marlin::gcode::GcodeProgram::load_for(gcode, firmware) {
        Ok(p) => p,
        Err(e) => {
            tracing::warn!(gcode = %gcode.display(), error = %e, "cannot read the plate's parts");
            return Vec::new();
        }
    };
    match program.marks() {
        Some(marks) => crispen_marlin::plate::PlateMap::read(program.iter(), marks, firmware).parts,
        None => Vec::new(),
    }
}

/// Copies a finished file (checked G-code, the mesh that was sliced) to its destination
/// without ever leaving a half-written one there: copy next to it, then rename over it.
pub fn persist(from: &Path, to: &Path) -> Result<(), SliceError> {
    let mut src = std::fs::File::open(from).map_err(SliceError::io("cannot read", from))?;
    crispen_fsutil::write_atomic_with(to, |file| std::io::copy(&mut src, file).map(|_| ())).map_err(
        |e| SliceError::Io {
            context: "cannot write",
            path: to.to_path_buf(),
            source: e.into(),
        },
    )
}
