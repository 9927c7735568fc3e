//! Monotonic rational-quadratic splines (Durkan et al. 2019, "Neural Spline Flows")
//! on [−B, B] with identity (linear, slope 1) tails, vectorised over [batch, dims].

use burn::prelude::*;
use burn::tensor::activation::{softmax, softplus};

/// Smallest bin width, bin height and interior knot derivative (as fractions of the
/// interval / slope units): the graph's spline here and the host's in `plain` share
/// them, so that both compute the same transform.
pub(crate) const MIN_WIDTH: f64 = 1e-3;
/// See [`MIN_WIDTH`].
pub(crate) const MIN_HEIGHT: f64 = 1e-3;
/// See [`MIN_WIDTH`].
pub(crate) const MIN_DERIVATIVE: f64 = 1e-3;

/// Raw parameters per transformed dim: K widths, K heights, K − 1 interior derivatives.
pub fn n_params(bins: usize) -> usize {
    3 * bins - 1
}

struct Knots {
    /// Knot positions [B, d, K+1] in x and y; bin sizes [B, d, K]; derivatives [B, d, K+1].
    cx: Tensor<3>,
    cy: Tensor<3>,
    w: Tensor<3>,
    h: Tensor<3>,
    d: Tensor<3>,
}

fn knots(raw: Tensor<3>, bins: usize, bound: f64) -> Knots {
    let [b, n, _] = raw.dims();
    let device = raw.device();
    let positions = |r: Tensor<3>, min: f64| -> Tensor<3> {
        let s = softmax(r, 2) * (1.0 - bins as f64 * min) + min;
        let c = s.cumsum(2);
        let zero = Tensor::<3>::zeros([b, n, 1], &device);
        Tensor::cat(vec![zero, c], 2) * (2.0 * bound) - bound
    };
    let cx = positions(raw.clone().narrow(2, 0, bins), MIN_WIDTH);
    let cy = positions(raw.clone().narrow(2, bins, bins), MIN_HEIGHT);
    let w = cx.clone().narrow(2, 1, bins) - cx.clone().narrow(2, 0, bins);
    let h = cy.clone().narrow(2, 1, bins) - cy.clone().narrow(2, 0, bins);
    let ones = Tensor::<3>::ones([b, n, 1], &device);
    let inner = softplus(raw.narrow(2, 2 * bins, bins - 1), 1.0) + MIN_DERIVATIVE;
    let d = Tensor::cat(vec![ones.clone(), inner, ones], 2);
    Knots { cx, cy, w, h, d }
}

/// Index of the bin holding v ([B, d, 1]) among knots c ([B, d, K+1]).
fn bin_of(v: Tensor<3>, c: &Tensor<3>, bins: usize) -> Tensor<3, Int> {
    let [b, n, _] = v.dims();
    let interior = c.clone().narrow(2, 1, bins - 1);
    v.expand([b, n, bins - 1]).greater_equal(interior).int().sum_dim(2)
}

/// y = f(x) and log |df/dx|, both [B, d]. Computed per element in f64 on the host
/// (`plain::spline_jacobians`) rather than as burn ops: the op-by-op graph (softmaxes,
/// cumulative sums, gathers and their backward, a few hundred small ops per coupling) was
/// about 70 % of a training epoch. With autodiff, the gradient enters through a term
/// whose value is exactly zero, J · (v − detach(v)) for v = (raw, x), so backward
/// applies the host's Jacobians J.
pub fn forward(x: Tensor<2>, raw: Tensor<3>, bins: usize, bound: f64) -> (Tensor<2>, Tensor<2>) {
    let [b, n] = x.dims();
    let np = n_params(bins);
    let device = x.device();
    let grad = x.is_tracked() || raw.is_tracked();
    let xs: Vec<f32> = x.clone().try_into_vec_as::<f32>().expect("spline input");
    let rs: Vec<f32> = raw.clone().try_into_vec_as::<f32>().expect("spline parameters");
    let (mut y, mut ld) = (vec![0.0f32; b * n], vec![0.0f32; b * n]);
    let (mut jy, mut jl) =
        if grad { (vec![0.0f32; b * n * (np + 1)], vec![0.0f32; b * n * (np + 1)]) } else { (vec![], vec![]) };
    let jacobians = grad.then_some((jy.as_mut_slice(), jl.as_mut_slice()));
    super::plain::spline_jacobians(&xs, &rs, bins, bound, (&mut y, &mut ld), jacobians);
    let y = Tensor::<2>::from_data(TensorData::new(y, [b, n]), &device);
    let ld = Tensor::<2>::from_data(TensorData::new(ld, [b, n]), &device);
    if !grad {
        return (y, ld);
    }
    let v = Tensor::cat(vec![raw, x.reshape([b, n, 1])], 2);
    let dv = v.clone() - v.detach();
    let jy = Tensor::<3>::from_data(TensorData::new(jy, [b, n, np + 1]), &device);
    let jl = Tensor::<3>::from_data(TensorData::new(jl, [b, n, np + 1]), &device);
    let y = y + (dv.clone() * jy).sum_dim(2).reshape([b, n]);
    let ld = ld + (dv * jl).sum_dim(2).reshape([b, n]);
    (y, ld)
}

