//! Several hosts, one queue: three real `crispen run` daemons, each with two simulated
//! printers, sharing one real PostgreSQL server (tests/common/postgres.rs) through
//! `[store] postgres`. Models and pre-sliced G-code dropped into the hosts' hot folders
//! print exactly once, on any host's printers; a host killed with `kill -9` mid-print
//! loses its work to the others after its lease (its print interrupted, never reprinted on
//! its own, its printers offline); a 20 s outage of the database loses nothing and prints
//! nothing twice. "Exactly once" is checked three ways: the status of every host, the
//! database's own history (`job_history`), and what each simulator executed.

use crate::common;

use common::farm::{drop_file, presliced_gcode, state_of, Farm, HostSpec};
use crispen::marlin::firmware::Firmware;
use crispen::marlin::gcode::GcodeProgram;
use crispen::sim::is_housekeeping;
use serde_json::Value;
use std::collections::{BTreeMap, BTreeSet};
use std::path::Path;
use std::time::{Duration, Instant};

const PRINTERS: [&str; 6] = ["a1", "a2", "b1", "b2", "c1", "c2"];

/// Hosts a, b and c with printers a1 a2, b1 b2, c1 c2; `folders(host)` gives each its hot
/// folders, every folder served by all six printers.
fn three_hosts(time_scale: f64, lease_s: Option<u32>, folders: &[&[&str]; 3]) -> Vec<HostSpec> {
    ["a", "b", "c"]
        .iter()
        .zip(folders)
        .map(|(name, folders)| HostSpec {
            name: name.to_string(),
            printers: vec![format!("{name}1"), format!("{name}2")],
            folders: folders
                .iter()
                .map(|f| (f.to_string(), PRINTERS.map(String::from).to_vec()))
                .collect(),
            time_scale,
            lease_s,
        })
        .collect()
}

fn printer<'a>(s: &'a Value, name: &str) -> Option<&'a Value> {
    s["printers"].as_array()?.iter().find(|p| p["name"] == name)
}

fn host_alive(s: &Value, host: &str) -> Option<bool> {
    s["farm"]["hosts"]
        .as_array()?
        .iter()
        .find(|h| h["name"] == host)?["alive"]
        .as_bool()
}

/// The whole farm is up as `host` sees it: all three hosts alive, all six printers
/// listed, none still connecting.
fn farm_is_up(s: &Value) -> bool {
    ["a", "b", "c"]
        .iter()
        .all(|h| host_alive(s, h) == Some(true))
        && PRINTERS.iter().all(|p| {
            printer(s, p).is_some_and(|p| p["state"] != "connecting" && p["offline"] == false)
        })
}

/// A job that failed, or was interrupted when it should not have been, ends the wait at
/// once, with its reason.
fn nothing_lost(s: &Value, may_be_interrupted: &[&str]) {
    for j in s["jobs"].as_array().into_iter().flatten() {
        let interrupted =
            j["state"] == "interrupted" && !may_be_interrupted.iter().any(|f| j["file"] == *f);
        assert!(
            j["state"] != "failed" && !interrupted,
            "job {} is {}: {}",
            j["file"],
            j["state"],
            j["reason"]
        );
    }
}

/// What a simulator executed, housekeeping dropped.
fn executed(record: &Path) -> Vec<String> {
    std::fs::read_to_string(record)
        .unwrap_or_default()
        .lines()
        .filter(|c| !is_housekeeping(c))
        .map(str::to_string)
        .collect()
}

/// Every job of the farm is in `files`, each done once with one copy, and every host's
/// status comes to say so (each host refreshes its view of the others' work on its own
/// schedule), naming the same printer; returns the printer of each file.
fn all_done_once(farm: &Farm, files: &[String]) -> BTreeMap<String, String> {
    let mut printed_on = BTreeMap::new();
    for h in &farm.hosts {
        let s = farm.wait_status(
            &h.name,
            Duration::from_secs(60),
            "every job done in this host's view",
            |s| files.iter().all(|f| state_of(s, f) == "done"),
        );
        let jobs = s["jobs"].as_array().unwrap();
        assert_eq!(
            jobs.len(),
            files.len(),
            "host {} lists every job of the farm, once: {s}",
            h.name
        );
        for f in files {
            let j = common::job_by_file(&s, f).unwrap();
            assert_eq!(j["copies_done"], 1, "{f} on {}: {j}", h.name);
            let p = j["printer"].as_str().unwrap().to_string();
            let seen = printed_on.entry(f.clone()).or_insert(p.clone());
            assert_eq!(*seen, p, "hosts disagree on {f}'s printer");
        }
    }
    printed_on
}

/// The database's history holds one `printing` entry per job, `except` those that may
/// hold none, and exactly `files.len()` jobs.
fn printed_once_by_history(farm: &Farm, files: &[String], never_printed: &[String]) {
    let ids: BTreeMap<String, String> = farm
        .query("SELECT file, id FROM jobs", &[])
        .iter()
        .map(|r| (r.get(0), r.get(1)))
        .collect();
    assert_eq!(
        ids.len(),
        files.len(),
        "one job per dropped file in the database: {ids:?}"
    );
    let entries = farm.printing_entries();
    for f in files {
        let id = &ids[f];
        let want = if never_printed.contains(f) { 0 } else { 1 };
        assert_eq!(
            entries[id], want,
            "{f} (job {id}) entered `printing` {} times in job_history",
            entries[id]
        );
    }
}

