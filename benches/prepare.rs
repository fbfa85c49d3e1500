//! Benchmark (issue 33): what crispen adds to the slicer's time before a job may print.
//! Spot 100 mm tall, enhanced at the automatic strength, PrusaSlicer, an Ultimaker 2, with
//! the pictures and thumbnails a daemon's job gets. Per run:
//!
//! - `slicer`: PrusaSlicer alone, on the enhanced and placed mesh the job kept, with the
//!   command line crispen gives it;
//! - `ready`: crispen's preparation until the job is ready, as the daemon runs it (a
//!   `crispen prepare-job` child given the daemon's task);
//! - `before`: the preparation as it was before issue 33, with the wall comparison inline
//!   (`SliceRequest::compare`, at the usual priority);
//! - `compare`: the wall comparison as the daemon now measures it after the job is ready
//!   (a child at the lowest CPU priority, so on a busy machine it takes longer: it only
//!   gets what is left over).
//!
//! It prints the medians and crispen's added time (`ready - slicer`) as a share of the
//! slicer's, now and before; the target is at most 10 %. `cargo bench --bench prepare`
//! (CRISPEN_BENCH_RUNS sets the runs, 3 by default).

use crispen::daemon::prepare::steps::{prepare, SliceRequest, Target};
use crispen::daemon::prepare::{run_child, run_compare_child, PrepareTask, TaskMachine};
use crispen::enhance::Strength;
use crispen::machine::Machine;
use crispen::mesh::place::UpAxis;
use crispen::slice::{profiles, SliceSettings, SlicerKind};
use std::path::Path;
use std::time::{Duration, Instant};
use tokio_util::sync::CancellationToken;

#[path = "../tests/common/mod.rs"]
mod common;

const HEIGHT_MM: f64 = 100.0;

/// The daemon's task for Spot dropped into a folder of an Ultimaker 2 at 100 mm.
fn task(job_dir: &Path) -> PrepareTask {
    let model = job_dir.join("spot.obj");
    std::fs::copy(common::model("spot.obj"), &model).expect("copy the model");
    let machine = Machine::builtin("ultimaker2").expect("built in");
    PrepareTask {
        job: "0001-spot_obj".into(),
        machines: vec![TaskMachine {
            output: job_dir.join(format!("spot.obj.{}.gcode", machine.name)),
            machine,
        }],
        enhanced_mesh: job_dir.join("spot.obj.enhanced.stl"),
        model,
        height_mm: HEIGHT_MM,
        strength: Strength::Auto,
        mode: Default::default(),
        slicer: SlicerKind::Prusa,
        // The OBJ is Y-up.
        up: UpAxis::Y,
        profile: None,
        settings: SliceSettings::default(),
        timeout: Duration::from_secs(600),
        compare: false,
        asks: Default::default(),
        observe: Default::default(),
        per_plate: 1,
    }
}

/// The preparation before issue 33: the daemon's steps for `task` with the comparison
/// inline, in this process; seconds.
fn inline_comparison(task: &PrepareTask) -> f64 {
    let mut req = SliceRequest::new(&task.model, task.height_mm);
    req.strength = task.strength;
    req.up = task.up;
    req.timeout = task.timeout;
    req.pictures = task.model.parent().map(Path::to_path_buf);
    req.compare = true;
    let target = Target {
        machine: task.machines[0].machine.clone(),
        output: task.machines[0].output.clone(),
        keep_mesh: Some(task.enhanced_mesh.clone()),
    };
    let t = Instant::now();
    let results = prepare(&req, &[target], &mut |_| {}).expect("Spot is prepared");
    let took = t.elapsed().as_secs_f64();
    let report = results[0].1.as_ref().expect("for the machine");
    assert!(report.walls.is_some(), "compared inline");
    took
}

/// PrusaSlicer alone on `stl` (the placed mesh), with crispen's command line for `machine`.
fn slicer_alone(stl: &Path, machine: &Machine, settings: &SliceSettings, work: &Path) -> f64 {
    let profile = crispen::slice::load_profile(SlicerKind::Prusa, None).expect("the profile");
    let (nozzle_temp_c, bed_temp_c) = settings.temperatures().expect("temperatures");
    let params = profiles::JobParams {
        settings,
        machine,
        nozzle_temp_c,
        bed_temp_c: if machine.heated_bed { bed_temp_c } else { 0.0 },
        height_mm: HEIGHT_MM,
        copies: 1,
    };
    let invocation = profile
        .invocation(
            &params,
            work,
            &[stl.to_path_buf()],
            &work.join("alone.gcode"),
        )
        .expect("the command line");
    let t = Instant::now();
    let status = std::process::Command::new(SlicerKind::Prusa.default_program())
        .args(&invocation.args)
        .envs(invocation.env.iter().map(|(k, v)| (k, v)))
        .stdout(std::process::Stdio::null())
        .stderr(std::process::Stdio::null())
        .status()
        .expect("PrusaSlicer runs");
    assert!(status.success(), "PrusaSlicer failed: {status}");
    t.elapsed().as_secs_f64()
}

