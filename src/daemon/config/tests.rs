//! The config's tests that go through the whole of it (a file's text to a [`Config`] or its
//! error): each section's values and errors as the operator meets them.

use super::check::{number, seconds_in};
use super::checked::{ApiKey, Checked, Config, OnShutdown, PrinterPort};
use super::error::ConfigError;
use super::http::MIN_API_KEY_CHARS;
use super::keys;
use super::raw::{KNOWN_TABLES, MAX_CONFIG_BYTES};
use super::store::LEASE_S;
use crate::enhance::Strength;
use crate::marlin::firmware::Firmware;
use crate::slice::SlicerKind;
use std::path::{Path, PathBuf};
use std::time::Duration;

const GOOD: &str = r#"
[spool]
dir = "/var/lib/crispen"
[control]
socket = "/run/crispen/crispen.sock"
[farm]
max_heating = 1
on_shutdown = "stop"
[[printer]]
name = "um2-a"
port = "/dev/ttyACM0"
firmware = "ultimaker2"
[[printer]]
name = "sim"
firmware = "marlin2"
[printer.simulate]
time_scale = 0.5
[[folder]]
path = "/srv/print/5cm"
height_mm = 50
printers = ["um2-a", "sim"]
strength = 0.4
[[folder]]
path = "hot/igea"
height_mm = 30
printers = ["sim"]
enhance = false
slicer = "cura"
"#;

fn parse(text: &str) -> Result<Config, ConfigError> {
    Config::parse(text, Path::new("/etc/crispen/crispen.toml"))
}

/// A reload compares printers' settings to decide which to restart, so a printer's
/// converted settings must not depend on the others (its default seed once did).
#[test]
fn printer_settings_do_not_depend_on_other_printers() {
    let printer = |name: &str| {
        format!("[[printer]]\nname = \"{name}\"\nfirmware = \"marlin2\"\n[printer.simulate]\n")
    };
    let spool = "[spool]\ndir = \"spool\"\n";
    let both = parse(&(spool.to_string() + &printer("a") + &printer("b"))).unwrap();
    let alone = parse(&(spool.to_string() + &printer("b"))).unwrap();
    assert_eq!(both.printers[1], alone.printers[0]);
    assert_ne!(both.printers[0].port, both.printers[1].port, "seeds differ");
}

#[test]
fn good_config_is_converted() {
    let c = parse(GOOD).unwrap();
    assert_eq!(c.farm.max_heating, 1);
    assert_eq!(c.farm.on_shutdown, OnShutdown::Stop);
    assert_eq!(c.printers[0].baud, 250_000);
    assert_eq!(c.printers[0].heat_timeout, Duration::from_secs(1200));
    let text = GOOD.replacen(
        "firmware = \"ultimaker2\"",
        "firmware = \"ultimaker2\"\nheat_timeout_s = 600",
        1,
    );
    assert_eq!(
        parse(&text).unwrap().printers[0].heat_timeout,
        Duration::from_secs(600)
    );
    assert_eq!(
        c.printers[0].port,
        PrinterPort::Serial("/dev/ttyACM0".into())
    );
    assert!(
        matches!(c.printers[1].port, PrinterPort::Simulated { time_scale, .. } if time_scale == 0.5)
    );
    assert_eq!(c.folders[0].strength, Strength::Lambda2(0.4));
    assert_eq!(c.folders[1].strength, Strength::Off);
    assert_eq!(c.folders[1].slicer, SlicerKind::Cura);
    // Relative paths are anchored at the config file's directory.
    assert_eq!(c.folders[1].path, PathBuf::from("/etc/crispen/hot/igea"));
}

/// The one-shot commands find the socket without the daemon's secrets, which an
/// operator may not be able to read (here: a key file that is not there at all).
#[test]
fn the_socket_is_found_without_reading_secrets() {
    let dir = tempfile::tempdir().unwrap();
    let file = dir.path().join("crispen.toml");
    let text =
        format!("{GOOD}\n[http]\nlisten = \"127.0.0.1:8080\"\napi_key_file = \"gone.key\"\n");
    std::fs::write(&file, &text).unwrap();
    assert!(Config::load(&file).is_err());
    assert_eq!(
        Config::socket_of(&file).unwrap(),
        PathBuf::from("/run/crispen/crispen.sock")
    );
    std::fs::write(&file, "[spool]\ndir = \"spool\"\n").unwrap();
    let base = std::path::absolute(dir.path()).unwrap();
    assert_eq!(
        Config::socket_of(&file).unwrap(),
        base.join("spool").join("crispen.sock")
    );
    // The daemon's rule, not a quiet default: an empty socket is an error for both.
    std::fs::write(
        &file,
        "[spool]\ndir = \"spool\"\n[control]\nsocket = \"\"\n",
    )
    .unwrap();
    let e = Config::socket_of(&file).unwrap_err().to_string();
    assert!(
        e.contains("[control]: key `socket`: must not be empty"),
        "{e}"
    );
}

