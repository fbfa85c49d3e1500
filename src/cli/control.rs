//! `crispen status|clear|cancel|pause|resume|retry|release`: clients of the daemon's HTTP API on its
//! control socket (`crispen::http`; no key there: the socket's file mode decides). The
//! socket is found through the same `--config` the daemon was started with (or the
//! built-in default).
//!
//! The client is hyper's HTTP/1.1 connection over the unix socket: the daemon's server
//! is hyper already, so this adds only its client half (two tiny crates), and chunked
//! answers, `Connection` handling and status lines are parsed by the same well-tested
//! code on both sides. The answer is read up to [`MAX_ANSWER_BYTES`] within
//! [`ANSWER_TIMEOUT`].

use anyhow::Context;
use axum::body::Bytes;
use crispen::daemon::config::Config;
use crispen::daemon::control::Status;
use crispen::percent::percent_encode;
use http_body_util::{BodyExt, Empty, Limited};
use hyper::{Method, Request, StatusCode};
use hyper_util::rt::TokioIo;
use std::path::{Path, PathBuf};
use std::process::ExitCode;
use std::time::Duration;

/// Largest answer read (the status of a big farm with a long history is far smaller).
const MAX_ANSWER_BYTES: usize = 64 * 1024 * 1024;
/// The daemon answers within this or the command gives up.
const ANSWER_TIMEOUT: Duration = Duration::from_secs(60);

#[derive(Debug, clap::Args)]
pub(crate) struct StatusArgs {
    /// The daemon's config file (to find its control socket)
    #[arg(long, short)]
    pub config: Option<PathBuf>,
    /// Print the status as JSON (every job and printer has a lower-case `state`)
    #[arg(long)]
    pub json: bool,
}

#[derive(Debug, clap::Args)]
pub(crate) struct HistoryArgs {
    /// The daemon's config file (to find its control socket)
    #[arg(long, short)]
    pub config: Option<PathBuf>,
    /// How many jobs to show, newest first (1 to 1000)
    #[arg(long, default_value_t = 50)]
    pub limit: usize,
    /// Show jobs older than this one's sequence number (the `next` a page ends with)
    #[arg(long)]
    pub before: Option<u64>,
    /// Print the page as JSON
    #[arg(long, conflicts_with = "csv")]
    pub json: bool,
    /// Print every job the filters take as CSV (the export; --limit is each read's size)
    #[arg(long)]
    pub csv: bool,
    /// Only jobs printed on this printer
    #[arg(long)]
    pub printer: Option<String>,
    /// Only jobs from this hot folder (its name or path)
    #[arg(long)]
    pub folder: Option<String>,
    /// Only jobs that ended so: done, failed or cancelled
    #[arg(long)]
    pub state: Option<String>,
    /// Only jobs that ended at or after this (YYYY-MM-DD in UTC, or seconds since the epoch)
    #[arg(long)]
    pub since: Option<String>,
    /// Only jobs that ended before this
    #[arg(long)]
    pub until: Option<String>,
}

impl HistoryArgs {
    /// The filters as a query string (`&key=value...`).
    pub(crate) fn filters(&self) -> String {
        let mut q = String::new();
        for (key, value) in [
            ("printer", &self.printer),
            ("folder", &self.folder),
            ("state", &self.state),
            ("since", &self.since),
            ("until", &self.until),
        ] {
            if let Some(v) = value {
                q.push_str(&format!("&{key}={}", percent_encode(v)));
            }
        }
        q
    }
}

#[derive(Debug, clap::Args)]
pub(crate) struct PrinterArgs {
    /// Printer name, as in the config's [[printer]] name
    pub printer: String,
    /// The daemon's config file (to find its control socket)
    #[arg(long, short)]
    pub config: Option<PathBuf>,
}

