//! Benchmark of the farm's queue with real daemons: three `crispen run` hosts sharing one
//! PostgreSQL server (tests/common/farm.rs), 60 simulated printers among them (instant
//! time scale), 1,000 tiny pre-sliced G-code files dropped into the hosts' hot folders.
//!
//! First every printer prints one warm-up job and holds it on its bed; then the 1,000
//! jobs are dropped and prepared (figure: jobs admitted and ready per second); then every
//! bed is cleared through the control socket (`POST /api/v1/printers/{name}/clear`) and
//! cleared again each time a print ends, until all are printed. Figures, comparable
//! with benches/claims.rs (the store alone):
//! - claims per second: jobs over the time from the first clear to the last claim;
//! - free to next job: from the clear request being sent to the job's `printing` entry in
//!   the database's history (the claim's transaction), per printer; median, p99, worst;
//! - the database server's CPU (postmaster and its children, utime+stime from /proc) per
//!   claim, and the three daemons' for comparison.
//!
//! The bench polls `GET /api/v1/printers` on each host every 50 ms (one thread per host)
//! to see beds to clear, and clears all it finds at once; that polling is part of the
//! daemons' CPU. The database's CPU includes the hosts' own upkeep meanwhile (leases,
//! reading each other's changes every second).
//! `cargo bench --bench farm`; `CRISPEN_BENCH_JOBS` and `CRISPEN_BENCH_PRINTERS` make it
//! smaller (e.g. 100 and 9) for a quick try.

#[path = "../tests/common/mod.rs"]
mod common;

use common::farm::{drop_file, presliced_gcode, process_cpu_s, Farm, HostSpec};
use serde_json::Value;
use std::collections::BTreeMap;
use std::sync::atomic::{AtomicUsize, Ordering};
use std::sync::Mutex;
use std::time::{Duration, Instant, SystemTime, UNIX_EPOCH};

const HOSTS: usize = 3;

fn env_or(name: &str, default: usize) -> usize {
    match std::env::var(name) {
        Ok(v) => v
            .parse()
            .unwrap_or_else(|_| panic!("{name}={v:?} is not a number")),
        Err(_) => default,
    }
}

fn now_s() -> f64 {
    SystemTime::now()
        .duration_since(UNIX_EPOCH)
        .unwrap()
        .as_secs_f64()
}

fn percentile(sorted: &[f64], p: f64) -> f64 {
    sorted[((sorted.len() - 1) as f64 * p).round() as usize]
}

/// The printers of `host` as it reports them: name, state, bed cleared; `None` while
/// it does not answer.
fn printers_of(farm: &Farm, host: usize) -> Option<Vec<(String, String, bool)>> {
    let h = &farm.hosts[host];
    let (code, body) = h.http("GET", "/api/v1/printers").ok()?;
    assert_eq!(code, 200, "GET /api/v1/printers on {}: {body}", h.name);
    let list: Vec<Value> = serde_json::from_str(&body).unwrap();
    Some(
        list.iter()
            .filter(|p| h.printers.iter().any(|n| p["name"] == n.as_str()))
            .map(|p| {
                (
                    p["name"].as_str().unwrap().to_string(),
                    p["state"].as_str().unwrap_or("").to_string(),
                    p["bed_cleared"] != false,
                )
            })
            .collect(),
    )
}

/// Clears `printer`'s bed through its own host; false when it was already clear (the
/// host's view was behind).
fn clear(farm: &Farm, host: usize, printer: &str) -> bool {
    let h = &farm.hosts[host];
    let path = format!("/api/v1/printers/{printer}/clear");
    let (code, body) = h
        .http("POST", &path)
        .unwrap_or_else(|e| panic!("POST {path} on {}: {e}", h.name));
    assert!(
        (200..300).contains(&code),
        "POST {path} on {}: {code} {body}",
        h.name
    );
    !body.contains("already clear")
}

/// Polls until `done` holds, panicking with the logs after `limit` without progress.
fn wait(farm: &Farm, limit: Duration, what: &str, mut done: impl FnMut() -> bool) {
    farm.wait_until(limit, what, |_| done().then_some(()));
}

fn count(farm: &Farm, state: &str) -> usize {
    let rows = farm.query("SELECT count(*) FROM jobs WHERE state = $1", &[&state]);
    rows[0].get::<_, i64>(0) as usize
}

