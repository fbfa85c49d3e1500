//! What a printer's supervisor does with its bed between prints when it may clear it by
//! machine: after a print, the gate it closes ([`close_gate`]: the eject due, or a person's
//! gate with the reason); the eject sequence run as a short job of its own ([`run`]:
//! wait for the bed to cool, record that it runs, stream it through the same link and
//! checks as a print, safe stop on failure, then hand the bed to the camera's check or
//! call it clear); and the check asked for before a job on a bed the camera found clear a
//! while ago ([`check_first`]). The check itself is the camera's (`camera::bedwatch`),
//! which follows the beds as the store publishes them.

use super::{JobEnd, PrintFailure, PrinterLink, Supervisor};
use crate::daemon::bed::{Bed, CheckFor, ClearBy, ClearedBy, Clearing, Why};
use crate::daemon::farm::{Farm, LiveProgress, PrintCommand, PrinterLive, PrinterState};
use crate::daemon::job::now_s;
use crate::daemon::store::BedChange;
use crate::marlin::stream::PrintError;
use std::time::Duration;
use tokio::sync::{mpsc, watch};
use tracing::Instrument;

/// A camera's "clear" older than this is looked at again before a job starts.
const CHECK_FRESH_S: f64 = 60.0;
/// The longest wait for the bed to cool to its release temperature.
const COOL_MAX: Duration = Duration::from_secs(2 * 3600);

/// What the store is asked when a print of `job` ended on `printer`: its eject when it
/// printed well and its printer (or the job's folder) clears beds by machine and the print
/// is not too tall; else a person's gate, with the reason when the eject was wanted.
pub(super) async fn close_gate(farm: &Farm, printer: &str, job: &str, printed: bool) {
    let bed = if printed {
        after_print(farm, printer, job)
    } else {
        Bed::Waiting { why: None }
    };
    let change = |to| BedChange {
        from: None,
        to,
        printed: Some(job.to_string()),
        check: None,
        record: None,
    };
    if let Err(e) = farm.jobs().change_bed(printer, change(bed)).await {
        // Whatever the bed was, a person's gate is always a legal next state.
        tracing::warn!(error = %e, "the bed cannot go on to be ejected; it waits for a person");
        if let Err(e) = farm
            .jobs()
            .change_bed(printer, change(Bed::Waiting { why: None }))
            .await
        {
            tracing::error!(error = %e, "cannot persist the bed gate");
        }
    }
}

/// The bed after a good print of `job` on `printer` (see [`close_gate`]).
fn after_print(farm: &Farm, printer: &str, job: &str) -> Bed {
    let config = farm.config();
    let store = farm.store();
    let waiting = |why| Bed::Waiting { why };
    let (Some(p), Some(job)) = (
        config.printers.iter().find(|p| p.name == printer),
        store.get(job),
    ) else {
        return waiting(None);
    };
    let clear = config
        .folder(&job.folder)
        .and_then(|f| f.bed_clear)
        .unwrap_or(p.bed_clear);
    if clear == ClearBy::Person {
        return waiting(None);
    }
    let Some(eject) = &p.eject else {
        return waiting(Some(Why::NoEject));
    };
    let height = job
        .slice_report
        .as_ref()
        .map(|r| r.top_layer_z_mm)
        .filter(|h| h.is_finite() && *h > 0.0);
    match height {
        None => waiting(Some(Why::HeightUnknown)),
        Some(h) if h > eject.max_height_mm => waiting(Some(Why::TooTall {
            height_mm: h,
            max_mm: eject.max_height_mm,
        })),
        Some(_) => Bed::EjectDue {
            check: clear == ClearBy::EjectAndCheck,
        },
    }
}

/// Whether the camera must look at a clear `bed` before `printer` takes a job: it was last
/// found clear by the camera over [`CHECK_FRESH_S`] ago, and a job waits for the printer.
pub(super) fn check_first(farm: &Farm, printer: &str, bed: &Bed) -> bool {
    matches!(bed, Bed::Clear { by: ClearedBy::Camera, at_s } if now_s() - at_s > CHECK_FRESH_S)
        && super::job_waiting_for(farm, printer)
}

/// Asks the camera to check `printer`'s bed before its next job.
pub(super) async fn check_before_job(farm: &Farm, printer: &str) {
    let change = BedChange {
        from: Some(&["clear"]),
        to: Bed::CheckDue {
            after_s: now_s(),
            before: CheckFor::NextJob,
        },
        printed: None,
        check: None,
        record: None,
    };
    if let Err(e) = farm.jobs().change_bed(printer, change).await {
        tracing::warn!(error = %e, "cannot ask for a check of the bed before the next job");
    }
}

