//! Several `crispen run` daemons ("hosts") sharing one real PostgreSQL server, for the
//! multi-host tests (tests/farm.rs) and the farm benchmark (benches/farm.rs).
//!
//! Each host is the real binary with its own config, spool, control socket and simulated
//! printers, all in one temporary directory (so folders with the same `path` are the same
//! directory, as a share mounted on every host would be). Its stderr goes to `<host>.log`
//! in that directory, shown on any failure. Set `CRISPEN_KEEP_FARM=1` to keep the
//! directory of a failed test.
//!
//! Printers are `marlin2` machines (`marlin-175`); [`presliced_gcode`] writes G-code made
//! for them whose `M118` line names the job in what each simulator executed.

use super::postgres::PgServer;
use serde_json::Value;
use std::io::{Read, Write};
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};

pub const BIN: &str = env!("CARGO_BIN_EXE_crispen");

/// One host's part of the farm.
pub struct HostSpec {
    pub name: String,
    /// Its simulated printers' names.
    pub printers: Vec<String>,
    /// Its hot folders: path (relative to the farm's directory) and the printers, of any
    /// host, that may print what is dropped there.
    pub folders: Vec<(String, Vec<String>)>,
    /// The simulators' time scale (0 = instant, 1 = real time).
    pub time_scale: f64,
    /// `[store] lease_s`; `None` leaves the default.
    pub lease_s: Option<u32>,
}

/// One `crispen run` process and its files.
pub struct Host {
    pub name: String,
    pub config: PathBuf,
    pub log: PathBuf,
    pub socket: PathBuf,
    pub printers: Vec<String>,
    /// Extra environment for `crispen run` (e.g. a stand-in slicer).
    pub env: Vec<(String, PathBuf)>,
    child: Option<Child>,
}

impl Host {
    /// Writes the host's config into `root`; the host is not started.
    pub fn configure(root: &Path, spec: &HostSpec, conninfo: &str) -> Host {
        let name = &spec.name;
        let mut text = format!(
            r#"[spool]
dir = "spool-{name}"
[control]
socket = "{name}.sock"
[store]
postgres = "{conninfo}"
{lease}[farm]
host = "{name}"
max_heating = {heating}
settle_s = 0.5
rescan_s = 2
"#,
            lease = spec
                .lease_s
                .map(|s| format!("lease_s = {s}\n"))
                .unwrap_or_default(),
            heating = spec.printers.len().max(1),
        );
        for p in &spec.printers {
            text += &format!(
                r#"
[[printer]]
name = "{p}"
firmware = "marlin2"
[printer.simulate]
time_scale = {}
record = "{p}.rec"
"#,
                spec.time_scale
            );
        }
        for (path, printers) in &spec.folders {
            std::fs::create_dir_all(root.join(path)).unwrap();
            let names: Vec<String> = printers.iter().map(|p| format!("{p:?}")).collect();
            text += &format!(
                r#"
[[folder]]
path = "{path}"
height_mm = 12
enhance = false
printers = [{}]
"#,
                names.join(", ")
            );
        }
        let config = root.join(format!("{name}.toml"));
        std::fs::write(&config, text).unwrap();
        Host {
            name: name.clone(),
            config,
            log: root.join(format!("{name}.log")),
            socket: root.join(format!("{name}.sock")),
            printers: spec.printers.clone(),
            env: Vec::new(),
            child: None,
        }
    }

    /// Starts `crispen run` (again, after [`Host::kill9`]); its log is appended to.
    pub fn start(&mut self) {
        assert!(self.child.is_none(), "{} is already running", self.name);
        let log = std::fs::OpenOptions::new()
            .create(true)
            .append(true)
            .open(&self.log)
            .unwrap();
        let child = Command::new(BIN)
            .args(["run", "--config"])
            .arg(&self.config)
            .env("RUST_LOG", "crispen=debug")
            .envs(self.env.iter().map(|(k, v)| (k, v)))
            .stdin(Stdio::null())
            .stdout(Stdio::null())
            .stderr(log)
            .spawn()
            .unwrap();
        self.child = Some(child);
    }

