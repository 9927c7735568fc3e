//! The likelihood's posterior within one request: importance sampling from the flow
//! ([`super::importance`]), guided by the Laplace approximation at the mode of the
//! likelihood times the flow's base density (`latent_guides`), first; and where its
//! weights do not pass, several short
//! Metropolis chains in the flow's latent space from dispersed starts, with the
//! diagnostics that say whether they agree.
//!
//! Measured on the default model's held-out ears (docs/results/posterior.md, "Guided
//! importance sampling, and ears with fewer measures"), the weights pass on every
//! seven-measure ear within a second on two cores and agree with the long chain (C2ST
//! near 0.5); with fewer measures they pass on about two ears in three, and where the
//! posterior has a mode no latent fit reaches the answer is too narrow (three-measure
//! ears: 90 % coverage 0.86). The chains after failed weights rarely have time to mix,
//! so those answers say `exact: false`.
//!
//! [`super::fitcheck::exact`] runs four long chains of this kernel (100,000 steps in
//! all, about 10 s on two cores) for the `exact` job. This runs [`Settings::chains`]
//! short chains at once, one rayon
//! task each, under a deadline, in the flow's base space: θ = T(z; x) is the flow's
//! sampling map for the observation ([`crate::npe::LatentMap`]), and the chains target
//! log p(x | T(z)) + log p(T(z)) + log |det ∂T/∂z|, whose push-forward through T is the
//! likelihood's posterior. Where the flow approximates that posterior the target in z is
//! near N(0, I), whatever the curvature in θ. Each chain starts at its own draw of
//! N(0, [`START_SD`]² I) (wider than the flow, which is wider than the likelihood's
//! posterior, so that the chains' agreement means something), redrawn where it has no
//! density. The warm-up runs in rounds; after each the shared proposal (a random walk,
//! and a Student-t independence proposal for a quarter of the steps) takes the mean and
//! covariance of all chains' histories, and the walk's scale moves towards a 0.234
//! acceptance. The kept steps use the last proposal, fixed. Beside the chains, a
//! Levenberg–Marquardt fit from the flow's MAP gives `map` and `reduced_chi2`.
//!
//! The chains alone, measured with an earlier default model (docs/results/posterior.md,
//! "Exact in the flow's latent space"), came much closer to the long chain in z than in
//! θ (C2ST 0.64 against 0.99) but did not mix in 2,000 steps (R̂ 1.17–2.55, bulk ESS
//! 5–17 of the 400 asked), and the diagnostics said so (`exact: false`).
//!
//! The diagnostics are rank-normalised split-R̂ (bulk and folded, the larger) and bulk
//! and tail ESS over all chains (Vehtari, Gelman, Simpson, Carpenter & Bürkner 2021), on
//! the chains' z and on their θ, the worse of the two ([`run_chains_mapped`]). The
//! answer is called exact only when R̂ ≤ [`Settings::rhat_max`], both ESS ≥
//! [`Settings::ess_min`] and the deadline was not hit; otherwise `exact` is false and
//! `reason` says which failed. The numerical core ([`run_chains`], [`diagnose`]) takes a
//! log density and knows nothing of the simulator, so it is tested on analytic targets.

use super::exact::{cholesky, spd_inverse};
use super::fit::{TRIES, damped_step, fit_columns, normal_equations, residuals};
use super::fitcheck::{FitCheckError, observation, simulator_for};
use super::importance::{Guide, ImportanceDiagnostics, ImportanceSettings};
use crate::npe::{Inference, Npe};
use crate::sim::batch::Design;
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use rand_distr::{ChiSquared, Distribution, StandardNormal};
use rayon::prelude::*;
use serde::Serialize;
use std::time::Instant;

/// How many chains, how long, and when their answer counts as exact.
#[derive(Clone, Debug, Serialize)]
pub struct Settings {
    /// Chains, each from its own dispersed start (at least 2: R̂ compares chains).
    pub chains: usize,
    /// Warm-up steps per chain (proposal adaptation; discarded).
    pub warmup: usize,
    /// Sampling steps per chain after warm-up, all kept.
    pub steps: usize,
    /// Levenberg–Marquardt steps of the fit from the flow's MAP (run beside the chains).
    pub fit_steps: usize,
    /// Largest R̂ (rank-normalised split, bulk and folded) called converged.
    pub rhat_max: f64,
    /// Smallest bulk and tail ESS (over all chains) called enough.
    pub ess_min: f64,
    /// Seed of the starts and the chains.
    pub seed: u64,
    /// Importance sampling from the flow tried first ([`super::importance`]; its seed is
    /// this one's); the chains run only when its weights do not pass. `None`: chains only.
    pub importance: Option<ImportanceSettings>,
}

impl Default for Settings {
    fn default() -> Self {
        Settings {
            chains: 4,
            warmup: 400,
            steps: 2000,
            fit_steps: 50,
            rhat_max: 1.05,
            ess_min: 400.0,
            seed: 0,
            importance: Some(ImportanceSettings::default()),
        }
    }
}

/// Chain agreement and effective sample sizes of one run.
#[derive(Clone, Debug, Serialize)]
pub struct Diagnostics {
    /// Largest rank-normalised split-R̂ over the coordinates (bulk and folded).
    pub rhat: f64,
    /// Smallest bulk ESS over the coordinates, all chains together.
    pub ess_bulk: f64,
    /// Smallest tail ESS (of the 5 % and 95 % quantiles) over the coordinates.
    pub ess_tail: f64,
    /// Per coordinate: R̂, bulk ESS, tail ESS.
    pub per_coordinate: Vec<[f64; 3]>,
    /// Each chain's acceptance rate over its sampling steps.
    pub acceptance: Vec<f64>,
    /// Sampling steps each chain took (fewer than asked when the deadline came first).
    pub steps: Vec<usize>,
    /// The deadline stopped the chains.
    pub deadline_hit: bool,
}

/// The chains' draws and whether they make an exact answer.
#[derive(Clone, Debug)]
pub struct Run {
    /// Each chain's kept draws (sampling phase, every step), in the target's coordinates.
    pub chains: Vec<Vec<Vec<f64>>>,
    /// The same draws' images under the density's map ([`run_chains_mapped`]); empty
    /// without one.
    pub images: Vec<Vec<Vec<f64>>>,
    /// How they went.
    pub diagnostics: Diagnostics,
    /// The diagnostics passed: the draws are the target's, up to their ESS.
    pub exact: bool,
    /// Why not, when not.
    pub reason: Option<String>,
}

/// Checks the clock this often (in steps).
const CLOCK_EVERY: usize = 16;

/// Degrees of freedom of the independence proposal's Student-t (heavy tails: a proposal
/// narrower than the target in some direction still reaches it).
const T_DOF: f64 = 5.0;

/// Scale of the independence proposal against the warm-up covariance.
const T_SCALE: f64 = 1.3;

/// Share of steps that propose independently (the rest random-walk).
const P_INDEPENDENT: f64 = 0.25;

/// Warm-up rounds: after each, the proposal is re-estimated from the chains' histories.
const ROUNDS: usize = 8;

/// Where a chain starts.
#[derive(Clone, Debug)]
pub struct Start {
    /// The chain's first state.
    pub at: Vec<f64>,
    /// A guess of the target's covariance near there (row-major d×d; e.g. the Laplace
    /// covariance of a fit): the first proposal is the mean of the chains' guesses.
    pub cov: Vec<f64>,
}

/// The proposal every chain shares in one phase: with probability [`P_INDEPENDENT`] a
/// Student-t around `mean` with covariance `cov`·[`T_SCALE`]², else a Gaussian random
/// walk with covariance `cov`·`scale`. A mixture of Metropolis–Hastings kernels that each
/// leave the target invariant leaves it invariant.
struct Kernel {
    d: usize,
    mean: Vec<f64>,
    chol: Vec<f64>,
    t_inv: Vec<f64>,
    scale: f64,
}

