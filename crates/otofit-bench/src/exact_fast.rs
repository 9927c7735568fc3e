//! The short chains of POST /infer's exact posterior (`discrepancy::exact_fast`) on
//! held-out simulated ears: `otofit bench exact`.
//!
//! The ears, their noise and their scoring are those of [`crate::posterior`] (half prior
//! draws, half near the model's degeneracies; 1× test–retest noise). On every ear: the
//! short chains' 50 % and 90 % coverage of the truth per tissue parameter, their
//! diagnostics (R-hat, ESS, `exact`) and wall time. On the first `reference` ears also
//! the long chains (`fitcheck::exact`, the `exact` job's four chains of 25,000 steps by
//! default) and the C2ST between
//! its draws and the short chains' over the tissue parameters: the short chains sample
//! the same posterior when it is near 0.5.

use crate::c2st::{self, C2stParams};
use crate::posterior::{
    C2ST_DRAWS, FLOW_SAMPLES, Marginal, ParamScore, Pooled, ears, marginals, pool, score, tissue_coords,
};
use anyhow::{Result, anyhow, bail};
use otofit_discrepancy::discrepancy::exact::MAX_STEPS;
use otofit_discrepancy::discrepancy::exact_fast::{self, Settings};
use otofit_discrepancy::discrepancy::fitcheck::{exact, simulator_for};
use otofit_npe::npe::{Npe, Obs};
use otofit_npe::stats;
use otofit_sim::N_TISSUE;
use otofit_sim::batch::{Design, Noise, default_noise_std, run_rows};
use serde::Serialize;
use std::fmt::Write;
use std::time::Instant;

/// How big a run is.
#[derive(Clone, Debug)]
pub struct FastParams {
    /// Held-out ears scored for coverage.
    pub ears: usize,
    /// Of those, the first this many also get the long chain and a C2ST.
    pub reference: usize,
    /// Long-chain steps.
    pub steps: usize,
    /// Seed of the ears, their noise, the flow's draws and the chains.
    pub seed: u64,
    /// Feature groups given (every feature when empty), as a clinic's subset of measures.
    pub measures: Vec<String>,
}

impl FastParams {
    /// Refuses sizes the benchmark cannot run, naming the CLI's argument.
    pub fn check(&self) -> Result<()> {
        if !(1..=crate::posterior::MAX_EARS).contains(&self.ears) {
            bail!("--ears must be 1..={} (got {})", crate::posterior::MAX_EARS, self.ears);
        }
        if self.reference > self.ears {
            bail!("--reference must be 0..=--ears ({}) (got {})", self.ears, self.reference);
        }
        if !(crate::posterior::MIN_STEPS..=MAX_STEPS).contains(&self.steps) {
            bail!("--steps must be {}..={MAX_STEPS} (got {})", crate::posterior::MIN_STEPS, self.steps);
        }
        Ok(())
    }
}

/// A scored ear, or the index of one that could not be scored and why.
pub type EarOutcome = Result<FastEar, (usize, String)>;

/// One ear's outcome.
#[derive(Clone, Debug, Serialize)]
pub struct FastEar {
    /// Its index.
    pub ear: usize,
    /// `prior` or the recipe's name.
    pub kind: &'static str,
    /// The flow (`flow`) and the short chains (`exact`) on each tissue parameter.
    pub params: Vec<ParamScore>,
    /// The in-request answer's verdict.
    pub exact: bool,
    /// What answered: `importance` or `chains`.
    pub method: &'static str,
    /// Why not exact, when not.
    pub reason: Option<String>,
    /// The importance weights' Kish ESS, when importance sampling ran.
    pub importance_ess: Option<f64>,
    /// Their Pareto k̂.
    pub pareto_k: Option<f64>,
    /// Largest R-hat over the parameters, when the chains ran and took a sampling step.
    pub rhat: Option<f64>,
    /// Smallest bulk ESS of the chains.
    pub ess_bulk: Option<f64>,
    /// Smallest tail ESS of the chains.
    pub ess_tail: Option<f64>,
    /// Wall time of the short chains (fits included).
    pub seconds: f64,
    /// C2ST between the short chains' and the long chain's draws (reference ears).
    pub c2st: Option<f64>,
    /// The same for the flow's draws against the long chain.
    pub c2st_flow: Option<f64>,
    /// Wall time of the long chain.
    pub long_seconds: Option<f64>,
    /// The long chains' own scores per tissue parameter (reference ears): the reference is
    /// a sampler too, so it is checked against the truth.
    pub long: Option<Vec<Marginal>>,
    /// The long chains' R-hat across the chains, as the `exact` job reports it.
    pub long_rhat: Option<f64>,
}

