//! Any bytes as what a printer sends, cut into pieces anywhere: every line is classified
//! into a `Reply` without a panic, a line ending or padding around a line changes nothing,
//! and a host in the middle of a job that reads the bytes (with time passing between the
//! pieces) never panics, never acknowledges more than it sent and only sends well-formed
//! numbered lines.
//!
//! Input layout: the first byte picks the firmware (its value mod 3: `0` Marlin 2.1, `1`
//! Marlin 2.0, `2` Ultimaker2Marlin, so a seed can start with that digit), whether the
//! printer announced ADVANCED_OK (bit 2: `6` is Marlin 2.1 with it), and seeds the cuts
//! and the time steps; the rest is the printer's output.
#![no_main]

use crispen::marlin::firmware::Firmware;
use crispen::marlin::protocol::reply::Reply;
use crispen::marlin::protocol::{checksum, Event, FirmwareInfo, Host, ProtocolOptions};
use libfuzzer_sys::fuzz_target;
use std::time::{Duration, Instant};

/// A short job with a heat wait, a long command and a command stock Marlin lacks (M73), so
/// the answers can reach every kind of line in flight.
const JOB: &[&str] = &[
    "G28",
    "M104 S200",
    "M140 S60",
    "M190 S60",
    "M109 S200",
    "G1 X10 Y10 F3000",
    "G1 X20 E1.5",
    "M73 P50",
    "M400",
    "M106 S255",
    "G1 X30 Y5 E2",
    "M110 N40",
    "G1 X1",
    "M107",
];

fuzz_target!(|data: &[u8]| {
    let Some((&control, stream)) = data.split_first() else {
        return;
    };
    for line in stream.split(|&b| b == b'\n') {
        classify_line(line);
    }
    drive_host(control, stream);
});

/// The pure parser: no panic, and the same reply for the line with a `\r` line ending
/// (Marlin on some boards ends lines with `\r\n`) or padded with blanks.
fn classify_line(line: &[u8]) {
    let reply = Reply::parse(line);
    let with_cr = [line, b"\r"].concat();
    assert_eq!(Reply::parse(&with_cr), reply, "{line:?} with \\r");
    let padded = [b" ", line, b" \t"].concat();
    assert_eq!(Reply::parse(&padded), reply, "{line:?} padded");
}

/// Xorshift: the cuts and time steps, reproducible from the input.
struct Cuts(u32);

impl Cuts {
    fn next(&mut self, below: u32) -> u32 {
        self.0 ^= self.0 << 13;
        self.0 ^= self.0 >> 17;
        self.0 ^= self.0 << 5;
        self.0 % below
    }
}

fn drive_host(control: u8, stream: &[u8]) {
    let firmware = Firmware::ALL[(control % 3) as usize];
    let mut info = FirmwareInfo::default();
    if control & 4 != 0 {
        info.capabilities.insert("ADVANCED_OK".into(), true);
    }
    let mut now = Instant::now();
    let mut host = Host::new(ProtocolOptions::for_firmware(firmware), now);
    host.mark_connected(info);
    let job: Vec<String> = JOB.iter().map(|c| c.to_string()).collect();
    assert!(host.start_job(job, now));
    let mut cuts = Cuts(u32::from(control).wrapping_mul(0x9E37_79B9) | 1);
    let mut rest = stream;
    loop {
        check_outgoing(&host.take_outgoing());
        while let Some(event) = host.poll_event() {
            if let Event::Progress { acked, total } = event {
                assert!(acked <= total && total == JOB.len(), "{acked}/{total}");
            }
        }
        assert!(host.acked_job_lines() <= JOB.len());
        if rest.is_empty() || host.is_finished() {
            break;
        }
        let (piece, tail) = rest.split_at((1 + cuts.next(24) as usize).min(rest.len()));
        rest = tail;
        host.feed(piece, now);
        // Mostly quick answers, sometimes a pause long enough for probes and timeouts.
        now += match cuts.next(8) {
            0 => Duration::from_secs(u64::from(cuts.next(400))),
            _ => Duration::from_millis(u64::from(cuts.next(50))),
        };
        if host.next_deadline().is_some_and(|deadline| deadline <= now) {
            host.tick(now);
        }
    }
}

/// Whole lines only; a numbered line carries its correct checksum.
fn check_outgoing(bytes: &[u8]) {
    if bytes.is_empty() {
        return;
    }
    assert_eq!(bytes.last(), Some(&b'\n'), "{bytes:?}");
    for line in bytes[..bytes.len() - 1].split(|&b| b == b'\n') {
        if line.first() != Some(&b'N') {
            continue;
        }
        let star = line
            .iter()
            .rposition(|&b| b == b'*')
            .expect("numbered line has *");
        let sent: u8 = std::str::from_utf8(&line[star + 1..])
            .ok()
            .and_then(|cs| cs.parse().ok())
            .expect("checksum is a number");
        assert_eq!(sent, checksum(&line[..star]), "{line:?}");
    }
}