impl Kernel {
    fn new(mean: Vec<f64>, cov: &[f64], scale: f64) -> Option<Kernel> {
        let d = mean.len();
        let chol = cholesky(cov, d)?;
        let t_inv = spd_inverse(cov, d)?.iter().map(|v| v / (T_SCALE * T_SCALE)).collect();
        Some(Kernel { d, mean, chol, t_inv, scale })
    }

    fn log_q(&self, v: &[f64]) -> f64 {
        let d = self.d;
        let r: Vec<f64> = (0..d).map(|i| v[i] - self.mean[i]).collect();
        let m: f64 = (0..d * d).map(|k| r[k / d] * self.t_inv[k] * r[k % d]).sum();
        -0.5 * (T_DOF + d as f64) * (1.0 + m / T_DOF).ln()
    }

    /// A proposal from `x`, its log Hastings ratio and whether it was a random-walk step.
    fn propose(&self, x: &[f64], rng: &mut ChaCha8Rng, chi: &ChiSquared<f64>) -> (Vec<f64>, f64, bool) {
        let d = self.d;
        let z: Vec<f64> = (0..d).map(|_| StandardNormal.sample(rng)).collect();
        let lz = |i: usize| (0..=i).map(|j| self.chol[i * d + j] * z[j]).sum::<f64>();
        if rng.random::<f64>() < P_INDEPENDENT {
            let g = (chi.sample(rng) / T_DOF).sqrt().max(1e-12);
            let y: Vec<f64> = (0..d).map(|i| self.mean[i] + T_SCALE * lz(i) / g).collect();
            let r = self.log_q(x) - self.log_q(&y);
            (y, r, false)
        } else {
            let s = self.scale.sqrt();
            ((0..d).map(|i| x[i] + s * lz(i)).collect(), 0.0, true)
        }
    }
}

/// A chain between phases.
struct State {
    x: Vec<f64>,
    lx: f64,
    /// The image of `x` under the density's map (empty: none).
    img: Vec<f64>,
    rng: ChaCha8Rng,
}

/// What one phase of one chain did.
struct Leg {
    states: Vec<Vec<f64>>,
    images: Vec<Vec<f64>>,
    accepted: usize,
    walks: usize,
    walked: usize,
    stopped: bool,
}

/// `steps` steps of `kernel` from `state`, every state (and its image) recorded; stops at
/// `deadline`.
fn advance(
    mut log_density: impl FnMut(&[f64]) -> (f64, Vec<f64>),
    state: &mut State,
    kernel: &Kernel,
    steps: usize,
    deadline: Instant,
) -> Leg {
    let mut leg = Leg {
        states: Vec::with_capacity(steps),
        images: Vec::with_capacity(steps),
        accepted: 0,
        walks: 0,
        walked: 0,
        stopped: false,
    };
    let Ok(chi) = ChiSquared::new(T_DOF) else { return leg };
    for step in 0..steps {
        if step % CLOCK_EVERY == 0 && Instant::now() >= deadline {
            leg.stopped = true;
            break;
        }
        let (y, log_ratio, walk) = kernel.propose(&state.x, &mut state.rng, &chi);
        let (ly, img) = log_density(&y);
        let u: f64 = state.rng.random();
        let ok = ly.is_finite() && ly - state.lx + log_ratio > u.ln();
        if ok {
            (state.x, state.lx, state.img) = (y, ly, img);
        }
        leg.accepted += usize::from(ok);
        leg.walks += usize::from(walk);
        leg.walked += usize::from(walk && ok);
        leg.states.push(state.x.clone());
        if !state.img.is_empty() {
            leg.images.push(state.img.clone());
        }
    }
    leg
}

/// Mean and covariance (row-major d×d) of rows.
fn moments(rows: &[&Vec<f64>], d: usize) -> (Vec<f64>, Vec<f64>) {
    let n = rows.len().max(2) as f64;
    let mean: Vec<f64> = (0..d).map(|k| rows.iter().map(|r| r[k]).sum::<f64>() / rows.len().max(1) as f64).collect();
    let mut c = vec![0.0; d * d];
    for r in rows {
        for i in 0..d {
            for j in 0..d {
                c[i * d + j] += (r[i] - mean[i]) * (r[j] - mean[j]) / (n - 1.0);
            }
        }
    }
    (mean, c)
}

/// Runs one chain per start, one rayon task each; `new_density` makes each chain its own
/// log density (e.g. with its own simulator workspace) for each phase. Warm-up in
/// rounds (`ROUNDS`): after each, the shared proposal's mean and covariance become those
/// of all chains' histories (the later half of the warm-up so far), shrunk towards the
/// starts' mean covariance, and the random walk's scale moves towards a 0.234 acceptance.
/// Then [`Settings::steps`] steps of the fixed kernel, all kept. The draws of all chains
/// cut to the shortest, with their diagnostics and verdict; `None` when no chain could
/// start or the starts' covariance is not positive definite.
pub fn run_chains<D, F>(new_density: F, starts: &[Start], s: &Settings, deadline: Instant) -> Option<Run>
where
    F: Fn() -> D + Sync,
    D: FnMut(&[f64]) -> f64,
{
    run_chains_mapped(
        || {
            let mut f = new_density();
            move |x: &[f64]| (f(x), vec![])
        },
        starts,
        s,
        deadline,
    )
}

/// [`run_chains`] for a density that also maps each point it is given (e.g. the flow's
/// latent z to the parameters θ it stands for: `(log density, θ)`; an empty image: none).
/// The kept draws' images come back in [`Run::images`], and the diagnostics are the worst
/// of the chains' own coordinates and of the images': R̂ and ESS are invariant under a
/// monotone map of one coordinate, not under a map that mixes them, and the answer is
/// read in the images' coordinates. `per_coordinate` is then the images'.
pub fn run_chains_mapped<D, F>(new_density: F, starts: &[Start], s: &Settings, deadline: Instant) -> Option<Run>
where
    F: Fn() -> D + Sync,
    D: FnMut(&[f64]) -> (f64, Vec<f64>),
{
    let d = starts.first()?.at.len();
    let mut states: Vec<State> = starts
        .par_iter()
        .enumerate()
        .filter_map(|(k, start)| {
            let seed = s.seed.wrapping_mul(0x9e37_79b9_7f4a_7c15).wrapping_add(k as u64);
            let (lx, img) = new_density()(&start.at);
            lx.is_finite().then(|| State { x: start.at.clone(), lx, img, rng: ChaCha8Rng::seed_from_u64(seed) })
        })
        .collect();
    if states.is_empty() {
        return None;
    }
    let failed = starts.len() - states.len();
    let mean_of = |f: &dyn Fn(&Start) -> f64| starts.iter().map(f).sum::<f64>() / starts.len() as f64;
    let prior_cov: Vec<f64> = (0..d * d).map(|k| mean_of(&|st| st.cov.get(k).copied().unwrap_or(f64::NAN))).collect();
    let centre: Vec<f64> = (0..d).map(|i| mean_of(&|st| st.at[i])).collect();
    let base = 2.38 * 2.38 / d.max(1) as f64;
    let mut kernel = Kernel::new(centre, &prior_cov, base)?;
    let mut history: Vec<Vec<Vec<f64>>> = vec![vec![]; states.len()];
    let round = s.warmup.div_ceil(ROUNDS);
    let mut stopped = false;
    for _ in 0..ROUNDS {
        if round == 0 || stopped {
            break;
        }
        let legs: Vec<Leg> =
            states.par_iter_mut().map(|st| advance(new_density(), st, &kernel, round, deadline)).collect();
        stopped = legs.iter().any(|l| l.stopped);
        let (walks, walked) = legs.iter().fold((0, 0), |(a, b), l| (a + l.walks, b + l.walked));
        for (h, l) in history.iter_mut().zip(legs) {
            h.extend(l.states);
        }
        // The later half of the warm-up so far, every chain.
        let rows: Vec<&Vec<f64>> = history.iter().flat_map(|h| &h[h.len() / 2..]).collect();
        let (mean, cov) = moments(&rows, d);
        let w = rows.len() as f64 / (rows.len() + 10 * d) as f64;
        let cov: Vec<f64> = cov.iter().zip(&prior_cov).map(|(c, c0)| w * c + (1.0 - w) * c0).collect();
        let rate = if walks > 0 { walked as f64 / walks as f64 } else { 0.234 };
        let scale = (kernel.scale.ln() + 2.0 * (rate - 0.234)).clamp(base.ln() - 6.0, base.ln() + 2.0).exp();
        kernel = Kernel::new(mean, &cov, scale).unwrap_or(Kernel { scale, ..kernel });
    }
    let legs: Vec<Leg> = if stopped {
        let stop = || Leg { states: vec![], images: vec![], accepted: 0, walks: 0, walked: 0, stopped: true };
        states.iter().map(|_| stop()).collect()
    } else {
        states.par_iter_mut().map(|st| advance(new_density(), st, &kernel, s.steps, deadline)).collect()
    };
    let n = legs.iter().map(|l| l.states.len()).min().unwrap_or(0);
    let deadline_hit = legs.iter().any(|l| l.stopped);
    let acceptance = legs.iter().map(|l| l.accepted as f64 / l.states.len().max(1) as f64).collect();
    let steps = legs.iter().map(|l| l.states.len()).collect();
    let mapped = legs.iter().all(|l| l.images.len() == l.states.len()) && legs.iter().any(|l| !l.images.is_empty());
    let mut images = vec![];
    let mut chains = vec![];
    for mut l in legs {
        chains.push(l.states.drain(..n).collect::<Vec<_>>());
        if mapped {
            images.push(l.images.drain(..n).collect::<Vec<_>>());
        }
    }
    let (mut rhat, mut ess_bulk, mut ess_tail, mut per_coordinate) = diagnose(&chains);
    if mapped {
        let (r, b, t, per) = diagnose(&images);
        let worse = |a: f64, b: f64, max: bool| match (a.is_nan() || b.is_nan(), max) {
            (true, _) => f64::NAN,
            (false, true) => a.max(b),
            (false, false) => a.min(b),
        };
        (rhat, ess_bulk, ess_tail, per_coordinate) =
            (worse(rhat, r, true), worse(ess_bulk, b, false), worse(ess_tail, t, false), per);
    }
    let diagnostics = Diagnostics { rhat, ess_bulk, ess_tail, per_coordinate, acceptance, steps, deadline_hit };
    let reason = verdict(&diagnostics, s, failed);
    Some(Run { chains, images, exact: reason.is_none(), reason, diagnostics })
}

