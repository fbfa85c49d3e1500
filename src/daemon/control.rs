//! The farm's operations, shared by every way in: the status snapshot ([`status`]) and the
//! operator's commands ([`execute`]: clear, cancel, cancel a part of a plate, pause,
//! resume, retry, release), and the
//! control socket they are served on ([`bind`]). The socket speaks the same HTTP API as the
//! TCP listener (the `http` module); its file mode (0660: the service user and its group)
//! decides who may use it, so no key is asked there.
//! `crispen status|clear|cancel|pause|resume|retry|release` are its clients.

use super::done::Done;
use super::farm::{Farm, LiveProgress, PrintCommand, PrinterStatus};
use super::job::{DatabaseFailure, JobState, StoreError};
use super::store::JobChange;
use crate::daemon::store::InventoryChange;
use serde::{Deserialize, Serialize};
use std::os::unix::fs::PermissionsExt;
use std::path::{Path, PathBuf};
use std::sync::Arc;

/// What an operator may ask of the farm (`Release`: let a held job, `hold = true` in its
/// sidecar, be printed).
#[derive(Debug, Clone, PartialEq)]
pub(crate) enum Command {
    Clear {
        printer: String,
    },
    /// Cancel a job; of a job with copies, every copy still active, or copy `copy` only.
    Cancel {
        job: String,
        copy: Option<u32>,
    },
    /// Stop printing one part of the job's plate (its name, or its number from 1); the
    /// others print on. The last part cancels the job.
    CancelPart {
        job: String,
        part: String,
    },
    Pause {
        printer: String,
    },
    Resume {
        printer: String,
    },
    /// Put a finished job back; of a job with copies, every copy that failed, was
    /// cancelled or interrupted, or copy `copy` only (the others stand).
    Retry {
        job: String,
        copy: Option<u32>,
    },
    Release {
        job: String,
    },
    Load {
        printer: String,
        what: super::spools::Load,
    },
    Unload {
        printer: String,
    },
    AddSpool(super::spools::NewSpool),
    /// Record a printer's care: a `[[maintenance]]` task done, or the printer put into or
    /// taken out of maintenance by hand; `by` and `note` are kept with it.
    Care {
        printer: String,
        what: CareAsk,
        by: String,
        note: Option<String>,
    },
    /// Switch a printer with a `[printer.power]` switch on or off (off with `force`: even
    /// with a print still on its bed; never while it prints or is hot).
    Power {
        printer: String,
        on: bool,
        force: bool,
    },
}

/// What an operator records of a printer's care (see [`Command::Care`]).
#[derive(Debug, Clone, PartialEq)]
pub(crate) enum CareAsk {
    Done { task: String },
    Start,
    End,
}

#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct Status {
    /// This host's printers, then (in a shared farm) the other hosts'.
    pub printers: Vec<PrinterStatus>,
    pub jobs: Vec<JobStatus>,
    /// The farm shared through `[store]`; absent for a host with its own spool.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub farm: Option<FarmStatus>,
    /// The job store's version these jobs are of: how many changes its task has published
    /// since the daemon started (a printer's `looked_at` is one of these).
    #[serde(default)]
    pub version: u64,
}

/// The hosts of a shared farm, as this host sees them.
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct FarmStatus {
    /// This host.
    pub host: String,
    /// None while the farm database answers; else why it does not (the error).
    pub database: Option<String>,
    pub hosts: Vec<super::store::postgres::FarmHost>,
}

#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct JobStatus {
    pub id: String,
    pub file: String,
    pub folder: PathBuf,
    pub state: JobState,
    pub printer: Option<String>,
    pub reason: Option<String>,
    /// Preparation step, while preparing.
    pub step: Option<String>,
    /// Print progress, while printing.
    pub progress: Option<LiveProgress>,
    pub copies_done: u32,
    pub copies: u32,
    /// A copy of another job: which, and its number.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub copy: Option<super::job::CopyOf>,
    /// The job that asked for copies: how they stand, all of them.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub copies_status: Option<CopiesStatus>,
    pub updated: f64,
    /// Waits for the operator's release before a printer may take it.
    #[serde(default)]
    pub held: bool,
    /// What it asks of its printer.
    #[serde(
        default,
        skip_serializing_if = "crate::daemon::filament::Asks::is_empty"
    )]
    pub asks: crate::daemon::filament::Asks,
    /// Ready, but no printer can take it now: why ("waiting for PETG black ...").
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub waiting: Option<String>,
    /// Filament one print of it needs (on the machine of its report), in grams at the
    /// density of the material it asks, where crispen knows it ...
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub need_g: Option<f64>,
    /// ... else in metres of filament.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub need_m: Option<f64>,
    /// What its prints took, grams, and their cost where the spool's price is known
    /// ([`Job::used`](super::job::Job::used)).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub used_g: Option<f64>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub cost: Option<f64>,
    /// What the enhancement moved, in words (from its slicing report's figures).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub moved: Option<String>,
    /// A plate of several parts: how many, and those cancelled for its current print.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub parts: Option<PartsStatus>,
}

