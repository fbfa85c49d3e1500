//! Preparing a job: read its sidecar, work out the folder's settings with the sidecar's
//! overrides and the machines that may print it (the distinct machines of the printers
//! serving its folder), then enhance the model once and slice it once per machine into
//! `<job dir>/<file>.<machine>.gcode` ([`steps`]), keeping the enhanced mesh that was
//! sliced as `<job dir>/<file>.enhanced.stl`. A dropped `.gcode` file is not sliced: it is
//! checked against each machine ([`crate::slice::presliced`]) and printed as it is. Every
//! G-code, dropped or sliced, passes the host's load checks and the G-code policy
//! ([`crate::slice::policy`]) here, before a printer may claim it; the verdict is in the
//! job's report.
//! [`queue`] is the daemon's loop that takes queued jobs through this.
//!
//! An enhanced job is ready as soon as its own G-code is checked. Whether the enhancement
//! reaches the nozzle (its outer walls against the unmodified model's, sliced the same
//! way: [`crate::slice::walls`]) is measured afterwards by a task of its own
//! ([`PrepareTask::compare`]), which the queue runs only while no job is being prepared or
//! waits to be, in a child process at the lowest CPU priority: the measurement used to
//! nearly double every job's preparation.
//!
//! The work runs in a child process (`crispen prepare-job`, [`run_child`]) rather than on a
//! thread: loading, cleaning and enhancing a model are long computations with nowhere to
//! stop, so a hostile or merely huge file could otherwise hold a preparation slot for as
//! long as it likes. A child can be killed at once, whatever it is doing, when the job is
//! cancelled, the daemon stops, or the configured time limit passes, and its memory goes
//! back to the system when it ends. The child speaks [`ChildMessage`] JSON lines on stdout.

pub mod queue;
pub mod steps;

use super::config::{parse_strength, FolderConfig};
#[cfg(test)]
use super::job::parse_sidecar;
use super::job::{ForMachine, Sidecar};
use crate::enhance::Strength;
use crate::machine::Machine;
use crate::mesh::place::UpAxis;
use crate::slice::walls::WallComparison;
use crate::slice::{SliceReport, SlicerKind};
use serde::{Deserialize, Serialize};
use std::collections::VecDeque;
use std::path::{Path, PathBuf};
use std::time::Duration;
use tokio::io::{AsyncBufReadExt, AsyncWriteExt};
use tokio_util::sync::CancellationToken;

/// Everything one preparation needs, resolved from the folder config and the sidecar.
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct PrepareTask {
    pub job: String,
    pub model: PathBuf,
    /// The machines that may print the job, each with its G-code file.
    pub machines: Vec<TaskMachine>,
    /// Where the enhanced, placed mesh that was sliced is kept.
    pub enhanced_mesh: PathBuf,
    pub height_mm: f64,
    pub strength: Strength,
    pub slicer: SlicerKind,
    pub up: UpAxis,
    pub profile: Option<PathBuf>,
    pub settings: crate::slice::SliceSettings,
    /// The whole preparation (load, enhance, slice) is stopped after this long.
    pub timeout: Duration,
    /// Not a preparation but the measurement of one already made: the job's G-code for
    /// its first machine (`machines[0].output`) against the unmodified model's, answered
    /// with [`ChildMessage::Compared`].
    #[serde(default)]
    pub compare: bool,
}

/// One machine of a task and where its G-code goes.
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct TaskMachine {
    pub machine: Machine,
    pub output: PathBuf,
}

/// What a preparation made: per machine, its G-code's report or why it cannot print it.
#[derive(Debug, Clone, Default, Serialize, Deserialize)]
pub struct Prepared {
    pub machines: Vec<(String, Result<SliceReport, String>)>,
}

impl Prepared {
    /// The job's record of it: per machine, the G-code file (in the job's directory) or
    /// the reason; and the first report, for the job's summary.
    pub fn for_machines(
        &self,
    ) -> (
        std::collections::BTreeMap<String, ForMachine>,
        Option<SliceReport>,
    ) {
        let mut first = None;
        let record = self
            .machines
            .iter()
            .map(|(name, result)| {
                let entry = match result {
                    Ok(report) => {
                        first.get_or_insert_with(|| report.clone());
                        let file = report.output.file_name().unwrap_or_default();
                        ForMachine::Gcode(file.to_string_lossy().into_owned())
                    }
                    Err(reason) => ForMachine::Refused(reason.clone()),
                };
                (name.clone(), entry)
            })
            .collect();
        (record, first)
    }

