//! Neural posterior estimation: prior bijection, standardisation, training, posterior
//! sampling / density / MAP / summaries, calibration, and the checkpoint file.
//! Synchronous; progress and cancellation go through a callback.

#![warn(missing_docs)]

mod adam;
pub mod calibrate;
pub mod data;
mod error;
pub mod model_error;
pub mod normal;
pub mod prior;
mod train;

pub use data::{Dataset, Group};
pub use error::{CheckpointError, NpeError, ObservationError};
pub use model_error::ModelError;
pub use prior::{Param, Scale};
pub use train::{
    CHECKPOINT_COST_SHARE, Checkpointing, EpochReport, TrainSettings, Trained, checkpoint_epochs, remove_checkpoint,
    train, train_checkpointed, validation_split,
};

use crate::dataset::FileError;
use crate::flow::plain::{Bound, PlainFlow};
use crate::flow::{Flow, FlowConfig};
use crate::stats;
use burn::module::Module;
use burn::prelude::*;
use burn::store::ModuleRecord;
use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;
use rand_distr::{Distribution, StandardNormal};
use rayon::prelude::*;
use serde::{Deserialize, Serialize};
use std::path::Path;

/// Results of this layer.
pub type Result<T, E = NpeError> = std::result::Result<T, E>;

/// 2: members stored as length-prefixed records (an ensemble); 1 (one record) is read too.
pub const FORMAT_VERSION: u32 = 2;
const MAGIC: &[u8; 11] = b"OTOFIT-NPE\n";

/// Everything about a model except its weights (the checkpoint's JSON header).
#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct Header {
    /// Checkpoint format ([`FORMAT_VERSION`]; 1 is read too).
    pub format_version: u32,
    /// The otofit version that wrote it.
    pub otofit_version: String,
    /// The prior box, one per parameter.
    pub params: Vec<Param>,
    /// One name per input feature.
    pub feature_names: Vec<String>,
    /// The features' frequency grid (empty when there is none).
    pub frequencies_hz: Vec<f64>,
    /// Feature groups (modalities).
    pub groups: Vec<Group>,
    /// Whether the network takes group masks (accepts any subset of groups).
    pub mask_groups: bool,
    /// Whether the network also takes one presence flag per feature, trained with the
    /// ends of each group's band cut away (up to `band_cut_max` grid points at each end):
    /// it then accepts observations covering a sub-band, never extrapolated.
    #[serde(default)]
    pub mask_bands: bool,
    /// Grid points a band may lose at each end (band-masked models).
    #[serde(default)]
    pub band_cut_max: usize,
    /// Feature means of the training rows.
    pub x_mean: Vec<f64>,
    /// Feature spreads of the training rows, training noise included.
    pub x_std: Vec<f64>,
    /// How θ maps to the flow's space before standardisation (`logit` in checkpoints
    /// written before the choice existed).
    #[serde(default)]
    pub theta_map: ThetaMap,
    /// Means of θ in the flow's space.
    pub u_mean: Vec<f64>,
    /// Spreads of θ in the flow's space.
    pub u_std: Vec<f64>,
    /// 1× noise model and the scale it was trained with.
    pub noise_std: Vec<f64>,
    /// The multiple of `noise_std` the model was trained with.
    pub noise_scale: f64,
    /// The smooth simulator-to-ear discrepancy added to the training inputs beside the
    /// noise (`None`: the simulator taken as exact).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub model_error: Option<ModelError>,
    /// The flow's architecture.
    pub flow: FlowConfig,
    /// How training went.
    pub training: TrainingSummary,
    /// Flows in the equal-weight ensemble (trained from different seeds).
    #[serde(default = "one")]
    pub members: usize,
    /// Standard deviation of the flow's base distribution at inference (1 = as trained),
    /// set by `otofit calibrate --tune` so that held-out coverage matches its level.
    #[serde(default = "unit_temperature")]
    pub temperature: f64,
    /// Null distribution of the fit check, measured on held-out simulations; `None` for
    /// models that have not been calibrated (their fit check says so).
    #[serde(default)]
    pub fit_null: Option<FitNull>,
    /// Null distribution of the diagnose workflow's alarm statistics, measured once on
    /// effect-free simulations (`otofit calibrate --diagnose-null`) so that a diagnosis
    /// need not re-measure it per ear; `None` when never measured.
    #[serde(default)]
    pub diagnose_null: Option<DiagnoseNull>,
    /// Whether a full-measure flow follows the members ([`Npe::answering`]): a second,
    /// unmasked model that answers observations with every feature present, sharper there
    /// than a network that must also answer every subset.
    #[serde(default, skip_serializing_if = "std::ops::Not::not")]
    pub full_measure_flow: bool,
    /// The feature groups a measure-set flow was trained on alone: every other group's
    /// features were zeroed in training and are ignored when it answers. Empty for a flow
    /// of every measure, and for a flow trained with masks.
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub measures: Vec<String>,
    /// How many measure-set flows follow the full-measure flow ([`Npe::answering`]).
    #[serde(default, skip_serializing_if = "is_zero")]
    pub measure_set_flows: usize,
    /// A measure-set flow trained on its groups from this frequency up (0: the whole
    /// band), as one device exports them (a wideband tympanometer from 226 Hz): it reads
    /// no lower point and answers ears given exactly that band.
    #[serde(default, skip_serializing_if = "is_zero_hz")]
    pub from_hz: f64,
}

fn is_zero(n: &usize) -> bool {
    *n == 0
}

fn is_zero_hz(hz: &f64) -> bool {
    *hz == 0.0
}

/// Measure-set flows a file may hold.
const MAX_MEASURE_SETS: usize = 8;

/// The first 8 bytes as a little-endian u64's bytes (zeros past the end).
fn le8(b: &[u8]) -> [u8; 8] {
    let mut out = [0u8; 8];
    let k = b.len().min(8);
    out[..k].copy_from_slice(&b[..k]);
    out
}

/// A u64-LE length and that many bytes, and what follows; `None` when the length exceeds
/// the bytes (lengths come from the file: compared without overflowing).
fn length_prefixed(b: &[u8]) -> Option<(&[u8], &[u8])> {
    let n = u64::from_le_bytes(le8(b.get(..8)?));
    let n = usize::try_from(n).ok().filter(|&n| n <= b.len() - 8)?;
    Some((&b[8..8 + n], &b[8 + n..]))
}

impl Header {
    /// The features given when the named feature groups are measured (every feature when
    /// `names` is empty); a name that is not one of the model's groups is refused by name.
    pub fn features_of_groups<S: AsRef<str>>(&self, names: &[S]) -> Result<Vec<bool>, ObservationError> {
        let mut given = vec![names.is_empty(); self.feature_names.len()];
        for name in names.iter().map(|n| n.as_ref().trim()) {
            let Some(g) = self.groups.iter().find(|g| g.name == name) else {
                let known: Vec<&str> = self.groups.iter().map(|g| g.name.as_str()).collect();
                return Err(ObservationError::UnknownGroup { name: name.to_string(), known: known.join(", ") });
            };
            g.features.iter().for_each(|&i| given[i] = true);
        }
        Ok(given)
    }

    /// [`Header::features_of_groups`] from `from_hz` up, as a device that exports from
    /// 226 Hz gives them: features are measure-major on the grid (feature i lies at grid
    /// point i mod n), and those below `from_hz` are left out.
    pub fn features_given<S: AsRef<str>>(&self, names: &[S], from_hz: f64) -> Result<Vec<bool>, ObservationError> {
        let mut given = self.features_of_groups(names)?;
        let grid = &self.frequencies_hz;
        for (i, g) in given.iter_mut().enumerate() {
            *g &= grid.get(i % grid.len().max(1)).is_none_or(|&hz| hz >= from_hz);
        }
        Ok(given)
    }

    /// The sampler of the model error the model was trained with, if any.
    pub fn model_error_sampler(&self) -> Result<Option<model_error::Discrepancy>> {
        self.model_error.map(|m| m.sampler(&self.frequencies_hz, &self.noise_std)).transpose()
    }

