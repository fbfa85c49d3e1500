//! A client for Spoolman, the filament-spool inventory server many farms already keep: the
//! spools it knows (material, colour, brand, weight left, price per kilogram), and the
//! filament a print used booked against its spool, so the inventory follows the farm
//! without anyone weighing spools.
//!
//! Spoolman's REST API (`/api/v1`) is spoken over HTTP/1.1 like the notification and camera
//! clients do: one connection per request (requests are rare), the whole exchange within
//! the client's time limit, answers capped at [`MAX_ANSWER_BYTES`]. What Spoolman answers
//! is read into private shapes of its JSON and then checked with the bounds of a spool of
//! the farm's own (the one check, `daemon::filament`'s), so a spool handed out is one the
//! farm could have entered itself, and a field that is missing or wrong is named. In a
//! list, a spool that fails the check is set aside with why, never the whole list.

pub mod link;

use crate::daemon::filament::{
    check_filament, colour_name, grams_in_bounds, Filament, FilamentError, SetAside,
};
use crate::outbound::HttpUrl;
use bytes::Bytes;
use http_body_util::Full;
use serde::{Deserialize, Serialize};
use std::time::Duration;

/// The largest answer read: a list of some thousand spools is well under 8 MiB; anything
/// bigger is not Spoolman speaking.
pub const MAX_ANSWER_BYTES: usize = 8 << 20;

/// The start of an error message kept from Spoolman's answer.
const MAX_MESSAGE_CHARS: usize = 300;

/// Why Spoolman could not be asked, or what it answered instead.
#[derive(Debug, thiserror::Error)]
pub enum SpoolmanError {
    #[error("cannot connect to Spoolman at {host}:{port}: {message}")]
    Connect {
        host: String,
        port: u16,
        message: String,
    },
    #[error("no answer from Spoolman within {0:?}")]
    Timeout(Duration),
    #[error("Spoolman answered {request} with HTTP {status}{}", colon(.message))]
    Status {
        request: String,
        status: u16,
        /// Spoolman's own `message` (or FastAPI's `detail`), when the answer had one.
        message: Option<String>,
    },
    #[error("Spoolman's answer to {request} is not what was expected: {detail}")]
    BadAnswer { request: String, detail: String },
    #[error("Spoolman's answer to {request} is larger than {} MiB", MAX_ANSWER_BYTES >> 20)]
    TooLarge { request: String },
    #[error("HTTP with Spoolman: {0}")]
    Http(String),
    #[error("{0} g is not an amount of filament used (a finite number of grams, at least 0)")]
    Amount(f64),
}

fn colon(message: &Option<String>) -> String {
    message
        .as_deref()
        .map(|m| format!(": {m}"))
        .unwrap_or_default()
}

/// One spool as the farm needs it, from Spoolman's spool and the filament it holds.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct SpoolmanSpool {
    pub id: u64,
    pub filament_name: Option<String>,
    pub material: Option<String>,
    /// As Spoolman has it: six or eight hex digits, no `#`.
    pub colour_hex: Option<String>,
    /// The filament's vendor.
    pub brand: Option<String>,
    pub diameter_mm: f64,
    pub density_g_cm3: f64,
    pub initial_g: Option<f64>,
    pub used_g: f64,
    /// Spoolman's own figure (it needs an initial weight, the spool's or the filament's).
    pub remaining_g: Option<f64>,
    /// The spool's price over its weight when the spool has a price, else the filament's
    /// price over the filament's weight; None when neither can be worked out.
    pub price_per_kg: Option<f64>,
    pub archived: bool,
}

impl SpoolmanSpool {
    /// The spool as the farm's inventory keeps it, its filament and weight left, checked
    /// by the one check of a spool ([`check_filament`], [`grams_in_bounds`]) whether the
    /// farm's own or Spoolman's. A material Spoolman leaves blank is `unknown`; the colour
    /// is named from the filament's name and hex colour, whose alpha (`RRGGBBAA`) is not
    /// kept.
    pub fn for_farm(&self) -> Result<(Filament, Option<f64>), FilamentError> {
        let material = self
            .material
            .as_deref()
            .map(str::trim)
            .filter(|m| !m.is_empty())
            .unwrap_or("unknown");
        let colour_hex = self.colour_hex.as_deref().map(|h| match h.len() {
            8 => h.get(..6).unwrap_or(h),
            _ => h,
        });
        let filament = check_filament(Filament {
            material: material.to_string(),
            colour: colour_name(self.filament_name.as_deref(), colour_hex),
            colour_hex: colour_hex.map(str::to_string),
            brand: self.brand.clone(),
            diameter_mm: self.diameter_mm,
            density_g_cm3: self.density_g_cm3,
            price_per_kg: self.price_per_kg,
        })?;
        let remaining = self
            .remaining_g
            .map(|g| {
                grams_in_bounds(g)
                    .map_err(|e| FilamentError::Invalid(format!("remaining_weight: {e}")))
            })
            .transpose()?;
        Ok((filament, remaining))
    }
}

