//! The daemon's configuration: a TOML file read in stages. First the text is parsed into
//! `Raw*` structs that mirror the file (unknown keys rejected); then every value is checked
//! and converted into the types the daemon uses ([`Checked`]), with nothing read but the
//! file; last, [`Checked::resolve`] reads and checks what the values name on this machine
//! (the API key and database password files, the printers' devices) into a [`Config`].
//! The daemon takes all of them; a command takes only what it needs (`crispen status`
//! the socket, from the first stage; `crispen ports` and `crispen slice` the checked
//! printers and machines), so an operator need not be able to read the daemon's secrets.
//! Every error names the file, the section and the key, so an operator can fix the file
//! without reading code; a wrong file is always an error, never silently replaced by
//! defaults.

// Read by tests only: they check the reload policy and `KNOWN_TABLES` against it.
#[cfg(test)]
pub(crate) mod keys;
pub mod notify;
pub mod octoprint;
mod pause;
pub mod ports;

use crate::enhance::Strength;
use crate::marlin::firmware::Firmware;
use crate::mesh::place::UpAxis;
use crate::slice::SlicerKind;
use serde::{Deserialize, Serialize};
use std::collections::BTreeSet;
use std::io::Read;
use std::path::{Path, PathBuf};
use std::time::Duration;

/// A configuration problem, located as precisely as the file allows.
#[derive(Debug, thiserror::Error)]
pub enum ConfigError {
    #[error("{file}: cannot read: {source} (hint: pass --config FILE with a readable file)")]
    Read {
        file: PathBuf,
        #[source]
        source: std::io::Error,
    },
    #[error("{file}: line {line}, in {section}: {message}")]
    Parse {
        file: PathBuf,
        line: usize,
        section: String,
        message: String,
    },
    #[error("{file}: {section}: key `{key}`: {message}")]
    Invalid {
        file: PathBuf,
        section: String,
        key: String,
        message: String,
    },
}

/// What SIGTERM does to a print in progress.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum OnShutdown {
    /// Keep streaming until the print ends, then exit.
    Finish,
    /// Stop safely (heaters off) and mark the job interrupted.
    Stop,
}

// ---------------------------------------------------------------- stage 1: the file's shape

#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
struct RawConfig {
    spool: RawSpool,
    #[serde(default)]
    control: Option<RawControl>,
    #[serde(default)]
    farm: Option<RawFarm>,
    #[serde(default, rename = "machine")]
    machines: Vec<crate::machine::MachineSpec>,
    #[serde(default, rename = "printer")]
    printers: Vec<RawPrinter>,
    #[serde(default, rename = "folder")]
    folders: Vec<RawFolder>,
    #[serde(default)]
    http: Option<RawHttp>,
    #[serde(default)]
    store: Option<RawStore>,
    #[serde(default)]
    history: Option<RawHistory>,
    #[serde(default, rename = "notify")]
    notify: Vec<notify::RawNotify>,
}

#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
struct RawHistory {
    live_days: Option<f64>,
    live_jobs: Option<i64>,
    keep_days: Option<f64>,
}

#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
struct RawStore {
    postgres: String,
    password_file: Option<PathBuf>,
    lease_s: Option<f64>,
}

#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
struct RawHttp {
    listen: String,
    api_key_file: PathBuf,
    read_only_without_key: Option<bool>,
    upload_max_mb: Option<i64>,
    /// The dashboard's address as operators reach it (notifications link to it).
    public_url: Option<String>,
    announce: Option<bool>,
    default_folder: Option<String>,
}

#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
struct RawSpool {
    dir: PathBuf,
}

#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
struct RawControl {
    socket: PathBuf,
}

#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
struct RawFarm {
    max_heating: Option<i64>,
    on_shutdown: Option<OnShutdown>,
    settle_s: Option<f64>,
    rescan_s: Option<f64>,
    finish_timeout_s: Option<f64>,
    host: Option<String>,
}

#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
struct RawPrinter {
    name: String,
    port: Option<PathBuf>,
    firmware: Option<String>,
    /// A machine's name (built-in or `[[machine]]`); the firmware then comes from it.
    machine: Option<String>,
    /// The nozzle fitted, for machines that take several (e.g. the Ultimaker 2+).
    nozzle_mm: Option<f64>,
    baud: Option<i64>,
    heat_timeout_s: Option<i64>,
    /// See `pause.rs`.
    pause_heaters_off_s: Option<i64>,
    simulate: Option<RawSimulate>,
}

#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
struct RawSimulate {
    /// A number (how many times faster than real time) or "instant".
    speed: Option<toml::Value>,
    /// Replaced by `speed`, its inverse; still read, with a warning.
    time_scale: Option<f64>,
    seed: Option<u64>,
    record: Option<PathBuf>,
}

#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
struct RawFolder {
    path: PathBuf,
    height_mm: f64,
    printers: Vec<String>,
    strength: Option<toml::Value>,
    enhance: Option<bool>,
    slicer: Option<SlicerKind>,
    up: Option<UpAxis>,
    profile: Option<PathBuf>,
    timeout_s: Option<f64>,
    settings: Option<toml::Table>,
}

// ---------------------------------------------------------------- stage 2: checked values

/// The checked configuration the daemon runs with.
#[derive(Debug, Clone)]
pub struct Config {
    /// The file it came from ("(built-in default)" when none).
    pub source: PathBuf,
    pub spool_dir: PathBuf,
    pub socket: PathBuf,
    pub farm: FarmConfig,
    pub printers: Vec<PrinterConfig>,
    /// The `[[machine]]` tables, checked (the built-in machines are not listed).
    pub machines: Vec<crate::machine::Machine>,
    pub folders: Vec<FolderConfig>,
    /// The HTTP API and dashboard on TCP (`[http]`), when configured.
    pub http: Option<HttpConfig>,
    /// The farm's queue in PostgreSQL (`[store]`), shared with other hosts; None: this
    /// host's own spool.
    pub store: Option<StoreConfig>,
    /// How long finished jobs stay live before they move to the history (`[history]`).
    pub history: HistoryConfig,
    /// Where the farm's events are sent (`[[notify]]`, see `notify`).
    pub notify: notify::NotifyConfig,
    /// What is accepted but unwise (a key file others can read), each naming its section
    /// and key: shown by `crispen run --check` and logged at every start and reload.
    pub warnings: Vec<String>,
}

/// `[history]`: a finished job (done, failed, cancelled) stays in the live queue (status,
/// dashboard, metrics) for `live_days` after it ended, and only the newest `live_jobs`
/// of them; older ones move to the history, which keeps them (see `store`).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct HistoryConfig {
    pub live_for: Duration,
    pub live_jobs: usize,
    /// How long the history keeps a job (`keep_days`); None: for good.
    pub keep_for: Option<Duration>,
}

