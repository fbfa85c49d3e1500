//! An MJPEG stream (`multipart/x-mixed-replace`, as ustreamer, mjpg-streamer, crowsnest and
//! ffmpeg serve it) read into frames: bytes in, JPEG frames out, no I/O. Each part is taken
//! by its `Content-Length` when it has one, else up to the next boundary; nothing grows
//! past the frame limit, so a stream that never sends a boundary is an error, not memory.

/// Why a stream is given up.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum MjpegError {
    #[error("a frame larger than {} ([camera] frame_max_mb)", megabytes(*max))]
    TooLarge { max: usize },
    #[error("no boundary within {}", megabytes(*max))]
    NoBoundary { max: usize },
    #[error("a part that is not a JPEG ({what})")]
    NotJpeg { what: String },
    #[error("a part's headers are unreadable or longer than {MAX_HEADER_BYTES} bytes")]
    BadHeaders,
    #[error("the stream ended (its closing boundary)")]
    Ended,
}

const MAX_HEADER_BYTES: usize = 8192;

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

    /// Takes the next bytes of the stream; returns the frames they complete, in order.
    pub fn feed(&mut self, bytes: &[u8]) -> Result<Vec<Vec<u8>>, MjpegError> {
        self.buf.extend_from_slice(bytes);
        let mut frames = Vec::new();
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
                        return Ok(frames);
                    };
                    if self.skipped + at > self.max_frame {
                        return Err(MjpegError::NoBoundary {
                            max: self.max_frame,
                        });
                    }
                    self.skipped = 0;
                    let after = at + self.delimiter.len();
                    let Some(eol) = self.buf[after..].iter().position(|&b| b == b'\n') else {
                        if self.buf.len() - after > MAX_HEADER_BYTES {
                            return Err(MjpegError::BadHeaders);
                        }
                        return Ok(frames);
                    };
                    let closing = self.buf[after..].starts_with(b"--");
                    self.buf.drain(..after + eol + 1);
                    self.state = if closing {
                        State::Ended
                    } else {
                        State::Headers
                    };
                }
                State::Headers => {
                    let Some((end, length)) = self.headers()? else {
                        return Ok(frames);
                    };
                    self.buf.drain(..end);
                    if length.is_some_and(|n| n > self.max_frame) {
                        return Err(MjpegError::TooLarge {
                            max: self.max_frame,
                        });
                    }
                    self.state = State::Body(length);
                }
                State::Body(Some(n)) => {
                    if self.buf.len() < n {
                        return Ok(frames);
                    }
                    let frame: Vec<u8> = self.buf.drain(..n).collect();
                    frames.push(jpeg(frame)?);
                    self.state = State::Boundary;
                }
                State::Body(None) => {
                    let mut end_marker = b"\r\n".to_vec();
                    end_marker.extend_from_slice(&self.delimiter);
                    let found = find(&self.buf, &end_marker);
                    // Too long whether or not its end has come: the same for any reads.
                    let too_long = match found {
                        Some(at) => at > self.max_frame,
                        None => self.buf.len() > self.max_frame + end_marker.len(),
                    };
                    if too_long {
                        return Err(MjpegError::TooLarge {
                            max: self.max_frame,
                        });
                    }
                    let Some(at) = found else {
                        return Ok(frames);
                    };
                    let frame: Vec<u8> = self.buf.drain(..at).collect();
                    frames.push(jpeg(frame)?);
                    self.state = State::Boundary;
                }
            }
        }
    }

    /// Bytes held now (a partial frame, headers, what may be a boundary's start).
    pub fn buffered(&self) -> usize {
        self.buf.len()
    }

    /// The end of the headers at the front of the buffer and the part's length, once they
    /// have all come; checks the part's type.
    fn headers(&self) -> Result<Option<(usize, Option<usize>)>, MjpegError> {
        let mut at = 0;
        let mut length = None;
        loop {
            let Some(eol) = self.buf[at..].iter().position(|&b| b == b'\n') else {
                if self.buf.len() > MAX_HEADER_BYTES {
                    return Err(MjpegError::BadHeaders);
                }
                return Ok(None);
            };
            let line = &self.buf[at..at + eol];
            at += eol + 1;
            if at > MAX_HEADER_BYTES {
                return Err(MjpegError::BadHeaders);
            }
            let line = std::str::from_utf8(line)
                .map_err(|_| MjpegError::BadHeaders)?
                .trim_end_matches('\r');
            if line.is_empty() {
                return Ok(Some((at, length)));
            }
            let Some((name, value)) = line.split_once(':') else {
                return Err(MjpegError::BadHeaders);
            };
            let value = value.trim();
            if name.trim().eq_ignore_ascii_case("content-length") {
                length = Some(value.parse().map_err(|_| MjpegError::BadHeaders)?);
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

/// A frame that starts as a JPEG does (SOI, then a marker).
fn jpeg(frame: Vec<u8>) -> Result<Vec<u8>, MjpegError> {
    if is_jpeg(&frame) {
        Ok(frame)
    } else {
        Err(MjpegError::NotJpeg {
            what: format!(
                "{} bytes starting {:02x?}",
                frame.len(),
                &frame[..frame.len().min(4)]
            ),
        })
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

    fn part(body: &[u8], with_length: bool) -> Vec<u8> {
        let mut p = b"--frame\r\nContent-Type: image/jpeg\r\n".to_vec();
        if with_length {
            p.extend_from_slice(format!("Content-Length: {}\r\n", body.len()).as_bytes());
        }
        p.extend_from_slice(b"\r\n");
        p.extend_from_slice(body);
        p.extend_from_slice(b"\r\n");
        p
    }

    fn frames() -> Vec<Vec<u8>> {
        (0..3u8)
            .map(|i| {
                let mut f = vec![0xFF, 0xD8, 0xFF, 0xE0];
                // Bytes a boundary search must not trip on: "--fram" and CR LF.
                f.extend_from_slice(b"\r\n--fram");
                f.extend(std::iter::repeat_n(i, 50 + i as usize));
                f.extend_from_slice(&[0xFF, 0xD9]);
                f
            })
            .collect()
    }

    /// Every split of the stream into two reads gives the same frames, with and without
    /// lengths, and with a preamble before the first boundary.
    #[test]
    fn frames_come_whole_whatever_the_reads() {
        for with_length in [true, false] {
            let mut stream = b"preamble \r\n".to_vec();
            for f in frames() {
                stream.extend(part(&f, with_length));
            }
            // A last boundary, so the last frame without a length is known to be complete.
            stream.extend_from_slice(b"--frame\r\n");
            for split in 0..=stream.len() {
                let mut r = MjpegReader::new("frame", 1000);
                let mut got = r.feed(&stream[..split]).unwrap();
                got.extend(r.feed(&stream[split..]).unwrap());
                assert_eq!(got, frames(), "split at {split}, lengths {with_length}");
            }
            // Byte by byte.
            let mut r = MjpegReader::new("--frame", 1000);
            let got: Vec<Vec<u8>> = stream.iter().flat_map(|b| r.feed(&[*b]).unwrap()).collect();
            assert_eq!(got, frames());
        }
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
        assert!(matches!(
            r.feed(b"--frame\r\nContent-Length: 6\r\n\r\n<html>"),
            Err(MjpegError::NotJpeg { .. })
        ));
        // Headers that never end.
        let mut r = MjpegReader::new("frame", 100);
        r.feed(b"--frame\r\n").unwrap();
        assert_eq!(r.feed(&[b'a'; 9000]), Err(MjpegError::BadHeaders));
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
