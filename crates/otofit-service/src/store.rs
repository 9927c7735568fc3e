//! The service's state (sqlx): models and jobs, in SQLite (embedded, the default) or
//! PostgreSQL (shared by any number of `serve` and `worker` processes). Static SQL with
//! bound parameters only, the same text for both backends (`$N` placeholders, which
//! SQLite reads as numbered ones) except where noted; every state change of a job is
//! one statement.
//!
//! Jobs are claimed with a lease: the claim writes a fresh `lease_token` and an expiry on
//! the database clock; the worker renews it (`heartbeat`) while it runs, and every write
//! of the attempt (progress, its end, a re-queue) is fenced by the token, so a worker
//! that lost its lease (stalled, partitioned, killed and re-claimed) changes nothing.

use serde::Serialize;
use sqlx::postgres::{PgPool, PgPoolOptions, PgRow};
use sqlx::sqlite::{
    SqliteConnectOptions, SqliteJournalMode, SqlitePool, SqlitePoolOptions, SqliteRow, SqliteSynchronous,
};
use sqlx::{AssertSqlSafe, Row};
use std::path::{Path, PathBuf};
use std::time::Duration;

/// Where the state lives, from `--database`.
#[derive(Clone, Debug, PartialEq)]
pub enum Database {
    /// A SQLite file (`sqlite://PATH` or `sqlite:PATH`); `serve` defaults to
    /// `DATA_DIR/otofit.db`.
    Sqlite(PathBuf),
    /// A PostgreSQL URL (`postgres://…` or `postgresql://…`), kept as given.
    Postgres(String),
}

/// A `--database` value that cannot be used.
#[derive(Debug, thiserror::Error)]
#[error("--database: {0}")]
pub struct DatabaseUrlError(String);

impl Database {
    /// Parses `sqlite://PATH`, `sqlite:PATH`, `postgres://…` or `postgresql://…`.
    pub fn parse(url: &str) -> Result<Database, DatabaseUrlError> {
        let url = url.trim();
        if let Some(rest) = url.strip_prefix("sqlite://").or_else(|| url.strip_prefix("sqlite:")) {
            let path = rest.split('?').next().unwrap_or("");
            if path.is_empty() || path == ":memory:" {
                return Err(DatabaseUrlError(format!(
                    "'{url}' names no file (sqlite://PATH, e.g. sqlite://data/otofit.db)"
                )));
            }
            return Ok(Database::Sqlite(PathBuf::from(path)));
        }
        if url.starts_with("postgres://") || url.starts_with("postgresql://") {
            // The pool checks the rest (host, port, user, database) when it connects.
            return Ok(Database::Postgres(url.to_string()));
        }
        let scheme = url.split_once(':').map_or(url, |(s, _)| s);
        Err(DatabaseUrlError(format!("unsupported scheme '{scheme}' (sqlite://PATH or postgres://USER@HOST:PORT/DB)")))
    }

    /// The URL for logs: a password, if any, replaced by `***`.
    pub fn redacted(&self) -> String {
        match self {
            Database::Sqlite(p) => format!("sqlite://{}", p.display()),
            Database::Postgres(url) => {
                let (scheme, rest) = url.split_once("://").unwrap_or(("postgres", url));
                match rest.split_once('@') {
                    Some((user, host)) if user.contains(':') => {
                        format!("{scheme}://{}:***@{host}", user.split(':').next().unwrap_or(""))
                    }
                    _ => url.clone(),
                }
            }
        }
    }
}

/// The connection pool of one backend (one enum so that every query is written once for both).
#[derive(Clone, Debug)]
pub enum Pool {
    /// SQLite, for a single host (the default under the data dir).
    Sqlite(SqlitePool),
    /// PostgreSQL, shared by workers on several hosts.
    Postgres(PgPool),
}

/// The job queue, model registry, API keys and chunks of one deployment, on either backend.
#[derive(Clone)]
pub struct Store {
    /// The backend's pool (`on_pool!` runs a query on whichever it is).
    pub pool: Pool,
}

/// Runs `$body` with `$p` bound to the pool of whichever backend the store has (the same
/// query text and binds compile against both drivers).
macro_rules! on_pool {
    ($store:expr, $p:ident => $body:expr) => {
        match &$store.pool {
            Pool::Sqlite($p) => $body,
            Pool::Postgres($p) => $body,
        }
    };
}

mod chunks;
mod keys;
mod relabel;

/// The PostgreSQL channel on which processes announce work ([`Store::announce_work`]).
pub const WORK_CHANNEL: &str = "otofit_work";

/// The SQLite schema's migrations.
static SQLITE_MIGRATIONS: sqlx::migrate::Migrator = sqlx::migrate!("../../migrations");
/// The PostgreSQL schema's migrations (the same tables, its own types).
static POSTGRES_MIGRATIONS: sqlx::migrate::Migrator = sqlx::migrate!("../../migrations/postgres");
pub use chunks::{ChunkClaim, ChunkRow, chunk_id};
pub use keys::{ApiKey, KeyOwner, NewKey, key_hash};

