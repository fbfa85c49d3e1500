//! Benchmark: the host streamer against `crispen sim` (its own process, over a pty).
//! Job lines per second and host CPU time per 10,000 lines, one line in flight (as
//! OctoPrint and Printrun do) against send-ahead, on near-instant moves (time scale 0) and
//! on realistic ones (time scale 1: short segments of a curve at print speed) over a link
//! with a USB serial adapter's round trip. The host runs in this process, so this
//! process's CPU time (from /proc) is the host's cost.
//! `cargo bench --bench stream` (CRISPEN_BENCH_LINES sets the instant-run line count).

use crispen::marlin::firmware::Firmware;
use crispen::marlin::gcode::GcodeProgram;
use crispen::marlin::stream::{Connection, PrintProgress, StreamOptions};
use std::path::PathBuf;
use std::process::Command;
use std::time::{Duration, Instant};

#[path = "../tests/common/mod.rs"]
mod common;
use common::daemon::{spawn_sim, Killed, BIN};

fn cpu_seconds() -> f64 {
    let stat = std::fs::read_to_string("/proc/self/stat").expect("stat");
    let after = stat.rsplit_once(')').expect("stat format").1;
    let fields: Vec<&str> = after.split_whitespace().collect();
    let ticks: f64 = fields[11].parse::<f64>().unwrap() + fields[12].parse::<f64>().unwrap();
    // USER_HZ is 100 on Linux.
    ticks / 100.0
}

/// Short segments of a circle, as slicers write for curved, finely tessellated models.
fn curve(lines: usize, segment_mm: f64, feed: f64) -> GcodeProgram {
    let radius = 20.0;
    let step = segment_mm / radius;
    // Start where the curve starts: a travel from the origin would take seconds at print
    // speed and hide the per-segment pace in the realistic runs.
    let start = format!("G92 X{:.3} Y100.000 E0", 100.0 + radius);
    let commands = std::iter::once(start)
        .chain((1..lines).map(|i| {
            let a = i as f64 * step;
            format!(
                "G1 X{:.3} Y{:.3} E{:.5} F{feed}",
                100.0 + radius * a.cos(),
                100.0 + radius * a.sin(),
                i as f64 * 0.002
            )
        }))
        .collect();
    GcodeProgram::from_commands("curve", commands)
}

/// How the simulated link behaves: a pty alone, or with a USB adapter's delay and speed.
#[derive(Clone, Copy)]
struct Link {
    round_trip_ms: f64,
    baud_limit: Option<u32>,
}

const PTY: Link = Link {
    round_trip_ms: 0.0,
    baud_limit: None,
};

/// A `crispen sim` process behind `link`, killed when dropped, and its pty.
fn start_sim(fw: Firmware, time_scale: f64, link: Link) -> (Killed, PathBuf) {
    let mut sim = Command::new(BIN);
    sim.args(["sim", "--firmware", fw.name(), "--speed"])
        .arg(crispen::sim::speed_of_time_scale(time_scale))
        // The simulator delays each direction by this, so a round trip costs twice it.
        .arg("--latency-ms")
        .arg((link.round_trip_ms / 2.0).to_string());
    if let Some(baud) = link.baud_limit {
        sim.arg("--baud-limit").arg(baud.to_string());
    }
    let (child, device) = spawn_sim(&mut sim);
    (Killed(child), device)
}

struct Run {
    lines_per_s: f64,
    cpu_per_10k: f64,
    cpu_percent: f64,
}