/// Models dropped into two hosts' hot folders (host c has none) are sliced by those
/// hosts and printed by all six printers, each exactly once: first every printer takes
/// one job and holds it on its bed, so even host c's printers print the others' work;
/// then beds are cleared through other hosts than the printers' own and the last two
/// jobs are printed. Each printer executed exactly the G-code of the jobs it printed, in
/// order, and nothing else.
#[test]
fn models_dropped_on_two_hosts_print_exactly_once() {
    let farm = Farm::start(&three_hosts(0.01, None, &[&["hot/a"], &["hot/b"], &[]]));
    for h in ["a", "b", "c"] {
        farm.wait_status(h, Duration::from_secs(120), "the farm up", farm_is_up);
    }
    let spot = std::fs::read(common::model("spot.obj")).unwrap();
    let mut files = Vec::new();
    for host in ["a", "b"] {
        for i in 1..=4 {
            let name = format!("{host}-{i}.obj");
            drop_file(&farm.root.join(format!("hot/{host}")), &name, &spot);
            files.push(name);
        }
    }

    // Eight jobs, six printers, no bed cleared: six printed, one per printer, two ready.
    let s = farm.wait_status(
        "c",
        Duration::from_secs(900),
        "six jobs printed and every bed holding one",
        |s| {
            nothing_lost(s, &[]);
            files.iter().filter(|f| state_of(s, f) == "done").count() == 6
                && PRINTERS
                    .iter()
                    .all(|p| printer(s, p).is_some_and(|p| p["bed_cleared"] == false))
        },
    );
    let mut first_round = BTreeSet::new();
    for f in &files {
        let j = common::job_by_file(&s, f).unwrap();
        if j["state"] == "done" {
            let p = j["printer"].as_str().unwrap();
            assert!(first_round.insert(p.to_string()), "{p} printed twice: {s}");
        } else {
            assert_eq!(j["state"], "ready", "{f} waits for a bed: {j}");
        }
    }
    assert_eq!(first_round.len(), 6, "every printer printed one job");
    for p in PRINTERS {
        let host = printer(&s, p).unwrap()["host"]
            .as_str()
            .unwrap()
            .to_string();
        assert_eq!(host, &p[..1], "{p} is shown on its own host");
    }

    // Clear every bed, each through another host than its own: the last two print.
    let mut cleared = BTreeSet::new();
    farm.wait_until(Duration::from_secs(600), "all eight jobs done", |last| {
        let s = farm.host("a").status()?;
        nothing_lost(&s, &[]);
        for p in PRINTERS {
            if !cleared.contains(p) && printer(&s, p).is_some_and(|p| p["bed_cleared"] == false) {
                let through = if p.starts_with('a') { "b" } else { "a" };
                let (ok, out) = farm.host(through).ctl(&["clear", p]);
                assert!(ok, "crispen clear {p} on host {through}: {out}");
                cleared.insert(p);
            }
        }
        *last = s.to_string();
        files
            .iter()
            .all(|f| state_of(&s, f) == "done")
            .then_some(())
    });
    let printed_on = all_done_once(&farm, &files);
    printed_once_by_history(&farm, &files, &[]);

    // Each printer executed the G-code of its jobs (as stored in the farm database), in
    // the order it printed them, whole and once, and nothing else.
    let order = farm.query(
        "SELECT j.file FROM jobs j JOIN job_history h ON h.job_id = j.id \
         WHERE h.state = 'printing' ORDER BY h.at",
        &[],
    );
    for p in PRINTERS {
        let mut expected = Vec::new();
        for row in &order {
            let file: String = row.get(0);
            if printed_on[&file] != p {
                continue;
            }
            let rows = farm.query(
                "SELECT f.name, f.bytes FROM job_files f JOIN jobs j ON j.id = f.job_id \
                 WHERE j.file = $1 AND f.name LIKE '%.gcode'",
                &[&file],
            );
            assert_eq!(
                rows.len(),
                1,
                "one G-code file stored for {file}: {:?}",
                rows.iter()
                    .map(|r| r.get::<_, String>(0))
                    .collect::<Vec<_>>()
            );
            let bytes: Vec<u8> = rows[0].get(1);
            let program = GcodeProgram::read(&bytes[..], &file, Firmware::Marlin2).unwrap();
            expected.extend(program.iter().map(str::to_owned));
        }
        let ran = executed(&farm.root.join(format!("{p}.rec")));
        assert!(!expected.is_empty(), "{p} printed something");
        if ran != expected {
            let i = (0..ran.len().min(expected.len()))
                .find(|&i| ran[i] != expected[i])
                .unwrap_or(ran.len().min(expected.len()));
            panic!(
                "{p} did not execute its jobs' G-code exactly once, in order: {} commands run, \
                 {} expected; first difference at {i}: ran {:?}, expected {:?}",
                ran.len(),
                expected.len(),
                &ran[i.saturating_sub(2)..(i + 3).min(ran.len())],
                &expected[i.saturating_sub(2)..(i + 3).min(expected.len())]
            );
        }
    }
}

/// A stand-in slicer that never finishes (it writes its pid, then sleeps).
fn endless_slicer(root: &Path) -> std::path::PathBuf {
    let script = root.join("endless-slicer");
    std::fs::write(
        &script,
        format!(
            "#!/bin/sh\necho $$ >> {}\nexec sleep 900\n",
            root.join("endless-slicer.pids").display()
        ),
    )
    .unwrap();
    std::fs::set_permissions(&script, std::os::unix::fs::PermissionsExt::from_mode(0o755)).unwrap();
    script
}

/// Stops the stand-in slicers a killed host left behind, by the pids they wrote.
fn stop_endless_slicers(root: &Path) {
    let pids = std::fs::read_to_string(root.join("endless-slicer.pids")).unwrap_or_default();
    for pid in pids.lines().filter_map(|l| l.trim().parse::<i32>().ok()) {
        let _ = nix::sys::signal::kill(
            nix::unistd::Pid::from_raw(pid),
            nix::sys::signal::Signal::SIGKILL,
        );
    }
}

