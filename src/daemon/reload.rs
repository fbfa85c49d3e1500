//! Reloading the config (SIGHUP), with a declared policy per key: [`POLICY`] says for
//! every key of the config file whether a change applies at once, when the printer's
//! supervisor restarts (once it is not printing), or only when the daemon restarts.
//! [`changed_keys`] destructures the config without `..`, so a field added to the config
//! does not compile until it is compared here; and a test walks every key of the file as
//! its `Raw*` structs declare it (`config::keys`), so a key added to the file fails the
//! suite until it has a policy here, or is said to change as another key (the tests'
//! `REPORTED_AS`).

use super::config::{Config, FarmConfig, FolderConfig, HttpConfig, PrinterConfig};
use super::farm::{ConfigOwner, Farm};
use std::sync::Arc;

/// When a changed config value takes effect.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(crate) enum Policy {
    /// At once: the next heat-up, pick-up, preparation or claim uses it.
    Live,
    /// When the printer's supervisor restarts with the new settings, which it does as soon
    /// as the printer is not printing (a print is never cut short by a reload).
    PrinterRestart,
    /// Only at the next start of the daemon: the old value stays in force, and the reload
    /// says so (the spool is locked and loaded once; the sockets are bound once).
    DaemonRestart,
}

impl Policy {
    pub(crate) fn describe(self) -> &'static str {
        match self {
            Policy::Live => "applied",
            Policy::PrinterRestart => "applies when the printer is not printing",
            Policy::DaemonRestart => "needs a daemon restart; the old value stays until then",
        }
    }
}

/// Every key of the config file and its reload policy. `printer` and `folder` alone stand
/// for a printer or folder added or removed.
pub(crate) const POLICY: &[(&str, Policy)] = &[
    ("spool.dir", Policy::DaemonRestart),
    ("control.socket", Policy::DaemonRestart),
    ("http", Policy::DaemonRestart),
    ("http.listen", Policy::DaemonRestart),
    // The key file is read again at every reload, so a rotated key takes effect at once
    // (the old one is refused from then on), whether or not its path changed.
    ("http.api_key_file", Policy::Live),
    ("http.read_only_without_key", Policy::DaemonRestart),
    ("http.upload_max_mb", Policy::DaemonRestart),
    // Notifications' tasks take their receivers and link when they start.
    ("http.public_url", Policy::DaemonRestart),
    ("http.announce", Policy::DaemonRestart),
    ("http.default_folder", Policy::DaemonRestart),
    ("farm.max_heating", Policy::Live),
    ("farm.on_shutdown", Policy::Live),
    ("farm.settle_s", Policy::Live),
    ("farm.rescan_s", Policy::Live),
    // Read when the stop begins.
    ("farm.finish_timeout_s", Policy::Live),
    ("farm.host", Policy::DaemonRestart),
    ("store", Policy::DaemonRestart),
    ("store.postgres", Policy::DaemonRestart),
    ("store.password_file", Policy::DaemonRestart),
    ("store.lease_s", Policy::DaemonRestart),
    // The job store's task takes its retention when it starts.
    ("history.live_days", Policy::DaemonRestart),
    ("history.live_jobs", Policy::DaemonRestart),
    ("history.keep_days", Policy::DaemonRestart),
    ("notify", Policy::DaemonRestart),
    // The cameras' tasks take their settings and sources when the daemon starts.
    ("camera", Policy::DaemonRestart),
    ("printer.camera", Policy::DaemonRestart),
    ("printer", Policy::PrinterRestart),
    ("printer.port", Policy::PrinterRestart),
    ("printer.simulate", Policy::PrinterRestart),
    ("printer.firmware", Policy::PrinterRestart),
    ("printer.baud", Policy::PrinterRestart),
    ("printer.heat_timeout_s", Policy::PrinterRestart),
    // The printer's supervisor takes it when it starts.
    ("printer.pause_heaters_off_s", Policy::PrinterRestart),
    ("printer.machine", Policy::PrinterRestart),
    ("folder", Policy::Live),
    ("folder.height_mm", Policy::Live),
    ("folder.printers", Policy::Live),
    ("folder.strength", Policy::Live),
    ("folder.enhancement", Policy::Live),
    ("folder.slicer", Policy::Live),
    ("folder.up", Policy::Live),
    ("folder.profile", Policy::Live),
    ("folder.timeout_s", Policy::Live),
    ("folder.settings", Policy::Live),
    // What a printer holds and carries, and what a folder's jobs ask: the next claim and
    // the next preparation read them.
    ("printer.material", Policy::Live),
    ("printer.nozzle", Policy::Live),
    ("printer.tags", Policy::Live),
    ("folder.material", Policy::Live),
    ("folder.colour", Policy::Live),
    ("folder.nozzle_mm", Policy::Live),
    ("folder.tags", Policy::Live),
    ("folder.priority", Policy::Live),
    ("folder.per_plate", Policy::Live),
    ("folder.copies", Policy::Live),
    ("farm.spool_low_g", Policy::Live),
    // How a bed is cleared: read when a print ends, and the sequence when it is sent.
    ("printer.eject", Policy::Live),
    ("printer.bed_clear", Policy::Live),
    ("folder.bed_clear", Policy::Live),
    // The link to Spoolman is one task started with the daemon.
    ("spoolman", Policy::DaemonRestart),
    // Read by each preparation.
    ("enhancement.reference_height_mm", Policy::Live),
    ("enhancement.observe_timeout_s", Policy::Live),
    // The printer's supervisor takes its switch when it starts.
    ("printer.power", Policy::PrinterRestart),
    // Read at each claim, status and notification.
    ("maintenance", Policy::Live),
];

