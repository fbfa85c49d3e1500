//! Benchmark of the farm's queue in PostgreSQL (src/daemon/store/postgres), at the store's level:
//! 1,000 ready jobs, 60 printers across 3 hosts (three stores, each with its own pool, in
//! one process), every printer claiming its next job the moment it is free and finishing it
//! at once, so the figures are the queue's own cost with no printing in between.
//!
//! Prints claims per second, the time from a printer being free to holding its next job
//! (median, 99th percentile, worst), and the database's CPU (every server process's
//! utime+stime from /proc) per claim. The server is a real one started for the run, as the
//! tests start it (tests/common/postgres.rs). `cargo bench --bench claims`.
//!
//! Not measured here: the daemons themselves (their supervisors, the wake-up after a job
//! becomes ready); that needs the store wired into the daemon.

#[path = "../tests/common/mod.rs"]
mod common;

use common::farm::process_cpu_s;
use common::postgres::PgServer;
use crispen::daemon::config::PgSettings;
use crispen::daemon::job::JobState;
use crispen::daemon::store::postgres::PgStore;
use std::time::{Duration, Instant};

const JOBS: usize = 1000;
const HOSTS: usize = 3;
const PRINTERS_PER_HOST: usize = 20;

fn percentile(sorted: &[Duration], p: f64) -> Duration {
    sorted[((sorted.len() - 1) as f64 * p).round() as usize]
}

fn main() {
    let pg = PgServer::start();
    let rt = tokio::runtime::Builder::new_multi_thread()
        .enable_all()
        .build()
        .unwrap();
    let settings = PgSettings {
        conninfo: pg.conninfo(),
        password_file: None,
    };
    let printers: Vec<String> = (0..HOSTS * PRINTERS_PER_HOST)
        .map(|i| format!("p{i:02}"))
        .collect();
    let (wall, latencies, cpu) = rt.block_on(async {
        let mut hosts = Vec::new();
        for h in 0..HOSTS {
            let store = PgStore::connect(&settings, &format!("rack-{h}"), Duration::from_secs(60))
                .await
                .unwrap();
            for p in &printers[h * PRINTERS_PER_HOST..(h + 1) * PRINTERS_PER_HOST] {
                store.register_printer(p, None).await.unwrap();
            }
            hosts.push(store);
        }
        // 1,000 ready jobs any printer may take.
        for i in 0..JOBS {
            hosts[i % HOSTS]
                .admit("part.gcode", "/srv/in", &printers, &[], None)
                .await
                .unwrap();
            let job = hosts[i % HOSTS].claim_preparation().await.unwrap().unwrap();
            hosts[i % HOSTS]
                .finish(&job.id, &[JobState::Preparing], JobState::Ready, None)
                .await
                .unwrap();
        }
        let cpu_before = process_cpu_s(pg.pid(), true);
        let start = Instant::now();
        let mut tasks = Vec::new();
        for (h, store) in hosts.iter().enumerate() {
            for p in &printers[h * PRINTERS_PER_HOST..(h + 1) * PRINTERS_PER_HOST] {
                let (store, printer) = (store.clone(), p.clone());
                tasks.push(tokio::spawn(async move {
                    let mut waits = Vec::new();
                    loop {
                        let free = Instant::now();
                        let Some(job) = store.claim_print(&printer).await.unwrap() else {
                            break;
                        };
                        waits.push(free.elapsed());
                        store
                            .finish(&job.id, &[JobState::Printing], JobState::Done, None)
                            .await
                            .unwrap();
                    }
                    waits
                }));
            }
        }
        let mut latencies = Vec::new();
        for task in tasks {
            latencies.extend(task.await.unwrap());
        }
        let wall = start.elapsed();
        (wall, latencies, process_cpu_s(pg.pid(), true) - cpu_before)
    });
    let mut sorted = latencies;
    sorted.sort();
    assert_eq!(sorted.len(), JOBS, "every job claimed exactly once");
    println!(
        "claims: {JOBS} jobs, {} printers on {HOSTS} hosts: {:.0} claims/s (claim + finish each), {:.2} s in all",
        HOSTS * PRINTERS_PER_HOST,
        JOBS as f64 / wall.as_secs_f64(),
        wall.as_secs_f64()
    );
    println!(
        "free to next job: median {:.1} ms, p99 {:.1} ms, worst {:.1} ms",
        percentile(&sorted, 0.5).as_secs_f64() * 1e3,
        percentile(&sorted, 0.99).as_secs_f64() * 1e3,
        sorted.last().unwrap().as_secs_f64() * 1e3
    );
    println!(
        "database CPU: {:.2} s in all, {:.2} ms per claim",
        cpu,
        cpu * 1e3 / JOBS as f64
    );
}
