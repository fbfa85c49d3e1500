//! Benchmark: one `crispen observe` of Spot 50 mm tall against 150 mm with four candidates
//! (the plain print and the paper's λ2 = 10, 20 and 40; PrusaSlicer, Ultimaker 2, 0.4 mm
//! nozzle; four views at 40 cm), as the daemon's `strength = "observed"` and the command
//! run it: the slicings (the reference and each candidate, once) and the looking, each
//! timed, the median of a few runs. `cargo bench --bench observe` (CRISPEN_BENCH_RUNS
//! sets the runs; the default is one, each run taking a minute or more).

use crispen::daemon::prepare::steps::observed::{
    observe_model, Candidate, ObserveJob, ObserveSettings, Observing,
};
use crispen::daemon::prepare::steps::{SliceRequest, Step};
use crispen::enhance::Mode;
use crispen::machine::Machine;
use crispen::mesh::place::UpAxis;
use crispen::observe::Conditions;
use std::time::{Duration, Instant};

#[path = "../tests/common/mod.rs"]
mod common;

fn main() {
    let runs = common::bench_runs(1);
    let machine = Machine::builtin("ultimaker2").expect("built in");
    let mut req = SliceRequest::new(common::model("spot.obj"), 50.0);
    req.up = UpAxis::Y;
    let settings = ObserveSettings {
        reference_height_mm: 150.0,
        timeout: Duration::from_secs(3600),
    };
    let conditions = Conditions::default();
    let candidates = Candidate::from_strengths(&[0.0, 10.0, 20.0, 40.0], Mode::Paper);
    println!(
        "observe benchmark: spot 50 mm against 150 mm, {} candidates, {} views (median of {runs}; seconds)\n\
         total_s  slicing_s  looking_s  chosen_λ2",
        candidates.len(),
        conditions.views
    );
    let mut rows = Vec::new();
    for _ in 0..runs {
        let work = tempfile::tempdir().expect("temporary folder");
        let job = ObserveJob {
            machine: &machine,
            candidates: &candidates,
            settings: &settings,
            conditions: &conditions,
            work: work.path(),
            measure_only: true,
            pictures: None,
        };
        let started = Instant::now();
        let mut looking_from: Option<Instant> = None;
        let observation = observe_model(&req, &job, &mut |step| {
            if let Step::Observing(Observing::Looking(..)) = step {
                looking_from.get_or_insert_with(Instant::now);
            }
        })
        .expect("observed");
        let total = started.elapsed().as_secs_f64();
        let looking = looking_from.map_or(0.0, |t| t.elapsed().as_secs_f64());
        let chosen = observation
            .chosen
            .map(|i| observation.candidates[i].strength);
        rows.push((total, total - looking, looking, chosen));
    }
    rows.sort_by(|a, b| a.0.total_cmp(&b.0));
    let (total, slicing, looking, chosen) = rows[rows.len() / 2];
    println!(
        "{total:>7.1} {slicing:>10.1} {looking:>10.1} {:>10}",
        chosen.map_or("-".into(), |l| l.to_string())
    );
}
