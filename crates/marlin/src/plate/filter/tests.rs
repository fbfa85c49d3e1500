//! The filter against the follower: a plate's file with a part cancelled at every line in
//! turn, each sent line followed as the firmware follows it ([`Motion`]), and compared
//! with the file's own moves: the other parts' moves go from and to the same places with
//! the same filament, the cancelled part's push none, and nothing goes where the file
//! does not.

use super::*;
use crate::labels::{LabelReader, LineLabel};

/// A file's commands and marks, as the host loads them.
fn load(text: &str) -> (GcodeCommands, Arc<Marks>) {
    let mut reader = LabelReader::default();
    let mut commands = Vec::new();
    for line in text.lines() {
        if reader.line(line, commands.len()) == LineLabel::No {
            let code = line.split(';').next().unwrap().trim();
            if !code.is_empty() {
                commands.push(code.to_string());
            }
        }
    }
    let n = commands.len();
    (
        GcodeCommands::from(commands),
        Arc::new(reader.finish(n).expect("a plate")),
    )
}

/// One move as the firmware makes it: from, to (X, Y, Z) and the filament it pushes.
#[derive(Debug, Clone, Copy, PartialEq)]
struct Made {
    from: [f64; 3],
    to: [f64; 3],
    push: f64,
}

fn made(m: &crate::motion::Move) -> Made {
    Made {
        from: [m.from[0], m.from[1], m.from[2]],
        to: [m.to[0], m.to[1], m.to[2]],
        push: m.extruded(),
    }
}

/// Sends `commands` through a filter that cancels `part` at `at` (None: never), and
/// follows both the file and what was sent. Checks, at every command of the file outside
/// the cancelled part's lines from the cancel on: the head is where the file puts it (in
/// the firmware's floats, exactly), and an extruding move of the file was sent as itself
/// (same ends, same filament within float rounding). Returns the filament sent and the
/// filament of the file, and what the filter says it dropped.
fn check(
    commands: &GcodeCommands,
    marks: &Arc<Marks>,
    fw: Firmware,
    part: u16,
    at: Option<usize>,
) -> (f64, f64, f64) {
    let mut filter = PartFilter::new(Arc::clone(marks), fw);
    let mut file = Motion::new(fw);
    let mut sent = Motion::new(fw);
    let (mut sent_e, mut file_e) = (0.0, 0.0);
    let mut lo = [f64::INFINITY; 3];
    let mut hi = [f64::NEG_INFINITY; 3];
    for i in 0..commands.len() {
        if at == Some(i) {
            assert_eq!(filter.cancel(part), Some(i));
        }
        let decision = filter.decide(commands).unwrap();
        let original = reader::read(&commands[i]).unwrap().unwrap();
        let fm = file.apply(&original).unwrap();
        if let Some(m) = fm {
            file_e += m.extruded();
            for k in 0..3 {
                lo[k] = lo[k].min(m.lo[k]);
                hi[k] = hi[k].max(m.hi[k]);
            }
        }
        let mut last = None;
        if let Some(line) = decision.line() {
            let cmd = reader::read(&line)
                .unwrap_or_else(|e| panic!("line {i}: sent `{line}`: {e}"))
                .unwrap();
            if let Some(m) = sent.apply(&cmd).unwrap() {
                sent_e += m.extruded();
                for k in 0..3 {
                    assert!(
                        m.lo[k] >= lo[k] - 1e-9 && m.hi[k] <= hi[k] + 1e-9,
                        "line {i}: `{line}` goes where the file never does ({m:?})"
                    );
                }
                last = Some(m);
            }
        }
        let dropped = marks.part_at(i) == Some(part) && at.is_some_and(|a| a <= i);
        if dropped {
            if let Some(m) = last {
                assert!(
                    !(m.extruded() > 0.0 && m.moves_xy()),
                    "line {i}: `{}` still extrudes as {m:?}",
                    &commands[i]
                );
            }
            continue;
        }
        let (f, s) = (file.position(), sent.position());
        assert_eq!(
            [f[0], f[1], f[2]],
            [s[0], s[1], s[2]],
            "line {i} `{}`: the head is not where the file puts it",
            &commands[i]
        );
        if let Some(fm) = fm.filter(|m| m.extruded() > 0.0 && m.moves_xy()) {
            let sm = made(&last.unwrap_or_else(|| panic!("line {i}: `{}` not sent", &commands[i])));
            let fm = made(&fm);
            assert_eq!((sm.from, sm.to), (fm.from, fm.to), "line {i}");
            assert!(
                (sm.push - fm.push).abs() < 1e-4,
                "line {i}: {sm:?} for {fm:?}"
            );
        }
    }
    (sent_e, file_e, filter.dropped_mm(part))
}

