//! The conditional neural spline flow on burn: an embedding MLP on the (standardised)
//! features, then coupling transforms whose rational-quadratic splines are set by small
//! MLPs of the untouched half and the embedding, with fixed permutations between them,
//! over a standard-normal base. No I/O here; `npe` owns data, training and checkpoints.

pub mod gradient;
pub mod plain;
pub mod spline;

use burn::module::Param;
use burn::nn::{Linear, LinearConfig};
use burn::prelude::*;
use burn::tensor::activation::{relu, softplus};
use serde::{Deserialize, Serialize};

/// Architecture; stored in checkpoints.
#[derive(Clone, Debug, Serialize, Deserialize, PartialEq)]
pub struct FlowConfig {
    /// Parameter dimension.
    pub dim: usize,
    /// Width of the network's input (features plus group-mask flags).
    pub inputs: usize,
    /// Embedding hidden widths; empty = no embedding (the input is the context).
    pub embedding: Vec<usize>,
    /// Coupling transforms, each with its own conditioner and permutation.
    pub transforms: usize,
    /// Hidden width of each conditioner (and of its residual blocks).
    pub hidden: usize,
    /// Spline bins per transformed coordinate: more bins bend the marginals more finely.
    pub bins: usize,
    /// Splines act on [−bound, bound] (standardised units) and are the identity outside.
    pub bound: f64,
    /// Conditioner: 0 = an MLP with two hidden layers of `hidden` units; n > 0 = a
    /// residual net of n blocks (as nflows' ResidualNet in sbi's NSF: each block two
    /// layers, its output gated by the context, the second layer started near zero).
    #[serde(default)]
    pub blocks: usize,
    /// Permutation applied before each transform.
    pub permutations: Vec<Vec<usize>>,
    /// A learned invertible linear map after each coupling (sbi's NSF has one: `LULinear`),
    /// so that scales, shifts and correlations of the parameters need not be bent into
    /// the bounded splines. Checkpoints from before it have none.
    #[serde(default)]
    pub lu: bool,
    /// The conditioners' raw bin widths and heights are divided by √hidden before their
    /// softmaxes, as nflows' spline couplings (sbi's NSF) do: the splines start near the
    /// identity and Adam moves their bins √hidden× more finely. Checkpoints from before
    /// it have none.
    #[serde(default)]
    pub scaled_bins: bool,
}

/// Flow settings the code cannot build, naming the setting.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
#[error("flow settings: {why}")]
pub struct FlowConfigError {
    /// The `FlowConfig` field at fault.
    pub field: &'static str,
    /// What it must be.
    pub why: &'static str,
}

impl FlowConfig {
    /// Checks settings read from a file: sizes the code can build (bins 2..=31 — the
    /// spline knots live in fixed arrays — positive widths, a positive tail bound, and
    /// one permutation of 0..dim per transform).
    pub fn validate(&self) -> Result<(), FlowConfigError> {
        let perm_ok = |p: &Vec<usize>| {
            let mut q = p.clone();
            q.sort_unstable();
            q.iter().copied().eq(0..self.dim)
        };
        let checks = [
            (self.dim >= 1 && self.dim <= 1000, "dim", "dim must be 1..=1000"),
            (self.inputs >= 1 && self.inputs <= 100_000, "inputs", "inputs must be 1..=100000"),
            ((2..=31).contains(&self.bins), "bins", "bins must be 2..=31"),
            ((1..=64).contains(&self.transforms), "transforms", "transforms must be 1..=64"),
            ((1..=4096).contains(&self.hidden), "hidden", "hidden must be 1..=4096"),
            (self.embedding.iter().all(|w| (1..=4096).contains(w)), "embedding", "embedding widths must be 1..=4096"),
            (self.bound.is_finite() && self.bound > 0.0, "bound", "bound must be finite and > 0"),
            (self.blocks <= 16, "blocks", "blocks must be 0..=16"),
            (self.permutations.len() == self.transforms, "permutations", "one permutation per transform"),
            (self.permutations.iter().all(perm_ok), "permutations", "each permutation must reorder 0..dim"),
        ];
        match checks.iter().find(|(ok, _, _)| !ok) {
            Some(&(_, field, why)) => Err(FlowConfigError { field, why }),
            None => Ok(()),
        }
    }

