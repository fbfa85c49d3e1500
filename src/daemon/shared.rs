//! This host's part in a farm shared through PostgreSQL (`[store] postgres`): one task
//! that renews the host's lease, applies the expiry rules to hosts that stopped renewing
//! theirs, takes in the other hosts' changes of jobs and bed gates, publishes this host's
//! printers (status and machine) and reads everyone else's, and carries out the commands
//! other hosts left for this host's printers (pause, resume, cancel).
//!
//! While the database is unreachable the task keeps trying; the status says so, prints in
//! progress go on, and nothing new is claimed (every claim needs the database).
//!
//! A run whose host's name was taken over by another run ([`PgError::Displaced`]: its
//! lease lapsed, say during a long outage, and a new run under the same name started)
//! stops here for good: it publishes, renews and carries out nothing more, its store
//! refuses every change, and its status and log say why. Its prints in progress go on
//! (stopping them would not help the printers); their outcomes are not recorded.

use super::control;
use super::farm::{Farm, FarmView, PrintCommand, PrinterStatus, SharedOwner, UnknownCommand};
use super::store::postgres::{PgError, PgStore};
use std::sync::Arc;
use std::time::Duration;
use tokio_util::sync::CancellationToken;

/// How often the other hosts' changes are read and this host's printers published.
const TICK: Duration = Duration::from_secs(1);

/// Runs until `stop`; `lease` is `[store] lease_s`.
/// `owner`: the view of the rest of the farm is this task's to show.
pub(crate) async fn run(
    farm: Arc<Farm>,
    owner: SharedOwner,
    db: PgStore,
    lease: Duration,
    stop: CancellationToken,
) {
    let heartbeat_every = lease / 5;
    let mut last_heartbeat: Option<tokio::time::Instant> = None;
    let mut ticker = tokio::time::interval(TICK);
    ticker.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Delay);
    loop {
        tokio::select! {
            _ = stop.cancelled() => break,
            _ = ticker.tick() => {}
        }
        let due = last_heartbeat.is_none_or(|t| t.elapsed() >= heartbeat_every);
        let outcome = tokio::select! {
            _ = stop.cancelled() => break,
            outcome = tick(&farm, &owner, &db, lease, due) => outcome,
        };
        match outcome {
            Ok(()) => {
                if due {
                    last_heartbeat = Some(tokio::time::Instant::now());
                }
                set_database(&farm, &owner, None);
            }
            Err(e @ PgError::Displaced { .. }) => {
                tracing::error!(host = %db.host(), "{e}");
                owner.set(|view| view.database = Some(e.to_string()));
                return;
            }
            Err(e) => set_database(&farm, &owner, Some(e.to_string())),
        }
    }
}

/// One round; fails at the first call the database does not answer.
async fn tick(
    farm: &Arc<Farm>,
    owner: &SharedOwner,
    db: &PgStore,
    lease: Duration,
    heartbeat: bool,
) -> Result<(), PgError> {
    let config = farm.config();
    if heartbeat {
        db.heartbeat(lease).await?;
        for p in &config.printers {
            let machine = serde_json::to_value(&p.machine).ok();
            db.register_printer(&p.name, machine.as_ref()).await?;
        }
        let expired = db.expire_hosts().await?;
        for host in &expired.hosts {
            tracing::warn!(host = %host, "a host of the farm stopped renewing its lease: its printers are offline, its work is handed back");
        }
        for id in &expired.requeued {
            tracing::warn!(job = %id, "its host is gone: back in the queue for preparation");
        }
        for id in &expired.interrupted {
            tracing::warn!(job = %id, "its host is gone during the print: interrupted (never reprinted on its own; `crispen retry` it once the printer is checked)");
        }
    }
    db.publish_printers(&published(farm)).await?;
    let printers = db.printers().await?;
    let hosts = db.hosts().await?;
    for (printer, command) in db.take_commands().await? {
        let Some(command) = to_carry_out(&printer, command) else {
            continue;
        };
        match control::send_print_command(farm, &printer, command).await {
            Ok(done) => tracing::info!(printer = %printer, "from another host: {done}"),
            Err(e) => {
                tracing::warn!(printer = %printer, error = %e, "a command from another host could not be carried out")
            }
        }
    }
    let mut view = FarmView::default();
    for p in printers {
        if p.host == config.farm.host {
            continue;
        }
        if let Some(machine) = p.machine.and_then(|m| serde_json::from_value(m).ok()) {
            view.machines.push((p.name.clone(), machine));
        }
        let mut status: PrinterStatus = match p.status.map(serde_json::from_value) {
            Some(Ok(status)) => status,
            _ => continue,
        };
        // The row's own columns are the farm's record of these (the status is as its host
        // last published it, up to a tick ago); its bed gate is the store's.
        status.host = Some(p.host);
        status.offline = p.offline;
        status.bed_cleared = !p.bed_not_cleared;
        let gate = farm.store().gate(&p.name);
        status.bed = gate.bed;
        status.last_check = gate.last_check;
        view.printers.push(status);
    }
    view.hosts = hosts;
    // Whether the database answers is `set_database`'s to change (and log).
    owner.set(|shown| {
        view.database = shown.database.take();
        *shown = view;
    });
    if let Err(e) = farm.jobs().resync().await {
        tracing::warn!(error = %e, "cannot take in the other hosts' changes");
    }
    Ok(())
}

