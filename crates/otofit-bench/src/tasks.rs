//! Standard simulation-based-inference benchmark tasks (Lueckmann et al. 2021,
//! "Benchmarking Simulation-Based Inference", arXiv:2101.04653), each a prior on a
//! box, a simulator and exact-or-MCMC reference posterior draws for an observation.
//!
//! Reference posteriors: analytic for the Gaussian tasks (truncated normals), exact
//! sampling by inverting the simulator's noise for two moons, Metropolis chains
//! started from a likelihood-weighted resample of the prior for SLCP, and Langevin
//! chains around the Laplace approximation for the Bernoulli GLM ([`super::glm`]).
//!
//! The last three tasks ([`CONFIRMATION`]) are variants of earlier ones with the same or
//! a known posterior: a Gaussian prior instead of a uniform one, 92 uninformative
//! distractors beside SLCP's data, and the GLM's raw outcomes instead of its sufficient
//! statistic. A training recipe chosen on the first five can be checked on them.

use super::glm;
use crate::npe::{Param, Scale};
use rand::seq::SliceRandom;
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use rand_distr::{Distribution, Exp1, StandardNormal};
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
    /// 10-D, x ~ N(θ, 0.1 I), θ ~ N(0, 0.1 I) (the benchmark's T.1 `gaussian_linear`),
    /// restricted to ±6 prior standard deviations; posterior N(x/2, 0.05 I).
    GaussianLinear,
    /// SLCP's θ and 8 data values among 92 distractors that do not depend on θ, the 100
    /// columns in a fixed shuffled order (the benchmark's T.4 `slcp_distractors`).
    SlcpDistractors,
    /// The Bernoulli GLM observed through its 100 raw 0/1 outcomes (the benchmark's T.6
    /// `bernoulli_glm_raw`); the same posterior, since the statistic is sufficient.
    BernoulliGlmRaw,
}

/// Every task, in the order they are reported.
pub const ALL: [Task; 8] = [
    Task::TwoMoons,
    Task::GaussianLinearUniform,
    Task::Slcp,
    Task::GaussianMixture,
    Task::BernoulliGlm,
    Task::GaussianLinear,
    Task::SlcpDistractors,
    Task::BernoulliGlmRaw,
];

/// The tasks no recipe was chosen on, to confirm one on (the last three of [`ALL`]).
pub const CONFIRMATION: [Task; 3] = [Task::GaussianLinear, Task::SlcpDistractors, Task::BernoulliGlmRaw];

/// The prior and noise variance of `gaussian_linear` (sbibm's `prior_scale` and
/// `simulator_scale`, both used as covariances 0.1 I).
const LINEAR_VAR: f64 = 0.1;

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
            Task::GaussianLinear => "gaussian_linear",
            Task::SlcpDistractors => "slcp_distractors",
            Task::BernoulliGlmRaw => "bernoulli_glm_raw",
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
            Task::GaussianLinearUniform | Task::GaussianLinear => 10,
            Task::Slcp | Task::SlcpDistractors => 5,
            Task::BernoulliGlm | Task::BernoulliGlmRaw => glm::DIM,
        }
    }

    /// The prior box's half-width in dimension k (the box is centred on 0). The Gaussian
    /// priors are cut at ±[`glm::BOX_SDS`] prior standard deviations (mass outside < 2·10⁻⁸).
    fn half_width(self, k: usize) -> f64 {
        match self {
            Task::TwoMoons | Task::GaussianLinearUniform => 1.0,
            Task::Slcp | Task::SlcpDistractors => 3.0,
            Task::GaussianMixture => 10.0,
            Task::BernoulliGlm | Task::BernoulliGlmRaw => glm::glm().half_width[k],
            Task::GaussianLinear => glm::BOX_SDS * LINEAR_VAR.sqrt(),
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
            Task::GaussianLinearUniform | Task::BernoulliGlm | Task::GaussianLinear => 10,
            Task::Slcp => 8,
            Task::SlcpDistractors => DISTRACTED,
            Task::BernoulliGlmRaw => glm::BINS,
        }
    }

    /// A prior draw: uniform in the box, except the Gaussians of the GLM and
    /// `gaussian_linear` (restricted to their boxes).
    pub fn prior(self, rng: &mut ChaCha8Rng) -> Vec<f64> {
        match self {
            Task::BernoulliGlm | Task::BernoulliGlmRaw => return glm::glm().prior(rng),
            Task::GaussianLinear => {
                let b = self.half_width(0);
                return (0..self.dim()).map(|_| truncated_normal(0.0, LINEAR_VAR.sqrt(), b, rng)).collect();
            }
            _ => {}
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
            Task::GaussianLinearUniform | Task::GaussianLinear => {
                theta.iter().map(|t| t + LINEAR_VAR.sqrt() * normal(rng)).collect()
            }
            Task::Slcp => slcp_simulate(theta, rng),
            Task::SlcpDistractors => distractors().simulate(theta, rng),
            Task::GaussianMixture => {
                let s = if rng.random::<bool>() { 1.0 } else { 0.1 };
                theta.iter().map(|t| t + s * normal(rng)).collect()
            }
            Task::BernoulliGlm => glm::glm().simulate(theta, rng),
            Task::BernoulliGlmRaw => glm::glm().simulate_raw(theta, rng),
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
            Task::GaussianLinearUniform | Task::GaussianLinear => {
                let ((m, s), b) = (self.linear_posterior(x), self.half_width(0));
                (0..n).map(|_| m.iter().map(|&m| truncated_normal(m, s, b, rng)).collect()).collect()
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
            Task::SlcpDistractors => slcp_reference(&distractors().informative(x), n, rng),
            Task::BernoulliGlm => glm::glm().reference(x, n, rng),
            Task::BernoulliGlmRaw => glm::glm().reference(&glm::glm().statistic(x), n, rng),
        }
    }

    /// The two Gaussian linear tasks' unrestricted posterior: its mean per dimension and
    /// its standard deviation. With the uniform prior the likelihood, N(x, 0.1 I); with
    /// the N(0, 0.1 I) prior the product of two equal Gaussians, N(x/2, 0.05 I).
    fn linear_posterior(self, x: &[f64]) -> (Vec<f64>, f64) {
        if self == Task::GaussianLinear {
            (x.iter().map(|v| v / 2.0).collect(), (LINEAR_VAR / 2.0).sqrt())
        } else {
            (x.to_vec(), LINEAR_VAR.sqrt())
        }
    }
}

