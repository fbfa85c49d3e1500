//! One follower of G-code motion, as Marlin moves the head: every reader of G-code that
//! needs to know where the nozzle goes (in `slice`: the slicer-output check `gcode`, the
//! pre-sliced check `presliced`, the outer-wall measure `walls`, the G-code policy
//! `policy`; in the host: where a pause parks the head and where the print resumes,
//! the sibling `pause`) reads commands with [`crate::reader`] and follows them
//! with one [`Motion`], so they cannot disagree about where a file sends the printer.
//!
//! Positions are kept in the machine's own coordinates (where the head physically is,
//! homed at 0), apart from the coordinates the file writes: `G92` shifts the file's
//! coordinates against the machine's, and `M206` (home offsets) does too. A move's extent
//! is what the head sweeps, not just where it ends: arcs (`G2`/`G3`, I/J and R forms, full
//! circles, P turns) reach their circle's extremes, a Bézier move (`G5`) stays in the hull
//! of its control points.
//!
//! Every position is computed as the firmware computes it, in its 32-bit floats (each
//! number read as its own `strtof` or avr-libc `strtod` reads it, `G92` and offsets as its
//! workspace keeps them, arcs through its own `plan_arc` or `mc_arc`: [`firmware_arc`]), and
//! again from the file's own numbers in 64-bit: where the two disagree on what the printer
//! does (an arc a whole circle in one, a sliver in the other; the bed's edge), or the
//! firmware would skip the move or answer an error, the line is refused. The rules, with
//! their source lines, are in `docs/gcode-policy.md` ("Arithmetic").
//!
//! What cannot be followed for certain is refused ([`Unfollowable`]), never guessed:
//! workspace coordinate systems (`G53`–`G59`, `G10 L2`/`L20`: off in stock Marlin, kept in
//! EEPROM where on, so a file's offsets would shift every later job), other arc planes
//! (`G18`, `G19`), inch units (`G20`), direct stepper moves (`G6`), `M428`, and arcs without
//! a centre. Lines are read by [`crate::reader`], which takes only what every
//! firmware reads alike (so no sub-codes such as `G92.1`: stock Marlin runs them as `G92`).

use crate::firmware::Firmware;
use std::f64::consts::{FRAC_PI_2, PI, TAU};
use std::ops::{Add, Div, Mul, Neg, Sub};

pub use crate::reader::Command;

/// A command the follower cannot follow for certain; the text says what and why.
#[derive(Clone, Debug, PartialEq, thiserror::Error)]
#[error("{0}")]
pub struct Unfollowable(pub String);

/// An arc whose end is this close to its start, as the file writes it, is a whole circle
/// (the rounding of 64-bit sums of the file's numbers, not a distance the file means).
const WHOLE_MM: f64 = 1e-9;
/// An arc that ends closer than this to where a whole circle or no arc at all would end
/// is refused: whether a firmware runs a circle, a sliver or nothing there turns on its
/// 32-bit rounding (and on its build: the Linux, ARM and AVR ones round apart).
const NEAR_MM: f64 = 1e-3;
/// How far the firmware's arc may end from the file's, along the circle, before the two
/// readings count as different arcs.
const ARC_AGREE_MM: f64 = 0.01;

/// One move: where it started and ended (machine X, Y, Z and the file's E), and the box
/// the head swept on the way (machine coordinates), as the firmware computes them.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Move {
    pub from: [f64; 4],
    pub to: [f64; 4],
    pub lo: [f64; 3],
    pub hi: [f64; 3],
    /// An arc or curve (its chord is from..to).
    pub curved: bool,
    /// The box as the file's own numbers put it (in 64-bit, lowest and highest corner),
    /// where `lo`..`hi` is the firmware's (its 32-bit floats): they differ by rounding.
    pub written: ([f64; 3], [f64; 3]),
}

/// Where a move stands against a bed.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum Bounds {
    Inside,
    /// Leaves it along this axis, as the firmware computes the move.
    Outside(usize),
    /// The firmware's 32-bit reading and the file's own disagree on whether the move stays
    /// within this axis's bounds.
    Rounding(usize),
}

impl Move {
    /// Filament pushed (negative: retracted), mm.
    pub fn extruded(&self) -> f64 {
        self.to[3] - self.from[3]
    }
    pub fn moves_xy(&self) -> bool {
        self.to[0] != self.from[0] || self.to[1] != self.from[1] || self.curved
    }
    pub fn moves_xyz(&self) -> bool {
        self.moves_xy() || self.to[2] != self.from[2]
    }

    /// Whether the move stays on a bed of `bed` mm (with `edge` allowance), read both as
    /// the firmware computes it and as the file writes it.
    pub fn bounds(&self, bed: [f64; 3], edge: f64) -> Bounds {
        let firmware = outside(self.lo, self.hi, bed, edge);
        let written = outside(self.written.0, self.written.1, bed, edge);
        match (firmware, written) {
            (None, None) => Bounds::Inside,
            (Some(k), Some(_)) => Bounds::Outside(k),
            (Some(k), None) | (None, Some(k)) => Bounds::Rounding(k),
        }
    }
}

/// Where the first axis of `lo..hi` leaves `0..bed` (with `edge` allowance), if any; a
/// coordinate that is no number counts as outside.
pub fn outside(lo: [f64; 3], hi: [f64; 3], bed: [f64; 3], edge: f64) -> Option<usize> {
    (0..3).find(|&k| !(lo[k] >= -edge && hi[k] <= bed[k] + edge))
}

/// The arithmetic a frame computes in: `f32`, as both firmwares do (Marlin 2.1's
/// positions, offsets and arcs are `float`; Ultimaker2Marlin's `double` is 32-bit on the
/// AVR), or `f64` for the file's own reading. Rust's `f32` rounds each operation to
/// nearest as x86-64 (no fused multiply-add by default) and avr-libc's float routines do.
pub trait Real:
    Copy
    + PartialOrd
    + std::fmt::Debug
    + Add<Output = Self>
    + Sub<Output = Self>
    + Mul<Output = Self>
    + Div<Output = Self>
    + Neg<Output = Self>
{
    const ZERO: Self;
    const ONE: Self;
    /// A whole turn as the firmwares have it: Marlin's `RADIANS(360)` (`360 *
    /// float(M_PI) / 180.0f`), Ultimaker2Marlin's `2*M_PI` on a 32-bit double.
    const TURN: Self;
    /// A constant of the firmware's source (`0.000001f`).
    fn of(v: f64) -> Self;
    fn wide(self) -> f64;
    fn sqrt(self) -> Self;
    fn atan2(self, x: Self) -> Self;
    fn abs(self) -> Self;
    /// A parameter as read in this arithmetic: the firmware's float, or the file's number.
    fn value(cmd: &Command, letter: char, firmware: Firmware) -> Option<Self>;
}

