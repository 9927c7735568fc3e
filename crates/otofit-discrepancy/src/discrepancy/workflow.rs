//! The whole diagnosis: fit (NPE) → check (posterior predictive, calibrated null) →
//! locate (bands) → name (candidate effects) → add (extend the prior, simulate, retrain)
//! → show (before/after numbers). Returns a report of data only; `plot::diagnosis` draws
//! it and writes the files.

#![warn(missing_docs)]

use super::fitcheck::present_groups;
use super::{Band, Observation, Thresholds, Verdict, fit, fit_and_rank, locate};
use crate::npe::{self, Dataset, DiagnoseNull, DiagnoseSubsetNull, Npe, NpeError, Obs, TrainSettings};
use crate::sim::batch::{Design, Noise, run_rows};
use crate::sim::output::{MEASURES, feature_names};
use crate::sim::params::{EFFECTS, N_PARAMS};
use crate::sim::{Model, SimError};
use crate::stats;
use serde::Serialize;
use std::sync::Arc;
use std::sync::atomic::AtomicBool;

/// How to run the workflow.
#[derive(Clone, Debug)]
pub struct Settings {
    /// Effect indices to try.
    pub candidates: Vec<usize>,
    /// Extend, simulate and retrain when an effect is named.
    pub extend: bool,
    /// Posterior draws re-simulated for the predictive check.
    pub draws: usize,
    /// Effect-free simulations for the null distribution of the statistics.
    pub null_cases: usize,
    /// Training set size of the extended model.
    pub train_rows: usize,
    /// Epochs at most of the extended model's training.
    pub max_epochs: usize,
    /// Seed of the null simulations, the fits' starts and the extended training.
    pub seed: u64,
    /// Thresholds measured earlier for the same base model (skips the null runs).
    pub thresholds: Option<Thresholds>,
    /// Measure the null for this ear even when the model stores one that applies.
    pub measure_null: bool,
    /// Set from outside to stop the workflow: checked between steps, null cases,
    /// simulation chunks and training epochs; the workflow then returns [`DiagnoseError::Cancelled`].
    pub cancel: Option<Arc<AtomicBool>>,
}

