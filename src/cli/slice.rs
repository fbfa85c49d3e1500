//! `crispen slice`: enhance, scale and slice one model into a Marlin G-code job for one
//! machine with a real slicer, through the same steps as the daemon's preparation
//! (`crispen::daemon::prepare::steps`). Shows the step on a terminal and prints a summary,
//! or the full report with `--json`.

use anyhow::Context;
use crispen::daemon::prepare::steps::{self, SliceRequest, Step};
use crispen::enhance::{Strength, StrengthTable};
use crispen::machine::Machine;
use crispen::mesh::place::UpAxis;
use crispen::slice::{SliceSettings, SlicerKind, SETTING_KEYS};
use std::io::IsTerminal;
use std::path::PathBuf;
use std::process::ExitCode;
use std::time::Duration;

#[derive(Debug, clap::Args)]
pub(crate) struct Args {
    /// The model to print (STL, OBJ or 3MF)
    pub model: PathBuf,
    /// Where to write the G-code
    #[arg(short, long, value_name = "OUT.gcode")]
    pub output: PathBuf,
    /// Printed height of the model in mm (its Z extent on the bed)
    #[arg(long, value_name = "MM")]
    pub height: f64,
    /// The machine to slice for: a built-in one (ultimaker2, ultimaker2-extended,
    /// ultimaker2plus, ultimaker-original-plus, marlin-175) or one of --config's
    /// [[machine]] tables
    #[arg(long, value_name = "NAME", default_value = "ultimaker2")]
    pub machine: String,
    /// The nozzle fitted, for a machine that takes several (ultimaker2plus: 0.25 to 0.8)
    #[arg(long, value_name = "MM")]
    pub nozzle: Option<f64>,
    /// A daemon config whose [[machine]] tables --machine may name
    #[arg(long, value_name = "FILE")]
    pub config: Option<PathBuf>,
    /// Slicer to run: prusa (PrusaSlicer) or cura (CuraEngine)
    #[arg(long, default_value = "prusa", value_parser = parse_slicer)]
    pub slicer: SlicerKind,
    /// Copies of the model side by side on one bed, each a part of the plate that can be
    /// cancelled alone while printing
    #[arg(long, value_name = "N", default_value_t = 1,
          value_parser = clap::value_parser!(u32).range(1..=i64::from(crispen::slice::plate::MAX_PER_PLATE)))]
    pub per_plate: u32,
    /// Enhancement strength λ2 (default: chosen from the printed height)
    #[arg(long, value_name = "L2", conflicts_with = "no_enhance")]
    pub strength: Option<f64>,
    /// Slice the model unmodified
    #[arg(long)]
    pub no_enhance: bool,
    /// The model's up axis: z (STL convention) or y (common in OBJ files)
    #[arg(long, default_value = "z", value_parser = parse_up)]
    pub up: UpAxis,
    /// Slicer profile replacing the machine's (PrusaSlicer .ini, CuraEngine .toml); the
    /// machine's bed, nozzle, filament and start/end code still apply
    #[arg(long, value_name = "FILE")]
    pub profile: Option<PathBuf>,
    /// Override a setting: layer_height, infill, supports, nozzle_temp, bed_temp, material
    #[arg(long = "set", value_name = "KEY=VALUE")]
    pub set: Vec<String>,
    /// Print the report as JSON on stdout
    #[arg(long)]
    pub json: bool,
    /// The enhancement: paper (the paper's bands, λ2 from the height table) or
    /// print-aware (bands and λ2 from the machine's nozzle and layer height at the
    /// printed size; see docs/method.md)
    #[arg(long, value_name = "MODE", default_value = "paper")]
    pub mode: crispen::enhance::Mode,
    /// Also slice the model unmodified with the same settings and compare the two jobs'
    /// outer walls layer by layer: how far the enhancement moves what the nozzle draws
    #[arg(long, conflicts_with = "no_enhance")]
    pub compare: bool,
    /// With --compare, also draw a few layers' outer walls, plain and enhanced, into
    /// DIR/walls.png (and the model before and after, as a job's pictures)
    #[arg(long, value_name = "DIR", requires = "compare")]
    pub pictures: Option<PathBuf>,
    /// Draw the print as the printer will lay it, from the G-code, into DIR/preview.png:
    /// the model, the plain print and the enhanced one from one camera under a grazing
    /// light, and below them the prints at their printed size. For an enhanced model this
    /// also slices the model unmodified, as --compare does
    #[arg(long, value_name = "DIR")]
    pub preview: Option<PathBuf>,
    /// Stop the slicer after this many seconds
    #[arg(long, value_name = "SECS", default_value_t = 600)]
    pub timeout: u64,
}

