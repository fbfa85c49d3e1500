//! The OctoPrint instance a request addresses: a hot folder's (`/octoprint/<folder>/`) or
//! the root (`/`), and the folder each stands for. Apart from `octoprint`, which serves the
//! instances, because the application keys (`appkeys`) are scoped to an instance too.

use super::upload;
use super::ApiError;
use crate::daemon::config::{Config, FolderConfig};
use axum::extract::FromRequestParts;
use axum::http::request::Parts;

/// The OctoPrint instance a request addresses: a hot folder's (`/octoprint/<folder>/`)
/// or the root (`/`).
#[derive(Debug, Clone, PartialEq, Eq)]
pub(crate) struct Instance {
    /// The folder named in the address (percent-decoded); None on the root.
    pub folder: Option<String>,
    /// The instance's base address, as the client used it (`/octoprint/hot/` or `/`).
    pub base: String,
    /// The rest of the address after the base (`api/files/local/a.gcode`).
    pub rest: String,
}

impl Instance {
    pub(crate) fn parse(path: &str) -> Instance {
        match path.strip_prefix("/octoprint/") {
            Some(after) => {
                let (segment, rest) = after.split_once('/').unwrap_or((after, ""));
                Instance {
                    folder: Some(crate::percent::percent_decode(segment)),
                    base: format!("/octoprint/{segment}/"),
                    rest: rest.to_string(),
                }
            }
            None => Instance {
                folder: None,
                base: "/".to_string(),
                rest: path.trim_start_matches('/').to_string(),
            },
        }
    }

    /// The hot folder this instance stands for: its own, or on the root the default
    /// folder (`[http] default_folder`, else the only folder), or None.
    pub(crate) fn folder<'a>(
        &self,
        config: &'a Config,
    ) -> Result<Option<&'a FolderConfig>, ApiError> {
        match &self.folder {
            Some(name) => upload::find_folder(config, name).map(Some),
            None => Ok(default_folder(config)),
        }
    }

    /// [`Instance::folder`], required: the root without a default folder is refused with
    /// the way out.
    pub(crate) fn some_folder<'a>(&self, config: &'a Config) -> Result<&'a FolderConfig, ApiError> {
        self.folder(config)?.ok_or_else(|| no_default(config))
    }
}

impl<S: Send + Sync> FromRequestParts<S> for Instance {
    type Rejection = ApiError;

    async fn from_request_parts(parts: &mut Parts, _: &S) -> Result<Instance, ApiError> {
        Ok(Instance::parse(parts.uri.path()))
    }
}

/// The folder the root instance stands for.
pub(crate) fn default_folder(config: &Config) -> Option<&FolderConfig> {
    let named = config
        .http
        .as_ref()
        .and_then(|h| h.octoprint.default_folder.as_deref());
    match named {
        // Checked at load to name exactly one folder.
        Some(name) => upload::find_folder(config, name).ok(),
        None => match config.folders.as_slice() {
            [only] => Some(only),
            _ => None,
        },
    }
}

fn no_default(config: &Config) -> ApiError {
    ApiError::bad_request(format!(
        "which hot folder? this address (the root OctoPrint instance) stands for none: use a folder's own instance /octoprint/<folder>/, give the folder as the upload's path, or set [http] default_folder; the folders are: {}",
        config
            .folders
            .iter()
            .map(upload::folder_name)
            .collect::<Vec<_>>()
            .join(", ")
    ))
}
