//! Slicing with real slicers: turn a model into a Marlin G-code job for an Ultimaker 2.
//!
//! [`slice`] loads the model ([`crate::mesh`]), enhances it for the printed height
//! ([`crate::enhance`]), scales it to that height, lays it on the bed and centres it, checks
//! it fits the build volume, then runs PrusaSlicer or CuraEngine as a child process on a
//! temporary STL ([`process`]), and checks the G-code before calling it a job ([`gcode`]).
//! The slicer profiles and the start/end G-code are embedded in the binary ([`profiles`]),
//! so an installed `crispen` needs nothing from the source tree; `profile` overrides them.
//!
//! Per-folder and per-job overrides are [`SliceSettings`]: a few named settings (layer
//! height, infill, supports, temperatures, material) that crispen maps onto each slicer's
//! own keys, so a print farm never edits the profile files. Temperatures are always
//! crispen's (from the material preset unless overridden), because the shared start code
//! heats with them.

pub mod cura;
pub mod gcode;
pub mod process;
pub mod profiles;
pub mod prusa;
mod settings;

pub use settings::{Material, SliceSettings, MATERIALS, SETTING_KEYS};

use crate::enhance::{EnhanceError, EnhanceOptions, EnhanceReport, Phase, Strength, StrengthTable};
use crate::mesh::place::PlaceError;
use crate::mesh::{Mesh, MeshError};
use serde::{Deserialize, Serialize};
use std::path::{Path, PathBuf};
use std::sync::atomic::AtomicBool;
use std::sync::Arc;
use std::time::{Duration, Instant};

/// Usable build volume of the Ultimaker 2, in mm (X, Y, Z).
pub const BED_MM: [f64; 3] = [223.0, 223.0, 205.0];
/// Printed heights accepted, mm: from a height that still holds a shape of a few layers
/// to the build volume's height.
pub const HEIGHT_MM: std::ops::RangeInclusive<f64> = 1.0..=BED_MM[2];
/// Room kept free around the model on each side, for the skirt the profiles print.
pub const SKIRT_MARGIN_MM: f64 = 5.0;

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
    pub fn package(self) -> &'static str {
        match self {
            SlicerKind::Prusa => "prusa-slicer",
            SlicerKind::Cura => "cura-engine",
        }
    }

    /// Environment variable naming another program to run (e.g. a wrapper script).
    pub fn program_env(self) -> &'static str {
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

/// Which of the model file's axes points up. STL files are Z-up by convention; many OBJ
/// files (the Stanford bunny, Spot) are Y-up and would otherwise print lying on their side.
#[derive(Clone, Copy, Debug, Serialize, Deserialize, PartialEq, Eq, Default)]
#[serde(rename_all = "lowercase")]
pub enum UpAxis {
    #[default]
    Z,
    Y,
}

impl std::str::FromStr for UpAxis {
    type Err = String;
    fn from_str(s: &str) -> Result<Self, String> {
        match s.to_ascii_lowercase().as_str() {
            "z" => Ok(UpAxis::Z),
            "y" => Ok(UpAxis::Y),
            _ => Err(format!("unknown up axis {s:?}; use z or y")),
        }
    }
}

/// One slicing job.
#[derive(Clone, Debug)]
pub struct SliceRequest {
    pub model: PathBuf,
    pub output: PathBuf,
    /// Printed height of the model (its Z extent on the bed), mm.
    pub height_mm: f64,
    pub slicer: SlicerKind,
    pub strength: Strength,
    pub strength_table: StrengthTable,
    pub settings: SliceSettings,
    /// A profile replacing the built-in one: PrusaSlicer `.ini`, or CuraEngine `.toml`.
    pub profile: Option<PathBuf>,
    /// The slicer is killed and the job fails after this long.
    pub timeout: Duration,
    /// Program to run instead of the slicer's usual one (also env CRISPEN_PRUSA_SLICER /
    /// CRISPEN_CURA_ENGINE); the request wins over the environment.
    pub slicer_program: Option<PathBuf>,
    /// Set to true from another thread to stop the job (the slicer is killed).
    pub cancel: Option<Arc<AtomicBool>>,
    /// The model's up axis (default Z).
    pub up: UpAxis,
    /// Where to keep the mesh that was sliced (enhanced, scaled and placed), as binary STL.
    pub keep_mesh: Option<PathBuf>,
    /// Where to draw the model before and after enhancement and the displacement's heat
    /// map (`crate::preview`, only when it is enhanced); with it, the G-code also gets
    /// PrusaSlicer-format thumbnails of the part as printed.
    pub pictures: Option<PathBuf>,
}