fn main() {
    let jobs = env_or("CRISPEN_BENCH_JOBS", 1000);
    let printers = env_or("CRISPEN_BENCH_PRINTERS", 60).max(HOSTS);
    let names: Vec<Vec<String>> = (0..HOSTS)
        .map(|h| {
            (h..printers)
                .step_by(HOSTS)
                .map(|i| format!("h{h}p{i:02}"))
                .collect()
        })
        .collect();
    let everyone: Vec<String> = names.iter().flatten().cloned().collect();
    let specs: Vec<HostSpec> = (0..HOSTS)
        .map(|h| HostSpec {
            name: format!("rack-{h}"),
            printers: names[h].clone(),
            folders: vec![(format!("hot/{h}"), everyone.clone())],
            time_scale: 0.0,
            lease_s: None,
        })
        .collect();
    let farm = Farm::start(&specs);
    let folder = |i: usize| farm.root.join(format!("hot/{}", i % HOSTS));
    wait(
        &farm,
        Duration::from_secs(300),
        "every printer idle",
        || {
            (0..HOSTS).all(|h| {
                printers_of(&farm, h).is_some_and(|ps| {
                    ps.len() == names[h].len() && ps.iter().all(|p| p.1 == "idle")
                })
            })
        },
    );

    // Warm-up: one job per printer, after which every printer holds its bed.
    for i in 0..printers {
        let gcode = presliced_gcode(&format!("warm-{i}"), 4, 6000);
        drop_file(&folder(i), &format!("warm-{i:03}.gcode"), gcode.as_bytes());
    }
    wait(
        &farm,
        Duration::from_secs(600),
        "the warm-up printed",
        || (0..HOSTS).all(|h| printers_of(&farm, h).is_some_and(|ps| ps.iter().all(|p| !p.2))),
    );

    // The queue: every job dropped, admitted and prepared while no bed is free.
    let started = Instant::now();
    for i in 0..jobs {
        let gcode = presliced_gcode(&format!("job-{i}"), 4, 6000);
        drop_file(&folder(i), &format!("job-{i:04}.gcode"), gcode.as_bytes());
    }
    wait(&farm, Duration::from_secs(1800), "every job ready", || {
        let failed = count(&farm, "failed");
        assert_eq!(failed, 0, "jobs failed\n{}", farm.diagnostics());
        count(&farm, "ready") == jobs
    });
    let admitted = started.elapsed();

    // The claims: clear every bed, and each again as soon as its print ends.
    let cpu = |pids: &[u32], children: bool| -> f64 {
        pids.iter().map(|&p| process_cpu_s(p, children)).sum()
    };
    let daemons: Vec<u32> = farm.hosts.iter().filter_map(|h| h.pid()).collect();
    let (db_before, hosts_before) = (cpu(&[farm.pg.pid()], true), cpu(&daemons, false));
    let first_clear = now_s();
    let start = Instant::now();
    // One thread per host watches its printers; the beds it finds held are cleared at
    // once, all together, so the bench's own round trips do not queue the claims.
    let clears: Mutex<BTreeMap<String, Vec<f64>>> = Mutex::new(BTreeMap::new());
    let cleared = AtomicUsize::new(0);
    let last_progress = Mutex::new(Instant::now());
    let all = printers + jobs;
    std::thread::scope(|scope| {
        for h in 0..HOSTS {
            let (farm, clears, cleared, last_progress) = (&farm, &clears, &cleared, &last_progress);
            scope.spawn(move || {
                while cleared.load(Ordering::SeqCst) < all {
                    let held: Vec<String> = printers_of(farm, h)
                        .unwrap_or_else(|| {
                            panic!(
                                "host {} stopped answering\n{}",
                                farm.hosts[h].name,
                                farm.diagnostics()
                            )
                        })
                        .into_iter()
                        .filter(|(_, state, bed_cleared)| !bed_cleared && state != "printing")
                        .map(|(name, _, _)| name)
                        .collect();
                    std::thread::scope(|each| {
                        for name in held {
                            each.spawn(move || {
                                let sent = now_s();
                                if clear(farm, h, &name) {
                                    clears.lock().unwrap().entry(name).or_default().push(sent);
                                    cleared.fetch_add(1, Ordering::SeqCst);
                                    *last_progress.lock().unwrap() = Instant::now();
                                }
                            });
                        }
                    });
                    let stalled = last_progress.lock().unwrap().elapsed();
                    assert!(
                        stalled < Duration::from_secs(300),
                        "no print ended for 300 s; {} of {all} beds cleared\n{}",
                        cleared.load(Ordering::SeqCst),
                        farm.diagnostics()
                    );
                    std::thread::sleep(Duration::from_millis(50));
                }
            });
        }
    });
    let clears = clears.into_inner().unwrap();
    let wall = start.elapsed();
    let db_cpu = cpu(&[farm.pg.pid()], true) - db_before;
    let hosts_cpu = cpu(&daemons, false) - hosts_before;

    // Each claim's moment from the database's history, against the clear before it.
    let rows = farm.query(
        "SELECT j.printer, extract(epoch FROM h.at)::float8 FROM job_history h \
         JOIN jobs j ON j.id = h.job_id \
         WHERE h.state = 'printing' AND j.file LIKE 'job-%' ORDER BY h.at",
        &[],
    );
    assert_eq!(rows.len(), jobs, "every job claimed exactly once");
    assert_eq!(count(&farm, "done"), jobs + printers, "every job printed");
    let mut waits = Vec::new();
    let mut last_claim = first_clear;
    for row in &rows {
        let (printer, at): (String, f64) = (row.get(0), row.get(1));
        let freed = clears[&printer]
            .iter()
            .rev()
            .find(|&&c| c <= at + 0.005)
            .unwrap_or_else(|| panic!("{printer} claimed at {at} before any clear"));
        waits.push((at - freed).max(0.0));
        last_claim = last_claim.max(at);
    }
    waits.sort_by(f64::total_cmp);
    let claiming = last_claim - first_clear;
    println!(
        "farm: {jobs} jobs, {printers} printers on {HOSTS} hosts (real daemons, simulated printers): \
         {:.1} claims/s ({:.1} s from the first clear to the last claim; {:.1} s until every bed was cleared again)",
        jobs as f64 / claiming,
        claiming,
        wall.as_secs_f64()
    );
    println!(
        "free to next job (clear sent -> claim in the database): median {:.1} ms, p99 {:.1} ms, worst {:.1} ms",
        percentile(&waits, 0.5) * 1e3,
        percentile(&waits, 0.99) * 1e3,
        waits.last().unwrap() * 1e3
    );
    println!(
        "database CPU: {:.2} s in all, {:.2} ms per claim; the three daemons: {:.2} s, {:.2} ms per claim",
        db_cpu,
        db_cpu * 1e3 / jobs as f64,
        hosts_cpu,
        hosts_cpu * 1e3 / jobs as f64
    );
    println!(
        "admission: {jobs} dropped files admitted and prepared in {:.1} s ({:.1} jobs/s)",
        admitted.as_secs_f64(),
        jobs as f64 / admitted.as_secs_f64()
    );
}
