//! A job's way through preparation, as its steps: load the model ([`crate::mesh::load`]),
//! enhance it for the printed height ([`crate::enhance`]) once, place it on a bed
//! ([`crate::mesh::place`]), then for each machine that may print it check it fits that
//! machine's bed and slice it ([`crate::slice::slice_mesh`]). The enhancement depends on
//! the height, not the machine, so it is shared; the slicing is once per machine.

pub mod observed;

use crate::enhance::{
    Bands, Displacements, EnhanceOptions, Mode, Phase, PrintResolution, Strength, StrengthTable,
};
use crate::machine::Machine;
use crate::mesh::place::{PlaceError, UpAxis};
use crate::mesh::Mesh;
use crate::slice::moved::WallsState;
use crate::slice::{
    EnhancementSummary, SliceError, SliceJob, SliceReport, SliceSettings, SliceStep, SlicerKind,
    HEIGHT_MM,
};
use std::path::{Path, PathBuf};
use std::sync::atomic::AtomicBool;
use std::sync::Arc;
use std::time::{Duration, Instant};

/// One model to prepare: what is shared by every machine it is sliced for.
#[derive(Clone, Debug)]
pub struct SliceRequest {
    pub model: PathBuf,
    /// Printed height of the model (its Z extent on the bed), mm.
    pub height_mm: f64,
    pub slicer: SlicerKind,
    pub strength: Strength,
    pub strength_table: StrengthTable,
    pub settings: SliceSettings,
    /// A profile replacing the machine's: PrusaSlicer `.ini`, or CuraEngine `.toml`.
    pub profile: Option<PathBuf>,
    /// Each slicer run is killed and fails after this long.
    pub timeout: Duration,
    /// Program to run instead of the slicer's usual one (see [`SliceJob::slicer_program`]).
    pub slicer_program: Option<PathBuf>,
    /// Set to true from another thread to stop the job (the slicer is killed).
    pub cancel: Option<Arc<AtomicBool>>,
    /// The model's up axis (default Z).
    pub up: UpAxis,
    /// Where to draw the model before and after enhancement and the displacement's heat
    /// map (`crate::preview`, only when it is enhanced; in print-aware mode, as enhanced
    /// for the first machine); with it, the G-code also gets PrusaSlicer-format thumbnails
    /// of the part as printed.
    pub pictures: Option<PathBuf>,
    /// Also slice the model unmodified for each machine and compare the two jobs' outer
    /// walls (`SliceReport::walls`, [`crate::slice::walls`]); with `pictures`, draw a few
    /// layers of both for the first machine. Only for an enhanced model. `crispen slice
    /// --compare` asks for it; the daemon never does (it would nearly double a job's
    /// preparation): it measures a ready job later, with [`compare_prepared`].
    pub compare: bool,
    /// Where to draw the print as the printer will lay it, from the G-code
    /// ([`crate::preview::print`], `preview.png`), for the first machine: beside the
    /// unmodified print for an enhanced model (sliced for it as `compare` does, which this
    /// implies), alone for one printed unmodified. The daemon never asks it of a
    /// preparation: it draws a ready job's, with [`compare_prepared`] or [`draw_preview`].
    pub preview: Option<PathBuf>,
    /// The paper's enhancement, or the print-aware one (bands and strength from each
    /// machine's nozzle and layer height, [`crate::enhance::print_aware`]; an explicit
    /// strength is then ignored, `Off` still prints unmodified).
    pub mode: Mode,
    /// Copies of the model side by side on one bed, each a part of the plate
    /// ([`crate::slice::plate`]).
    pub per_plate: u32,
    /// With `strength` [`Strength::Observed`]: the observer's reference size and time
    /// bound ([`observed`]).
    pub observe: observed::ObserveSettings,
}

impl SliceRequest {
    /// A request with the defaults: PrusaSlicer, automatic strength, the machine's
    /// profile, 10 minute timeout.
    pub fn new(model: impl Into<PathBuf>, height_mm: f64) -> Self {
        SliceRequest {
            model: model.into(),
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
            pictures: None,
            compare: false,
            preview: None,
            mode: Mode::default(),
            per_plate: 1,
            observe: observed::ObserveSettings::default(),
        }
    }
}

/// A machine to slice for, and where its G-code goes.
#[derive(Clone, Debug)]
pub struct Target {
    pub machine: Machine,
    pub output: PathBuf,
    /// Where to keep the mesh that was sliced (enhanced, scaled and placed), binary STL.
    pub keep_mesh: Option<PathBuf>,
}