    /// The defaults of npe.md: 3×50 embedding, 5 transforms, 2×50 conditioners, 10 bins.
    pub fn new(dim: usize, inputs: usize, embedding: bool) -> FlowConfig {
        let transforms = 5;
        let permutations = permutations(dim, transforms);
        FlowConfig {
            dim,
            inputs,
            embedding: if embedding { vec![50, 50, 50] } else { vec![] },
            transforms,
            hidden: 50,
            bins: 10,
            bound: 5.0,
            blocks: 0,
            permutations,
            lu: false,
            scaled_bins: false,
        }
    }

    /// The factor on the raw bin widths and heights ([`FlowConfig::scaled_bins`]).
    fn bin_scale(&self) -> f64 {
        if self.scaled_bins { 1.0 / (self.hidden as f64).sqrt() } else { 1.0 }
    }

    fn context(&self) -> usize {
        self.embedding.last().copied().unwrap_or(self.inputs)
    }

    /// Dims left untouched (conditioning) and transformed per coupling.
    fn split(&self) -> (usize, usize) {
        let dc = self.dim / 2;
        (dc, self.dim - dc)
    }
}

/// Transform t sees the parameters in the order `order(t)[j] = (dim − 1 − j + t·s) mod dim`
/// (reversed, then rotated by s per transform) and transforms its second half; s is the
/// step that transforms every parameter most often (at least twice for dim ≥ 2 with 5
/// transforms). Each stored permutation takes the previous transform's order to this
/// one's, since `log_prob` applies them one after another.
///
/// Checkpoints before this (before v7) stored the orders themselves, which composed left
/// the last parameter of a model with 6 or more never transformed: its posterior was the
/// base distribution whatever the observation. They keep loading with their stored
/// permutations.
pub fn permutations(dim: usize, transforms: usize) -> Vec<Vec<usize>> {
    let order = |t: usize, s: usize| -> Vec<usize> { (0..dim).map(|j| (dim - 1 - j + t * s) % dim).collect() };
    let least = |s: usize| -> usize {
        let mut count = vec![0; dim];
        for t in 0..transforms {
            for &o in &order(t, s)[dim / 2..] {
                count[o] += 1;
            }
        }
        count.into_iter().min().unwrap_or(0)
    };
    let step = (1..=dim).max_by_key(|&s| (least(s), std::cmp::Reverse(s))).unwrap_or(1);
    let mut current: Vec<usize> = (0..dim).collect();
    (0..transforms)
        .map(|t| {
            let next = order(t, step);
            let mut position = vec![0; dim];
            for (i, &o) in current.iter().enumerate() {
                position[o] = i;
            }
            let relative = next.iter().map(|&o| position[o]).collect();
            current = next;
            relative
        })
        .collect()
}

/// Fully connected layers with ReLU between them (none after the last).
#[derive(Module, Debug)]
pub struct Mlp {
    layers: Vec<Linear>,
}

impl Mlp {
    /// Layers `sizes[0] → sizes[1] → …`, weights drawn by burn's default initialiser.
    pub fn new(sizes: &[usize], device: &Device) -> Mlp {
        Mlp { layers: sizes.windows(2).map(|w| LinearConfig::new(w[0], w[1]).init(device)).collect() }
    }

    /// The weights as plain f64 layers.
    fn dense(&self) -> Vec<plain::Dense> {
        self.layers
            .iter()
            .map(|l| {
                let w = l.weight.val();
                let [i, o] = w.dims();
                let w: Vec<f32> = w.try_into_vec_as::<f32>().expect("weights");
                let b: Vec<f32> = l
                    .bias
                    .as_ref()
                    .map(|b| b.val().try_into_vec_as::<f32>().expect("bias"))
                    .unwrap_or_else(|| vec![0.0; o]);
                plain::Dense {
                    w: faer::Mat::from_fn(i, o, |r, c| w[r * o + c] as f64),
                    b: b.into_iter().map(f64::from).collect(),
                }
            })
            .collect()
    }

