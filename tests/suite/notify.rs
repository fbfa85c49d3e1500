//! Notifications end to end: the real daemon, simulated printers, pre-sliced G-code, and a
//! real HTTP receiver started by the test (`common::receiver`): a done job, a failed job
//! and a printer gone offline each arrive once, signed; a receiver down for a while gets
//! every event once it is back, each id once, across a kill -9 of the daemon; a receiver
//! that never answers does not slow a print; `crispen notify test` says what each
//! receiver answered.

use crate::common::daemon::{ctl, spawn_sim, state_of, status, wait_for, Daemon, Killed, BIN};
use crate::common::farm::presliced_gcode;
use crate::common::receiver::{Received, Receiver};
use hmac::{KeyInit, Mac};
use serde_json::Value;
use std::collections::BTreeMap;
use std::os::unix::fs::PermissionsExt;
use std::path::{Path, PathBuf};
use std::process::Command;
use std::time::{Duration, Instant};

const SECRET: &str = "a-signing-secret-of-the-test-0123";
const LIMIT: Duration = Duration::from_secs(120);

/// A farm directory: config with `printers` (each a `[[printer]]` body), one hot folder
/// for them, and `notify` (the `[[notify]]` tables, verbatim).
fn configure(root: &Path, printers: &[(&str, String)], notify: &str) -> PathBuf {
    std::fs::create_dir_all(root.join("hot")).unwrap();
    std::fs::write(root.join("secret"), SECRET).unwrap();
    std::fs::set_permissions(root.join("secret"), std::fs::Permissions::from_mode(0o600)).unwrap();
    std::fs::write(root.join("key"), "k".repeat(32)).unwrap();
    std::fs::set_permissions(root.join("key"), std::fs::Permissions::from_mode(0o600)).unwrap();
    let mut text = String::from(
        "[spool]\ndir = \"spool\"\n[control]\nsocket = \"c.sock\"\n[farm]\nsettle_s = 0.3\nrescan_s = 1\n\
         [http]\nlisten = \"127.0.0.1:0\"\napi_key_file = \"key\"\npublic_url = \"http://farm.example:8080/\"\n",
    );
    let names: Vec<String> = printers.iter().map(|(n, _)| format!("{n:?}")).collect();
    for (name, body) in printers {
        text += &format!("[[printer]]\nname = \"{name}\"\nfirmware = \"marlin2\"\n{body}\n");
    }
    text += &format!(
        "[[folder]]\npath = \"hot\"\nheight_mm = 12\nenhance = false\nprinters = [{}]\n{notify}",
        names.join(", ")
    );
    let config = root.join("crispen.toml");
    std::fs::write(&config, text).unwrap();
    config
}

fn simulated(time_scale: f64) -> String {
    format!("[printer.simulate]\ntime_scale = {time_scale}")
}

fn drop_file(root: &Path, name: &str, bytes: &[u8]) {
    crate::common::farm::drop_file(&root.join("hot"), name, bytes);
}

/// The event's signature checked against the body received, with the test's secret.
fn assert_signed(r: &Received) {
    let header = r.header("x-crispen-signature").expect("a signature header");
    let mut mac = hmac::Hmac::<sha2::Sha256>::new_from_slice(SECRET.as_bytes()).unwrap();
    mac.update(&r.body);
    let hex: String = mac
        .finalize()
        .into_bytes()
        .iter()
        .map(|b| format!("{b:02x}"))
        .collect();
    assert_eq!(
        header,
        format!("sha256={hex}"),
        "signature of {:?}",
        r.json()
    );
}

fn events_of<'a>(taken: &'a [Received], kind: &str) -> Vec<&'a Received> {
    taken.iter().filter(|r| r.json()["event"] == kind).collect()
}

/// What the receiver took before a later event of the farm's own (a model that fails,
/// dropped now), once that event is taken: a receiver's events are sent oldest first,
/// and those taken so far were made before it, so one of them sent twice, or made twice,
/// would have come before it. The event that shows the moment has passed, where waiting
/// a while would only guess.
fn taken_before_a_later_event(receiver: &Receiver, root: &Path, log: &Path) -> Vec<Received> {
    drop_file(root, "later.stl", b"solid later but nothing\n");
    let later = |r: &Received| r.json()["job"]["file"] == "later.stl";
    receiver.wait_taken(
        LIMIT,
        "the later event",
        |t| t.iter().any(later),
        log_of(log),
    );
    let taken = receiver.taken();
    let at = taken.iter().position(later).unwrap();
    taken[..at].to_vec()
}