/// Where a preparation is, for progress displays.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum Step<'a> {
    Loading,
    Enhancing(Phase),
    /// Slicing or checking for the named machine.
    Slice(&'a str, SliceStep),
    /// Slicing the unmodified model for the named machine and comparing the G-code.
    Comparing(&'a str),
    /// Choosing the strength by looking ([`observed`]).
    Observing(observed::Observing),
}

impl Step<'_> {
    /// The step as `crispen status` shows it.
    pub fn describe(self) -> String {
        match self {
            Step::Loading => "loading".into(),
            Step::Enhancing(Phase::Operators) => "enhancing: operators".into(),
            Step::Enhancing(Phase::Factorize) => "enhancing: factorizing".into(),
            Step::Enhancing(Phase::Solve(i)) => format!("enhancing: solve {i}"),
            Step::Enhancing(Phase::Combine) => "enhancing: combining".into(),
            Step::Slice(m, SliceStep::Slicing) => format!("slicing for {m}"),
            Step::Slice(m, SliceStep::Checking) => format!("checking the G-code for {m}"),
            Step::Comparing(m) => format!("slicing the unmodified model for {m} to compare"),
            Step::Observing(observed::Observing::Reference) => {
                "observing: slicing the model at the reference size".into()
            }
            Step::Observing(observed::Observing::Candidate(i, n)) => {
                format!("observing: making candidate {i} of {n}")
            }
            Step::Observing(observed::Observing::Looking(i, n)) => {
                format!("observing: looking from view {i} of {n}")
            }
        }
    }
}

/// What one machine got: its G-code's report, or why it cannot print the job.
pub(crate) type MachineResult = (String, Result<SliceReport, SliceError>);

