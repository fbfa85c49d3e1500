//! The simulated firmware itself, without I/O: bytes from the host and the current time go
//! in, bytes for the host and the next deadline come out. It follows Marlin's structure:
//! a serial receive ring (`rx_buffer_bytes`), a line assembler that moves complete lines
//! into `command_slots` after checking line number and checksum, a main loop that executes
//! one command at a time (a blocking command such as M109 stalls it, so the ring fills and
//! the host must wait), a 16-move planner that drains at the moves' real speed, and an
//! emergency parser that sees M108/M112 as the bytes arrive.
//!
//! This file holds the printer's main loop and command execution; its state (the
//! [`Printer`] and its parts) is in [`state`], and the seams live beside it: [`serial`]
//! (receive ring and line checks), [`motion`] (planner and move times), [`thermal`]
//! (heaters and reports), [`dialect`] (what each flavour knows and says) and [`faults`]
//! (what it does wrong on purpose).

mod dialect;
mod faults;
mod motion;
mod serial;
mod state;
mod thermal;

pub(crate) use state::{Printer, Status};

use super::config::SimConfig;
use super::recorder::Recorder;
use crispen_marlin::firmware::Firmware;
use dialect::known_marlin2;
use motion::{parse_words, word, word_present};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use state::{Active, Heater, Queued, Temperature, Wait};
use std::collections::VecDeque;
use std::time::{Duration, Instant};
use thermal::AMBIENT;

const PLANNER_MOVES: usize = 16;
/// A homing takes seconds: an Ultimaker 2 moves its bed up to 205 mm at 40 mm/s, and every
/// axis bumps its switch twice. Longer than the host's 3 s silence probe, as on a real
/// printer, whose firmware reads no serial input meanwhile.
const HOMING_SECONDS: f64 = 8.0;
const DEFAULT_FEEDRATE: f64 = 1500.0; // mm/min
/// Shortest real interval between periodic messages, so a tiny time scale cannot turn
/// keep-alives and temperature reports into a flood.
const MIN_PERIOD: Duration = Duration::from_millis(50);

impl Printer {
    pub(crate) fn new(cfg: &SimConfig, now: Instant) -> Self {
        let mut p = Printer {
            fw: cfg.firmware,
            time_scale: cfg.time_scale.max(0.0),
            faults: cfg.faults.clone(),
            rng: ChaCha8Rng::seed_from_u64(cfg.seed),
            status: Status::Running,
            rx: VecDeque::new(),
            assembling: Vec::new(),
            emergency: Vec::new(),
            slots: VecDeque::new(),
            last_n: 0,
            active: None,
            planner: VecDeque::new(),
            planner_head_end: None,
            position: [0.0; 4],
            relative: false,
            relative_e: false,
            feedrate: DEFAULT_FEEDRATE,
            settings: crispen_marlin::estimate::Limits::of(cfg.firmware),
            hotend: Temperature {
                current: AMBIENT,
                target: 0.0,
            },
            bed: Temperature {
                current: AMBIENT,
                target: 0.0,
            },
            temps_at: now,
            autoreport: None,
            next_autoreport: None,
            keepalive: 2.0,
            next_keepalive: None,
            heat_break: false,
            numbered_executed: 0,
            in_comment: false,
            escaped: false,
            emergency_parser: cfg
                .emergency_parser
                .unwrap_or(cfg.firmware.emergency_parser()),
            answered: false,
            wait_when_idle: cfg.wait_when_idle,
            next_wait: None,
            advanced_ok: cfg.advanced_ok.unwrap_or(cfg.firmware.advanced_ok()),
            advanced_pause: cfg.advanced_pause,
            report_style: cfg.report_style,
            out: Vec::new(),
        };
        p.boot();
        p
    }

