//! Print-time estimation as Marlin's planner would execute a G-code file: the time left
//! that status, the dashboard and the OctoPrint endpoints show (`daemon::time_left`).
//!
//! Pure and streaming: feed lines to [`Estimator`], then [`Estimator::finish`] gives an
//! [`Estimate`] with the total, the number of heating waits (their length is unknowable to a
//! planner, so they are counted, not timed) and the times of the commands, kept in chunks
//! (a job of ten million commands keeps under 4 MB of them).
//!
//! Model: every accepted move is a block with a nominal speed (feed, min feed, min segment time
//! slowdown, per-axis max feed), an acceleration (print / travel / retract, clamped per axis) and a
//! maximum entry speed (classic jerk or junction deviation). A block's speeds are frozen when the
//! stepper starts it; at that moment the buffer holds it and the next `block_buffer_size - 1`
//! blocks, the last of which must be able to stop. So we plan (backward then forward pass) over
//! that window, commit the front block with a trapezoid, and slide. We assume the buffer is
//! always full (printing from a host that keeps up or from SD). Simplified away: S-curve
//! (off in both stock configs), step rounding, linear advance, M221 flow, arcs outside the XY
//! plane, Marlin 2's arc "curve radius" hints (small-segment junction handling gives the same
//! a·r corner limit).

use std::collections::VecDeque;

const X: usize = 0;
const Y: usize = 1;
const Z: usize = 2;
const E: usize = 3;
/// Coordinates and parameters are clamped to this so that sums and squares stay finite.
const BIG: f64 = 1e9;

/// Firmware family: it decides G-code semantics that differ between the two.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum Dialect {
    /// Ultimaker2Marlin (Marlin 1.0 lineage): `M204 S T` = print, retract; G90 leaves M83 alone;
    /// per-axis accel clamp snaps to the axis limit in steps; jerk needs 2 queued blocks.
    Ultimaker2,
    /// Marlin 2.x: `M204 P R T` (S = print+travel); G90/G91 also set E; proportional clamp.
    Marlin2,
}

/// How corner speeds are limited.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum Junction {
    /// Classic jerk as in Ultimaker2Marlin: XY speed-vector change, Z and E changes (mm/s).
    Classic { xy: f64, z: f64, e: f64 },
    /// Junction deviation (mm), with Marlin 2's JD_HANDLE_SMALL_SEGMENTS curvature limit.
    Deviation { mm: f64 },
}

/// How G2/G3 are cut into lines.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum Arcs {
    /// Arcs ignored (firmware without ARC_SUPPORT).
    None,
    /// Old Marlin `mc_arc`: floor(length / mm) segments, at least one; I/J form only.
    Fixed { mm: f64 },
    /// Marlin 2.1 `plan_arc`: segment length between min and max, a minimum count per circle.
    Scaled {
        min_mm: f64,
        max_mm: f64,
        min_circle_segments: f64,
    },
}

/// The planner's settings. Arrays are X, Y, Z, E.
#[derive(Clone, Debug, PartialEq)]
pub struct Limits {
    pub dialect: Dialect,
    pub max_feedrate: [f64; 4],
    pub max_accel: [f64; 4],
    pub steps_per_mm: [f64; 4],
    pub accel: f64,
    pub retract_accel: f64,
    /// `None`: the firmware has no travel acceleration (moves without E use `accel`).
    pub travel_accel: Option<f64>,
    pub junction: Junction,
    pub min_feedrate: f64,
    pub min_travel_feedrate: f64,
    pub min_segment_time_us: f64,
    pub block_buffer_size: usize,
    /// Blocks with fewer steps than this on every axis are dropped (merged into the next).
    pub min_steps: f64,
    pub min_planner_speed: f64,
    pub arcs: Arcs,
}

impl Limits {
    /// Ultimaker2Marlin commit 8698fb6, Marlin/Configuration.h (C) and Configuration_adv.h (A).
    pub fn ultimaker2() -> Limits {
        Limits {
            dialect: Dialect::Ultimaker2,
            max_feedrate: [300.0, 300.0, 40.0, 45.0], // C:367 DEFAULT_MAX_FEEDRATE
            max_accel: [9000.0, 9000.0, 100.0, 10000.0], // C:368 DEFAULT_MAX_ACCELERATION
            steps_per_mm: [80.0, 80.0, 200.0, 282.0], // C:366 DEFAULT_AXIS_STEPS_PER_UNIT
            accel: 3000.0,                            // C:370 DEFAULT_ACCELERATION
            retract_accel: 3000.0,                    // C:371 DEFAULT_RETRACT_ACCELERATION
            travel_accel: None, // no such setting: Marlin_main.cpp:1705-1708 (M204 S, T only)
            junction: Junction::Classic {
                xy: 20.0,
                z: 0.4,
                e: 5.0,
            }, // C:380-382 DEFAULT_*JERK
            min_feedrate: 0.0,  // A:174 DEFAULT_MINIMUMFEEDRATE
            min_travel_feedrate: 0.0, // A:175 DEFAULT_MINTRAVELFEEDRATE
            min_segment_time_us: 20000.0, // A:178 DEFAULT_MINSEGMENTTIME (SLOWDOWN on, A:181)
            block_buffer_size: 16, // A:287/289 BLOCK_BUFFER_SIZE
            min_steps: 6.0,     // A:252 dropsegments=5, planner.cpp:596 drops `<= 5`
            min_planner_speed: 0.05, // A:191 MINIMUM_PLANNER_SPEED
            arcs: Arcs::Fixed { mm: 1.0 }, // A:249 MM_PER_ARC_SEGMENT; G2/G3 at Marlin_main.cpp:910-919
        }
    }