    /// Checks every field read from a file against what the code can use, naming the
    /// first field at fault.
    pub fn validate(&self) -> Result<(), CheckpointError> {
        if self.format_version != FORMAT_VERSION && self.format_version != 1 {
            return Err(CheckpointError::Format(self.format_version));
        }
        let (d, f) = (self.params.len(), self.feature_names.len());
        let g = if self.mask_groups { self.groups.len() } else { 0 } + if self.mask_bands { f } else { 0 };
        let shapes_ok = self.flow.dim == d
            && self.flow.inputs == f + g
            && self.x_mean.len() == f
            && self.x_std.len() == f
            && self.noise_std.len() == f
            && self.u_mean.len() == d
            && self.u_std.len() == d;
        if !shapes_ok {
            return Err(CheckpointError::Shapes { params: d, features: f });
        }
        self.flow.validate()?;
        if self.mask_bands && (self.frequencies_hz.is_empty() || self.band_cut_max >= self.frequencies_hz.len()) {
            return Err(CheckpointError::field(
                "band_cut_max",
                "band masks need a frequency grid longer than band_cut_max",
            ));
        }
        if !(self.temperature.is_finite() && (0.1..=10.0).contains(&self.temperature)) {
            return Err(CheckpointError::field("temperature", format!("{} is outside 0.1..=10", self.temperature)));
        }
        for p in &self.params {
            p.validate().map_err(|e| CheckpointError::field("params", e.to_string()))?;
        }
        if let Some(n) = &self.diagnose_null {
            n.validate()?;
        }
        self.validate_measures()?;
        self.model_error_sampler().map_err(|e| CheckpointError::field("model_error", e.to_string()))?;
        let finite = |v: &[f64]| v.iter().all(|x| x.is_finite());
        let positive = |v: &[f64]| v.iter().all(|x| x.is_finite() && *x > 0.0);
        let checks: [(bool, &'static str, &str); 8] = [
            (finite(&self.x_mean), "x_mean", "must be finite"),
            (positive(&self.x_std), "x_std", "must be finite and > 0"),
            (finite(&self.u_mean), "u_mean", "must be finite"),
            (positive(&self.u_std), "u_std", "must be finite and > 0"),
            (self.noise_std.iter().all(|x| x.is_finite() && *x >= 0.0), "noise_std", "must be finite and ≥ 0"),
            (self.noise_scale.is_finite() && self.noise_scale >= 0.0, "noise_scale", "must be finite and ≥ 0"),
            (self.groups.iter().all(|g| g.features.iter().all(|&i| i < f)), "groups", "feature index out of range"),
            (self.format_version == 1 || (1..=64).contains(&self.members), "members", "must be 1..=64"),
        ];
        match checks.iter().find(|(ok, _, _)| !ok) {
            Some(&(_, field, why)) => Err(CheckpointError::field(field, why)),
            None => Ok(()),
        }
    }
}

impl Header {
    /// A measure-set flow's groups name distinct groups of its own, fewer than all, and
    /// go without masks; a file holds at most [`MAX_MEASURE_SETS`] such flows.
    fn validate_measures(&self) -> Result<(), CheckpointError> {
        let field = |why: String| Err(CheckpointError::field("measures", why));
        if self.measure_set_flows > MAX_MEASURE_SETS {
            return Err(CheckpointError::field(
                "measure_set_flows",
                format!("{} exceeds {MAX_MEASURE_SETS}", self.measure_set_flows),
            ));
        }
        let top = self.frequencies_hz.iter().copied().fold(f64::NAN, f64::max);
        if self.from_hz != 0.0
            && (self.measures.is_empty() || self.mask_bands || !(self.from_hz > 0.0 && self.from_hz < top))
        {
            return Err(CheckpointError::field(
                "from_hz",
                format!(
                    "{} Hz: a band's start is for a measure-set flow without band masks, below the grid's top",
                    self.from_hz
                ),
            ));
        }
        if self.measures.is_empty() {
            return Ok(());
        }
        if self.mask_groups {
            return field("a measure-set flow is trained without group masks".into());
        }
        for (k, m) in self.measures.iter().enumerate() {
            if !self.groups.iter().any(|g| &g.name == m) {
                return field(format!("'{m}' is not one of the model's feature groups"));
            }
            if self.measures[..k].contains(m) {
                return field(format!("'{m}' is named twice"));
            }
        }
        if self.measures.len() >= self.groups.len() {
            return field("names every group (a flow of every measure names none)".into());
        }
        Ok(())
    }

    /// Which features belong to a feature group (the others must always be given).
    fn grouped_features(&self) -> Vec<bool> {
        let f = self.feature_names.len();
        let mut grouped = vec![false; f];
        for &i in self.groups.iter().flat_map(|g| &g.features).filter(|&&i| i < f) {
            grouped[i] = true;
        }
        grouped
    }

    /// The features a measure-set flow reads: its groups' and those outside every group;
    /// `None` for a flow that reads them all.
    pub fn measure_features(&self) -> Option<Vec<bool>> {
        if self.measures.is_empty() {
            return None;
        }
        // Its groups as a device gives them from `from_hz` up, and every ungrouped feature.
        let mut read = self.features_given(&self.measures, self.from_hz).ok()?;
        let grouped = self.grouped_features();
        read.iter_mut().zip(grouped).filter(|(_, g)| !g).for_each(|(r, _)| *r = true);
        Some(read)
    }
}

/// The map from θ to the space the flow is trained in (then z-scored).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum ThetaMap {
    /// Logit of each parameter's position in its box: every draw lands inside the box.
    #[default]
    Logit,
    /// The scale coordinate only (log10 on log parameters), as sbi z-scores θ: the
    /// posterior keeps its shape near the box's edges; draws outside the box are
    /// rejected at sampling.
    Scale,
}

fn one() -> usize {
    1
}

fn unit_temperature() -> f64 {
    1.0
}

/// What the fit check and the input-typicality check compare an observation against:
/// quantiles of their statistics over held-out simulations of the model's own simulator
/// (with its training noise), so that the false-alarm rate is measured, not assumed.
#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct FitNull {
    /// The check's level (e.g. 0.99: 1 % of the model's own ears fail it). With `joint`,
    /// the thresholds are set together so that the check as a whole (any statistic over
    /// its threshold) fails that share; without, each is its statistic's own quantile.
    pub quantile: f64,
    /// The thresholds were set together (false in files calibrated before this existed:
    /// their check fails up to three times the share `quantile` says).
    #[serde(default)]
    pub joint: bool,
    /// Threshold on the posterior-predictive reduced χ².
    pub reduced_chi2: f64,
    /// Threshold on the input score: mean of squared standardised features.
    pub input_score: f64,
    /// Threshold on the worst measure's own reduced χ² (a misfit confined to one measure
    /// is diluted in the overall mean); 0 in checkpoints written before it existed.
    #[serde(default)]
    pub measure_chi2: f64,
    /// Held-out cases and posterior draws per case behind the thresholds.
    pub cases: usize,
    /// Posterior draws per case.
    pub draws: usize,
    /// The same thresholds when only some feature groups are given (models trained with
    /// group masks; e.g. wideband tympanometry without stapes velocity).
    #[serde(default)]
    pub subsets: Vec<SubsetNull>,
}

/// Fit-check thresholds for one subset of feature groups (names sorted).
#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct SubsetNull {
    /// The groups given, names sorted.
    pub groups: Vec<String>,
    /// Threshold on the posterior-predictive reduced χ².
    pub reduced_chi2: f64,
    /// Threshold on the worst measure's reduced χ².
    pub measure_chi2: f64,
    /// Threshold on the input score.
    pub input_score: f64,
}

/// The diagnose workflow's alarm thresholds, measured on effect-free simulations of the
/// model's own simulator pushed through the same fit and candidate ranking as an ear.
#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct DiagnoseNull {
    /// The quantile used as threshold.
    pub quantile: f64,
    /// Effect-free cases behind the thresholds.
    pub cases: usize,
    /// Posterior draws re-simulated per case for its predictive check.
    pub draws: usize,
    /// The candidate effects ranked per case: the thresholds hold for these or any
    /// subset of them (a best drop over fewer candidates is never larger).
    pub candidates: Vec<String>,
    /// The thresholds per set of feature groups given (names sorted).
    pub subsets: Vec<DiagnoseSubsetNull>,
    /// Version of the candidate fit the thresholds were measured with (0: not recorded).
    /// A better fit moves the best drop, so a diagnosis uses only a null of its own fit.
    #[serde(default)]
    pub fit_version: u32,
}

/// Diagnose thresholds for one set of feature groups.
#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct DiagnoseSubsetNull {
    /// The groups given, names sorted.
    pub groups: Vec<String>,
    /// Threshold on the base model's posterior-predictive reduced χ².
    pub base_reduced_chi2: f64,
    /// Threshold on the best candidate's χ² drop.
    pub best_drop: f64,
}

impl DiagnoseNull {
    /// Checks the values read from a file, naming the first at fault.
    fn validate(&self) -> Result<(), CheckpointError> {
        let field = |why: String| Err(CheckpointError::field("diagnose_null", why));
        if !(self.quantile > 0.0 && self.quantile < 1.0) {
            return field(format!("quantile {} is outside (0, 1)", self.quantile));
        }
        if self.cases == 0 || self.draws == 0 {
            return field("cases and draws must be at least 1".into());
        }
        for s in &self.subsets {
            // +∞ when every case failed; a best drop may be below 0 (no candidate helps).
            if s.base_reduced_chi2.is_nan() || s.base_reduced_chi2 < 0.0 || s.best_drop.is_nan() {
                return field(format!("thresholds of {:?} must be numbers (χ² ≥ 0)", s.groups));
            }
        }
        Ok(())
    }
}

/// How a model was trained (stored in its header).
#[derive(Clone, Debug, Default, Serialize, Deserialize)]
pub struct TrainingSummary {
    /// Epochs run, summed over ensemble members.
    pub epochs: usize,
    /// Epoch of member 0's best validation loss.
    pub best_epoch: usize,
    /// Mean best validation loss over members.
    pub best_val_loss: f64,
    /// Training rows.
    pub train_rows: usize,
    /// Validation rows.
    pub val_rows: usize,
    /// Wall time of the training.
    pub wall_seconds: f64,
    /// The training seed.
    pub seed: u64,
}

/// A trained posterior estimator, ready to answer on the CPU (`flex`) backend.
pub struct Npe {
    /// Everything but the weights.
    pub header: Header,
    /// The ensemble's flows (one for a single model), as trained and stored by burn.
    flows: Vec<Flow>,
    /// The same weights for inference in plain Rust (flow::plain).
    plains: Vec<PlainFlow>,
    /// The full-measure flow, when the file holds one ([`Npe::answering`]).
    full: Option<Box<Npe>>,
    /// The measure-set flows the file holds ([`Npe::answering`]).
    sets: Vec<Npe>,
}

/// The members bound to one observation: an equal-weight mixture.
struct Mixture<'a> {
    members: Vec<Bound<'a>>,
}