/// A registered model: a checkpoint file the service can load by id.
#[derive(Clone, Debug, Serialize)]
pub struct ModelRow {
    /// The model's id, as clients name it.
    pub id: String,
    /// Where its checkpoint is: a file path, or its URL in the object store.
    pub path: String,
    /// Whether /infer uses it when a request names no model.
    pub is_default: bool,
    /// When it was registered (RFC 3339).
    pub created_at: String,
    /// The train job that made it; `None` for models registered by hand.
    pub source_job: Option<String>,
    /// The tenant the model belongs to (its source job's); `None`: shared by all.
    pub tenant: Option<String>,
}

/// Where a job is in its life: queued → running → succeeded, failed or cancelled (a
/// failed attempt with attempts left, or a job re-queued at shutdown, is queued again).
/// Stored and served as its lower-case name.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, serde::Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum JobState {
    /// Waiting for a worker (or for its retry's backoff to pass).
    Queued,
    /// Claimed by a worker under a lease.
    Running,
    /// Ended with a result.
    Succeeded,
    /// Ended without one, its attempts spent.
    Failed,
    /// Ended at a client's request.
    Cancelled,
}

impl JobState {
    /// Every state, in the order of a job's life.
    pub const ALL: [JobState; 5] =
        [JobState::Queued, JobState::Running, JobState::Succeeded, JobState::Failed, JobState::Cancelled];

    /// The stored and served name.
    pub fn as_str(self) -> &'static str {
        match self {
            JobState::Queued => "queued",
            JobState::Running => "running",
            JobState::Succeeded => "succeeded",
            JobState::Failed => "failed",
            JobState::Cancelled => "cancelled",
        }
    }

    /// The state called `name`, if any.
    pub fn parse(name: &str) -> Option<JobState> {
        JobState::ALL.into_iter().find(|s| s.as_str() == name)
    }

    /// Queued or running: not ended.
    pub fn is_active(self) -> bool {
        matches!(self, JobState::Queued | JobState::Running)
    }
}

impl std::fmt::Display for JobState {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(self.as_str())
    }
}

impl PartialEq<&str> for JobState {
    fn eq(&self, other: &&str) -> bool {
        self.as_str() == *other
    }
}

/// A job as stored: its spec, where it is in its life and how it ended.
#[derive(Clone, Debug, Serialize)]
pub struct JobRow {
    /// The job's id (`jobs::new_id`: time-ordered hex).
    pub id: String,
    /// The tenant that made the job (and owns its dataset, report and model).
    pub tenant: String,
    /// `simulate`, `train`, `diagnose` or another kind of `JobSpec`.
    pub kind: String,
    /// Where the job is in its life.
    pub state: JobState,
    /// The job's parameters as JSON (the `JobSpec` without its kind).
    pub params: serde_json::Value,
    /// Fraction done, 0 to 1, as last reported by the worker.
    pub progress: f64,
    /// The worker's last progress message.
    pub message: String,
    /// Attempts started so far (a retry or re-queue after a crash adds one).
    pub attempts: i64,
    /// Attempts allowed before the job fails for good.
    pub max_attempts: i64,
    /// Whether a client asked to cancel it (the worker checks between steps).
    pub cancel_requested: bool,
    /// Why the last attempt failed, if it did.
    pub error: Option<String>,
    /// What the job produced (paths, summary numbers), once it succeeded.
    pub result: Option<serde_json::Value>,
    /// When the job was queued (RFC 3339).
    pub created_at: String,
    /// When its current or last attempt started.
    pub started_at: Option<String>,
    /// When it ended (succeeded, failed or cancelled).
    pub finished_at: Option<String>,
    /// A failed attempt's job waits in the queue until then (RFC 3339; `error` says why
    /// the attempt failed); `None`: claimable at once, or not queued.
    pub retry_at: Option<String>,
    /// The fencing token of the current claim (never shown to clients).
    #[serde(skip)]
    pub lease_token: Option<String>,
    /// The worker that holds (or last held) the job: `host:pid`.
    #[serde(skip)]
    pub worker: Option<String>,
}

/// RFC 3339 UTC timestamp of now, to the millisecond.
pub fn now() -> String {
    let d = std::time::SystemTime::now().duration_since(std::time::UNIX_EPOCH).unwrap_or_default();
    rfc3339_ms(d.as_millis() as i64)
}

/// RFC 3339 UTC timestamp of `ms` since 1970, to the millisecond.
pub fn rfc3339_ms(ms: i64) -> String {
    let secs = ms.div_euclid(1000);
    let millis = ms.rem_euclid(1000);
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
    format!("{year:04}-{month:02}-{day:02}T{:02}:{:02}:{:02}.{:03}Z", rem / 3600, rem % 3600 / 60, rem % 60, millis)
}