impl SliceRequest {
    /// A request with the defaults: PrusaSlicer, automatic strength, built-in profile,
    /// 10 minute timeout.
    pub fn new(model: impl Into<PathBuf>, output: impl Into<PathBuf>, height_mm: f64) -> Self {
        SliceRequest {
            model: model.into(),
            output: output.into(),
            height_mm,
            slicer: SlicerKind::default(),
            strength: Strength::Auto,
            strength_table: StrengthTable::default(),
            settings: SliceSettings::default(),
            profile: None,
            timeout: Duration::from_secs(600),
            slicer_program: None,
            cancel: None,
            up: UpAxis::Z,
            keep_mesh: None,
            pictures: None,
        }
    }
}

/// Where a job is; reported through the `progress` callback of [`slice`].
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum SliceStep {
    Loading,
    Enhancing(Phase),
    Slicing,
    Checking,
}

/// How the model was changed before slicing.
#[derive(Clone, Debug, Default, Serialize, Deserialize)]
pub struct EnhancementSummary {
    /// The λ2 used, or `None` when the model was printed unmodified.
    pub lambda2: Option<f64>,
    /// `"enhanced"` or `"unmodified"`.
    pub mode: String,
    pub report: Option<EnhanceReport>,
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
         the Ultimaker 2's {max_mm:?} mm (including {SKIRT_MARGIN_MM} mm around it for the skirt); \
         print it smaller"
    )]
    TooBig {
        model: PathBuf,
        height_mm: f64,
        size_mm: [f64; 3],
        max_mm: [f64; 3],
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
    fn io<'a>(
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

/// Runs a whole job: load, enhance, place, slice, check, and write `req.output` (only when
/// the G-code passed the checks; an existing file is replaced atomically). Blocking.
pub fn slice(
    req: &SliceRequest,
    progress: &mut dyn FnMut(SliceStep),
) -> Result<SliceReport, SliceError> {
    let started = Instant::now();
    let mut timings = StepTimings::default();
    req.settings.validate()?;
    let (nozzle_temp_c, bed_temp_c) = req.settings.temperatures()?;
    let material = req.settings.material_preset()?;
    // Too tall is reported by the placement, with the model's size.
    if !(req.height_mm.is_finite() && req.height_mm >= *HEIGHT_MM.start()) {
        return Err(SliceError::BadSetting {
            key: "height".into(),
            value: req.height_mm.to_string(),
            hint: format!(
                "the printed height must be from {} to {} mm",
                HEIGHT_MM.start(),
                HEIGHT_MM.end()
            ),
        });
    }
    // Fail on a bad profile or a missing Cura installation before the (slow) enhancement.
    let profile = profiles::load_profile(req.slicer, req.profile.as_deref())?;

    progress(SliceStep::Loading);
    let t = Instant::now();
    let loaded = crate::mesh::load(&req.model)?;
    timings.load_s = t.elapsed().as_secs_f64();

    // Enhance for the printed height; then scale to it (enhancement keeps the size roughly,
    // so scaling afterwards makes the printed height exact).
    let t = Instant::now();
    let lambda2 = req
        .strength_table
        .resolve(req.strength, Some(req.height_mm));
    let (mut mesh, report) = match lambda2 {
        Some(lambda2) => {
            let opts = EnhanceOptions {
                lambda1: 0.0,
                lambda2,
                mu: None,
            };
            let mut on_phase = |p: Phase| progress(SliceStep::Enhancing(p));
            let (mesh, report) = crate::enhance::enhance(&loaded.mesh, &opts, &mut on_phase)
                .map_err(|source| SliceError::Enhance {
                    model: req.model.clone(),
                    source,
                })?;
            if let Some(dir) = &req.pictures {
                draw_pictures(&loaded.mesh, &mesh, req.up, dir);
            }
            (mesh, Some(report))
        }
        None => (loaded.mesh, None),
    };
    timings.enhance_s = t.elapsed().as_secs_f64();
    if req.up == UpAxis::Y {
        crate::mesh::place::turn_y_up(&mut mesh);
    }
    let size = place_on_bed(&mut mesh, req.height_mm, &req.model)?;

    progress(SliceStep::Slicing);
    let t = Instant::now();
    let work = tempfile::Builder::new()
        .prefix("crispen-slice-")
        .tempdir()
        .map_err(SliceError::io(
            "cannot create a temporary folder in",
            &std::env::temp_dir(),
        ))?;
    let stl_path = work.path().join("model.stl");
    {
        let file = std::fs::File::create(&stl_path)
            .map_err(SliceError::io("cannot write temporary STL", &stl_path))?;
        let mut w = std::io::BufWriter::new(file);
        crate::mesh::write_stl(&mut w, &mesh)
            .and_then(|_| std::io::Write::flush(&mut w))
            .map_err(SliceError::io("cannot write temporary STL", &stl_path))?;
    }
    if let Some(keep) = &req.keep_mesh {
        persist(&stl_path, keep)?;
    }
    let gcode_path = work.path().join("job.gcode");
    let job = profiles::JobParams {
        settings: &req.settings,
        nozzle_temp_c,
        bed_temp_c,
        height_mm: req.height_mm,
    };
    let invocation = profile.invocation(&job, work.path(), &stl_path, &gcode_path)?;
    let program = req
        .slicer_program
        .clone()
        .or_else(|| std::env::var_os(req.slicer.program_env()).map(PathBuf::from))
        .unwrap_or_else(|| PathBuf::from(req.slicer.default_program()));
    tracing::info!(slicer = %req.slicer, program = %program.display(), model = %req.model.display(), "slicing");
    let run = process::run(
        &program,
        &invocation.args,
        &invocation.env,
        req.timeout,
        req.cancel.as_deref(),
    );
    let outcome = match run {
        Ok(o) => o,
        Err(process::RunError::NotFound) => {
            return Err(SliceError::SlicerMissing {
                slicer: req.slicer,
                program,
                package: req.slicer.package(),
                env: req.slicer.program_env(),
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
                slicer: req.slicer,
                model: req.model.clone(),
                status: status.to_string(),
                output_tail,
            })
        }
        process::End::TimedOut => {
            return Err(SliceError::Timeout {
                slicer: req.slicer,
                model: req.model.clone(),
                after: req.timeout,
                output_tail,
            })
        }
        process::End::Cancelled => {
            return Err(SliceError::Cancelled {
                model: req.model.clone(),
            })
        }
    }

    progress(SliceStep::Checking);
    let t = Instant::now();
    let bad_output = |reason: String| SliceError::BadOutput {
        slicer: req.slicer,
        model: req.model.clone(),
        reason,
        output_tail: output_tail.clone(),
    };
    let file = std::fs::File::open(&gcode_path)
        .map_err(|e| bad_output(format!("no G-code file was written ({e})")))?;
    let expect = gcode::Expectations {
        bed_mm: BED_MM,
        height_mm: req.height_mm,
        layer_height_mm: req.settings.layer_height_mm,
    };
    let stats = gcode::check(std::io::BufReader::new(file), &expect).map_err(bad_output)?;
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
            let r_cm = 0.285 / 2.0;
            mm / 10.0 * std::f64::consts::PI * r_cm * r_cm * material.density_g_cm3
        })
    });

    if req.pictures.is_some() {
        // A picture is a nicety: a job is never failed for want of one.
        let blocks = crate::preview::thumbnail::blocks(&mesh, UpAxis::Z);
        if let Err(e) = crate::preview::thumbnail::insert_into_file(&gcode_path, &blocks) {
            tracing::warn!(error = %e, "cannot put thumbnails into the G-code");
        }
    }
    persist(&gcode_path, &req.output)?;
    timings.total_s = started.elapsed().as_secs_f64();
    Ok(SliceReport {
        model: req.model.clone(),
        output: req.output.clone(),
        height_mm: req.height_mm,
        up: req.up,
        enhancement: EnhancementSummary {
            lambda2,
            mode: if lambda2.is_some() {
                "enhanced"
            } else {
                "unmodified"
            }
            .to_string(),
            report,
        },
        slicer: req.slicer,
        slicer_version: stats.slicer_version,
        material: material.name.to_string(),
        nozzle_temp_c,
        bed_temp_c,
        model_size_mm: size,
        timings,
        layer_count: stats.layer_count,
        layer_height_mm: stats.layer_height_mm,
        top_layer_z_mm: stats.top_z_mm,
        estimated_print_time_s,
        filament_mm,
        filament_g,
        gcode_lines: stats.lines,
    })
}

