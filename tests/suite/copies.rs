//! Copies at once, through the real daemon and four simulated printers: a job with
//! `copies = 6` prints four copies at the same time, one on each printer, then the last
//! two once two beds are cleared; every copy exactly once (by each simulator's record and
//! each copy's history), and the farm's status says how they stand at every answer it
//! gives on the way (`copies_status` against the copies' own states and printers, and
//! `crispen status` in words). One copy cancelled alone and retried alone; the others
//! stand.

use crate::common;

use common::daemon::{ctl, status, wait_for, Daemon};
use common::farm::{drop_file, markers, presliced_gcode};
use serde_json::Value;
use std::collections::BTreeMap;
use std::path::Path;
use std::time::{Duration, Instant};

const PRINTERS: [&str; 4] = ["a", "b", "c", "d"];
const LIMIT: Duration = Duration::from_secs(120);

/// A farm of four `marlin2` printers recording what they execute (`<name>.rec`), two hot
/// folders served by all of them (`hot`, and `many`, whose jobs ask for three copies);
/// started and idle. `http`: an `[http]` table, or nothing.
fn four_printers(
    root: &Path,
    time_scale: f64,
    http: &str,
) -> (Daemon, std::path::PathBuf, std::path::PathBuf) {
    std::fs::create_dir_all(root.join("hot")).unwrap();
    std::fs::create_dir_all(root.join("many")).unwrap();
    let mut text = format!(
        "[spool]\ndir = \"spool\"\n[control]\nsocket = \"c.sock\"\n[farm]\nsettle_s = 0.2\n{http}"
    );
    for p in PRINTERS {
        text += &format!(
            "[[printer]]\nname = \"{p}\"\nfirmware = \"marlin2\"\n\
             [printer.simulate]\ntime_scale = {time_scale}\nrecord = \"{p}.rec\"\n"
        );
    }
    for (folder, copies) in [("hot", 1), ("many", 3)] {
        text += &format!(
            "[[folder]]\npath = \"{folder}\"\nheight_mm = 1\ncopies = {copies}\n\
             printers = [\"a\", \"b\", \"c\", \"d\"]\n"
        );
    }
    let config = root.join("crispen.toml");
    std::fs::write(&config, text).unwrap();
    let log = root.join("daemon.log");
    let daemon = Daemon::start(&config, &log);
    wait_for(&config, &log, LIMIT, "four printers idle", |s| {
        PRINTERS.iter().all(|p| {
            s["printers"].as_array().is_some_and(|a| !a.is_empty())
                && common::printer(s, p)["state"] == "idle"
        })
    });
    (daemon, config, log)
}

/// The copies of the job for `file`, by number: (id, state, printer).
fn copies(s: &Value, file: &str) -> BTreeMap<u64, (String, String, Option<String>)> {
    s["jobs"]
        .as_array()
        .into_iter()
        .flatten()
        .filter(|j| j["file"] == file)
        .map(|j| {
            let n = j["copy"]["n"].as_u64().unwrap_or(1);
            let entry = (
                j["id"].as_str().unwrap().to_string(),
                j["state"].as_str().unwrap().to_string(),
                j["printer"].as_str().map(str::to_string),
            );
            (n, entry)
        })
        .collect()
}

/// Checks that the first job's `copies_status` in `s` says what its copies are, and
/// returns it: printed, printing (on which printers), waiting and stopped add up to
/// `total`, each as the copies' own states say, a printer printing one copy at most.
/// None while the job is not prepared (its sidecar, which asks for the copies, is read
/// by its preparation).
fn copies_agree(s: &Value, file: &str, total: u64) -> Option<Value> {
    let first = s["jobs"]
        .as_array()?
        .iter()
        .find(|j| j["file"] == file && j["copy"].is_null())?
        .clone();
    if first["state"] == "queued" || first["state"] == "preparing" {
        return None;
    }
    let c = first["copies_status"].clone();
    assert_eq!(c["total"], total, "{first}");
    let made = copies(s, file);
    let count = |state: &str| made.values().filter(|(_, st, _)| st == state).count() as u64;
    let printing: Vec<String> = made
        .values()
        .filter(|(_, st, _)| st == "printing")
        .map(|(_, _, p)| p.clone().expect("a printing copy has its printer"))
        .collect();
    assert_eq!(c["printed"], count("done"), "{c} against {made:?}");
    assert_eq!(
        c["printing"],
        serde_json::json!(printing),
        "{c} against {made:?}"
    );
    let stopped = count("failed") + count("cancelled") + count("interrupted");
    assert_eq!(c["stopped"], stopped, "{c} against {made:?}");
    let sum = c["printed"].as_u64().unwrap()
        + printing.len() as u64
        + c["waiting"].as_u64().unwrap()
        + stopped;
    assert_eq!(sum, total, "every copy counted once: {c}");
    let mut distinct = printing.clone();
    distinct.sort();
    distinct.dedup();
    assert_eq!(distinct.len(), printing.len(), "one copy per printer: {c}");
    assert_eq!(
        c["jobs"].as_array().unwrap().len(),
        made.len(),
        "the copies made, each named: {c}"
    );
    Some(c)
}

