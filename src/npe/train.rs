//! Maximum-likelihood training of the flow on (θ, x) pairs with per-batch noise
//! augmentation, optional group masking, early stopping on a validation split, and the
//! best-validation weights kept. Deterministic for a seed.

use super::{Dataset, FORMAT_VERSION, Header, Npe, NpeError, Result, ThetaMap, TrainingSummary};
use crate::flow::{Flow, FlowConfig};
use crate::stats;
use burn::grad_clipping::GradientClippingConfig;
use burn::module::Module;
use burn::optim::{AdamConfig, GradientsParams, ModuleOptimizer};
use burn::prelude::*;
use burn::store::ModuleRecord;
use rand::seq::SliceRandom;
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use rand_distr::{Distribution, StandardNormal};

/// How to train (`otofit train`'s flags).
#[derive(Clone, Debug)]
pub struct TrainSettings {
    /// An embedding network before the flow's conditioners.
    pub embedding: bool,
    /// Training noise = the dataset's 1× noise model × this.
    pub noise_scale: f64,
    /// Seed of the split, the batches, the noise and the weights.
    pub seed: u64,
    /// Epochs at most, per member.
    pub max_epochs: usize,
    /// Epochs without a better validation loss before stopping (or dropping the rate).
    pub patience: usize,
    /// Rows per batch.
    pub batch: usize,
    /// Adam's learning rate.
    pub lr: f64,
    /// Drop whole feature groups at random (one model for any subset of modalities).
    pub mask_groups: bool,
    /// Also cut each kept group's band at random (up to a quarter of the grid at each end)
    /// and give the network per-feature presence flags: one model for sub-band inputs.
    pub mask_bands: bool,
    /// Fraction of the rows held out for validation (0 < f < 1).
    pub val_fraction: f64,
    /// θ → the flow's space: logit of the box position, or the scale coordinate z-scored.
    pub theta_map: ThetaMap,
    /// The splines' tail bound B (identity outside [−B, B] in the standardised space).
    pub tail_bound: f64,
    /// Residual blocks per conditioner (0: a plain two-hidden-layer MLP).
    pub blocks: usize,
    /// Learning rate halved after this many epochs without a better validation loss
    /// (counted again from each halving); 0: constant.
    pub lr_plateau: usize,
    /// Instead of stopping after `patience` epochs without improvement, divide the
    /// learning rate by 10 and go on, this many times.
    pub lr_drops: usize,
    /// Flows trained from different seeds and averaged as an equal-weight mixture
    /// (wider, better-calibrated joint posteriors; K× the training time).
    pub ensemble: usize,
}

impl Default for TrainSettings {
    fn default() -> Self {
        TrainSettings {
            embedding: true,
            noise_scale: 1.0,
            seed: 0,
            max_epochs: 300,
            patience: 20,
            batch: 200,
            lr: 5e-4,
            mask_groups: false,
            mask_bands: false,
            val_fraction: 0.1,
            theta_map: ThetaMap::Scale,
            tail_bound: 3.0,
            blocks: 0,
            lr_plateau: 8,
            lr_drops: 0,
            ensemble: 1,
        }
    }
}

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
    if s.mask_bands && (!s.mask_groups || n_freq < 8 || f % n_freq != 0) {
        return Err(NpeError::settings(
            "mask-bands",
            "--mask-bands needs --mask-groups and a frequency grid (meta.json frequencies_hz) of at least 8 points",
        ));
    }
    if s.batch == 0 {
        return Err(NpeError::settings("batch", "--batch must be at least 1"));
    }
    if !(s.lr.is_finite() && s.lr > 0.0) {
        return Err(NpeError::settings("lr", format!("--lr must be finite and > 0 (got {})", s.lr)));
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
        x_std.push((sd * sd + (s.noise_scale * ds.noise_std[k]).powi(2)).sqrt().max(1e-9));
    }
    let flags = if s.mask_groups { ds.groups.len() } else { 0 } + if s.mask_bands { f } else { 0 };
    let cfg = FlowConfig { bound: s.tail_bound, blocks: s.blocks, ..FlowConfig::new(d, f + flags, s.embedding) };
    Header {
        format_version: FORMAT_VERSION,
        otofit_version: env!("CARGO_PKG_VERSION").into(),
        params: ds.params.clone(),
        feature_names: ds.feature_names.clone(),
        frequencies_hz: ds.frequencies_hz.clone(),
        groups: ds.groups.clone(),
        mask_groups: s.mask_groups,
        mask_bands: s.mask_bands,
        band_cut_max: if s.mask_bands { n_freq / 4 } else { 0 },
        x_mean,
        x_std,
        theta_map: s.theta_map,
        u_mean,
        u_std,
        noise_std: ds.noise_std.clone(),
        noise_scale: s.noise_scale,
        flow: cfg,
        training: TrainingSummary { seed: s.seed, train_rows: train_idx.len(), val_rows: n_val, ..Default::default() },
        members: 1,
        temperature: 1.0,
        fit_null: None,
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
}