/// Draws cut into `segments` consecutive equal segments read as that many chains by
/// [`diagnose`]; (R̂, bulk ESS, tail ESS, draws used). On one chain's draws it sees a
/// chain that has not settled — a drift, a slow excursion — not a mode the chain never
/// visited; on the draws of equal chains stored one after another (the `exact` job's,
/// `segments` their number) it compares the chains.
pub fn by_segments(draws: &[Vec<f64>], segments: usize) -> (f64, f64, f64, usize) {
    let (rhat, ess_bulk, ess_tail, _) = diagnose(&cut(draws, segments));
    let per = draws.len() / segments.max(1);
    (rhat, ess_bulk, ess_tail, per * segments)
}

/// [`by_segments`]'s R̂ per coordinate: one coordinate that has not settled leaves the
/// others' marginals readable, and a reading reads marginals.
pub fn segment_rhats(draws: &[Vec<f64>], segments: usize) -> Vec<f64> {
    diagnose(&cut(draws, segments)).3.iter().map(|c| c[0]).collect()
}

/// `draws` cut into `segments` consecutive equal parts (the remainder dropped).
fn cut(draws: &[Vec<f64>], segments: usize) -> Vec<Vec<Vec<f64>>> {
    let per = draws.len() / segments.max(1);
    draws.chunks_exact(per.max(1)).take(segments).map(<[_]>::to_vec).collect()
}

/// Why a run is not exact, or `None` when it is.
fn verdict(g: &Diagnostics, s: &Settings, failed: usize) -> Option<String> {
    let mut why = vec![];
    if g.deadline_hit {
        why.push(format!(
            "the deadline stopped the chains after {} sampling steps each",
            g.steps.iter().min().unwrap_or(&0)
        ));
    }
    if failed > 0 {
        why.push(format!("{failed} chain(s) could not start"));
    }
    if g.steps.len() < 2 {
        why.push("fewer than two chains: their agreement cannot be checked".into());
    }
    if g.rhat.is_nan() || g.rhat > s.rhat_max {
        why.push(format!("the chains disagree: R-hat {:.3} > {}", g.rhat, s.rhat_max));
    }
    let ess = g.ess_bulk.min(g.ess_tail);
    if ess.is_nan() || ess < s.ess_min {
        why.push(format!(
            "too few effective draws: bulk ESS {:.0}, tail ESS {:.0} (need {:.0})",
            g.ess_bulk, g.ess_tail, s.ess_min
        ));
    }
    (!why.is_empty()).then(|| why.join("; "))
}

/// Rank-normalised split-R̂ (the larger of bulk and folded) and bulk and tail ESS of
/// equal-length chains, the worst over the coordinates, and per coordinate [R̂, bulk ESS,
/// tail ESS]. NaN when the chains are too short (fewer than 4 draws).
pub fn diagnose(chains: &[Vec<Vec<f64>>]) -> (f64, f64, f64, Vec<[f64; 3]>) {
    let n = chains.iter().map(Vec::len).min().unwrap_or(0);
    let d = chains.first().and_then(|c| c.first()).map_or(0, Vec::len);
    if n < 4 || d == 0 {
        return (f64::NAN, f64::NAN, f64::NAN, vec![]);
    }
    let per: Vec<[f64; 3]> = (0..d)
        .map(|k| {
            let cols: Vec<Vec<f64>> = chains.iter().map(|c| c[..n].iter().map(|r| r[k]).collect()).collect();
            coordinate(&cols)
        })
        .collect();
    let worst = |i: usize, max: bool| {
        per.iter().map(|p| p[i]).fold(if max { f64::NEG_INFINITY } else { f64::INFINITY }, |a, b| {
            if a.is_nan() || b.is_nan() {
                f64::NAN
            } else if max {
                a.max(b)
            } else {
                a.min(b)
            }
        })
    };
    (worst(0, true), worst(1, false), worst(2, false), per)
}

/// [R̂, bulk ESS, tail ESS] of one scalar over chains of equal length.
fn coordinate(cols: &[Vec<f64>]) -> [f64; 3] {
    let split = split_halves(cols);
    let z = rank_normal(&split);
    let med = {
        let all = crate::stats::sorted(split.iter().flatten().copied().collect());
        crate::stats::quantile_linear(&all, 0.5)
    };
    let folded: Vec<Vec<f64>> = split.iter().map(|c| c.iter().map(|v| (v - med).abs()).collect()).collect();
    let rhat = rhat(&z).max(rhat(&rank_normal(&folded)));
    let ess_bulk = ess(&z);
    let all = crate::stats::sorted(split.iter().flatten().copied().collect());
    let tail = [0.05, 0.95]
        .map(|q| {
            let t = crate::stats::quantile_linear(&all, q);
            let ind: Vec<Vec<f64>> =
                split.iter().map(|c| c.iter().map(|&v| if v <= t { 1.0 } else { 0.0 }).collect()).collect();
            ess(&ind)
        })
        .into_iter()
        .fold(f64::INFINITY, f64::min);
    [rhat, ess_bulk, tail]
}

/// Each chain cut into its two halves (the middle draw of an odd chain dropped).
fn split_halves(cols: &[Vec<f64>]) -> Vec<Vec<f64>> {
    cols.iter()
        .flat_map(|c| {
            let h = c.len() / 2;
            [c[..h].to_vec(), c[c.len() - h..].to_vec()]
        })
        .collect()
}

