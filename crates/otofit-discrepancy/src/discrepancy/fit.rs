//! Levenberg–Marquardt fit of a design's columns (the seven parameters plus any varied
//! effects) to one observation, in the unbounded coordinates of the prior box, so every
//! iterate stays inside the bounds.

use crate::npe::prior::{FIT_EDGE, space};
use crate::sim::batch::Design;
use crate::sim::output::MEASURES;
use crate::sim::params::ParamSpec;
use crate::sim::{Model, Runner, simulate};
use faer::Mat;
use faer::prelude::Solve;
use std::f64::consts::{PI, TAU};

/// One observation with its per-feature noise standard deviation.
#[derive(Clone, Debug)]
pub struct Observation {
    /// Features in the model's order; a non-finite one was not measured.
    pub x: Vec<f64>,
    /// Noise standard deviation per feature: the residuals' unit.
    pub sigma: Vec<f64>,
}

/// θ ↔ u: scale, then logit of the position in the box (the shared map, with the fit's
/// edge clamp).
pub fn to_unbounded(p: &ParamSpec, v: f64) -> f64 {
    space::to_logit(p.scale, p.low, p.high, v, FIT_EDGE)
}

/// u → θ, inside the box.
pub fn from_unbounded(p: &ParamSpec, u: f64) -> f64 {
    space::from_logit(p.scale, p.low, p.high, u)
}

/// Residual of one feature, with phase differences wrapped into (−π, π] so that a
/// different unwrapping start is not mistaken for misfit.
pub fn feature_residual(feature: usize, n_freq: usize, sim: f64, obs: f64) -> f64 {
    let d = sim - obs;
    if MEASURES[feature / n_freq].name.ends_with("_phase") { d - TAU * ((d + PI) / TAU).floor() } else { d }
}

/// Standardised residuals (sim − obs)/σ over the observed features (a non-finite
/// observation is absent and has none); `None` if the simulation failed.
pub fn residuals(runner: &mut Runner<'_>, design: &Design, row: &[f64], obs: &Observation) -> Option<Vec<f64>> {
    let (theta, fx) = design.split(row);
    let x = simulate(runner, &theta, &fx).ok()?;
    let nf = x.len() / MEASURES.len();
    let on = (0..x.len().min(obs.x.len())).filter(|&i| obs.x[i].is_finite());
    Some(on.map(|i| feature_residual(i, nf, x[i], obs.x[i]) / obs.sigma[i]).collect())
}

/// A converged (or stopped) least-squares fit of one observation.
#[derive(Clone, Debug)]
pub struct Fit {
    /// The best row (natural units, design column order).
    pub row: Vec<f64>,
    /// Σ r² at the best row.
    pub chi2: f64,
    /// Observed features in the fit (the χ²'s terms).
    pub n_features: usize,
    /// Levenberg–Marquardt steps taken.
    pub iterations: usize,
    /// Laplace standard deviation of each column in unbounded coordinates (from JᵀJ).
    pub u_std: Vec<f64>,
    /// JᵀJ at the best row (unbounded coordinates, row-major d×d): half the Hessian of
    /// χ² in the Gauss–Newton approximation.
    pub jtj: Vec<f64>,
}

impl Fit {
    /// χ² per degree of freedom (features minus fitted columns): ≈ 1 for a model that
    /// explains the data to its noise.
    pub fn reduced_chi2(&self) -> f64 {
        self.chi2 / (self.n_features - self.row.len()) as f64
    }
}

fn chi2(r: &[f64]) -> f64 {
    r.iter().map(|v| v * v).sum()
}

/// Fits from each start (rows in natural units) and keeps the best.
pub fn fit(model: &Model, design: &Design, starts: &[Vec<f64>], obs: &Observation, max_iter: usize) -> Option<Fit> {
    let mut runner = model.runner();
    runner.remember_jacobian(design.columns().len());
    starts
        .iter()
        .filter_map(|s| fit_one(&mut runner, design, s, obs, max_iter))
        .min_by(|a, b| a.chi2.total_cmp(&b.chi2))
}

fn fit_one(runner: &mut Runner<'_>, design: &Design, start: &[f64], obs: &Observation, max_iter: usize) -> Option<Fit> {
    fit_columns(&design.columns(), start, max_iter, |row| residuals(runner, design, row, obs))
}

