//! A noisy link as a property (issue 48): lines lost whole or arriving corrupted on the way
//! to the printer, and the printer's answers lost on the way back, in any mix and at any
//! line (a job's line, a replay, a probe `M105`), on every firmware's rules. Whatever the
//! noise, the job ends done, with every line executed exactly once and in minutes: it
//! never sits probing with nothing moving, nor fails for want of an answer it could ask
//! for. On the fake clock, against the unit tests' model printer.

use super::*;

/// A small deterministic generator (xorshift64*): the cases are the same on every run.
struct Noise(u64);

impl Noise {
    fn next(&mut self) -> u64 {
        self.0 ^= self.0 >> 12;
        self.0 ^= self.0 << 25;
        self.0 ^= self.0 >> 27;
        self.0.wrapping_mul(0x2545_F491_4F6C_DD1D)
    }

    /// True with probability `per_mille` / 1000.
    fn hits(&mut self, per_mille: u64) -> bool {
        self.next() % 1000 < per_mille
    }
}

/// How often the printer reports its temperatures unasked (the `M155 S2` the host asks
/// for): a printer that talks is never taken for silent.
const AUTOREPORT: Duration = Duration::from_secs(2);

/// The test's clock, the printer reporting its temperatures every [`AUTOREPORT`].
struct Clock {
    now: Instant,
    reported: Instant,
}

impl Clock {
    fn new(now: Instant) -> Self {
        Clock { now, reported: now }
    }

    /// The link is quiet: time goes on to the host's deadline `d` or to the printer's next
    /// report, whichever comes first.
    fn pass(&mut self, host: &mut Host, d: Instant) {
        if d > self.reported + AUTOREPORT {
            self.now = self.now.max(self.reported + AUTOREPORT);
            self.reported = self.now;
            host.feed(b" T:20.1 /0.0 B:19.8 /0.0 @:0 B@:0\n", self.now);
        } else {
            self.now = d.max(self.now);
            host.tick(self.now);
        }
    }
}

/// The job's lines the printer ran, before the safe stop of a failure.
fn job_lines_run(printer: &MiniPrinter) -> Vec<String> {
    printer
        .job_executed()
        .into_iter()
        .take_while(|c| c.starts_with("G1 "))
        .collect()
}

/// Longer than any job here may take on the fake clock, limits and stop included: a job
/// still running then is wedged.
const WEDGED: Duration = Duration::from_secs(4 * 3600);

/// Runs `commands` through a link that loses `lost` and corrupts `corrupt` per mille of
/// the host's lines and loses `answers` per mille of the printer's answer lines, the
/// printer reporting its temperatures every [`AUTOREPORT`]. Returns the events, the
/// printer, and how long the job took on the fake clock (None: wedged).
fn through_noise(
    o: ProtocolOptions,
    advanced: bool,
    commands: &[String],
    seed: u64,
    (lost, corrupt, answers): (u64, u64, u64),
) -> (Vec<Event>, MiniPrinter, Option<Duration>) {
    let marlin20 = o.firmware == Firmware::Marlin20;
    let (mut host, mut printer, start) = connected(o);
    printer.advanced = advanced;
    // Marlin 2.0 sends no `ok` after `Resend:`; Marlin flushes what arrived with a bad
    // line on some builds and not on others.
    printer.ok_after_resend = !marlin20;
    printer.flush_on_error = seed % 2 == 1;
    let mut noise = Noise(seed.wrapping_mul(0x9E37_79B9_7F4A_7C15) | 1);
    host.start_job(commands.to_vec(), start);
    let mut clock = Clock::new(start);
    let mut events = Vec::new();
    while !host.is_finished() && clock.now - start < WEDGED {
        let out = host.take_outgoing();
        if out.is_empty() {
            while let Some(e) = host.poll_event() {
                events.push(e);
            }
            let Some(d) = host.next_deadline() else {
                panic!(
                    "seed {seed}: stalled without a deadline: {}",
                    host.debug_state()
                );
            };
            clock.pass(&mut host, d);
            continue;
        }
        let text = String::from_utf8(out).unwrap();
        let mut kept = String::new();
        for line in text.split_inclusive('\n') {
            // The connection's own lines (the handshake is over) and unnumbered ones pass.
            let number = line
                .strip_prefix('N')
                .and_then(|l| l.split_once(' '))
                .and_then(|(n, _)| n.parse::<u64>().ok());
            if let Some(n) = number {
                if noise.hits(lost) {
                    continue;
                }
                if noise.hits(corrupt) {
                    printer.corrupt.insert(n);
                }
            }
            kept.push_str(line);
        }
        let answer = String::from_utf8(printer.receive(kept.as_bytes())).unwrap();
        let heard: String = answer
            .split_inclusive('\n')
            .filter(|_| !noise.hits(answers))
            .collect();
        host.feed(heard.as_bytes(), clock.now);
    }
    while let Some(e) = host.poll_event() {
        events.push(e);
    }
    let took = host.is_finished().then(|| clock.now - start);
    (events, printer, took)
}

