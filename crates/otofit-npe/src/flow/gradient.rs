//! The training loss and its gradient on the host: mean −log q over a batch, forward and
//! backward by hand in f32 (faer matmuls, the splines' Jacobians of `plain`), with no burn
//! graph. burn's autodiff records every op under one process-wide lock, so the parts of a
//! batch on more threads queued on each other and an epoch stopped getting faster at four
//! threads (docs/results/scaling.md); here a part shares nothing with the others but the
//! weights it reads. A test holds it to burn's gradient for every architecture the flow
//! builds.

use super::{Flow, FlowConfig, LU_MIN_DIAG, Mlp, plain, spline};
use burn::module::ParamId;
use burn::nn::Linear;

use burn::prelude::*;
use faer::linalg::matmul::matmul;
use faer::{Accum, MatMut, MatRef, Par};

/// One linear layer, y = x W + b: where its weight W [in × out] (row-major, burn's layout)
/// sits in [`Weights`]' values, its bias next to it.
#[derive(Clone)]
struct Layer {
    at: usize,
    inputs: usize,
    outputs: usize,
}

/// An LU layer: where its (lower, upper, diag, bias) sit in [`Weights`]' values, and
/// what its map and gradient need, computed from them: W = L U, the unit lower L, the
/// upper U (its diagonal softplus(s) + min), and σ(s), the softplus's slope.
#[derive(Clone)]
struct Lu {
    at: usize,
    w: Vec<f32>,
    l: Vec<f32>,
    u: Vec<f32>,
    diag: Vec<f32>,
    slope: Vec<f32>,
}

/// The flow's weights on the host for [`loss_and_gradient`]: every parameter tensor's
/// values, id and shape, in the order of [`Gradient`]'s tensors (each layer's weight and
/// bias, embedding first, then each conditioner's, then the LU layers').
#[derive(Clone)]
pub struct Weights {
    cfg: FlowConfig,
    embedding: Vec<Layer>,
    conditioners: Vec<Vec<Layer>>,
    lu: Vec<Lu>,
    params: Vec<(ParamId, Vec<usize>)>,
    values: Vec<Vec<f32>>,
}

/// d loss / d parameter for every parameter of a flow, in [`Weights`]' order.
#[derive(Clone, Debug, PartialEq)]
pub struct Gradient(pub Vec<Vec<f32>>);

fn values<const D: usize>(t: Tensor<D>) -> Vec<f32> {
    t.try_into_vec_as::<f32>().expect("weights as f32")
}

impl Weights {
    /// The weights of `flow` (architecture `cfg`) as they are now.
    pub fn of(flow: &Flow, cfg: &FlowConfig) -> Weights {
        let (mut params, mut vals) = (vec![], vec![]);
        let mut layer = |l: &Linear| {
            let [inputs, outputs] = l.weight.val().dims();
            let at = params.len();
            params.push((l.weight.id, vec![inputs, outputs]));
            vals.push(values(l.weight.val()));
            // Every layer the flow builds has a bias (the slot after its weight).
            let b = l.bias.as_ref().expect("flow layers have biases");
            params.push((b.id, vec![outputs]));
            vals.push(values(b.val()));
            Layer { at, inputs, outputs }
        };
        let mut mlp = |m: &Mlp| -> Vec<Layer> { m.layers.iter().map(&mut layer).collect() };
        let embedding = mlp(&flow.embedding);
        let conditioners = flow.conditioners.iter().map(&mut mlp).collect();
        let d = cfg.dim;
        let mut lu = vec![];
        for layer in &flow.lu {
            let at = params.len();
            for p in [&layer.lower, &layer.upper] {
                params.push((p.id, vec![d, d]));
                vals.push(values(p.val()));
            }
            for p in [&layer.diag, &layer.bias] {
                params.push((p.id, vec![d]));
                vals.push(values(p.val()));
            }
            lu.push(Lu { at, w: vec![], l: vec![], u: vec![], diag: vec![], slope: vec![] });
        }
        let mut w = Weights { cfg: cfg.clone(), embedding, conditioners, lu, params, values: vals };
        w.refresh();
        w
    }

