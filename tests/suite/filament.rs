//! A farm that knows what its printers hold: the real daemon with four simulated printers
//! holding two materials, two colours and two nozzles (one in a group), and a folder of
//! pre-sliced jobs asking for them. Each job ends on a printer that holds what it asked
//! for, in priority order; a job nobody can take waits with the reason; a job larger than
//! its spool waits until a fuller one is loaded; what each print took is booked to its
//! spool to the gram of what the simulator executed. With Spoolman (the real server,
//! `CRISPEN_SPOOLMAN_DIR`), what Spoolman holds after the jobs equals its starting weights
//! less what the printers executed, a `kill -9` mid-print included.

use crate::common;

use common::daemon::{ctl, recorded, status, wait_for, Daemon};
use common::farm::{drop_file, markers, presliced_gcode, state_of};
use crispen::marlin::firmware::Firmware;
use serde_json::Value;
use std::path::{Path, PathBuf};
use std::time::{Duration, Instant};

/// Grams of 1.75 mm filament per mm at `density`.
fn grams_per_mm(density: f64) -> f64 {
    let r_cm = 1.75 / 20.0;
    std::f64::consts::PI * r_cm * r_cm * 0.1 * density
}

/// Filament a simulator executed, mm: its record followed as Marlin follows it.
fn executed_mm(record: &Path) -> f64 {
    let lines = recorded(record);
    crispen::marlin::motion::extruded_mm(lines.iter().map(String::as_str), Firmware::Marlin2)
}

/// Executed mm per job marker (`M118 <marker>` starts each job's lines in the record).
fn executed_by_marker(record: &Path) -> Vec<(String, f64)> {
    let mut out: Vec<(String, Vec<String>)> = Vec::new();
    for line in recorded(record) {
        if let Some(m) = line.trim().strip_prefix("M118 ") {
            out.push((m.trim().to_string(), Vec::new()));
        } else if let Some(last) = out.last_mut() {
            last.1.push(line);
        }
    }
    out.into_iter()
        .map(|(m, lines)| {
            let mm = crispen::marlin::motion::extruded_mm(
                lines.iter().map(String::as_str),
                Firmware::Marlin2,
            );
            (m, mm)
        })
        .collect()
}

/// Pre-sliced G-code for a 0.6 mm nozzle (its header says so; the machine check reads it).
fn gcode_for_nozzle(marker: &str, moves: usize, nozzle: &str) -> String {
    presliced_gcode(marker, moves, 6000).replace(
        "; nozzle_diameter = 0.4",
        &format!("; nozzle_diameter = {nozzle}"),
    )
}

fn job<'a>(s: &'a Value, file: &str) -> &'a Value {
    common::job_by_file(s, file).unwrap_or_else(|| panic!("no job {file}: {s}"))
}

fn spools(config: &Path) -> Value {
    let (ok, out) = ctl(config, &["spools", "--json", "--archived"]);
    assert!(ok, "{out}");
    serde_json::from_str(&out).unwrap()
}

fn spool<'a>(list: &'a Value, id: &str) -> &'a Value {
    list["spools"]
        .as_array()
        .unwrap()
        .iter()
        .find(|s| s["id"] == id)
        .unwrap_or_else(|| panic!("no spool {id}: {list}"))
}

/// Four printers: a PLA white (group `big`), b PLA black, c PETG black, d PETG white on a
/// 0.6 mm nozzle; every bed starts not cleared so that every job is ready before any
/// printer takes one.
fn four_printers(root: &Path, extra: &str) -> (PathBuf, PathBuf) {
    std::fs::create_dir_all(root.join("hot")).unwrap();
    std::fs::create_dir_all(root.join("spool")).unwrap();
    std::fs::write(
        root.join("spool/printers.json"),
        r#"{"a": {"bed_not_cleared": true, "last_job": null},
            "b": {"bed_not_cleared": true, "last_job": null},
            "c": {"bed_not_cleared": true, "last_job": null},
            "d": {"bed_not_cleared": true, "last_job": null}}"#,
    )
    .unwrap();
    let mut text = format!(
        "[spool]\ndir = \"spool\"\n[control]\nsocket = \"c.sock\"\n[farm]\nsettle_s = 0.3\nmax_heating = 4\n{extra}"
    );
    for (name, more) in [
        ("a", "tags = [\"big\"]\n"),
        ("b", ""),
        ("c", ""),
        ("d", "nozzle_mm = 0.6\n"),
    ] {
        text += &format!(
            "[[printer]]\nname = \"{name}\"\nfirmware = \"marlin2\"\n{more}[printer.simulate]\ntime_scale = 0.0\nrecord = \"{name}.rec\"\n"
        );
    }
    text += "[[folder]]\npath = \"hot\"\nheight_mm = 1\nprinters = [\"a\", \"b\", \"c\", \"d\"]\n";
    let config = root.join("crispen.toml");
    std::fs::write(&config, text).unwrap();
    (config, root.join("daemon.log"))
}

