//! Classifier two-sample test (Lopez-Paz & Oquab 2017, arXiv:1610.06545) as the SBI
//! benchmark uses it: both sample sets z-scored by the first one's mean and spread, an
//! MLP with two hidden ReLU layers of 10 × dim units, binary cross-entropy with a small
//! L2 penalty, Adam (lr 1e-3, batches of 200); the score is the mean held-out accuracy
//! of 5-fold cross-validation. 0.5: indistinguishable; 1: fully separable.
//!
//! One departure, for time: the benchmark stops the classifier when its training loss
//! stalls (up to 10,000 epochs); here it stops when the accuracy on a tenth of the
//! training fold stalls for 10 epochs and keeps the best weights (scikit-learn's
//! `early_stopping=True`). The numbers differ: on two moons (3 observations) the
//! benchmark's rule gave 0.666 and 0.608 for two flows where this one gives 0.639 and
//! 0.582, on the 10-D Gaussian task 0.699 and 0.686 where this one gives 0.761 and 0.744
//! (the long-trained classifier overfits there); `train_loss_stop` restores the
//! benchmark's rule.

use faer::linalg::matmul::matmul;
use faer::{Accum, Mat, MatRef, Par};
use rand::SeedableRng;
use rand::seq::SliceRandom;
use rand_chacha::ChaCha8Rng;
use rayon::prelude::*;

/// How the classifier two-sample test is run.
#[derive(Clone, Debug)]
pub struct C2stParams {
    /// Cross-validation folds (at least 2).
    pub folds: usize,
    /// Most classifier epochs per fold.
    pub max_epochs: usize,
    /// Seed of the fold split and the classifier's weights.
    pub seed: u64,
    /// Stop as the benchmark does (training loss stalled) instead of on held-out accuracy.
    pub train_loss_stop: bool,
}

impl Default for C2stParams {
    fn default() -> Self {
        C2stParams { folds: 5, max_epochs: 500, seed: 0, train_loss_stop: false }
    }
}

const LR: f32 = 1e-3;
const BATCH: usize = 200;
const ALPHA: f32 = 1e-4;
const TOL: f64 = 1e-4;
const NO_CHANGE: usize = 10;

/// C2ST accuracy between sample sets `a` and `b` (rows of equal length).
pub fn c2st(a: &[Vec<f64>], b: &[Vec<f64>], p: &C2stParams) -> f64 {
    let d = a[0].len();
    let n = a.len() as f64;
    let mean: Vec<f64> = (0..d).map(|k| a.iter().map(|r| r[k]).sum::<f64>() / n).collect();
    let std: Vec<f64> =
        (0..d).map(|k| (a.iter().map(|r| (r[k] - mean[k]).powi(2)).sum::<f64>() / n).sqrt().max(1e-12)).collect();
    let rows: Vec<(Vec<f32>, f32)> = a
        .iter()
        .map(|r| (r, 0.0))
        .chain(b.iter().map(|r| (r, 1.0)))
        .map(|(r, y)| ((0..d).map(|k| ((r[k] - mean[k]) / std[k]) as f32).collect(), y))
        .collect();
    let mut order: Vec<usize> = (0..rows.len()).collect();
    order.shuffle(&mut ChaCha8Rng::seed_from_u64(p.seed));
    let folds = p.folds.max(2);
    let acc: Vec<f64> = (0..folds)
        .into_par_iter()
        .map(|f| {
            let (lo, hi) = (f * rows.len() / folds, (f + 1) * rows.len() / folds);
            let test: Vec<usize> = order[lo..hi].to_vec();
            let train: Vec<usize> = order[..lo].iter().chain(&order[hi..]).copied().collect();
            let mut net = Mlp::new(&[d, 10 * d, 10 * d, 1], p.seed.wrapping_add(f as u64 + 1));
            let seed = p.seed ^ (f as u64) << 8;
            if p.train_loss_stop {
                net.fit_to_training_loss(&rows, &train, p.max_epochs, seed);
            } else {
                net.fit(&rows, &train, p.max_epochs, seed);
            }
            net.accuracy(&rows, &test)
        })
        .collect();
    acc.iter().sum::<f64>() / acc.len() as f64
}

/// A column-major batch [dim × n] of the given rows.
fn batch(rows: &[(Vec<f32>, f32)], idx: &[usize]) -> (Mat<f32>, Vec<f32>) {
    let d = rows[idx[0]].0.len();
    let x = Mat::from_fn(d, idx.len(), |k, j| rows[idx[j]].0[k]);
    (x, idx.iter().map(|&i| rows[i].1).collect())
}

struct Layer {
    /// [out × in], bias [out]; Adam moments alongside.
    w: Mat<f32>,
    b: Vec<f32>,
    mw: Mat<f32>,
    vw: Mat<f32>,
    mb: Vec<f32>,
    vb: Vec<f32>,
}

struct Mlp {
    layers: Vec<Layer>,
    step: i32,
}