impl Batcher<'_> {
    fn batch(&self, rows: &[usize], rng: &mut ChaCha8Rng) -> (Vec<f32>, Vec<f32>) {
        let (h, ds, s) = (self.header, self.ds, self.s);
        let (d, f, n_freq) = (h.params.len(), h.feature_names.len(), h.frequencies_hz.len());
        let band_cut_max = h.band_cut_max;
        let mut v = Vec::with_capacity(rows.len() * d);
        let mut inp = Vec::with_capacity(rows.len() * h.flow.inputs);
        for &i in rows {
            v.extend((0..d).map(|k| ((self.u_rows[i][k] - h.u_mean[k]) / h.u_std[k]) as f32));
            // Each group kept with probability 1/2, at least one kept.
            let mut keep: Vec<bool> = self.groups.iter().map(|_| rng.random::<bool>()).collect();
            if !keep.is_empty() && !keep.iter().any(|&k| k) {
                let j = rng.random_range(0..keep.len());
                keep[j] = true;
            }
            let start = inp.len();
            for k in 0..f {
                let e: f64 = StandardNormal.sample(rng);
                inp.push(((ds.x[i][k] + s.noise_scale * ds.noise_std[k] * e - h.x_mean[k]) / h.x_std[k]) as f32);
            }
            let mut here = vec![true; f];
            for (g, &on) in self.groups.iter().zip(&keep) {
                // A kept group loses the ends of its band with probability 1/2.
                let (lo, hi) = if on && s.mask_bands && rng.random::<bool>() {
                    (rng.random_range(0..=band_cut_max), n_freq - 1 - rng.random_range(0..=band_cut_max))
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
            inp.extend(keep.iter().map(|&on| if on { 1.0 } else { 0.0 }));
            if s.mask_bands {
                inp.extend(here.iter().map(|&on| if on { 1.0f32 } else { 0.0 }));
            }
        }
        (v, inp)
    }
}

/// Mean negative log-likelihood of one batch.
fn loss_of(flow: &Flow, cfg: &FlowConfig, v: Vec<f32>, inp: Vec<f32>, b: usize, dev: &Device) -> Tensor<1> {
    let vt = Tensor::<2>::from_data(TensorData::new(v, [b, cfg.dim]), dev);
    let it = Tensor::<2>::from_data(TensorData::new(inp, [b, cfg.inputs]), dev);
    let ctx = flow.embed(it);
    flow.log_prob(cfg, vt, ctx).mean().neg()
}

/// A one-element loss tensor as f64 (NaN when it cannot be read).
fn scalar(loss: Tensor<1>) -> f64 {
    loss.try_into_vec_as::<f32>().map(|v| v[0] as f64).unwrap_or(f64::NAN)
}

/// What one member's training left: its best weights and when, and its epochs.
struct Member {
    best_val_loss: f64,
    best_epoch: usize,
    record: Option<ModuleRecord>,
    epochs: usize,
    /// The progress callback asked to stop.
    stopped: bool,
}

/// Everything a member's training reads.
struct Run<'a> {
    s: &'a TrainSettings,
    cfg: &'a FlowConfig,
    batcher: Batcher<'a>,
    train_idx: &'a [usize],
    /// Validation inputs with one fixed noise draw: (v, input, rows).
    val_batches: Vec<(Vec<f32>, Vec<f32>, usize)>,
    n_val: usize,
    /// The autodiff device the member trains on.
    device: Device,
}

