//! `GET /metrics`: the farm in Prometheus' text format (version 0.0.4). Names follow
//! Prometheus' conventions (`crispen_` prefix, base units in the name: `_celsius`,
//! `_seconds`, counters ending in `_total`). Labels are printer names, states and hot
//! folder names, all from the config; never a file name, which would make a new series
//! for every job.

use super::counters::Counters;
use super::AppState;
use crate::daemon::farm::PrinterState;
use crate::daemon::job::JobState;
use axum::extract::State;
use axum::http::header;
use axum::response::IntoResponse;
use std::fmt::Write;

const PRINTER_STATES: [PrinterState; 14] = [
    PrinterState::Connecting,
    PrinterState::Idle,
    PrinterState::WaitingToHeat,
    PrinterState::Printing,
    PrinterState::Paused,
    PrinterState::WaitingForOperator,
    PrinterState::Halted,
    PrinterState::BedNotCleared,
    PrinterState::Ejecting,
    PrinterState::CheckingBed,
    PrinterState::Maintenance,
    PrinterState::Off,
    PrinterState::Disconnected,
    PrinterState::Stopped,
];

pub(crate) async fn metrics(State(state): State<AppState>) -> impl IntoResponse {
    let farm = state.farm.clone();
    let cameras = state.cameras.clone();
    let counters = state.counters.clone();
    let text = tokio::task::spawn_blocking(move || {
        render(&farm, &counters) + &render_cameras(&farm, &cameras)
    })
    .await
    .unwrap_or_default();
    (
        [(
            header::CONTENT_TYPE,
            "text/plain; version=0.0.4; charset=utf-8",
        )],
        text,
    )
}

/// A label value, escaped as the text format wants.
fn label(value: &str) -> String {
    value
        .replace('\\', "\\\\")
        .replace('"', "\\\"")
        .replace('\n', "\\n")
}

struct Out(String);

impl Out {
    fn family(&mut self, name: &str, kind: &str, help: &str) {
        let _ = writeln!(self.0, "# HELP {name} {help}\n# TYPE {name} {kind}");
    }
    fn sample(&mut self, name: &str, labels: &[(&str, &str)], value: f64) {
        let labels: Vec<String> = labels
            .iter()
            .map(|(k, v)| format!("{k}=\"{}\"", label(v)))
            .collect();
        let labels = if labels.is_empty() {
            String::new()
        } else {
            format!("{{{}}}", labels.join(","))
        };
        let _ = writeln!(self.0, "{name}{labels} {value}");
    }
}

/// The cameras' figures: whether each answers, its frames and failures, and what the
/// jobs' pictures take on disk.
fn render_cameras(farm: &crate::daemon::farm::Farm, cameras: &crate::camera::Cameras) -> String {
    use crate::camera::feed::CameraState;
    let mut out = Out(String::new());
    let statuses: Vec<_> = cameras
        .printers()
        .filter_map(|p| cameras.status(p, super::camera::prints(farm, p)))
        .collect();
    type Figure = fn(&crate::camera::hub::CameraStatus) -> f64;
    let families: [(&str, &str, &str, Figure); 4] = [
        (
            "crispen_camera_online",
            "gauge",
            "1 when the printer's camera gives fresh frames (0: offline, starting or frozen).",
            |s| f64::from(u8::from(s.state == CameraState::Online)),
        ),
        (
            "crispen_camera_frozen",
            "gauge",
            "1 when the printer's camera repeats one picture while it prints.",
            |s| f64::from(u8::from(s.state == CameraState::Frozen)),
        ),
        (
            "crispen_camera_frames_total",
            "counter",
            "Frames taken from the printer's camera.",
            |s| s.frames as f64,
        ),
        (
            "crispen_camera_failures_total",
            "counter",
            "Fetches from the printer's camera that failed.",
            |s| s.failures as f64,
        ),
    ];
    for (name, kind, help, figure) in families {
        out.family(name, kind, help);
        for s in &statuses {
            out.sample(name, &[("printer", &s.printer)], figure(s));
        }
    }
    out.family(
        "crispen_camera_disk_bytes",
        "gauge",
        "Bytes the jobs' snapshots and timelapses take ([camera] disk_limit_mb bounds it).",
    );
    out.sample(
        "crispen_camera_disk_bytes",
        &[],
        crate::camera::timelapse::total_bytes(cameras.root()) as f64,
    );
    out.0
}

