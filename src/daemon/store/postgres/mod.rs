//! The farm's queue in PostgreSQL, shared by several hosts (issue 12's store). Hosts share
//! nothing but the database: jobs with their history, reports and files, printers with
//! their bed gates, and each host's lease.
//!
//! Every change is one transaction, and a job only changes through the claims,
//! [`PgStore::finish`] or [`PgStore::transition`], which check [`JobState::can_go_to`], the same table as the spool's.
//! Claims take the oldest waiting job with `FOR UPDATE SKIP LOCKED`, so hosts claiming at
//! once never wait on each other and a job goes to one printer once. A host that stops
//! renewing its lease loses its work by the rules of [`PgStore::expire_hosts`]: preparing
//! jobs go back to the queue, printing jobs become `interrupted` (never reprinted on their
//! own), and its printers show as offline with the time they were last seen.
//!
//! - [`schema`]: the versioned schema and its migrations.

pub mod schema;

use crate::daemon::job::{Job, JobState};
use std::path::PathBuf;
use std::time::Duration;
use tokio_postgres::Row;

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
    #[error("the farm database has schema version {found}, newer than this crispen knows ({known}) (hint: upgrade crispen on this host to the version the other hosts run)")]
    SchemaTooNew { found: i32, known: i32 },
    #[error("migrating the farm database to schema version {version}: {source}")]
    Migration {
        version: i32,
        source: tokio_postgres::Error,
    },
    #[error("the farm database is unreachable: {0}")]
    Pool(#[from] deadpool_postgres::PoolError),
    #[error("the farm database: {0}")]
    Db(#[from] tokio_postgres::Error),
    #[error("no job {0:?} in the farm database (hint: `crispen status` lists the jobs)")]
    NoSuchJob(String),
    #[error("job {id} cannot go from {from} to {to}")]
    IllegalTransition {
        id: String,
        from: JobState,
        to: JobState,
    },
    #[error("job {id} is no longer held by host {host} (its lease expired and the job is {state} now); the outcome was not recorded")]
    LostClaim {
        id: String,
        host: String,
        state: JobState,
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

/// How to reach the database: `[store] postgres` and `[store] password_file`.
#[derive(Debug, Clone, PartialEq)]
pub struct PgSettings {
    /// A libpq connection string without a password (`host=/run/postgresql dbname=crispen`).
    pub conninfo: String,
    pub password_file: Option<PathBuf>,
}

/// A host's handle on the farm database: a small pool of connections and its own name.
#[derive(Clone)]
pub struct PgStore {
    pool: deadpool_postgres::Pool,
    host: String,
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
}

/// Checks the connection string (no password in it) and builds the client settings, with
/// the password from `password_file` or `PGPASSWORD`.
fn client_config(settings: &PgSettings) -> Result<tokio_postgres::Config, PgError> {
    let config: tokio_postgres::Config = settings
        .conninfo
        .parse()
        .map_err(|e: tokio_postgres::Error| PgError::BadConnectionString(e.to_string()))?;
    if config.get_password().is_some() {
        return Err(PgError::PasswordInConnectionString(
            "the connection string holds a password",
        ));
    }
    let mut config = config;
    if let Some(path) = &settings.password_file {
        let text = std::fs::read_to_string(path).map_err(|source| PgError::PasswordFile {
            path: path.clone(),
            source,
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
    /// host's lease.
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
        };
        let mut client = store.pool.get().await?;
        schema::migrate(&mut client).await?;
        drop(client);
        store.heartbeat(lease).await?;
        Ok(store)
    }

    pub fn host(&self) -> &str {
        &self.host
    }

    /// Renews this host's lease until `lease` from now (by the database's clock, so hosts'
    /// clocks need not agree). A host whose lease had expired comes back with no claims.
    pub async fn heartbeat(&self, lease: Duration) -> Result<(), PgError> {
        let client = self.pool.get().await?;
        client
            .execute(
                "INSERT INTO hosts (name, lease_until) \
                 VALUES ($1, now() + make_interval(secs => $2)) \
                 ON CONFLICT (name) DO UPDATE SET lease_until = EXCLUDED.lease_until, \
                 last_seen = now(), expired_at = NULL",
                &[&self.host, &lease.as_secs_f64()],
            )
            .await?;
        client
            .execute(
                "UPDATE printers SET last_seen = now() WHERE host = $1",
                &[&self.host],
            )
            .await?;
        Ok(())
    }

    /// Applies the expiry rules to every host whose lease ran out (any host may run this;
    /// each dead host is handled once): its preparing jobs go back to the queue, its
    /// printing jobs become `interrupted` and their printers wait for their beds.
    pub async fn expire_hosts(&self) -> Result<Expired, PgError> {
        // Both changes are legal in the one table; the test below keeps it so.
        debug_assert!(JobState::Preparing.can_go_to(JobState::Queued));
        debug_assert!(JobState::Printing.can_go_to(JobState::Interrupted));
        let mut client = self.pool.get().await?;
        let tx = client.transaction().await?;
        let hosts: Vec<String> = tx
            .query(
                "UPDATE hosts SET expired_at = now() \
                 WHERE lease_until < now() AND expired_at IS NULL RETURNING name",
                &[],
            )
            .await?
            .iter()
            .map(|r| r.get(0))
            .collect();
        if hosts.is_empty() {
            return Ok(Expired::default());
        }
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
                 reason = 'host ' || claimed_by || ' stopped renewing its lease during the print' \
                 WHERE state = 'printing' AND claimed_by = ANY($1) RETURNING id, printer",
                &[&hosts],
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
        tx.execute("SELECT pg_notify('crispen_jobs', '')", &[])
            .await?;
        tx.commit().await?;
        Ok(Expired {
            hosts,
            requeued,
            interrupted,
        })
    }

    /// Records a picked-up file as a queued job of this host's folder `folder`, with its
    /// files, all or nothing. `printers` is the folder's rule.
    pub async fn admit(
        &self,
        id: &str,
        file: &str,
        folder: &str,
        printers: &[String],
        files: &[(&str, &[u8])],
    ) -> Result<Job, PgError> {
        let mut client = self.pool.get().await?;
        let tx = client.transaction().await?;
        tx.execute(
            "INSERT INTO jobs (id, file, origin_host, folder, printers, state) \
             VALUES ($1, $2, $3, $4, $5, 'queued')",
            &[&id, &file, &self.host, &folder, &printers],
        )
        .await?;
        for (name, bytes) in files {
            tx.execute(
                "INSERT INTO job_files (job_id, name, bytes) VALUES ($1, $2, $3)",
                &[&id, name, bytes],
            )
            .await?;
        }
        tx.execute(
            "INSERT INTO job_history (job_id, state, host) VALUES ($1, 'queued', $2)",
            &[&id, &self.host],
        )
        .await?;
        tx.execute("SELECT pg_notify('crispen_jobs', $1)", &[&id])
            .await?;
        tx.commit().await?;
        one_job(&client, id).await
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
        let mut client = self.pool.get().await?;
        let tx = client.transaction().await?;
        let Some(row) = tx.query_opt(pick, params).await? else {
            return Ok(None);
        };
        let id: String = row.get(0);
        tx.execute(
            "UPDATE jobs SET state = $2, claimed_by = $3, printer = COALESCE($4, printer), \
             updated_at = now() WHERE id = $1",
            &[&id, &to.name(), &self.host, &printer],
        )
        .await?;
        tx.execute(
            "INSERT INTO job_history (job_id, state, host) VALUES ($1, $2, $3)",
            &[&id, &to.name(), &self.host],
        )
        .await?;
        tx.commit().await?;
        Ok(Some(one_job(&client, &id).await?))
    }

    /// Records the outcome of this host's own work on a job (`from` is preparing or
    /// printing): refused with [`PgError::LostClaim`] when the job is no longer in `from`
    /// held by this host, because its lease expired and the farm moved the job on, so a
    /// print is never recorded over the farm's decision.
    pub async fn finish(
        &self,
        id: &str,
        from: JobState,
        to: JobState,
        reason: Option<&str>,
    ) -> Result<Job, PgError> {
        self.change(id, Some(from), to, reason).await
    }

    /// An operator's change (cancel, retry, clear), from any host, if the one table allows it.
    pub async fn transition(
        &self,
        id: &str,
        to: JobState,
        reason: Option<&str>,
    ) -> Result<Job, PgError> {
        self.change(id, None, to, reason).await
    }

    async fn change(
        &self,
        id: &str,
        held_in: Option<JobState>,
        to: JobState,
        reason: Option<&str>,
    ) -> Result<Job, PgError> {
        let mut client = self.pool.get().await?;
        let tx = client.transaction().await?;
        let row = tx
            .query_opt(
                "SELECT state, claimed_by FROM jobs WHERE id = $1 FOR UPDATE",
                &[&id],
            )
            .await?
            .ok_or_else(|| PgError::NoSuchJob(id.to_string()))?;
        let from = parse_state(id, row.get(0))?;
        let claimed_by: Option<String> = row.get(1);
        if let Some(held_in) = held_in {
            if from != held_in || claimed_by.as_deref() != Some(self.host.as_str()) {
                return Err(PgError::LostClaim {
                    id: id.to_string(),
                    host: self.host.clone(),
                    state: from,
                });
            }
        }
        if !from.can_go_to(to) {
            return Err(PgError::IllegalTransition {
                id: id.to_string(),
                from,
                to,
            });
        }
        // A job keeps its host while it moves between preparing and printing states of
        // that host's work; any other state is nobody's.
        let keeps_claim = matches!(to, JobState::Preparing | JobState::Printing);
        tx.execute(
            "UPDATE jobs SET state = $2, reason = COALESCE($3, reason), updated_at = now(), \
             claimed_by = CASE WHEN $4 THEN claimed_by ELSE NULL END WHERE id = $1",
            &[&id, &to.name(), &reason, &keeps_claim],
        )
        .await?;
        tx.execute(
            "INSERT INTO job_history (job_id, state, host) VALUES ($1, $2, $3)",
            &[&id, &to.name(), &self.host],
        )
        .await?;
        tx.execute("SELECT pg_notify('crispen_jobs', $1)", &[&id])
            .await?;
        tx.commit().await?;
        one_job(&client, id).await
    }

    /// Stores (or replaces) one of a job's files.
    pub async fn put_file(&self, id: &str, name: &str, bytes: &[u8]) -> Result<(), PgError> {
        let client = self.pool.get().await?;
        client
            .execute(
                "INSERT INTO job_files (job_id, name, bytes) VALUES ($1, $2, $3) \
                 ON CONFLICT (job_id, name) DO UPDATE SET bytes = EXCLUDED.bytes",
                &[&id, &name, &bytes],
            )
            .await?;
        Ok(())
    }

    pub async fn file(&self, id: &str, name: &str) -> Result<Option<Vec<u8>>, PgError> {
        let client = self.pool.get().await?;
        Ok(client
            .query_opt(
                "SELECT bytes FROM job_files WHERE job_id = $1 AND name = $2",
                &[&id, &name],
            )
            .await?
            .map(|r| r.get(0)))
    }

    /// Registers (or moves to this host) one of this host's printers.
    pub async fn register_printer(&self, name: &str) -> Result<(), PgError> {
        let client = self.pool.get().await?;
        client
            .execute(
                "INSERT INTO printers (name, host) VALUES ($1, $2) \
                 ON CONFLICT (name) DO UPDATE SET host = EXCLUDED.host, last_seen = now()",
                &[&name, &self.host],
            )
            .await?;
        Ok(())
    }

    /// Sets a printer's bed gate: a print ended on it (`true`) or its bed was cleared.
    pub async fn set_bed_gate(
        &self,
        printer: &str,
        bed_not_cleared: bool,
        last_job: Option<&str>,
    ) -> Result<(), PgError> {
        let client = self.pool.get().await?;
        let changed = client
            .execute(
                "UPDATE printers SET bed_not_cleared = $2, last_job = COALESCE($3, last_job) \
                 WHERE name = $1",
                &[&printer, &bed_not_cleared, &last_job],
            )
            .await?;
        debug_assert!(changed <= 1);
        Ok(())
    }

    /// Every printer of the farm, with whether its host is offline.
    pub async fn printers(&self) -> Result<Vec<FarmPrinter>, PgError> {
        let client = self.pool.get().await?;
        let rows = client
            .query(
                "SELECT p.name, p.host, p.bed_not_cleared, p.last_job, \
                 h.lease_until < now(), extract(epoch FROM p.last_seen)::float8 \
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
            })
            .collect())
    }

    pub async fn job(&self, id: &str) -> Result<Job, PgError> {
        let client = self.pool.get().await?;
        one_job(&client, id).await
    }

    /// Every job of the farm, oldest first.
    pub async fn jobs(&self) -> Result<Vec<Job>, PgError> {
        self.load_jobs(None).await
    }

    async fn load_jobs(&self, only: Option<&str>) -> Result<Vec<Job>, PgError> {
        let client = self.pool.get().await?;
        load_jobs(&client, only).await
    }
}

/// Jobs with their history, read on `client` (a connection a caller already holds, so a
/// call never waits on the pool for a second one).
async fn load_jobs(
    client: &tokio_postgres::Client,
    only: Option<&str>,
) -> Result<Vec<Job>, PgError> {
    // Two spellings rather than `$1 IS NULL OR id = $1`, which no index serves: reading
    // one job must not scan every job's history.
    const JOB: &str = "SELECT id, seq, file, folder, state, printer, reason, sidecar, \
        copies_done, slice_report, print_report FROM jobs";
    const HISTORY: &str = "SELECT job_id, state, extract(epoch FROM at)::float8 FROM job_history";
    let (rows, history) = match only {
        Some(id) => (
            client
                .query(&format!("{JOB} WHERE id = $1"), &[&id])
                .await?,
            client
                .query(&format!("{HISTORY} WHERE job_id = $1 ORDER BY at"), &[&id])
                .await?,
        ),
        None => (
            client.query(&format!("{JOB} ORDER BY seq"), &[]).await?,
            client.query(&format!("{HISTORY} ORDER BY at"), &[]).await?,
        ),
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

async fn one_job(client: &tokio_postgres::Client, id: &str) -> Result<Job, PgError> {
    load_jobs(client, Some(id))
        .await?
        .pop()
        .ok_or_else(|| PgError::NoSuchJob(id.to_string()))
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

/// A `jsonb` column as the typed field it holds.
fn from_json<T: serde::de::DeserializeOwned>(
    id: &str,
    what: &'static str,
    value: Option<serde_json::Value>,
) -> Result<Option<T>, PgError> {
    value
        .map(serde_json::from_value)
        .transpose()
        .map_err(|e| PgError::Corrupt {
            id: id.to_string(),
            what,
            message: e.to_string(),
        })
}

fn job_of_row(row: &Row) -> Result<Job, PgError> {
    let id: String = row.get(0);
    let seq: i64 = row.get(1);
    let copies_done: i32 = row.get(8);
    Ok(Job {
        seq: seq as u64,
        file: row.get(2),
        folder: PathBuf::from(row.get::<_, String>(3)),
        state: parse_state(&id, row.get(4))?,
        history: Vec::new(),
        printer: row.get(5),
        reason: row.get(6),
        sidecar: from_json(&id, "sidecar", row.get(7))?,
        copies_done: copies_done.max(0) as u32,
        slice_report: from_json(&id, "slice_report", row.get(9))?,
        print_report: from_json(&id, "print_report", row.get(10))?,
        // Per-machine G-code is not kept in the database yet.
        machines: Default::default(),
        released: false,
        id,
    })
}
