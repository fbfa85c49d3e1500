//! What finished jobs cost the running daemon: a spool holding 300, then 3,000 finished
//! jobs (written straight in the spool's on-disk format: one directory per job with its
//! model, `origin.json` and `job.json`), and the real `crispen run` on it with one
//! simulated printer. Figures per spool, comparable between builds:
//! - first start: from the start of `crispen run` until the control socket answers
//!   `GET /api/v1/status` (a build with retention moves old jobs to the history then);
//! - restart: the same after a clean stop (SIGTERM) and a new start, median of 5;
//! - `crispen status`: the command line's whole run, median of 10;
//! - `GET /api/v1/status` and `GET /metrics` on the socket: median of 10, and the size of
//!   the status answer;
//! - idle CPU: the daemon's utime+stime (from /proc) over `CRISPEN_BENCH_IDLE_S` seconds
//!   (default 10) with nobody asking anything, per second of wall time;
//! - memory: VmRSS and VmHWM of the daemon after the above.
//!
//! `cargo bench --bench history`; `CRISPEN_BIN=/path/to/crispen` measures another build
//! (e.g. one of main, for a before/after table); `CRISPEN_BENCH_JOBS=300,3000` sets the
//! spools.

use crispen::daemon::job::{Job, JobState, PrintReport};
use std::io::{Read, Write};
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant, SystemTime, UNIX_EPOCH};

fn binary() -> PathBuf {
    match std::env::var_os("CRISPEN_BIN") {
        Some(p) => PathBuf::from(p),
        None => PathBuf::from(env!("CARGO_BIN_EXE_crispen")),
    }
}

fn now_s() -> f64 {
    SystemTime::now()
        .duration_since(UNIX_EPOCH)
        .unwrap()
        .as_secs_f64()
}

/// Writes `n` finished jobs into `spool`, one every 10 minutes back from now, as the
/// spool keeps them (a done job with its reports).
fn write_spool(spool: &Path, n: usize) {
    let jobs = spool.join("jobs");
    std::fs::create_dir_all(&jobs).unwrap();
    let now = now_s();
    for i in 0..n {
        let seq = i as u64 + 1;
        let file = format!("part-{seq}.stl");
        let id = Job::make_id(seq, &file);
        let dir = jobs.join(&id);
        std::fs::create_dir_all(&dir).unwrap();
        std::fs::write(dir.join(&file), b"solid x\nendsolid x\n").unwrap();
        let origin = serde_json::json!({"id": id, "file": file, "folder": "/srv/hot"});
        std::fs::write(dir.join("origin.json"), origin.to_string()).unwrap();
        let ended = now - 600.0 * (n - i) as f64;
        let mut job = Job::queued(id.clone(), seq, file.clone(), "/srv/hot".into());
        job.history = vec![
            (JobState::Queued, ended - 3_000.0),
            (JobState::Preparing, ended - 2_990.0),
            (JobState::Ready, ended - 2_900.0),
            (JobState::Printing, ended - 2_800.0),
            (JobState::Done, ended),
        ];
        job.state = JobState::Done;
        job.printer = Some("p1".into());
        job.copies_done = 1;
        job.slice_report = Some(Default::default());
        job.print_report = Some(PrintReport {
            port: "/dev/ttyACM0".into(),
            lines_total: 40_000,
            lines_acked: 40_000,
            lines_sent: 40_010,
            resends: 3,
            duration_s: 2_800.0,
            ..Default::default()
        });
        std::fs::write(
            dir.join("job.json"),
            serde_json::to_vec_pretty(&job).unwrap(),
        )
        .unwrap();
    }
}

fn write_config(root: &Path) -> PathBuf {
    let hot = root.join("hot");
    std::fs::create_dir_all(&hot).unwrap();
    let config = root.join("crispen.toml");
    let text = format!(
        "[spool]\ndir = {spool:?}\n[control]\nsocket = {socket:?}\n\
         [farm]\nmax_heating = 1\nsettle_s = 1\n\
         [[printer]]\nname = \"p1\"\nfirmware = \"marlin2\"\n[printer.simulate]\nspeed = \"instant\"\n\
         [[folder]]\npath = {hot:?}\nheight_mm = 30\nprinters = [\"p1\"]\n",
        spool = root.join("spool"),
        socket = root.join("crispen.sock"),
        hot = hot,
    );
    std::fs::write(&config, text).unwrap();
    config
}

