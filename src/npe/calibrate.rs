//! Calibration on held-out simulations: expected coverage of highest-density regions at
//! credible levels 0.05…0.95 (Hermans et al. 2022) and SBC ranks per parameter (Talts
//! et al. 2018).

use super::{Npe, Obs};
use anyhow::Result;
use serde::Serialize;

#[derive(Clone, Debug, Serialize)]
pub struct Calibration {
    pub rows: usize,
    pub samples_per_row: usize,
    pub levels: Vec<f64>,
    /// Fraction of rows whose true θ lies inside the level's highest-density region.
    pub coverage: Vec<f64>,
    /// Per parameter: rank of the true value among the samples (0..=samples) per row.
    pub sbc_ranks: Vec<ParamRanks>,
    /// Per parameter: fraction of rows with the truth inside the central 90 % interval.
    pub marginal_coverage90: Vec<f64>,
}

#[derive(Clone, Debug, Serialize)]
pub struct ParamRanks {
    pub name: String,
    pub ranks: Vec<usize>,
}

/// `rows`: (θ, x) pairs not used in training.
pub fn calibrate(npe: &Npe, rows: &[(Vec<f64>, Vec<f64>)], samples: usize, seed: u64) -> Result<Calibration> {
    let levels: Vec<f64> = (1..=19).map(|i| i as f64 * 0.05).collect();
    let d = npe.params().len();
    let mut inside = vec![0usize; levels.len()];
    let mut ranks = vec![Vec::with_capacity(rows.len()); d];
    let mut marginal = vec![0usize; d];
    for (r, (theta, x)) in rows.iter().enumerate() {
        let obs = Obs { x, present: None };
        let draws = npe.sample(&obs, samples, seed.wrapping_add(r as u64))?;
        let lp = npe.log_prob(&obs, &draws)?;
        let lp_true = npe.log_prob(&obs, std::slice::from_ref(theta))?[0];
        // θ lies in the α-HPD region iff fewer than α of the draws are denser than it.
        let denser = lp.iter().filter(|&&l| l > lp_true).count() as f64 / samples as f64;
        for (k, &a) in levels.iter().enumerate() {
            if denser < a {
                inside[k] += 1;
            }
        }
        for k in 0..d {
            let mut v: Vec<f64> = draws.iter().map(|s| s[k]).collect();
            ranks[k].push(v.iter().filter(|&&s| s < theta[k]).count());
            v.sort_by(f64::total_cmp);
            let (lo, hi) = (v[(0.05 * (samples - 1) as f64) as usize], v[(0.95 * (samples - 1) as f64) as usize]);
            if theta[k] >= lo && theta[k] <= hi {
                marginal[k] += 1;
            }
        }
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