    /// Power-on or reset: everything but the temperatures is forgotten.
    fn boot(&mut self) {
        self.rx.clear();
        self.assembling.clear();
        self.emergency.clear();
        self.slots.clear();
        self.last_n = 0;
        self.active = None;
        self.planner.clear();
        self.planner_head_end = None;
        self.position = [0.0; 4];
        self.relative = false;
        self.relative_e = false;
        self.feedrate = DEFAULT_FEEDRATE;
        self.settings = crispen_marlin::estimate::Limits::of(self.fw);
        self.hotend.target = 0.0;
        self.bed.target = 0.0;
        self.autoreport = None;
        self.next_autoreport = None;
        self.keepalive = 2.0;
        self.next_keepalive = None;
        self.heat_break = false;
        self.in_comment = false;
        self.escaped = false;
        self.next_wait = None;
        self.say("start");
        if self.fw == Firmware::Marlin20 {
            self.say("echo:Marlin 2.0.9.3");
            self.say("echo: Last Updated: 2021-12-25 | Author: (crispen sim)");
        }
        if self.fw == Firmware::Marlin2 {
            self.say("echo:Marlin 2.1.2");
            self.say("echo: Last Updated: 2023-03-21 | Author: (crispen sim)");
            self.say("echo:Compiled: crispen");
            self.say("echo: Free Memory: 2714  PlannerBufferBytes: 1296");
        }
    }

    pub(crate) fn status(&self) -> Status {
        self.status
    }

    /// The host opened the port: DTR resets the board, the bootloader waits `delay`, then
    /// the firmware boots. A halted or silent printer is reset too, as a real one would be.
    pub(crate) fn reset_on_open(&mut self, now: Instant, delay: Duration) {
        if self.status == Status::Unplugged {
            return;
        }
        tracing::info!(
            ?delay,
            "host opened the port: reset (DTR) and bootloader delay"
        );
        self.out.clear();
        self.status = Status::Booting(now + delay);
    }

    #[cfg(test)]
    fn output(&self) -> &[u8] {
        &self.out
    }

    pub(crate) fn take_output(&mut self) -> Vec<u8> {
        std::mem::take(&mut self.out)
    }

    fn real(&self, sim_seconds: f64) -> Duration {
        Duration::from_secs_f64((sim_seconds * self.time_scale).max(0.0))
    }

    fn period(&self, sim_seconds: f64) -> Duration {
        self.real(sim_seconds).max(MIN_PERIOD)
    }

    // ----- output -------------------------------------------------------------------

    /// Emit a line exactly as given (banners, errors, M115: never garbled).
    fn say(&mut self, line: &str) {
        if self.status != Status::Running {
            return;
        }
        self.out.extend_from_slice(line.as_bytes());
        self.out.push(b'\n');
    }

    fn ok(&mut self, n: Option<u64>) {
        if std::mem::take(&mut self.answered) || self.drop_this_ok() {
            return;
        }
        let line = if self.advanced_ok {
            let planner_free = PLANNER_MOVES - self.planner.len().min(PLANNER_MOVES);
            // Marlin counts the command being acknowledged as still occupying its slot.
            let slots_free = self.fw.command_slots().saturating_sub(self.slots.len() + 1);
            match n {
                Some(n) => format!("ok N{n} P{planner_free} B{slots_free}"),
                None => format!("ok P{planner_free} B{slots_free}"),
            }
        } else {
            "ok".to_string()
        };
        self.say_noisy(&line);
    }

    // ----- time ---------------------------------------------------------------------

