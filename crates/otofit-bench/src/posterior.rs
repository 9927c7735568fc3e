//! The shipped amortized posterior (the flow of a model such as `models/default.otofit`)
//! against the posterior under the model's own likelihood (`discrepancy::exact`:
//! least-squares fits from the flow's MAP and draws, and four adaptive Metropolis chains
//! in the flow's latent space),
//! on held-out simulated ears: `otofit bench posterior`.
//!
//! The flow is trained to be calibrated on average over the prior; the chain is exact for
//! each ear under the model, up to its sampling error. Where two parameters trade off
//! against each other (a degeneracy of the simulator), an amortized flow is most likely to
//! be too wide or to put its mass in the wrong place, so half the ears are drawn there.
//!
//! Ears (deterministic for the seed): the first ⌈N/2⌉ are prior draws (`Design::draw`, as
//! `otofit simulate` draws them); the rest cycle through [`RECIPES`], each a prior draw
//! with two tissue parameters moved near chosen ends of their prior boxes. Every ear gets
//! otofit's 1× test–retest noise (`default_noise_std`), one noise stream per ear.
//!
//! Scores per tissue parameter (the seven read against normal ranges), for the flow and
//! the chain: how often the central 50 % and 90 % intervals hold the truth; the width of the
//! 90 % interval on the parameter's scale (log10 units for log-scale parameters) and its
//! ratio flow/exact per ear; confident wrong readings (`normal::read` says below or above
//! while the truth lies within the normal range or on its other side). Per ear: C2ST
//! between the flow's draws and the chain's over the tissue parameters, and each method's
//! wall time.

use crate::c2st::{self, C2stParams};
use anyhow::{Result, anyhow, bail};
use otofit_discrepancy::discrepancy::exact::MAX_STEPS;
use otofit_discrepancy::discrepancy::exact_fast::by_segments;
use otofit_discrepancy::discrepancy::fitcheck::{SETTLED_RHAT, exact, simulator_for};
use otofit_npe::npe::normal::{self, Differential};
use otofit_npe::npe::prior::space;
use otofit_npe::npe::{Npe, Obs, Param};
use otofit_npe::stats;
use otofit_sim::batch::{Design, Noise, default_noise_std, run_rows};
use otofit_sim::{N_TISSUE, PARAMS};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use serde::Serialize;
use std::fmt::Write;
use std::time::Instant;

/// Posterior samples the flow draws per ear (the CLI's and the service's default).
pub const FLOW_SAMPLES: usize = 1000;

/// Draws per method in each C2ST: the flow's first ones and the chain's evenly thinned.
pub const C2ST_DRAWS: usize = 1000;

/// Chain steps by default: the length `otofit infer --exact` requires, measured
/// calibrated (`discrepancy::exact::MIN_STEPS`; 20,000 steps under-covered). About 9 s per
/// ear, so `--ears 4` takes under a minute on two cores.
pub const DEFAULT_STEPS: usize = otofit_discrepancy::discrepancy::exact::MIN_STEPS;

/// Fewest chain steps: a quarter is burn-in and every tenth of the rest is kept, so this
/// leaves 300 draws for the 5 % and 95 % quantiles.
pub const MIN_STEPS: usize = 4_000;

/// Most ears in one run.
pub const MAX_EARS: usize = 10_000;

/// The target on the flow's 90 % interval: at most this many times the chain's width.
pub const WIDTH_TARGET: f64 = 1.5;

/// The target on the flow's coverage: within this of the nominal 0.5 and 0.9.
pub const COVERAGE_TOLERANCE: f64 = 0.03;

/// Which end of its prior box a recipe moves a parameter to.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize)]
#[serde(rename_all = "lowercase")]
pub enum End {
    /// Position 0.03–0.15 in the box (on the parameter's scale).
    Low,
    /// Position 0.85–0.97 in the box.
    High,
}

impl End {
    /// The band of box positions drawn from: near the end, not on it, so that the
    /// truth stays representable (the flow, which the chains work through, has no mass
    /// on a bound, and the reading calls a posterior piled within 2.5 % of a bound
    /// undetermined).
    pub fn band(self) -> (f64, f64) {
        match self {
            End::Low => (0.03, 0.15),
            End::High => (0.85, 0.97),
        }
    }
}

/// A way to place an ear near one of the model's degeneracies: two tissue parameters
/// (indices into `PARAMS`) moved near the given ends of their boxes, the rest from the prior.
#[derive(Clone, Copy, Debug, Serialize)]
pub struct Recipe {
    /// Name, as in the JSON and the group table.
    pub name: &'static str,
    /// The parameters moved and where.
    pub pins: [(usize, End); 2],
}

/// The degeneracy recipes, cycled through by the second half of the ears. The malleus'
/// suspension has two stiffnesses in parallel (E_ligaments, E_tendons), so raising or
/// lowering both shows mostly as their sum; a stiff drum with soft joints and a soft
/// drum with stiff joints move the low-frequency impedance in opposite directions and
/// can partly cancel.
pub const RECIPES: [Recipe; 4] = [
    Recipe { name: "ligaments_tendons_high", pins: [(1, End::High), (2, End::High)] },
    Recipe { name: "ligaments_tendons_low", pins: [(1, End::Low), (2, End::Low)] },
    Recipe { name: "eardrum_high_joints_low", pins: [(0, End::High), (4, End::Low)] },
    Recipe { name: "eardrum_low_joints_high", pins: [(0, End::Low), (4, End::High)] },
];