/// The draws replaced by the normal scores of their pooled ranks (Blom's offsets).
fn rank_normal(chains: &[Vec<f64>]) -> Vec<Vec<f64>> {
    let all: Vec<f64> = chains.iter().flatten().copied().collect();
    let r = crate::stats::ranks(&all);
    let total = all.len() as f64;
    let mut it = r.into_iter().map(|r| probit((r + 1.0 - 0.375) / (total + 0.25)));
    chains.iter().map(|c| c.iter().map(|_| it.next().unwrap_or(0.0)).collect()).collect()
}

/// Split-R̂ of chains (already split) of equal length: √(var⁺/W).
fn rhat(chains: &[Vec<f64>]) -> f64 {
    let (m, n) = (chains.len() as f64, chains[0].len() as f64);
    let stats: Vec<(f64, f64)> = chains.iter().map(|c| crate::stats::mean_var_sample(c)).collect();
    let w = stats.iter().map(|s| s.1).sum::<f64>() / m;
    let grand = stats.iter().map(|s| s.0).sum::<f64>() / m;
    let b = n * stats.iter().map(|s| (s.0 - grand).powi(2)).sum::<f64>() / (m - 1.0).max(1.0);
    let var_plus = (n - 1.0) / n * w + b / n;
    if w > 0.0 { (var_plus / w).sqrt() } else { f64::NAN }
}

/// Multi-chain ESS of chains of equal length (Geyer's initial monotone sequence on the
/// chains' combined autocorrelation, as Stan computes it); at most the draws' count times
/// log10 of it (antithetic chains can exceed the count, not without bound).
fn ess(chains: &[Vec<f64>]) -> f64 {
    let (m, n) = (chains.len(), chains[0].len());
    let stats: Vec<(f64, f64)> = chains.iter().map(|c| crate::stats::mean_var_sample(c)).collect();
    let w = stats.iter().map(|s| s.1).sum::<f64>() / m as f64;
    let grand = stats.iter().map(|s| s.0).sum::<f64>() / m as f64;
    let b_over_n = stats.iter().map(|s| (s.0 - grand).powi(2)).sum::<f64>() / (m as f64 - 1.0).max(1.0);
    let var_plus = (n as f64 - 1.0) / n as f64 * w + b_over_n;
    if var_plus <= 0.0 || !var_plus.is_finite() {
        // A constant coordinate: every draw is the same, nothing to estimate.
        return f64::NAN;
    }
    // Autocovariance at lag t, averaged over chains (biased estimator, divided by n).
    let acov = |t: usize| -> f64 {
        chains
            .iter()
            .zip(&stats)
            .map(|(c, s)| (0..n - t).map(|i| (c[i] - s.0) * (c[i + t] - s.0)).sum::<f64>() / n as f64)
            .sum::<f64>()
            / m as f64
    };
    let rho = |t: usize| 1.0 - (w * (n as f64 - 1.0) / n as f64 - acov(t)) / var_plus;
    let (mut sum, mut prev) = (0.0, f64::INFINITY);
    let mut t = 0;
    while t + 1 < n {
        let mut pair = rho(t) + rho(t + 1);
        if pair < 0.0 {
            break;
        }
        pair = pair.min(prev);
        sum += pair;
        prev = pair;
        t += 2;
    }
    let tau = (-1.0 + 2.0 * sum).max(1.0 / ((m * n) as f64).log10());
    (m * n) as f64 / tau
}

/// Φ⁻¹(p), Acklam's rational approximation (relative error below 1.2e-9).
fn probit(p: f64) -> f64 {
    const A: [f64; 6] = [
        -3.969683028665376e1,
        2.209460984245205e2,
        -2.759285104469687e2,
        1.38357751867269e2,
        -3.066479806614716e1,
        2.506628277459239,
    ];
    const B: [f64; 5] =
        [-5.447609879822406e1, 1.615858368580409e2, -1.556989798598866e2, 6.680131188771972e1, -1.328068155288572e1];
    const C: [f64; 6] = [
        -7.784894002430293e-3,
        -3.223964580411365e-1,
        -2.400758277161838,
        -2.549732539343734,
        4.374664141464968,
        2.938163982698783,
    ];
    const D: [f64; 4] = [7.784695709041462e-3, 3.224671290700398e-1, 2.445134137142996, 3.754408661907416];
    let p = p.clamp(1e-300, 1.0 - 1e-16);
    let tail = |q: f64| {
        (((((C[0] * q + C[1]) * q + C[2]) * q + C[3]) * q + C[4]) * q + C[5])
            / ((((D[0] * q + D[1]) * q + D[2]) * q + D[3]) * q + 1.0)
    };
    if p < 0.02425 {
        tail((-2.0 * p.ln()).sqrt())
    } else if p > 1.0 - 0.02425 {
        -tail((-2.0 * (1.0 - p).ln()).sqrt())
    } else {
        let q = p - 0.5;
        let r = q * q;
        (((((A[0] * r + A[1]) * r + A[2]) * r + A[3]) * r + A[4]) * r + A[5]) * q
            / (((((B[0] * r + B[1]) * r + B[2]) * r + B[3]) * r + B[4]) * r + 1.0)
    }
}

/// The likelihood's posterior of one ear, from importance sampling or short chains:
/// summaries, draws, diagnostics.
#[derive(Clone, Debug, Serialize)]
pub struct FastExact {
    /// The diagnostics passed (and the deadline was not hit).
    pub exact: bool,
    /// What answered: `importance` (weighted draws from the flow, their weights passed)
    /// or `chains` (the weights did not pass, or importance sampling was not asked for).
    pub method: &'static str,
    /// Why it is not exact, when not.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub reason: Option<String>,
    /// Per-parameter summaries of all chains' draws; `map` is the least-squares fit from
    /// the flow's MAP.
    pub summaries: Vec<crate::npe::Summary>,
    /// The fit's χ² per degree of freedom.
    pub reduced_chi2: f64,
    /// Chains whose first dispersed start had no density (outside the prior box, or the
    /// simulator failed) and were started at a further draw.
    pub restarted: usize,
    /// The importance weights' ESS and Pareto k̂, when importance sampling ran.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub importance: Option<ImportanceDiagnostics>,
    /// The chains' R̂, ESS, acceptance, steps, when they ran.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub diagnostics: Option<Diagnostics>,
    /// What was run.
    pub settings: Settings,
    /// Wall time: fit, importance sampling and chains.
    pub ms: f64,
    /// All chains' draws (natural units, the model's parameter order).
    #[serde(skip)]
    pub samples: Vec<Vec<f64>>,
}

/// Longest the importance sampling and the chains may run for one ear (fits included) in
/// POST /infer and `otofit infer --posterior exact`; the service's deadline, when
/// shorter, bounds it too. A round of importance sampling the deadline cuts is left out;
/// chains it cuts are not exact. 1.8 s: with the flow's own answer, inside the two
/// seconds asked of the slowest requests on two cores.
pub const BUDGET: std::time::Duration = std::time::Duration::from_millis(1800);

/// What the answer is, said beside it wherever it is reported.
pub const NOTE: &str = "the posterior under the model's own noise likelihood: importance-weighted draws from the flow \
     and a Laplace guess of the posterior's mode (method `importance`), or where their weights do not pass, short Metropolis chains in the flow's latent space \
     started at dispersed points (method `chains`); exact (up to its ESS) only when `exact` is true, i.e. the weights \
     have enough effective draws and a light tail (importance: ESS, Pareto k) or the chains agree and have enough \
     effective draws (R-hat, ESS), within the deadline, and the model fits the ear (fit.ok); narrower than the flow's; \
     parameters[].map is a least-squares fit from the flow's MAP";

impl FastExact {
    /// The normal-range reading of the draws, withdrawn (every parameter `unreliable`,
    /// with the reason) when the answer is not exact.
    pub fn reading(&self, npe: &Npe) -> Vec<crate::npe::normal::Differential> {
        if self.samples.is_empty() {
            return vec![];
        }
        let mut reading = crate::npe::normal::read(npe.params(), &self.samples);
        if !self.exact {
            crate::npe::normal::withdraw(&mut reading, self.reason.as_deref().unwrap_or("not exact"));
        }
        reading
    }