    /// Run the printer up to `now`: drain the planner, heat, finish and start commands.
    pub(crate) fn advance(&mut self, now: Instant, recorder: &mut Recorder) {
        if let Status::Booting(until) = self.status {
            if now < until {
                return;
            }
            self.status = Status::Running;
            self.temps_at = now;
            self.boot();
        }
        if self.status != Status::Running {
            return;
        }
        self.update_planner(now);
        self.update_temperatures(now);
        loop {
            if self.status != Status::Running {
                return;
            }
            // A command in progress holds the main loop (as in Marlin, where M109 or a move
            // waiting for planner room blocks in its handler): no lines are read meanwhile.
            if self.active.is_some() {
                if !self.progress_active(now) {
                    // Marlin 2's heat waits call idle(), whose manage_inactivity reads the
                    // serial input into free command slots (temperature.cpp:4122,
                    // MarlinCore.cpp:412): an unnumbered M108 read there ends the wait.
                    // Ultimaker2Marlin's read nothing (Marlin_main.cpp:1419-1460, 1472-1490).
                    if self.fw.is_marlin2() && self.in_heat_wait() {
                        self.fill_slots();
                        if self.heat_break {
                            continue;
                        }
                    }
                    break;
                }
                continue;
            }
            self.fill_slots();
            let Some(next) = self.slots.pop_front() else {
                break;
            };
            self.execute(next, now, recorder);
        }
        if let (Some(period), Some(at)) = (self.autoreport, self.next_autoreport) {
            if now >= at {
                let report = self.temperature_report();
                self.say_noisy(&report);
                self.next_autoreport = Some(now + period);
            }
        }
        let busy = self.active.as_ref().is_some_and(|a| a.busy);
        if busy && self.fw.busy_protocol() && self.keepalive > 0.0 {
            if let Some(at) = self.next_keepalive {
                if now >= at {
                    let text = self.keepalive_text();
                    self.say_noisy(text);
                    self.next_keepalive = Some(now + self.period(self.keepalive));
                }
            }
        }
        if let Some(active) = &mut self.active {
            if let (Some(at), Wait::Heat { heater, .. }) = (active.next_heat_report, &active.wait) {
                if now >= at {
                    let heater = *heater;
                    let period = Duration::from_secs_f64(self.time_scale).max(MIN_PERIOD);
                    active.next_heat_report = Some(now + period);
                    let report = self.heat_wait_report(heater);
                    self.say_noisy(&report);
                }
            }
        }
        // NO_TIMEOUTS: `wait` while the command queue is empty.
        if let Some(interval) = self.wait_when_idle {
            if self.is_idle() {
                let at = *self.next_wait.get_or_insert(now + interval);
                if now >= at {
                    self.say("wait");
                    self.next_wait = Some(now + interval);
                }
            } else {
                self.next_wait = None;
            }
        }
    }

    fn in_heat_wait(&self) -> bool {
        self.active
            .as_ref()
            .is_some_and(|a| matches!(a.wait, Wait::Heat { .. }))
    }

    fn is_idle(&self) -> bool {
        self.active.is_none() && self.slots.is_empty() && self.rx.is_empty()
    }

    /// Try to finish the active command; true if it finished.
    fn progress_active(&mut self, now: Instant) -> bool {
        let Some(mut active) = self.active.take() else {
            return true;
        };
        loop {
            let done = match &active.wait {
                Wait::PlannerSlot { seconds } => {
                    if self.planner.len() < PLANNER_MOVES {
                        let seconds = *seconds;
                        self.plan(seconds, now);
                        true
                    } else {
                        false
                    }
                }
                Wait::Drain { then } => {
                    if self.planner.is_empty() {
                        match then {
                            Some(next) => {
                                active.wait = (**next).clone();
                                continue;
                            }
                            None => true,
                        }
                    } else {
                        false
                    }
                }
                Wait::For(seconds) => {
                    active.wait = Wait::Until(now + self.real(*seconds));
                    continue;
                }
                Wait::Until(at) => now >= *at,
                Wait::User => false,
                Wait::Heat {
                    heater,
                    cooling_too,
                } => {
                    let t = match heater {
                        Heater::Hotend => self.hotend,
                        Heater::Bed => self.bed,
                    };
                    let reached = if *cooling_too {
                        (t.current - t.target.max(AMBIENT)).abs() <= 1.0
                    } else {
                        t.current >= t.target - 1.0
                    };
                    std::mem::take(&mut self.heat_break) || reached
                }
            };
            if done {
                self.answered = active.answered;
                self.ok(active.n);
                self.next_keepalive = None;
                return true;
            }
            self.active = Some(active);
            return false;
        }
    }

