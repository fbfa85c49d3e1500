//! A printer whose line count is no longer the host's, and stops that must work anyway.
//! Marlin 2.1.2.1 takes any numbered line with `M110` in it for a new count
//! (queue.cpp:463-470): after `M117 M110 N999` it refuses every later line with `Last
//! Line: 999`, `Resend: 1000`, `ok`. The host once counted those `ok`s as progress, showed
//! 100 % and held the heaters on, and its cancel went out as numbered lines the printer
//! refused. Each order of events, on a fake clock.

use super::*;

/// The job's line after which the printer counts from elsewhere.
const MARK: &str = "M117 renumbered";

/// `job(30)` with [`MARK`] as its 11th command.
fn marked_job() -> Vec<String> {
    let mut commands = job(30);
    commands.insert(10, MARK.into());
    commands
}

/// A printer of `fw` as the tests' printer models it (ADVANCED_OK or not, an `ok` after
/// `Resend:` where the firmware prints one).
fn printer_of(fw: Firmware, advanced: bool) -> MiniPrinter {
    let mut printer = MiniPrinter::new();
    printer.advanced = advanced;
    printer.ok_after_resend = fw.ok_after_resend();
    printer
}

fn every_profile() -> Vec<(Firmware, bool)> {
    vec![
        (Firmware::Marlin2, false),
        (Firmware::Marlin2, true),
        (Firmware::Marlin20, false),
        (Firmware::Ultimaker2, false),
    ]
}

fn progress_shown(events: &[Event]) -> usize {
    events
        .iter()
        .filter_map(|e| match e {
            Event::Progress { acked, .. } => Some(*acked),
            _ => None,
        })
        .max()
        .unwrap_or(0)
}

/// What the printer ran after the job's lines up to `through` (their count): the stop's
/// lines only, the unnumbered heaters off among them.
fn assert_only_the_stop_ran_after(printer: &MiniPrinter, commands: &[String], through: usize) {
    let executed = printer.job_executed();
    assert_eq!(&executed[..through], &commands[..through]);
    let after = &executed[through..];
    let stop = ["M108", "M104 S0", "M140 S0", "M107", "M84"];
    assert!(
        after.iter().all(|c| stop.contains(&c.as_str())),
        "{after:?}"
    );
    for line in SAFE_STOP {
        assert!(after.iter().any(|c| c == line), "{line} missing: {after:?}");
    }
}

#[test]
fn a_printer_renumbered_ahead_is_stopped_and_the_job_fails_with_what_happened() {
    for (fw, advanced) in every_profile() {
        let (mut host, _, now) = connected(opts(fw));
        let mut printer = printer_of(fw, advanced);
        // The host's numbers continue from the greeting; the printer's count too.
        printer.expected = 2;
        printer.renumber_at = Some((MARK.into(), 999));
        let commands = marked_job();
        host.start_job(commands.clone(), now);
        let events = run_job(&mut host, &mut printer, now);
        let Some(Failure::LostNumbering { what, last_acked }) = failure(&events) else {
            panic!("{fw} {advanced}: {:?}", failure(&events));
        };
        assert!(
            matches!(
                what,
                Numbering::AheadOfHost {
                    requested: 1000,
                    last_line: Some(999),
                    ..
                }
            ),
            "{fw}: {what:?}"
        );
        assert!(*last_acked <= 11, "{fw}: {last_acked}");
        assert!(
            progress_shown(&events) <= 11,
            "{fw}: no progress for refused lines"
        );
        assert!(
            events.contains(&Event::SafeStop { confirmed: true }),
            "{fw}"
        );
        assert_only_the_stop_ran_after(&printer, &commands, 11);
    }
}

#[test]
fn a_printer_whose_count_went_back_is_stopped_rather_than_sent_lines_again() {
    // Renumbered lower, and to 0.
    for last in [3, 0] {
        for (fw, advanced) in every_profile() {
            let (mut host, _, now) = connected(opts(fw));
            let mut printer = printer_of(fw, advanced);
            printer.expected = 2;
            printer.renumber_at = Some((MARK.into(), last));
            let commands = marked_job();
            host.start_job(commands.clone(), now);
            let events = run_job(&mut host, &mut printer, now);
            match failure(&events) {
                Some(Failure::LostNumbering {
                    what: Numbering::WentBack { requested, .. },
                    ..
                }) => assert_eq!(*requested, last + 1, "{fw}"),
                // An answered `M105` or `ok N<n>` had confirmed those lines: the same
                // stop, named so.
                Some(Failure::LostState { line, .. }) => assert_eq!(*line, last + 1),
                other => panic!("{fw} {advanced} to {last}: {other:?}"),
            }
            assert!(
                events.contains(&Event::SafeStop { confirmed: true }),
                "{fw}"
            );
            // Nothing ran twice: the lines it asked for again were not sent again.
            assert_only_the_stop_ran_after(&printer, &commands, 11);
        }
    }
}

