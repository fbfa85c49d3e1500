//! The printers' cameras against a real camera server (ffmpeg's moving test pattern, see
//! `common::camera`) and the real daemon: a print on a simulated printer ends with its
//! snapshots and a timelapse of one frame per layer (counted by ffprobe), the pictures are
//! real JPEGs of the pattern cut and turned as configured, cameras that hang, lie, send
//! too much or never a boundary change nothing about the prints but their state, and the
//! dashboard shows the frames in a real browser.

use crate::common;
use crate::http::Browser;
use common::camera::{TestCamera, HEIGHT, WIDTH};
use common::daemon::{Daemon, Killed};
use common::http::{request, Answer};
use common::job_by_file;
use crispen::camera::mjpeg::Part;
use serde_json::Value;
use std::path::Path;
use std::process::{Command, Stdio};
use std::time::{Duration, Instant};

const LAYERS: usize = 6;
const KEY: &str = "camera-test-key-0123456789";

/// A small pre-sliced job of `LAYERS` layers (PrusaSlicer's layer comments), a square wall
/// each, about 1.5 s a side at real speed.
fn layered_gcode() -> String {
    layered_gcode_of(LAYERS)
}

fn layered_gcode_of(layers: usize) -> String {
    let mut g = String::from(
        "; a square wall, layer by layer\nM140 S60\nM104 S200\nM190 S60\nM109 S200\nG28\nG92 E0\n",
    );
    let mut e = 0.0;
    for layer in 0..layers {
        let z = 0.2 * (layer + 1) as f64;
        g += &format!(";LAYER_CHANGE\n;Z:{z:.1}\nG1 Z{z:.1} F600\nG1 X40 Y40 F6000\n");
        for (x, y) in [(70, 40), (70, 70), (40, 70), (40, 40)] {
            e += 1.0;
            g += &format!("G1 X{x} Y{y} E{e:.1} F1200\n");
        }
    }
    g += "M104 S0\nM140 S0\nM84\n";
    g
}

fn get(addr: &str, path: &str) -> Answer {
    request(addr, "GET", path, &[], b"")
}

fn decode(jpeg: &[u8]) -> image::RgbImage {
    image::load_from_memory_with_format(jpeg, image::ImageFormat::Jpeg)
        .expect("a JPEG")
        .to_rgb8()
}

/// A stream's part that must be a whole frame.
fn whole(part: Result<Part, crispen::camera::fetch::FetchError>) -> Vec<u8> {
    match part {
        Ok(Part::Frame(jpeg)) => jpeg,
        other => panic!("not a whole frame: {other:?}"),
    }
}

/// Frames and size of a video, by ffprobe.
fn probe(video: &Path) -> (u64, u32, u32) {
    let out = Command::new("ffprobe")
        .args(["-v", "error", "-count_frames", "-select_streams", "v:0"])
        .args([
            "-show_entries",
            "stream=nb_read_frames,width,height,codec_name",
        ])
        .args(["-of", "json"])
        .arg(video)
        .output()
        .expect("ffprobe");
    let v: Value = serde_json::from_slice(&out.stdout).unwrap();
    let s = &v["streams"][0];
    assert_eq!(s["codec_name"], "h264", "{v}");
    (
        s["nb_read_frames"].as_str().unwrap().parse().unwrap(),
        s["width"].as_u64().unwrap() as u32,
        s["height"].as_u64().unwrap() as u32,
    )
}

/// ffmpeg's own MJPEG server (`-f mpjpeg -listen 1`), read by crispen's stream reader: each
/// frame a whole JPEG of the pattern, and the pattern moves.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn ffmpegs_own_mjpeg_server_is_read_frame_by_frame() {
    let port = std::net::TcpListener::bind("127.0.0.1:0")
        .unwrap()
        .local_addr()
        .unwrap()
        .port();
    let url = format!("http://127.0.0.1:{port}/stream");
    let _ffmpeg = Killed(
        common::camera::pattern(10)
            .args(["-f", "mpjpeg", "-q:v", "5", "-listen", "1"])
            .arg(&url)
            .stdin(Stdio::null())
            .spawn()
            .expect("ffmpeg (Debian's package; scripts/setup installs it)"),
    );
    let parsed = crispen::outbound::HttpUrl::parse(&url).unwrap();
    let started = Instant::now();
    let mut stream = loop {
        match crispen::camera::fetch::Stream::open(&parsed, Duration::from_secs(5), 8 << 20).await {
            Ok(s) => break s,
            Err(e) if started.elapsed() < Duration::from_secs(20) => {
                let _ = e;
                tokio::time::sleep(Duration::from_millis(100)).await;
            }
            Err(e) => panic!("ffmpeg's server: {e}"),
        }
    };
    let mut frames = Vec::new();
    for _ in 0..5 {
        let picture = decode(&whole(stream.next().await));
        assert_eq!(picture.dimensions(), (WIDTH, HEIGHT));
        frames.push(picture);
    }
    assert!(
        frames.windows(2).all(|w| w[0] != w[1]),
        "the pattern moves from frame to frame"
    );
}

