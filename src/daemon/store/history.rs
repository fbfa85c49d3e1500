//! The history: finished jobs that have left the live queue. A job that is done, failed or
//! cancelled stays live (in the snapshot that status, the dashboard, SSE and metrics read)
//! for [`Retention::live_for`] after it ended, and only the newest
//! [`Retention::live_jobs`] of them; then the store's task moves it here in a batch
//! ([`to_retire`] picks them, for both stores). So the live daemon's cost follows the jobs
//! at work, not the farm's past.
//!
//! The history keeps a compact record of each job ([`Retired`]); the job's directory
//! (model, G-code, pictures, `job.json`) stays where it was. In the spool the records are
//! JSON lines in `<spool>/history/YYYY-MM.jsonl`, by the month of retirement, appended
//! and synced before the job leaves the live queue: a crash in between leaves the job in
//! the history and still in `jobs/`, and [`HistoryFiles::open`] then counts it as retired,
//! so it appears once. In PostgreSQL the job's row is marked retired
//! (`store::postgres`).

use super::rules::io_err;
use crate::calendar::{iso_utc, month_of};
use crate::daemon::job::{Job, JobState, StoreError};
use crate::slice::moved::Moved;
use serde::{Deserialize, Serialize};
use std::collections::{BTreeMap, HashSet};
use std::io::{BufRead, Write};
use std::path::{Path, PathBuf};
use std::time::Duration;

/// How long finished jobs stay live (see the module's comment).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Retention {
    pub live_for: Duration,
    pub live_jobs: usize,
    /// How long the history keeps a job after it moved there (None: for good). Kept by
    /// the month: a month's jobs go together once the whole month is older than this.
    pub keep_for: Option<Duration>,
}

impl Default for Retention {
    /// Keep live a week, at most 200 finished jobs.
    fn default() -> Retention {
        Retention {
            live_for: Duration::from_secs(7 * 86_400),
            live_jobs: 200,
            keep_for: None,
        }
    }
}

/// At most this many jobs move to the history in one step of the store's task, so a
/// first start on a long-kept spool never holds the store for long.
pub(crate) const BATCH: usize = 256;

/// A job that has ended for good as far as the queue is concerned: done, failed or
/// cancelled (an interrupted job waits for the operator, so it stays live).
pub(crate) fn is_finished(state: JobState) -> bool {
    matches!(
        state,
        JobState::Done | JobState::Failed | JobState::Cancelled
    )
}

/// When a job ended: its last state change.
pub(crate) fn ended_at(job: &Job) -> f64 {
    job.history.last().map_or(0.0, |h| h.1)
}

/// The one rule of retirement, for both stores: of the finished `jobs`, those that ended
/// more than `live_for` before `now`, and those beyond the newest `live_jobs`; oldest
/// first, at most [`BATCH`]. `skip` are jobs that must stay (an outcome not yet written).
/// Copies of one job leave together, once none is active, so the queue shows how many
/// of them are printed as long as any is not.
pub(crate) fn to_retire<'a>(
    jobs: impl Iterator<Item = &'a Job>,
    retention: &Retention,
    now: f64,
    skip: &dyn Fn(&str) -> bool,
) -> Vec<String> {
    let jobs: Vec<&Job> = jobs.collect();
    let busy: std::collections::HashSet<&str> = jobs
        .iter()
        .filter(|j| j.state.is_active())
        .map(|j| j.group())
        .collect();
    let mut finished: Vec<(f64, u64, &str)> = jobs
        .into_iter()
        .filter(|j| is_finished(j.state) && !skip(&j.id) && !busy.contains(j.group()))
        .map(|j| (ended_at(j), j.seq, j.id.as_str()))
        .collect();
    // Newest first: the first `live_jobs` that ended recently enough stay.
    finished.sort_by(|a, b| b.0.total_cmp(&a.0).then(b.1.cmp(&a.1)));
    let oldest_kept = now - retention.live_for.as_secs_f64();
    let mut out: Vec<(f64, u64, &str)> = finished
        .into_iter()
        .enumerate()
        .filter(|(i, (ended, _, _))| *i >= retention.live_jobs || *ended < oldest_kept)
        .map(|(_, j)| j)
        .collect();
    out.reverse();
    out.truncate(BATCH);
    out.into_iter().map(|(_, _, id)| id.to_string()).collect()
}