    /// Withdraws the answer because the fit check failed for reason `why`: the likelihood
    /// is then that of a model that does not describe the ear, so it is not exact.
    pub fn withdraw(&mut self, why: &str) {
        let w = format!("withdrawn: the fit check failed ({why})");
        self.exact = false;
        self.reason = Some(self.reason.take().map_or_else(|| w.clone(), |r| format!("{w}; {r}")));
    }
}

/// The posterior of the features `x` that are `present` under `npe`'s simulator and
/// training noise (as [`super::fitcheck::exact`]), by guided importance sampling or,
/// where its weights fail, [`Settings::chains`] short chains in the flow's latent space
/// ([`latent_chains`]), stopping at `deadline`; beside them a least-squares fit from the
/// flow's MAP (`inf.map`, [`Settings::fit_steps`] steps) gives `map` and `reduced_chi2`.
/// The guides' own fits (`latent_guides`, at most as many steps each) run first on the same
/// side of the join as the weighting.
pub fn sample(
    npe: &Npe,
    x: &[f64],
    present: &[bool],
    inf: &Inference,
    s: &Settings,
    deadline: Instant,
) -> Result<FastExact, FitCheckError> {
    let model = simulator_for(npe)?;
    let t0 = Instant::now();
    let target = LatentTarget::new(npe, x, present)?;
    let fit_from_map = || {
        let design = Design::default();
        let mut runner = model.runner();
        fit_columns(&design.columns(), &inf.map, s.fit_steps, |r| residuals(&mut runner, &design, r, &target.obs))
    };
    // The guides' fits run beside the fit from the flow's MAP; the weighting after them.
    let guided = || weighted_or_chains(&target, s, &latent_guides(&target, s.fit_steps, s.seed), deadline);
    let (best, drawn) = rayon::join(fit_from_map, guided);
    let drawn = drawn?;
    let best = best.ok_or_else(|| FitCheckError::Inference("the simulator failed at the flow's MAP".into()))?;
    Ok(FastExact {
        exact: drawn.reason.is_none(),
        method: drawn.method,
        reason: drawn.reason,
        // No draws when the deadline came during the warm-up: nothing to summarise.
        summaries: if drawn.samples.is_empty() {
            vec![]
        } else {
            crate::npe::summarize(npe.params(), &drawn.samples, &best.row)
        },
        reduced_chi2: best.reduced_chi2(),
        restarted: drawn.chains.as_ref().map_or(0, |c| c.restarted),
        importance: drawn.importance,
        diagnostics: drawn.chains.map(|c| c.diagnostics),
        settings: s.clone(),
        ms: t0.elapsed().as_secs_f64() * 1e3,
        samples: drawn.samples,
    })
}

/// The draws of [`sample`] and how they were had.
struct Drawn {
    method: &'static str,
    samples: Vec<Vec<f64>>,
    reason: Option<String>,
    importance: Option<ImportanceDiagnostics>,
    chains: Option<LatentChains>,
}

/// Importance sampling from the flow ([`Settings::importance`]) when its weights pass;
/// else the chains ([`latent_chains`]) until `deadline`, their reason then also saying
/// why the weights did not pass.
fn weighted_or_chains(
    target: &LatentTarget,
    s: &Settings,
    guides: &[Guide],
    deadline: Instant,
) -> Result<Drawn, FitCheckError> {
    let mut importance = None;
    let mut why_not = None;
    if let Some(is) = &s.importance {
        let is = ImportanceSettings { seed: s.seed, ..is.clone() };
        let w = super::importance::sample(|| target.densities(), target.latent.dim(), &is, guides, deadline);
        if w.reason.is_none() {
            let importance = Some(w.diagnostics);
            return Ok(Drawn { method: "importance", samples: w.resampled, reason: None, importance, chains: None });
        }
        why_not = w.reason.map(|r| format!("importance sampling: {r}"));
        importance = Some((w.diagnostics, w.resampled));
    }
    let chains = chains_on(target, s, deadline)?;
    let (importance, weighted) = importance.map_or((None, vec![]), |(g, draws)| (Some(g), draws));
    if chains.samples.is_empty() && !weighted.is_empty() {
        // The deadline came in the chains' warm-up: the weighted draws, not exact, are
        // all there is to summarise.
        let reason = why_not.map(|w| format!("{w}; the deadline left the chains no time to sample"));
        return Ok(Drawn { method: "importance", samples: weighted, reason, importance, chains: Some(chains) });
    }
    let reason = match (chains.reason.clone(), why_not) {
        (Some(r), Some(w)) => Some(format!("{r}; {w}")),
        (r, _) => r,
    };
    let samples = chains.samples.clone();
    Ok(Drawn { method: "chains", samples, reason, importance, chains: Some(chains) })
}

/// What [`latent_chains`] ran and drew.
pub struct LatentChains {
    /// All chains' draws (natural units, the model's parameter order), chain after chain,
    /// each chain's the same length.
    pub samples: Vec<Vec<f64>>,
    /// R̂, ESS, acceptance, steps.
    pub diagnostics: Diagnostics,
    /// Why the draws are not exact, when not.
    pub reason: Option<String>,
    /// Chains whose first dispersed start had no density.
    pub restarted: usize,
    /// What was run (`chains` at least 2).
    pub settings: Settings,
}

/// The chains of [`sample`] alone, without its fit: [`Settings::chains`] random walks in
/// the flow's latent space ([`crate::npe::LatentMap`]) started at dispersed points
/// z ~ N(0, [`START_SD`]² I), stopping at `deadline`. The `exact` job calls this beside
/// its own sixteen fits, whose best already holds what a fit from the MAP would give.
pub fn latent_chains(
    npe: &Npe,
    x: &[f64],
    present: &[bool],
    s: &Settings,
    deadline: Instant,
) -> Result<LatentChains, FitCheckError> {
    chains_on(&LatentTarget::new(npe, x, present)?, s, deadline)
}

/// [`latent_chains`] on a target already built (its flow map is conditioned once).
fn chains_on(target: &LatentTarget, s: &Settings, deadline: Instant) -> Result<LatentChains, FitCheckError> {
    let d = target.latent.dim();
    let chains = s.chains.max(2);
    let new_density = || target.density();
    // Dispersed starts in the latent space, each redrawn (up to START_TRIES times) where
    // it has no density.
    let mut rng = ChaCha8Rng::seed_from_u64(s.seed ^ 0x005e_ed0f_57a7);
    let mut restarted = 0;
    let starts: Vec<Start> = (0..chains)
        .filter_map(|_| {
            let mut density = new_density();
            for attempt in 0..START_TRIES {
                let z: Vec<f64> =
                    (0..d).map(|_| START_SD * Distribution::<f64>::sample(&StandardNormal, &mut rng)).collect();
                if density(&z).0.is_finite() {
                    restarted += usize::from(attempt > 0);
                    return Some(Start { at: z, cov: identity(d) });
                }
            }
            None
        })
        .collect();
    let settings = Settings { chains, ..s.clone() };
    let run = run_chains_mapped(new_density, &starts, &settings, deadline)
        .ok_or_else(|| FitCheckError::Inference("no chain could start in the flow's latent space".into()))?;
    let failed = chains - starts.len();
    let reason = match (run.reason, failed) {
        (r, 0) => r,
        (r, k) => {
            let why = format!("{k} chain(s) found no start with a density in {START_TRIES} draws");
            Some(r.map_or(why.clone(), |r| format!("{why}; {r}")))
        }
    };
    let samples = run.images.into_iter().flatten().collect();
    Ok(LatentChains { samples, diagnostics: run.diagnostics, reason, restarted, settings })
}