/// Typed column access shared by the two drivers' rows. A column of an unexpected type
/// (a schema drift) is an error of the query, never a panic inside a handler or the
/// dispatcher.
trait Cols {
    fn text(&self, c: &str) -> Result<String, sqlx::Error>;
    fn opt_text(&self, c: &str) -> Result<Option<String>, sqlx::Error>;
    fn int(&self, c: &str) -> Result<i64, sqlx::Error>;
    fn opt_int(&self, c: &str) -> Result<Option<i64>, sqlx::Error>;
    fn real(&self, c: &str) -> Result<f64, sqlx::Error>;
}

macro_rules! impl_cols {
    ($row:ty) => {
        impl Cols for $row {
            fn text(&self, c: &str) -> Result<String, sqlx::Error> {
                self.try_get(c)
            }
            fn opt_text(&self, c: &str) -> Result<Option<String>, sqlx::Error> {
                self.try_get(c)
            }
            fn int(&self, c: &str) -> Result<i64, sqlx::Error> {
                self.try_get(c)
            }
            fn opt_int(&self, c: &str) -> Result<Option<i64>, sqlx::Error> {
                self.try_get(c)
            }
            fn real(&self, c: &str) -> Result<f64, sqlx::Error> {
                self.try_get(c)
            }
        }
    };
}
impl_cols!(SqliteRow);
impl_cols!(PgRow);

fn job_from(row: &impl Cols) -> Result<JobRow, sqlx::Error> {
    let json = |s: Option<String>| s.and_then(|s| serde_json::from_str(&s).ok());
    let text = row.text("state")?;
    let state = JobState::parse(&text).ok_or_else(|| sqlx::Error::ColumnDecode {
        index: "state".into(),
        source: format!("unknown job state '{text}'").into(),
    })?;
    Ok(JobRow {
        id: row.text("id")?,
        tenant: row.text("tenant")?,
        kind: row.text("kind")?,
        retry_at: row.opt_int("run_after_ms")?.filter(|_| state == JobState::Queued).map(rfc3339_ms),
        state,
        params: json(Some(row.text("params")?)).unwrap_or(serde_json::Value::Null),
        progress: row.real("progress")?,
        message: row.text("message")?,
        attempts: row.int("attempts")?,
        max_attempts: row.int("max_attempts")?,
        cancel_requested: row.int("cancel_requested")? != 0,
        error: row.opt_text("error")?,
        result: json(row.opt_text("result")?),
        created_at: row.text("created_at")?,
        started_at: row.opt_text("started_at")?,
        finished_at: row.opt_text("finished_at")?,
        lease_token: row.opt_text("lease_token")?,
        worker: row.opt_text("worker")?,
    })
}

fn model_from(row: &impl Cols) -> Result<ModelRow, sqlx::Error> {
    Ok(ModelRow {
        id: row.text("id")?,
        path: row.text("path")?,
        is_default: row.int("is_default")? != 0,
        created_at: row.text("created_at")?,
        source_job: row.opt_text("source_job")?,
        tenant: row.opt_text("tenant")?,
    })
}

/// Active jobs of one kind in one state, for /metrics.
#[derive(Clone, Debug, PartialEq)]
pub struct QueueCount {
    /// The job kind.
    pub kind: String,
    /// The job state.
    pub state: String,
    /// How many jobs of that kind are in that state.
    pub count: i64,
}

/// Most active (queued + running) jobs: in all, and of one tenant.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct QueueBounds {
    /// Most active jobs in all (the queue's length).
    pub queue: i64,
    /// Most active jobs of any one tenant.
    pub per_tenant: i64,
}

/// Whether a job was queued, or which bound refused it.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Admission {
    /// The job is in the queue.
    Queued,
    /// The queue holds its limit of active (queued + running) jobs.
    QueueFull,
    /// The tenant has its limit of active jobs.
    TenantFull,
}

/// A fresh lease token: 128 random bits, hex.
pub fn new_token() -> String {
    use rand::Rng;
    format!("{:032x}", rand::rng().random::<u128>())
}

/// `host:pid` of this process, naming it as a worker in the job table.
pub fn worker_name() -> String {
    let host = std::fs::read_to_string("/etc/hostname").map(|h| h.trim().to_string()).unwrap_or_default();
    let host = if host.is_empty() { "localhost".to_string() } else { host };
    format!("{host}:{}", std::process::id())
}

/// The tenant of jobs made before tenants existed, by a keyless server or with a
/// `--api-key-hash` key.
pub const DEFAULT_TENANT: &str = "default";

/// Key of the PostgreSQL advisory lock that serialises `insert_job_within`.
const QUEUE_LOCK: i64 = 0x6f746f666974; // "otofit"

impl Store {
    /// Opens (creating if needed) the SQLite database in WAL mode and applies migrations.
    pub async fn open(path: &Path) -> Result<Store, sqlx::Error> {
        let opts = SqliteConnectOptions::new()
            .filename(path)
            .create_if_missing(true)
            .journal_mode(SqliteJournalMode::Wal)
            .synchronous(SqliteSynchronous::Normal)
            .busy_timeout(Duration::from_secs(5))
            .foreign_keys(true);
        let pool = SqlitePoolOptions::new().max_connections(4).connect_with(opts).await?;
        let store = Store { pool: Pool::Sqlite(pool.clone()) };
        relabel::repair(&store, &SQLITE_MIGRATIONS, &relabel::SQLITE).await?;
        SQLITE_MIGRATIONS.run(&pool).await?;
        Ok(store)
    }

