//! `crispen keys`: the application keys that OctoPrint clients (Cura's OctoPrint
//! connection) asked for: list the requests and keys (with each key's scope), allow a
//! request with a scope (upload only by default; `--control`, `--everywhere`) or deny
//! it, change a key's scope (`allow KEY-ID` with the flags it should have), revoke a key.
//! A client of the daemon's HTTP API on its control socket, as the dashboard's
//! Application keys panel is over TCP.

use super::control::ask;
use anyhow::Context;
use crispen::percent::percent_encode;
use hyper::Method;
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
    /// List pending requests and the keys given (the default)
    List,
    /// Give the application that made request ID a key of its own (upload only, on the
    /// instance it asked on, unless the flags say more); given a key's ID, set that
    /// key's scope to exactly what the flags say
    Allow {
        id: String,
        /// Also control prints through OctoPrint's `POST api/job` (pause, resume, cancel)
        #[arg(long)]
        control: bool,
        /// On every OctoPrint instance of the farm, not only the one it asked on
        #[arg(long)]
        everywhere: bool,
    },
    /// Refuse request ID
    Deny { id: String },
    /// Take back key ID: its application is refused from now on
    Revoke { id: String },
}

pub(crate) fn run(a: Args) -> anyhow::Result<ExitCode> {
    let path = match a.action.unwrap_or(Action::List) {
        Action::List => return list(&a.config),
        Action::Allow {
            id,
            control,
            everywhere,
        } => {
            // A key's id sets its scope; else it is a request's.
            let listed = ask(&a.config, Method::GET, "/api/v1/appkeys")?;
            let is_key = listed["keys"]
                .as_array()
                .is_some_and(|keys| keys.iter().any(|k| k["id"] == id.as_str()));
            format!(
                "/api/v1/appkeys/{}/{}/allow?control={control}&everywhere={everywhere}",
                if is_key { "keys" } else { "requests" },
                percent_encode(&id)
            )
        }
        Action::Deny { id } => format!("/api/v1/appkeys/requests/{}/deny", percent_encode(&id)),
        Action::Revoke { id } => format!("/api/v1/appkeys/keys/{}/revoke", percent_encode(&id)),
    };
    let answer = ask(&a.config, Method::POST, &path)?;
    if let Some(message) = answer["message"].as_str() {
        println!("{message}");
    }
    Ok(ExitCode::SUCCESS)
}

fn list(config: &Option<PathBuf>) -> anyhow::Result<ExitCode> {
    let answer = ask(config, Method::GET, "/api/v1/appkeys")?;
    let text =
        |v: &serde_json::Value| crispen::daemon::hotfolder::printable(v.as_str().unwrap_or(""));
    let pending = answer["pending"]
        .as_array()
        .context("the daemon's answer has no pending requests list")?;
    let keys = answer["keys"]
        .as_array()
        .context("the daemon's answer has no keys list")?;
    println!("REQUEST    APPLICATION          FROM             INSTANCE");
    for r in pending {
        println!(
            "{:<10} {:<20} {:<16} {}",
            text(&r["id"]),
            text(&r["app"]),
            text(&r["source"]),
            text(&r["instance"])
        );
    }
    println!("KEY        APPLICATION          FROM             SCOPE");
    for k in keys {
        println!(
            "{:<10} {:<20} {:<16} {}",
            text(&k["id"]),
            text(&k["app"]),
            text(&k["source"]),
            text(&k["scope_text"])
        );
    }
    if pending.is_empty() && keys.is_empty() {
        println!("(no requests and no application keys)");
    }
    Ok(ExitCode::SUCCESS)
}