/// Forgets what `p` said of its bed (its gate's reason, the eject's progress) as it goes
/// idle on a clear bed.
pub(super) fn forget_bed_shown(p: &mut PrinterLive) {
    let gate_shown = matches!(
        p.state,
        PrinterState::BedNotCleared | PrinterState::Ejecting | PrinterState::CheckingBed
    );
    let eject_shown = p
        .detail
        .as_deref()
        .is_some_and(|d| d.starts_with(COOLING) || d.starts_with(EJECTING));
    if gate_shown || eject_shown {
        p.detail = None;
    }
}

const COOLING: &str = "ejecting: waiting for the bed to cool";
const EJECTING: &str = "ejecting: the eject sequence is running";

/// How the wait for a cool bed ended.
enum Cooled {
    Yes,
    /// The bed's gate changed meanwhile (a person cleared it), or the daemon stops.
    Changed,
    TimedOut(Option<f64>),
    Lost(String),
    Halted(String),
}

/// Waits until the bed is at most `release_c`, reading the printer's temperatures as
/// between jobs, showing how far it is.
async fn cool(
    sup: &Supervisor,
    link: &mut dyn PrinterLink,
    release_c: f64,
    follow: &mut super::Follow,
) -> Cooled {
    let deadline = tokio::time::Instant::now() + COOL_MAX;
    let mut bed_c = None;
    loop {
        let news = tokio::select! {
            () = follow.changed() => {
                let due = matches!(sup.farm.store().gate(&sup.name).bed, Bed::EjectDue { .. });
                if !due || sup.farm.stopping() {
                    return Cooled::Changed;
                }
                continue;
            }
            () = tokio::time::sleep_until(deadline) => return Cooled::TimedOut(bed_c),
            news = link.watch_idle() => news,
        };
        match news {
            super::IdleNews::Temperatures(t) => {
                bed_c = t.and_then(|t| t.bed_c);
                sup.show(|p| {
                    p.temperatures = t;
                    p.detail = Some(format!(
                        "{COOLING} to {release_c:.0} °C{}",
                        bed_c
                            .map(|c| format!(" (now {c:.0} °C)"))
                            .unwrap_or_default()
                    ));
                });
                if bed_c.is_some_and(|c| c <= release_c) {
                    return Cooled::Yes;
                }
            }
            // The sequence starts on a fresh handshake.
            super::IdleNews::Rebooted => {}
            super::IdleNews::Lost(why) => return Cooled::Lost(why),
            super::IdleNews::Halted(message) => return Cooled::Halted(message),
        }
    }
}

/// Sets the bed from `from` to `to`, with a step for the last job's record.
async fn settle(
    farm: &Farm,
    printer: &str,
    from: &'static [&'static str],
    to: Bed,
    record: Option<Clearing>,
) {
    let change = BedChange {
        from: Some(from),
        to,
        printed: None,
        check: None,
        record,
    };
    if let Err(e) = farm.jobs().change_bed(printer, change).await {
        tracing::error!(error = %e, "cannot record the bed's state");
    }
}

