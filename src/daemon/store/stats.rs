//! Statistics of the farm over a chosen period, per printer, per hot folder and per
//! material: jobs by outcome, printing time, utilisation (the share of the period a
//! printer was printing, also per UTC day for the dashboard's chart), filament used, its
//! cost and the most common failure reasons. Computed from the history's records and the live jobs (both as
//! [`Retired`] records), by arithmetic without I/O, so the rules are tested on their own.
//!
//! Also the counters behind `/metrics` ([`Tally`]): counted by the store's task as jobs
//! change state, from the start of the process (Prometheus takes a restart's reset), so they never
//! go down when finished jobs move to the history.
//!
//! The rules: a job counts in the outcomes, filament, cost and failure reasons of the
//! period in which it ended; its printing time counts where it was printing (a print across
//! midnight or across the period's edge is split there).

use super::history::{folder_is, Retired};
use crate::calendar::date_of;
use crate::daemon::job::{Job, JobState};
use serde::{Deserialize, Serialize};
use std::collections::{BTreeMap, HashMap};

const DAY: f64 = 86_400.0;

/// The longest period asked for (the chart has a column per day).
pub(crate) const MAX_DAYS: f64 = 400.0;
/// How many failure reasons are listed, most common first.
pub(crate) const TOP_REASONS: usize = 5;
/// A failure reason is compared (and shown) by its first line, at most this long.
const REASON_CHARS: usize = 200;

/// A period, `[from, to)` in seconds since the epoch.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct Period {
    pub from: f64,
    pub to: f64,
}

impl Period {
    /// A period that starts before it ends and lasts at most [`MAX_DAYS`].
    pub fn new(from: f64, to: f64) -> Result<Period, String> {
        if !from.is_finite() || !to.is_finite() || from < 0.0 {
            return Err(format!("from {from} and to {to}: not times"));
        }
        if to <= from {
            return Err(format!("from {from} must be before to {to}"));
        }
        if to - from > MAX_DAYS * DAY {
            return Err(format!(
                "a period of {:.1} days: at most {MAX_DAYS} days",
                (to - from) / DAY
            ));
        }
        Ok(Period { from, to })
    }

    /// The last `days` whole UTC days up to and including the day of `now`.
    pub(crate) fn last_days(days: u32, now: f64) -> Result<Period, String> {
        let end = ((now / DAY).floor() + 1.0) * DAY;
        Period::new(end - f64::from(days) * DAY, end)
    }

    /// The UTC days the period touches: each day's start, clipped to the period.
    fn days(&self) -> Vec<(f64, f64)> {
        let mut out = Vec::new();
        let mut start = self.from;
        while start < self.to {
            let end = (((start / DAY).floor() + 1.0) * DAY).min(self.to);
            out.push((start, end));
            start = end;
        }
        out
    }
}

/// A time given as seconds since the epoch, or as a UTC date `YYYY-MM-DD` (its midnight).
pub(crate) fn parse_time(text: &str) -> Result<f64, String> {
    if let Ok(t) = text.parse::<f64>() {
        if t.is_finite() && t >= 0.0 {
            return Ok(t);
        }
    }
    crate::calendar::midnight_of(text)
        .ok_or_else(|| format!("{text:?}: not a time (seconds since the epoch, or YYYY-MM-DD)"))
}

/// Jobs by outcome.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct Outcomes {
    pub done: u64,
    pub failed: u64,
    pub cancelled: u64,
}

/// A failure reason and how many jobs failed so.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Reason {
    pub reason: String,
    pub jobs: u64,
}

/// The figures of one printer, one folder, one material, or the whole farm.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct Group {
    pub name: String,
    pub jobs: Outcomes,
    /// Time spent printing within the period.
    pub printing_s: f64,
    /// Filament of the prints finished in the period (each copy printed counts), as their
    /// G-code pushes it net; in grams, of the jobs that asked a material crispen knows
    /// the density of (see `crate::daemon::filament::routing::Need`).
    pub filament_mm: f64,
    pub filament_g: f64,
    /// Filament the jobs that ended in the period used, grams: as their prints were
    /// weighed (a failed or cancelled print as far as it got), else the estimate
    /// (`Retired::used_or_estimated_g`).
    #[serde(default)]
    pub used_g: f64,
    /// What the filament they used cost, of the prints whose spool's price is known; None:
    /// no price was known.
    #[serde(default)]
    pub cost: Option<f64>,
    /// Most common first, at most [`TOP_REASONS`].
    pub failure_reasons: Vec<Reason>,
    /// Printers only: `printing_s` over the period's length, and the same per day of
    /// [`Stats::days`] (not capped: above 1 would mean records that overlap).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub utilisation: Option<f64>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub daily_utilisation: Option<Vec<f64>>,
}

