//! Standard simulation-based-inference benchmark tasks (Lueckmann et al. 2021,
//! "Benchmarking Simulation-Based Inference", arXiv:2101.04653), each a uniform prior
//! box, a simulator and exact-or-MCMC reference posterior draws for an observation.
//!
//! Reference posteriors: analytic for the Gaussian tasks (truncated normals), exact
//! sampling by inverting the simulator's noise for two moons, Metropolis chains
//! started from a likelihood-weighted resample of the prior for SLCP, and Langevin
//! chains around the Laplace approximation for the Bernoulli GLM ([`super::glm`]).

use super::glm;
use crate::npe::{Param, Scale};
use rand::Rng;
use rand_chacha::ChaCha8Rng;
use rand_distr::{Distribution, StandardNormal};
use std::f64::consts::{FRAC_1_SQRT_2, PI};

/// A benchmark task of the SBI benchmark suite (Lueckmann et al. 2021).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Task {
    /// 2-D, crescent-shaped bimodal posterior.
    TwoMoons,
    /// 10-D, x ~ N(θ, 0.1 I), θ uniform on [−1, 1]¹⁰.
    GaussianLinearUniform,
    /// 5-D, four draws of a 2-D Gaussian whose mean and covariance are set by θ
    /// ("simple likelihood, complex posterior"): four symmetric modes.
    Slcp,
    /// 2-D, x ~ ½ N(θ, I) + ½ N(θ, 0.01 I), θ uniform on [−10, 10]².
    GaussianMixture,
    /// 10-D, a bias and a 9-tap filter with a Gaussian smoothness prior; 100 Bernoulli
    /// trials through a logistic link, observed through their 10-D sufficient statistic.
    BernoulliGlm,
}

/// Every task, in the order they are reported.
pub const ALL: [Task; 5] =
    [Task::TwoMoons, Task::GaussianLinearUniform, Task::Slcp, Task::GaussianMixture, Task::BernoulliGlm];

pub(super) fn normal(rng: &mut ChaCha8Rng) -> f64 {
    StandardNormal.sample(rng)
}