/// `GET /api/v1/jobs/{id}` on the control socket.
fn job_record(root: &Path, id: &str) -> Value {
    let (code, body) =
        common::farm::http_on(&root.join("c.sock"), "GET", &format!("/api/v1/jobs/{id}")).unwrap();
    assert_eq!(code, 200, "{body}");
    serde_json::from_str(&body).unwrap()
}

/// Polls the status until `done` holds, checking [`copies_agree`] on every answer on the
/// way; returns the status that satisfied `done`.
fn watch(
    config: &Path,
    log: &Path,
    file: &str,
    total: u64,
    what: &str,
    done: impl Fn(&Value, &Value) -> bool,
) -> Value {
    let start = Instant::now();
    loop {
        if let Some(s) = status(config) {
            if let Some(c) = copies_agree(&s, file, total) {
                if done(&s, &c) {
                    return s;
                }
            }
        }
        assert!(
            start.elapsed() < LIMIT,
            "timed out waiting for {what}\nlog:\n{}",
            std::fs::read_to_string(log).unwrap_or_default()
        );
        std::thread::sleep(Duration::from_millis(100));
    }
}

#[test]
fn six_copies_on_four_printers_print_four_at_once_then_two_each_once() {
    let tmp = tempfile::tempdir().unwrap();
    let root = tmp.path();
    // About 8 s a print: the four overlap whatever the machine's load.
    let (_daemon, config, log) = four_printers(root, 0.2, "");
    let hot = root.join("hot");
    drop_file(&hot, "part.gcode.toml", b"copies = 6\n");
    drop_file(
        &hot,
        "part.gcode",
        presliced_gcode("part", 40, 6000).as_bytes(),
    );

    // Four at once, one on each printer; two wait.
    let s = watch(
        &config,
        &log,
        "part.gcode",
        6,
        "four copies printing",
        |_, c| c["printing"].as_array().unwrap().len() == 4,
    );
    let c = copies_agree(&s, "part.gcode", 6).unwrap();
    assert_eq!(
        (c["printed"].as_u64(), c["waiting"].as_u64()),
        (Some(0), Some(2)),
        "{c}"
    );
    let mut on: Vec<&str> = c["printing"]
        .as_array()
        .unwrap()
        .iter()
        .map(|p| p.as_str().unwrap())
        .collect();
    on.sort();
    assert_eq!(on, PRINTERS, "one copy on each printer");
    let (ok, words) = ctl(&config, &["status"]);
    assert!(ok, "{words}");
    assert!(
        words.contains("copies: 0 of 6 printed, 4 printing on "),
        "{words}"
    );
    assert!(words.contains(", 2 waiting"), "{words}");
    assert!(
        words.contains("(copy 2 of 6, "),
        "each copy says which it is: {words}"
    );

    // The four end and hold their beds: the two copies left wait for a cleared bed.
    let s = watch(
        &config,
        &log,
        "part.gcode",
        6,
        "four copies printed",
        |s, c| {
            c["printed"] == 4
                && PRINTERS
                    .iter()
                    .all(|p| common::printer(s, p)["bed_cleared"] == false)
        },
    );
    let s = common::daemon::passed_over(
        &config,
        &log,
        &s,
        &PRINTERS,
        "every printer passes the last two over",
    );
    let c = copies_agree(&s, "part.gcode", 6).unwrap();
    assert_eq!(
        (c["printed"].as_u64(), c["waiting"].as_u64()),
        (Some(4), Some(2)),
        "{c}"
    );

    // Two beds cleared: the last two print there.
    for p in ["a", "b"] {
        let (ok, out) = ctl(&config, &["clear", p]);
        assert!(ok, "{out}");
    }
    let s = watch(
        &config,
        &log,
        "part.gcode",
        6,
        "six copies printed",
        |_, c| c["printed"] == 6,
    );
    let made = copies(&s, "part.gcode");
    assert_eq!(made.len(), 6, "{made:?}");
    assert_eq!(made.keys().copied().collect::<Vec<_>>(), [1, 2, 3, 4, 5, 6]);

    // Each copy printed once: its history, and the simulators' records (the G-code's
    // marker once per print: two on the cleared printers, one on the others).
    for (id, state, _) in made.values() {
        assert_eq!(state, "done");
        let job = job_record(root, id);
        let printing = job["job"]["history"]
            .as_array()
            .unwrap()
            .iter()
            .filter(|h| h[0] == "printing")
            .count();
        assert_eq!(printing, 1, "copy {id} went to a printer once: {job}");
    }
    let prints: BTreeMap<&str, usize> = PRINTERS
        .iter()
        .map(|p| {
            (
                *p,
                markers(&root.join(format!("{p}.rec")))
                    .iter()
                    .filter(|m| *m == "part")
                    .count(),
            )
        })
        .collect();
    assert_eq!(
        prints.values().sum::<usize>(),
        6,
        "six prints in all: {prints:?}"
    );
    assert_eq!(
        (prints["a"], prints["b"], prints["c"], prints["d"]),
        (2, 2, 1, 1),
        "{prints:?}"
    );
}