    /// Recomputes the LU layers' maps from their parameters (after the values changed).
    pub fn refresh(&mut self) {
        let d = self.cfg.dim;
        for lu in &mut self.lu {
            let (lower, upper, s) = (&self.values[lu.at], &self.values[lu.at + 1], &self.values[lu.at + 2]);
            // softplus(s) = max(s, 0) + ln(1 + e^−|s|), without overflow.
            lu.diag = s.iter().map(|&s| s.max(0.0) + (-s.abs()).exp().ln_1p() + LU_MIN_DIAG as f32).collect();
            lu.slope = s.iter().map(|&s| 1.0 / (1.0 + (-s).exp())).collect();
            lu.l = (0..d * d)
                .map(|k| match (k / d, k % d) {
                    (r, c) if r > c => lower[k],
                    (r, c) if r == c => 1.0,
                    _ => 0.0,
                })
                .collect();
            lu.u = (0..d * d)
                .map(|k| match (k / d, k % d) {
                    (r, c) if r < c => upper[k],
                    (r, c) if r == c => lu.diag[r],
                    _ => 0.0,
                })
                .collect();
            lu.w = product(&lu.l, &lu.u, d);
        }
    }

    /// Every parameter tensor's values, in [`Gradient`]'s order.
    pub fn values(&self) -> &[Vec<f32>] {
        &self.values
    }

    /// [`Weights::values`] to change; call [`Weights::refresh`] after.
    pub fn values_mut(&mut self) -> &mut [Vec<f32>] {
        &mut self.values
    }

    /// Every parameter tensor's length, in [`Gradient`]'s order.
    pub fn sizes(&self) -> impl Iterator<Item = usize> + '_ {
        self.values.iter().map(Vec::len)
    }

    /// `flow` with these weights (the same parameter ids).
    pub fn to_flow(&self, flow: Flow) -> Flow {
        let by_id = self.params.iter().map(|p| p.0).zip(self.values.iter().cloned()).collect();
        let mut mapper = SetValues { by_id };
        flow.map(&mut mapper)
    }
}

/// Puts host values into a flow's parameters, by id (each on its tensor's device).
struct SetValues {
    by_id: std::collections::HashMap<ParamId, Vec<f32>>,
}

impl burn::module::ModuleMapper for SetValues {
    fn map_float<const D: usize>(&mut self, param: burn::module::Param<Tensor<D>>) -> burn::module::Param<Tensor<D>> {
        let Some(v) = self.by_id.remove(&param.id) else { return param };
        let (id, tensor, mapper) = param.consume();
        let new = Tensor::<D>::from_data(TensorData::new(v, tensor.dims()), &tensor.device());
        let new = if tensor.is_require_grad() { new.require_grad() } else { new };
        burn::module::Param::from_mapped_value(id, new, mapper)
    }
}

impl Gradient {
    /// Σ w_k · parts[k], element by element, the parts added in order; the tensors are
    /// summed on the thread pool (on many cores the sum of many parts was a serial step
    /// of every batch), each by one thread, so the bits do not depend on the threads.
    pub fn weighted_sum(parts: &[Gradient], shares: &[f32]) -> Gradient {
        use rayon::prelude::*;
        let tensors = parts.first().map_or(0, |p| p.0.len());
        Gradient(
            (0..tensors)
                .into_par_iter()
                .map(|t| {
                    let mut sum = vec![0.0f32; parts[0].0[t].len()];
                    for (p, &w) in parts.iter().zip(shares) {
                        sum.iter_mut().zip(&p.0[t]).for_each(|(a, b)| *a += w * b);
                    }
                    sum
                })
                .collect(),
        )
    }