/// Spoolman's spools as read: those the farm takes, and those set aside, each with why.
#[derive(Debug, Default)]
pub struct SpoolList {
    pub spools: Vec<SpoolmanSpool>,
    pub set_aside: Vec<SetAside>,
}

/// Spoolman's spool as it sends it; absent and `null` fields are None, unknown ones are
/// ignored (Spoolman adds fields between versions). The filament is read as a layer of
/// its own, so a malformed one is named as the filament's.
#[derive(Deserialize)]
struct RawSpool {
    id: u64,
    filament: Option<serde_json::Value>,
    price: Option<f64>,
    initial_weight: Option<f64>,
    used_weight: Option<f64>,
    remaining_weight: Option<f64>,
    archived: Option<bool>,
}

#[derive(Deserialize)]
struct RawFilament {
    name: Option<String>,
    material: Option<String>,
    color_hex: Option<String>,
    vendor: Option<serde_json::Value>,
    diameter: Option<f64>,
    density: Option<f64>,
    /// The net weight of filament on a spool of this kind, in grams.
    weight: Option<f64>,
    price: Option<f64>,
}

#[derive(Deserialize)]
struct RawVendor {
    name: Option<String>,
}

/// A weight of Spoolman's (`field`), within the bounds of a spool of the farm's own.
fn weight(value: Option<f64>, field: &str) -> Result<Option<f64>, String> {
    value
        .map(|g| grams_in_bounds(g).map_err(|e| format!("{field}: {e}")))
        .transpose()
}

/// A price of Spoolman's (`field`): a finite amount of at least 0 (the price per kg
/// worked out from it is checked with the filament).
fn price(value: Option<f64>, field: &str) -> Result<Option<f64>, String> {
    match value {
        Some(p) if !(p >= 0.0) || !p.is_finite() => Err(format!(
            "{field}: a price of at least 0, got {}",
            crate::names::number(p)
        )),
        v => Ok(v),
    }
}

/// A quantity the spool cannot do without (its filament's diameter and density); its
/// bounds are checked with the rest of the filament ([`SpoolmanSpool::for_farm`]).
fn present(value: Option<f64>, field: &str) -> Result<f64, String> {
    value.ok_or_else(|| format!("{field} is missing"))
}

/// One spool of Spoolman's JSON, read and checked with the bounds of a spool of the
/// farm's own (see [`SpoolmanSpool::for_farm`]); what is wrong with it otherwise.
fn spool_from_json(value: serde_json::Value) -> Result<SpoolmanSpool, String> {
    let raw: RawSpool = serde_json::from_value(value).map_err(|e| format!("not a spool ({e})"))?;
    let id = raw.id;
    let at = |detail: String| format!("spool {id}: {detail}");
    let filament = raw
        .filament
        .ok_or_else(|| at("filament is missing".into()))?;
    let filament: RawFilament = serde_json::from_value(filament)
        .map_err(|e| at(format!("filament is not a filament ({e})")))?;
    let brand = match filament.vendor {
        None => None,
        Some(vendor) => {
            serde_json::from_value::<RawVendor>(vendor)
                .map_err(|e| at(format!("filament.vendor is not a vendor ({e})")))?
                .name
        }
    };
    let diameter_mm = present(filament.diameter, "filament.diameter").map_err(at)?;
    let density_g_cm3 = present(filament.density, "filament.density").map_err(at)?;
    let filament_weight = weight(filament.weight, "filament.weight").map_err(at)?;
    let initial_g = weight(raw.initial_weight, "initial_weight").map_err(at)?;
    let used_g = weight(raw.used_weight, "used_weight")
        .map_err(at)?
        .unwrap_or(0.0);
    let remaining_g = raw.remaining_weight;
    let spool_price = price(raw.price, "price").map_err(at)?;
    let filament_price = price(filament.price, "filament.price").map_err(at)?;

    // A spool without its own initial weight holds the filament's weight: Spoolman works
    // out the weight left the same way. The price per kg is checked with the filament.
    let per_kg = |price: Option<f64>, grams: Option<f64>| match (price, grams) {
        (Some(price), Some(grams)) if grams > 0.0 => Some(price / grams * 1000.0),
        _ => None,
    };
    let price_per_kg = match spool_price {
        Some(_) => per_kg(spool_price, initial_g.or(filament_weight)),
        None => None,
    }
    .or_else(|| per_kg(filament_price, filament_weight));

    let spool = SpoolmanSpool {
        id,
        filament_name: filament.name,
        material: filament.material,
        colour_hex: filament.color_hex,
        brand,
        diameter_mm,
        density_g_cm3,
        initial_g,
        used_g,
        remaining_g,
        price_per_kg,
        archived: raw.archived.unwrap_or(false),
    };
    spool.for_farm().map_err(|e| at(e.to_string()))?;
    Ok(spool)
}