struct Farm {
    _daemon: Daemon,
    addr: String,
    log: std::path::PathBuf,
}

impl Farm {
    fn status(&self) -> Value {
        let a = get(&self.addr, "/api/v1/status");
        assert_eq!(a.status, 200, "{}", a.text());
        a.json()
    }

    fn wait_for(&self, limit: Duration, what: &str, check: impl Fn(&Value) -> bool) -> Value {
        common::http::poll_status(limit, what, &self.log, || self.status(), check)
    }
}

/// The daemon's printers, one with a working camera and five with cameras that fail in
/// each way, every printer printing the same layered job at once.
fn start_farm(root: &Path, camera: &TestCamera, hook: &common::receiver::Receiver) -> Farm {
    for folder in ["seen", "bad"] {
        std::fs::create_dir_all(root.join(folder)).unwrap();
    }
    std::fs::write(root.join("key"), format!("{KEY}\n")).unwrap();
    let dead = {
        let l = std::net::TcpListener::bind("127.0.0.1:0").unwrap();
        format!("http://{}/snapshot", l.local_addr().unwrap())
    };
    let printer = |name: &str, camera: &str| {
        format!(
            "[[printer]]\nname = \"{name}\"\nfirmware = \"marlin2\"\n\
             [printer.simulate]\ntime_scale = 0.3\n[printer.camera]\n{camera}\n"
        )
    };
    // The dashboard's public address is in the events' links: a port known beforehand.
    let port = std::net::TcpListener::bind("127.0.0.1:0")
        .unwrap()
        .local_addr()
        .unwrap()
        .port();
    let mut config = format!(
        "[spool]\ndir = \"spool\"\n[control]\nsocket = \"c.sock\"\n\
         [farm]\nsettle_s = 0.3\nmax_heating = 8\n\
         [http]\nlisten = \"127.0.0.1:{port}\"\napi_key_file = \"key\"\nread_only_without_key = true\n\
         public_url = \"http://127.0.0.1:{port}\"\n\
         [[notify]]\nname = \"hook\"\nurl = \"{}\"\nevents = [\"job_done\"]\n\
         [camera]\nrefresh_s = 1\ntimeout_s = 2\n",
        hook.url("/hook")
    );
    config += &printer(
        "seen",
        &format!(
            "stream = \"{}\"\ncrop = [40, 30, 200, 150]\nrotate = 90",
            camera.url("/stream")
        ),
    );
    for (name, path) in [("hang", "/hang"), ("lying", "/html"), ("huge", "/huge")] {
        config += &printer(name, &format!("snapshot = \"{}\"", camera.url(path)));
    }
    config += &printer(
        "noboundary",
        &format!("stream = \"{}\"", camera.url("/noboundary")),
    );
    config += &printer("dead", &format!("snapshot = \"{dead}\""));
    config += "[[folder]]\npath = \"seen\"\nheight_mm = 25\nprinters = [\"seen\"]\n\
               [[folder]]\npath = \"bad\"\nheight_mm = 25\nprinters = [\"hang\", \"lying\", \"huge\", \"noboundary\", \"dead\"]\n";
    let file = root.join("crispen.toml");
    std::fs::write(&file, config).unwrap();
    let log = root.join("daemon.log");
    let daemon = Daemon::start(&file, &log);
    let addr = common::daemon::http_address(&log);
    Farm {
        _daemon: daemon,
        addr,
        log,
    }
}