impl Real for f32 {
    const ZERO: f32 = 0.0;
    const ONE: f32 = 1.0;
    const TURN: f32 = std::f32::consts::TAU;
    fn of(v: f64) -> f32 {
        v as f32
    }
    fn wide(self) -> f64 {
        f64::from(self)
    }
    fn sqrt(self) -> f32 {
        f32::sqrt(self)
    }
    fn atan2(self, x: f32) -> f32 {
        f32::atan2(self, x)
    }
    fn abs(self) -> f32 {
        f32::abs(self)
    }
    fn value(cmd: &Command, letter: char, firmware: Firmware) -> Option<f32> {
        cmd.get_f32(letter, firmware)
    }
}

impl Real for f64 {
    const ZERO: f64 = 0.0;
    const ONE: f64 = 1.0;
    const TURN: f64 = TAU;
    fn of(v: f64) -> f64 {
        v
    }
    fn wide(self) -> f64 {
        self
    }
    fn sqrt(self) -> f64 {
        f64::sqrt(self)
    }
    fn atan2(self, x: f64) -> f64 {
        f64::atan2(self, x)
    }
    fn abs(self) -> f64 {
        f64::abs(self)
    }
    fn value(cmd: &Command, letter: char, _: Firmware) -> Option<f64> {
        cmd.get(letter)
    }
}

/// Marlin's `NEAR_ZERO` (`macros.h`): within `0.000001f`, bounds included.
fn near_zero<T: Real>(d: T) -> bool {
    d >= -T::of(1e-6) && d <= T::of(1e-6)
}

/// Where a firmware keeps the head, in one arithmetic.
#[derive(Clone, Debug)]
struct Frame<T> {
    /// The firmware's `current_position`: on Marlin 2 native X, Y, Z (the machine's,
    /// homed at 0), on Ultimaker2Marlin the file's own (its `G92` sets it); E the file's.
    pos: [T; 4],
    /// Marlin 2's `position_shift` (`G92`), `home_offset` (`M206`) and their sum, its
    /// `workspace_offset`: the file's coordinate is `pos + ws`. Ultimaker2Marlin's
    /// `add_homing` (`M206`, in force from the next homing) is `home` too.
    shift: [T; 3],
    home: [T; 3],
    ws: [T; 3],
    /// Ultimaker2Marlin: its coordinate minus the machine's (what `G92` and homing with a
    /// home offset changed), exact: differences of its floats.
    um2: [f64; 3],
    /// Where `G60` saved the head.
    saved: Option<[T; 3]>,
}

impl<T: Real> Frame<T> {
    fn new() -> Frame<T> {
        Frame {
            pos: [T::ZERO; 4],
            shift: [T::ZERO; 3],
            home: [T::ZERO; 3],
            ws: [T::ZERO; 3],
            um2: [0.0; 3],
            saved: None,
        }
    }

    /// A coordinate of axis `k` (0..3) of this frame, on the machine.
    fn to_machine(&self, fw: Firmware, k: usize, v: T) -> f64 {
        match fw {
            Firmware::Ultimaker2 => v.wide() - self.um2[k],
            Firmware::Marlin2 | Firmware::Marlin20 => v.wide(),
        }
    }

    /// Machine X, Y, Z and the file's E.
    fn machine(&self, fw: Firmware) -> [f64; 4] {
        std::array::from_fn(|k| match k {
            3 => self.pos[3].wide(),
            _ => self.to_machine(fw, k, self.pos[k]),
        })
    }

    /// The file's coordinate minus the machine's, per axis.
    fn offset(&self, fw: Firmware, k: usize) -> f64 {
        match fw {
            Firmware::Ultimaker2 => self.um2[k],
            Firmware::Marlin2 | Firmware::Marlin20 => self.ws[k].wide(),
        }
    }

    /// Where the head is in the file's coordinates, as the firmware's `M114` reports it
    /// (Marlin 2: `NATIVE_TO_LOGICAL`, a float sum).
    fn file(&self, fw: Firmware, k: usize) -> f64 {
        match fw {
            Firmware::Ultimaker2 => self.pos[k].wide(),
            Firmware::Marlin2 | Firmware::Marlin20 => (self.pos[k] + self.ws[k]).wide(),
        }
    }

    /// Where a move's axes end: Marlin 2's `get_destination_from_command` (`gcode.cpp`
    /// 185-205: relative `current + v`, absolute `LOGICAL_TO_NATIVE(v)` = `v -
    /// workspace_offset`), Ultimaker2Marlin's `get_coordinates` (`Marlin_main.cpp` 2489-2500:
    /// `v + relative * current`).
    fn target(&self, cmd: &Command, fw: Firmware, relative: [bool; 4]) -> [T; 4] {
        let mut to = self.pos;
        for (k, letter) in ['X', 'Y', 'Z', 'E'].into_iter().enumerate() {
            let Some(v) = T::value(cmd, letter, fw) else {
                continue;
            };
            to[k] = if relative[k] {
                self.pos[k] + v
            } else if k == 3 || fw == Firmware::Ultimaker2 {
                v
            } else {
                v - self.ws[k]
            };
        }
        to
    }

    /// `G92`: Marlin 2 (`G92.cpp` 88-117) shifts its workspace by the difference unless it
    /// is `NEAR_ZERO` (E is set, likewise only if not near); Ultimaker2Marlin
    /// (`Marlin_main.cpp` 1146-1160) sets its position, and the machine stays.
    fn g92(&mut self, cmd: &Command, fw: Firmware) {
        for (k, letter) in ['X', 'Y', 'Z', 'E'].into_iter().enumerate() {
            let Some(v) = T::value(cmd, letter, fw) else {
                continue;
            };
            match fw {
                Firmware::Ultimaker2 => {
                    if k < 3 {
                        self.um2[k] += v.wide() - self.pos[k].wide();
                    }
                    self.pos[k] = v;
                }
                Firmware::Marlin2 | Firmware::Marlin20 => {
                    let native = if k == 3 { v } else { v - self.ws[k] };
                    let d = native - self.pos[k];
                    if near_zero(d) {
                        continue;
                    }
                    if k == 3 {
                        self.pos[3] = native;
                    } else {
                        self.shift[k] = self.shift[k] + d;
                        self.ws[k] = self.home[k] + self.shift[k];
                    }
                }
            }
        }
    }

    /// Homing axis `k`: Marlin 2's `set_axis_is_at_home` (`motion.cpp` 2317-2365: native at
    /// home, the shift dropped); Ultimaker2Marlin's `axis_is_at_home` (`Marlin_main.cpp`
    /// 770: home plus `add_homing`, in its own coordinates).
    fn g28(&mut self, fw: Firmware, k: usize) {
        match fw {
            Firmware::Ultimaker2 => {
                self.pos[k] = self.home[k];
                self.um2[k] = self.home[k].wide();
            }
            Firmware::Marlin2 | Firmware::Marlin20 => {
                self.pos[k] = T::ZERO;
                self.shift[k] = T::ZERO;
                self.ws[k] = self.home[k] + self.shift[k];
            }
        }
    }