    /// The job's failure when no machine can print it: every machine's reason.
    pub fn failure(&self) -> Option<String> {
        if self.machines.iter().any(|(_, r)| r.is_ok()) {
            return None;
        }
        let reasons: Vec<String> = self
            .machines
            .iter()
            .map(|(name, r)| format!("{name}: {}", r.as_ref().err().map_or("", |e| e)))
            .collect();
        Some(match reasons.len() {
            0 => "no machine may print it".into(),
            1 => reasons[0].clone(),
            _ => format!("no machine can print it; {}", reasons.join("; ")),
        })
    }
}

/// What the preparation child writes on stdout, one JSON object per line.
#[derive(Debug, Clone, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum ChildMessage {
    /// The step it is on (shown by `crispen status`).
    Step(String),
    Done(Box<Prepared>),
    /// The wall comparison a [`PrepareTask::compare`] task made.
    Compared(Box<WallComparison>),
    /// The job (or its comparison) failed; the reason is for the operator.
    Failed(String),
}

/// Why a preparation did not produce G-code.
#[derive(Debug, thiserror::Error)]
pub enum PrepareError {
    /// The model, its settings or the slicer failed; the message says which and why.
    #[error("{0}")]
    Failed(String),
    #[error("preparation took longer than {after:?} and was stopped (hint: raise the folder's `timeout_s`, or print a smaller model)")]
    TimedOut { after: Duration },
    #[error("preparation was stopped (the job was cancelled or the daemon is stopping)")]
    Cancelled,
    #[error("cannot start the preparation process {program}: {source}")]
    Spawn {
        program: PathBuf,
        #[source]
        source: std::io::Error,
    },
    #[error("the preparation process ended without an answer ({status}); its last output:\n{stderr_tail}")]
    Crashed { status: String, stderr_tail: String },
}

/// Stderr lines of the child kept for an error message.
const STDERR_TAIL_LINES: usize = 20;

/// Runs one preparation in a child process: `program prepare-job`, the task as JSON on its
/// stdin. `on_step` hears each step. The child is killed (and with it any slicer it runs,
/// which dies with its parent) when `cancel` fires or `task.timeout` passes.
pub async fn run_child(
    program: &Path,
    task: &PrepareTask,
    cancel: &CancellationToken,
    on_step: impl FnMut(String),
) -> Result<Prepared, PrepareError> {
    match child_answer(program, task, cancel, on_step).await? {
        ChildMessage::Done(prepared) => Ok(*prepared),
        other => Err(unexpected(other)),
    }
}

/// Runs a [`PrepareTask::compare`] task in a child process, as [`run_child`] runs a
/// preparation.
pub async fn run_compare_child(
    program: &Path,
    task: &PrepareTask,
    cancel: &CancellationToken,
) -> Result<WallComparison, PrepareError> {
    match child_answer(program, task, cancel, |_| {}).await? {
        ChildMessage::Compared(comparison) => Ok(*comparison),
        other => Err(unexpected(other)),
    }
}

/// A child that answered another task's message: a crispen of another version.
fn unexpected(message: ChildMessage) -> PrepareError {
    PrepareError::Failed(format!(
        "the preparation process answered the wrong kind of task: {message:?}"
    ))
}

