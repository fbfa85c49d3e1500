//! A real Spoolman server (0.26.1) for one test, from the folder `CRISPEN_SPOOLMAN_DIR`
//! names (its `serve-spoolman PORT DATA_DIR` script): on a free port of 127.0.0.1, with a
//! fresh SQLite database in a temporary folder, stopped when the value is dropped. The
//! server is not part of the repository: the tests that use it are `ignore`d, with the
//! reason, where the variable was unset at build time (the `crispen_spoolman` cfg).
#![allow(dead_code)] // each test binary uses its own part of this module

use super::http;
use serde_json::{json, Value};
use std::os::unix::process::CommandExt;
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};

/// The first start installs Spoolman's Python dependencies from PyPI into a venv (about a
/// minute, longer on a slow mirror); later ones take a few seconds.
const START_LIMIT: Duration = Duration::from_secs(240);
/// How long the server has to stop on SIGTERM before it is killed.
const STOP_LIMIT: Duration = Duration::from_secs(10);

pub struct SpoolmanServer {
    /// The base address, `http://127.0.0.1:PORT`.
    pub url: String,
    /// `127.0.0.1:PORT`, for the tests' plain HTTP client.
    addr: String,
    child: Option<Child>,
    data: tempfile::TempDir,
}

/// The folder with `serve-spoolman`, from `CRISPEN_SPOOLMAN_DIR`. The tests that start a
/// server are `ignore`d where the variable was unset at build time (`build.rs` sets the
/// `crispen_spoolman` cfg), so this is reached without it only through `--ignored`.
fn spoolman_dir() -> PathBuf {
    let dir = std::env::var_os("CRISPEN_SPOOLMAN_DIR")
        .filter(|d| !d.is_empty())
        .map(PathBuf::from)
        .expect(
            "set CRISPEN_SPOOLMAN_DIR to the folder with the real Spoolman server \
             (serve-spoolman) to run this test",
        );
    assert!(
        dir.join("serve-spoolman").exists(),
        "CRISPEN_SPOOLMAN_DIR={} has no serve-spoolman",
        dir.display()
    );
    dir
}

/// A port nothing listens on now. Another process could take it before Spoolman binds it;
/// then the server dies at start and the panic shows its log.
fn free_port() -> u16 {
    std::net::TcpListener::bind("127.0.0.1:0")
        .unwrap()
        .local_addr()
        .unwrap()
        .port()
}

/// How a start ended when the server did not come up.
enum Start {
    Healthy,
    /// Another process took the port between [`free_port`] and the server's bind.
    PortTaken,
}

impl SpoolmanServer {
    /// Starts a server and waits until it says it is healthy.
    pub fn start() -> SpoolmanServer {
        let dir = spoolman_dir();
        let data = tempfile::Builder::new()
            .prefix("crispen-spoolman.")
            .tempdir()
            .unwrap();
        let mut server = SpoolmanServer {
            url: String::new(),
            addr: String::new(),
            child: None,
            data,
        };
        for _ in 0..5 {
            let port = free_port();
            server.addr = format!("127.0.0.1:{port}");
            server.url = format!("http://{}", server.addr);
            server.child = Some(server.spawn(&dir, port));
            if let Start::Healthy = server.wait_healthy(port) {
                return server;
            }
        }
        panic!(
            "Spoolman found its port taken five times; its log ends:\n{}",
            server.log_tail()
        );
    }

    /// `serve-spoolman PORT DATA_DIR`, its output in the data folder's `server.log`.
    fn spawn(&self, dir: &Path, port: u16) -> Child {
        let log = std::fs::File::create(self.data.path().join("server.log")).unwrap();
        // A process group of its own, so the script and everything it started end together.
        Command::new(dir.join("serve-spoolman"))
            .arg(port.to_string())
            .arg(self.data.path().join("db"))
            // Its access log goes to a file: line by line, so a test can follow it.
            .env("PYTHONUNBUFFERED", "1")
            .process_group(0)
            .stdin(Stdio::null())
            .stdout(log.try_clone().unwrap())
            .stderr(log)
            .spawn()
            .unwrap_or_else(|e| panic!("starting {}/serve-spoolman: {e}", dir.display()))
    }

    fn wait_healthy(&mut self, port: u16) -> Start {
        // Uvicorn says where it listens only once it has bound the port, after the app has
        // started (its migrations run): until then a server on that port is someone
        // else's, e.g. another test's.
        let listening = format!("Uvicorn running on http://127.0.0.1:{port}");
        let started = Instant::now();
        loop {
            if let Some(status) = self.child.as_mut().unwrap().try_wait().unwrap() {
                self.child = None;
                if self.log().contains("address already in use") {
                    return Start::PortTaken;
                }
                panic!(
                    "Spoolman exited ({status}) at start; its log ends:\n{}",
                    self.log_tail()
                );
            }
            if self.log().contains(&listening) {
                let answer = http::request(&self.addr, "GET", "/api/v1/health", &[], b"");
                assert!(
                    answer.status == 200 && answer.json()["status"] == "healthy",
                    "Spoolman's health: HTTP {} {}",
                    answer.status,
                    answer.text()
                );
                return Start::Healthy;
            }
            assert!(
                started.elapsed() < START_LIMIT,
                "Spoolman was not healthy within {START_LIMIT:?}; its log ends:\n{}",
                self.log_tail()
            );
            std::thread::sleep(Duration::from_millis(200));
        }
    }