#[test]
fn prints_keep_their_snapshots_and_timelapse_and_bad_cameras_change_nothing() {
    let tmp = tempfile::tempdir().unwrap();
    let camera = TestCamera::start(10);
    let hook = common::receiver::Receiver::start();
    let farm = start_farm(tmp.path(), &camera, &hook);
    let gcode = layered_gcode();
    std::fs::write(tmp.path().join("seen/wall.gcode"), &gcode).unwrap();
    for i in 0..5 {
        std::fs::write(tmp.path().join(format!("bad/wall-{i}.gcode")), &gcode).unwrap();
    }
    let files: Vec<String> = std::iter::once("wall.gcode".to_string())
        .chain((0..5).map(|i| format!("wall-{i}.gcode")))
        .collect();
    let s = farm.wait_for(Duration::from_secs(240), "every job done", |s| {
        files
            .iter()
            .all(|f| job_by_file(s, f).is_some_and(|j| j["state"] == "done"))
    });

    // The working camera: online, its picture cut and turned (200x150 turned a quarter).
    let cams = get(&farm.addr, "/api/v1/cameras").json();
    let state_of = |p: &str| {
        cams.as_array()
            .unwrap()
            .iter()
            .find(|c| c["printer"] == p)
            .unwrap_or_else(|| panic!("no camera for {p}: {cams}"))
            .clone()
    };
    assert_eq!(state_of("seen")["state"], "online", "{cams}");
    let a = get(&farm.addr, "/api/v1/printers/seen/snapshot");
    assert_eq!(a.status, 200, "{}", a.text());
    assert_eq!(a.header("content-type").as_deref(), Some("image/jpeg"));
    assert_eq!(decode(&a.body).dimensions(), (150, 200));

    // Each failing camera is offline and says why; its printer printed all the same.
    for (printer, why) in [
        ("hang", "no answer within"),
        ("lying", "not a JPEG"),
        ("huge", "larger than"),
        ("noboundary", "no boundary within"),
        ("dead", "cannot connect"),
    ] {
        let c = state_of(printer);
        assert_eq!(c["state"], "offline", "{printer}: {c}");
        assert!(
            c["error"].as_str().is_some_and(|e| e.contains(why)),
            "{printer}: {c}"
        );
        let a = get(&farm.addr, &format!("/api/v1/printers/{printer}/snapshot"));
        assert_eq!(a.status, 503, "{printer}: {}", a.text());
    }
    let metrics = get(&farm.addr, "/metrics").text();
    assert!(
        metrics.contains("crispen_camera_online{printer=\"seen\"} 1"),
        "{metrics}"
    );
    assert!(
        metrics.contains("crispen_camera_online{printer=\"dead\"} 0"),
        "{metrics}"
    );

    // The prints took as long with a failing camera as with a working one (the same job
    // at the same time on the same simulated printers): a camera never holds a print.
    let took = |file: &str| {
        let id = job_by_file(&s, file).unwrap()["id"]
            .as_str()
            .unwrap()
            .to_string();
        let j = get(&farm.addr, &format!("/api/v1/jobs/{id}")).json();
        (
            id,
            j["job"]["print_report"]["duration_s"].as_f64().unwrap(),
            j,
        )
    };
    let (seen_id, seen_took, _) = took("wall.gcode");
    for i in 0..5 {
        let (_, t, j) = took(&format!("wall-{i}.gcode"));
        assert!(
            t < seen_took * 1.5 + 2.0,
            "{t} s with a failing camera, {seen_took} s with a working one"
        );
        assert!(
            j["camera"].is_null()
                || j["camera"]["snapshots"]
                    .as_array()
                    .is_some_and(|s| s.is_empty()),
            "no pictures from a failing camera: {}",
            j["camera"]
        );
    }

    // The job with the working camera: its snapshots in order, real pictures of the
    // pattern, and a timelapse of one frame per layer (encoded once the print is over).
    let started = Instant::now();
    let seen_job = loop {
        let j = get(&farm.addr, &format!("/api/v1/jobs/{seen_id}")).json();
        let c = &j["camera"];
        if !c["timelapse"].is_null() || !c["timelapse_error"].is_null() {
            break j;
        }
        assert!(
            started.elapsed() < Duration::from_secs(60),
            "no timelapse: {c}\n{}",
            std::fs::read_to_string(&farm.log).unwrap_or_default()
        );
        std::thread::sleep(Duration::from_millis(200));
    };
    let cam = &seen_job["camera"];
    let names: Vec<&str> = cam["snapshots"]
        .as_array()
        .unwrap_or_else(|| panic!("no camera section: {seen_job:#}"))
        .iter()
        .map(|s| s["name"].as_str().unwrap())
        .collect();
    assert_eq!(names, ["start", "first-layer", "end"], "{cam}");
    let times: Vec<f64> = cam["snapshots"]
        .as_array()
        .unwrap()
        .iter()
        .map(|s| s["at"].as_f64().unwrap())
        .collect();
    assert!(
        times.windows(2).all(|w| w[0] < w[1]),
        "taken in order: {times:?}"
    );
    let mut pictures = Vec::new();
    for s in cam["snapshots"].as_array().unwrap() {
        let a = get(
            &farm.addr,
            &format!(
                "/api/v1/jobs/{seen_id}/camera/{}",
                s["file"].as_str().unwrap()
            ),
        );
        assert_eq!(a.status, 200, "{}", a.text());
        let p = decode(&a.body);
        assert_eq!(p.dimensions(), (150, 200));
        pictures.push(p);
    }
    assert!(
        pictures.windows(2).all(|w| w[0] != w[1]),
        "the pattern moved between snapshots"
    );
    assert_eq!(cam["timelapse"]["frames"], LAYERS, "{cam}");
    let video = tmp
        .path()
        .join("spool/camera")
        .join(&seen_id)
        .join("timelapse.mp4");
    let (frames, w, h) = probe(&video);
    assert_eq!((frames, w, h), (LAYERS as u64, 150, 200));
    assert_eq!(
        cam["timelapse"]["bytes"].as_u64(),
        Some(std::fs::metadata(&video).unwrap().len())
    );
    eprintln!(
        "FIGURES timelapse of a {LAYERS}-layer print: {frames} frames, {} bytes",
        cam["timelapse"]["bytes"]
    );
    // The "done" notification carries the print's last picture, which crispen serves.
    let taken = hook.wait_taken(
        Duration::from_secs(30),
        "the done event of wall.gcode",
        |t| t.iter().any(|r| r.json()["job"]["file"] == "wall.gcode"),
        String::new,
    );
    let event = taken
        .iter()
        .map(|r| r.json())
        .find(|e| e["job"]["file"] == "wall.gcode")
        .unwrap();
    let link = format!("http://{}/api/v1/jobs/{seen_id}/camera/end.jpg", farm.addr);
    assert_eq!(event["snapshot"], link.as_str(), "{event}");
    let a = get(
        &farm.addr,
        link.strip_prefix(&format!("http://{}", farm.addr)).unwrap(),
    );
    assert_eq!(decode(&a.body).dimensions(), (150, 200));
    let blind = taken
        .iter()
        .map(|r| r.json())
        .find(|e| e["job"]["file"] == "wall-0.gcode");
    if let Some(e) = blind {
        // A failing camera took no picture, but its printer is one with a camera: the link
        // is there and answers 404 until a picture exists (never another job's).
        let path = e["snapshot"]
            .as_str()
            .unwrap()
            .split_once("/api/")
            .unwrap()
            .1;
        assert_eq!(get(&farm.addr, &format!("/api/{path}")).status, 404);
    }

    // Only the files the manifest lists are served.
    for other in [
        "camera.json",
        "..%2Fjob.json",
        "frames",
        "timelapse.partial.mp4",
    ] {
        let a = get(
            &farm.addr,
            &format!("/api/v1/jobs/{seen_id}/camera/{other}"),
        );
        assert_eq!(a.status, 404, "{other}: {}", a.text());
    }

    // Home Assistant's camera entity through the folder's OctoPrint instance: its webcam is
    // crispen's view of the printer, a stream, and a still where it asks for one.
    let settings = request(
        &farm.addr,
        "GET",
        "/octoprint/seen/api/settings",
        &[("X-Api-Key", KEY)],
        b"",
    )
    .json();
    let webcam = &settings["webcam"];
    assert_eq!(webcam["webcamEnabled"], true, "{webcam}");
    let stream_url = webcam["streamUrl"].as_str().unwrap().to_string();
    assert_eq!(
        stream_url,
        format!("http://{}/api/v1/printers/seen/stream", farm.addr)
    );
    let still = get(&farm.addr, "/api/v1/printers/seen/stream?action=snapshot");
    assert_eq!(decode(&still.body).dimensions(), (150, 200));
    let bad = request(
        &farm.addr,
        "GET",
        "/octoprint/bad/api/settings",
        &[("X-Api-Key", KEY)],
        b"",
    )
    .json();
    assert_eq!(
        bad["webcam"]["streamUrl"],
        format!("http://{}/api/v1/printers/hang/stream", farm.addr),
        "the folder's first printer with a camera"
    );
    let frames = tokio::runtime::Runtime::new().unwrap().block_on(async {
        let url = crispen::outbound::HttpUrl::parse(&stream_url).unwrap();
        let mut s = crispen::camera::fetch::Stream::open(&url, Duration::from_secs(5), 8 << 20)
            .await
            .expect("crispen's own stream");
        let mut frames = Vec::new();
        for _ in 0..2 {
            frames.push(decode(&whole(s.next().await)));
        }
        frames
    });
    assert!(frames.iter().all(|f| f.dimensions() == (150, 200)));
    assert_ne!(frames[0], frames[1], "a new part for a new frame");

    // A print stopped half way keeps the picture of its failure and the frames before it.
    let a = request(
        &farm.addr,
        "POST",
        "/api/v1/printers/seen/clear",
        &[("X-Api-Key", KEY)],
        b"",
    );
    assert_eq!(a.status, 200, "{}", a.text());
    std::fs::write(tmp.path().join("seen/long.gcode"), layered_gcode_of(40)).unwrap();
    let s = farm.wait_for(
        Duration::from_secs(120),
        "the long job a few layers in",
        |s| {
            job_by_file(s, "long.gcode").is_some_and(|j| j["state"] == "printing")
                && common::printer(s, "seen")["progress"]["lines_acked"].as_u64() > Some(40)
        },
    );
    let long = job_by_file(&s, "long.gcode").unwrap()["id"]
        .as_str()
        .unwrap()
        .to_string();
    std::thread::sleep(Duration::from_secs(4));
    let a = request(
        &farm.addr,
        "POST",
        &format!("/api/v1/jobs/{long}/cancel"),
        &[("X-Api-Key", KEY)],
        b"",
    );
    assert!(a.status < 300, "{}", a.text());
    let started = Instant::now();
    let names = loop {
        let j = get(&farm.addr, &format!("/api/v1/jobs/{long}")).json();
        let names: Vec<String> = j["camera"]["snapshots"]
            .as_array()
            .map(|a| {
                a.iter()
                    .map(|s| s["name"].as_str().unwrap().to_string())
                    .collect()
            })
            .unwrap_or_default();
        if names.iter().any(|n| n == "failure") {
            break names;
        }
        assert!(
            started.elapsed() < Duration::from_secs(60),
            "no failure snapshot: {j:#}"
        );
        std::thread::sleep(Duration::from_millis(200));
    };
    assert_eq!(
        names.first().map(String::as_str),
        Some("start"),
        "{names:?}"
    );
    assert!(names.iter().any(|n| n == "before-failure-1"), "{names:?}");
    assert_eq!(
        names.last().map(String::as_str),
        Some("failure"),
        "{names:?}"
    );

    // The dashboard: the working camera's live picture on its tile, a failing camera's
    // state on its own; the job page with its snapshots and a timelapse that plays.
    let browser = Browser::start(&tmp.path().join("chromium-profile"));
    browser.go(&format!("http://{}/", farm.addr));
    browser.wait_until(
        Duration::from_secs(30),
        "the camera picture on seen's tile and dead's camera state",
        "const img = document.querySelector('[data-printer=\"seen\"] img.cam');
         const dead = document.querySelector('[data-printer=\"dead\"] .camstate');
         return (!!img && img.naturalWidth === 150 && img.naturalHeight === 200
           && !!dead && /offline/.test(dead.textContent)) || [!!img && img.naturalWidth, dead && dead.textContent].join(' ');",
    );
    let shots = Path::new(env!("CARGO_TARGET_TMPDIR"));
    browser.screenshot(&shots.join("dashboard-cameras.png"));
    // The picture on the tile follows the camera.
    let first = browser.exec(
        "return document.querySelector('[data-printer=\"seen\"] img.cam').src",
        serde_json::json!([]),
    );
    browser.wait_until(
        Duration::from_secs(20),
        "a newer frame on seen's tile",
        &format!(
            "return document.querySelector('[data-printer=\"seen\"] img.cam').src !== {first}"
        ),
    );
    browser.go(&format!("http://{}/#job/{seen_id}", farm.addr));
    browser.wait_until(
        Duration::from_secs(30),
        "the job page's snapshots and timelapse",
        "const imgs = document.querySelectorAll('#jobpage .snapshots img');
         const v = document.querySelector('#jobpage video');
         return (imgs.length === 3 && Array.from(imgs).every(i => i.naturalWidth === 150)
           && !!v && v.readyState >= 1 && v.videoWidth === 150 && v.duration > 0)
           || [imgs.length, v && v.readyState, v && v.videoWidth, v && v.duration].join(' ');",
    );
    browser.screenshot(&shots.join("dashboard-job-camera.png"));
    browser.go(&format!("http://{}/#camera/seen", farm.addr));
    browser.wait_until(
        Duration::from_secs(20),
        "the live view",
        "const img = document.querySelector('#live');
         return !!img && img.naturalWidth === 150 && /frame of/.test(document.querySelector('#livestate').textContent);",
    );
}

