//! Answers that come late: Ultimaker2Marlin (Marlin_main.cpp, MarlinSerial.h of commit
//! 8698fb6) reads serial only while fewer than seven of its eight command slots are taken,
//! answers a move as it reads the line and an `M105` only when it runs it, and a move that
//! waits for a free planner block keeps it from reading anything. A long move (a 3-second
//! prime with cold extrusion allowed) therefore keeps the host's probes unread for seconds,
//! and their answers come later, in order. The host must never count more bytes out of the
//! 127-byte receive ring than the printer has read, nor take a line for confirmed before
//! the printer has it. On a fake clock, against a model of that loop.

use super::*;
use std::collections::VecDeque;

/// The ring's bytes: 128 cells, one left unused to tell full from empty.
const RING: usize = 127;
/// Command slots (BUFSIZE) and planner blocks (BLOCK_BUFFER_SIZE) of the firmware.
const SLOTS: usize = 8;
const BLOCKS: usize = 16;

/// How long the model's moves take, in milliseconds.
#[derive(Clone, Copy)]
struct Pace {
    prime: u64,
    /// Each move of the job after the prime (long travels at a low speed).
    travel: u64,
    /// A retraction (`F3000`) after every `retract_every` moves (none for 0).
    retract: u64,
    retract_every: usize,
}

/// Ultimaker2Marlin's loop, its ring and its planner, on the test's clock.
struct Um2 {
    ring: VecDeque<u8>,
    /// Bytes the ring had no room for (the receive interrupt drops them silently).
    dropped: usize,
    /// The most bytes the ring held at once.
    fullest: usize,
    line: Vec<u8>,
    slots: VecDeque<(u64, String)>,
    /// When each planned move ends, in order.
    planner: VecDeque<Instant>,
    expected: u64,
    /// Numbered lines read into a slot, in order.
    read: Vec<u64>,
    executed: Vec<String>,
    out: String,
    pace: Pace,
    /// The next line read arrives corrupted (noise on the cable).
    corrupt_next: bool,
}

impl Um2 {
    /// A printer whose count is at `last` (the host's `M110` and greeting ran).
    fn new(last: u64, pace: Pace) -> Self {
        Um2 {
            ring: VecDeque::new(),
            dropped: 0,
            fullest: 0,
            line: Vec::new(),
            slots: VecDeque::new(),
            planner: VecDeque::new(),
            expected: last + 1,
            read: Vec::new(),
            executed: Vec::new(),
            out: String::new(),
            pace,
            corrupt_next: false,
        }
    }

    /// Bytes arriving on the wire: each takes a cell while one is free.
    fn receive(&mut self, bytes: &[u8]) {
        for &b in bytes {
            if self.ring.len() < RING {
                self.ring.push_back(b);
            } else {
                self.dropped += 1;
            }
        }
        self.fullest = self.fullest.max(self.ring.len());
    }

    /// `get_command`: reads while a slot is free; a move is answered as it is read.
    fn get_command(&mut self) {
        while self.slots.len() < SLOTS {
            let Some(b) = self.ring.pop_front() else {
                return;
            };
            if b != b'\n' {
                self.line.push(b);
                continue;
            }
            let text = String::from_utf8(std::mem::take(&mut self.line)).unwrap();
            let Some((body, cs)) = text.split_once('*') else {
                // Unnumbered (a stop's heaters off): run without any check.
                self.slots.push_back((0, canonical(&text)));
                continue;
            };
            let (n, command) = body.split_once(' ').unwrap();
            let n: u64 = n[1..].parse().unwrap();
            let last = self.expected - 1;
            // A line with `M110` in it sets the count (no M110 handler: it answers `ok`).
            let error = if std::mem::take(&mut self.corrupt_next)
                || checksum(body.as_bytes()).to_string() != cs
            {
                Some("checksum mismatch")
            } else if n != self.expected && !command.contains("M110") {
                Some("Line Number is not Last Line Number+1")
            } else {
                None
            };
            if let Some(error) = error {
                // FlushSerialRequestResend: the whole ring is discarded.
                let resend = last + 1;
                self.out.push_str(&format!(
                    "Error:{error}, Last Line: {last}\nResend: {resend}\nok\n"
                ));
                self.ring.clear();
                return;
            }
            self.expected = n + 1;
            self.read.push(n);
            let command = canonical(command);
            if command.starts_with("G1 ") {
                self.out.push_str("ok\n");
            }
            self.slots.push_back((n, command));
        }
    }

    /// The loop until it blocks: the head slot runs when it can; a move waits for a
    /// planner block, and nothing is read meanwhile.
    fn run(&mut self, now: Instant) {
        loop {
            while self.planner.front().is_some_and(|end| *end <= now) {
                self.planner.pop_front();
            }
            if self.slots.len() < SLOTS - 1 {
                self.get_command();
            }
            let Some((_, command)) = self.slots.front().cloned() else {
                return;
            };
            if command.starts_with("G1 ") {
                if self.planner.len() >= BLOCKS {
                    return; // plan_buffer_line waits for a block
                }
                let takes = if command.contains("F200") {
                    self.pace.prime
                } else if command.contains("F3000") {
                    self.pace.retract
                } else {
                    self.pace.travel
                };
                let start = self.planner.back().map_or(now, |end| (*end).max(now));
                self.planner.push_back(start + Duration::from_millis(takes));
            } else if command == "M105" {
                self.out.push_str("ok T:20.0 /0.0 B:20.0 /0.0 @:0 B@:0\n");
            } else {
                self.out.push_str("ok\n");
            }
            self.slots.pop_front();
            self.executed.push(command);
        }
    }

