//! A job and its life: [`JobState`] and its one table of legal changes
//! ([`JobState::can_go_to`]), the record every store keeps of a job ([`Job`]), its
//! [`Sidecar`] and how one is read (by the preparation and by the operator's `release`), a
//! printer's bed gate, and the errors of a job store. Where jobs are kept is the business
//! of the stores (`daemon::store`), which build on this module.
use serde::{Deserialize, Serialize};
use std::io::Read;
use std::path::{Path, PathBuf};
use std::time::{SystemTime, UNIX_EPOCH};

#[derive(Debug, thiserror::Error)]
pub enum StoreError {
    #[error("spool {path}: {action}: {source}")]
    Io {
        path: PathBuf,
        action: &'static str,
        #[source]
        source: std::io::Error,
    },
    #[error("spool {path}: unreadable job state: {message} (hint: the job directory is kept; fix or move it away and restart)")]
    Corrupt { path: PathBuf, message: String },
    #[error("no job {0:?} (hint: `crispen status` lists the jobs)")]
    NoSuchJob(String),
    #[error("spool {path} is in use by another crispen daemon (hint: stop it, or give this one another [spool] dir)")]
    Locked { path: PathBuf },
    #[error("job {id}: its directory {dir} was removed; the job failed")]
    DirectoryGone { id: String, dir: PathBuf },
    #[error(
        "{path}: not a regular file (symbolic links and other special files are not picked up)"
    )]
    NotAFile { path: PathBuf },
    #[error("job {id} cannot go from {from} to {to}")]
    IllegalTransition {
        id: String,
        from: JobState,
        to: JobState,
    },
    #[error("job {id} is {state} now, no longer {expected}")]
    StateChanged {
        id: String,
        state: JobState,
        expected: String,
    },
    #[error(
        "the job store has stopped (the daemon is shutting down, or the store failed; see the log)"
    )]
    Stopped,
    #[error("{message} (hint: check that PostgreSQL runs and [store] postgres reaches it; outcomes are kept and written once it is back)")]
    Database {
        failure: DatabaseFailure,
        message: String,
    },
    #[error("job {id} is no longer held by host {host} (its lease ran out and the farm moved it on: it is {state} now); the change was not recorded")]
    LostClaim {
        id: String,
        host: String,
        state: JobState,
    },
    #[error("{0}")]
    Filament(#[from] crate::daemon::filament::FilamentError),
    #[error("printer {printer}'s bed is {from}; it cannot go to {to} now")]
    BedChange {
        printer: String,
        from: &'static str,
        to: &'static str,
    },
    #[error("{path}: picked up by another host of the farm (the hot folder is shared); it leaves the folder with that host")]
    TakenElsewhere { path: PathBuf },
    #[error("job {id} is {state}; {action} needs it to be {allowed}")]
    WrongState {
        id: String,
        state: JobState,
        action: &'static str,
        allowed: &'static str,
    },
}

/// Why the farm database failed a request: the callers decide by it whether to wait for
/// it (keep an outcome, try a claim again) or report a fault.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum DatabaseFailure {
    /// It could not be reached, or the connection failed under the request.
    Outage,
    /// It answered with an error of its own, or with something this crispen cannot read.
    Other,
}

impl StoreError {
    /// The farm database could not be reached (as opposed to a change refused by the
    /// job's rules, or a fault).
    pub fn is_outage(&self) -> bool {
        matches!(
            self,
            StoreError::Database {
                failure: DatabaseFailure::Outage,
                ..
            }
        )
    }
}

#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum JobState {
    Queued,
    Preparing,
    Ready,
    Printing,
    Done,
    Failed,
    Cancelled,
    Interrupted,
}

impl JobState {
    pub(crate) const ALL: [JobState; 8] = [
        JobState::Queued,
        JobState::Preparing,
        JobState::Ready,
        JobState::Printing,
        JobState::Done,
        JobState::Failed,
        JobState::Cancelled,
        JobState::Interrupted,
    ];

    /// The one table of legal state changes; the store's `transition_with` refuses any
    /// other.
    /// A job is prepared once per retry and printed once per copy; `done` is final, so a
    /// finished job can never be offered for a reprint. Preparing goes back to queued only
    /// by the restart rules (preparation is redone); a job whose files vanished or whose
    /// state could not be read fails from wherever it waits.
    pub(crate) fn can_go_to(self, next: JobState) -> bool {
        use JobState::*;
        matches!(
            (self, next),
            (Queued, Preparing | Cancelled | Failed)
                | (Preparing, Ready | Failed | Cancelled | Queued)
                | (Ready, Printing | Cancelled | Failed)
                | (Printing, Done | Ready | Failed | Cancelled | Interrupted)
                | (Failed | Cancelled | Interrupted, Queued | Ready)
        )
    }