    /// Marlin 2.1.2.1 (09d0b4d) stock config, as in MarlinFirmware/Configurations tag 2.1.2.1
    /// config/default/Configuration.h (C) and Configuration_adv.h (A), which are the stock
    /// Marlin/ files. Cross-checked with `M503` of the firmware built for BOARD_SIMULATED
    /// (the firmware tests' `marlin-2.1.2.1-default` build): M203 X300 Y300 Z5 E25, M201 X3000 Y3000
    /// Z100 E10000, M204 P3000 R3000 T3000, M205 B20000 S0 T0 J0.01, M92 .. E500; M115 Cap:ARCS:1.
    pub fn marlin_2_1_2_1() -> Limits {
        Limits {
            dialect: Dialect::Marlin2,
            max_feedrate: [300.0, 300.0, 5.0, 25.0], // C:1178 DEFAULT_MAX_FEEDRATE
            max_accel: [3000.0, 3000.0, 100.0, 10000.0], // C:1191 DEFAULT_MAX_ACCELERATION
            steps_per_mm: [80.0, 80.0, 400.0, 500.0], // C:1171 DEFAULT_AXIS_STEPS_PER_UNIT
            accel: 3000.0,                           // C:1206 DEFAULT_ACCELERATION
            retract_accel: 3000.0,                   // C:1207 DEFAULT_RETRACT_ACCELERATION
            travel_accel: Some(3000.0),              // C:1208 DEFAULT_TRAVEL_ACCELERATION
            // C:1218 `//#define CLASSIC_JERK` (off) => C:1248 JUNCTION_DEVIATION_MM 0.013,
            // C:1249 JD_HANDLE_SMALL_SEGMENTS on. C:1261 S_CURVE_ACCELERATION off.
            junction: Junction::Deviation { mm: 0.013 },
            min_feedrate: 0.0,            // A:1133 DEFAULT_MINIMUMFEEDRATE
            min_travel_feedrate: 0.0,     // A:1134 DEFAULT_MINTRAVELFEEDRATE
            min_segment_time_us: 20000.0, // A:1137 DEFAULT_MINSEGMENTTIME; SLOWDOWN, divisor 2: A:1141-1143
            block_buffer_size: 16,        // A:2389 BLOCK_BUFFER_SIZE (no SD support)
            min_steps: 6.0,               // A:2326 MIN_STEPS_PER_SEGMENT
            min_planner_speed: 0.05,      // A:1160 MINIMUM_PLANNER_SPEED
            // A:2284 ARC_SUPPORT on; A:2286-2288 MIN/MAX_ARC_SEGMENT_MM 0.1/1.0, MIN_CIRCLE_SEGMENTS 72
            arcs: Arcs::Scaled {
                min_mm: 0.1,
                max_mm: 1.0,
                min_circle_segments: 72.0,
            },
        }
    }

    /// Take settings from `M503` output (`echo:  M203 X300.00 ...`). Unknown lines and keys are
    /// ignored. Returns the keys taken, like `"M203 X"`. Both firmwares print their values
    /// with two decimals (Marlin 2.1.2.1 reports its junction deviation of 0.013 mm as
    /// `J0.01`): a reported value within that rounding of the one held is the same value,
    /// and the one held, more precise, is kept.
    pub fn apply_m503(&mut self, text: &str) -> Vec<String> {
        let mut taken = Vec::new();
        for line in text.lines() {
            let line = line.trim_start();
            let line = line.strip_prefix("echo:").unwrap_or(line);
            let w = Words::parse(strip_comment(line));
            if w.cmd.0 == b'M' {
                let before = self.clone();
                for k in self.apply_setting(w.cmd.1, &w) {
                    taken.push(format!("M{} {}", w.cmd.1, k));
                }
                self.keep_within_rounding(&before);
            }
        }
        taken
    }

    /// Apply one command that sets the planner (`M203 X200`), exactly as given; other
    /// commands change nothing. For a printer's own planner, as the simulator keeps it.
    pub fn apply_command(&mut self, command: &str) {
        let w = Words::parse(strip_comment(command));
        if w.cmd.0 == b'M' {
            self.apply_setting(w.cmd.1, &w);
        }
    }

    /// Where a value differs from `before` by no more than a report's rounding (half of
    /// its last decimal), `before`'s is kept.
    fn keep_within_rounding(&mut self, before: &Limits) {
        const HALF_LAST_DECIMAL: f64 = 0.005;
        let keep = |now: &mut f64, was: f64| {
            if (*now - was).abs() <= HALF_LAST_DECIMAL + 1e-12 {
                *now = was;
            }
        };
        for i in 0..4 {
            keep(&mut self.max_feedrate[i], before.max_feedrate[i]);
            keep(&mut self.max_accel[i], before.max_accel[i]);
            keep(&mut self.steps_per_mm[i], before.steps_per_mm[i]);
        }
        keep(&mut self.accel, before.accel);
        keep(&mut self.retract_accel, before.retract_accel);
        if let (Some(now), Some(was)) = (&mut self.travel_accel, before.travel_accel) {
            keep(now, was);
        }
        keep(&mut self.min_feedrate, before.min_feedrate);
        keep(&mut self.min_travel_feedrate, before.min_travel_feedrate);
        keep(&mut self.min_segment_time_us, before.min_segment_time_us);
        match (&mut self.junction, before.junction) {
            (
                Junction::Classic { xy, z, e },
                Junction::Classic {
                    xy: x0,
                    z: z0,
                    e: e0,
                },
            ) => {
                keep(xy, x0);
                keep(z, z0);
                keep(e, e0);
            }
            (Junction::Deviation { mm }, Junction::Deviation { mm: was }) => keep(mm, was),
            _ => {}
        }
    }

    /// Apply M92/M201/M203/M204/M205; returns the parameter letters used.
    fn apply_setting(&mut self, code: u32, w: &Words) -> Vec<char> {
        let mut used = Vec::new();
        let u = &mut used;
        match code {
            92 | 201 | 203 => {
                let (dst, lo) = match code {
                    92 => (&mut self.steps_per_mm, 1e-3),
                    201 => (&mut self.max_accel, 1.0),
                    _ => (&mut self.max_feedrate, 1e-3),
                };
                dst.iter_mut()
                    .enumerate()
                    .for_each(|(i, d)| _ = take(w, AXES[i], d, lo, u));
            }
            204 if self.dialect == Dialect::Marlin2 => {
                let mut t = self.travel_accel.unwrap_or(self.accel);
                if take(w, 'S', &mut self.accel, 1.0, u) {
                    t = self.accel;
                } // legacy S: print + travel
                take(w, 'P', &mut self.accel, 1.0, u);
                take(w, 'R', &mut self.retract_accel, 1.0, u);
                take(w, 'T', &mut t, 1.0, u);
                self.travel_accel = self.travel_accel.map(|_| t);
            }
            204 => {
                take(w, 'S', &mut self.accel, 1.0, u);
                take(w, 'T', &mut self.retract_accel, 1.0, u); // UM2: T is the retract accel
            }
            205 => {
                take(w, 'S', &mut self.min_feedrate, 0.0, u);
                take(w, 'T', &mut self.min_travel_feedrate, 0.0, u);
                take(w, 'B', &mut self.min_segment_time_us, 0.0, u);
                match &mut self.junction {
                    Junction::Classic { xy, z, e } => {
                        take(w, 'X', xy, 0.0, u);
                        take(w, 'Y', xy, 0.0, u);
                        take(w, 'Z', z, 0.0, u);
                        take(w, 'E', e, 0.0, u);
                    }
                    Junction::Deviation { mm } => _ = take(w, 'J', mm, 0.0, u),
                }
            }
            _ => {}
        }
        used
    }
}

