//! Benchmark: the G-code measure's cost (`crispen::slice::walls`), so that comparing every
//! enhanced job with its unmodified slicing stays affordable next to the slicing itself.
//! For the bunny at 20 mm and Spot at 25, 50 and 100 mm (PrusaSlicer, Ultimaker 2, 0.4 mm
//! nozzle), sliced plain and enhanced once, it times reading both files' outer walls and
//! comparing them: the median of a few runs. (The bunny's open base makes PrusaSlicer
//! leave empty layers in it unmodified above about 40 mm.) `cargo bench --bench walls` (CRISPEN_BENCH_RUNS sets the runs).

use crispen::machine::Machine;
use crispen::slice::walls;
use std::time::Instant;

#[path = "../tests/common/mod.rs"]
mod common;

fn main() {
    let runs = common::bench_runs(3);
    let dir = tempfile::tempdir().expect("temporary folder");
    let machine = Machine::builtin("ultimaker2").expect("built in");
    println!("case          slice_s  MB(2 files)  segments  samples  read_s  compare_s  total_s");
    for (model, height) in [
        ("bunny", 20.0),
        ("spot", 25.0),
        ("spot", 50.0),
        ("spot", 100.0),
    ] {
        let (paths, slice_s) =
            common::slice_plain_and_enhanced(dir.path(), &machine, model, height);
        let bytes: u64 = paths
            .iter()
            .map(|p| std::fs::metadata(p).map_or(0, |m| m.len()))
            .sum();
        let (mut read, mut cmp, mut last) = (Vec::new(), Vec::new(), None);
        for _ in 0..runs {
            let t = Instant::now();
            let read_walls = |p: &std::path::Path| {
                walls::outer_walls(std::io::BufReader::new(std::fs::File::open(p).unwrap()))
                    .unwrap()
            };
            let (plain, enhanced) = (read_walls(&paths[0]), read_walls(&paths[1]));
            read.push(t.elapsed().as_secs_f64());
            let t = Instant::now();
            let c = walls::compare(&plain, &enhanced, 0.4);
            cmp.push(t.elapsed().as_secs_f64());
            last = Some((plain.segment_count() + enhanced.segment_count(), c.samples));
        }
        let (segments, samples) = last.unwrap();
        let (r, c) = (common::median(read), common::median(cmp));
        println!(
            "{model:<5} {height:>3} mm {slice_s:>8.2} {:>12.1} {segments:>9} {samples:>8} {r:>7.3} {c:>10.3} {:>8.3}",
            bytes as f64 / 1e6,
            r + c
        );
    }
}