    pub fn name(self) -> &'static str {
        match self {
            JobState::Queued => "queued",
            JobState::Preparing => "preparing",
            JobState::Ready => "ready",
            JobState::Printing => "printing",
            JobState::Done => "done",
            JobState::Failed => "failed",
            JobState::Cancelled => "cancelled",
            JobState::Interrupted => "interrupted",
        }
    }
    /// Still has work ahead of it (the daemon is not idle while any job is active).
    pub(crate) fn is_active(self) -> bool {
        matches!(
            self,
            JobState::Queued | JobState::Preparing | JobState::Ready | JobState::Printing
        )
    }
}

impl std::fmt::Display for JobState {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(self.name())
    }
}

/// What a sidecar (`model.stl.toml`) may override for one model.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Sidecar {
    pub height_mm: Option<f64>,
    pub enhance: Option<bool>,
    pub strength: Option<toml::Value>,
    pub copies: Option<u32>,
    pub printer: Option<String>,
    /// One copy on each of these printers (copy N on the Nth), at the same time: what
    /// the dashboard's "send to printers" asks. Neither `copies` nor `printer` with it.
    pub printers: Option<Vec<String>>,
    /// Which of the model's axes points up: "z" or "y".
    pub up: Option<crate::mesh::place::UpAxis>,
    /// `hold = true`: prepare the job, but let no printer take it until the operator
    /// releases it (`crispen release JOB`); what an upload with `print=false` asks for.
    pub hold: Option<bool>,
    /// What the printer must hold (see `crate::daemon::filament`): these override the
    /// folder's.
    pub material: Option<String>,
    pub colour: Option<String>,
    pub nozzle_mm: Option<f64>,
    pub tags: Option<Vec<String>>,
    pub priority: Option<i32>,
    /// Copies of the model side by side on one bed (a plate): each a part that can be
    /// cancelled alone while the others print on.
    pub per_plate: Option<u32>,
}

/// Reads a sidecar file (`model.stl.toml`); unknown keys are an error.
pub(crate) fn read_sidecar(path: &Path) -> Result<Option<Sidecar>, String> {
    let file = match std::fs::File::open(path) {
        Ok(f) => f,
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => return Ok(None),
        Err(e) => return Err(format!("sidecar {}: cannot read: {e}", path.display())),
    };
    parse_sidecar(file, path).map(Some)
}

/// A sidecar holds a handful of short keys; anything bigger is not one.
pub(crate) const MAX_SIDECAR_BYTES: u64 = 16 * 1024;

/// Parses a sidecar from any reader; `path` names it in errors.
pub fn parse_sidecar(reader: impl Read, path: &Path) -> Result<Sidecar, String> {
    let mut text = String::new();
    reader
        .take(MAX_SIDECAR_BYTES + 1)
        .read_to_string(&mut text)
        .map_err(|e| format!("sidecar {}: cannot read: {e}", path.display()))?;
    if text.len() as u64 > MAX_SIDECAR_BYTES {
        return Err(format!(
            "sidecar {}: larger than {MAX_SIDECAR_BYTES} bytes; a sidecar holds a few keys",
            path.display()
        ));
    }
    let sidecar: Sidecar = toml::from_str(&text).map_err(|e| {
        format!(
            "sidecar {}: {} (allowed keys: height_mm, enhance, strength, up, copies, per_plate, printer, printers, hold, material, colour, nozzle_mm, tags, priority)",
            path.display(),
            e.message().trim()
        )
    })?;
    if let Some(h) = sidecar.height_mm {
        crate::daemon::config::check_height(h)
            .map_err(|m| format!("sidecar {}: key `height_mm`: {m}", path.display()))?;
    }
    if let Some(n) = sidecar.copies {
        crate::daemon::config::check_copies(n)
            .map_err(|m| format!("sidecar {}: key `copies`: {m}", path.display()))?;
    }
    if let Some(printers) = &sidecar.printers {
        use crate::daemon::config::MAX_COPIES;
        let problem = if sidecar.copies.is_some() || sidecar.printer.is_some() {
            Some(
                "one copy goes to each printer named: give neither `copies` nor `printer` with it"
                    .to_string(),
            )
        } else if printers.is_empty() || printers.len() > MAX_COPIES as usize {
            Some(format!("must name 1 to {MAX_COPIES} printers"))
        } else if let Some(problem) = printers.iter().find_map(|p| crate::names::problem(p)) {
            Some(problem.to_string())
        } else if (1..printers.len()).any(|i| printers[..i].contains(&printers[i])) {
            Some("names a printer twice (a printer prints one copy at a time)".to_string())
        } else {
            None
        };
        if let Some(problem) = problem {
            return Err(format!(
                "sidecar {}: key `printers`: {problem}",
                path.display()
            ));
        }
    }
    if let Some(n) = sidecar.per_plate {
        crate::daemon::config::check_per_plate(n)
            .map_err(|m| format!("sidecar {}: key `per_plate`: {m}", path.display()))?;
    }
    if let Some(s) = &sidecar.strength {
        crate::daemon::config::parse_strength(s)
            .map_err(|m| format!("sidecar {}: key `strength`: {m}", path.display()))?;
    }
    if let Some(problem) = sidecar.printer.as_deref().and_then(crate::names::problem) {
        return Err(format!(
            "sidecar {}: key `printer`: {problem}",
            path.display()
        ));
    }
    crate::daemon::filament::routing::check_asks(
        sidecar.material.as_deref(),
        sidecar.colour.as_deref(),
        sidecar.nozzle_mm,
        sidecar.tags.as_deref(),
        sidecar.priority,
    )
    .map_err(|(key, m)| format!("sidecar {}: key `{key}`: {m}", path.display()))?;
    Ok(sidecar)
}