/// Checking reads nothing but the file: a config whose key and password files cannot
/// be read (here: are not there) is checked whole, with its printers and machines;
/// only the resolution reads them, and refuses each by its section and key.
#[test]
fn checking_reads_no_secret_and_resolving_reads_each() {
    let dir = tempfile::tempdir().unwrap();
    let file = dir.path().join("crispen.toml");
    let text = format!(
        "{GOOD}\n[http]\nlisten = \"127.0.0.1:8080\"\napi_key_file = \"api.key\"\n\
         [store]\npostgres = \"host=/run/postgresql dbname=crispen\"\npassword_file = \"pw\"\n"
    );
    std::fs::write(&file, &text).unwrap();
    let checked = Checked::load(&file).unwrap();
    assert_eq!(checked.printers().len(), 2);
    assert_eq!(checked.socket(), Path::new("/run/crispen/crispen.sock"));
    assert_eq!(checked.source(), file);
    let e = checked.clone().resolve().unwrap_err().to_string();
    assert!(e.contains("[store]: key `password_file`"), "{e}");
    std::fs::write(dir.path().join("pw"), "secret\n").unwrap();
    let e = checked.clone().resolve().unwrap_err().to_string();
    assert!(e.contains("[http]: key `api_key_file`"), "{e}");
    assert!(Config::load(&file).is_err());
    let key = "k".repeat(MIN_API_KEY_CHARS);
    std::fs::write(dir.path().join("api.key"), &key).unwrap();
    let config = checked.resolve().unwrap();
    assert_eq!(config.http.unwrap().api_key, ApiKey(key));
    // Checking still refuses a wrong value, before any secret is looked at.
    let wrong = text.replace("listen = \"127.0.0.1:8080\"", "listen = \"127.0.0.1:80\"");
    std::fs::remove_file(dir.path().join("api.key")).unwrap();
    let e = Checked::parse(&wrong, &file).unwrap_err().to_string();
    assert!(e.contains("[http]: key `listen`"), "{e}");
}

/// A config file is a page: a huge one is refused, not read whole or cut.
#[test]
fn a_huge_config_file_is_refused() {
    let dir = tempfile::tempdir().unwrap();
    let file = dir.path().join("crispen.toml");
    let mut text = GOOD.to_string();
    text += &"# padding\n".repeat((MAX_CONFIG_BYTES as usize / 10) + 1);
    std::fs::write(&file, &text).unwrap();
    for e in [
        Checked::load(&file).unwrap_err(),
        Config::socket_of(&file).unwrap_err(),
    ] {
        assert!(e.to_string().contains("larger than 1 MiB"), "{e}");
    }
}

/// Numbers in errors stay short whatever was written.
#[test]
fn numbers_in_errors_are_short() {
    assert_eq!(number(15.0), "15");
    assert_eq!(number(0.25), "0.25");
    assert_eq!(number(1e308), "1e308");
    assert_eq!(number(-1e300), "-1e300");
    let e = seconds_in(1e308, &LEASE_S).unwrap_err();
    assert!(e.ends_with("got 1e308"), "{e}");
}

/// A table missing a key is named by its own header, not by the table before it.
#[test]
fn a_missing_key_names_its_own_table() {
    let file = Path::new("/etc/crispen/crispen.toml");
    let text = "[[printer]]\nname = \"p\"\nfirmware = \"marlin2\"\n[printer.simulate]\n\
                time_scale = 0.0\n[[folder]]\npath = \"/srv/hot\"\nprinters = [\"p\"]\n";
    let e = Config::parse(text, file).unwrap_err().to_string();
    assert!(
        e.contains("line 6, in [[folder]] #1") && e.contains("height_mm"),
        "{e}"
    );
}

/// A machine's pause and resume code is sent mid-job: what a file may not ask for (a
/// refused command, a pause of its own, a line the firmware cannot take) is refused in
/// it too, naming the machine and the key.
#[test]
fn pause_and_resume_code_is_checked_as_job_lines() {
    let dir = tempfile::tempdir().unwrap();
    let file = dir.path().join("crispen.toml");
    let with = |key: &str, code: &str| {
        std::fs::write(dir.path().join("code.gcode"), code).unwrap();
        Config::parse(
            &format!(
                "{GOOD}\n[[machine]]\nname = \"m\"\nbased_on = \"ultimaker2\"\n\
                 {key} = \"code.gcode\"\n"
            ),
            &file,
        )
    };
    let c = with("pause_gcode", "G91 ; lift\nG1 Z5\nG90\nG1 X10 Y200\n").unwrap();
    let m = c.machines.iter().find(|m| m.name == "m").unwrap();
    assert_eq!(
        m.pause_gcode.as_deref(),
        Some("G91 ; lift\nG1 Z5\nG90\nG1 X10 Y200\n")
    );
    for (key, code, says) in [
        ("pause_gcode", "G1 Z5\nM500\n", "line 2: `M500`"),
        ("resume_gcode", "M0 press the knob\n", "asks for a pause"),
        ("resume_gcode", "M104 S400\n", "line 1: `M104 S400`"),
        ("pause_gcode", "G1 X999\n", "line 1"),
        (
            "pause_gcode",
            &format!("M117 {}\n", "x".repeat(200)),
            "bytes",
        ),
    ] {
        let e = with(key, code).unwrap_err().to_string();
        assert!(
            e.contains("[[machine]] #1 (name \"m\")") && e.contains(key) && e.contains(says),
            "{key} {code:?}: {e}"
        );
    }
}