/// One held-out ear: what it is (`prior` or a recipe's name) and its parameter row.
#[derive(Clone, Debug)]
pub struct Ear {
    /// `prior` or the recipe's name.
    pub kind: &'static str,
    /// Its parameters (design column order, natural units).
    pub row: Vec<f64>,
}

/// The `n` ears of `seed`: ⌈n/2⌉ prior draws, then the recipes in turn.
pub fn ears(n: usize, seed: u64) -> Vec<Ear> {
    let prior = n - n / 2;
    Design::default()
        .draw(seed, 0, n)
        .into_iter()
        .enumerate()
        .map(|(i, mut row)| {
            if i < prior {
                return Ear { kind: "prior", row };
            }
            let recipe = &RECIPES[(i - prior) % RECIPES.len()];
            // Its own stream, apart from the prior draw's and the noise's.
            let mut rng = ChaCha8Rng::seed_from_u64(seed ^ 0x5eed_0fea);
            rng.set_stream(i as u64);
            for &(k, end) in &recipe.pins {
                let (low, high) = end.band();
                row[k] = PARAMS[k].from_unit(rng.random_range(low..high));
            }
            Ear { kind: recipe.name, row }
        })
        .collect()
}

/// The highest `--from-hz`: every sub-band a model accepts reaches 494 Hz.
pub const MAX_FROM_HZ: f64 = 500.0;

/// How big a run is.
#[derive(Clone, Debug)]
pub struct PosteriorParams {
    /// Held-out ears.
    pub ears: usize,
    /// Seed of the ears, their noise, the flow's draws, the chains and the C2STs.
    pub seed: u64,
    /// Metropolis steps per chain.
    pub steps: usize,
    /// Feature groups given (every feature when empty), as a clinic's subset of measures:
    /// the flow that answers them and the likelihood of those features alone.
    pub measures: Vec<String>,
    /// The lowest frequency given (Hz; 0: the whole grid), as a device that exports from
    /// 226 Hz: features below it are left out of the flow's input and of the likelihood.
    pub from_hz: f64,
}

impl Default for PosteriorParams {
    fn default() -> Self {
        PosteriorParams { ears: 20, seed: 1, steps: DEFAULT_STEPS, measures: vec![], from_hz: 0.0 }
    }
}

impl PosteriorParams {
    /// Refuses sizes the benchmark cannot run, naming the CLI's argument.
    pub fn check(&self) -> Result<()> {
        if !(1..=MAX_EARS).contains(&self.ears) {
            bail!("--ears must be 1..={MAX_EARS} (got {})", self.ears);
        }
        if !(MIN_STEPS..=MAX_STEPS).contains(&self.steps) {
            bail!("--steps must be {MIN_STEPS}..={MAX_STEPS} (got {})", self.steps);
        }
        check_from_hz(self.from_hz)
    }
}

/// Refuses a `--from-hz` outside 0..=[`MAX_FROM_HZ`], naming the argument.
pub fn check_from_hz(from_hz: f64) -> Result<()> {
    if !(from_hz.is_finite() && (0.0..=MAX_FROM_HZ).contains(&from_hz)) {
        bail!("--from-hz must be 0..={MAX_FROM_HZ} Hz (got {from_hz})");
    }
    Ok(())
}

/// One method's posterior of one parameter, against the truth.
#[derive(Clone, Debug, Serialize)]
pub struct Marginal {
    /// The central 50 % interval holds the truth.
    pub in50: bool,
    /// The central 90 % interval holds the truth.
    pub in90: bool,
    /// The central 90 % interval's width on the parameter's scale (log10 units on a log
    /// scale).
    pub width90: f64,
    /// `normal::read`'s reading of the draws (`none` for a parameter without a range).
    pub reading: &'static str,
    /// The reading is below or above and the truth is not.
    pub confident_wrong: bool,
}

/// Both methods on one parameter of one ear.
#[derive(Clone, Debug, Serialize)]
pub struct ParamScore {
    /// The parameter.
    pub name: String,
    /// The true value (natural units).
    pub truth: f64,
    /// The flow's posterior.
    pub flow: Marginal,
    /// The chain's posterior.
    pub exact: Marginal,
    /// `flow.width90 / exact.width90`.
    pub width_ratio: f64,
}

/// The central `level` interval of ascending `sorted` (quantiles interpolated linearly,
/// as the posterior summaries take them).
pub fn central(sorted: &[f64], level: f64) -> (f64, f64) {
    let tail = (1.0 - level) / 2.0;
    (stats::quantile_linear(sorted, tail), stats::quantile_linear(sorted, 1.0 - tail))
}

/// Whether a below or above reading is contradicted by the truth: it lies within the
/// normal range or on its other side.
pub fn contradicted(reading: &Differential, truth: f64) -> bool {
    match reading.reading {
        "below" => truth >= reading.normal_low,
        "above" => truth <= reading.normal_high,
        _ => false,
    }
}

