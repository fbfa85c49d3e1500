//! A host's handle on the farm database and its lease: connecting (the schema migrated,
//! the host's row taken with this run's token), renewing, giving up and expiring leases,
//! and the restart rules for the work of a host that stopped. Apart from the jobs'
//! changes, which only check the token this file's [`PgStore`] holds.

use super::error::PgError;
use super::rows::ids;
use super::schema;
use crate::daemon::config::{parse_conninfo, ConninfoError, PgSettings};
use crate::daemon::job::JobState;
use std::time::Duration;

/// A host's handle on the farm database: a small pool of connections, its own name, and
/// this run's token in the host's row.
#[derive(Clone)]
pub struct PgStore {
    pub(super) pool: deadpool_postgres::Pool,
    pub(super) host: String,
    pub(super) token: String,
    /// Set once the host's row was found to hold another run's token: every call fails.
    pub(super) displaced: std::sync::Arc<std::sync::atomic::AtomicBool>,
}

/// What a lease expiry did, for the log.
#[derive(Debug, Default, PartialEq)]
pub struct Expired {
    pub hosts: Vec<String>,
    pub requeued: Vec<String>,
    pub interrupted: Vec<String>,
}

/// A host of the farm and its lease.
#[derive(Debug, Clone, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct FarmHost {
    pub name: String,
    pub alive: bool,
    /// Seconds since the epoch of its last heartbeat.
    pub last_seen: f64,
}

/// Checks the connection string (no password in it) and builds the client settings, with
/// the password from `password_file` or `PGPASSWORD`.
fn client_config(settings: &PgSettings) -> Result<tokio_postgres::Config, PgError> {
    let mut config = parse_conninfo(&settings.conninfo).map_err(|e| match e {
        ConninfoError::Password => {
            PgError::PasswordInConnectionString("the connection string holds a password")
        }
        ConninfoError::Bad(m) => PgError::BadConnectionString(m),
    })?;
    if let Some(path) = &settings.password_file {
        // The same bounded read as the config check's: never a device or a directory.
        let (text, _) =
            crate::daemon::config::read_secret(path).map_err(|m| PgError::PasswordFile {
                path: path.clone(),
                source: std::io::Error::other(m),
            })?;
        config.password(text.trim_end_matches(['\r', '\n']));
    } else if let Ok(password) = std::env::var("PGPASSWORD") {
        config.password(password);
    }
    if config.get_application_name().is_none() {
        config.application_name("crispen");
    }
    Ok(config)
}

impl PgStore {
    /// Connects as host `host`, migrates the schema (or refuses a newer one) and takes the
    /// host's lease with a new token, unless another run holds it ([`PgError::HostInUse`]).
    pub async fn connect(
        settings: &PgSettings,
        host: &str,
        lease: Duration,
    ) -> Result<PgStore, PgError> {
        let config = client_config(settings)?;
        let manager = deadpool_postgres::Manager::from_config(
            config,
            tokio_postgres::NoTls,
            deadpool_postgres::ManagerConfig {
                recycling_method: deadpool_postgres::RecyclingMethod::Fast,
            },
        );
        let pool = deadpool_postgres::Pool::builder(manager)
            .max_size(4)
            .runtime(deadpool_postgres::Runtime::Tokio1)
            // An outage must fail calls within seconds, not hang the caller.
            .wait_timeout(Some(Duration::from_secs(5)))
            .create_timeout(Some(Duration::from_secs(5)))
            .recycle_timeout(Some(Duration::from_secs(5)))
            .build()
            .map_err(|e| PgError::BadConnectionString(e.to_string()))?;
        let store = PgStore {
            pool,
            host: host.to_string(),
            token: format!("{:032x}", rand::random::<u128>()),
            displaced: Default::default(),
        };
        let mut client = store.pool.get().await?;
        schema::migrate(&mut client).await?;
        drop(client);
        store.take_host(lease).await?;
        Ok(store)
    }