/// Host a, alone at first, takes two long pre-sliced prints and three models from a
/// folder all three hosts serve; its slicer hangs, so it holds a model in `preparing`.
/// Hosts b and c join; a is killed with `kill -9` mid-print. After a's lease (6 s) the
/// others show a's printers offline and a as not alive, a's two prints become
/// `interrupted` (and stay so: never reprinted on their own), the model it was
/// preparing goes back to the queue, and every model is sliced and printed by b's and c's
/// printers, each once. Started again, host a prints nothing blind: its printers hold
/// the interrupted prints' beds.
#[test]
fn a_host_killed_mid_print_loses_its_work_to_the_others() {
    let specs = three_hosts(0.05, Some(6), &[&["hot/in"], &["hot/in"], &["hot/in"]]);
    let mut farm = Farm::configure(&specs);
    let slicer = endless_slicer(&farm.root);
    farm.host_mut("a")
        .env
        .push(("CRISPEN_PRUSA_SLICER".into(), slicer));
    farm.host_mut("a").start();
    farm.wait_status("a", Duration::from_secs(120), "host a up", |s| {
        ["a1", "a2"]
            .iter()
            .all(|p| printer(s, p).is_some_and(|p| p["state"] == "idle"))
    });

    // Two prints of 10,000 s' simulated time (500 s here: long enough to be killed in),
    // and three models.
    let hot = farm.root.join("hot/in");
    let long = presliced_gcode("long-1", 2000, 1200);
    drop_file(&hot, "long-1.gcode", long.as_bytes());
    let long = presliced_gcode("long-2", 2000, 1200);
    drop_file(&hot, "long-2.gcode", long.as_bytes());
    let spot = std::fs::read(common::model("spot.obj")).unwrap();
    let models: Vec<String> = (1..=3).map(|i| format!("m-{i}.obj")).collect();
    for m in &models {
        drop_file(&hot, m, &spot);
    }
    let mut files: Vec<String> = vec!["long-1.gcode".into(), "long-2.gcode".into()];
    files.extend(models.iter().cloned());

    // Host a prints both and hangs slicing a model.
    farm.wait_until(
        Duration::from_secs(300),
        "host a printing both long jobs and preparing a model",
        |last| {
            let s = farm.host("a").status()?;
            nothing_lost(&s, &[]);
            *last = s.to_string();
            let printing = ["a1", "a2"].iter().all(|p| {
                printer(&s, p).is_some_and(|p| {
                    p["state"] == "printing"
                        && p["progress"]["lines_acked"].as_u64().unwrap_or(0) > 20
                })
            });
            let preparing = models.iter().any(|m| state_of(&s, m) == "preparing");
            (printing && preparing).then_some(())
        },
    );

    // b and c join the farm (they may help with the models a has not started on).
    farm.host_mut("b").start();
    farm.host_mut("c").start();
    farm.wait_status("b", Duration::from_secs(120), "the farm up", farm_is_up);
    let held: Vec<String> = farm
        .query(
            "SELECT file FROM jobs WHERE state = 'preparing' AND claimed_by = 'a'",
            &[],
        )
        .iter()
        .map(|r| r.get(0))
        .collect();
    assert!(!held.is_empty(), "host a holds a model in preparation");
    let printing_on_a: BTreeMap<String, String> = farm
        .query(
            "SELECT file, printer FROM jobs WHERE state = 'printing' AND printer IN ('a1', 'a2')",
            &[],
        )
        .iter()
        .map(|r| (r.get(0), r.get(1)))
        .collect();
    assert_eq!(
        printing_on_a.keys().cloned().collect::<Vec<_>>(),
        ["long-1.gcode", "long-2.gcode"],
        "a's printers print the two long jobs"
    );

    let killed_at = std::time::SystemTime::now()
        .duration_since(std::time::UNIX_EPOCH)
        .unwrap()
        .as_secs_f64();
    farm.host_mut("a").kill9();
    let t0 = Instant::now();

    // After the lease: a is dead, its printers offline, its prints interrupted.
    let s = farm.wait_status(
        "b",
        Duration::from_secs(120),
        "host a's lease to run out",
        |s| {
            host_alive(s, "a") == Some(false)
                && ["a1", "a2"]
                    .iter()
                    .all(|p| printer(s, p).is_some_and(|p| p["offline"] == true))
                && ["long-1.gcode", "long-2.gcode"]
                    .iter()
                    .all(|f| state_of(s, f) == "interrupted")
        },
    );
    eprintln!(
        "host a's work was taken back {:.1} s after kill -9 (lease 6 s)",
        t0.elapsed().as_secs_f64()
    );
    let a = s["farm"]["hosts"]
        .as_array()
        .unwrap()
        .iter()
        .find(|h| h["name"] == "a")
        .unwrap();
    let last_seen = a["last_seen"].as_f64().unwrap();
    assert!(
        (killed_at - 30.0..=killed_at + 1.0).contains(&last_seen),
        "a was last seen at {last_seen}, killed at {killed_at}"
    );
    for f in ["long-1.gcode", "long-2.gcode"] {
        assert_eq!(
            common::job_by_file(&s, f).unwrap()["printer"],
            printing_on_a[f].as_str(),
            "{f} keeps the printer it was interrupted on"
        );
    }

    // Every model is sliced (by b and c: a's slicer hangs) and printed on b's or c's
    // printers; the interrupted prints are never started again on their own.
    farm.wait_until(Duration::from_secs(900), "every model printed", |last| {
        let s = farm.host("c").status()?;
        nothing_lost(&s, &["long-1.gcode", "long-2.gcode"]);
        farm.clear_finished(&s, &["b", "c"]);
        *last = s.to_string();
        models
            .iter()
            .all(|m| state_of(&s, m) == "done")
            .then_some(())
    });
    for h in ["b", "c"] {
        let s = farm.host(h).status().unwrap();
        for m in &models {
            let p = common::job_by_file(&s, m).unwrap()["printer"]
                .as_str()
                .unwrap()
                .to_string();
            assert!(
                !p.starts_with('a'),
                "{m} printed on {p}, a dead host's printer"
            );
        }
        for f in ["long-1.gcode", "long-2.gcode"] {
            assert_eq!(state_of(&s, f), "interrupted", "{f} as host {h} sees it");
        }
    }
    let history = farm.query(
        "SELECT j.file, h.state, h.host FROM job_history h JOIN jobs j ON j.id = h.job_id \
         ORDER BY h.at",
        &[],
    );
    for f in &held {
        let entries: Vec<(String, String)> = history
            .iter()
            .filter(|r| r.get::<_, String>(0) == *f)
            .map(|r| (r.get(1), r.get(2)))
            .collect();
        let preparing_by_a = entries
            .iter()
            .position(|(state, host)| state == "preparing" && host == "a");
        let went_back =
            preparing_by_a.is_some_and(|i| entries[i..].iter().any(|e| e.0 == "queued"));
        let prepared_by_other = entries
            .iter()
            .any(|(state, host)| state == "ready" && host != "a");
        assert!(
            went_back && prepared_by_other,
            "{f}, held by a, went back to the queue and was prepared by another host: {entries:?}"
        );
    }
    printed_once_by_history(&farm, &files, &[]);
    let markers = farm.markers_by_printer();
    for (p, m) in &markers {
        let want: Vec<String> = printing_on_a
            .iter()
            .filter(|(_, on)| on == &p)
            .map(|(f, _)| f.trim_end_matches(".gcode").to_string())
            .collect();
        assert_eq!(
            m, &want,
            "the long prints ran on {p}: only those it was given, once"
        );
    }

    // Host a comes back: it prints nothing blind; its printers hold the interrupted
    // prints on their beds until cleared.
    stop_endless_slicers(&farm.root);
    farm.host_mut("a").env.clear();
    farm.host_mut("a").start();
    // Read from host a itself: host b's view of a's printers may still be the record a
    // published before it was killed (printing) until a's fresh start publishes anew.
    let s = farm.wait_status("a", Duration::from_secs(120), "host a back", |s| {
        host_alive(s, "a") == Some(true)
            && ["a1", "a2"]
                .iter()
                .all(|p| printer(s, p).is_some_and(|p| p["offline"] == false))
    });
    for p in ["a1", "a2"] {
        let p = printer(&s, p).unwrap();
        assert_eq!(p["bed_cleared"], false, "{p}");
        assert_ne!(p["state"], "printing", "{p}");
    }
    // A print that does not start announces nothing, but a printer that looks for a job
    // and takes none does (its `looked_at`): once both of host a's printers have looked
    // in the job store's version of that status or a later one, whatever they would have
    // started they would have started by then. Until then, and after, the interrupted
    // prints stay so.
    let since = s["version"].as_u64().expect("a status has its version");
    farm.wait_status(
        "a",
        Duration::from_secs(120),
        "host a's printers to look for a job since it came back",
        |s| {
            for f in ["long-1.gcode", "long-2.gcode"] {
                assert_eq!(
                    state_of(s, f),
                    "interrupted",
                    "{f} after a's restart: {s:#}"
                );
            }
            // Connected and between jobs, too: `looked_at` is 0 until a printer first looks,
            // and so is a store's version before its first change after a restart (under
            // load this once ended the wait while a printer was still connecting).
            ["a1", "a2"].iter().all(|p| {
                printer(s, p).is_some_and(|p| {
                    p["state"] == "bed_not_cleared"
                        && p["looked_at"].as_u64().is_some_and(|v| v >= since)
                })
            })
        },
    );
    printed_once_by_history(&farm, &files, &[]);
    stop_endless_slicers(&farm.root);
}