/// Keys of the file (and every key under them) whose change is seen as the change of a
/// key of [`POLICY`]: they are settings of that key's value.
#[cfg(test)]
pub(crate) const REPORTED_AS: &[(&str, &str)] = &[
    // A `[[machine]]` table matters only through the printers whose machine it is.
    ("machine", "printer.machine"),
    ("printer.nozzle_mm", "printer.machine"),
    ("printer.name", "printer"),
    ("printer.simulate", "printer.simulate"),
    ("folder.path", "folder"),
    // `enhance = false` is `strength = "off"`.
    ("folder.enhance", "folder.strength"),
    ("notify", "notify"),
    ("camera", "camera"),
    ("printer.camera", "printer.camera"),
    ("printer.eject", "printer.eject"),
    // The default filament is the material and colour together.
    ("printer.colour", "printer.material"),
    ("spoolman", "spoolman"),
    ("maintenance", "maintenance"),
    ("printer.power", "printer.power"),
];

/// The policy of a key of [`POLICY`]. A key missing from the table is treated as needing
/// a daemon restart, the safe choice (a unit test keeps the table complete).
pub(crate) fn policy(key: &str) -> Policy {
    POLICY
        .iter()
        .find(|(k, _)| *k == key)
        .map_or(Policy::DaemonRestart, |(_, p)| *p)
}

