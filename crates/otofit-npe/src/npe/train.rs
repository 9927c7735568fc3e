//! Maximum-likelihood training of the flow on (θ, x) pairs with per-batch noise
//! augmentation, optional group masking, early stopping on a validation split, and the
//! best-validation weights kept. Deterministic for a seed. With a checkpoint file
//! (`train_checkpointed`) the training saves its whole state as it goes and a new run of
//! the same training resumes from it, ending with the same weights as an uninterrupted run.

use super::adam::Adam;
use super::model_error::Discrepancy;
use super::{Dataset, FORMAT_VERSION, Header, ModelError, Npe, NpeError, Result, ThetaMap, TrainingSummary};
use crate::flow::gradient::{self, Weights};
use crate::flow::{Flow, FlowConfig};
use crate::stats;
use burn::module::Module;
use burn::prelude::*;
use burn::store::ModuleRecord;
use rand::seq::SliceRandom;
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use rand_distr::{Distribution, StandardNormal};
use serde::{Deserialize, Serialize};
use sha2::{Digest, Sha256};
use std::io::{Read, Write};
use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::time::{Duration, Instant};

mod side_by_side;

/// How to train (`otofit train`'s flags).
#[derive(Clone, Debug)]
pub struct TrainSettings {
    /// An embedding network before the flow's conditioners.
    pub embedding: bool,
    /// Training noise = the dataset's 1× noise model × this.
    pub noise_scale: f64,
    /// A smooth simulator-to-ear discrepancy added beside the noise (`None`: none).
    pub model_error: Option<ModelError>,
    /// Seed of the split, the batches, the noise and the weights.
    pub seed: u64,
    /// Epochs at most, per member.
    pub max_epochs: usize,
    /// Epochs without a better validation loss before stopping (or dropping the rate).
    pub patience: usize,
    /// Rows per batch (0: from the table, [`TrainSettings::batch_for`]).
    pub batch: usize,
    /// Adam's learning rate (0: from the batch, [`TrainSettings::lr_for`]).
    pub lr: f64,
    /// Drop whole feature groups at random (one model for any subset of modalities).
    pub mask_groups: bool,
    /// Also cut each kept group's band at random (up to a quarter of the grid at each end)
    /// and give the network per-feature presence flags: one model for sub-band inputs.
    pub mask_bands: bool,
    /// With `mask_bands`: the most grid points a cut takes off each end (0: a quarter of
    /// the grid). A flow cut less answers fewer bands and learns no cuts it will not
    /// meet: devices drop two or three points at the low end (from 226 or 250 Hz).
    pub band_cut: usize,
    /// With `mask_bands`: in half the rows every group takes the row's one cut (drawn as
    /// a group's would be, no cut among them); the other half cut each group on its own.
    /// A device exports every measure of one recording over the same band (a wideband
    /// tympanometer's impedance and absorbance always, its LDV often); cut on their own,
    /// three groups share a device's cut in one row of thousands.
    pub band_cut_together: bool,
    /// With `measures`, without `mask_bands`: train on those groups from this frequency
    /// up, every row (0: the whole band). A device's fixed band (from 226 Hz) is then all
    /// the flow learns, where a band-masked flow shares its capacity among every cut
    /// (for WBT with umbo LDV from 226 Hz no sharper: docs/results/posterior.md).
    pub from_hz: f64,
    /// Feature groups to train on alone (every other group's features zeroed): a
    /// measure-set flow for ears that give exactly these ([`super::Npe::answering`]).
    /// Empty: every group.
    pub measures: Vec<String>,
    /// Fraction of the rows held out for validation (0 < f < 1).
    pub val_fraction: f64,
    /// θ → the flow's space: logit of the box position, or the scale coordinate z-scored.
    pub theta_map: ThetaMap,
    /// The splines' tail bound B (identity outside [−B, B] in the standardised space).
    pub tail_bound: f64,
    /// Residual blocks per conditioner (0: a plain two-hidden-layer MLP).
    pub blocks: usize,
    /// An LU linear layer after each coupling (`FlowConfig::lu`).
    pub lu: bool,
    /// Raw bin widths and heights divided by √hidden (`FlowConfig::scaled_bins`).
    pub scaled_bins: bool,
    /// Adam's ε (burn's default 1e-5; PyTorch's, as in sbi, 1e-8).
    pub adam_eps: f64,
    /// Each parameter tensor's gradient clipped to this norm (0: no clipping).
    pub clip: f64,
    /// L2 penalty on the weights, through Adam's gradient (0: none).
    pub weight_decay: f64,
    /// Learning rate halved after this many epochs without a better validation loss
    /// (counted again from each halving); 0: constant.
    pub lr_plateau: usize,
    /// Instead of stopping after `patience` epochs without improvement, divide the
    /// learning rate by 10 and go on, this many times.
    pub lr_drops: usize,
    /// The rate also follows a half cosine from its value down to 0 at `max_epochs`.
    pub lr_cosine: bool,
    /// 0: stop at the patience limit. Above 0: at the limit, anneal instead — the rate
    /// follows a half cosine down to 0 over max(patience, this × the epochs so far)
    /// epochs (within `max_epochs`), and the training ends there. A long run at a
    /// constant rate finds the basin; the anneal settles into it, which the best epoch of
    /// a constant rate does not (the 2-D benchmark tasks: docs/results/npe.md).
    pub lr_anneal: f64,
    /// Flows trained from different seeds and averaged as an equal-weight mixture
    /// (wider, better-calibrated joint posteriors; K× the training time); 0: from the
    /// table's size ([`TrainSettings::members_for`]).
    pub ensemble: usize,
    /// Hidden width of the conditioners and of each embedding layer (the default 50).
    pub hidden: usize,
    /// Coupling transforms (the default 5).
    pub transforms: usize,
}

/// The default recipe, one for every table (docs/design/npe.md, "One default recipe"): sbi's
/// neural spline flow (two residual blocks per conditioner, LU layers, scaled bins, Adam
/// ε 1e-8), a batch of a tenth of the training rows (64 to 1000) at a rate proportional to
/// it, a constant rate until 10 epochs pass without a better validation loss, then a
/// half-cosine anneal over half the epochs so far. This library default trains one flow
/// (`ensemble: 1`), for the callers that want one for time (the diagnose workflow's
/// extension, the studies, the tests); what users run — `otofit train`, the train job and
/// `otofit bench c2st` — sets `ensemble` to 0, the rule that gives a small table several
/// flows ([`TrainSettings::members_for`]). Chosen on the two-moons, mixture, SLCP and
/// 10-D Gaussian tasks against fixed budgets and other patiences; the anneal adapts
/// the length to the table where a fixed budget cannot (the middle-ear tables need
/// hundreds of epochs, the 2-D tasks tens).
impl Default for TrainSettings {
    fn default() -> Self {
        TrainSettings {
            embedding: true,
            noise_scale: 1.0,
            model_error: None,
            seed: 0,
            max_epochs: 1000,
            patience: 10,
            batch: 0,
            lr: 0.0,
            mask_groups: false,
            mask_bands: false,
            band_cut: 0,
            band_cut_together: false,
            from_hz: 0.0,
            measures: Vec::new(),
            val_fraction: 0.1,
            theta_map: ThetaMap::Scale,
            tail_bound: 3.0,
            blocks: 2,
            lu: true,
            scaled_bins: true,
            adam_eps: 1e-8,
            clip: 5.0,
            weight_decay: 0.0,
            lr_plateau: 0,
            lr_drops: 0,
            lr_cosine: false,
            lr_anneal: 0.5,
            ensemble: 1,
            hidden: 50,
            transforms: 5,
        }
    }
}

impl TrainSettings {
    /// The batch for `train_rows` training rows: as set, or a tenth of them within 64..=1000
    /// (ten steps per epoch on small tables; on large ones the batch a CPU step handles
    /// well, measured in docs/results/npe.md).
    pub fn batch_for(&self, train_rows: usize) -> usize {
        if self.batch > 0 { self.batch } else { (train_rows / 10).clamp(64, 1000) }
    }

    /// The rate for a batch: as set, or 3e-3 per 1000 rows (the rate scaled with the batch,
    /// so the noise of a step stays the same).
    pub fn lr_for(&self, batch: usize) -> f64 {
        if self.lr > 0.0 { self.lr } else { 3e-3 * batch as f64 / 1000.0 }
    }

    /// The recipe the shipped v8 model was trained with (models/README.md), the default
    /// until the one-recipe change: plain two-layer conditioners, batch 200, rate 5e-4
    /// halved after 8 epochs without improvement, Adam ε 1e-5, early stopping (no anneal).
    pub fn v8() -> TrainSettings {
        TrainSettings {
            max_epochs: 300,
            patience: 20,
            batch: 200,
            lr: 5e-4,
            blocks: 0,
            lu: false,
            scaled_bins: false,
            adam_eps: 1e-5,
            lr_plateau: 8,
            lr_anneal: 0.0,
            ..TrainSettings::default()
        }
    }

    /// The flows trained for `train_rows` training rows: as set, or [`ENSEMBLE_ROWS`] /
    /// `train_rows` within 1..=[`ENSEMBLE_MAX`] (five flows on a 10,000-row table, one
    /// above 25,000 training rows). A flow from a small table varies from seed to seed by as
    /// much as it misses the posterior (the 2-D tasks: 0.005–0.01 of C2ST), and small
    /// tables train in seconds; the mixture of a few seeds averages that spread away
    /// (docs/results/npe.md, "Five flows on small tables").
    pub fn members_for(&self, train_rows: usize) -> usize {
        if self.ensemble > 0 { self.ensemble } else { (ENSEMBLE_ROWS / train_rows.max(1)).clamp(1, ENSEMBLE_MAX) }
    }

    /// [`TrainSettings::members_for`] a table of `rows` rows: the rows left once the
    /// validation rows are held out (a table too small to split holds none out).
    pub fn members_for_table(&self, rows: usize) -> usize {
        let held = if rows < 2 { 0 } else { validation_rows(rows, self.val_fraction) };
        self.members_for(rows - held)
    }

    /// These settings with the batch, the rate and the flows set for `train_rows`
    /// training rows.
    fn for_rows(&self, train_rows: usize) -> TrainSettings {
        let batch = self.batch_for(train_rows);
        TrainSettings { batch, lr: self.lr_for(batch), ensemble: self.members_for(train_rows), ..self.clone() }
    }
}

/// Training rows whose flow the default recipe trains once: a smaller table gets
/// `ENSEMBLE_ROWS / rows` flows ([`TrainSettings::members_for`]).
pub const ENSEMBLE_ROWS: usize = 50_000;

/// Most flows the default recipe trains for a small table.
pub const ENSEMBLE_MAX: usize = 5;

/// One epoch's numbers, passed to the progress callback.
#[derive(Clone, Debug)]
pub struct EpochReport {
    /// Ensemble member (0 for a single model).
    pub member: usize,
    /// Epoch within the member, from 1.
    pub epoch: usize,
    /// Mean training loss (negative log-likelihood) of the epoch.
    pub train_loss: f64,
    /// Validation loss after the epoch.
    pub val_loss: f64,
    /// Best validation loss of the member so far.
    pub best_val_loss: f64,
    /// Wall time of the epoch.
    pub seconds: f64,
}

/// Column `k` of `rows`: mean and population standard deviation.
fn mean_std(rows: &[Vec<f64>], k: usize) -> (f64, f64) {
    stats::mean_std_population(&rows.iter().map(|r| r[k]).collect::<Vec<_>>())
}