impl Default for HistoryConfig {
    fn default() -> HistoryConfig {
        HistoryConfig {
            live_for: Duration::from_secs(7 * 86_400),
            live_jobs: 200,
            keep_for: None,
        }
    }
}

/// Bounds of `[history] live_days` (0: a finished job leaves the queue at once).
pub const LIVE_DAYS: Bounds = 0.0..=3650.0;
/// Bounds of `[history] keep_days`: at least a day; absent, the history keeps everything.
pub const KEEP_DAYS: Bounds = 1.0..=36_500.0;
/// Bounds of `[history] live_jobs`: the live queue stays small whatever the history holds.
pub const LIVE_JOBS: std::ops::RangeInclusive<i64> = 0..=10_000;

fn check_history(h: RawHistory) -> Result<HistoryConfig, (&'static str, String)> {
    let days = h.live_days.unwrap_or(7.0);
    if !LIVE_DAYS.contains(&days) {
        let (lo, hi) = (LIVE_DAYS.start(), LIVE_DAYS.end());
        return Err((
            "live_days",
            format!("must be between {lo} and {hi} days, got {days}"),
        ));
    }
    let jobs = h.live_jobs.unwrap_or(200);
    if !LIVE_JOBS.contains(&jobs) {
        let (lo, hi) = (LIVE_JOBS.start(), LIVE_JOBS.end());
        return Err((
            "live_jobs",
            format!("must be between {lo} and {hi}, got {jobs}"),
        ));
    }
    let keep_for = match h.keep_days {
        None => None,
        Some(keep) if KEEP_DAYS.contains(&keep) => Some(Duration::from_secs_f64(keep * 86_400.0)),
        Some(keep) => {
            let (lo, hi) = (KEEP_DAYS.start(), KEEP_DAYS.end());
            return Err((
                "keep_days",
                format!("must be between {lo} and {hi} days (leave it out to keep for good), got {keep}"),
            ));
        }
    };
    Ok(HistoryConfig {
        live_for: Duration::from_secs_f64(days * 86_400.0),
        live_jobs: jobs as usize,
        keep_for,
    })
}

/// `[store]`: the farm database.
#[derive(Debug, Clone, PartialEq)]
pub struct StoreConfig {
    pub postgres: PgSettings,
    /// A host silent this long loses its work to the others (see `store::postgres`).
    pub lease: Duration,
}

/// How to reach the farm database: `[store] postgres` and `[store] password_file`.
#[derive(Debug, Clone, PartialEq)]
pub struct PgSettings {
    /// A libpq connection string without a password (`host=/run/postgresql dbname=crispen`).
    pub conninfo: String,
    pub password_file: Option<PathBuf>,
}

/// Why a `[store] postgres` connection string is refused.
#[derive(Debug, Clone, PartialEq)]
pub enum ConninfoError {
    /// It holds a password, which belongs in `password_file` or `PGPASSWORD`.
    Password,
    /// It is too long, does not parse or names no server; the reason.
    Bad(String),
}

/// A `[store] postgres` connection string checked and parsed, the one rule for both the
/// config check and the store's connection: at most 4096 characters, it parses, names the
/// server (there is no default to fall back on), and holds no password.
pub fn parse_conninfo(conninfo: &str) -> Result<tokio_postgres::Config, ConninfoError> {
    if conninfo.len() > 4096 {
        return Err(ConninfoError::Bad(format!(
            "{} characters: too long for a connection string",
            conninfo.len()
        )));
    }
    let config: tokio_postgres::Config = conninfo.parse().map_err(|e: tokio_postgres::Error| {
        // The parser's reason (e.g. the unknown option) is the error's source.
        let reason = std::error::Error::source(&e).map(|s| format!(": {s}"));
        ConninfoError::Bad(format!("{e}{}", reason.unwrap_or_default()))
    })?;
    if config.get_hosts().is_empty() && config.get_hostaddrs().is_empty() {
        return Err(ConninfoError::Bad(format!(
            "{conninfo:?} names no server (hint: \"host=/run/postgresql dbname=crispen\", or host=NAME for one on another machine)"
        )));
    }
    if config.get_password().is_some() {
        return Err(ConninfoError::Password);
    }
    Ok(config)
}

/// Bounds of `[store] lease_s`: long enough for a busy host's heartbeat, short enough that
/// a dead host's printers are seen offline the same minute.
pub const LEASE_S: Bounds = 3.0..=600.0;

/// `[http]`: the TCP listener of the HTTP API and dashboard (see `crate::http`).
#[derive(Debug, Clone)]
pub struct HttpConfig {
    pub listen: std::net::SocketAddr,
    /// The key every request must carry in `X-Api-Key`, read from `api_key_file`.
    pub api_key: ApiKey,
    /// GET requests (dashboard, status, pictures, metrics) are answered without the key.
    pub read_only_without_key: bool,
    /// The largest upload accepted, in bytes.
    pub upload_max_bytes: u64,
    /// Listen on a port the system picks when `listen`'s port is taken: only for the
    /// built-in default, never for a configured port.
    pub any_port_if_taken: bool,
    /// The OctoPrint emulation's keys (`announce`, `default_folder`).
    pub octoprint: octoprint::OctoPrintConfig,
}

/// An API key; never shown in logs or debug output.
#[derive(Clone, PartialEq, Eq)]
pub struct ApiKey(pub String);

impl std::fmt::Debug for ApiKey {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str("ApiKey(..)")
    }
}

/// Shortest API key accepted: a guessable key on a network port is no key.
pub const MIN_API_KEY_CHARS: usize = 16;
/// Bounds of `[http] upload_max_mb`.
pub const UPLOAD_MAX_MB: std::ops::RangeInclusive<i64> = 1..=4096;

#[derive(Debug, Clone)]
pub struct FarmConfig {
    /// At most this many printers heat up at once.
    pub max_heating: usize,
    pub on_shutdown: OnShutdown,
    /// A dropped file whose size and mtime stay unchanged this long is taken as complete.
    pub settle: Duration,
    /// Hot folders are rescanned this often in case a watch event was missed.
    pub rescan: Duration,
    /// With `on_shutdown = "finish"`, prints still running this long after the stop began
    /// are stopped safely (the daemon asks systemd for time up to then, no longer).
    pub finish_timeout: Duration,
    /// This host's name in a farm shared through `[store]` (default: the hostname).
    pub host: String,
}

/// Where a printer is reached: a real serial port, or a simulated printer the daemon
/// starts once at startup (and then treats exactly like a serial port).
#[derive(Debug, Clone, PartialEq)]
pub enum PrinterPort {
    Serial(PathBuf),
    Simulated {
        time_scale: f64,
        seed: u64,
        record: Option<PathBuf>,
    },
}

