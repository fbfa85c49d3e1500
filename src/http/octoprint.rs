//! The part of OctoPrint's REST API that slicers' "Send to printer" uses (PrusaSlicer,
//! OrcaSlicer, Cura's OctoPrint connection): `GET /api/version` to test the connection and
//! `POST /api/files/local` to upload. The upload is multipart with the fields `path` (here:
//! the hot folder's name), `print`, `select` and `file`; the file goes into the hot folder:
//! a model through the normal pipeline, G-code (what a slicer sends after slicing itself)
//! as pre-sliced. Slicers send the key in `X-Api-Key`, as here.
//!
//! Every field is bounded while it is read ([`MAX_FIELD_BYTES`]; the body is parsed by
//! [`super::multipart`]), and the file's name passes [`upload::check_name`] whatever the
//! other fields say.
//!
//! `print`: with `print=true` ("Upload and print") the file prints once ready, as every
//! file in a hot folder does (`true`, `yes`, `y`, `1` are true, as in OctoPrint; `select`
//! alone is reported as `effectiveSelect` and holds). Without it ("Upload"; OctoPrint's
//! default is false) the job
//! is held: prepared as usual, then kept from the printers until the operator releases it
//! (`crispen release JOB`, `POST /api/v1/jobs/{id}/release`, the dashboard's Print
//! button). The hold travels as the model's sidecar `<file>.toml` with `hold = true`,
//! received whole and linked into the hot folder right before the model itself, so the
//! pick-up finds it with the model. A sidecar of that name already there is not
//! replaced: the upload is refused.

use super::upload;
use super::{ApiError, AppState, UPLOAD_IDLE_TIMEOUT};
use axum::extract::State;
use axum::http::header::CONTENT_TYPE;
use axum::http::{HeaderMap, StatusCode};
use axum::Json;
use futures_util::StreamExt;

/// The OctoPrint API version whose answers these are.
const API_VERSION: &str = "0.1";
/// The OctoPrint server version reported; clients only check that it is recent enough.
const SERVER_VERSION: &str = "1.10.0";

pub async fn version() -> Json<serde_json::Value> {
    Json(serde_json::json!({
        "api": API_VERSION,
        "server": SERVER_VERSION,
        "text": format!("OctoPrint (crispen {})", env!("CARGO_PKG_VERSION")),
    }))
}

/// The longest value of a text field (`path`, `print`, `select`, or one this ignores).
pub const MAX_FIELD_BYTES: usize = 1024;
/// The most parts before the file: slicers send two or three.
const MAX_PARTS_BEFORE_FILE: usize = 16;

/// What an upload's text fields said, read before its file.
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
pub enum Step {
    /// Push more of the body (or finish it).
    More,
    /// The file begins; its name has passed [`upload::check_name`].
    File { name: String, kind: upload::Upload },
    /// A piece of the file.
    Data(axum::body::Bytes),
    /// The file ended.
    FileEnd,
}

/// An upload's form read as it arrives, pure: the text fields before the file are
/// collected (each bounded while it is read), the file's name checked, its bytes passed
/// on. The handler drives it from the request body, the fuzz target from bytes.
#[derive(Debug)]
pub struct FormReader {
    parser: super::multipart::Parser,
    form: Form,
    field: Option<(String, Vec<u8>)>,
    in_file: bool,
    parts: usize,
}

impl FormReader {
    pub fn new(content_type: &str) -> Result<FormReader, ApiError> {
        let boundary = super::multipart::boundary(content_type).map_err(|e| {
            ApiError::bad_request(format!(
                "POST /api/files/local needs a multipart/form-data body with a `file` field: {e}"
            ))
        })?;
        Ok(FormReader {
            parser: super::multipart::Parser::new(&boundary),
            form: Form::default(),
            field: None,
            in_file: false,
            parts: 0,
        })
    }

    pub fn push(&mut self, bytes: &[u8]) {
        self.parser.push(bytes);
    }

    pub fn finish(&mut self) {
        self.parser.finish();
    }

    /// The text fields read so far.
    pub fn form(&self) -> &Form {
        &self.form
    }

    pub fn step(&mut self) -> Result<Step, ApiError> {
        use super::multipart::Event;
        loop {
            let event = self
                .parser
                .next()
                .map_err(|e| ApiError::bad_request(format!("the multipart body is broken: {e}")))?;
            match event {
                None => return Ok(Step::More),
                Some(Event::Part(head)) => {
                    self.parts += 1;
                    if self.parts > MAX_PARTS_BEFORE_FILE {
                        return Err(ApiError::bad_request(format!(
                            "more than {MAX_PARTS_BEFORE_FILE} fields before the `file` field"
                        )));
                    }
                    if head.name == "file" {
                        let name = head.file_name.unwrap_or_default();
                        let kind = upload::check_name(&name)?;
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
                Some(Event::End) => {
                    return Err(ApiError::bad_request(
                        "the multipart body has no `file` field (hint: the slicer sends the file as `file`)",
                    ))
                }
            }
        }
    }
}

/// What a whole upload body says, read as [`upload`] reads it but from memory, in the
/// given pieces: the form, the file's name and kind, and the file's size. Pure, for the
/// fuzz target and tests.
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
            Step::FileEnd => {
                let (name, kind) = file.expect("a file ends after it began");
                return Ok((reader.form().clone(), name, kind, size));
            }
        }
    }
}