/// One job as persisted in `job.json`.
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct Job {
    pub id: String,
    /// Sequence number: the order jobs were picked up in (oldest first).
    pub seq: u64,
    /// The dropped file's name; the model is `<job dir>/<file>`.
    pub file: String,
    /// The hot folder it was dropped into.
    pub folder: PathBuf,
    pub state: JobState,
    /// Seconds since the epoch of each state change: (state, time).
    pub history: Vec<(JobState, f64)>,
    pub printer: Option<String>,
    pub reason: Option<String>,
    pub sidecar: Option<Sidecar>,
    /// Prints of it finished whole: 0 or 1 (a job prints once; its copies are jobs of
    /// their own, [`Job::copy`]). A job of an older crispen printed its copies one after
    /// another and counted them here.
    #[serde(default)]
    pub copies_done: u32,
    /// A copy of another job (its sidecar asked for `copies`): which job, and which copy.
    /// The job that asked is copy 1 itself; copies 2 to N are made, each a job of its own
    /// with the first one's G-code, when it is ready ([`Job::copies_due`]).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub copy: Option<CopyOf>,
    /// How many copies of it were made (the first job of copies only): they are made once.
    #[serde(default, skip_serializing_if = "is_zero")]
    pub copies_made: u32,
    pub slice_report: Option<crate::slice::SliceReport>,
    pub print_report: Option<PrintReport>,
    /// Per machine that may print it: its G-code, or why it cannot (see
    /// `crate::daemon::prepare`). Empty for jobs prepared before machines existed, whose
    /// `<file>.gcode` was made for an Ultimaker 2.
    #[serde(default, skip_serializing_if = "std::collections::BTreeMap::is_empty")]
    pub machines: std::collections::BTreeMap<String, ForMachine>,
    /// The operator released a job its sidecar holds (see [`Job::held`]). Kept through a
    /// retry: a released job is printed when it is ready again, a held one is not.
    #[serde(default)]
    pub released: bool,
    /// Where a job of a farm shared by several hosts came from (None in a host's own
    /// spool, whose folders are all in its config).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub origin: Option<Origin>,
    /// The wall comparison of an enhanced job (its G-code against the unmodified model's,
    /// sliced the same way), measured after the job is ready; its figures go into the slice
    /// report's `walls`. None for a job with nothing to compare (printed unmodified,
    /// pre-sliced, or prepared before the comparison was deferred).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub comparison: Option<Comparison>,
    /// What it asks of its printer (material, colour, nozzle, group, priority), set when
    /// it is prepared from its folder and sidecar.
    #[serde(
        default,
        skip_serializing_if = "crate::daemon::filament::Asks::is_empty"
    )]
    pub asks: crate::daemon::filament::Asks,
    /// What each of its prints took from a spool, recorded with the print's outcome (the
    /// spools' ledgers are brought up to date from these, once each).
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub uses: Vec<JobUse>,
    /// The parts of its plate the operator cancelled, per print, in order (see
    /// `crate::marlin::plate`).
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub parts_cancelled: Vec<PartCancel>,
    /// How its prints were cleared off the bed by machine: each eject and camera check, in
    /// order (see `daemon::bed`).
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub clearing: Vec<super::bed::Clearing>,
    /// Filament one print needs, per machine it has G-code for (the net push of that
    /// G-code, as a print of it is booked), set when it is prepared.
    #[serde(default, skip_serializing_if = "std::collections::BTreeMap::is_empty")]
    pub needs: std::collections::BTreeMap<String, crate::daemon::filament::Need>,
}

fn is_zero(n: &u32) -> bool {
    *n == 0
}

/// Which copy of which job a job is (see [`Job::copy`]).
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
pub struct CopyOf {
    /// The job that asked for the copies: copy 1.
    pub job: String,
    /// This one's number, from 2.
    pub n: u32,
}

/// A part of a job's plate the operator cancelled: the rest of the plate prints on.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct PartCancel {
    /// The part's name, as its G-code labels it (the slice report's `parts`).
    pub part: String,
    /// The print of the job it was cancelled for, from 1 (see [`Job::print_number`]).
    pub print: u32,
    /// When it was asked for (seconds since the epoch).
    pub at_s: f64,
    /// Where the print dropped it; None while not known (cancelled before the print began:
    /// dropped from its first line; or asked for and not yet carried out).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub dropped: Option<Dropped>,
}

