//! The HTTP API, the dashboard and the OctoPrint-compatible upload, against the real
//! binary: a daemon with simulated printers and `[http]` on a loopback port, spoken to
//! over real TCP and over its control socket by a minimal HTTP/1.1 client (so every byte
//! on the wire is the test's own, as a slicer would send it), and the dashboard driven in
//! a real headless Chromium through chromedriver (Debian packages `chromium` and
//! `chromium-driver`).

use crate::common;
use common::daemon::{Daemon, Killed, BIN};
use common::http::{exchange, on_socket, raw, request, Answer};
use common::{job_by_file, printer};
use serde_json::{json, Value};
use std::io::{BufRead, BufReader, Write};
use std::net::TcpStream;
use std::path::{Path, PathBuf};
use std::process::{Command, Stdio};
use std::time::{Duration, Instant};

const KEY: &str = "test-key-0123456789abcdef";

/// A daemon serving `[http]` on a loopback port the system picks.
struct Farm {
    _daemon: Daemon,
    addr: String,
    root: PathBuf,
    log: PathBuf,
}

impl Farm {
    fn start(root: &Path, time_scale: f64, http_extra: &str) -> Farm {
        Farm::start_with(root, time_scale, "", http_extra)
    }

    /// [`Farm::start`] with more keys for `[farm]`; `http_extra` may set `upload_max_mb`
    /// (else 1).
    fn start_with(root: &Path, time_scale: f64, farm_extra: &str, http_extra: &str) -> Farm {
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
                "[spool]\ndir = \"spool\"\n[control]\nsocket = \"c.sock\"\n[farm]\n{}{farm_extra}\n\
                 [http]\nlisten = \"127.0.0.1:0\"\napi_key_file = \"key\"\n{}{http_extra}\n\
                 {}{}[[folder]]\npath = \"hot\"\nheight_mm = 25\nprinters = [\"alpha\", \"beta\"]\n",
                if farm_extra.contains("settle_s") { "" } else { "settle_s = 0.3\n" },
                if http_extra.contains("upload_max_mb") { "" } else { "upload_max_mb = 1\n" },
                printer("alpha"),
                printer("beta")
            ),
        )
        .unwrap();
        let log = root.join("daemon.log");
        let daemon = Daemon::start(&config, &log);
        let addr = common::daemon::http_address(&log);
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
        common::http::poll_status(limit, what, &self.log, || self.status(), check)
    }
}

fn key_header(key: Option<&str>) -> Vec<(&'static str, &str)> {
    key.map(|k| vec![("X-Api-Key", k)]).unwrap_or_default()
}

