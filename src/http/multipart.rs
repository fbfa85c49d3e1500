//! A `multipart/form-data` body read as it arrives, with every part bounded while it is
//! read: the preamble, each part's headers and (by the caller) each field's value. The
//! parser is pure (bytes in, events out, no I/O), so the upload's whole reading of a body
//! can be fuzzed (`fuzz/fuzz_targets/upload_form.rs`). It holds at most the bytes pushed
//! since the last event plus a delimiter's length: a field of any size passes through in
//! pieces, and a part whose headers never end is refused after [`MAX_PART_HEAD_BYTES`].
//! (axum's extractor reads a text field whole and buffers part headers without a limit.)

use axum::body::Bytes;

/// Largest header block of one part (`Content-Disposition`, `Content-Type`).
pub(crate) const MAX_PART_HEAD_BYTES: usize = 8 * 1024;
/// Largest preamble before the first delimiter (clients send none).
const MAX_PREAMBLE_BYTES: usize = 4 * 1024;
/// Most headers in one part.
const MAX_PART_HEADERS: usize = 16;
/// RFC 2046: a boundary is 1 to 70 characters.
const MAX_BOUNDARY: usize = 70;

/// Why a body is not a readable multipart form.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub(crate) enum MultipartError {
    #[error("the Content-Type is not multipart/form-data with a boundary of 1 to 70 characters")]
    NotMultipart,
    #[error("more than {MAX_PREAMBLE_BYTES} bytes before the first boundary")]
    LongPreamble,
    #[error("a part's headers are longer than {MAX_PART_HEAD_BYTES} bytes or more than {MAX_PART_HEADERS}")]
    LongPartHead,
    #[error("a part's headers are malformed: {0}")]
    BadPartHead(&'static str),
    #[error("the body ends before its closing boundary")]
    Truncated,
}

/// The name and file name a part's `Content-Disposition` gives.
#[derive(Debug, Clone, PartialEq, Eq)]
pub(crate) struct PartHead {
    pub name: String,
    pub file_name: Option<String>,
}

/// What the parser found next.
#[derive(Debug, Clone, PartialEq, Eq)]
pub(super) enum Event {
    /// A part begins.
    Part(PartHead),
    /// A piece of the current part's value.
    Data(Bytes),
    /// The current part ended.
    PartEnd,
    /// The closing boundary: nothing more is read.
    End,
}

#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Stage {
    Preamble,
    AfterDelimiter,
    Head,
    Data,
    Done,
}

/// The parser: [`Parser::push`] bytes, take [`Parser::next`] events until it answers
/// `Ok(None)` (wants more), and call [`Parser::finish`] at the end of the body.
#[derive(Debug)]
pub(crate) struct Parser {
    /// `\r\n--boundary`: the body is read as if it began with `\r\n`, so the first
    /// delimiter looks like every other.
    delimiter: Vec<u8>,
    buf: Vec<u8>,
    stage: Stage,
    eof: bool,
}

/// The boundary of a `multipart/form-data` Content-Type.
pub(crate) fn boundary(content_type: &str) -> Result<String, MultipartError> {
    let mut parts = content_type.split(';');
    let kind = parts.next().unwrap_or("").trim();
    if !kind.eq_ignore_ascii_case("multipart/form-data") {
        return Err(MultipartError::NotMultipart);
    }
    for param in parts {
        let Some((key, value)) = param.split_once('=') else {
            continue;
        };
        if key.trim().eq_ignore_ascii_case("boundary") {
            let value = value.trim();
            let value = value
                .strip_prefix('"')
                .and_then(|v| v.strip_suffix('"'))
                .unwrap_or(value);
            if value.is_empty()
                || value.len() > MAX_BOUNDARY
                || value.bytes().any(|b| b.is_ascii_control())
            {
                return Err(MultipartError::NotMultipart);
            }
            return Ok(value.to_string());
        }
    }
    Err(MultipartError::NotMultipart)
}

impl Parser {
    pub(crate) fn new(boundary: &str) -> Parser {
        Parser {
            delimiter: [b"\r\n--", boundary.as_bytes()].concat(),
            buf: b"\r\n".to_vec(),
            stage: Stage::Preamble,
            eof: false,
        }
    }

    /// More of the body.
    pub(crate) fn push(&mut self, bytes: &[u8]) {
        self.buf.extend_from_slice(bytes);
    }

    /// The body has ended.
    pub(crate) fn finish(&mut self) {
        self.eof = true;
    }

