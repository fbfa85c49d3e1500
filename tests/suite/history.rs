//! The history through the real daemon: a spool holding finished jobs (written in its
//! on-disk format), `crispen run` with `[history] live_jobs = 2`, and the jobs beyond that
//! moved out of the live status into the history, paged through `GET /api/v1/history` and
//! `crispen history`, one found by `GET /api/v1/jobs/{id}`, before and after a restart,
//! its files where they were.

use crispen::daemon::job::{Job, JobState};
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant, SystemTime, UNIX_EPOCH};

const BIN: &str = env!("CARGO_BIN_EXE_crispen");

fn now_s() -> f64 {
    SystemTime::now()
        .duration_since(UNIX_EPOCH)
        .unwrap()
        .as_secs_f64()
}

/// `n` done jobs, an hour apart, the last an hour ago; their ids, oldest first.
fn write_spool(spool: &Path, n: usize) -> Vec<String> {
    let now = now_s();
    (1..=n as u64)
        .map(|seq| {
            let file = format!("part-{seq}.stl");
            let id = Job::make_id(seq, &file);
            let dir = spool.join("jobs").join(&id);
            std::fs::create_dir_all(&dir).unwrap();
            std::fs::write(dir.join(&file), b"solid x\nendsolid x\n").unwrap();
            let ended = now - 3_600.0 * (n as u64 + 1 - seq) as f64;
            let mut job = Job::queued(id.clone(), seq, file, "/srv/hot".into());
            job.history = vec![
                (JobState::Queued, ended - 600.0),
                (JobState::Preparing, ended - 590.0),
                (JobState::Ready, ended - 500.0),
                (JobState::Printing, ended - 400.0),
                (JobState::Done, ended),
            ];
            job.state = JobState::Done;
            job.printer = Some("p1".into());
            std::fs::write(dir.join("job.json"), serde_json::to_vec(&job).unwrap()).unwrap();
            id
        })
        .collect()
}

fn get(socket: &Path, path: &str) -> Option<(u16, serde_json::Value)> {
    let (code, body) = crate::common::farm::http_on(socket, "GET", path).ok()?;
    Some((code, serde_json::from_str(&body).ok()?))
}

struct Daemon {
    child: Child,
    socket: PathBuf,
    log: PathBuf,
}

impl Daemon {
    fn start(root: &Path, config: &Path) -> Daemon {
        let log = root.join("daemon.log");
        let child = Command::new(BIN)
            .args(["run", "--config"])
            .arg(config)
            .stdout(Stdio::null())
            .stderr(std::fs::File::create(&log).unwrap())
            .spawn()
            .unwrap();
        let mut daemon = Daemon {
            child,
            socket: root.join("crispen.sock"),
            log,
        };
        daemon.wait_for(|d| get(&d.socket, "/api/v1/status").is_some(), "the socket");
        daemon
    }

    /// Waits (bounded) until `ready` holds, looking again as soon as it does not.
    fn wait_for(&mut self, ready: impl Fn(&Daemon) -> bool, what: &str) {
        let deadline = Instant::now() + Duration::from_secs(60);
        while !ready(self) {
            if let Ok(Some(status)) = self.child.try_wait() {
                panic!(
                    "crispen run ended ({status}) waiting for {what}: {}",
                    std::fs::read_to_string(&self.log).unwrap_or_default()
                );
            }
            assert!(Instant::now() < deadline, "{what}: not within 60 s");
            std::thread::sleep(Duration::from_millis(20));
        }
    }

    fn live_jobs(&self) -> Vec<String> {
        let (_, status) = get(&self.socket, "/api/v1/status").unwrap();
        status["jobs"]
            .as_array()
            .unwrap()
            .iter()
            .map(|j| j["id"].as_str().unwrap().to_string())
            .collect()
    }
}

impl Drop for Daemon {
    fn drop(&mut self) {
        let pid = nix::unistd::Pid::from_raw(self.child.id() as i32);
        let _ = nix::sys::signal::kill(pid, nix::sys::signal::Signal::SIGTERM);
        let _ = self.child.wait();
    }
}