/// How the copies of a job stand ("3 of 6 printed, 2 printing on a, c, 1 waiting").
#[derive(Debug, Clone, Serialize, Deserialize, PartialEq)]
pub struct CopiesStatus {
    /// How many were asked for.
    pub total: u32,
    pub printed: u32,
    /// The printers printing one, by copy number.
    pub printing: Vec<String>,
    /// Not printed yet nor printing: waiting to be prepared or for a printer.
    pub waiting: u32,
    /// Failed, cancelled or interrupted (each may be retried alone).
    pub stopped: u32,
    /// Each copy's job, by number from 1 (those made so far).
    pub jobs: Vec<String>,
}

impl CopiesStatus {
    /// Of the job `first` that asked for copies, with the other copies among `jobs`.
    fn of(first: &super::job::Job, members: &[&super::job::Job]) -> Option<Self> {
        let total = first.copies_wanted();
        if first.copy.is_some() || total < 2 {
            return None;
        }
        let mut members = members.to_vec();
        members.sort_by_key(|j| j.copy_number());
        let count = |states: &[JobState]| {
            members.iter().filter(|j| states.contains(&j.state)).count() as u32
        };
        // A job of an older crispen printed its copies one after another: those count.
        let printed = count(&[JobState::Done]) + first.copies_done.saturating_sub(1);
        let stopped = count(&[JobState::Failed, JobState::Cancelled, JobState::Interrupted]);
        let printing: Vec<String> = members
            .iter()
            .filter(|j| j.state == JobState::Printing)
            .map(|j| j.printer.clone().unwrap_or_default())
            .collect();
        let settled = printed + stopped + printing.len() as u32;
        Some(CopiesStatus {
            total,
            printed,
            waiting: total.saturating_sub(settled),
            stopped,
            printing,
            jobs: members.iter().map(|j| j.id.clone()).collect(),
        })
    }
}

impl std::fmt::Display for CopiesStatus {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "{} of {} printed", self.printed, self.total)?;
        if !self.printing.is_empty() {
            write!(
                f,
                ", {} printing on {}",
                self.printing.len(),
                self.printing.join(", ")
            )?;
        }
        if self.waiting > 0 {
            write!(f, ", {} waiting", self.waiting)?;
        }
        if self.stopped > 0 {
            write!(f, ", {} stopped (retry one with --copy N)", self.stopped)?;
        }
        Ok(())
    }
}

/// A plate's parts, as status shows them.
#[derive(Debug, Clone, Serialize, Deserialize, PartialEq)]
pub struct PartsStatus {
    pub total: usize,
    /// By name, in the order they were cancelled.
    pub cancelled: Vec<String>,
}

impl PartsStatus {
    fn of(job: &super::job::Job) -> Option<Self> {
        let total = job.part_names().len();
        (total > 1).then(|| PartsStatus {
            total,
            cancelled: job
                .parts_cancelled_in(job.shown_print())
                .map(|c| c.part.clone())
                .collect(),
        })
    }
}

/// Why a command was refused; the operator sees the message.
#[derive(Debug, thiserror::Error)]
pub(crate) enum CommandError {
    #[error("no printer {0:?} (hint: `crispen status` lists the printers)")]
    NoPrinter(String),
    #[error("{0} is not printing")]
    NotPrinting(String),
    #[error("{0}: the print just ended")]
    PrintEnded(String),
    #[error("job {id} is {state}; only active jobs can be cancelled")]
    NotActive { id: String, state: JobState },
    #[error("{0} is running its eject sequence; wait until it ends (its bed then waits for you if it must)")]
    Ejecting(String),
    #[error("job {0} is not held; it prints once ready")]
    NotHeld(String),
    #[error("job {id} has no parts to cancel one of: its G-code labels none{}", if *.prepared { "" } else { " yet (it is not prepared)" })]
    NoParts { id: String, prepared: bool },
    #[error("job {id} has no part {part:?} (its parts: {names})")]
    NoSuchPart {
        id: String,
        part: String,
        names: String,
    },
    /// The job store could not write the change (a full disk, the farm database down):
    /// what stays as it was, and what to do. The server's path is in the log, never in
    /// the answer.
    #[error("{undone}: {why}; {stays} (hint: {fix}, then {again})", fix = why.fix())]
    NotWritten {
        undone: String,
        why: Unwritable,
        stays: String,
        again: String,
    },
    #[error("job {0}: its directory in the spool was removed; the job failed")]
    DirectoryGone(String),
    #[error("no maintenance task {task:?} for printer {printer} (its tasks: {tasks}; see [[maintenance]] in the config)")]
    NoSuchTask {
        printer: String,
        task: String,
        tasks: String,
    },
    #[error("job {id} has no copy {copy} (its copies: {copies})")]
    NoSuchCopy {
        id: String,
        copy: u32,
        copies: String,
    },
    #[error("{0}")]
    BadCareNote(String),
    #[error("{0}")]
    Power(String),
    #[error(transparent)]
    Store(#[from] StoreError),
}

/// Why a command's change could not be written.
#[derive(Debug)]
pub enum Unwritable {
    /// The spool's disk (full, most often).
    Spool(String),
    /// The farm database could not be reached.
    Database(String),
}

impl std::fmt::Display for Unwritable {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            Unwritable::Spool(cause) => write!(f, "the spool could not be written ({cause})"),
            Unwritable::Database(cause) => write!(f, "{cause}"),
        }
    }
}