/// Set `dst` from parameter `c` if present; limits below `lo` would stall the model: clamp.
fn take(w: &Words, c: char, dst: &mut f64, lo: f64, used: &mut Vec<char>) -> bool {
    let v = w.get(c);
    if let Some(v) = v {
        *dst = v.max(lo);
        used.push(c);
    }
    v.is_some()
}

const AXES: [char; 4] = ['X', 'Y', 'Z', 'E'];

fn strip_comment(line: &str) -> &str {
    line.split(';').next().unwrap_or("").trim()
}

/// One line's command (letter, number) and its finite, clamped parameters, as
/// [`crate::reader`] reads it (the one reader of G-code: a line it cannot read is
/// one the job could not hold, and plans as nothing).
struct Words {
    cmd: (u8, u32),
    vals: [Option<f64>; 26],
}

impl Words {
    fn parse(s: &str) -> Words {
        let mut w = Words {
            cmd: (0, 0),
            vals: [None; 26],
        };
        let Ok(Some(command)) = crate::reader::read(s) else {
            return w;
        };
        w.cmd = (command.letter() as u8, command.number());
        for word in &command.words {
            if word.letter.is_ascii_uppercase() {
                w.vals[(word.letter as u8 - b'A') as usize] = word
                    .value
                    .filter(|v| v.is_finite())
                    .map(|v| v.clamp(-BIG, BIG));
            }
        }
        w
    }
    fn get(&self, c: char) -> Option<f64> {
        self.vals[(c as u8 - b'A') as usize]
    }
}

/// A planned move. Speeds are squared, as in the planner.
#[derive(Clone, Debug)]
struct Block {
    cmd: usize,
    mm: f64,
    accel: f64,
    nominal_sqr: f64,
    max_entry_sqr: f64,
    entry_sqr: f64,
}

/// Streaming estimator: `feed` every line of the file in order, then `finish`.
pub struct Estimator {
    lim: Limits,
    pos: [f64; 4],  // G-code position
    ppos: [f64; 4], // planner position (lags `pos` while moves are dropped as too short)
    rel_xyz: bool,
    rel_e: bool,
    feed: f64, // mm/s
    speed_pct: f64,
    window: VecDeque<Block>,
    front_entry: Option<f64>, // entry of window[0] once its predecessor has run
    queued: usize,            // blocks in the buffer before the next one (0 after a sync)
    prev: Option<([f64; 4], [f64; 4], f64)>, // unit vector, axis speeds, nominal speed
    /// Seconds of the commands from `first` on, whose blocks may still be in the window,
    /// and whether each waits for the planner to empty.
    per_cmd: VecDeque<(f32, bool)>,
    first: usize,
    /// The commands settled so far, as the estimate keeps them.
    kept: Kept,
    total: f64, // exact sum in f64
    dwell: f64,
    heat_waits: usize,
}

/// Result of a whole file.
#[derive(Clone, Debug)]
pub struct Estimate {
    /// Motion plus dwell seconds (heating waits excluded).
    pub total_seconds: f64,
    pub dwell_seconds: f64,
    /// M109/M190/M116 count: their duration depends on the heaters, not the planner.
    pub heating_waits: usize,
    kept: Kept,
}

/// Commands per chunk of [`Kept`].
const CHUNK: usize = 16;

/// The commands' times, compact: the seconds at the end of each chunk of [`CHUNK`]
/// commands, which commands take time and which wait for the planner to empty (a bit
/// each); within a chunk, its time is shared among those that take time. Per-command
/// figures would cost a job of ten million commands 40 MB or more, beside its program.
#[derive(Clone, Debug, Default)]
struct Kept {
    commands: usize,
    chunks: Vec<f64>,
    timed: Vec<u64>,
    /// Once one of these is acknowledged, every move before it is made.
    syncs: Vec<u64>,
    seconds: f64,
}

impl Kept {
    fn push(&mut self, seconds: f64, sync: bool) {
        let k = self.commands;
        if k % 64 == 0 {
            self.timed.push(0);
            self.syncs.push(0);
        }
        if seconds > 0.0 {
            self.timed[k / 64] |= 1 << (k % 64);
        }
        if sync {
            self.syncs[k / 64] |= 1 << (k % 64);
        }
        self.seconds += seconds;
        self.commands += 1;
        if self.commands % CHUNK == 0 {
            self.chunks.push(self.seconds);
        }
    }

    fn timed(&self, k: usize) -> bool {
        self.timed[k / 64] >> (k % 64) & 1 == 1
    }

    fn sync(&self, k: usize) -> bool {
        self.syncs[k / 64] >> (k % 64) & 1 == 1
    }

    /// Seconds of the first `done` commands.
    fn elapsed_at(&self, done: usize) -> f64 {
        let done = done.min(self.commands);
        let c = done / CHUNK;
        let before = if c == 0 { 0.0 } else { self.chunks[c - 1] };
        let (start, end) = (c * CHUNK, ((c + 1) * CHUNK).min(self.commands));
        if done == start {
            return before;
        }
        let after = self.chunks.get(c).copied().unwrap_or(self.seconds);
        let timed = (start..end).filter(|&k| self.timed(k)).count();
        let done_timed = (start..done).filter(|&k| self.timed(k)).count();
        if timed == 0 {
            return before;
        }
        before + (after - before) * done_timed as f64 / timed as f64
    }
}

impl Estimate {
    /// Number of commands (non-empty lines after stripping `;` comments).
    pub fn commands(&self) -> usize {
        self.kept.commands
    }
    /// Seconds of motion in the first `done` commands (within a chunk of [`CHUNK`], shared
    /// among its commands that take time).
    pub fn elapsed_at(&self, done: usize) -> f64 {
        self.kept.elapsed_at(done)
    }
    /// Seconds left once `done` commands have completed; non-increasing, 0 at the end.
    pub fn left_after(&self, done: usize) -> f64 {
        (self.kept.seconds - self.elapsed_at(done)).max(0.0)
    }

