//! A plate on the real firmware: six parts sliced by a real slicer onto one bed, printed
//! through the relay, one part cancelled mid-print. After every layer the firmware's own
//! `M114` (position and E) must be what the follower predicts for the plate without that
//! part from the line it was dropped at, and the filament the firmware pushed must be the
//! plate's less that part's share from there on, reckoned from the file itself.

use super::common::relay::{firmware_dir, noise, parse_position_e, Build, Relay, RelayLog};
use crispen::daemon::prepare::steps::{prepare_one, SliceRequest, Target};
use crispen::enhance::Strength;
use crispen::machine::Machine;
use crispen::marlin::firmware::Firmware;
use crispen::marlin::gcode::GcodeProgram;
use crispen::marlin::motion::Motion;
use crispen::marlin::reader;
use crispen::marlin::stream::{
    CancelledPart, Connection, PrintProgress, PrintReport, StreamControl, StreamOptions,
};
use crispen::slice::SlicerKind;
use std::time::Duration;
use tokio::sync::{mpsc, watch};

/// A box `x` by `y` mm and `h` tall, as an ASCII STL.
fn box_stl(x: f64, y: f64, h: f64) -> String {
    let v = [
        [0.0, 0.0, 0.0],
        [x, 0.0, 0.0],
        [x, y, 0.0],
        [0.0, y, 0.0],
        [0.0, 0.0, h],
        [x, 0.0, h],
        [x, y, h],
        [0.0, y, h],
    ];
    let faces = [
        [0, 2, 1],
        [0, 3, 2],
        [4, 5, 6],
        [4, 6, 7],
        [0, 1, 5],
        [0, 5, 4],
        [1, 2, 6],
        [1, 6, 5],
        [2, 3, 7],
        [2, 7, 6],
        [3, 0, 4],
        [3, 4, 7],
    ];
    let mut s = String::from("solid box\n");
    for f in faces {
        s += " facet normal 0 0 0\n  outer loop\n";
        for i in f {
            s += &format!("   vertex {} {} {}\n", v[i][0], v[i][1], v[i][2]);
        }
        s += "  endloop\n endfacet\n";
    }
    s + "endsolid box\n"
}

/// Six 5 mm boxes 1 mm tall on one plate, sliced by `slicer` for `machine` with
/// crispen's own preparation.
fn slice_plate(dir: &std::path::Path, slicer: SlicerKind, machine: &str) -> String {
    let model = dir.join("box.stl");
    std::fs::write(&model, box_stl(5.0, 5.0, 1.0)).unwrap();
    let mut req = SliceRequest::new(&model, 1.0);
    req.strength = Strength::Off;
    req.slicer = slicer;
    req.per_plate = 6;
    let output = dir.join("plate.gcode");
    let target = Target {
        machine: Machine::builtin(machine).unwrap(),
        output: output.clone(),
        keep_mesh: None,
    };
    let report = prepare_one(&req, target, &mut |_| {})
        .unwrap_or_else(|e| panic!("{slicer} slices the plate: {e}"));
    assert_eq!(report.parts.len(), 6, "{slicer}: {:?}", report.parts);
    std::fs::read_to_string(output).unwrap()
}

/// The sliced plate as these emulated printers can run it, changed only where they differ
/// from a printer on a desk: no heating (Marlin's simulated hotend takes minutes, and
/// `M302` lets the extruder move cold, as it moves hot); on the Ultimaker 2, no homing
/// (its emulator has no endstops: `G92` says where the head is instead). And the position
/// asked for (`M114`) at the end of every layer and before every `G92 E`, where the
/// filament count starts again, and at the end.
fn printable(text: &str, build: Build) -> String {
    let mut out = String::from(match build {
        Build::Ultimaker2 => "M302\n",
        _ => "M302 S0\n",
    });
    for line in text.lines() {
        let code = line.split(';').next().unwrap_or("").trim();
        let word = code.split_whitespace().next().unwrap_or("");
        if matches!(word, "M104" | "M109" | "M140" | "M190") {
            continue;
        }
        if word == "G28" && build == Build::Ultimaker2 {
            out += "G92 X0 Y0 Z0\n";
            continue;
        }
        let layer = line.starts_with(";LAYER_CHANGE") || line.starts_with(";LAYER:");
        let e_reset = word == "G92" && code.contains('E');
        if layer || e_reset {
            out += "M114\n";
        }
        out += line;
        out += "\n";
    }
    out + "M400\nM114\n"
}

/// What a plate's print on the firmware gave.
struct Printed {
    report: PrintReport,
    cancelled: Vec<CancelledPart>,
    log: RelayLog,
}

