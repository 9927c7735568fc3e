//! `simulate`: prior draws or given rows through the simulator into a dataset folder,
//! `datasets/<job id>/`, in chunks: each chunk (claimed by the job's worker or by any
//! idle one) is written as a part file in `datasets/<job id>/parts/`; a re-claimed job
//! resumes from the finished parts; the job's worker joins the parts in order, as they
//! finish, in this attempt's staging folder, and at the end moves the dataset into place
//! after a fresh renewal of its lease.

use super::spec::{FieldError, effects_of, non_negative, theta_values, with_geometry};
use super::{Ctx, JobContext, JobError, JobSpec, Reporter, Stopped, limits};
use crate::dataset::{self, Rows};
use crate::sim::batch::{Design, Noise, default_noise_std};
use crate::sim::params::{Effects, N_PARAMS, N_TISSUE};
use crate::sim::{Model, ModelConfig};
use crate::store::{ChunkClaim, ChunkRow};
use anyhow::Context;
use serde::{Deserialize, Serialize};
use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::sync::atomic::{AtomicBool, Ordering};
use std::time::Duration;

/// The params of a simulate job: a dataset of simulated rows.
#[derive(Clone, Debug, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct SimulateParams {
    /// Prior draws (or `theta`).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub n: Option<usize>,
    /// Seed of the prior draws and the noise.
    #[serde(default)]
    pub seed: u64,
    /// Rows in the order of the 10 parameters (or the 7 tissue ones), then the `vary`
    /// effects.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub theta: Option<Vec<Vec<f64>>>,
    /// Modelling effects set to a fixed value, by name.
    #[serde(default)]
    pub effects: BTreeMap<String, f64>,
    /// Effects drawn from their range per row (extra columns of theta).
    #[serde(default)]
    pub vary: Vec<String>,
    /// Multiple of the 1× noise model added to x (default 0: noiseless).
    #[serde(default)]
    pub noise_scale: f64,
}

impl SimulateParams {
    pub(super) fn validate(&self, errs: &mut Vec<FieldError>) {
        effects_of(&self.effects, errs);
        for (i, v) in self.vary.iter().enumerate() {
            if Effects::index(v).is_none() {
                errs.push((format!("params.vary[{i}]"), format!("unknown effect '{v}'")));
            } else if self.vary[..i].contains(v) {
                errs.push((format!("params.vary[{i}]"), format!("'{v}' is already varied")));
            }
        }
        match (&self.n, &self.theta) {
            (Some(n), None) => super::spec::in_range("params.n", &limits::SIMULATE_ROWS, *n, errs),
            (None, Some(rows)) if !limits::THETA_ROWS.contains(&rows.len()) => {
                errs.push(("params.theta".into(), format!("needs 1..={} rows", limits::THETA_ROWS.end())))
            }
            (None, Some(rows)) => {
                // Full rows, or tissue-only rows that take the nominal other parameters.
                let (w, short) = (N_PARAMS + self.vary.len(), N_TISSUE + self.vary.len());
                if let Some(i) = rows.iter().position(|r| r.len() != w && r.len() != short) {
                    errs.push((
                        format!("params.theta[{i}]"),
                        format!(
                            "needs {w} values (the {N_PARAMS} parameters, then the varied effects) or {short} \
                             (the {N_TISSUE} tissue parameters with nominal geometry, then the varied effects)"
                        ),
                    ));
                } else {
                    theta_values(&with_geometry(rows, self.vary.len()), errs);
                }
            }
            (Some(_), Some(_)) => errs.push(("params".into(), "give either n or theta, not both".into())),
            (None, None) => errs.push(("params.n".into(), "give n (prior draws) or theta (rows)".into())),
        }
        non_negative("params.noise_scale", self.noise_scale, errs);
    }
}

/// What a simulate job's chunks are run with, from its params.
struct Setup {
    model: Model,
    design: Design,
    noise: Noise,
    rows: Rows,
}

impl Setup {
    fn of(p: &SimulateParams) -> Result<Setup, JobError> {
        let mut design = Design { fixed: effects_of(&p.effects, &mut vec![]), varied: vec![] };
        design.varied = p.vary.iter().filter_map(|v| Effects::index(v)).collect();
        let model = Model::new(ModelConfig::default()).internal("the simulator could not be set up")?;
        let noise = Noise { std: default_noise_std(&model), scale: p.noise_scale, seed: p.seed };
        let rows = match &p.theta {
            Some(t) => Rows::Given(with_geometry(t, design.varied.len())),
            None => Rows::Prior { n: p.n.unwrap_or(0), seed: p.seed },
        };
        Ok(Setup { model, design, noise, rows })
    }

