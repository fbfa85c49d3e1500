//! `crispen enhance INPUT -o OUTPUT [--height MM] [--strength L2] [--lambda1 L1] [--mu MU]
//! [--json] [--machine NAME] [--nozzle MM] [--layer-height MM]`: load and clean a mesh, enhance it (λ2 from `--strength`, or from the height
//! table for `--height`), scale it to the printed height, write it in the format of
//! OUTPUT's extension. A phase display on a terminal; `--json` prints one report;
//! `--preview DIR` draws the model before and after and the displacement's heat map.
//! With `--height`, the report gives the displacement in printed mm (`printed`), and with a
//! machine or a nozzle, next to its line width and layer height.

use anyhow::Context;
use crispen::enhance::{
    self, Displacements, EnhanceOptions, Phase, PhaseTimings, PrintResolution, PrintedDisplacement,
    StrengthTable,
};
use crispen::mesh::place::UpAxis;
use crispen::mesh::{self, CleanReport, MeshFormat};
use crispen::preview;
use serde::Serialize;
use std::io::IsTerminal;
use std::path::PathBuf;
use std::process::ExitCode;
use std::time::Instant;

#[derive(Debug, clap::Args)]
pub(crate) struct Args {
    /// Mesh to enhance (STL, OBJ or 3MF; the format is detected from the content)
    pub input: PathBuf,
    /// Where to write the result; `.stl` (binary) or `.obj` (full precision)
    #[arg(short, long)]
    pub output: PathBuf,
    /// Printed height in mm: scales the output to this Z extent and picks λ2 from the
    /// height table (at 150 mm and above the model is left unmodified)
    #[arg(long, value_name = "MM")]
    pub height: Option<f64>,
    /// λ2 (strength) directly; the paper's light / medium / strong are 10 / 20 / 40.
    /// Without --height the model keeps its size
    #[arg(long, value_name = "L2")]
    pub strength: Option<f64>,
    /// λ1, weight of the finest band (0 avoids amplifying scan noise)
    #[arg(long, value_name = "L1", default_value_t = 0.0)]
    pub lambda1: f64,
    /// μ, weight falloff (default: 0.1·λ2 / max‖Δ3‖²)
    #[arg(long, value_name = "MU")]
    pub mu: Option<f64>,
    /// Print one JSON report on stdout
    #[arg(long)]
    pub json: bool,
    /// Also write pictures into DIR: the model before and after from one camera, and a
    /// heat map of the displacement (before.png, after.png, displacement.png)
    #[arg(long, value_name = "DIR")]
    pub preview: Option<PathBuf>,
    /// The model's up axis, for the pictures' camera: z (slicers, STL files) or y (many
    /// OBJ files)
    #[arg(long, value_name = "AXIS", default_value = "z")]
    pub up: UpAxis,
    /// The machine the print is for (a built-in one, e.g. ultimaker2plus): the report
    /// sets the printed displacement against its nozzle and layer height
    #[arg(long, value_name = "NAME")]
    pub machine: Option<String>,
    /// The nozzle fitted, mm (default: the machine's, or 0.4 without --machine)
    #[arg(long, value_name = "MM")]
    pub nozzle: Option<f64>,
    /// The layer height the print is sliced with, mm (the built-in profiles' 0.2)
    #[arg(long, value_name = "MM", default_value_t = 0.2)]
    pub layer_height: f64,
}

#[derive(Serialize)]
struct Report {
    input: PathBuf,
    output: PathBuf,
    format: MeshFormat,
    vertices: usize,
    faces: usize,
    clean: CleanReport,
    /// False when the height table says to print the model unmodified.
    enhanced: bool,
    lambda1: f64,
    lambda2: Option<f64>,
    mu: Option<f64>,
    w_min: Option<f64>,
    w_mean: Option<f64>,
    /// In output units (mm after --height).
    max_displacement: f64,
    mean_displacement: f64,
    max_solve_residual: Option<f64>,
    /// The displacement at the printed size (with --height), against the machine's line
    /// width and layer height (with --machine or --nozzle).
    printed: Option<PrintedDisplacement>,
    /// The pictures written for --preview.
    pictures: Vec<PathBuf>,
    scale: f64,
    height_mm: Option<f64>,
    timings: Timings,
}

