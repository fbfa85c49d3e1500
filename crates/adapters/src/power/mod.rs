//! Printers' power switches: the smart plug or relay in front of a printer, switched on
//! when it has work and off when it has been idle and cool (the printer's supervisor
//! decides; this only speaks to the switch). Each kind of switch is a request to make and
//! an answer to read ([`Switch::request`], [`Switch::read`]: no I/O, tested alone), and
//! [`Switch::send`] carries one out through `outbound`:
//!
//! - Tasmota: `GET /cm?cmnd=Power%20On` (`Off`, or `Power` to ask), answering
//!   `{"POWER":"ON"}`.
//! - Shelly Gen1: `GET /relay/0?turn=on` (`off`, or no query to ask), answering
//!   `{"ison":true}`.
//! - Shelly Gen2 and later (RPC): `GET /rpc/Switch.Set?id=0&on=true`, answering
//!   `{"was_on":false}`; `GET /rpc/Switch.GetStatus?id=0` answers `{"output":true}`.
//! - Home Assistant: `POST /api/services/switch/turn_on` with `{"entity_id": ...}` and a
//!   long-lived token; `GET /api/states/<entity>` answers `{"state":"on"}`.
//! - A plain HTTP pair: a `GET` of the on or off URL; any 2xx is done; its state cannot be
//!   asked.

use crate::outbound::{Cap, HttpUrl};
use bytes::Bytes;
use http_body_util::Full;
use std::time::Duration;

/// How long one exchange with a switch may take.
pub const TIMEOUT: Duration = Duration::from_secs(10);
/// The most of a switch's answer that is read.
const MAX_ANSWER_BYTES: usize = 64 * 1024;

/// A printer's power switch, checked.
#[derive(Debug, Clone, PartialEq)]
pub enum Switch {
    /// Its address (`http://plug-a.local`).
    Tasmota(HttpUrl),
    ShellyGen1(HttpUrl),
    ShellyRpc(HttpUrl),
    HomeAssistant {
        url: HttpUrl,
        /// `switch.printer_a`.
        entity: String,
        /// A file holding a long-lived access token, read at each use (never logged).
        token_file: std::path::PathBuf,
    },
    Http {
        on: HttpUrl,
        off: HttpUrl,
    },
}

/// What is asked of a switch.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Ask {
    On,
    Off,
    /// Whether it is on.
    State,
}

/// One request to a switch.
#[derive(Debug, Clone, PartialEq)]
pub struct Request {
    pub url: HttpUrl,
    pub method: hyper::Method,
    /// Path and query on `url`'s host.
    pub target: String,
    pub body: Option<String>,
}

/// Why a switch did not do what was asked.
#[derive(Debug, thiserror::Error)]
pub enum PowerError {
    #[error("the switch did not answer: {0}")]
    Unreachable(#[from] crate::outbound::OutboundError),
    #[error("the switch did not answer within {} s", TIMEOUT.as_secs())]
    Timeout,
    #[error("the switch answered HTTP {status}: {body}")]
    Refused { status: u16, body: String },
    #[error("the switch's answer is not one it gives: {0}")]
    Answer(String),
    #[error("the switch cannot be asked whether it is on")]
    NoState,
    #[error("the Home Assistant token file {path}: {message}")]
    Token { path: String, message: String },
    #[error("the switch is {} after it was switched {}", if *now { "on" } else { "off" }, if *now { "off" } else { "on" })]
    Unchanged { now: bool },
}

impl Switch {
    /// The kind, as `[printer.power] kind` names it.
    pub fn kind(&self) -> &'static str {
        match self {
            Switch::Tasmota(_) => "tasmota",
            Switch::ShellyGen1(_) => "shelly",
            Switch::ShellyRpc(_) => "shelly-rpc",
            Switch::HomeAssistant { .. } => "homeassistant",
            Switch::Http { .. } => "http",
        }
    }