    fn parts<'a>(&'a self, parts: &'a Path) -> dataset::PartRun<'a> {
        dataset::PartRun { model: &self.model, design: &self.design, rows: &self.rows, noise: &self.noise, parts }
    }
}

/// Rows per chunk by default (`serve`/`worker --chunk-rows`).
pub const CHUNK_ROWS: usize = 10_000;

/// The chunks (first row, rows) of a job of `n` rows with chunks of at most `chunk_rows`:
/// at least 4 chunks when `n` allows chunks of 1,000 rows (or of `chunk_rows`, if
/// smaller), so that a small job still resumes and spreads over workers.
pub fn chunk_plan(n: usize, chunk_rows: usize) -> Vec<(usize, usize)> {
    let floor = chunk_rows.clamp(1, 1_000);
    let size = chunk_rows.max(1).min(n.div_ceil(4).max(floor));
    (0..n).step_by(size).map(|first| (first, size.min(n - first))).collect()
}

/// Runs a simulate job as chunks (planned at its first attempt, kept across attempts):
/// claims the chunks nobody holds, one after another, each written as a part file by
/// `run_chunk`, while idle dispatchers anywhere may claim others (`help`); waits for
/// those; joins each leading run of finished parts into this attempt's staging folder
/// as it forms (so that the end copies only the last parts); then, the lease renewed,
/// moves the dataset into `datasets/<id>/`. Chunks finished by an earlier attempt, or by a worker that
/// died after writing its part, are not run again: the job resumes from them, and its
/// dataset is the same bytes as an uninterrupted run (every row has its own streams).
pub(super) fn execute(ctx: &Ctx, id: &str, p: &SimulateParams, r: &Reporter) -> Result<serde_json::Value, JobError> {
    let setup = Setup::of(p)?;
    let n = setup.rows.len();
    let rt = tokio::runtime::Handle::current();
    let dir = ctx.dataset_dir(id);
    let parts = dir.join(dataset::PARTS);
    std::fs::create_dir_all(&parts)
        .with_context(|| format!("creating {}", parts.display()))
        .internal("the dataset's folder could not be created")?;
    let mut chunks = rt.block_on(ctx.store.plan_chunks(id, &chunk_plan(n, ctx.chunk_rows)))?;
    let resumed = chunks.iter().filter(|c| part_finished(&parts, c)).count();
    if resumed > 0 {
        tracing::info!(job = %id, resumed, chunks = chunks.len(), "resuming from finished chunks");
    }
    let mut meta = dataset::Meta::new(
        &setup.design,
        setup.model.config.preset,
        setup.model.frequencies(),
        &setup.noise,
        setup.rows.seed(),
    );
    // The parts are joined in order as they finish, while other chunks still run: at
    // the end only the last ones are left to copy.
    let staging = staging_dir(&dir, &r.claim.1);
    let mut joiner =
        dataset::PartJoiner::create(&parts, &staging, &meta).internal("the dataset's tables could not be created")?;
    if let Err(e) = run_chunks(ctx, id, (&setup, &parts), r, &mut chunks, &mut joiner) {
        joiner.abandon();
        return Err(e);
    }
    joiner.finish(chunks.len(), n, &mut meta).internal("the dataset's chunks could not be joined")?;
    r.still_ours(ctx)?;
    publish_dataset(&staging, &dir)?;
    // The parts are in the dataset now: gone before the job is marked done, so that no
    // end of this process (even a kill right after) leaves them behind.
    remove_temporary_files(&dir, true);
    Ok(serde_json::json!({
        "dataset": format!("/datasets/{id}"),
        "rows": meta.n_rows,
        "failed": meta.failed.len(),
        "wall_seconds": meta.wall_seconds,
        "chunks": chunks.len(),
        "resumed_chunks": resumed,
    }))
}

/// Whether chunk `c`'s part is finished in `parts`: it counts only if it holds the
/// chunk's rows (not those of another plan's chunk).
fn part_finished(parts: &Path, c: &ChunkRow) -> bool {
    dataset::read_part(parts, c.idx).is_some_and(|p| p.first == c.first_row && p.len == c.n_rows)
}