/// Refuses settings that do not suit the data or cannot train, naming the setting.
fn check(ds: &Dataset, s: &TrainSettings) -> Result<()> {
    let (n, f, n_freq) = (ds.theta.len(), ds.feature_names.len(), ds.frequencies_hz.len());
    if n < 20 {
        return Err(NpeError::table("the dataset", format!("{n} usable rows: too few to train (need at least 20)")));
    }
    if s.mask_groups && ds.groups.is_empty() {
        return Err(NpeError::settings("mask-groups", "--mask-groups needs feature groups (declared in meta.json)"));
    }
    if s.mask_bands && ((!s.mask_groups && s.measures.is_empty()) || n_freq < 8 || f % n_freq != 0) {
        return Err(NpeError::settings(
            "mask-bands",
            "--mask-bands needs --mask-groups or --measures, and a frequency grid (meta.json frequencies_hz) of at \
             least 8 points",
        ));
    }
    if s.band_cut_together && !s.mask_bands {
        return Err(NpeError::settings("band-cut-together", "--band-cut-together needs --mask-bands"));
    }
    if s.band_cut > 0 && !(s.mask_bands && s.band_cut <= n_freq / 4) {
        return Err(NpeError::settings(
            "band-cut",
            format!(
                "--band-cut {} needs --mask-bands and at most a quarter of the {n_freq}-point grid ({})",
                s.band_cut,
                n_freq / 4
            ),
        ));
    }
    if s.from_hz != 0.0 {
        let grid = &ds.frequencies_hz;
        let why = if s.measures.is_empty() || s.mask_bands {
            Some("--from-hz trains a measure-set flow (--measures) on one band: it goes without --mask-bands".into())
        } else if !(s.from_hz.is_finite() && s.from_hz > 0.0) || n_freq < 8 || f % n_freq != 0 {
            Some(format!("--from-hz {} needs a positive frequency and a grid of at least 8 points", s.from_hz))
        } else if s.from_hz <= grid[0] || s.from_hz > grid[n_freq * 3 / 4] {
            // Above the first point, or it is the whole band; a quarter of the grid kept.
            Some(format!(
                "--from-hz {} Hz must lie above the grid's first point ({:.0} Hz) and at most at {:.0} Hz (a \
                 quarter of the grid kept)",
                s.from_hz,
                grid[0],
                grid[n_freq * 3 / 4]
            ))
        } else {
            None
        };
        if let Some(why) = why {
            return Err(NpeError::settings("from-hz", why));
        }
    }
    if !s.measures.is_empty() {
        let why = if s.mask_groups {
            Some("--measures trains on those groups alone: it goes without --mask-groups".to_string())
        } else if let Some(m) = s.measures.iter().find(|m| !ds.groups.iter().any(|g| &&g.name == m)) {
            let names: Vec<&str> = ds.groups.iter().map(|g| g.name.as_str()).collect();
            Some(format!("--measures: '{m}' is not one of the dataset's feature groups ({})", names.join(", ")))
        } else if s.measures.iter().enumerate().any(|(k, m)| s.measures[..k].contains(m)) {
            Some("--measures: a group is named twice".into())
        } else if s.measures.len() >= ds.groups.len() {
            Some("--measures names every group: leave it out to train on every measure".into())
        } else {
            None
        };
        if let Some(why) = why {
            return Err(NpeError::settings("measures", why));
        }
    }
    if !(4..=512).contains(&s.hidden) {
        return Err(NpeError::settings("hidden", format!("--hidden must be 4..=512 (got {})", s.hidden)));
    }
    if !(1..=16).contains(&s.transforms) {
        return Err(NpeError::settings("transforms", format!("--transforms must be 1..=16 (got {})", s.transforms)));
    }
    if !(s.lr.is_finite() && s.lr >= 0.0) {
        return Err(NpeError::settings("lr", format!("--lr must be finite and ≥ 0 (0: from the batch; got {})", s.lr)));
    }
    if !(s.lr_anneal.is_finite() && (0.0..=10.0).contains(&s.lr_anneal)) {
        return Err(NpeError::settings("lr-anneal", format!("--lr-anneal must be in 0..=10 (got {})", s.lr_anneal)));
    }
    if !(s.val_fraction.is_finite() && s.val_fraction > 0.0 && s.val_fraction < 1.0) {
        return Err(NpeError::settings(
            "val-fraction",
            format!("the validation fraction must be in (0, 1) (got {})", s.val_fraction),
        ));
    }
    if !(s.noise_scale.is_finite() && s.noise_scale >= 0.0) {
        return Err(NpeError::settings(
            "noise-scale",
            format!("--noise-scale must be finite and ≥ 0 (got {})", s.noise_scale),
        ));
    }
    if ds.noise_std.len() != f
        || ds.x.iter().any(|r| r.len() != f)
        || ds.theta.iter().any(|t| t.len() != ds.params.len())
    {
        return Err(NpeError::table("the dataset", "rows, features and noise disagree in width"));
    }
    if let Some(me) = &s.model_error {
        me.sampler(&ds.frequencies_hz, &ds.noise_std)?;
    }
    Ok(())
}

/// θ rows in the flow's space before standardisation.
fn u_rows(ds: &Dataset, map: ThetaMap) -> Vec<Vec<f64>> {
    ds.theta
        .iter()
        .map(|t| {
            ds.params
                .iter()
                .zip(t)
                .map(|(p, v)| match map {
                    ThetaMap::Logit => p.to_u(*v),
                    ThetaMap::Scale => p.to_t(*v),
                })
                .collect()
        })
        .collect()
}

/// The header of the model to train: standardisation from the training rows (the x
/// spread includes the training noise), the flow's settings and the data's description.
fn standardise(ds: &Dataset, s: &TrainSettings, u_rows: &[Vec<f64>], train_idx: &[usize], n_val: usize) -> Header {
    let (d, f, n_freq) = (ds.params.len(), ds.feature_names.len(), ds.frequencies_hz.len());
    let train_u: Vec<Vec<f64>> = train_idx.iter().map(|&i| u_rows[i].clone()).collect();
    let train_x: Vec<Vec<f64>> = train_idx.iter().map(|&i| ds.x[i].clone()).collect();
    let (mut u_mean, mut u_std, mut x_mean, mut x_std) = (vec![], vec![], vec![], vec![]);
    for k in 0..d {
        let (m, sd) = mean_std(&train_u, k);
        u_mean.push(m);
        u_std.push(sd.max(1e-6));
    }
    for k in 0..f {
        let (m, sd) = mean_std(&train_x, k);
        x_mean.push(m);
        let me = s.model_error.map_or(0.0, |m| (m.scale * ds.noise_std[k]).powi(2) * m.variance_share());
        x_std.push((sd * sd + (s.noise_scale * ds.noise_std[k]).powi(2) + me).sqrt().max(1e-9));
    }
    let flags = if s.mask_groups { ds.groups.len() } else { 0 } + if s.mask_bands { f } else { 0 };
    let base = FlowConfig::new(d, f + flags, s.embedding);
    let cfg = FlowConfig {
        bound: s.tail_bound,
        blocks: s.blocks,
        lu: s.lu,
        scaled_bins: s.scaled_bins,
        hidden: s.hidden,
        transforms: s.transforms,
        permutations: crate::flow::permutations(d, s.transforms),
        embedding: base.embedding.iter().map(|_| s.hidden).collect(),
        ..base
    };
    Header {
        format_version: FORMAT_VERSION,
        otofit_version: env!("CARGO_PKG_VERSION").into(),
        params: ds.params.clone(),
        feature_names: ds.feature_names.clone(),
        frequencies_hz: ds.frequencies_hz.clone(),
        groups: ds.groups.clone(),
        mask_groups: s.mask_groups,
        mask_bands: s.mask_bands,
        band_cut_max: match (s.mask_bands, s.band_cut) {
            (false, _) => 0,
            (true, 0) => n_freq / 4,
            (true, k) => k,
        },
        x_mean,
        x_std,
        theta_map: s.theta_map,
        u_mean,
        u_std,
        noise_std: ds.noise_std.clone(),
        noise_scale: s.noise_scale,
        model_error: s.model_error,
        flow: cfg,
        training: TrainingSummary { seed: s.seed, train_rows: train_idx.len(), val_rows: n_val, ..Default::default() },
        members: 1,
        temperature: 1.0,
        fit_null: None,
        diagnose_null: None,
        full_measure_flow: false,
        measures: s.measures.clone(),
        measure_set_flows: 0,
        from_hz: s.from_hz,
    }
}

/// Builds batches: v (standardised u) and the network input with fresh noise and masks.
struct Batcher<'a> {
    ds: &'a Dataset,
    s: &'a TrainSettings,
    header: &'a Header,
    u_rows: &'a [Vec<f64>],
    /// The groups masked at random (none without `mask_groups`).
    groups: &'a [super::Group],
    /// The model-error sampler (none without `model_error`).
    discrepancy: Option<Discrepancy>,
    /// The features a measure-set flow reads (none: all).
    read: Option<Vec<bool>>,
}

impl Batcher<'_> {
    /// A batch's rows with their noise and masks drawn from the batch's `seed`.
    fn batch(&self, rows: &[usize], seed: u64) -> (Vec<f32>, Vec<f32>) {
        self.rows(rows, 0, seed)
    }

    /// Rows `rows` of a batch, the first of them the batch's row `first`: row k draws its
    /// noise and masks from stream k of the batch's `seed`, so any cut of a batch into
    /// chunks draws the same numbers, and the chunks can be drawn on different threads.
    fn rows(&self, rows: &[usize], first: usize, seed: u64) -> (Vec<f32>, Vec<f32>) {
        let (h, ds, s) = (self.header, self.ds, self.s);
        let (d, f, n_freq) = (h.params.len(), h.feature_names.len(), h.frequencies_hz.len());
        let band_cut_max = h.band_cut_max;
        let mut v = Vec::with_capacity(rows.len() * d);
        let mut inp = Vec::with_capacity(rows.len() * h.flow.inputs);
        // The noise's standard deviation per feature, and a row's standard normal draws.
        let noise: Vec<f64> = ds.noise_std.iter().map(|sd| s.noise_scale * sd).collect();
        let mut e = vec![0.0f64; f];
        for (pos, &i) in rows.iter().enumerate() {
            let rng = &mut ChaCha8Rng::seed_from_u64(seed);
            rng.set_stream((first + pos) as u64);
            v.extend((0..d).map(|k| ((self.u_rows[i][k] - h.u_mean[k]) / h.u_std[k]) as f32));
            // Each group kept with probability 1/2, at least one kept.
            let mut keep: Vec<bool> = self.groups.iter().map(|_| rng.random::<bool>()).collect();
            if !keep.is_empty() && !keep.iter().any(|&k| k) {
                let j = rng.random_range(0..keep.len());
                keep[j] = true;
            }
            let start = inp.len();
            // Drawn first, in the features' order, then applied in one pass that the
            // compiler vectorises (the draw runs beside Adam's step: `batch_step`).
            e.iter_mut().for_each(|e| *e = StandardNormal.sample(rng));
            let x = match &self.discrepancy {
                Some(d) => {
                    let mut x = ds.x[i].clone();
                    d.add(&mut x, rng);
                    std::borrow::Cow::Owned(x)
                }
                None => std::borrow::Cow::Borrowed(&ds.x[i]),
            };
            let row = x.iter().zip(&noise).zip(&e).zip(&h.x_mean).zip(&h.x_std);
            inp.extend(row.map(|((((x, sd), e), mean), std)| ((x + sd * e - mean) / std) as f32));
            let mut here = vec![true; f];
            // One cut for every group of the row, in half the rows (`band_cut_together`).
            let together = (s.mask_bands && s.band_cut_together && rng.random::<bool>())
                .then(|| band_cut(rng, n_freq, band_cut_max));
            for (g, &on) in self.groups.iter().zip(&keep) {
                // A kept group loses the ends of its band with probability 1/2.
                let (lo, hi) = if let (true, Some(cut)) = (on, together) {
                    cut
                } else if on && s.mask_bands && rng.random::<bool>() {
                    band_cut(rng, n_freq, band_cut_max)
                } else {
                    (0, n_freq.saturating_sub(1))
                };
                for &k in &g.features {
                    if !on || (s.mask_bands && !(lo..=hi).contains(&(k % n_freq))) {
                        inp[start + k] = 0.0;
                        here[k] = false;
                    }
                }
            }
            if let Some(read) = &self.read {
                // A band-masked measure-set flow: each of its groups loses the ends of its
                // band with probability 1/2, as a masked flow's kept groups do, or all of
                // them the row's one cut.
                if s.mask_bands {
                    for g in ds.groups.iter().filter(|g| h.measures.contains(&g.name)) {
                        let cut =
                            together.or_else(|| rng.random::<bool>().then(|| band_cut(rng, n_freq, band_cut_max)));
                        if let Some((lo, hi)) = cut {
                            for &k in g.features.iter().filter(|&&k| !(lo..=hi).contains(&(k % n_freq))) {
                                inp[start + k] = 0.0;
                                here[k] = false;
                            }
                        }
                    }
                }
                for (k, _) in read.iter().enumerate().filter(|(_, r)| !**r) {
                    inp[start + k] = 0.0;
                    here[k] = false;
                }
            }
            inp.extend(keep.iter().map(|&on| if on { 1.0 } else { 0.0 }));
            if s.mask_bands {
                inp.extend(here.iter().map(|&on| if on { 1.0f32 } else { 0.0 }));
            }
        }
        (v, inp)
    }
}

/// The grid indices a cut band keeps: up to `band_cut_max` points off each end.
fn band_cut(rng: &mut ChaCha8Rng, n_freq: usize, band_cut_max: usize) -> (usize, usize) {
    let lo = rng.random_range(0..=band_cut_max);
    (lo, n_freq - 1 - rng.random_range(0..=band_cut_max))
}

/// Mean negative log-likelihood of one batch, through burn (the tests hold the host's to it).
#[cfg(test)]
fn loss_of(flow: &Flow, cfg: &FlowConfig, v: Vec<f32>, inp: Vec<f32>, b: usize, dev: &Device) -> Tensor<1> {
    let vt = Tensor::<2>::from_data(TensorData::new(v, [b, cfg.dim]), dev);
    let it = Tensor::<2>::from_data(TensorData::new(inp, [b, cfg.inputs]), dev);
    let ctx = flow.embed(it);
    flow.log_prob(cfg, vt, ctx).mean().neg()
}

/// Rows of a batch (or of a part of one): standardised θ, the network's input, the count.
type Rows = (Vec<f32>, Vec<f32>, usize);

/// A mean loss and its gradient.
type Gradient = (f64, gradient::Gradient);

/// One part's mean loss and gradient at `weights` ([`gradient::loss_and_gradient`]);
/// `None` if the loss is not finite.
fn part_gradient(weights: &Weights, (v, inp, b): Rows) -> Option<Gradient> {
    let (l, g) = gradient::loss_and_gradient(weights, &v, &inp, b);
    l.is_finite().then_some((l, g))
}

