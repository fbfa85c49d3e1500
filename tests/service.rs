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