/// Stock Marlin 2.1.2.1's order, byte for byte: errors are printed when a line is read,
/// `ok`s when a command is done, so the refusals of the lines behind the renumbering line
/// can come before or after its own `ok`; Marlin 2.0 prints no `ok` after `Resend:`; any
/// split of the bytes.
#[test]
fn each_order_of_the_refusals_ends_the_same_way() {
    let block = "Error:Line Number is not Last Line Number+1, Last Line: 999\nResend: 1000\n";
    let orders: [(&str, Firmware, String); 4] = [
        (
            "refusals first",
            Firmware::Marlin2,
            format!("{block}ok\n{block}ok\nok\n"),
        ),
        (
            "its own ok first",
            Firmware::Marlin2,
            format!("ok\n{block}ok\n{block}ok\n"),
        ),
        (
            "no ok after Resend",
            Firmware::Marlin20,
            format!("{block}{block}ok\n"),
        ),
        (
            "ultimaker2",
            Firmware::Ultimaker2,
            format!("ok\n{block}ok\n{block}ok\n"),
        ),
    ];
    for (name, fw, answer) in orders {
        for split in 0..=answer.len() {
            let mut o = opts(fw);
            o.uncuttable_lines = false;
            let (mut host, _, now) = connected(o);
            let commands = vec![MARK.to_string(), "G1 X1".into(), "G1 X2".into()];
            host.start_job(commands, now);
            // The job's M110 answered, then the rest goes out in one write: any line
            // before the three job lines (M155) is answered first.
            let mut before = 0;
            for _ in 0..10 {
                let out = sent(&mut host);
                if out.contains("G1 X2") {
                    before = out.lines().take_while(|l| !l.contains(MARK)).count();
                    break;
                }
                for _ in out.lines() {
                    host.feed(b"ok\n", now);
                }
            }
            let acked_before = host.acked_job_lines();
            let answer = "ok\n".repeat(before) + &answer;
            host.feed(&answer.as_bytes()[..split.min(answer.len())], now);
            host.feed(&answer.as_bytes()[split.min(answer.len())..], now);
            let out = sent(&mut host);
            // Heaters off at once, without a number; then a new count, alone (after what
            // went out before the refusals came, an M73 of the progress).
            let unnumbered = if fw.reads_serial_while_heating() {
                "M108\nM104 S0\nM140 S0\nN"
            } else {
                "M104 S0\nM140 S0\nN"
            };
            let at = out
                .find(unnumbered)
                .unwrap_or_else(|| panic!("{name} {split}: {out:?}"));
            assert!(out[at..].contains(" M110 N"), "{name} {split}: {out:?}");
            // Only the renumbering line itself may be counted, never a refused one.
            assert!(
                host.acked_job_lines() <= (acked_before + 1).max(1),
                "{name} {split}"
            );
            host.outgoing.splice(0..0, out.bytes());
            let executed = answer_safe_stop(&mut host, now);
            assert_safe_stop(&executed);
            let events = drain_events(&mut host);
            assert!(
                matches!(
                    failure(&events),
                    Some(Failure::LostNumbering {
                        what: Numbering::AheadOfHost {
                            requested: 1000,
                            ..
                        },
                        ..
                    })
                ),
                "{name} {split}: {events:?}"
            );
            assert!(events.contains(&Event::SafeStop { confirmed: true }));
        }
    }
}

