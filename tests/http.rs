//! The HTTP API, the dashboard and the OctoPrint-compatible upload, against the real
//! binary: a daemon with simulated printers and `[http]` on a loopback port, spoken to
//! over real TCP by a minimal HTTP/1.1 client (so every byte on the wire is the test's
//! own, as a slicer would send it), and the dashboard driven in a real headless Chromium
//! through chromedriver (Debian packages `chromium` and `chromium-driver`).

use serde_json::{json, Value};
use std::io::{BufRead, BufReader, Read, Write};
use std::net::TcpStream;
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};

const BIN: &str = env!("CARGO_BIN_EXE_crispen");
const KEY: &str = "test-key-0123456789abcdef";

struct Killed(Child);

impl Drop for Killed {
    fn drop(&mut self) {
        let _ = self.0.kill();
        let _ = self.0.wait();
    }
}

/// A daemon serving `[http]` on a loopback port the system picks.
struct Farm {
    _daemon: Killed,
    addr: String,
    root: PathBuf,
    log: PathBuf,
}

impl Farm {
    fn start(root: &Path, time_scale: f64, http_extra: &str) -> Farm {
        std::fs::create_dir_all(root.join("hot")).unwrap();
        std::fs::write(root.join("key"), format!("{KEY}\n")).unwrap();
        let printer = |name: &str| {
            format!(
                "[[printer]]\nname = \"{name}\"\nfirmware = \"marlin2\"\n\
                 [printer.simulate]\ntime_scale = {time_scale}\n"
            )
        };
        let config = root.join("crispen.toml");
        std::fs::write(
            &config,
            format!(
                "[spool]\ndir = \"spool\"\n[control]\nsocket = \"c.sock\"\n[farm]\nsettle_s = 0.3\n\
                 [http]\nlisten = \"127.0.0.1:0\"\napi_key_file = \"key\"\nupload_max_mb = 1\n{http_extra}\n\
                 {}{}[[folder]]\npath = \"hot\"\nheight_mm = 25\nprinters = [\"alpha\", \"beta\"]\n",
                printer("alpha"),
                printer("beta")
            ),
        )
        .unwrap();
        let log = root.join("daemon.log");
        let daemon = Command::new(BIN)
            .args(["run", "--config"])
            .arg(&config)
            .env("RUST_LOG", "info")
            .stdout(Stdio::null())
            .stderr(std::fs::File::create(&log).unwrap())
            .spawn()
            .unwrap();
        let daemon = Killed(daemon);
        // The daemon logs the address it listens on (port 0: the system's pick).
        let started = Instant::now();
        let addr = loop {
            let text = std::fs::read_to_string(&log).unwrap_or_default();
            if let Some(line) = text.lines().find(|l| l.contains("http: listening")) {
                let at = line.find("address=").expect("address field") + "address=".len();
                break line[at..].split_whitespace().next().unwrap().to_string();
            }
            assert!(
                started.elapsed() < Duration::from_secs(30),
                "the daemon did not start listening:\n{text}"
            );
            std::thread::sleep(Duration::from_millis(50));
        };
        Farm {
            _daemon: daemon,
            addr,
            root: root.to_path_buf(),
            log,
        }
    }

    fn get(&self, path: &str, key: Option<&str>) -> Answer {
        request(&self.addr, "GET", path, &key_header(key), b"")
    }

    fn post(&self, path: &str, key: Option<&str>) -> Answer {
        request(&self.addr, "POST", path, &key_header(key), b"")
    }

    fn status(&self) -> Value {
        let a = self.get("/api/v1/status", Some(KEY));
        assert_eq!(a.status, 200, "{}", a.text());
        a.json()
    }

    /// Polls the status until `check` holds.
    fn wait_for(&self, limit: Duration, what: &str, check: impl Fn(&Value) -> bool) -> Value {
        let started = Instant::now();
        loop {
            let s = self.status();
            if check(&s) {
                return s;
            }
            if started.elapsed() > limit {
                panic!(
                    "timed out waiting for {what}\nlast status: {s:#}\nlog:\n{}",
                    std::fs::read_to_string(&self.log).unwrap_or_default()
                );
            }
            std::thread::sleep(Duration::from_millis(200));
        }
    }
}

