//! Events derived from the farm's published state, without I/O: [`Observer::observe`] is
//! given the jobs, this host's printers and the farm's hosts as they are now (and the
//! time), compares them with what it saw last, and returns what happened in between.
//! Nothing in the printer or job code calls it; a new printer state (a halted printer, a
//! printer waiting for the operator) needs only its line in [`presence`], whose `match`
//! has no fallback arm so the compiler asks for it.
//!
//! The published state is followed through `watch` channels, which keep the latest value
//! only: a state held for less than one look (a printer offline for a few milliseconds)
//! may pass unseen. A job's final state never passes: it is kept until the job is retried.
//!
//! In a farm shared by several hosts every host sees every job; exactly one sends each
//! event: a job's by the host of the printer that took it (else by the host of the folder
//! it was dropped into), a printer's by its host, a lost host's by the live host whose
//! name sorts first.

use super::event::{Event, EventCopy, EventJob, EventKind};
use crate::daemon::bed::Why;
use crate::daemon::farm::{PrinterState, PrinterStatus};
use crate::daemon::filament::Inventory;
use crate::daemon::job::{Job, JobState};
use crate::daemon::store::postgres::FarmHost;
use std::collections::{BTreeMap, BTreeSet, HashMap};

/// Why `maintenance_due` was told: the task, the intervals it reached, and whether the
/// printer waits for it.
fn due_reason(printer: &str, task: &crate::daemon::care::TaskStatus) -> String {
    let reached: Vec<String> = task
        .intervals
        .iter()
        .filter(|i| i.reached())
        .map(ToString::to_string)
        .collect();
    let then = if task.block {
        format!(
            "{printer} takes no job until `crispen maintenance done {printer} {:?}`",
            task.task
        )
    } else {
        format!(
            "record it with `crispen maintenance done {printer} {:?}`",
            task.task
        )
    };
    format!("{}: {}; {then}", task.task, reached.join(", "))
}

/// How a printer's state counts for notifications.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Presence {
    /// Not known yet (connecting).
    Unknown,
    Online,
    /// Online, and waiting for the operator.
    Waiting,
    Offline,
    /// Its supervisor stopped (shutdown, or removed by a reload): nothing to tell.
    Stopped,
}

/// Every printer state's meaning for notifications; no fallback arm (see the module).
fn presence(state: PrinterState) -> Presence {
    match state {
        PrinterState::Connecting => Presence::Unknown,
        PrinterState::Idle
        | PrinterState::WaitingToHeat
        | PrinterState::Printing
        | PrinterState::BedNotCleared
        | PrinterState::Ejecting
        | PrinterState::CheckingBed
        // Its due task is an event of its own (`maintenance_due`).
        | PrinterState::Maintenance => Presence::Online,
        // A halted printer needs the operator as much as a paused one: it takes no job
        // until it was reset. (A halt that stopped a print is the job's `printer_error`.)
        PrinterState::Paused | PrinterState::WaitingForOperator | PrinterState::Halted => {
            Presence::Waiting
        }
        PrinterState::Disconnected => Presence::Offline,
        // Switched off on purpose (idle, or by hand): nothing to tell.
        PrinterState::Stopped | PrinterState::Off => Presence::Stopped,
    }
}

#[derive(Debug, Clone, Copy)]
struct PrinterSeen {
    presence: Presence,
    /// A `printer_offline` was sent and no `printer_online` since.
    told_offline: bool,
    /// Its bed waits for a person because clearing it by machine stopped (a bed found
    /// not clear, no check possible, a failed eject): `bed_not_clear` was told.
    bed_stopped: bool,
}

/// What the observer was last shown.
#[derive(Debug)]
pub(crate) struct Observer {
    /// This host (`[farm] host`).
    host: String,
    /// The farm is shared with other hosts (`[store]`).
    shared: bool,
    dashboard: Option<String>,
    /// The printers with a camera: their jobs' events carry its snapshot.
    cameras: BTreeSet<String>,
    /// None until the first look, which is the baseline: what was so before this run is
    /// not news.
    jobs: Option<HashMap<String, JobState>>,
    printers: BTreeMap<String, PrinterSeen>,
    /// Whether each host of a shared farm was alive.
    hosts: BTreeMap<String, bool>,
    /// Whether each spool was low (below `[farm] spool_low_g`) at the last look.
    low: BTreeMap<String, bool>,
    /// The `[[maintenance]]` tasks due on each of this host's printers at the last look.
    due: BTreeMap<String, BTreeSet<String>>,
}