/// Parameter `k` of `draws` against `truth`, with the draws' normal-range readings.
fn marginal(p: &Param, k: usize, truth: f64, draws: &[Vec<f64>], readings: &[Differential]) -> Marginal {
    let col = stats::sorted(draws.iter().map(|d| space::coord(p.scale, d[k])).collect());
    let t = space::coord(p.scale, truth);
    let holds = |level: f64| {
        let (low, high) = central(&col, level);
        (low..=high).contains(&t)
    };
    let (low, high) = central(&col, 0.9);
    let reading = readings.iter().find(|r| r.name == p.name);
    Marginal {
        in50: holds(0.5),
        in90: holds(0.9),
        width90: high - low,
        reading: reading.map_or("none", |r| r.reading),
        confident_wrong: reading.is_some_and(|r| contradicted(r, truth)),
    }
}

/// Each parameter of `params` in `draws` against `truth` (one method alone).
pub fn marginals(params: &[Param], truth: &[f64], draws: &[Vec<f64>]) -> Vec<Marginal> {
    let readings = normal::read(params, draws);
    params.iter().enumerate().map(|(k, p)| marginal(p, k, truth[k], draws, &readings)).collect()
}

/// Scores the flow's and the chain's draws (rows in `params` order, natural units) of one
/// ear against its `truth`, for every parameter in `params`.
pub fn score(params: &[Param], truth: &[f64], flow: &[Vec<f64>], exact: &[Vec<f64>]) -> Vec<ParamScore> {
    let (flow_readings, exact_readings) = (normal::read(params, flow), normal::read(params, exact));
    params
        .iter()
        .enumerate()
        .map(|(k, p)| {
            let f = marginal(p, k, truth[k], flow, &flow_readings);
            let e = marginal(p, k, truth[k], exact, &exact_readings);
            ParamScore { name: p.name.clone(), truth: truth[k], width_ratio: f.width90 / e.width90, flow: f, exact: e }
        })
        .collect()
}

/// Coverage, widths and wrong readings pooled over (ear, parameter) pairs.
#[derive(Clone, Debug, Serialize)]
pub struct Pooled {
    /// Pairs pooled.
    pub pairs: usize,
    /// Fraction of pairs whose flow 50 % interval holds the truth.
    pub flow_cover50: f64,
    /// The same for the chain.
    pub exact_cover50: f64,
    /// Fraction of pairs whose flow 90 % interval holds the truth.
    pub flow_cover90: f64,
    /// The same for the chain.
    pub exact_cover90: f64,
    /// Median of the flow/exact 90 % width ratio.
    pub width_ratio_median: f64,
    /// Pairs the flow reads confidently (below or above).
    pub flow_confident: usize,
    /// Of those, the ones the truth contradicts.
    pub flow_confident_wrong: usize,
    /// Pairs the chain reads confidently.
    pub exact_confident: usize,
    /// Of those, the ones the truth contradicts.
    pub exact_confident_wrong: usize,
}

/// Pools `scores`.
pub fn pool<'a>(scores: impl IntoIterator<Item = &'a ParamScore>) -> Pooled {
    let scores: Vec<&ParamScore> = scores.into_iter().collect();
    let n = scores.len();
    let rate = |f: &dyn Fn(&ParamScore) -> bool| scores.iter().filter(|s| f(s)).count() as f64 / n as f64;
    let count = |f: &dyn Fn(&ParamScore) -> bool| scores.iter().filter(|s| f(s)).count();
    let confident = |m: &Marginal| matches!(m.reading, "below" | "above");
    Pooled {
        pairs: n,
        flow_cover50: rate(&|s| s.flow.in50),
        exact_cover50: rate(&|s| s.exact.in50),
        flow_cover90: rate(&|s| s.flow.in90),
        exact_cover90: rate(&|s| s.exact.in90),
        width_ratio_median: median(scores.iter().map(|s| s.width_ratio).collect()),
        flow_confident: count(&|s| confident(&s.flow)),
        flow_confident_wrong: count(&|s| s.flow.confident_wrong),
        exact_confident: count(&|s| confident(&s.exact)),
        exact_confident_wrong: count(&|s| s.exact.confident_wrong),
    }
}

/// The upper median; NaN when empty.
fn median(v: Vec<f64>) -> f64 {
    stats::median_upper(&stats::sorted(v))
}

/// One ear's outcome.
#[derive(Clone, Debug, Serialize)]
pub struct EarResult {
    /// Its index (its noise stream).
    pub ear: usize,
    /// `prior` or the recipe's name.
    pub kind: &'static str,
    /// Its parameters (natural units, all fourteen).
    pub truth: Vec<f64>,
    /// Both methods on each tissue parameter.
    pub params: Vec<ParamScore>,
    /// C2ST accuracy between the flow's and the chain's draws of the tissue parameters
    /// (0.5: indistinguishable, 1: separable).
    pub c2st: f64,
    /// Wall time of the flow's inference (samples and MAP).
    pub flow_seconds: f64,
    /// Wall time of the exact posterior (16 least-squares fits and the chain; its starts
    /// come from the flow's inference, which is not counted here).
    pub exact_seconds: f64,
    /// The chain's acceptance rate after burn-in.
    pub acceptance: f64,
    /// The chain's draws kept.
    pub chain_draws: usize,
    /// χ² of the best least-squares fit (the chain's start).
    pub chi2_start: f64,
    /// Median χ² over the chain's draws.
    pub chi2_median: f64,
    /// The chains' R-hat over all their coordinates (as the `exact` job's `diagnostics`
    /// report it): above `SETTLED_RHAT` the reference has not settled. The reading's own
    /// rule (`ExactPosterior::unsettled`) judges each tissue coordinate alone.
    pub chain_rhat: f64,
}