    /// As burn's gradients of `weights`' parameters (burn's optimizer takes them; the
    /// tests compare it with the host's).
    #[cfg(test)]
    pub(crate) fn into_params(self, weights: &Weights, device: &Device) -> burn::optim::GradientsParams {
        let mut out = burn::optim::GradientsParams::new();
        for ((id, shape), g) in weights.params.iter().zip(self.0) {
            match shape[..] {
                [n] => out.register(*id, Tensor::<1>::from_data(TensorData::new(g, [n]), device)),
                [r, c] => out.register(*id, Tensor::<2>::from_data(TensorData::new(g, [r, c]), device)),
                _ => unreachable!("parameters are vectors or matrices"),
            }
        }
        out
    }
}

/// a b for row-major d × d matrices.
fn product(a: &[f32], b: &[f32], d: usize) -> Vec<f32> {
    let mut out = vec![0.0f32; d * d];
    for r in 0..d {
        for k in 0..d {
            let ark = a[r * d + k];
            for c in 0..d {
                out[r * d + c] += ark * b[k * d + c];
            }
        }
    }
    out
}

/// x [n × in] through a layer (its weights in `v`), ReLU after it unless `last`: [n × out].
fn forward(l: &Layer, v: &[Vec<f32>], x: &[f32], n: usize, last: bool) -> Vec<f32> {
    let mut y = Vec::with_capacity(n * l.outputs);
    for _ in 0..n {
        y.extend_from_slice(&v[l.at + 1]);
    }
    matmul(
        MatMut::from_row_major_slice_mut(&mut y, n, l.outputs),
        Accum::Add,
        MatRef::from_row_major_slice(x, n, l.inputs),
        MatRef::from_row_major_slice(&v[l.at], l.inputs, l.outputs),
        1.0f32,
        Par::Seq,
    );
    plain::clear_upper();
    if !last {
        y.iter_mut().for_each(|v| *v = v.max(0.0));
    }
    y
}

/// The backward pass of a layer (its weights in `v`) at input x [n × in] for the output
/// gradient g [n × out]: adds W's and b's gradients to `grads`; with `input`, returns x's
/// gradient (without, a product the caller would drop is not computed).
fn backward(
    l: &Layer,
    v: &[Vec<f32>],
    x: &[f32],
    g: &[f32],
    n: usize,
    grads: &mut [Vec<f32>],
    input: bool,
) -> Vec<f32> {
    let (i, o) = (l.inputs, l.outputs);
    let (gw, gb) = pair(grads, l.at);
    matmul(
        MatMut::from_row_major_slice_mut(gw, i, o),
        Accum::Add,
        MatRef::from_row_major_slice(x, n, i).transpose(),
        MatRef::from_row_major_slice(g, n, o),
        1.0f32,
        Par::Seq,
    );
    for row in g.chunks_exact(o) {
        gb.iter_mut().zip(row).for_each(|(b, g)| *b += g);
    }
    if !input {
        plain::clear_upper();
        return vec![];
    }
    let mut gx = vec![0.0f32; n * i];
    matmul(
        MatMut::from_row_major_slice_mut(&mut gx, n, i),
        Accum::Replace,
        MatRef::from_row_major_slice(g, n, o),
        MatRef::from_row_major_slice(&v[l.at], i, o).transpose(),
        1.0f32,
        Par::Seq,
    );
    plain::clear_upper();
    gx
}

/// g ⊙ [a > 0]: the gradient through a ReLU whose output was a.
fn through_relu(g: &mut [f32], a: &[f32]) {
    // A select rather than a branch: the compiler vectorises it.
    g.iter_mut().zip(a).for_each(|(g, &a)| *g = if a > 0.0 { *g } else { 0.0 });
}

/// What a conditioner's backward pass reads: each layer's input, and for residual
/// blocks their branch outputs and gates.
struct Tape {
    inputs: Vec<Vec<f32>>,
    branches: Vec<Vec<f32>>,
    gates: Vec<Vec<f32>>,
}

