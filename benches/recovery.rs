//! Benchmark: what line noise costs against the real firmware (`CRISPEN_FIRMWARE_DIR`),
//! through the tests' fault-injecting relay. Per build, a clean 3,000-move job, then the
//! same job under the noise (2 % corrupted lines, 1 % lost whole, 0.5 % lost
//! `ok`s) for `CRISPEN_BENCH_RUNS` seeds (default 5): median and worst time under noise
//! against the clean one. The target is at most 3x (issue 21); the firmware tests prove
//! every run exact, this only times it. Run on a quiet machine: the firmware and the
//! emulator share its cores with the host.
//! `cargo bench --bench recovery`; `CRISPEN_RELAY_TRACE=PREFIX` writes what crossed the
//! relay in each noisy run to `PREFIX.<build>.<seed>`.

#[path = "../tests/common/mod.rs"]
mod common;
use common::relay::{noise, print_through, Build, RelayFaults};

const MOVES: usize = 3000;

fn main() {
    if std::env::var_os("CRISPEN_FIRMWARE_DIR").is_none_or(|d| d.is_empty()) {
        println!("recovery: skipped, CRISPEN_FIRMWARE_DIR is unset (the real firmware's folder)");
        return;
    }
    let dir = common::relay::firmware_dir();
    let runs = common::bench_runs(5) as u64;
    let rt = tokio::runtime::Builder::new_multi_thread()
        .worker_threads(2)
        .enable_all()
        .build()
        .unwrap();
    println!("recovery: {MOVES} moves, {runs} noisy seeds per build");
    for build in Build::ALL {
        let clean = rt.block_on(print_through(&dir, build, RelayFaults::default(), MOVES));
        if let Err(e) = &clean.result {
            println!("{:<24} clean run failed: {e}", build.name());
            continue;
        }
        let clean = clean.took.as_secs_f64();
        let mut noisy = Vec::new();
        for seed in 0..runs {
            let o = rt.block_on(print_through(&dir, build, noise(seed), MOVES));
            if let Some(prefix) = std::env::var_os("CRISPEN_RELAY_TRACE") {
                let mut path = prefix;
                path.push(format!(".{}.{seed}", build.name()));
                let text: String = o
                    .log
                    .wire
                    .iter()
                    .map(|(t, d, l)| format!("{t:>9.3} {d} {l}\n"))
                    .collect();
                std::fs::write(path, text).unwrap();
            }
            if let Err(e) = &o.result {
                println!("{:<24} seed {seed} failed: {e}", build.name());
                continue;
            }
            noisy.push(o.took.as_secs_f64());
        }
        if noisy.is_empty() {
            continue;
        }
        let worst = noisy.iter().copied().fold(0.0, f64::max);
        let median = common::median(noisy);
        println!(
            "{:<24} clean {clean:5.2} s   noisy median {median:5.2} s ({:.2}x)   worst {worst:5.2} s ({:.2}x)",
            build.name(),
            median / clean,
            worst / clean
        );
    }
}
