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
