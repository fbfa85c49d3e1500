//! Enhancement benchmark: time per phase and peak memory for the bunny, Nefertiti and a
//! subdivided Nefertiti (0.8 M vertices) and a subdivided Homer (1.01 M), plus the whole
//! `crispen enhance` process from file to file on the bunny and on the 1 M mesh.
//!
//! Each case runs in a child process (this binary re-executed with `--case NAME`) so its
//! peak resident memory (VmHWM) is its own. Run with `cargo bench --bench enhance`;
//! `-- --quick` skips the large meshes.

use crispen::enhance::{Bands, EnhanceOptions, Phase, Solver};
use crispen::mesh::{self, Mesh};
use nix::sys::resource::{getrusage, UsageWho};
use std::path::Path;
use std::process::Command;
use std::time::Instant;

#[path = "../tests/common/mod.rs"]
mod common;

fn peak_rss_mib() -> f64 {
    let status = std::fs::read_to_string("/proc/self/status").unwrap_or_default();
    status
        .lines()
        .find(|l| l.starts_with("VmHWM:"))
        .and_then(|l| l.split_whitespace().nth(1))
        .and_then(|kb| kb.parse::<f64>().ok())
        .map_or(f64::NAN, |kb| kb / 1024.0)
}

/// MODEL or MODEL-xK: a model of tests/data, or it subdivided with k segments per edge.
fn case_mesh(name: &str) -> Mesh {
    let (model, k) = match name.split_once("-x") {
        Some((model, k)) => (model, k.parse().expect("case MODEL-xK")),
        None => (name, 1),
    };
    let base = mesh::load(&common::model(&format!("{model}.obj")))
        .unwrap()
        .mesh;
    if k == 1 {
        base
    } else {
        common::subdivide(&base, k)
    }
}

/// One case, in this (child) process: load or make the mesh, compute bands, combine,
/// write; print one line of figures.
fn run_case(name: &str, solver: &str) {
    let t = Instant::now();
    let mesh = case_mesh(name);
    let load_s = t.elapsed().as_secs_f64();
    let t = Instant::now();
    let chosen = match solver {
        "cholesky" => Solver::Cholesky,
        "cg" => Solver::ConjugateGradient,
        _ => Solver::Auto,
    };
    let bands = Bands::compute_with(&mesh, chosen, &mut |_: Phase| {}).unwrap();
    let compute_s = t.elapsed().as_secs_f64();
    let t = Instant::now();
    let combined = bands.combine(&EnhanceOptions::with_lambda2(20.0)).unwrap();
    let combine_s = t.elapsed().as_secs_f64();
    let out = Mesh {
        vertices: combined.vertices,
        faces: mesh.faces.clone(),
    };
    let dir = tempfile::tempdir().unwrap();
    let t = Instant::now();
    mesh::save(&dir.path().join("out.stl"), &out).unwrap();
    let save_s = t.elapsed().as_secs_f64();
    let tm = &bands.timings;
    println!(
        "{name:<14} {solver:<8} {:>9} {:>9} | load/make {:>6.3} | operators {:>6.3} | factorize {:>6.3} (symbolic {:>6.3}) | solve {:>6.3} | combine {:>6.4} | save stl {:>6.3} | enhance total {:>6.3} s | residual {:.1e} | peak {:>7.1} MiB",
        mesh.vertices.len(),
        mesh.faces.len(),
        load_s,
        tm.operators_s,
        tm.factorize_s,
        tm.symbolic_s,
        tm.solve_s,
        combine_s,
        save_s,
        compute_s + combine_s,
        bands.residuals.iter().copied().fold(0.0, f64::max),
        peak_rss_mib(),
    );
}

