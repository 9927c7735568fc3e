//! Chunked, resumable simulate jobs on both backends: a worker
//! process killed mid-job leaves finished part files; the job, taken up again (SQLite:
//! a new process; PostgreSQL: another worker after the lease), resumes from them, and
//! its dataset is the same bytes as an uninterrupted run with the same seed.

use crate::pg::{Procs, backends, temp_dir, wait_state};
use otofit::jobs::{self, JobSpec};
use otofit::store::{Database, Store};
use serde_json::json;
use std::path::Path;
use std::process::{Command, Stdio};
use std::time::{Duration, Instant};

const ROWS: usize = 5000;
const CHUNK: usize = 500;
const SEED: u64 = 7;

fn spawn_worker(db: &Database, data: &Path, lease: &str) -> std::process::Child {
    let mut c = Command::new(env!("CARGO_BIN_EXE_otofit"));
    c.args(["worker", "--data-dir", data.to_str().unwrap(), "--lease-seconds", lease]);
    c.args(["--threads", "1", "--chunk-rows", &CHUNK.to_string()]);
    if let Database::Postgres(url) = db {
        c.args(["--database", url]);
    }
    c.stdout(Stdio::null()).stderr(Stdio::null()).spawn().unwrap()
}

/// The reference: the same rows by `otofit simulate` in one uninterrupted pass.
fn reference(dir: &Path) {
    let out = Command::new(env!("CARGO_BIN_EXE_otofit"))
        .args(["simulate", "--n", &ROWS.to_string(), "--seed", &SEED.to_string(), "--noise-scale", "1"])
        .args(["--out", dir.to_str().unwrap()])
        .output()
        .unwrap();
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
}

async fn done_chunks(store: &Store, id: &str) -> usize {
    store.chunks(id).await.unwrap().iter().filter(|c| c.state == "done").count()
}

/// A dispatcher of worker "w" on `store`, in chunks of `chunk_rows`, running on the
/// test's runtime.
fn dispatching(store: &Store, data: &Path, chunk_rows: usize) -> std::sync::Arc<otofit::jobs::Ctx> {
    let ctx = crate::pg::ctx_on(store.clone(), data, "w", Duration::from_secs(30));
    let ctx = std::sync::Arc::new(std::sync::Arc::into_inner(ctx).unwrap().with_chunk_rows(chunk_rows));
    tokio::spawn(jobs::dispatcher(ctx.clone()));
    ctx
}

/// Every file under `dir`, recursively, by name.
fn files_under(dir: &Path) -> Vec<String> {
    let mut out = vec![];
    for e in std::fs::read_dir(dir).into_iter().flatten().flatten() {
        let p = e.path();
        if p.is_dir() {
            out.push(format!("{}/", e.file_name().to_string_lossy()));
            out.extend(files_under(&p));
        } else {
            out.push(e.file_name().to_string_lossy().into_owned());
        }
    }
    out
}

/// A 5,000-row simulate job in chunks of 500 (10 parts), its worker process stopped
/// (SIGSTOP, so that it cannot finish meanwhile) once a chunk is done and killed
/// (SIGKILL: no re-queue, no clean-up); a new worker process takes the job up (SQLite:
/// at its start; PostgreSQL: after the dead worker's lease) and resumes from the parts.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_killed_simulate_resumes_from_its_finished_chunks_with_the_same_bytes() {
    let ref_dir = temp_dir("resume-ref");
    reference(&ref_dir);
    for (name, db) in backends().await {
        let data = temp_dir(&format!("resume-{name}"));
        // SQLite: the database in the data directory, as `otofit worker` opens it.
        let db = match db {
            Database::Sqlite(_) => Database::Sqlite(data.join("otofit.db")),
            pg => pg,
        };
        let store = Store::connect(&db).await.unwrap();
        let spec = JobSpec::parse("simulate", &json!({"n": ROWS, "seed": SEED, "noise_scale": 1})).unwrap();
        assert!(store.insert_job_within("big", "simulate", &spec.params(), 3, 8).await.unwrap());
        let mut procs = Procs(vec![spawn_worker(&db, &data, "2")]);
        let t0 = Instant::now();
        while done_chunks(&store, "big").await == 0 && t0.elapsed() < Duration::from_secs(60) {
            tokio::time::sleep(Duration::from_millis(5)).await;
        }
        let pid = procs.0[0].id() as i32;
        // SAFETY: a signal to our own child.
        unsafe { libc::kill(pid, libc::SIGSTOP) };
        let before = done_chunks(&store, "big").await;
        assert!((1..10).contains(&before), "{name}: {before} of 10 chunks done at the kill");
        procs.0[0].kill().unwrap();
        procs.0[0].wait().unwrap();
        let parts = data.join("datasets/big/parts");
        let finished = (0..10).filter(|i| parts.join(format!("part-{i:05}.json")).exists()).count();
        assert!(finished >= before, "{name}: the done chunks' parts are on disk ({finished})");
        assert_eq!(store.job("big").await.unwrap().unwrap().state, "running", "{name}");
        procs.0.push(spawn_worker(&db, &data, "2"));
        let j = wait_state(&store, "big", &["succeeded", "failed", "cancelled"], 120).await;
        drop(procs);
        assert_eq!((j.state.as_str(), j.attempts), ("succeeded", 2), "{name}: {:?}", j.error);
        let result = j.result.unwrap();
        assert_eq!((result["rows"].as_u64(), result["chunks"].as_u64()), (Some(ROWS as u64), Some(10)), "{name}");
        let resumed = result["resumed_chunks"].as_u64().unwrap();
        assert!(resumed as usize >= finished, "{name}: resumed from {resumed} chunks, {finished} were finished");
        for f in ["theta.csv", "x.csv"] {
            let (got, want) =
                (std::fs::read(data.join("datasets/big").join(f)).unwrap(), std::fs::read(ref_dir.join(f)).unwrap());
            assert!(
                got == want,
                "{name}: {f} differs from the uninterrupted run ({} vs {} bytes)",
                got.len(),
                want.len()
            );
        }
        // Nothing but the dataset is left: no parts, no temporary files.
        let mut left = files_under(&data.join("datasets/big"));
        left.sort();
        assert_eq!(left, ["meta.json", "theta.csv", "x.csv"], "{name}");
    }
}

