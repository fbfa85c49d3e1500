//! The farm's queue in PostgreSQL, shared by several hosts (issue 12's store). Hosts share
//! nothing but the database: jobs with their history, reports and files, printers with
//! their bed gates, and each host's lease.
//!
//! Every change of a job is one transaction on its locked row ([`PgStore::modify`]),
//! checked against [`JobState::can_go_to`], the same table as the spool's, and against who
//! holds the job: a job preparing or printing belongs to the host that claimed it, and
//! only that host records what became of it. Claims of the oldest waiting job
//! ([`PgStore::claim_preparation`], [`PgStore::claim_print`]) use `FOR UPDATE SKIP LOCKED`,
//! so hosts claiming at once never wait on each other and a job goes to one printer once.
//! A host that stops renewing its lease loses its work by the rules of
//! [`PgStore::expire_hosts`]: preparing jobs go back to the queue, printing jobs become
//! `interrupted` (never reprinted on their own), and its printers show as offline with the
//! time they were last seen.
//!
//! A host's name is held by one run of crispen at a time: each run draws a random token
//! and takes the host's row with it ([`PgStore::connect`]), which it may only do once the
//! lease of the run before has run out ([`PgError::HostInUse`] otherwise: a cloned machine
//! keeps the hostname, the default `[farm] host`). Every change a run makes checks, in its
//! transaction, that the row still holds its token; a run whose token was replaced (its
//! lease lapsed during an outage and a new run took the name) is [`PgError::Displaced`]
//! and acts for the host no more.
//!
//! - [`schema`]: the versioned schema and its migrations.
//! - [`store`]: the daemon's [`super::JobStore`] over it: a local copy of each job's files,
//!   and outcomes kept while the database is unreachable.

pub mod schema;
pub mod store;

use super::JobEdit;
use super::StateFilter;
use crate::daemon::config::{parse_conninfo, ConninfoError, PgSettings};
use crate::daemon::job::{Job, JobState, Origin, PrinterGate, StoreError};
use postgres_protocol::escape::escape_literal;
use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::time::Duration;
use tokio_postgres::{GenericClient, Row};

#[derive(Debug, thiserror::Error)]
pub enum PgError {
    #[error("[store] postgres: {0} (hint: put the password in [store] password_file or the PGPASSWORD environment variable, never in the connection string)")]
    PasswordInConnectionString(&'static str),
    #[error("[store] postgres: {0}")]
    BadConnectionString(String),
    #[error("[store] password_file {path}: {source}")]
    PasswordFile {
        path: PathBuf,
        source: std::io::Error,
    },
    #[error("[farm] host {host:?} is in use: another run of crispen holds this host's lease in the farm database for {remaining_s:.0} s more, and renews it while it runs (hint: give each machine its own [farm] host (the default is the hostname, which a cloned machine keeps); after a crash, start again once the lease has run out)")]
    HostInUse { host: String, remaining_s: f64 },
    #[error("[farm] host {host:?} was taken over by another run of crispen after this run's lease ran out: this run no longer acts for it (takes no work, records no outcome, publishes nothing) (hint: stop this run; give each machine its own [farm] host)")]
    Displaced { host: String },
    #[error("the farm database has schema version {found}, newer than this crispen knows ({known}) (hint: upgrade crispen on this host to the version the other hosts run)")]
    SchemaTooNew { found: i32, known: i32 },
    #[error("migrating the farm database to schema version {version}: {source}")]
    Migration {
        version: i32,
        source: tokio_postgres::Error,
    },
    #[error("the farm database is unreachable: {0}")]
    Pool(#[from] deadpool_postgres::PoolError),
    /// An earlier call found it unreachable, and it has not been reached since.
    #[error("the farm database is unreachable (since: {0})")]
    Unreachable(String),
    #[error("the farm database: {0}")]
    Db(#[from] tokio_postgres::Error),
    /// What the job's rules refused (no such job, a change the table forbids, a claim lost).
    #[error(transparent)]
    Job(#[from] StoreError),
    #[error("job {id}: file {name}: {source}")]
    File {
        id: String,
        name: String,
        source: std::io::Error,
    },
    #[error(
        "job {id}: the farm database holds a value this crispen cannot read ({what}): {message}"
    )]
    Corrupt {
        id: String,
        what: &'static str,
        message: String,
    },
}

impl From<PgError> for StoreError {
    fn from(e: PgError) -> StoreError {
        match e {
            PgError::Job(e) => e,
            other => StoreError::Database {
                failure: if other.is_outage() {
                    crate::daemon::job::DatabaseFailure::Outage
                } else {
                    crate::daemon::job::DatabaseFailure::Other
                },
                message: other.to_string(),
            },
        }
    }
}

impl PgError {
    /// The database could not be reached or answered with a failure of its own (as opposed
    /// to refusing the change by the job's rules).
    pub fn is_outage(&self) -> bool {
        matches!(
            self,
            PgError::Pool(_) | PgError::Db(_) | PgError::Unreachable(_)
        )
    }
}

/// A host's handle on the farm database: a small pool of connections, its own name, and
/// this run's token in the host's row.
#[derive(Clone)]
pub struct PgStore {
    pool: deadpool_postgres::Pool,
    host: String,
    token: String,
    /// Set once the host's row was found to hold another run's token: every call fails.
    displaced: std::sync::Arc<std::sync::atomic::AtomicBool>,
}

/// What [`PgStore::jobs_since`] found.
#[derive(Debug, Default)]
pub struct Changes {
    pub jobs: Vec<Job>,
    pub retired: Vec<String>,
    pub now: f64,
}

/// What a lease expiry did, for the log.
#[derive(Debug, Default, PartialEq)]
pub struct Expired {
    pub hosts: Vec<String>,
    pub requeued: Vec<String>,
    pub interrupted: Vec<String>,
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

/// A host of the farm and its lease.
#[derive(Debug, Clone, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct FarmHost {
    pub name: String,
    pub alive: bool,
    /// Seconds since the epoch of its last heartbeat.
    pub last_seen: f64,
}

/// A change of one job, made by [`PgStore::modify`] on its locked row.
pub struct Change<'a> {
    /// The states the job must be in now (else [`StoreError::StateChanged`]). A job
    /// preparing or printing must also be held by this host (else
    /// [`StoreError::LostClaim`]), unless the change cancels it.
    pub from: Option<StateFilter>,
    /// The new state; `None` changes other fields only.
    pub to: Option<JobState>,
    pub reason: Option<String>,
    pub edit: JobEdit,
    /// A local job directory whose files the database lacks are stored with the change
    /// (preparation's G-code, as the job becomes ready).
    pub upload_from: Option<&'a Path>,
    /// A local job directory to write the job's files into that it lacks (a host taking
    /// a job another host picked up); `only_gcode` limits it to G-code.
    pub download_to: Option<(&'a Path, bool)>,
}

impl Change<'_> {
    pub fn to(state: JobState) -> Change<'static> {
        Change {
            from: None,
            to: Some(state),
            reason: None,
            edit: Box::new(|_| {}),
            upload_from: None,
            download_to: None,
        }
    }
}

