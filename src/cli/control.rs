//! `crispen status|clear|cancel|pause|resume|retry`: clients of the daemon's control socket
//! ([`crispen::daemon::control`]). The socket is found through the same `--config` the
//! daemon was started with (or the built-in default).

use crispen::daemon::config::Config;
use crispen::daemon::control::{self, Request, Response, Status};
use std::path::PathBuf;
use std::process::ExitCode;

#[derive(Debug, clap::Args)]
pub struct StatusArgs {
    /// The daemon's config file (to find its control socket)
    #[arg(long, short)]
    pub config: Option<PathBuf>,
    /// Print the status as JSON (every job and printer has a lower-case `state`)
    #[arg(long)]
    pub json: bool,
}

#[derive(Debug, clap::Args)]
pub struct PrinterArgs {
    /// Printer name, as in the config's [[printer]] name
    pub printer: String,
    /// The daemon's config file (to find its control socket)
    #[arg(long, short)]
    pub config: Option<PathBuf>,
}

#[derive(Debug, clap::Args)]
pub struct JobArgs {
    /// Job id, as shown by `crispen status`
    pub job: String,
    /// The daemon's config file (to find its control socket)
    #[arg(long, short)]
    pub config: Option<PathBuf>,
}

fn ask(config: &Option<PathBuf>, req: Request) -> anyhow::Result<Response> {
    let config = match config {
        Some(path) => Config::load(path)?,
        None => Config::builtin_default(),
    };
    Ok(control::request(&config.socket, &req)?)
}

fn report(response: Response) -> anyhow::Result<ExitCode> {
    if response.ok {
        if let Some(m) = response.message {
            println!("{m}");
        }
        Ok(ExitCode::SUCCESS)
    } else {
        anyhow::bail!(response
            .error
            .unwrap_or_else(|| "the daemon refused".into()))
    }
}

pub fn status(a: StatusArgs) -> anyhow::Result<ExitCode> {
    let response = ask(&a.config, Request::Status)?;
    if !response.ok {
        return report(response);
    }
    let status = response.status.unwrap_or(Status {
        printers: vec![],
        jobs: vec![],
    });
    if a.json {
        println!("{}", serde_json::to_string_pretty(&status)?);
        return Ok(ExitCode::SUCCESS);
    }
    println!("PRINTER          STATE            JOB                          HOTEND      BED        PROGRESS");
    for p in &status.printers {
        let state = serde_json::to_value(p.state)?;
        let temps = |cur: Option<f64>, target: Option<f64>| match (cur, target) {
            (Some(c), Some(t)) => format!("{c:.0}/{t:.0}C"),
            (Some(c), None) => format!("{c:.0}C"),
            _ => "-".into(),
        };
        let (hotend, bed, progress) = match &p.progress {
            Some(l) => (
                temps(l.hotend_c, l.hotend_target_c),
                temps(l.bed_c, l.bed_target_c),
                if l.lines_total > 0 {
                    format!(
                        "{:.1}% ({}/{} lines){}",
                        100.0 * l.lines_acked as f64 / l.lines_total as f64,
                        l.lines_acked,
                        l.lines_total,
                        l.remaining_s
                            .map(|r| format!(", {:.0} min left", r / 60.0))
                            .unwrap_or_default()
                    )
                } else {
                    "-".into()
                },
            ),
            None => ("-".into(), "-".into(), "-".into()),
        };
        println!(
            "{:<16} {:<16} {:<28} {:<11} {:<10} {}{}",
            p.name,
            state.as_str().unwrap_or("?"),
            p.job.as_deref().unwrap_or("-"),
            hotend,
            bed,
            progress,
            p.detail
                .as_deref()
                .map(|d| format!("  ({d})"))
                .unwrap_or_default()
        );
        if !p.bed_cleared {
            println!(
                "{:<16} bed not cleared: remove the print, then `crispen clear {}`",
                "", p.name
            );
        }
    }
    println!();
    println!("JOB                          STATE        PRINTER          FILE / REASON");
    for j in &status.jobs {
        let extra = match (&j.reason, &j.step, &j.progress) {
            (Some(r), _, _) => format!("{}: {r}", j.file),
            (None, Some(step), _) => format!("{} [{step}]", j.file),
            (None, None, Some(l)) if l.lines_total > 0 => format!(
                "{} [{:.1}%]",
                j.file,
                100.0 * l.lines_acked as f64 / l.lines_total as f64
            ),
            _ => j.file.clone(),
        };
        println!(
            "{:<28} {:<12} {:<16} {}",
            j.id,
            j.state.name(),
            j.printer.as_deref().unwrap_or("-"),
            extra
        );
    }
    Ok(ExitCode::SUCCESS)
}

pub fn clear(a: PrinterArgs) -> anyhow::Result<ExitCode> {
    report(ask(&a.config, Request::Clear { printer: a.printer })?)
}
pub fn cancel(a: JobArgs) -> anyhow::Result<ExitCode> {
    report(ask(&a.config, Request::Cancel { job: a.job })?)
}
pub fn pause(a: PrinterArgs) -> anyhow::Result<ExitCode> {
    report(ask(&a.config, Request::Pause { printer: a.printer })?)
}
pub fn resume(a: PrinterArgs) -> anyhow::Result<ExitCode> {
    report(ask(&a.config, Request::Resume { printer: a.printer })?)
}
pub fn retry(a: JobArgs) -> anyhow::Result<ExitCode> {
    report(ask(&a.config, Request::Retry { job: a.job })?)
}
