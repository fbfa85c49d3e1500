//! The printer supervisors, the fleet, heating permits, reload and shutdown, tested on a
//! paused tokio clock: the real daemon code with only the printers replaced by bench
//! printers ([`super::doubles`]) and the job store a real spool in a temporary directory.
//! Simulated time runs ahead whenever every task waits, so a heat-up of minutes takes
//! milliseconds, and nothing depends on how fast the machine is.

use super::control::{self, Command};
use super::done::Done;
use super::doubles::{farm_config, open_farm, ready_job, until, BenchPorts, SAFE_STOP};
use super::farm::{Farm, PrinterState, PrinterStatus};
use super::fleet::{Fleet, Port};
use super::job::{Job, JobState};
use super::printer::{BoxFuture, ConnectError, Connector, PrinterLink};
use std::sync::Arc;
use std::time::Duration;

/// Heats the bed to 60 °C and the hotend to 200 °C (100 s on the bench), then prints.
const HEAT_AND_PRINT: &str =
    "M140 S60\nM104 S200\nM190 S60\nM109 S200\nG28\nG1 X10 E5\nG1 X20 E6\nG1 X30 E7\n";

fn lines(gcode: &str) -> Vec<String> {
    gcode.lines().map(str::to_string).collect()
}

/// A long print: `moves` moves after the heat-up (each 0.1 s on the bench).
fn long_print(moves: usize) -> String {
    let mut g = String::from(HEAT_AND_PRINT);
    for i in 0..moves {
        g += &format!("G1 X{} E{}\n", i % 100, i + 10);
    }
    g
}

fn printer(farm: &Farm, name: &str) -> Option<PrinterStatus> {
    farm.local_printers().into_iter().find(|p| p.name == name)
}

fn state(farm: &Farm, id: &str) -> JobState {
    farm.store().get(id).unwrap().state
}

const LIMIT: Duration = Duration::from_secs(3600);

/// The supervisor's cycle: it connects, takes the ready job, sends its every line once
/// in order, records it done, and then holds the next job while the bed is not cleared,
/// however long; the operator's clear lets it take the next.
#[tokio::test(start_paused = true)]
async fn a_printer_prints_then_waits_for_its_bed_to_be_cleared() {
    let tmp = tempfile::tempdir().unwrap();
    let (farm, owners) = open_farm(farm_config(tmp.path(), &["p1"], ""));
    let bench = BenchPorts::default();
    let fleet = Fleet::start_all(
        &farm,
        owners.printers,
        &farm.config().printers,
        bench.ports(),
    )
    .unwrap();
    let first = ready_job(&farm, "a.stl", HEAT_AND_PRINT).await;
    until(&farm, LIMIT, "the first job done", || {
        state(&farm, &first) == JobState::Done
    })
    .await;
    assert_eq!(bench.printer("p1").job_lines(), lines(HEAT_AND_PRINT));
    until(&farm, LIMIT, "the bed shown not cleared", || {
        printer(&farm, "p1").is_some_and(|p| p.state == PrinterState::BedNotCleared)
    })
    .await;
    let p1 = printer(&farm, "p1").unwrap();
    assert!(!p1.bed_cleared);
    assert_eq!(p1.job.as_deref(), Some(first.as_str()));

    let second = ready_job(&farm, "b.stl", HEAT_AND_PRINT).await;
    tokio::time::sleep(Duration::from_secs(600)).await;
    assert_eq!(
        state(&farm, &second),
        JobState::Ready,
        "held by the bed gate"
    );
    assert_eq!(
        bench.printer("p1").job_lines().len(),
        lines(HEAT_AND_PRINT).len()
    );

    let said = control::execute(
        &farm,
        Command::Clear {
            printer: "p1".into(),
        },
    )
    .await
    .unwrap();
    assert_eq!(
        said,
        Done::Cleared {
            printer: "p1".into(),
            already: false
        }
    );
    until(&farm, LIMIT, "the second job done", || {
        state(&farm, &second) == JobState::Done
    })
    .await;
    assert_eq!(
        bench.printer("p1").job_lines(),
        [lines(HEAT_AND_PRINT), lines(HEAT_AND_PRINT)].concat()
    );
    assert_eq!(bench.printer("p1").connects(), 1);
    owners.stop.begin();
    fleet.join().await;
    assert_eq!(printer(&farm, "p1").unwrap().state, PrinterState::Stopped);
}

