//! Any bytes as an OctoPrint upload's body (`POST /api/files/local`): the form is read as
//! the daemon reads it (`crispen::http::read_upload_form`, the same parser and checks the
//! handler drives), whole and in pieces. Never a panic; the same outcome however the body
//! is cut into pieces; an accepted upload's file name is one plain file name that passes
//! the name check, and its fields are within their bounds.
//!
//! The first byte chooses the piece size (1 to 64 bytes) and whether the Content-Type is
//! the usual one with boundary `XyZ` (even) or the input's first line (odd).
#![no_main]

use libfuzzer_sys::fuzz_target;
use std::path::{Component, Path};

fuzz_target!(|data: &[u8]| {
    let Some((&first, rest)) = data.split_first() else {
        return;
    };
    let (content_type, body) = if first % 2 == 0 {
        ("multipart/form-data; boundary=XyZ".to_string(), rest)
    } else {
        let line_end = rest.iter().position(|b| *b == b'\n').unwrap_or(rest.len());
        let (line, body) = rest.split_at(line_end);
        (String::from_utf8_lossy(line).into_owned(), body)
    };
    let piece = usize::from(first / 2 % 64) + 1;
    let pieces: Vec<&[u8]> = body.chunks(piece).collect();
    let read = |pieces: &[&[u8]]| {
        crispen::http::read_upload_form(&content_type, pieces)
            .map_err(|e| (e.status.as_u16(), e.message))
    };
    let whole = read(&[body]);
    let cut = read(&pieces);
    assert_eq!(whole, cut, "pieces of {piece} read otherwise than the whole");
    if let Ok((form, name, kind, size)) = whole {
        assert_eq!(crispen::http::check_upload_name(&name).ok(), Some(kind));
        assert!(!name.chars().any(char::is_control), "{name:?}");
        let parts: Vec<Component> = Path::new(&name).components().collect();
        assert!(
            matches!(parts.as_slice(), [Component::Normal(n)] if *n == name.as_str()),
            "{name:?} is not one plain file name"
        );
        assert!(form.path.is_none_or(|p| p.len() <= 1024));
        assert!(size <= body.len() as u64);
    }
});
