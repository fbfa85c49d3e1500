//! Soak benchmark of the print-farm daemon: simulated printers (separate `crispen sim`
//! processes, so their cost is not counted as the daemon's) all printing from one
//! `crispen run`. Two loads (`CRISPEN_SOAK_JOB`):
//! - `moves` (default; 60 printers): a pre-sliced job of short moves on every printer, so
//!   every printer asks for lines as fast as a real one drawing small detail does. This is
//!   the per-line cost of the daemon: the goal is under 10 % of one core for 60 printers.
//! - `spot` (20 printers): tests/data/spot.obj enhanced and sliced for 50 mm by
//!   PrusaSlicer on every printer, a realistic job (preparing them is not measured).
//!
//! Measured over a window of CRISPEN_SOAK_SECONDS (default 60) once every printer is past
//! its heat-up:
//! - the daemon's CPU (utime+stime from /proc/<pid>/stat) as a share of one core, per
//!   thousand acknowledged lines a second too, and its memory (VmRSS now, VmHWM peak since
//!   start, which includes preparing the jobs);
//! - starvation: each printer's acknowledged lines per second in the window, compared with
//!   the same job streamed by a daemon driving a single printer (the uncontended rate, same
//!   window after heat-up). A ratio near 1.0 means no printer waited for lines.
//!
//! Sims run at CRISPEN_SOAK_TIME_SCALE (default 1.0: real motion and heating, so each
//! printer asks for lines at the rate a real printer would). Real heat-up takes a minute
//! or two; it is not measured: the window opens only once every printer reports `heated`
//! and is printing. `CRISPEN_SOAK_PRINTERS` sets the count. `cargo bench --bench soak`.

#[path = "../tests/common/mod.rs"]
mod common;

use common::daemon::{spawn_sim, status, Killed, BIN};
use common::farm::drop_file;
use std::path::PathBuf;
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};

/// Starts a `crispen sim` process: its pty device (the process is killed with `sims`).
fn start_sim(firmware: &str, time_scale: f64, sims: &mut Vec<Killed>) -> PathBuf {
    let (child, device) = spawn_sim(
        Command::new(BIN)
            .args(["sim", "--firmware", firmware, "--speed"])
            .arg(crispen::sim::speed_of_time_scale(time_scale)),
    );
    sims.push(Killed(child));
    device
}

fn proc_cpu_s(pid: u32) -> f64 {
    let stat = std::fs::read_to_string(format!("/proc/{pid}/stat")).unwrap();
    let fields: Vec<&str> = stat
        .rsplit_once(')')
        .unwrap()
        .1
        .split_whitespace()
        .collect();
    (fields[11].parse::<f64>().unwrap() + fields[12].parse::<f64>().unwrap()) / 100.0
}

fn proc_kb(pid: u32, key: &str) -> f64 {
    std::fs::read_to_string(format!("/proc/{pid}/status"))
        .unwrap()
        .lines()
        .find(|l| l.starts_with(key))
        .and_then(|l| l.split_whitespace().nth(1))
        .and_then(|v| v.parse().ok())
        .unwrap_or(0.0)
}

struct Farm {
    dir: tempfile::TempDir,
    config: PathBuf,
    daemon: Child,
    _sims: Vec<Killed>,
}

/// What every printer prints.
#[derive(Clone, Copy, PartialEq)]
enum Load {
    Moves,
    Spot,
}

/// Short moves (0.5 mm, as small detail asks for: about 60 lines a second on the simulated
/// Marlin at real speed), enough to outlast heat-up and the window.
fn moves_gcode() -> String {
    let mut g = String::from(
        "; short moves for crispen's soak benchmark\n; filament_diameter = 1.75\n\
         ; nozzle_diameter = 0.4\nM140 S60\nM104 S200\nM190 S60\nM109 S200\nG28\nG90\nM82\n\
         G92 E0\nG1 Z0.3 F600\nG1 X50 Y50 F3000\n",
    );
    let mut e = 0.0;
    for i in 0..40_000 {
        let (row, step) = (i / 200, i % 200);
        let x = 50.0 + 0.5 * if row % 2 == 0 { step } else { 199 - step } as f64;
        e += 0.017;
        g += &format!("G1 X{x:.1} Y{:.1} E{e:.3}\n", 50.0 + (row % 100) as f64);
    }
    g += "G1 Z10 F600\nM104 S0\nM140 S0\nM84\n";
    g
}