/// The child's last message, [`ChildMessage::Done`] or [`ChildMessage::Compared`].
async fn child_answer(
    program: &Path,
    task: &PrepareTask,
    cancel: &CancellationToken,
    mut on_step: impl FnMut(String),
) -> Result<ChildMessage, PrepareError> {
    let mut cmd = tokio::process::Command::new(program);
    cmd.arg("prepare-job")
        .stdin(std::process::Stdio::piped())
        .stdout(std::process::Stdio::piped())
        .stderr(std::process::Stdio::piped())
        .kill_on_drop(true);
    // The child (and the slicer it runs, in turn) dies with the daemon.
    crate::slice::process::die_with_this_process(cmd.as_std_mut());
    let mut child = cmd.spawn().map_err(|source| PrepareError::Spawn {
        program: program.to_path_buf(),
        source,
    })?;
    let input = serde_json::to_vec(task).expect("a task serialises");
    let mut stdin = child.stdin.take().expect("stdin is piped");
    let mut stdout =
        tokio::io::BufReader::new(child.stdout.take().expect("stdout is piped")).lines();
    let mut stderr =
        tokio::io::BufReader::new(child.stderr.take().expect("stderr is piped")).lines();
    let feed = async move {
        let _ = stdin.write_all(&input).await;
        // stdin dropped here: the child sees the end of the task.
    };
    let deadline = tokio::time::sleep(task.timeout);
    tokio::pin!(feed, deadline);
    let mut fed = false;
    let mut answer = None;
    let mut stdout_open = true;
    let mut stderr_open = true;
    let mut tail = VecDeque::with_capacity(STDERR_TAIL_LINES);
    while stdout_open || stderr_open {
        tokio::select! {
            _ = &mut feed, if !fed => fed = true,
            line = stdout.next_line(), if stdout_open => match line {
                Ok(Some(line)) => match serde_json::from_str::<ChildMessage>(&line) {
                    Ok(ChildMessage::Step(step)) => on_step(step),
                    Ok(end) => answer = Some(end),
                    Err(_) => push_tail(&mut tail, line),
                },
                _ => stdout_open = false,
            },
            line = stderr.next_line(), if stderr_open => match line {
                Ok(Some(line)) => {
                    tracing::debug!(child = %line, "preparation output");
                    push_tail(&mut tail, line);
                }
                _ => stderr_open = false,
            },
            _ = cancel.cancelled() => {
                let _ = child.start_kill();
                let _ = child.wait().await;
                return Err(PrepareError::Cancelled);
            }
            _ = &mut deadline => {
                let _ = child.start_kill();
                let _ = child.wait().await;
                return Err(PrepareError::TimedOut { after: task.timeout });
            }
        }
    }
    let status = tokio::select! {
        status = child.wait() => status,
        _ = cancel.cancelled() => {
            let _ = child.start_kill();
            return Err(PrepareError::Cancelled);
        }
    };
    match answer {
        Some(ChildMessage::Failed(reason)) => Err(PrepareError::Failed(reason)),
        Some(end) => Ok(end),
        None => Err(PrepareError::Crashed {
            status: status.map_or_else(|e| e.to_string(), |s| s.to_string()),
            stderr_tail: Vec::from(tail).join("\n"),
        }),
    }
}

fn push_tail(tail: &mut VecDeque<String>, line: String) {
    if tail.len() == STDERR_TAIL_LINES {
        tail.pop_front();
    }
    tail.push_back(line.chars().take(400).collect());
}

/// Combines a folder's settings with a sidecar's overrides into a task, for the distinct
/// machines of the printers that may take the job (`printers`: every printer of the farm
/// by name, with its machine; see `Farm::printer_machines`).
pub fn resolve_task(
    job: &str,
    job_dir: &Path,
    file: &str,
    folder: &FolderConfig,
    printers: &[(String, Machine)],
    sidecar: Option<&Sidecar>,
) -> Result<PrepareTask, String> {
    let mut strength = folder.strength;
    let mut height_mm = folder.height_mm;
    let mut up = folder.up;
    if let Some(s) = sidecar {
        if let Some(h) = s.height_mm {
            height_mm = h;
        }
        if let Some(axis) = s.up {
            up = axis;
        }
        if let Some(v) = &s.strength {
            strength = parse_strength(v)?;
        }
        if s.enhance == Some(false) {
            strength = Strength::Off;
        } else if s.enhance == Some(true) && strength == Strength::Off {
            strength = Strength::Auto;
        }
        if let Some(p) = &s.printer {
            if !folder.printers.contains(p) {
                return Err(format!(
                    "sidecar {file}.toml: key `printer`: {p:?} does not serve folder {} (it is served by {})",
                    folder.path.display(),
                    folder.printers.join(", ")
                ));
            }
        }
    }
    let wanted = sidecar.and_then(|s| s.printer.as_deref());
    let mut machines: Vec<TaskMachine> = Vec::new();
    for (name, machine) in printers {
        let serves = folder.printers.contains(name) && wanted.is_none_or(|w| w == name);
        if serves && !machines.iter().any(|m| m.machine.name == machine.name) {
            let output = if is_presliced(file) {
                job_dir.join(file)
            } else {
                job_dir.join(format!("{file}.{}.gcode", machine.name))
            };
            machines.push(TaskMachine {
                machine: machine.clone(),
                output,
            });
        }
    }
    Ok(PrepareTask {
        job: job.to_string(),
        model: job_dir.join(file),
        machines,
        enhanced_mesh: job_dir.join(format!("{file}.enhanced.stl")),
        height_mm,
        strength,
        slicer: folder.slicer,
        up,
        profile: folder.profile.clone(),
        settings: folder.settings.clone(),
        timeout: folder.timeout,
        compare: false,
    })
}