#[derive(Debug, Clone, PartialEq)]
pub struct PrinterConfig {
    pub name: String,
    pub port: PrinterPort,
    pub firmware: Firmware,
    /// What its G-code is made for (see `crate::machine`).
    pub machine: crate::machine::Machine,
    pub baud: u32,
    /// An M109/M190 whose temperature stops coming closer to its target for this long
    /// fails the job (heaters off).
    pub heat_timeout: Duration,
    /// A pause the file asked for that nobody resumes this long turns the heaters off.
    pub pause_heaters_off: Duration,
}

#[derive(Debug, Clone)]
pub struct FolderConfig {
    pub path: PathBuf,
    pub height_mm: f64,
    pub printers: Vec<String>,
    pub strength: Strength,
    pub slicer: SlicerKind,
    /// Which of the dropped files' axes points up (STL: z; many OBJ files: y).
    pub up: UpAxis,
    pub profile: Option<PathBuf>,
    pub timeout: Duration,
    /// Slicer setting overrides on top of the profile.
    pub settings: crate::slice::SliceSettings,
}

/// The second stage: every value of the file checked and converted, with nothing read but
/// the file itself (no key or password file, no device). It is all that the commands which
/// only read the machines or the printers need, and an operator in the daemon's group may
/// not read its secrets; the daemon goes on to [`Checked::resolve`].
#[derive(Debug, Clone)]
pub struct Checked {
    /// Everything but `[http]`, whose key is read in the third stage.
    config: Config,
    http: Option<CheckedHttp>,
}

/// `[http]` checked, its key file not yet read.
#[derive(Debug, Clone)]
struct CheckedHttp {
    listen: std::net::SocketAddr,
    api_key_file: PathBuf,
    read_only_without_key: bool,
    upload_max_bytes: u64,
    octoprint: octoprint::OctoPrintConfig,
}

impl Checked {
    /// Reads a config file (at most [`MAX_CONFIG_BYTES`]) and checks it.
    pub fn load(path: &Path) -> Result<Checked, ConfigError> {
        Checked::parse(&read_text(path)?, path)
    }

    /// Parses and checks config text; `path` names it in errors and anchors relative paths
    /// (they are relative to the file's directory).
    pub fn parse(text: &str, path: &Path) -> Result<Checked, ConfigError> {
        let (raw, base) = Config::parse_raw(text, path)?;
        Config::check(raw, path, &base)
    }

    /// The file the config came from.
    pub fn source(&self) -> &Path {
        &self.config.source
    }

    /// The control socket.
    pub fn socket(&self) -> &Path {
        &self.config.socket
    }

    /// The `[[printer]]` tables, checked.
    pub fn printers(&self) -> &[PrinterConfig] {
        &self.config.printers
    }

    /// The `[[machine]]` tables, checked (the built-in machines are not listed).
    pub fn machines(&self) -> &[crate::machine::Machine] {
        &self.config.machines
    }

    /// The third stage: what the checked values name on this machine, read and checked:
    /// the API key file (its key is what `[http]` runs with), the database password file
    /// (as the store will read it), and the printers' devices (two printers on one device
    /// are refused). Warnings (a secret others can read) are added to the config's.
    pub fn resolve(self) -> Result<Config, ConfigError> {
        let Checked { mut config, http } = self;
        let file = config.source.clone();
        let invalid = |section: &str, key: &str, message: String| ConfigError::Invalid {
            file: file.clone(),
            section: section.into(),
            key: key.into(),
            message,
        };
        if let Some(path) = config
            .store
            .as_ref()
            .and_then(|s| s.postgres.password_file.as_ref())
        {
            let (_, warning) =
                read_secret(path).map_err(|m| invalid("[store]", "password_file", m))?;
            if let Some(w) = warning {
                config
                    .warnings
                    .push(format!("[store] key `password_file`: {w}"));
            }
        }
        ports::check_unique(&config.printers, &file)?;
        notify::resolve(&mut config.notify, &file, &mut config.warnings)?;
        if let Some(h) = &http {
            octoprint::check_folder(&h.octoprint, &config.folders)
                .map_err(|(key, m)| invalid("[http]", key, m))?;
        }
        config.http = match http {
            None => None,
            Some(h) => {
                let (api_key, warning) = read_api_key_warning(&h.api_key_file)
                    .map_err(|m| invalid("[http]", "api_key_file", m))?;
                if let Some(w) = warning {
                    config
                        .warnings
                        .push(format!("[http] key `api_key_file`: {w}"));
                }
                Some(HttpConfig {
                    listen: h.listen,
                    api_key,
                    read_only_without_key: h.read_only_without_key,
                    upload_max_bytes: h.upload_max_bytes,
                    any_port_if_taken: false,
                    octoprint: h.octoprint,
                })
            }
        };
        Ok(config)
    }
}

/// The text of a config file, refused beyond [`MAX_CONFIG_BYTES`] (a config is a page,
/// not a stream) or when it is not UTF-8.
fn read_text(path: &Path) -> Result<String, ConfigError> {
    let read = |source| ConfigError::Read {
        file: path.to_path_buf(),
        source,
    };
    let mut bytes = Vec::new();
    std::fs::File::open(path)
        .and_then(|f| f.take(MAX_CONFIG_BYTES + 1).read_to_end(&mut bytes))
        .map_err(read)?;
    if bytes.len() as u64 > MAX_CONFIG_BYTES {
        return Err(read(std::io::Error::new(
            std::io::ErrorKind::InvalidData,
            format!(
                "larger than {} MiB: not a crispen config",
                MAX_CONFIG_BYTES >> 20
            ),
        )));
    }
    String::from_utf8(bytes).map_err(|_| {
        read(std::io::Error::new(
            std::io::ErrorKind::InvalidData,
            "not UTF-8 text",
        ))
    })
}

impl Config {
    /// Reads a config file and takes it through all three stages.
    pub fn load(path: &Path) -> Result<Config, ConfigError> {
        Checked::load(path)?.resolve()
    }

    /// Parses config text and takes it through all three stages.
    pub fn parse(text: &str, path: &Path) -> Result<Config, ConfigError> {
        Checked::parse(text, path)?.resolve()
    }

    /// The control socket a config file names, from the file's first stage alone: what
    /// the one-shot commands (`crispen status`, `clear`, ...) need to reach the daemon,
    /// without reading its secrets (its key and password files are the daemon's user's
    /// alone, and an operator in its group runs these commands), and without refusing a
    /// file the daemon's other settings were since edited wrongly in.
    pub fn socket_of(path: &Path) -> Result<PathBuf, ConfigError> {
        let text = read_text(path)?;
        let (raw, base) = Config::parse_raw(&text, path)?;
        let (_, socket) = spool_and_socket(&raw, path, &base)?;
        Ok(socket)
    }