/// A batch's mean loss and gradient at `weights` (`None` if a part's loss is not finite).
///
/// A batch of [`SPLIT_ROWS`] or more rows is cut into [`parts`] contiguous parts whose
/// gradients are added weighted by their rows, in the parts' order: the batch's gradient
/// up to rounding. Without `helpers` (one thread) the parts run one after the other; with
/// them, the first part runs on the calling thread and part j + 1 on helper j, all at
/// once, reading the same weights; with `draw_next` (batch i, its rows), the helpers then
/// draw that batch of the epoch in chunks, beside the calling thread's adding and Adam's
/// step. One and two threads split alike, so they give the same numbers.
fn batch_gradient(
    weights: &Arc<Weights>,
    cfg: &FlowConfig,
    (v, inp, b): Rows,
    threads: usize,
    helpers: Option<(&Helpers, Option<(usize, usize)>)>,
) -> Option<Gradient> {
    let k = parts(b, threads);
    // Part i holds rows i·b/k .. (i+1)·b/k; split off from the end, the first stays.
    let bounds: Vec<usize> = (0..=k).map(|i| i * b / k).collect();
    let (mut v, mut inp) = (v, inp);
    let mut rest: Vec<Rows> = (1..k)
        .rev()
        .map(|i| (v.split_off(bounds[i] * cfg.dim), inp.split_off(bounds[i] * cfg.inputs), bounds[i + 1] - bounds[i]))
        .collect();
    rest.reverse();
    let first = (v, inp, bounds[1]);
    let results: Vec<Option<Gradient>> = match helpers {
        None => std::iter::once(first).chain(rest).map(|p| part_gradient(weights, p)).collect(),
        Some((h, draw_next)) => {
            assert!(rest.len() <= h.jobs.len(), "a helper for each part after the first");
            let others = rest.len();
            for (j, part) in rest.into_iter().enumerate() {
                h.send(j, Job::Part(j, weights.clone(), part));
            }
            if let Some((i, rows)) = draw_next {
                h.draw(i, rows);
            }
            let mut results = vec![part_gradient(weights, first)];
            results.resize_with(k, || None);
            for (j, got) in h.grads.iter().take(others) {
                results[j + 1] = got;
            }
            results
        }
    };
    let (losses, grads): (Vec<f64>, Vec<gradient::Gradient>) = results.into_iter().collect::<Option<_>>()?;
    let shares: Vec<f64> = bounds.windows(2).map(|w| (w[1] - w[0]) as f64 / b as f64).collect();
    let loss = losses.iter().zip(&shares).fold(0.0, |acc, (l, w)| acc + w * l);
    let shares: Vec<f32> = shares.iter().map(|&w| w as f32).collect();
    Some((loss, gradient::Gradient::weighted_sum(&grads, &shares)))
}

/// Work for a helper thread ([`Helpers`]).
enum Job {
    /// Part j + 1 of the batch under way, at these weights.
    Part(usize, Arc<Weights>, Rows),
    /// Draw chunk c, rows `lo..hi`, of the epoch's batch i.
    Draw(usize, usize, (usize, usize)),
}

/// Draws rows `lo..hi` of the epoch's batch i (`Batcher::rows`).
type Draw<'a> = dyn Fn(usize, usize, usize) -> Rows + Sync + 'a;

/// Threads beside the calling thread for one epoch of a training on more than one thread,
/// so that no thread is started per batch: helper j takes part j + 1 of each split batch,
/// then chunk j of the next batch's draw. They end when this is dropped (their scope joins
/// them).
struct Helpers {
    jobs: Vec<std::sync::mpsc::Sender<Job>>,
    /// Parts' gradients as they finish: (j, gradient of part j + 1).
    grads: std::sync::mpsc::Receiver<(usize, Option<Gradient>)>,
    /// Chunks of the next batch as they are drawn: (c, rows), `None` from a draw that
    /// panicked.
    drawn: std::sync::mpsc::Receiver<(usize, Option<Rows>)>,
}

impl Helpers {
    /// `n` helpers in scope `s`, drawing with `draw`.
    fn start<'scope>(s: &'scope std::thread::Scope<'scope, '_>, n: usize, draw: &'scope Draw<'scope>) -> Helpers {
        use std::sync::mpsc::channel;
        let (grads_tx, grads) = channel();
        let (drawn_tx, drawn) = channel();
        let jobs = (0..n)
            .map(|_| {
                let (tx, rx) = channel::<Job>();
                let (grads_tx, drawn_tx) = (grads_tx.clone(), drawn_tx.clone());
                s.spawn(move || {
                    for job in rx {
                        // A send fails only once the calling thread has stopped listening.
                        match job {
                            Job::Part(j, weights, part) => {
                                // A part that panics counts as a bad batch (skipped), as its
                                // loss would.
                                let got = std::panic::catch_unwind(std::panic::AssertUnwindSafe(|| {
                                    part_gradient(&weights, part)
                                }));
                                // Let go of the weights first: the calling thread steps them
                                // in place once every part is in.
                                drop(weights);
                                let _ = grads_tx.send((j, got.ok().flatten()));
                            }
                            Job::Draw(i, c, (lo, hi)) => {
                                // A draw that panics is reported, then passed on to the scope:
                                // the calling thread stops waiting for the batch.
                                let got = std::panic::catch_unwind(std::panic::AssertUnwindSafe(|| draw(i, lo, hi)));
                                match got {
                                    Ok(rows) => {
                                        let _ = drawn_tx.send((c, Some(rows)));
                                    }
                                    Err(panic) => {
                                        let _ = drawn_tx.send((c, None));
                                        std::panic::resume_unwind(panic);
                                    }
                                }
                            }
                        }
                    }
                });
                tx
            })
            .collect();
        Helpers { jobs, grads, drawn }
    }

    /// Asks every helper for a chunk of batch i, of `rows` rows.
    fn draw(&self, i: usize, rows: usize) {
        let n = self.jobs.len();
        for c in 0..n {
            self.send(c, Job::Draw(i, c, (c * rows / n, (c + 1) * rows / n)));
        }
    }

    /// The batch asked for with [`Helpers::draw`], its chunks joined in order; `None` if a
    /// draw panicked.
    fn drawn(&self) -> Option<Rows> {
        let mut chunks: Vec<Option<Rows>> = vec![None; self.jobs.len()];
        for _ in 0..chunks.len() {
            let (c, rows) = self.drawn.recv().ok()?;
            chunks[c] = Some(rows?);
        }
        let mut batch: Rows = (vec![], vec![], 0);
        for (v, inp, n) in chunks.into_iter().flatten() {
            batch.0.extend(v);
            batch.1.extend(inp);
            batch.2 += n;
        }
        Some(batch)
    }

    /// Hands helper `j` a job; one that has stopped (it panicked) is reported when its
    /// scope joins it.
    fn send(&self, j: usize, job: Job) {
        let _ = self.jobs[j].send(job);
    }
}

/// Batches of this many rows or more are split over threads ([`batch_step`]).
pub const SPLIT_ROWS: usize = 128;

/// The fewest rows of a part of a split batch: smaller parts cost more in hand-overs
/// between threads and in small matrix products than their gradients save.
pub const MIN_PART_ROWS: usize = 64;

/// The most parts a batch is split into, whatever the cores. The parts' gradients are
/// taken on the host and share nothing but the weights, so this is the sixteen cores the
/// split was measured on (docs/results/scaling.md); beyond them a part's rows get too
/// few for its matrix products.
pub const MAX_PARTS: usize = 16;

/// Rows per piece of the validation pass (a fixed size, so that the sum does not depend
/// on the threads).
const VALIDATION_PIECE: usize = 125;

/// How many parts a batch of `b` rows is split into on `threads` threads: one below
/// [`SPLIT_ROWS`]; else as many as the threads up to [`MAX_PARTS`], at least two and no
/// more than parts of [`MIN_PART_ROWS`]. One and two threads split alike (two parts,
/// the second after the first on one thread), so a seed trains the same weights with
/// either; more threads split finer, which changes the rounding of the summed gradient,
/// so a seed's weights are the same for a given thread count above two (and for every
/// count from [`MAX_PARTS`] up).
pub fn parts(b: usize, threads: usize) -> usize {
    if b < SPLIT_ROWS { 1 } else { threads.min(MAX_PARTS).clamp(2, (b / MIN_PART_ROWS).max(2)) }
}

/// A one-element loss tensor as f64 (NaN when it cannot be read).
#[cfg(test)]
fn scalar(loss: Tensor<1>) -> f64 {
    loss.try_into_vec_as::<f32>().map(|v| v[0] as f64).unwrap_or(f64::NAN)
}

/// One member's training under way: everything a checkpoint keeps to go on from it.
struct MemberRun {
    member: usize,
    flow: Flow,
    opt: Adam,
    /// Drives the batch order and the training noise.
    rng: ChaCha8Rng,
    /// The training rows as the last epoch left them (each epoch shuffles them further).
    order: Vec<usize>,
    /// Epochs done.
    epoch: usize,
    lr: f64,
    /// Epoch of the last halving or drop (plateaus are counted from it).
    last_change: usize,
    /// Epoch of the last drop by 10 (patience is counted from it).
    last_drop: usize,
    /// Drops by 10 so far.
    drops: usize,
    /// The anneal once begun: the epoch before its first, and its length.
    anneal: Option<(usize, usize)>,
    best_val_loss: f64,
    best_epoch: usize,
    /// The best weights (without autodiff), once an epoch gave a finite validation loss.
    record: Option<ModuleRecord>,
}

/// How a member's epochs ended.
struct MemberEnd {
    /// It stopped improving or ran out of epochs.
    done: bool,
    /// The progress callback asked to stop.
    stopped: bool,
}

/// A member that ended (or was stopped): what the model keeps of it.
struct Ended {
    member: usize,
    epoch: usize,
    best_epoch: usize,
    best_val_loss: f64,
    /// The best weights; none if no epoch gave a finite validation loss.
    record: Option<ModuleRecord>,
}

impl MemberRun {
    fn ended(self) -> Ended {
        let MemberRun { member, epoch, best_epoch, best_val_loss, record, .. } = self;
        Ended { member, epoch, best_epoch, best_val_loss, record }
    }
}

/// Where a training goes on from (a checkpoint's state, or nothing).
#[derive(Default)]
struct Start {
    /// The members the model has, in order.
    fin: Finished,
    /// Members that ended while one before them was still under way.
    ended: Vec<Ended>,
    /// Members under way.
    under_way: Vec<MemberRun>,
}

impl Start {
    /// Epochs done, summed over the members.
    fn epochs(&self) -> usize {
        let (ended, under_way) = (self.ended.iter().map(|m| m.epoch), self.under_way.iter().map(|m| m.epoch));
        self.fin.epochs + ended.sum::<usize>() + under_way.sum::<usize>()
    }
}

/// The members trained to the end: their best weights and the summary's sums.
#[derive(Default)]
struct Finished {
    records: Vec<ModuleRecord>,
    /// Epochs, summed over the members.
    epochs: usize,
    /// Member 0's best epoch.
    best_epoch: usize,
    /// Sum of the members' best validation losses.
    best_sum: f64,
}

impl Finished {
    /// Adds a member that ended, the next in order, with its best weights.
    fn add(&mut self, m: Ended) -> Result<()> {
        self.epochs += m.epoch;
        let Some(record) = m.record else { return Err(NpeError::NoFiniteLoss { member: m.member }) };
        self.records.push(record);
        if m.member == 0 {
            self.best_epoch = m.best_epoch;
        }
        self.best_sum += m.best_val_loss;
        Ok(())
    }
}

/// Adam with the clipping every member trains with.
fn optimizer(s: &TrainSettings) -> Adam {
    Adam::new(
        s.adam_eps as f32,
        (s.clip > 0.0).then_some(s.clip as f32),
        (s.weight_decay > 0.0).then_some(s.weight_decay as f32),
    )
}

/// A new flow; with `seed`, its weights drawn from that seed. The backend's RNG is
/// process-wide: seeding and drawing under one lock keeps a seed's weights the same when
/// other trainings run beside this one (a flow whose weights are loaded afterwards takes
/// the lock too). burn draws a parameter lazily, at its first use, so every weight is
/// drawn here, under the lock; otherwise the draws happened in the first training step,
/// after another thread may have re-seeded the RNG or drawn from it.
fn new_flow(cfg: &FlowConfig, device: &Device, seed: Option<u64>) -> Flow {
    Flow::seeded(cfg, device, seed)
}

/// Everything a member's training reads.
struct Run<'a> {
    s: &'a TrainSettings,
    cfg: &'a FlowConfig,
    batcher: Batcher<'a>,
    train_idx: &'a [usize],
    /// Validation inputs with one fixed noise draw: (v, input, rows).
    val_batches: Vec<Rows>,
    n_val: usize,
    /// The device of the member's burn flow, which holds the weights between epochs (for
    /// the best weights and checkpoints); the epochs themselves train on the host.
    device: Device,
}