/// The weight and bias gradients of the layer whose weight is at `at`.
fn pair(g: &mut [Vec<f32>], at: usize) -> (&mut [f32], &mut [f32]) {
    let (w, rest) = g[at..].split_at_mut(1);
    (&mut w[0], &mut rest[0])
}

/// A conditioner's output [n × out] for its input [n × in] and the context [n × c].
fn conditioner(
    cfg: &FlowConfig,
    layers: &[Layer],
    v: &[Vec<f32>],
    input: Vec<f32>,
    ctx: &[f32],
    n: usize,
) -> (Vec<f32>, Tape) {
    let mut tape = Tape { inputs: vec![], branches: vec![], gates: vec![] };
    if cfg.blocks == 0 {
        let mut x = input;
        for (k, l) in layers.iter().enumerate() {
            let y = forward(l, v, &x, n, k + 1 == layers.len());
            tape.inputs.push(x);
            x = y;
        }
        return (x, tape);
    }
    // Layers: input, then per block (first, second, context gate), output.
    let mut h = forward(&layers[0], v, &input, n, true);
    tape.inputs.push(input);
    for k in 0..cfg.blocks {
        let p: Vec<f32> = h.iter().map(|v| v.max(0.0)).collect();
        let q = forward(&layers[1 + 3 * k], v, &p, n, false);
        let r = forward(&layers[2 + 3 * k], v, &q, n, true);
        let z = forward(&layers[3 + 3 * k], v, ctx, n, true);
        let mut s = vec![0.0f32; z.len()];
        plain::sigmoids(&z, &mut s, None);
        h.iter_mut().zip(r.iter().zip(&s)).for_each(|(h, (r, s))| *h += r * s);
        tape.inputs.extend([p, q]);
        tape.branches.push(r);
        tape.gates.push(s);
    }
    let out = forward(&layers[layers.len() - 1], v, &h, n, true);
    tape.inputs.push(h);
    (out, tape)
}

/// The conditioner's backward pass for its output gradient `g`: adds its weights'
/// gradients to `grads` and, when given `g_ctx`, the context's gradient to it; with
/// `input`, returns its input's.
#[allow(clippy::too_many_arguments)]
fn conditioner_back(
    cfg: &FlowConfig,
    (layers, v): (&[Layer], &[Vec<f32>]),
    tape: &Tape,
    ctx: &[f32],
    n: usize,
    g: Vec<f32>,
    grads: &mut [Vec<f32>],
    mut g_ctx: Option<&mut [f32]>,
    input: bool,
) -> Vec<f32> {
    let last = layers.len() - 1;
    if cfg.blocks == 0 {
        let mut g = g;
        for k in (0..layers.len()).rev() {
            let x = &tape.inputs[k];
            let mut gx = backward(&layers[k], v, x, &g, n, grads, k > 0 || input);
            if k > 0 {
                through_relu(&mut gx, x);
            }
            g = gx;
        }
        return g;
    }
    let mut gh = backward(&layers[last], v, &tape.inputs[1 + 2 * cfg.blocks], &g, n, grads, true);
    for k in (0..cfg.blocks).rev() {
        let (p, q) = (&tape.inputs[1 + 2 * k], &tape.inputs[2 + 2 * k]);
        let (r, s) = (&tape.branches[k], &tape.gates[k]);
        let gr: Vec<f32> = gh.iter().zip(s).map(|(g, s)| g * s).collect();
        let gz: Vec<f32> = gh.iter().zip(r.iter().zip(s)).map(|(g, (r, s))| g * r * s * (1.0 - s)).collect();
        let gc = backward(&layers[3 + 3 * k], v, ctx, &gz, n, grads, g_ctx.is_some());
        if let Some(g_ctx) = g_ctx.as_deref_mut() {
            g_ctx.iter_mut().zip(&gc).for_each(|(a, b)| *a += b);
        }
        let mut gq = backward(&layers[2 + 3 * k], v, q, &gr, n, grads, true);
        through_relu(&mut gq, q);
        let mut gp = backward(&layers[1 + 3 * k], v, p, &gq, n, grads, true);
        through_relu(&mut gp, p);
        gh.iter_mut().zip(&gp).for_each(|(a, b)| *a += b);
    }
    backward(&layers[0], v, &tape.inputs[0], &gh, n, grads, input)
}