/// An ear that could not be scored, and why.
#[derive(Clone, Debug, Serialize)]
pub struct Skipped {
    /// Its index.
    pub ear: usize,
    /// `prior` or the recipe's name.
    pub kind: &'static str,
    /// What failed.
    pub reason: String,
}

/// One tissue parameter pooled over the ears.
#[derive(Clone, Debug, Serialize)]
pub struct ParamSummary {
    /// The parameter.
    pub name: String,
    /// Its scores.
    #[serde(flatten)]
    pub pooled: Pooled,
}

/// A group of ears pooled over ears and tissue parameters.
#[derive(Clone, Debug, Serialize)]
pub struct GroupSummary {
    /// `all`, `prior` or `degeneracy`.
    pub group: &'static str,
    /// Ears scored.
    pub ears: usize,
    /// Their scores.
    #[serde(flatten)]
    pub pooled: Pooled,
    /// Median C2ST over the ears.
    pub c2st_median: f64,
    /// Median wall time per ear of the flow.
    pub flow_seconds_median: f64,
    /// Median wall time per ear of the exact posterior.
    pub exact_seconds_median: f64,
}

/// A whole run.
#[derive(Clone, Debug, Serialize)]
pub struct Report {
    /// Ears asked for.
    pub ears: usize,
    /// The seed.
    pub seed: u64,
    /// Chain steps per ear.
    pub steps: usize,
    /// Feature groups given (empty: every one).
    pub measures: Vec<String>,
    /// The lowest frequency given (Hz; 0: the whole grid).
    pub from_hz: f64,
    /// Features given to the flow and to the likelihood.
    pub features: usize,
    /// The flow that answered: `full-measure`, `measure-set` or `masked` (the file's main flow).
    pub flow: &'static str,
    /// Flow draws per ear.
    pub flow_samples: usize,
    /// The degeneracy recipes.
    pub recipes: Vec<Recipe>,
    /// Largest relative difference between the ears' noise and the model's training noise
    /// (the chain's likelihood): 0 when the model was trained on 1× default noise.
    pub noise_mismatch: f64,
    /// Per tissue parameter, over every scored ear.
    pub per_param: Vec<ParamSummary>,
    /// All ears, the prior draws, the degeneracy ears.
    pub groups: Vec<GroupSummary>,
    /// Every scored ear.
    pub per_ear: Vec<EarResult>,
    /// Ears that could not be scored.
    pub skipped: Vec<Skipped>,
}

/// `n` of `draws` (all if fewer), evenly spaced, as scale coordinates of `params` (the
/// C2ST's inputs: the chain's draws are correlated, so thinned rather than taken in a row).
pub fn tissue_coords(params: &[Param], draws: &[Vec<f64>], n: usize) -> Vec<Vec<f64>> {
    let m = n.min(draws.len());
    (0..m)
        .map(|i| &draws[i * draws.len() / m])
        .map(|d| params.iter().enumerate().map(|(k, p)| space::coord(p.scale, d[k])).collect())
        .collect()
}

/// Runs the flow and the chain on one ear whose features are `x`.
fn one_ear(npe: &Npe, i: usize, ear: &Ear, x: &[f64], present: &[bool], p: &PosteriorParams) -> Result<EarResult> {
    let seed = p.seed.wrapping_add(i as u64);
    // The flow the service would answer with: the full-measure flow, when the model holds
    // one, for every measure; the masked flow for a subset.
    let npe = npe.answering(&Obs { x, present: Some(present) });
    let t = Instant::now();
    let inf = npe.infer(&Obs { x, present: Some(present) }, FLOW_SAMPLES, seed)?;
    let flow_seconds = t.elapsed().as_secs_f64();
    let t = Instant::now();
    let ex = exact(npe, x, present, &inf, p.steps, seed)?;
    let exact_seconds = t.elapsed().as_secs_f64();
    let tissue = &npe.params()[..N_TISSUE];
    let (flow, chain) = (&inf.samples, &ex.chain.samples);
    let m = C2ST_DRAWS.min(chain.len()).min(flow.len());
    let c2st = c2st::c2st(
        &tissue_coords(tissue, chain, m),
        &tissue_coords(tissue, &flow[..m], m),
        &C2stParams { seed, ..C2stParams::default() },
    );
    Ok(EarResult {
        ear: i,
        kind: ear.kind,
        truth: ear.row.clone(),
        params: score(tissue, &ear.row, flow, chain),
        c2st,
        flow_seconds,
        exact_seconds,
        acceptance: ex.chain.acceptance,
        chain_draws: chain.len(),
        chi2_start: ex.chain.chi2_start,
        chi2_median: ex.chain.chi2_median,
        chain_rhat: by_segments(chain, ex.chain.chains).0,
    })
}

