//! A printer's care by use: what it has done ([`Counts`]: print time, filament by
//! material, prints, failures), the `[[maintenance]]` tasks that fall due by those counts
//! or by days ([`Task`], [`status`]), the work recorded when one is done, and a printer
//! held out of the queue by hand ([`PrinterCare::held`]).
//!
//! The records live with the farm's spools (`Inventory::care`): one document in both
//! stores, changed under its row's lock in PostgreSQL, so every host sees the same counts
//! and a restart keeps them. A print is counted once, by whichever host's store first sees
//! its use in the job's record (the store's catch-up of the spools' ledgers, which calls
//! [`count`]: keyed by the use as the ledgers are). A task done keeps the counts it was done at, and falls due again when
//! the counts have grown by its interval since: a pruned history changes nothing. Nothing
//! here does I/O or reads a clock.

use serde::{Deserialize, Serialize};
use std::collections::BTreeMap;

/// What a printer has done since its counting began (its first print counted).
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct Counts {
    /// Seconds printing, from each print's start to its end.
    pub print_s: f64,
    /// Prints that pushed filament, whatever their end (each heated the printer up once).
    pub prints: u64,
    /// Of those, the ones that failed.
    pub failed: u64,
    pub filament_mm: f64,
    /// Grams of the prints whose filament was known (see [`Counts::materials`]).
    pub filament_g: f64,
    /// Grams of abrasive filament (carbon or glass fibre, glow-in-the-dark).
    pub abrasive_g: f64,
    /// By material, as the printer's spool or its default filament named it (`unknown`
    /// for prints whose filament was not known: their metres only).
    #[serde(default)]
    pub materials: BTreeMap<String, MaterialCount>,
}

/// A material's share of [`Counts`].
#[derive(Debug, Clone, Copy, Default, PartialEq, Serialize, Deserialize)]
pub struct MaterialCount {
    pub mm: f64,
    pub g: f64,
}

/// One print as counted: what its use in the job's record says.
#[derive(Debug, Clone, Copy)]
pub(crate) struct Print<'a> {
    pub print_s: f64,
    pub failed: bool,
    pub material: &'a str,
    pub mm: f64,
    pub g: f64,
    pub abrasive: bool,
}

impl Counts {
    pub(crate) fn add(&mut self, p: Print<'_>) {
        // A record's figures are bounded where they are made; a bad one still never makes
        // a count go back or become NaN.
        let sane = |x: f64| if x.is_finite() { x.max(0.0) } else { 0.0 };
        self.print_s += sane(p.print_s);
        self.prints += 1;
        self.failed += u64::from(p.failed);
        self.filament_mm += sane(p.mm);
        self.filament_g += sane(p.g);
        if p.abrasive {
            self.abrasive_g += sane(p.g);
        }
        let m = self.materials.entry(p.material.to_string()).or_default();
        m.mm += sane(p.mm);
        m.g += sane(p.g);
    }

    /// What was done between `then` and these counts (a count never goes back; none below
    /// zero).
    pub fn since(&self, then: &Counts) -> Counts {
        let d = |a: f64, b: f64| (a - b).max(0.0);
        Counts {
            print_s: d(self.print_s, then.print_s),
            prints: self.prints.saturating_sub(then.prints),
            failed: self.failed.saturating_sub(then.failed),
            filament_mm: d(self.filament_mm, then.filament_mm),
            filament_g: d(self.filament_g, then.filament_g),
            abrasive_g: d(self.abrasive_g, then.abrasive_g),
            materials: self
                .materials
                .iter()
                .map(|(k, v)| {
                    let t = then.materials.get(k).copied().unwrap_or_default();
                    (
                        k.clone(),
                        MaterialCount {
                            mm: d(v.mm, t.mm),
                            g: d(v.g, t.g),
                        },
                    )
                })
                .collect(),
        }
    }
}

/// Counts `print` (the use `key`, ended at `at_s`) on `printer`'s record, once: a key
/// counted before is passed over. Says whether it was new.
pub(crate) fn count(
    care: &mut BTreeMap<String, PrinterCare>,
    printer: &str,
    key: &str,
    at_s: f64,
    print: Print<'_>,
) -> bool {
    let record = care.entry(printer.to_string()).or_default();
    if record.counted.contains_key(key) {
        return false;
    }
    record.counted.insert(key.to_string(), at_s);
    record.counts.add(print);
    if record.since_s == 0.0 {
        record.since_s = at_s;
    }
    true
}