    /// When `advance` must run again (None: only when input arrives).
    pub(crate) fn next_deadline(&self) -> Option<Instant> {
        if let Status::Booting(until) = self.status {
            return Some(until);
        }
        if self.status != Status::Running {
            return None;
        }
        let mut next: Option<Instant> = self.planner_head_end;
        let mut consider = |t: Option<Instant>| {
            if let Some(t) = t {
                next = Some(next.map_or(t, |n| n.min(t)));
            }
        };
        consider(self.next_autoreport);
        if let Some(interval) = self.wait_when_idle {
            if self.is_idle() {
                consider(Some(
                    self.next_wait.unwrap_or_else(|| Instant::now() + interval),
                ));
            }
        }
        if let Some(active) = &self.active {
            if active.busy && self.fw.busy_protocol() && self.keepalive > 0.0 {
                consider(self.next_keepalive);
            }
            match active.wait {
                Wait::Until(at) => consider(Some(at)),
                Wait::Heat { .. } => {
                    consider(active.next_heat_report);
                    // Re-check the temperature every simulated second (and at least
                    // every 50 ms of real time).
                    consider(Some(
                        Instant::now() + Duration::from_secs_f64(self.time_scale).max(MIN_PERIOD),
                    ));
                }
                Wait::For(_) => consider(Some(Instant::now())),
                _ => {}
            }
        }
        next
    }

