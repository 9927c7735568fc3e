//! `otofit serve`: the HTTP service with its job queue.

use crate::http::{self, AppState};
use crate::jobs::{self, Ctx};
use crate::store::{Database, QueueBounds, Store};
use anyhow::{Context, Result, bail};
use clap::Args;
use std::net::SocketAddr;
use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::sync::atomic::Ordering;

/// Arguments of `otofit serve`.
#[derive(Args, Debug)]
pub struct ServeArgs {
    /// Listen address (loopback by default).
    #[arg(long, default_value = "127.0.0.1:8080")]
    pub addr: SocketAddr,
    /// Database, datasets and trained models live here.
    #[arg(long, default_value = "data")]
    pub data_dir: PathBuf,
    /// The job and model tables: `sqlite://PATH` (default: DATA_DIR/otofit.db, embedded,
    /// one process per data directory) or `postgres://USER:PASSWORD@HOST:PORT/DB`, shared
    /// by any number of `serve` and `otofit worker` processes (which then share DATA_DIR
    /// too, e.g. on a network volume).
    #[arg(long, env = "OTOFIT_DATABASE")]
    pub database: Option<String>,
    /// Job dispatchers this process runs (0: HTTP only, jobs run by `otofit worker`s).
    #[arg(long, default_value_t = 1)]
    pub workers: usize,
    /// How this process runs jobs: leases, chunks, retries, the artifact store.
    #[command(flatten)]
    pub jobs: JobFlags,
    /// Checkpoint registered as the default model on first start; the server refuses to
    /// start when it cannot be loaded (`none`: no default model).
    #[arg(long, default_value = "models/default.otofit")]
    pub default_model: PathBuf,
    /// SHA-256 (hex) of an accepted API key; repeat or comma-separate. When set (or when
    /// `otofit keys add` stored a key in the database), every route but /health needs
    /// `Authorization: Bearer <key>`. These keys are admin keys of the tenant `default`
    /// (they see every tenant's work, as every key did before tenants); per-tenant keys
    /// come from `otofit keys add --tenant NAME`.
    #[arg(long = "api-key-hash", env = "OTOFIT_API_KEY_HASHES", value_delimiter = ',')]
    pub api_key_hashes: Vec<String>,
    /// A host name clients address this server by (repeat or comma-separate). Without
    /// API keys the server answers only requests addressed to localhost or an IP address
    /// (a guard against DNS rebinding); name the others here.
    #[arg(long = "allowed-host", value_delimiter = ',')]
    pub allowed_hosts: Vec<String>,
    /// Most queued + running jobs before POST /jobs answers 429.
    #[arg(long, default_value_t = 64)]
    pub max_queue: i64,
    /// Most queued + running jobs of one tenant before its POST /jobs answers 429, so
    /// that one tenant cannot fill the whole queue (default: half of --max-queue).
    #[arg(long)]
    pub max_queue_per_tenant: Option<i64>,
    /// Most inferences running at once (default: 2 × cores).
    #[arg(long)]
    pub infer_concurrency: Option<usize>,
    /// Most inferences waiting for a slot before POST /infer answers 503 + Retry-After
    /// (default: 32 × cores).
    #[arg(long)]
    pub infer_queue: Option<usize>,
    /// Seconds an inference may take, waiting included, before it answers 503.
    #[arg(long, default_value_t = 10.0)]
    pub infer_deadline: f64,
    /// Seconds a connection may stay silent (no byte either way: a half-sent request, an
    /// idle keep-alive) before it is closed; also bounds a request's total time (408).
    #[arg(long, default_value_t = 30.0)]
    pub idle_timeout: f64,
    /// Logs as JSON lines.
    #[arg(long)]
    pub log_json: bool,
}

impl ServeArgs {
    fn infer_limits(&self) -> Result<http::InferLimits> {
        let d = http::InferLimits::default();
        if !(self.infer_deadline > 0.0 && self.infer_deadline < self.idle_timeout) {
            bail!("--infer-deadline must be > 0 and below --idle-timeout ({} s)", self.idle_timeout);
        }
        Ok(http::InferLimits {
            concurrency: self.infer_concurrency.unwrap_or(d.concurrency).max(1),
            queue: self.infer_queue.unwrap_or(d.queue),
            deadline: std::time::Duration::from_secs_f64(self.infer_deadline),
        })
    }
}