pub(crate) fn parse_slicer(s: &str) -> Result<SlicerKind, String> {
    s.parse()
}

pub(crate) fn parse_up(s: &str) -> Result<UpAxis, String> {
    s.parse()
}

/// The machine `--machine` names (`name`): one of `--config`'s, or a built-in one; with
/// `--nozzle`, that nozzle fitted.
pub(crate) fn find_machine(
    name: &str,
    nozzle: Option<f64>,
    config: Option<&std::path::Path>,
) -> anyhow::Result<Machine> {
    let defined = match config {
        // Checked only: the machines need none of the daemon's key and password files.
        Some(path) => crispen::daemon::config::Checked::load(path)?
            .machines()
            .to_vec(),
        None => Vec::new(),
    };
    let machine = defined
        .into_iter()
        .find(|m| m.name == name)
        .or_else(|| Machine::builtin(name))
        .with_context(|| {
            let builtin: Vec<&str> = crispen::machine::BUILTIN.iter().map(|b| b.name).collect();
            format!(
                "--machine {name:?}: no such machine (built-in: {}; others from --config FILE's [[machine]] tables)",
                builtin.join(", ")
            )
        })?;
    match nozzle {
        Some(mm) => machine
            .with_nozzle(mm)
            .map_err(|m| anyhow::anyhow!("--nozzle {mm}: {m}")),
        None => Ok(machine),
    }
}