    /// Marlin's keep-alive says why it is busy: `paused for user` while it waits for the
    /// knob (KEEPALIVE_STATE(PAUSED_FOR_USER)), `processing` otherwise.
    fn keepalive_text(&self) -> &'static str {
        match self.active.as_ref().map(|a| &a.wait) {
            Some(Wait::User) => "echo:busy: paused for user",
            _ => "echo:busy: processing",
        }
    }

    // ----- commands -----------------------------------------------------------------

    fn execute(&mut self, queued: Queued, now: Instant, recorder: &mut Recorder) {
        let Queued { n, cmd, acked } = queued;
        tracing::trace!(line = ?n, cmd = %cmd, "executing");
        let words = parse_words(self.fw, &cmd);
        if !cmd.is_empty() && words.is_empty() {
            // Not a command at all, e.g. the tail of a line cut in two when a line error
            // flushed the receive buffer (`300 F1800b1`). Marlin's parser finds no G/M/T
            // word, says so and acknowledges; nothing is executed, so nothing is recorded.
            self.say(&format!("echo:Unknown command: \"{cmd}\""));
            return self.ok(n);
        }
        recorder.push(&cmd);
        if n.is_some() {
            self.numbered_executed += 1;
            if self.fire_line_faults() {
                return;
            }
        }
        let Some(&(letter, code)) = words.first() else {
            return self.ok(n);
        };
        let code_int = code as i64;
        let is_whole = (code - code.round()).abs() < 1e-9;
        let busy_fault = self.fw.busy_protocol()
            && self.faults.busy > 0.0
            && self.rng.random_bool(self.faults.busy.min(1.0));
        if busy_fault {
            tracing::debug!("fault: busy period");
        }
        let mut wait: Option<Wait> = None;
        let mut long = false;
        match (letter, is_whole.then_some(code_int)) {
            ('G', Some(0..=3)) => {
                let seconds = self.move_seconds(&words, code_int);
                if self.planner.len() < PLANNER_MOVES {
                    self.plan(seconds, now);
                } else {
                    wait = Some(Wait::PlannerSlot { seconds });
                    long = true;
                }
            }
            ('G', Some(4)) => {
                let ms =
                    word(&words, 'P').unwrap_or(0.0) + word(&words, 'S').unwrap_or(0.0) * 1000.0;
                wait = Some(Wait::Drain {
                    then: Some(Box::new(Wait::For(ms / 1000.0))),
                });
                long = true;
            }
            ('G', Some(28)) => {
                for (i, axis) in ['X', 'Y', 'Z'].into_iter().enumerate() {
                    let all = !['X', 'Y', 'Z'].iter().any(|a| word_present(&words, *a));
                    if all || word_present(&words, axis) {
                        self.position[i] = 0.0;
                    }
                }
                wait = Some(Wait::Drain {
                    then: Some(Box::new(Wait::For(HOMING_SECONDS))),
                });
                long = true;
            }
            ('G', Some(29)) => {
                wait = Some(Wait::Drain {
                    then: Some(Box::new(Wait::For(HOMING_SECONDS * 3.0))),
                });
                long = true;
            }
            // Marlin 2 sets every axis's mode with G90/G91, E's too; Ultimaker2Marlin
            // (Marlin 1) keeps E's own mode (M82/M83) and makes E relative under G91.
            ('G', Some(90)) => {
                self.relative = false;
                if self.fw != Firmware::Ultimaker2 {
                    self.relative_e = false;
                }
            }
            ('G', Some(91)) => {
                self.relative = true;
                if self.fw != Firmware::Ultimaker2 {
                    self.relative_e = true;
                }
            }
            ('G', Some(92)) => {
                for (i, axis) in ['X', 'Y', 'Z', 'E'].into_iter().enumerate() {
                    if let Some(v) = word(&words, axis) {
                        self.position[i] = v;
                    }
                }
            }
            ('M', Some(82)) => self.relative_e = false,
            ('M', Some(83)) => self.relative_e = true,
            ('M', Some(400)) => {
                wait = Some(Wait::Drain { then: None });
                long = true;
            }
            ('M', Some(104)) | ('M', Some(109)) => {
                let t = word(&words, 'S').or_else(|| word(&words, 'R'));
                if let Some(t) = t {
                    self.hotend.target = t.max(0.0);
                }
                if code_int == 109 {
                    wait = Some(Wait::Heat {
                        heater: Heater::Hotend,
                        cooling_too: word_present(&words, 'R'),
                    });
                    long = true;
                }
            }
            ('M', Some(140)) | ('M', Some(190)) => {
                let t = word(&words, 'S').or_else(|| word(&words, 'R'));
                if let Some(t) = t {
                    self.bed.target = t.max(0.0);
                }
                if code_int == 190 {
                    wait = Some(Wait::Heat {
                        heater: Heater::Bed,
                        cooling_too: word_present(&words, 'R'),
                    });
                    long = true;
                }
            }
            ('M', Some(105)) => {
                // M105 answers `ok` and the report on one line; never dropped, so a host's
                // probe after a lost ok always gets through.
                let report = format!("ok {}", self.temperature_report());
                self.say_noisy(&report);
                return;
            }
            ('M', Some(108)) => {}
            ('M', Some(112)) if self.fw.is_marlin2() => {
                self.say("Error:Printer halted. kill() called!");
                self.status = Status::Halted;
                return;
            }
            ('M', Some(110)) if self.fw == Firmware::Ultimaker2 => {
                // No M110 handler: the line's own number already reset the counter.
                self.say(&format!("echo:Unknown command: \"{cmd}\""));
            }
            ('M', Some(110)) => {
                // M110.cpp:31-32: the count is set again when the command runs (for an
                // unnumbered `M110 N5`, only then).
                let view = crispen_marlin::reader::marlin2::read(&cmd);
                if let Some(Some(v)) = view.params[usize::from(b'N' - b'A')] {
                    self.last_n = v.max(0.0) as u64;
                }
            }
            ('M', Some(113)) if self.fw.busy_protocol() => {
                match word(&words, 'S') {
                    // S0 turns the keep-alives off, as in Marlin.
                    Some(s) => self.keepalive = s.clamp(0.0, 60.0),
                    None => {
                        let interval = self.keepalive;
                        self.say(&format!("echo:M113 S{interval}"));
                    }
                }
            }
            ('M', Some(114)) => {
                let [x, y, z, e] = self.position;
                self.say(&format!(
                    "X:{x:.2} Y:{y:.2} Z:{z:.2} E:{e:.2} Count X:{} Y:{} Z:{}",
                    (x * 80.0) as i64,
                    (y * 80.0) as i64,
                    (z * 400.0) as i64
                ));
            }
            ('M', Some(115)) => self.m115(),
            ('M', Some(503)) => self.m503(),
            ('M', Some(92 | 201 | 203 | 204 | 205)) => {
                self.settings.apply_command(&cmd);
            }
            ('M', Some(155)) if self.fw.autoreport_temp() => {
                let s = word(&words, 'S').unwrap_or(0.0);
                if s > 0.0 {
                    let period = self.period(s);
                    self.autoreport = Some(period);
                    self.next_autoreport = Some(now + period);
                } else {
                    self.autoreport = None;
                    self.next_autoreport = None;
                }
            }
            ('M', Some(27)) => self.say("Not SD printing"),
            // Pauses a file may ask for; crispen never sends them, and the simulator does
            // what the firmware does with them, so a host that forwarded one is caught.
            // Printers with a display (HAS_RESUME_CONTINUE) wait for the knob at M0/M1;
            // Ultimaker2Marlin too, silently (it has no busy protocol).
            ('M', Some(0 | 1)) => {
                wait = Some(Wait::Drain {
                    then: Some(Box::new(Wait::User)),
                });
                long = true;
            }
            ('M', Some(600)) if self.fw.is_marlin2() && self.advanced_pause => {
                wait = Some(Wait::Drain {
                    then: Some(Box::new(Wait::User)),
                });
                long = true;
            }
            // Stock Marlin 2.1 lacks the features behind them (ADVANCED_PAUSE_FEATURE,
            // SDSUPPORT, PARK_HEAD_ON_PAUSE, DIRECT_PIN_CONTROL): the file's pause is lost.
            ('M', Some(25 | 125 | 226 | 600 | 601)) if self.fw.is_marlin2() => {
                self.say(&format!("echo:Unknown command: \"{cmd}\""));
            }
            _ if self.fw.is_marlin2() && !known_marlin2(letter, code) => {
                self.say(&format!("echo:Unknown command: \"{cmd}\""));
            }
            _ => {}
        }
        if busy_fault && wait.is_none() {
            // The command holds the main loop for three keep-alive intervals.
            let hold = self.period(self.keepalive) * 3;
            wait = Some(Wait::Until(now + hold));
            long = true;
        }
        // An `ok` already sent on entry is not sent again.
        self.answered = acked;
        match wait {
            None => self.ok(n),
            Some(wait) => {
                let heat = matches!(wait, Wait::Heat { .. });
                self.active = Some(Active {
                    wait,
                    n,
                    answered: std::mem::take(&mut self.answered),
                    busy: long,
                    next_heat_report: heat.then(|| now + MIN_PERIOD.max(self.real(1.0))),
                });
                self.next_keepalive = Some(now + self.period(self.keepalive));
                // A wait that is already over (instant timing) finishes right away.
                self.progress_active(now);
            }
        }
    }
}