    /// `M206`: Marlin 2's `set_home_offset` (`motion.cpp` 2387-2390) at once;
    /// Ultimaker2Marlin's `add_homing` from the next homing.
    fn m206(&mut self, fw: Firmware, k: usize, v: T) {
        self.home[k] = v;
        if fw != Firmware::Ultimaker2 {
            self.ws[k] = self.home[k] + self.shift[k];
        }
    }
}

/// What a firmware does with a `G2`/`G3`, computed in its arithmetic.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum ArcRun<T> {
    /// It turns `sweep` radians (negative: clockwise) about `centre` (its own
    /// coordinates) from its start, and ends at the end; `whole`: it took the end for the
    /// start and runs a whole circle.
    Runs {
        centre: [T; 2],
        radius: T,
        sweep: T,
        whole: bool,
    },
    /// Marlin 2 answers `Error:G2/G3 bad parameters` and stays where it is.
    BadParameters,
    /// It plans no move: Marlin 2 stays where it is (Z and E included), Ultimaker2Marlin
    /// takes the end as reached.
    Skipped(Skip),
}

#[derive(Clone, Copy, Debug, PartialEq)]
pub enum Skip {
    /// Marlin 2: no angle to turn (the end on the line from the centre through the start).
    NoAngle,
    /// Shorter than Marlin 2's 0.0001 mm (and not rising in Z) or Ultimaker2Marlin's 0.001 mm.
    Short,
}

/// A `G2` (`clockwise`) or `G3` from `from` to `to` (the firmware's own coordinates, its
/// destination already computed), with the `R`, `I`, `J` it read, as `fw` runs it in
/// arithmetic `T`.
pub fn firmware_arc<T: Real>(
    fw: Firmware,
    clockwise: bool,
    from: [T; 4],
    to: [T; 4],
    [r, i, j]: [Option<T>; 3],
) -> ArcRun<T> {
    let zero = T::ZERO;
    match fw {
        Firmware::Marlin2 | Firmware::Marlin20 => {
            // GcodeSuite::G2_G3 (G2_G3.cpp 442-474): R wins over I and J; an offset of
            // (0, 0) is "bad parameters".
            let offset = match r {
                Some(r) => {
                    let (p1, p2) = ([from[0], from[1]], [to[0], to[1]]);
                    if r != zero && p1 != p2 {
                        r_offset(clockwise, p1, p2, r)
                    } else {
                        [zero, zero]
                    }
                }
                None => [i.unwrap_or(zero), j.unwrap_or(zero)],
            };
            if offset[0] == zero && offset[1] == zero {
                return ArcRun::BadParameters;
            }
            // plan_arc (G2_G3.cpp 76-126).
            let rvec = [-offset[0], -offset[1]];
            let radius = (rvec[0] * rvec[0] + rvec[1] * rvec[1]).sqrt();
            let centre = [from[0] - rvec[0], from[1] - rvec[1]];
            let rt = [to[0] - centre[0], to[1] - centre[1]];
            let (sweep, whole) = if near_zero(from[0] - to[0]) && near_zero(from[1] - to[1]) {
                (if clockwise { -T::TURN } else { T::TURN }, true)
            } else {
                let mut a =
                    (rvec[0] * rt[1] - rvec[1] * rt[0]).atan2(rvec[0] * rt[0] + rvec[1] * rt[1]);
                if a == zero {
                    return ArcRun::Skipped(Skip::NoAngle);
                }
                if a > zero && clockwise {
                    a = a - T::TURN;
                } else if a < zero && !clockwise {
                    a = a + T::TURN;
                }
                (a, false)
            };
            // G2_G3.cpp 182-195: Z's travel is compared signed, as written there.
            let flat = radius * sweep.abs();
            if flat < T::of(1e-4) && to[2] - from[2] < T::of(1e-4) {
                return ArcRun::Skipped(Skip::Short);
            }
            ArcRun::Runs {
                centre,
                radius,
                sweep,
                whole,
            }
        }
        Firmware::Ultimaker2 => {
            // get_arc_coordinates (Marlin_main.cpp 2545-2568): I, J or 0; mc_arc
            // (motion_control.cpp 33-48).
            let offset = [i.unwrap_or(zero), j.unwrap_or(zero)];
            let centre = [from[0] + offset[0], from[1] + offset[1]];
            let r = [-offset[0], -offset[1]];
            let rt = [to[0] - centre[0], to[1] - centre[1]];
            let mut a = (r[0] * rt[1] - r[1] * rt[0]).atan2(r[0] * rt[0] + r[1] * rt[1]);
            if a < zero {
                a = a + T::TURN;
            }
            if clockwise {
                a = a - T::TURN;
            }
            let radius = (offset[0] * offset[0] + offset[1] * offset[1]).sqrt();
            let flat = a * radius;
            let linear = to[2] - from[2];
            if (flat * flat + linear * linear).sqrt() < T::of(1e-3) {
                return ArcRun::Skipped(Skip::Short);
            }
            ArcRun::Runs {
                centre,
                radius,
                sweep: a,
                whole: from[0] == to[0] && from[1] == to[1] && a.abs().wide() > PI,
            }
        }
    }
}

/// Marlin 2's centre of an R arc, relative to its start (G2_G3.cpp 448-454).
fn r_offset<T: Real>(clockwise: bool, p1: [T; 2], p2: [T; 2], r: T) -> [T; 2] {
    let half = T::of(0.5);
    let d2 = [(p2[0] - p1[0]) * half, (p2[1] - p1[1]) * half];
    let e = if clockwise ^ (r < T::ZERO) {
        -T::ONE
    } else {
        T::ONE
    };
    let len = (d2[0] * d2[0] + d2[1] * d2[1]).sqrt();
    let h2 = (r - len) * (r + len);
    let h = if h2 >= T::ZERO { h2.sqrt() } else { T::ZERO };
    let s = [-d2[1], d2[0]];
    [d2[0] + s[0] / len * e * h, d2[1] + s[1] / len * e * h]
}

/// The box an arc sweeps (machine coordinates): its start, its end and every extreme of
/// its circle it passes, turning `sweep` radians about `centre` from `from`.
fn arc_box(from: [f64; 4], to: [f64; 4], centre: [f64; 2], sweep: f64) -> ([f64; 3], [f64; 3]) {
    let (mut lo, mut hi) = line_box(from, to);
    let r = (from[0] - centre[0])
        .hypot(from[1] - centre[1])
        .max((to[0] - centre[0]).hypot(to[1] - centre[1]));
    let a0 = (from[1] - centre[1]).atan2(from[0] - centre[0]);
    for k in 0..4 {
        let theta = f64::from(k) * FRAC_PI_2;
        let from_start = if sweep < 0.0 {
            (a0 - theta).rem_euclid(TAU)
        } else {
            (theta - a0).rem_euclid(TAU)
        };
        if sweep.abs() >= TAU || from_start <= sweep.abs() {
            let e = [centre[0] + r * theta.cos(), centre[1] + r * theta.sin()];
            for (k, v) in e.into_iter().enumerate() {
                lo[k] = lo[k].min(v);
                hi[k] = hi[k].max(v);
            }
        }
    }
    (lo, hi)
}