/// The keys whose values differ between two configs (each once, in [`POLICY`]'s order; a
/// key missing from it last, so it is still reported).
pub(crate) fn changed_keys(old: &Config, new: &Config) -> Vec<&'static str> {
    let mut changed = std::collections::BTreeSet::new();
    let mut differs = |key: &'static str, different: bool| {
        if different {
            changed.insert(key);
        }
    };
    let Config {
        source: _,
        spool_dir,
        socket,
        farm,
        printers,
        // A `[[machine]]` table matters only through the printers whose machine it is:
        // their machines are compared below (`printer.machine`).
        machines: _,
        folders,
        http,
        store,
        history,
        notify,
        camera,
        spoolman,
        enhancement,
        maintenance,
        // Said again at every reload; not a setting.
        warnings: _,
    } = new;
    differs("maintenance", *maintenance != old.maintenance);
    differs("spool.dir", *spool_dir != old.spool_dir);
    differs("control.socket", *socket != old.socket);
    let FarmConfig {
        max_heating,
        on_shutdown,
        settle,
        rescan,
        finish_timeout,
        host,
        spool_low_g,
    } = farm;
    differs("farm.max_heating", *max_heating != old.farm.max_heating);
    differs("farm.on_shutdown", *on_shutdown != old.farm.on_shutdown);
    differs("farm.settle_s", *settle != old.farm.settle);
    differs("farm.rescan_s", *rescan != old.farm.rescan);
    differs(
        "farm.finish_timeout_s",
        *finish_timeout != old.farm.finish_timeout,
    );
    differs("farm.host", *host != old.farm.host);
    differs("farm.spool_low_g", *spool_low_g != old.farm.spool_low_g);
    differs("spoolman", *spoolman != old.spoolman);
    let super::prepare::steps::observed::ObserveSettings {
        reference_height_mm,
        timeout,
    } = enhancement;
    differs(
        "enhancement.reference_height_mm",
        *reference_height_mm != old.enhancement.reference_height_mm,
    );
    differs(
        "enhancement.observe_timeout_s",
        *timeout != old.enhancement.timeout,
    );
    let super::config::HistoryConfig {
        live_for,
        live_jobs,
        keep_for,
    } = history;
    differs("history.live_days", *live_for != old.history.live_for);
    differs("history.live_jobs", *live_jobs != old.history.live_jobs);
    differs("history.keep_days", *keep_for != old.history.keep_for);
    differs("http.public_url", notify.dashboard != old.notify.dashboard);
    differs("notify", notify.receivers != old.notify.receivers);
    differs("camera", *camera != old.camera);
    match (store, &old.store) {
        (None, None) => {}
        (Some(new), Some(old)) => {
            let super::config::StoreConfig { postgres, lease } = new;
            let super::config::PgSettings {
                conninfo,
                password_file,
            } = postgres;
            differs("store.postgres", *conninfo != old.postgres.conninfo);
            differs(
                "store.password_file",
                *password_file != old.postgres.password_file,
            );
            differs("store.lease_s", *lease != old.lease);
        }
        _ => differs("store", true),
    }
    match (http, &old.http) {
        (None, None) => {}
        (Some(new), Some(old)) => {
            let HttpConfig {
                listen,
                api_key,
                read_only_without_key,
                upload_max_bytes,
                any_port_if_taken,
                octoprint,
            } = new;
            // Only the built-in default may fall back to another port; part of `listen`.
            differs(
                "http.listen",
                *listen != old.listen || *any_port_if_taken != old.any_port_if_taken,
            );
            differs("http.api_key_file", *api_key != old.api_key);
            differs(
                "http.read_only_without_key",
                *read_only_without_key != old.read_only_without_key,
            );
            differs(
                "http.upload_max_mb",
                *upload_max_bytes != old.upload_max_bytes,
            );
            differs(
                "http.announce",
                octoprint.announce != old.octoprint.announce,
            );
            differs(
                "http.default_folder",
                octoprint.default_folder != old.octoprint.default_folder,
            );
        }
        _ => differs("http", true),
    }
    for new in printers {
        let Some(old) = old.printers.iter().find(|p| p.name == new.name) else {
            differs("printer", true);
            continue;
        };
        let PrinterConfig {
            name: _,
            port,
            firmware,
            machine,
            baud,
            heat_timeout,
            pause_heaters_off,
            camera,
            filament,
            hardened,
            tags,
            eject,
            bed_clear,
            power,
        } = new;
        let simulated = |p: &super::config::PrinterPort| {
            matches!(p, super::config::PrinterPort::Simulated { .. })
        };
        let port_key = if simulated(port) && simulated(&old.port) {
            "printer.simulate"
        } else {
            "printer.port"
        };
        differs(port_key, *port != old.port);
        differs("printer.firmware", *firmware != old.firmware);
        differs("printer.baud", *baud != old.baud);
        differs("printer.heat_timeout_s", *heat_timeout != old.heat_timeout);
        differs(
            "printer.pause_heaters_off_s",
            *pause_heaters_off != old.pause_heaters_off,
        );
        differs("printer.machine", *machine != old.machine);
        differs("printer.camera", *camera != old.camera);
        differs("printer.material", *filament != old.filament);
        differs("printer.nozzle", *hardened != old.hardened);
        differs("printer.tags", *tags != old.tags);
        differs("printer.eject", *eject != old.eject);
        differs("printer.bed_clear", *bed_clear != old.bed_clear);
        differs("printer.power", *power != old.power);
    }
    differs(
        "printer",
        old.printers
            .iter()
            .any(|o| !printers.iter().any(|p| p.name == o.name)),
    );
    for new in folders {
        let Some(old) = old.folders.iter().find(|f| f.path == new.path) else {
            differs("folder", true);
            continue;
        };
        let FolderConfig {
            path: _,
            height_mm,
            printers,
            strength,
            mode,
            slicer,
            up,
            profile,
            timeout,
            settings,
            asks,
            per_plate,
            copies,
            bed_clear,
        } = new;
        // Compared by their debug form: these types carry no equality of their own.
        let same =
            |a: &dyn std::fmt::Debug, b: &dyn std::fmt::Debug| format!("{a:?}") == format!("{b:?}");
        differs("folder.height_mm", *height_mm != old.height_mm);
        differs("folder.per_plate", *per_plate != old.per_plate);
        differs("folder.copies", *copies != old.copies);
        differs("folder.printers", *printers != old.printers);
        differs("folder.strength", !same(strength, &old.strength));
        differs("folder.enhancement", *mode != old.mode);
        differs("folder.slicer", !same(slicer, &old.slicer));
        differs("folder.up", !same(up, &old.up));
        differs("folder.profile", *profile != old.profile);
        differs("folder.timeout_s", *timeout != old.timeout);
        // `material` sets the slicer's material too: one change, reported as itself.
        differs(
            "folder.settings",
            !same(settings, &old.settings) && asks.material == old.asks.material,
        );
        differs("folder.material", asks.material != old.asks.material);
        differs("folder.colour", asks.colour != old.asks.colour);
        differs("folder.nozzle_mm", asks.nozzle_mm != old.asks.nozzle_mm);
        differs("folder.tags", asks.tags != old.asks.tags);
        differs("folder.priority", asks.priority != old.asks.priority);
        differs("folder.bed_clear", *bed_clear != old.bed_clear);
    }
    differs(
        "folder",
        old.folders
            .iter()
            .any(|o| !folders.iter().any(|f| f.path == o.path)),
    );
    let mut changed: Vec<&'static str> = changed.into_iter().collect();
    changed.sort_by_key(|k| {
        POLICY
            .iter()
            .position(|(p, _)| p == k)
            .unwrap_or(POLICY.len())
    });
    changed
}

