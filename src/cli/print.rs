//! `crispen print FILE.gcode --port PATH`: stream one G-code file to a Marlin printer.
//! A thin layer over [`crispen::marlin::stream::Connection`]: the file is checked first as
//! the daemon checks it (the host's load checks, then the G-code policy for the machine's
//! limits), a progress bar on a terminal, Ctrl-C cancels safely (heaters, fan and motors
//! off), exit 0 only when every line was acknowledged.

use anyhow::Context;
use crispen::machine::{Machine, BUILTIN};
use crispen::marlin::firmware::Firmware;
use crispen::marlin::gcode::GcodeProgram;
use crispen::marlin::stream::{
    Connection, PrintProgress, PrintState, StreamControl, StreamOptions,
};
use indicatif::{ProgressBar, ProgressStyle};
use std::io::IsTerminal;
use std::path::PathBuf;
use std::process::ExitCode;
use std::time::Duration;

#[derive(Debug, clap::Args)]
pub(crate) struct Args {
    /// The G-code file (Marlin flavour, with its own heating and start/end code)
    pub file: PathBuf,
    /// Serial device of the printer (e.g. /dev/ttyUSB0, or the pty `crispen sim` prints)
    #[arg(long)]
    pub port: PathBuf,
    /// Baud rate (default: the firmware's usual rate)
    #[arg(long)]
    pub baud: Option<u32>,
    /// Firmware profile: marlin2, marlin20 or ultimaker2 (default: the machine's, else
    /// marlin2)
    #[arg(long)]
    pub firmware: Option<Firmware>,
    /// The built-in machine whose limits (bed, temperatures, tools) the file is checked
    /// against: ultimaker2, ultimaker2-extended, ultimaker2plus, ultimaker-original-plus,
    /// marlin-175 (default: the firmware's usual machine)
    #[arg(long)]
    pub machine: Option<String>,
    /// Keep only one line in flight (as OctoPrint and Printrun do) instead of sending ahead
    #[arg(long)]
    pub one_line: bool,
    /// Fail the job (heaters off) when M109/M190 has not come closer to its temperature
    /// for this many seconds
    #[arg(long, default_value_t = 1200, value_parser = clap::value_parser!(u64).range(10..=86_400))]
    pub heat_timeout: u64,
}

/// The machine of `--machine` and `--firmware`, as a `[[printer]]` table resolves them.
fn machine_of(args: &Args) -> anyhow::Result<Machine> {
    let Some(name) = &args.machine else {
        return Ok(Machine::default_for(
            args.firmware.unwrap_or(Firmware::Marlin2),
        ));
    };
    let machine = Machine::builtin(name).with_context(|| {
        let names: Vec<&str> = BUILTIN.iter().map(|b| b.name).collect();
        format!(
            "--machine {name:?} is not built in; one of: {}",
            names.join(", ")
        )
    })?;
    if let Some(f) = args.firmware.filter(|f| *f != machine.firmware) {
        anyhow::bail!(
            "--firmware {f}, but machine {name:?} runs {}; leave --firmware out",
            machine.firmware
        );
    }
    Ok(machine)
}

pub fn run(args: Args) -> anyhow::Result<ExitCode> {
    let machine = machine_of(&args)?;
    let program = GcodeProgram::load_for(&args.file, machine.firmware)?;
    let verdict = crispen::slice::policy::check_path(&args.file, &machine)?;
    if !verdict.passed() {
        anyhow::bail!(
            "{}: {} (the limits of machine {:?}; --machine names another)",
            args.file.display(),
            verdict.summary(),
            machine.name
        );
    }
    let mut opts = StreamOptions::for_firmware(machine.firmware);
    if let Some(baud) = args.baud {
        opts.baud = baud;
    }
    opts.send_ahead = !args.one_line;
    opts.protocol.heat_timeout = Duration::from_secs(args.heat_timeout);
    let runtime = tokio::runtime::Builder::new_current_thread()
        .enable_all()
        .build()
        .context("cannot start the async runtime")?;
    // The same `printer` and `job` fields the daemon's logs carry.
    let span = tracing::info_span!(
        "print",
        printer = %args.port.display(),
        job = %args.file.display()
    );
    runtime.block_on(tracing::Instrument::instrument(
        print(args, program, opts),
        span,
    ))
}

async fn print(args: Args, program: GcodeProgram, opts: StreamOptions) -> anyhow::Result<ExitCode> {
    let mut conn = Connection::open(&args.port, &opts).await?;
    let info = conn.firmware_info();
    tracing::info!(
        firmware = info.name.as_deref().unwrap_or("unknown"),
        lines = program.len(),
        "streaming {}",
        args.file.display()
    );

    let (control_tx, control_rx) = tokio::sync::mpsc::channel(4);
    let (progress_tx, mut progress_rx) = tokio::sync::watch::channel(PrintProgress::default());

    // Ctrl-C: first press cancels safely; the job then ends with the safe-stop lines.
    let ctrl_c = tokio::spawn(async move {
        if tokio::signal::ctrl_c().await.is_ok() {
            eprintln!(
                "\ncancelling: switching heaters, fan and motors off (Ctrl-C again to abort)"
            );
            let _ = control_tx.send(StreamControl::Cancel).await;
            if tokio::signal::ctrl_c().await.is_ok() {
                std::process::exit(130);
            }
        }
    });

    let bar = std::io::stderr().is_terminal().then(|| {
        let bar = ProgressBar::new(program.len() as u64);
        bar.set_style(
            ProgressStyle::with_template(
                "{bar:30} {pos}/{len} lines {percent}% {msg} [{elapsed_precise}, {eta} left]",
            )
            .unwrap_or_else(|_| ProgressStyle::default_bar()),
        );
        bar
    });
    let bar_task = bar.clone().map(|bar| {
        tokio::spawn(async move {
            while progress_rx.changed().await.is_ok() {
                let p = progress_rx.borrow_and_update().clone();
                bar.set_position(p.lines_acked as u64);
                bar.set_message(describe(&p));
            }
        })
    });

    let result = conn.print(&program, control_rx, progress_tx).await;
    ctrl_c.abort();
    if let Some(task) = bar_task {
        let _ = task.await;
    }
    if let Some(bar) = bar {
        bar.finish_and_clear();
    }
    let report = result.with_context(|| format!("printing {}", args.file.display()))?;
    eprintln!(
        "done: {} lines acknowledged in {:.1} s ({} resends, {} silence probes, {} fragments)",
        report.lines_acked,
        report.duration_s,
        report.resends,
        report.silence_probes,
        report.fragments
    );
    Ok(ExitCode::SUCCESS)
}

fn describe(p: &PrintProgress) -> String {
    let temp = |name: &str, t: Option<crispen::marlin::stream::Temp>| match t {
        Some(t) => match t.target {
            Some(target) if target > 0.0 => format!(" {name} {:.0}/{:.0}°C", t.current, target),
            _ => format!(" {name} {:.0}°C", t.current),
        },
        None => String::new(),
    };
    let state = match p.state {
        PrintState::Printing => "",
        PrintState::Heating => "heating",
        PrintState::Paused => "paused",
        PrintState::WaitingForOperator => "waiting for the operator",
        PrintState::Pausing => "pausing",
        PrintState::Cancelling => "cancelling",
        PrintState::Connecting => "connecting",
        PrintState::Done => "done",
        PrintState::Failed => "failed",
    };
    format!("{state}{}{}", temp("hotend", p.hotend), temp("bed", p.bed))
}