/// Levenberg–Marquardt over columns `cols` (each inside its own box, through the
/// unbounded map) from `start` (natural units), at most `max_iter` steps, for any
/// standardised residual function of a row (`None`: the row failed to simulate). [`fit`]
/// is this with the design's columns and [`residuals`]; a caller may bound the columns
/// differently or add its own (e.g. the simulator's structural constants).
pub fn fit_columns(
    cols: &[ParamSpec],
    start: &[f64],
    max_iter: usize,
    mut residuals: impl FnMut(&[f64]) -> Option<Vec<f64>>,
) -> Option<Fit> {
    let d = cols.len();
    let to_row = |u: &[f64]| -> Vec<f64> { cols.iter().zip(u).map(|(p, &v)| from_unbounded(p, v)).collect() };
    let mut u: Vec<f64> = cols.iter().zip(start).map(|(p, &v)| to_unbounded(p, v)).collect();
    let mut r = residuals(&to_row(&u))?;
    let mut c = chi2(&r);
    let mut lambda = 1e-2;
    let mut iterations = 0;
    let mut jtj = Mat::<f64>::zeros(d, d);
    for it in 0..max_iter {
        iterations = it + 1;
        let jtr;
        (jtj, jtr) = normal_equations(&u, &r, false, |up| residuals(&to_row(up)))?;
        let to_trial = |step: &Mat<f64>| (0..d).map(|i| (u[i] + step[(i, 0)]).clamp(-20.0, 20.0)).collect();
        let Some((trial, rt, ct)) = damped_step(&jtj, &jtr, &mut lambda, c, to_trial, |t| residuals(&to_row(t)), TRIES)
        else {
            break;
        };
        let gain = c - ct;
        (u, r) = (trial, rt);
        c -= gain;
        if gain <= 1e-6 * c.max(1.0) {
            break;
        }
    }
    // Laplace approximation of the posterior in u (flat prior in u): cov ≈ (JᵀJ)⁻¹.
    let inv = jtj.partial_piv_lu().solve(Mat::<f64>::identity(d, d));
    let u_std = (0..d).map(|i| inv[(i, i)].abs().sqrt()).collect();
    let jtj = (0..d * d).map(|k| jtj[(k / d, k % d)]).collect();
    Some(Fit { row: to_row(&u), chi2: c, n_features: r.len(), iterations, u_std, jtj })
}

/// JᵀJ and Jᵀr of `residuals` at `x`, whose residuals are `r`, by forward differences in
/// each coordinate (step 1e-4). A step whose row fails to simulate gives up (`None`), or,
/// with `zero_failed`, leaves its column at zero (that direction drops out of the step).
pub(crate) fn normal_equations(
    x: &[f64],
    r: &[f64],
    zero_failed: bool,
    mut residuals: impl FnMut(&[f64]) -> Option<Vec<f64>>,
) -> Option<(Mat<f64>, Vec<f64>)> {
    let (d, h) = (x.len(), 1e-4);
    let mut jac = Vec::with_capacity(d);
    for k in 0..d {
        let mut up = x.to_vec();
        up[k] += h;
        jac.push(match residuals(&up) {
            Some(rk) => rk.iter().zip(r).map(|(a, b)| (a - b) / h).collect::<Vec<f64>>(),
            None if zero_failed => vec![0.0; r.len()],
            None => return None,
        });
    }
    let jtj = Mat::from_fn(d, d, |i, j| jac[i].iter().zip(&jac[j]).map(|(a, b)| a * b).sum());
    let jtr = (0..d).map(|i| jac[i].iter().zip(r).map(|(a, b)| a * b).sum()).collect();
    Some((jtj, jtr))
}

/// Floor of the damping diagonal, relative to its largest entry. Without a relative floor a
/// direction the residuals barely see at this point (JᵀJ's entry ~1e-12 against ~1e8) is
/// damped by almost nothing: its step, Jᵀr over a near-zero entry, throws that parameter to
/// the edge of its box, every try fails however large λ grows in ten tries, and the fit
/// stops where it started (seen from most starts of a strong perforation's fit).
const DAMPING_FLOOR: f64 = 1e-9;

