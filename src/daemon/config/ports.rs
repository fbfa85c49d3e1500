//! Checks of the printers' serial ports in a config: two printers on one device is an
//! error (each would read half of the other's answers), and a kernel name such as
//! `/dev/ttyACM0`, which may name another printer after a reboot, gets a warning naming
//! the stable `/dev/serial/by-id` link for the same device where there is one.

use super::checked::{PrinterConfig, PrinterPort};
use super::error::ConfigError;
use crate::ports;
use std::path::Path;

/// Refuses printers that share a device, also when their paths differ but resolve to the
/// same file (a by-id link and the device it points at). `file` names the config in errors.
pub(crate) fn check_unique(printers: &[PrinterConfig], file: &Path) -> Result<(), ConfigError> {
    let serial: Vec<(usize, &PrinterConfig, &Path)> = printers
        .iter()
        .enumerate()
        .filter_map(|(i, p)| match &p.port {
            PrinterPort::Serial(path) => Some((i, p, path.as_path())),
            PrinterPort::Simulated { .. } => None,
        })
        .collect();
    for (n, &(i, printer, port)) in serial.iter().enumerate() {
        if let Some((_, first, first_port)) = serial[..n]
            .iter()
            .find(|(_, _, other)| ports::same_device(other, port))
        {
            let same = if *first_port == port {
                String::new()
            } else {
                format!(
                    " ({} and {} are the same device)",
                    first_port.display(),
                    port.display()
                )
            };
            return Err(ConfigError::Invalid {
                file: file.to_path_buf(),
                section: format!("[[printer]] #{} (name {:?})", i + 1, printer.name),
                key: "port".into(),
                message: format!(
                    "printer {:?} already uses this port{same}; each printer needs its own",
                    first.name
                ),
            });
        }
    }
    Ok(())
}

/// A printer's port that works but deserves a change.
#[derive(Debug, Clone, PartialEq)]
pub struct PortWarning {
    pub printer: String,
    pub message: String,
}

impl std::fmt::Display for PortWarning {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "printer {:?}: {}", self.printer, self.message)
    }
}

/// Warnings about ports named by kernel names that change between boots.
pub fn warnings(printers: &[PrinterConfig]) -> Vec<PortWarning> {
    printers
        .iter()
        .filter_map(|p| match &p.port {
            PrinterPort::Serial(path) if ports::is_unstable_name(path) => {
                let advice = match ports::by_id_name(path) {
                    Some(link) => format!(
                        "use port = {:?}, the same device now",
                        link.display().to_string()
                    ),
                    None => "no /dev/serial/by-id link points at it now; `crispen ports` lists \
                             the stable names of the plugged-in devices"
                        .to_string(),
                };
                Some(PortWarning {
                    printer: p.name.clone(),
                    message: format!(
                        "port {} may name another device after a reboot or re-plug; {advice}",
                        path.display()
                    ),
                })
            }
            _ => None,
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::daemon::config::Config;

    fn config(ports: &[&str]) -> Result<Config, ConfigError> {
        let mut text = "[spool]\ndir = \"spool\"\n".to_string();
        for (i, port) in ports.iter().enumerate() {
            text +=
                &format!("[[printer]]\nname = \"p{i}\"\nport = {port:?}\nfirmware = \"marlin2\"\n");
        }
        Config::parse(&text, Path::new("/etc/crispen/crispen.toml"))
    }

    #[test]
    fn the_same_path_twice_is_refused() {
        let err = config(&["/dev/ttyACM0", "/dev/ttyACM1", "/dev/ttyACM0"])
            .unwrap_err()
            .to_string();
        assert_eq!(
            err,
            "/etc/crispen/crispen.toml: [[printer]] #3 (name \"p2\"): key `port`: printer \"p0\" \
             already uses this port; each printer needs its own"
        );
    }

    #[test]
    fn a_link_and_its_device_are_the_same_port() {
        let dev = tempfile::tempdir().unwrap();
        let by_id = dev.path().join(ports::BY_ID);
        std::fs::create_dir_all(&by_id).unwrap();
        let device = dev.path().join("ttyUSB0");
        std::fs::write(&device, "").unwrap();
        std::fs::write(dev.path().join("ttyUSB1"), "").unwrap();
        let link = by_id.join("usb-1a86_USB_Serial-if00-port0");
        std::os::unix::fs::symlink("../../ttyUSB0", &link).unwrap();
        let (device, link) = (device.to_str().unwrap(), link.to_str().unwrap());

        let err = config(&[link, device]).unwrap_err().to_string();
        assert!(
            err.contains("#2 (name \"p1\"): key `port`: printer \"p0\" already uses"),
            "{err}"
        );
        assert!(
            err.contains(&format!("({link} and {device} are the same device)")),
            "{err}"
        );

        let other = dev.path().join("ttyUSB1");
        let ok = config(&[link, other.to_str().unwrap()]).unwrap();
        let warnings = warnings(&ok.printers);
        assert_eq!(warnings.len(), 1, "{warnings:?}");
        assert_eq!(warnings[0].printer, "p1");
        let text = warnings[0].to_string();
        assert!(text.starts_with("printer \"p1\": port "), "{text}");
        assert!(
            text.contains("no /dev/serial/by-id link points at it"),
            "{text}"
        );

        let linked = config(&[device]).unwrap();
        assert_eq!(
            super::warnings(&linked.printers)[0].to_string(),
            format!(
                "printer \"p0\": port {device} may name another device after a reboot or \
                 re-plug; use port = {link:?}, the same device now"
            )
        );
    }
}
