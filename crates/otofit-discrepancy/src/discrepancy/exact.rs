//! The posterior under the model's own likelihood, sampled by Metropolis–Hastings.
//!
//! The simulator is deterministic and the training noise is Gaussian with a known
//! standard deviation per feature, so for an ear the model fits, the posterior is
//! p(θ | x) ∝ exp(−χ²(θ)/2)·prior(θ), computable to any accuracy by re-simulating. The
//! flow's posterior is calibrated but wide (docs/results/posterior.md); this samples the
//! likelihood's posterior instead ([`super::fitcheck::exact`]): [`CHAINS`] chains of the
//! same kernel as POST /infer's short chains ([`super::exact_fast`]: a random walk in the
//! flow's latent space, where the flow's map straightens the posterior's ridges), each a
//! quarter of the steps, from dispersed starts, run side by side. A single random walk
//! in the fit's own coordinates with the same number of steps, used before, left 4 of 10
//! chains unsettled on the default model's ears where these leave 1 (docs/results/
//! posterior.md, "What settles the long chain"), and one chain cannot see a mode it never
//! visited. It is exact only under the model: when the fit check fails, it is the
//! posterior of a model that does not describe the ear.

use serde::Serialize;

/// Most chain steps one call may take (one simulation each, all chains together).
pub const MAX_STEPS: usize = 200_000;

/// Fewest chain steps a user may ask for: the length whose calibration the 40-ear test
/// measures.
pub const MIN_STEPS: usize = 100_000;

/// Chains of one exact posterior; its draws are stored chain after chain, each chain's
/// the same number, so the draws cut into this many segments are the chains.
pub const CHAINS: usize = 4;

/// The chains' draws and how they went.
#[derive(Clone, Debug, Serialize)]
pub struct Chain {
    /// Draws after warm-up (natural units, design column order), every `thin`-th step of
    /// each chain, chain after chain (each chain's the same number).
    #[serde(skip)]
    pub samples: Vec<Vec<f64>>,
    /// Chains that ran (fewer than [`CHAINS`] when one found no start with a density).
    pub chains: usize,
    /// Accepted proposals over steps after warm-up, the mean over the chains.
    pub acceptance: f64,
    /// Steps after warm-up, all chains.
    pub steps: usize,
    /// Steps of warm-up (a quarter of each chain's, which sets the proposal), all chains.
    pub burn_in: usize,
    /// χ² of the best least-squares fit.
    pub chi2_start: f64,
    /// Median χ² over (up to 256 evenly spaced of) the draws: the best fit's plus about
    /// half the parameters the data pin down.
    pub chi2_median: f64,
}

/// Lower Cholesky factor (row-major, flat) of a symmetric positive definite d×d matrix.
pub(super) fn cholesky(a: &[f64], d: usize) -> Option<Vec<f64>> {
    otofit_npe::spd::cholesky(&rows(a, d)).map(|l| l.concat())
}

/// The inverse (row-major, flat) of a symmetric positive definite d×d matrix.
pub(super) fn spd_inverse(a: &[f64], d: usize) -> Option<Vec<f64>> {
    otofit_npe::spd::inverse(&rows(a, d)).map(|m| m.concat())
}

fn rows(a: &[f64], d: usize) -> Vec<Vec<f64>> {
    a.chunks(d.max(1)).map(<[f64]>::to_vec).collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn spd_inverse_inverts_and_refuses_an_indefinite_matrix() {
        let a = [4.0, 1.0, 0.5, 1.0, 3.0, 0.2, 0.5, 0.2, 2.0];
        let inv = spd_inverse(&a, 3).unwrap();
        for i in 0..3 {
            for j in 0..3 {
                let v: f64 = (0..3).map(|k| a[i * 3 + k] * inv[k * 3 + j]).sum();
                assert!((v - if i == j { 1.0 } else { 0.0 }).abs() < 1e-12, "({i},{j}) {v}");
            }
        }
        assert!(spd_inverse(&[1.0, 2.0, 2.0, 1.0], 2).is_none());
    }
}
