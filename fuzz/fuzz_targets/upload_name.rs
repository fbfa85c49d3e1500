//! Any string as the name of an uploaded file (the last part of an upload's URL, or a
//! multipart `filename`): refused or accepted, never a panic, and an accepted name is one
//! plain file name that cannot reach outside its hot folder.
#![no_main]

use libfuzzer_sys::fuzz_target;
use std::path::{Component, Path};

fuzz_target!(|data: &[u8]| {
    let Ok(name) = std::str::from_utf8(data) else {
        return;
    };
    if crispen::http::check_upload_name(name).is_ok() {
        assert!(!name.contains(['/', '\\', '\0']), "{name:?}");
        assert!(!name.chars().any(char::is_control), "{name:?}");
        assert!(
            !name.contains(['\u{202a}', '\u{202b}', '\u{202c}', '\u{202d}', '\u{202e}']),
            "{name:?}"
        );
        assert!(name.len() <= 205, "{name:?}");
        let parts: Vec<Component> = Path::new(name).components().collect();
        assert!(
            matches!(parts.as_slice(), [Component::Normal(n)] if *n == name),
            "{name:?} is not one plain file name"
        );
    }
});