    /// When the loop can go on by itself: the planner's next block ends.
    fn next_event(&self) -> Option<Instant> {
        self.planner.front().copied()
    }
}

/// The shape of the PrusaSlicer job that overran the real firmware's ring in the
/// time-left bench: cold extrusion allowed, a prime, then moves with a retraction now and
/// then.
fn primed_job(moves: usize, retract_every: usize) -> Vec<String> {
    let mut commands = vec![
        "M302 S0".to_string(),
        "G92 X0 Y0 Z0 E0".into(),
        "G1 F200 E10".into(),
        "G92 E0".into(),
    ];
    for i in 0..moves {
        if retract_every > 0 && i % retract_every == retract_every - 1 {
            commands.extend(["G1 E-0.5 F3000".to_string(), "G92 E0".into()]);
        }
        commands.push(canonical(&format!(
            "G1 X{}.{:03} Y{}.{:03} E{}.{:05}",
            100 + i % 20,
            (i * 37) % 1000,
            100 + i % 17,
            (i * 91) % 1000,
            i / 100,
            (i * 4133) % 100_000
        )));
    }
    commands
}

/// What came of streaming a primed job to the model.
struct Streamed {
    printer: Um2,
    host: Host,
    events: Vec<Event>,
    commands: Vec<String>,
}

/// Streams `primed_job(moves, ..)` to the model at `pace`. Should the host take a line for
/// confirmed that the printer has not read yet, that line arrives corrupted (as noise may
/// make any line do): the printer asks for it again.
fn stream_primed(pace: Pace, moves: usize) -> Streamed {
    let mut mini = MiniPrinter::new();
    let (mut host, _) = connect(opts(Firmware::Ultimaker2), &mut mini, Instant::now());
    let mut printer = Um2::new(mini.expected - 1, pace);
    // Connected (the handshake took a second of the fake clock).
    let start = Instant::now() + Duration::from_secs(1);
    let commands = primed_job(moves, pace.retract_every);
    host.start_job(commands.clone(), start);
    // The first temperature poll goes with the job's first lines, and is answered at once.
    host.tick(start);
    let mut now = start;
    let mut events = Vec::new();
    for _ in 0..1_000_000 {
        let out = host.take_outgoing();
        printer.receive(&out);
        if printer.dropped > 0 {
            break; // lines were cut: asserted by the caller
        }
        let unread_confirmed = host
            .confirmed
            .is_some_and(|c| printer.read.last().is_none_or(|r| c > *r));
        printer.corrupt_next |= unread_confirmed;
        printer.run(now);
        let answer = std::mem::take(&mut printer.out);
        host.feed(answer.as_bytes(), now);
        events.extend(std::iter::from_fn(|| host.poll_event()));
        if host.is_finished() {
            break;
        }
        if !out.is_empty() || !answer.is_empty() {
            continue;
        }
        let next = [host.next_deadline(), printer.next_event()]
            .into_iter()
            .flatten()
            .min()
            .expect("a deadline while waiting");
        now = next.max(now);
        host.tick(now);
    }
    Streamed {
        printer,
        host,
        events,
        commands,
    }
}

/// Every command of the job ran once, in order, and the job ended done.
fn assert_ran_once(s: &Streamed) {
    assert!(done(&s.events), "{:?}", failure(&s.events));
    let ran: Vec<&String> = s
        .printer
        .executed
        .iter()
        .filter(|c| !is_housekeeping(c))
        .collect();
    let job: Vec<&String> = s.commands.iter().collect();
    assert_eq!(ran, job);
    assert!(s.host.stats.probes > 0, "the prime made the host probe");
}

/// Issue 48, from the time-left bench: while the prime ran, the host's probes waited unread
/// in the ring, and their answers came seconds later, in order. The host had taken the
/// older ones for lost after a quarter of a second (the `M105`s answered at once before),
/// so a late answer was taken for a later `M105`'s, and the last ones, finding no `M105`
/// left, for moves' `ok`s: the host counted lines out of the ring that were still in it.
/// The real firmware dropped 169 bytes of a clean link, and here the model's ring overran.
#[test]
fn late_probe_answers_never_free_ring_bytes_still_in_use() {
    let pace = Pace {
        prime: 3000,
        travel: 1500,
        retract: 60,
        retract_every: 5,
    };
    let s = stream_primed(pace, 60);
    assert_eq!(
        s.printer.dropped,
        0,
        "the ring overran: {:?}",
        failure(&s.events)
    );
    assert!(s.printer.fullest <= RING);
    assert_ran_once(&s);
}

/// Issue 48's "asked for line N again although it had confirmed line N": an answer of an
/// `M105` read long before, taken for a later probe's, confirmed that probe while it still
/// waited in the ring. Noise on that line then drew a resend request for it, which the host
/// took for a printer that had lost its state, and stopped the job.
#[test]
fn late_probe_answers_never_confirm_a_line_the_printer_has_not_read() {
    let pace = Pace {
        prime: 3000,
        travel: 700,
        retract: 60,
        retract_every: 0,
    };
    let s = stream_primed(pace, 60);
    assert_eq!(s.printer.dropped, 0);
    assert_ran_once(&s);
}
