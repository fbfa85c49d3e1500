//! One line from the printer, classified without any state: the host state machine first
//! turns each line into a [`Reply`] and only then acts on it. Nothing here knows what the
//! host sent; the classification is the same for every firmware, because the printer-to-host
//! direction has no checksum and real answers arrive garbled (`okk`, `Resend:12`, a `start`
//! glued to the end of a temperature report when the board resets mid-line).

use super::temperature::{Temp, Temperatures};

/// A classified printer line.
#[derive(Debug, Clone, PartialEq)]
pub enum Reply {
    /// `start`: the board has just booted. Also found at the end of a line the reset cut
    /// short (`T:205.3 /210 B:6start`).
    Start,
    Ok(OkReply),
    /// `Resend: 12`, `Resend:12`, `rs 12`.
    Resend(u64),
    /// `Error:checksum mismatch, Last Line: 6` and its kin: a `Resend:` follows.
    LineError(String),
    /// The printer halted (`kill()`, `Printer halted`, `Printer stopped`): nothing answers
    /// after it.
    Fatal(String),
    /// Any other `Error:` or `!!` line (including Ultimaker2Marlin's `Error:No Line Number
    /// with checksum`, which has neither a `Resend:` nor an `ok` after it).
    Error(String),
    /// `echo:busy: processing` and the other busy keep-alives.
    Busy(String),
    /// `wait`: the printer's command queue is empty (NO_TIMEOUTS). Not a keep-alive.
    Wait,
    /// `echo:Unknown command: "M73 P0"`, with the text between the quotes. An `ok` follows.
    UnknownCommand(String),
    /// A temperature report not attached to an `ok`.
    Temperatures(Report),
    /// An `M115` line with `FIRMWARE_NAME:`.
    FirmwareName(String),
    /// `Cap:NAME:0|1`.
    Capability(String, bool),
    /// `echo:  M203 X300.00 Y300.00 Z5.00 E25.00`: one of the planner's settings (steps
    /// per mm `M92`, accelerations `M201`/`M204`, feed rates `M203`, advanced `M205`) as the
    /// printer reports them in answer to `M503` and in its boot banner; the command as
    /// written, without `echo:`.
    Setting(String),
    /// `//action:NAME ...` (HOST_ACTION_COMMANDS): the printer's own Stop or Pause menu.
    Action(HostAction),
    /// Anything else (`echo:` lines, banners, noise), kept for the log.
    Other(String),
}

/// `ok`, `ok N12 P15 B3` (ADVANCED_OK), `ok T:210.0 /210.0 ...` (an answered `M105`).
#[derive(Debug, Clone, PartialEq, Default)]
pub struct OkReply {
    /// `N<n>`: the line this `ok` answers (ADVANCED_OK builds, numbered lines only).
    pub line: Option<u64>,
    /// `P<p> B<b>` seen: an ADVANCED_OK build. Without `N` it answers a line that had no
    /// number, i.e. a fragment of a line cut by a receive-buffer flush.
    pub advanced: bool,
    /// The temperatures of an `M105` answer.
    pub report: Option<Report>,
    /// Words after `ok` other than the ADVANCED_OK fields: only an `M105`'s answer carries
    /// text, whatever its form, so this (not whether the temperatures parse) marks one.
    pub text: bool,
}

/// A temperature report.
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub struct Report {
    pub temperatures: Temperatures,
    /// `W:` present: the printer is inside an M109/M190 wait (Marlin counts the residency
    /// time down in it; Ultimaker2Marlin prints `W:?`).
    pub waiting: bool,
}

#[derive(Debug, Clone, PartialEq, Eq)]
pub enum HostAction {
    Cancel,
    Pause,
    Resume,
    /// Actions crispen does not act on (`//action:notification ...`, `prompt_begin`...).
    Other(String),
}

