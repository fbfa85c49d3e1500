//! Fault injection: what the simulated printer does wrong on purpose, drawn from the
//! seeded generator so a test sees the same faults every run (garbled answers, lost `ok`s,
//! corrupted received lines, spurious resends), the faults that fire after N lines (reset,
//! unplug, silence, halt, host actions, firmware errors), and pokes on demand. Kept out of
//! the firmware model so that it reads as what a healthy printer does.

use super::super::poke::Poke;
use super::state::{Printer, Status};
use rand::Rng;

impl Printer {
    /// Emit a line that the garbage fault may corrupt in ways a correct host survives.
    pub(super) fn say_noisy(&mut self, line: &str) {
        if self.status != Status::Running {
            return;
        }
        if self.faults.garbage > 0.0 && self.rng.random_bool(self.faults.garbage.min(1.0)) {
            let mut bytes = line.as_bytes().to_vec();
            if line.starts_with("ok") {
                if self.rng.random_bool(0.5) {
                    bytes.insert(2, b'k'); // `okk`: still reads as an ok to a lenient host
                } else {
                    // The ok drowned in noise: a lost ack the host recovers by probing.
                    bytes = b"o\xff\xfek".to_vec();
                }
            } else if line.starts_with("Resend: ") {
                bytes = line.replacen("Resend: ", "Resend:", 1).into_bytes();
            } else if !bytes.is_empty() {
                let at = self.rng.random_range(0..bytes.len());
                bytes[at] = 0x80 | self.rng.random::<u8>();
            }
            self.out.extend_from_slice(&bytes);
            self.out.push(b'\n');
            if self.rng.random_bool(0.3) {
                self.out.extend_from_slice(b"\xfe\x00\xc3(noise\x9f\n");
            }
            return;
        }
        self.say(line);
    }

    pub(super) fn drop_this_ok(&mut self) -> bool {
        let drop = self.faults.drop_ok > 0.0 && self.rng.random_bool(self.faults.drop_ok.min(1.0));
        if drop {
            tracing::debug!("fault: dropping an ok");
        }
        drop
    }

    /// The corruption fault on a line just assembled from the receive ring.
    pub(super) fn corrupt_received(&mut self, raw: &mut [u8]) {
        if self.faults.corrupt_host_bytes > 0.0
            && !raw.is_empty()
            && self
                .rng
                .random_bool(self.faults.corrupt_host_bytes.min(1.0))
        {
            // Any byte but the framing a checksum cannot protect: the leading `N` (without
            // it Marlin 2 checks nothing and runs the rest) and the `*`; and no new ones.
            let start = usize::from(raw[0] == b'N');
            let mut at = self.rng.random_range(start.min(raw.len() - 1)..raw.len());
            if raw[at] == b'*' {
                // The last checksum-protected byte before it.
                at = at.saturating_sub(1).max(start);
            }
            let mut c = raw[at];
            while c == raw[at] || c == b'N' || c == b'*' {
                c = self.rng.random_range(0x20u8..0x7f);
            }
            if raw[at] != b'*' && !(at == 0 && raw[0] == b'N') {
                tracing::debug!(at, "fault: corrupting a received line");
                raw[at] = c;
            }
        }
    }

    /// The star-for-dot fault on a numbered line just assembled from the receive ring.
    pub(super) fn star_for_dot(&mut self, raw: &mut [u8]) {
        if self.faults.star_for_dot > 0.0
            && raw.first() == Some(&b'N')
            && self.rng.random_bool(self.faults.star_for_dot.min(1.0))
        {
            let dots: Vec<usize> = (0..raw.len()).filter(|&i| raw[i] == b'.').collect();
            if !dots.is_empty() {
                let at = dots[self.rng.random_range(0..dots.len())];
                tracing::debug!(at, "fault: a `.` arrives as `*`");
                raw[at] = b'*';
            }
        }
    }

    /// The lost-line fault: a numbered line just assembled never arrived.
    pub(super) fn lose_line(&mut self, raw: &[u8]) -> bool {
        let hit = self.faults.lose_line > 0.0
            && raw.first() == Some(&b'N')
            && self.rng.random_bool(self.faults.lose_line.min(1.0));
        if hit {
            tracing::debug!("fault: a line lost whole");
        }
        hit
    }

    /// The spurious-resend fault: a good line answered as if it had been corrupted.
    pub(super) fn spurious_resend(&mut self) -> bool {
        let hit = self.faults.spurious_resend > 0.0
            && self.rng.random_bool(self.faults.spurious_resend.min(1.0));
        if hit {
            tracing::debug!("fault: spurious resend");
        }
        hit
    }

    /// Apply the `*_after_lines` faults; true if the command must not run.
    pub(super) fn fire_line_faults(&mut self) -> bool {
        let count = self.numbered_executed;
        // Host actions and firmware errors due now: as if someone poked the printer.
        let due = |list: &[(usize, String)]| -> Vec<String> {
            list.iter()
                .filter(|(after, _)| *after == count)
                .map(|(_, text)| text.clone())
                .collect()
        };
        let pokes: Vec<Poke> = (due(&self.faults.actions).into_iter().map(Poke::Action))
            .chain(due(&self.faults.errors).into_iter().map(Poke::Error))
            .chain(due(&self.faults.receive).into_iter().map(Poke::Receive))
            .collect();
        for poke in pokes {
            tracing::info!(lines = count, ?poke, "fault: due after these lines");
            self.poke(poke);
        }
        if self.faults.reset_after_lines == Some(count) {
            tracing::warn!(lines = count, "fault: printer reset");
            self.boot();
            return true;
        }
        if self.faults.unplug_after_lines == Some(count) {
            tracing::warn!(lines = count, "fault: unplug");
            self.status = Status::Unplugged;
            return true;
        }
        if self.faults.silence_after_lines == Some(count) {
            tracing::warn!(lines = count, "fault: silence");
            self.status = Status::Silent;
            return true;
        }
        if self.faults.fatal_after_lines == Some(count) {
            tracing::warn!(lines = count, "fault: fatal error");
            self.say("Error:Thermal Runaway, system stopped! Heater_ID: 0");
            self.say("Error:Printer halted. kill() called!");
            self.status = Status::Halted;
            return true;
        }
        false
    }

    /// Act on a [`Poke`] at once, whatever the printer is doing.
    pub(crate) fn poke(&mut self, poke: Poke) {
        match poke {
            Poke::Reset => {
                if self.status == Status::Unplugged {
                    return;
                }
                tracing::warn!("poke: reset");
                // A reset brings a halted or mute board back.
                self.status = Status::Running;
                self.boot();
            }
            Poke::Action(name) => {
                tracing::info!(action = %name, "poke: host action from the printer's menu");
                self.say(&format!("//action:{name}"));
            }
            Poke::Error(text) => {
                tracing::warn!(error = %text, "poke: firmware error");
                self.say(&format!("Error:{text}"));
            }
            Poke::Receive(text) => {
                tracing::warn!(line = %text, "poke: a line received between the host's");
                // Between two of the host's lines: next, or after the one being received.
                let at = if self.assembling.is_empty() {
                    0
                } else {
                    self.rx
                        .iter()
                        .position(|&b| b == b'\n' || b == b'\r')
                        .map_or(self.rx.len(), |i| i + 1)
                };
                for (i, b) in text.bytes().chain([b'\n']).enumerate() {
                    self.rx.insert(at + i, b);
                }
            }
        }
    }
}
