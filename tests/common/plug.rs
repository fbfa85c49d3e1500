//! A smart plug of our own on loopback for the power tests: a real HTTP server, in a thread
//! of its own, that speaks Tasmota's (`/cm?cmnd=Power%20On`) and Shelly's protocols (Gen1
//! `/relay/0?turn=on`, Gen2 RPC `/rpc/Switch.Set?id=0&on=true` and
//! `/rpc/Switch.GetStatus?id=0`) as those devices answer, and whose relay really powers a
//! printer: switched on, it starts a simulated printer (`crispen sim --link PATH`); switched
//! off, it kills it, as a power cut would, and its pty is gone. Each switch is recorded, so
//! a test can prove a plug was or was not switched. Stopped (and its printer killed) when
//! dropped.

use std::io::{BufRead, BufReader, Write};
use std::net::TcpListener;
use std::path::{Path, PathBuf};
use std::process::{Child, Command};
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, Mutex};

/// What the plug was asked and what it did.
#[derive(Debug, Clone, PartialEq)]
pub enum Switched {
    On,
    Off,
}

struct Relay {
    printer: Option<Child>,
    /// The starts so far: each simulator records to `<record>.<n>`.
    starts: usize,
    switched: Vec<Switched>,
}

pub struct Plug {
    pub port: u16,
    relay: Arc<Mutex<Relay>>,
    stop: Arc<AtomicBool>,
}

impl Plug {
    /// A plug whose printer is `crispen sim` (firmware marlin2, instant) linked at `link`,
    /// recording to `<record>.<n>` for its n-th start; on at once when `on`.
    pub fn start(bin: &str, link: &Path, record: &Path, on: bool) -> Plug {
        let listener = TcpListener::bind(("127.0.0.1", 0)).expect("bind the plug");
        listener.set_nonblocking(true).unwrap();
        let port = listener.local_addr().unwrap().port();
        let relay = Arc::new(Mutex::new(Relay {
            printer: None,
            starts: 0,
            switched: Vec::new(),
        }));
        let stop = Arc::new(AtomicBool::new(false));
        let (bin, link, record) = (bin.to_string(), link.to_path_buf(), record.to_path_buf());
        let power = {
            let relay = relay.clone();
            move |on: bool| {
                let mut r = relay.lock().unwrap();
                match (on, r.printer.is_some()) {
                    (true, false) => {
                        r.starts += 1;
                        let rec = PathBuf::from(format!("{}.{}", record.display(), r.starts));
                        let mut sim = Command::new(&bin);
                        sim.args([
                            "sim",
                            "--firmware",
                            "marlin2",
                            "--speed",
                            "instant",
                            "--link",
                        ])
                        .arg(&link)
                        .arg("--record")
                        .arg(rec);
                        let (child, _) = super::daemon::spawn_sim(&mut sim);
                        r.printer = Some(child);
                    }
                    (false, true) => {
                        let mut child = r.printer.take().unwrap();
                        let _ = child.kill();
                        let _ = child.wait();
                        let _ = std::fs::remove_file(&link);
                    }
                    _ => {}
                }
                r.switched
                    .push(if on { Switched::On } else { Switched::Off });
            }
        };
        if on {
            power(true);
            relay.lock().unwrap().switched.clear();
        }
        {
            let (relay, stop) = (relay.clone(), stop.clone());
            std::thread::spawn(move || {
                while !stop.load(Ordering::SeqCst) {
                    let Ok((stream, _)) = listener.accept() else {
                        std::thread::sleep(std::time::Duration::from_millis(10));
                        continue;
                    };
                    stream.set_nonblocking(false).unwrap();
                    let mut reader = BufReader::new(stream.try_clone().unwrap());
                    let mut head = String::new();
                    let _ = reader.read_line(&mut head);
                    // The rest of the head; these requests carry no body.
                    let mut line = String::new();
                    while reader.read_line(&mut line).is_ok_and(|n| n > 2) {
                        line.clear();
                    }
                    let target = head.split_whitespace().nth(1).unwrap_or("").to_string();
                    let is_on = || relay.lock().unwrap().printer.is_some();
                    let body = match target.as_str() {
                        "/cm?cmnd=Power%20On" => Some(("tasmota", Some(true))),
                        "/cm?cmnd=Power%20Off" => Some(("tasmota", Some(false))),
                        "/cm?cmnd=Power" => Some(("tasmota", None)),
                        "/relay/0?turn=on" => Some(("shelly", Some(true))),
                        "/relay/0?turn=off" => Some(("shelly", Some(false))),
                        "/relay/0" => Some(("shelly", None)),
                        "/rpc/Switch.Set?id=0&on=true" => Some(("rpc-set", Some(true))),
                        "/rpc/Switch.Set?id=0&on=false" => Some(("rpc-set", Some(false))),
                        "/rpc/Switch.GetStatus?id=0" => Some(("rpc-status", None)),
                        _ => None,
                    }
                    .map(|(kind, set)| {
                        let was = is_on();
                        if let Some(on) = set {
                            power(on);
                        }
                        let now = is_on();
                        match kind {
                            "tasmota" => {
                                format!(r#"{{"POWER":"{}"}}"#, if now { "ON" } else { "OFF" })
                            }
                            "shelly" => {
                                format!(r#"{{"ison":{now},"has_timer":false,"source":"http"}}"#)
                            }
                            "rpc-set" => format!(r#"{{"was_on":{was}}}"#),
                            _ => format!(r#"{{"id":0,"source":"http","output":{now}}}"#),
                        }
                    });
                    let mut out = stream;
                    let answer = match body {
                        Some(b) => format!(
                            "HTTP/1.1 200 OK\r\nContent-Type: application/json\r\nContent-Length: {}\r\nConnection: close\r\n\r\n{b}",
                            b.len()
                        ),
                        None => "HTTP/1.1 404 Not Found\r\nContent-Length: 0\r\nConnection: close\r\n\r\n".into(),
                    };
                    let _ = out.write_all(answer.as_bytes());
                }
            });
        }
        Plug { port, relay, stop }
    }

    /// Its address, for `[printer.power] url`.
    pub fn url(&self) -> String {
        format!("http://127.0.0.1:{}", self.port)
    }

    /// Every switching it was asked for, in order (a query of its state is none).
    pub fn switched(&self) -> Vec<Switched> {
        self.relay.lock().unwrap().switched.clone()
    }

    /// Its printer runs.
    pub fn is_on(&self) -> bool {
        self.relay.lock().unwrap().printer.is_some()
    }

    /// How many times its printer was started.
    pub fn starts(&self) -> usize {
        self.relay.lock().unwrap().starts
    }
}

impl Drop for Plug {
    fn drop(&mut self) {
        self.stop.store(true, Ordering::SeqCst);
        if let Some(mut child) = self.relay.lock().unwrap().printer.take() {
            let _ = child.kill();
            let _ = child.wait();
        }
    }
}
