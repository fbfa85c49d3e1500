//! The child's side of a preparation: what `crispen prepare-job` does with the task it
//! is handed, the [`steps`] for a model or the pre-sliced check for G-code, and the
//! measurement of a comparison task.

use super::steps;
use super::task::{is_presliced, ChildMessage, PrepareTask, Prepared};
use crate::slice::walls::WallComparison;
use crate::slice::SliceReport;
use std::path::Path;

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
    req.mode = task.mode;
    req.up = task.up;
    req.settings = task.settings.clone();
    req.profile = task.profile.clone();
    req.timeout = task.timeout;
    req.observe = task.observe.clone();
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
    // No comparison here: the job is ready without it (see `daemon::prepare`'s comment).
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
    // The walls of a few layers, and the preview of both prints, into the job's directory.
    let drawn = steps::Drawn {
        pictures: req.pictures.clone(),
        preview: req.pictures.clone(),
    };
    steps::compare_prepared(&req, &target.machine, &target.output, &drawn)
        .map_err(|e| e.to_string())
}

/// The preview of a job printed unmodified or pre-sliced: its G-code for its first
/// machine (beside the model, if it has one), into the job's directory (failures are
/// logged there). Blocking.
pub(crate) fn preview_task(task: &PrepareTask) -> Result<(), String> {
    let target = task.machines.first().ok_or("no machine's G-code to draw")?;
    let req = slice_request(task);
    let dir = req.pictures.as_deref().ok_or("no job directory")?;
    steps::preview_prepared(&req, &target.machine, &target.output, dir);
    Ok(())
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
                    mode: crate::slice::moved::PRESLICED.into(),
                    report: None,
                    printed: None,
                    print_aware: None,
                    observed: None,
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