impl Reply {
    /// Classify one line (without its line ending). Never panics, whatever the bytes.
    pub fn parse(raw: &[u8]) -> Option<Reply> {
        let text = String::from_utf8_lossy(raw);
        let line = text.trim_matches(|c: char| c.is_whitespace() || c == '\0');
        if line.is_empty() {
            return None;
        }
        let lower = line.to_ascii_lowercase();
        if ends_with_start(&lower) {
            return Some(Reply::Start);
        }
        if let Some(action) = line.strip_prefix("//action:") {
            let name = action.split_whitespace().next().unwrap_or("");
            return Some(Reply::Action(match name.to_ascii_lowercase().as_str() {
                "cancel" => HostAction::Cancel,
                "pause" => HostAction::Pause,
                "resume" => HostAction::Resume,
                _ => HostAction::Other(action.trim().to_string()),
            }));
        }
        if lower.starts_with("error:") || lower.starts_with("!!") {
            if lower.contains("kill()")
                || lower.contains("printer halted")
                || lower.contains("printer stopped")
            {
                return Some(Reply::Fatal(line.to_string()));
            }
            if lower.contains("last line") {
                return Some(Reply::LineError(line.to_string()));
            }
            return Some(Reply::Error(line.to_string()));
        }
        if let Some(n) = parse_resend(&lower) {
            return Some(Reply::Resend(n));
        }
        if lower.starts_with("ok") {
            return Some(Reply::Ok(parse_ok(line)));
        }
        if lower.contains("busy:") {
            return Some(Reply::Busy(line.to_string()));
        }
        if lower == "wait" {
            return Some(Reply::Wait);
        }
        if let Some(at) = lower.find("unknown command:") {
            let rest = line[at + "unknown command:".len()..].trim();
            let inner = rest.trim_matches('"');
            return Some(Reply::UnknownCommand(inner.to_string()));
        }
        if lower.starts_with("firmware_name:") || lower.contains(" firmware_name:") {
            return Some(Reply::FirmwareName(line.to_string()));
        }
        if let Some(cap) = line.strip_prefix("Cap:") {
            if let Some((name, value)) = cap.rsplit_once(':') {
                return Some(Reply::Capability(
                    name.trim().to_string(),
                    value.trim() == "1",
                ));
            }
        }
        if let Some(setting) = parse_setting(line) {
            return Some(Reply::Setting(setting.to_string()));
        }
        if let Some(report) = parse_report(line) {
            return Some(Reply::Temperatures(report));
        }
        Some(Reply::Other(line.to_string()))
    }
}

/// `start` alone, or glued to the end of a line a reset cut short. A word ending in
/// `start` (`restart`) is not a boot.
fn ends_with_start(lower: &str) -> bool {
    let Some(before) = lower.strip_suffix("start") else {
        return false;
    };
    before
        .chars()
        .last()
        .is_none_or(|c| !c.is_ascii_alphabetic())
        && !before.contains('"')
}

/// The planner settings `M503` reports, as the one G-code reader reads them (both
/// firmwares write them as plain commands after `echo:` and spaces; Marlin 2 puts a
/// comment line before each, Ultimaker2Marlin a title).
const SETTINGS: [&str; 5] = ["M92", "M201", "M203", "M204", "M205"];

/// `echo:  M92 X80.00 Y80.00 Z400.00 E500.00`: the command, if it is one of [`SETTINGS`]
/// with at least one value.
fn parse_setting(line: &str) -> Option<&str> {
    let command = line.strip_prefix("echo:").unwrap_or(line).trim();
    let read = crate::reader::read(command).ok()??;
    (SETTINGS.contains(&read.code.as_str()) && read.words.iter().any(|w| w.value.is_some()))
        .then_some(command)
}

/// `Resend: 12`, `Resend:12`, `rs 12`, `rs:12`.
fn parse_resend(lower: &str) -> Option<u64> {
    let rest = match lower.find("resend") {
        Some(pos) => &lower[pos + "resend".len()..],
        None => lower.strip_prefix("rs")?,
    };
    let rest = rest.trim_start_matches([':', ' ', '\t']);
    let digits: String = rest.chars().take_while(|c| c.is_ascii_digit()).collect();
    digits.parse().ok()
}