/// The printers' care (see `daemon::care`): what each has done since its counting began
/// (kept in the store, so these survive restarts) and which `[[maintenance]]` tasks are due.
fn render_care(out: &mut Out, printers: &[crate::daemon::farm::PrinterStatus]) {
    type Figure = fn(&crate::daemon::care::Counts) -> f64;
    let families: [(&str, &str, Figure); 4] = [
        (
            "crispen_printer_care_print_seconds_total",
            "Seconds the printer has printed since its care counting began.",
            |c| c.print_s,
        ),
        (
            "crispen_printer_care_prints_total",
            "Prints the printer has made (each heats it up once) since its counting began.",
            |c| c.prints as f64,
        ),
        (
            "crispen_printer_care_failed_prints_total",
            "Of those prints, the ones that failed.",
            |c| c.failed as f64,
        ),
        (
            "crispen_printer_care_filament_grams_total",
            "Grams of filament the printer has pushed (of prints whose filament was known).",
            |c| c.filament_g,
        ),
    ];
    for (name, help, figure) in families {
        out.family(name, "counter", help);
        for p in printers {
            if let Some(c) = &p.care {
                out.sample(name, &[("printer", &p.name)], figure(c));
            }
        }
    }
    out.family(
        "crispen_maintenance_due",
        "gauge",
        "1 when the printer's [[maintenance]] task is due (blocking: it takes no job until done).",
    );
    for p in printers {
        for t in &p.maintenance {
            let block = if t.block { "true" } else { "false" };
            out.sample(
                "crispen_maintenance_due",
                &[("printer", &p.name), ("task", &t.task), ("blocking", block)],
                f64::from(u8::from(t.due)),
            );
        }
    }
    out.family(
        "crispen_printer_in_maintenance",
        "gauge",
        "1 while the printer is in maintenance by hand.",
    );
    for p in printers {
        out.sample(
            "crispen_printer_in_maintenance",
            &[("printer", &p.name)],
            f64::from(u8::from(p.held.is_some())),
        );
    }
}

