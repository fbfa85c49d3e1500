//! The OctoPrint emulation against the real binary, driven as OctoPrint clients drive it:
//! Cura's OctoPrint connection replayed call by call in the order of its source (over
//! real TCP, every byte the test's own), the real Python clients `octorest` and
//! `octoprint client` from the venv that `scripts/setup` makes (`CRISPEN_PY_VENV`,
//! default /usr/local/share/crispen/venv), and the zeroconf announcement browsed by the
//! Python `zeroconf` package in a network namespace of the test's own.

use crate::common;
use common::daemon::{Daemon, BIN};
use common::http::{request, Answer};
use common::job_by_file;
use serde_json::{json, Value};
use std::path::{Path, PathBuf};
use std::process::Command;
use std::time::{Duration, Instant};

const KEY: &str = "octo-test-key-0123456789";

/// Heat, two lines, heaters off: pre-sliced G-code as a slicer sends it.
const GCODE: &str = "; sent by a slicer\nM140 S60\nM104 S200\nM190 S60\nM109 S200\nG28\nG92 E0\n\
    G1 Z0.3 F600\nG1 X20 Y20 F3000\nG1 X60 Y20 E4 F1200\nG1 X60 Y60 E8\nM104 S0\nM140 S0\nM84\n";

fn venv() -> PathBuf {
    PathBuf::from(
        std::env::var("CRISPEN_PY_VENV")
            .unwrap_or_else(|_| "/usr/local/share/crispen/venv".to_string()),
    )
}

fn python() -> PathBuf {
    let python = venv().join("bin/python");
    assert!(
        python.exists(),
        "{} is missing: run scripts/setup (it makes the venv with the OctoPrint clients)",
        python.display()
    );
    python
}

/// A daemon with two hot folders, `hot` (printer alpha, the root instance's default
/// folder) and `other` (printer beta), and `[http]` on a loopback port.
struct Farm {
    daemon: Daemon,
    addr: String,
    root: PathBuf,
    log: PathBuf,
}

fn config_text(http_extra: &str) -> String {
    let printer = |name: &str| {
        format!(
            "[[printer]]\nname = \"{name}\"\nfirmware = \"marlin2\"\n\
             [printer.simulate]\ntime_scale = 0.0\n"
        )
    };
    format!(
        "[spool]\ndir = \"spool\"\n[control]\nsocket = \"c.sock\"\n[farm]\nsettle_s = 0.3\n\
         [http]\nlisten = \"127.0.0.1:0\"\napi_key_file = \"key\"\nupload_max_mb = 4\n{http_extra}\n\
         {}{}[[folder]]\npath = \"hot\"\nheight_mm = 25\nprinters = [\"alpha\"]\n\
         [[folder]]\npath = \"other\"\nheight_mm = 25\nprinters = [\"beta\"]\n",
        printer("alpha"),
        printer("beta")
    )
}

fn prepare(root: &Path, http_extra: &str) -> PathBuf {
    std::fs::create_dir_all(root.join("hot")).unwrap();
    std::fs::create_dir_all(root.join("other")).unwrap();
    std::fs::write(root.join("key"), format!("{KEY}\n")).unwrap();
    let config = root.join("crispen.toml");
    std::fs::write(&config, config_text(http_extra)).unwrap();
    config
}

impl Farm {
    fn start(root: &Path) -> Farm {
        prepare(root, "default_folder = \"hot\"\nannounce = false\n");
        Farm::started(root)
    }

    /// The daemon on the config already in `root`.
    fn started(root: &Path) -> Farm {
        let config = root.join("crispen.toml");
        let log = root.join("daemon.log");
        let daemon = Daemon::start(&config, &log);
        let addr = common::daemon::http_address(&log);
        Farm {
            daemon,
            addr,
            root: root.to_path_buf(),
            log,
        }
    }

    fn call(&self, method: &str, path: &str, headers: &[(&str, &str)], body: &[u8]) -> Answer {
        request(&self.addr, method, path, headers, body)
    }

    fn status(&self) -> Value {
        let a = self.call("GET", "/api/v1/status", &[("X-Api-Key", KEY)], b"");
        assert_eq!(a.status, 200, "{}", a.text());
        a.json()
    }

    fn wait_for(&self, what: &str, check: impl Fn(&Value) -> bool) -> Value {
        common::http::poll_status(
            Duration::from_secs(120),
            what,
            &self.log,
            || self.status(),
            check,
        )
    }
}

/// A multipart form with `parts` in this order; `("file", name)` is the file.
fn form(parts: &[(&str, &str)], content: &[u8]) -> (String, Vec<u8>) {
    let boundary = "boundary_.oOo._MTc0OTQ5NTQ2Mg==";
    let mut body = Vec::new();
    for (name, value) in parts {
        if *name == "file" {
            body.extend_from_slice(
                format!(
                    "--{boundary}\r\nContent-Type: application/octet-stream\r\n\
                     Content-Disposition: form-data; name=\"file\"; filename=\"{value}\"\r\n\r\n"
                )
                .as_bytes(),
            );
            body.extend_from_slice(content);
            body.extend_from_slice(b"\r\n");
        } else {
            body.extend_from_slice(
                format!(
                    "--{boundary}\r\nContent-Type: text/plain\r\n\
                     Content-Disposition: form-data; name=\"{name}\"\r\n\r\n{value}\r\n"
                )
                .as_bytes(),
            );
        }
    }
    body.extend_from_slice(format!("--{boundary}--\r\n").as_bytes());
    (
        format!("multipart/form-data; boundary=\"{boundary}\""),
        body,
    )
}

/// The path part of an absolute `Location`.
fn path_of(location: &str) -> String {
    let rest = location
        .strip_prefix("http://")
        .unwrap_or_else(|| panic!("not absolute: {location}"));
    rest[rest.find('/').unwrap()..].to_string()
}