/// Pools a group of ears.
fn group(name: &'static str, ears: &[&EarResult]) -> GroupSummary {
    GroupSummary {
        group: name,
        ears: ears.len(),
        pooled: pool(ears.iter().flat_map(|e| &e.params)),
        c2st_median: median(ears.iter().map(|e| e.c2st).collect()),
        flow_seconds_median: median(ears.iter().map(|e| e.flow_seconds).collect()),
        exact_seconds_median: median(ears.iter().map(|e| e.exact_seconds).collect()),
    }
}

/// Pools scored ears per tissue parameter and per group.
pub fn summarize(per_ear: &[EarResult]) -> (Vec<ParamSummary>, Vec<GroupSummary>) {
    let names: Vec<String> = per_ear.first().map_or(vec![], |e| e.params.iter().map(|s| s.name.clone()).collect());
    let per_param = names
        .iter()
        .enumerate()
        .map(|(k, name)| ParamSummary { name: name.clone(), pooled: pool(per_ear.iter().map(|e| &e.params[k])) })
        .collect();
    let all: Vec<&EarResult> = per_ear.iter().collect();
    let (prior, degenerate): (Vec<&EarResult>, Vec<&EarResult>) = all.iter().partition(|e| e.kind == "prior");
    // The reference's own diagnostic: widths against a chain that has not settled say
    // little, so the settled ears are pooled apart too.
    let settled: Vec<&EarResult> = all.iter().copied().filter(|e| e.chain_rhat <= SETTLED_RHAT).collect();
    let groups = vec![
        group("all", &all),
        group("prior", &prior),
        group("degeneracy", &degenerate),
        group("chain settled", &settled),
    ];
    (per_param, groups)
}

/// Simulates the ears of `p` with `npe`'s simulator, reads each with the flow and the
/// chain, one ear after the other (each method's wall time is then its own), and pools
/// the scores. `progress` hears each ear as it ends.
pub fn run(npe: &Npe, p: &PosteriorParams, progress: &mut dyn FnMut(&Result<EarResult, Skipped>)) -> Result<Report> {
    p.check()?;
    let present = npe.header.features_given(&p.measures, p.from_hz).map_err(|e| anyhow!("--measures: {e}"))?;
    // The flow the service would answer these ears with (`main` is the masked one).
    let flow = match npe.answering_name(&Obs { x: &vec![0.0; present.len()], present: Some(&present) }) {
        "main" => "masked",
        other => other,
    };
    let model = simulator_for(npe)?;
    let held = ears(p.ears, p.seed);
    let rows: Vec<Vec<f64>> = held.iter().map(|e| e.row.clone()).collect();
    let noise = Noise { std: default_noise_std(model), scale: 1.0, seed: p.seed };
    let trained = npe
        .header
        .noise_std
        .iter()
        .map(|s| s * if npe.header.noise_scale > 0.0 { npe.header.noise_scale } else { 1.0 });
    let noise_mismatch = noise.std.iter().zip(trained).map(|(a, b)| (a - b).abs() / a).fold(0.0, f64::max);
    let xs = run_rows(model, &Design::default(), &rows, 0, Some(&noise));
    let (mut per_ear, mut skipped) = (vec![], vec![]);
    for (i, (ear, x)) in held.iter().zip(xs).enumerate() {
        let outcome = x
            .map_err(anyhow::Error::from)
            .and_then(|x| one_ear(npe, i, ear, &x, &present, p))
            .map_err(|e| Skipped { ear: i, kind: ear.kind, reason: format!("{e:#}") });
        progress(&outcome);
        match outcome {
            Ok(r) => per_ear.push(r),
            Err(s) => skipped.push(s),
        }
    }
    let (per_param, groups) = summarize(&per_ear);
    Ok(Report {
        ears: p.ears,
        seed: p.seed,
        steps: p.steps,
        measures: p.measures.clone(),
        from_hz: p.from_hz,
        features: present.iter().filter(|&&g| g).count(),
        flow,
        flow_samples: FLOW_SAMPLES,
        recipes: RECIPES.to_vec(),
        noise_mismatch,
        per_param,
        groups,
        per_ear,
        skipped,
    })
}

/// Whether `v` is within [`COVERAGE_TOLERANCE`] of `nominal`.
fn covers(v: f64, nominal: f64) -> bool {
    (v - nominal).abs() <= COVERAGE_TOLERANCE + 1e-12
}

/// "met for all 7" or "met for 3 of 7; missed: NAME value, …".
fn verdict(per_param: &[ParamSummary], value: impl Fn(&Pooled) -> f64, met: impl Fn(f64) -> bool) -> String {
    let missed: Vec<String> = per_param
        .iter()
        .filter(|s| !met(value(&s.pooled)))
        .map(|s| format!("{} {:.2}", s.name, value(&s.pooled)))
        .collect();
    let n = per_param.len();
    if missed.is_empty() {
        format!("met for all {n}")
    } else {
        format!("met for {} of {n}; missed: {}", n - missed.len(), missed.join(", "))
    }
}

/// The columns both tables share: the four coverages and the median width ratio.
fn cells(q: &Pooled) -> String {
    format!(
        "{:.2} | {:.2} | {:.2} | {:.2} | {:.2}",
        q.flow_cover50, q.exact_cover50, q.flow_cover90, q.exact_cover90, q.width_ratio_median
    )
}