fn log_of(log: &Path) -> impl Fn() -> String + '_ {
    move || format!("log:\n{}", std::fs::read_to_string(log).unwrap_or_default())
}

/// A done job, a failed job and a printer that goes offline each send one event, signed
/// with the receiver's secret, naming the printer, the job (id, file, folder), the reason
/// and the dashboard's link.
#[test]
fn a_done_job_a_failed_job_and_an_offline_printer_each_send_one_signed_event() {
    let tmp = tempfile::tempdir().unwrap();
    let root = tmp.path();
    let receiver = Receiver::start();
    let link = root.join("ttyP");
    let (sim, device) = spawn_sim(
        Command::new(BIN)
            .args([
                "sim",
                "--firmware",
                "marlin2",
                "--time-scale",
                "0",
                "--link",
            ])
            .arg(&link),
    );
    let sim = Killed(sim);
    let _ = device;
    let config = configure(
        root,
        &[("p", format!("port = \"{}\"", link.display()))],
        &format!(
            "[[notify]]\nname = \"hook\"\nurl = \"{}\"\nsecret_file = \"secret\"\nbackoff_max_s = 0.5\n",
            receiver.url("/hook")
        ),
    );
    let log = root.join("daemon.log");
    let _daemon = Daemon::start(&config, &log);
    wait_for(&config, &log, LIMIT, "printer idle", |s| {
        crate::common::printer(s, "p")["state"] == "idle"
    });
    drop_file(
        root,
        "good.gcode",
        presliced_gcode("good", 20, 6000).as_bytes(),
    );
    drop_file(root, "bad.stl", b"solid nothing but words\n");
    let s = wait_for(&config, &log, LIMIT, "done and failed", |s| {
        state_of(s, "good.gcode") == "done" && state_of(s, "bad.stl") == "failed"
    });
    let good = crate::common::job_by_file(&s, "good.gcode")
        .unwrap()
        .clone();
    let bad = crate::common::job_by_file(&s, "bad.stl").unwrap().clone();
    drop(sim);
    let taken = receiver.wait_taken(
        LIMIT,
        "done, failed and offline",
        |t| {
            let kinds: Vec<String> = t.iter().map(|r| r.json()["event"].to_string()).collect();
            ["job_done", "job_failed", "printer_offline"]
                .iter()
                .all(|k| kinds.contains(&format!("{k:?}")))
        },
        log_of(&log),
    );
    drop(taken);
    let taken = taken_before_a_later_event(&receiver, root, &log);
    assert!(taken.len() >= 3);
    for r in &taken {
        assert_eq!((r.method.as_str(), r.path.as_str()), ("POST", "/hook"));
        assert_signed(r);
        let e = r.json();
        assert_eq!(r.header("x-crispen-id"), e["id"].as_str());
        let link = e["link"].as_str().unwrap();
        match e["job"]["id"].as_str() {
            Some(id) => assert_eq!(link, format!("http://farm.example:8080/#job/{id}")),
            None => assert_eq!(link, "http://farm.example:8080"),
        }
        assert!(e["time"].as_f64().unwrap() > 1.7e9);
    }
    let done = events_of(&taken, "job_done");
    assert_eq!(done.len(), 1, "one job_done");
    let done = done[0].json();
    assert_eq!(done["printer"], "p");
    assert_eq!(done["job"]["id"], good["id"]);
    assert_eq!(done["job"]["file"], "good.gcode");
    assert!(done["job"]["folder"].as_str().unwrap().ends_with("hot"));
    let failed = events_of(&taken, "job_failed");
    assert_eq!(failed.len(), 1, "one job_failed");
    let failed = failed[0].json();
    assert_eq!(failed["job"]["id"], bad["id"]);
    assert_eq!(failed["reason"], bad["reason"], "the job's reason");
    assert!(!failed["reason"].as_str().unwrap_or("").is_empty());
    let offline = events_of(&taken, "printer_offline");
    assert_eq!(offline.len(), 1, "one printer_offline");
    assert_eq!(offline[0].json()["printer"], "p");
    let ids: std::collections::BTreeSet<&str> = taken
        .iter()
        .map(|r| r.header("x-crispen-id").unwrap())
        .collect();
    assert_eq!(ids.len(), taken.len(), "each event once: {taken:?}");

    // The counters say so.
    let port = listening_port(&log);
    let (code, metrics) = http_get(port, "/metrics");
    assert_eq!(code, 200);
    assert!(
        metrics.contains("crispen_notifications_total{receiver=\"hook\",result=\"delivered\"} 4")
            || metrics
                .contains("crispen_notifications_total{receiver=\"hook\",result=\"delivered\"} 5"),
        "{metrics}"
    );
    assert!(
        metrics.contains("crispen_build_info{version=\""),
        "{metrics}"
    );
}

