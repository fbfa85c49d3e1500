//! What a request may change in a job besides its state, and in the farm's spools and the
//! printers' care, as typed commands: each variant names what it sets and the condition
//! it sets it under, and [`JobChange::apply`] and [`InventoryChange::apply`] are the one
//! place that carries them out, inside the store's step that also checks and changes the
//! state (the embedded spool's write, or the farm database's transaction). A caller says
//! what happened; the rule for what that does lives here.

use crate::daemon::care::CareChange;
use crate::daemon::filament::{Asks, Filament, FilamentError, Inventory, Need, Report, SetAside};
use crate::daemon::job::{
    Comparison, ForMachine, Job, JobState, JobUse, PartCancel, PrintReport, Sidecar,
};
use crate::slice::moved::WallsState;
use crate::slice::walls::WallComparison;
use crate::slice::SliceReport;
use std::collections::BTreeMap;

/// A change to a job's other fields, made in the same step as its state change (or
/// alone, as an update).
pub enum JobChange {
    /// Nothing besides the state; as an update, a change of the job for its followers to
    /// look at again (a preview drawn beside it).
    Nothing,
    /// Its preparation ended with G-code for at least one machine.
    Prepared(Box<PreparedJob>),
    /// Its preparation ended with no machine able to print it: each machine's reason.
    Unprintable {
        machines: BTreeMap<String, ForMachine>,
        sidecar: Option<Sidecar>,
        asks: Asks,
    },
    /// The operator releases a held job: one whose sidecar holds it, or, not prepared yet,
    /// whose sidecar file on disk does (`held_on_disk`); only while it is active.
    Release { held_on_disk: bool },
    /// The operator cancels a part of a ready job's plate, before its print begins.
    CancelPart { part: String, at_s: f64 },
    /// A print ended: its report when it printed whole (a copy done), and what it took
    /// from the spool, booked once per print.
    Printed {
        report: Option<PrintReport>,
        usage: Option<Use>,
    },
    /// What an earlier run's print took from the spool, found at the next start.
    Used(Use),
    /// The parts print `print` dropped, with where: one cancelled before the print is
    /// completed with it, any other added.
    PartsDropped {
        print: u32,
        dropped: Vec<PartCancel>,
    },
    /// A wall comparison starts: counted as `next` if it is still pending after `tries`.
    ComparisonStarted { tries: u32, next: Comparison },
    /// A wall comparison ended, for the G-code the job had when it started (pending after
    /// `tries`): its figures, or why there are none.
    ComparisonEnded {
        tries: u32,
        walls: Result<WallComparison, String>,
        started_s: f64,
        took_s: f64,
    },
    /// Tests set what they need of a job directly.
    #[cfg(test)]
    Edit(Box<dyn FnOnce(&mut Job) + Send>),
}

/// What preparation made of a job that some machine can print.
pub struct PreparedJob {
    pub machines: BTreeMap<String, ForMachine>,
    pub needs: BTreeMap<String, Need>,
    pub sidecar: Option<Sidecar>,
    pub asks: Asks,
    pub report: Option<SliceReport>,
    /// The wall comparison it waits for (an enhanced model's).
    pub comparison: Option<Comparison>,
}

/// A print's use of a spool: the print it belongs to (the job's uses count its prints, so
/// a use is booked once whoever records it first).
pub struct Use {
    pub print: usize,
    pub usage: JobUse,
}

impl Use {
    fn book(self, job: &mut Job) -> bool {
        let due = job.uses.len() == self.print;
        if due {
            job.uses.push(self.usage);
        }
        due
    }
}

