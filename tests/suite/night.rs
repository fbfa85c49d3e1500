//! A night of printing with nobody there: the real daemon, four simulated printers whose
//! beds clear themselves (an eject sequence, then the camera's check against the picture
//! of the empty bed), a camera over each bed that shows the part a print leaves and the
//! bed the eject sequence empties (`common::bed::BedCamera`, following each simulator's
//! record), and a dozen jobs. Every job prints once without a person; each eject runs
//! once after each good print and is followed by a check; a printer whose eject does not
//! remove its part stops with the marked picture and a `bed_not_clear` notification
//! while the others go on; a failed print waits for a person (no eject); and a `kill -9`
//! in the middle of an eject and in the middle of a check prints nothing twice: the
//! eject is never run again (a person looks), the check is made again.

use crate::common;
use common::bed::{prints_and_ejects, BedCamera};
use common::daemon::{ctl, spawn_sim, wait_for, Daemon, Killed};
use common::http::request;
use common::printer;
use serde_json::Value;
use std::path::{Path, PathBuf};
use std::process::Command;
use std::time::Duration;

const KEY: &str = "night-test-key-0123456789";
const JOBS: usize = 12;

/// A small print: heat, six layers of a square, the marker the camera and the test
/// read, cool down. 1.2 mm tall.
fn job(name: &str) -> String {
    job_of(name, 6)
}

/// A print of `layers` layers of 0.2 mm.
fn job_of(name: &str, layers: u32) -> String {
    let mut g = String::from("M140 S50\nM104 S200\nM190 S50\nM109 S200\nG28\nG92 E0\n");
    let mut e = 0.0;
    for layer in 1..=layers {
        let z = 0.2 * f64::from(layer);
        g += &format!(";LAYER_CHANGE\n;Z:{z:.1}\nG1 Z{z:.1} F600\nG1 X90 Y90 F6000\n");
        for (x, y) in [(110, 90), (110, 110), (90, 110), (90, 90)] {
            e += 0.8;
            g += &format!("G1 X{x} Y{y} E{e:.1} F1800\n");
        }
    }
    g += &format!("M117 printed {name}\nM104 S0\nM140 S0\nM84\n");
    g
}

/// A push-off in lanes across the bed. `held`: a dwell of ten (simulated) hours right
/// after its start, which only the test's `kill -9` ends: an eject caught in the middle
/// by an event (the dwell in the printer's record), not by a race with the clock.
fn eject_gcode(held: bool) -> String {
    let mut g = String::from("M117 eject start\n");
    if held {
        g += HOLD;
        g += "\n";
    }
    g += "G28\nG1 Z2 F600\n";
    for x in [20, 45, 70, 95, 120, 145, 170, 195] {
        g += &format!("G1 X{x} Y0 F6000\nG1 Y210 F1200\nG1 Y0 F6000\n");
    }
    g += "M117 ejected\n";
    g
}

const HOLD: &str = "G4 S36000";

struct Night {
    root: PathBuf,
    config: PathBuf,
    log: PathBuf,
    addr: String,
}

impl Night {
    fn status(&self) -> Value {
        wait_for(
            &self.config,
            &self.log,
            Duration::from_secs(30),
            "status",
            |_| true,
        )
    }

    fn wait(&self, limit_s: u64, what: &str, check: impl Fn(&Value) -> bool) -> Value {
        wait_for(
            &self.config,
            &self.log,
            Duration::from_secs(limit_s),
            what,
            check,
        )
    }

    fn record(&self, printer: &str) -> PathBuf {
        self.root.join(format!("{printer}.rec"))
    }

    /// A printer's gate as the spool has it on disk.
    fn gate_on_disk(&self, printer: &str) -> Value {
        let text = std::fs::read(self.root.join("spool/printers.json")).unwrap();
        let gates: Value = serde_json::from_slice(&text).unwrap();
        gates[printer].clone()
    }