/// A daemon with one printer per `(name, camera table)`, each fed by a folder of its name.
fn start_printers(root: &Path, printers: &[(&str, String)]) -> Farm {
    let mut config = String::from(
        "[spool]\ndir = \"spool\"\n[control]\nsocket = \"c.sock\"\n\
         [farm]\nsettle_s = 0.3\nmax_heating = 8\n\
         [http]\nlisten = \"127.0.0.1:0\"\napi_key_file = \"key\"\nread_only_without_key = true\n\
         [camera]\nrefresh_s = 1\ntimeout_s = 2\n",
    );
    std::fs::write(root.join("key"), format!("{KEY}\n")).unwrap();
    for (name, camera) in printers {
        std::fs::create_dir_all(root.join(name)).unwrap();
        config += &format!(
            "[[printer]]\nname = \"{name}\"\nfirmware = \"marlin2\"\n\
             [printer.simulate]\ntime_scale = 0.3\n[printer.camera]\n{camera}\n\
             [[folder]]\npath = \"{name}\"\nheight_mm = 25\nprinters = [\"{name}\"]\n"
        );
    }
    let file = root.join("crispen.toml");
    std::fs::write(&file, config).unwrap();
    let log = root.join("daemon.log");
    let daemon = Daemon::start(&file, &log);
    let addr = common::daemon::http_address(&log);
    Farm {
        _daemon: daemon,
        addr,
        log,
    }
}