/// What the history keeps of a job: what it was, how it went, and where its files are.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Retired {
    pub id: String,
    pub seq: u64,
    /// The dropped file's name, and the hot folder it came from.
    pub file: String,
    pub folder: PathBuf,
    pub state: JobState,
    pub reason: Option<String>,
    pub printer: Option<String>,
    /// The machine it was sliced for (from its slicing report).
    pub machine: Option<String>,
    /// The printed height, and the enhancement as applied ("enhanced" with its λ2, or
    /// "unmodified"), from its slicing report.
    pub height_mm: Option<f64>,
    pub enhancement: Option<String>,
    pub lambda2: Option<f64>,
    /// Seconds since the epoch: picked up, first print started, ended.
    pub queued_at: f64,
    pub started_at: Option<f64>,
    pub ended_at: f64,
    pub copies_done: u32,
    /// A copy of another job: which, and its number.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub copy: Option<crate::daemon::job::CopyOf>,
    /// From the last print's report.
    pub resends: Option<u64>,
    pub print_s: Option<f64>,
    /// Filament one print needs, as the slicer estimated it (see `used_g` for what was
    /// taken).
    pub filament_mm: Option<f64>,
    pub filament_g: Option<f64>,
    /// The job's directory on the host that kept it (model, G-code, pictures, job.json).
    pub dir: PathBuf,
    /// When it left the live queue.
    pub retired_at: f64,
    /// Each time it was printing: (start, end), seconds since the epoch, from its state
    /// changes (a copy or a retried print is a time of its own). Records written before
    /// this field existed have none.
    #[serde(default)]
    pub printing: Vec<(f64, f64)>,
    /// What its prints took from spools ([`Job::used`]): the material, grams and cost.
    /// None in records written before uses were recorded.
    #[serde(default)]
    pub material: Option<String>,
    #[serde(default)]
    pub used_g: Option<f64>,
    #[serde(default)]
    pub cost: Option<f64>,
    /// What the enhancement moved: its slicing report's figures, said where shown. None
    /// in records made before they were kept, and in those that kept it in words.
    #[serde(
        default,
        skip_serializing_if = "Option::is_none",
        deserialize_with = "figures_only"
    )]
    pub moved: Option<Moved>,
}

/// A record's `moved`: its figures, or nothing for one that kept the line in words (before
/// the words were made where shown), so an old record still reads.
fn figures_only<'de, D: serde::Deserializer<'de>>(d: D) -> Result<Option<Moved>, D::Error> {
    #[derive(Deserialize)]
    #[serde(untagged)]
    enum Kept {
        Figures(Moved),
        Other(serde::de::IgnoredAny),
    }
    Ok(match Option::<Kept>::deserialize(d)? {
        Some(Kept::Figures(m)) => Some(m),
        Some(Kept::Other(_)) | None => None,
    })
}

/// The times `job` was printing, from its state changes: each `Printing` until the next
/// change; one still printing ends at `now`.
pub(crate) fn printing_times(job: &Job, now: f64) -> Vec<(f64, f64)> {
    let mut out = Vec::new();
    for (i, (state, start)) in job.history.iter().enumerate() {
        if *state == JobState::Printing {
            let end = job.history.get(i + 1).map_or(now, |next| next.1);
            out.push((*start, end.max(*start)));
        }
    }
    out
}

/// Which finished jobs a history page or an export takes; every part optional.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct Filter {
    /// The printer's name, as in `[[printer]] name`.
    pub printer: Option<String>,
    /// The hot folder: its name (the last part of its path) or its whole path.
    pub folder: Option<String>,
    pub state: Option<JobState>,
    /// Ended at or after this (seconds since the epoch).
    pub since: Option<f64>,
    /// Ended before this.
    pub until: Option<f64>,
}

impl Filter {
    pub(crate) fn matches(&self, r: &Retired) -> bool {
        self.printer
            .as_ref()
            .is_none_or(|p| r.printer.as_deref() == Some(p.as_str()))
            && self.folder.as_ref().is_none_or(|f| folder_is(&r.folder, f))
            && self.state.is_none_or(|s| r.state == s)
            && self.since.is_none_or(|t| r.ended_at >= t)
            && self.until.is_none_or(|t| r.ended_at < t)
    }

    pub(crate) fn is_empty(&self) -> bool {
        *self == Filter::default()
    }
}

