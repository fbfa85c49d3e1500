//! Any string as the name of an uploaded file (the last part of an upload's URL, or a
//! multipart `filename`): refused or accepted, never a panic, and an accepted name is one
//! plain file name that cannot reach outside its hot folder. The name as the farm keeps it
//! ([`crispen::http::upload_name`], in its one spelling) is such a name too, spelt once:
//! normalising it again changes nothing, and any other spelling of it is kept the same.
#![no_main]

use libfuzzer_sys::fuzz_target;
use std::path::{Component, Path};

fn plain(name: &str) {
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

fuzz_target!(|data: &[u8]| {
    let Ok(name) = std::str::from_utf8(data) else {
        return;
    };
    if crispen::http::check_upload_name(name).is_ok() {
        plain(name);
    }
    if let Ok((kept, kind)) = crispen::http::upload_name(name) {
        plain(&kept);
        assert_eq!(crispen::http::check_upload_name(&kept).ok(), Some(kind));
        assert_eq!(
            crispen::daemon::hotfolder::normal_name(&kept),
            kept.as_str(),
            "{kept:?} is spelt once"
        );
        assert!(crispen::daemon::hotfolder::same_name(name, &kept));
        let again = crispen::http::upload_name(&kept).map(|(n, _)| n).ok();
        assert_eq!(again.as_deref(), Some(kept.as_str()), "{name:?}");
    }
});
