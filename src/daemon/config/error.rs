//! [`ConfigError`], what every stage of the config and every section's check fails with:
//! apart from the root, which returns it, so that the sections' checks can make it.

use std::path::PathBuf;

/// A configuration problem, located as precisely as the file allows.
#[derive(Debug, thiserror::Error)]
pub enum ConfigError {
    #[error("{file}: cannot read: {source} (hint: pass --config FILE with a readable file)")]
    Read {
        file: PathBuf,
        #[source]
        source: std::io::Error,
    },
    #[error("{file}: line {line}, in {section}: {message}")]
    Parse {
        file: PathBuf,
        line: usize,
        section: String,
        message: String,
    },
    #[error("{file}: {section}: key `{key}`: {message}")]
    Invalid {
        file: PathBuf,
        section: String,
        key: String,
        message: String,
    },
}
