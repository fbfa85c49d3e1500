//! What every handler takes: who may do what on a listener ([`Access`]) and the listener's
//! state ([`AppState`]). Apart from the root, which builds the router from the handlers,
//! so the handlers do not depend on what routes to them.

use super::appkeys::AppKeys;
use super::streams::Streams;
use crate::daemon::config::ApiKey;
use crate::daemon::farm::Farm;
use std::sync::Arc;

/// Who may do what on a listener.
#[derive(Debug, Clone)]
pub enum Access {
    /// The control socket: whoever may open it (its mode is 0660) may do everything.
    Socket,
    /// TCP: every request carries the key, or reads go without it if allowed.
    Key {
        key: ApiKey,
        read_only_without_key: bool,
    },
}

/// What every handler needs.
#[derive(Clone)]
pub struct AppState {
    pub farm: Arc<Farm>,
    pub access: Arc<Access>,
    /// The largest upload accepted, in bytes.
    pub upload_max_bytes: u64,
    /// The listener's open event streams (capped).
    pub streams: Arc<Streams>,
    /// Application keys and pending key requests (shared by both listeners).
    pub appkeys: Arc<AppKeys>,
    /// The printers' cameras (shared by both listeners).
    pub cameras: Arc<crate::camera::Cameras>,
    /// The run's counters for `/metrics` (shared by both listeners).
    pub(crate) counters: Arc<super::counters::Counters>,
    /// OctoPrint's held uploads waiting for their select-and-print (shared by both
    /// listeners and the sweeper).
    pub(crate) pending: Arc<super::pending::Pending>,
}