/// The CLI against the farm made in `root`: whether it succeeded, and what it said.
fn run_cli(root: &Path, args: &[&str]) -> (bool, String) {
    let out = Command::new(BIN)
        .args(args)
        .arg("--config")
        .arg(root.join("crispen.toml"))
        .output()
        .unwrap();
    let text =
        String::from_utf8_lossy(&out.stdout).into_owned() + &String::from_utf8_lossy(&out.stderr);
    (out.status.success(), text)
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

/// A file uploaded exactly as PrusaSlicer's "Send to printer" (OctoPrint host type) sends
/// it: libcurl's multipart POST with the fields `print`, `path` and `file`, `Expect:
/// 100-continue`, and the key in `X-Api-Key`.
fn octoprint_upload(addr: &str, file_name: &str, content: &[u8], print: &str) -> Answer {
    octoprint_form(
        addr,
        &[("print", print), ("path", "hot")],
        file_name,
        content,
    )
}

/// An OctoPrint upload with the given text fields before the file.
fn octoprint_form(addr: &str, fields: &[(&str, &str)], file_name: &str, content: &[u8]) -> Answer {
    let boundary = "------------------------a1b2c3d4e5f60718";
    let mut body = Vec::new();
    for (name, value) in fields {
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
        "POST /api/files/local HTTP/1.1\r\nHost: {addr}\r\nUser-Agent: PrusaSlicer/2.9.2\r\n\
         Accept: */*\r\nX-Api-Key: {KEY}\r\nContent-Length: {}\r\n\
         Content-Type: multipart/form-data; boundary={boundary}\r\nExpect: 100-continue\r\n\r\n",
        body.len()
    )
    .into_bytes();
    bytes.extend_from_slice(&body);
    raw(addr, &bytes)
}

/// A small job written by hand, printed as pre-sliced G-code (no slicer needed): heat the
/// bed to 60 °C and the nozzle to 200 °C, two extruding moves, heaters off.
const WARM_GCODE: &str = "; heat, two lines, heaters off\n\
    M140 S60\nM104 S200\nM190 S60\nM109 S200\nG28\nG92 E0\nG1 Z0.3 F600\n\
    G1 X20 Y20 F3000\nG1 X60 Y20 E4 F1200\nG1 X60 Y60 E8\nM104 S0\nM140 S0\nM84\n";

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

    // The same API on the control socket, without a key (the socket's mode decides), and
    // the CLI speaking it.
    let socket = tmp.path().join("c.sock");
    let a = on_socket(&socket, "GET", "/api/v1/status");
    assert_eq!(a.status, 200, "{}", a.text());
    assert_eq!(a.json()["folders"][0]["name"], "hot");
    let a = on_socket(&socket, "POST", "/api/v1/printers/zeta/clear");
    assert_eq!(a.status, 404);
    assert!(a.error().contains("\"zeta\""), "{}", a.text());
    let a = on_socket(&socket, "POST", "/api/v1/printers/alpha/clear");
    assert_eq!(a.status, 200, "{}", a.text());
    assert!(a.json()["message"].as_str().unwrap().contains("alpha"));
    let cli = |args: &[&str]| run_cli(tmp.path(), args);
    let (ok, text) = cli(&["status", "--json"]);
    assert!(ok, "{text}");
    let json: Value = serde_json::from_str(&text).unwrap();
    assert_eq!(printer(&json, "beta")["state"], "idle");
    let (ok, text) = cli(&["status"]);
    assert!(
        ok && text.contains("alpha") && text.contains("beta"),
        "{text}"
    );
    let (ok, text) = cli(&["clear", "zeta"]);
    assert!(!ok && text.contains("\"zeta\""), "{text}");
    let (ok, text) = cli(&["pause", "alpha"]);
    assert!(!ok && text.contains("not printing"), "{text}");
    let (ok, text) = cli(&["retry", "0099-none"]);
    assert!(!ok && text.contains("0099-none"), "{text}");

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
    let a = put("hot", "huge.stl", &vec![b'x'; 1024 * 1024 + 1]);
    assert_eq!(a.status, 413);
    assert!(a.error().contains("upload_max_mb"), "{}", a.text());
    assert!(!tmp.path().join("escape.stl").exists());
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
    // Its wall comparison is measured after it is ready: printing does not wait for it.
    // It runs at nice 19 and gets only what CPU is left over: on a machine kept busy it
    // can take many times its usual minute; the limit only keeps a hang from lasting.
    let s = farm.wait_for(
        Duration::from_secs(900),
        "the upload printed and measured",
        |s| {
            job_by_file(s, "spot.obj")
                .is_some_and(|j| j["state"] == "done" && j["comparison"]["state"] == "done")
        },
    );
    let done = job_by_file(&s, "spot.obj").unwrap().clone();
    let id = done["id"].as_str().unwrap();
    assert_eq!(done["height_mm"], 25.0);
    assert_eq!(done["strength"], "auto");
    assert_eq!(
        done["pictures"],
        json!([
            "before.png",
            "after.png",
            "displacement.png",
            "walls.png",
            "preview.png"
        ])
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
    // The enhancement in printed mm against the machine's nozzle, and in the G-code.
    let enhancement = &detail["job"]["slice_report"]["enhancement"];
    assert_eq!(enhancement["printed"]["nozzle_mm"], 0.4, "{enhancement}");
    assert!(enhancement["printed"]["max_mm"].as_f64().unwrap() > 0.0);
    let walls = &detail["job"]["slice_report"]["walls"];
    assert!(walls["layers"].as_u64().unwrap() > 50, "{walls}");
    assert!(walls["mean_mm"].as_f64().unwrap() > 0.0, "{walls}");
    assert!(
        detail["job"]["print_report"]["lines_acked"]
            .as_u64()
            .unwrap()
            > 1000
    );
    for name in [
        "before.png",
        "after.png",
        "displacement.png",
        "walls.png",
        "preview.png",
    ] {
        let a = farm.get(&format!("/api/v1/jobs/{id}/pictures/{name}"), Some(KEY));
        assert_eq!(a.status, 200, "{name}");
        assert_eq!(a.header("content-type").as_deref(), Some("image/png"));
        assert_eq!(&a.body[..8], b"\x89PNG\r\n\x1a\n", "{name} is a PNG");
    }
    for other in ["job.json", "..%2Fjob.json", "spot.obj.gcode"] {
        let a = farm.get(&format!("/api/v1/jobs/{id}/pictures/{other}"), Some(KEY));
        assert_eq!(a.status, 404, "{other} is not served");
        assert!(a.error().contains("after.png"), "{}", a.text());
    }
    let gcode = std::fs::read_to_string(
        tmp.path()
            .join(format!("spool/jobs/{id}/spot.obj.marlin-175.gcode")),
    )
    .unwrap();
    for size in ["300x300", "32x32"] {
        assert!(
            gcode.contains(&format!("; thumbnail begin {size} ")),
            "the G-code has a {size} thumbnail"
        );
    }

    // Actions are the control socket's: the bed gate.
    let s = farm.status();
    let printed_on = job_by_file(&s, "spot.obj").unwrap()["printer"]
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
    assert!(m
        .header("content-type")
        .unwrap()
        .contains("text/plain; version=0.0.4"));
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

/// Issue 20: a rotated API key is read again on reload (SIGHUP): from then on the old key
/// is refused and the new one accepted. The key file, readable by every user as written
/// here, is accepted with a warning in the log.
#[test]
fn a_rotated_key_takes_effect_on_reload() {
    let tmp = tempfile::tempdir().unwrap();
    let farm = Farm::start(tmp.path(), 0.0, "");
    assert_eq!(farm.get("/api/v1/status", Some(KEY)).status, 200);
    let log = std::fs::read_to_string(&farm.log).unwrap();
    let mode = std::os::unix::fs::PermissionsExt::mode(
        &std::fs::metadata(tmp.path().join("key"))
            .unwrap()
            .permissions(),
    );
    if mode & 0o004 != 0 {
        assert!(
            log.contains("[http] key `api_key_file`") && log.contains("readable by every user"),
            "{log}"
        );
    }
    const NEW: &str = "rotated-key-9876543210fedcba";
    std::fs::write(tmp.path().join("key"), format!("{NEW}\n")).unwrap();
    let pid = nix::unistd::Pid::from_raw(farm._daemon.child.id() as i32);
    nix::sys::signal::kill(pid, nix::sys::signal::Signal::SIGHUP).unwrap();
    let started = Instant::now();
    while !std::fs::read_to_string(&farm.log)
        .unwrap()
        .contains("SIGHUP: config reloaded")
    {
        assert!(
            started.elapsed() < Duration::from_secs(30),
            "no reload: {}",
            std::fs::read_to_string(&farm.log).unwrap()
        );
        std::thread::sleep(Duration::from_millis(50));
    }
    let old = farm.get("/api/v1/status", Some(KEY));
    assert_eq!(
        old.status,
        403,
        "the old key after the reload: {}",
        old.text()
    );
    assert_eq!(farm.get("/api/v1/status", Some(NEW)).status, 200);
    assert_eq!(
        farm.post("/api/v1/printers/alpha/clear", Some(KEY)).status,
        403
    );
}

/// An upload made exactly as PrusaSlicer's "Send to printer" (OctoPrint host type) makes
/// it: first `GET /api/version` (its connection test wants "OctoPrint" in `text`), then
/// libcurl's multipart POST with the fields `print`, `path` and `file`, `Expect:
/// 100-continue`, and the key in `X-Api-Key`. The model becomes a job and prints; G-code
/// (what PrusaSlicer sends after slicing itself) lands in the hot folder and becomes a job.
#[test]
fn an_upload_as_prusaslicer_sends_it_becomes_a_job_and_prints() {
    let tmp = tempfile::tempdir().unwrap();
    let farm = Farm::start(tmp.path(), 0.0, "");
    let v = farm.get("/api/version", Some(KEY));
    assert_eq!(v.status, 200);
    let v = v.json();
    assert!(v["text"].as_str().unwrap().starts_with("OctoPrint"), "{v}");
    assert!(v["api"].is_string() && v["server"].is_string(), "{v}");

    let send = |file_name: &str, content: &[u8], print: &str| {
        octoprint_upload(&farm.addr, file_name, content, print)
    };

    // G-code (what PrusaSlicer sends after slicing itself) goes into the hot folder too,
    // as pre-sliced G-code, and prints as it is.
    let sliced = tmp.path().join("sliced.gcode");
    let out = Command::new(BIN)
        .arg("slice")
        .arg(common::model("spot.obj"))
        .arg("-o")
        .arg(&sliced)
        .args(["--height", "10", "--no-enhance", "--up", "y"])
        .args(["--machine", "marlin-175"])
        .output()
        .unwrap();
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let a = send("part.gcode", &std::fs::read(&sliced).unwrap(), "true");
    assert_eq!(a.status, 201, "{}", a.text());
    let answer = a.json();
    assert_eq!(answer["files"]["local"]["path"], "hot/part.gcode");
    assert_eq!(answer["effectivePrint"], true);
    let status = farm.wait_for(
        Duration::from_secs(180),
        "the uploaded G-code printed",
        |s| job_by_file(s, "part.gcode").is_some_and(|j| j["state"] == "done"),
    );
    // Its printer takes the next job once someone has cleared its bed.
    let printer = job_by_file(&status, "part.gcode").unwrap()["printer"]
        .as_str()
        .unwrap()
        .to_string();
    let cleared = farm.post(&format!("/api/v1/printers/{printer}/clear"), Some(KEY));
    assert_eq!(cleared.status, 200, "{}", cleared.text());

    let a = send("part.stl", &spot_stl(), "true");
    assert_eq!(a.status, 201, "{}", a.text());
    let answer = a.json();
    assert_eq!(answer["done"], true);
    assert_eq!(answer["files"]["local"]["name"], "part.stl");
    farm.wait_for(
        Duration::from_secs(180),
        "the slicer's upload printed",
        |s| job_by_file(s, "part.stl").is_some_and(|j| j["state"] == "done"),
    );
    assert_eq!(hot_files(tmp.path()), Vec::<String>::new());
    let _ = &farm.root;
}

/// "Upload" without "and print" (`print=false`), as PrusaSlicer sends it: the job is
/// prepared and then held. A job uploaded to print after it is printed while the held one
/// stays ready, though a printer is idle all along; cancel and retry keep it held; once
/// released (`crispen release`) it prints, exactly once.
#[test]
fn an_upload_without_print_is_held_until_released_and_prints_once() {
    let tmp = tempfile::tempdir().unwrap();
    let farm = Farm::start(tmp.path(), 0.0, "");
    farm.wait_for(Duration::from_secs(30), "two idle printers", |s| {
        ["alpha", "beta"]
            .iter()
            .all(|p| printer(s, p)["state"] == "idle")
    });
    let a = octoprint_upload(&farm.addr, "held.gcode", WARM_GCODE.as_bytes(), "false");
    assert_eq!(a.status, 201, "{}", a.text());
    let answer = a.json();
    assert_eq!(answer["effectivePrint"], false, "{answer}");
    assert!(
        answer["message"].as_str().unwrap().contains("held"),
        "{answer}"
    );
    let s = farm.wait_for(Duration::from_secs(60), "the held job ready", |s| {
        job_by_file(s, "held.gcode").is_some_and(|j| j["state"] == "ready" && j["held"] == true)
    });
    let id = job_by_file(&s, "held.gcode").unwrap()["id"]
        .as_str()
        .unwrap()
        .to_string();
    assert_eq!(
        hot_files(tmp.path()),
        Vec::<String>::new(),
        "the sidecar went with it"
    );

    let a = octoprint_upload(&farm.addr, "free.gcode", WARM_GCODE.as_bytes(), "true");
    assert_eq!(a.status, 201, "{}", a.text());
    assert_eq!(a.json()["effectivePrint"], true);
    let s = farm.wait_for(Duration::from_secs(60), "the other upload printed", |s| {
        job_by_file(s, "free.gcode").is_some_and(|j| j["state"] == "done")
    });
    let held = job_by_file(&s, "held.gcode").unwrap();
    assert_eq!(held["state"], "ready", "{s:#}");
    assert_eq!(held["printer"], Value::Null);
    let used = job_by_file(&s, "free.gcode").unwrap()["printer"]
        .as_str()
        .unwrap()
        .to_string();
    let other = if used == "alpha" { "beta" } else { "alpha" };
    assert_eq!(printer(&s, other)["state"], "idle", "{s:#}");
    let free = job_by_file(&s, "free.gcode").unwrap()["id"]
        .as_str()
        .unwrap()
        .to_string();

    let cli = |args: &[&str]| run_cli(tmp.path(), args);
    let (ok, table) = cli(&["status"]);
    let row = table.lines().find(|l| l.starts_with(&id)).unwrap_or("");
    assert!(ok && row.contains("ready (held)"), "{table}");

    // Cancelled and retried, it is still held; a cancelled job is not released.
    let a = farm.post(&format!("/api/v1/jobs/{id}/cancel"), Some(KEY));
    assert_eq!(a.status, 200, "{}", a.text());
    let a = farm.post(&format!("/api/v1/jobs/{id}/release"), Some(KEY));
    assert_eq!(a.status, 409, "{}", a.text());
    assert!(a.error().contains("retry it first"), "{}", a.text());
    let a = farm.post(&format!("/api/v1/jobs/{id}/retry"), Some(KEY));
    assert_eq!(a.status, 200, "{}", a.text());
    assert!(
        a.json()["message"].as_str().unwrap().contains("release"),
        "{}",
        a.text()
    );
    let s = farm.status();
    let held = job_by_file(&s, "held.gcode").unwrap();
    assert!(held["state"] == "ready" && held["held"] == true, "{held:#}");

    let a = farm.post(&format!("/api/v1/jobs/{free}/release"), Some(KEY));
    assert_eq!(a.status, 409, "{}", a.text());
    assert!(a.error().contains("not held"), "{}", a.text());
    let (ok, text) = cli(&["release", &id]);
    assert!(ok && text.contains("released"), "{text}");
    let s = farm.wait_for(Duration::from_secs(60), "the released job printed", |s| {
        job_by_file(s, "held.gcode").is_some_and(|j| j["state"] == "done")
    });
    assert_eq!(job_by_file(&s, "held.gcode").unwrap()["printer"], other);
    let detail = farm.get(&format!("/api/v1/jobs/{id}"), Some(KEY)).json();
    let printings = detail["job"]["history"]
        .as_array()
        .unwrap()
        .iter()
        .filter(|h| h[0] == "printing")
        .count();
    assert_eq!(printings, 1, "printed once: {detail:#}");
    assert_eq!(detail["job"]["copies_done"], 1);
    assert_eq!(detail["held"], false);
    let (ok, text) = cli(&["release", &id]);
    assert!(!ok && text.contains("not held"), "{text}");
}

/// Idle printers' temperatures, read between jobs, in the API, the status and the
/// metrics; and they follow the printer: after a print (200 °C nozzle, 60 °C bed) the
/// simulator cools down, and so do the daemon's figures, to the room's 21 °C.
#[test]
fn idle_temperatures_follow_the_printer() {
    let tmp = tempfile::tempdir().unwrap();
    let farm = Farm::start(tmp.path(), 0.1, "");
    let reading = |s: &Value, p: &str, what: &str| printer(s, p)["temperatures"][what].as_f64();
    let ambient = |s: &Value, p: &str| {
        ["hotend_c", "bed_c"]
            .iter()
            .all(|w| reading(s, p, w).is_some_and(|c| (c - 21.0).abs() < 0.5))
            && ["hotend_target_c", "bed_target_c"]
                .iter()
                .all(|w| reading(s, p, w) == Some(0.0))
    };
    farm.wait_for(Duration::from_secs(60), "idle printers at 21 °C", |s| {
        ["alpha", "beta"]
            .iter()
            .all(|p| printer(s, p)["state"] == "idle" && ambient(s, p))
    });
    let a = farm.get("/api/v1/printers/alpha", Some(KEY));
    assert_eq!(a.status, 200);
    assert_eq!(a.json()["temperatures"]["bed_target_c"], 0.0);
    let metrics = farm.get("/metrics", Some(KEY)).text();
    let gauge = |metrics: &str, name: &str, p: &str| -> Option<f64> {
        let prefix = format!("{name}{{printer=\"{p}\"}} ");
        metrics
            .lines()
            .find_map(|l| l.strip_prefix(&prefix))
            .and_then(|v| v.parse().ok())
    };
    for p in ["alpha", "beta"] {
        let c = gauge(&metrics, "crispen_printer_hotend_celsius", p);
        assert!(c.is_some_and(|c| (c - 21.0).abs() < 0.5), "{metrics}");
        assert_eq!(
            gauge(&metrics, "crispen_printer_bed_target_celsius", p),
            Some(0.0),
            "{metrics}"
        );
    }

    let a = request(
        &farm.addr,
        "PUT",
        "/api/v1/folders/hot/files/warm.gcode",
        &key_header(Some(KEY)),
        WARM_GCODE.as_bytes(),
    );
    assert_eq!(a.status, 201, "{}", a.text());
    let s = farm.wait_for(Duration::from_secs(120), "the warm-up printed", |s| {
        job_by_file(s, "warm.gcode").is_some_and(|j| j["state"] == "done")
    });
    let p = job_by_file(&s, "warm.gcode").unwrap()["printer"]
        .as_str()
        .unwrap()
        .to_string();
    // Cooling from 200 °C at the simulator's 1 °C per simulated second, ten times
    // faster than real: well over 100 °C for the first 9 s after the print.
    let s = farm.wait_for(Duration::from_secs(30), "the heaters off", |s| {
        reading(s, &p, "hotend_target_c") == Some(0.0)
    });
    let hot = reading(&s, &p, "hotend_c").unwrap();
    assert!(hot > 100.0, "just after the print: {s:#}");
    assert_eq!(printer(&s, &p)["state"], "bed_not_cleared");
    farm.wait_for(Duration::from_secs(60), "cooling down", |s| {
        reading(s, &p, "hotend_c").is_some_and(|c| c < hot - 50.0)
    });
    farm.wait_for(Duration::from_secs(120), "back at 21 °C", |s| {
        ambient(s, &p)
    });
    let metrics = farm.get("/metrics", Some(KEY)).text();
    let c = gauge(&metrics, "crispen_printer_hotend_celsius", &p);
    assert!(c.is_some_and(|c| c < 22.0), "{metrics}");
}

/// chromedriver and one headless Chromium session, spoken to in W3C WebDriver JSON over
/// the same minimal HTTP client.
pub(crate) struct Browser {
    _driver: Killed,
    addr: String,
    session: String,
}

const ELEMENT: &str = "element-6066-11e4-a52e-4f735466cecf";

impl Browser {
    pub(crate) fn start(profile: &Path) -> Browser {
        let port = std::net::TcpListener::bind("127.0.0.1:0")
            .unwrap()
            .local_addr()
            .unwrap()
            .port();
        let driver = Command::new("chromedriver")
            .arg(format!("--port={port}"))
            .stdout(Stdio::null())
            .stderr(Stdio::null())
            .spawn()
            .expect("chromedriver (Debian packages chromium and chromium-driver; scripts/setup installs them)");
        let driver = Killed(driver);
        let addr = format!("127.0.0.1:{port}");
        let started = Instant::now();
        while TcpStream::connect(&addr).is_err() {
            assert!(
                started.elapsed() < Duration::from_secs(30),
                "chromedriver did not start"
            );
            std::thread::sleep(Duration::from_millis(100));
        }
        let mut args = vec![
            "--headless".to_string(),
            "--no-sandbox".into(),
            "--disable-gpu".into(),
            "--disable-background-networking".into(),
            "--disable-component-update".into(),
            "--no-first-run".into(),
            "--disable-dev-shm-usage".into(),
            "--window-size=1200,1000".into(),
        ];
        args.push(format!("--user-data-dir={}", profile.display()));
        let mut options = json!({ "args": args });
        if Path::new("/usr/bin/chromium").exists() {
            options["binary"] = json!("/usr/bin/chromium");
        }
        let caps = json!({"capabilities": {"alwaysMatch": {
            "browserName": "chrome", "goog:chromeOptions": options }}});
        let answer = webdriver(&addr, "POST", "/session", &caps);
        let session = answer["sessionId"]
            .as_str()
            .unwrap_or_else(|| panic!("no session: {answer}"))
            .to_string();
        Browser {
            _driver: driver,
            addr,
            session,
        }
    }

    pub(crate) fn call(&self, method: &str, path: &str, body: &Value) -> Value {
        webdriver(
            &self.addr,
            method,
            &format!("/session/{}{path}", self.session),
            body,
        )
    }

    pub(crate) fn go(&self, url: &str) {
        self.call("POST", "/url", &json!({ "url": url }));
    }

    pub(crate) fn exec(&self, script: &str, args: Value) -> Value {
        self.call(
            "POST",
            "/execute/sync",
            &json!({ "script": script, "args": args }),
        )
    }

    pub(crate) fn find(&self, css: &str) -> String {
        let v = self.call(
            "POST",
            "/element",
            &json!({"using": "css selector", "value": css}),
        );
        v[ELEMENT]
            .as_str()
            .unwrap_or_else(|| panic!("no element {css}: {v}"))
            .to_string()
    }

    /// Clicks the element `css` selects. The dashboard redraws a tile at each change of
    /// its printer: an element redrawn between its finding and its click ("stale element
    /// reference", which a loaded machine makes likely) is found again and clicked, the
    /// redraw being the event that says so.
    pub(crate) fn click(&self, css: &str) {
        loop {
            let id = self.find(css);
            let path = format!("/session/{}/element/{id}/click", self.session);
            let a = request(
                &self.addr,
                "POST",
                &path,
                &[("Content-Type", "application/json")],
                b"{}",
            );
            let v = a.json();
            if a.status == 200 {
                return;
            }
            assert_eq!(
                v["value"]["error"], "stale element reference",
                "WebDriver POST {path}: {v}"
            );
        }
    }

    pub(crate) fn type_into(&self, css: &str, text: &str) {
        let id = self.find(css);
        self.call(
            "POST",
            &format!("/element/{id}/value"),
            &json!({ "text": text }),
        );
    }

    pub(crate) fn screenshot(&self, path: &Path) {
        use base64::Engine;
        let v = self.call("GET", "/screenshot", &Value::Null);
        let png = base64::engine::general_purpose::STANDARD
            .decode(v.as_str().unwrap())
            .unwrap();
        std::fs::write(path, png).unwrap();
    }

    /// Waits until `script` (a function body) returns true in the page; anything else it
    /// returns is shown if it never does.
    pub(crate) fn wait_until(&self, limit: Duration, what: &str, script: &str) {
        let started = Instant::now();
        let mut seen: Vec<Value> = Vec::new();
        loop {
            let last = self.exec(script, json!([]));
            if last == json!(true) {
                return;
            }
            if !seen.contains(&last) {
                seen.push(last);
            }
            if started.elapsed() > limit {
                let body = self.exec("return document.body.innerText", json!([]));
                panic!("timed out waiting in the page for {what} (it returned: {seen:?}); the page shows:\n{body}");
            }
            std::thread::sleep(Duration::from_millis(200));
        }
    }
}

impl Drop for Browser {
    fn drop(&mut self) {
        let _ = std::panic::catch_unwind(|| {
            webdriver(
                &self.addr,
                "DELETE",
                &format!("/session/{}", self.session),
                &Value::Null,
            )
        });
    }
}

/// One WebDriver command; returns its `value`, panicking on a WebDriver error.
fn webdriver(addr: &str, method: &str, path: &str, body: &Value) -> Value {
    let body = if body.is_null() {
        Vec::new()
    } else {
        serde_json::to_vec(body).unwrap()
    };
    let headers = [("Content-Type", "application/json")];
    let a = request(addr, method, path, &headers, &body);
    let v = a.json();
    assert_eq!(a.status, 200, "WebDriver {method} {path}: {v}");
    v["value"].clone()
}

/// The dashboard in a real headless Chromium: two simulated printers printing, each
/// tile with its state, progress, temperatures and the part's picture; the bed-clear
/// button asks for the key (read-only without it), then clears the bed with it; a model
/// dropped on the hot folder's name becomes a job; a held upload's Print button releases
/// it; the job page shows the three pictures; and the page fits a phone's width.
#[test]
fn dashboard_in_a_real_browser() {
    let tmp = tempfile::tempdir().unwrap();
    let farm = Farm::start(tmp.path(), 0.02, "read_only_without_key = true");
    for name in ["left.obj", "right.obj"] {
        let a = request(
            &farm.addr,
            "PUT",
            &format!("/api/v1/folders/hot/files/{name}"),
            &key_header(Some(KEY)),
            &spot_obj(),
        );
        assert_eq!(a.status, 201, "{}", a.text());
    }
    // Read-only without the key: the status is open, changes are not.
    assert_eq!(farm.get("/api/v1/status", None).status, 200);
    assert_eq!(farm.post("/api/v1/printers/alpha/clear", None).status, 401);

    let browser = Browser::start(&tmp.path().join("chromium-profile"));
    browser.go(&format!("http://{}/", farm.addr));
    browser.wait_until(
        Duration::from_secs(240),
        "both printers printing, with progress, temperatures and the part's picture",
        "const seen = ['alpha', 'beta'].map(p => {
           const t = document.querySelector('[data-printer=\"' + p + '\"]');
           if (!t) return p + ': no tile';
           const img = t.querySelector('img.part');
           const bar = t.querySelector('progress.bar');
           return [t.querySelector('.state').textContent, !!bar && Math.abs(bar.value - parseFloat(t.querySelector('.pct').textContent)) < 0.05,
             /°C/.test((t.querySelector('.temps') || {}).textContent), /left/.test(t.textContent),
             !!img && img.naturalWidth > 0,
             // Under way, for a screenshot that shows it.
             parseFloat((t.querySelector('.pct') || {}).textContent) > 5].join(' ');
         });
         return seen.every(s => s === 'printing true true true true true') || seen.join('; ');",
    );
    let shots = Path::new(env!("CARGO_TARGET_TMPDIR"));
    browser.screenshot(&shots.join("dashboard.png"));

    // The print ends and alpha waits for its bed to be cleared.
    browser.wait_until(
        Duration::from_secs(240),
        "alpha's bed-clear button",
        "return !!document.querySelector('button[data-action=\"clear\"][data-printer=\"alpha\"]')",
    );
    // Without the key the click is refused and the page asks for the key.
    browser.click("button[data-action=\"clear\"][data-printer=\"alpha\"]");
    browser.wait_until(
        Duration::from_secs(20),
        "the key form",
        "return !document.querySelector('#keyform').hidden",
    );
    assert_eq!(printer(&farm.status(), "alpha")["bed_cleared"], false);
    browser.type_into("#key", KEY);
    browser.click("#keyform button");
    browser.click("button[data-action=\"clear\"][data-printer=\"alpha\"]");
    farm.wait_for(
        Duration::from_secs(20),
        "alpha's bed cleared by the click",
        |s| printer(s, "alpha")["bed_cleared"] == true,
    );
    browser.wait_until(
        Duration::from_secs(20),
        "the clear button gone",
        "return !document.querySelector('button[data-action=\"clear\"][data-printer=\"alpha\"]')",
    );

    // A model dropped on the hot folder's name is uploaded and becomes a job. WebDriver
    // cannot drag a file from the desktop, so the page gets the events a real drop fires.
    let dropped = browser.exec(
        "const [text] = arguments;
         const zone = document.querySelector('[data-folder=\"hot\"]');
         const data = new DataTransfer();
         data.items.add(new File([text], 'dropped.obj', { type: 'application/octet-stream' }));
         for (const type of ['dragenter', 'dragover', 'drop'])
           zone.dispatchEvent(new DragEvent(type, { bubbles: true, cancelable: true, dataTransfer: data }));
         return data.files.length;",
        json!([String::from_utf8(spot_obj()).unwrap()]),
    );
    assert_eq!(dropped, json!(1));
    farm.wait_for(Duration::from_secs(60), "the dropped model as a job", |s| {
        job_by_file(s, "dropped.obj").is_some()
    });
    browser.wait_until(
        Duration::from_secs(20),
        "the dropped job in the queue",
        "return Array.from(document.querySelectorAll('#queue tr[data-job]')).some(r => r.textContent.includes('dropped.obj'))",
    );

    // A held upload (without "print") shows as held with a Print button, which releases it.
    let a = octoprint_upload(&farm.addr, "held.gcode", WARM_GCODE.as_bytes(), "false");
    assert_eq!(a.status, 201, "{}", a.text());
    browser.wait_until(
        Duration::from_secs(60),
        "the held job's Print button",
        "const row = Array.from(document.querySelectorAll('#queue tr[data-job]'))
           .find(r => r.textContent.includes('held.gcode'));
         return !!row && /held/.test(row.textContent) && !!row.querySelector('button[data-action=\"release\"]');",
    );
    // Clicked from the page's own script: the queue's rows are redrawn whenever another
    // job moves on, which a WebDriver element reference would not survive.
    let clicked = browser.exec(
        "const b = document.querySelector('button[data-action=\"release\"]');
         if (b) b.click();
         return !!b;",
        json!([]),
    );
    assert_eq!(clicked, json!(true));
    farm.wait_for(
        Duration::from_secs(20),
        "the held job released by the click",
        |s| job_by_file(s, "held.gcode").is_some_and(|j| j["held"] == false),
    );

    // The job page: the report, the three pictures and the preview of the print. Its
    // wall comparison runs at the lowest CPU priority, after every preparation: the page
    // is looked at once the daemon says it is made, however long a busy machine took.
    let s = farm.wait_for(
        Duration::from_secs(600),
        "left.obj's wall comparison made",
        |s| job_by_file(s, "left.obj").is_some_and(|j| j["comparison"]["state"] == "done"),
    );
    let left = job_by_file(&s, "left.obj").unwrap()["id"]
        .as_str()
        .unwrap()
        .to_string();
    browser.go(&format!("http://{}/#job/{left}", farm.addr));
    browser.wait_until(
        Duration::from_secs(20),
        "the job page with its pictures",
        "const imgs = document.querySelectorAll('#jobpage .pictures img');
         return imgs.length === 3 && Array.from(imgs).every(i => i.naturalWidth > 0)
           && document.querySelector('#jobpage h2').textContent.includes('left.obj')
           && document.querySelector('#jobpage').textContent.includes('What moved')
           && /mean \\/ p95 \\/ max\\s*[0-9.]+ \\/ [0-9.]+ \\/ [0-9.]+ mm/.test(document.querySelector('#printed').textContent)
           && /more than 0.1 mm\\s*[0-9.]+ %/.test(document.querySelector('#walls').textContent)
           && document.querySelector('#jobpage figure.walls img').naturalWidth > 0
           && document.querySelector('#jobpage #preview img')?.naturalWidth > 0
           && (document.querySelector('#preview figcaption')?.textContent || '').includes('actual size');",
    );
    browser.screenshot(&shots.join("dashboard-job.png"));

    // A phone's width: nothing wider than the screen.
    browser.call(
        "POST",
        "/window/rect",
        &json!({"width": 390, "height": 844}),
    );
    browser.go(&format!("http://{}/", farm.addr));
    browser.wait_until(
        Duration::from_secs(20),
        "the dashboard at a phone's width",
        "const wide = Array.from(document.querySelectorAll('body *'))
           .filter(e => e.getBoundingClientRect().right > window.innerWidth + 1)
           .map(e => e.tagName + '.' + e.className + ' ' + Math.round(e.getBoundingClientRect().right));
         return (document.querySelectorAll('.tile[data-printer]').length === 2
           && document.documentElement.scrollWidth <= window.innerWidth && wide.length === 0)
           || [window.innerWidth, document.documentElement.scrollWidth, ...wide.slice(0, 5)].join(' ');",
    );
    browser.screenshot(&shots.join("dashboard-phone.png"));
}