    /// Connects to PostgreSQL and applies its migrations (`migrations/postgres`; sqlx takes
    /// an advisory lock, so processes starting together migrate once).
    pub async fn open_postgres(url: &str) -> Result<Store, sqlx::Error> {
        let pool =
            PgPoolOptions::new().max_connections(8).acquire_timeout(Duration::from_secs(10)).connect(url).await?;
        let store = Store { pool: Pool::Postgres(pool.clone()) };
        relabel::repair(&store, &POSTGRES_MIGRATIONS, &relabel::POSTGRES).await?;
        POSTGRES_MIGRATIONS.run(&pool).await?;
        Ok(store)
    }

    /// Opens the store `db` names.
    pub async fn connect(db: &Database) -> Result<Store, sqlx::Error> {
        match db {
            Database::Sqlite(path) => Store::open(path).await,
            Database::Postgres(url) => Store::open_postgres(url).await,
        }
    }

    /// Whether the backend is PostgreSQL (some behaviour, such as lease recovery timing, differs).
    pub fn is_postgres(&self) -> bool {
        matches!(self.pool, Pool::Postgres(_))
    }

    /// The SQLite pool, for tests and tools that speak SQLite only.
    pub fn sqlite(&self) -> Option<&SqlitePool> {
        match &self.pool {
            Pool::Sqlite(p) => Some(p),
            Pool::Postgres(_) => None,
        }
    }

    /// `sql` with `NOW_MS` replaced by this backend's clock in ms since 1970: the
    /// database's clock, so workers on several hosts agree on lease expiry.
    fn clocked(&self, sql: &str) -> AssertSqlSafe<String> {
        let now_ms = match self.pool {
            Pool::Sqlite(_) => "CAST((julianday('now') - 2440587.5) * 86400000.0 AS INTEGER)",
            Pool::Postgres(_) => "CAST(EXTRACT(EPOCH FROM clock_timestamp()) * 1000 AS BIGINT)",
        };
        AssertSqlSafe(sql.replace("NOW_MS", now_ms))
    }

    /// Whether the database answers a trivial query (for /ready).
    pub async fn ping(&self) -> bool {
        on_pool!(self, p => sqlx::query("SELECT 1").fetch_one(p).await.is_ok())
    }

    /// Registers a model; it belongs to `source_job`'s tenant, or to every tenant
    /// without a source job (the default model, models the operator registers).
    pub async fn add_model(
        &self,
        id: &str,
        path: &str,
        is_default: bool,
        source_job: Option<&str>,
    ) -> Result<(), sqlx::Error> {
        const SQL: &str = "INSERT INTO models (id, path, is_default, created_at, source_job, tenant)
             VALUES ($1, $2, $3, $4, $5, (SELECT tenant FROM jobs WHERE id = $5))
             ON CONFLICT DO NOTHING";
        let ts = now();
        on_pool!(self, p => sqlx::query(SQL)
            .bind(id)
            .bind(path)
            .bind(is_default as i64)
            .bind(&ts)
            .bind(source_job)
            .execute(p)
            .await?
            .rows_affected());
        Ok(())
    }

    /// The models `tenant` may use (its own and the shared ones); all with `None`.
    pub async fn models(&self, tenant: Option<&str>) -> Result<Vec<ModelRow>, sqlx::Error> {
        const SQL: &str =
            "SELECT * FROM models WHERE ($1 IS NULL OR tenant IS NULL OR tenant = $1) ORDER BY created_at, id";
        Ok(
            on_pool!(self, p => sqlx::query(SQL).bind(tenant).fetch_all(p).await?.iter().map(model_from).collect::<Result<_, _>>()?),
        )
    }

    /// The registered model `id`, if any.
    pub async fn model(&self, id: &str) -> Result<Option<ModelRow>, sqlx::Error> {
        const SQL: &str = "SELECT * FROM models WHERE id = $1";
        Ok(
            on_pool!(self, p => sqlx::query(SQL).bind(id).fetch_optional(p).await?.as_ref().map(model_from).transpose()?),
        )
    }

    /// The model marked as default, if any.
    pub async fn default_model(&self) -> Result<Option<ModelRow>, sqlx::Error> {
        const SQL: &str = "SELECT * FROM models WHERE is_default = 1 LIMIT 1";
        Ok(on_pool!(self, p => sqlx::query(SQL).fetch_optional(p).await?.as_ref().map(model_from).transpose()?))
    }