impl Task {
    /// log p(θ | x) of the tasks whose posterior density is known in closed form (the
    /// Gaussian tasks: products and mixtures of truncated normals, as their reference
    /// draws); `None` for the others. With the flow's log q on reference draws it gives
    /// KL(p ‖ q) = E_p[log p − log q], a fit error that does not need a classifier.
    pub fn log_posterior(self, x: &[f64], theta: &[f64]) -> Option<f64> {
        let ln_norm = |z: f64, s: f64| -0.5 * z * z - s.ln() - 0.5 * (2.0 * PI).ln();
        match self {
            Task::GaussianLinearUniform | Task::GaussianLinear => {
                let ((mean, s), b) = (self.linear_posterior(x), self.half_width(0));
                Some(
                    mean.iter()
                        .zip(theta)
                        .map(|(&m, &t)| ln_norm((t - m) / s, s) - (phi((b - m) / s) - phi((-b - m) / s)).ln())
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

/// SLCP's data: four draws of a 2-D Gaussian set by θ, flattened to 8 values.
fn slcp_simulate(theta: &[f64], rng: &mut ChaCha8Rng) -> Vec<f64> {
    let (m, l) = slcp_mean_chol(theta);
    (0..4)
        .flat_map(|_| {
            let (e0, e1) = (normal(rng), normal(rng));
            [m[0] + l[0] * e0, m[1] + l[1] * e0 + l[2] * e1]
        })
        .collect()
}

/// `slcp_distractors`' x: SLCP's 8 values and 92 distractors.
const DISTRACTED: usize = 100;
/// Distractor values per simulation.
const NOISE_DIM: usize = DISTRACTED - 8;
/// Components of the distractors' mixture.
const NOISE_COMPONENTS: usize = 20;

/// `slcp_distractors`' fixed parts, as sbibm draws them (`_generate_noise_dist_parameters`)
/// but from ChaCha8 with seed 42 where sbibm uses numpy's seed 42, so the numbers differ:
/// the distractors follow an equal-weight mixture of 20 92-D Student-t distributions with
/// 2 degrees of freedom (heavy tails, no finite variance), each with location 15·N(0, I)
/// and scale factor 3·(L + diag(e^g)), L lower-triangular with N(0, 1) entries and g
/// N(0, 1); then the 100 columns (SLCP's 8 first) are shuffled by a fixed permutation.
struct Distractors {
    /// Each component's location.
    loc: Vec<Vec<f64>>,
    /// Each component's lower-triangular scale factor, row i holding columns 0..=i.
    scale: Vec<Vec<Vec<f64>>>,
    /// Column i of x is column `perm[i]` of (SLCP's data, distractors).
    perm: Vec<usize>,
    /// The column of x that holds SLCP's value j.
    informative: [usize; 8],
}

fn distractors() -> &'static Distractors {
    static D: std::sync::OnceLock<Distractors> = std::sync::OnceLock::new();
    D.get_or_init(|| {
        let mut rng = ChaCha8Rng::seed_from_u64(42);
        let loc = (0..NOISE_COMPONENTS).map(|_| (0..NOISE_DIM).map(|_| 15.0 * normal(&mut rng)).collect()).collect();
        let scale = (0..NOISE_COMPONENTS)
            .map(|_| {
                let mut l: Vec<Vec<f64>> =
                    (0..NOISE_DIM).map(|i| (0..=i).map(|_| 3.0 * normal(&mut rng)).collect()).collect();
                for (i, row) in l.iter_mut().enumerate() {
                    row[i] += 3.0 * normal(&mut rng).exp();
                }
                l
            })
            .collect();
        let mut perm: Vec<usize> = (0..DISTRACTED).collect();
        perm.shuffle(&mut rng);
        let informative = std::array::from_fn(|j| perm.iter().position(|&p| p == j).expect("a permutation"));
        Distractors { loc, scale, perm, informative }
    })
}

impl Distractors {
    /// SLCP's data for θ, then the distractors (drawn after, so SLCP's values are what
    /// [`Task::Slcp`] gives on the same generator), in the shuffled column order.
    fn simulate(&self, theta: &[f64], rng: &mut ChaCha8Rng) -> Vec<f64> {
        let mut v = slcp_simulate(theta, rng);
        let c = rng.random_range(0..NOISE_COMPONENTS);
        let z: Vec<f64> = (0..NOISE_DIM).map(|_| normal(rng)).collect();
        // A Student-t with ν = 2: a normal over √(χ²₂/2), and χ²₂/2 is a unit exponential.
        let e: f64 = Exp1.sample(rng);
        let w = 1.0 / e.sqrt();
        let (loc, l) = (&self.loc[c], &self.scale[c]);
        v.extend((0..NOISE_DIM).map(|i| loc[i] + w * l[i].iter().zip(&z).map(|(a, b)| a * b).sum::<f64>()));
        self.perm.iter().map(|&p| v[p]).collect()
    }

    /// SLCP's 8 values, picked out of x.
    fn informative(&self, x: &[f64]) -> Vec<f64> {
        self.informative.iter().map(|&i| x[i]).collect()
    }
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

    #[test]
    fn normal_cdf_matches_known_values() {
        for (z, p) in [(0.0, 0.5), (1.0, 0.841_344_746), (-1.96, 0.024_997_895), (3.0, 0.998_650_102)] {
            assert!((phi(z) - p).abs() < 2e-7, "Φ({z}) = {} vs {p}", phi(z));
        }
    }

    /// The closed-form posteriors integrate to 1 over the box, near a bound too (where
    /// the truncation matters): the 10-D Gaussians' through their one-dimensional factor
    /// (x with equal coordinates, θ along the diagonal), the mixture on a 2-D grid.
    #[test]
    fn closed_form_posteriors_integrate_to_one() {
        let grid = |lo: f64, hi: f64, n: usize| (0..n).map(move |i| lo + (hi - lo) * (i as f64 + 0.5) / n as f64);
        // The 10-D Gaussians' posterior means are x and x/2: near the bound at 0.9 and 1.3
        // (box ±1), and at 0.9 and 1.5 (box ±1.9, posterior σ 0.22).
        for (task, xs) in [(Task::GaussianLinearUniform, [0.2, 0.9, 1.3]), (Task::GaussianLinear, [0.4, 1.8, 3.0])] {
            let b = task.half_width(0);
            for m in xs {
                let x = [m; 10];
                let f = |t: f64| (task.log_posterior(&x, &[t; 10]).unwrap() / 10.0).exp();
                let total: f64 = grid(-b, b, 4000).map(f).sum::<f64>() * 2.0 * b / 4000.0;
                assert!((total - 1.0).abs() < 1e-4, "{}, x = {m}: {total}", task.name());
            }
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

    /// Every task: its name finds it, its prior draws lie in its box and have its
    /// dimension, its simulations have its feature count.
    #[test]
    fn every_task_is_consistent_with_its_name_box_and_sizes() {
        let mut rng = ChaCha8Rng::seed_from_u64(4);
        for task in ALL {
            assert_eq!(Task::from_name(task.name()), Some(task));
            assert_eq!(task.params().len(), task.dim());
            let theta = task.prior(&mut rng);
            assert!(theta.len() == task.dim() && task.in_prior(&theta), "{}", task.name());
            assert_eq!(task.simulate(&theta, &mut rng).len(), task.features(), "{}", task.name());
        }
        assert_eq!(ALL[ALL.len() - CONFIRMATION.len()..], CONFIRMATION);
    }

    /// `gaussian_linear`'s reference draws have the analytic posterior's mean x/2 and
    /// variance 0.05 per dimension (within 4.5 standard errors of 20,000 draws).
    #[test]
    fn gaussian_linear_reference_has_the_analytic_moments() {
        let task = Task::GaussianLinear;
        let mut rng = ChaCha8Rng::seed_from_u64(11);
        let x = task.simulate(&task.prior(&mut rng), &mut rng);
        let n = 20_000;
        let draws = task.reference(&x, n, &mut rng);
        for (k, &xk) in x.iter().enumerate() {
            let (mean, sd) = crate::stats::mean_std_population(&draws.iter().map(|t| t[k]).collect::<Vec<_>>());
            let se_mean = (0.05 / n as f64).sqrt();
            let se_var = 0.05 * (2.0 / n as f64).sqrt();
            assert!((mean - xk / 2.0).abs() < 4.5 * se_mean, "θ{k}: mean {mean} vs {}", xk / 2.0);
            assert!((sd * sd - 0.05).abs() < 4.5 * se_var, "θ{k}: variance {}", sd * sd);
        }
    }

    /// `slcp_distractors`: SLCP's columns, picked back out through the permutation, are
    /// what SLCP's simulator gives for the same θ and generator; the other 92 columns are
    /// the same for another θ; the reference is SLCP's at the picked-out columns.
    #[test]
    fn slcp_distractors_hide_slcp_data_among_columns_free_of_theta() {
        let d = distractors();
        let mut sorted = d.perm.clone();
        sorted.sort_unstable();
        assert_eq!(sorted, (0..DISTRACTED).collect::<Vec<_>>());
        let (a, b) = ([0.7, -1.2, 0.9, -0.6, 0.4], [-2.0, 1.5, -0.3, 1.1, -2.5]);
        let run = |theta: &[f64], task: Task| task.simulate(theta, &mut ChaCha8Rng::seed_from_u64(21));
        let (xa, xb) = (run(&a, Task::SlcpDistractors), run(&b, Task::SlcpDistractors));
        assert_eq!(d.informative(&xa), run(&a, Task::Slcp));
        assert_eq!(d.informative(&xb), run(&b, Task::Slcp));
        let rest =
            |x: &[f64]| -> Vec<f64> { (0..DISTRACTED).filter(|i| !d.informative.contains(i)).map(|i| x[i]).collect() };
        assert_eq!(rest(&xa), rest(&xb));
        assert!(rest(&xa).iter().all(|v| v.is_finite()) && xa != xb);
        let reference = |task: Task, x: &[f64]| task.reference(x, 200, &mut ChaCha8Rng::seed_from_u64(22));
        let same = reference(Task::SlcpDistractors, &xa) == reference(Task::Slcp, &d.informative(&xa));
        assert!(same, "the reference differs from SLCP's at the picked-out columns");
    }

    /// `bernoulli_glm_raw`: the statistic of its 0/1 outcomes is `bernoulli_glm`'s x for the
    /// same θ and generator, and its reference draws are `bernoulli_glm`'s at that x.
    #[test]
    fn bernoulli_glm_raw_statistic_and_reference_match_the_glm() {
        let mut rng = ChaCha8Rng::seed_from_u64(31);
        let theta = Task::BernoulliGlmRaw.prior(&mut rng);
        let run = |task: Task| task.simulate(&theta, &mut ChaCha8Rng::seed_from_u64(32));
        let (raw, x) = (run(Task::BernoulliGlmRaw), run(Task::BernoulliGlm));
        assert!(raw.iter().all(|&v| v == 0.0 || v == 1.0));
        assert_eq!(x[0], raw.iter().sum::<f64>());
        assert_eq!(glm::glm().statistic(&raw), x);
        let reference = |task: Task, x: &[f64]| task.reference(x, 100, &mut ChaCha8Rng::seed_from_u64(33));
        let same = reference(Task::BernoulliGlmRaw, &raw) == reference(Task::BernoulliGlm, &x);
        assert!(same, "the reference differs from the GLM's at the statistic");
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
