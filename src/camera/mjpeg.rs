//! An MJPEG stream (`multipart/x-mixed-replace`, as ustreamer, mjpg-streamer, crowsnest and
//! ffmpeg serve it) read into frames: bytes in, parts out, no I/O. Each part is taken by
//! its `Content-Length` when it has one, else up to the next boundary; nothing grows past
//! the frame limit, so a stream that never sends a boundary is an error, not memory.
//!
//! A part is a frame only when it is a whole JPEG ([`check_jpeg`]: its segments from SOI
//! to EOI, nothing after but padding). Any other part (cut short by a `Content-Length`
//! shorter than the picture, running into the next part by one longer, cut at a boundary
//! inside the picture, headers that cannot be read) is refused ([`Part::Refused`], with
//! why) and the reader finds its place again at the next boundary, counted from the start
//! of the part refused, so the parts after it are read whole.

use serde::{Deserialize, Serialize};

/// Why a stream is given up.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum MjpegError {
    #[error("a frame larger than {} ([camera] frame_max_mb)", megabytes(*max))]
    TooLarge { max: usize },
    #[error("no boundary within {}", megabytes(*max))]
    NoBoundary { max: usize },
    #[error("a part that is not a JPEG ({what})")]
    NotJpeg { what: String },
    #[error("the stream ended (its closing boundary)")]
    Ended,
}

/// Why a part (or a snapshot) is not taken as a frame. Data, not words: the job page and
/// the status word it.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, thiserror::Error)]
#[serde(tag = "kind", rename_all = "snake_case")]
pub enum FrameFault {
    /// The part's headers are unreadable, or longer than [`MAX_HEADER_BYTES`].
    #[error("a part's headers are unreadable")]
    Headers,
    /// It does not start as a JPEG does (SOI, then a marker).
    #[error("a part of {bytes} bytes that is not a JPEG")]
    NotJpeg { bytes: usize },
    /// It ends before its end marker: the picture is cut.
    #[error("a frame cut short ({bytes} bytes, no end marker)")]
    Cut { bytes: usize },
    /// Something other than padding follows its end marker (a part that ran into the
    /// next one).
    #[error("a frame followed by {bytes} bytes of something else")]
    Trailing { bytes: usize },
    /// Its segments are not a JPEG's (a marker where data should be, no picture in it).
    #[error("a frame whose JPEG segments are malformed")]
    Malformed,
    /// Whole, but its picture does not decode.
    #[error("a frame whose picture does not decode")]
    Undecodable,
}

/// What a stream gives, part by part.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum Part {
    /// A whole JPEG, from SOI to EOI.
    Frame(Vec<u8>),
    Refused(FrameFault),
}

/// The most a part's headers may take.
pub const MAX_HEADER_BYTES: usize = 8192;

/// A size as the errors say it.
pub(crate) fn megabytes(bytes: usize) -> String {
    format!("{:.1} MB", bytes as f64 / (1024.0 * 1024.0))
}

#[derive(Debug)]
enum State {
    /// Looking for the next boundary line.
    Boundary,
    /// Reading a part's headers.
    Headers,
    /// Reading a part's body: its length when given.
    Body(Option<usize>),
    Ended,
}

/// What follows a boundary's text in the buffer.
enum AfterBoundary {
    /// More bytes are needed to say.
    Unknown,
    /// Not a boundary line (the text inside something else).
    No,
    /// A boundary line, this many bytes long from the boundary's start; closing or not.
    Line { len: usize, closing: bool },
}

/// Reads one stream. `boundary` is the `boundary=` of its content type (a leading `--`,
/// which some servers put there, is taken off).
#[derive(Debug)]
pub struct MjpegReader {
    /// `--boundary`.
    delimiter: Vec<u8>,
    buf: Vec<u8>,
    state: State,
    max_frame: usize,
    /// Bytes passed over while looking for a boundary.
    skipped: usize,
}

/// What a part's headers say, once they have come.
enum Headers {
    Incomplete,
    /// Unreadable, or too long.
    Bad,
    /// They end at `end`; the part's length when given.
    Read {
        end: usize,
        length: Option<usize>,
    },
}