    /// The server's output.
    pub fn log(&self) -> String {
        std::fs::read_to_string(self.data.path().join("server.log")).unwrap_or_default()
    }

    /// The last lines of the server's output.
    pub fn log_tail(&self) -> String {
        let log = self.log();
        let lines: Vec<&str> = log.lines().collect();
        lines[lines.len().saturating_sub(40)..].join("\n")
    }

    /// One JSON request; the answer's JSON, asserting a success.
    fn call(&self, method: &str, path: &str, body: Option<Value>) -> Value {
        let body = body.map(|b| b.to_string()).unwrap_or_default();
        let headers: &[(&str, &str)] = if body.is_empty() {
            &[]
        } else {
            &[("Content-Type", "application/json")]
        };
        let answer = http::request(&self.addr, method, path, headers, body.as_bytes());
        assert!(
            (200..300).contains(&answer.status),
            "{method} {path} {body}: HTTP {} {}",
            answer.status,
            answer.text()
        );
        answer.json()
    }

    /// The vendor called `name`, made when there is none yet.
    fn vendor(&self, name: &str) -> u64 {
        // Spoolman's `name` filter matches loosely (any case, part of the name): the exact
        // one is picked here.
        let query = crispen::percent::percent_encode(name);
        let found = self.call("GET", &format!("/api/v1/vendor?name={query}"), None);
        if let Some(v) = found.as_array().unwrap().iter().find(|v| v["name"] == name) {
            return v["id"].as_u64().unwrap();
        }
        self.call("POST", "/api/v1/vendor", Some(json!({ "name": name })))["id"]
            .as_u64()
            .unwrap()
    }

    /// A spool of a new filament (`material` in `colour_hex` by `brand`, priced per kg)
    /// holding `initial_g` of which `used_g` are used; its id.
    #[allow(clippy::too_many_arguments)] // the figures a test sets, named at each call
    pub fn create_spool(
        &self,
        material: &str,
        colour_hex: &str,
        brand: &str,
        initial_g: f64,
        used_g: f64,
        price_per_kg: f64,
        diameter_mm: f64,
    ) -> u64 {
        let vendor = self.vendor(brand);
        let density = match material {
            "PETG" => 1.27,
            "ABS" => 1.04,
            "ASA" => 1.07,
            "TPU" => 1.21,
            _ => 1.24,
        };
        // The filament is priced per 1000 g, so its price is the price per kg as given.
        let filament = self.call(
            "POST",
            "/api/v1/filament",
            Some(json!({
                "name": format!("{material} {colour_hex}"),
                "vendor_id": vendor,
                "material": material,
                "density": density,
                "diameter": diameter_mm,
                "weight": 1000.0,
                "price": price_per_kg,
                "color_hex": colour_hex,
            })),
        );
        let spool = self.call(
            "POST",
            "/api/v1/spool",
            Some(json!({
                "filament_id": filament["id"],
                "initial_weight": initial_g,
                "used_weight": used_g,
            })),
        );
        spool["id"].as_u64().unwrap()
    }

    /// A spool of a new filament, both as given (Spoolman's own fields: what its API
    /// takes, whatever crispen makes of it); its id. `filament` needs no vendor.
    pub fn create_raw(&self, filament: Value, spool: Value) -> u64 {
        let filament = self.call("POST", "/api/v1/filament", Some(filament));
        let mut spool = spool;
        spool["filament_id"] = filament["id"].clone();
        self.call("POST", "/api/v1/spool", Some(spool))["id"]
            .as_u64()
            .unwrap()
    }

    /// How many times the spools were listed (`GET /api/v1/spool?...`), from the
    /// server's access log: a client's reading of them, seen from the server.
    pub fn listings(&self) -> usize {
        self.log()
            .lines()
            .filter(|l| l.contains("\"GET /api/v1/spool?"))
            .count()
    }

    /// Spoolman's own JSON for spool `id`.
    pub fn spool_json(&self, id: u64) -> Value {
        self.call("GET", &format!("/api/v1/spool/{id}"), None)
    }

    /// Archives spool `id` (Spoolman then leaves it out of its list unless asked).
    pub fn archive(&self, id: u64) {
        self.call(
            "PATCH",
            &format!("/api/v1/spool/{id}"),
            Some(json!({ "archived": true })),
        );
    }
}

impl Drop for SpoolmanServer {
    fn drop(&mut self) {
        let Some(mut child) = self.child.take() else {
            return;
        };
        let group = nix::unistd::Pid::from_raw(child.id() as i32);
        let _ = nix::sys::signal::killpg(group, nix::sys::signal::Signal::SIGTERM);
        let deadline = Instant::now() + STOP_LIMIT;
        while Instant::now() < deadline {
            // The script execs uvicorn, which runs alone: its end is the group's.
            if let Ok(Some(_)) = child.try_wait() {
                return;
            }
            std::thread::sleep(Duration::from_millis(50));
        }
        // Not reaped yet, so the group's id is still the server's.
        let _ = nix::sys::signal::killpg(group, nix::sys::signal::Signal::SIGKILL);
        let _ = child.wait();
    }
}