    /// Seconds left once the printer has acknowledged `acked` commands, holding up to
    /// `ahead` of the moves among them not yet made ([`moves_ahead`]): those are counted
    /// as still to come, back to the last acknowledged command that waits for the planner
    /// to empty (`M400`, a dwell, a heat wait, homing), before which every move is made.
    pub fn left_after_acked(&self, acked: usize, ahead: usize) -> f64 {
        // Commands that neither move nor wait are passed over, as many as a printer could
        // hold between two moves and no more: the walk stays short whatever the file.
        const PASSED_OVER: usize = 100_000;
        let acked = acked.min(self.kept.commands);
        let (mut done, mut moves) = (acked, 0);
        while done > 0 && moves < ahead && acked - done < PASSED_OVER {
            if self.kept.sync(done - 1) {
                break;
            }
            done -= 1;
            if self.kept.timed(done) {
                moves += 1;
            }
        }
        self.left_after(done)
    }
}

fn trapezoid_time(mm: f64, a: f64, entry_sqr: f64, exit_sqr: f64, nominal_sqr: f64) -> f64 {
    let (v0s, v1s) = (entry_sqr.min(nominal_sqr), exit_sqr.min(nominal_sqr));
    let (vn, v0, v1) = (nominal_sqr.sqrt(), v0s.sqrt(), v1s.sqrt());
    let (acc_d, dec_d) = (
        (nominal_sqr - v0s) / (2.0 * a),
        (nominal_sqr - v1s) / (2.0 * a),
    );
    if acc_d + dec_d <= mm {
        (vn - v0) / a + (vn - v1) / a + (mm - acc_d - dec_d) / vn
    } else {
        // Never reaches cruise: accelerate to the peak where both ramps meet.
        let vp = ((2.0 * a * mm + v0s + v1s) / 2.0).max(v0s).max(v1s).sqrt();
        (vp - v0) / a + (vp - v1) / a
    }
}

fn norm(v: &[f64; 4]) -> f64 {
    v.iter().map(|x| x * x).sum::<f64>().sqrt()
}

impl Estimator {
    pub fn new(lim: Limits) -> Estimator {
        let (pos, ppos, window, per_cmd) = ([0.0; 4], [0.0; 4], VecDeque::new(), VecDeque::new());
        let feed = 1500.0 / 60.0; // both firmwares start at F1500
        let (rel_xyz, rel_e, speed_pct, front_entry, queued, prev) =
            (false, false, 100.0, None, 0, None);
        let (total, dwell, heat_waits) = (0.0, 0.0, 0);
        Estimator {
            lim,
            pos,
            ppos,
            rel_xyz,
            rel_e,
            feed,
            speed_pct,
            window,
            front_entry,
            queued,
            prev,
            per_cmd,
            first: 0,
            kept: Kept::default(),
            total,
            dwell,
            heat_waits,
        }
    }

    /// Feed one line of G-code (a command if non-empty after stripping the comment).
    pub fn feed(&mut self, line: &str) {
        let s = strip_comment(line);
        if s.is_empty() {
            return;
        }
        // Commands whose blocks have all run are settled into the compact record.
        let settled = self
            .window
            .front()
            .map_or(self.first + self.per_cmd.len(), |b| b.cmd);
        self.settle(settled);
        let cmd = self.first + self.per_cmd.len();
        self.per_cmd.push_back((0.0, false));
        let w = Words::parse(s);
        match w.cmd {
            (b'G', 0) | (b'G', 1) => {
                self.take_feed(&w);
                let t = self.target(&w);
                self.line_to(t, cmd);
            }
            (b'G', c @ (2 | 3)) => self.arc(&w, c == 2, cmd),
            (b'G', 4) => {
                self.sync_at(cmd);
                let ms = w.get('S').map(|s| s * 1000.0).or(w.get('P')).unwrap_or(0.0);
                let secs = (ms / 1000.0).clamp(0.0, BIG);
                self.dwell += secs;
                self.total += secs;
                self.per_cmd[cmd - self.first].0 += secs as f32;
            }
            (b'G', 28) => {
                // Homing takes unknown, small time: count zero. Position: homed axes at 0.
                self.sync_at(cmd);
                let any = (0..3).any(|i| w.get(AXES[i]).is_some());
                for i in (0..3).filter(|&i| !any || w.get(AXES[i]).is_some()) {
                    (self.pos[i], self.ppos[i]) = (0.0, 0.0);
                }
            }
            (b'G', 90) | (b'G', 91) => {
                self.rel_xyz = w.cmd.1 == 91;
                if self.lim.dialect == Dialect::Marlin2 {
                    self.rel_e = self.rel_xyz; // Marlin 2 G90/G91 set every axis, E included
                }
            }
            (b'G', 92) => {
                // X/Y/Z: UM2 drains the buffer, Marlin 2 queues a sync block; both restart
                // junctions from rest. E only: neither touches the planner's speeds.
                if (0..3).any(|i| w.get(AXES[i]).is_some()) {
                    self.sync_at(cmd);
                }
                for i in 0..4 {
                    if let Some(v) = w.get(AXES[i]) {
                        (self.pos[i], self.ppos[i]) = (v, v);
                    }
                }
            }
            (b'M', 82) => self.rel_e = false,
            (b'M', 83) => self.rel_e = true,
            (b'M', 400) => self.sync_at(cmd),
            (b'M', 109) | (b'M', 190) | (b'M', 116) => {
                // The queue stops while heating, so the planner drains to a standstill.
                self.sync_at(cmd);
                self.heat_waits += 1;
            }
            (b'M', 220) => {
                self.speed_pct = w.get('S').map_or(self.speed_pct, |s| s.clamp(1.0, 1000.0))
            }
            (b'M', c @ (92 | 201 | 203 | 204 | 205)) => {
                self.lim.apply_setting(c, &w); // applies to moves planned after it, no sync
            }
            _ => {}
        }
    }

    fn take_feed(&mut self, w: &Words) {
        // F0 (or negative) is ignored by both firmwares.
        self.feed = w
            .get('F')
            .filter(|f| *f > 0.0)
            .map_or(self.feed, |f| f / 60.0);
    }