/// Keeps the counted keys of [`PrinterCare::counted`] as long as a print could come again:
/// a key whose job is live here (`live`) is marked seen at `now`; one not seen live for
/// `kept_s` is forgotten (every host of a shared farm has seen its job leave by then).
pub(crate) fn refresh(
    care: &mut BTreeMap<String, PrinterCare>,
    live: impl Fn(&str) -> bool,
    now: f64,
    kept_s: f64,
) {
    for record in care.values_mut() {
        record.counted.retain(|key, seen| {
            if live(key) {
                *seen = now;
                true
            } else {
                now - *seen < kept_s
            }
        });
    }
}

/// Whether a counted key of a live job (`live`) was last marked seen more than `every_s`
/// before `now`: [`refresh`] is due, so that a job long live is kept a whole `kept_s` from
/// when it leaves.
pub(crate) fn stale(
    care: &BTreeMap<String, PrinterCare>,
    live: impl Fn(&str) -> bool,
    now: f64,
    every_s: f64,
) -> bool {
    care.values()
        .flat_map(|r| r.counted.iter())
        .any(|(key, seen)| live(key) && now - seen > every_s)
}

/// A printer's care record: its counts, the work done on it, and whether it is held.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct PrinterCare {
    /// When its counting began (days-long intervals of a task never done count from here).
    pub since_s: f64,
    pub counts: Counts,
    /// The uses counted (`<job>#<n>`), each with when its job was last seen live (at first,
    /// when its print ended), kept a day after its job left, so that no host whose view is
    /// a moment behind counts one twice (see [`refresh`]).
    #[serde(default)]
    pub counted: BTreeMap<String, f64>,
    /// Each task's last time done, with the counts then.
    #[serde(default)]
    pub done: BTreeMap<String, Done>,
    /// Held out of the queue by hand: it finishes its print, then takes no job.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub held: Option<Work>,
    /// The work recorded, oldest first, at most [`LOG`] entries.
    #[serde(default)]
    pub log: Vec<Logged>,
}

/// How many entries of work a printer's log keeps.
pub const LOG: usize = 200;

/// Who did something, when, and what they noted.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Work {
    pub at_s: f64,
    pub by: String,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub note: Option<String>,
}

/// A task done, and the printer's counts when it was.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Done {
    pub work: Work,
    pub counts: Counts,
}

/// An entry of a printer's log of work.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Logged {
    pub what: Did,
    pub work: Work,
}

/// What was recorded.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case", tag = "kind", content = "task")]
pub enum Did {
    /// A task was done.
    Done(String),
    /// The printer was taken out of the queue by hand, or given back.
    Held,
    Released,
}

/// The longest note an operator may give with their work, in characters.
pub const NOTE_CHARS: usize = 500;
/// The longest name of who did it, in characters.
pub const BY_CHARS: usize = 64;

/// A change of a printer's care record by an operator: the one table of them.
#[derive(Debug, Clone, PartialEq)]
pub enum CareChange {
    Done { task: String, work: Work },
    Hold(Work),
    Release(Work),
}

/// Why a change of a care record was refused.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum CareError {
    #[error("printer {0} is not in maintenance")]
    NotHeld(String),
    #[error("printer {0} is already in maintenance (since it was put there by {1})")]
    AlreadyHeld(String, String),
}

impl CareChange {
    /// Carries the change out on `printer`'s record (made if it has none), logged.
    pub(crate) fn apply(
        self,
        printer: &str,
        care: &mut BTreeMap<String, PrinterCare>,
    ) -> Result<(), CareError> {
        let record = care.entry(printer.to_string()).or_default();
        let logged = match self {
            CareChange::Done { task, work } => {
                let done = Done {
                    work: work.clone(),
                    counts: record.counts.clone(),
                };
                record.done.insert(task.clone(), done);
                Logged {
                    what: Did::Done(task),
                    work,
                }
            }
            CareChange::Hold(work) => {
                if let Some(held) = &record.held {
                    return Err(CareError::AlreadyHeld(printer.into(), held.by.clone()));
                }
                record.held = Some(work.clone());
                Logged {
                    what: Did::Held,
                    work,
                }
            }
            CareChange::Release(work) => {
                if record.held.take().is_none() {
                    return Err(CareError::NotHeld(printer.into()));
                }
                Logged {
                    what: Did::Released,
                    work,
                }
            }
        };
        if record.since_s == 0.0 {
            record.since_s = logged.work.at_s;
        }
        record.log.push(logged);
        let over = record.log.len().saturating_sub(LOG);
        record.log.drain(..over);
        Ok(())
    }
}