/// Whether a dropped file is G-code sliced elsewhere (printed as it is, never sliced).
pub fn is_presliced(file: &str) -> bool {
    crate::daemon::hotfolder::file_kind(file) == Some(crate::daemon::hotfolder::FileKind::Gcode)
}

/// What the child answers for `task`: [`ChildMessage::Done`] for a preparation,
/// [`ChildMessage::Compared`] for a comparison, or [`ChildMessage::Failed`]. `progress`
/// hears each step's name. Blocking.
pub fn answer(task: &PrepareTask, progress: &mut dyn FnMut(String)) -> ChildMessage {
    let answer = if task.compare {
        compare_task(task).map(|c| ChildMessage::Compared(Box::new(c)))
    } else {
        run_task(task, progress).map(|p| ChildMessage::Done(Box::new(p)))
    };
    answer.unwrap_or_else(ChildMessage::Failed)
}

/// The [`steps`]' request for a task's model.
fn slice_request(task: &PrepareTask) -> steps::SliceRequest {
    let mut req = steps::SliceRequest::new(&task.model, task.height_mm);
    req.slicer = task.slicer;
    req.strength = task.strength;
    req.up = task.up;
    req.settings = task.settings.clone();
    req.profile = task.profile.clone();
    req.timeout = task.timeout;
    // Pictures and thumbnails go next to the G-code, in the job's directory.
    req.pictures = task.model.parent().map(Path::to_path_buf);
    req
}

/// The preparation itself, as the child runs it: the [`steps`] for a model, the
/// pre-sliced check for G-code. `progress` hears each step's name. Blocking.
pub fn run_task(task: &PrepareTask, progress: &mut dyn FnMut(String)) -> Result<Prepared, String> {
    let file = task.model.file_name().unwrap_or_default().to_string_lossy();
    if is_presliced(&file) {
        progress("checking the pre-sliced G-code".into());
        return check_presliced(task);
    }
    // No comparison here: the job is ready without it (see the module's comment).
    let req = slice_request(task);
    let targets: Vec<steps::Target> = task
        .machines
        .iter()
        .enumerate()
        .map(|(i, m)| steps::Target {
            machine: m.machine.clone(),
            output: m.output.clone(),
            // The placed mesh is the same for every machine: kept once.
            keep_mesh: (i == 0).then(|| task.enhanced_mesh.clone()),
        })
        .collect();
    let results = steps::prepare(&req, &targets, &mut |step| progress(step.describe()))
        .map_err(|e| e.to_string())?;
    Ok(Prepared {
        machines: results
            .into_iter()
            .map(|(name, r)| (name, r.map_err(|e| e.to_string())))
            .collect(),
    })
}

/// Nice value of a comparison's process (and of the slicer it runs, which inherits it):
/// the lowest priority, so that it takes only what CPU the farm leaves over.
const COMPARE_NICE: i32 = 19;

/// A comparison, as the child runs it: at the lowest CPU priority, the job's G-code for
/// its first machine against the unmodified model's. Blocking.
fn compare_task(task: &PrepareTask) -> Result<WallComparison, String> {
    // SAFETY: setpriority only changes this process's scheduling; it touches no memory.
    let niced = unsafe { nix::libc::setpriority(nix::libc::PRIO_PROCESS, 0, COMPARE_NICE) };
    if niced != 0 {
        // Still worth measuring; it only competes harder for the CPU.
        tracing::warn!(error = %std::io::Error::last_os_error(), "cannot lower the comparison's priority");
    }
    let target = task
        .machines
        .first()
        .ok_or("no machine's G-code to compare")?;
    let req = slice_request(task);
    steps::compare_prepared(
        &req,
        &target.machine,
        &target.output,
        req.pictures.as_deref(),
    )
    .map_err(|e| e.to_string())
}

