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
//!
//! The file's shape (the `Raw*` structs) and its reading are in `raw`, the checked types in
//! `checked`; each section has its check in a module of its own (`farm`, `store`,
//! `machines`, `printers`, `folders`, [`notify`], `http`, `history`, `enhancement`), which this root calls
//! in turn.

pub mod camera;
mod check;
mod checked;
mod enhancement;
mod error;
mod farm;
mod folders;
mod history;
mod http;
mod machines;
mod maintenance;
pub(crate) mod notify;
pub(crate) mod octoprint;
mod pause;
pub mod ports;
pub mod power;
mod printers;
mod raw;
mod secret;
pub mod spoolman;
mod store;

// Read by tests only: they check the reload policy and `KNOWN_TABLES` against it.
#[cfg(test)]
pub(crate) mod keys;

#[cfg(test)]
mod tests;

pub use check::{number, Bounds};
pub use checked::{
    ApiKey, Checked, Config, FarmConfig, FolderConfig, HistoryConfig, HttpConfig, OnShutdown,
    PgSettings, PrinterConfig, PrinterPort, StoreConfig,
};
pub(crate) use error::ConfigError;
pub(crate) use folders::{check_copies, check_height, check_per_plate, parse_strength, MAX_COPIES};
pub(crate) use http::read_api_key;
pub(crate) use secret::read_secret;
pub(crate) use store::{parse_conninfo, ConninfoError};

use check::Context;
use farm::spool_and_socket;
use raw::{parse_raw, read_text, RawConfig};
use std::path::{Path, PathBuf};

impl Checked {
    /// Reads a config file (at most `raw::MAX_CONFIG_BYTES`) and checks it.
    pub fn load(path: &Path) -> Result<Checked, ConfigError> {
        Checked::parse(&read_text(path)?, path)
    }

    /// Parses and checks config text; `path` names it in errors and anchors relative paths
    /// (they are relative to the file's directory).
    pub(crate) fn parse(text: &str, path: &Path) -> Result<Checked, ConfigError> {
        let (raw, base) = parse_raw(text, path)?;
        Config::check(raw, path, &base)
    }

    /// The third stage: what the checked values name on this machine, read and checked:
    /// the API key file (its key is what `[http]` runs with), the database password file
    /// (as the store will read it), and the printers' devices (two printers on one device
    /// are refused). Warnings (a secret others can read) are added to the config's.
    pub(crate) fn resolve(self) -> Result<Config, ConfigError> {
        let Checked { mut config, http } = self;
        let file = config.source.clone();
        store::resolve(config.store.as_ref(), &file, &mut config.warnings)?;
        ports::check_unique(&config.printers, &file)?;
        notify::resolve(&mut config.notify, &file, &mut config.warnings)?;
        config.http = http::resolve(http, &config.folders, &file, &mut config.warnings)?;
        Ok(config)
    }
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
        let (raw, base) = parse_raw(&text, path)?;
        let (_, socket) = spool_and_socket(&raw, path, &base)?;
        Ok(socket)
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
        let cx = Context {
            invalid: &invalid,
            anchor: &anchor,
        };

        let (spool_dir, socket) = spool_and_socket(&raw, file, base)?;
        // What is accepted but should change (see `Config::warnings`).
        let mut warnings = Vec::new();

        let farm = farm::check(raw.farm, &cx)?;
        let store = store::check(raw.store, &cx)?;

        let machines = machines::check(raw.machines, &cx)?;
        let printers = printers::check(raw.printers, &machines, &cx, &mut warnings)?;
        let folders = folders::check(raw.folders, &printers, store.is_some(), &spool_dir, &cx)?;

        let notify = notify::check(
            raw.notify,
            raw.http.as_ref().and_then(|h| h.public_url.as_deref()),
            file,
            &anchor,
        )?;
        let http = match raw.http {
            None => None,
            Some(h) => {
                Some(http::check(h, &anchor).map_err(|(key, m)| invalid("[http]".into(), key, m))?)
            }
        };
        let camera =
            camera::check(raw.camera).map_err(|(key, m)| invalid("[camera]".into(), key, m))?;
        let spoolman = match raw.spoolman {
            None => None,
            Some(s) => {
                Some(spoolman::check(s).map_err(|(key, m)| invalid("[spoolman]".into(), key, m))?)
            }
        };
        let enhancement = enhancement::check(raw.enhancement)
            .map_err(|(key, m)| invalid("[enhancement]".into(), key, m))?;
        let maintenance = maintenance::check(raw.maintenance, &printers)
            .map_err(|(section, key, m)| invalid(section, key, m))?;
        let history = match raw.history {
            None => HistoryConfig::default(),
            Some(h) => history::check(h).map_err(|(key, m)| invalid("[history]".into(), key, m))?,
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
                camera,
                spoolman,
                enhancement,
                maintenance,
                warnings,
            },
            http,
        })
    }
}