/// Where a print dropped a cancelled part.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Dropped {
    /// The G-code's command (0-based, comments and blank lines not counted) it was dropped
    /// from, and that command's line in the file (1-based).
    pub command: usize,
    pub line: usize,
    /// The layer that command is in (from 1) and its Z, mm.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub layer: Option<usize>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub z_mm: Option<f64>,
}

/// What one print of a job took from the spool on its printer.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct JobUse {
    /// The use's key in the spool's ledger (`<job>#<n>`).
    pub key: String,
    /// The spool it came from; None: no spool was recorded on the printer.
    pub spool: Option<String>,
    pub printer: String,
    pub material: String,
    pub colour: String,
    pub grams: f64,
    pub mm: f64,
    /// grams × the spool's price per kg; None: its price is not known.
    pub cost: Option<f64>,
    pub at_s: f64,
    /// Seconds the print took, from its start to its end (0 in records made before it was
    /// kept): the printer's care counts its hours by it.
    #[serde(default)]
    pub print_s: f64,
    /// The print failed (a cancel, a stop or a daemon killed during it is no failure).
    #[serde(default)]
    pub failed: bool,
}

impl JobUse {
    /// The `material` and `colour` of a use on a printer whose filament was not known:
    /// its `grams` are 0 for want of a density, not because nothing was pushed.
    pub const UNKNOWN: &'static str = "unknown";

    /// Its `grams` are a weight (the printer's filament was known).
    pub fn weighed(&self) -> bool {
        self.material != JobUse::UNKNOWN
    }
}

/// What a job's prints took from spools, summed from its weighed uses ([`Job::used`]).
#[derive(Debug, Clone, Default, PartialEq)]
pub struct Used {
    /// The first weighed print's.
    pub material: Option<String>,
    /// None: no print was weighed.
    pub grams: Option<f64>,
    /// The prints whose spool's price is known (a print without one adds nothing);
    /// None: no price was known.
    pub cost: Option<f64>,
}

/// Where a job's wall comparison is. It is a measurement, never part of the job: the job
/// is printable without it, and one that cannot be made is shown as not measured.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case", tag = "state")]
pub enum Comparison {
    /// Waits for a moment when no job is being prepared or waits to be; `tries` counts
    /// the runs started (a run the daemon's stop cut short leaves it pending).
    Pending { tries: u32 },
    /// Measured (the figures are the slice report's `walls`): when it started and how long
    /// it took, seconds.
    Done { started_s: f64, took_s: f64 },
    /// Not measured, and not tried again: why.
    NotMeasured { reason: String },
}

/// The host whose hot folder a farm job was dropped into, and that folder's rule as it
/// was then: hosts without the folder in their config still know which printers serve it.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Origin {
    pub host: String,
    pub printers: Vec<String>,
}

/// What preparation made of a job for one machine.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum ForMachine {
    /// Its G-code: a file in the job's directory.
    Gcode(String),
    /// Why this machine cannot print the job.
    Refused(String),
}

impl Job {
    /// Its sidecar is not read into it yet: that is its preparation's first step, so a
    /// job not prepared yet is held or not as the sidecar file in its directory says.
    pub(crate) fn sidecar_unread(&self) -> bool {
        self.sidecar.is_none() && matches!(self.state, JobState::Queued | JobState::Preparing)
    }

    /// Held: its sidecar says `hold = true` and the operator has not released it yet. A
    /// held job is prepared as usual; no printer claims it.
    pub(crate) fn held(&self) -> bool {
        !self.released && self.sidecar.as_ref().and_then(|s| s.hold) == Some(true)
    }

    /// The G-code file (in the job's directory) made for `machine`, if any.
    pub fn gcode_for(&self, machine: &str) -> Option<String> {
        if self.machines.is_empty() {
            // Prepared before machines existed: sliced for an Ultimaker 2.
            return (self.slice_report.is_some() && machine == "ultimaker2")
                .then(|| format!("{}.gcode", self.file));
        }
        match self.machines.get(machine)? {
            ForMachine::Gcode(file) => Some(file.clone()),
            ForMachine::Refused(_) => None,
        }
    }
}

/// What a print did, as kept with its job. The job's own type, not the streamer's: a
/// job's state must stay readable whatever the streamer reports next (a figure missing
/// from an older job reads as 0).
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
#[serde(default)]
pub struct PrintReport {
    /// The printer's device.
    pub port: PathBuf,
    pub lines_total: usize,
    pub lines_acked: usize,
    /// Lines written, including housekeeping and replays.
    pub lines_sent: u64,
    pub resends: u64,
    pub silence_probes: u64,
    /// Pieces of lines the printer answered on their own after a receive-buffer flush.
    pub fragments: u64,
    pub duration_s: f64,
    /// Its motion as planned and as it went, for its printer's pace (none for a print
    /// paused, or with a part cancelled).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub pace: Option<super::time_left::PaceSample>,
}

