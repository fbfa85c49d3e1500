//! Reading a secret file (the API key, the database password, a receiver's signing
//! secret): the one rule for every section that names one, and for the store, which reads
//! its password file again when it connects.

use std::io::Read;
use std::path::Path;

/// The largest key or password file read: a secret is a line, not a stream.
pub(crate) const MAX_SECRET_BYTES: u64 = 4096;

/// Reads a secret file (an API key, a database password): a regular file (a link to one
/// is followed) of at most [`MAX_SECRET_BYTES`] of UTF-8. Returns its text, and a warning
/// when users other than its owner may read it: accepted (a root-owned file readable by
/// group `crispen` is a fair setup), but said at every start and by `--check`.
pub(crate) fn read_secret(path: &Path) -> Result<(String, Option<String>), String> {
    use std::os::unix::fs::PermissionsExt;
    let shown = path.display();
    let meta = std::fs::metadata(path).map_err(|e| format!("cannot read {shown}: {e}"))?;
    if !meta.is_file() {
        return Err(format!(
            "{shown} is not a regular file (hint: a secret is a small regular file of its own, mode 0600)"
        ));
    }
    let mut bytes = Vec::new();
    std::fs::File::open(path)
        .and_then(|f| f.take(MAX_SECRET_BYTES + 1).read_to_end(&mut bytes))
        .map_err(|e| format!("cannot read {shown}: {e}"))?;
    if bytes.len() as u64 > MAX_SECRET_BYTES {
        return Err(format!(
            "{shown} is larger than {MAX_SECRET_BYTES} bytes: not a key or password file"
        ));
    }
    let text = String::from_utf8(bytes).map_err(|_| format!("{shown} is not UTF-8 text"))?;
    let mode = meta.permissions().mode() & 0o777;
    let warning = (mode & 0o044 != 0).then(|| {
        let who = if mode & 0o004 != 0 {
            "every user"
        } else {
            "its group"
        };
        format!("{shown} is readable by {who} (mode {mode:04o}) (hint: chmod 600 {shown}, owned by the daemon's user)")
    });
    Ok((text, warning))
}
