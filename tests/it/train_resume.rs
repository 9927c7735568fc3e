//! Checkpointed training: a training stopped (in process) or killed (a worker
//! process, SIGKILL) resumes from its last checkpoint, and its model is the same, bit for
//! bit, as an uninterrupted run's with the same seed.

use crate::pg::{Procs, temp_dir, wait_state};
use otofit::jobs::JobSpec;
use otofit::npe::{self, Checkpointing, Dataset, Obs, Param, Scale, TrainSettings};
use otofit::store::{Database, Store};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use serde_json::json;
use std::path::Path;
use std::process::{Command, Stdio};
use std::time::{Duration, Instant};

/// 300 rows of x = (θ0 + θ1, θ0 − θ1, θ0 θ1 / 4), θ uniform on [−2, 2]².
fn tiny(seed: u64) -> Dataset {
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    let theta: Vec<Vec<f64>> =
        (0..300).map(|_| vec![rng.random_range(-2.0..2.0), rng.random_range(-2.0..2.0)]).collect();
    Dataset {
        params: ["p", "q"]
            .iter()
            .map(|n| Param { name: n.to_string(), unit: "1".into(), scale: Scale::Linear, low: -2.0, high: 2.0 })
            .collect(),
        feature_names: vec!["s".into(), "d".into(), "m".into()],
        frequencies_hz: vec![],
        groups: vec![],
        noise_std: vec![0.2; 3],
        x: theta.iter().map(|t| vec![t[0] + t[1], t[0] - t[1], t[0] * t[1] / 4.0]).collect(),
        theta,
        skipped: 0,
    }
}

/// The model's numbers and its draws for `x`: what "the same model" is compared by (a
/// model file also has the wall time, and burn's parameter ids, random per process).
fn fingerprint(m: &npe::Npe, x: &[f64]) -> (usize, usize, u64, Vec<Vec<f64>>) {
    let t = &m.header.training;
    (t.epochs, t.best_epoch, t.best_val_loss.to_bits(), m.sample(&Obs { x, present: None }, 200, 1).unwrap())
}

/// A two-member ensemble (side by side where there are two threads) stopped by its
/// progress callback in member 1's 6th epoch (a checkpoint is written at the stop), then
/// trained again with the checkpoint: it resumes from the epochs the stopped training
/// ran, trains none of them again, and ends with the model of an uninterrupted training,
/// bit for bit. A checkpoint of other settings is not resumed from.
#[test]
fn a_stopped_training_resumes_from_its_checkpoint_to_the_same_model() {
    let ds = tiny(1);
    let s =
        TrainSettings { embedding: false, max_epochs: 12, patience: 40, ensemble: 2, seed: 4, ..Default::default() };
    let whole = npe::train(&ds, &s, &mut |_| true).unwrap();
    assert_eq!(whole.header.training.epochs, 24);
    let dir = temp_dir("train-ckpt");
    let c = Checkpointing::new(dir.join("t.ckpt"), "a");
    let mut last = [0; 2];
    let stopped = npe::train_checkpointed(&ds, &s, Some(&c), &mut |e| {
        last[e.member] = e.epoch;
        !(e.member == 1 && e.epoch == 6)
    })
    .unwrap();
    let ran = last.iter().sum::<usize>();
    assert!(last[1] == 6 && ran < 24, "{last:?}");
    assert_eq!((stopped.resumed_from_epoch, stopped.model.header.training.epochs), (0, ran));
    assert_eq!(npe::checkpoint_epochs(&c.path), Some(ran));
    // Other settings (a seed) do not resume from it, and their checkpoints replace it.
    let other = TrainSettings { seed: 5, max_epochs: 2, ensemble: 1, ..s.clone() };
    let o = npe::train_checkpointed(&ds, &other, Some(&Checkpointing::new(dir.join("o.ckpt"), "b")), &mut |_| true);
    assert_eq!(o.unwrap().resumed_from_epoch, 0);
    std::fs::copy(&c.path, dir.join("o.ckpt")).unwrap();
    let o = npe::train_checkpointed(&ds, &other, Some(&Checkpointing::new(dir.join("o.ckpt"), "b")), &mut |_| true);
    assert_eq!(o.unwrap().resumed_from_epoch, 0, "a checkpoint of another seed was resumed from");
    assert_eq!(npe::checkpoint_epochs(&dir.join("o.ckpt")), Some(2));

    let resumed = npe::train_checkpointed(&ds, &s, Some(&c), &mut |e| {
        assert!(e.epoch > last[e.member], "epoch {} of member {} trained again", e.epoch, e.member);
        true
    })
    .unwrap();
    assert_eq!(resumed.resumed_from_epoch, ran);
    assert_eq!(resumed.model.header.members, 2);
    let x = [0.5, -0.3, 0.1];
    assert!(
        fingerprint(&resumed.model, &x) == fingerprint(&whole, &x),
        "the resumed model differs from the uninterrupted one"
    );
    assert_eq!(npe::remove_checkpoint(&c.path), 1);
    assert!(!c.path.exists());
    let _ = std::fs::remove_dir_all(&dir);
}