/// Takes the data directory for this process: an exclusive lock (flock) on
/// `DATA_DIR/otofit.lock`, which holds the owner's pid. The kernel releases it when the
/// process ends, however it ends, so a crash never leaves a stale lock behind.
pub fn lock_data_dir(data_dir: &Path) -> Result<std::fs::File> {
    use std::io::Write;
    let path = data_dir.join("otofit.lock");
    let mut f = std::fs::OpenOptions::new()
        .create(true)
        .truncate(false)
        .read(true)
        .write(true)
        .open(&path)
        .with_context(|| format!("cannot open {}", path.display()))?;
    match f.try_lock() {
        Ok(()) => {}
        Err(std::fs::TryLockError::WouldBlock) => {
            let pid = std::fs::read_to_string(&path).unwrap_or_default();
            bail!(
                "the data directory {} is in use by another otofit process (pid {}); stop it or use another --data-dir",
                data_dir.display(),
                pid.trim()
            );
        }
        Err(std::fs::TryLockError::Error(e)) => {
            return Err(e).with_context(|| format!("cannot lock {}", path.display()));
        }
    }
    f.set_len(0)?;
    write!(f, "{}", std::process::id())?;
    Ok(f)
}

/// Locks the data directory, opens the store, recovers interrupted jobs and registers the
/// default model; /infer gets the default limits.
/// The first of `given`, then `given` under each of `roots`, that exists (else `given`):
/// a relative default model is found when `serve` starts outside the repository.
fn resolve_in(given: &Path, roots: &[PathBuf]) -> PathBuf {
    if given.exists() || given.is_absolute() {
        return given.to_path_buf();
    }
    roots.iter().map(|r| r.join(given)).find(|p| p.exists()).unwrap_or_else(|| given.to_path_buf())
}

/// `--default-model` as given, else under the binary's prefix (`bin/../share/otofit/`) or
/// in the source tree it was built from (`cargo install --path .` from a clone).
fn resolve_default_model(given: &Path) -> PathBuf {
    let mut roots = Vec::new();
    if let Some(bin) = std::env::current_exe().ok().and_then(|e| e.parent().map(Path::to_path_buf)) {
        roots.push(bin.join("../share/otofit"));
    }
    roots.push(PathBuf::from(env!("CARGO_MANIFEST_DIR")));
    let found = resolve_in(given, &roots);
    if found != given {
        tracing::info!(path = %found.display(), "default model found outside the working directory");
    }
    found
}

/// `--default-model` resolved and loaded once, so that a server never starts with a
/// default it cannot answer with; `none` serves without one (models come from train jobs).
/// The fit check's simulator is built here too (the eardrum's mesh and modes, ~0.1 s from
/// the mode cache), so that the first request does not pay for it.
fn usable_default_model(given: &Path) -> Result<PathBuf> {
    if given == Path::new("none") {
        return Ok(PathBuf::new());
    }
    let path = resolve_default_model(given);
    let npe = crate::npe::Npe::load(&path).with_context(|| {
        format!(
            "--default-model {}: not a usable otofit model (pass --default-model none to serve without one)",
            given.display()
        )
    })?;
    // A model of another simulator is served without a fit check (its answers say so).
    let _ = crate::discrepancy::fitcheck::simulator_for(&npe);
    Ok(path)
}

/// The service context on `data_dir` (SQLite there) with the default /infer limits: the
/// store opened, `default_model` registered, leftovers of killed runs removed.
pub async fn open(data_dir: &Path, default_model: &Path, max_queue: i64) -> Result<Arc<Ctx>> {
    open_with(data_dir, default_model, max_queue, http::InferLimits::default()).await
}

/// `open` with the given /infer limits.
pub async fn open_with(
    data_dir: &Path,
    default_model: &Path,
    max_queue: i64,
    infer: http::InferLimits,
) -> Result<Arc<Ctx>> {
    let db = Database::Sqlite(data_dir.join("otofit.db"));
    let queue = QueueBounds { queue: max_queue, per_tenant: max_queue };
    open_db(&db, data_dir, default_model, queue, infer, jobs::JobSettings::default(), None).await
}

/// Most dispatchers one process runs.
pub const MAX_WORKERS: usize = 64;

/// `--database` as given, else SQLite in the data directory.
pub fn database_arg(url: Option<&str>, data_dir: &Path) -> Result<Database> {
    match url {
        Some(u) => Ok(Database::parse(u)?),
        None => Ok(Database::Sqlite(data_dir.join("otofit.db"))),
    }
}