/// The config to run with after a reload: `new`, except the values whose policy is
/// [`Policy::DaemonRestart`], which stay as in `old`.
pub(crate) fn merge(old: &Config, new: Config) -> Config {
    // The listener stays as it was bound; its key is the new file's.
    let http = match (&old.http, &new.http) {
        (Some(old), Some(new)) => Some(HttpConfig {
            api_key: new.api_key.clone(),
            ..old.clone()
        }),
        (old, _) => old.clone(),
    };
    Config {
        spool_dir: old.spool_dir.clone(),
        socket: old.socket.clone(),
        http,
        store: old.store.clone(),
        history: old.history,
        notify: old.notify.clone(),
        camera: old.camera.clone(),
        spoolman: old.spoolman.clone(),
        // The cameras' sources are fetched as the daemon started: a printer keeps the
        // camera it had (a new printer has none) until the next start.
        printers: new
            .printers
            .into_iter()
            .map(|mut p| {
                p.camera = old
                    .printers
                    .iter()
                    .find(|o| o.name == p.name)
                    .and_then(|o| o.camera.clone());
                p
            })
            .collect(),
        farm: super::config::FarmConfig {
            host: old.farm.host.clone(),
            ..new.farm
        },
        ..new
    }
}

/// Reads the config file again and installs it in the farm as [`merge`] says, logging
/// each changed key with its policy, and returns the config now in force; None when the
/// new file was refused (the error is logged) and the old config stays. The caller
/// restarts what depends on it (pick-up, printers).
pub(crate) fn reload(
    farm: &Arc<Farm>,
    owner: &ConfigOwner,
    path: &std::path::Path,
) -> Option<Config> {
    let new = match Config::load(path) {
        Err(e) => {
            tracing::error!(error = %e, "SIGHUP: new config refused; keeping the old one");
            return None;
        }
        Ok(new) => new,
    };
    for warning in &new.warnings {
        tracing::warn!("SIGHUP: {warning}");
    }
    let old = farm.config();
    let changed: Vec<(&'static str, Policy)> = changed_keys(&old, &new)
        .into_iter()
        .map(|k| (k, policy(k)))
        .collect();
    for (key, policy) in &changed {
        match policy {
            Policy::DaemonRestart => {
                tracing::warn!(key, "SIGHUP: {key} changed: {}", policy.describe())
            }
            _ => tracing::info!(key, "SIGHUP: {key} changed: {}", policy.describe()),
        }
    }
    let config = merge(&old, new);
    owner.set(config.clone());
    Some(config)
}

#[cfg(test)]
mod tests {
    use super::*;

    const BASE: &str = "[spool]\ndir = \"spool\"\n[control]\nsocket = \"c.sock\"\n\
        [farm]\nmax_heating = 2\nsettle_s = 1\nrescan_s = 10\non_shutdown = \"finish\"\nhost = \"rack-1\"\n\
        [store]\npostgres = \"host=/run/postgresql dbname=crispen\"\npassword_file = \"pw\"\nlease_s = 15\n\
        [history]\nlive_days = 7\nlive_jobs = 200\n\
        [http]\nlisten = \"127.0.0.1:0\"\napi_key_file = \"key\"\n\
        [[machine]]\nname = \"wide\"\nbased_on = \"marlin-175\"\nbed_mm = [300, 300, 300]\n\
        [[printer]]\nname = \"a\"\nfirmware = \"marlin2\"\nbaud = 115200\n[printer.simulate]\ntime_scale = 0.0\n\
        [printer.eject]\ngcode = \"G1 Z20 F600\"\nmax_height_mm = 30\n\
        [[printer]]\nname = \"b\"\nport = \"/dev/ttyUSB0\"\nfirmware = \"marlin2\"\n\
        [[folder]]\npath = \"hot\"\nheight_mm = 20\nprinters = [\"a\"]\n";

    /// One change per key of [`POLICY`], as (key, text to replace, replacement).
    const CHANGES: &[(&str, &str, &str)] = &[
        ("spool.dir", "dir = \"spool\"", "dir = \"spool2\""),
        ("control.socket", "c.sock", "d.sock"),
        (
            "http",
            "[http]\nlisten = \"127.0.0.1:0\"\napi_key_file = \"key\"\n",
            "",
        ),
        ("http.listen", "127.0.0.1:0", "127.0.0.1:8081"),
        (
            "http.api_key_file",
            "api_key_file = \"key\"",
            "api_key_file = \"key2\"",
        ),
        (
            "http.read_only_without_key",
            "api_key_file = \"key\"\n",
            "api_key_file = \"key\"\nread_only_without_key = true\n",
        ),
        (
            "http.upload_max_mb",
            "api_key_file = \"key\"\n",
            "api_key_file = \"key\"\nupload_max_mb = 7\n",
        ),
        (
            "http.public_url",
            "api_key_file = \"key\"\n",
            "api_key_file = \"key\"\npublic_url = \"http://farm.example:8080/\"\n",
        ),
        (
            "http.announce",
            "api_key_file = \"key\"\n",
            "api_key_file = \"key\"\nannounce = false\n",
        ),
        (
            "http.default_folder",
            "api_key_file = \"key\"\n",
            "api_key_file = \"key\"\ndefault_folder = \"hot\"\n",
        ),
        ("farm.max_heating", "max_heating = 2", "max_heating = 3"),
        ("farm.on_shutdown", "\"finish\"", "\"stop\""),
        ("farm.settle_s", "settle_s = 1", "settle_s = 2"),
        ("farm.rescan_s", "rescan_s = 10", "rescan_s = 11"),
        (
            "farm.finish_timeout_s",
            "rescan_s = 10",
            "rescan_s = 10\nfinish_timeout_s = 60",
        ),
        ("farm.host", "host = \"rack-1\"", "host = \"rack-2\""),
        (
            "store",
            "[store]\npostgres = \"host=/run/postgresql dbname=crispen\"\npassword_file = \"pw\"\nlease_s = 15\n",
            "",
        ),
        ("store.postgres", "dbname=crispen", "dbname=farm"),
        ("store.password_file", "\"pw\"", "\"pw2\""),
        ("store.lease_s", "lease_s = 15", "lease_s = 16"),
        ("history.live_days", "live_days = 7", "live_days = 1.5"),
        ("history.live_jobs", "live_jobs = 200", "live_jobs = 20"),
        (
            "history.keep_days",
            "live_jobs = 200",
            "live_jobs = 200\nkeep_days = 30",
        ),
        (
            "notify",
            "[http]\n",
            "[[notify]]\nname = \"phone\"\nurl = \"https://ntfy.sh/farm\"\nformat = \"ntfy\"\n[http]\n",
        ),
        ("camera", "[history]\n", "[camera]\nrefresh_s = 2\n[history]\n"),
        (
            "printer.camera",
            "time_scale = 0.0\n",
            "time_scale = 0.0\n[printer.camera]\nsnapshot = \"http://cam:8080/snapshot\"\n",
        ),
        (
            "printer",
            "[[printer]]\nname = \"b\"\nport = \"/dev/ttyUSB0\"\nfirmware = \"marlin2\"\n",
            "",
        ),
        ("printer.port", "/dev/ttyUSB0", "/dev/ttyUSB1"),
        ("printer.simulate", "time_scale = 0.0", "time_scale = 1.0"),
        (
            "printer.firmware",
            "name = \"a\"\nfirmware = \"marlin2\"",
            "name = \"a\"\nfirmware = \"ultimaker2\"",
        ),
        (
            "printer.baud",
            "port = \"/dev/ttyUSB0\"\n",
            "port = \"/dev/ttyUSB0\"\nbaud = 250000\n",
        ),
        (
            "printer.heat_timeout_s",
            "port = \"/dev/ttyUSB0\"\n",
            "port = \"/dev/ttyUSB0\"\nheat_timeout_s = 77\n",
        ),
        (
            "printer.pause_heaters_off_s",
            "port = \"/dev/ttyUSB0\"\n",
            "port = \"/dev/ttyUSB0\"\npause_heaters_off_s = 60\n",
        ),
        (
            "printer.machine",
            "port = \"/dev/ttyUSB0\"\n",
            "port = \"/dev/ttyUSB0\"\nmachine = \"wide\"\n",
        ),
        (
            "folder",
            "printers = [\"a\"]\n",
            "printers = [\"a\"]\n[[folder]]\npath = \"hot2\"\nheight_mm = 20\nprinters = [\"a\"]\n",
        ),
        ("folder.height_mm", "height_mm = 20", "height_mm = 21"),
        (
            "folder.printers",
            "printers = [\"a\"]",
            "printers = [\"a\", \"b\"]",
        ),
        (
            "folder.strength",
            "printers = [\"a\"]\n",
            "printers = [\"a\"]\nstrength = 2.5\n",
        ),
        (
            "folder.enhancement",
            "printers = [\"a\"]\n",
            "printers = [\"a\"]\nenhancement = \"print-aware\"\n",
        ),
        (
            "folder.slicer",
            "printers = [\"a\"]\n",
            "printers = [\"a\"]\nslicer = \"cura\"\n",
        ),
        (
            "folder.up",
            "printers = [\"a\"]\n",
            "printers = [\"a\"]\nup = \"y\"\n",
        ),
        (
            "folder.profile",
            "printers = [\"a\"]\n",
            "printers = [\"a\"]\nprofile = \"p.ini\"\n",
        ),
        (
            "folder.timeout_s",
            "printers = [\"a\"]\n",
            "printers = [\"a\"]\ntimeout_s = 99\n",
        ),
        (
            "folder.settings",
            "printers = [\"a\"]\n",
            "printers = [\"a\"]\n[folder.settings]\ninfill_percent = 30\n",
        ),
        (
            "printer.material",
            "port = \"/dev/ttyUSB0\"\n",
            "port = \"/dev/ttyUSB0\"\nmaterial = \"PETG\"\n",
        ),
        (
            "printer.nozzle",
            "port = \"/dev/ttyUSB0\"\n",
            "port = \"/dev/ttyUSB0\"\nnozzle = \"hardened\"\n",
        ),
        (
            "printer.tags",
            "port = \"/dev/ttyUSB0\"\n",
            "port = \"/dev/ttyUSB0\"\ntags = [\"big\"]\n",
        ),
        (
            "folder.material",
            "printers = [\"a\"]\n",
            "printers = [\"a\"]\nmaterial = \"PETG\"\n",
        ),
        (
            "folder.colour",
            "printers = [\"a\"]\n",
            "printers = [\"a\"]\ncolour = \"black\"\n",
        ),
        (
            "folder.nozzle_mm",
            "printers = [\"a\"]\n",
            "printers = [\"a\"]\nnozzle_mm = 0.4\n",
        ),
        (
            "folder.tags",
            "printers = [\"a\"]\n",
            "printers = [\"a\"]\ntags = [\"big\"]\n",
        ),
        (
            "folder.priority",
            "printers = [\"a\"]\n",
            "printers = [\"a\"]\npriority = 3\n",
        ),
        (
            "folder.per_plate",
            "printers = [\"a\"]\n",
            "printers = [\"a\"]\nper_plate = 4\n",
        ),
        (
            "folder.copies",
            "printers = [\"a\"]\n",
            "printers = [\"a\"]\ncopies = 4\n",
        ),
        (
            "farm.spool_low_g",
            "rescan_s = 10",
            "rescan_s = 10\nspool_low_g = 50",
        ),
        (
            "printer.eject",
            "gcode = \"G1 Z20 F600\"",
            "gcode = \"G1 Z25 F600\"",
        ),
        (
            "printer.bed_clear",
            "baud = 115200\n",
            "baud = 115200\nbed_clear = \"eject\"\n",
        ),
        (
            "folder.bed_clear",
            "printers = [\"a\"]\n",
            "printers = [\"a\"]\nbed_clear = \"eject\"\n",
        ),
        (
            "spoolman",
            "[history]\n",
            "[spoolman]\nurl = \"http://127.0.0.1:7912\"\n[history]\n",
        ),
        (
            "enhancement.reference_height_mm",
            "[history]\n",
            "[enhancement]\nreference_height_mm = 100\n[history]\n",
        ),
        (
            "enhancement.observe_timeout_s",
            "[history]\n",
            "[enhancement]\nobserve_timeout_s = 60\n[history]\n",
        ),
        (
            "printer.power",
            "baud = 115200\n",
            "baud = 115200\n[printer.power]\nkind = \"tasmota\"\nurl = \"http://plug\"\n",
        ),
        (
            "maintenance",
            "[history]\n",
            "[[maintenance]]\nname = \"nozzle\"\nevery_kg = 2\n[history]\n",
        ),
    ];

    fn parse(dir: &std::path::Path, text: &str) -> Config {
        Config::parse(text, &dir.join("crispen.toml")).unwrap_or_else(|e| panic!("{e}\n{text}"))
    }

    /// Every key of the table has a change here, each change is seen as exactly its key,
    /// and after a merge a daemon-restart key keeps its old value while every other key
    /// takes the new one.
    #[test]
    fn each_key_changes_as_its_policy_declares() {
        let tmp = tempfile::tempdir().unwrap();
        std::fs::write(tmp.path().join("key"), "k".repeat(32)).unwrap();
        std::fs::write(tmp.path().join("key2"), "q".repeat(32)).unwrap();
        std::fs::write(tmp.path().join("pw"), "secret").unwrap();
        std::fs::write(tmp.path().join("pw2"), "secret").unwrap();
        std::fs::write(tmp.path().join("p.ini"), "").unwrap();
        for dir in ["hot", "hot2"] {
            std::fs::create_dir(tmp.path().join(dir)).unwrap();
        }
        let old = parse(tmp.path(), BASE);
        let keys: Vec<&str> = CHANGES.iter().map(|c| c.0).collect();
        let table: Vec<&str> = POLICY.iter().map(|p| p.0).collect();
        assert_eq!(keys, table, "one change per key of the table");
        assert!(changed_keys(&old, &old).is_empty());
        for (key, from, to) in CHANGES {
            assert!(BASE.contains(from), "{key}: {from:?} is in the base config");
            let new = parse(tmp.path(), &BASE.replacen(from, to, 1));
            // A printer without `machine` takes its machine from its firmware, so a new
            // firmware is a new machine too (both restart the printer).
            let expected = match *key {
                "printer.firmware" => vec!["printer.firmware", "printer.machine"],
                _ => vec![*key],
            };
            assert_eq!(changed_keys(&old, &new), expected, "{key}");
            let merged = merge(&old, new);
            let kept = changed_keys(&old, &merged).is_empty();
            assert_eq!(kept, policy(key) == Policy::DaemonRestart, "{key}");
        }
    }

    /// Every key the file may hold (as its `Raw*` structs declare it) has a policy, or
    /// is a setting of a key that has one; a table is covered by its keys. Two keys once
    /// had neither, and a reload dropped their changes without a word.
    #[test]
    fn every_key_of_the_file_has_a_policy() {
        let keys = crate::daemon::config::keys::all().unwrap();
        let under = |key: &str, table: &str| {
            key == table || key.strip_prefix(table).is_some_and(|r| r.starts_with('.'))
        };
        for key in &keys {
            let is_table = keys.iter().any(|k| k != key && under(k, key));
            let reported = REPORTED_AS.iter().find(|(table, _)| under(key, table));
            match reported {
                Some((_, as_key)) => assert!(
                    POLICY.iter().any(|(k, _)| k == as_key),
                    "{key} is reported as {as_key}, which has no policy"
                ),
                None => assert!(
                    is_table || POLICY.iter().any(|(k, _)| k == key),
                    "the config key `{key}` has no reload policy: give it one in POLICY \
                     (and compare it in changed_keys), or list it in REPORTED_AS"
                ),
            }
        }
        // And the table names nothing the file does not hold.
        for (key, _) in POLICY {
            assert!(keys.iter().any(|k| k == key), "{key} is no key of the file");
        }
    }

    /// The keys of [`REPORTED_AS`] change as the key they are reported as.
    #[test]
    fn settings_of_a_key_are_reported_as_it() {
        let tmp = tempfile::tempdir().unwrap();
        std::fs::write(tmp.path().join("key"), "k".repeat(32)).unwrap();
        std::fs::write(tmp.path().join("pw"), "secret").unwrap();
        std::fs::create_dir(tmp.path().join("hot")).unwrap();
        // Printer b on the `[[machine]]` table, so that a change of the table matters.
        let base = BASE.replacen(
            "port = \"/dev/ttyUSB0\"\n",
            "port = \"/dev/ttyUSB0\"\nmachine = \"wide\"\n",
            1,
        );
        let old = parse(tmp.path(), &base);
        let cases = [
            (
                "machine",
                "bed_mm = [300, 300, 300]",
                "bed_mm = [300, 300, 250]",
                "printer.machine",
            ),
            (
                "folder.enhance",
                "printers = [\"a\"]\n",
                "printers = [\"a\"]\nenhance = false\n",
                "folder.strength",
            ),
            (
                "printer.simulate",
                "time_scale = 0.0",
                "time_scale = 0.0\nseed = 7",
                "printer.simulate",
            ),
        ];
        for (key, from, to, as_key) in cases {
            assert!(base.contains(from), "{key}");
            let new = parse(tmp.path(), &base.replacen(from, to, 1));
            assert_eq!(changed_keys(&old, &new), [as_key], "{key}");
        }
    }
}