/// A `[[maintenance]]` task, checked.
#[derive(Debug, Clone, PartialEq)]
pub struct Task {
    pub name: String,
    /// The printers it applies to by name, and by tag; both empty: every printer.
    pub printers: Vec<String>,
    pub tags: Vec<String>,
    /// Its intervals, each a measure and how much of it: it falls due when any is reached.
    pub every: Vec<(Measure, f64)>,
    /// A due task keeps its printer out of the queue after its print.
    pub block: bool,
}

/// What an interval of a task is measured in.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Measure {
    PrintHours,
    Kg,
    AbrasiveKg,
    /// Prints, whatever their end.
    Jobs,
    Days,
}

impl Measure {
    pub const ALL: [Measure; 5] = [
        Measure::PrintHours,
        Measure::Kg,
        Measure::AbrasiveKg,
        Measure::Jobs,
        Measure::Days,
    ];

    /// The config's key for an interval in it.
    pub fn key(self) -> &'static str {
        match self {
            Measure::PrintHours => "every_print_hours",
            Measure::Kg => "every_kg",
            Measure::AbrasiveKg => "every_abrasive_kg",
            Measure::Jobs => "every_jobs",
            Measure::Days => "every_days",
        }
    }

    /// Its unit as shown.
    pub fn unit(self) -> &'static str {
        match self {
            Measure::PrintHours => "print hours",
            Measure::Kg => "kg",
            Measure::AbrasiveKg => "kg abrasive",
            Measure::Jobs => "prints",
            Measure::Days => "days",
        }
    }

    /// How much of it `used` (the counts since the task was last done) and `days` (since
    /// then) make.
    fn of(self, used: &Counts, days: f64) -> f64 {
        match self {
            Measure::PrintHours => used.print_s / 3600.0,
            Measure::Kg => used.filament_g / 1000.0,
            Measure::AbrasiveKg => used.abrasive_g / 1000.0,
            Measure::Jobs => used.prints as f64,
            Measure::Days => days,
        }
    }
}

impl Task {
    /// Whether it applies to a printer of this name and these tags.
    pub fn applies_to(&self, printer: &str, tags: &[String]) -> bool {
        (self.printers.is_empty() && self.tags.is_empty())
            || self.printers.iter().any(|p| p == printer)
            || self.tags.iter().any(|t| tags.contains(t))
    }
}

/// Where one task stands on one printer.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct TaskStatus {
    pub task: String,
    pub block: bool,
    pub due: bool,
    /// Each interval: its measure, how much of it was used since the task was last done,
    /// and the interval.
    pub intervals: Vec<Interval>,
    pub last_done: Option<Work>,
}

/// One interval of a [`TaskStatus`].
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Interval {
    pub measure: Measure,
    pub used: f64,
    pub every: f64,
}

impl Interval {
    pub fn reached(&self) -> bool {
        self.used >= self.every
    }
}

/// `2.1 of 3 kg`: what was used, to a tenth, of the interval.
impl std::fmt::Display for Interval {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(
            f,
            "{} of {} {}",
            crate::names::number((self.used * 10.0).round() / 10.0),
            crate::names::number(self.every),
            self.measure.unit()
        )
    }
}

