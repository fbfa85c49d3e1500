//! Pauses a G-code file asks for (`M0`, `M600`, ...), streamed by the host to the simulated
//! printer over real ptys for every firmware flavour: the printer executes exactly the lines
//! before the pause, is parked, shows the file's message, turns its heaters off when nobody
//! comes, and on resume heats up, returns and runs every remaining line exactly once. The
//! pause command itself never reaches the printer (the simulator would wait for a knob that
//! nobody presses, as the real firmware does).

use crispen::marlin::firmware::Firmware;
use crispen::marlin::gcode::GcodeProgram;
use crispen::marlin::motion::Motion;
use crispen::marlin::pause::{find_pauses, park_lines, resume_lines};
use crispen::marlin::reader;
use crispen::marlin::stream::{
    Connection, PauseSettings, PrintError, PrintProgress, PrintState, StreamControl, StreamOptions,
    Temp, Temperatures,
};
use crispen::sim::{self, is_housekeeping, SimConfig, SimHandle};
use std::time::Duration;
use tokio::sync::{mpsc, watch};

const VOLUME: [f64; 3] = [220.0, 220.0, 250.0];

fn executed(sim: &SimHandle) -> Vec<String> {
    sim.executed()
        .into_iter()
        .filter(|c| !is_housekeeping(c))
        .collect()
}

/// Heat, home, set a position, print a few moves, show a message, pause, print on.
fn paused_job() -> String {
    let mut s = String::from(
        "M140 S60\nM104 S200\nM190 S60\nM109 S200\nG28\nG90\nM83\nG92 E0\nG1 Z0.3 F600\n",
    );
    for i in 0..20 {
        s += &format!("G1 X{} Y{} E0.5 F1800\n", 50 + i, 60 + i % 3);
    }
    s += "M117 Insert magnets\nM0\n";
    for i in 0..20 {
        s += &format!("G1 X{} Y70 E0.5\n", 80 + i);
    }
    s += "M104 S0\nM140 S0\n";
    s
}

async fn wait_for(
    rx: &mut watch::Receiver<PrintProgress>,
    what: &str,
    test: impl Fn(&PrintProgress) -> bool,
) -> PrintProgress {
    let waited = tokio::time::timeout(Duration::from_secs(60), async {
        loop {
            let now = rx.borrow_and_update().clone();
            if test(&now) {
                return now;
            }
            if rx.changed().await.is_err() {
                panic!("the print ended before {what}");
            }
        }
    })
    .await;
    waited.unwrap_or_else(|_| panic!("{what}: not within 60 s"))
}

/// The done-when case, for every firmware flavour: the printer runs every line before the
/// `M0` and none after until the operator resumes; it is parked and shows the message; a
/// pause left alone turns the heaters off and keeps waiting; the resume heats up to the
/// temperatures before the pause, returns, and every job line has run exactly once.
#[tokio::test]
async fn a_file_pause_stops_at_exactly_its_line_and_resumes_every_line_once() {
    for fw in [Firmware::Marlin2, Firmware::Marlin20, Firmware::Ultimaker2] {
        let sim = sim::spawn(SimConfig::new(fw)).unwrap();
        let program = GcodeProgram::read(paused_job().as_bytes(), "magnets.gcode", fw).unwrap();
        let commands = program.to_vec();
        let pause = find_pauses(program.commands())[0].clone();
        let before = &commands[..pause.index];
        let after = &commands[pause.index + 1..];
        let mut motion = Motion::new(fw);
        for c in before.iter().filter_map(|c| reader::read(c).ok().flatten()) {
            motion.apply(&c).unwrap();
        }
        let mut settings = PauseSettings::new(VOLUME);
        settings.heaters_off_after = Duration::from_secs(2);
        let park = park_lines(&settings, &motion).unwrap();

        let mut opts = StreamOptions::for_firmware(fw);
        opts.pause = Some(settings.clone());
        let mut conn = Connection::open(sim.device_path(), &opts).await.unwrap();
        let (control, control_rx) = mpsc::channel(1);
        let (progress, mut rx) = watch::channel(PrintProgress::default());
        let print = conn.print(&program, control_rx, progress);
        tokio::pin!(print);
        let driver = async {
            let waiting = wait_for(&mut rx, "waiting for the operator", |p| {
                p.state == PrintState::WaitingForOperator
            })
            .await;
            let at_pause = executed(&sim);
            let shown = waiting.pause.clone().expect("the pause is shown");
            let off = wait_for(&mut rx, "heaters off", |p| {
                p.pause.as_ref().is_some_and(|p| p.heaters_off)
            })
            .await;
            assert_eq!(
                off.state,
                PrintState::WaitingForOperator,
                "{fw:?}: still waiting"
            );
            let at_heaters_off = executed(&sim);
            control.send(StreamControl::Resume).await.unwrap();
            (waiting, at_pause, shown, at_heaters_off)
        };
        let (result, (waiting, at_pause, shown, at_heaters_off)) = tokio::join!(&mut print, driver);
        let report = result.unwrap_or_else(|e| panic!("{fw:?}: {e}"));

        assert_eq!(
            at_pause,
            [before, &park[..]].concat(),
            "{fw:?}: every line before the pause, then the park, nothing after"
        );
        assert_eq!(shown.message, "Insert magnets", "{fw:?}");
        assert_eq!(shown.command, "M0");
        assert_eq!(shown.line, program.source_line(pause.index));
        assert!(shown.parked && !shown.heaters_off);
        assert_eq!(waiting.lines_acked, pause.index, "{fw:?}");
        assert_eq!(
            at_heaters_off,
            [
                &at_pause[..],
                &["M104 S0".to_string(), "M140 S0".to_string()]
            ]
            .concat(),
            "{fw:?}: heaters off after the limit, still waiting"
        );
        let targets = Temperatures {
            hotend: Some(Temp {
                current: 0.0,
                target: Some(200.0),
            }),
            bed: Some(Temp {
                current: 0.0,
                target: Some(60.0),
            }),
        };
        let resume = resume_lines(&settings, &motion, true, Some(&targets));
        assert!(resume.starts_with(&["M140 S60".into(), "M104 S200".into()]));
        assert_eq!(
            executed(&sim),
            [&at_heaters_off[..], &resume[..], after].concat(),
            "{fw:?}: reheated, returned, and every remaining line once"
        );
        assert!(
            executed(&sim).iter().all(|c| c != "M0"),
            "{fw:?}: the pause itself never reached the printer"
        );
        assert_eq!(report.lines_acked, program.len());
    }
}