impl Mixture<'_> {
    /// log q(v) = log mean_k q_k(v).
    fn log_prob(&self, v: &[f64]) -> Vec<f64> {
        self.mix(v, None)
    }

    /// The mixture density, reusing member `known.0`'s densities `known.1` when given.
    fn mix(&self, v: &[f64], known: Option<(usize, Vec<f64>)>) -> Vec<f64> {
        let mut known = known;
        let mut all: Vec<Vec<f64>> = Vec::with_capacity(self.members.len());
        for (k, m) in self.members.iter().enumerate() {
            all.push(match known.take_if(|(j, _)| *j == k) {
                Some((_, l)) => l,
                None => m.log_prob(v),
            });
        }
        if all.len() == 1 {
            return all.pop().unwrap_or_default();
        }
        let ln_k = (self.members.len() as f64).ln();
        (0..all[0].len())
            .map(|i| {
                let top = all.iter().map(|l| l[i]).fold(f64::NEG_INFINITY, f64::max);
                if !top.is_finite() {
                    return top;
                }
                top + all.iter().map(|l| (l[i] - top).exp()).sum::<f64>().ln() - ln_k
            })
            .collect()
    }

    /// log q(v) and ∂ log q / ∂v: each member's by one forward and one backward pass,
    /// mixed with the members' posterior weights q_k / Σ q_j.
    fn log_prob_grad(&self, v: &[f64]) -> (Vec<f64>, Vec<f64>) {
        let mut all: Vec<(Vec<f64>, Vec<f64>)> = self.members.iter().map(|m| m.log_prob_grad(v)).collect();
        if all.len() == 1 {
            return all.pop().unwrap_or_default();
        }
        let n = all[0].0.len();
        let d = v.len() / n.max(1);
        let ln_k = (all.len() as f64).ln();
        let (mut lp, mut g) = (vec![f64::NEG_INFINITY; n], vec![0.0; v.len()]);
        for i in 0..n {
            let top = all.iter().map(|(l, _)| l[i]).fold(f64::NEG_INFINITY, f64::max);
            if !top.is_finite() {
                continue;
            }
            let w: Vec<f64> = all.iter().map(|(l, _)| (l[i] - top).exp()).collect();
            let total: f64 = w.iter().sum();
            lp[i] = top + total.ln() - ln_k;
            for ((_, gk), wk) in all.iter().zip(&w) {
                for j in 0..d {
                    g[i * d + j] += wk / total * gk[i * d + j];
                }
            }
        }
        (lp, g)
    }

    /// Block `b` of base draws through member b mod K, with mixture log-densities.
    fn sample(&self, b: usize, z: &[f64]) -> (Vec<f64>, Vec<f64>) {
        let k = b % self.members.len();
        let (v, lp) = self.members[k].sample(z);
        let lp = self.mix(&v, Some((k, lp)));
        (v, lp)
    }
}

/// One observation: features in header order, with the features present.
pub struct Obs<'a> {
    /// Features in header order.
    pub x: &'a [f64],
    /// `None`: all features present.
    pub present: Option<&'a [bool]>,
}

/// Per-parameter posterior summary in natural units.
#[derive(Clone, Debug, Serialize)]
pub struct Summary {
    /// The parameter.
    pub name: String,
    /// Its unit.
    pub unit: String,
    /// The posterior mode (MAP).
    pub map: f64,
    /// Posterior mean.
    pub mean: f64,
    /// Posterior median.
    pub median: f64,
    /// 5 % quantile.
    pub q05: f64,
    /// 95 % quantile.
    pub q95: f64,
    /// Posterior standard deviation.
    pub std: f64,
    /// Coefficient of variation std/mean (natural units, as the study reports it).
    pub cv: f64,
}

/// For a band-masked model: the present band (first, last grid index) of group `g`, `None`
/// when the group is absent; an error when its features are not one contiguous band or
/// the band is narrower than training covered (never extrapolated).
fn band_of(
    h: &Header,
    g: &data::Group,
    present: &dyn Fn(usize) -> bool,
) -> Result<Option<(usize, usize)>, ObservationError> {
    let n = h.frequencies_hz.len().max(1);
    let on: Vec<usize> = g.features.iter().copied().filter(|&i| present(i)).collect();
    if on.is_empty() {
        return Ok(None);
    }
    // The group's features as grid indices, each index with all of its features present.
    let mut idx: Vec<usize> = on.iter().map(|i| i % n).collect();
    idx.sort_unstable();
    idx.dedup();
    let (lo, hi) = (idx[0], idx[idx.len() - 1]);
    let per_index = g.features.len() / n.min(g.features.len()).max(1);
    if on.len() != (hi - lo + 1) * per_index {
        return Err(ObservationError::NotContiguous { group: g.name.clone() });
    }
    if lo > h.band_cut_max || n - 1 - hi > h.band_cut_max {
        let f = |k: usize| h.frequencies_hz.get(k).copied().unwrap_or(f64::NAN);
        return Err(ObservationError::BandTooNarrow {
            group: g.name.clone(),
            lo_hz: f(lo),
            hi_hz: f(hi),
            need_lo_hz: f(h.band_cut_max),
            need_hi_hz: f(n - 1 - h.band_cut_max),
        });
    }
    Ok(Some((lo, hi)))
}

impl Npe {
    fn from_parts(header: Header, records: Vec<ModuleRecord>) -> Npe {
        let device = Device::flex();
        let flows: Vec<Flow> = records.into_iter().map(|r| Flow::new(&header.flow, &device).load_record(r)).collect();
        let plains = flows.iter().map(|f| f.plain(&header.flow)).collect();
        Npe { header, flows, plains, full: None, sets: Vec::new() }
    }

    /// The model that answers an observation with these features present: the
    /// full-measure flow when the file holds one and every feature is present and
    /// finite; else a measure-set flow whose groups are exactly those given, whole and
    /// finite; else this one. Its own header (temperature, fit-check null) goes with it.
    pub fn answering(&self, obs: &Obs<'_>) -> &Npe {
        match &self.full {
            Some(full) if self.full_measure_answers(obs) => full,
            _ => self.measure_set_answering(obs).unwrap_or(self),
        }
    }

    /// Which flow [`Npe::answering`] gives: `full-measure`, `measure-set` or `main`.
    pub fn answering_name(&self, obs: &Obs<'_>) -> &'static str {
        let a = self.answering(obs);
        if std::ptr::eq(a, self) {
            "main"
        } else if a.header.measures.is_empty() {
            "full-measure"
        } else {
            "measure-set"
        }
    }

    /// The measure-set flow whose groups are exactly the groups given whole (every
    /// feature present and finite), no feature of another group given.
    fn measure_set_answering(&self, obs: &Obs<'_>) -> Option<&Npe> {
        if obs.x.len() != self.header.feature_names.len() || obs.present.is_some_and(|p| p.len() != obs.x.len()) {
            return None;
        }
        let given = |i: usize| obs.present.is_none_or(|p| p[i]) && obs.x[i].is_finite();
        // A feature a set does not read belongs to another group: it must be absent. A set
        // that reads every feature given whole answers before a band-masked one.
        let whole =
            |s: &&Npe| s.header.measure_features().is_some_and(|read| (0..obs.x.len()).all(|i| read[i] == given(i)));
        let banded = |s: &&Npe| {
            let h = &s.header;
            h.mask_bands
                && h.measure_features().is_some_and(|read| (0..obs.x.len()).all(|i| read[i] || !given(i)))
                && h.groups.iter().all(|g| {
                    let band = band_of(h, g, &given);
                    if h.measures.contains(&g.name) { matches!(band, Ok(Some(_))) } else { matches!(band, Ok(None)) }
                })
                && h.grouped_features().iter().enumerate().all(|(i, &grouped)| grouped || given(i))
        };
        let unmasked = |s: &&Npe| !s.header.mask_bands;
        // Of the band-masked sets that cover the ear, the one trained on the narrowest cuts.
        let narrowest = || self.sets.iter().filter(banded).min_by_key(|s| s.header.band_cut_max);
        self.sets.iter().filter(unmasked).find(whole).or_else(narrowest)
    }

    /// Whether [`Npe::answering`] gives the full-measure flow for `obs`: the file holds
    /// one, and every feature is present and finite.
    pub fn full_measure_answers(&self, obs: &Obs<'_>) -> bool {
        self.full.is_some()
            && obs.x.len() == self.header.feature_names.len()
            && obs.x.iter().all(|v| v.is_finite())
            && obs.present.is_none_or(|p| p.iter().all(|&b| b))
    }

    /// The measure-set flows the file holds.
    pub fn measure_sets(&self) -> &[Npe] {
        &self.sets
    }

    /// The full-measure flow, if the file holds one.
    pub fn full_measure(&self) -> Option<&Npe> {
        self.full.as_deref()
    }

    /// The flows the file holds besides the main one (full-measure first, then the
    /// measure-set flows), to be calibrated again in place.
    pub fn attached_mut(&mut self) -> impl Iterator<Item = &mut Npe> {
        self.full.as_deref_mut().into_iter().chain(self.sets.iter_mut())
    }

    /// Stores `full` as this model's full-measure flow ([`Npe::answering`]): an unmasked
    /// model of the same parameters, features and grid, without one of its own.
    pub fn attach_full_measure(&mut self, full: Npe) -> Result<(), CheckpointError> {
        let f = &full.header;
        let why = if f.mask_groups || f.mask_bands {
            Some("it was trained with masks (it must answer the full set of measures only)")
        } else if !f.measures.is_empty() {
            Some("it was trained on some measures only (attach it as a measure-set flow)")
        } else if f.full_measure_flow || full.full.is_some() || !full.sets.is_empty() {
            Some("it holds a full-measure flow of its own")
        } else {
            self.same_ear(f)
        };
        if let Some(why) = why {
            return Err(CheckpointError::field("full_measure_flow", why));
        }
        self.full = Some(Box::new(full));
        self.header.full_measure_flow = true;
        Ok(())
    }

    /// Stores `flow` as a measure-set flow ([`Npe::answering`]): a model trained on some
    /// of this one's feature groups alone (`otofit train --measures`), of the same
    /// parameters, features and grid, without flows of its own; one per set of groups.
    pub fn attach_measure_set(&mut self, flow: Npe) -> Result<(), CheckpointError> {
        let why = if flow.header.measures.is_empty() {
            Some("it was not trained on a set of measures (otofit train --measures)".to_string())
        } else if flow.full.is_some() || !flow.sets.is_empty() {
            Some("it holds flows of its own".into())
        } else {
            self.same_ear(&flow.header).map(str::to_string)
        };
        let mut wanted = flow.header.measures.clone();
        wanted.sort();
        // One flow per set of measures read whole, and one per set and cut limit read on
        // part of the band.
        let held = |s: &Npe| {
            let mut m = s.header.measures.clone();
            m.sort();
            m == wanted
                && (s.header.mask_bands, s.header.band_cut_max) == (flow.header.mask_bands, flow.header.band_cut_max)
                && s.header.from_hz == flow.header.from_hz
        };
        let why = why.or_else(|| {
            if self.sets.iter().any(held) {
                let kind = if flow.header.mask_bands {
                    format!(
                        " with band masks cutting at most {} of the grid's points from each end",
                        flow.header.band_cut_max
                    )
                } else if flow.header.from_hz > 0.0 {
                    format!(" from {} Hz", flow.header.from_hz)
                } else {
                    String::new()
                };
                Some(format!("the model holds a flow{kind} of the measures {} already", wanted.join(", ")))
            } else if self.sets.len() >= MAX_MEASURE_SETS {
                Some(format!("the model holds {MAX_MEASURE_SETS} measure-set flows, the most a file may"))
            } else {
                None
            }
        });
        if let Some(why) = why {
            return Err(CheckpointError::field("measure_set_flows", why));
        }
        self.sets.push(flow);
        self.header.measure_set_flows = self.sets.len();
        Ok(())
    }

    /// Why a flow with header `f` does not answer this model's ears: other features,
    /// grid, parameters or prior boxes.
    fn same_ear(&self, f: &Header) -> Option<&'static str> {
        let h = &self.header;
        if f.feature_names != h.feature_names || f.frequencies_hz != h.frequencies_hz {
            Some("its features or frequency grid differ")
        } else if f.params.len() != h.params.len()
            || f.params.iter().zip(&h.params).any(|(a, b)| a.name != b.name || a.low != b.low || a.high != b.high)
        {
            Some("its parameters or their prior boxes differ")
        } else if f.groups.iter().map(|g| (&g.name, &g.features)).ne(h.groups.iter().map(|g| (&g.name, &g.features))) {
            Some("its feature groups differ")
        } else {
            None
        }
    }

