//! SQLite state of the service (sqlx): models and jobs. Static SQL with bound
//! parameters only; every state change of a job is one statement.

use serde::Serialize;
use sqlx::sqlite::{SqliteConnectOptions, SqliteJournalMode, SqlitePoolOptions, SqliteSynchronous};
use sqlx::{Row, SqlitePool};
use std::path::Path;
use std::time::Duration;

#[derive(Clone)]
pub struct Store {
    pub pool: SqlitePool,
}

#[derive(Clone, Debug, Serialize)]
pub struct ModelRow {
    pub id: String,
    pub path: String,
    pub is_default: bool,
    pub created_at: String,
    pub source_job: Option<String>,
}

#[derive(Clone, Debug, Serialize)]
pub struct JobRow {
    pub id: String,
    pub kind: String,
    pub state: String,
    pub params: serde_json::Value,
    pub progress: f64,
    pub message: String,
    pub attempts: i64,
    pub max_attempts: i64,
    pub cancel_requested: bool,
    pub error: Option<String>,
    pub result: Option<serde_json::Value>,
    pub created_at: String,
    pub started_at: Option<String>,
    pub finished_at: Option<String>,
}

/// RFC 3339 UTC timestamp of now, to the millisecond.
pub fn now() -> String {
    let d = std::time::SystemTime::now().duration_since(std::time::UNIX_EPOCH).unwrap_or_default();
    let secs = d.as_secs() as i64;
    let (days, rem) = (secs.div_euclid(86_400), secs.rem_euclid(86_400));
    // Civil date from days since 1970-01-01 (Howard Hinnant's algorithm).
    let z = days + 719_468;
    let era = z.div_euclid(146_097);
    let doe = z - era * 146_097;
    let yoe = (doe - doe / 1460 + doe / 36_524 - doe / 146_096) / 365;
    let doy = doe - (365 * yoe + yoe / 4 - yoe / 100);
    let mp = (5 * doy + 2) / 153;
    let day = doy - (153 * mp + 2) / 5 + 1;
    let month = if mp < 10 { mp + 3 } else { mp - 9 };
    let year = yoe + era * 400 + i64::from(month <= 2);
    format!(
        "{year:04}-{month:02}-{day:02}T{:02}:{:02}:{:02}.{:03}Z",
        rem / 3600,
        rem % 3600 / 60,
        rem % 60,
        d.subsec_millis()
    )
}

fn job_from(row: &sqlx::sqlite::SqliteRow) -> JobRow {
    let json = |s: Option<String>| s.and_then(|s| serde_json::from_str(&s).ok());
    JobRow {
        id: row.get("id"),
        kind: row.get("kind"),
        state: row.get("state"),
        params: json(row.get("params")).unwrap_or(serde_json::Value::Null),
        progress: row.get("progress"),
        message: row.get("message"),
        attempts: row.get("attempts"),
        max_attempts: row.get("max_attempts"),
        cancel_requested: row.get::<i64, _>("cancel_requested") != 0,
        error: row.get("error"),
        result: json(row.get("result")),
        created_at: row.get("created_at"),
        started_at: row.get("started_at"),
        finished_at: row.get("finished_at"),
    }
}

fn model_from(row: &sqlx::sqlite::SqliteRow) -> ModelRow {
    ModelRow {
        id: row.get("id"),
        path: row.get("path"),
        is_default: row.get::<i64, _>("is_default") != 0,
        created_at: row.get("created_at"),
        source_job: row.get("source_job"),
    }
}

impl Store {
    /// Opens (creating if needed) the database in WAL mode and applies migrations.
    pub async fn open(path: &Path) -> Result<Store, sqlx::Error> {
        let opts = SqliteConnectOptions::new()
            .filename(path)
            .create_if_missing(true)
            .journal_mode(SqliteJournalMode::Wal)
            .synchronous(SqliteSynchronous::Normal)
            .busy_timeout(Duration::from_secs(5))
            .foreign_keys(true);
        let pool = SqlitePoolOptions::new().max_connections(4).connect_with(opts).await?;
        sqlx::migrate!("./migrations").run(&pool).await?;
        Ok(Store { pool })
    }

