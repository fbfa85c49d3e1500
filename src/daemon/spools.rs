//! The operator's spool commands: load a spool on a printer (one the farm knows, or a new
//! one), unload it, add a spool to the farm's own inventory. Each is one change of the
//! inventory by the job store's task, checked there against the inventory as it is.

use super::done::Done;
use super::farm::Farm;
use super::filament::{check_filament, check_grams, Filament, FilamentError};
use super::job::{JobState, StoreError};
use super::store::InventoryChange;

/// A spool the operator describes (what `crispen load --material ...` and the dashboard's
/// "new spool" send). What is left out comes from the printer's machine (diameter) and the
/// material's preset (density).
#[derive(Debug, Clone, PartialEq, Default, serde::Deserialize)]
#[serde(deny_unknown_fields)]
pub struct NewSpool {
    pub material: String,
    pub colour: String,
    pub colour_hex: Option<String>,
    pub brand: Option<String>,
    pub diameter_mm: Option<f64>,
    pub density_g_cm3: Option<f64>,
    pub price_per_kg: Option<f64>,
    pub grams: f64,
}

impl NewSpool {
    fn filament(&self, diameter_mm: f64) -> Result<Filament, FilamentError> {
        check_filament(Filament {
            material: self.material.clone(),
            colour: self.colour.clone(),
            colour_hex: self.colour_hex.clone(),
            brand: self.brand.clone(),
            diameter_mm: self.diameter_mm.unwrap_or(diameter_mm),
            density_g_cm3: self
                .density_g_cm3
                .unwrap_or_else(|| crate::slice::density_of(&self.material)),
            price_per_kg: self.price_per_kg,
        })
    }
}

/// What to load.
#[derive(Debug, Clone, PartialEq)]
pub enum Load {
    /// A spool the farm knows, by id (`s3`, or `sm12` for Spoolman's spool 12).
    Spool(String),
    New(NewSpool),
}

/// Loads a spool on `printer` (this host's or, in a shared farm, another's: the inventory
/// is the farm's). Refused while the printer prints: its print's filament is booked to
/// the spool it started with.
pub(crate) async fn load(farm: &Farm, printer: &str, what: Load) -> Result<Done, StoreError> {
    if let Load::Spool(id) = &what {
        if let Some(problem) = crate::names::problem(id) {
            let id = crate::names::printable(id);
            return Err(FilamentError::Invalid(format!("spool \"{id}\": {problem}")).into());
        }
    }
    let diameter = machine_filament(farm, printer)?;
    check_not_printing(farm, printer)?;
    let spoolman = farm.config().spoolman.is_some();
    // A new spool checked before it reaches the store.
    let printer_name = printer.to_string();
    let change = match what {
        Load::New(n) if spoolman => {
            return Err(FilamentError::Invalid(format!(
                "the farm's spools come from Spoolman: add the {} {} spool there, then load it by its id (sm<id>)",
                n.material, n.colour
            ))
            .into())
        }
        Load::New(n) => InventoryChange::AddAndLoad {
            printer: printer_name,
            filament: n.filament(diameter)?,
            grams: check_grams(n.grams)?,
        },
        Load::Spool(spool) => InventoryChange::Load {
            printer: printer_name,
            spool,
        },
    };
    let inventory = farm.jobs().edit_inventory(change).await?;
    let spool = inventory
        .spool_on(printer)
        .map_or_else(String::new, |s| s.describe());
    tracing::info!(printer, spool = %spool, "spool loaded");
    Ok(Done::Loaded {
        printer: printer.to_string(),
        spool,
    })
}

/// Takes the spool off `printer`: it holds nothing, and takes no job, until one is loaded.
pub(crate) async fn unload(farm: &Farm, printer: &str) -> Result<Done, StoreError> {
    machine_filament(farm, printer)?;
    check_not_printing(farm, printer)?;
    farm.jobs()
        .edit_inventory(InventoryChange::Unload {
            printer: printer.to_string(),
        })
        .await?;
    tracing::info!(printer, "spool unloaded");
    Ok(Done::Unloaded {
        printer: printer.to_string(),
    })
}

/// Adds a spool of the farm's own, loaded nowhere; its id.
pub(crate) async fn add(farm: &Farm, new: NewSpool) -> Result<Done, StoreError> {
    if farm.config().spoolman.is_some() {
        return Err(FilamentError::Invalid(
            "the farm's spools come from Spoolman: add the spool there".into(),
        )
        .into());
    }
    // Without a printer to take it from, the diameter is the farm's first machine's.
    let diameter = farm
        .config()
        .printers
        .first()
        .map_or(1.75, |p| p.machine.filament_mm);
    let filament = new.filament(diameter)?;
    let grams = check_grams(new.grams)?;
    let inventory = farm
        .jobs()
        .edit_inventory(InventoryChange::Add { filament, grams })
        .await?;
    // Ids are handed out in order: the newest is the one just added.
    let id = format!("s{}", inventory.next_id);
    tracing::info!(spool = %id, "spool added");
    Ok(Done::SpoolAdded { id, grams })
}

/// The filament diameter `printer`'s machine takes (the caller has checked the printer is
/// the farm's; one whose machine is not known yet is refused).
fn machine_filament(farm: &Farm, printer: &str) -> Result<f64, StoreError> {
    if let Some(p) = farm.config().printers.iter().find(|p| p.name == printer) {
        return Ok(p.machine.filament_mm);
    }
    // Another host's printer in a shared farm: its machine as it registered it.
    farm.printer_machines()
        .into_iter()
        .find(|(n, _)| n == printer)
        .map(|(_, m)| m.filament_mm)
        .ok_or_else(|| {
            FilamentError::Invalid(format!(
                "{printer}: its machine is not known yet (its host has not registered it)"
            ))
            .into()
        })
}

fn check_not_printing(farm: &Farm, printer: &str) -> Result<(), StoreError> {
    let store = farm.store();
    let printing = store
        .jobs()
        .find(|j| j.state == JobState::Printing && j.printer.as_deref() == Some(printer))
        .map(|j| j.id.clone());
    match printing {
        Some(id) => Err(FilamentError::Invalid(format!(
            "{printer} is printing job {id}: change its spool once the print has ended (the print's filament is booked to the spool it started with)"
        ))
        .into()),
        None => Ok(()),
    }
}