    /// The first stage: the text as the file's shape, and the directory that anchors its
    /// relative paths.
    fn parse_raw(text: &str, path: &Path) -> Result<(RawConfig, PathBuf), ConfigError> {
        let raw: RawConfig = toml::from_str(text).map_err(|e| {
            let offset = e.span().map(|s| s.start).unwrap_or(0);
            let (line, mut section) = locate(text, offset);
            let mut message = e.message().trim().to_string();
            // serde speaks of fields; the file has keys.
            if let Some(key) = message.strip_prefix("missing field ") {
                message = format!("missing key {key}");
            }
            // An unknown table is reported where serde sees it, as a key of the document;
            // its header is on the error's line, so name it as what it is.
            if let Some(header) = unknown_table_header(text, offset) {
                section = "the top level".into();
                message = format!(
                    "unknown table `{header}` (known tables: {})",
                    KNOWN_TABLES.join(", ")
                );
            }
            ConfigError::Parse {
                file: path.to_path_buf(),
                line,
                section,
                message,
            }
        })?;
        // Every configured path is made absolute here, once: the watcher compares event
        // paths (absolute) with folder paths, and the daemon may change directory later.
        // `crispen.toml` has the parent "", which is the current directory.
        let dir = match path.parent() {
            Some(dir) if !dir.as_os_str().is_empty() => dir,
            _ => Path::new("."),
        };
        let base = std::path::absolute(dir).unwrap_or_else(|_| dir.to_path_buf());
        Ok((raw, base))
    }

    /// The configuration used when no file is given: everything under `./crispen-demo/`,
    /// one hot folder for 50 mm prints and one fast simulated Ultimaker 2, so the quick
    /// start needs no hardware.
    pub fn builtin_default() -> Config {
        let text = r#"
[spool]
dir = "crispen-demo/spool"
[control]
socket = "crispen-demo/crispen.sock"
[farm]
max_heating = 1
settle_s = 2
[[printer]]
name = "demo"
firmware = "ultimaker2"
[printer.simulate]
speed = 100
[[folder]]
path = "crispen-demo/hot/50mm"
height_mm = 50
printers = ["demo"]
"#;
        let mut config = Config::parse(text, Path::new("./(built-in default)"))
            .expect("the built-in default config is valid");
        config.source = PathBuf::from("(built-in default)");
        config
    }

    /// The folder configuration a hot-folder path belongs to.
    pub fn folder(&self, path: &Path) -> Option<&FolderConfig> {
        self.folders.iter().find(|f| f.path == path)
    }

