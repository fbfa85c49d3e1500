//! A printer's bed between prints ([`Bed`]) and its one table of legal changes
//! ([`Bed::can_go_to`]), which the job store applies to every change of a bed, as it
//! applies the jobs' own table (`JobState::can_go_to`) to jobs; what a bed's clearing
//! left in a job's record ([`Clearing`]); and how each printer's bed is cleared
//! (`bed_clear`, [`ClearBy`]).
//!
//! A print ends on a bed that is then clear only once someone makes it so: a person
//! (`crispen clear`, the dashboard), or the printer's eject sequence, trusted
//! (`bed_clear = "eject"`) or followed by the camera's check (`"eject-and-check"`). What
//! is recorded before each step makes a restart safe: an eject that had begun is never run
//! again (the bed waits for a person), a check that had not answered is made again (it
//! moves nothing).

use serde::{Deserialize, Serialize};

/// How a printer's bed is cleared after a good print (`bed_clear`, per printer or folder).
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum ClearBy {
    /// A person clears it and says so (`crispen clear`): the gate of old.
    #[default]
    Person,
    /// The printer's eject sequence, trusted.
    Eject,
    /// The eject sequence, then the camera's check against the picture of the empty bed.
    EjectAndCheck,
}

impl ClearBy {
    pub fn name(self) -> &'static str {
        match self {
            ClearBy::Person => "person",
            ClearBy::Eject => "eject",
            ClearBy::EjectAndCheck => "eject-and-check",
        }
    }

    /// The value of `bed_clear` as written.
    pub(crate) fn parse(text: &str) -> Result<ClearBy, String> {
        [ClearBy::Person, ClearBy::Eject, ClearBy::EjectAndCheck]
            .into_iter()
            .find(|c| c.name() == text)
            .ok_or_else(|| format!("\"person\", \"eject\" or \"eject-and-check\", got {text:?}"))
    }
}

/// Who found the bed clear.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum ClearedBy {
    Person,
    /// The camera's check.
    Camera,
    /// The eject sequence ran (`bed_clear = "eject"`: trusted).
    Eject,
}

/// Where a printer's bed is between prints.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(tag = "state", rename_all = "snake_case")]
pub enum Bed {
    /// Known clear: by whom, and when (seconds since the epoch).
    Clear { by: ClearedBy, at_s: f64 },
    /// A person must clear it: after a print (`why` None), or because clearing it by
    /// machine did not happen or did not end well (`why` says so).
    Waiting {
        #[serde(default, skip_serializing_if = "Option::is_none")]
        why: Option<Why>,
    },
    /// A good print ended on it and its eject sequence is to run; `check`: the camera
    /// checks the bed after it.
    EjectDue { check: bool },
    /// The eject sequence is being sent, since `since_s`; recorded before its first line,
    /// so a restart that finds it does not run it again.
    Ejecting { since_s: f64, check: bool },
    /// The camera is to check the bed with a frame taken after `after_s`.
    CheckDue { after_s: f64, before: CheckFor },
}

impl Default for Bed {
    /// A printer never seen: clear, as a person set it up.
    fn default() -> Bed {
        Bed::Clear {
            by: ClearedBy::Person,
            at_s: 0.0,
        }
    }
}

/// Why a check is due.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum CheckFor {
    /// The eject sequence just ran.
    AfterEject,
    /// A job is about to start and the bed was last found clear by the camera, a while ago.
    NextJob,
}

/// Why a bed waits for a person although its printer may clear it by machine.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(tag = "kind", rename_all = "snake_case")]
pub enum Why {
    /// The print is taller than the eject sequence may push off (`max_height_mm`).
    TooTall { height_mm: f64, max_mm: f64 },
    /// How tall the print is is not known (no report of its G-code).
    HeightUnknown,
    /// The printer has no eject sequence (its folder asks for one).
    NoEject,
    /// The bed did not cool to `release_bed_c` in time.
    StayedWarm { bed_c: Option<f64>, release_c: f64 },
    /// The eject sequence failed (the printer's or the link's error).
    EjectFailed { error: String },
    /// The daemon stopped while the eject sequence was being sent.
    EjectInterrupted,
    /// The camera found the bed not clear.
    NotClear { check: Box<CheckRecord> },
    /// The camera could not check it.
    NoCheck { problem: CameraProblem },
}

/// Why the camera could not check a bed.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(tag = "kind", rename_all = "snake_case")]
pub enum CameraProblem {
    /// The printer has no camera.
    NoCamera,
    /// No picture of the empty bed was taken yet.
    NoReference,
    /// The camera answers no more (its error), or gave no frame in time.
    Offline { error: Option<String> },
    /// The camera repeats one picture.
    Frozen { seconds: u64 },
    /// The frame or the reference could not be compared (the error).
    Unreadable { error: String },
}

