//! A receiver's queue of events not delivered yet: one file per event in
//! `<spool>/notify/<receiver>/<event id>.json`, written atomically and durably
//! ([`crate::fsutil::write_atomic`]) before the receiver's task is woken, and removed once
//! the receiver took it. Ids sort by time, so the oldest is sent first. A restart finds
//! the queue as it was; an event whose removal was lost in a crash is sent again with the
//! same id (delivery is at least once). Blocking I/O: callers run it on blocking threads.

use super::event::Event;
use crate::fsutil::{self, WriteError};
use std::path::{Path, PathBuf};

/// Most events kept per receiver: a receiver down for long loses the oldest beyond it.
pub(crate) const MAX_PENDING: usize = 10_000;
/// Largest event file read (an event is a few hundred bytes).
const MAX_EVENT_BYTES: u64 = 64 * 1024;

#[derive(Debug, Clone)]
pub(crate) struct Outbox {
    dir: PathBuf,
}

/// An event file that cannot be read as an event (set aside as `<name>.bad`).
#[derive(Debug, thiserror::Error)]
#[error("notification queue: {path}: {message}")]
pub(crate) struct BadEvent {
    pub path: PathBuf,
    pub message: String,
}

impl Outbox {
    /// The queue of `receiver` in `spool`, made if missing.
    pub(crate) fn open(spool: &Path, receiver: &str) -> std::io::Result<Outbox> {
        let dir = spool.join("notify").join(receiver);
        std::fs::create_dir_all(&dir).map_err(|e| {
            std::io::Error::new(e.kind(), format!("cannot make {}: {e}", dir.display()))
        })?;
        Ok(Outbox { dir })
    }

    pub(crate) fn dir(&self) -> &Path {
        &self.dir
    }

    /// Keeps `event` until it is delivered.
    pub(crate) fn put(&self, event: &Event) -> Result<(), WriteError> {
        let bytes = serde_json::to_vec(event).unwrap_or_default();
        fsutil::write_atomic(&self.path(&event.id), &bytes)
    }

    fn path(&self, id: &str) -> PathBuf {
        self.dir.join(format!("{id}.json"))
    }

    /// The ids waiting, oldest first. Beyond [`MAX_PENDING`], the oldest are removed and
    /// returned as dropped.
    pub(crate) fn pending(&self) -> std::io::Result<(Vec<String>, Vec<String>)> {
        let mut ids: Vec<String> = std::fs::read_dir(&self.dir)?
            .filter_map(|e| e.ok())
            .filter_map(|e| {
                let name = e.file_name().into_string().ok()?;
                let id = name.strip_suffix(".json")?;
                (!name.starts_with('.')).then(|| id.to_string())
            })
            .collect();
        ids.sort();
        let over = ids.len().saturating_sub(MAX_PENDING);
        let dropped: Vec<String> = ids.drain(..over).collect();
        for id in &dropped {
            self.remove(id)?;
        }
        Ok((ids, dropped))
    }

    /// Reads the event `id`; one that cannot be read is set aside (renamed `.bad`) so it
    /// never blocks the queue.
    pub(crate) fn read(&self, id: &str) -> Result<Event, BadEvent> {
        use std::io::Read;
        let path = self.path(id);
        let bad = |message: String| {
            let _ = std::fs::rename(&path, path.with_extension("bad"));
            BadEvent {
                path: path.clone(),
                message,
            }
        };
        let mut bytes = Vec::new();
        std::fs::File::open(&path)
            .and_then(|f| f.take(MAX_EVENT_BYTES + 1).read_to_end(&mut bytes))
            .map_err(|e| bad(format!("cannot read: {e}")))?;
        if bytes.len() as u64 > MAX_EVENT_BYTES {
            return Err(bad(format!("larger than {MAX_EVENT_BYTES} bytes")));
        }
        let event: Event =
            serde_json::from_slice(&bytes).map_err(|e| bad(format!("not an event: {e}")))?;
        if event.id != id {
            return Err(bad(format!("holds event {:?}", event.id)));
        }
        Ok(event)
    }

    /// Forgets a delivered (or dropped) event. Not synced: a removal lost in a crash sends
    /// the event again, which at-least-once delivery allows.
    pub(crate) fn remove(&self, id: &str) -> std::io::Result<()> {
        match std::fs::remove_file(self.path(id)) {
            Err(e) if e.kind() != std::io::ErrorKind::NotFound => Err(e),
            _ => Ok(()),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::notify::event::EventKind;

    #[test]
    fn events_wait_in_order_and_bad_files_are_set_aside() {
        let tmp = tempfile::tempdir().unwrap();
        let outbox = Outbox::open(tmp.path(), "r").unwrap();
        let a = Event::new(EventKind::JobDone, 2.0, "h");
        let b = Event::new(EventKind::JobFailed, 1.0, "h");
        outbox.put(&a).unwrap();
        outbox.put(&b).unwrap();
        std::fs::write(outbox.dir().join("0000000000000-junk.json"), "{").unwrap();
        let (ids, dropped) = outbox.pending().unwrap();
        assert!(dropped.is_empty());
        assert_eq!(ids.len(), 3);
        assert!(outbox.read(&ids[0]).is_err(), "junk first");
        assert_eq!(outbox.read(&ids[1]).unwrap(), b);
        assert_eq!(outbox.read(&ids[2]).unwrap(), a);
        outbox.remove(&b.id).unwrap();
        let (ids, _) = outbox.pending().unwrap();
        assert_eq!(
            ids,
            std::slice::from_ref(&a.id),
            "the junk is set aside, b delivered"
        );
    }
}