/// PrusaSlicer's way (absolute E, `G92 E0` after each retraction, the retraction inside the
/// next part's label) and a wipe; Cura's way (absolute E, never reset, retraction at the
/// end of each mesh).
const PRUSA: &str = "G28\nG90\nM82\nG92 E0\nG1 Z0.2 F9000\n\
    ; printing object a\nG1 E-1 F3000\nG92 E0\nG1 X10 Y10 F9000\nG1 E6 F3000\nG1 F1200\n\
    G1 X20 Y10 E6.5\nG1 X20 Y20 E7\nG1 X10.5 Y20 E7.47\nG1 X10.7 Y19 F9000\nG1 X11 Y18 E7.2\n\
    ; stop printing object a\n; printing object b\nG1 E1.2 F3000\nG92 E0\nG1 X50 Y50 F9000\n\
    G1 E6 F3000\nG1 F1200\nG1 X60 Y50 E6.41\nG1 X60 Y60 E6.82\nG1 X50 Y60 E7.23\n\
    ; stop printing object b\nG1 E1.23 F3000\nG92 E0\nG1 Z0.4 F9000\n\
    ; printing object a\nG1 X10 Y10\nG1 E6 F3000\nG1 F1200\nG1 X20 Y10 E6.50001\n\
    G1 X20 Y20 E7.00002\n; stop printing object a\n; printing object b\nG1 E1.00002 F3000\n\
    G92 E0\nG1 X50 Y50 F9000\nG1 E6 F3000\nG1 X60 Y50 E6.41\nG2 X60 Y60 I0 J5 E6.9\n\
    G1 X50 Y60 F1200 E7.31\nG1 X50 Y55 F9000\n; stop printing object b\n\
    ; printing object a\nG1 E1.31 F3000\nG92 E0\nG1 X10 Y10 F9000\nG1 E6 F3000\n\
    G1 X20 Y10 E6.5 F1200\n; stop printing object a\nG1 E0.5 F3000\nM104 S0\n";

const CURA: &str = "G28\nG90\nM82\nG92 E0\nG0 F600 Z0.3\n;MESH:a.stl\nG0 F3600 X10 Y10\n\
    G1 F1500 E6.5\nG1 F1800 X20 Y10 E6.71\nG1 X20 Y20 E6.92\nG0 F5400 X20.2 Y20.2\n\
    G1 F1800 X10 Y20 E7.13\nG1 F1500 E0.63\n;MESH:b.stl\nG0 F5400 X50 Y50\nG1 F1500 E7.13\n\
    G1 F1800 X60 Y50 E7.34\nG1 X60 Y60 E7.55\nG1 F1500 E1.05\n;MESH:NONMESH\nG0 F600 Z0.5\n\
    M106 S255\n;MESH:a.stl\nG0 F3600 X10 Y10\nG1 F1500 E7.55\nG1 F1800 X20 Y10 E7.76\n\
    G1 X20 Y20 E7.97\nG1 F1500 E1.47\n;MESH:b.stl\nG0 F5400 X50 Y50\nG1 F1500 E7.97\n\
    G1 F1800 X60 Y50 E8.18\nG1 X60 Y60 E8.39\nG1 F1500 E1.89\n;MESH:NONMESH\nM104 S0\n";

#[test]
fn each_part_cancelled_at_every_line_leaves_the_others_as_the_file_prints_them() {
    for (name, text) in [("prusa", PRUSA), ("cura", CURA)] {
        let (commands, marks) = load(text);
        for fw in [Firmware::Marlin2, Firmware::Ultimaker2] {
            let (sent, file, dropped) = check(&commands, &marks, fw, 0, None);
            assert!((sent - file).abs() < 1e-4 && dropped == 0.0, "{name} {fw}");
            for part in 0..2u16 {
                for at in 0..commands.len() {
                    let (sent, file, dropped) = check(&commands, &marks, fw, part, Some(at));
                    assert!(
                        (file - dropped - sent).abs() < 1e-4,
                        "{name} {fw} part {part} at {at}: sent {sent}, file {file}, dropped {dropped}"
                    );
                }
            }
            // Cancelled from the start, a part pushes nothing of its own.
            let (_, _, dropped) = check(&commands, &marks, fw, 1, Some(0));
            assert!(dropped > 0.8, "{name}: {dropped}");
        }
    }
}