impl Run<'_> {
    /// One pass over the training rows: the flow with its new weights, the same weights
    /// on the host, and the mean loss of the finite batches.
    fn epoch(
        &self,
        flow: Flow,
        opt: &mut Adam,
        lr: f64,
        order: &mut [usize],
        rng: &mut ChaCha8Rng,
    ) -> (Flow, Weights, f64) {
        order.shuffle(rng);
        let threads = rayon::current_num_threads();
        let batches: Vec<&[usize]> = order.chunks(self.s.batch).collect();
        // One seed per batch, drawn in order: a batch's rows are the same however many
        // threads draw it (`Batcher::rows`).
        let seeds: Vec<u64> = batches.iter().map(|_| rng.random()).collect();
        let draw = |i: usize, lo: usize, hi: usize| {
            let (v, inp) = self.batcher.rows(&batches[i][lo..hi], lo, seeds[i]);
            (v, inp, hi - lo)
        };
        let (mut sum, mut count) = (0.0, 0);
        // The weights stay on the host for the epoch; the parts read them, Adam steps them.
        let mut weights = Arc::new(Weights::of(&flow, self.cfg));
        let mut step = |weights: &mut Arc<Weights>, got: Option<Gradient>, rows: usize| {
            // A rare bad batch is skipped rather than poison the weights.
            if let Some((l, g)) = got {
                sum += l * rows as f64;
                count += rows;
                opt.step(lr, Arc::make_mut(weights), g);
            }
        };
        let cfg = self.cfg;
        if threads == 1 {
            for (i, rows) in batches.iter().enumerate() {
                let batch = draw(i, 0, rows.len());
                let rows = batch.2;
                let got = batch_gradient(&weights, cfg, batch, threads, None);
                step(&mut weights, got, rows);
            }
        } else if let Some(first) = batches.first().map(|b| draw(0, 0, b.len())) {
            // Batch i + 1 is drawn while batch i's gradients are added and Adam steps.
            std::thread::scope(|s| {
                let n = (parts(self.s.batch, threads) - 1).max(1);
                let helpers = Helpers::start(s, n, &draw);
                let mut batch = first;
                for i in 1..=batches.len() {
                    let rows = batch.2;
                    let next = (i < batches.len()).then(|| (i, batches[i].len()));
                    let got = batch_gradient(&weights, cfg, batch, threads, Some((&helpers, next)));
                    step(&mut weights, got, rows);
                    // None after the last batch, or if a draw panicked (the scope then
                    // passes its panic on).
                    let Some(Some(drawn)) = next.map(|_| helpers.drawn()) else { break };
                    batch = drawn;
                }
            });
        }
        let weights = Arc::try_unwrap(weights).unwrap_or_else(|shared| (*shared).clone());
        (weights.to_flow(flow), weights, sum / count.max(1) as f64)
    }

    /// Validation loss (mean −log q over the validation rows) of `weights`, on the host.
    /// The rows are cut into pieces of [`VALIDATION_PIECE`] (a fixed size: on many cores
    /// the few 1000-row batches left threads idle while the epoch waited), taken on the
    /// thread pool, and their rows' losses added in the rows' order: the same bits for
    /// any number of threads.
    fn validate(&self, weights: &Weights) -> f64 {
        use rayon::prelude::*;
        let (d, k) = (self.cfg.dim, self.cfg.inputs);
        let pieces: Vec<(&Rows, usize)> =
            self.val_batches.iter().flat_map(|b| (0..b.2).step_by(VALIDATION_PIECE).map(move |lo| (b, lo))).collect();
        let losses: Vec<Vec<f64>> = pieces
            .par_iter()
            .map(|&((v, inp, b), lo)| {
                let hi = (lo + VALIDATION_PIECE).min(*b);
                gradient::row_losses(weights, &v[lo * d..hi * d], &inp[lo * k..hi * k], hi - lo)
            })
            .collect();
        losses.iter().flatten().fold(0.0, |sum, l| sum + l) / self.n_val as f64
    }

    /// Ensemble member `member` before its first epoch: weights from its own seed, batches
    /// from `rng`.
    fn fresh(&self, member: usize, rng: ChaCha8Rng) -> MemberRun {
        let flow = new_flow(self.cfg, &self.device, Some(self.s.seed.wrapping_add(member as u64)));
        MemberRun {
            member,
            flow,
            opt: optimizer(self.s),
            rng,
            order: self.train_idx.to_vec(),
            epoch: 0,
            lr: self.s.lr,
            last_change: 0,
            last_drop: 0,
            drops: 0,
            anneal: None,
            best_val_loss: f64::INFINITY,
            best_epoch: 0,
            record: None,
        }
    }

    /// Trains a member on from where it is, keeping its best weights; the rate is halved on
    /// plateaus and divided by 10 instead of stopping `lr_drops` times. After each epoch
    /// that does not end the member, `save` is offered its state (`true`: the training
    /// stops here, save it whatever the time).
    /// Each epoch runs on the `lane`'s threads ([`side_by_side::Lane`]).
    fn member(
        &self,
        mut m: MemberRun,
        lane: &side_by_side::Lane,
        progress: &mut dyn FnMut(&EpochReport) -> bool,
        save: &mut dyn FnMut(&MemberRun, bool),
    ) -> (MemberRun, MemberEnd) {
        let s = self.s;
        let mut end = MemberEnd { done: m.epoch >= s.max_epochs, stopped: false };
        while !end.done {
            let t0 = Instant::now();
            m.epoch += 1;
            let epoch = m.epoch;
            let train_loss;
            let half_cosine =
                |done: usize, len: usize| 0.5 * (1.0 + (std::f64::consts::PI * done as f64 / len as f64).cos());
            let mut lr = if s.lr_cosine { m.lr * half_cosine(epoch - 1, s.max_epochs) } else { m.lr };
            if let Some((start, len)) = m.anneal {
                lr *= half_cosine(epoch - 1 - start, len);
            }
            let val_loss;
            let pass = || {
                let (flow, weights, loss) = self.epoch(m.flow, &mut m.opt, lr, &mut m.order, &mut m.rng);
                (flow, loss, self.validate(&weights))
            };
            (m.flow, train_loss, val_loss) = lane.run(pass);
            if val_loss < m.best_val_loss {
                (m.best_val_loss, m.best_epoch, m.record) = (val_loss, epoch, Some(m.flow.valid().into_record()));
            }
            end.done = epoch == s.max_epochs;
            if let Some((start, len)) = m.anneal {
                end.done |= epoch >= start + len;
            } else if s.lr_plateau > 0 && epoch - m.best_epoch.max(m.last_change) >= s.lr_plateau {
                m.lr *= 0.5;
                m.last_change = epoch;
            }
            if m.anneal.is_none() && epoch - m.best_epoch.max(m.last_drop) >= s.patience {
                if m.drops == s.lr_drops {
                    let len = s.patience.max((s.lr_anneal * epoch as f64).ceil() as usize).min(s.max_epochs - epoch);
                    if s.lr_anneal > 0.0 && len > 0 {
                        m.anneal = Some((epoch, len));
                    } else {
                        end.done = true;
                    }
                } else {
                    m.drops += 1;
                    m.lr *= 0.1;
                    (m.last_drop, m.last_change) = (epoch, epoch);
                }
            }
            let seconds = t0.elapsed().as_secs_f64();
            let (member, best_val_loss) = (m.member, m.best_val_loss);
            let report = EpochReport { member, epoch, train_loss, val_loss, best_val_loss, seconds };
            end.stopped = !progress(&report);
            if !end.done {
                save(&m, end.stopped);
            }
            if end.stopped {
                break;
            }
        }
        (m, end)
    }
}

/// Member `member`'s batch stream: member 0 goes on from the split's `rng` (so a
/// one-member ensemble is the single model), member k draws from a stream of its own.
fn member_stream(rng: &ChaCha8Rng, seed: u64, member: usize) -> ChaCha8Rng {
    match member {
        0 => rng.clone(),
        k => ChaCha8Rng::seed_from_u64(seed ^ (0x9E37_79B9_7F4A_7C15u64.wrapping_mul(k as u64))),
    }
}

/// Where and how often a training saves the state it resumes from
/// ([`train_checkpointed`]).
#[derive(Clone, Debug)]
pub struct Checkpointing {
    /// The checkpoint file: a training of the same settings and data resumes from it;
    /// replaced as the training goes by a temporary file renamed over it.
    pub path: PathBuf,
    /// Names this writer's temporary file (`<path>.<tag>.tmp`), so that two writers of
    /// one checkpoint (a stalled attempt of a job and the one that took over) never share
    /// one.
    pub tag: String,
    /// Most training time between two checkpoints; less when writing one is cheap (at most
    /// 1/[`CHECKPOINT_COST_SHARE`] of the time goes to checkpoints). One is written too
    /// when a member ends and when the progress callback stops the training.
    pub every: Duration,
}

impl Checkpointing {
    /// Checkpoints at `path` at least every 30 s; `tag` names this writer's temporary file.
    pub fn new(path: PathBuf, tag: &str) -> Checkpointing {
        Checkpointing { path, tag: tag.to_string(), every: Duration::from_secs(30) }
    }
}

/// A checkpoint is written once the training since the last one took this many times
/// what writing the last one took (or `Checkpointing::every`, if sooner).
pub const CHECKPOINT_COST_SHARE: u32 = 20;

/// A trained model and where its training began.
pub struct Trained {
    /// The model, as an uninterrupted training would have made it.
    pub model: Npe,
    /// Epochs (summed over members) read back from a checkpoint; 0: from the start.
    pub resumed_from_epoch: usize,
}

const CKPT_MAGIC: &[u8; 12] = b"OTOFIT-CKPT\n";

/// A checkpoint's numbers (its JSON part); the weights follow as length-prefixed
/// records: each finished member's best, then for each of `states` in turn its blobs
/// ([`Snapshot`]). Floats that steer the training are kept as bits: exact through JSON.
/// Each member's state is its own: a checkpoint may hold members at different epochs.
/// Written with the states borrowed (`S = &MemberState`), read with them owned.
#[derive(Serialize, Deserialize)]
struct Saved<S = MemberState> {
    /// The settings and the data's standardisation, hashed: a checkpoint of another
    /// training is not resumed from.
    fingerprint: String,
    /// Epochs done over all members: a checkpoint never replaces one further on.
    epochs_done: usize,
    /// Finished members and their sums (`Finished`).
    members: usize,
    epochs: usize,
    best_epoch: usize,
    best_sum_bits: u64,
    /// Training time before this checkpoint, over all runs.
    wall_seconds: f64,
    /// The members not in `members`: ended after one still under way, or under way.
    #[serde(default)]
    states: Vec<S>,
    /// The one member under way of a checkpoint written before members trained side by
    /// side (read, never written).
    #[serde(default, skip_serializing)]
    current: Option<S>,
}

/// `MemberRun`'s numbers, or an ended member's (`done`: no order, stream or optimizer).
#[derive(Default, Serialize, Deserialize)]
struct MemberState {
    member: usize,
    #[serde(default)]
    done: bool,
    epoch: usize,
    lr_bits: u64,
    last_change: usize,
    last_drop: usize,
    drops: usize,
    /// Absent in checkpoints written before annealing existed (none had begun).
    #[serde(default)]
    anneal: Option<(usize, usize)>,
    best_val_loss_bits: u64,
    best_epoch: usize,
    #[serde(default)]
    order: Vec<usize>,
    /// The batch stream: seed (hex), stream, word position (decimal: a u128).
    #[serde(default)]
    rng: (String, u64, String),
}

/// A member's state as a checkpoint holds it: its numbers and its weights encoded, the
/// current flow and the optimizer (under way only), then the best weights (if any).
struct Snapshot {
    state: MemberState,
    blobs: Vec<Vec<u8>>,
}

impl Snapshot {
    /// The state of member `m`, under way.
    fn of(m: &MemberRun) -> CheckpointResult<Snapshot> {
        let mut blobs = vec![record_bytes(&m.flow.clone().into_record())?, m.opt.to_bytes()];
        if let Some(r) = &m.record {
            blobs.push(record_bytes(r)?);
        }
        let state = MemberState {
            member: m.member,
            done: false,
            epoch: m.epoch,
            lr_bits: m.lr.to_bits(),
            last_change: m.last_change,
            last_drop: m.last_drop,
            drops: m.drops,
            anneal: m.anneal,
            best_val_loss_bits: m.best_val_loss.to_bits(),
            best_epoch: m.best_epoch,
            order: m.order.clone(),
            rng: (hex::encode(m.rng.get_seed()), m.rng.get_stream(), m.rng.get_word_pos().to_string()),
        };
        Ok(Snapshot { state, blobs })
    }

    /// The state of member `e`, ended: its best weights and its sums.
    fn ended(e: &Ended) -> CheckpointResult<Snapshot> {
        let blobs = e.record.iter().map(record_bytes).collect::<CheckpointResult<_>>()?;
        let state = MemberState {
            member: e.member,
            done: true,
            epoch: e.epoch,
            best_val_loss_bits: e.best_val_loss.to_bits(),
            best_epoch: e.best_epoch,
            ..MemberState::default()
        };
        Ok(Snapshot { state, blobs })
    }

    fn member(&self) -> usize {
        self.state.member
    }

    fn done(&self) -> bool {
        self.state.done
    }
}

/// The hash of what a training depends on besides its seed's streams: every setting and
/// the header (the data's standardisation and shape).
fn fingerprint(s: &TrainSettings, header: &Header) -> String {
    let mut h = Sha256::new();
    h.update(format!("{s:?}").as_bytes());
    h.update(serde_json::to_vec(header).unwrap_or_default());
    hex::encode(h.finalize())
}

/// Why a training checkpoint was not written or not used. Neither stops the training:
/// it goes on without writing, or starts over, and the log says why.
#[derive(Debug, thiserror::Error)]
enum CheckpointError {
    /// The file system refused.
    #[error("cannot {action} {}: {source}", path.display())]
    Io {
        /// What was being done.
        action: &'static str,
        /// The file.
        path: PathBuf,
        /// The refusal.
        source: std::io::Error,
    },
    /// Weights or the optimizer's state could not be encoded (burn's recorder).
    #[error("cannot encode the {what}: {why}")]
    Encode {
        /// Which part.
        what: &'static str,
        /// burn's message.
        why: String,
    },
    /// A part of the file does not decode into this training's flow or optimizer.
    #[error("the checkpoint's {what} do not fit this training: {why}")]
    Decode {
        /// Which part.
        what: &'static str,
        /// The decoder's message.
        why: String,
    },
    /// The file is a checkpoint of a training with other settings or data.
    #[error("a checkpoint of another training (settings or data differ)")]
    Foreign,
    /// The file is not a checkpoint, or is truncated or inconsistent.
    #[error("not a training checkpoint (damaged or truncated)")]
    Damaged,
}

type CheckpointResult<T> = std::result::Result<T, CheckpointError>;

/// A record's bytes.
fn record_bytes(r: &ModuleRecord) -> CheckpointResult<Vec<u8>> {
    r.clone()
        .into_bytes()
        .map(|b| b.to_vec())
        .map_err(|e| CheckpointError::Encode { what: "weights", why: format!("{e:?}") })
}

/// A record from its bytes, checked against the flow it is for.
fn record_from(b: &[u8], cfg: &FlowConfig) -> CheckpointResult<ModuleRecord> {
    let decode = |e: &dyn std::fmt::Debug| CheckpointError::Decode { what: "weights", why: format!("{e:?}") };
    let r = ModuleRecord::from_bytes(burn::tensor::Bytes::from_bytes_vec(b.to_vec())).map_err(|e| decode(&e))?;
    new_flow(cfg, &Device::flex(), None).try_load_record(r.clone()).map_err(|e| decode(&e))?;
    Ok(r)
}

/// Writes and reads one training's checkpoints.
struct Saver<'a> {
    c: &'a Checkpointing,
    fingerprint: String,
    /// Training time of earlier runs (from the checkpoint resumed from).
    wall_before: f64,
    start: Instant,
    last: Instant,
    /// How long the last checkpoint took: encoding the members' states and writing.
    cost: Duration,
    /// The finished members' records, encoded once.
    members: Vec<Vec<u8>>,
}

