//! Posterior accuracy on standard SBI benchmark tasks: simulate a training table per
//! task, train through the generic table interface (theta.csv, x.csv, prior.json),
//! draw from the posterior for a few fixed observations and score the draws against
//! reference posterior draws with a classifier two-sample test (C2ST); and the cross-model
//! suite (`crossmodel`): ears from published middle-ear models otofit does not contain,
//! read by the shipped posterior and its fit check; and the shipped posterior against the
//! likelihood's own on held-out simulated ears (`posterior`); and how often the readings
//! find a simulated pathology and stay silent on a healthy ear (`readings`).

pub mod c2st;
pub mod crossmodel;
pub mod exact_fast;
pub mod glm;
pub mod mcmc;
pub mod posterior;
pub mod readings;
pub mod tasks;

// The layer below, under the names the modules use for it (`crate::npe::…`).
use otofit_npe::{dataset, npe, stats};

use crate::npe::{Dataset, Obs, TrainSettings};
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
    /// Where to write the trained flow's draws and its log q at the reference draws, in
    /// [`score_files`]' format (samples_K.csv, logq_K.csv), to score them elsewhere.
    pub save_samples: Option<std::path::PathBuf>,
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
    /// The lowest validation loss (mean −log q of θ z-scored on the training rows; mean
    /// over ensemble members), or `None` for scored files.
    pub best_val_loss: Option<f64>,
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
    writeln!(xs, "{}", numbered("x", task.features()))?;
    for _ in 0..n {
        let theta = task.prior(&mut rng);
        let x = task.simulate(&theta, &mut rng);
        writeln!(th, "{}", csv_row(&theta))?;
        writeln!(xs, "{}", csv_row(&x))?;
    }
    th.flush()?;
    xs.flush()?;
    std::fs::write(dir.join("prior.json"), serde_json::to_vec_pretty(&serde_json::json!({ "parameters": params }))?)?;
    Ok(())
}

/// sbi 0.27's NSF (`density_estimator="nsf"` with its defaults, read in sbi's
/// `build_nsf` and nflows) and its training (`train()`'s defaults) in otofit's settings: no
/// embedding (the z-scored x goes straight to the conditioners), conditioners of two
/// residual blocks gated by the context, an LU layer after each coupling, raw bin widths
/// and heights over √hidden, Adam's ε 1e-8, 5 couplings, 50 hidden, 10 bins, bound 3,
/// batch 200 at a constant rate 5e-4, early stopping with patience 20, a tenth for
/// validation, gradient norm clipped at 5 — except that sbi clips the whole gradient's
/// norm and burn each tensor's, and sbi alternates even/odd coupling masks where otofit
/// rotates its permutations. On the same simulations and split it reaches sbi's own
/// validation loss (docs/npe.md). The comparison for the default recipe.
pub fn sbi_nsf_settings() -> TrainSettings {
    TrainSettings {
        embedding: false,
        batch: 200,
        lr: 5e-4,
        patience: 20,
        max_epochs: 1000,
        lr_anneal: 0.0,
        ..TrainSettings::default()
    }
}

/// `otofit train`'s defaults as the benchmark runs them: the default recipe
/// ([`TrainSettings::default`]) with its flows from the table's size, without the
/// embedding network, which is for spectra (`otofit train --embedding none`).
pub fn default_settings() -> TrainSettings {
    TrainSettings { embedding: false, ensemble: 0, ..TrainSettings::default() }
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
    let s = score(task, p, &mut |k, x, reference| {
        let obs = Obs { x, present: None };
        let (draws, lq) = (model.sample(&obs, p.samples, k as u64)?, model.log_prob(&obs, reference)?);
        if let Some(out) = &p.save_samples {
            let out = out.join(task.name());
            std::fs::create_dir_all(&out)?;
            write_rows(&out.join(format!("samples_{k}.csv")), &numbered("theta", task.dim()), &draws)?;
            write_rows(&out.join(format!("logq_{k}.csv")), "logq", &lq.iter().map(|&v| vec![v]).collect::<Vec<_>>())?;
        }
        Ok((draws, Some(lq)))
    })?;
    let mut r = s.result(task, p.sims, t.wall_seconds, t.epochs, t.best_epoch);
    r.best_val_loss = Some(t.best_val_loss);
    Ok(r)
}

/// The reference draws of observation `k` (1-based) of `task`, as every scoring uses them.
fn reference(task: Task, x: &[f64], k: usize, n: usize) -> Vec<Vec<f64>> {
    task.reference(x, n, &mut ChaCha8Rng::seed_from_u64(7_000 + k as u64))
}

/// A posterior's scores at the task's observations.
struct Scores {
    c2st: Vec<f64>,
    kl: Option<f64>,
    box_mass: Option<f64>,
    width_ratio: f64,
    seconds: f64,
}