impl Unwritable {
    fn fix(&self) -> &'static str {
        match self {
            Unwritable::Spool(_) => "free space on the spool's disk",
            Unwritable::Database(_) => "check that PostgreSQL runs and [store] postgres reaches it",
        }
    }
}

impl CommandError {
    /// The printer or job named does not exist (as opposed to: it cannot do that now).
    pub(crate) fn is_not_found(&self) -> bool {
        matches!(
            self,
            CommandError::NoPrinter(_)
                | CommandError::NoSuchPart { .. }
                | CommandError::NoSuchTask { .. }
                | CommandError::NoSuchCopy { .. }
                | CommandError::Store(StoreError::NoSuchJob(_))
                | CommandError::Store(StoreError::Filament(
                    super::filament::FilamentError::NoSuchSpool(_)
                ))
        )
    }

    /// The change could not be written now (a full disk, the farm database down): the
    /// same command may succeed later, unchanged.
    pub(crate) fn is_unavailable(&self) -> bool {
        matches!(self, CommandError::NotWritten { .. })
    }
}

pub use super::error::ControlError;

/// Builds the status snapshot.
pub(crate) fn status(farm: &Farm) -> Status {
    let mut printers = farm.local_printers();
    let preparing = farm.preparation_steps();
    let store = farm.store();
    let shared = farm.shared();
    let farm_status = farm.db.get().map(|db| {
        let view = shared.clone().unwrap_or_default();
        FarmStatus {
            host: db.host().to_string(),
            database: view.database,
            hosts: view.hosts,
        }
    });
    if let Some(view) = shared {
        printers.extend(view.printers);
    }
    let config = farm.config();
    let names: Vec<&str> = config.printers.iter().map(|p| p.name.as_str()).collect();
    let offers = super::farm::offers(&config, &store, &names);
    let mut groups: std::collections::HashMap<&str, Vec<&super::job::Job>> = Default::default();
    for j in store.jobs() {
        groups.entry(j.group()).or_default().push(j);
    }
    let jobs = store
        .jobs()
        .map(|j| (j, first_need(j)))
        .map(|(j, need)| JobStatus {
            id: j.id.clone(),
            file: j.file.clone(),
            folder: j.folder.clone(),
            state: j.state,
            printer: j.printer.clone(),
            reason: j.reason.clone(),
            step: (j.state == JobState::Preparing)
                .then(|| preparing.get(&j.id).cloned())
                .flatten(),
            progress: (j.state == JobState::Printing)
                .then(|| {
                    printers
                        .iter()
                        .find(|p| p.job.as_deref() == Some(j.id.as_str()))
                        .and_then(|p| p.progress.clone())
                })
                .flatten(),
            copies_done: j.copies_done,
            copies: j.copies_wanted(),
            copy: j.copy.clone(),
            copies_status: CopiesStatus::of(j, groups.get(j.id.as_str()).map_or(&[], |g| g)),
            updated: j.history.last().map(|h| h.1).unwrap_or(0.0),
            held: j.held(),
            asks: j.asks.clone(),
            // Worded here, at the edge: the routing's reasons are data.
            waiting: super::farm::waiting(&config, j, &offers).map(|w| w.to_string()),
            need_g: need.and_then(|n| n.g),
            need_m: need.filter(|n| n.g.is_none()).map(|n| n.mm / 1000.0),
            used_g: j.used().grams,
            cost: j.used().cost,
            moved: j.slice_report.as_ref().map(|r| r.moved().to_string()),
            parts: PartsStatus::of(j),
        })
        .collect();
    Status {
        printers,
        jobs,
        farm: farm_status,
        version: store.version(),
    }
}

/// What one print of `job` needs on the machine of its report (its first).
fn first_need(job: &super::job::Job) -> Option<super::filament::Need> {
    job.need_on(&job.slice_report.as_ref()?.machine)
}

/// Carries out one command; the answer says what was done, or what was not and why.
pub(crate) async fn execute(farm: &Arc<Farm>, command: Command) -> Result<Done, CommandError> {
    let asked = command.clone();
    run(farm, command)
        .await
        .map_err(|e| for_clients(farm, &asked, e))
}

async fn run(farm: &Arc<Farm>, command: Command) -> Result<Done, CommandError> {
    match command {
        Command::Clear { printer } => clear(farm, &printer).await,
        Command::Pause { printer } => send_print_command(farm, &printer, PrintCommand::Pause).await,
        Command::Resume { printer } => {
            send_print_command(farm, &printer, PrintCommand::Resume).await
        }
        Command::Cancel { job, copy } => each_copy(farm, &job, copy, Op::Cancel).await,
        Command::CancelPart { job, part } => cancel_part(farm, &job, &part).await,
        Command::Retry { job, copy } => each_copy(farm, &job, copy, Op::Retry).await,
        Command::Release { job } => each_copy(farm, &job, None, Op::Release).await,
        Command::Load { printer, what } => {
            known_printer(farm, &printer)?;
            Ok(super::spools::load(farm, &printer, what).await?)
        }
        Command::Unload { printer } => {
            known_printer(farm, &printer)?;
            Ok(super::spools::unload(farm, &printer).await?)
        }
        Command::AddSpool(new) => Ok(super::spools::add(farm, new).await?),
        Command::Care {
            printer,
            what,
            by,
            note,
        } => care(farm, &printer, what, by, note).await,
        Command::Power { printer, on, force } => power(farm, &printer, on, force).await,
    }
}