    /// Takes the host's row for this run: refused while another run's lease holds (its
    /// token differs, whatever it is; an older crispen's row has none).
    async fn take_host(&self, lease: Duration) -> Result<(), PgError> {
        let mut client = self.client().await?;
        let tx = client.transaction().await?;
        let held = tx
            .query_opt(
                "SELECT token, lease_until >= now(), \
                 greatest(extract(epoch FROM lease_until - now()), 0)::float8 \
                 FROM hosts WHERE name = $1 FOR UPDATE",
                &[&self.host],
            )
            .await?;
        if let Some(row) = held {
            let token: Option<String> = row.get(0);
            if row.get::<_, bool>(1) && token.as_deref() != Some(self.token.as_str()) {
                let _ = tx.rollback().await;
                return Err(PgError::HostInUse {
                    host: self.host.clone(),
                    remaining_s: row.get(2),
                });
            }
        }
        tx.execute(
            "INSERT INTO hosts (name, lease_until, token) \
             VALUES ($1, now() + make_interval(secs => $2), $3) \
             ON CONFLICT (name) DO UPDATE SET lease_until = EXCLUDED.lease_until, \
             token = EXCLUDED.token, started_at = now(), last_seen = now(), expired_at = NULL",
            &[&self.host, &lease.as_secs_f64(), &self.token],
        )
        .await?;
        tx.commit().await?;
        Ok(())
    }

    /// A connection, unless this run was found displaced.
    pub(super) async fn client(&self) -> Result<deadpool_postgres::Object, PgError> {
        if self.displaced.load(std::sync::atomic::Ordering::SeqCst) {
            return Err(self.displaced_error());
        }
        Ok(self.pool.get().await?)
    }

    pub(super) fn displaced_error(&self) -> PgError {
        self.displaced
            .store(true, std::sync::atomic::Ordering::SeqCst);
        PgError::Displaced {
            host: self.host.clone(),
        }
    }

    /// Inside a change's transaction: the host's row still holds this run's token. The
    /// row is locked `FOR KEY SHARE`, which heartbeats and expiry (plain updates) pass,
    /// but a run taking the name over (`FOR UPDATE`) waits for: no change of this run
    /// lands after a takeover.
    pub(super) async fn check_token(
        &self,
        tx: &tokio_postgres::Transaction<'_>,
    ) -> Result<(), PgError> {
        let row = tx
            .query_opt(
                "SELECT token FROM hosts WHERE name = $1 FOR KEY SHARE",
                &[&self.host],
            )
            .await?;
        match row {
            Some(row) if row.get::<_, Option<String>>(0).as_deref() == Some(&self.token) => Ok(()),
            _ => Err(self.displaced_error()),
        }
    }

    /// Gives the lease up at a clean stop (this run's prints have ended): the next run
    /// under this name may start at once, and the others see the host offline now.
    pub(crate) async fn release_host(&self) -> Result<(), PgError> {
        let client = self.client().await?;
        client
            .execute(
                "UPDATE hosts SET lease_until = now() WHERE name = $1 AND token = $2",
                &[&self.host, &self.token],
            )
            .await?;
        Ok(())
    }

    pub(crate) fn host(&self) -> &str {
        &self.host
    }

    /// Renews this host's lease until `lease` from now (by the database's clock, so hosts'
    /// clocks need not agree). A host whose lease had expired comes back with no claims;
    /// one whose row holds another run's token is [`PgError::Displaced`].
    pub async fn heartbeat(&self, lease: Duration) -> Result<(), PgError> {
        let client = self.client().await?;
        let renewed = client
            .execute(
                "INSERT INTO hosts (name, lease_until, token) \
                 VALUES ($1, now() + make_interval(secs => $2), $3) \
                 ON CONFLICT (name) DO UPDATE SET lease_until = EXCLUDED.lease_until, \
                 last_seen = now(), expired_at = NULL WHERE hosts.token = EXCLUDED.token",
                &[&self.host, &lease.as_secs_f64(), &self.token],
            )
            .await?;
        if renewed == 0 {
            return Err(self.displaced_error());
        }
        client
            .execute(
                "UPDATE printers SET last_seen = now() WHERE host = $1",
                &[&self.host],
            )
            .await?;
        Ok(())
    }

