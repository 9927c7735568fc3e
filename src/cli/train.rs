//! `otofit train`: a dataset folder → a model file.

use crate::npe::{self, Dataset, TrainSettings};
use anyhow::{Context, Result, bail};
use clap::{Args, ValueEnum};
use std::path::PathBuf;

/// Arguments of `otofit train`.
#[derive(Args, Debug)]
pub struct TrainArgs {
    /// Folder with theta.csv, x.csv and meta.json (or prior.json).
    #[arg(long)]
    pub data: PathBuf,
    /// Model file to write.
    #[arg(long)]
    pub out: PathBuf,
    /// Summary network in front of the flow: mlp (learned features of x) or none (x as
    /// it is).
    #[arg(long, value_enum, default_value_t = Embedding::Mlp)]
    pub embedding: Embedding,
    /// Training noise: the dataset's noise model × K.
    #[arg(long, default_value_t = 1.0)]
    pub noise_scale: f64,
    /// Per-feature STD table (one row, header = feature names) replacing the dataset's
    /// noise model, e.g. reference/std.csv.
    #[arg(long)]
    pub noise_table: Option<PathBuf>,
    /// A smooth model error added beside the noise: its standard deviation in multiples
    /// of each feature's 1× noise (0: the simulator taken as exact). For ears the
    /// simulator does not make exactly, e.g. real ones (docs/results/crossmodel.md).
    #[arg(long, default_value_t = 0.0, value_name = "K")]
    pub model_error: f64,
    /// The model error's correlation length across frequency, octaves.
    #[arg(long, default_value_t = 1.0, value_name = "OCTAVES")]
    pub model_error_octaves: f64,
    /// Draw each row's model-error size uniformly from 0 to K (the flow can then stay
    /// sharp for ears the simulator reproduces).
    #[arg(long, requires = "model_error")]
    pub model_error_varying: bool,
    /// Hidden width of the flow's conditioners and embedding layers, 4..=512.
    #[arg(long, default_value_t = 50)]
    pub hidden: usize,
    /// Coupling transforms of the flow, 1..=16.
    #[arg(long, default_value_t = 5)]
    pub transforms: usize,
    /// Seed of the initial weights, the batches and the training noise.
    #[arg(long, default_value_t = 0)]
    pub seed: u64,
    /// Epochs at most, 1..=5000 (the default recipe ends sooner: --patience).
    #[arg(long, default_value_t = 1000)]
    pub max_epochs: usize,
    /// Epochs without a better validation loss before the rate is annealed to 0 over half
    /// the epochs so far, which ends the training (docs/design/npe.md, "One default recipe").
    #[arg(long, default_value_t = 10)]
    pub patience: usize,
    /// `default` (one recipe for every table: docs/design/npe.md, "One default recipe") or `v8`,
    /// the recipe the shipped v8 model was trained with (models/README.md).
    #[arg(long, value_enum, default_value = "default")]
    pub recipe: Recipe,
    /// Drop whole feature groups at random so one network answers any subset.
    #[arg(long)]
    pub mask_groups: bool,
    /// Also cut the ends of each group's band at random (up to a quarter of the grid) so
    /// one network answers sub-band measurements (with --mask-groups, or with --measures
    /// for a measure-set flow that takes its groups on part of the band).
    #[arg(long)]
    pub mask_bands: bool,
    /// With --mask-bands: cut at most this many grid points off each end (default a
    /// quarter of the grid). A flow for a device's band (from 226 Hz: 2 points) then
    /// spends no capacity on cuts it will never meet; attach it beside a wider one.
    #[arg(long, default_value_t = 0)]
    pub band_cut: usize,
    /// With --mask-bands: in half the rows every measure takes one shared cut (or none),
    /// as a device's export does (a wideband tympanometer's impedance and absorbance from
    /// 226 Hz together). Without it each measure is cut on its own, and an ear whose
    /// every measure starts at 226 Hz is a pattern training almost never shows.
    #[arg(long)]
    pub band_cut_together: bool,
    /// With --measures, without --mask-bands: train on those measures from this frequency
    /// up, as one device exports them (226: a wideband tympanometer's band), without the
    /// masks' other cuts. Attached beside the whole-band flow, it answers ears given
    /// exactly that band.
    #[arg(long, value_name = "HZ", default_value_t = 0.0)]
    pub from_hz: f64,
    /// Train on these feature groups alone (comma-separated, e.g.
    /// `stapes_velocity,impedance,absorbance`): a measure-set flow, sharper than the
    /// masked flow on ears that give exactly these; store it with `otofit attach
    /// --measure-set`. Not with --mask-groups.
    #[arg(long, value_delimiter = ',')]
    pub measures: Vec<String>,
    /// Train K flows (1..=16) from different seeds and store them as one equal-weight
    /// ensemble. Default: the default recipe trains 50,000 / training rows of them, 1 to 5
    /// (five on a 10,000-row table, one from about 28,000 rows on); `--recipe v8` one.
    #[arg(long)]
    pub ensemble: Option<usize>,
    /// Keep the training's state in FILE as it goes (at least every 30 s) and, if FILE
    /// holds a state of this same training (flags and data), resume from it: the model is
    /// the same as an uninterrupted run's. FILE is removed once the model is written.
    #[arg(long, value_name = "FILE")]
    pub checkpoint: Option<PathBuf>,
}