fn parse_ok(line: &str) -> OkReply {
    let mut ok = OkReply::default();
    // Words after `ok` (a garbled `okk` keeps its words).
    for word in line.split_whitespace().skip(1) {
        let mut chars = word.chars();
        let letter = chars.next().unwrap_or(' ');
        let digits = chars.as_str();
        if digits.is_empty() || !digits.bytes().all(|b| b.is_ascii_digit()) {
            continue;
        }
        match letter {
            'N' => ok.line = digits.parse().ok(),
            'P' | 'B' => ok.advanced = true,
            _ => {}
        }
    }
    ok.report = parse_report(line);
    ok.text = ok.report.is_some()
        || line.split_whitespace().skip(1).any(|word| {
            let mut chars = word.chars();
            let letter = chars.next().unwrap_or(' ');
            let digits = chars.as_str();
            !(matches!(letter, 'N' | 'P' | 'B')
                && !digits.is_empty()
                && digits.bytes().all(|b| b.is_ascii_digit()))
        });
    ok
}

/// `T:cur /target B:cur /target @:0 B@:0`, `T:210.0 E:0 W:?` (Ultimaker2Marlin while
/// heating: no target). Firmwares space the `/` every way (`T:24.99 /0.00` from Marlin,
/// `T:24.99/ 0.00` from OctoPrint's virtual printer, `T:24.99/0.00`, `T:24.99 / 0.00`), so
/// the spaces around it are dropped first. None if the line has no hotend or bed reading.
pub(crate) fn parse_report(line: &str) -> Option<Report> {
    let mut temps = Temperatures::default();
    let mut waiting = false;
    let joined = line
        .split_whitespace()
        .collect::<Vec<_>>()
        .join(" ")
        .replace(" /", "/")
        .replace("/ ", "/");
    for token in joined.split(' ') {
        if token.starts_with("W:") {
            waiting = true;
            continue;
        }
        let (slot, value) = if let Some(v) = token.strip_prefix("T:") {
            (&mut temps.hotend, v)
        } else if let Some(v) = token.strip_prefix("B:") {
            (&mut temps.bed, v)
        } else {
            continue;
        };
        let (current, target) = match value.split_once('/') {
            Some((current, target)) => (current, Some(target)),
            None => (value, None),
        };
        let Some(current) = current.parse::<f64>().ok().filter(|c| c.is_finite()) else {
            continue;
        };
        let target = target
            .and_then(|t| t.parse::<f64>().ok())
            .filter(|t| t.is_finite());
        if slot.is_none() {
            *slot = Some(Temp { current, target });
        }
    }
    (temps.hotend.is_some() || temps.bed.is_some()).then_some(Report {
        temperatures: temps,
        waiting,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    fn parse(s: &str) -> Reply {
        Reply::parse(s.as_bytes()).expect("not empty")
    }

    #[test]
    fn classifies_every_kind_of_line() {
        assert_eq!(parse("start"), Reply::Start);
        assert_eq!(parse("T:205.3 /210.00 B:6start"), Reply::Start);
        assert_eq!(parse("ok T:20 /0 B:6start"), Reply::Start);
        assert!(matches!(parse("echo:restart"), Reply::Other(_)));
        assert_eq!(parse("ok"), Reply::Ok(OkReply::default()));
        assert_eq!(parse("okk"), Reply::Ok(OkReply::default()));
        assert_eq!(
            parse("ok N12 P15 B3"),
            Reply::Ok(OkReply {
                line: Some(12),
                advanced: true,
                report: None,
                text: false
            })
        );
        assert_eq!(
            parse("ok P15 B3"),
            Reply::Ok(OkReply {
                line: None,
                advanced: true,
                report: None,
                text: false
            })
        );
        let Reply::Ok(ok) = parse("ok T:210.0 /210.0 B:60.0 /60.0 @:127 B@:0") else {
            panic!()
        };
        assert_eq!(ok.line, None);
        assert!(!ok.advanced, "B:60.0 is a bed reading, not B<free slots>");
        let report = ok.report.unwrap();
        assert_eq!(
            report.temperatures.bed,
            Some(Temp {
                current: 60.0,
                target: Some(60.0)
            })
        );
        assert_eq!(parse("Resend: 12"), Reply::Resend(12));
        assert_eq!(parse("Resend:12"), Reply::Resend(12));
        assert_eq!(parse("rs 12"), Reply::Resend(12));
        assert!(matches!(
            parse("Error:checksum mismatch, Last Line: 6"),
            Reply::LineError(_)
        ));
        assert!(matches!(
            parse("Error:No Line Number with checksum"),
            Reply::Error(_)
        ));
        assert!(matches!(
            parse("Error:Printer halted. kill() called!"),
            Reply::Fatal(_)
        ));
        assert!(matches!(parse("echo:busy: processing"), Reply::Busy(_)));
        assert_eq!(parse("wait"), Reply::Wait);
        assert_eq!(
            parse("echo:Unknown command: \"300 F1800\""),
            Reply::UnknownCommand("300 F1800".into())
        );
        assert_eq!(parse("//action:cancel"), Reply::Action(HostAction::Cancel));
        assert_eq!(parse("//action:pause"), Reply::Action(HostAction::Pause));
        assert_eq!(parse("//action:resume"), Reply::Action(HostAction::Resume));
        assert_eq!(
            parse("Cap:AUTOREPORT_TEMP:1"),
            Reply::Capability("AUTOREPORT_TEMP".into(), true)
        );
        assert!(matches!(
            parse("FIRMWARE_NAME:Marlin 2.1.2.1 PROTOCOL_VERSION:1.0"),
            Reply::FirmwareName(_)
        ));
        assert!(matches!(parse("\u{fffd}(noise"), Reply::Other(_)));
        assert_eq!(Reply::parse(b"  \r"), None);
    }

    /// The answers of the real firmware to `M503` (Marlin 2.1.2.1's Linux build,
    /// Ultimaker2Marlin in its emulator), as they came: the planner's settings are read,
    /// every other line (titles, `G21`, `M149 C`, `M206`, PID) is not one.
    #[test]
    fn settings_are_read_from_both_firmwares_m503_answers() {
        let settings = |text: &str| -> Vec<String> {
            text.lines()
                .filter_map(|l| match parse(l) {
                    Reply::Setting(s) => Some(s),
                    _ => None,
                })
                .collect()
        };
        assert_eq!(
            settings(include_str!("tests/m503/marlin-2.1.2.1.txt")),
            [
                "M92 X80.00 Y80.00 Z400.00 E500.00",
                "M203 X300.00 Y300.00 Z5.00 E25.00",
                "M201 X3000.00 Y3000.00 Z100.00 E10000.00",
                "M204 P3000.00 R3000.00 T3000.00",
                "M205 B20000.00 S0.00 T0.00 J0.01",
            ]
        );
        assert_eq!(
            settings(include_str!("tests/m503/ultimaker2marlin-8698fb6.txt")),
            [
                "M92 X80.00 Y80.00 Z200.00 E282.00",
                "M203 X300.00 Y300.00 Z40.00 E45.00",
                "M201 X9000 Y9000 Z100 E10000",
                "M204 S3000.00 T3000.00",
                "M205 S0.00 T0.00 B20000 X20.00 Z0.40 E5.00",
            ]
        );
        // Not a setting: no value, another command, a garbled one, a message about one.
        for line in [
            "echo:  M203",
            "echo:  M206 X0.00 Y0.00 Z0.00",
            "echo:  M2O3 X300.00",
            "echo:Unknown command: \"M203 X1\"",
        ] {
            assert!(!matches!(parse(line), Reply::Setting(_)), "{line}");
        }
    }

    /// Issue 21, failure 0: OctoPrint's virtual printer writes `T:24.99/ 0.00`; read as no
    /// temperature at all, its `M105` answers counted as plain `ok`s and a job never ended.
    #[test]
    fn reports_are_read_whatever_the_spacing_around_the_slash() {
        for (text, hotend, bed) in [
            (
                "ok T:24.99/ 0.00 B:48.23/ 0.00 @:64",
                (24.99, 0.0),
                (48.23, 0.0),
            ),
            (
                "ok T:24.99 /0.00 B:48.23 /60.00 @:64",
                (24.99, 0.0),
                (48.23, 60.0),
            ),
            ("ok T:24.99/0.00 B:48.23/60.00", (24.99, 0.0), (48.23, 60.0)),
            (
                "ok T:24.99 / 0.00 B:48.23  /  60.00",
                (24.99, 0.0),
                (48.23, 60.0),
            ),
            (
                "ok T:25.00/ 25.00 B:60.00/ 60.00 @:64",
                (25.0, 25.0),
                (60.0, 60.0),
            ),
            (
                "ok T:21.9 /0.0 B:22.0 /0.0 @:0 B@:0",
                (21.9, 0.0),
                (22.0, 0.0),
            ),
        ] {
            let Reply::Ok(ok) = parse(text) else {
                panic!("{text}")
            };
            assert!(ok.text, "{text}");
            let t = ok.report.unwrap_or_else(|| panic!("{text}")).temperatures;
            assert_eq!(
                t.hotend,
                Some(Temp {
                    current: hotend.0,
                    target: Some(hotend.1)
                }),
                "{text}"
            );
            assert_eq!(
                t.bed,
                Some(Temp {
                    current: bed.0,
                    target: Some(bed.1)
                }),
                "{text}"
            );
        }
        // Text that is no temperature still marks the answer of an M105.
        let Reply::Ok(ok) = parse("ok T:garbled?? B:") else {
            panic!()
        };
        assert!(ok.text && ok.report.is_none());
        for plain in ["ok", "okk", "ok N12 P15 B3", "ok P15 B3"] {
            let Reply::Ok(ok) = parse(plain) else {
                panic!()
            };
            assert!(!ok.text, "{plain}");
        }
    }

    #[test]
    fn ultimaker2_heat_reports_have_no_target_but_say_they_wait() {
        let Reply::Temperatures(r) = parse("T:210.0 E:0 W:?") else {
            panic!()
        };
        assert!(r.waiting);
        assert_eq!(
            r.temperatures.hotend,
            Some(Temp {
                current: 210.0,
                target: None
            })
        );
        let Reply::Temperatures(r) = parse(" T:190.00 /200.00 B:60.00 /60.00 @:127 B@:0 W:5")
        else {
            panic!()
        };
        assert!(r.waiting);
        let Reply::Temperatures(r) = parse("T:190.00 /200.00 B:60.00 /60.00 @:127 B@:0") else {
            panic!()
        };
        assert!(!r.waiting);
    }

    /// The host assembles lines from arbitrary chunks; whatever the split, every line gives
    /// the same reply, and garbage never panics.
    #[test]
    fn lines_split_at_every_byte_classify_the_same() {
        let stream: &[u8] = b"ok N3 P15 B3\nok T:200.0 /210.0 B:60.0 /60.0\necho:busy: processing\r\nResend:2\nok\nwait\nT:210.0 E:0 W:?\n//action:pause\necho:Unknown command: \"X\"\n\xff\xfe\x00\nT:1 /2 B:6start\n";
        let whole: Vec<Option<Reply>> = stream.split(|&b| b == b'\n').map(Reply::parse).collect();
        for cut in 0..=stream.len() {
            let mut partial = Vec::new();
            let mut replies = Vec::new();
            for chunk in [&stream[..cut], &stream[cut..]] {
                for &b in chunk {
                    if b == b'\n' {
                        replies.push(Reply::parse(&std::mem::take(&mut partial)));
                    } else {
                        partial.push(b);
                    }
                }
            }
            replies.push(Reply::parse(&partial));
            assert_eq!(replies, whole, "split at {cut}");
        }
        for len in 0..stream.len() {
            let _ = Reply::parse(&stream[..len]);
        }
    }
}