/// Cura's OctoPrint connection, call by call in the order of its source
/// (`DiscoverOctoPrintAction.py`, `OctoPrintOutputDevice.py`), on the instance of hot
/// folder `other`: the application-key flow (probe, request, poll until the operator
/// allows it through the API as the dashboard does, the key in the poll's answer), then
/// with that key `api/settings`, `api/version`, passive `api/login`,
/// `api/printerprofiles`, polling `api/printer` and `api/job`; "Upload" (no `select` or
/// `print`): `path`, then the file; the file's address from `Location`; then the
/// select-and-print command to it releases the held job, which prints on `other`'s
/// printer. "Upload and print" with `select` and `print` after the file prints at once.
/// The key opens no operator API, and a revoked key opens nothing.
#[test]
fn cura_plugin_calls_in_order_get_a_key_and_the_job_prints() {
    let tmp = tempfile::tempdir().unwrap();
    let farm = Farm::start(tmp.path());
    let base = "/octoprint/other/";
    let ua = ("User-Agent", "Cura-OctoPrintPlugin/3.7.3");

    // DiscoverOctoPrintAction.probeAppKeySupport / requestApiKey / _pollApiKey.
    let a = farm.call("GET", &format!("{base}plugin/appkeys/probe"), &[ua], b"");
    assert_eq!(a.status, 204, "{}", a.text());
    let a = farm.call(
        "POST",
        &format!("{base}plugin/appkeys/request"),
        &[ua, ("Content-Type", "application/json")],
        br#"{"app": "Cura"}"#,
    );
    assert_eq!(a.status, 201, "{}", a.text());
    assert!(a.json()["app_token"].is_string(), "{}", a.text());
    let poll = path_of(&a.header("location").expect("Location to poll"));
    assert!(
        poll.starts_with(&format!("{base}plugin/appkeys/request/")),
        "{poll}"
    );
    let a = farm.call("GET", &poll, &[ua, ("Content-Type", "")], b"");
    assert_eq!(a.status, 202, "undecided: {}", a.text());

    // The operator sees the request (application and address) and allows it, as the
    // dashboard's panel (its own script, on the page) does.
    let page = farm.call("GET", "/", &[], b"");
    assert!(
        page.text().contains("/appkeys.js"),
        "the panel's script is on the page"
    );
    let script = farm.call("GET", "/appkeys.js", &[], b"");
    assert_eq!(script.status, 200);
    assert!(
        script.text().contains("/api/v1/appkeys/requests/"),
        "{}",
        script.text()
    );
    let list = farm.call("GET", "/api/v1/appkeys", &[("X-Api-Key", KEY)], b"");
    assert_eq!(list.status, 200, "{}", list.text());
    let list = list.json();
    let request = &list["pending"][0];
    assert_eq!(request["app"], "Cura", "{list}");
    assert_eq!(request["source"], "127.0.0.1", "{list}");
    assert_eq!(request["instance"], base, "{list}");
    assert!(
        !list.to_string().contains(poll.rsplit('/').next().unwrap()),
        "no token listed"
    );
    let id = request["id"].as_str().unwrap();
    let a = farm.call(
        "POST",
        &format!("/api/v1/appkeys/requests/{id}/allow"),
        &[],
        b"",
    );
    assert_eq!(a.status, 401, "allowing needs the operator's key");
    let a = farm.call(
        "POST",
        &format!("/api/v1/appkeys/requests/{id}/allow"),
        &[("X-Api-Key", KEY)],
        b"",
    );
    assert_eq!(a.status, 200, "{}", a.text());
    let a = farm.call("GET", &poll, &[ua], b"");
    assert_eq!(a.status, 200, "{}", a.text());
    let app_key = a.json()["api_key"].as_str().unwrap().to_string();
    assert_ne!(app_key, KEY);
    assert_eq!(farm.call("GET", &poll, &[ua], b"").status, 404, "told once");
    let k = ("X-Api-Key", app_key.as_str());

    // testApiKey: api/settings with the key.
    let a = farm.call("GET", &format!("{base}api/settings"), &[ua, k], b"");
    assert_eq!(a.status, 200, "{}", a.text());
    let settings = a.json();
    assert_eq!(settings["feature"]["sdSupport"], false);
    assert!(settings["plugins"].is_object());
    let wrong = farm.call(
        "GET",
        &format!("{base}api/settings"),
        &[("X-Api-Key", "nope-nope-nope")],
        b"",
    );
    assert_eq!(wrong.status, 403);
    // connect(): version, passive login, printer profiles.
    let v = farm
        .call("GET", &format!("{base}api/version"), &[ua, k], b"")
        .json();
    assert!(v["text"].as_str().unwrap().starts_with("OctoPrint"), "{v}");
    assert!(v["server"].is_string() && v["api"].is_string(), "{v}");
    let a = farm.call(
        "POST",
        &format!("{base}api/login"),
        &[ua, k, ("Content-Type", "application/json")],
        br#"{"passive": true}"#,
    );
    assert_eq!(a.status, 200, "{}", a.text());
    assert_eq!(a.json()["name"], "Cura");
    let profiles = farm
        .call("GET", &format!("{base}api/printerprofiles"), &[ua, k], b"")
        .json();
    let current = profiles["profiles"]
        .as_object()
        .unwrap()
        .values()
        .find(|p| p["current"] == true)
        .unwrap_or_else(|| panic!("a current profile: {profiles}"))
        .clone();
    assert!(
        current["volume"]["width"].as_f64().unwrap() > 0.0,
        "{current}"
    );
    assert!(current["heatedBed"].is_boolean());
    assert!(current["axes"]["x"]["speed"].is_number());
    assert!(current["extruder"]["nozzleDiameter"].as_f64().unwrap() > 0.0);
    // The polls (every 2 s in Cura).
    let started = Instant::now();
    let printer = loop {
        let p = farm.call("GET", &format!("{base}api/printer"), &[ua, k], b"");
        assert_eq!(p.status, 200, "{}", p.text());
        let p = p.json();
        if p["state"]["flags"]["ready"] == true {
            break p;
        }
        assert!(
            started.elapsed() < Duration::from_secs(60),
            "beta ready: {p}"
        );
        std::thread::sleep(Duration::from_millis(200));
    };
    assert!(printer["temperature"]["tool0"]
        .as_object()
        .unwrap()
        .contains_key("actual"));
    assert!(printer["temperature"]["bed"]
        .as_object()
        .unwrap()
        .contains_key("target"));
    assert_eq!(printer["state"]["flags"]["operational"], true);
    assert_eq!(
        printer["crispen"]["printer"], "beta",
        "other's printer: {printer}"
    );
    let job = farm
        .call("GET", &format!("{base}api/job"), &[ua, k], b"")
        .json();
    assert_eq!(job["state"], "Operational", "{job}");
    assert!(job["progress"]
        .as_object()
        .unwrap()
        .contains_key("completion"));
    assert!(job["job"]["file"].as_object().unwrap().contains_key("name"));

    // _sendPrintJob, "Upload" only: `path` (empty), then the file; no select or print.
    let (ct, body) = form(
        &[("path", ""), ("file", "cura_part.gcode")],
        GCODE.as_bytes(),
    );
    let a = farm.call(
        "POST",
        &format!("{base}api/files/local"),
        &[ua, k, ("Content-Type", &ct)],
        &body,
    );
    assert_eq!(a.status, 201, "{}", a.text());
    let answer = a.json();
    assert_eq!(answer["done"], true);
    assert_eq!(answer["effectivePrint"], false, "{answer}");
    assert_eq!(answer["files"]["local"]["name"], "cura_part.gcode");
    let location = a.header("location").expect("Location");
    // _onUploadFinished: the end point is what follows "api/" in the Location.
    let end_point = location.split_once("api/").unwrap().1.to_string();
    assert_eq!(end_point, "files/local/cura_part.gcode");
    assert!(location.contains(base), "under the instance: {location}");
    let s = farm.wait_for("the upload held and ready", |s| {
        job_by_file(s, "cura_part.gcode")
            .is_some_and(|j| j["state"] == "ready" && j["held"] == true)
    });
    let j = job_by_file(&s, "cura_part.gcode").unwrap();
    assert!(j["folder"].as_str().unwrap().ends_with("other"), "{j}");
    // api/job names the next job while it waits.
    let job = farm
        .call("GET", &format!("{base}api/job"), &[ua, k], b"")
        .json();
    assert_eq!(job["job"]["file"]["name"], "cura_part.gcode", "{job}");
    // _selectAndPrint.
    let a = farm.call(
        "POST",
        &format!("{base}api/{end_point}"),
        &[ua, k, ("Content-Type", "application/json")],
        &serde_json::to_vec(&json!({"command": "select", "print": true})).unwrap(),
    );
    assert_eq!(a.status, 204, "{}", a.text());
    let s = farm.wait_for("the released job printed", |s| {
        job_by_file(s, "cura_part.gcode").is_some_and(|j| j["state"] == "done")
    });
    assert_eq!(
        job_by_file(&s, "cura_part.gcode").unwrap()["printer"],
        "beta"
    );
    assert_eq!(
        job_by_file(&s, "cura_part.gcode").unwrap()["copies_done"],
        1
    );
    // Selecting it again prints nothing twice.
    let a = farm.call(
        "POST",
        &format!("{base}api/{end_point}"),
        &[ua, k, ("Content-Type", "application/json")],
        br#"{"command": "select", "print": true}"#,
    );
    assert_eq!(a.status, 409, "{}", a.text());
    let cleared = farm.call(
        "POST",
        "/api/v1/printers/beta/clear",
        &[("X-Api-Key", KEY)],
        b"",
    );
    assert_eq!(cleared.status, 200, "{}", cleared.text());

    // "Upload and print": `select` and `print` after the file (Cura's order).
    let (ct, body) = form(
        &[
            ("path", ""),
            ("file", "cura_now.gcode"),
            ("select", "true"),
            ("print", "true"),
        ],
        GCODE.as_bytes(),
    );
    let a = farm.call(
        "POST",
        &format!("{base}api/files/local"),
        &[ua, k, ("Content-Type", &ct)],
        &body,
    );
    assert_eq!(a.status, 201, "{}", a.text());
    assert_eq!(a.json()["effectivePrint"], true, "{}", a.text());
    farm.wait_for("the upload-and-print printed", |s| {
        job_by_file(s, "cura_now.gcode").is_some_and(|j| j["state"] == "done" && j["held"] == false)
    });

    // An application key is for the OctoPrint emulation only, on its own instance; a
    // revoked one is refused.
    assert_eq!(farm.call("GET", "/api/v1/status", &[k], b"").status, 403);
    assert_eq!(
        farm.call(
            "GET",
            &format!("{base}api/job"),
            &[("Authorization", &format!("Bearer {app_key}"))],
            b""
        )
        .status,
        200
    );
    assert_eq!(
        farm.call("GET", &format!("{base}api/job?apikey={app_key}"), &[], b"")
            .status,
        200
    );
    assert_eq!(
        farm.call("GET", &format!("/api/job?apikey={app_key}"), &[], b"")
            .status,
        403,
        "the root is another instance"
    );
    let (ok, listed) = cli(&farm.root, &["keys"]);
    assert!(ok && listed.contains("Cura"), "{listed}");
    let key_id = farm
        .call("GET", "/api/v1/appkeys", &[("X-Api-Key", KEY)], b"")
        .json()["keys"][0]["id"]
        .as_str()
        .unwrap()
        .to_string();
    let (ok, said) = cli(&farm.root, &["keys", "revoke", &key_id]);
    assert!(ok, "{said}");
    assert_eq!(
        farm.call("GET", &format!("{base}api/job"), &[k], b"")
            .status,
        403
    );
    // Kept across a restart: the file is there, without the revoked key.
    let stored = std::fs::read_to_string(farm.root.join("spool/appkeys.json")).unwrap();
    assert!(!stored.contains(&app_key), "{stored}");
    drop(farm.daemon);
}