/// A sidecar naming a printer twice in `printers` fails its job with the key named. Of
/// three copies (a folder's `copies`) printing at once, one is cancelled alone (`crispen cancel JOB --copy N`):
/// the others print on; retried alone (`crispen retry JOB --copy N`), the same copy prints
/// again, and the job ends with every copy printed, the cancelled one started twice, the
/// others once.
#[test]
fn one_copy_is_cancelled_and_retried_alone_while_the_others_stand() {
    let tmp = tempfile::tempdir().unwrap();
    let root = tmp.path();
    let (_daemon, config, log) = four_printers(root, 0.2, "");
    let hot = root.join("hot");
    drop_file(
        &hot,
        "cup.gcode.toml",
        b"printers = [\"a\", \"b\", \"a\"]\n",
    );
    std::thread::sleep(Duration::from_millis(10));
    drop_file(
        &hot,
        "cup.gcode",
        presliced_gcode("cup", 400, 6000).as_bytes(),
    );
    let s = wait_for(&config, &log, LIMIT, "the sidecar refused", |s| {
        common::daemon::state_of(s, "cup.gcode") == "failed"
    });
    let reason = common::job_by_file(&s, "cup.gcode").unwrap()["reason"].to_string();
    assert!(
        reason.contains("printers") && reason.contains("twice"),
        "{reason}"
    );

    // Three copies: its folder's.
    drop_file(
        &root.join("many"),
        "mug.gcode",
        presliced_gcode("mug", 100, 6000).as_bytes(),
    );
    let s = watch(
        &config,
        &log,
        "mug.gcode",
        3,
        "three copies printing",
        |_, c| c["printing"].as_array().unwrap().len() == 3,
    );
    let made = copies(&s, "mug.gcode");
    let first = made[&1].0.clone();
    let (n, (victim, _, printer)) = made
        .iter()
        .find(|(_, (_, st, _))| st == "printing")
        .map(|(n, e)| (*n, e.clone()))
        .unwrap();
    let printer = printer.unwrap();
    let (ok, out) = ctl(&config, &["cancel", &first, "--copy", &n.to_string()]);
    assert!(ok, "{out}");
    assert!(
        out.contains(&format!("job {victim}: stopping the print on {printer}")),
        "{out}"
    );
    let s = watch(
        &config,
        &log,
        "mug.gcode",
        3,
        "the copy cancelled",
        |_, c| c["stopped"] == 1,
    );
    let after = copies(&s, "mug.gcode");
    assert_eq!(after[&n].1, "cancelled");
    for (m, (_, state, _)) in &after {
        if *m != n {
            assert!(
                state == "printing" || state == "done",
                "copy {m} stands: {after:?}"
            );
        }
    }
    // A copy that does not exist is named as such.
    let (ok, out) = ctl(&config, &["retry", &first, "--copy", "4"]);
    assert!(
        !ok && out.contains("has no copy 4 (its copies: 1, 2, 3)"),
        "{out}"
    );
    let (ok, out) = ctl(&config, &["retry", &first, "--copy", &n.to_string()]);
    assert!(ok, "{out}");
    let (ok, out) = ctl(&config, &["clear", &printer]);
    assert!(ok, "{out}");
    let s = watch(
        &config,
        &log,
        "mug.gcode",
        3,
        "the cancelled copy printing again",
        |s, c| c["stopped"] == 0 && copies(s, "mug.gcode")[&n].1 == "printing",
    );
    let again = copies(&s, "mug.gcode");
    assert_eq!(again[&n].0, victim, "the same copy, not a new one");
    assert_eq!(again.len(), 3, "no copy made again: {again:?}");
    // The others' beds are cleared as they end; all three are printed.
    let s = watch(
        &config,
        &log,
        "mug.gcode",
        3,
        "three copies printed",
        |s, c| {
            for p in PRINTERS {
                if common::printer(s, p)["bed_cleared"] == false
                    && common::printer(s, p)["state"] != "printing"
                {
                    let _ = ctl(&config, &["clear", p]);
                }
            }
            c["printed"] == 3
        },
    );
    for (m, (id, _, _)) in copies(&s, "mug.gcode") {
        let starts = job_record(root, &id)["job"]["history"]
            .as_array()
            .unwrap()
            .iter()
            .filter(|h| h[0] == "printing")
            .count();
        assert_eq!(starts, if m == n { 2 } else { 1 }, "copy {m}");
    }
}