/// The training recipe (--recipe).
#[derive(Clone, Copy, Debug, ValueEnum)]
// Explained in the flag's help, as `Embedding`'s values are.
#[allow(missing_docs)]
pub enum Recipe {
    Default,
    V8,
}

/// The summary network in front of the flow (--embedding).
#[derive(Clone, Copy, Debug, ValueEnum)]
// The values are explained in the flag's help: a doc comment on a value would become clap's
// help for it and switch --help to the long layout.
#[allow(missing_docs)]
pub enum Embedding {
    Mlp,
    None,
}

/// Runs `otofit train`.
pub fn run(args: TrainArgs) -> Result<()> {
    if !(args.noise_scale.is_finite() && args.noise_scale >= 0.0) {
        bail!("--noise-scale must be a finite number ≥ 0, got {}", args.noise_scale);
    }
    // A train job's limits (jobs::limits): 1..=5000 epochs, 1..=16 flows.
    use crate::jobs::limits::{ENSEMBLE, EPOCHS, check};
    check(&EPOCHS, args.max_epochs).map_err(|m| anyhow::anyhow!("--max-epochs {m}"))?;
    if !(1..=1000).contains(&args.patience) {
        bail!("--patience must be between 1 and 1000 epochs, got {}", args.patience);
    }
    if let Some(k) = args.ensemble {
        check(&ENSEMBLE, k).map_err(|m| anyhow::anyhow!("--ensemble {m}"))?;
    }
    let mut ds = Dataset::load(&args.data)?;
    if let Some(p) = &args.noise_table {
        ds.noise_std = crate::dataset::read_noise_table(p, &ds.feature_names).context("--noise-table")?;
    }
    eprintln!(
        "{} rows ({} skipped), {} parameters, {} features",
        ds.theta.len(),
        ds.skipped,
        ds.params.len(),
        ds.feature_names.len()
    );
    let settings = TrainSettings {
        embedding: matches!(args.embedding, Embedding::Mlp),
        noise_scale: args.noise_scale,
        model_error: (args.model_error != 0.0).then_some(npe::ModelError {
            scale: args.model_error,
            octaves: args.model_error_octaves,
            varying: args.model_error_varying,
        }),
        seed: args.seed,
        hidden: args.hidden,
        transforms: args.transforms,
        max_epochs: args.max_epochs,
        patience: args.patience,
        mask_groups: args.mask_groups,
        mask_bands: args.mask_bands,
        band_cut: args.band_cut,
        band_cut_together: args.band_cut_together,
        from_hz: args.from_hz,
        measures: args.measures.iter().map(|m| m.trim().to_string()).collect(),
        ensemble: args.ensemble.unwrap_or(match args.recipe {
            Recipe::Default => 0,
            Recipe::V8 => 1,
        }),
        ..match args.recipe {
            Recipe::Default => TrainSettings::default(),
            Recipe::V8 => TrainSettings::v8(),
        }
    };
    let members = settings.members_for_table(ds.theta.len());
    if members > 1 && args.ensemble.is_none() {
        eprintln!("training {members} flows (the default for {} rows; --ensemble 1 for one)", ds.theta.len());
    }
    let checkpoint =
        args.checkpoint.as_ref().map(|path| npe::Checkpointing::new(path.clone(), &std::process::id().to_string()));
    // On a terminal a bar over every member's epoch budget (early stopping ends a
    // member sooner: the ETA is an upper bound) at the epochs done, summed over the
    // members (they may train side by side, their reports interleaved: each is one epoch
    // more, on top of a checkpoint's); otherwise a line per epoch.
    let budget = (args.max_epochs * members) as u64;
    let mut bar = super::progress::Progress::new("training", "epochs (at most)", budget);
    let mut done = checkpoint.as_ref().and_then(|c| npe::checkpoint_epochs(&c.path)).unwrap_or(0) as u64;
    let trained = npe::train_checkpointed(&ds, &settings, checkpoint.as_ref(), &mut |r| {
        let m = if members > 1 { format!("member {} ", r.member) } else { String::new() };
        let line = format!(
            "{m}epoch {:4}  train {:8.4}  val {:8.4}  best {:8.4}  ({:.2} s)",
            r.epoch, r.train_loss, r.val_loss, r.best_val_loss, r.seconds
        );
        if bar.is_bar() {
            bar.message(&format!("training: {}", line.trim()));
            done += 1;
            bar.set(done.min(budget));
        } else {
            eprintln!("{line}");
        }
        true
    })?;
    bar.finish();
    if trained.resumed_from_epoch > 0 {
        eprintln!("resumed from epoch {} (summed over members) of the checkpoint", trained.resumed_from_epoch);
    }
    let model = trained.model;
    model.save(&args.out)?;
    if let Some(c) = &checkpoint {
        npe::remove_checkpoint(&c.path);
    }
    let t = &model.header.training;
    eprintln!(
        "wrote {} (best epoch {} of {}, val loss {:.4}, {:.1} s)",
        args.out.display(),
        t.best_epoch,
        t.epochs,
        t.best_val_loss,
        t.wall_seconds
    );
    Ok(())
}