/// Side of the before/after pictures of a job, pixels.
pub const PICTURE_SIZE: u32 = 600;

/// Draws the before/after pictures and the heat map into `dir`; failures are logged, not
/// returned (see [`SliceRequest::pictures`]).
fn draw_pictures(before: &Mesh, after: &Mesh, up: UpAxis, dir: &Path) {
    let t = Instant::now();
    let Some(pictures) = crate::preview::pictures(before, after, up, PICTURE_SIZE) else {
        tracing::warn!("no pictures: the enhanced mesh does not match the model's vertices");
        return;
    };
    match pictures.save(dir) {
        Ok(_) => {
            tracing::info!(dir = %dir.display(), seconds = t.elapsed().as_secs_f64(), "pictures drawn")
        }
        Err(e) => tracing::warn!(dir = %dir.display(), error = %e, "cannot write the pictures"),
    }
}

/// Places the mesh on the Ultimaker 2's bed at `height_mm` tall, keeping room for the
/// skirt (see [`crate::mesh::place::place_on_bed`]). Returns its size (X, Y, Z) in mm.
pub fn place_on_bed(mesh: &mut Mesh, height_mm: f64, model: &Path) -> Result<[f64; 3], SliceError> {
    let fits = [
        BED_MM[0] - 2.0 * SKIRT_MARGIN_MM,
        BED_MM[1] - 2.0 * SKIRT_MARGIN_MM,
        BED_MM[2],
    ];
    crate::mesh::place::place_on_bed(mesh, height_mm, fits).map_err(|e| match e {
        PlaceError::Empty => SliceError::EmptyModel {
            model: model.to_path_buf(),
        },
        PlaceError::TooBig { size_mm, max_mm } => SliceError::TooBig {
            model: model.to_path_buf(),
            height_mm,
            size_mm,
            max_mm,
        },
    })
}