fn main() {
    let runs = common::bench_runs(3);
    let program = Path::new(env!("CARGO_BIN_EXE_crispen"));
    let runtime = tokio::runtime::Builder::new_current_thread()
        .enable_all()
        .build()
        .expect("a runtime");
    let cancel = CancellationToken::new();
    let (mut slicer, mut ready, mut compare, mut before) =
        (Vec::new(), Vec::new(), Vec::new(), Vec::new());
    // The steps of `ready` as its report has them.
    let mut steps: Vec<[f64; 5]> = Vec::new();
    let mut ratios = Vec::new();
    for _ in 0..runs {
        let dir = tempfile::tempdir().expect("temporary folder");
        let task = task(dir.path());
        let t = Instant::now();
        let prepared = runtime
            .block_on(run_child(program, &task, &cancel, |_| {}))
            .expect("Spot is prepared");
        let ready_s = t.elapsed().as_secs_f64();
        assert!(prepared.failure().is_none(), "{prepared:?}");
        let timings = &prepared.machines[0].1.as_ref().expect("sliced").timings;
        steps.push([
            timings.load_s,
            timings.enhance_s,
            timings.slice_s,
            timings.check_s,
            timings.total_s,
        ]);
        // Right after the preparation, so that both meet much the same load.
        let work = tempfile::tempdir().expect("temporary folder");
        let slicer_s = slicer_alone(
            &task.enhanced_mesh,
            &task.machines[0].machine,
            &task.settings,
            work.path(),
        );

        let t = Instant::now();
        let measure = PrepareTask {
            compare: true,
            ..task.clone()
        };
        let walls = runtime
            .block_on(run_compare_child(program, &measure, &cancel))
            .expect("the comparison is made");
        let compare_s = t.elapsed().as_secs_f64();
        assert!(walls.layers > 100, "{walls:?}");

        let earlier = tempfile::tempdir().expect("temporary folder");
        let before_s = inline_comparison(&self::task(earlier.path()));
        eprintln!(
            "run: slicer {slicer_s:.2} s, ready {ready_s:.2} s, before {before_s:.2} s, comparison {compare_s:.2} s"
        );
        ratios.push(100.0 * (ready_s - slicer_s) / slicer_s);
        slicer.push(slicer_s);
        ready.push(ready_s);
        compare.push(compare_s);
        before.push(before_s);
    }
    let (slicer, ready, compare, before) = (
        common::median(slicer),
        common::median(ready),
        common::median(compare),
        common::median(before),
    );
    let share = |prepared: f64| 100.0 * (prepared - slicer) / slicer;
    // On a shared machine the slicer's own time varies from run to run by more than
    // crispen adds: the share is also taken within each run, the slicer's run beside the
    // preparation's.
    let paired = common::median(ratios);
    println!("spot@{HEIGHT_MM}mm PrusaSlicer ultimaker2, median of {runs} runs");
    println!("  slicer alone                        {slicer:>7.2} s");
    println!(
        "  crispen until ready                 {ready:>7.2} s  added {:>5.2} s = {:>5.1} % of the slicer's (target <= 10 %)",
        ready - slicer,
        share(ready)
    );
    println!(
        "  crispen's added share, run by run   {paired:>7.1} % (median of each run's (ready - slicer) / slicer)"
    );
    let step = |i: usize| common::median(steps.iter().map(|s| s[i]).collect());
    println!(
        "    its steps: load {:.2} s, enhance {:.2} s, slice {:.2} s, check {:.2} s, total {:.2} s",
        step(0),
        step(1),
        step(2),
        step(3),
        step(4)
    );
    println!(
        "  before issue 33 (comparison inline) {before:>7.2} s  added {:>5.2} s = {:>5.1} % of the slicer's",
        before - slicer,
        share(before)
    );
    println!("  the comparison after ready, niced   {compare:>7.2} s");
}