fn start_farm(printers: usize, time_scale: f64, load: Load) -> Farm {
    let dir = tempfile::tempdir().unwrap();
    let mut sims = Vec::new();
    let mut text = format!(
        "[spool]\ndir = \"spool\"\n[control]\nsocket = \"crispen.sock\"\n\
         [farm]\nmax_heating = {printers}\nsettle_s = 0.5\n",
    );
    let mut names = Vec::new();
    for i in 0..printers {
        // One pre-sliced file fits one kind of machine: the moves are for the Marlin 2 one.
        let firmware = if i % 2 == 0 || load == Load::Moves {
            "marlin2"
        } else {
            "ultimaker2"
        };
        let port = start_sim(firmware, time_scale, &mut sims);
        text += &format!(
            "[[printer]]\nname = \"p{i:02}\"\nport = \"{}\"\nfirmware = \"{firmware}\"\n",
            port.display()
        );
        names.push(format!("\"p{i:02}\""));
    }
    text += &format!(
        "[[folder]]\npath = \"hot\"\nheight_mm = 50\nprinters = [{}]\n",
        names.join(", ")
    );
    let config = dir.path().join("crispen.toml");
    std::fs::write(&config, text).unwrap();
    let log = std::fs::File::create(dir.path().join("daemon.log")).unwrap();
    let daemon = Command::new(BIN)
        .args(["run", "--config"])
        .arg(&config)
        .env("RUST_LOG", "warn")
        .stdout(Stdio::null())
        .stderr(log)
        .spawn()
        .unwrap();
    let hot = dir.path().join("hot");
    std::fs::create_dir_all(&hot).unwrap();
    match load {
        Load::Moves => {
            let gcode = moves_gcode();
            for i in 0..printers {
                drop_file(&hot, &format!("moves{i:02}.gcode"), gcode.as_bytes());
            }
        }
        Load::Spot => {
            let model = concat!(env!("CARGO_MANIFEST_DIR"), "/tests/data/spot.obj");
            let spot = std::fs::read(model).unwrap();
            for i in 0..printers {
                drop_file(&hot, &format!("spot{i:02}.obj"), &spot);
            }
        }
    }
    Farm {
        dir,
        config,
        daemon,
        _sims: sims,
    }
}

/// Per printer: acknowledged lines per second over `window`, starting when the printer
/// is first seen past its heat-up. Also returns the farm-wide window of the last printer
/// for the CPU measurement.
fn measure(
    farm: &mut Farm,
    printers: usize,
    window: Duration,
) -> (Vec<f64>, f64, f64, f64, Duration) {
    let began = Instant::now();
    let mut all_heated_after = Duration::ZERO;
    let deadline = Instant::now() + Duration::from_secs(900);
    let mut start: Vec<Option<(Instant, u64)>> = vec![None; printers];
    let mut rate: Vec<Option<f64>> = vec![None; printers];
    let mut cpu_window: Option<(Instant, f64)> = None;
    let mut cpu_share = 0.0;
    let pid = farm.daemon.id();
    while rate.iter().any(Option::is_none) {
        assert!(
            Instant::now() < deadline,
            "farm did not get going; see {}",
            farm.dir.path().join("daemon.log").display()
        );
        assert!(farm.daemon.try_wait().unwrap().is_none(), "daemon exited");
        std::thread::sleep(Duration::from_millis(500));
        let Some(s) = status(&farm.config) else {
            continue;
        };
        // A failed job leaves its printer idle: the figures would no longer be a farm's.
        if let Some(failed) = s["jobs"]
            .as_array()
            .and_then(|jobs| jobs.iter().find(|j| j["state"] == "failed"))
        {
            let log =
                std::fs::read_to_string(farm.dir.path().join("daemon.log")).unwrap_or_default();
            let tail: Vec<&str> = log.lines().rev().take(20).collect();
            panic!(
                "job {} failed: {}; the daemon's log ends:\n{}",
                failed["id"],
                failed["reason"],
                tail.into_iter().rev().collect::<Vec<_>>().join("\n")
            );
        }
        let now = Instant::now();
        for (i, p) in s["printers"]
            .as_array()
            .unwrap()
            .iter()
            .enumerate()
            .take(printers)
        {
            let acked = p["progress"]["lines_acked"].as_u64().unwrap_or(0);
            let heated =
                p["progress"]["heated"].as_bool().unwrap_or(false) && p["state"] == "printing";
            match start[i] {
                None if heated => start[i] = Some((now, acked)),
                Some((t0, a0)) if rate[i].is_none() && now - t0 >= window => {
                    rate[i] = Some((acked - a0) as f64 / (now - t0).as_secs_f64());
                }
                _ => {}
            }
        }
        // CPU window: from the moment all printers are past heat-up, for `window`.
        if cpu_window.is_none() && start.iter().all(Option::is_some) {
            cpu_window = Some((now, proc_cpu_s(pid)));
            all_heated_after = now - began;
        }
        if let Some((t0, c0)) = cpu_window {
            if now - t0 >= window && cpu_share == 0.0 {
                cpu_share = (proc_cpu_s(pid) - c0) / (now - t0).as_secs_f64();
            }
        }
    }
    while cpu_share == 0.0 {
        let (t0, c0) = cpu_window.unwrap();
        std::thread::sleep(Duration::from_millis(500));
        if t0.elapsed() >= window {
            cpu_share = (proc_cpu_s(pid) - c0) / t0.elapsed().as_secs_f64();
        }
    }
    let rss = proc_kb(pid, "VmRSS:") / 1024.0;
    let hwm = proc_kb(pid, "VmHWM:") / 1024.0;
    (
        rate.into_iter().map(Option::unwrap).collect(),
        cpu_share,
        rss,
        hwm,
        all_heated_after,
    )
}