/// Whether `folder` is the one called `name` (its last part) or at path `name`.
pub(crate) fn folder_is(folder: &Path, name: &str) -> bool {
    folder.file_name().is_some_and(|n| n == name) || folder == Path::new(name)
}

impl Retired {
    pub(crate) fn of(job: &Job, dir: PathBuf, now: f64) -> Retired {
        let report = job.slice_report.as_ref();
        let used = job.used();
        Retired {
            id: job.id.clone(),
            seq: job.seq,
            file: job.file.clone(),
            folder: job.folder.clone(),
            state: job.state,
            reason: job.reason.clone(),
            printer: job.printer.clone(),
            machine: report.map(|r| r.machine.clone()),
            height_mm: report.map(|r| r.height_mm),
            enhancement: report.map(|r| r.enhancement.mode.clone()),
            lambda2: report.and_then(|r| r.enhancement.lambda2),
            queued_at: job.history.first().map_or(0.0, |h| h.1),
            started_at: job
                .history
                .iter()
                .find(|h| h.0 == JobState::Printing)
                .map(|h| h.1),
            ended_at: ended_at(job),
            copies_done: job.copies_done,
            copy: job.copy.clone(),
            resends: job.print_report.as_ref().map(|r| r.resends),
            print_s: job.print_report.as_ref().map(|r| r.duration_s),
            filament_mm: report.and_then(|r| r.filament_mm),
            filament_g: report.and_then(|r| r.filament_g),
            dir,
            retired_at: now,
            printing: printing_times(job, now),
            material: used.material,
            used_g: used.grams,
            cost: used.cost,
            moved: report.map(|r| r.moved()),
        }
    }
}

/// A page of the history, newest first.
#[derive(Debug, Clone, Default, Serialize, Deserialize)]
pub struct Page {
    pub jobs: Vec<Retired>,
    /// Pass as `before` for the next (older) page; None on the last page.
    pub next: Option<u64>,
}

/// Bounds of a page's `limit`.
pub(crate) const PAGE_LIMIT: std::ops::RangeInclusive<usize> = 1..=1000;

/// Keeps the newest `limit` of `records` (by sequence number, each job once) below
/// `before` that `filter` takes, as a page.
pub(crate) fn page_of(
    records: impl Iterator<Item = Retired>,
    before: Option<u64>,
    limit: usize,
    filter: &Filter,
) -> Page {
    let mut newest: BTreeMap<u64, Retired> = BTreeMap::new();
    let mut more = false;
    for r in records.filter(|r| before.is_none_or(|b| r.seq < b) && filter.matches(r)) {
        newest.insert(r.seq, r);
        if newest.len() > limit {
            newest.pop_first();
            more = true;
        }
    }
    let jobs: Vec<Retired> = newest.into_values().rev().collect();
    Page {
        next: if more {
            jobs.last().map(|r| r.seq)
        } else {
            None
        },
        jobs,
    }
}

/// The columns of the history as CSV, in order.
/// Columns are only ever added at the end, so a consumer's column positions hold.
pub(crate) const CSV_COLUMNS: [&str; 28] = [
    "id",
    "seq",
    "file",
    "folder",
    "machine",
    "printer",
    "height_mm",
    "enhancement",
    "lambda2",
    "state",
    "reason",
    "queued_at",
    "started_at",
    "ended_at",
    "print_s",
    "printing_s",
    "copies_done",
    "filament_mm",
    "filament_g",
    "resends",
    "dir",
    "retired_at",
    "ended_unix",
    "material",
    "used_g",
    "cost",
    "copy_of",
    "copy",
];

impl Retired {
    /// Its time spent printing, over all its prints: the printers' time it took.
    pub(crate) fn printing_s(&self) -> f64 {
        self.printing.iter().map(|(a, b)| (b - a).max(0.0)).sum()
    }

    /// Grams of filament it used: as its prints were weighed, else the slicer's estimate
    /// for each copy printed (a record from before uses were recorded, or prints on a
    /// printer whose filament was not known).
    pub(crate) fn used_or_estimated_g(&self) -> Option<f64> {
        self.used_g
            .or_else(|| self.filament_g.map(|g| g * f64::from(self.copies_done)))
    }

