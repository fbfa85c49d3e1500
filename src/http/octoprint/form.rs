//! An upload's `multipart/form-data` form read as it arrives, as OctoPrint reads it: the
//! text fields `path`, `print` and `select` may come before or after the `file` (Cura's
//! plugin sends `path`, then the file, then `select` and `print`), so the handler reads
//! the whole form before it decides where the file goes and whether it prints. Every field
//! is bounded while it is read ([`MAX_FIELD_BYTES`], at most [`MAX_PARTS`] parts; the
//! body is parsed by [`super::super::multipart`]), and the file's name is normalised and
//! passes [`upload::check_name`] whatever the other fields say ([`upload::upload_name`]).

use super::super::upload;
use super::super::ApiError;

/// The longest value of a text field (`path`, `print`, `select`, or one this ignores).
pub(crate) const MAX_FIELD_BYTES: usize = 1024;
/// The most parts in a form: slicers send two to four.
pub(crate) const MAX_PARTS: usize = 16;

/// What an upload's text fields said.
#[derive(Debug, Default, Clone, PartialEq, Eq)]
pub struct Form {
    pub path: Option<String>,
    pub print: bool,
    pub select: bool,
}

/// OctoPrint's truth: `true`, `yes`, `y` and `1` (any case) are true, anything else false.
pub fn truthy(value: &str) -> bool {
    ["true", "yes", "y", "1"]
        .iter()
        .any(|t| value.trim().eq_ignore_ascii_case(t))
}

/// What [`FormReader::step`] found.
#[derive(Debug, PartialEq, Eq)]
pub(crate) enum Step {
    /// Push more of the body (or finish it).
    More,
    /// The file begins; its name is in its one spelling (NFC) and has passed
    /// [`upload::check_name`].
    File { name: String, kind: upload::Upload },
    /// A piece of the file.
    Data(axum::body::Bytes),
    /// The file ended.
    FileEnd,
    /// The form ended (after its file); [`FormReader::form`] is complete.
    End,
}

/// An upload's form read as it arrives, pure: the text fields before and after the file
/// are collected (each bounded while it is read), the file's name checked, its bytes
/// passed on. The handler drives it from the request body, the fuzz target from bytes.
#[derive(Debug)]
pub(crate) struct FormReader {
    parser: super::super::multipart::Parser,
    form: Form,
    field: Option<(String, Vec<u8>)>,
    in_file: bool,
    file_seen: bool,
    parts: usize,
}

impl FormReader {
    pub(crate) fn new(content_type: &str) -> Result<FormReader, ApiError> {
        let boundary = super::super::multipart::boundary(content_type).map_err(|e| {
            ApiError::bad_request(format!(
                "POST /api/files/local needs a multipart/form-data body with a `file` field: {e}"
            ))
        })?;
        Ok(FormReader {
            parser: super::super::multipart::Parser::new(&boundary),
            form: Form::default(),
            field: None,
            in_file: false,
            file_seen: false,
            parts: 0,
        })
    }

    pub(crate) fn push(&mut self, bytes: &[u8]) {
        self.parser.push(bytes);
    }

    pub(crate) fn finish(&mut self) {
        self.parser.finish();
    }

    /// The text fields read so far (all of them once [`Step::End`] came).
    pub(crate) fn form(&self) -> &Form {
        &self.form
    }

