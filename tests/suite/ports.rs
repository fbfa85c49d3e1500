//! `crispen ports` and the port checks of `crispen run --check`, with the real binary on
//! real ptys: the probe asks `crispen sim` for its M115 answer and gives up clearly on a
//! silent port; the listing reads a `/dev`-like folder laid out by the test, whose
//! `serial/by-id` links point at real pty devices; the config check refuses two printers
//! on one device and warns about kernel names such as `ttyACM0`.

use crate::common;
use common::daemon::{spawn_sim, Killed, BIN};

use std::os::fd::OwnedFd;
use std::os::unix::fs::symlink;
use std::path::{Path, PathBuf};
use std::process::{Command, Output};

/// A `crispen sim` process and the pty it listens on.
struct Sim {
    _process: Killed,
    device: PathBuf,
}

impl Sim {
    fn start(firmware: &str) -> Sim {
        let (child, device) =
            spawn_sim(Command::new(BIN).args(["sim", "--time-scale", "0", "--firmware", firmware]));
        Sim {
            _process: Killed(child),
            device,
        }
    }
}

/// A pty nobody answers on: the test keeps the master side open and never reads it.
fn silent_pty() -> (OwnedFd, PathBuf) {
    let pty = nix::pty::openpty(None, None).unwrap();
    let device = nix::unistd::ttyname(&pty.slave).unwrap();
    (pty.master, device)
}

fn crispen(args: &[&str]) -> Output {
    Command::new(BIN).args(args).output().unwrap()
}

fn text(bytes: &[u8]) -> String {
    String::from_utf8_lossy(bytes).into_owned()
}

fn s(path: &Path) -> &str {
    path.to_str().unwrap()
}

#[test]
fn probe_prints_the_firmware_answer_as_written() {
    let marlin = Sim::start("marlin2");
    let um2 = Sim::start("ultimaker2");
    let out = crispen(&["ports", "--probe", s(&marlin.device), "--timeout", "30"]);
    let stdout = text(&out.stdout);
    assert!(out.status.success(), "{}\n{}", stdout, text(&out.stderr));
    let lines: Vec<&str> = stdout.lines().collect();
    // The whole first line, with the keys the protocol parser does not know about.
    assert_eq!(
        lines[0],
        "FIRMWARE_NAME:Marlin 2.1.2 (crispen sim) SOURCE_CODE_URL:github.com/MarlinFirmware/Marlin \
         PROTOCOL_VERSION:1.0 MACHINE_TYPE:crispen sim EXTRUDER_COUNT:1 \
         UUID:cede2a2f-41a2-4748-9b12-c55c62f367ff"
    );
    assert!(lines.contains(&"Cap:AUTOREPORT_TEMP:1"), "{stdout}");
    assert!(lines.contains(&"Cap:ADVANCED_OK:1"), "{stdout}");
    assert!(lines[1..].iter().all(|l| l.starts_with("Cap:")), "{stdout}");
    assert!(text(&out.stderr).contains("answered after"));

    let out = crispen(&["ports", "--probe", s(&um2.device), "--timeout", "30"]);
    assert!(out.status.success(), "{}", text(&out.stderr));
    // Ultimaker2Marlin has no M110 (its `Unknown command` echo is not part of the answer)
    // and no Cap: lines.
    assert_eq!(
        text(&out.stdout),
        "FIRMWARE_NAME:Marlin Ultimaker2; Sprinter/grbl mashup for gen6 \
         FIRMWARE_URL:https://github.com/Ultimaker/Ultimaker2Marlin PROTOCOL_VERSION:1.0 \
         MACHINE_TYPE:Ultimaker EXTRUDER_COUNT:1\n"
    );
}