/// The report as markdown: the per-parameter table, the groups, the targets.
pub fn table(r: &Report) -> String {
    let mut s = String::new();
    let scored = r.per_ear.len();
    let _ = writeln!(
        s,
        "{scored} of {} ears scored ({} skipped), seed {}, measures {}{} ({} features, {} flow), {} chain steps, {} \
         flow draws per ear",
        r.ears,
        r.skipped.len(),
        r.seed,
        if r.measures.is_empty() { "all".to_string() } else { r.measures.join(",") },
        if r.from_hz > 0.0 { format!(" from {} Hz", r.from_hz) } else { String::new() },
        r.features,
        r.flow,
        r.steps,
        r.flow_samples
    );
    if r.noise_mismatch > 1e-9 {
        let _ = writeln!(
            s,
            "note: the ears' noise differs from the model's training noise by up to {:.0} % (the chain's likelihood \
             uses the training noise)",
            100.0 * r.noise_mismatch
        );
    }
    let _ = writeln!(s);
    let _ = writeln!(
        s,
        "| parameter | flow in 50 % | exact in 50 % | flow in 90 % | exact in 90 % | 90 % width flow/exact, median \
         | confident wrong, flow | confident wrong, exact |"
    );
    let _ = writeln!(s, "|---|---|---|---|---|---|---|---|");
    for p in &r.per_param {
        let q = &p.pooled;
        let _ = writeln!(
            s,
            "| {} | {} | {} of {} | {} of {} |",
            p.name,
            cells(q),
            q.flow_confident_wrong,
            q.flow_confident,
            q.exact_confident_wrong,
            q.exact_confident
        );
    }
    let _ = writeln!(s);
    let _ = writeln!(
        s,
        "| ears | n | flow in 50 % | exact in 50 % | flow in 90 % | exact in 90 % | 90 % width flow/exact, median \
         | C2ST, median | flow ms/ear | exact s/ear |"
    );
    let _ = writeln!(s, "|---|---|---|---|---|---|---|---|---|---|");
    for g in &r.groups {
        let _ = writeln!(
            s,
            "| {} | {} | {} | {:.3} | {:.1} | {:.1} |",
            g.group,
            g.ears,
            cells(&g.pooled),
            g.c2st_median,
            1e3 * g.flow_seconds_median,
            g.exact_seconds_median
        );
    }
    let _ = writeln!(s);
    let se = |c: f64| (c * (1.0 - c) / scored.max(1) as f64).sqrt();
    let _ = writeln!(s, "Targets (the flow, per tissue parameter, over all {scored} ears):");
    let _ = writeln!(
        s,
        "- 90 % width flow/exact ≤ {WIDTH_TARGET}: {}",
        verdict(&r.per_param, |q| q.width_ratio_median, |v| v <= WIDTH_TARGET)
    );
    for (level, value) in [(0.5, (|q: &Pooled| q.flow_cover50) as fn(&Pooled) -> f64), (0.9, |q| q.flow_cover90)] {
        let _ = writeln!(
            s,
            "- coverage of the {:.0} % interval within ±{COVERAGE_TOLERANCE} of {level}: {} (binomial standard \
             error at {scored} ears: {:.3})",
            100.0 * level,
            verdict(&r.per_param, value, |v| covers(v, level)),
            se(level)
        );
    }
    s
}

#[cfg(test)]
mod tests {
    use super::*;
    use otofit_npe::npe::Scale;
    use rand_distr::{Distribution, StandardNormal};

    /// Draws (one column per parameter, in natural units) whose scale coordinates are
    /// `centre + sd · z` for standard normal `z`.
    fn gaussian(params: &[Param], z: &[f64], centre: f64, sd: f64) -> Vec<Vec<f64>> {
        z.iter().map(|z| params.iter().map(|p| space::value(p.scale, centre + sd * z)).collect()).collect()
    }

    /// Two parameters without normal ranges, one linear and one log-scale (the width of a
    /// log-scale parameter is taken in log10 units).
    fn two_params() -> Vec<Param> {
        let p = |name: &str, scale, low, high| Param { name: name.into(), unit: String::new(), scale, low, high };
        vec![p("linear", Scale::Linear, -100.0, 100.0), p("log", Scale::Log10, 1e-3, 1e13)]
    }

