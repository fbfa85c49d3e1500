//! The child's side of a preparation: what `crispen prepare-job` does with the task it
//! is handed, the [`steps`] for a model or the pre-sliced check for G-code, and the
//! measurement of a comparison task.

use super::steps;
use super::task::{is_presliced, ChildMessage, PrepareTask, Prepared};
use crate::daemon::filament::Need;
use crate::machine::Machine;
use crate::marlin::firmware::Firmware;
use crate::marlin::gcode;
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
    req.per_plate = task.per_plate;
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
    let material = task.asks.material.as_deref();
    Ok(Prepared {
        machines: results
            .into_iter()
            .map(|(name, r)| {
                let r = r.map_err(|e| e.to_string()).and_then(|mut report| {
                    let m = task
                        .machines
                        .iter()
                        .find(|m| m.machine.name == name)
                        .ok_or("a G-code for a machine not asked for")?;
                    let mm = pushed_mm(&report.output, m.machine.firmware)?;
                    // A job that asks no material is weighed as what it was sliced for.
                    let material = material.unwrap_or(&report.material).to_owned();
                    weigh(&mut report, mm, &m.machine, Some(&material));
                    Ok(report)
                });
                (name, r)
            })
            .collect(),
        file_material: None,
    })
}

/// The net filament a G-code file pushes, mm, as a print of it is booked
/// ([`gcode::pushed_mm`]): a job's need and what its print took are one figure. The error
/// is the host's refusal to load it.
fn pushed_mm(gcode: &Path, firmware: Firmware) -> Result<f64, String> {
    let (mm, commands) = gcode::pushed_mm(gcode, firmware, None).map_err(|e| e.to_string())?;
    if commands == 0 {
        let file = gcode.display().to_string();
        return Err(gcode::GcodeError::Empty { file }.to_string());
    }
    Ok(mm)
}

/// Sets what one print needs on `machine` in its report: `mm`, weighed at the density of
/// `material`, the material the job asks, where crispen knows it.
fn weigh(report: &mut SliceReport, mm: f64, machine: &Machine, material: Option<&str>) {
    let need = Need::of(mm, material, machine.filament_mm);
    report.filament_mm = Some(need.mm);
    report.filament_g = need.g;
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
    // What the job asks: the file's own material where its folder and sidecar name none.
    let asks = task
        .asks
        .clone()
        .with_file_material(target.material.as_deref())
        .map_err(|e| format!("{name}: {e}"))?;
    // The host's load, and what it pushes, depend on the firmware only: once per firmware.
    let mut loads: Vec<(Firmware, Result<f64, String>)> = Vec::new();
    let mut machines = Vec::new();
    for m in &task.machines {
        let firmware = m.machine.firmware;
        let load = match loads.iter().find(|(f, _)| *f == firmware) {
            Some((_, r)) => r.clone(),
            None => {
                let r = pushed_mm(model, firmware);
                loads.push((firmware, r.clone()));
                r
            }
        };
        // The policy first: its refusals name the line.
        let verdict = load
            .and_then(|mm| {
                let verdict = policy::check_path(model, &m.machine).map_err(|e| e.to_string())?;
                if verdict.passed() {
                    Ok((mm, verdict))
                } else {
                    Err(verdict.summary())
                }
            })
            .and_then(|(mm, verdict)| {
                presliced::check_for(&target, &m.machine).map(|()| (mm, verdict))
            })
            .map(|(mm, verdict)| {
                let mut report = SliceReport {
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
                    gcode_lines: target.lines,
                    policy: Some(verdict),
                    parts: crate::slice::plate_parts(model, m.machine.firmware),
                    ..SliceReport::default()
                };
                weigh(&mut report, mm, &m.machine, asks.material.as_deref());
                report
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
    Ok(Prepared {
        machines,
        // Only as checked, and only where it is what the job asks.
        file_material: asks.material.filter(|_| asks.material_of_file),
    })
}