impl Task {
    /// The task's name, as the benchmark and `--task` spell it.
    pub fn name(self) -> &'static str {
        match self {
            Task::TwoMoons => "two_moons",
            Task::GaussianLinearUniform => "gaussian_linear_uniform",
            Task::Slcp => "slcp",
            Task::GaussianMixture => "gaussian_mixture",
            Task::BernoulliGlm => "bernoulli_glm",
        }
    }

    /// The task named `s`, if any.
    pub fn from_name(s: &str) -> Option<Task> {
        ALL.into_iter().find(|t| t.name() == s)
    }

    /// Dimension of θ.
    pub fn dim(self) -> usize {
        match self {
            Task::TwoMoons | Task::GaussianMixture => 2,
            Task::GaussianLinearUniform => 10,
            Task::Slcp => 5,
            Task::BernoulliGlm => glm::DIM,
        }
    }

    /// The prior box's half-width in dimension k (the box is centred on 0).
    fn half_width(self, k: usize) -> f64 {
        match self {
            Task::TwoMoons | Task::GaussianLinearUniform => 1.0,
            Task::Slcp => 3.0,
            Task::GaussianMixture => 10.0,
            Task::BernoulliGlm => glm::glm().half_width[k],
        }
    }

    /// θ's parameters: `theta0`, `theta1`, … on the prior box, linear scale.
    pub fn params(self) -> Vec<Param> {
        (0..self.dim())
            .map(|k| {
                let b = self.half_width(k);
                Param { name: format!("theta{k}"), unit: String::new(), scale: Scale::Linear, low: -b, high: b }
            })
            .collect()
    }

    /// Dimension of x.
    pub fn features(self) -> usize {
        match self {
            Task::TwoMoons | Task::GaussianMixture => 2,
            Task::GaussianLinearUniform | Task::BernoulliGlm => 10,
            Task::Slcp => 8,
        }
    }

    /// A prior draw: uniform in the box, except the GLM's Gaussian (restricted to its box).
    pub fn prior(self, rng: &mut ChaCha8Rng) -> Vec<f64> {
        if self == Task::BernoulliGlm {
            return glm::glm().prior(rng);
        }
        (0..self.dim())
            .map(|k| {
                let b = self.half_width(k);
                rng.random_range(-b..b)
            })
            .collect()
    }

    fn in_prior(self, theta: &[f64]) -> bool {
        theta.iter().enumerate().all(|(k, v)| v.abs() <= self.half_width(k))
    }

    /// A draw of x given θ.
    pub fn simulate(self, theta: &[f64], rng: &mut ChaCha8Rng) -> Vec<f64> {
        match self {
            Task::TwoMoons => {
                let p = moon_noise(rng);
                let z0 = (theta[0] + theta[1]) * FRAC_1_SQRT_2;
                let z1 = (theta[1] - theta[0]) * FRAC_1_SQRT_2;
                vec![p[0] - z0.abs(), p[1] + z1]
            }
            Task::GaussianLinearUniform => theta.iter().map(|t| t + 0.1f64.sqrt() * normal(rng)).collect(),
            Task::Slcp => {
                let (m, l) = slcp_mean_chol(theta);
                (0..4)
                    .flat_map(|_| {
                        let (e0, e1) = (normal(rng), normal(rng));
                        [m[0] + l[0] * e0, m[1] + l[1] * e0 + l[2] * e1]
                    })
                    .collect()
            }
            Task::GaussianMixture => {
                let s = if rng.random::<bool>() { 1.0 } else { 0.1 };
                theta.iter().map(|t| t + s * normal(rng)).collect()
            }
            Task::BernoulliGlm => glm::glm().simulate(theta, rng),
        }
    }

    /// `n` draws from the posterior p(θ | x) (deterministic for the generator).
    pub fn reference(self, x: &[f64], n: usize, rng: &mut ChaCha8Rng) -> Vec<Vec<f64>> {
        match self {
            Task::TwoMoons => {
                let mut out = Vec::with_capacity(n);
                while out.len() < n {
                    // x = p + (−|z0|, z1): invert for z given a draw of p, either sign of z0.
                    let p = moon_noise(rng);
                    let (q0, z1) = (x[0] - p[0], x[1] - p[1]);
                    if q0 > 0.0 {
                        continue;
                    }
                    let z0 = if rng.random::<bool>() { -q0 } else { q0 };
                    let theta = vec![(z0 - z1) * FRAC_1_SQRT_2, (z0 + z1) * FRAC_1_SQRT_2];
                    if self.in_prior(&theta) {
                        out.push(theta);
                    }
                }
                out
            }
            Task::GaussianLinearUniform => {
                (0..n).map(|_| x.iter().map(|&m| truncated_normal(m, 0.1f64.sqrt(), 1.0, rng)).collect()).collect()
            }
            Task::GaussianMixture => {
                // Each component's weight: ½ × its normal's mass inside the box.
                let mass = |s: f64| x.iter().map(|&m| phi((10.0 - m) / s) - phi((-10.0 - m) / s)).product::<f64>();
                let (w1, w2) = (mass(1.0), mass(0.1));
                (0..n)
                    .map(|_| {
                        let s = if rng.random::<f64>() * (w1 + w2) < w1 { 1.0 } else { 0.1 };
                        x.iter().map(|&m| truncated_normal(m, s, 10.0, rng)).collect()
                    })
                    .collect()
            }
            Task::Slcp => slcp_reference(x, n, rng),
            Task::BernoulliGlm => glm::glm().reference(x, n, rng),
        }
    }
}

impl Task {
    /// log p(θ | x) of the tasks whose posterior density is known in closed form (the two
    /// Gaussian tasks: products and mixtures of truncated normals, as their reference
    /// draws); `None` for the others. With the flow's log q on reference draws it gives
    /// KL(p ‖ q) = E_p[log p − log q], a fit error that does not need a classifier.
    pub fn log_posterior(self, x: &[f64], theta: &[f64]) -> Option<f64> {
        let ln_norm = |z: f64, s: f64| -0.5 * z * z - s.ln() - 0.5 * (2.0 * PI).ln();
        match self {
            Task::GaussianLinearUniform => {
                let s = 0.1f64.sqrt();
                Some(
                    x.iter()
                        .zip(theta)
                        .map(|(&m, &t)| ln_norm((t - m) / s, s) - (phi((1.0 - m) / s) - phi((-1.0 - m) / s)).ln())
                        .sum(),
                )
            }
            Task::GaussianMixture => {
                let mass = |s: f64| x.iter().map(|&m| phi((10.0 - m) / s) - phi((-10.0 - m) / s)).product::<f64>();
                let comp = |s: f64| x.iter().zip(theta).map(|(&m, &t)| ln_norm((t - m) / s, s)).sum::<f64>();
                let (a, b) = (comp(1.0), comp(0.1));
                let top = a.max(b);
                Some(top + ((a - top).exp() + (b - top).exp()).ln() - (mass(1.0) + mass(0.1)).ln())
            }
            _ => None,
        }
    }
}

/// Two moons' noise: radius N(0.1, 0.01²) at an angle uniform on (−π/2, π/2), shifted by 0.25.
fn moon_noise(rng: &mut ChaCha8Rng) -> [f64; 2] {
    let a = rng.random_range(-PI / 2.0..PI / 2.0);
    let r = 0.1 + 0.01 * normal(rng);
    [r * a.cos() + 0.25, r * a.sin()]
}