    /// Tells the dispatchers of other processes that there is work to claim (a job queued,
    /// chunks planned or given back): a PostgreSQL NOTIFY on [`WORK_CHANNEL`], which
    /// [`Store::listen_for_work`] turns into a wake-up. With SQLite every dispatcher is in
    /// this process and `Ctx::notify` reaches them; nothing is sent.
    pub async fn announce_work(&self) -> Result<(), sqlx::Error> {
        if let Pool::Postgres(pool) = &self.pool {
            sqlx::query("SELECT pg_notify($1, '')").bind(WORK_CHANNEL).execute(pool).await?;
        }
        Ok(())
    }

    /// Calls `wake` each time a process announces work, for as long as the process runs
    /// (PostgreSQL LISTEN on its own connection, which sqlx re-opens if it drops). Idle
    /// dispatchers then start on new work at once instead of at their next poll. Returns
    /// at once with SQLite.
    pub async fn listen_for_work(&self, wake: impl Fn()) {
        let Pool::Postgres(pool) = &self.pool else { return };
        loop {
            let listening = async {
                let mut listener = sqlx::postgres::PgListener::connect_with(pool).await?;
                listener.listen(WORK_CHANNEL).await?;
                loop {
                    listener.recv().await?;
                    wake();
                }
            };
            let res: Result<(), sqlx::Error> = listening.await;
            if let Err(e) = res {
                tracing::warn!(error = %e, "listening for work failed; polling meanwhile");
            }
            tokio::time::sleep(std::time::Duration::from_secs(1)).await;
        }
    }

    /// Queues a job if fewer than `limit` jobs are queued or running. The count and the
    /// insert are one statement; SQLite takes the write lock before it reads, and with
    /// PostgreSQL the statement runs under a transaction-scoped advisory lock (READ
    /// COMMITTED alone would let two inserts see the same count), so concurrent posts,
    /// from any number of servers, cannot overshoot the limit. Returns whether the job
    /// was queued.
    pub async fn insert_job_within(
        &self,
        id: &str,
        kind: &str,
        params: &serde_json::Value,
        max_attempts: i64,
        limit: i64,
    ) -> Result<bool, sqlx::Error> {
        let bounds = QueueBounds { queue: limit, per_tenant: limit };
        let admitted = self.insert_tenant_job_within(id, DEFAULT_TENANT, kind, params, max_attempts, bounds).await?;
        Ok(admitted == Admission::Queued)
    }

    /// `insert_job_within` for a job of `tenant`, which may have at most `bounds.per_tenant`
    /// jobs queued or running (so that one tenant cannot fill the whole queue): both
    /// counts and the insert are one statement, as there.
    pub async fn insert_tenant_job_within(
        &self,
        id: &str,
        tenant: &str,
        kind: &str,
        params: &serde_json::Value,
        max_attempts: i64,
        bounds: QueueBounds,
    ) -> Result<Admission, sqlx::Error> {
        let QueueBounds { queue: limit, per_tenant: tenant_limit } = bounds;
        const SQL: &str = "INSERT INTO jobs (id, kind, params, max_attempts, created_at, tenant)
             SELECT $1, $2, $3, $4, $5, $7
             WHERE (SELECT COUNT(*) FROM jobs WHERE state IN ('queued', 'running')) < $6
               AND (SELECT COUNT(*) FROM jobs WHERE state IN ('queued', 'running') AND tenant = $7) < $8";
        let (params, ts) = (params.to_string(), now());
        // The same statement for both drivers (a macro: the query type depends on the driver).
        macro_rules! insert {
            () => {
                sqlx::query(SQL)
                    .bind(id)
                    .bind(kind)
                    .bind(&params)
                    .bind(max_attempts)
                    .bind(&ts)
                    .bind(limit)
                    .bind(tenant)
                    .bind(tenant_limit)
            };
        }
        let done = match &self.pool {
            Pool::Sqlite(p) => insert!().execute(p).await?.rows_affected(),
            Pool::Postgres(p) => {
                let mut tx = p.begin().await?;
                sqlx::query("SELECT pg_advisory_xact_lock($1)").bind(QUEUE_LOCK).execute(&mut *tx).await?;
                // A statement of its own after the lock: its snapshot sees every insert
                // committed by the lock's previous holder.
                let n = insert!().execute(&mut *tx).await?.rows_affected();
                if n == 1 {
                    // Delivered at the commit: the listening dispatchers of other
                    // processes see the job as soon as it can be claimed.
                    sqlx::query("SELECT pg_notify($1, '')").bind(WORK_CHANNEL).execute(&mut *tx).await?;
                }
                tx.commit().await?;
                n
            }
        };
        if done == 1 {
            return Ok(Admission::Queued);
        }
        // Which bound refused it, for the answer (counted again: a job may have ended since).
        const MINE: &str = "SELECT COUNT(*) FROM jobs WHERE state IN ('queued', 'running') AND tenant = $1";
        let mine: i64 = on_pool!(self, p => sqlx::query_scalar(MINE).bind(tenant).fetch_one(p).await?);
        Ok(if mine >= tenant_limit { Admission::TenantFull } else { Admission::QueueFull })
    }

