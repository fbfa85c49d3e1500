//! The systemd unit in `config/` is checked by systemd itself (`systemd-analyze verify`),
//! with its ExecStart pointed at the binary under test: a typo in a sandboxing option
//! would otherwise only show on a print-farm host. Its sandboxing is scored by
//! `systemd-analyze security`, which must not get worse.

use std::process::Command;

fn config_file(name: &str) -> String {
    std::fs::read_to_string(format!("{}/config/{name}", env!("CARGO_MANIFEST_DIR"))).unwrap()
}

/// Writes the unit (running the binary under test) and, if given, the HTTP drop-in into a
/// temporary folder laid out as systemd expects, and has systemd verify them.
fn verify(unit: &str, http_drop_in: Option<&str>) {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("crispen.service");
    std::fs::write(
        &path,
        unit.replace("/usr/bin/crispen", env!("CARGO_BIN_EXE_crispen")),
    )
    .unwrap();
    if let Some(drop_in) = http_drop_in {
        std::fs::create_dir(dir.path().join("crispen.service.d")).unwrap();
        std::fs::write(dir.path().join("crispen.service.d/http.conf"), drop_in).unwrap();
    }
    let out = Command::new("systemd-analyze")
        .arg("verify")
        .arg(&path)
        .output()
        .expect("systemd-analyze (Debian package systemd; scripts/setup installs it)");
    let stderr = String::from_utf8_lossy(&out.stderr);
    // verify prints problems with these files prefixed by their file or unit name.
    let problems: Vec<&str> = stderr
        .lines()
        .filter(|l| l.contains("crispen.service") || l.contains("http.conf"))
        .collect();
    assert!(out.status.success() && problems.is_empty(), "{}", stderr);
}

#[test]
fn systemd_unit_verifies() {
    let unit = config_file("crispen.service");
    assert!(unit.contains("ExecStart=/usr/bin/crispen run"));
    verify(&unit, None);
}

/// The TCP listener of `[http]` is allowed only where it is configured: the unit itself
/// keeps the daemon off the network, and the drop-in `config/crispen-http.conf` opens
/// exactly the HTTP port; systemd accepts the unit with the drop-in.
#[test]
fn tcp_only_with_the_http_drop_in() {
    let unit = config_file("crispen.service");
    assert!(unit.lines().any(|l| l == "PrivateNetwork=yes"));
    assert!(unit.lines().any(|l| l == "RestrictAddressFamilies=AF_UNIX"));
    let drop_in = config_file("crispen-http.conf");
    for line in [
        "PrivateNetwork=no",
        "RestrictAddressFamilies=AF_UNIX AF_INET AF_INET6",
        "SocketBindDeny=any",
    ] {
        assert!(drop_in.lines().any(|l| l == line), "drop-in lacks {line}");
    }
    verify(&unit, Some(&drop_in));
}

/// The exposure `systemd-analyze security` gives the unit (0 safest, 10 unsafe).
fn exposure(unit: &str) -> f64 {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("crispen.service");
    std::fs::write(&path, unit).unwrap();
    let out = Command::new("systemd-analyze")
        .args(["security", "--offline=true", "--no-pager"])
        .arg(&path)
        .output()
        .expect("systemd-analyze (Debian package systemd; scripts/setup installs it)");
    let text = String::from_utf8_lossy(&out.stdout);
    let line = text
        .lines()
        .find(|l| l.contains("Overall exposure level"))
        .unwrap_or_else(|| {
            panic!(
                "no exposure level in: {text}{}",
                String::from_utf8_lossy(&out.stderr)
            )
        });
    line.split_once("crispen.service:")
        .and_then(|(_, rest)| rest.split_whitespace().next())
        .and_then(|n| n.parse().ok())
        .unwrap_or_else(|| panic!("cannot read the exposure in {line:?}"))
}

/// The unit's sandboxing scores 0.7 (issue 20: it was 2.7, without a system call filter,
/// ProtectProc, ProcSubset, RemoveIPC or an IP deny list); what is left is what serial
/// ports need (devices, the dialout group, no private users: see the unit) and the
/// slicers' setpriority.
#[test]
fn the_units_exposure_is_at_most_0_7() {
    let unit = config_file("crispen.service");
    let score = exposure(&unit);
    assert!(
        score <= 0.7,
        "systemd-analyze security: exposure {score}, more than 0.7"
    );
    // The score moves with what the unit says: without its system call filter it is worse.
    let unfiltered: String = unit
        .lines()
        .filter(|l| !l.starts_with("SystemCallFilter="))
        .map(|l| format!("{l}\n"))
        .collect();
    assert!(exposure(&unfiltered) > score);
}