/// Asks a printer's supervisor to switch it (see [`Command::Power`]); between prints
/// only, as it answers within [`POWER_ANSWER`](super::farm::POWER_ANSWER).
async fn power(farm: &Farm, printer: &str, on: bool, force: bool) -> Result<Done, CommandError> {
    use super::farm::{PowerRequest, PrinterState, POWER_ANSWER};
    let handle = match known_printer(farm, printer)? {
        Whose::Mine => farm
            .printer(printer)
            .ok_or_else(|| CommandError::NoPrinter(printer.into()))?,
        Whose::Other => {
            return Err(CommandError::Power(format!(
                "{printer} is another host's printer: switch it on its host"
            )))
        }
    };
    if !farm
        .config()
        .printers
        .iter()
        .any(|p| p.name == printer && p.power.is_some())
    {
        return Err(CommandError::Power(format!(
            "{printer} has no [printer.power] switch"
        )));
    }
    let state = handle.live.borrow().state;
    let busy = state.has_print_under_way()
        || matches!(
            state,
            PrinterState::WaitingToHeat | PrinterState::Ejecting | PrinterState::CheckingBed
        );
    if busy {
        return Err(CommandError::Power(format!(
            "{printer} is busy ({state:?}); it is switched between prints only"
        )));
    }
    let (reply, answer) = tokio::sync::oneshot::channel();
    let request = PowerRequest {
        on,
        force,
        asked: std::time::Instant::now(),
        reply,
    };
    handle.power.try_send(request).map_err(|_| {
        CommandError::Power(format!("{printer}: other power requests wait; ask again"))
    })?;
    match tokio::time::timeout(POWER_ANSWER, answer).await {
        Ok(Ok(Ok(changed))) => Ok(Done::Switched {
            printer: printer.into(),
            on,
            already: !changed,
        }),
        Ok(Ok(Err(why))) => Err(CommandError::Power(format!("{printer}: {why}"))),
        Ok(Err(_)) => Err(CommandError::Power(format!(
            "{printer}: its supervisor stopped"
        ))),
        Err(_) => Err(CommandError::Power(format!(
            "{printer}: no answer within {} s (it may have started a print); nothing was switched",
            POWER_ANSWER.as_secs()
        ))),
    }
}

/// Records a printer's care (see [`Command::Care`]): the task must be one of the
/// printer's, `by` and `note` within their bounds.
async fn care(
    farm: &Farm,
    printer: &str,
    what: CareAsk,
    by: String,
    note: Option<String>,
) -> Result<Done, CommandError> {
    use super::care::{CareChange, Work, BY_CHARS, NOTE_CHARS};
    known_printer(farm, printer)?;
    let bounded = |what: &str, text: &str, max: usize| {
        if let Some(problem) = crate::names::problem(text) {
            return Err(CommandError::BadCareNote(format!("the {what} {problem}")));
        }
        if text.trim().is_empty() || text.chars().count() > max {
            return Err(CommandError::BadCareNote(format!(
                "the {what} must be 1 to {max} characters"
            )));
        }
        Ok(())
    };
    bounded("name of who did it", &by, BY_CHARS)?;
    if let Some(note) = &note {
        bounded("note", note, NOTE_CHARS)?;
    }
    let work = Work {
        at_s: super::job::now_s(),
        by: by.trim().to_string(),
        note: note.map(|n| n.trim().to_string()),
    };
    let (change, done) = match what {
        CareAsk::Done { task } => {
            let config = farm.config();
            let tasks: Vec<&str> = config.tasks_of(printer).map(|t| t.name.as_str()).collect();
            if !tasks.contains(&task.as_str()) {
                return Err(CommandError::NoSuchTask {
                    printer: printer.to_string(),
                    task,
                    tasks: if tasks.is_empty() {
                        "none".into()
                    } else {
                        tasks.join(", ")
                    },
                });
            }
            let done = Done::Serviced {
                printer: printer.to_string(),
                task: task.clone(),
            };
            (CareChange::Done { task, work }, done)
        }
        CareAsk::Start => (
            CareChange::Hold(work),
            Done::InMaintenance {
                printer: printer.to_string(),
                now: true,
            },
        ),
        CareAsk::End => (
            CareChange::Release(work),
            Done::InMaintenance {
                printer: printer.to_string(),
                now: false,
            },
        ),
    };
    farm.jobs()
        .edit_inventory(InventoryChange::Care {
            printer: printer.to_string(),
            change,
        })
        .await?;
    Ok(done)
}