#[test]
fn probe_of_a_silent_port_gives_up_with_the_reason() {
    let (_master, device) = silent_pty();
    let out = crispen(&["ports", "--probe", s(&device), "--timeout", "2"]);
    let stderr = text(&out.stderr);
    assert!(!out.status.success());
    assert!(out.stdout.is_empty());
    assert!(
        stderr.contains(&format!(
            "error: {}: no answer to M115 within 2.",
            device.display()
        )),
        "{stderr}"
    );
    assert!(stderr.contains("nothing at all was received"), "{stderr}");

    // A port another program holds (as the daemon holds its printers') is refused once the
    // wait for it ran out.
    let held = serialport::new(s(&device), 0).open_native().unwrap();
    let out = crispen(&["ports", "--probe", s(&device), "--timeout", "2"]);
    let stderr = text(&out.stderr);
    assert!(!out.status.success());
    assert!(
        stderr.contains(&format!("cannot open printer port {}", device.display())),
        "{stderr}"
    );
    assert!(stderr.contains("another program has it open"), "{stderr}");
    drop(held);

    let out = crispen(&["ports", "--probe", "/nonexistent/ttyACM9", "--timeout", "2"]);
    let stderr = text(&out.stderr);
    assert!(!out.status.success());
    assert!(
        stderr.contains("cannot open printer port /nonexistent/ttyACM9"),
        "{stderr}"
    );
}

/// A `/dev`-like folder with a `serial/by-id` link to a real pty.
fn dev_dir(link_name: &str, device: &Path) -> (tempfile::TempDir, PathBuf) {
    let dev = tempfile::tempdir().unwrap();
    let by_id = dev.path().join("serial/by-id");
    std::fs::create_dir_all(&by_id).unwrap();
    let link = by_id.join(link_name);
    symlink(device, &link).unwrap();
    (dev, link)
}

fn write_config(dir: &Path, printers: &[(&str, &str)]) -> PathBuf {
    let mut config = format!("[spool]\ndir = {:?}\n", s(&dir.join("spool")));
    for (name, port) in printers {
        config +=
            &format!("[[printer]]\nname = {name:?}\nport = {port:?}\nfirmware = \"marlin2\"\n");
    }
    let path = dir.join("crispen.toml");
    std::fs::write(&path, config).unwrap();
    path
}

#[test]
fn listing_shows_stable_names_and_the_printers_on_them() {
    let (_master, device) = silent_pty();
    let (dev, link) = dev_dir(
        "usb-Prusa_Research__prusa3d.com__Original_Prusa_i3_MK3_CZPX1234-if00",
        &device,
    );
    let config = write_config(
        dev.path(),
        &[
            ("mk3", s(&link)),
            (
                "um2",
                "/dev/serial/by-id/usb-Ultimaker_B.V._Ultimaker_2-if00",
            ),
        ],
    );
    let out = crispen(&["ports", "--dev", s(dev.path()), "--config", s(&config)]);
    let stdout = text(&out.stdout);
    assert!(out.status.success(), "{stdout}\n{}", text(&out.stderr));
    let block = format!(
        "{}\n  device   {}\n  printer  mk3 (in {})\n",
        link.display(),
        device.display(),
        config.display()
    );
    assert!(stdout.contains(&block), "{stdout}\nexpected:\n{block}");
    assert!(
        stdout.contains(&format!(
            "\nPrinters in {} on other ports:\n  um2  /dev/serial/by-id/usb-Ultimaker_B.V._Ultimaker_2-if00 (not present",
            config.display()
        )),
        "{stdout}"
    );

    // A config that was asked for but cannot be read is an error, not an empty listing.
    let out = crispen(&[
        "ports",
        "--dev",
        s(dev.path()),
        "--config",
        "/nonexistent.toml",
    ]);
    assert!(!out.status.success(), "a missing --config is an error");
    assert!(text(&out.stderr).contains("/nonexistent.toml: cannot read"));
}