impl From<crate::marlin::stream::PrintReport> for PrintReport {
    fn from(r: crate::marlin::stream::PrintReport) -> PrintReport {
        PrintReport {
            port: r.port,
            lines_total: r.lines_total,
            lines_acked: r.lines_acked,
            lines_sent: r.lines_sent,
            resends: r.resends,
            silence_probes: r.silence_probes,
            fragments: r.fragments,
            duration_s: r.duration_s,
            pace: None,
        }
    }
}

impl Job {
    /// A job's id: its sequence number and its file's name in letters, digits, `-` and
    /// `_` (safe as a directory name and in a URL).
    pub fn make_id(seq: u64, file: &str) -> String {
        let stem: String = file
            .chars()
            .map(|c| {
                if c.is_ascii_alphanumeric() || c == '-' {
                    c
                } else {
                    '_'
                }
            })
            .take(40)
            .collect();
        format!("{seq:04}-{stem}")
    }

    /// A job just picked up: queued, with nothing prepared or printed yet.
    pub fn queued(id: String, seq: u64, file: String, folder: PathBuf) -> Job {
        Job {
            id,
            seq,
            file,
            folder,
            state: JobState::Queued,
            history: vec![(JobState::Queued, now_s())],
            printer: None,
            reason: None,
            sidecar: None,
            copies_done: 0,
            copy: None,
            copies_made: 0,
            slice_report: None,
            print_report: None,
            machines: Default::default(),
            released: false,
            origin: None,
            comparison: None,
            asks: Default::default(),
            uses: Vec::new(),
            parts_cancelled: Vec::new(),
            clearing: Vec::new(),
            needs: Default::default(),
        }
    }
}

impl Job {
    /// Filament one print of it needs on `machine`, when measured. A job prepared before
    /// needs were kept per machine has its first machine's length, told in metres.
    /// Parts of the plate cancelled before its next or running print began are not
    /// needed, so their share is left out; a part cancelled mid-print stays counted (what
    /// is left of it is not known without following the print, and too much booked is
    /// safer than too little).
    pub fn need_on(&self, machine: &str) -> Option<crate::daemon::filament::Need> {
        let need = if self.needs.is_empty() {
            let mm = self.slice_report.as_ref()?.filament_mm?;
            crate::daemon::filament::Need { mm, g: None }
        } else {
            *self.needs.get(machine)?
        };
        let left = 1.0 - self.share_cancelled_before_print();
        Some(crate::daemon::filament::Need {
            mm: need.mm * left,
            g: need.g.map(|g| g * left),
        })
    }

    /// The share of the plate's filament (as its report's G-code pushes it) in parts
    /// cancelled before the next or running print began, 0 to 1.
    fn share_cancelled_before_print(&self) -> f64 {
        let Some(report) = self.slice_report.as_ref() else {
            return 0.0;
        };
        let Some(total) = report.filament_mm.filter(|mm| *mm > 0.0) else {
            return 0.0;
        };
        let began = match self.state {
            JobState::Printing => self
                .history
                .iter()
                .rev()
                .find(|(s, _)| *s == JobState::Printing)
                .map_or(f64::INFINITY, |(_, at)| *at),
            _ => f64::INFINITY,
        };
        let dropped: f64 = self
            .parts_cancelled_in(self.print_number())
            .filter(|c| c.at_s <= began)
            .filter_map(|c| report.parts.iter().find(|p| p.name == c.part))
            .map(|p| p.extruded_mm)
            .sum();
        (dropped / total).clamp(0.0, 1.0)
    }

    /// What its prints took (each copy, and a print that failed or was cancelled as far
    /// as it got): the one sum of its uses, for its status, its history record and the
    /// statistics.
    pub fn used(&self) -> Used {
        let mut used = Used::default();
        for u in self.uses.iter().filter(|u| u.weighed()) {
            used.material.get_or_insert_with(|| u.material.clone());
            *used.grams.get_or_insert(0.0) += u.grams;
            if let Some(cost) = u.cost {
                *used.cost.get_or_insert(0.0) += cost;
            }
        }
        used
    }

    /// The print its next or running print is, from 1: how many times it went to a
    /// printer (its history's `printing` entries), the next one when it is not printing.
    pub fn print_number(&self) -> u32 {
        let started = self
            .history
            .iter()
            .filter(|(s, _)| *s == JobState::Printing)
            .count() as u32;
        if self.state == JobState::Printing {
            started.max(1)
        } else {
            started + 1
        }
    }

    /// The print a plate's cancelled parts are shown for: the running or next one while
    /// the job may still print, else its last.
    pub fn shown_print(&self) -> u32 {
        match self.state {
            JobState::Queued | JobState::Preparing | JobState::Ready | JobState::Printing => {
                self.print_number()
            }
            JobState::Done | JobState::Failed | JobState::Cancelled | JobState::Interrupted => {
                self.print_number().saturating_sub(1).max(1)
            }
        }
    }