/// A command's error as its client is told it: a store error naming a file of the spool
/// (the disk full, a job's directory removed), or the farm database unreachable, says
/// what did not happen and what stays as it was; a file is named in the log (with the
/// printer or job), not to the client. Every change the store could not write is one it
/// did not make: a clear, a cancel, a retry, a release, a spool's change (a print's end
/// and the bed gate it closes are kept and written later, but no command makes those).
fn for_clients(farm: &Farm, command: &Command, e: CommandError) -> CommandError {
    let (printer, job) = match command {
        Command::Cancel { job, .. }
        | Command::CancelPart { job, .. }
        | Command::Retry { job, .. }
        | Command::Release { job } => ("-", job.as_str()),
        Command::Clear { printer }
        | Command::Pause { printer }
        | Command::Resume { printer }
        | Command::Load { printer, .. }
        | Command::Unload { printer }
        | Command::Care { printer, .. }
        | Command::Power { printer, .. } => (printer.as_str(), "-"),
        Command::AddSpool(_) => ("-", "-"),
    };
    // Why, and the spool's file it could not write (for the log only).
    let (why, file) = match e {
        CommandError::Store(StoreError::Io {
            path,
            action,
            source,
        }) => (Unwritable::Spool(source.to_string()), Some((path, action))),
        CommandError::Store(StoreError::Database {
            failure: DatabaseFailure::Outage,
            message,
        }) => (Unwritable::Database(message), None),
        CommandError::Store(StoreError::DirectoryGone { id, dir }) => {
            tracing::error!(job = %id, dir = %dir.display(), "the job's directory was removed; the job failed");
            return CommandError::DirectoryGone(id);
        }
        e => return e,
    };
    let state_of = |id: &str| farm.store().get(id).map_or("unknown", |j| j.state.name());
    // What was not done, what stays as it was, and what to do once it can be written.
    let (undone, stays, again) = match command {
        Command::Clear { printer } => (
            format!("{printer}: the bed is not marked clear"),
            "the printer takes no job until it is".to_string(),
            format!("`crispen clear {printer}` again"),
        ),
        Command::Cancel { job, .. } => (
            format!("job {job} is not cancelled"),
            format!("it stays {}", state_of(job)),
            "cancel it again".to_string(),
        ),
        Command::CancelPart { job, part } => (
            format!("job {job}: part {part:?} is not cancelled"),
            format!("it prints on, {}", state_of(job)),
            "cancel the part again".to_string(),
        ),
        Command::Retry { job, .. } => (
            format!("job {job} is not retried"),
            format!("it stays {}", state_of(job)),
            "retry it again".to_string(),
        ),
        Command::Release { job } => (
            format!("job {job} is not released"),
            format!("it stays {} and held", state_of(job)),
            "release it again".to_string(),
        ),
        Command::Load { printer, .. } | Command::Unload { printer } => (
            format!("{printer}: its spool is not changed"),
            "it holds what it held".to_string(),
            "load or unload it again".to_string(),
        ),
        Command::AddSpool(_) => (
            "the spool is not added".to_string(),
            "the farm's spools are as they were".to_string(),
            "add it again".to_string(),
        ),
        Command::Pause { printer } | Command::Resume { printer } => (
            format!("{printer}: not done"),
            "nothing changed".to_string(),
            "ask again".to_string(),
        ),
        Command::Power { printer, .. } => (
            format!("{printer}: not switched"),
            "its switch is as it was".to_string(),
            "ask again".to_string(),
        ),
        Command::Care { printer, .. } => (
            format!("{printer}: its maintenance is not recorded"),
            "its care record is as it was".to_string(),
            "record it again".to_string(),
        ),
    };
    match &file {
        Some((path, action)) => {
            tracing::error!(printer = %printer, job = %job, file = %path.display(), action, error = %why, "{undone}: the spool could not be written")
        }
        None => {
            tracing::error!(printer = %printer, job = %job, error = %why, "{undone}: the farm database could not be reached")
        }
    }
    CommandError::NotWritten {
        undone,
        why,
        stays,
        again,
    }
}

/// A command that applies to each copy of a job (see [`Command::Cancel`]).
#[derive(Clone, Copy)]
enum Op {
    Cancel,
    Retry,
    Release,
}

/// The copies of job `id` a command is for, by number: copy `copy` of its job's copies;
/// else, for the job that asked for copies, every one of them; else the job alone.
fn copies_for(
    farm: &Farm,
    id: &str,
    copy: Option<u32>,
) -> Result<Vec<(u32, String)>, CommandError> {
    let store = farm.store();
    let job = store
        .get(id)
        .ok_or_else(|| StoreError::NoSuchJob(id.to_string()))?;
    let mut members: Vec<(u32, String)> = store
        .jobs()
        .filter(|j| j.group() == job.group())
        .map(|j| (j.copy_number(), j.id.clone()))
        .collect();
    members.sort();
    match copy {
        Some(n) => members
            .iter()
            .find(|(m, _)| *m == n)
            .map(|m| vec![m.clone()])
            .ok_or_else(|| CommandError::NoSuchCopy {
                id: id.to_string(),
                copy: n,
                copies: members
                    .iter()
                    .map(|(m, _)| m.to_string())
                    .collect::<Vec<_>>()
                    .join(", "),
            }),
        None if job.copy.is_none() && members.len() > 1 => Ok(members),
        None => Ok(vec![(job.copy_number(), id.to_string())]),
    }
}