/// The flags of how a process runs jobs, shared by `serve` and `worker`.
#[derive(Args, Debug, Clone)]
pub struct JobFlags {
    /// Seconds a claimed job's lease lasts; renewed every third of it. A worker that
    /// stops renewing loses the job to another after this long.
    #[arg(long, default_value_t = 30.0)]
    pub lease_seconds: f64,
    /// Most rows per chunk of a simulate job (each chunk is a part file any worker may
    /// run; a killed job resumes from its finished chunks). Smaller jobs get smaller
    /// chunks, at least four when that leaves 1,000 rows each.
    #[arg(long, default_value_t = jobs::CHUNK_ROWS)]
    pub chunk_rows: usize,
    /// Seconds a job waits in the queue after its first failed attempt before it is
    /// tried again (doubling after each further failure; 3 attempts in all).
    #[arg(long, default_value_t = 10.0)]
    pub retry_backoff_seconds: f64,
    /// The longest wait between two attempts of a failing job.
    #[arg(long, default_value_t = 600.0)]
    pub retry_backoff_max_seconds: f64,
    /// Where datasets, models and reports are kept: `s3://BUCKET/PREFIX` for
    /// S3-compatible object storage (credentials, region, endpoint from the AWS_*
    /// variables; AWS_ENDPOINT=http://HOST:PORT with AWS_ALLOW_HTTP=true for a local
    /// server); a worker stores a job's files there when it succeeds and every process
    /// fetches them into its data directory on first use. Default: the data directory
    /// itself (shared by every process, e.g. a shared volume).
    #[arg(long, env = "OTOFIT_ARTIFACTS")]
    pub artifacts: Option<String>,
}

impl JobFlags {
    /// The settings, each flag checked (an error names it).
    pub fn settings(&self) -> Result<jobs::JobSettings> {
        let mut s = job_settings(self.lease_seconds, self.chunk_rows)?;
        let (first, max) = (self.retry_backoff_seconds, self.retry_backoff_max_seconds);
        if !(0.0..=86_400.0).contains(&first) {
            bail!("--retry-backoff-seconds must be 0..=86400, got {first}");
        }
        if !(first..=86_400.0).contains(&max) {
            bail!("--retry-backoff-max-seconds must be --retry-backoff-seconds ({first})..=86400, got {max}");
        }
        let secs = std::time::Duration::from_secs_f64;
        s.retry = jobs::Backoff { first: secs(first), max: secs(max) };
        Ok(s)
    }
}

/// `--lease-seconds` (1 s ..= 1 h; a renewal every third of it) and `--chunk-rows`
/// (100 ..= 100,000), with the default retry backoff.
pub fn job_settings(lease_seconds: f64, chunk_rows: usize) -> Result<jobs::JobSettings> {
    if !(1.0..=3600.0).contains(&lease_seconds) {
        bail!("--lease-seconds must be 1..=3600, got {lease_seconds}");
    }
    // At least 100: a job's worker looks at every part between its chunks.
    if !(100..=jobs::MAX_ROWS).contains(&chunk_rows) {
        bail!("--chunk-rows must be 100..={}, got {chunk_rows}", jobs::MAX_ROWS);
    }
    let lease = std::time::Duration::from_secs_f64(lease_seconds);
    Ok(jobs::JobSettings { lease, chunk_rows, ..Default::default() })
}

/// `--max-queue` (≥ 1) and `--max-queue-per-tenant` (1 ..= --max-queue; default half).
pub fn queue_bounds(max_queue: i64, per_tenant: Option<i64>) -> Result<QueueBounds> {
    if max_queue < 1 {
        bail!("--max-queue must be at least 1, got {max_queue}");
    }
    let per_tenant = per_tenant.unwrap_or((max_queue / 2).max(1));
    if !(1..=max_queue).contains(&per_tenant) {
        bail!("--max-queue-per-tenant must be 1..={max_queue} (--max-queue), got {per_tenant}");
    }
    Ok(QueueBounds { queue: max_queue, per_tenant })
}

