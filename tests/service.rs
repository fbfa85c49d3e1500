//! The systemd unit in `config/` is checked by systemd itself (`systemd-analyze verify`),
//! with its ExecStart pointed at the binary under test: a typo in a sandboxing option
//! would otherwise only show on a print-farm host.

use std::process::Command;

#[test]
fn systemd_unit_verifies() {
    let unit = std::fs::read_to_string(concat!(
        env!("CARGO_MANIFEST_DIR"),
        "/config/crispen.service"
    ))
    .unwrap();
    assert!(unit.contains("ExecStart=/usr/bin/crispen run"));
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("crispen.service");
    std::fs::write(
        &path,
        unit.replace("/usr/bin/crispen", env!("CARGO_BIN_EXE_crispen")),
    )
    .unwrap();
    let out = Command::new("systemd-analyze")
        .arg("verify")
        .arg(&path)
        .output()
        .expect("systemd-analyze (Debian package systemd; scripts/setup installs it)");
    let stderr = String::from_utf8_lossy(&out.stderr);
    // verify prints problems with this unit prefixed by its file or unit name.
    let problems: Vec<&str> = stderr
        .lines()
        .filter(|l| l.contains("crispen.service"))
        .collect();
    assert!(out.status.success() && problems.is_empty(), "{}", stderr);
}

/// The TCP listener of `[http]` is allowed only where it is configured: the unit itself
/// keeps the daemon off the network, and the drop-in `config/crispen-http.conf` opens
/// exactly the HTTP port; systemd accepts the unit with the drop-in.
#[test]
fn tcp_only_with_the_http_drop_in() {
    let root = env!("CARGO_MANIFEST_DIR");
    let unit = std::fs::read_to_string(format!("{root}/config/crispen.service")).unwrap();
    assert!(unit.lines().any(|l| l == "PrivateNetwork=yes"));
    assert!(unit.lines().any(|l| l == "RestrictAddressFamilies=AF_UNIX"));
    let drop_in = std::fs::read_to_string(format!("{root}/config/crispen-http.conf")).unwrap();
    for line in [
        "PrivateNetwork=no",
        "RestrictAddressFamilies=AF_UNIX AF_INET AF_INET6",
        "SocketBindDeny=any",
    ] {
        assert!(drop_in.lines().any(|l| l == line), "drop-in lacks {line}");
    }
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("crispen.service");
    std::fs::write(
        &path,
        unit.replace("/usr/bin/crispen", env!("CARGO_BIN_EXE_crispen")),
    )
    .unwrap();
    std::fs::create_dir(dir.path().join("crispen.service.d")).unwrap();
    std::fs::write(dir.path().join("crispen.service.d/http.conf"), &drop_in).unwrap();
    let out = Command::new("systemd-analyze")
        .arg("verify")
        .arg(&path)
        .output()
        .expect("systemd-analyze");
    let stderr = String::from_utf8_lossy(&out.stderr);
    let problems: Vec<&str> = stderr
        .lines()
        .filter(|l| l.contains("crispen.service") || l.contains("http.conf"))
        .collect();
    assert!(out.status.success() && problems.is_empty(), "{}", stderr);
}