/// Whether a line starts with a command word (`G1`, `M105`, `T0`, also lower case) that
#[cfg(test)]
mod tests {
    use super::*;

    fn printer(fw: Firmware) -> Printer {
        let mut cfg = SimConfig::new(fw);
        cfg.time_scale = 1.0;
        Printer::new(&cfg, Instant::now())
    }

    #[test]
    fn moves_take_their_distance_over_their_feedrate() {
        let mut p = printer(Firmware::Marlin2);
        let secs = p.move_seconds(&parse_words(Firmware::Marlin2, "G1 X10 F600"), 1);
        assert!((secs - 1.0).abs() < 1e-9, "{secs}");
        // F is persistent; then a diagonal from (10, 0) to (0, 20).
        let secs = p.move_seconds(&parse_words(Firmware::Marlin2, "G1 X0 Y20"), 1);
        assert!((secs - 500f64.sqrt() / 10.0).abs() < 1e-9, "{secs}");
        // Relative mode after G91 (handled in execute): emulate it directly.
        p.relative = true;
        let secs = p.move_seconds(&parse_words(Firmware::Marlin2, "G1 X-10"), 1);
        assert!((secs - 1.0).abs() < 1e-9);
        // Extrusion-only moves take their filament length.
        p.relative_e = true;
        let secs = p.move_seconds(&parse_words(Firmware::Marlin2, "G1 E5 F300"), 1);
        assert!((secs - 1.0).abs() < 1e-9, "{secs}");
    }