/// Spoolman's explanation in an error answer: its own `{"message": …}`, or FastAPI's
/// `{"detail": …}` (a text, or a list of what failed validation), cut to a readable length.
fn error_message(body: &[u8]) -> Option<String> {
    let value: serde_json::Value = serde_json::from_slice(body).ok()?;
    let text = match (&value["message"], &value["detail"]) {
        (serde_json::Value::String(m), _) => m.clone(),
        (_, serde_json::Value::String(d)) => d.clone(),
        (_, serde_json::Value::Array(items)) => items.first()?["msg"].as_str()?.to_string(),
        _ => return None,
    };
    let text = text.trim();
    (!text.is_empty()).then(|| text.chars().take(MAX_MESSAGE_CHARS).collect())
}

/// A Spoolman server.
#[derive(Debug, Clone)]
pub struct Spoolman {
    url: HttpUrl,
    timeout: Duration,
}

impl Spoolman {
    /// The server at `url`, its base address (`http://127.0.0.1:7912`, or with the path a
    /// proxy serves it under, `https://farm.example/spoolman`); each request, from connecting
    /// to the answer's last byte, takes at most `timeout`.
    pub fn new(url: HttpUrl, timeout: Duration) -> Spoolman {
        Spoolman { url, timeout }
    }

    /// The base address as given.
    pub fn url(&self) -> &str {
        &self.url.text
    }

    /// Whether the server is up and says it is healthy.
    pub async fn health(&self) -> Result<(), SpoolmanError> {
        let (request, body) = self
            .call(hyper::Method::GET, "/api/v1/health", None)
            .await?;
        let value: serde_json::Value =
            serde_json::from_slice(&body).map_err(|e| SpoolmanError::BadAnswer {
                request: request.clone(),
                detail: format!("not JSON ({e})"),
            })?;
        match value["status"].as_str() {
            Some("healthy") => Ok(()),
            other => Err(SpoolmanError::BadAnswer {
                request,
                detail: match other {
                    Some(s) => format!("status is {s:?}, not \"healthy\""),
                    None => "no status".into(),
                },
            }),
        }
    }

    /// Every spool, archived ones too (flagged): Spoolman leaves them out unless asked. A
    /// spool outside the bounds of a spool of the farm's own is set aside with why, and
    /// the others are taken all the same; only an answer that is not a list fails.
    pub async fn spools(&self) -> Result<SpoolList, SpoolmanError> {
        let (request, body) = self
            .call(
                hyper::Method::GET,
                "/api/v1/spool?allow_archived=true",
                None,
            )
            .await?;
        let list: Vec<serde_json::Value> =
            serde_json::from_slice(&body).map_err(|e| SpoolmanError::BadAnswer {
                request: request.clone(),
                detail: format!("not a JSON list of spools ({e})"),
            })?;
        let mut read = SpoolList::default();
        for (i, value) in list.into_iter().enumerate() {
            let spoolman = value["id"].as_u64();
            match spool_from_json(value) {
                Ok(spool) => read.spools.push(spool),
                Err(reason) => read.set_aside.push(SetAside {
                    spoolman,
                    // One without an id is named by its place in the list.
                    reason: match spoolman {
                        Some(_) => reason,
                        None => format!("item {i}: {reason}"),
                    },
                }),
            }
        }
        Ok(read)
    }

    /// Spool `id`; an unknown one is Spoolman's 404.
    pub async fn spool(&self, id: u64) -> Result<SpoolmanSpool, SpoolmanError> {
        let (request, body) = self
            .call(hyper::Method::GET, &format!("/api/v1/spool/{id}"), None)
            .await?;
        one_spool(request, &body, id)
    }

    /// Books `grams` of filament used against spool `id` and returns the spool as it is
    /// now. A print only uses filament, so a negative amount is refused here (Spoolman
    /// would take it as filament given back).
    pub async fn use_weight(&self, id: u64, grams: f64) -> Result<SpoolmanSpool, SpoolmanError> {
        if !(grams >= 0.0) || !grams.is_finite() {
            return Err(SpoolmanError::Amount(grams));
        }
        let body = serde_json::json!({ "use_weight": grams }).to_string();
        let (request, body) = self
            .call(
                hyper::Method::PUT,
                &format!("/api/v1/spool/{id}/use"),
                Some(body.into_bytes()),
            )
            .await?;
        one_spool(request, &body, id)
    }