    fn start(&self) -> Daemon {
        let d = Daemon::start(&self.config, &self.log);
        self.wait(30, "the printers connected", |s| {
            s["printers"]
                .as_array()
                .is_some_and(|p| p.len() == 4 && p.iter().all(|p| p["state"] != "connecting"))
        });
        d
    }

    fn get(&self, path: &str) -> common::http::Answer {
        request(&self.addr, "GET", path, &[("X-Api-Key", KEY)], b"")
    }
}

fn bed_state(s: &Value, p: &str) -> String {
    printer(s, p)["bed"]["state"]
        .as_str()
        .unwrap_or("")
        .to_string()
}

fn bed_why(s: &Value, p: &str) -> String {
    printer(s, p)["bed"]["why"]["kind"]
        .as_str()
        .unwrap_or("")
        .to_string()
}

fn state_of(s: &Value, file: &str) -> String {
    common::daemon::state_of(s, file)
}

fn drop_job(hot: &Path, name: &str, only: Option<&str>) {
    if let Some(p) = only {
        std::fs::write(
            hot.join(format!("{name}.toml")),
            format!("printer = \"{p}\"\n"),
        )
        .unwrap();
    }
    common::daemon::drop_model(hot, name, job(name).as_bytes());
}

/// A bed the machine may not clear waits for a person, with the reason: a check the
/// camera cannot make (no picture of the empty bed yet: the eject ran, the bed is not
/// called clear), and a print taller than the sequence may push off (no eject at all). A
/// person's clear takes the missing reference.
#[test]
fn a_bed_the_machine_may_not_clear_waits_for_a_person() {
    let tmp = tempfile::tempdir().unwrap();
    let root = tmp.path().to_path_buf();
    let hot = root.join("hot");
    std::fs::create_dir_all(&hot).unwrap();
    let camera = BedCamera::start();
    let record = root.join("e.rec");
    camera.add("e", &record, true);
    let config = root.join("crispen.toml");
    let log = root.join("daemon.log");
    std::fs::write(
        &config,
        format!(
            "[spool]\ndir = \"spool\"\n[control]\nsocket = \"c.sock\"\n[farm]\nsettle_s = 0.3\n\
             [camera]\nrefresh_s = 1\n\
             [[printer]]\nname = \"e\"\nfirmware = \"marlin2\"\nbed_clear = \"eject-and-check\"\n\
             [printer.simulate]\ntime_scale = 0.05\nrecord = \"{}\"\n\
             [printer.camera]\nsnapshot = \"{}\"\n\
             [printer.eject]\ngcode = \"\"\"\n{}\"\"\"\nmax_height_mm = 2\n\
             [[folder]]\npath = \"hot\"\nheight_mm = 20\nprinters = [\"e\"]\n",
            record.display(),
            camera.url("e"),
            eject_gcode(false),
        ),
    )
    .unwrap();
    let _daemon = Daemon::start(&config, &log);
    let wait = |what: &str, check: &dyn Fn(&Value) -> bool| {
        wait_for(&config, &log, Duration::from_secs(120), what, check)
    };

    common::daemon::drop_model(&hot, "low.gcode", job_of("low.gcode", 6).as_bytes());
    let s = wait("e's bed waiting: no reference to check it with", &|s| {
        bed_state(s, "e") == "waiting" && printer(s, "e")["state"] == "bed_not_cleared"
    });
    let why = &printer(&s, "e")["bed"]["why"];
    assert_eq!(why["kind"], "no_check", "{why}");
    assert_eq!(why["problem"]["kind"], "no_reference", "{why}");
    assert_eq!(
        prints_and_ejects(&record),
        (1, 1),
        "the eject ran, then no check"
    );
    let (ok, out) = ctl(&config, &["status"]);
    assert!(
        ok && out.contains("no picture of the empty bed yet"),
        "{out}"
    );

    camera.person_cleared("e");
    let (ok, out) = ctl(&config, &["clear", "e"]);
    assert!(ok && out.contains("reference"), "{out}");
    assert!(root.join("spool/bed/e/reference.jpg").is_file());

    // 3 mm tall, over the sequence's 2 mm: printed, never ejected.
    common::daemon::drop_model(&hot, "tall.gcode", job_of("tall.gcode", 15).as_bytes());
    let s = wait("e's bed waiting: the print too tall to push off", &|s| {
        state_of(s, "tall.gcode") == "done" && bed_state(s, "e") == "waiting"
    });
    let why = &printer(&s, "e")["bed"]["why"];
    assert_eq!(why["kind"], "too_tall", "{why}");
    assert!(
        (why["height_mm"].as_f64().unwrap() - 3.0).abs() < 0.01,
        "{why}"
    );
    assert_eq!(
        prints_and_ejects(&record),
        (2, 1),
        "no eject of a tall print"
    );
}