pub(crate) fn run(args: Args) -> anyhow::Result<ExitCode> {
    let mut settings = SliceSettings::default();
    for pair in &args.set {
        let (key, value) = pair.split_once('=').with_context(|| {
            format!(
                "--set {pair:?}: expected KEY=VALUE with KEY one of {}",
                SETTING_KEYS.join(", ")
            )
        })?;
        settings.set(key.trim(), value)?;
    }
    let strength = if args.no_enhance {
        Strength::Off
    } else if let Some(l2) = args.strength {
        Strength::Lambda2(l2)
    } else {
        Strength::Auto
    };
    let machine = find_machine(&args.machine, args.nozzle, args.config.as_deref())?;
    let mut req = SliceRequest::new(&args.model, args.height);
    req.slicer = args.slicer;
    req.up = args.up;
    req.strength = strength;
    req.strength_table = StrengthTable::default();
    req.settings = settings;
    req.profile = args.profile.clone();
    req.timeout = Duration::from_secs(args.timeout.max(1));
    req.compare = args.compare;
    req.mode = args.mode;
    req.per_plate = args.per_plate;
    if let Some(dir) = &args.pictures {
        std::fs::create_dir_all(dir)
            .with_context(|| format!("cannot create the picture folder {}", dir.display()))?;
        req.pictures = Some(dir.clone());
    }
    if let Some(dir) = &args.preview {
        std::fs::create_dir_all(dir)
            .with_context(|| format!("cannot create the preview folder {}", dir.display()))?;
        // Not an earlier run's picture taken for this one's.
        let _ = std::fs::remove_file(dir.join(crispen::preview::PREVIEW_PNG));
        req.preview = Some(dir.clone());
    }

    let bar = step_spinner();
    let mut progress = |step: Step| {
        if let Some(bar) = &bar {
            bar.set_message(format!("{}: {}", args.model.display(), step.describe()));
        }
    };
    let target = steps::Target {
        machine,
        output: args.output.clone(),
        keep_mesh: None,
    };
    let result = steps::prepare_one(&req, target, &mut progress);
    if let Some(bar) = &bar {
        bar.finish_and_clear();
    }
    let report = result?;

    if args.json {
        // The figures, and the line on what the enhancement moved in words, made here.
        let mut json = serde_json::to_value(&report)?;
        json["moved"] = report.moved().to_string().into();
        println!("{}", serde_json::to_string_pretty(&json)?);
    } else {
        let enhancement = match report.enhancement.lambda2 {
            Some(l2) => format!("{} with λ2 = {l2:.3}", report.enhancement.mode),
            None => "unmodified".into(),
        };
        let time = report
            .estimated_print_time_s
            .map(|s| {
                let s = s.round() as u64;
                format!("{}h {:02}m", s / 3600, (s % 3600) / 60)
            })
            .unwrap_or_else(|| "unknown".into());
        let filament = match (report.filament_mm, report.filament_g) {
            (Some(mm), Some(g)) => format!("{:.2} m ({g:.1} g)", mm / 1000.0),
            (Some(mm), None) => format!("{:.2} m", mm / 1000.0),
            _ => "unknown".into(),
        };
        println!(
            "{}: {} mm tall, {enhancement}; sliced for the {} by {} into {} layers ({} G-code lines)\n\
             estimated print time {time}, filament {filament}; took {:.1} s\nwrote {}",
            report.model.display(),
            report.height_mm,
            report.machine,
            report
                .slicer_version
                .clone()
                .unwrap_or_else(|| report.slicer.to_string()),
            report.layer_count,
            report.gcode_lines,
            report.timings.total_s,
            report.output.display()
        );
        println!("{}", report.moved());
        if let Some(verdict) = &report.policy {
            println!("{}", verdict.summary());
        }
        if let Some(p) = &report.enhancement.printed {
            let share = p
                .share_above_threshold
                .map(|s| {
                    format!(
                        ", {:.1} % of the surface by more than {:.2} mm",
                        100.0 * s,
                        p.threshold_mm.unwrap_or(0.0)
                    )
                })
                .unwrap_or_default();
            println!(
                "the surface moved up to {:.3} mm (p95 {:.3}, mean {:.3}){share}; nozzle {} mm, layers {} mm",
                p.max_mm,
                p.p95_mm,
                p.mean_mm,
                p.nozzle_mm.map_or("?".into(), |v| v.to_string()),
                p.layer_height_mm.map_or("?".into(), |v| v.to_string()),
            );
        }
        match &report.walls {
            Some(w) => println!(
                "outer wall against the unmodified model's ({} layers, {:.0} mm of wall): mean {:.3} mm, \
                 p95 {:.3} mm; moved more than 0.05 / 0.1 / 0.2 mm: {:.2} % / {:.2} % / {:.2} %",
                w.layers,
                w.wall_mm,
                w.mean_mm,
                w.p95_mm,
                100.0 * w.share_over_0_05_mm,
                100.0 * w.share_over_0_1_mm,
                100.0 * w.share_over_0_2_mm
            ),
            None if args.compare || args.preview.is_some() && report.enhancement.lambda2.is_some() => println!(
                "no comparison: the model was printed unmodified, or the unmodified slicing failed (see the log)"
            ),
            None => {}
        }
    }
    if let Some(dir) = &args.preview {
        let path = dir.join(crispen::preview::PREVIEW_PNG);
        // Drawn or not, the G-code stands: a picture that failed is in the log.
        if path.is_file() {
            if args.json {
                eprintln!("wrote {}", path.display());
            } else {
                println!("wrote {}", path.display());
            }
        } else {
            eprintln!("no preview drawn (see the log)");
        }
    }
    Ok(ExitCode::SUCCESS)
}

/// A spinner on the terminal that shows the preparation's step and the time so far;
/// none when standard error is no terminal.
pub(super) fn step_spinner() -> Option<indicatif::ProgressBar> {
    std::io::stderr().is_terminal().then(|| {
        let bar = indicatif::ProgressBar::new_spinner();
        bar.set_style(
            indicatif::ProgressStyle::with_template("{spinner} [{elapsed}] {msg}")
                .unwrap_or_else(|_| indicatif::ProgressStyle::default_spinner()),
        );
        bar.enable_steady_tick(Duration::from_millis(120));
        bar
    })
}
