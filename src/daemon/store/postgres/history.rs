//! The farm's history in the database: finished jobs marked retired, pages of them, one
//! retired job, and forgetting the oldest. Apart from the live jobs' changes: a retired
//! job no longer changes.

use super::error::PgError;
use super::lease::PgStore;
use super::rows::{ids, load_jobs, one_job, Only};
use crate::daemon::job::{Job, JobState};

impl PgStore {
    /// Marks the jobs `ids` retired, those still finished and live (another host may have
    /// retried or retired one meanwhile); returns the ones it marked.
    pub(crate) async fn retire(&self, wanted: &[String]) -> Result<Vec<String>, PgError> {
        let mut client = self.client().await?;
        let tx = client.transaction().await?;
        self.check_token(&tx).await?;
        let finished: Vec<&str> = JobState::ALL
            .into_iter()
            .filter(|s| super::super::history::is_finished(*s))
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
    pub(crate) async fn history(
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
    pub(crate) async fn retired_job(&self, id: &str) -> Result<Option<(Job, f64)>, PgError> {
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
