//! The strength chosen by looking (a folder's or sidecar's `strength = "observed"`, and
//! `crispen observe`): the model is sliced unmodified at the reference size and once per
//! candidate at the job's height, each G-code read once, and the observer
//! ([`crate::observe`]) says how much each small print looks like the big one. Every
//! slicing is made once: the daemon prints the chosen candidate's G-code as sliced here
//! (for the job's first machine), the others are only measured.
//!
//! The time bound is the observer's own: past it, nothing is chosen and the job gets the
//! paper's table, as it would without `"observed"`; a failed reference slicing does the
//! same. A candidate that cannot be made (its slicing fails) is left out, with the reason.

use super::{place, placed_plain, slice_job, Placed, PrintResolution, SliceRequest, Step};
use crate::enhance::{Bands, Mode, Strength};
use crate::machine::Machine;
use crate::mesh::Mesh;
use crate::observe::{Conditions, ObserveError, OnBed};
use crate::preview::print::{read_print_file, Print};
use crate::slice::{SliceError, SliceJob, SliceReport};
use serde::{Deserialize, Serialize};

pub use crate::observation::{
    CandidateMode, Choice, Looked, Observation, ObserveSettings, DEFAULT_OBSERVE_TIMEOUT_S,
    OBSERVED_PNG,
};
use std::path::Path;
use std::time::{Duration, Instant};

/// One print the observer looks at.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct Candidate {
    pub mode: CandidateMode,
    /// The λ2 asked of the paper's method, or the strength the print-aware mode's target
    /// scales with (None: the height table's at the printed height).
    pub lambda2: Option<f64>,
}

impl Candidate {
    pub const PLAIN: Candidate = Candidate {
        mode: CandidateMode::Plain,
        lambda2: None,
    };

    /// What a folder's `strength = "observed"` chooses among: the plain print, the
    /// paper's light, medium and strong settings (λ2 = 10, 20, 40, its user study's), and
    /// the print-aware mode at the height table's strength.
    pub fn folder_set() -> Vec<Candidate> {
        let paper = |l: f64| Candidate {
            mode: CandidateMode::Paper,
            lambda2: Some(l),
        };
        vec![
            Candidate::PLAIN,
            paper(10.0),
            paper(20.0),
            paper(40.0),
            Candidate {
                mode: CandidateMode::PrintAware,
                lambda2: None,
            },
        ]
    }

    /// The candidates of `crispen observe --strengths ... --mode ...`: 0 is the plain print.
    pub fn from_strengths(strengths: &[f64], mode: Mode) -> Vec<Candidate> {
        strengths
            .iter()
            .map(|&l| match (l > 0.0, mode) {
                (false, _) => Candidate::PLAIN,
                (true, Mode::Paper) => Candidate {
                    mode: CandidateMode::Paper,
                    lambda2: Some(l),
                },
                (true, Mode::PrintAware) => Candidate {
                    mode: CandidateMode::PrintAware,
                    lambda2: Some(l),
                },
            })
            .collect()
    }

    /// The strength and mode a preparation makes it with.
    pub fn strength(&self) -> (Strength, Mode) {
        match self.mode {
            CandidateMode::Plain => (Strength::Off, Mode::Paper),
            CandidateMode::Paper => (
                self.lambda2.map_or(Strength::Auto, Strength::Lambda2),
                Mode::Paper,
            ),
            CandidateMode::PrintAware => (
                self.lambda2.map_or(Strength::Auto, Strength::Lambda2),
                Mode::PrintAware,
            ),
        }
    }
}

/// A candidate made and sliced, ready to be the job (see the module's comment).
pub(super) struct Made {
    pub(super) placed: Placed,
    pub(super) report: SliceReport,
}

/// How large the views are drawn into `observed.png`.
#[derive(Clone, Copy, Debug)]
pub enum PictureScale {
    /// At the observer's own resolution: the prints at their real size on the retina.
    RealSize,
    /// As large as fits this many pixels across (never larger than the real size).
    FitWidth(u32),
}

/// Where an observation's files go and how it is bounded.
pub struct ObserveJob<'a> {
    pub machine: &'a Machine,
    pub candidates: &'a [Candidate],
    pub settings: &'a ObserveSettings,
    pub conditions: &'a Conditions,
    /// Where the G-code of the reference and the candidates is written.
    pub work: &'a Path,
    /// The candidates are only measured (`crispen observe`): a G-code that would not pass
    /// as a job (an open scan's) is still looked at. The daemon makes them as jobs.
    pub measure_only: bool,
    /// Where to draw [`OBSERVED_PNG`], and how large.
    pub pictures: Option<(&'a Path, PictureScale)>,
}