/// A request for a line beyond any the host sent, with no error naming the line before it
/// (a garbled number): ignored, and the `ok` printed with it is no line's. Three in a
/// row, each for a line sent and unanswered, with no line answered between, are no
/// accident: the printer counts from elsewhere.
#[test]
fn a_resend_for_a_future_line_is_ignored_once_and_stops_the_job_when_repeated() {
    let mut o = opts(Firmware::Marlin2);
    o.send_ahead = false;
    let (mut host, mut printer, now) = connected(o.clone());
    printer.expected = 2;
    let commands = job(20);
    host.start_job(commands.clone(), now);
    exchange(&mut host, &mut printer, now, 6);
    let acked = host.acked_job_lines();
    assert!(acked > 0);
    // One line on its way: the printer runs it, its `ok` not yet back.
    let answer = printer.receive(&host.take_outgoing());
    host.feed(b"Resend: 500\nok\n", now);
    assert_eq!(
        host.acked_job_lines(),
        acked,
        "the ok of a refusal is no progress"
    );
    host.feed(&answer, now);
    let events = run_job(&mut host, &mut printer, now);
    assert!(done(&events), "{:?}", failure(&events));
    assert_eq!(printer.job_executed(), commands);

    // Every line refused so, its error lines lost: the third refusal stops the job.
    let (mut host, _, now) = connected(o);
    let mut printer = MiniPrinter::new();
    printer.expected = 2;
    let commands = marked_job();
    printer.refuse_after = Some((MARK.into(), "Error:\u{1}\nResend: 500\nok\n".into()));
    host.start_job(commands.clone(), now);
    let events = run_job(&mut host, &mut printer, now);
    assert!(
        matches!(
            failure(&events),
            Some(Failure::LostNumbering {
                what: Numbering::NoAdvance { refusals: 3, .. },
                ..
            })
        ),
        "{events:?}"
    );
    assert!(events.contains(&Event::SafeStop { confirmed: true }));
    assert!(progress_shown(&events) <= 11);
    assert_only_the_stop_ran_after(&printer, &commands, 11);
}

/// ADVANCED_OK `ok`s that name a line the host never sent advance nothing: the printer
/// counts from elsewhere.
#[test]
fn oks_that_do_not_advance_stop_the_job() {
    let (mut host, _, now) = connected(opts(Firmware::Marlin2));
    let mut printer = printer_of(Firmware::Marlin2, true);
    printer.expected = 2;
    printer.refuse_after = Some((MARK.into(), "ok N999 P15 B3\n".into()));
    let commands = marked_job();
    host.start_job(commands.clone(), now);
    let events = run_job(&mut host, &mut printer, now);
    assert!(
        matches!(
            failure(&events),
            Some(Failure::LostNumbering {
                what: Numbering::NoAdvance { .. },
                ..
            })
        ),
        "{events:?}"
    );
    assert!(events.contains(&Event::SafeStop { confirmed: true }));
    assert!(progress_shown(&events) <= 11);
    assert_only_the_stop_ran_after(&printer, &commands, 11);
}

/// `crispen cancel` on a printer renumbered before the host noticed: its stop once went
/// out numbered in the host's count and was refused, so the heaters stayed on. Now the
/// heaters go off unnumbered at once, and the rest follows a new count.
#[test]
fn a_cancel_stops_a_printer_that_counts_from_elsewhere() {
    for (fw, advanced) in every_profile() {
        let mut o = opts(fw);
        o.send_ahead = false;
        let (mut host, _, now) = connected(o);
        let mut printer = printer_of(fw, advanced);
        printer.expected = 2;
        host.start_job(job(30), now);
        exchange(&mut host, &mut printer, now, 8);
        // What `M117 M110 N999` did, without the host seeing a refusal yet.
        printer.expected = 1000;
        host.cancel(now);
        let events = run_job(&mut host, &mut printer, now);
        assert!(
            matches!(failure(&events), Some(Failure::Cancelled { .. })),
            "{fw}: {events:?}"
        );
        assert!(
            events.contains(&Event::SafeStop { confirmed: true }),
            "{fw}"
        );
        // The heaters off twice: at once without a number, then in the new count.
        let executed = &printer.executed;
        let off: Vec<usize> = (0..executed.len())
            .filter(|&i| executed[i] == "M104 S0")
            .collect();
        assert_eq!(off.len(), 2, "{fw}: {executed:?}");
        for line in SAFE_STOP {
            assert!(executed[off[1]..].iter().any(|c| c == line), "{fw}: {line}");
        }
    }
}