/// A cancel while waiting at a file's pause stops the printer safely (heaters, fan and
/// motors off, confirmed) and sends nothing of the rest of the job.
#[tokio::test]
async fn a_cancel_while_waiting_at_a_pause_stops_safely() {
    let fw = Firmware::Marlin2;
    let sim = sim::spawn(SimConfig::new(fw)).unwrap();
    let program = GcodeProgram::read(paused_job().as_bytes(), "magnets.gcode", fw).unwrap();
    let mut opts = StreamOptions::for_firmware(fw);
    opts.pause = Some(PauseSettings::new(VOLUME));
    let mut conn = Connection::open(sim.device_path(), &opts).await.unwrap();
    let (control, control_rx) = mpsc::channel(1);
    let (progress, mut rx) = watch::channel(PrintProgress::default());
    let print = conn.print(&program, control_rx, progress);
    tokio::pin!(print);
    let driver = async {
        wait_for(&mut rx, "waiting", |p| {
            p.state == PrintState::WaitingForOperator
        })
        .await;
        let at_pause = executed(&sim);
        control.send(StreamControl::Cancel).await.unwrap();
        at_pause
    };
    let (result, at_pause) = tokio::join!(&mut print, driver);
    match result {
        Err(PrintError::Cancelled { stop, .. }) => {
            assert_eq!(stop, crispen::marlin::stream::StopOutcome::Confirmed)
        }
        other => panic!("cancelled, not {other:?}"),
    }
    let stop = ["M104 S0", "M140 S0", "M107", "M84"].map(String::from);
    assert_eq!(executed(&sim), [&at_pause[..], &stop[..]].concat());
}

/// Without an operator to resume (`crispen print`), a file with a pause is refused before
/// anything is sent, naming the line and the command.
#[tokio::test]
async fn without_an_operator_a_file_pause_is_refused_before_anything_is_sent() {
    let fw = Firmware::Marlin2;
    let sim = sim::spawn(SimConfig::new(fw)).unwrap();
    let text = "G28\nG1 X10\n; colour change\nM600\nG1 X20\n";
    let program = GcodeProgram::read(text.as_bytes(), "colours.gcode", fw).unwrap();
    let opts = StreamOptions::for_firmware(fw);
    let mut conn = Connection::open(sim.device_path(), &opts).await.unwrap();
    let (_control, control_rx) = mpsc::channel(1);
    let (progress, _rx) = watch::channel(PrintProgress::default());
    let err = conn
        .print(&program, control_rx, progress)
        .await
        .expect_err("refused");
    let msg = err.to_string();
    assert!(
        msg.contains("colours.gcode:4") && msg.contains("`M600`"),
        "{msg}"
    );
    assert!(executed(&sim).is_empty(), "{:?}", executed(&sim));
}