    /// Analytic case: both posteriors Gaussian on the parameter's scale around 5, the chain's
    /// σ = 1 and the flow's σ = 2; the truths spaced evenly over 5 ± 5 (101 ears). An
    /// interval of half-width h then holds the truth for a fraction ≈ h / 5 of the ears:
    /// the chain's 50 % interval (h = 0.674) 0.135, its 90 % (h = 1.645) 0.329; the flow's
    /// twice that. The 90 % width ratio is 2 on both scales.
    #[test]
    fn coverage_and_width_ratio_match_gaussian_posteriors() {
        let params = two_params();
        let mut rng = ChaCha8Rng::seed_from_u64(3);
        let z: Vec<f64> = (0..20_000).map(|_| StandardNormal.sample(&mut rng)).collect();
        let (flow, chain) = (gaussian(&params, &z, 5.0, 2.0), gaussian(&params, &z[..10_000], 5.0, 1.0));
        let ears: Vec<EarResult> = (0..=100)
            .map(|i| {
                let t = i as f64 / 10.0;
                let truth: Vec<f64> = params.iter().map(|p| space::value(p.scale, t)).collect();
                EarResult {
                    ear: i,
                    kind: if i % 2 == 0 { "prior" } else { "ligaments_tendons_high" },
                    params: score(&params, &truth, &flow, &chain),
                    truth,
                    c2st: i as f64,
                    flow_seconds: 0.0,
                    exact_seconds: 0.0,
                    acceptance: 0.0,
                    chain_draws: chain.len(),
                    chi2_start: 0.0,
                    chi2_median: 0.0,
                    chain_rhat: if i % 4 == 0 { 1.2 } else { 1.0 },
                }
            })
            .collect();
        let (per_param, groups) = summarize(&ears);
        // Grid points inside ±h of 5 (a step of 0.1), over 101.
        let inside = |h: f64| (2.0 * (h * 10.0).floor() + 1.0) / 101.0;
        for p in &per_param {
            let q = &p.pooled;
            let near = |got: f64, want: f64, what: &str| {
                // Two ears of slack: the sampled quantiles may cross the grid point next to h.
                assert!((got - want).abs() < 0.025, "{} {what}: {got} against {want}", p.name);
            };
            near(q.exact_cover50, inside(0.6745), "chain 50 %");
            near(q.exact_cover90, inside(1.6449), "chain 90 %");
            near(q.flow_cover50, inside(2.0 * 0.6745), "flow 50 %");
            near(q.flow_cover90, inside(2.0 * 1.6449), "flow 90 %");
            assert!((q.width_ratio_median - 2.0).abs() < 0.04, "{} width ratio {}", p.name, q.width_ratio_median);
            assert_eq!((q.pairs, q.flow_confident, q.exact_confident), (101, 0, 0));
        }
        let width = ears[0].params[1].exact.width90;
        assert!((width - 2.0 * 1.6449).abs() < 0.05, "the log parameter's 90 % width in log10 units: {width}");
        assert_eq!(
            groups.iter().map(|g| (g.group, g.ears)).collect::<Vec<_>>(),
            [("all", 101), ("prior", 51), ("degeneracy", 50), ("chain settled", 75)]
        );
        assert_eq!(groups[0].c2st_median, 50.0);
        assert_eq!(groups[0].pooled.pairs, 202);
    }

    /// A reading is confidently wrong when the truth lies within the normal range or
    /// beyond its other side; right when the truth is on the side read.
    #[test]
    fn a_confident_reading_is_wrong_when_the_truth_contradicts_it() {
        let params: Vec<Param> = PARAMS[..N_TISSUE].iter().map(Param::from).collect();
        let k = 2; // E_tendons: normal 0.52–5 MPa, prior 0.05–50 MPa
        let r = &normal::NORMAL[k];
        assert_eq!(r.name, params[k].name);
        let nominal: Vec<f64> = PARAMS[..N_TISSUE].iter().map(|p| p.nominal).collect();
        let with = |row: &[f64], v: f64| -> Vec<f64> {
            let mut row = row.to_vec();
            row[k] = v;
            row
        };
        let mut rng = ChaCha8Rng::seed_from_u64(1);
        // Draws 0.05 decades wide around 10^centre Pa.
        let mut at = |centre: f64| -> Vec<Vec<f64>> {
            (0..2000)
                .map(|_| {
                    let z: f64 = StandardNormal.sample(&mut rng);
                    with(&nominal, 10f64.powf(centre + 0.05 * z))
                })
                .collect()
        };
        let (below, above, within) = (at(5.0), at(7.3), at(6.2));
        for (draws, truth, reading, wrong) in [
            (&below, 1e5, "below", false),
            (&below, 1e6, "below", true),
            (&below, 2e7, "below", true),
            (&below, r.low, "below", true),
            (&above, 2e7, "above", false),
            (&above, 1e6, "above", true),
            (&above, 1e5, "above", true),
            (&within, 1e5, "within", false),
        ] {
            let s = &score(&params, &with(&nominal, truth), draws, draws)[k];
            assert_eq!((s.flow.reading, s.flow.confident_wrong), (reading, wrong), "truth {truth}");
            assert_eq!(s.exact.confident_wrong, wrong);
        }
        let q = pool(&score(&params, &with(&nominal, 1e6), &below, &above));
        assert_eq!(
            (q.flow_confident, q.flow_confident_wrong, q.exact_confident, q.exact_confident_wrong),
            (1, 1, 1, 1)
        );
    }

    #[test]
    fn ears_are_half_prior_half_recipes_and_deterministic() {
        let a = ears(9, 4);
        assert_eq!(a.iter().filter(|e| e.kind == "prior").count(), 5);
        let prior = Design::default().draw(4, 0, 9);
        for (i, e) in a.iter().enumerate() {
            if i < 5 {
                assert_eq!(e.row, prior[i]);
                continue;
            }
            let recipe = &RECIPES[(i - 5) % RECIPES.len()];
            assert_eq!(e.kind, recipe.name);
            for k in 0..e.row.len() {
                match recipe.pins.iter().find(|(j, _)| *j == k) {
                    Some(&(_, end)) => {
                        let (low, high) = end.band();
                        let q = Param::from(&PARAMS[k]).position(e.row[k]);
                        assert!((low..high).contains(&q), "ear {i} {}: position {q}", PARAMS[k].name);
                    }
                    None => assert_eq!(e.row[k], prior[i][k]),
                }
            }
        }
        let again = ears(9, 4);
        assert!(a.iter().zip(&again).all(|(x, y)| x.row == y.row));
        assert_ne!(ears(9, 5)[6].row, a[6].row);
    }