/// Nothing goes out behind a heat wait until it is answered: a stop then finds a command
/// slot free for its M108, which Marlin reads during the wait, and no move of the job is
/// left in the printer to run after a stop.
#[test]
fn nothing_is_sent_behind_a_heat_wait() {
    for fw in Firmware::ALL {
        let (mut host, _, now) = connected(opts(fw));
        host.start_job(
            vec!["M109 S210".into(), "G1 X1".into(), "G1 X2".into()],
            now,
        );
        let mut out = String::new();
        for _ in 0..5 {
            let more = sent(&mut host);
            if more.is_empty() {
                break;
            }
            for line in more.lines() {
                if !line.contains("M109") {
                    host.feed(b"ok\n", now);
                }
            }
            out += &more;
        }
        assert!(out.contains("M109 S210"), "{fw}: {out}");
        assert!(!out.contains("G1 X1"), "{fw}: {out}");
        host.feed(b"ok\n", now);
        assert!(sent(&mut host).contains("G1 X1"), "{fw}");
    }
}

/// Reports of a heat wait from 25 °C towards 210, two degrees a second; the time they end,
/// and what the host sent meanwhile (probes), which the printer reads after the wait.
fn heat_reports(
    host: &mut Host,
    from: Instant,
    seconds: u64,
    with_target: bool,
) -> (Instant, String) {
    let mut t = from;
    let mut wire = String::new();
    for s in 1..=seconds {
        t = from + Duration::from_secs(s);
        let line = if with_target {
            format!(
                "T:{:.1} /210.0 B:20.0 /0.0 @:127 B@:0 W:?\n",
                25.0 + 2.0 * s as f64
            )
        } else {
            format!("T:{:.1} E:0 W:?\n", 25.0 + 2.0 * s as f64)
        };
        host.feed(line.as_bytes(), t);
        host.tick(t);
        wire += &sent(host);
    }
    (t, wire)
}

/// A host inside the job's `M109 S210`, its earlier lines answered.
fn heating(fw: Firmware, greeting: Option<&str>) -> (Host, Instant) {
    let now = Instant::now();
    let mut host = Host::new(opts(fw), now);
    host.feed(b"start\n", now);
    host.tick(now + Duration::from_secs(1));
    let now = now + Duration::from_secs(1);
    host.take_outgoing();
    host.feed(b"ok\n", now);
    let greeting = greeting.unwrap_or(if fw == Firmware::Ultimaker2 {
        UM2_GREETING
    } else {
        GREETING
    });
    host.feed(format!("{greeting}ok\n").as_bytes(), now);
    assert!(host.is_idle());
    host.start_job(vec!["M109 S210".into(), "G1 X1".into()], now);
    for _ in 0..5 {
        let out = sent(&mut host);
        for line in out.lines() {
            if !line.contains("M109") {
                host.feed(b"ok\n", now);
            }
        }
        if out.contains("M109") {
            break;
        }
    }
    (host, now)
}

/// A stop asked for during `M109`: where an unnumbered `M108` ends the wait (an emergency
/// parser, or Marlin 2 without one, whose queue reads lines during the wait and acts on
/// an `M108` as it reads it), it goes first, then the heaters off, at once. Once took 44 s.
#[test]
fn a_stop_during_a_heat_wait_breaks_it_where_the_firmware_can() {
    let no_parser = GREETING.replace("EMERGENCY_PARSER:1", "EMERGENCY_PARSER:0");
    for greeting in [GREETING, no_parser.as_str()] {
        let (mut host, now) = heating(Firmware::Marlin2, Some(greeting));
        let (t, _) = heat_reports(&mut host, now, 5, true);
        host.cancel(t);
        let out = sent(&mut host);
        assert!(out.starts_with("M108\nM104 S0\nM140 S0\n"), "{out:?}");
        let events = drain_events(&mut host);
        assert!(
            !events
                .iter()
                .any(|e| matches!(e, Event::StopWaitsForHeat(_))),
            "{events:?}"
        );
        // A wait that began after the M108 was read (it waited behind another command)
        // is broken too, once a second at most.
        host.feed(b"T:40.0 /210.0 B:20.0 /0.0 @:127 B@:0 W:?\n", t);
        assert_eq!(sent(&mut host), "", "not twice within a second");
        let later = t + Duration::from_millis(1500);
        host.feed(b"T:41.0 /210.0 B:20.0 /0.0 @:127 B@:0 W:?\n", later);
        assert_eq!(sent(&mut host), "M108\n");
    }
}

