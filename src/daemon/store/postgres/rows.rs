//! A job as the database keeps it: its row's columns and record, read back into a
//! [`Job`] with its history, and the record written for it. Apart because every part of
//! the store (the lease's expiry, the jobs, the files, the history) reads rows this way.

use super::error::PgError;
use crate::daemon::job::{Job, JobState, Origin, StoreError};
use tokio_postgres::{GenericClient, Row};

/// The job's record as kept in its row: everything but what has columns of its own.
pub(super) fn record_of(job: &Job) -> serde_json::Value {
    let mut record = job.clone();
    record.history = Vec::new();
    record.origin = None;
    serde_json::to_value(&record).expect("a job serialises")
}

pub(super) enum Only<'a> {
    All,
    One(&'a str),
    /// The live jobs changed since then.
    Since(f64),
    Ids(&'a [String]),
}

pub(super) const JOB_COLUMNS: &str =
    "SELECT id, seq, file, folder, state, printer, reason, record, \
    origin_host, printers, claimed_by, extract(epoch FROM retired_at)::float8 FROM jobs";

/// Where `claimed_by` is in [`JOB_COLUMNS`].
pub(super) const JOB_COLUMN_COUNT: usize = 10;

/// Where the time it was retired is in [`JOB_COLUMNS`] (NULL: a live job).
pub(super) const RETIRED_COLUMN: usize = 11;

/// Jobs with their history, read on `client` (a connection a caller already holds, so a
/// call never waits on the pool for a second one).
pub(super) async fn load_jobs(
    client: &impl GenericClient,
    only: Only<'_>,
) -> Result<Vec<Job>, PgError> {
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

pub(super) async fn one_job(client: &impl GenericClient, id: &str) -> Result<Job, PgError> {
    load_jobs(client, Only::One(id))
        .await?
        .pop()
        .ok_or_else(|| StoreError::NoSuchJob(id.to_string()).into())
}

pub(super) fn ids(rows: Vec<Row>) -> Vec<String> {
    rows.iter().map(|r| r.get(0)).collect()
}

pub(super) fn parse_state(id: &str, name: &str) -> Result<JobState, PgError> {
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
pub(super) fn job_of_row(row: &Row) -> Result<Job, PgError> {
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