/// One coupling's record for the backward pass.
struct Coupling {
    tape: Tape,
    jy: Vec<f32>,
    jl: Vec<f32>,
    /// The rows before the LU layer, when there is one.
    before_lu: Vec<f32>,
}

/// What the forward pass keeps for the backward one.
struct Record {
    /// Each embedding layer's input.
    emb_inputs: Vec<Vec<f32>>,
    /// The embedding's output, the conditioners' context [n × context].
    ctx: Vec<f32>,
    /// The rows at the base [n × dim].
    u: Vec<f32>,
    couplings: Vec<Coupling>,
}

/// −log q(v | inp) of each of `n` rows (v: standardised parameters [n × dim], inp: the
/// network's inputs [n × inputs], row-major), and with `record` what the backward pass
/// reads (without it the splines' Jacobians are not taken: the validation loss).
fn forward_pass(weights: &Weights, v: &[f32], inp: &[f32], n: usize, record: bool) -> (Vec<f64>, Record) {
    let cfg = &weights.cfg;
    let (d, (dc, dt)) = (cfg.dim, cfg.split());
    let np = spline::n_params(cfg.bins);
    let factor = raw_factors(cfg);
    let vals = &weights.values;
    let mut emb_inputs = vec![];
    let mut ctx = inp.to_vec();
    for (k, l) in weights.embedding.iter().enumerate() {
        let y = forward(l, vals, &ctx, n, k + 1 == weights.embedding.len());
        emb_inputs.push(std::mem::replace(&mut ctx, y));
    }
    let c = cfg.context();
    let mut u = v.to_vec();
    let mut logdet = vec![0.0f64; n];
    let mut couplings = vec![];
    for t in 0..cfg.transforms {
        let perm = &cfg.permutations[t];
        u = (0..n).flat_map(|i| perm.iter().map(move |&p| (i, p))).map(|(i, p)| u[i * d + p]).collect();
        let mut input = Vec::with_capacity(n * (dc + c));
        for i in 0..n {
            input.extend_from_slice(&u[i * d..i * d + dc]);
            input.extend_from_slice(&ctx[i * c..(i + 1) * c]);
        }
        let (mut raw, tape) = conditioner(cfg, &weights.conditioners[t], vals, input, &ctx, n);
        for r in raw.chunks_exact_mut(np) {
            r.iter_mut().zip(&factor).for_each(|(r, f)| *r *= f);
        }
        let x: Vec<f32> = (0..n).flat_map(|i| u[i * d + dc..(i + 1) * d].iter().copied()).collect();
        let (mut y, mut ld) = (vec![0.0f32; n * dt], vec![0.0f32; n * dt]);
        let jacobians = if record { n * dt * (np + 1) } else { 0 };
        let (mut jy, mut jl) = (vec![0.0f32; jacobians], vec![0.0f32; jacobians]);
        let wanted = record.then_some((&mut jy[..], &mut jl[..]));
        plain::spline_jacobians(&x, &raw, cfg.bins, cfg.bound, (&mut y, &mut ld), wanted);
        for i in 0..n {
            logdet[i] += ld[i * dt..(i + 1) * dt].iter().map(|&v| v as f64).sum::<f64>();
            u[i * d + dc..(i + 1) * d].copy_from_slice(&y[i * dt..(i + 1) * dt]);
        }
        let mut before_lu = vec![];
        if let Some(lu) = weights.lu.get(t) {
            let ld: f64 = lu.diag.iter().map(|&v| (v as f64).ln()).sum();
            let mut out = vec![0.0f32; n * d];
            for i in 0..n {
                let row = &u[i * d..(i + 1) * d];
                for r in 0..d {
                    let w = &lu.w[r * d..(r + 1) * d];
                    out[i * d + r] = vals[lu.at + 3][r] + w.iter().zip(row).map(|(w, x)| w * x).sum::<f32>();
                }
                logdet[i] += ld;
            }
            before_lu = std::mem::replace(&mut u, out);
        }
        if record {
            couplings.push(Coupling { tape, jy, jl, before_lu });
        }
    }
    let half_log_2pi = 0.5 * (2.0 * std::f64::consts::PI).ln();
    let losses = (0..n)
        .map(|i| {
            let sq: f64 = u[i * d..(i + 1) * d].iter().map(|&v| (v as f64).powi(2)).sum();
            0.5 * sq + d as f64 * half_log_2pi - logdet[i]
        })
        .collect();
    (losses, Record { emb_inputs, ctx, u, couplings })
}