    /// Its CSV record in the order of [`CSV_COLUMNS`]: times as UTC
    /// `YYYY-MM-DDTHH:MM:SSZ`, an absent value empty, texts [`spreadsheet_safe`].
    fn csv_record(&self) -> [String; CSV_COLUMNS.len()] {
        let num = |v: Option<f64>| v.map_or(String::new(), |v| format!("{v}"));
        let time = |v: Option<f64>| v.map_or(String::new(), iso_utc);
        let text = |v: &str| spreadsheet_safe(v);
        [
            text(&self.id),
            self.seq.to_string(),
            text(&self.file),
            text(&self.folder.display().to_string()),
            text(self.machine.as_deref().unwrap_or("")),
            text(self.printer.as_deref().unwrap_or("")),
            num(self.height_mm),
            text(self.enhancement.as_deref().unwrap_or("")),
            num(self.lambda2),
            self.state.name().to_string(),
            text(self.reason.as_deref().unwrap_or("")),
            time(Some(self.queued_at)),
            time(self.started_at),
            time(Some(self.ended_at)),
            num(self.print_s),
            num(Some(self.printing_s())),
            self.copies_done.to_string(),
            num(self.filament_mm),
            num(self.filament_g),
            self.resends.map_or(String::new(), |r| r.to_string()),
            text(&self.dir.display().to_string()),
            time(Some(self.retired_at)),
            format!("{}", self.ended_at),
            text(self.material.as_deref().unwrap_or("")),
            num(self.used_g),
            num(self.cost),
            text(self.copy.as_ref().map_or("", |c| c.job.as_str())),
            self.copy
                .as_ref()
                .map_or(String::new(), |c| c.n.to_string()),
        ]
    }
}

/// The history as CSV (RFC 4180, CRLF-ended records, quoted where needed): the header,
/// then one record a retired job.
pub(crate) struct Csv(csv::Writer<Vec<u8>>);

impl Csv {
    pub(crate) fn new() -> Csv {
        let mut writer = csv::WriterBuilder::new()
            .terminator(csv::Terminator::CRLF)
            .from_writer(Vec::new());
        // Into memory: a write cannot fail.
        let _ = writer.write_record(CSV_COLUMNS);
        Csv(writer)
    }

    pub(crate) fn push(&mut self, job: &Retired) {
        let _ = self.0.write_record(job.csv_record());
    }

    pub(crate) fn into_bytes(self) -> Vec<u8> {
        self.0
            .into_inner()
            .unwrap_or_else(|e| e.into_inner().into_inner().unwrap_or_default())
    }
}

/// A text a spreadsheet opening the file shows as text: one starting with `=`, `+`,
/// `-`, `@`, a tab or a carriage return gets a `'` in front, so a file name or reason is
/// never run as a formula.
fn spreadsheet_safe(text: &str) -> String {
    if text.starts_with(['=', '+', '-', '@', '\t', '\r']) {
        format!("'{text}")
    } else {
        text.to_string()
    }
}

/// The spool's history files, `<spool>/history/YYYY-MM.jsonl`.
pub(crate) struct HistoryFiles {
    dir: PathBuf,
}

impl HistoryFiles {
    /// Reads the ids of every retired job, mending a line cut short by a crash (it is
    /// cut off: that job was not retired, and is again).
    pub(crate) fn open(spool: &Path) -> Result<(HistoryFiles, HashSet<String>), StoreError> {
        let dir = spool.join("history");
        std::fs::create_dir_all(&dir).map_err(io_err(&dir, "create"))?;
        let files = HistoryFiles { dir };
        let mut ids = HashSet::new();
        for path in files.files()? {
            // A line at a time: the history may be large, the daemon's memory is not.
            let file = std::fs::File::open(&path).map_err(io_err(&path, "read"))?;
            let mut reader = std::io::BufReader::new(file);
            let (mut line, mut whole) = (Vec::new(), 0u64);
            loop {
                line.clear();
                let n = reader
                    .read_until(b'\n', &mut line)
                    .map_err(io_err(&path, "read"))?;
                if n == 0 || line.last() != Some(&b'\n') {
                    break;
                }
                whole += n as u64;
                if let Some(id) = id_of_line(&line[..n - 1]) {
                    ids.insert(id);
                }
            }
            if !line.is_empty() {
                tracing::warn!(file = %path.display(), "the history's last line was cut short (a crash while retiring); cut off, its job is retired again");
                let f = std::fs::OpenOptions::new()
                    .write(true)
                    .open(&path)
                    .map_err(io_err(&path, "open"))?;
                f.set_len(whole).map_err(io_err(&path, "truncate"))?;
                f.sync_all().map_err(io_err(&path, "fsync"))?;
            }
        }
        Ok((files, ids))
    }