/// One check of a bed by the camera, as kept with the gate and the job.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct CheckRecord {
    /// When the frame was taken (seconds since the epoch).
    pub at_s: f64,
    pub verdict: crate::bedcheck::Verdict,
    /// The frame with the differing patches marked, relative to the spool.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub picture: Option<String>,
}

/// A step of clearing a job's print off its bed, kept in the job's record in order.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(tag = "step", rename_all = "snake_case")]
pub enum Clearing {
    /// The eject sequence ran from `started_s` to `ended_s`; `error`: how it failed.
    Eject {
        printer: String,
        started_s: f64,
        ended_s: f64,
        #[serde(default, skip_serializing_if = "Option::is_none")]
        error: Option<String>,
    },
    /// The camera checked the bed.
    Check { printer: String, check: CheckRecord },
}

/// The words of an outcome counted in `/metrics`.
pub(crate) mod result {
    pub(crate) const DONE: &str = "done";
    pub(crate) const FAILED: &str = "failed";
    pub(crate) const CLEAR: &str = "clear";
    pub(crate) const NOT_CLEAR: &str = "not_clear";
    pub(crate) const UNAVAILABLE: &str = "unavailable";
    pub(crate) const EJECTS: [&str; 2] = [DONE, FAILED];
    pub(crate) const CHECKS: [&str; 3] = [CLEAR, NOT_CLEAR, UNAVAILABLE];
}

impl Bed {
    /// The state's name (its `state` in JSON).
    pub fn name(&self) -> &'static str {
        match self {
            Bed::Clear { .. } => "clear",
            Bed::Waiting { .. } => "waiting",
            Bed::EjectDue { .. } => "eject_due",
            Bed::Ejecting { .. } => "ejecting",
            Bed::CheckDue { .. } => "check_due",
        }
    }

    pub fn is_clear(&self) -> bool {
        matches!(self, Bed::Clear { .. })
    }

    /// The one table of legal changes of a bed; the job store refuses any other. A person
    /// is always a safe answer: any bed may go to waiting. A person's clear ends every
    /// state but an eject in progress (the printer is moving); an eject is begun only when
    /// due, and ends in a check, a clear it is trusted with, or a person's gate; only a
    /// check answers clear or not for the camera; a check is asked for on a clear bed
    /// (before a job) or after an eject.
    pub fn can_go_to(&self, next: &Bed) -> bool {
        use Bed::*;
        match (self, next) {
            (_, Waiting { .. }) => true,
            (Ejecting { .. }, Clear { by, .. }) => *by == ClearedBy::Eject,
            (_, Clear { by, .. }) if *by == ClearedBy::Person => true,
            (CheckDue { .. }, Clear { by, .. }) => *by == ClearedBy::Camera,
            (Clear { .. }, EjectDue { .. }) => true,
            (EjectDue { .. }, Ejecting { .. }) => true,
            (Ejecting { .. }, CheckDue { before, .. }) => *before == CheckFor::AfterEject,
            (Clear { .. }, CheckDue { before, .. }) => *before == CheckFor::NextJob,
            _ => false,
        }
    }

    /// What the metrics count of a change from `self` to `next`: (`ejects` or `checks`,
    /// the result), if anything.
    pub(crate) fn counted(&self, next: &Bed) -> Option<(&'static str, &'static str)> {
        match (self, next) {
            (Bed::Ejecting { .. }, Bed::Waiting { .. }) => Some(("ejects", result::FAILED)),
            (Bed::Ejecting { .. }, _) => Some(("ejects", result::DONE)),
            (Bed::CheckDue { .. }, Bed::Clear { by, .. }) if *by == ClearedBy::Camera => {
                Some(("checks", result::CLEAR))
            }
            (
                Bed::CheckDue { .. },
                Bed::Waiting {
                    why: Some(Why::NotClear { .. }),
                },
            ) => Some(("checks", result::NOT_CLEAR)),
            (
                Bed::CheckDue { .. },
                Bed::Waiting {
                    why: Some(Why::NoCheck { .. }),
                },
            ) => Some(("checks", result::UNAVAILABLE)),
            _ => None,
        }
    }

    /// What a person reads of it (the dashboard, `crispen status`, a notification).
    pub fn describe(&self) -> Option<String> {
        match self {
            Bed::Clear { .. } => None,
            Bed::Waiting { why: None } => {
                Some("the print is on the bed: remove it, then clear the bed".into())
            }
            Bed::Waiting { why: Some(why) } => Some(why.describe()),
            Bed::EjectDue { .. } => Some("the eject sequence is to run".into()),
            Bed::Ejecting { .. } => Some("the eject sequence is running".into()),
            Bed::CheckDue {
                before: CheckFor::AfterEject,
                ..
            } => Some("the camera is checking the bed after the eject".into()),
            Bed::CheckDue {
                before: CheckFor::NextJob,
                ..
            } => Some("the camera is checking the bed before the next job".into()),
        }
    }
}