#[derive(Debug, clap::Args)]
pub(crate) struct ClearArgs {
    /// Printer name, as in the config's [[printer]] name
    pub printer: String,
    /// Also take the camera's picture of the empty bed now as the reference its bed check
    /// compares with (replacing the one it has)
    #[arg(long)]
    pub reference: bool,
    /// The daemon's config file (to find its control socket)
    #[arg(long, short)]
    pub config: Option<PathBuf>,
}

#[derive(Debug, clap::Args)]
pub(crate) struct JobArgs {
    /// Job id, as shown by `crispen status`
    pub job: String,
    /// The daemon's config file (to find its control socket)
    #[arg(long, short)]
    pub config: Option<PathBuf>,
}

#[derive(Debug, clap::Args)]
pub(crate) struct CancelArgs {
    /// Job id, as shown by `crispen status`
    pub job: String,
    /// Cancel only this part of the job's plate, by its name or its number from 1 (as
    /// `crispen status --json` and the job page list them); the others print on
    #[arg(long, conflicts_with = "copy")]
    pub part: Option<String>,
    /// Of a job with copies, cancel only copy N (`crispen status` shows each copy's
    /// number); without it every copy still active is cancelled
    #[arg(long, value_parser = clap::value_parser!(u32).range(1..=1000))]
    pub copy: Option<u32>,
    /// The daemon's config file (to find its control socket)
    #[arg(long, short)]
    pub config: Option<PathBuf>,
}

#[derive(Debug, clap::Args)]
pub(crate) struct RetryArgs {
    /// Job id, as shown by `crispen status`
    pub job: String,
    /// Of a job with copies, retry only copy N (the others stand); without it every copy
    /// that failed, was cancelled or interrupted is retried
    #[arg(long, value_parser = clap::value_parser!(u32).range(1..=1000))]
    pub copy: Option<u32>,
    /// The daemon's config file (to find its control socket)
    #[arg(long, short)]
    pub config: Option<PathBuf>,
}

/// Sends one request to the daemon; returns the JSON answer of a success, or the
/// daemon's error message as the error.
pub(crate) fn ask(
    config: &Option<PathBuf>,
    method: Method,
    path: &str,
) -> anyhow::Result<serde_json::Value> {
    let (socket, body) = ask_raw(config, method, path)?;
    serde_json::from_slice(&body).with_context(|| {
        format!(
            "control socket {}: the answer is not JSON",
            socket.display()
        )
    })
}

/// Sends one GET to the daemon; returns the body of a success as text (a CSV export),
/// or the daemon's error message as the error.
pub(crate) fn ask_text(config: &Option<PathBuf>, path: &str) -> anyhow::Result<String> {
    let (_, body) = ask_raw(config, Method::GET, path)?;
    String::from_utf8(body.to_vec()).context("the daemon's answer is not UTF-8")
}

/// One request on the control socket of `config`: the socket and the body of a
/// success; a refusal becomes the daemon's own message (its JSON `error`).
fn ask_raw(
    config: &Option<PathBuf>,
    method: Method,
    path: &str,
) -> anyhow::Result<(PathBuf, Bytes)> {
    let socket = match config {
        Some(path) => Config::socket_of(path)?,
        None => Config::builtin_default().socket,
    };
    let runtime = tokio::runtime::Builder::new_current_thread()
        .enable_all()
        .build()
        .context("cannot start the async runtime")?;
    let (status, body) = runtime
        .block_on(async {
            tokio::time::timeout(ANSWER_TIMEOUT, exchange_raw(&socket, method, path)).await
        })
        .map_err(|_| {
            anyhow::anyhow!(
                "control socket {}: no answer within {} s",
                socket.display(),
                ANSWER_TIMEOUT.as_secs()
            )
        })??;
    if status.is_success() {
        return Ok((socket, body));
    }
    let answer: serde_json::Value = serde_json::from_slice(&body).unwrap_or_default();
    match answer["error"].as_str() {
        Some(message) => anyhow::bail!("{message}"),
        None => anyhow::bail!("the daemon refused: HTTP {status}"),
    }
}

