//! Test doubles for the daemon's I/O seams, so the real supervisor, fleet, permits and
//! shutdown code can be tested in-process on a paused tokio clock:
//!
//! - [`BenchPrinter`]: a printer on the bench. Its [`PrinterLink`] takes a job's G-code
//!   line by line as a Marlin printer would: each line is recorded as it is sent, a
//!   heat-and-wait (`M109`/`M190`) is acknowledged only once its heater has reached the
//!   target (heaters warm at [`BenchPrinter::HEAT_C_PER_S`]), a move takes
//!   [`BenchPrinter::MOVE`], pause holds the next line, and a cancel sends the heaters-off
//!   lines before the print ends cancelled. Between jobs it answers temperature polls every
//!   few seconds; a test may unplug it. An `M112` halts it (the print fails as on a real
//!   firmware's `kill()`) until a test resets it, which the link reports as a reboot.
//! - [`BenchConnector`]: opens links to a bench printer, or refuses while it is unplugged.
//! - [`ports`]: a fleet's [`Ports`] resolving each configured printer to a bench printer.
//!
//! The job store is the real spool in a temporary directory.

use super::config::{Config, PrinterConfig};
use super::farm::{Farm, LiveProgress, PrintCommand, PrinterTemperatures};
use super::fleet::{Port, Ports};
use super::job::{ForMachine, JobState, PrintReport};
use super::printer::{
    heat_up_end, BoxFuture, ConnectError, Connector, IdleNews, PrintFailure, PrinterLink,
};
use super::store::JobChange;
use crate::marlin::stream::{PrintError, StopOutcome};
use crate::marlin::transport::TransportError;
use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::sync::{Arc, Mutex};
use std::time::Duration;
use tokio::sync::{mpsc, watch};

/// The lines a stop sends: heaters, fan and motors off.
pub(crate) const SAFE_STOP: [&str; 4] = ["M104 S0", "M140 S0", "M107", "M84"];

/// One printer on the bench, shared by its connector and its links.
#[derive(Clone, Default)]
pub(crate) struct BenchPrinter(Arc<Mutex<Bench>>);

#[derive(Default)]
struct Bench {
    /// Every line it was sent, in order (temperature polls as `M105`).
    sent: Vec<String>,
    unplugged: bool,
    hotend_c: f64,
    bed_c: f64,
    connects: usize,
    /// Tells an open link that it was unplugged.
    unplug: Option<mpsc::UnboundedSender<()>>,
    /// Halted by an `M112`.
    halted: bool,
    /// Tells an open link that the printer was reset (it says `start`).
    reset: Option<mpsc::UnboundedSender<()>>,
}

impl BenchPrinter {
    pub(crate) const HEAT_C_PER_S: f64 = 2.0;
    pub(crate) const MOVE: Duration = Duration::from_millis(100);
    pub(crate) const POLL: Duration = Duration::from_secs(3);

    fn lock(&self) -> std::sync::MutexGuard<'_, Bench> {
        self.0.lock().unwrap()
    }

    /// Every line sent so far.
    pub(crate) fn sent(&self) -> Vec<String> {
        self.lock().sent.clone()
    }

    /// The lines sent so far that are not temperature polls.
    pub(crate) fn job_lines(&self) -> Vec<String> {
        self.sent().into_iter().filter(|l| l != "M105").collect()
    }

    pub(crate) fn connects(&self) -> usize {
        self.lock().connects
    }

    /// Pulls the cable: the open link, if any, is lost; connecting fails until plugged.
    pub(crate) fn unplug(&self) {
        let mut bench = self.lock();
        bench.unplugged = true;
        if let Some(tx) = bench.unplug.take() {
            let _ = tx.send(());
        }
    }

    pub(crate) fn plug_in(&self) {
        self.lock().unplugged = false;
    }

    pub(crate) fn halted(&self) -> bool {
        self.lock().halted
    }

    /// Presses the reset button: no longer halted, and the open link hears `start`.
    pub(crate) fn reset(&self) {
        let mut bench = self.lock();
        bench.halted = false;
        if let Some(tx) = &bench.reset {
            let _ = tx.send(());
        }
    }

    fn send(&self, line: &str) {
        self.lock().sent.push(line.to_string());
    }
}

/// Connects to a [`BenchPrinter`].
pub(crate) struct BenchConnector(pub BenchPrinter);