/// The farm as it is now, as the observer reads it.
pub(crate) struct Look<'a, J: Iterator<Item = &'a Job>> {
    pub jobs: J,
    /// This host's printers.
    pub printers: &'a [PrinterStatus],
    /// The hosts of a shared farm (empty when not shared).
    pub hosts: &'a [FarmHost],
    /// The farm's spools, and below how many grams one is low.
    pub inventory: &'a Inventory,
    pub spool_low_g: f64,
    /// Seconds since the epoch.
    pub now: f64,
}

impl Observer {
    pub(crate) fn new(host: &str, shared: bool, dashboard: Option<String>) -> Observer {
        Observer {
            host: host.to_string(),
            shared,
            dashboard,
            cameras: BTreeSet::new(),
            jobs: None,
            printers: BTreeMap::new(),
            hosts: BTreeMap::new(),
            low: BTreeMap::new(),
            due: BTreeMap::new(),
        }
    }

    /// Job events on these printers carry the snapshot their camera took.
    pub(crate) fn with_cameras(mut self, printers: BTreeSet<String>) -> Observer {
        self.cameras = printers;
        self
    }

    /// What happened since the last look.
    pub(crate) fn observe<'a>(
        &mut self,
        look: Look<'a, impl Iterator<Item = &'a Job>>,
    ) -> Vec<Event> {
        let first = self.jobs.is_none();
        let mut events = Vec::new();
        let local: BTreeSet<&str> = look.printers.iter().map(|p| p.name.as_str()).collect();

        let before = self.jobs.take().unwrap_or_default();
        let mut now_jobs = HashMap::with_capacity(before.len());
        for job in look.jobs {
            let was = before.get(&job.id).copied();
            now_jobs.insert(job.id.clone(), job.state);
            if first || was == Some(job.state) || !self.mine(job, &local) {
                continue;
            }
            if let Some(kind) = job_event(was, job) {
                events.push(self.job_event(kind, job, look.now));
            }
        }
        self.jobs = Some(now_jobs);

        let mut printers = BTreeMap::new();
        for p in look.printers {
            let now = presence(p.state);
            let seen = self.printers.get(&p.name).copied();
            let mut told_offline = seen.is_some_and(|s| s.told_offline);
            let was = seen.map(|s| s.presence);
            if !first {
                let mut tell = |kind: EventKind| {
                    let mut e = self.event(kind, look.now);
                    e.printer = Some(p.name.clone());
                    e.reason = p.detail.clone();
                    events.push(e);
                };
                match now {
                    Presence::Offline if !told_offline && was != Some(Presence::Stopped) => {
                        tell(EventKind::PrinterOffline);
                        told_offline = true;
                    }
                    Presence::Online | Presence::Waiting if told_offline => {
                        tell(EventKind::PrinterOnline);
                        told_offline = false;
                    }
                    _ => {}
                }
                if now == Presence::Waiting && was != Some(Presence::Waiting) {
                    tell(EventKind::PrinterWaiting);
                }
            }
            let bed_stopped = bed_stopped(&p.bed);
            let was_stopped = seen.is_some_and(|s| s.bed_stopped);
            if !first && bed_stopped && !was_stopped {
                events.push(self.bed_event(p, look.now));
            }
            let due: BTreeSet<String> = p
                .maintenance
                .iter()
                .filter(|t| t.due)
                .map(|t| t.task.clone())
                .collect();
            let was_due = self.due.remove(&p.name).unwrap_or_default();
            for task in p.maintenance.iter().filter(|t| t.due) {
                if !first && !was_due.contains(&task.task) {
                    let mut e = self.event(EventKind::MaintenanceDue, look.now);
                    e.printer = Some(p.name.clone());
                    e.reason = Some(due_reason(&p.name, task));
                    events.push(e);
                }
            }
            self.due.insert(p.name.clone(), due);
            printers.insert(
                p.name.clone(),
                PrinterSeen {
                    presence: now,
                    told_offline,
                    bed_stopped,
                },
            );
        }
        self.printers = printers;

        // The live host whose name sorts first tells of a lost one.
        let first_alive = look
            .hosts
            .iter()
            .filter(|h| h.alive)
            .map(|h| h.name.as_str())
            .chain(std::iter::once(self.host.as_str()))
            .min()
            .map(str::to_string);
        let teller = first_alive.as_deref() == Some(self.host.as_str());
        let mut hosts = BTreeMap::new();
        for h in look.hosts {
            if !first && teller && !h.alive && self.hosts.get(&h.name) == Some(&true) {
                let mut e = self.event(EventKind::HostLost, look.now);
                e.reason = Some(format!(
                    "host {} stopped renewing its lease; its printers show as offline",
                    h.name
                ));
                events.push(e);
            }
            hosts.insert(h.name.clone(), h.alive);
        }
        self.hosts = hosts;

        // A spool that became low: told by the host of the printer holding it (the first
        // live host for one on no printer).
        let mut low = BTreeMap::new();
        for s in look.inventory.spools.values().filter(|s| !s.archived) {
            let Some(left) = s.remaining_g() else {
                continue;
            };
            let is_low = left < look.spool_low_g;
            let holder = look.inventory.holder(&s.id);
            let tells = match holder {
                Some(p) => !self.shared || local.contains(p),
                None => teller,
            };
            if !first && is_low && self.low.get(&s.id) == Some(&false) && tells {
                let mut e = self.event(EventKind::SpoolLow, look.now);
                e.printer = holder.map(str::to_string);
                e.reason = Some(format!(
                    "{} has {left:.0} g left, below [farm] spool_low_g ({:.0} g): load a fuller spool before a long print",
                    s.describe_filament(),
                    look.spool_low_g
                ));
                events.push(e);
            }
            low.insert(s.id.clone(), is_low);
        }
        self.low = low;
        events
    }

    /// `bed_not_clear` of printer `p`: why, the job on its bed, and the marked picture of
    /// the camera's check when there is one (under the dashboard's address).
    fn bed_event(&self, p: &PrinterStatus, now: f64) -> Event {
        let mut e = self.event(EventKind::BedNotClear, now);
        e.printer = Some(p.name.clone());
        e.reason = p.bed.describe();
        if let (
            Some(dashboard),
            crate::daemon::bed::Bed::Waiting {
                why: Some(Why::NotClear { check }),
            },
        ) = (&self.dashboard, &p.bed)
        {
            if let Some(picture) = &check.picture {
                e.snapshot = Some(format!(
                    "{dashboard}/api/v1/printers/{}/bed/{}",
                    crate::percent::percent_encode(&p.name),
                    crate::percent::percent_encode(
                        std::path::Path::new(picture)
                            .file_name()
                            .map(|n| n.to_string_lossy())
                            .unwrap_or_default()
                            .as_ref()
                    )
                ));
            }
        }
        e
    }

    /// Whether this host tells of `job` (see the module on shared farms).
    fn mine(&self, job: &Job, local: &BTreeSet<&str>) -> bool {
        if !self.shared {
            return true;
        }
        match (&job.printer, &job.origin) {
            (Some(p), _) => local.contains(p.as_str()),
            (None, Some(origin)) => origin.host == self.host,
            (None, None) => true,
        }
    }

    fn event(&self, kind: EventKind, now: f64) -> Event {
        let mut e = Event::new(kind, now, &self.host);
        e.link = self.dashboard.clone();
        e
    }

    fn job_event(&self, kind: EventKind, job: &Job, now: f64) -> Event {
        let mut e = self.event(kind, now);
        e.printer = job.printer.clone();
        e.reason = job.reason.clone();
        // The dashboard's page of the job.
        if let Some(link) = &mut e.link {
            link.push_str("/#job/");
            link.push_str(&crate::percent::percent_encode(&job.id));
        }
        // The picture the printer's camera took as the print ended (see `camera::recorder`).
        let picture = match kind {
            EventKind::JobDone => Some("end.jpg"),
            EventKind::JobFailed
            | EventKind::JobCancelled
            | EventKind::JobInterrupted
            | EventKind::PrinterError => Some("failure.jpg"),
            EventKind::PrinterOffline
            | EventKind::PrinterOnline
            | EventKind::PrinterWaiting
            | EventKind::HostLost
            | EventKind::SpoolLow
            | EventKind::BedNotClear
            | EventKind::MaintenanceDue
            | EventKind::Test => None,
        };
        if let (Some(dashboard), Some(picture), Some(printer)) =
            (&self.dashboard, picture, &job.printer)
        {
            if self.cameras.contains(printer) {
                e.snapshot = Some(format!(
                    "{dashboard}/api/v1/jobs/{}/camera/{picture}",
                    crate::percent::percent_encode(&job.id)
                ));
            }
        }
        let total = job.copies_wanted();
        e.job = Some(EventJob {
            id: job.id.clone(),
            file: job.file.clone(),
            folder: job.folder.display().to_string(),
            copy: (total > 1).then(|| EventCopy {
                of: job.group().to_string(),
                n: job.copy_number(),
                total,
            }),
        });
        e
    }
}