/// One HTTP/1.1 GET on the control socket; the answer's body, None while nobody answers.
fn get(socket: &Path, path: &str) -> Option<Vec<u8>> {
    let mut stream = std::os::unix::net::UnixStream::connect(socket).ok()?;
    stream
        .set_read_timeout(Some(Duration::from_secs(30)))
        .ok()?;
    write!(
        stream,
        "GET {path} HTTP/1.1\r\nHost: localhost\r\nConnection: close\r\n\r\n"
    )
    .ok()?;
    let mut answer = Vec::new();
    stream.read_to_end(&mut answer).ok()?;
    if !answer.starts_with(b"HTTP/1.1 200") {
        return None;
    }
    let body = answer.windows(4).position(|w| w == b"\r\n\r\n")? + 4;
    Some(answer[body..].to_vec())
}

struct Daemon {
    child: Child,
    socket: PathBuf,
}

impl Daemon {
    /// Starts `crispen run` and waits until its socket answers; returns it and the time.
    fn start(config: &Path, root: &Path) -> (Daemon, Duration) {
        let socket = root.join("crispen.sock");
        let log = std::fs::File::create(root.join("daemon.log")).unwrap();
        let started = Instant::now();
        let child = Command::new(binary())
            .arg("run")
            .arg("--config")
            .arg(config)
            .stdout(Stdio::null())
            .stderr(log)
            .spawn()
            .expect("crispen run starts");
        let mut daemon = Daemon { child, socket };
        loop {
            if get(&daemon.socket, "/api/v1/status").is_some() {
                return (daemon, started.elapsed());
            }
            if let Ok(Some(status)) = daemon.child.try_wait() {
                panic!(
                    "crispen run ended ({status}): {}",
                    std::fs::read_to_string(root.join("daemon.log")).unwrap_or_default()
                );
            }
            assert!(
                started.elapsed() < Duration::from_secs(120),
                "no answer in 2 min"
            );
            std::thread::sleep(Duration::from_millis(5));
        }
    }

    fn pid(&self) -> u32 {
        self.child.id()
    }