/// Prepares a model for each target machine: load, enhance (once), place, then per
/// machine check the fit and slice. An error of the shared steps (the model cannot be
/// read or enhanced, a bad setting) is the whole job's; a model too big for one machine,
/// or a slicer failing for it, is that machine's. Blocking.
pub fn prepare(
    req: &SliceRequest,
    targets: &[Target],
    progress: &mut dyn FnMut(Step),
) -> Result<Vec<MachineResult>, SliceError> {
    let started = Instant::now();
    req.settings.validate()?;
    req.settings.temperatures()?;
    // Too tall for a machine is reported by the fit check, with the model's size.
    if !(req.height_mm.is_finite() && HEIGHT_MM.contains(&req.height_mm)) {
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
    for t in targets {
        let path = req.profile.as_deref().or(match req.slicer {
            SlicerKind::Prusa => t.machine.prusa_profile.as_deref(),
            SlicerKind::Cura => t.machine.cura_profile.as_deref(),
        });
        crate::slice::load_profile(req.slicer, path)?;
    }

    progress(Step::Loading);
    let t = Instant::now();
    let loaded = crate::mesh::load(&req.model)?;
    let load_s = t.elapsed().as_secs_f64();
    let models = Models::of(req, loaded)?;
    let original = &models.0[0].mesh;

    // `strength = "observed"`: the observer settles the strength and the mode first, for
    // the first machine, whose G-code is then the chosen print as the observer made it.
    let mut chosen = match req.strength {
        Strength::Observed if models.0.len() > 1 => {
            return Err(SliceError::BadSetting {
                key: "strength".into(),
                value: "observed".into(),
                hint: format!(
                    "the observer chooses the strength of one model, and {} holds a plate of {} \
                     objects: give the job a strength (\"auto\" or a number)",
                    req.model.display(),
                    models.0.len()
                ),
            })
        }
        Strength::Observed => Some(observed::choose(req, original, targets.first(), progress)?),
        _ => None,
    };
    let (mut adopted, mut made_placed) = match chosen.as_mut().and_then(|c| c.made.take()) {
        Some(m) => (Some(m.report), Some(m.placed)),
        None => (None, None),
    };
    let req = chosen.as_ref().map_or(req, |c| &c.req);
    let observation = chosen.as_ref().and_then(|c| c.observation.clone());

    // The paper's enhancement depends on the printed height only, so it is shared by every
    // machine; the print-aware one on each machine's nozzle and layer height.
    let print_aware = req.mode == Mode::PrintAware
        && req
            .strength_table
            .resolve(req.strength, Some(req.height_mm))
            .is_some();
    let layer_height_mm = req
        .settings
        .layer_height_mm
        .unwrap_or(crate::slice::DEFAULT_LAYER_HEIGHT_MM);
    let printer_of = |machine: &crate::machine::Machine| PrintResolution {
        nozzle_mm: machine.nozzle_mm,
        layer_height_mm,
    };
    // Each model of the job, placed: one, or a plate's several (the first is the tallest).
    let mut shared: Option<Vec<Placed>> = None;
    let mut per_printer: Vec<(PrintResolution, Vec<Placed>)> = Vec::new();
    match (made_placed.take(), targets.first()) {
        (Some(p), Some(first)) if print_aware => {
            per_printer.push((printer_of(&first.machine), vec![p]))
        }
        (Some(p), _) => shared = Some(vec![p]),
        (None, _) => {}
    }
    if !print_aware && shared.is_none() {
        shared = Some(models.place(req, None, req.pictures.as_deref(), progress)?);
    }

    // A plate of several models is neither compared nor drawn beside its model: the
    // unmodified print would be one model, and the preview's mesh is one.
    let plain = if (req.compare || req.preview.is_some()) && models.0.len() == 1 {
        placed_plain(req, original.clone()).ok()
    } else {
        None
    };

    let mut results = Vec::with_capacity(targets.len());
    for (index, target) in targets.iter().enumerate() {
        let machine = &target.machine;
        let plate: &[Placed] = match &shared {
            Some(p) => p,
            None => {
                let printer = printer_of(machine);
                let known = per_printer.iter().position(|(p, _)| *p == printer);
                let at = match known {
                    Some(at) => at,
                    // The pictures are the first machine's, as the job's report is.
                    None => match models.place(
                        req,
                        Some(printer),
                        req.pictures.as_deref().filter(|_| per_printer.is_empty()),
                        progress,
                    ) {
                        Ok(p) => {
                            per_printer.push((printer, p));
                            per_printer.len() - 1
                        }
                        Err(e) => {
                            tracing::warn!(machine = %machine.name, error = %e, "cannot prepare the job for this machine");
                            results.push((machine.name.clone(), Err(e)));
                            continue;
                        }
                    },
                };
                &per_printer[at].1
            }
        };
        // The tallest model stands for the plate in the report's enhancement and pictures.
        let placed = &plate[0];
        let compare = plain.as_ref().filter(|_| placed.summary.lambda2.is_some());
        let sliced = plate
            .iter()
            .try_for_each(|p| crate::mesh::place::check_fits(p.size, machine.fits_mm()))
            .map_err(|e| place_error(e, req, &machine.name))
            .and_then(|()| {
                // The observer's chosen print, made for this machine: its G-code is the job's.
                if let Some(report) = adopted.take().filter(|_| index == 0) {
                    let report = observed::adopt(report, &target.output)?;
                    if let Some(path) = &target.keep_mesh {
                        keep_mesh(&placed.mesh, path)?;
                    }
                    if req.pictures.is_some() {
                        add_thumbnails(&placed.mesh, &target.output);
                    }
                    return Ok(report);
                }
                let job = SliceJob {
                    keep_mesh: target.keep_mesh.as_deref(),
                    ..slice_job(req, machine, &target.output)
                };
                let parts: Vec<crate::slice::plate::PlatePart> = models
                    .0
                    .iter()
                    .zip(plate)
                    .map(|(model, p)| crate::slice::plate::PlatePart {
                        name: &model.name,
                        mesh: &p.mesh,
                    })
                    .collect();
                let report = crate::slice::slice_plate(&parts, &job, &mut |s| {
                    progress(Step::Slice(&machine.name, s))
                })?;
                if req.pictures.is_some() {
                    add_thumbnails(&placed.mesh, &target.output);
                }
                Ok(report)
            })
            .map(|mut report| {
                report.up = req.up;
                report.enhancement = placed.summary.clone();
                report.enhancement.observed = observation.clone();
                report.enhancement.printed = placed.displacements.as_ref().map(|d| {
                    let printer = PrintResolution {
                        nozzle_mm: machine.nozzle_mm,
                        layer_height_mm: report.layer_height_mm.unwrap_or(layer_height_mm),
                    };
                    d.summary(placed.scale, req.height_mm, Some(printer))
                });
                if let Some(plain) = compare {
                    progress(Step::Comparing(&machine.name));
                    let first = |dir: &Option<PathBuf>| dir.clone().filter(|_| index == 0);
                    let drawn = Drawn {
                        pictures: first(&req.pictures),
                        preview: first(&req.preview),
                    };
                    report.walls = compare_walls(req, plain, machine, &report.output, &drawn)
                        .map_err(|e| tracing::warn!(machine = %machine.name, error = %e, "no wall comparison"))
                        .ok();
                } else if let Some(dir) = req.preview.as_deref().filter(|_| index == 0) {
                    // Printed unmodified: its own G-code is the plain print.
                    draw_preview(dir, Some(&placed.mesh), machine, &report.output, None);
                }
                // Asked for (by --preview too) and not made: the warning above says why.
                report.walls_state = if req.compare || req.preview.is_some() {
                    WallsState::NotMeasured
                } else {
                    WallsState::NotAsked
                };
                // What the plate's largest model takes on each axis.
                report.model_size_mm = plate.iter().fold([0.0; 3], |size, p| {
                    [0, 1, 2].map(|k| size[k].max(p.size[k]))
                });
                report.timings.load_s = load_s;
                report.timings.enhance_s = plate.iter().map(|p| p.enhance_s).sum();
                report.timings.total_s = started.elapsed().as_secs_f64();
                report
            });
        if let Err(e) = &sliced {
            tracing::warn!(machine = %machine.name, error = %e, "cannot prepare the job for this machine");
        }
        results.push((machine.name.clone(), sliced));
    }
    Ok(results)
}

/// One model of a job: its name (a part of the plate's label) and the printed height it
/// gets.
#[derive(Debug)]
struct Model {
    name: String,
    mesh: Mesh,
    height_mm: f64,
}

/// The models a job prints: the file's one model at the job's height, or the objects of
/// a 3MF whose build places several, tallest first, as one plate: scaled alike so that
/// the tallest is the job's height (a set of parts keeps its proportions), each enhanced
/// for its own printed height and arranged on the bed by the slicer.
#[derive(Debug)]
struct Models(Vec<Model>);

impl Models {
    fn of(req: &SliceRequest, loaded: crate::mesh::LoadedMesh) -> Result<Models, SliceError> {
        if loaded.objects.is_empty() {
            let name = req
                .model
                .file_stem()
                .map_or_else(|| "model".to_string(), |s| s.to_string_lossy().into_owned());
            return Ok(Models(vec![Model {
                name,
                mesh: loaded.mesh,
                height_mm: req.height_mm,
            }]));
        }
        // Each object is enhanced on its own: as many as a plate may hold copies, no more.
        let max = crate::slice::plate::MAX_PER_PLATE as usize;
        let copies = loaded.objects.len() * req.per_plate.max(1) as usize;
        if copies > max {
            return Err(SliceError::BadSetting {
                key: "per_plate".into(),
                value: req.per_plate.to_string(),
                hint: format!(
                    "{} holds a plate of {} objects, {copies} parts with {} of each: a plate \
                     holds at most {max} (split the file, or lower per_plate)",
                    req.model.display(),
                    loaded.objects.len(),
                    req.per_plate
                ),
            });
        }
        // The extent along the model's up axis, which becomes its printed height.
        let up = match req.up {
            UpAxis::Z => 2,
            UpAxis::Y => 1,
        };
        let mut models: Vec<(Model, f64)> = loaded
            .objects
            .iter()
            .map(|object| {
                let mesh = loaded.mesh.sub(object.faces.clone());
                let extent = mesh.bounds().map_or(0.0, |(lo, hi)| hi[up] - lo[up]);
                let model = Model {
                    name: object.name.clone(),
                    mesh,
                    height_mm: 0.0,
                };
                (model, extent)
            })
            .collect();
        models.sort_by(|a, b| b.1.total_cmp(&a.1));
        let tallest = models[0].1;
        let mut out = Vec::with_capacity(models.len());
        for (mut model, extent) in models {
            model.height_mm = req.height_mm * extent / tallest;
            if !(model.height_mm >= *HEIGHT_MM.start()) {
                return Err(SliceError::BadSetting {
                    key: "height".into(),
                    value: req.height_mm.to_string(),
                    hint: format!(
                        "{}: object {:?} would print {:.2} mm tall beside the tallest at {} mm, \
                         under the least printed height of {} mm: print it larger, or on a \
                         plate of its own",
                        req.model.display(),
                        model.name,
                        model.height_mm,
                        req.height_mm,
                        HEIGHT_MM.start()
                    ),
                });
            }
            out.push(model);
        }
        Ok(Models(out))
    }

    /// Enhances each model (for `printer` in print-aware mode) and places it; the first
    /// model's pictures go into `pictures`.
    fn place(
        &self,
        req: &SliceRequest,
        printer: Option<PrintResolution>,
        pictures: Option<&Path>,
        progress: &mut dyn FnMut(Step),
    ) -> Result<Vec<Placed>, SliceError> {
        self.0
            .iter()
            .enumerate()
            .map(|(i, model)| {
                let req = &SliceRequest {
                    height_mm: model.height_mm,
                    ..req.clone()
                };
                let pictures = pictures.filter(|_| i == 0);
                place(req, &model.mesh, printer, pictures, None, progress)
            })
            .collect()
    }
}

/// A mesh enhanced (for a printer, in print-aware mode) and placed on the bed.
struct Placed {
    mesh: Mesh,
    size: [f64; 3],
    /// Model units → printed mm.
    scale: f64,
    summary: EnhancementSummary,
    displacements: Option<Displacements>,
    enhance_s: f64,
    /// Its pictures, drawn while it is sliced.
    _pictures: Drawing,
}

/// Pictures drawn on a thread of their own, beside the slicing: a job's slicer need not
/// wait for them. Joined when dropped, so that none is left half-written when the
/// preparation (and its process) ends.
struct Drawing(Option<std::thread::JoinHandle<()>>);

impl Drop for Drawing {
    fn drop(&mut self) {
        if let Some(thread) = self.0.take() {
            // A panic in a picture was the picture's; the job stands without it.
            let _ = thread.join();
        }
    }
}

/// Enhances `original` (for `printer` in print-aware mode; from `bands`, `original`'s,
/// when they are at hand in the paper's mode), turns it upright and places it; draws its
/// pictures into `pictures` meanwhile.
fn place(
    req: &SliceRequest,
    original: &Mesh,
    printer: Option<PrintResolution>,
    pictures: Option<&Path>,
    bands: Option<&Bands>,
    progress: &mut dyn FnMut(Step),
) -> Result<Placed, SliceError> {
    let t = Instant::now();
    let (mut mesh, summary, displacements, pictures) =
        enhance(req, original.clone(), printer, pictures, bands, progress)?;
    let enhance_s = t.elapsed().as_secs_f64();
    if req.up == UpAxis::Y {
        crate::mesh::place::turn_y_up(&mut mesh);
    }
    // Model units → printed mm, as place_on_bed is about to scale it.
    let scale = mesh
        .bounds()
        .map(|(lo, hi)| hi[2] - lo[2])
        .filter(|z| *z > 0.0)
        .map_or(1.0, |z| req.height_mm / z);
    let size = crate::mesh::place::place_on_bed(&mut mesh, req.height_mm, [f64::INFINITY; 3])
        .map_err(|e| place_error(e, req, "any machine"))?;
    Ok(Placed {
        mesh,
        size,
        scale,
        summary,
        displacements,
        enhance_s,
        _pictures: pictures,
    })
}

/// The slicing of `req` for `machine` into `output`, as both the job's and the comparison's
/// slicings share it: no mesh kept, the whole G-code.
fn slice_job<'a>(
    req: &'a SliceRequest,
    machine: &'a crate::machine::Machine,
    output: &'a Path,
) -> SliceJob<'a> {
    SliceJob {
        model: &req.model,
        output,
        machine,
        height_mm: req.height_mm,
        slicer: req.slicer,
        settings: &req.settings,
        profile: req.profile.as_deref(),
        timeout: req.timeout,
        slicer_program: req.slicer_program.as_deref(),
        cancel: req.cancel.as_deref(),
        keep_mesh: None,
        measure_only: false,
        per_plate: req.per_plate,
    }
}