const ROWS: usize = 400;

/// A worker on `threads` threads.
fn spawn_worker(db: &Database, data: &Path, threads: usize) -> std::process::Child {
    let mut c = Command::new(env!("CARGO_BIN_EXE_otofit"));
    c.args(["worker", "--data-dir", data.to_str().unwrap(), "--lease-seconds", "2"]);
    c.args(["--threads", &threads.to_string()]);
    if let Database::Postgres(url) = db {
        c.args(["--database", url]);
    }
    c.stdout(Stdio::null()).stderr(Stdio::null()).spawn().unwrap()
}

/// The job table of a data directory on `backend`: SQLite in the directory (as `otofit
/// worker` opens it) or a fresh PostgreSQL database.
async fn database(backend: &str, data: &Path) -> Database {
    match backend {
        "postgres" => Database::Postgres(crate::pg::fresh_database().await.unwrap()),
        _ => Database::Sqlite(data.join("otofit.db")),
    }
}

/// A simulated dataset of `ROWS` rows (`otofit simulate`), in a folder of its own.
fn simulated() -> crate::pg::TempDir {
    let dataset = temp_dir("train-resume-ds");
    let out = Command::new(env!("CARGO_BIN_EXE_otofit"))
        .args(["simulate", "--n", &ROWS.to_string(), "--seed", "2", "--noise-scale", "1"])
        .args(["--out", dataset.to_str().unwrap()])
        .output()
        .unwrap();
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    dataset
}

/// A data directory with the dataset `ds` (simulated once, copied) and train job `t`.
async fn train_job(db: &Database, data: &Path, dataset: &Path, max_epochs: usize) -> Store {
    let ds = data.join("datasets/ds");
    std::fs::create_dir_all(&ds).unwrap();
    for f in ["theta.csv", "x.csv", "meta.json"] {
        std::fs::copy(dataset.join(f), ds.join(f)).unwrap();
    }
    let store = Store::connect(db).await.unwrap();
    let spec = JobSpec::parse("train", &json!({"dataset": "ds", "seed": 3, "max_epochs": max_epochs})).unwrap();
    assert!(store.insert_job_within("t", "train", &spec.params(), 3, 8).await.unwrap());
    store
}

