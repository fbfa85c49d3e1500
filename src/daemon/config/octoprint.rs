//! The OctoPrint emulation's keys of `[http]`: whether each hot folder is announced by
//! zeroconf (`announce`), and the folder an upload without a `path` goes to on the root
//! instance (`default_folder`). Kept apart from the rest of `[http]` (`http.rs`) so that each
//! stays small.

use std::path::Path;

/// `[http]`'s OctoPrint keys, checked.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct OctoPrintConfig {
    /// Announce `_octoprint._tcp` per hot folder on the local network (default true).
    pub announce: bool,
    /// The hot folder (by name, the last component of its path) that the root instance
    /// (`/api/...`) stands for: uploads without a `path`, `/api/printer`, `/api/job`.
    /// None: the only folder when there is one, else such requests are refused.
    pub default_folder: Option<String>,
}

impl Default for OctoPrintConfig {
    fn default() -> OctoPrintConfig {
        OctoPrintConfig {
            announce: true,
            default_folder: None,
        }
    }
}

/// Longest `default_folder` accepted (a file name's bound).
const MAX_FOLDER_NAME: usize = 255;

/// Checks the raw keys; the error names the key.
pub(crate) fn check(
    announce: Option<bool>,
    default_folder: Option<String>,
) -> Result<OctoPrintConfig, (&'static str, String)> {
    if let Some(name) = &default_folder {
        if name.is_empty() || name.len() > MAX_FOLDER_NAME || name.contains(['/', '\0']) {
            return Err((
                "default_folder",
                format!(
                    "{name:?} is not a hot folder's name (the last part of its path, 1 to {MAX_FOLDER_NAME} bytes, without /)"
                ),
            ));
        }
    }
    Ok(OctoPrintConfig {
        announce: announce.unwrap_or(true),
        default_folder,
    })
}

/// `default_folder` names exactly one configured hot folder (`folders`: their paths).
pub(crate) fn check_folder(
    octoprint: &OctoPrintConfig,
    folders: &[&Path],
) -> Result<(), (&'static str, String)> {
    let Some(name) = &octoprint.default_folder else {
        return Ok(());
    };
    let named = |f: &&&Path| f.file_name().is_some_and(|n| n == name.as_str());
    match folders.iter().filter(named).count() {
        1 => Ok(()),
        0 => Err((
            "default_folder",
            format!(
                "no [[folder]] is called {name:?} (a folder's name is the last part of its path; the folders are: {})",
                folders
                    .iter()
                    .map(|f| f.file_name().map(|n| n.to_string_lossy().into_owned()).unwrap_or_default())
                    .collect::<Vec<_>>()
                    .join(", ")
            ),
        )),
        _ => Err((
            "default_folder",
            format!("two [[folder]]s are called {name:?}; rename one so uploads can tell them apart"),
        )),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn keys_are_bounded() {
        assert_eq!(check(None, None).unwrap(), OctoPrintConfig::default());
        assert!(!check(Some(false), None).unwrap().announce);
        for bad in ["", "a/b", &"x".repeat(256)] {
            let (key, _) = check(None, Some(bad.to_string())).unwrap_err();
            assert_eq!(key, "default_folder");
        }
    }
}