async fn exchange_raw(
    socket: &Path,
    method: Method,
    path: &str,
) -> anyhow::Result<(StatusCode, Bytes)> {
    let stream = tokio::net::UnixStream::connect(socket).await.with_context(|| {
        format!(
            "cannot reach the daemon at {} (hint: is `crispen run` running with the same --config?)",
            socket.display()
        )
    })?;
    let broken = || format!("control socket {}", socket.display());
    let (mut sender, connection) = hyper::client::conn::http1::handshake(TokioIo::new(stream))
        .await
        .with_context(broken)?;
    tokio::spawn(connection);
    let request = Request::builder()
        .method(method)
        .uri(path)
        .header(hyper::header::HOST, "localhost")
        .body(Empty::<Bytes>::new())
        .context("the request")?;
    let response = sender.send_request(request).await.with_context(broken)?;
    let status = response.status();
    let body = Limited::new(response.into_body(), MAX_ANSWER_BYTES)
        .collect()
        .await
        .map_err(|e| anyhow::anyhow!("{}: the answer broke off: {e}", broken()))?
        .to_bytes();
    Ok((status, body))
}

/// A command's answer: its message on stdout.
fn act(config: &Option<PathBuf>, path: String) -> anyhow::Result<ExitCode> {
    let answer = ask(config, Method::POST, &path)?;
    if let Some(message) = answer["message"].as_str() {
        println!("{message}");
    }
    Ok(ExitCode::SUCCESS)
}