/// A train job's worker process (two threads: its five flows train side by side) is
/// stopped (SIGSTOP) once the job has a checkpoint and killed (SIGKILL: no re-queue, no
/// clean-up); a new worker on one thread takes the job up (SQLite: at its start;
/// PostgreSQL: after the dead worker's lease) and resumes from the checkpoint. Its model
/// is the same (numbers and draws) as that of the same job run uninterrupted by another
/// one-thread worker beside it, and the checkpoint is gone at the end.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_killed_train_job_resumes_from_its_checkpoint_to_the_same_model() {
    let dataset = simulated();
    let x = Dataset::load(&dataset).unwrap().x.swap_remove(0);
    for (name, _) in crate::pg::backends().await {
        let (data, reference) = (temp_dir("train-resume"), temp_dir("train-resume-ref"));
        let (db, ref_db) = (database(&name, &data).await, database(&name, &reference).await);
        let store = train_job(&db, &data, &dataset, 60).await;
        let ref_store = train_job(&ref_db, &reference, &dataset, 60).await;
        let mut procs = Procs(vec![spawn_worker(&db, &data, 2), spawn_worker(&ref_db, &reference, 1)]);
        let ckpt = data.join("checkpoints/t.ckpt");
        wait_checkpoint(&ckpt, 3).await;
        // SAFETY: a signal to our own child.
        unsafe { libc::kill(procs.0[0].id() as i32, libc::SIGSTOP) };
        let at_kill = npe::checkpoint_epochs(&ckpt).expect("a checkpoint before the kill");
        procs.0[0].kill().unwrap();
        procs.0[0].wait().unwrap();
        let j = store.job("t").await.unwrap().unwrap();
        assert_eq!(j.state, "running", "{name}: the job ended before the kill: {:?}", j.result);
        procs.0.push(spawn_worker(&db, &data, 1));
        let (j, r) = (
            wait_state(&store, "t", &["succeeded", "failed", "cancelled"], 120).await,
            wait_state(&ref_store, "t", &["succeeded", "failed", "cancelled"], 120).await,
        );
        drop(procs);
        assert_eq!((j.state.as_str(), j.attempts), ("succeeded", 2), "{name}: {:?}", j.error);
        assert_eq!((r.state.as_str(), r.attempts), ("succeeded", 1), "{name}: {:?}", r.error);
        let (got, want) = (j.result.unwrap(), r.result.unwrap());
        eprintln!("{name}: resumed: {got}\nuninterrupted: {want}");
        let resumed = got["resumed_from_epoch"].as_u64().unwrap() as usize;
        assert!(resumed >= at_kill && resumed > 0, "{name}: resumed from epoch {resumed}, {at_kill} were checkpointed");
        assert_eq!(want["resumed_from_epoch"], 0);
        assert_eq!(got["epochs"], want["epochs"], "{name}: epochs in all");
        assert!(resumed < got["epochs"].as_u64().unwrap() as usize, "{name}: the kill came after the last epoch");
        assert_eq!(got["best_val_loss"], want["best_val_loss"], "{name}");
        let model = |d: &Path| fingerprint(&npe::Npe::load(&d.join("models/t.otofit")).unwrap(), &x);
        assert!(model(&data) == model(&reference), "{name}: the model differs from the uninterrupted run's");
        let left: Vec<_> =
            std::fs::read_dir(data.join("checkpoints")).unwrap().flatten().map(|e| e.file_name()).collect();
        assert!(left.is_empty(), "{name}: left behind: {left:?}");
    }
}