    pub async fn ping(&self) -> bool {
        sqlx::query("SELECT 1").fetch_one(&self.pool).await.is_ok()
    }

    pub async fn add_model(
        &self,
        id: &str,
        path: &str,
        is_default: bool,
        source_job: Option<&str>,
    ) -> Result<(), sqlx::Error> {
        sqlx::query(
            "INSERT OR IGNORE INTO models (id, path, is_default, created_at, source_job) VALUES (?, ?, ?, ?, ?)",
        )
        .bind(id)
        .bind(path)
        .bind(is_default as i64)
        .bind(now())
        .bind(source_job)
        .execute(&self.pool)
        .await?;
        Ok(())
    }

    pub async fn models(&self) -> Result<Vec<ModelRow>, sqlx::Error> {
        Ok(sqlx::query("SELECT * FROM models ORDER BY created_at")
            .fetch_all(&self.pool)
            .await?
            .iter()
            .map(model_from)
            .collect())
    }

    pub async fn model(&self, id: &str) -> Result<Option<ModelRow>, sqlx::Error> {
        Ok(sqlx::query("SELECT * FROM models WHERE id = ?")
            .bind(id)
            .fetch_optional(&self.pool)
            .await?
            .as_ref()
            .map(model_from))
    }

    pub async fn default_model(&self) -> Result<Option<ModelRow>, sqlx::Error> {
        Ok(sqlx::query("SELECT * FROM models WHERE is_default = 1 LIMIT 1")
            .fetch_optional(&self.pool)
            .await?
            .as_ref()
            .map(model_from))
    }

    /// Queues a job if fewer than `limit` jobs are queued or running. The count and the
    /// insert are one statement (SQLite takes the write lock before it reads), so
    /// concurrent posts cannot overshoot the limit. Returns whether the job was queued.
    pub async fn insert_job_within(
        &self,
        id: &str,
        kind: &str,
        params: &serde_json::Value,
        max_attempts: i64,
        limit: i64,
    ) -> Result<bool, sqlx::Error> {
        let done = sqlx::query(
            "INSERT INTO jobs (id, kind, params, max_attempts, created_at) SELECT ?, ?, ?, ?, ?
             WHERE (SELECT COUNT(*) FROM jobs WHERE state IN ('queued', 'running')) < ?",
        )
        .bind(id)
        .bind(kind)
        .bind(params.to_string())
        .bind(max_attempts)
        .bind(now())
        .bind(limit)
        .execute(&self.pool)
        .await?;
        Ok(done.rows_affected() == 1)
    }

    pub async fn job(&self, id: &str) -> Result<Option<JobRow>, sqlx::Error> {
        Ok(sqlx::query("SELECT * FROM jobs WHERE id = ?")
            .bind(id)
            .fetch_optional(&self.pool)
            .await?
            .as_ref()
            .map(job_from))
    }

    pub async fn jobs(&self, state: Option<&str>, limit: i64) -> Result<Vec<JobRow>, sqlx::Error> {
        let rows = sqlx::query("SELECT * FROM jobs WHERE (?1 IS NULL OR state = ?1) ORDER BY created_at DESC LIMIT ?2")
            .bind(state)
            .bind(limit)
            .fetch_all(&self.pool)
            .await?;
        Ok(rows.iter().map(job_from).collect())
    }

    /// Claims the oldest queued job atomically (one statement), counting the attempt.
    pub async fn claim(&self) -> Result<Option<JobRow>, sqlx::Error> {
        let row = sqlx::query(
            "UPDATE jobs SET state = 'running', attempts = attempts + 1, started_at = ?1, message = 'started'
             WHERE id = (SELECT id FROM jobs WHERE state = 'queued' ORDER BY created_at, id LIMIT 1) AND state = 'queued'
             RETURNING *",
        )
        .bind(now())
        .fetch_optional(&self.pool)
        .await?;
        Ok(row.as_ref().map(job_from))
    }