    /// The second stage (see [`Checked`]).
    fn check(raw: RawConfig, file: &Path, base: &Path) -> Result<Checked, ConfigError> {
        let invalid = |section: String, key: &str, message: String| ConfigError::Invalid {
            file: file.to_path_buf(),
            section,
            key: key.to_string(),
            message,
        };
        let anchor = |p: &Path| {
            if p.is_absolute() {
                p.to_path_buf()
            } else {
                base.join(p)
            }
        };

        let (spool_dir, socket) = spool_and_socket(&raw, file, base)?;
        // What is accepted but should change (see `Config::warnings`).
        let mut warnings = Vec::new();

        let farm = {
            let raw_farm = raw.farm.unwrap_or(RawFarm {
                max_heating: None,
                on_shutdown: None,
                settle_s: None,
                rescan_s: None,
                finish_timeout_s: None,
                host: None,
            });
            let max_heating = match raw_farm.max_heating {
                None => 2,
                Some(n) if (1..=MAX_PRINTERS as i64).contains(&n) => n as usize,
                Some(n) => {
                    return Err(invalid(
                        "[farm]".into(),
                        "max_heating",
                        format!("must be between 1 and {MAX_PRINTERS}, got {n}"),
                    ))
                }
            };
            let seconds = |key: &str, value: Option<f64>, default: f64, range: &Bounds| {
                seconds_in(value.unwrap_or(default), range)
                    .map_err(|m| invalid("[farm]".into(), key, m))
            };
            FarmConfig {
                max_heating,
                on_shutdown: raw_farm.on_shutdown.unwrap_or(OnShutdown::Finish),
                settle: seconds("settle_s", raw_farm.settle_s, 5.0, &SETTLE_S)?,
                rescan: seconds("rescan_s", raw_farm.rescan_s, 30.0, &RESCAN_S)?,
                finish_timeout: seconds(
                    "finish_timeout_s",
                    raw_farm.finish_timeout_s,
                    DEFAULT_FINISH_TIMEOUT_S,
                    &FINISH_TIMEOUT_S,
                )?,
                host: match raw_farm.host {
                    None => this_hostname(),
                    Some(h) => {
                        check_host_name(&h).map_err(|m| invalid("[farm]".into(), "host", m))?
                    }
                },
            }
        };
        let store = match raw.store {
            None => None,
            Some(s) => {
                let invalid = |key, m| invalid("[store]".into(), key, m);
                parse_conninfo(&s.postgres).map_err(|e| {
                    invalid(
                        "postgres",
                        match e {
                            ConninfoError::Password => "the connection string holds a password (hint: put the password in [store] password_file or PGPASSWORD)".into(),
                            ConninfoError::Bad(m) => m,
                        },
                    )
                })?;
                if s.password_file
                    .as_ref()
                    .is_some_and(|p| p.as_os_str().is_empty())
                {
                    return Err(invalid("password_file", "must not be empty".into()));
                }
                Some(StoreConfig {
                    postgres: PgSettings {
                        conninfo: s.postgres,
                        password_file: s.password_file.map(|p| anchor(&p)),
                    },
                    lease: seconds_in(s.lease_s.unwrap_or(15.0), &LEASE_S)
                        .map_err(|m| invalid("lease_s", m))?,
                })
            }
        };

        let machines = check_machines(raw.machines, &invalid, &anchor)?;
        let find_machine = |name: &str| {
            machines
                .iter()
                .find(|m| m.name == name)
                .cloned()
                .or_else(|| crate::machine::Machine::builtin(name))
        };

        if raw.printers.len() > MAX_PRINTERS {
            return Err(invalid(
                "[[printer]]".into(),
                "name",
                format!(
                    "at most {MAX_PRINTERS} printers, got {}",
                    raw.printers.len()
                ),
            ));
        }
        let mut printers = Vec::new();
        let mut names = BTreeSet::new();
        for (i, p) in raw.printers.into_iter().enumerate() {
            let section = format!("[[printer]] #{} (name {:?})", i + 1, p.name);
            if p.name.is_empty()
                || !p
                    .name
                    .chars()
                    .all(|c| c.is_ascii_alphanumeric() || c == '-' || c == '_' || c == '.')
            {
                return Err(invalid(
                    section,
                    "name",
                    "must be non-empty and use only letters, digits, `-`, `_`, `.`".into(),
                ));
            }
            if !names.insert(p.name.clone()) {
                return Err(invalid(
                    section,
                    "name",
                    "is used by another printer".into(),
                ));
            }
            let stated: Option<Firmware> = p
                .firmware
                .as_deref()
                .map(str::parse)
                .transpose()
                .map_err(|m: String| invalid(section.clone(), "firmware", m))?;
            let mut machine = match (&p.machine, stated) {
                (Some(name), _) => find_machine(name).ok_or_else(|| {
                    invalid(
                        section.clone(),
                        "machine",
                        format!(
                            "no machine is named {name:?} (built-in: {}; or define it in a [[machine]] table)",
                            crate::machine::BUILTIN
                                .iter()
                                .map(|b| b.name)
                                .collect::<Vec<_>>()
                                .join(", ")
                        ),
                    )
                })?,
                (None, Some(firmware)) => crate::machine::Machine::default_for(firmware),
                (None, None) => {
                    return Err(invalid(
                        section,
                        "machine",
                        "missing (give `machine`, e.g. \"ultimaker2\", or at least `firmware`)"
                            .into(),
                    ))
                }
            };
            if let Some(f) = stated.filter(|f| *f != machine.firmware) {
                return Err(invalid(
                    section,
                    "firmware",
                    format!(
                        "is {f}, but machine {:?} runs {}; leave `firmware` out (it comes from the machine)",
                        machine.name, machine.firmware
                    ),
                ));
            }
            if let Some(nozzle) = p.nozzle_mm {
                machine = machine
                    .with_nozzle(nozzle)
                    .map_err(|m| invalid(section.clone(), "nozzle_mm", m))?;
                if machines.iter().any(|m| m.name == machine.name) {
                    return Err(invalid(
                        section,
                        "nozzle_mm",
                        format!(
                            "this nozzle makes a machine named {:?}, which a [[machine]] table already names",
                            machine.name
                        ),
                    ));
                }
            }
            let firmware = machine.firmware;
            let baud = match p.baud {
                None => firmware.default_baud(),
                Some(b) if (300..=4_000_000).contains(&b) => b as u32,
                Some(b) => {
                    return Err(invalid(
                        section,
                        "baud",
                        format!("must be between 300 and 4000000, got {b}"),
                    ))
                }
            };
            let heat_timeout = match p.heat_timeout_s {
                None => Duration::from_secs(1200),
                Some(s) if (10..=86_400).contains(&s) => Duration::from_secs(s as u64),
                Some(s) => {
                    return Err(invalid(
                        section,
                        "heat_timeout_s",
                        format!("must be between 10 and 86400 seconds, got {s}"),
                    ))
                }
            };
            let pause_heaters_off = pause::heaters_off_after(p.pause_heaters_off_s)
                .map_err(|m| invalid(section.clone(), "pause_heaters_off_s", m))?;
            let port = match (p.port, p.simulate) {
                (Some(_), Some(_)) => {
                    return Err(invalid(
                        section,
                        "simulate",
                        "give either `port` or a `[printer.simulate]` table, not both".into(),
                    ))
                }
                (None, None) => {
                    return Err(invalid(
                        section,
                        "port",
                        "missing (hint: a serial device such as /dev/ttyUSB0, or a \
                         [printer.simulate] table for a simulated printer)"
                            .into(),
                    ))
                }
                (Some(port), None) => PrinterPort::Serial(anchor(&port)),
                (None, Some(sim)) => {
                    let sim_section = format!("{section}.simulate");
                    let time_scale =
                        simulate_time_scale(sim.speed, sim.time_scale, &sim_section, &mut warnings)
                            .map_err(|(key, m)| invalid(sim_section, key, m))?;
                    PrinterPort::Simulated {
                        time_scale,
                        // From the name, not the position: removing another printer
                        // must not change this one (a reload would restart it).
                        seed: sim.seed.unwrap_or_else(|| name_seed(&p.name)),
                        record: sim.record.map(|r| anchor(&r)),
                    }
                }
            };
            printers.push(PrinterConfig {
                name: p.name,
                port,
                firmware,
                machine,
                baud,
                heat_timeout,
                pause_heaters_off,
            });
        }

        let mut folders: Vec<FolderConfig> = Vec::new();
        for (i, f) in raw.folders.into_iter().enumerate() {
            let section = format!(
                "[[folder]] #{} (path {:?})",
                i + 1,
                f.path.display().to_string()
            );
            if f.path.as_os_str().is_empty() {
                return Err(invalid(section, "path", "must not be empty".into()));
            }
            let path = anchor(&f.path);
            if folders.iter().any(|o| o.path == path) {
                return Err(invalid(section, "path", "is configured twice".into()));
            }
            check_height(f.height_mm).map_err(|m| invalid(section.clone(), "height_mm", m))?;
            // A height no machine of the folder can build would fail every job.
            let tallest = printers
                .iter()
                .filter(|p| f.printers.contains(&p.name))
                .map(|p| p.machine.bed_mm[2])
                .fold(0.0, f64::max);
            if !f.printers.is_empty() && tallest > 0.0 && f.height_mm > tallest {
                return Err(invalid(
                    section,
                    "height_mm",
                    format!(
                        "{} mm is taller than any of its printers' machines builds ({tallest} mm)",
                        f.height_mm
                    ),
                ));
            }
            let inside = |a: &Path, b: &Path| normalise(a).starts_with(normalise(b));
            if inside(&path, &spool_dir) || inside(&spool_dir, &path) {
                return Err(invalid(
                    section,
                    "path",
                    format!(
                        "the hot folder and the spool ({}) must not contain each other",
                        spool_dir.display()
                    ),
                ));
            }
            if f.printers.is_empty() {
                return Err(invalid(
                    section,
                    "printers",
                    "must name at least one printer".into(),
                ));
            }
            for name in &f.printers {
                // In a shared farm, a folder may name other hosts' printers.
                if !names.contains(name) && store.is_none() {
                    return Err(invalid(
                        section,
                        "printers",
                        format!("no [[printer]] is named {name:?}"),
                    ));
                }
            }
            let strength = match (&f.strength, f.enhance) {
                (_, Some(false)) => Strength::Off,
                (None, _) => Strength::Auto,
                (Some(v), _) => {
                    parse_strength(v).map_err(|m| invalid(section.clone(), "strength", m))?
                }
            };
            let timeout = seconds_in(f.timeout_s.unwrap_or(600.0), &PREPARE_TIMEOUT_S)
                .map_err(|m| invalid(section.clone(), "timeout_s", m))?;
            let settings = match f.settings {
                None => crate::slice::SliceSettings::default(),
                Some(table) => {
                    let settings: crate::slice::SliceSettings = toml::Value::Table(table)
                        .try_into()
                        .map_err(|e: toml::de::Error| {
                            invalid(section.clone(), "settings", e.message().trim().to_string())
                        })?;
                    settings
                        .validate()
                        .map_err(|e| invalid(section.clone(), "settings", e.to_string()))?;
                    settings
                }
            };
            folders.push(FolderConfig {
                path,
                height_mm: f.height_mm,
                printers: f.printers,
                strength,
                slicer: f.slicer.unwrap_or_default(),
                up: f.up.unwrap_or_default(),
                profile: f.profile.map(|p| anchor(&p)),
                timeout,
                settings,
            });
        }

        let notify = notify::check(
            raw.notify,
            raw.http.as_ref().and_then(|h| h.public_url.as_deref()),
            file,
            &anchor,
        )?;
        let http = match raw.http {
            None => None,
            Some(h) => {
                Some(check_http(h, &anchor).map_err(|(key, m)| invalid("[http]".into(), key, m))?)
            }
        };
        let history = match raw.history {
            None => HistoryConfig::default(),
            Some(h) => check_history(h).map_err(|(key, m)| invalid("[history]".into(), key, m))?,
        };

        Ok(Checked {
            config: Config {
                source: file.to_path_buf(),
                spool_dir,
                socket,
                farm,
                printers,
                machines,
                folders,
                http: None,
                store,
                history,
                notify,
                warnings,
            },
            http,
        })
    }
}