    /// A second host under this one's `[farm] host`, as on a cloned machine: the same
    /// config but for its own spool, control socket, log and simulators' records (each
    /// named with `tag`). Not started.
    pub fn clone_as(&self, tag: &str) -> Host {
        let root = self.config.parent().unwrap();
        let name = &self.name;
        let mut text = std::fs::read_to_string(&self.config)
            .unwrap()
            .replace(
                &format!("dir = \"spool-{name}\""),
                &format!("dir = \"spool-{tag}\""),
            )
            .replace(
                &format!("socket = \"{name}.sock\""),
                &format!("socket = \"{tag}.sock\""),
            );
        for p in &self.printers {
            text = text.replace(
                &format!("record = \"{p}.rec\""),
                &format!("record = \"{tag}-{p}.rec\""),
            );
        }
        let config = root.join(format!("{tag}.toml"));
        std::fs::write(&config, text).unwrap();
        Host {
            name: self.name.clone(),
            config,
            log: root.join(format!("{tag}.log")),
            socket: root.join(format!("{tag}.sock")),
            printers: self.printers.clone(),
            env: self.env.clone(),
            child: None,
        }
    }

    /// Waits up to `limit` for the host to exit: its exit status, or `None` if it runs on.
    pub fn wait_exit(&mut self, limit: Duration) -> Option<std::process::ExitStatus> {
        let start = Instant::now();
        loop {
            let child = self.child.as_mut()?;
            if let Some(status) = child.try_wait().unwrap() {
                self.child = None;
                return Some(status);
            }
            if start.elapsed() > limit {
                return None;
            }
            std::thread::sleep(Duration::from_millis(100));
        }
    }

    /// Sends `signal` to the running host (SIGSTOP freezes it as a hung machine would).
    pub fn signal(&self, signal: nix::sys::signal::Signal) {
        let pid = self.pid().expect("the host is running");
        nix::sys::signal::kill(nix::unistd::Pid::from_raw(pid as i32), signal).unwrap();
    }

    /// `kill -9`: the host dies with its printers mid-whatever.
    pub fn kill9(&mut self) {
        if let Some(mut child) = self.child.take() {
            let _ = child.kill();
            let _ = child.wait();
        }
    }

    pub fn pid(&self) -> Option<u32> {
        self.child.as_ref().map(|c| c.id())
    }

    /// A `crispen` command against this host: success and its output. One that takes
    /// longer than a minute (a daemon stuck on its database) is killed and failed.
    pub fn ctl(&self, args: &[&str]) -> (bool, String) {
        let mut child = Command::new(BIN)
            .args(args)
            .arg("--config")
            .arg(&self.config)
            .stdin(Stdio::null())
            .stdout(Stdio::piped())
            .stderr(Stdio::piped())
            .spawn()
            .unwrap();
        let read = |mut r: Box<dyn Read + Send>| {
            std::thread::spawn(move || {
                let mut text = Vec::new();
                let _ = r.read_to_end(&mut text);
                String::from_utf8_lossy(&text).into_owned()
            })
        };
        let stdout = read(Box::new(child.stdout.take().unwrap()));
        let stderr = read(Box::new(child.stderr.take().unwrap()));
        let start = Instant::now();
        let status = loop {
            if let Some(status) = child.try_wait().unwrap() {
                break Some(status);
            }
            if start.elapsed() > Duration::from_secs(60) {
                let _ = child.kill();
                let _ = child.wait();
                break None;
            }
            std::thread::sleep(Duration::from_millis(20));
        };
        let text = format!(
            "{}{}",
            stdout.join().unwrap_or_default(),
            stderr.join().unwrap_or_default()
        );
        match status {
            Some(status) => (status.success(), text),
            None => (
                false,
                format!("`crispen {}` took over 60 s: {text}", args.join(" ")),
            ),
        }
    }