/// The statistics of a period.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct Stats {
    pub from: f64,
    pub to: f64,
    /// The UTC days the period touches, `YYYY-MM-DD`.
    pub days: Vec<String>,
    pub farm: Group,
    pub printers: Vec<Group>,
    pub folders: Vec<Group>,
    /// By the material the jobs were printed in (jobs whose prints were not weighed are
    /// in none).
    #[serde(default)]
    pub materials: Vec<Group>,
}

/// A group while its records are added.
#[derive(Default)]
struct Sums {
    jobs: Outcomes,
    printing_s: f64,
    filament_mm: f64,
    filament_g: f64,
    used_g: f64,
    cost: Option<f64>,
    reasons: HashMap<String, u64>,
    daily_s: Vec<f64>,
}

impl Sums {
    fn finish(self, name: String, period: &Period, days: &[(f64, f64)], printer: bool) -> Group {
        let mut reasons: Vec<Reason> = self
            .reasons
            .into_iter()
            .map(|(reason, jobs)| Reason { reason, jobs })
            .collect();
        reasons.sort_by(|a, b| b.jobs.cmp(&a.jobs).then(a.reason.cmp(&b.reason)));
        reasons.truncate(TOP_REASONS);
        Group {
            name,
            jobs: self.jobs,
            printing_s: self.printing_s,
            filament_mm: self.filament_mm,
            filament_g: self.filament_g,
            used_g: self.used_g,
            cost: self.cost,
            failure_reasons: reasons,
            utilisation: printer.then(|| self.printing_s / (period.to - period.from)),
            daily_utilisation: printer.then(|| {
                days.iter()
                    .enumerate()
                    .map(|(i, (a, b))| self.daily_s.get(i).copied().unwrap_or(0.0) / (b - a))
                    .collect()
            }),
        }
    }
}

/// Adds records up into [`Stats`]; each job once, however often it is added (the same
/// job may be live on one host and retired on another, or twice in a spool's history
/// after a crash while retiring).
pub(crate) struct Builder {
    period: Period,
    days: Vec<(f64, f64)>,
    seen: std::collections::HashSet<u64>,
    farm: Sums,
    printers: BTreeMap<String, Sums>,
    folders: BTreeMap<String, Sums>,
    materials: BTreeMap<String, Sums>,
}

impl Builder {
    /// `printers`: those listed even when they did nothing (the config's); `folders`
    /// likewise (their names).
    pub(crate) fn new(period: Period, printers: &[String], folders: &[String]) -> Builder {
        let days = period.days();
        let empty = || Sums {
            daily_s: vec![0.0; days.len()],
            ..Sums::default()
        };
        Builder {
            printers: printers.iter().map(|p| (p.clone(), empty())).collect(),
            folders: folders.iter().map(|f| (f.clone(), empty())).collect(),
            farm: empty(),
            materials: BTreeMap::new(),
            seen: Default::default(),
            period,
            days,
        }
    }

    pub(crate) fn add(&mut self, r: &Retired) {
        if !self.seen.insert(r.seq) {
            return;
        }
        let period = self.period;
        let ended_in = r.ended_at >= period.from && r.ended_at < period.to;
        let mut daily = vec![0.0; self.days.len()];
        let mut printing = 0.0;
        for &(start, end) in &r.printing {
            printing += overlap((start, end), (period.from, period.to));
            for (i, day) in self.days.iter().enumerate() {
                daily[i] += overlap((start, end), *day);
            }
        }
        if !ended_in && printing == 0.0 {
            return;
        }
        let folder = r.folder.file_name().map_or_else(
            || r.folder.display().to_string(),
            |n| n.to_string_lossy().into_owned(),
        );
        let folder = match self.folders.keys().find(|f| folder_is(&r.folder, f)) {
            Some(f) => f.clone(),
            None => folder,
        };
        let days = self.days.len();
        let empty = || Sums {
            daily_s: vec![0.0; days],
            ..Sums::default()
        };
        let mut groups: Vec<&mut Sums> = vec![&mut self.farm];
        groups.push(self.folders.entry(folder).or_insert_with(empty));
        if let Some(p) = &r.printer {
            groups.push(self.printers.entry(p.clone()).or_insert_with(empty));
        }
        if let Some(m) = &r.material {
            groups.push(self.materials.entry(m.clone()).or_insert_with(empty));
        }
        for g in groups {
            g.printing_s += printing;
            for (d, s) in g.daily_s.iter_mut().zip(&daily) {
                *d += s;
            }
            if !ended_in {
                continue;
            }
            match r.state {
                JobState::Done => g.jobs.done += 1,
                JobState::Failed => {
                    g.jobs.failed += 1;
                    let reason = reason_key(r.reason.as_deref());
                    *g.reasons.entry(reason).or_default() += 1;
                }
                JobState::Cancelled => g.jobs.cancelled += 1,
                // A live job that ended no print yet: its printing time only.
                _ => {}
            }
            let copies = f64::from(r.copies_done);
            g.filament_mm += r.filament_mm.unwrap_or(0.0) * copies;
            g.filament_g += r.filament_g.unwrap_or(0.0) * copies;
            g.used_g += r.used_or_estimated_g().unwrap_or(0.0);
            if let Some(cost) = r.cost {
                *g.cost.get_or_insert(0.0) += cost;
            }
        }
    }