impl JobChange {
    /// Carries the change out on `job`; whether it did (a change whose condition the job
    /// no longer meets leaves it as it was).
    pub(crate) fn apply(self, job: &mut Job) -> bool {
        match self {
            JobChange::Nothing => false,
            JobChange::Prepared(prepared) => {
                let PreparedJob {
                    machines,
                    needs,
                    sidecar,
                    asks,
                    report,
                    comparison,
                } = *prepared;
                job.machines = machines;
                job.needs = needs;
                job.sidecar = sidecar;
                job.asks = asks;
                job.slice_report = report;
                job.comparison = comparison;
                true
            }
            JobChange::Unprintable {
                machines,
                sidecar,
                asks,
            } => {
                job.machines = machines;
                job.sidecar = sidecar;
                job.asks = asks;
                true
            }
            JobChange::Release { held_on_disk } => {
                let held_unprepared = held_on_disk && !job.released && job.sidecar_unread();
                let release = (job.held() || held_unprepared) && job.state.is_active();
                job.released |= release;
                release
            }
            JobChange::CancelPart { part, at_s } => {
                if job.state != JobState::Ready {
                    return false;
                }
                let print = job.print_number();
                if job.parts_cancelled_in(print).any(|c| c.part == part) {
                    return false;
                }
                job.parts_cancelled.push(PartCancel {
                    part,
                    print,
                    at_s,
                    dropped: None,
                });
                true
            }
            JobChange::Printed { report, usage } => {
                let copy = report.is_some();
                if let Some(report) = report {
                    job.copies_done += 1;
                    job.print_report = Some(report);
                }
                usage.is_some_and(|u| u.book(job)) || copy
            }
            JobChange::Used(usage) => usage.book(job),
            JobChange::PartsDropped { print, dropped } => {
                let any = !dropped.is_empty();
                for d in dropped {
                    tracing::info!(part = %d.part, at = ?d.dropped, "a part of the plate dropped");
                    let known = job
                        .parts_cancelled
                        .iter_mut()
                        .find(|c| c.print == print && c.part == d.part);
                    match known {
                        Some(c) => c.dropped = c.dropped.take().or(d.dropped),
                        None => job.parts_cancelled.push(PartCancel { print, ..d }),
                    }
                }
                any
            }
            JobChange::ComparisonStarted { tries, next } => {
                let due = job.comparison == Some(Comparison::Pending { tries });
                if due {
                    job.comparison = Some(next);
                }
                due
            }
            JobChange::ComparisonEnded {
                tries,
                walls,
                started_s,
                took_s,
            } => {
                // Measured for the G-code the job has now: not when it was prepared again
                // (and its comparison pending afresh) meanwhile.
                if job.comparison != Some(Comparison::Pending { tries }) {
                    return false;
                }
                let measured = walls.is_ok();
                job.comparison = Some(match walls {
                    Ok(walls) => {
                        if let Some(report) = &mut job.slice_report {
                            report.walls = Some(walls);
                        }
                        Comparison::Done { started_s, took_s }
                    }
                    Err(reason) => Comparison::NotMeasured { reason },
                });
                if let Some(report) = &mut job.slice_report {
                    // With the walls measured their figures are said; else why they are not.
                    report.walls_state = if measured {
                        WallsState::Pending
                    } else {
                        WallsState::NotMeasured
                    };
                }
                true
            }
            #[cfg(test)]
            JobChange::Edit(edit) => {
                edit(job);
                true
            }
        }
    }
}

/// A change to the farm's spools or a printer's care. A shared store may apply it again to
/// a newer inventory (another host changed it meanwhile), so it never counts on what an
/// earlier attempt did.
#[derive(Debug, Clone)]
pub enum InventoryChange {
    /// Loads spool `spool` onto `printer`.
    Load { printer: String, spool: String },
    /// Adds a spool of the farm's own and loads it onto `printer`.
    AddAndLoad {
        printer: String,
        filament: Filament,
        grams: f64,
    },
    /// Takes the spool off `printer`.
    Unload { printer: String },
    /// Adds a spool of the farm's own, loaded nowhere.
    Add { filament: Filament, grams: f64 },
    /// A maintenance task done, or the printer held for one or released.
    Care { printer: String, change: CareChange },
    /// Spoolman's spools as just read (see `Inventory::take_spoolman`).
    Spoolman {
        spools: Vec<(u64, Filament, Option<f64>, bool)>,
        set_aside: Vec<SetAside>,
    },
    /// Where a use stands with Spoolman after it was told.
    Reported {
        spool: String,
        key: String,
        report: Report,
        remaining_g: Option<f64>,
    },
}

impl InventoryChange {
    /// Carries the change out on `inventory`; a refused change is an error, and the store
    /// keeps the inventory as it was.
    pub(crate) fn apply(&self, inventory: &mut Inventory) -> Result<(), FilamentError> {
        match self {
            InventoryChange::Load { printer, spool } => inventory.load(printer, spool),
            InventoryChange::AddAndLoad {
                printer,
                filament,
                grams,
            } => {
                let id = inventory.add_spool(filament.clone(), *grams)?;
                inventory.load(printer, &id)
            }
            InventoryChange::Unload { printer } => {
                inventory.unload(printer);
                Ok(())
            }
            InventoryChange::Add { filament, grams } => {
                inventory.add_spool(filament.clone(), *grams).map(drop)
            }
            InventoryChange::Care { printer, change } => {
                Ok(change.clone().apply(printer, &mut inventory.care)?)
            }
            InventoryChange::Spoolman { spools, set_aside } => {
                inventory.take_spoolman(spools.clone(), set_aside.clone());
                Ok(())
            }
            InventoryChange::Reported {
                spool,
                key,
                report,
                remaining_g,
            } => {
                inventory.set_report(spool, key, *report, *remaining_g);
                Ok(())
            }
        }
    }
}
