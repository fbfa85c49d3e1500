//! The farm's printers in the database: registered by their host, their live status
//! published, their bed gates set and read by any host, and the whole farm's list. Apart
//! from the jobs: a printer's row changes with its host's doings, not a job's.

use super::error::PgError;
use super::lease::PgStore;
use crate::daemon::job::PrinterGate;
use std::collections::BTreeMap;

/// The gate in a row's columns from `at`: `bed_not_cleared`, `last_job`, `bed`,
/// `last_check` (a row written before beds had states reads as waiting or clear).
fn gate_of(row: &tokio_postgres::Row, at: usize) -> PrinterGate {
    let file = serde_json::json!({
        "bed_not_cleared": row.get::<_, bool>(at),
        "last_job": row.get::<_, Option<String>>(at + 1),
        "bed": row.get::<_, Option<serde_json::Value>>(at + 2),
        "last_check": row.get::<_, Option<serde_json::Value>>(at + 3),
    });
    serde_json::from_value(file).unwrap_or_else(|e| {
        // A bed of a newer crispen's: waiting is the safe reading.
        tracing::warn!(error = %e, "a printer's bed in the farm database cannot be read; it waits for a person");
        PrinterGate {
            bed: crate::daemon::bed::Bed::Waiting { why: None },
            last_job: row.get(at + 1),
            last_check: None,
        }
    })
}

/// A printer as the whole farm sees it.
#[derive(Debug, Clone, PartialEq)]
pub struct FarmPrinter {
    pub name: String,
    pub host: String,
    pub bed_not_cleared: bool,
    pub last_job: Option<String>,
    /// The host's lease has run out: the printer is offline since `last_seen_s`.
    pub offline: bool,
    pub last_seen_s: f64,
    /// What its host last published: its live status and its machine (JSON).
    pub status: Option<serde_json::Value>,
    pub machine: Option<serde_json::Value>,
}

impl PgStore {
    /// Registers (or moves to this host) one of this host's printers, with its machine.
    pub async fn register_printer(
        &self,
        name: &str,
        machine: Option<&serde_json::Value>,
    ) -> Result<(), PgError> {
        let client = self.client().await?;
        client
            .execute(
                "INSERT INTO printers (name, host, machine) SELECT $1::text, $2::text, $3::jsonb \
                 WHERE EXISTS (SELECT 1 FROM hosts WHERE name = $2 AND token = $4) \
                 ON CONFLICT (name) DO UPDATE SET host = EXCLUDED.host, \
                 machine = EXCLUDED.machine, last_seen = now()",
                &[&name, &self.host, &machine, &self.token],
            )
            .await?;
        Ok(())
    }

    /// Publishes the live status of this host's printers (JSON, by name).
    pub(crate) async fn publish_printers(
        &self,
        statuses: &[(String, serde_json::Value)],
    ) -> Result<(), PgError> {
        // One statement for all of them: this runs every second on every host.
        let (names, statuses): (Vec<&String>, Vec<&serde_json::Value>) =
            statuses.iter().map(|(n, s)| (n, s)).unzip();
        let client = self.client().await?;
        client
            .execute(
                "UPDATE printers p SET status = v.status, last_seen = now() \
                 FROM unnest($1::text[], $2::jsonb[]) AS v(name, status) \
                 WHERE p.name = v.name AND p.host = $3 \
                 AND EXISTS (SELECT 1 FROM hosts WHERE name = $3 AND token = $4)",
                &[&names, &statuses, &self.host, &self.token],
            )
            .await?;
        Ok(())
    }

    /// Sets a printer's bed gate (any host's printer: an operator clears beds farm-wide).
    pub(crate) async fn set_gate(&self, printer: &str, gate: &PrinterGate) -> Result<(), PgError> {
        let mut client = self.client().await?;
        let tx = client.transaction().await?;
        self.check_token(&tx).await?;
        let bed = serde_json::to_value(&gate.bed).expect("a bed serialises");
        let check = gate
            .last_check
            .as_ref()
            .map(|c| serde_json::to_value(c).expect("a check serialises"));
        tx.execute(
            "INSERT INTO printers (name, host, bed_not_cleared, last_job, bed, last_check) \
                 VALUES ($1, $2, $3, $4, $5, $6) ON CONFLICT (name) DO UPDATE \
                 SET bed_not_cleared = EXCLUDED.bed_not_cleared, last_job = EXCLUDED.last_job, \
                 bed = EXCLUDED.bed, last_check = EXCLUDED.last_check",
            &[
                &printer,
                &self.host,
                &gate.bed_not_cleared(),
                &gate.last_job,
                &bed,
                &check,
            ],
        )
        .await?;
        tx.commit().await?;
        Ok(())
    }

    /// Every printer's bed gate.
    pub(crate) async fn gates(&self) -> Result<BTreeMap<String, PrinterGate>, PgError> {
        let client = self.client().await?;
        let rows = client
            .query(
                "SELECT name, bed_not_cleared, last_job, bed, last_check FROM printers",
                &[],
            )
            .await?;
        Ok(rows.iter().map(|r| (r.get(0), gate_of(r, 1))).collect())
    }

    /// Every printer of the farm, with whether its host is offline.
    pub async fn printers(&self) -> Result<Vec<FarmPrinter>, PgError> {
        let client = self.client().await?;
        let rows = client
            .query(
                "SELECT p.name, p.host, p.bed_not_cleared, p.last_job, \
                 h.lease_until < now(), extract(epoch FROM p.last_seen)::float8, \
                 p.status, p.machine \
                 FROM printers p JOIN hosts h ON h.name = p.host ORDER BY p.name",
                &[],
            )
            .await?;
        Ok(rows
            .iter()
            .map(|r| FarmPrinter {
                name: r.get(0),
                host: r.get(1),
                bed_not_cleared: r.get(2),
                last_job: r.get(3),
                offline: r.get(4),
                last_seen_s: r.get(5),
                status: r.get(6),
                machine: r.get(7),
            })
            .collect())
    }
}
