//! The bounds on a request: its body, its time, an upload's size and pace. Apart from the
//! listener's state because the upload reading that the keys' instances use needs them.

use std::time::Duration;

/// The upload bound where `[http]` sets none (the control socket without `[http]`).
pub(crate) const DEFAULT_UPLOAD_MAX_BYTES: u64 = 512 * 1024 * 1024;

/// Largest body of any request but an upload: actions carry no body or a few fields.
pub(crate) const MAX_BODY_BYTES: usize = 64 * 1024;
/// A request (other than an upload or the event stream) is answered within this or gets 503.
pub(crate) const REQUEST_TIMEOUT: Duration = Duration::from_secs(30);
/// An upload may take this long in all…
pub(crate) const UPLOAD_TIMEOUT: Duration = Duration::from_secs(3600);
/// …but no more than this between two pieces of it.
pub(crate) const UPLOAD_IDLE_TIMEOUT: Duration = Duration::from_secs(60);
