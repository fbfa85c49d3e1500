//! The config's checked types: what the daemon runs with ([`Config`]), section by section,
//! and the second stage's [`Checked`], whose secrets are not read yet. Apart from the raw
//! structs that mirror the file and from the checks that make these, so that every part of
//! the daemon (and every section's check) can name them.

use super::{notify, octoprint};
use crate::enhance::Strength;
use crate::marlin::firmware::Firmware;
use crate::mesh::place::UpAxis;
use crate::slice::SlicerKind;
use serde::{Deserialize, Serialize};
use std::path::{Path, PathBuf};
use std::time::Duration;

/// What SIGTERM does to a print in progress.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum OnShutdown {
    /// Keep streaming until the print ends, then exit.
    Finish,
    /// Stop safely (heaters off) and mark the job interrupted.
    Stop,
}

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
    /// How frames are fetched and kept (`[camera]`); each printer's camera is its own.
    pub camera: super::camera::CameraSettings,
    /// The farm's spools come from Spoolman (`[spoolman]`); None: crispen keeps its own.
    pub spoolman: Option<super::spoolman::SpoolmanConfig>,
    /// The observer's reference size and time bound (`[enhancement]`).
    pub enhancement: crate::observation::ObserveSettings,
    /// The printers' care by use (`[[maintenance]]`).
    pub maintenance: Vec<crate::daemon::care::Task>,
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
    /// A spool with less than this many grams left after a print sends `spool_low`.
    pub spool_low_g: f64,
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
    /// Where its pictures come from (`[printer.camera]`).
    pub camera: Option<super::camera::PrinterCamera>,
    /// The filament it holds while no spool is recorded on it (`material`, `colour`).
    pub filament: Option<crate::daemon::filament::Filament>,
    /// Its nozzle is hardened steel (`nozzle = "hardened"`): it may print abrasive fills.
    pub hardened: bool,
    /// Its groups (`tags`).
    pub tags: Vec<String>,
    /// Its eject sequence: `[printer.eject]`, else its machine's (checked against the
    /// machine's G-code policy).
    pub eject: Option<crate::machine::eject::Eject>,
    /// How its bed is cleared after a good print (`bed_clear`), unless the job's folder
    /// says otherwise.
    pub bed_clear: crate::daemon::bed::ClearBy,
    /// Its power switch (`[printer.power]`).
    pub power: Option<super::power::PowerConfig>,
}

#[derive(Debug, Clone)]
pub struct FolderConfig {
    pub path: PathBuf,
    pub height_mm: f64,
    pub printers: Vec<String>,
    pub strength: Strength,
    /// How the enhancement chooses its bands and strength (`enhancement`).
    pub mode: crate::enhance::Mode,
    pub slicer: SlicerKind,
    /// Which of the dropped files' axes points up (STL: z; many OBJ files: y).
    pub up: UpAxis,
    pub profile: Option<PathBuf>,
    pub timeout: Duration,
    /// Slicer setting overrides on top of the profile.
    pub settings: crate::slice::SliceSettings,
    /// What its jobs ask of their printer, unless a sidecar says otherwise.
    pub asks: crate::daemon::filament::Asks,
    /// Copies of each model side by side on one bed, each a part of the plate that can be
    /// cancelled alone (`per_plate`, 1 by default).
    pub per_plate: u32,
    /// Copies of each model its jobs print, each on its own printer at the same time, as
    /// many at once as printers are free (`copies`, 1 by default; a sidecar overrides).
    pub copies: u32,
    /// How its jobs' beds are cleared (`bed_clear`); None: as each printer says.
    pub bed_clear: Option<crate::daemon::bed::ClearBy>,
}

/// The second stage: every value of the file checked and converted, with nothing read but
/// the file itself (no key or password file, no device). It is all that the commands which
/// only read the machines or the printers need, and an operator in the daemon's group may
/// not read its secrets; the daemon goes on to [`Checked::resolve`].
#[derive(Debug, Clone)]
pub struct Checked {
    /// Everything but `[http]`, whose key is read in the third stage.
    pub(super) config: Config,
    pub(super) http: Option<CheckedHttp>,
}

/// `[http]` checked, its key file not yet read.
#[derive(Debug, Clone)]
pub(super) struct CheckedHttp {
    pub(super) listen: std::net::SocketAddr,
    pub(super) api_key_file: PathBuf,
    pub(super) read_only_without_key: bool,
    pub(super) upload_max_bytes: u64,
    pub(super) octoprint: octoprint::OctoPrintConfig,
}

impl Checked {
    /// The file the config came from.
    pub fn source(&self) -> &Path {
        &self.config.source
    }

    /// The control socket.
    #[cfg(test)]
    pub(crate) fn socket(&self) -> &Path {
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
}

impl Config {
    /// The `[[maintenance]]` tasks that apply to `printer` (by name, by its tags, or to
    /// every printer).
    pub(crate) fn tasks_of<'a>(
        &'a self,
        printer: &'a str,
    ) -> impl Iterator<Item = &'a crate::daemon::care::Task> {
        let tags = self
            .printers
            .iter()
            .find(|p| p.name == printer)
            .map_or(&[][..], |p| &p.tags[..]);
        self.maintenance
            .iter()
            .filter(move |t| t.applies_to(printer, tags))
    }

    /// The folder configuration a hot-folder path belongs to.
    pub(crate) fn folder(&self, path: &Path) -> Option<&FolderConfig> {
        self.folders.iter().find(|f| f.path == path)
    }
}