impl Farm {
    fn camera(&self, printer: &str) -> Value {
        let cams = get(&self.addr, "/api/v1/cameras").json();
        cams.as_array()
            .unwrap()
            .iter()
            .find(|c| c["printer"] == printer)
            .unwrap_or_else(|| panic!("no camera for {printer}: {cams}"))
            .clone()
    }

    fn wait_camera(&self, printer: &str, what: &str, check: impl Fn(&Value) -> bool) -> Value {
        common::http::poll_status(
            Duration::from_secs(60),
            what,
            &self.log,
            || self.camera(printer),
            check,
        )
    }

    /// The job's camera section once the recorder has said its last word on it: its
    /// timelapse made or given up, or every layer said to have no frame (then there is no
    /// timelapse to make).
    fn finished_camera(&self, job: &str) -> Value {
        common::http::poll_status(
            Duration::from_secs(60),
            "the job's timelapse made or given up, or every layer said to have no frame",
            &self.log,
            || get(&self.addr, &format!("/api/v1/jobs/{job}")).json()["camera"].clone(),
            |c| {
                // With no frame at all there is no timelapse to make: the layers said
                // missing, the last one included, are the recorder's last word.
                let none_taken = c["missing"].as_array().is_some_and(|m| {
                    m.len() == 1 && m[0]["first"] == 1 && m[0]["last"] == c["layers"]
                });
                !c["timelapse"].is_null() || !c["timelapse_error"].is_null() || none_taken
            },
        )
    }
}