/// The boundary of a `multipart/x-mixed-replace; boundary=...` content type.
pub fn boundary_of(content_type: &str) -> Option<String> {
    let (kind, params) = content_type.split_once(';')?;
    if !kind
        .trim()
        .eq_ignore_ascii_case("multipart/x-mixed-replace")
    {
        return None;
    }
    params.split(';').find_map(|p| {
        let (k, v) = p.split_once('=')?;
        k.trim()
            .eq_ignore_ascii_case("boundary")
            .then(|| v.trim().trim_matches('"').to_string())
            .filter(|b| !b.is_empty() && b.len() <= 200)
    })
}

impl MjpegReader {
    pub fn new(boundary: &str, max_frame: usize) -> MjpegReader {
        let bare = boundary.strip_prefix("--").unwrap_or(boundary);
        MjpegReader {
            delimiter: format!("--{bare}").into_bytes(),
            buf: Vec::new(),
            state: State::Boundary,
            max_frame,
            skipped: 0,
        }
    }

    /// Takes the next bytes of the stream; returns the parts they complete, in order.
    pub fn feed(&mut self, bytes: &[u8]) -> Result<Vec<Part>, MjpegError> {
        self.buf.extend_from_slice(bytes);
        let mut parts = Vec::new();
        loop {
            match self.state {
                State::Ended => return Err(MjpegError::Ended),
                State::Boundary => {
                    let Some(at) = find(&self.buf, &self.delimiter) else {
                        // Keep only what may be the start of a boundary.
                        let keep = self.delimiter.len();
                        if self.buf.len() > keep {
                            self.skipped += self.buf.len() - keep;
                            self.buf.drain(..self.buf.len() - keep);
                        }
                        if self.skipped > self.max_frame {
                            return Err(MjpegError::NoBoundary {
                                max: self.max_frame,
                            });
                        }
                        return Ok(parts);
                    };
                    if self.skipped + at > self.max_frame {
                        return Err(MjpegError::NoBoundary {
                            max: self.max_frame,
                        });
                    }
                    match self.after_boundary(at) {
                        AfterBoundary::Unknown => return Ok(parts),
                        AfterBoundary::No => {
                            self.skipped += at + 1;
                            self.buf.drain(..=at);
                        }
                        AfterBoundary::Line { len, closing } => {
                            self.skipped = 0;
                            self.buf.drain(..at + len);
                            self.state = if closing {
                                State::Ended
                            } else {
                                State::Headers
                            };
                        }
                    }
                }
                State::Headers => match self.headers()? {
                    Headers::Incomplete => return Ok(parts),
                    Headers::Bad => {
                        // Found again at the next boundary, looked for from here.
                        parts.push(Part::Refused(FrameFault::Headers));
                        self.state = State::Boundary;
                    }
                    Headers::Read { end, length } => {
                        if length.is_some_and(|n| n > self.max_frame) {
                            return Err(MjpegError::TooLarge {
                                max: self.max_frame,
                            });
                        }
                        self.buf.drain(..end);
                        self.state = State::Body(length);
                    }
                },
                State::Body(Some(n)) => {
                    if self.buf.len() < n {
                        return Ok(parts);
                    }
                    self.state = State::Boundary;
                    match check_jpeg(&self.buf[..n]) {
                        Ok(len) => {
                            parts.push(Part::Frame(self.buf[..len].to_vec()));
                            self.buf.drain(..n);
                        }
                        // Not what its length said: the next boundary is looked for from
                        // the part's start, so one inside it (a length too long) is found.
                        Err(fault) => parts.push(Part::Refused(fault)),
                    }
                }
                State::Body(None) => {
                    let Some(at) = self.body_end()? else {
                        return Ok(parts);
                    };
                    parts.push(match check_jpeg(&self.buf[..at]) {
                        Ok(len) => Part::Frame(self.buf[..len].to_vec()),
                        Err(fault) => Part::Refused(fault),
                    });
                    self.buf.drain(..at);
                    self.state = State::Boundary;
                }
            }
        }
    }