impl Connector for BenchConnector {
    fn connect(&self) -> BoxFuture<'_, Result<Box<dyn PrinterLink>, ConnectError>> {
        Box::pin(async move {
            let printer = self.0.clone();
            let (tx, rx) = mpsc::unbounded_channel();
            let (reset_tx, reset_rx) = mpsc::unbounded_channel();
            {
                let mut bench = printer.lock();
                bench.connects += 1;
                if bench.unplugged {
                    return Err(ConnectError(PrintError::Open(TransportError::Open {
                        port: PathBuf::from("/dev/bench"),
                        message: "No such file or directory".into(),
                    })));
                }
                bench.unplug = Some(tx);
                bench.reset = Some(reset_tx);
            }
            Ok(Box::new(BenchLink {
                printer,
                unplugged: rx,
                resets: reset_rx,
            }) as Box<dyn PrinterLink>)
        })
    }
}

struct BenchLink {
    printer: BenchPrinter,
    unplugged: mpsc::UnboundedReceiver<()>,
    resets: mpsc::UnboundedReceiver<()>,
}

impl BenchLink {
    fn temperatures(&self) -> PrinterTemperatures {
        let bench = self.printer.lock();
        PrinterTemperatures {
            hotend_c: Some(bench.hotend_c),
            hotend_target_c: Some(0.0),
            bed_c: Some(bench.bed_c),
            bed_target_c: Some(0.0),
        }
    }

    /// Waits out one line as the printer would take it; false when unplugged meanwhile.
    async fn execute(&mut self, line: &str) -> bool {
        let word = line.split_whitespace().next().unwrap_or("");
        let target = line
            .split_whitespace()
            .find_map(|w| w.strip_prefix('S'))
            .and_then(|t| t.parse::<f64>().ok());
        let wait = match (word, target) {
            ("M109" | "M190", Some(target)) => {
                let now = {
                    let bench = self.printer.lock();
                    if word == "M109" {
                        bench.hotend_c
                    } else {
                        bench.bed_c
                    }
                };
                Duration::from_secs_f64(((target - now) / BenchPrinter::HEAT_C_PER_S).max(0.0))
            }
            ("G0" | "G1", _) => BenchPrinter::MOVE,
            _ => Duration::ZERO,
        };
        tokio::select! {
            _ = tokio::time::sleep(wait) => {}
            _ = self.unplugged.recv() => return false,
        }
        if let ("M109" | "M190", Some(target)) = (word, target) {
            let mut bench = self.printer.lock();
            if word == "M109" {
                bench.hotend_c = target;
            } else {
                bench.bed_c = target;
            }
        }
        true
    }
}

impl PrinterLink for BenchLink {
    fn print<'a>(
        &'a mut self,
        gcode: &'a Path,
        _cancelled: Vec<String>,
        _pace: crate::daemon::time_left::Pace,
        mut control: mpsc::Receiver<PrintCommand>,
        progress: watch::Sender<LiveProgress>,
    ) -> BoxFuture<'a, Result<PrintReport, PrintFailure>> {
        Box::pin(async move {
            let text = std::fs::read_to_string(gcode).map_err(|source| {
                crate::marlin::gcode::GcodeError::Io {
                    path: gcode.to_path_buf(),
                    source,
                }
            })?;
            let lines: Vec<&str> = text
                .lines()
                .map(|l| l.split(';').next().unwrap_or("").trim())
                .filter(|l| !l.is_empty())
                .collect();
            let heat_end = heat_up_end(&lines);
            let port = PathBuf::from("/dev/bench");
            let mut paused = false;
            let mut acked = 0;
            let publish = |acked: usize, paused: bool| {
                progress.send_replace(LiveProgress {
                    lines_acked: acked,
                    lines_total: lines.len(),
                    heated: heat_end.is_none_or(|i| acked > i),
                    paused,
                    ..LiveProgress::default()
                });
            };
            publish(0, false);
            while acked < lines.len() {
                // Commands are read between lines (and while paused).
                let command = if paused {
                    control.recv().await
                } else {
                    control.try_recv().ok()
                };
                match command {
                    Some(PrintCommand::Pause) => paused = true,
                    Some(PrintCommand::Resume) => paused = false,
                    // The bench printer draws nothing: a part's lines are sent all the same.
                    Some(PrintCommand::CancelPart(_)) => {}
                    Some(PrintCommand::Cancel) => {
                        for line in SAFE_STOP {
                            self.printer.send(line);
                        }
                        return Err(PrintFailure::Cancelled(PrintError::Cancelled {
                            port,
                            last_acked: acked,
                            stop: StopOutcome::Confirmed,
                        }));
                    }
                    None => {}
                }
                if paused {
                    publish(acked, true);
                    continue;
                }
                self.printer.send(lines[acked]);
                if lines[acked] == "M112" {
                    self.printer.lock().halted = true;
                    return Err(PrintFailure::Failed(PrintError::Fatal {
                        port,
                        message: "Error:Printer halted. kill() called!".into(),
                        last_acked: acked,
                    }));
                }
                if !self.execute(lines[acked]).await {
                    return Err(PrintFailure::Lost(PrintError::Disconnected {
                        port,
                        reason: "unplugged".into(),
                        last_acked: acked,
                    }));
                }
                acked += 1;
                publish(acked, false);
            }
            Ok(PrintReport::default())
        })
    }

    fn watch_idle(&mut self) -> BoxFuture<'_, IdleNews> {
        Box::pin(async move {
            tokio::select! {
                _ = tokio::time::sleep(BenchPrinter::POLL) => {
                    self.printer.send("M105");
                    IdleNews::Temperatures(Some(self.temperatures()))
                }
                _ = self.unplugged.recv() => IdleNews::Lost("unplugged".into()),
                Some(()) = self.resets.recv() => IdleNews::Rebooted,
            }
        })
    }
}