    pub(crate) fn step(&mut self) -> Result<Step, ApiError> {
        use super::super::multipart::Event;
        loop {
            let event = self
                .parser
                .next()
                .map_err(|e| ApiError::bad_request(format!("the multipart body is broken: {e}")))?;
            match event {
                None => return Ok(Step::More),
                Some(Event::Part(head)) => {
                    self.parts += 1;
                    if self.parts > MAX_PARTS {
                        return Err(ApiError::bad_request(format!(
                            "the form has more than {MAX_PARTS} fields"
                        )));
                    }
                    if head.name == "file" && self.file_seen {
                        return Err(ApiError::bad_request(
                            "the form has two `file` fields; send one file per upload",
                        ));
                    }
                    if head.name == "file" {
                        self.file_seen = true;
                        // In its one spelling from here on: the file, its hold
                        // sidecar and the answer all carry that name.
                        let (name, kind) =
                            upload::upload_name(&head.file_name.unwrap_or_default())?;
                        self.in_file = true;
                        return Ok(Step::File { name, kind });
                    }
                    self.field = Some((head.name, Vec::new()));
                }
                Some(Event::Data(data)) if self.in_file => return Ok(Step::Data(data)),
                Some(Event::Data(data)) => {
                    let Some((name, value)) = self.field.as_mut() else {
                        continue;
                    };
                    if value.len() + data.len() > MAX_FIELD_BYTES {
                        return Err(ApiError::bad_request(format!(
                            "field `{}` is longer than {MAX_FIELD_BYTES} bytes",
                            crate::daemon::hotfolder::printable(name)
                        )));
                    }
                    value.extend_from_slice(&data);
                }
                Some(Event::PartEnd) if self.in_file => {
                    self.in_file = false;
                    return Ok(Step::FileEnd);
                }
                Some(Event::PartEnd) => {
                    let Some((name, value)) = self.field.take() else {
                        continue;
                    };
                    let value = String::from_utf8(value).map_err(|_| {
                        ApiError::bad_request(format!(
                            "field `{}` is not UTF-8",
                            crate::daemon::hotfolder::printable(&name)
                        ))
                    })?;
                    match name.as_str() {
                        "path" => self.form.path = Some(value),
                        "print" => self.form.print = truthy(&value),
                        "select" => self.form.select = truthy(&value),
                        // OctoPrint ignores fields it does not know; so do we.
                        _ => {}
                    }
                }
                Some(Event::End) if self.file_seen => return Ok(Step::End),
                Some(Event::End) => {
                    return Err(ApiError::bad_request(
                        "the multipart body has no `file` field (hint: the slicer sends the file as `file`)",
                    ))
                }
            }
        }
    }
}