/// Clears every bed that waits for it until `done` holds.
fn clear_until(config: &Path, log: &Path, what: &str, done: impl Fn(&Value) -> bool) -> Value {
    let started = Instant::now();
    loop {
        let s = status(config).unwrap_or(Value::Null);
        if s.is_object() && done(&s) {
            return s;
        }
        for p in ["a", "b", "c", "d"] {
            let waiting = s["printers"]
                .as_array()
                .into_iter()
                .flatten()
                .any(|x| x["name"] == p && x["bed_cleared"] == false);
            if waiting {
                ctl(config, &["clear", p]);
            }
        }
        assert!(
            started.elapsed() < Duration::from_secs(120),
            "timed out waiting for {what}\nstatus: {s}\nlog:\n{}",
            std::fs::read_to_string(log).unwrap_or_default()
        );
        std::thread::sleep(Duration::from_millis(150));
    }
}

#[test]
fn jobs_go_to_the_printers_that_hold_what_they_ask() {
    let tmp = tempfile::tempdir().unwrap();
    let root = tmp.path();
    let (config, log) = four_printers(root, "");
    let _daemon = Daemon::start(&config, &log);
    wait_for(
        &config,
        &log,
        Duration::from_secs(30),
        "the printers",
        |s| s["printers"].as_array().is_some_and(|p| p.len() == 4),
    );
    for (printer, args) in [
        (
            "a",
            "--material PLA --colour white --grams 1000 --price-per-kg 20",
        ),
        (
            "b",
            "--material PLA --colour black --grams 1000 --price-per-kg 20",
        ),
        // Enough for a small job, not for the heavy one.
        (
            "c",
            "--material PETG --colour black --grams 20 --price-per-kg 30",
        ),
        ("d", "--material PETG --colour white --grams 1000"),
    ] {
        let mut argv = vec!["load", printer];
        argv.extend(args.split(' '));
        let (ok, out) = ctl(&config, &argv);
        assert!(ok && out.contains("loaded"), "{out}");
    }
    let hot = root.join("hot");
    let sidecar =
        |name: &str, text: &str| drop_file(&hot, &format!("{name}.toml"), text.as_bytes());
    // Each job's sidecar first, then its G-code: the sidecar is read as it is prepared.
    let jobs: &[(&str, &str, String)] = &[
        (
            "petg-black",
            "material = \"PETG\"\ncolour = \"black\"\n",
            presliced_gcode("petg-black", 100, 6000),
        ),
        (
            "nozzle-06",
            "nozzle_mm = 0.6\n",
            gcode_for_nozzle("nozzle-06", 100, "0.6"),
        ),
        (
            "big",
            "tags = [\"big\"]\n",
            presliced_gcode("big", 100, 6000),
        ),
        // Dropped oldest first: the priority, not the age, orders them.
        (
            "black-low",
            "material = \"PLA\"\ncolour = \"black\"\npriority = -5\n",
            presliced_gcode("black-low", 50, 6000),
        ),
        (
            "black-mid",
            "material = \"PLA\"\ncolour = \"black\"\n",
            presliced_gcode("black-mid", 50, 6000),
        ),
        (
            "black-high",
            "material = \"PLA\"\ncolour = \"black\"\npriority = 10\n",
            presliced_gcode("black-high", 50, 6000),
        ),
        (
            "abs",
            "material = \"ABS\"\ncolour = \"red\"\n",
            presliced_gcode("abs", 50, 6000),
        ),
        // About 30 g of PETG: more than c's spool holds.
        (
            "heavy",
            "material = \"PETG\"\ncolour = \"black\"\n",
            presliced_gcode("heavy", 3000, 6000),
        ),
    ];
    for (name, asks, gcode) in jobs {
        sidecar(&format!("{name}.gcode"), asks);
        drop_file(&hot, &format!("{name}.gcode"), gcode.as_bytes());
    }
    let s = wait_for(
        &config,
        &log,
        Duration::from_secs(60),
        "every job ready",
        |s| {
            jobs.iter()
                .all(|(n, _, _)| state_of(s, &format!("{n}.gcode")) == "ready")
        },
    );
    // The jobs nobody can take say why, in the operator's words.
    let abs = job(&s, "abs.gcode")["waiting"].as_str().unwrap_or_default();
    assert!(
        abs.starts_with("waiting for ABS red: loaded are PLA white (a")
            && abs.contains("PLA black (b)")
            && abs.contains("PETG black (c)"),
        "{abs}"
    );
    let heavy = job(&s, "heavy.gcode")["waiting"]
        .as_str()
        .unwrap_or_default();
    assert!(
        heavy.starts_with("waiting for 30 g of PETG black: c has 20 g;"),
        "{heavy}"
    );
    assert!(job(&s, "petg-black.gcode")["waiting"].is_null());
    // The tiles show what each printer holds.
    let c = common::printer(&s, "c");
    assert_eq!(c["holds"]["filament"]["material"], "PETG");
    assert_eq!(c["holds"]["remaining_g"], 20.0);
    assert_eq!(common::printer(&s, "d")["holds"]["nozzle_mm"], 0.6);

    let printable = [
        "petg-black",
        "nozzle-06",
        "big",
        "black-low",
        "black-mid",
        "black-high",
    ];
    clear_until(&config, &log, "the printable jobs done", |s| {
        printable
            .iter()
            .all(|n| state_of(s, &format!("{n}.gcode")) == "done")
    });
    let markers_of = |p: &str| markers(&root.join(format!("{p}.rec")));
    assert_eq!(markers_of("a"), ["big"]);
    assert_eq!(markers_of("b"), ["black-high", "black-mid", "black-low"]);
    assert_eq!(markers_of("c"), ["petg-black"]);
    assert_eq!(markers_of("d"), ["nozzle-06"]);

    // The heavy job still waits; a fuller spool on c lets it print.
    let s = status(&config).unwrap();
    assert_eq!(state_of(&s, "heavy.gcode"), "ready");
    let (ok, out) = ctl(
        &config,
        &[
            "load",
            "c",
            "--material",
            "PETG",
            "--colour",
            "black",
            "--grams",
            "750",
            "--price-per-kg",
            "30",
        ],
    );
    assert!(ok, "{out}");
    let s = clear_until(&config, &log, "the heavy job done", |s| {
        state_of(s, "heavy.gcode") == "done"
    });
    assert_eq!(markers_of("c"), ["petg-black", "heavy"]);
    assert_eq!(state_of(&s, "abs.gcode"), "ready", "nobody holds ABS");

    // What each print took is what its printer executed, booked to the spool it ran on.
    let list = spools(&config);
    let petg = grams_per_mm(1.27);
    let pla = grams_per_mm(1.24);
    let by_marker: Vec<(String, f64)> = ["a", "b", "c", "d"]
        .iter()
        .flat_map(|p| executed_by_marker(&root.join(format!("{p}.rec"))))
        .collect();
    let mm_of = |m: &str| {
        by_marker
            .iter()
            .find(|(k, _)| k == m)
            .map(|(_, mm)| *mm)
            .unwrap()
    };
    for (name, density, price) in [
        ("petg-black", petg, Some(30.0)),
        ("heavy", petg, Some(30.0)),
        ("black-high", pla, Some(20.0)),
        ("nozzle-06", petg, None),
    ] {
        let j = job(&s, &format!("{name}.gcode"));
        let expected = mm_of(name) * density;
        let used = j["used_g"].as_f64().unwrap();
        assert!(
            (used - expected).abs() < 1e-6,
            "{name}: used {used} g, executed {expected} g"
        );
        match price {
            Some(p) => assert!((j["cost"].as_f64().unwrap() - expected * p / 1000.0).abs() < 1e-6),
            None => assert!(j["cost"].is_null(), "{name}: no price, no cost"),
        }
    }
    // c's first spool: 20 g less the small job; the new one: 750 g less the heavy one.
    let first = spool(&list, "s3");
    assert!(
        (first["remaining_g"].as_f64().unwrap() - (20.0 - mm_of("petg-black") * petg)).abs() < 1e-6
    );
    let fresh = spool(&list, "s5");
    assert_eq!(fresh["loaded_on"], "c");
    assert!(
        (fresh["remaining_g"].as_f64().unwrap() - (750.0 - mm_of("heavy") * petg)).abs() < 1e-6
    );
    let b = spool(&list, "s2");
    let executed_b = executed_mm(&root.join("b.rec")) * pla;
    assert!((b["remaining_g"].as_f64().unwrap() - (1000.0 - executed_b)).abs() < 1e-6);

    // A spool cannot be on two printers, nor changed under a print; bad input is refused
    // with the key.
    let (ok, out) = ctl(&config, &["load", "a", "--spool", "s5"]);
    assert!(!ok && out.contains("spool s5 is loaded on c"), "{out}");
    let (ok, out) = ctl(
        &config,
        &[
            "load",
            "a",
            "--material",
            "PLA",
            "--colour",
            "white",
            "--grams=-3",
        ],
    );
    assert!(!ok && out.contains("grams"), "{out}");
    let (ok, out) = ctl(&config, &["load", "zz", "--spool", "s1"]);
    assert!(!ok && out.contains("no printer"), "{out}");
    // Unloaded, a printer takes nothing and says so.
    let (ok, out) = ctl(&config, &["unload", "a"]);
    assert!(ok, "{out}");
    let s = status(&config).unwrap();
    assert_eq!(common::printer(&s, "a")["holds"]["unloaded"], true);
    let abs = job(&s, "abs.gcode")["waiting"].as_str().unwrap_or_default();
    assert!(abs.contains("nothing (a)"), "{abs}");
}