/// Errors of the workflow: the caller's input at fault ([`DiagnoseError::is_input`]), a
/// cancellation, or an internal failure.
#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum DiagnoseError {
    /// The workflow stopped because [`Settings::cancel`] was set.
    #[error("the diagnosis was cancelled")]
    Cancelled,
    /// The base model is not one of otofit's simulator (bad input).
    #[error("the base model must be an otofit model of the seven parameters on the simulator's grid")]
    NotBaseModel,
    /// The observation's length is not the model's feature count (bad input).
    #[error("the observation has {got} features, the model has {expected}")]
    Observation {
        /// Features given.
        got: usize,
        /// Features of the base model.
        expected: usize,
    },
    /// The posterior estimator failed (input or internal, as the error says).
    #[error(transparent)]
    Npe(#[from] NpeError),
    /// The MAP could not be simulated (internal).
    #[error("the MAP re-simulation failed")]
    Sim(#[from] SimError),
    /// Most posterior draws failed to simulate (internal).
    #[error("most posterior draws failed to simulate")]
    DrawsFailed,
    /// The least-squares base fit failed (internal).
    #[error("the base fit failed")]
    BaseFitFailed,
    /// A null to store was asked for a feature set that is not made of whole groups.
    #[error("a stored null needs each feature group given whole or not at all")]
    PartialGroups,
}

impl DiagnoseError {
    /// Whether the caller's input is at fault.
    pub fn is_input(&self) -> bool {
        match self {
            DiagnoseError::NotBaseModel | DiagnoseError::Observation { .. } | DiagnoseError::PartialGroups => true,
            DiagnoseError::Npe(e) => e.is_input(),
            _ => false,
        }
    }
}

/// Results of the workflow.
pub type Result<T, E = DiagnoseError> = std::result::Result<T, E>;

impl Settings {
    fn cancelled(&self) -> bool {
        super::stopped(self.cancel.as_deref())
    }

    /// `Err(Cancelled)` once cancellation was requested.
    fn go_on(&self) -> Result<()> {
        if self.cancelled() { Err(DiagnoseError::Cancelled) } else { Ok(()) }
    }
}

impl Default for Settings {
    fn default() -> Self {
        Settings {
            candidates: (0..EFFECTS.len()).collect(),
            extend: true,
            draws: 200,
            null_cases: 40,
            train_rows: 10_000,
            max_epochs: 300,
            seed: 0,
            thresholds: None,
            measure_null: false,
            cancel: None,
        }
    }
}

/// Posterior-predictive check of one model against the observation.
#[derive(Clone, Debug, Serialize)]
pub struct Check {
    /// Reduced χ² of the observation against the posterior predictive.
    pub reduced_chi2: f64,
    /// Standardised residuals (obs − predictive mean)/σ_total per feature.
    #[serde(skip)]
    pub z: Vec<f64>,
    /// Where the misfit lies (|z| > 2.5 over at least 3 neighbouring frequencies).
    pub bands: Vec<Band>,
    /// Spearman ρ per measure between the MAP re-simulation and the observation.
    pub spearman: Vec<(String, f64)>,
    /// The MAP re-simulated.
    #[serde(skip)]
    pub map_x: Vec<f64>,
    /// Lower edge of the 90 % predictive band (noise included).
    #[serde(skip)]
    pub lo: Vec<f64>,
    /// Upper edge of the 90 % predictive band (noise included).
    #[serde(skip)]
    pub hi: Vec<f64>,
    /// Up to five posterior draws re-simulated.
    #[serde(skip)]
    pub draws_x: Vec<Vec<f64>>,
}

/// The named effect's posterior under the extended model.
#[derive(Clone, Debug, Serialize)]
pub struct EffectPosterior {
    /// The effect.
    pub effect: &'static str,
    /// Its unit.
    pub unit: &'static str,
    /// Posterior median.
    pub median: f64,
    /// 5 % quantile.
    pub q05: f64,
    /// 95 % quantile.
    pub q95: f64,
}

/// Where a diagnosis' alarm thresholds came from.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize)]
#[serde(tag = "source", rename_all = "snake_case")]
pub enum NullSource {
    /// Stored in the model (`otofit calibrate --diagnose-null`), measured on `cases` ears.
    Model {
        /// Effect-free cases behind them.
        cases: usize,
    },
    /// Measured for this ear on `cases` effect-free simulations.
    Measured {
        /// Effect-free cases asked for.
        cases: usize,
    },
    /// Given by the caller (a benchmark measuring them once for many ears).
    Given,
}

impl NullSource {
    /// Where the thresholds came from, in words.
    pub fn describe(&self) -> String {
        match self {
            NullSource::Model { cases } => format!("the model's null, measured on {cases} effect-free ears"),
            NullSource::Measured { cases } => format!("measured for this ear on {cases} effect-free ears"),
            NullSource::Given => "given by the caller".to_string(),
        }
    }
}

/// The outcome of one diagnosis: data only (`plot::diagnosis` draws and writes it).
#[derive(Serialize)]
pub struct Report {
    /// No discrepancy, an effect named, or unexplained.
    pub verdict: Verdict,
    /// The alarm thresholds used.
    pub thresholds: Thresholds,
    /// Where the thresholds came from.
    pub null: NullSource,
    /// The base model's predictive check.
    pub before: Check,
    /// The candidate effects' fits, best first.
    pub candidates: Vec<super::Candidate>,
    /// The effect named, if any.
    pub named: Option<&'static str>,
    /// Best χ² drop minus the runner-up's.
    pub margin: Option<f64>,
    /// The extended model's predictive check, when one was trained.
    pub after: Option<Check>,
    /// The effect's posterior under the extended model.
    pub effect_posterior: Option<EffectPosterior>,
    /// The base model's MAP.
    pub map_before: Vec<f64>,
    /// The extended model's MAP.
    pub map_after: Option<Vec<f64>>,
    /// The extended model, when one was trained.
    #[serde(skip)]
    pub extended_model: Option<Npe>,
    /// The observation diagnosed (for the figures).
    #[serde(skip)]
    pub observation: Vec<f64>,
    /// The observation's frequency grid.
    #[serde(skip)]
    pub frequencies_hz: Vec<f64>,
    /// Wall time of the diagnosis.
    pub seconds: f64,
}

fn wrap(i: usize, nf: usize, d: f64) -> f64 {
    fit::feature_residual(i, nf, d, 0.0)
}

/// Re-simulates posterior draws (rows in `design` order) and compares with `obs`.
pub fn check(model: &Model, design: &Design, draws: &[Vec<f64>], map: &[f64], obs: &Observation) -> Result<Check> {
    check_present(model, design, draws, map, obs, None)
}

/// `check` over the features marked present (`None`: all); absent features get z = 0
/// and stay out of the reduced χ² and the Spearman ρ.
pub fn check_present(
    model: &Model,
    design: &Design,
    draws: &[Vec<f64>],
    map: &[f64],
    obs: &Observation,
    present: Option<&[bool]>,
) -> Result<Check> {
    // The draws and the MAP in one batch: one fan-out over the cores instead of a second
    // one for the MAP alone.
    let mut rows = draws.to_vec();
    rows.push(map.to_vec());
    let mut runs = run_rows(model, design, &rows, 0, None);
    let map_run = runs.pop().ok_or(DiagnoseError::DrawsFailed)?;
    let sims: Vec<Vec<f64>> = runs.into_iter().filter_map(|r| r.ok()).collect();
    if sims.len() < draws.len() / 2 {
        return Err(DiagnoseError::DrawsFailed);
    }
    let map_x = map_run?;
    let nf = obs.x.len() / MEASURES.len();
    let mut z = Vec::with_capacity(obs.x.len());
    let (mut lo, mut hi) = (Vec::new(), Vec::new());
    for i in 0..obs.x.len() {
        // Residuals relative to the MAP spectrum keep phase wraps out of the spread.
        let d: Vec<f64> = sims.iter().map(|s| wrap(i, nf, s[i] - map_x[i])).collect();
        let (mean, var) = stats::mean_var_sample(&d);
        let centre = map_x[i] + mean;
        let on = present.is_none_or(|p| p[i]) && obs.x[i].is_finite();
        z.push(if on { wrap(i, nf, obs.x[i] - centre) / (var + obs.sigma[i].powi(2)).sqrt() } else { 0.0 });
        // Floor ranks: the band of few draws never rests on its outermost draw.
        let sorted = stats::sorted(d);
        lo.push(map_x[i] + stats::quantile_floor(&sorted, 0.05) - 1.645 * obs.sigma[i]);
        hi.push(map_x[i] + stats::quantile_floor(&sorted, 0.95) + 1.645 * obs.sigma[i]);
    }
    let freqs = model.frequencies();
    let on = |i: usize| present.is_none_or(|p| p[i]) && obs.x[i].is_finite();
    let spearman = MEASURES
        .iter()
        .enumerate()
        .zip(stats::spearman_per_block(&map_x, &obs.x, MEASURES.len()))
        .filter(|((m, _), _)| (m * nf..(m + 1) * nf).all(on))
        .map(|((_, ms), r)| (ms.name.to_string(), r))
        .collect();
    let used = (0..z.len()).filter(|&i| on(i)).count().max(1);
    let reduced_chi2 = z.iter().map(|v| v * v).sum::<f64>() / used as f64;
    Ok(Check {
        reduced_chi2,
        bands: locate(&z, freqs, 2.5, 3),
        z,
        spearman,
        map_x,
        lo,
        hi,
        draws_x: sims.into_iter().take(5).collect(),
    })
}

/// Rows simulated between two cancellation checks.
const CHUNK: usize = 1024;

/// Simulates a training set for `design` and trains an estimator on it, on the features
/// marked in `given` (those the observation has), stopping with
/// [`DiagnoseError::Cancelled`] between simulation chunks and epochs once `cancelled()` says so.
#[allow(clippy::too_many_arguments)]
pub fn train_for(
    model: &Model,
    design: &Design,
    noise: &Noise,
    given: &[bool],
    rows: usize,
    max_epochs: usize,
    seed: u64,
    progress: &mut dyn FnMut(&str),
    cancelled: &dyn Fn() -> bool,
) -> Result<Npe> {
    let theta = design.draw(seed, 0, rows);
    let mut out = Vec::with_capacity(theta.len());
    for (k, chunk) in theta.chunks(CHUNK).enumerate() {
        if cancelled() {
            return Err(DiagnoseError::Cancelled);
        }
        out.extend(run_rows(model, design, chunk, k * CHUNK, None));
    }
    let keep = |v: Vec<f64>| -> Vec<f64> { v.into_iter().zip(given).filter(|(_, g)| **g).map(|(f, _)| f).collect() };
    let (mut t, mut x) = (Vec::new(), Vec::new());
    for (row, r) in theta.into_iter().zip(out) {
        if let Ok(v) = r
            && v.iter().all(|f| f.is_finite())
        {
            t.push(row);
            x.push(keep(v));
        }
    }
    let names = feature_names(model.frequencies()).into_iter().zip(given).filter(|(_, g)| **g).map(|(n, _)| n);
    let ds = Dataset {
        params: design.columns().iter().map(npe::Param::from).collect(),
        feature_names: names.collect(),
        frequencies_hz: model.frequencies().to_vec(),
        groups: vec![],
        noise_std: keep(noise.std.clone()),
        theta: t,
        x,
        skipped: 0,
    };
    let s = TrainSettings { seed, max_epochs, noise_scale: 1.0, ..TrainSettings::default() };
    let npe = npe::train(&ds, &s, &mut |e| {
        progress(&format!("training the extended model: epoch {} val {:.3}", e.epoch, e.val_loss));
        !cancelled()
    })?;
    // A training stopped early returns its best weights; a cancelled one returns nothing.
    if cancelled() {
        return Err(DiagnoseError::Cancelled);
    }
    Ok(npe)
}

/// Quantile of the null at which each of the two alarm statistics fires: a Bonferroni
/// split of a 5 % false-alarm budget between them (at 95 % each, 12 % of effect-free
/// cases raised an alarm).
pub const ALARM_QUANTILE: f64 = 0.975;

/// The null: effect-free simulations from the prior, pushed through the same fit and
/// candidate ranking; their `ALARM_QUANTILE` quantiles are the alarm thresholds.
/// `given`: the features the observation has; the null's ears lack the same ones.
/// Also returns how many ears the null holds (those that simulated).
pub fn null_thresholds(
    model: &Model,
    base: &Npe,
    noise: &Noise,
    given: &[bool],
    s: &Settings,
) -> Result<(Thresholds, usize)> {
    let sims = null_simulations(model, noise, s)?;
    let (chi, drops) = null_statistics(model, base, noise, &sims, given, s)?;
    Ok((thresholds_of(chi, drops), sims.len()))
}

/// The null measured once for each feature set in `given_sets` (the same effect-free
/// ears, each with the features outside its set removed), to be stored in the model:
/// a diagnosis with the model's null skips the per-ear null, its slowest stage.
pub fn measure_null(
    model: &Model,
    base: &Npe,
    noise: &Noise,
    given_sets: &[Vec<bool>],
    s: &Settings,
    progress: &mut dyn FnMut(usize, usize),
) -> Result<DiagnoseNull> {
    let mut sims = null_simulations(model, noise, s)?;
    // With the model error the base model was trained with, if any: what its ears are.
    base.add_model_error(&mut sims, s.seed)?;
    let mut subsets = Vec::with_capacity(given_sets.len());
    for (k, given) in given_sets.iter().enumerate() {
        progress(k, given_sets.len());
        let groups = groups_given(base, given).ok_or(DiagnoseError::PartialGroups)?;
        let (chi, drops) = null_statistics(model, base, noise, &sims, given, s)?;
        let t = thresholds_of(chi, drops);
        subsets.push(DiagnoseSubsetNull { groups, base_reduced_chi2: t.base_reduced_chi2, best_drop: t.best_drop });
    }
    progress(given_sets.len(), given_sets.len());
    Ok(DiagnoseNull {
        quantile: ALARM_QUANTILE,
        cases: sims.len(),
        draws: s.draws,
        candidates: s.candidates.iter().map(|&e| EFFECTS[e].name.to_string()).collect(),
        subsets,
        fit_version: super::CANDIDATE_FIT_VERSION,
    })
}

/// The thresholds the model stores for this observation's feature groups, when they
/// were measured with the same draws, the same candidate fit and with every candidate
/// asked for (a best drop over more candidates is never smaller, so a superset errs
/// toward fewer alarms).
pub fn stored_thresholds(base: &Npe, given: &[bool], s: &Settings) -> Option<(Thresholds, usize)> {
    let null = base.header.diagnose_null.as_ref()?;
    let same_statistic = null.draws == s.draws
        && (null.quantile - ALARM_QUANTILE).abs() < 1e-12
        && null.fit_version == super::CANDIDATE_FIT_VERSION;
    let covered = s.candidates.iter().all(|&e| null.candidates.iter().any(|c| c == EFFECTS[e].name));
    let groups = groups_given(base, given)?;
    let t = null.subsets.iter().find(|x| x.groups == groups).filter(|_| same_statistic && covered)?;
    Some((
        Thresholds { base_reduced_chi2: t.base_reduced_chi2, best_drop: t.best_drop, explained: EXPLAINED },
        null.cases,
    ))
}

/// The sorted names of the feature groups `given` holds, when it holds each group whole
/// (a band-limited observation has no stored null); the empty list for a model without
/// groups given every feature.
pub fn groups_given(base: &Npe, given: &[bool]) -> Option<Vec<String>> {
    let groups = &base.header.groups;
    if groups.is_empty() {
        return given.iter().all(|g| *g).then(Vec::new);
    }
    let names = present_groups(base, given);
    // The groups touched must be given whole: as many features as they hold.
    let whole: usize = groups.iter().filter(|g| names.contains(&g.name)).map(|g| g.features.len()).sum();
    (whole == given.iter().filter(|g| **g).count()).then_some(names)
}

/// A named effect must bring the reduced χ² at or below this.
const EXPLAINED: f64 = 1.5;

fn thresholds_of(chi: Vec<f64>, drops: Vec<f64>) -> Thresholds {
    let quantile = |v| super::null_quantile(v, ALARM_QUANTILE);
    Thresholds { base_reduced_chi2: quantile(chi), best_drop: quantile(drops), explained: EXPLAINED }
}

/// The null's effect-free ears: prior draws with the base noise (failed runs dropped).
fn null_simulations(model: &Model, noise: &Noise, s: &Settings) -> Result<Vec<Vec<f64>>> {
    let design = Design::default();
    let rows = design.draw(s.seed ^ 0x4E55, 0, s.null_cases);
    let noisy = Noise { seed: s.seed ^ 0x4E55, ..noise.clone() };
    let mut sims = Vec::with_capacity(rows.len());
    // Smaller chunks than the training set's: each null row costs a full fit afterwards.
    for (k, chunk) in rows.chunks(CHUNK / 16).enumerate() {
        s.go_on()?;
        sims.extend(run_rows(model, &design, chunk, k * (CHUNK / 16), Some(&noisy)).into_iter().filter_map(|r| r.ok()));
    }
    Ok(sims)
}

/// The two alarm statistics of each null ear with only `given` features: the base
/// model's reduced χ² and, where the fits converge, the best candidate's χ² drop. Ears
/// run one after another (each fit spreads its candidates over the cores): a cancel then
/// waits for one ear's fits, not for one per core.
fn null_statistics(
    model: &Model,
    base: &Npe,
    noise: &Noise,
    sims: &[Vec<f64>],
    given: &[bool],
    s: &Settings,
) -> Result<(Vec<f64>, Vec<f64>)> {
    let design = Design::default();
    let per_case: Vec<(f64, Option<f64>)> = sims
        .iter()
        .enumerate()
        .map(|(k, x)| {
            s.go_on()?;
            let mut x = x.clone();
            x.iter_mut().zip(given).filter(|(_, g)| !**g).for_each(|(v, _)| *v = f64::NAN);
            let obs = Observation { x, sigma: noise.std.clone() };
            let inf = base.infer(&Obs { x: &obs.x, present: None }, s.draws, s.seed + k as u64)?;
            s.go_on()?;
            let c = check(model, &design, &inf.samples[..s.draws.min(inf.samples.len())], &inf.map, &obs)?;
            s.go_on()?;
            let drop = fit_and_rank(model, &obs, std::slice::from_ref(&inf.map), &s.candidates, s.cancel.as_deref())
                .map(|(b, ranked)| ranked.first().map_or(0.0, |c| b.chi2 - c.chi2));
            Ok((c.reduced_chi2, drop))
        })
        .collect::<Result<_>>()?;
    Ok((per_case.iter().map(|c| c.0).collect(), per_case.iter().filter_map(|c| c.1).collect()))
}

/// The workflow's stages, in order, as its progress messages start.
pub const STAGES: [&str; 6] = ["fit", "check", "null", "name", "add", "training"];

/// The stage (index into [`STAGES`]) a progress message of [`diagnose`] belongs to (by
/// its first word: "name: fitting …" is the naming stage, not the fit).
pub fn stage_of(message: &str) -> usize {
    STAGES.iter().position(|s| message.starts_with(s)).unwrap_or(0)
}

/// Runs the workflow for one observation (features in otofit's order) with a base model.
pub fn diagnose(model: &Model, base: &Npe, x: &[f64], s: &Settings, progress: &mut dyn FnMut(&str)) -> Result<Report> {
    let t0 = std::time::Instant::now();
    let given = given_features(model, base, x)?;
    let noise = Noise { std: base.header.noise_std.clone(), scale: 1.0, seed: s.seed };
    let obs = Observation { x: x.to_vec(), sigma: noise.std.clone() };
    progress("fit: base posterior");
    let inf = base.infer(&Obs { x, present: None }, s.draws.max(200), s.seed)?;
    s.go_on()?;
    progress("check: posterior predictive");
    let base_design = Design::default();
    let before = check(model, &base_design, &inf.samples[..s.draws.min(inf.samples.len())], &inf.map, &obs)?;
    let stored = if s.measure_null { None } else { stored_thresholds(base, &given, s) };
    let (thresholds, null) = match (s.thresholds, stored) {
        (Some(t), _) => (t, NullSource::Given),
        (None, Some((t, cases))) => (t, NullSource::Model { cases }),
        (None, None) => {
            progress("null distribution of the statistics");
            let (t, cases) = null_thresholds(model, base, &noise, &given, s)?;
            (t, NullSource::Measured { cases })
        }
    };
    s.go_on()?;
    progress("name: fitting candidate effects");
    let median: Vec<f64> = inf.summaries.iter().map(|p| p.median).collect();
    let (base_fit, ranked) = fit_and_rank(model, &obs, &[inf.map.clone(), median], &s.candidates, s.cancel.as_deref())
        .ok_or_else(|| if s.cancelled() { DiagnoseError::Cancelled } else { DiagnoseError::BaseFitFailed })?;
    // Alarm: either statistic beyond its null quantile. Candidate: the best effect if its
    // χ² drop beats both the BIC penalty and the null quantile of the best drop.
    s.go_on()?;
    let best_drop = ranked.first().map_or(0.0, |c| base_fit.chi2 - c.chi2);
    let alarm = before.reduced_chi2 > thresholds.base_reduced_chi2 || best_drop > thresholds.best_drop;
    let candidate = ranked.first().filter(|c| c.score > 0.0 && best_drop > thresholds.best_drop).map(|c| c.effect);
    let margin = (ranked.len() > 1).then(|| ranked[0].score - ranked[1].score);
    let (after, effect_posterior, map_after, extended) = match (candidate, s.extend && alarm) {
        (Some(name), true) => {
            let e = extend(model, name, &noise, &given, &obs, s, progress)?;
            (Some(e.after), Some(e.effect_posterior), Some(e.map_after), Some(e.model))
        }
        _ => (None, None, None, None),
    };
    let (verdict, named) = decide(alarm, candidate, &ranked, after.as_ref(), &thresholds);
    s.go_on()?;
    Ok(Report {
        verdict,
        thresholds,
        null,
        before,
        candidates: ranked,
        named,
        margin,
        after,
        effect_posterior,
        map_before: inf.map,
        map_after,
        extended_model: extended,
        observation: obs.x,
        frequencies_hz: model.frequencies().to_vec(),
        seconds: t0.elapsed().as_secs_f64(),
    })
}

/// Which features the observation gives, once it is known to fit the base model. Absent
/// features (NaN: a measure not taken) stay out of every statistic; the base model must
/// accept the subset (group masks), and the extended one is trained on it.
fn given_features(model: &Model, base: &Npe, x: &[f64]) -> Result<Vec<bool>> {
    if base.header.feature_names != feature_names(model.frequencies()) || base.params().len() != N_PARAMS {
        return Err(DiagnoseError::NotBaseModel);
    }
    if x.len() != base.header.feature_names.len() {
        return Err(DiagnoseError::Observation { got: x.len(), expected: base.header.feature_names.len() });
    }
    let given: Vec<bool> = x.iter().map(|v| v.is_finite()).collect();
    if !given.iter().any(|g| *g) {
        return Err(DiagnoseError::Observation { got: 0, expected: x.len() });
    }
    Ok(given)
}

/// The base model extended by the named effect, and what it says about the observation.
struct Extension {
    after: Check,
    effect_posterior: EffectPosterior,
    map_after: Vec<f64>,
    model: Npe,
}

/// Adds effect `name` to the prior, trains an estimator on simulations of it and checks
/// the observation against the new posterior: the step that shows whether the effect
/// really explains the data, not only fits it.
fn extend(
    model: &Model,
    name: &'static str,
    noise: &Noise,
    given: &[bool],
    obs: &Observation,
    s: &Settings,
    progress: &mut dyn FnMut(&str),
) -> Result<Extension> {
    let e = EFFECTS.iter().position(|x| x.name == name).expect("named effect");
    let design = Design { varied: vec![e], ..Design::default() };
    progress(&format!("add: simulating {} rows with {name} in the prior", s.train_rows));
    let cancelled = || s.cancelled();
    let npe2 = train_for(model, &design, noise, given, s.train_rows, s.max_epochs, s.seed, progress, &cancelled)?;
    s.go_on()?;
    let x_given: Vec<f64> = obs.x.iter().copied().filter(|v| v.is_finite()).collect();
    let inf2 = npe2.infer(&Obs { x: &x_given, present: None }, s.draws.max(200), s.seed)?;
    let c2 = check(model, &design, &inf2.samples[..s.draws.min(inf2.samples.len())], &inf2.map, obs)?;
    let p = &inf2.summaries[N_PARAMS];
    Ok(Extension {
        after: c2,
        effect_posterior: EffectPosterior {
            effect: name,
            unit: EFFECTS[e].unit,
            median: p.median,
            q05: p.q05,
            q95: p.q95,
        },
        map_after: inf2.map.clone(),
        model: npe2,
    })
}

/// The verdict and the effect named. Named when the candidate's fit explains the data:
/// by its direct fit, or (when the model was extended) by the retrained posterior's
/// predictive check.
fn decide(
    alarm: bool,
    candidate: Option<&'static str>,
    ranked: &[super::Candidate],
    after: Option<&Check>,
    thresholds: &Thresholds,
) -> (Verdict, Option<&'static str>) {
    let explained = |c: &super::Candidate| {
        c.reduced_chi2 <= thresholds.explained || after.is_some_and(|a: &Check| a.reduced_chi2 <= thresholds.explained)
    };
    let v = match (alarm, ranked.first().filter(|c| Some(c.effect) == candidate)) {
        (false, _) => Verdict::NoDiscrepancy,
        (true, Some(c)) if explained(c) => Verdict::EffectNamed,
        _ => Verdict::Unexplained,
    };
    let named = (v == Verdict::EffectNamed).then_some(candidate).flatten();
    (v, named)
}

#[cfg(test)]
mod tests {
    #[test]
    fn each_progress_message_names_its_stage() {
        let stage = |m: &str| super::STAGES[super::stage_of(m)];
        assert_eq!(stage("fit: base posterior"), "fit");
        assert_eq!(stage("check: posterior predictive"), "check");
        assert_eq!(stage("name: fitting candidate effects"), "name");
        assert_eq!(stage("null distribution of the statistics"), "null");
        assert_eq!(stage("add: simulating 10000 rows with cavity in the prior"), "add");
        assert_eq!(stage("training the extended model: epoch 3 val 1.2"), "training");
    }
}