fn main() {
    let args: Vec<String> = std::env::args().collect();
    if let Some(i) = args.iter().position(|a| a == "--case") {
        run_case(&args[i + 1], args.get(i + 2).map_or("auto", String::as_str));
        return;
    }
    if let Some(i) = args.iter().position(|a| a == "--write-mesh") {
        // For profiling outside the benchmark: `-- --write-mesh homer-x13 /tmp/big.obj`.
        mesh::save(Path::new(&args[i + 2]), &case_mesh(&args[i + 1])).unwrap();
        return;
    }
    if let Some(i) = args.iter().position(|a| a == "--file-to-file") {
        let runs = args[i + 2]
            .parse()
            .expect("--file-to-file INPUT RUNS OUTDIR");
        run_file_to_file(Path::new(&args[i + 1]), runs, Path::new(&args[i + 3]));
        return;
    }
    let quick = args.iter().any(|a| a == "--quick");
    let exe = std::env::current_exe().unwrap();
    println!(
        "enhance benchmark ({} CPUs; lambda2 = 20; times in seconds, one line per run)",
        std::thread::available_parallelism().map_or(1, |n| n.get())
    );
    println!(
        "{:<14} {:<8} {:>9} {:>9}",
        "mesh", "solver", "vertices", "faces"
    );
    let mut cases: Vec<(&str, &str, usize)> = vec![
        ("bunny", "cholesky", 3),
        ("bunny", "cg", 3),
        ("nefertiti", "cholesky", 3),
        ("nefertiti", "cg", 3),
        ("nefertiti", "auto", 1),
        ("bunny", "auto", 1),
    ];
    if !quick {
        // k = 2: ~200 k vertices, above the 134 k-vertex scan that libigl + CHOLMOD needs
        // about 8 s for (crispen's target there: 5x faster, i.e. under 1.6 s).
        cases.push(("nefertiti-x2", "auto", 1));
        // k = 4 splits each edge in four (= midpoint subdivision twice): ~0.8 M vertices.
        // Conjugate gradients need ~35 s at 0.8 M (their iteration count grows with the
        // resolution), so only the automatic choice (Cholesky) runs for these.
        cases.push(("nefertiti-x4", "auto", 1));
        // homer.obj has 6 k vertices: k = 13 makes 1.01 M, the 1 M target itself.
        cases.push(("homer-x13", "auto", 1));
    }
    for (case, solver, repeats) in cases {
        for _ in 0..repeats {
            let status = Command::new(&exe)
                .args(["--case", case, solver])
                .status()
                .unwrap();
            assert!(status.success(), "case {case} failed");
        }
    }

    // The whole process, file to file, as a user runs it.
    let dir = tempfile::tempdir().unwrap();
    file_to_file(&exe, &common::model("bunny.obj"), 7, dir.path());
    if !quick {
        let big = dir.path().join("homer-x13.obj");
        mesh::save(&big, &case_mesh("homer-x13")).unwrap();
        file_to_file(&exe, &big, 2, dir.path());
    }
}

/// Runs `crispen enhance INPUT` (λ2 = 20) as its own process from a child of the
/// benchmark, so that the children's peak memory is only crispen's.
fn file_to_file(exe: &Path, input: &Path, runs: usize, out_dir: &Path) {
    let status = Command::new(exe)
        .arg("--file-to-file")
        .args([input, Path::new(&runs.to_string()), out_dir])
        .status()
        .unwrap();
    assert!(
        status.success(),
        "file-to-file run on {} failed",
        input.display()
    );
}

fn run_file_to_file(input: &Path, runs: usize, out_dir: &Path) {
    let crispen = env!("CARGO_BIN_EXE_crispen");
    let name = input.file_stem().unwrap().to_string_lossy();
    let output = out_dir.join(format!("{name}-enhanced.stl"));
    let mut times = Vec::new();
    let mut report = serde_json::Value::Null;
    for _ in 0..runs {
        let t = Instant::now();
        let out = Command::new(crispen)
            .arg("enhance")
            .arg(input)
            .arg("-o")
            .arg(&output)
            .args(["--strength", "20", "--json"])
            .env("RUST_LOG", "warn")
            .output()
            .unwrap();
        assert!(
            out.status.success(),
            "{}",
            String::from_utf8_lossy(&out.stderr)
        );
        times.push(t.elapsed().as_secs_f64());
        report = serde_json::from_slice(&out.stdout).expect("crispen enhance --json report");
    }
    times.sort_by(f64::total_cmp);
    let phase = |key: &str| report["timings"][key].as_f64().unwrap_or(f64::NAN);
    let usage = getrusage(UsageWho::RUSAGE_CHILDREN).unwrap();
    println!(
        "crispen enhance {name}.obj -> {name}-enhanced.stl (whole process, {runs} runs): best {:.3} s, median {:.3} s (last run: load {:.3} s, enhance {:.3} s, save {:.3} s), peak {:.1} MiB",
        times[0],
        times[times.len() / 2],
        phase("load_s"),
        phase("total_s") - phase("load_s") - phase("save_s"),
        phase("save_s"),
        usage.max_rss() as f64 / 1024.0
    );
}