/// With Spoolman: its spools are the farm's, and after the jobs each spool's weight in
/// Spoolman is its starting weight less what the printers executed, to the gram, a
/// `kill -9` in the middle of a print and the restart after it included.
#[cfg_attr(
    not(crispen_spoolman),
    ignore = "CRISPEN_SPOOLMAN_DIR was unset at build time"
)]
#[test]
fn spoolman_holds_what_the_printers_pushed_across_a_kill() {
    let spoolman = common::spoolman::SpoolmanServer::start();
    let pla_id = spoolman.create_spool("PLA", "ffffff", "Acme", 1000.0, 0.0, 20.0, 1.75);
    // A filament no farm spool could be (a density of 80 g/cm³), between the two: it is
    // set aside alone, with why, and the others are taken (it was taken as it was).
    let unlikely = spoolman.create_raw(
        serde_json::json!({"material": "PLA", "density": 80.0, "diameter": 1.75, "weight": 1000.0}),
        serde_json::json!({}),
    );
    let petg_id = spoolman.create_spool("PETG", "000000", "Acme", 500.0, 100.0, 30.0, 1.75);
    let tmp = tempfile::tempdir().unwrap();
    let root = tmp.path();
    std::fs::create_dir_all(root.join("hot")).unwrap();
    let config = root.join("crispen.toml");
    // b prints at a twentieth of real time: slow enough to be killed mid-print.
    std::fs::write(
        &config,
        format!(
            "[spool]\ndir = \"spool\"\n[control]\nsocket = \"c.sock\"\n[farm]\nsettle_s = 0.3\n\
             [spoolman]\nurl = \"{}\"\npoll_s = 1\n\
             [[printer]]\nname = \"a\"\nfirmware = \"marlin2\"\n[printer.simulate]\ntime_scale = 0.0\nrecord = \"a.rec\"\n\
             [[printer]]\nname = \"b\"\nfirmware = \"marlin2\"\n[printer.simulate]\ntime_scale = 0.05\nrecord = \"b.rec\"\n\
             [[folder]]\npath = \"hot\"\nheight_mm = 1\nprinters = [\"a\", \"b\"]\n",
            spoolman.url
        ),
    )
    .unwrap();
    let log = root.join("daemon.log");
    let mut daemon = Daemon::start(&config, &log);
    let (pla, petg) = (format!("sm{pla_id}"), format!("sm{petg_id}"));
    let started = Instant::now();
    loop {
        let (ok, out) = ctl(&config, &["spools", "--json"]);
        if ok && out.contains(&format!("\"{pla}\"")) && out.contains(&format!("\"{petg}\"")) {
            let list: Value = serde_json::from_str(&out).unwrap();
            assert_eq!(list["source"], "spoolman");
            assert_eq!(spool(&list, &pla)["material"], "PLA");
            assert_eq!(spool(&list, &pla)["colour"], "white");
            assert_eq!(spool(&list, &petg)["remaining_g"], 400.0);
            assert_eq!(spool(&list, &petg)["price_per_kg"], 30.0);
            let aside = &list["set_aside"];
            assert_eq!(aside.as_array().map(Vec::len), Some(1), "{list:#}");
            assert_eq!(aside[0]["id"], format!("sm{unlikely}"));
            assert_eq!(
                aside[0]["reason"],
                format!("spool {unlikely}: density: 0.5 to 5 g/cm³, got 80")
            );
            assert!(list["spools"]
                .as_array()
                .unwrap()
                .iter()
                .all(|s| s["id"] != format!("sm{unlikely}")));
            break;
        }
        assert!(
            started.elapsed() < Duration::from_secs(60),
            "the daemon never read Spoolman's spools: {out}\n{}",
            std::fs::read_to_string(&log).unwrap_or_default()
        );
        std::thread::sleep(Duration::from_millis(200));
    }
    // A new spool belongs in Spoolman, not in crispen.
    let (ok, out) = ctl(
        &config,
        &[
            "load",
            "a",
            "--material",
            "PLA",
            "--colour",
            "red",
            "--grams",
            "5",
        ],
    );
    assert!(!ok && out.contains("Spoolman"), "{out}");
    // The spool set aside is not loaded, and says why; `crispen spools` lists it apart.
    let (ok, out) = ctl(&config, &["load", "a", "--spool", &format!("sm{unlikely}")]);
    assert!(
        !ok && out.contains("was set aside") && out.contains("density"),
        "{out}"
    );
    let (ok, table) = ctl(&config, &["spools"]);
    assert!(ok, "{table}");
    let aside = table.split("set aside").nth(1).unwrap_or_default();
    assert!(
        aside.contains(&format!("sm{unlikely}")) && aside.contains("got 80"),
        "{table}"
    );
    // Logged when it was first set aside, not at each read: two reads later, still once.
    let listed = spoolman.listings();
    let started = Instant::now();
    while spoolman.listings() < listed + 2 {
        assert!(started.elapsed() < Duration::from_secs(60), "no more reads");
        std::thread::sleep(Duration::from_millis(100));
    }
    let said = std::fs::read_to_string(&log)
        .unwrap()
        .lines()
        .filter(|l| l.contains("a spool of Spoolman's is set aside"))
        .count();
    assert_eq!(said, 1, "logged once");
    for (printer, id) in [("a", &pla), ("b", &petg)] {
        let (ok, out) = ctl(&config, &["load", printer, "--spool", id]);
        assert!(ok, "{out}");
    }
    let hot = root.join("hot");
    drop_file(&hot, "pla.gcode.toml", b"material = \"PLA\"\n");
    drop_file(
        &hot,
        "pla.gcode",
        presliced_gcode("pla", 300, 6000).as_bytes(),
    );
    drop_file(&hot, "petg.gcode.toml", b"material = \"PETG\"\n");
    drop_file(
        &hot,
        "petg.gcode",
        presliced_gcode("petg", 200, 6000).as_bytes(),
    );
    let acked = |s: &Value| {
        job(s, "petg.gcode")["progress"]["lines_acked"]
            .as_u64()
            .unwrap_or(0)
    };
    wait_for(
        &config,
        &log,
        Duration::from_secs(60),
        "pla done, petg part printed",
        |s| {
            state_of(s, "pla.gcode") == "done"
                && state_of(s, "petg.gcode") == "printing"
                && acked(s) > 60
        },
    );
    daemon.kill9();

    // The restart interrupts the print, and books what it had pushed.
    let mut daemon = Daemon::start(&config, &log);
    let s = wait_for(
        &config,
        &log,
        Duration::from_secs(60),
        "petg interrupted",
        |s| {
            state_of(s, "petg.gcode") == "interrupted"
                && job(s, "petg.gcode")["used_g"].as_f64().is_some()
        },
    );
    let partial = job(&s, "petg.gcode")["used_g"].as_f64().unwrap();
    let petg_g = grams_per_mm(1.27);
    let executed_before = executed_mm(&root.join("b.rec")) * petg_g;
    eprintln!(
        "killed mid-print: booked {partial:.3} g, the printer had executed {executed_before:.3} g"
    );
    assert!(
        (partial - executed_before).abs() < 0.25,
        "the interrupted print booked {partial} g; b executed {executed_before} g"
    );
    // Printed again from the start once the bed is clear.
    assert!(ctl(&config, &["clear", "b"]).0);
    let (ok, out) = ctl(
        &config,
        &["retry", job(&s, "petg.gcode")["id"].as_str().unwrap()],
    );
    assert!(ok, "{out}");
    wait_for(&config, &log, Duration::from_secs(120), "petg done", |s| {
        state_of(s, "petg.gcode") == "done"
    });

    // Spoolman has each use once: its weights are the starting ones less what was executed.
    let expected_pla = 1000.0 - executed_mm(&root.join("a.rec")) * grams_per_mm(1.24);
    let expected_petg = 400.0 - executed_mm(&root.join("b.rec")) * petg_g;
    let remaining = |id: u64| {
        spoolman.spool_json(id)["remaining_weight"]
            .as_f64()
            .unwrap()
    };
    let settled = |what: &str| {
        let started = Instant::now();
        loop {
            let list = spools(&config);
            let pending: u64 = list["spools"]
                .as_array()
                .unwrap()
                .iter()
                .map(|s| s["unreported"].as_u64().unwrap_or(0))
                .sum();
            if pending == 0 {
                return list;
            }
            assert!(
                started.elapsed() < Duration::from_secs(60),
                "{what}: uses still unreported: {list}\n{}",
                std::fs::read_to_string(&log).unwrap_or_default()
            );
            std::thread::sleep(Duration::from_millis(200));
        }
    };
    let list = settled("after the jobs");
    for (id, farm_id, expected) in [
        (pla_id, &pla, expected_pla),
        (petg_id, &petg, expected_petg),
    ] {
        let got = remaining(id);
        eprintln!(
            "spool {id}: Spoolman holds {got:.3} g, the printers executed down to {expected:.3} g"
        );
        assert!(
            (got - expected).abs() < 0.5,
            "spool {id}: Spoolman holds {got} g, the printers executed down to {expected} g"
        );
        // crispen shows what Spoolman holds.
        let shown = spool(&list, farm_id)["remaining_g"].as_f64().unwrap();
        assert!(
            (shown - got).abs() < 1e-6,
            "{farm_id}: shown {shown} g, Spoolman {got} g"
        );
    }
    // Nothing is told twice: a restart leaves Spoolman as it is. The restarted daemon's
    // first round tells Spoolman what it has not counted, then lists the spools: once
    // Spoolman has been asked for the list, that round's telling is over.
    let before = (remaining(pla_id), remaining(petg_id));
    daemon.kill9();
    let listed = spoolman.listings();
    let _daemon = Daemon::start(&config, &log);
    let started = Instant::now();
    while spoolman.listings() == listed {
        assert!(
            started.elapsed() < Duration::from_secs(60),
            "the restarted daemon never listed the spools:\n{}",
            std::fs::read_to_string(&log).unwrap_or_default()
        );
        std::thread::sleep(Duration::from_millis(100));
    }
    settled("after a restart");
    assert_eq!((remaining(pla_id), remaining(petg_id)), before);
}

