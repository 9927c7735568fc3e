//! Calibration on held-out simulations: expected coverage of highest-density regions at
//! credible levels 0.05…0.95 (Hermans et al. 2022) and SBC ranks per parameter (Talts
//! et al. 2018).

use super::{Npe, NpeError, Obs, Result};
use crate::stats::quantile_floor;
use serde::Serialize;

/// Coverage and SBC ranks of a model on held-out simulations.
#[derive(Clone, Debug, Serialize)]
pub struct Calibration {
    /// Held-out rows used.
    pub rows: usize,
    /// Posterior samples drawn per row.
    pub samples_per_row: usize,
    /// Credible levels 0.05…0.95.
    pub levels: Vec<f64>,
    /// Fraction of rows whose true θ lies inside the level's highest-density region.
    pub coverage: Vec<f64>,
    /// Per parameter: rank of the true value among the samples (0..=samples) per row.
    pub sbc_ranks: Vec<ParamRanks>,
    /// Per parameter: fraction of rows with the truth inside the central 90 % interval.
    pub marginal_coverage90: Vec<f64>,
}

/// SBC ranks of one parameter over the rows.
#[derive(Clone, Debug, Serialize)]
pub struct ParamRanks {
    /// The parameter.
    pub name: String,
    /// Rank of the truth among the samples, per row.
    pub ranks: Vec<usize>,
}

impl ParamRanks {
    /// Pearson χ² of the ranks in `bins` equal bins against a uniform histogram (SBC:
    /// uniform ranks ⇔ calibrated marginal), and its degrees of freedom (bins − 1). For
    /// 10 bins the 99 % quantile of χ²(9) is 21.7.
    pub fn chi2(&self, samples: usize, bins: usize) -> (f64, usize) {
        let bins = bins.max(1);
        let mut counts = vec![0.0; bins];
        for &r in &self.ranks {
            counts[((r as f64 / (samples + 1) as f64 * bins as f64) as usize).min(bins - 1)] += 1.0;
        }
        let e = self.ranks.len() as f64 / bins as f64;
        (counts.iter().map(|c| (c - e).powi(2) / e.max(1e-12)).sum(), bins - 1)
    }
}

/// `rows`: (θ, x) pairs not used in training.
pub fn calibrate(npe: &Npe, rows: &[(Vec<f64>, Vec<f64>)], samples: usize, seed: u64) -> Result<Calibration> {
    calibrate_with(npe, rows, samples, seed, &mut |_| {})
}

/// [`calibrate`], calling `progress` with the number of rows done as they finish.
///
/// The rows are read side by side, a few per thread at a time (the progress callback runs
/// between those chunks): a row's draws come from its own seed (`seed` + its index), so
/// the result is the same on any number of threads.
pub fn calibrate_with(
    npe: &Npe,
    rows: &[(Vec<f64>, Vec<f64>)],
    samples: usize,
    seed: u64,
    progress: &mut dyn FnMut(usize),
) -> Result<Calibration> {
    calibrate_given(npe, rows, samples, seed, None, progress)
}

/// [`calibrate_with`] on the rows as a clinic gives them: only the features `present`
/// marks (some measures, part of the band), each row answered by the flow of the file
/// that answers such ears ([`Npe::answering`]) — the calibration of what a user of
/// those measures gets. `None`: every feature, the file's main flow.
pub fn calibrate_given(
    npe: &Npe,
    rows: &[(Vec<f64>, Vec<f64>)],
    samples: usize,
    seed: u64,
    present: Option<&[bool]>,
    progress: &mut dyn FnMut(usize),
) -> Result<Calibration> {
    use rayon::prelude::*;
    if samples < 2 {
        return Err(NpeError::settings(
            "samples",
            format!("calibration needs at least 2 samples per row, got {samples}"),
        ));
    }
    let levels: Vec<f64> = (1..=19).map(|i| i as f64 * 0.05).collect();
    let d = npe.params().len();
    if let Some(r) = rows.iter().position(|(theta, _)| theta.len() != d) {
        return Err(NpeError::settings("rows", format!("row {r} has {} parameters, the model {d}", rows[r].0.len())));
    }
    if let Some(p) = present.filter(|p| p.len() != npe.header.feature_names.len()) {
        let n = npe.header.feature_names.len();
        return Err(NpeError::settings("present", format!("{} feature flags, the model has {n} features", p.len())));
    }
    let mut inside = vec![0usize; levels.len()];
    let mut ranks = vec![Vec::with_capacity(rows.len()); d];
    let mut marginal = vec![0usize; d];
    let chunk = 4 * rayon::current_num_threads().max(1);
    for (c, part) in rows.chunks(chunk).enumerate() {
        let read: Vec<RowReading> = (part.par_iter().enumerate())
            .map(|(i, row)| read_row(npe, row, present, samples, seed.wrapping_add((c * chunk + i) as u64)))
            .collect::<Result<_>>()?;
        for row in read {
            for (k, &a) in levels.iter().enumerate() {
                if row.denser < a {
                    inside[k] += 1;
                }
            }
            for k in 0..d {
                ranks[k].push(row.ranks[k]);
                marginal[k] += usize::from(row.inside90[k]);
            }
        }
        progress(rows.len().min((c + 1) * chunk));
    }
    let n = rows.len().max(1) as f64;
    Ok(Calibration {
        rows: rows.len(),
        samples_per_row: samples,
        coverage: inside.iter().map(|&c| c as f64 / n).collect(),
        levels,
        sbc_ranks: npe.params().iter().zip(ranks).map(|(p, r)| ParamRanks { name: p.name.clone(), ranks: r }).collect(),
        marginal_coverage90: marginal.iter().map(|&c| c as f64 / n).collect(),
    })
}