    pub async fn progress(&self, id: &str, progress: f64, message: &str) -> Result<(), sqlx::Error> {
        sqlx::query("UPDATE jobs SET progress = ?, message = ? WHERE id = ? AND state = 'running'")
            .bind(progress)
            .bind(message)
            .bind(id)
            .execute(&self.pool)
            .await?;
        Ok(())
    }

    /// Final state of a running job, fenced by its attempt: only the worker that claimed
    /// `attempt` may end it (after a restart re-queued and re-claimed the job, a late
    /// worker's result is dropped). Returns whether the job was this worker's to end.
    pub async fn finish(
        &self,
        id: &str,
        attempt: i64,
        state: &str,
        error: Option<&str>,
        result: Option<&serde_json::Value>,
    ) -> Result<bool, sqlx::Error> {
        let done = sqlx::query("UPDATE jobs SET state = ?, error = ?, result = ?, finished_at = ?, progress = CASE WHEN ? = 'succeeded' THEN 1 ELSE progress END WHERE id = ? AND state = 'running' AND attempts = ?")
            .bind(state)
            .bind(error)
            .bind(result.map(|r| r.to_string()))
            .bind(now())
            .bind(state)
            .bind(id)
            .bind(attempt)
            .execute(&self.pool)
            .await?;
        Ok(done.rows_affected() == 1)
    }

    /// Requests cancellation: a queued job ends at once; a running one at its next check.
    /// Returns the job after the change, or `None` if it does not exist.
    pub async fn cancel(&self, id: &str) -> Result<Option<JobRow>, sqlx::Error> {
        sqlx::query("UPDATE jobs SET state = 'cancelled', finished_at = ?, message = 'cancelled before it started' WHERE id = ? AND state = 'queued'")
            .bind(now())
            .bind(id)
            .execute(&self.pool)
            .await?;
        sqlx::query("UPDATE jobs SET cancel_requested = 1 WHERE id = ? AND state = 'running'")
            .bind(id)
            .execute(&self.pool)
            .await?;
        self.job(id).await
    }

    pub async fn cancel_requested(&self, id: &str) -> bool {
        sqlx::query("SELECT cancel_requested FROM jobs WHERE id = ?")
            .bind(id)
            .fetch_optional(&self.pool)
            .await
            .ok()
            .flatten()
            .is_some_and(|r| r.get::<i64, _>("cancel_requested") != 0)
    }

    /// After a crash: jobs left `running` go back to the queue, or fail after their last
    /// attempt. Returns (requeued, failed).
    pub async fn recover(&self) -> Result<(u64, u64), sqlx::Error> {
        let failed = sqlx::query(
            "UPDATE jobs SET state = 'failed', finished_at = ?, error = 'interrupted by a restart on its last attempt' WHERE state = 'running' AND attempts >= max_attempts",
        )
        .bind(now())
        .execute(&self.pool)
        .await?
        .rows_affected();
        let requeued = sqlx::query(
            "UPDATE jobs SET state = 'queued', message = 're-queued after a restart' WHERE state = 'running'",
        )
        .execute(&self.pool)
        .await?
        .rows_affected();
        Ok((requeued, failed))
    }

    /// Puts a running job back in the queue (graceful shutdown), not counting the attempt;
    /// fenced by the attempt like `finish`.
    pub async fn requeue(&self, id: &str, attempt: i64) -> Result<bool, sqlx::Error> {
        let done = sqlx::query("UPDATE jobs SET state = 'queued', attempts = attempts - 1, message = 're-queued at shutdown' WHERE id = ? AND state = 'running' AND attempts = ?")
            .bind(id)
            .bind(attempt)
            .execute(&self.pool)
            .await?;
        Ok(done.rows_affected() == 1)
    }
}

#[cfg(test)]
mod tests {
    #[test]
    fn timestamps_are_rfc3339() {
        let t = super::now();
        assert_eq!(t.len(), 24, "{t}");
        assert!(t.starts_with("20") && t.ends_with('Z') && &t[10..11] == "T");
    }
}