/// The HTTP port the daemon logged.
fn listening_port(log: &Path) -> u16 {
    let text = std::fs::read_to_string(log).unwrap();
    let at = text
        .find("dashboard: http://")
        .expect("the dashboard's address logged");
    let rest = &text[at + "dashboard: http://".len()..];
    let addr = rest.split('/').next().unwrap();
    addr.rsplit(':').next().unwrap().parse().unwrap()
}

fn http_get(port: u16, path: &str) -> (u16, String) {
    use std::io::{Read, Write};
    let mut s = std::net::TcpStream::connect(("127.0.0.1", port)).unwrap();
    let key = "k".repeat(32);
    write!(
        s,
        "GET {path} HTTP/1.1\r\nHost: x\r\nX-Api-Key: {key}\r\nConnection: close\r\n\r\n"
    )
    .unwrap();
    let mut text = String::new();
    s.read_to_string(&mut text).unwrap();
    let code = text.split_whitespace().nth(1).unwrap().parse().unwrap();
    (code, text)
}

/// With the receiver answering 503, events wait in the spool and are retried with the
/// same id; the daemon is killed (-9) and started again meanwhile; once the receiver
/// answers, every event arrives, each id taken once, none lost.
#[test]
fn a_receiver_down_for_a_while_gets_every_event_once_even_across_a_restart() {
    let tmp = tempfile::tempdir().unwrap();
    let root = tmp.path();
    let receiver = Receiver::start();
    receiver.answer(503);
    let config = configure(
        root,
        &[("p1", simulated(0.0)), ("p2", simulated(0.0))],
        &format!(
            "[[notify]]\nname = \"hook\"\nurl = \"{}\"\nsecret_file = \"secret\"\nbackoff_max_s = 0.3\nevents = [\"job_done\", \"job_failed\"]\n",
            receiver.url("/hook")
        ),
    );
    let log = root.join("daemon.log");
    let mut daemon = Daemon::start(&config, &log);
    drop_file(root, "a.gcode", presliced_gcode("a", 5, 6000).as_bytes());
    drop_file(root, "b.gcode", presliced_gcode("b", 5, 6000).as_bytes());
    drop_file(root, "bad.stl", b"solid nothing\n");
    wait_for(&config, &log, LIMIT, "two done, one failed", |s| {
        state_of(s, "a.gcode") == "done"
            && state_of(s, "b.gcode") == "done"
            && state_of(s, "bad.stl") == "failed"
    });
    // Retried while down: the same ids again and again.
    let start = Instant::now();
    while receiver.received().len() < 6 {
        assert!(start.elapsed() < LIMIT, "no retries:\n{}", log_of(&log)());
        std::thread::sleep(Duration::from_millis(100));
    }
    let queue = root.join("spool/notify/hook");
    let queued = std::fs::read_dir(&queue).unwrap().count();
    assert_eq!(queued, 3, "three events wait in {}", queue.display());
    daemon.kill9();
    drop(daemon);
    let refused_before_restart = receiver.received().len();

    let _daemon = Daemon::start(&config, &log);
    let start = Instant::now();
    while receiver.received().len() < refused_before_restart + 3 {
        assert!(
            start.elapsed() < LIMIT,
            "not retried after the restart:\n{}",
            log_of(&log)()
        );
        std::thread::sleep(Duration::from_millis(100));
    }
    receiver.answer(200);
    let taken = receiver.wait_taken(LIMIT, "three events", |t| t.len() >= 3, log_of(&log));
    let taken_after = taken_before_a_later_event(&receiver, root, &log);
    assert_eq!(taken_after.len(), 3, "each event once: {taken:?}");
    let mut by_id: BTreeMap<String, Value> = BTreeMap::new();
    for r in &taken_after {
        assert_signed(r);
        by_id.insert(r.header("x-crispen-id").unwrap().to_string(), r.json());
    }
    assert_eq!(by_id.len(), 3, "three ids, each taken once");
    let mut files: Vec<&str> = by_id
        .values()
        .map(|e| e["job"]["file"].as_str().unwrap())
        .collect();
    files.sort();
    assert_eq!(files, ["a.gcode", "b.gcode", "bad.stl"]);
    // Every refused attempt was one of these events, under its one id.
    let earlier = receiver.received();
    for r in earlier
        .iter()
        .filter(|r| r.json()["job"]["file"] != "later.stl")
    {
        let id = r.header("x-crispen-id").unwrap();
        assert!(
            by_id.contains_key(id),
            "an attempt under an unknown id {id}"
        );
        assert_eq!(by_id[id], r.json(), "the same event on every attempt");
    }
    let start = Instant::now();
    while std::fs::read_dir(&queue).unwrap().count() > 0 {
        assert!(start.elapsed() < LIMIT, "the queue is not emptied");
        std::thread::sleep(Duration::from_millis(100));
    }
}