    /// Adds to each simulation in `xs` (row k: the k-th) its draw of the model error the
    /// model was trained with, so that held-out checks see the inputs the training saw;
    /// unchanged without one.
    pub fn add_model_error<'a>(&self, xs: impl IntoIterator<Item = &'a mut Vec<f64>>, seed: u64) -> Result<()> {
        if let Some(d) = self.header.model_error_sampler()? {
            xs.into_iter().enumerate().for_each(|(row, x)| d.add_for_row(x, seed, row));
        }
        Ok(())
    }

    /// The prior box, one per parameter.
    pub fn params(&self) -> &[Param] {
        &self.header.params
    }

    /// Writes the checkpoint: magic, header length (u64 LE), JSON header, then per member
    /// its burn record's length (u64 LE) and bytes, then the full-measure flow's whole
    /// checkpoint, length-prefixed, when there is one.
    pub fn save(&self, path: &Path) -> Result<()> {
        let out = self.to_bytes()?;
        let tmp = path.with_extension("tmp");
        std::fs::write(&tmp, &out).map_err(FileError::on("write", &tmp))?;
        std::fs::rename(&tmp, path).map_err(FileError::on("write", path))?;
        Ok(())
    }

    /// The checkpoint's bytes ([`Npe::save`]).
    fn to_bytes(&self) -> Result<Vec<u8>> {
        let mut h = self.header.clone();
        h.format_version = FORMAT_VERSION;
        h.members = self.flows.len();
        h.full_measure_flow = self.full.is_some();
        h.measure_set_flows = self.sets.len();
        let header = serde_json::to_vec(&h).map_err(|e| NpeError::Encode { what: "header", why: e.to_string() })?;
        let mut out = Vec::with_capacity(header.len() + 400_000 * self.flows.len());
        out.extend_from_slice(MAGIC);
        out.extend_from_slice(&(header.len() as u64).to_le_bytes());
        out.extend_from_slice(&header);
        for f in &self.flows {
            let record = f
                .clone()
                .into_record()
                .into_bytes()
                .map_err(|e| NpeError::Encode { what: "record", why: format!("{e:?}") })?;
            out.extend_from_slice(&(record.len() as u64).to_le_bytes());
            out.extend_from_slice(&record);
        }
        if let Some(full) = &self.full {
            let bytes = full.to_bytes()?;
            out.extend_from_slice(&(bytes.len() as u64).to_le_bytes());
            out.extend_from_slice(&bytes);
        }
        for set in &self.sets {
            let bytes = set.to_bytes()?;
            out.extend_from_slice(&(bytes.len() as u64).to_le_bytes());
            out.extend_from_slice(&bytes);
        }
        Ok(out)
    }

    /// Reads a checkpoint file; a file that is not a usable model names itself.
    pub fn load(path: &Path) -> Result<Npe> {
        let bytes = std::fs::read(path).map_err(FileError::on("read model", path))?;
        Self::from_bytes(&bytes).map_err(|source| NpeError::Unusable { path: path.into(), source })
    }

    /// Decodes a checkpoint: every length is checked against the file and every header
    /// field against what the code can build, before any weights are read.
    pub fn from_bytes(bytes: &[u8]) -> Result<Npe, CheckpointError> {
        Self::decode(bytes, false)
    }

    /// [`Npe::from_bytes`]; `nested` for a full-measure flow, which may not hold another.
    fn decode(bytes: &[u8], nested: bool) -> Result<Npe, CheckpointError> {
        let start = MAGIC.len() + 8;
        if bytes.len() < start || &bytes[..MAGIC.len()] != MAGIC {
            return Err(CheckpointError::BadMagic);
        }
        let (n, rest) = length_prefixed(&bytes[MAGIC.len()..])
            .ok_or_else(|| CheckpointError::HeaderLength(u64::from_le_bytes(le8(&bytes[MAGIC.len()..start]))))?;
        let header: Header = serde_json::from_slice(n).map_err(CheckpointError::Header)?;
        header.validate()?;
        let record = |b: &[u8]| {
            ModuleRecord::from_bytes(burn::tensor::Bytes::from_bytes_vec(b.to_vec()))
                .map_err(|e| CheckpointError::Weights(format!("{e:?}")))
        };
        let (records, rest) = if header.format_version == 1 {
            (vec![record(rest)?], &[][..])
        } else {
            let mut rest = rest;
            let mut out = Vec::new();
            for member in 0..header.members {
                let (r, after) =
                    length_prefixed(rest).ok_or(CheckpointError::Truncated { member, members: header.members })?;
                out.push(record(r)?);
                rest = after;
            }
            (out, rest)
        };
        if records.is_empty() {
            return Err(CheckpointError::NoWeights);
        }
        let (with_full, sets) = (header.full_measure_flow, header.measure_set_flows);
        if nested && (with_full || sets > 0) {
            let field = if with_full { "full_measure_flow" } else { "measure_set_flows" };
            return Err(CheckpointError::field(field, "a flow inside a model holds another"));
        }
        let expected = Flow::new(&header.flow, &Device::flex()).num_params();
        let mut npe = Npe::from_parts(header, records);
        if npe.flows.iter().any(|f| f.num_params() != expected) {
            return Err(CheckpointError::Architecture);
        }
        npe.header.measure_set_flows = 0;
        let mut rest = rest;
        if with_full {
            let (bytes, after) = length_prefixed(rest)
                .ok_or_else(|| CheckpointError::field("full_measure_flow", "the file ends before the flow"))?;
            let full =
                Npe::decode(bytes, true).map_err(|e| CheckpointError::field("full_measure_flow", e.to_string()))?;
            npe.attach_full_measure(full)?;
            rest = after;
        }
        for k in 0..sets {
            let field = |why: String| CheckpointError::field("measure_set_flows", format!("flow {}: {why}", k + 1));
            let (bytes, after) = length_prefixed(rest).ok_or_else(|| field("the file ends before it".into()))?;
            let set = Npe::decode(bytes, true).map_err(|e| field(e.to_string()))?;
            npe.attach_measure_set(set)?;
            rest = after;
        }
        Ok(npe)
    }

    /// Network input for one observation: standardised features (absent ones zero) and,
    /// for mask-trained models, one presence flag per group.
    pub fn input_row(&self, obs: &Obs<'_>) -> Result<Vec<f32>> {
        let h = &self.header;
        let f = h.feature_names.len();
        if obs.x.len() != f {
            return Err(ObservationError::FeatureCount { got: obs.x.len(), expected: f }.into());
        }
        if obs.present.is_some_and(|p| p.len() != f) {
            return Err(
                ObservationError::FeatureCount { got: obs.present.map_or(0, <[bool]>::len), expected: f }.into()
            );
        }
        let present = |i: usize| obs.present.is_none_or(|p| p[i]);
        let mut row: Vec<f32> =
            (0..f)
                .map(|i| {
                    if present(i) && obs.x[i].is_finite() {
                        ((obs.x[i] - h.x_mean[i]) / h.x_std[i]) as f32
                    } else {
                        0.0
                    }
                })
                .collect();
        if h.mask_groups {
            let mut any = false;
            for g in &h.groups {
                let on = if h.mask_bands {
                    band_of(h, g, &present)?.is_some()
                } else {
                    g.features.iter().all(|&i| present(i))
                };
                any |= on;
                row.push(if on { 1.0 } else { 0.0 });
            }
            if !any {
                let groups = h.groups.iter().map(|g| g.name.as_str()).collect::<Vec<_>>().join(", ");
                return Err(ObservationError::NoGroup { groups }.into());
            }
            // Features outside every group must be present.
            for i in 0..f {
                if !present(i) && !h.groups.iter().any(|g| g.features.contains(&i)) {
                    return Err(ObservationError::Missing { feature: h.feature_names[i].clone() }.into());
                }
            }
            if h.mask_bands {
                row.extend((0..f).map(|i| if present(i) && obs.x[i].is_finite() { 1.0 } else { 0.0 }));
            }
        } else if let Some(read) = h.measure_features() {
            // A band-masked one reads each of its groups on a band as wide as training cut.
            let banded = if h.mask_bands { h.grouped_features() } else { vec![false; f] };
            if h.mask_bands {
                let given = |i: usize| present(i) && obs.x[i].is_finite();
                for g in h.groups.iter().filter(|g| h.measures.contains(&g.name)) {
                    if band_of(h, g, &given)?.is_none() {
                        return Err(ObservationError::MissingOrNotFinite {
                            feature: h.feature_names[g.features[0]].clone(),
                        }
                        .into());
                    }
                }
            }
            // A measure-set flow never saw the other groups: they stay zero, given or not.
            for i in 0..f {
                if !read[i] {
                    row[i] = 0.0;
                } else if !present(i) || !obs.x[i].is_finite() {
                    if !banded[i] {
                        return Err(ObservationError::MissingOrNotFinite { feature: h.feature_names[i].clone() }.into());
                    }
                    row[i] = 0.0;
                }
            }
            if h.mask_bands {
                row.extend((0..f).map(|i| if read[i] && present(i) && obs.x[i].is_finite() { 1.0 } else { 0.0 }));
            }
        } else if let Some(i) = (0..f).find(|&i| !present(i) || !obs.x[i].is_finite()) {
            return Err(ObservationError::MissingOrNotFinite { feature: h.feature_names[i].clone() }.into());
        }
        Ok(row)
    }

    /// Standardised-u samples → natural θ.
    fn to_theta(&self, v: &[f64]) -> Vec<f64> {
        let h = &self.header;
        let u = |k: usize| v[k] * h.u_std[k] + h.u_mean[k];
        match h.theta_map {
            ThetaMap::Logit => h.params.iter().enumerate().map(|(k, p)| p.from_u(u(k))).collect(),
            ThetaMap::Scale => h.params.iter().enumerate().map(|(k, p)| p.from_t(u(k))).collect(),
        }
    }

    /// Whether a standardised draw maps inside the prior box (always, through the logit).
    fn inside(&self, v: &[f64]) -> bool {
        let h = &self.header;
        h.theta_map == ThetaMap::Logit
            || h.params.iter().enumerate().all(|(k, p)| p.t_inside(v[k] * h.u_std[k] + h.u_mean[k]))
    }

    fn to_v(&self, theta: &[f64]) -> Vec<f32> {
        self.to_v_wide(theta).into_iter().map(|v| v as f32).collect()
    }

    /// Natural θ → standardised u, in f64.
    fn to_v_wide(&self, theta: &[f64]) -> Vec<f64> {
        let h = &self.header;
        let u = |p: &Param, v: f64| match h.theta_map {
            ThetaMap::Logit => p.to_u(v),
            ThetaMap::Scale => p.to_t(v),
        };
        h.params.iter().enumerate().map(|(k, p)| (u(p, theta[k]) - h.u_mean[k]) / h.u_std[k]).collect()
    }

    /// log |dv/dθ| summed over parameters (v: standardised u).
    pub(crate) fn log_jacobian(&self, theta: &[f64]) -> f64 {
        let h = &self.header;
        let j = |p: &Param, v: f64| match h.theta_map {
            ThetaMap::Logit => p.log_jacobian(v),
            ThetaMap::Scale => p.t_log_jacobian(v),
        };
        h.params.iter().enumerate().map(|(k, p)| j(p, theta[k]) - h.u_std[k].ln()).sum()
    }

    /// `n` posterior draws inside the prior box (standardised space), deterministic for
    /// `seed`, with their log-densities in the flow's space. Draws outside the box (only
    /// with `ThetaMap::Scale`) are replaced by further rounds, within a budget of
    /// `DRAW_BUDGET`·n draws in all; beyond it (a flow with less than ~1/8 of its mass in
    /// the box: an observation unlike the training set) the last rejected draws fill the
    /// rest and are clamped into the box later, so the posterior piles at a bound — which
    /// the reading and the fit check then see — instead of the request running for minutes.
    /// A further round draws what is missing at the acceptance seen so far, × 1.2, and at
    /// least 32: its draws are the first of that round's seed whatever their number (one
    /// stream of base draws), so sizing a round to the need changes no accepted draw.
    fn draw(&self, bound: &Mixture<'_>, n: usize, seed: u64) -> (Vec<Vec<f64>>, Vec<f64>) {
        const DRAW_BUDGET: usize = 8;
        let (mut v, mut lp) = self.draw_raw(bound, n, seed);
        if self.header.theta_map == ThetaMap::Logit {
            return (v, lp);
        }
        let (mut out_v, mut out_lp) = (Vec::with_capacity(n), Vec::with_capacity(n));
        let (mut drawn, mut round) = (n, 0u64);
        loop {
            let (mut rej_v, mut rej_lp) = (Vec::new(), Vec::new());
            for (a, l) in v.into_iter().zip(lp) {
                if out_v.len() < n && self.inside(&a) {
                    out_v.push(a);
                    out_lp.push(l);
                } else if rej_v.len() < n {
                    rej_v.push(a);
                    rej_lp.push(l);
                }
            }
            let need = n - out_v.len();
            if need == 0 {
                return (out_v, out_lp);
            }
            if drawn >= DRAW_BUDGET * n {
                out_v.extend(rej_v.into_iter().take(need));
                out_lp.extend(rej_lp.into_iter().take(need));
                return (out_v, out_lp);
            }
            // Enough for the rest at the acceptance seen so far, within the budget.
            round += 1;
            let rate = (out_v.len() as f64 / drawn as f64).max(0.01);
            let m = ((need as f64 / rate * 1.2).ceil() as usize).max(32).min(DRAW_BUDGET * n - drawn).max(need);
            drawn += m;
            (v, lp) = self.draw_raw(bound, m, seed ^ round.wrapping_mul(0x9E37_79B9_7F4A_7C15));
        }
    }

    /// `n` draws of the flow (standardised space) with their log-densities.
    fn draw_raw(&self, bound: &Mixture<'_>, n: usize, seed: u64) -> (Vec<Vec<f64>>, Vec<f64>) {
        let d = self.header.params.len();
        let mut rng = ChaCha8Rng::seed_from_u64(seed);
        let z: Vec<f32> = (0..n * d).map(|_| StandardNormal.sample(&mut rng)).collect();
        // Blocks of 128 rows: buffers stay in cache (and under the allocator's mmap
        // threshold); rayon spreads them over the cores; block b comes from member b mod K.
        let z: Vec<f64> = z.into_iter().map(f64::from).collect();
        let blocks: Vec<(Vec<f64>, Vec<f64>)> =
            z.par_chunks(d * 128).enumerate().map(|(b, c)| bound.sample(b, c)).collect();
        let mut v = Vec::with_capacity(n);
        let mut lp = Vec::with_capacity(n);
        for (m, l) in blocks {
            v.extend(m.chunks_exact(d).map(<[f64]>::to_vec));
            lp.extend(l);
        }
        (v, lp)
    }

    fn bind(&self, input: &[f32]) -> Mixture<'_> {
        let x: Vec<f64> = input.iter().map(|&v| v as f64).collect();
        let t = self.header.temperature;
        Mixture { members: self.plains.iter().map(|p| p.bind(&x).with_temperature(t)).collect() }
    }

    /// Posterior samples in natural units.
    pub fn sample(&self, obs: &Obs<'_>, n: usize, seed: u64) -> Result<Vec<Vec<f64>>> {
        let input = self.input_row(obs)?;
        let (v, _) = self.draw(&self.bind(&input), n, seed);
        Ok(v.iter().map(|r| self.to_theta(r)).collect())
    }

    /// log q(θ | x) in natural units (with the Jacobian of the bijection).
    pub fn log_prob(&self, obs: &Obs<'_>, thetas: &[Vec<f64>]) -> Result<Vec<f64>> {
        let d = self.header.params.len();
        if let Some(t) = thetas.iter().find(|t| t.len() != d) {
            return Err(ObservationError::ThetaWidth { got: t.len(), expected: d }.into());
        }
        let input = self.input_row(obs)?;
        Ok(self.log_prob_input(&input, thetas))
    }

    fn log_prob_input(&self, input: &[f32], thetas: &[Vec<f64>]) -> Vec<f64> {
        let d = self.header.params.len();
        let v: Vec<f64> = thetas.iter().flat_map(|t| self.to_v(t)).map(f64::from).collect();
        let lp = self.bind(input).log_prob(&v);
        debug_assert_eq!(lp.len() * d, v.len());
        lp.iter().zip(thetas).map(|(l, t)| l + self.log_jacobian(t)).collect()
    }

    /// Samples, MAP and per-parameter summaries for one observation.
    pub fn infer(&self, obs: &Obs<'_>, n: usize, seed: u64) -> Result<Inference> {
        let t0 = std::time::Instant::now();
        let input = self.input_row(obs)?;
        // The observation embedded once, for the draws and the MAP search.
        let bound = self.bind(&input);
        let (v, lp) = self.draw(&bound, n.max(1), seed);
        let samples: Vec<Vec<f64>> = v.iter().map(|r| self.to_theta(r)).collect();
        let sample_ms = t0.elapsed().as_secs_f64() * 1e3;
        let map = self.map_from(&bound, &v, &lp);
        let map_ms = t0.elapsed().as_secs_f64() * 1e3 - sample_ms;
        let summaries = summarize(&self.header.params, &samples, &map);
        Ok(Inference { samples, map, summaries, sample_ms, map_ms })
    }

    /// MAP in the flow's (unbounded, standardised) space: gradient ascent with Adam from
    /// the two best draws, with analytic gradients (one forward and one backward pass of
    /// the flow per step for both starts; `flow::plain` tests them against differences).
    fn map_from(&self, bound: &Mixture<'_>, v: &[Vec<f64>], lp: &[f64]) -> Vec<f64> {
        let d = self.header.params.len();
        // The two highest densities, ties to the earlier draw (as a stable sort would).
        let mut order: Vec<usize> = Vec::with_capacity(2);
        for i in 0..v.len().min(lp.len()) {
            let at = order.iter().position(|&j| lp[i].total_cmp(&lp[j]).is_gt()).unwrap_or(order.len());
            if at < 2 {
                order.insert(at, i);
                order.truncate(2);
            }
        }
        let (lr, b1, b2) = (0.05, 0.9f64, 0.999f64);
        let mut best = (f64::NEG_INFINITY, vec![0f64; d]);
        let mut xs: Vec<f64> = order.iter().take(2).flat_map(|&i| v[i].iter().copied()).collect();
        let (mut m, mut s) = (vec![0.0; xs.len()], vec![0.0; xs.len()]);
        for step in 1..=20 {
            let (l, grad) = bound.log_prob_grad(&xs);
            for (si, x) in xs.chunks_exact_mut(d).enumerate() {
                if l[si].is_finite() && l[si] > best.0 {
                    best = (l[si], x.to_vec());
                }
                for j in 0..d {
                    let g = -grad[si * d + j]; // ascend
                    let (m, s) = (&mut m[si * d + j], &mut s[si * d + j]);
                    *m = b1 * *m + (1.0 - b1) * g;
                    *s = b2 * *s + (1.0 - b2) * g * g;
                    let mh = *m / (1.0 - b1.powi(step));
                    let sh = *s / (1.0 - b2.powi(step));
                    x[j] -= lr * mh / (sh.sqrt() + 1e-8);
                }
            }
        }
        self.to_theta(&best.1)
    }
}