/// A bed that waits for a person because clearing it by machine stopped.
fn bed_stopped(bed: &crate::daemon::bed::Bed) -> bool {
    use crate::daemon::bed::Bed;
    match bed {
        Bed::Waiting { why } => why.is_some(),
        Bed::Clear { .. } | Bed::EjectDue { .. } | Bed::Ejecting { .. } | Bed::CheckDue { .. } => {
            false
        }
    }
}

/// The event of a job now in `job.state`, last seen in `was` (None: new since).
fn job_event(was: Option<JobState>, job: &Job) -> Option<EventKind> {
    match job.state {
        JobState::Done => Some(EventKind::JobDone),
        JobState::Failed if was == Some(JobState::Printing) && by_the_printer(job) => {
            Some(EventKind::PrinterError)
        }
        JobState::Failed => Some(EventKind::JobFailed),
        JobState::Cancelled => Some(EventKind::JobCancelled),
        JobState::Interrupted => Some(EventKind::JobInterrupted),
        JobState::Queued | JobState::Preparing | JobState::Ready | JobState::Printing => None,
    }
}

/// The print failed by an error the printer reported (a thermal runaway or other kill,
/// which Marlin answers with a fatal error; a reset), as the print's error words it
/// (`marlin::stream::PrintError`).
fn by_the_printer(job: &Job) -> bool {
    job.reason
        .as_deref()
        .is_some_and(|r| r.contains("stopped with a fatal error") || r.contains("reset itself"))
}

