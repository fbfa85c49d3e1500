//! Serial ports as an operator sees them when choosing a printer's `port`: the kernel's
//! device (`/dev/ttyACM0`, which may name another printer after a reboot), the stable
//! `/dev/serial/by-id/…` links udev makes for it, and what USB says about the device.
//!
//! The serialport crate enumerates the devices (from sysfs); the by-id links are read here
//! from a `/dev`-like folder given by the caller, so tests can lay out their own.
//! - [`probe`]: asking the printer on a port for its M115 answer.

pub mod probe;

use std::path::{Path, PathBuf};

/// The folder udev fills with one stable link per serial device, under a `/dev` folder.
pub(crate) const BY_ID: &str = "serial/by-id";

/// One serial device.
#[derive(Debug, Clone, PartialEq)]
pub struct SerialDevice {
    /// The device node the kernel named, e.g. `/dev/ttyACM0` (for a by-id link whose
    /// target could not be resolved: the link itself).
    pub device: PathBuf,
    /// Links in `/dev/serial/by-id` that point at this device.
    pub by_id: Vec<PathBuf>,
    pub usb: Option<UsbInfo>,
}

impl SerialDevice {
    /// The path to put in a config: the first by-id link, else the device node.
    pub fn stable_path(&self) -> &Path {
        self.by_id.first().unwrap_or(&self.device)
    }
}

/// What the USB device says about itself.
#[derive(Debug, Clone, PartialEq)]
pub struct UsbInfo {
    pub vendor_id: u16,
    pub product_id: u16,
    pub manufacturer: Option<String>,
    pub product: Option<String>,
    pub serial_number: Option<String>,
}

#[derive(Debug, thiserror::Error)]
pub enum ListError {
    #[error("cannot list serial ports: {0} (is /sys mounted?)")]
    Enumerate(String),
}

/// The serial devices an operator may connect a printer to: every USB serial device the
/// kernel knows (every serial device with `all`), and every device a link in
/// `<dev_dir>/serial/by-id` points at. Sorted by stable path.
pub fn list(dev_dir: &Path, all: bool) -> Result<Vec<SerialDevice>, ListError> {
    // serialport panics when /sys/class/tty is missing (a container without sysfs).
    let kernel_ports = if Path::new("/sys/class/tty").is_dir() {
        serialport::available_ports().map_err(|e| ListError::Enumerate(e.to_string()))?
    } else {
        Vec::new()
    };
    let kernel_ports = kernel_ports
        .into_iter()
        .filter(|p| all || matches!(p.port_type, serialport::SerialPortType::UsbPort(_)))
        .collect();
    Ok(join(kernel_ports, by_id_links(&dev_dir.join(BY_ID))))
}

/// The links in a by-id folder and the device each resolves to (None: dangling).
pub(crate) fn by_id_links(by_id_dir: &Path) -> Vec<(PathBuf, Option<PathBuf>)> {
    let Ok(entries) = std::fs::read_dir(by_id_dir) else {
        return Vec::new(); // no folder: no USB serial device is plugged in
    };
    let mut links: Vec<_> = entries
        .filter_map(|e| e.ok())
        .map(|e| {
            let link = e.path();
            let target = std::fs::canonicalize(&link).ok();
            (link, target)
        })
        .collect();
    links.sort();
    links
}

/// Joins the kernel's ports with the by-id links that point at them.
pub(crate) fn join(
    kernel_ports: Vec<serialport::SerialPortInfo>,
    links: Vec<(PathBuf, Option<PathBuf>)>,
) -> Vec<SerialDevice> {
    let mut devices: Vec<SerialDevice> = kernel_ports
        .into_iter()
        .map(|p| {
            let device = PathBuf::from(&p.port_name);
            let usb = match p.port_type {
                serialport::SerialPortType::UsbPort(u) => Some(UsbInfo {
                    vendor_id: u.vid,
                    product_id: u.pid,
                    manufacturer: u.manufacturer,
                    product: u.product,
                    serial_number: u.serial_number,
                }),
                _ => None,
            };
            SerialDevice {
                device: std::fs::canonicalize(&device).unwrap_or(device),
                by_id: Vec::new(),
                usb,
            }
        })
        .collect();
    for (link, target) in links {
        let device = target.unwrap_or_else(|| link.clone());
        match devices.iter_mut().find(|d| d.device == device) {
            Some(d) => d.by_id.push(link),
            None => devices.push(SerialDevice {
                device,
                by_id: vec![link],
                usb: None,
            }),
        }
    }
    devices.sort_by(|a, b| a.stable_path().cmp(b.stable_path()));
    devices
}

/// Whether two port paths name the same device now: equal, or resolving (through
/// symlinks such as the by-id links) to the same file.
pub fn same_device(a: &Path, b: &Path) -> bool {
    if a == b {
        return true;
    }
    match (std::fs::canonicalize(a), std::fs::canonicalize(b)) {
        (Ok(a), Ok(b)) => a == b,
        _ => false,
    }
}