/// The flow's sampling map for one observation, θ = T(z; x): standard-normal z (the
/// flow's base space) → natural θ, with log |det ∂θ/∂z|. A posterior known up to a
/// constant in θ, π(θ), is π(T(z)) |det ∂T/∂z| in z; where the flow approximates π that
/// is near N(0, I), so simple Markov kernels mix there (`discrepancy::exact_fast`).
///
/// It is the first ensemble member's map at temperature 1 (a mixture of flows has no
/// single bijection; any bijection serves), with every conditioner in f64 so that the
/// map is smooth and its log-determinant is that of the map computed.
pub struct LatentMap<'a> {
    npe: &'a Npe,
    member: Bound<'a>,
}

impl Npe {
    /// The flow's z → θ map conditioned on `obs` (see [`LatentMap`]).
    pub fn latent(&self, obs: &Obs<'_>) -> Result<LatentMap<'_>> {
        let input = self.input_row(obs)?;
        let x: Vec<f64> = input.iter().map(|&v| f64::from(v)).collect();
        // A checkpoint has at least one member (`Header::validate`).
        Ok(LatentMap { npe: self, member: self.plains[0].bind(&x) })
    }
}

impl LatentMap<'_> {
    /// Parameters (the length of z and of θ).
    pub fn dim(&self) -> usize {
        self.npe.header.params.len()
    }

