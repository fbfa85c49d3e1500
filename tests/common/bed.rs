//! The bed pictures of `tests/data/bed` (made by `scripts/make-bed-pictures`, described
//! in its `pictures.json`) and the bed check's answers on them: what the tests pin and
//! the `bedcheck` bench prints.

use crispen::bedcheck::{Reference, Region, Verdict};
use serde_json::Value;
use std::collections::BTreeMap;
use std::path::PathBuf;

pub fn dir() -> PathBuf {
    super::data_dir().join("bed")
}

/// `pictures.json`.
pub fn manifest() -> Value {
    serde_json::from_slice(&std::fs::read(dir().join("pictures.json")).unwrap()).unwrap()
}

pub fn read(file: &str) -> Vec<u8> {
    std::fs::read(dir().join(file)).unwrap_or_else(|e| panic!("{file}: {e}"))
}

fn region(v: &Value) -> Region {
    let n = |i: usize| v[i].as_u64().unwrap() as u32;
    Region {
        x: n(0),
        y: n(1),
        w: n(2),
        h: n(3),
    }
}

/// One picture of the set and the check's answer.
pub struct Case {
    pub file: String,
    /// What it shows: `empty`, `part`, `purge line`, `blob`, `spaghetti`.
    pub what: String,
    pub size_mm: Option<f64>,
    pub colour: Option<String>,
    pub light: String,
    /// Whether the bed is clear in it.
    pub clear: bool,
    pub verdict: Verdict,
}

/// Every picture of the set checked against its bed's reference.
pub fn check_all() -> Vec<Case> {
    let m = manifest();
    let region = region(&m["region"]);
    let bed_mm = [
        m["bed_mm"][0].as_f64().unwrap(),
        m["bed_mm"][1].as_f64().unwrap(),
    ];
    let mut references: BTreeMap<String, Reference> = BTreeMap::new();
    m["pictures"]
        .as_array()
        .unwrap()
        .iter()
        .map(|p| {
            let file = p["file"].as_str().unwrap().to_string();
            let reference_file = p["reference"].as_str().unwrap().to_string();
            let reference = references.entry(reference_file.clone()).or_insert_with(|| {
                Reference::prepare(&read(&reference_file), Some(region), Some(bed_mm)).unwrap()
            });
            let verdict = reference
                .check(&read(&file))
                .unwrap_or_else(|e| panic!("{file}: {e}"));
            Case {
                what: p["what"].as_str().unwrap().to_string(),
                size_mm: p["size_mm"].as_f64(),
                colour: p["colour"].as_str().map(str::to_string),
                light: p["light"].as_str().unwrap().to_string(),
                clear: p["clear"].as_bool().unwrap(),
                verdict,
                file,
            }
        })
        .collect()
}

/// The 1280 × 720 pair: the reference prepared, and the frame's bytes.
pub fn hd_pair() -> (Reference, Vec<u8>) {
    let m = manifest();
    let hd = &m["hd"];
    let reference = Reference::prepare(
        &read(hd["reference"].as_str().unwrap()),
        Some(region(&hd["region"])),
        Some([223.0, 223.0]),
    )
    .unwrap();
    (reference, read(hd["frame"].as_str().unwrap()))
}

/// The false "clear" and false "not clear" rates of `cases`, %: (false clear, of the
/// pictures with something on the bed; false not clear, of the empty ones).
pub fn rates(cases: &[Case]) -> (f64, f64) {
    let rate = |clear: bool| {
        let of: Vec<&Case> = cases.iter().filter(|c| c.clear == clear).collect();
        let wrong = of.iter().filter(|c| c.verdict.clear != clear).count();
        100.0 * wrong as f64 / of.len().max(1) as f64
    };
    (rate(false), rate(true))
}

/// A camera over each simulated printer's bed for the daemon's tests: it shows the empty
/// bed, or the bed with a part on it once the printer's record (`crispen sim`'s record of
/// what it executed) shows a print ended (`M117 printed`), until an eject sequence ran
/// (`M117 ejected`); a printer whose eject "fails" keeps showing its part. Each answer is
/// a different file (a comment with a counter), as a real camera's frames are. A camera
/// can be held: it answers nothing until let go ([`BedCamera::hold`]), so a test can act
/// while a check waits for it without racing the clock.
pub struct BedCamera {
    pub addr: String,
    cams: Arc<(Mutex<HashMap<String, Cam>>, Condvar)>,
    stop: Arc<AtomicBool>,
}

struct Cam {
    record: PathBuf,
    eject_removes: bool,
    held: bool,
    /// Parts a person took off by hand.
    removed: usize,
}

use std::collections::HashMap;
use std::io::{BufRead, BufReader, Write};
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::{Arc, Condvar, Mutex};

/// The pictures it shows: the empty bed (the one a reference is taken of, then one under
/// another light and a small shift), and a part on it.
pub const EMPTY: &str = "pei-reference.jpg";
pub const EMPTY_LATER: &str = "pei-02-empty-evening.jpg";
pub const PART: &str = "pei-30-part20mm-red.jpg";