/// Observes `original` (the model as loaded) printed at `req`'s height against the
/// reference size: see the module's comment. Always answers with an observation (a
/// failure is in it, see [`Choice`]), and for each candidate what was made of it; the one
/// error is the job's cancellation. Blocking.
pub(super) fn observe(
    req: &SliceRequest,
    original: &Mesh,
    job: &ObserveJob,
    bands: &mut Option<Bands>,
    progress: &mut dyn FnMut(Step),
) -> Result<(Observation, Vec<Option<Made>>), SliceError> {
    let started = Instant::now();
    let deadline = started + job.settings.timeout;
    let mut observation = Observation {
        height_mm: req.height_mm,
        reference_height_mm: job.settings.reference_height_mm,
        machine: job.machine.name.clone(),
        conditions: job.conditions.clone(),
        ..Observation::default()
    };
    let mut made: Vec<Option<Made>> = Vec::new();
    let outcome = look(
        req,
        original,
        job,
        deadline,
        bands,
        &mut observation,
        &mut made,
        progress,
    );
    observation.seconds = started.elapsed().as_secs_f64();
    match outcome {
        Ok(()) => {}
        Err(Stop::Cancelled(e)) => return Err(e),
        Err(Stop::TimedOut) => observation.choice = Choice::TimedOut,
        Err(Stop::Failed(reason)) => {
            observation.choice = Choice::Failed;
            observation.failure = Some(reason);
        }
    }
    if observation.choice != Choice::MostAlike {
        observation.chosen = None;
    }
    tracing::info!(
        height_mm = req.height_mm,
        reference_height_mm = job.settings.reference_height_mm,
        choice = ?observation.choice,
        chosen = ?observation.chosen,
        seconds = observation.seconds,
        "observed"
    );
    Ok((observation, made))
}

/// Why an observation ended early.
enum Stop {
    Cancelled(SliceError),
    TimedOut,
    Failed(String),
}