    /// Bytes held now (a partial frame, headers, what may be a boundary's start).
    pub fn buffered(&self) -> usize {
        self.buf.len()
    }

    /// Whether the boundary's text at `at` starts a boundary line: then `--` (the closing
    /// one), or blanks and the line's end.
    fn after_boundary(&self, at: usize) -> AfterBoundary {
        let start = at + self.delimiter.len();
        let rest = &self.buf[start..];
        if rest.starts_with(b"--") {
            return AfterBoundary::Line {
                len: self.delimiter.len() + 2,
                closing: true,
            };
        }
        if rest == b"-" {
            return AfterBoundary::Unknown;
        }
        let blanks = rest
            .iter()
            .take_while(|&&b| b == b' ' || b == b'\t')
            .count();
        if blanks > MAX_HEADER_BYTES {
            return AfterBoundary::No;
        }
        let line = |end: usize| AfterBoundary::Line {
            len: self.delimiter.len() + blanks + end,
            closing: false,
        };
        match &rest[blanks..] {
            [] | [b'\r'] => AfterBoundary::Unknown,
            [b'\r', b'\n', ..] => line(2),
            [b'\n', ..] => line(1),
            _ => AfterBoundary::No,
        }
    }

    /// Where a part without a length ends: before the CR LF of the next boundary line.
    /// None until it has come; an error when the part is longer than a frame may be,
    /// whether or not its end has come (the same for any reads).
    fn body_end(&self) -> Result<Option<usize>, MjpegError> {
        let mut marker = b"\r\n".to_vec();
        marker.extend_from_slice(&self.delimiter);
        let too_large = Err(MjpegError::TooLarge {
            max: self.max_frame,
        });
        let mut from = 0;
        while let Some(found) = find(&self.buf[from..], &marker) {
            let at = from + found;
            if at > self.max_frame {
                return too_large;
            }
            match self.after_boundary(at + 2) {
                AfterBoundary::Unknown => return Ok(None),
                AfterBoundary::No => from = at + 1,
                AfterBoundary::Line { .. } => return Ok(Some(at)),
            }
        }
        if self.buf.len() > self.max_frame + marker.len() {
            return too_large;
        }
        Ok(None)
    }

    /// The part's headers at the front of the buffer, once they have all come; checks
    /// the part's type.
    fn headers(&self) -> Result<Headers, MjpegError> {
        let mut at = 0;
        let mut length = None;
        loop {
            let Some(eol) = self.buf[at..].iter().position(|&b| b == b'\n') else {
                if self.buf.len() > MAX_HEADER_BYTES {
                    return Ok(Headers::Bad);
                }
                return Ok(Headers::Incomplete);
            };
            let line = &self.buf[at..at + eol];
            at += eol + 1;
            if at > MAX_HEADER_BYTES {
                return Ok(Headers::Bad);
            }
            let Ok(line) = std::str::from_utf8(line) else {
                return Ok(Headers::Bad);
            };
            let line = line.trim_end_matches('\r');
            if line.is_empty() {
                return Ok(Headers::Read { end: at, length });
            }
            let Some((name, value)) = line.split_once(':') else {
                return Ok(Headers::Bad);
            };
            let value = value.trim();
            if name.trim().eq_ignore_ascii_case("content-length") {
                let Ok(n) = value.parse() else {
                    return Ok(Headers::Bad);
                };
                length = Some(n);
            } else if name.trim().eq_ignore_ascii_case("content-type")
                && !value.to_ascii_lowercase().starts_with("image/j")
            {
                return Err(MjpegError::NotJpeg {
                    what: format!(
                        "Content-Type {}",
                        value.chars().take(60).collect::<String>()
                    ),
                });
            }
        }
    }
}

