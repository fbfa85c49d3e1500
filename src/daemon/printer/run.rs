//! The decisions of one print apart from its I/O: from what the printer's link reports
//! (its progress, how it ended) and the farm's stop, what the printer shows, when the
//! odometer is written and what it holds, which dropped parts go to the job's record,
//! when the heating permit goes back, and what became of the job. `run_job` moves these
//! between the link, the store and the disk and decides nothing itself; this is tested
//! without a printer, a store or a disk.

use crate::daemon::farm::{LiveProgress, PrinterState};
use crate::daemon::job::{JobState, PartCancel, PrintReport};
use crate::marlin::gcode::GcodeError;
use crate::marlin::stream::PrintError;

/// How a print ended, if not well: the cause, with the streamer's own error.
#[derive(Debug, thiserror::Error)]
pub(crate) enum PrintFailure {
    /// Stopped on request (heaters off).
    #[error("{0}")]
    Cancelled(PrintError),
    /// The printer went away; the connection must be re-opened.
    #[error("{0}")]
    Lost(PrintError),
    /// The print failed on the printer's side (it said so, or reset).
    #[error("{0}")]
    Failed(PrintError),
    /// The job's G-code cannot be read or is not for this printer; nothing was sent.
    #[error("cannot load the G-code: {0}")]
    Gcode(#[from] GcodeError),
    /// Loading the G-code crashed; nothing was sent.
    #[error("cannot load the G-code: {0}")]
    LoaderCrashed(#[source] tokio::task::JoinError),
}

impl PrintFailure {
    /// The cause of a streamer's error: the one place its kinds are sorted.
    pub(crate) fn of(e: PrintError) -> PrintFailure {
        match e {
            PrintError::Cancelled { .. } => PrintFailure::Cancelled(e),
            PrintError::Open(_)
            | PrintError::NoAnswer { .. }
            | PrintError::Disconnected { .. }
            | PrintError::PrinterReset { .. }
            | PrintError::Silent { .. } => PrintFailure::Lost(e),
            _ => PrintFailure::Failed(e),
        }
    }
}

/// One print, from its first line to its end.
#[derive(Debug)]
pub(super) struct JobRun {
    /// The dropped parts the store has been given (it keeps them across a restart).
    recorded_parts: usize,
    /// The lines acknowledged as the odometer on disk last said.
    odometer_lines: usize,
    /// The heating permit is held (until the heat-up is done).
    permit: bool,
    /// The farm stopped its prints (a shutdown): the print was asked to stop.
    shutdown_stop: bool,
}

/// What one report of the print's progress asks of the driver.
#[derive(Debug, PartialEq)]
pub(super) struct Step {
    /// Write the odometer.
    pub odometer: Option<OdometerWrite>,
    /// Parts newly dropped, for the job's record.
    pub record_parts: Vec<PartCancel>,
    /// Hand the heating permit back: the heat-up is done.
    pub release_permit: bool,
    /// What the printer shows: its state, and a detail when it waits.
    pub state: PrinterState,
    pub detail: Option<String>,
}

/// What the odometer is to say now.
#[derive(Debug, PartialEq)]
pub(super) struct OdometerWrite {
    pub lines_acked: usize,
    /// The parts dropped so far with the command each was dropped from; None: as they
    /// were.
    pub cancels: Option<Vec<(String, usize)>>,
}

/// How a print ended, as the driver acts on it.
#[derive(Debug, PartialEq)]
pub(super) struct Ending {
    pub state: JobState,
    pub reason: Option<String>,
    /// The connection was lost.
    pub lost: bool,
    /// The firmware halted (its message).
    pub halted: Option<String>,
    /// Nothing reached the printer (its G-code could not be loaded): the bed is as it was.
    pub sent_nothing: bool,
    /// The bed may be ejected (a print that ended well, not stopped); else it waits for a
    /// person.
    pub may_eject: bool,
    /// The lines the print pushed: every line of a finished one, else what was
    /// acknowledged (`last_acked`), none when nothing was sent.
    pub lines_acked: usize,
}

impl JobRun {
    /// A print about to start, holding its heating permit.
    pub(super) fn new() -> JobRun {
        JobRun {
            recorded_parts: 0,
            odometer_lines: 0,
            permit: true,
            shutdown_stop: false,
        }
    }

    /// The print reported `live`.
    pub(super) fn progress(&mut self, live: &LiveProgress) -> Step {
        let mut step = Step {
            odometer: None,
            record_parts: Vec::new(),
            release_permit: false,
            state: PrinterState::Printing,
            detail: None,
        };
        let new_parts = live.parts_cancelled.len() > self.recorded_parts;
        if live.lines_acked != self.odometer_lines || new_parts {
            let cancels = new_parts.then(|| {
                live.parts_cancelled
                    .iter()
                    .filter_map(|c| Some((c.part.clone(), c.dropped.as_ref()?.command)))
                    .collect()
            });
            step.odometer = Some(OdometerWrite {
                lines_acked: live.lines_acked,
                cancels,
            });
            self.odometer_lines = live.lines_acked;
        }
        if new_parts {
            step.record_parts = live.parts_cancelled[self.recorded_parts..].to_vec();
            self.recorded_parts = live.parts_cancelled.len();
        }
        if self.permit && live.heated {
            self.permit = false;
            step.release_permit = true;
        }
        (step.state, step.detail) = match &live.pause {
            Some(pause) => (
                PrinterState::WaitingForOperator,
                Some(waiting_detail(pause)),
            ),
            None if live.paused => (
                PrinterState::Paused,
                live.stop_wait.as_ref().map(stop_wait_detail),
            ),
            None => (
                PrinterState::Printing,
                live.stop_wait.as_ref().map(stop_wait_detail),
            ),
        };
        step
    }

    /// The farm stops its prints (a shutdown): whether to ask this one to stop (once).
    pub(super) fn stop(&mut self) -> bool {
        !std::mem::replace(&mut self.shutdown_stop, true)
    }

    /// The print was asked to stop by a shutdown.
    pub(super) fn stopped(&self) -> bool {
        self.shutdown_stop
    }

    /// The print ended with `outcome`, `last_acked` lines acknowledged as last reported.
    pub(super) fn end(
        &self,
        outcome: &Result<PrintReport, PrintFailure>,
        last_acked: usize,
    ) -> Ending {
        let sent_nothing = matches!(
            outcome,
            Err(PrintFailure::Gcode(_) | PrintFailure::LoaderCrashed(_))
        );
        let lines_acked = match outcome {
            Ok(report) => report.lines_acked,
            Err(_) if sent_nothing => 0,
            Err(_) => last_acked,
        };
        let halted = match outcome {
            Err(PrintFailure::Failed(PrintError::Fatal { message, .. })) => Some(message.clone()),
            _ => None,
        };
        let (state, reason, lost) = match outcome {
            Ok(_) => (JobState::Done, None, false),
            Err(why @ PrintFailure::Cancelled(_)) if self.shutdown_stop => (
                JobState::Interrupted,
                Some(format!(
                    "stopped safely at shutdown ({why}); clear the bed, then `crispen retry` if wanted"
                )),
                false,
            ),
            Err(why @ PrintFailure::Cancelled(_)) => {
                (JobState::Cancelled, Some(why.to_string()), false)
            }
            Err(why @ PrintFailure::Lost(_)) => (
                JobState::Interrupted,
                Some(format!(
                    "{why}; check the printer and clear its bed, then `crispen retry` if wanted"
                )),
                true,
            ),
            Err(
                why @ (PrintFailure::Failed(_)
                | PrintFailure::Gcode(_)
                | PrintFailure::LoaderCrashed(_)),
            ) => (JobState::Failed, Some(why.to_string()), false),
        };
        Ending {
            state,
            reason,
            lost,
            halted,
            sent_nothing,
            may_eject: outcome.is_ok() && !self.shutdown_stop,
            lines_acked,
        }
    }
}

/// The status line of a printer waiting at a pause its file asked for.
fn waiting_detail(pause: &crate::marlin::stream::PauseInfo) -> String {
    let mut text = format!("waiting for the operator: {}", pause.message);
    match pause.line {
        Some(line) => text += &format!(" (`{}`, line {line})", pause.command),
        None => text += &format!(" (`{}`)", pause.command),
    }
    if !pause.parked {
        text += "; not parked: the head's position was not known from the file";
    }
    if pause.heaters_off {
        text += "; heaters turned off after waiting too long, the resume heats up first";
    }
    text += "; resume with `crispen resume`";
    text
}

/// What a stop that waits for the heat-up waits for, as the status shows it.
fn stop_wait_detail(w: &crate::marlin::stream::StopWait) -> String {
    let heater = if w.bed { "bed" } else { "hotend" };
    let mut text = format!("stopping: the printer reads nothing until its {heater} is hot");
    if let Some(command) = &w.command {
        text += &format!(" (`{command}`)");
    }
    if let (Some(now), Some(target)) = (w.current_c, w.target_c) {
        text += &format!(", {now:.0} of {target:.0} °C");
    }
    match w.remaining_s {
        Some(s) => text += &format!("; heaters off in about {s:.0} s"),
        None => text += "; heaters off once it is there",
    }
    text += &format!(" (at most {:.0} s)", w.limit_s);
    text
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::daemon::job::Dropped;
    use crate::marlin::stream::{PauseInfo, StopOutcome};
    use std::path::PathBuf;

    fn live(lines_acked: usize) -> LiveProgress {
        LiveProgress {
            lines_acked,
            lines_total: 100,
            ..LiveProgress::default()
        }
    }

    fn part(name: &str, command: Option<usize>) -> PartCancel {
        PartCancel {
            part: name.into(),
            print: 1,
            at_s: 1.0,
            dropped: command.map(|command| Dropped {
                command,
                line: command + 1,
                layer: None,
                z_mm: None,
            }),
        }
    }

    fn write(lines_acked: usize, cancels: Option<&[(&str, usize)]>) -> OdometerWrite {
        OdometerWrite {
            lines_acked,
            cancels: cancels.map(|c| c.iter().map(|(p, n)| (p.to_string(), *n)).collect()),
        }
    }

    fn report(lines_acked: usize) -> PrintReport {
        PrintReport {
            lines_total: 100,
            lines_acked,
            ..PrintReport::default()
        }
    }

    fn cancelled() -> PrintFailure {
        PrintFailure::Cancelled(PrintError::Cancelled {
            port: PathBuf::from("/dev/p"),
            last_acked: 40,
            stop: StopOutcome::Confirmed,
        })
    }

    /// The odometer is written when the lines move or a part is dropped, never for a
    /// report that changed neither (a temperature); each dropped part goes to the record
    /// once; the permit goes back once, when the heat-up is done.
    #[test]
    fn progress_writes_the_odometer_and_records_each_part_once() {
        let mut run = JobRun::new();
        let first = run.progress(&live(0));
        assert_eq!(first.odometer, None, "nothing moved yet");
        assert_eq!(first.state, PrinterState::Printing);
        assert!(!first.release_permit);

        let mut heated = live(10);
        heated.heated = true;
        let step = run.progress(&heated);
        assert_eq!(step.odometer, Some(write(10, None)));
        assert!(step.release_permit);
        let mut hotter = heated.clone();
        hotter.hotend_c = Some(210.0);
        let again = run.progress(&hotter);
        assert_eq!((again.odometer, again.release_permit), (None, false));

        let mut dropped = hotter.clone();
        dropped.parts_cancelled = vec![part("a", Some(7))];
        let step = run.progress(&dropped);
        assert_eq!(step.odometer, Some(write(10, Some(&[("a", 7)]))));
        assert_eq!(step.record_parts, vec![part("a", Some(7))]);
        let step = run.progress(&dropped);
        assert_eq!(
            (step.odometer, step.record_parts, step.release_permit),
            (None, Vec::new(), false),
            "nothing new"
        );

        dropped.parts_cancelled.push(part("b", None));
        dropped.lines_acked = 12;
        let step = run.progress(&dropped);
        // A part not dropped yet has no command to count from: the odometer lists only
        // those it has.
        assert_eq!(step.odometer, Some(write(12, Some(&[("a", 7)]))));
        assert_eq!(step.record_parts, vec![part("b", None)]);
    }

    /// A pause the file asked for shows the printer waiting for its operator with what to
    /// do; an operator's pause shows it paused.
    #[test]
    fn a_pause_is_shown_for_what_it_is() {
        let mut run = JobRun::new();
        let mut waiting = live(5);
        waiting.pause = Some(PauseInfo {
            message: "insert the nut".into(),
            command: "M0".into(),
            line: Some(12),
            parked: true,
            heaters_off: false,
        });
        let step = run.progress(&waiting);
        assert_eq!(step.state, PrinterState::WaitingForOperator);
        let detail = step.detail.unwrap();
        assert!(
            detail.contains("insert the nut") && detail.contains("crispen resume"),
            "{detail}"
        );
        let mut paused = live(5);
        paused.paused = true;
        let step = run.progress(&paused);
        assert_eq!((step.state, step.detail), (PrinterState::Paused, None));
    }

    /// A shutdown asks the print to stop once; a print stopped so ends interrupted and
    /// its bed waits for a person, where an operator's cancel ends cancelled.
    #[test]
    fn a_stop_at_shutdown_interrupts_and_a_cancel_cancels() {
        let mut run = JobRun::new();
        let ending = run.end(&Err(cancelled()), 40);
        assert_eq!(ending.state, JobState::Cancelled);
        assert!(!ending.may_eject && !ending.sent_nothing && !ending.lost);
        assert_eq!(ending.lines_acked, 40);

        assert!(run.stop());
        assert!(!run.stop(), "asked once");
        let ending = run.end(&Err(cancelled()), 40);
        assert_eq!(ending.state, JobState::Interrupted);
        assert!(ending
            .reason
            .unwrap()
            .starts_with("stopped safely at shutdown"));
        // Even a print that finished as the stop came is not ejected unattended.
        let ending = run.end(&Ok(report(100)), 90);
        assert_eq!((ending.state, ending.may_eject), (JobState::Done, false));
    }

    /// Each way a print ends, as the job and the printer take it.
    #[test]
    fn each_ending_is_sorted() {
        let run = JobRun::new();
        let done = run.end(&Ok(report(100)), 90);
        assert_eq!(
            done,
            Ending {
                state: JobState::Done,
                reason: None,
                lost: false,
                halted: None,
                sent_nothing: false,
                may_eject: true,
                lines_acked: 100,
            }
        );
        let lost = run.end(
            &Err(PrintFailure::of(PrintError::Disconnected {
                port: PathBuf::from("/dev/p"),
                reason: "gone".into(),
                last_acked: 30,
            })),
            30,
        );
        assert_eq!(
            (lost.state, lost.lost, lost.lines_acked),
            (JobState::Interrupted, true, 30)
        );
        assert!(lost
            .reason
            .unwrap()
            .ends_with("then `crispen retry` if wanted"));
        let halted = run.end(
            &Err(PrintFailure::of(PrintError::Fatal {
                port: PathBuf::from("/dev/p"),
                message: "Printer halted. kill() called!".into(),
                last_acked: 20,
            })),
            20,
        );
        assert_eq!(halted.state, JobState::Failed);
        assert_eq!(
            halted.halted.as_deref(),
            Some("Printer halted. kill() called!")
        );
        let unread = run.end(
            &Err(PrintFailure::Gcode(GcodeError::Io {
                path: PathBuf::from("/spool/job.gcode"),
                source: std::io::Error::from(std::io::ErrorKind::NotFound),
            })),
            0,
        );
        assert_eq!(
            (
                unread.state,
                unread.sent_nothing,
                unread.may_eject,
                unread.lines_acked
            ),
            (JobState::Failed, true, false, 0)
        );
    }
}
