//! Benchmark: the camera's bed check. On the bed pictures of `tests/data/bed` (see
//! `scripts/make-bed-pictures`): its false "clear" rate (something left on the bed,
//! found clear: a crash) and false "not clear" rate (an empty bed refused: a person's
//! visit), each case's answer, and the smallest part found; and the time of one check of
//! a 1280 × 720 frame (decoding the frame included, the reference prepared once), on one
//! core (target: under 50 ms). `cargo bench --bench bedcheck` (CRISPEN_BENCH_RUNS changes
//! the timed runs).

#[path = "../tests/common/mod.rs"]
mod common;

fn main() {
    let cases = common::bed::check_all();
    println!(
        "bed check on the pictures of tests/data/bed ({} pictures)",
        cases.len()
    );
    println!(
        "{:<34} {:<10} {:>7} {:<6} {:<10} {:>9} {:>6} {:>6} {:>5}  largest patch",
        "picture", "what", "size_mm", "colour", "light", "expected", "found", "diff%", "thr"
    );
    // CRISPEN_BENCH_MARKED=DIR: the marked picture of each wrong answer, to look at.
    let marked = std::env::var_os("CRISPEN_BENCH_MARKED").map(std::path::PathBuf::from);
    for c in &cases {
        let word = |clear: bool| if clear { "clear" } else { "not" };
        let largest = c
            .verdict
            .patches
            .first()
            .map(|p| match p.size_mm {
                Some([w, h]) => format!("{w:.1} x {h:.1} mm"),
                None => format!("{} x {} px", p.w, p.h),
            })
            .unwrap_or_default();
        if let (Some(dir), true) = (&marked, c.clear != c.verdict.clear) {
            let jpeg =
                crispen::bedcheck::marked_jpeg(&common::bed::read(&c.file), &c.verdict).unwrap();
            std::fs::write(dir.join(&c.file), jpeg).unwrap();
        }
        println!(
            "{:<34} {:<10} {:>7} {:<6} {:<10} {:>9} {:>6} {:>6.2} {:>5.1}  {}{}",
            c.file,
            c.what,
            c.size_mm.map_or("-".into(), |s| format!("{s}")),
            c.colour.as_deref().unwrap_or("-"),
            c.light,
            word(c.clear),
            word(c.verdict.clear),
            c.verdict.differs_percent,
            c.verdict.threshold,
            largest,
            if c.clear == c.verdict.clear {
                ""
            } else {
                "   <-- WRONG"
            }
        );
    }
    let (false_clear, false_not_clear) = common::bed::rates(&cases);
    let empties = cases.iter().filter(|c| c.clear).count();
    println!(
        "false clear: {false_clear:.1} % of {} pictures with something on the bed; false not clear: {false_not_clear:.1} % of {empties} empty beds",
        cases.len() - empties
    );
    let smallest = cases
        .iter()
        .filter(|c| c.what == "part" && !c.verdict.clear)
        .filter_map(|c| c.size_mm)
        .fold(f64::INFINITY, f64::min);
    let every_size_found = |size: f64| {
        cases
            .iter()
            .filter(|c| c.what == "part" && c.size_mm == Some(size))
            .all(|c| !c.verdict.clear)
    };
    let sizes: std::collections::BTreeSet<u64> = cases
        .iter()
        .filter(|c| c.what == "part")
        .filter_map(|c| c.size_mm.map(|s| s as u64))
        .collect();
    let all_found = sizes
        .iter()
        .copied()
        .find(|&s| every_size_found(s as f64))
        .map_or("none".into(), |s| format!("{s} mm"));
    println!("smallest part found: {smallest} mm; smallest size found in every colour and light: {all_found}");

    let runs = common::bench_runs(30);
    let (reference, frame) = common::bed::hd_pair();
    let seconds = common::median_seconds(runs, || reference.check(&frame).unwrap());
    let verdict = reference.check(&frame).unwrap();
    println!(
        "one check of a 1280x720 frame (median of {runs}, one thread): {:.1} ms [{}]",
        seconds * 1000.0,
        verdict.summary()
    );
    let prepare = common::median_seconds(runs.min(10), || {
        crispen::bedcheck::Reference::prepare(
            &common::bed::read("pei-hd-reference.jpg"),
            Some(reference.region()),
            None,
        )
        .unwrap()
    });
    println!("preparing the reference once: {:.1} ms", prepare * 1000.0);
}
