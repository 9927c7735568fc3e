//! `otofit bench c2st`: posterior accuracy (C2ST against reference posteriors) and
//! training time on standard SBI benchmark tasks, trained with `otofit train`'s default
//! recipe (one for every task) or sbi 0.27's defaults (`--recipe sbi`).

use crate::bench::{self, BenchParams, Task, c2st::C2stParams};
use crate::npe::{ThetaMap, TrainSettings};
use anyhow::{Result, bail};
use clap::Args;
use std::path::PathBuf;

#[derive(Args, Debug)]
pub struct C2stArgs {
    /// Tasks, comma-separated (two_moons, gaussian_linear_uniform, slcp, gaussian_mixture,
    /// bernoulli_glm; and, to confirm a recipe on tasks it was not chosen on,
    /// gaussian_linear, slcp_distractors, bernoulli_glm_raw, with their sibling's recipe).
    #[arg(long, default_value = "two_moons,gaussian_linear_uniform,slcp,gaussian_mixture,bernoulli_glm")]
    pub tasks: String,
    /// Training simulations per task.
    #[arg(long, default_value_t = 10_000)]
    pub sims: usize,
    /// Fixed observations per task.
    #[arg(long, default_value_t = 3)]
    pub observations: usize,
    /// Posterior and reference draws per observation.
    #[arg(long, default_value_t = 10_000)]
    pub samples: usize,
    /// Seed of the simulations, the training and the classifier.
    #[arg(long, default_value_t = 0)]
    pub seed: u64,
    /// Cap on the classifier's epochs (lower: faster, less sensitive; for quick comparisons).
    #[arg(long, default_value_t = 500)]
    pub c2st_epochs: usize,
    /// Stop the classifier as the SBI benchmark does (training loss stalled, minutes per
    /// 10-D observation) instead of on held-out accuracy (seconds; less sensitive).
    #[arg(long)]
    pub c2st_train_loss_stop: bool,
    /// Print each observation's marginal means and spreads (reference and flow).
    #[arg(long)]
    pub verbose: bool,
    /// Results as JSON.
    #[arg(long, default_value = "c2st.json")]
    pub json: PathBuf,
    /// Training settings the options below change: `otofit` (`otofit train`'s default
    /// recipe without the embedding network, as `otofit train --embedding none` trains; the
    /// default) or `sbi` (sbi 0.27's NSF and training defaults: batch 200, rate 5e-4, early
    /// stopping after 20 epochs; docs/npe.md).
    #[arg(long, value_enum, default_value = "otofit")]
    pub recipe: RecipeArg,
    /// Train without the embedding network (`otofit train --embedding none`).
    #[arg(long)]
    pub no_embedding: bool,
    /// Training settings to compare (defaults: the recipe's).
    #[arg(long, value_enum)]
    pub theta_map: Option<ThetaMapArg>,
    /// Spline tail bound B (the flow is the identity outside [−B, B]).
    #[arg(long)]
    pub tail_bound: Option<f64>,
    /// Residual blocks per conditioner (0: plain MLP).
    #[arg(long)]
    pub blocks: Option<usize>,
    /// An LU linear layer after each coupling (as sbi's NSF): true or false.
    #[arg(long)]
    pub lu: Option<bool>,
    /// Training batch size.
    #[arg(long)]
    pub batch: Option<usize>,
    /// Initial learning rate.
    #[arg(long)]
    pub lr: Option<f64>,
    /// Halve the learning rate after this many epochs without improvement (0: constant).
    #[arg(long)]
    pub lr_plateau: Option<usize>,
    /// At the patience limit, divide the learning rate by 10 and go on, this many times.
    #[arg(long)]
    pub lr_drops: Option<usize>,
    /// Early-stopping epochs without improvement.
    #[arg(long)]
    pub patience: Option<usize>,
    /// Epochs at most.
    #[arg(long)]
    pub max_epochs: Option<usize>,
    /// Decay the learning rate by a half cosine to 0 at the last epoch: true or false.
    #[arg(long)]
    pub lr_cosine: Option<bool>,
    /// At the patience limit anneal instead of stopping: a half cosine to 0 over
    /// max(patience, this × epochs so far) epochs (0: stop).
    #[arg(long)]
    pub lr_anneal: Option<f64>,
    /// Share of the simulations held out for validation (early stopping).
    #[arg(long)]
    pub val_fraction: Option<f64>,
    /// Raw spline bin widths and heights divided by √hidden, as nflows does: true or false.
    #[arg(long)]
    pub scaled_bins: Option<bool>,
    /// Adam's ε.
    #[arg(long)]
    pub adam_eps: Option<f64>,
    /// Gradient clipping: each parameter tensor's gradient norm at most this (0: none).
    #[arg(long)]
    pub clip: Option<f64>,
    /// L2 penalty on the weights (through Adam's gradient).
    #[arg(long)]
    pub weight_decay: Option<f64>,
    /// Flows trained from different seeds, sampled as an equal-weight mixture (the
    /// default recipe: from the table's size, as `otofit train`).
    #[arg(long)]
    pub ensemble: Option<usize>,
    /// Hidden units of each conditioner layer (`otofit train --hidden`).
    #[arg(long)]
    pub hidden: Option<usize>,
    /// Coupling transforms of the flow (`otofit train --transforms`).
    #[arg(long)]
    pub transforms: Option<usize>,
    /// Train nothing: write each task's training table, validation split, observations and
    /// reference draws into DIR/<task>/ for another trainer (see `--score-samples`).
    #[arg(long, value_name = "DIR", conflicts_with = "score_samples")]
    pub export: Option<PathBuf>,
    /// Train nothing: score another trainer's posterior draws DIR/<task>/samples_K.csv
    /// (and, for the KL, its log q at the exported reference draws, logq_K.csv) with the
    /// same C2ST, widths and KL as otofit's.
    #[arg(long, value_name = "DIR")]
    pub score_samples: Option<PathBuf>,
    /// Also write each trained flow's draws and log q at the reference draws into
    /// DIR/<task>/ in `--score-samples`' format.
    #[arg(long, value_name = "DIR")]
    pub save_samples: Option<PathBuf>,
}

