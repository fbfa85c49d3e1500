//! Benchmark: the preview of the print drawn from G-code (`crispen::preview::print`), so
//! that drawing it for every job stays cheap next to the slicing. For the bunny at 20 mm
//! and Spot at 25 and 50 mm (PrusaSlicer, Ultimaker 2, 0.4 mm nozzle), sliced plain and
//! enhanced once, it times reading the visible lines of one file, drawing one 400 × 400
//! panel of it, and the whole `preview.png` (three panels and the strip at the printed
//! size, PNG encoded): the median of a few runs; then a synthetic print of 3 million
//! lines, sampled under the cap. `cargo bench --bench print_preview`
//! (CRISPEN_BENCH_RUNS sets the runs).

use crispen::machine::Machine;
use crispen::preview::print::{self, read_print, read_print_file, render_print, PANEL_PX};
use crispen::preview::{Camera, Lighting};

#[path = "../tests/common/mod.rs"]
mod common;

fn main() {
    let runs = common::bench_runs(3);
    let dir = tempfile::tempdir().expect("temporary folder");
    let machine = Machine::builtin("ultimaker2").expect("built in");
    println!(
        "print preview benchmark (median of {runs}; seconds; panel {PANEL_PX} px)\n\
         case              MB  segments stride  read_s  panel_s  preview_s  png_KiB"
    );
    for (model, height) in [("bunny", 20.0), ("spot", 25.0), ("spot", 50.0)] {
        let (paths, _) = common::slice_plain_and_enhanced(dir.path(), &machine, model, height);
        let mb = std::fs::metadata(&paths[0]).map_or(0, |m| m.len()) as f64 / 1e6;
        let read = common::median_seconds(runs, || read_print_file(&paths[0], 0.4).unwrap());
        let plain = read_print_file(&paths[0], 0.4).unwrap();
        let enhanced = read_print_file(&paths[1], 0.4).unwrap();
        let camera = Camera::looking_at(
            plain.bounds().unwrap(),
            [0.5, -0.8, 0.4],
            [0.0, 0.0, 1.0],
            PANEL_PX,
            PANEL_PX,
        );
        let light = Lighting::grazing(&camera, [0.0, 0.0, 1.0], 20.0);
        let panel = common::median_seconds(runs, || render_print(&plain, &camera, &light));
        let mut png = 0;
        let preview = common::median_seconds(runs, || {
            let image = print::preview_picture(None, &plain, Some(&enhanced), PANEL_PX).unwrap();
            png = image.to_png().len();
        });
        println!(
            "{model:<5} {height:>3} mm {mb:>8.1} {:>9} {:>6} {read:>7.3} {panel:>8.3} {preview:>10.3} {:>8}",
            plain.segment_count(),
            plain.stride,
            png / 1024
        );
    }

    // A print far over the cap: 1500 layers of 2000 lines (a 300 mm tower of rings).
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
    let read = common::median_seconds(runs, || {
        read_print(g.as_bytes(), 0.4, print::MAX_SEGMENTS).unwrap()
    });
    let tower = read_print(g.as_bytes(), 0.4, print::MAX_SEGMENTS).unwrap();
    let preview = common::median_seconds(runs, || {
        print::preview_picture(None, &tower, None, PANEL_PX).unwrap()
    });
    println!(
        "tower 300 mm {:>8.1} {:>9} {:>6} {read:>7.3} {:>8} {preview:>10.3}",
        g.len() as f64 / 1e6,
        tower.segment_count(),
        tower.stride,
        "-"
    );

    // 6,000 short moves stacked within 0.3 mm (a purge pattern, or a file crafted so): the
    // camera fits the spot, so every bead covers most of the panel.
    let g = common::stacked_moves(6000, 0.3);
    let read = common::median_seconds(runs, || {
        read_print(g.as_bytes(), 0.4, print::MAX_SEGMENTS).unwrap()
    });
    let stack = read_print(g.as_bytes(), 0.4, print::MAX_SEGMENTS).unwrap();
    let preview = common::median_seconds(runs, || {
        print::preview_picture(None, &stack, None, PANEL_PX).unwrap()
    });
    println!(
        "stack 0.3 mm {:>8.1} {:>9} {:>6} {read:>7.3} {:>8} {preview:>10.3}",
        g.len() as f64 / 1e6,
        stack.segment_count(),
        stack.stride,
        "-"
    );
}
