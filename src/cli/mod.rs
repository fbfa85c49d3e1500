//! The `crispen` command line. Each subcommand lives in its own file and is a thin layer
//! over the library: parse arguments, set up logging and progress, call in, report.
//! `anyhow` is used only in this layer.

use clap::{Parser, Subcommand};
use error::describe;
use std::process::ExitCode;

pub(crate) mod bedcheck;
pub(crate) mod control;
pub(crate) mod enhance;
mod error;
pub(crate) mod keys;
pub(crate) mod logging;
pub(crate) mod maintenance;
pub(crate) mod notify;
pub(crate) mod observe;
pub(crate) mod ports;
pub(crate) mod power;
pub(crate) mod prepare_job;
pub(crate) mod print;
pub(crate) mod run;
pub(crate) mod sim;
pub(crate) mod slice;
pub(crate) mod spools;
pub(crate) mod stats;

#[derive(Debug, Parser)]
#[command(
    name = "crispen",
    version,
    about = "Sharpen small 3D prints, slice them, and print them on a farm of Marlin printers"
)]
pub(crate) struct Cli {
    #[command(subcommand)]
    pub command: Command,
}

#[derive(Debug, Subcommand)]
pub(crate) enum Command {
    /// Enhance a mesh for a printed height (adaptive unsharp masking)
    Enhance(enhance::Args),
    /// Enhance, scale and slice a model into Marlin G-code for one machine with a real slicer
    Slice(slice::Args),
    /// Which small print looks most like the big one: each strength's print against the
    /// unmodified model at a reference height, through a model of a person's eye
    Observe(observe::Args),
    /// Stream a G-code file to a Marlin printer over serial
    Print(print::Args),
    /// Run a simulated Marlin printer on a pty
    Sim(sim::Args),
    /// List serial ports (stable names, USB ids, which printer uses each), or probe one
    Ports(ports::Args),
    /// Run the print-farm daemon (hot folders of models or pre-sliced G-code, jobs, printers)
    Run(run::Args),
    /// Show the daemon's printers and jobs
    Status(control::StatusArgs),
    /// Page through the finished jobs that have left the queue (newest first)
    History(control::HistoryArgs),
    /// Statistics per printer and per hot folder over a period (jobs, hours, filament)
    Stats(stats::Args),
    /// Confirm a printer's bed has been cleared so it may take the next job
    Clear(control::ClearArgs),
    /// Cancel a job (a printing job is stopped safely), or one part of its plate (--part)
    Cancel(control::CancelArgs),
    /// Pause a printer's current print
    Pause(control::PrinterArgs),
    /// Resume a paused printer
    Resume(control::PrinterArgs),
    /// Put a failed, cancelled or interrupted job back in the queue
    Retry(control::RetryArgs),
    /// Let a held job (an upload without "print", or `hold = true` in its sidecar) print
    Release(control::JobArgs),
    /// Load a spool on a printer: one the farm knows (--spool), or a new one
    Load(spools::LoadArgs),
    /// Take the spool off a printer (it takes no job until one is loaded)
    Unload(control::PrinterArgs),
    /// List the farm's spools: material, colour, what is left, the printer each is on
    Spools(spools::SpoolsArgs),
    /// The printers' care by use: tasks due, work done, a printer in maintenance by hand
    Maintenance(maintenance::Args),
    /// Switch a printer with a [printer.power] switch on or off, between prints
    Power(power::Args),
    /// Notifications: `crispen notify test` sends a test event to every receiver
    Notify(notify::Args),
    /// Application keys of OctoPrint clients: list, allow or deny a request, revoke a key
    Keys(keys::Args),
    /// Compare a picture of the bed with a picture of it empty, as the daemon's bed check does
    BedCheck(bedcheck::Args),
    /// The daemon's preparation child (internal)
    #[command(hide = true)]
    PrepareJob(prepare_job::Args),
}

pub(crate) fn main() -> ExitCode {
    let cli = Cli::parse();
    let daemon = matches!(&cli.command, Command::Run(a) if !a.check);
    if !daemon {
        // A one-shot command whose reader goes away (`crispen status | head`, `crispen
        // run --check | head -1`) ends quietly as Unix tools do, instead of panicking in
        // `println!`. The daemon keeps SIGPIPE ignored: a client closing its connection
        // must not end it.
        use nix::sys::signal::{signal, SigHandler, Signal};
        // SAFETY: no other thread exists yet, and the default action installs no handler.
        let _ = unsafe { signal(Signal::SIGPIPE, SigHandler::SigDfl) };
    }
    logging::init();
    let result = match cli.command {
        Command::Enhance(a) => enhance::run(a),
        Command::Slice(a) => slice::run(a),
        Command::Observe(a) => observe::run(a),
        Command::Print(a) => print::run(a),
        Command::Sim(a) => sim::run(a),
        Command::Ports(a) => ports::run(a),
        Command::Run(a) => run::run(a),
        Command::Status(a) => control::status(a),
        Command::History(a) => control::history(a),
        Command::Stats(a) => stats::run(a),
        Command::Clear(a) => control::clear(a),
        Command::Cancel(a) => control::cancel(a),
        Command::Pause(a) => control::pause(a),
        Command::Resume(a) => control::resume(a),
        Command::Retry(a) => control::retry(a),
        Command::Release(a) => control::release(a),
        Command::Load(a) => spools::load(a),
        Command::Unload(a) => spools::unload(a),
        Command::Spools(a) => spools::spools(a),
        Command::Maintenance(a) => maintenance::run(a),
        Command::Power(a) => power::run(a),
        Command::Notify(a) => notify::run(a),
        Command::Keys(a) => keys::run(a),
        Command::BedCheck(a) => bedcheck::run(a),
        Command::PrepareJob(a) => prepare_job::run(a),
    };
    match result {
        Ok(code) => code,
        Err(err) => {
            eprintln!("error: {}", describe(&err));
            ExitCode::FAILURE
        }
    }
}