    /// The layers applied to a batch.
    ///
    /// # Shapes
    /// x: [batch, sizes[0]] → [batch, sizes[last]].
    pub fn forward(&self, mut x: Tensor<2>) -> Tensor<2> {
        let n = self.layers.len();
        for (i, l) in self.layers.iter().enumerate() {
            x = l.forward(x);
            if i + 1 < n {
                x = relu(x);
            }
        }
        x
    }
}

/// σ(x), the residual blocks' context gate, computed on the host ([`plain::sigmoids`]);
/// with autodiff its value and gradient come from the tangent line at x, slope·x + offset
/// (two tensor ops, the gradient slope·grad). burn's sigmoid took a quarter of a
/// two-moons training in libm's `expf` (training now takes its gradient on the host,
/// [`gradient`]).
fn gate(x: Tensor<2>) -> Tensor<2> {
    let dims = x.dims();
    let device = x.device();
    let xs: Vec<f32> = x.clone().try_into_vec_as::<f32>().expect("gate input");
    let mut s = vec![0.0f32; xs.len()];
    let tensor = |v: Vec<f32>| Tensor::<2>::from_data(TensorData::new(v, dims), &device);
    if !x.is_tracked() {
        plain::sigmoids(&xs, &mut s, None);
        return tensor(s);
    }
    let (mut slope, mut offset) = (vec![0.0f32; xs.len()], vec![0.0f32; xs.len()]);
    plain::sigmoids(&xs, &mut s, Some((&mut slope, &mut offset)));
    x * tensor(slope) + tensor(offset)
}

/// Initialises every lazy parameter it visits.
struct DrawNow;

impl burn::module::ModuleVisitor for DrawNow {
    fn visit_float<const D: usize>(&mut self, param: &Param<Tensor<D>>) {
        let _ = param.val();
    }
}

/// Smallest diagonal entry of an LU layer's U: keeps W invertible.
pub const LU_MIN_DIAG: f64 = 1e-3;

/// y = W u + b with W = L U: L unit lower-triangular, U upper-triangular with the
/// diagonal softplus(s) + [`LU_MIN_DIAG`] > 0, so W is invertible and log |det W| =
/// Σ log diag. Starts as the identity.
#[derive(Module, Debug)]
pub struct LuLinear {
    lower: Param<Tensor<2>>,
    upper: Param<Tensor<2>>,
    diag: Param<Tensor<1>>,
    bias: Param<Tensor<1>>,
}

impl LuLinear {
    /// The identity map on `d` dims.
    fn identity(d: usize, device: &Device) -> LuLinear {
        // softplus(s) + min = 1.
        let s = ((1.0 - LU_MIN_DIAG).exp() - 1.0).ln();
        LuLinear {
            lower: Param::from_tensor(Tensor::zeros([d, d], device)),
            upper: Param::from_tensor(Tensor::zeros([d, d], device)),
            diag: Param::from_tensor(Tensor::full([d], s, device)),
            bias: Param::from_tensor(Tensor::zeros([d], device)),
        }
    }

    fn diagonal(&self) -> Tensor<1> {
        softplus(self.diag.val(), 1.0) + LU_MIN_DIAG
    }

    /// W = L U.
    fn weight(&self) -> Tensor<2> {
        let [d, _] = self.lower.val().dims();
        let device = self.lower.val().device();
        let eye = Tensor::<2>::eye(d, &device);
        let l = self.lower.val().tril(-1) + eye.clone();
        let u = self.upper.val().triu(1) + eye * self.diagonal().reshape([1, d]);
        l.matmul(u)
    }

    /// u [B, d] → (u Wᵀ + b, log |det W|).
    fn forward(&self, u: Tensor<2>) -> (Tensor<2>, Tensor<1>) {
        let [_, d] = u.dims();
        let y = u.matmul(self.weight().transpose()) + self.bias.val().reshape([1, d]);
        (y, self.diagonal().log().sum())
    }

    /// W, b and log |det W| in f64 for the plain path.
    fn dense(&self) -> plain::Affine {
        let [d, _] = self.lower.val().dims();
        let w: Vec<f32> = self.weight().try_into_vec_as::<f32>().expect("LU weight");
        let b: Vec<f32> = self.bias.val().try_into_vec_as::<f32>().expect("LU bias");
        let diag: Vec<f32> = self.diagonal().try_into_vec_as::<f32>().expect("LU diagonal");
        plain::Affine::new(
            faer::Mat::from_fn(d, d, |r, c| w[r * d + c] as f64),
            b.into_iter().map(f64::from).collect(),
            diag.iter().map(|&v| (v as f64).ln()).sum(),
        )
    }
}