    /// `path` (under `/api/v1`) on the base address: the base's own path with its query
    /// and trailing slashes left out.
    fn target(&self, path: &str) -> String {
        let base = self.url.path.split('?').next().unwrap_or("");
        format!("{}{path}", base.trim_end_matches('/'))
    }

    /// One request, whole within the time limit: the request's name for errors (method
    /// and path) and a successful answer's body; any other status is an error.
    async fn call(
        &self,
        method: hyper::Method,
        path: &str,
        json: Option<Vec<u8>>,
    ) -> Result<(String, Vec<u8>), SpoolmanError> {
        let target = self.target(path);
        let request = format!("{method} {target}");
        let (status, body) =
            tokio::time::timeout(self.timeout, self.exchange(method, &target, json, &request))
                .await
                .map_err(|_| SpoolmanError::Timeout(self.timeout))??;
        if (200..300).contains(&status) {
            Ok((request, body))
        } else {
            Err(SpoolmanError::Status {
                request,
                status,
                message: error_message(&body),
            })
        }
    }

    async fn exchange(
        &self,
        method: hyper::Method,
        target: &str,
        json: Option<Vec<u8>>,
        name: &str,
    ) -> Result<(u16, Vec<u8>), SpoolmanError> {
        let mut request = crate::outbound::request(&self.url, method, target)
            .header(hyper::header::ACCEPT, "application/json");
        if json.is_some() {
            request = request.header(hyper::header::CONTENT_TYPE, "application/json");
        }
        let request = request
            .body(Full::new(Bytes::from(json.unwrap_or_default())))
            .map_err(|e| SpoolmanError::Http(e.to_string()))?;
        let cap = crate::outbound::Cap::Refuse(MAX_ANSWER_BYTES);
        crate::outbound::send(&self.url, request, cap)
            .await
            .map_err(|e| match (e.connect_failure(), e) {
                (Some(message), _) => SpoolmanError::Connect {
                    host: self.url.host.clone(),
                    port: self.url.port,
                    message,
                },
                (None, crate::outbound::OutboundError::TooLarge(_)) => SpoolmanError::TooLarge {
                    request: name.to_string(),
                },
                (None, e) => SpoolmanError::Http(e.to_string()),
            })
    }
}

/// The spool in an answer about spool `id`.
fn one_spool(request: String, body: &[u8], id: u64) -> Result<SpoolmanSpool, SpoolmanError> {
    let bad = |detail: String| SpoolmanError::BadAnswer {
        request: request.clone(),
        detail,
    };
    let value: serde_json::Value =
        serde_json::from_slice(body).map_err(|e| bad(format!("not JSON ({e})")))?;
    let spool = spool_from_json(value).map_err(bad)?;
    if spool.id != id {
        return Err(bad(format!("it is about spool {}", spool.id)));
    }
    Ok(spool)
}

#[cfg(test)]
mod tests {
    use super::*;
    use serde_json::json;

    /// A spool as Spoolman 0.26 sends it (measured), with its filament and vendor.
    fn measured() -> serde_json::Value {
        json!({
            "id": 1, "registered": "2026-12-04T22:27:52Z",
            "filament": {
                "id": 1, "registered": "2026-12-04T22:27:52Z", "name": "PETG Black",
                "vendor": {"id": 1, "registered": "2026-12-04T22:27:52Z", "name": "Prusament", "extra": {}},
                "material": "PETG", "price": 25.0, "density": 1.27, "diameter": 1.75,
                "weight": 1000.0, "color_hex": "000000", "extra": {}
            },
            "remaining_weight": 900.0, "initial_weight": 1000.0, "used_weight": 100.0,
            "remaining_length": 294627.1805268575, "used_length": 32736.353391873057,
            "archived": false, "extra": {}
        })
    }

    #[test]
    fn a_measured_spool_converts() {
        let s = spool_from_json(measured()).unwrap();
        assert_eq!(
            s,
            SpoolmanSpool {
                id: 1,
                filament_name: Some("PETG Black".into()),
                material: Some("PETG".into()),
                colour_hex: Some("000000".into()),
                brand: Some("Prusament".into()),
                diameter_mm: 1.75,
                density_g_cm3: 1.27,
                initial_g: Some(1000.0),
                used_g: 100.0,
                remaining_g: Some(900.0),
                price_per_kg: Some(25.0),
                archived: false,
            }
        );
        // The farm keeps it as JSON too: it comes back the same.
        let text = serde_json::to_string(&s).unwrap();
        assert_eq!(serde_json::from_str::<SpoolmanSpool>(&text).unwrap(), s);
    }