    /// θ = T(z) and log |det ∂θ/∂z| for one z.
    pub fn to_theta(&self, z: &[f64]) -> (Vec<f64>, f64) {
        self.to_thetas(z).pop().unwrap_or_else(|| (vec![], f64::NAN))
    }

    /// [`Self::to_theta`] of n points z (n rows of [`Self::dim`], row-major), in one
    /// pass. The log-determinant is −∞ where θ would leave the prior box (possible only
    /// with `ThetaMap::Scale`, whose map clamps there: zero prior mass, no density).
    ///
    /// log q(v) = log N(z; 0, I) − log |det ∂v/∂z| for the flow's standardised v, and
    /// log |det ∂θ/∂v| = −log |det ∂v/∂θ| ([`Npe::log_jacobian`]).
    pub fn to_thetas(&self, z: &[f64]) -> Vec<(Vec<f64>, f64)> {
        let d = self.dim();
        if d == 0 || z.is_empty() {
            return vec![];
        }
        let (v, lp) = self.member.sample_wide(z);
        let log_n = |c: &[f64]| {
            -0.5 * c.iter().map(|x| x * x).sum::<f64>() - 0.5 * d as f64 * (2.0 * std::f64::consts::PI).ln()
        };
        v.chunks_exact(d)
            .zip(z.chunks_exact(d))
            .zip(lp)
            .map(|((v, z), lp)| {
                let theta = self.npe.to_theta(v);
                let ld =
                    if self.npe.inside(v) { log_n(z) - lp - self.npe.log_jacobian(&theta) } else { f64::NEG_INFINITY };
                (theta, ld)
            })
            .collect()
    }

    /// z = T⁻¹(θ) for θ inside the prior box.
    pub fn to_z(&self, theta: &[f64]) -> Vec<f64> {
        self.member.base(&self.npe.to_v_wide(theta)).0
    }
}

/// The result of one inference.
#[derive(Clone, Debug, Serialize)]
pub struct Inference {
    /// Posterior samples, natural units.
    #[serde(skip)]
    pub samples: Vec<Vec<f64>>,
    /// The MAP, natural units.
    pub map: Vec<f64>,
    /// Per-parameter summaries.
    pub summaries: Vec<Summary>,
    /// Time spent sampling.
    pub sample_ms: f64,
    /// Time spent on the MAP search.
    pub map_ms: f64,
}

/// Per-parameter summaries of samples (rows of natural θ), with the MAP given. Quantiles
/// interpolate linearly between order statistics ([`crate::stats::quantile_linear`]).
pub fn summarize(params: &[Param], samples: &[Vec<f64>], map: &[f64]) -> Vec<Summary> {
    params
        .iter()
        .enumerate()
        .map(|(k, p)| {
            let v = stats::sorted(samples.iter().map(|s| s[k]).collect());
            let (mean, var) = stats::mean_var_sample(&v);
            let std = var.sqrt();
            Summary {
                name: p.name.clone(),
                unit: p.unit.clone(),
                map: map[k],
                mean,
                median: stats::quantile_linear(&v, 0.5),
                q05: stats::quantile_linear(&v, 0.05),
                q95: stats::quantile_linear(&v, 0.95),
                std,
                // Draws without spread vary by nothing, even at a mean of 0 (a prior box
                // that starts at 0, every draw on it): 0, not 0/0.
                cv: if std == 0.0 { 0.0 } else { std / mean.abs() },
            }
        })
        .collect()
}

#[allow(dead_code)]
fn assert_send_sync() {
    fn is<T: Send + Sync>() {}
    is::<Npe>();
}

#[cfg(test)]
mod tests {
    use super::*;

    fn model() -> Npe {
        Npe::load(&Path::new(env!("CARGO_MANIFEST_DIR")).join("../../models/default.otofit")).unwrap()
    }

    /// log |det| of a d×d row-major matrix by Gaussian elimination with partial pivoting.
    fn log_abs_det(mut a: Vec<f64>, d: usize) -> f64 {
        let mut sum = 0.0;
        for c in 0..d {
            let p = (c..d).max_by(|&i, &j| a[i * d + c].abs().total_cmp(&a[j * d + c].abs())).unwrap();
            for k in 0..d {
                a.swap(c * d + k, p * d + k);
            }
            let pivot = a[c * d + c];
            sum += pivot.abs().ln();
            for r in c + 1..d {
                let f = a[r * d + c] / pivot;
                for k in c..d {
                    a[r * d + k] -= f * a[c * d + k];
                }
            }
        }
        sum
    }

    /// Points z that map inside the prior box: the origin, and draws of N(0, I) and of
    /// N(0, 1.5² I) (the default model clamps at the box: `ThetaMap::Scale`).
    fn points(map: &LatentMap<'_>) -> Vec<Vec<f64>> {
        let d = map.dim();
        let mut rng = ChaCha8Rng::seed_from_u64(11);
        let mut out = vec![vec![0.0; d]];
        for s in [1.0, 1.0, 1.0, 1.5, 1.5, 1.5] {
            let z: Vec<f64> = (0..d).map(|_| s * Distribution::<f64>::sample(&StandardNormal, &mut rng)).collect();
            if map.to_theta(&z).1.is_finite() {
                out.push(z);
            }
        }
        assert!(out.len() >= 4, "{} of 7 points inside the box", out.len());
        out
    }

    /// Named groups give exactly their features, none gives all, and an unknown name is
    /// refused with the model's groups listed.
    #[test]
    fn measures_named_by_group_give_their_features() {
        let h = model().header;
        let names: Vec<&str> = h.groups.iter().map(|g| g.name.as_str()).collect();
        assert!(h.features_of_groups::<&str>(&[]).unwrap().iter().all(|&g| g));
        let given = h.features_of_groups(&[names[1], names[2]]).unwrap();
        for (i, &g) in given.iter().enumerate() {
            let member = h.groups[1..=2].iter().any(|grp| grp.features.contains(&i));
            assert_eq!(g, member, "feature {i} ({})", h.feature_names[i]);
        }
        assert_eq!(
            h.features_of_groups(&[format!(" {} ", names[0])]).unwrap().iter().filter(|&&g| g).count(),
            h.groups[0].features.len()
        );
        let e = h.features_of_groups(&["tympanogram"]).unwrap_err().to_string();
        assert!(e.contains("'tympanogram'") && names.iter().all(|n| e.contains(n)), "{e}");
    }

    /// The shipped model's masked flow alone, without the flows stored beside it.
    fn bare_model() -> Npe {
        let mut m = model();
        m.full = None;
        m.sets.clear();
        m
    }

    /// An untrained flow that takes `m`'s features without masks (the weights do not
    /// matter to how a file is stored or which flow answers).
    fn unmasked_like(m: &Npe) -> Npe {
        let mut h = m.header.clone();
        h.mask_groups = false;
        h.mask_bands = false;
        h.flow.inputs = h.feature_names.len();
        h.full_measure_flow = false;
        let flow = Flow::new(&h.flow, &Device::flex());
        Npe::from_parts(h, vec![flow.into_record()])
    }

    #[test]
    fn draws_without_spread_have_a_coefficient_of_variation_of_zero() {
        let params = model().header.params;
        let k = params.iter().position(|p| p.low == 0.0).expect("a prior box that starts at 0");
        let draws: Vec<Vec<f64>> = (0..4)
            .map(|i| params.iter().enumerate().map(|(j, p)| if j == k { 0.0 } else { p.low + i as f64 }).collect())
            .collect();
        let s = summarize(&params, &draws, &draws[0]);
        assert_eq!((s[k].mean, s[k].std, s[k].cv), (0.0, 0.0, 0.0), "{:?}", s[k]);
        assert!(s.iter().all(|p| p.cv.is_finite()), "{s:?}");
    }

    #[test]
    fn a_full_measure_flow_answers_ears_with_every_measure_and_is_stored_with_the_model() {
        let mut m = bare_model();
        let full = unmasked_like(&m);
        m.attach_full_measure(full).unwrap();
        let bytes = m.to_bytes().unwrap();
        let back = Npe::from_bytes(&bytes).unwrap();
        assert!(back.header.full_measure_flow && back.full_measure().is_some());
        assert_eq!(back.to_bytes().unwrap(), bytes, "the model with its full-measure flow round-trips");
        let x = back.header.x_mean.clone();
        let f = x.len();
        let all = vec![true; f];
        let answering = |present: &[bool], x: &[f64]| back.answering(&Obs { x, present: Some(present) });
        let full = back.full_measure().unwrap();
        assert!(std::ptr::eq(answering(&all, &x), full), "every measure present: the full-measure flow");
        assert!(std::ptr::eq(back.answering(&Obs { x: &x, present: None }), full));
        let mut one_gone = all.clone();
        one_gone[f - 1] = false;
        assert!(std::ptr::eq(answering(&one_gone, &x), &back), "a feature absent: the main flow");
        let says = |present: &[bool]| back.full_measure_answers(&Obs { x: &x, present: Some(present) });
        assert!(says(&all) && !says(&one_gone), "the name the service gives follows the flow that answers");
        let bare = bare_model();
        assert!(!bare.full_measure_answers(&Obs { x: &x, present: Some(&all) }), "no full-measure flow, none answers");
        let mut nan = x.clone();
        nan[0] = f64::NAN;
        assert!(std::ptr::eq(answering(&all, &nan), &back), "a feature not finite: the main flow");
    }

