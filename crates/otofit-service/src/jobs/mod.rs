//! The job queue: a tokio dispatcher claims queued jobs from the store (SQLite or
//! PostgreSQL) one at a time and runs the CPU work on the blocking pool (simulations fan
//! out on rayon inside it), so the async runtime never blocks. Progress goes to the
//! database as the work goes; cancellation and shutdown are checked between chunks.
//!
//! Every claim is a lease (see `store`): the dispatcher renews it every third of its
//! length while the job runs, and a job whose lease is lost (this worker stalled or was
//! cut off, and another took the job back) is stopped and writes nothing: results are
//! fenced by the lease token in the database, and files are written into an attempt's own
//! staging place and moved into place only after a fresh renewal.
//!
//! A job is a [`JobSpec`] (`spec`): parsed and validated once when it is posted, stored
//! as JSON, executed from the typed value. One file per kind holds its params, their
//! checks and its execution (`simulate`, `train`, `resimulate`, `diagnose`); `limits`
//! holds the bounds the CLI shares.

mod diagnose;
mod error;
mod exact;
pub mod limits;
mod resimulate;
mod simulate;
mod spec;
mod train;

pub use diagnose::DiagnoseParams;
pub use error::{JobContext, JobError};
pub use exact::ExactParams;
pub use limits::MAX_ROWS;
pub use resimulate::ResimulateParams;
pub use simulate::{CHUNK_ROWS, SimulateParams, chunk_plan, progress_from_chunks, remove_temporary_files};
pub use spec::{FieldError, JobSpec, KINDS, MAX_ID, effect_names, field_error, is_plain_id, theta_box};
pub use train::TrainParams;

use crate::npe::Npe;
use crate::store::{JobRow, JobState, Store};
use anyhow::{Result, anyhow};
use std::collections::HashMap;
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, RwLock};
use std::time::Duration;
use tokio::sync::Notify;

/// Shared service state.
pub struct Ctx {
    /// The job queue and model registry.
    pub store: Store,
    /// Where datasets, reports, checkpoints and models are written.
    pub data_dir: PathBuf,
    /// Wakes the dispatcher when a job is queued.
    pub notify: Notify,
    /// Set when the process is shutting down: dispatchers stop claiming, running jobs stop.
    pub shutdown: AtomicBool,
    models: RwLock<HashMap<String, Arc<Npe>>>,
    /// Most active (queued + running) jobs in all (`--max-queue`).
    pub max_queue: i64,
    /// Most active jobs of one tenant (`--max-queue-per-tenant`; default half the queue).
    pub max_queue_per_tenant: i64,
    /// The data directory's lock, held as long as this context lives (see `with_lock`).
    data_lock: Option<std::fs::File>,
    /// Slots and deadline of POST /infer.
    pub infer_gate: crate::gate::InferGate,
    /// This process as a worker (`host:pid`), written into the jobs it claims.
    pub worker: String,
    /// Length of a claim's lease; renewed every third of it.
    pub lease: Duration,
    /// Counters and histograms of this process, for GET /metrics.
    pub metrics: crate::metrics::Metrics,
    /// Most rows per chunk of the simulate jobs this process plans (`simulate::chunk_plan`).
    pub chunk_rows: usize,
    /// Backoff of a failed attempt's retry.
    pub retry: Backoff,
    /// Where datasets, models and reports are kept: the data directory (default) or an
    /// object store (`--artifacts`), to which a job's files go when it succeeds.
    pub artifacts: crate::artifacts::Artifacts,
}

/// How a `serve` or `worker` process runs jobs (its flags).
#[derive(Clone, Copy, Debug)]
pub struct JobSettings {
    /// Length of a claim's lease (`--lease-seconds`).
    pub lease: Duration,
    /// Most rows per chunk of the simulate jobs this process plans (`--chunk-rows`).
    pub chunk_rows: usize,
    /// How long a failed attempt's job waits before it is claimed again.
    pub retry: Backoff,
}

impl Default for JobSettings {
    fn default() -> Self {
        JobSettings { lease: DEFAULT_LEASE, chunk_rows: CHUNK_ROWS, retry: Backoff::default() }
    }
}