/// The claim-and-run loop of [`execute`]: until every chunk's part is finished, claims
/// and runs the chunks nobody holds, waits for the others, reports progress and hands
/// `joiner` each leading run of finished parts.
fn run_chunks(
    ctx: &Ctx,
    id: &str,
    (setup, parts): (&Setup, &Path),
    r: &Reporter,
    chunks: &mut Vec<ChunkRow>,
    joiner: &mut dataset::PartJoiner<'_>,
) -> Result<(), JobError> {
    let rt = tokio::runtime::Handle::current();
    let n = setup.rows.len();
    let finished = |c: &ChunkRow| part_finished(parts, c);
    loop {
        // The parts on disk say what is finished; the table is brought in line with them.
        let (mut done, mut done_rows) = (0, 0);
        // Parts already joined are finished: their JSON is not read again.
        let joined = joiner.appended();
        let ended: Vec<bool> = chunks.iter().enumerate().map(|(i, c)| i < joined || finished(c)).collect();
        for (c, &end) in chunks.iter().zip(&ended) {
            match (end, c.state.as_str()) {
                (true, _) => (done, done_rows) = (done + 1, done_rows + c.n_rows),
                (false, "done") => rt.block_on(ctx.store.set_chunk_state(&c.id, "queued"))?,
                _ => {}
            }
        }
        let leading = ended.iter().take_while(|&&e| e).count();
        joiner.append_upto(leading).internal("the dataset's chunks could not be joined")?;
        let status = |rows: usize| format!("simulated {rows}/{n} rows ({done}/{} chunks)", chunks.len());
        if !r.report(done_rows as f64 / n.max(1) as f64, status(done_rows)) {
            return Err(Stopped.into());
        }
        if done == chunks.len() {
            break;
        }
        match rt.block_on(ctx.store.claim_chunk(Some(id), &ctx.worker, ctx.chunk_lease()))? {
            Some(claim) if finished(&claim.chunk) => {
                rt.block_on(ctx.store.end_chunk(&claim, true))?;
            }
            Some(claim) => {
                let mut progress =
                    |rows: usize| r.report((done_rows + rows) as f64 / n as f64, status(done_rows + rows));
                match run_chunk(ctx, setup, parts, &claim, &mut progress) {
                    // The job is stopping (cancel, shutdown, its lease lost).
                    Err(e) if e.is::<Stopped>() && r.cancel.load(Ordering::Relaxed) => return Err(e),
                    // Only the chunk's lease was lost: another worker runs it.
                    Err(e) if e.is::<Stopped>() => {}
                    res => res?,
                }
            }
            // Every chunk left is held by another worker: wait for its part (a short
            // poll: at the job's end this wait is the whole job's, and it costs two
            // small queries).
            None => std::thread::sleep(Duration::from_millis(50)),
        }
        *chunks = rt.block_on(ctx.store.chunks(id))?;
    }
    Ok(())
}

/// A running simulate job's progress as its chunk table tells it: the rows of finished
/// chunks, whichever worker finished them, over all rows, with the job's own message
/// format. `None` before the chunks are planned. GET /jobs/{id} shows the larger of this
/// and what the job's worker last wrote, which lags while that worker runs a chunk of
/// its own or waits for others.
pub fn progress_from_chunks(chunks: &[ChunkRow]) -> Option<(f64, String)> {
    let total: usize = chunks.iter().map(|c| c.n_rows).sum();
    if total == 0 {
        return None;
    }
    let finished: Vec<&ChunkRow> = chunks.iter().filter(|c| c.state == "done").collect();
    let rows: usize = finished.iter().map(|c| c.n_rows).sum();
    let message = format!("simulated {rows}/{total} rows ({}/{} chunks)", finished.len(), chunks.len());
    Some((rows as f64 / total as f64, message))
}