/// Carries `op` out on each of the copies [`copies_for`] names. A copy it does not apply
/// to (a cancel of a finished one, a retry of a printed one) is passed over; when it
/// applies to none, the first one's refusal is the answer.
async fn each_copy(
    farm: &Arc<Farm>,
    id: &str,
    copy: Option<u32>,
    op: Op,
) -> Result<Done, CommandError> {
    let members = copies_for(farm, id, copy)?;
    if let [(_, only)] = members.as_slice() {
        return one(farm, only, op).await;
    }
    let mut each = Vec::new();
    let mut first_refusal = None;
    for (n, member) in members {
        match one(farm, &member, op).await {
            Ok(done) => each.push((n, done)),
            Err(
                e @ (CommandError::NotActive { .. }
                | CommandError::NotHeld(_)
                | CommandError::Store(StoreError::WrongState { .. })),
            ) => {
                first_refusal.get_or_insert(e);
            }
            Err(e) if each.is_empty() => return Err(e),
            // Some copies changed already: the answer says which, and the log why the
            // rest did not.
            Err(e) => {
                tracing::warn!(job = %member, error = %e, "a copy's command failed; the copies before it were changed");
                break;
            }
        }
    }
    match first_refusal {
        Some(e) if each.is_empty() => Err(e),
        _ => Ok(Done::Copies {
            job: id.to_string(),
            each,
        }),
    }
}

/// `op` on one job.
async fn one(farm: &Arc<Farm>, id: &str, op: Op) -> Result<Done, CommandError> {
    match op {
        Op::Cancel => cancel(farm, id).await,
        Op::Release => release(farm, id).await,
        Op::Retry => {
            let retried = farm.jobs().retry(id).await?;
            Ok(Done::Retried {
                ready: retried.state == JobState::Ready,
                held: retried.held(),
                job: id.to_string(),
            })
        }
    }
}

/// Releases a held job, checked and changed as one step of the store (a cancel between a
/// check and the change would otherwise leave a cancelled job released for a retry).
async fn release(farm: &Farm, id: &str) -> Result<Done, CommandError> {
    // A job not prepared yet has not had its sidecar read into it (the preparation does
    // that): whether it is held is in the sidecar file in its directory. Released now, it
    // stays released when the preparation reads the sidecar.
    let sidecar_file = {
        let store = farm.store();
        store
            .get(id)
            .filter(|j| j.sidecar_unread())
            .map(|j| store.job_dir(id).join(format!("{}.toml", j.file)))
    };
    let held_on_disk = match sidecar_file {
        None => false,
        Some(path) => {
            let read = tokio::task::spawn_blocking(move || super::job::read_sidecar(&path)).await;
            matches!(read, Ok(Ok(Some(s))) if s.hold == Some(true))
        }
    };
    let released = farm
        .jobs()
        .update(id, JobChange::Release { held_on_disk })
        .await?;
    let job = released.job;
    if !released.applied {
        return Err(match job.sidecar.as_ref().and_then(|s| s.hold) {
            Some(true) if !job.released => CommandError::Store(StoreError::WrongState {
                id: id.to_string(),
                state: job.state,
                action: "release",
                allowed:
                    "queued, preparing or ready (retry it first; it stays held until released)",
            }),
            _ => CommandError::NotHeld(id.to_string()),
        });
    }
    tracing::info!(job = id, "held job released");
    Ok(Done::Released {
        job: id.to_string(),
        ready: job.state == JobState::Ready,
    })
}

/// Every printer's name: this host's, then (in a shared farm) the other hosts'.
pub(crate) fn printer_names(farm: &Farm) -> Vec<String> {
    let mut names: Vec<String> = farm.local_printers().into_iter().map(|p| p.name).collect();
    if let Some(view) = farm.shared() {
        names.extend(view.printers.into_iter().map(|p| p.name));
    }
    names
}

/// Where a printer named in a command is attached.
enum Whose {
    Mine,
    /// Another host's, in a shared farm.
    Other,
}

fn known_printer(farm: &Farm, printer: &str) -> Result<Whose, CommandError> {
    if farm.printer(printer).is_some() {
        Ok(Whose::Mine)
    } else if printer_names(farm).iter().any(|n| n == printer) {
        Ok(Whose::Other)
    } else {
        Err(CommandError::NoPrinter(printer.to_string()))
    }
}

async fn clear(farm: &Farm, printer: &str) -> Result<Done, CommandError> {
    known_printer(farm, printer)?;
    match farm.jobs().clear_gate(printer).await {
        Ok(cleared) => Ok(Done::Cleared {
            printer: printer.to_string(),
            already: !cleared,
        }),
        // The one state a person's clear cannot end: the printer is moving.
        Err(StoreError::BedChange { .. }) => Err(CommandError::Ejecting(printer.to_string())),
        Err(e) => Err(e.into()),
    }
}

