//! Benchmark: the pictures of a job. Per mesh, the time to render the before, after and
//! heat-map pictures at 800 × 800 (rendering only, then PNG encoding), and the two G-code
//! thumbnails, as the median of a few runs. The goal is well under a second for 200 k
//! triangles. `cargo bench --bench render` (CRISPEN_BENCH_RUNS changes the runs).

use crispen::enhance::{self, EnhanceOptions};
use crispen::mesh::place::UpAxis;
use crispen::mesh::{self, Mesh};
use crispen::preview::{self, thumbnail};

#[path = "../tests/common/mod.rs"]
mod common;

fn main() {
    let runs = common::bench_runs(5);
    let load = |name: &str| mesh::load(&common::model(name)).unwrap().mesh;
    let homer = load("homer.obj");
    let cases: Vec<(&str, Mesh)> = vec![
        ("spot", load("spot.obj")),
        ("bunny", load("bunny.obj")),
        ("nefertiti", load("nefertiti.obj")),
        ("homer-x4", common::subdivide(&homer, 4)),
    ];
    println!(
        "render benchmark (median of {runs}; seconds; three 800x800 pictures, two thumbnails)"
    );
    println!(
        "{:<10} {:>9} {:>10} {:>8} {:>8} {:>11}",
        "mesh", "faces", "render_3_s", "png_3_s", "total_s", "thumbnail_s"
    );
    for (name, before) in &cases {
        let (after, _) =
            enhance::enhance(before, &EnhanceOptions::with_lambda2(20.0), &mut |_| {}).unwrap();
        let render = common::median_seconds(runs, || {
            preview::pictures(before, &after, UpAxis::Y, 800).unwrap()
        });
        let pictures = preview::pictures(before, &after, UpAxis::Y, 800).unwrap();
        let png = common::median_seconds(runs, || {
            [&pictures.before, &pictures.after, &pictures.displacement].map(|i| i.to_png())
        });
        let thumbnails = common::median_seconds(runs, || thumbnail::blocks(&after, UpAxis::Y));
        println!(
            "{:<10} {:>9} {:>10.3} {:>8.3} {:>8.3} {:>11.3}",
            name,
            before.faces.len(),
            render,
            png,
            render + png,
            thumbnails
        );
    }
}