/// An operator allowed on the control socket but not to read the daemon's key and password
/// files (here: they are not there at all) can still list the ports against the config and
/// ask the daemon for its status: neither command reads a secret. `crispen ports` once
/// loaded the whole config and failed on them.
#[test]
fn commands_short_of_the_daemon_read_none_of_its_secrets() {
    let (_master, device) = silent_pty();
    let (dev, link) = dev_dir("usb-Prusa_Research_MK3_CZPX9-if00", &device);
    let config = write_config(dev.path(), &[("mk3", s(&link))]);
    let mut toml = std::fs::read_to_string(&config).unwrap();
    toml += "[http]\nlisten = \"127.0.0.1:8080\"\napi_key_file = \"unreadable.key\"\n\
             [store]\npostgres = \"host=/run/postgresql dbname=crispen\"\n\
             password_file = \"unreadable.pw\"\n";
    std::fs::write(&config, toml).unwrap();

    let out = crispen(&["ports", "--dev", s(dev.path()), "--config", s(&config)]);
    let (stdout, stderr) = (text(&out.stdout), text(&out.stderr));
    assert!(out.status.success(), "{stdout}\n{stderr}");
    assert!(stdout.contains("printer  mk3"), "{stdout}");

    // No daemon runs: the answer is about the socket, never about a secret.
    let out = crispen(&["status", "--config", s(&config)]);
    let stderr = text(&out.stderr);
    assert!(!out.status.success());
    assert!(
        stderr.contains(&format!(
            "cannot reach the daemon at {}",
            dev.path().join("spool/crispen.sock").display()
        )),
        "{stderr}"
    );

    // The daemon itself reads them, and says which it cannot.
    let out = crispen(&["run", "--check", "--config", s(&config)]);
    assert!(!out.status.success());
    assert!(
        text(&out.stderr).contains("[store]: key `password_file`"),
        "{}",
        text(&out.stderr)
    );
}

#[test]
fn run_check_refuses_two_printers_on_one_device() {
    let (_master, device) = silent_pty();
    let (dev, link) = dev_dir("usb-1a86_USB_Serial-if00-port0", &device);
    let config = write_config(dev.path(), &[("a", s(&link)), ("b", s(&device))]);
    let out = crispen(&["run", "--check", "--config", s(&config)]);
    let stderr = text(&out.stderr);
    assert!(!out.status.success(), "{stderr}");
    assert_eq!(
        stderr.trim_end(),
        format!(
            "error: {}: [[printer]] #2 (name \"b\"): key `port`: printer \"a\" already uses this \
             port ({} and {} are the same device); each printer needs its own",
            config.display(),
            link.display(),
            device.display()
        )
    );
}

#[test]
fn run_check_warns_about_kernel_names_and_names_the_stable_one() {
    let (_master, device) = silent_pty();
    let dev = tempfile::tempdir().unwrap();
    // As udev lays it out: the kernel name, and a by-id link to it.
    let acm = dev.path().join("ttyACM0");
    symlink(&device, &acm).unwrap();
    std::fs::create_dir_all(dev.path().join("serial/by-id")).unwrap();
    let link = dev
        .path()
        .join("serial/by-id/usb-Ultimaker_B.V._Ultimaker_2-if00");
    symlink("../../ttyACM0", &link).unwrap();
    let unplugged = dev.path().join("ttyUSB3");
    let config = write_config(
        dev.path(),
        &[
            ("um2", s(&acm)),
            ("gone", s(&unplugged)),
            ("good", s(&link.with_file_name("x"))),
        ],
    );
    let out = crispen(&["run", "--check", "--config", s(&config)]);
    let stderr = text(&out.stderr);
    assert!(out.status.success(), "{stderr}");
    assert_eq!(
        stderr,
        format!(
            "warning: printer \"um2\": port {} may name another device after a reboot or \
             re-plug; use port = {:?}, the same device now\n\
             warning: printer \"gone\": port {} may name another device after a reboot or \
             re-plug; no /dev/serial/by-id link points at it now; `crispen ports` lists the \
             stable names of the plugged-in devices\n",
            acm.display(),
            s(&link),
            unplugged.display()
        )
    );
    assert!(text(&out.stdout).contains(": OK (3 printers, 0 folders)"));
}

/// `crispen ports | head` with the reader gone before anything is written: the command ends
/// as Unix tools do (SIGPIPE), without a panic on stderr.
#[test]
fn a_listing_whose_reader_is_gone_ends_quietly() {
    use std::os::unix::process::ExitStatusExt;
    let (reader, writer) = nix::unistd::pipe().unwrap();
    drop(reader);
    let output = Command::new(BIN)
        .arg("ports")
        .stdout(std::process::Stdio::from(writer))
        .stderr(std::process::Stdio::piped())
        .output()
        .unwrap();
    let stderr = text(&output.stderr);
    assert!(!stderr.contains("panicked"), "{stderr}");
    assert_eq!(
        output.status.signal(),
        Some(13),
        "{:?}: {stderr}",
        output.status
    );
}
