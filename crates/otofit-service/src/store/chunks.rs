//! Chunks of simulate jobs (the `job_chunks` table): a job's rows split into chunks,
//! planned once at its first attempt, each claimed with a lease of its own by any worker
//! (the job's owner or an idle dispatcher anywhere), fenced by its token like a job.
//! The part files on disk say which chunks are finished (`dataset::read_part`); this
//! table says who works on which.

use super::{Cols, Pool, Store, new_token};
use std::time::Duration;

/// One chunk: rows `first_row .. first_row + n_rows` of job `job_id`.
#[derive(Clone, Debug, PartialEq)]
pub struct ChunkRow {
    /// `<job id>:<idx, 5 digits>`.
    pub id: String,
    /// The simulate job the chunk belongs to.
    pub job_id: String,
    /// The chunk's position in the job, from 0.
    pub idx: usize,
    /// The first dataset row the chunk simulates.
    pub first_row: usize,
    /// How many rows it simulates.
    pub n_rows: usize,
    /// `queued`, `running` or `done`.
    pub state: String,
    /// The worker that holds (or last held) the chunk.
    pub worker: Option<String>,
    /// Claims of the chunk so far.
    pub attempts: i64,
}

/// A claimed chunk: its row and the fencing token of this claim.
#[derive(Clone, Debug)]
pub struct ChunkClaim {
    /// The chunk as claimed.
    pub chunk: ChunkRow,
    /// The claim's fencing token: writes for the chunk are refused once another claim has it.
    pub token: String,
}

fn chunk_from(row: &impl Cols) -> Result<ChunkRow, sqlx::Error> {
    Ok(ChunkRow {
        id: row.text("id")?,
        job_id: row.text("job_id")?,
        idx: row.int("idx")? as usize,
        first_row: row.int("first_row")? as usize,
        n_rows: row.int("n_rows")? as usize,
        state: row.text("state")?,
        worker: row.opt_text("worker")?,
        attempts: row.int("attempts")?,
    })
}

/// Whether `chunks` (in order) cover rows `0..n` once each, in a row.
fn covers(chunks: &[ChunkRow], n: usize) -> bool {
    let mut next = 0;
    for (i, c) in chunks.iter().enumerate() {
        if c.idx != i || c.first_row != next || c.n_rows == 0 {
            return false;
        }
        next += c.n_rows;
    }
    next == n
}

/// The id of chunk `idx` of `job`.
pub fn chunk_id(job: &str, idx: usize) -> String {
    format!("{job}:{idx:05}")
}

impl Store {
    /// The chunks of `job`: planned now as `plan` (first row, rows) unless the job has a
    /// complete plan already (from an earlier attempt, whatever chunk size that attempt's
    /// worker used). The plan is written in one transaction: a process killed while
    /// planning leaves no plan, not part of one. A plan that does not cover the same rows
    /// as `plan` (left by a version that planned chunk by chunk) is replaced. In chunk order.
    pub async fn plan_chunks(&self, job: &str, plan: &[(usize, usize)]) -> Result<Vec<ChunkRow>, sqlx::Error> {
        const INSERT: &str = "INSERT INTO job_chunks (id, job_id, idx, first_row, n_rows) VALUES ($1, $2, $3, $4, $5)
             ON CONFLICT DO NOTHING";
        const DELETE: &str = "DELETE FROM job_chunks WHERE job_id = $1";
        let total: usize = plan.iter().map(|(_, n)| n).sum();
        let existing = self.chunks(job).await?;
        if existing.is_empty() || !covers(&existing, total) {
            if !existing.is_empty() {
                tracing::warn!(job, chunks = existing.len(), rows = total, "an incomplete chunk plan replaced");
            }
            on_pool!(self, p => {
                let mut tx = p.begin().await?;
                sqlx::query(DELETE).bind(job).execute(&mut *tx).await?;
                for (idx, (first, n)) in plan.iter().enumerate() {
                    sqlx::query(INSERT)
                        .bind(chunk_id(job, idx))
                        .bind(job)
                        .bind(idx as i64)
                        .bind(*first as i64)
                        .bind(*n as i64)
                        .execute(&mut *tx)
                        .await?;
                }
                tx.commit().await?
            });
        }
        // Queued chunks, new or left by an earlier attempt: idle workers elsewhere may help.
        self.announce_work().await?;
        self.chunks(job).await
    }