/// The factor on each of a spline's raw parameters (the bin scale on widths and heights).
fn raw_factors(cfg: &FlowConfig) -> Vec<f32> {
    let np = spline::n_params(cfg.bins);
    (0..np).map(|k| if cfg.scaled_bins && k < 2 * cfg.bins { cfg.bin_scale() as f32 } else { 1.0 }).collect()
}

/// −log q(v | inp) of each of `n` rows, as [`loss_and_gradient`] takes it, without the
/// records of its backward pass.
pub fn row_losses(weights: &Weights, v: &[f32], inp: &[f32], n: usize) -> Vec<f64> {
    forward_pass(weights, v, inp, n, false).0
}

/// Mean −log q(v | inp) over `n` rows (v: standardised parameters [n × dim], inp: the
/// network's inputs [n × inputs], row-major) and its gradient with respect to every weight:
/// the value of burn's `Flow::log_prob(…).mean().neg()` and of its backward pass, up to
/// f32 rounding.
pub fn loss_and_gradient(weights: &Weights, v: &[f32], inp: &[f32], n: usize) -> (f64, Gradient) {
    let (losses, record) = forward_pass(weights, v, inp, n, true);
    let loss = losses.iter().sum::<f64>() / n as f64;
    (loss, backward_pass(weights, record, n))
}