#[test]
fn a_cancelled_stretch_becomes_one_travel_to_where_it_ends() {
    let (commands, marks) = load(PRUSA);
    let mut filter = PartFilter::new(Arc::clone(&marks), Firmware::Marlin2);
    filter.cancel(1);
    let sent: Vec<String> = (0..commands.len())
        .filter_map(|_| {
            filter
                .decide(&commands)
                .unwrap()
                .line()
                .map(|l| l.into_owned())
        })
        .collect();
    let first_b = sent.iter().position(|l| l == "G1 E1.2 F3000").unwrap();
    assert_eq!(
        &sent[first_b..first_b + 5],
        [
            "G1 E1.2 F3000",
            "G92 E0",
            "G1 E6 F3000",
            "G1 F1200",
            "G1 X50 Y60 F1200"
        ],
        "{sent:#?}"
    );
    // A wipe's retraction is kept, as a move of E alone; the part's own lines, none.
    let (commands, marks) = load(
        "G92 E0\n;MESH:a\nG1 X1 Y1 E1 F1200\nG1 X2 Y1 E0.5\nG1 X3 Y1 E0.2\n;MESH:NONMESH\nG1 X5 E1\n",
    );
    let mut filter = PartFilter::new(Arc::clone(&marks), Firmware::Marlin2);
    filter.cancel(0);
    let sent: Vec<Option<String>> = (0..commands.len())
        .map(|_| {
            filter
                .decide(&commands)
                .unwrap()
                .line()
                .map(|l| l.into_owned())
        })
        .collect();
    assert_eq!(
        sent,
        [
            Some("G92 E0".into()),
            None,
            Some("G1 E-0.5 F1200".into()),
            Some("G1 X3 Y1 E-0.8 F1200".into()),
            Some("G1 X5 E0".into()),
        ]
    );
    assert!((filter.dropped_mm(0) - 1.0).abs() < 1e-12);
}

#[test]
fn relative_moves_and_extrusion_are_sent_without_the_extrusion() {
    let (commands, marks) = load(
        "M83\nG1 X10 Y10 F3000\n; printing object a\nG91\nG1 X1 Y0 E0.1\nG1 X0 Y1 E0.1\n\
         G1 E-2\nG90\nM83\n; stop printing object a\nG1 E2\nG1 X20 Y20 E0.5\n",
    );
    for fw in [Firmware::Marlin2, Firmware::Ultimaker2] {
        for at in 0..commands.len() {
            check(&commands, &marks, fw, 0, Some(at));
        }
    }
    let mut filter = PartFilter::new(Arc::clone(&marks), Firmware::Marlin2);
    filter.cancel(0);
    let sent: Vec<String> = (0..commands.len())
        .filter_map(|_| {
            filter
                .decide(&commands)
                .unwrap()
                .line()
                .map(|l| l.into_owned())
        })
        .collect();
    assert_eq!(
        sent,
        [
            "M83",
            "G1 X10 Y10 F3000",
            "G91",
            "G1 X1 Y0",
            "G1 X0 Y1",
            "G1 E-2",
            "G90",
            "M83",
            "G1 E2",
            "G1 X20 Y20 E0.5"
        ]
    );
}

#[test]
fn a_command_that_moves_the_frame_ends_a_stretch() {
    // G92 of X inside the part: the head must be where the file has it before it.
    let (commands, marks) = load(
        "G1 X5 Y5\n; printing object a\nG1 X10 Y10 E1\nG1 X20 Y10 E2\nG92 X0\nG1 X5 Y20 E3\n\
         G10\nG11\n; stop printing object a\nG1 X30 Y30 E4\n",
    );
    for fw in [Firmware::Marlin2, Firmware::Ultimaker2] {
        for at in 0..commands.len() {
            check(&commands, &marks, fw, 0, Some(at));
        }
    }
}

#[test]
fn a_part_cancelled_twice_keeps_its_first_cancel_and_all_cancelled_is_known() {
    let (commands, marks) = load(CURA);
    let mut filter = PartFilter::new(marks, Firmware::Marlin2);
    for _ in 0..3 {
        filter.decide(&commands);
    }
    assert_eq!(filter.cancel(0), Some(3));
    filter.decide(&commands);
    assert_eq!(filter.cancel(0), Some(3));
    assert!(!filter.all_cancelled());
    assert_eq!(filter.cancel(1), Some(4));
    assert!(filter.all_cancelled());
    assert_eq!(filter.cancel(7), None);
}

#[test]
fn filament_decimals_add_exactly() {
    for (text, n) in [
        ("6.02193", 6_021_930_000),
        ("-.5", -500_000_000),
        ("+12", 12_000_000_000),
        ("0.0000000004", 0),
        ("0.0000000005", 1),
    ] {
        assert_eq!(nano(text), Some(n), "{text}");
    }
    assert_eq!(nano("1e3"), None);
    for v in [0, 1, -1, 6_021_930_000, -500_000_000, 12_000_000_000] {
        assert_eq!(nano(&decimal(v)), Some(v), "{v}");
    }
    assert_eq!(decimal(6_021_930_000), "6.02193");
    assert_eq!(decimal(-500_000_000), "-0.5");
}
