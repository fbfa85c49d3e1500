//! `crispen maintenance`: the printers' care by use. `list` shows each printer's
//! `[[maintenance]]` tasks (how much of each interval is used, which are due) and whether
//! it is held; `done PRINTER TASK` records a task done (its count starts again); `start` and
//! `end` put a printer into maintenance by hand and take it out; `log PRINTER` shows what
//! it has done and the work recorded. A client of the daemon's HTTP API on its control
//! socket, as the dashboard is over TCP.

use super::control::ask;
use crispen::daemon::care::Interval;
use crispen::names::{escaped, number, printable};
use crispen::percent::percent_encode;
use hyper::Method;
use serde_json::Value;
use std::path::PathBuf;
use std::process::ExitCode;

#[derive(clap::Args, Debug)]
pub(crate) struct Args {
    #[command(subcommand)]
    pub action: Option<Action>,
    /// The daemon's config file (to find its control socket)
    #[arg(long, short, global = true)]
    pub config: Option<PathBuf>,
}

#[derive(clap::Subcommand, Debug)]
pub(crate) enum Action {
    /// Each printer's tasks and where they stand (the default)
    List {
        /// Print the daemon's JSON instead of the table
        #[arg(long)]
        json: bool,
    },
    /// Record TASK done on PRINTER: its count starts again from now
    Done {
        printer: String,
        task: String,
        /// What was done, kept with the record
        #[arg(long)]
        note: Option<String>,
    },
    /// Put PRINTER into maintenance: it finishes its print, then takes no job
    Start {
        printer: String,
        #[arg(long)]
        note: Option<String>,
    },
    /// Take PRINTER out of maintenance: it may take the next job
    End {
        printer: String,
        #[arg(long)]
        note: Option<String>,
    },
    /// What PRINTER has done since its counting began, and the work recorded on it
    Log {
        printer: String,
        #[arg(long)]
        json: bool,
    },
}

pub(crate) fn run(a: Args) -> anyhow::Result<ExitCode> {
    let (printer, action, task, note) = match a.action.unwrap_or(Action::List { json: false }) {
        Action::List { json } => return list(&a.config, json),
        Action::Log { printer, json } => return log(&a.config, &printer, json),
        Action::Done {
            printer,
            task,
            note,
        } => (printer, "done", Some(task), note),
        Action::Start { printer, note } => (printer, "start", None, note),
        Action::End { printer, note } => (printer, "end", None, note),
    };
    let mut query = vec![format!("by={}", percent_encode(&who()))];
    if let Some(task) = task {
        query.push(format!("task={}", percent_encode(&task)));
    }
    if let Some(note) = note {
        query.push(format!("note={}", percent_encode(&note)));
    }
    let path = format!(
        "/api/v1/printers/{}/maintenance/{action}?{}",
        percent_encode(&printer),
        query.join("&")
    );
    let answer = ask(&a.config, Method::POST, &path)?;
    println!("{}", answer["message"].as_str().unwrap_or_default());
    Ok(ExitCode::SUCCESS)
}

/// Who records the work: the user's login name (the control socket is theirs).
fn who() -> String {
    let uid = nix::unistd::getuid();
    match nix::unistd::User::from_uid(uid) {
        Ok(Some(user)) => user.name,
        _ => format!("uid {uid}"),
    }
}

fn list(config: &Option<PathBuf>, json: bool) -> anyhow::Result<ExitCode> {
    let answer = ask(config, Method::GET, "/api/v1/printers")?;
    let printers = answer.as_array().cloned().unwrap_or_default();
    if json {
        let care: Vec<Value> = printers
            .iter()
            .map(|p| {
                serde_json::json!({
                    "printer": p["name"],
                    "state": p["state"],
                    "held": p["held"],
                    "tasks": p.get("maintenance").cloned().unwrap_or(Value::Array(vec![])),
                    "counts": p["care"],
                })
            })
            .collect();
        println!("{}", serde_json::to_string_pretty(&care)?);
        return Ok(ExitCode::SUCCESS);
    }
    let mut any = false;
    for p in &printers {
        let name = printable(p["name"].as_str().unwrap_or("?"));
        let tasks = p["maintenance"].as_array().cloned().unwrap_or_default();
        if let Some(held) = p["held"].as_object() {
            any = true;
            println!(
                "{name:<12} in maintenance by {}{}",
                escaped(held["by"].as_str().unwrap_or("?")),
                held["note"]
                    .as_str()
                    .map_or(String::new(), |n| format!(": {}", escaped(n)))
            );
        }
        for t in tasks {
            any = true;
            let mark = match (t["due"].as_bool(), t["block"].as_bool()) {
                (Some(true), Some(true)) => "DUE (takes no job)",
                (Some(true), _) => "DUE",
                _ => "ok",
            };
            let intervals: Vec<String> =
                serde_json::from_value::<Vec<Interval>>(t["intervals"].clone())
                    .unwrap_or_default()
                    .iter()
                    .map(ToString::to_string)
                    .collect();
            println!(
                "{name:<12} {:<20} {mark:<18} {}",
                escaped(t["task"].as_str().unwrap_or("?")),
                intervals.join(", ")
            );
        }
    }
    if !any {
        println!("no maintenance tasks (add [[maintenance]] tables to the config) and no printer in maintenance");
    }
    Ok(ExitCode::SUCCESS)
}

fn log(config: &Option<PathBuf>, printer: &str, json: bool) -> anyhow::Result<ExitCode> {
    let path = format!("/api/v1/printers/{}/maintenance", percent_encode(printer));
    let answer = ask(config, Method::GET, &path)?;
    if json {
        println!("{}", serde_json::to_string_pretty(&answer)?);
        return Ok(ExitCode::SUCCESS);
    }
    let c = &answer["counts"];
    let f = |key: &str| c[key].as_f64().unwrap_or(0.0);
    println!(
        "{}: {} print hours, {} prints ({} failed), {} m of filament, {} g ({} g abrasive)",
        printable(printer),
        number((f("print_s") / 360.0).round() / 10.0),
        number(f("prints")),
        number(f("failed")),
        number((f("filament_mm") / 100.0).round() / 10.0),
        number(f("filament_g").round()),
        number(f("abrasive_g").round()),
    );
    for entry in answer["log"].as_array().into_iter().flatten() {
        let w = &entry["work"];
        let what = match entry["what"]["kind"].as_str() {
            Some("done") => format!(
                "done: {}",
                escaped(entry["what"]["task"].as_str().unwrap_or("?"))
            ),
            Some("held") => "put into maintenance".to_string(),
            Some("released") => "taken out of maintenance".to_string(),
            _ => "?".to_string(),
        };
        let at = crispen::calendar::iso_utc(w["at_s"].as_f64().unwrap_or(0.0));
        let note = w["note"]
            .as_str()
            .map_or(String::new(), |n| format!(" ({})", escaped(n)));
        println!(
            "  {at}  {what} by {}{note}",
            escaped(w["by"].as_str().unwrap_or("?"))
        );
    }
    Ok(ExitCode::SUCCESS)
}