    fn target(&self, w: &Words) -> [f64; 4] {
        let mut t = self.pos;
        for i in 0..4 {
            if let Some(v) = w.get(AXES[i]) {
                let rel = if i == E {
                    self.rel_e || (self.rel_xyz && self.lim.dialect == Dialect::Ultimaker2)
                } else {
                    self.rel_xyz
                };
                t[i] = if rel { (t[i] + v).clamp(-BIG, BIG) } else { v };
            }
        }
        t
    }

    /// Arc in the XY plane, cut into lines the way the firmware does.
    fn arc(&mut self, w: &Words, cw: bool, cmd: usize) {
        let arcs = self.lim.arcs;
        if arcs == Arcs::None {
            return;
        }
        self.take_feed(w);
        let t = self.target(w);
        let (p, r_word) = (
            self.pos,
            w.get('R').filter(|_| matches!(arcs, Arcs::Scaled { .. })),
        );
        let center = if let Some(r) = r_word {
            let (dx, dy) = (t[X] - p[X], t[Y] - p[Y]);
            let d = dx.hypot(dy);
            if d == 0.0 || r == 0.0 {
                return;
            } // Marlin reports a bad arc and does not move
            let h = (r * r - d * d / 4.0).max(0.0).sqrt();
            let s = if cw != (r < 0.0) { -1.0 } else { 1.0 }; // centre right of travel for CW minor arcs
            [
                p[X] + dx / 2.0 - s * h * dy / d,
                p[Y] + dy / 2.0 + s * h * dx / d,
            ]
        } else {
            [
                p[X] + w.get('I').unwrap_or(0.0),
                p[Y] + w.get('J').unwrap_or(0.0),
            ]
        };
        let (r0x, r0y) = (p[X] - center[0], p[Y] - center[1]);
        let (r1x, r1y) = (t[X] - center[0], t[Y] - center[1]);
        let radius = r0x.hypot(r0y);
        let mut ang = (r0x * r1y - r0y * r1x).atan2(r0x * r1x + r0y * r1y);
        let tau = std::f64::consts::TAU;
        let segments = match arcs {
            Arcs::Fixed { mm } => {
                ang += (if ang < 0.0 { tau } else { 0.0 }) - (if cw { tau } else { 0.0 });
                let len = (ang * radius).hypot(t[Z] - p[Z]);
                if !(len >= 0.001) {
                    return;
                }
                (len / mm.max(1e-3)).floor().max(1.0)
            }
            Arcs::Scaled {
                min_mm,
                max_mm,
                min_circle_segments,
            } => {
                let full = (p[X] - t[X]).abs() < 1e-6 && (p[Y] - t[Y]).abs() < 1e-6;
                if full {
                    ang = if cw { -tau } else { tau };
                } else if ang == 0.0 {
                    return;
                } else if cw != (ang < 0.0) {
                    ang += if cw { -tau } else { tau }; // go the long way round as asked
                }
                let flat = radius * ang.abs();
                if !(flat >= 1e-4) && (t[Z] - p[Z]).abs() < 1e-4 {
                    return;
                }
                let min_seg = (min_circle_segments * ang.abs() / tau).ceil().max(1.0);
                let (lo, hi) = (min_mm.max(1e-3), max_mm.max(1e-3));
                let nominal = (flat / hi).floor().max(min_seg);
                if flat / nominal > hi {
                    (flat / hi).ceil()
                } else if flat / nominal < lo {
                    (flat / lo).floor().max(1.0)
                } else {
                    nominal
                }
            }
            Arcs::None => return,
        };
        let n = segments.min(1e5) as usize; // bound work per line (100 m of 1 mm segments)
        for k in 1..n {
            let f = k as f64 / n as f64;
            let (s, c) = (ang * f).sin_cos();
            let q = [
                center[0] + r0x * c - r0y * s,
                center[1] + r0x * s + r0y * c,
                p[Z] + (t[Z] - p[Z]) * f,
                p[E] + (t[E] - p[E]) * f,
            ];
            self.pos = q;
            self.line_to(q, cmd);
        }
        self.line_to(t, cmd);
    }