/// The trainable flow: the embedding net, one conditioner per coupling transform and,
/// with [`FlowConfig::lu`], an LU layer after each.
#[derive(Module, Debug)]
pub struct Flow {
    embedding: Mlp,
    conditioners: Vec<Mlp>,
    lu: Vec<LuLinear>,
}

impl Flow {
    /// A flow of architecture `cfg` with freshly drawn weights (residual conditioners
    /// start their blocks' second layers near zero, so each block starts near identity).
    pub fn new(cfg: &FlowConfig, device: &Device) -> Flow {
        let mut emb = vec![cfg.inputs];
        emb.extend(&cfg.embedding);
        let (dc, dt) = cfg.split();
        let cond = [dc + cfg.context(), cfg.hidden, cfg.hidden, dt * spline::n_params(cfg.bins)];
        let conditioner = || {
            if cfg.blocks == 0 {
                return Mlp::new(&cond, device);
            }
            // Layers in order: input, then per block (first, second, context gate), output.
            let (h, c) = (cfg.hidden, cfg.context());
            let small = burn::nn::Initializer::Uniform { min: -1e-3, max: 1e-3 };
            let mut layers = vec![LinearConfig::new(dc + c, h).init(device)];
            for _ in 0..cfg.blocks {
                layers.push(LinearConfig::new(h, h).init(device));
                layers.push(LinearConfig::new(h, h).with_initializer(small.clone()).init(device));
                layers.push(LinearConfig::new(c, h).init(device));
            }
            layers.push(LinearConfig::new(h, dt * spline::n_params(cfg.bins)).init(device));
            Mlp { layers }
        };
        let lu =
            if cfg.lu { (0..cfg.transforms).map(|_| LuLinear::identity(cfg.dim, device)).collect() } else { vec![] };
        Flow {
            embedding: Mlp::new(&emb, device),
            conditioners: (0..cfg.transforms).map(|_| conditioner()).collect(),
            lu,
        }
    }

    /// [`Flow::new`] with every weight drawn now, from `seed` when given, under a lock
    /// that other seeded constructions (trainings, tests) share: burn draws a parameter
    /// lazily, at its first use, from one RNG per device, so a draw left for later, or
    /// made while another thread re-seeds, would not follow the seed.
    pub fn seeded(cfg: &FlowConfig, device: &Device, seed: Option<u64>) -> Flow {
        static INIT: std::sync::Mutex<()> = std::sync::Mutex::new(());
        let _one_at_a_time = INIT.lock().unwrap_or_else(|e| e.into_inner());
        if let Some(seed) = seed {
            device.seed(seed);
        }
        let flow = Flow::new(cfg, device);
        flow.visit(&mut DrawNow);
        flow
    }

    /// A plain-Rust copy for inference.
    pub fn plain(&self, cfg: &FlowConfig) -> plain::PlainFlow {
        // The bin scale folded into each conditioner's output layer: the plain path reads
        // raw parameters as they are.
        let np = spline::n_params(cfg.bins);
        let conditioner = |c: &Mlp| {
            let mut layers = c.dense();
            if let Some(out) = layers.last_mut().filter(|_| cfg.scaled_bins) {
                for col in (0..out.b.len()).filter(|col| col % np < 2 * cfg.bins) {
                    out.b[col] *= cfg.bin_scale();
                    for row in 0..out.w.nrows() {
                        out.w[(row, col)] *= cfg.bin_scale();
                    }
                }
            }
            layers
        };
        plain::PlainFlow {
            cfg: cfg.clone(),
            embedding: self.embedding.dense(),
            conditioners: self.conditioners.iter().map(conditioner).collect(),
            lu: self.lu.iter().map(LuLinear::dense).collect(),
        }
    }