    /// The spool's own price goes over its own weight (or the filament's when it has none);
    /// without one the filament's price goes over the filament's weight.
    #[test]
    fn price_per_kg_follows_spool_then_filament() {
        let mut v = measured();
        v["price"] = json!(20.0);
        v["initial_weight"] = json!(500.0);
        assert_eq!(spool_from_json(v.clone()).unwrap().price_per_kg, Some(40.0));
        v["initial_weight"] = json!(null);
        assert_eq!(spool_from_json(v.clone()).unwrap().price_per_kg, Some(20.0));
        // No weight to divide by: the filament's own figure.
        v["filament"]["weight"] = json!(0.0);
        v["filament"]["price"] = json!(30.0);
        assert_eq!(spool_from_json(v.clone()).unwrap().price_per_kg, None);
        v["filament"]["weight"] = json!(750.0);
        v["initial_weight"] = json!(0.0);
        assert_eq!(spool_from_json(v.clone()).unwrap().price_per_kg, Some(40.0));
        let mut v = measured();
        v["filament"]["weight"] = json!(250.0);
        v["filament"]["price"] = json!(5.0);
        assert_eq!(spool_from_json(v.clone()).unwrap().price_per_kg, Some(20.0));
        v["filament"].as_object_mut().unwrap().remove("price");
        assert_eq!(spool_from_json(v).unwrap().price_per_kg, None);
    }

    /// The least Spoolman sends (a filament with only its density and diameter): every
    /// optional figure is None, the used weight 0.
    #[test]
    fn missing_fields_are_none_or_defaults() {
        let v = json!({
            "id": 2,
            "filament": {"id": 2, "density": 1.24, "diameter": 1.75, "extra": {}},
            "used_weight": 0.0, "archived": true, "extra": {}
        });
        let s = spool_from_json(v).unwrap();
        assert_eq!(
            s,
            SpoolmanSpool {
                id: 2,
                filament_name: None,
                material: None,
                colour_hex: None,
                brand: None,
                diameter_mm: 1.75,
                density_g_cm3: 1.24,
                initial_g: None,
                used_g: 0.0,
                remaining_g: None,
                price_per_kg: None,
                archived: true,
            }
        );
        let v = json!({"id": 3, "filament": {"density": 1.24, "diameter": 1.75, "vendor": null}});
        let s = spool_from_json(v).unwrap();
        assert_eq!((s.used_g, s.archived, s.brand), (0.0, false, None));
    }

    /// Whatever comes, the answer is an error naming what is wrong, never a panic.
    #[test]
    fn garbage_is_an_error_naming_the_field() {
        let cases: Vec<(serde_json::Value, &str)> = vec![
            (json!(null), "not a spool"),
            (json!([1, 2]), "not a spool"),
            (json!({"filament": {}}), "id"),
            (json!({"id": -1}), "not a spool"),
            (json!({"id": 4}), "spool 4: filament is missing"),
            (
                json!({"id": 4, "filament": "PLA"}),
                "spool 4: filament is not",
            ),
            (
                json!({"id": 4, "filament": {"density": 1.24}}),
                "filament.diameter is missing",
            ),
            (
                json!({"id": 4, "filament": {"density": 0, "diameter": 1.75}}),
                "spool 4: density: 0.5 to 5 g/cm³, got 0",
            ),
            (
                json!({"id": 4, "filament": {"density": "x", "diameter": 1.75}}),
                "spool 4: filament is not",
            ),
            (
                json!({"id": 4, "filament": {"density": 1.2, "diameter": 1.75, "vendor": 7}}),
                "filament.vendor",
            ),
            (
                json!({"id": 4, "filament": {"density": 1.2, "diameter": 1.75}, "used_weight": -3}),
                "spool 4: used_weight: 0 to 100000 g, got -3",
            ),
            (
                json!({"id": 4, "filament": {"density": 1.2, "diameter": 1.75}, "remaining_weight": -0.5}),
                "spool 4: remaining_weight: 0 to 100000 g, got -0.5",
            ),
            (
                json!({"id": 4, "filament": {"density": 1.2, "diameter": 1.75, "price": -1}}),
                "spool 4: filament.price: a price of at least 0, got -1",
            ),
        ];
        for (value, expected) in cases {
            let text = value.to_string();
            let error = spool_from_json(value).unwrap_err();
            assert!(error.contains(expected), "{text}: {error}");
        }
        // A number too large for a double is refused by the JSON reader.
        let huge = r#"{"id": 1, "filament": {"density": 1e999, "diameter": 1.75}}"#;
        let parsed = serde_json::from_str::<serde_json::Value>(huge);
        if let Ok(value) = parsed {
            assert!(spool_from_json(value).is_err());
        }
    }