/// Writes the mesh that was sliced to `path` (binary STL), as a slicing keeps it.
fn keep_mesh(mesh: &Mesh, path: &Path) -> Result<(), SliceError> {
    crate::fsutil::write_atomic_with(path, |file| {
        let mut w = std::io::BufWriter::new(file);
        crate::mesh::write_stl(&mut w, mesh)?;
        std::io::Write::flush(&mut w)
    })
    .map_err(|e| SliceError::Io {
        context: "cannot write",
        path: path.to_path_buf(),
        source: e.into(),
    })
}

/// Puts PrusaSlicer-format thumbnails of the part as sliced (Z up) into its G-code, after
/// the slicer's checks passed (the file is replaced whole). A picture is a nicety: a job
/// is never failed for want of one.
fn add_thumbnails(mesh: &Mesh, gcode: &Path) {
    let blocks = crate::preview::thumbnail::blocks(mesh, UpAxis::Z);
    if let Err(e) = crate::preview::thumbnail::insert_into_file(gcode, &blocks) {
        tracing::warn!(error = %e, gcode = %gcode.display(), "cannot put thumbnails into the G-code");
    }
}

/// Why a wall comparison was not made. A comparison is a measurement, not part of the
/// job: its failure is the measurement's, never the job's.
#[derive(Debug, thiserror::Error)]
pub(crate) enum CompareError {
    #[error("cannot slice the unmodified model to compare: {0}")]
    Plain(#[source] SliceError),
    #[error("cannot read the G-code to compare, {path}: {source}")]
    Read {
        path: PathBuf,
        #[source]
        source: std::io::Error,
    },
    #[error("a plate of {0} models is not compared with one unmodified model")]
    Plate(usize),
    #[error("no temporary folder to compare in: {0}")]
    Work(#[source] std::io::Error),
}

/// The model unmodified, turned and placed as [`place`] places the enhanced one, so both
/// G-codes share one frame.
fn placed_plain(req: &SliceRequest, mut mesh: Mesh) -> Result<Mesh, SliceError> {
    if req.up == UpAxis::Y {
        crate::mesh::place::turn_y_up(&mut mesh);
    }
    crate::mesh::place::place_on_bed(&mut mesh, req.height_mm, [f64::INFINITY; 3])
        .map_err(|e| place_error(e, req, "any machine"))?;
    Ok(mesh)
}

/// The comparison of a job already prepared (the daemon measures it after the job is
/// ready, see `daemon::prepare::queue`): loads the model, places it unmodified as
/// [`prepare`] placed the enhanced one, and compares the outer walls of its slicing for
/// `machine` with `enhanced_gcode`'s; with `pictures`, draws a few layers of both there.
/// Blocking.
pub(crate) fn compare_prepared(
    req: &SliceRequest,
    machine: &Machine,
    enhanced_gcode: &Path,
    drawn: &Drawn,
) -> Result<crate::slice::walls::WallComparison, CompareError> {
    let loaded = crate::mesh::load(&req.model).map_err(|e| CompareError::Plain(e.into()))?;
    if !loaded.objects.is_empty() {
        return Err(CompareError::Plate(loaded.objects.len()));
    }
    let plain = placed_plain(req, loaded.mesh).map_err(CompareError::Plain)?;
    compare_walls(req, &plain, machine, enhanced_gcode, drawn)
}

/// The preview of a job printed unmodified or pre-sliced, already prepared (the daemon
/// draws it after the job is ready, see `daemon::prepare::queue`): loads the model, places
/// it as [`prepare`] placed it, and draws it beside its print from `gcode` into `dir` (a
/// pre-sliced job's print alone). A picture
/// that cannot be drawn is logged; the job stands without it. Blocking.
pub(crate) fn preview_prepared(req: &SliceRequest, machine: &Machine, gcode: &Path, dir: &Path) {
    let name = req.model.file_name().unwrap_or_default().to_string_lossy();
    // A pre-sliced job has no model: its print is drawn alone.
    if super::task::is_presliced(&name) {
        return draw_preview(dir, None, machine, gcode, None);
    }
    let mesh = crate::mesh::load(&req.model)
        .map_err(SliceError::from)
        .and_then(|loaded| match loaded.objects.is_empty() {
            true => placed_plain(req, loaded.mesh).map(Some),
            // A plate of several models: its print alone, as no one mesh stands beside it.
            false => Ok(None),
        });
    match mesh {
        Ok(mesh) => draw_preview(dir, mesh.as_ref(), machine, gcode, None),
        Err(e) => tracing::warn!(machine = %machine.name, error = %e, "no preview of the print"),
    }
}

/// Where the pictures of a comparison go: the walls of a few layers into `pictures`, the
/// preview of both prints into `preview` (either may be None).
#[derive(Clone, Debug, Default)]
pub(crate) struct Drawn {
    pub pictures: Option<PathBuf>,
    pub preview: Option<PathBuf>,
}

/// Draws [`crate::preview::PREVIEW_PNG`] into `dir` from `plain_gcode` (and the enhanced
/// print's, when there is one) beside the placed `mesh`; a failure is logged, never the
/// job's.
fn draw_preview(
    dir: &Path,
    mesh: Option<&Mesh>,
    machine: &Machine,
    plain_gcode: &Path,
    enhanced_gcode: Option<&Path>,
) {
    let drawn = crate::preview::print::draw_preview(
        dir,
        mesh,
        plain_gcode,
        enhanced_gcode,
        crate::enhance::line_width_mm(machine.nozzle_mm),
    );
    if let Err(e) = drawn {
        tracing::warn!(machine = %machine.name, error = %e, "no preview of the print");
    }
}

/// Slices the placed, unmodified mesh as the enhanced one was and compares the two jobs'
/// outer walls; draws a few layers of both and the preview of both prints where `drawn`
/// says (a picture that cannot be written is logged: the figures stand without it).
fn compare_walls(
    req: &SliceRequest,
    plain: &Mesh,
    machine: &Machine,
    enhanced_gcode: &Path,
    drawn: &Drawn,
) -> Result<crate::slice::walls::WallComparison, CompareError> {
    use crate::slice::walls;
    let started = Instant::now();
    let work = tempfile::Builder::new()
        .prefix("crispen-compare-")
        .tempdir()
        .map_err(CompareError::Work)?;
    let output = work.path().join("plain.gcode");
    let job = SliceJob {
        measure_only: true,
        ..slice_job(req, machine, &output)
    };
    crate::slice::slice_mesh(plain, &job, &mut |_| {}).map_err(CompareError::Plain)?;
    let read = |path: &Path| {
        std::fs::File::open(path)
            .map(std::io::BufReader::new)
            .and_then(walls::outer_walls)
            .map_err(|source| CompareError::Read {
                path: path.to_path_buf(),
                source,
            })
    };
    let (plain_walls, enhanced_walls) = (read(&output)?, read(enhanced_gcode)?);
    let comparison = walls::compare(
        &plain_walls,
        &enhanced_walls,
        crate::enhance::line_width_mm(machine.nozzle_mm),
    );
    if let Some(dir) = &drawn.preview {
        draw_preview(dir, Some(plain), machine, &output, Some(enhanced_gcode));
    }
    if let Some(dir) = &drawn.pictures {
        let layers = crate::preview::walls::layers_to_show(&comparison, WALL_LAYERS_SHOWN);
        let drawn = crate::preview::walls::walls_picture(
            &plain_walls,
            &enhanced_walls,
            &layers,
            PICTURE_SIZE,
        );
        if let Some(image) = drawn {
            let path = dir.join(crate::preview::walls::WALLS_PNG);
            if let Err(e) = crate::preview::write_png(&path, &image) {
                tracing::warn!(file = %path.display(), error = %e, "cannot write the walls picture");
            }
        }
    }
    tracing::info!(
        machine = %machine.name,
        mean_mm = comparison.mean_mm,
        p95_mm = comparison.p95_mm,
        share_over_0_1_mm = comparison.share_over_0_1_mm,
        seconds = started.elapsed().as_secs_f64(),
        "compared the outer walls with the unmodified model's"
    );
    Ok(comparison)
}

/// How many layers the walls picture shows.
pub(crate) const WALL_LAYERS_SHOWN: usize = 3;

/// [`prepare`] for one machine, its error the job's.
pub fn prepare_one(
    req: &SliceRequest,
    target: Target,
    progress: &mut dyn FnMut(Step),
) -> Result<SliceReport, SliceError> {
    let mut results = prepare(req, std::slice::from_ref(&target), progress)?;
    results.pop().expect("one result per target").1
}

/// The enhancement step: for the printed height, or none when the strength says so; with
/// how far each vertex moved, for the printed figures, and its pictures being drawn into
/// `pictures` (see [`Drawing`]). The paper's mode combines `bands` (the mesh's) when given
/// rather than computing them.
fn enhance(
    req: &SliceRequest,
    mesh: Mesh,
    printer: Option<PrintResolution>,
    pictures: Option<&Path>,
    bands: Option<&Bands>,
    progress: &mut dyn FnMut(Step),
) -> Result<(Mesh, EnhancementSummary, Option<Displacements>, Drawing), SliceError> {
    let lambda2 = req
        .strength_table
        .resolve(req.strength, Some(req.height_mm));
    let Some(lambda2) = lambda2 else {
        let summary = EnhancementSummary {
            lambda2: None,
            mode: "unmodified".into(),
            report: None,
            printed: None,
            print_aware: None,
            observed: None,
        };
        return Ok((mesh, summary, None, Drawing(None)));
    };
    let mut on_phase = |p: Phase| progress(Step::Enhancing(p));
    let failed = |source| SliceError::Enhance {
        model: req.model.clone(),
        source,
    };
    let (enhanced, report, lambda2, mode, print_aware) = match printer {
        Some(printer) => {
            // The printed scale before enhancing: the model's extent along its up axis.
            let axis = if req.up == UpAxis::Y { 1 } else { 2 };
            let extent = mesh.bounds().map_or(0.0, |(lo, hi)| hi[axis] - lo[axis]);
            let scale = req.height_mm / extent;
            let (enhanced, report, chosen) =
                crate::enhance::print_aware::enhance(&mesh, scale, printer, lambda2, &mut on_phase)
                    .map_err(failed)?;
            tracing::info!(
                nozzle_mm = printer.nozzle_mm,
                band_mm = ?chosen.band_mm,
                lambda2 = chosen.lambda2,
                share = chosen.share,
                target_share = chosen.target_share,
                limited_by = ?chosen.limited_by,
                "print-aware enhancement"
            );
            let lambda2 = chosen.lambda2;
            (
                enhanced,
                report,
                lambda2,
                "enhanced (print-aware)",
                Some(chosen),
            )
        }
        None => {
            let opts = EnhanceOptions {
                lambda1: 0.0,
                lambda2,
                mu: None,
            };
            let (enhanced, report) = match bands {
                Some(bands) => {
                    on_phase(Phase::Combine);
                    let t = Instant::now();
                    let combined = opts
                        .validate()
                        .and_then(|()| bands.combine(&opts))
                        .map_err(failed)?;
                    crate::enhance::finish(&mesh, bands, combined, opts.lambda1, lambda2, t)
                }
                None => crate::enhance::enhance(&mesh, &opts, &mut on_phase).map_err(failed)?,
            };
            (enhanced, report, lambda2, "enhanced", None)
        }
    };
    let displacements = Displacements::between(&mesh, &enhanced);
    let pictures = Drawing(pictures.and_then(|dir| {
        let (dir, after, up) = (dir.to_path_buf(), enhanced.clone(), req.up);
        let span = tracing::Span::current();
        std::thread::Builder::new()
            .name("pictures".into())
            .spawn(move || {
                let _entered = span.enter();
                draw_pictures(&mesh, &after, up, &dir);
            })
            .map_err(|e| tracing::warn!(error = %e, "no pictures: cannot start a thread"))
            .ok()
    }));
    let summary = EnhancementSummary {
        lambda2: Some(lambda2),
        mode: mode.into(),
        report: Some(report),
        printed: None,
        print_aware,
        observed: None,
    };
    Ok((enhanced, summary, displacements, pictures))
}

fn place_error(e: PlaceError, req: &SliceRequest, machine: &str) -> SliceError {
    match e {
        PlaceError::Empty => SliceError::EmptyModel {
            model: req.model.clone(),
        },
        PlaceError::TooBig { size_mm, max_mm } => SliceError::TooBig {
            model: req.model.clone(),
            machine: machine.to_string(),
            height_mm: req.height_mm,
            size_mm,
            max_mm,
        },
    }
}

/// Side of the before/after pictures of a job, pixels.
pub(crate) const PICTURE_SIZE: u32 = 600;

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

#[cfg(test)]
mod tests {
    use super::*;
    use crate::mesh::{CleanReport, LoadedMesh, MeshFormat, MeshObject};

    /// `n` tetrahedra side by side, the `i`th `i + 1` units tall, each an object.
    fn plate_of(n: usize) -> LoadedMesh {
        let mut mesh = Mesh::default();
        let mut objects = Vec::new();
        for i in 0..n {
            let (x, h, base) = (3.0 * i as f64, (i + 1) as f64, mesh.vertices.len() as u32);
            mesh.vertices
                .extend([[x, 0., 0.], [x + 1., 0., 0.], [x, 1., 0.], [x, 0., h]]);
            let faces = mesh.faces.len();
            mesh.faces.extend(
                [[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 3]].map(|f: [u32; 3]| f.map(|v| v + base)),
            );
            objects.push(MeshObject {
                name: format!("t{i}"),
                faces: faces..faces + 4,
            });
        }
        LoadedMesh {
            mesh,
            format: MeshFormat::ThreeMf,
            clean: CleanReport::default(),
            objects,
        }
    }

    /// A plate's models: tallest first at the job's height, the others in proportion; a
    /// model that would print under the least height, or more models than a plate holds,
    /// refused with the file and the figures.
    #[test]
    fn a_plates_models_keep_their_proportions_within_bounds() {
        let req = SliceRequest::new("set.3mf", 30.0);
        let models = Models::of(&req, plate_of(3)).unwrap();
        let got: Vec<(&str, f64)> = models
            .0
            .iter()
            .map(|m| (m.name.as_str(), m.height_mm))
            .collect();
        assert_eq!(got, [("t2", 30.0), ("t1", 20.0), ("t0", 10.0)]);
        assert_eq!(models.0[2].mesh.faces.len(), 4);

        let small = SliceRequest::new("set.3mf", 2.0);
        let e = Models::of(&small, plate_of(3)).unwrap_err().to_string();
        assert!(
            e.contains("set.3mf") && e.contains("\"t0\"") && e.contains("0.67 mm"),
            "{e}"
        );

        let mut many = SliceRequest::new("set.3mf", 30.0);
        many.per_plate = 2;
        let e = Models::of(&many, plate_of(26)).unwrap_err().to_string();
        assert!(e.contains("26 objects") && e.contains("52 parts"), "{e}");
        Models::of(&many, plate_of(25)).unwrap();
    }
}