/// What one held-out row says of the posterior: the share of draws denser than the
/// truth, and per parameter the truth's rank among the draws and whether the central
/// 90 % interval holds it.
struct RowReading {
    denser: f64,
    ranks: Vec<usize>,
    inside90: Vec<bool>,
}

fn read_row(
    npe: &Npe,
    (theta, x): &(Vec<f64>, Vec<f64>),
    present: Option<&[bool]>,
    samples: usize,
    seed: u64,
) -> Result<RowReading> {
    let obs = Obs { x, present };
    let npe = if present.is_some() { npe.answering(&obs) } else { npe };
    let draws = npe.sample(&obs, samples, seed)?;
    // Densities in the flow's unbounded space (natural-unit densities less the
    // bijection's Jacobian): there a widened posterior stays a bell, whereas in θ the
    // logit's Jacobian piles density onto the box edges and ranks edge draws above the
    // truth. HPD regions of either density are valid credible regions.
    let flow_lp = |t: &[Vec<f64>]| -> Result<Vec<f64>> {
        let lp = npe.log_prob(&obs, t)?;
        Ok(lp.iter().zip(t).map(|(l, t)| l - npe.log_jacobian(t)).collect())
    };
    let lp = flow_lp(&draws)?;
    let lp_true = flow_lp(std::slice::from_ref(theta))?[0];
    // θ lies in the α-HPD region iff fewer than α of the draws are denser than it.
    let denser = lp.iter().filter(|&&l| l > lp_true).count() as f64 / samples as f64;
    let (mut ranks, mut inside90) = (Vec::with_capacity(theta.len()), Vec::with_capacity(theta.len()));
    for (k, &t) in theta.iter().enumerate() {
        let mut v: Vec<f64> = draws.iter().map(|s| s[k]).collect();
        ranks.push(v.iter().filter(|&&s| s < t).count());
        v.sort_by(f64::total_cmp);
        inside90.push(t >= quantile_floor(&v, 0.05) && t <= quantile_floor(&v, 0.95));
    }
    Ok(RowReading { denser, ranks, inside90 })
}

/// Credible levels the temperature is tuned at (the levels the calibration targets name).
pub const TUNE_LEVELS: [f64; 4] = [0.5, 0.8, 0.9, 0.95];

/// The outcome of tuning the base temperature.
#[derive(Clone, Debug, Serialize)]
pub struct Tuning {
    /// The tuned base-distribution temperature.
    pub temperature: f64,
    /// Whether `temperature` reaches every level (less the slack); when no temperature
    /// in the searched range does, `temperature` is the one that came closest.
    pub reached: bool,
    /// Joint HPD coverage at `TUNE_LEVELS` on the tuning rows, before and after.
    pub levels: Vec<f64>,
    /// Coverage at temperature 1.
    pub coverage_before: Vec<f64>,
    /// Coverage at the tuned temperature.
    pub coverage_after: Vec<f64>,
}

/// Joint HPD coverage at `levels` on `rows` with the model's current temperature.
pub fn joint_coverage(npe: &Npe, rows: &[(Vec<f64>, Vec<f64>)], samples: usize, seed: u64) -> Result<Vec<f64>> {
    let cal = calibrate(npe, rows, samples, seed)?;
    Ok(TUNE_LEVELS
        .iter()
        .map(|l| {
            let k = cal.levels.iter().position(|v| (v - l).abs() < 1e-9).unwrap_or(0);
            cal.coverage[k]
        })
        .collect())
}

/// Post-hoc recalibration: the smallest base-distribution temperature T (the flow's
/// z ~ N(0, T² I)) in [1, 4] at which the joint HPD coverage on `rows` reaches every
/// level in `TUNE_LEVELS` less `slack`; where none does, the one that comes closest
/// (`reached: false`). The coverage of the result must be measured on other held-out
/// rows.
pub fn tune_temperature(
    npe: &mut Npe,
    rows: &[(Vec<f64>, Vec<f64>)],
    samples: usize,
    seed: u64,
    slack: f64,
) -> Result<Tuning> {
    let tuning = search_temperature(
        &mut |t| {
            npe.header.temperature = t;
            joint_coverage(npe, rows, samples, seed)
        },
        slack,
    )?;
    npe.header.temperature = tuning.temperature;
    Ok(tuning)
}