fn line_box(from: [f64; 4], to: [f64; 4]) -> ([f64; 3], [f64; 3]) {
    (
        std::array::from_fn(|k| from[k].min(to[k])),
        std::array::from_fn(|k| from[k].max(to[k])),
    )
}

/// The follower's state: where the head is, as the firmware computes it (its 32-bit
/// floats) and as the file's own numbers put it (64-bit), and how the file's coordinates
/// map onto the machine's.
#[derive(Clone, Debug)]
pub struct Motion {
    /// The firmware's reading.
    fw: Frame<f32>,
    /// The file's own reading, in 64-bit: where the two disagree on what the printer does
    /// (a whole circle or a sliver, on the bed or off it), the line is refused.
    written: Frame<f64>,
    /// `G90` (true) or `G91`.
    absolute: bool,
    /// E's own mode, `M82` (true) or `M83`; on Marlin 2 `G90`/`G91` set it too.
    absolute_e: bool,
    /// Whether the position `G60` saved was known, per axis.
    saved_known: [bool; 3],
    /// Whether the file has said where the head is: X, Y, Z on the machine (not after
    /// homing, whose position the file does not give, until an absolute move) and its E.
    /// The bed checks count from the origin either way; a pause parks only a head whose
    /// place is known, since a blind move could hit the print.
    known: [bool; 4],
    /// Whether `G92`'s shift of X, Y, Z is known: one given while the axis's position was
    /// not known makes the file's coordinates count from an unknown place.
    shift_known: [bool; 3],
    /// The last feed rate (mm/min) a move gave.
    feed: Option<f64>,
    firmware: Firmware,
}

impl Default for Motion {
    fn default() -> Self {
        Motion::new(Firmware::Marlin2)
    }
}

impl Motion {
    /// A printer of this firmware at its origin (where a file's first `G28` puts it; a file
    /// that never homes is taken to start there too).
    pub fn new(firmware: Firmware) -> Motion {
        Motion {
            fw: Frame::new(),
            written: Frame::new(),
            absolute: true,
            absolute_e: true,
            saved_known: [false; 3],
            known: [false; 4],
            shift_known: [true; 3],
            feed: None,
            firmware,
        }
    }

    /// Whether E moves are relative: `M83`, or on Marlin 2 a `G91` not followed by `M82`;
    /// on Ultimaker2Marlin (Marlin 1) `G91` makes E relative whatever `M82` said.
    pub(crate) fn e_relative(&self) -> bool {
        match self.firmware {
            Firmware::Ultimaker2 => !self.absolute || !self.absolute_e,
            Firmware::Marlin2 | Firmware::Marlin20 => !self.absolute_e,
        }
    }

    /// Whether X, Y and Z moves are relative (`G91`).
    pub(crate) fn xyz_relative(&self) -> bool {
        !self.absolute
    }

    /// The commands that put the firmware back into the file's modes (positioning and E),
    /// after a host's own lines changed them.
    pub(crate) fn mode_commands(&self) -> [&'static str; 2] {
        [
            if self.absolute { "G90" } else { "G91" },
            if self.absolute_e { "M82" } else { "M83" },
        ]
    }

    /// Machine X, Y, Z, where the file has said where the head is (see [`Motion::new`]).
    pub(crate) fn known_machine_position(&self) -> Option<[f64; 3]> {
        let [x, y, z, _] = self.position();
        (self.known[0] && self.known[1] && self.known[2]).then_some([x, y, z])
    }

    /// Where the head is in the file's own coordinates (what a `G90` move in the file
    /// names, and what the firmware's `M114` reports), per axis where known; E the file's.
    pub fn file_position(&self) -> [Option<f64>; 4] {
        std::array::from_fn(|k| match k {
            3 => self.known[3].then(|| self.fw.pos[3].wide()),
            _ => (self.known[k] && self.shift_known[k]).then(|| self.fw.file(self.firmware, k)),
        })
    }

    /// A machine coordinate of axis `k` (0..3) in the file's coordinates.
    pub fn to_file(&self, k: usize, machine: f64) -> f64 {
        machine + self.fw.offset(self.firmware, k)
    }

    /// The last feed rate a move gave, mm/min.
    pub(crate) fn feed(&self) -> Option<f64> {
        self.feed
    }

    /// Machine X, Y, Z and the file's E, as the firmware holds them.
    pub fn position(&self) -> [f64; 4] {
        self.fw.machine(self.firmware)
    }

    /// Whether a move's value for axis X, Y, Z, E is a distance, not a position.
    fn relative(&self) -> [bool; 4] {
        [
            !self.absolute,
            !self.absolute,
            !self.absolute,
            self.e_relative(),
        ]
    }

    /// After a move (`G0`-`G3`, `G5`): an axis it named absolutely is known from then on
    /// (X, Y, Z where the shift is known); the feed rate it gave stays in force.
    fn moved(&mut self, cmd: &Command) {
        let relative = self.relative();
        for (k, letter) in ['X', 'Y', 'Z', 'E'].into_iter().enumerate() {
            if !relative[k] && cmd.get(letter).is_some() {
                self.known[k] = k == 3 || self.shift_known[k];
            }
        }
        if let Some(f) = cmd.get('F') {
            self.feed = Some(f);
        }
    }

    /// Follows one command; a move is returned with what it swept.
    pub fn apply(&mut self, cmd: &Command) -> Result<Option<Move>, Unfollowable> {
        let moved = self.follow(cmd);
        if matches!(cmd.code.as_str(), "G0" | "G1" | "G2" | "G3" | "G5") && moved.is_ok() {
            self.moved(cmd);
        }
        moved
    }