/// The likelihood's posterior of one ear in the flow's latent space: its log density
/// log p(x | T(z)) + log p(T(z)) + log |det ∂T/∂z| at z, with T(z) beside it.
struct LatentTarget<'a> {
    npe: &'a Npe,
    model: &'static crate::sim::Model,
    design: Design,
    obs: super::Observation,
    latent: crate::npe::LatentMap<'a>,
}

impl<'a> LatentTarget<'a> {
    fn new(npe: &'a Npe, x: &[f64], present: &[bool]) -> Result<LatentTarget<'a>, FitCheckError> {
        let model = simulator_for(npe)?;
        let latent = npe
            .latent(&crate::npe::Obs { x, present: Some(present) })
            .map_err(|e| FitCheckError::Inference(e.to_string()))?;
        Ok(LatentTarget { npe, model, design: Design::default(), obs: observation(npe, x, present), latent })
    }

    /// The log density and θ at z (−∞ outside the prior box or where the simulator
    /// fails), with a simulator runner of its own. The prior is uniform on each
    /// parameter's scale in its box (that of `super::exact`): log p(θ) = log |dt/dθ|.
    fn density(&self) -> impl FnMut(&[f64]) -> (f64, Vec<f64>) + '_ {
        let mut runner = self.model.runner();
        move |z: &[f64]| {
            let (theta, log_det) = self.latent.to_theta(z);
            self.at(&mut runner, theta, log_det)
        }
    }

    /// [`Self::density`] of a batch of points, the flow's map run once for all of them.
    fn densities(&self) -> impl FnMut(&[Vec<f64>]) -> Vec<(f64, Vec<f64>)> + '_ {
        let mut runner = self.model.runner();
        move |zs: &[Vec<f64>]| {
            let mapped = self.latent.to_thetas(&zs.concat());
            mapped.into_iter().map(|(theta, log_det)| self.at(&mut runner, theta, log_det)).collect()
        }
    }

    /// The log density at θ = T(z), given log |det ∂T/∂z|, and θ.
    fn at(&self, runner: &mut crate::sim::Runner<'_>, theta: Vec<f64>, log_det: f64) -> (f64, Vec<f64>) {
        let params = self.npe.params();
        if !log_det.is_finite() || !params.iter().zip(&theta).all(|(p, &v)| p.contains(v)) {
            return (f64::NEG_INFINITY, theta);
        }
        let prior: f64 = params.iter().zip(&theta).map(|(p, &v)| p.t_log_jacobian(v)).sum();
        let chi2 =
            residuals(runner, &self.design, &theta, &self.obs).map_or(f64::INFINITY, |r| r.iter().map(|v| v * v).sum());
        (-0.5 * chi2 + prior + log_det, theta)
    }
}

/// The mode of exp(−χ²(T(z))/2)·N(z; 0, I) in the flow's latent space and its Laplace
/// covariance, by Levenberg–Marquardt from `start` on the residuals [r(T(z)); z] (at
/// most `steps` steps), with the fit's final Σr² beside it. Where the flow is wider than
/// the likelihood's posterior its density varies slowly across that posterior, so the
/// target π(z) is near this product; its precision JᵀJ includes the identity of the z
/// residuals, so the covariance is never wider than the flow's. Unlike a fit in θ from
/// the flow's MAP, it weighs the flow's own view along the likelihood's ridges. `None`
/// when `start` has no density or a matrix is not positive definite.
fn latent_guide(target: &LatentTarget, start: &[f64], steps: usize) -> Option<(Guide, f64)> {
    let d = target.latent.dim();
    let mut runner = target.model.runner();
    let params = target.npe.params();
    let mut resid = |z: &[f64]| -> Option<Vec<f64>> {
        let (theta, log_det) = target.latent.to_theta(z);
        if !log_det.is_finite() || !params.iter().zip(&theta).all(|(p, &v)| p.contains(v)) {
            return None;
        }
        let mut r = residuals(&mut runner, &target.design, &theta, &target.obs)?;
        r.extend_from_slice(z);
        Some(r)
    };
    let sum_sq = |r: &[f64]| r.iter().map(|v| v * v).sum::<f64>();
    let mut z = start.to_vec();
    let mut r = resid(&z)?;
    let mut c = sum_sq(&r);
    let mut lambda = 1e-2;
    // A step with no density leaves its Jacobian column at zero.
    for _ in 0..steps {
        let (m, g) = normal_equations(&z, &r, true, &mut resid)?;
        let to_trial = |step: &faer::Mat<f64>| (0..d).map(|i| z[i] + step[(i, 0)]).collect();
        let Some((trial, rt, ct)) = damped_step(&m, &g, &mut lambda, c, to_trial, &mut resid, TRIES) else {
            break;
        };
        let gain = c - ct;
        (z, r, c) = (trial, rt, ct);
        if gain <= 1e-6 * c.max(1.0) {
            break;
        }
    }
    let (m, _) = normal_equations(&z, &r, true, &mut resid)?;
    let precision: Vec<f64> = (0..d * d).map(|k| m[(k / d, k % d)]).collect();
    Some((Guide { cov: spd_inverse(&precision, d)?, mean: z }, c))
}

/// Draws of the flow whose best few start further latent fits beside the flow's centre.
const GUIDE_DRAWS: usize = 128;

/// Latent fits (`latent_guide`) beyond the one from the flow's centre.
const GUIDE_STARTS: usize = 7;

/// The modes `latent_guide` finds from the flow's centre and from the best
/// [`GUIDE_STARTS`] of [`GUIDE_DRAWS`] draws of the flow (by the target's density), run
/// side by side, each mode once: a posterior with several modes (ears with fewer
/// measures, whose likelihood has ridges the flow spans) gets a guide at each the fits
/// reach, so the weights see them all; from one start, the rounds could pass on one mode
/// alone. A fit that ends within three of its Laplace deviations of a better one's mode
/// is the same mode.
fn latent_guides(target: &LatentTarget, steps: usize, seed: u64) -> Vec<Guide> {
    let d = target.latent.dim();
    let mut rng = ChaCha8Rng::seed_from_u64(seed ^ 0x0960_1de5);
    let drawn: Vec<Vec<f64>> =
        (0..GUIDE_DRAWS).map(|_| (0..d).map(|_| StandardNormal.sample(&mut rng)).collect()).collect();
    let mut scored: Vec<(f64, Vec<f64>)> =
        target.densities()(&drawn).into_iter().map(|(l, _)| l).zip(drawn).filter(|(l, _)| l.is_finite()).collect();
    scored.sort_by(|a, b| b.0.total_cmp(&a.0));
    let starts: Vec<Vec<f64>> =
        std::iter::once(vec![0.0; d]).chain(scored.into_iter().take(GUIDE_STARTS).map(|(_, z)| z)).collect();
    distinct_modes(starts.par_iter().filter_map(|z| latent_guide(target, z, steps)).collect())
}

/// The fits (each a guide and its objective, lower better) best first, each mode once: a
/// fit whose mode lies within three Laplace deviations of a better fit's mode (in that
/// fit's covariance) is the same mode.
fn distinct_modes(mut fits: Vec<(Guide, f64)>) -> Vec<Guide> {
    fits.sort_by(|a, b| a.1.total_cmp(&b.1));
    // Each kept mode with its precision, inverted once (none: compared with nothing).
    let mut kept: Vec<(Guide, Option<Vec<f64>>)> = vec![];
    for (g, _) in fits {
        let d = g.mean.len();
        let same = kept.iter().any(|(k, inv)| {
            let r: Vec<f64> = (0..d).map(|i| g.mean[i] - k.mean[i]).collect();
            inv.as_ref().is_some_and(|inv| (0..d * d).map(|m| r[m / d] * inv[m] * r[m % d]).sum::<f64>() < 9.0)
        });
        if !same {
            let inv = spd_inverse(&g.cov, d);
            kept.push((g, inv));
        }
    }
    kept.into_iter().map(|(g, _)| g).collect()
}