impl Mlp {
    /// Glorot-uniform weights (bound √(6/(in+out))), zero biases.
    fn new(sizes: &[usize], seed: u64) -> Mlp {
        use rand::Rng;
        let mut rng = ChaCha8Rng::seed_from_u64(seed);
        let layers = sizes
            .windows(2)
            .map(|s| {
                let bound = (6.0 / (s[0] + s[1]) as f64).sqrt() as f32;
                Layer {
                    w: Mat::from_fn(s[1], s[0], |_, _| rng.random_range(-bound..bound)),
                    b: vec![0.0; s[1]],
                    mw: Mat::zeros(s[1], s[0]),
                    vw: Mat::zeros(s[1], s[0]),
                    mb: vec![0.0; s[1]],
                    vb: vec![0.0; s[1]],
                }
            })
            .collect();
        Mlp { layers, step: 0 }
    }

    /// Activations of every layer for x [in × n] (the last one: logits [1 × n]).
    fn forward(&self, x: MatRef<'_, f32>) -> Vec<Mat<f32>> {
        let mut acts: Vec<Mat<f32>> = Vec::with_capacity(self.layers.len());
        let last = self.layers.len() - 1;
        for (i, l) in self.layers.iter().enumerate() {
            let input = if i == 0 { x } else { acts[i - 1].as_ref() };
            let mut h = Mat::zeros(l.w.nrows(), input.ncols());
            matmul(h.as_mut(), Accum::Replace, l.w.as_ref(), input, 1.0, Par::Seq);
            for j in 0..h.ncols() {
                for k in 0..h.nrows() {
                    let v = h[(k, j)] + l.b[k];
                    h[(k, j)] = if i < last { v.max(0.0) } else { v };
                }
            }
            acts.push(h);
        }
        acts
    }

    /// One Adam step on a batch; returns the batch's mean cross-entropy.
    fn train_step(&mut self, x: MatRef<'_, f32>, y: &[f32]) -> f64 {
        let n = y.len() as f32;
        let acts = self.forward(x);
        let z = acts.last().expect("layers");
        let mut loss = 0.0f64;
        // d loss / d logit = σ(z) − y, averaged over the batch.
        let mut delta = Mat::from_fn(1, y.len(), |_, j| {
            let zj = z[(0, j)];
            loss += (zj.max(0.0) - zj * y[j] + (-zj.abs()).exp().ln_1p()) as f64;
            (1.0 / (1.0 + (-zj).exp()) - y[j]) / n
        });
        self.step += 1;
        let (b1, b2, eps) = (0.9f32, 0.999f32, 1e-8f32);
        let (c1, c2) = (1.0 - b1.powi(self.step), 1.0 - b2.powi(self.step));
        for i in (0..self.layers.len()).rev() {
            let input = if i == 0 { x } else { acts[i - 1].as_ref() };
            let l = &self.layers[i];
            let mut gw = Mat::zeros(l.w.nrows(), l.w.ncols());
            matmul(gw.as_mut(), Accum::Replace, delta.as_ref(), input.transpose(), 1.0, Par::Seq);
            let gb: Vec<f32> = (0..delta.nrows()).map(|k| (0..delta.ncols()).map(|j| delta[(k, j)]).sum()).collect();
            if i > 0 {
                let mut back = Mat::zeros(l.w.ncols(), delta.ncols());
                matmul(back.as_mut(), Accum::Replace, l.w.transpose(), delta.as_ref(), 1.0, Par::Seq);
                for j in 0..back.ncols() {
                    for k in 0..back.nrows() {
                        if input[(k, j)] <= 0.0 {
                            back[(k, j)] = 0.0;
                        }
                    }
                }
                delta = back;
            }
            let l = &mut self.layers[i];
            for c in 0..l.w.ncols() {
                for r in 0..l.w.nrows() {
                    loss += 0.5 * (ALPHA * l.w[(r, c)] * l.w[(r, c)] / n) as f64;
                    let g = gw[(r, c)] + ALPHA * l.w[(r, c)] / n;
                    l.mw[(r, c)] = b1 * l.mw[(r, c)] + (1.0 - b1) * g;
                    l.vw[(r, c)] = b2 * l.vw[(r, c)] + (1.0 - b2) * g * g;
                    l.w[(r, c)] -= LR * (l.mw[(r, c)] / c1) / ((l.vw[(r, c)] / c2).sqrt() + eps);
                }
            }
            for (k, g) in gb.iter().enumerate() {
                l.mb[k] = b1 * l.mb[k] + (1.0 - b1) * g;
                l.vb[k] = b2 * l.vb[k] + (1.0 - b2) * g * g;
                l.b[k] -= LR * (l.mb[k] / c1) / ((l.vb[k] / c2).sqrt() + eps);
            }
        }
        loss / n as f64
    }