fn history_cli(config: &Path, args: &[&str]) -> String {
    let out = Command::new(BIN)
        .arg("history")
        .arg("--config")
        .arg(config)
        .args(args)
        .output()
        .unwrap();
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    String::from_utf8(out.stdout).unwrap()
}

#[test]
fn finished_jobs_are_paged_through_the_history_by_api_and_cli() {
    let tmp = tempfile::tempdir().unwrap();
    let root = tmp.path();
    let ids = write_spool(&root.join("spool"), 5);
    std::fs::create_dir_all(root.join("hot")).unwrap();
    let config = root.join("crispen.toml");
    std::fs::write(
        &config,
        format!(
            "[spool]\ndir = {:?}\n[control]\nsocket = {:?}\n[history]\nlive_jobs = 2\n\
             [[printer]]\nname = \"p1\"\nfirmware = \"marlin2\"\n[printer.simulate]\ntime_scale = 0.0\n\
             [[folder]]\npath = {:?}\nheight_mm = 30\nprinters = [\"p1\"]\n",
            root.join("spool"),
            root.join("crispen.sock"),
            root.join("hot"),
        ),
    )
    .unwrap();

    let mut daemon = Daemon::start(root, &config);
    daemon.wait_for(|d| d.live_jobs().len() == 2, "the older jobs to leave");
    assert_eq!(daemon.live_jobs(), ids[3..].to_vec());

    let (code, page) = get(&daemon.socket, "/api/v1/history?limit=2").unwrap();
    assert_eq!(code, 200);
    let listed = |page: &serde_json::Value| -> Vec<String> {
        page["jobs"]
            .as_array()
            .unwrap()
            .iter()
            .map(|j| j["id"].as_str().unwrap().to_string())
            .collect()
    };
    assert_eq!(listed(&page), [ids[2].clone(), ids[1].clone()]);
    assert_eq!(page["jobs"][0]["state"], "done");
    assert_eq!(page["jobs"][0]["printer"], "p1");
    let next = page["next"].as_u64().expect("a next page");
    let (_, page) = get(
        &daemon.socket,
        &format!("/api/v1/history?limit=2&before={next}"),
    )
    .unwrap();
    assert_eq!(listed(&page), [ids[0].clone()]);
    assert!(page["next"].is_null());
    let (code, err) = get(&daemon.socket, "/api/v1/history?limit=0").unwrap();
    assert_eq!(code, 400, "{err}");

    let (code, job) = get(&daemon.socket, &format!("/api/v1/jobs/{}", ids[0])).unwrap();
    assert_eq!(code, 200, "{job}");
    assert_eq!(job["retired"], true);
    assert_eq!(job["state"], "done");
    assert_eq!(job["job"]["id"], ids[0].as_str());
    let (code, job) = get(&daemon.socket, &format!("/api/v1/jobs/{}", ids[4])).unwrap();
    assert_eq!(code, 200);
    assert!(job["retired"].is_null(), "a live job: {job}");

    let text = history_cli(&config, &["--limit", "2"]);
    assert!(text.contains(&ids[2]) && text.contains(&ids[1]), "{text}");
    assert!(!text.contains(&ids[0]), "{text}");
    assert!(
        text.contains(&format!("crispen history --before {next}")),
        "{text}"
    );
    let text = history_cli(&config, &["--before", &next.to_string()]);
    assert!(text.contains(&ids[0]) && !text.contains(&ids[1]), "{text}");

    // After a restart: the same live jobs, the same history, the files where they were.
    drop(daemon);
    let daemon = Daemon::start(root, &config);
    assert_eq!(daemon.live_jobs(), ids[3..].to_vec());
    let (_, page) = get(&daemon.socket, "/api/v1/history?limit=10").unwrap();
    assert_eq!(
        listed(&page),
        [ids[2].clone(), ids[1].clone(), ids[0].clone()]
    );
    let (_, job) = get(&daemon.socket, &format!("/api/v1/jobs/{}", ids[1])).unwrap();
    assert_eq!(job["retired"], true);
    let dir = PathBuf::from(job["dir"].as_str().unwrap());
    assert!(dir.join("part-2.stl").is_file(), "{}", dir.display());
}