/// `[http]`: the key file is read and checked at startup; every error names the key.
#[test]
fn http_section_is_checked() {
    let dir = tempfile::tempdir().unwrap();
    let file = dir.path().join("crispen.toml");
    std::fs::write(dir.path().join("good.key"), "0123456789abcdefXYZ\n").unwrap();
    std::fs::write(dir.path().join("weak.key"), "short\n").unwrap();
    let with = |http: &str| Config::parse(&format!("{GOOD}\n[http]\n{http}\n"), &file);
    let c = with("listen = \"127.0.0.1:8080\"\napi_key_file = \"good.key\"").unwrap();
    let http = c.http.unwrap();
    assert_eq!(http.api_key.0, "0123456789abcdefXYZ");
    assert!(!http.read_only_without_key);
    assert!(
        !format!("{http:?}").contains("0123456789"),
        "the key is never shown"
    );
    for (text, key, says) in [
        (
            "listen = \"8080\"\napi_key_file = \"good.key\"",
            "listen",
            "address and port",
        ),
        (
            "listen = \"0.0.0.0:80\"\napi_key_file = \"good.key\"",
            "listen",
            "port 80 is privileged",
        ),
        (
            "listen = \"0.0.0.0:8080\"\napi_key_file = \"none.key\"",
            "api_key_file",
            "none.key",
        ),
        (
            "listen = \"0.0.0.0:8080\"\napi_key_file = \"weak.key\"",
            "api_key_file",
            "at least 16",
        ),
        (
            "listen = \"0.0.0.0:8080\"\napi_key_file = \"good.key\"\nupload_max_mb = 0",
            "upload_max_mb",
            "from 1",
        ),
    ] {
        let e = with(text).unwrap_err().to_string();
        assert!(
            e.contains("[http]") && e.contains(&format!("`{key}`")) && e.contains(says),
            "{text}: {e}"
        );
    }
    let e = with("listen = \"0.0.0.0:80\"").unwrap_err().to_string();
    assert!(e.contains("api_key_file"), "{e}");
}

#[test]
fn unknown_key_names_line_section_and_key() {
    let text = GOOD.replace("height_mm = 30", "heigth_mm = 30");
    let err = parse(&text).unwrap_err().to_string();
    assert!(err.starts_with("/etc/crispen/crispen.toml: line "), "{err}");
    assert!(err.contains("[[folder]] #2"), "{err}");
    assert!(err.contains("heigth_mm"), "{err}");
}

#[test]
fn unknown_key_in_simulate_table_is_located() {
    let text = GOOD.replace("time_scale = 0.5", "time_scael = 0.5");
    let err = parse(&text).unwrap_err().to_string();
    assert!(err.contains("[[printer]] #2.simulate"), "{err}");
    assert!(err.contains("time_scael"), "{err}");
}

#[test]
fn bad_values_name_section_and_key() {
    let cases = [
        ("height_mm = 50", "height_mm = -5", "[[folder]] #1 (path \"/srv/print/5cm\"): key `height_mm`: must be from 1 to 2000 mm"),
        ("max_heating = 1", "max_heating = 0", "[farm]: key `max_heating`"),
        ("firmware = \"ultimaker2\"", "firmware = \"repetier\"", "[[printer]] #1 (name \"um2-a\"): key `firmware`"),
        ("printers = [\"sim\"]", "printers = [\"nope\"]", "[[folder]] #2 (path \"hot/igea\"): key `printers`: no [[printer]] is named \"nope\""),
        ("strength = 0.4", "strength = \"max\"", "key `strength`"),
        ("port = \"/dev/ttyACM0\"\n", "", "key `port`: missing"),
        ("firmware = \"ultimaker2\"", "firmware = \"ultimaker2\"\nheat_timeout_s = 5", "[[printer]] #1 (name \"um2-a\"): key `heat_timeout_s`: must be between 10"),
        ("firmware = \"ultimaker2\"", "firmware = \"ultimaker2\"\npause_heaters_off_s = 0", "[[printer]] #1 (name \"um2-a\"): key `pause_heaters_off_s`: must be between 10 and 86400 seconds, got 0"),
        ("strength = 0.4", "strength = 0.4\nsettings = { infil_percent = 20 }", "key `settings`: unknown field `infil_percent`"),
    ];
    for (from, to, expected) in cases {
        let text = GOOD.replacen(from, to, 1);
        assert_ne!(text, GOOD, "{from}");
        let err = parse(&text).unwrap_err().to_string();
        assert!(err.contains(expected), "{err}\n  expected: {expected}");
        assert!(err.starts_with("/etc/crispen/crispen.toml: "), "{err}");
    }
}

/// `[history] keep_days`: absent, the history keeps everything; else bounded.
#[test]
fn the_history_keeps_for_good_or_as_long_as_asked() {
    assert_eq!(parse(GOOD).unwrap().history.keep_for, None);
    let with = |keep: &str| parse(&format!("{GOOD}\n[history]\nkeep_days = {keep}\n"));
    assert_eq!(
        with("365").unwrap().history.keep_for,
        Some(Duration::from_secs(365 * 86_400))
    );
    for bad in ["0", "-1", "nan", "1e9"] {
        let err = with(bad).unwrap_err().to_string();
        assert!(err.contains("[history]: key `keep_days`"), "{bad}: {err}");
    }
}

/// `[enhancement]`: absent, the observer compares with 150 mm prints and may take ten
/// minutes; each key bounded, and named when wrong; a folder may ask `"observed"`.
#[test]
fn the_observers_settings_are_checked() {
    let c = parse(GOOD).unwrap();
    assert_eq!(c.enhancement.reference_height_mm, 150.0);
    assert_eq!(c.enhancement.timeout, Duration::from_secs(600));
    let with = |table: &str| parse(&format!("{GOOD}\n[enhancement]\n{table}\n"));
    let c = with("reference_height_mm = 120\nobserve_timeout_s = 90").unwrap();
    assert_eq!(c.enhancement.reference_height_mm, 120.0);
    assert_eq!(c.enhancement.timeout, Duration::from_secs(90));
    for (bad, key) in [
        ("reference_height_mm = 0", "reference_height_mm"),
        ("reference_height_mm = nan", "reference_height_mm"),
        ("observe_timeout_s = 1", "observe_timeout_s"),
        ("observe_timeout_s = 1e300", "observe_timeout_s"),
        ("reference_heigth_mm = 100", "reference_heigth_mm"),
    ] {
        let err = with(bad).unwrap_err().to_string();
        assert!(
            err.contains("[enhancement]") && err.contains(key),
            "{bad}: {err}"
        );
    }
    let observed = parse(&GOOD.replacen("strength = 0.4", "strength = \"observed\"", 1)).unwrap();
    assert_eq!(observed.folders[0].strength, Strength::Observed);
}