/// A job whose sidecar asks `strength = "observed"`: the observer looks at the folder's
/// five candidates against the model printed at the farm's reference size
/// (`[enhancement] reference_height_mm`), and the job page says which it chose and why,
/// with every candidate's score and the views it compared.
#[test]
fn the_job_page_shows_what_the_observer_chose_in_a_real_browser() {
    let tmp = tempfile::tempdir().unwrap();
    let farm = Farm::start_with(
        tmp.path(),
        0.0,
        "\n[enhancement]\nreference_height_mm = 50\n",
        "",
    );
    let hot = tmp.path().join("hot");
    std::fs::write(hot.join("spot.obj.toml"), "strength = \"observed\"\n").unwrap();
    std::fs::write(hot.join("spot.obj"), spot_obj()).unwrap();
    let s = farm.wait_for(Duration::from_secs(900), "spot.obj prepared", |s| {
        job_by_file(s, "spot.obj").is_some_and(|j| {
            ["ready", "printing", "done", "waiting"].contains(&j["state"].as_str().unwrap_or(""))
                || j["state"] == "failed"
        })
    });
    let job = job_by_file(&s, "spot.obj").unwrap();
    assert_ne!(job["state"], "failed", "{job}");
    let id = job["id"].as_str().unwrap().to_string();
    let answer = farm.get(&format!("/api/v1/jobs/{id}"), Some(KEY)).json();
    let observed = &answer["job"]["slice_report"]["enhancement"]["observed"];
    assert_eq!(observed["choice"], "most_alike", "{observed}");
    assert_eq!(observed["reference_height_mm"], 50.0);
    assert_eq!(
        observed["candidates"].as_array().unwrap().len(),
        5,
        "{observed}"
    );
    assert!(
        answer["pictures"]
            .as_array()
            .unwrap()
            .contains(&json!("observed.png")),
        "{answer}"
    );

    let browser = Browser::start(&tmp.path().join("chromium-profile"));
    browser.go(&format!("http://{}/", farm.addr));
    browser.exec(
        "localStorage.setItem('crispen-key', arguments[0]);",
        json!([KEY]),
    );
    browser.go(&format!("http://{}/#job/{id}", farm.addr));
    browser.call("POST", "/refresh", &json!({}));
    browser.wait_until(
        Duration::from_secs(30),
        "the observer's section",
        "const text = (q) => (document.querySelector(q) || {}).textContent || '';
         const rows = document.querySelectorAll('table#observed tbody tr');
         const checks = {
           heading: text('#jobpage').includes('Strength chosen by the observer'),
           why: /looks most like the model printed 50 mm tall, seen from 40 cm in 4 views/.test(text('#observed-why')),
           rows: rows.length === 5,
           chosen: document.querySelectorAll('table#observed tr.chosen').length === 1,
           scores: Array.from(rows).every(r => /0\\.[0-9]+/.test(r.textContent)),
           views: document.querySelector('#observed-views img')?.naturalWidth > 0,
         };
         const failed = Object.keys(checks).filter(k => !checks[k]);
         return failed.length === 0 || failed.join(' ');",
    );
    let shots = Path::new(env!("CARGO_TARGET_TMPDIR"));
    browser.screenshot(&shots.join("dashboard-observed.png"));
}

