//! A real PostgreSQL server for one test: `initdb` into a temporary directory, then the
//! `postgres` server on a unix socket in that directory (no TCP), stopped and removed when
//! the value is dropped. The server comes from Debian's `postgresql` package
//! (`scripts/setup` installs it).
//!
//! `initdb` and `postgres` refuse to run as root, so under root (CI, containers) both run
//! as the `postgres` system user the package creates, and the directory is handed to it.

use std::os::unix::fs::PermissionsExt;
use std::os::unix::process::CommandExt;
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};

pub struct PgServer {
    dir: tempfile::TempDir,
    server: Option<Child>,
}

/// The directory holding `initdb`, `postgres` and `pg_ctl`: Debian keeps them out of PATH,
/// under `/usr/lib/postgresql/<major>/bin`; the newest major wins.
fn bin_dir() -> PathBuf {
    let mut found: Vec<(u32, PathBuf)> = std::fs::read_dir("/usr/lib/postgresql")
        .expect("PostgreSQL is not installed (run scripts/setup: it installs Debian's postgresql)")
        .filter_map(|e| e.ok())
        .filter_map(|e| {
            let major = e.file_name().to_str()?.parse().ok()?;
            let bin = e.path().join("bin");
            bin.join("postgres").exists().then_some((major, bin))
        })
        .collect();
    found.sort();
    found
        .pop()
        .expect("no /usr/lib/postgresql/<major>/bin/postgres (run scripts/setup)")
        .1
}

/// The uid and gid to run the server as: ours, or the `postgres` user's when we are root.
fn server_user() -> Option<(u32, u32)> {
    if !nix::unistd::geteuid().is_root() {
        return None;
    }
    let user = nix::unistd::User::from_name("postgres")
        .expect("reading the user database")
        .expect("running as root needs the `postgres` user (Debian's postgresql package makes it)");
    Some((user.uid.as_raw(), user.gid.as_raw()))
}

/// One of the server's programs, to run as `user`.
fn server_command(program: &str, user: Option<(u32, u32)>) -> Command {
    let mut command = Command::new(bin_dir().join(program));
    if let Some((uid, gid)) = user {
        command.uid(uid).gid(gid);
    }
    command
}

/// Runs `postgres` on the cluster in `dir/data`, its socket in `dir`, its output appended to
/// `dir/server.log`.
fn spawn_server(dir: &Path, user: Option<(u32, u32)>) -> Child {
    let log_path = dir.join("server.log");
    let log = std::fs::OpenOptions::new()
        .create(true)
        .append(true)
        .open(&log_path)
        .unwrap();
    server_command("postgres", user)
        .arg("-D")
        .arg(dir.join("data"))
        .arg("-k")
        .arg(dir)
        // Unix socket only; fsync off because the cluster is thrown away.
        .args(["-c", "listen_addresses=", "-c", "fsync=off"])
        .args(["-c", "max_connections=200"])
        // The setting under which hand-made SQL literals go wrong: crispen's must not.
        .args(["-c", "standard_conforming_strings=off"])
        .stdin(Stdio::null())
        .stdout(log.try_clone().unwrap())
        .stderr(log)
        .spawn()
        .expect("starting postgres")
}

impl PgServer {
    /// Creates a cluster with the superuser `crispen` and a database `crispen`, and starts it.
    pub fn start() -> PgServer {
        let user = server_user();
        let dir = tempfile::Builder::new()
            .prefix("crispen-pg.")
            .tempdir()
            .unwrap();
        // The server user must be able to reach and own its directory.
        std::fs::set_permissions(dir.path(), std::fs::Permissions::from_mode(0o755)).unwrap();
        if let Some((uid, gid)) = user {
            std::os::unix::fs::chown(dir.path(), Some(uid), Some(gid)).unwrap();
        }
        let data = dir.path().join("data");
        let out = server_command("initdb", user)
            .args([
                "--auth=trust",
                "--username=crispen",
                "--encoding=UTF8",
                "--no-sync",
            ])
            .arg("-D")
            .arg(&data)
            .env("LC_ALL", "C")
            .output()
            .expect("running initdb");
        assert!(
            out.status.success(),
            "initdb failed: {}",
            String::from_utf8_lossy(&out.stderr)
        );
        let server = spawn_server(dir.path(), user);
        let mut pg = PgServer {
            dir,
            server: Some(server),
        };
        pg.wait_ready(user);
        pg
    }

    fn wait_ready(&mut self, user: Option<(u32, u32)>) {
        let deadline = Instant::now() + Duration::from_secs(120);
        loop {
            if let Some(status) = self.server.as_mut().unwrap().try_wait().unwrap() {
                panic!("postgres exited ({status}) at start: {}", self.log());
            }
            let created = server_command("createdb", user)
                .args(["-h"])
                .arg(self.dir.path())
                .args(["-U", "crispen", "crispen"])
                .output()
                .unwrap();
            if created.status.success() {
                return;
            }
            assert!(
                Instant::now() < deadline,
                "postgres did not accept connections in 120 s: {}\n{}",
                String::from_utf8_lossy(&created.stderr),
                self.log()
            );
            std::thread::sleep(Duration::from_millis(200));
        }
    }

    /// The socket directory, the `host=` of a connection string.
    pub fn socket_dir(&self) -> &Path {
        self.dir.path()
    }

    /// A libpq connection string for the `crispen` database.
    pub fn conninfo(&self) -> String {
        format!(
            "host={} user=crispen dbname=crispen",
            self.socket_dir().display()
        )
    }

    /// The postmaster's process id (the server's CPU is its and its children's).
    pub fn pid(&self) -> u32 {
        self.server.as_ref().expect("the server is running").id()
    }

    pub fn log(&self) -> String {
        std::fs::read_to_string(self.dir.path().join("server.log")).unwrap_or_default()
    }

    /// Stops the server (fast shutdown: running transactions are rolled back), as an
    /// outage would; [`PgServer::restart`] brings it back on the same socket and data.
    pub fn stop(&mut self) {
        if let Some(mut child) = self.server.take() {
            let _ = nix::sys::signal::kill(
                nix::unistd::Pid::from_raw(child.id() as i32),
                nix::sys::signal::Signal::SIGINT,
            );
            let _ = child.wait();
        }
    }

    pub fn restart(&mut self) {
        assert!(self.server.is_none(), "restart of a running server");
        let server = spawn_server(self.dir.path(), server_user());
        self.server = Some(server);
        let deadline = Instant::now() + Duration::from_secs(120);
        while !self.dir.path().join(".s.PGSQL.5432").exists() {
            assert!(
                Instant::now() < deadline,
                "postgres did not come back: {}",
                self.log()
            );
            std::thread::sleep(Duration::from_millis(100));
        }
    }
}

impl Drop for PgServer {
    fn drop(&mut self) {
        self.stop();
    }
}
