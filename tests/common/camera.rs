//! A camera server for the tests: ffmpeg's moving test pattern (`testsrc2`, a clock and a
//! moving gradient) encoded to JPEG frames by ffmpeg itself, served on 127.0.0.1 the ways
//! camera servers publish them: `/snapshot` (one JPEG, as ustreamer's) and `/stream` (an
//! MJPEG stream, `multipart/x-mixed-replace`). And the ways a camera goes wrong: `/hang`
//! (reads the request, never answers), `/html` (an error page), `/huge` (a 50 MB "JPEG"),
//! `/noboundary` (a stream that never sends a boundary), and streams whose parts declare a
//! `Content-Length` shorter than the JPEG they carry: `/cut` every part, `/sometimes-cut`
//! every other one (the whole JPEG is sent all the same, as such cameras do).

use super::daemon::Killed;
use std::io::{BufRead, BufReader, Read, Write};
use std::net::{TcpListener, TcpStream};
use std::process::{Command, Stdio};
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, Mutex};
use std::time::Duration;

/// Frame size of the pattern.
pub const WIDTH: u32 = 320;
pub const HEIGHT: u32 = 240;

/// ffmpeg making the moving pattern at `fps`, in real time; the output is the caller's.
pub fn pattern(fps: u32) -> Command {
    let mut c = Command::new("ffmpeg");
    c.args(["-hide_banner", "-loglevel", "error", "-nostdin", "-re"])
        .args(["-f", "lavfi", "-i"])
        .arg(format!("testsrc2=size={WIDTH}x{HEIGHT}:rate={fps}"));
    c
}

pub struct TestCamera {
    pub addr: String,
    latest: Arc<Mutex<(u64, Vec<u8>)>>,
    stop: Arc<AtomicBool>,
    _ffmpeg: Killed,
}

impl TestCamera {
    /// ffmpeg at `fps` frames a second, and the server in front of it.
    pub fn start(fps: u32) -> TestCamera {
        let mut ffmpeg = pattern(fps)
            .args(["-f", "image2pipe", "-c:v", "mjpeg", "-q:v", "5", "pipe:1"])
            .stdin(Stdio::null())
            .stdout(Stdio::piped())
            .stderr(Stdio::inherit())
            .spawn()
            .expect("ffmpeg (Debian's package; scripts/setup installs it)");
        let mut out = ffmpeg.stdout.take().unwrap();
        let latest = Arc::new(Mutex::new((0u64, Vec::new())));
        let stop = Arc::new(AtomicBool::new(false));
        {
            let latest = Arc::clone(&latest);
            std::thread::spawn(move || {
                // ffmpeg's frames end with EOI (FF D9), which nothing inside a frame is.
                let mut buf = Vec::new();
                let mut chunk = [0u8; 65536];
                while let Ok(n) = out.read(&mut chunk) {
                    if n == 0 {
                        return;
                    }
                    buf.extend_from_slice(&chunk[..n]);
                    while let Some(end) = buf.windows(2).position(|w| w == [0xFF, 0xD9]) {
                        let frame: Vec<u8> = buf.drain(..end + 2).collect();
                        let mut l = latest.lock().unwrap();
                        l.0 += 1;
                        l.1 = frame;
                    }
                }
            });
        }
        let listener = TcpListener::bind("127.0.0.1:0").unwrap();
        let addr = listener.local_addr().unwrap().to_string();
        {
            let (latest, stop) = (Arc::clone(&latest), Arc::clone(&stop));
            std::thread::spawn(move || {
                for conn in listener.incoming() {
                    if stop.load(Ordering::SeqCst) {
                        return;
                    }
                    let Ok(conn) = conn else { continue };
                    let (latest, stop) = (Arc::clone(&latest), Arc::clone(&stop));
                    std::thread::spawn(move || serve(conn, &latest, &stop));
                }
            });
        }
        let camera = TestCamera {
            addr,
            latest,
            stop,
            _ffmpeg: Killed(ffmpeg),
        };
        let started = std::time::Instant::now();
        while camera.latest.lock().unwrap().0 == 0 {
            assert!(
                started.elapsed() < Duration::from_secs(20),
                "ffmpeg gave no frame"
            );
            std::thread::sleep(Duration::from_millis(20));
        }
        camera
    }

    pub fn url(&self, path: &str) -> String {
        format!("http://{}{path}", self.addr)
    }
}