    #[test]
    fn a_full_measure_flow_must_be_unmasked_and_of_the_same_ear_and_a_cut_file_is_refused() {
        let mut m = bare_model();
        let why = |e: CheckpointError| e.to_string();
        let masked = model();
        assert!(why(m.attach_full_measure(masked).unwrap_err()).contains("masks"));
        let mut other = unmasked_like(&m);
        other.header.params[0].high *= 2.0;
        assert!(why(m.attach_full_measure(other).unwrap_err()).contains("prior boxes"));
        let mut nested = unmasked_like(&m);
        nested.full = Some(Box::new(unmasked_like(&m)));
        assert!(why(m.attach_full_measure(nested).unwrap_err()).contains("of its own"));
        m.attach_full_measure(unmasked_like(&m)).unwrap();
        let bytes = m.to_bytes().unwrap();
        let cut = Npe::from_bytes(&bytes[..bytes.len() - 1000]).err().map(why).unwrap_or_default();
        assert!(cut.contains("full_measure_flow"), "{cut}");
    }

    /// An untrained flow of `m`'s features that reads only the groups named.
    fn measure_set_like(m: &Npe, groups: &[&str]) -> Npe {
        let mut n = unmasked_like(m);
        n.full = None;
        n.header.measures = groups.iter().map(|g| g.to_string()).collect();
        n
    }

    /// The features given when the groups named are measured whole.
    fn given(h: &Header, groups: &[&str]) -> Vec<bool> {
        let mut p = vec![false; h.feature_names.len()];
        for g in h.groups.iter().filter(|g| groups.contains(&g.name.as_str())) {
            g.features.iter().for_each(|&i| p[i] = true);
        }
        p
    }

    #[test]
    fn a_measure_set_flow_answers_ears_of_exactly_its_groups_and_reads_only_them() {
        let mut m = model();
        m.sets.clear();
        let names: Vec<String> = m.header.groups.iter().map(|g| g.name.clone()).collect();
        let (a, b, c) = (names[0].as_str(), names[1].as_str(), names[2].as_str());
        assert!(names.len() >= 4, "{names:?}");
        m.attach_measure_set(measure_set_like(&m, &[a, b])).unwrap();
        let bytes = m.to_bytes().unwrap();
        let back = Npe::from_bytes(&bytes).unwrap();
        assert_eq!(back.to_bytes().unwrap(), bytes, "the model with its measure-set flow round-trips");
        assert!(back.full_measure().is_some(), "the full-measure flow is kept beside it");
        let set = &back.measure_sets()[0];
        assert_eq!(set.header.measures, [a, b]);
        let x = back.header.x_mean.clone();
        let answering = |present: &[bool]| back.answering(&Obs { x: &x, present: Some(present) });
        let ab = given(&back.header, &[b, a]);
        assert!(std::ptr::eq(answering(&ab), set), "exactly its groups: the measure-set flow");
        assert_eq!(back.answering_name(&Obs { x: &x, present: Some(&ab) }), "measure-set");
        let all = vec![true; x.len()];
        assert!(std::ptr::eq(answering(&all), back.full_measure().unwrap()), "every group: the full-measure flow");
        assert_eq!(back.answering_name(&Obs { x: &x, present: None }), "full-measure");
        let abc = given(&back.header, &[a, b, c]);
        assert!(std::ptr::eq(answering(&abc), &back), "a group besides its own: the masked flow");
        let mut cut = ab.clone();
        cut[back.header.groups[1].features[0]] = false;
        assert!(std::ptr::eq(answering(&cut), &back), "part of one of its groups missing: the masked flow");
        assert!(std::ptr::eq(answering(&given(&back.header, &[a])), &back), "one of its groups alone: masked");
        assert_eq!(back.answering_name(&Obs { x: &x, present: Some(&cut) }), "main");
        let mut nan = x.clone();
        nan[back.header.groups[0].features[0]] = f64::NAN;
        assert!(std::ptr::eq(back.answering(&Obs { x: &nan, present: Some(&ab) }), &back), "not finite: masked");
        // The other groups' values, given or not, never reach its network; its own must.
        let mut moved = x.clone();
        for (i, v) in moved.iter_mut().enumerate().filter(|(i, _)| !ab[*i]) {
            *v += 5.0 * back.header.x_std[i];
        }
        let row = |x: &[f64], p: &[bool]| set.input_row(&Obs { x, present: Some(p) }).unwrap();
        assert_eq!(row(&x, &ab), row(&moved, &all), "features outside its groups are ignored");
        let mut inside = x.clone();
        inside[back.header.groups[0].features[0]] += back.header.x_std[0];
        assert_ne!(row(&x, &ab), row(&inside, &ab), "its own features are read");
        let e = set.input_row(&Obs { x: &x, present: Some(&cut) }).unwrap_err().to_string();
        assert!(e.contains(&back.header.feature_names[back.header.groups[1].features[0]]), "{e}");
    }

    /// An untrained measure-set flow of `groups` that reads them on part of the band.
    fn banded_set_like(m: &Npe, groups: &[&str]) -> Npe {
        let mut h = measure_set_like(m, groups).header;
        h.mask_bands = true;
        h.band_cut_max = m.header.band_cut_max;
        h.flow.inputs = 2 * h.feature_names.len();
        let flow = Flow::new(&h.flow, &Device::flex());
        Npe::from_parts(h, vec![flow.into_record()])
    }

    /// `present` without the lowest `n` grid points of group `g`.
    fn without_low(h: &Header, present: &[bool], g: usize, n: usize) -> Vec<bool> {
        let grid = h.frequencies_hz.len();
        let mut p = present.to_vec();
        h.groups[g].features.iter().filter(|&&i| i % grid < n).for_each(|&i| p[i] = false);
        p
    }

    #[test]
    fn a_band_masked_measure_set_flow_answers_its_groups_on_part_of_the_band() {
        let mut m = bare_model();
        let names: Vec<String> = m.header.groups.iter().map(|g| g.name.clone()).collect();
        let (a, b, c) = (names[0].as_str(), names[1].as_str(), names[2].as_str());
        let cut_max = m.header.band_cut_max;
        assert!(cut_max >= 2, "{cut_max}");
        m.attach_measure_set(banded_set_like(&m, &[a, b])).unwrap();
        m.attach_measure_set(measure_set_like(&m, &[a, b])).unwrap();
        let e = m.attach_measure_set(banded_set_like(&m, &[b, a])).unwrap_err().to_string();
        assert!(e.contains("with band masks") && e.contains("already"), "{e}");
        let back = Npe::from_bytes(&m.to_bytes().unwrap()).unwrap();
        let (banded, whole) = (&back.measure_sets()[0], &back.measure_sets()[1]);
        assert!(banded.header.mask_bands && !whole.header.mask_bands, "both kept, in order");
        let h = &back.header;
        let x = h.x_mean.clone();
        let answering = |present: &[bool]| back.answering(&Obs { x: &x, present: Some(present) });
        let ab = given(h, &[a, b]);
        assert!(std::ptr::eq(answering(&ab), whole), "the whole band: the set read whole answers first");
        let low2 = without_low(h, &ab, 0, 2);
        assert!(std::ptr::eq(answering(&low2), banded), "two points short: the band-masked set");
        assert_eq!(back.answering_name(&Obs { x: &x, present: Some(&low2) }), "measure-set");
        let both = without_low(h, &low2, 1, cut_max);
        assert!(std::ptr::eq(answering(&both), banded), "each group cut as far as training did");
        assert!(std::ptr::eq(answering(&without_low(h, &ab, 0, cut_max + 1)), &back), "cut further: masked");
        assert!(std::ptr::eq(answering(&without_low(h, &given(h, &[a, b, c]), 0, 2)), &back), "another group");
        let mut gap = ab.clone();
        gap[h.groups[0].features.iter().copied().find(|&i| i % h.frequencies_hz.len() == 10).unwrap()] = false;
        assert!(std::ptr::eq(answering(&gap), &back), "a gap inside the band: masked");
        assert!(std::ptr::eq(answering(&given(h, &[a])), &back), "one of its groups alone: masked");
        // Its input: the features given, the other groups as zeros, a flag per feature.
        let row = banded.input_row(&Obs { x: &x, present: Some(&low2) }).unwrap();
        let f = x.len();
        assert_eq!(row.len(), 2 * f);
        assert!((0..f).all(|i| (row[f + i] == 1.0) == low2[i]), "the flags are the features given");
        let mut moved = x.clone();
        (0..f).filter(|&i| !ab[i]).for_each(|i| moved[i] += 5.0 * h.x_std[i]);
        let all_low2 = without_low(h, &without_low(h, &vec![true; f], 0, 2), 2, 0);
        let row_moved = banded.input_row(&Obs { x: &moved, present: Some(&all_low2) }).unwrap();
        assert_eq!(row, row_moved, "the other groups, given or not, never reach its network");
        let e = banded.input_row(&Obs { x: &x, present: Some(&without_low(h, &ab, 0, cut_max + 1)) });
        assert!(e.unwrap_err().to_string().contains(a), "a band narrower than training covered names the group");
        let mut alone = bare_model();
        alone.attach_measure_set(banded_set_like(&m, &[a, b])).unwrap();
        let one = &alone.measure_sets()[0];
        assert!(std::ptr::eq(alone.answering(&Obs { x: &x, present: Some(&ab) }), one), "alone: the whole band too");
    }