    /// Plan a straight move to `t` (the heart of the planner's `buffer_line`).
    fn line_to(&mut self, t: [f64; 4], cmd: usize) {
        self.pos = t;
        let lim = &self.lim;
        let (mut d, mut steps) = ([0.0; 4], [0.0; 4]);
        for i in 0..4 {
            d[i] = t[i] - self.ppos[i];
            steps[i] = (d[i] * lim.steps_per_mm[i]).abs().round();
        }
        let events = steps.iter().cloned().fold(0.0, f64::max);
        if !(events >= lim.min_steps) {
            return;
        } // too short: kept for the next move to absorb
        self.ppos = t;
        let xyz_short = (0..3).all(|i| steps[i] < lim.min_steps);
        let mm = if xyz_short {
            d[E].abs()
        } else {
            (d[X] * d[X] + d[Y] * d[Y] + d[Z] * d[Z]).sqrt()
        };
        if !(mm > 1e-9) {
            return;
        }
        let has_e = steps[E] > 0.0;
        let retract = (0..3).all(|i| steps[i] == 0.0);

        // Nominal speed: feed (with M220), min feed, buffer-draining slowdown, per-axis max feed.
        let min_fr = if has_e {
            lim.min_feedrate
        } else {
            lim.min_travel_feedrate
        };
        let fr = (self.feed * self.speed_pct / 100.0).max(min_fr).max(1e-6);
        let mut inv_s = fr / mm;
        let q = self.queued as f64;
        if q > 1.0 && q < lim.block_buffer_size as f64 / 2.0 {
            let seg_us = 1e6 / inv_s;
            if seg_us < lim.min_segment_time_us {
                inv_s = 1e6 / (seg_us + 2.0 * (lim.min_segment_time_us - seg_us) / q);
            }
        }
        let mut v = [0.0; 4];
        let mut factor: f64 = 1.0;
        for i in 0..4 {
            v[i] = d[i] * inv_s;
            if v[i].abs() > lim.max_feedrate[i] {
                factor = factor.min(lim.max_feedrate[i] / v[i].abs());
            }
        }
        v.iter_mut().for_each(|x| *x *= factor);
        let nominal = (mm * inv_s * factor).max(lim.min_planner_speed);

        // Acceleration: retract for E-only, print with E, travel without; then per axis.
        let mut a = if retract {
            lim.retract_accel
        } else if has_e {
            lim.accel
        } else {
            lim.travel_accel.unwrap_or(lim.accel)
        };
        if !retract {
            match lim.dialect {
                Dialect::Marlin2 => {
                    for i in (0..4).filter(|&i| steps[i] > 0.0) {
                        a = a.min(lim.max_accel[i] * mm / d[i].abs());
                    }
                }
                Dialect::Ultimaker2 => {
                    // Old clamp in steps/s²: set to the axis limit itself (order X, Y, E, Z).
                    let spmm = events / mm;
                    let mut a_st = (a * spmm).ceil();
                    for i in [X, Y, E, Z] {
                        let axis_max = lim.max_accel[i] * lim.steps_per_mm[i];
                        if a_st * steps[i] / events > axis_max {
                            a_st = axis_max;
                        }
                    }
                    a = a_st / spmm;
                }
            }
        }
        let a = a.max(1e-3);

        // Junction: the most this block may enter at, given the previous one.
        let mut u = d;
        if !has_e {
            u[E] = 0.0;
        } // E joins the direction only when the block extrudes
        let un = norm(&u);
        u.iter_mut().for_each(|x| *x /= un);
        let max_entry = match (lim.junction, self.prev) {
            (Junction::Deviation { mm: jd }, Some((pu, _, pn)))
                if self.queued >= 1 && pn > 1e-6 =>
            {
                let cos = -(0..4).map(|i| pu[i] * u[i]).sum::<f64>();
                let vmax_sqr = if cos > 0.999_999 {
                    lim.min_planner_speed.powi(2) // full reversal
                } else {
                    let cos = cos.max(-0.999_999);
                    let mut ju = [0.0; 4];
                    (0..4).for_each(|i| ju[i] = u[i] - pu[i]);
                    let jn = norm(&ju);
                    let mut ja = a;
                    for i in 0..4 {
                        let c = (ju[i] / jn).abs();
                        if c > 0.0 && ja * c > lim.max_accel[i] {
                            ja = lim.max_accel[i] / c;
                        }
                    }
                    let sin_half = (0.5 * (1.0 - cos)).sqrt();
                    let mut vs = ja * jd * sin_half / (1.0 - sin_half);
                    if mm < 1.0 && cos < -std::f64::consts::FRAC_1_SQRT_2 {
                        // Short segments of a curve: limit to the centripetal a·r of its circle.
                        let theta = (-cos).acos().max(1e-3);
                        vs = vs.min(mm * ja / theta);
                    }
                    vs
                };
                vmax_sqr.min(nominal * nominal).min(pn * pn).sqrt()
            }
            (Junction::Deviation { .. }, _) => 0.0, // starts from rest
            (Junction::Classic { xy, z, e }, prev) => {
                // "Safe" speed: a start from rest is allowed half the jerk of each moving axis.
                let mut safe = xy / 2.0;
                if v[Z].abs() > z / 2.0 {
                    safe = safe.min(z / 2.0);
                }
                if v[E].abs() > e / 2.0 {
                    safe = safe.min(e / 2.0);
                }
                match prev {
                    Some((_, pv, pn)) if self.queued > 1 && pn > 1e-4 => {
                        let mut f: f64 = 1.0;
                        let jxy = (v[X] - pv[X]).hypot(v[Y] - pv[Y]);
                        for (jerk, lim_j) in [
                            (jxy, xy),
                            ((v[Z] - pv[Z]).abs(), z),
                            ((v[E] - pv[E]).abs(), e),
                        ] {
                            if jerk > lim_j {
                                f = f.min(lim_j / jerk);
                            }
                        }
                        pn.min(nominal * f)
                    }
                    _ => safe.min(nominal),
                }
            }
        };
        self.prev = Some((u, v, nominal));
        self.queued = (self.queued + 1).min(lim.block_buffer_size.saturating_sub(1).max(1));
        let max_entry_sqr = max_entry * max_entry;
        self.window.push_back(Block {
            cmd,
            mm,
            accel: a,
            nominal_sqr: nominal * nominal,
            max_entry_sqr,
            entry_sqr: 0.0,
        });
        // The front block starts when the buffer is full: it sees `size - 1` blocks incl. itself.
        if self.window.len() >= self.lim.block_buffer_size.saturating_sub(1).max(1) {
            self.plan();
            self.commit_front();
        }
    }

    /// Backward pass (each block must be able to slow to the next one's entry, the last to a
    /// stop), then forward pass (each block can only reach what it can accelerate to).
    fn plan(&mut self) {
        let mut next = self.lim.min_planner_speed.powi(2);
        for b in self.window.iter_mut().rev() {
            b.entry_sqr = b.max_entry_sqr.min(next + 2.0 * b.accel * b.mm);
            next = b.entry_sqr;
        }
        if let (Some(f), Some(b)) = (self.front_entry, self.window.front_mut()) {
            b.entry_sqr = f; // already running into it: frozen
        }
        for k in 1..self.window.len() {
            let p = &self.window[k - 1];
            let reach = p.entry_sqr + 2.0 * p.accel * p.mm;
            let b = &mut self.window[k];
            b.entry_sqr = b.entry_sqr.min(reach);
        }
    }

    fn commit_front(&mut self) {
        if let Some(b) = self.window.pop_front() {
            let exit = self
                .window
                .front()
                .map_or(self.lim.min_planner_speed.powi(2), |n| n.entry_sqr);
            let t = trapezoid_time(b.mm, b.accel, b.entry_sqr, exit, b.nominal_sqr);
            if t.is_finite() {
                self.total += t;
                let c = &mut self.per_cmd[b.cmd - self.first].0;
                *c = (*c as f64 + t).min(f32::MAX as f64 / 4.0) as f32;
            }
            self.front_entry = self.window.front().map(|n| n.entry_sqr);
        }
    }

    /// [`sync`](Self::sync) for command `cmd`, which waits for it.
    fn sync_at(&mut self, cmd: usize) {
        self.sync();
        if let Some(c) = self.per_cmd.get_mut(cmd - self.first) {
            c.1 = true;
        }
    }

    /// Drain the buffer to a standstill (G4, M400, heating waits, G28, G92 of X/Y/Z).
    fn sync(&mut self) {
        self.plan();
        while !self.window.is_empty() {
            self.commit_front();
        }
        (self.front_entry, self.queued, self.prev) = (None, 0, None); // next move starts from rest
    }

