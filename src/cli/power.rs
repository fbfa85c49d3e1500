//! `crispen power PRINTER on|off [--force]`: switches a printer with a `[printer.power]`
//! switch between prints (off: only when it is cool; with a print still on its bed only
//! with `--force`). A client of the daemon's HTTP API on its control socket.

use super::control::ask;
use crispen::percent::percent_encode;
use hyper::Method;
use std::path::PathBuf;
use std::process::ExitCode;

#[derive(clap::Args, Debug)]
pub(crate) struct Args {
    /// Printer name, as in the config's [[printer]] name
    pub printer: String,
    /// `on` or `off`
    #[arg(value_parser = ["on", "off"])]
    pub switch: String,
    /// Off even with a finished print still on its bed (never while it is hot)
    #[arg(long)]
    pub force: bool,
    /// The daemon's config file (to find its control socket)
    #[arg(long, short)]
    pub config: Option<PathBuf>,
}

pub(crate) fn run(a: Args) -> anyhow::Result<ExitCode> {
    let mut path = format!(
        "/api/v1/printers/{}/power/{}",
        percent_encode(&a.printer),
        a.switch
    );
    if a.force {
        path.push_str("?force=true");
    }
    let answer = ask(&a.config, Method::POST, &path)?;
    println!("{}", answer["message"].as_str().unwrap_or_default());
    Ok(ExitCode::SUCCESS)
}