    /// The chunks of `job`, in order (none for a job that was never run or is not a
    /// simulate job).
    pub async fn chunks(&self, job: &str) -> Result<Vec<ChunkRow>, sqlx::Error> {
        const SQL: &str = "SELECT * FROM job_chunks WHERE job_id = $1 ORDER BY idx";
        Ok(
            on_pool!(self, p => sqlx::query(SQL).bind(job).fetch_all(p).await?.iter().map(chunk_from).collect::<Result<_, _>>()?),
        )
    }

    /// Claims a chunk that is neither done nor held under a live lease, of `job` or (with
    /// `None`) of any running, not cancelled job, with a fresh token and a lease of
    /// `lease` on the database clock. One statement; with PostgreSQL the row is picked
    /// `FOR UPDATE SKIP LOCKED` so concurrent claimers take different chunks.
    pub async fn claim_chunk(
        &self,
        job: Option<&str>,
        worker: &str,
        lease: Duration,
    ) -> Result<Option<ChunkClaim>, sqlx::Error> {
        const SQL: &str = "UPDATE job_chunks SET state = 'running', lease_token = $1, lease_expires_ms = NOW_MS + $2,
                 worker = $3, attempts = attempts + 1
             WHERE id = (SELECT c.id FROM job_chunks c JOIN jobs j ON j.id = c.job_id
                         WHERE ($4 IS NULL OR c.job_id = $4) AND j.state = 'running' AND j.cancel_requested = 0
                           AND (c.state = 'queued' OR (c.state = 'running' AND c.lease_expires_ms < NOW_MS))
                         ORDER BY j.created_at, c.job_id, c.idx LIMIT 1 SKIP_LOCKED)
               AND (state = 'queued' OR (state = 'running' AND lease_expires_ms < NOW_MS))
             RETURNING *";
        let skip = if self.is_postgres() { "FOR UPDATE OF c SKIP LOCKED" } else { "" };
        let sql = self.clocked(&SQL.replace("SKIP_LOCKED", skip));
        let (token, ms) = (new_token(), lease.as_millis() as i64);
        let row = on_pool!(self, p => sqlx::query(sql)
            .bind(&token)
            .bind(ms)
            .bind(worker)
            .bind(job)
            .fetch_optional(p)
            .await?
            .as_ref()
            .map(chunk_from)
            .transpose()?);
        Ok(row.map(|chunk| ChunkClaim { chunk, token }))
    }

    /// Renews the lease of a chunk claim; `false`: lost (the chunk is another's now).
    pub async fn chunk_heartbeat(&self, claim: &ChunkClaim, lease: Duration) -> Result<bool, sqlx::Error> {
        const SQL: &str = "UPDATE job_chunks SET lease_expires_ms = NOW_MS + $3
             WHERE id = $1 AND state = 'running' AND lease_token = $2";
        let sql = self.clocked(SQL);
        let ms = lease.as_millis() as i64;
        let n = on_pool!(self, p => sqlx::query(sql)
            .bind(&claim.chunk.id)
            .bind(&claim.token)
            .bind(ms)
            .execute(p)
            .await?
            .rows_affected());
        Ok(n == 1)
    }

    /// Ends a chunk claim: `done` (its part is in place) or back to `queued` (stopped or
    /// failed, for any worker to take at once). Fenced by the claim's token; returns
    /// whether the chunk was still this claim's.
    pub async fn end_chunk(&self, claim: &ChunkClaim, done: bool) -> Result<bool, sqlx::Error> {
        const SQL: &str = "UPDATE job_chunks SET state = $3, lease_token = NULL
             WHERE id = $1 AND state = 'running' AND lease_token = $2";
        let state = if done { "done" } else { "queued" };
        let n = on_pool!(self, p => sqlx::query(SQL)
            .bind(&claim.chunk.id)
            .bind(&claim.token)
            .bind(state)
            .execute(p)
            .await?
            .rows_affected());
        if n == 1 && !done {
            self.announce_work().await?;
        }
        Ok(n == 1)
    }

    /// Sets a chunk's state whatever its claim: `done` when its part is found on disk
    /// (finished by a worker that died before saying so), `queued` when a chunk marked
    /// done has no part (the files were removed).
    pub async fn set_chunk_state(&self, id: &str, state: &str) -> Result<(), sqlx::Error> {
        const SQL: &str = "UPDATE job_chunks SET state = $2, lease_token = NULL WHERE id = $1";
        on_pool!(self, p => sqlx::query(SQL).bind(id).bind(state).execute(p).await?.rows_affected());
        Ok(())
    }
}