/// N(m, s²) restricted to [−b, b] by rejection (m lies near the box).
fn truncated_normal(m: f64, s: f64, b: f64, rng: &mut ChaCha8Rng) -> f64 {
    loop {
        let v = m + s * normal(rng);
        if v.abs() <= b {
            return v;
        }
    }
}

/// Standard normal CDF via erfc (Numerical Recipes' Chebyshev fit, |error| < 1.2e-7).
pub fn phi(z: f64) -> f64 {
    let x = -z * FRAC_1_SQRT_2;
    let t = 1.0 / (1.0 + 0.5 * x.abs());
    let poly = -x * x - 1.265_512_23
        + t * (1.000_023_68
            + t * (0.374_091_96
                + t * (0.096_784_18
                    + t * (-0.186_288_06
                        + t * (0.278_868_07
                            + t * (-1.135_203_98 + t * (1.488_515_87 + t * (-0.822_152_23 + t * 0.170_872_77))))))));
    let erfc = t * poly.exp();
    0.5 * if x >= 0.0 { erfc } else { 2.0 - erfc }
}

/// SLCP's mean and the Cholesky factor (l00, l10, l11) of its covariance.
fn slcp_mean_chol(theta: &[f64]) -> ([f64; 2], [f64; 3]) {
    let (s1, s2, rho) = (theta[2] * theta[2], theta[3] * theta[3], theta[4].tanh());
    ([theta[0], theta[1]], [s1, rho * s2, s2 * (1.0 - rho * rho).sqrt()])
}

fn slcp_log_lik(theta: &[f64], x: &[f64]) -> f64 {
    let (m, l) = slcp_mean_chol(theta);
    if l[0] <= 0.0 || l[2] <= 0.0 {
        return f64::NEG_INFINITY;
    }
    let mut ll = -4.0 * ((l[0] * l[2]).ln() + (2.0 * PI).ln());
    for p in x.chunks_exact(2) {
        let e0 = (p[0] - m[0]) / l[0];
        let e1 = (p[1] - m[1] - l[1] * e0) / l[2];
        ll -= 0.5 * (e0 * e0 + e1 * e1);
    }
    ll
}

/// SLCP reference: the likelihood is unchanged by the signs of θ2 and θ3, so chains start
/// with both non-negative and each draw gets random signs (an exact move of the target).
/// 100 random-walk Metropolis chains start from a likelihood-weighted resample of
/// 200,000 prior draws, with a proposal covariance from that resample; 1,000 steps of
/// burn-in, then one draw every 10 steps.
fn slcp_reference(x: &[f64], n: usize, rng: &mut ChaCha8Rng) -> Vec<Vec<f64>> {
    let fold = |mut t: Vec<f64>| {
        t[2] = t[2].abs();
        t[3] = t[3].abs();
        t
    };
    let pool: Vec<Vec<f64>> = (0..200_000).map(|_| fold(Task::Slcp.prior(rng))).collect();
    let ll: Vec<f64> = pool.iter().map(|t| slcp_log_lik(t, x)).collect();
    let top = ll.iter().copied().fold(f64::NEG_INFINITY, f64::max);
    let w: Vec<f64> = ll.iter().map(|l| (l - top).exp()).collect();
    let total: f64 = w.iter().sum();
    let pick = |rng: &mut ChaCha8Rng| {
        let mut u = rng.random::<f64>() * total;
        for (i, wi) in w.iter().enumerate() {
            u -= wi;
            if u <= 0.0 {
                return i;
            }
        }
        w.len() - 1
    };
    let l = slcp_proposal(&pool, &w, total);
    let chains = 100;
    let per_chain = n.div_ceil(chains);
    let mut out = Vec::with_capacity(chains * per_chain);
    for _ in 0..chains {
        let start = pool[pick(rng)].clone();
        slcp_chain(start, x, &l, per_chain, rng, &mut out);
    }
    out.truncate(n);
    out
}

/// The random walk's proposal: the Cholesky factor of the pool's weighted covariance
/// scaled by 2.38²/d, then halved (the resample is wider than the posterior's modes).
fn slcp_proposal(pool: &[Vec<f64>], w: &[f64], total: f64) -> [[f64; 5]; 5] {
    let d = 5;
    let mut mean = [0.0; 5];
    for (t, wi) in pool.iter().zip(w) {
        for k in 0..d {
            mean[k] += wi * t[k] / total;
        }
    }
    let mut cov = [[0.0; 5]; 5];
    for (t, wi) in pool.iter().zip(w) {
        for i in 0..d {
            for j in 0..d {
                cov[i][j] += wi * (t[i] - mean[i]) * (t[j] - mean[j]) / total;
            }
        }
    }
    let scale = 2.38 * 2.38 / d as f64 * 0.5;
    let mut l = [[0.0; 5]; 5];
    for i in 0..d {
        for j in 0..=i {
            let s: f64 = (0..j).map(|k| l[i][k] * l[j][k]).sum();
            if i == j {
                l[i][i] = (cov[i][i] * scale - s).max(1e-12).sqrt();
            } else {
                l[i][j] = (cov[i][j] * scale - s) / l[j][j];
            }
        }
    }
    l
}