    /// The context the conditioners see: the embedding of the (standardised) inputs, or
    /// the inputs themselves without an embedding.
    ///
    /// # Shapes
    /// x: [batch, inputs] → [batch, context].
    pub fn embed(&self, x: Tensor<2>) -> Tensor<2> {
        self.embedding.forward(x)
    }

    fn spline_params(&self, cfg: &FlowConfig, t: usize, a: Tensor<2>, ctx: Tensor<2>) -> Tensor<3> {
        let [b, _] = ctx.dims();
        let (dc, dt) = cfg.split();
        let input = if dc == 0 { ctx.clone() } else { Tensor::cat(vec![a, ctx.clone()], 1) };
        let out = if cfg.blocks == 0 {
            self.conditioners[t].forward(input)
        } else {
            let l = &self.conditioners[t].layers;
            let mut h = l[0].forward(input);
            for k in 0..cfg.blocks {
                let r = l[1 + 3 * k].forward(relu(h.clone()));
                let r = l[2 + 3 * k].forward(relu(r));
                h = h + r * gate(l[3 + 3 * k].forward(ctx.clone()));
            }
            l[l.len() - 1].forward(h)
        };
        let np = spline::n_params(cfg.bins);
        let out = out.reshape([b, dt, np]);
        if !cfg.scaled_bins {
            return out;
        }
        let f = cfg.bin_scale() as f32;
        let scale: Vec<f32> = (0..np).map(|k| if k < 2 * cfg.bins { f } else { 1.0 }).collect();
        out * Tensor::<1>::from_data(TensorData::new(scale, [np]), &ctx.device()).reshape([1, 1, np])
    }

    /// log q(u | context) for standardised parameters u [B, D] and embedded context [B, C].
    pub fn log_prob(&self, cfg: &FlowConfig, mut u: Tensor<2>, ctx: Tensor<2>) -> Tensor<1> {
        let device = u.device();
        let (dc, dt) = cfg.split();
        let [b, d] = u.dims();
        let mut logdet = Tensor::<1>::zeros([b], &device);
        for t in 0..cfg.transforms {
            let perm = Tensor::<1, Int>::from_data(
                TensorData::new(cfg.permutations[t].iter().map(|&i| i as i64).collect::<Vec<_>>(), [d]),
                &device,
            );
            u = u.select(1, perm);
            let a = u.clone().narrow(1, 0, dc);
            let x = u.narrow(1, dc, dt);
            let raw = self.spline_params(cfg, t, a.clone(), ctx.clone());
            let (y, ld) = spline::forward(x, raw, cfg.bins, cfg.bound);
            logdet = logdet + ld.sum_dim(1).reshape([b]);
            u = if dc == 0 { y } else { Tensor::cat(vec![a, y], 1) };
            if let Some(lu) = self.lu.get(t) {
                let (y, ld) = lu.forward(u);
                u = y;
                logdet = logdet + ld;
            }
        }
        let base =
            (u.powi_scalar(2).sum_dim(1).reshape([b]) * -0.5) - 0.5 * d as f64 * (2.0 * std::f64::consts::PI).ln();
        base + logdet
    }