impl Saver<'_> {
    /// A saver of the training `fingerprint` names, started at `start`, before any
    /// checkpoint is read.
    fn new(c: &Checkpointing, fingerprint: String, start: Instant) -> Saver<'_> {
        Saver { c, fingerprint, wall_before: 0.0, start, last: start, cost: Duration::ZERO, members: vec![] }
    }

    /// Where this training goes on from its checkpoint (from the start when there is
    /// none, or it cannot be used: the log says why).
    fn resume(&mut self, run: &Run) -> Start {
        match self.load(run) {
            Ok(Some((start, wall))) => {
                self.wall_before = wall;
                let epochs = start.epochs();
                tracing::info!(checkpoint = %self.c.path.display(), epochs, "training resumed from its checkpoint");
                start
            }
            Ok(None) => Default::default(),
            Err(why) => {
                tracing::warn!(checkpoint = %self.c.path.display(), %why, "checkpoint not used; training from the start");
                Default::default()
            }
        }
    }

    /// Whether a checkpoint is due: the training since the last one took
    /// `Checkpointing::every`, or [`CHECKPOINT_COST_SHARE`] times what writing it took.
    fn due(&self) -> bool {
        self.last.elapsed() >= self.c.every.min(self.cost * CHECKPOINT_COST_SHARE)
    }

    /// Writes a checkpoint of `fin` and the other members' `states`, whose encoding took
    /// `encoding` (on the lanes); a failure is logged, not fatal: the training goes on.
    fn save<'s>(&mut self, fin: &Finished, states: impl Iterator<Item = &'s Snapshot>, encoding: Duration) {
        let t0 = Instant::now();
        if let Err(why) = self.write(fin, states) {
            tracing::warn!(checkpoint = %self.c.path.display(), %why, "training checkpoint not written");
        }
        (self.last, self.cost) = (Instant::now(), t0.elapsed() + encoding);
    }

    fn write<'s>(&mut self, fin: &Finished, states: impl Iterator<Item = &'s Snapshot>) -> CheckpointResult<()> {
        for r in &fin.records[self.members.len()..] {
            self.members.push(record_bytes(r)?);
        }
        let states: Vec<&Snapshot> = states.collect();
        let saved = Saved {
            fingerprint: self.fingerprint.clone(),
            epochs_done: fin.epochs + states.iter().map(|m| m.state.epoch).sum::<usize>(),
            members: fin.records.len(),
            epochs: fin.epochs,
            best_epoch: fin.best_epoch,
            best_sum_bits: fin.best_sum.to_bits(),
            wall_seconds: self.wall_before + self.start.elapsed().as_secs_f64(),
            states: states.iter().map(|m| &m.state).collect(),
            current: None,
        };
        let json = serde_json::to_vec(&saved)
            .map_err(|e| CheckpointError::Encode { what: "training state", why: e.to_string() })?;
        let mut out = CKPT_MAGIC.to_vec();
        let blobs = states.iter().flat_map(|m| &m.blobs);
        for part in std::iter::once(&json).chain(&self.members).chain(blobs) {
            out.extend_from_slice(&(part.len() as u64).to_le_bytes());
            out.extend_from_slice(part);
        }
        let path = &self.c.path;
        let mut tmp = path.as_os_str().to_owned();
        tmp.push(format!(".{}.tmp", self.c.tag));
        let tmp = PathBuf::from(tmp);
        let io = |action: &'static str, path: &Path| {
            let path = path.to_path_buf();
            move |source| CheckpointError::Io { action, path, source }
        };
        let mut f = std::fs::File::create(&tmp).map_err(io("create", &tmp))?;
        f.write_all(&out).and_then(|_| f.sync_all()).map_err(io("write", &tmp))?;
        drop(f);
        // Another writer of this training (an attempt that took the job over) got further.
        if read_head(path).is_some_and(|h| h.fingerprint == saved.fingerprint && h.epochs_done > saved.epochs_done) {
            let _ = std::fs::remove_file(&tmp);
            return Ok(());
        }
        std::fs::rename(&tmp, path).map_err(io("rename", path))
    }

    /// The state a checkpoint of this training holds, if there is one, and the training
    /// time before it. `Err` says why a checkpoint there is not used.
    fn load(&self, run: &Run) -> CheckpointResult<Option<(Start, f64)>> {
        let bytes = match std::fs::read(&self.c.path) {
            Ok(b) => b,
            Err(e) if e.kind() == std::io::ErrorKind::NotFound => return Ok(None),
            Err(source) => return Err(CheckpointError::Io { action: "read", path: self.c.path.clone(), source }),
        };
        let bad = || CheckpointError::Damaged;
        let mut rest = bytes.strip_prefix(CKPT_MAGIC.as_slice()).ok_or_else(bad)?;
        let mut parts = vec![];
        while !rest.is_empty() {
            let (part, after) = super::length_prefixed(rest).ok_or_else(bad)?;
            parts.push(part);
            rest = after;
        }
        let saved: Saved = serde_json::from_slice(parts.first().ok_or_else(bad)?).map_err(|_| bad())?;
        if saved.fingerprint != self.fingerprint {
            return Err(CheckpointError::Foreign);
        }
        let (cfg, members) = (run.cfg, run.s.ensemble.max(1));
        // Counts past the settings' (a damaged file) would overflow the sums of epochs.
        if saved.members > members || saved.epochs > members * run.s.max_epochs {
            return Err(bad());
        }
        let blobs = parts.get(1..1 + saved.members).ok_or_else(bad)?;
        let fin = Finished {
            records: blobs.iter().map(|b| record_from(b, cfg)).collect::<std::result::Result<_, _>>()?,
            epochs: saved.epochs,
            best_epoch: saved.best_epoch,
            best_sum: f64::from_bits(saved.best_sum_bits),
        };
        let mut blobs = parts[1 + saved.members..].iter();
        let mut start = Start { fin, ..Default::default() };
        let mut seen = vec![false; members];
        for st in saved.states.into_iter().chain(saved.current) {
            // Each member once, after the model's own, within its epochs.
            let again = std::mem::replace(seen.get_mut(st.member).ok_or_else(bad)?, true);
            if st.member < saved.members || again || st.epoch > run.s.max_epochs {
                return Err(bad());
            }
            match st.done {
                true => start.ended.push(Ended {
                    member: st.member,
                    epoch: st.epoch,
                    best_epoch: st.best_epoch,
                    best_val_loss: f64::from_bits(st.best_val_loss_bits),
                    record: (st.best_epoch > 0)
                        .then(|| blobs.next().ok_or_else(bad).and_then(|b| record_from(b, cfg)))
                        .transpose()?,
                }),
                false => {
                    let (flow, opt) = (blobs.next().ok_or_else(bad)?, blobs.next().ok_or_else(bad)?);
                    let best = (st.best_epoch > 0).then(|| blobs.next().ok_or_else(bad)).transpose()?;
                    start.under_way.push(member_run(run, st, flow, opt, best.copied())?);
                }
            }
        }
        if blobs.next().is_some() {
            return Err(bad());
        }
        Ok(Some((start, saved.wall_seconds)))
    }
}

/// A member under way from its checkpointed numbers and blobs (its flow, optimizer and
/// best weights).
fn member_run(run: &Run, st: MemberState, flow: &[u8], opt: &[u8], best: Option<&[u8]>) -> CheckpointResult<MemberRun> {
    let (cfg, bad) = (run.cfg, || CheckpointError::Damaged);
    let mut sorted = st.order.clone();
    sorted.sort_unstable();
    let mut want = run.train_idx.to_vec();
    want.sort_unstable();
    if sorted != want {
        return Err(bad());
    }
    let flow = new_flow(cfg, &run.device, None)
        .try_load_record(record_from(flow, cfg)?)
        .map_err(|e| CheckpointError::Decode { what: "weights", why: format!("{e:?}") })?;
    let opt = optimizer(run.s)
        .with_state(opt, &Weights::of(&flow, cfg))
        .map_err(|e| CheckpointError::Decode { what: "optimizer state", why: e.to_string() })?;
    let seed: [u8; 32] = hex::decode(&st.rng.0).ok().and_then(|s| s.try_into().ok()).ok_or_else(bad)?;
    let mut rng = ChaCha8Rng::from_seed(seed);
    rng.set_stream(st.rng.1);
    rng.set_word_pos(st.rng.2.parse().map_err(|_| bad())?);
    Ok(MemberRun {
        member: st.member,
        flow,
        opt,
        rng,
        order: st.order,
        epoch: st.epoch,
        lr: f64::from_bits(st.lr_bits),
        last_change: st.last_change,
        last_drop: st.last_drop,
        drops: st.drops,
        anneal: st.anneal,
        best_val_loss: f64::from_bits(st.best_val_loss_bits),
        best_epoch: st.best_epoch,
        record: best.map(|b| record_from(b, cfg)).transpose()?,
    })
}

/// The JSON part of the checkpoint at `path`, read without its weights.
fn read_head(path: &Path) -> Option<Saved> {
    let mut f = std::fs::File::open(path).ok()?;
    let mut head = [0u8; CKPT_MAGIC.len() + 8];
    f.read_exact(&mut head).ok()?;
    if &head[..CKPT_MAGIC.len()] != CKPT_MAGIC {
        return None;
    }
    let n = u64::from_le_bytes(head[CKPT_MAGIC.len()..].try_into().ok()?);
    let mut json = vec![];
    f.take(n).read_to_end(&mut json).ok()?;
    serde_json::from_slice(&json).ok()
}

/// Epochs done (over all members) in the checkpoint at `path`, if it is one.
pub fn checkpoint_epochs(path: &Path) -> Option<usize> {
    read_head(path).map(|h| h.epochs_done)
}

/// Removes the checkpoint at `path` and the temporary files of its writers
/// (`<path>.*.tmp`). Returns how many files went.
pub fn remove_checkpoint(path: &Path) -> usize {
    let (Some(dir), Some(name)) = (path.parent(), path.file_name()) else { return 0 };
    let name = name.to_string_lossy();
    let tmp = |f: &str| f.strip_prefix(&*name).is_some_and(|t| t.starts_with('.') && t.ends_with(".tmp"));
    let entries = std::fs::read_dir(if dir.as_os_str().is_empty() { Path::new(".") } else { dir });
    let temporaries = entries
        .into_iter()
        .flatten()
        .flatten()
        .filter(|e| tmp(&e.file_name().to_string_lossy()) && std::fs::remove_file(e.path()).is_ok())
        .count();
    temporaries + usize::from(std::fs::remove_file(path).is_ok())
}

/// Trains a model. `progress` gets one report per epoch and returns `false` to stop early
/// (the best weights so far are kept).
pub fn train(ds: &Dataset, s: &TrainSettings, progress: &mut dyn FnMut(&EpochReport) -> bool) -> Result<Npe> {
    train_checkpointed(ds, s, None, progress).map(|t| t.model)
}

/// Trains a model as [`train`] does; with `checkpoint`, resumes from the checkpoint file
/// if it holds a state of this training (same settings and data) and saves its state
/// there as it goes. The model is the same, weights and numbers, as an uninterrupted
/// training's (the wall time apart). The file is left in place: the caller removes it
/// ([`remove_checkpoint`]) once the model is safe.
pub fn train_checkpointed(
    ds: &Dataset,
    s: &TrainSettings,
    checkpoint: Option<&Checkpointing>,
    progress: &mut dyn FnMut(&EpochReport) -> bool,
) -> Result<Trained> {
    let start = Instant::now();
    check(ds, s)?;
    let (idx, n_val, rng) = seeded_split(ds.theta.len(), s.val_fraction, s.seed);
    let (val_idx, train_idx) = idx.split_at(n_val);
    let s = &s.for_rows(train_idx.len());
    let u_rows = u_rows(ds, s.theta_map);
    let header = standardise(ds, s, &u_rows, train_idx, n_val);
    // The network is built from the settings as computed (the header keeps its copy).
    let cfg = header.flow.clone();
    let header = reread(&header)?;
    let groups = if s.mask_groups { ds.groups.clone() } else { vec![] };
    let discrepancy = header.model_error_sampler()?;
    let read = header.measure_features();
    let batcher = Batcher { ds, s, header: &header, u_rows: &u_rows, groups: &groups, discrepancy, read };
    let val_batches = validation_batches(&batcher, val_idx, s.seed);
    let run = Run { s, cfg: &cfg, batcher, train_idx, val_batches, n_val, device: Device::flex().autodiff() };
    let mut saver = checkpoint.map(|c| Saver::new(c, fingerprint(s, &header), start));
    let from = saver.as_mut().map(|sv| sv.resume(&run)).unwrap_or_default();
    let resumed_from_epoch = from.epochs();
    let lanes = side_by_side::Lanes::for_members(s.ensemble.max(1))?;
    let fin = run.side_by_side(&rng, from, lanes, saver.as_mut(), progress)?;
    let wall = saver.map_or(0.0, |sv| sv.wall_before) + start.elapsed().as_secs_f64();
    Ok(Trained { model: summarise(header, fin, wall), resumed_from_epoch })
}

/// The rows shuffled by the training's seed, how many of the first go to validation, and
/// the generator as the split left it (member 0's batch stream goes on from it).
fn seeded_split(n: usize, val_fraction: f64, seed: u64) -> (Vec<usize>, usize, ChaCha8Rng) {
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    let (idx, n_val) = split(n, val_fraction, &mut rng);
    (idx, n_val, rng)
}

/// The (validation, training) row indices a training of `n` rows with this validation
/// fraction and seed uses (for comparing other trainers on the same split).
pub fn validation_split(n: usize, val_fraction: f64, seed: u64) -> (Vec<usize>, Vec<usize>) {
    let (mut idx, n_val, _) = seeded_split(n, val_fraction, seed);
    let train = idx.split_off(n_val);
    (idx, train)
}

