//! The run's counters for `/metrics` that no farm state holds: made once by the service
//! and shared by both listeners (see `Shared` in the parent).

use std::collections::BTreeMap;
use std::sync::Mutex;

/// The notifications' counts (published by their tasks) and the control actions asked through an
/// OctoPrint instance (`POST api/job`), by hot folder, action and result. From zero at
/// each start. Bounded: folders are the config's (a request naming no configured folder
/// is refused before it is counted), actions and results are fixed words; past
/// [`MAX_CONTROL_SERIES`] series (folders renamed by many reloads) new series are not made.
#[derive(Debug, Default)]
pub(crate) struct Counters {
    notifications: crate::notify::Counts,
    control: Mutex<BTreeMap<(String, &'static str, &'static str), u64>>,
}

/// The most series `crispen_octoprint_control_total` keeps.
const MAX_CONTROL_SERIES: usize = 4096;

impl Counters {
    pub(crate) fn new(notifications: crate::notify::Counts) -> Counters {
        Counters {
            notifications,
            control: Default::default(),
        }
    }

    /// Counts one control action through OctoPrint: `action` pause, resume, toggle,
    /// cancel, start; `result` done, refused (the key may not), failed (nothing to act on,
    /// or the farm refused).
    pub(crate) fn count_octoprint_control(
        &self,
        folder: &str,
        action: &'static str,
        result: &'static str,
    ) {
        let mut map = self.control.lock().unwrap_or_else(|e| e.into_inner());
        let key = (folder.to_string(), action, result);
        if map.len() >= MAX_CONTROL_SERIES && !map.contains_key(&key) {
            return;
        }
        *map.entry(key).or_insert(0) += 1;
    }

    /// Every (folder, action, result, count).
    pub(crate) fn octoprint_control(&self) -> Vec<(String, &'static str, &'static str, u64)> {
        let map = self.control.lock().unwrap_or_else(|e| e.into_inner());
        map.iter()
            .map(|((f, a, r), n)| (f.clone(), *a, *r, *n))
            .collect()
    }

    /// Every (receiver, outcome, count) of the notifications.
    pub(crate) fn notifications(&self) -> Vec<(String, crate::notify::counts::Outcome, u64)> {
        self.notifications.all()
    }
}