/// One Metropolis chain from `start` with proposal factor `l`: 1,000 steps of burn-in,
/// then `per_chain` draws one every 10 steps, each with random signs of θ2 and θ3.
fn slcp_chain(
    mut cur: Vec<f64>,
    x: &[f64],
    l: &[[f64; 5]; 5],
    per_chain: usize,
    rng: &mut ChaCha8Rng,
    out: &mut Vec<Vec<f64>>,
) {
    let d = 5;
    let mut cur_ll = slcp_log_lik(&cur, x);
    let steps = 1000 + 10 * per_chain;
    for step in 1..=steps {
        let e: Vec<f64> = (0..d).map(|_| normal(rng)).collect();
        let prop: Vec<f64> = (0..d).map(|i| cur[i] + (0..=i).map(|k| l[i][k] * e[k]).sum::<f64>()).collect();
        if Task::Slcp.in_prior(&prop) {
            let pl = slcp_log_lik(&prop, x);
            if (pl - cur_ll).is_finite() && rng.random::<f64>().ln() < pl - cur_ll {
                cur = prop;
                cur_ll = pl;
            }
        }
        if step > 1000 && (step - 1000) % 10 == 0 {
            let mut t = cur.clone();
            for k in [2, 3] {
                if rng.random::<bool>() {
                    t[k] = -t[k];
                }
            }
            out.push(t);
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::SeedableRng;

    #[test]
    fn normal_cdf_matches_known_values() {
        for (z, p) in [(0.0, 0.5), (1.0, 0.841_344_746), (-1.96, 0.024_997_895), (3.0, 0.998_650_102)] {
            assert!((phi(z) - p).abs() < 2e-7, "Φ({z}) = {} vs {p}", phi(z));
        }
    }

    /// The closed-form posteriors integrate to 1 over the box, near a bound too (where
    /// the truncation matters): the 10-D Gaussian's through its one-dimensional factor
    /// (x with equal coordinates, θ along the diagonal), the mixture on a 2-D grid.
    #[test]
    fn closed_form_posteriors_integrate_to_one() {
        let grid = |lo: f64, hi: f64, n: usize| (0..n).map(move |i| lo + (hi - lo) * (i as f64 + 0.5) / n as f64);
        for m in [0.2, 0.9, 1.3] {
            let x = [m; 10];
            let f = |t: f64| (Task::GaussianLinearUniform.log_posterior(&x, &[t; 10]).unwrap() / 10.0).exp();
            let total: f64 = grid(-1.0, 1.0, 4000).map(f).sum::<f64>() * 2.0 / 4000.0;
            assert!((total - 1.0).abs() < 1e-4, "x = {m}: {total}");
        }
        let x = [9.5, -9.85];
        let n = 2000;
        let step = 20.0 / n as f64;
        let total: f64 = grid(-10.0, 10.0, n)
            .flat_map(|a| grid(-10.0, 10.0, n).map(move |b| [a, b]))
            .map(|t| Task::GaussianMixture.log_posterior(&x, &t).unwrap().exp())
            .sum::<f64>()
            * step
            * step;
        assert!((total - 1.0).abs() < 1e-3, "mixture: {total}");
        assert!(Task::Slcp.log_posterior(&[0.0; 8], &[0.0; 5]).is_none());
    }

    /// Two moons' reference draws reproduce the observation when pushed back through
    /// the noiseless part of the simulator: |x − g(θ) − (0.25, 0)| ≈ radius 0.1.
    #[test]
    fn two_moons_reference_lies_on_the_crescent() {
        let mut rng = ChaCha8Rng::seed_from_u64(1);
        let x = Task::TwoMoons.simulate(&[0.3, -0.2], &mut rng);
        for t in Task::TwoMoons.reference(&x, 500, &mut rng) {
            let z0 = (t[0] + t[1]) * FRAC_1_SQRT_2;
            let z1 = (t[1] - t[0]) * FRAC_1_SQRT_2;
            let p = [x[0] + z0.abs() - 0.25, x[1] - z1];
            let r = p[0].hypot(p[1]);
            assert!((r - 0.1).abs() < 0.06 && p[0] >= -1e-12, "radius {r}");
        }
    }
}
