//! A real HTTP receiver of notifications for the tests: a TCP listener on 127.0.0.1 in a
//! thread of its own that reads each request (head and body), keeps it, and answers as
//! the test sets it: a status (200, 503...) or nothing at all (a black hole that holds
//! the connection open, as a hung server does). Stopped when dropped.

use std::io::{BufRead, BufReader, Read, Write};
use std::net::{TcpListener, TcpStream};
use std::sync::atomic::{AtomicBool, AtomicU16, Ordering};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

/// One request as received.
#[derive(Debug, Clone)]
pub struct Received {
    pub method: String,
    pub path: String,
    /// Header names in lower case.
    pub headers: Vec<(String, String)>,
    pub body: Vec<u8>,
    /// The status it was answered with (0: not answered).
    pub answered: u16,
}

impl Received {
    pub fn header(&self, name: &str) -> Option<&str> {
        self.headers
            .iter()
            .find(|(k, _)| k == name)
            .map(|(_, v)| v.as_str())
    }

    pub fn json(&self) -> serde_json::Value {
        serde_json::from_slice(&self.body)
            .unwrap_or_else(|e| panic!("not JSON ({e}): {}", String::from_utf8_lossy(&self.body)))
    }
}

pub struct Receiver {
    pub port: u16,
    /// The status answered now; 0: never answer.
    status: Arc<AtomicU16>,
    received: Arc<Mutex<Vec<Received>>>,
    stop: Arc<AtomicBool>,
}

impl Receiver {
    /// Listens on a free port (or `port`, to come back on the same one), answering 200.
    pub fn start_on(port: u16) -> Receiver {
        let listener = TcpListener::bind(("127.0.0.1", port)).expect("bind the receiver");
        listener.set_nonblocking(true).unwrap();
        let port = listener.local_addr().unwrap().port();
        let status = Arc::new(AtomicU16::new(200));
        let received = Arc::new(Mutex::new(Vec::new()));
        let stop = Arc::new(AtomicBool::new(false));
        {
            let (status, received, stop) = (status.clone(), received.clone(), stop.clone());
            std::thread::spawn(move || {
                let mut held = Vec::new();
                while !stop.load(Ordering::SeqCst) {
                    match listener.accept() {
                        Ok((stream, _)) => {
                            let (status, received) = (status.clone(), received.clone());
                            // Each connection on a thread: a black-holed one blocks only itself.
                            let stop = stop.clone();
                            held.push(std::thread::spawn(move || {
                                serve(stream, &status, &received, &stop)
                            }));
                        }
                        Err(_) => std::thread::sleep(Duration::from_millis(10)),
                    }
                }
            });
        }
        Receiver {
            port,
            status,
            received,
            stop,
        }
    }

    pub fn start() -> Receiver {
        Receiver::start_on(0)
    }

    pub fn url(&self, path: &str) -> String {
        format!("http://127.0.0.1:{}{path}", self.port)
    }

    pub fn answer(&self, status: u16) {
        self.status.store(status, Ordering::SeqCst);
    }

    pub fn received(&self) -> Vec<Received> {
        self.received.lock().unwrap().clone()
    }

    /// The requests it answered with a 2xx.
    pub fn taken(&self) -> Vec<Received> {
        self.received()
            .into_iter()
            .filter(|r| (200..300).contains(&r.answered))
            .collect()
    }

    /// Waits until `check` holds on what it took; panics after `limit` with `context()`.
    pub fn wait_taken(
        &self,
        limit: Duration,
        what: &str,
        check: impl Fn(&[Received]) -> bool,
        context: impl Fn() -> String,
    ) -> Vec<Received> {
        let start = Instant::now();
        loop {
            let taken = self.taken();
            if check(&taken) {
                return taken;
            }
            if start.elapsed() > limit {
                let got: Vec<String> = self
                    .received()
                    .iter()
                    .map(|r| format!("{} {}", r.answered, String::from_utf8_lossy(&r.body)))
                    .collect();
                panic!(
                    "timed out waiting for {what}; received:\n{}\n{}",
                    got.join("\n"),
                    context()
                );
            }
            std::thread::sleep(Duration::from_millis(100));
        }
    }
}

impl Drop for Receiver {
    fn drop(&mut self) {
        self.stop.store(true, Ordering::SeqCst);
    }
}

fn serve(
    stream: TcpStream,
    status: &AtomicU16,
    received: &Mutex<Vec<Received>>,
    stop: &AtomicBool,
) {
    stream.set_nonblocking(false).unwrap();
    stream
        .set_read_timeout(Some(Duration::from_secs(10)))
        .unwrap();
    let mut reader = BufReader::new(stream.try_clone().unwrap());
    let mut line = String::new();
    if reader.read_line(&mut line).unwrap_or(0) == 0 {
        return;
    }
    let mut parts = line.split_whitespace();
    let method = parts.next().unwrap_or("").to_string();
    let path = parts.next().unwrap_or("").to_string();
    let mut headers = Vec::new();
    loop {
        let mut h = String::new();
        if reader.read_line(&mut h).unwrap_or(0) == 0 {
            return;
        }
        let h = h.trim_end();
        if h.is_empty() {
            break;
        }
        if let Some((k, v)) = h.split_once(':') {
            headers.push((k.trim().to_ascii_lowercase(), v.trim().to_string()));
        }
    }
    let length: usize = headers
        .iter()
        .find(|(k, _)| k == "content-length")
        .and_then(|(_, v)| v.parse().ok())
        .unwrap_or(0);
    let mut body = vec![0; length];
    if reader.read_exact(&mut body).is_err() {
        return;
    }
    let answer = status.load(Ordering::SeqCst);
    received.lock().unwrap().push(Received {
        method,
        path,
        headers,
        body,
        answered: answer,
    });
    let mut stream = stream;
    if answer == 0 {
        // A black hole: the connection stays open, unanswered, until the test ends.
        while !stop.load(Ordering::SeqCst) {
            std::thread::sleep(Duration::from_millis(50));
        }
        return;
    }
    let text = format!("answered {answer}");
    let _ = write!(
        stream,
        "HTTP/1.1 {answer} X\r\nContent-Type: text/plain\r\nContent-Length: {}\r\nConnection: close\r\n\r\n{text}",
        text.len()
    );
    let _ = stream.flush();
}