/// Values that once passed the check and then crashed the daemon (a duration too big
/// for `Duration`, a zero rescan period panicking the watcher) or made no sense (a
/// 0.001 mm print, a hot folder inside the spool) are refused, section and key named.
#[test]
fn every_value_is_bounded() {
    let cases = [
        ("strength = 0.4", "strength = 0.4\ntimeout_s = 1e300", "key `timeout_s`: must be a number of seconds"),
        ("strength = 0.4", "strength = 0.4\ntimeout_s = nan", "key `timeout_s`"),
        ("on_shutdown = \"stop\"", "on_shutdown = \"stop\"\nrescan_s = 1e-12", "[farm]: key `rescan_s`"),
        ("on_shutdown = \"stop\"", "on_shutdown = \"stop\"\nsettle_s = 1e30", "[farm]: key `settle_s`"),
        ("max_heating = 1", "max_heating = 100000", "[farm]: key `max_heating`: must be between 1 and 256"),
        ("on_shutdown = \"stop\"", "on_shutdown = \"stop\"\nfinish_timeout_s = 0.5", "[farm]: key `finish_timeout_s`: must be a number of seconds from 1 to 172800, got 0.5"),
        ("on_shutdown = \"stop\"", "on_shutdown = \"stop\"\nfinish_timeout_s = 1e9", "[farm]: key `finish_timeout_s`"),
        ("height_mm = 50", "height_mm = 0.001", "key `height_mm`: must be from 1 to 2000 mm"),
        ("height_mm = 50", "height_mm = 500", "key `height_mm`: 500 mm is taller than any of its printers' machines builds (250 mm)"),
        ("strength = 0.4", "strength = 1e9", "key `strength`: must be \"auto\", \"off\", \"observed\" or a lambda2 from 0 to 100"),
        ("path = \"/srv/print/5cm\"", "path = \"/var/lib/crispen/hot\"", "[[folder]] #1 (path \"/var/lib/crispen/hot\"): key `path`: the hot folder and the spool (/var/lib/crispen) must not contain each other"),
        ("path = \"/srv/print/5cm\"", "path = \"/var/lib\"", "key `path`: the hot folder and the spool"),
        ("path = \"/srv/print/5cm\"", "path = \"/var/lib/x/../crispen/./in\"", "key `path`: the hot folder and the spool"),
        ("path = \"hot/igea\"", "path = \"/srv/print/5cm/igea\"", "[[folder]] #2 (path \"/srv/print/5cm/igea\"): key `path`: the hot folders /srv/print/5cm and /srv/print/5cm/igea must not contain each other"),
    ];
    for (from, to, expected) in cases {
        let text = GOOD.replacen(from, to, 1);
        assert_ne!(text, GOOD, "{from}");
        let err = parse(&text).unwrap_err().to_string();
        assert!(err.contains(expected), "{err}\n  expected: {expected}");
    }
    // Near the spool but not inside it is fine.
    parse(&GOOD.replacen("/srv/print/5cm", "/var/lib/crispen-hot", 1)).unwrap();
}

/// `[store]` and `[farm] host`: a shared farm's settings are checked like the rest, a
/// password in the connection string is refused without being repeated, and a folder
/// may then name printers of other hosts.
#[test]
fn a_shared_farm_is_checked() {
    let store = "[store]\npostgres = \"host=/run/postgresql dbname=crispen\"\n";
    let c = parse(&format!("{GOOD}{store}")).unwrap();
    let shared = c.store.expect("[store] read");
    assert_eq!(shared.lease, Duration::from_secs(15));
    assert!(!c.farm.host.is_empty(), "the hostname by default");
    let other = GOOD.replacen("printers = [\"sim\"]", "printers = [\"rack-2-a\"]", 1);
    assert!(
        parse(&other).is_err(),
        "an unknown printer without a shared farm"
    );
    parse(&format!("{other}{store}")).expect("another host's printer in a shared farm");
    for (text, key, says) in [
        (
            "postgres = \"host=/tmp password=hunter2\"",
            "postgres",
            "holds a password",
        ),
        ("postgres = \"host=/tmp bogus=1\"", "postgres", "bogus"),
        (
            "postgres = \"host=/tmp\"\nlease_s = 1",
            "lease_s",
            "must be",
        ),
        (
            "postgres = \"host=/tmp\"\nlease_s = 1e300",
            "lease_s",
            "must be",
        ),
    ] {
        let err = parse(&format!("{GOOD}[store]\n{text}\n"))
            .unwrap_err()
            .to_string();
        assert!(err.contains(&format!("[store]: key `{key}`")), "{err}");
        assert!(err.contains(says) && !err.contains("hunter2"), "{err}");
    }
    for bad in ["", "rack 2", "r/2", &"x".repeat(65)] {
        let text = GOOD.replacen(
            "max_heating = 1",
            &format!("max_heating = 1\nhost = {bad:?}"),
            1,
        );
        let err = parse(&text).unwrap_err().to_string();
        assert!(err.contains("[farm]: key `host`"), "{err}");
    }
    let named = GOOD.replacen(
        "max_heating = 1",
        "max_heating = 1\nhost = \"rack-2.b_c\"",
        1,
    );
    assert_eq!(parse(&named).unwrap().farm.host, "rack-2.b_c");
}