/// PostgreSQL stopped for 20 seconds while prints run: the hosts keep streaming what
/// they have, start nothing new, say in their status that the database is unreachable,
/// and record the outcomes once it is back; a file dropped during the outage is taken
/// once it is back. Every job ends done exactly once, each print on the printer that
/// started it.
#[test]
fn a_database_outage_loses_nothing_and_prints_nothing_twice() {
    let mut farm = Farm::start(&three_hosts(0.05, None, &[&["hot/a"], &["hot/b"], &[]]));
    for h in ["a", "b", "c"] {
        farm.wait_status(h, Duration::from_secs(120), "the farm up", farm_is_up);
    }
    // Nine prints of 16 to 40 s here (plus heating), dropped on two hosts: six print at
    // once, some of them end during the outage.
    let mut files = Vec::new();
    for i in 0..9 {
        let host = if i % 2 == 0 { "a" } else { "b" };
        let name = format!("{host}-{i}.gcode");
        let gcode = presliced_gcode(&format!("{host}-{i}"), 64 + 24 * (i % 4), 1200);
        drop_file(
            &farm.root.join(format!("hot/{host}")),
            &name,
            gcode.as_bytes(),
        );
        files.push(name);
    }
    let printing_before: BTreeMap<String, String> =
        farm.wait_until(Duration::from_secs(300), "six prints running", |last| {
            let rows = farm.query(
                "SELECT file, printer FROM jobs WHERE state = 'printing'",
                &[],
            );
            *last = format!("{} printing", rows.len());
            (rows.len() == 6).then(|| rows.iter().map(|r| (r.get(0), r.get(1))).collect())
        });
    // Let the prints get going (as each host sees its own printers), then stop the
    // database.
    for h in ["a", "b", "c"] {
        farm.wait_status(h, Duration::from_secs(120), "prints under way", |s| {
            [format!("{h}1"), format!("{h}2")].iter().all(|p| {
                printer(s, p)
                    .is_some_and(|p| p["progress"]["lines_acked"].as_u64().unwrap_or(0) > 10)
            })
        });
    }
    farm.pg.stop();
    let stopped = Instant::now();
    // A file dropped while the database is down can be admitted only once it is back:
    // it must neither be lost nor taken twice.
    let late = presliced_gcode("a-late", 16, 1200);
    drop_file(&farm.root.join("hot/a"), "a-late.gcode", late.as_bytes());
    files.push("a-late.gcode".into());

    // During the outage: each host says so, and no printer starts a job it did not have.
    let mut said_unreachable = BTreeSet::new();
    let mut ended_while_down = BTreeSet::new();
    let mut refused_clear: Option<String> = None;
    let mut polls: BTreeMap<String, Vec<String>> = BTreeMap::new();
    while stopped.elapsed() < Duration::from_secs(20) {
        for h in &farm.hosts {
            let asked = Instant::now();
            let answer = h.status();
            polls.entry(h.name.clone()).or_default().push(format!(
                "{:.1}s: {} in {:.1}s",
                (asked - stopped).as_secs_f64(),
                match &answer {
                    None => "no answer".to_string(),
                    Some(s) => format!("database {}", s["farm"]["database"]),
                },
                asked.elapsed().as_secs_f64()
            ));
            let Some(s) = answer else { continue };
            if s["farm"]["database"]
                .as_str()
                .is_some_and(|d| d.contains("unreachable"))
            {
                said_unreachable.insert(h.name.clone());
            }
            for p in s["printers"].as_array().into_iter().flatten() {
                if p["host"] != h.name.as_str() {
                    continue;
                }
                let job = p["job"].as_str().unwrap_or("");
                let file = s["jobs"]
                    .as_array()
                    .into_iter()
                    .flatten()
                    .find(|j| j["id"] == job)
                    .and_then(|j| j["file"].as_str())
                    .unwrap_or(job)
                    .to_string();
                if p["state"] == "printing" {
                    assert_eq!(
                        printing_before.get(&file).map(String::as_str),
                        p["name"].as_str(),
                        "{} started {file} while the database was down (job {job})",
                        p["name"]
                    );
                } else if p["state"] == "bed_not_cleared" {
                    ended_while_down.insert(file);
                    // A person's clear cannot be written to the farm: refused, saying
                    // what stays as it was and what to do.
                    if refused_clear.is_none() {
                        let name = p["name"].as_str().unwrap();
                        let (ok, out) = h.ctl(&["clear", name]);
                        assert!(
                            !ok,
                            "crispen clear {name} while the database is down: {out}"
                        );
                        assert!(
                            out.contains(&format!("{name}: the bed is not marked clear"))
                                && out.contains("the printer takes no job until it is")
                                && out.contains("PostgreSQL"),
                            "{out}"
                        );
                        refused_clear = Some(name.to_string());
                    }
                }
            }
        }
        std::thread::sleep(Duration::from_millis(500));
    }
    farm.pg.restart();
    assert_eq!(
        said_unreachable.len(),
        3,
        "every host's status said the database was unreachable during the outage; only {said_unreachable:?} did\n\
         the hosts' answers (time since the stop: answer in how long): {polls:#?}\n{}",
        farm.diagnostics()
    );

    assert!(
        !ended_while_down.is_empty(),
        "some prints ended during the outage (their outcomes to be recorded later)"
    );
    // Each host reaches the database again on its own before a person's clear can be
    // written through it.
    for h in ["a", "b", "c"] {
        farm.wait_status(
            h,
            Duration::from_secs(120),
            "the database reached again",
            |s| s["farm"]["database"].is_null(),
        );
    }

    // Back: the outcomes are recorded, beds cleared, the other three jobs printed.
    farm.wait_until(Duration::from_secs(600), "every job done", |last| {
        let s = farm.host("b").status()?;
        nothing_lost(&s, &[]);
        farm.clear_finished(&s, &["a", "b", "c"]);
        *last = s.to_string();
        files
            .iter()
            .all(|f| state_of(&s, f) == "done")
            .then_some(())
    });
    for h in &farm.hosts {
        let s = h.status().unwrap();
        assert!(
            s["farm"]["database"].is_null(),
            "host {} says the database is back: {}",
            h.name,
            s["farm"]
        );
    }
    let printed_on = all_done_once(&farm, &files);
    for (f, p) in &printing_before {
        assert_eq!(
            &printed_on[f], p,
            "{f} finished on the printer it started on"
        );
    }
    printed_once_by_history(&farm, &files, &[]);
    let mut seen: BTreeMap<String, Vec<String>> = BTreeMap::new();
    for (p, markers) in farm.markers_by_printer() {
        for m in markers {
            seen.entry(m).or_default().push(p.clone());
        }
    }
    for f in &files {
        let m = f.trim_end_matches(".gcode");
        assert_eq!(
            seen.get(m).map(Vec::as_slice),
            Some(&[printed_on[f].clone()][..]),
            "{f} started exactly once, on its printer"
        );
    }
}