/// Prints `program` through the relay in front of `build`, cancelling `part` once the
/// printer has acknowledged `cancel_at` of its lines.
async fn print_plate(build: Build, program: &GcodeProgram, part: u16, cancel_at: f64) -> Printed {
    let relay = Relay::start(&firmware_dir(), build, noise(5));
    let opts = StreamOptions::for_firmware(program.firmware());
    let mut conn = Connection::open(relay.device_path(), &opts)
        .await
        .unwrap_or_else(|e| panic!("{}: {e}", build.name()));
    let (control, control_rx) = mpsc::channel(4);
    let (progress, mut progress_rx) = watch::channel(PrintProgress::default());
    let print = conn.print_plate(program, &[], control_rx, progress);
    tokio::pin!(print);
    let total = program.len() as f64;
    let mut sent = false;
    // A guard against a hang, not a deadline: once the plate's print sat for twenty
    // minutes with the firmware answering nothing but its temperature reports, and nothing
    // ended it; the wire's last lines say where it stood. It counts from the last line
    // acknowledged: on a starved machine the whole print takes ten minutes and more.
    const STALL: Duration = Duration::from_secs(300);
    let guard = tokio::time::sleep(STALL);
    tokio::pin!(guard);
    let mut last_acked = 0;
    let result = loop {
        tokio::select! {
            result = &mut print => break result,
            Ok(()) = progress_rx.changed() => {
                let acked = progress_rx.borrow_and_update().lines_acked;
                if acked > last_acked {
                    last_acked = acked;
                    guard.as_mut().reset(tokio::time::Instant::now() + STALL);
                }
                let acked = acked as f64;
                if !sent && acked >= cancel_at * total {
                    sent = true;
                    control.send(StreamControl::CancelPart(part)).await.unwrap();
                }
            }
            () = &mut guard => {
                let log = relay.log();
                let wire: Vec<String> = log.wire[log.wire.len().saturating_sub(60)..]
                    .iter()
                    .map(|(t, way, line)| format!("{t:9.3} {way} {line}"))
                    .collect();
                panic!(
                    "{}: no line acknowledged for {} s ({last_acked} so far); the wire's last \
                     lines:\n{}",
                    build.name(),
                    STALL.as_secs(),
                    wire.join("\n")
                );
            }
        }
    };
    let report = result.unwrap_or_else(|e| {
        panic!(
            "{}: the plate's print failed: {e}\nlast lines:\n{:?}",
            build.name(),
            relay
                .log()
                .printer_lines
                .iter()
                .rev()
                .take(20)
                .collect::<Vec<_>>()
        )
    });
    let cancelled = progress_rx.borrow().cancelled_parts.clone();
    // Every line is acknowledged, but the firmware still holds moves in its planner (and
    // Ultimaker2Marlin in its command slots) ahead of the last reports: they come once
    // those moves ran. The limit only keeps a firmware that never answers from hanging.
    let reports = program
        .iter()
        .filter_map(|line| reader::read(line).ok().flatten())
        .filter(|cmd| answers_position(program.firmware(), &cmd.code))
        .count();
    let log = tokio::task::block_in_place(|| {
        relay.wait_until(Duration::from_secs(300), |log| {
            log.printer_lines
                .iter()
                .filter_map(|l| parse_position_e(l))
                .count()
                >= reports
        })
    });
    Printed {
        report,
        cancelled,
        log,
    }
}

/// Whether the firmware answers `code` with its position: `M114`, and on Marlin 2.1 `G92`
/// and `G28` too (`G92.cpp`, `G28.cpp`: `report_current_position()` at their end).
fn answers_position(fw: Firmware, code: &str) -> bool {
    match fw {
        Firmware::Ultimaker2 => code == "M114",
        _ => matches!(code, "M114" | "G92" | "G28"),
    }
}

/// Where the firmware reports the head and E (in the file's coordinates) at each command
/// that answers with its position, among the lines the host sent for `program` with `part` dropped from command `from`,
/// as the follower predicts; and the filament the firmware pushed meanwhile, reckoned from
/// those reports and the `G92 E` the host sent.
fn predict(program: &GcodeProgram, part: u16, from: usize) -> (Vec<[f64; 4]>, Vec<Option<f64>>) {
    let fw = program.firmware();
    let mut motion = Motion::new(fw);
    let mut reports = Vec::new();
    // Per report: the E a `G92 E` sent since the report before set (None: none).
    let mut resets = Vec::new();
    let mut reset = None;
    for (_, line) in crispen::marlin::plate::sent_lines(program, &[(part, from)]) {
        let Some(line) = line else { continue };
        let Ok(Some(cmd)) = reader::read(&line) else {
            continue;
        };
        motion.apply(&cmd).unwrap();
        if cmd.code == "G92" {
            if let Some(e) = cmd.get('E') {
                reset = Some(e);
            }
        }
        if answers_position(fw, &cmd.code) {
            let p = motion.position();
            reports.push([
                motion.to_file(0, p[0]),
                motion.to_file(1, p[1]),
                motion.to_file(2, p[2]),
                p[3],
            ]);
            resets.push(reset.take());
        }
    }
    (reports, resets)
}

