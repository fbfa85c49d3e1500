//! The record of what a simulated printer executed.

use crispen_marlin::protocol::canonical;
use std::fs::File;
use std::io::Write;
use std::sync::{Arc, Mutex};

/// Where executed commands go: the shared list, and the record file if any.
pub(crate) struct Recorder {
    pub(super) executed: Option<Arc<Mutex<Vec<String>>>>,
    pub(super) file: Option<File>,
}

impl Recorder {
    /// Records what the printer ran as it reads it ([`canonical`]: a host may write the
    /// same command with an extra space or trailing zeros, e.g. crispen's cut-line guard).
    pub(crate) fn push(&mut self, cmd: &str) {
        let cmd = &canonical(cmd);
        if let Some(executed) = &self.executed {
            executed
                .lock()
                .unwrap_or_else(|e| e.into_inner())
                .push(cmd.to_string());
        }
        if let Some(file) = &mut self.file {
            if let Err(err) = writeln!(file, "{cmd}").and_then(|_| file.flush()) {
                tracing::warn!(%err, "cannot append to the record file; recording stopped");
                self.file = None;
            }
        }
    }
}
