//! `[spoolman]`: the Spoolman server the farm's spools come from, and how often it is read.

use super::check::{seconds_in, Bounds};
use crate::outbound::HttpUrl;
use serde::Deserialize;
use std::time::Duration;

#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
pub(super) struct RawSpoolman {
    url: String,
    poll_s: Option<f64>,
    timeout_s: Option<f64>,
}

/// `[spoolman]` checked.
#[derive(Debug, Clone, PartialEq)]
pub struct SpoolmanConfig {
    /// Its base address (`http://spoolman:7912`).
    pub url: HttpUrl,
    /// Its spools are read this often (and after every use reported).
    pub poll: Duration,
    /// Each request's time limit.
    pub timeout: Duration,
}

const POLL_S: Bounds = 1.0..=3600.0;
const TIMEOUT_S: Bounds = 0.5..=120.0;

pub(super) fn check(raw: RawSpoolman) -> Result<SpoolmanConfig, (&'static str, String)> {
    Ok(SpoolmanConfig {
        url: HttpUrl::parse(&raw.url).map_err(|m| ("url", m))?,
        poll: seconds_in(raw.poll_s.unwrap_or(30.0), &POLL_S).map_err(|m| ("poll_s", m))?,
        timeout: seconds_in(raw.timeout_s.unwrap_or(5.0), &TIMEOUT_S)
            .map_err(|m| ("timeout_s", m))?,
    })
}