/// Bench printers for a fleet, one per printer name (made on first use).
#[derive(Clone, Default)]
pub(crate) struct BenchPorts(Arc<Mutex<BTreeMap<String, BenchPrinter>>>);

impl BenchPorts {
    pub(crate) fn printer(&self, name: &str) -> BenchPrinter {
        self.0
            .lock()
            .unwrap()
            .entry(name.to_string())
            .or_default()
            .clone()
    }

    /// The fleet's way to the bench printers.
    pub(crate) fn ports(&self) -> Ports {
        let bench = self.clone();
        Box::new(move |spec: &PrinterConfig| {
            Ok(Port {
                connector: Box::new(BenchConnector(bench.printer(&spec.name))),
                shown: format!("bench:{}", spec.name),
                keep: None,
            })
        })
    }
}

/// A farm on a spool in `root`: `printers` (simulated in the config, reached through the
/// bench), one hot folder served by all of them, and `extra` config text.
pub(crate) fn farm_config(root: &Path, printers: &[&str], extra: &str) -> Config {
    let hot = root.join("hot");
    std::fs::create_dir_all(&hot).unwrap();
    let mut text = format!("[spool]\ndir = \"spool\"\n{extra}\n");
    for p in printers {
        text +=
            &format!("[[printer]]\nname = \"{p}\"\nfirmware = \"marlin2\"\n[printer.simulate]\n");
    }
    text += &format!(
        "[[folder]]\npath = {:?}\nheight_mm = 30\nprinters = {:?}\n",
        hot.display().to_string(),
        printers
    );
    Config::parse(&text, &root.join("crispen.toml")).unwrap()
}

/// Opens the farm on its spool, with the owners of its state for the test to hand out.
pub(crate) fn open_farm(config: Config) -> (Arc<Farm>, super::farm::Owners) {
    let store = super::store::spool::SpoolStore::open(&config.spool_dir).unwrap();
    let (farm, owners, task) = Farm::new(config, store);
    tokio::spawn(task);
    (farm, owners)
}

/// A job made ready with `gcode` for every printer of the config's machine, as
/// preparation would leave it.
pub(crate) async fn ready_job(farm: &Farm, name: &str, gcode: &str) -> String {
    let config = farm.config();
    let folder = &config.folders[0].path;
    let file = folder.join(name);
    std::fs::write(&file, b"solid x\nendsolid x\n").unwrap();
    let job = farm.jobs().admit(&file, folder, &[]).await.unwrap();
    let machine = config.printers[0].machine.name.clone();
    let gcode_name = format!("{name}.{machine}.gcode");
    let dir = farm.store().job_dir(&job.id);
    std::fs::write(dir.join(&gcode_name), gcode).unwrap();
    farm.jobs()
        .transition(&job.id, JobState::Preparing, None)
        .await
        .unwrap();
    farm.jobs()
        .transition_with(
            &job.id,
            JobState::Ready,
            None,
            JobChange::Edit(Box::new(move |j| {
                j.machines.insert(machine, ForMachine::Gcode(gcode_name));
            })),
        )
        .await
        .unwrap();
    job.id
}

/// Waits until `test` holds, looking again at each change of the farm (a job, a
/// printer's live status, a gate...), for at most `limit` of simulated time (the paused
/// clock runs ahead while every task waits).
pub(crate) async fn until(
    farm: &Farm,
    limit: Duration,
    what: &str,
    mut test: impl FnMut() -> bool,
) {
    let deadline = tokio::time::Instant::now() + limit;
    let mut changes = farm.watch();
    while !test() {
        if tokio::time::timeout_at(deadline, changes.changed())
            .await
            .is_err()
        {
            panic!("not within {limit:?}: {what}");
        }
    }
}