/// The gradient of the mean −log q over the `n` rows whose forward pass left `record`.
fn backward_pass(weights: &Weights, record: Record, n: usize) -> Gradient {
    let cfg = &weights.cfg;
    let (d, (dc, dt)) = (cfg.dim, cfg.split());
    let np = spline::n_params(cfg.bins);
    let factor = raw_factors(cfg);
    let vals = &weights.values;
    let c = cfg.context();
    let Record { emb_inputs, ctx, u, couplings: tapes } = record;
    // Backward: ∂loss/∂u = u / n at the base; every row's log-determinant enters with −1/n.
    let mut grad = Gradient(weights.params.iter().map(|(_, s)| vec![0.0; s.iter().product()]).collect());
    let inv_n = 1.0 / n as f32;
    let g_ld = -inv_n;
    let mut g: Vec<f32> = u.iter().map(|&v| v * inv_n).collect();
    // The context's gradient reaches only an embedding's weights.
    let mut g_ctx = (!weights.embedding.is_empty()).then(|| vec![0.0f32; n * c]);
    for t in (0..cfg.transforms).rev() {
        let rec = &tapes[t];
        if let Some(lu) = weights.lu.get(t) {
            g = lu_back(lu, &rec.before_lu, g, n, d, &mut grad.0[lu.at..lu.at + 4]);
        }
        // The spline: x's and raw's gradients from their Jacobians.
        let mut g_raw = vec![0.0f32; n * dt * np];
        let mut g_x = vec![0.0f32; n * dt];
        for i in 0..n {
            for j in 0..dt {
                let e = i * dt + j;
                let gy = g[i * d + dc + j];
                let (jy, jl) = (&rec.jy[e * (np + 1)..(e + 1) * (np + 1)], &rec.jl[e * (np + 1)..(e + 1) * (np + 1)]);
                g_x[e] = gy * jy[np] + g_ld * jl[np];
                let out = &mut g_raw[e * np..(e + 1) * np];
                for (k, o) in out.iter_mut().enumerate() {
                    *o = (gy * jy[k] + g_ld * jl[k]) * factor[k];
                }
            }
        }
        // The conditioner's input is [a, context]: a's gradient is wanted where a coupling
        // comes before, the context's where an embedding does.
        let input = g_ctx.is_some() || t > 0;
        let layers = (&weights.conditioners[t][..], &vals[..]);
        let g_in = conditioner_back(cfg, layers, &rec.tape, &ctx, n, g_raw, &mut grad.0, g_ctx.as_deref_mut(), input);
        if let Some(g_ctx) = g_ctx.as_deref_mut() {
            for (gc, gi) in g_ctx.chunks_exact_mut(c).zip(g_in.chunks_exact(dc + c)) {
                gc.iter_mut().zip(&gi[dc..]).for_each(|(a, b)| *a += b);
            }
        }
        if t == 0 {
            break;
        }
        // u = [a, y] after the coupling; before it the permuted [a, x].
        let perm = &cfg.permutations[t];
        let mut before = vec![0.0f32; n * d];
        for i in 0..n {
            let gi = &g_in[i * (dc + c)..(i + 1) * (dc + c)];
            for k in 0..d {
                let gk = if k < dc { g[i * d + k] + gi[k] } else { g_x[i * dt + k - dc] };
                before[i * d + perm[k]] = gk;
            }
        }
        g = before;
    }
    let Some(mut gc) = g_ctx else { return grad };
    for k in (0..weights.embedding.len()).rev() {
        let x = &emb_inputs[k];
        let mut gx = backward(&weights.embedding[k], vals, x, &gc, n, &mut grad.0, k > 0);
        if k > 0 {
            through_relu(&mut gx, x);
        }
        gc = gx;
    }
    grad
}

/// The LU layer's backward pass: y = W x + b per row, W = L U, and −log |det W| in the
/// loss; adds the gradients of (lower, upper, diag, bias) to `out`, returns x's.
fn lu_back(lu: &Lu, x: &[f32], g: Vec<f32>, n: usize, d: usize, out: &mut [Vec<f32>]) -> Vec<f32> {
    let mut gw = vec![0.0f32; d * d];
    let mut gx = vec![0.0f32; n * d];
    for i in 0..n {
        let (gi, xi) = (&g[i * d..(i + 1) * d], &x[i * d..(i + 1) * d]);
        for r in 0..d {
            out[3][r] += gi[r];
            for k in 0..d {
                gw[r * d + k] += gi[r] * xi[k];
                gx[i * d + k] += gi[r] * lu.w[r * d + k];
            }
        }
    }
    // ∂/∂L = gW Uᵀ below the diagonal; ∂/∂U = Lᵀ gW on and above it.
    let ut: Vec<f32> = (0..d * d).map(|k| lu.u[(k % d) * d + k / d]).collect();
    let lt: Vec<f32> = (0..d * d).map(|k| lu.l[(k % d) * d + k / d]).collect();
    let gl = product(&gw, &ut, d);
    let gu = product(&lt, &gw, d);
    for r in 0..d {
        for col in 0..d {
            let k = r * d + col;
            if r > col {
                out[0][k] += gl[k];
            } else if r < col {
                out[1][k] += gu[k];
            }
        }
        // The diagonal softplus(s) + min; the loss holds −Σ log diag once per batch.
        out[2][r] += (gu[r * d + r] - 1.0 / lu.diag[r]) * lu.slope[r];
    }
    gx
}

