//! Maximum-likelihood training of the flow on (θ, x) pairs with per-batch noise
//! augmentation, optional group masking, early stopping on a validation split, and the
//! best-validation weights kept. Deterministic for a seed.

use super::{Dataset, FORMAT_VERSION, Header, Npe, ThetaMap, TrainingSummary};
use crate::flow::{Flow, FlowConfig};
use anyhow::{Result, bail};
use burn::grad_clipping::GradientClippingConfig;
use burn::module::Module;
use burn::optim::{AdamConfig, GradientsParams};
use burn::prelude::*;
use burn::store::ModuleRecord;
use rand::seq::SliceRandom;
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use rand_distr::{Distribution, StandardNormal};

#[derive(Clone, Debug)]
pub struct TrainSettings {
    pub embedding: bool,
    /// Training noise = the dataset's 1× noise model × this.
    pub noise_scale: f64,
    pub seed: u64,
    pub max_epochs: usize,
    pub patience: usize,
    pub batch: usize,
    pub lr: f64,
    pub mask_groups: bool,
    /// Also cut each kept group's band at random (up to a quarter of the grid at each end)
    /// and give the network per-feature presence flags: one model for sub-band inputs.
    pub mask_bands: bool,
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

#[derive(Clone, Debug)]
pub struct EpochReport {
    /// Ensemble member (0 for a single model).
    pub member: usize,
    pub epoch: usize,
    pub train_loss: f64,
    pub val_loss: f64,
    pub best_val_loss: f64,
    pub seconds: f64,
}

fn mean_std(rows: &[Vec<f64>], k: usize) -> (f64, f64) {
    let n = rows.len() as f64;
    let m = rows.iter().map(|r| r[k]).sum::<f64>() / n;
    let v = rows.iter().map(|r| (r[k] - m).powi(2)).sum::<f64>() / n;
    (m, v.sqrt())
}

/// Trains a model. `progress` gets one report per epoch and returns `false` to stop early
/// (the best weights so far are kept).
pub fn train(ds: &Dataset, s: &TrainSettings, progress: &mut dyn FnMut(&EpochReport) -> bool) -> Result<Npe> {
    let start = std::time::Instant::now();
    let (n, d, f) = (ds.theta.len(), ds.params.len(), ds.feature_names.len());
    if n < 20 {
        bail!("{n} usable rows: too few to train (need at least 20)");
    }
    if s.mask_groups && ds.groups.is_empty() {
        bail!("--mask-groups needs feature groups (declared in meta.json)");
    }
    let n_freq = ds.frequencies_hz.len();
    if s.mask_bands && (!s.mask_groups || n_freq < 8 || f % n_freq != 0) {
        bail!("--mask-bands needs --mask-groups and a frequency grid (meta.json frequencies_hz) of at least 8 points");
    }
    let band_cut_max = if s.mask_bands { n_freq / 4 } else { 0 };
    let mut rng = ChaCha8Rng::seed_from_u64(s.seed);
    let mut idx: Vec<usize> = (0..n).collect();
    idx.shuffle(&mut rng);
    let n_val = ((n as f64 * s.val_fraction).round() as usize).clamp(1, n - 1);
    let (val_idx, train_idx) = idx.split_at(n_val);

    // Standardisation from the training rows; x spread includes the training noise.
    let u_rows: Vec<Vec<f64>> = ds
        .theta
        .iter()
        .map(|t| {
            ds.params
                .iter()
                .zip(t)
                .map(|(p, v)| match s.theta_map {
                    ThetaMap::Logit => p.to_u(*v),
                    ThetaMap::Scale => p.to_t(*v),
                })
                .collect()
        })
        .collect();
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
    let groups = if s.mask_groups { ds.groups.clone() } else { vec![] };
    let flags = groups.len() + if s.mask_bands { f } else { 0 };
    let cfg = FlowConfig { bound: s.tail_bound, blocks: s.blocks, ..FlowConfig::new(d, f + flags, s.embedding) };
    let header = Header {
        format_version: FORMAT_VERSION,
        otofit_version: env!("CARGO_PKG_VERSION").into(),
        params: ds.params.clone(),
        feature_names: ds.feature_names.clone(),
        frequencies_hz: ds.frequencies_hz.clone(),
        groups: ds.groups.clone(),
        mask_groups: s.mask_groups,
        mask_bands: s.mask_bands,
        band_cut_max,
        x_mean,
        x_std,
        theta_map: s.theta_map,
        u_mean,
        u_std,
        noise_std: ds.noise_std.clone(),
        noise_scale: s.noise_scale,
        flow: cfg.clone(),
        training: TrainingSummary { seed: s.seed, train_rows: train_idx.len(), val_rows: n_val, ..Default::default() },
        members: 1,
        temperature: 1.0,
        fit_null: None,
    };

    // The header as a checkpoint reads it back (serde_json may move a float by one ulp),
    // so that a saved and reloaded model draws exactly what the trained one draws.
    let header: Header = serde_json::from_slice(&serde_json::to_vec(&header)?)?;
    let device = Device::flex().autodiff();

    // One batch: v (standardised u) and the network input with fresh noise and masks.
    let batch = |rows: &[usize], rng: &mut ChaCha8Rng| -> (Vec<f32>, Vec<f32>) {
        let h = &header;
        let mut v = Vec::with_capacity(rows.len() * d);
        let mut inp = Vec::with_capacity(rows.len() * cfg.inputs);
        for &i in rows {
            v.extend((0..d).map(|k| ((u_rows[i][k] - h.u_mean[k]) / h.u_std[k]) as f32));
            // Each group kept with probability 1/2, at least one kept.
            let mut keep: Vec<bool> = groups.iter().map(|_| rng.random::<bool>()).collect();
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
            for (g, &on) in groups.iter().zip(&keep) {
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
    };
    let loss_of = |flow: &Flow, v: Vec<f32>, inp: Vec<f32>, b: usize, dev: &Device| -> Tensor<1> {
        let vt = Tensor::<2>::from_data(TensorData::new(v, [b, d]), dev);
        let it = Tensor::<2>::from_data(TensorData::new(inp, [b, cfg.inputs]), dev);
        let ctx = flow.embed(it);
        flow.log_prob(&cfg, vt, ctx).mean().neg()
    };

    // Validation inputs with one fixed noise draw.
    let mut val_rng = ChaCha8Rng::seed_from_u64(s.seed ^ 0x5EED);
    let val_batches: Vec<(Vec<f32>, Vec<f32>, usize)> = val_idx
        .chunks(1000)
        .map(|c| {
            let (v, i) = batch(c, &mut val_rng);
            (v, i, c.len())
        })
        .collect();

    // Member 0 uses the seed and the batch stream exactly as a single model does, so a
    // one-member ensemble is the single model.
    let mut records = Vec::new();
    let (mut epochs, mut best_epoch, mut best_sum) = (0, 0, 0.0);
    let mut stopped = false;
    for member in 0..s.ensemble.max(1) {
        if stopped {
            break;
        }
        // The backend's RNG is process-wide: seeding and initialising under one lock keeps
        // a seed's weights the same when other trainings run beside this one.
        let mut flow = {
            static INIT: std::sync::Mutex<()> = std::sync::Mutex::new(());
            let _one_at_a_time = INIT.lock().unwrap_or_else(|e| e.into_inner());
            device.seed(s.seed.wrapping_add(member as u64));
            Flow::new(&cfg, &device)
        };
        let mut opt = AdamConfig::new().with_grad_clipping(Some(GradientClippingConfig::Norm(5.0))).init();
        if member > 0 {
            rng = ChaCha8Rng::seed_from_u64(s.seed ^ (0x9E37_79B9_7F4A_7C15u64.wrapping_mul(member as u64)));
        }
        let mut best: (f64, usize, Option<ModuleRecord>) = (f64::INFINITY, 0, None);
        let mut train_order = train_idx.to_vec();
        let (mut lr, mut last_change, mut last_drop, mut drops) = (s.lr, 0, 0, 0);
        for epoch in 1..=s.max_epochs {
            let t0 = std::time::Instant::now();
            epochs += 1;
            train_order.shuffle(&mut rng);
            let (mut sum, mut count) = (0.0, 0);
            for rows in train_order.chunks(s.batch) {
                let (v, inp) = batch(rows, &mut rng);
                let loss = loss_of(&flow, v, inp, rows.len(), &device);
                let l = loss.clone().try_into_vec_as::<f32>().map(|v| v[0] as f64).unwrap_or(f64::NAN);
                if !l.is_finite() {
                    continue; // a rare bad batch: skip rather than poison the weights
                }
                sum += l * rows.len() as f64;
                count += rows.len();
                let grads = GradientsParams::from_grads(loss.backward(), &flow);
                flow = opt.step(lr, flow, grads);
            }
            let valid = flow.valid();
            let plain = Device::flex();
            let mut vsum = 0.0;
            for (v, inp, b) in &val_batches {
                let l = loss_of(&valid, v.clone(), inp.clone(), *b, &plain);
                vsum += l.try_into_vec_as::<f32>().map(|v| v[0] as f64).unwrap_or(f64::NAN) * *b as f64;
            }
            let val_loss = vsum / n_val as f64;
            if val_loss < best.0 {
                best = (val_loss, epoch, Some(valid.into_record()));
            }
            let report = EpochReport {
                member,
                epoch,
                train_loss: sum / count.max(1) as f64,
                val_loss,
                best_val_loss: best.0,
                seconds: t0.elapsed().as_secs_f64(),
            };
            if !progress(&report) {
                stopped = true;
                break;
            }
            if s.lr_plateau > 0 && epoch - best.1.max(last_change) >= s.lr_plateau {
                lr *= 0.5;
                last_change = epoch;
            }
            if epoch - best.1.max(last_drop) >= s.patience {
                if drops == s.lr_drops {
                    break;
                }
                drops += 1;
                lr *= 0.1;
                (last_drop, last_change) = (epoch, epoch);
            }
        }
        let Some(record) = best.2 else { bail!("training produced no finite validation loss (member {member})") };
        records.push(record);
        if member == 0 {
            best_epoch = best.1;
        }
        best_sum += best.0;
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
