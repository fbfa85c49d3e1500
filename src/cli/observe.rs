//! `crispen observe`: which small print looks most like the big one. Slices the model
//! unmodified at the reference height and once per candidate strength at the height, and
//! prints how alike each looks to a model of a person's eye
//! (`crispen::daemon::prepare::steps::observed`, docs/method.md "The observer").

use super::slice::{find_machine, parse_slicer, parse_up, step_spinner};
use anyhow::Context;
use crispen::daemon::prepare::steps::observed::{
    self, Candidate, CandidateMode, Choice, ObserveJob, ObserveSettings, PictureScale,
};
use crispen::daemon::prepare::steps::{SliceRequest, Step};
use crispen::enhance::Mode;
use crispen::mesh::place::UpAxis;
use crispen::observe::Conditions;
use crispen::slice::SlicerKind;
use std::path::PathBuf;
use std::process::ExitCode;
use std::time::Duration;

#[derive(Debug, clap::Args)]
pub(crate) struct Args {
    /// The model (STL, OBJ or 3MF)
    pub model: PathBuf,
    /// Printed height of the small print, mm
    #[arg(long, value_name = "MM")]
    pub height: f64,
    /// Printed height of the print it should look like, mm (unmodified)
    #[arg(long, value_name = "MM")]
    pub reference_height: f64,
    /// The model's up axis: z (STL convention) or y (common in OBJ files)
    #[arg(long, default_value = "z", value_parser = parse_up)]
    pub up: UpAxis,
    /// The machine to slice for (see `crispen slice --help`)
    #[arg(long, value_name = "NAME", default_value = "ultimaker2")]
    pub machine: String,
    /// The nozzle fitted, for a machine that takes several
    #[arg(long, value_name = "MM")]
    pub nozzle: Option<f64>,
    /// A daemon config whose [[machine]] tables --machine may name
    #[arg(long, value_name = "FILE")]
    pub config: Option<PathBuf>,
    /// The candidates' strengths λ2, comma-separated; 0 is the plain print
    #[arg(
        long,
        value_name = "L2,...",
        value_delimiter = ',',
        default_value = "0,10,20,40"
    )]
    pub strengths: Vec<f64>,
    /// The enhancement of the candidates: paper, or print-aware (its target scaled by each
    /// strength)
    #[arg(long, value_name = "MODE", default_value = "paper")]
    pub mode: Mode,
    /// Slicer to run: prusa (PrusaSlicer) or cura (CuraEngine)
    #[arg(long, default_value = "prusa", value_parser = parse_slicer)]
    pub slicer: SlicerKind,
    /// Write the views into DIR/observed.png: the reference (scaled to the print's size)
    /// and each candidate, from every view, at their real size on the retina
    #[arg(long, value_name = "DIR")]
    pub pictures: Option<PathBuf>,
    /// Print the observation as JSON on stdout
    #[arg(long)]
    pub json: bool,
    /// From the eye to the print, mm
    #[arg(long, value_name = "MM", default_value_t = 400.0)]
    pub distance: f64,
    /// How many views around the print
    #[arg(long, value_name = "N", default_value_t = 4)]
    pub views: usize,
    /// Stop after this many seconds
    #[arg(long, value_name = "SECS", default_value_t = 3600)]
    pub timeout: u64,
}

/// The strengths accepted, as a folder's: 0 (plain) to five times the table's strongest.
const LAMBDA2: std::ops::RangeInclusive<f64> = 0.0..=100.0;
/// At most this many candidates: each is a slicing.
const MAX_CANDIDATES: usize = 12;