#[derive(Clone, Copy, Debug, clap::ValueEnum)]
pub enum RecipeArg {
    Sbi,
    Otofit,
}

#[derive(Clone, Copy, Debug, clap::ValueEnum)]
pub enum ThetaMapArg {
    Logit,
    Scale,
}

pub fn run(a: C2stArgs) -> Result<()> {
    let tasks: Vec<Task> = a
        .tasks
        .split(',')
        .map(|s| Task::from_name(s.trim()).ok_or_else(|| anyhow::anyhow!("unknown task '{s}'")))
        .collect::<Result<_>>()?;
    if a.sims < 100 || a.observations == 0 || a.samples < 100 {
        bail!("--sims and --samples must be at least 100, --observations at least 1");
    }
    let p = BenchParams {
        sims: a.sims,
        observations: a.observations,
        samples: a.samples,
        seed: a.seed,
        verbose: a.verbose,
        save_samples: a.save_samples.clone(),
        c2st: C2stParams {
            seed: a.seed,
            max_epochs: a.c2st_epochs,
            train_loss_stop: a.c2st_train_loss_stop,
            ..Default::default()
        },
    };
    let root = std::env::temp_dir().join(format!("otofit-c2st-{}", std::process::id()));
    let mut results = Vec::new();
    let mut used = Vec::new();
    if a.export.is_none() {
        println!("{:<24} {:>6} {:>7} {:>9}  per observation", "task", "sims", "C2ST", "train s");
    }
    for task in tasks {
        let settings = settings(&a);
        eprintln!("{settings:?}");
        if let Some(dir) = &a.export {
            let d = dir.join(task.name());
            bench::export_task(task, &p, &settings, &d)?;
            println!("{}: wrote {}", task.name(), d.display());
            continue;
        }
        let r = match &a.score_samples {
            Some(dir) => bench::score_files(task, &p, &dir.join(task.name()))?,
            None => bench::run_task(task, &p, &settings, &root.join(task.name()))?,
        };
        println!(
            "{:<24} {:>6} {:>7.3} {:>9.1}  {} (epochs {}, best {}{}; width ×{:.3}{}; C2ST {:.0} s)",
            r.task,
            r.sims,
            r.c2st_mean,
            r.train_seconds,
            r.c2st.iter().map(|c| format!("{c:.3}")).collect::<Vec<_>>().join(" "),
            r.epochs,
            r.best_epoch,
            r.best_val_loss.map(|v| format!(", val loss {v:.4}")).unwrap_or_default(),
            r.width_ratio,
            r.kl.zip(r.box_mass).map(|(k, m)| format!(", KL {k:.4}, mass in box {m:.3}")).unwrap_or_default(),
            r.c2st_seconds
        );
        results.push(r);
        used.push(format!("{}: {settings:?}", task.name()));
    }
    if a.export.is_some() {
        return Ok(());
    }
    let _ = std::fs::remove_dir_all(&root);
    let out = serde_json::json!({
        "sims": a.sims,
        "observations": a.observations,
        "samples": a.samples,
        "c2st_epochs": a.c2st_epochs,
        "c2st_train_loss_stop": a.c2st_train_loss_stop,
        "seed": a.seed,
        "recipe": format!("{:?}", a.recipe),
        "scored_samples": a.score_samples,
        "settings": used,
        "tasks": results,
    });
    std::fs::write(&a.json, serde_json::to_vec_pretty(&out)?)?;
    println!("wrote {}", a.json.display());
    Ok(())
}