/// Pauses, resumes or cancels a printer's print: here, or through the farm database by
/// the printer's own host.
pub(crate) async fn send_print_command(
    farm: &Farm,
    printer: &str,
    command: PrintCommand,
) -> Result<Done, CommandError> {
    if let Whose::Other = known_printer(farm, printer)? {
        let db = farm
            .db
            .get()
            .ok_or(CommandError::NoPrinter(printer.to_string()))?;
        if !db
            .push_command(printer, &command)
            .await
            .map_err(|e| CommandError::Store(e.into()))?
        {
            return Err(CommandError::NoPrinter(printer.to_string()));
        }
        tracing::info!(
            printer,
            ?command,
            "print command left for the printer's host"
        );
        return Ok(Done::Sent {
            printer: printer.to_string(),
            command,
            to_its_host: true,
        });
    }
    let tx = farm.printer(printer).and_then(|p| p.print.borrow().clone());
    let Some(tx) = tx else {
        return Err(CommandError::NotPrinting(printer.to_string()));
    };
    tx.send(command.clone())
        .await
        .map_err(|_| CommandError::PrintEnded(printer.to_string()))?;
    tracing::info!(printer, ?command, "print command sent");
    Ok(Done::Sent {
        printer: printer.to_string(),
        command,
        to_its_host: false,
    })
}

async fn cancel(farm: &Arc<Farm>, id: &str) -> Result<Done, CommandError> {
    // Checked and changed as one step of the store: a printer claiming the job between
    // the two would otherwise print a job marked cancelled.
    const NOT_STARTED: &[JobState] = &[JobState::Queued, JobState::Preparing, JobState::Ready];
    let reason = Some("cancelled by the operator".into());
    let cancelled = farm
        .jobs()
        .transition_from(
            id,
            NOT_STARTED,
            JobState::Cancelled,
            reason,
            JobChange::Nothing,
        )
        .await;
    match cancelled {
        Ok(_) => {
            // A slicer already running for it is stopped, not left to finish unwanted.
            farm.cancel_preparation(id);
            Ok(Done::Cancelled {
                job: id.to_string(),
            })
        }
        Err(StoreError::StateChanged {
            state: JobState::Printing,
            ..
        }) => {
            let printer = farm
                .store()
                .get(id)
                .and_then(|j| j.printer.clone())
                .unwrap_or_default();
            send_print_command(farm, &printer, PrintCommand::Cancel).await?;
            Ok(Done::Stopping {
                job: id.to_string(),
                printer,
            })
        }
        Err(StoreError::StateChanged { state, .. }) => Err(CommandError::NotActive {
            id: id.to_string(),
            state,
        }),
        Err(e) => Err(e.into()),
    }
}

/// Cancels a part of a job's plate: on the printer printing it (the others print on; its
/// supervisor records where it was dropped), or, before the job prints, in the job's record
/// (the print drops it from its first line). The last part cancels the job.
async fn cancel_part(farm: &Arc<Farm>, id: &str, part: &str) -> Result<Done, CommandError> {
    let job = farm
        .store()
        .get(id)
        .cloned()
        .ok_or_else(|| StoreError::NoSuchJob(id.to_string()))?;
    let names = job.part_names();
    if names.is_empty() {
        return Err(CommandError::NoParts {
            id: id.to_string(),
            prepared: job.slice_report.is_some(),
        });
    }
    let name = names
        .iter()
        .position(|n| *n == part)
        .or_else(|| {
            let n: usize = part.trim().parse().ok()?;
            (1..=names.len()).contains(&n).then(|| n - 1)
        })
        .map(|i| names[i].to_string())
        .ok_or_else(|| CommandError::NoSuchPart {
            id: id.to_string(),
            part: part.to_string(),
            names: names
                .iter()
                .enumerate()
                .map(|(i, n)| format!("{} {n:?}", i + 1))
                .collect::<Vec<_>>()
                .join(", "),
        })?;
    if job.state == JobState::Printing {
        let printer = job.printer.clone().unwrap_or_default();
        send_print_command(farm, &printer, PrintCommand::CancelPart(name.clone())).await?;
        return Ok(Done::PartDropped {
            job: id.to_string(),
            part: name,
            printer,
        });
    }
    // Checked and changed as one step of the store: a printer claiming the job between a
    // check and the change would print it with the part. The job it returns is as the
    // change left it: ready, the part recorded; anything else, nothing changed.
    let every = names.len();
    let change = JobChange::CancelPart {
        part: name.clone(),
        at_s: super::job::now_s(),
    };
    let job = farm.jobs().update(id, change).await?.job;
    if job.state != JobState::Ready {
        return match job.state {
            // A printer took it meanwhile: the printer drops it.
            JobState::Printing => Box::pin(cancel_part(farm, id, &name)).await,
            state => Err(CommandError::Store(StoreError::WrongState {
                id: id.to_string(),
                state,
                action: "cancelling a part",
                allowed: "ready or printing",
            })),
        };
    }
    tracing::info!(job = id, part = %name, "part of the plate cancelled before its print");
    let last = job.parts_cancelled_in(job.print_number()).count() >= every;
    if last {
        cancel(farm, id).await?;
    }
    Ok(Done::PartCancelled {
        job: id.to_string(),
        part: name,
        last,
    })
}