/// The control commands act on any printer or job of the farm from any host: a print on
/// host b's printer is paused through host a, resumed through host c, cancelled through
/// host a (the job ends cancelled, the printer holds its bed), retried through host c
/// (it waits for the bed) and, once the bed is cleared through host a, printed again
/// from its first line on the same printer.
#[test]
fn control_commands_act_across_hosts() {
    let mut specs = three_hosts(0.05, None, &[&[], &["hot/b"], &[]]);
    specs[1].folders[0].1 = vec!["b1".to_string()];
    let farm = Farm::start(&specs);
    for h in ["a", "b", "c"] {
        farm.wait_status(h, Duration::from_secs(120), "the farm up", farm_is_up);
    }
    let gcode = presliced_gcode("long", 2000, 1200);
    drop_file(&farm.root.join("hot/b"), "long.gcode", gcode.as_bytes());
    let acked = |s: &Value| {
        printer(s, "b1").map_or(0, |p| p["progress"]["lines_acked"].as_u64().unwrap_or(0))
    };
    let s = farm.wait_status("b", Duration::from_secs(120), "b1 printing", |s| {
        printer(s, "b1").is_some_and(|p| p["state"] == "printing") && acked(s) > 20
    });
    let id = common::job_by_file(&s, "long.gcode").unwrap()["id"]
        .as_str()
        .unwrap()
        .to_string();

    let (ok, out) = farm.host("a").ctl(&["pause", "b1"]);
    assert!(ok, "pause b1 through host a: {out}");
    let paused = farm.wait_status("b", Duration::from_secs(60), "b1 paused", |s| {
        printer(s, "b1").is_some_and(|p| p["state"] == "paused")
    });
    farm.wait_status(
        "c",
        Duration::from_secs(60),
        "b1 paused as c sees it",
        |s| printer(s, "b1").is_some_and(|p| p["state"] == "paused"),
    );
    let s = farm.host("b").status().unwrap();
    assert_eq!(acked(&s), acked(&paused), "lines went on while paused");

    let (ok, out) = farm.host("c").ctl(&["resume", "b1"]);
    assert!(ok, "resume b1 through host c: {out}");
    let before = acked(&s);
    farm.wait_status("b", Duration::from_secs(60), "b1 resumed", |s| {
        printer(s, "b1").is_some_and(|p| p["state"] == "printing") && acked(s) > before + 20
    });

    let (ok, out) = farm.host("a").ctl(&["cancel", &id]);
    assert!(ok, "cancel {id} through host a: {out}");
    farm.wait_status("b", Duration::from_secs(60), "the print cancelled", |s| {
        state_of(s, "long.gcode") == "cancelled"
            && printer(s, "b1").is_some_and(|p| p["state"] == "bed_not_cleared")
    });
    farm.wait_status("a", Duration::from_secs(60), "a sees it cancelled", |s| {
        state_of(s, "long.gcode") == "cancelled"
    });
    // Host c checks the job's state in its own copy of the farm: wait until the cancel
    // has reached it (under load it once still said printing and refused the retry).
    farm.wait_status("c", Duration::from_secs(60), "c sees it cancelled", |s| {
        state_of(s, "long.gcode") == "cancelled"
    });

    let (ok, out) = farm.host("c").ctl(&["retry", &id]);
    assert!(ok, "retry {id} through host c: {out}");
    let s = farm.wait_status("b", Duration::from_secs(60), "the job ready again", |s| {
        state_of(s, "long.gcode") == "ready"
    });
    assert_eq!(
        printer(&s, "b1").unwrap()["bed_cleared"],
        false,
        "the bed gate holds"
    );

    let (ok, out) = farm.host("a").ctl(&["clear", "b1"]);
    assert!(ok, "clear b1 through host a: {out}");
    farm.wait_status("b", Duration::from_secs(60), "printing again", |s| {
        state_of(s, "long.gcode") == "printing" && acked(s) > 20
    });
    let markers = farm.markers_by_printer();
    for (p, m) in &markers {
        let want: &[&str] = if p == "b1" { &["long", "long"] } else { &[] };
        assert_eq!(
            m, want,
            "{p} started the job from its first line, as often as told"
        );
    }
    let entries = farm.printing_entries();
    assert_eq!(entries[&id], 2, "printed once, then once more when retried");
}