/// A known table missing a required key was once refused as an unknown table (a
/// `[[notify]]` without `name`, the list of known tables leaving it out): each table
/// says which of its keys is missing, and the known tables are the file's.
#[test]
fn a_missing_key_is_named_in_every_table() {
    let cases = [
        (
            "[[notify]]\nurl = \"https://ntfy.sh/farm\"\n",
            "[[notify]] #1: missing key `name`",
        ),
        (
            "[[machine]]\nbased_on = \"marlin-175\"\n",
            "[[machine]] #1: missing key `name`",
        ),
        (
            "[[printer]]\nfirmware = \"marlin2\"\n",
            "[[printer]] #3: missing key `name`",
        ),
        (
            "[[folder]]\nheight_mm = 5\nprinters = [\"sim\"]\n",
            "[[folder]] #3: missing key `path`",
        ),
        (
            "[http]\napi_key_file = \"k\"\n",
            "[http]: missing key `listen`",
        ),
        ("[store]\nlease_s = 5\n", "[store]: missing key `postgres`"),
        ("[spoolman]\npoll_s = 5\n", "[spoolman]: missing key `url`"),
    ];
    for (table, expected) in cases {
        let err = parse(&format!("{GOOD}{table}")).unwrap_err().to_string();
        assert!(err.contains(expected), "{err}");
        assert!(!err.contains("unknown table"), "{err}");
    }
    let err = parse("[control]\nsocket = \"s\"\n")
        .unwrap_err()
        .to_string();
    assert!(err.contains("missing key `spool`"), "{err}");
    let headers: Vec<&str> = KNOWN_TABLES
        .iter()
        .map(|h| h.trim_matches(['[', ']']))
        .collect();
    assert_eq!(headers, keys::tables().unwrap());
}

/// An unknown table was once reported as an unknown key of the table above it.
#[test]
fn unknown_top_level_table_is_named_as_a_table() {
    for header in ["[[gantry]]", "[machines]", "[gantry.x]"] {
        let text = format!("{GOOD}{header}\nname = \"x\"\n");
        let err = parse(&text).unwrap_err().to_string();
        assert!(err.contains(&format!("unknown table `{header}`")), "{err}");
        assert!(err.contains("the top level"), "{err}");
        assert!(!err.contains("[[folder]] #2"), "{err}");
    }
}

/// `[[machine]]` tables and `machine =` on printers: the firmware comes from the
/// machine, a printer without one keeps its old meaning, and every mistake is named.
#[test]
fn machines_are_checked_and_printers_take_theirs() {
    let c = parse(GOOD).unwrap();
    // Without `machine`: what the firmware always meant.
    assert_eq!(c.printers[0].machine.name, "ultimaker2");
    assert_eq!(
        c.printers[1].machine.name,
        crate::machine::DEFAULT_MARLIN_MACHINE
    );
    let machines = "[[machine]]\nname = \"generic-175\"\nfirmware = \"marlin20\"\n\
        bed_mm = [220, 220, 250]\nnozzle_mm = 0.4\nfilament_mm = 1.75\nheated_bed = true\n\
        max_hotend_c = 260\nmax_bed_c = 110\n";
    let text = GOOD
        .replacen("[[printer]]", &format!("{machines}[[printer]]"), 1)
        .replacen("firmware = \"marlin2\"", "machine = \"generic-175\"", 1)
        .replacen(
            "firmware = \"ultimaker2\"",
            "machine = \"ultimaker2plus\"\nnozzle_mm = 0.8",
            1,
        );
    let c = parse(&text).unwrap();
    assert_eq!(c.machines.len(), 1);
    assert_eq!(c.printers[1].machine.name, "generic-175");
    assert_eq!(c.printers[1].firmware, Firmware::Marlin20);
    assert_eq!(c.printers[1].baud, 115_200);
    assert_eq!(c.printers[0].machine.name, "ultimaker2plus-0.8mm");
    assert_eq!(c.printers[0].firmware, Firmware::Ultimaker2);

    let with = |extra: &str, printer: &str| {
        let text = GOOD
            .replacen("[[printer]]", &format!("{machines}{extra}[[printer]]"), 1)
            .replacen("firmware = \"ultimaker2\"", printer, 1);
        parse(&text).unwrap_err().to_string()
    };
    for (extra, printer, expected) in [
        ("", "machine = \"nope\"", "[[printer]] #1 (name \"um2-a\"): key `machine`: no machine is named \"nope\""),
        ("", "machine = \"generic-175\"\nfirmware = \"ultimaker2\"", "key `firmware`: is ultimaker2, but machine \"generic-175\" runs marlin20"),
        ("", "machine = \"ultimaker2\"\nnozzle_mm = 0.6", "key `nozzle_mm`: the ultimaker2 takes nozzles from 0.4 to 0.4 mm"),
        ("", "", "key `machine`: missing"),
        ("[[machine]]\nname = \"x\"\nbased_on = \"generic-175\"\nbed_mm = [0, 1, 2]\n", "firmware = \"ultimaker2\"", "[[machine]] #2 (name \"x\"): key `bed_mm`"),
        ("[[machine]]\nname = \"generic-175\"\nbased_on = \"ultimaker2\"\n", "firmware = \"ultimaker2\"", "[[machine]] #2 (name \"generic-175\"): key `name`: \"generic-175\" is already a machine"),
        ("[[machine]]\nname = \"x\"\nbased_on = \"ultimaker2\"\nnozle_mm = 1\n", "firmware = \"ultimaker2\"", "unknown field `nozle_mm`"),
    ] {
        let e = with(extra, printer);
        assert!(e.contains(expected), "{e}\n  expected: {expected}");
    }
    // A folder taller than all its printers' machines build fails every job: refused.
    let e = parse(&GOOD.replacen("height_mm = 30", "height_mm = 260", 1))
        .unwrap_err()
        .to_string();
    assert!(
        e.contains("[[folder]] #2") && e.contains("taller than any"),
        "{e}"
    );
}