fn main() {
    let window = Duration::from_secs_f64(
        std::env::var("CRISPEN_SOAK_SECONDS")
            .ok()
            .and_then(|v| v.parse().ok())
            .unwrap_or(60.0),
    );
    let time_scale: f64 = std::env::var("CRISPEN_SOAK_TIME_SCALE")
        .ok()
        .and_then(|v| v.parse().ok())
        .unwrap_or(1.0);
    let load = match std::env::var("CRISPEN_SOAK_JOB").as_deref() {
        Ok("moves") | Err(_) => Load::Moves,
        Ok("spot") => Load::Spot,
        Ok(other) => panic!("CRISPEN_SOAK_JOB={other:?}: `moves` or `spot`"),
    };
    let printers: usize = std::env::var("CRISPEN_SOAK_PRINTERS")
        .ok()
        .and_then(|v| v.parse().ok())
        .unwrap_or(if load == Load::Moves { 60 } else { 20 });
    println!(
        "soak: {printers} printers printing {}, sim time scale {time_scale} (1.0 = real speed), \
         window {:.0} s opening once every printer is heated and printing",
        if load == Load::Moves {
            "short moves"
        } else {
            "Spot at 50 mm"
        },
        window.as_secs_f64()
    );

    let mut solo = start_farm(1, time_scale, load);
    let (solo_rate, solo_cpu, solo_rss, _, _) = measure(&mut solo, 1, window);
    let _ = solo.daemon.kill();
    let _ = solo.daemon.wait();
    println!(
        "soak: reference, 1 printer alone: {:.0} lines/s acknowledged, daemon CPU {:.2}% of a core, VmRSS {solo_rss:.1} MB",
        solo_rate[0],
        solo_cpu * 100.0
    );

    let mut farm = start_farm(printers, time_scale, load);
    let (rates, cpu, rss, hwm, heated_after) = measure(&mut farm, printers, window);
    let _ = farm.daemon.kill();
    let _ = farm.daemon.wait();
    let min = rates.iter().cloned().fold(f64::INFINITY, f64::min);
    let mean = rates.iter().sum::<f64>() / rates.len() as f64;
    println!(
        "soak: all {printers} printers heated and printing {:.0} s after start (preparing \
         jobs + heat-up, not measured)",
        heated_after.as_secs_f64()
    );
    let lines_per_s: f64 = rates.iter().sum();
    println!(
        "soak: daemon CPU while streaming to {printers} printers: {:.2}% of one core (goal < 10% \
         for 60), {lines_per_s:.0} lines/s acknowledged in all: {:.2}% of a core per 1,000 lines/s",
        cpu * 100.0,
        cpu * 100.0 / (lines_per_s / 1000.0)
    );
    println!("soak: daemon memory: VmRSS {rss:.1} MB, VmHWM {hwm:.1} MB (peak includes preparing {printers} jobs; goal < 100 MB)");
    println!(
        "soak: lines/s per printer: min {min:.0}, mean {mean:.0}; vs alone {:.0}: min ratio {:.2}, mean ratio {:.2} (1.0 = not starved)",
        solo_rate[0],
        min / solo_rate[0],
        mean / solo_rate[0]
    );
}