/// Issue 20: a second daemon started under the `[farm] host` of a running one (a cloned
/// machine keeps the hostname, the default name) used to take the live job for one left
/// "mid-flight after a restart", interrupt it, and so have it printed twice. Now each run
/// holds its own token in the host's row:
/// 1. while host a prints, a clone of it (same name, its own spool, socket and
///    simulator) refuses to start, naming the host and the lease's time left; a's job is
///    not interrupted and is printed once;
/// 2. once a stops renewing (frozen with SIGSTOP, as a hung machine or a long outage
///    would) and its lease has run out, the clone does take the name over and interrupts
///    a's print; a, thawed, finds its token replaced, says so, and acts for the host no
///    more: a file dropped in its folder is not taken in;
/// 3. a run killed with `kill -9` mid-print: the next run under the name, started once
///    the lease has run out, takes over and interrupts that print.
#[test]
fn a_second_run_under_a_live_hosts_name_refuses_to_start() {
    let spec = HostSpec {
        name: "a".into(),
        printers: vec!["a1".into()],
        folders: vec![("hot/a".into(), vec!["a1".into()])],
        time_scale: 0.05,
        lease_s: Some(6),
    };
    let mut farm = Farm::start(&[spec]);
    let hot = farm.root.join("hot/a");
    let acked = |s: &Value| {
        printer(s, "a1").map_or(0, |p| p["progress"]["lines_acked"].as_u64().unwrap_or(0))
    };
    farm.wait_status("a", Duration::from_secs(120), "a1 idle", |s| {
        printer(s, "a1").is_some_and(|p| p["state"] == "idle")
    });
    // 60 moves of 5 s' simulated time: about 15 s here, long enough for the clone to
    // start and refuse while it prints.
    drop_file(
        &hot,
        "job-1.gcode",
        presliced_gcode("job-1", 60, 1200).as_bytes(),
    );
    farm.wait_status("a", Duration::from_secs(120), "a1 printing job-1", |s| {
        state_of(s, "job-1.gcode") == "printing" && acked(s) > 10
    });

    let mut clone = farm.host("a").clone_as("clone");
    clone.start();
    let status = clone.wait_exit(Duration::from_secs(60));
    let log = std::fs::read_to_string(&clone.log).unwrap_or_default();
    assert!(
        status.is_some_and(|s| !s.success()),
        "a second run under host a's name must refuse to start: {status:?}\n{log}{}",
        farm.diagnostics()
    );
    for part in [
        "[farm] host \"a\" is in use",
        "s more",
        "give each machine its own [farm] host",
    ] {
        assert!(log.contains(part), "the refusal says {part:?}: {log}");
    }
    let s = farm.host("a").status().unwrap();
    assert_eq!(state_of(&s, "job-1.gcode"), "printing", "{s}");
    farm.wait_status("a", Duration::from_secs(300), "job-1 done", |s| {
        state_of(s, "job-1.gcode") == "done"
    });
    assert!(
        !std::fs::read_to_string(&farm.host("a").log)
            .unwrap()
            .contains("mid-flight"),
        "nothing of a's was taken for a restart's leftovers"
    );
    let id1: String = farm.query("SELECT id FROM jobs WHERE file = 'job-1.gcode'", &[])[0].get(0);
    assert_eq!(
        farm.printing_entries()[&id1],
        1,
        "job-1 entered printing once"
    );
    assert_eq!(
        common::farm::markers(&farm.root.join("a1.rec")),
        ["job-1"],
        "a1 printed job-1 once"
    );
    assert!(common::farm::markers(&farm.root.join("clone-a1.rec")).is_empty());

    // Part 2: a long print, then a freezes.
    let (ok, out) = farm.host("a").ctl(&["clear", "a1"]);
    assert!(ok, "clear a1: {out}");
    drop_file(
        &hot,
        "job-2.gcode",
        presliced_gcode("job-2", 2000, 1200).as_bytes(),
    );
    farm.wait_status("a", Duration::from_secs(120), "a1 printing job-2", |s| {
        state_of(s, "job-2.gcode") == "printing" && acked(s) > 10
    });
    farm.host("a").signal(nix::sys::signal::Signal::SIGSTOP);
    lease_run_out(&farm, "a's lease to run out");
    clone.start();
    farm.wait_until(
        Duration::from_secs(120),
        "the clone to take the name over and interrupt job-2",
        |last| {
            let rows = farm.query(
                "SELECT state, coalesce(reason, '') FROM jobs WHERE file = 'job-2.gcode'",
                &[],
            );
            *last = format!("{:?}", rows.first().map(|r| r.get::<_, String>(0)));
            rows.first()
                .is_some_and(|r| r.get::<_, String>(0) == "interrupted")
                .then_some(())
        },
    );
    // The clone runs on; a thaws and learns it was displaced.
    farm.host("a").signal(nix::sys::signal::Signal::SIGCONT);
    farm.wait_status(
        "a",
        Duration::from_secs(60),
        "a says it was taken over",
        |s| {
            s["farm"]["database"]
                .as_str()
                .is_some_and(|d| d.contains("taken over by another run"))
        },
    );
    clone.kill9();
    drop_file(
        &hot,
        "job-3.gcode",
        presliced_gcode("job-3", 2000, 1200).as_bytes(),
    );
    farm.wait_until(Duration::from_secs(60), "a to refuse job-3", |last| {
        let log = std::fs::read_to_string(&farm.host("a").log).unwrap_or_default();
        *last = farm.host("a").log_tail(5);
        log.lines()
            .any(|l| {
                l.contains("cannot pick up") && l.contains("job-3") && l.contains("taken over")
            })
            .then_some(())
    });
    let files: Vec<String> = farm
        .query("SELECT file FROM jobs ORDER BY seq", &[])
        .iter()
        .map(|r| r.get(0))
        .collect();
    assert_eq!(
        files,
        ["job-1.gcode", "job-2.gcode"],
        "job-3 was not taken in"
    );
    let rows = farm.query("SELECT state FROM jobs WHERE file = 'job-2.gcode'", &[]);
    assert_eq!(rows[0].get::<_, String>(0), "interrupted");

    // Part 3: a crash. The clone, started again once its lease has run out, takes job-3
    // in and prints it; killed with `kill -9` mid-print, it leaves job-3 `printing` until
    // a run under the name, started after its lease has run out, interrupts it.
    farm.host_mut("a").kill9();
    lease_run_out(&farm, "the clone's lease to run out");
    clone.start();
    let clone_printing = |s: &Value| state_of(s, "job-3.gcode") == "printing" && acked(s) > 10;
    let started = Instant::now();
    loop {
        let _ = clone.ctl(&["clear", "a1"]);
        if clone.status().is_some_and(|s| clone_printing(&s)) {
            break;
        }
        assert!(
            started.elapsed() < Duration::from_secs(120),
            "the clone did not print job-3: {}",
            clone.log_tail(40)
        );
        std::thread::sleep(Duration::from_millis(300));
    }
    clone.kill9();
    let rows = farm.query("SELECT state FROM jobs WHERE file = 'job-3.gcode'", &[]);
    assert_eq!(
        rows[0].get::<_, String>(0),
        "printing",
        "nothing took it yet"
    );
    lease_run_out(&farm, "the killed clone's lease to run out");
    farm.host_mut("a").start();
    farm.wait_until(
        Duration::from_secs(120),
        "the restart to interrupt job-3",
        |last| {
            let rows = farm.query(
                "SELECT state, coalesce(reason, '') FROM jobs WHERE file = 'job-3.gcode'",
                &[],
            );
            *last = format!("{:?}", rows.first().map(|r| r.get::<_, String>(1)));
            rows.first()
                .is_some_and(|r| {
                    r.get::<_, String>(0) == "interrupted"
                        && r.get::<_, String>(1).contains("restarted during the print")
                })
                .then_some(())
        },
    );
    let entries = farm.printing_entries();
    assert!(
        entries.values().all(|n| *n == 1) && entries.len() == 3,
        "each job entered printing once: {entries:?}"
    );
    assert_eq!(
        common::farm::markers(&farm.root.join("a1.rec")),
        ["job-1", "job-2"]
    );
    assert_eq!(
        common::farm::markers(&farm.root.join("clone-a1.rec")),
        ["job-3"]
    );

    // A clean stop gives the lease up: the next run under the name starts at once.
    farm.host("a").signal(nix::sys::signal::Signal::SIGTERM);
    let stopped = farm.host_mut("a").wait_exit(Duration::from_secs(60));
    assert!(stopped.is_some_and(|s| s.success()), "{stopped:?}");
    let rows = farm.query(
        "SELECT lease_until <= now() FROM hosts WHERE name = 'a'",
        &[],
    );
    assert!(
        rows[0].get::<_, bool>(0),
        "a's lease was given up at its stop"
    );
    clone.start();
    farm.wait_until(Duration::from_secs(60), "the clone to start", |last| {
        *last = clone.log_tail(5);
        clone.status().map(|_| ())
    });
}

/// Waits until host a's lease has run out, by the database's clock.
fn lease_run_out(farm: &Farm, what: &str) {
    farm.wait_until(Duration::from_secs(60), what, |last| {
        let rows = farm.query(
            "SELECT lease_until < now() FROM hosts WHERE name = 'a'",
            &[],
        );
        *last = format!("{:?}", rows.first().map(|r| r.get::<_, bool>(0)));
        rows.first()
            .is_some_and(|r| r.get::<_, bool>(0))
            .then_some(())
    })
}