    /// `crispen status --json`, or `None` while the host does not answer.
    pub fn status(&self) -> Option<Value> {
        let (ok, text) = self.ctl(&["status", "--json"]);
        if !ok {
            return None;
        }
        serde_json::from_str(&text).ok()
    }

    /// One HTTP request on the control socket: status code and body.
    pub fn http(&self, method: &str, path: &str) -> std::io::Result<(u16, String)> {
        http_on(&self.socket, method, path)
    }

    /// The last `lines` lines of the host's log.
    pub fn log_tail(&self, lines: usize) -> String {
        let text = std::fs::read_to_string(&self.log).unwrap_or_default();
        let all: Vec<&str> = text.lines().collect();
        all[all.len().saturating_sub(lines)..].join("\n")
    }
}

impl Drop for Host {
    fn drop(&mut self) {
        self.kill9();
    }
}

/// One HTTP/1.1 request on a unix socket, `Connection: close`, no body.
pub fn http_on(socket: &Path, method: &str, path: &str) -> std::io::Result<(u16, String)> {
    let mut stream = std::os::unix::net::UnixStream::connect(socket)?;
    stream.set_read_timeout(Some(Duration::from_secs(60)))?;
    write!(
        stream,
        "{method} {path} HTTP/1.1\r\nHost: crispen\r\nContent-Length: 0\r\nConnection: close\r\n\r\n"
    )?;
    let mut answer = Vec::new();
    stream.read_to_end(&mut answer)?;
    let answer = String::from_utf8_lossy(&answer);
    let (head, body) = answer.split_once("\r\n\r\n").unwrap_or((&answer, ""));
    let code = head
        .split_whitespace()
        .nth(1)
        .and_then(|c| c.parse().ok())
        .ok_or_else(|| std::io::Error::other(format!("not an HTTP answer: {head}")))?;
    let body = if head
        .to_ascii_lowercase()
        .contains("transfer-encoding: chunked")
    {
        unchunk(body)
    } else {
        body.to_string()
    };
    Ok((code, body))
}

fn unchunk(mut body: &str) -> String {
    let mut out = String::new();
    while let Some((size, rest)) = body.split_once("\r\n") {
        let Ok(n) = usize::from_str_radix(size.trim(), 16) else {
            break;
        };
        if n == 0 || rest.len() < n {
            break;
        }
        out += &rest[..n];
        body = rest[n..].trim_start_matches("\r\n");
    }
    out
}

/// A PostgreSQL server and the hosts sharing it, in one temporary directory.
pub struct Farm {
    pub root: PathBuf,
    dir: Option<tempfile::TempDir>,
    pub pg: PgServer,
    pub hosts: Vec<Host>,
}

impl Farm {
    /// Starts the database, writes every host's config and starts the hosts.
    pub fn start(specs: &[HostSpec]) -> Farm {
        let mut farm = Farm::configure(specs);
        for h in &mut farm.hosts {
            h.start();
        }
        farm
    }

    /// Starts the database and writes every host's config; no host is started.
    pub fn configure(specs: &[HostSpec]) -> Farm {
        let pg = PgServer::start();
        let dir = tempfile::Builder::new()
            .prefix("crispen-farm.")
            .tempdir()
            .unwrap();
        let root = dir.path().to_path_buf();
        let hosts = specs
            .iter()
            .map(|s| Host::configure(&root, s, &pg.conninfo()))
            .collect();
        Farm {
            root,
            dir: Some(dir),
            pg,
            hosts,
        }
    }

    pub fn host(&self, name: &str) -> &Host {
        self.hosts
            .iter()
            .find(|h| h.name == name)
            .unwrap_or_else(|| panic!("no host {name}"))
    }

    pub fn host_mut(&mut self, name: &str) -> &mut Host {
        self.hosts
            .iter_mut()
            .find(|h| h.name == name)
            .unwrap_or_else(|| panic!("no host {name}"))
    }