/// Rows of a table of `n` (at least 2) held out for validation: at least one row on each
/// side.
fn validation_rows(n: usize, val_fraction: f64) -> usize {
    ((n as f64 * val_fraction).round() as usize).clamp(1, n - 1)
}

/// The rows shuffled by `rng` and how many of the first go to validation.
fn split(n: usize, val_fraction: f64, rng: &mut ChaCha8Rng) -> (Vec<usize>, usize) {
    let mut idx: Vec<usize> = (0..n).collect();
    idx.shuffle(rng);
    (idx, validation_rows(n, val_fraction))
}

/// The header as a checkpoint reads it back (serde_json may move a float by one ulp), so
/// that a saved and reloaded model draws exactly what the trained one draws.
fn reread(header: &Header) -> Result<Header> {
    let encode = |e: serde_json::Error| NpeError::Encode { what: "header", why: e.to_string() };
    serde_json::from_slice(&serde_json::to_vec(header).map_err(encode)?).map_err(encode)
}

/// The validation rows in batches of 1000 with one noise draw of their own (seeded apart
/// from the training stream), fixed for the whole training: (v, input, rows).
fn validation_batches(batcher: &Batcher, val_idx: &[usize], seed: u64) -> Vec<(Vec<f32>, Vec<f32>, usize)> {
    let mut val_rng = ChaCha8Rng::seed_from_u64(seed ^ 0x5EED);
    val_idx
        .chunks(1000)
        .map(|c| {
            let (v, i) = batcher.batch(c, val_rng.random());
            (v, i, c.len())
        })
        .collect()
}

