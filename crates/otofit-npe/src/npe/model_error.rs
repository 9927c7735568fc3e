//! A model-error term: a smooth random discrepancy between the simulator and a real ear,
//! added to the training inputs beside the measurement noise, so that the flow learns the
//! posterior of an approximate simulator (Kennedy & O'Hagan 2001's discrepancy term,
//! marginalised by simulation rather than inferred).
//!
//! Per measure (a block of consecutive features on the frequency grid) the discrepancy is a
//! zero-mean Gaussian process in log₂ frequency with a squared-exponential kernel of
//! correlation length `octaves`, its standard deviation `scale` times the feature's 1×
//! noise: a shifted resonance or a mis-sized compliance moves neighbouring frequencies
//! together, which independent noise cannot mimic. Measures are drawn independently.

use super::{NpeError, Result};
use crate::spd;
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use rand_distr::{Distribution, StandardNormal};
use serde::{Deserialize, Serialize};

/// Largest scale accepted (in noise standard deviations): beyond it the data say nothing.
pub const MAX_SCALE: f64 = 50.0;

/// The size and smoothness of the discrepancy a model was trained with.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct ModelError {
    /// Standard deviation per feature, in multiples of the feature's 1× noise.
    pub scale: f64,
    /// Correlation length across frequency, octaves.
    pub octaves: f64,
    /// Each row's size drawn uniformly from [0, `scale`] instead of `scale` itself: ears
    /// the simulator makes well and ears it makes badly both in the training, so the
    /// flow can stay sharp where the data show no discrepancy.
    #[serde(default)]
    pub varying: bool,
}

impl ModelError {
    /// Refuses sizes that cannot be drawn, naming the setting.
    pub fn check(&self) -> Result<()> {
        if !(self.scale.is_finite() && (0.0..=MAX_SCALE).contains(&self.scale)) {
            return Err(NpeError::settings(
                "model-error",
                format!("--model-error must be 0..={MAX_SCALE} (got {})", self.scale),
            ));
        }
        if !(self.octaves.is_finite() && self.octaves > 0.01 && self.octaves <= 10.0) {
            let why = format!("--model-error-octaves must be in (0.01, 10] (got {})", self.octaves);
            return Err(NpeError::settings("model-error-octaves", why));
        }
        Ok(())
    }

    /// The sampler for a feature layout: `frequencies_hz` the grid, `noise_std` the 1×
    /// noise per feature, features in blocks of one measure each over the grid.
    pub fn sampler(&self, frequencies_hz: &[f64], noise_std: &[f64]) -> Result<Discrepancy> {
        self.check()?;
        let n = frequencies_hz.len();
        if n == 0 || noise_std.is_empty() || !noise_std.len().is_multiple_of(n) {
            let why = "--model-error needs a frequency grid (meta.json frequencies_hz) that divides the features";
            return Err(NpeError::settings("model-error", why));
        }
        if frequencies_hz.iter().any(|f| !(f.is_finite() && *f > 0.0)) {
            return Err(NpeError::settings("model-error", "--model-error needs a frequency grid finite and > 0"));
        }
        let l2: Vec<f64> = frequencies_hz.iter().map(|f| f.log2()).collect();
        // A small nugget keeps the factorisation defined on dense grids (the kernel's
        // matrix is numerically singular); 1e-6 of the variance changes nothing drawn.
        let k: Vec<Vec<f64>> = (0..n)
            .map(|i| {
                (0..n)
                    .map(|j| {
                        let d = (l2[i] - l2[j]) / self.octaves;
                        (-0.5 * d * d).exp() + if i == j { 1e-6 } else { 0.0 }
                    })
                    .collect()
            })
            .collect();
        let chol = spd::cholesky(&k).ok_or_else(|| {
            NpeError::settings("model-error", "--model-error's kernel cannot be factorised on this grid")
        })?;
        let sd = noise_std.iter().map(|s| self.scale * s).collect();
        Ok(Discrepancy { chol, sd, varying: self.varying })
    }

    /// The variance of the term relative to `scale`² (1, or 1/3 when varying: E[u²] for
    /// u uniform on [0, 1]).
    pub fn variance_share(&self) -> f64 {
        if self.varying { 1.0 / 3.0 } else { 1.0 }
    }
}

/// Draws the discrepancy for one feature layout.
#[derive(Clone, Debug)]
pub struct Discrepancy {
    /// Lower Cholesky factor of the kernel on the grid.
    chol: Vec<Vec<f64>>,
    /// Standard deviation per feature.
    sd: Vec<f64>,
    /// A size per row (see [`ModelError::varying`]).
    varying: bool,
}

impl Discrepancy {
    /// Features the sampler draws for.
    pub fn features(&self) -> usize {
        self.sd.len()
    }

    /// Adds one draw to `x` (one row of features).
    pub fn add<R: Rng>(&self, x: &mut [f64], rng: &mut R) {
        let n = self.chol.len();
        let mut z = vec![0.0; n];
        let size = if self.varying { rng.random::<f64>() } else { 1.0 };
        for (block, sd) in x.chunks_mut(n).zip(self.sd.chunks(n)) {
            z.iter_mut().for_each(|v| *v = StandardNormal.sample(rng));
            for (i, (x, s)) in block.iter_mut().zip(sd).enumerate() {
                let d: f64 = self.chol[i][..=i].iter().zip(&z).map(|(l, z)| l * z).sum();
                *x += size * s * d;
            }
        }
    }