    /// Each host's log tail and the database server's, for a failure message.
    pub fn diagnostics(&self) -> String {
        let mut text = String::new();
        for h in &self.hosts {
            text += &format!(
                "\n===== host {} ({}), last lines of its log =====\n{}\n",
                h.name,
                h.log.display(),
                h.log_tail(150)
            );
        }
        let pg_log = self.pg.log();
        let pg_lines: Vec<&str> = pg_log.lines().collect();
        text += &format!(
            "\n===== PostgreSQL server log (last lines) =====\n{}\n",
            pg_lines[pg_lines.len().saturating_sub(40)..].join("\n")
        );
        text
    }

    /// Polls `check` every 300 ms until it gives a value; after `limit`, panics with
    /// `what`, the last thing `check` saw (it may keep it in `last`) and the logs.
    pub fn wait_until<T>(
        &self,
        limit: Duration,
        what: &str,
        mut check: impl FnMut(&mut String) -> Option<T>,
    ) -> T {
        let start = Instant::now();
        let mut last = String::new();
        loop {
            if let Some(v) = check(&mut last) {
                return v;
            }
            if start.elapsed() > limit {
                panic!(
                    "timed out after {:?} waiting for {what}\nlast seen: {last}\n{}",
                    limit,
                    self.diagnostics()
                );
            }
            std::thread::sleep(Duration::from_millis(300));
        }
    }

    /// Waits until `host`'s status satisfies `check`; returns that status.
    pub fn wait_status(
        &self,
        host: &str,
        limit: Duration,
        what: &str,
        check: impl Fn(&Value) -> bool,
    ) -> Value {
        let h = self.host(host);
        self.wait_until(limit, what, |last| {
            let s = h.status()?;
            if check(&s) {
                return Some(s);
            }
            *last = serde_json::to_string_pretty(&s).unwrap();
            None
        })
    }

    /// Clears the bed of every printer of the farm that holds a finished print and is
    /// not offline, each through another host than its own (`crispen clear` acts
    /// farm-wide), using only the hosts in `via`. Returns the printers cleared.
    pub fn clear_finished(&self, status: &Value, via: &[&str]) -> Vec<String> {
        let mut cleared = Vec::new();
        for p in status["printers"].as_array().into_iter().flatten() {
            let name = p["name"].as_str().unwrap_or_default();
            if p["bed_cleared"] != false || p["offline"] == true || p["state"] == "printing" {
                continue;
            }
            let own = p["host"].as_str().unwrap_or_default();
            let through = via
                .iter()
                .find(|h| **h != own)
                .or(via.first())
                .expect("a host to clear through");
            let (ok, out) = self.host(through).ctl(&["clear", name]);
            assert!(ok, "crispen clear {name} on {through}: {out}");
            cleared.push(name.to_string());
        }
        cleared
    }

    /// Queries the farm database directly.
    pub fn query(
        &self,
        sql: &str,
        params: &[&(dyn tokio_postgres::types::ToSql + Sync)],
    ) -> Vec<tokio_postgres::Row> {
        let rt = tokio::runtime::Builder::new_current_thread()
            .enable_all()
            .build()
            .unwrap();
        rt.block_on(async {
            let (client, conn) =
                tokio_postgres::connect(&self.pg.conninfo(), tokio_postgres::NoTls)
                    .await
                    .unwrap_or_else(|e| panic!("connecting to the farm database: {e}"));
            let conn = tokio::spawn(conn);
            let rows = client
                .query(sql, params)
                .await
                .unwrap_or_else(|e| panic!("{sql}: {e}"));
            drop(client);
            let _ = conn.await;
            rows
        })
    }

    /// How many times each job entered `printing`, by the database's history.
    pub fn printing_entries(&self) -> std::collections::BTreeMap<String, i64> {
        self.query(
            "SELECT j.id, count(h.job_id) FROM jobs j \
             LEFT JOIN job_history h ON h.job_id = j.id AND h.state = 'printing' GROUP BY j.id",
            &[],
        )
        .iter()
        .map(|r| (r.get(0), r.get(1)))
        .collect()
    }

