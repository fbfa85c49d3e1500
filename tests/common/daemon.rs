//! The real `crispen` binary as the end-to-end tests drive it: a daemon started with a
//! config, its command-line client, waiting for a condition on `crispen status`, a
//! `crispen sim` process, and child processes that never outlive a test, however it ends.

use crispen::marlin::firmware::Firmware;
use crispen::marlin::gcode::GcodeProgram;
use crispen::sim::is_housekeeping;
use serde_json::Value;
use std::io::{BufRead, BufReader};
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};

pub const BIN: &str = env!("CARGO_BIN_EXE_crispen");

/// A `crispen run`, killed when dropped.
pub struct Daemon {
    pub child: Child,
}

impl Daemon {
    /// `crispen run --config CONFIG`, logging at info level to the end of `log`.
    pub fn start(config: &Path, log: &Path) -> Daemon {
        Daemon::start_by(Command::new(BIN), config, log)
    }

    /// `crispen run` through `launcher` (a command line ending in the binary).
    pub fn start_by(mut launcher: Command, config: &Path, log: &Path) -> Daemon {
        let log = std::fs::OpenOptions::new()
            .create(true)
            .append(true)
            .open(log)
            .unwrap();
        let child = launcher
            .args(["run", "--config"])
            .arg(config)
            .env("RUST_LOG", "info")
            .stdout(Stdio::null())
            .stderr(log)
            .spawn()
            .unwrap();
        Daemon { child }
    }