/// Issue 22: a command for a printer that its host does not know (a newer host's word, a
/// hand-written row) is taken out of the table, logged and refused; it once fell through
/// to a cancel and stopped the print.
#[test]
fn an_unknown_command_from_the_database_does_not_cancel_a_print() {
    let specs = vec![HostSpec {
        name: "a".into(),
        printers: vec!["a1".into()],
        folders: vec![("hot/a".into(), vec!["a1".into()])],
        time_scale: 0.05,
        lease_s: None,
    }];
    let farm = Farm::start(&specs);
    let gcode = presliced_gcode("long", 2000, 1200);
    drop_file(&farm.root.join("hot/a"), "long.gcode", gcode.as_bytes());
    let acked = |s: &Value| {
        printer(s, "a1").map_or(0, |p| p["progress"]["lines_acked"].as_u64().unwrap_or(0))
    };
    farm.wait_status("a", Duration::from_secs(120), "a1 printing", |s| {
        printer(s, "a1").is_some_and(|p| p["state"] == "printing") && acked(s) > 20
    });
    // This schema's CHECK refuses other words; a newer one (or a hand) may not.
    farm.query(
        "ALTER TABLE commands DROP CONSTRAINT commands_command_check",
        &[],
    );
    farm.query(
        "INSERT INTO commands (host, printer, command) VALUES ('a', 'a1', 'stop')",
        &[],
    );
    farm.wait_until(Duration::from_secs(60), "the command taken", |_| {
        let left: i64 = farm.query("SELECT count(*) FROM commands", &[])[0].get(0);
        (left == 0).then_some(())
    });
    farm.wait_until(Duration::from_secs(30), "the refusal logged", |last| {
        *last = farm.host("a").log_tail(20);
        last.contains("refused a command from another host")
            .then_some(())
    });
    let log = farm.host("a").log_tail(40);
    let refusal = log
        .lines()
        .find(|l| l.contains("refused a command"))
        .unwrap();
    assert!(
        refusal.contains("a1") && refusal.contains("stop"),
        "{refusal}"
    );
    let s = farm.host("a").status().unwrap();
    let before = acked(&s);
    let s = farm.wait_status("a", Duration::from_secs(60), "the print going on", |s| {
        acked(s) > before + 20
    });
    assert_eq!(state_of(&s, "long.gcode"), "printing", "{s:#}");
}

/// The spools are the farm's: a spool loaded through one host on another host's printer is
/// what both hosts show; a job asking for its material goes to that printer, whichever
/// host it was dropped on; and what the print took is booked to the spool, and counted in
/// the printer's care, once, as every host sees it (the inventory is one row of the
/// database, changed under its lock).
#[test]
fn the_spools_are_the_whole_farms() {
    let specs = vec![
        HostSpec {
            name: "a".into(),
            printers: vec!["a1".into()],
            folders: vec![("hot/in".into(), vec!["a1".into(), "b1".into()])],
            time_scale: 0.0,
            lease_s: None,
        },
        HostSpec {
            name: "b".into(),
            printers: vec!["b1".into()],
            folders: vec![],
            time_scale: 0.0,
            lease_s: None,
        },
    ];
    let farm = Farm::start(&specs);
    for h in ["a", "b"] {
        farm.wait_status(h, Duration::from_secs(120), "the farm up", |s| {
            ["a1", "b1"].iter().all(|p| printer(s, p).is_some())
        });
    }
    // Each host loads a spool on the other's printer.
    let (ok, out) = farm.host("a").ctl(&[
        "load",
        "b1",
        "--material",
        "PETG",
        "--colour",
        "black",
        "--grams",
        "500",
        "--price-per-kg",
        "30",
    ]);
    assert!(ok, "{out}");
    let (ok, out) = farm.host("b").ctl(&[
        "load",
        "a1",
        "--material",
        "PLA",
        "--colour",
        "white",
        "--grams",
        "800",
    ]);
    assert!(ok, "{out}");
    let holds = |s: &Value, p: &str| {
        printer(s, p).map_or(String::new(), |p| {
            format!(
                "{} {} {}",
                p["holds"]["filament"]["material"].as_str().unwrap_or("?"),
                p["holds"]["spool"].as_str().unwrap_or("?"),
                p["holds"]["remaining_g"]
            )
        })
    };
    for h in ["a", "b"] {
        farm.wait_status(
            h,
            Duration::from_secs(60),
            "both spools, seen from every host",
            |s| holds(s, "b1") == "PETG s1 500.0" && holds(s, "a1") == "PLA s2 800.0",
        );
    }
    drop_file(
        &farm.root.join("hot/in"),
        "petg.gcode.toml",
        b"material = \"PETG\"\n",
    );
    drop_file(
        &farm.root.join("hot/in"),
        "petg.gcode",
        presliced_gcode("petg", 100, 6000).as_bytes(),
    );
    let s = farm.wait_status(
        "a",
        Duration::from_secs(120),
        "the PETG job done on b1",
        |s| state_of(s, "petg.gcode") == "done",
    );
    let job = common::job_by_file(&s, "petg.gcode").unwrap();
    assert_eq!(job["printer"], "b1");
    let used = job["used_g"].as_f64().unwrap();
    assert!(used > 0.5, "{job}");
    for h in ["a", "b"] {
        farm.wait_status(
            h,
            Duration::from_secs(60),
            "the use booked, seen from every host",
            |s| {
                printer(s, "b1")
                    .and_then(|p| p["holds"]["remaining_g"].as_f64())
                    .is_some_and(|g| (g - (500.0 - used)).abs() < 1e-9)
            },
        );
    }
    let rows = farm.query("SELECT doc->'spools'->'s1'->'uses' FROM filament", &[]);
    let uses: Value = rows[0].get(0);
    assert_eq!(
        uses.as_object().map(|u| u.len()),
        Some(1),
        "booked once: {uses}"
    );
    // The printer's care counted the print once, though both hosts' stores saw its use,
    // and every host reads the same counts (`crispen maintenance log`).
    for h in ["a", "b"] {
        let (ok, out) = farm.host(h).ctl(&["maintenance", "log", "b1", "--json"]);
        assert!(ok, "{out}");
        let record: Value = serde_json::from_str(&out).unwrap();
        let counts = &record["counts"];
        assert_eq!(counts["prints"], 1, "on host {h}: {record}");
        let g = counts["materials"]["PETG"]["g"].as_f64().unwrap();
        assert!(
            (g - used).abs() < 1e-9,
            "on host {h}: {g} g counted, {used} g used"
        );
    }
    let rows = farm.query(
        "SELECT doc->'care'->'b1'->'counts'->'prints' FROM filament",
        &[],
    );
    let prints: Value = rows[0].get(0);
    assert_eq!(prints, 1, "counted once in the farm database");
}

/// How the first job of `file`'s copies stands in `s` (its `copies_status`).
fn copies_of(s: &Value, file: &str) -> Option<Value> {
    s["jobs"]
        .as_array()?
        .iter()
        .find(|j| j["file"] == file && j["copy"].is_null())
        .map(|j| j["copies_status"].clone())
}