/// The long chain against the short chains on the reference ears, pooled over (ear,
/// tissue parameter) pairs.
#[derive(Clone, Debug, Serialize)]
pub struct LongChain {
    /// Pairs pooled.
    pub pairs: usize,
    /// Fraction whose long-chain 50 % interval holds the truth.
    pub cover50: f64,
    /// Fraction whose long-chain 90 % interval holds the truth.
    pub cover90: f64,
    /// The short chains' 90 % coverage on the same pairs.
    pub short_cover90: f64,
    /// Median of the short chains' 90 % width over the long chain's.
    pub width_ratio_median: f64,
}

/// Pools the reference ears' long-chain scores beside the short chains'.
fn pool_long(per_ear: &[FastEar]) -> LongChain {
    let pairs: Vec<(&Marginal, &ParamScore)> =
        per_ear.iter().filter_map(|e| e.long.as_ref().map(|l| l.iter().zip(&e.params))).flatten().collect();
    let n = pairs.len().max(1) as f64;
    let share = |f: &dyn Fn(&(&Marginal, &ParamScore)) -> bool| pairs.iter().filter(|p| f(p)).count() as f64 / n;
    LongChain {
        pairs: pairs.len(),
        cover50: share(&|(l, _)| l.in50),
        cover90: share(&|(l, _)| l.in90),
        short_cover90: share(&|(_, s)| s.exact.in90),
        width_ratio_median: median(pairs.iter().map(|(l, s)| s.exact.width90 / l.width90).collect()),
    }
}

/// A whole run.
#[derive(Clone, Debug, Serialize)]
pub struct FastReport {
    /// The ears asked for, the reference ears, the long chain's steps, the seed.
    pub ears: usize,
    /// Ears with the long chain.
    pub reference: usize,
    /// Long-chain steps.
    pub steps: usize,
    /// The seed.
    pub seed: u64,
    /// Feature groups given (all when empty).
    pub measures: Vec<String>,
    /// The short chains' settings.
    pub settings: Settings,
    /// Pooled over all scored ears and tissue parameters (`exact_*`: the short chains).
    pub all: Pooled,
    /// The same over the ears called exact.
    pub called_exact: Pooled,
    /// Ears called exact.
    pub exact_ears: usize,
    /// Median C2ST short chains against the long chain, over the reference ears.
    pub c2st_median: f64,
    /// Median C2ST of the flow against the long chain.
    pub c2st_flow_median: f64,
    /// The long chain's own coverage and the short chains' width against it.
    pub long: LongChain,
    /// Ears called exact by importance sampling (the rest by the chains).
    pub importance_ears: usize,
    /// Median Kish ESS and Pareto k̂ of the importance weights over the ears.
    pub importance_ess_median: f64,
    /// Median Pareto k̂.
    pub pareto_k_median: f64,
    /// Median and largest wall time of the short chains.
    pub seconds_median: f64,
    /// Largest wall time of the short chains.
    pub seconds_max: f64,
    /// Every scored ear.
    pub per_ear: Vec<FastEar>,
    /// Ears that could not be scored, and why.
    pub skipped: Vec<(usize, String)>,
}

fn c2st_of(npe: &Npe, a: &[Vec<f64>], b: &[Vec<f64>], seed: u64) -> f64 {
    let tissue = &npe.params()[..N_TISSUE];
    let m = C2ST_DRAWS.min(a.len()).min(b.len());
    c2st::c2st(
        &tissue_coords(tissue, a, m),
        &tissue_coords(tissue, b, m),
        &C2stParams { seed, ..C2stParams::default() },
    )
}