    /// The parts cancelled for print `print`.
    pub fn parts_cancelled_in(&self, print: u32) -> impl Iterator<Item = &PartCancel> {
        self.parts_cancelled
            .iter()
            .filter(move |c| c.print == print)
    }

    /// The names of its plate's parts (empty: no plate labelled).
    pub fn part_names(&self) -> Vec<&str> {
        self.slice_report
            .as_ref()
            .map(|r| r.parts.iter().map(|p| p.name.as_str()).collect())
            .unwrap_or_default()
    }

    pub(crate) fn copies_wanted(&self) -> u32 {
        let Some(sidecar) = &self.sidecar else {
            return 1;
        };
        match &sidecar.printers {
            Some(printers) => printers.len() as u32,
            None => sidecar.copies.unwrap_or(1),
        }
        .max(1)
    }

    /// The one printer it may print on, if its sidecar names one: `printer`, or of
    /// `printers`, the one for its copy.
    pub fn wanted_printer(&self) -> Option<&str> {
        let sidecar = self.sidecar.as_ref()?;
        match &sidecar.printers {
            Some(printers) => printers
                .get(self.copy_number() as usize - 1)
                .map(String::as_str),
            None => sidecar.printer.as_deref(),
        }
    }

    /// The job its copies belong to: the one that asked for them (its own id when it is
    /// no copy).
    pub fn group(&self) -> &str {
        self.copy.as_ref().map_or(&self.id, |c| &c.job)
    }

    /// Which copy it is, from 1 (the job that asked for them is 1).
    pub fn copy_number(&self) -> u32 {
        self.copy.as_ref().map_or(1, |c| c.n)
    }

    /// The numbers of the copies still to be made of it: none until it is prepared (its
    /// copies take its G-code), none once made, and none of a copy. A job of an older
    /// crispen that printed some of its copies one after another makes only the rest.
    pub(crate) fn copies_due(&self) -> std::ops::Range<u32> {
        let prepared = matches!(
            self.state,
            JobState::Ready | JobState::Printing | JobState::Done
        );
        if self.copy.is_some() || self.copies_made > 0 || !prepared {
            return 0..0;
        }
        // It prints once more unless it is done; what it printed (one after another, an
        // older crispen's way) is not made again.
        let own = u32::from(self.state != JobState::Done);
        let first = (1 + own + self.copies_done).max(2);
        first..self.copies_wanted() + 1
    }

    /// Copy `n` of this job (see [`Job::copies_due`]): a ready job of its own, numbered
    /// `seq`, with this one's preparation (its G-code files are the caller's to give it),
    /// and nothing printed.
    pub(crate) fn copy_for(&self, n: u32, seq: u64) -> Job {
        let mut copy = Job::queued(
            Job::make_id(seq, &self.file),
            seq,
            self.file.clone(),
            self.folder.clone(),
        );
        copy.state = JobState::Ready;
        copy.history.push((JobState::Ready, now_s()));
        copy.copy = Some(CopyOf {
            job: self.id.clone(),
            n,
        });
        copy.sidecar = self.sidecar.clone();
        copy.released = self.released;
        copy.origin = self.origin.clone();
        copy.slice_report = self.slice_report.clone();
        copy.machines = self.machines.clone();
        copy.asks = self.asks.clone();
        copy.needs = self.needs.clone();
        // The same G-code: its wall comparison is the first job's, shared once made (see
        // `daemon::store::copies`), never measured again.
        copy.comparison = self.comparison.clone();
        copy
    }
}

pub fn now_s() -> f64 {
    SystemTime::now()
        .duration_since(UNIX_EPOCH)
        .map(|d| d.as_secs_f64())
        .unwrap_or(0.0)
}

/// Persisted per-printer state that must survive a restart: its bed (see
/// [`super::bed`]) and the last job printed on it.
#[derive(Debug, Clone, Default, Serialize, Deserialize, PartialEq)]
#[serde(from = "GateFile", into = "GateFile")]
pub struct PrinterGate {
    pub bed: super::bed::Bed,
    pub last_job: Option<String>,
    /// The camera's last check of the bed, whatever it answered.
    pub last_check: Option<super::bed::CheckRecord>,
}

impl PrinterGate {
    /// A print ended (or was interrupted) and the bed is not known clear since: the
    /// printer takes no job.
    pub fn bed_not_cleared(&self) -> bool {
        !self.bed.is_clear()
    }

    /// The gate after a print of `job` that leaves the bed `bed`.
    pub(crate) fn after_print(&self, job: &str, bed: super::bed::Bed) -> PrinterGate {
        PrinterGate {
            bed,
            last_job: Some(job.to_string()),
            last_check: self.last_check.clone(),
        }
    }
}