/// Tries of [`damped_step`] when its Jacobian is fresh.
pub(super) const TRIES: usize = 10;

/// Levenberg–Marquardt's damped step, up to `tries` tries: solves (JᵀJ + λ·D) s = −Jᵀr, D
/// the diagonal of JᵀJ floored at [`DAMPING_FLOOR`] of its largest entry, makes a trial
/// point of s with `to_trial`, and keeps the first whose χ² is below `c`. λ falls by 3 on
/// a success (not below 1e-7) and grows by 4 on a failure. The point, its residuals and
/// its χ²; `None` after `tries` failures. Shared by the unbounded fit here, the box fit of
/// the alternatives and the exact sampler's mode search.
pub(super) fn damped_step(
    jtj: &Mat<f64>,
    jtr: &[f64],
    lambda: &mut f64,
    c: f64,
    mut to_trial: impl FnMut(&Mat<f64>) -> Vec<f64>,
    mut residuals: impl FnMut(&[f64]) -> Option<Vec<f64>>,
    tries: usize,
) -> Option<(Vec<f64>, Vec<f64>, f64)> {
    let n = jtr.len();
    let top = (0..n).map(|i| jtj[(i, i)]).fold(0.0_f64, f64::max);
    let floor = (DAMPING_FLOOR * top).max(1e-9);
    for _ in 0..tries {
        let a = Mat::from_fn(n, n, |i, j| jtj[(i, j)] + if i == j { *lambda * jtj[(i, i)].max(floor) } else { 0.0 });
        let rhs = Mat::from_fn(n, 1, |i, _| -jtr[i]);
        let trial = to_trial(&a.partial_piv_lu().solve(&rhs));
        match residuals(&trial) {
            Some(rt) if chi2(&rt) < c => {
                *lambda = (*lambda / 3.0).max(1e-7);
                let ct = chi2(&rt);
                return Some((trial, rt, ct));
            }
            _ => *lambda *= 4.0,
        }
    }
    None
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::sim::params::PARAMS;

    #[test]
    fn a_direction_the_residuals_barely_see_does_not_stall_the_fit() {
        // r₀ pins u₀ at 1 steeply; r₁ hardly sees u₁ at the start (slope 1e-6) but grows
        // fast away from it. Damped by its own ~1e-12 entry, the u₁ step reaches the box
        // edge at every λ of ten tries and the fit never moves u₀.
        let col = ParamSpec {
            name: "a",
            unit: "",
            scale: crate::sim::params::Scale::Linear,
            low: -1.0,
            high: 1.0,
            nominal: 0.0,
        };
        let cols = [col, ParamSpec { name: "b", ..col }];
        let f = fit_columns(&cols, &[0.0, 0.0], 100, |row| {
            let u: Vec<f64> = cols.iter().zip(row).map(|(p, &v)| to_unbounded(p, v)).collect();
            Some(vec![1e4 * (u[0] - 1.0), 30.0 + 1e-6 * u[1] + 1e3 * u[1].powi(4)])
        })
        .unwrap();
        let u0 = to_unbounded(&cols[0], f.row[0]);
        assert!((u0 - 1.0).abs() < 1e-4, "u₀ {u0} after {} steps, χ² {}", f.iterations, f.chi2);
    }

    #[test]
    fn unbounded_map_round_trips_inside_the_box() {
        for p in PARAMS {
            for q in [0.01, 0.5, 0.99] {
                let v = p.from_unit(q);
                let back = from_unbounded(&p, to_unbounded(&p, v));
                assert!((back - v).abs() < 1e-9 * v.abs(), "{} {v} {back}", p.name);
            }
            assert!(p.contains(from_unbounded(&p, 40.0)) && p.contains(from_unbounded(&p, -40.0)));
        }
    }

    #[test]
    fn phase_residuals_are_wrapped() {
        let n = 50;
        let r = feature_residual(60, n, 0.1 + TAU, 0.0);
        assert!((r - 0.1).abs() < 1e-12);
        assert_eq!(feature_residual(10, n, 0.1 + TAU, 0.0), 0.1 + TAU); // a magnitude
    }
}