/// A camera that dies mid-print: the timelapse is short, and the job's `camera.json` and
/// its page (in a real browser) say which layers have no frame and why (the camera went
/// offline: its stream ended, then no connection). The frames and the layers said missing
/// add up to the print's layers.
#[test]
fn a_camera_that_dies_mid_print_says_which_layers_have_no_frame() {
    const LAYERS: u64 = 12;
    let tmp = tempfile::tempdir().unwrap();
    let camera = TestCamera::start(10);
    let farm = start_printers(
        tmp.path(),
        &[("seen", format!("stream = \"{}\"", camera.url("/stream")))],
    );
    farm.wait_camera("seen", "the camera online", |c| c["state"] == "online");
    std::fs::write(
        tmp.path().join("seen/wall.gcode"),
        layered_gcode_of(LAYERS as usize),
    )
    .unwrap();
    // The first layer's frame is taken with its snapshot: then the camera dies.
    let s = farm.wait_for(Duration::from_secs(120), "the job printing", |s| {
        job_by_file(s, "wall.gcode").is_some()
    });
    let id = job_by_file(&s, "wall.gcode").unwrap()["id"]
        .as_str()
        .unwrap()
        .to_string();
    common::http::poll_status(
        Duration::from_secs(120),
        "the first layer's snapshot",
        &farm.log,
        || get(&farm.addr, &format!("/api/v1/jobs/{id}")).json(),
        |j| {
            j["camera"]["snapshots"]
                .as_array()
                .is_some_and(|s| s.iter().any(|s| s["name"] == "first-layer"))
        },
    );
    drop(camera);
    farm.wait_camera("seen", "the camera offline", |c| c["state"] == "offline");
    let j = get(&farm.addr, &format!("/api/v1/jobs/{id}")).json();
    assert_eq!(
        j["job"]["state"], "printing",
        "the camera must die mid-print for this test: {j:#}"
    );
    farm.wait_for(Duration::from_secs(240), "the job done", |s| {
        job_by_file(s, "wall.gcode").is_some_and(|j| j["state"] == "done")
    });
    let cam = farm.finished_camera(&id);
    assert_eq!(cam["layers"], LAYERS, "{cam:#}");
    let missing = cam["missing"].as_array().expect("layers without a frame");
    let mut said = 0;
    let mut next = None;
    for m in missing {
        let (first, last) = (m["first"].as_u64().unwrap(), m["last"].as_u64().unwrap());
        assert!(first <= last && next.is_none_or(|n| first >= n), "{cam:#}");
        next = Some(last + 1);
        said += last - first + 1;
        assert_eq!(m["why"]["kind"], "offline", "{cam:#}");
        assert!(
            ["closed", "connect"].contains(&m["why"]["fault"]["kind"].as_str().unwrap_or("")),
            "{cam:#}"
        );
        assert!(m["why"]["since"].as_f64().is_some() && m["at"].as_f64().is_some());
    }
    assert!(missing[0]["first"].as_u64() >= Some(2), "{cam:#}");
    assert_eq!(
        next,
        Some(LAYERS + 1),
        "the last layers have no frame: {cam:#}"
    );
    let frames = cam["timelapse"]["frames"].as_u64().expect("a timelapse");
    assert_eq!(frames + said, LAYERS, "{cam:#}");
    let video = tmp
        .path()
        .join("spool/camera")
        .join(&id)
        .join("timelapse.mp4");
    assert_eq!(probe(&video).0, frames);
    // camera.json itself, as the recorder wrote it.
    let manifest: Value = serde_json::from_slice(
        &std::fs::read(
            tmp.path()
                .join("spool/camera")
                .join(&id)
                .join("camera.json"),
        )
        .unwrap(),
    )
    .unwrap();
    assert_eq!(manifest["missing"], cam["missing"]);
    eprintln!(
        "FIGURES a camera dead mid-print: {frames} frames of {LAYERS} layers, missing {missing:?}"
    );

    // The job page says it.
    let browser = Browser::start(&tmp.path().join("chromium-profile"));
    browser.go(&format!("http://{}/#job/{id}", farm.addr));
    let first = missing[0]["first"].as_u64().unwrap();
    let expected = if missing.len() == 1 && first < LAYERS {
        format!("No timelapse frame of layers {first}–{LAYERS} of {LAYERS}: the camera was offline")
    } else {
        "No timelapse frame of layer".to_string()
    };
    browser.wait_until(
        Duration::from_secs(30),
        "the job page's missing layers",
        &format!(
            "const li = document.querySelectorAll('#jobpage ul.missing li');
             const t = Array.from(li).map(l => l.textContent);
             return (li.length === {} && t[0].startsWith({expected:?})
               && t.every(x => /offline since .*\\((the stream ended|cannot connect)\\)/.test(x))) || t.join(' | ');",
            missing.len()
        ),
    );
    browser.screenshot(&Path::new(env!("CARGO_TARGET_TMPDIR")).join("job-camera-missing.png"));
}