/// Opens the state of a `serve` or `worker` process. With SQLite the process takes the
/// data directory for itself (its lock), puts jobs left running by a crash straight back
/// in the queue and removes their temporary files. With PostgreSQL the data directory is
/// shared with other processes: no lock, and jobs of workers that died come back when
/// their lease expires (`Store::reap_expired`).
pub async fn open_state(
    db: &Database,
    data_dir: &Path,
    settings: jobs::JobSettings,
    artifacts: Option<&str>,
) -> Result<Ctx> {
    std::fs::create_dir_all(data_dir).with_context(|| format!("cannot create {}", data_dir.display()))?;
    let artifacts = crate::artifacts::Artifacts::open(artifacts, data_dir)?;
    let lock = match db {
        Database::Sqlite(_) => Some(lock_data_dir(data_dir)?),
        Database::Postgres(_) => None,
    };
    let store = Store::connect(db).await.with_context(|| format!("opening the database {}", db.redacted()))?;
    if lock.is_some() {
        let (requeued, failed) = store.recover().await?;
        if requeued + failed > 0 {
            tracing::warn!(requeued, failed, "recovered jobs left running by a previous process");
        }
        // No job runs yet (the lock is ours): temporary files are leftovers of runs that
        // failed or were killed. Finished parts stay for the jobs that will run again
        // (they resume from them); those of jobs that ended go.
        let mut stale = 0;
        for d in std::fs::read_dir(data_dir.join("datasets")).into_iter().flatten().flatten() {
            let id = d.file_name().to_string_lossy().into_owned();
            let active = store.job(&id).await?.is_some_and(|j| j.state == "queued" || j.state == "running");
            stale += jobs::remove_temporary_files(&d.path(), !active);
        }
        if stale > 0 {
            tracing::info!(files = stale, "removed temporary files of interrupted simulate jobs");
        }
    }
    let ctx = Ctx::new(store, data_dir.to_path_buf(), 0).with_settings(settings).with_artifacts(artifacts);
    Ok(match lock {
        Some(l) => ctx.with_lock(l),
        None => ctx,
    })
}

/// `open_state` for `serve`: registers the default model; /infer gets `infer`.
pub async fn open_db(
    db: &Database,
    data_dir: &Path,
    default_model: &Path,
    queue: QueueBounds,
    infer: http::InferLimits,
    settings: jobs::JobSettings,
    artifacts: Option<&str>,
) -> Result<Arc<Ctx>> {
    let mut ctx = open_state(db, data_dir, settings, artifacts).await?;
    (ctx.max_queue, ctx.max_queue_per_tenant) = (queue.queue, queue.per_tenant);
    let store = &ctx.store;
    if default_model.exists() {
        let path = std::fs::canonicalize(default_model)?;
        store.add_model("default", &path.display().to_string(), true, None).await?;
    } else {
        tracing::warn!(path = %default_model.display(), "default model not found; /infer answers 503 until one is registered");
    }
    Ok(Arc::new(ctx.with_infer_limits(infer)))
}

/// Stops `dispatchers`: no new claims; running jobs are interrupted at their next check
/// and go back to the queue. Whether they all ended within the 60 s grace.
pub async fn stop_dispatchers(ctx: &Ctx, dispatchers: Vec<tokio::task::JoinHandle<()>>) -> bool {
    ctx.shutdown.store(true, Ordering::Relaxed);
    ctx.notify.notify_waiters();
    let all = async {
        for d in dispatchers {
            let _ = d.await;
        }
    };
    tokio::time::timeout(std::time::Duration::from_secs(60), all).await.is_ok()
}

/// The `--api-key-hash` values as SHA-256 digests (empty ones skipped); an error names a bad one.
pub fn parse_key_hashes(hex_hashes: &[String]) -> Result<Vec<[u8; 32]>> {
    hex_hashes
        .iter()
        .filter(|h| !h.is_empty())
        .map(|h| {
            let b = hex::decode(h.trim()).ok().filter(|b| b.len() == 32);
            b.map(|b| b.try_into().expect("32 bytes"))
                .with_context(|| format!("--api-key-hash: '{h}' is not a SHA-256 hex digest"))
        })
        .collect()
}

/// Logs to stdout (`RUST_LOG` filters; JSON lines with `json`).
pub fn init_logs(json: bool) {
    let filter = tracing_subscriber::EnvFilter::try_from_default_env()
        .unwrap_or_else(|_| "info,tower_http=info,sqlx=warn".into());
    // Colour codes only for a terminal: redirected to a file or a collector, plain text.
    let ansi = std::io::IsTerminal::is_terminal(&std::io::stdout());
    let sub = tracing_subscriber::fmt().with_env_filter(filter).with_ansi(ansi);
    if json { sub.json().init() } else { sub.init() }
}

