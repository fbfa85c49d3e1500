//! `crispen run`: the print-farm daemon. Loads the config (or the built-in demo default,
//! which also serves the dashboard on 127.0.0.1:8080 with a key made in ./crispen-demo),
//! then hands over to [`crispen::service::run`] on a multi-threaded tokio runtime.

use anyhow::Context;
use crispen::daemon::{self, config::Config};
use crispen::service::{self, RunOptions};
use std::path::PathBuf;
use std::process::ExitCode;

#[derive(Debug, clap::Args)]
pub(crate) struct Args {
    /// Config file (default: the built-in demo under ./crispen-demo/ with a simulated printer)
    #[arg(long, short)]
    pub config: Option<PathBuf>,
    /// Exit once no job is waiting, preparing or printing and at least one job finished
    #[arg(long)]
    pub exit_when_idle: bool,
    /// Check the config and exit
    #[arg(long)]
    pub check: bool,
}

pub fn run(args: Args) -> anyhow::Result<ExitCode> {
    let config = match &args.config {
        Some(path) => Config::load(path)?,
        None => {
            let mut config = Config::builtin_default();
            if !args.check {
                let key_file = config
                    .spool_dir
                    .parent()
                    .unwrap_or(&config.spool_dir)
                    .join("api-key");
                config.http = Some(crispen::http::demo_http(&key_file)?);
                tracing::info!(
                    key_file = %key_file.display(),
                    "the dashboard shows the farm to anyone on this machine; to act (clear a bed, cancel, upload) enter the key from {}",
                    key_file.display()
                );
            }
            config
        }
    };
    // What the config allows but should not (a key file others can read).
    for warning in &config.warnings {
        if args.check {
            eprintln!("warning: {warning}");
        } else {
            tracing::warn!("{warning}");
        }
    }
    // Kernel names such as /dev/ttyACM0 work today but may swap printers after a reboot.
    for warning in daemon::config::ports::warnings(&config.printers) {
        if args.check {
            eprintln!("warning: {warning}");
        } else {
            tracing::warn!(printer = %warning.printer, "{}", warning.message);
        }
    }
    if args.check {
        println!(
            "{}: OK ({} printers, {} folders)",
            config.source.display(),
            config.printers.len(),
            config.folders.len()
        );
        // What each printer's G-code will be made for.
        for p in &config.printers {
            let m = &p.machine;
            let [x, y, z] = m.bed_mm;
            println!(
                "  {}: machine {} ({x} x {y} x {z} mm, {} mm nozzle, {} mm filament, {} bed, firmware {})",
                p.name,
                m.name,
                m.nozzle_mm,
                m.filament_mm,
                if m.heated_bed { "heated" } else { "unheated" },
                m.firmware
            );
        }
        return Ok(ExitCode::SUCCESS);
    }
    // One worker: the async side only moves bytes and state (preparation, slicing, G-code
    // loading and disk writes run on blocking threads), and with 20 printers streaming a
    // second worker cost more in wake-ups between the two than it saved: 150 instead of
    // 193 µs of CPU per acknowledged line (the soak benchmark's farm). A printer's planner
    // holds seconds of moves, so a moment's wait for the worker starves none.
    let runtime = tokio::runtime::Builder::new_multi_thread()
        .worker_threads(1)
        .enable_all()
        .build()
        .context("cannot start the async runtime")?;
    let options = RunOptions {
        config_path: args.config.clone(),
        exit_when_idle: args.exit_when_idle,
        prepare_program: None,
    };
    runtime.block_on(service::run(config, options))?;
    Ok(ExitCode::SUCCESS)
}