/// Two printers, one heating permit: the second starts only once the first's heat-up is
/// done (its heat-and-wait lines acknowledged), and then both print.
#[tokio::test(start_paused = true)]
async fn one_heating_permit_staggers_two_heat_ups() {
    let tmp = tempfile::tempdir().unwrap();
    let config = farm_config(tmp.path(), &["p1", "p2"], "[farm]\nmax_heating = 1\n");
    let (farm, owners) = open_farm(config);
    let bench = BenchPorts::default();
    let fleet = Fleet::start_all(
        &farm,
        owners.printers,
        &farm.config().printers,
        bench.ports(),
    )
    .unwrap();
    let a = ready_job(&farm, "a.stl", &long_print(600)).await;
    let b = ready_job(&farm, "b.stl", &long_print(600)).await;
    let mut waited = false;
    let deadline = tokio::time::Instant::now() + LIMIT;
    // Looked at after each change of the farm.
    let mut changes = farm.watch();
    while state(&farm, &a) != JobState::Done || state(&farm, &b) != JobState::Done {
        assert!(tokio::time::Instant::now() < deadline, "both printed");
        let shown = farm.local_printers();
        let heating: Vec<&str> = shown
            .iter()
            .filter(|p| {
                p.state == PrinterState::Printing && p.progress.as_ref().is_some_and(|l| !l.heated)
            })
            .map(|p| p.name.as_str())
            .collect();
        assert!(heating.len() <= 1, "two heat-ups at once: {heating:?}");
        if shown.iter().any(|p| p.state == PrinterState::WaitingToHeat) {
            waited = true;
            // Nothing of the waiting printer's job was sent.
            let other = shown
                .iter()
                .find(|p| p.state == PrinterState::WaitingToHeat)
                .unwrap();
            assert!(bench.printer(&other.name).job_lines().is_empty());
        }
        tokio::time::timeout_at(deadline, changes.changed())
            .await
            .expect("both printed");
    }
    assert!(waited, "one printer waited for the permit");
    assert_eq!(farm.heating.in_use(), 0, "permits handed back");
    owners.stop.begin();
    fleet.join().await;
}

/// Shutdown with `on_shutdown = "stop"`: the token stops the print in progress through
/// the safe stop (heaters, fan and motors off), the job ends interrupted, and every task
/// (supervisors, preparation) ends.
#[tokio::test(start_paused = true)]
async fn shutdown_stops_prints_safely_and_ends_every_task() {
    let tmp = tempfile::tempdir().unwrap();
    let config = farm_config(tmp.path(), &["p1"], "[farm]\non_shutdown = \"stop\"\n");
    let (farm, owners) = open_farm(config);
    let bench = BenchPorts::default();
    let fleet = Fleet::start_all(
        &farm,
        owners.printers,
        &farm.config().printers,
        bench.ports(),
    )
    .unwrap();
    let preparation = tokio::spawn(super::prepare::queue::prepare_loop(
        Arc::clone(&farm),
        owners.preparing,
        "/nonexistent/crispen".into(),
    ));
    let job = ready_job(&farm, "a.stl", &long_print(10_000)).await;
    past_the_heat_up(&farm).await;
    owners.stop.begin();
    tokio::time::timeout(Duration::from_secs(60), fleet.join())
        .await
        .expect("the supervisor ends");
    tokio::time::timeout(Duration::from_secs(60), preparation)
        .await
        .expect("the preparation loop ends")
        .unwrap();
    let stored = cut_short_by_the_safe_stop(&bench, &farm, &job);
    let reason = stored.reason.unwrap_or_default();
    assert!(reason.contains("stopped safely at shutdown"), "{reason}");
    assert_eq!(printer(&farm, "p1").unwrap().state, PrinterState::Stopped);
}

/// Waits until `p1` prints past its heat-up.
async fn past_the_heat_up(farm: &Farm) {
    until(farm, LIMIT, "printing past the heat-up", || {
        printer(farm, "p1")
            .and_then(|p| p.progress)
            .is_some_and(|l| l.heated)
    })
    .await;
}