    /// The request that asks `ask` of it; None when it cannot be asked (the state of a
    /// plain HTTP pair).
    pub fn request(&self, ask: Ask) -> Option<Request> {
        let get = |url: &HttpUrl, target: String| Request {
            url: url.clone(),
            method: hyper::Method::GET,
            target,
            body: None,
        };
        let base = |url: &HttpUrl| url.path.trim_end_matches('/').to_string();
        Some(match (self, ask) {
            (Switch::Tasmota(url), ask) => {
                let cmnd = match ask {
                    Ask::On => "Power%20On",
                    Ask::Off => "Power%20Off",
                    Ask::State => "Power",
                };
                get(url, format!("{}/cm?cmnd={cmnd}", base(url)))
            }
            (Switch::ShellyGen1(url), ask) => {
                let query = match ask {
                    Ask::On => "?turn=on",
                    Ask::Off => "?turn=off",
                    Ask::State => "",
                };
                get(url, format!("{}/relay/0{query}", base(url)))
            }
            (Switch::ShellyRpc(url), Ask::State) => {
                get(url, format!("{}/rpc/Switch.GetStatus?id=0", base(url)))
            }
            (Switch::ShellyRpc(url), ask) => get(
                url,
                format!("{}/rpc/Switch.Set?id=0&on={}", base(url), ask == Ask::On),
            ),
            (Switch::HomeAssistant { url, entity, .. }, Ask::State) => {
                get(url, format!("{}/api/states/{entity}", base(url)))
            }
            (Switch::HomeAssistant { url, entity, .. }, ask) => Request {
                url: url.clone(),
                method: hyper::Method::POST,
                target: format!(
                    "{}/api/services/switch/{}",
                    base(url),
                    if ask == Ask::On {
                        "turn_on"
                    } else {
                        "turn_off"
                    }
                ),
                body: Some(serde_json::json!({ "entity_id": entity }).to_string()),
            },
            (Switch::Http { on, .. }, Ask::On) => get(on, on.path.clone()),
            (Switch::Http { off, .. }, Ask::Off) => get(off, off.path.clone()),
            (Switch::Http { .. }, Ask::State) => return None,
        })
    }

    /// Whether the switch is on, by its answer (`status`, `body`) to `ask`: None when the
    /// answer does not say (a plain HTTP pair; Home Assistant's service call).
    pub fn read(&self, ask: Ask, status: u16, body: &[u8]) -> Result<Option<bool>, PowerError> {
        if !(200..300).contains(&status) {
            let text = String::from_utf8_lossy(&body[..body.len().min(200)]);
            return Err(PowerError::Refused {
                status,
                // A device's text, shown in an error: nothing in it may steer a terminal.
                body: text.trim().escape_debug().to_string(),
            });
        }
        let json = || -> Result<serde_json::Value, PowerError> {
            serde_json::from_slice(body).map_err(|e| PowerError::Answer(format!("not JSON: {e}")))
        };
        let missing = |what: &str| PowerError::Answer(format!("no {what} in it"));
        match (self, ask) {
            (Switch::Tasmota(_), _) => {
                let v = json()?;
                // One relay answers `POWER`, a device of several `POWER1` for the first.
                let power = v
                    .get("POWER")
                    .or_else(|| v.get("POWER1"))
                    .and_then(|p| p.as_str())
                    .ok_or_else(|| missing("POWER"))?;
                match power {
                    "ON" => Ok(Some(true)),
                    "OFF" => Ok(Some(false)),
                    other => Err(PowerError::Answer(format!("POWER is {other:?}"))),
                }
            }
            (Switch::ShellyGen1(_), _) => json()?
                .get("ison")
                .and_then(|v| v.as_bool())
                .map(Some)
                .ok_or_else(|| missing("ison")),
            (Switch::ShellyRpc(_), Ask::State) => json()?
                .get("output")
                .and_then(|v| v.as_bool())
                .map(Some)
                .ok_or_else(|| missing("output")),
            // `Switch.Set` answers what it was before; done, it is as asked.
            (Switch::ShellyRpc(_), ask) => {
                json()?
                    .get("was_on")
                    .and_then(|v| v.as_bool())
                    .ok_or_else(|| missing("was_on"))?;
                Ok(Some(ask == Ask::On))
            }
            (Switch::HomeAssistant { .. }, Ask::State) => {
                match json()?.get("state").and_then(|s| s.as_str()) {
                    Some("on") => Ok(Some(true)),
                    Some("off") => Ok(Some(false)),
                    Some(other) => Err(PowerError::Answer(format!("state is {other:?}"))),
                    None => Err(missing("state")),
                }
            }
            (Switch::HomeAssistant { .. } | Switch::Http { .. }, _) => Ok(None),
        }
    }