    fn stop(mut self) {
        let pid = nix::unistd::Pid::from_raw(self.child.id() as i32);
        let _ = nix::sys::signal::kill(pid, nix::sys::signal::Signal::SIGTERM);
        let deadline = Instant::now() + Duration::from_secs(60);
        while Instant::now() < deadline {
            if let Ok(Some(_)) = self.child.try_wait() {
                return;
            }
            std::thread::sleep(Duration::from_millis(20));
        }
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

/// utime + stime of a process (all its threads), in seconds.
fn cpu_s(pid: u32) -> f64 {
    let stat = std::fs::read_to_string(format!("/proc/{pid}/stat")).unwrap();
    // Fields after the command's closing parenthesis: state is field 3, utime 14, stime 15.
    let rest = &stat[stat.rfind(')').unwrap() + 2..];
    let fields: Vec<&str> = rest.split_whitespace().collect();
    let ticks = nix::unistd::sysconf(nix::unistd::SysconfVar::CLK_TCK)
        .ok()
        .flatten()
        .unwrap_or(100) as f64;
    (fields[11].parse::<f64>().unwrap() + fields[12].parse::<f64>().unwrap()) / ticks
}

/// VmRSS and VmHWM in MiB.
fn memory_mib(pid: u32) -> (f64, f64) {
    let status = std::fs::read_to_string(format!("/proc/{pid}/status")).unwrap();
    let field = |name: &str| {
        status
            .lines()
            .find_map(|l| l.strip_prefix(name))
            .and_then(|v| v.split_whitespace().next())
            .and_then(|kb| kb.parse::<f64>().ok())
            .unwrap_or(0.0)
            / 1024.0
    };
    (field("VmRSS:"), field("VmHWM:"))
}

fn median(mut v: Vec<f64>) -> f64 {
    v.sort_by(f64::total_cmp);
    v[v.len() / 2]
}

fn ms(d: Duration) -> f64 {
    d.as_secs_f64() * 1e3
}

struct Figures {
    jobs: usize,
    first_start_ms: f64,
    restart_ms: f64,
    cli_status_ms: f64,
    api_status_ms: f64,
    status_kib: f64,
    metrics_ms: f64,
    idle_cpu_ms_per_s: f64,
    rss_mib: f64,
    hwm_mib: f64,
    live_jobs: usize,
}

fn measure(jobs: usize, idle: Duration) -> Figures {
    let tmp = tempfile::tempdir().unwrap();
    let root = tmp.path();
    write_spool(&root.join("spool"), jobs);
    let config = write_config(root);

    let (daemon, first_start) = Daemon::start(&config, root);
    // Whatever the first start does in the background (moving jobs to the history) is
    // given time to finish before the restarts that are measured.
    std::thread::sleep(Duration::from_secs(3));
    daemon.stop();
    let mut restarts = Vec::new();
    for _ in 0..4 {
        let (daemon, restart) = Daemon::start(&config, root);
        restarts.push(ms(restart));
        daemon.stop();
    }
    let (daemon, restart) = Daemon::start(&config, root);
    restarts.push(ms(restart));
    std::thread::sleep(Duration::from_secs(1));

    let socket = daemon.socket.clone();
    let mut cli = Vec::new();
    for _ in 0..10 {
        let t = Instant::now();
        let out = Command::new(binary())
            .arg("status")
            .arg("--config")
            .arg(&config)
            .output()
            .unwrap();
        assert!(
            out.status.success(),
            "{}",
            String::from_utf8_lossy(&out.stderr)
        );
        cli.push(ms(t.elapsed()));
    }
    let mut api = Vec::new();
    let mut size = 0;
    let mut live_jobs = 0;
    for _ in 0..10 {
        let t = Instant::now();
        let body = get(&socket, "/api/v1/status").expect("status answers");
        api.push(ms(t.elapsed()));
        size = body.len();
        let status: serde_json::Value = serde_json::from_slice(&body).unwrap();
        live_jobs = status["jobs"].as_array().map_or(0, Vec::len);
    }
    let mut metrics = Vec::new();
    for _ in 0..10 {
        let t = Instant::now();
        get(&socket, "/metrics").expect("metrics answer");
        metrics.push(ms(t.elapsed()));
    }

    let pid = daemon.pid();
    let before = cpu_s(pid);
    let t = Instant::now();
    std::thread::sleep(idle);
    let idle_cpu = (cpu_s(pid) - before) / t.elapsed().as_secs_f64();
    let (rss, hwm) = memory_mib(pid);
    daemon.stop();
    Figures {
        jobs,
        first_start_ms: ms(first_start),
        restart_ms: median(restarts),
        cli_status_ms: median(cli),
        api_status_ms: median(api),
        status_kib: size as f64 / 1024.0,
        metrics_ms: median(metrics),
        idle_cpu_ms_per_s: idle_cpu * 1e3,
        rss_mib: rss,
        hwm_mib: hwm,
        live_jobs,
    }
}

fn main() {
    let sizes: Vec<usize> = std::env::var("CRISPEN_BENCH_JOBS")
        .unwrap_or_else(|_| "300,3000".into())
        .split(',')
        .map(|n| n.trim().parse().expect("CRISPEN_BENCH_JOBS: numbers"))
        .collect();
    let idle = Duration::from_secs_f64(
        std::env::var("CRISPEN_BENCH_IDLE_S")
            .ok()
            .and_then(|s| s.parse().ok())
            .unwrap_or(10.0),
    );
    println!("binary: {}", binary().display());
    println!(
        "{:>6} {:>6} {:>10} {:>10} {:>11} {:>11} {:>10} {:>11} {:>12} {:>8} {:>8}",
        "jobs",
        "live",
        "start ms",
        "restart ms",
        "status ms",
        "GET st. ms",
        "status KiB",
        "metrics ms",
        "idle CPU ms/s",
        "RSS MiB",
        "HWM MiB"
    );
    for n in sizes {
        let f = measure(n, idle);
        println!(
            "{:>6} {:>6} {:>10.0} {:>10.0} {:>11.1} {:>11.1} {:>10.1} {:>11.1} {:>12.2} {:>8.1} {:>8.1}",
            f.jobs,
            f.live_jobs,
            f.first_start_ms,
            f.restart_ms,
            f.cli_status_ms,
            f.api_status_ms,
            f.status_kib,
            f.metrics_ms,
            f.idle_cpu_ms_per_s,
            f.rss_mib,
            f.hwm_mib
        );
    }
}