/// The same as burn ops (the training graph before the host pass), for the tests.
#[cfg(test)]
pub fn forward_ops(x: Tensor<2>, raw: Tensor<3>, bins: usize, bound: f64) -> (Tensor<2>, Tensor<2>) {
    let [b, n] = x.dims();
    let k = knots(raw, bins, bound);
    let outside = x.clone().abs().greater_elem(bound);
    let xc = x.clone().clamp(-bound, bound).reshape([b, n, 1]);
    let idx = bin_of(xc.clone(), &k.cx, bins);
    let g = |t: &Tensor<3>| t.clone().gather(2, idx.clone());
    let (x0, w, y0, h) = (g(&k.cx), g(&k.w), g(&k.cy), g(&k.h));
    let d0 = g(&k.d);
    let d1 = k.d.clone().narrow(2, 1, bins).gather(2, idx.clone());
    let delta = h.clone() / w.clone();
    let t = ((xc - x0) / w).clamp(0.0, 1.0);
    let t1 = t.clone() * (t.clone().neg() + 1.0); // t(1 − t)
    let den = delta.clone() + (d0.clone() + d1.clone() - delta.clone() * 2.0) * t1.clone();
    let y = y0 + h * (delta.clone() * t.clone().powi_scalar(2) + d0.clone() * t1.clone()) / den.clone();
    let dnum = delta.clone().powi_scalar(2)
        * (d1 * t.clone().powi_scalar(2) + delta * t1 * 2.0 + d0 * (t.neg() + 1.0).powi_scalar(2));
    let logdet = dnum.log() - den.log() * 2.0;
    let y = y.reshape([b, n]).mask_where(outside.clone(), x);
    let logdet = logdet.reshape([b, n]).mask_fill(outside, 0.0);
    (y, logdet)
}