    fn follow(&mut self, cmd: &Command) -> Result<Option<Move>, Unfollowable> {
        let refuse = |why: &str| Err(Unfollowable(format!("{} {why}", cmd.code)));
        let fw = self.firmware;
        match cmd.code.as_str() {
            "G0" | "G1" => {
                let relative = self.relative();
                let to = (
                    self.fw.target(cmd, fw, relative),
                    self.written.target(cmd, fw, relative),
                );
                Ok(Some(self.go(to, None)))
            }
            "G2" | "G3" => self.arc(cmd),
            "G5" => {
                // A cubic Bézier lies inside the hull of its control points: start + (I,
                // J), end + (P, Q).
                let relative = self.relative();
                let to = (
                    self.fw.target(cmd, fw, relative),
                    self.written.target(cmd, fw, relative),
                );
                let offsets = ['I', 'J', 'P', 'Q'].map(|l| cmd.get(l).unwrap_or(0.0));
                Ok(Some(self.go(to, Some(offsets))))
            }
            "G90" | "G91" => {
                self.absolute = cmd.code == "G90";
                // Marlin 2 sets every axis's mode, E's with them; Marlin 1 keeps M82/M83.
                if fw != Firmware::Ultimaker2 {
                    self.absolute_e = self.absolute;
                }
                Ok(None)
            }
            "M82" => {
                self.absolute_e = true;
                Ok(None)
            }
            "M83" => {
                self.absolute_e = false;
                Ok(None)
            }
            "G92" => {
                self.fw.g92(cmd, fw);
                self.written.g92(cmd, fw);
                for (k, letter) in ['X', 'Y', 'Z', 'E'].into_iter().enumerate() {
                    if cmd.get(letter).is_some() {
                        if k < 3 {
                            self.shift_known[k] = self.known[k];
                        } else {
                            self.known[3] = true;
                        }
                    }
                }
                Ok(None)
            }
            "G28" => {
                let named: Vec<usize> = ['X', 'Y', 'Z']
                    .into_iter()
                    .enumerate()
                    .filter(|(_, l)| cmd.has(*l))
                    .map(|(k, _)| k)
                    .collect();
                let axes = if named.is_empty() {
                    vec![0, 1, 2]
                } else {
                    named
                };
                // Homed axes are at the origin (Z's endstop may be at the bottom on an
                // Ultimaker 2; its start code moves Z absolutely, so 0 is safe), and homing
                // ends G92's shift for them.
                for k in axes {
                    self.fw.g28(fw, k);
                    self.written.g28(fw, k);
                    self.known[k] = false;
                    self.shift_known[k] = true;
                }
                Ok(None)
            }
            "M206" => {
                for (k, letter) in ['X', 'Y', 'Z'].into_iter().enumerate() {
                    if let (Some(v32), Some(v64)) = (cmd.get_f32(letter, fw), cmd.get(letter)) {
                        self.fw.m206(fw, k, v32);
                        self.written.m206(fw, k, v64);
                    }
                }
                Ok(None)
            }
            "G60" => {
                self.fw.saved = Some([self.fw.pos[0], self.fw.pos[1], self.fw.pos[2]]);
                self.written.saved = Some([
                    self.written.pos[0],
                    self.written.pos[1],
                    self.written.pos[2],
                ]);
                self.saved_known = [self.known[0], self.known[1], self.known[2]];
                Ok(None)
            }
            "G61" => {
                let (Some(saved32), Some(saved64)) = (self.fw.saved, self.written.saved) else {
                    return Ok(None);
                };
                let mut to = (self.fw.pos, self.written.pos);
                let any = ['X', 'Y', 'Z'].iter().any(|l| cmd.has(*l));
                for (k, letter) in ['X', 'Y', 'Z'].into_iter().enumerate() {
                    if !any || cmd.has(letter) {
                        to.0[k] = saved32[k];
                        to.1[k] = saved64[k];
                        self.known[k] = self.saved_known[k];
                    }
                }
                Ok(Some(self.go(to, None)))
            }
            "G53" | "G54" | "G55" | "G56" | "G57" | "G58" | "G59" => refuse(
                "selects a workspace coordinate system, which stock Marlin leaves out and \
                 keeps in EEPROM where it has them; its moves cannot be followed",
            ),
            "G10" if cmd.has('L') => refuse(
                "with L sets workspace or tool offsets (RepRapFirmware's form), which \
                 cannot be followed on Marlin",
            ),
            "G18" | "G19" => {
                refuse("selects another plane for arcs; only the XY plane's arcs are followed")
            }
            "G20" => refuse("switches to inches; a file for the printers here is in millimetres"),
            "G6" => refuse("moves the steppers directly, outside the firmware's coordinates"),
            "M428" => refuse("sets the home offsets from wherever the head happens to be"),
            _ => Ok(None),
        }
    }

    /// Moves both readings to `to` in a straight line; with `bezier` offsets (I, J from the
    /// start; P, Q from the end) the box takes in a curve's control points.
    fn go(&mut self, to: ([f32; 4], [f64; 4]), bezier: Option<[f64; 4]>) -> Move {
        let fw = self.firmware;
        let (from, written_from) = (self.position(), self.written.machine(fw));
        self.fw.pos = to.0;
        self.written.pos = to.1;
        let (to, written_to) = (self.position(), self.written.machine(fw));
        let boxed = |from: [f64; 4], to: [f64; 4]| {
            let (mut lo, mut hi) = line_box(from, to);
            if let Some([i, j, p, q]) = bezier {
                for c in [[from[0] + i, from[1] + j], [to[0] + p, to[1] + q]] {
                    for k in 0..2 {
                        lo[k] = lo[k].min(c[k]);
                        hi[k] = hi[k].max(c[k]);
                    }
                }
            }
            (lo, hi)
        };
        let (lo, hi) = boxed(from, to);
        Move {
            from,
            to,
            lo,
            hi,
            curved: bezier.is_some(),
            written: boxed(written_from, written_to),
        }
    }