    /// The whole run on two ears of the shipped model (about 5 s on two cores).
    #[test]
    #[ignore]
    fn two_ears_of_the_shipped_model_are_scored() {
        let path = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("../../models/default.otofit");
        let npe = Npe::load(&path).unwrap();
        let p = PosteriorParams { ears: 2, seed: 3, steps: 20_000, ..PosteriorParams::default() };
        let mut heard = 0;
        let r = run(&npe, &p, &mut |_| heard += 1).unwrap();
        assert_eq!((heard, r.per_ear.len() + r.skipped.len()), (2, 2));
        assert_eq!(r.per_param.len(), N_TISSUE);
        for e in &r.per_ear {
            assert!((0.0..=1.0).contains(&e.c2st) && e.exact_seconds > e.flow_seconds, "{e:?}");
            assert_eq!(e.chain_draws, 1500);
        }
        assert!(table(&r).contains("| E_eardrum |"));
        assert!(serde_json::to_string(&r).unwrap().contains("\"per_ear\""));
    }

    /// A subset of measures is answered by the flow that answers it in the service (a
    /// measure-set flow for exactly its groups, else the masked flow) and scored against
    /// the likelihood of its features alone; an unknown group is refused by its argument.
    #[test]
    fn a_subset_of_measures_is_read_by_the_flow_that_answers_it() {
        let path = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("../../models/default.otofit");
        let npe = Npe::load(&path).unwrap();
        let clinic: Vec<String> = ["impedance", "absorbance", "umbo_velocity"].map(String::from).to_vec();
        let p = PosteriorParams { ears: 1, seed: 3, steps: MIN_STEPS, measures: clinic.clone(), from_hz: 0.0 };
        let r = run(&npe, &p, &mut |_| {}).unwrap();
        assert_eq!((r.flow, &r.measures, r.per_ear.len()), ("measure-set", &clinic, 1), "{:?}", r.skipped);
        assert!(table(&r).contains("measures impedance,absorbance,umbo_velocity (250 features, measure-set flow)"));
        // Both velocities alone: no flow of their own, so the masked flow.
        let lasers: Vec<String> = ["stapes_velocity", "umbo_velocity"].map(String::from).to_vec();
        let v = run(&npe, &PosteriorParams { measures: lasers.clone(), ..p.clone() }, &mut |_| {}).unwrap();
        assert_eq!((v.flow, &v.measures, v.per_ear.len()), ("masked", &lasers, 1), "{:?}", v.skipped);
        assert!(table(&v).contains("measures stapes_velocity,umbo_velocity (200 features, masked flow)"));
        // Fewer features, a wider likelihood: the chain's intervals widen.
        let width = |r: &Report| r.per_ear[0].params.iter().map(|s| s.exact.width90).sum::<f64>();
        let wbt = PosteriorParams { measures: clinic[..2].to_vec(), ..p.clone() };
        let whole = run(&npe, &wbt, &mut |_| {}).unwrap();
        assert_eq!(whole.flow, "measure-set");
        // From 226 Hz, as a device exports, or from 480 Hz (the lowest 12 of the 50 grid
        // points gone, the most the band-masked flow learned to miss): that flow, on the
        // features of the band alone.
        let device = run(&npe, &PosteriorParams { from_hz: 226.0, ..wbt.clone() }, &mut |_| {}).unwrap();
        assert_eq!((device.flow, device.per_ear.len()), ("measure-set", 1), "{:?}", device.skipped);
        assert!(table(&device).contains("measures impedance,absorbance from 226 Hz (144 features, measure-set flow)"));
        let high = run(&npe, &PosteriorParams { from_hz: 480.0, ..wbt.clone() }, &mut |_| {}).unwrap();
        assert_eq!((high.flow, high.per_ear.len()), ("measure-set", 1), "{:?}", high.skipped);
        // Three curves (impedance magnitude and phase, absorbance) of 50 points each.
        assert_eq!((whole.features, device.features, high.features), (150, 144, 114));
        let e = PosteriorParams { from_hz: 600.0, ..wbt }.check().unwrap_err().to_string();
        assert!(e.contains("--from-hz"), "{e}");
        let all = PosteriorParams { measures: vec![], ..p.clone() };
        let every = run(&npe, &all, &mut |_| {}).unwrap();
        assert_eq!(every.flow, "full-measure");
        assert!(width(&r) > width(&every), "{} vs {}", width(&r), width(&every));
        let bad = PosteriorParams { measures: vec!["tympanogram".into()], ..p };
        let e = run(&npe, &bad, &mut |_| {}).unwrap_err().to_string();
        assert!(e.contains("--measures") && e.contains("tympanogram"), "{e}");
    }

    #[test]
    fn sizes_out_of_range_name_their_argument() {
        let p = PosteriorParams::default();
        assert!(p.check().is_ok());
        let e = PosteriorParams { ears: 0, ..p.clone() }.check().unwrap_err().to_string();
        assert!(e.contains("--ears"), "{e}");
        let e = PosteriorParams { steps: 10, ..p }.check().unwrap_err().to_string();
        assert!(e.contains("--steps"), "{e}");
    }
}