    /// A spool of Spoolman's is held to the bounds of a spool of the farm's own, by the
    /// same check: its weights, diameter, density, price per kg, colour and names. The
    /// attack run's `remaining_weight: 1e308` and `color_hex: "zzzzzz"` were taken.
    #[test]
    fn a_spool_is_held_to_the_farms_bounds() {
        /// A change made to a measured spool's JSON.
        type Edit<'a> = &'a dyn Fn(&mut serde_json::Value);
        let with = |edit: Edit| {
            let mut v = measured();
            edit(&mut v);
            spool_from_json(v)
        };
        let cases: Vec<(Edit, &str)> = vec![
            (
                &|v| v["remaining_weight"] = json!(1e308),
                "spool 1: remaining_weight: 0 to 100000 g, got 1e308",
            ),
            (
                &|v| v["remaining_weight"] = json!(100_000.5),
                "remaining_weight: 0 to 100000 g, got 100000.5",
            ),
            (
                &|v| v["remaining_weight"] = json!(-50.0),
                "remaining_weight: 0 to 100000 g, got -50",
            ),
            (
                &|v| v["initial_weight"] = json!(1e300),
                "initial_weight: 0 to 100000 g",
            ),
            (
                &|v| v["filament"]["weight"] = json!(-1.0),
                "filament.weight: 0 to 100000 g",
            ),
            (
                &|v| v["filament"]["color_hex"] = json!("zzzzzz"),
                "colour_hex: six hex digits (RRGGBB), got \"zzzzzz\"",
            ),
            (
                &|v| v["filament"]["color_hex"] = json!("12345"),
                "colour_hex: six hex digits",
            ),
            (
                &|v| v["filament"]["color_hex"] = json!("ééé"),
                "colour_hex: six hex digits",
            ),
            (
                &|v| v["filament"]["diameter"] = json!(0.0),
                "diameter_mm: 1 to 3.5 mm, got 0",
            ),
            (
                &|v| v["filament"]["diameter"] = json!(1e308),
                "diameter_mm: 1 to 3.5 mm",
            ),
            (
                &|v| v["filament"]["density"] = json!(1e-9),
                "density: 0.5 to 5 g/cm³",
            ),
            (
                &|v| v["filament"]["price"] = json!(1e12),
                "price_per_kg: 0 to 100000",
            ),
            (
                &|v| v["price"] = json!(-3),
                "price: a price of at least 0, got -3",
            ),
            (
                &|v| v["filament"]["material"] = json!("PLA\u{202e}GTEP"),
                "material: \"PLA\\u{202e}GTEP\" contains characters that reverse",
            ),
            (
                &|v| v["filament"]["material"] = json!("PLA\u{1b}[31m"),
                "material: \"PLA\\u{1b}[31m\" contains control characters",
            ),
            (
                &|v| v["filament"]["material"] = json!("x".repeat(41)),
                "material: 1 to 40 characters",
            ),
            (
                &|v| v["filament"]["vendor"]["name"] = json!("Acme\u{2066}"),
                "brand: \"Acme\\u{2066}\" contains characters that reverse",
            ),
            (
                &|v| v["filament"]["vendor"]["name"] = json!("b".repeat(81)),
                "brand: 1 to 80 characters",
            ),
        ];
        for (edit, expected) in cases {
            let error = with(edit).unwrap_err();
            assert!(error.contains(expected), "{error} (expected {expected})");
        }
        // At the bounds, and Spoolman's own forms: taken.
        let taken: Vec<Edit> = vec![
            &|v| v["remaining_weight"] = json!(100_000.0),
            &|v| v["remaining_weight"] = json!(0.0),
            &|v| v["filament"]["color_hex"] = json!("FF8800CC"),
            &|v| v["filament"]["color_hex"] = json!(null),
            &|v| v["filament"]["material"] = json!("  "),
            &|v| v["filament"]["vendor"]["name"] = json!(""),
            &|v| v["filament"]["material"] = json!("PLA+ Ζ"),
        ];
        for edit in taken {
            let spool = with(edit).unwrap();
            spool.for_farm().unwrap();
        }
        // An eight-digit colour keeps its RRGGBB; a blank material is `unknown`.
        let spool = with(&|v| v["filament"]["color_hex"] = json!("FF8800CC")).unwrap();
        assert_eq!(
            spool.for_farm().unwrap().0.colour_hex.as_deref(),
            Some("ff8800")
        );
        let spool = with(&|v| v["filament"]["material"] = json!(" ")).unwrap();
        assert_eq!(spool.for_farm().unwrap().0.material, "UNKNOWN");
    }