    /// Asks `ask` of the switch: whether it is on after it (when its answer says; for a
    /// switch whose answer does not, as asked). A switch that says it is not as asked is an
    /// error.
    pub async fn send(&self, ask: Ask) -> Result<bool, PowerError> {
        let Some(r) = self.request(ask) else {
            return Err(PowerError::NoState);
        };
        let mut builder = crate::outbound::request(&r.url, r.method.clone(), &r.target);
        if let Switch::HomeAssistant { token_file, .. } = self {
            let token =
                tokio::fs::read_to_string(token_file)
                    .await
                    .map_err(|e| PowerError::Token {
                        path: token_file.display().to_string(),
                        message: e.to_string(),
                    })?;
            builder = builder
                .header(
                    hyper::header::AUTHORIZATION,
                    format!("Bearer {}", token.trim()),
                )
                .header(hyper::header::CONTENT_TYPE, "application/json");
        }
        let request = builder
            .body(Full::new(Bytes::from(r.body.unwrap_or_default())))
            .map_err(|e| PowerError::Answer(format!("the request: {e}")))?;
        let (status, body) = tokio::time::timeout(
            TIMEOUT,
            crate::outbound::send(&r.url, request, Cap::Refuse(MAX_ANSWER_BYTES)),
        )
        .await
        .map_err(|_| PowerError::Timeout)??;
        let now = self.read(ask, status, &body)?;
        match (ask, now) {
            (Ask::On, Some(false)) => Err(PowerError::Unchanged { now: false }),
            (Ask::Off, Some(true)) => Err(PowerError::Unchanged { now: true }),
            (_, Some(on)) => Ok(on),
            (Ask::State, None) => Err(PowerError::NoState),
            (ask, None) => Ok(ask == Ask::On),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn url(text: &str) -> HttpUrl {
        HttpUrl::parse(text).unwrap()
    }

    /// Each kind's requests, as its own documentation spells them.
    #[test]
    fn each_kind_asks_as_its_device_expects() {
        let target = |s: &Switch, ask| s.request(ask).map(|r| (r.method, r.target));
        let t = Switch::Tasmota(url("http://plug.local/"));
        assert_eq!(
            target(&t, Ask::On),
            Some((hyper::Method::GET, "/cm?cmnd=Power%20On".into()))
        );
        assert_eq!(target(&t, Ask::State).unwrap().1, "/cm?cmnd=Power");
        let s = Switch::ShellyGen1(url("http://10.0.0.9"));
        assert_eq!(target(&s, Ask::Off).unwrap().1, "/relay/0?turn=off");
        assert_eq!(target(&s, Ask::State).unwrap().1, "/relay/0");
        let r = Switch::ShellyRpc(url("http://10.0.0.9"));
        assert_eq!(
            target(&r, Ask::On).unwrap().1,
            "/rpc/Switch.Set?id=0&on=true"
        );
        assert_eq!(
            target(&r, Ask::State).unwrap().1,
            "/rpc/Switch.GetStatus?id=0"
        );
        let h = Switch::HomeAssistant {
            url: url("http://ha.local:8123/"),
            entity: "switch.printer_a".into(),
            token_file: "/etc/crispen/ha.token".into(),
        };
        let on = h.request(Ask::On).unwrap();
        assert_eq!(
            (on.method, on.target.as_str()),
            (hyper::Method::POST, "/api/services/switch/turn_on")
        );
        assert_eq!(
            on.body.as_deref(),
            Some(r#"{"entity_id":"switch.printer_a"}"#)
        );
        assert_eq!(
            target(&h, Ask::State).unwrap().1,
            "/api/states/switch.printer_a"
        );
        let p = Switch::Http {
            on: url("http://relay/on?x=1"),
            off: url("http://relay/off"),
        };
        assert_eq!(target(&p, Ask::On).unwrap().1, "/on?x=1");
        assert_eq!(p.request(Ask::State), None);
    }

    /// Answers are read strictly: what each kind says it is, and an error for anything
    /// else (a refusal, a body that is not the device's).
    #[test]
    fn answers_are_read_strictly() {
        let t = Switch::Tasmota(url("http://plug"));
        assert_eq!(
            t.read(Ask::On, 200, br#"{"POWER":"ON"}"#).unwrap(),
            Some(true)
        );
        assert_eq!(
            t.read(Ask::State, 200, br#"{"POWER1":"OFF"}"#).unwrap(),
            Some(false)
        );
        assert!(matches!(
            t.read(Ask::On, 200, b"<html>"),
            Err(PowerError::Answer(_))
        ));
        assert!(matches!(
            t.read(Ask::On, 401, b"denied"),
            Err(PowerError::Refused { status: 401, .. })
        ));
        let s = Switch::ShellyGen1(url("http://s"));
        assert_eq!(
            s.read(Ask::Off, 200, br#"{"ison":false,"source":"http"}"#)
                .unwrap(),
            Some(false)
        );
        let r = Switch::ShellyRpc(url("http://s"));
        assert_eq!(
            r.read(Ask::Off, 200, br#"{"was_on":true}"#).unwrap(),
            Some(false)
        );
        assert_eq!(
            r.read(Ask::State, 200, br#"{"id":0,"output":true}"#)
                .unwrap(),
            Some(true)
        );
        let h = Switch::HomeAssistant {
            url: url("http://ha"),
            entity: "switch.a".into(),
            token_file: "t".into(),
        };
        assert_eq!(h.read(Ask::On, 200, b"[]").unwrap(), None);
        assert_eq!(
            h.read(Ask::State, 200, br#"{"state":"off"}"#).unwrap(),
            Some(false)
        );
        assert!(h
            .read(Ask::State, 200, br#"{"state":"unavailable"}"#)
            .is_err());
    }
}