/// Cameras whose MJPEG parts declare a `Content-Length` shorter than the JPEG they carry:
/// every part (the camera is offline, says the frames are cut, gives no picture, and the
/// job's layers have no frame for that reason), or every other one (the cut ones are
/// failures; every picture kept is a whole JPEG that decodes strictly).
#[test]
fn cut_frames_are_failures_and_never_a_jobs_pictures() {
    const LAYERS: u64 = 3;
    let tmp = tempfile::tempdir().unwrap();
    let camera = TestCamera::start(10);
    let farm = start_printers(
        tmp.path(),
        &[
            ("cut", format!("stream = \"{}\"", camera.url("/cut"))),
            (
                "sometimes",
                format!("stream = \"{}\"", camera.url("/sometimes-cut")),
            ),
        ],
    );
    farm.wait_camera("cut", "the cut camera failing", |c| {
        c["failures"].as_u64() > Some(2)
    });
    farm.wait_camera(
        "sometimes",
        "the other camera with frames and failures",
        |c| c["frames"].as_u64() > Some(0) && c["failures"].as_u64() > Some(0),
    );
    for printer in ["cut", "sometimes"] {
        std::fs::write(
            tmp.path().join(printer).join("wall.gcode"),
            layered_gcode_of(LAYERS as usize),
        )
        .unwrap();
    }
    let s = farm.wait_for(Duration::from_secs(240), "both jobs done", |s| {
        s["jobs"]
            .as_array()
            .is_some_and(|j| j.len() == 2 && j.iter().all(|j| j["state"] == "done"))
    });
    let job_of = |printer: &str| {
        s["jobs"]
            .as_array()
            .unwrap()
            .iter()
            .find(|j| j["printer"] == printer)
            .unwrap_or_else(|| panic!("no job on {printer}: {s:#}"))["id"]
            .as_str()
            .unwrap()
            .to_string()
    };

    let cut = farm.camera("cut");
    assert_eq!(cut["state"], "offline", "{cut}");
    assert_eq!(cut["frames"], 0, "{cut}");
    assert!(
        cut["error"]
            .as_str()
            .is_some_and(|e| e.contains("cut short")),
        "{cut}"
    );
    let a = get(&farm.addr, "/api/v1/printers/cut/snapshot");
    assert_eq!(a.status, 503, "{}", a.text());
    let cam = farm.finished_camera(&job_of("cut"));
    assert!(
        cam["snapshots"].as_array().is_some_and(|s| s.is_empty()),
        "{cam:#}"
    );
    assert!(cam["timelapse"].is_null(), "{cam:#}");
    let missing = cam["missing"].as_array().expect("layers without a frame");
    assert_eq!(missing.len(), 1, "{cam:#}");
    assert_eq!(
        (missing[0]["first"].as_u64(), missing[0]["last"].as_u64()),
        (Some(1), Some(LAYERS)),
        "{cam:#}"
    );
    assert_eq!(missing[0]["why"]["kind"], "offline", "{cam:#}");
    assert_eq!(missing[0]["why"]["fault"]["kind"], "refused", "{cam:#}");
    assert_eq!(
        missing[0]["why"]["fault"]["frame"]["kind"], "cut",
        "{cam:#}"
    );

    // Every picture of the other camera is a whole JPEG, strictly decoded.
    let whole = |what: &str, jpeg: &[u8]| {
        assert_eq!(
            crispen::camera::mjpeg::check_jpeg(jpeg),
            Ok(jpeg.len()),
            "{what}"
        );
        assert_eq!(crispen::camera::picture::decodes(jpeg), Ok(()), "{what}");
        assert_eq!(decode(jpeg).dimensions(), (WIDTH, HEIGHT), "{what}");
    };
    let sometimes = farm.camera("sometimes");
    assert!(sometimes["frames"].as_u64() > Some(0), "{sometimes}");
    assert!(sometimes["failures"].as_u64() > Some(0), "{sometimes}");
    let a = get(&farm.addr, "/api/v1/printers/sometimes/snapshot");
    assert_eq!(a.status, 200, "{}", a.text());
    whole("the latest picture", &a.body);
    let id = job_of("sometimes");
    let cam = farm.finished_camera(&id);
    for s in cam["snapshots"].as_array().unwrap() {
        let file = s["file"].as_str().unwrap();
        let a = get(&farm.addr, &format!("/api/v1/jobs/{id}/camera/{file}"));
        assert_eq!(a.status, 200, "{}", a.text());
        whole(file, &a.body);
    }
}