#[derive(Serialize)]
struct Timings {
    load_s: f64,
    #[serde(flatten)]
    enhance: PhaseTimings,
    save_s: f64,
    total_s: f64,
}

pub(crate) fn run(args: Args) -> anyhow::Result<ExitCode> {
    let started = Instant::now();
    if let Some(h) = args.height {
        anyhow::ensure!(
            h.is_finite() && h > 0.0,
            "--height must be a positive number of mm, not {h}"
        );
    }
    if let Some(s) = args.strength {
        anyhow::ensure!(s.is_finite(), "--strength must be a finite number, not {s}");
    }
    let out_ext = args
        .output
        .extension()
        .and_then(|e| e.to_str())
        .map(str::to_ascii_lowercase);
    if !matches!(out_ext.as_deref(), Some("stl" | "obj")) {
        anyhow::bail!(
            "{}: cannot tell the output format from the extension (hint: use .stl or .obj)",
            args.output.display()
        );
    }
    let printer = printer(&args)?;
    let lambda2 = match (args.strength, args.height) {
        (Some(s), _) => Some(s),
        (None, Some(h)) => StrengthTable::default().lambda2_for_height(h),
        (None, None) => anyhow::bail!(
            "say how strongly to enhance: give --height MM (the printed height; λ2 comes from \
             the height table) or --strength L2 (e.g. 10, 20 or 40)"
        ),
    };

    let progress = Progress::new();
    progress.set("reading");
    let t = Instant::now();
    let loaded = mesh::load(&args.input)?;
    let load_s = t.elapsed().as_secs_f64();
    tracing::info!(
        input = %args.input.display(),
        format = %loaded.format,
        vertices = loaded.mesh.vertices.len(),
        faces = loaded.mesh.faces.len(),
        welded = loaded.clean.welded_vertices,
        dropped_faces = loaded.clean.dropped_degenerate_faces,
        dropped_vertices = loaded.clean.dropped_unreferenced_vertices,
        "loaded mesh"
    );

    let (mut mesh, enhance_report) = match lambda2 {
        Some(lambda2) => {
            let opts = EnhanceOptions {
                lambda1: args.lambda1,
                lambda2,
                mu: args.mu,
            };
            let mut on_phase = |p: Phase| {
                progress.set(match p {
                    Phase::Operators => "building the Laplacian and mass matrix".to_string(),
                    Phase::Factorize => "analysing the sparsity pattern".to_string(),
                    Phase::Solve(k) => format!("smoothing step {} of 3", k + 1),
                    Phase::Combine => "combining the bands".to_string(),
                })
            };
            let (mesh, report) = enhance::enhance(&loaded.mesh, &opts, &mut on_phase)
                .with_context(|| format!("cannot enhance {}", args.input.display()))?;
            (mesh, Some(report))
        }
        None => {
            tracing::info!(
                height_mm = args.height,
                "printed at this height the model is left unmodified"
            );
            (loaded.mesh.clone(), None)
        }
    };
    // Before scaling, so both pictures share the input's camera.
    let mut pictures = Vec::new();
    if let Some(dir) = &args.preview {
        progress.set("drawing the pictures");
        std::fs::create_dir_all(dir)
            .with_context(|| format!("cannot create the picture folder {}", dir.display()))?;
        let drawn = preview::pictures(&loaded.mesh, &mesh, args.up, 800)
            .context("the mesh has no vertices to draw")?;
        pictures = drawn
            .save(dir)
            .with_context(|| format!("cannot write the pictures into {}", dir.display()))?;
    }
    let displacements = Displacements::between(&loaded.mesh, &mesh);
    let scale = match args.height {
        Some(h) => crispen::mesh::place::scale_to_height(&mut mesh, h),
        None => 1.0,
    };
    let printed = match (args.height, &displacements) {
        (Some(h), Some(d)) => Some(d.summary(scale, h, printer)),
        _ => None,
    };

    progress.set("writing");
    let t = Instant::now();
    mesh::save(&args.output, &mesh)?;
    let save_s = t.elapsed().as_secs_f64();
    progress.finish();

    let report = Report {
        input: args.input.clone(),
        output: args.output.clone(),
        format: loaded.format,
        vertices: mesh.vertices.len(),
        faces: mesh.faces.len(),
        clean: loaded.clean,
        enhanced: enhance_report.is_some(),
        lambda1: args.lambda1,
        lambda2,
        mu: enhance_report.as_ref().map(|r| r.mu),
        w_min: enhance_report.as_ref().map(|r| r.w_min),
        w_mean: enhance_report.as_ref().map(|r| r.w_mean),
        max_displacement: enhance_report
            .as_ref()
            .map_or(0.0, |r| r.max_displacement * scale),
        mean_displacement: enhance_report
            .as_ref()
            .map_or(0.0, |r| r.mean_displacement * scale),
        max_solve_residual: enhance_report.as_ref().map(|r| r.max_solve_residual),
        printed,
        pictures,
        scale,
        height_mm: args.height,
        timings: Timings {
            load_s,
            enhance: enhance_report.map(|r| r.timings).unwrap_or_default(),
            save_s,
            total_s: started.elapsed().as_secs_f64(),
        },
    };
    tracing::info!(
        output = %args.output.display(),
        lambda2 = report.lambda2,
        max_displacement = report.max_displacement,
        total_s = report.timings.total_s,
        "wrote enhanced mesh"
    );
    if args.json {
        println!("{}", serde_json::to_string_pretty(&report)?);
    }
    Ok(ExitCode::SUCCESS)
}