/// An application key asked for on `instance` and allowed with `query` (`""`,
/// `?control=true`, …) by the operator: (its secret, its id).
fn allowed_key(farm: &Farm, instance: &str, app: &str, query: &str) -> (String, String) {
    let a = farm.call(
        "POST",
        &format!("{instance}plugin/appkeys/request"),
        &[("Content-Type", "application/json")],
        &serde_json::to_vec(&json!({ "app": app })).unwrap(),
    );
    assert_eq!(a.status, 201, "{}", a.text());
    let poll = path_of(&a.header("location").unwrap());
    let list = farm
        .call("GET", "/api/v1/appkeys", &[("X-Api-Key", KEY)], b"")
        .json();
    let id = list["pending"]
        .as_array()
        .unwrap()
        .iter()
        .find(|r| r["app"] == app)
        .unwrap_or_else(|| panic!("{app}'s request: {list}"))["id"]
        .as_str()
        .unwrap()
        .to_string();
    let a = farm.call(
        "POST",
        &format!("/api/v1/appkeys/requests/{id}/allow{query}"),
        &[("X-Api-Key", KEY)],
        b"",
    );
    assert_eq!(a.status, 200, "{}", a.text());
    let secret = farm.call("GET", &poll, &[], b"").json()["api_key"]
        .as_str()
        .unwrap()
        .to_string();
    let keys = farm
        .call("GET", "/api/v1/appkeys", &[("X-Api-Key", KEY)], b"")
        .json();
    let key_id = keys["keys"]
        .as_array()
        .unwrap()
        .iter()
        .find(|k| k["app"] == app)
        .unwrap()["id"]
        .as_str()
        .unwrap()
        .to_string();
    (secret, key_id)
}

/// A long print: moves at 5 mm/s, long enough to pause, resume and cancel.
fn slow_gcode() -> String {
    let mut text = "; slow\nM104 S200\nM109 S200\nG28\nG92 E0\nG1 Z0.3 F600\n".to_string();
    for i in 0..60 {
        text.push_str(&format!(
            "G1 X10 Y10 E{} F300\nG1 X100 Y100 E{} F300\n",
            2 * i + 1,
            2 * i + 2
        ));
    }
    text.push_str("M104 S0\nM84\n");
    text
}