    /// Moves the commands before `upto` into the compact record.
    fn settle(&mut self, upto: usize) {
        while self.first < upto {
            let Some((t, sync)) = self.per_cmd.pop_front() else {
                break;
            };
            self.kept.push(t as f64, sync);
            self.first += 1;
        }
    }

    pub fn finish(mut self) -> Estimate {
        self.sync();
        self.settle(usize::MAX);
        Estimate {
            total_seconds: self.total,
            dwell_seconds: self.dwell,
            heating_waits: self.heat_waits,
            kept: self.kept,
        }
    }
}

impl Limits {
    /// The stock settings of `firmware`'s planner (the Marlin 2 family as 2.1.2.1 ships).
    pub fn of(firmware: crate::firmware::Firmware) -> Limits {
        use crate::firmware::Firmware;
        match firmware {
            Firmware::Ultimaker2 => Limits::ultimaker2(),
            Firmware::Marlin2 | Firmware::Marlin20 => Limits::marlin_2_1_2_1(),
        }
    }
}

/// The moves a printer on `firmware` may hold acknowledged but not yet made: its planner's
/// blocks (one fewer than its buffer's size: a ring that keeps one slot free), and on
/// Ultimaker2Marlin its command slots too (it acknowledges `G0`-`G3` as they are queued,
/// before they reach the planner).
pub fn moves_ahead(firmware: crate::firmware::Firmware) -> usize {
    use crate::firmware::Firmware;
    let planner = Limits::of(firmware).block_buffer_size - 1;
    match firmware {
        Firmware::Ultimaker2 => planner + firmware.command_slots(),
        Firmware::Marlin2 | Firmware::Marlin20 => planner,
    }
}

/// The planner's estimate of a job's commands (as loaded, one per command) on `firmware`
/// with its stock settings.
pub fn estimate<S: AsRef<str>>(
    commands: impl IntoIterator<Item = S>,
    firmware: crate::firmware::Firmware,
) -> Estimate {
    estimate_with(commands, Limits::of(firmware))
}

/// The planner's estimate of a job's commands with the planner's settings `limits` (a
/// printer's own, as it reported them).
pub fn estimate_with<S: AsRef<str>>(
    commands: impl IntoIterator<Item = S>,
    limits: Limits,
) -> Estimate {
    let mut estimator = Estimator::new(limits);
    for command in commands {
        estimator.feed(command.as_ref());
    }
    estimator.finish()
}

#[cfg(test)]
mod tests {
    use super::*;
    fn run(lim: Limits, g: &str) -> Estimate {
        let mut e = Estimator::new(lim);
        g.lines().for_each(|l| e.feed(l));
        e.finish()
    }
    fn m2(g: &str) -> f64 {
        run(Limits::marlin_2_1_2_1(), g).total_seconds
    }
    fn um2(g: &str) -> f64 {
        run(Limits::ultimaker2(), g).total_seconds
    }
    /// Closed-form trapezoid (ramps as mean speed × time), independent of the module's helper.
    fn trap(l: f64, a: f64, v0: f64, vn: f64, v1: f64) -> f64 {
        let (ta, tb) = ((vn - v0) / a, (vn - v1) / a);
        ta + tb + (l - (v0 + vn) / 2.0 * ta - (v1 + vn) / 2.0 * tb) / vn
    }
    fn close(a: f64, b: f64, tol: f64) {
        assert!((a - b).abs() <= tol, "{a} vs {b}");
    }

    #[test]
    fn long_move_is_a_trapezoid() {
        // Travel accel 3000, 100 mm/s, from rest to MINIMUM_PLANNER_SPEED.
        close(
            m2("G1 X100 F6000"),
            trap(100.0, 3000.0, 0.0, 100.0, 0.05),
            1e-9,
        );
    }

    #[test]
    fn short_move_is_a_triangle() {
        // 1 mm cannot reach 100 mm/s at 3000 mm/s²: peak v² = (2aL + v0² + v1²)/2.
        let vp = (3000.0f64 + 0.05f64.powi(2) / 2.0).sqrt();
        close(m2("G1 X1 F6000"), vp / 3000.0 + (vp - 0.05) / 3000.0, 1e-9);
    }

    #[test]
    fn collinear_joins_at_full_speed_corner_is_limited() {
        let one = m2("G1 X100 F6000");
        close(m2("G1 X50 F6000\nG1 X100"), one, 1e-9);
        // 90°: JD speed² = a·jd·sin(45°)/(1 - sin(45°)) ≈ 9.7 mm/s.
        let s = std::f64::consts::FRAC_1_SQRT_2;
        let vj = (3000.0 * 0.013 * s / (1.0 - s)).sqrt();
        let got = m2("G1 X50 F6000\nG1 Y50");
        close(
            got,
            trap(50.0, 3000.0, 0.0, 100.0, vj) + trap(50.0, 3000.0, vj, 100.0, 0.05),
            1e-9,
        );
        assert!(got > one + 0.02); // two ramps 100 -> 9.7 -> 100 mm/s cost ~0.027 s
                                   // Classic jerk (UM2): XY vector change 141 mm/s > 20 scales the corner to 14 mm/s.
        assert!(um2("G1 X1 F6000\nG1 X50\nG1 Y50") > um2("G1 X1 F6000\nG1 X50\nG1 X99") + 0.01);
    }

    #[test]
    fn per_axis_feed_and_accel_limit() {
        close(m2("G1 Z10 F6000"), trap(10.0, 100.0, 0.0, 5.0, 0.05), 1e-9); // Z: 5 mm/s, 100 mm/s²
                                                                            // UM2 Z: 40 mm/s, 100 mm/s², starts at the jerk "safe speed" Z/2 = 0.2 mm/s; 10 mm
                                                                            // peaks below 40 mm/s.
        let vp = ((2.0 * 100.0 * 10.0 + 0.2f64.powi(2) + 0.05f64.powi(2)) / 2.0).sqrt();
        close(
            um2("G1 Z10 F6000"),
            (vp - 0.2) / 100.0 + (vp - 0.05) / 100.0,
            1e-9,
        );
    }