    /// Two band-masked flows of one set, trained on different cut limits, are both held;
    /// an ear is answered by the one of the narrowest cuts that covers its band.
    #[test]
    fn of_two_band_masked_flows_the_narrowest_cut_that_covers_the_ear_answers() {
        let mut m = bare_model();
        let names: Vec<String> = m.header.groups.iter().map(|g| g.name.clone()).collect();
        let (a, b) = (names[0].as_str(), names[1].as_str());
        let cut_max = m.header.band_cut_max;
        assert!(cut_max >= 2, "{cut_max}");
        let mut narrow = banded_set_like(&m, &[a, b]);
        narrow.header.band_cut_max = 1;
        m.attach_measure_set(banded_set_like(&m, &[a, b])).unwrap();
        m.attach_measure_set(narrow).unwrap();
        let mut again = banded_set_like(&m, &[a, b]);
        again.header.band_cut_max = 1;
        let e = m.attach_measure_set(again).unwrap_err().to_string();
        assert!(e.contains("at most 1 of the grid") && e.contains("already"), "{e}");
        let back = Npe::from_bytes(&m.to_bytes().unwrap()).unwrap();
        let (wide, narrow) = (&back.measure_sets()[0], &back.measure_sets()[1]);
        assert_eq!((wide.header.band_cut_max, narrow.header.band_cut_max), (cut_max, 1));
        let h = &back.header;
        let x = h.x_mean.clone();
        let answering = |present: &[bool]| back.answering(&Obs { x: &x, present: Some(present) });
        let ab = given(h, &[a, b]);
        assert!(std::ptr::eq(answering(&without_low(h, &ab, 0, 1)), narrow), "one point short: the narrow cuts");
        assert!(std::ptr::eq(answering(&without_low(h, &ab, 0, 2)), wide), "two points short: the wide cuts");
        assert!(std::ptr::eq(answering(&without_low(h, &ab, 0, cut_max + 1)), &back), "further: masked");
    }

    /// A measure-set flow trained from a frequency up (a device's band) is held beside the
    /// whole-band and band-masked flows of its set; it answers ears whose groups are all
    /// given exactly from there, and reads no point below.
    #[test]
    fn a_flow_from_a_frequency_up_answers_ears_given_exactly_from_there() {
        let mut m = bare_model();
        let names: Vec<String> = m.header.groups.iter().map(|g| g.name.clone()).collect();
        let (a, b) = (names[0].as_str(), names[1].as_str());
        let grid = m.header.frequencies_hz.clone();
        let from_hz = (grid[1] + grid[2]) / 2.0;
        let from_like = |m: &Npe, groups: &[&str]| {
            let mut n = measure_set_like(m, groups);
            n.header.from_hz = from_hz;
            n
        };
        m.attach_measure_set(measure_set_like(&m, &[a, b])).unwrap();
        m.attach_measure_set(banded_set_like(&m, &[a, b])).unwrap();
        m.attach_measure_set(from_like(&m, &[a, b])).unwrap();
        let e = m.attach_measure_set(from_like(&m, &[b, a])).unwrap_err().to_string();
        assert!(e.contains(&format!("from {from_hz} Hz")) && e.contains("already"), "{e}");
        let back = Npe::from_bytes(&m.to_bytes().unwrap()).unwrap();
        let (whole, banded, from) = (&back.measure_sets()[0], &back.measure_sets()[1], &back.measure_sets()[2]);
        assert_eq!(from.header.from_hz, from_hz, "kept in the file");
        let h = &back.header;
        let x = h.x_mean.clone();
        let answering = |present: &[bool]| back.answering(&Obs { x: &x, present: Some(present) });
        let ab = given(h, &[a, b]);
        let both = without_low(h, &without_low(h, &ab, 0, 2), 1, 2);
        assert!(std::ptr::eq(answering(&ab), whole), "the whole band: the whole-band flow");
        assert!(std::ptr::eq(answering(&both), from), "both groups from its frequency: the flow from there");
        assert!(std::ptr::eq(answering(&without_low(h, &ab, 0, 2)), banded), "one group cut: band-masked");
        assert!(std::ptr::eq(answering(&without_low(h, &both, 0, 3)), banded), "cut further: band-masked");
        // It reads its groups from its frequency up, and nothing below.
        let read = from.header.measure_features().unwrap();
        let unread: Vec<bool> = read.iter().zip(&ab).map(|(r, g)| *g && !*r).collect();
        let below: Vec<bool> = ab.iter().zip(&both).map(|(g, b)| *g && !*b).collect();
        assert!(unread == below && below.contains(&true), "its groups' two lowest points are all it leaves");
        let mut moved = x.clone();
        (0..x.len()).filter(|&i| ab[i] && !both[i]).for_each(|i| moved[i] += 5.0 * h.x_std[i]);
        let row = |x: &[f64], p: &[bool]| from.input_row(&Obs { x, present: Some(p) }).unwrap();
        assert_eq!(row(&x, &both), row(&moved, &ab), "points below its band never reach its network");
        for (bad, hz) in [(banded_set_like(&m, &[a]).header, from_hz), (measure_set_like(&m, &[a]).header, 1e9)] {
            let e = Header { from_hz: hz, ..bad }.validate().unwrap_err().to_string();
            assert!(e.contains("from_hz"), "{e}");
        }
        let e = Header { from_hz, ..bare_model().header }.validate().unwrap_err().to_string();
        assert!(e.contains("from_hz"), "a flow of every measure has no band's start: {e}");
    }

    #[test]
    fn a_measure_set_flow_names_some_groups_once_each_set_is_held_once_and_a_cut_file_is_refused() {
        let mut m = bare_model();
        let names: Vec<String> = m.header.groups.iter().map(|g| g.name.clone()).collect();
        let (a, b) = (names[0].as_str(), names[1].as_str());
        let why = |e: CheckpointError| e.to_string();
        let unmasked = unmasked_like(&m);
        assert!(why(m.attach_measure_set(unmasked).unwrap_err()).contains("--measures"));
        assert!(why(m.attach_full_measure(measure_set_like(&m, &[a])).unwrap_err()).contains("some measures only"));
        let mut other = measure_set_like(&m, &[a]);
        other.header.groups.swap(0, 1);
        assert!(why(m.attach_measure_set(other).unwrap_err()).contains("groups differ"));
        m.attach_measure_set(measure_set_like(&m, &[a, b])).unwrap();
        assert!(why(m.attach_measure_set(measure_set_like(&m, &[b, a])).unwrap_err()).contains("already"));
        m.attach_measure_set(measure_set_like(&m, &[b])).unwrap();
        let bytes = m.to_bytes().unwrap();
        assert_eq!(Npe::from_bytes(&bytes).unwrap().measure_sets().len(), 2);
        let cut = Npe::from_bytes(&bytes[..bytes.len() - 1000]).err().map(why).unwrap_or_default();
        assert!(cut.contains("measure_set_flows") && cut.contains("flow 2"), "{cut}");
        for (measures, says) in [
            (vec!["tympanogram".to_string()], "not one of the model's feature groups"),
            (vec![a.into(), a.into()], "named twice"),
            (names.clone(), "names every group"),
        ] {
            let mut h = measure_set_like(&m, &[a]).header;
            h.measures = measures;
            let e = h.validate().unwrap_err().to_string();
            assert!(e.contains("measures") && e.contains(says), "{e}");
        }
        let mut masked = measure_set_like(&m, &[a]).header;
        masked.mask_groups = true;
        masked.flow.inputs += masked.groups.len();
        assert!(masked.validate().unwrap_err().to_string().contains("without group masks"));
    }

    fn latent_of(npe: &Npe) -> LatentMap<'_> {
        let x = npe.header.x_mean.clone();
        npe.latent(&Obs { x: &x, present: None }).unwrap()
    }

    #[test]
    fn the_latent_map_inverts_and_its_log_determinant_matches_finite_differences() {
        let npe = model();
        let map = latent_of(&npe);
        let d = map.dim();
        for z in points(&map) {
            let (theta, ld) = map.to_theta(&z);
            assert!(ld.is_finite(), "log-det {ld} at {z:?}");
            // Round trip z → θ → z.
            let back = map.to_z(&theta);
            for (a, b) in z.iter().zip(&back) {
                assert!((a - b).abs() < 1e-6, "z {z:?} → {back:?}");
            }
            // ∂θ/∂z by central differences, in the standardised coordinates' scale.
            let h = 1e-5;
            let mut jac = vec![0.0; d * d];
            for j in 0..d {
                let step = |s: f64| {
                    let mut zz = z.clone();
                    zz[j] += s * h;
                    map.to_theta(&zz).0
                };
                let (up, down) = (step(1.0), step(-1.0));
                for i in 0..d {
                    jac[i * d + j] = (up[i] - down[i]) / (2.0 * h);
                }
            }
            let fd = log_abs_det(jac, d);
            assert!((fd - ld).abs() < 1e-4 * (1.0 + ld.abs()), "log-det {ld} vs finite differences {fd} at {z:?}");
        }
        // Batched: the same as one at a time.
        let zs = points(&map);
        let flat: Vec<f64> = zs.iter().flatten().copied().collect();
        for (one, (theta, ld)) in zs.iter().zip(map.to_thetas(&flat)) {
            let (t1, l1) = map.to_theta(one);
            assert!((l1 - ld).abs() < 1e-9 && t1.iter().zip(&theta).all(|(a, b)| (a - b).abs() <= 1e-9 * a.abs()));
        }
    }

    #[test]
    fn the_latent_maps_draws_are_the_flows() {
        // The flow's density at T(z) is N(z)/|det ∂θ/∂z|: the map's log-det agrees with
        // the flow's own density of the first member.
        let npe = model();
        let map = latent_of(&npe);
        let x = npe.header.x_mean.clone();
        let obs = Obs { x: &x, present: None };
        for z in points(&map) {
            let (theta, ld) = map.to_theta(&z);
            let log_n =
                -0.5 * z.iter().map(|v| v * v).sum::<f64>() - 0.5 * z.len() as f64 * (2.0 * std::f64::consts::PI).ln();
            let input = npe.input_row(&obs).unwrap();
            let x64: Vec<f64> = input.iter().map(|&v| f64::from(v)).collect();
            let q = npe.plains[0].bind(&x64).log_prob(&npe.to_v_wide(&theta))[0] + npe.log_jacobian(&theta);
            assert!((q - (log_n - ld)).abs() < 1e-6, "log q {q} vs log N − log-det {}", log_n - ld);
        }
    }
}