/// Exponential backoff of retries: after failed attempt k (1, 2, …) a job waits
/// `first × 2^(k−1)`, at most `max` (`--retry-backoff-seconds`, `--retry-backoff-max-seconds`).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Backoff {
    /// The wait after the first failed attempt.
    pub first: Duration,
    /// The longest wait.
    pub max: Duration,
}

impl Default for Backoff {
    /// 10 s, 20 s, 40 s, … at most 10 minutes.
    fn default() -> Self {
        Backoff { first: Duration::from_secs(10), max: Duration::from_secs(600) }
    }
}

impl Backoff {
    /// The wait after failed attempt `attempt` (1-based).
    pub fn after(&self, attempt: i64) -> Duration {
        let doublings = attempt.clamp(1, 64) as u32 - 1;
        self.first.checked_mul(1u32.checked_shl(doublings).unwrap_or(u32::MAX)).unwrap_or(self.max).min(self.max)
    }
}

/// Default lease of a claimed job: a worker that stops renewing it for this long loses
/// the job to another.
pub const DEFAULT_LEASE: Duration = Duration::from_secs(30);

impl Ctx {
    /// The context of a service on `store` writing under `data_dir`, with default limits and lease.
    pub fn new(store: Store, data_dir: PathBuf, max_queue: i64) -> Ctx {
        Ctx {
            store,
            artifacts: crate::artifacts::Artifacts::local(&data_dir),
            data_dir,
            notify: Notify::new(),
            shutdown: AtomicBool::new(false),
            models: RwLock::new(HashMap::new()),
            max_queue,
            max_queue_per_tenant: max_queue,
            data_lock: None,
            infer_gate: crate::gate::InferGate::new(crate::gate::InferLimits::default()),
            worker: crate::store::worker_name(),
            lease: DEFAULT_LEASE,
            metrics: Default::default(),
            chunk_rows: CHUNK_ROWS,
            retry: Backoff::default(),
        }
    }

    /// Plans simulate jobs in chunks of at most `rows` rows instead of 10,000.
    pub fn with_chunk_rows(mut self, rows: usize) -> Ctx {
        self.chunk_rows = rows.max(1);
        self
    }

    /// Runs jobs with `s` (lease, chunks, retries).
    pub fn with_settings(mut self, s: JobSettings) -> Ctx {
        self.retry = s.retry;
        self.with_lease(s.lease).with_chunk_rows(s.chunk_rows)
    }

    /// The lease of a chunk claim: the job's lease, at most [`CHUNK_LEASE`]. A chunk is
    /// renewed every third of it, so a killed worker's chunk is free again within
    /// seconds, not after the job's 30 s lease.
    pub fn chunk_lease(&self) -> Duration {
        self.lease.min(CHUNK_LEASE)
    }

    /// Claims jobs with leases of `lease` (renewed every third of it) instead of 30 s.
    pub fn with_lease(mut self, lease: Duration) -> Ctx {
        self.lease = lease;
        self
    }

    /// Bounds POST /infer by `limits` instead of the defaults.
    pub fn with_infer_limits(mut self, limits: crate::gate::InferLimits) -> Ctx {
        self.infer_gate = crate::gate::InferGate::new(limits);
        self
    }

    /// Keeps artifacts in `artifacts` instead of the data directory alone.
    pub fn with_artifacts(mut self, artifacts: crate::artifacts::Artifacts) -> Ctx {
        self.artifacts = artifacts;
        self
    }

    /// Keeps `lock` (the data directory's lock file, locked) for the life of the context.
    pub fn with_lock(mut self, lock: std::fs::File) -> Ctx {
        self.data_lock = Some(lock);
        self
    }

    /// A registered model, loaded once and shared. `path` is its row's: a file, or a URL
    /// in the artifact store, fetched into the data directory on first use.
    pub fn loaded(&self, id: &str, path: &Path) -> Result<Arc<Npe>> {
        if let Some(m) = self.models.read().map_err(|_| anyhow!("model cache poisoned"))?.get(id) {
            return Ok(m.clone());
        }
        let file = self.artifacts.model_file(&path.to_string_lossy())?;
        let m = Arc::new(Npe::load(&file)?);
        self.models.write().map_err(|_| anyhow!("model cache poisoned"))?.insert(id.to_string(), m.clone());
        Ok(m)
    }

    /// The folder of dataset `id` under the data dir.
    pub fn dataset_dir(&self, id: &str) -> PathBuf {
        self.data_dir.join("datasets").join(id)
    }
}

