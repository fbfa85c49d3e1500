//! `crispen stats`: the farm's statistics over a period (`GET /api/v1/stats` on the
//! control socket), as tables per printer, per hot folder and per material, or as JSON.

use super::control::ask;
use anyhow::Context;
use crispen::daemon::store::stats::{Group, Stats};
use crispen::percent::percent_encode;
use hyper::Method;
use std::path::PathBuf;
use std::process::ExitCode;

#[derive(Debug, clap::Args)]
pub(crate) struct Args {
    /// The daemon's config file (to find its control socket)
    #[arg(long, short)]
    pub config: Option<PathBuf>,
    /// The last N UTC days, today included (1 to 400; default 7)
    #[arg(long, conflicts_with_all = ["from", "to"])]
    pub days: Option<u32>,
    /// The period's start: YYYY-MM-DD (UTC) or seconds since the epoch
    #[arg(long)]
    pub from: Option<String>,
    /// The period's end (not included; default now)
    #[arg(long, requires = "from")]
    pub to: Option<String>,
    /// Print the statistics as JSON
    #[arg(long)]
    pub json: bool,
}

pub(crate) fn run(a: Args) -> anyhow::Result<ExitCode> {
    let mut query = Vec::new();
    if let Some(days) = a.days {
        query.push(format!("days={days}"));
    }
    if let Some(from) = &a.from {
        query.push(format!("from={}", percent_encode(from)));
    }
    if let Some(to) = &a.to {
        query.push(format!("to={}", percent_encode(to)));
    }
    let path = format!("/api/v1/stats?{}", query.join("&"));
    let answer = ask(&a.config, Method::GET, &path)?;
    if a.json {
        println!("{}", serde_json::to_string_pretty(&answer)?);
        return Ok(ExitCode::SUCCESS);
    }
    let stats: Stats =
        serde_json::from_value(answer).context("the daemon's statistics are not as expected")?;
    println!(
        "{} to {} (UTC)",
        crispen::calendar::utc_minute(stats.from),
        crispen::calendar::utc_minute(stats.to)
    );
    println!();
    table("PRINTER", &stats.printers, true);
    println!();
    table("FOLDER", &stats.folders, false);
    println!();
    if !stats.materials.is_empty() {
        table("MATERIAL", &stats.materials, false);
        println!();
    }
    table("FARM", std::slice::from_ref(&stats.farm), false);
    Ok(ExitCode::SUCCESS)
}

fn table(title: &str, groups: &[Group], printers: bool) {
    println!(
        "{title:<16} {:>6} {:>6} {:>9} {:>9} {:>7} {:>10} {:>10} {:>9}  MOST COMMON FAILURES",
        "DONE", "FAILED", "CANCELLED", "PRINTING", "USE", "FILAMENT", "USED", "COST"
    );
    for g in groups {
        let utilisation = match (printers, g.utilisation) {
            (true, Some(u)) => format!("{:.1}%", 100.0 * u),
            _ => "-".into(),
        };
        let reasons: Vec<String> = g
            .failure_reasons
            .iter()
            .map(|r| {
                format!(
                    "{} ({})",
                    crispen::daemon::hotfolder::escaped(&r.reason),
                    r.jobs
                )
            })
            .collect();
        let cost = g.cost.map_or_else(|| "-".into(), |c| format!("{c:.2}"));
        println!(
            "{:<16} {:>6} {:>6} {:>9} {:>8.1}h {:>7} {:>9.2}m {:>9.1}g {:>9}  {}",
            crispen::daemon::hotfolder::printable(&g.name),
            g.jobs.done,
            g.jobs.failed,
            g.jobs.cancelled,
            g.printing_s / 3600.0,
            utilisation,
            g.filament_mm / 1000.0,
            g.used_g,
            cost,
            reasons.join("; ")
        );
    }
}