/// The 10,000-line print on `p1` was cut short by the safe stop's lines; its job
/// (returned) is interrupted.
fn cut_short_by_the_safe_stop(bench: &BenchPorts, farm: &Farm, job: &str) -> Job {
    let sent = bench.printer("p1").job_lines();
    assert_eq!(
        sent[sent.len() - SAFE_STOP.len()..],
        SAFE_STOP.map(String::from)
    );
    assert!(sent.len() < 10_000, "cut short: {} lines", sent.len());
    let stored = farm.store().get(job).unwrap().clone();
    assert_eq!(stored.state, JobState::Interrupted);
    stored
}

/// Shutdown with `on_shutdown = "finish"`: the print goes on after the stop began, until
/// `StopOwner::stop_prints` (a second SIGTERM, or `finish_timeout_s` run out) stops it through
/// the same safe stop as "stop".
#[tokio::test(start_paused = true)]
async fn a_finishing_print_goes_on_until_the_prints_are_stopped() {
    let tmp = tempfile::tempdir().unwrap();
    let config = farm_config(tmp.path(), &["p1"], "[farm]\non_shutdown = \"finish\"\n");
    let (farm, owners) = open_farm(config);
    let bench = BenchPorts::default();
    let fleet = Fleet::start_all(
        &farm,
        owners.printers,
        &farm.config().printers,
        bench.ports(),
    )
    .unwrap();
    let job = ready_job(&farm, "a.stl", &long_print(10_000)).await;
    let acked = |farm: &Farm| {
        printer(farm, "p1")
            .and_then(|p| p.progress)
            .map_or(0, |l| l.lines_acked)
    };
    past_the_heat_up(&farm).await;
    owners.stop.begin();
    let at_stop = acked(&farm);
    until(&farm, LIMIT, "the print going on", || {
        acked(&farm) > at_stop + 100
    })
    .await;
    assert!(!farm.stop_prints.is_cancelled());
    owners.stop.stop_prints();
    tokio::time::timeout(Duration::from_secs(60), fleet.join())
        .await
        .expect("the supervisor ends");
    cut_short_by_the_safe_stop(&bench, &farm, &job);
}

/// A reload adds a printer at once and removes an idle one at once while another prints,
/// and a printer removed while it prints finishes its print (every line, no stop) before
/// it leaves the farm.
#[tokio::test(start_paused = true)]
async fn a_reload_never_cuts_a_print_short() {
    let tmp = tempfile::tempdir().unwrap();
    let (farm, owners) = open_farm(farm_config(tmp.path(), &["p1"], ""));
    let bench = BenchPorts::default();
    let mut fleet = Fleet::start_all(
        &farm,
        owners.printers,
        &farm.config().printers,
        bench.ports(),
    )
    .unwrap();
    let gcode = long_print(3000);
    let job = ready_job(&farm, "a.stl", &gcode).await;
    until(&farm, LIMIT, "p1 printing", || {
        printer(&farm, "p1").is_some_and(|p| p.state == PrinterState::Printing)
    })
    .await;

    // p2 added.
    let both = farm_config(tmp.path(), &["p1", "p2"], "");
    owners.config.set(both.clone());
    fleet.apply(&both.printers);
    until(&farm, LIMIT, "p2 connected", || {
        printer(&farm, "p2").is_some_and(|p| p.state == PrinterState::Idle)
    })
    .await;

    // p2 removed while p1 prints: p2 leaves at once, p1 prints on.
    let only_p1 = farm_config(tmp.path(), &["p1"], "");
    owners.config.set(only_p1.clone());
    fleet.apply(&only_p1.printers);
    tokio::select! {
        (name, how) = fleet.next_end() => panic!("{name}'s supervisor ended: {how:?}"),
        () = until(&farm, LIMIT, "p2 gone from the farm", || printer(&farm, "p2").is_none()) => {}
    }
    assert_eq!(printer(&farm, "p1").unwrap().state, PrinterState::Printing);

    // p2 back, and p1 removed while it prints: it goes on to the end, then leaves.
    let only_p2 = farm_config(tmp.path(), &["p2"], "");
    owners.config.set(only_p2.clone());
    fleet.apply(&only_p2.printers);
    assert_eq!(printer(&farm, "p1").unwrap().state, PrinterState::Printing);
    tokio::select! {
        (name, how) = fleet.next_end() => panic!("{name}'s supervisor ended: {how:?}"),
        () = until(&farm, LIMIT, "p1 gone from the farm", || printer(&farm, "p1").is_none()) => {}
    }
    assert_eq!(state(&farm, &job), JobState::Done);
    assert_eq!(bench.printer("p1").job_lines(), lines(&gcode));
    assert!(printer(&farm, "p2").is_some());
    owners.stop.begin();
    fleet.join().await;
}