/// How long job `file` printed, from its record in the spool.
fn print_seconds(root: &Path, config: &Path, file: &str) -> f64 {
    let s = status(config).unwrap();
    let id = crate::common::job_by_file(&s, file).unwrap()["id"]
        .as_str()
        .unwrap()
        .to_string();
    let record: Value = serde_json::from_slice(
        &std::fs::read(root.join("spool/jobs").join(id).join("job.json")).unwrap(),
    )
    .unwrap();
    record["print_report"]["duration_s"].as_f64().unwrap()
}

/// One print on a paced simulator, after a failed job whose event goes to `notify`:
/// the print's duration.
fn timed_print(notify: &str) -> f64 {
    let tmp = tempfile::tempdir().unwrap();
    let root = tmp.path();
    let config = configure(root, &[("p", simulated(0.05))], notify);
    let log = root.join("daemon.log");
    let _daemon = Daemon::start(&config, &log);
    drop_file(root, "bad.stl", b"solid nothing\n");
    wait_for(&config, &log, LIMIT, "failed", |s| {
        state_of(s, "bad.stl") == "failed"
    });
    drop_file(
        root,
        "timed.gcode",
        presliced_gcode("t", 60, 3000).as_bytes(),
    );
    wait_for(&config, &log, LIMIT, "printed", |s| {
        state_of(s, "timed.gcode") == "done"
    });
    print_seconds(root, &config, "timed.gcode")
}

/// A receiver that takes connections and never answers (a hung server) while a job
/// prints: the print takes as long as without any receiver (a generous bound; the
/// figures are printed).
#[test]
fn a_receiver_that_never_answers_does_not_slow_a_print() {
    let hole = Receiver::start();
    hole.answer(0);
    let with_hole = timed_print(&format!(
        "[[notify]]\nname = \"hole\"\nurl = \"{}\"\ntimeout_s = 60\n",
        hole.url("/")
    ));
    assert!(!hole.received().is_empty(), "the black hole was tried");
    let without = timed_print("");
    println!("print duration: {without:.2} s without a receiver, {with_hole:.2} s with one that never answers");
    assert!(
        with_hole < without * 2.0 + 5.0,
        "{with_hole:.2} s with a black-hole receiver vs {without:.2} s without"
    );
}

/// `crispen notify test` sends a test event to every receiver and says what each
/// answered; a receiver that refuses makes it fail.
#[test]
fn notify_test_says_what_each_receiver_answered() {
    let tmp = tempfile::tempdir().unwrap();
    let root = tmp.path();
    let ok = Receiver::start();
    let refusing = Receiver::start();
    refusing.answer(404);
    let notify = |second: &str| {
        format!(
            "[[notify]]\nname = \"ok\"\nurl = \"{}\"\nsecret_file = \"secret\"\n\
             [[notify]]\nname = \"second\"\nurl = \"{second}\"\nformat = \"slack\"\n",
            ok.url("/a")
        )
    };
    let config = configure(root, &[("p", simulated(0.0))], &notify(&refusing.url("/b")));
    let (success, out) = ctl(&config, &["notify", "test"]);
    assert!(!success, "one receiver refused: {out}");
    assert!(out.contains("ok (http://127.0.0.1:"), "{out}");
    assert!(out.contains("ok: HTTP 200 answered 200"), "{out}");
    assert!(
        out.contains("second (") && out.contains("FAILED: HTTP 404"),
        "{out}"
    );
    let sent = ok.taken();
    assert_eq!(sent.len(), 1);
    assert_signed(&sent[0]);
    assert_eq!(sent[0].json()["event"], "test");
    let slack: Value = refusing.received()[0].json();
    assert!(
        slack["text"]
            .as_str()
            .unwrap()
            .starts_with("Test notification"),
        "{slack}"
    );

    let config = configure(root, &[("p", simulated(0.0))], &notify(&ok.url("/c")));
    let (success, out) = ctl(&config, &["notify", "test"]);
    assert!(success, "{out}");
    assert_eq!(ok.taken().len(), 3);
}

