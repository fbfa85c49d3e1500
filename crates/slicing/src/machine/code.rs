//! The operator's own G-code files a machine names (start, end, pause, resume, eject),
//! read with a bound.

use std::path::Path;

/// The largest start or end code file read.
pub(crate) const MAX_CODE_BYTES: u64 = 64 * 1024;

/// Reads a start or end code file: text, at most [`MAX_CODE_BYTES`].
pub(crate) fn read_code(path: &Path) -> Result<String, String> {
    use std::io::Read;
    let mut text = String::new();
    std::fs::File::open(path)
        .and_then(|f| f.take(MAX_CODE_BYTES + 1).read_to_string(&mut text))
        .map_err(|e| format!("cannot read {}: {e}", path.display()))?;
    if text.len() as u64 > MAX_CODE_BYTES {
        return Err(format!(
            "{}: larger than {MAX_CODE_BYTES} bytes; start and end code is a few lines",
            path.display()
        ));
    }
    Ok(text)
}