    pub(crate) fn finish(self) -> Stats {
        let Builder {
            period,
            days,
            farm,
            printers,
            folders,
            materials,
            ..
        } = self;
        Stats {
            from: period.from,
            to: period.to,
            days: days.iter().map(|d| date_of(d.0)).collect(),
            farm: farm.finish("farm".into(), &period, &days, false),
            printers: printers
                .into_iter()
                .map(|(n, s)| s.finish(n, &period, &days, true))
                .collect(),
            folders: folders
                .into_iter()
                .map(|(n, s)| s.finish(n, &period, &days, false))
                .collect(),
            materials: materials
                .into_iter()
                .map(|(n, s)| s.finish(n, &period, &days, false))
                .collect(),
        }
    }
}

/// How long two intervals overlap.
fn overlap(a: (f64, f64), b: (f64, f64)) -> f64 {
    (a.1.min(b.1) - a.0.max(b.0)).max(0.0)
}

/// A failure reason as counted: its first line, at most [`REASON_CHARS`] characters.
fn reason_key(reason: Option<&str>) -> String {
    let first = reason.and_then(|r| r.lines().next()).unwrap_or("");
    if first.trim().is_empty() {
        return "(no reason given)".into();
    }
    first.chars().take(REASON_CHARS).collect()
}

/// One printer's counters since the process started.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct PrinterTally {
    pub done: u64,
    pub failed: u64,
    pub cancelled: u64,
    pub printing_s: f64,
    /// Prints that ended (a copy each), and filament of those that finished.
    pub prints: u64,
    pub filament_m: f64,
    pub resends: u64,
    pub silence_probes: u64,
}

/// Counters of what jobs did since the process started, by printer: kept by the store's
/// task, which counts every state change it publishes ([`Tally::count`]), this host's and,
/// in a shared farm, the other hosts' it takes in, and published in its snapshot for
/// `/metrics`. Monotonic while the process runs; a restart starts them again from zero,
/// which Prometheus' `rate()` and `increase()` take as a counter reset. Every host of a
/// shared farm sees the whole farm, so each reports the farm's figures (not its share).
#[derive(Debug, Clone, Default, PartialEq)]
pub struct Tally(BTreeMap<String, PrinterTally>);

impl Tally {
    /// Counts `job`'s state change `k` (its entry in `job.history`). Jobs without a printer
    /// (a failed preparation) have nothing to count.
    pub(crate) fn count(&mut self, job: &Job, k: usize) {
        let Some(printer) = &job.printer else { return };
        let Some(&(now_state, at)) = job.history.get(k) else {
            return;
        };
        let left = k.checked_sub(1).and_then(|i| job.history.get(i));
        let t = self.0.entry(printer.clone()).or_default();
        if let Some(&(JobState::Printing, started)) = left {
            t.printing_s += (at - started).max(0.0);
            t.prints += 1;
            // The job's reports are of its last print: only that change has them.
            let last = k + 1 == job.history.len();
            if last && matches!(now_state, JobState::Done | JobState::Ready) {
                let mm = job.slice_report.as_ref().and_then(|r| r.filament_mm);
                t.filament_m += mm.unwrap_or(0.0) / 1000.0;
            }
            if let (true, Some(report)) = (last, &job.print_report) {
                t.resends += report.resends;
                t.silence_probes += report.silence_probes;
            }
        }
        match now_state {
            JobState::Done => t.done += 1,
            JobState::Failed => t.failed += 1,
            JobState::Cancelled => t.cancelled += 1,
            _ => {}
        }
    }

