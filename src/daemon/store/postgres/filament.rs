//! The farm's spools in the database: one document, changed under its row's lock so that
//! hosts loading spools and recording prints at once never overwrite each other.

use super::error::PgError;
use super::lease::PgStore;
use crate::daemon::filament::Inventory;
use crate::daemon::store::InventoryEdit;

impl PgStore {
    /// The farm's spools and which printer holds which.
    pub(crate) async fn inventory(&self) -> Result<Inventory, PgError> {
        let client = self.client().await?;
        let row = client
            .query_opt("SELECT doc FROM filament WHERE id = 1", &[])
            .await?;
        row.map_or(Ok(Inventory::default()), |r| read(r.get(0)))
    }

    /// Applies `edit` to the inventory as the database holds it, in one transaction on its
    /// locked row; returns the inventory as written.
    pub(crate) async fn edit_inventory(
        &self,
        edit: &mut InventoryEdit<'_>,
    ) -> Result<Inventory, PgError> {
        let mut client = self.client().await?;
        let tx = client.transaction().await?;
        tx.execute(
            "INSERT INTO filament (id, doc) VALUES (1, '{}') ON CONFLICT (id) DO NOTHING",
            &[],
        )
        .await?;
        let row = tx
            .query_one("SELECT doc FROM filament WHERE id = 1 FOR UPDATE", &[])
            .await?;
        let mut inventory = read(row.get(0))?;
        let before = inventory.clone();
        edit(&mut inventory).map_err(|e| PgError::Job(e.into()))?;
        if inventory != before {
            let doc = serde_json::to_value(&inventory).map_err(|e| corrupt(e.to_string()))?;
            tx.execute("UPDATE filament SET doc = $1 WHERE id = 1", &[&doc])
                .await?;
        }
        tx.commit().await?;
        Ok(inventory)
    }
}

fn read(doc: serde_json::Value) -> Result<Inventory, PgError> {
    serde_json::from_value(doc).map_err(|e| corrupt(e.to_string()))
}

fn corrupt(message: String) -> PgError {
    PgError::Corrupt {
        id: "(none)".into(),
        what: "the spools' record",
        message,
    }
}