    /// `G2` (clockwise) or `G3`, as the firmware runs it in its 32-bit arithmetic
    /// ([`firmware_arc`]), checked against the file's own reading: the centre its I and J
    /// (or R) give, a whole circle where its end is its start. Refused where the firmware
    /// skips it, answers an error, or could read it otherwise than the file: an end within
    /// [`NEAR_MM`] of where a whole circle or no arc would end, or a different arc.
    fn arc(&mut self, cmd: &Command) -> Result<Option<Move>, Unfollowable> {
        let fw = self.firmware;
        let clockwise = cmd.code == "G2";
        let refuse = |why: String| Err(Unfollowable(format!("{} {why}", cmd.code)));
        let name = match fw {
            Firmware::Ultimaker2 => "Ultimaker2Marlin",
            Firmware::Marlin2 | Firmware::Marlin20 => "Marlin 2",
        };
        if cmd.has('R') && fw == Firmware::Ultimaker2 {
            return refuse("with R: Ultimaker2Marlin's arcs take I and J only".into());
        }
        if !['I', 'J', 'R'].iter().any(|l| cmd.has(*l)) {
            return refuse(
                "without I, J or R: an arc without a centre, which firmwares treat differently"
                    .into(),
            );
        }
        if let Some(p) = cmd.get('P').filter(|p| *p != 0.0) {
            return refuse(format!(
                "with P{p}: whole turns before the arc, which stock Marlin 2.1 (built \
                 without ARC_P_CIRCLES) and Ultimaker2Marlin ignore and a build with \
                 ARC_P_CIRCLES runs"
            ));
        }
        let relative = self.relative();
        let to32 = self.fw.target(cmd, fw, relative);
        let to64 = self.written.target(cmd, fw, relative);
        let read = ['R', 'I', 'J'].map(|l| cmd.get_f32(l, fw));
        let (centre32, sweep32, whole32) =
            match firmware_arc(fw, clockwise, self.fw.pos, to32, read) {
                ArcRun::Runs {
                    centre,
                    sweep,
                    whole,
                    ..
                } => (centre, sweep, whole),
                ArcRun::BadParameters => return refuse(
                    "has no centre in Marlin 2's 32-bit reading (I and J zero, R zero, or an R \
                     arc back to its own start): it answers `Error:G2/G3 bad parameters` and \
                     does not move"
                        .into(),
                ),
                ArcRun::Skipped(Skip::NoAngle) => {
                    return refuse(
                        "ends on the line from its centre through its start in Marlin 2's 32-bit \
                     arithmetic, so it has no angle to turn: Marlin 2 skips it without moving \
                     (Z and E included)"
                            .into(),
                    )
                }
                ArcRun::Skipped(Skip::Short) => {
                    return refuse(match fw {
                        Firmware::Ultimaker2 => "is shorter than 0.001 mm in Ultimaker2Marlin's \
                        32-bit arithmetic (a G3 back to its own start is, and a G2 whose end \
                        rounds just past its start): it plans no move, yet takes the end as \
                        reached"
                            .into(),
                        Firmware::Marlin2 | Firmware::Marlin20 => "is shorter than 0.0001 mm in \
                        Marlin 2's 32-bit arithmetic and does not rise: Marlin 2 skips it \
                        without moving (Z and E included)"
                            .into(),
                    })
                }
            };
        // The file's own reading.
        let (p, q) = (
            [self.written.pos[0], self.written.pos[1]],
            [to64[0], to64[1]],
        );
        let offset64 = match cmd.get('R') {
            Some(r) if r != 0.0 && p != q => r_offset(clockwise, p, q, r),
            Some(_) => {
                return refuse(
                    "with R from a point to itself or R0: no arc is defined; Marlin 2 answers \
                     `Error:G2/G3 bad parameters`"
                        .into(),
                )
            }
            None => [cmd.get('I').unwrap_or(0.0), cmd.get('J').unwrap_or(0.0)],
        };
        let centre64 = [p[0] + offset64[0], p[1] + offset64[1]];
        let radius64 = offset64[0].hypot(offset64[1]);
        let chord64 = (q[0] - p[0]).hypot(q[1] - p[1]);
        let whole64 = chord64 <= WHOLE_MM;
        let sweep64 = if whole64 {
            if clockwise {
                -TAU
            } else {
                TAU
            }
        } else {
            let a0 = (p[1] - centre64[1]).atan2(p[0] - centre64[0]);
            let a1 = (q[1] - centre64[1]).atan2(q[0] - centre64[0]);
            if clockwise {
                -(a0 - a1).rem_euclid(TAU)
            } else {
                (a1 - a0).rem_euclid(TAU)
            }
        };
        let sweep32 = f64::from(sweep32);
        if whole64 && !whole32 {
            return refuse(format!(
                "returns to its start as written, but {name}'s 32-bit floats put its end \
                 {:.2e} mm away: it turns {:.1} degrees, not a whole circle",
                (f64::from(to32[0]) - f64::from(self.fw.pos[0]))
                    .hypot(f64::from(to32[1]) - f64::from(self.fw.pos[1])),
                sweep32.to_degrees().abs()
            ));
        }
        if !whole64 {
            let slack = sweep64.abs().min(TAU - sweep64.abs()) * radius64;
            if whole32 {
                return refuse(format!(
                    "ends {chord64:.2e} mm from its start as written, which {name}'s 32-bit \
                     floats make its start: it runs a whole circle (radius {radius64:.1} mm) \
                     where the file asks for {:.1} degrees",
                    sweep64.to_degrees().abs()
                ));
            }
            if slack < NEAR_MM {
                return refuse(format!(
                    "ends {slack:.2e} mm along its circle from where a whole circle or no arc \
                     would end (radius {radius64:.2e} mm): whether {name} turns a sliver, all \
                     the way round, or not at all turns on its 32-bit rounding"
                ));
            }
            let agree = sweep32.signum() == sweep64.signum()
                && (sweep32 - sweep64).abs() * radius64 <= ARC_AGREE_MM;
            if !agree {
                return refuse(format!(
                    "turns {:.1} degrees as written but {:.1} in {name}'s 32-bit arithmetic",
                    sweep64.to_degrees(),
                    sweep32.to_degrees()
                ));
            }
        }
        let centre = [
            self.fw.to_machine(fw, 0, centre32[0]),
            self.fw.to_machine(fw, 1, centre32[1]),
        ];
        let written_centre = [
            self.written.to_machine(fw, 0, centre64[0]),
            self.written.to_machine(fw, 1, centre64[1]),
        ];
        let written_from = self.written.machine(fw);
        let mut m = self.go((to32, to64), None);
        (m.lo, m.hi) = arc_box(m.from, m.to, centre, sweep32);
        m.written = arc_box(
            written_from,
            self.written.machine(fw),
            written_centre,
            sweep64,
        );
        m.curved = true;
        Ok(Some(m))
    }
}

/// Net filament `commands` push, mm (a retraction counts back until it is pushed again),
/// followed as `firmware` follows them: what a print of them takes from the spool. A
/// command the firmware could not follow ends the count there, as it would end the print.
pub fn extruded_mm<S: AsRef<str>>(
    commands: impl IntoIterator<Item = S>,
    firmware: Firmware,
) -> f64 {
    let mut pushed = Pushed::new(firmware);
    for line in commands {
        pushed.follow(line.as_ref());
    }
    pushed.mm()
}

/// [`extruded_mm`] one command at a time, for commands read as they stream by.
pub struct Pushed {
    motion: Motion,
    total: f64,
    ended: bool,
}

impl Pushed {
    pub fn new(firmware: Firmware) -> Self {
        Pushed {
            motion: Motion::new(firmware),
            total: 0.0,
            ended: false,
        }
    }

    pub fn follow(&mut self, line: &str) {
        if self.ended {
            return;
        }
        let code = line.split(';').next().unwrap_or_default();
        let Ok(Some(cmd)) = crate::reader::read(code) else {
            return;
        };
        match self.motion.apply(&cmd) {
            Ok(Some(m)) => self.total += m.extruded(),
            Ok(None) => {}
            Err(_) => self.ended = true,
        }
    }

    pub fn mm(&self) -> f64 {
        self.total
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn parse(line: &str) -> Option<Command<'_>> {
        crate::reader::read(line).unwrap()
    }

    fn follow(text: &str) -> (Motion, Vec<Move>) {
        let mut m = Motion::default();
        let mut moves = Vec::new();
        for line in text.lines() {
            if let Some(cmd) = parse(line) {
                if let Some(mv) = m.apply(&cmd).unwrap() {
                    moves.push(mv);
                }
            }
        }
        (m, moves)
    }

