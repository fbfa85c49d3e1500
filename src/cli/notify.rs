//! `crispen notify test`: sends a test event to every `[[notify]]` receiver of a config,
//! directly (the daemon need not run), and says what each answered.

use anyhow::Context;
use crispen::daemon::config::Config;
use crispen::notify::{wire, Event, EventKind};
use std::path::PathBuf;
use std::process::ExitCode;

#[derive(Debug, clap::Args)]
pub(crate) struct Args {
    #[command(subcommand)]
    pub command: NotifyCommand,
}

#[derive(Debug, clap::Subcommand)]
pub(crate) enum NotifyCommand {
    /// Send a test event to every receiver and show what each answered
    Test {
        /// The daemon's config file (its [[notify]] tables)
        #[arg(long, short)]
        config: PathBuf,
    },
}

pub fn run(args: Args) -> anyhow::Result<ExitCode> {
    let NotifyCommand::Test { config } = args.command;
    let config = Config::load(&config)?;
    if config.notify.receivers.is_empty() {
        anyhow::bail!(
            "{}: no [[notify]] table: nothing to test",
            config.source.display()
        );
    }
    let runtime = tokio::runtime::Builder::new_current_thread()
        .enable_all()
        .build()
        .context("cannot start the async runtime")?;
    let now = std::time::SystemTime::now()
        .duration_since(std::time::UNIX_EPOCH)
        .map_or(0.0, |d| d.as_secs_f64());
    let mut failed = 0;
    for receiver in &config.notify.receivers {
        let mut event = Event::new(EventKind::Test, now, &config.farm.host);
        event.reason = Some(format!(
            "sent by `crispen notify test` to receiver {}",
            receiver.name
        ));
        event.link = config.notify.dashboard.clone();
        let answer = runtime.block_on(wire::send(receiver, &event));
        let shown = match &answer {
            Ok(a) => {
                let body = a.body.trim();
                let body: String = body.chars().take(300).collect();
                let verdict = if a.ok() { "ok" } else { "FAILED" };
                format!("{verdict}: HTTP {} {}", a.status, body.escape_debug())
            }
            Err(e) => format!("FAILED: {e}"),
        };
        if !answer.as_ref().is_ok_and(|a| a.ok()) {
            failed += 1;
        }
        println!("{} ({}): {shown}", receiver.name, receiver.url.text);
    }
    Ok(if failed == 0 {
        ExitCode::SUCCESS
    } else {
        ExitCode::FAILURE
    })
}