/// A plate's parts on the job page, in a real browser: three copies of Spot on one bed
/// (`per_plate` in its sidecar, held so that it waits), drawn as their outlines on the bed
/// and listed, each with its button; the second's button cancels it (the store has it,
/// the page draws it cancelled), and the others stay.
#[test]
fn the_job_page_shows_a_plates_parts_and_cancels_one_in_a_real_browser() {
    let tmp = tempfile::tempdir().unwrap();
    let farm = Farm::start(tmp.path(), 0.0, "");
    let hot = tmp.path().join("hot");
    std::fs::write(
        hot.join("spot.obj.toml"),
        "per_plate = 3\nhold = true\nstrength = \"off\"\n",
    )
    .unwrap();
    std::fs::write(hot.join("spot.obj"), spot_obj()).unwrap();
    let s = farm.wait_for(Duration::from_secs(600), "the plate prepared", |s| {
        job_by_file(s, "spot.obj").is_some_and(|j| j["state"] == "ready" || j["state"] == "failed")
    });
    let job = job_by_file(&s, "spot.obj").unwrap();
    assert_eq!(job["state"], "ready", "{job}");
    assert_eq!(job["parts"]["total"], 3, "{job}");
    let id = job["id"].as_str().unwrap().to_string();
    let answer = farm.get(&format!("/api/v1/jobs/{id}"), Some(KEY)).json();
    let second = answer["job"]["slice_report"]["parts"][1]["name"]
        .as_str()
        .unwrap()
        .to_string();

    let browser = Browser::start(&tmp.path().join("chromium-profile"));
    browser.go(&format!("http://{}/", farm.addr));
    browser.exec(
        "localStorage.setItem('crispen-key', arguments[0]);",
        json!([KEY]),
    );
    browser.go(&format!("http://{}/#job/{id}", farm.addr));
    browser.call("POST", "/refresh", &json!({}));
    browser.wait_until(
        Duration::from_secs(30),
        "the plate's parts",
        "const checks = {
           heading: /Parts\\s*3 of 3 on the plate/.test(document.querySelector('#jobpage').textContent),
           outlines: document.querySelectorAll('svg.plate polygon').length === 3,
           rows: document.querySelectorAll('#parts li').length === 3,
           buttons: document.querySelectorAll('#parts button[data-action=\"cancelpart\"]').length === 3,
         };
         const failed = Object.keys(checks).filter(k => !checks[k]);
         return failed.length === 0 || failed.join(' ');",
    );
    browser.exec(
        "window.confirm = () => true;
         document.querySelectorAll('#parts button[data-action=\"cancelpart\"]')[1].click();",
        json!([]),
    );
    browser.wait_until(
        Duration::from_secs(30),
        "the second part drawn cancelled",
        "const rows = document.querySelectorAll('#parts li');
         const checks = {
           heading: /Parts\\s*2 of 3 on the plate/.test(document.querySelector('#jobpage').textContent),
           second: rows.length === 3 && rows[1].classList.contains('cancelled') && /before its print/.test(rows[1].textContent),
           others: rows.length === 3 && !rows[0].classList.contains('cancelled') && !rows[2].classList.contains('cancelled'),
           outline: document.querySelectorAll('svg.plate g.cancelled').length === 1,
           buttons: document.querySelectorAll('#parts button[data-action=\"cancelpart\"]').length === 2,
         };
         const failed = Object.keys(checks).filter(k => !checks[k]);
         return failed.length === 0 || failed.join(' ');",
    );
    let s = farm.status();
    let job = job_by_file(&s, "spot.obj").unwrap();
    assert_eq!(job["parts"]["cancelled"], json!([second]), "{job}");
    assert_eq!(job["state"], "ready", "{job}");
    let shots = Path::new(env!("CARGO_TARGET_TMPDIR"));
    browser.screenshot(&shots.join("dashboard-plate.png"));
}

