//! Benchmark: loading a large G-code file for streaming. A file of millions of very short
//! lines is the worst case for per-command overhead; this reads one (30 MB, 10 million
//! commands, as in the security review) with [`GcodeProgram::load_for`], as a printer's
//! job does, and prints the time taken and this process's memory high-water mark (VmHWM)
//! before and after, so figures compare across changes.
//! `cargo bench --bench gcode_load` (CRISPEN_BENCH_GCODE_LINES sets the command count).

use crispen::marlin::firmware::Firmware;
use crispen::marlin::gcode::GcodeProgram;
use std::io::Write;
use std::time::Instant;

/// A field of /proc/self/status, in kB.
fn status_kb(field: &str) -> u64 {
    let status = std::fs::read_to_string("/proc/self/status").expect("status");
    status
        .lines()
        .find_map(|l| l.strip_prefix(field))
        .and_then(|rest| rest.trim().trim_end_matches("kB").trim().parse().ok())
        .expect("field in /proc/self/status")
}

fn main() {
    let lines: usize = std::env::var("CRISPEN_BENCH_GCODE_LINES")
        .ok()
        .and_then(|v| v.parse().ok())
        .unwrap_or(10_000_000);
    let dir = tempfile::tempdir().expect("temp dir");
    let path = dir.path().join("short.gcode");
    {
        let mut out = std::io::BufWriter::new(std::fs::File::create(&path).expect("create"));
        // `G4`, `G90`, `G91` in turn: two and three bytes each, 3.3 bytes a line on disk.
        let words = ["G4\n", "G90\n", "G91\n"];
        for i in 0..lines {
            out.write_all(words[i % 3].as_bytes()).expect("write");
        }
        out.flush().expect("flush");
    }
    let file_mb = std::fs::metadata(&path).expect("size").len() as f64 / 1e6;
    let before_kb = status_kb("VmHWM:");
    let start = Instant::now();
    let program = GcodeProgram::load_for(&path, Firmware::Marlin2).expect("load");
    let seconds = start.elapsed().as_secs_f64();
    let peak_kb = status_kb("VmHWM:");
    let held_kb = status_kb("VmRSS:");
    assert_eq!(program.len(), lines);
    println!(
        "gcode_load: {lines} commands, {file_mb:.1} MB file: {seconds:.2} s; \
         VmHWM {:.0} MB before, {:.0} MB after ({:.1}x the file); VmRSS {:.0} MB while held",
        before_kb as f64 / 1e3,
        peak_kb as f64 / 1e3,
        (peak_kb - before_kb) as f64 / 1e3 / file_mb,
        held_kb as f64 / 1e3,
    );
    drop(program);
}