    /// The history files, oldest month first.
    fn files(&self) -> Result<Vec<PathBuf>, StoreError> {
        let mut files = Vec::new();
        for entry in std::fs::read_dir(&self.dir).map_err(io_err(&self.dir, "list"))? {
            let entry = entry.map_err(io_err(&self.dir, "list"))?;
            let name = entry.file_name().to_string_lossy().into_owned();
            if is_month_file(&name) {
                files.push(entry.path());
            }
        }
        files.sort();
        Ok(files)
    }

    /// Appends `records` to the month of `now` and syncs them (and the directory, for a
    /// new month's file) before returning.
    pub(crate) fn append(&self, records: &[Retired], now: f64) -> Result<(), StoreError> {
        let path = self.dir.join(format!("{}.jsonl", month_of(now)));
        let new = !path.exists();
        let mut text = Vec::new();
        for r in records {
            serde_json::to_writer(&mut text, r).expect("a history record serialises");
            text.push(b'\n');
        }
        let mut f = std::fs::OpenOptions::new()
            .create(true)
            .append(true)
            .open(&path)
            .map_err(io_err(&path, "open"))?;
        f.write_all(&text).map_err(io_err(&path, "append"))?;
        f.sync_all().map_err(io_err(&path, "fsync"))?;
        if new {
            crate::fsutil::sync_dir(&self.dir)?;
        }
        Ok(())
    }

    /// Every record, oldest file first, read a line at a time (never the whole history in
    /// memory). A line that cannot be read is logged and passed over.
    pub(crate) fn records(&self) -> Result<impl Iterator<Item = Retired>, StoreError> {
        self.records_since(0.0)
    }

    /// [`HistoryFiles::records`] of the months from that of `since` on: the records of
    /// jobs retired at or after `since`, and some before.
    pub(crate) fn records_since(
        &self,
        since: f64,
    ) -> Result<impl Iterator<Item = Retired>, StoreError> {
        Ok(self
            .months_since(since)?
            .into_iter()
            .flat_map(|path| HistoryFiles::month_records(&path)))
    }

    /// The month files from that of `since` on, oldest first.
    pub(crate) fn months_since(&self, since: f64) -> Result<Vec<PathBuf>, StoreError> {
        let first = format!("{}.jsonl", month_of(since));
        let mut files = self.files()?;
        files.retain(|f| {
            f.file_name()
                .is_some_and(|n| *n.to_string_lossy() >= *first.as_str())
        });
        Ok(files)
    }

    /// The records of the month file at `path`, read a line at a time; a file or a line
    /// that cannot be read is logged and passed over.
    pub(crate) fn month_records(path: &Path) -> impl Iterator<Item = Retired> {
        let path = path.to_path_buf();
        let file = match std::fs::File::open(&path) {
            Ok(f) => Some(std::io::BufReader::new(f)),
            Err(e) => {
                tracing::warn!(file = %path.display(), error = %e, "history file unreadable; passed over");
                None
            }
        };
        file.into_iter().flat_map(|f| f.lines()).filter_map(move |line| {
            let line = line.ok()?;
            match serde_json::from_str(&line) {
                Ok(r) => Some(r),
                Err(e) => {
                    tracing::warn!(file = %path.display(), error = %e, "history line unreadable; passed over");
                    None
                }
            }
        })
    }

    /// The month files wholly older than `cutoff` (every job in them retired before it),
    /// oldest first.
    pub(crate) fn months_before(&self, cutoff: f64) -> Result<Vec<PathBuf>, StoreError> {
        let first_kept = format!("{}.jsonl", month_of(cutoff));
        let mut files = self.files()?;
        files.retain(|f| {
            f.file_name()
                .is_some_and(|n| *n.to_string_lossy() < *first_kept)
        });
        Ok(files)
    }

    /// The records of one month file (unreadable lines passed over, as in `records`).
    pub(crate) fn records_of(path: &Path) -> Result<Vec<Retired>, StoreError> {
        let text = std::fs::read_to_string(path).map_err(io_err(path, "read"))?;
        Ok(text
            .lines()
            .filter_map(|l| serde_json::from_str(l).ok())
            .collect())
    }

