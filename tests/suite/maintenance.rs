//! A printer's care by use, through the real daemon and a simulated printer: a blocking
//! `[[maintenance]]` task falls due by the prints counted, keeps the printer out of the
//! queue (the next job stays ready while the printer looks at it and declines), is told
//! once to a real receiver, shows in `/metrics`, and lets the printer go on once recorded
//! done with `crispen maintenance done`; the counts equal what the simulator executed; a
//! printer put into maintenance by hand takes no job until it is taken out.

use crate::common;

use common::daemon::{clear_after_done, ctl, passed_over, recorded, wait_for, Daemon};
use common::farm::{drop_file, presliced_gcode, state_of};
use common::receiver::Receiver;
use crispen::marlin::firmware::Firmware;
use serde_json::Value;
use std::path::Path;
use std::time::Duration;

const LIMIT: Duration = Duration::from_secs(90);

/// `crispen maintenance ARGS --json` as JSON.
fn care_json(config: &Path, args: &[&str]) -> Value {
    let mut argv = vec!["maintenance"];
    argv.extend_from_slice(args);
    argv.push("--json");
    let (ok, out) = ctl(config, &argv);
    assert!(ok, "crispen {argv:?}: {out}");
    serde_json::from_str(&out).unwrap_or_else(|e| panic!("{e}: {out}"))
}