    /// The next event; `Ok(None)` when more of the body is needed first.
    pub(crate) fn next(&mut self) -> Result<Option<Event>, MultipartError> {
        loop {
            match self.stage {
                Stage::Done => return Ok(Some(Event::End)),
                // Each bound is checked the same way whether the body came whole or a
                // byte at a time (the fuzz target compares the two).
                Stage::Preamble => match find(&self.buf, &self.delimiter) {
                    Some(at) if at > MAX_PREAMBLE_BYTES => {
                        return Err(MultipartError::LongPreamble)
                    }
                    Some(at) => {
                        self.buf.drain(..at + self.delimiter.len());
                        self.stage = Stage::AfterDelimiter;
                    }
                    None if self.buf.len() > MAX_PREAMBLE_BYTES + self.delimiter.len() => {
                        return Err(MultipartError::LongPreamble)
                    }
                    None => return self.more(),
                },
                Stage::AfterDelimiter => {
                    if self.buf.starts_with(b"--") {
                        self.stage = Stage::Done;
                        self.buf = Vec::new();
                        return Ok(Some(Event::End));
                    }
                    // Transport padding (spaces, tabs) may follow a delimiter.
                    let padding = self
                        .buf
                        .iter()
                        .take_while(|b| **b == b' ' || **b == b'\t')
                        .count();
                    if padding > 64 {
                        return Err(MultipartError::BadPartHead("padding after a boundary"));
                    }
                    let rest = &self.buf[padding..];
                    if rest.len() < 2 {
                        return self.more();
                    }
                    if !rest.starts_with(b"\r\n") {
                        return Err(MultipartError::BadPartHead(
                            "a boundary is not followed by a line end",
                        ));
                    }
                    self.buf.drain(..padding + 2);
                    self.stage = Stage::Head;
                }
                Stage::Head => {
                    let end = if self.buf.starts_with(b"\r\n") {
                        Some(0)
                    } else {
                        find(&self.buf, b"\r\n\r\n").map(|at| at + 2)
                    };
                    let Some(end) = end else {
                        // A terminator still to come would end past the bound.
                        if self.buf.len() > MAX_PART_HEAD_BYTES + 2 {
                            return Err(MultipartError::LongPartHead);
                        }
                        return self.more();
                    };
                    if end > MAX_PART_HEAD_BYTES {
                        return Err(MultipartError::LongPartHead);
                    }
                    let head = parse_head(&self.buf[..end])?;
                    self.buf.drain(..end + 2);
                    self.stage = Stage::Data;
                    return Ok(Some(Event::Part(head)));
                }
                Stage::Data => match find(&self.buf, &self.delimiter) {
                    Some(0) => {
                        self.buf.drain(..self.delimiter.len());
                        self.stage = Stage::AfterDelimiter;
                        return Ok(Some(Event::PartEnd));
                    }
                    Some(at) => {
                        let data: Vec<u8> = self.buf.drain(..at).collect();
                        return Ok(Some(Event::Data(Bytes::from(data))));
                    }
                    None => {
                        // The last bytes may be the start of a delimiter: kept back.
                        let keep = (self.delimiter.len() - 1).min(self.buf.len());
                        let take = self.buf.len() - keep;
                        if take == 0 {
                            return self.more();
                        }
                        let data: Vec<u8> = self.buf.drain(..take).collect();
                        return Ok(Some(Event::Data(Bytes::from(data))));
                    }
                },
            }
        }
    }

    fn more(&self) -> Result<Option<Event>, MultipartError> {
        match self.eof {
            true => Err(MultipartError::Truncated),
            false => Ok(None),
        }
    }
}

fn find(haystack: &[u8], needle: &[u8]) -> Option<usize> {
    memchr::memmem::find(haystack, needle)
}

/// A part's header lines (each ending in CRLF): the name and file name of its
/// `Content-Disposition: form-data; name="…"; filename="…"`; other headers are ignored.
fn parse_head(block: &[u8]) -> Result<PartHead, MultipartError> {
    let mut head = None;
    let lines: Vec<&[u8]> = block
        .split(|b| *b == b'\n')
        .filter(|l| !l.is_empty())
        .collect();
    if lines.len() > MAX_PART_HEADERS {
        return Err(MultipartError::LongPartHead);
    }
    for line in lines {
        let line = line.strip_suffix(b"\r").unwrap_or(line);
        let line = std::str::from_utf8(line)
            .map_err(|_| MultipartError::BadPartHead("a header is not UTF-8"))?;
        let (key, value) = line
            .split_once(':')
            .ok_or(MultipartError::BadPartHead("a header line without a colon"))?;
        if key.trim().eq_ignore_ascii_case("content-disposition") {
            if head.is_some() {
                return Err(MultipartError::BadPartHead(
                    "two Content-Disposition headers",
                ));
            }
            head = Some(parse_disposition(value)?);
        }
    }
    head.ok_or(MultipartError::BadPartHead(
        "a part without Content-Disposition",
    ))
}