/// Copies a finished file (checked G-code, the mesh that was sliced) to its destination
/// without ever leaving a half-written one there: copy next to it, then rename over it.
fn persist(from: &Path, to: &Path) -> Result<(), SliceError> {
    let dir = match to.parent() {
        Some(p) if !p.as_os_str().is_empty() => p,
        _ => Path::new("."),
    };
    let mut tmp = tempfile::Builder::new()
        .prefix(".crispen-")
        .suffix(".part")
        .tempfile_in(dir)
        .map_err(SliceError::io("cannot write into", dir))?;
    let mut src = std::fs::File::open(from).map_err(SliceError::io("cannot read", from))?;
    std::io::copy(&mut src, tmp.as_file_mut()).map_err(SliceError::io("cannot write", to))?;
    // Temporary files are private (0600); a job's files are ordinary files others may read.
    {
        use std::os::unix::fs::PermissionsExt;
        let _ = tmp
            .as_file()
            .set_permissions(std::fs::Permissions::from_mode(0o644));
    }
    tmp.as_file()
        .sync_all()
        .map_err(SliceError::io("cannot write", to))?;
    tmp.persist(to).map_err(|e| SliceError::Io {
        context: "cannot write",
        path: to.to_path_buf(),
        source: e.error,
    })?;
    Ok(())
}