impl BedCamera {
    pub fn start() -> BedCamera {
        let listener = std::net::TcpListener::bind("127.0.0.1:0").unwrap();
        let addr = listener.local_addr().unwrap().to_string();
        let cams: Arc<(Mutex<HashMap<String, Cam>>, Condvar)> = Default::default();
        let stop = Arc::new(AtomicBool::new(false));
        let pictures = Arc::new([read(EMPTY), read(EMPTY_LATER), read(PART)]);
        let counter = Arc::new(AtomicU64::new(0));
        {
            let (cams, stop) = (Arc::clone(&cams), Arc::clone(&stop));
            std::thread::spawn(move || {
                for conn in listener.incoming() {
                    if stop.load(Ordering::SeqCst) {
                        return;
                    }
                    let Ok(conn) = conn else { continue };
                    let (cams, pictures, counter) = (
                        Arc::clone(&cams),
                        Arc::clone(&pictures),
                        Arc::clone(&counter),
                    );
                    std::thread::spawn(move || serve_bed(conn, &cams, &pictures, &counter));
                }
            });
        }
        BedCamera { addr, cams, stop }
    }

    /// A printer's bed, followed from its simulator's `record`.
    pub fn add(&self, printer: &str, record: &std::path::Path, eject_removes: bool) {
        self.cams.0.lock().unwrap().insert(
            printer.to_string(),
            Cam {
                record: record.to_path_buf(),
                eject_removes,
                held: false,
                removed: 0,
            },
        );
    }

    /// Holds the printer's camera (`true`: each request waits, unanswered) or lets it go
    /// (the requests held are answered with the bed as it is then).
    pub fn hold(&self, printer: &str, held: bool) {
        if let Some(c) = self.cams.0.lock().unwrap().get_mut(printer) {
            c.held = held;
        }
        self.cams.1.notify_all();
    }

    /// A person took the part off the printer's bed by hand.
    pub fn person_cleared(&self, printer: &str) {
        if let Some(c) = self.cams.0.lock().unwrap().get_mut(printer) {
            c.removed += 1;
        }
    }

    pub fn url(&self, printer: &str) -> String {
        format!("http://{}/cam/{printer}/snapshot", self.addr)
    }
}

impl Drop for BedCamera {
    fn drop(&mut self) {
        self.stop.store(true, Ordering::SeqCst);
        if let Ok(mut cams) = self.cams.0.lock() {
            cams.values_mut().for_each(|c| c.held = false);
        }
        self.cams.1.notify_all();
        let _ = std::net::TcpStream::connect(&self.addr);
    }
}

/// Prints ended and ejects run on a printer, by its record.
pub fn prints_and_ejects(record: &std::path::Path) -> (usize, usize) {
    let text = std::fs::read_to_string(record).unwrap_or_default();
    let count = |what: &str| text.lines().filter(|l| l.starts_with(what)).count();
    (count("M117 printed"), count("M117 ejected"))
}

fn serve_bed(
    mut conn: std::net::TcpStream,
    cams: &(Mutex<HashMap<String, Cam>>, Condvar),
    pictures: &[Vec<u8>; 3],
    counter: &AtomicU64,
) {
    let mut reader = BufReader::new(conn.try_clone().unwrap());
    let mut request = String::new();
    if reader.read_line(&mut request).is_err() {
        return;
    }
    loop {
        let mut line = String::new();
        if reader.read_line(&mut line).unwrap_or(0) == 0 || line == "\r\n" || line == "\n" {
            break;
        }
    }
    let path = request.split_whitespace().nth(1).unwrap_or("/").to_string();
    let printer = path
        .strip_prefix("/cam/")
        .and_then(|p| p.strip_suffix("/snapshot"))
        .unwrap_or("");
    let (lock, let_go) = cams;
    let held = |c: &mut HashMap<String, Cam>| c.get(printer).is_some_and(|c| c.held);
    let cams = let_go.wait_while(lock.lock().unwrap(), held).unwrap();
    let (record, removes, removed) = match cams.get(printer) {
        Some(c) => (c.record.clone(), c.eject_removes, c.removed),
        None => {
            let _ = conn.write_all(
                b"HTTP/1.1 404 Not Found\r\nContent-Length: 0\r\nConnection: close\r\n\r\n",
            );
            return;
        }
    };
    drop(cams);
    let (printed, ejected) = prints_and_ejects(&record);
    let taken_off = removed + if removes { ejected } else { 0 };
    let on_bed = printed > taken_off;
    let picture = match (on_bed, printed) {
        (true, _) => &pictures[2],
        (false, 0) => &pictures[0],
        (false, _) => &pictures[1],
    };
    // A comment after the start of image: the same picture, another file.
    let n = counter.fetch_add(1, Ordering::SeqCst);
    let comment = format!("frame {n}");
    let mut jpeg = picture[..2].to_vec();
    jpeg.extend_from_slice(&[0xFF, 0xFE]);
    jpeg.extend_from_slice(&((comment.len() + 2) as u16).to_be_bytes());
    jpeg.extend_from_slice(comment.as_bytes());
    jpeg.extend_from_slice(&picture[2..]);
    let _ = write!(
        conn,
        "HTTP/1.1 200 OK\r\nContent-Type: image/jpeg\r\nContent-Length: {}\r\nConnection: close\r\n\r\n",
        jpeg.len()
    );
    let _ = conn.write_all(&jpeg);
}