/// The nozzle and layer height of `--machine` / `--nozzle`, if either is given.
fn printer(args: &Args) -> anyhow::Result<Option<PrintResolution>> {
    anyhow::ensure!(
        args.layer_height.is_finite() && (0.01..=2.0).contains(&args.layer_height),
        "--layer-height must be from 0.01 to 2 mm, not {}",
        args.layer_height
    );
    let nozzle_mm = match (&args.machine, args.nozzle) {
        (None, None) => return Ok(None),
        (Some(name), nozzle) => {
            let machine = crispen::machine::Machine::builtin(name).with_context(|| {
                let builtin: Vec<&str> = crispen::machine::BUILTIN.iter().map(|b| b.name).collect();
                format!(
                    "--machine {name:?}: no such built-in machine (built-in: {})",
                    builtin.join(", ")
                )
            })?;
            match nozzle {
                Some(mm) => {
                    machine
                        .with_nozzle(mm)
                        .map_err(|m| anyhow::anyhow!("--nozzle {mm}: {m}"))?
                        .nozzle_mm
                }
                None => machine.nozzle_mm,
            }
        }
        (None, Some(mm)) => {
            anyhow::ensure!(
                mm.is_finite() && (0.1..=2.0).contains(&mm),
                "--nozzle must be from 0.1 to 2 mm, not {mm}"
            );
            mm
        }
    };
    Ok(Some(PrintResolution {
        nozzle_mm,
        layer_height_mm: args.layer_height,
    }))
}

/// A spinner with the current phase, only when stderr is a terminal.
struct Progress(Option<indicatif::ProgressBar>);

impl Progress {
    fn new() -> Self {
        let bar = std::io::stderr().is_terminal().then(|| {
            let bar = indicatif::ProgressBar::new_spinner();
            bar.set_style(
                indicatif::ProgressStyle::with_template("{spinner} [{elapsed}] {msg}")
                    .unwrap_or_else(|_| indicatif::ProgressStyle::default_spinner()),
            );
            bar.enable_steady_tick(std::time::Duration::from_millis(120));
            bar
        });
        Progress(bar)
    }
    fn set(&self, message: impl Into<std::borrow::Cow<'static, str>>) {
        if let Some(bar) = &self.0 {
            bar.set_message(message);
        }
    }
    fn finish(&self) {
        if let Some(bar) = &self.0 {
            bar.finish_and_clear();
        }
    }
}