    /// The job `id`, if any.
    pub async fn job(&self, id: &str) -> Result<Option<JobRow>, sqlx::Error> {
        const SQL: &str = "SELECT * FROM jobs WHERE id = $1";
        Ok(on_pool!(self, p => sqlx::query(SQL).bind(id).fetch_optional(p).await?.as_ref().map(job_from).transpose()?))
    }

    /// The newest `limit` jobs (of `state` if given) of `tenant`; of all tenants with `None`.
    pub async fn jobs(
        &self,
        state: Option<&str>,
        limit: i64,
        tenant: Option<&str>,
    ) -> Result<Vec<JobRow>, sqlx::Error> {
        const SQL: &str = "SELECT * FROM jobs WHERE ($1 IS NULL OR state = $1) AND ($3 IS NULL OR tenant = $3)
             ORDER BY created_at DESC, id DESC LIMIT $2";
        Ok(on_pool!(self, p => sqlx::query(SQL)
            .bind(state)
            .bind(limit)
            .bind(tenant)
            .fetch_all(p)
            .await?
            .iter()
            .map(job_from)
            .collect::<Result<_, _>>()?))
    }

    /// Claims the oldest queued job that is due (not waiting out a retry's backoff)
    /// atomically (one statement), counting the attempt,
    /// with a fresh lease token and a lease of `lease` on the database clock. With
    /// PostgreSQL the row is picked `FOR UPDATE SKIP LOCKED`, so concurrent claimers
    /// take different jobs instead of queueing on the same row; SQLite serialises writers.
    pub async fn claim(&self, worker: &str, lease: Duration) -> Result<Option<JobRow>, sqlx::Error> {
        const SQL: &str =
            "UPDATE jobs SET state = 'running', attempts = attempts + 1, started_at = $1, message = 'started',
                 lease_token = $2, lease_expires_ms = NOW_MS + $3, worker = $4, run_after_ms = NULL
             WHERE id = (SELECT id FROM jobs WHERE state = 'queued' AND (run_after_ms IS NULL OR run_after_ms <= NOW_MS)
                         ORDER BY created_at, id LIMIT 1 SKIP_LOCKED)
               AND state = 'queued'
             RETURNING *";
        let skip = if self.is_postgres() { "FOR UPDATE SKIP LOCKED" } else { "" };
        let sql = self.clocked(&SQL.replace("SKIP_LOCKED", skip));
        let (ts, token, ms) = (now(), new_token(), lease.as_millis() as i64);
        Ok(on_pool!(self, p => sqlx::query(sql)
            .bind(&ts)
            .bind(&token)
            .bind(ms)
            .bind(worker)
            .fetch_optional(p)
            .await?
            .as_ref()
            .map(job_from)
            .transpose()?))
    }

    /// Renews the lease of the claim `token` for `lease` more. `false`: the lease is lost
    /// (expired and taken back, or the job ended); the worker must stop and write nothing.
    pub async fn heartbeat(&self, id: &str, token: &str, lease: Duration) -> Result<bool, sqlx::Error> {
        const SQL: &str = "UPDATE jobs SET lease_expires_ms = NOW_MS + $3
             WHERE id = $1 AND state = 'running' AND lease_token = $2";
        let sql = self.clocked(SQL);
        let ms = lease.as_millis() as i64;
        let n = on_pool!(self, p => sqlx::query(sql).bind(id).bind(token).bind(ms).execute(p).await?.rows_affected());
        Ok(n == 1)
    }

    /// Jobs whose worker stopped renewing its lease go back to the queue (their token
    /// cleared, so that worker's later writes are refused), or fail after their last
    /// attempt. Any worker calls this before it claims. Returns (requeued, failed).
    pub async fn reap_expired(&self) -> Result<(u64, u64), sqlx::Error> {
        const FAIL: &str = "UPDATE jobs SET state = 'failed', finished_at = $1, lease_token = NULL,
                 error = 'its worker stopped renewing the lease on its last attempt'
             WHERE state = 'running' AND lease_expires_ms < NOW_MS AND attempts >= max_attempts";
        const REQUEUE: &str = "UPDATE jobs SET state = 'queued', lease_token = NULL,
                 message = 're-queued: its worker stopped renewing the lease'
             WHERE state = 'running' AND lease_expires_ms < NOW_MS";
        let (fail, requeue, ts) = (self.clocked(FAIL), self.clocked(REQUEUE), now());
        let failed = on_pool!(self, p => sqlx::query(fail).bind(&ts).execute(p).await?.rows_affected());
        let requeued = on_pool!(self, p => sqlx::query(requeue).execute(p).await?.rows_affected());
        Ok((requeued, failed))
    }

    /// Progress of the claim `token` (fenced: a stale worker's progress is dropped).
    pub async fn progress(&self, id: &str, token: &str, progress: f64, message: &str) -> Result<(), sqlx::Error> {
        const SQL: &str =
            "UPDATE jobs SET progress = $1, message = $2 WHERE id = $3 AND state = 'running' AND lease_token = $4";
        on_pool!(self, p => sqlx::query(SQL).bind(progress).bind(message).bind(id).bind(token).execute(p).await?.rows_affected());
        Ok(())
    }