fn get_text(socket: &Path, path: &str) -> (u16, String) {
    crate::common::farm::http_on(socket, "GET", path).unwrap()
}

/// The value of a sample in a `/metrics` text.
fn sample(metrics: &str, series: &str) -> f64 {
    metrics
        .lines()
        .find_map(|l| l.strip_prefix(series)?.strip_prefix(' '))
        .unwrap_or_else(|| panic!("no {series} in\n{metrics}"))
        .trim()
        .parse()
        .unwrap()
}

/// Pre-sliced G-code a `marlin2` printer's bed cannot hold (its preparation fails).
const TOO_BIG: &str = "; filament_diameter = 1.75\nM104 S200\nM109 S200\nG28\nG90\nM82\n\
                       G1 X900 Y900 Z0.3 E5 F6000\nM104 S0\n";

/// Jobs the farm ran (a real daemon, a simulated printer): two printed, one cancelled,
/// one failed. The statistics (counts, printing time, filament, failure reasons) and the
/// counters of `/metrics` agree with the jobs' own records, while the jobs are live and
/// again from the history after a restart; the history filters and its CSV (read by
/// Python's csv module) hold the same jobs.
#[test]
fn statistics_history_filters_and_csv_of_jobs_the_farm_ran() {
    use crate::common::farm::{drop_file, presliced_gcode};
    let tmp = tempfile::tempdir().unwrap();
    let root = tmp.path();
    let hot = root.join("hot");
    std::fs::create_dir_all(&hot).unwrap();
    let config = root.join("crispen.toml");
    // Finished jobs stay live until the next start's round moves them all to the history
    // (`live_days = 0`); `live_jobs` is above their four, or each would leave as it ends.
    // p1's filament is known (PLA, no price): its prints are weighed, not costed.
    std::fs::write(
        &config,
        format!(
            "[spool]\ndir = {:?}\n[control]\nsocket = {:?}\n[farm]\nsettle_s = 0.2\n\
             [history]\nlive_days = 0\nlive_jobs = 10\n\
             [[printer]]\nname = \"p1\"\nfirmware = \"marlin2\"\nmaterial = \"PLA\"\n[printer.simulate]\ntime_scale = 0.05\n\
             [[folder]]\npath = {:?}\nheight_mm = 30\nprinters = [\"p1\"]\n",
            root.join("spool"),
            root.join("crispen.sock"),
            hot,
        ),
    )
    .unwrap();
    let started = now_s();
    let mut daemon = Daemon::start(root, &config);
    let status = |d: &Daemon| get(&d.socket, "/api/v1/status").unwrap().1;
    let state = |d: &Daemon, file: &str| crate::common::farm::state_of(&status(d), file);
    let id_of = |d: &Daemon, file: &str| {
        crate::common::job_by_file(&status(d), file).unwrap()["id"]
            .as_str()
            .unwrap()
            .to_string()
    };
    let ctl = |args: &[&str]| {
        let (ok, out) = crate::common::daemon::ctl(&config, args);
        assert!(ok, "crispen {args:?}: {out}");
        out
    };

    drop_file(&hot, "a.gcode", presliced_gcode("a", 10, 6000).as_bytes());
    daemon.wait_for(|d| state(d, "a.gcode") == "done", "a printed");
    // p1 waits for its bed to be cleared: b waits, and is cancelled.
    drop_file(&hot, "b.gcode", presliced_gcode("b", 10, 6000).as_bytes());
    daemon.wait_for(|d| state(d, "b.gcode") == "ready", "b prepared");
    ctl(&["cancel", &id_of(&daemon, "b.gcode")]);
    drop_file(&hot, "big.gcode", TOO_BIG.as_bytes());
    daemon.wait_for(|d| state(d, "big.gcode") == "failed", "big refused");
    ctl(&["clear", "p1"]);
    drop_file(&hot, "c.gcode", presliced_gcode("c", 20, 6000).as_bytes());
    daemon.wait_for(|d| state(d, "c.gcode") == "done", "c printed");

    // What the jobs' own records say.
    let files = ["a.gcode", "b.gcode", "big.gcode", "c.gcode"];
    let jobs: Vec<serde_json::Value> = files
        .iter()
        .map(|f| {
            let id = id_of(&daemon, f);
            get(&daemon.socket, &format!("/api/v1/jobs/{id}"))
                .unwrap()
                .1["job"]
                .clone()
        })
        .collect();
    let mut printing_s = 0.0;
    for job in &jobs {
        let history = job["history"].as_array().unwrap();
        for (i, h) in history.iter().enumerate() {
            if h[0] == "printing" {
                printing_s += history[i + 1][1].as_f64().unwrap() - h[1].as_f64().unwrap();
            }
        }
    }
    assert!(printing_s > 0.0);
    // The G-code extrudes 3.3 mm a move (a: 10 moves, c: 20), on 1.75 mm filament.
    let filament_mm = 30.0 * 3.3;
    for (job, moves) in [(&jobs[0], 10.0), (&jobs[3], 20.0)] {
        let reported = job["slice_report"]["filament_mm"].as_f64().unwrap();
        assert!((reported - moves * 3.3).abs() < 1e-6, "{job}");
    }
    let filament_g = filament_mm / 10.0 * std::f64::consts::PI * 0.0875 * 0.0875 * 1.24;
    let failure = jobs[2]["reason"].as_str().unwrap().lines().next().unwrap();

    let (from, to) = (started - 60.0, now_s() + 60.0);
    let check = |stats: &serde_json::Value| {
        let farm = &stats["farm"];
        assert_eq!(
            farm["jobs"],
            serde_json::json!({"done": 2, "failed": 1, "cancelled": 1}),
            "{stats}"
        );
        let p1 = &stats["printers"][0];
        assert_eq!(p1["name"], "p1");
        assert_eq!(p1["jobs"]["done"], 2, "{stats}");
        let near = |a: &serde_json::Value, b: f64| (a.as_f64().unwrap() - b).abs() < 1e-6;
        assert!(
            near(&p1["printing_s"], printing_s),
            "{stats} vs {printing_s}"
        );
        assert!(
            near(&p1["utilisation"], printing_s / (to - from)),
            "{stats}"
        );
        let daily: f64 = p1["daily_utilisation"]
            .as_array()
            .unwrap()
            .iter()
            .map(|u| u.as_f64().unwrap())
            .sum();
        assert!(daily > 0.0, "{stats}");
        assert!(near(&p1["filament_mm"], filament_mm), "{stats}");
        // No job asked a material: their needs have no density to be weighed at.
        assert!(near(&p1["filament_g"], 0.0), "{stats}");
        // Weighed at p1's PLA: every line of a and c acknowledged, so what their G-code
        // pushes; no price.
        assert!(near(&p1["used_g"], filament_g), "{stats}");
        assert_eq!(p1["cost"], serde_json::Value::Null, "{stats}");
        let materials = stats["materials"].as_array().unwrap();
        assert_eq!(materials.len(), 1, "{stats}");
        assert_eq!(materials[0]["name"], "PLA");
        assert_eq!(materials[0]["jobs"]["done"], 2, "{stats}");
        assert!(near(&materials[0]["used_g"], filament_g), "{stats}");
        assert!(near(&materials[0]["printing_s"], printing_s), "{stats}");
        assert_eq!(farm["failure_reasons"][0]["reason"], failure, "{stats}");
        assert_eq!(farm["failure_reasons"][0]["jobs"], 1);
        assert_eq!(stats["folders"][0]["name"], "hot");
        assert_eq!(stats["folders"][0]["jobs"]["cancelled"], 1);
    };
    let stats_path = format!("/api/v1/stats?from={from}&to={to}");
    let (code, live_stats) = get(&daemon.socket, &stats_path).unwrap();
    assert_eq!(code, 200, "{live_stats}");
    check(&live_stats);
    let (code, err) = get(&daemon.socket, "/api/v1/stats?days=0").unwrap();
    assert_eq!(code, 400, "{err}");
    let (code, err) = get(&daemon.socket, "/api/v1/stats?from=2026-02-31").unwrap();
    assert_eq!(code, 400, "{err}");
    assert!(err["error"].as_str().unwrap().contains("from"), "{err}");

    // The counters of this run.
    let (_, metrics) = get_text(&daemon.socket, "/metrics");
    let done = "crispen_jobs_total{printer=\"p1\",result=\"done\"}";
    assert_eq!(sample(&metrics, done), 2.0);
    let printed = sample(&metrics, "crispen_printing_seconds_total{printer=\"p1\"}");
    assert!(
        (printed - printing_s).abs() < 1e-3,
        "{printed} vs {printing_s}"
    );
    let meters = sample(
        &metrics,
        "crispen_filament_used_meters_total{printer=\"p1\"}",
    );
    assert!((meters - filament_mm / 1000.0).abs() < 1e-9, "{meters}");

    // A restart moves every finished job to the history: the same statistics from there.
    drop(daemon);
    let daemon = Daemon::start(root, &config);
    let mut daemon = daemon;
    daemon.wait_for(
        |d| d.live_jobs().is_empty(),
        "the jobs to move to the history",
    );
    let (_, history_stats) = get(&daemon.socket, &stats_path).unwrap();
    check(&history_stats);
    // The same figures (times as the spool stored them: to a microsecond).
    for group in ["printers", "folders"] {
        let (now, then) = (&history_stats[group][0], &live_stats[group][0]);
        assert_eq!(now["jobs"], then["jobs"], "{group}");
        assert_eq!(now["filament_mm"], then["filament_mm"], "{group}");
        let (a, b) = (
            now["printing_s"].as_f64().unwrap(),
            then["printing_s"].as_f64().unwrap(),
        );
        assert!((a - b).abs() < 1e-5, "{group}: {a} vs {b}");
    }

    let listed = |query: &str| -> Vec<String> {
        let (code, page) = get(&daemon.socket, &format!("/api/v1/history?{query}")).unwrap();
        assert_eq!(code, 200, "{query}: {page}");
        page["jobs"]
            .as_array()
            .unwrap()
            .iter()
            .map(|j| j["file"].as_str().unwrap().to_string())
            .collect()
    };
    assert_eq!(listed("printer=p1&state=done"), ["c.gcode", "a.gcode"]);
    assert_eq!(listed("state=failed"), ["big.gcode"]);
    assert_eq!(listed("folder=hot").len(), 4);
    assert_eq!(listed(&format!("folder={}", hot.display())).len(), 4);
    assert!(listed("folder=elsewhere").is_empty());
    assert!(listed(&format!("since={}", to as u64)).is_empty());
    assert_eq!(
        listed(&format!("since={}&until={}", from as u64, to as u64)).len(),
        4
    );
    let (code, err) = get(&daemon.socket, "/api/v1/history?state=printing").unwrap();
    assert_eq!(code, 400, "{err}");
    let (code, err) = get(&daemon.socket, "/api/v1/history?colour=red").unwrap();
    assert_eq!(code, 400, "{err}");
    let (_, page) = get(&daemon.socket, "/api/v1/history?state=done&limit=1").unwrap();
    let record = &page["jobs"][0];
    assert_eq!(record["file"], "c.gcode");
    assert!((record["filament_mm"].as_f64().unwrap() - 66.0).abs() < 1e-6);
    assert!(record["filament_g"].is_null(), "it asked no material");
    assert_eq!(record["resends"], 0);
    assert_eq!(record["material"], "PLA");
    assert!((record["used_g"].as_f64().unwrap() - filament_g * 20.0 / 30.0).abs() < 1e-6);
    assert_eq!(record["cost"], serde_json::Value::Null);
    assert!(record["print_s"].as_f64().unwrap() > 0.0);

    // The export, by the CLI, read as CSV by another program.
    let csv = history_cli(&config, &["--csv", "--folder", "hot"]);
    let parsed = Command::new("python3")
        .args([
            "-c",
            "import csv, json, sys; print(json.dumps(list(csv.DictReader(sys.stdin))))",
        ])
        .stdin(Stdio::piped())
        .stdout(Stdio::piped())
        .spawn()
        .and_then(|mut child| {
            use std::io::Write;
            child.stdin.take().unwrap().write_all(csv.as_bytes())?;
            child.wait_with_output()
        })
        .expect("python3");
    assert!(parsed.status.success(), "{csv}");
    let rows: Vec<serde_json::Value> = serde_json::from_slice(&parsed.stdout).unwrap();
    assert_eq!(rows.len(), 4, "{csv}");
    let row = rows.iter().find(|r| r["file"] == "big.gcode").unwrap();
    assert_eq!(row["state"], "failed");
    assert_eq!(
        row["reason"].as_str().unwrap(),
        jobs[2]["reason"].as_str().unwrap(),
        "the reason whole, commas, quotes and line breaks and all"
    );
    let row = rows.iter().find(|r| r["file"] == "a.gcode").unwrap();
    assert_eq!(row["printer"], "p1");
    assert_eq!(
        row["filament_mm"].as_str().unwrap().parse::<f64>().unwrap(),
        33.0
    );
    assert_eq!(row["material"], "PLA");
    assert!(row["used_g"].as_str().unwrap().parse::<f64>().unwrap() > 0.0);
    assert_eq!(row["cost"], "", "no price known");
    let row = rows.iter().find(|r| r["file"] == "big.gcode").unwrap();
    assert_eq!(
        (&row["material"], &row["used_g"]),
        (&serde_json::json!(""), &serde_json::json!("")),
        "never printed"
    );
    let text = history_cli(&config, &["--state", "failed"]);
    assert!(
        text.contains("big.gcode") && !text.contains("a.gcode"),
        "{text}"
    );

    let (ok, text) = crate::common::daemon::ctl(
        &config,
        &[
            "stats",
            "--from",
            &format!("{}", from as u64),
            "--to",
            &format!("{}", to as u64),
        ],
    );
    assert!(ok, "{text}");
    assert!(
        text.lines()
            .any(|l| l.starts_with("p1 ") && l.contains(" 2 ")),
        "{text}"
    );
    assert!(
        text.contains("MATERIAL") && text.lines().any(|l| l.starts_with("PLA ")),
        "{text}"
    );
}