    /// Maps base draws z [B, D] to standardised parameters (the inverse direction).
    pub fn sample_from(&self, cfg: &FlowConfig, mut z: Tensor<2>, ctx: Tensor<2>) -> Tensor<2> {
        let device = z.device();
        let (dc, dt) = cfg.split();
        let d = cfg.dim;
        for t in (0..cfg.transforms).rev() {
            if let Some(lu) = self.lu.get(t) {
                // u = W⁻¹ (y − b), W⁻¹ formed on the host (d is small).
                let inv = lu.dense().inverse_row_major();
                let inv: Vec<f32> = inv.into_iter().map(|v| v as f32).collect();
                let inv = Tensor::<2>::from_data(TensorData::new(inv, [d, d]), &device);
                z = (z - lu.bias.val().reshape([1, d])).matmul(inv.transpose());
            }
            let a = z.clone().narrow(1, 0, dc);
            let y = z.narrow(1, dc, dt);
            let raw = self.spline_params(cfg, t, a.clone(), ctx.clone());
            let x = spline::inverse(y, raw, cfg.bins, cfg.bound);
            z = if dc == 0 { x } else { Tensor::cat(vec![a, x], 1) };
            let mut inv = vec![0i64; d];
            for (k, &p) in cfg.permutations[t].iter().enumerate() {
                inv[p] = k as i64;
            }
            z = z.select(1, Tensor::<1, Int>::from_data(TensorData::new(inv, [d]), &device));
        }
        z
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use burn::optim::{AdamConfig, GradientsParams};

    /// Applied one after another, the permutations leave every parameter in a transformed
    /// half at least twice (once they left the last of 6 or more untouched).
    #[test]
    fn every_parameter_is_transformed_at_least_twice() {
        for dim in 2..=40 {
            let cfg = FlowConfig::new(dim, 3, false);
            cfg.validate().unwrap();
            let mut order: Vec<usize> = (0..dim).collect();
            let mut count = vec![0; dim];
            for p in &cfg.permutations {
                order = p.iter().map(|&j| order[j]).collect();
                for &o in &order[dim / 2..] {
                    count[o] += 1;
                }
            }
            assert!(count.iter().all(|&c| c >= 2), "dim {dim}: transformed {count:?} times");
        }
    }

    /// One Adam step on the negative log-likelihood moves every weight matrix and bias of
    /// the embedding and of every conditioner: the gradient reaches all of them.
    #[test]
    fn gradient_reaches_every_layer() {
        let dev = Device::flex().autodiff();
        let cfg = FlowConfig::new(7, 12, true);
        // Seeded: a draw with many dead ReLUs failed the count now and then.
        let flow = Flow::seeded(&cfg, &dev, Some(7));
        let before = flow.plain(&cfg);
        let n = 32;
        let u: Vec<f32> = (0..n * 7).map(|i| ((i * 7919 % 97) as f32 / 97.0 - 0.5) * 4.0).collect();
        let x: Vec<f32> = (0..n * 12).map(|i| ((i * 104_729 % 89) as f32 / 89.0 - 0.5) * 2.0).collect();
        let ctx = flow.embed(Tensor::<2>::from_data(TensorData::new(x, [n, 12]), &dev));
        let loss = flow.log_prob(&cfg, Tensor::<2>::from_data(TensorData::new(u, [n, 7]), &dev), ctx).mean().neg();
        let grads = GradientsParams::from_grads(loss.backward(), &flow);
        let mut opt = AdamConfig::new().init();
        let after = opt.step(1e-3, flow, grads).plain(&cfg);
        let moved = |a: &plain::Dense, b: &plain::Dense| {
            let w = (0..a.w.nrows())
                .flat_map(|i| (0..a.w.ncols()).map(move |j| (i, j)))
                .filter(|&(i, j)| a.w[(i, j)] != b.w[(i, j)])
                .count();
            let bias = a.b.iter().zip(&b.b).filter(|(p, q)| p != q).count();
            (w, bias)
        };
        let layers = before.embedding.iter().zip(&after.embedding).map(|(a, b)| ("embedding", a, b));
        let layers = layers.chain(
            before
                .conditioners
                .iter()
                .zip(&after.conditioners)
                .flat_map(|(a, b)| a.iter().zip(b).map(|(a, b)| ("conditioner", a, b))),
        );
        let mut count = 0;
        for (k, (what, a, b)) in layers.enumerate() {
            let (w, bias) = moved(a, b);
            assert!(
                w > a.w.nrows() * a.w.ncols() / 2,
                "{what} layer {k}: only {w} of {} weights moved",
                a.w.nrows() * a.w.ncols()
            );
            assert!(bias > 0, "{what} layer {k}: no bias moved");
            count += 1;
        }
        assert_eq!(count, 3 + 5 * 3);
    }

    /// burn's gradient of the training loss (mean −log q over a batch, through the
    /// embedding, the conditioners' softmaxes, cumulative sums and gathers, f32) against
    /// central differences of the same loss on the plain f64 path, for every bias of the
    /// embedding's last layer and of each conditioner's output layer, with and without
    /// scaled bins: a wrong backward pass would train a worse flow with no other symptom.
    #[test]
    fn training_gradient_matches_finite_differences() {
        let configs = [
            FlowConfig::new(3, 2, true),
            FlowConfig { scaled_bins: true, ..FlowConfig::new(3, 2, true) },
            // Residual conditioners: the context reaches them through the host-side gates.
            FlowConfig { blocks: 2, lu: true, ..FlowConfig::new(3, 2, true) },
        ];
        for cfg in configs {
            let dev = Device::flex().autodiff();
            let mut flow = Flow::seeded(&cfg, &dev, Some(5));
            let n = 24;
            let u: Vec<f32> = (0..n * 3).map(|i| ((i * 7919 % 97) as f32 / 97.0 - 0.5) * 3.0).collect();
            let x: Vec<f32> = (0..n * 2).map(|i| ((i * 104_729 % 89) as f32 / 89.0 - 0.5) * 2.0).collect();
            let tensors = || {
                let x = Tensor::<2>::from_data(TensorData::new(x.clone(), [n, 2]), &dev);
                (x, Tensor::<2>::from_data(TensorData::new(u.clone(), [n, 3]), &dev))
            };
            // Residual blocks start with their second layers near zero, which hides the
            // gates: a few Adam steps first give them weight.
            let mut opt = AdamConfig::new().init();
            for _ in 0..if cfg.blocks > 0 { 30 } else { 0 } {
                let (xt, ut) = tensors();
                let loss = flow.log_prob(&cfg, ut, flow.embed(xt)).mean().neg();
                let grads = GradientsParams::from_grads(loss.backward(), &flow);
                flow = opt.step(1e-2, flow, grads);
            }
            let (xt, ut) = tensors();
            let loss = flow.log_prob(&cfg, ut, flow.embed(xt)).mean().neg();
            let grads = loss.backward();
            let bias_grad = |l: &Linear| -> Vec<f32> {
                l.bias.as_ref().unwrap().val().grad(&grads).unwrap().try_into_vec_as::<f32>().unwrap()
            };
            let plain = flow.plain(&cfg);
            let loss_of = |p: &plain::PlainFlow| -> f64 {
                (0..n)
                    .map(|i| {
                        let xi: Vec<f64> = x[2 * i..2 * i + 2].iter().map(|&v| v as f64).collect();
                        let ui: Vec<f64> = u[3 * i..3 * i + 3].iter().map(|&v| v as f64).collect();
                        -p.bind(&xi).log_prob(&ui)[0]
                    })
                    .sum::<f64>()
                    / n as f64
            };
            // The plain copy (the bin scale folded into its output layers) has burn's loss.
            let burn_loss = loss.clone().try_into_vec_as::<f32>().unwrap()[0] as f64;
            assert!((loss_of(&plain) - burn_loss).abs() < 1e-4, "plain {} vs burn {burn_loss}", loss_of(&plain));
            let h = 1e-5;
            let mut checked = 0;
            let mut check = |burn: Vec<f32>, edit: &dyn Fn(&mut plain::PlainFlow, usize, f64)| {
                for (j, g) in burn.iter().enumerate() {
                    let (mut up, mut down) = (plain.clone(), plain.clone());
                    edit(&mut up, j, h);
                    edit(&mut down, j, -h);
                    let fd = (loss_of(&up) - loss_of(&down)) / (2.0 * h);
                    let g = *g as f64;
                    assert!((fd - g).abs() < 2e-5 + 2e-3 * fd.abs(), "{cfg:?} parameter {j}: burn {g} vs {fd}");
                    checked += 1;
                }
            };
            let last = cfg.embedding.len() - 1;
            check(bias_grad(&flow.embedding.layers[last]), &|p, j, e| p.embedding[last].b[j] += e);
            let np = spline::n_params(cfg.bins);
            let out_layer = flow.conditioners[0].layers.len() - 1;
            for t in 0..cfg.transforms {
                let out = &flow.conditioners[t].layers[out_layer];
                // The plain copy holds the output layer times the bin scale.
                let scale = |j: usize| if j % np < 2 * cfg.bins { cfg.bin_scale() } else { 1.0 };
                let burn: Vec<f32> = bias_grad(out).into_iter().enumerate().map(|(j, g)| g / scale(j) as f32).collect();
                check(burn, &|p, j, e| p.conditioners[t][out_layer].b[j] += e);
            }
            assert_eq!(checked, 50 + 5 * 2 * np);
        }
    }
}