/// Reports progress and tells the worker whether to stop.
pub struct Reporter {
    tx: tokio::sync::mpsc::UnboundedSender<(f64, String)>,
    /// Raised when the job must stop: cancel, shutdown, its lease lost.
    cancel: Arc<AtomicBool>,
    /// The claim: (job id, lease token), for the renewal before results are written.
    claim: (String, String),
}

impl Reporter {
    fn report(&self, progress: f64, message: String) -> bool {
        let _ = self.tx.send((progress, message));
        !self.cancel.load(Ordering::Relaxed)
    }

    /// Renews the lease (blocking; called from the job's thread) right before results are
    /// written: `Err(LeaseLost)` if the job is no longer this worker's, so nothing is
    /// written. After a renewal no other worker can claim the job for a whole lease.
    fn still_ours(&self, ctx: &Ctx) -> Result<(), JobError> {
        let (id, token) = (&self.claim.0, &self.claim.1);
        let renewed = tokio::runtime::Handle::current().block_on(ctx.store.heartbeat(id, token, ctx.lease));
        match renewed {
            Ok(true) => Ok(()),
            Ok(false) => {
                self.cancel.store(true, Ordering::Relaxed);
                Err(LeaseLost.into())
            }
            Err(e) => Err(JobError::internal("the job's lease could not be renewed before writing its results", e)),
        }
    }
}

#[derive(Debug, thiserror::Error)]
#[error("stopped on request")]
struct Stopped;

/// The job's lease was lost: another worker may hold it now.
#[derive(Debug, thiserror::Error)]
#[error("the job's lease was lost; this worker's results are dropped")]
pub struct LeaseLost;

impl JobSpec {
    /// Runs the job `id`'s CPU work (on a blocking thread). Returns its result document.
    fn execute(&self, ctx: &Ctx, id: &str, r: &Reporter) -> Result<serde_json::Value, JobError> {
        match self {
            JobSpec::Simulate(p) => simulate::execute(ctx, id, p, r),
            JobSpec::Train(p) => train::execute(ctx, id, p, r),
            JobSpec::Resimulate(p) => resimulate::execute(ctx, id, p, r),
            JobSpec::Diagnose(p) => diagnose::execute(ctx, id, p, r),
            JobSpec::Exact(p) => exact::execute(ctx, p, r),
        }
    }
}

/// A model by its id, looked up in the store (never a path built from the id). Errors
/// name the id; why a registered model cannot be loaded (its file) is the cause.
pub fn registered_model(ctx: &Ctx, id: &str) -> Result<Arc<Npe>, JobError> {
    let unknown = || JobError::client(format!("model '{id}' is not registered"));
    if !is_plain_id(id) {
        return Err(unknown());
    }
    let rt = tokio::runtime::Handle::current();
    let row = rt.block_on(ctx.store.model(id))?.ok_or_else(unknown)?;
    ctx.loaded(&row.id, Path::new(&row.path))
        .internal(format!("model '{id}' cannot be loaded (the server log says why)"))
}

/// Longest lease of a chunk claim (see [`Ctx::chunk_lease`]).
pub const CHUNK_LEASE: Duration = Duration::from_secs(6);

/// How long an idle dispatcher waits before looking for work again when nothing in this
/// process told it of new work (a job posted to another process, a chunk freed by a
/// dead worker): short, so that a second worker joins a job within a fraction of a
/// second. Each look is a few indexed queries.
const IDLE_POLL: Duration = Duration::from_millis(250);

/// Wakes this process' idle dispatchers whenever another process announces work
/// (PostgreSQL; a no-op with SQLite, whose dispatchers all share `ctx.notify`). Spawn it
/// once per process beside the dispatchers; it runs until the process ends.
pub async fn wake_on_announced_work(ctx: Arc<Ctx>) {
    ctx.store.listen_for_work(|| ctx.notify.notify_waiters()).await
}