    /// E's mode as each firmware's source keeps it: Marlin 2's G90/G91 set E's mode too,
    /// Ultimaker2Marlin's leave M82/M83 alone but make E relative under G91. The host's
    /// follower must agree, or a resume after a pause would restore E wrongly.
    #[test]
    fn e_mode_per_firmware_and_the_hosts_follower_agrees() {
        use crispen_marlin::motion::Motion;
        let cases: [(&[&str], f64, f64); 4] = [
            // (commands after G92 E0, E on Marlin 2, E on Ultimaker2Marlin)
            (&["M83", "G90", "G1 E5", "G1 E5"], 5.0, 10.0),
            (&["G91", "M82", "G1 E5", "G1 E5"], 5.0, 10.0),
            (&["M82", "G91", "G1 E5", "G1 E5"], 10.0, 10.0),
            (&["M83", "G1 E5", "G90", "M83", "G1 E5"], 10.0, 10.0),
        ];
        for fw in [Firmware::Marlin2, Firmware::Marlin20, Firmware::Ultimaker2] {
            for (commands, marlin2, um2) in cases {
                let mut p = printer(fw);
                let mut recorder = Recorder {
                    executed: None,
                    file: None,
                };
                let mut host = Motion::new(fw);
                for cmd in std::iter::once(&"G92 E0").chain(commands) {
                    let queued = Queued {
                        n: None,
                        cmd: cmd.to_string(),
                        acked: false,
                    };
                    p.execute(queued, Instant::now(), &mut recorder);
                    host.apply(&crispen_marlin::reader::read(cmd).unwrap().unwrap())
                        .unwrap();
                }
                let expected = if fw == Firmware::Ultimaker2 {
                    um2
                } else {
                    marlin2
                };
                assert_eq!(p.position[3], expected, "{fw} {commands:?}");
                assert_eq!(host.file_position()[3], Some(expected), "{fw} {commands:?}");
            }
        }
    }

    /// `M503` answers as the real firmware does (its transcripts, taken from Marlin
    /// 2.1.2.1's Linux build and Ultimaker2Marlin in its emulator), and reports a setting
    /// a command changed; the host's reading of it gives the firmware's stock planner.
    #[test]
    fn m503_answers_as_the_real_firmware_does() {
        use crispen_marlin::estimate::Limits;
        for (fw, real) in [
            (
                Firmware::Marlin2,
                include_str!("../../marlin/src/protocol/tests/m503/marlin-2.1.2.1.txt"),
            ),
            (
                Firmware::Ultimaker2,
                include_str!("../../marlin/src/protocol/tests/m503/ultimaker2marlin-8698fb6.txt"),
            ),
        ] {
            let mut p = printer(fw);
            p.take_output();
            let mut recorder = Recorder {
                executed: None,
                file: None,
            };
            let mut run = |p: &mut Printer, cmd: &str| {
                let queued = Queued {
                    n: None,
                    cmd: cmd.to_string(),
                    acked: false,
                };
                p.execute(queued, Instant::now(), &mut recorder);
                String::from_utf8(p.take_output()).unwrap()
            };
            let answer = run(&mut p, "M503");
            // Up to its `ok` (the sim's Marlin 2 has ADVANCED_OK on, the real build not).
            let before_ok = |t: &str| t.lines().take_while(|l| !l.starts_with("ok")).count();
            let (lines, real_lines) = (answer.lines(), real.lines());
            assert_eq!(
                lines.take(before_ok(&answer)).collect::<Vec<_>>(),
                real_lines.take(before_ok(real)).collect::<Vec<_>>(),
                "{fw}"
            );
            let mut read = Limits::of(fw);
            read.apply_m503(&answer);
            assert_eq!(read, Limits::of(fw), "{fw}");
            run(&mut p, "M203 X200 Z4.5");
            let mut read = Limits::of(fw);
            read.apply_m503(&run(&mut p, "M503"));
            assert_eq!((read.max_feedrate[0], read.max_feedrate[2]), (200.0, 4.5));
        }
    }