#[test]
fn a_blocking_task_due_by_prints_holds_the_printer_until_it_is_done() {
    let tmp = tempfile::tempdir().unwrap();
    let root = tmp.path();
    std::fs::create_dir_all(root.join("hot")).unwrap();
    let receiver = Receiver::start();
    let config = root.join("crispen.toml");
    std::fs::write(
        &config,
        format!(
            "[spool]\ndir = \"spool\"\n[control]\nsocket = \"c.sock\"\n[farm]\nsettle_s = 0.2\n\
             [[printer]]\nname = \"a\"\nfirmware = \"marlin2\"\nmaterial = \"PLA\"\ncolour = \"black\"\n\
             [printer.simulate]\ntime_scale = 0.0\nrecord = \"a.rec\"\n\
             [[folder]]\npath = \"hot\"\nheight_mm = 1\nprinters = [\"a\"]\n\
             [[maintenance]]\nname = \"nozzle\"\nprinters = [\"a\"]\nevery_jobs = 2\nblock = true\n\
             [[maintenance]]\nname = \"belts\"\nevery_print_hours = 500\n\
             [[notify]]\nname = \"hook\"\nurl = \"{}\"\nbackoff_max_s = 0.5\n",
            receiver.url("/hook")
        ),
    )
    .unwrap();
    let log = root.join("daemon.log");
    let _daemon = Daemon::start(&config, &log);
    wait_for(&config, &log, LIMIT, "printer a idle", |s| {
        s["printers"].as_array().is_some_and(|p| !p.is_empty())
            && common::printer(s, "a")["state"] == "idle"
    });
    let hot = root.join("hot");

    // Two prints: the second makes the nozzle due.
    for (i, name) in ["one", "two"].into_iter().enumerate() {
        let file = format!("{name}.gcode");
        drop_file(
            &hot,
            &file,
            presliced_gcode(name, 40 + 10 * i, 6000).as_bytes(),
        );
        clear_after_done(&config, &log, "a", &file);
    }
    // The third is ready, and the printer looks at it and declines: in maintenance.
    drop_file(
        &hot,
        "three.gcode",
        presliced_gcode("three", 30, 6000).as_bytes(),
    );
    let ready = wait_for(&config, &log, LIMIT, "three ready", |s| {
        state_of(s, "three.gcode") == "ready"
    });
    let s = passed_over(&config, &log, &ready, &["a"], "a passes three over");
    let a = common::printer(&s, "a");
    assert_eq!(a["state"], "maintenance", "{a}");
    assert!(
        a["detail"].as_str().unwrap_or("").contains("nozzle"),
        "the tile says which task: {a}"
    );
    assert_eq!(state_of(&s, "three.gcode"), "ready");

    // The counts are what the simulator executed: two prints, their filament in mm and in
    // grams of PLA (1.24 g/cm³, 1.75 mm).
    let executed = crispen::marlin::motion::extruded_mm(
        recorded(&root.join("a.rec")).iter().map(String::as_str),
        Firmware::Marlin2,
    );
    let record = care_json(&config, &["log", "a"]);
    let counts = &record["counts"];
    assert_eq!(counts["prints"], 2, "{record}");
    assert_eq!(counts["failed"], 0, "{record}");
    let mm = counts["filament_mm"].as_f64().unwrap();
    assert!(
        (mm - executed).abs() < 1e-6,
        "{mm} mm counted, {executed} executed"
    );
    let r_cm = 1.75 / 20.0;
    let grams = executed * std::f64::consts::PI * r_cm * r_cm * 0.1 * 1.24;
    let g = counts["filament_g"].as_f64().unwrap();
    assert!(
        (g - grams).abs() < 1e-6,
        "{g} g counted, {grams} g executed"
    );
    assert!((counts["materials"]["PLA"]["g"].as_f64().unwrap() - grams).abs() < 1e-6);
    assert!(counts["print_s"].as_f64().unwrap() > 0.0, "{record}");
    let list = care_json(&config, &["list"]);
    let tasks = list[0]["tasks"].as_array().unwrap();
    let nozzle = tasks.iter().find(|t| t["task"] == "nozzle").unwrap();
    assert_eq!(
        (nozzle["due"].as_bool(), nozzle["block"].as_bool()),
        (Some(true), Some(true))
    );
    assert_eq!(nozzle["intervals"][0]["used"], 2.0);
    let belts = tasks.iter().find(|t| t["task"] == "belts").unwrap();
    assert_eq!(
        belts["due"], false,
        "the second task applies to every printer, not due"
    );

    // `/metrics` says so.
    let (code, metrics) = common::farm::http_on(&root.join("c.sock"), "GET", "/metrics").unwrap();
    assert_eq!(code, 200);
    assert!(
        metrics
            .contains("crispen_maintenance_due{printer=\"a\",task=\"nozzle\",blocking=\"true\"} 1"),
        "{metrics}"
    );
    assert!(metrics.contains("crispen_printer_care_prints_total{printer=\"a\"} 2"));

    // A task that is not the printer's is refused with its tasks named.
    let (ok, out) = ctl(&config, &["maintenance", "done", "a", "bed"]);
    assert!(!ok && out.contains("nozzle, belts"), "{out}");

    // Done: the third prints, and the nozzle counts again from here.
    let (ok, out) = ctl(
        &config,
        &[
            "maintenance",
            "done",
            "a",
            "nozzle",
            "--note",
            "0.4 mm brass nozzle",
        ],
    );
    assert!(ok && out.contains("recorded as done"), "{out}");
    clear_after_done(&config, &log, "a", "three.gcode");
    let record = care_json(&config, &["log", "a"]);
    assert_eq!(record["counts"]["prints"], 3, "{record}");
    let nozzle = &record["tasks"].as_array().unwrap()[0];
    assert_eq!(
        (nozzle["task"].as_str(), nozzle["due"].as_bool()),
        (Some("nozzle"), Some(false))
    );
    assert_eq!(nozzle["intervals"][0]["used"], 1.0);
    let entry = &record["log"][0];
    assert_eq!(entry["what"]["task"], "nozzle", "{record}");
    assert_eq!(entry["work"]["note"], "0.4 mm brass nozzle");
    assert!(!entry["work"]["by"].as_str().unwrap_or("").is_empty());

    // Told once: by the time the third job's `job_done` is taken, one `maintenance_due`.
    let events = |taken: &[common::receiver::Received]| -> Vec<Value> {
        taken.iter().map(|r| r.json()).collect()
    };
    let taken = receiver.wait_taken(
        LIMIT,
        "the third job's job_done",
        |t| {
            events(t)
                .iter()
                .any(|e| e["event"] == "job_done" && e["job"]["file"] == "three.gcode")
        },
        || std::fs::read_to_string(&log).unwrap_or_default(),
    );
    let due: Vec<Value> = events(&taken)
        .into_iter()
        .filter(|e| e["event"] == "maintenance_due")
        .collect();
    assert_eq!(due.len(), 1, "{due:?}");
    assert_eq!(due[0]["printer"], "a");
    assert!(
        due[0]["reason"]
            .as_str()
            .unwrap_or("")
            .starts_with("nozzle: 2 of 2 prints"),
        "{due:?}"
    );

    // By hand: in maintenance, a new job waits (the printer looks at it and declines);
    // out of it, the job prints.
    let (ok, out) = ctl(
        &config,
        &["maintenance", "start", "a", "--note", "belt check"],
    );
    assert!(ok, "{out}");
    let (ok, out) = ctl(&config, &["maintenance", "start", "a"]);
    assert!(!ok && out.contains("already in maintenance"), "{out}");
    drop_file(
        &hot,
        "four.gcode",
        presliced_gcode("four", 20, 6000).as_bytes(),
    );
    let ready = wait_for(&config, &log, LIMIT, "four ready", |s| {
        state_of(s, "four.gcode") == "ready"
    });
    let s = passed_over(&config, &log, &ready, &["a"], "a passes four over");
    let a = common::printer(&s, "a");
    assert_eq!(a["state"], "maintenance", "{a}");
    assert_eq!(a["held"]["note"], "belt check", "{a}");
    let (ok, out) = ctl(&config, &["maintenance", "end", "a"]);
    assert!(ok && out.contains("out of maintenance"), "{out}");
    clear_after_done(&config, &log, "a", "four.gcode");
    let log_entries = care_json(&config, &["log", "a"])["log"].clone();
    let kinds: Vec<&str> = log_entries
        .as_array()
        .unwrap()
        .iter()
        .map(|e| e["what"]["kind"].as_str().unwrap_or(""))
        .collect();
    assert_eq!(kinds, ["done", "held", "released"]);
}