/// A bad `[[notify]]` table is refused with its number, name and key.
#[test]
fn a_bad_notify_table_is_named() {
    let tmp = tempfile::tempdir().unwrap();
    let root = tmp.path();
    for (table, expected) in [
        (
            "[[notify]]\nname = \"x\"\nurl = \"ftp://h/\"\n",
            "[[notify]] #1 (name \"x\"): key `url`",
        ),
        (
            "[[notify]]\nname = \"x\"\nurl = \"http://h/\"\nevents = [\"job_don\"]\n",
            "key `events`: unknown event \"job_don\"",
        ),
        (
            "[[notify]]\nname = \"x\"\nurl = \"http://h/\"\nformat = \"teams\"\n",
            "key `format`: unknown format \"teams\"",
        ),
        (
            "[[notify]]\nname = \"x\"\nurl = \"http://h/\"\ntimeout_s = 0\n",
            "key `timeout_s`",
        ),
        (
            "[[notify]]\nname = \"a/b\"\nurl = \"http://h/\"\n",
            "key `name`",
        ),
        (
            "[[notify]]\nname = \"x\"\nurl = \"http://h/\"\nsecret_file = \"missing\"\n",
            "key `secret_file`: cannot read",
        ),
    ] {
        let config = configure(root, &[("p", simulated(0.0))], table);
        let (ok, out) = ctl(&config, &["run", "--check"]);
        assert!(!ok, "{table}");
        assert!(out.contains(expected), "{table}: {out}");
    }
}

/// A printer that halts with a fatal error mid-print (as Marlin does on a thermal
/// runaway: `Error:Printer halted. kill() called!`) sends one `printer_error` naming the
/// printer, the job and the firmware's message, and no `job_failed` besides.
#[test]
fn a_printer_halting_mid_print_sends_a_printer_error() {
    let tmp = tempfile::tempdir().unwrap();
    let root = tmp.path();
    let receiver = Receiver::start();
    let link = root.join("ttyP");
    let (sim, _) = spawn_sim(
        Command::new(BIN)
            .args(["sim", "--firmware", "marlin2", "--time-scale", "0"])
            .args(["--fatal-after", "20", "--link"])
            .arg(&link),
    );
    let _sim = Killed(sim);
    let config = configure(
        root,
        &[("p", format!("port = \"{}\"", link.display()))],
        &format!(
            "[[notify]]\nname = \"hook\"\nurl = \"{}\"\nsecret_file = \"secret\"\n",
            receiver.url("/hook")
        ),
    );
    let log = root.join("daemon.log");
    let _daemon = Daemon::start(&config, &log);
    drop_file(
        root,
        "halt.gcode",
        presliced_gcode("h", 60, 6000).as_bytes(),
    );
    let s = wait_for(&config, &log, LIMIT, "failed", |s| {
        state_of(s, "halt.gcode") == "failed"
    });
    let job = crate::common::job_by_file(&s, "halt.gcode")
        .unwrap()
        .clone();
    let taken = receiver.wait_taken(
        LIMIT,
        "printer_error",
        |t| !events_of(t, "printer_error").is_empty(),
        log_of(&log),
    );
    drop(taken);
    let taken = taken_before_a_later_event(&receiver, root, &log);
    let errors = events_of(&taken, "printer_error");
    assert_eq!(errors.len(), 1, "one printer_error");
    assert_signed(errors[0]);
    let e = errors[0].json();
    assert_eq!(e["printer"], "p");
    assert_eq!(e["job"]["id"], job["id"]);
    assert_eq!(e["reason"], job["reason"]);
    assert!(e["reason"].as_str().unwrap().contains("fatal error"), "{e}");
    assert!(
        events_of(&taken, "job_failed").is_empty(),
        "not also a job_failed"
    );
}