pub(crate) fn status(a: StatusArgs) -> anyhow::Result<ExitCode> {
    let answer = ask(&a.config, Method::GET, "/api/v1/status")?;
    if a.json {
        println!("{}", serde_json::to_string_pretty(&answer)?);
        return Ok(ExitCode::SUCCESS);
    }
    let status: Status =
        serde_json::from_value(answer).context("the daemon's status is not as expected")?;
    if let Some(farm) = &status.farm {
        let hosts: Vec<String> = farm
            .hosts
            .iter()
            .map(|h| format!("{}{}", h.name, if h.alive { "" } else { " (offline)" }))
            .collect();
        println!("farm: this host {}; hosts: {}", farm.host, hosts.join(", "));
        if let Some(e) = &farm.database {
            println!("{e}: prints go on, nothing new is taken until it answers");
        }
        println!();
    }
    println!("PRINTER          STATE            JOB                          HOTEND      BED        PROGRESS");
    for p in &status.printers {
        let state = serde_json::to_value(p.state)?;
        let temps = |cur: Option<f64>, target: Option<f64>| match (cur, target) {
            (Some(c), Some(t)) => format!("{c:.0}/{t:.0}C"),
            (Some(c), None) => format!("{c:.0}C"),
            _ => "-".into(),
        };
        let (hotend, bed) = match &p.temperatures {
            Some(t) => (
                temps(t.hotend_c, t.hotend_target_c),
                temps(t.bed_c, t.bed_target_c),
            ),
            None => ("-".into(), "-".into()),
        };
        let progress = match &p.progress {
            Some(l) => {
                if l.lines_total > 0 {
                    format!(
                        "{:.1}% ({}/{} lines){}",
                        100.0 * l.lines_acked as f64 / l.lines_total as f64,
                        l.lines_acked,
                        l.lines_total,
                        l.time_left
                            .map(|t| format!(", {}", time_left_words(&t)))
                            .unwrap_or_default()
                    )
                } else {
                    "-".into()
                }
            }
            None => "-".into(),
        };
        let state = match (&p.host, p.offline) {
            (_, true) => "offline".to_string(),
            _ => state.as_str().unwrap_or("?").to_string(),
        };
        println!(
            "{:<16} {:<16} {:<28} {:<11} {:<10} {}{}{}",
            p.name,
            state,
            p.job.as_deref().unwrap_or("-"),
            hotend,
            bed,
            progress,
            p.detail
                .as_deref()
                .map(|d| format!("  ({})", crispen::daemon::hotfolder::escaped(d)))
                .unwrap_or_default(),
            p.host
                .as_deref()
                .map(|h| format!("  [{h}]"))
                .unwrap_or_default()
        );
        use crispen::daemon::bed::Bed;
        match &p.bed {
            _ if p.bed_cleared => {}
            Bed::Waiting { why: None } => println!(
                "{:<16} bed not cleared: remove the print, then `crispen clear {}`",
                "", p.name
            ),
            bed => println!(
                "{:<16} bed {}: {}",
                "",
                bed.name().replace('_', " "),
                crispen::daemon::hotfolder::escaped(&bed.describe().unwrap_or_default())
            ),
        }
        if let Some(check) = &p.last_check {
            println!("{:<16} last bed check: {}", "", check.verdict.summary());
        }
        for t in p.maintenance.iter().filter(|t| t.due) {
            let reached: Vec<String> = t
                .intervals
                .iter()
                .filter(|i| i.reached())
                .map(ToString::to_string)
                .collect();
            println!(
                "{:<16} maintenance due: {} ({}){}",
                "",
                crispen::names::escaped(&t.task),
                reached.join(", "),
                if t.block {
                    ", takes no job until done"
                } else {
                    ""
                }
            );
        }
    }
    println!();
    println!("JOB                          STATE        PRINTER          FILE / REASON");
    // Names and reasons are the daemon's report of files anyone could name: shown
    // escaped, so a name cannot drive the terminal.
    use crispen::daemon::hotfolder::{escaped, printable};
    for j in &status.jobs {
        let file = printable(&j.file);
        let extra = match (&j.reason, &j.step, &j.progress) {
            (Some(r), _, _) => format!("{file}: {}", escaped(r)),
            (None, Some(step), _) => format!("{file} [{}]", escaped(step)),
            (None, None, Some(l)) if l.lines_total > 0 => format!(
                "{file} [{:.1}%]",
                100.0 * l.lines_acked as f64 / l.lines_total as f64
            ),
            _ => file,
        };
        let extra = match &j.copy {
            Some(c) => format!("{extra} (copy {} of {}, {})", c.n, j.copies, c.job),
            None => extra,
        };
        let state = if j.held {
            format!("{} (held)", j.state.name())
        } else {
            j.state.name().to_string()
        };
        println!(
            "{:<28} {:<12} {:<16} {}",
            j.id,
            state,
            j.printer.as_deref().unwrap_or("-"),
            extra
        );
        if let Some(parts) = j.parts.as_ref().filter(|p| !p.cancelled.is_empty()) {
            let names: Vec<String> = parts.cancelled.iter().map(|n| printable(n)).collect();
            println!(
                "{:<28} {} of {} parts on the plate; cancelled: {}",
                "",
                parts.total - parts.cancelled.len().min(parts.total),
                parts.total,
                names.join(", ")
            );
        }
        if let Some(copies) = &j.copies_status {
            println!("{:<28} copies: {copies}", "");
        }
        // Why a ready job waits, under it.
        if let Some(why) = &j.waiting {
            println!("{:<28} {}", "", escaped(why));
        }
    }
    Ok(ExitCode::SUCCESS)
}

/// A print's time left with what it rests on: "12 min left (planned with the printer's
/// settings, × 1.04 by 3 prints)".
fn time_left_words(t: &crispen::daemon::time_left::TimeLeft) -> String {
    use crispen::daemon::time_left::Settings;
    let pace = match t.pace.prints {
        0 => String::new(),
        1 => format!(", × {:.2} by 1 print", t.pace.factor),
        n => format!(", × {:.2} by {n} prints", t.pace.factor),
    };
    let settings = match t.settings {
        Settings::Printer => "the printer's settings",
        Settings::Stock => "stock settings",
    };
    let heating = if t.heating { " + heat-up" } else { "" };
    format!(
        "{:.0} min left{heating} (planned with {settings}{pace})",
        t.seconds() / 60.0
    )
}