    /// Trains on 90 % of `train`; stops when the accuracy on the other 10 % has not
    /// improved by 1e-4 for 10 epochs and keeps the best weights.
    fn fit(&mut self, rows: &[(Vec<f32>, f32)], train: &[usize], max_epochs: usize, seed: u64) {
        let mut rng = ChaCha8Rng::seed_from_u64(seed);
        let n_val = (train.len() / 10).max(1);
        let (val, fit) = train.split_at(n_val);
        let mut order = fit.to_vec();
        let (mut best, mut stale) = (f64::NEG_INFINITY, 0);
        let mut kept: Vec<(Mat<f32>, Vec<f32>)> = Vec::new();
        for _ in 0..max_epochs {
            order.shuffle(&mut rng);
            for idx in order.chunks(BATCH) {
                let (x, y) = batch(rows, idx);
                self.train_step(x.as_ref(), &y);
            }
            let acc = self.accuracy(rows, val);
            if acc > best + TOL {
                best = acc;
                stale = 0;
                kept = self.layers.iter().map(|l| (l.w.clone(), l.b.clone())).collect();
            } else {
                stale += 1;
                if stale >= NO_CHANGE {
                    break;
                }
            }
        }
        for (l, (w, b)) in self.layers.iter_mut().zip(kept) {
            l.w = w;
            l.b = b;
        }
    }

    /// The benchmark's rule: all of `train`, stopped when the training loss has not
    /// improved by 1e-4 for 10 epochs.
    fn fit_to_training_loss(&mut self, rows: &[(Vec<f32>, f32)], train: &[usize], max_epochs: usize, seed: u64) {
        let mut rng = ChaCha8Rng::seed_from_u64(seed);
        let mut order = train.to_vec();
        let (mut best, mut stale) = (f64::INFINITY, 0);
        for _ in 0..max_epochs {
            order.shuffle(&mut rng);
            let mut sum = 0.0;
            for idx in order.chunks(BATCH) {
                let (x, y) = batch(rows, idx);
                sum += self.train_step(x.as_ref(), &y) * idx.len() as f64;
            }
            let loss = sum / order.len() as f64;
            if loss > best - TOL {
                stale += 1;
                if stale >= NO_CHANGE {
                    break;
                }
            } else {
                stale = 0;
            }
            best = best.min(loss);
        }
    }

    fn accuracy(&self, rows: &[(Vec<f32>, f32)], test: &[usize]) -> f64 {
        let mut right = 0;
        for idx in test.chunks(1000) {
            let (x, y) = batch(rows, idx);
            let acts = self.forward(x.as_ref());
            let z = acts.last().expect("layers");
            right += (0..y.len()).filter(|&j| (z[(0, j)] > 0.0) == (y[j] > 0.5)).count();
        }
        right as f64 / test.len() as f64
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::Rng;
    use rand_distr::{Distribution, StandardNormal};

    fn gauss(n: usize, shift: f64, seed: u64) -> Vec<Vec<f64>> {
        let mut rng = ChaCha8Rng::seed_from_u64(seed);
        (0..n)
            .map(|_| {
                let a: f64 = StandardNormal.sample(&mut rng);
                vec![a + shift, rng.random::<f64>()]
            })
            .collect()
    }

    /// Same distribution: about 0.5; means 2 σ apart: near the Bayes accuracy Φ(1) = 0.84.
    #[test]
    fn same_distributions_score_one_half_and_separated_ones_more() {
        let p = C2stParams { max_epochs: 100, ..Default::default() };
        let same = c2st(&gauss(1000, 0.0, 1), &gauss(1000, 0.0, 2), &p);
        assert!((same - 0.5).abs() < 0.05, "same: {same}");
        let apart = c2st(&gauss(1000, 0.0, 1), &gauss(1000, 2.0, 2), &p);
        assert!((apart - 0.84).abs() < 0.04, "apart: {apart}");
    }

    /// The floor at the benchmark's shape: two independent sets of exact reference draws
    /// of the 10-D Gaussian task (observation 1) score about 0.5, and the same draws
    /// spread 10 % wider about the observation score clearly above it.
    #[test]
    fn two_reference_draws_of_the_10d_gaussian_task_score_one_half() {
        use crate::{Task, observation};
        let task = Task::GaussianLinearUniform;
        let x = observation(task, 1);
        let draw = |seed| task.reference(&x, 3000, &mut ChaCha8Rng::seed_from_u64(seed));
        let wide: Vec<Vec<f64>> =
            draw(3).into_iter().map(|t| t.iter().zip(&x).map(|(v, m)| m + 1.1 * (v - m)).collect()).collect();
        let p = C2stParams::default();
        let (same, wider) = (c2st(&draw(1), &draw(2), &p), c2st(&draw(1), &wide, &p));
        eprintln!("C2ST: two reference draws {same:.3}, one 10 % wider {wider:.3}");
        assert!((same - 0.5).abs() < 0.03, "same: {same}");
        assert!(wider > same + 0.04, "10 % wider: {wider} against {same}");
    }
}