/// The dispatcher: takes back jobs whose lease expired, claims and runs jobs until
/// shutdown; with no job queued it helps with a chunk of a running simulate job (any
/// worker's). Any number of dispatchers, in any number of processes, may share a store.
pub async fn dispatcher(ctx: Arc<Ctx>) {
    loop {
        if ctx.shutdown.load(Ordering::Relaxed) {
            break;
        }
        match ctx.store.reap_expired().await {
            Ok((0, 0)) => {}
            Ok((requeued, failed)) => {
                ctx.metrics.reaped(requeued + failed);
                tracing::warn!(requeued, failed, "took back jobs whose lease expired")
            }
            Err(e) => tracing::error!(error = %e, "reaping expired leases failed"),
        }
        match ctx.store.claim(&ctx.worker, ctx.lease).await {
            Ok(Some(job)) => {
                ctx.metrics.claimed();
                run(ctx.clone(), job).await
            }
            // Chunks of other workers' jobs only where part files are shared: with an
            // object store, workers need not share a data directory (parts are local).
            Ok(None) if ctx.artifacts.is_remote() => {
                tokio::select! {
                    _ = ctx.notify.notified() => {}
                    _ = tokio::time::sleep(IDLE_POLL) => {}
                }
            }
            Ok(None) => match ctx.store.claim_chunk(None, &ctx.worker, ctx.chunk_lease()).await {
                Ok(Some(chunk)) => simulate::help(ctx.clone(), chunk).await,
                Ok(None) => {
                    tokio::select! {
                        _ = ctx.notify.notified() => {}
                        _ = tokio::time::sleep(IDLE_POLL) => {}
                    }
                }
                Err(e) => {
                    tracing::error!(error = %e, "claiming a chunk failed");
                    tokio::time::sleep(Duration::from_secs(1)).await;
                }
            },
            Err(e) => {
                tracing::error!(error = %e, "claiming a job failed");
                tokio::time::sleep(Duration::from_secs(1)).await;
            }
        }
    }
}

async fn run(ctx: Arc<Ctx>, job: JobRow) {
    let t0 = std::time::Instant::now();
    let token = job.lease_token.clone().unwrap_or_default();
    tracing::info!(job = %job.id, kind = %job.kind, attempt = job.attempts, worker = %ctx.worker, "job started");
    let cancel = Arc::new(AtomicBool::new(false));
    let (tx, rx) = tokio::sync::mpsc::unbounded_channel();
    let reporter = Reporter { tx, cancel: cancel.clone(), claim: (job.id.clone(), token.clone()) };
    let spec = JobSpec::of(&job);
    // What the job leaves behind: a dataset folder (simulate), a model (train, diagnose).
    let leaves = Leaves {
        dataset: matches!(spec, Ok(JobSpec::Simulate(_))),
        model: matches!(spec, Ok(JobSpec::Train(_) | JobSpec::Diagnose(_))),
    };
    let handle = start(ctx.clone(), job.id.clone(), spec, reporter);
    let mut renew = tokio::time::interval(ctx.lease / 3);
    renew.reset();
    let (result, lost) = supervise(&ctx, &job, &token, &cancel, rx, handle, &mut renew).await;
    let stop =
        Stop { lost, cancelled: cancel.load(Ordering::Relaxed), shutting_down: ctx.shutdown.load(Ordering::Relaxed) };
    let (label, outcome) = settle(&ctx, &job, &token, result, stop, leaves, &mut renew).await;
    let label = match outcome {
        Ok(true) => label,
        Ok(false) => "lease_lost",
        Err(_) => "not_saved",
    };
    ctx.metrics.job_ended(&job.kind, label, t0.elapsed().as_secs_f64());
    let owned = match outcome {
        Ok(owned) => owned,
        Err(e) => {
            tracing::error!(job = %job.id, error = %e, "job state not saved");
            false
        }
    };
    clean_up(&ctx, &job, &token, label, owned, leaves).await;
    tracing::info!(job = %job.id, seconds = t0.elapsed().as_secs_f64(), "job ended");
}

/// What a job of some kind leaves behind.
#[derive(Clone, Copy)]
struct Leaves {
    dataset: bool,
    model: bool,
}

/// Why a job's run ended early, if it did.
#[derive(Clone, Copy)]
struct Stop {
    lost: bool,
    cancelled: bool,
    shutting_down: bool,
}

