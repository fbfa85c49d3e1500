//! What a command did, as figures for the one who asked: each way in (the HTTP API, the
//! dashboard, the OctoPrint endpoints, the CLI through the socket) shows it where it
//! answers, with [`Done`]'s `Display` as the sentence an operator reads.

use crate::daemon::farm::PrintCommand;

/// A command carried out.
#[derive(Debug, Clone, PartialEq)]
pub(crate) enum Done {
    /// The printer's bed is marked clear (`already`: it was).
    Cleared {
        printer: String,
        already: bool,
    },
    /// A pause, resume, cancel or part's cancel given to the printer's supervisor, or left
    /// in the farm database for the printer's own host.
    Sent {
        printer: String,
        command: PrintCommand,
        to_its_host: bool,
    },
    /// A job that had not begun printing is cancelled.
    Cancelled {
        job: String,
    },
    /// A printing job's print is being stopped safely.
    Stopping {
        job: String,
        printer: String,
    },
    /// A part of a printing job's plate is dropped by its printer.
    PartDropped {
        job: String,
        part: String,
        printer: String,
    },
    /// A part of a job's plate is cancelled before its print (`last`: it was the last part
    /// left, so the job is cancelled).
    PartCancelled {
        job: String,
        part: String,
        last: bool,
    },
    /// A finished job is back: `ready` to print again, or queued to be prepared; `held`
    /// until it is released.
    Retried {
        job: String,
        ready: bool,
        held: bool,
    },
    /// A held job is released: `ready` now, or once prepared.
    Released {
        job: String,
        ready: bool,
    },
    /// A spool is loaded on the printer (as `spool` describes it).
    Loaded {
        printer: String,
        spool: String,
    },
    Unloaded {
        printer: String,
    },
    SpoolAdded {
        id: String,
        grams: f64,
    },
    /// A `[[maintenance]]` task is recorded done on the printer: its counts start again.
    Serviced {
        printer: String,
        task: String,
    },
    /// The printer is put into maintenance by hand (`now`), or taken out of it.
    InMaintenance {
        printer: String,
        now: bool,
    },
    /// A command carried out on several copies of a job: each copy's number and what was
    /// done (copies it did not apply to are not named).
    Copies {
        job: String,
        each: Vec<(u32, Done)>,
    },
    /// The printer's switch is switched on or off (`already`: it was).
    Switched {
        printer: String,
        on: bool,
        already: bool,
    },
}

impl std::fmt::Display for Done {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            Done::Cleared {
                printer,
                already: false,
            } => write!(f, "{printer}: bed cleared; it may take the next job"),
            Done::Cleared {
                printer,
                already: true,
            } => write!(f, "{printer}: bed was already clear"),
            Done::Sent {
                printer,
                command,
                to_its_host,
            } => {
                write!(f, "{printer}: {command:?} sent")?;
                if *to_its_host {
                    f.write_str(" to its host")?;
                }
                Ok(())
            }
            Done::Cancelled { job } => write!(f, "job {job} cancelled"),
            Done::Stopping { job, printer } => {
                write!(f, "job {job}: stopping the print on {printer} (heaters off)")
            }
            Done::PartDropped { job, part, printer } => write!(
                f,
                "job {job}: part {part:?} is no longer printed on {printer}; the others print on"
            ),
            Done::PartCancelled {
                job,
                part,
                last: true,
            } => write!(
                f,
                "job {job}: part {part:?} cancelled; it was the last part left, so the job is cancelled"
            ),
            Done::PartCancelled {
                job,
                part,
                last: false,
            } => write!(
                f,
                "job {job}: part {part:?} will not be printed; the others will"
            ),
            Done::Retried { job, ready, held } => {
                match ready {
                    true => write!(f, "job {job} is ready to print again")?,
                    false => write!(f, "job {job} queued for preparation again")?,
                }
                if *held {
                    write!(f, "; it stays held until `crispen release {job}`")?;
                }
                Ok(())
            }
            Done::Released { job, ready: true } => {
                write!(f, "job {job} released; the next free printer takes it")
            }
            Done::Released { job, ready: false } => {
                write!(f, "job {job} released; it prints once ready")
            }
            Done::Loaded { printer, spool } => write!(f, "{printer}: loaded {spool}"),
            Done::Unloaded { printer } => write!(
                f,
                "{printer}: unloaded; it takes no job until a spool is loaded"
            ),
            Done::SpoolAdded { id, grams } => write!(f, "spool {id} added ({grams} g)"),
            Done::Serviced { printer, task } => write!(
                f,
                "{printer}: {task} recorded as done; its count starts again from now"
            ),
            Done::InMaintenance { printer, now: true } => write!(
                f,
                "{printer} is in maintenance: it finishes its print, then takes no job until `crispen maintenance end {printer}`"
            ),
            Done::InMaintenance {
                printer,
                now: false,
            } => write!(f, "{printer} is out of maintenance; it may take the next job"),
            Done::Copies { job, each } => {
                write!(f, "job {job}, {} copies: ", each.len())?;
                for (i, (n, done)) in each.iter().enumerate() {
                    if i > 0 {
                        f.write_str("; ")?;
                    }
                    write!(f, "copy {n}: {done}")?;
                }
                Ok(())
            }
            Done::Switched {
                printer,
                on,
                already,
            } => {
                let state = if *on { "on" } else { "off" };
                match already {
                    true => write!(f, "{printer} was already switched {state}"),
                    false if *on => write!(f, "{printer} switched on; it connects once it has booted"),
                    false => write!(f, "{printer} switched off; it is switched on again when it has work"),
                }
            }
        }
    }
}