    /// Applies the expiry rules to every host whose lease ran out (any host may run this;
    /// each dead host is handled once). A lease is only judged once the database has been
    /// up for that long itself: after the database's own restart every host gets a full
    /// lease to come back before its work is taken.
    pub async fn expire_hosts(&self) -> Result<Expired, PgError> {
        let mut client = self.client().await?;
        let tx = client.transaction().await?;
        let hosts: Vec<String> = ids(tx
            .query(
                "UPDATE hosts SET expired_at = now() \
                 WHERE lease_until < now() AND expired_at IS NULL \
                 AND pg_postmaster_start_time() < now() - (lease_until - last_seen) \
                 RETURNING name",
                &[],
            )
            .await?);
        if hosts.is_empty() {
            return Ok(Expired::default());
        }
        let why = "stopped renewing its lease";
        let (requeued, interrupted) = self.release_work(&tx, &hosts, why).await?;
        tx.commit().await?;
        Ok(Expired {
            hosts,
            requeued,
            interrupted,
        })
    }

    /// The restart rules for this host's own work (it stopped without handing it back):
    /// preparing jobs go back to the queue, printing jobs become interrupted. Only a run
    /// that holds the host's row does this: [`PgStore::connect`] took it only once the run
    /// before had let its lease run out, so no live run's prints are interrupted.
    pub async fn recover_own(&self) -> Result<Vec<String>, PgError> {
        let mut client = self.client().await?;
        let tx = client.transaction().await?;
        self.check_token(&tx).await?;
        let hosts = [self.host.clone()];
        let (mut requeued, interrupted) = self
            .release_work(&tx, &hosts, "restarted during the print")
            .await?;
        tx.commit().await?;
        requeued.extend(interrupted);
        Ok(requeued)
    }

    /// Hands back the work `hosts` held: preparing → queued, printing → interrupted (with
    /// its printer's bed to be cleared). Returns (requeued, interrupted).
    async fn release_work(
        &self,
        tx: &tokio_postgres::Transaction<'_>,
        hosts: &[String],
        why: &str,
    ) -> Result<(Vec<String>, Vec<String>), PgError> {
        // Both changes are legal in the one table; the test below keeps it so.
        debug_assert!(JobState::Preparing.can_go_to(JobState::Queued));
        debug_assert!(JobState::Printing.can_go_to(JobState::Interrupted));
        let requeued = ids(tx
            .query(
                "UPDATE jobs SET state = 'queued', claimed_by = NULL, updated_at = now() \
                 WHERE state = 'preparing' AND claimed_by = ANY($1) RETURNING id",
                &[&hosts],
            )
            .await?);
        let interrupted_rows = tx
            .query(
                "UPDATE jobs SET state = 'interrupted', claimed_by = NULL, updated_at = now(), \
                 reason = 'host ' || claimed_by || ' ' || $2 \
                 WHERE state = 'printing' AND claimed_by = ANY($1) RETURNING id, printer",
                &[&hosts, &why],
            )
            .await?;
        for row in &interrupted_rows {
            let printer: Option<String> = row.get(1);
            tx.execute(
                "UPDATE printers SET bed_not_cleared = true, last_job = $2, bed = NULL \
                 WHERE name = $1",
                &[&printer, &row.get::<_, String>(0)],
            )
            .await?;
        }
        // An eject sequence that was running is never run again: a person looks.
        tx.execute(
            "UPDATE printers SET bed_not_cleared = true, \
             bed = '{\"state\": \"waiting\", \"why\": {\"kind\": \"eject_interrupted\"}}' \
             WHERE host = ANY($1) AND bed->>'state' = 'ejecting'",
            &[&hosts],
        )
        .await?;
        let interrupted = ids(interrupted_rows);
        for (ids, state) in [(&requeued, "queued"), (&interrupted, "interrupted")] {
            tx.execute(
                "INSERT INTO job_history (job_id, state, host) SELECT unnest($1::text[]), $2, $3",
                &[ids, &state, &self.host],
            )
            .await?;
        }
        Ok((requeued, interrupted))
    }

    /// Every host of the farm and whether its lease holds.
    pub(crate) async fn hosts(&self) -> Result<Vec<FarmHost>, PgError> {
        let client = self.client().await?;
        let rows = client
            .query(
                "SELECT name, lease_until >= now(), extract(epoch FROM last_seen)::float8 \
                 FROM hosts ORDER BY name",
                &[],
            )
            .await?;
        Ok(rows
            .iter()
            .map(|r| FarmHost {
                name: r.get(0),
                alive: r.get(1),
                last_seen: r.get(2),
            })
            .collect())
    }
}
