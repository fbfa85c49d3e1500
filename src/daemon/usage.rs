//! What a print took from its spool, and the printer's odometer.
//!
//! A print's use is the filament its acknowledged lines push (a printer acknowledges a
//! line once it has taken it in: what it acknowledged, it prints), measured from the job's
//! G-code when the print ends and recorded with its outcome. So that a daemon killed
//! mid-print still knows at its next start how far the print got, the supervisor keeps an
//! odometer while it prints: `<spool>/odometer/<printer>.json`, the job and the lines
//! acknowledged, rewritten with the progress (a few times a second). A process killed
//! leaves the file as last written (the kernel has it); the next start of that printer's
//! supervisor measures the use from it and records it with the job if the job has no use
//! for that print yet (a print that ended recorded its own), then removes it.

use super::filament::Filament;
use super::job::JobUse;
use super::store::{JobChange, Use};
use crate::marlin::firmware::Firmware;
use serde::{Deserialize, Serialize};
use std::path::{Path, PathBuf};

/// How far a print has got, and what to measure its use by.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub(crate) struct Odometer {
    pub job: String,
    pub printer: String,
    /// The job's uses before this print: this print's use is the next one (`<job>#<n>`).
    pub print: usize,
    /// The spool on the printer when the print started, and its filament (or the
    /// printer's default filament).
    pub spool: Option<String>,
    pub filament: Option<Filament>,
    pub gcode: PathBuf,
    pub firmware: Firmware,
    pub lines_acked: usize,
    /// When the print started, and when the odometer was last written (seconds since the
    /// epoch): a print the daemon was killed during took until then. 0 in odometers left
    /// by a version that did not keep them.
    #[serde(default)]
    pub started_s: f64,
    #[serde(default)]
    pub written_s: f64,
    /// The parts of the plate the print dropped, and the command each was dropped from:
    /// their lines from there on pushed nothing.
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub cancels: Vec<(String, usize)>,
}

/// Where `printer`'s odometer is kept.
pub(crate) fn path(spool_dir: &Path, printer: &str) -> PathBuf {
    spool_dir.join("odometer").join(format!("{printer}.json"))
}

impl Odometer {
    /// The odometer of `job`'s print starting on `printer` from `gcode`: what the printer
    /// holds now (the print's filament is booked to it), no line acknowledged yet.
    pub(crate) fn start(
        farm: &super::farm::Farm,
        printer: &str,
        job: &str,
        gcode: &Path,
    ) -> Odometer {
        let config = farm.config();
        let store = farm.store();
        let on = config.printers.iter().find(|p| p.name == printer);
        let holds = on.map(|p| super::farm::offer(p, store.inventory(), 0.0));
        Odometer {
            job: job.to_string(),
            printer: printer.to_string(),
            print: store.get(job).map_or(0, |j| j.uses.len()),
            spool: holds.as_ref().and_then(|o| o.spool).map(|s| s.id.clone()),
            filament: holds.as_ref().and_then(|o| o.filament).cloned(),
            gcode: gcode.to_path_buf(),
            firmware: on.map_or(Firmware::Marlin2, |p| p.firmware),
            lines_acked: 0,
            started_s: super::job::now_s(),
            written_s: 0.0,
            cancels: Vec::new(),
        }
    }

    /// Writes the odometer (a temporary file renamed over it, not synced: it must outlive
    /// the process, not a power cut, and it is rewritten several times a second).
    pub(crate) async fn write(&mut self, path: &Path) {
        self.written_s = super::job::now_s();
        let bytes = serde_json::to_vec(self).expect("an odometer serialises");
        let temp = crate::fsutil::temp_path(path);
        let written = async {
            if let Some(dir) = path.parent() {
                tokio::fs::create_dir_all(dir).await?;
            }
            tokio::fs::write(&temp, &bytes).await?;
            tokio::fs::rename(&temp, path).await
        };
        if let Err(e) = written.await {
            tracing::warn!(path = %path.display(), error = %e, "cannot write the printer's odometer; a kill now would lose this print's filament use");
        }
    }

    /// The odometer a print left, if any (unreadable: logged and dropped).
    pub(crate) async fn read(path: &Path) -> Option<Odometer> {
        let bytes = tokio::fs::read(path).await.ok()?;
        match serde_json::from_slice(&bytes) {
            Ok(o) => Some(o),
            Err(e) => {
                tracing::error!(path = %path.display(), error = %e, "unreadable odometer; its print's filament use is not recorded");
                remove(path).await;
                None
            }
        }
    }