/// The daemon end to end (the real binary, a simulated printer declared in the config): a
/// pre-sliced file with `M0` stops at exactly its line, the printer is shown waiting for
/// the operator with the file's message in the API's status, the heaters go off after
/// `pause_heaters_off_s` while the job keeps waiting, and the API's resume heats up again
/// and finishes the job with every line executed exactly once.
#[test]
fn the_daemon_shows_a_file_pause_and_the_api_resumes_it() {
    use crate::common::daemon::{drop_model, recorded, state_of, wait_for, Daemon};
    use crate::common::printer;
    let dir = tempfile::tempdir().unwrap();
    let root = dir.path();
    std::fs::create_dir_all(root.join("hot")).unwrap();
    let config = root.join("crispen.toml");
    let record = root.join("p.record");
    std::fs::write(
        &config,
        format!(
            "[spool]\ndir = \"spool\"\n[control]\nsocket = \"c.sock\"\n[farm]\nsettle_s = 0.3\n\
             [[machine]]\nname = \"parking\"\nbased_on = \"marlin-175\"\n\
             pause_gcode = \"park.gcode\"\nresume_gcode = \"resume.gcode\"\n\
             [[printer]]\nname = \"p\"\nmachine = \"parking\"\npause_heaters_off_s = 10\n\
             [printer.simulate]\ntime_scale = 0.0\nrecord = {:?}\n\
             [[folder]]\npath = \"hot\"\nheight_mm = 25\nprinters = [\"p\"]\n",
            record.display().to_string()
        ),
    )
    .unwrap();
    // The machine's own park (aside to the front left, lifted) and resume code (a fan).
    std::fs::write(
        root.join("park.gcode"),
        "; park for magnets\nG91\nG1 Z7 F600\nG90\nG1 X5 Y200 F6000\n",
    )
    .unwrap();
    std::fs::write(root.join("resume.gcode"), "M106 S128 ; cool the magnets\n").unwrap();
    let log = root.join("daemon.log");
    let _daemon = Daemon::start(&config, &log);
    // The first part without the end code (which cools down and turns the motors off).
    let before = crate::common::farm::presliced_gcode("before", 8, 1200);
    let mut gcode = before.replace("G1 Z10 F600\nM104 S0\nM84\n", "");
    assert_ne!(gcode, before);
    let tail = crate::common::farm::presliced_gcode("after", 8, 1200);
    gcode += "M117 Insert magnets\nM0\n";
    gcode += &tail;
    drop_model(&root.join("hot"), "magnets.gcode", gcode.as_bytes());

    let s = wait_for(
        &config,
        &log,
        Duration::from_secs(120),
        "waiting for the operator",
        |s| printer(s, "p")["state"] == "waiting_for_operator",
    );
    let p = printer(&s, "p");
    let detail = p["detail"].as_str().unwrap_or_default();
    assert!(
        detail.contains("Insert magnets") && detail.contains("crispen resume"),
        "{p}"
    );
    assert_eq!(p["progress"]["pause"]["message"], "Insert magnets", "{p}");
    assert_eq!(p["progress"]["pause"]["command"], "M0", "{p}");
    let file = GcodeProgram::read(gcode.as_bytes(), "magnets.gcode", Firmware::Marlin2)
        .unwrap()
        .to_vec();
    let pause = file.iter().position(|c| c == "M0").unwrap();
    let at_pause = recorded(&record);
    assert_eq!(
        at_pause[..pause],
        file[..pause],
        "every line before the pause, in order"
    );
    assert_eq!(
        at_pause[pause..],
        [
            "M400",
            "G90",
            "G91",
            "G1 Z7 F600",
            "G90",
            "G1 X5 Y200 F6000",
            "M400"
        ],
        "nothing after the pause but the machine's park"
    );

    let s = wait_for(&config, &log, Duration::from_secs(60), "heaters off", |s| {
        printer(s, "p")["progress"]["pause"]["heaters_off"] == true
    });
    assert_eq!(printer(&s, "p")["state"], "waiting_for_operator");
    assert_eq!(
        state_of(&s, "magnets.gcode"),
        "printing",
        "the job is not failed"
    );

    let (code, body) =
        crate::common::farm::http_on(&root.join("c.sock"), "POST", "/api/v1/printers/p/resume")
            .unwrap();
    assert_eq!(code, 200, "{body}");
    wait_for(
        &config,
        &log,
        Duration::from_secs(120),
        "the job done",
        |s| state_of(s, "magnets.gcode") == "done",
    );
    let all = recorded(&record);
    assert!(
        all.iter().all(|c| c != "M0"),
        "the pause never reached the printer"
    );
    // Every job line exactly once, in order: the lines before the pause, the host's own
    // lines (park, heaters off, reheat and return), then every line after it.
    let tail = &file[pause + 1..];
    assert_eq!(all[..pause], file[..pause]);
    assert!(all.ends_with(tail), "{all:?}");
    let host = &all[pause..all.len() - tail.len()];
    let off = host
        .iter()
        .position(|c| c == "M104 S0")
        .expect("heaters off");
    let reheat = host
        .iter()
        .position(|c| c == "M109 S200")
        .expect("reheated");
    assert!(off < reheat, "{host:?}");
    let fan = host
        .iter()
        .position(|c| c == "M106 S128")
        .expect("the machine's resume code");
    assert!(
        reheat < fan && host[fan + 1..].iter().any(|c| c.starts_with("G1 X")),
        "resume code after the reheat, before the return: {host:?}"
    );
    assert!(host.iter().all(|c| !c.starts_with("M118")), "{host:?}");
    let markers: Vec<&String> = all.iter().filter(|c| c.starts_with("M118")).collect();
    assert_eq!(markers, ["M118 before", "M118 after"]);
}
