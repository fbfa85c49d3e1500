//! Benchmark: one job's preparation (load, enhance, place, slice) end to end, per slicer and model, with the time of
//! each step (load, enhance, slice, check). Prints one comparable line per case: the median
//! of a few runs. `cargo bench --bench slice` (set CRISPEN_BENCH_RUNS to change the runs).

use crispen::daemon::prepare::steps::{prepare_one, SliceRequest, Target};
use crispen::enhance::Strength;
use crispen::machine::Machine;
use crispen::mesh::place::UpAxis;
use crispen::slice::{SliceReport, SlicerKind};

#[path = "../tests/common/mod.rs"]
mod common;

fn um2(dir: &std::path::Path) -> Target {
    Target {
        machine: Machine::builtin("ultimaker2").expect("built in"),
        output: dir.join("bench.gcode"),
        keep_mesh: None,
    }
}

fn main() {
    let runs = common::bench_runs(3);
    let cases = [
        ("spot", common::model("spot.obj"), 30.0),
        ("bunny", common::model("bunny.obj"), 40.0),
    ];
    let dir = tempfile::tempdir().expect("temporary folder");
    println!(
        "case                         load_s enhance_s  slice_s  check_s  total_s layers  lines"
    );
    for (name, model, height) in &cases {
        for slicer in [SlicerKind::Prusa, SlicerKind::Cura] {
            for strength in [Strength::Off, Strength::Auto] {
                let mut req = SliceRequest::new(model, *height);
                req.slicer = slicer;
                req.strength = strength;
                // Both models are Y-up OBJ files.
                req.up = UpAxis::Y;
                let reports: Vec<SliceReport> = (0..runs)
                    .map(|_| match prepare_one(&req, um2(dir.path()), &mut |_| {}) {
                        Ok(r) => r,
                        Err(e) => panic!("{name} with {slicer}: {e}"),
                    })
                    .collect();
                let m =
                    |f: fn(&SliceReport) -> f64| common::median(reports.iter().map(f).collect());
                let label = format!(
                    "{name}@{height}mm {slicer} {}",
                    if strength == Strength::Off {
                        "plain"
                    } else {
                        "auto"
                    }
                );
                println!(
                    "{label:<28} {:>6.3} {:>9.3} {:>8.3} {:>8.3} {:>8.3} {:>6} {:>6}",
                    m(|r| r.timings.load_s),
                    m(|r| r.timings.enhance_s),
                    m(|r| r.timings.slice_s),
                    m(|r| r.timings.check_s),
                    m(|r| r.timings.total_s),
                    reports[0].layer_count,
                    reports[0].gcode_lines,
                );
            }
        }
    }
}