/// The model of the finished members, its header summing up the training: epochs summed
/// over members, best epoch of member 0, mean best validation loss, `wall` seconds.
fn summarise(mut header: Header, fin: Finished, wall: f64) -> Npe {
    header.members = fin.records.len();
    header.training.epochs = fin.epochs;
    header.training.best_epoch = fin.best_epoch;
    header.training.best_val_loss = fin.best_sum / fin.records.len() as f64;
    header.training.wall_seconds = wall;
    Npe::from_parts(header, fin.records)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn small_tables_get_an_ensemble_and_large_ones_one_flow() {
        let auto = TrainSettings { ensemble: 0, ..TrainSettings::default() };
        let members: Vec<usize> = [100, 9_000, 10_000, 12_500, 16_666, 25_000, 25_001, 1_000_000]
            .iter()
            .map(|&rows| auto.members_for(rows))
            .collect();
        assert_eq!(members, [5, 5, 5, 4, 3, 2, 1, 1]);
        // A 10,000-row table trains on 9,000 rows; 27,778 rows (25,000 training) is the
        // last with two.
        assert_eq!(auto.members_for_table(10_000), 5);
        assert_eq!(auto.members_for_table(27_778), 2);
        assert_eq!(auto.members_for_table(27_779), 1);
        assert_eq!(auto.members_for_table(2), 5);
        // Too small to split (refused by the dataset's check, but no panic here).
        assert_eq!([auto.members_for_table(0), auto.members_for_table(1)], [5, 5]);
        // A count that is set is kept, on any table; the library's default is one flow.
        let three = TrainSettings { ensemble: 3, ..auto.clone() };
        assert_eq!([three.members_for(100), three.members_for(1_000_000)], [3, 3]);
        assert_eq!(TrainSettings::default().members_for(100), 1);
        assert_eq!(TrainSettings::v8().members_for(100), 1);
        assert_eq!(auto.for_rows(9_000).ensemble, 5);
    }

    /// The largest difference between two gradients relative to each tensor's largest
    /// entry, and how many tensors were compared.
    fn compare(a: &gradient::Gradient, b: &gradient::Gradient) -> (f64, usize) {
        let mut worst = 0.0f64;
        for (a, b) in a.0.iter().zip(&b.0) {
            let scale = a.iter().fold(1e-6f32, |m, v| m.max(v.abs()));
            let diff = a.iter().zip(b).fold(0.0f32, |m, (x, y)| m.max((x - y).abs()));
            worst = worst.max((diff / scale) as f64);
        }
        (worst, a.0.len().min(b.0.len()))
    }

    /// A batch split over 1, 2, 3 or 5 threads has the whole batch's loss and gradient
    /// (to f32 rounding), for every parameter, with parts of unequal size; one and two
    /// threads give the same bits.
    #[test]
    fn a_split_batch_has_the_whole_batchs_gradient() {
        let device = Device::flex().autodiff();
        let cfg = FlowConfig { blocks: 2, lu: true, scaled_bins: true, ..FlowConfig::new(3, 4, false) };
        let flow = Flow::seeded(&cfg, &device, Some(11));
        let weights = Arc::new(Weights::of(&flow, &cfg));
        let b = 5 * MIN_PART_ROWS + 3;
        let mut rng = ChaCha8Rng::seed_from_u64(3);
        let v: Vec<f32> = (0..b * cfg.dim).map(|_| rng.random_range(-2.0..2.0)).collect();
        let inp: Vec<f32> = (0..b * cfg.inputs).map(|_| rng.random_range(-1.0..1.0)).collect();
        let (whole_loss, whole) = gradient::loss_and_gradient(&weights, &v, &inp, b);
        let mut losses = vec![];
        for threads in [1, 2, 3, 5] {
            let pool = rayon::ThreadPoolBuilder::new().num_threads(threads).build().unwrap();
            let (split_loss, split) = pool
                .install(|| {
                    let batch = (v.clone(), inp.clone(), b);
                    if threads == 1 {
                        return batch_gradient(&weights, &cfg, batch, 1, None);
                    }
                    std::thread::scope(|s| {
                        let helpers = Helpers::start(s, threads - 1, &|_, _, _| unreachable!("no draws"));
                        batch_gradient(&weights, &cfg, batch, threads, Some((&helpers, None)))
                    })
                })
                .unwrap();
            let close = (split_loss - whole_loss).abs() < 1e-5 * whole_loss.abs().max(1.0);
            assert!(close, "{threads} threads: {split_loss} vs {whole_loss}");
            let (worst, count) = compare(&whole, &split);
            assert_eq!(count, weights.sizes().count(), "{threads} threads: every parameter's gradient is there");
            assert!(worst < 1e-4, "{threads} threads: worst relative difference {worst}");
            losses.push(split_loss);
        }
        assert_eq!(losses[0].to_bits(), losses[1].to_bits(), "one and two threads split alike");
    }

    /// Every weight of a flow, parameter by parameter.
    struct Collect(Vec<f32>);

    impl burn::module::ModuleVisitor for Collect {
        fn visit_float<const D: usize>(&mut self, param: &burn::module::Param<Tensor<D>>) {
            self.0.extend(param.val().try_into_vec_as::<f32>().unwrap());
        }
    }

    fn weights(flow: &Flow) -> Vec<f32> {
        let mut w = Collect(vec![]);
        flow.visit(&mut w);
        w.0
    }

    /// `n` rows of x = (θ0 + θ1, θ0 − θ1, θ0 θ1 / 4) with θ uniform on [−2, 2]², noisy.
    fn toy(n: usize) -> Dataset {
        let mut rng = ChaCha8Rng::seed_from_u64(1);
        let theta: Vec<Vec<f64>> =
            (0..n).map(|_| vec![rng.random_range(-2.0..2.0), rng.random_range(-2.0..2.0)]).collect();
        let param = |name: &str| super::super::Param {
            name: name.into(),
            unit: "1".into(),
            scale: super::super::Scale::Linear,
            low: -2.0,
            high: 2.0,
        };
        Dataset {
            params: vec![param("p"), param("q")],
            feature_names: vec!["s".into(), "d".into(), "m".into()],
            frequencies_hz: vec![],
            groups: vec![],
            noise_std: vec![0.2; 3],
            x: theta.iter().map(|t| vec![t[0] + t[1], t[0] - t[1], t[0] * t[1] / 4.0]).collect(),
            theta,
            skipped: 0,
        }
    }

    /// `f` given the training run `train_checkpointed` sets up for `ds` and `s`.
    fn with_run<R>(ds: &Dataset, s: &TrainSettings, f: impl FnOnce(&Run) -> R) -> R {
        let (idx, n_val, _) = seeded_split(ds.theta.len(), s.val_fraction, s.seed);
        let (val_idx, train_idx) = idx.split_at(n_val);
        let s = &s.for_rows(train_idx.len());
        let u_rows = u_rows(ds, s.theta_map);
        let header = standardise(ds, s, &u_rows, train_idx, n_val);
        let discrepancy = header.model_error_sampler().unwrap();
        let read = header.measure_features();
        let batcher = Batcher { ds, s, header: &header, u_rows: &u_rows, groups: &[], discrepancy, read };
        let val_batches = validation_batches(&batcher, val_idx, s.seed);
        let cfg = &header.flow;
        f(&Run { s, cfg, batcher, train_idx, val_batches, n_val, device: Device::flex().autodiff() })
    }

    /// A measure-set flow's batches give its network the other groups' features as
    /// zeros, and its own as drawn; the trained model says which groups it reads and
    /// ignores the rest when it answers. A group it cannot have is refused by name.
    #[test]
    fn a_measure_set_flow_trains_on_its_groups_alone() {
        let mut ds = toy(300);
        let group = |name: &str, features: Vec<usize>| super::super::Group { name: name.into(), features };
        ds.groups = vec![group("sum", vec![0]), group("rest", vec![1, 2])];
        let s = TrainSettings {
            embedding: false,
            seed: 3,
            batch: 100,
            max_epochs: 2,
            measures: vec!["rest".into()],
            ..Default::default()
        };
        with_run(&ds, &s, |run| {
            let (_, inp) = run.batcher.batch(&run.train_idx[..50], 11);
            let col = |k: usize| inp.iter().skip(k).step_by(3).copied().collect::<Vec<f32>>();
            assert!(col(0).iter().all(|&v| v == 0.0), "the group it does without: zeros");
            assert!(col(1).iter().chain(&col(2)).all(|&v| v != 0.0), "its own group: drawn");
        });
        let m = train(&ds, &s, &mut |_| true).unwrap();
        assert_eq!(m.header.measures, ["rest"]);
        let (x, moved) =
            (m.header.x_mean.clone(), vec![m.header.x_mean[0] + 9.0, m.header.x_mean[1], m.header.x_mean[2]]);
        let given = [false, true, true];
        let row = |x: &[f64], p: Option<&[bool]>| m.input_row(&super::super::Obs { x, present: p }).unwrap();
        assert_eq!(row(&x, Some(&given)), row(&moved, None), "the other group is not read");
        for (measures, says) in [
            (vec!["tympanogram".to_string()], "'tympanogram' is not one of the dataset's feature groups (sum, rest)"),
            (vec!["rest".into(), "sum".into()], "names every group"),
            (vec!["rest".into(), "rest".into()], "named twice"),
        ] {
            let e = train(&ds, &TrainSettings { measures, ..s.clone() }, &mut |_| true).err().unwrap().to_string();
            assert!(e.contains("measures") && e.contains(says), "{e}");
        }
        let masked = TrainSettings { mask_groups: true, ..s.clone() };
        assert!(train(&ds, &masked, &mut |_| true).err().unwrap().to_string().contains("--mask-groups"));
    }

    /// A table of two groups of eight features on an eight-point grid.
    fn gridded(n: usize) -> Dataset {
        let mut ds = toy(n);
        let x: Vec<Vec<f64>> = ds
            .theta
            .iter()
            .map(|t| {
                (0..16)
                    .map(|k| if k < 8 { t[0] + t[1] * k as f64 / 8.0 } else { t[0] * (k - 8) as f64 / 8.0 - t[1] })
                    .collect()
            })
            .collect();
        let group = |name: &str, features: Vec<usize>| super::super::Group { name: name.into(), features };
        ds.feature_names = (0..16).map(|k| format!("f{k}")).collect();
        ds.frequencies_hz = (0..8).map(|k| 200.0 * 2f64.powi(k)).collect();
        ds.groups = vec![group("sum", (0..8).collect()), group("rest", (8..16).collect())];
        ds.noise_std = vec![0.2; 16];
        ds.x = x;
        ds
    }

    /// Two quick epochs of a flow of the gridded table's group "rest" alone.
    fn rest_alone() -> TrainSettings {
        TrainSettings {
            embedding: false,
            seed: 5,
            batch: 100,
            max_epochs: 2,
            measures: vec!["rest".into()],
            ..Default::default()
        }
    }

    /// A measure-set flow trained from a frequency up sees its groups' lower points as
    /// zeros in every row, and its band above as drawn; it answers an ear given from that
    /// frequency without reading a lower point. Settings it cannot train are refused.
    #[test]
    fn a_flow_from_a_frequency_up_never_sees_the_points_below_it() {
        let ds = gridded(300);
        let s = TrainSettings { from_hz: 500.0, ..rest_alone() };
        with_run(&ds, &s, |run| {
            let (_, inp) = run.batcher.batch(&run.train_idx[..60], 13);
            let col = |k: usize| inp.iter().skip(k).step_by(16).copied().collect::<Vec<f32>>();
            assert!((0..10).all(|k| col(k).iter().all(|&v| v == 0.0)), "the other group and 200, 400 Hz: zeros");
            assert!((10..16).all(|k| col(k).iter().all(|&v| v != 0.0)), "its band from 800 Hz: drawn");
        });
        let m = train(&ds, &s, &mut |_| true).unwrap();
        assert_eq!((m.header.from_hz, m.header.measures.as_slice()), (500.0, ["rest".to_string()].as_slice()));
        let x = m.header.x_mean.clone();
        let mut moved = x.clone();
        (0..10).for_each(|k| moved[k] += 9.0);
        let given: Vec<bool> = (0..16).map(|k| k >= 10).collect();
        let row = |x: &[f64], p: Option<&[bool]>| m.input_row(&super::super::Obs { x, present: p }).unwrap();
        assert_eq!(row(&x, Some(&given)), row(&moved, None), "points below its band are not read");
        for (bad, says) in [
            (TrainSettings { measures: vec![], ..s.clone() }, "--measures"),
            (TrainSettings { mask_bands: true, ..s.clone() }, "without --mask-bands"),
            (TrainSettings { from_hz: 200.0, ..s.clone() }, "above the grid's first point (200 Hz)"),
            (TrainSettings { from_hz: 20_000.0, ..s.clone() }, "at most at 12800 Hz"),
            (TrainSettings { from_hz: f64::NAN, ..s.clone() }, "positive frequency"),
        ] {
            let e = train(&ds, &bad, &mut |_| true).err().unwrap().to_string();
            assert!(e.contains("from-hz") && e.contains(says), "{e}");
        }
    }

    /// A band-masked measure-set flow sees its groups whole or with the ends of the band
    /// cut (never beyond a quarter of the grid), a flag per feature saying which are
    /// there; the other groups never. It answers an ear of its groups on part of the band.
    #[test]
    fn a_band_masked_measure_set_flow_trains_on_its_groups_with_their_band_ends_cut() {
        let ds = gridded(400);
        let s = TrainSettings { mask_bands: true, ..rest_alone() };
        let (mut cut, mut whole) = (0, 0);
        with_run(&ds, &s, |run| {
            assert_eq!(run.cfg.inputs, 32, "16 features and 16 flags");
            let (_, inp) = run.batcher.batch(&run.train_idx[..200], 17);
            for row in inp.chunks(32) {
                let (x, flag) = row.split_at(16);
                assert!(x[..8].iter().chain(&flag[..8]).all(|&v| v == 0.0), "the other group: absent, {row:?}");
                let on: Vec<usize> = (0..8).filter(|&k| flag[8 + k] == 1.0).collect();
                let (lo, hi) = (on[0], on[on.len() - 1]);
                assert!(on.len() == hi - lo + 1 && lo <= 2 && hi >= 5, "one band, cut ≤ 2 points each end: {on:?}");
                assert!((0..8).all(|k| (flag[8 + k] == 1.0) == (x[8 + k] != 0.0)), "zeros where cut: {row:?}");
                if on.len() < 8 { cut += 1 } else { whole += 1 }
            }
        });
        assert!((60..=140).contains(&cut) && whole > 0, "about half the rows cut: {cut} of 200");
        let m = train(&ds, &s, &mut |_| true).unwrap();
        assert!(m.header.mask_bands && m.header.measures == ["rest"] && m.header.band_cut_max == 2);
        let x = m.header.x_mean.clone();
        let mut given = vec![false; 8];
        given.extend((0..8).map(|k| k >= 2));
        let row = m.input_row(&super::super::Obs { x: &x, present: Some(&given) }).unwrap();
        assert_eq!(&row[16..], given.iter().map(|&g| if g { 1.0 } else { 0.0 }).collect::<Vec<f32>>(), "flags");
        given[10] = false;
        let e = m.input_row(&super::super::Obs { x: &x, present: Some(&given) }).unwrap_err().to_string();
        assert!(e.contains("rest"), "a band cut further than training did is refused: {e}");
        let neither = TrainSettings { measures: vec![], ..s.clone() };
        let e = train(&ds, &neither, &mut |_| true).err().unwrap().to_string();
        assert!(e.contains("--mask-groups or --measures"), "{e}");
    }

    /// `band_cut` bounds how far a cut reaches (a flow for devices that drop a point or
    /// two), is stored as the flow's limit, and is refused without band masks or beyond a
    /// quarter of the grid.
    #[test]
    fn a_band_cut_bounds_the_cuts_and_is_the_flows_limit() {
        let ds = gridded(400);
        let s = TrainSettings {
            embedding: false,
            seed: 5,
            batch: 100,
            max_epochs: 1,
            measures: vec!["rest".into()],
            mask_bands: true,
            band_cut: 1,
            ..Default::default()
        };
        let mut widest = 0;
        with_run(&ds, &s, |run| {
            let (_, inp) = run.batcher.batch(&run.train_idx[..200], 17);
            for row in inp.chunks(32) {
                let on: Vec<usize> = (0..8).filter(|&k| row[24 + k] == 1.0).collect();
                let cut = on[0].max(7 - on[on.len() - 1]);
                assert!(cut <= 1, "a cut of {cut} points: {on:?}");
                widest = widest.max(cut);
            }
        });
        assert_eq!(widest, 1, "some rows are cut");
        let m = train(&ds, &s, &mut |_| true).unwrap();
        assert_eq!(m.header.band_cut_max, 1);
        for bad in [TrainSettings { band_cut: 3, ..s.clone() }, TrainSettings { mask_bands: false, ..s.clone() }] {
            let e = train(&ds, &bad, &mut |_| true).err().unwrap().to_string();
            assert!(e.contains("band-cut"), "{e}");
        }
    }

    /// With `band_cut_together`, half the rows cut every group of a measure-set
    /// flow to one band (a device's export); cut on their own, two groups share a cut in
    /// about one row of forty.
    #[test]
    fn cuts_together_give_every_group_of_a_row_one_band() {
        let mut ds = gridded(400);
        // A third group, for a measure-set flow of two groups that is not every group.
        for (x, t) in ds.x.iter_mut().zip(&ds.theta) {
            x.extend((0..8).map(|k| t[1] * k as f64 / 8.0));
        }
        ds.feature_names = (0..24).map(|k| format!("f{k}")).collect();
        ds.groups.push(super::super::Group { name: "third".into(), features: (16..24).collect() });
        ds.noise_std = vec![0.2; 24];
        let s = TrainSettings {
            embedding: false,
            seed: 5,
            batch: 100,
            max_epochs: 1,
            measures: vec!["sum".into(), "rest".into()],
            mask_bands: true,
            band_cut: 2,
            ..Default::default()
        };
        // Rows whose two groups are both cut, to the same band.
        let shared = |s: &TrainSettings| {
            let (mut rows, mut same) = (0, 0);
            with_run(&ds, s, |run| {
                let (_, inp) = run.batcher.batch(run.train_idx, 17);
                for row in inp.chunks(48) {
                    let here = &row[24..40];
                    rows += 1;
                    same += usize::from(here.contains(&0.0) && here[..8] == here[8..]);
                }
            });
            (rows, same)
        };
        let (rows, alone) = shared(&s);
        let (_, together) = shared(&TrainSettings { band_cut_together: true, ..s.clone() });
        assert_eq!(rows, 360);
        assert!(alone * 15 <= rows, "cut on their own, one band for both in {alone} of {rows}");
        assert!(together * 3 >= rows, "cut together, one band for both in {together} of {rows}");
        let e = train(&ds, &TrainSettings { band_cut_together: true, mask_bands: false, ..s.clone() }, &mut |_| true)
            .err()
            .unwrap()
            .to_string();
        assert!(e.contains("band-cut-together"), "{e}");
    }

    fn on_threads<R: Send>(threads: usize, f: impl FnOnce() -> R + Send) -> R {
        rayon::ThreadPoolBuilder::new().num_threads(threads).build().unwrap().install(f)
    }

    /// Two epochs (batches of 200, 200, 200 and an unsplit 30) on 1, 2 and 3 threads
    /// give the weights, the mean losses and the batch stream's position of the same
    /// epochs run one step after the other: shuffle, a seed per batch, then each batch
    /// drawn whole, its gradient taken and Adam's step. On three threads the helpers draw
    /// each batch in two chunks ahead of its step. One and two threads give the same bits.
    #[test]
    fn an_epoch_draws_its_batches_in_the_order_of_one_after_the_other() {
        let ds = toy(700);
        let s = TrainSettings { embedding: false, seed: 3, batch: 200, ..Default::default() };
        with_run(&ds, &s, |run| {
            let fresh = || run.fresh(0, ChaCha8Rng::seed_from_u64(9));
            let reference = |threads: usize| {
                on_threads(threads, || {
                    let mut m = fresh();
                    let mut losses = vec![];
                    for _ in 0..2 {
                        m.order.shuffle(&mut m.rng);
                        let seeds: Vec<u64> = m.order.chunks(run.s.batch).map(|_| m.rng.random()).collect();
                        let (mut sum, mut count) = (0.0, 0);
                        let mut w = Arc::new(Weights::of(&m.flow, run.cfg));
                        for (rows, &seed) in m.order.chunks(run.s.batch).zip(&seeds) {
                            let (v, inp) = run.batcher.batch(rows, seed);
                            let batch = (v, inp, rows.len());
                            let (l, g) = batch_gradient(&w, run.cfg, batch, threads, None).unwrap();
                            sum += l * rows.len() as f64;
                            count += rows.len();
                            m.opt.step(run.s.lr, Arc::make_mut(&mut w), g);
                        }
                        m.flow = w.to_flow(m.flow);
                        losses.push(sum / count as f64);
                    }
                    (weights(&m.flow), losses, m.rng.get_word_pos())
                })
            };
            let epochs = |threads: usize| {
                on_threads(threads, || {
                    let mut m = fresh();
                    let mut losses = vec![];
                    for _ in 0..2 {
                        let loss;
                        (m.flow, _, loss) = run.epoch(m.flow, &mut m.opt, run.s.lr, &mut m.order, &mut m.rng);
                        losses.push(loss);
                    }
                    (weights(&m.flow), losses, m.rng.get_word_pos())
                })
            };
            let one = reference(1);
            assert!(one.0.iter().all(|w| w.is_finite()) && one.1.iter().all(|l| l.is_finite()));
            assert!(epochs(1) == one, "1 thread");
            assert!(epochs(2) == one, "2 threads");
            assert!(epochs(3) == reference(3), "3 threads");
        });
    }

    /// From [`MAX_PARTS`] threads up a batch is cut alike: an epoch of 1,100-row batches
    /// (seventeen parts' worth of rows) gives the same bits on 16 and 18 threads.
    #[test]
    fn threads_beyond_the_part_cap_train_the_same_weights() {
        let ds = toy(1500);
        let s = TrainSettings { embedding: false, seed: 3, batch: 1100, ..Default::default() };
        with_run(&ds, &s, |run| {
            let epoch = |threads: usize| {
                on_threads(threads, || {
                    let mut m = run.fresh(0, ChaCha8Rng::seed_from_u64(9));
                    let loss;
                    (m.flow, _, loss) = run.epoch(m.flow, &mut m.opt, run.s.lr, &mut m.order, &mut m.rng);
                    (weights(&m.flow), loss)
                })
            };
            let capped = epoch(MAX_PARTS);
            assert!(capped.0.iter().all(|w| w.is_finite()) && capped.1.is_finite());
            assert!(epoch(MAX_PARTS + 2) == capped, "{} threads", MAX_PARTS + 2);
        });
    }

    /// The validation loss is the rows' losses added in order, whatever the threads: the
    /// same bits on 1, 2, 3 and 4 threads as a plain loop over the rows (7 batches: 6 of
    /// 1000, one of 500), and burn's mean −log q of the same weights up to f32 rounding.
    #[test]
    fn the_validation_loss_is_the_same_on_any_number_of_threads() {
        let ds = toy(13_000);
        let s = TrainSettings { embedding: true, val_fraction: 0.5, ..Default::default() };
        with_run(&ds, &s, |run| {
            assert_eq!(
                run.val_batches.iter().map(|b| b.2).collect::<Vec<_>>(),
                [1000, 1000, 1000, 1000, 1000, 1000, 500]
            );
            let valid = new_flow(run.cfg, &Device::flex(), Some(4));
            let weights = Weights::of(&valid, run.cfg);
            let (mut plain, mut burn) = (0.0, 0.0);
            for (v, inp, b) in &run.val_batches {
                for l in gradient::row_losses(&weights, v, inp, *b) {
                    plain += l;
                }
                burn += scalar(loss_of(&valid, run.cfg, v.clone(), inp.clone(), *b, &Device::flex())) * *b as f64;
            }
            let (plain, burn) = (plain / run.n_val as f64, burn / run.n_val as f64);
            assert!(plain.is_finite());
            assert!((plain - burn).abs() < 1e-5 * burn.abs().max(1.0), "host {plain} vs burn {burn}");
            for threads in [1, 2, 3, 4] {
                let got = on_threads(threads, || run.validate(&weights));
                assert_eq!(got.to_bits(), plain.to_bits(), "{threads} threads: {got} vs {plain}");
            }
        });
    }

    /// A draw that panics is heard by the calling thread (no batch comes, rather than a
    /// wait for ever) while the helper beside it lives on, and the scope passes the panic
    /// on.
    #[test]
    fn a_helper_that_panics_while_drawing_is_not_waited_for() {
        let heard = std::cell::Cell::new(None);
        // The second chunk's draw fails; the first helper draws and stays.
        let draw = |_: usize, lo: usize, hi: usize| {
            assert!(lo == 0, "a failed draw");
            (vec![], vec![], hi - lo)
        };
        let got = std::panic::catch_unwind(std::panic::AssertUnwindSafe(|| {
            std::thread::scope(|s| {
                let helpers = Helpers::start(s, 2, &draw);
                let (tx, rx) = std::sync::mpsc::channel();
                s.spawn(move || {
                    helpers.draw(0, 10);
                    let _ = tx.send(helpers.drawn().is_none());
                });
                heard.set(rx.recv_timeout(Duration::from_secs(20)).ok());
            })
        }));
        assert_eq!(heard.get(), Some(true), "the calling thread heard of the failed draw");
        assert!(got.is_err(), "the scope passes the panic on");
    }

    /// A whole training (3 epochs, validation and best weights) gives the same model on
    /// one and on two threads, and again on two.
    #[test]
    fn one_and_two_threads_train_the_same_model() {
        let ds = toy(700);
        let s = TrainSettings { embedding: true, max_epochs: 3, seed: 5, ..Default::default() };
        let trained = |threads| {
            let m = on_threads(threads, || train(&ds, &s, &mut |_| true)).unwrap();
            let draws = m.sample(&super::super::Obs { x: &[0.5, -0.3, 0.1], present: None }, 50, 2).unwrap();
            (m.header.training.best_val_loss.to_bits(), m.header.training.best_epoch, draws)
        };
        let one = trained(1);
        assert!(trained(2) == one, "two threads differ from one");
        assert!(trained(2) == one, "two threads differ from themselves");
    }

    /// An ensemble's settings for the side-by-side tests: no embedding, no early stop.
    fn lanes_settings(ensemble: usize, max_epochs: usize, seed: u64) -> TrainSettings {
        TrainSettings { embedding: false, max_epochs, patience: 40, seed, ensemble, ..Default::default() }
    }

    /// What "the same model" is compared by: members, epochs, best epoch and loss, draws.
    fn model(m: &Npe) -> (usize, usize, usize, u64, Vec<Vec<f64>>) {
        let t = &m.header.training;
        let draws = m.sample(&super::super::Obs { x: &[0.5, -0.3, 0.1], present: None }, 50, 2).unwrap();
        (m.header.members, t.epochs, t.best_epoch, t.best_val_loss.to_bits(), draws)
    }

    /// An ensemble's members trained side by side (two and three threads, checkpointed or
    /// not) are the members trained one after another (one thread): the same model, bit
    /// for bit. On two threads the reports of two members interleave, all on the calling
    /// thread.
    #[test]
    fn an_ensemble_side_by_side_is_the_ensemble_one_after_another() {
        let ds = toy(700);
        let s = lanes_settings(3, 12, 2);
        let trained = |threads: usize, checkpoint: Option<&Checkpointing>| {
            let mut order = vec![];
            let m = on_threads(threads, || {
                let caller = std::thread::current().id();
                train_checkpointed(&ds, &s, checkpoint, &mut |r| {
                    assert_eq!(std::thread::current().id(), caller, "a report off the calling thread");
                    // Member 0 slowed down, so that member 1 surely starts beside it.
                    if r.member == 0 {
                        std::thread::sleep(Duration::from_millis(10));
                    }
                    order.push(r.member);
                    true
                })
            });
            (model(&m.unwrap().model), order)
        };
        let (one, order) = trained(1, None);
        assert_eq!(one.1, 36, "three members of 12 epochs");
        assert!(order.is_sorted(), "one thread: one member after another {order:?}");
        let (two, order) = trained(2, None);
        assert!(two == one, "two threads side by side differ from one thread");
        assert!(!order.is_sorted(), "two threads: members one after another {order:?}");
        assert!(trained(3, None).0 == one, "three threads side by side differ from one thread");
        let dir = std::env::temp_dir().join(format!("otofit-side-by-side-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let c = Checkpointing::new(dir.join("t.ckpt"), "a");
        let (saved, order) = trained(2, Some(&c));
        assert!(saved == one, "checkpointed side by side differs from one thread");
        assert!(!order.is_sorted(), "checkpointed: members one after another {order:?}");
        let _ = std::fs::remove_dir_all(&dir);
    }

    /// A checkpointed ensemble side by side (two threads, three members, a checkpoint due
    /// at every epoch) stopped once member 1 has ended while member 0 is still training:
    /// checkpoints are written while both are under way, and the last holds member 1
    /// ended beside a member under way, each at its own epoch, and every epoch the stopped
    /// model trained. Resumed from it on two threads, and from a copy on one, the training
    /// trains no epoch twice and ends with the uninterrupted model, bit for bit.
    #[test]
    fn a_side_by_side_checkpoint_resumes_to_the_same_model() {
        let ds = toy(700);
        let s = lanes_settings(3, 12, 2);
        let whole = model(&on_threads(1, || train(&ds, &s, &mut |_| true)).unwrap());
        let dir = std::env::temp_dir().join(format!("otofit-side-ckpt-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        // Member 0's reports are slowed so that member 1 ends first; on a busy host it may
        // still end first, so the stop is tried again, slower each time, on a fresh file.
        let mut tried = vec![];
        let (c, head, last) = [30, 120, 480]
            .into_iter()
            .find_map(|pause| {
                let c = Checkpointing {
                    every: Duration::ZERO,
                    ..Checkpointing::new(dir.join(format!("t{pause}.ckpt")), "a")
                };
                let (mut last, mut one_ended, mut written_under_way) = ([0; 3], false, false);
                let stopped = on_threads(2, || {
                    train_checkpointed(&ds, &s, Some(&c), &mut |r| {
                        last[r.member] = r.epoch;
                        if r.member == 0 {
                            std::thread::sleep(Duration::from_millis(pause));
                        }
                        one_ended |= r.member == 1 && r.epoch == 12;
                        written_under_way |= !one_ended && read_head(&c.path).is_some_and(|h| h.epochs_done > 0);
                        !(one_ended && r.member == 0)
                    })
                })
                .unwrap();
                let head = read_head(&c.path)?;
                let state = |member: usize| head.states.iter().find(|m| m.member == member).map(|m| (m.done, m.epoch));
                tried.push((pause, state(0), state(1), last));
                // Member 1 ended beside member 0 under way: the case this test is about.
                let under_way = matches!(state(0), Some((false, e)) if e == last[0] && e < 12);
                if !(under_way && state(1) == Some((true, 12))) {
                    return None;
                }
                assert!(written_under_way, "no checkpoint while the members were under way");
                assert_eq!(head.epochs_done, stopped.model.header.training.epochs, "{last:?}");
                Some((c, head, last))
            })
            .unwrap_or_else(|| panic!("member 1 never ended while member 0 trained: {tried:?}"));
        std::fs::copy(&c.path, dir.join("u.ckpt")).unwrap();
        for (threads, file) in [(2, c.path.clone()), (1, dir.join("u.ckpt"))] {
            let c = Checkpointing::new(file, "b");
            let mut twice = vec![];
            let resumed = on_threads(threads, || {
                train_checkpointed(&ds, &s, Some(&c), &mut |r| {
                    if r.epoch <= last[r.member] {
                        twice.push((r.member, r.epoch));
                    }
                    true
                })
            })
            .unwrap();
            assert_eq!(resumed.resumed_from_epoch, head.epochs_done, "{threads} threads");
            assert!(twice.is_empty(), "{threads} threads: epochs trained again {twice:?}");
            assert!(model(&resumed.model) == whole, "{threads} threads: the resumed model differs");
        }
        let _ = std::fs::remove_dir_all(&dir);
    }

    /// A checkpoint's bytes with its JSON part rewritten by `edit`.
    fn rewritten(bytes: &[u8], edit: &dyn Fn(&mut serde_json::Value)) -> Vec<u8> {
        let (json, rest) = super::super::length_prefixed(&bytes[CKPT_MAGIC.len()..]).unwrap();
        let mut json: serde_json::Value = serde_json::from_slice(json).unwrap();
        edit(&mut json);
        let json = serde_json::to_vec(&json).unwrap();
        let mut out = CKPT_MAGIC.to_vec();
        out.extend_from_slice(&(json.len() as u64).to_le_bytes());
        out.extend_from_slice(&json);
        out.extend_from_slice(rest);
        out
    }

    /// A checkpoint whose numbers were damaged (member or epoch counts past the settings',
    /// a member out of range or twice) is refused as damaged: never a panic or an
    /// overflowing sum.
    #[test]
    fn damaged_checkpoint_counts_are_refused() {
        let ds = toy(700);
        let s = lanes_settings(2, 3, 4);
        let dir = std::env::temp_dir().join(format!("otofit-ckpt-counts-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let c = Checkpointing::new(dir.join("t.ckpt"), "a");
        on_threads(2, || train_checkpointed(&ds, &s, Some(&c), &mut |r| !(r.member == 1 && r.epoch == 2))).unwrap();
        let bytes = std::fs::read(&c.path).unwrap();
        let fingerprint = read_head(&c.path).unwrap().fingerprint;
        let max = serde_json::json!(usize::MAX);
        type Edit<'a> = (&'a str, &'a dyn Fn(&mut serde_json::Value));
        let edits: [Edit; 5] = [
            ("members", &|j| j["members"] = max.clone()),
            ("epochs", &|j| j["epochs"] = max.clone()),
            ("a state's epoch", &|j| j["states"][0]["epoch"] = max.clone()),
            ("a state's member", &|j| j["states"][0]["member"] = serde_json::json!(99)),
            ("a member twice", &|j| {
                let first = j["states"][0].clone();
                j["states"].as_array_mut().unwrap().push(first)
            }),
        ];
        with_run(&ds, &s, |run| {
            let saver = Saver::new(&c, fingerprint, Instant::now());
            assert!(matches!(saver.load(run), Ok(Some(_))), "the intact checkpoint");
            for (what, edit) in edits {
                std::fs::write(&c.path, rewritten(&bytes, edit)).unwrap();
                let got = saver.load(run);
                assert!(matches!(got, Err(CheckpointError::Damaged)), "{what}: {:?}", got.err());
            }
        });
        let _ = std::fs::remove_dir_all(&dir);
    }

    /// A checkpoint written before members trained side by side (its one member under way
    /// in `current`, no `states`) is resumed from, to the uninterrupted model.
    #[test]
    fn a_checkpoint_of_one_member_under_way_is_resumed_from() {
        let ds = toy(700);
        let s = lanes_settings(1, 5, 3);
        let whole = model(&train(&ds, &s, &mut |_| true).unwrap());
        let dir = std::env::temp_dir().join(format!("otofit-ckpt-current-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let c = Checkpointing::new(dir.join("t.ckpt"), "a");
        train_checkpointed(&ds, &s, Some(&c), &mut |r| r.epoch < 2).unwrap();
        let old = rewritten(&std::fs::read(&c.path).unwrap(), &|json| {
            let states = json.as_object_mut().unwrap().remove("states").unwrap();
            json["current"] = states[0].clone();
            json["current"].as_object_mut().unwrap().remove("done");
        });
        std::fs::write(&c.path, old).unwrap();
        let resumed = train_checkpointed(&ds, &s, Some(&c), &mut |_| true).unwrap();
        assert_eq!(resumed.resumed_from_epoch, 2);
        assert!(model(&resumed.model) == whole, "the resumed model differs");
        let _ = std::fs::remove_dir_all(&dir);
    }

    /// Threads shared between lanes: two members on six threads train three threads
    /// each, the model of one member after another on one lane of three threads, which a
    /// three-way split makes other than one thread's.
    #[test]
    fn lanes_of_three_threads_train_as_one_after_another_on_three() {
        let ds = toy(700);
        let s = TrainSettings { batch: 300, ..lanes_settings(2, 4, 6) };
        let trained = |threads: usize| {
            let m = on_threads(threads, || train(&ds, &s, &mut |_| true)).unwrap();
            (m.header.members, m.header.training.best_val_loss.to_bits())
        };
        // One lane of three threads, the members one after another.
        let three = with_run(&ds, &s, |run| {
            let (_, _, rng) = seeded_split(ds.theta.len(), s.val_fraction, s.seed);
            let lanes = side_by_side::Lanes::one(3);
            let fin = run.side_by_side(&rng, Start::default(), lanes, None, &mut |_| true).unwrap();
            (fin.records.len(), (fin.best_sum / 2.0).to_bits())
        });
        assert!(trained(6) == three, "two lanes of three threads differ from one lane of three");
        assert!(trained(1) != three, "three threads gave one thread's bits: the check cannot fail");
    }

    /// A stop from the progress callback ends every member training side by side at its
    /// next epoch and starts no other; the model keeps the members that ran.
    #[test]
    fn a_stop_ends_every_member_side_by_side() {
        let ds = toy(700);
        let s = lanes_settings(4, 30, 2);
        let mut seen = vec![];
        let m = on_threads(2, || {
            train(&ds, &s, &mut |r| {
                seen.push((r.member, r.epoch));
                !(r.member == 0 && r.epoch == 3)
            })
        })
        .unwrap();
        let stop = seen.iter().position(|&r| r == (0, 3)).unwrap();
        // At most the other lane's member reports once more (and is told to stop).
        assert!(seen.len() <= stop + 2, "reports after the stop: {seen:?}");
        assert!(seen.iter().all(|&(member, _)| member < 2), "a member started after the stop: {seen:?}");
        assert_eq!(m.header.members, seen.iter().map(|r| r.0).max().unwrap() + 1);
        assert_eq!(m.header.training.epochs, seen.len());
    }

    /// Weights of another flow, or bytes that are no record, are a typed refusal that
    /// says which part, not a panic or a bare string.
    #[test]
    fn checkpoint_weights_of_another_flow_are_refused_by_name() {
        let small = FlowConfig::new(3, 4, false);
        let other = FlowConfig { blocks: 2, ..FlowConfig::new(5, 4, false) };
        let bytes = record_bytes(&Flow::seeded(&small, &Device::flex(), Some(1)).into_record()).unwrap();
        assert!(record_from(&bytes, &small).is_ok());
        let e = record_from(&bytes, &other).unwrap_err();
        assert!(matches!(e, CheckpointError::Decode { what: "weights", .. }), "{e:?}");
        let e = record_from(b"not a record", &small).unwrap_err();
        assert!(e.to_string().starts_with("the checkpoint's weights do not fit"), "{e}");
    }

    #[test]
    fn batches_split_by_size_and_threads_alike_for_one_and_two() {
        assert_eq!(parts(SPLIT_ROWS - 1, 16), 1);
        assert_eq!(parts(200, 1), 2);
        assert_eq!(parts(200, 2), 2);
        assert_eq!(parts(200, 16), 3);
        assert_eq!(parts(1000, 4), 4);
        assert_eq!(parts(1000, 8), 8);
        assert_eq!(parts(1000, 64), 15);
        assert_eq!(parts(2000, 64), MAX_PARTS);
        assert_eq!(parts(300, 64), 4);
    }
}