impl Why {
    /// Why a person is needed, in words.
    pub fn describe(&self) -> String {
        let person = "clear the bed by hand, then `crispen clear`";
        match self {
            Why::TooTall { height_mm, max_mm } => format!(
                "the print is {height_mm:.0} mm tall, taller than the eject sequence may push off ({max_mm:.0} mm): {person}"
            ),
            Why::HeightUnknown => format!("the print's height is not known, so it is not pushed off: {person}"),
            Why::NoEject => format!("the printer has no eject sequence: {person}"),
            Why::StayedWarm { bed_c, release_c } => format!(
                "the bed did not cool to {release_c:.0} °C in time{}, so the eject did not run: {person}",
                bed_c.map(|c| format!(" (it is {c:.0} °C)")).unwrap_or_default()
            ),
            Why::EjectFailed { error } => format!("the eject sequence failed ({error}): check the printer, {person}"),
            Why::EjectInterrupted => format!(
                "the daemon stopped while the eject sequence ran; it is not run again: check the printer, {person}"
            ),
            Why::NotClear { check } => format!(
                "the camera found the bed {}: remove what is left, then `crispen clear`",
                check.verdict.summary()
            ),
            Why::NoCheck { problem } => format!(
                "the camera could not check the bed ({}): look at it, then `crispen clear`",
                problem.describe()
            ),
        }
    }
}

impl CameraProblem {
    pub fn describe(&self) -> String {
        match self {
            CameraProblem::NoCamera => "the printer has no camera".into(),
            CameraProblem::NoReference => {
                "no picture of the empty bed yet: `crispen clear PRINTER --reference` on an empty bed takes one".into()
            }
            CameraProblem::Offline { error: Some(e) } => format!("the camera is offline: {e}"),
            CameraProblem::Offline { error: None } => "the camera gave no new frame in time".into(),
            CameraProblem::Frozen { seconds } => {
                format!("the camera has sent the same picture for {seconds} s")
            }
            CameraProblem::Unreadable { error } => error.clone(),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Every pair of kinds of state, against a table written out by hand: a change to
    /// `can_go_to` must be a deliberate change here too.
    #[test]
    fn bed_table_is_exactly_this() {
        let clear = |by| Bed::Clear { by, at_s: 1.0 };
        let due = |before| Bed::CheckDue {
            after_s: 1.0,
            before,
        };
        let states = [
            clear(ClearedBy::Person),
            clear(ClearedBy::Camera),
            clear(ClearedBy::Eject),
            Bed::Waiting { why: None },
            Bed::EjectDue { check: true },
            Bed::Ejecting {
                since_s: 1.0,
                check: true,
            },
            due(CheckFor::AfterEject),
            due(CheckFor::NextJob),
        ];
        // Rows: from; columns: to, in `states`' order (clear by person, camera, eject;
        // waiting; eject due; ejecting; check after eject, before the next job).
        let expected: [[u8; 8]; 8] = [
            [1, 0, 0, 1, 1, 0, 0, 1],
            [1, 0, 0, 1, 1, 0, 0, 1],
            [1, 0, 0, 1, 1, 0, 0, 1],
            [1, 0, 0, 1, 0, 0, 0, 0],
            [1, 0, 0, 1, 0, 1, 0, 0],
            [0, 0, 1, 1, 0, 0, 1, 0],
            [1, 1, 0, 1, 0, 0, 0, 0],
            [1, 1, 0, 1, 0, 0, 0, 0],
        ];
        for (from, row) in states.iter().zip(expected) {
            for (to, allowed) in states.iter().zip(row) {
                assert_eq!(from.can_go_to(to), allowed == 1, "{from:?} -> {to:?}");
            }
        }
    }

    #[test]
    fn bed_clear_is_read_as_written() {
        assert_eq!(
            ClearBy::parse("eject-and-check"),
            Ok(ClearBy::EjectAndCheck)
        );
        assert!(ClearBy::parse("robot").unwrap_err().contains("\"eject\""));
    }
}