    /// Final state of a running job, fenced by its lease token: only the worker holding
    /// the claim `token` may end it (once the job was re-queued or re-claimed, a late
    /// worker's result is dropped). Returns whether the job was this worker's to end.
    pub async fn finish(
        &self,
        id: &str,
        token: &str,
        state: JobState,
        error: Option<&str>,
        result: Option<&serde_json::Value>,
    ) -> Result<bool, sqlx::Error> {
        const SQL: &str = "UPDATE jobs SET state = $1, error = $2, result = $3, finished_at = $4, lease_token = NULL,
                 progress = CASE WHEN $1 = 'succeeded' THEN 1 ELSE progress END
             WHERE id = $5 AND state = 'running' AND lease_token = $6";
        let (result, ts) = (result.map(|r| r.to_string()), now());
        let n = on_pool!(self, p => sqlx::query(SQL)
            .bind(state.as_str())
            .bind(error)
            .bind(&result)
            .bind(&ts)
            .bind(id)
            .bind(token)
            .execute(p)
            .await?
            .rows_affected());
        Ok(n == 1)
    }

    /// A failed attempt, fenced like `finish`: with attempts left the job goes back to the
    /// queue, claimable from `backoff` after now (database clock), keeping the attempt's
    /// `error`; on its last attempt it fails. One statement. Returns the job's state
    /// after it (`queued` or `failed`), or `None` if the attempt was no longer this
    /// worker's.
    pub async fn fail_or_retry(
        &self,
        id: &str,
        token: &str,
        error: &str,
        backoff: Duration,
    ) -> Result<Option<String>, sqlx::Error> {
        const SQL: &str = "UPDATE jobs SET
                 state = CASE WHEN attempts < max_attempts THEN 'queued' ELSE 'failed' END,
                 finished_at = CASE WHEN attempts < max_attempts THEN NULL ELSE $1 END,
                 run_after_ms = CASE WHEN attempts < max_attempts THEN NOW_MS + $2 ELSE NULL END,
                 message = CASE WHEN attempts < max_attempts THEN 'failed; retried after a backoff' ELSE message END,
                 error = $3, lease_token = NULL
             WHERE id = $4 AND state = 'running' AND lease_token = $5
             RETURNING state";
        let sql = self.clocked(SQL);
        let (ts, ms) = (now(), backoff.as_millis() as i64);
        Ok(on_pool!(self, p => sqlx::query_scalar(sql)
            .bind(&ts)
            .bind(ms)
            .bind(error)
            .bind(id)
            .bind(token)
            .fetch_optional(p)
            .await?))
    }

    /// Requests cancellation: a queued job ends at once; a running one at its next check.
    /// Returns the job after the change, or `None` if it does not exist.
    pub async fn cancel(&self, id: &str) -> Result<Option<JobRow>, sqlx::Error> {
        const QUEUED: &str =
            "UPDATE jobs SET state = 'cancelled', finished_at = $1, message = 'cancelled before it started'
             WHERE id = $2 AND state = 'queued'";
        const RUNNING: &str = "UPDATE jobs SET cancel_requested = 1 WHERE id = $1 AND state = 'running'";
        let ts = now();
        on_pool!(self, p => sqlx::query(QUEUED).bind(&ts).bind(id).execute(p).await?.rows_affected());
        on_pool!(self, p => sqlx::query(RUNNING).bind(id).execute(p).await?.rows_affected());
        self.job(id).await
    }

    /// Whether a cancel was asked for job `id` (false if the job is gone or the query fails).
    pub async fn cancel_requested(&self, id: &str) -> bool {
        const SQL: &str = "SELECT cancel_requested FROM jobs WHERE id = $1";
        let v: Option<i64> =
            on_pool!(self, p => sqlx::query_scalar(SQL).bind(id).fetch_optional(p).await.ok().flatten());
        v.is_some_and(|v| v != 0)
    }

    /// After a crash of the only process on an embedded (SQLite) store: jobs left
    /// `running` go back to the queue, or fail after their last attempt, at once rather
    /// than after their lease. Never with a shared database, where other workers' jobs
    /// are `running` too (there `reap_expired` does it). Returns (requeued, failed).
    pub async fn recover(&self) -> Result<(u64, u64), sqlx::Error> {
        const FAIL: &str = "UPDATE jobs SET state = 'failed', finished_at = $1, lease_token = NULL,
                 error = 'interrupted by a restart on its last attempt'
             WHERE state = 'running' AND attempts >= max_attempts";
        const REQUEUE: &str =
            "UPDATE jobs SET state = 'queued', lease_token = NULL, message = 're-queued after a restart'
             WHERE state = 'running'";
        // Chunks the dead process held: free at once (their leases would run out anyway).
        const CHUNKS: &str = "UPDATE job_chunks SET state = 'queued', lease_token = NULL WHERE state = 'running'";
        let ts = now();
        let failed = on_pool!(self, p => sqlx::query(FAIL).bind(&ts).execute(p).await?.rows_affected());
        let requeued = on_pool!(self, p => sqlx::query(REQUEUE).execute(p).await?.rows_affected());
        on_pool!(self, p => sqlx::query(CHUNKS).execute(p).await?.rows_affected());
        Ok((requeued, failed))
    }