pub(crate) fn render(farm: &crate::daemon::farm::Farm, counters: &Counters) -> String {
    let view = super::api::snapshot(farm);
    let mut out = Out(String::new());

    out.family(
        "crispen_printer_up",
        "gauge",
        "1 when the printer is connected and answering.",
    );
    for p in &view.printers {
        let up = !matches!(
            p.state,
            PrinterState::Connecting
                | PrinterState::Disconnected
                | PrinterState::Stopped
                | PrinterState::Off
        );
        out.sample(
            "crispen_printer_up",
            &[("printer", &p.name)],
            f64::from(u8::from(up)),
        );
    }
    out.family(
        "crispen_printer_state",
        "gauge",
        "1 for the state each printer is in.",
    );
    for p in &view.printers {
        for s in PRINTER_STATES {
            let name = serde_json::to_value(s).ok();
            let name = name.as_ref().and_then(|v| v.as_str()).unwrap_or("?");
            let value = f64::from(u8::from(p.state == s));
            out.sample(
                "crispen_printer_state",
                &[("printer", &p.name), ("state", name)],
                value,
            );
        }
    }
    render_care(&mut out, &view.printers);
    out.family(
        "crispen_printer_bed_cleared",
        "gauge",
        "0 while a finished print waits on the bed.",
    );
    for p in &view.printers {
        out.sample(
            "crispen_printer_bed_cleared",
            &[("printer", &p.name)],
            f64::from(u8::from(p.bed_cleared)),
        );
    }
    type Reading = fn(&crate::daemon::farm::PrinterTemperatures) -> Option<f64>;
    let temperatures: [(&str, &str, Reading); 4] = [
        (
            "crispen_printer_hotend_celsius",
            "Hotend temperature, printing or idle (absent while not known now).",
            |t| t.hotend_c,
        ),
        (
            "crispen_printer_hotend_target_celsius",
            "Hotend target temperature (0: heater off).",
            |t| t.hotend_target_c,
        ),
        (
            "crispen_printer_bed_celsius",
            "Bed temperature, printing or idle (absent while not known now).",
            |t| t.bed_c,
        ),
        (
            "crispen_printer_bed_target_celsius",
            "Bed target temperature (0: heater off).",
            |t| t.bed_target_c,
        ),
    ];
    for (name, help, read) in temperatures {
        out.family(name, "gauge", help);
        for p in &view.printers {
            if let Some(v) = p.temperatures.as_ref().and_then(read) {
                out.sample(name, &[("printer", &p.name)], v);
            }
        }
    }
    out.family(
        "crispen_printer_job_progress_ratio",
        "gauge",
        "Share of the current print's lines acknowledged, 0 to 1.",
    );
    for p in &view.printers {
        if let Some(l) = p.progress.as_ref().filter(|l| l.lines_total > 0) {
            out.sample(
                "crispen_printer_job_progress_ratio",
                &[("printer", &p.name)],
                l.lines_acked as f64 / l.lines_total as f64,
            );
        }
    }
    out.family(
        "crispen_printer_job_remaining_seconds",
        "gauge",
        "Estimated time left of the current print.",
    );
    for p in &view.printers {
        if let Some(r) = p.progress.as_ref().and_then(|l| l.remaining_s) {
            out.sample(
                "crispen_printer_job_remaining_seconds",
                &[("printer", &p.name)],
                r,
            );
        }
    }

    // The counts and the tally are of the snapshot's changes: taken from one snapshot,
    // they agree with each other.
    let store = farm.store();
    let counts = store.counts();
    out.family("crispen_jobs", "gauge", "Jobs in the spool by state.");
    for s in JobState::ALL {
        let n = view.jobs.iter().filter(|j| j.status.state == s).count();
        out.sample("crispen_jobs", &[("state", s.name())], n as f64);
    }
    // What is left on each spool the farm knows and has not archived.
    let inventory = store.inventory();
    out.family(
        "crispen_spool_remaining_grams",
        "gauge",
        "Filament left on each spool, grams (less what prints took that its source has not counted yet); `printer` is where it is loaded.",
    );
    for s in inventory.spools.values().filter(|s| !s.archived) {
        if let Some(g) = s.remaining_g() {
            out.sample(
                "crispen_spool_remaining_grams",
                &[
                    ("spool", s.id.as_str()),
                    ("material", s.filament.material.as_str()),
                    ("colour", s.filament.colour.as_str()),
                    ("printer", inventory.holder(&s.id).unwrap_or("")),
                ],
                g,
            );
        }
    }
    out.family(
        "crispen_job_changes_total",
        "counter",
        "Job state changes since the daemon started, by the state reached (in a shared farm, every host's).",
    );
    for s in JobState::ALL {
        let n = counts.entered(s);
        out.sample(
            "crispen_job_changes_total",
            &[("state", s.name())],
            n as f64,
        );
    }
    out.family(
        "crispen_folder_queue_length",
        "gauge",
        "Jobs from each hot folder that have not reached a printer yet.",
    );
    for f in &view.folders {
        out.sample(
            "crispen_folder_queue_length",
            &[("folder", &f.name)],
            f.queued as f64,
        );
    }

    // Preparation times of the live jobs (a summary of what the snapshot holds).
    let mut prepare = (0.0, 0u64);
    for job in store.jobs() {
        for pair in job.history.windows(2) {
            if let ((JobState::Preparing, t0), (JobState::Ready, t1)) = (pair[0], pair[1]) {
                prepare.0 += (t1 - t0).max(0.0);
                prepare.1 += 1;
            }
        }
    }
    out.family(
        "crispen_preparation_duration_seconds",
        "summary",
        "Time from the start of a preparation to ready, of the live jobs.",
    );
    out.sample("crispen_preparation_duration_seconds_sum", &[], prepare.0);
    out.sample(
        "crispen_preparation_duration_seconds_count",
        &[],
        prepare.1 as f64,
    );

    // Counters since the process started, by printer (`store::stats::Tally`): they only
    // grow while it runs, whatever moves to the history; every configured printer has
    // its series from the start.
    let mut tally = store.tally().read();
    for p in &view.printers {
        tally.entry(p.name.clone()).or_default();
    }
    let print: (f64, u64) = tally
        .values()
        .fold((0.0, 0), |(s, n), t| (s + t.printing_s, n + t.prints));
    out.family(
        "crispen_print_duration_seconds",
        "summary",
        "Time from the start of a print to its end, of the prints ended since the daemon started.",
    );
    out.sample("crispen_print_duration_seconds_sum", &[], print.0);
    out.sample("crispen_print_duration_seconds_count", &[], print.1 as f64);
    out.family(
        "crispen_jobs_total",
        "counter",
        "Jobs finished since the daemon started, by printer and result (done, failed, cancelled).",
    );
    for (printer, t) in &tally {
        for (result, n) in [
            ("done", t.done),
            ("failed", t.failed),
            ("cancelled", t.cancelled),
        ] {
            out.sample(
                "crispen_jobs_total",
                &[("printer", printer), ("result", result)],
                n as f64,
            );
        }
    }
    type Read = fn(&crate::daemon::store::stats::PrinterTally) -> f64;
    let printer_counters: [(&str, &str, Read); 4] = [
        (
            "crispen_printing_seconds_total",
            "Time spent printing since the daemon started.",
            |t| t.printing_s,
        ),
        (
            "crispen_filament_used_meters_total",
            "Filament of the prints finished since the daemon started (the slicer's figure, or the extrusion followed).",
            |t| t.filament_m,
        ),
        (
            "crispen_printer_resends_total",
            "Lines the printer asked to have sent again, over the prints ended since the daemon started.",
            |t| t.resends as f64,
        ),
        (
            "crispen_printer_silence_probes_total",
            "M105 probes sent to a silent printer, over the prints ended since the daemon started.",
            |t| t.silence_probes as f64,
        ),
    ];
    for (name, help, read) in printer_counters {
        out.family(name, "counter", help);
        for (printer, t) in &tally {
            out.sample(name, &[("printer", printer)], read(t));
        }
    }
    beds(&mut out, &store, tally.keys());
    notifications(&mut out, counters);
    octoprint_control(&mut out, counters);
    out.0
}

