//! One event of the farm as sent to receivers: what happened, when, to which printer and
//! job, why, and where to look. Its `id` is made once, when the event is seen, and sent
//! unchanged on every retry, so a receiver can drop the repeats of at-least-once delivery.

use serde::{Deserialize, Serialize};

/// What happened (its name is the `event` field, and what `[[notify]] events` lists).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum EventKind {
    /// A job printed; its printer now waits for its bed to be cleared.
    JobDone,
    JobFailed,
    JobCancelled,
    /// A print stopped half way (its printer went away, or the daemon stopped it).
    JobInterrupted,
    /// The printer stopped a print with an error of its own (thermal runaway, kill, reset).
    PrinterError,
    PrinterOffline,
    PrinterOnline,
    /// A printer waits for the operator (a paused print).
    PrinterWaiting,
    /// A host of a shared farm stopped renewing its lease.
    HostLost,
    /// A print left a spool with less than `[farm] spool_low_g`.
    SpoolLow,
    /// A printer that clears its bed by machine stopped for a person: the camera found the
    /// bed not clear (with the marked picture), could not check it, or the eject failed.
    BedNotClear,
    /// A `[[maintenance]]` task fell due on a printer (see `daemon::care`).
    MaintenanceDue,
    /// `crispen notify test`.
    Test,
}

impl EventKind {
    pub(crate) fn name(self) -> &'static str {
        match self {
            EventKind::JobDone => "job_done",
            EventKind::JobFailed => "job_failed",
            EventKind::JobCancelled => "job_cancelled",
            EventKind::JobInterrupted => "job_interrupted",
            EventKind::PrinterError => "printer_error",
            EventKind::PrinterOffline => "printer_offline",
            EventKind::PrinterOnline => "printer_online",
            EventKind::PrinterWaiting => "printer_waiting",
            EventKind::HostLost => "host_lost",
            EventKind::SpoolLow => "spool_low",
            EventKind::BedNotClear => "bed_not_clear",
            EventKind::MaintenanceDue => "maintenance_due",
            EventKind::Test => "test",
        }
    }

    /// A short line for people (chat messages, phone notifications' titles).
    pub(crate) fn title(self) -> &'static str {
        match self {
            EventKind::JobDone => "Print done: clear the bed",
            EventKind::JobFailed => "Job failed",
            EventKind::JobCancelled => "Job cancelled",
            EventKind::JobInterrupted => "Print interrupted",
            EventKind::PrinterError => "Printer error stopped a print",
            EventKind::PrinterOffline => "Printer offline",
            EventKind::PrinterOnline => "Printer back online",
            EventKind::PrinterWaiting => "Printer waiting for the operator",
            EventKind::HostLost => "Farm host lost",
            EventKind::SpoolLow => "Spool running low",
            EventKind::BedNotClear => "Bed not clear: the printer waits for a person",
            EventKind::MaintenanceDue => "Maintenance due",
            EventKind::Test => "Test notification",
        }
    }

    /// Whether it asks for someone to act (ntfy's priority, tags).
    pub(crate) fn urgent(self) -> bool {
        matches!(
            self,
            EventKind::JobFailed
                | EventKind::JobInterrupted
                | EventKind::PrinterError
                | EventKind::PrinterOffline
                | EventKind::PrinterWaiting
                | EventKind::HostLost
                | EventKind::SpoolLow
                | EventKind::BedNotClear
                | EventKind::MaintenanceDue
        )
    }
}

/// The job an event is about.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct EventJob {
    pub id: String,
    pub file: String,
    pub folder: String,
    /// One of the copies of a job that asked for several: which.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub copy: Option<EventCopy>,
}

/// Which copy of a job an event's job is: copy `n` of `total` of job `of` (the job that
/// asked for them, copy 1).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct EventCopy {
    pub of: String,
    pub n: u32,
    pub total: u32,
}