/// The dashboard in a real browser: a blocking task due shows on the printer's tile with
/// what it reached and a **Done** button; clicking it records the work (by `dashboard`)
/// and the printer goes back to idle; **Maintenance** and **End maintenance** hold it and
/// give it back.
#[test]
fn the_tile_shows_a_due_task_and_records_it_done_in_a_real_browser() {
    use common::http::request;
    const KEY: &str = "maintenance-key-0123456789abcdef";
    let tmp = tempfile::tempdir().unwrap();
    let root = tmp.path();
    std::fs::create_dir_all(root.join("hot")).unwrap();
    std::fs::write(root.join("key"), KEY).unwrap();
    let config = root.join("crispen.toml");
    std::fs::write(
        &config,
        "[spool]\ndir = \"spool\"\n[control]\nsocket = \"c.sock\"\n[farm]\nsettle_s = 0.2\n\
         [http]\nlisten = \"127.0.0.1:0\"\napi_key_file = \"key\"\n\
         [[printer]]\nname = \"a\"\nfirmware = \"marlin2\"\n[printer.simulate]\ntime_scale = 0.0\n\
         [[folder]]\npath = \"hot\"\nheight_mm = 1\nprinters = [\"a\"]\n\
         [[maintenance]]\nname = \"nozzle\"\nevery_jobs = 1\nblock = true\n",
    )
    .unwrap();
    let log = root.join("daemon.log");
    let _daemon = Daemon::start(&config, &log);
    let addr = common::daemon::http_address(&log);
    drop_file(
        &root.join("hot"),
        "one.gcode",
        presliced_gcode("one", 20, 6000).as_bytes(),
    );
    clear_after_done(&config, &log, "a", "one.gcode");

    let browser = crate::http::Browser::start(&root.join("chromium-profile"));
    browser.go(&format!("http://{addr}/"));
    browser.exec(
        "localStorage.setItem('crispen-key', arguments[0]); window.confirm = () => true;",
        serde_json::json!([KEY]),
    );
    browser.go(&format!("http://{addr}/"));
    browser.wait_until(
        LIMIT,
        "the due task on a's tile",
        "const t = document.querySelector('article[data-printer=\"a\"]');
         const li = t && t.querySelector('ul.care li.blocking');
         return (!!li && t.classList.contains('state-maintenance') && /nozzle due: 1 of 1 prints/.test(li.textContent)
           && !!li.querySelector('button[data-action=\"caredone\"][data-task=\"nozzle\"]'))
           || (t ? t.textContent : 'no tile');",
    );
    browser.exec(
        "window.confirm = () => true;
         document.querySelector('button[data-action=\"caredone\"][data-task=\"nozzle\"]').click();",
        serde_json::json!([]),
    );
    browser.wait_until(
        LIMIT,
        "a idle, nothing due",
        "const t = document.querySelector('article[data-printer=\"a\"]');
         return (!!t && t.classList.contains('state-idle') && !t.querySelector('ul.care')
           && !/maintenance due/.test(t.textContent)
           && !!t.querySelector('button[data-action=\"carestart\"]')) || (t ? t.className + ' ' + t.textContent : 'no tile');",
    );
    let record = request(
        &addr,
        "GET",
        "/api/v1/printers/a/maintenance",
        &[("X-Api-Key", KEY)],
        b"",
    )
    .json();
    assert_eq!(record["log"][0]["what"]["task"], "nozzle", "{record}");
    assert_eq!(record["log"][0]["work"]["by"], "dashboard", "{record}");
    // By hand, from the tile.
    browser.exec(
        "window.confirm = () => true;
         document.querySelector('button[data-action=\"carestart\"]').click();",
        serde_json::json!([]),
    );
    browser.wait_until(
        LIMIT,
        "a in maintenance by hand",
        "const t = document.querySelector('article[data-printer=\"a\"]');
         return (!!t && t.classList.contains('state-maintenance') && /by dashboard/.test(t.textContent)
           && !!t.querySelector('button[data-action=\"careend\"]')) || (t ? t.textContent : 'no tile');",
    );
    browser.click("button[data-action=\"careend\"]");
    browser.wait_until(
        LIMIT,
        "a idle again",
        "const t = document.querySelector('article[data-printer=\"a\"]');
         return (!!t && t.classList.contains('state-idle') && !/in maintenance/.test(t.textContent))
           || (t ? t.textContent : 'no tile');",
    );
    let shots = Path::new(env!("CARGO_TARGET_TMPDIR"));
    browser.screenshot(&shots.join("dashboard-maintenance.png"));
}
