//! Power that follows the queue, through the real daemon and a plug of our own
//! (`common::plug`) that speaks Tasmota's and Shelly's protocols and really starts and
//! stops a simulated printer: an idle, cool printer is switched off, switched on again by
//! the next job and prints it; a hot one is never switched off, by the idle timer or by
//! hand; an operator switches one off and the next job switches it on.

use crate::common;

use common::daemon::{clear_after_done, ctl, wait_for, Daemon, BIN};
use common::farm::{drop_file, markers, presliced_gcode, state_of};
use common::plug::{Plug, Switched};
use serde_json::Value;
use std::path::Path;
use std::time::Duration;

const LIMIT: Duration = Duration::from_secs(90);

/// A daemon with printer `a` behind `plug` (`kind`, and the rest of `[printer.power]`).
fn farm_with_plug(
    root: &Path,
    plug: &Plug,
    kind: &str,
    more: &str,
) -> (std::path::PathBuf, std::path::PathBuf) {
    std::fs::create_dir_all(root.join("hot")).unwrap();
    let config = root.join("crispen.toml");
    std::fs::write(
        &config,
        format!(
            "[spool]\ndir = \"spool\"\n[control]\nsocket = \"c.sock\"\n[farm]\nsettle_s = 0.2\n\
             [[printer]]\nname = \"a\"\nport = \"{}\"\nfirmware = \"marlin2\"\n\
             [printer.power]\nkind = \"{kind}\"\nurl = \"{}\"\nboot_s = 30\n{more}\
             [[folder]]\npath = \"hot\"\nheight_mm = 1\nprinters = [\"a\"]\n",
            root.join("ttyA").display(),
            plug.url()
        ),
    )
    .unwrap();
    (config, root.join("daemon.log"))
}

fn printer(s: &Value) -> &Value {
    common::printer(s, "a")
}

/// Tasmota: off when idle and cool, on for the next job; a job that leaves the hotend hot
/// keeps the printer on past its idle time (the supervisor says so once the time is up),
/// and a hand asking it off is refused; once a job cools it, it goes off again.
#[test]
fn an_idle_cool_printer_is_switched_off_and_on_again_by_the_next_job() {
    let tmp = tempfile::tempdir().unwrap();
    let root = tmp.path();
    let plug = Plug::start(BIN, &root.join("ttyA"), &root.join("a.rec"), true);
    let (config, log) = farm_with_plug(root, &plug, "tasmota", "off_after_idle_min = 0.01\n");
    let _daemon = Daemon::start(&config, &log);
    // Idle and cool from the start: switched off.
    let s = wait_for(&config, &log, LIMIT, "a switched off", |s| {
        s["printers"].as_array().is_some_and(|p| !p.is_empty()) && printer(s)["state"] == "off"
    });
    assert!(
        printer(&s)["detail"]
            .as_str()
            .unwrap_or("")
            .contains("idle"),
        "{s}"
    );
    assert_eq!(plug.switched(), [Switched::Off]);
    assert!(!plug.is_on(), "the plug cut its printer's power");

    // A job whose end leaves the hotend at 200 °C: switched on for it, printed.
    let hot = presliced_gcode("hot", 30, 6000).replace("M104 S0\n", "");
    drop_file(&root.join("hot"), "hot.gcode", hot.as_bytes());
    clear_after_done(&config, &log, "a", "hot.gcode");
    assert_eq!(plug.switched(), [Switched::Off, Switched::On]);
    // Idle past its time, it stays on while hot: the supervisor says so.
    let s = wait_for(&config, &log, LIMIT, "a kept on while hot", |s| {
        printer(s)["detail"]
            .as_str()
            .is_some_and(|d| d.contains("stays on while its hotend is"))
    });
    assert_eq!(printer(&s)["state"], "idle", "{s}");
    let (ok, out) = ctl(&config, &["power", "a", "off"]);
    assert!(!ok && out.contains("hotend"), "{out}");
    assert_eq!(
        plug.switched(),
        [Switched::Off, Switched::On],
        "never off while hot"
    );

    // A job that turns its heater off: printed on the same power, then off once cool.
    drop_file(
        &root.join("hot"),
        "cool.gcode",
        presliced_gcode("cool", 20, 6000).as_bytes(),
    );
    clear_after_done(&config, &log, "a", "cool.gcode");
    wait_for(&config, &log, LIMIT, "a switched off again", |s| {
        printer(s)["state"] == "off"
    });
    assert_eq!(
        plug.switched(),
        [Switched::Off, Switched::On, Switched::Off]
    );
    // Each job printed once, both on the printer's second power-up.
    assert_eq!(markers(&root.join("a.rec.2")), ["hot", "cool"]);
    assert_eq!(plug.starts(), 2);
}

/// Shelly (Gen2 RPC): no idle switching; an operator switches the printer off by hand
/// (refused while a print waits on its bed unless forced), and the next job switches it on
/// and prints.
#[test]
fn a_printer_switched_off_by_hand_is_switched_on_by_the_next_job() {
    let tmp = tempfile::tempdir().unwrap();
    let root = tmp.path();
    let plug = Plug::start(BIN, &root.join("ttyA"), &root.join("a.rec"), true);
    let (config, log) = farm_with_plug(root, &plug, "shelly-rpc", "");
    let _daemon = Daemon::start(&config, &log);
    wait_for(&config, &log, LIMIT, "a idle", |s| {
        s["printers"].as_array().is_some_and(|p| !p.is_empty()) && printer(s)["state"] == "idle"
    });
    drop_file(
        &root.join("hot"),
        "one.gcode",
        presliced_gcode("one", 20, 6000).as_bytes(),
    );
    wait_for(&config, &log, LIMIT, "one done", |s| {
        state_of(s, "one.gcode") == "done" && printer(s)["bed_cleared"] == false
    });
    let (ok, out) = ctl(&config, &["power", "a", "off"]);
    assert!(!ok && out.contains("still on its bed"), "{out}");
    let (ok, out) = ctl(&config, &["clear", "a"]);
    assert!(ok, "{out}");
    wait_for(&config, &log, LIMIT, "a idle and cool", |s| {
        printer(s)["state"] == "idle"
            && printer(s)["temperatures"]["hotend_c"]
                .as_f64()
                .is_some_and(|c| c < 50.0)
    });
    let (ok, out) = ctl(&config, &["power", "a", "off"]);
    assert!(ok && out.contains("switched off"), "{out}");
    assert!(!plug.is_on());
    let s = wait_for(&config, &log, LIMIT, "a off", |s| {
        printer(s)["state"] == "off"
    });
    assert!(
        printer(&s)["detail"]
            .as_str()
            .unwrap_or("")
            .contains("by hand"),
        "{s}"
    );
    drop_file(
        &root.join("hot"),
        "two.gcode",
        presliced_gcode("two", 20, 6000).as_bytes(),
    );
    wait_for(&config, &log, LIMIT, "two done", |s| {
        state_of(s, "two.gcode") == "done"
    });
    assert_eq!(plug.switched(), [Switched::Off, Switched::On]);
    assert_eq!(markers(&root.join("a.rec.1")), ["one"]);
    assert_eq!(markers(&root.join("a.rec.2")), ["two"]);
}