    /// Puts a running job back in the queue (graceful shutdown), not counting the attempt;
    /// fenced by the lease token like `finish`.
    pub async fn requeue(&self, id: &str, token: &str) -> Result<bool, sqlx::Error> {
        const SQL: &str = "UPDATE jobs SET state = 'queued', attempts = attempts - 1, lease_token = NULL,
                 message = 're-queued at shutdown'
             WHERE id = $1 AND state = 'running' AND lease_token = $2";
        let n = on_pool!(self, p => sqlx::query(SQL).bind(id).bind(token).execute(p).await?.rows_affected());
        Ok(n == 1)
    }

    /// Jobs per (kind, state), for /metrics: one tenant's, or every tenant's (`None`).
    pub async fn queue_counts(&self, tenant: Option<&str>) -> Result<Vec<QueueCount>, sqlx::Error> {
        const SQL: &str = "SELECT kind, state, COUNT(*) AS n FROM jobs WHERE ($1 IS NULL OR tenant = $1) \
                           GROUP BY kind, state ORDER BY kind, state";
        Ok(on_pool!(self, p => sqlx::query(SQL)
            .bind(tenant)
            .fetch_all(p)
            .await?
            .iter()
            .map(|r| Ok(QueueCount { kind: r.text("kind")?, state: r.text("state")?, count: r.int("n")? }))
            .collect::<Result<_, sqlx::Error>>()?))
    }

    /// The lease expiry of a job in ms on the database clock (tests, operators).
    pub async fn lease_expires_ms(&self, id: &str) -> Result<Option<i64>, sqlx::Error> {
        const SQL: &str = "SELECT lease_expires_ms FROM jobs WHERE id = $1";
        Ok(
            on_pool!(self, p => sqlx::query(SQL).bind(id).fetch_optional(p).await?.map(|r| r.opt_int("lease_expires_ms")).transpose()?.flatten()),
        )
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn timestamps_are_rfc3339() {
        let t = super::now();
        assert_eq!(t.len(), 24, "{t}");
        assert!(t.starts_with("20") && t.ends_with('Z') && &t[10..11] == "T");
    }

    /// A column whose stored type drifted (SQLite keeps whatever it is given) fails the
    /// query with an error naming the column; reading it must not panic the caller.
    #[tokio::test]
    async fn a_drifted_column_is_an_error_not_a_panic() {
        let dir = tempfile::tempdir().unwrap();
        let store = Store::open(&dir.path().join("otofit.db")).await.unwrap();
        assert!(store.insert_job_within("j1", "simulate", &serde_json::json!({"n": 1}), 1, 10).await.unwrap());
        let Pool::Sqlite(pool) = &store.pool else { unreachable!() };
        sqlx::query("UPDATE jobs SET progress = 'half' WHERE id = 'j1'").execute(pool).await.unwrap();
        let e = store.job("j1").await.expect_err("a text progress must not read as a job");
        assert!(e.to_string().contains("progress"), "{e}");
        assert!(store.jobs(None, 10, None).await.is_err());
        sqlx::query("UPDATE jobs SET progress = 0.5, state = 'paused' WHERE id = 'j1'").execute(pool).await.unwrap();
        let e = store.job("j1").await.expect_err("a state no job has must not read as a job");
        assert!(e.to_string().contains("unknown job state 'paused'"), "{e}");
    }

    #[test]
    fn job_states_are_served_by_their_stored_names() {
        for s in JobState::ALL {
            assert_eq!(JobState::parse(s.as_str()), Some(s));
            assert_eq!(serde_json::to_value(s).unwrap(), s.as_str());
        }
        assert_eq!(JobState::parse("Queued"), None);
        assert!(JobState::Running.is_active() && !JobState::Cancelled.is_active());
    }

    #[test]
    fn database_urls_are_parsed_or_refused_naming_the_flag() {
        assert_eq!(Database::parse("sqlite://data/otofit.db").unwrap(), Database::Sqlite("data/otofit.db".into()));
        assert_eq!(Database::parse("sqlite:/tmp/x.db").unwrap(), Database::Sqlite("/tmp/x.db".into()));
        let pg = "postgres://otofit:secret@db:5432/otofit";
        assert_eq!(Database::parse(pg).unwrap(), Database::Postgres(pg.into()));
        assert_eq!(Database::parse(pg).unwrap().redacted(), "postgres://otofit:***@db:5432/otofit");
        for bad in ["mysql://db/x", "data/otofit.db", "sqlite://", "sqlite::memory:"] {
            let e = Database::parse(bad).unwrap_err().to_string();
            assert!(e.starts_with("--database: "), "{bad}: {e}");
        }
    }
}