/// Ultimaker2Marlin reads nothing while it heats: the stop waits for the heat-up, and the
/// host says so, with how long that may take (from the rate the heater rose so far), as
/// figures; it does not give the stop up while the heater still comes closer.
#[test]
fn a_stop_that_must_wait_for_the_heat_up_says_how_long() {
    let (mut host, now) = heating(Firmware::Ultimaker2, None);
    let (t, before) = heat_reports(&mut host, now, 10, false);
    host.cancel(t);
    let out = sent(&mut host);
    assert!(out.starts_with("M104 S0\nM140 S0\n"), "{out:?}");
    assert!(!out.contains("M108"));
    let events = drain_events(&mut host);
    let estimate = events
        .iter()
        .find_map(|e| match e {
            Event::StopWaitsForHeat(e) => Some(e.clone()),
            _ => None,
        })
        .expect("the stop waits for the heat-up");
    assert_eq!(estimate.command.as_deref(), Some("M109 S210"));
    assert!(!estimate.bed);
    assert_eq!(estimate.current, Some(45.0));
    assert_eq!(estimate.target, Some(210.0));
    // 165 degrees to go at two a second.
    let remaining = estimate.remaining.unwrap().as_secs_f64();
    assert!((remaining - 82.5).abs() < 1.0, "{remaining}");
    assert!(estimate.limit <= opts(Firmware::Ultimaker2).heat_timeout);
    // Past the stop's own limit the printer still heats and reports: the stop waits on.
    let stop_timeout = opts(Firmware::Ultimaker2).stop_timeout;
    let seconds = stop_timeout.as_secs() + 10;
    let (t, during) = heat_reports(&mut host, t, seconds, false);
    assert!(!host.is_finished());
    // Said again as the heater's reports come, every five seconds: the figure follows it.
    let again: Vec<_> = drain_events(&mut host)
        .into_iter()
        .filter_map(|e| match e {
            Event::StopWaitsForHeat(e) => Some(e),
            _ => None,
        })
        .collect();
    assert_eq!(again.len() as u64, seconds / 5, "{again:?}");
    assert!(
        again.windows(2).all(|w| w[1].current > w[0].current),
        "{again:?}"
    );
    let below = |e: &HeatWaitEstimate| e.current < e.target;
    assert!(
        again
            .windows(2)
            .filter(|w| below(&w[1]))
            .all(|w| w[1].remaining < w[0].remaining),
        "closer, less to wait: {again:?}"
    );
    // The wait ends: its `ok`, then what waited in the printer's buffer, in order (a probe
    // sent before the stop is answered first, and confirms nothing of it).
    host.feed(b"ok\n", t);
    host.outgoing
        .splice(0..0, (before + &out + &during).bytes());
    let executed = answer_safe_stop(&mut host, t);
    assert_safe_stop(&executed);
    let events = drain_events(&mut host);
    assert!(
        events.contains(&Event::SafeStop { confirmed: true }),
        "{events:?}"
    );
}

/// A stop whose numbered lines the printer does not take (its new count lost on a noisy
/// link) still learns the heaters are off from the printer's own answer to the M105 sent
/// without a number after the unnumbered heaters-off lines; an answer with a target not
/// at 0 says nothing of the kind.
#[test]
fn the_printers_report_after_the_unnumbered_stop_shows_its_heaters_off() {
    for (target, off) in [("0.0", true), ("210.0", false)] {
        let now = Instant::now();
        let mut host = Host::new(opts(Firmware::Marlin2), now);
        host.feed(b"start\n", now);
        let now = now + Duration::from_secs(1);
        host.tick(now);
        host.take_outgoing();
        host.feed(format!("ok\n{GREETING}ok\n").as_bytes(), now);
        assert!(host.is_idle());
        host.start_job(job(10), now);
        sent(&mut host);
        host.cancel(now);
        let out = sent(&mut host);
        assert!(out.contains("M104 S0\nM140 S0\n"), "{out:?}");
        // The unnumbered lines are answered; the new count's M110 never is.
        host.feed(b"ok\nok\nok\n", now);
        let (t, probe) = loop {
            let t = host.next_deadline().expect("the stop waits for something");
            host.tick(t);
            let out = sent(&mut host);
            if out.lines().any(|l| l == "M105") {
                break (t, out);
            }
            assert!(
                !host.is_finished(),
                "no unnumbered M105 before the stop ended"
            );
        };
        drain_events(&mut host);
        host.feed(
            format!("ok T:20.0 /{target} B:20.0 /0.0 @:0 B@:0\n").as_bytes(),
            t,
        );
        let events = drain_events(&mut host);
        assert_eq!(
            events.contains(&Event::HeatersOff),
            off,
            "target {target} after {probe:?}: {events:?}"
        );
    }
}