/// `[printer.simulate] speed` (see [`crate::marlin::sim::time_scale_of_speed`]), or the
/// old `time_scale`, its inverse, read as before with a warning in `warnings` that names
/// `speed`: the simulator's time scale. An error names its key.
fn simulate_time_scale(
    speed: Option<toml::Value>,
    time_scale: Option<f64>,
    section: &str,
    warnings: &mut Vec<String>,
) -> Result<f64, (&'static str, String)> {
    use crate::marlin::sim::{speed_of_time_scale, time_scale_of_speed};
    match (speed, time_scale) {
        (Some(_), Some(_)) => Err((
            "time_scale",
            "give `speed` alone (`time_scale` is its old, inverse form)".into(),
        )),
        (Some(speed), None) => {
            let text = match speed {
                toml::Value::String(s) => s,
                other => other.to_string(),
            };
            time_scale_of_speed(&text).map_err(|m| ("speed", m))
        }
        (None, Some(old)) => {
            if !(old.is_finite() && (0.0..=100.0).contains(&old)) {
                return Err((
                    "time_scale",
                    format!(
                        "must be between 0 (instant) and 100, got {} (hint: use `speed`, how many times faster than real time)",
                        number(old)
                    ),
                ));
            }
            let speed = match speed_of_time_scale(old) {
                word if old == 0.0 => format!("{word:?}"),
                factor => factor,
            };
            warnings.push(format!(
                "{section} key `time_scale`: replaced by `speed`, a speed-up factor (higher is faster); time_scale = {} is speed = {speed}",
                number(old)
            ));
            Ok(old)
        }
        (None, None) => Ok(1.0),
    }
}

/// `[spool] dir` and the control socket (`[control] socket`, else `crispen.sock` in the
/// spool), made absolute: the one rule for the daemon and for the commands that reach it.
fn spool_and_socket(
    raw: &RawConfig,
    file: &Path,
    base: &Path,
) -> Result<(PathBuf, PathBuf), ConfigError> {
    let invalid = |section: &str, key: &str| ConfigError::Invalid {
        file: file.to_path_buf(),
        section: section.into(),
        key: key.into(),
        message: "must not be empty".into(),
    };
    if raw.spool.dir.as_os_str().is_empty() {
        return Err(invalid("[spool]", "dir"));
    }
    // `join` keeps an absolute path as it is.
    let spool_dir = base.join(&raw.spool.dir);
    let socket = match &raw.control {
        Some(c) if c.socket.as_os_str().is_empty() => return Err(invalid("[control]", "socket")),
        Some(c) => base.join(&c.socket),
        None => spool_dir.join("crispen.sock"),
    };
    Ok((spool_dir, socket))
}

/// A host name as `[farm] host` takes it: it names the host in the farm database, the
/// logs and job reasons. 1 to 64 ASCII letters, digits, `.`, `_` and `-`, starting with a
/// letter, digit or `_` (so never `.`, `..` or an option-like `-x`).
fn check_host_name(name: &str) -> Result<String, String> {
    let ok = (1..=64).contains(&name.len())
        && name
            .chars()
            .all(|c| c.is_ascii_alphanumeric() || matches!(c, '.' | '_' | '-'))
        && !name.starts_with(['.', '-']);
    if ok {
        Ok(name.to_string())
    } else {
        Err(format!(
            "{}: use 1 to 64 letters, digits, '.', '_' or '-', not starting with '.' or '-'",
            shorten(&format!("{name:?}"))
        ))
    }
}

/// The system's host name (the default `[farm] host`), made to fit [`check_host_name`].
/// From uname(2), not /proc/sys (which the service unit's `ProcSubset=pid` hides).
fn this_hostname() -> String {
    let raw = nix::unistd::gethostname()
        .map(|h| h.to_string_lossy().into_owned())
        .unwrap_or_default();
    let name: String = raw
        .trim()
        .trim_start_matches(['.', '-'])
        .chars()
        .map(|c| {
            if c.is_ascii_alphanumeric() || matches!(c, '.' | '_' | '-') {
                c
            } else {
                '-'
            }
        })
        .take(64)
        .collect();
    if name.is_empty() {
        "localhost".into()
    } else {
        name
    }
}

/// Checks `[http]`; errors name the key. Its key file is read by [`Checked::resolve`],
/// so a missing or weak key stops the daemon at startup rather than leaving the port open.
fn check_http(
    h: RawHttp,
    anchor: &dyn Fn(&Path) -> PathBuf,
) -> Result<CheckedHttp, (&'static str, String)> {
    let listen: std::net::SocketAddr = h.listen.parse().map_err(|_| {
        (
            "listen",
            format!(
                "{:?} is not an address and port (e.g. \"0.0.0.0:8080\" or \"127.0.0.1:8080\")",
                h.listen
            ),
        )
    })?;
    // Port 0 lets the system pick one (tests); any other port below 1024 needs a
    // capability the service unit does not grant (`CapabilityBoundingSet=` is empty).
    if (1..1024).contains(&listen.port()) {
        return Err((
            "listen",
            format!(
                "port {} is privileged (below 1024): the daemon runs without the capability to bind it (hint: use a port from 1024 up, e.g. 8080, and a reverse proxy if it must be 80 or 443)",
                listen.port()
            ),
        ));
    }
    let upload_max_mb = h.upload_max_mb.unwrap_or(512);
    if !UPLOAD_MAX_MB.contains(&upload_max_mb) {
        return Err((
            "upload_max_mb",
            format!(
                "must be from {} to {}, got {upload_max_mb}",
                UPLOAD_MAX_MB.start(),
                UPLOAD_MAX_MB.end()
            ),
        ));
    }
    Ok(CheckedHttp {
        listen,
        api_key_file: anchor(&h.api_key_file),
        read_only_without_key: h.read_only_without_key.unwrap_or(false),
        upload_max_bytes: upload_max_mb as u64 * 1024 * 1024,
        octoprint: octoprint::check(h.announce, h.default_folder)?,
    })
}