/// Whether `bytes` are one whole JPEG: SOI, its segments each as long as it says, a frame
/// header and at least one scan, the scans' data up to the next marker, and EOI; after it
/// only padding (blanks, line ends, NULs, which some cameras add inside the part). The
/// length up to the end of EOI when so. Reads the markers only, never the picture (see
/// [`decodes`](super::picture::decodes) for that).
pub fn check_jpeg(bytes: &[u8]) -> Result<usize, FrameFault> {
    if !is_jpeg(bytes) {
        return Err(FrameFault::NotJpeg { bytes: bytes.len() });
    }
    let cut = Err(FrameFault::Cut { bytes: bytes.len() });
    let (mut at, mut frame_header, mut scans) = (2, false, 0);
    loop {
        // A marker: 0xFF (more of them are fill), then its code.
        if bytes.get(at) != Some(&0xFF) {
            return if at >= bytes.len() {
                cut
            } else {
                Err(FrameFault::Malformed)
            };
        }
        while bytes.get(at) == Some(&0xFF) {
            at += 1;
        }
        let Some(&code) = bytes.get(at) else {
            return cut;
        };
        at += 1;
        match code {
            0xD9 => {
                if !(frame_header && scans > 0) {
                    return Err(FrameFault::Malformed);
                }
                let padding = bytes[at..]
                    .iter()
                    .all(|b| matches!(b, b'\r' | b'\n' | b' ' | b'\t' | 0));
                return if padding {
                    Ok(at)
                } else {
                    Err(FrameFault::Trailing {
                        bytes: bytes.len() - at,
                    })
                };
            }
            // Markers without a segment (TEM, RSTn).
            0x01 | 0xD0..=0xD7 => {}
            0x00 | 0xD8 => return Err(FrameFault::Malformed),
            _ => {
                let Some(len) = bytes.get(at..at + 2) else {
                    return cut;
                };
                let len = usize::from(u16::from_be_bytes([len[0], len[1]]));
                if len < 2 {
                    return Err(FrameFault::Malformed);
                }
                if at + len > bytes.len() {
                    return cut;
                }
                at += len;
                // SOF0..SOF15 but DHT (C4), JPG (C8) and DAC (CC).
                if matches!(code, 0xC0..=0xCF) && !matches!(code, 0xC4 | 0xC8 | 0xCC) {
                    frame_header = true;
                }
                if code == 0xDA {
                    if !frame_header {
                        return Err(FrameFault::Malformed);
                    }
                    scans += 1;
                    // The scan's data: up to the first 0xFF that is neither a stuffed byte
                    // (FF 00), a restart marker nor fill.
                    loop {
                        let Some(ff) = memchr::memchr(0xFF, &bytes[at..]) else {
                            return cut;
                        };
                        at += ff;
                        match bytes.get(at + 1) {
                            None => return cut,
                            Some(0x00 | 0xD0..=0xD7) => at += 2,
                            Some(0xFF) => at += 1,
                            Some(_) => break,
                        }
                    }
                }
            }
        }
    }
}

/// Whether bytes start as a JPEG file does.
pub fn is_jpeg(bytes: &[u8]) -> bool {
    bytes.len() > 3 && bytes[0] == 0xFF && bytes[1] == 0xD8 && bytes[2] == 0xFF
}