/// What a whole upload body says, read as the handler reads it but from memory, in the
/// given pieces: the whole form, the file's name and kind, and the file's size. Pure, for
/// the fuzz target and tests.
pub fn read_form(
    content_type: &str,
    pieces: &[&[u8]],
) -> Result<(Form, String, upload::Upload, u64), ApiError> {
    let mut reader = FormReader::new(content_type)?;
    let mut pieces = pieces.iter();
    let mut file = None;
    let mut size = 0u64;
    loop {
        match reader.step()? {
            Step::More => match pieces.next() {
                Some(piece) => reader.push(piece),
                None => reader.finish(),
            },
            Step::File { name, kind } => file = Some((name, kind)),
            Step::Data(data) => size += data.len() as u64,
            Step::FileEnd => {}
            Step::End => {
                let (name, kind) = file.expect("the form ends after its file");
                return Ok((reader.form().clone(), name, kind, size));
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn body(fields: &[(&str, &str)], file_name: &str) -> Vec<u8> {
        let mut body = Vec::new();
        for (name, value) in fields {
            body.extend_from_slice(
                format!(
                    "--B\r\nContent-Disposition: form-data; name=\"{name}\"\r\n\r\n{value}\r\n"
                )
                .as_bytes(),
            );
        }
        body.extend_from_slice(
            format!(
                "--B\r\nContent-Disposition: form-data; name=\"file\"; filename=\"{file_name}\"\r\n\r\nG28\r\n--B--\r\n"
            )
            .as_bytes(),
        );
        body
    }

    #[test]
    fn a_form_is_read_with_octoprint_truths_and_bounds() {
        let ct = "multipart/form-data; boundary=B";
        let read = |fields: &[(&str, &str)], name: &str| {
            let body = body(fields, name);
            let pieces: Vec<&[u8]> = body.chunks(3).collect();
            read_form(ct, &pieces)
        };
        let (form, name, kind, size) =
            read(&[("print", "Yes"), ("path", "hot"), ("x", "y")], "a.gcode").unwrap();
        assert_eq!(
            form,
            Form {
                path: Some("hot".into()),
                print: true,
                select: false
            }
        );
        assert_eq!(
            (name.as_str(), kind, size),
            ("a.gcode", upload::Upload::Gcode, 3)
        );
        for (value, truth) in [
            ("1", true),
            ("y", true),
            ("TRUE", true),
            ("0", false),
            ("on", false),
        ] {
            assert_eq!(
                read(&[("select", value)], "a.stl").unwrap().0.select,
                truth,
                "{value}"
            );
        }
        let long = "p".repeat(MAX_FIELD_BYTES + 1);
        let e = read(&[("path", &long)], "a.gcode").unwrap_err();
        assert!(e.message.contains("`path` is longer"), "{}", e.message);
        let e = read(&[("print", "true")], "../a.gcode").unwrap_err();
        assert_eq!(e.status, axum::http::StatusCode::BAD_REQUEST);
        let many: Vec<(&str, &str)> = vec![("x", "y"); MAX_PARTS];
        assert!(read(&many, "a.gcode").is_err());
        assert!(read_form("text/plain", &[b"x"]).is_err());
    }

    /// A name in its decomposed spelling (as a Mac sends `café`) comes out in its one
    /// spelling, composed, even when the body's pieces split it between `e` and the accent.
    #[test]
    fn a_file_name_comes_out_in_its_one_spelling() {
        let ct = "multipart/form-data; boundary=B";
        let decomposed = "cafe\u{301}.gcode";
        let body = body(&[("print", "true")], decomposed);
        for step in [1, 2, 3, 7, body.len()] {
            let pieces: Vec<&[u8]> = body.chunks(step).collect();
            let (_, name, kind, _) = read_form(ct, &pieces).unwrap();
            assert_eq!(name, "caf\u{e9}.gcode", "pieces of {step}");
            assert_eq!(kind, upload::Upload::Gcode);
        }
    }

    /// Cura's order: `path`, the file, then `select` and `print`: the fields after the
    /// file count as much as those before it. A second file is refused.
    #[test]
    fn fields_after_the_file_are_read() {
        let ct = "multipart/form-data; boundary=B";
        let part = |name: &str, value: &str| {
            format!("--B\r\nContent-Disposition: form-data; name=\"{name}\"\r\nContent-Type: text/plain\r\n\r\n{value}\r\n")
        };
        let file = "--B\r\nContent-Disposition: form-data; name=\"file\"; filename=\"cura.gcode\"\r\n\r\nG28\r\n";
        let body = format!(
            "{}{file}{}{}--B--\r\n",
            part("path", ""),
            part("select", "true"),
            part("print", "true")
        );
        let pieces: Vec<&[u8]> = body.as_bytes().chunks(5).collect();
        let (form, name, _, size) = read_form(ct, &pieces).unwrap();
        assert_eq!(
            form,
            Form {
                path: Some(String::new()),
                print: true,
                select: true
            }
        );
        assert_eq!((name.as_str(), size), ("cura.gcode", 3));
        let two = format!("{file}{file}--B--\r\n");
        let e = read_form(ct, &[two.as_bytes()]).unwrap_err();
        assert!(e.message.contains("two `file` fields"), "{}", e.message);
    }

    proptest::proptest! {
        #![proptest_config(proptest::prelude::ProptestConfig::with_cases(512))]
        /// Bodies made of the pieces forms are made of (delimiters, line ends, headers,
        /// names, bytes), in any order: read whole or in pieces of any size, the outcome
        /// is the same, and an accepted name passes the name check.
        #[test]
        fn any_body_reads_the_same_in_any_pieces(
            tokens in proptest::collection::vec(0usize..14, 0..40),
            step in 1usize..40,
        ) {
            const TOKENS: [&str; 14] = [
                "--B", "\r\n", "--", "Content-Disposition: form-data; name=\"file\"; filename=\"a.gcode\"",
                "Content-Disposition: form-data; name=\"print\"", "Content-Disposition: form-data; name=\"path\"",
                "Content-Type: x", "yes", "hot", "G28 ", "\r\n\r\n", "../x.stl\"", "filename=\"", "\u{1b}",
            ];
            let body: Vec<u8> = tokens.iter().flat_map(|t| TOKENS[*t].bytes()).collect();
            let ct = "multipart/form-data; boundary=B";
            let key = |r: Result<(Form, String, upload::Upload, u64), ApiError>| {
                r.map_err(|e| (e.status, e.message))
            };
            let whole = key(read_form(ct, &[&body]));
            let pieces: Vec<&[u8]> = body.chunks(step).collect();
            proptest::prop_assert_eq!(&whole, &key(read_form(ct, &pieces)));
            if let Ok((_, name, kind, _)) = whole {
                proptest::prop_assert_eq!(upload::check_name(&name).ok(), Some(kind));
            }
        }
    }
}