    pub fn kill9(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

impl Drop for Daemon {
    fn drop(&mut self) {
        self.kill9();
    }
}

/// The address a starting daemon logs for `[http] listen` (port 0: the system's pick), read
/// from its `log` once it is there.
pub fn http_address(log: &Path) -> String {
    let started = Instant::now();
    loop {
        let text = std::fs::read_to_string(log).unwrap_or_default();
        if let Some(line) = text.lines().find(|l| l.contains("http: listening")) {
            let at = line.find("address=").expect("address field") + "address=".len();
            return line[at..].split_whitespace().next().unwrap().to_string();
        }
        assert!(
            started.elapsed() < Duration::from_secs(30),
            "the daemon did not start listening:
{text}"
        );
        std::thread::sleep(Duration::from_millis(50));
    }
}

/// Any other child process, killed and reaped when dropped.
pub struct Killed(pub Child);

impl Drop for Killed {
    fn drop(&mut self) {
        let _ = self.0.kill();
        let _ = self.0.wait();
    }
}

/// Kills the processes it watches when dropped, for children the test itself stops and
/// waits for (to let a simulator finish its record, say): a failing test leaves none behind.
#[derive(Default)]
pub struct Reaper(std::cell::RefCell<Vec<u32>>);

impl Reaper {
    pub fn watch(&self, child: &Child) {
        self.0.borrow_mut().push(child.id());
    }
}

impl Drop for Reaper {
    fn drop(&mut self) {
        for pid in self.0.borrow().iter() {
            let _ = nix::sys::signal::kill(
                nix::unistd::Pid::from_raw(*pid as i32),
                nix::sys::signal::Signal::SIGKILL,
            );
        }
    }
}

/// Starts a `crispen sim` command line (its stdout is taken here) and reads its greeting:
/// the process and the pty device it listens on.
pub fn spawn_sim(sim: &mut Command) -> (Child, PathBuf) {
    let mut child = sim
        .stdout(Stdio::piped())
        .stderr(Stdio::null())
        .spawn()
        .expect("start crispen sim");
    let mut line = String::new();
    BufReader::new(child.stdout.take().unwrap())
        .read_line(&mut line)
        .unwrap();
    let device = line
        .trim()
        .strip_prefix("crispen sim: listening on ")
        .unwrap_or_else(|| panic!("unexpected first line {line:?}"))
        .into();
    (child, device)
}

/// Runs `crispen ARGS --config CONFIG`: whether it succeeded, and its stdout then stderr.
pub fn ctl(config: &Path, args: &[&str]) -> (bool, String) {
    let out = Command::new(BIN)
        .args(args)
        .arg("--config")
        .arg(config)
        .output()
        .unwrap();
    (
        out.status.success(),
        format!(
            "{}{}",
            String::from_utf8_lossy(&out.stdout),
            String::from_utf8_lossy(&out.stderr)
        ),
    )
}

/// `crispen status --json`, or None while the daemon does not answer.
pub fn status(config: &Path) -> Option<Value> {
    let (ok, text) = ctl(config, &["status", "--json"]);
    if !ok {
        return None;
    }
    serde_json::from_str(&text).ok()
}

/// Polls the status until `check` holds; panics with the last status and the log after
/// `limit`.
pub fn wait_for(
    config: &Path,
    log: &Path,
    limit: Duration,
    what: &str,
    check: impl Fn(&Value) -> bool,
) -> Value {
    let start = Instant::now();
    let mut last = None;
    while start.elapsed() < limit {
        if let Some(s) = status(config) {
            if check(&s) {
                return s;
            }
            last = Some(s);
        }
        std::thread::sleep(Duration::from_millis(200));
    }
    panic!(
        "timed out waiting for {what}\nlast status: {}\nlog:\n{}",
        serde_json::to_string_pretty(&last).unwrap(),
        std::fs::read_to_string(log).unwrap_or_default()
    );
}

/// Waits until each of `printers` has looked for a job in the job store's version of
/// `since` (a status answer) or a later one and taken none (its `looked_at`): the event
/// after which a ready job it could take would have been taken, so what it did not do
/// by then is proven not done, with no window watched. Returns that status.
pub fn passed_over(
    config: &Path,
    log: &Path,
    since: &Value,
    printers: &[&str],
    what: &str,
) -> Value {
    let version = since["version"].as_u64().expect("a status has its version");
    wait_for(config, log, Duration::from_secs(60), what, |s| {
        printers.iter().all(|name| {
            super::printer(s, name)["looked_at"]
                .as_u64()
                .is_some_and(|v| v >= version)
        })
    })
}

/// Waits until the job of `file` is done on `printer` and its bed waits to be cleared, then
/// clears it (`crispen clear`).
pub fn clear_after_done(config: &Path, log: &Path, printer: &str, file: &str) {
    wait_for(
        config,
        log,
        Duration::from_secs(90),
        &format!("{file} done"),
        |s| state_of(s, file) == "done" && super::printer(s, printer)["bed_cleared"] == false,
    );
    let (ok, out) = ctl(config, &["clear", printer]);
    assert!(ok, "{out}");
}

/// The state of the job for `file` in a status answer ("" when there is none).
pub fn state_of(s: &Value, file: &str) -> String {
    super::job_by_file(s, file)
        .and_then(|j| j["state"].as_str())
        .unwrap_or("")
        .to_string()
}

/// What a simulator executed, from its record file, housekeeping (temperature reports,
/// line numbers) dropped.
pub fn recorded(path: &Path) -> Vec<String> {
    std::fs::read_to_string(path)
        .unwrap_or_default()
        .lines()
        .filter(|c| !is_housekeeping(c))
        .map(str::to_string)
        .collect()
}

/// Drops a file into a hot folder as a well-behaved program does: written under a hidden
/// temporary name, then renamed into place.
pub fn drop_model(hot: &Path, name: &str, bytes: &[u8]) {
    let part = hot.join(format!(".{name}.part"));
    std::fs::write(&part, bytes).unwrap();
    std::fs::rename(&part, hot.join(name)).unwrap();
}

/// A job's G-code in the spool under `root`, as a `marlin2` printer must execute it (the
/// farms using this have one machine: a `marlin2` printer without `machine`), each command
/// as the printer reads it and the simulator records it (`canonical`).
pub fn job_gcode(root: &Path, id: &str, file: &str) -> Vec<String> {
    let path = root
        .join("spool/jobs")
        .join(id)
        .join(format!("{file}.marlin-175.gcode"));
    GcodeProgram::load_for(&path, Firmware::Marlin2)
        .unwrap()
        .to_vec()
        .iter()
        .map(|c| crispen::marlin::protocol::canonical(c))
        .collect()
}