/// Runs one claimed chunk into its part file under the chunk's lease (renewed on the
/// runtime meanwhile), then marks it done; a chunk that stops or fails goes back to the
/// queue for any worker. `Err(Stopped)` when `progress` or the lease stopped it.
fn run_chunk(
    ctx: &Ctx,
    setup: &Setup,
    parts: &Path,
    claim: &ChunkClaim,
    progress: &mut dyn FnMut(usize) -> bool,
) -> Result<(), JobError> {
    let rt = tokio::runtime::Handle::current();
    let c = &claim.chunk;
    ctx.metrics.chunk_run();
    let lost = Arc::new(AtomicBool::new(false));
    let renewal = rt.spawn(renew_chunk(ctx.store.clone(), claim.clone(), ctx.chunk_lease(), lost.clone()));
    let mut last = 0;
    let res = setup.parts(parts).simulate(c.idx, c.first_row, c.n_rows, &claim.token[..16], &mut |rows| {
        ctx.metrics.simulated(rows.saturating_sub(last) as u64);
        last = rows;
        progress(rows) && !lost.load(Ordering::Relaxed)
    });
    renewal.abort();
    let ended = rt.block_on(ctx.store.end_chunk(claim, res.is_ok()));
    match res {
        Ok(_) => {
            ended?;
            Ok(())
        }
        Err(dataset::DatasetError::Cancelled(_)) => Err(Stopped.into()),
        Err(e) => Err(JobError::internal(
            format!("chunk {} (rows {}..{}) could not be simulated", c.idx, c.first_row, c.first_row + c.n_rows),
            e,
        )),
    }
}

/// Renews a chunk's lease every third of it until aborted; raises `lost` if it is lost.
async fn renew_chunk(store: crate::store::Store, claim: ChunkClaim, lease: Duration, lost: Arc<AtomicBool>) {
    loop {
        tokio::time::sleep(lease / 3).await;
        match store.chunk_heartbeat(&claim, lease).await {
            Ok(true) => {}
            Ok(false) => {
                tracing::warn!(chunk = %claim.chunk.id, "chunk lease lost: another worker runs it");
                lost.store(true, Ordering::Relaxed);
                return;
            }
            // A database hiccup: two thirds of the lease remain; retried next time.
            Err(e) => tracing::warn!(chunk = %claim.chunk.id, error = %e, "chunk lease not renewed"),
        }
    }
}

/// An idle dispatcher's share of another job: runs the claimed chunk of a simulate job
/// that some worker owns. It stops when the job is cancelled, ends or the process shuts
/// down (checked every 300 ms on the runtime), and gives the chunk back.
pub(super) async fn help(ctx: Arc<Ctx>, claim: ChunkClaim) {
    let c = claim.chunk.clone();
    let stop = Arc::new(AtomicBool::new(false));
    let (c2, s2) = (ctx.clone(), stop.clone());
    let mut work = tokio::task::spawn_blocking(move || -> Result<(), JobError> {
        let rt = tokio::runtime::Handle::current();
        let job = rt.block_on(c2.store.job(&claim.chunk.job_id))?.ok_or_else(|| JobError::client("the job is gone"))?;
        let JobSpec::Simulate(p) = JobSpec::of(&job).internal("the job's stored params do not read")? else {
            return Err(JobError::client("not a simulate job"));
        };
        let setup = Setup::of(&p)?;
        let parts = c2.dataset_dir(&job.id).join(dataset::PARTS);
        run_chunk(&c2, &setup, &parts, &claim, &mut |_| !s2.load(Ordering::Relaxed))
    });
    let mut check = tokio::time::interval(Duration::from_millis(300));
    let res = loop {
        tokio::select! {
            res = &mut work => break res,
            _ = check.tick() => {
                let job = ctx.store.job(&c.job_id).await.ok().flatten();
                let going = job.is_some_and(|j| j.state == "running" && !j.cancel_requested);
                if !going || ctx.shutdown.load(Ordering::Relaxed) {
                    stop.store(true, Ordering::Relaxed);
                }
            }
        }
    };
    match res {
        Ok(Ok(())) => tracing::info!(chunk = %c.id, rows = c.n_rows, "chunk of another worker's job done"),
        Ok(Err(e)) if e.is::<Stopped>() => tracing::info!(chunk = %c.id, "chunk stopped and given back"),
        Ok(Err(e)) => {
            let cause = e.cause().map(|c| format!("{c:#}"));
            tracing::warn!(chunk = %c.id, error = %e, cause = ?cause, "chunk failed and given back")
        }
        Err(e) => tracing::error!(chunk = %c.id, error = %e, "chunk panicked"),
    }
    // The job may have ended (cancelled, failed) while this chunk ran: its worker removed
    // the job's files then, and what this chunk wrote afterwards must go too.
    let ended =
        ctx.store.job(&c.job_id).await.ok().flatten().filter(|j| !matches!(j.state.as_str(), "queued" | "running"));
    if let Some(job) = ended {
        let dir = ctx.dataset_dir(&job.id);
        let _ = tokio::task::spawn_blocking(move || remove_temporary_files(&dir, true)).await;
    }
}