fn one_ear(
    npe: &Npe,
    (i, kind): (usize, &'static str),
    truth: &[f64],
    x: &[f64],
    present: &[bool],
    p: &FastParams,
) -> Result<FastEar> {
    let seed = p.seed.wrapping_add(i as u64);
    // The flow the service would pick: with every measure, the model's full-measure flow
    // when it holds one.
    let npe = npe.answering(&Obs { x, present: Some(present) });
    let inf = npe.infer(&Obs { x, present: Some(present) }, FLOW_SAMPLES, seed)?;
    let t = Instant::now();
    let settings = Settings { seed, ..Settings::default() };
    let fast = exact_fast::sample(npe, x, present, &inf, &settings, Instant::now() + exact_fast::BUDGET)?;
    let seconds = t.elapsed().as_secs_f64();
    if fast.samples.is_empty() {
        bail!("no draws within {:.1} s: {}", seconds, fast.reason.as_deref().unwrap_or("?"));
    }
    let tissue = &npe.params()[..N_TISSUE];
    let (mut c2st, mut c2st_flow, mut long_seconds, mut long_scores, mut long_rhat) = (None, None, None, None, None);
    if i < p.reference {
        let t = Instant::now();
        let long = exact(npe, x, present, &inf, p.steps, seed)?;
        long_seconds = Some(t.elapsed().as_secs_f64());
        c2st = Some(c2st_of(npe, &long.chain.samples, &fast.samples, seed));
        c2st_flow = Some(c2st_of(npe, &long.chain.samples, &inf.samples, seed));
        long_scores = Some(marginals(tissue, truth, &long.chain.samples));
        long_rhat = Some(exact_fast::by_segments(&long.chain.samples, long.chain.chains).0);
    }
    let g = fast.diagnostics.as_ref();
    let w = fast.importance.as_ref();
    Ok(FastEar {
        ear: i,
        kind,
        params: score(tissue, truth, &inf.samples, &fast.samples),
        exact: fast.exact,
        method: fast.method,
        reason: fast.reason.clone(),
        importance_ess: w.map(|w| w.ess),
        pareto_k: w.map(|w| w.pareto_k),
        // Chains that took no sampling step have no R-hat or ESS (NaN): none is printed.
        rhat: g.map(|g| g.rhat).filter(|v| v.is_finite()),
        ess_bulk: g.map(|g| g.ess_bulk).filter(|v| v.is_finite()),
        ess_tail: g.map(|g| g.ess_tail).filter(|v| v.is_finite()),
        seconds,
        c2st,
        c2st_flow,
        long_seconds,
        long: long_scores,
        long_rhat,
    })
}

fn median(v: Vec<f64>) -> f64 {
    stats::median_upper(&stats::sorted(v))
}

/// Simulates the ears of `p`, reads each with the flow and the short chains (and the
/// long chain on the reference ears), one ear after the other, and pools the scores.
pub fn run(npe: &Npe, p: &FastParams, progress: &mut dyn FnMut(&EarOutcome)) -> Result<FastReport> {
    p.check()?;
    let model = simulator_for(npe)?;
    let present = npe.header.features_of_groups(&p.measures).map_err(|e| anyhow!("--measures: {e}"))?;
    let held = ears(p.ears, p.seed);
    let rows: Vec<Vec<f64>> = held.iter().map(|e| e.row.clone()).collect();
    let noise = Noise { std: default_noise_std(model), scale: 1.0, seed: p.seed };
    let xs = run_rows(model, &Design::default(), &rows, 0, Some(&noise));
    let (mut per_ear, mut skipped) = (vec![], vec![]);
    for (i, (ear, x)) in held.iter().zip(xs).enumerate() {
        let outcome = x
            .map_err(anyhow::Error::from)
            .and_then(|x| one_ear(npe, (i, ear.kind), &ear.row, &x, &present, p))
            .map_err(|e| (i, format!("{e:#}")));
        progress(&outcome);
        match outcome {
            Ok(r) => per_ear.push(r),
            Err(s) => skipped.push(s),
        }
    }
    let exact_ears: Vec<&FastEar> = per_ear.iter().filter(|e| e.exact).collect();
    let seconds: Vec<f64> = per_ear.iter().map(|e| e.seconds).collect();
    Ok(FastReport {
        ears: p.ears,
        reference: p.reference,
        steps: p.steps,
        seed: p.seed,
        measures: p.measures.clone(),
        settings: Settings::default(),
        all: pool(per_ear.iter().flat_map(|e| &e.params)),
        called_exact: pool(exact_ears.iter().flat_map(|e| &e.params)),
        exact_ears: exact_ears.len(),
        c2st_median: median(per_ear.iter().filter_map(|e| e.c2st).collect()),
        c2st_flow_median: median(per_ear.iter().filter_map(|e| e.c2st_flow).collect()),
        long: pool_long(&per_ear),
        importance_ears: exact_ears.iter().filter(|e| e.method == "importance").count(),
        importance_ess_median: median(per_ear.iter().filter_map(|e| e.importance_ess).collect()),
        pareto_k_median: median(per_ear.iter().filter_map(|e| e.pareto_k).collect()),
        seconds_median: median(seconds.clone()),
        seconds_max: seconds.iter().copied().fold(f64::NAN, f64::max),
        per_ear,
        skipped,
    })
}

/// The report as text: coverage, agreement, diagnostics, time, against the targets.
pub fn table(r: &FastReport) -> String {
    let mut s = String::new();
    let scored = r.per_ear.len();
    let _ = writeln!(
        s,
        "{scored} of {} ears scored ({} skipped), seed {}, measures {}; importance sampling {:?} draws per round (+{} wide), \
         else {} chains × ({} warm-up + {} steps); {} reference ears with a {}-step chain",
        r.ears,
        r.skipped.len(),
        r.seed,
        if r.measures.is_empty() { "all".to_string() } else { r.measures.join(",") },
        r.settings.importance.as_ref().map(|i| i.rounds.clone()).unwrap_or_default(),
        r.settings.importance.as_ref().map_or(0, |i| i.wide),
        r.settings.chains,
        r.settings.warmup,
        r.settings.steps,
        r.reference,
        r.steps
    );
    let _ = writeln!(s, "\n| ears | pairs | 50 % coverage | 90 % coverage (target 0.87–0.93) | flow 90 % coverage |");
    let _ = writeln!(s, "|---|---|---|---|---|");
    for (name, q) in [("all", &r.all), ("called exact", &r.called_exact)] {
        let _ = writeln!(
            s,
            "| {name} | {} | {:.3} | {:.3} | {:.3} |",
            q.pairs, q.exact_cover50, q.exact_cover90, q.flow_cover90
        );
    }
    let _ = writeln!(
        s,
        "\ncalled exact: {} of {scored} ({} by importance sampling: median ESS {:.0}, Pareto k {:.2}); median C2ST \
         in-request vs long chain {:.3} (target ≤ 0.6), flow vs long chain {:.3}; in-request wall time median \
         {:.2} s, max {:.2} s",
        r.exact_ears,
        r.importance_ears,
        r.importance_ess_median,
        r.pareto_k_median,
        r.c2st_median,
        r.c2st_flow_median,
        r.seconds_median,
        r.seconds_max
    );
    let l = &r.long;
    if l.pairs > 0 {
        let _ = writeln!(
            s,
            "long chain on the {} reference pairs: 50 % coverage {:.3}, 90 % coverage {:.3} (short chains {:.3}); \
             short/long 90 % width, median {:.2}",
            l.pairs, l.cover50, l.cover90, l.short_cover90, l.width_ratio_median
        );
    }
    let mut reasons: Vec<&str> = r.per_ear.iter().filter_map(|e| e.reason.as_deref()).collect();
    reasons.sort_unstable();
    for why in reasons.iter().take(10) {
        let _ = writeln!(s, "not exact: {why}");
    }
    s
}

#[cfg(test)]
mod tests {
    use super::*;

    fn marginal(in90: bool, width90: f64) -> Marginal {
        Marginal { in50: false, in90, width90, reading: "within", confident_wrong: false }
    }

    fn ear(long: Option<Vec<Marginal>>, short: Vec<Marginal>) -> FastEar {
        let params = short
            .into_iter()
            .map(|m| ParamScore { name: "p".into(), truth: 1.0, flow: m.clone(), exact: m, width_ratio: 1.0 })
            .collect();
        FastEar {
            ear: 0,
            kind: "prior",
            params,
            exact: false,
            method: "chains",
            reason: None,
            importance_ess: None,
            pareto_k: None,
            rhat: Some(1.0),
            ess_bulk: Some(1.0),
            ess_tail: Some(1.0),
            seconds: 0.0,
            c2st: None,
            c2st_flow: None,
            long_seconds: None,
            long,
            long_rhat: None,
        }
    }

    /// The long chain is scored on the reference ears only, pair by pair against the short
    /// chains of the same ear: a reference chain narrower than the short chains and missing
    /// a truth they hold shows as lower coverage and a width ratio above 1.
    #[test]
    fn the_long_chain_is_pooled_over_the_reference_ears_only() {
        let reference =
            ear(Some(vec![marginal(true, 1.0), marginal(false, 0.5)]), vec![marginal(true, 1.0), marginal(true, 1.5)]);
        let other = ear(None, vec![marginal(false, 9.0), marginal(false, 9.0)]);
        let l = pool_long(&[reference, other]);
        assert_eq!(l.pairs, 2);
        assert_eq!((l.cover90, l.short_cover90), (0.5, 1.0));
        assert!((l.width_ratio_median - 3.0).abs() < 1e-12, "{}", l.width_ratio_median);
    }
}