/// One event, as kept in a receiver's queue and sent in the `json` format.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Event {
    /// Unique; the same on every retry. Sorts in the order the events were seen.
    pub id: String,
    pub event: EventKind,
    /// Seconds since the epoch when it was seen.
    pub time: f64,
    /// The host that saw it (`[farm] host`).
    pub host: String,
    pub printer: Option<String>,
    pub job: Option<EventJob>,
    pub reason: Option<String>,
    /// The dashboard (`[http] public_url`), where one is configured.
    pub link: Option<String>,
    /// The picture the printer's camera took as its print ended, under the dashboard's
    /// address (a printer with a camera, and `[http] public_url`).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub snapshot: Option<String>,
}

impl Event {
    /// A new event with a fresh id.
    pub fn new(event: EventKind, time: f64, host: &str) -> Event {
        Event {
            id: new_id(time),
            event,
            time,
            host: host.to_string(),
            printer: None,
            job: None,
            reason: None,
            link: None,
            snapshot: None,
        }
    }

    /// The event in a sentence, for chat and phone messages.
    pub(crate) fn text(&self) -> String {
        let mut text = self.event.title().to_string();
        if let Some(p) = &self.printer {
            text += &format!(" on {p}");
        }
        if let Some(j) = &self.job {
            text += &format!(": {}", j.file);
            if let Some(c) = &j.copy {
                text += &format!(", copy {} of {}", c.n, c.total);
            }
            text += &format!(" (job {}, folder {})", j.id, j.folder);
        }
        if let Some(r) = &self.reason {
            text += &format!(". {r}");
        }
        if self.event == EventKind::HostLost || self.printer.is_none() {
            text += &format!(" [host {}]", self.host);
        }
        text
    }
}

/// Milliseconds of `time` (13 digits, so names sort by time) and 64 random bits.
fn new_id(time: f64) -> String {
    let millis = (time.max(0.0) * 1000.0) as u64;
    format!("{millis:013}-{:016x}", rand::random::<u64>())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn names_are_the_configs() {
        use crate::daemon::config::notify::EVENT_NAMES;
        let all = [
            EventKind::JobDone,
            EventKind::JobFailed,
            EventKind::JobCancelled,
            EventKind::JobInterrupted,
            EventKind::PrinterError,
            EventKind::PrinterOffline,
            EventKind::PrinterOnline,
            EventKind::PrinterWaiting,
            EventKind::HostLost,
            EventKind::SpoolLow,
            EventKind::BedNotClear,
            EventKind::MaintenanceDue,
            EventKind::Test,
        ];
        let names: Vec<&str> = all.iter().map(|k| k.name()).collect();
        assert_eq!(names, EVENT_NAMES);
        for k in all {
            let json = serde_json::to_string(&k).unwrap();
            assert_eq!(json, format!("\"{}\"", k.name()));
        }
        let (a, b) = (new_id(1.0), new_id(1.0));
        assert_ne!(a, b, "ids are unique");
        assert!(new_id(1.0) < new_id(2.0), "ids sort by time");
    }

    /// A copy's event says which copy it is, in its sentence and its JSON.
    #[test]
    fn a_copy_says_which_it_is() {
        let mut e = Event::new(EventKind::JobDone, 1.0, "h");
        e.printer = Some("b".into());
        e.job = Some(EventJob {
            id: "0009-cup_stl".into(),
            file: "cup.stl".into(),
            folder: "/hot".into(),
            copy: Some(EventCopy {
                of: "0007-cup_stl".into(),
                n: 2,
                total: 6,
            }),
        });
        assert!(
            e.text()
                .contains("on b: cup.stl, copy 2 of 6 (job 0009-cup_stl, folder /hot)"),
            "{}",
            e.text()
        );
        let json = serde_json::to_value(&e).unwrap();
        assert_eq!(json["job"]["copy"]["of"], "0007-cup_stl");
    }
}
