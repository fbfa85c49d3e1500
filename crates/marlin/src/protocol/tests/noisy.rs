//! A noisy link as a property (issue 48): lines lost whole or arriving corrupted on the way
//! to the printer, and the printer's answers lost on the way back, in any mix and at any
//! line (a job's line, a replay, a probe `M105`), on every firmware's rules. Whatever the
//! noise, the job ends done with every line executed exactly once, or fails by one of the
//! host's own limits; it never sits probing with nothing moving. On the fake clock.

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

/// Runs `commands` through a link that loses `lost` and corrupts `corrupt` per mille of
/// the host's lines and loses `answers` per mille of the printer's answer lines. Returns
/// the events, the printer, and how long the job took on the fake clock.
fn through_noise(
    o: ProtocolOptions,
    advanced: bool,
    commands: &[String],
    seed: u64,
    (lost, corrupt, answers): (u64, u64, u64),
) -> (Vec<Event>, MiniPrinter, Duration) {
    let marlin20 = o.firmware == Firmware::Marlin20;
    let (mut host, mut printer, start) = connected(o);
    printer.advanced = advanced;
    // Marlin 2.0 sends no `ok` after `Resend:`; Marlin flushes what arrived with a bad
    // line on some builds and not on others.
    printer.ok_after_resend = !marlin20;
    printer.flush_on_error = seed % 2 == 1;
    let mut noise = Noise(seed.wrapping_mul(0x9E37_79B9_7F4A_7C15) | 1);
    host.start_job(commands.to_vec(), start);
    let mut now = start;
    let mut events = Vec::new();
    for _ in 0..200_000 {
        if host.is_finished() {
            break;
        }
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
            now = d.max(now);
            host.tick(now);
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
        host.feed(heard.as_bytes(), now);
    }
    while let Some(e) = host.poll_event() {
        events.push(e);
    }
    assert!(host.is_finished(), "seed {seed}: {}", host.debug_state());
    (events, printer, now - start)
}

/// Runs 150 noisy jobs on one flavour of printer and host; returns what went wrong.
fn noisy_jobs(firmware: Firmware, send_ahead: bool, advanced: bool) -> Vec<String> {
    let commands = job(300);
    let mut failed = Vec::new();
    for seed in 0..150 {
        let mut o = opts(firmware);
        o.send_ahead = send_ahead;
        let rates = [(20, 20, 10), (5, 50, 30), (50, 0, 0), (0, 0, 50)][seed as usize % 4];
        let (events, printer, took) = through_noise(o, advanced, &commands, seed, rates);
        let what = format!(
            "{firmware:?} send_ahead {send_ahead} advanced {advanced} seed {seed} {rates:?}"
        );
        // The job's lines the printer ran, before the safe stop of a failure.
        let executed: Vec<String> = printer
            .job_executed()
            .into_iter()
            .take_while(|c| c.starts_with("G1 "))
            .collect();
        assert_eq!(
            executed[..],
            commands[..executed.len()],
            "{what}: a line run twice or out of order"
        );
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

/// One line at a time (`crispen print --one-line`), where a lost `M105` answer used to
/// leave one probe always seeming unanswered and nothing but probes sent: 42 of these 150
/// jobs failed or took ten minutes and more before the fix in `window_allows`, 5 still do
/// (every one at 5 % of the printer's answers lost): each lost answer leaves an `M105`
/// the host cannot tell from one still to be answered, until they fill the printer's
/// receive ring and nothing more is sent. The printer is stopped safely ("silent") here;
/// a printer that reports its temperatures unasked would keep such a host waiting.
#[test]
#[ignore = "issue 48: unanswered M105s pile up in one-line mode when the printer's answers are lost (5 of 150 jobs)"]
fn one_line_at_a_time_a_noisy_link_never_wedges_a_job() {
    let failed = noisy_jobs(Firmware::Marlin2, false, false);
    assert!(
        failed.is_empty(),
        "{} jobs failed: {failed:#?}",
        failed.len()
    );
}