/// A printer supervisor that panics is reported by the fleet, named, with the panic
/// (the service stops on it, see `service::failure_of_printer`); the other printers go on.
#[tokio::test(start_paused = true)]
async fn a_panicking_supervisor_is_reported_by_name() {
    struct Panics;
    impl Connector for Panics {
        fn connect(&self) -> BoxFuture<'_, Result<Box<dyn PrinterLink>, ConnectError>> {
            Box::pin(async {
                tokio::time::sleep(Duration::from_secs(5)).await;
                panic!("the link broke its promise")
            })
        }
    }
    let tmp = tempfile::tempdir().unwrap();
    let (farm, owners) = open_farm(farm_config(tmp.path(), &["good", "bad"], ""));
    let bench = BenchPorts::default();
    let ports = bench.ports();
    let mut fleet = Fleet::start_all(
        &farm,
        owners.printers,
        &farm.config().printers,
        Box::new(move |spec| {
            if spec.name == "bad" {
                Ok(Port {
                    connector: Box::new(Panics),
                    shown: "bench:bad".into(),
                    keep: None,
                })
            } else {
                ports(spec)
            }
        }),
    )
    .unwrap();
    let (name, how) = fleet.next_end().await;
    assert_eq!(name, "bad");
    let panic = how.expect_err("it panicked").into_panic();
    assert_eq!(
        panic.downcast_ref::<&str>(),
        Some(&"the link broke its promise")
    );
    assert_eq!(printer(&farm, "good").unwrap().state, PrinterState::Idle);
    owners.stop.begin();
    fleet.join().await;
}

/// A retry is counted by the store's task like every change, once, in the snapshot
/// that publishes it (it once went to the store past the farm's wrapper that counted
/// changes: no `job state` line, no count).
#[tokio::test(start_paused = true)]
async fn a_retry_is_announced_and_counted() {
    let tmp = tempfile::tempdir().unwrap();
    let (farm, _) = open_farm(farm_config(tmp.path(), &["p1"], ""));
    let job = ready_job(&farm, "a.stl", HEAT_AND_PRINT).await;
    farm.jobs()
        .transition(&job, JobState::Cancelled, None)
        .await
        .unwrap();
    let all = |farm: &Farm| -> u64 {
        let counts = farm.store().counts();
        JobState::ALL.iter().map(|s| counts.entered(*s)).sum()
    };
    let queued = || farm.store().counts().entered(JobState::Queued);
    let (before, queued_before) = (all(&farm), queued());
    control::execute(
        &farm,
        Command::Retry {
            job: job.clone(),
            copy: None,
        },
    )
    .await
    .unwrap();
    // Prepared again (the spool keeps no slice report for this hand-made job).
    assert_eq!(state(&farm, &job), JobState::Queued);
    assert_eq!(queued(), queued_before + 1);
    assert_eq!(all(&farm), before + 1, "one change, counted once");
}

/// Shutdown while a printer waits for its heating permit: nothing is sent to it, and its
/// job goes back to ready for the next start.
#[tokio::test(start_paused = true)]
async fn shutdown_while_waiting_to_heat_sends_nothing() {
    let tmp = tempfile::tempdir().unwrap();
    let extra = "[farm]\nmax_heating = 1\non_shutdown = \"stop\"\n";
    let (farm, owners) = open_farm(farm_config(tmp.path(), &["p1", "p2"], extra));
    let bench = BenchPorts::default();
    let fleet = Fleet::start_all(
        &farm,
        owners.printers,
        &farm.config().printers,
        bench.ports(),
    )
    .unwrap();
    ready_job(&farm, "a.stl", &long_print(100)).await;
    ready_job(&farm, "b.stl", &long_print(100)).await;
    until(&farm, LIMIT, "one heating, one waiting", || {
        let states: Vec<PrinterState> = farm.local_printers().iter().map(|p| p.state).collect();
        states.contains(&PrinterState::Printing) && states.contains(&PrinterState::WaitingToHeat)
    })
    .await;
    let waiting = farm
        .local_printers()
        .into_iter()
        .find(|p| p.state == PrinterState::WaitingToHeat)
        .unwrap();
    let job = waiting.job.clone().unwrap();
    owners.stop.begin();
    tokio::time::timeout(Duration::from_secs(60), fleet.join())
        .await
        .expect("the supervisors end");
    assert!(bench.printer(&waiting.name).job_lines().is_empty());
    assert_eq!(state(&farm, &job), JobState::Ready);
}

