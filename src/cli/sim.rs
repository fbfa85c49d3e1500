//! `crispen sim`: run a simulated Marlin printer on a pty until SIGINT/SIGTERM. The first
//! line on stdout names the device (scripts and the quick start read it); `--link` adds a
//! stable symlink, removed again on exit.

use anyhow::{bail, Context};
use crispen::marlin::firmware::Firmware;
use crispen::sim::{self, Faults, SimConfig};
use nix::sys::signal::{SigSet, Signal};
use std::io::Write;
use std::path::PathBuf;
use std::process::ExitCode;

#[derive(Debug, clap::Args)]
pub(crate) struct Args {
    /// Make a symlink to the pty device here (replaces an existing symlink)
    #[arg(long)]
    pub link: Option<PathBuf>,
    /// Firmware to behave like: marlin2 (2.1), marlin20 (no `ok` after `Resend:`, no
    /// ADVANCED_OK) or ultimaker2
    #[arg(long, default_value = "marlin2")]
    pub firmware: Firmware,
    /// Seed for the fault generator (same seed, same faults)
    #[arg(long, default_value_t = 0)]
    pub seed: u64,
    /// How many times faster than the real printer, higher is faster: 1 = real timing,
    /// 20 = twenty times faster, "instant" = moves and heating take no time
    #[arg(long, value_name = "FACTOR", conflicts_with = "time_scale")]
    pub speed: Option<String>,
    /// Replaced by --speed (its inverse): real seconds per simulated second, so 20 was
    /// twenty times slower. Still accepted, with a warning.
    #[arg(long, hide = true)]
    pub time_scale: Option<f64>,
    /// One-way link latency in milliseconds, both directions (a USB serial adapter adds
    /// 1-16 ms; a pty adds none)
    #[arg(long, value_name = "MS", default_value_t = 0.0)]
    pub latency_ms: f64,
    /// Limit the link to this many bits per second (10 bits per byte), both directions
    #[arg(long, value_name = "BAUD")]
    pub baud_limit: Option<u32>,
    /// Append every executed command to this file
    #[arg(long)]
    pub record: Option<PathBuf>,
    /// Probability that a received line arrives corrupted
    #[arg(long, default_value_t = 0.0)]
    pub corrupt: f64,
    /// Probability that an `ok` is lost
    #[arg(long, default_value_t = 0.0)]
    pub drop_ok: f64,
    /// Probability of a resend request for a good line
    #[arg(long, default_value_t = 0.0)]
    pub spurious_resend: f64,
    /// Probability that a command starts a busy period (marlin2)
    #[arg(long, default_value_t = 0.0)]
    pub busy: f64,
    /// Probability that an answer is garbled or noise is sent
    #[arg(long, default_value_t = 0.0)]
    pub garbage: f64,
    /// Reset (print `start`) after N numbered lines
    #[arg(long, value_name = "N")]
    pub reset_after: Option<usize>,
    /// Close the pty (unplug) after N numbered lines
    #[arg(long, value_name = "N")]
    pub unplug_after: Option<usize>,
    /// Stop answering after N numbered lines
    #[arg(long, value_name = "N")]
    pub silence_after: Option<usize>,
    /// Halt with a fatal error after N numbered lines
    #[arg(long, value_name = "N")]
    pub fatal_after: Option<usize>,
    /// Send `//action:NAME` after N numbered lines, as the printer's own Stop/Pause/Resume
    /// menu items do (e.g. `--action-after 100:pause --action-after 120:resume`)
    #[arg(long, value_name = "N:NAME", value_parser = parse_action)]
    pub action_after: Vec<(usize, String)>,
    /// Report `Error:TEXT` after N numbered lines, a firmware error that is not a halt
    /// (e.g. `--error-after 50:"Probing Failed"`)
    #[arg(long, value_name = "N:TEXT", value_parser = parse_error)]
    pub error_after: Vec<(usize, String)>,
    /// Read commands from stdin, one a line, as a person at the printer: `reset`, `action
    /// NAME` (the printer's menu), `error TEXT` (a firmware error), `line TEXT` (received
    /// as if from the cable, between the host's lines)
    #[arg(long)]
    pub stdin: bool,
    /// Build without EMERGENCY_PARSER (`Cap:EMERGENCY_PARSER:0`), as the real Marlin
    /// 2.1.2.1 builds: an unnumbered M108 then acts only when the queue reads it
    #[arg(long)]
    pub no_emergency_parser: bool,
    /// Say `wait` every MS milliseconds while the command queue is empty (NO_TIMEOUTS)
    #[arg(long, value_name = "MS")]
    pub wait_when_idle_ms: Option<u64>,
    /// Reset when a host opens the port (DTR), with this bootloader delay in milliseconds
    #[arg(long, value_name = "MS")]
    pub reset_on_open_ms: Option<u64>,
}

fn parse_action(text: &str) -> Result<(usize, String), String> {
    let (n, name) = text
        .split_once(':')
        .ok_or_else(|| format!("`{text}`: expected N:NAME, e.g. 100:pause"))?;
    let n = n
        .parse()
        .map_err(|_| format!("`{text}`: {n} is not a line count"))?;
    if name.is_empty() || !name.bytes().all(|b| b.is_ascii_alphanumeric() || b == b'_') {
        return Err(format!(
            "`{text}`: the action name must be letters, digits or `_` (cancel, pause, resume)"
        ));
    }
    Ok((n, name.to_string()))
}

