//! The printer fleet: one supervisor task per configured printer, and how a reload
//! changes the set. It owns which printers the farm has (it adds each to the farm as its
//! supervisor starts and takes it out once a retired supervisor has ended), and it
//! supervises its tasks: [`Fleet::next_end`] tells the service of a supervisor that ended
//! while it should run. Its rule, read on its own: a print in progress is never cut short
//! by a reload.
//!
//! How a printer's port is reached is handed in ([`Ports`]): the real serial ports and
//! simulators ([`marlin_ports`]), or a test's doubles.

use super::config::{PrinterConfig, PrinterPort};
use super::error::DaemonError;
use super::farm::{printer_channels, Farm, PrinterLive, PrintersOwner};
use super::printer;
use std::collections::{BTreeMap, HashMap};
use std::sync::Arc;
use tokio::sync::watch;
use tokio::task::{Id, JoinSet};

/// A printer's way in, as [`Ports`] resolves it.
pub(crate) struct Port {
    pub connector: Box<dyn printer::Connector>,
    /// Shown in the status (the device, or the simulator's pty).
    pub shown: String,
    /// Kept alive as long as the supervisor (a simulated printer's handle).
    pub keep: Option<Box<dyn Send>>,
}

/// Resolves a configured printer to its [`Port`].
pub(crate) type Ports = Box<dyn Fn(&PrinterConfig) -> Result<Port, DaemonError> + Send + Sync>;

/// The real ports: a serial device, or a simulated printer started here.
pub(crate) fn marlin_ports() -> Ports {
    Box::new(|spec: &PrinterConfig| {
        let (port, simulator) = match &spec.port {
            PrinterPort::Serial(path) => (path.clone(), None),
            PrinterPort::Simulated {
                time_scale,
                seed,
                record,
            } => {
                let mut sim = crate::sim::SimConfig::new(spec.firmware);
                sim.time_scale = *time_scale;
                sim.seed = *seed;
                sim.record = record.clone();
                // Tests read what it ran from the record file; memory must not grow with jobs.
                sim.keep_executed = false;
                let handle = crate::sim::spawn(sim).map_err(|e| DaemonError::Simulator {
                    printer: spec.name.clone(),
                    message: e.to_string(),
                })?;
                let device = handle.device_path().to_path_buf();
                tracing::info!(printer = %spec.name, device = %device.display(), time_scale, "simulated printer started");
                (device, Some(handle))
            }
        };
        Ok(Port {
            shown: port.display().to_string(),
            connector: Box::new(printer::MarlinConnector {
                port,
                firmware: spec.firmware,
                baud: spec.baud,
                heat_timeout: spec.heat_timeout,
                pause: {
                    let mut pause = crate::marlin::stream::PauseSettings::new(spec.machine.bed_mm);
                    pause.heaters_off_after = spec.pause_heaters_off;
                    pause.park_gcode = spec.machine.pause_gcode.clone();
                    pause.resume_gcode = spec.machine.resume_gcode.clone();
                    pause
                },
            }),
            keep: simulator.map(|s| Box::new(s) as Box<dyn Send>),
        })
    })
}

/// The printer supervisors, one per configured printer, and how a reload changes them:
/// a printer added to the config starts at once; one removed or changed retires when it
/// is not printing (a print in progress is never cut short by a reload), and a changed
/// one then starts again with its new settings.
pub(crate) struct Fleet {
    farm: Arc<Farm>,
    owner: PrintersOwner,
    ports: Ports,
    tasks: JoinSet<()>,
    running: BTreeMap<String, Supervised>,
    /// Retired supervisors still finishing a print, by task.
    retiring: HashMap<Id, Supervised>,
    /// New settings for printers whose old supervisor is still retiring.
    waiting: Vec<PrinterConfig>,
}

struct Supervised {
    spec: PrinterConfig,
    task: Id,
    retire: watch::Sender<bool>,
    _keep: Option<Box<dyn Send>>,
}