    /// In a list, a spool outside the bounds (or not a spool at all) is set aside with
    /// why, and the rest is taken: one bad spool once failed the whole list.
    #[tokio::test]
    async fn a_bad_spool_is_set_aside_from_the_list_alone() {
        let mut negative = measured();
        negative["id"] = json!(2);
        negative["remaining_weight"] = json!(-5.0);
        let mut third = measured();
        third["id"] = json!(3);
        let list = json!([measured(), negative, {"no": "id"}, third]).to_string();
        let answer = format!(
            "HTTP/1.1 200 OK\r\nContent-Length: {}\r\n\r\n{list}",
            list.len()
        );
        let (spoolman, _request) = one_answer(Some(answer.into_bytes())).await;
        let read = spoolman.spools().await.unwrap();
        let ids: Vec<u64> = read.spools.iter().map(|s| s.id).collect();
        assert_eq!(ids, [1, 3]);
        assert_eq!(read.set_aside.len(), 2, "{:?}", read.set_aside);
        assert_eq!(read.set_aside[0].spoolman, Some(2));
        assert_eq!(
            read.set_aside[0].reason,
            "spool 2: remaining_weight: 0 to 100000 g, got -5"
        );
        assert_eq!(read.set_aside[1].spoolman, None);
        assert!(
            read.set_aside[1].reason.starts_with("item 2: not a spool"),
            "{}",
            read.set_aside[1].reason
        );
    }