#[cfg(test)]
mod tests {
    use super::*;

    fn job(id: &str, state: JobState, printer: Option<&str>) -> Job {
        let mut j: Job = serde_json::from_value(serde_json::json!({
            "id": id, "seq": 1, "file": "a.gcode", "folder": "/hot", "state": "queued",
            "history": [], "printer": null, "reason": null, "sidecar": null,
            "slice_report": null, "print_report": null,
        }))
        .unwrap();
        j.state = state;
        j.printer = printer.map(str::to_string);
        j
    }

    fn printer(name: &str, state: PrinterState) -> PrinterStatus {
        PrinterStatus {
            name: name.into(),
            state,
            firmware: "marlin2".into(),
            port: "/dev/x".into(),
            job: None,
            progress: None,
            temperatures: None,
            detail: Some("why".into()),
            bed_cleared: true,
            host: None,
            offline: false,
            holds: None,
            bed: Default::default(),
            last_check: None,
            looked_at: 0,
            maintenance: Vec::new(),
            care: None,
            held: None,
            switchable: false,
        }
    }

    fn look<'a>(
        o: &mut Observer,
        jobs: &'a [Job],
        printers: &'a [PrinterStatus],
        hosts: &'a [FarmHost],
    ) -> Vec<&'static str> {
        o.observe(Look {
            jobs: jobs.iter(),
            printers,
            hosts,
            inventory: &Inventory::default(),
            spool_low_g: 100.0,
            now: 1000.0,
        })
        .iter()
        .map(|e| e.event.name())
        .collect()
    }

    /// Every job outcome is told once, what was so at the start is not, and a job
    /// failed by the printer's own error is a printer error.
    #[test]
    fn job_outcomes_are_told_once() {
        let mut o = Observer::new("h", false, Some("http://farm".into()));
        let p = [printer("p", PrinterState::Idle)];
        let old = job("old", JobState::Failed, None);
        assert!(
            look(&mut o, std::slice::from_ref(&old), &p, &[]).is_empty(),
            "baseline"
        );
        let mut a = job("a", JobState::Printing, Some("p"));
        let b = job("b", JobState::Queued, None);
        assert!(look(&mut o, &[old.clone(), a.clone(), b.clone()], &p, &[]).is_empty());
        a.state = JobState::Done;
        let c = job("c", JobState::Cancelled, None);
        let both = [old.clone(), a.clone(), b.clone(), c.clone()];
        assert_eq!(look(&mut o, &both, &p, &[]), ["job_done", "job_cancelled"]);
        assert!(look(&mut o, &both, &p, &[]).is_empty(), "told once");
        let mut d = job("d", JobState::Printing, Some("p"));
        assert!(look(&mut o, &[d.clone()], &p, &[]).is_empty());
        d.state = JobState::Failed;
        d.reason = Some("printer on /dev/x stopped with a fatal error: Thermal Runaway".into());
        assert_eq!(look(&mut o, &[d.clone()], &p, &[]), ["printer_error"]);
        let mut e = job("e", JobState::Preparing, None);
        assert!(look(&mut o, &[e.clone()], &p, &[]).is_empty());
        e.state = JobState::Failed;
        assert_eq!(look(&mut o, &[e.clone()], &p, &[]), ["job_failed"]);
        let made = o.observe(Look {
            jobs: [job("f", JobState::Interrupted, Some("p"))].iter(),
            printers: &p,
            hosts: &[],
            inventory: &Inventory::default(),
            spool_low_g: 100.0,
            now: 5.0,
        });
        assert_eq!(made.len(), 1);
        let f = &made[0];
        assert_eq!(f.event, EventKind::JobInterrupted);
        assert_eq!(f.job.as_ref().unwrap().id, "f");
        assert_eq!(f.printer.as_deref(), Some("p"));
        assert_eq!(f.link.as_deref(), Some("http://farm/#job/f"));
        assert_eq!(f.snapshot, None, "p has no camera");
    }

    /// A printer's camera puts the picture of the print's end in its jobs' events: the
    /// last one for a done job, the failure's for the others; other printers' have none.
    #[test]
    fn job_events_carry_the_camera_snapshot() {
        let mut o = Observer::new("h", false, Some("http://farm".into()))
            .with_cameras(["cam".to_string()].into());
        let p = [
            printer("cam", PrinterState::Idle),
            printer("blind", PrinterState::Idle),
        ];
        let printing = [
            job("a", JobState::Printing, Some("cam")),
            job("b", JobState::Printing, Some("cam")),
            job("c", JobState::Printing, Some("blind")),
        ];
        assert!(look(&mut o, &printing, &p, &[]).is_empty());
        let mut ended = printing.clone();
        ended[0].state = JobState::Done;
        ended[1].state = JobState::Cancelled;
        ended[2].state = JobState::Done;
        let made = o.observe(Look {
            jobs: ended.iter(),
            printers: &p,
            hosts: &[],
            inventory: &Inventory::default(),
            spool_low_g: 100.0,
            now: 5.0,
        });
        let snapshots: Vec<Option<&str>> = made.iter().map(|e| e.snapshot.as_deref()).collect();
        assert_eq!(
            snapshots,
            [
                Some("http://farm/api/v1/jobs/a/camera/end.jpg"),
                Some("http://farm/api/v1/jobs/b/camera/failure.jpg"),
                None
            ]
        );
    }

    /// A printer offline is told once however often it retries, and its return once;
    /// a paused printer waits for the operator; a stopped supervisor is no news.
    #[test]
    fn printer_presence_is_told_on_change() {
        let mut o = Observer::new("h", false, None);
        let at = |s| [printer("p", s)];
        assert!(look(&mut o, &[], &at(PrinterState::Connecting), &[]).is_empty());
        let offline = at(PrinterState::Disconnected);
        assert_eq!(look(&mut o, &[], &offline, &[]), ["printer_offline"]);
        assert!(look(&mut o, &[], &at(PrinterState::Connecting), &[]).is_empty());
        assert!(look(&mut o, &[], &offline, &[]).is_empty(), "told once");
        assert_eq!(
            look(&mut o, &[], &at(PrinterState::Idle), &[]),
            ["printer_online"]
        );
        assert!(look(&mut o, &[], &at(PrinterState::Printing), &[]).is_empty());
        assert_eq!(
            look(&mut o, &[], &at(PrinterState::Paused), &[]),
            ["printer_waiting"]
        );
        assert!(look(&mut o, &[], &at(PrinterState::Paused), &[]).is_empty());
        assert!(look(&mut o, &[], &at(PrinterState::Stopped), &[]).is_empty());
        assert!(look(&mut o, &[], &offline, &[]).is_empty(), "after a stop");
    }

    /// In a shared farm a job is told by its printer's host only, a lost host by the
    /// first live host only.
    #[test]
    fn a_shared_farm_tells_each_event_once() {
        let hosts = |b_alive| {
            [
                FarmHost {
                    name: "a".into(),
                    alive: true,
                    last_seen: 0.0,
                },
                FarmHost {
                    name: "b".into(),
                    alive: b_alive,
                    last_seen: 0.0,
                },
                FarmHost {
                    name: "c".into(),
                    alive: true,
                    last_seen: 0.0,
                },
            ]
        };
        let mut a = Observer::new("a", true, None);
        let mut c = Observer::new("c", true, None);
        let pa = [printer("pa", PrinterState::Idle)];
        let pc = [printer("pc", PrinterState::Idle)];
        let jobs = [job("1", JobState::Printing, Some("pc"))];
        for (o, p) in [(&mut a, &pa), (&mut c, &pc)] {
            assert!(look(o, &jobs, p, &hosts(true)).is_empty());
            assert!(look(o, &jobs, p, &hosts(true)).is_empty());
        }
        let done = [job("1", JobState::Done, Some("pc"))];
        assert_eq!(look(&mut a, &done, &pa, &hosts(false)), ["host_lost"]);
        assert_eq!(look(&mut c, &done, &pc, &hosts(false)), ["job_done"]);
    }

    /// A spool that falls below the threshold is told once, by the host of its printer;
    /// one already low at the first look is not news.
    #[test]
    fn a_spool_falling_low_is_told_once() {
        use crate::daemon::filament::{Report, Use};
        let mut inv = Inventory::default();
        let f = crate::daemon::filament::tests::petg_black();
        let id = inv.add_spool(f.clone(), 150.0).unwrap();
        let low = inv.add_spool(f, 50.0).unwrap();
        inv.load("p", &id).unwrap();
        let p = [printer("p", PrinterState::Idle)];
        let mut o = Observer::new("h", false, None);
        let look = |o: &mut Observer, inv: &Inventory| -> Vec<Event> {
            o.observe(Look {
                jobs: std::iter::empty(),
                printers: &p,
                hosts: &[],
                inventory: inv,
                spool_low_g: 100.0,
                now: 1.0,
            })
        };
        assert!(
            look(&mut o, &inv).is_empty(),
            "{low} was low before: not news"
        );
        let use_of = |g: f64| Use {
            job: "j".into(),
            printer: "p".into(),
            grams: g,
            mm: 0.0,
            at_s: 0.0,
            report: Report::Local,
        };
        inv.record_use(&id, "j#0", use_of(40.0));
        assert!(look(&mut o, &inv).is_empty(), "110 g left");
        inv.record_use(&id, "j#1", use_of(20.0));
        let made = look(&mut o, &inv);
        assert_eq!(made.len(), 1);
        assert_eq!(made[0].event, EventKind::SpoolLow);
        assert_eq!(made[0].printer.as_deref(), Some("p"));
        let reason = made[0].reason.as_deref().unwrap();
        assert!(reason.contains("PETG black (s1) has 90 g left"), "{reason}");
        inv.record_use(&id, "j#2", use_of(20.0));
        assert!(look(&mut o, &inv).is_empty(), "told once");
    }
}