/// A pre-sliced file: read what it was made for, then accept or refuse it per machine.
fn check_presliced(task: &PrepareTask) -> Result<Prepared, String> {
    use crate::slice::{policy, presliced};
    let model = &task.model;
    // The reason is the job's, shown to clients: the file by the job's own name, never by
    // its path in the spool.
    let name = model.file_name().unwrap_or_default().to_string_lossy();
    let file = std::fs::File::open(model).map_err(|e| format!("{name}: cannot read: {e}"))?;
    // Refused here, before a printer claims it, rather than when the printer loads it.
    let size = file
        .metadata()
        .map_err(|e| format!("{name}: cannot read: {e}"))?
        .len();
    let limit = crate::marlin::gcode::MAX_GCODE_BYTES;
    if size > limit {
        return Err(format!(
            "{name}: {} MiB of G-code, more than the {} MiB crispen streams; split the job",
            size >> 20,
            limit >> 20
        ));
    }
    let target = presliced::read_target(std::io::BufReader::new(file))
        .map_err(|e| format!("{name}: {e}"))?;
    tracing::info!(
        slicer = ?target.slicer,
        filament_mm = ?target.filament_mm,
        nozzle_mm = ?target.nozzle_mm,
        printer_model = ?target.printer_model,
        "pre-sliced G-code"
    );
    // The host's load checks depend on the firmware only: run once per firmware.
    let mut loads: Vec<(crate::marlin::firmware::Firmware, Result<(), String>)> = Vec::new();
    let mut machines = Vec::new();
    for m in &task.machines {
        let firmware = m.machine.firmware;
        let load = match loads.iter().find(|(f, _)| *f == firmware) {
            Some((_, r)) => r.clone(),
            None => {
                let r = policy::load_check(model, firmware).map_err(|e| e.to_string());
                loads.push((firmware, r.clone()));
                r
            }
        };
        // The policy first: its refusals name the line.
        let verdict = load
            .and_then(|()| {
                let verdict = policy::check_path(model, &m.machine).map_err(|e| e.to_string())?;
                if verdict.passed() {
                    Ok(verdict)
                } else {
                    Err(verdict.summary())
                }
            })
            .and_then(|verdict| presliced::check_for(&target, &m.machine).map(|()| verdict))
            .map(|verdict| SliceReport {
                model: model.clone(),
                output: m.output.clone(),
                machine: m.machine.name.clone(),
                enhancement: crate::slice::EnhancementSummary {
                    lambda2: None,
                    mode: "pre-sliced".into(),
                    report: None,
                    printed: None,
                    print_aware: None,
                },
                slicer_version: target.slicer.clone(),
                model_size_mm: target
                    .extent_mm
                    .map_or([0.0; 3], |e| e.map(|[lo, hi]| hi - lo)),
                top_layer_z_mm: target.extent_mm.map_or(0.0, |e| e[2][1]),
                filament_mm: Some(target.extruded_mm),
                // The file names no material: grams as for PLA (the default preset),
                // on this machine's filament.
                filament_g: Some({
                    let r_cm = m.machine.filament_mm / 20.0;
                    let pla = crate::slice::MATERIALS[0];
                    target.extruded_mm / 10.0
                        * std::f64::consts::PI
                        * r_cm
                        * r_cm
                        * pla.density_g_cm3
                }),
                gcode_lines: target.lines,
                policy: Some(verdict),
                ..SliceReport::default()
            })
            .map_err(|reason| {
                format!(
                    "{} is not for the {}: {reason}",
                    model.file_name().unwrap_or_default().to_string_lossy(),
                    m.machine.name
                )
            });
        if let Ok(report) = &verdict {
            if let Some(v) = &report.policy {
                tracing::info!(job = %task.job, machine = %m.machine.name, verdict = %v.summary(), "G-code policy");
            }
        }
        machines.push((m.machine.name.clone(), verdict));
    }
    Ok(Prepared { machines })
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Pre-sliced is what the hot folder's one classifier calls G-code.
    #[test]
    fn gcode_files_are_presliced() {
        for name in ["a.gcode", "a.bgcode", "a.g", "A.GCO"] {
            assert!(is_presliced(name), "{name}");
        }
        for name in ["a.stl", "a.obj", "a.3mf", "a.gcode.txt"] {
            assert!(!is_presliced(name), "{name}");
        }
    }

    fn folder() -> FolderConfig {
        FolderConfig {
            path: "/hot".into(),
            height_mm: 50.0,
            printers: vec!["a".into(), "b".into(), "c".into()],
            strength: Strength::Auto,
            slicer: SlicerKind::Prusa,
            up: UpAxis::Z,
            profile: None,
            timeout: Duration::from_secs(60),
            settings: Default::default(),
        }
    }

    /// Printers a and c are Ultimaker 2s, b a 1.75 mm Marlin machine; d serves no folder.
    fn printers() -> Vec<(String, Machine)> {
        let text = "[spool]\ndir = \"s\"\n\
            [[printer]]\nname = \"a\"\nport = \"/dev/a\"\nmachine = \"ultimaker2\"\n\
            [[printer]]\nname = \"b\"\nport = \"/dev/b\"\nfirmware = \"marlin2\"\n\
            [[printer]]\nname = \"c\"\nport = \"/dev/c\"\nfirmware = \"ultimaker2\"\n\
            [[printer]]\nname = \"d\"\nport = \"/dev/d\"\nmachine = \"ultimaker2plus\"\n";
        super::super::config::Config::parse(text, Path::new("/c.toml"))
            .unwrap()
            .printers
            .into_iter()
            .map(|p| (p.name, p.machine))
            .collect()
    }

    #[test]
    fn a_job_is_prepared_once_per_machine_of_its_printers() {
        let t = resolve_task(
            "j",
            Path::new("/s/j"),
            "m.stl",
            &folder(),
            &printers(),
            None,
        )
        .unwrap();
        let names: Vec<&str> = t.machines.iter().map(|m| m.machine.name.as_str()).collect();
        assert_eq!(
            names,
            ["ultimaker2", crate::machine::DEFAULT_MARLIN_MACHINE]
        );
        assert_eq!(
            t.machines[0].output,
            PathBuf::from("/s/j/m.stl.ultimaker2.gcode")
        );

        let s = parse_sidecar(&b"printer = \"b\"\n"[..], Path::new("m.stl.toml")).unwrap();
        let t = resolve_task(
            "j",
            Path::new("/s/j"),
            "m.stl",
            &folder(),
            &printers(),
            Some(&s),
        )
        .unwrap();
        assert_eq!(t.machines.len(), 1);
        assert_eq!(t.machines[0].machine.filament_mm, 1.75);

        // Pre-sliced G-code is printed from the dropped file itself.
        let t = resolve_task(
            "j",
            Path::new("/s/j"),
            "p.gcode",
            &folder(),
            &printers(),
            None,
        )
        .unwrap();
        assert!(t
            .machines
            .iter()
            .all(|m| m.output == Path::new("/s/j/p.gcode")));
    }

    #[test]
    fn no_machine_able_means_failed_with_every_reason() {
        let prepared = Prepared {
            machines: vec![
                ("ultimaker2".into(), Err("too big".into())),
                ("marlin-175".into(), Err("also too big".into())),
            ],
        };
        let reason = prepared.failure().unwrap();
        assert!(
            reason.contains("ultimaker2: too big") && reason.contains("marlin-175: also too big"),
            "{reason}"
        );
        let prepared = Prepared {
            machines: vec![
                ("ultimaker2".into(), Err("too big".into())),
                (
                    "marlin-175".into(),
                    Ok(SliceReport {
                        output: "/s/j/m.stl.marlin-175.gcode".into(),
                        ..Default::default()
                    }),
                ),
            ],
        };
        assert_eq!(prepared.failure(), None);
        let (record, first) = prepared.for_machines();
        assert_eq!(
            record["marlin-175"],
            ForMachine::Gcode("m.stl.marlin-175.gcode".into())
        );
        assert_eq!(record["ultimaker2"], ForMachine::Refused("too big".into()));
        assert!(first.is_some());
    }

    #[test]
    fn sidecar_overrides_and_rejects_unknown_keys() {
        let s = parse_sidecar(
            &b"enhance = false\nheight_mm = 20\nup = \"y\"\n"[..],
            Path::new("m.stl.toml"),
        )
        .unwrap();
        let t = resolve_task(
            "j",
            Path::new("/s/j"),
            "m.stl",
            &folder(),
            &printers(),
            Some(&s),
        )
        .unwrap();
        assert_eq!(t.strength, Strength::Off);
        assert_eq!(t.height_mm, 20.0);
        assert_eq!(t.up, UpAxis::Y);

        let err = parse_sidecar(&b"enhanse = false\n"[..], Path::new("m.stl.toml")).unwrap_err();
        assert!(
            err.contains("m.stl.toml") && err.contains("enhanse"),
            "{err}"
        );
        let err = parse_sidecar(&b"height_mm = -1\n"[..], Path::new("m.stl.toml")).unwrap_err();
        assert!(err.contains("height_mm"), "{err}");

        let s = parse_sidecar(&b"printer = \"zz\"\n"[..], Path::new("m.stl.toml")).unwrap();
        let err = resolve_task(
            "j",
            Path::new("/s/j"),
            "m.stl",
            &folder(),
            &printers(),
            Some(&s),
        )
        .unwrap_err();
        assert!(err.contains("\"zz\""), "{err}");
    }
}