/// The dashboard in a real browser: with two printers ticked, a file dropped on a folder
/// is sent to them, one copy each (its sidecar's `printers`, written by the page); the
/// queue says how the copies stand and which each is, the job page lists them, and a
/// printer tile's Cancel stops its own copy only while the other prints on.
#[test]
fn the_dashboard_sends_a_file_to_chosen_printers_and_cancels_one_copy() {
    const KEY: &str = "copies-key-0123456789abcdef0123";
    let tmp = tempfile::tempdir().unwrap();
    let root = tmp.path();
    std::fs::write(root.join("key"), KEY).unwrap();
    let (_daemon, config, log) = four_printers(
        root,
        0.2,
        "[http]\nlisten = \"127.0.0.1:0\"\napi_key_file = \"key\"\n",
    );
    let addr = common::daemon::http_address(&log);
    let browser = crate::http::Browser::start(&root.join("chromium-profile"));
    browser.go(&format!("http://{addr}/"));
    browser.exec(
        "localStorage.setItem('crispen-key', arguments[0]); window.confirm = () => true;",
        serde_json::json!([KEY]),
    );
    browser.go(&format!("http://{addr}/"));
    browser.wait_until(
        LIMIT,
        "the printers to send to",
        "return document.querySelectorAll('#sendto input').length === 4",
    );
    // WebDriver cannot drag a file from the desktop: the page gets the events a drop fires.
    let dropped = browser.exec(
        "const [text] = arguments;
         for (const p of ['d', 'b']) document.querySelector('#sendto input[value=\"' + p + '\"]').checked = true;
         const zone = document.querySelector('[data-folder=\"hot\"]');
         const data = new DataTransfer();
         data.items.add(new File([text], 'pair.gcode', { type: 'application/octet-stream' }));
         for (const type of ['dragenter', 'dragover', 'drop'])
           zone.dispatchEvent(new DragEvent(type, { bubbles: true, cancelable: true, dataTransfer: data }));
         return data.files.length;",
        serde_json::json!([presliced_gcode("pair", 100, 6000)]),
    );
    assert_eq!(dropped, serde_json::json!(1));
    // The page's order of the boxes is the farm's, so the copies go to b, then d.
    let s = watch(
        &config,
        &log,
        "pair.gcode",
        2,
        "both copies printing",
        |_, c| c["printing"].as_array().unwrap().len() == 2,
    );
    let c = copies_agree(&s, "pair.gcode", 2).unwrap();
    assert_eq!(c["printing"], serde_json::json!(["b", "d"]), "{c}");
    browser.wait_until(
        LIMIT,
        "the queue's copies",
        "const rows = Array.from(document.querySelectorAll('#queue tr[data-job]')).filter(r => r.textContent.includes('pair.gcode'));
         const text = rows.map(r => r.textContent).join(' | ');
         return (rows.length === 2 && text.includes('0 of 2 printed, 2 printing on b, d') && text.includes('copy 2 of 2')) || text;",
    );
    let first = c["jobs"][0].as_str().unwrap().to_string();
    browser.go(&format!("http://{addr}/#job/{first}"));
    browser.wait_until(
        LIMIT,
        "the job page's copies",
        "const p = document.querySelector('#copies');
         return (!!p && /of 2 printed/.test(p.textContent) && document.querySelectorAll('#copylist a[href^=\"#job/\"]').length === 2)
           || document.querySelector('#jobpage').textContent;",
    );
    browser.go(&format!("http://{addr}/"));
    // d's tile cancels d's copy: the second.
    browser.wait_until(
        LIMIT,
        "d's Cancel",
        "return !!document.querySelector('article[data-printer=\"d\"] button[data-action=\"cancel\"][data-copy=\"2\"]')",
    );
    let clicked = browser.exec(
        "window.confirm = () => true;
         const b = document.querySelector('article[data-printer=\"d\"] button[data-action=\"cancel\"]');
         if (b) b.click();
         return !!b;",
        serde_json::json!([]),
    );
    assert_eq!(clicked, serde_json::json!(true));
    let s = watch(
        &config,
        &log,
        "pair.gcode",
        2,
        "d's copy cancelled",
        |_, c| c["stopped"] == 1,
    );
    let made = copies(&s, "pair.gcode");
    assert_eq!(made[&2].1, "cancelled", "{made:?}");
    assert!(
        made[&1].1 == "printing" || made[&1].1 == "done",
        "b's copy prints on: {made:?}"
    );
    let shots = Path::new(env!("CARGO_TARGET_TMPDIR"));
    browser.screenshot(&shots.join("dashboard-copies.png"));
}
