//! What one preparation is: the [`PrepareTask`] the daemon resolves from the folder's
//! settings and the job's sidecar and hands to the child, and what the child answers
//! ([`ChildMessage`], with what it [`Prepared`]).

use crate::daemon::config::{parse_strength, FolderConfig};
use crate::daemon::filament::Asks;
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
    /// The enhancement's mode, the folder's.
    #[serde(default)]
    pub mode: crate::enhance::Mode,
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
    /// What the job asks of its printer (the folder's, with the sidecar's over them).
    #[serde(default)]
    pub asks: crate::daemon::filament::Asks,
    /// Copies of the model side by side on one bed (the folder's, or the sidecar's).
    #[serde(default = "one")]
    pub per_plate: u32,
    /// The observer's reference size and time bound (`[enhancement]`), for
    /// `strength = "observed"`.
    #[serde(default)]
    pub observe: crate::observation::ObserveSettings,
}

fn one() -> u32 {
    1
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
    /// The material a pre-sliced file says it was sliced for (see
    /// `crate::slice::presliced`), as written: what the job asks unless its folder or
    /// sidecar names one ([`Asks::with_file_material`]).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub file_material: Option<String>,
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

    /// What one print needs on each machine with G-code: its report's net filament,
    /// weighed as the report weighed it.
    pub(crate) fn needs(
        &self,
    ) -> std::collections::BTreeMap<String, crate::daemon::filament::Need> {
        self.machines
            .iter()
            .filter_map(|(name, r)| {
                let r = r.as_ref().ok()?;
                let need = crate::daemon::filament::Need {
                    mm: r.filament_mm?,
                    g: r.filament_g,
                };
                Some((name.clone(), need))
            })
            .collect()
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
        let named = s.printer.iter().map(|p| ("printer", p));
        let listed = s.printers.iter().flatten().map(|p| ("printers", p));
        if let Some((key, p)) = named
            .chain(listed)
            .find(|(_, p)| !folder.printers.contains(p))
        {
            return Err(format!(
                "sidecar {file}.toml: key `{key}`: {p:?} does not serve folder {} (it is served by {})",
                folder.path.display(),
                folder.printers.join(", ")
            ));
        }
    }
    let (asks, settings) = asks_of(folder, sidecar, file)?;
    // Sliced for the machines of the printers it may go to: the one named, or those of
    // its copies.
    let wanted: Option<Vec<&str>> = sidecar.and_then(|s| match (&s.printers, &s.printer) {
        (Some(list), _) => Some(list.iter().map(String::as_str).collect()),
        (None, Some(one)) => Some(vec![one.as_str()]),
        (None, None) => None,
    });
    let mut machines: Vec<TaskMachine> = Vec::new();
    for (name, machine) in printers {
        let serves = folder.printers.contains(name)
            && wanted.as_ref().is_none_or(|w| w.contains(&name.as_str()))
            && asks
                .nozzle_mm
                .is_none_or(|n| (n - machine.nozzle_mm).abs() < 1e-6);
        if serves && !machines.iter().any(|m| m.machine.name == machine.name) {
            let machine = &for_material(machine, settings.material.as_deref());
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
    if let (true, Some(n)) = (machines.is_empty(), asks.nozzle_mm) {
        return Err(format!(
            "no printer of folder {} has a {n} mm nozzle (its printers: {})",
            folder.path.display(),
            folder.printers.join(", ")
        ));
    }
    Ok(PrepareTask {
        job: job.to_string(),
        model: job_dir.join(file),
        machines,
        enhanced_mesh: job_dir.join(format!("{file}.enhanced.stl")),
        height_mm,
        strength,
        mode: folder.mode,
        slicer: folder.slicer,
        up,
        profile: folder.profile.clone(),
        settings,
        timeout: folder.timeout,
        compare: false,
        asks,
        per_plate: sidecar
            .and_then(|s| s.per_plate)
            .unwrap_or(folder.per_plate),
        observe: Default::default(),
    })
}

/// What a job asks of its printer, its folder's with its sidecar's over them, and the
/// slicer settings for the material it asks.
fn asks_of(
    folder: &FolderConfig,
    sidecar: Option<&Sidecar>,
    file: &str,
) -> Result<(Asks, crate::slice::SliceSettings), String> {
    let mut asks = folder.asks.clone();
    let mut settings = folder.settings.clone();
    let Some(s) = sidecar else {
        return Ok((asks, settings));
    };
    if let Some(m) = &s.material {
        let preset = m.trim().to_ascii_lowercase();
        if crate::slice::MATERIALS.iter().any(|p| p.name == preset) {
            settings.material = Some(preset);
        } else if !is_presliced(file) {
            return Err(format!(
                "sidecar {file}.toml: key `material`: crispen slices for {} (a material of your own is set per folder, with its temperatures in [folder.settings])",
                crate::slice::MATERIALS
                    .iter()
                    .map(|p| p.name.to_ascii_uppercase())
                    .collect::<Vec<_>>()
                    .join(", ")
            ));
        }
        asks.material = Some(m.trim().to_ascii_uppercase());
    }
    if let Some(c) = &s.colour {
        asks.colour = Some(c.trim().to_ascii_lowercase());
    }
    if let Some(n) = s.nozzle_mm {
        asks.nozzle_mm = Some(n);
    }
    if let Some(t) = &s.tags {
        asks.tags = t.clone();
    }
    if let Some(p) = s.priority {
        asks.priority = p;
    }
    Ok((asks, settings))
}

/// `machine` with the G-code policy's temperature limits narrowed to what `material` (a
/// preset's name) prints at: a file that heats PLA to 250 °C is refused like one that
/// heats beyond the machine.
fn for_material(machine: &Machine, material: Option<&str>) -> Machine {
    let preset = crate::slice::MATERIALS
        .iter()
        .find(|m| Some(m.name) == material);
    let mut narrowed = machine.clone();
    if let Some(p) = preset {
        narrowed.max_hotend_c = narrowed.max_hotend_c.min(p.nozzle_range_c[1]);
        narrowed.max_bed_c = narrowed.max_bed_c.min(p.bed_range_c[1]);
    }
    narrowed
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
            mode: Default::default(),
            slicer: SlicerKind::Prusa,
            up: UpAxis::Z,
            profile: None,
            timeout: Duration::from_secs(60),
            settings: Default::default(),
            asks: Default::default(),
            per_plate: 1,
            copies: 1,
            bed_clear: None,
        }
    }

    /// The sidecar's asks override the folder's; the material is what the job is sliced
    /// for and narrows the policy's temperature limits; a nozzle no printer of the folder
    /// has fails the job with the reason.
    #[test]
    fn asks_come_from_folder_and_sidecar() {
        let mut f = folder();
        f.asks.priority = 5;
        f.asks.tags = vec!["big".into()];
        let resolve = |sidecar: &str| {
            let s = parse_sidecar(sidecar.as_bytes(), Path::new("m.stl.toml"))?;
            resolve_task(
                "j",
                Path::new("/spool/j"),
                "m.stl",
                &f,
                &printers(),
                Some(&s),
            )
        };
        let task = resolve("material = \"petg\"\ncolour = \"Black\"\npriority = 9\n").unwrap();
        assert_eq!(task.asks.material.as_deref(), Some("PETG"));
        assert_eq!(task.asks.colour.as_deref(), Some("black"));
        assert_eq!(
            (task.asks.priority, task.asks.tags.clone()),
            (9, vec!["big".to_string()])
        );
        assert_eq!(task.settings.material.as_deref(), Some("petg"));
        assert!(task
            .machines
            .iter()
            .all(|m| m.machine.max_hotend_c <= 255.0));
        let e = resolve("nozzle_mm = 0.8\n").unwrap_err();
        assert!(e.contains("0.8 mm nozzle"), "{e}");
        let e = resolve("material = \"nylon\"\n").unwrap_err();
        assert!(e.contains("key `material`"), "{e}");
        assert!(resolve("priority = 1000\n").is_err());
        assert!(resolve("tags = [\"a b\"]\n").is_err());
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
            file_material: None,
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
            file_material: None,
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