    /// The counters of each printer that has any.
    pub fn read(&self) -> BTreeMap<String, PrinterTally> {
        self.0.clone()
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::path::PathBuf;

    fn record(seq: u64, state: JobState, printing: &[(f64, f64)], ended: f64) -> Retired {
        Retired {
            id: format!("{seq:04}-x"),
            seq,
            file: "x.stl".into(),
            folder: PathBuf::from("/srv/hot/parts"),
            state,
            reason: (state == JobState::Failed).then(|| "thermal runaway\nat line 12".into()),
            printer: Some("p1".into()),
            machine: None,
            height_mm: None,
            enhancement: None,
            lambda2: None,
            queued_at: 0.0,
            started_at: printing.first().map(|p| p.0),
            ended_at: ended,
            copies_done: u32::from(state == JobState::Done),
            copy: None,
            resends: None,
            print_s: None,
            filament_mm: Some(1000.0),
            filament_g: Some(3.0),
            dir: PathBuf::from("/d"),
            retired_at: ended,
            printing: printing.to_vec(),
            material: None,
            used_g: None,
            cost: None,
            moved: None,
        }
    }

    const D0: f64 = 20_000.0 * DAY;

    #[test]
    fn utilisation_is_split_at_midnight() {
        // Two days; a print from 22:00 on day 1 to 04:00 on day 2.
        let period = Period::new(D0, D0 + 2.0 * DAY).unwrap();
        let mut b = Builder::new(period, &["p1".into(), "p2".into()], &[]);
        let (start, end) = (D0 + 22.0 * 3600.0, D0 + DAY + 4.0 * 3600.0);
        b.add(&record(1, JobState::Done, &[(start, end)], end));
        let s = b.finish();
        assert_eq!(s.days, [date_of(D0), date_of(D0 + DAY)]);
        let p1 = &s.printers[0];
        assert_eq!(p1.name, "p1");
        assert_eq!(p1.printing_s, 6.0 * 3600.0);
        assert_eq!(p1.utilisation, Some(6.0 / 48.0));
        assert_eq!(p1.daily_utilisation, Some(vec![2.0 / 24.0, 4.0 / 24.0]));
        assert_eq!(p1.jobs.done, 1);
        assert_eq!((p1.filament_mm, p1.filament_g), (1000.0, 3.0));
        // A printer that did nothing is listed with zeros.
        assert_eq!(s.printers[1].utilisation, Some(0.0));
        assert_eq!(s.folders[0].name, "parts");
        assert_eq!(s.farm.jobs.done, 1);
        assert_eq!(s.farm.utilisation, None);
    }

    #[test]
    fn a_job_across_the_period_edge() {
        // The period starts at noon: a print from 10:00 to 14:00 counts 2 h, and its
        // outcome counts (it ended inside); one that ended before counts nothing; one
        // printing past the end counts its time inside, not its outcome.
        let period = Period::new(D0 + 12.0 * 3600.0, D0 + DAY).unwrap();
        let mut b = Builder::new(period, &[], &[]);
        let h = |x: f64| D0 + x * 3600.0;
        b.add(&record(1, JobState::Failed, &[(h(10.0), h(14.0))], h(14.0)));
        b.add(&record(2, JobState::Done, &[(h(8.0), h(11.0))], h(11.0)));
        b.add(&record(3, JobState::Done, &[(h(23.0), h(26.0))], h(26.0)));
        // The same job again (live on one host, retired on another) counts once.
        b.add(&record(1, JobState::Failed, &[(h(10.0), h(14.0))], h(14.0)));
        let s = b.finish();
        assert_eq!(s.days.len(), 1);
        let p1 = &s.printers[0];
        assert_eq!(p1.printing_s, 3.0 * 3600.0);
        assert_eq!(p1.utilisation, Some(3.0 / 12.0));
        assert_eq!(p1.daily_utilisation, Some(vec![3.0 / 12.0]));
        assert_eq!(
            p1.jobs,
            Outcomes {
                done: 0,
                failed: 1,
                cancelled: 0
            }
        );
        assert_eq!(
            p1.failure_reasons,
            [Reason {
                reason: "thermal runaway".into(),
                jobs: 1
            }]
        );
        assert_eq!(p1.filament_mm, 0.0, "a failed job printed no whole copy");
    }

    /// Used filament, cost and printing time per printer, folder and material: weighed
    /// where the job was, else estimated; a cost only where a price was known.
    #[test]
    fn used_filament_and_cost_per_material() {
        let period = Period::new(D0, D0 + DAY).unwrap();
        let mut b = Builder::new(period, &["p1".into(), "p2".into()], &[]);
        let h = |x: f64| D0 + x * 3600.0;
        // Two copies of PETG, weighed and priced.
        let mut two = record(
            1,
            JobState::Done,
            &[(h(1.0), h(2.0)), (h(3.0), h(4.0))],
            h(4.0),
        );
        two.copies_done = 2;
        (two.material, two.used_g, two.cost) = (Some("PETG".into()), Some(7.0), Some(0.14));
        b.add(&two);
        // A failed PETG print, part of it weighed and priced.
        let mut failed = record(2, JobState::Failed, &[(h(5.0), h(5.5))], h(5.5));
        (failed.material, failed.used_g, failed.cost) =
            (Some("PETG".into()), Some(1.0), Some(0.02));
        b.add(&failed);
        // PLA weighed, its price unknown, on p2.
        let mut pla = record(3, JobState::Done, &[(h(6.0), h(8.0))], h(8.0));
        (pla.material, pla.used_g, pla.printer) =
            (Some("PLA".into()), Some(4.0), Some("p2".into()));
        b.add(&pla);
        // An old record, not weighed: its estimate (3 g a copy), in no material.
        b.add(&record(4, JobState::Done, &[(h(9.0), h(10.0))], h(10.0)));
        let s = b.finish();

        let p1 = &s.printers[0];
        assert_eq!(p1.used_g, 7.0 + 1.0 + 3.0);
        assert!((p1.cost.unwrap() - 0.16).abs() < 1e-9);
        assert_eq!(p1.printing_s, 3.5 * 3600.0);
        assert_eq!(
            p1.filament_g,
            3.0 * 3.0,
            "the estimate: copies printed only"
        );
        let p2 = &s.printers[1];
        assert_eq!(
            (p2.used_g, p2.cost),
            (4.0, None),
            "no price: no cost, not 0"
        );
        assert_eq!(s.farm.used_g, 15.0);
        assert_eq!(s.folders[0].used_g, 15.0);

        let names: Vec<&str> = s.materials.iter().map(|m| m.name.as_str()).collect();
        assert_eq!(names, ["PETG", "PLA"]);
        let petg = &s.materials[0];
        assert_eq!((petg.jobs.done, petg.jobs.failed), (1, 1));
        assert_eq!(petg.used_g, 8.0);
        assert!((petg.cost.unwrap() - 0.16).abs() < 1e-9);
        assert_eq!(petg.printing_s, 2.5 * 3600.0);
        assert_eq!(petg.utilisation, None);
        let pla = &s.materials[1];
        assert_eq!((pla.jobs.done, pla.used_g, pla.cost), (1, 4.0, None));
        assert_eq!(pla.printing_s, 2.0 * 3600.0);

        // Statistics from before materials were counted still read.
        let mut old = serde_json::to_value(&s).unwrap();
        old.as_object_mut().unwrap().remove("materials");
        for field in ["used_g", "cost"] {
            old["farm"].as_object_mut().unwrap().remove(field);
        }
        let read: Stats = serde_json::from_value(old).unwrap();
        assert!(read.materials.is_empty());
        assert_eq!((read.farm.used_g, read.farm.cost), (0.0, None));
    }

    #[test]
    fn periods_and_dates() {
        assert!(Period::new(10.0, 10.0).is_err());
        assert!(Period::new(0.0, 401.0 * DAY).is_err());
        assert!(Period::new(f64::NAN, 1.0).is_err());
        let p = Period::last_days(7, D0 + 5.0).unwrap();
        assert_eq!((p.from, p.to), (D0 - 6.0 * DAY, D0 + DAY));
        assert_eq!(p.days().len(), 7);
        assert_eq!(parse_time("2024-02-29").unwrap(), 19_782.0 * DAY);
        assert_eq!(parse_time("1970-01-01").unwrap(), 0.0);
        assert_eq!(parse_time("1700000000").unwrap(), 1_700_000_000.0);
        assert!(parse_time("2026-02-31").is_err());
        assert!(parse_time("yesterday").is_err());
        assert!(parse_time("-5").is_err());
    }

    #[test]
    fn the_tally_counts_each_print_once() {
        let mut job = Job::queued("0001-x".into(), 1, "x.stl".into(), "/hot".into());
        job.printer = Some("p1".into());
        let mut tally = Tally::default();
        let mut step = |state: JobState, at: f64| {
            job.state = state;
            job.history.push((state, at));
            tally.count(&job, job.history.len() - 1);
        };
        step(JobState::Printing, 100.0);
        step(JobState::Ready, 160.0); // a copy
        step(JobState::Printing, 200.0);
        step(JobState::Failed, 230.0);
        let t = &tally.read()["p1"];
        assert_eq!((t.printing_s, t.prints, t.failed, t.done), (90.0, 2, 1, 0));
    }
}