#[cfg(test)]
mod tests {
    use super::*;
    use burn::optim::{AdamConfig, GradientsParams};

    /// The host's loss and gradient are burn's (its autodiff through `Flow::log_prob`) for
    /// every parameter tensor of every architecture the flow builds: plain and residual
    /// conditioners, LU layers, scaled bins, with and without an embedding, odd and even
    /// dimensions. Residual and LU flows take a few Adam steps first, so that their gates,
    /// second layers and triangles carry weight.
    #[test]
    fn the_host_gradient_is_burns() {
        let configs = [
            FlowConfig::new(3, 4, true),
            FlowConfig { scaled_bins: true, lu: true, ..FlowConfig::new(4, 3, true) },
            FlowConfig { blocks: 2, lu: true, scaled_bins: true, ..FlowConfig::new(5, 6, true) },
            FlowConfig { blocks: 1, ..FlowConfig::new(2, 2, false) },
            FlowConfig { lu: true, ..FlowConfig::new(2, 3, false) },
        ];
        for cfg in configs {
            let dev = Device::flex().autodiff();
            let mut flow = Flow::seeded(&cfg, &dev, Some(11));
            let n = 40;
            let (d, k) = (cfg.dim, cfg.inputs);
            let v: Vec<f32> = (0..n * d).map(|i| ((i * 7919 % 97) as f32 / 97.0 - 0.5) * 5.0).collect();
            let x: Vec<f32> = (0..n * k).map(|i| ((i * 104_729 % 89) as f32 / 89.0 - 0.5) * 2.0).collect();
            let loss = |flow: &Flow| {
                let xt = Tensor::<2>::from_data(TensorData::new(x.clone(), [n, k]), &dev);
                let vt = Tensor::<2>::from_data(TensorData::new(v.clone(), [n, d]), &dev);
                flow.log_prob(&cfg, vt, flow.embed(xt)).mean().neg()
            };
            let mut opt = AdamConfig::new().init();
            for _ in 0..if cfg.blocks > 0 || cfg.lu { 20 } else { 0 } {
                let grads = GradientsParams::from_grads(loss(&flow).backward(), &flow);
                flow = opt.step(1e-2, flow, grads);
            }
            let l = loss(&flow);
            let burn_loss = l.clone().try_into_vec_as::<f32>().unwrap()[0] as f64;
            let burn = GradientsParams::from_grads(l.backward(), &flow);
            let weights = Weights::of(&flow, &cfg);
            let (host_loss, host) = loss_and_gradient(&weights, &v, &x, n);
            assert!(
                (host_loss - burn_loss).abs() < 1e-4 * (1.0 + burn_loss.abs()),
                "{cfg:?}: loss {host_loss} vs {burn_loss}"
            );
            assert_eq!(host.0.len(), weights.params.len());
            for (j, ((id, shape), h)) in weights.params.iter().zip(&host.0).enumerate() {
                let b: Vec<f32> = match shape.len() {
                    1 => burn.get::<1>(*id).map(values),
                    _ => burn.get::<2>(*id).map(values),
                }
                .unwrap_or_else(|| vec![0.0; h.len()]);
                let scale = b.iter().fold(0.0f32, |m, v| m.max(v.abs()));
                assert!(scale > 0.0 || cfg.blocks == 0 && !cfg.lu, "{cfg:?}: tensor {j} has no gradient in burn");
                for (e, (h, b)) in h.iter().zip(&b).enumerate() {
                    assert!(
                        (h - b).abs() <= 1e-3 * scale + 1e-6,
                        "{cfg:?}: tensor {j} {shape:?} element {e}: host {h} vs burn {b}"
                    );
                }
            }
        }
    }
}
