//! How to run a simulated printer: its firmware, timing, link and the faults it injects.

use crispen_marlin::firmware::Firmware;
use std::path::PathBuf;
use std::time::Duration;

/// Faults to inject. Probabilities are per received line (host side) or per emitted line
/// (printer side); `*_after_lines` fire once, right after the printer starts executing its
/// N-th numbered line (so exactly N numbered lines have been executed, and the N-th one's
/// `ok` is never sent). `Default` injects nothing.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct Faults {
    /// Probability per received line that one of its bytes arrives corrupted, which the
    /// printer detects (checksum / line number) and answers with a resend request.
    pub corrupt_host_bytes: f64,
    /// Probability per received numbered line that one of its `.` arrives as `*`: Marlin 2
    /// then fails the checksum (it takes the last `*`), Ultimaker2Marlin checks only up to
    /// the first `*` and may run the cut line (seen on the real firmware).
    pub star_for_dot: f64,
    /// Probability that the `ok` for a command is never sent (M105's answer is exempt, so
    /// a host's M105 probe always recovers).
    pub drop_ok: f64,
    /// Probability that a good numbered line is answered as if it had been corrupted.
    pub spurious_resend: f64,
    /// Probability per received numbered line that it is lost whole (a noisy cable, a
    /// relay): the printer first sees the next line's number and answers it, as the real
    /// Marlin 2.1.2.1 does, with `Error:Line Number is not Last Line Number+1, Last Line:
    /// N`, `Resend: N+1` and `ok`, and so every line behind it already on its way.
    pub lose_line: f64,
    /// Probability that a command triggers a busy period with `echo:busy: processing`
    /// keep-alives before its `ok` (firmware with the busy protocol only).
    pub busy: f64,
    /// Probability per emitted line of garbage: a corrupted `ok` (`okk`, or an `ok` lost
    /// in binary noise), a garbled temperature report, a non-UTF-8 noise line, or the
    /// `Resend:12` spelling. Never a resend request for a different line.
    pub garbage: f64,
    /// Reboot (`start`, state forgotten, line numbers back to 0) after N numbered lines.
    pub reset_after_lines: Option<usize>,
    /// Close the pty after N numbered lines: the host sees a hang-up and the device vanishes.
    pub unplug_after_lines: Option<usize>,
    /// Stop answering anything after N numbered lines.
    pub silence_after_lines: Option<usize>,
    /// Halt with `Error:...` / `Error:Printer halted. kill() called!` after N numbered lines.
    pub fatal_after_lines: Option<usize>,
    /// Host actions (`//action:NAME`) to send after N numbered lines, as when someone
    /// presses Stop, Pause or Resume on the printer's screen: `(N, "pause")`.
    pub actions: Vec<(usize, String)>,
    /// Firmware errors that are not a halt (`Error:TEXT`, e.g. a failed probing) to report
    /// after N numbered lines: `(N, "Probing Failed")`.
    pub errors: Vec<(usize, String)>,
    /// Lines to receive after N numbered lines, as if they came over the cable between the
    /// host's (a relay injecting them): `(N, "N0 M117 M110 N999*<checksum>")`.
    pub receive: Vec<(usize, String)>,
}

/// The largest speed-up factor taken; faster than that is "instant".
pub const MAX_SPEED: f64 = 1_000_000.0;

/// A simulated printer's speed as operators give it (`crispen sim --speed`,
/// `[printer.simulate] speed`): how many times faster than the real printer, higher is
/// faster (1 = real timing, 20 = twenty times faster), from 0.01 to [`MAX_SPEED`], or
/// "instant" (moves, heating and homing take no time). Returned as
/// [`SimConfig::time_scale`], its inverse. Operators once gave that inverse, which read as
/// a speed: 20 made a demo twenty times slower, and it looked hung.
pub fn time_scale_of_speed(speed: &str) -> Result<f64, String> {
    if speed.trim() == "instant" {
        return Ok(0.0);
    }
    match speed.trim().parse::<f64>() {
        Ok(x) if (0.01..=MAX_SPEED).contains(&x) => Ok(1.0 / x),
        _ => Err(format!(
            "speed {speed:?}: give how many times faster than real time, from 0.01 to {MAX_SPEED} (1 = real time, 20 = twenty times faster), or \"instant\""
        )),
    }
}

