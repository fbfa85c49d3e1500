//! One follower of G-code motion, as Marlin moves the head: every reader of G-code that
//! needs to know where the nozzle goes (in `slice`: the slicer-output check `gcode`, the
//! pre-sliced check `presliced`, the outer-wall measure `walls`, the G-code policy
//! `policy`; in the host: where a pause parks the head and where the print resumes,
//! the sibling `pause`) reads commands with [`crate::marlin::reader`] and follows them
//! with one [`Motion`], so they cannot disagree about where a file sends the printer.
//!
//! Positions are kept in the machine's own coordinates (where the head physically is,
//! homed at 0), apart from the coordinates the file writes: `G92` shifts the file's
//! coordinates against the machine's, and `M206` (home offsets) does too. A move's extent
//! is what the head sweeps, not just where it ends: arcs (`G2`/`G3`, I/J and R forms, full
//! circles, P turns) reach their circle's extremes, a Bézier move (`G5`) stays in the hull
//! of its control points.
//!
//! What cannot be followed for certain is refused ([`Unfollowable`]), never guessed:
//! workspace coordinate systems (`G53`–`G59`, `G10 L2`/`L20`: off in stock Marlin, kept in
//! EEPROM where on, so a file's offsets would shift every later job), other arc planes
//! (`G18`, `G19`), inch units (`G20`), direct stepper moves (`G6`), `M428`, and arcs without
//! a centre. Lines are read by [`crate::marlin::reader`], which takes only what every
//! firmware reads alike (so no sub-codes such as `G92.1`: stock Marlin runs them as `G92`).

use crate::marlin::firmware::Firmware;
use std::f64::consts::{FRAC_PI_2, TAU};

pub(crate) use crate::marlin::reader::Command;

/// A command the follower cannot follow for certain; the text says what and why.
#[derive(Clone, Debug, PartialEq, thiserror::Error)]
#[error("{0}")]
pub struct Unfollowable(pub String);

/// One move: where it started and ended (machine X, Y, Z and the file's E), and the box
/// the head swept on the way (machine coordinates).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Move {
    pub from: [f64; 4],
    pub to: [f64; 4],
    pub lo: [f64; 3],
    pub hi: [f64; 3],
    /// An arc or curve (its chord is from..to).
    pub curved: bool,
}

impl Move {
    /// Filament pushed (negative: retracted), mm.
    pub(crate) fn extruded(&self) -> f64 {
        self.to[3] - self.from[3]
    }
    pub(crate) fn moves_xy(&self) -> bool {
        self.to[0] != self.from[0] || self.to[1] != self.from[1] || self.curved
    }
    pub(crate) fn moves_xyz(&self) -> bool {
        self.moves_xy() || self.to[2] != self.from[2]
    }
}

/// Where the first axis of `lo..hi` leaves `0..bed` (with `edge` allowance), if any; a
/// coordinate that is no number counts as outside.
pub(crate) fn outside(lo: [f64; 3], hi: [f64; 3], bed: [f64; 3], edge: f64) -> Option<usize> {
    (0..3).find(|&k| !(lo[k] >= -edge && hi[k] <= bed[k] + edge))
}