/// `form-data; name="file"; filename="part.stl"`. Values are quoted strings (a backslash
/// escapes the next character, as curl writes them) or plain tokens.
fn parse_disposition(value: &str) -> Result<PartHead, MultipartError> {
    let value = value.trim();
    let rest = value
        .get(.."form-data".len())
        .filter(|k| k.eq_ignore_ascii_case("form-data"))
        .map(|_| &value["form-data".len()..])
        .ok_or(MultipartError::BadPartHead(
            "Content-Disposition is not form-data",
        ))?;
    let mut name = None;
    let mut file_name = None;
    let mut chars = rest.chars().peekable();
    loop {
        while chars.peek().is_some_and(|c| *c == ' ' || *c == '\t') {
            chars.next();
        }
        match chars.next() {
            None => break,
            Some(';') => {}
            Some(_) => {
                return Err(MultipartError::BadPartHead(
                    "Content-Disposition parameters",
                ))
            }
        }
        while chars.peek().is_some_and(|c| *c == ' ' || *c == '\t') {
            chars.next();
        }
        let mut key = String::new();
        while let Some(c) = chars.next_if(|c| *c != '=' && *c != ';') {
            key.push(c);
        }
        if chars.next_if_eq(&'=').is_none() {
            continue; // a parameter without a value: ignored
        }
        let mut val = String::new();
        if chars.next_if_eq(&'"').is_some() {
            let mut closed = false;
            while let Some(c) = chars.next() {
                match c {
                    '"' => {
                        closed = true;
                        break;
                    }
                    '\\' => val.extend(chars.next()),
                    c => val.push(c),
                }
            }
            if !closed {
                return Err(MultipartError::BadPartHead("an unclosed quoted string"));
            }
        } else {
            while let Some(c) = chars.next_if(|c| *c != ';') {
                val.push(c);
            }
            val = val.trim().to_string();
        }
        let slot = match key.trim().to_ascii_lowercase().as_str() {
            "name" => &mut name,
            "filename" => &mut file_name,
            _ => continue,
        };
        if slot.replace(val).is_some() {
            return Err(MultipartError::BadPartHead("a parameter given twice"));
        }
    }
    Ok(PartHead {
        name: name.ok_or(MultipartError::BadPartHead("a part without a name"))?,
        file_name,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Every event of `body` pushed in pieces of `step` bytes; data pieces joined.
    fn events(body: &[u8], step: usize) -> Result<Vec<Event>, MultipartError> {
        let mut p = Parser::new("XyZ");
        let mut out: Vec<Event> = Vec::new();
        let mut pieces = body.chunks(step.max(1));
        loop {
            match p.next()? {
                Some(Event::End) => {
                    out.push(Event::End);
                    return Ok(out);
                }
                Some(Event::Data(d)) => match out.last_mut() {
                    Some(Event::Data(prev)) => *prev = [&prev[..], &d[..]].concat().into(),
                    _ => out.push(Event::Data(d)),
                },
                Some(e) => out.push(e),
                None => match pieces.next() {
                    Some(piece) => p.push(piece),
                    None => p.finish(),
                },
            }
        }
    }

    #[test]
    fn a_form_is_read_whatever_the_pieces() {
        let body = b"--XyZ\r\nContent-Disposition: form-data; name=\"path\"\r\n\r\nhot\r\n\
            --XyZ  \r\ncontent-disposition: form-data; name=\"file\"; filename=\"a \\\"b\\\".stl\"\r\n\
            Content-Type: application/octet-stream\r\n\r\nsolid\r\n--X\r\nend\r\n--XyZ--\r\nignored";
        let want = vec![
            Event::Part(PartHead {
                name: "path".into(),
                file_name: None,
            }),
            Event::Data(Bytes::from_static(b"hot")),
            Event::PartEnd,
            Event::Part(PartHead {
                name: "file".into(),
                file_name: Some("a \"b\".stl".into()),
            }),
            Event::Data(Bytes::from_static(b"solid\r\n--X\r\nend")),
            Event::PartEnd,
            Event::End,
        ];
        for step in [1, 2, 3, 7, 1000] {
            assert_eq!(events(body, step).unwrap(), want, "pieces of {step}");
        }
    }

    #[test]
    fn bounds_and_breaks_are_errors() {
        let long_head = format!(
            "--XyZ\r\nContent-Disposition: form-data; name=\"{}\"\r\n\r\n",
            "n".repeat(MAX_PART_HEAD_BYTES)
        );
        assert_eq!(
            events(long_head.as_bytes(), 100),
            Err(MultipartError::LongPartHead)
        );
        let endless = vec![b'x'; 3 * MAX_PART_HEAD_BYTES];
        assert_eq!(events(&endless, 100), Err(MultipartError::LongPreamble));
        let cut = b"--XyZ\r\nContent-Disposition: form-data; name=\"a\"\r\n\r\nvalue";
        assert_eq!(events(cut, 3), Err(MultipartError::Truncated));
        let nameless = b"--XyZ\r\nContent-Disposition: form-data\r\n\r\nv\r\n--XyZ--";
        assert!(matches!(
            events(nameless, 5),
            Err(MultipartError::BadPartHead(_))
        ));
        assert_eq!(
            boundary("multipart/form-data; boundary=\"a b\"").unwrap(),
            "a b"
        );
        assert!(boundary("text/plain; boundary=x").is_err());
        assert!(boundary(&format!("multipart/form-data; boundary={}", "b".repeat(71))).is_err());
    }
}