/// Runs `otofit serve` until SIGTERM or Ctrl-C.
pub fn run(args: ServeArgs) -> Result<()> {
    init_logs(args.log_json);
    let keys = parse_key_hashes(&args.api_key_hashes)?;
    let mut allowed_hosts = Vec::new();
    for h in args.allowed_hosts.iter().map(|h| h.trim()).filter(|h| !h.is_empty()) {
        let valid = h.chars().all(|c| c.is_ascii_alphanumeric() || c == '-' || c == '.') && h.len() <= 253;
        if !valid {
            bail!("--allowed-host: '{h}' is not a host name (letters, digits, '-' and '.'; no port or scheme)");
        }
        allowed_hosts.push(h.to_string());
    }
    let limits = args.infer_limits()?;
    let database = database_arg(args.database.as_deref(), &args.data_dir)?;
    let settings = args.jobs.settings()?;
    let queue = queue_bounds(args.max_queue, args.max_queue_per_tenant)?;
    if args.workers > MAX_WORKERS {
        bail!("--workers must be 0..={MAX_WORKERS}, got {}", args.workers);
    }
    let idle = std::time::Duration::from_secs_f64(args.idle_timeout);
    let default_model = usable_default_model(&args.default_model)?;
    let rt = tokio::runtime::Builder::new_multi_thread().enable_all().build()?;
    let res = rt.block_on(async move {
        let artifacts = args.jobs.artifacts.as_deref();
        let ctx = open_db(&database, &args.data_dir, &default_model, queue, limits, settings, artifacts).await?;
        if !args.addr.ip().is_loopback() && keys.is_empty() && !ctx.store.has_keys().await? {
            tracing::warn!(addr = %args.addr, "listening beyond loopback without API keys");
        }
        let dispatchers: Vec<_> = (0..args.workers).map(|_| tokio::spawn(jobs::dispatcher(ctx.clone()))).collect();
        if args.workers > 0 {
            tokio::spawn(jobs::wake_on_announced_work(ctx.clone()));
        }
        let app = http::router(AppState::new(ctx.clone(), keys).with_allowed_hosts(allowed_hosts));
        let inner = tokio::net::TcpListener::bind(args.addr)
            .await
            .with_context(|| format!("cannot listen on {}", args.addr))?;
        let listener = http::conn::IdleTimeoutListener { inner, idle };
        tracing::info!(addr = %args.addr, data_dir = %args.data_dir.display(), database = %database.redacted(), artifacts = %ctx.artifacts.describe(), workers = args.workers, ?limits, "otofit serving");
        let c2 = ctx.clone();
        let stopping = Arc::new(tokio::sync::Notify::new());
        let s2 = stopping.clone();
        // The peer address reaches the handlers: the inference gate bounds bodies per address.
        let app = http::with_request_timeout(app, idle).into_make_service_with_connect_info::<http::conn::ClientAddr>();
        let server = axum::serve(listener, app).with_graceful_shutdown(async move {
            shutdown_signal().await;
            tracing::info!("shutting down: no new jobs; the running one stops at its next check");
            c2.shutdown.store(true, Ordering::Relaxed);
            c2.notify.notify_one();
            s2.notify_one();
        });
        // Open connections get one idle period to finish after the signal, no more.
        tokio::select! {
            r = server => r?,
            _ = async { stopping.notified().await; tokio::time::sleep(idle).await } => {
                tracing::warn!("connections still open {} s after the signal: closing them", idle.as_secs_f64());
            }
        }
        if !stop_dispatchers(&ctx, dispatchers).await {
            bail!("the running job did not stop within 60 s; it will be re-queued at the next start");
        }
        Ok(())
    });
    // Dropping a runtime waits for its blocking tasks; a job that ignored the stop must not
    // keep the process (and its writes) alive after the grace period.
    rt.shutdown_timeout(std::time::Duration::from_secs(1));
    res
}

/// Resolves at the first SIGTERM or Ctrl-C.
pub async fn shutdown_signal() {
    let ctrl_c = async {
        let _ = tokio::signal::ctrl_c().await;
    };
    #[cfg(unix)]
    let term = async {
        if let Ok(mut s) = tokio::signal::unix::signal(tokio::signal::unix::SignalKind::terminate()) {
            s.recv().await;
        }
    };
    #[cfg(not(unix))]
    let term = std::future::pending::<()>();
    tokio::select! { _ = ctrl_c => {}, _ = term => {} }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_relative_default_model_is_found_under_the_install_roots() {
        let root = std::env::temp_dir().join(format!("otofit-resolve-{}", std::process::id()));
        std::fs::create_dir_all(root.join("share/models")).unwrap();
        std::fs::write(root.join("share/models/m.otofit"), b"x").unwrap();
        let given = Path::new("models/m.otofit");
        let roots = [root.join("nowhere"), root.join("share")];
        assert_eq!(resolve_in(given, &roots), root.join("share/models/m.otofit"));
        // Not found anywhere: the path as given (the server then warns and answers 503).
        assert_eq!(resolve_in(Path::new("models/none.otofit"), &roots), Path::new("models/none.otofit"));
        std::fs::remove_dir_all(&root).unwrap();
    }
}