#[test]
fn a_night_of_printing_clears_its_own_beds() {
    let tmp = tempfile::tempdir().unwrap();
    let root = tmp.path().to_path_buf();
    let hot = root.join("hot");
    std::fs::create_dir_all(&hot).unwrap();
    std::fs::write(root.join("key"), format!("{KEY}\n")).unwrap();
    let camera = BedCamera::start();
    let hook = common::receiver::Receiver::start();
    // Printer d is a simulator of its own whose first job fails with a firmware error.
    let d_record = root.join("d.rec");
    let (d_sim, d_port) = spawn_sim(
        Command::new(common::daemon::BIN)
            .args(["sim", "--firmware", "marlin2", "--speed", "20"])
            .args(["--error-after", "20:Heater malfunction"])
            .arg("--record")
            .arg(&d_record),
    );
    let _d_sim = Killed(d_sim);
    let port = std::net::TcpListener::bind("127.0.0.1:0")
        .unwrap()
        .local_addr()
        .unwrap()
        .port();
    let mut config = format!(
        "[spool]\ndir = \"spool\"\n[control]\nsocket = \"c.sock\"\n\
         [farm]\nsettle_s = 0.3\nmax_heating = 4\n\
         [http]\nlisten = \"127.0.0.1:{port}\"\napi_key_file = \"key\"\n\
         public_url = \"http://127.0.0.1:{port}\"\n\
         [[notify]]\nname = \"hook\"\nurl = \"{}\"\nevents = [\"bed_not_clear\"]\n\
         [camera]\nrefresh_s = 1\ntimeout_s = 60\n",
        hook.url("/hook")
    );
    // a's sequence is a file under the config's folder, held in its first run.
    let a_eject = root.join("eject-a.gcode");
    std::fs::write(&a_eject, eject_gcode(true)).unwrap();
    let eject = eject_gcode(false);
    for name in ["a", "b", "c", "d"] {
        let record = root.join(format!("{name}.rec"));
        let port = if name == "d" {
            format!("port = \"{}\"\n", d_port.display())
        } else {
            format!(
                "[printer.simulate]\ntime_scale = 0.05\nrecord = \"{}\"\n",
                record.display()
            )
        };
        // The table order: the printer's keys, then its sub-tables.
        let (keys, sim) = port
            .split_once("[printer.simulate]")
            .map_or((port.as_str(), String::new()), |(k, s)| {
                (k, format!("[printer.simulate]{s}"))
            });
        config += &format!(
            "[[printer]]\nname = \"{name}\"\nfirmware = \"marlin2\"\nbed_clear = \"eject-and-check\"\n{keys}{sim}\
             [printer.camera]\nsnapshot = \"{}\"\n\
             [printer.eject]\n{sequence}release_bed_c = 35\nmax_height_mm = 60\n",
            camera.url(name),
            sequence = if name == "a" {
                "file = \"eject-a.gcode\"\n".to_string()
            } else {
                format!("gcode = \"\"\"\n{eject}\"\"\"\n")
            },
        );
        // c's eject "fails to remove the part": its camera keeps showing it.
        camera.add(name, &record, name != "c");
    }
    config +=
        "[[folder]]\npath = \"hot\"\nheight_mm = 20\nprinters = [\"a\", \"b\", \"c\", \"d\"]\n";
    let night = Night {
        config: root.join("crispen.toml"),
        log: root.join("daemon.log"),
        addr: format!("127.0.0.1:{port}"),
        root: root.clone(),
    };
    std::fs::write(&night.config, &config).unwrap();
    let mut daemon = night.start();

    // A person sets the farm up in the evening: each empty bed's picture is its reference.
    for p in ["a", "b", "c", "d"] {
        let (ok, out) = ctl(&night.config, &["clear", p, "--reference"]);
        assert!(ok && out.contains("reference"), "{p}: {out}");
        assert!(root.join(format!("spool/bed/{p}/reference.jpg")).is_file());
    }

    // 1. A kill -9 in the middle of an eject: a job for a alone, the daemon killed while
    //    its eject sequence runs (held in its dwell). After the restart the eject is not
    //    run again: the bed waits for a person, who clears it.
    drop_job(&hot, "part-01.gcode", Some("a"));
    night.wait(120, "a's eject sequence running", |s| {
        let p = printer(s, "a");
        p["state"] == "ejecting"
            && p["detail"].as_str() == Some("ejecting: the eject sequence is running")
    });
    night.wait(60, "a's eject in its dwell", |_| {
        common::daemon::recorded(&night.record("a"))
            .iter()
            .any(|l| l == HOLD)
    });
    daemon.kill9();
    // The operator's sequence from now on, without the hold.
    std::fs::write(&a_eject, eject_gcode(false)).unwrap();
    assert_eq!(night.gate_on_disk("a")["bed"]["state"], "ejecting");
    let ejects_begun = |p: &str| {
        std::fs::read_to_string(night.record(p))
            .unwrap_or_default()
            .lines()
            .filter(|l| l.starts_with("M117 eject start"))
            .count()
    };
    let begun = ejects_begun("a");
    assert_eq!(begun, 1);
    let mut daemon = night.start();
    let s = night.wait(30, "a's bed waiting after the interrupted eject", |s| {
        bed_state(s, "a") == "waiting" && printer(s, "a")["state"] == "bed_not_cleared"
    });
    assert_eq!(
        bed_why(&s, "a"),
        "eject_interrupted",
        "{}",
        printer(&s, "a")
    );
    assert_eq!(state_of(&s, "part-01.gcode"), "done");
    assert_eq!(ejects_begun("a"), begun, "the eject is never sent again");
    camera.person_cleared("a");
    let (ok, out) = ctl(&night.config, &["clear", "a"]);
    assert!(ok, "{out}");

    // 2. A kill -9 in the middle of a check: b's camera is held (it answers nothing), the
    //    daemon killed while the check waits for its frame (up to the camera's 60 s
    //    timeout and a few refreshes); after the restart the check is made again.
    camera.hold("b", true);
    drop_job(&hot, "part-02.gcode", Some("b"));
    night.wait(120, "b's bed being checked", |s| {
        printer(s, "b")["state"] == "checking_bed"
    });
    daemon.kill9();
    assert_eq!(night.gate_on_disk("b")["bed"]["state"], "check_due");
    camera.hold("b", false);
    let daemon = night.start();
    let s = night.wait(60, "b's bed checked clear after the restart", |s| {
        bed_state(s, "b") == "clear"
    });
    assert_eq!(
        printer(&s, "b")["bed"]["by"],
        "camera",
        "{}",
        printer(&s, "b")
    );

    // 3. The rest of the night: ten jobs for any printer.
    let names: Vec<String> = (1..=JOBS).map(|i| format!("part-{i:02}.gcode")).collect();
    for name in &names[2..] {
        drop_job(&hot, name, None);
    }
    // d's first job fails (the printer's error): its bed waits for a person, no eject.
    let s = night.wait(240, "d's failed print waiting for a person", |s| {
        names.iter().any(|n| state_of(s, n) == "failed") && bed_state(s, "d") == "waiting"
    });
    assert!(
        printer(&s, "d")["bed"]["why"].is_null(),
        "{}",
        printer(&s, "d")
    );
    assert_eq!(
        prints_and_ejects(&d_record),
        (0, 0),
        "no eject after a failed print"
    );
    let failed: Vec<&String> = names
        .iter()
        .filter(|n| state_of(&s, n) == "failed")
        .collect();
    assert_eq!(failed.len(), 1, "{s:#}");
    let (ok, out) = ctl(&night.config, &["clear", "d"]);
    assert!(ok, "{out}");
    // c's eject leaves its part on the bed: the camera finds it, c stops with the marked
    // picture, and the farm goes on.
    let s = night.wait(240, "c stopped with its bed not clear", |s| {
        bed_state(s, "c") == "waiting" && bed_why(s, "c") == "not_clear"
    });
    let check = &printer(&s, "c")["bed"]["why"]["check"];
    assert_eq!(check["verdict"]["clear"], false);
    let picture = check["picture"].as_str().expect("a marked picture");
    assert!(root.join("spool").join(picture).is_file(), "{picture}");
    let of = |r: &common::receiver::Received, p: &str| {
        let e = r.json();
        e["event"] == "bed_not_clear" && e["printer"] == p
    };
    let told = hook.wait_taken(
        Duration::from_secs(60),
        "bed_not_clear of c",
        |r| r.iter().any(|r| of(r, "c")),
        || std::fs::read_to_string(&night.log).unwrap_or_default(),
    );
    let event = told.iter().find(|r| of(r, "c")).unwrap().json();
    assert!(
        event["reason"]
            .as_str()
            .unwrap()
            .contains("% of the bed differs"),
        "{event}"
    );
    let link = event["snapshot"].as_str().expect("the picture's link");
    let path = link.split_once(&night.addr).unwrap().1;
    let a = night.get(path);
    assert_eq!(a.status, 200, "{link}: {}", a.text());
    assert_eq!(&a.body[..2], b"\xff\xd8", "a JPEG");

    // Every good job is printed, each once, by a, b and d; c keeps its first.
    night.wait(600, "every job printed", |s| {
        names.iter().filter(|n| state_of(s, n) == "done").count() == JOBS - 1
    });
    // The last prints' ejects and checks, after them.
    let s = night.wait(120, "every bed but c's clear again", |s| {
        ["a", "b", "d"].iter().all(|p| bed_state(s, p) == "clear")
    });
    let printed: Vec<String> = ["a", "b", "c", "d"]
        .iter()
        .flat_map(|p| {
            std::fs::read_to_string(night.record(p))
                .unwrap_or_default()
                .lines()
                .filter_map(|l| l.strip_prefix("M117 printed ").map(str::to_string))
                .collect::<Vec<_>>()
        })
        .collect();
    for n in &names {
        let times = printed.iter().filter(|p| *p == n).count();
        let want = usize::from(state_of(&s, n) == "done");
        assert_eq!(times, want, "{n} printed {times} times: {printed:?}");
    }
    // Each good print was ejected once and then checked, in its job's record.
    let jobs = night.get("/api/v1/jobs").json();
    for j in jobs
        .as_array()
        .unwrap()
        .iter()
        .filter(|j| j["state"] == "done")
    {
        let id = j["id"].as_str().unwrap();
        let detail = night.get(&format!("/api/v1/jobs/{id}")).json();
        let steps: Vec<&str> = detail["job"]["clearing"]
            .as_array()
            .map(|s| s.iter().map(|s| s["step"].as_str().unwrap()).collect())
            .unwrap_or_default();
        if j["file"] == "part-01.gcode" {
            // Its eject was cut by the kill; a person cleared the bed.
            assert!(steps.is_empty(), "{id}: {steps:?}");
            continue;
        }
        assert_eq!(steps, ["eject", "check"], "{id}");
    }
    for p in ["a", "b", "d"] {
        let (prints, ejects) = prints_and_ejects(&night.record(p));
        let begun = ejects_begun(p);
        assert_eq!(begun, prints, "{p}: one eject begun per good print");
        let cut = usize::from(p == "a");
        assert_eq!(
            ejects,
            prints - cut,
            "{p}: every eject but the one cut ran to its end"
        );
    }
    assert_eq!(prints_and_ejects(&night.record("c")), (1, 1));
    let s = night.status();
    assert_eq!(bed_why(&s, "c"), "not_clear", "c still waits for a person");

    // What the farm says of it: status, metrics.
    let (ok, out) = ctl(&night.config, &["status"]);
    assert!(
        ok && out.contains("bed waiting: the camera found the bed not clear"),
        "{out}"
    );
    let metrics = night.get("/metrics").text();
    for line in [
        "crispen_ejects_total{printer=\"c\",result=\"done\"} 1",
        "crispen_bed_checks_total{printer=\"c\",result=\"not_clear\"} 1",
        "crispen_ejects_total{printer=\"d\",result=\"failed\"} 0",
    ] {
        assert!(metrics.contains(line), "{line} in\n{metrics}");
    }
    assert!(
        metrics.lines().any(|l| l
            .starts_with("crispen_bed_checks_total{printer=\"a\",result=\"clear\"}")
            && !l.ends_with(" 0")),
        "{metrics}"
    );

    // The dashboard in a real headless Chromium: c's tile shows the marked picture and
    // the check's figures, and its job's page the eject and the check with the picture.
    let c_job = jobs
        .as_array()
        .unwrap()
        .iter()
        .find(|j| j["printer"] == "c" && j["state"] == "done")
        .map(|j| j["id"].as_str().unwrap().to_string())
        .expect("c's job");
    let browser = crate::http::Browser::start(&root.join("chromium-profile"));
    browser.go(&format!("http://{}/", night.addr));
    browser.exec(
        "localStorage.setItem('crispen-key', arguments[0])",
        serde_json::json!([KEY]),
    );
    browser.go(&format!("http://{}/", night.addr));
    let not_clear = r"/^not clear: \d+\.\d % of the bed differs, largest patch \d+ × \d+ mm/";
    browser.wait_until(
        Duration::from_secs(60),
        "c's tile with the marked picture and the check's figures",
        &format!(
            "const t = document.querySelector('[data-printer=\"c\"]');
             const img = t && t.querySelector('.bedcheck img.marked');
             const v = t && t.querySelector('.bedcheck .verdict');
             return (!!img && img.naturalWidth > 0 && !!v && {not_clear}.test(v.textContent)
               && !!t.querySelector('button[data-action=\"clear\"]'))
               || [!!img && img.naturalWidth, v && v.textContent].join(' ');"
        ),
    );
    let shots = Path::new(env!("CARGO_TARGET_TMPDIR"));
    browser.screenshot(&shots.join("night-tile-not-clear.png"));
    browser.go(&format!("http://{}/#job/{c_job}", night.addr));
    browser.wait_until(
        Duration::from_secs(60),
        "c's job page with its eject and the check's marked picture",
        &format!(
            "const steps = document.querySelectorAll('#clearing > li');
             const img = document.querySelector('#clearing figure img.marked');
             return (steps.length === 2 && /Eject sequence on c .*: done/.test(steps[0].textContent)
               && /not clear: /.test(steps[1].textContent) && {not_clear}.test(steps[1].querySelector('b').textContent)
               && !!img && img.naturalWidth > 0)
               || [steps.length, steps.length && steps[steps.length - 1].textContent, !!img && img.naturalWidth].join(' ');"
        ),
    );
    browser.exec(
        "document.querySelector('#clearing').scrollIntoView()",
        serde_json::json!([]),
    );
    browser.screenshot(&shots.join("night-job-not-clear.png"));
    drop(daemon);
}
