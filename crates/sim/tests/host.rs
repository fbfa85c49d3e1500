//! The host's side (`crispen-marlin`'s `Connection`) against the simulated printer, where
//! only the two together show a behaviour.

use crispen_marlin::firmware::Firmware;
use crispen_marlin::gcode::GcodeProgram;
use crispen_marlin::stream::{Connection, PrintProgress, StreamOptions};
use crispen_sim::{is_housekeeping, spawn, SimConfig};
use std::time::Duration;
use tokio::sync::{mpsc, watch};

/// An idle `M105` whose answer is still on its way when a job starts: the job waits
/// for it, so its `ok` is never taken for the job's `M110` (and every later `ok` for
/// the line before its own). Checked on a link with a real round trip (300 ms each
/// way), for every firmware flavour: the host never counts a job line acknowledged
/// before the printer has executed it, no line is resent, and each runs exactly once.
#[tokio::test]
async fn an_idle_m105_in_flight_when_a_job_starts_is_not_taken_for_its_answers() {
    // Ten lines: an answer taken for the wrong line shows at the first ones, and each
    // line costs two 300 ms link delays.
    let commands: Vec<String> = (0..10)
        .map(|i| match i % 2 {
            0 => format!("M106 S{}", i * 8),
            _ => "M107".to_string(),
        })
        .collect();
    let program = GcodeProgram::from_commands("fans.gcode", commands.clone());
    for firmware in [Firmware::Marlin20, Firmware::Ultimaker2, Firmware::Marlin2] {
        let mut sim = SimConfig::new(firmware);
        sim.link_latency = Duration::from_millis(300);
        let printer = spawn(sim).unwrap();
        let opts = StreamOptions::for_firmware(firmware);
        let mut conn = Connection::open(printer.device_path(), &opts)
            .await
            .unwrap();
        // The first poll goes at once; the watch is cut short (as the daemon's is when
        // a job arrives) long before its answer can be back.
        let watched = tokio::time::timeout(
            Duration::from_millis(50),
            conn.idle_for(Duration::from_secs(60)),
        )
        .await;
        assert!(watched.is_err(), "{firmware:?}: nothing came back in 50 ms");

        let (progress_tx, mut progress_rx) = watch::channel(PrintProgress::default());
        let (_control, control_rx) = mpsc::channel(1);
        let print = conn.print(&program, control_rx, progress_tx);
        tokio::pin!(print);
        let executed_job_lines = || {
            printer
                .executed()
                .iter()
                .filter(|c| !is_housekeeping(c))
                .count()
        };
        let mut ahead = None;
        let report = loop {
            tokio::select! {
                report = &mut print => break report,
                Ok(()) = progress_rx.changed() => {
                    let acked = progress_rx.borrow_and_update().lines_acked;
                    // Read after the figure: the printer's count can only have grown.
                    let executed = executed_job_lines();
                    if acked > executed {
                        ahead.get_or_insert((acked, executed));
                    }
                }
            }
        };
        let report = report.unwrap_or_else(|e| panic!("{firmware:?}: {e}"));
        assert_eq!(
            ahead, None,
            "{firmware:?}: (lines the host counted acknowledged, lines the printer had run)"
        );
        assert_eq!(report.resends, 0, "{firmware:?}");
        let job: Vec<String> = printer
            .executed()
            .into_iter()
            .filter(|c| !is_housekeeping(c))
            .collect();
        assert_eq!(job, commands, "{firmware:?}: every line once, in order");
        // The poll went before the job: the printer ran an M105 before the job's first
        // line, which it got 300 ms after the poll was sent, as its answer was 300 ms away.
        let executed = printer.executed();
        let first = executed.iter().position(|c| *c == commands[0]).unwrap();
        assert!(
            executed[..first].iter().any(|c| c == "M105"),
            "{firmware:?}: no M105 before the job: {executed:?}"
        );
    }
}