/// With PostgreSQL, the chunks of one job are run by every idle worker: three
/// dispatchers (as three worker processes would) share the 20 chunks of one job, and
/// the dataset is the same bytes as one uninterrupted run.
#[tokio::test(flavor = "multi_thread", worker_threads = 4)]
async fn the_chunks_of_one_job_are_shared_by_all_workers() {
    let Some(url) = crate::pg::fresh_database().await else { return };
    let db = Database::Postgres(url);
    let data = temp_dir("chunks-pg");
    let ref_dir = temp_dir("chunks-ref");
    reference(&ref_dir);
    let store = Store::connect(&db).await.unwrap();
    let spec = JobSpec::parse("simulate", &json!({"n": ROWS, "seed": SEED, "noise_scale": 1})).unwrap();
    assert!(store.insert_job_within("shared", "simulate", &spec.params(), 3, 8).await.unwrap());
    let mut ctxs = vec![];
    for w in 0..3 {
        let ctx =
            crate::pg::ctx_on(Store::connect(&db).await.unwrap(), &data, &format!("w{w}"), Duration::from_secs(30));
        let ctx = std::sync::Arc::new(std::sync::Arc::into_inner(ctx).unwrap().with_chunk_rows(250));
        tokio::spawn(jobs::dispatcher(ctx.clone()));
        ctxs.push(ctx);
        if w == 0 {
            // The others start once w0 has planned the chunks: idle, they look for
            // chunks at once (and then every second, which a fast job may not wait for).
            let t0 = Instant::now();
            while store.chunks("shared").await.unwrap().is_empty() && t0.elapsed() < Duration::from_secs(60) {
                tokio::time::sleep(Duration::from_millis(5)).await;
            }
        }
    }
    let j = wait_state(&store, "shared", &["succeeded", "failed", "cancelled"], 120).await;
    for c in &ctxs {
        c.shutdown.store(true, std::sync::atomic::Ordering::Relaxed);
    }
    assert_eq!((j.state.as_str(), j.attempts), ("succeeded", 1), "{:?}", j.error);
    let chunks = store.chunks("shared").await.unwrap();
    assert_eq!(chunks.len(), 20);
    let by: std::collections::BTreeSet<_> = chunks.iter().filter_map(|c| c.worker.clone()).collect();
    assert!(by.len() >= 2, "the chunks were run by one worker only: {by:?}");
    // Each worker's /metrics counts the chunks it ran, its own job's and others'.
    let ran = |c: &otofit::jobs::Ctx| -> u64 {
        let text = c.metrics.render(&otofit::jobs::KINDS, &[], true);
        let line = text.lines().find(|l| l.starts_with("otofit_chunk_runs_total ")).unwrap().to_string();
        line.rsplit(' ').next().unwrap().parse().unwrap()
    };
    let counted: Vec<u64> = ctxs.iter().map(|c| ran(c)).collect();
    for (c, n) in ctxs.iter().zip(&counted) {
        let marked = chunks.iter().filter(|k| k.worker.as_deref() == Some(c.worker.as_str())).count() as u64;
        assert!(*n >= marked, "worker {} counted {n} chunks but ran {marked}: {counted:?}", c.worker);
    }
    assert!(counted.iter().sum::<u64>() >= 20, "{counted:?}");
    for f in ["theta.csv", "x.csv"] {
        let (got, want) =
            (std::fs::read(data.join("datasets/shared").join(f)).unwrap(), std::fs::read(ref_dir.join(f)).unwrap());
        assert!(got == want, "{f} differs from the uninterrupted run");
    }
}