    #[test]
    fn g92_and_m206_shift_the_files_coordinates() {
        // At X100, G92 X0 calls that 0: X200 is then 300 on the machine.
        let (m, _) = follow("G28\nG1 X100\nG92 X0\nG1 X200\n");
        assert_eq!(m.position()[0], 300.0);
        // Homing ends the shift.
        let (m, _) = follow("G92 X50\nG28 X\nG1 X10\n");
        assert_eq!(m.position()[0], 10.0);
        // M206 X-100 on Marlin 2: X10 is machine 110.
        let (m, _) = follow("G28\nM206 X-100\nG1 X10\n");
        assert_eq!(m.position()[0], 110.0);
        // On Ultimaker2Marlin it counts from the next homing.
        let mut m = Motion::new(Firmware::Ultimaker2);
        for l in ["M206 X-100", "G1 X10"] {
            m.apply(&parse(l).unwrap()).unwrap();
        }
        assert_eq!(m.position()[0], 10.0);
        for l in ["G28", "G1 X10"] {
            m.apply(&parse(l).unwrap()).unwrap();
        }
        assert_eq!(m.position()[0], 110.0);
    }

    #[test]
    fn arcs_reach_the_extremes_of_their_circle() {
        // Clockwise from (100, 100) back to itself about (50, 100): a whole circle.
        let (_, moves) = follow("G1 X100 Y100\nG2 X100 Y100 I-50 J0\n");
        let arc = moves[1];
        assert!((arc.lo[0] - 0.0).abs() < 1e-9 && (arc.hi[1] - 150.0).abs() < 1e-9);
        // No end given: a whole circle from (1, 50) about (-99, 50), reaching X -199.
        let (_, moves) = follow("G1 X1 Y50\nG2 I-100\n");
        assert!((moves[1].lo[0] + 199.0).abs() < 1e-9, "{:?}", moves[1]);
        // A quarter arc counter-clockwise from (110, 100) about (100, 100) to (100, 110):
        // no extreme beyond its ends but the one at 0 degrees (its start).
        let (_, moves) = follow("G1 X110 Y100\nG3 X100 Y110 I-10 J0\n");
        assert_eq!(moves[1].hi[0], 110.0);
        assert_eq!(moves[1].hi[1], 110.0);
        assert_eq!(moves[1].lo[0], 100.0);
        // The same ends clockwise: three quarters, reaching X 90 and Y 90.
        let (_, moves) = follow("G1 X110 Y100\nG2 X100 Y110 I-10 J0\n");
        assert!((moves[1].lo[0] - 90.0).abs() < 1e-9 && (moves[1].lo[1] - 90.0).abs() < 1e-9);
        // R form: a half circle of radius 10 from (100, 100) to (120, 100), clockwise:
        // bulging to Y 110.
        let (_, moves) = follow("G1 X100 Y100\nG2 X120 Y100 R10\n");
        assert!((moves[1].hi[1] - 110.0).abs() < 1e-9, "{:?}", moves[1]);
        let (_, moves) = follow("G1 X100 Y100\nG3 X120 Y100 R10\n");
        assert!((moves[1].lo[1] - 90.0).abs() < 1e-9, "{:?}", moves[1]);
    }

    #[test]
    fn what_cannot_be_followed_is_refused_saying_why() {
        let mut m = Motion::default();
        for l in ["G54", "G53 X0", "G10 L2 P1 X10", "G19", "G20", "G2 X10"] {
            let e = m.apply(&parse(l).unwrap()).unwrap_err();
            assert!(e.0.starts_with(parse(l).unwrap().code.as_str()), "{l}: {e}");
        }
        let mut um2 = Motion::new(Firmware::Ultimaker2);
        assert!(um2.apply(&parse("G2 X10 R5").unwrap()).is_err());
    }

    /// Follows `text` on `fw` and returns the last line's result.
    fn last(fw: Firmware, text: &str) -> Result<Option<Move>, Unfollowable> {
        let mut m = Motion::new(fw);
        let mut result = Ok(None);
        for line in text.lines() {
            result = m.apply(&parse(line).unwrap());
        }
        result
    }

    const BOTH: [Firmware; 2] = [Firmware::Marlin2, Firmware::Ultimaker2];

    #[test]
    fn the_firmwares_turn_is_marlins_radians_360_and_avr_libcs_two_pi() {
        // RADIANS(360) = 360 * float(M_PI) / 180.0f, 2*M_PI with a 32-bit double.
        let pi = std::f32::consts::PI;
        assert_eq!(<f32 as Real>::TURN, 360.0f32 * pi / 180.0f32);
        assert_eq!(<f32 as Real>::TURN, 2.0 * pi);
    }

    /// Issue 42: ends equal in float, not in double. Both firmwares read 210.000005 and
    /// 209.999995 as 210 and run a whole circle of radius 141 mm; the 64-bit reading is a
    /// sliver. Refused, on both, for each variant.
    #[test]
    fn ends_equal_in_float_but_not_in_double_are_refused() {
        for fw in BOTH {
            for (text, says) in [
                (
                    "G1 X210 Y210\nG2 X210.000005 Y209.999995 I-100 J-100 F3000",
                    "whole circle",
                ),
                ("G1 X150 Y150\nG2 X150.000005 Y150 I-5 J0", "whole circle"),
                ("G1 X150 Y150\nG2 X150 Y149.999995 I-5 J0", "whole circle"),
                // Relative, and after G92: the same sum in float.
                (
                    "G1 X150 Y150\nG91\nG2 X0.000005 Y-0.000005 I-50 J-50",
                    "whole circle",
                ),
            ] {
                let e = last(fw, text).unwrap_err();
                assert!(e.0.contains(says), "{fw} {text}: {e}");
            }
            // Counter-clockwise: Marlin 2 runs a whole circle, Ultimaker2Marlin nothing.
            let e = last(fw, "G1 X150 Y150\nG3 X150.000005 Y149.999995 I-50 J-50").unwrap_err();
            let says = match fw {
                Firmware::Ultimaker2 => "plans no move",
                _ => "whole circle",
            };
            assert!(e.0.contains(says), "{fw}: {e}");
        }
        // After G92 the file's numbers are small, where floats are fine: Marlin 2 adds
        // them to its workspace offset (150) and rounds them away; Ultimaker2Marlin keeps
        // them, and its end rounds just past its start: a sliver it does not run.
        let g92 = "G1 X150 Y150\nG92 X0 Y0\nG2 X0.000005 Y-0.000005 I-50 J-50";
        assert!(last(Firmware::Marlin2, g92)
            .unwrap_err()
            .0
            .contains("whole circle"));
        assert!(last(Firmware::Ultimaker2, g92)
            .unwrap_err()
            .0
            .contains("plans no move"));
        // An end a thousandth of a millimetre away is an arc on both, followed.
        for fw in BOTH {
            let m = last(fw, "G1 X150 Y150\nG2 X150.001 Y149.999 I-50 J-50")
                .unwrap()
                .unwrap();
            assert!(m.hi[0] < 150.01 && m.lo[0] > 149.99, "{fw}: {m:?}");
        }
    }