/// A file a job may not have in the database: the column holds at most 1 GiB.
pub const MAX_FILE_BYTES: u64 = 1 << 30;

/// A file stored with a job: small ones given whole, others read from their path as they
/// are sent, never whole in memory.
#[derive(Debug, Clone, Copy)]
pub enum FileBody<'a> {
    Bytes(&'a [u8]),
    Path(&'a Path),
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
    async fn client(&self) -> Result<deadpool_postgres::Object, PgError> {
        if self.displaced.load(std::sync::atomic::Ordering::SeqCst) {
            return Err(self.displaced_error());
        }
        Ok(self.pool.get().await?)
    }

    fn displaced_error(&self) -> PgError {
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
    async fn check_token(&self, tx: &tokio_postgres::Transaction<'_>) -> Result<(), PgError> {
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
    pub async fn release_host(&self) -> Result<(), PgError> {
        let client = self.client().await?;
        client
            .execute(
                "UPDATE hosts SET lease_until = now() WHERE name = $1 AND token = $2",
                &[&self.host, &self.token],
            )
            .await?;
        Ok(())
    }

    pub fn host(&self) -> &str {
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
                "UPDATE printers SET bed_not_cleared = true, last_job = $2 WHERE name = $1",
                &[&printer, &row.get::<_, String>(0)],
            )
            .await?;
        }
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

    /// Records a picked-up file as a queued job of this host's folder `folder`, with its
    /// files, all or nothing. `printers` is the folder's rule; the id is made from the
    /// farm-wide sequence number.
    pub async fn admit(
        &self,
        file: &str,
        folder: &str,
        printers: &[String],
        files: &[(&str, FileBody<'_>)],
    ) -> Result<Job, PgError> {
        let mut client = self.client().await?;
        let tx = client.transaction().await?;
        self.check_token(&tx).await?;
        let seq: i64 = tx
            .query_one("SELECT nextval(pg_get_serial_sequence('jobs', 'seq'))", &[])
            .await?
            .get(0);
        let mut job = Job::queued(
            Job::make_id(seq as u64, file),
            seq as u64,
            file.to_string(),
            PathBuf::from(folder),
        );
        job.origin = Some(Origin {
            host: self.host.clone(),
            printers: printers.to_vec(),
        });
        tx.execute(
            "INSERT INTO jobs (id, seq, file, origin_host, folder, printers, state, record) \
             OVERRIDING SYSTEM VALUE VALUES ($1, $2, $3, $4, $5, $6, 'queued', $7)",
            &[
                &job.id,
                &seq,
                &file,
                &self.host,
                &folder,
                &printers,
                &record_of(&job),
            ],
        )
        .await?;
        for (name, body) in files {
            match body {
                FileBody::Bytes(bytes) => {
                    tx.execute(
                        "INSERT INTO job_files (job_id, name, bytes) VALUES ($1, $2, $3)",
                        &[&job.id, name, bytes],
                    )
                    .await?;
                }
                FileBody::Path(path) => copy_file_in(&tx, &job.id, name, path).await?,
            }
        }
        tx.execute(
            "INSERT INTO job_history (job_id, state, host) VALUES ($1, 'queued', $2)",
            &[&job.id, &self.host],
        )
        .await?;
        tx.commit().await?;
        one_job(&**client, &job.id).await
    }

    /// Takes the oldest queued job for preparation on this host, if any.
    pub async fn claim_preparation(&self) -> Result<Option<Job>, PgError> {
        self.claim(
            "SELECT id FROM jobs WHERE state = 'queued' \
             ORDER BY seq FOR UPDATE SKIP LOCKED LIMIT 1",
            &[],
            JobState::Preparing,
            None,
        )
        .await
    }

    /// Takes the oldest ready job that `printer` (one of this host's) may print, unless the
    /// printer's bed is still to be cleared.
    pub async fn claim_print(&self, printer: &str) -> Result<Option<Job>, PgError> {
        self.claim(
            "SELECT id FROM jobs WHERE state = 'ready' AND $1 = ANY(printers) \
             AND NOT EXISTS (SELECT 1 FROM printers p WHERE p.name = $1 AND p.bed_not_cleared) \
             ORDER BY seq FOR UPDATE SKIP LOCKED LIMIT 1",
            &[&printer],
            JobState::Printing,
            Some(printer),
        )
        .await
    }

    async fn claim(
        &self,
        pick: &str,
        params: &[&(dyn tokio_postgres::types::ToSql + Sync)],
        to: JobState,
        printer: Option<&str>,
    ) -> Result<Option<Job>, PgError> {
        let mut client = self.client().await?;
        let tx = client.transaction().await?;
        self.check_token(&tx).await?;
        let Some(row) = tx.query_opt(pick, params).await? else {
            return Ok(None);
        };
        let id: String = row.get(0);
        let printer = printer.map(str::to_string);
        let mut change = Change::to(to);
        change.edit = Box::new(move |j| {
            if printer.is_some() {
                j.printer = printer;
            }
        });
        let job = undo_on_error(self.modify_in(&tx, &id, change).await, tx).await?;
        Ok(Some(job))
    }

    /// Records the outcome of this host's own work on a job (`from` is preparing or
    /// printing): refused when the job is no longer in `from` held by this host, because
    /// its lease expired and the farm moved the job on, so a print is never recorded over
    /// the farm's decision.
    pub async fn finish(
        &self,
        id: &str,
        from: StateFilter,
        to: JobState,
        reason: Option<&str>,
    ) -> Result<Job, PgError> {
        let mut change = Change::to(to);
        change.from = Some(from);
        change.reason = reason.map(str::to_string);
        self.modify(id, change).await
    }

    /// Makes one change of a job as one transaction on its locked row (see [`Change`]).
    pub async fn modify(&self, id: &str, change: Change<'_>) -> Result<Job, PgError> {
        let mut client = self.client().await?;
        let tx = client.transaction().await?;
        self.check_token(&tx).await?;
        let job = undo_on_error(self.modify_in(&tx, id, change).await, tx).await?;
        Ok(job)
    }

    async fn modify_in(
        &self,
        tx: &tokio_postgres::Transaction<'_>,
        id: &str,
        change: Change<'_>,
    ) -> Result<Job, PgError> {
        // A claim passes over a job another host is changing this moment (it is most likely
        // taking it) instead of waiting for it, as the claims above do.
        let claim = matches!(change.to, Some(JobState::Preparing | JobState::Printing));
        let lock = if claim {
            "FOR UPDATE SKIP LOCKED"
        } else {
            "FOR UPDATE"
        };
        let row = tx
            .query_opt(&format!("{JOB_COLUMNS} WHERE id = $1 {lock}"), &[&id])
            .await?;
        let Some(row) = row else {
            let state = tx
                .query_opt("SELECT state FROM jobs WHERE id = $1", &[&id])
                .await?
                .ok_or_else(|| StoreError::NoSuchJob(id.to_string()))?;
            return Err(StoreError::StateChanged {
                id: id.to_string(),
                state: parse_state(id, state.get(0))?,
                expected: "free (another host is taking it)".into(),
            }
            .into());
        };
        let mut job = job_of_row(&row)?;
        if row.get::<_, Option<f64>>(RETIRED_COLUMN).is_some() {
            // The history is not the queue: a host that had not yet seen it retired.
            return Err(super::retired_refusal(id, job.state, "a change").into());
        }
        let holder: Option<String> = row.get(JOB_COLUMN_COUNT);
        let mine = holder.as_deref() == Some(self.host.as_str());
        super::check_from(&job, change.from)?;
        // Work in progress is its host's to record; an operator may only cancel it.
        if is_held(job.state) && !mine && change.to != Some(JobState::Cancelled) {
            return Err(StoreError::LostClaim {
                id: id.to_string(),
                host: self.host.clone(),
                state: job.state,
            }
            .into());
        }
        let before = job.state;
        match change.to {
            Some(to) => job.apply_transition(to, change.reason, change.edit)?,
            None => (change.edit)(&mut job),
        }
        let state = change.to.unwrap_or(before);
        job.state = state;
        if let Some(dir) = change.upload_from {
            upload_missing(tx, &job.id, dir).await?;
        }
        if let Some((dir, only_gcode)) = change.download_to {
            download_missing(tx, &job.id, dir, only_gcode).await?;
        }
        let holder = is_held(state).then(|| self.host.clone());
        self.write_row(tx, &job, holder.as_deref(), state != before)
            .await?;
        one_job(tx, id).await
    }

    /// Writes a job's row (its state, printer, reason and record) with the host holding it.
    async fn write_row(
        &self,
        tx: &tokio_postgres::Transaction<'_>,
        job: &Job,
        holder: Option<&str>,
        state_changed: bool,
    ) -> Result<(), PgError> {
        tx.execute(
            "UPDATE jobs SET state = $2, printer = $3, reason = $4, record = $5, \
             claimed_by = $6, updated_at = now() WHERE id = $1",
            &[
                &job.id,
                &job.state.name(),
                &job.printer,
                &job.reason,
                &record_of(job),
                &holder,
            ],
        )
        .await?;
        if state_changed {
            tx.execute(
                "INSERT INTO job_history (job_id, state, host) VALUES ($1, $2, $3)",
                &[&job.id, &job.state.name(), &self.host],
            )
            .await?;
        }
        Ok(())
    }

    /// Writes an outcome recorded while the database was unreachable: `job` as this host
    /// left it, if the job is still `from` and held by this host.
    pub async fn write_outcome(&self, job: &Job, from: JobState) -> Result<Job, PgError> {
        let mut client = self.client().await?;
        let tx = client.transaction().await?;
        self.check_token(&tx).await?;
        let written = async {
            let row = tx
                .query_opt(
                    "SELECT state, claimed_by FROM jobs WHERE id = $1 FOR UPDATE",
                    &[&job.id],
                )
                .await?
                .ok_or_else(|| StoreError::NoSuchJob(job.id.clone()))?;
            let state = parse_state(&job.id, row.get(0))?;
            let holder: Option<String> = row.get(1);
            if state != from || holder.as_deref() != Some(self.host.as_str()) {
                return Err(StoreError::LostClaim {
                    id: job.id.clone(),
                    host: self.host.clone(),
                    state,
                }
                .into());
            }
            let holder = is_held(job.state).then(|| self.host.clone());
            self.write_row(&tx, job, holder.as_deref(), job.state != from)
                .await
        }
        .await;
        undo_on_error(written, tx).await?;
        one_job(&**client, &job.id).await
    }

    /// Stores (or replaces) one of a job's files.
    pub async fn put_file(&self, id: &str, name: &str, bytes: &[u8]) -> Result<(), PgError> {
        let client = self.client().await?;
        client
            .execute(
                "INSERT INTO job_files (job_id, name, bytes) VALUES ($1, $2, $3) \
                 ON CONFLICT (job_id, name) DO UPDATE SET bytes = EXCLUDED.bytes",
                &[&id, &name, &bytes],
            )
            .await?;
        Ok(())
    }

    /// The names of a job's files.
    pub async fn file_names(&self, id: &str) -> Result<Vec<String>, PgError> {
        let client = self.client().await?;
        Ok(ids(client
            .query("SELECT name FROM job_files WHERE job_id = $1", &[&id])
            .await?))
    }

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
    pub async fn publish_printers(
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
    pub async fn set_gate(&self, printer: &str, gate: &PrinterGate) -> Result<(), PgError> {
        let mut client = self.client().await?;
        let tx = client.transaction().await?;
        self.check_token(&tx).await?;
        tx.execute(
            "INSERT INTO printers (name, host, bed_not_cleared, last_job) \
                 VALUES ($1, $2, $3, $4) ON CONFLICT (name) DO UPDATE \
                 SET bed_not_cleared = EXCLUDED.bed_not_cleared, last_job = EXCLUDED.last_job",
            &[&printer, &self.host, &gate.bed_not_cleared, &gate.last_job],
        )
        .await?;
        tx.commit().await?;
        Ok(())
    }

    /// Every printer's bed gate.
    pub async fn gates(&self) -> Result<BTreeMap<String, PrinterGate>, PgError> {
        let client = self.client().await?;
        let rows = client
            .query("SELECT name, bed_not_cleared, last_job FROM printers", &[])
            .await?;
        Ok(rows
            .iter()
            .map(|r| {
                let gate = PrinterGate {
                    bed_not_cleared: r.get(1),
                    last_job: r.get(2),
                };
                (r.get(0), gate)
            })
            .collect())
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

    /// Every host of the farm and whether its lease holds.
    pub async fn hosts(&self) -> Result<Vec<FarmHost>, PgError> {
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

    /// Asks the host of `printer` to pause, resume or cancel its print; false when the
    /// farm has no such printer.
    pub async fn push_command(
        &self,
        printer: &str,
        command: crate::daemon::command::PrintCommand,
    ) -> Result<bool, PgError> {
        let client = self.client().await?;
        let added = client
            .execute(
                "INSERT INTO commands (host, printer, command) \
                 SELECT host, name, $2 FROM printers WHERE name = $1",
                &[&printer, &command.word()],
            )
            .await?;
        Ok(added == 1)
    }

    /// Takes the commands other hosts left for this host's printers, oldest first, each
    /// parsed: an unknown one is taken out of the table all the same (the table has no
    /// state; a row taken is a row answered), for the caller to log and refuse.
    #[allow(clippy::type_complexity)]
    pub async fn take_commands(
        &self,
    ) -> Result<
        Vec<(
            String,
            Result<crate::daemon::command::PrintCommand, crate::daemon::command::UnknownCommand>,
        )>,
        PgError,
    > {
        let client = self.client().await?;
        let mut rows = client
            .query(
                "DELETE FROM commands WHERE host = $1 \
                 AND EXISTS (SELECT 1 FROM hosts WHERE name = $1 AND token = $2) \
                 RETURNING id, printer, command",
                &[&self.host, &self.token],
            )
            .await?;
        rows.sort_by_key(|r| r.get::<_, i64>(0));
        Ok(rows
            .iter()
            .map(|r| {
                let word: String = r.get(2);
                (r.get(1), crate::daemon::command::PrintCommand::parse(&word))
            })
            .collect())
    }

    pub async fn job(&self, id: &str) -> Result<Job, PgError> {
        let client = self.client().await?;
        one_job(&**client, id).await
    }

    /// Every job of the farm, oldest first.
    pub async fn jobs(&self) -> Result<Vec<Job>, PgError> {
        let client = self.client().await?;
        load_jobs(&**client, Only::All).await
    }

    /// The live jobs changed since `since` (seconds since the epoch, by the database's
    /// clock), the jobs retired since then, and the database's time now, for the next call.
    pub async fn jobs_since(&self, since: f64) -> Result<Changes, PgError> {
        let client = self.client().await?;
        let now: f64 = client
            .query_one("SELECT extract(epoch FROM now())::float8", &[])
            .await?
            .get(0);
        let retired = ids(client
            .query(
                "SELECT id FROM jobs WHERE retired_at >= to_timestamp($1)",
                &[&since],
            )
            .await?);
        Ok(Changes {
            jobs: load_jobs(&**client, Only::Since(since)).await?,
            retired,
            now,
        })
    }

    /// Marks the jobs `ids` retired, those still finished and live (another host may have
    /// retried or retired one meanwhile); returns the ones it marked.
    pub async fn retire(&self, wanted: &[String]) -> Result<Vec<String>, PgError> {
        let mut client = self.client().await?;
        let tx = client.transaction().await?;
        self.check_token(&tx).await?;
        let finished: Vec<&str> = JobState::ALL
            .into_iter()
            .filter(|s| super::history::is_finished(*s))
            .map(JobState::name)
            .collect();
        let retired = ids(tx
            .query(
                "UPDATE jobs SET retired_at = now(), updated_at = now() \
                 WHERE id = ANY($1) AND retired_at IS NULL AND state = ANY($2) RETURNING id",
                &[&wanted, &finished],
            )
            .await?);
        tx.commit().await?;
        Ok(retired)
    }

    /// A page of the farm's history, newest first: jobs retired at or after
    /// `retired_since` (seconds since the epoch) below `before`, with the time each was
    /// retired.
    pub async fn history(
        &self,
        before: Option<u64>,
        limit: usize,
        retired_since: f64,
    ) -> Result<Vec<(Job, f64)>, PgError> {
        let client = self.client().await?;
        let before = before.map_or(i64::MAX, |b| b.min(i64::MAX as u64) as i64);
        let rows = client
            .query(
                "SELECT id, extract(epoch FROM retired_at)::float8 FROM jobs \
                 WHERE retired_at IS NOT NULL AND seq < $1 \
                 AND retired_at >= to_timestamp($3) ORDER BY seq DESC LIMIT $2",
                &[&before, &(limit as i64), &retired_since],
            )
            .await?;
        let when: std::collections::HashMap<String, f64> =
            rows.iter().map(|r| (r.get(0), r.get(1))).collect();
        let page: Vec<String> = rows.iter().map(|r| r.get(0)).collect();
        let mut jobs = load_jobs(&**client, Only::Ids(&page)).await?;
        jobs.sort_by_key(|j| std::cmp::Reverse(j.seq));
        Ok(jobs
            .into_iter()
            .map(|j| {
                let at = when.get(&j.id).copied().unwrap_or(0.0);
                (j, at)
            })
            .collect())
    }

    /// Deletes the jobs retired before `cutoff` (seconds since the epoch), with their
    /// history and files; returns their ids.
    pub async fn forget_retired(&self, cutoff: f64) -> Result<Vec<String>, PgError> {
        let client = self.client().await?;
        Ok(ids(client
            .query(
                "DELETE FROM jobs WHERE retired_at < to_timestamp($1) RETURNING id",
                &[&cutoff],
            )
            .await?))
    }

    /// A retired job and when it was retired; None when `id` is live or unknown.
    pub async fn retired_job(&self, id: &str) -> Result<Option<(Job, f64)>, PgError> {
        let client = self.client().await?;
        let row = client
            .query_opt(
                "SELECT extract(epoch FROM retired_at)::float8 FROM jobs \
                 WHERE id = $1 AND retired_at IS NOT NULL",
                &[&id],
            )
            .await?;
        let Some(row) = row else { return Ok(None) };
        Ok(Some((one_job(&**client, id).await?, row.get(0))))
    }
}

/// Commits `tx` after `result` succeeded, else rolls it back before returning the error:
/// a refused change must not keep the job's row locked (claims would pass it over) until
/// the dropped transaction's rollback reaches the server.
async fn undo_on_error<T>(
    result: Result<T, PgError>,
    tx: deadpool_postgres::Transaction<'_>,
) -> Result<T, PgError> {
    match result {
        Ok(value) => {
            tx.commit().await?;
            Ok(value)
        }
        Err(e) => {
            let _ = tx.rollback().await;
            Err(e)
        }
    }
}

/// A job preparing or printing is held by the host that claimed it.
fn is_held(state: JobState) -> bool {
    matches!(state, JobState::Preparing | JobState::Printing)
}

/// Stores the regular files of `dir` that the job does not have in the database yet.
async fn upload_missing(
    tx: &tokio_postgres::Transaction<'_>,
    id: &str,
    dir: &Path,
) -> Result<(), PgError> {
    let have: Vec<String> = ids(tx
        .query("SELECT name FROM job_files WHERE job_id = $1", &[&id])
        .await?);
    let file_err = |name: &str| {
        let (id, name) = (id.to_string(), name.to_string());
        move |source| PgError::File { id, name, source }
    };
    let entries = std::fs::read_dir(dir).map_err(file_err("."))?;
    for entry in entries {
        let entry = entry.map_err(file_err("."))?;
        let name = entry.file_name().to_string_lossy().into_owned();
        let meta = entry.metadata().map_err(file_err(&name))?;
        let temporary = name.ends_with(".tmp") || name.starts_with(crate::fsutil::TEMP_PREFIX);
        if !meta.is_file() || have.contains(&name) || temporary {
            continue;
        }
        if meta.len() > MAX_FILE_BYTES {
            return Err(file_err(&name)(std::io::Error::other(format!(
                "{} bytes, more than the farm database keeps ({MAX_FILE_BYTES})",
                meta.len()
            ))));
        }
        copy_file_in(tx, id, &name, &entry.path()).await?;
    }
    Ok(())
}

/// The header of PostgreSQL's binary COPY format: signature, flags, extension length.
const COPY_HEADER: &[u8] = b"PGCOPY\n\xff\r\n\0\0\0\0\0\0\0\0\0";

/// Stores the file at `path` as job `id`'s file `name` with `COPY … FROM STDIN` in the
/// binary format, sending it in pieces as it is read: a G-code file of hundreds of MB is
/// never whole in this process's memory.
async fn copy_file_in(
    tx: &tokio_postgres::Transaction<'_>,
    id: &str,
    name: &str,
    path: &Path,
) -> Result<(), PgError> {
    use futures_util::SinkExt;
    use std::io::Read;
    let file_err = |source| PgError::File {
        id: id.to_string(),
        name: name.to_string(),
        source,
    };
    let file = std::fs::File::open(path).map_err(file_err)?;
    let len = file.metadata().map_err(file_err)?.len();
    if len > MAX_FILE_BYTES {
        return Err(file_err(std::io::Error::other(format!(
            "{len} bytes, more than the farm database keeps ({MAX_FILE_BYTES})"
        ))));
    }
    let sink = tx
        .copy_in::<_, bytes::Bytes>(
            "COPY job_files (job_id, name, bytes) FROM STDIN (FORMAT binary)",
        )
        .await?;
    futures_util::pin_mut!(sink);
    // One row of three fields, each its length then its bytes; then the trailer.
    let mut head = COPY_HEADER.to_vec();
    head.extend_from_slice(&3i16.to_be_bytes());
    for text in [id, name] {
        head.extend_from_slice(&(text.len() as i32).to_be_bytes());
        head.extend_from_slice(text.as_bytes());
    }
    head.extend_from_slice(&(len as i32).to_be_bytes());
    sink.send(bytes::Bytes::from(head)).await?;
    let mut reader = file.take(len);
    let mut sent = 0u64;
    loop {
        let mut piece = vec![0u8; 1 << 20];
        let n = reader.read(&mut piece).map_err(file_err)?;
        if n == 0 {
            break;
        }
        piece.truncate(n);
        sent += n as u64;
        sink.send(bytes::Bytes::from(piece)).await?;
    }
    if sent != len {
        // The file shrank while it was read: the row would not match its length.
        return Err(file_err(std::io::Error::other(format!(
            "changed while it was stored ({sent} of {len} bytes read)"
        ))));
    }
    sink.send(bytes::Bytes::copy_from_slice(&(-1i16).to_be_bytes()))
        .await?;
    sink.as_mut().finish().await?;
    Ok(())
}

/// Writes job `id`'s file `name` to `to` with `COPY … TO STDOUT` in the binary format,
/// piece by piece as it arrives, atomically (see [`crate::fsutil`]).
async fn copy_file_out(
    tx: &tokio_postgres::Transaction<'_>,
    id: &str,
    name: &str,
    to: &Path,
) -> Result<(), PgError> {
    use futures_util::StreamExt;
    use std::io::Write;
    let file_err = |source| PgError::File {
        id: id.to_string(),
        name: name.to_string(),
        source,
    };
    let corrupt = |message: &str| PgError::Corrupt {
        id: id.to_string(),
        what: "file",
        message: format!("{name}: {message}"),
    };
    // COPY takes no parameters: the literals are spelt by the client library's escaping,
    // which is right whatever the server's `standard_conforming_strings`.
    let query = format!(
        "COPY (SELECT bytes FROM job_files WHERE job_id = {} AND name = {}) TO STDOUT (FORMAT binary)",
        escape_literal(id),
        escape_literal(name)
    );
    let stream = tx.copy_out(&query).await?;
    futures_util::pin_mut!(stream);
    let mut out =
        crate::fsutil::AtomicFile::create(to).map_err(|e| file_err(std::io::Error::from(e)))?;
    // Header, field count and length first; then the bytes, up to the trailer.
    const START: usize = COPY_HEADER.len() + 2 + 4;
    let mut head: Vec<u8> = Vec::new();
    let mut left: Option<u64> = None;
    let mut rows = 0;
    while let Some(piece) = stream.next().await {
        let piece = piece?;
        let data: &[u8] = match left {
            Some(_) => &piece,
            None => {
                head.extend_from_slice(&piece);
                if head.len() < START {
                    continue;
                }
                if !head.starts_with(&COPY_HEADER[..11]) {
                    return Err(corrupt("not a binary COPY answer"));
                }
                let size = i32::from_be_bytes([head[21], head[22], head[23], head[24]]);
                if size < 0 || size as u64 > MAX_FILE_BYTES {
                    return Err(corrupt("bad length"));
                }
                rows += 1;
                left = Some(size as u64);
                &head[START..]
            }
        };
        let want = left.unwrap_or(0);
        let take = (data.len() as u64).min(want) as usize;
        out.file().write_all(&data[..take]).map_err(file_err)?;
        left = Some(want - take as u64);
    }
    if rows != 1 || left != Some(0) {
        return Err(corrupt("missing or cut short"));
    }
    out.commit()
        .map_err(|e| file_err(std::io::Error::from(e)))?;
    Ok(())
}

/// Writes the job's files that `dir` lacks (only its G-code with `only_gcode`).
async fn download_missing(
    tx: &tokio_postgres::Transaction<'_>,
    id: &str,
    dir: &Path,
    only_gcode: bool,
) -> Result<(), PgError> {
    let names: Vec<String> = ids(tx
        .query("SELECT name FROM job_files WHERE job_id = $1", &[&id])
        .await?);
    let file_err = |name: &str| {
        let (id, name) = (id.to_string(), name.to_string());
        move |source| PgError::File { id, name, source }
    };
    std::fs::create_dir_all(dir).map_err(file_err("."))?;
    for name in names {
        // Names come from hosts of the farm; still, nothing leaves the job's directory.
        let plain = !name.is_empty() && !name.contains('/') && name != "." && name != "..";
        if !plain || (only_gcode && !name.ends_with(".gcode")) || dir.join(&name).exists() {
            continue;
        }
        copy_file_out(tx, id, &name, &dir.join(&name)).await?;
    }
    Ok(())
}

/// The job's record as kept in its row: everything but what has columns of its own.
fn record_of(job: &Job) -> serde_json::Value {
    let mut record = job.clone();
    record.history = Vec::new();
    record.origin = None;
    serde_json::to_value(&record).expect("a job serialises")
}

enum Only<'a> {
    All,
    One(&'a str),
    /// The live jobs changed since then.
    Since(f64),
    Ids(&'a [String]),
}

const JOB_COLUMNS: &str = "SELECT id, seq, file, folder, state, printer, reason, record, \
    origin_host, printers, claimed_by, extract(epoch FROM retired_at)::float8 FROM jobs";
/// Where `claimed_by` is in [`JOB_COLUMNS`].
const JOB_COLUMN_COUNT: usize = 10;
/// Where the time it was retired is in [`JOB_COLUMNS`] (NULL: a live job).
const RETIRED_COLUMN: usize = 11;

/// Jobs with their history, read on `client` (a connection a caller already holds, so a
/// call never waits on the pool for a second one).
async fn load_jobs(client: &impl GenericClient, only: Only<'_>) -> Result<Vec<Job>, PgError> {
    const HISTORY: &str = "SELECT job_id, state, extract(epoch FROM at)::float8 FROM job_history";
    // Separate spellings rather than `$1 IS NULL OR id = $1`, which no index serves:
    // reading one job must not scan every job's history.
    let (rows, history) = match only {
        Only::One(id) => (
            client
                .query(&format!("{JOB_COLUMNS} WHERE id = $1"), &[&id])
                .await?,
            client
                .query(&format!("{HISTORY} WHERE job_id = $1 ORDER BY at"), &[&id])
                .await?,
        ),
        Only::All => (
            client
                .query(&format!("{JOB_COLUMNS} ORDER BY seq"), &[])
                .await?,
            client.query(&format!("{HISTORY} ORDER BY at"), &[]).await?,
        ),
        Only::Ids(ids) => (
            client
                .query(
                    &format!("{JOB_COLUMNS} WHERE id = ANY($1) ORDER BY seq"),
                    &[&ids],
                )
                .await?,
            client
                .query(
                    &format!("{HISTORY} WHERE job_id = ANY($1) ORDER BY at"),
                    &[&ids],
                )
                .await?,
        ),
        Only::Since(since) => {
            let rows = client
                .query(
                    &format!(
                        "{JOB_COLUMNS} WHERE updated_at >= to_timestamp($1) \
                         AND retired_at IS NULL ORDER BY seq"
                    ),
                    &[&since],
                )
                .await?;
            let changed = ids(rows.clone());
            let history = client
                .query(
                    &format!("{HISTORY} WHERE job_id = ANY($1) ORDER BY at"),
                    &[&changed],
                )
                .await?;
            (rows, history)
        }
    };
    let mut jobs = rows.iter().map(job_of_row).collect::<Result<Vec<_>, _>>()?;
    let index: std::collections::HashMap<String, usize> = jobs
        .iter()
        .enumerate()
        .map(|(i, j)| (j.id.clone(), i))
        .collect();
    for row in &history {
        let id: String = row.get(0);
        if let Some(&i) = index.get(&id) {
            let state = parse_state(&id, row.get(1))?;
            jobs[i].history.push((state, row.get(2)));
        }
    }
    Ok(jobs)
}

async fn one_job(client: &impl GenericClient, id: &str) -> Result<Job, PgError> {
    load_jobs(client, Only::One(id))
        .await?
        .pop()
        .ok_or_else(|| StoreError::NoSuchJob(id.to_string()).into())
}

fn ids(rows: Vec<Row>) -> Vec<String> {
    rows.iter().map(|r| r.get(0)).collect()
}

fn parse_state(id: &str, name: &str) -> Result<JobState, PgError> {
    JobState::ALL
        .into_iter()
        .find(|s| s.name() == name)
        .ok_or_else(|| PgError::Corrupt {
            id: id.to_string(),
            what: "state",
            message: format!("unknown state {name:?}"),
        })
}

/// A job from its row: the record, with the columns' values (which SQL alone may change,
/// as lease expiry does) over it.
fn job_of_row(row: &Row) -> Result<Job, PgError> {
    let id: String = row.get(0);
    let seq: i64 = row.get(1);
    let state = parse_state(&id, row.get(4))?;
    let mut record: serde_json::Value = row.get(7);
    let Some(fields) = record.as_object_mut() else {
        return Err(PgError::Corrupt {
            id,
            what: "record",
            message: "not a JSON object".into(),
        });
    };
    let columns = [
        ("id", serde_json::json!(id)),
        ("seq", serde_json::json!(seq.max(0))),
        ("file", serde_json::json!(row.get::<_, String>(2))),
        ("folder", serde_json::json!(row.get::<_, String>(3))),
        ("state", serde_json::json!(state)),
        (
            "printer",
            serde_json::json!(row.get::<_, Option<String>>(5)),
        ),
        ("reason", serde_json::json!(row.get::<_, Option<String>>(6))),
        ("history", serde_json::json!([])),
    ];
    for (key, value) in columns {
        fields.insert(key.to_string(), value);
    }
    let mut job: Job = serde_json::from_value(record).map_err(|e| PgError::Corrupt {
        id: id.clone(),
        what: "record",
        message: e.to_string(),
    })?;
    job.origin = Some(Origin {
        host: row.get(8),
        printers: row.get(9),
    });
    Ok(job)
}
