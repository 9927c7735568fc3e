//! `otofit worker`: a job runner without HTTP. It claims jobs from the shared job table
//! (PostgreSQL; or SQLite, where it then owns the data directory alone), renews each
//! claim's lease while it runs, and stops at SIGTERM/Ctrl-C after putting its running job
//! back in the queue.

use super::serve::{database_arg, open_state, shutdown_signal, stop_dispatchers};
use crate::jobs;
use anyhow::{Context, Result, bail};
use clap::Args;
use std::path::PathBuf;
use std::sync::Arc;

/// Arguments of `otofit worker`.
#[derive(Args, Debug)]
pub struct WorkerArgs {
    /// The job table: `postgres://USER:PASSWORD@HOST:PORT/DB` (shared with `serve` and
    /// other workers) or `sqlite://PATH` (default: DATA_DIR/otofit.db).
    #[arg(long, env = "OTOFIT_DATABASE")]
    pub database: Option<String>,
    /// Datasets, models and reports: the same directory (a shared volume) as the servers',
    /// or this worker's scratch space with `--artifacts s3://…`.
    #[arg(long, default_value = "data")]
    pub data_dir: PathBuf,
    /// Jobs this process runs at once.
    #[arg(long, default_value_t = 1)]
    pub concurrency: usize,
    /// Threads for the simulations and training of this process (default: all cores).
    #[arg(long)]
    pub threads: Option<usize>,
    /// How this process runs jobs: leases, chunks, retries, the artifact store.
    #[command(flatten)]
    pub jobs: super::serve::JobFlags,
    /// Serve GET /metrics (Prometheus text: this worker's claims, simulated rows, job
    /// durations, and the job table) on this address; no API, no keys: keep it on
    /// loopback or a private network.
    #[arg(long)]
    pub metrics_addr: Option<std::net::SocketAddr>,
    /// Logs as JSON lines.
    #[arg(long)]
    pub log_json: bool,
}

/// Runs `otofit worker` until SIGTERM or Ctrl-C.
pub fn run(args: WorkerArgs) -> Result<()> {
    super::serve::init_logs(args.log_json);
    let database = database_arg(args.database.as_deref(), &args.data_dir)?;
    let settings = args.jobs.settings()?;
    if !(1..=super::serve::MAX_WORKERS).contains(&args.concurrency) {
        bail!("--concurrency must be 1..={}, got {}", super::serve::MAX_WORKERS, args.concurrency);
    }
    if let Some(n) = args.threads {
        if !(1..=1024).contains(&n) {
            bail!("--threads must be 1..=1024, got {n}");
        }
        rayon::ThreadPoolBuilder::new().num_threads(n).build_global()?;
    }
    let rt = tokio::runtime::Builder::new_multi_thread().enable_all().build()?;
    let res = rt.block_on(async move {
        let ctx = Arc::new(open_state(&database, &args.data_dir, settings, args.jobs.artifacts.as_deref()).await?);
        tracing::info!(
            worker = %ctx.worker,
            database = %database.redacted(),
            data_dir = %args.data_dir.display(),
            artifacts = %ctx.artifacts.describe(),
            concurrency = args.concurrency,
            lease_seconds = settings.lease.as_secs_f64(),
            chunk_rows = settings.chunk_rows,
            "otofit worker started"
        );
        if let Some(addr) = args.metrics_addr {
            let listener = tokio::net::TcpListener::bind(addr)
                .await
                .with_context(|| format!("--metrics-addr: cannot listen on {addr}"))?;
            let app = crate::http::metrics_router(ctx.clone());
            tokio::spawn(async move { axum::serve(listener, app).await });
            tracing::info!(%addr, "serving /metrics");
        }
        let dispatchers: Vec<_> = (0..args.concurrency).map(|_| tokio::spawn(jobs::dispatcher(ctx.clone()))).collect();
        if args.concurrency > 0 {
            tokio::spawn(jobs::wake_on_announced_work(ctx.clone()));
        }
        shutdown_signal().await;
        tracing::info!("shutting down: no new jobs; the running ones stop at their next check");
        if !stop_dispatchers(&ctx, dispatchers).await {
            bail!("a running job did not stop within 60 s; its lease expires and another worker takes it");
        }
        Ok(())
    });
    rt.shutdown_timeout(std::time::Duration::from_secs(1));
    res
}
