//! The farm's spools over the API: `GET /api/v1/spools` lists them (with the printer each
//! is on and what is left, and Spoolman's spools set aside with why), `POST /api/v1/spools?material=..&colour=..&grams=..` adds one of
//! the farm's own, `POST /api/v1/printers/{name}/load?spool=s3` (or a new spool's fields)
//! loads one; `unload` is a printer action. The changes are the farm's own commands.

use super::api::{act, bad_query, no_printer};
use super::{ApiError, AppState};
use crate::daemon::control::{self, Command};
use crate::daemon::spools::{Load, NewSpool};
use axum::extract::rejection::QueryRejection;
use axum::extract::{Path, Query, State};
use axum::Json;
use serde::{Deserialize, Serialize};

/// One spool as the API shows it.
#[derive(Debug, Serialize)]
pub(crate) struct SpoolView {
    pub id: String,
    #[serde(flatten)]
    pub filament: crate::daemon::filament::Filament,
    pub remaining_g: Option<f64>,
    /// The printer it is on.
    pub loaded_on: Option<String>,
    /// Spoolman's id, when the spool is Spoolman's.
    pub spoolman: Option<u64>,
    /// Prints booked to it that Spoolman has not counted yet.
    pub unreported: usize,
    pub archived: bool,
}

#[derive(Debug, Serialize)]
pub(crate) struct SpoolsView {
    /// `spoolman` (its spools, read every `[spoolman] poll_s`) or `crispen` (its own).
    pub source: &'static str,
    pub spools: Vec<SpoolView>,
    /// Spoolman's spools not taken at its last read, each with why (`id`: `sm<id>`,
    /// absent for an item that is not even a spool).
    pub set_aside: Vec<SetAsideView>,
}

/// A spool of Spoolman's the farm did not take.
#[derive(Debug, Serialize)]
pub(crate) struct SetAsideView {
    pub id: Option<String>,
    pub spoolman: Option<u64>,
    pub reason: String,
}

#[derive(Debug, Deserialize)]
pub(crate) struct SpoolsQuery {
    /// Archived spools too.
    #[serde(default)]
    archived: bool,
}

/// `GET /api/v1/spools[?archived=true]`.
pub(crate) async fn list(
    State(state): State<AppState>,
    query: Result<Query<SpoolsQuery>, QueryRejection>,
) -> Result<Json<SpoolsView>, ApiError> {
    let Query(query) = query.map_err(bad_query)?;
    let store = state.farm.store();
    let inventory = store.inventory();
    let spools = inventory
        .spools
        .values()
        .filter(|s| query.archived || !s.archived)
        .map(|s| SpoolView {
            id: s.id.clone(),
            filament: s.filament.clone(),
            remaining_g: s.remaining_g(),
            loaded_on: inventory.holder(&s.id).map(str::to_string),
            spoolman: s.spoolman,
            unreported: s
                .uses
                .values()
                .filter(|u| {
                    matches!(
                        u.report,
                        crate::daemon::filament::Report::Pending
                            | crate::daemon::filament::Report::Sending { .. }
                    )
                })
                .count(),
            archived: s.archived,
        })
        .collect();
    let source = if state.farm.config().spoolman.is_some() {
        "spoolman"
    } else {
        "crispen"
    };
    let set_aside = inventory
        .set_aside
        .iter()
        .map(|a| SetAsideView {
            id: a.id(),
            spoolman: a.spoolman,
            reason: a.reason.clone(),
        })
        .collect();
    Ok(Json(SpoolsView {
        source,
        spools,
        set_aside,
    }))
}

/// A new spool's fields, or an existing spool's id (`load` only).
#[derive(Debug, Default, Deserialize)]
#[serde(deny_unknown_fields)]
pub(crate) struct SpoolQuery {
    spool: Option<String>,
    material: Option<String>,
    colour: Option<String>,
    colour_hex: Option<String>,
    brand: Option<String>,
    diameter_mm: Option<f64>,
    density_g_cm3: Option<f64>,
    price_per_kg: Option<f64>,
    grams: Option<f64>,
}

impl SpoolQuery {
    fn new_spool(self) -> Result<NewSpool, ApiError> {
        let missing = |key: &str| {
            ApiError::bad_request(format!(
                "a new spool needs `{key}` (material, colour and grams; or `spool=<id>` to load one the farm knows)"
            ))
        };
        Ok(NewSpool {
            material: self.material.ok_or_else(|| missing("material"))?,
            colour: self.colour.ok_or_else(|| missing("colour"))?,
            grams: self.grams.ok_or_else(|| missing("grams"))?,
            colour_hex: self.colour_hex,
            brand: self.brand,
            diameter_mm: self.diameter_mm,
            density_g_cm3: self.density_g_cm3,
            price_per_kg: self.price_per_kg,
        })
    }
}

/// `POST /api/v1/spools?material=PETG&colour=black&grams=750[&price_per_kg=25...]`.
pub(crate) async fn add(
    State(state): State<AppState>,
    query: Result<Query<SpoolQuery>, QueryRejection>,
) -> Result<Json<serde_json::Value>, ApiError> {
    let Query(query) = query.map_err(bad_query)?;
    if query.spool.is_some() {
        return Err(ApiError::bad_request(
            "`spool` names a spool to load (POST /api/v1/printers/{name}/load); adding one takes its material, colour and grams",
        ));
    }
    act(&state, Command::AddSpool(query.new_spool()?)).await
}

/// `POST /api/v1/printers/{name}/load?spool=s3`, or with a new spool's fields.
pub(crate) async fn load(
    State(state): State<AppState>,
    Path(name): Path<String>,
    query: Result<Query<SpoolQuery>, QueryRejection>,
) -> Result<Json<serde_json::Value>, ApiError> {
    let Query(mut query) = query.map_err(bad_query)?;
    if !control::printer_names(&state.farm).contains(&name) {
        return Err(no_printer(&state.farm, &name));
    }
    let what = match query.spool.take() {
        Some(id) => Load::Spool(id),
        None => Load::New(query.new_spool()?),
    };
    act(
        &state,
        Command::Load {
            printer: name,
            what,
        },
    )
    .await
}