    /// The use of the print as far as it got: the filament the acknowledged lines of its
    /// G-code push, as the host sent them (a cancelled part's lines from its cancel on
    /// push nothing: `crate::marlin::plate::sent_lines`). Reads the G-code on a blocking
    /// thread. None when nothing was acknowledged or the G-code cannot be read. `ended_s`:
    /// when the print ended.
    pub(crate) async fn measure(&self, ended_s: f64) -> Option<JobUse> {
        if self.lines_acked == 0 {
            return None;
        }
        let (gcode, firmware, lines) = (self.gcode.clone(), self.firmware, self.lines_acked);
        let cancels = self.cancels.clone();
        let mm = tokio::task::spawn_blocking(move || {
            if cancels.is_empty() {
                // The commands as the host loaded them, read as they stream by: a job of
                // millions of lines is not held a second time for this.
                return crate::marlin::gcode::pushed_mm(&gcode, firmware, Some(lines))
                    .map(|(mm, _)| mm);
            }
            let program = crate::marlin::gcode::GcodeProgram::load_for(&gcode, firmware)?;
            let cancels: Vec<(u16, usize)> = program
                .marks()
                .map(|marks| {
                    cancels
                        .iter()
                        .filter_map(|(name, from)| Some((marks.find(name)?, *from)))
                        .collect()
                })
                .unwrap_or_default();
            let sent = crate::marlin::plate::sent_lines(&program, &cancels)
                .take_while(|(i, _)| *i < lines)
                .filter_map(|(_, line)| line);
            Ok::<_, crate::marlin::gcode::GcodeError>(crate::marlin::motion::extruded_mm(
                sent, firmware,
            ))
        })
        .await;
        let mm = match mm {
            Ok(Ok(mm)) => mm.max(0.0),
            Ok(Err(e)) => {
                tracing::error!(job = %self.job, error = %e, "cannot measure the print's filament use");
                return None;
            }
            Err(e) => {
                tracing::error!(job = %self.job, error = %e, "measuring the print's filament use crashed");
                return None;
            }
        };
        let grams = self.filament.as_ref().map_or(0.0, |f| f.grams(mm));
        Some(JobUse {
            key: format!("{}#{}", self.job, self.print),
            spool: self.spool.clone(),
            printer: self.printer.clone(),
            material: self
                .filament
                .as_ref()
                .map_or_else(|| JobUse::UNKNOWN.into(), |f| f.material.clone()),
            colour: self
                .filament
                .as_ref()
                .map_or_else(|| JobUse::UNKNOWN.into(), |f| f.colour.clone()),
            grams,
            mm,
            cost: self
                .filament
                .as_ref()
                .and_then(|f| f.price_per_kg)
                .map(|p| grams * p / 1000.0),
            at_s: ended_s,
            print_s: if self.started_s > 0.0 {
                (ended_s - self.started_s).max(0.0)
            } else {
                0.0
            },
            failed: false,
        })
    }
}

async fn remove(path: &Path) {
    match tokio::fs::remove_file(path).await {
        Ok(()) => {}
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => {}
        Err(e) => {
            tracing::warn!(path = %path.display(), error = %e, "cannot remove the printer's odometer")
        }
    }
}

/// At a supervisor's start: the use of a print the daemon was killed during, recorded with
/// its job (once: only while the job has no use for that print yet).
pub(crate) async fn recover(farm: &super::farm::Farm, printer: &str) {
    let path = path(&farm.config().spool_dir, printer);
    let Some(odometer) = Odometer::read(&path).await else {
        return;
    };
    // The print ended, as far as anyone can tell, when its odometer was last written.
    let ended_s = if odometer.written_s > 0.0 {
        odometer.written_s
    } else {
        super::job::now_s()
    };
    if let Some(usage) = odometer.measure(ended_s).await {
        let (print, grams) = (odometer.print, usage.grams);
        let recorded = farm
            .jobs()
            .update(&odometer.job, JobChange::Used(Use { print, usage }))
            .await;
        match recorded {
            Ok(_) => {
                tracing::info!(job = %odometer.job, lines = odometer.lines_acked, grams, "recorded the filament of a print the daemon stopped during")
            }
            Err(e) => {
                tracing::error!(job = %odometer.job, error = %e, "cannot record the filament of a print the daemon stopped during");
                return;
            }
        }
    }
    remove(&path).await;
}