    #[test]
    fn arcs_take_their_arc_length() {
        let mut p = printer(Firmware::Marlin2);
        p.position = [10.0, 0.0, 0.0, 0.0];
        // Counter-clockwise quarter circle of radius 10 around the origin at 60 mm/s.
        let secs = p.move_seconds(
            &parse_words(Firmware::Marlin2, "G3 X0 Y10 I-10 J0 F3600"),
            3,
        );
        // The firmware's angle is a float's: within 1e-7 of a quarter turn.
        let expected = std::f64::consts::FRAC_PI_2 * 10.0 / 60.0;
        assert!((secs - expected).abs() < 1e-6, "{secs} vs {expected}");
    }

    /// Issue 42: an arc whose ends are equal in float, not in double, is a whole circle on
    /// both firmwares (141 mm of radius: about 17.8 s at 50 mm/s); the same arc ending a
    /// thousandth away is a sliver. Marlin 2 answers the R form back to its start with
    /// `bad parameters`; Ultimaker2Marlin runs no counter-clockwise circle.
    #[test]
    fn arcs_run_as_the_firmware_computes_them() {
        let whole = 2.0 * std::f64::consts::PI * 100.0 * 2f64.sqrt() / 50.0;
        for fw in [Firmware::Marlin2, Firmware::Ultimaker2] {
            let mut p = printer(fw);
            p.position = [210.0, 210.0, 0.0, 0.0];
            let line = "G2 X210.000005 Y209.999995 I-100 J-100 F3000";
            let secs = p.move_seconds(&parse_words(fw, line), 2);
            assert!((secs - whole).abs() < 1e-3, "{fw}: {secs} vs {whole}");
            let line = "G2 X210.001 Y209.999 I-100 J-100";
            let secs = p.move_seconds(&parse_words(fw, line), 2);
            assert!(secs < 1e-4, "{fw}: {secs}");
            let read = |t| f64::from(crispen_marlin::reader::firmware_float(fw, t));
            assert_eq!(p.position[..2], [read("210.001"), read("209.999")], "{fw}");
        }
        let mut p = printer(Firmware::Marlin2);
        p.position = [150.0, 150.0, 0.0, 0.0];
        let secs = p.move_seconds(
            &parse_words(Firmware::Marlin2, "G2 X150.000005 Y150.000005 R50"),
            2,
        );
        assert_eq!(secs, 0.0);
        assert!(String::from_utf8_lossy(p.output()).contains("Error:G2/G3 bad parameters"));
        assert_eq!(p.position[..2], [150.0, 150.0]);
        let mut p = printer(Firmware::Ultimaker2);
        p.position = [150.0, 150.0, 0.0, 0.0];
        let secs = p.move_seconds(&parse_words(Firmware::Ultimaker2, "G3 I-5 J0"), 3);
        assert_eq!(secs, 0.0);
        let secs = p.move_seconds(&parse_words(Firmware::Ultimaker2, "G2 I-5 J0 F600"), 2);
        assert!((secs - std::f64::consts::PI).abs() < 1e-5, "{secs}");
    }

    #[test]
    fn boot_banner_per_profile() {
        let p = printer(Firmware::Ultimaker2);
        assert_eq!(p.output(), b"start\n");
        let p = printer(Firmware::Marlin2);
        assert!(p.output().starts_with(b"start\necho:Marlin 2.1.2\n"));
    }

    #[test]
    fn parses_words_without_spaces() {
        assert_eq!(
            parse_words(Firmware::Marlin2, "G1X10.5Y-2F3000"),
            vec![('G', 1.0), ('F', 3000.0), ('X', 10.5), ('Y', -2.0)]
        );
        // As each firmware reads them: junk hides nothing, an exponent, a G anywhere.
        let s = |fw, line| word(&parse_words(fw, line), 'S');
        assert_eq!(s(Firmware::Marlin2, "M104 @S400"), Some(400.0));
        assert_eq!(s(Firmware::Marlin2, "M104 S2.7E2"), Some(f64::from(2.7f32)));
        assert_eq!(s(Firmware::Ultimaker2, "M104 S2.7E2"), Some(270.0));
        assert_eq!(
            parse_words(Firmware::Ultimaker2, "M400 G92 Z50")[0],
            ('G', 92.0)
        );
        assert!(parse_words(Firmware::Marlin2, "m104 S400").is_empty());
    }
}
