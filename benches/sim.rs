//! Benchmark: what a simulated printer costs. The daemon's demo farm and soak runs keep
//! many `crispen sim` processes alive, so this measures, per firmware profile, the
//! simulator process's CPU time (from /proc) while it answers 10,000 numbered moves one
//! line in flight at instant timing, and while it idles with a host connected and
//! temperature autoreport on. `cargo bench --bench sim` (CRISPEN_BENCH_LINES changes the
//! line count).

use std::io::{Read, Write};
use std::os::fd::AsFd;
use std::os::unix::fs::OpenOptionsExt;
use std::process::{Child, Command};
use std::time::{Duration, Instant};

#[path = "../tests/common/mod.rs"]
mod common;
use common::daemon::{spawn_sim, BIN};

fn cpu_seconds(child: &Child) -> f64 {
    let stat = std::fs::read_to_string(format!("/proc/{}/stat", child.id())).expect("stat");
    let after = stat.rsplit_once(')').expect("stat format").1;
    let fields: Vec<&str> = after.split_whitespace().collect();
    // utime and stime are fields 14 and 15 of the full line (11 and 12 after the name).
    let ticks: f64 = fields[11].parse::<f64>().unwrap() + fields[12].parse::<f64>().unwrap();
    // /proc reports in USER_HZ, which is 100 on every Linux architecture.
    let hz = 100.0;
    ticks / hz
}

fn numbered(n: usize, cmd: &str) -> String {
    let body = format!("N{n} {cmd}");
    let sum = body.bytes().fold(0u8, |a, b| a ^ b);
    format!("{body}*{sum}\n")
}

struct Port {
    file: std::fs::File,
    pending: Vec<u8>,
}

impl Port {
    /// Read until a line starting with `ok` (other lines are skipped).
    fn wait_ok(&mut self) {
        loop {
            while let Some(at) = self.pending.iter().position(|&b| b == b'\n') {
                let line: Vec<u8> = self.pending.drain(..=at).collect();
                if line.starts_with(b"ok") {
                    return;
                }
            }
            let mut fds = [nix::poll::PollFd::new(
                self.file.as_fd(),
                nix::poll::PollFlags::POLLIN,
            )];
            let n = nix::poll::poll(&mut fds, nix::poll::PollTimeout::from(5000u16)).unwrap();
            assert!(n > 0, "the simulator stopped answering");
            let mut buf = [0u8; 4096];
            match self.file.read(&mut buf) {
                Ok(n) => self.pending.extend_from_slice(&buf[..n]),
                Err(e) if e.kind() == std::io::ErrorKind::WouldBlock => {}
                Err(e) => panic!("read: {e}"),
            }
        }
    }
}

fn main() {
    let lines: usize = std::env::var("CRISPEN_BENCH_LINES")
        .ok()
        .and_then(|v| v.parse().ok())
        .unwrap_or(10_000);
    println!("firmware    lines  wall_s  lines_per_s  sim_cpu_ms_per_10k  idle_cpu_pct");
    for firmware in ["marlin2", "ultimaker2"] {
        let (mut child, device) = spawn_sim(Command::new(BIN).args([
            "sim",
            "--speed",
            "instant",
            "--firmware",
            firmware,
        ]));
        let file = std::fs::OpenOptions::new()
            .read(true)
            .write(true)
            .custom_flags(nix::libc::O_NOCTTY | nix::libc::O_NONBLOCK)
            .open(&device)
            .expect("open the pty");
        let mut attrs = nix::sys::termios::tcgetattr(&file).unwrap();
        nix::sys::termios::cfmakeraw(&mut attrs);
        nix::sys::termios::tcsetattr(&file, nix::sys::termios::SetArg::TCSANOW, &attrs).unwrap();
        let mut port = Port {
            file,
            pending: Vec::new(),
        };
        port.file
            .write_all(numbered(0, "M110 N0").as_bytes())
            .unwrap();
        port.wait_ok();

        let cpu0 = cpu_seconds(&child);
        let t0 = Instant::now();
        for n in 1..=lines {
            let cmd = format!(
                "G1 X{}.{} Y{}.5 E0.0{} F1800",
                n % 200,
                n % 10,
                n % 150,
                n % 97
            );
            port.file.write_all(numbered(n, &cmd).as_bytes()).unwrap();
            port.wait_ok();
        }
        let wall = t0.elapsed().as_secs_f64();
        let cpu = cpu_seconds(&child) - cpu0;

        port.file
            .write_all(numbered(lines + 1, "M155 S1").as_bytes())
            .unwrap();
        port.wait_ok();
        let idle0 = cpu_seconds(&child);
        let idle_for = Duration::from_secs(3);
        std::thread::sleep(idle_for);
        let idle = cpu_seconds(&child) - idle0;

        println!(
            "{firmware:<10} {lines:>6} {wall:>7.2} {:>12.0} {:>19.1} {:>13.2}",
            lines as f64 / wall,
            cpu * 1000.0 * 10_000.0 / lines as f64,
            idle / idle_for.as_secs_f64() * 100.0
        );
        let _ = nix::sys::signal::kill(
            nix::unistd::Pid::from_raw(child.id() as i32),
            nix::sys::signal::Signal::SIGTERM,
        );
        let _ = child.wait();
    }
}