/// Runs the eject sequence due on the supervisor's printer (`check`: the camera checks the
/// bed after it). Exactly once: the bed is recorded as ejecting before the first line is
/// sent, and a restart that finds it so does not send it again.
pub(super) async fn run(
    sup: &Supervisor,
    link: &mut dyn PrinterLink,
    check: bool,
    follow: &mut super::Follow,
) -> JobEnd {
    let farm = &sup.farm;
    let printer = sup.name.as_str();
    let job = farm.store().gate(printer).last_job;
    let span = tracing::info_span!("eject", job = job.as_deref().unwrap_or("-"));
    async move {
        let config = farm.config();
        let Some(eject) = config
            .printers
            .iter()
            .find(|p| p.name == printer)
            .and_then(|p| p.eject.clone())
        else {
            // A reload took the printer's sequence away since the print ended.
            let to = Bed::Waiting {
                why: Some(Why::NoEject),
            };
            settle(farm, printer, &["eject_due"], to, None).await;
            return JobEnd::default();
        };
        sup.show(|p| {
            p.state = PrinterState::Ejecting;
            p.job = job.clone();
            p.progress = None;
        });
        if let Some(release_c) = eject.release_bed_c {
            match cool(sup, link, release_c, follow).await {
                Cooled::Yes => {}
                Cooled::Changed => return JobEnd::default(),
                Cooled::TimedOut(bed_c) => {
                    tracing::warn!(
                        release_c,
                        bed_c,
                        "the bed did not cool in time; it waits for a person"
                    );
                    let to = Bed::Waiting {
                        why: Some(Why::StayedWarm { bed_c, release_c }),
                    };
                    settle(farm, printer, &["eject_due"], to, None).await;
                    return JobEnd::default();
                }
                Cooled::Lost(why) => {
                    super::lost_between_jobs(sup, why);
                    return JobEnd {
                        lost: true,
                        halted: None,
                    };
                }
                Cooled::Halted(message) => {
                    tracing::error!(message, "the printer halted while its bed cooled");
                    return JobEnd {
                        lost: false,
                        halted: Some(message),
                    };
                }
            }
        }
        // Recorded before the first line: from here on it is never sent again.
        let started_s = now_s();
        let begin = BedChange {
            from: Some(&["eject_due"]),
            to: Bed::Ejecting {
                since_s: started_s,
                check,
            },
            printed: None,
            check: None,
            record: None,
        };
        if let Err(e) = farm.jobs().change_bed(printer, begin).await {
            tracing::warn!(error = %e, "the eject does not run");
            return JobEnd::default();
        }
        tracing::info!("eject sequence starting");
        let outcome = stream(sup, link, &eject.gcode).await;
        let ended_s = now_s();
        let error = outcome.as_ref().err().map(|e| e.to_string());
        let record = Clearing::Eject {
            printer: printer.to_string(),
            started_s,
            ended_s,
            error: error.clone(),
        };
        let to = match &outcome {
            Ok(()) if check => Bed::CheckDue {
                after_s: ended_s,
                before: CheckFor::AfterEject,
            },
            Ok(()) => Bed::Clear {
                by: ClearedBy::Eject,
                at_s: ended_s,
            },
            Err(PrintFailure::Cancelled(_)) if farm.stopping() => Bed::Waiting {
                why: Some(Why::EjectInterrupted),
            },
            Err(e) => Bed::Waiting {
                why: Some(Why::EjectFailed {
                    error: e.to_string(),
                }),
            },
        };
        match &error {
            None => tracing::info!("eject sequence done"),
            Some(e) => {
                tracing::error!(error = %e, "eject sequence failed; the bed waits for a person")
            }
        }
        settle(farm, printer, &["ejecting"], to, Some(record)).await;
        sup.show(|p| {
            p.progress = None;
            p.detail = None;
        });
        match outcome {
            Err(PrintFailure::Lost(_)) => {
                sup.show(|p| p.temperatures = None);
                JobEnd {
                    lost: true,
                    halted: None,
                }
            }
            Err(PrintFailure::Failed(PrintError::Fatal { message, .. })) => JobEnd {
                lost: false,
                halted: Some(message),
            },
            _ => JobEnd::default(),
        }
    }
    .instrument(span)
    .await
}

/// Streams the sequence (with an `M400`, so its last answer comes once the moves are
/// done and the camera sees the bed as they left it) from a file in the spool.
async fn stream(
    sup: &Supervisor,
    link: &mut dyn PrinterLink,
    gcode: &str,
) -> Result<(), PrintFailure> {
    let farm = &sup.farm;
    let dir = farm.config().spool_dir.join("eject");
    let path = dir.join(format!("{}.gcode", sup.name));
    let text = format!("{}\nM400\n", gcode.trim_end());
    let written = {
        let path = path.clone();
        tokio::task::spawn_blocking(move || -> std::io::Result<()> {
            std::fs::create_dir_all(&dir)?;
            Ok(crate::fsutil::write_atomic(&path, text.as_bytes())?)
        })
        .await
    };
    match written {
        Ok(Ok(())) => {}
        // Nothing was sent: the bed waits for a person with the reason.
        Ok(Err(e)) => {
            return Err(PrintFailure::Gcode(crate::marlin::gcode::GcodeError::Io {
                path,
                source: e,
            }))
        }
        Err(e) => return Err(PrintFailure::LoaderCrashed(e)),
    }
    sup.show(|p| p.detail = Some(EJECTING.to_string()));
    let (control_tx, control_rx) = mpsc::channel(8);
    let (progress_tx, mut progress_rx) = watch::channel(LiveProgress::default());
    let print = link.print(
        &path,
        Vec::new(),
        Default::default(),
        control_rx,
        progress_tx,
    );
    tokio::pin!(print);
    let mut stopping = false;
    let mut progress_open = true;
    loop {
        tokio::select! {
            outcome = &mut print => return outcome.map(|_| ()),
            changed = progress_rx.changed(), if progress_open => {
                if changed.is_err() {
                    progress_open = false;
                    continue;
                }
                let live = progress_rx.borrow_and_update().clone();
                sup.show(|p| super::show_progress(p, live));
            }
            // A stop of the prints stops the sequence too (heaters off).
            _ = farm.stop_prints.cancelled(), if !stopping => {
                stopping = true;
                let _ = control_tx.send(PrintCommand::Cancel).await;
            }
        }
    }
}