    #[test]
    fn error_messages_are_read_from_either_shape() {
        assert_eq!(
            error_message(br#"{"message":"No spool with ID 99 found."}"#).as_deref(),
            Some("No spool with ID 99 found.")
        );
        assert_eq!(
            error_message(
                br#"{"detail":[{"type":"float_parsing","msg":"Input should be a valid number"}]}"#
            )
            .as_deref(),
            Some("Input should be a valid number")
        );
        assert_eq!(
            error_message(br#"{"detail":"Not Found"}"#).as_deref(),
            Some("Not Found")
        );
        for nothing in [
            &b"<html>"[..],
            b"",
            b"[]",
            br#"{"message":""}"#,
            br#"{"detail":[]}"#,
        ] {
            assert_eq!(error_message(nothing), None);
        }
        let long = format!(r#"{{"message":"{}"}}"#, "é".repeat(1000));
        assert_eq!(
            error_message(long.as_bytes()).unwrap().chars().count(),
            MAX_MESSAGE_CHARS
        );
        let e = SpoolmanError::Status {
            request: "GET /api/v1/spool/99".into(),
            status: 404,
            message: Some("No spool with ID 99 found.".into()),
        };
        assert_eq!(
            e.to_string(),
            "Spoolman answered GET /api/v1/spool/99 with HTTP 404: No spool with ID 99 found."
        );
    }

    /// The base address's path is a prefix (a proxy's); its query and trailing slash are
    /// not part of the API's paths.
    #[test]
    fn paths_go_under_the_base_address() {
        let at = |base: &str| {
            let url = HttpUrl::parse(base).unwrap();
            Spoolman::new(url, Duration::from_secs(1)).target("/api/v1/spool/3")
        };
        assert_eq!(at("http://127.0.0.1:7912"), "/api/v1/spool/3");
        assert_eq!(at("http://127.0.0.1:7912/"), "/api/v1/spool/3");
        assert_eq!(at("https://farm/spoolman/"), "/spoolman/api/v1/spool/3");
        assert_eq!(at("https://farm/spoolman?x=1"), "/spoolman/api/v1/spool/3");
    }

    /// A server on a free port of 127.0.0.1 that takes one request, hands its head and body
    /// back, and answers `answer` (nothing at all when None) then keeps the connection open.
    async fn one_answer(
        answer: Option<Vec<u8>>,
    ) -> (Spoolman, tokio::sync::oneshot::Receiver<String>) {
        use tokio::io::{AsyncReadExt, AsyncWriteExt};
        let listener = tokio::net::TcpListener::bind("127.0.0.1:0").await.unwrap();
        let port = listener.local_addr().unwrap().port();
        let (tx, rx) = tokio::sync::oneshot::channel();
        tokio::spawn(async move {
            let (mut socket, _) = listener.accept().await.unwrap();
            let mut request = Vec::new();
            let mut buf = [0u8; 4096];
            // The head, then as much body as its Content-Length says.
            loop {
                let n = socket.read(&mut buf).await.unwrap();
                request.extend_from_slice(&buf[..n]);
                let text = String::from_utf8_lossy(&request).to_string();
                if let Some(end) = text.find("\r\n\r\n") {
                    let length = text
                        .lines()
                        .find_map(|l| {
                            l.to_ascii_lowercase()
                                .strip_prefix("content-length:")
                                .map(|v| v.trim().parse::<usize>().unwrap())
                        })
                        .unwrap_or(0);
                    if n == 0 || request.len() >= end + 4 + length {
                        break;
                    }
                }
                if n == 0 {
                    break;
                }
            }
            let _ = tx.send(String::from_utf8_lossy(&request).into_owned());
            if let Some(answer) = answer {
                let _ = socket.write_all(&answer).await;
            }
            tokio::time::sleep(Duration::from_secs(30)).await;
        });
        let url = HttpUrl::parse(&format!("http://127.0.0.1:{port}/spoolman/")).unwrap();
        (Spoolman::new(url, Duration::from_millis(500)), rx)
    }

    /// The request as Spoolman gets it: under the base path, with Host, User-Agent, and a
    /// JSON body said to be JSON.
    #[tokio::test]
    async fn requests_carry_their_headers_and_body() {
        let spool = measured().to_string();
        let answer = format!(
            "HTTP/1.1 200 OK\r\nContent-Type: application/json\r\nContent-Length: {}\r\n\r\n{spool}",
            spool.len()
        );
        let (spoolman, request) = one_answer(Some(answer.into_bytes())).await;
        let port = spoolman.url.port;
        let s = spoolman.use_weight(1, 12.5).await.unwrap();
        assert_eq!(s.id, 1);
        let request = request.await.unwrap();
        let lower = request.to_ascii_lowercase();
        assert!(
            request.starts_with("PUT /spoolman/api/v1/spool/1/use HTTP/1.1\r\n"),
            "{request}"
        );
        assert!(
            lower.contains(&format!("host: 127.0.0.1:{port}\r\n")),
            "{request}"
        );
        assert!(lower.contains("user-agent: crispen/"), "{request}");
        assert!(
            lower.contains("content-type: application/json\r\n"),
            "{request}"
        );
        assert!(
            request.ends_with("\r\n\r\n{\"use_weight\":12.5}"),
            "{request}"
        );
    }

    /// A server that takes the request and says nothing is a timeout, at the time limit.
    #[tokio::test]
    async fn silence_is_a_timeout() {
        let (spoolman, _request) = one_answer(None).await;
        let started = std::time::Instant::now();
        let e = spoolman.spools().await.unwrap_err();
        assert!(matches!(e, SpoolmanError::Timeout(_)), "{e}");
        assert!(
            started.elapsed() < Duration::from_secs(5),
            "{:?}",
            started.elapsed()
        );
    }

    /// An answer over the cap is refused, whether its length is declared or not.
    #[tokio::test]
    async fn answers_over_the_cap_are_refused() {
        let declared = format!(
            "HTTP/1.1 200 OK\r\nContent-Length: {}\r\n\r\n[",
            MAX_ANSWER_BYTES + 1
        );
        let mut streamed = b"HTTP/1.1 200 OK\r\nConnection: close\r\n\r\n[".to_vec();
        streamed.resize(streamed.len() + MAX_ANSWER_BYTES + 1, b' ');
        for answer in [declared.into_bytes(), streamed] {
            let (mut spoolman, _request) = one_answer(Some(answer)).await;
            spoolman.timeout = Duration::from_secs(20);
            let e = spoolman.spools().await.unwrap_err();
            assert!(matches!(e, SpoolmanError::TooLarge { .. }), "{e}");
        }
    }

    /// An answer that is not Spoolman's JSON is named with the request it answered.
    #[tokio::test]
    async fn a_page_instead_of_json_is_named() {
        let answer = b"HTTP/1.1 200 OK\r\nContent-Length: 6\r\n\r\n<html>".to_vec();
        let (spoolman, _request) = one_answer(Some(answer)).await;
        let e = spoolman.spools().await.unwrap_err().to_string();
        assert!(
            e.contains("GET /spoolman/api/v1/spool?allow_archived=true")
                && e.contains("not a JSON list of spools"),
            "{e}"
        );
    }

    /// Amounts that are not filament used are refused before anything is sent.
    #[tokio::test]
    async fn odd_amounts_are_refused() {
        let url = HttpUrl::parse("http://127.0.0.1:1").unwrap();
        let spoolman = Spoolman::new(url, Duration::from_secs(1));
        for grams in [-1.0, f64::NAN, f64::INFINITY] {
            let e = spoolman.use_weight(1, grams).await.unwrap_err();
            assert!(matches!(e, SpoolmanError::Amount(_)), "{e}");
        }
    }
}
