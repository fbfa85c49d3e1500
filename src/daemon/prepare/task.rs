//! What one preparation is: the [`PrepareTask`] the daemon resolves from the folder's
//! settings and the job's sidecar and hands to the child, and what the child answers
//! ([`ChildMessage`], with what it [`Prepared`]).

use crate::daemon::config::{parse_strength, FolderConfig};
#[cfg(test)]
use crate::daemon::job::parse_sidecar;
use crate::daemon::job::{ForMachine, Sidecar};
use crate::enhance::Strength;
use crate::machine::Machine;
use crate::mesh::place::UpAxis;
use crate::slice::walls::WallComparison;
use crate::slice::{SliceReport, SlicerKind};
use serde::{Deserialize, Serialize};
use std::path::{Path, PathBuf};
use std::time::Duration;

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
    pub(crate) fn for_machines(
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
        crate::daemon::config::Config::parse(text, Path::new("/c.toml"))
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