/// The shipped example names two Ultimaker 2s: they must be sliced for that machine,
/// and the `[[machine]]` example in its comments must load as written.
#[test]
fn the_example_config_is_right_for_its_printers() {
    let text = include_str!("../../../config/crispen.toml");
    let c = parse(text).unwrap();
    assert_eq!(c.printers.len(), 2);
    for p in &c.printers {
        assert_eq!(
            (p.machine.name.as_str(), p.firmware),
            ("ultimaker2", Firmware::Ultimaker2)
        );
    }
    let example: String = text
        .lines()
        .skip_while(|l| !l.starts_with("# [[machine]]"))
        .take_while(|l| l.starts_with("# ") && !l.starts_with("# # "))
        .map(|l| format!("{}\n", &l[2..]))
        .collect();
    let c = parse(&format!("{text}\n{example}")).unwrap();
    assert_eq!(c.machines[0].filament_mm, 1.75);
}

#[test]
fn wrong_type_is_a_parse_error_with_location() {
    let text = GOOD.replace("max_heating = 1", "max_heating = \"one\"");
    let err = parse(&text).unwrap_err().to_string();
    assert!(err.contains("[farm]"), "{err}");
    assert!(err.contains("line 7"), "{err}");
}

/// `[printer.simulate] speed` is a speed-up factor, higher is faster; `time_scale`, its
/// inverse (which read as a speed: 20 made a printer twenty times slower), is still
/// read, with a warning that names `speed`.
#[test]
fn simulated_speed_is_a_factor_and_time_scale_still_read() {
    let sim = |table: &str| parse(&GOOD.replace("time_scale = 0.5", table));
    let scale = |c: &Config| match c.printers[1].port {
        PrinterPort::Simulated { time_scale, .. } => time_scale,
        _ => panic!("not simulated"),
    };
    let c = sim("speed = 20").unwrap();
    assert_eq!(scale(&c), 0.05);
    assert!(c.warnings.is_empty(), "{:?}", c.warnings);
    assert_eq!(scale(&sim("speed = 2.5").unwrap()), 0.4);
    assert_eq!(scale(&sim("speed = \"instant\"").unwrap()), 0.0);
    let c = sim("time_scale = 0.5").unwrap();
    assert_eq!(scale(&c), 0.5);
    assert!(
        c.warnings.iter().any(|w| w.contains(
            "[[printer]] #2 (name \"sim\").simulate key `time_scale`: replaced by `speed`"
        ) && w.ends_with("time_scale = 0.5 is speed = 2")),
        "{:?}",
        c.warnings
    );
    for (bad, key) in [
        ("speed = 0", "speed"),
        ("speed = \"fast\"", "speed"),
        ("speed = 1e9", "speed"),
        ("speed = 2\ntime_scale = 0.5", "time_scale"),
    ] {
        let e = sim(bad).unwrap_err().to_string();
        assert!(e.contains(&format!(".simulate: key `{key}`")), "{e}");
    }
}

#[test]
fn builtin_default_is_a_simulated_demo() {
    let c = Config::builtin_default();
    assert_eq!(c.printers.len(), 1);
    assert!(matches!(c.printers[0].port, PrinterPort::Simulated { .. }));
    assert!(c.folders[0].path.ends_with("crispen-demo/hot/50mm"));
    // Absolute, so watch events (which carry absolute paths) match the folder.
    assert!(c.folders[0].path.is_absolute() && c.spool_dir.is_absolute());
    assert_eq!(c.folders[0].height_mm, 50.0);
}