fn key_header(key: Option<&str>) -> Vec<(&'static str, String)> {
    key.map(|k| vec![("X-Api-Key", k.to_string())])
        .unwrap_or_default()
}

fn job<'a>(status: &'a Value, file: &str) -> Option<&'a Value> {
    status["jobs"]
        .as_array()?
        .iter()
        .find(|j| j["file"] == file)
}

fn printer<'a>(status: &'a Value, name: &str) -> &'a Value {
    status["printers"]
        .as_array()
        .unwrap()
        .iter()
        .find(|p| p["name"] == name)
        .unwrap()
}

struct Answer {
    status: u16,
    headers: String,
    body: Vec<u8>,
}

impl Answer {
    fn text(&self) -> String {
        String::from_utf8_lossy(&self.body).into_owned()
    }
    fn json(&self) -> Value {
        serde_json::from_slice(&self.body)
            .unwrap_or_else(|e| panic!("not JSON ({e}): {}", self.text()))
    }
    /// The JSON error message, asserting the body is `{"error": "..."}`.
    fn error(&self) -> String {
        self.json()["error"]
            .as_str()
            .unwrap_or_else(|| panic!("no error message in {}", self.text()))
            .to_string()
    }
}

/// One HTTP/1.1 request on its own connection, the bytes written exactly as given.
fn request(
    addr: &str,
    method: &str,
    path: &str,
    headers: &[(&str, String)],
    body: &[u8],
) -> Answer {
    let mut head = format!("{method} {path} HTTP/1.1\r\nHost: {addr}\r\nConnection: close\r\n");
    for (k, v) in headers {
        head.push_str(&format!("{k}: {v}\r\n"));
    }
    head.push_str(&format!("Content-Length: {}\r\n\r\n", body.len()));
    let mut bytes = head.into_bytes();
    bytes.extend_from_slice(body);
    raw(addr, &bytes)
}

/// Sends `bytes` and reads the answer to the end (skipping a `100 Continue`).
fn raw(addr: &str, bytes: &[u8]) -> Answer {
    let mut stream = TcpStream::connect(addr).unwrap();
    stream
        .set_read_timeout(Some(Duration::from_secs(60)))
        .unwrap();
    // The server may answer (an error) before taking the whole body; that is fine.
    let _ = stream.write_all(bytes);
    let mut reader = BufReader::new(stream);
    loop {
        let mut status_line = String::new();
        reader.read_line(&mut status_line).unwrap();
        let status: u16 = status_line
            .split_whitespace()
            .nth(1)
            .unwrap_or_else(|| panic!("no status line: {status_line:?}"))
            .parse()
            .unwrap();
        let mut headers = String::new();
        loop {
            let mut line = String::new();
            reader.read_line(&mut line).unwrap();
            if line == "\r\n" || line.is_empty() {
                break;
            }
            headers.push_str(&line.to_ascii_lowercase());
        }
        if status == 100 {
            continue;
        }
        let mut body = Vec::new();
        if headers.contains("transfer-encoding: chunked") {
            loop {
                let mut size = String::new();
                reader.read_line(&mut size).unwrap();
                let size = usize::from_str_radix(size.trim(), 16).unwrap();
                let mut chunk = vec![0; size + 2];
                reader.read_exact(&mut chunk).unwrap();
                if size == 0 {
                    break;
                }
                body.extend_from_slice(&chunk[..size]);
            }
        } else {
            let _ = reader.read_to_end(&mut body);
        }
        return Answer {
            status,
            headers,
            body,
        };
    }
}

/// A model as a binary STL, as slicers hold it.
fn spot_stl() -> Vec<u8> {
    let path = Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/data/spot.obj");
    let mesh = crispen::mesh::load(&path).unwrap().mesh;
    let mut bytes = Vec::new();
    crispen::mesh::write_stl(&mut bytes, &mesh).unwrap();
    bytes
}