    /// Removes a month file once its jobs' directories are gone (and syncs the directory).
    pub(crate) fn remove_month(&self, path: &Path) -> Result<(), StoreError> {
        std::fs::remove_file(path).map_err(io_err(path, "remove"))?;
        crate::fsutil::sync_dir(&self.dir)?;
        Ok(())
    }

    /// The record of one retired job.
    pub(crate) fn find(&self, id: &str) -> Result<Option<Retired>, StoreError> {
        Ok(self.records()?.filter(|r| r.id == id).last())
    }
}

/// The `id` of a history line, without reading the rest of it.
fn id_of_line(line: &[u8]) -> Option<String> {
    #[derive(Deserialize)]
    struct Id {
        id: String,
    }
    if line.is_empty() {
        return None;
    }
    serde_json::from_slice::<Id>(line).ok().map(|i| i.id)
}

/// `YYYY-MM.jsonl`.
fn is_month_file(name: &str) -> bool {
    let b = name.as_bytes();
    name.len() == 13
        && name.ends_with(".jsonl")
        && b[4] == b'-'
        && b[..4].iter().chain(&b[5..7]).all(u8::is_ascii_digit)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::daemon::job::JobUse;

    fn job(seq: u64, state: JobState, ended: f64) -> Job {
        let mut j = Job::queued(
            Job::make_id(seq, "m.stl"),
            seq,
            "m.stl".into(),
            "/hot".into(),
        );
        j.state = state;
        j.history = vec![(JobState::Queued, ended - 100.0), (state, ended)];
        j
    }

    const DAY: f64 = 86_400.0;

    /// By age and by count, finished jobs only, oldest first, and never one kept back.
    #[test]
    fn retirement_by_age_and_by_count() {
        let now = 1_000.0 * DAY;
        let retention = Retention {
            live_for: Duration::from_secs(7 * 86_400),
            live_jobs: 3,
            keep_for: None,
        };
        let jobs = [
            job(1, JobState::Done, now - 8.0 * DAY),         // too old
            job(2, JobState::Failed, now - 6.0 * DAY),       // 5th newest finished: too many
            job(3, JobState::Cancelled, now - 5.0 * DAY),    // 4th newest: too many
            job(4, JobState::Interrupted, now - 30.0 * DAY), // waits for the operator
            job(5, JobState::Ready, now - 30.0 * DAY),       // at work
            job(6, JobState::Done, now - 1.0 * DAY),
            job(7, JobState::Done, now - 2.0 * DAY),
            job(8, JobState::Done, now - 3.0 * DAY),
            job(9, JobState::Done, now - 9.0 * DAY), // kept back: an outcome not written
        ];
        let skip = |id: &str| id == jobs[8].id;
        let ids = to_retire(jobs.iter(), &retention, now, &skip);
        let seqs: Vec<&str> = ids.iter().map(|i| &i[..4]).collect();
        assert_eq!(seqs, ["0001", "0002", "0003"]);

        // Young and few: nothing moves; a count of 0 moves every finished job.
        let few = Retention {
            live_for: Duration::from_secs(7 * 86_400),
            live_jobs: 200,
            keep_for: None,
        };
        assert_eq!(
            to_retire(jobs[4..8].iter(), &few, now, &|_| false),
            Vec::<String>::new()
        );
        let none = Retention {
            live_for: Duration::from_secs(7 * 86_400),
            live_jobs: 0,
            keep_for: None,
        };
        assert_eq!(
            to_retire(jobs[4..8].iter(), &none, now, &|_| false).len(),
            3
        );

        // At most a batch at a time.
        let many: Vec<Job> = (1..=BATCH as u64 + 10)
            .map(|s| job(s, JobState::Done, now - 30.0 * DAY))
            .collect();
        let first = to_retire(many.iter(), &retention, now, &|_| false);
        assert_eq!(first.len(), BATCH);
        assert_eq!(first[0], many[0].id, "oldest first");
    }

    #[test]
    fn pages_are_newest_first_and_each_job_once() {
        let record = |seq| Retired::of(&job(seq, JobState::Done, 1e9), "/d".into(), 1e9);
        let records: Vec<Retired> = [5, 1, 4, 2, 3, 4].map(record).to_vec();
        let all = Filter::default();
        let page = page_of(records.clone().into_iter(), None, 2, &all);
        assert_eq!(page.jobs.iter().map(|r| r.seq).collect::<Vec<_>>(), [5, 4]);
        assert_eq!(page.next, Some(4));
        let page = page_of(records.clone().into_iter(), page.next, 2, &all);
        assert_eq!(page.jobs.iter().map(|r| r.seq).collect::<Vec<_>>(), [3, 2]);
        let page = page_of(records.into_iter(), page.next, 2, &all);
        assert_eq!(page.jobs.iter().map(|r| r.seq).collect::<Vec<_>>(), [1]);
        assert_eq!(page.next, None);
    }

    #[test]
    fn csv_fields_are_quoted() {
        let csv = |jobs: &[Retired]| {
            let mut csv = Csv::new();
            for j in jobs {
                csv.push(j);
            }
            String::from_utf8(csv.into_bytes()).unwrap()
        };
        let mut j = job(3, JobState::Failed, 1e9);
        j.reason = Some("bad, \"very\"\nso".into());
        j.file = "=cmd().stl".into();
        let text = csv(&[Retired::of(&j, "/d".into(), 1e9)]);
        let (header, line) = text.split_once("\r\n").unwrap();
        assert_eq!(header, CSV_COLUMNS.join(","));
        assert!(line.ends_with("\r\n"));
        assert!(line.contains(",\"bad, \"\"very\"\"\nso\","), "{line}");
        assert!(line.contains(",'=cmd().stl,"), "{line}");
        assert!(line.contains(",failed,"), "{line}");
        assert_eq!(csv(&[]), format!("{}\r\n", CSV_COLUMNS.join(",")));
    }

    fn a_use(n: u32, material: &str, grams: f64, cost: Option<f64>) -> JobUse {
        JobUse {
            key: format!("0001-m_stl#{n}"),
            spool: None,
            printer: "p1".into(),
            material: material.into(),
            colour: "black".into(),
            grams,
            mm: grams * 300.0,
            cost,
            at_s: 1e9,
            print_s: 0.0,
            failed: false,
        }
    }

    /// Material, grams and cost from the job's uses; its printers' time from its state
    /// changes.
    #[test]
    fn what_a_job_used_and_cost() {
        // Two copies, each weighed and priced (20 €/kg); a retried print first failed
        // part way, its partial use counted too.
        let mut j = job(1, JobState::Done, 1e9);
        j.history = vec![
            (JobState::Queued, 0.0),
            (JobState::Printing, 100.0),
            (JobState::Failed, 130.0),
            (JobState::Ready, 140.0),
            (JobState::Printing, 150.0),
            (JobState::Ready, 250.0),
            (JobState::Printing, 300.0),
            (JobState::Done, 400.0),
        ];
        j.uses = vec![
            a_use(0, "PETG", 2.0, Some(0.04)),
            a_use(1, "PETG", 10.0, Some(0.2)),
            a_use(2, "PLA", 10.0, Some(0.2)),
        ];
        let r = Retired::of(&j, "/d".into(), 1e9);
        assert_eq!(r.material.as_deref(), Some("PETG"), "the first print's");
        assert!((r.used_g.unwrap() - 22.0).abs() < 1e-9);
        assert!((r.cost.unwrap() - 0.44).abs() < 1e-9);
        assert_eq!(r.printing_s(), 30.0 + 100.0 + 100.0);

        // A failed job: its one partial print.
        let mut j = job(2, JobState::Failed, 1e9);
        j.uses = vec![a_use(0, "PLA", 1.5, Some(0.03))];
        let r = Retired::of(&j, "/d".into(), 1e9);
        assert_eq!((r.used_g, r.cost), (Some(1.5), Some(0.03)));

        // No price known: grams, no cost; one print priced of two: that one's cost.
        let mut j = job(3, JobState::Done, 1e9);
        j.uses = vec![a_use(0, "PLA", 5.0, None), a_use(1, "PLA", 5.0, None)];
        let r = Retired::of(&j, "/d".into(), 1e9);
        assert_eq!((r.used_g, r.cost), (Some(10.0), None));
        j.uses[1].cost = Some(0.1);
        assert_eq!(Retired::of(&j, "/d".into(), 1e9).cost, Some(0.1));

        // On a printer whose filament was not known, a use has no weight: the slicer's
        // estimate stands in for it.
        let mut j = job(4, JobState::Done, 1e9);
        j.copies_done = 2;
        j.slice_report = None;
        j.uses = vec![a_use(0, JobUse::UNKNOWN, 0.0, None)];
        let mut r = Retired::of(&j, "/d".into(), 1e9);
        assert_eq!((&r.material, r.used_g, r.cost), (&None, None, None));
        r.filament_g = Some(3.0);
        assert_eq!(r.used_or_estimated_g(), Some(6.0), "3 g each of 2 copies");
        r.used_g = Some(5.5);
        assert_eq!(
            r.used_or_estimated_g(),
            Some(5.5),
            "weighed beats estimated"
        );
    }

    /// A record written before uses were recorded still reads, without them; its CSV line
    /// leaves their columns empty, after the older columns.
    #[test]
    fn an_old_record_reads_without_uses() {
        let mut old =
            serde_json::to_value(Retired::of(&job(5, JobState::Done, 1e9), "/d".into(), 1e9))
                .unwrap();
        for field in ["material", "used_g", "cost"] {
            old.as_object_mut().unwrap().remove(field).unwrap();
        }
        let r: Retired = serde_json::from_value(old).unwrap();
        assert_eq!((&r.material, r.used_g, r.cost), (&None, None, None));
        let mut csv = Csv::new();
        csv.push(&r);
        let text = String::from_utf8(csv.into_bytes()).unwrap();
        let line = text.split("\r\n").nth(1).unwrap();
        assert_eq!(line.split(',').count(), CSV_COLUMNS.len());
        assert!(line.ends_with(",,,"), "{line}");
        // The columns consumers know stay where they were; the new ones come last.
        assert_eq!(CSV_COLUMNS[22], "ended_unix");
        assert_eq!(CSV_COLUMNS[23..26], ["material", "used_g", "cost"]);
        assert_eq!(CSV_COLUMNS[26..], ["copy_of", "copy"]);
    }

    /// A record keeps what the enhancement moved as figures and reads them back; one that
    /// kept it in words (before the words were made where shown) reads without it.
    #[test]
    fn what_moved_is_kept_as_figures() {
        let mut job = job(6, JobState::Done, 1e9);
        job.slice_report = Some(crate::slice::SliceReport {
            enhancement: crate::slice::EnhancementSummary {
                mode: "unmodified".into(),
                ..Default::default()
            },
            ..Default::default()
        });
        let r = Retired::of(&job, "/d".into(), 1e9);
        assert_eq!(r.moved, Some(Moved::Unmodified));
        let json = serde_json::to_value(&r).unwrap();
        assert_eq!(json["moved"], serde_json::json!({"from": "unmodified"}));
        assert_eq!(serde_json::from_value::<Retired>(json.clone()).unwrap(), r);
        let mut words = json;
        words["moved"] = "The outer wall moves by at most 0.1 mm.".into();
        assert_eq!(
            serde_json::from_value::<Retired>(words).unwrap().moved,
            None
        );
    }

    #[test]
    fn month_files_are_known_by_name() {
        assert!(is_month_file("2026-12.jsonl"));
        assert!(!is_month_file("2026-12.jsonl.tmp"));
        assert!(!is_month_file("notes.jsonl"));
    }

    /// Copies of one job leave the queue together: none while another is active.
    #[test]
    fn copies_retire_together() {
        let retention = Retention {
            live_for: std::time::Duration::ZERO,
            ..Retention::default()
        };
        let mut first = Job::queued("0001-a_stl".into(), 1, "a.stl".into(), "/hot".into());
        first.state = JobState::Done;
        let mut second = first.copy_for(2, 2);
        second.state = JobState::Printing;
        let mut other = Job::queued("0003-b_stl".into(), 3, "b.stl".into(), "/hot".into());
        other.state = JobState::Done;
        let now = crate::daemon::job::now_s() + 10.0;
        let ids = to_retire(
            [&first, &second, &other].into_iter(),
            &retention,
            now,
            &|_| false,
        );
        assert_eq!(ids, ["0003-b_stl"]);
        second.state = JobState::Failed;
        let ids = to_retire(
            [&first, &second, &other].into_iter(),
            &retention,
            now,
            &|_| false,
        );
        assert_eq!(ids.len(), 3);
    }
}