/// Issue 31: a job's failure reason names its files relative to the spool or by the job's
/// own file name, never by the server's path, wherever clients read it: `/api/v1/jobs`,
/// the status (the dashboard's), a job's record, and the history after a restart. The
/// failures: a job whose `job.json` cannot be read, a `.gcode` that is not G-code, and
/// G-code the host refuses to load (its error names the file by path).
#[test]
fn failure_reasons_name_files_never_server_paths() {
    use crate::common::farm::drop_file;
    let tmp = tempfile::tempdir().unwrap();
    let root = tmp.path();
    let hot = root.join("hot");
    std::fs::create_dir_all(&hot).unwrap();
    let spool = root.join("spool");
    // A job whose state was cut short (a crash, a full disk): it is loaded as failed.
    let broken = Job::make_id(1, "broken.gcode");
    let dir = spool.join("jobs").join(&broken);
    std::fs::create_dir_all(&dir).unwrap();
    std::fs::write(dir.join("broken.gcode"), "G28\n").unwrap();
    std::fs::write(
        dir.join("origin.json"),
        serde_json::json!({"id": broken, "file": "broken.gcode", "folder": hot}).to_string(),
    )
    .unwrap();
    std::fs::write(
        dir.join("job.json"),
        format!("{{\"id\": \"{broken}\", trunc"),
    )
    .unwrap();
    let config = root.join("crispen.toml");
    // Live for a week first; then, restarted with none live, all move to the history.
    let write_config = |history: &str| {
        std::fs::write(
            &config,
            format!(
                "[spool]\ndir = {:?}\n[control]\nsocket = {:?}\n[farm]\nsettle_s = 0.2\n\
                 [history]\n{history}\n\
                 [[printer]]\nname = \"p1\"\nfirmware = \"marlin2\"\n[printer.simulate]\ntime_scale = 0.0\n\
                 [[folder]]\npath = {:?}\nheight_mm = 30\nprinters = [\"p1\"]\n",
                spool,
                root.join("crispen.sock"),
                hot,
            ),
        )
        .unwrap()
    };
    write_config("live_days = 7");
    let mut daemon = Daemon::start(root, &config);
    drop_file(&hot, "notes.gcode", b"G28\n\0\0 a picture, not G-code\n");
    drop_file(&hot, "star.gcode", b"G28\nM117 five*six\n");
    let status = |d: &Daemon| get(&d.socket, "/api/v1/status").unwrap().1;
    let files = ["broken.gcode", "notes.gcode", "star.gcode"];
    daemon.wait_for(
        |d| {
            let s = status(d);
            files
                .iter()
                .all(|f| crate::common::farm::state_of(&s, f) == "failed")
        },
        "the three jobs failed",
    );
    // The spool's path as written and as it resolves (/tmp may be a link).
    let paths = [
        spool.to_string_lossy().into_owned(),
        spool.canonicalize().unwrap().to_string_lossy().into_owned(),
        root.to_string_lossy().into_owned(),
    ];
    let id_of = |s: &serde_json::Value, file: &str| {
        crate::common::job_by_file(s, file).unwrap()["id"]
            .as_str()
            .unwrap()
            .to_string()
    };
    let s = status(&daemon);
    let ids: Vec<String> = files.iter().map(|f| id_of(&s, f)).collect();
    assert_eq!(ids[0], broken);
    // What each reason must name: the file relative to the spool, or by its name.
    let named = [
        format!("jobs/{broken}/job.json"),
        "notes.gcode: not G-code".to_string(),
        "star.gcode".to_string(),
    ];
    let check = |where_: &str, id: &str, reason: &serde_json::Value| {
        let reason = reason
            .as_str()
            .unwrap_or_else(|| panic!("{where_}: {id} has no reason"));
        let i = ids.iter().position(|i| i == id).unwrap();
        assert!(reason.contains(&named[i]), "{where_}: {id}: {reason}");
        for path in &paths {
            assert!(
                !reason.contains(path.as_str()),
                "{where_}: {id} names the server's path {path}: {reason}"
            );
        }
    };
    let (code, jobs) = get(&daemon.socket, "/api/v1/jobs").unwrap();
    assert_eq!(code, 200, "{jobs}");
    for job in jobs.as_array().unwrap() {
        check("/api/v1/jobs", job["id"].as_str().unwrap(), &job["reason"]);
    }
    assert_eq!(jobs.as_array().unwrap().len(), 3, "{jobs:#}");
    for job in s["jobs"].as_array().unwrap() {
        check(
            "/api/v1/status",
            job["id"].as_str().unwrap(),
            &job["reason"],
        );
    }
    for id in &ids {
        let (_, detail) = get(&daemon.socket, &format!("/api/v1/jobs/{id}")).unwrap();
        check("/api/v1/jobs/{id}", id, &detail["job"]["reason"]);
    }

    // After a restart, in the history.
    drop(daemon);
    write_config("live_days = 0\nlive_jobs = 0");
    let mut daemon = Daemon::start(root, &config);
    let history = |d: &Daemon| get(&d.socket, "/api/v1/history?limit=10");
    daemon.wait_for(
        |d| history(d).is_some_and(|(_, p)| p["jobs"].as_array().is_some_and(|j| j.len() == 3)),
        "the three jobs in the history",
    );
    let (code, page) = history(&daemon).unwrap();
    assert_eq!(code, 200, "{page}");
    let listed = page["jobs"].as_array().unwrap();
    assert_eq!(listed.len(), 3, "{page:#}");
    for record in listed {
        check(
            "/api/v1/history",
            record["id"].as_str().unwrap(),
            &record["reason"],
        );
    }
    for id in &ids {
        let (_, retired) = get(&daemon.socket, &format!("/api/v1/jobs/{id}")).unwrap();
        assert_eq!(retired["retired"], true, "{retired}");
        check("/api/v1/jobs/{id} (retired)", id, &retired["reason"]);
    }
}