fn spot_obj() -> Vec<u8> {
    std::fs::read(Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/data/spot.obj")).unwrap()
}

/// Files in the hot folder, hidden ones (an upload's temporary file) included.
fn hot_files(root: &Path) -> Vec<String> {
    let mut names: Vec<String> = std::fs::read_dir(root.join("hot"))
        .unwrap()
        .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
        .collect();
    names.sort();
    names
}

/// The API on TCP: the key is required (401 without, 403 wrong), every error is JSON
/// naming what is wrong, uploads are bounded and land only in the hot folder by their
/// plain name, an uploaded model becomes a job that is prepared (with its pictures and
/// G-code thumbnails) and printed, the actions work, and events and metrics describe the farm.
#[test]
fn api_over_tcp_with_and_without_the_key() {
    let tmp = tempfile::tempdir().unwrap();
    let farm = Farm::start(tmp.path(), 0.0, "");

    // The key.
    let a = farm.get("/api/v1/status", None);
    assert_eq!(a.status, 401);
    assert!(a.error().contains("X-Api-Key"), "{}", a.text());
    let a = farm.get("/api/v1/status", Some("not-the-key-at-all"));
    assert_eq!(a.status, 403);
    assert!(a.error().contains("does not match"), "{}", a.text());
    assert_eq!(farm.post("/api/v1/printers/alpha/clear", None).status, 401);
    for path in [
        "/metrics",
        "/api/v1/events",
        "/api/version",
        "/api/v1/jobs/x/pictures/after.png",
    ] {
        assert_eq!(farm.get(path, None).status, 401, "{path} needs the key");
    }
    // The dashboard's own files hold no data and ask for the key themselves.
    let page = farm.get("/", None);
    assert_eq!(page.status, 200);
    assert!(page.text().contains("/app.js"));

    let s = farm.wait_for(Duration::from_secs(30), "two idle printers", |s| {
        ["alpha", "beta"]
            .iter()
            .all(|p| printer(s, p)["state"] == "idle")
    });
    assert_eq!(s["folders"][0]["name"], "hot");

    // Errors are JSON and name what is wrong.
    let a = farm.post("/api/v1/printers/zeta/clear", Some(KEY));
    assert_eq!(a.status, 404);
    assert!(
        a.error().contains("\"zeta\"") && a.error().contains("alpha"),
        "{}",
        a.text()
    );
    let a = farm.post("/api/v1/printers/alpha/explode", Some(KEY));
    assert_eq!(a.status, 404);
    assert!(a.error().contains("explode"), "{}", a.text());
    let a = farm.post("/api/v1/jobs/0042-nothing/retry", Some(KEY));
    assert_eq!(a.status, 404);
    assert!(a.error().contains("0042-nothing"), "{}", a.text());
    let a = farm.post("/api/v1/printers/alpha/pause", Some(KEY));
    assert_eq!(a.status, 409);
    assert!(a.error().contains("not printing"), "{}", a.text());
    let a = farm.get("/no/such/page", Some(KEY));
    assert_eq!(a.status, 404);
    assert!(a.error().contains("/no/such/page"), "{}", a.text());
    let a = request(
        &farm.addr,
        "DELETE",
        "/api/v1/status",
        &key_header(Some(KEY)),
        b"",
    );
    assert_eq!(a.status, 405);
    assert!(a.error().contains("DELETE"), "{}", a.text());

    // Uploads: only a plain model name, only into a configured hot folder, bounded.
    let put = |folder: &str, name: &str, body: &[u8]| {
        request(
            &farm.addr,
            "PUT",
            &format!("/api/v1/folders/{folder}/files/{name}"),
            &key_header(Some(KEY)),
            body,
        )
    };
    for (name, expect) in [
        ("..%2F..%2Fescape.stl", "without folders"),
        ("%2Fetc%2Fpasswd.stl", "without folders"),
        (".hidden.stl", "hidden"),
        ("notes.txt", ".stl"),
    ] {
        let a = put("hot", name, b"solid x\nendsolid x\n");
        assert_eq!(a.status, 400, "{name}: {}", a.text());
        assert!(a.error().contains(expect), "{name}: {}", a.text());
    }
    let a = put("nowhere", "a.stl", b"x");
    assert_eq!(a.status, 404);
    assert!(
        a.error().contains("nowhere") && a.error().contains("hot"),
        "{}",
        a.text()
    );
    let a = put("hot", "part.gcode", b"G28\n");
    assert_eq!(a.status, 415);
    assert!(a.error().contains("G-code"), "{}", a.text());
    let a = put("hot", "huge.stl", &vec![b'x'; 1024 * 1024 + 1]);
    assert_eq!(a.status, 413);
    assert!(a.error().contains("upload_max_mb"), "{}", a.text());
    assert!(tmp.path().join("escape.stl").exists() == false);
    assert_eq!(
        hot_files(tmp.path()),
        Vec::<String>::new(),
        "nothing left behind"
    );

    // A model uploaded by name becomes a job, prepared with pictures and printed.
    let a = put("hot", "spot.obj", &spot_obj());
    assert_eq!(a.status, 201, "{}", a.text());
    let a = put("hot", "spot.obj", b"v 0 0 0\n");
    assert!(
        a.status == 409 || a.status == 201,
        "a second upload of the name either waits its turn (409) or follows the first: {}",
        a.text()
    );
    let s = farm.wait_for(Duration::from_secs(180), "the upload printed", |s| {
        job(s, "spot.obj").is_some_and(|j| j["state"] == "done")
    });
    let done = job(&s, "spot.obj").unwrap().clone();
    let id = done["id"].as_str().unwrap();
    assert_eq!(done["height_mm"], 25.0);
    assert_eq!(done["strength"], "auto");
    assert_eq!(
        done["pictures"],
        json!(["before.png", "after.png", "displacement.png"])
    );
    let detail = farm.get(&format!("/api/v1/jobs/{id}"), Some(KEY));
    assert_eq!(detail.status, 200);
    let detail = detail.json();
    assert!(
        detail["job"]["slice_report"]["gcode_lines"]
            .as_u64()
            .unwrap()
            > 1000
    );
    assert!(
        detail["job"]["print_report"]["lines_acked"]
            .as_u64()
            .unwrap()
            > 1000
    );
    for name in ["before.png", "after.png", "displacement.png"] {
        let a = farm.get(&format!("/api/v1/jobs/{id}/pictures/{name}"), Some(KEY));
        assert_eq!(a.status, 200, "{name}");
        assert!(a.headers.contains("content-type: image/png"));
        assert_eq!(&a.body[..8], b"\x89PNG\r\n\x1a\n", "{name} is a PNG");
    }
    for other in ["job.json", "..%2Fjob.json", "spot.obj.gcode"] {
        let a = farm.get(&format!("/api/v1/jobs/{id}/pictures/{other}"), Some(KEY));
        assert_eq!(a.status, 404, "{other} is not served");
        assert!(a.error().contains("after.png"), "{}", a.text());
    }
    let gcode = std::fs::read_to_string(tmp.path().join(format!("spool/jobs/{id}/spot.obj.gcode")))
        .unwrap();
    for size in ["300x300", "32x32"] {
        assert!(
            gcode.contains(&format!("; thumbnail begin {size} ")),
            "the G-code has a {size} thumbnail"
        );
    }

    // Actions are the control socket's: the bed gate.
    let s = farm.status();
    let printed_on = job(&s, "spot.obj").unwrap()["printer"]
        .as_str()
        .unwrap()
        .to_string();
    assert_eq!(printer(&s, &printed_on)["bed_cleared"], false);
    let a = farm.post(&format!("/api/v1/printers/{printed_on}/clear"), Some(KEY));
    assert_eq!(a.status, 200, "{}", a.text());
    assert!(a.json()["message"]
        .as_str()
        .unwrap()
        .contains("bed cleared"));
    assert_eq!(printer(&farm.status(), &printed_on)["bed_cleared"], true);
    let a = farm.post(&format!("/api/v1/jobs/{id}/cancel"), Some(KEY));
    assert_eq!(a.status, 409);
    assert!(a.error().contains("only active jobs"), "{}", a.text());

    // Live events: the first one is the whole state.
    let mut stream = TcpStream::connect(&farm.addr).unwrap();
    stream
        .set_read_timeout(Some(Duration::from_secs(20)))
        .unwrap();
    write!(
        stream,
        "GET /api/v1/events HTTP/1.1\r\nHost: x\r\nX-Api-Key: {KEY}\r\n\r\n"
    )
    .unwrap();
    let mut seen = String::new();
    let mut reader = BufReader::new(stream);
    while !seen.contains("\"printers\"") {
        let mut line = String::new();
        if reader.read_line(&mut line).unwrap() == 0 {
            break;
        }
        seen.push_str(&line);
    }
    assert!(seen.contains("text/event-stream"), "{seen}");
    assert!(
        seen.contains("event: status") && seen.contains(id),
        "{seen}"
    );

    // Metrics: Prometheus names, no file names as labels.
    let m = farm.get("/metrics", Some(KEY));
    assert_eq!(m.status, 200);
    assert!(m.headers.contains("text/plain; version=0.0.4"));
    let m = m.text();
    for line in [
        "crispen_printer_up{printer=\"alpha\"} 1",
        "crispen_printer_up{printer=\"beta\"} 1",
        "crispen_jobs{state=\"done\"} 1",
        "crispen_folder_queue_length{folder=\"hot\"} 0",
        "crispen_preparation_duration_seconds_count 1",
        "crispen_print_duration_seconds_count 1",
        "# TYPE crispen_printer_resends_total counter",
        "# TYPE crispen_printer_hotend_celsius gauge",
    ] {
        assert!(m.lines().any(|l| l == line), "metrics lack {line:?}:\n{m}");
    }
    assert!(!m.contains("spot"), "no file name in the metrics:\n{m}");
}

/// An upload made exactly as PrusaSlicer's "Send to printer" (OctoPrint host type) makes
/// it: first `GET /api/version` (its connection test wants "OctoPrint" in `text`), then
/// libcurl's multipart POST with the fields `print`, `path` and `file`, `Expect:
/// 100-continue`, and the key in `X-Api-Key`. The model becomes a job and prints; G-code
/// (what PrusaSlicer sends after slicing itself) is refused with a JSON error until
/// pre-sliced G-code has its own path.
#[test]
fn an_upload_as_prusaslicer_sends_it_becomes_a_job_and_prints() {
    let tmp = tempfile::tempdir().unwrap();
    let farm = Farm::start(tmp.path(), 0.0, "");
    let v = farm.get("/api/version", Some(KEY));
    assert_eq!(v.status, 200);
    let v = v.json();
    assert!(v["text"].as_str().unwrap().starts_with("OctoPrint"), "{v}");
    assert!(v["api"].is_string() && v["server"].is_string(), "{v}");

    let send = |file_name: &str, content: &[u8]| {
        let boundary = "------------------------a1b2c3d4e5f60718";
        let mut body = Vec::new();
        for (name, value) in [("print", "true"), ("path", "hot")] {
            body.extend_from_slice(
                format!(
                    "--{boundary}\r\nContent-Disposition: form-data; name=\"{name}\"\r\n\r\n{value}\r\n"
                )
                .as_bytes(),
            );
        }
        body.extend_from_slice(
            format!(
                "--{boundary}\r\nContent-Disposition: form-data; name=\"file\"; filename=\"{file_name}\"\r\n\
                 Content-Type: application/octet-stream\r\n\r\n"
            )
            .as_bytes(),
        );
        body.extend_from_slice(content);
        body.extend_from_slice(format!("\r\n--{boundary}--\r\n").as_bytes());
        let mut bytes = format!(
            "POST /api/files/local HTTP/1.1\r\nHost: {}\r\nUser-Agent: PrusaSlicer/2.9.2\r\n\
             Accept: */*\r\nX-Api-Key: {KEY}\r\nContent-Length: {}\r\n\
             Content-Type: multipart/form-data; boundary={boundary}\r\nExpect: 100-continue\r\n\r\n",
            farm.addr,
            body.len()
        )
        .into_bytes();
        bytes.extend_from_slice(&body);
        raw(&farm.addr, &bytes)
    };

    let a = send("part.gcode", b"; generated by PrusaSlicer\nG28\n");
    assert_eq!(a.status, 415, "{}", a.text());
    assert!(
        a.error().contains("part.gcode") && a.error().contains("G-code"),
        "{}",
        a.text()
    );

    let a = send("part.stl", &spot_stl());
    assert_eq!(a.status, 201, "{}", a.text());
    let answer = a.json();
    assert_eq!(answer["done"], true);
    assert_eq!(answer["files"]["local"]["name"], "part.stl");
    farm.wait_for(
        Duration::from_secs(180),
        "the slicer's upload printed",
        |s| job(s, "part.stl").is_some_and(|j| j["state"] == "done"),
    );
    assert_eq!(hot_files(tmp.path()), Vec::<String>::new());
    let _ = &farm.root;
}