/// The beds' ejects and camera checks since the daemon started, by printer and result
/// (counted by the job store's task as it changes the beds), every printer's series from
/// the start.
fn beds<'a>(
    out: &mut Out,
    store: &crate::daemon::store::Snapshot,
    printers: impl Iterator<Item = &'a String> + Clone,
) {
    use crate::daemon::bed::result;
    let counts = store.bed_counts();
    for (name, kind, results, help) in [
        (
            "crispen_ejects_total",
            "ejects",
            &result::EJECTS[..],
            "Eject sequences run since the daemon started, by printer and result (done, failed).",
        ),
        (
            "crispen_bed_checks_total",
            "checks",
            &result::CHECKS[..],
            "Camera checks of a bed since the daemon started, by printer and result (clear, not_clear, unavailable: the camera could not check).",
        ),
    ] {
        out.family(name, "counter", help);
        for printer in printers.clone() {
            for &r in results {
                let n = counts
                    .get(&(printer.clone(), kind, r))
                    .copied()
                    .unwrap_or(0);
                out.sample(name, &[("printer", printer), ("result", r)], n as f64);
            }
        }
    }
}

fn octoprint_control(out: &mut Out, counters: &Counters) {
    out.family(
        "crispen_octoprint_control_total",
        "counter",
        "Control actions (pause, resume, toggle, cancel, start) asked through an OctoPrint instance, by hot folder, action and result (done, refused, failed).",
    );
    for (folder, action, result, n) in counters.octoprint_control() {
        out.sample(
            "crispen_octoprint_control_total",
            &[("folder", &folder), ("action", action), ("result", result)],
            n as f64,
        );
    }
}

/// The notification counters and the build's version.
fn notifications(out: &mut Out, counters: &Counters) {
    out.family(
        "crispen_notifications_total",
        "counter",
        "Notification attempts and events by receiver: delivered, error (an attempt failed; retried), dropped (given up).",
    );
    for (receiver, outcome, n) in counters.notifications() {
        out.sample(
            "crispen_notifications_total",
            &[("receiver", &receiver), ("result", outcome.name())],
            n as f64,
        );
    }
    out.family(
        "crispen_build_info",
        "gauge",
        "Always 1; the running crispen's version as a label.",
    );
    out.sample(
        "crispen_build_info",
        &[("version", env!("CARGO_PKG_VERSION"))],
        1.0,
    );
}