fn parse_error(text: &str) -> Result<(usize, String), String> {
    let (n, message) = text
        .split_once(':')
        .ok_or_else(|| format!("`{text}`: expected N:TEXT, e.g. 50:Probing Failed"))?;
    let n = n
        .parse()
        .map_err(|_| format!("`{text}`: {n} is not a line count"))?;
    if message.trim().is_empty() {
        return Err(format!("`{text}`: the error needs a text"));
    }
    Ok((n, message.trim().to_string()))
}

pub(crate) fn run(args: Args) -> anyhow::Result<ExitCode> {
    for (name, p) in [
        ("--corrupt", args.corrupt),
        ("--drop-ok", args.drop_ok),
        ("--spurious-resend", args.spurious_resend),
        ("--busy", args.busy),
        ("--garbage", args.garbage),
    ] {
        if !(0.0..=1.0).contains(&p) {
            bail!("{name} {p} is not a probability; give a value from 0 to 1");
        }
    }
    let time_scale = match (&args.speed, args.time_scale) {
        (Some(speed), _) => {
            sim::time_scale_of_speed(speed).map_err(|e| anyhow::anyhow!("--{e}"))?
        }
        (None, Some(old)) => {
            if !(old >= 0.0 && old.is_finite()) {
                bail!(
                    "--time-scale {old} must be 0 (instant) or a positive number (1 = real time)"
                );
            }
            eprintln!(
                "warning: --time-scale is replaced by --speed, a speed-up factor (higher is faster); --time-scale {old} is --speed {}",
                sim::speed_of_time_scale(old)
            );
            old
        }
        (None, None) => 1.0,
    };
    if !(args.latency_ms >= 0.0 && args.latency_ms <= 60_000.0) {
        bail!(
            "--latency-ms {} must be from 0 to 60000 milliseconds",
            args.latency_ms
        );
    }
    if args.baud_limit == Some(0) {
        bail!("--baud-limit 0 would never deliver a byte; give a rate such as 115200");
    }
    let mut cfg = SimConfig::new(args.firmware);
    cfg.link_latency = std::time::Duration::from_secs_f64(args.latency_ms / 1000.0);
    cfg.baud = args.baud_limit;
    cfg.seed = args.seed;
    cfg.time_scale = time_scale;
    cfg.record = args.record;
    cfg.keep_executed = false;
    cfg.link = args.link.clone();
    cfg.faults = Faults {
        corrupt_host_bytes: args.corrupt,
        // Tests only (tests/print.rs): the cut line Ultimaker2Marlin may run.
        star_for_dot: 0.0,
        drop_ok: args.drop_ok,
        spurious_resend: args.spurious_resend,
        // Tests only (the co-simulation): a line lost whole.
        lose_line: 0.0,
        busy: args.busy,
        garbage: args.garbage,
        reset_after_lines: args.reset_after,
        unplug_after_lines: args.unplug_after,
        silence_after_lines: args.silence_after,
        fatal_after_lines: args.fatal_after,
        actions: args.action_after.clone(),
        errors: args.error_after.clone(),
        // Tests only: `line TEXT` on --stdin receives a line by hand.
        receive: Vec::new(),
    };
    if args.no_emergency_parser {
        cfg.emergency_parser = Some(false);
    }
    if args.wait_when_idle_ms == Some(0) {
        bail!("--wait-when-idle-ms 0 would flood the link; give an interval such as 1000");
    }
    cfg.wait_when_idle = args.wait_when_idle_ms.map(std::time::Duration::from_millis);
    cfg.reset_on_open = args
        .reset_on_open_ms
        .map(|ms| std::time::Duration::from_millis(ms.min(60_000)));

    // Block the stop signals before the printer thread starts so it inherits the mask and
    // only this thread receives them, in sigwait below.
    let mut signals = SigSet::empty();
    signals.add(Signal::SIGINT);
    signals.add(Signal::SIGTERM);
    signals
        .thread_block()
        .context("cannot block SIGINT/SIGTERM")?;

    let handle = sim::spawn(cfg).with_context(|| match &args.link {
        Some(link) => format!(
            "cannot start the simulated printer (link {})",
            link.display()
        ),
        None => "cannot start the simulated printer".to_string(),
    })?;
    let mut stdout = std::io::stdout().lock();
    writeln!(
        stdout,
        "crispen sim: listening on {}",
        handle.device_path().display()
    )?;
    stdout.flush()?;
    drop(stdout);
    tracing::info!(
        printer = %handle.device_path().display(),
        firmware = %args.firmware,
        link = ?args.link,
        "simulated printer running; stop with Ctrl-C"
    );
    if args.stdin {
        let poker = handle.poker();
        // Detached: it ends with the process, or at the end of stdin.
        std::thread::spawn(move || {
            for line in std::io::stdin().lines() {
                let Ok(line) = line else { return };
                if line.trim().is_empty() {
                    continue;
                }
                match line.parse::<sim::Poke>() {
                    Ok(poke) => {
                        if !poker.poke(poke) {
                            return;
                        }
                    }
                    Err(e) => eprintln!("crispen sim: {e}"),
                }
            }
        });
    }
    let signal = signals.wait().context("waiting for SIGINT/SIGTERM")?;
    tracing::info!(?signal, "stopping the simulated printer");
    handle.shutdown();
    Ok(ExitCode::SUCCESS)
}