/// The follower's state: where the head is and how the file's coordinates map onto the
/// machine's.
#[derive(Clone, Debug)]
pub struct Motion {
    /// Machine X, Y, Z (homed at 0).
    native: [f64; 3],
    /// The file's E.
    e: f64,
    /// The file's coordinate minus the machine's, per axis: `G92`'s shift ...
    shift: [f64; 3],
    /// ... plus the home offset in force (`M206`).
    home_offset: [f64; 3],
    /// `M206` given but, on Marlin 1 (Ultimaker2Marlin), in force only from the next homing.
    pending_home_offset: Option<[f64; 3]>,
    /// `G90` (true) or `G91`.
    absolute: bool,
    /// E's own mode, `M82` (true) or `M83`; on Marlin 2 `G90`/`G91` set it too.
    absolute_e: bool,
    /// Where `G60` saved the head, and whether that position was known.
    saved: Option<([f64; 3], [bool; 3])>,
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
            native: [0.0; 3],
            e: 0.0,
            shift: [0.0; 3],
            home_offset: [0.0; 3],
            pending_home_offset: None,
            absolute: true,
            absolute_e: true,
            saved: None,
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
        (self.known[0] && self.known[1] && self.known[2]).then_some(self.native)
    }

    /// Where the head is in the file's own coordinates (what a `G90` move in the file
    /// names), per axis where known; E the file's.
    pub(crate) fn file_position(&self) -> [Option<f64>; 4] {
        std::array::from_fn(|k| match k {
            3 => self.known[3].then_some(self.e),
            _ => (self.known[k] && self.shift_known[k]).then(|| self.native[k] + self.offset(k)),
        })
    }

    /// A machine coordinate of axis `k` (0..3) in the file's coordinates.
    pub fn to_file(&self, k: usize, machine: f64) -> f64 {
        machine + self.offset(k)
    }

    /// The last feed rate a move gave, mm/min.
    pub(crate) fn feed(&self) -> Option<f64> {
        self.feed
    }

    /// Machine X, Y, Z and the file's E.
    pub fn position(&self) -> [f64; 4] {
        [self.native[0], self.native[1], self.native[2], self.e]
    }

    /// Whether a move's value for axis `k` (X, Y, Z, E) is a position, not a distance.
    fn axis_absolute(&self, k: usize) -> bool {
        if k < 3 {
            self.absolute
        } else {
            !self.e_relative()
        }
    }

    fn offset(&self, k: usize) -> f64 {
        self.shift[k] + self.home_offset[k]
    }

    /// Where the given axes of a move or arc end, in machine coordinates (E the file's).
    fn target(&self, cmd: &Command) -> [f64; 4] {
        let mut to = self.position();
        for (k, letter) in ['X', 'Y', 'Z', 'E'].into_iter().enumerate() {
            let Some(v) = cmd.get(letter) else { continue };
            to[k] = match (self.axis_absolute(k), k < 3) {
                (true, true) => v - self.offset(k),
                (true, false) => v,
                (false, _) => to[k] + v,
            };
        }
        to
    }

    /// After a move (`G0`-`G3`, `G5`): an axis it named absolutely is known from then on
    /// (X, Y, Z where the shift is known); the feed rate it gave stays in force.
    fn moved(&mut self, cmd: &Command) {
        for (k, letter) in ['X', 'Y', 'Z', 'E'].into_iter().enumerate() {
            if self.axis_absolute(k) && cmd.get(letter).is_some() {
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
        match cmd.code.as_str() {
            "G0" | "G1" => {
                let to = self.target(cmd);
                Ok(Some(self.go(to, None)))
            }
            "G2" | "G3" => self.arc(cmd),
            "G5" => {
                // A cubic Bézier lies inside the hull of its control points: start + (I,
                // J), end + (P, Q).
                let to = self.target(cmd);
                let from = self.position();
                let c1 = [
                    from[0] + cmd.get('I').unwrap_or(0.0),
                    from[1] + cmd.get('J').unwrap_or(0.0),
                ];
                let c2 = [
                    to[0] + cmd.get('P').unwrap_or(0.0),
                    to[1] + cmd.get('Q').unwrap_or(0.0),
                ];
                Ok(Some(self.go(to, Some([c1, c2]))))
            }
            "G90" | "G91" => {
                self.absolute = cmd.code == "G90";
                // Marlin 2 sets every axis's mode, E's with them; Marlin 1 keeps M82/M83.
                if self.firmware != Firmware::Ultimaker2 {
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
                for (k, letter) in ['X', 'Y', 'Z', 'E'].into_iter().enumerate() {
                    if let Some(v) = cmd.get(letter) {
                        if k < 3 {
                            self.shift[k] = v - self.home_offset[k] - self.native[k];
                            self.shift_known[k] = self.known[k];
                        } else {
                            self.e = v;
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
                    self.native[k] = 0.0;
                    self.shift[k] = 0.0;
                    self.known[k] = false;
                    self.shift_known[k] = true;
                    if let Some(pending) = self.pending_home_offset {
                        self.home_offset[k] = pending[k];
                    }
                }
                Ok(None)
            }
            "M206" => {
                let mut offset = self.pending_home_offset.unwrap_or(self.home_offset);
                for (k, letter) in ['X', 'Y', 'Z'].into_iter().enumerate() {
                    if let Some(v) = cmd.get(letter) {
                        offset[k] = v;
                    }
                }
                match self.firmware {
                    // Ultimaker2Marlin adds its home offset when homing.
                    Firmware::Ultimaker2 => self.pending_home_offset = Some(offset),
                    Firmware::Marlin2 | Firmware::Marlin20 => self.home_offset = offset,
                }
                Ok(None)
            }
            "G60" => {
                self.saved = Some((self.native, [self.known[0], self.known[1], self.known[2]]));
                Ok(None)
            }
            "G61" => {
                let Some((saved, known)) = self.saved else {
                    return Ok(None);
                };
                let mut to = self.position();
                let any = ['X', 'Y', 'Z'].iter().any(|l| cmd.has(*l));
                for (k, letter) in ['X', 'Y', 'Z'].into_iter().enumerate() {
                    if !any || cmd.has(letter) {
                        to[k] = saved[k];
                        self.known[k] = known[k];
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

    /// Moves to `to`; the extent is the straight line's, widened by `extra` points.
    fn go(&mut self, to: [f64; 4], extra: Option<[[f64; 2]; 2]>) -> Move {
        let from = self.position();
        let mut lo = [0.0; 3];
        let mut hi = [0.0; 3];
        for k in 0..3 {
            lo[k] = from[k].min(to[k]);
            hi[k] = from[k].max(to[k]);
        }
        for p in extra.iter().flatten() {
            for k in 0..2 {
                lo[k] = lo[k].min(p[k]);
                hi[k] = hi[k].max(p[k]);
            }
        }
        self.set(to);
        Move {
            from,
            to,
            lo,
            hi,
            curved: extra.is_some(),
        }
    }

    fn set(&mut self, to: [f64; 4]) {
        self.native = [to[0], to[1], to[2]];
        self.e = to[3];
    }

    /// `G2` (clockwise) or `G3`: the centre from I/J (relative to the start) or from R
    /// (the shorter arc, the longer for a negative R), P full turns more; the extent is the
    /// start, the end and every extreme of the circle the arc passes.
    fn arc(&mut self, cmd: &Command) -> Result<Option<Move>, Unfollowable> {
        let clockwise = cmd.code == "G2";
        let from = self.position();
        let to = self.target(cmd);
        let (p, q) = ([from[0], from[1]], [to[0], to[1]]);
        let centre = if let Some(r) = cmd.get('R') {
            if self.firmware == Firmware::Ultimaker2 {
                return Err(Unfollowable(format!(
                    "{} with R: Ultimaker2Marlin's arcs take I and J only",
                    cmd.code
                )));
            }
            let (dx, dy) = (q[0] - p[0], q[1] - p[1]);
            let d = dx.hypot(dy);
            if r == 0.0 || d == 0.0 {
                return Err(Unfollowable(format!(
                    "{} with R {r} from a point to {}: no arc is defined",
                    cmd.code,
                    if d == 0.0 { "itself" } else { "another" }
                )));
            }
            // The centre lies on the chord's perpendicular bisector, h from its middle.
            let h2 = (r - 0.5 * d) * (r + 0.5 * d);
            let h = if h2 >= 0.0 { h2.sqrt() } else { 0.0 };
            let e = if clockwise ^ (r < 0.0) { -1.0 } else { 1.0 };
            [
                p[0] + dx / 2.0 + e * h * (-dy / d),
                p[1] + dy / 2.0 + e * h * (dx / d),
            ]
        } else if cmd.has('I') || cmd.has('J') {
            [
                p[0] + cmd.get('I').unwrap_or(0.0),
                p[1] + cmd.get('J').unwrap_or(0.0),
            ]
        } else {
            return Err(Unfollowable(format!(
                "{} without I, J or R: an arc without a centre, which firmwares treat differently",
                cmd.code
            )));
        };
        let turns = cmd.get('P').unwrap_or(0.0).max(0.0);
        let r = (p[0] - centre[0])
            .hypot(p[1] - centre[1])
            .max((q[0] - centre[0]).hypot(q[1] - centre[1]));
        let a0 = (p[1] - centre[1]).atan2(p[0] - centre[0]);
        let a1 = (q[1] - centre[1]).atan2(q[0] - centre[0]);
        let mut sweep = if clockwise {
            (a0 - a1).rem_euclid(TAU)
        } else {
            (a1 - a0).rem_euclid(TAU)
        };
        // Back where it started: a whole circle (Marlin's reading of it).
        if sweep < 1e-9 && (p[0] - q[0]).hypot(p[1] - q[1]) < 1e-6 {
            sweep = TAU;
        }
        sweep += turns * TAU;
        let mut extremes = Vec::with_capacity(4);
        for k in 0..4 {
            let theta = k as f64 * FRAC_PI_2;
            let from_start = if clockwise {
                (a0 - theta).rem_euclid(TAU)
            } else {
                (theta - a0).rem_euclid(TAU)
            };
            if sweep >= TAU || from_start <= sweep {
                extremes.push([centre[0] + r * theta.cos(), centre[1] + r * theta.sin()]);
            }
        }
        let mut m = self.go(to, Some([p, q]));
        for e in extremes {
            for (k, v) in e.into_iter().enumerate() {
                m.lo[k] = m.lo[k].min(v);
                m.hi[k] = m.hi[k].max(v);
            }
        }
        m.curved = true;
        Ok(Some(m))
    }
}

/// Net filament `commands` push, mm (a retraction counts back until it is pushed again),
/// followed as `firmware` follows them: what a print of them takes from the spool. A
/// command the firmware could not follow ends the count there, as it would end the print.
pub fn extruded_mm<'a>(commands: impl IntoIterator<Item = &'a str>, firmware: Firmware) -> f64 {
    let mut motion = Motion::new(firmware);
    let mut total = 0.0;
    for line in commands {
        let code = line.split(';').next().unwrap_or_default();
        let Ok(Some(cmd)) = crate::marlin::reader::read(code) else {
            continue;
        };
        match motion.apply(&cmd) {
            Ok(Some(m)) => total += m.extruded(),
            Ok(None) => {}
            Err(_) => break,
        }
    }
    total
}

#[cfg(test)]
mod tests {
    use super::*;

    fn parse(line: &str) -> Option<Command<'_>> {
        crate::marlin::reader::read(line).unwrap()
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

    #[test]
    fn outside_counts_numbers_that_are_none() {
        let bed = [100.0, 100.0, 100.0];
        assert_eq!(outside([0.0; 3], [100.0; 3], bed, 0.5), None);
        assert_eq!(outside([0.0, -1.0, 0.0], [1.0; 3], bed, 0.5), Some(1));
        assert_eq!(outside([f64::NAN, 0.0, 0.0], [1.0; 3], bed, 0.5), Some(0));
    }
}