/// `otofit train --checkpoint FILE` resumes from a checkpoint of the same training (here
/// one stopped in process at epoch 4), ends with the uninterrupted model and removes FILE.
#[test]
fn otofit_train_resumes_from_its_checkpoint_file() {
    let dir = temp_dir("train-cli-ckpt");
    otofit::bench::write_table(otofit::bench::Task::GaussianMixture, 300, 1, &dir).unwrap();
    let ds = Dataset::load(&dir).unwrap();
    let s = TrainSettings { seed: 2, max_epochs: 10, ..Default::default() };
    let ckpt = dir.join("run.ckpt");
    npe::train_checkpointed(&ds, &s, Some(&Checkpointing::new(ckpt.clone(), "t")), &mut |e| e.epoch < 4).unwrap();
    assert_eq!(npe::checkpoint_epochs(&ckpt), Some(4));
    let (data, model, c) = (dir.to_str().unwrap(), dir.join("m.otofit"), ckpt.to_str().unwrap());
    let out = Command::new(env!("CARGO_BIN_EXE_otofit"))
        .args(["train", "--data", data, "--out", model.to_str().unwrap(), "--seed", "2", "--max-epochs", "10"])
        .args(["--ensemble", "1"])
        .args(["--checkpoint", c])
        .output()
        .unwrap();
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(out.status.success() && err.contains("resumed from epoch 4"), "{err}");
    assert!(!ckpt.exists(), "the checkpoint is left");
    // The uninterrupted model through a file as well: a header number read back from JSON
    // may differ from the one in memory in its last bit.
    let whole_file = dir.join("whole.otofit");
    npe::train(&ds, &s, &mut |_| true).unwrap().save(&whole_file).unwrap();
    let x = otofit::bench::observation(otofit::bench::Task::GaussianMixture, 1);
    let load = |p: &Path| fingerprint(&npe::Npe::load(p).unwrap(), &x);
    assert!(load(&model) == load(&whole_file), "the resumed model differs from the uninterrupted one");
    let _ = std::fs::remove_dir_all(&dir);
}

/// Until the checkpoint at `path` holds at least `epochs` epochs (60 s at most).
async fn wait_checkpoint(path: &Path, epochs: usize) {
    let t0 = Instant::now();
    while npe::checkpoint_epochs(path).unwrap_or(0) < epochs && t0.elapsed() < Duration::from_secs(60) {
        tokio::time::sleep(Duration::from_millis(5)).await;
    }
}

/// In one process: a shutdown re-queues a running train job and keeps its checkpoint
/// (written at the stop); the next dispatcher resumes from it; a cancel then ends the job
/// (cancelled, its best weights kept as its result) and removes the checkpoint.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_shut_down_train_job_keeps_its_checkpoint_and_a_cancelled_one_removes_it() {
    let (dataset, data) = (simulated(), temp_dir("train-stop"));
    let store = train_job(&database("sqlite", &data).await, &data, &dataset, 1000).await;
    let ckpt = data.join("checkpoints/t.ckpt");
    let first = crate::pg::ctx_on(store.clone(), &data, "w1", Duration::from_secs(30));
    tokio::spawn(otofit::jobs::dispatcher(first.clone()));
    wait_checkpoint(&ckpt, 2).await;
    first.shutdown.store(true, std::sync::atomic::Ordering::Relaxed);
    let j = wait_state(&store, "t", &["queued"], 30).await;
    assert_eq!(j.state, "queued", "{:?}", j.error);
    let kept = npe::checkpoint_epochs(&ckpt).expect("the checkpoint is kept for the next attempt");
    let second = crate::pg::ctx_on(store.clone(), &data, "w2", Duration::from_secs(30));
    tokio::spawn(otofit::jobs::dispatcher(second.clone()));
    wait_checkpoint(&ckpt, kept + 2).await;
    store.cancel("t").await.unwrap();
    let j = wait_state(&store, "t", &["succeeded", "failed", "cancelled"], 60).await;
    second.shutdown.store(true, std::sync::atomic::Ordering::Relaxed);
    assert_eq!(j.state, "cancelled", "{:?}", j.error);
    let result = j.result.expect("a cancelled training keeps its best weights as its result");
    assert_eq!(result["cancelled_early"], true, "{result}");
    let resumed = result["resumed_from_epoch"].as_u64().unwrap() as usize;
    assert!(resumed >= kept && resumed > 0, "resumed from {resumed}, {kept} kept: {result}");
    let left: Vec<_> = std::fs::read_dir(data.join("checkpoints")).unwrap().flatten().map(|e| e.file_name()).collect();
    assert!(left.is_empty(), "left behind: {left:?}");
}