    #[test]
    fn what_the_firmware_skips_or_answers_with_an_error_is_refused() {
        // The R form back to its start (in float): Marlin's `bad parameters`.
        let e = last(
            Firmware::Marlin2,
            "G1 X150 Y150\nG2 X150.000005 Y150.000005 R50",
        )
        .unwrap_err();
        assert!(e.0.contains("bad parameters"), "{e}");
        for text in ["G2 X10 Y10 I0 J0", "G2 X10 Y10 R0", "G2 X0 Y0 R5"] {
            let e = last(Firmware::Marlin2, text).unwrap_err();
            assert!(e.0.contains("bad parameters"), "{text}: {e}");
        }
        // I and J near zero: a radius too small for the firmware to turn on.
        for fw in BOTH {
            for text in [
                "G1 X150 Y150\nG2 X160 Y150 I0.0000001 J0",
                "G1 X150 Y150\nG2 X160 Y150 I0.0001 J0",
            ] {
                assert!(last(fw, text).is_err(), "{fw} {text}");
            }
        }
        // An I that rounds to 0 in float but not in double.
        let e = last(
            Firmware::Marlin2,
            "G1 X150 Y150\nG2 X160 Y150 I0.0000000000000000000000000000000000000000000001",
        )
        .unwrap_err();
        assert!(e.0.contains("bad parameters"), "{e}");
        // The end on the start's ray, farther out: Marlin 2 has no angle to turn.
        let e = last(Firmware::Marlin2, "G1 X150 Y150\nG2 X160 Y150 I-5 J0").unwrap_err();
        assert!(e.0.contains("no angle"), "{e}");
        // Whole turns before the arc: read differently by builds and firmwares.
        for fw in BOTH {
            let e = last(fw, "G1 X150 Y150\nG2 X150 Y150 I-5 J0 P1").unwrap_err();
            assert!(e.0.contains("ARC_P_CIRCLES"), "{fw}: {e}");
            assert!(last(fw, "G1 X150 Y150\nG2 I-5 J0 P0").is_ok(), "{fw}");
        }
    }

    #[test]
    fn whole_circles_as_written_are_whole_circles_where_the_firmware_runs_them() {
        for fw in BOTH {
            let m = last(fw, "G1 X150 Y150\nG2 X150 Y150 I-5 J0")
                .unwrap()
                .unwrap();
            assert_eq!((m.lo[0], m.hi[0]), (140.0, 150.0), "{fw}");
            assert_eq!((m.lo[1], m.hi[1]), (145.0, 155.0), "{fw}");
        }
        // Marlin 2 runs a G3 back to its start as a circle; Ultimaker2Marlin's mc_arc finds
        // no angle and, counter-clockwise, adds no turn: it does not move.
        assert!(last(Firmware::Marlin2, "G1 X150 Y150\nG3 I-5 J0").is_ok());
        let e = last(Firmware::Ultimaker2, "G1 X150 Y150\nG3 I-5 J0").unwrap_err();
        assert!(e.0.contains("plans no move"), "{e}");
        // Where Ultimaker2Marlin's centre rounds (150.3 - 50.7 is no float), its end and start
        // differ from the centre's view: whether it turns a whole circle or nothing is its
        // float's, and the follower computes it so.
        let um2 = last(Firmware::Ultimaker2, "G1 X150.3 Y150.3\nG2 I-50.7 J-50.1");
        let fw_run = {
            let read = |t| crate::reader::firmware_float(Firmware::Ultimaker2, t);
            let from = [read("150.3"), read("150.3"), 0.0, 0.0];
            let offset = [None, Some(read("-50.7")), Some(read("-50.1"))];
            firmware_arc(Firmware::Ultimaker2, true, from, from, offset)
        };
        match fw_run {
            ArcRun::Runs { whole: true, .. } => assert!(um2.is_ok(), "{um2:?}"),
            _ => assert!(um2.is_err(), "{fw_run:?} {um2:?}"),
        }
    }

    #[test]
    fn positions_offsets_and_bounds_are_the_firmwares_floats() {
        // Relative moves add in float: 0.1 a thousand times from 0 is not 100 there.
        let mut m = Motion::default();
        m.apply(&parse("G91").unwrap()).unwrap();
        for _ in 0..1000 {
            m.apply(&parse("G1 X0.1").unwrap()).unwrap();
        }
        let mut x = 0.0f32;
        for _ in 0..1000 {
            x += 0.1f32;
        }
        assert_eq!(m.position()[0], f64::from(x));
        assert_ne!(m.position()[0], 100.0);
        // Marlin 2's G92 shifts its workspace in float: the file's coordinate is the sum.
        let (m, _) = follow("G28\nG1 X100.3\nG92 X0.7\nG1 X10.1\n");
        let ws = 0.7f32 - 100.3f32;
        assert_eq!(m.position()[0], f64::from(10.1f32 - ws));
        assert_eq!(m.file_position()[0], Some(f64::from((10.1f32 - ws) + ws)));
        // A G92 within NEAR_ZERO of where it is changes nothing (G92.cpp 94).
        let (m, _) = follow("G28\nG1 X10\nG92 X10.0000005\nG1 X20\n");
        assert_eq!(m.position()[0], 20.0);
        // Ultimaker2Marlin reads numbers with avr-libc's strtod: 149.999 is one float away
        // from the nearest.
        let mut um2 = Motion::new(Firmware::Ultimaker2);
        um2.apply(&parse("G1 Y149.999").unwrap()).unwrap();
        assert_eq!(um2.position()[1], f64::from(149.999_01f32));
        assert_ne!(149.999_01f32, 149.999f32);
    }

    #[test]
    fn the_bed_edge_is_judged_in_both_readings() {
        let bed = [220.0, 220.0, 250.0];
        // 220.5000001 is 220.5 in float: on the edge for the firmware, past it as written.
        let m = last(Firmware::Marlin2, "G1 X220.5000001").unwrap().unwrap();
        assert_eq!(m.bounds(bed, 0.5), Bounds::Rounding(0));
        let m = last(Firmware::Marlin2, "G1 X220.5").unwrap().unwrap();
        assert_eq!(m.bounds(bed, 0.5), Bounds::Inside);
        let m = last(Firmware::Marlin2, "G1 X221").unwrap().unwrap();
        assert_eq!(m.bounds(bed, 0.5), Bounds::Outside(0));
        // After G92, the same edge through the workspace offset.
        let m = last(Firmware::Marlin2, "G1 X100\nG92 X0\nG1 X120.5000001")
            .unwrap()
            .unwrap();
        assert_eq!(m.bounds(bed, 0.5), Bounds::Rounding(0));
    }

    #[test]
    fn outside_counts_numbers_that_are_none() {
        let bed = [100.0, 100.0, 100.0];
        assert_eq!(outside([0.0; 3], [100.0; 3], bed, 0.5), None);
        assert_eq!(outside([0.0, -1.0, 0.0], [1.0; 3], bed, 0.5), Some(1));
        assert_eq!(outside([f64::NAN, 0.0, 0.0], [1.0; 3], bed, 0.5), Some(0));
    }
}