/// The speed an old time scale (real seconds per simulated second) is, as `speed` is
/// written: for the warning that names its replacement.
pub fn speed_of_time_scale(time_scale: f64) -> String {
    if time_scale == 0.0 {
        "instant".into()
    } else {
        (1.0 / time_scale).to_string()
    }
}

/// How to run a simulated printer.
#[derive(Debug, Clone)]
pub struct SimConfig {
    pub firmware: Firmware,
    /// Seed of the fault generator: the same seed and input give the same faults.
    pub seed: u64,
    /// Simulated seconds → real seconds. 0.0 makes moves, heating and homing instant;
    /// 1.0 is real timing.
    pub time_scale: f64,
    pub faults: Faults,
    /// Append each executed command to this file, one per line, flushed at once.
    pub record: Option<PathBuf>,
    /// Keep every executed command in memory for `SimHandle::executed` (tests do). A
    /// long-running simulated printer (the daemon's, `crispen sim`) must not: a job of
    /// millions of lines would keep them all.
    pub keep_executed: bool,
    /// Make a symlink to the pty device here (an existing symlink is replaced).
    pub link: Option<PathBuf>,
    /// One-way delay of the link, applied in both directions: bytes the printer sends reach
    /// the host no earlier than this after the printer produced them, and bytes the host
    /// writes reach the printer no earlier than this after they were written. A pty has no
    /// latency of its own, but a USB serial link does (1 ms full-speed frames; an FTDI
    /// adapter holds short answers up to its 16 ms latency timer), and that round trip is
    /// what a host with one line in flight pays per line. Zero by default so tests and the
    /// fault simulation stay fast and exact; benchmarks set it to compare hosts fairly.
    pub link_latency: Duration,
    /// Line speed in bits per second (10 bits per byte, 8N1) in both directions, or `None`
    /// for no limit. A pty moves bytes as fast as memory; at 115200 baud a 30-byte G1 line
    /// takes 2.6 ms on the wire.
    pub baud: Option<u32>,
    /// NO_TIMEOUTS: say `wait` this often while the command queue is empty.
    pub wait_when_idle: Option<Duration>,
    /// Opening the port resets the board (DTR): input is lost for this bootloader delay,
    /// then the firmware boots and says `start`.
    pub reset_on_open: Option<Duration>,
    /// ADVANCED_OK on or off, whatever the firmware profile says (`None`: the profile's).
    /// The real Marlin 2.1.2.1 ships with it off.
    pub advanced_ok: Option<bool>,
    /// EMERGENCY_PARSER on or off (`Cap:EMERGENCY_PARSER`), whatever the profile says
    /// (`None`: the profile's). On, `M108`/`M112`/`M410` act as their bytes arrive; off (as
    /// in the real Marlin 2.1.2.1 builds here), an unnumbered one acts when the queue reads
    /// it, which it does during a heat wait while a command slot is free (queue.cpp:524-531).
    pub emergency_parser: Option<bool>,
    /// How temperature reports are spaced around `/`.
    pub report_style: ReportStyle,
    /// Marlin 2 built with ADVANCED_PAUSE_FEATURE: `M600` parks and waits for the user
    /// (`busy: paused for user`, no `ok` until the knob). Off, as in stock Marlin 2.1, whose
    /// answer is `Unknown command`. (Ultimaker2Marlin answers `M600` with `ok` either way.)
    pub advanced_pause: bool,
}

/// The spacing of a temperature report: printers differ, and a host must read them all.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub enum ReportStyle {
    /// Marlin's and Ultimaker2Marlin's `T:24.99 /0.00`.
    #[default]
    Marlin,
    /// OctoPrint's virtual printer's `T:24.99/ 0.00`.
    SlashFirst,
    /// `T:24.99/0.00`, no space at all.
    Tight,
}

impl SimConfig {
    /// A fault-free printer with instant timing and seed 0.
    pub fn new(firmware: Firmware) -> Self {
        SimConfig {
            firmware,
            seed: 0,
            time_scale: 0.0,
            faults: Faults::default(),
            record: None,
            keep_executed: true,
            link: None,
            link_latency: Duration::ZERO,
            baud: None,
            wait_when_idle: None,
            reset_on_open: None,
            advanced_ok: None,
            emergency_parser: None,
            report_style: ReportStyle::Marlin,
            advanced_pause: false,
        }
    }
}