fn find(haystack: &[u8], needle: &[u8]) -> Option<usize> {
    memchr::memmem::find(haystack, needle)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn part(body: &[u8], length: Option<usize>) -> Vec<u8> {
        let mut p = b"--frame\r\nContent-Type: image/jpeg\r\n".to_vec();
        if let Some(n) = length {
            p.extend_from_slice(format!("Content-Length: {n}\r\n").as_bytes());
        }
        p.extend_from_slice(b"\r\n");
        p.extend_from_slice(body);
        p.extend_from_slice(b"\r\n");
        p
    }

    /// A JPEG's segments around `data` (in an APP0 segment) and `scan` (the entropy-coded
    /// data, stuffed where it needs to be): enough for the markers' reading, not a picture.
    fn jpeg_with(data: &[u8], scan: &[u8]) -> Vec<u8> {
        let mut f = vec![0xFF, 0xD8];
        let segment = |f: &mut Vec<u8>, code: u8, body: &[u8]| {
            f.extend_from_slice(&[0xFF, code]);
            f.extend_from_slice(&(body.len() as u16 + 2).to_be_bytes());
            f.extend_from_slice(body);
        };
        segment(&mut f, 0xE0, data);
        segment(&mut f, 0xC0, &[8, 0, 8, 0, 8, 1, 1, 0x11, 0]);
        segment(&mut f, 0xDA, &[1, 1, 0, 0, 63, 0]);
        for &b in scan {
            f.push(b);
            if b == 0xFF {
                f.push(0);
            }
        }
        f.extend_from_slice(&[0xFF, 0xD0, 0x12, 0xFF, 0xD9]);
        f
    }

    fn frames() -> Vec<Vec<u8>> {
        (0..3u8)
            .map(|i| {
                // Bytes a boundary search must not trip on: "--fram" and CR LF; a marker's
                // 0xFF in the scan, stuffed.
                let scan: Vec<u8> = std::iter::repeat_n(i, 50 + i as usize)
                    .chain([0xFF, 0x10])
                    .collect();
                jpeg_with(b"\r\n--fram", &scan)
            })
            .collect()
    }

    /// The parts read from `stream` in every split into two reads, and byte by byte: the
    /// same each time (asserted), returned once.
    fn read_any_way(stream: &[u8], max: usize) -> Vec<Part> {
        let whole = MjpegReader::new("frame", max).feed(stream).unwrap();
        for split in 0..=stream.len() {
            let mut r = MjpegReader::new("frame", max);
            let mut got = r.feed(&stream[..split]).unwrap();
            got.extend(r.feed(&stream[split..]).unwrap());
            assert_eq!(got, whole, "split at {split}");
        }
        let mut r = MjpegReader::new("--frame", max);
        let got: Vec<Part> = stream.iter().flat_map(|b| r.feed(&[*b]).unwrap()).collect();
        assert_eq!(got, whole, "byte by byte");
        whole
    }

    fn whole_frames(frames: &[Vec<u8>]) -> Vec<Part> {
        frames.iter().cloned().map(Part::Frame).collect()
    }

    /// Every split of the stream into two reads gives the same frames, with and without
    /// lengths, and with a preamble before the first boundary.
    #[test]
    fn frames_come_whole_whatever_the_reads() {
        for with_length in [true, false] {
            let mut stream = b"preamble \r\n".to_vec();
            for f in frames() {
                stream.extend(part(&f, with_length.then_some(f.len())));
            }
            // A last boundary, so the last frame without a length is known to be complete.
            stream.extend_from_slice(b"--frame\r\n");
            assert_eq!(read_any_way(&stream, 1000), whole_frames(&frames()));
        }
    }

    /// A part whose length is shorter than its JPEG is refused as cut, one whose length
    /// runs into the next part is refused for what follows its end, and in both cases
    /// the reader finds the next boundary: the parts after are read whole.
    #[test]
    fn a_part_whose_length_lies_is_refused_and_the_next_is_read() {
        let f = frames();
        for (lie, fault) in [
            (
                -1,
                FrameFault::Cut {
                    bytes: f[1].len() - 1,
                },
            ),
            (
                -(f[1].len() as isize) / 2,
                FrameFault::Cut {
                    bytes: f[1].len() - f[1].len() / 2,
                },
            ),
            (12, FrameFault::Trailing { bytes: 12 }),
            (40, FrameFault::Trailing { bytes: 40 }),
        ] {
            let mut stream = part(&f[0], Some(f[0].len()));
            stream.extend(part(&f[1], Some((f[1].len() as isize + lie) as usize)));
            stream.extend(part(&f[2], Some(f[2].len())));
            stream.extend(part(&f[0], Some(f[0].len())));
            assert_eq!(
                read_any_way(&stream, 1000),
                [
                    Part::Frame(f[0].clone()),
                    Part::Refused(fault),
                    Part::Frame(f[2].clone()),
                    Part::Frame(f[0].clone()),
                ],
                "length off by {lie}"
            );
        }
        // A length that counts the part's line end, or padding a camera adds inside it, is
        // no lie: the frame is its JPEG.
        for padding in [&b"\r\n"[..], b"\0\0\0\0", b"  \r\n"] {
            let mut body = f[1].clone();
            body.extend_from_slice(padding);
            let stream = [part(&body, Some(body.len())), part(&f[2], Some(f[2].len()))].concat();
            assert_eq!(read_any_way(&stream, 1000), whole_frames(&f[1..]));
        }
    }

    /// Garbage between parts is passed over; a part whose headers cannot be read is
    /// refused and the next boundary found.
    #[test]
    fn garbage_between_parts_and_bad_headers_are_passed_over() {
        let f = frames();
        let mut stream = part(&f[0], Some(f[0].len()));
        stream.extend_from_slice(b"some junk\r\n\x00\x01 --fra\r\n");
        stream.extend(part(&f[1], None));
        stream.extend_from_slice(b"--frame\r\nno colon here\r\n\r\n\xff\xd8\xff\r\n");
        stream.extend_from_slice(b"--frame\r\nContent-Length: twelve\r\n\r\nabc\r\n");
        stream.extend_from_slice(b"--frame\r\n\xff\xfe: x\r\n\r\n\r\n");
        stream.extend(part(&f[2], Some(f[2].len())));
        assert_eq!(
            read_any_way(&stream, 1000),
            [
                Part::Frame(f[0].clone()),
                Part::Frame(f[1].clone()),
                Part::Refused(FrameFault::Headers),
                Part::Refused(FrameFault::Headers),
                Part::Refused(FrameFault::Headers),
                Part::Frame(f[2].clone()),
            ]
        );
    }

    /// The boundary's text inside a JPEG: harmless with a length; without one, a whole
    /// boundary line there cuts the part (refused) and the reader goes on at the next
    /// boundary; the text without a line's end after it is no boundary.
    #[test]
    fn a_boundary_inside_the_jpeg() {
        let f = frames();
        let inside = jpeg_with(
            b"x\r\n--frame\r\nContent-Type: image/jpeg\r\n\r\ny",
            &[7; 20],
        );
        let lookalike = jpeg_with(b"\r\n--frame2\r\n\r\n--framed", &[7; 20]);
        let mut stream = part(&inside, Some(inside.len()));
        stream.extend(part(&lookalike, None));
        stream.extend(part(&f[0], None));
        stream.extend(part(&inside, None));
        stream.extend(part(&f[1], Some(f[1].len())));
        let parts = read_any_way(&stream, 1000);
        assert_eq!(
            parts[..3],
            [
                Part::Frame(inside.clone()),
                Part::Frame(lookalike),
                Part::Frame(f[0].clone())
            ]
        );
        // The cut one is refused, and what followed the boundary inside it too; the next
        // part is whole.
        assert_eq!(parts[3], Part::Refused(FrameFault::Cut { bytes: 7 }));
        assert_eq!(parts.last(), Some(&Part::Frame(f[1].clone())));
        assert!(
            parts[4..parts.len() - 1]
                .iter()
                .all(|p| matches!(p, Part::Refused(_))),
            "{parts:?}"
        );
    }

    #[test]
    fn a_whole_jpeg_is_read_by_its_markers() {
        let f = &frames()[0];
        assert_eq!(check_jpeg(f), Ok(f.len()));
        // Cut anywhere before its end marker's last byte.
        for n in 4..f.len() {
            assert!(
                matches!(check_jpeg(&f[..n]), Err(FrameFault::Cut { .. })),
                "cut at {n}: {:?}",
                check_jpeg(&f[..n])
            );
        }
        for n in 0..4 {
            assert_eq!(check_jpeg(&f[..n]), Err(FrameFault::NotJpeg { bytes: n }));
        }
        // A thumbnail's end marker inside a segment is not the frame's end.
        let thumb = jpeg_with(&[0xFF, 0xD8, 0xFF, 0xD9], &[1, 2, 3]);
        let cut_after_thumb = thumb.iter().position(|&b| b == 0xD9).unwrap() + 1;
        assert!(matches!(
            check_jpeg(&thumb[..cut_after_thumb]),
            Err(FrameFault::Cut { .. })
        ));
        assert_eq!(check_jpeg(&thumb), Ok(thumb.len()));
        // No scan, no frame header, a marker in a segment's place.
        assert_eq!(
            check_jpeg(&[0xFF, 0xD8, 0xFF, 0xD9]),
            Err(FrameFault::Malformed)
        );
        let mut no_header = f.clone();
        let sof = no_header
            .windows(2)
            .position(|w| w == [0xFF, 0xC0])
            .unwrap();
        no_header[sof + 1] = 0xE1;
        assert_eq!(check_jpeg(&no_header), Err(FrameFault::Malformed));
        assert_eq!(
            check_jpeg(&[0xFF, 0xD8, 0xFF, 0xE0, 0, 2, 0x12]),
            Err(FrameFault::Malformed)
        );
        let mut trailing = f.clone();
        trailing.extend_from_slice(b"\r\n--frame");
        assert_eq!(
            check_jpeg(&trailing),
            Err(FrameFault::Trailing { bytes: 9 })
        );
    }

    #[test]
    fn a_stream_without_boundaries_or_with_other_parts_is_refused() {
        let mut r = MjpegReader::new("frame", 10_000);
        // No boundary at all: what is kept stays small, and past a frame's size it is an
        // error.
        for _ in 0..10 {
            assert!(r.feed(&[0u8; 1000]).unwrap().is_empty());
            assert!(r.buf.len() <= 16);
        }
        assert_eq!(
            r.feed(&[0u8; 1000]),
            Err(MjpegError::NoBoundary { max: 10_000 })
        );
        // A part that never ends.
        let mut r = MjpegReader::new("frame", 100);
        r.feed(b"--frame\r\n\r\n\xff\xd8\xff").unwrap();
        assert_eq!(r.feed(&[1u8; 200]), Err(MjpegError::TooLarge { max: 100 }));
        // Too long by its own header.
        let mut r = MjpegReader::new("frame", 100);
        assert_eq!(
            r.feed(b"--frame\r\nContent-Length: 101\r\n\r\n"),
            Err(MjpegError::TooLarge { max: 100 })
        );
        // HTML where a picture should be.
        let mut r = MjpegReader::new("frame", 100);
        assert!(matches!(
            r.feed(b"--frame\r\nContent-Type: text/html\r\n\r\n<html>"),
            Err(MjpegError::NotJpeg { .. })
        ));
        let mut r = MjpegReader::new("frame", 100);
        assert_eq!(
            r.feed(b"--frame\r\nContent-Length: 6\r\n\r\n<html>"),
            Ok(vec![Part::Refused(FrameFault::NotJpeg { bytes: 6 })])
        );
        // Headers that never end: refused, and the search for a boundary goes on.
        let mut r = MjpegReader::new("frame", 100_000);
        r.feed(b"--frame\r\n").unwrap();
        assert_eq!(
            r.feed(&[b'a'; 9000]),
            Ok(vec![Part::Refused(FrameFault::Headers)])
        );
        assert!(r.buf.len() <= 16);
        // The closing boundary.
        let mut r = MjpegReader::new("frame", 100);
        assert_eq!(r.feed(b"--frame--\r\n"), Err(MjpegError::Ended));
    }

    #[test]
    fn boundaries_are_read_from_the_content_type() {
        for (ct, b) in [
            ("multipart/x-mixed-replace;boundary=ffmpeg", Some("ffmpeg")),
            (
                "multipart/x-mixed-replace; boundary=\"boundarydonotcross\"",
                Some("boundarydonotcross"),
            ),
            (
                "Multipart/X-Mixed-Replace; charset=x; Boundary=--b",
                Some("--b"),
            ),
            ("image/jpeg", None),
            ("multipart/x-mixed-replace", None),
            ("multipart/x-mixed-replace; boundary=", None),
        ] {
            assert_eq!(boundary_of(ct).as_deref(), b, "{ct}");
        }
    }
}