fn run(
    rt: &tokio::runtime::Runtime,
    fw: Firmware,
    send_ahead: bool,
    time_scale: f64,
    link: Link,
    program: &GcodeProgram,
) -> Run {
    let (sim, device) = start_sim(fw, time_scale, link);
    let mut opts = StreamOptions::for_firmware(fw);
    opts.send_ahead = send_ahead;
    opts.protocol.quiet_period = Duration::from_millis(200);
    let (wall, cpu) = rt.block_on(async {
        let mut conn = Connection::open(&device, &opts).await.expect("connects");
        let (_control, control_rx) = tokio::sync::mpsc::channel(1);
        let (progress, _) = tokio::sync::watch::channel(PrintProgress::default());
        let cpu0 = cpu_seconds();
        let t0 = Instant::now();
        conn.print(program, control_rx, progress)
            .await
            .expect("job done");
        (t0.elapsed().as_secs_f64(), cpu_seconds() - cpu0)
    });
    drop(sim);
    let n = program.len() as f64;
    Run {
        lines_per_s: n / wall,
        cpu_per_10k: cpu / n * 10_000.0,
        cpu_percent: cpu / wall * 100.0,
    }
}

fn main() {
    let instant_lines: usize = std::env::var("CRISPEN_BENCH_LINES")
        .ok()
        .and_then(|v| v.parse().ok())
        .unwrap_or(10_000);
    let rt = tokio::runtime::Builder::new_current_thread()
        .enable_all()
        .build()
        .unwrap();
    // 250000 baud carries 25,000 bytes/s: about this many of these lines per second.
    let sample = curve(100, 0.2, 3000.0);
    let bytes: usize = sample.iter().map(|c| c.len() + 12).sum();
    let link_rate = 25_000.0 / (bytes as f64 / 100.0);
    println!("stream benchmark: a 250000-baud link carries ~{link_rate:.0} such lines/s");
    println!(
        "{:<11} {:<19} {:<12} {:>9} {:>12} {:>11}",
        "firmware", "moves, link", "mode", "lines/s", "cpu s/10k", "cpu %core"
    );
    for fw in Firmware::ALL {
        // A pty answers in microseconds, so on realistic moves both hosts are held to the
        // same pace by the planner and the benchmark cannot show what send-ahead buys. A
        // real printer sits behind USB: 1 ms full-speed frames each way make ~2 ms a round
        // trip on a native-USB (CDC-ACM) board, which ignores the baud rate. An FTDI/CH340
        // adapter adds its latency timer (FTDI's default flushes short packets such as
        // `ok` after up to 16 ms), ~8 ms being a fair middle, and really runs at the
        // firmware's baud rate; the last row adds that limit.
        let usb = |round_trip_ms| Link {
            round_trip_ms,
            baud_limit: None,
        };
        let adapter = Link {
            round_trip_ms: 8.0,
            baud_limit: Some(fw.default_baud()),
        };
        let realistic = || curve(1_500, 0.2, 3000.0);
        for (label, time_scale, link, program) in [
            ("instant, pty", 0.0, PTY, curve(instant_lines, 0.2, 3000.0)),
            // 0.2 mm segments at 50 mm/s: 250 segments/s wanted by the motion, 4 ms each.
            ("realistic, pty", 1.0, PTY, realistic()),
            ("realistic, 2 ms", 1.0, usb(2.0), realistic()),
            ("realistic, 8 ms", 1.0, usb(8.0), realistic()),
            ("realistic, 8ms+baud", 1.0, adapter, realistic()),
        ] {
            let mut rates = Vec::new();
            let mut cpu = Vec::new();
            for (mode, send_ahead) in [("one-line", false), ("send-ahead", true)] {
                let r = run(&rt, fw, send_ahead, time_scale, link, &program);
                println!(
                    "{:<11} {:<19} {:<12} {:>9.0} {:>12.3} {:>11.2}",
                    fw.name(),
                    label,
                    mode,
                    r.lines_per_s,
                    r.cpu_per_10k,
                    r.cpu_percent
                );
                rates.push(r.lines_per_s);
                cpu.push(r.cpu_per_10k);
            }
            println!(
                "{:<11} {:<19} send-ahead / one-line = {:.2}x; send-ahead CPU per line × link rate ≈ {:.2}% of a core",
                fw.name(),
                label,
                rates[1] / rates[0],
                cpu[1] / 10_000.0 * link_rate * 100.0
            );
        }
    }
}