/// Waits for the next piece of the body (at most [`UPLOAD_IDLE_TIMEOUT`]) and pushes it.
async fn pull(
    reader: &mut FormReader,
    body: &mut axum::body::BodyDataStream,
) -> Result<(), String> {
    match tokio::time::timeout(UPLOAD_IDLE_TIMEOUT, body.next()).await {
        Err(_) => Err(format!(
            "the upload stalled for {} s",
            UPLOAD_IDLE_TIMEOUT.as_secs()
        )),
        Ok(Some(Ok(piece))) => {
            reader.push(&piece);
            Ok(())
        }
        Ok(Some(Err(e))) => Err(format!("the upload broke off: {e}")),
        Ok(None) => {
            reader.finish();
            Ok(())
        }
    }
}

pub async fn upload(
    State(state): State<AppState>,
    headers: HeaderMap,
    body: axum::body::Body,
) -> Result<(StatusCode, Json<serde_json::Value>), ApiError> {
    let content_type = headers
        .get(CONTENT_TYPE)
        .and_then(|v| v.to_str().ok())
        .unwrap_or("");
    let mut reader = FormReader::new(content_type)?;
    let mut body = body.into_data_stream();
    let (file_name, kind) = loop {
        match reader.step()? {
            Step::More => pull(&mut reader, &mut body)
                .await
                .map_err(ApiError::bad_request)?,
            Step::File { name, kind } => break (name, kind),
            Step::Data(_) | Step::FileEnd => unreachable!("no file data before the file"),
        }
    };
    let form = reader.form().clone();
    let config = state.farm.config();
    let folder = folder_for(&config, form.path.as_deref())?;
    // A sidecar is no job of its own: nothing to hold. `select` alone (OctoPrint: load
    // the file, do not start it) holds, as no `print` does.
    let hold = !form.print && kind != upload::Upload::Sidecar;
    let data = futures_util::stream::unfold(
        (&mut reader, &mut body, false),
        |(reader, body, failed)| async move {
            if failed {
                return None;
            }
            loop {
                match reader.step() {
                    Ok(Step::Data(data)) => return Some((Ok(data), (reader, body, false))),
                    Ok(Step::FileEnd) => return None,
                    Ok(Step::More) => {
                        if let Err(e) = pull(reader, body).await {
                            return Some((Err(e), (reader, body, true)));
                        }
                    }
                    Ok(Step::File { .. }) => unreachable!("one file at a time"),
                    Err(e) => return Some((Err(e.message), (reader, body, true))),
                }
            }
        },
    );
    let received = upload::receive(&folder.path, &file_name, data, state.upload_max_bytes).await?;
    let size = received.size;
    let sidecar = match hold {
        true => Some(receive_hold(&folder.path, &file_name).await?),
        false => None,
    };
    let stored = upload::place_with_sidecar(received, sidecar).await?;
    let print = form.print;
    tracing::info!(file = %stored.display(), size, print, "octoprint upload into a hot folder");
    let folder_name = upload::folder_name(folder);
    let shown = crate::daemon::hotfolder::printable(&file_name);
    let message = if !hold {
        format!("{shown} is in hot folder {folder_name}; it prints once ready")
    } else {
        format!(
            "{shown} is in hot folder {folder_name}; it is prepared and then held \
             until released (`crispen release JOB` or the dashboard's Print button)"
        )
    };
    Ok((
        StatusCode::CREATED,
        Json(serde_json::json!({
            "done": true,
            "effectivePrint": !hold,
            "message": message,
            "effectiveSelect": form.select || form.print,
            "files": { "local": {
                "name": file_name,
                "path": format!("{folder_name}/{file_name}"),
                "origin": "local",
            }},
        })),
    ))
}

/// The sidecar that holds `file_name`, received into `folder` under a temporary name.
async fn receive_hold(
    folder: &std::path::Path,
    file_name: &str,
) -> Result<upload::Received, ApiError> {
    let text = futures_util::stream::iter([Ok::<_, std::convert::Infallible>(
        axum::body::Bytes::from_static(HOLD_SIDECAR.as_bytes()),
    )]);
    let sidecar = format!("{file_name}.toml");
    upload::receive(folder, &sidecar, text, HOLD_SIDECAR.len() as u64).await
}

/// The sidecar of an upload without `print`.
const HOLD_SIDECAR: &str =
    "# an upload without \"print\": prepared, then held until released\nhold = true\n";

/// The hot folder a slicer's `path` names; with no path, the only folder there is.
fn folder_for<'a>(
    config: &'a crate::daemon::config::Config,
    path: Option<&str>,
) -> Result<&'a crate::daemon::config::FolderConfig, ApiError> {
    let name = path.unwrap_or("").trim().trim_matches('/');
    if name.is_empty() {
        return match config.folders.as_slice() {
            [only] => Ok(only),
            _ => Err(ApiError::bad_request(format!(
                "which hot folder? give its name as the upload path (in the slicer's physical printer settings); the folders are: {}",
                config
                    .folders
                    .iter()
                    .map(upload::folder_name)
                    .collect::<Vec<_>>()
                    .join(", ")
            ))),
        };
    }
    upload::find_folder(config, name)
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
        assert_eq!(e.status, StatusCode::BAD_REQUEST);
        let many: Vec<(&str, &str)> = vec![("x", "y"); MAX_PARTS_BEFORE_FILE];
        assert!(read(&many, "a.gcode").is_err());
        assert!(read_form("text/plain", &[b"x"]).is_err());
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
