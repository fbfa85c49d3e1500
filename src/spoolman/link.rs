//! The farm's link to Spoolman (`[spoolman] url`): its spools are read into the farm's
//! inventory every `poll_s`, and each print's use is booked to its spool there once.
//!
//! Once, across retries and restarts: a use is in the spool's ledger (the job store's, on
//! disk or in the farm database) before it is sent. It is marked `sending` with Spoolman's
//! `used_weight` as it was just before, then sent, then marked `sent` with the weight
//! Spoolman answered. A use found `sending` (the daemon stopped, or the answer was lost,
//! between the two marks) is looked up first: if Spoolman's `used_weight` has grown by it
//! since, it counted and is only marked; else it is sent. (Another client booking the same
//! spool in that window could be mistaken for it; crispen's printer is the spool's only
//! user while it holds it.) A use Spoolman cannot be told now stays pending and is tried
//! at the next round; nothing is dropped.

use super::{Spoolman, SpoolmanError};
use crate::daemon::farm::Farm;
use crate::daemon::filament::{Report, SetAside};
use crate::daemon::store::InventoryChange;
use std::sync::Arc;
use tokio_util::sync::CancellationToken;

/// Runs the link until `stop` (a daemon without `[spoolman]` has none: it waits).
pub async fn run(farm: Arc<Farm>, stop: CancellationToken) {
    let Some(config) = farm.config().spoolman.clone() else {
        stop.cancelled().await;
        return;
    };
    let client = Spoolman::new(config.url, config.timeout);
    let mut changes = farm.jobs().subscribe();
    let mut failing: Option<String> = None;
    tracing::info!(
        url = client.url(),
        "reading the farm's spools from Spoolman"
    );
    'run: loop {
        let round = async {
            report(&farm, &client).await?;
            read(&farm, &client).await
        };
        let outcome = tokio::select! {
            outcome = round => outcome,
            () = stop.cancelled() => break 'run,
        };
        // Said once when it starts failing and once when it works again, not every round.
        match (outcome, &failing) {
            (Ok(()), Some(_)) => {
                tracing::info!(url = client.url(), "Spoolman answers again");
                failing = None;
            }
            (Err(e), None) => {
                tracing::warn!(url = client.url(), error = %e, "cannot read the farm's spools from Spoolman; they stay as last read and uses are kept until it answers");
                failing = Some(e.to_string());
            }
            _ => {}
        }
        // Until the next poll, or until a print's use waits to be told.
        let poll = tokio::time::sleep(config.poll);
        tokio::pin!(poll);
        loop {
            tokio::select! {
                () = &mut poll => break,
                () = stop.cancelled() => break 'run,
                changed = changes.changed() => {
                    if changed.is_err() {
                        stop.cancelled().await;
                        break 'run;
                    }
                    let waiting = !changes.borrow_and_update().inventory().unreported().is_empty();
                    if waiting && failing.is_none() {
                        break;
                    }
                }
            }
        }
    }
    // The daemon stops after its prints: their last uses are told now if Spoolman
    // answers in time, else at the next start.
    let last = tokio::time::timeout(config.timeout * 4, report(&farm, &client)).await;
    if !matches!(last, Ok(Ok(()))) {
        tracing::warn!("not every print's use was told to Spoolman before the stop; they are told at the next start");
    }
}

/// Takes in Spoolman's spools; each one set aside is logged once, when it first is.
async fn read(farm: &Farm, client: &Spoolman) -> Result<(), LinkError> {
    let list = client.spools().await?;
    let mut spools = Vec::new();
    let mut set_aside = list.set_aside;
    for s in list.spools {
        // Checked as it was read: this cannot fail, and would be set aside if it did.
        match s.for_farm() {
            Ok((filament, remaining)) => spools.push((s.id, filament, remaining, s.archived)),
            Err(e) => set_aside.push(SetAside {
                spoolman: Some(s.id),
                reason: format!("spool {}: {e}", s.id),
            }),
        }
    }
    let before = farm.store().inventory().set_aside.clone();
    for aside in set_aside.iter().filter(|a| !before.contains(a)) {
        tracing::warn!(
            url = client.url(),
            spool = aside.id().as_deref().unwrap_or("-"),
            reason = %crate::names::escaped(&aside.reason),
            "a spool of Spoolman's is set aside: it is outside the bounds of a spool of the farm's own; the others are taken (correct it in Spoolman)"
        );
    }
    farm.jobs()
        .edit_inventory(InventoryChange::Spoolman { spools, set_aside })
        .await?;
    Ok(())
}

/// Tells Spoolman each use it has not counted yet (see the module).
async fn report(farm: &Farm, client: &Spoolman) -> Result<(), LinkError> {
    let unreported = farm.store().inventory().unreported();
    for (spool, key, id, usage) in unreported {
        // A spool deleted from Spoolman cannot be booked to: said, and not tried again.
        let now = match client.spool(id).await {
            Err(SpoolmanError::Status { status: 404, .. }) => {
                tracing::error!(spool = %spool, job = %usage.job, grams = usage.grams, "the spool is gone from Spoolman: this use is not booked anywhere");
                mark(farm, &spool, &key, Report::Sent, None).await?;
                continue;
            }
            // A spool outside the farm's bounds (set aside at the read, and logged then):
            // its uses wait until it is corrected; the other spools' go on.
            Err(e @ SpoolmanError::BadAnswer { .. }) => {
                tracing::debug!(spool = %spool, job = %usage.job, error = %e, "a use waits: its spool's answer is not taken");
                continue;
            }
            other => other?,
        };
        let before = match usage.report {
            Report::Sending { used_before_g } => {
                if now.used_g + 1e-6 >= used_before_g + usage.grams {
                    tracing::info!(spool = %spool, key = %key, "Spoolman had counted this use before the daemon stopped; marked");
                    mark(farm, &spool, &key, Report::Sent, now.remaining_g).await?;
                    continue;
                }
                now.used_g
            }
            _ => {
                mark(
                    farm,
                    &spool,
                    &key,
                    Report::Sending {
                        used_before_g: now.used_g,
                    },
                    None,
                )
                .await?;
                now.used_g
            }
        };
        let after = match client.use_weight(id, usage.grams).await {
            // Booked, but the spool's answer is outside the farm's bounds (used past its
            // weight): the use stays `sending`, and is found counted once it is corrected.
            Err(e @ SpoolmanError::BadAnswer { .. }) => {
                tracing::warn!(spool = %spool, job = %usage.job, error = %e, "filament use told to Spoolman; its answer is not taken");
                continue;
            }
            other => other?,
        };
        tracing::info!(
            spool = %spool,
            job = %usage.job,
            printer = %usage.printer,
            grams = usage.grams,
            used_before_g = before,
            remaining_g = after.remaining_g,
            "filament use told to Spoolman"
        );
        mark(farm, &spool, &key, Report::Sent, after.remaining_g).await?;
    }
    Ok(())
}

async fn mark(
    farm: &Farm,
    spool: &str,
    key: &str,
    report: Report,
    remaining_g: Option<f64>,
) -> Result<(), LinkError> {
    farm.jobs()
        .edit_inventory(InventoryChange::Reported {
            spool: spool.to_string(),
            key: key.to_string(),
            report,
            remaining_g,
        })
        .await?;
    Ok(())
}

#[derive(Debug, thiserror::Error)]
enum LinkError {
    #[error(transparent)]
    Spoolman(#[from] SpoolmanError),
    #[error("the job store: {0}")]
    Store(#[from] crate::daemon::job::StoreError),
}