/// A name with a control or bidi character is refused wherever the operator gives one
/// on the command line (a new spool's material, colour and brand, a spool's id), naming
/// the key and showing the name escaped; and one stored before names were checked is
/// printed escaped by `crispen spools`, never raw (a material with U+202E was taken and
/// printed as it was).
#[test]
fn names_with_control_or_bidi_characters_are_refused_and_never_printed_raw() {
    let tmp = tempfile::tempdir().unwrap();
    let root = tmp.path();
    std::fs::create_dir_all(root.join("hot")).unwrap();
    std::fs::create_dir_all(root.join("spool")).unwrap();
    std::fs::write(
        root.join("spool/filament.json"),
        serde_json::json!({
            "spools": {"s1": {
                "id": "s1", "material": "PLA\u{202e}GTEP", "colour": "wh\u{1b}[31mite",
                "brand": "Acme\u{2067}", "diameter_mm": 1.75, "density_g_cm3": 1.24,
                "base_g": 750.0, "uses": {}, "archived": false
            }},
            "loaded": {},
            "next_id": 1
        })
        .to_string(),
    )
    .unwrap();
    let config = root.join("crispen.toml");
    std::fs::write(
        &config,
        "[spool]\ndir = \"spool\"\n[control]\nsocket = \"c.sock\"\n\
         [[printer]]\nname = \"p\"\nfirmware = \"marlin2\"\n[printer.simulate]\ntime_scale = 0.0\n\
         [[folder]]\npath = \"hot\"\nheight_mm = 1\nprinters = [\"p\"]\n",
    )
    .unwrap();
    let log = root.join("daemon.log");
    let _daemon = Daemon::start(&config, &log);
    wait_for(&config, &log, Duration::from_secs(30), "the daemon", |s| {
        s["printers"].as_array().is_some_and(|p| p.len() == 1)
    });
    let raw = ['\u{202e}', '\u{1b}', '\u{2067}', '\u{7}', '\u{2028}'];
    let (ok, table) = ctl(&config, &["spools"]);
    assert!(ok, "{table}");
    assert!(
        table.contains("PLA\\u{202e}GTEP") && table.contains("wh\\u{1b}[31mite"),
        "{table}"
    );
    assert!(!table.contains(raw), "raw in the table: {table:?}");

    let new_spool = |material: &str, colour: &str, brand: &str| {
        ctl(
            &config,
            &[
                "load",
                "p",
                "--material",
                material,
                "--colour",
                colour,
                "--grams",
                "750",
                "--brand",
                brand,
            ],
        )
    };
    for ((ok, out), key, shown) in [
        (
            new_spool("PLA\u{202e}", "white", "Acme"),
            "material",
            "PLA\\u{202e}",
        ),
        (
            new_spool("PLA", "wh\u{7}ite", "Acme"),
            "colour",
            "wh\\u{7}ite",
        ),
        (
            new_spool("PLA", "white", "Ac\u{2028}me"),
            "brand",
            "Ac\\u{2028}me",
        ),
        (
            ctl(&config, &["load", "p", "--spool", "s1\u{2067}"]),
            "spool",
            "s1\\u{2067}",
        ),
    ] {
        assert!(!ok, "{out}");
        assert!(
            out.contains(key) && out.contains(shown) && out.contains("contains"),
            "{key}: {out}"
        );
        assert!(!out.contains(raw), "raw in the answer: {out:?}");
    }
    // Nothing was added; the stored spool is still the only one.
    let list = spools(&config);
    assert_eq!(list["spools"].as_array().unwrap().len(), 1, "{list}");
    assert!(
        !std::fs::read_to_string(&log).unwrap().contains(raw),
        "raw in the log"
    );
}