/// The filament `program` pushes, and what `part`'s extruding moves push from command
/// `from` on: read from the file alone, with no filter.
fn file_filament(program: &GcodeProgram, part: u16, from: usize) -> (f64, f64) {
    let marks = program.marks().expect("a labelled plate");
    let mut motion = Motion::new(program.firmware());
    let (mut total, mut share) = (0.0, 0.0);
    for (i, line) in program.iter().enumerate() {
        let Ok(Some(cmd)) = reader::read(line) else {
            continue;
        };
        if let Ok(Some(m)) = motion.apply(&cmd) {
            total += m.extruded();
            if i >= from && marks.part_at(i) == Some(part) && m.extruded() > 0.0 && m.moves_xy() {
                share += m.extruded();
            }
        }
    }
    (total, share)
}

async fn plate_on(build: Build, slicer: SlicerKind, machine: &str) {
    let tmp = tempfile::tempdir().unwrap();
    let sliced = slice_plate(tmp.path(), slicer, machine);
    let text = printable(&sliced, build);
    let fw = match build {
        Build::Ultimaker2 => Firmware::Ultimaker2,
        _ => Firmware::Marlin2,
    };
    let program = GcodeProgram::read(text.as_bytes(), "plate.gcode", fw).unwrap();
    let names = program.marks().expect("the plate's parts").names().to_vec();
    assert_eq!(names.len(), 6, "{names:?}");
    let part = 2;
    let printed = print_plate(build, &program, part, 0.45).await;
    assert_eq!(printed.report.lines_acked, program.len());
    let [cancel] = printed.cancelled.as_slice() else {
        panic!("one part cancelled: {:?}", printed.cancelled);
    };
    assert_eq!((cancel.part, &cancel.name), (part, &names[2]));
    let (predicted, resets) = predict(&program, part, cancel.from);
    let answers: Vec<[f64; 4]> = printed
        .log
        .printer_lines
        .iter()
        .filter_map(|l| parse_position_e(l))
        .collect();
    assert_eq!(
        answers.len(),
        predicted.len(),
        "{}: one report per command that reports",
        build.name()
    );
    let layers = text.lines().filter(|l| l.starts_with(";LAYER")).count();
    assert!(layers >= 5, "{layers} layers");
    for (k, (at, want)) in answers.iter().zip(&predicted).enumerate() {
        for axis in 0..4 {
            assert!(
                (at[axis] - want[axis]).abs() <= 0.0051,
                "{}: report {k} of {}: the firmware is at {at:?}, the follower predicted {want:?} \
                 for the plate without {:?} from command {}",
                build.name(),
                answers.len(),
                cancel.name,
                cancel.from
            );
        }
    }
    // The filament the firmware pushed: its E from report to report, counted again from
    // each `G92 E` the host sent between two reports.
    let mut pushed = 0.0;
    let mut last = 0.0;
    for (at, reset) in answers.iter().zip(&resets) {
        if let Some(e) = reset {
            // The report right before each `G92 E` is where the count stopped.
            last = *e;
        }
        pushed += at[3] - last;
        last = at[3];
    }
    let (total, share) = file_filament(&program, part, cancel.from);
    assert!(share > 0.3, "the part had {share} mm left to push");
    assert!(
        (pushed - (total - share)).abs() < 0.1,
        "{}: the firmware pushed {pushed:.3} mm; the plate is {total:.3} mm, {share:.3} of it the \
         cancelled part's from command {}",
        build.name(),
        cancel.from
    );
    eprintln!(
        "FIGURES {} {slicer} plate: part {:?} dropped at command {} of {}; {} reports after \
         every layer and E reset agree with the follower; pushed {pushed:.3} mm = {total:.3} \
         - {share:.3} mm",
        build.name(),
        cancel.name,
        cancel.from,
        program.len(),
        answers.len()
    );
}

#[cfg_attr(
    not(crispen_firmware),
    ignore = "CRISPEN_FIRMWARE_DIR was unset at build time"
)]
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn marlin_prints_a_prusaslicer_plate_without_the_part_cancelled_as_predicted() {
    plate_on(Build::Default, SlicerKind::Prusa, "marlin-175").await;
}

#[cfg_attr(
    not(crispen_firmware),
    ignore = "CRISPEN_FIRMWARE_DIR was unset at build time"
)]
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn ultimaker2_prints_a_cura_plate_without_the_part_cancelled_as_predicted() {
    plate_on(Build::Ultimaker2, SlicerKind::Cura, "ultimaker2").await;
}