/// Standard deviation of the chains' starting points in the flow's latent space: wider
/// than the flow (whose draws are N(0, I) there), which is itself wider than the
/// likelihood's posterior, so that agreeing chains have come together.
pub const START_SD: f64 = 1.5;

/// Draws per chain for a starting point with a density (inside the prior box, simulated).
const START_TRIES: usize = 20;

fn identity(d: usize) -> Vec<f64> {
    (0..d * d).map(|k| if k % (d + 1) == 0 { 1.0 } else { 0.0 }).collect()
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::time::Duration;

    /// Fits ending at one mode count once, the best of them kept; a fit four Laplace
    /// deviations away is another mode.
    #[test]
    fn fits_at_the_same_mode_count_once() {
        let guide = |x: f64| Guide { mean: vec![x, 0.0], cov: vec![0.01, 0.0, 0.0, 0.01] };
        let fits = vec![(guide(0.25), 3.0), (guide(0.0), 1.0), (guide(0.4), 2.0), (guide(-0.1), 4.0)];
        let modes = distinct_modes(fits);
        let means: Vec<f64> = modes.iter().map(|g| g.mean[0]).collect();
        assert_eq!(means, [0.0, 0.4], "{means:?}");
    }

    /// The nominal ear with stapes velocity, impedance and absorbance only (five measures,
    /// the guide's example) read by the model's flow for any subset, about 3× wider than
    /// the likelihood's posterior: with the latent Laplace guide the weights pass after
    /// seven rounds, 6,500 draws (ESS 667, k 0.40); from the flow alone only after all
    /// fifteen, 28,000 draws (after eleven, 16,000 draws: ESS 111), more than a request's
    /// budget allows on two cores under load. (The shipped model's own flow for these
    /// three measures is sharp enough to need no guide: 4,500 draws with it, 5,000 without.)
    #[test]
    fn a_five_measure_ear_is_reached_sooner_with_the_latent_guide() {
        let npe =
            Npe::load(&std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("../../models/default.otofit")).unwrap();
        let model = simulator_for(&npe).unwrap();
        let design = Design::default();
        let row: Vec<f64> = design.columns().iter().map(|c| c.nominal).collect();
        let x = crate::sim::batch::run_rows(model, &design, &[row], 0, None).remove(0).unwrap();
        let present = npe.header.features_of_groups(&["stapes_velocity", "impedance", "absorbance"]).unwrap();
        // The masked flow itself, not the three-measure flow `answering` would give.
        let target = LatentTarget::new(&npe, &x, &present).unwrap();
        let guides = latent_guides(&target, 50, 0);
        let is = ImportanceSettings::default();
        let d = target.latent.dim();
        let with = super::super::importance::sample(|| target.densities(), d, &is, &guides, later());
        assert!(with.reason.is_none(), "{:?} {:?}", with.reason, with.diagnostics);
        let without = super::super::importance::sample(|| target.densities(), d, &is, &[], later());
        let (w, wo) = (&with.diagnostics, &without.diagnostics);
        assert!(without.reason.is_some() || wo.draws >= 3 * w.draws, "the flow alone as fast: {wo:?} vs {w:?}");
    }

    fn later() -> Instant {
        Instant::now() + Duration::from_secs(600)
    }

    /// A Gaussian N(μ, Σ) log density, Σ given by standard deviations and one correlation
    /// between the first two coordinates.
    fn gaussian(mu: Vec<f64>, sd: Vec<f64>, rho: f64) -> impl Fn(&[f64]) -> f64 + Sync {
        let d = mu.len();
        let s: Vec<f64> = (0..d * d)
            .map(|k| {
                let (i, j) = (k / d, k % d);
                let r = match (i, j) {
                    _ if i == j => 1.0,
                    (0, 1) | (1, 0) => rho,
                    _ => 0.0,
                };
                r * sd[i] * sd[j]
            })
            .collect();
        let p = spd_inverse(&s, d).unwrap();
        move |x: &[f64]| {
            let r: Vec<f64> = (0..d).map(|i| x[i] - mu[i]).collect();
            -0.5 * (0..d * d).map(|k| r[k / d] * p[k] * r[k % d]).sum::<f64>()
        }
    }

    fn identity(d: usize, v: f64) -> Vec<f64> {
        (0..d * d).map(|k| if k % (d + 1) == 0 { v } else { 0.0 }).collect()
    }

    fn column(run: &Run, k: usize) -> Vec<f64> {
        run.chains.iter().flatten().map(|r| r[k]).collect()
    }

    #[test]
    fn a_correlated_gaussian_is_recovered_and_called_exact() {
        let (mu, sd) = (vec![1.0, -2.0, 0.5, 3.0], vec![0.1, 1.0, 0.3, 2.0]);
        let target = gaussian(mu.clone(), sd.clone(), 0.8);
        // Dispersed starts; a first proposal ten times too narrow and blind to the
        // correlation.
        let starts: Vec<Start> = [[-3.0, 2.0, 3.0, -3.0], [3.0, -6.0, -2.0, 8.0], [0.0; 4], [2.0; 4]]
            .iter()
            .map(|s| Start { at: s.to_vec(), cov: identity(4, 0.01) })
            .collect();
        let run = run_chains(|| &target, &starts, &Settings::default(), later()).unwrap();
        assert!(run.exact, "{:?}", run.reason);
        for k in 0..4 {
            let (m, v) = crate::stats::mean_var_sample(&column(&run, k));
            assert!((m - mu[k]).abs() < 0.1 * sd[k], "mean {k}: {m} vs {}", mu[k]);
            assert!((v.sqrt() / sd[k] - 1.0).abs() < 0.1, "sd {k}: {} vs {}", v.sqrt(), sd[k]);
        }
    }

    /// Two far-apart equal modes at ±10 on the first axis: the mean is 0, and a chain
    /// in one mode never sees the other.
    fn bimodal() -> impl Fn(&[f64]) -> f64 + Sync {
        |x: &[f64]| {
            let a = -0.5 * ((x[0] + 10.0).powi(2) + x[1] * x[1]);
            let b = -0.5 * ((x[0] - 10.0).powi(2) + x[1] * x[1]);
            a.max(b) + (1.0 + (-(a - b).abs()).exp()).ln()
        }
    }

    #[test]
    fn chains_in_different_modes_are_flagged_where_one_chain_alone_looks_converged() {
        let target = bimodal();
        let s = Settings::default();
        let at = |x0: f64| Start { at: vec![x0, 1.0], cov: identity(2, 1.0) };
        // One chain alone: its own split-R-hat and ESS look fine, its mean is wrong.
        let one = |x0: f64| run_chains(|| &target, &[at(x0)], &s, later()).unwrap().chains.remove(0);
        let left = one(-9.0);
        let (rhat, ess, _, _) = diagnose(std::slice::from_ref(&left));
        let m = crate::stats::mean(left.iter().map(|r| r[0]));
        assert!(rhat < s.rhat_max && ess > 100.0, "one chain: R-hat {rhat}, ESS {ess}");
        assert!(m < -9.0, "one chain's mean {m} (the target's is 0)");
        // Four such chains, two in each mode: R-hat says they disagree, and the verdict
        // names it.
        let chains = vec![left, one(-12.0), one(11.0), one(9.0)];
        let (rhat, ess_bulk, ess_tail, per_coordinate) = diagnose(&chains);
        assert!(rhat > 1.5, "R-hat {rhat}");
        let g = Diagnostics {
            rhat,
            ess_bulk,
            ess_tail,
            per_coordinate,
            acceptance: vec![0.3; 4],
            steps: vec![s.steps; 4],
            deadline_hit: false,
        };
        assert!(verdict(&g, &s, 0).is_some_and(|r| r.contains("R-hat")), "{:?}", verdict(&g, &s, 0));
        // Run together from dispersed starts, the chains share what they learn: they
        // either cross between the modes (the mean near 0) or are not called exact.
        let run = run_chains(|| &target, &[-12.0, 11.0, -8.0, 9.0].map(at), &s, later()).unwrap();
        let m = crate::stats::mean(column(&run, 0));
        assert!(!run.exact || m.abs() < 1.0, "called exact with mean {m} (R-hat {})", run.diagnostics.rhat);
    }

    #[test]
    fn a_passed_deadline_stops_the_chains_and_is_not_exact() {
        let target = gaussian(vec![0.0; 3], vec![1.0; 3], 0.0);
        let starts: Vec<Start> = (0..4).map(|k| Start { at: vec![k as f64; 3], cov: identity(3, 1.0) }).collect();
        let run = run_chains(|| &target, &starts, &Settings::default(), Instant::now()).unwrap();
        assert!(!run.exact && run.diagnostics.deadline_hit);
        assert!(run.reason.as_deref().is_some_and(|r| r.contains("deadline")), "{:?}", run.reason);
        // A start without density or a proposal that is not positive definite: no chain.
        let bad = [
            Start { at: vec![f64::NAN; 3], cov: identity(3, 1.0) },
            Start { at: vec![0.0; 3], cov: identity(3, -1.0) },
        ];
        assert!(run_chains(|| |x: &[f64]| -x[0].powi(2), &bad, &Settings::default(), later()).is_none());
    }

    /// AR(1) chains x_t = φ x_{t−1} + √(1 − φ²) ε_t: unit variance and ESS n(1 − φ)/(1 + φ).
    fn ar1(phi: f64, chains: usize, n: usize, shift: f64) -> Vec<Vec<Vec<f64>>> {
        let mut rng = ChaCha8Rng::seed_from_u64(3);
        (0..chains)
            .map(|c| {
                let mut x: f64 = StandardNormal.sample(&mut rng);
                (0..n)
                    .map(|_| {
                        let e: f64 = StandardNormal.sample(&mut rng);
                        x = phi * x + (1.0 - phi * phi).sqrt() * e;
                        vec![x + shift * c as f64]
                    })
                    .collect()
            })
            .collect()
    }

    #[test]
    fn ess_matches_an_autoregressive_chains_and_rhat_sees_shifted_chains() {
        let (phi, m, n) = (0.9, 4, 20_000);
        let (rhat, ess, tail, _) = diagnose(&ar1(phi, m, n, 0.0));
        let expected = (m * n) as f64 * (1.0 - phi) / (1.0 + phi);
        assert!((ess / expected - 1.0).abs() < 0.15, "bulk ESS {ess} vs {expected}");
        // An indicator of an AR(1) forgets faster than the chain itself.
        assert!(tail > 0.85 * expected && tail < (m * n) as f64, "tail ESS {tail} vs {expected}");
        let (_, ess, tail, _) = diagnose(&ar1(0.0, m, n, 0.0));
        assert!(ess > 0.85 * (m * n) as f64 && tail > 0.85 * (m * n) as f64, "independent draws: {ess}, {tail}");
        assert!(rhat < 1.01, "R-hat of agreeing chains {rhat}");
        // Chains half a standard deviation apart.
        let (rhat, _, _, _) = diagnose(&ar1(phi, m, n, 0.5));
        assert!(rhat > 1.05, "R-hat of shifted chains {rhat}");
    }

    #[test]
    fn a_drifting_chain_is_flagged_by_split_rhat() {
        // Four chains that agree with each other but each drift from −1 to +1 (a trend
        // of two standard deviations of the noise around it): their first and second
        // halves differ, which only the split R-hat sees; one such chain alone too.
        let mut rng = ChaCha8Rng::seed_from_u64(5);
        let n = 2000;
        let drifting: Vec<Vec<Vec<f64>>> = (0..4)
            .map(|_| {
                (0..n)
                    .map(|t| {
                        let e: f64 = StandardNormal.sample(&mut rng);
                        vec![-1.0 + 2.0 * t as f64 / n as f64 + 0.5 * e]
                    })
                    .collect()
            })
            .collect();
        let (rhat, ..) = diagnose(&drifting);
        assert!(rhat > 1.2, "four drifting chains: R-hat {rhat}");
        let (rhat, ..) = diagnose(&drifting[..1]);
        assert!(rhat > 1.2, "one drifting chain: R-hat {rhat}");
        // The same noise without the drift is not flagged.
        let flat: Vec<Vec<Vec<f64>>> = drifting
            .iter()
            .map(|c| c.iter().enumerate().map(|(t, r)| vec![r[0] + 1.0 - 2.0 * t as f64 / n as f64]).collect())
            .collect();
        let (rhat, ..) = diagnose(&flat);
        assert!(rhat < 1.01, "stationary chains: R-hat {rhat}");
    }

    #[test]
    fn mapped_chains_keep_each_draws_own_image_and_are_diagnosed_in_both() {
        // A standard normal in z, read through θ = (e^z0, z0 + z1, z1³): every kept image is
        // the map of its own kept draw (not of a rejected proposal), and the images'
        // moments are the map's (E e^z0 = e^½).
        let image = |z: &[f64]| vec![z[0].exp(), z[0] + z[1], z[1].powi(3)];
        let target = |z: &[f64]| (-0.5 * (z[0] * z[0] + z[1] * z[1]), image(z));
        let starts: Vec<Start> = [[-2.0, 2.0], [2.0, -2.0], [0.0, 2.0], [1.0, 1.0]]
            .iter()
            .map(|a| Start { at: a.to_vec(), cov: identity(2, 1.0) })
            .collect();
        let run = run_chains_mapped(|| target, &starts, &Settings::default(), later()).unwrap();
        assert!(run.exact, "{:?}", run.reason);
        assert_eq!(run.images.len(), run.chains.len());
        for (c, im) in run.chains.iter().zip(&run.images) {
            assert_eq!(c.len(), im.len());
            assert!(c.iter().zip(im).all(|(z, t)| *t == image(z)), "an image that is not its draw's");
        }
        let m = crate::stats::mean(run.images.iter().flatten().map(|t| t[0]));
        assert!((m / 0.5f64.exp() - 1.0).abs() < 0.1, "E e^z0 {m} vs {}", 0.5f64.exp());
        // The diagnostics are the worse of the draws' and the images' (the images are
        // what the answer reports); per coordinate, the images'.
        let (rhat_z, ess_z, ..) = diagnose(&run.chains);
        let (rhat_t, ess_t, ..) = diagnose(&run.images);
        let g = &run.diagnostics;
        assert_eq!(g.per_coordinate.len(), 3, "{:?}", g.per_coordinate);
        assert!(g.rhat == rhat_z.max(rhat_t) && g.ess_bulk == ess_z.min(ess_t), "{g:?}");
    }

    #[test]
    fn a_failed_fit_check_withdraws_an_exact_answer_and_its_reading() {
        let g = Diagnostics {
            rhat: 1.0,
            ess_bulk: 1000.0,
            ess_tail: 1000.0,
            per_coordinate: vec![],
            acceptance: vec![0.3; 4],
            steps: vec![2000; 4],
            deadline_hit: false,
        };
        let mut e = FastExact {
            exact: true,
            method: "chains",
            reason: None,
            summaries: vec![],
            reduced_chi2: 1.0,
            restarted: 0,
            importance: None,
            diagnostics: Some(g),
            settings: Settings::default(),
            ms: 1.0,
            samples: vec![],
        };
        e.withdraw("χ² too large");
        assert!(!e.exact);
        assert_eq!(e.reason.as_deref(), Some("withdrawn: the fit check failed (χ² too large)"));
        e.reason = Some("the chains disagree".into());
        e.withdraw("again");
        assert!(e.reason.as_deref().is_some_and(|r| r.starts_with("withdrawn") && r.ends_with("the chains disagree")));
    }

    #[test]
    fn probit_inverts_the_normal_cdf() {
        for (p, z) in [(0.5, 0.0), (0.975, 1.959_963_985), (0.05, -1.644_853_627), (1e-6, -4.753_424_309)] {
            assert!((probit(p) - z).abs() < 1e-6, "probit({p}) = {} vs {z}", probit(p));
        }
    }
}