/// A cancelled chunked simulate removes everything it wrote: finished parts, the
/// temporary files of the chunk under way, staging folders.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_cancelled_simulate_leaves_no_parts_or_temporary_files() {
    for (name, db) in backends().await {
        let data = temp_dir(&format!("cancel-{name}"));
        let store = Store::connect(&db).await.unwrap();
        let spec = JobSpec::parse("simulate", &json!({"n": 100_000, "seed": 1})).unwrap();
        assert!(store.insert_job_within("c", "simulate", &spec.params(), 3, 8).await.unwrap());
        let ctx = dispatching(&store, &data, 2000);
        let t0 = Instant::now();
        while done_chunks(&store, "c").await == 0 && t0.elapsed() < Duration::from_secs(60) {
            tokio::time::sleep(Duration::from_millis(10)).await;
        }
        assert!(data.join("datasets/c/parts/part-00000.json").exists(), "{name}: a part is written");
        store.cancel("c").await.unwrap();
        let j = wait_state(&store, "c", &["succeeded", "failed", "cancelled"], 60).await;
        ctx.shutdown.store(true, std::sync::atomic::Ordering::Relaxed);
        assert_eq!(j.state, "cancelled", "{name}");
        let left = files_under(&data.join("datasets/c"));
        assert!(left.is_empty(), "{name}: {left:?}");
    }
}

/// A chunk plan left incomplete (a process killed while planning, before the plan was
/// written in one transaction) is replaced, not taken for the whole job: the dataset
/// has every row. A CI run once published 20,000 of 40,000 rows this way.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_partial_chunk_plan_is_replaced_and_the_dataset_has_every_row() {
    for (name, db) in backends().await {
        let data = temp_dir(&format!("partial-{name}"));
        let store = Store::connect(&db).await.unwrap();
        let spec = JobSpec::parse("simulate", &json!({"n": 4000, "seed": 3})).unwrap();
        assert!(store.insert_job_within("p", "simulate", &spec.params(), 3, 8).await.unwrap());
        // Half a plan of 1,000-row chunks, as a kill between two inserts left it.
        let half = store.plan_chunks("p", &[(0, 1000), (1000, 1000)]).await.unwrap();
        assert_eq!(half.len(), 2, "{name}");
        let ctx = dispatching(&store, &data, 1000);
        let j = wait_state(&store, "p", &["succeeded", "failed", "cancelled"], 60).await;
        ctx.shutdown.store(true, std::sync::atomic::Ordering::Relaxed);
        assert_eq!(j.state, "succeeded", "{name}: {j:?}");
        assert_eq!(store.chunks("p").await.unwrap().len(), 4, "{name}");
        let x = std::fs::read_to_string(data.join("datasets/p/x.csv")).unwrap();
        assert_eq!(x.lines().count(), 4001, "{name}: every row, once");
    }
}

/// Parts that leave a gap, or cover fewer rows than the dataset has, are refused at the
/// merge: the job fails rather than publish a short dataset.
#[test]
fn merging_parts_that_do_not_cover_every_row_is_an_error() {
    use otofit::dataset::{self, Meta, PartRun, Rows};
    use otofit::sim::batch::{Design, Noise};
    use otofit::sim::{Model, ModelConfig};
    let dir = temp_dir("merge-gap");
    let parts = dir.join("parts");
    std::fs::create_dir_all(&parts).unwrap();
    let model = Model::new(ModelConfig::default()).unwrap();
    let design = Design::default();
    let noise = Noise { std: vec![0.0; model.frequencies().len() * 5], scale: 0.0, seed: 1 };
    let rows = Rows::Prior { n: 30, seed: 1 };
    let run = PartRun { model: &model, design: &design, rows: &rows, noise: &noise, parts: &parts };
    run.simulate(0, 0, 10, "t", &mut |_| true).unwrap();
    run.simulate(1, 20, 10, "t", &mut |_| true).unwrap();
    let meta = || Meta::new(&design, model.config.preset, model.frequencies(), &noise, Some(1));
    // The error with its causes, as the job's error shows it.
    let chain = |e: dataset::DatasetError| format!("{:#}", anyhow::Error::from(e));
    let err = chain(dataset::merge_parts(&parts, 2, 30, &dir.join("a"), &mut meta()).unwrap_err());
    assert!(err.contains("part-00001") && err.contains("expected from row 10"), "{err}");
    assert!(!dir.join("a/x.csv").exists(), "nothing published");
    let err = chain(dataset::merge_parts(&parts, 1, 30, &dir.join("b"), &mut meta()).unwrap_err());
    assert!(err.contains("10 of 30"), "{err}");
    run.simulate(1, 10, 10, "t", &mut |_| true).unwrap();
    run.simulate(2, 20, 10, "t", &mut |_| true).unwrap();
    dataset::merge_parts(&parts, 3, 30, &dir.join("c"), &mut meta()).unwrap();
    assert_eq!(std::fs::read_to_string(dir.join("c/x.csv")).unwrap().lines().count(), 31);
}