/// An enhanced job's page reads as a report for an operator: once the job is prepared,
/// compared and printed, it says in one line how much the enhancement moved (in % and mm),
/// the printed size, machine and print time, how the print went, and the history in
/// words; none of the report's raw keys (`mu`, the solver's residual, the radius in model
/// units, the timings as JSON) nor the server's paths; the raw report is one click away.
#[test]
fn the_job_page_reads_as_a_report_in_a_real_browser() {
    let tmp = tempfile::tempdir().unwrap();
    let farm = Farm::start(tmp.path(), 0.0, "");
    let a = request(
        &farm.addr,
        "PUT",
        "/api/v1/folders/hot/files/spot.obj",
        &key_header(Some(KEY)),
        &spot_obj(),
    );
    assert_eq!(a.status, 201, "{}", a.text());
    let s = farm.wait_for(
        Duration::from_secs(600),
        "spot.obj prepared, compared and printed",
        |s| {
            job_by_file(s, "spot.obj")
                .is_some_and(|j| j["state"] == "done" && j["comparison"]["state"] == "done")
        },
    );
    let job = job_by_file(&s, "spot.obj").unwrap();
    let id = job["id"].as_str().unwrap().to_string();
    // The line is the report's, as every client reads it.
    let moved = job["moved"].as_str().unwrap().to_string();
    assert!(moved.starts_with("The outer wall moves by"), "{moved}");

    let browser = Browser::start(&tmp.path().join("chromium-profile"));
    browser.go(&format!("http://{}/", farm.addr));
    browser.exec(
        "localStorage.setItem('crispen-key', arguments[0]);",
        json!([KEY]),
    );
    // Only the hash changes: the page is loaded again to read the key.
    browser.go(&format!("http://{}/#job/{id}", farm.addr));
    browser.call("POST", "/refresh", &json!({}));
    browser.wait_until(
        Duration::from_secs(30),
        "the job page as a report",
        "const m = document.querySelector('#moved');
         const p = document.querySelector('#print');
         const pics = document.querySelector('#jobpage .pictures');
         const text = (e) => e ? e.textContent : '';
         const checks = {
           moved: !!m && /[0-9.]+ %/.test(m.textContent) && /[0-9.]+ mm/.test(m.textContent),
           movedFirst: !!m && !!pics && !!(m.compareDocumentPosition(pics) & Node.DOCUMENT_POSITION_FOLLOWING),
           size: /Printed size\\s*[0-9.]+ × [0-9.]+ × 25 mm/.test(text(p)),
           machine: /Machine\\s*(ultimaker2|marlin-175), on printer (alpha|beta)/.test(text(p)),
           time: /Print time\\s*([0-9]+ h )?[0-9]+ (min|s)/.test(text(p)),
           filament: /Filament\\s*[0-9.]+ g \\/ [0-9.]+ m/.test(text(p)),
           strength: /Enhancement\\s*(strong|medium|light) \\(λ2 [0-9.]+, the paper's method\\)/.test(text(p)),
           walls: /more than 0.1 mm\\s*[0-9.]+ %/.test(text(document.querySelector('table#walls'))),
           printing: /took .*: finished/.test(text(document.querySelector('#printing'))),
           history: /ready to print/.test(text(document.querySelector('.history'))),
           raw: !!document.querySelector('a#raw[href^=\"blob:\"]'),
         };
         const failed = Object.keys(checks).filter(k => !checks[k]);
         return failed.length === 0 || failed.join(' ');",
    );
    let page = browser
        .exec(
            "return document.querySelector('#jobpage').innerText",
            json!([]),
        )
        .as_str()
        .unwrap()
        .to_string();
    println!("the job page:\n{page}");
    assert!(page.contains(&moved), "{page}");
    let root = tmp.path().to_str().unwrap();
    for dump in [
        "max solve residual",
        "radius",
        "\"timings\"",
        "load_s",
        root,
        "/spool/",
    ] {
        assert!(!page.contains(dump), "{dump:?} on the page:\n{page}");
    }
    assert!(
        !page.split_whitespace().any(|w| w == "mu"),
        "mu on the page:\n{page}"
    );
    let shots = Path::new(env!("CARGO_TARGET_TMPDIR"));
    browser.screenshot(&shots.join("dashboard-report.png"));
    // At a phone's width the page fits, its tables of figures too.
    browser.call(
        "POST",
        "/window/rect",
        &json!({"width": 390, "height": 844}),
    );
    browser.wait_until(
        Duration::from_secs(20),
        "the job page at a phone's width",
        "const wide = Array.from(document.querySelectorAll('#jobpage *'))
           .filter(e => e.getBoundingClientRect().right > window.innerWidth + 1)
           .map(e => e.tagName + '.' + e.className + ' ' + Math.round(e.getBoundingClientRect().right));
         return (document.documentElement.scrollWidth <= window.innerWidth && wide.length === 0
           && getComputedStyle(document.querySelector('table#walls thead')).display !== 'none')
           || [window.innerWidth, document.documentElement.scrollWidth, ...wide.slice(0, 5)].join(' ');",
    );
    browser.screenshot(&shots.join("dashboard-report-phone.png"));

    // The raw report opens in a window of its own, as the page fetched it (with its key).
    browser.click("a#raw");
    let handles = browser.call("GET", "/window/handles", &Value::Null);
    let page_window = browser.call("GET", "/window", &Value::Null);
    let raw_window = handles
        .as_array()
        .unwrap()
        .iter()
        .find(|h| **h != page_window)
        .unwrap_or_else(|| panic!("no window for the raw report: {handles}"))
        .clone();
    browser.call("POST", "/window", &json!({ "handle": raw_window }));
    let read = "const t = (document.querySelector('pre') || document.body).textContent;
         try { return JSON.parse(t).job.id === ID || t.slice(0, 200); } catch (_) { return t.slice(0, 200); }"
        .replace("ID", &format!("{id:?}"));
    browser.wait_until(Duration::from_secs(20), "the raw report", &read);
    let raw = browser.exec(
        "return JSON.parse((document.querySelector('pre') || document.body).textContent);",
        json!([]),
    );
    // The report keeps the figures the line is made from, not the line.
    assert!(raw["job"]["slice_report"]["walls"]["p99_mm"].is_number());
    assert!(raw["job"]["slice_report"].get("moved").is_none());
    assert!(raw["job"]["slice_report"]["enhancement"]["report"].is_object());
}

/// The quick start's `crispen run` without a config serves the dashboard on
/// 127.0.0.1:8080 and logs its address; with that port taken (here by the test itself) it
/// listens on a port the system picks and logs that one. The farm is open to look at
/// without a key; acting takes the key the daemon made in ./crispen-demo/api-key
/// (mode 0600), which stays the same at the next start.
#[test]
fn the_built_in_default_serves_the_dashboard_with_a_key_file() {
    use std::os::unix::fs::PermissionsExt;
    let tmp = tempfile::tempdir().unwrap();
    // Holds 8080 if it is free; if it is not, someone else does. Either way it is taken.
    let _taken = std::net::TcpListener::bind("127.0.0.1:8080");
    let start = |log: &Path| {
        let daemon = Command::new(BIN)
            .current_dir(tmp.path())
            .arg("run")
            .env("RUST_LOG", "info")
            .stdout(Stdio::null())
            .stderr(std::fs::File::create(log).unwrap())
            .spawn()
            .unwrap();
        let daemon = Killed(daemon);
        let started = Instant::now();
        let addr = loop {
            let text = std::fs::read_to_string(log).unwrap_or_default();
            if let Some(line) = text.lines().find(|l| l.contains("dashboard: http://")) {
                let at = line.find("http://").unwrap() + "http://".len();
                break line[at..].trim_end().trim_end_matches('/').to_string();
            }
            assert!(
                started.elapsed() < Duration::from_secs(30),
                "no dashboard address logged:\n{text}"
            );
            std::thread::sleep(Duration::from_millis(50));
        };
        let text = std::fs::read_to_string(log).unwrap();
        assert!(text.contains("the port is taken"), "{text}");
        assert!(text.contains("crispen-demo/api-key"), "{text}");
        (daemon, addr)
    };
    let (daemon, addr) = start(&tmp.path().join("first.log"));
    assert!(
        addr.starts_with("127.0.0.1:") && addr != "127.0.0.1:8080",
        "{addr}"
    );
    let key_file = tmp.path().join("crispen-demo/api-key");
    let mode = std::fs::metadata(&key_file).unwrap().permissions().mode();
    assert_eq!(mode & 0o777, 0o600, "the key file is the owner's only");
    let key = std::fs::read_to_string(&key_file)
        .unwrap()
        .trim()
        .to_string();
    assert!(key.len() >= 16, "{key}");

    let page = request(&addr, "GET", "/", &[], b"");
    assert_eq!(page.status, 200);
    assert!(page.text().contains("keybutton"), "the page offers the key");
    let a = request(&addr, "GET", "/api/v1/status", &[], b"");
    assert_eq!(a.status, 200, "read-only without the key: {}", a.text());
    assert_eq!(printer(&a.json(), "demo")["name"], "demo");
    let a = request(&addr, "POST", "/api/v1/printers/demo/clear", &[], b"");
    assert_eq!(a.status, 401, "{}", a.text());
    let a = request(
        &addr,
        "POST",
        "/api/v1/printers/demo/clear",
        &key_header(Some(&key)),
        b"",
    );
    assert_eq!(a.status, 200, "{}", a.text());
    drop(daemon);

    // The next start keeps the key.
    let (_daemon, _) = start(&tmp.path().join("second.log"));
    let again = std::fs::read_to_string(&key_file).unwrap();
    assert_eq!(again.trim(), key);
}

/// The answer on `stream`, or `None` when none came within `limit` (a failure bound only:
/// the tests that use it expect an answer).
fn answer_within(stream: TcpStream, bytes: &[u8], limit: Duration) -> Option<Answer> {
    stream.set_read_timeout(Some(limit)).unwrap();
    let mut peek = [0u8; 1];
    let mut s = stream;
    let _ = s.write_all(bytes);
    match s.peek(&mut peek) {
        Ok(n) if n > 0 => Some(exchange(s, b"")),
        _ => None,
    }
}

/// Issue 20, severe: every OctoPrint upload's name is checked whatever its fields say
/// (`print=true` skipped the check and wrote anywhere the daemon could); a name that is
/// not one plain file name of a model, a sidecar or G-code gets a clear 400 naming it
/// (shortened), never 500, and never a 409 that tells whether a file exists elsewhere;
/// answers carry no server paths. `print` and `select` are true as OctoPrint has them
/// (`true`, `yes`, `y`, `1`, any case).
#[test]
fn every_upload_name_is_checked_whatever_its_fields() {
    let tmp = tempfile::tempdir().unwrap();
    let farm = Farm::start(tmp.path(), 0.0, "");
    let root = tmp.path().canonicalize().unwrap();
    let send = |fields: &[(&str, &str)], name: &str| {
        octoprint_form(&farm.addr, fields, name, WARM_GCODE.as_bytes())
    };
    // A held job, whose directory an attacker would plant a file in.
    let a = send(&[("path", "hot")], "held.gcode");
    assert_eq!(a.status, 201, "{}", a.text());
    let s = farm.wait_for(Duration::from_secs(60), "the held job", |s| {
        job_by_file(s, "held.gcode").is_some()
    });
    let id = job_by_file(&s, "held.gcode").unwrap()["id"]
        .as_str()
        .unwrap()
        .to_string();
    let job_dir = root.join("spool/jobs").join(&id);
    assert!(job_dir.is_dir());
    let up = "./".to_string() + &"../".repeat(root.components().count() + 2);
    let planted = format!(
        "{up}{}/planted.txt",
        job_dir.display().to_string().trim_start_matches('/')
    );
    let long = format!("{}.gcode", "x".repeat(244));
    let bidi = "part\u{202e}edocg.gcode";
    let escape = "red\u{1b}[31m.gcode";
    let existing = format!(
        "{up}{}/crispen.toml",
        root.display().to_string().trim_start_matches('/')
    );
    let cases: Vec<(&str, &str)> = vec![
        (&planted, "without folders"),
        ("./../../escape.sh", "without folders"),
        (&existing, "without folders"),
        (".hidden.gcode", "hidden"),
        ("x.gcode.part", "hidden or temporary"),
        ("notes.txt", ".stl"),
        (&long, "200 bytes"),
        (bidi, "bidi"),
        (escape, "control characters"),
        ("", "1 to 200 bytes"),
    ];
    for fields in [
        &[("print", "true"), ("path", "hot")][..],
        &[("print", "false"), ("path", "hot")][..],
        &[("select", "true"), ("print", "1")][..],
        &[][..],
    ] {
        for (name, why) in &cases {
            let a = send(fields, name);
            assert_eq!(a.status, 400, "{name:?} with {fields:?}: {}", a.text());
            let e = a.error();
            assert!(e.contains(why), "{name:?}: {e}");
            assert!(e.len() < 400, "the name is shortened: {e}");
            // A name may hold a path of the client's own; the server adds none.
            let own = name.contains(root.to_string_lossy().trim_start_matches('/'));
            assert!(
                (own || !e.contains(&*root.to_string_lossy()))
                    && !e.contains('\u{1b}')
                    && !e.contains('\u{202e}'),
                "no server path, no raw control characters: {e}"
            );
        }
    }
    assert!(!job_dir.join("planted.txt").exists(), "planted in a job");
    assert!(!root.parent().unwrap().join("escape.sh").exists());
    let left: Vec<String> = hot_files(tmp.path())
        .into_iter()
        .filter(|n| n != "held.gcode" && n != "held.gcode.toml")
        .collect();
    assert_eq!(left, Vec::<String>::new(), "nothing left behind");

    // A name that is taken: 409, naming the file but no server path.
    std::fs::create_dir(tmp.path().join("hot/taken.gcode")).unwrap();
    let a = send(&[("print", "true"), ("path", "hot")], "taken.gcode");
    assert_eq!(a.status, 409, "{}", a.text());
    assert!(a.error().contains("taken.gcode"), "{}", a.text());
    assert!(
        !a.error().contains(&*root.to_string_lossy()),
        "{}",
        a.text()
    );
    std::fs::remove_dir(tmp.path().join("hot/taken.gcode")).unwrap();

    // OctoPrint's truths.
    for (n, (fields, print, select)) in [
        (&[("print", "1")][..], true, true),
        (&[("print", "yes")][..], true, true),
        (&[("print", "Y")][..], true, true),
        (&[("print", "TRUE")][..], true, true),
        (&[("print", "0")][..], false, false),
        (&[("print", "no")][..], false, false),
        (&[("select", "1")][..], false, true),
        (&[("select", "yes"), ("print", "false")][..], false, true),
    ]
    .into_iter()
    .enumerate()
    {
        let a = send(fields, &format!("truth{n}.gcode"));
        assert_eq!(a.status, 201, "{fields:?}: {}", a.text());
        let answer = a.json();
        assert_eq!(answer["effectivePrint"], print, "{fields:?}: {answer}");
        assert_eq!(answer["effectiveSelect"], select, "{fields:?}: {answer}");
    }
    // The held ones are held, the others not.
    let s = farm.wait_for(Duration::from_secs(120), "the uploads prepared", |s| {
        (0..8).all(|n| {
            job_by_file(s, &format!("truth{n}.gcode"))
                .is_some_and(|j| j["state"] != "queued" && j["state"] != "preparing")
        })
    });
    for n in 0..8 {
        let held = job_by_file(&s, &format!("truth{n}.gcode")).unwrap()["held"] == true;
        assert_eq!(held, n >= 4, "truth{n}.gcode: {s:#}");
    }
}

/// The daemon's high-water mark of resident memory, in MiB.
fn vm_hwm_mib(pid: u32) -> u64 {
    let status = std::fs::read_to_string(format!("/proc/{pid}/status")).unwrap();
    let line = status.lines().find(|l| l.starts_with("VmHWM:")).unwrap();
    line.split_whitespace()
        .nth(1)
        .unwrap()
        .parse::<u64>()
        .unwrap()
        / 1024
}

/// Issue 20: a form field is bounded while it is read. A 400 MB `path` field (inside a
/// 1 GiB upload limit) is refused after its first KiB, and the daemon's memory does not
/// grow with it (it read the field whole: 255 MB to 1.08 GB before the 400).
#[test]
fn a_huge_form_field_is_refused_without_reading_it() {
    let tmp = tempfile::tempdir().unwrap();
    let farm = Farm::start(tmp.path(), 0.0, "upload_max_mb = 1024");
    farm.status();
    let pid = farm._daemon.child.id();
    let before = vm_hwm_mib(pid);
    let boundary = "------------------------a1b2c3d4e5f60718";
    let field: u64 = 400 * 1024 * 1024;
    let head = format!("--{boundary}\r\nContent-Disposition: form-data; name=\"path\"\r\n\r\n");
    let tail = format!(
        "\r\n--{boundary}\r\nContent-Disposition: form-data; name=\"file\"; filename=\"a.gcode\"\r\n\r\nG28\r\n--{boundary}--\r\n"
    );
    let length = head.len() as u64 + field + tail.len() as u64;
    let mut stream = TcpStream::connect(&farm.addr).unwrap();
    write!(
        stream,
        "POST /api/files/local HTTP/1.1\r\nHost: x\r\nX-Api-Key: {KEY}\r\nConnection: close\r\n\
         Content-Type: multipart/form-data; boundary={boundary}\r\nContent-Length: {length}\r\n\r\n{head}"
    )
    .unwrap();
    let mut writer = stream.try_clone().unwrap();
    writer
        .set_write_timeout(Some(Duration::from_secs(60)))
        .unwrap();
    // Sent in pieces of 1 MiB while the answer is awaited; the server may stop reading.
    let sender = std::thread::spawn(move || {
        let piece = vec![b'h'; 1024 * 1024];
        let mut sent = 0u64;
        while sent < field {
            if writer.write_all(&piece).is_err() {
                return sent;
            }
            sent += piece.len() as u64;
        }
        let _ = writer.write_all(tail.as_bytes());
        sent
    });
    stream
        .set_read_timeout(Some(Duration::from_secs(120)))
        .unwrap();
    let a = exchange(stream, b"");
    let sent = sender.join().unwrap();
    let after = vm_hwm_mib(pid);
    eprintln!(
        "400 MB path field: answered {} after {} MiB sent; daemon VmHWM {before} MiB before, {after} MiB after",
        a.status,
        sent / (1024 * 1024)
    );
    assert_eq!(a.status, 400, "{}", a.text());
    assert!(a.error().contains("`path`"), "{}", a.text());
    assert!(
        after < before + 64,
        "the daemon's memory grew from {before} to {after} MiB"
    );
    assert!(sent < field, "the whole field was read before the answer");
    // Still serving.
    farm.status();
}

/// Issue 20: 64 event streams without the key and a slowloris of 100 connections sending
/// a byte a second held every connection slot, so a keyed `clear` and a status probe went
/// unanswered. Streams are now capped per client and in all, and connections that have
/// not sent a request head make room; the keyed request and the probe are answered.
#[test]
fn event_streams_and_slow_clients_leave_room_for_requests() {
    let tmp = tempfile::tempdir().unwrap();
    let farm = Farm::start(tmp.path(), 0.0, "read_only_without_key = true");
    farm.wait_for(Duration::from_secs(30), "two idle printers", |s| {
        ["alpha", "beta"]
            .iter()
            .all(|p| printer(s, p)["state"] == "idle")
    });
    let mut streams = Vec::new();
    for _ in 0..64 {
        let mut stream = TcpStream::connect(&farm.addr).unwrap();
        stream
            .write_all(b"GET /api/v1/events HTTP/1.1\r\nHost: x\r\n\r\n")
            .unwrap();
        streams.push(stream);
    }
    let stop = std::sync::Arc::new(std::sync::atomic::AtomicBool::new(false));
    let (begun, began) = std::sync::mpsc::channel();
    let slowloris = {
        let (addr, stop) = (farm.addr.clone(), stop.clone());
        let mut sockets: Vec<TcpStream> = (0..100)
            .map(|_| TcpStream::connect(&addr).unwrap())
            .collect();
        std::thread::spawn(move || {
            let head = b"GET /api/v1/status HTTP/1.1\r\nHost: x\r\nX-Padding: ";
            let mut at = 0;
            while !stop.load(std::sync::atomic::Ordering::Relaxed) {
                for s in &mut sockets {
                    let _ = s.write_all(&[*head.get(at).unwrap_or(&b'a')]);
                }
                if at == 0 {
                    let _ = begun.send(());
                }
                at += 1;
                std::thread::sleep(Duration::from_secs(1));
            }
        })
    };
    // Every slow connection has begun its request (and the kernel queues connections in
    // order, so the keyed one below comes after all of them).
    began
        .recv_timeout(Duration::from_secs(30))
        .expect("the slow clients began");
    let keyed = answer_within(
        TcpStream::connect(&farm.addr).unwrap(),
        format!(
            "POST /api/v1/printers/alpha/clear HTTP/1.1\r\nHost: x\r\nX-Api-Key: {KEY}\r\n\
             Connection: close\r\nContent-Length: 0\r\n\r\n"
        )
        .as_bytes(),
        Duration::from_secs(60),
    );
    let probe = answer_within(
        TcpStream::connect(&farm.addr).unwrap(),
        b"GET /api/v1/status HTTP/1.1\r\nHost: x\r\nConnection: close\r\n\r\n",
        Duration::from_secs(60),
    );
    stop.store(true, std::sync::atomic::Ordering::Relaxed);
    let keyed = keyed.expect("the keyed clear was answered");
    assert_eq!(keyed.status, 200, "{}", keyed.text());
    let probe = probe.expect("the status probe was answered");
    assert_eq!(probe.status, 200, "{}", probe.text());
    // Of the streams from this one address, 8 were taken and the others refused.
    let mut statuses = Vec::new();
    for stream in streams {
        stream
            .set_read_timeout(Some(Duration::from_secs(30)))
            .unwrap();
        let mut line = String::new();
        let _ = BufReader::new(stream).read_line(&mut line);
        statuses.push(line.split_whitespace().nth(1).unwrap_or("none").to_string());
    }
    let taken = statuses.iter().filter(|s| *s == "200").count();
    let refused = statuses.iter().filter(|s| *s == "503").count();
    assert_eq!((taken, refused), (8, 56), "{statuses:?}");
    slowloris.join().unwrap();
}

/// Issue 20: a file named with terminal escapes or bidi controls is not taken: it is set
/// aside in the hot folder's `set-aside/` with a log line that shows its name escaped, and
/// neither `crispen status` nor the log carries the raw characters. An uploaded sidecar
/// whose model never comes is set aside too (it stayed in the hot folder for ever).
#[test]
fn bad_names_and_lone_sidecars_are_set_aside() {
    let tmp = tempfile::tempdir().unwrap();
    let farm = Farm::start_with(tmp.path(), 0.0, "rescan_s = 1", "");
    farm.status();
    let escape = "red\u{1b}[31m\u{1b}]0;owned\u{7}.gcode";
    let bidi = "invoice\u{202e}edocg.gcode";
    for name in [escape, bidi] {
        std::fs::write(tmp.path().join("hot").join(name), WARM_GCODE).unwrap();
    }
    let a = request(
        &farm.addr,
        "PUT",
        "/api/v1/folders/hot/files/lonely.stl.toml",
        &key_header(Some(KEY)),
        b"copies = 2\n",
    );
    assert_eq!(a.status, 201, "{}", a.text());
    let aside = tmp.path().join("hot/set-aside");
    let started = Instant::now();
    let log = || std::fs::read_to_string(&farm.log).unwrap_or_default();
    while !["lonely.stl.toml", escape, bidi]
        .iter()
        .all(|n| aside.join(n).exists())
    {
        assert!(
            started.elapsed() < Duration::from_secs(180),
            "not set aside: {:?}\n{}",
            hot_files(tmp.path()),
            log()
        );
        std::thread::sleep(Duration::from_millis(200));
    }
    assert_eq!(hot_files(tmp.path()), ["set-aside"]);
    let (ok, table) = run_cli(tmp.path(), &["status"]);
    assert!(ok, "{table}");
    let s = farm.status();
    assert_eq!(s["jobs"], json!([]), "no job of them: {s:#}");
    let log = log();
    for text in [&table, &log] {
        assert!(
            !text.contains('\u{1b}') && !text.contains('\u{202e}') && !text.contains('\u{7}'),
            "raw control characters: {text}"
        );
    }
    assert!(log.contains("red\\u{1b}[31m"), "{log}");
    assert!(
        log.contains("bidi controls") && log.contains("set aside"),
        "{log}"
    );
    assert!(
        log.contains("lonely.stl.toml") && log.contains("did not arrive"),
        "{log}"
    );
}

/// Issue 22: a held upload can be released before it is prepared (it once answered "not
/// held": the sidecar that holds it is read into the job only by the preparation). A long
/// settle time keeps the job queued while it is released; it then prints once ready.
#[test]
fn a_held_upload_is_released_before_it_is_prepared() {
    let tmp = tempfile::tempdir().unwrap();
    let farm = Farm::start_with(tmp.path(), 0.0, "settle_s = 8", "");
    let a = octoprint_upload(&farm.addr, "early.gcode", WARM_GCODE.as_bytes(), "false");
    assert_eq!(a.status, 201, "{}", a.text());
    let s = farm.wait_for(Duration::from_secs(60), "the held job picked up", |s| {
        job_by_file(s, "early.gcode").is_some()
    });
    let id = job_by_file(&s, "early.gcode").unwrap()["id"]
        .as_str()
        .unwrap()
        .to_string();
    let (ok, text) = run_cli(tmp.path(), &["release", &id]);
    assert!(ok && text.contains("released"), "{text}");
    let s = farm.status();
    let job = job_by_file(&s, "early.gcode").unwrap();
    assert!(
        job["state"] == "queued" || job["state"] == "preparing",
        "released before it was prepared: {job:#}"
    );
    let s = farm.wait_for(Duration::from_secs(60), "the released job printed", |s| {
        job_by_file(s, "early.gcode").is_some_and(|j| j["state"] == "done")
    });
    assert_eq!(job_by_file(&s, "early.gcode").unwrap()["held"], false);
}

/// `café.gcode` composed (U+00E9).
const CAFE_COMPOSED: &str = "caf\u{e9}.gcode";
/// `café.gcode` decomposed (`e` and U+0301), as macOS spells names.
const CAFE_DECOMPOSED: &str = "cafe\u{301}.gcode";

/// `PUT /api/v1/folders/hot/files/<name>` with a small G-code job.
fn put_gcode(farm: &Farm, name: &str) -> Answer {
    request(
        &farm.addr,
        "PUT",
        &format!(
            "/api/v1/folders/hot/files/{}",
            crispen::percent::percent_encode(name)
        ),
        &key_header(Some(KEY)),
        WARM_GCODE.as_bytes(),
    )
}

/// Issue 31: the two spellings of `café.gcode` are one name through the API and the
/// OctoPrint upload. The first upload (decomposed, held) is kept under the composed
/// spelling and answered with it; while it waits in the hot folder, the name in either
/// spelling and by either way is refused as the same name twice is (409); it becomes one
/// job named in the composed spelling, which Cura's select-and-print finds by the other.
#[test]
fn two_spellings_of_an_uploaded_name_are_one_name() {
    let tmp = tempfile::tempdir().unwrap();
    // Long enough a settle time that the upload waits in the folder for the others.
    let farm = Farm::start_with(tmp.path(), 0.0, "settle_s = 8", "");
    let a = octoprint_upload(&farm.addr, CAFE_DECOMPOSED, WARM_GCODE.as_bytes(), "false");
    assert_eq!(a.status, 201, "{}", a.text());
    let local = &a.json()["files"]["local"];
    assert_eq!(local["name"], CAFE_COMPOSED, "{local}");
    assert_eq!(local["path"], format!("hot/{CAFE_COMPOSED}"), "{local}");
    for name in [CAFE_COMPOSED, CAFE_DECOMPOSED] {
        let a = put_gcode(&farm, name);
        assert_eq!(a.status, 409, "PUT {name:?}: {}", a.text());
        assert!(a.error().contains(CAFE_COMPOSED), "{}", a.text());
        let a = octoprint_upload(&farm.addr, name, WARM_GCODE.as_bytes(), "true");
        assert_eq!(a.status, 409, "OctoPrint {name:?}: {}", a.text());
    }
    assert_eq!(
        hot_files(tmp.path()),
        [CAFE_COMPOSED.to_string(), format!("{CAFE_COMPOSED}.toml")],
        "one file (and its hold), in the composed spelling"
    );
    let s = farm.wait_for(Duration::from_secs(60), "the held job ready", |s| {
        job_by_file(s, CAFE_COMPOSED).is_some_and(|j| j["state"] == "ready" && j["held"] == true)
    });
    assert_eq!(s["jobs"].as_array().unwrap().len(), 1, "one job: {s:#}");
    // Cura's select-and-print, by the decomposed name: it finds and releases the job.
    let a = request(
        &farm.addr,
        "POST",
        &format!(
            "/api/files/local/{}",
            crispen::percent::percent_encode(CAFE_DECOMPOSED)
        ),
        &[("X-Api-Key", KEY), ("Content-Type", "application/json")],
        br#"{"command": "select", "print": true}"#,
    );
    assert_eq!(a.status, 204, "{}", a.text());
    farm.wait_for(Duration::from_secs(60), "the released job printed", |s| {
        job_by_file(s, CAFE_COMPOSED).is_some_and(|j| j["state"] == "done")
    });
    // The name once free again, the other spelling makes a second job of the same name,
    // as a second upload of one name does.
    let a = put_gcode(&farm, CAFE_DECOMPOSED);
    assert_eq!(a.status, 201, "{}", a.text());
    assert_eq!(a.json()["file"], CAFE_COMPOSED);
    let s = farm.wait_for(Duration::from_secs(60), "the second job", |s| {
        s["jobs"].as_array().unwrap().len() == 2
    });
    for job in s["jobs"].as_array().unwrap() {
        assert_eq!(job["file"], CAFE_COMPOSED, "{s:#}");
    }
}

/// Issue 31: files dropped into a hot folder under either spelling of a name. The file
/// keeps its name in the folder, but its job is named in the one spelling, its sidecar
/// spelt otherwise goes with it (here holding it), and while it waits an upload of the
/// name in the other spelling is refused as one of the same name is.
#[test]
fn two_spellings_of_a_dropped_name_are_one_name() {
    let tmp = tempfile::tempdir().unwrap();
    let farm = Farm::start_with(tmp.path(), 0.0, "settle_s = 8", "");
    farm.status();
    let hot = tmp.path().join("hot");
    std::fs::write(hot.join(format!("{CAFE_COMPOSED}.toml")), "hold = true\n").unwrap();
    std::fs::write(hot.join(CAFE_DECOMPOSED), WARM_GCODE).unwrap();
    for name in [CAFE_COMPOSED, CAFE_DECOMPOSED] {
        let a = put_gcode(&farm, name);
        assert_eq!(a.status, 409, "PUT {name:?}: {}", a.text());
        let a = octoprint_upload(&farm.addr, name, WARM_GCODE.as_bytes(), "false");
        assert_eq!(a.status, 409, "OctoPrint {name:?}: {}", a.text());
    }
    assert_eq!(
        hot_files(tmp.path()),
        [CAFE_DECOMPOSED.to_string(), format!("{CAFE_COMPOSED}.toml")],
        "the dropped files as they were, nothing uploaded"
    );
    let s = farm.wait_for(Duration::from_secs(60), "the held job ready", |s| {
        job_by_file(s, CAFE_COMPOSED).is_some_and(|j| j["state"] == "ready")
    });
    assert_eq!(s["jobs"].as_array().unwrap().len(), 1, "one job: {s:#}");
    let job = job_by_file(&s, CAFE_COMPOSED).unwrap();
    assert_eq!(job["held"], true, "its sidecar went with it: {job:#}");
    assert_eq!(
        hot_files(tmp.path()),
        Vec::<String>::new(),
        "both taken, nothing set aside"
    );
}

/// A pause the file asks for, on the dashboard in a real headless Chromium: the printer's
/// tile shows it waiting for the operator with the file's message and a Resume button,
/// whose click (with the key) finishes the job.
#[test]
fn dashboard_shows_a_file_pause_and_its_resume_button_resumes() {
    let tmp = tempfile::tempdir().unwrap();
    let farm = Farm::start(tmp.path(), 0.0, "read_only_without_key = true");
    let gcode = "M104 S200\nM109 S200\nG28\nG90\nM82\nG92 E0\nG1 Z0.3 F600\n\
                 G1 X20 Y20 F3000\nG1 X60 Y20 E4 F1200\nM117 Insert magnets\nM0\n\
                 G1 X60 Y60 E8\nM104 S0\n";
    let a = request(
        &farm.addr,
        "PUT",
        "/api/v1/folders/hot/files/magnets.gcode",
        &key_header(Some(KEY)),
        gcode.as_bytes(),
    );
    assert_eq!(a.status, 201, "{}", a.text());
    let browser = Browser::start(&tmp.path().join("chromium-profile"));
    browser.go(&format!("http://{}/", farm.addr));
    browser.wait_until(
        Duration::from_secs(120),
        "a tile waiting for the operator, with the message and a Resume button",
        "const t = Array.from(document.querySelectorAll('.tile[data-printer]'))
           .find(t => t.querySelector('.state').textContent === 'waiting for operator');
         return (!!t && t.querySelector('.detail').textContent.includes('Insert magnets')
           && !!t.querySelector('button[data-action=\"resume\"]'))
           || Array.from(document.querySelectorAll('.tile .state')).map(s => s.textContent).join(', ');",
    );
    let click_resume = || {
        browser.exec(
            "const b = document.querySelector('button[data-action=\"resume\"]');
             if (b) b.click();
             return !!b;",
            json!([]),
        )
    };
    assert_eq!(click_resume(), json!(true));
    // Acting takes the key: the page asks for it, then the click goes through.
    browser.wait_until(
        Duration::from_secs(20),
        "the key form, or the print going on",
        "return !document.querySelector('#keyform').hidden
           || !Array.from(document.querySelectorAll('.tile .state')).some(s => s.textContent === 'waiting for operator');",
    );
    if browser.exec(
        "return !document.querySelector('#keyform').hidden;",
        json!([]),
    ) == json!(true)
    {
        browser.type_into("#key", KEY);
        browser.click("#keyform button");
        assert_eq!(click_resume(), json!(true));
    }
    farm.wait_for(Duration::from_secs(120), "the paused job done", |s| {
        job_by_file(s, "magnets.gcode").is_some_and(|j| j["state"] == "done")
    });
}

/// The statistics page in a real browser: finished jobs in the spool (alpha printed two
/// today, one of them across the last hour) are drawn as alpha's bar of today in the
/// SVG chart and counted in the table, with the filament the weighed one used and its
/// cost, also per material; the dashboard links to the page.
#[test]
fn statistics_page_in_a_real_browser() {
    use crispen::daemon::job::{Job, JobState};
    let tmp = tempfile::tempdir().unwrap();
    let root = tmp.path();
    let now = crispen::daemon::job::now_s();
    // Printing from 30 min to 20 min ago and from 15 min to 5 min ago (today, unless the
    // test runs in the first half hour of a UTC day: then partly yesterday).
    for (seq, (start, end)) in [(1u64, (1800.0, 1200.0)), (2, (900.0, 300.0))] {
        let file = format!("part-{seq}.stl");
        let id = Job::make_id(seq, &file);
        let dir = root.join("spool/jobs").join(&id);
        std::fs::create_dir_all(&dir).unwrap();
        std::fs::write(dir.join(&file), b"solid x\nendsolid x\n").unwrap();
        let mut job = Job::queued(id, seq, file, root.join("hot"));
        job.history = vec![
            (JobState::Queued, now - start - 60.0),
            (JobState::Printing, now - start),
            (JobState::Done, now - end),
        ];
        job.state = JobState::Done;
        job.printer = Some("alpha".into());
        job.copies_done = 1;
        if seq == 1 {
            job.uses = vec![crispen::daemon::job::JobUse {
                key: format!("{}#0", job.id),
                spool: Some("s1".into()),
                printer: "alpha".into(),
                material: "PETG".into(),
                colour: "black".into(),
                grams: 12.5,
                mm: 4000.0,
                cost: Some(0.3125),
                at_s: now - end,
                print_s: 0.0,
                failed: false,
            }];
        }
        std::fs::write(dir.join("job.json"), serde_json::to_vec(&job).unwrap()).unwrap();
    }
    let farm = Farm::start(root, 0.0, "read_only_without_key = true");
    let browser = Browser::start(&root.join("chromium-profile"));
    browser.go(&format!("http://{}/", farm.addr));
    browser.wait_until(
        Duration::from_secs(30),
        "the dashboard's link to the statistics",
        "const a = document.querySelector('a#statslink'); return !!a && a.getAttribute('href') === '/stats';",
    );
    browser.click("a#statslink");
    browser.wait_until(
        Duration::from_secs(30),
        "alpha's bar and row on the statistics page",
        "if (document.querySelector('#stats').dataset.loaded !== 'true') return 'not loaded: ' + document.querySelector('#notice').textContent;
         const bars = [...document.querySelectorAll('#chart svg rect[data-printer=\"alpha\"]')];
         const used = bars.reduce((s, r) => s + parseFloat(r.getAttribute('height')), 0);
         const row = document.querySelector('#printers tr[data-name=\"alpha\"]');
         const beta = document.querySelector('#printers tr[data-name=\"beta\"]');
         const cells = row ? [...row.querySelectorAll('td')].map(c => c.textContent) : [];
         const petg = document.querySelector('#materials tr[data-name=\"PETG\"]');
         const material = petg ? [...petg.querySelectorAll('td')].map(c => c.textContent) : [];
         return (bars.length === 7 && used > 0 && cells[1] === '2' && cells[4] === '0.3' && !!beta
                 && cells[7] === '12.5' && cells[8] === '0.31' && material[1] === '1' && material[7] === '0.31')
           || JSON.stringify({bars: bars.length, used, cells, material});",
    );
    let shots = Path::new(env!("CARGO_TARGET_TMPDIR"));
    browser.screenshot(&shots.join("stats.png"));
}