/// Where each of a printer's `tasks` stands at `now_s`, given its care record (None: it
/// has printed nothing counted and had no work done).
pub fn status<'a>(
    tasks: impl IntoIterator<Item = &'a Task>,
    care: Option<&PrinterCare>,
    now_s: f64,
) -> Vec<TaskStatus> {
    let empty = PrinterCare::default();
    let care = care.unwrap_or(&empty);
    tasks
        .into_iter()
        .map(|t| {
            let done = care.done.get(&t.name);
            let used = done.map_or_else(|| care.counts.clone(), |d| care.counts.since(&d.counts));
            // A printer that never printed nor had work done has no time counted yet.
            let from = done.map_or(care.since_s, |d| d.work.at_s);
            let days = if from > 0.0 {
                ((now_s - from) / 86_400.0).max(0.0)
            } else {
                0.0
            };
            let intervals: Vec<Interval> = t
                .every
                .iter()
                .map(|&(measure, every)| Interval {
                    measure,
                    used: measure.of(&used, days),
                    every,
                })
                .collect();
            TaskStatus {
                task: t.name.clone(),
                block: t.block,
                due: intervals.iter().any(Interval::reached),
                intervals,
                last_done: done.map(|d| d.work.clone()),
            }
        })
        .collect()
}

/// Why a printer takes no job for its care, if it takes none.
#[derive(Debug, Clone, PartialEq)]
pub enum Kept {
    /// Held by hand.
    Held(Work),
    /// These blocking tasks are due.
    Due(Vec<String>),
}

/// Whether the printer is kept out of the queue: held by hand, or one of its blocking
/// `tasks` due.
pub fn kept<'a>(
    tasks: impl IntoIterator<Item = &'a Task>,
    care: Option<&PrinterCare>,
    now_s: f64,
) -> Option<Kept> {
    if let Some(held) = care.and_then(|c| c.held.as_ref()) {
        return Some(Kept::Held(held.clone()));
    }
    let due: Vec<String> = status(tasks, care, now_s)
        .into_iter()
        .filter(|s| s.block && s.due)
        .map(|s| s.task)
        .collect();
    (!due.is_empty()).then_some(Kept::Due(due))
}