impl Fleet {
    /// Starts a supervisor for each of `printers`; the fleet alone adds and removes the
    /// farm's printers (`owner`).
    pub(crate) fn start_all(
        farm: &Arc<Farm>,
        owner: PrintersOwner,
        printers: &[PrinterConfig],
        ports: Ports,
    ) -> Result<Fleet, DaemonError> {
        let mut fleet = Fleet {
            farm: Arc::clone(farm),
            owner,
            ports,
            tasks: JoinSet::new(),
            running: BTreeMap::new(),
            retiring: HashMap::new(),
            waiting: Vec::new(),
        };
        for spec in printers {
            fleet.start(spec.clone())?;
        }
        Ok(fleet)
    }

    /// Resolves the printer's port, adds it to the farm and starts its supervisor.
    fn start(&mut self, spec: PrinterConfig) -> Result<(), DaemonError> {
        let port = (self.ports)(&spec)?;
        let (owner, handle) =
            printer_channels(PrinterLive::connecting(spec.firmware.name(), &port.shown));
        self.owner.add(&spec.name, handle);
        let (retire, retired) = watch::channel(false);
        let task = self.tasks.spawn(printer::supervise(
            Arc::clone(&self.farm),
            spec.name.clone(),
            owner,
            port.connector,
            retired,
        ));
        self.running.insert(
            spec.name.clone(),
            Supervised {
                spec,
                task: task.id(),
                retire,
                _keep: port.keep,
            },
        );
        Ok(())
    }

    /// Applies a reloaded config's printers.
    pub(crate) fn apply(&mut self, printers: &[PrinterConfig]) {
        let names: Vec<String> = self.running.keys().cloned().collect();
        for name in names {
            let spec = &self.running[&name].spec;
            match printers.iter().find(|p| p.name == name) {
                Some(new) if new == spec => {}
                new => {
                    let old = self.running.remove(&name).expect("listed above");
                    old.retire.send_replace(true);
                    tracing::info!(printer = %name, "config reload: retiring the printer's supervisor");
                    self.retiring.insert(old.task, old);
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
        self.start_waiting();
    }

    /// Starts the waiting printers whose names are free again.
    fn start_waiting(&mut self) {
        let waiting = std::mem::take(&mut self.waiting);
        for spec in waiting {
            if self.retiring.values().any(|s| s.spec.name == spec.name) {
                self.waiting.push(spec);
                continue;
            }
            let name = spec.name.clone();
            if let Err(e) = self.start(spec) {
                tracing::error!(printer = %name, error = %e, "config reload: cannot start the printer");
            }
        }
    }

    /// Waits for a supervisor that ended while it should run (it ends only once retired,
    /// or at shutdown): its printer's name and how it ended. A retired one that ended is
    /// let go of here (and its printer taken out of the farm, or started again with its
    /// new settings). Pending while there is nothing to wait for.
    pub(crate) async fn next_end(&mut self) -> (String, Result<(), tokio::task::JoinError>) {
        loop {
            let Some(ended) = self.tasks.join_next_with_id().await else {
                return std::future::pending().await;
            };
            let (id, how) = match ended {
                Ok((id, ())) => (id, Ok(())),
                Err(e) => (e.id(), Err(e)),
            };
            if let Some(retired) = self.retiring.remove(&id) {
                let name = retired.spec.name.clone();
                if !self.running.contains_key(&name) {
                    self.owner.remove(&name);
                }
                self.start_waiting();
                continue;
            }
            if let Some(name) = self
                .running
                .iter()
                .find(|(_, s)| s.task == id)
                .map(|(n, _)| n.clone())
            {
                self.running.remove(&name);
                return (name, how);
            }
        }
    }

    /// Waits for every supervisor to end (after [`StopOwner::begin`](super::farm::StopOwner::begin)).
    pub(crate) async fn join(mut self) {
        while self.tasks.join_next().await.is_some() {}
    }
}