/// A printer unplugged mid-print: the job ends interrupted (never reprinted on its own),
/// the printer shows disconnected and is connected again once plugged in, with its bed
/// gate closed.
#[tokio::test(start_paused = true)]
async fn an_unplugged_printer_interrupts_its_job_and_reconnects() {
    let tmp = tempfile::tempdir().unwrap();
    let (farm, owners) = open_farm(farm_config(tmp.path(), &["p1"], ""));
    let bench = BenchPorts::default();
    let fleet = Fleet::start_all(
        &farm,
        owners.printers,
        &farm.config().printers,
        bench.ports(),
    )
    .unwrap();
    let job = ready_job(&farm, "a.stl", &long_print(1000)).await;
    past_the_heat_up(&farm).await;
    bench.printer("p1").unplug();
    until(&farm, LIMIT, "the job interrupted", || {
        state(&farm, &job) == JobState::Interrupted
    })
    .await;
    until(&farm, LIMIT, "shown disconnected", || {
        printer(&farm, "p1").is_some_and(|p| p.state == PrinterState::Disconnected)
    })
    .await;
    let reason = farm.store().get(&job).unwrap().reason.clone().unwrap();
    assert!(reason.contains("unplugged"), "{reason}");
    tokio::time::sleep(Duration::from_secs(120)).await;
    assert!(bench.printer("p1").connects() > 2, "it keeps trying");
    bench.printer("p1").plug_in();
    until(&farm, LIMIT, "connected again, bed not cleared", || {
        printer(&farm, "p1").is_some_and(|p| p.state == PrinterState::BedNotCleared)
    })
    .await;
    assert!(!printer(&farm, "p1").unwrap().bed_cleared);
    owners.stop.begin();
    fleet.join().await;
}

/// Pause, resume and cancel reach the print through the farm's operations: paused, no
/// line is sent however long; resumed, it goes on; cancelled, the safe stop is sent and
/// the job ends cancelled with the bed gate closed.
#[tokio::test(start_paused = true)]
async fn pause_resume_and_cancel_reach_the_print() {
    let tmp = tempfile::tempdir().unwrap();
    let (farm, owners) = open_farm(farm_config(tmp.path(), &["p1"], ""));
    let bench = BenchPorts::default();
    let fleet = Fleet::start_all(
        &farm,
        owners.printers,
        &farm.config().printers,
        bench.ports(),
    )
    .unwrap();
    let job = ready_job(&farm, "a.stl", &long_print(5000)).await;
    past_the_heat_up(&farm).await;
    let p1 = || Command::Pause {
        printer: "p1".into(),
    };
    control::execute(&farm, p1()).await.unwrap();
    until(&farm, LIMIT, "shown paused", || {
        printer(&farm, "p1").is_some_and(|p| p.state == PrinterState::Paused)
    })
    .await;
    let sent = bench.printer("p1").job_lines().len();
    tokio::time::sleep(Duration::from_secs(300)).await;
    assert_eq!(
        bench.printer("p1").job_lines().len(),
        sent,
        "nothing sent while paused"
    );
    control::execute(
        &farm,
        Command::Resume {
            printer: "p1".into(),
        },
    )
    .await
    .unwrap();
    until(&farm, LIMIT, "printing again", || {
        bench.printer("p1").job_lines().len() > sent + 10
    })
    .await;
    let said = control::execute(
        &farm,
        Command::Cancel {
            job: job.clone(),
            copy: None,
        },
    )
    .await
    .unwrap();
    assert_eq!(
        said,
        Done::Stopping {
            job: job.clone(),
            printer: "p1".into()
        }
    );
    until(&farm, LIMIT, "cancelled", || {
        state(&farm, &job) == JobState::Cancelled
    })
    .await;
    let lines = bench.printer("p1").job_lines();
    assert_eq!(
        lines[lines.len() - SAFE_STOP.len()..],
        SAFE_STOP.map(String::from)
    );
    assert!(lines.len() < 5000);
    assert!(!printer(&farm, "p1").unwrap().bed_cleared);
    let e = control::execute(&farm, p1()).await.unwrap_err();
    assert!(e.to_string().contains("p1 is not printing"), "{e}");
    owners.stop.begin();
    fleet.join().await;
}