/// A plate of two labelled parts, one cancelled mid-print: the timelapse marks where it
/// was dropped (the store's layer, and the frames taken before it), and the job's camera
/// section says so for the page.
#[test]
fn the_timelapse_marks_where_a_part_was_dropped() {
    const LAYERS: usize = 12;
    let tmp = tempfile::tempdir().unwrap();
    let camera = TestCamera::start(10);
    let farm = start_printers(
        tmp.path(),
        &[("seen", format!("stream = \"{}\"", camera.url("/stream")))],
    );
    farm.wait_camera("seen", "the camera online", |c| c["state"] == "online");
    // Two squares a layer, labelled as PrusaSlicer labels its objects.
    let mut g = String::from("M140 S60\nM104 S200\nM190 S60\nM109 S200\nG28\nG92 E0\n");
    let mut e = 0.0;
    for layer in 0..LAYERS {
        let z = 0.2 * (layer + 1) as f64;
        g += &format!(";LAYER_CHANGE\n;Z:{z:.1}\nG1 Z{z:.1} F600\n");
        for (name, x0) in [("a", 40), ("b", 100)] {
            g += &format!("; printing object {name}\nG1 X{x0} Y40 F6000\n");
            for (x, y) in [(x0 + 30, 40), (x0 + 30, 70), (x0, 70), (x0, 40)] {
                e += 1.0;
                g += &format!("G1 X{x} Y{y} E{e:.1} F1200\n");
            }
            g += &format!("; stop printing object {name}\n");
        }
    }
    g += "M104 S0\nM140 S0\nM84\n";
    std::fs::write(tmp.path().join("seen/plate.gcode"), g).unwrap();
    let s = farm.wait_for(Duration::from_secs(120), "a few layers printed", |s| {
        job_by_file(s, "plate.gcode").is_some_and(|j| j["state"] == "printing")
            && common::printer(s, "seen")["progress"]["lines_acked"].as_u64() > Some(60)
    });
    let id = job_by_file(&s, "plate.gcode").unwrap()["id"]
        .as_str()
        .unwrap()
        .to_string();
    let a = request(
        &farm.addr,
        "POST",
        &format!("/api/v1/jobs/{id}/parts/b/cancel"),
        &[("X-Api-Key", KEY)],
        b"",
    );
    assert!(a.status < 300, "{}", a.text());
    farm.wait_for(Duration::from_secs(240), "the job done", |s| {
        job_by_file(s, "plate.gcode").is_some_and(|j| j["state"] == "done")
    });
    let cam = farm.finished_camera(&id);
    let job = get(&farm.addr, &format!("/api/v1/jobs/{id}")).json()["job"].clone();
    let layer = job["parts_cancelled"][0]["dropped"]["layer"].clone();
    assert!(layer.as_u64().is_some_and(|l| l > 1), "{job:#}");
    let dropped = cam["dropped"].as_array().expect("a mark");
    assert_eq!(dropped.len(), 1, "{cam:#}");
    let mark = &dropped[0];
    assert_eq!(mark["part"], "b", "{cam:#}");
    assert_eq!(mark["layer"], layer, "{cam:#}");
    // One frame a layer: the frames before it are those of the layers before the one it
    // was dropped at, less any the camera gave none of; at 10 frames a second.
    let layer = layer.as_u64().unwrap();
    let missed: u64 = cam["missing"].as_array().map_or(0, |runs| {
        runs.iter()
            .map(|m| {
                let (first, last) = (m["first"].as_u64().unwrap(), m["last"].as_u64().unwrap());
                (last.min(layer - 1) + 1).saturating_sub(first)
            })
            .sum()
    });
    let frame = mark["frame"].as_u64().unwrap();
    assert_eq!(frame, layer - 1 - missed, "{cam:#}");
    assert!(
        frame <= cam["timelapse"]["frames"].as_u64().unwrap(),
        "{cam:#}"
    );
    assert_eq!(
        mark["video_s"].as_f64(),
        Some(frame as f64 / 10.0),
        "{cam:#}"
    );
}