#[allow(clippy::too_many_arguments)]
fn look(
    req: &SliceRequest,
    original: &Mesh,
    job: &ObserveJob,
    deadline: Instant,
    bands: &mut Option<Bands>,
    observation: &mut Observation,
    made: &mut Vec<Option<Made>>,
    progress: &mut dyn FnMut(Step),
) -> Result<(), Stop> {
    let reference_mm = job.settings.reference_height_mm;
    let left = || deadline.saturating_duration_since(Instant::now());
    let timeout = || req.timeout.min(left()).max(Duration::from_millis(1));
    // A slicing that ran out of the observer's time is its time bound, not the slicer's.
    let slice_failed = |e: SliceError| match e {
        SliceError::Cancelled { .. } => Stop::Cancelled(e),
        _ if left().is_zero() => Stop::TimedOut,
        e => Stop::Failed(e.to_string()),
    };
    let line_width = crate::enhance::line_width_mm(job.machine.nozzle_mm);
    let read = |path: &Path| {
        read_print_file(path, line_width)
            .map_err(|e| Stop::Failed(format!("cannot read {}: {e}", path.display())))
    };
    let centre_xy = [0.5 * job.machine.bed_mm[0], 0.5 * job.machine.bed_mm[1]];

    // The reference: unmodified at the reference size, only measured.
    progress(Step::Observing(Observing::Reference));
    let reference_req = SliceRequest {
        height_mm: reference_mm,
        timeout: timeout(),
        ..req.clone()
    };
    let reference_mesh =
        placed_plain(&reference_req, original.clone()).map_err(|e| Stop::Failed(e.to_string()))?;
    let reference_gcode = job.work.join("reference.gcode");
    let reference_job = SliceJob {
        measure_only: true,
        ..slice_job(&reference_req, job.machine, &reference_gcode)
    };
    crate::slice::slice_mesh(&reference_mesh, &reference_job, &mut |_| {}).map_err(slice_failed)?;
    drop(reference_mesh);
    let reference = read(&reference_gcode)?;

    // The candidates, each made and sliced once. The paper's bands are the mesh's alone:
    // computed once for all its strengths.
    let mut prints: Vec<(usize, Print)> = Vec::new();
    let count = job.candidates.len();
    for (i, candidate) in job.candidates.iter().enumerate() {
        progress(Step::Observing(Observing::Candidate(i + 1, count)));
        let (strength, mode) = candidate.strength();
        let candidate_req = SliceRequest {
            strength,
            mode,
            timeout: timeout(),
            ..req.clone()
        };
        let enhanced = candidate_req
            .strength_table
            .resolve(strength, Some(req.height_mm))
            .is_some();
        if enhanced && mode == Mode::Paper && bands.is_none() {
            *bands = Some(
                Bands::compute(original, &mut |p| progress(Step::Enhancing(p))).map_err(|e| {
                    Stop::Failed(
                        SliceError::Enhance {
                            model: req.model.clone(),
                            source: e,
                        }
                        .to_string(),
                    )
                })?,
            );
        }
        let printer = (enhanced && mode == Mode::PrintAware).then(|| PrintResolution {
            nozzle_mm: job.machine.nozzle_mm,
            layer_height_mm: req
                .settings
                .layer_height_mm
                .unwrap_or(crate::slice::DEFAULT_LAYER_HEIGHT_MM),
        });
        let gcode = job.work.join(format!("candidate-{i}.gcode"));
        let t = Instant::now();
        let outcome = place(
            &candidate_req,
            original,
            printer,
            None,
            bands.as_ref(),
            progress,
        )
        .and_then(|placed| {
            let slicing = SliceJob {
                measure_only: job.measure_only,
                ..slice_job(&candidate_req, job.machine, &gcode)
            };
            let report = crate::slice::slice_mesh(&placed.mesh, &slicing, &mut |_| {})?;
            Ok(Made { placed, report })
        });
        let slice_s = t.elapsed().as_secs_f64();
        match outcome {
            Ok(m) => {
                let print = read(&gcode)?;
                observation.candidates.push(Looked {
                    mode: candidate.mode,
                    strength: m.placed.summary.lambda2.unwrap_or(0.0),
                    seen: None,
                    error: None,
                    slice_s,
                    lines: print.segment_count(),
                });
                prints.push((i, print));
                made.push(Some(m));
            }
            Err(e @ SliceError::Cancelled { .. }) => return Err(Stop::Cancelled(e)),
            Err(_) if left().is_zero() => return Err(Stop::TimedOut),
            Err(e) => {
                tracing::warn!(candidate = ?candidate, error = %e, "a candidate of the observer cannot be made");
                observation.candidates.push(Looked {
                    mode: candidate.mode,
                    strength: candidate.lambda2.unwrap_or(0.0),
                    seen: None,
                    error: Some(e.to_string()),
                    slice_s,
                    lines: 0,
                });
                made.push(None);
            }
        }
    }
    if prints.is_empty() {
        return Err(Stop::Failed("no candidate could be made".into()));
    }

    let reference_on_bed = OnBed {
        print: &reference,
        centre_xy,
        height_mm: reference_mm,
    };
    let candidates_on_bed: Vec<OnBed> = prints
        .iter()
        .map(|(_, print)| OnBed {
            print,
            centre_xy,
            height_mm: req.height_mm,
        })
        .collect();
    let cancelled = || {
        req.cancel
            .as_ref()
            .is_some_and(|c| c.load(std::sync::atomic::Ordering::Relaxed))
    };
    let stop = || cancelled() || left().is_zero();
    let views = job.conditions.views;
    let seen = crate::observe::observe(
        &reference_on_bed,
        &candidates_on_bed,
        job.conditions,
        &stop,
        &mut |view, _| progress(Step::Observing(Observing::Looking(view + 1, views))),
    );
    let seen = match seen {
        Ok(seen) => seen,
        Err(ObserveError::Stopped) if cancelled() => {
            return Err(Stop::Cancelled(SliceError::Cancelled {
                model: req.model.clone(),
            }))
        }
        Err(ObserveError::Stopped) => return Err(Stop::TimedOut),
        Err(e) => return Err(Stop::Failed(e.to_string())),
    };
    for ((i, _), s) in prints.iter().zip(seen) {
        observation.candidates[*i].seen = Some(s);
    }
    // The most alike; of equals, the first (the plain print comes first: no change
    // without a reason).
    observation.chosen = observation
        .candidates
        .iter()
        .enumerate()
        .filter_map(|(i, c)| Some((i, c.seen.as_ref()?.resemblance)))
        .fold(None, |best: Option<(usize, f64)>, (i, r)| match best {
            Some((_, b)) if b >= r => best,
            _ => Some((i, r)),
        })
        .map(|(i, _)| i);
    observation.choice = Choice::MostAlike;

    if let Some((dir, scale)) = job.pictures {
        let real = crate::observe::real_size_px_per_mm(job.conditions);
        let px_per_mm = match scale {
            PictureScale::RealSize => real,
            PictureScale::FitWidth(width) => crate::observe::fit_px_per_mm(
                &reference_on_bed,
                &candidates_on_bed[0],
                job.conditions,
                width,
            )
            .min(real),
        };
        let picture = crate::observe::views_picture(
            &reference_on_bed,
            &candidates_on_bed,
            job.conditions,
            px_per_mm,
        );
        if let Some(image) = picture {
            let path = dir.join(OBSERVED_PNG);
            if let Err(e) = crate::preview::write_png(&path, &image) {
                tracing::warn!(file = %path.display(), error = %e, "cannot write the observer's views");
            }
        }
    }
    Ok(())
}

