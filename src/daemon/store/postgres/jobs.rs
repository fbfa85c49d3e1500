//! The jobs' changes in the farm database, each one transaction on the job's locked row:
//! admitting a picked-up file, claiming the oldest waiting job, a change checked against
//! the table and against who holds the job, an outcome written late, and reading jobs
//! back. Apart from the lease (who may change) and the files (what a change may carry).

use super::copy::{copy_file_in, download_missing, upload_missing, FileBody};
use super::error::PgError;
use super::lease::PgStore;
use super::rows::{
    ids, job_of_row, load_jobs, one_job, parse_state, record_of, Only, JOB_COLUMNS,
    JOB_COLUMN_COUNT, RETIRED_COLUMN,
};
use crate::daemon::job::{Job, JobState, Origin, StoreError};
use crate::daemon::store::{JobEdit, StateFilter};
use std::path::{Path, PathBuf};

/// What [`PgStore::jobs_since`] found.
#[derive(Debug, Default)]
pub(crate) struct Changes {
    pub jobs: Vec<Job>,
    pub retired: Vec<String>,
    pub now: f64,
}

/// A change of one job, made by [`PgStore::modify`] on its locked row.
pub(crate) struct Change<'a> {
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
    pub(crate) fn to(state: JobState) -> Change<'static> {
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

impl PgStore {
    /// Records a picked-up file as a queued job of this host's folder `folder`, with its
    /// files, all or nothing. `printers` is the folder's rule; the id is made from the
    /// farm-wide sequence number. `pickup` names the dropped file itself (see
    /// `PgJobStore::admit`): a second job of one file is refused with
    /// [`StoreError::TakenElsewhere`].
    pub async fn admit(
        &self,
        file: &str,
        folder: &str,
        printers: &[String],
        files: &[(&str, FileBody<'_>)],
        pickup: Option<&str>,
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
        let inserted = tx
            .execute(
                "INSERT INTO jobs (id, seq, file, origin_host, folder, printers, state, record, \
                 pickup) OVERRIDING SYSTEM VALUE VALUES ($1, $2, $3, $4, $5, $6, 'queued', $7, $8)",
                &[
                    &job.id,
                    &seq,
                    &file,
                    &self.host,
                    &folder,
                    &printers,
                    &record_of(&job),
                    &pickup,
                ],
            )
            .await;
        if let Err(e) = &inserted {
            let db = e.as_db_error();
            if db.is_some_and(|d| d.constraint() == Some("jobs_pickup")) {
                return Err(StoreError::TakenElsewhere {
                    path: Path::new(folder).join(file),
                }
                .into());
            }
        }
        inserted?;
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

    /// Makes the copies due of job `id` ([`Job::copies_due`]) in one transaction on its
    /// locked row: each a ready job, and the job marked, so whichever host comes first
    /// makes them and no other does. A copy stores no files: it shares its first job's
    /// (see `download_missing`), so a big G-code is kept once however many copies.
    pub(crate) async fn make_copies(&self, id: &str) -> Result<Vec<Job>, PgError> {
        let mut client = self.client().await?;
        let tx = client.transaction().await?;
        self.check_token(&tx).await?;
        let made = undo_on_error(self.make_copies_in(&tx, id).await, tx).await?;
        if made.is_empty() {
            return Ok(Vec::new());
        }
        load_jobs(&**client, Only::Ids(&made)).await
    }

    async fn make_copies_in(
        &self,
        tx: &tokio_postgres::Transaction<'_>,
        id: &str,
    ) -> Result<Vec<String>, PgError> {
        let row = tx
            .query_opt(&format!("{JOB_COLUMNS} WHERE id = $1 FOR UPDATE"), &[&id])
            .await?
            .ok_or_else(|| StoreError::NoSuchJob(id.to_string()))?;
        let mut job = job_of_row(&row)?;
        let due = job.copies_due();
        if row.get::<_, Option<f64>>(RETIRED_COLUMN).is_some() || due.is_empty() {
            return Ok(Vec::new());
        }
        let (origin_host, printers): (String, Vec<String>) = (row.get(8), row.get(9));
        let folder = job.folder.to_string_lossy().into_owned();
        let mut made = Vec::new();
        for n in due.clone() {
            let seq: i64 = tx
                .query_one("SELECT nextval(pg_get_serial_sequence('jobs', 'seq'))", &[])
                .await?
                .get(0);
            let copy = job.copy_for(n, seq as u64);
            tx.execute(
                "INSERT INTO jobs (id, seq, file, origin_host, folder, printers, state, record) \
                 OVERRIDING SYSTEM VALUE VALUES ($1, $2, $3, $4, $5, $6, 'ready', $7)",
                &[
                    &copy.id,
                    &seq,
                    &copy.file,
                    &origin_host,
                    &folder,
                    &printers,
                    &record_of(&copy),
                ],
            )
            .await?;
            tx.execute(
                "INSERT INTO job_history (job_id, state, host) \
                 VALUES ($1, 'queued', $2), ($1, 'ready', $2)",
                &[&copy.id, &self.host],
            )
            .await?;
            made.push(copy.id);
        }
        job.copies_made = due.end - 1;
        tx.execute(
            "UPDATE jobs SET record = $2, updated_at = now() WHERE id = $1",
            &[&id, &record_of(&job)],
        )
        .await?;
        Ok(made)
    }

    /// Makes one change of a job as one transaction on its locked row (see [`Change`]).
    pub(crate) async fn modify(&self, id: &str, change: Change<'_>) -> Result<Job, PgError> {
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
            return Err(super::super::retired_refusal(id, job.state, "a change").into());
        }
        let holder: Option<String> = row.get(JOB_COLUMN_COUNT);
        let mine = holder.as_deref() == Some(self.host.as_str());
        super::super::check_from(&job, change.from)?;
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
            download_missing(tx, &job, dir, only_gcode).await?;
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
    pub(crate) async fn write_outcome(&self, job: &Job, from: JobState) -> Result<Job, PgError> {
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
    pub(crate) async fn jobs_since(&self, since: f64) -> Result<Changes, PgError> {
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