impl Kept {
    /// What the printer's tile and status say.
    pub fn describe(&self) -> String {
        match self {
            Kept::Held(w) => match &w.note {
                Some(note) => format!("in maintenance (by {}: {note})", w.by),
                None => format!("in maintenance (by {})", w.by),
            },
            Kept::Due(tasks) => format!(
                "maintenance due: {}; `crispen maintenance done PRINTER TASK` when done",
                tasks.join(", ")
            ),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn print(g: f64, failed: bool) -> Print<'static> {
        Print {
            print_s: 1800.0,
            failed,
            material: "PLA",
            mm: g * 330.0,
            g,
            abrasive: false,
        }
    }

    fn work(at_s: f64) -> Work {
        Work {
            at_s,
            by: "ann".into(),
            note: None,
        }
    }

    fn task(every: Vec<(Measure, f64)>, block: bool) -> Task {
        Task {
            name: "nozzle".into(),
            printers: vec![],
            tags: vec![],
            every,
            block,
        }
    }

    /// Counts grow with each print; a task done keeps the counts of its moment and falls
    /// due again only once the printer has done its interval since.
    #[test]
    fn a_task_falls_due_by_what_was_done_since_it_was_last_done() {
        let tasks = [task(vec![(Measure::Jobs, 2.0), (Measure::Kg, 1.0)], true)];
        let mut care = BTreeMap::new();
        let mut record = PrinterCare {
            since_s: 100.0,
            ..PrinterCare::default()
        };
        record.counts.add(print(300.0, false));
        care.insert("a".to_string(), record);
        assert_eq!(kept(&tasks, care.get("a"), 200.0), None);
        care.get_mut("a").unwrap().counts.add(print(300.0, true));
        let s = status(&tasks, care.get("a"), 200.0);
        assert!(s[0].due, "two prints: {s:?}");
        assert_eq!(s[0].intervals[1].used, 0.6);
        assert_eq!(
            kept(&tasks, care.get("a"), 200.0),
            Some(Kept::Due(vec!["nozzle".into()]))
        );
        CareChange::Done {
            task: "nozzle".into(),
            work: work(300.0),
        }
        .apply("a", &mut care)
        .unwrap();
        assert_eq!(kept(&tasks, care.get("a"), 300.0), None);
        care.get_mut("a").unwrap().counts.add(print(500.0, false));
        let s = status(&tasks, care.get("a"), 300.0);
        assert!(!s[0].due, "one print since: {s:?}");
        assert_eq!(s[0].intervals[0].used, 1.0);
        assert_eq!(s[0].intervals[1].used, 0.5);
        care.get_mut("a").unwrap().counts.add(print(600.0, false));
        assert!(status(&tasks, care.get("a"), 300.0)[0].due);
        let r = &care["a"];
        assert_eq!((r.counts.prints, r.counts.failed), (4, 1));
        assert_eq!(r.log.len(), 1);
    }

    /// Days count from the last time done, else from when counting began; a printer
    /// never counted is never due by days.
    #[test]
    fn days_count_from_the_work_or_the_first_print() {
        let tasks = [task(vec![(Measure::Days, 30.0)], false)];
        assert!(!status(&tasks, None, 1e9)[0].due);
        let record = PrinterCare {
            since_s: 1000.0,
            ..PrinterCare::default()
        };
        assert!(!status(&tasks, Some(&record), 1000.0 + 29.0 * 86_400.0)[0].due);
        assert!(status(&tasks, Some(&record), 1000.0 + 30.0 * 86_400.0)[0].due);
        // Not blocking: due, yet the printer is not kept.
        assert_eq!(kept(&tasks, Some(&record), 1e12), None);
    }

    /// A hold keeps the printer whatever its tasks; holding twice or releasing a printer
    /// not held is refused; the log keeps the newest entries only.
    #[test]
    fn a_printer_held_by_hand_stays_held_until_released() {
        let mut care = BTreeMap::new();
        CareChange::Hold(work(1.0)).apply("a", &mut care).unwrap();
        assert!(matches!(kept(&[], care.get("a"), 2.0), Some(Kept::Held(_))));
        assert!(matches!(
            CareChange::Hold(work(2.0)).apply("a", &mut care),
            Err(CareError::AlreadyHeld(..))
        ));
        CareChange::Release(work(3.0))
            .apply("a", &mut care)
            .unwrap();
        assert_eq!(kept(&[], care.get("a"), 4.0), None);
        assert_eq!(
            CareChange::Release(work(4.0)).apply("a", &mut care),
            Err(CareError::NotHeld("a".into()))
        );
        for i in 0..(LOG + 10) {
            CareChange::Done {
                task: "t".into(),
                work: work(10.0 + i as f64),
            }
            .apply("a", &mut care)
            .unwrap();
        }
        let log = &care["a"].log;
        assert_eq!(log.len(), LOG);
        assert_eq!(log.last().unwrap().work.at_s, 10.0 + (LOG + 9) as f64);
    }

    /// A counted key is marked while its job is live, kept `kept_s` after it was last seen
    /// live, then forgotten; a key of a live job not marked for long is stale.
    #[test]
    fn counted_keys_outlive_their_job_by_the_time_kept() {
        let mut care = BTreeMap::new();
        assert!(count(&mut care, "a", "j1#0", 10.0, print(1.0, false)));
        assert!(
            !count(&mut care, "a", "j1#0", 10.0, print(1.0, false)),
            "once"
        );
        let live = |on: bool| move |key: &str| on && key.starts_with("j1");
        assert!(stale(&care, live(true), 5000.0, 3600.0));
        refresh(&mut care, live(true), 5000.0, 86_400.0);
        assert!(!stale(&care, live(true), 5000.0, 3600.0));
        // It left the view: kept a day from when it was last seen live, not from its print.
        refresh(&mut care, live(false), 5000.0 + 86_000.0, 86_400.0);
        assert!(care["a"].counted.contains_key("j1#0"));
        refresh(&mut care, live(false), 5000.0 + 86_400.0, 86_400.0);
        assert!(care["a"].counted.is_empty());
        assert_eq!(care["a"].counts.prints, 1);
    }

    /// Tasks apply by name, by tag, or to every printer when they name neither.
    #[test]
    fn tasks_apply_by_name_tag_or_to_all() {
        let mut t = task(vec![(Measure::Jobs, 1.0)], false);
        assert!(t.applies_to("x", &[]));
        t.tags = vec!["big".into()];
        assert!(!t.applies_to("x", &[]));
        assert!(t.applies_to("x", &["big".into()]));
        t.printers = vec!["x".into()];
        assert!(t.applies_to("x", &[]));
    }
}
