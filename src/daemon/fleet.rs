//! The printer fleet: one supervisor task per configured printer, and how a reload
//! changes the set. Kept apart from `run()` because it is the one piece of the daemon's
//! wiring with state of its own across reloads (running, retiring and waiting
//! supervisors), and its rules (a print in progress is never cut short) are read on their own.

use super::config::{PrinterConfig, PrinterPort};
use super::farm::{Farm, PrinterState, PrinterStatus};
use super::{printer, DaemonError};
use std::collections::BTreeMap;
use std::sync::Arc;
use tokio::sync::watch;

/// The printer supervisors, one per configured printer, and how a reload changes them:
/// a printer added to the config starts at once; one removed or changed retires when it
/// is not printing (a print in progress is never cut short by a reload), and a changed
/// one then starts again with its new settings.
pub(super) struct Fleet {
    running: BTreeMap<String, Supervised>,
    /// Retired supervisors still finishing a print.
    retiring: Vec<Supervised>,
    /// New settings for printers whose old supervisor is still retiring.
    waiting: Vec<PrinterConfig>,
}

struct Supervised {
    spec: PrinterConfig,
    task: tokio::task::JoinHandle<()>,
    retire: watch::Sender<bool>,
    /// Keeps a simulated printer alive as long as its supervisor.
    _simulator: Option<crate::marlin::sim::SimHandle>,
}

impl Fleet {
    pub(super) fn start_all(
        farm: &Arc<Farm>,
        printers: &[PrinterConfig],
    ) -> Result<Fleet, DaemonError> {
        let mut fleet = Fleet {
            running: BTreeMap::new(),
            retiring: Vec::new(),
            waiting: Vec::new(),
        };
        for spec in printers {
            fleet.start(farm, spec.clone())?;
        }
        Ok(fleet)
    }

    /// Resolves the printer's port (starting its simulator if it has one), shows it in
    /// the status and starts its supervisor.
    pub(super) fn start(
        &mut self,
        farm: &Arc<Farm>,
        spec: PrinterConfig,
    ) -> Result<(), DaemonError> {
        let (port, simulator) = match &spec.port {
            PrinterPort::Serial(path) => (path.clone(), None),
            PrinterPort::Simulated {
                time_scale,
                seed,
                record,
            } => {
                let mut sim = crate::marlin::sim::SimConfig::new(spec.firmware);
                sim.time_scale = *time_scale;
                sim.seed = *seed;
                sim.record = record.clone();
                // Tests read what it ran from the record file; memory must not grow with jobs.
                sim.keep_executed = false;
                let handle =
                    crate::marlin::sim::spawn(sim).map_err(|e| DaemonError::Simulator {
                        printer: spec.name.clone(),
                        message: e.to_string(),
                    })?;
                let device = handle.device_path().to_path_buf();
                tracing::info!(printer = %spec.name, device = %device.display(), time_scale, "simulated printer started");
                (device, Some(handle))
            }
        };
        farm.printers
            .lock()
            .unwrap_or_else(|e| e.into_inner())
            .insert(
                spec.name.clone(),
                PrinterStatus {
                    name: spec.name.clone(),
                    state: PrinterState::Connecting,
                    firmware: spec.firmware.name().to_string(),
                    port: port.display().to_string(),
                    job: None,
                    progress: None,
                    temperatures: None,
                    detail: None,
                    bed_cleared: true,
                    host: farm
                        .config()
                        .store
                        .as_ref()
                        .map(|_| farm.config().farm.host.clone()),
                    offline: false,
                },
            );
        let connector = Box::new(printer::MarlinConnector {
            port,
            firmware: spec.firmware,
            baud: spec.baud,
            heat_timeout: spec.heat_timeout,
        });
        let (retire, retired) = watch::channel(false);
        let task = tokio::spawn(printer::supervise(
            Arc::clone(farm),
            spec.name.clone(),
            connector,
            retired,
        ));
        self.running.insert(
            spec.name.clone(),
            Supervised {
                spec,
                task,
                retire,
                _simulator: simulator,
            },
        );
        Ok(())
    }

    /// Applies a reloaded config's printers.
    pub(super) fn apply(&mut self, farm: &Arc<Farm>, printers: &[PrinterConfig]) {
        let names: Vec<String> = self.running.keys().cloned().collect();
        for name in names {
            let spec = &self.running[&name].spec;
            match printers.iter().find(|p| p.name == name) {
                Some(new) if new == spec => {}
                new => {
                    let old = self.running.remove(&name).expect("listed above");
                    old.retire.send_replace(true);
                    tracing::info!(printer = %name, "config reload: retiring the printer's supervisor");
                    self.retiring.push(old);
                    if let Some(new) = new {
                        self.waiting.push(new.clone());
                    }
                }
            }
        }
        self.waiting
            .retain(|w| printers.iter().any(|p| p.name == w.name));
        for new in printers {
            if !self.running.contains_key(&new.name)
                && !self.waiting.iter().any(|w| w.name == new.name)
            {
                self.waiting.push(new.clone());
            }
        }
        self.settle(farm);
    }

    /// Lets go of retired supervisors that have finished and starts the waiting printers
    /// whose names are free again.
    pub(super) fn settle(&mut self, farm: &Arc<Farm>) {
        self.retiring.retain(|s| !s.task.is_finished());
        let waiting = std::mem::take(&mut self.waiting);
        for spec in waiting {
            if self.retiring.iter().any(|s| s.spec.name == spec.name) {
                self.waiting.push(spec);
                continue;
            }
            let name = spec.name.clone();
            if let Err(e) = self.start(farm, spec) {
                tracing::error!(printer = %name, error = %e, "config reload: cannot start the printer");
            }
        }
    }

    /// A printer whose supervisor ended (it panicked: it ends only once retired, which
    /// moves it out of `running`, or at shutdown).
    pub(super) fn ended(&self) -> Option<String> {
        if self.running.is_empty() {
            return None;
        }
        self.running
            .iter()
            .find(|(_, s)| s.task.is_finished())
            .map(|(name, _)| name.clone())
    }

    /// Waits for every supervisor to end (after [`Farm::begin_stop`]).
    pub(super) async fn join(self) {
        for s in self.running.into_values().chain(self.retiring) {
            let _ = s.task.await;
        }
    }
}
