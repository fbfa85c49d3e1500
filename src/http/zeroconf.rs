//! Each hot folder announced on the local network as an OctoPrint instance
//! (`_octoprint._tcp`, as OctoPrint announces itself), so Cura's OctoPrint connection
//! lists "crispen: &lt;folder&gt;" without anyone typing an address. The TXT record carries
//! what Cura reads: `path` (the instance's base, `/octoprint/<folder>/`), `version` and
//! `api`, and what Home Assistant reads: `uuid`, the instance's identity, the same as its
//! `api/settings` `plugins.discovery.upnpUuid` (see `super::octoprint::identity`), so a
//! discovered instance and one set up by hand are one device. Multicast DNS is answered by the `mdns-sd` crate's own thread.
//!
//! Where: on the interfaces the HTTP listener is reachable on: all of them for an
//! unspecified address (`0.0.0.0`), only that address's interface for a specific one,
//! only loopback for a loopback address. `[http] announce = false` turns it off. The
//! folders are those at start (a folder added by a reload is announced at the next start).

use crate::daemon::config::Config;

/// The service type OctoPrint announces.
pub(crate) const SERVICE_TYPE: &str = "_octoprint._tcp.local.";
/// A DNS label's bound, which the instance name must keep.
const MAX_LABEL_BYTES: usize = 63;

/// The announcement failed (no multicast socket, a name refused).
#[derive(Debug, thiserror::Error)]
#[error("zeroconf: {0}")]
pub(crate) struct ZeroconfError(String);

/// The announcements in force; withdrawn when dropped.
pub(crate) struct Announcer {
    daemon: mdns_sd::ServiceDaemon,
    names: Vec<String>,
}

impl Drop for Announcer {
    fn drop(&mut self) {
        for name in &self.names {
            let _ = self.daemon.unregister(name);
        }
        let _ = self.daemon.shutdown();
    }
}

/// "crispen: &lt;folder&gt;", cut to a DNS label's length on a character boundary.
pub(crate) fn instance_name(folder: &str) -> String {
    let mut name = format!("crispen: {folder}");
    while name.len() > MAX_LABEL_BYTES {
        name.pop();
    }
    name
}

/// Announces every hot folder of `config` for the listener on `listen` (its real port).
/// None when `[http] announce` is off or there is no `[http]`.
pub(crate) fn announce(
    config: &Config,
    listen: std::net::SocketAddr,
) -> Result<Option<Announcer>, ZeroconfError> {
    let Some(http) = &config.http else {
        return Ok(None);
    };
    if !http.octoprint.announce {
        return Ok(None);
    }
    let failed = |what: &str, e: mdns_sd::Error| ZeroconfError(format!("{what}: {e}"));
    let daemon = mdns_sd::ServiceDaemon::new().map_err(|e| failed("cannot start", e))?;
    let ip = listen.ip();
    if ip.is_loopback() {
        daemon
            .disable_interface(mdns_sd::IfKind::All)
            .and_then(|_| {
                daemon.enable_interface(match ip {
                    std::net::IpAddr::V4(_) => mdns_sd::IfKind::LoopbackV4,
                    std::net::IpAddr::V6(_) => mdns_sd::IfKind::LoopbackV6,
                })
            })
            .map_err(|e| failed("cannot choose the interfaces", e))?;
    } else if !ip.is_unspecified() {
        daemon
            .disable_interface(mdns_sd::IfKind::All)
            .and_then(|_| daemon.enable_interface(mdns_sd::IfKind::Addr(ip)))
            .map_err(|e| failed("cannot choose the interfaces", e))?;
    }
    let host = nix::unistd::gethostname()
        .ok()
        .and_then(|h| h.into_string().ok())
        .filter(|h| !h.is_empty() && h.bytes().all(|b| b.is_ascii_alphanumeric() || b == b'-'))
        .unwrap_or_else(|| "crispen".to_string());
    let host = format!("{host}.local.");
    let mut announcer = Announcer {
        daemon,
        names: Vec::new(),
    };
    for folder in &config.folders {
        let name = super::upload::folder_name(folder);
        let path = format!("/octoprint/{}/", crate::percent::percent_encode(&name));
        let uuid = super::octoprint::identity::uuid(
            &config.spool_dir,
            super::octoprint::identity::Which::Folder(&name),
        )
        .map_err(|e| ZeroconfError(format!("folder {name}: {e}")))?;
        let properties = [
            ("path", path.as_str()),
            ("version", super::octoprint::SERVER_VERSION),
            ("api", super::octoprint::API_VERSION),
            ("uuid", uuid.as_str()),
        ];
        let info = mdns_sd::ServiceInfo::new(
            SERVICE_TYPE,
            &instance_name(&name),
            &host,
            "",
            listen.port(),
            &properties[..],
        )
        .map_err(|e| failed(&format!("folder {name}"), e))?
        .enable_addr_auto();
        let full = info.get_fullname().to_string();
        announcer
            .daemon
            .register(info)
            .map_err(|e| failed(&format!("folder {name}"), e))?;
        tracing::info!(folder = %name, %path, port = listen.port(), "zeroconf: announced as an OctoPrint instance");
        announcer.names.push(full);
    }
    Ok(Some(announcer))
}

#[cfg(test)]
mod tests {
    #[test]
    fn names_fit_a_label() {
        assert_eq!(super::instance_name("hot"), "crispen: hot");
        let long = super::instance_name(&"é".repeat(60));
        assert!(long.len() <= 63 && long.starts_with("crispen: é"), "{long}");
    }
}