/// Where an observation is, for progress displays.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum Observing {
    /// Slicing the model at the reference size.
    Reference,
    /// Making and slicing candidate i of n.
    Candidate(usize, usize),
    /// Looking from view i of n.
    Looking(usize, usize),
}

/// The G-code of a made candidate put in place as `output`, its report saying so.
pub(super) fn adopt(made_report: SliceReport, output: &Path) -> Result<SliceReport, SliceError> {
    crate::slice::persist(&made_report.output, output)?;
    Ok(SliceReport {
        output: output.to_path_buf(),
        ..made_report
    })
}

/// What a job's preparation does with `strength = "observed"`.
pub(super) struct Chosen {
    /// The request with the strength and mode settled.
    pub(super) req: SliceRequest,
    pub(super) observation: Option<Observation>,
    /// The chosen candidate as made for `first`'s machine, to be its G-code.
    pub(super) made: Option<Made>,
    /// Holds the made G-code until it is put in place.
    pub(super) _work: Option<tempfile::TempDir>,
}

/// Settles `req`'s [`Strength::Observed`] for a job printed by `first` (its first
/// machine): observes the folder's candidates ([`Candidate::folder_set`]) against the
/// reference size within the observer's time bound (and half the job's), and takes the
/// most alike; at or above the reference size the model is printed unmodified; when the
/// observer could not choose, the paper's table. The chosen print is re-placed with the
/// job's pictures when it has them (the same mesh: the bands are reused). Blocking.
pub(super) fn choose(
    req: &SliceRequest,
    original: &Mesh,
    first: Option<&super::Target>,
    progress: &mut dyn FnMut(Step),
) -> Result<Chosen, SliceError> {
    let mut chosen = Chosen {
        req: SliceRequest {
            strength: Strength::Auto,
            ..req.clone()
        },
        observation: None,
        made: None,
        _work: None,
    };
    let Some(first) = first else {
        return Ok(chosen);
    };
    let settings = ObserveSettings {
        timeout: req.observe.timeout.min(req.timeout / 2),
        ..req.observe.clone()
    };
    if req.height_mm >= settings.reference_height_mm {
        chosen.req.strength = Strength::Off;
        chosen.observation = Some(Observation {
            height_mm: req.height_mm,
            reference_height_mm: settings.reference_height_mm,
            machine: first.machine.name.clone(),
            choice: Choice::AtReference,
            ..Observation::default()
        });
        return Ok(chosen);
    }
    let work = tempfile::Builder::new()
        .prefix("crispen-observe-")
        .tempdir()
        .map_err(SliceError::io(
            "cannot create a temporary folder in",
            &std::env::temp_dir(),
        ))?;
    let candidates = Candidate::folder_set();
    let job = ObserveJob {
        machine: &first.machine,
        candidates: &candidates,
        settings: &settings,
        conditions: &Conditions::default(),
        work: work.path(),
        measure_only: false,
        pictures: req
            .pictures
            .as_deref()
            .map(|dir| (dir, PictureScale::FitWidth(JOB_PAGE_WIDTH_PX))),
    };
    let mut bands = None;
    let (observation, mut made) = observe(req, original, &job, &mut bands, progress)?;
    if let (Choice::MostAlike, Some(i)) = (observation.choice, observation.chosen) {
        let (strength, mode) = candidates[i].strength();
        chosen.req.strength = strength;
        chosen.req.mode = mode;
        chosen.made = made.get_mut(i).and_then(Option::take);
        if let (Some(m), Some(dir)) = (&mut chosen.made, req.pictures.as_deref()) {
            if m.placed.summary.lambda2.is_some() {
                let printer = m
                    .placed
                    .summary
                    .print_aware
                    .as_ref()
                    .map(|_| PrintResolution {
                        nozzle_mm: first.machine.nozzle_mm,
                        layer_height_mm: req
                            .settings
                            .layer_height_mm
                            .unwrap_or(crate::slice::DEFAULT_LAYER_HEIGHT_MM),
                    });
                m.placed = place(
                    &chosen.req,
                    original,
                    printer,
                    Some(dir),
                    bands.as_ref(),
                    progress,
                )?;
            }
        }
    }
    chosen.observation = Some(observation);
    chosen._work = Some(work);
    Ok(chosen)
}

/// The width of the views on a job's page, pixels.
const JOB_PAGE_WIDTH_PX: u32 = 1200;

/// [`observe`] for `crispen observe`: loads `req`'s model and observes it, with only the
/// observation to answer. Blocking.
pub fn observe_model(
    req: &SliceRequest,
    job: &ObserveJob,
    progress: &mut dyn FnMut(Step),
) -> Result<Observation, SliceError> {
    progress(Step::Loading);
    let loaded = crate::mesh::load(&req.model)?;
    let (observation, _) = observe(req, &loaded.mesh, job, &mut None, progress)?;
    Ok(observation)
}