/// Parts joined as they finish, a few at a time while others are still running, give
/// the same dataset bytes as parts joined all at once; a part not yet finished is not
/// joined.
#[test]
fn parts_joined_as_they_finish_are_the_same_bytes_as_joined_at_once() {
    use otofit::dataset::{self, Meta, PartJoiner, PartRun, Rows};
    use otofit::sim::batch::{Design, Noise};
    use otofit::sim::{Model, ModelConfig};
    let dir = temp_dir("join-steps");
    let parts = dir.join("parts");
    std::fs::create_dir_all(&parts).unwrap();
    let model = Model::new(ModelConfig::default()).unwrap();
    let design = Design::default();
    let noise = Noise { std: otofit::sim::batch::default_noise_std(&model), scale: 1.0, seed: 4 };
    let rows = Rows::Prior { n: 30, seed: 2 };
    let run = PartRun { model: &model, design: &design, rows: &rows, noise: &noise, parts: &parts };
    let meta = || Meta::new(&design, model.config.preset, model.frequencies(), &noise, Some(2));
    run.simulate(0, 0, 12, "t", &mut |_| true).unwrap();
    let mut joiner = PartJoiner::create(&parts, &dir.join("steps"), &meta()).unwrap();
    joiner.append_upto(1).unwrap();
    let err = format!("{:#}", anyhow::Error::from(joiner.append_upto(2).unwrap_err()));
    assert!(err.contains("part-00001") && err.contains("not finished"), "{err}");
    run.simulate(1, 12, 9, "t", &mut |_| true).unwrap();
    run.simulate(2, 21, 9, "t", &mut |_| true).unwrap();
    joiner.append_upto(2).unwrap();
    assert_eq!(joiner.appended(), 2);
    let mut stepped = meta();
    joiner.finish(3, 30, &mut stepped).unwrap();
    let mut at_once = meta();
    dataset::merge_parts(&parts, 3, 30, &dir.join("once"), &mut at_once).unwrap();
    for f in dataset::FILES {
        let (a, b) =
            (std::fs::read(dir.join("steps").join(f)).unwrap(), std::fs::read(dir.join("once").join(f)).unwrap());
        if f != "meta.json" {
            assert!(a == b, "{f} differs");
        }
    }
    assert_eq!((stepped.n_rows, stepped.failed.len()), (at_once.n_rows, at_once.failed.len()));
    assert_eq!(std::fs::read_to_string(dir.join("steps/x.csv")).unwrap().lines().count(), 31);
}

/// A simulate job's progress follows every worker's finished chunks: the chunk table,
/// not only what the job's own worker last wrote (which lags while it runs a chunk of its
/// own). Two of three chunks finished by "other workers", the third running, read as
/// 2/3 of the rows.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn progress_counts_chunks_finished_by_any_worker() {
    for (name, db) in backends().await {
        let store = Store::connect(&db).await.unwrap();
        let spec = JobSpec::parse("simulate", &json!({"n": 3000, "seed": 3})).unwrap();
        assert!(store.insert_job_within("g", "simulate", &spec.params(), 3, 8).await.unwrap());
        let lease = Duration::from_secs(30);
        let job = store.claim("owner", lease).await.unwrap().expect("the job is claimed");
        store.plan_chunks("g", &[(0, 1000), (1000, 1000), (2000, 1000)]).await.unwrap();
        let planned = otofit::jobs::progress_from_chunks(&store.chunks("g").await.unwrap()).unwrap();
        assert_eq!(planned, (0.0, "simulated 0/3000 rows (0/3 chunks)".to_string()), "{name}");
        for helper in ["w1", "w2"] {
            let claim = store.claim_chunk(Some("g"), helper, lease).await.unwrap().unwrap();
            assert!(store.end_chunk(&claim, true).await.unwrap(), "{name}");
        }
        // The third is running on the owner: not finished, not counted.
        store.claim_chunk(Some("g"), "owner", lease).await.unwrap().unwrap();
        let (p, message) = otofit::jobs::progress_from_chunks(&store.chunks("g").await.unwrap()).unwrap();
        assert!((p - 2.0 / 3.0).abs() < 1e-12, "{name}: {p}");
        assert_eq!(message, "simulated 2000/3000 rows (2/3 chunks)", "{name}");
        assert!(job.progress < p, "{name}: the owner wrote nothing meanwhile");
    }
}