/// `crispen history`: a page of the finished jobs that have left the queue.
pub(crate) fn history(a: HistoryArgs) -> anyhow::Result<ExitCode> {
    let mut path = format!("/api/v1/history?limit={}{}", a.limit, a.filters());
    if let Some(before) = a.before {
        path.push_str(&format!("&before={before}"));
    }
    if a.csv {
        path.push_str("&format=csv");
        print!("{}", ask_text(&a.config, &path)?);
        return Ok(ExitCode::SUCCESS);
    }
    let answer = ask(&a.config, Method::GET, &path)?;
    if a.json {
        println!("{}", serde_json::to_string_pretty(&answer)?);
        return Ok(ExitCode::SUCCESS);
    }
    let page: crispen::daemon::store::history::Page =
        serde_json::from_value(answer).context("the daemon's history is not as expected")?;
    use crispen::daemon::hotfolder::{escaped, printable};
    println!("JOB                          STATE        PRINTER          ENDED (UTC)       MATERIAL      COST FILE / REASON");
    for r in &page.jobs {
        let file = match &r.copy {
            Some(c) => format!("{} (copy {} of {})", printable(&r.file), c.n, c.job),
            None => printable(&r.file),
        };
        let extra = match &r.reason {
            Some(reason) => format!("{file}: {}", escaped(reason)),
            None => file,
        };
        println!(
            "{:<28} {:<12} {:<16} {:<17} {:<8} {:>9} {}",
            r.id,
            r.state.name(),
            r.printer.as_deref().unwrap_or("-"),
            crispen::calendar::utc_minute(r.ended_at),
            r.material.as_deref().map_or_else(|| "-".into(), printable),
            r.cost.map_or_else(|| "-".into(), |c| format!("{c:.2}")),
            extra
        );
    }
    match page.next {
        Some(next) => println!("older: crispen history --before {next}"),
        None if page.jobs.is_empty() => println!("(no finished job has left the queue yet)"),
        None => {}
    }
    Ok(ExitCode::SUCCESS)
}

pub(crate) fn clear(a: ClearArgs) -> anyhow::Result<ExitCode> {
    let mut path = printer_path(&a.printer, "clear");
    if a.reference {
        path.push_str("?reference=true");
    }
    act(&a.config, path)
}
pub(crate) fn cancel(a: CancelArgs) -> anyhow::Result<ExitCode> {
    match &a.part {
        Some(part) => act(
            &a.config,
            format!(
                "/api/v1/jobs/{}/parts/{}/cancel",
                percent_encode(&a.job),
                percent_encode(part)
            ),
        ),
        None => act(&a.config, copy_path(&a.job, "cancel", a.copy)),
    }
}
pub(crate) fn pause(a: PrinterArgs) -> anyhow::Result<ExitCode> {
    act(&a.config, printer_path(&a.printer, "pause"))
}
pub(crate) fn resume(a: PrinterArgs) -> anyhow::Result<ExitCode> {
    act(&a.config, printer_path(&a.printer, "resume"))
}
pub(crate) fn retry(a: RetryArgs) -> anyhow::Result<ExitCode> {
    act(&a.config, copy_path(&a.job, "retry", a.copy))
}
pub(crate) fn release(a: JobArgs) -> anyhow::Result<ExitCode> {
    act(&a.config, job_path(&a.job, "release"))
}

fn printer_path(printer: &str, action: &str) -> String {
    format!("/api/v1/printers/{}/{action}", percent_encode(printer))
}

fn job_path(job: &str, action: &str) -> String {
    format!("/api/v1/jobs/{}/{action}", percent_encode(job))
}

/// A job action for one copy of a job (`copy`), or for all of them.
fn copy_path(job: &str, action: &str, copy: Option<u32>) -> String {
    match copy {
        Some(n) => format!("{}?copy={n}", job_path(job, action)),
        None => job_path(job, action),
    }
}