/// This host's printers as published to the farm database, by name: as `crispen status`
/// shows them here (their bed gates as the store has them now).
fn published(farm: &Farm) -> Vec<(String, serde_json::Value)> {
    farm.local_printers()
        .iter()
        .filter_map(|p| Some((p.name.clone(), serde_json::to_value(p).ok()?)))
        .collect()
}

/// The command from another host to carry out, or None for one this host does not know
/// (a newer host's, a hand-written row): that one is logged and refused, its row already
/// taken out of the table, and the print goes on.
fn to_carry_out(
    printer: &str,
    command: Result<PrintCommand, UnknownCommand>,
) -> Option<PrintCommand> {
    match command {
        Ok(command) => Some(command),
        Err(e) => {
            tracing::error!(printer = %printer, command = %e.text.escape_debug(), "refused a command from another host: {e}");
            None
        }
    }
}

/// Records whether the database answers, logging each change once (the printers waiting
/// for a job follow it: claims that failed meanwhile are tried again).
fn set_database(farm: &Farm, owner: &SharedOwner, error: Option<String>) {
    let was = farm.shared().and_then(|v| v.database);
    match (&was, &error) {
        (None, Some(e)) => {
            tracing::error!(error = %e, "the farm database is unreachable: prints in progress go on, nothing new is taken until it is back")
        }
        (Some(_), None) => tracing::info!("the farm database answers again"),
        _ => {}
    }
    owner.set(|view| view.database = error);
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A command word this host does not know is refused, never carried out as a cancel
    /// (it once was, stopping the print); the known ones are carried out as themselves.
    #[test]
    fn an_unknown_command_from_another_host_is_refused() {
        for word in ["stop", "CANCEL", "pause\n"] {
            assert_eq!(
                to_carry_out("p1", PrintCommand::parse(word, None)),
                None,
                "{word:?}"
            );
        }
        for c in [
            PrintCommand::Pause,
            PrintCommand::Resume,
            PrintCommand::Cancel,
            PrintCommand::CancelPart("a".into()),
        ] {
            assert_eq!(
                to_carry_out("p1", PrintCommand::parse(c.word(), c.part())),
                Some(c)
            );
        }
    }

    /// What this host publishes of its printers to the farm database shows each bed gate
    /// as it is now: closed after a print, open after a clear. It once published a value
    /// set when the printer started (always "cleared"), which other hosts then corrected
    /// from another column.
    #[tokio::test]
    async fn the_published_bed_gate_is_the_current_one() {
        use crate::daemon::doubles::{farm_config, open_farm};
        use crate::daemon::farm::{printer_channels, PrinterLive};
        let tmp = tempfile::tempdir().unwrap();
        let (farm, owners) = open_farm(farm_config(tmp.path(), &["p1"], ""));
        let (_owner, handle) = printer_channels(PrinterLive::connecting("marlin2", "/dev/x"));
        owners.printers.add("p1", handle);
        let bed_cleared = |farm: &Farm| {
            let published = published(farm);
            assert_eq!(published.len(), 1);
            assert_eq!(published[0].0, "p1");
            published[0].1["bed_cleared"].as_bool().unwrap()
        };
        assert!(bed_cleared(&farm));
        farm.jobs().close_gate("p1", "0001-a").await.unwrap();
        assert!(!bed_cleared(&farm), "a finished print waits on the bed");
        farm.jobs().clear_gate("p1").await.unwrap();
        assert!(bed_cleared(&farm));
    }

    /// A store error from the farm database keeps whether the database was out of reach
    /// (the callers wait for it) or answered with a fault; it was once only a message.
    #[test]
    fn a_database_error_keeps_whether_it_is_an_outage() {
        use crate::daemon::job::StoreError;
        let out: StoreError = PgError::Unreachable("connection refused".into()).into();
        assert!(out.is_outage(), "{out}");
        let fault: StoreError = PgError::Corrupt {
            id: "0001-a".into(),
            what: "state",
            message: "no such state \"melted\"".into(),
        }
        .into();
        assert!(!fault.is_outage(), "{fault}");
        assert!(fault.to_string().contains("melted"), "{fault}");
    }
}