/// Temperatures tried in turn before bisecting between the last short one and the first
/// that reaches the levels.
const TEMPERATURE_GRID: [f64; 7] = [1.0, 1.25, 1.5, 2.0, 2.5, 3.0, 4.0];

/// The search of [`tune_temperature`] over a coverage curve `coverage_at(T)`. Coverage
/// need not grow with T: far out, a flow's HPD ranks follow its Jacobian more than its
/// base density and coverage can fall, so the grid is walked upwards and bisection is
/// used only inside the first bracket, keeping only temperatures whose coverage was
/// measured to reach the levels.
fn search_temperature(coverage_at: &mut dyn FnMut(f64) -> Result<Vec<f64>>, slack: f64) -> Result<Tuning> {
    // How far the worst level falls short of its target (≤ 0: reached).
    let shortfall = |c: &[f64]| TUNE_LEVELS.iter().zip(c).map(|(l, c)| l - slack - c).fold(f64::MIN, f64::max);
    let before = coverage_at(TEMPERATURE_GRID[0])?;
    let mut best = (TEMPERATURE_GRID[0], before.clone());
    let tuning = |t: f64, after: Vec<f64>, reached: bool, before: Vec<f64>| Tuning {
        temperature: t,
        reached,
        levels: TUNE_LEVELS.to_vec(),
        coverage_before: before,
        coverage_after: after,
    };
    if shortfall(&before) <= 0.0 {
        return Ok(tuning(1.0, before.clone(), true, before));
    }
    for pair in TEMPERATURE_GRID.windows(2) {
        let c = coverage_at(pair[1])?;
        if shortfall(&c) < shortfall(&best.1) {
            best = (pair[1], c.clone());
        }
        if shortfall(&c) > 0.0 {
            continue;
        }
        let (mut lo, mut hi, mut at_hi) = (pair[0], pair[1], c);
        for _ in 0..5 {
            let mid = 0.5 * (lo + hi);
            let c = coverage_at(mid)?;
            if shortfall(&c) > 0.0 {
                lo = mid;
            } else {
                (hi, at_hi) = (mid, c);
            }
        }
        return Ok(tuning(hi, at_hi, true, before));
    }
    Ok(tuning(best.0, best.1, false, before))
}

#[cfg(test)]
mod tests {
    use super::{ParamRanks, TUNE_LEVELS, Tuning, search_temperature};

    /// Tunes against a coverage curve that is the same at every level, counting calls.
    fn search(curve: impl Fn(f64) -> f64) -> (Tuning, usize) {
        let mut calls = 0;
        let t = search_temperature(
            &mut |t| {
                calls += 1;
                Ok(vec![curve(t); TUNE_LEVELS.len()])
            },
            0.01,
        )
        .unwrap();
        (t, calls)
    }

    #[test]
    fn the_temperature_is_the_smallest_that_reaches_the_levels_and_never_a_worse_one() {
        // Covered already: T stays 1.
        let (t, calls) = search(|_| 0.97);
        assert!(t.reached && t.temperature == 1.0 && calls == 1, "{t:?}");
        // Coverage rising with T, reaching 0.95 − 0.01 at T = 1.88: found to within the
        // bisection's step and measured to reach it.
        let (t, _) = search(|t| (0.5 * t).min(1.0));
        assert!(t.reached && (1.88..1.92).contains(&t.temperature), "{t:?}");
        assert!(t.coverage_after.iter().all(|&c| c >= 0.94), "{t:?}");
        // Coverage that peaks short of the levels at T = 1.25 and then falls: no T
        // reaches them, and the answer is the one that came closest, not the range's end.
        let (t, _) = search(|t| if t <= 1.25 { 0.8 + 0.4 * (t - 1.0) } else { 0.9 - 0.2 * (t - 1.25) });
        assert!(!t.reached && t.temperature == 1.25, "{t:?}");
        assert!(t.coverage_after[0] >= t.coverage_before[0], "{t:?}");
        // Falling from the start: T stays 1.
        let (t, _) = search(|t| 0.83 - 0.1 * (t - 1.0));
        assert!(!t.reached && t.temperature == 1.0, "{t:?}");
    }

    #[test]
    fn sbc_chi2_is_small_for_uniform_ranks_and_large_for_skewed_ones() {
        let uniform = ParamRanks { name: "u".into(), ranks: (0..1000).map(|i| i % 101).collect() };
        let (c, dof) = uniform.chi2(100, 10);
        assert_eq!(dof, 9);
        assert!(c < 5.0, "uniform ranks: χ² {c}");
        // A posterior biased high puts the truth at low ranks.
        let skewed = ParamRanks { name: "s".into(), ranks: (0..1000).map(|i| (i % 101) / 2).collect() };
        assert!(skewed.chi2(100, 10).0 > 100.0);
    }
}