/// Runs 150 noisy jobs on one flavour of printer and host; returns what went wrong.
fn noisy_jobs(firmware: Firmware, send_ahead: bool, advanced: bool) -> Vec<String> {
    let commands = job(300);
    let mut failed = Vec::new();
    for seed in 0..150 {
        let mut o = opts(firmware);
        o.send_ahead = send_ahead;
        let rates = [
            (20, 20, 10),
            (5, 50, 30),
            (50, 0, 0),
            (0, 0, 50),
            (0, 0, 150),
        ][seed as usize % 5];
        let (events, printer, took) = through_noise(o, advanced, &commands, seed, rates);
        let what = format!(
            "{firmware:?} send_ahead {send_ahead} advanced {advanced} seed {seed} {rates:?}"
        );
        let executed = job_lines_run(&printer);
        assert_eq!(
            executed[..],
            commands[..executed.len()],
            "{what}: a line run twice or out of order"
        );
        let Some(took) = took else {
            failed.push(format!("{what}: wedged"));
            continue;
        };
        if !done(&events) {
            failed.push(format!("{what}: {:?}", failure(&events)));
        } else if executed.len() != commands.len() {
            failed.push(format!("{what}: done after {} lines", executed.len()));
        } else if took > Duration::from_secs(600) {
            // 300 lines take seconds; ten minutes is a host that all but stopped.
            failed.push(format!("{what}: done after {took:?}"));
        }
    }
    failed
}

/// Each firmware as the daemon drives it (sending ahead), Marlin 2 with and without
/// ADVANCED_OK.
#[test]
fn a_noisy_link_never_wedges_a_job_and_never_runs_a_line_twice() {
    let mut failed = Vec::new();
    for (firmware, advanced) in [
        (Firmware::Marlin2, false),
        (Firmware::Marlin2, true),
        (Firmware::Marlin20, false),
        (Firmware::Ultimaker2, false),
    ] {
        failed.extend(noisy_jobs(firmware, true, advanced));
    }
    assert!(
        failed.is_empty(),
        "{} jobs failed: {failed:#?}",
        failed.len()
    );
}

/// One line at a time (`crispen print --one-line`). A lost `M105` answer used to leave
/// one probe always seeming unanswered and nothing but probes sent (with the first four
/// kinds of noise, 42 of 150 jobs failed or took ten minutes and more): a line may now
/// follow `M105`s. Answers lost often enough then left unanswered `M105`s filling the
/// printer's ring until nothing more was sent (5 of 150 failed): an `M105` without a
/// number now asks what the printer read (see `probe`).
#[test]
fn one_line_at_a_time_a_noisy_link_never_wedges_a_job() {
    let failed = noisy_jobs(Firmware::Marlin2, false, false);
    assert!(
        failed.is_empty(),
        "{} jobs failed: {failed:#?}",
        failed.len()
    );
}

/// The printer's answers lost for a while (a burst of noise on its way back) after the job
/// began: for two seconds the host's probes go unanswered (until they fill the room it
/// keeps in the ring), then everything is heard again, the printer reporting its
/// temperatures all along. Each lost answer leaves the host counting bytes in the
/// printer's ring that it has read, and the printer, reporting, is never silent: an
/// `M105` without a number, which fits, asks what it read. The job ends done, every line
/// once (it failed for want of progress after 180 s before).
#[test]
fn probes_whose_answers_were_lost_never_hold_a_job_for_ever() {
    for firmware in [Firmware::Marlin2, Firmware::Ultimaker2] {
        let (mut host, mut printer, start) = connected(opts(firmware));
        let commands = job(200);
        host.start_job(commands.clone(), start);
        let mut now = start;
        // A few lines heard, then nothing of what the printer says until the host sends
        // no more.
        for _ in 0..5 {
            let answer = printer.receive(&host.take_outgoing());
            host.feed(&answer, now);
        }
        let mut deaf = 0;
        loop {
            let out = host.take_outgoing();
            if out.is_empty() {
                let d = host
                    .next_deadline()
                    .unwrap_or_else(|| panic!("{firmware:?}: {:?}", drain_events(&mut host)));
                if d - start > Duration::from_secs(2) {
                    break;
                }
                now = d;
                host.tick(now);
                continue;
            }
            deaf += 1;
            printer.receive(&out);
        }
        assert!(deaf > 2, "{firmware:?}: the host probed");
        // Heard again, with the printer's reports.
        let mut clock = Clock::new(now);
        while !host.is_finished() && clock.now - start < WEDGED {
            let out = host.take_outgoing();
            if out.is_empty() {
                let d = host.next_deadline().expect("a job has a clock");
                clock.pass(&mut host, d);
                continue;
            }
            let answer = printer.receive(&out);
            host.feed(&answer, clock.now);
        }
        assert!(
            host.is_finished(),
            "{firmware:?}: wedged: {}",
            host.debug_state()
        );
        let events = drain_events(&mut host);
        assert!(done(&events), "{firmware:?}: {:?}", failure(&events));
        let executed = job_lines_run(&printer);
        assert_eq!(executed[..], commands[..executed.len()], "{firmware:?}");
    }
}