/// Copies at once across two hosts: six copies of one file on a farm of four printers on
/// hosts a and b print four at once, one on each printer; b is killed with `kill -9`
/// mid-print: its two copies become interrupted (never printed again on their own) while
/// a's print on, and the two waiting copies go to a's printers; one interrupted copy
/// retried alone (`crispen retry JOB --copy N`) prints once more. The copies were made
/// once (six rows, the G-code stored once), each went to a printer once but the one
/// retried, and b, started again, prints nothing blind and sees the copies as a does.
#[test]
fn copies_across_two_hosts_print_once_through_a_kill_9() {
    let specs: Vec<HostSpec> = ["a", "b"]
        .iter()
        .map(|name| HostSpec {
            name: name.to_string(),
            printers: vec![format!("{name}1"), format!("{name}2")],
            folders: vec![(
                "hot/in".to_string(),
                ["a1", "a2", "b1", "b2"].map(String::from).to_vec(),
            )],
            time_scale: 0.05,
            lease_s: Some(6),
        })
        .collect();
    let mut farm = Farm::start(&specs);
    let all = ["a1", "a2", "b1", "b2"];
    farm.wait_status("a", Duration::from_secs(120), "the farm up", |s| {
        ["a", "b"].iter().all(|h| host_alive(s, h) == Some(true))
            && all
                .iter()
                .all(|p| printer(s, p).is_some_and(|p| p["state"] == "idle"))
    });
    // 400 s of simulated printing each, 20 s here: long enough to be killed in.
    let hot = farm.root.join("hot/in");
    drop_file(&hot, "part.gcode.toml", b"copies = 6\n");
    drop_file(
        &hot,
        "part.gcode",
        presliced_gcode("part", 400, 6000).as_bytes(),
    );

    let s = farm.wait_status("a", Duration::from_secs(120), "four copies printing", |s| {
        copies_of(s, "part.gcode")
            .is_some_and(|c| c["printing"].as_array().is_some_and(|p| p.len() == 4))
            && ["b1", "b2"].iter().all(|p| {
                printer(s, p)
                    .is_some_and(|p| p["progress"]["lines_acked"].as_u64().unwrap_or(0) > 20)
            })
    });
    let c = copies_of(&s, "part.gcode").unwrap();
    assert_eq!(
        (c["printed"].as_u64(), c["waiting"].as_u64()),
        (Some(0), Some(2)),
        "{c}"
    );
    let on_b: Vec<String> = s["jobs"]
        .as_array()
        .unwrap()
        .iter()
        .filter(|j| {
            j["file"] == "part.gcode" && j["printer"].as_str().is_some_and(|p| p.starts_with('b'))
        })
        .map(|j| j["id"].as_str().unwrap().to_string())
        .collect();
    assert_eq!(on_b.len(), 2, "{s}");
    let first = s["jobs"]
        .as_array()
        .unwrap()
        .iter()
        .find(|j| j["file"] == "part.gcode" && j["copy"].is_null())
        .unwrap()["id"]
        .as_str()
        .unwrap()
        .to_string();

    farm.host_mut("b").kill9();
    // After b's lease: its copies interrupted, a's printing, two waiting.
    let s = farm.wait_status(
        "a",
        Duration::from_secs(120),
        "b's copies interrupted",
        |s| {
            host_alive(s, "b") == Some(false)
                && on_b.iter().all(|id| {
                    s["jobs"]
                        .as_array()
                        .unwrap()
                        .iter()
                        .any(|j| j["id"] == *id && j["state"] == "interrupted")
                })
        },
    );
    let c = copies_of(&s, "part.gcode").unwrap();
    assert_eq!(c["stopped"], 2, "{c}");
    assert_eq!(
        c["printed"].as_u64().unwrap()
            + c["printing"].as_array().unwrap().len() as u64
            + c["waiting"].as_u64().unwrap(),
        4,
        "{c}"
    );

    // a's printers print the rest; then the interrupted copy `n` is retried alone.
    let retried: String = on_b[0].clone();
    let n = s["jobs"]
        .as_array()
        .unwrap()
        .iter()
        .find(|j| j["id"] == *retried)
        .map(|j| j["copy"]["n"].as_u64().unwrap_or(1))
        .unwrap();
    farm.wait_until(
        Duration::from_secs(300),
        "four copies printed on a",
        |last| {
            let s = farm.host("a").status()?;
            farm.clear_finished(&s, &["a"]);
            let c = copies_of(&s, "part.gcode")?;
            *last = c.to_string();
            (c["printed"] == 4).then_some(())
        },
    );
    let (ok, out) = farm
        .host("a")
        .ctl(&["retry", &first, "--copy", &n.to_string()]);
    assert!(ok, "{out}");
    assert!(
        out.contains(&format!("job {retried} is ready to print again")),
        "{out}"
    );
    let s = farm.wait_until(Duration::from_secs(300), "five copies printed", |last| {
        let s = farm.host("a").status()?;
        farm.clear_finished(&s, &["a"]);
        let c = copies_of(&s, "part.gcode")?;
        *last = c.to_string();
        (c["printed"] == 5).then_some(s)
    });
    let c = copies_of(&s, "part.gcode").unwrap();
    assert_eq!(
        (c["stopped"].as_u64(), c["waiting"].as_u64()),
        (Some(1), Some(0)),
        "{c}"
    );

    // Made once, each to a printer once but the one retried; a's printers ran the other
    // five prints, b's no more than the one each was killed in.
    let ids: Vec<String> = farm
        .query("SELECT id FROM jobs WHERE file = 'part.gcode'", &[])
        .iter()
        .map(|r| r.get(0))
        .collect();
    assert_eq!(ids.len(), 6, "{ids:?}");
    // The G-code is kept once: the copies share the first job's files.
    let copies_files: i64 = farm.query(
        "SELECT count(*) FROM job_files WHERE job_id = ANY($1) AND job_id <> $2",
        &[&ids, &first],
    )[0]
    .get(0);
    assert_eq!(copies_files, 0);
    let entries = farm.printing_entries();
    for id in &ids {
        let want = if *id == retried { 2 } else { 1 };
        assert_eq!(
            entries[id], want,
            "copy {id} went to a printer {} times",
            entries[id]
        );
    }
    let markers = farm.markers_by_printer();
    let on = |p: &str| markers[p].iter().filter(|m| *m == "part").count();
    assert_eq!(on("a1") + on("a2"), 5, "{markers:?}");
    assert!(on("b1") <= 1 && on("b2") <= 1, "{markers:?}");

    // b again: nothing printed blind, its beds held, the copies as a sees them.
    farm.host_mut("b").start();
    let up = farm.wait_status("b", Duration::from_secs(120), "b back", |s| {
        host_alive(s, "b") == Some(true)
            && ["b1", "b2"]
                .iter()
                .all(|p| printer(s, p).is_some_and(|p| p["offline"] == false))
    });
    let since = up["version"].as_u64().expect("a status has its version");
    let s = farm.wait_status("b", Duration::from_secs(120), "b's printers looking", |s| {
        ["b1", "b2"].iter().all(|p| {
            printer(s, p).is_some_and(|p| {
                p["state"] == "bed_not_cleared"
                    && p["looked_at"].as_u64().is_some_and(|v| v >= since)
            })
        })
    });
    let seen_by_b = copies_of(&s, "part.gcode").unwrap();
    assert_eq!(
        (seen_by_b["printed"].as_u64(), seen_by_b["stopped"].as_u64()),
        (Some(5), Some(1)),
        "{seen_by_b}"
    );
    assert_eq!(
        farm.printing_entries(),
        entries,
        "nothing printed after b came back"
    );
}