/// A gate as written (`printers.json`, the farm database): `bed_not_cleared` as before
/// beds had states, so a gate written before reads as waiting or clear.
#[derive(Serialize, Deserialize)]
struct GateFile {
    bed_not_cleared: bool,
    last_job: Option<String>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    bed: Option<super::bed::Bed>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    last_check: Option<super::bed::CheckRecord>,
}

impl From<GateFile> for PrinterGate {
    fn from(f: GateFile) -> PrinterGate {
        let bed = match (f.bed, f.bed_not_cleared) {
            (Some(bed), _) => bed,
            (None, true) => super::bed::Bed::Waiting { why: None },
            (None, false) => super::bed::Bed::default(),
        };
        PrinterGate {
            bed,
            last_job: f.last_job,
            last_check: f.last_check,
        }
    }
}

impl From<PrinterGate> for GateFile {
    fn from(g: PrinterGate) -> GateFile {
        GateFile {
            bed_not_cleared: g.bed_not_cleared(),
            last_job: g.last_job,
            bed: Some(g.bed),
            last_check: g.last_check,
        }
    }
}

impl Job {
    /// Checks a state change against [`JobState::can_go_to`] (the only place it is
    /// checked, for every store) and applies it with `also`'s changes to the other fields.
    pub(crate) fn apply_transition(
        &mut self,
        state: JobState,
        reason: Option<String>,
        also: impl FnOnce(&mut Job),
    ) -> Result<(), StoreError> {
        if !self.state.can_go_to(state) {
            return Err(StoreError::IllegalTransition {
                id: self.id.clone(),
                from: self.state,
                to: state,
            });
        }
        also(self);
        self.state = state;
        self.history.push((state, now_s()));
        if reason.is_some() || state.is_active() {
            self.reason = reason;
        }
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A sidecar's names (what it asks the printer to hold, the printer it asks for) are
    /// refused with a control or bidi character, naming the sidecar and key, the name
    /// shown escaped.
    #[test]
    fn a_sidecar_refuses_names_with_control_or_bidi_characters() {
        let path = Path::new("hot/m.stl.toml");
        for (text, key) in [
            ("material = \"PLA\\u202E\"\n", "material"),
            ("material = \"PLA\"\ncolour = \"re\\u001Bd\"\n", "colour"),
            ("printer = \"p\\u2067\"\n", "printer"),
            ("tags = [\"a\\u202Db\"]\n", "tags"),
            ("material = \"PLA\\u0085\"\n", "material"),
        ] {
            let err = parse_sidecar(text.as_bytes(), path).unwrap_err();
            assert!(
                err.contains("hot/m.stl.toml") && err.contains(&format!("key `{key}`")),
                "{text}: {err}"
            );
            assert!(
                !err.contains(['\u{202e}', '\u{1b}', '\u{2067}', '\u{202d}', '\u{85}']),
                "{err:?}"
            );
        }
        let fine = "material = \"PLA+\"\ncolour = \"gris fonc\u{e9}\"\nprinter = \"a\"\n";
        parse_sidecar(fine.as_bytes(), path).unwrap();
    }

    /// A part cancelled before the print leaves the booking; one cancelled while it
    /// prints, or for an earlier print, does not.
    #[test]
    fn a_part_cancelled_before_its_print_is_not_booked() {
        use crate::daemon::filament::Need;
        use crate::marlin::plate::PartInfo;
        let part = |name: &str, mm: f64| PartInfo {
            name: name.into(),
            outline: Vec::new(),
            extruded_mm: mm,
            z_mm: [0.2, 4.0],
        };
        let mut job = Job::queued("0001-p".into(), 1, "p.3mf".into(), PathBuf::from("hot"));
        job.state = JobState::Ready;
        job.slice_report = Some(crate::slice::SliceReport {
            machine: "um2".into(),
            filament_mm: Some(1000.0),
            parts: vec![part("a", 300.0), part("b", 500.0)],
            ..Default::default()
        });
        job.needs.insert(
            "um2".into(),
            Need {
                mm: 1000.0,
                g: Some(8.0),
            },
        );
        // A second machine's G-code pushes more: the same share of it is left out.
        job.needs.insert(
            "mk3".into(),
            Need {
                mm: 2000.0,
                g: None,
            },
        );
        let cancel = |part: &str, print: u32, at_s: f64| PartCancel {
            part: part.into(),
            print,
            at_s,
            dropped: None,
        };
        assert_eq!(job.need_on("um2").unwrap().mm, 1000.0);
        job.parts_cancelled.push(cancel("a", 1, 100.0));
        let need = job.need_on("um2").unwrap();
        assert!((need.mm - 700.0).abs() < 1e-9, "{need:?}");
        assert!((need.g.unwrap() - 5.6).abs() < 1e-9, "{need:?}");
        assert!((job.need_on("mk3").unwrap().mm - 1400.0).abs() < 1e-9);
        // Printing since 200 s: a cancel at 300 s is mid-print and stays booked.
        job.state = JobState::Printing;
        job.history.push((JobState::Printing, 200.0));
        job.parts_cancelled.push(cancel("b", 1, 300.0));
        assert!((job.need_on("um2").unwrap().mm - 700.0).abs() < 1e-9);
        // The next print: the first print's cancels are not its.
        job.state = JobState::Ready;
        job.history.push((JobState::Ready, 400.0));
        assert_eq!(job.need_on("um2").unwrap().mm, 1000.0);
    }

    /// Every pair of states, against a table written out by hand: a change to
    /// `can_go_to` must be a deliberate change here too.
    #[test]
    fn transition_table_is_exactly_this() {
        use JobState::*;
        // Rows: from; columns: to, in JobState::ALL's order
        // (queued preparing ready printing done failed cancelled interrupted).
        let expected: [(JobState, [u8; 8]); 8] = [
            (Queued, [0, 1, 0, 0, 0, 1, 1, 0]),
            (Preparing, [1, 0, 1, 0, 0, 1, 1, 0]),
            (Ready, [0, 0, 0, 1, 0, 1, 1, 0]),
            (Printing, [0, 0, 1, 0, 1, 1, 1, 1]),
            (Done, [0, 0, 0, 0, 0, 0, 0, 0]),
            (Failed, [1, 0, 1, 0, 0, 0, 0, 0]),
            (Cancelled, [1, 0, 1, 0, 0, 0, 0, 0]),
            (Interrupted, [1, 0, 1, 0, 0, 0, 0, 0]),
        ];
        assert_eq!(expected.map(|(s, _)| s), JobState::ALL);
        for (from, row) in expected {
            for (to, allowed) in JobState::ALL.into_iter().zip(row) {
                assert_eq!(from.can_go_to(to), allowed == 1, "{from} -> {to}");
            }
        }
    }

    /// Copies are made once the job is ready, numbered from 2, and none of a copy; a job
    /// of an older crispen that printed some one after another makes only the rest; a
    /// copy prints on the printer its number names in `printers`.
    #[test]
    fn which_copies_are_due() {
        let mut job = Job::queued("0007-a_stl".into(), 7, "a.stl".into(), "/hot".into());
        job.sidecar = Some(Sidecar {
            copies: Some(4),
            ..Default::default()
        });
        assert!(job.copies_due().is_empty(), "not prepared");
        job.state = JobState::Ready;
        assert_eq!(job.copies_due(), 2..5);
        job.state = JobState::Printing;
        assert_eq!(
            job.copies_due(),
            2..5,
            "a run that stopped before making them"
        );
        job.state = JobState::Done;
        job.copies_done = 1;
        assert_eq!(
            job.copies_due(),
            2..5,
            "printed itself, copies still to make"
        );
        job.copies_done = 4;
        assert!(
            job.copies_due().is_empty(),
            "an older crispen printed all four"
        );
        job.copies_done = 0;
        assert_eq!(
            job.copies_due(),
            2..5,
            "done, but no print counted: never a copy 1"
        );
        job.state = JobState::Ready;
        job.copies_done = 2;
        assert_eq!(
            job.copies_due(),
            4..5,
            "an older crispen printed two; it prints the third"
        );
        job.copies_done = 0;
        job.copies_made = 4;
        assert!(job.copies_due().is_empty(), "made");

        job.copies_made = 0;
        job.sidecar = Some(Sidecar {
            printers: Some(vec!["a".into(), "c".into()]),
            ..Default::default()
        });
        assert_eq!(job.copies_wanted(), 2);
        assert_eq!(job.wanted_printer(), Some("a"));
        let copy = job.copy_for(2, 9);
        assert_eq!(copy.id, "0009-a_stl");
        assert_eq!((copy.group(), copy.copy_number()), ("0007-a_stl", 2));
        assert_eq!(copy.wanted_printer(), Some("c"));
        assert_eq!(copy.state, JobState::Ready);
        assert!(copy.copies_due().is_empty());
    }

    /// `printers` names each printer once, and neither `copies` nor `printer` with it.
    #[test]
    fn a_sidecars_printers_are_checked() {
        let parse = |text: &str| parse_sidecar(text.as_bytes(), Path::new("m.stl.toml"));
        assert_eq!(
            parse("printers = [\"a\", \"b\"]\n")
                .unwrap()
                .printers
                .unwrap()
                .len(),
            2
        );
        for (text, says) in [
            ("printers = []\n", "1 to 100"),
            ("printers = [\"a\", \"a\"]\n", "twice"),
            ("printers = [\"a\"]\ncopies = 2\n", "neither"),
            ("printers = [\"a\"]\nprinter = \"a\"\n", "neither"),
            ("copies = 0\n", "from 1 to 100"),
        ] {
            let e = parse(text).unwrap_err();
            assert!(e.contains("m.stl.toml") && e.contains(says), "{text}: {e}");
        }
    }
}