/// What a key opens is what the operator allowed: an upload-only Cura key on `hot`'s
/// instance reads and uploads there, prints its own uploads (held, then select-and-print;
/// upload-and-print), but releases no job held by a sidecar or by the operator, uses no
/// other instance (`403` naming `--everywhere`), and controls no print (`409`, as OctoPrint refuses a
/// command, naming `--control`). `crispen keys allow ID --everywhere` opens the other instances, `--control`
/// pause, resume and cancel through `POST api/job`. A key stored before scopes existed
/// loads with the narrowest (upload, its own instance). Listings show the scopes.
#[test]
fn application_keys_open_only_what_their_scope_allows() {
    let tmp = tempfile::tempdir().unwrap();
    let root = tmp.path();
    prepare(root, "default_folder = \"hot\"\nannounce = false\n");
    // beta (folder `other`) prints at a fifth of real time: long enough to control.
    let config = std::fs::read_to_string(root.join("crispen.toml")).unwrap();
    let beta = "name = \"beta\"\nfirmware = \"marlin2\"\n[printer.simulate]\ntime_scale = 0.0";
    assert!(config.contains(beta));
    std::fs::write(
        root.join("crispen.toml"),
        config.replace(beta, &beta.replace("0.0", "0.2")),
    )
    .unwrap();
    // A key from before scopes, on `other`'s instance.
    std::fs::create_dir_all(root.join("spool")).unwrap();
    let old_key = "old-key-0123456789abcdefghij";
    std::fs::write(
        root.join("spool/appkeys.json"),
        json!({"keys": [{"id": "oldkey01", "app": "OldSlicer", "source": "10.0.0.9",
            "instance": "/octoprint/other/", "created_s": 1700000000u64, "key": old_key}]})
        .to_string(),
    )
    .unwrap();
    let farm = Farm::started(root);
    let (cura, cura_id) = allowed_key(&farm, "/octoprint/hot/", "Cura", "");
    let k = ("X-Api-Key", cura.as_str());
    let json_type = ("Content-Type", "application/json");
    let select_print = br#"{"command": "select", "print": true}"#;
    // A job command (`POST api/job`) with the Cura key on one instance.
    let post_job = |instance: &str, body: &[u8]| {
        farm.call(
            "POST",
            &format!("/octoprint/{instance}/api/job"),
            &[k, json_type],
            body,
        )
    };

    // Listed with their scopes: the API, the CLI.
    let keys = farm
        .call("GET", "/api/v1/appkeys", &[("X-Api-Key", KEY)], b"")
        .json();
    let scope_of = |keys: &Value, app: &str| {
        keys["keys"]
            .as_array()
            .unwrap()
            .iter()
            .find(|k| k["app"] == app)
            .unwrap()["scope_text"]
            .as_str()
            .unwrap()
            .to_string()
    };
    assert_eq!(
        scope_of(&keys, "Cura"),
        "upload on /octoprint/hot/",
        "{keys}"
    );
    assert_eq!(
        scope_of(&keys, "OldSlicer"),
        "upload on /octoprint/other/",
        "{keys}"
    );
    let (ok, listed) = cli(root, &["keys"]);
    assert!(
        ok && listed.contains("upload on /octoprint/hot/")
            && listed.contains("upload on /octoprint/other/"),
        "{listed}"
    );

    // The old key: its own instance only.
    let old = ("X-Api-Key", old_key);
    assert_eq!(
        farm.call("GET", "/octoprint/other/api/job", &[old], b"")
            .status,
        200
    );
    assert_eq!(
        farm.call("GET", "/octoprint/hot/api/job", &[old], b"")
            .status,
        403
    );

    // Another instance: refused, whatever the call, saying how to widen the key.
    let (ct, body) = form(
        &[("file", "elsewhere.gcode"), ("print", "true")],
        GCODE.as_bytes(),
    );
    for (method, path, body, ct) in [
        ("GET", "/octoprint/other/api/printer", &b""[..], ""),
        ("GET", "/api/printer", &b""[..], ""),
        (
            "POST",
            "/octoprint/other/api/files/local",
            &body[..],
            ct.as_str(),
        ),
        ("POST", "/api/files/local", &body[..], ct.as_str()),
    ] {
        let a = farm.call(method, path, &[k, ("Content-Type", ct)], body);
        assert_eq!(a.status, 403, "{path}: {}", a.text());
        assert!(
            a.error()
                .contains(&format!("crispen keys allow {cura_id} --everywhere")),
            "{}",
            a.text()
        );
    }
    assert!(!root.join("other/elsewhere.gcode").exists());
    let log = std::fs::read_to_string(&farm.log).unwrap();
    assert!(
        log.contains("application key refused") && log.contains("Cura"),
        "refusals are logged with the app: {log}"
    );

    // A job held by its sidecar, and one the operator uploaded without print: ready and
    // held; Cura's select-and-print releases neither.
    std::fs::write(root.join("hot/side.gcode.toml"), "hold = true\n").unwrap();
    std::fs::write(root.join("hot/side.gcode"), GCODE).unwrap();
    let (ct, body) = form(&[("file", "op.gcode")], GCODE.as_bytes());
    let a = farm.call(
        "POST",
        "/octoprint/hot/api/files/local",
        &[("X-Api-Key", KEY), ("Content-Type", &ct)],
        &body,
    );
    assert_eq!(a.status, 201, "{}", a.text());
    farm.wait_for("both held and ready", |s| {
        ["side.gcode", "op.gcode"]
            .iter()
            .all(|f| job_by_file(s, f).is_some_and(|j| j["state"] == "ready" && j["held"] == true))
    });
    for file in ["side.gcode", "op.gcode"] {
        let a = farm.call(
            "POST",
            &format!("/octoprint/hot/api/files/local/{file}"),
            &[k, json_type],
            select_print,
        );
        assert_eq!(a.status, 403, "{file}: {}", a.text());
        assert!(
            a.error().contains("held by its sidecar or by the operator"),
            "{}",
            a.text()
        );
        // Selecting without print changes nothing and is fine.
        let a = farm.call(
            "POST",
            &format!("/octoprint/hot/api/files/local/{file}"),
            &[k, json_type],
            br#"{"command": "select"}"#,
        );
        assert_eq!(a.status, 204, "{file}: {}", a.text());
    }

    // Its own upload, held, then select-and-print: prints. Upload-and-print: prints.
    let (ct, body) = form(&[("path", ""), ("file", "mine.gcode")], GCODE.as_bytes());
    let a = farm.call(
        "POST",
        "/octoprint/hot/api/files/local",
        &[k, ("Content-Type", &ct)],
        &body,
    );
    assert_eq!(a.status, 201, "{}", a.text());
    farm.wait_for("its own upload held", |s| {
        job_by_file(s, "mine.gcode").is_some_and(|j| j["state"] == "ready" && j["held"] == true)
    });
    let a = farm.call(
        "POST",
        "/octoprint/hot/api/files/local/mine.gcode",
        &[k, json_type],
        select_print,
    );
    assert_eq!(a.status, 204, "{}", a.text());
    farm.wait_for("its own upload printed", |s| {
        job_by_file(s, "mine.gcode").is_some_and(|j| j["state"] == "done")
    });
    let clear = |printer: &str| {
        let a = farm.call(
            "POST",
            &format!("/api/v1/printers/{printer}/clear"),
            &[("X-Api-Key", KEY)],
            b"",
        );
        assert_eq!(a.status, 200, "{}", a.text());
    };
    clear("alpha");
    let (ct, body) = form(
        &[
            ("path", ""),
            ("file", "now.gcode"),
            ("select", "true"),
            ("print", "true"),
        ],
        GCODE.as_bytes(),
    );
    let a = farm.call(
        "POST",
        "/octoprint/hot/api/files/local",
        &[k, ("Content-Type", &ct)],
        &body,
    );
    assert_eq!(a.status, 201, "{}", a.text());
    let s = farm.wait_for("upload-and-print printed", |s| {
        job_by_file(s, "now.gcode").is_some_and(|j| j["state"] == "done")
    });
    for file in ["side.gcode", "op.gcode"] {
        assert_eq!(
            job_by_file(&s, file).unwrap()["held"],
            true,
            "{file} still held"
        );
    }

    // Control: not in its scope.
    let a = post_job("hot", br#"{"command": "cancel"}"#);
    assert_eq!(a.status, 409, "{}", a.text());
    assert!(
        a.error()
            .contains(&format!("crispen keys allow {cura_id} --control")),
        "{}",
        a.text()
    );

    // Everywhere: the other instance opens.
    let (ok, said) = cli(root, &["keys", "allow", &cura_id, "--everywhere"]);
    assert!(ok && said.contains("upload everywhere"), "{said}");
    let a = farm.call("GET", "/octoprint/other/api/printer", &[k], b"");
    assert_eq!(a.status, 200, "{}", a.text());
    let a = post_job("other", br#"{"command": "pause", "action": "pause"}"#);
    assert_eq!(a.status, 409, "still no control: {}", a.text());

    // Control (and everywhere): pause, resume, cancel the print of `other`.
    let (ok, said) = cli(
        root,
        &["keys", "allow", &cura_id, "--control", "--everywhere"],
    );
    assert!(ok && said.contains("upload, control everywhere"), "{said}");
    let (ok, listed) = cli(root, &["keys"]);
    assert!(
        ok && listed.contains("upload, control everywhere"),
        "{listed}"
    );
    let a = post_job("other", br#"{"command": "pause", "action": "pause"}"#);
    assert_eq!(a.status, 409, "nothing prints yet: {}", a.text());
    let (ct, body) = form(
        &[("file", "slow.gcode"), ("print", "true")],
        slow_gcode().as_bytes(),
    );
    let a = farm.call(
        "POST",
        "/octoprint/other/api/files/local",
        &[k, ("Content-Type", &ct)],
        &body,
    );
    assert_eq!(a.status, 201, "{}", a.text());
    let beta = |s: &Value| common::printer(s, "beta")["state"].clone();
    farm.wait_for("beta printing", |s| beta(s) == "printing");
    let job_command = |body: &[u8]| {
        let a = post_job("other", body);
        assert_eq!(a.status, 204, "{}", a.text());
    };
    job_command(br#"{"command": "pause", "action": "pause"}"#);
    farm.wait_for("beta paused", |s| beta(s) == "paused");
    let job = farm
        .call("GET", "/octoprint/other/api/job", &[k], b"")
        .json();
    assert_eq!(job["state"], "Paused", "{job}");
    job_command(br#"{"command": "pause", "action": "resume"}"#);
    farm.wait_for("beta printing again", |s| beta(s) == "printing");
    job_command(br#"{"command": "cancel"}"#);
    farm.wait_for("the slow job cancelled", |s| {
        job_by_file(s, "slow.gcode").is_some_and(|j| j["state"] == "cancelled")
    });
    // The holds stay the operator's even so.
    let a = farm.call(
        "POST",
        "/octoprint/hot/api/files/local/op.gcode",
        &[k, json_type],
        select_print,
    );
    assert_eq!(a.status, 403, "{}", a.text());
}

/// Key requests free their places the moment they stop waiting: two may wait from one
/// address, a third is told what frees a place (the operator's decision, or time); a
/// denied request leaves the list at once (its client is told at once), so does an
/// allowed one (its key waits for its client outside the list).
#[test]
fn key_requests_free_their_places_at_once() {
    let tmp = tempfile::tempdir().unwrap();
    let farm = Farm::start(tmp.path());
    let ask = |app: &str| {
        farm.call(
            "POST",
            "/octoprint/hot/plugin/appkeys/request",
            &[("Content-Type", "application/json")],
            &serde_json::to_vec(&json!({ "app": app })).unwrap(),
        )
    };
    let pending = || {
        farm.call("GET", "/api/v1/appkeys", &[("X-Api-Key", KEY)], b"")
            .json()["pending"]
            .as_array()
            .unwrap()
            .clone()
    };
    let polls: Vec<String> = ["one", "two"]
        .iter()
        .map(|app| {
            let a = ask(app);
            assert_eq!(a.status, 201, "{}", a.text());
            path_of(&a.header("location").unwrap())
        })
        .collect();
    let a = ask("three");
    assert_eq!(a.status, 429, "{}", a.text());
    let said = a.error();
    assert!(
        said.contains("from 127.0.0.1") && said.contains("frees its place at once"),
        "{said}"
    );
    assert!(said.contains("forgotten in"), "{said}");
    assert_eq!(pending().len(), 2);

    // Denied: gone at once, its client told so; the place is free.
    let id = pending().iter().find(|r| r["app"] == "one").unwrap()["id"]
        .as_str()
        .unwrap()
        .to_string();
    let (ok, said) = cli(&farm.root, &["keys", "deny", &id]);
    assert!(ok, "{said}");
    assert_eq!(pending().len(), 1);
    assert_eq!(farm.call("GET", &polls[0], &[], b"").status, 404);
    let (ok, said) = cli(&farm.root, &["keys", "deny", &id]);
    assert!(!ok, "decided already: {said}");
    let a = ask("three");
    assert_eq!(a.status, 201, "{}", a.text());

    // Allowed: gone from the list at once too; its client still gets the key, once.
    let id = pending().iter().find(|r| r["app"] == "two").unwrap()["id"]
        .as_str()
        .unwrap()
        .to_string();
    let (ok, said) = cli(&farm.root, &["keys", "allow", &id]);
    assert!(ok && said.contains("upload on /octoprint/hot/"), "{said}");
    assert_eq!(
        pending()
            .iter()
            .map(|r| r["app"].clone())
            .collect::<Vec<_>>(),
        [json!("three")]
    );
    let a = farm.call("GET", &polls[1], &[], b"");
    assert_eq!(a.status, 200, "{}", a.text());
    assert!(a.json()["api_key"].is_string());
    assert_eq!(
        farm.call("GET", &polls[1], &[], b"").status,
        404,
        "told once"
    );
    assert_eq!(ask("four").status, 201, "two places again");
}

/// The CLI against the farm in `root`.
fn cli(root: &Path, args: &[&str]) -> (bool, String) {
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

/// The real clients from PyPI: `octorest` (which talks to the root instance only and
/// drops `path`, `select` and `print` from its uploads: the file lands held in the default
/// folder) reads version, printer and job, uploads, and selects-and-prints the file by its
/// root path `hot/<file>`; OctoPrint's own `octoprint client` reads a folder's instance
/// (`--prefix /octoprint/other`), uploads there with `print` (prints) and without (held),
/// and selects-and-prints with `command`. Its key is an application key asked for on the
/// root and allowed through the HTTP API as the dashboard allows it, for every instance.
#[test]
fn octorest_and_octoprint_client_drive_the_farm() {
    let python = python();
    let tmp = tempfile::tempdir().unwrap();
    let farm = Farm::start(tmp.path());
    // The key: asked for, allowed by the operator for every instance, fetched.
    let (app_key, _) = allowed_key(&farm, "/", "octorest", "?everywhere=true");

    let gcode = tmp.path().join("rest.gcode");
    std::fs::write(&gcode, GCODE).unwrap();
    let script = r#"
import json, sys
from octorest import OctoRest
url, key, path = sys.argv[1], sys.argv[2], sys.argv[3]
client = OctoRest(url=url, apikey=key)
out = {"version": client.version}
out["printer"] = client.printer()
out["job"] = client.job_info()
out["upload"] = client.upload(path, select=False, print=False)
print(json.dumps(out))
"#;
    let run = |args: &[&str]| {
        let out = Command::new(&python)
            .args(args)
            .env("HOME", tmp.path())
            .output()
            .unwrap();
        let text = String::from_utf8_lossy(&out.stdout).into_owned();
        assert!(
            out.status.success(),
            "{args:?}: {text}\n{}\nlog:\n{}",
            String::from_utf8_lossy(&out.stderr),
            std::fs::read_to_string(&farm.log).unwrap_or_default()
        );
        text
    };
    let url = format!("http://{}/", farm.addr);
    let out: Value = serde_json::from_str(
        run(&["-c", script, &url, &app_key, gcode.to_str().unwrap()])
            .lines()
            .last()
            .unwrap(),
    )
    .unwrap();
    assert!(
        out["version"]["text"]
            .as_str()
            .unwrap()
            .starts_with("OctoPrint"),
        "{out}"
    );
    assert_eq!(
        out["printer"]["crispen"]["printer"], "alpha",
        "the default folder's: {out}"
    );
    assert!(out["printer"]["state"]["flags"].is_object(), "{out}");
    assert!(out["job"]["progress"].is_object(), "{out}");
    assert_eq!(
        out["upload"]["files"]["local"]["path"], "hot/rest.gcode",
        "{out}"
    );
    assert_eq!(out["upload"]["effectivePrint"], false, "{out}");
    farm.wait_for("octorest's upload held", |s| {
        job_by_file(s, "rest.gcode").is_some_and(|j| j["state"] == "ready" && j["held"] == true)
    });
    let select = r#"
import sys
from octorest import OctoRest
client = OctoRest(url=sys.argv[1], apikey=sys.argv[2])
client.select("hot/rest.gcode", print=True)
print("selected")
"#;
    assert!(run(&["-c", select, &url, &app_key]).contains("selected"));
    farm.wait_for("octorest's upload printed", |s| {
        job_by_file(s, "rest.gcode").is_some_and(|j| j["state"] == "done")
    });

    // `octoprint client` on hot folder `other`'s instance.
    let port = farm.addr.rsplit(':').next().unwrap().to_string();
    let octoprint = venv().join("bin/octoprint");
    let client = |args: &[&str]| {
        let out = Command::new(&octoprint)
            .args([
                "client",
                "--host",
                "127.0.0.1",
                "--port",
                &port,
                "--apikey",
                &app_key,
            ])
            .args(["--prefix", "/octoprint/other"])
            .args(args)
            .env("HOME", tmp.path())
            .output()
            .unwrap();
        let text = String::from_utf8_lossy(&out.stdout).into_owned()
            + &String::from_utf8_lossy(&out.stderr);
        assert!(out.status.success(), "{args:?}: {text}");
        text
    };
    let printer = client(&["get", "api/printer"]);
    assert!(
        printer.contains("Status Code: 200") && printer.contains("\"beta\""),
        "{printer}"
    );
    let job = client(&["get", "api/job"]);
    assert!(
        job.contains("Status Code: 200") && job.contains("\"progress\""),
        "{job}"
    );
    let held = tmp.path().join("client_held.gcode");
    std::fs::write(&held, GCODE).unwrap();
    let up = client(&["upload", "api/files/local", held.to_str().unwrap()]);
    assert!(
        up.contains("Status Code: 201") && up.contains("\"effectivePrint\": false")
            || up.contains("\"effectivePrint\":false"),
        "{up}"
    );
    let now = tmp.path().join("client_now.gcode");
    std::fs::write(&now, GCODE).unwrap();
    let up = client(&[
        "upload",
        "-P",
        "print",
        "true",
        "api/files/local",
        now.to_str().unwrap(),
    ]);
    assert!(up.contains("Status Code: 201"), "{up}");
    farm.wait_for("the client's printing upload printed", |s| {
        job_by_file(s, "client_now.gcode").is_some_and(|j| j["state"] == "done")
    });
    let s = farm.wait_for("the client's held upload ready", |s| {
        job_by_file(s, "client_held.gcode")
            .is_some_and(|j| j["state"] == "ready" && j["held"] == true)
    });
    assert!(job_by_file(&s, "client_now.gcode").unwrap()["folder"]
        .as_str()
        .unwrap()
        .ends_with("other"));
    let cleared = farm.call(
        "POST",
        "/api/v1/printers/beta/clear",
        &[("X-Api-Key", KEY)],
        b"",
    );
    assert_eq!(cleared.status, 200, "{}", cleared.text());
    let sel = client(&[
        "command",
        "-b",
        "print",
        "true",
        "api/files/local/client_held.gcode",
        "select",
    ]);
    assert!(sel.contains("Status Code: 204"), "{sel}");
    farm.wait_for("the client's held upload printed", |s| {
        job_by_file(s, "client_held.gcode").is_some_and(|j| j["state"] == "done")
    });
}

/// A `path` sent after the file lands the file in that folder (it was received into
/// the default folder first), and an upload without a path on the root goes to the default
/// folder; a path naming no folder is refused with the folders' names, leaving nothing.
#[test]
fn a_path_after_the_file_moves_it_to_that_folder() {
    let tmp = tempfile::tempdir().unwrap();
    let farm = Farm::start(tmp.path());
    let (ct, body) = form(
        &[("file", "late.gcode"), ("path", "other"), ("print", "true")],
        GCODE.as_bytes(),
    );
    let a = farm.call(
        "POST",
        "/api/files/local",
        &[("X-Api-Key", KEY), ("Content-Type", &ct)],
        &body,
    );
    assert_eq!(a.status, 201, "{}", a.text());
    assert_eq!(a.json()["files"]["local"]["path"], "other/late.gcode");
    let s = farm.wait_for("the late-path upload printed", |s| {
        job_by_file(s, "late.gcode").is_some_and(|j| j["state"] == "done")
    });
    assert_eq!(job_by_file(&s, "late.gcode").unwrap()["printer"], "beta");
    let (ct, body) = form(
        &[("file", "lost.gcode"), ("path", "nowhere")],
        GCODE.as_bytes(),
    );
    let a = farm.call(
        "POST",
        "/api/files/local",
        &[("X-Api-Key", KEY), ("Content-Type", &ct)],
        &body,
    );
    assert_eq!(a.status, 404, "{}", a.text());
    assert!(
        a.text().contains("other"),
        "names the folders: {}",
        a.text()
    );
    let (ct, body) = form(&[("file", "lost.gcode"), ("path", "hot")], GCODE.as_bytes());
    let a = farm.call(
        "POST",
        "/octoprint/other/api/files/local",
        &[("X-Api-Key", KEY), ("Content-Type", &ct)],
        &body,
    );
    assert_eq!(a.status, 400, "{}", a.text());
    for folder in ["hot", "other"] {
        let left: Vec<_> = std::fs::read_dir(tmp.path().join(folder))
            .unwrap()
            .map(|e| e.unwrap().file_name())
            .filter(|n| n.to_string_lossy().contains("lost"))
            .collect();
        assert!(left.is_empty(), "{folder}: {left:?}");
    }
}

/// Zeroconf: in a network namespace of the test's own (multicast on its loopback), the
/// Python `zeroconf` package browses `_octoprint._tcp` and finds each hot folder as
/// "crispen: <folder>" with its path, version, the daemon's port and its `uuid` (the
/// same as its `api/settings` `upnpUuid`, another for each folder); with
/// `announce = false` it finds none.
#[test]
fn each_folder_is_announced_by_zeroconf() {
    let python = python();
    let browse = r#"
import json, sys, time
from zeroconf import Zeroconf, ServiceBrowser, ServiceListener
want = int(sys.argv[1]); limit = float(sys.argv[2])
found = {}
class L(ServiceListener):
    def add_service(self, zc, type_, name):
        info = zc.get_service_info(type_, name, timeout=3000)
        if info:
            found[name] = {"port": info.port, "props": {k.decode(): (v or b"").decode() for k, v in info.properties.items()}}
    def update_service(self, zc, type_, name): self.add_service(zc, type_, name)
    def remove_service(self, zc, type_, name): pass
zc = Zeroconf(interfaces=["127.0.0.1"])
ServiceBrowser(zc, "_octoprint._tcp.local.", L())
end = time.time() + limit
while time.time() < end and len(found) < want:
    time.sleep(0.2)
zc.close()
# What the same instance says in api/settings (Home Assistant's unique id when set up by hand).
import urllib.request
for entry in found.values():
    url = "http://127.0.0.1:%d%sapi/settings" % (entry["port"], entry["props"].get("path", "/"))
    req = urllib.request.Request(url, headers={"X-Api-Key": sys.argv[3]})
    entry["upnpUuid"] = json.load(urllib.request.urlopen(req, timeout=5))["plugins"]["discovery"]["upnpUuid"]
print(json.dumps(found))
"#;
    for announce in [true, false] {
        let tmp = tempfile::tempdir().unwrap();
        let config = prepare(tmp.path(), &format!("announce = {announce}\n"));
        let log = tmp.path().join("daemon.log");
        let mut launcher = Command::new("unshare");
        launcher.args([
            "-rn",
            "sh",
            "-c",
            "ip link set lo up && ip link set lo multicast on && exec \"$@\"",
            "sh",
            BIN,
        ]);
        let daemon = Daemon::start_by(launcher, &config, &log);
        let addr = common::daemon::http_address(&log);
        let port = addr.rsplit(':').next().unwrap().to_string();
        let pid = daemon.child.id().to_string();
        let (want, limit) = if announce { ("2", "20") } else { ("1", "4") };
        let out = Command::new("nsenter")
            .args(["-t", &pid, "-n", "-U", "--preserve-credentials"])
            .arg(&python)
            .args(["-c", browse, want, limit, KEY])
            .output()
            .unwrap();
        assert!(
            out.status.success(),
            "{}\nlog:\n{}",
            String::from_utf8_lossy(&out.stderr),
            std::fs::read_to_string(&log).unwrap_or_default()
        );
        let found: Value = serde_json::from_slice(&out.stdout)
            .unwrap_or_else(|e| panic!("{e}: {}", String::from_utf8_lossy(&out.stdout)));
        if !announce {
            assert_eq!(found, json!({}), "announce = false");
            continue;
        }
        for folder in ["hot", "other"] {
            let name = format!("crispen: {folder}._octoprint._tcp.local.");
            let entry = &found[&name];
            assert_eq!(
                entry["props"]["path"],
                format!("/octoprint/{folder}/"),
                "{found:#}"
            );
            assert!(
                entry["props"]["version"]
                    .as_str()
                    .is_some_and(|v| !v.is_empty()),
                "{found:#}"
            );
            assert_eq!(entry["port"].to_string(), port, "{found:#}");
            // Home Assistant's zeroconf discovery takes `uuid` as the unique id: the
            // instance's `upnpUuid`, so discovered and configured are one device.
            let uuid = entry["props"]["uuid"].as_str().unwrap_or("");
            assert_eq!(uuid.len(), 36, "{found:#}");
            assert_eq!(entry["upnpUuid"], uuid, "{found:#}");
        }
        assert_ne!(
            found["crispen: hot._octoprint._tcp.local."]["props"]["uuid"],
            found["crispen: other._octoprint._tcp.local."]["props"]["uuid"],
            "{found:#}"
        );
    }
}

/// Home Assistant's OctoPrint integration as it runs, through the library it ships
/// (`pyoctoprintapi`, from the venv), one step per run of [`HA_SCRIPT`], in its order:
/// `key` (the config flow's `request_app_key("Home Assistant", user, timeout)`),
/// `discovery` (`_finish_config`: `get_discovery_info` for the unique id; then what the
/// entities read at setup: server, webcam, tracking), `poll` (the coordinator's
/// `get_job_info` then `get_printer_info`), and the buttons `pause`, `resume`, `stop`
/// (each reads the printer's flags first and acts only as `button.py` does).
const HA_SCRIPT: &str = r#"
import asyncio, json, sys
import aiohttp
from pyoctoprintapi import OctoprintClient, ApiError

async def main():
    step, host, port, path, arg = sys.argv[1], sys.argv[2], int(sys.argv[3]), sys.argv[4], sys.argv[5]
    connector = aiohttp.TCPConnector(force_close=True)
    async with aiohttp.ClientSession(connector=connector) as session:
        client = OctoprintClient(host=host, session=session, port=port, ssl=False, path=path)
        out = {}
        if step == "key":
            out["key"] = await client.request_app_key(arg, "homeassistant", 60)
            print(json.dumps(out))
            return
        client.set_api_key(arg)
        if step == "discovery":
            discovery = await client.get_discovery_info()
            out["uuid"] = discovery.upnp_uuid if discovery else None
            server = await client.get_server_info()
            out["server"] = {"version": server.version, "safemode": server.safe_mode}
            webcam = await client.get_webcam_info()
            out["webcam"] = None if webcam is None else webcam.enabled
            out["tracking"] = (await client.get_tracking_info()) is not None
        elif step == "poll":
            job = await client.get_job_info()
            printer = await client.get_printer_info()
            out = {
                "state": job.state,
                "name": job.job.file.name,
                "completion": job.progress.completion,
                "print_time": job.progress.print_time,
                "print_time_left": job.progress.print_time_left,
                "estimated": job.job.estimated_print_time,
                "text": printer.state.text,
                "printing": printer.state.flags.printing,
                "paused": printer.state.flags.paused,
                "error": printer.state.flags.error,
                "bed": printer.has_heated_bed,
                "temps": {t.name: [t.actual_temp, t.target_temp] for t in printer.temperatures},
            }
        else:
            flags = (await client.get_printer_info()).state.flags
            try:
                if step == "pause" and flags.printing:
                    await client.pause_job()
                    out["sent"] = True
                elif step == "resume" and flags.paused:
                    await client.resume_job()
                    out["sent"] = True
                elif step == "stop" and (flags.printing or flags.paused):
                    await client.cancel_job()
                    out["sent"] = True
                else:
                    out["sent"] = False
            except ApiError as e:
                out["error"] = str(e)
        print(json.dumps(out))

asyncio.run(main())
"#;

/// Runs one step of [`HA_SCRIPT`] against the instance `path` and reads its JSON line.
fn ha_step(farm: &Farm, step: &str, path: &str, arg: &str) -> Value {
    let (host, port) = farm.addr.rsplit_once(':').unwrap();
    let out = Command::new(python())
        .args(["-c", HA_SCRIPT, step, host, port, path, arg])
        .output()
        .unwrap();
    let text = String::from_utf8_lossy(&out.stdout).into_owned();
    assert!(
        out.status.success(),
        "home assistant step {step}: {text}\n{}\nlog:\n{}",
        String::from_utf8_lossy(&out.stderr),
        std::fs::read_to_string(&farm.log).unwrap_or_default()
    );
    serde_json::from_str(text.lines().last().unwrap_or(""))
        .unwrap_or_else(|e| panic!("{e}: {text}"))
}

/// Home Assistant's key request, allowed from the test by `crispen keys allow ID`
/// (with `extra`, e.g. `--control`) while the library polls: the key.
fn ha_key(farm: &Farm, path: &str, app: &str, extra: &[&str]) -> String {
    let (host, port) = farm.addr.rsplit_once(':').unwrap();
    let child = Command::new(python())
        .args(["-c", HA_SCRIPT, "key", host, port, path, app])
        .stdout(std::process::Stdio::piped())
        .stderr(std::process::Stdio::piped())
        .spawn()
        .unwrap();
    let started = Instant::now();
    let id = loop {
        let list = farm
            .call("GET", "/api/v1/appkeys", &[("X-Api-Key", KEY)], b"")
            .json();
        let found = list["pending"].as_array().and_then(|p| {
            p.iter()
                .find(|r| r["app"] == app)
                .and_then(|r| r["id"].as_str().map(str::to_string))
        });
        if let Some(id) = found {
            break id;
        }
        assert!(
            started.elapsed() < Duration::from_secs(30),
            "no request from {app}: {list}"
        );
        std::thread::sleep(Duration::from_millis(100));
    };
    let mut args = vec!["keys", "allow", id.as_str()];
    args.extend_from_slice(extra);
    let (ok, said) = cli(&farm.root, &args);
    assert!(ok, "{said}");
    let out = child.wait_with_output().unwrap();
    let text = String::from_utf8_lossy(&out.stdout).into_owned();
    assert!(
        out.status.success(),
        "{text}\n{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let v: Value = serde_json::from_str(text.lines().last().unwrap_or("")).unwrap();
    v["key"].as_str().unwrap().to_string()
}

/// Home Assistant set up against hot folder `other`'s instance with its own library:
/// the key asked for and allowed with `crispen keys allow ID --control`; the unique id
/// (`upnpUuid`) there, the same after a restart and in the zeroconf-ready answer, other
/// than `hot`'s; server, webcam (off), tracking (none) as its entities read them; while
/// a real print runs the coordinator's polls show the job's name, its completion and the
/// hotend's temperature; Pause, Resume and Stop act on the printer. A key allowed
/// without control gets the 409 that says how to give it, and the actions are counted.
#[test]
fn home_assistant_sets_up_and_its_buttons_act_on_the_printer() {
    python();
    let tmp = tempfile::tempdir().unwrap();
    let root = tmp.path();
    prepare(root, "default_folder = \"hot\"\nannounce = false\n");
    // beta (folder `other`) prints at a fifth of real time: long enough to poll and control.
    let config = std::fs::read_to_string(root.join("crispen.toml")).unwrap();
    let beta = "name = \"beta\"\nfirmware = \"marlin2\"\n[printer.simulate]\ntime_scale = 0.0";
    std::fs::write(
        root.join("crispen.toml"),
        config.replace(beta, &beta.replace("0.0", "0.2")),
    )
    .unwrap();
    let mut farm = Farm::started(root);
    let path = "/octoprint/other/";
    let key = ha_key(&farm, path, "Home Assistant", &["--control"]);

    let d = ha_step(&farm, "discovery", path, &key);
    let uuid = d["uuid"]
        .as_str()
        .unwrap_or_else(|| panic!("no upnpUuid: {d}"))
        .to_string();
    assert_eq!(uuid.len(), 36, "{d}");
    assert_eq!(d["server"]["version"], "1.10.0", "{d}");
    assert_eq!(d["server"]["safemode"], Value::Null, "{d}");
    assert_eq!(d["webcam"], false, "{d}");
    assert_eq!(d["tracking"], false, "{d}");
    let hot = farm
        .call(
            "GET",
            "/octoprint/hot/api/settings",
            &[("X-Api-Key", KEY)],
            b"",
        )
        .json();
    let hot_uuid = hot["plugins"]["discovery"]["upnpUuid"]
        .as_str()
        .unwrap()
        .to_string();
    assert_ne!(hot_uuid, uuid);
    let connection = farm.call(
        "GET",
        &format!("{path}api/connection"),
        &[("X-Api-Key", &key)],
        b"",
    );
    assert_eq!(connection.status, 200, "{}", connection.text());

    // Stable across a restart.
    farm.daemon.kill9();
    farm.daemon = Daemon::start(&root.join("crispen.toml"), &root.join("daemon2.log"));
    farm.log = root.join("daemon2.log");
    farm.addr = common::daemon::http_address(&farm.log);
    let again = ha_step(&farm, "discovery", path, &key);
    assert_eq!(
        again["uuid"],
        uuid.as_str(),
        "the unique id changed across a restart"
    );

    // Idle: the coordinator's poll answers, no job.
    let idle = ha_step(&farm, "poll", path, &key);
    assert_eq!(idle["printing"], false, "{idle}");

    // A real print on beta: the polls show it.
    let (ct, body) = form(
        &[("file", "ha_print.gcode"), ("print", "true")],
        slow_gcode().as_bytes(),
    );
    let a = farm.call(
        "POST",
        &format!("{path}api/files/local"),
        &[("X-Api-Key", KEY), ("Content-Type", &ct)],
        &body,
    );
    assert_eq!(a.status, 201, "{}", a.text());
    let started = Instant::now();
    let shown = loop {
        let p = ha_step(&farm, "poll", path, &key);
        let hot_c = p["temps"]["tool0"][0].as_f64().unwrap_or(0.0);
        if p["printing"] == true && p["completion"].as_f64().unwrap_or(0.0) > 0.0 && hot_c > 100.0 {
            break p;
        }
        assert!(
            started.elapsed() < Duration::from_secs(90),
            "never seen printing: {p}"
        );
        std::thread::sleep(Duration::from_millis(300));
    };
    assert_eq!(shown["name"], "ha_print.gcode", "{shown}");
    assert_eq!(shown["state"], "Printing", "{shown}");
    assert_eq!(shown["text"], "Printing", "{shown}");
    assert_eq!(shown["bed"], true, "{shown}");

    let beta = |s: &Value| {
        common::printer(s, "beta")["state"]
            .as_str()
            .unwrap_or("")
            .to_string()
    };
    // A key without control: the button's press is refused with the way to give it.
    let weak = ha_key(&farm, path, "Home Assistant (no control)", &[]);
    let refused = ha_step(&farm, "pause", path, &weak);
    assert!(refused["error"].is_string(), "{refused}");
    let a = farm.call(
        "POST",
        &format!("{path}api/job"),
        &[("X-Api-Key", &weak), ("Content-Type", "application/json")],
        br#"{"command": "pause", "action": "pause"}"#,
    );
    assert_eq!(a.status, 409, "{}", a.text());
    assert!(a.error().contains("--control"), "{}", a.text());
    assert_eq!(beta(&farm.status()), "printing");

    // Pause, Resume, Stop.
    let p = ha_step(&farm, "pause", path, &key);
    assert_eq!(p["sent"], true, "{p}");
    farm.wait_for("beta paused", |s| beta(s) == "paused");
    let polled = ha_step(&farm, "poll", path, &key);
    assert_eq!(
        (polled["paused"].clone(), polled["text"].clone()),
        (json!(true), json!("Paused")),
        "{polled}"
    );
    let r = ha_step(&farm, "resume", path, &key);
    assert_eq!(r["sent"], true, "{r}");
    farm.wait_for("beta printing again", |s| beta(s) == "printing");
    let c = ha_step(&farm, "stop", path, &key);
    assert_eq!(c["sent"], true, "{c}");
    farm.wait_for("the print cancelled", |s| {
        job_by_file(s, "ha_print.gcode").is_some_and(|j| j["state"] == "cancelled")
    });
    let metrics = farm
        .call("GET", "/metrics", &[("X-Api-Key", KEY)], b"")
        .text();
    for line in [
        r#"crispen_octoprint_control_total{folder="other",action="pause",result="done"} 1"#,
        r#"crispen_octoprint_control_total{folder="other",action="pause",result="refused"} 2"#,
        r#"crispen_octoprint_control_total{folder="other",action="resume",result="done"} 1"#,
        r#"crispen_octoprint_control_total{folder="other",action="cancel",result="done"} 1"#,
    ] {
        assert!(metrics.contains(line), "{line} not in\n{metrics}");
    }
    let log = std::fs::read_to_string(&farm.log).unwrap_or_default();
    assert!(
        log.contains("octoprint: job command") && log.contains("Home Assistant"),
        "{log}"
    );
    // Nothing of the host's to stop, and nothing to start: refused, not a 404.
    let a = farm.call(
        "POST",
        &format!("{path}/api/system/commands/core/restart"),
        &[("X-Api-Key", &key)],
        b"",
    );
    assert_eq!(a.status, 409, "{}", a.text());
    let a = farm.call(
        "POST",
        &format!("{path}api/job"),
        &[("X-Api-Key", &key), ("Content-Type", "application/json")],
        br#"{"command": "start"}"#,
    );
    assert_eq!(a.status, 409, "{}", a.text());
}

/// Cura's "Upload" and then its select-and-print on the upload's `Location` with no wait
/// between them, as a client that does not wait sends them, 100 times in a row: each
/// command comes before the hot folder has taken its file, and every job prints. Four
/// fast simulated printers print them; the test clears their beds as an operator would.
#[test]
fn cura_select_and_print_sent_at_once_prints_every_time() {
    const N: usize = 100;
    let tmp = tempfile::tempdir().unwrap();
    let root = tmp.path();
    prepare(root, "default_folder = \"hot\"\nannounce = false\n");
    let mut config = std::fs::read_to_string(root.join("crispen.toml"))
        .unwrap()
        .replace(
            "printers = [\"alpha\"]",
            "printers = [\"alpha\", \"gamma\", \"delta\", \"epsilon\"]",
        );
    for name in ["gamma", "delta", "epsilon"] {
        config.push_str(&format!(
            "[[printer]]\nname = \"{name}\"\nfirmware = \"marlin2\"\n\
             [printer.simulate]\ntime_scale = 0.0\n"
        ));
    }
    std::fs::write(root.join("crispen.toml"), config).unwrap();
    let farm = Farm::started(root);
    let (key, _) = allowed_key(&farm, "/octoprint/hot/", "Cura", "");
    let k = ("X-Api-Key", key.as_str());
    let names: Vec<String> = (0..N).map(|i| format!("cura_fast_{i}.gcode")).collect();
    for name in &names {
        let (ct, body) = form(&[("path", ""), ("file", name)], GCODE.as_bytes());
        let a = farm.call(
            "POST",
            "/octoprint/hot/api/files/local",
            &[k, ("Content-Type", &ct)],
            &body,
        );
        assert_eq!(a.status, 201, "{name}: {}", a.text());
        assert_eq!(a.json()["effectivePrint"], false);
        let at = path_of(&a.header("location").unwrap());
        let a = farm.call(
            "POST",
            &at,
            &[k, ("Content-Type", "application/json")],
            br#"{"command": "select", "print": true}"#,
        );
        assert_eq!(a.status, 204, "{name}: {}", a.text());
    }
    let started = Instant::now();
    loop {
        let s = farm.status();
        for p in s["printers"].as_array().unwrap() {
            if p["state"] == "bed_not_cleared" {
                let name = p["name"].as_str().unwrap();
                farm.call(
                    "POST",
                    &format!("/api/v1/printers/{name}/clear"),
                    &[("X-Api-Key", KEY)],
                    b"",
                );
            }
        }
        let done = names
            .iter()
            .filter(|n| job_by_file(&s, n).is_some_and(|j| j["state"] == "done"))
            .count();
        let bad: Vec<&String> = names
            .iter()
            .filter(|n| {
                job_by_file(&s, n)
                    .is_some_and(|j| j["state"] == "failed" || j["state"] == "cancelled")
            })
            .collect();
        assert!(bad.is_empty(), "{bad:?} did not print: {s:#}");
        if done == N {
            break;
        }
        assert!(
            started.elapsed() < Duration::from_secs(400),
            "{done} of {N} printed; status: {s:#}\nlog:\n{}",
            std::fs::read_to_string(&farm.log).unwrap_or_default()
        );
        std::thread::sleep(Duration::from_millis(100));
    }
}