/// The by-id link naming the same device as `port` now, looked up next to it: for
/// `/dev/ttyACM0`, in `/dev/serial/by-id`.
pub(crate) fn by_id_name(port: &Path) -> Option<PathBuf> {
    let target = std::fs::canonicalize(port).ok()?;
    let dev_dir = port.parent()?;
    by_id_links(&dev_dir.join(BY_ID))
        .into_iter()
        .find(|(_, t)| t.as_ref() == Some(&target))
        .map(|(link, _)| link)
}

/// Kernel names of USB serial devices, numbered in the order they appear, so the same name
/// may mean another printer after a reboot or a re-plug.
pub(crate) fn is_unstable_name(port: &Path) -> bool {
    let in_by_id = port
        .parent()
        .is_some_and(|dir| dir.ends_with(BY_ID) || dir.ends_with("serial/by-path"));
    let name = port.file_name().and_then(|n| n.to_str()).unwrap_or("");
    !in_by_id && (name.starts_with("ttyACM") || name.starts_with("ttyUSB"))
}

#[cfg(test)]
mod tests {
    use super::*;
    use serialport::{SerialPortInfo, SerialPortType, UsbPortInfo};
    use std::os::unix::fs::symlink;

    fn usb_port(name: &str, serial: &str) -> SerialPortInfo {
        SerialPortInfo {
            port_name: name.into(),
            port_type: SerialPortType::UsbPort(UsbPortInfo {
                vid: 0x2c99,
                pid: 0x0002,
                serial_number: Some(serial.into()),
                manufacturer: Some("Prusa Research (prusa3d.com)".into()),
                product: Some("Original Prusa i3 MK3".into()),
            }),
        }
    }

    #[test]
    fn links_join_the_device_they_point_at() {
        let dev = tempfile::tempdir().unwrap();
        let by_id = dev.path().join(BY_ID);
        std::fs::create_dir_all(&by_id).unwrap();
        for name in ["ttyACM0", "ttyACM1"] {
            std::fs::write(dev.path().join(name), "").unwrap();
        }
        let mk3 = by_id.join("usb-Prusa_Research__prusa3d.com__Original_Prusa_i3_MK3_CZPX1-if00");
        symlink("../../ttyACM1", &mk3).unwrap();
        let dangling = by_id.join("usb-gone-if00");
        symlink("../../ttyACM7", &dangling).unwrap();

        let acm = |n: &str| dev.path().join(n).to_string_lossy().into_owned();
        let devices = join(
            vec![
                usb_port(&acm("ttyACM0"), "A"),
                usb_port(&acm("ttyACM1"), "CZPX1"),
            ],
            by_id_links(&by_id),
        );
        assert_eq!(devices.len(), 3, "{devices:#?}");
        // Sorted by stable path: the two by-id paths first, then the bare device.
        let canonical = |n: &str| std::fs::canonicalize(dev.path().join(n)).unwrap();
        assert_eq!(devices[0].device, canonical("ttyACM1"));
        assert_eq!(devices[0].by_id, std::slice::from_ref(&mk3));
        assert_eq!(devices[0].stable_path(), mk3);
        assert_eq!(
            devices[0].usb.as_ref().unwrap().serial_number.as_deref(),
            Some("CZPX1")
        );
        assert_eq!(devices[1].device, dangling);
        assert!(devices[1].usb.is_none());
        assert_eq!(devices[2].device, canonical("ttyACM0"));
        assert!(devices[2].by_id.is_empty());

        assert_eq!(by_id_name(&dev.path().join("ttyACM1")), Some(mk3.clone()));
        assert_eq!(by_id_name(&dev.path().join("ttyACM0")), None);
        assert!(same_device(&mk3, &dev.path().join("ttyACM1")));
        assert!(!same_device(&mk3, &dev.path().join("ttyACM0")));
        assert!(!same_device(&dangling, &dev.path().join("ttyACM7")));
    }

    #[test]
    fn kernel_names_are_unstable_by_id_names_are_not() {
        assert!(is_unstable_name(Path::new("/dev/ttyACM0")));
        assert!(is_unstable_name(Path::new("/dev/ttyUSB12")));
        assert!(!is_unstable_name(Path::new(
            "/dev/serial/by-id/usb-ttyACM0-if00"
        )));
        assert!(!is_unstable_name(Path::new("/dev/serial/by-id/ttyUSB0")));
        assert!(!is_unstable_name(Path::new("/dev/ttyS0")));
        assert!(!is_unstable_name(Path::new("/dev/printers/mk3")));
    }

    #[test]
    fn a_missing_by_id_folder_is_no_links() {
        assert!(by_id_links(Path::new("/nonexistent/serial/by-id")).is_empty());
    }
}