/// The job's work on a blocking thread: its spec read, a train job's dataset fetched from
/// the object store when another worker made it, then executed.
fn start(
    ctx: Arc<Ctx>,
    id: String,
    spec: Result<JobSpec, serde_json::Error>,
    reporter: Reporter,
) -> tokio::task::JoinHandle<Result<serde_json::Value, JobError>> {
    tokio::task::spawn_blocking(move || {
        // serde's message names the params' fields and their place in the JSON.
        let spec = spec.map_err(|e| JobError::client(format!("the job's stored params do not read: {e}")))?;
        if let JobSpec::Train(p) = &spec
            && ctx.artifacts.is_remote()
        {
            for f in crate::dataset::FILES {
                ctx.artifacts
                    .fetch_blocking(&crate::artifacts::dataset_key(&p.dataset, f))
                    .internal(format!("dataset '{}' could not be fetched from the artifact store", p.dataset))?;
            }
        }
        spec.execute(&ctx, &id, &reporter)
    })
}

/// Waits for the job's work while saving its progress, raising `cancel` on a cancel
/// request or shutdown, and renewing its lease; returns the work's result and whether the
/// lease was lost.
async fn supervise(
    ctx: &Ctx,
    job: &JobRow,
    token: &str,
    cancel: &AtomicBool,
    mut rx: tokio::sync::mpsc::UnboundedReceiver<(f64, String)>,
    mut handle: tokio::task::JoinHandle<Result<serde_json::Value, JobError>>,
    renew: &mut tokio::time::Interval,
) -> (Result<Result<serde_json::Value, JobError>, tokio::task::JoinError>, bool) {
    // Intervals, not sleeps inside select!: progress messages must not starve the checks.
    let mut check = tokio::time::interval(Duration::from_millis(300));
    let mut lost = false;
    let result = loop {
        tokio::select! {
            Some((p, m)) = rx.recv() => {
                if let Err(e) = ctx.store.progress(&job.id, token, p, &m).await {
                    tracing::warn!(job = %job.id, error = %e, "progress not saved");
                }
            }
            _ = check.tick() => {
                if ctx.shutdown.load(Ordering::Relaxed) || ctx.store.cancel_requested(&job.id).await {
                    cancel.store(true, Ordering::Relaxed);
                }
            }
            _ = renew.tick() => match ctx.store.heartbeat(&job.id, token, ctx.lease).await {
                Ok(true) => {}
                Ok(false) => {
                    ctx.metrics.lease_lost();
                    tracing::warn!(job = %job.id, "lease lost: stopping the job; its results will be dropped");
                    lost = true;
                    cancel.store(true, Ordering::Relaxed);
                }
                // A database hiccup: the lease still has two thirds to run; retried next tick.
                Err(e) => tracing::warn!(job = %job.id, error = %e, "lease not renewed"),
            },
            res = &mut handle => break res,
        }
    };
    (result, lost)
}

/// Records how the job ended (every end fenced by this worker's lease token, see
/// `Store::finish`): (label, Ok(whether the job was still this worker's)).
async fn settle(
    ctx: &Ctx,
    job: &JobRow,
    token: &str,
    result: Result<Result<serde_json::Value, JobError>, tokio::task::JoinError>,
    stop: Stop,
    leaves: Leaves,
    renew: &mut tokio::time::Interval,
) -> (&'static str, Result<bool, sqlx::Error>) {
    let store = &ctx.store;
    let id = job.id.as_str();
    // A failed attempt with attempts left goes back to the queue after a backoff. The job's
    // row keeps the public message; the cause goes to the log.
    let backoff = ctx.retry.after(job.attempts);
    let fail = |e: JobError| async move {
        e.log(id);
        match store.fail_or_retry(id, token, e.public(), backoff).await {
            Ok(Some(state)) if state == "queued" => {
                tracing::warn!(job = %id, attempt = job.attempts, retry_in_s = backoff.as_secs_f64(), "job failed; retried after a backoff");
                ("retried", Ok(true))
            }
            Ok(Some(_)) => ("failed", Ok(true)),
            Ok(None) => ("failed", Ok(false)),
            Err(e) => ("failed", Err(e)),
        }
    };
    match result {
        _ if stop.lost => ("lease_lost", Ok(false)),
        Ok(Err(e)) if e.is::<LeaseLost>() => ("lease_lost", Ok(false)),
        Err(e) => fail(JobError::internal("the job's worker panicked", e)).await,
        // Interrupted by shutdown: back to the queue, the attempt not counted.
        Ok(_) if stop.cancelled && stop.shutting_down => ("requeued", store.requeue(id, token).await),
        // A cancelled training still returns its best weights: a result, kept, under the
        // state the user asked for. Its files go to the object store (if one is
        // configured) before the job shows as ended.
        Ok(Ok(doc)) => match put_outputs(ctx, id, token, renew).await {
            Ok(()) => {
                // The model is registered before the job shows as ended: a client that
                // sees the job end must find its model (`clean_up` registering it again
                // is a no-op).
                if leaves.model {
                    register_model(ctx, id).await;
                }
                let state = if stop.cancelled { JobState::Cancelled } else { JobState::Succeeded };
                (state.as_str(), store.finish(id, token, state, None, Some(&doc)).await)
            }
            Err(e) if e.is::<LeaseLost>() => ("lease_lost", Ok(false)),
            Err(e) => fail(e).await,
        },
        Ok(Err(e)) if stop.cancelled || e.is::<Stopped>() => {
            if leaves.dataset {
                simulate::clear_cancelled(ctx, id, token).await;
            }
            ("cancelled", store.finish(id, token, JobState::Cancelled, None, None).await)
        }
        Ok(Err(e)) => fail(e).await,
    }
}