/// x = f⁻¹(y), [B, d].
pub fn inverse(y: Tensor<2>, raw: Tensor<3>, bins: usize, bound: f64) -> Tensor<2> {
    let [b, n] = y.dims();
    let k = knots(raw, bins, bound);
    let outside = y.clone().abs().greater_elem(bound);
    let yc = y.clone().clamp(-bound, bound).reshape([b, n, 1]);
    let idx = bin_of(yc.clone(), &k.cy, bins);
    let g = |t: &Tensor<3>| t.clone().gather(2, idx.clone());
    let (x0, w, y0, h) = (g(&k.cx), g(&k.w), g(&k.cy), g(&k.h));
    let d0 = g(&k.d);
    let d1 = k.d.clone().narrow(2, 1, bins).gather(2, idx);
    let delta = h.clone() / w.clone();
    let dy = yc - y0;
    let s = d0.clone() + d1 - delta.clone() * 2.0;
    let a = h.clone() * (delta.clone() - d0.clone()) + dy.clone() * s.clone();
    let bb = h * d0 - dy.clone() * s;
    let c = (delta * dy).neg();
    let disc = (bb.clone().powi_scalar(2) - a * c.clone() * 4.0).clamp_min(0.0);
    let t = (c * 2.0) / (bb.neg() - disc.sqrt());
    let x = t.clamp(0.0, 1.0) * w + x0;
    x.reshape([b, n]).mask_where(outside, y)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn device() -> Device {
        Device::flex()
    }

    fn vec2(t: Tensor<2>) -> Vec<f32> {
        t.try_into_vec_as::<f32>().unwrap()
    }

    #[test]
    fn inverse_undoes_forward_and_logdet_matches_finite_differences() {
        let dev = device();
        let bins = 8;
        let (b, n) = (5, 3);
        let raw: Vec<f32> = (0..b * n * n_params(bins)).map(|i| ((i * 7919 % 101) as f32 / 50.0 - 1.0) * 2.0).collect();
        let raw = Tensor::<3>::from_data(TensorData::new(raw, [b, n, n_params(bins)]), &dev);
        let xs: Vec<f32> = (0..b * n).map(|i| -3.5 + 7.0 * i as f32 / (b * n) as f32).collect();
        let x = Tensor::<2>::from_data(TensorData::new(xs.clone(), [b, n]), &dev);
        let (y, ld) = forward(x.clone(), raw.clone(), bins, 3.0);
        // The inverse's f32 twin: the host pass's f64 knots move a flat bin's round trip by ~1e-4.
        let back = vec2(inverse(forward_ops(x.clone(), raw.clone(), bins, 3.0).0, raw.clone(), bins, 3.0));
        for (a, c) in xs.iter().zip(&back) {
            assert!((a - c).abs() < 1e-4, "{a} vs {c}");
        }
        let eps = 1e-3f32;
        let shifted = |e: f32| {
            Tensor::<2>::from_data(TensorData::new(xs.iter().map(|v| v + e).collect::<Vec<_>>(), [b, n]), &dev)
        };
        let (yp, _) = forward(shifted(eps), raw.clone(), bins, 3.0);
        let (ym, _) = forward(shifted(-eps), raw, bins, 3.0);
        let (y, yp, ym, ld) = (vec2(y), vec2(yp), vec2(ym), vec2(ld));
        for i in 0..b * n {
            // Compare slopes (f32 differences of flat parts are too noisy for their log).
            let fd = (yp[i] - ym[i]) / (2.0 * eps);
            assert!((fd - ld[i].exp()).abs() < 2e-3 + 2e-2 * fd, "x = {}: fd {fd} vs {}", xs[i], ld[i].exp());
            if xs[i].abs() > 3.0 {
                assert_eq!(y[i], xs[i], "identity tails");
            }
        }
    }

    /// The host pass against the burn-op graph it replaced: the same y and log-slope, and
    /// through burn's backward the same gradients for the raw parameters and x (inside
    /// the bound, in the tails, at bins of every width).
    #[test]
    fn host_pass_matches_burn_ops_in_value_and_gradient() {
        let dev = Device::flex().autodiff();
        let (bins, bound) = (10, 3.0);
        let (b, n) = (40, 7);
        let np = n_params(bins);
        let raw: Vec<f32> = (0..b * n * np).map(|i| ((i * 7919 % 211) as f32 / 105.0 - 1.0) * 3.0).collect();
        let xs: Vec<f32> = (0..b * n).map(|i| ((i * 104_729 % 97) as f32 / 96.0 - 0.5) * 7.0).collect();
        let (wy, wl): (Vec<f32>, Vec<f32>) =
            (0..b * n).map(|i| ((i % 5) as f32 - 2.0, ((i * 3) % 7) as f32 / 3.0 - 1.0)).unzip();
        let run = |ops: bool| {
            let r = Tensor::<3>::from_data(TensorData::new(raw.clone(), [b, n, np]), &dev).require_grad();
            let x = Tensor::<2>::from_data(TensorData::new(xs.clone(), [b, n]), &dev).require_grad();
            let (y, ld) = if ops {
                forward_ops(x.clone(), r.clone(), bins, bound)
            } else {
                forward(x.clone(), r.clone(), bins, bound)
            };
            let a = Tensor::<2>::from_data(TensorData::new(wy.clone(), [b, n]), &dev);
            let c = Tensor::<2>::from_data(TensorData::new(wl.clone(), [b, n]), &dev);
            let (yv, lv) = (vec2(y.clone()), vec2(ld.clone()));
            let grads = (y * a + ld * c).sum().backward();
            let gr = r.grad(&grads).unwrap().try_into_vec_as::<f32>().unwrap();
            let gx = vec2(x.grad(&grads).unwrap());
            (yv, lv, gr, gx)
        };
        let (new, old) = (run(false), run(true));
        let close = |what: &str, p: &[f32], q: &[f32], tol: f32| {
            assert_eq!(p.len(), q.len());
            for (i, (u, v)) in p.iter().zip(q).enumerate() {
                assert!((u - v).abs() <= tol * (1.0 + v.abs()), "{what}[{i}]: host {u} vs burn ops {v}");
            }
        };
        close("y", &new.0, &old.0, 1e-5);
        close("log slope", &new.1, &old.1, 1e-4);
        close("d/draw", &new.2, &old.2, 1e-3);
        close("d/dx", &new.3, &old.3, 1e-3);
        assert!(xs.iter().any(|v| v.abs() > bound as f32) && xs.iter().any(|v| v.abs() < 1.0));
    }
}