/// The training settings: the recipe's, changed by the options given.
fn settings(a: &C2stArgs) -> TrainSettings {
    let d = match a.recipe {
        RecipeArg::Sbi => bench::sbi_nsf_settings(),
        RecipeArg::Otofit => bench::default_settings(),
    };
    TrainSettings {
        embedding: d.embedding && !a.no_embedding,
        seed: a.seed,
        theta_map: match a.theta_map {
            Some(ThetaMapArg::Logit) => ThetaMap::Logit,
            Some(ThetaMapArg::Scale) => ThetaMap::Scale,
            None => d.theta_map,
        },
        tail_bound: a.tail_bound.unwrap_or(d.tail_bound),
        blocks: a.blocks.unwrap_or(d.blocks),
        lu: a.lu.unwrap_or(d.lu),
        batch: a.batch.unwrap_or(d.batch),
        lr: a.lr.unwrap_or(d.lr),
        lr_plateau: a.lr_plateau.unwrap_or(d.lr_plateau),
        lr_drops: a.lr_drops.unwrap_or(d.lr_drops),
        patience: a.patience.unwrap_or(d.patience),
        max_epochs: a.max_epochs.unwrap_or(d.max_epochs),
        lr_cosine: a.lr_cosine.unwrap_or(d.lr_cosine),
        lr_anneal: a.lr_anneal.unwrap_or(d.lr_anneal),
        val_fraction: a.val_fraction.unwrap_or(d.val_fraction),
        scaled_bins: a.scaled_bins.unwrap_or(d.scaled_bins),
        adam_eps: a.adam_eps.unwrap_or(d.adam_eps),
        clip: a.clip.unwrap_or(d.clip),
        weight_decay: a.weight_decay.unwrap_or(d.weight_decay),
        ensemble: a.ensemble.unwrap_or(d.ensemble),
        hidden: a.hidden.unwrap_or(d.hidden),
        transforms: a.transforms.unwrap_or(d.transforms),
        ..d.clone()
    }
}
