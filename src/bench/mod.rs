//! Posterior accuracy on standard SBI benchmark tasks: simulate a training table per
//! task, train through the generic table interface (theta.csv, x.csv, prior.json),
//! draw from the posterior for a few fixed observations and score the draws against
//! reference posterior draws with a classifier two-sample test (C2ST).

pub mod c2st;
pub mod glm;
pub mod mcmc;
pub mod tasks;

use crate::npe::{self, Dataset, Obs, TrainSettings};
use anyhow::{Context, Result};
use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;
use serde::Serialize;
use std::io::Write;
use std::path::Path;
pub use tasks::Task;

/// How big a benchmark run is: simulations, observations and draws per task.
#[derive(Clone, Debug)]
pub struct BenchParams {
    /// Training simulations per task.
    pub sims: usize,
    /// Fixed observations per task (θ drawn from the prior with seeds 1, 2, …).
    pub observations: usize,
    /// Posterior and reference draws per observation.
    pub samples: usize,
    /// Seed of the training table's simulations.
    pub seed: u64,
    /// How the classifier two-sample test is run.
    pub c2st: c2st::C2stParams,
    /// Per-observation marginal means and spreads (reference and flow) on stderr.
    pub verbose: bool,
}

/// One task's outcome: C2ST accuracy and the training it took.
#[derive(Clone, Debug, Serialize)]
pub struct TaskResult {
    /// The task's name.
    pub task: String,
    /// Training simulations used.
    pub sims: usize,
    /// One C2ST accuracy per observation, and their mean.
    pub c2st: Vec<f64>,
    /// Mean of `c2st` (the task's score).
    pub c2st_mean: f64,
    /// Time spent training the flow.
    pub train_seconds: f64,
    /// Epochs run, summed over ensemble members.
    pub epochs: usize,
    /// The epoch of member 0's lowest validation loss (the weights kept).
    pub best_epoch: usize,
    /// Reference draws and classifier tests, all observations.
    pub c2st_seconds: f64,
    /// KL(p ‖ q) in nats, mean over the observations, where the task's posterior density
    /// is known ([`Task::log_posterior`]), estimated on the reference draws; q is the
    /// posterior as sampled: the flow's density restricted to the prior box.
    pub kl: Option<f64>,
    /// The flow's mass inside the prior box (the rest is rejected at sampling), mean over
    /// the observations, where `kl` is known.
    pub box_mass: Option<f64>,
    /// Median over observations and dimensions of the flow's marginal standard deviation
    /// over the reference's (1: right width; above 1: too wide).
    pub width_ratio: f64,
}

/// Writes a task's training table (theta.csv, x.csv, prior.json) into `dir`.
pub fn write_table(task: Task, n: usize, seed: u64, dir: &Path) -> Result<()> {
    std::fs::create_dir_all(dir).with_context(|| format!("cannot create {}", dir.display()))?;
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    let params = task.params();
    let mut th = std::io::BufWriter::new(std::fs::File::create(dir.join("theta.csv"))?);
    let mut xs = std::io::BufWriter::new(std::fs::File::create(dir.join("x.csv"))?);
    writeln!(th, "{}", params.iter().map(|p| p.name.as_str()).collect::<Vec<_>>().join(","))?;
    writeln!(xs, "{}", (0..task.features()).map(|k| format!("x{k}")).collect::<Vec<_>>().join(","))?;
    let join = |v: &[f64]| v.iter().map(|a| format!("{a:e}")).collect::<Vec<_>>().join(",");
    for _ in 0..n {
        let theta = task.prior(&mut rng);
        let x = task.simulate(&theta, &mut rng);
        writeln!(th, "{}", join(&theta))?;
        writeln!(xs, "{}", join(&x))?;
    }
    th.flush()?;
    xs.flush()?;
    std::fs::write(dir.join("prior.json"), serde_json::to_vec_pretty(&serde_json::json!({ "parameters": params }))?)?;
    Ok(())
}

/// The task's fixed observation `k` (1-based): x simulated at a prior draw of seed k.
pub fn observation(task: Task, k: usize) -> Vec<f64> {
    let mut rng = ChaCha8Rng::seed_from_u64(1_000 + k as u64);
    let theta = task.prior(&mut rng);
    task.simulate(&theta, &mut rng)
}

/// Trains on a fresh table of `p.sims` simulations in `dir` and scores the posterior
/// at the task's first `p.observations` observations.
pub fn run_task(task: Task, p: &BenchParams, settings: &TrainSettings, dir: &Path) -> Result<TaskResult> {
    write_table(task, p.sims, p.seed, dir)?;
    let ds = Dataset::load(dir)?;
    let model = npe::train(&ds, settings, &mut |r| {
        if p.verbose {
            eprintln!("{} epoch {} train {:.4} val {:.4}", task.name(), r.epoch, r.train_loss, r.val_loss);
        }
        true
    })?;
    let t = &model.header.training;
    let (mut scores, mut kls, mut masses, mut ratios) = (vec![], vec![], vec![], vec![]);
    let t0 = std::time::Instant::now();
    for k in 1..=p.observations {
        let x = observation(task, k);
        let mut rng = ChaCha8Rng::seed_from_u64(7_000 + k as u64);
        let reference = task.reference(&x, p.samples, &mut rng);
        let draws = model.sample(&Obs { x: &x, present: None }, p.samples, k as u64)?;
        scores.push(c2st::c2st(&reference, &draws, &p.c2st));
        let lq = model.log_prob(&Obs { x: &x, present: None }, &reference)?;
        let lp: Option<Vec<f64>> = reference.iter().map(|t| task.log_posterior(&x, t)).collect();
        if let Some(lp) = lp {
            // The sampled posterior is q restricted to the box, q / Z with Z = E_p[q / p]
            // (the box is p's support): KL(p ‖ q / Z) = E_p[log p − log q] + log Z.
            let diff: Vec<f64> = lp.iter().zip(&lq).map(|(a, b)| a - b).collect();
            let n = diff.len() as f64;
            let least = diff.iter().copied().fold(f64::INFINITY, f64::min);
            let log_z = (diff.iter().map(|d| (least - d).exp()).sum::<f64>() / n).ln() - least;
            kls.push(diff.iter().sum::<f64>() / n + log_z);
            masses.push(log_z.exp());
        }
        let ms =
            |v: &[Vec<f64>], k: usize| crate::stats::mean_std_population(&v.iter().map(|r| r[k]).collect::<Vec<_>>());
        for j in 0..task.dim() {
            let ((rm, rs), (dm, ds)) = (ms(&reference, j), ms(&draws, j));
            ratios.push(ds / rs);
            if p.verbose {
                eprintln!("{} obs {k}: θ{j} reference {rm:.3} ± {rs:.3}, flow {dm:.3} ± {ds:.3}", task.name());
            }
        }
    }
    ratios.sort_by(f64::total_cmp);
    Ok(TaskResult {
        task: task.name().into(),
        sims: p.sims,
        c2st_mean: scores.iter().sum::<f64>() / scores.len().max(1) as f64,
        c2st: scores,
        train_seconds: t.wall_seconds,
        epochs: t.epochs,
        best_epoch: t.best_epoch,
        c2st_seconds: t0.elapsed().as_secs_f64(),
        kl: (!kls.is_empty()).then(|| crate::stats::mean(kls)),
        box_mass: (!masses.is_empty()).then(|| crate::stats::mean(masses)),
        width_ratio: crate::stats::median_upper(&ratios),
    })
}