/// Binds the control socket with mode 0660. An existing socket nobody answers on (left by
/// a daemon that was killed) is replaced; anything else at the path is left alone and
/// refused, so a mistyped `[control] socket` can never remove a file.
pub(crate) fn bind(socket: &Path) -> Result<tokio::net::UnixListener, ControlError> {
    use std::os::unix::fs::FileTypeExt;
    let io = |source| ControlError {
        socket: socket.to_path_buf(),
        source,
    };
    if let Some(dir) = socket.parent() {
        std::fs::create_dir_all(dir).map_err(io)?;
    }
    match std::fs::symlink_metadata(socket) {
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => {}
        Err(e) => return Err(io(e)),
        Ok(meta) if !meta.file_type().is_socket() => {
            return Err(io(std::io::Error::new(
                std::io::ErrorKind::AlreadyExists,
                "the path exists and is not a socket; it is left alone (hint: use another [control] socket)",
            )))
        }
        Ok(_) => {
            if std::os::unix::net::UnixStream::connect(socket).is_ok() {
                return Err(io(std::io::Error::new(
                    std::io::ErrorKind::AddrInUse,
                    "another daemon is listening here (hint: stop it, or use another [control] socket)",
                )));
            }
            std::fs::remove_file(socket).map_err(io)?;
        }
    }
    let listener = tokio::net::UnixListener::bind(socket).map_err(io)?;
    std::fs::set_permissions(socket, std::fs::Permissions::from_mode(0o660)).map_err(io)?;
    Ok(listener)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::daemon::doubles::{farm_config, open_farm, ready_job};
    use crate::daemon::farm::{printer_channels, PrinterLive};

    /// Makes every later write of `file` fail, as a full disk would: its temporary name
    /// is taken by a directory.
    fn block(file: &Path) -> PathBuf {
        let blocker = crate::fsutil::temp_path(file);
        std::fs::create_dir_all(&blocker).unwrap();
        blocker
    }

    /// A command whose change the store cannot write says what did not happen, what
    /// stays as it was and what to do, never a server path (the log has it), with 503's
    /// test; and it did not happen, then or once writing works again. `crispen clear`
    /// once answered `spool /abs/.../.crispen-tmp-printers.json: write: No space left on
    /// device`, and the clear took effect when space came back.
    #[tokio::test]
    async fn a_change_that_cannot_be_written_says_so_without_a_path() {
        let tmp = tempfile::tempdir().unwrap();
        let (farm, owners) = open_farm(farm_config(tmp.path(), &["p1"], ""));
        let (_owner, handle) = printer_channels(PrinterLive::connecting("marlin2", "/dev/x"));
        owners.printers.add("p1", handle);
        farm.jobs().close_gate("p1", "0001-a").await.unwrap();
        let job = ready_job(&farm, "b.stl", "G28\n").await;
        let spool = farm.config().spool_dir.clone();
        let blockers = [
            block(&spool.join("printers.json")),
            block(&spool.join("filament.json")),
            block(&farm.store().job_dir(&job).join("job.json")),
        ];
        let new_spool = crate::daemon::spools::NewSpool {
            material: "PLA".into(),
            colour: "white".into(),
            grams: 750.0,
            ..Default::default()
        };
        let cases = [
            (
                Command::Clear {
                    printer: "p1".into(),
                },
                "p1: the bed is not marked clear",
                "the printer takes no job until it is",
            ),
            (
                Command::Cancel {
                    job: job.clone(),
                    copy: None,
                },
                &*format!("job {job} is not cancelled"),
                "it stays ready",
            ),
            (
                Command::Load {
                    printer: "p1".into(),
                    what: crate::daemon::spools::Load::New(new_spool.clone()),
                },
                "p1: its spool is not changed",
                "it holds what it held",
            ),
            (
                Command::AddSpool(new_spool),
                "the spool is not added",
                "the farm's spools are as they were",
            ),
        ];
        for (command, undone, stays) in cases {
            let e = execute(&farm, command.clone()).await.unwrap_err();
            assert!(e.is_unavailable() && !e.is_not_found(), "{command:?}: {e}");
            let text = e.to_string();
            for said in [
                undone,
                stays,
                "the spool could not be written",
                "free space",
            ] {
                assert!(
                    text.contains(said),
                    "{command:?}: {text}\n(expected {said})"
                );
            }
            assert!(
                !text.contains(&spool.display().to_string())
                    && !text.contains(crate::fsutil::TEMP_PREFIX)
                    && !text.contains('/'),
                "{command:?}: a path in {text}"
            );
        }
        let nothing_changed = |farm: &Farm| {
            let store = farm.store();
            assert!(store.gate("p1").bed_not_cleared());
            assert_eq!(store.get(&job).unwrap().state, JobState::Ready);
            assert!(store.inventory().spools.is_empty());
            assert_eq!(store.inventory().spool_on("p1"), None);
        };
        nothing_changed(&farm);
        for blocker in blockers {
            std::fs::remove_dir(blocker).unwrap();
        }
        assert_eq!(farm.jobs().write_pending().await.unwrap(), 0);
        nothing_changed(&farm);
        let gates: serde_json::Value =
            serde_json::from_slice(&std::fs::read(spool.join("printers.json")).unwrap()).unwrap();
        assert_eq!(gates["p1"]["bed_not_cleared"], true);
        let said = execute(
            &farm,
            Command::Clear {
                printer: "p1".into(),
            },
        )
        .await
        .unwrap();
        assert_eq!(
            said,
            Done::Cleared {
                printer: "p1".into(),
                already: false
            }
        );
    }
}
