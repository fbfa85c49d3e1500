//! The farm's adapters to the devices and services around it, with nothing of the farm:
//!
//! - [`outbound`]: outbound HTTP/1.1 (notification receivers, cameras, Spoolman, power
//!   switches): one connection per request, https through rustls with the Mozilla roots,
//!   and the URLs it is given.
//! - [`power`]: the printers' power switches (Tasmota, Shelly, Home Assistant, plain HTTP):
//!   each one's requests and answers, and one exchange with a switch.
//!
//! The farm (`crispen`) decides when to call them; cameras, notifications and Spoolman join
//! them here once they take narrow inputs instead of the farm's own types (issue 47).

#![warn(unreachable_pub)]

pub mod outbound;
pub mod power;
