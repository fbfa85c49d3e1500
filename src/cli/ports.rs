//! `crispen ports`: the serial devices an operator can give a printer as its `port`, with
//! their stable `/dev/serial/by-id` names, USB ids, names and serial numbers, and which
//! configured printer uses each. `--probe PATH` asks the printer on one port for its M115
//! answer.

use anyhow::{bail, Context};
use crispen::daemon::config::{Checked, PrinterConfig, PrinterPort};
use crispen::marlin::transport::TransportError;
use crispen::ports::{self, probe, SerialDevice};
use std::path::{Path, PathBuf};
use std::process::ExitCode;
use std::time::Duration;

/// Where the Debian package installs the daemon's config.
pub(crate) const DEFAULT_CONFIG: &str = "/etc/crispen/crispen.toml";

#[derive(Debug, clap::Args)]
pub(crate) struct Args {
    /// Open this port, wait out the printer's reset, and print its answer to M115
    #[arg(long, value_name = "PATH")]
    pub probe: Option<PathBuf>,
    /// Baud rate for --probe (default: the configured printer's on that port, else 115200)
    #[arg(long, requires = "probe")]
    pub baud: Option<u32>,
    /// Give up --probe after this many seconds
    #[arg(
        long,
        value_name = "SECONDS",
        default_value_t = 20.0,
        requires = "probe"
    )]
    pub timeout: f64,
    /// Config whose printers are matched to the ports (default: /etc/crispen/crispen.toml
    /// when it exists)
    #[arg(long, short)]
    pub config: Option<PathBuf>,
    /// Also list serial devices that are not USB (built-in UARTs, PCI cards)
    #[arg(long, conflicts_with = "probe")]
    pub all: bool,
    /// The folder whose serial/by-id links are read (tests lay out their own)
    #[arg(long, hide = true, default_value = "/dev")]
    pub dev: PathBuf,
}

pub(crate) fn run(args: Args) -> anyhow::Result<ExitCode> {
    let config = load_config(args.config.as_deref())?;
    match &args.probe {
        Some(port) => probe_port(port, &args, config.as_ref()),
        None => list(&args, config.as_ref()),
    }
}

/// The config to match printers against: the one given (an error if it is bad), else the
/// installed one if there is one (a bad one is only a warning: the listing still helps).
/// Checked only, never resolved: the listing needs the printers, not the daemon's key and
/// password files, which the operator running it may not be allowed to read.
fn load_config(path: Option<&Path>) -> anyhow::Result<Option<Checked>> {
    if let Some(path) = path {
        return Ok(Some(Checked::load(path)?));
    }
    let default = Path::new(DEFAULT_CONFIG);
    if !default.exists() {
        return Ok(None);
    }
    match Checked::load(default) {
        Ok(config) => Ok(Some(config)),
        Err(e) => {
            eprintln!("warning: printers not shown: {e}");
            Ok(None)
        }
    }
}

fn serial_printers(config: Option<&Checked>) -> impl Iterator<Item = (&PrinterConfig, &Path)> {
    config
        .into_iter()
        .flat_map(|c| c.printers())
        .filter_map(|p| match &p.port {
            PrinterPort::Serial(path) => Some((p, path.as_path())),
            PrinterPort::Simulated { .. } => None,
        })
}

fn list(args: &Args, config: Option<&Checked>) -> anyhow::Result<ExitCode> {
    let devices = ports::list(&args.dev, args.all)?;
    let source = config.map(|c| c.source().display().to_string());
    let mut out = String::new();
    if devices.is_empty() {
        out += "No USB serial devices found (is the printer plugged in and switched on?).\n";
    }
    for device in &devices {
        out += &describe(device);
        let users: Vec<&str> = serial_printers(config)
            .filter(|(_, port)| uses(port, device))
            .map(|(p, _)| p.name.as_str())
            .collect();
        match (&source, users.is_empty()) {
            (Some(source), false) => {
                out += &format!("  printer  {} (in {source})\n", users.join(", "))
            }
            (Some(_), true) => out += "  printer  none\n",
            (None, _) => {}
        }
    }
    let absent: Vec<String> = serial_printers(config)
        .filter(|(_, port)| !devices.iter().any(|d| uses(port, d)))
        .map(|(p, port)| {
            let state = if port.exists() {
                "present, not a USB serial device"
            } else {
                "not present: unplugged, switched off, or a wrong path"
            };
            format!("  {}  {} ({state})\n", p.name, port.display())
        })
        .collect();
    if let (Some(source), false) = (&source, absent.is_empty()) {
        out += &format!("\nPrinters in {source} on other ports:\n");
        out += &absent.concat();
    }
    print!("{out}");
    Ok(ExitCode::SUCCESS)
}

/// A device's block: its stable name first, as it should go into a config.
fn describe(device: &SerialDevice) -> String {
    let mut out = format!("{}\n", device.stable_path().display());
    if device.by_id.is_empty() {
        out += "  (no /dev/serial/by-id link)\n";
    } else {
        for link in &device.by_id[1..] {
            out += &format!("  also     {}\n", link.display());
        }
        out += &format!("  device   {}\n", device.device.display());
    }
    if let Some(usb) = &device.usb {
        let names: Vec<&str> = [&usb.manufacturer, &usb.product]
            .into_iter()
            .flatten()
            .map(String::as_str)
            .collect();
        out += &format!(
            "  usb      {:04x}:{:04x} {}\n",
            usb.vendor_id,
            usb.product_id,
            names.join(" ")
        );
        if let Some(serial) = &usb.serial_number {
            out += &format!("  serial   {serial}\n");
        }
    }
    out
}

fn uses(port: &Path, device: &SerialDevice) -> bool {
    ports::same_device(port, &device.device) || device.by_id.iter().any(|l| l == port)
}

fn probe_port(port: &Path, args: &Args, config: Option<&Checked>) -> anyhow::Result<ExitCode> {
    if !(args.timeout.is_finite() && (1.0..=600.0).contains(&args.timeout)) {
        bail!("--timeout {} must be from 1 to 600 seconds", args.timeout);
    }
    let user = serial_printers(config).find(|(_, p)| ports::same_device(p, port));
    let baud = args
        .baud
        .or(user.map(|(p, _)| p.baud))
        .unwrap_or(crispen::marlin::firmware::Firmware::Marlin2.default_baud());
    match (user, config) {
        (Some((printer, _)), Some(config)) => eprintln!(
            "probing {} at {baud} baud (the port of printer {:?} in {})",
            port.display(),
            printer.name,
            config.source().display()
        ),
        _ => eprintln!("probing {} at {baud} baud", port.display()),
    }
    let runtime = tokio::runtime::Builder::new_current_thread()
        .enable_all()
        .build()
        .context("cannot start the async runtime")?;
    let timeout = Duration::from_secs_f64(args.timeout);
    let report = runtime
        .block_on(probe::probe(port, baud, timeout))
        .map_err(|e| match &e {
            // The daemon holds its printers' ports.
            probe::ProbeError::Open(TransportError::Busy { .. }) => anyhow::anyhow!(
                "{e}; the crispen daemon keeps its printers' ports (`crispen status` shows them)"
            ),
            _ => e.into(),
        })?;
    for line in &report.answer {
        println!("{line}");
    }
    eprintln!(
        "answered after {:.1} s{}",
        report.waited.as_secs_f64(),
        if report.saw_start {
            " (the printer restarted when the port was opened)"
        } else {
            ""
        }
    );
    Ok(ExitCode::SUCCESS)
}
