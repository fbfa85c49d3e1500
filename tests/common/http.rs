//! A plain HTTP/1.1 client for the tests: one request on its own connection, the bytes
//! written exactly as given (so a test can send what no well-behaved client would), the
//! answer read to its end. Nothing here interprets the answer beyond its framing.

use serde_json::Value;
use std::io::{BufRead, BufReader, Read, Write};
use std::net::TcpStream;
use std::os::unix::net::UnixStream;
use std::path::Path;
use std::time::Duration;

pub struct Answer {
    pub status: u16,
    /// The header lines as sent (a Location's token is case-sensitive).
    pub headers: String,
    pub body: Vec<u8>,
}

impl Answer {
    pub fn text(&self) -> String {
        String::from_utf8_lossy(&self.body).into_owned()
    }

    pub fn json(&self) -> Value {
        serde_json::from_slice(&self.body)
            .unwrap_or_else(|e| panic!("not JSON ({e}): {}", self.text()))
    }

    /// The JSON error message, asserting the body is `{"error": "..."}`.
    pub fn error(&self) -> String {
        self.json()["error"]
            .as_str()
            .unwrap_or_else(|| panic!("no error message in {}", self.text()))
            .to_string()
    }

    /// The value of header `name` (any case), trimmed.
    pub fn header(&self, name: &str) -> Option<String> {
        self.headers.lines().find_map(|l| {
            let (n, v) = l.split_once(':')?;
            n.eq_ignore_ascii_case(name).then(|| v.trim().to_string())
        })
    }
}

/// One request to `addr` with `headers` and a Content-Length for `body`.
pub fn request(
    addr: &str,
    method: &str,
    path: &str,
    headers: &[(&str, &str)],
    body: &[u8],
) -> Answer {
    let mut head = format!("{method} {path} HTTP/1.1\r\nHost: {addr}\r\nConnection: close\r\n");
    for (k, v) in headers {
        head.push_str(&format!("{k}: {v}\r\n"));
    }
    head.push_str(&format!("Content-Length: {}\r\n\r\n", body.len()));
    let mut bytes = head.into_bytes();
    bytes.extend_from_slice(body);
    raw(addr, &bytes)
}

/// Sends `bytes` to `addr` and reads the answer to the end (skipping a `100 Continue`).
pub fn raw(addr: &str, bytes: &[u8]) -> Answer {
    let stream = TcpStream::connect(addr).unwrap();
    stream
        .set_read_timeout(Some(Duration::from_secs(60)))
        .unwrap();
    exchange(stream, bytes)
}

/// One request on a daemon's control socket, which needs no key.
pub fn on_socket(socket: &Path, method: &str, path: &str) -> Answer {
    let stream = UnixStream::connect(socket).unwrap();
    stream
        .set_read_timeout(Some(Duration::from_secs(60)))
        .unwrap();
    let head = format!(
        "{method} {path} HTTP/1.1\r\nHost: localhost\r\nConnection: close\r\nContent-Length: 0\r\n\r\n"
    );
    exchange(stream, head.as_bytes())
}

/// Writes `bytes` on `stream` and reads one answer.
pub fn exchange(mut stream: impl Read + Write, bytes: &[u8]) -> Answer {
    // The server may answer (an error) before taking the whole body; that is fine.
    let _ = stream.write_all(bytes);
    let mut reader = BufReader::new(stream);
    loop {
        let mut status_line = String::new();
        reader.read_line(&mut status_line).unwrap();
        let status: u16 = status_line
            .split_whitespace()
            .nth(1)
            .unwrap_or_else(|| panic!("no status line: {status_line:?}"))
            .parse()
            .unwrap();
        let mut headers = String::new();
        loop {
            let mut line = String::new();
            reader.read_line(&mut line).unwrap();
            if line == "\r\n" || line.is_empty() {
                break;
            }
            headers.push_str(&line);
        }
        if status == 100 {
            continue;
        }
        let answer = Answer {
            status,
            headers,
            body: Vec::new(),
        };
        let mut body = Vec::new();
        if answer
            .header("transfer-encoding")
            .is_some_and(|v| v.eq_ignore_ascii_case("chunked"))
        {
            loop {
                let mut size = String::new();
                reader.read_line(&mut size).unwrap();
                let size = usize::from_str_radix(size.trim(), 16).unwrap();
                let mut chunk = vec![0; size + 2];
                reader.read_exact(&mut chunk).unwrap();
                if size == 0 {
                    break;
                }
                body.extend_from_slice(&chunk[..size]);
            }
        } else if let Some(length) = answer.header("content-length") {
            body.resize(length.parse().unwrap(), 0);
            reader.read_exact(&mut body).unwrap();
        } else {
            let _ = reader.read_to_end(&mut body);
        }
        return Answer { body, ..answer };
    }
}

/// Polls `status` (a daemon's `GET /api/v1/status`) until `check` holds on it; after
/// `limit`, panics naming `what`, with the last status and the daemon's `log`.
pub fn poll_status(
    limit: Duration,
    what: &str,
    log: &Path,
    status: impl Fn() -> Value,
    check: impl Fn(&Value) -> bool,
) -> Value {
    let started = std::time::Instant::now();
    loop {
        let s = status();
        if check(&s) {
            return s;
        }
        assert!(
            started.elapsed() < limit,
            "timed out waiting for {what}\nlast status: {s:#}\nlog:\n{}",
            std::fs::read_to_string(log).unwrap_or_default()
        );
        std::thread::sleep(Duration::from_millis(200));
    }
}
