//! Each OctoPrint instance's identity: the UUID OctoPrint's bundled Discovery plugin keeps
//! as `plugins.discovery.upnpUuid` and announces as the `uuid` TXT record of
//! `_octoprint._tcp`. Home Assistant takes it as the device's unique id (from
//! `api/settings` when set up by hand, from the TXT record when discovered), so it must
//! be the same in both places, the same across restarts and reloads, and different per
//! instance; else a discovered instance and a configured one are two devices, or two
//! folders are taken for one.
//!
//! How: one random seed per spool, made once (`octoprint-uuid-seed`, 32 random bytes in
//! hex, never replaced), and each instance's UUID is SHA-256 of the seed and the
//! instance's name, shaped as an RFC 9562 UUID of version 8 (custom). Nothing else to
//! store: a folder added by a reload has its UUID already, a folder renamed is a new
//! instance (a new device for Home Assistant, as a new OctoPrint would be).

use sha2::{Digest, Sha256};
use std::io::{Read, Write};
use std::path::Path;

/// The seed's file in the spool directory.
pub(crate) const SEED_FILE: &str = "octoprint-uuid-seed";
/// The seed's length in bytes (written as twice as many hex digits).
const SEED_BYTES: usize = 32;

/// The seed cannot be read or made.
#[derive(Debug, thiserror::Error)]
#[error("the OctoPrint instances' identity seed {path}: {message}")]
pub(crate) struct IdentityError {
    pub path: String,
    pub message: String,
}

/// Which instance: the root (`/`) or a hot folder's (`/octoprint/<folder>/`).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(crate) enum Which<'a> {
    Root,
    Folder(&'a str),
}

/// The UUID of instance `which` on the farm whose spool is `spool_dir`; the seed is made
/// there the first time.
pub(crate) fn uuid(spool_dir: &Path, which: Which<'_>) -> Result<String, IdentityError> {
    let seed = seed(spool_dir)?;
    Ok(uuid_from(&seed, which))
}

/// The UUID of `which` for `seed` (pure).
pub(crate) fn uuid_from(seed: &[u8], which: Which<'_>) -> String {
    let mut hash = Sha256::new();
    hash.update(b"crispen octoprint instance\0");
    hash.update(seed);
    match which {
        Which::Root => hash.update(b"\0root"),
        Which::Folder(name) => {
            hash.update(b"\0folder\0");
            hash.update(name.as_bytes());
        }
    }
    let digest = hash.finalize();
    let mut b = [0u8; 16];
    b.copy_from_slice(&digest[..16]);
    // Version 8 (custom), variant RFC 9562.
    b[6] = (b[6] & 0x0f) | 0x80;
    b[8] = (b[8] & 0x3f) | 0x80;
    let hex: String = b.iter().map(|x| format!("{x:02x}")).collect();
    format!(
        "{}-{}-{}-{}-{}",
        &hex[0..8],
        &hex[8..12],
        &hex[12..16],
        &hex[16..20],
        &hex[20..32]
    )
}

/// The spool's seed: read, or made and put in place without replacing one another
/// process (or request) made meanwhile.
fn seed(spool_dir: &Path) -> Result<Vec<u8>, IdentityError> {
    let path = spool_dir.join(SEED_FILE);
    let failed = |message: String| IdentityError {
        path: path.display().to_string(),
        message,
    };
    if let Some(seed) = read_seed(&path).map_err(|e| failed(e.to_string()))? {
        return Ok(seed);
    }
    let mut bytes = [0u8; SEED_BYTES];
    rand::fill(&mut bytes[..]);
    let hex: String = bytes.iter().map(|x| format!("{x:02x}")).collect();
    let mut tmp = tempfile::Builder::new()
        .prefix(crate::fsutil::TEMP_PREFIX)
        .tempfile_in(spool_dir)
        .map_err(|e| failed(format!("cannot create: {e}")))?;
    tmp.write_all(format!("{hex}\n").as_bytes())
        .and_then(|_| tmp.as_file().sync_all())
        .map_err(|e| failed(format!("cannot write: {e}")))?;
    match tmp.persist_noclobber(&path) {
        Ok(_) => {
            tracing::info!(path = %path.display(), "octoprint: made the instances' identity seed");
            Ok(bytes.to_vec())
        }
        // Made meanwhile: that one is the seed.
        Err(e) if e.error.kind() == std::io::ErrorKind::AlreadyExists => read_seed(&path)
            .map_err(|e| failed(e.to_string()))?
            .ok_or_else(|| failed("vanished right after it was made".to_string())),
        Err(e) => Err(failed(format!("cannot put in place: {}", e.error))),
    }
}

/// The seed in `path`, None if there is no such file; a file that is not a seed is an
/// error (never replaced: the identities hang on it).
fn read_seed(path: &Path) -> std::io::Result<Option<Vec<u8>>> {
    let file = match std::fs::File::open(path) {
        Ok(f) => f,
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => return Ok(None),
        Err(e) => return Err(e),
    };
    let mut text = String::new();
    file.take(4 * SEED_BYTES as u64).read_to_string(&mut text)?;
    let text = text.trim();
    let bytes: Option<Vec<u8>> = (text.len() == 2 * SEED_BYTES)
        .then(|| {
            (0..SEED_BYTES)
                .map(|i| u8::from_str_radix(text.get(2 * i..2 * i + 2)?, 16).ok())
                .collect()
        })
        .flatten();
    bytes.map(Some).ok_or_else(|| {
        std::io::Error::new(
            std::io::ErrorKind::InvalidData,
            format!("not {} hex digits", 2 * SEED_BYTES),
        )
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn identities_are_stable_and_distinct() {
        let dir = tempfile::tempdir().unwrap();
        let hot = uuid(dir.path(), Which::Folder("hot")).unwrap();
        let other = uuid(dir.path(), Which::Folder("other")).unwrap();
        let root = uuid(dir.path(), Which::Root).unwrap();
        assert_eq!(hot.len(), 36);
        assert_eq!(&hot[14..15], "8", "{hot}");
        assert!(hot != other && hot != root && other != root);
        // Read again (a restart): the same.
        assert_eq!(uuid(dir.path(), Which::Folder("hot")).unwrap(), hot);
        // Another spool: another farm, other identities.
        let dir2 = tempfile::tempdir().unwrap();
        assert_ne!(uuid(dir2.path(), Which::Folder("hot")).unwrap(), hot);
        // A damaged seed is an error, never silently replaced.
        std::fs::write(dir.path().join(SEED_FILE), "junk").unwrap();
        assert!(uuid(dir.path(), Which::Folder("hot")).is_err());
    }
}