/// The dashboard in a real headless Chromium: each tile shows what its printer holds (a
/// swatch of the spool's colour, its material, what is left, its nozzle); "Load spool"
/// opens the panel, a spool picked there is loaded; a job nobody can take shows why.
#[test]
fn spools_on_the_dashboard_in_a_real_browser() {
    use common::http::request;
    const KEY: &str = "filament-key-0123456789abcdef";
    let tmp = tempfile::tempdir().unwrap();
    let root = tmp.path();
    std::fs::create_dir_all(root.join("hot")).unwrap();
    std::fs::write(root.join("key"), KEY).unwrap();
    let config = root.join("crispen.toml");
    std::fs::write(
        &config,
        "[spool]\ndir = \"spool\"\n[control]\nsocket = \"c.sock\"\n[farm]\nsettle_s = 0.3\n\
         [http]\nlisten = \"127.0.0.1:0\"\napi_key_file = \"key\"\n\
         [[printer]]\nname = \"alpha\"\nfirmware = \"marlin2\"\ntags = [\"big\"]\n[printer.simulate]\ntime_scale = 0.0\n\
         [[printer]]\nname = \"beta\"\nfirmware = \"marlin2\"\nnozzle = \"hardened\"\n[printer.simulate]\ntime_scale = 0.0\n\
         [[folder]]\npath = \"hot\"\nheight_mm = 1\nprinters = [\"alpha\", \"beta\"]\n",
    )
    .unwrap();
    let log = root.join("daemon.log");
    let _daemon = Daemon::start(&config, &log);
    let addr = common::daemon::http_address(&log);
    let key = [("X-Api-Key", KEY)];
    let post = |path: &str| {
        let a = request(&addr, "POST", path, &key, b"");
        assert_eq!(a.status, 200, "{path}: {}", a.text());
        a.json()
    };
    post("/api/v1/printers/alpha/load?material=PLA&colour=white&colour_hex=f4f4f4&grams=1000&price_per_kg=20&brand=Acme");
    let added = post(
        "/api/v1/spools?material=PETG&colour=black&colour_hex=101010&grams=750&price_per_kg=30",
    );
    assert!(
        added["message"]
            .as_str()
            .unwrap()
            .starts_with("spool s2 added"),
        "{added}"
    );
    // Bad requests name what is wrong.
    let a = request(
        &addr,
        "POST",
        "/api/v1/spools?material=PETG&grams=5",
        &key,
        b"",
    );
    assert_eq!(a.status, 400);
    assert!(a.error().contains("`colour`"), "{}", a.error());
    let a = request(
        &addr,
        "POST",
        "/api/v1/spools?material=PETG&colour=x&grams=5&colour=y&weight=2",
        &key,
        b"",
    );
    assert_eq!(a.status, 400, "{}", a.text());
    let a = request(
        &addr,
        "POST",
        "/api/v1/printers/beta/load?spool=s9",
        &key,
        b"",
    );
    assert_eq!(a.status, 404, "{}", a.text());
    let a = request(
        &addr,
        "POST",
        "/api/v1/printers/beta/load?spool=s1",
        &[],
        b"",
    );
    assert_eq!(a.status, 401, "changes need the key");
    // A job nobody can take.
    for (name, body) in [
        ("abs.gcode.toml", b"material = \"ABS\"\n".to_vec()),
        ("abs.gcode", presliced_gcode("abs", 20, 6000).into_bytes()),
    ] {
        let a = request(
            &addr,
            "PUT",
            &format!("/api/v1/folders/hot/files/{name}"),
            &key,
            &body,
        );
        assert_eq!(a.status, 201, "{}", a.text());
    }

    let browser = crate::http::Browser::start(&root.join("chromium-profile"));
    // The key as the page keeps it once entered.
    browser.go(&format!("http://{addr}/"));
    browser.exec(
        "localStorage.setItem('crispen-key', arguments[0]);",
        serde_json::json!([KEY]),
    );
    browser.go(&format!("http://{addr}/"));
    browser.wait_until(
        Duration::from_secs(60),
        "alpha's spool on its tile, and the ABS job's reason",
        "const a = document.querySelector('[data-printer=\"alpha\"]');
         const h = a && a.querySelector('.holds');
         const fill = h && h.querySelector('svg.swatch circle');
         const row = Array.from(document.querySelectorAll('#queue tr[data-job]')).find(r => r.textContent.includes('abs.gcode'));
         const why = row && row.querySelector('.waiting');
         return (!!h && /PLA white/.test(h.textContent) && /s1/.test(h.textContent) && /1000 g left/.test(h.textContent)
           && fill.getAttribute('fill') === '#f4f4f4' && /0.4 mm brass · big/.test(a.querySelector('.nozzle').textContent)
           && !!why && /waiting for ABS: loaded are PLA white \\(alpha\\)/.test(why.textContent))
           || [h && h.textContent, why && why.textContent].join(' | ');",
    );
    // Beta holds nothing known; its panel offers the free spool.
    browser.click("button[data-spool-printer=\"beta\"]");
    browser.wait_until(
        Duration::from_secs(20),
        "the load panel with the free spool",
        "const f = document.querySelector('#loadform');
         return (!f.hidden && /beta/.test(f.querySelector('#loadtitle').textContent)
           && Array.from(f.querySelectorAll('#loadspool option')).some(o => o.value === 's2')
           && !Array.from(f.querySelectorAll('#loadspool option')).some(o => o.value === 's1'))
           || f.textContent;",
    );
    browser.exec(
        "const s = document.querySelector('#loadspool'); s.value = 's2'; s.dispatchEvent(new Event('change'));",
        serde_json::json!([]),
    );
    browser.click("#loadform button[type=submit]");
    browser.wait_until(
        Duration::from_secs(20),
        "beta's tile with the PETG spool",
        "const b = document.querySelector('[data-printer=\"beta\"] .holds');
         return (!!b && /PETG black/.test(b.textContent) && /750 g left/.test(b.textContent)
           && b.querySelector('svg.swatch circle').getAttribute('fill') === '#101010'
           && document.querySelector('#loadform').hidden) || (b && b.textContent);",
    );
    let metrics = request(&addr, "GET", "/metrics", &key, b"").text();
    for line in [
        "crispen_spool_remaining_grams{spool=\"s1\",material=\"PLA\",colour=\"white\",printer=\"alpha\"} 1000",
        "crispen_spool_remaining_grams{spool=\"s2\",material=\"PETG\",colour=\"black\",printer=\"beta\"} 750",
    ] {
        assert!(metrics.lines().any(|l| l == line), "{line} in\n{metrics}");
    }
    let s = status(&config).unwrap();
    assert_eq!(common::printer(&s, "beta")["holds"]["spool"], "s2");
    assert_eq!(common::printer(&s, "beta")["holds"]["hardened"], true);
    let shots = Path::new(env!("CARGO_TARGET_TMPDIR"));
    browser.screenshot(&shots.join("dashboard-spools.png"));
}