    /// The `M118` markers each printer of the farm executed, by printer.
    pub fn markers_by_printer(&self) -> std::collections::BTreeMap<String, Vec<String>> {
        self.hosts
            .iter()
            .flat_map(|h| h.printers.iter())
            .map(|p| (p.clone(), markers(&self.root.join(format!("{p}.rec")))))
            .collect()
    }
}

impl Drop for Farm {
    fn drop(&mut self) {
        for h in &mut self.hosts {
            h.kill9();
        }
        if std::thread::panicking() && std::env::var_os("CRISPEN_KEEP_FARM").is_some() {
            if let Some(dir) = self.dir.take() {
                eprintln!("kept the farm's directory {}", dir.keep().display());
            }
        }
    }
}

/// Pre-sliced G-code for a `marlin-175` printer, as a slicer would write it: heat, home,
/// `M118 <marker>`, then `moves` extruding moves of 100 mm at `feed` mm/min around a
/// square, heaters off. The simulator takes 6000 / `feed` seconds per move (times its
/// time scale) plus its heat-up.
pub fn presliced_gcode(marker: &str, moves: usize, feed: u32) -> String {
    let mut g = String::from(
        "; generated by crispen's farm tests\n; filament_diameter = 1.75\n; nozzle_diameter = 0.4\n\
         M104 S200\nM109 S200\nG28\nG90\nM82\nG92 E0\nG1 Z0.3 F600\n",
    );
    g += &format!("M118 {marker}\n");
    let corners = [(60, 60), (160, 60), (160, 160), (60, 160)];
    for i in 0..moves {
        let (x, y) = corners[(i + 1) % 4];
        g += &format!("G1 X{x} Y{y} E{:.1} F{feed}\n", (i + 1) as f64 * 3.3);
    }
    g += "G1 Z10 F600\nM104 S0\nM84\n";
    g
}

/// Drops a file into a hot folder as a careful user does: written under a temporary
/// name, then renamed in.
pub fn drop_file(folder: &Path, name: &str, bytes: &[u8]) {
    let part = folder.join(format!(".{name}.part"));
    std::fs::write(&part, bytes).unwrap();
    std::fs::rename(&part, folder.join(name)).unwrap();
}

/// The markers (`M118 <marker>`) a simulator executed, in order.
pub fn markers(record: &Path) -> Vec<String> {
    std::fs::read_to_string(record)
        .unwrap_or_default()
        .lines()
        .filter_map(|l| l.trim().strip_prefix("M118 "))
        .map(|m| m.trim().to_string())
        .collect()
}

/// The state of the job for `file` ("" when there is none).
pub fn state_of(status: &Value, file: &str) -> String {
    super::job_by_file(status, file)
        .and_then(|j| j["state"].as_str())
        .unwrap_or("")
        .to_string()
}

/// CPU seconds (utime + stime, all threads) used so far by process `pid`, and with
/// `children` also by every process whose parent it is (a PostgreSQL server's backends).
pub fn process_cpu_s(pid: u32, children: bool) -> f64 {
    let ticks = nix::unistd::sysconf(nix::unistd::SysconfVar::CLK_TCK)
        .ok()
        .flatten()
        .unwrap_or(100) as f64;
    let mut total = 0.0;
    for entry in std::fs::read_dir("/proc").unwrap().flatten() {
        let Some(this) = entry
            .file_name()
            .to_str()
            .and_then(|s| s.parse::<u32>().ok())
        else {
            continue;
        };
        let Ok(stat) = std::fs::read_to_string(entry.path().join("stat")) else {
            continue;
        };
        // The command may hold spaces: the fields after it start past the last ')'.
        let Some(after) = stat.rfind(')').map(|i| &stat[i + 2..]) else {
            continue;
        };
        let fields: Vec<&str> = after.split_whitespace().collect();
        let parent: u32 = fields[1].parse().unwrap_or(0);
        if this == pid || (children && parent == pid) {
            let utime: f64 = fields[11].parse().unwrap_or(0.0);
            let stime: f64 = fields[12].parse().unwrap_or(0.0);
            total += (utime + stime) / ticks;
        }
    }
    total
}