    /// Adds row `row`'s draw of stream `seed` (reproducible in any order, apart from
    /// every other random stream of the project by its own seed mixing).
    pub fn add_for_row(&self, x: &mut [f64], seed: u64, row: usize) {
        let mut rng = ChaCha8Rng::seed_from_u64(seed ^ 0x6D0D_E1E2_2024_0001);
        rng.set_stream(row as u64);
        self.add(x, &mut rng);
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn grid(n: usize) -> Vec<f64> {
        (0..n).map(|i| 200.0 * 40f64.powf(i as f64 / (n - 1) as f64)).collect()
    }

    /// The draws' covariance is scale² · σᵢσⱼ · exp(−Δ²/2ℓ²) within a measure and zero
    /// between measures: the discrepancy the training claims to add.
    #[test]
    fn draws_have_the_stated_covariance() {
        let f = grid(12);
        let noise: Vec<f64> = (0..24).map(|k| 0.05 + 0.01 * (k % 12) as f64).collect();
        let me = ModelError { scale: 2.0, octaves: 1.0, varying: false };
        let d = me.sampler(&f, &noise).unwrap();
        let reps = 40_000;
        let mut rng = ChaCha8Rng::seed_from_u64(3);
        let mut sum = vec![vec![0.0; 24]; 24];
        for _ in 0..reps {
            let mut x = vec![0.0; 24];
            d.add(&mut x, &mut rng);
            for i in 0..24 {
                for j in 0..24 {
                    sum[i][j] += x[i] * x[j];
                }
            }
        }
        for i in 0..24 {
            for j in 0..24 {
                let c = sum[i][j] / reps as f64;
                let want = if i / 12 == j / 12 {
                    let dl = (f[i % 12].log2() - f[j % 12].log2()) / me.octaves;
                    me.scale * me.scale * noise[i] * noise[j] * (-0.5 * dl * dl).exp()
                } else {
                    0.0
                };
                let tol = 0.04 * me.scale * me.scale * noise[i] * noise[j];
                assert!((c - want).abs() < tol, "cov[{i}][{j}] {c:.5} against {want:.5}");
            }
        }
    }

    /// With a size per row the variance is a third (E[u²], u uniform on [0, 1]) and the
    /// draws are no longer Gaussian: their kurtosis is E[u⁴]/E[u²]² · 3 = 27/5.
    #[test]
    fn a_varying_size_has_a_third_of_the_variance_and_heavy_tails() {
        let me = ModelError { scale: 3.0, octaves: 1.0, varying: true };
        assert!((me.variance_share() - 1.0 / 3.0).abs() < 1e-12);
        let d = me.sampler(&grid(4), &[0.1; 4]).unwrap();
        let mut rng = ChaCha8Rng::seed_from_u64(5);
        let (mut m2, mut m4, reps) = (0.0, 0.0, 200_000);
        for _ in 0..reps {
            let mut x = vec![0.0; 4];
            d.add(&mut x, &mut rng);
            m2 += x[0] * x[0];
            m4 += x[0].powi(4);
        }
        let (m2, m4) = (m2 / reps as f64, m4 / reps as f64);
        let want = 0.09 / 3.0;
        assert!((m2 / want - 1.0).abs() < 0.02, "variance {m2} against {want}");
        assert!((m4 / (m2 * m2) - 5.4).abs() < 0.3, "kurtosis {}", m4 / (m2 * m2));
    }

    #[test]
    fn a_row_draw_is_reproducible_and_rows_differ() {
        let d = ModelError { scale: 1.0, octaves: 0.5, varying: false }.sampler(&grid(8), &[0.1; 16]).unwrap();
        let draw = |row| {
            let mut x = vec![0.0; 16];
            d.add_for_row(&mut x, 9, row);
            x
        };
        assert_eq!(draw(4), draw(4));
        assert_ne!(draw(4), draw(5));
    }

    #[test]
    fn bad_sizes_and_layouts_are_refused_by_name() {
        let bad = |me: ModelError, f: &[f64], n: &[f64]| match me.sampler(f, n) {
            Err(NpeError::Settings { field, .. }) => field,
            other => panic!("accepted: {other:?}"),
        };
        let ok = ModelError { scale: 1.0, octaves: 1.0, varying: false };
        assert_eq!(bad(ModelError { scale: -1.0, ..ok }, &grid(8), &[0.1; 16]), "model-error");
        assert_eq!(bad(ModelError { scale: f64::NAN, ..ok }, &grid(8), &[0.1; 16]), "model-error");
        assert_eq!(bad(ModelError { octaves: 0.0, ..ok }, &grid(8), &[0.1; 16]), "model-error-octaves");
        assert_eq!(bad(ok, &grid(8), &[0.1; 15]), "model-error");
        assert_eq!(bad(ok, &[], &[0.1; 16]), "model-error");
    }
}