pub(crate) fn run(args: Args) -> anyhow::Result<ExitCode> {
    if args.strengths.is_empty() || args.strengths.len() > MAX_CANDIDATES {
        anyhow::bail!(
            "--strengths: give 1 to {MAX_CANDIDATES} strengths, got {}",
            args.strengths.len()
        );
    }
    if let Some(bad) = args
        .strengths
        .iter()
        .find(|l| !(l.is_finite() && LAMBDA2.contains(l)))
    {
        anyhow::bail!("--strengths: {bad} is not a λ2 from 0 to 100");
    }
    if !(args.height.is_finite() && args.height > 0.0 && args.height <= args.reference_height) {
        anyhow::bail!(
            "--height {} must be a positive number of mm, at most --reference-height ({})",
            args.height,
            args.reference_height
        );
    }
    let conditions = Conditions {
        distance_mm: args.distance,
        views: args.views,
        ..Conditions::default()
    };
    conditions.check().context("the viewing conditions")?;
    let machine = find_machine(&args.machine, args.nozzle, args.config.as_deref())?;
    let mut req = SliceRequest::new(&args.model, args.height);
    req.slicer = args.slicer;
    req.up = args.up;
    req.timeout = Duration::from_secs(args.timeout.max(1));
    let settings = ObserveSettings {
        reference_height_mm: args.reference_height,
        timeout: req.timeout,
    };
    if let Some(dir) = &args.pictures {
        std::fs::create_dir_all(dir)
            .with_context(|| format!("cannot create the picture folder {}", dir.display()))?;
        // Not an earlier run's picture taken for this one's.
        let _ = std::fs::remove_file(dir.join(observed::OBSERVED_PNG));
    }
    let work = tempfile::Builder::new()
        .prefix("crispen-observe-")
        .tempdir()
        .context("cannot create a temporary folder")?;
    let candidates = Candidate::from_strengths(&args.strengths, args.mode);
    let job = ObserveJob {
        machine: &machine,
        candidates: &candidates,
        settings: &settings,
        conditions: &conditions,
        work: work.path(),
        measure_only: true,
        pictures: args
            .pictures
            .as_deref()
            .map(|d| (d, PictureScale::RealSize)),
    };

    let bar = step_spinner();
    let mut progress = |step: Step| {
        if let Some(bar) = &bar {
            bar.set_message(format!("{}: {}", args.model.display(), step.describe()));
        }
    };
    let result = observed::observe_model(&req, &job, &mut progress);
    if let Some(bar) = &bar {
        bar.finish_and_clear();
    }
    let observation = result?;

    if args.json {
        #[derive(serde::Serialize)]
        struct Out<'a> {
            model: &'a std::path::Path,
            #[serde(flatten)]
            observation: &'a observed::Observation,
        }
        let out = Out {
            model: &args.model,
            observation: &observation,
        };
        println!("{}", serde_json::to_string_pretty(&out)?);
    } else {
        println!(
            "{} at {} mm against {} mm, sliced for the {} ({} mm nozzle), seen from {} mm in {} views; took {:.0} s",
            args.model.display(),
            observation.height_mm,
            observation.reference_height_mm,
            machine.name,
            machine.nozzle_mm,
            conditions.distance_mm,
            conditions.views,
            observation.seconds
        );
        println!(
            "{:>8}  {:<12} {:>11} {:>11} {:>8} {:>8}",
            "λ2", "mode", "resemblance", "difference", "lost", "added"
        );
        for (i, c) in observation.candidates.iter().enumerate() {
            let mode = match c.mode {
                CandidateMode::Plain => "plain",
                CandidateMode::Paper => "paper",
                CandidateMode::PrintAware => "print-aware",
            };
            let mark = if observation.chosen == Some(i) {
                "  ← most alike"
            } else {
                ""
            };
            match (&c.seen, &c.error) {
                (Some(s), _) => println!(
                    "{:>8.2}  {mode:<12} {:>11.4} {:>11.3} {:>8.3} {:>8.3}{mark}",
                    c.strength, s.resemblance, s.difference_jnd, s.lost_jnd, s.added_jnd
                ),
                (None, Some(e)) => println!("{:>8.2}  {mode:<12} not made: {e}", c.strength),
                (None, None) => println!("{:>8.2}  {mode:<12} not seen", c.strength),
            }
        }
        if let Some(dir) = &args.pictures {
            let path = dir.join(observed::OBSERVED_PNG);
            if path.is_file() {
                println!("wrote {}", path.display());
            }
        }
    }
    match observation.choice {
        Choice::MostAlike | Choice::AtReference => Ok(ExitCode::SUCCESS),
        Choice::TimedOut => {
            eprintln!(
                "error: the observation took longer than --timeout {} s",
                args.timeout
            );
            Ok(ExitCode::FAILURE)
        }
        Choice::Failed => {
            eprintln!(
                "error: nothing could be observed: {}",
                observation
                    .failure
                    .as_deref()
                    .unwrap_or("no candidate could be made")
            );
            Ok(ExitCode::FAILURE)
        }
    }
}