/// A printer whose firmware halted (here at an `M112` in its job) is shown halted with the
/// firmware's message and takes no job, even once its bed is cleared, until it was reset
/// (its `start` seen on the link); then it prints the next job.
#[tokio::test(start_paused = true)]
async fn a_halted_printer_takes_no_job_until_it_was_reset() {
    let tmp = tempfile::tempdir().unwrap();
    let (farm, owners) = open_farm(farm_config(tmp.path(), &["p1"], ""));
    let bench = BenchPorts::default();
    let fleet = Fleet::start_all(
        &farm,
        owners.printers,
        &farm.config().printers,
        bench.ports(),
    )
    .unwrap();
    let first = ready_job(&farm, "a.stl", "G28\nM112\nG1 X10\n").await;
    until(&farm, LIMIT, "the halted job failed", || {
        state(&farm, &first) == JobState::Failed
    })
    .await;
    until(&farm, LIMIT, "the printer shown halted", || {
        printer(&farm, "p1").is_some_and(|p| p.state == PrinterState::Halted)
    })
    .await;
    let p1 = printer(&farm, "p1").unwrap();
    assert!(
        p1.detail
            .as_deref()
            .is_some_and(|d| d.contains("kill() called")),
        "{p1:?}"
    );
    control::execute(
        &farm,
        Command::Clear {
            printer: "p1".into(),
        },
    )
    .await
    .unwrap();
    let second = ready_job(&farm, "b.stl", HEAT_AND_PRINT).await;
    tokio::time::sleep(Duration::from_secs(600)).await;
    assert_eq!(
        state(&farm, &second),
        JobState::Ready,
        "no job while halted"
    );
    assert_eq!(printer(&farm, "p1").unwrap().state, PrinterState::Halted);
    assert_eq!(bench.printer("p1").job_lines(), lines("G28\nM112"));
    assert!(bench.printer("p1").halted());

    bench.printer("p1").reset();
    until(&farm, LIMIT, "the next job done after the reset", || {
        state(&farm, &second) == JobState::Done
    })
    .await;
    owners.stop.begin();
    fleet.join().await;
}

/// A job that fails at load (its G-code cannot be read) sent the printer nothing: the
/// printer waits for no bed clear and takes the next job at once.
#[tokio::test(start_paused = true)]
async fn a_job_that_sent_nothing_leaves_no_bed_to_clear() {
    let tmp = tempfile::tempdir().unwrap();
    let (farm, owners) = open_farm(farm_config(tmp.path(), &["p1"], ""));
    let bench = BenchPorts::default();
    let first = ready_job(&farm, "a.stl", HEAT_AND_PRINT).await;
    let machine = farm.config().printers[0].machine.name.clone();
    let gcode = farm
        .store()
        .job_dir(&first)
        .join(format!("a.stl.{machine}.gcode"));
    std::fs::remove_file(gcode).unwrap();
    let fleet = Fleet::start_all(
        &farm,
        owners.printers,
        &farm.config().printers,
        bench.ports(),
    )
    .unwrap();
    until(&farm, LIMIT, "the unreadable job failed", || {
        state(&farm, &first) == JobState::Failed
    })
    .await;
    let second = ready_job(&farm, "b.stl", HEAT_AND_PRINT).await;
    until(&farm, LIMIT, "the next job done without a clear", || {
        state(&farm, &second) == JobState::Done
    })
    .await;
    assert_eq!(bench.printer("p1").job_lines(), lines(HEAT_AND_PRINT));
    owners.stop.begin();
    fleet.join().await;
}