impl Drop for TestCamera {
    fn drop(&mut self) {
        self.stop.store(true, Ordering::SeqCst);
        let _ = TcpStream::connect(&self.addr);
    }
}

fn serve(mut conn: TcpStream, latest: &Mutex<(u64, Vec<u8>)>, stop: &AtomicBool) {
    let mut reader = BufReader::new(conn.try_clone().unwrap());
    let mut request = String::new();
    if reader.read_line(&mut request).is_err() {
        return;
    }
    // The rest of the head.
    loop {
        let mut line = String::new();
        if reader.read_line(&mut line).unwrap_or(0) == 0 || line == "\r\n" || line == "\n" {
            break;
        }
    }
    let path = request.split_whitespace().nth(1).unwrap_or("/").to_string();
    let frame = || latest.lock().unwrap().clone();
    match path.as_str() {
        "/snapshot" => {
            let (_, jpeg) = frame();
            let _ = write!(
                conn,
                "HTTP/1.1 200 OK\r\nContent-Type: image/jpeg\r\nContent-Length: {}\r\nConnection: close\r\n\r\n",
                jpeg.len()
            );
            let _ = conn.write_all(&jpeg);
        }
        "/stream" => stream(conn, latest, stop, |_| false),
        "/cut" => stream(conn, latest, stop, |_| true),
        "/sometimes-cut" => stream(conn, latest, stop, |seq| seq % 2 == 0),
        "/hang" => {
            while !stop.load(Ordering::SeqCst) {
                std::thread::sleep(Duration::from_millis(100));
            }
        }
        "/html" => {
            let body = "<html><body>camera not configured</body></html>";
            let _ = write!(
                conn,
                "HTTP/1.1 200 OK\r\nContent-Type: text/html\r\nContent-Length: {}\r\nConnection: close\r\n\r\n{body}",
                body.len()
            );
        }
        "/huge" => {
            let len = 50 << 20;
            let _ = write!(
                conn,
                "HTTP/1.1 200 OK\r\nContent-Type: image/jpeg\r\nContent-Length: {len}\r\nConnection: close\r\n\r\n"
            );
            let mut chunk = vec![0u8; 65536];
            chunk[..3].copy_from_slice(&[0xFF, 0xD8, 0xFF]);
            for _ in 0..(len / chunk.len()) {
                if stop.load(Ordering::SeqCst) || conn.write_all(&chunk).is_err() {
                    return;
                }
                chunk[..3].fill(0);
            }
        }
        "/noboundary" => {
            let _ = conn.write_all(
                b"HTTP/1.1 200 OK\r\nContent-Type: multipart/x-mixed-replace;boundary=never\r\nConnection: close\r\n\r\n",
            );
            let chunk = vec![0x55u8; 65536];
            while !stop.load(Ordering::SeqCst) && conn.write_all(&chunk).is_ok() {}
        }
        _ => {
            let _ = conn.write_all(
                b"HTTP/1.1 404 Not Found\r\nContent-Length: 0\r\nConnection: close\r\n\r\n",
            );
        }
    }
}

/// Serves the frames as an MJPEG stream, each part's `Content-Length` two thirds of its
/// JPEG where `lie(frame number)`.
fn stream(
    mut conn: TcpStream,
    latest: &Mutex<(u64, Vec<u8>)>,
    stop: &AtomicBool,
    lie: fn(u64) -> bool,
) {
    if conn
        .write_all(b"HTTP/1.1 200 OK\r\nContent-Type: multipart/x-mixed-replace;boundary=testframe\r\nConnection: close\r\n\r\n")
        .is_err()
    {
        return;
    }
    let mut sent = 0;
    while !stop.load(Ordering::SeqCst) {
        let (seq, jpeg) = latest.lock().unwrap().clone();
        if seq != sent {
            sent = seq;
            let length = if lie(seq) {
                jpeg.len() * 2 / 3
            } else {
                jpeg.len()
            };
            let head = format!(
                "--testframe\r\nContent-Type: image/jpeg\r\nContent-Length: {length}\r\n\r\n"
            );
            if conn.write_all(head.as_bytes()).is_err()
                || conn.write_all(&jpeg).is_err()
                || conn.write_all(b"\r\n").is_err()
            {
                return;
            }
        }
        std::thread::sleep(Duration::from_millis(20));
    }
}