/// After the job's end is recorded: this attempt's staging folder goes; if the job was
/// still this worker's, a simulate job's leftovers go and a succeeded model is registered.
async fn clean_up(ctx: &Ctx, job: &JobRow, token: &str, label: &str, owned: bool, leaves: Leaves) {
    if leaves.dataset {
        // This attempt's staging folder: moved into place on success, else left over.
        let staging = simulate::staging_dir(&ctx.dataset_dir(&job.id), token);
        if staging.exists() {
            let _ = std::fs::remove_dir_all(&staging);
        }
    }
    if !owned {
        // Another worker holds the job now: its files and its model are its own.
        tracing::warn!(job = %job.id, attempt = job.attempts, "the job is no longer this worker's; its outcome is dropped");
        return;
    }
    if leaves.dataset {
        // Ended: its parts and the leftovers of earlier attempts are garbage now. Re-queued
        // (shutdown, a retry): the finished parts stay, the next attempt resumes from them.
        remove_temporary_files(&ctx.dataset_dir(&job.id), !matches!(label, "requeued" | "retried"));
    }
    if leaves.model
        && let Ok(Some(j)) = ctx.store.job(&job.id).await
        && matches!(j.state, JobState::Succeeded | JobState::Cancelled)
    {
        register_model(ctx, &job.id).await;
    }
}

/// Registers the model job `id` wrote, if it wrote one: by an absolute path (every
/// process sharing the data directory, mounted at the same path, loads the model there
/// whatever its working directory) or by its URL in the object store (every process
/// fetches it from there).
async fn register_model(ctx: &Ctx, id: &str) {
    let file = ctx.artifacts.local_path(&crate::artifacts::model_key(id));
    if file.exists()
        && let Ok(path) = ctx.artifacts.model_ref(id)
    {
        let _ = ctx.store.add_model(id, &path, false, Some(id)).await;
    }
}

/// Stores a succeeded job's files in the object store (nothing to do for local
/// artifacts), renewing the job's lease meanwhile: `Err(LeaseLost)` if it is lost.
async fn put_outputs(ctx: &Ctx, id: &str, token: &str, renew: &mut tokio::time::Interval) -> Result<(), JobError> {
    if !ctx.artifacts.is_remote() {
        return Ok(());
    }
    let up = ctx.artifacts.put_job(id);
    tokio::pin!(up);
    loop {
        tokio::select! {
            res = &mut up => {
                let keys = res.internal("the job's files could not be stored in the artifact store")?;
                tracing::info!(job = %id, files = keys.len(), store = %ctx.artifacts.describe(), "job's files stored");
                return Ok(());
            }
            _ = renew.tick() => if let Ok(false) = ctx.store.heartbeat(id, token, ctx.lease).await {
                ctx.metrics.lease_lost();
                return Err(LeaseLost.into());
            },
        }
    }
}

/// A new job id: time-ordered, unguessable enough for a local service.
pub fn new_id() -> String {
    use rand::Rng;
    let ms = std::time::SystemTime::now().duration_since(std::time::UNIX_EPOCH).unwrap_or_default().as_millis();
    format!("{ms:012x}{:08x}", rand::rng().random::<u32>())
}