/// Before a cancelled simulate job shows as cancelled: waits (at most 10 s) for the
/// idle dispatchers that run its chunks to give them back (they check every 300 ms),
/// then removes its parts and temporary files, so that a job seen as cancelled has left
/// nothing behind. Only while this worker still holds the job's lease: otherwise the
/// files are another attempt's.
pub(super) async fn clear_cancelled(ctx: &Ctx, id: &str, token: &str) {
    let t0 = std::time::Instant::now();
    loop {
        // The job's lease, renewed while waiting (its renewal loop has ended).
        if !matches!(ctx.store.heartbeat(id, token, ctx.lease).await, Ok(true)) {
            return;
        }
        let held = ctx.store.chunks(id).await.is_ok_and(|cs| cs.iter().any(|c| c.state == "running"));
        if !held || t0.elapsed() > Duration::from_secs(10) {
            break;
        }
        tokio::time::sleep(Duration::from_millis(100)).await;
    }
    let dir = ctx.dataset_dir(id);
    let _ = tokio::task::spawn_blocking(move || remove_temporary_files(&dir, true)).await;
}

/// Moves a finished simulate attempt's files from its staging folder into `dir`;
/// meta.json goes last; if a move fails, the files moved before it are taken away again,
/// so that a failed job leaves no half dataset.
fn publish_dataset(staging: &Path, dir: &Path) -> Result<(), JobError> {
    for (i, name) in dataset::FILES.iter().enumerate() {
        let (from, to) = (staging.join(name), dir.join(name));
        if let Err(e) = std::fs::rename(&from, &to) {
            for moved in &dataset::FILES[..i] {
                let _ = std::fs::remove_file(dir.join(moved));
            }
            let cause = anyhow::Error::from(e).context(format!("moving {} to {}", from.display(), to.display()));
            return Err(JobError::internal(format!("the dataset's {name} could not be moved into place"), cause));
        }
    }
    let _ = std::fs::remove_dir(staging);
    Ok(())
}

/// The staging folder of one attempt of a simulate job: its own, so two attempts of the
/// same job (a stalled worker and the one that took over) never write the same files.
pub(super) fn staging_dir(dir: &Path, token: &str) -> PathBuf {
    dir.join(format!(".attempt-{}", &token[..token.len().min(16)]))
}

/// Removes what a simulate run leaves besides its dataset: `*.tmp` files (in the
/// folder and among the parts), the staging folders (`.attempt-*`) of its attempts,
/// and, with `parts`, the finished parts too (the job has ended: they are in its
/// dataset, or no longer wanted). Finished parts are kept otherwise: a re-queued job
/// resumes from them. Returns how many entries went.
pub fn remove_temporary_files(dir: &Path, parts: bool) -> usize {
    let tmp = |d: &Path| -> usize {
        let Ok(entries) = std::fs::read_dir(d) else { return 0 };
        entries
            .flatten()
            .filter(|e| {
                let name = e.file_name().to_string_lossy().into_owned();
                if name.starts_with(".attempt-") {
                    std::fs::remove_dir_all(e.path()).is_ok()
                } else {
                    name.ends_with(".tmp") && std::fs::remove_file(e.path()).is_ok()
                }
            })
            .count()
    };
    let parts_dir = dir.join(dataset::PARTS);
    let n = tmp(dir) + tmp(&parts_dir);
    if parts && parts_dir.exists() {
        return n + usize::from(std::fs::remove_dir_all(&parts_dir).is_ok());
    }
    n
}

#[cfg(test)]
mod tests {
    use super::chunk_plan;

    #[test]
    fn chunk_plans_cover_every_row_once_in_chunks_of_at_most_the_limit() {
        assert_eq!(chunk_plan(100_000, 10_000).len(), 10);
        assert_eq!(chunk_plan(30_000, 10_000), [(0, 7500), (7500, 7500), (15_000, 7500), (22_500, 7500)]);
        assert_eq!(chunk_plan(200, 10_000), [(0, 200)]);
        assert_eq!(chunk_plan(5000, 500).len(), 10);
        for (n, size) in [(1, 1), (999, 10_000), (4001, 1000), (12_345, 333)] {
            let plan = chunk_plan(n, size);
            assert!(plan.iter().all(|(_, len)| (1..=size).contains(len)), "{n} {size}: {plan:?}");
            let mut next = 0;
            for (first, len) in plan {
                assert_eq!(first, next);
                next += len;
            }
            assert_eq!(next, n);
        }
    }
}