impl Run<'_> {
    /// One pass over the training rows; the mean loss of the finite batches.
    fn epoch(
        &self,
        mut flow: Flow,
        opt: &mut ModuleOptimizer,
        lr: f64,
        order: &mut [usize],
        rng: &mut ChaCha8Rng,
    ) -> (Flow, f64) {
        order.shuffle(rng);
        let (mut sum, mut count) = (0.0, 0);
        for rows in order.chunks(self.s.batch) {
            let (v, inp) = self.batcher.batch(rows, rng);
            let loss = loss_of(&flow, self.cfg, v, inp, rows.len(), &self.device);
            let l = scalar(loss.clone());
            if !l.is_finite() {
                continue; // a rare bad batch: skip rather than poison the weights
            }
            sum += l * rows.len() as f64;
            count += rows.len();
            let grads = GradientsParams::from_grads(loss.backward(), &flow);
            flow = opt.step(lr, flow, grads);
        }
        (flow, sum / count.max(1) as f64)
    }

    /// Validation loss of the current weights (without autodiff).
    fn validate(&self, valid: &Flow) -> f64 {
        let plain = Device::flex();
        let mut vsum = 0.0;
        for (v, inp, b) in &self.val_batches {
            vsum += scalar(loss_of(valid, self.cfg, v.clone(), inp.clone(), *b, &plain)) * *b as f64;
        }
        vsum / self.n_val as f64
    }

    /// Trains ensemble member `member` from its own seed, keeping its best weights; the
    /// rate is halved on plateaus and divided by 10 instead of stopping `lr_drops` times.
    fn member(&self, member: usize, rng: &mut ChaCha8Rng, progress: &mut dyn FnMut(&EpochReport) -> bool) -> Member {
        let (s, device) = (self.s, &self.device);
        // The backend's RNG is process-wide: seeding and initialising under one lock keeps
        // a seed's weights the same when other trainings run beside this one.
        let mut flow = {
            static INIT: std::sync::Mutex<()> = std::sync::Mutex::new(());
            let _one_at_a_time = INIT.lock().unwrap_or_else(|e| e.into_inner());
            device.seed(s.seed.wrapping_add(member as u64));
            Flow::new(self.cfg, device)
        };
        let mut opt = AdamConfig::new().with_grad_clipping(Some(GradientClippingConfig::Norm(5.0))).init();
        let mut out = Member { best_val_loss: f64::INFINITY, best_epoch: 0, record: None, epochs: 0, stopped: false };
        let mut order = self.train_idx.to_vec();
        let (mut lr, mut last_change, mut last_drop, mut drops) = (s.lr, 0, 0, 0);
        for epoch in 1..=s.max_epochs {
            let t0 = std::time::Instant::now();
            out.epochs += 1;
            let train_loss;
            (flow, train_loss) = self.epoch(flow, &mut opt, lr, &mut order, rng);
            let valid = flow.valid();
            let val_loss = self.validate(&valid);
            if val_loss < out.best_val_loss {
                (out.best_val_loss, out.best_epoch, out.record) = (val_loss, epoch, Some(valid.into_record()));
            }
            let seconds = t0.elapsed().as_secs_f64();
            let report = EpochReport { member, epoch, train_loss, val_loss, best_val_loss: out.best_val_loss, seconds };
            if !progress(&report) {
                out.stopped = true;
                break;
            }
            if s.lr_plateau > 0 && epoch - out.best_epoch.max(last_change) >= s.lr_plateau {
                lr *= 0.5;
                last_change = epoch;
            }
            if epoch - out.best_epoch.max(last_drop) >= s.patience {
                if drops == s.lr_drops {
                    break;
                }
                drops += 1;
                lr *= 0.1;
                (last_drop, last_change) = (epoch, epoch);
            }
        }
        out
    }
}

/// Trains a model. `progress` gets one report per epoch and returns `false` to stop early
/// (the best weights so far are kept).
pub fn train(ds: &Dataset, s: &TrainSettings, progress: &mut dyn FnMut(&EpochReport) -> bool) -> Result<Npe> {
    let start = std::time::Instant::now();
    check(ds, s)?;
    let n = ds.theta.len();
    let mut rng = ChaCha8Rng::seed_from_u64(s.seed);
    let mut idx: Vec<usize> = (0..n).collect();
    idx.shuffle(&mut rng);
    let n_val = ((n as f64 * s.val_fraction).round() as usize).clamp(1, n - 1);
    let (val_idx, train_idx) = idx.split_at(n_val);
    let u_rows = u_rows(ds, s.theta_map);
    let header = standardise(ds, s, &u_rows, train_idx, n_val);
    // The network is built from the settings as computed (the header keeps its copy).
    let cfg = header.flow.clone();
    // The header as a checkpoint reads it back (serde_json may move a float by one ulp),
    // so that a saved and reloaded model draws exactly what the trained one draws.
    let encode = |e: serde_json::Error| NpeError::Encode { what: "header", why: e.to_string() };
    let header: Header = serde_json::from_slice(&serde_json::to_vec(&header).map_err(encode)?).map_err(encode)?;
    let groups = if s.mask_groups { ds.groups.clone() } else { vec![] };
    let batcher = Batcher { ds, s, header: &header, u_rows: &u_rows, groups: &groups };
    let mut val_rng = ChaCha8Rng::seed_from_u64(s.seed ^ 0x5EED);
    let val_batches = val_idx
        .chunks(1000)
        .map(|c| {
            let (v, i) = batcher.batch(c, &mut val_rng);
            (v, i, c.len())
        })
        .collect();
    let run = Run { s, cfg: &cfg, batcher, train_idx, val_batches, n_val, device: Device::flex().autodiff() };

    // Member 0 uses the seed and the batch stream exactly as a single model does, so a
    // one-member ensemble is the single model.
    let mut records = Vec::new();
    let (mut epochs, mut best_epoch, mut best_sum) = (0, 0, 0.0);
    for member in 0..s.ensemble.max(1) {
        if member > 0 {
            rng = ChaCha8Rng::seed_from_u64(s.seed ^ (0x9E37_79B9_7F4A_7C15u64.wrapping_mul(member as u64)));
        }
        let m = run.member(member, &mut rng, progress);
        epochs += m.epochs;
        let Some(record) = m.record else { return Err(NpeError::NoFiniteLoss { member }) };
        records.push(record);
        if member == 0 {
            best_epoch = m.best_epoch;
        }
        best_sum += m.best_val_loss;
        if m.stopped {
            break;
        }
    }
    // Summary: epochs summed over members; best epoch of member 0; mean best val loss.
    let mut header = header;
    header.members = records.len();
    header.training.epochs = epochs;
    header.training.best_epoch = best_epoch;
    header.training.best_val_loss = best_sum / records.len() as f64;
    header.training.wall_seconds = start.elapsed().as_secs_f64();
    Ok(Npe::from_parts(header, records))
}