/// Reads an API key file; a missing or weak key is refused (see [`read_secret`]).
pub fn read_api_key(key_file: &Path) -> Result<ApiKey, String> {
    read_api_key_warning(key_file).map(|(key, _)| key)
}

/// The largest key or password file read: a secret is a line, not a stream.
pub const MAX_SECRET_BYTES: u64 = 4096;

/// Reads a secret file (an API key, a database password): a regular file (a link to one
/// is followed) of at most [`MAX_SECRET_BYTES`] of UTF-8. Returns its text, and a warning
/// when users other than its owner may read it: accepted (a root-owned file readable by
/// group `crispen` is a fair setup), but said at every start and by `--check`.
pub fn read_secret(path: &Path) -> Result<(String, Option<String>), String> {
    use std::os::unix::fs::PermissionsExt;
    let shown = path.display();
    let meta = std::fs::metadata(path).map_err(|e| format!("cannot read {shown}: {e}"))?;
    if !meta.is_file() {
        return Err(format!(
            "{shown} is not a regular file (hint: a secret is a small regular file of its own, mode 0600)"
        ));
    }
    let mut bytes = Vec::new();
    std::fs::File::open(path)
        .and_then(|f| f.take(MAX_SECRET_BYTES + 1).read_to_end(&mut bytes))
        .map_err(|e| format!("cannot read {shown}: {e}"))?;
    if bytes.len() as u64 > MAX_SECRET_BYTES {
        return Err(format!(
            "{shown} is larger than {MAX_SECRET_BYTES} bytes: not a key or password file"
        ));
    }
    let text = String::from_utf8(bytes).map_err(|_| format!("{shown} is not UTF-8 text"))?;
    let mode = meta.permissions().mode() & 0o777;
    let warning = (mode & 0o044 != 0).then(|| {
        let who = if mode & 0o004 != 0 {
            "every user"
        } else {
            "its group"
        };
        format!("{shown} is readable by {who} (mode {mode:04o}) (hint: chmod 600 {shown}, owned by the daemon's user)")
    });
    Ok((text, warning))
}

/// [`read_api_key`], with [`read_secret`]'s warning.
fn read_api_key_warning(key_file: &Path) -> Result<(ApiKey, Option<String>), String> {
    let (text, warning) = read_secret(key_file).map_err(|e| {
        if key_file.exists() {
            e
        } else {
            format!(
                "{e} (hint: make one: (umask 077; head -c 24 /dev/urandom | base64 > {}))",
                key_file.display()
            )
        }
    })?;
    let key = text.trim();
    if key.chars().count() < MIN_API_KEY_CHARS || !key.chars().all(|c| c.is_ascii_graphic()) {
        return Err(format!(
            "{}: the key must be at least {MIN_API_KEY_CHARS} printable ASCII characters without spaces",
            key_file.display()
        ));
    }
    Ok((ApiKey(key.to_string()), warning))
}

/// The largest config file read.
const MAX_CONFIG_BYTES: u64 = 1 << 20;

/// At most this many printers (and so heating permits) in one farm.
pub const MAX_PRINTERS: usize = 256;

/// A range of seconds a setting may take.
pub type Bounds = std::ops::RangeInclusive<f64>;
/// Settle time of a dropped file: long enough to see a write, short enough to notice.
const SETTLE_S: Bounds = 0.05..=3600.0;
/// Rescan period of the hot folders.
const RESCAN_S: Bounds = 0.5..=86_400.0;
/// How long prints may take to finish at a stop: from a second (tests) to two days.
pub const FINISH_TIMEOUT_S: Bounds = 1.0..=2.0 * 86_400.0;
/// Two hours, what the service unit once waited for a stop before it killed the daemon.
pub const DEFAULT_FINISH_TIMEOUT_S: f64 = 2.0 * 3600.0;
/// Time limit of one preparation (enhance and slice).
pub const PREPARE_TIMEOUT_S: Bounds = 0.1..=7.0 * 86_400.0;

/// Checks the `[[machine]]` tables in order (one may be `based_on` an earlier one).
fn check_machines(
    specs: Vec<crate::machine::MachineSpec>,
    invalid: &dyn Fn(String, &str, String) -> ConfigError,
    anchor: &dyn Fn(&Path) -> PathBuf,
) -> Result<Vec<crate::machine::Machine>, ConfigError> {
    use crate::machine::{Machine, MAX_MACHINES};
    if specs.len() > MAX_MACHINES {
        return Err(invalid(
            "[[machine]]".into(),
            "name",
            format!("at most {MAX_MACHINES} machines, got {}", specs.len()),
        ));
    }
    let mut machines: Vec<Machine> = Vec::new();
    for (i, spec) in specs.into_iter().enumerate() {
        let section = format!("[[machine]] #{} (name {:?})", i + 1, spec.name);
        let known = |name: &str| {
            machines
                .iter()
                .find(|m| m.name == name)
                .cloned()
                .or_else(|| Machine::builtin(name))
        };
        let machine = spec
            .check(&known, anchor)
            .map_err(|(key, m)| invalid(section.clone(), key, m))?;
        for (key, code) in [
            ("pause_gcode", &machine.pause_gcode),
            ("resume_gcode", &machine.resume_gcode),
        ] {
            if let Some(code) = code {
                pause_code_fits(code, &machine).map_err(|m| invalid(section.clone(), key, m))?;
            }
        }
        machines.push(machine);
    }
    Ok(machines)
}

/// A machine's pause or resume code is sent by the host in the middle of a job: it must
/// load as any job's lines do (text, length, characters), pass the machine's G-code
/// policy, and ask for no pause itself.
fn pause_code_fits(code: &str, machine: &crate::machine::Machine) -> Result<(), String> {
    crate::marlin::gcode::GcodeProgram::read(code.as_bytes(), "the code", machine.firmware)
        .map_err(|e| e.to_string())?;
    let verdict = crate::slice::policy::check(code.as_bytes(), machine)
        .map_err(|e| format!("cannot read the code: {e}"))?;
    if !verdict.passed() {
        return Err(verdict.summary());
    }
    match verdict.pauses.first() {
        Some(p) => Err(format!(
            "line {}: `{}` asks for a pause; the code runs at one",
            p.line, p.command
        )),
        None => Ok(()),
    }
}

/// A number of seconds within `range`, as a duration (never a panic for NaN, infinity or
/// a value too big for a `Duration`).
fn seconds_in(value: f64, range: &Bounds) -> Result<Duration, String> {
    if value.is_finite() && range.contains(&value) {
        Ok(Duration::from_secs_f64(value))
    } else {
        Err(format!(
            "must be a number of seconds from {} to {}, got {}",
            range.start(),
            range.end(),
            number(value)
        ))
    }
}

/// A number as an error shows it: as written for ordinary values, in exponent form when
/// that would take more than 16 characters (`1e308`, not 309 digits).
pub fn number(value: f64) -> String {
    let plain = value.to_string();
    if plain.len() <= 16 {
        plain
    } else {
        format!("{value:e}")
    }
}