impl Scores {
    fn result(self, task: Task, sims: usize, train_seconds: f64, epochs: usize, best_epoch: usize) -> TaskResult {
        TaskResult {
            task: task.name().into(),
            sims,
            c2st_mean: self.c2st.iter().sum::<f64>() / self.c2st.len().max(1) as f64,
            c2st: self.c2st,
            train_seconds,
            epochs,
            best_epoch,
            best_val_loss: None,
            c2st_seconds: self.seconds,
            kl: self.kl,
            box_mass: self.box_mass,
            width_ratio: self.width_ratio,
        }
    }
}

/// What a posterior gives at observation `k` (1-based) with value `x`: its draws and,
/// where it has a density, its log q (unnormalised in the box) at the reference draws.
type Posterior<'a> = dyn FnMut(usize, &[f64], &[Vec<f64>]) -> Result<(Vec<Vec<f64>>, Option<Vec<f64>>)> + 'a;

/// Scores a posterior at the task's first `p.observations` observations: C2ST against the
/// reference draws, the marginal widths and, where both densities are known, KL(p ‖ q).
fn score(task: Task, p: &BenchParams, posterior: &mut Posterior<'_>) -> Result<Scores> {
    let (mut scores, mut kls, mut masses, mut ratios) = (vec![], vec![], vec![], vec![]);
    let t0 = std::time::Instant::now();
    for k in 1..=p.observations {
        let x = observation(task, k);
        let reference = reference(task, &x, k, p.samples);
        let (draws, lq) = posterior(k, &x, &reference)?;
        scores.push(c2st::c2st(&reference, &draws, &p.c2st));
        let lp: Option<Vec<f64>> = reference.iter().map(|t| task.log_posterior(&x, t)).collect();
        if let (Some(lp), Some(lq)) = (lp, lq) {
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
    Ok(Scores {
        c2st: scores,
        kl: (!kls.is_empty()).then(|| crate::stats::mean(kls)),
        box_mass: (!masses.is_empty()).then(|| crate::stats::mean(masses)),
        width_ratio: crate::stats::median_upper(&ratios),
        seconds: t0.elapsed().as_secs_f64(),
    })
}

/// Writes what another trainer needs to train on and be scored against exactly what
/// [`run_task`] uses, into `dir`: the training table (theta.csv, x.csv, prior.json), the
/// validation split `settings` would make (split.json: `val` and `train` row indices, and
/// θ's training-row mean and population standard deviation, the flow's standardisation),
/// the observations (obs.csv, one row each) and each observation's reference draws
/// (reference_K.csv, K from 1). Score the other trainer's draws with [`score_files`].
pub fn export_task(task: Task, p: &BenchParams, settings: &TrainSettings, dir: &Path) -> Result<()> {
    write_table(task, p.sims, p.seed, dir)?;
    let ds = Dataset::load(dir)?;
    let (val, train) = npe::validation_split(ds.theta.len(), settings.val_fraction, settings.seed);
    let (mean, std): (Vec<f64>, Vec<f64>) = (0..task.dim())
        .map(|j| crate::stats::mean_std_population(&train.iter().map(|&i| ds.theta[i][j]).collect::<Vec<_>>()))
        .unzip();
    let split = serde_json::json!({ "val": val, "train": train, "theta_mean": mean, "theta_std": std });
    std::fs::write(dir.join("split.json"), serde_json::to_vec(&split)?)?;
    let mut obs = vec![];
    for k in 1..=p.observations {
        let x = observation(task, k);
        write_rows(
            &dir.join(format!("reference_{k}.csv")),
            &numbered("theta", task.dim()),
            &reference(task, &x, k, p.samples),
        )?;
        obs.push(x);
    }
    write_rows(&dir.join("obs.csv"), &numbered("x", task.features()), &obs)
}

/// `prefix0,prefix1,…`: the column names of an unnamed table.
fn numbered(prefix: &str, n: usize) -> String {
    (0..n).map(|k| format!("{prefix}{k}")).collect::<Vec<_>>().join(",")
}

/// One CSV row of exact round-trip floats.
fn csv_row(v: &[f64]) -> String {
    v.iter().map(|a| format!("{a:e}")).collect::<Vec<_>>().join(",")
}

/// A CSV file: the header row, then the rows (exact round-trip floats).
fn write_rows(path: &Path, header: &str, rows: &[Vec<f64>]) -> Result<()> {
    let mut f = std::io::BufWriter::new(std::fs::File::create(path)?);
    writeln!(f, "{header}")?;
    for r in rows {
        writeln!(f, "{}", csv_row(r))?;
    }
    f.flush()?;
    Ok(())
}

/// Scores another trainer's posterior at the task's observations as [`run_task`] scores
/// otofit's: its draws from `dir`/samples_K.csv (K from 1; a header row, then one θ per
/// row) and, if present, its log q at the reference draws of [`export_task`] from
/// `dir`/logq_K.csv (a header row, then one value per row, in the reference's order;
/// unnormalised in the prior box: the KL corrects for the mass outside). No training:
/// the result's time and epochs are 0.
pub fn score_files(task: Task, p: &BenchParams, dir: &Path) -> Result<TaskResult> {
    let s = score(task, p, &mut |k, _, reference| {
        let draws = crate::dataset::read_csv(&dir.join(format!("samples_{k}.csv")))?.rows;
        if let Some(r) = draws.iter().find(|r| r.len() != task.dim()) {
            anyhow::bail!("samples_{k}.csv: a row of {} values, the task has {} parameters", r.len(), task.dim());
        }
        let path = dir.join(format!("logq_{k}.csv"));
        let lq = if path.exists() {
            let rows = crate::dataset::read_csv(&path)?.rows;
            if rows.len() != reference.len() || rows.iter().any(|r| r.len() != 1) {
                anyhow::bail!("logq_{k}.csv: expected {} rows of one value", reference.len());
            }
            Some(rows.into_iter().map(|r| r[0]).collect())
        } else {
            None
        };
        Ok((draws, lq))
    })?;
    Ok(s.result(task, p.sims, 0.0, 0, 0))
}

#[cfg(test)]
mod tests {
    use super::*;

    /// An exported task scored from files: exact posterior draws (another seed) with the
    /// exact log density score C2ST ≈ 0.5, KL 0 and width 1; the same draws shifted by half
    /// a posterior σ score clearly worse; the split is otofit's training split.
    #[test]
    fn exported_task_scores_exact_draws_from_files_as_exact() {
        let dir = tempfile::tempdir().unwrap();
        let task = Task::GaussianLinearUniform;
        let p = BenchParams {
            sims: 200,
            observations: 1,
            samples: 1500,
            seed: 3,
            verbose: false,
            c2st: c2st::C2stParams::default(),
            save_samples: None,
        };
        let settings = TrainSettings { seed: 3, ..Default::default() };
        export_task(task, &p, &settings, dir.path()).unwrap();
        let split: serde_json::Value =
            serde_json::from_slice(&std::fs::read(dir.path().join("split.json")).unwrap()).unwrap();
        let ids = |k: &str| -> Vec<usize> { serde_json::from_value(split[k].clone()).unwrap() };
        assert_eq!((ids("val"), ids("train")), npe::validation_split(200, settings.val_fraction, 3));
        assert_eq!(ids("val").len(), 20);
        let reference = crate::dataset::read_csv(&dir.path().join("reference_1.csv")).unwrap().rows;
        let x = observation(task, 1);
        assert_eq!(reference, super::reference(task, &x, 1, p.samples));
        let head = numbered("theta", 10);
        let exact = task.reference(&x, p.samples, &mut ChaCha8Rng::seed_from_u64(99));
        let shifted: Vec<Vec<f64>> =
            exact.iter().map(|t| t.iter().map(|v| v + 0.5 * 0.1f64.sqrt()).collect()).collect();
        let mut outcome = vec![];
        for draws in [&exact, &shifted] {
            write_rows(&dir.path().join("samples_1.csv"), &head, draws).unwrap();
            let lq: Vec<Vec<f64>> = reference.iter().map(|t| vec![task.log_posterior(&x, t).unwrap()]).collect();
            write_rows(&dir.path().join("logq_1.csv"), "logq", &lq).unwrap();
            outcome.push(score_files(task, &p, dir.path()).unwrap());
        }
        let (same, off) = (&outcome[0], &outcome[1]);
        assert!((same.c2st_mean - 0.5).abs() < 0.04, "exact draws: C2ST {}", same.c2st_mean);
        assert!(same.kl.unwrap().abs() < 1e-9 && (same.box_mass.unwrap() - 1.0).abs() < 1e-9);
        assert!((same.width_ratio - 1.0).abs() < 0.05, "width {}", same.width_ratio);
        assert!(off.c2st_mean > same.c2st_mean + 0.1, "shifted: C2ST {} against {}", off.c2st_mean, same.c2st_mean);
        std::fs::remove_file(dir.path().join("logq_1.csv")).unwrap();
        assert!(score_files(task, &p, dir.path()).unwrap().kl.is_none());
        write_rows(&dir.path().join("samples_1.csv"), "theta0", &[vec![0.1]]).unwrap();
        assert!(score_files(task, &p, dir.path()).is_err());
    }
}