    #[test]
    fn relative_absolute_and_g92() {
        close(
            m2("G91\nG1 X10 F3000\nG1 X10"),
            m2("G90\nG1 X10 F3000\nG1 X20"),
            1e-12,
        );
        assert_eq!(m2("G1 X10 F3000\nG1 X10"), m2("G1 X10 F3000"));
        close(
            m2("G1 X10 F3000\nG92 X0\nG1 X10"),
            2.0 * m2("G1 X10 F3000"),
            1e-9,
        );
        close(
            m2("M83\nG1 X10 E1 F3000\nG1 X20 E1"),
            m2("M82\nG1 X10 E1 F3000\nG1 X20 E2"),
            1e-12,
        );
        close(
            m2("G1 X10 E1 F3000\nG92 E0\nG1 X20 E1"),
            m2("M83\nG1 X10 E1 F3000\nG1 X20 E1"),
            1e-12,
        );
        // Marlin 2's G90 resets M83; UM2's does not.
        assert!(m2("M83\nG90\nG1 E5 F600\nG1 E5") < um2("M83\nG90\nG1 E5 F600\nG1 E5") - 0.5);
    }

    #[test]
    fn m204_mid_file_changes_later_moves() {
        let base = m2("G1 X100 F6000");
        close(
            m2("M204 T500\nG1 X100 F6000"),
            trap(100.0, 500.0, 0.0, 100.0, 0.05),
            1e-9,
        );
        close(m2("G1 X100 F6000\nM204 T500"), base, 1e-12);
        close(m2("M204 P500\nG1 X100 F6000"), base, 1e-12); // print accel: this move has no E
        let mut l = Limits::ultimaker2();
        let keys = l.apply_m503("echo:  M204 S1000 T2000\necho:  M203 X200 Y200 Z5 E25\nok\n");
        assert_eq!(
            (l.accel, l.retract_accel, l.max_feedrate[Z], keys.len()),
            (1000.0, 2000.0, 5.0, 6)
        );
        let mut m = Limits::marlin_2_1_2_1();
        m.apply_m503(
            "echo:  M204 P1500.00 R3000.00 T2500.00\necho:  M205 B20000.00 S0.00 T0.00 J0.02",
        );
        assert_eq!(
            (m.accel, m.travel_accel, m.junction),
            (1500.0, Some(2500.0), Junction::Deviation { mm: 0.02 })
        );
    }

    #[test]
    fn progress_heating_arcs() {
        let g = "; header\nM190 S60\nM109 S200\nG28\nG1 X10 F3000 ; move\n\nG4 P500\nG1 Y50\nM116\nG2 X0 Y50 I-5 J0\n";
        let est = run(Limits::marlin_2_1_2_1(), g);
        assert_eq!((est.heating_waits, est.commands()), (3, 8));
        close(est.dwell_seconds, 0.5, 1e-12);
        assert_eq!(
            (
                est.elapsed_at(0),
                est.left_after(8),
                est.left_after(usize::MAX)
            ),
            (0.0, 0.0, 0.0)
        );
        close(est.left_after(0), est.total_seconds, 1e-3);
        let left: Vec<f64> = (0..=9).map(|k| est.left_after(k)).collect();
        assert!(left.windows(2).all(|p| p[1] <= p[0]), "{left:?}");
        // Half circle r=5 at 50 mm/s: a little more than length / speed.
        let arc = m2("G1 X10 F3000\nG2 X0 Y0 I-5 J0") - m2("G1 X10 F3000");
        assert!(
            arc > 5.0 * std::f64::consts::PI / 50.0 && arc < 0.45,
            "{arc}"
        );
        let um2_arc = um2("G1 X10 F3000\nG2 X0 Y0 I-5 J0") - um2("G1 X10 F3000"); // 15 segments
        assert!(
            um2_arc > 5.0 * std::f64::consts::PI / 50.0 && um2_arc < 0.45,
            "{um2_arc}"
        );
    }

    #[test]
    fn garbage_does_not_panic() {
        let nasty = "G1 X1e999\nG1 X99999999999999999999999999999999999999999999 F1\nG1 F0 X10\nG1 FNaN\n\
            M203 X0 Y-1\nM204 S-5\nM205 J-1 X-3\nG2 X10 I0 J0\nG2 R0 X1\nG3 R-1e9 X1e9\nG1 X--1\nG...\n\
            M220 S0\nG4 P-1\nG4 S1e300\nN5 G1 X5*99\nG1 X.\n\u{0}\u{ff}\nG92 X1e9\nG91\nG1 X1e9 F1e9\nG1 X1e9\n\
            G1 X1e9\nG2 X0 Y0 I1e9 J1e9 F6000";
        for lim in [Limits::marlin_2_1_2_1(), Limits::ultimaker2()] {
            let r = run(lim.clone(), nasty);
            assert!(r.total_seconds.is_finite() && r.left_after(0).is_finite());
            // Random bytes from a fixed LCG, biased toward G-code characters.
            let (mut x, mut e) = (0x9E37_79B9_7F4A_7C15u64, Estimator::new(lim));
            for _ in 0..3000 {
                let mut b = Vec::new();
                for _ in 0..(x >> 59) as usize + 1 {
                    x = x
                        .wrapping_mul(6364136223846793005)
                        .wrapping_add(1442695040888963407);
                    let (abc, r) = (b"GMXYZEFIJRPST0123456789.-+ ;\n*N", (x >> 33) as usize);
                    b.push(if r % 4 == 0 {
                        (r >> 8) as u8
                    } else {
                        abc[r % abc.len()]
                    });
                }
                String::from_utf8_lossy(&b).lines().for_each(|l| e.feed(l));
            }
            let r = e.finish();
            assert!(r.total_seconds.is_finite() && r.total_seconds >= 0.0);
        }
    }

    #[test]
    fn moves_acknowledged_but_still_in_the_planner_are_still_to_come() {
        let g: String = (1..=40).map(|i| format!("G1 X{} F6000\n", i * 5)).collect();
        let e = run(Limits::marlin_2_1_2_1(), &format!("{g}M400\n{g}"));
        // 20 moves acknowledged, 16 of them perhaps still in the planner: 4 made.
        close(e.left_after_acked(20, 16), e.left_after(4), 1e-9);
        // Past the M400 (command 40), the moves before it are made whatever the planner
        // holds.
        close(e.left_after_acked(43, 16), e.left_after(41), 1e-9);
        // All acknowledged: the last 16 moves may still be in the planner.
        close(e.left_after_acked(81, 16), e.left_after(65), 1e-9);
        assert!(e.left_after_acked(60, 16) > e.left_after(60));
    }
}