/// A value as an error echoes it: at most 80 characters, the rest marked as cut.
fn shorten(text: &str) -> String {
    match text.char_indices().nth(80) {
        None => text.to_string(),
        Some((cut, _)) => format!("{}… ({} characters)", &text[..cut], text.chars().count()),
    }
}

/// A printed height in mm: what the printer can build, and enough to hold a shape.
pub fn check_height(height_mm: f64) -> Result<(), String> {
    let range = crate::slice::HEIGHT_MM;
    if height_mm.is_finite() && range.contains(&height_mm) {
        Ok(())
    } else {
        Err(format!(
            "must be from {} to {} mm, got {}",
            range.start(),
            range.end(),
            number(height_mm)
        ))
    }
}

/// `path` with `.` and `..` taken out lexically (links are not resolved: the folders may
/// not exist yet).
fn normalise(path: &Path) -> PathBuf {
    let mut out = PathBuf::new();
    for c in path.components() {
        match c {
            std::path::Component::CurDir => {}
            std::path::Component::ParentDir => {
                out.pop();
            }
            other => out.push(other),
        }
    }
    out
}

/// A stable seed from a printer's name (FNV-1a), the same on every run and reload.
fn name_seed(name: &str) -> u64 {
    name.bytes().fold(0xcbf2_9ce4_8422_2325, |h, b| {
        (h ^ u64::from(b)).wrapping_mul(0x0100_0000_01b3)
    })
}

/// The strongest enhancement accepted: five times the automatic table's strongest (20),
/// beyond which a shape is distorted rather than sharpened.
pub const MAX_LAMBDA2: f64 = 100.0;

/// `strength = "auto" | "off" | <lambda2>`.
pub fn parse_strength(value: &toml::Value) -> Result<Strength, String> {
    match value {
        toml::Value::String(s) if s == "auto" => Ok(Strength::Auto),
        toml::Value::String(s) if s == "off" => Ok(Strength::Off),
        toml::Value::Float(x) if (0.0..=MAX_LAMBDA2).contains(x) => Ok(Strength::Lambda2(*x)),
        toml::Value::Integer(x) if (0..=MAX_LAMBDA2 as i64).contains(x) => {
            Ok(Strength::Lambda2(*x as f64))
        }
        other => Err(format!(
            "must be \"auto\", \"off\" or a lambda2 from 0 to {MAX_LAMBDA2}, got {other}"
        )),
    }
}

/// The tables as their headers are written, for an error about an unknown one. A test
/// checks it against the file's shape ([`keys::tables`]).
const KNOWN_TABLES: [&str; 10] = [
    "[spool]",
    "[control]",
    "[farm]",
    "[[machine]]",
    "[[printer]]",
    "[[folder]]",
    "[http]",
    "[store]",
    "[history]",
    "[[notify]]",
];

/// The table header on the line of `offset`, when that header names no known table.
fn unknown_table_header(text: &str, offset: usize) -> Option<String> {
    let offset = offset.min(text.len());
    let start = text[..offset].rfind('\n').map_or(0, |i| i + 1);
    let line = text[start..].lines().next()?.trim();
    let name = line
        .strip_prefix("[[")
        .and_then(|l| l.split_once("]]"))
        .or_else(|| line.strip_prefix('[').and_then(|l| l.split_once(']')))?
        .0
        .trim();
    let top = name.split('.').next()?.trim().trim_matches('"');
    let known = KNOWN_TABLES
        .iter()
        .any(|h| h.trim_matches(['[', ']']) == top);
    (!known).then(|| {
        line.split_once('#')
            .map_or(line, |(h, _)| h)
            .trim()
            .to_string()
    })
}

/// Line number (1-based) of a byte offset and the table header that encloses it.
fn locate(text: &str, offset: usize) -> (usize, String) {
    let offset = offset.min(text.len());
    let before = &text[..offset];
    let line = before.matches('\n').count() + 1;
    let mut section = "the top level".to_string();
    let mut counts: std::collections::HashMap<String, usize> = Default::default();
    // Up to the end of the offset's own line: an error about a table as a whole (a missing
    // key) points at its header, which names it.
    let line_end = text[offset..].find('\n').map_or(text.len(), |i| offset + i);
    for l in text[..line_end].lines() {
        let t = l.trim();
        if t.starts_with("[[") {
            if let Some(end) = t.find("]]") {
                let name = t[2..end].trim().to_string();
                let n = counts.entry(name.clone()).or_insert(0);
                *n += 1;
                section = format!("[[{name}]] #{n}");
            }
        } else if t.starts_with('[') {
            if let Some(end) = t.find(']') {
                let name = t[1..end].trim().to_string();
                // `[printer.simulate]` belongs to the latest `[[printer]]`.
                match name.split_once('.') {
                    Some((parent, child)) if counts.contains_key(parent) => {
                        section = format!("[[{parent}]] #{}.{child}", counts[parent]);
                    }
                    _ => section = format!("[{name}]"),
                }
            }
        }
    }
    (line, section)
}

#[cfg(test)]
mod tests {
    use super::*;

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

    /// `[http]`: the key file is read and checked at startup; every error names the key.
    /// A host name is a plain word of the farm: no `.`/`..`, nothing option-like, bounded.
    #[test]
    fn host_names() {
        for good in ["rack-1", "a", "_x", "host.example.org", &"h".repeat(64)] {
            assert_eq!(check_host_name(good).as_deref(), Ok(good), "{good}");
        }
        for bad in [
            "",
            ".",
            "..",
            "-",
            "-x",
            ".hidden",
            "a/b",
            "a b",
            "é",
            &"h".repeat(65),
        ] {
            assert!(check_host_name(bad).is_err(), "{bad:?}");
        }
        let long = check_host_name(&"/".repeat(4000)).unwrap_err();
        assert!(long.len() < 300, "{long}");
        assert!(check_host_name(&this_hostname()).is_ok());
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

    /// A machine's pause and resume code is sent mid-job: what a file may not ask for (a
    /// refused command, a pause of its own, a line the firmware cannot take) is refused in
    /// it too, naming the machine and the key.
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
            ("strength = 0.4", "strength = 1e9", "key `strength`: must be \"auto\", \"off\" or a lambda2 from 0 to 100"),
            ("path = \"/srv/print/5cm\"", "path = \"/var/lib/crispen/hot\"", "[[folder]] #1 (path \"/var/lib/crispen/hot\"): key `path`: the hot folder and the spool (/var/lib/crispen) must not contain each other"),
            ("path = \"/srv/print/5cm\"", "path = \"/var/lib\"", "key `path`: the hot folder and the spool"),
            ("path = \"/srv/print/5cm\"", "path = \"/var/lib/x/../crispen/./in\"", "key `path`: the hot folder and the spool"),
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
}