/// What printers hold and folders ask: read into the checked config, and every bad value
/// refused with its section and key.
#[test]
fn filament_keys_are_checked_with_section_and_key() {
    let text = GOOD
        .replace(
            "port = \"/dev/ttyACM0\"\n",
            "port = \"/dev/ttyACM0\"\nmaterial = \"petg\"\ncolour = \"Black\"\nnozzle = \"hardened\"\ntags = [\"big\"]\n",
        )
        + "[spoolman]\nurl = \"http://127.0.0.1:7912\"\npoll_s = 5\n";
    let c = parse(&text).unwrap();
    let p = &c.printers[0];
    let f = p.filament.as_ref().unwrap();
    assert_eq!((f.material.as_str(), f.colour.as_str()), ("PETG", "black"));
    assert_eq!(f.diameter_mm, p.machine.filament_mm);
    assert!(p.hardened);
    assert_eq!(p.tags, ["big"]);
    assert_eq!(
        c.spoolman.as_ref().unwrap().poll,
        std::time::Duration::from_secs(5)
    );
    assert_eq!(c.farm.spool_low_g, 100.0);
    for (from, to, expected) in [
        (
            "port = \"/dev/ttyACM0\"\n",
            "port = \"/dev/ttyACM0\"\nnozzle = \"steel\"\n",
            "[[printer]] #1 (name \"um2-a\"): key `nozzle`",
        ),
        (
            "port = \"/dev/ttyACM0\"\n",
            "port = \"/dev/ttyACM0\"\ncolour = \"red\"\n",
            "key `colour`: needs `material`",
        ),
        (
            "port = \"/dev/ttyACM0\"\n",
            "port = \"/dev/ttyACM0\"\ntags = [\"a b\"]\n",
            "key `tags`",
        ),
        (
            "max_heating = 1\n",
            "max_heating = 1\nspool_low_g = -1\n",
            "[farm]: key `spool_low_g`",
        ),
    ] {
        let err = parse(&GOOD.replacen(from, to, 1)).unwrap_err().to_string();
        assert!(err.contains(expected), "{err}");
    }
    for (extra, expected) in [
        ("[spoolman]\nurl = \"ftp://x\"\n", "[spoolman]: key `url`"),
        (
            "[spoolman]\nurl = \"http://x\"\npoll_s = 0\n",
            "[spoolman]: key `poll_s`",
        ),
        (
            "[spoolman]\nurl = \"http://x\"\nport = 1\n",
            "unknown field `port`",
        ),
    ] {
        let err = parse(&format!("{GOOD}{extra}")).unwrap_err().to_string();
        assert!(err.contains(expected), "{err}");
    }
    let folder = |extra: &str| {
        let text = format!(
            "{GOOD}[[folder]]\npath = \"/srv/x\"\nheight_mm = 30\nprinters = [\"um2-a\"]\n{extra}"
        );
        parse(&text)
    };
    let c = folder("material = \"PETG\"\ncolour = \"black\"\nnozzle_mm = 0.4\npriority = 5\ntags = [\"big\"]\n").unwrap();
    let f = c.folders.last().unwrap();
    assert_eq!(f.asks.material.as_deref(), Some("PETG"));
    assert_eq!(
        f.settings.material.as_deref(),
        Some("petg"),
        "sliced for what it asks"
    );
    assert_eq!((f.asks.priority, f.asks.nozzle_mm), (5, Some(0.4)));
    for (extra, key) in [
        ("priority = 101\n", "key `priority`"),
        ("nozzle_mm = 0\n", "key `nozzle_mm`"),
        ("material = \"\"\n", "key `material`"),
        (
            "material = \"pla\"\n[folder.settings]\nmaterial = \"petg\"\n",
            "key `material`",
        ),
    ] {
        let err = folder(extra).unwrap_err().to_string();
        assert!(
            err.contains("[[folder]]") && err.contains(key),
            "{extra}: {err}"
        );
    }
}

/// Every name an operator gives in the config is refused with a control or bidi
/// character, naming its section and key (a material with U+202E was taken and printed
/// raw by `crispen spools`): by the one check file names have (`crate::names`), or by the
/// plain-word rules of printer, machine, host and tag names.
#[test]
fn names_with_control_or_bidi_characters_are_refused() {
    // TOML escapes: the parsed text holds the characters themselves.
    let printer = "port = \"/dev/ttyACM0\"\n";
    for (from, to, section, key) in [
        (
            printer,
            "port = \"/dev/ttyACM0\"\nmaterial = \"PLA\\u202EGTEP\"\n",
            "[[printer]] #1",
            "key `material`",
        ),
        (
            printer,
            "port = \"/dev/ttyACM0\"\nmaterial = \"PLA\"\ncolour = \"bl\\u001B[31mack\"\n",
            "[[printer]] #1",
            "key `colour`",
        ),
        (
            printer,
            "port = \"/dev/ttyACM0\"\nmaterial = \"PLA\\u2028x\"\n",
            "[[printer]] #1",
            "key `material`",
        ),
        (
            printer,
            "port = \"/dev/ttyACM0\"\ntags = [\"big\\u2066\"]\n",
            "[[printer]] #1",
            "key `tags`",
        ),
        (
            "name = \"um2-a\"",
            "name = \"um2\\u202E-a\"",
            "[[printer]] #1",
            "key `name`",
        ),
        (
            "path = \"/srv/print/5cm\"",
            "path = \"/srv/print/5cm\\u202Emc5\"",
            "[[folder]] #1",
            "key `path`",
        ),
        (
            "path = \"hot/igea\"",
            "path = \"hot/ig\\u0007ea\"",
            "[[folder]] #2",
            "key `path`",
        ),
        (
            "strength = 0.4\n",
            "strength = 0.4\nmaterial = \"P\\u200FLA\"\n",
            "[[folder]] #1",
            "key `material`",
        ),
        (
            "strength = 0.4\n",
            "strength = 0.4\nmaterial = \"PLA\"\ncolour = \"\\u061Cred\"\n",
            "[[folder]] #1",
            "key `colour`",
        ),
        (
            "max_heating = 1\n",
            "max_heating = 1\nhost = \"rack\\u202E1\"\n",
            "[farm]",
            "key `host`",
        ),
    ] {
        let text = GOOD.replacen(from, to, 1);
        assert_ne!(text, GOOD, "{to}");
        let err = parse(&text).unwrap_err().to_string();
        assert!(err.contains(section) && err.contains(key), "{to}: {err}");
        // The error shows the name harmless.
        assert!(
            !err.contains([
                '\u{202e}', '\u{1b}', '\u{2028}', '\u{2066}', '\u{7}', '\u{200f}', '\u{61c}'
            ]),
            "{to}: {err:?}"
        );
    }
    let machine = format!("{GOOD}\n[[machine]]\nname = \"m\\u202E\"\nbased_on = \"ultimaker2\"\n");
    let err = parse(&machine).unwrap_err().to_string();
    assert!(
        err.contains("[[machine]] #1") && err.contains("name"),
        "{err}"
    );
    // Any script is a name all the same.
    let text = GOOD.replacen(
        "strength = 0.4\n",
        "strength = 0.4\nmaterial = \"PLA\"\ncolour = \"чёрный\"\n",
        1,
    );
    parse(&text).unwrap();
}

