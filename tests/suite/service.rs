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
    assert!(unit.lines().any(|l| l == "IPAddressDeny=any"));
    let drop_in = config_file("crispen-http.conf");
    for line in [
        "PrivateNetwork=no",
        "RestrictAddressFamilies=AF_UNIX AF_INET AF_INET6",
        // The unit denies every IP address; the drop-in lifts that.
        "IPAddressDeny=",
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

// libseccomp, which systemd itself uses (Debian's systemd depends on libseccomp2; only the
// runtime library is installed, hence the verbatim name).
#[link(name = "libseccomp.so.2", kind = "dylib", modifiers = "+verbatim")]
unsafe extern "C" {
    fn seccomp_init(default_action: u32) -> *mut std::ffi::c_void;
    fn seccomp_syscall_resolve_name(name: *const std::ffi::c_char) -> i32;
    fn seccomp_rule_add(
        ctx: *mut std::ffi::c_void,
        action: u32,
        syscall: i32,
        arg_count: u32,
        ...
    ) -> i32;
    fn seccomp_export_bpf(ctx: *const std::ffi::c_void, fd: i32) -> i32;
    fn seccomp_release(ctx: *mut std::ffi::c_void);
    fn prctl(option: i32, ...) -> i32;
}

/// The system calls the unit's `SystemCallFilter=` lines allow, in systemd's own terms:
/// the groups as `systemd-analyze syscall-filter` lists them, each line applied in order
/// (the first allows, `~` takes away, later plain lines add back).
fn allowed_by_the_unit(unit: &str) -> std::collections::BTreeSet<String> {
    let out = Command::new("systemd-analyze")
        .arg("syscall-filter")
        .output()
        .expect("systemd-analyze");
    let text = String::from_utf8_lossy(&out.stdout);
    let mut groups: std::collections::BTreeMap<String, Vec<String>> = Default::default();
    let mut current = None;
    for line in text.lines() {
        if line.starts_with('@') {
            let name = line.split_whitespace().next().unwrap().to_string();
            groups.insert(name.clone(), Vec::new());
            current = Some(name);
        } else if let (Some(g), t) = (&current, line.trim()) {
            if !t.is_empty() && !t.starts_with('#') {
                groups.get_mut(g).unwrap().push(t.to_string());
            }
        }
    }
    fn expand(groups: &std::collections::BTreeMap<String, Vec<String>>, item: &str) -> Vec<String> {
        match groups.get(item) {
            Some(members) => members.iter().flat_map(|m| expand(groups, m)).collect(),
            None => vec![item.to_string()],
        }
    }
    let mut allowed = std::collections::BTreeSet::new();
    for line in unit.lines() {
        let Some(value) = line.strip_prefix("SystemCallFilter=") else {
            continue;
        };
        let (remove, items) = match value.strip_prefix('~') {
            Some(rest) => (true, rest),
            None => (false, value),
        };
        for item in items.split_whitespace() {
            for call in expand(&groups, item) {
                if remove {
                    allowed.remove(&call);
                } else {
                    allowed.insert(call);
                }
            }
        }
    }
    assert!(allowed.contains("read"), "no filter read from the unit");
    allowed
}

/// The unit's filter as a seccomp program (a refused call fails with EPERM, as
/// `SystemCallErrorNumber=EPERM` says), built by libseccomp.
fn seccomp_program(allowed: &std::collections::BTreeSet<String>) -> Vec<u8> {
    const ERRNO_EPERM: u32 = 0x0005_0000 | 1;
    const ALLOW: u32 = 0x7fff_0000;
    let file = tempfile::tempfile().unwrap();
    unsafe {
        let ctx = seccomp_init(ERRNO_EPERM);
        assert!(!ctx.is_null());
        for call in allowed {
            let name = std::ffi::CString::new(call.as_str()).unwrap();
            let nr = seccomp_syscall_resolve_name(name.as_ptr());
            // Calls of other architectures or newer kernels have no number here.
            if nr >= 0 {
                assert_eq!(seccomp_rule_add(ctx, ALLOW, nr, 0), 0, "{call}");
            }
        }
        use std::os::fd::AsRawFd;
        assert_eq!(seccomp_export_bpf(ctx, file.as_raw_fd()), 0);
        seccomp_release(ctx);
    }
    let mut file = file;
    use std::io::{Read, Seek};
    file.rewind().unwrap();
    let mut program = Vec::new();
    file.read_to_end(&mut program).unwrap();
    assert!(!program.is_empty() && program.len() % 8 == 0);
    program
}

/// The daemon and both slicers run under the unit's system call filter: a daemon with an
/// HTTP listener and two simulated printers, one hot folder sliced by PrusaSlicer and one
/// by CuraEngine, runs until both models are printed, with the filter the unit declares
/// applied as systemd would (no new privileges, then the seccomp program, inherited by
/// every child). `systemd-analyze` cannot run the unit here (systemd is not PID 1), so
/// this is the check that the filter leaves out nothing they need.
#[test]
fn the_daemon_and_both_slicers_run_under_the_units_system_call_filter() {
    use std::os::unix::process::CommandExt;
    let program = seccomp_program(&allowed_by_the_unit(&config_file("crispen.service")));
    let dir = tempfile::tempdir().unwrap();
    let root = dir.path();
    let spot = std::fs::read(format!(
        "{}/tests/data/spot.obj",
        env!("CARGO_MANIFEST_DIR")
    ))
    .unwrap();
    for folder in ["prusa", "cura"] {
        std::fs::create_dir(root.join(folder)).unwrap();
        std::fs::write(root.join(folder).join("spot.obj"), &spot).unwrap();
    }
    std::fs::write(root.join("key"), "k-0123456789abcdef-k\n").unwrap();
    std::fs::write(
        root.join("crispen.toml"),
        "[spool]\ndir = \"spool\"\n[control]\nsocket = \"c.sock\"\n[farm]\nsettle_s = 0.3\n\
         [http]\nlisten = \"127.0.0.1:0\"\napi_key_file = \"key\"\n\
         [[printer]]\nname = \"p\"\nfirmware = \"marlin2\"\n[printer.simulate]\ntime_scale = 0.0\n\
         [[printer]]\nname = \"u\"\nmachine = \"ultimaker2\"\n[printer.simulate]\ntime_scale = 0.0\n\
         [[folder]]\npath = \"prusa\"\nheight_mm = 20\nprinters = [\"p\"]\n\
         [[folder]]\npath = \"cura\"\nheight_mm = 20\nslicer = \"cura\"\nprinters = [\"u\"]\n",
    )
    .unwrap();
    let mut command = Command::new(env!("CARGO_BIN_EXE_crispen"));
    command
        .args(["run", "--exit-when-idle", "--config"])
        .arg(root.join("crispen.toml"))
        .env("RUST_LOG", "info")
        .stdin(std::process::Stdio::null());
    // SAFETY: between fork and exec only two prctl calls, on memory made before the fork.
    unsafe {
        command.pre_exec(move || {
            #[repr(C)]
            struct SockFprog {
                len: u16,
                filter: *const u8,
            }
            const PR_SET_NO_NEW_PRIVS: i32 = 38;
            const PR_SET_SECCOMP: i32 = 22;
            const SECCOMP_MODE_FILTER: u64 = 2;
            let fprog = SockFprog {
                len: (program.len() / 8) as u16,
                filter: program.as_ptr(),
            };
            if prctl(PR_SET_NO_NEW_PRIVS, 1u64, 0u64, 0u64, 0u64) != 0
                || prctl(
                    PR_SET_SECCOMP,
                    SECCOMP_MODE_FILTER,
                    &fprog as *const SockFprog,
                ) != 0
            {
                return Err(std::io::Error::last_os_error());
            }
            Ok(())
        });
    }
    let mut child = command
        .stdout(std::process::Stdio::null())
        .stderr(std::process::Stdio::piped())
        .spawn()
        .unwrap();
    let mut log = String::new();
    let stderr = child.stderr.take().unwrap();
    let reader = std::thread::spawn(move || {
        use std::io::Read;
        let mut stderr = stderr;
        let _ = stderr.read_to_string(&mut log);
        log
    });
    let started = std::time::Instant::now();
    let status = loop {
        if let Some(status) = child.try_wait().unwrap() {
            break status;
        }
        if started.elapsed() > std::time::Duration::from_secs(600) {
            let _ = child.kill();
            let _ = child.wait();
            panic!(
                "the daemon did not finish in 600 s: {}",
                reader.join().unwrap()
            );
        }
        std::thread::sleep(std::time::Duration::from_millis(100));
    };
    let log = reader.join().unwrap();
    assert!(status.success(), "{status}: {log}");
    let done = log.lines().filter(|l| l.contains("state=\"done\"")).count();
    assert_eq!(done, 2, "both jobs printed under the filter: {log}");
}
