//! Benchmark: the preview of the print drawn from G-code (`crispen::preview::print`), so
//! that drawing it for every job stays cheap next to the slicing, and costs at most what
//! its picture and its file bound whatever the file. For the bunny at 20 mm and Spot at 25
//! and 50 mm (PrusaSlicer, Ultimaker 2, 0.4 mm nozzle), sliced plain and enhanced once, it
//! times reading the visible lines of one file, drawing one 400 × 400 panel of it, and the
//! whole `preview.png` (three panels and the strip at the printed size, PNG encoded): the
//! median of a few runs; then a synthetic print of 3 million lines, sampled under the cap,
//! and 6,000 short lines stacked within 0.3 mm (a purge pattern, or a file crafted so),
//! drawn alone as a pre-sliced job's is. Each row also counts the panel's work: the beads
//! drawn, the rays cast per sample, the samples that reached the rays' cap and the beads
//! left out past the rows' budget, and the CPU seconds (all threads) of one preview.
//! `cargo bench --bench print_preview` (CRISPEN_BENCH_RUNS sets the runs;
//! CRISPEN_BENCH_CASES=stack,tower runs only the cases whose names hold one of those words).

use crispen::machine::Machine;
use crispen::preview::print::{
    self, read_print, read_print_file, render_print_counted, DrawWork, Print, PANEL_PX,
};
use crispen::preview::{Camera, Lighting};

#[path = "../tests/common/mod.rs"]
mod common;

fn main() {
    let runs = common::bench_runs(3);
    let dir = tempfile::tempdir().expect("temporary folder");
    let machine = Machine::builtin("ultimaker2").expect("built in");
    println!(
        "print preview benchmark (median of {runs}; seconds; panel {PANEL_PX} px)\n\
         case              MB  segments stride  read_s  panel_s  preview_s  cpu_s  png_KiB    beads rays/sample capped left_out"
    );
    for (model, height) in [("bunny", 20.0), ("spot", 25.0), ("spot", 50.0)] {
        if !wanted(model) {
            continue;
        }
        let (paths, _) = common::slice_plain_and_enhanced(dir.path(), &machine, model, height);
        let mb = std::fs::metadata(&paths[0]).map_or(0, |m| m.len()) as f64 / 1e6;
        let read = common::median_seconds(runs, || read_print_file(&paths[0], 0.4).unwrap());
        let plain = read_print_file(&paths[0], 0.4).unwrap();
        let enhanced = read_print_file(&paths[1], 0.4).unwrap();
        row(
            &format!("{model:<5} {height:>3} mm"),
            runs,
            mb,
            read,
            &plain,
            Some(&enhanced),
        );
    }

    // A print far over the cap: 1500 layers of 2000 lines (a 300 mm tower of rings).
    if wanted("tower") {
        synthetic("tower 300 mm", runs, &tower());
    }

    // 6,000 short moves stacked within 0.3 mm: the camera fits the spot, so every bead
    // covers most of the panel and reaches in front of the others.
    if wanted("stack") {
        synthetic("stack 0.3 mm", runs, &common::stacked_moves(6000, 0.3));
    }
}

/// Whether the case `name` is to run (CRISPEN_BENCH_CASES, all when unset).
fn wanted(name: &str) -> bool {
    std::env::var("CRISPEN_BENCH_CASES").map_or(true, |cases| {
        cases.split(',').any(|c| name.contains(c.trim()))
    })
}

/// CPU seconds this process has used, all threads.
fn cpu_seconds() -> f64 {
    use nix::sys::resource::{getrusage, UsageWho};
    let u = getrusage(UsageWho::RUSAGE_SELF).expect("getrusage");
    let s = |t: nix::sys::time::TimeVal| t.tv_sec() as f64 + t.tv_usec() as f64 / 1e6;
    s(u.user_time()) + s(u.system_time())
}

fn tower() -> String {
    let mut g = String::from("G90\nM83\n;TYPE:External perimeter\n");
    for layer in 1..=1500 {
        g += &format!("G1 Z{:.2}\n", 0.2 * layer as f64);
        for i in 0..=2000 {
            let a = i as f64 / 2000.0 * std::f64::consts::TAU;
            g += &format!(
                "G1 X{:.3} Y{:.3} E0.01\n",
                100.0 + 20.0 * a.cos(),
                100.0 + 20.0 * a.sin()
            );
        }
    }
    g
}

/// A G-code file of our own, read and drawn alone (as a pre-sliced job's preview is).
fn synthetic(case: &str, runs: usize, g: &str) {
    let read = common::median_seconds(runs, || {
        read_print(g.as_bytes(), 0.4, print::MAX_SEGMENTS).unwrap()
    });
    let p = read_print(g.as_bytes(), 0.4, print::MAX_SEGMENTS).unwrap();
    row(case, runs, g.len() as f64 / 1e6, read, &p, None);
}

/// One row: a panel of `plain` from a three-quarter camera (timed and counted) and the
/// whole preview of `plain` and `enhanced`.
fn row(case: &str, runs: usize, mb: f64, read: f64, plain: &Print, enhanced: Option<&Print>) {
    let camera = Camera::looking_at(
        plain.bounds().unwrap(),
        [0.5, -0.8, 0.4],
        [0.0, 0.0, 1.0],
        PANEL_PX,
        PANEL_PX,
    );
    let light = Lighting::grazing(&camera, [0.0, 0.0, 1.0], 20.0);
    let mut work = DrawWork::default();
    let panel = common::median_seconds(runs, || {
        work = render_print_counted(plain, &camera, &light).1;
    });
    let mut png = 0;
    let cpu = cpu_seconds();
    let preview = common::median_seconds(runs, || {
        let image = print::preview_picture(None, plain, enhanced, PANEL_PX).unwrap();
        png = image.to_png().len();
    });
    let cpu = (cpu_seconds() - cpu) / runs as f64;
    println!(
        "{case:<12} {mb:>8.1} {:>9} {:>6} {read:>7.3} {panel:>8.3} {preview:>10.3} {cpu:>6.2} {:>8} {:>8} {:>11.2} {:>6} {:>8}",
        plain.segment_count(),
        plain.stride,
        png / 1024,
        work.beads,
        work.rays as f64 / work.samples as f64,
        work.capped,
        work.beads_left_out,
    );
}