/// `[[maintenance]]`: tasks apply by printer or tag, need an interval within its bounds,
/// and are refused naming the table and the key.
#[test]
fn maintenance_tasks_are_checked() {
    let with = |table: &str| parse(&format!("{GOOD}\n[[maintenance]]\n{table}"));
    let c = with(
        "name = \"nozzle\"\nprinters = [\"sim\"]\nevery_kg = 2\nevery_jobs = 100\nblock = true\n",
    )
    .unwrap();
    let t = &c.maintenance[0];
    assert_eq!(t.name, "nozzle");
    assert!(t.block);
    assert_eq!(
        t.every,
        [
            (crate::daemon::care::Measure::Kg, 2.0),
            (crate::daemon::care::Measure::Jobs, 100.0)
        ]
    );
    assert!(t.applies_to("sim", &[]) && !t.applies_to("um2-a", &[]));
    for (table, key, says) in [
        ("name = \"n\"\n", "every_print_hours", "needs an interval"),
        (
            "name = \"n\"\nevery_jobs = 0.5\n",
            "every_jobs",
            "whole number",
        ),
        ("name = \"n\"\nevery_kg = -1\n", "every_kg", "from 0.01"),
        ("name = \"n\"\nevery_days = nan\n", "every_days", "got NaN"),
        (
            "name = \"n\"\nprinters = [\"x\"]\nevery_days = 1\n",
            "printers",
            "\"x\"",
        ),
        (
            "name = \"n\"\ntags = [\"big\"]\nevery_days = 1\n",
            "tags",
            "\"big\"",
        ),
        ("name = \"a/b\"\nevery_days = 1\n", "name", "without `/`"),
    ] {
        let e = with(table).unwrap_err().to_string();
        assert!(
            e.contains("[[maintenance]] #1")
                && e.contains(&format!("key `{key}`"))
                && e.contains(says),
            "{table}: {e}"
        );
    }
    let e = with("name = \"n\"\nevery_days = 1\n[[maintenance]]\nname = \"n\"\nevery_days = 2\n")
        .unwrap_err()
        .to_string();
    assert!(
        e.contains("[[maintenance]] #2") && e.contains("another task"),
        "{e}"
    );
    let e = with("name = \"n\"\nevery_day = 1\n")
        .unwrap_err()
        .to_string();
    assert!(e.contains("every_day"), "{e}");
}

/// `[printer.power]`: each kind with what it needs, nothing it does not take, bounded
/// timings; the error names the printer's table and the key.
#[test]
fn power_switches_are_checked() {
    let with = |table: &str| {
        parse(&GOOD.replace(
            "[[printer]]\nname = \"sim\"\nfirmware = \"marlin2\"\n",
            &format!(
                "[[printer]]\nname = \"sim\"\nfirmware = \"marlin2\"\n[printer.power]\n{table}"
            ),
        ))
    };
    let c =
        with("kind = \"shelly\"\nurl = \"http://10.0.0.5\"\noff_after_idle_min = 30\n").unwrap();
    let p = c.printers[1].power.as_ref().unwrap();
    assert_eq!(p.switch.kind(), "shelly");
    assert_eq!(p.off_after_idle, Some(Duration::from_secs(1800)));
    assert_eq!((p.safe_hotend_c, p.boot), (50.0, Duration::from_secs(120)));
    let c = with("kind = \"homeassistant\"\nurl = \"http://ha:8123\"\nentity = \"switch.um2\"\ntoken_file = \"ha.token\"\n")
        .unwrap();
    assert!(matches!(
        &c.printers[1].power.as_ref().unwrap().switch,
        crate::power::Switch::HomeAssistant { token_file, .. } if token_file == Path::new("/etc/crispen/ha.token")
    ));
    for (table, key, says) in [
        ("kind = \"kasa\"\n", "kind", "\"kasa\""),
        ("kind = \"tasmota\"\n", "url", "needs `url`"),
        ("kind = \"tasmota\"\nurl = \"ftp://x\"\n", "url", "not an http"),
        ("kind = \"tasmota\"\nurl = \"http://x\"\nentity = \"switch.a\"\n", "entity", "homeassistant"),
        ("kind = \"homeassistant\"\nurl = \"http://x\"\nentity = \"light.a\"\ntoken_file = \"t\"\n", "entity", "switch.NAME"),
        ("kind = \"homeassistant\"\nurl = \"http://x\"\nentity = \"switch.a\"\n", "token_file", "needs"),
        ("kind = \"http\"\non_url = \"http://r/on\"\n", "off_url", "needs"),
        ("kind = \"shelly\"\nurl = \"http://x\"\nsafe_hotend_c = 200\n", "safe_hotend_c", "from 25"),
        ("kind = \"shelly\"\nurl = \"http://x\"\noff_after_idle_min = 0\n", "off_after_idle_min", "from 0.01"),
        ("kind = \"shelly\"\nurl = \"http://x\"\nboot_s = inf\n", "boot_s", "got inf"),
    ] {
        let e = with(table).unwrap_err().to_string();
        assert!(
            e.contains("[[printer]] #2 (name \"sim\").power") && e.contains(&format!("key `{key}`")) && e.contains(says),
            "{table}: {e}"
        );
    }
}
