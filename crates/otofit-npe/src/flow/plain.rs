//! The trained flow's inference path in plain f64 Rust (faer matmuls): posterior draws
//! with their log-densities in one inverse pass, and log-densities of given points.
//! burn trains and stores the flow; this copy of its weights serves `infer`, where
//! burn's per-op overhead on small tensors dominated (see docs/npe.md). A test checks
//! both paths agree. The draws' conditioners run in f32 (the weights are burn's f32):
//! twice the SIMD lanes, −1.3 ms of a `POST /infer` (docs/service.md).

use super::FlowConfig;
use faer::linalg::matmul::matmul;
use faer::traits::{ComplexField, Conjugate};
use faer::{Accum, Mat, MatMut, MatRef, Par};
use std::sync::OnceLock;

mod lane_jacobians;
mod lanes;

use super::spline::{MIN_DERIVATIVE, MIN_HEIGHT, MIN_WIDTH};

/// One linear layer: y = x W + b, W [in × out].
#[derive(Clone, Debug)]
pub struct Dense<T = f64> {
    /// Weights, [in × out] (burn's layout).
    pub w: Mat<T>,
    /// Bias, one per output.
    pub b: Vec<T>,
}

/// The float types the layers run in: f64 everywhere, f32 for the conditioners of the
/// sampling pass (twice the SIMD lanes; see [`Bound::sample`]).
trait Real: ComplexField + Conjugate<Canonical = Self> + Copy + PartialOrd + std::ops::AddAssign {
    const ZERO: Self;
    const ONE: Self;
}

impl Real for f64 {
    const ZERO: f64 = 0.0;
    const ONE: f64 = 1.0;
}

impl Real for f32 {
    const ZERO: f32 = 0.0;
    const ONE: f32 = 1.0;
}

/// ReLU; NaN maps to 0 as `f64::max` does.
#[inline(always)]
fn relu<T: Real>(v: T) -> T {
    if v > T::ZERO { v } else { T::ZERO }
}

/// A batch through a layer: x is [in × n] column-major (each sample contiguous), the
/// result [out × n]; `bias` added, then ReLU unless `last`.
fn batch_forward<T: Real>(w: MatRef<'_, T>, bias: &[T], x: &[T], n: usize, last: bool) -> Vec<T> {
    let (o, i) = (w.ncols(), w.nrows());
    // The bias first and the product added to it: no zeroing pass, no bias pass.
    let mut y: Vec<T> = Vec::with_capacity(o * n);
    for _ in 0..n {
        y.extend_from_slice(&bias[..o]);
    }
    matmul(
        MatMut::from_column_major_slice_mut(&mut y, o, n),
        Accum::Add,
        w.transpose(),
        MatRef::from_column_major_slice(x, i, n),
        T::ONE,
        Par::Seq,
    );
    clear_upper();
    if !last {
        y.iter_mut().for_each(|v| *v = relu(*v));
    }
    y
}

/// [`batch_forward`] of a last layer (no ReLU), the result transposed: [n × out]
/// column-major, one output of every sample contiguous (the layout of [`lanes`]).
fn batch_forward_t<T: Real>(w: MatRef<'_, T>, bias: &[T], x: &[T], n: usize) -> Vec<T> {
    let (i, o) = (w.nrows(), w.ncols());
    let mut y: Vec<T> = Vec::with_capacity(n * o);
    for &b in &bias[..o] {
        y.extend(std::iter::repeat_n(b, n));
    }
    matmul(
        MatMut::from_column_major_slice_mut(&mut y, n, o),
        Accum::Add,
        MatRef::from_column_major_slice(x, i, n).transpose(),
        w,
        T::ONE,
        Par::Seq,
    );
    clear_upper();
    y
}

/// The gradient through a layer's weights: W g for g [out × n] (column-major), [in × n].
fn back(w: MatRef<'_, f64>, g: &[f64], n: usize) -> Vec<f64> {
    let (i, o) = (w.nrows(), w.ncols());
    let mut out = vec![0.0; i * n];
    matmul(
        MatMut::from_column_major_slice_mut(&mut out, i, n),
        Accum::Replace,
        w,
        MatRef::from_column_major_slice(g, o, n),
        1.0,
        Par::Seq,
    );
    clear_upper();
    out
}

/// Clears the upper halves of the vector registers (`vzeroupper`). faer's matmul kernels
/// (AVX-512 on this project's hosts) return with them dirty, and the SSE code compiled for
/// baseline x86-64 that runs after them — the rest of this file, and the simulator of the
/// fit check on the same thread — then ran 2–3× slower (measured: `DrumModes::schur` 2.8×,
/// a whole `POST /infer` 33 → 19 ms of CPU on one thread, `otofit bench infer --direct`).
#[inline]
pub(super) fn clear_upper() {
    #[cfg(target_arch = "x86_64")]
    if std::arch::is_x86_feature_detected!("avx") {
        // SAFETY: the CPU has AVX (just detected).
        unsafe { zeroupper() }
    }
}

#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx")]
fn zeroupper() {
    std::arch::x86_64::_mm256_zeroupper();
}

/// An invertible affine map on each row: y = W u + b (a trained LU layer), with W⁻¹ and
/// log |det W| computed once.
#[derive(Clone, Debug)]
pub struct Affine {
    w: Mat<f64>,
    inv: Mat<f64>,
    b: Vec<f64>,
    logdet: f64,
}

impl Affine {
    /// The map of weight `w` (square, invertible), bias `b` and log |det w|.
    pub fn new(w: Mat<f64>, b: Vec<f64>, logdet: f64) -> Affine {
        let inv = invert(&w);
        Affine { w, inv, b, logdet }
    }

    /// W⁻¹ row by row (for burn's sampling path in tests).
    pub fn inverse_row_major(&self) -> Vec<f64> {
        let d = self.b.len();
        (0..d * d).map(|k| self.inv[(k / d, k % d)]).collect()
    }

    /// Every row u of `rows` (d wide) to W u + b, or back to W⁻¹ (u − b).
    fn apply(&self, rows: &mut [f64], inverse: bool) {
        let d = self.b.len();
        let mut tmp = vec![0.0; d];
        let m = if inverse { &self.inv } else { &self.w };
        for row in rows.chunks_exact_mut(d) {
            if inverse {
                row.iter_mut().zip(&self.b).for_each(|(v, b)| *v -= b);
            }
            for (i, t) in tmp.iter_mut().enumerate() {
                *t = (0..d).map(|j| m[(i, j)] * row[j]).sum::<f64>();
            }
            if !inverse {
                tmp.iter_mut().zip(&self.b).for_each(|(v, b)| *v += b);
            }
            row.copy_from_slice(&tmp);
        }
    }

    /// A gradient with respect to y back to u: g ← Wᵀ g, row by row.
    fn back(&self, g: &mut [f64]) {
        let d = self.b.len();
        let mut tmp = vec![0.0; d];
        for row in g.chunks_exact_mut(d) {
            for (j, t) in tmp.iter_mut().enumerate() {
                *t = (0..d).map(|i| self.w[(i, j)] * row[i]).sum::<f64>();
            }
            row.copy_from_slice(&tmp);
        }
    }
}

/// The inverse of a small invertible matrix, through faer's LU with partial pivoting (an
/// LU layer's W = L U is well conditioned: its U diagonal is ≥ 1e-3).
fn invert(w: &Mat<f64>) -> Mat<f64> {
    use faer::linalg::solvers::Solve;
    w.partial_piv_lu().solve(Mat::<f64>::identity(w.nrows(), w.nrows()))
}

/// The flow's weights and architecture.
#[derive(Clone, Debug)]
pub struct PlainFlow {
    /// The architecture the weights belong to.
    pub cfg: FlowConfig,
    /// The embedding net's layers (empty: no embedding).
    pub embedding: Vec<Dense>,
    /// Each coupling transform's conditioner, layer by layer.
    pub conditioners: Vec<Vec<Dense>>,
    /// The LU layer after each coupling transform (empty: none).
    pub lu: Vec<Affine>,
}

/// The flow bound to one observation: the embedding and each conditioner's context
/// term (first layer's context rows × context + bias) computed once.
pub struct Bound<'a> {
    flow: &'a PlainFlow,
    ctx_bias: Vec<Vec<f64>>,
    /// Residual conditioners: each block's context gate σ(W h + b), per conditioner.
    gates: Vec<Vec<Vec<f64>>>,
    /// The conditioners in f32 for [`Bound::sample`], made on its first call (after any
    /// edit of the flow's f64 weights, which tests make).
    narrow: OnceLock<Narrow>,
    /// Standard deviation of the base distribution (1: the flow as trained; > 1 widens
    /// the posterior, the post-hoc recalibration of `npe::calibrate`).
    temperature: f64,
}

/// Every conditioner's layers, context term and gates in f32.
struct Narrow {
    layers: Vec<Vec<Dense<f32>>>,
    ctx_bias: Vec<Vec<f32>>,
    gates: Vec<Vec<Vec<f32>>>,
}

/// One conditioner bound to the observation, in f64 or f32.
struct Conditioner<'c, T> {
    layers: &'c [Dense<T>],
    /// The first layer's bias plus its context rows times the embedded observation.
    ctx_bias: &'c [T],
    /// Residual blocks' context gates.
    gates: &'c [Vec<T>],
}

impl<T: Real> Conditioner<'_, T> {
    /// Raw spline parameters [P × n] (P = dt·(3K−1)) for the untouched parts `a` [dc × n]
    /// (`transposed`: [n × P], the layout of [`lanes`]), keeping in `acts` what the
    /// gradient needs: the input of every layer after the first (MLP), or each residual
    /// block's state h and inner activation s, then the final h.
    fn raw(
        &self,
        dc: usize,
        blocks: usize,
        a: &[T],
        n: usize,
        mut acts: Option<&mut Vec<Vec<T>>>,
        transposed: bool,
    ) -> Vec<T> {
        let layers = self.layers;
        let mut keep = |v: &Vec<T>| {
            if let Some(acts) = acts.as_deref_mut() {
                acts.push(v.clone());
            }
        };
        // First layer: the untouched rows of W on `a`, plus the folded context term.
        let mut h = batch_forward(layers[0].w.as_ref().subrows(0, dc), self.ctx_bias, a, n, blocks > 0);
        let last = layers.len() - 1;
        if blocks > 0 {
            let width = layers[0].w.ncols();
            for (k, gate) in self.gates.iter().enumerate().take(blocks) {
                keep(&h);
                let relu: Vec<T> = h.iter().map(|&v| relu(v)).collect();
                let (l1, l2) = (&layers[1 + 3 * k], &layers[2 + 3 * k]);
                let r = batch_forward(l1.w.as_ref(), &l1.b, &relu, n, false);
                keep(&r);
                let r = batch_forward(l2.w.as_ref(), &l2.b, &r, n, true);
                for (hc, rc) in h.chunks_exact_mut(width).zip(r.chunks_exact(width)) {
                    for ((hv, &rv), &g) in hc.iter_mut().zip(rc).zip(gate) {
                        *hv += rv * g;
                    }
                }
            }
        } else {
            for l in &layers[1..last] {
                keep(&h);
                h = batch_forward(l.w.as_ref(), &l.b, &h, n, false);
            }
        }
        keep(&h);
        let l = &layers[last];
        if transposed {
            batch_forward_t(l.w.as_ref(), &l.b, &h, n)
        } else {
            batch_forward(l.w.as_ref(), &l.b, &h, n, true)
        }
    }
}

impl PlainFlow {
    /// Embeds one input row and folds it into each conditioner's first layer.
    pub fn bind(&self, input: &[f64]) -> Bound<'_> {
        let mut h = input.to_vec();
        let last = self.embedding.len().saturating_sub(1);
        for (i, l) in self.embedding.iter().enumerate() {
            h = batch_forward(l.w.as_ref(), &l.b, &h, 1, i == last);
        }
        let dc = self.cfg.dim / 2;
        // The context rows of each first layer, applied once: bias + h W[dc..].
        let ctx_bias = self
            .conditioners
            .iter()
            .map(|c| batch_forward(c[0].w.as_ref().subrows(dc, h.len()), &c[0].b, &h, 1, true))
            .collect();
        let gates = self
            .conditioners
            .iter()
            .map(|c| {
                (0..self.cfg.blocks)
                    .map(|k| {
                        let g = &c[3 + 3 * k];
                        let v = batch_forward(g.w.as_ref(), &g.b, &h, 1, true);
                        v.into_iter().map(|z| 1.0 / (1.0 + (-z).exp())).collect()
                    })
                    .collect()
            })
            .collect();
        Bound { flow: self, ctx_bias, gates, narrow: OnceLock::new(), temperature: 1.0 }
    }
}

/// exp_neg's constants: 1.5·2^52 (adding it rounds to an integer), ln 2 split so that
/// n·LN2_HI is exact (fdlibm's constants), and the Taylor coefficients 1/k!, k = 13 down
/// to 0 (the first is the Horner start).
const EXP_SHIFT: f64 = 6_755_399_441_055_744.0;
const LN2_HI: f64 = f64::from_bits(0x3fe6_2e42_fee0_0000);
const LN2_LO: f64 = f64::from_bits(0x3dea_39ef_3579_3c76);
const INV_FACT: [f64; 14] = [
    1.0 / 6_227_020_800.0,
    1.0 / 479_001_600.0,
    1.0 / 39_916_800.0,
    1.0 / 3_628_800.0,
    1.0 / 362_880.0,
    1.0 / 40_320.0,
    1.0 / 5_040.0,
    1.0 / 720.0,
    1.0 / 120.0,
    1.0 / 24.0,
    1.0 / 6.0,
    0.5,
    1.0,
    1.0,
];

/// e^x for x ≤ 0 (a softmax after its maximum, softplus's e^−|r|), inlined so that the
/// knot loops stay free of calls: Cody–Waite reduction x = n ln 2 + r, |r| ≤ ln 2 / 2, and
/// the degree-13 Taylor polynomial of e^r (truncation < 1e-17 relative; the test measures
/// ≤ 4 ulp against `f64::exp`). Below −708 the argument is clamped there (e^−708 ≈ 3e-308
/// instead of a denormal: nothing beside a softmax sum ≥ 1 or 1 + e); NaN stays NaN.
#[inline(always)]
fn exp_neg<const FMA: bool>(x: f64) -> f64 {
    exp_taylor::<FMA, 0>(if x < -708.0 { -708.0 } else { x })
}

/// [`exp_neg`] to f32's precision, for [`sigmoids`]: the Taylor polynomial to degree 7
/// (truncation < 5e-9 relative, f32's ulp is 6e-8), for x ≥ −87 (clamped there).
#[inline(always)]
fn exp_neg_short<const FMA: bool>(x: f64) -> f64 {
    exp_taylor::<FMA, 6>(if x < -87.0 { -87.0 } else { x })
}

/// e^x for −708 ≤ x ≤ 0: Cody–Waite reduction, then Horner on `INV_FACT[FIRST..]` (the
/// polynomial of degree 13 − FIRST), times 2^n built from the shifted value's bits.
#[inline(always)]
fn exp_taylor<const FMA: bool, const FIRST: usize>(x: f64) -> f64 {
    let shifted = x * std::f64::consts::LOG2_E + EXP_SHIFT;
    let n = shifted - EXP_SHIFT;
    let r = (x - n * LN2_HI) - n * LN2_LO;
    let mut p = INV_FACT[FIRST];
    for &c in &INV_FACT[FIRST + 1..] {
        p = mul_add::<FMA>(p, r, c);
    }
    // 2^n from the integer in the shifted value's low mantissa bits (n ∈ −1022..=0).
    let k = (shifted.to_bits() as i64).wrapping_sub(EXP_SHIFT.to_bits() as i64);
    p * f64::from_bits(((k + 1023) as u64) << 52)
}

/// The logistic function σ(x) of each x into `s`; with `line`, also each point's tangent
/// line σ(x) ≈ slope·x + offset at x, slope = σ(1 − σ), as (slope, offset): training
/// builds its gate from them with two tensor ops (`flow::gate`). In f64 through
/// [`exp_neg`] (branch-free: σ = 1/(1 + e) or e/(1 + e), e = e^−|x|), rounded to f32;
/// compiled for AVX2 and FMA where the CPU has them. burn's own sigmoid calls libm's
/// `expf` element by element: a quarter of a two-moons training (docs/npe.md).
pub(crate) fn sigmoids(x: &[f32], s: &mut [f32], line: Option<(&mut [f32], &mut [f32])>) {
    #[cfg(target_arch = "x86_64")]
    if std::arch::is_x86_feature_detected!("avx2") && std::arch::is_x86_feature_detected!("fma") {
        // SAFETY: the CPU has the features `sigmoids_avx2` is compiled for (just detected).
        return unsafe { sigmoids_avx2(x, s, line) };
    }
    sigmoids_with::<false>(x, s, line);
}

#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2,fma")]
fn sigmoids_avx2(x: &[f32], s: &mut [f32], line: Option<(&mut [f32], &mut [f32])>) {
    sigmoids_with::<true>(x, s, line);
}

#[inline(always)]
fn sigmoids_with<const FMA: bool>(x: &[f32], s: &mut [f32], line: Option<(&mut [f32], &mut [f32])>) {
    let sigmoid = |v: f32| -> f64 {
        let v = f64::from(v);
        // Past 87, e^−|v| < 1.7e-38 (a subnormal in f32): σ is taken as exactly 0 or 1.
        let e = if v.abs() > 87.0 { 0.0 } else { exp_neg_short::<FMA>(-v.abs()) };
        let num = if v >= 0.0 { 1.0 } else { e };
        num / (1.0 + e)
    };
    match line {
        None => s.iter_mut().zip(x).for_each(|(s, &v)| *s = sigmoid(v) as f32),
        Some((slope, offset)) => {
            for (((s, k), c), &v) in s.iter_mut().zip(slope.iter_mut()).zip(offset.iter_mut()).zip(x) {
                let sv = sigmoid(v);
                let kv = (sv * (1.0 - sv)) as f32;
                (*s, *k, *c) = (sv as f32, kv, (sv - f64::from(kv) * f64::from(v)) as f32);
            }
        }
    }
}

/// a·b + c, fused where the caller was compiled with FMA (`FMA`), else two operations
/// (`f64::mul_add` without the instruction is a slow library call).
#[inline(always)]
fn mul_add<const FMA: bool>(a: f64, b: f64, c: f64) -> f64 {
    if FMA { a.mul_add(b, c) } else { a * b + c }
}

/// Softmax weights of one knot axis, scaled so that knot k sits at
/// −bound + 2·bound·Σ_{j<k} (e_j·scale + min): (e, scale); e is K long.
#[inline(always)]
fn axis_weights<const FMA: bool>(r: &[f64], min: f64, bins: usize) -> ([f64; 32], f64) {
    assert!(bins < 32, "at most 31 bins");
    let m = r.iter().fold(f64::NEG_INFINITY, |a, &b| a.max(b));
    let mut e = [0.0; 32];
    for (ek, v) in e.iter_mut().zip(r) {
        *ek = exp_neg::<FMA>(v - m);
    }
    let s: f64 = e[..bins].iter().sum();
    (e, (1.0 - bins as f64 * min) / s)
}

/// Derivative at knot k (1 at both ends; softplus of the raw value inside). Only the
/// two knots of the active bin are needed, so they are computed on demand.
#[inline(always)]
fn derivative<const FMA: bool>(raw: &[f64], bins: usize, k: usize) -> f64 {
    if k == 0 || k == bins {
        return 1.0;
    }
    let r = raw[2 * bins + k - 1];
    r.max(0.0) + ln_1p_unit(exp_neg::<FMA>(-r.abs())) + MIN_DERIVATIVE
}

/// fdlibm's log1p polynomial: ln((1 + s)/(1 − s)) = 2s + Σ LG_k s^(2k+1), |s| ≤ 0.1716.
const LG: [f64; 7] = [
    f64::from_bits(0x3fe5_5555_5555_5593),
    f64::from_bits(0x3fd9_9999_9997_fa04),
    f64::from_bits(0x3fd2_4924_9422_9359),
    f64::from_bits(0x3fcc_71c5_1d8e_78af),
    f64::from_bits(0x3fc7_4664_96cb_03de),
    f64::from_bits(0x3fc3_9a09_d078_c69f),
    f64::from_bits(0x3fc2_f112_df3e_5244),
];

/// ln(1 + x) for x ∈ [0, 1] (softplus's e^−|r|), inlined instead of libm's `log1p` call
/// (6 % of a `POST /infer`): fdlibm's log1p — u = 1 + x with its rounding error c carried
/// to first order, u = 2^k (1 + f) with 1 + f ∈ [√2/2, √2], ln(1 + f) by its polynomial in
/// s = f / (2 + f) — without its branches for other ranges (the test measures ≤ 1 ulp
/// against `f64::ln_1p`). NaN stays NaN. `lanes` computes the same in four lanes.
#[inline(always)]
fn ln_1p_unit(x: f64) -> f64 {
    let u = 1.0 + x;
    let c = (x - (u - 1.0)) / u;
    let big = u > std::f64::consts::SQRT_2;
    let (m, k) = if big { (u * 0.5, 1.0) } else { (u, 0.0) };
    let f = m - 1.0;
    let s = f / (2.0 + f);
    let z = s * s;
    let w = z * z;
    let t1 = w * (LG[1] + w * (LG[3] + w * LG[5]));
    let t2 = z * (LG[0] + w * (LG[2] + w * (LG[4] + w * LG[6])));
    let r = t2 + t1;
    let hfsq = 0.5 * f * f;
    k * LN2_HI - ((hfsq - (s * (hfsq + r) + (k * LN2_LO + c))) - f)
}

/// The bin holding v on an axis of unnormalised weights `w` (× `scale`, + `min` each),
/// counted as burn's `bin_of` does.
#[inline(always)]
fn active(v: f64, w: &[f64; 32], scale: f64, min: f64, bins: usize, bound: f64) -> usize {
    let (mut acc, mut k) = (0.0, 0);
    while k + 1 < bins {
        let next = acc + w[k] * scale + min;
        if v < next * 2.0 * bound - bound {
            break;
        }
        acc = next;
        k += 1;
    }
    k
}

/// The active bin of one dim's spline: (x0, y0, width, height, d at both ends). The bin
/// holds v among the interior knots of the searched axis (x, or y when `by_y`), counted
/// as burn's `bin_of` does; only that bin's two knots of the other axis are formed (the
/// inference path's hot loop: no knot arrays, one division per axis).
#[inline(always)]
fn bin<const FMA: bool>(v: f64, raw: &[f64], bins: usize, bound: f64, by_y: bool) -> (f64, f64, f64, f64, [f64; 2]) {
    bin_with::<FMA>(v, raw, bins, bound, by_y, &weights::<FMA>(raw, bins))
}

/// Both axes' softmax weights and scales ([`axis_weights`]): x, then y.
#[inline(always)]
fn weights<const FMA: bool>(raw: &[f64], bins: usize) -> [([f64; 32], f64); 2] {
    [axis_weights::<FMA>(&raw[..bins], MIN_WIDTH, bins), axis_weights::<FMA>(&raw[bins..2 * bins], MIN_HEIGHT, bins)]
}

/// [`bin`] with the axes' weights given.
#[inline(always)]
fn bin_with<const FMA: bool>(
    v: f64,
    raw: &[f64],
    bins: usize,
    bound: f64,
    by_y: bool,
    weights: &[([f64; 32], f64); 2],
) -> (f64, f64, f64, f64, [f64; 2]) {
    let [(wx, sx), (wy, sy)] = weights;
    let (sx, sy) = (*sx, *sy);
    let (search, scale, min) = if by_y { (wy, sy, MIN_HEIGHT) } else { (wx, sx, MIN_WIDTH) };
    let k = active(v, search, scale, min, bins, bound);
    let knot = |w: &[f64; 32], scale: f64, min: f64| {
        let lo: f64 = w[..k].iter().fold(0.0, |a, e| a + e * scale + min);
        let hi = lo + w[k] * scale + min;
        (lo * 2.0 * bound - bound, if k + 1 == bins { bound } else { hi * 2.0 * bound - bound })
    };
    let (x0, x1) = knot(wx, sx, MIN_WIDTH);
    let (y0, y1) = knot(wy, sy, MIN_HEIGHT);
    (x0, y0, x1 - x0, y1 - y0, [derivative::<FMA>(raw, bins, k), derivative::<FMA>(raw, bins, k + 1)])
}

/// f′ at position t ∈ [0, 1] in a bin of slope delta with end derivatives d (its log is
/// taken once per row: a product of a few slopes, far from f64's range limits).
#[inline(always)]
fn slope(delta: f64, d: [f64; 2], t: f64) -> f64 {
    let t1 = t * (1.0 - t);
    let den = delta + (d[0] + d[1] - 2.0 * delta) * t1;
    let dnum = delta * delta * (d[1] * t * t + 2.0 * delta * t1 + d[0] * (1.0 - t) * (1.0 - t));
    dnum / (den * den)
}

/// y = f(x) and |f'(x)| for one dim.
#[inline(always)]
fn spline_forward<const FMA: bool>(x: f64, raw: &[f64], bins: usize, bound: f64) -> (f64, f64) {
    if x.abs() > bound {
        return (x, 1.0);
    }
    let (x0, y0, w, h, d) = bin::<FMA>(x, raw, bins, bound, false);
    let delta = h / w;
    let t = ((x - x0) / w).clamp(0.0, 1.0);
    let t1 = t * (1.0 - t);
    let y = y0 + h * (delta * t * t + d[0] * t1) / (delta + (d[0] + d[1] - 2.0 * delta) * t1);
    (y, slope(delta, d, t))
}

/// x = f⁻¹(y) and |f'(x)| for one dim.
#[inline(always)]
fn spline_inverse<const FMA: bool>(y: f64, raw: &[f64], bins: usize, bound: f64) -> (f64, f64) {
    if y.abs() > bound {
        return (y, 1.0);
    }
    let (x0, y0, w, h, d) = bin::<FMA>(y, raw, bins, bound, true);
    let delta = h / w;
    let dy = y - y0;
    let s = d[0] + d[1] - 2.0 * delta;
    let a = h * (delta - d[0]) + dy * s;
    let b = h * d[0] - dy * s;
    let c = -delta * dy;
    let disc = (b * b - 4.0 * a * c).max(0.0);
    let t = ((2.0 * c) / (-b - disc.sqrt())).clamp(0.0, 1.0);
    (t * w + x0, slope(delta, d, t))
}

/// The spline's terms at x inside the bound that its value, log-slope and their
/// derivatives share (y = y0 + h·a/den, f′ = δ²·n2/den², and the partials of a, den, n2).
struct Local {
    weights: [([f64; 32], f64); 2],
    w: f64,
    h: f64,
    delta: f64,
    t: f64,
    t1: f64,
    den: f64,
    a: f64,
    y: f64,
    n2: f64,
    ld: f64,
    den_t: f64,
    den_delta: f64,
    a_t: f64,
    n2_t: f64,
    den2: f64,
}

#[inline(always)]
fn local<const FMA: bool>(x: f64, raw: &[f64], bins: usize, bound: f64) -> Local {
    let weights = weights::<FMA>(raw, bins);
    let (x0, y0, w, h, [d0, d1]) = bin_with::<FMA>(x, raw, bins, bound, false, &weights);
    let delta = h / w;
    let t = ((x - x0) / w).clamp(0.0, 1.0);
    let t1 = t * (1.0 - t);
    let s = d0 + d1 - 2.0 * delta;
    let den = delta + s * t1;
    let a = delta * t * t + d0 * t1;
    let y = y0 + h * a / den;
    let n2 = d1 * t * t + 2.0 * delta * t1 + d0 * (1.0 - t) * (1.0 - t);
    let ld = (delta * delta * n2 / (den * den)).ln();
    let (den_t, den_delta) = (s * (1.0 - 2.0 * t), 1.0 - 2.0 * t1);
    let a_t = 2.0 * delta * t + d0 * (1.0 - 2.0 * t);
    let n2_t = 2.0 * d1 * t + 2.0 * delta * (1.0 - 2.0 * t) - 2.0 * d0 * (1.0 - t);
    let den2 = den * den;
    Local { weights, w, h, delta, t, t1, den, a, y, n2, ld, den_t, den_delta, a_t, n2_t, den2 }
}

/// y = f(x), log |f′(x)| and the gradient of gy·y + log |f′(x)| with respect to x
/// (returned) and to the spline's raw parameters (written to `g_raw`, 3K−1 long): the
/// MAP's analytic gradient. Within the active bin y depends on t = (x − x0)/w, the slope
/// δ = h/w, y0, h and the end derivatives; the knots on the softmaxes of the raw widths
/// and heights (∂W_j/∂r_i = 2B(1 − K·min) S_j (δ_ij − S_i)) and the interior derivatives
/// on softplus (∂/∂r = σ(r)).
#[inline(always)]
fn spline_forward_grad<const FMA: bool>(
    x: f64,
    raw: &[f64],
    bins: usize,
    bound: f64,
    gy: f64,
    g_raw: &mut [f64],
) -> (f64, f64, f64) {
    g_raw.iter_mut().for_each(|g| *g = 0.0);
    if x.abs() > bound {
        return (x, 0.0, gy);
    }
    let Local { weights, w, h, delta, t, t1, den, a, y, n2, ld, den_t, den_delta, a_t, n2_t, den2 } =
        local::<FMA>(x, raw, bins, bound);
    // ∂ over t, δ, d0, d1 and h (δ held), each of gy·y + ld.
    let g_t = gy * h * (a_t * den - a * den_t) / den2 + n2_t / n2 - 2.0 * den_t / den;
    let g_delta = gy * h * (t * t * den - a * den_delta) / den2 + 2.0 / delta + 2.0 * t1 / n2 - 2.0 * den_delta / den;
    let g_d0 = gy * h * t1 * (den - a) / den2 + (1.0 - t) * (1.0 - t) / n2 - 2.0 * t1 / den;
    let g_d1 = -gy * h * a * t1 / den2 + t * t / n2 - 2.0 * t1 / den;
    let g_h = gy * a / den + g_delta / w;
    let g_x = g_t / w;
    let (g_x0, g_w) = (-g_t / w, -g_t * t / w - g_delta * delta / w);
    // Knots: x0 = −B + Σ_{j<k} W_j, w = W_k (heights alike, with y0 and h).
    let k = active(x, &weights[0].0, weights[0].1, MIN_WIDTH, bins, bound);
    for (axis, (g_lo, g_len), min) in [(0, (g_x0, g_w), MIN_WIDTH), (1, (gy, g_h), MIN_HEIGHT)] {
        let e = &weights[axis].0;
        let total: f64 = e[..bins].iter().sum();
        let c = 2.0 * bound * (1.0 - bins as f64 * min);
        let sm = |i: usize| e[i] / total;
        let mean = g_lo * (0..k).map(sm).sum::<f64>() + g_len * sm(k);
        for (i, g) in g_raw[axis * bins..(axis + 1) * bins].iter_mut().enumerate() {
            let gi = if i < k {
                g_lo
            } else if i == k {
                g_len
            } else {
                0.0
            };
            *g = c * sm(i) * (gi - mean);
        }
    }
    let sigmoid = |r: f64| 1.0 / (1.0 + (-r).exp());
    if k > 0 {
        g_raw[2 * bins + k - 1] += g_d0 * sigmoid(raw[2 * bins + k - 1]);
    }
    if k + 1 < bins {
        g_raw[2 * bins + k] += g_d1 * sigmoid(raw[2 * bins + k]);
    }
    (y, ld, g_x)
}

/// y = f(x) and log |f′(x)| for x inside the bound, with the gradient of each with
/// respect to the raw parameters (into `jy` and `jl`, 3K − 1 each) and to x (returned
/// last): [`spline_forward_grad`]'s derivatives, for y and log f′ apart (the training's
/// backward pass weighs them itself).
#[inline(always)]
fn spline_jacobian<const FMA: bool>(
    x: f64,
    raw: &[f64],
    bins: usize,
    bound: f64,
    jy: &mut [f32],
    jl: &mut [f32],
) -> (f64, f64, f64, f64) {
    let Local { weights, w, h, delta, t, t1, den, a, y, n2, ld, den_t, den_delta, a_t, n2_t, den2 } =
        local::<FMA>(x, raw, bins, bound);
    // ∂ over t, δ, d0, d1 and h (δ held): of y, then of log f′.
    let (yt, ydelta) = (h * (a_t * den - a * den_t) / den2, h * (t * t * den - a * den_delta) / den2);
    let (yd0, yd1, yh) = (h * t1 * (den - a) / den2, -h * a * t1 / den2, a / den + ydelta / w);
    let (lt, ldelta) = (n2_t / n2 - 2.0 * den_t / den, 2.0 / delta + 2.0 * t1 / n2 - 2.0 * den_delta / den);
    let (ld0, ld1, lh) = ((1.0 - t) * (1.0 - t) / n2 - 2.0 * t1 / den, t * t / n2 - 2.0 * t1 / den, ldelta / w);
    // Through t = (x − x0)/w and δ = h/w: (∂x, ∂x0, ∂w).
    let via = |gt: f64, gdelta: f64| (gt / w, -gt / w, -gt * t / w - gdelta * delta / w);
    let ((yx, yx0, yw), (lx, lx0, lw)) = (via(yt, ydelta), via(lt, ldelta));
    // Knots: x0 = −B + Σ_{j<k} W_j, w = W_k (heights alike, with y0 and h), W on a softmax.
    let k = active(x, &weights[0].0, weights[0].1, MIN_WIDTH, bins, bound);
    for (axis, min, (y_lo, y_len), (l_lo, l_len)) in
        [(0, MIN_WIDTH, (yx0, yw), (lx0, lw)), (1, MIN_HEIGHT, (1.0, yh), (0.0, lh))]
    {
        let e = &weights[axis].0;
        let total: f64 = e[..bins].iter().sum();
        let c = 2.0 * bound * (1.0 - bins as f64 * min);
        let below: f64 = e[..k].iter().map(|v| v / total).sum();
        let (y_mean, l_mean) = (y_lo * below + y_len * (e[k] / total), l_lo * below + l_len * (e[k] / total));
        for i in 0..bins {
            let si = c * (e[i] / total);
            let (gy, gl) = match i.cmp(&k) {
                std::cmp::Ordering::Less => (y_lo, l_lo),
                std::cmp::Ordering::Equal => (y_len, l_len),
                std::cmp::Ordering::Greater => (0.0, 0.0),
            };
            jy[axis * bins + i] = (si * (gy - y_mean)) as f32;
            jl[axis * bins + i] = (si * (gl - l_mean)) as f32;
        }
    }
    // Interior derivatives: softplus, ∂/∂r = σ(r).
    jy[2 * bins..].iter_mut().chain(jl[2 * bins..].iter_mut()).for_each(|v| *v = 0.0);
    let sigmoid = |r: f64| 1.0 / (1.0 + (-r).exp());
    for (knot, gy, gl) in [(k, yd0, ld0), (k + 1, yd1, ld1)] {
        if knot > 0 && knot < bins {
            let j = 2 * bins + knot - 1;
            let sg = sigmoid(raw[j]);
            (jy[j], jl[j]) = ((gy * sg) as f32, (gl * sg) as f32);
        }
    }
    (y, ld, yx, lx)
}

/// Spline parameters per element at most (3K − 1, K ≤ 31).
const MAX_PARAMS: usize = 92;

/// Elements per task of [`spline_jacobians`]' parallel loop.
const JACOBIAN_CHUNK: usize = 256;

/// Up to this many elements [`spline_jacobians`] runs on the calling thread: handing a
/// training batch's few thousand elements to rayon cost more in wake-ups (futex,
/// sched_yield) than it saved on two cores (docs/results/npe.md).
const SERIAL_ELEMENTS: usize = 16_384;

/// The training's spline pass (`spline::forward`), in f64 from burn's f32: for element e,
/// y[e] = f(x[e]) and ld[e] = log |f′(x[e])| with parameters `raw[e·np..(e+1)·np]`, and
/// with `jacobians` also ∂y and ∂ld with respect to (raw, x), np + 1 entries per element.
/// Elements are independent: chunks of them run on rayon; where the CPU has AVX2 and FMA,
/// four elements at a time in one register (`lane_jacobians`, the same bits), with or
/// without the Jacobians.
pub(crate) fn spline_jacobians(
    x: &[f32],
    raw: &[f32],
    bins: usize,
    bound: f64,
    (y, ld): (&mut [f32], &mut [f32]),
    jacobians: Option<(&mut [f32], &mut [f32])>,
) {
    use rayon::prelude::*;
    let np = 3 * bins - 1;
    assert!(np <= MAX_PARAMS, "at most 31 bins");
    let c = JACOBIAN_CHUNK;
    if x.len() <= SERIAL_ELEMENTS {
        return lane_jacobians::chunk(x, raw, bins, bound, (y, ld), jacobians);
    }
    let chunks = x.par_chunks(c).zip(raw.par_chunks(c * np)).zip(y.par_chunks_mut(c)).zip(ld.par_chunks_mut(c));
    match jacobians {
        Some((jy, jl)) => chunks.zip(jy.par_chunks_mut(c * (np + 1))).zip(jl.par_chunks_mut(c * (np + 1))).for_each(
            |(((((x, raw), y), ld), jy), jl)| lane_jacobians::chunk(x, raw, bins, bound, (y, ld), Some((jy, jl))),
        ),
        None => chunks.for_each(|(((x, raw), y), ld)| lane_jacobians::chunk(x, raw, bins, bound, (y, ld), None)),
    }
}

#[inline(always)]
fn jacobian_chunk_with<const FMA: bool>(
    x: &[f32],
    raw: &[f32],
    bins: usize,
    bound: f64,
    (y, ld): (&mut [f32], &mut [f32]),
    mut jacobians: Option<(&mut [f32], &mut [f32])>,
) {
    let np = 3 * bins - 1;
    let mut r = [0.0; MAX_PARAMS];
    for (e, &xe) in x.iter().enumerate() {
        let xe = f64::from(xe);
        for (rk, &v) in r.iter_mut().zip(&raw[e * np..(e + 1) * np]) {
            *rk = f64::from(v);
        }
        let r = &r[..np];
        let Some((jy, jl)) = jacobians.as_mut() else {
            let (v, slope) = spline_forward::<FMA>(xe, r, bins, bound);
            (y[e], ld[e]) = (v as f32, slope.ln() as f32);
            continue;
        };
        let (jy, jl) = (&mut jy[e * (np + 1)..(e + 1) * (np + 1)], &mut jl[e * (np + 1)..(e + 1) * (np + 1)]);
        if xe.abs() > bound {
            // The identity tail.
            jy.iter_mut().chain(jl.iter_mut()).for_each(|v| *v = 0.0);
            (y[e], ld[e], jy[np]) = (xe as f32, 0.0, 1.0);
            continue;
        }
        let (v, l, yx, lx) = spline_jacobian::<FMA>(xe, r, bins, bound, &mut jy[..np], &mut jl[..np]);
        (y[e], ld[e], jy[np], jl[np]) = (v as f32, l as f32, yx as f32, lx as f32);
    }
}

/// One coupling's splines over a block: the layout and direction.
struct Splines {
    d: usize,
    dc: usize,
    bins: usize,
    bound: f64,
    inverse: bool,
}

/// Every transformed dim of every column of u [d × n] through its spline (parameters
/// `raw`, dt·(3K−1) per column), adding log |f′| to `logdet`. The exponentials of the
/// knot softmaxes are most of a sample's cost: on x86-64 with AVX2 and FMA (detected once
/// at run time) the same code is compiled for them, 4-wide and fused.
fn splines(s: &Splines, u: &mut [f64], raw: &[f64], logdet: &mut [f64]) {
    #[cfg(target_arch = "x86_64")]
    if std::arch::is_x86_feature_detected!("avx2") && std::arch::is_x86_feature_detected!("fma") {
        // SAFETY: the CPU has the features `splines_avx2` is compiled for (just detected).
        return unsafe { splines_avx2(s, u, raw, logdet) };
    }
    splines_with::<false>(s, u, raw, logdet);
}

#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2,fma")]
fn splines_avx2(s: &Splines, u: &mut [f64], raw: &[f64], logdet: &mut [f64]) {
    splines_with::<true>(s, u, raw, logdet);
}

#[inline(always)]
fn splines_with<const FMA: bool>(s: &Splines, u: &mut [f64], raw: &[f64], logdet: &mut [f64]) {
    let (d, dc) = (s.d, s.dc);
    let dt = d - dc;
    let np = 3 * s.bins - 1;
    for ((col, r), ld) in u.chunks_exact_mut(d).zip(raw.chunks_exact(dt * np)).zip(logdet.iter_mut()) {
        let mut jac = 1.0;
        for k in 0..dt {
            let p = &r[k * np..(k + 1) * np];
            let (y, f) = if s.inverse {
                spline_inverse::<FMA>(col[dc + k], p, s.bins, s.bound)
            } else {
                spline_forward::<FMA>(col[dc + k], p, s.bins, s.bound)
            };
            col[dc + k] = y;
            jac *= f;
        }
        *ld += jac.ln();
    }
}

/// The gradients back through one coupling's splines (the MAP search's backward pass):
/// for each column, g of the transformed dims from ∂/∂y to ∂/∂x at the points `before`,
/// and ∂/∂raw into `g_raw` ([`spline_forward_grad`]); compiled for AVX2 and FMA where the
/// CPU has them, as [`splines`].
fn spline_grads(s: &Splines, g: &mut [f64], before: &[f64], raw: &[f64], g_raw: &mut [f64]) {
    #[cfg(target_arch = "x86_64")]
    if std::arch::is_x86_feature_detected!("avx2") && std::arch::is_x86_feature_detected!("fma") {
        // SAFETY: the CPU has the features `spline_grads_avx2` is compiled for (just detected).
        return unsafe { spline_grads_avx2(s, g, before, raw, g_raw) };
    }
    spline_grads_with::<false>(s, g, before, raw, g_raw);
}

#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2,fma")]
fn spline_grads_avx2(s: &Splines, g: &mut [f64], before: &[f64], raw: &[f64], g_raw: &mut [f64]) {
    spline_grads_with::<true>(s, g, before, raw, g_raw);
}

#[inline(always)]
fn spline_grads_with<const FMA: bool>(s: &Splines, g: &mut [f64], before: &[f64], raw: &[f64], g_raw: &mut [f64]) {
    let (d, dc) = (s.d, s.dc);
    let dt = d - dc;
    let np = 3 * s.bins - 1;
    for (((gc, bc), rc), grc) in g
        .chunks_exact_mut(d)
        .zip(before.chunks_exact(d))
        .zip(raw.chunks_exact(dt * np))
        .zip(g_raw.chunks_exact_mut(dt * np))
    {
        for k in 0..dt {
            let p = &rc[k * np..(k + 1) * np];
            let gp = &mut grc[k * np..(k + 1) * np];
            gc[dc + k] = spline_forward_grad::<FMA>(bc[dc + k], p, s.bins, s.bound, gc[dc + k], gp).2;
        }
    }
}

/// Applies permutation p to every row of u (new[j] = old[p[j]], as burn's `select`), or
/// undoes it.
fn permute(u: &mut [f64], p: &[usize], undo: bool) {
    let mut tmp = vec![0.0; p.len()];
    for row in u.chunks_exact_mut(p.len()) {
        for (j, &pj) in p.iter().enumerate() {
            if undo {
                tmp[pj] = row[j];
            } else {
                tmp[j] = row[pj];
            }
        }
        row.copy_from_slice(&tmp);
    }
}

/// log N(z; 0, t² I).
fn log_normal(z: &[f64], t: f64) -> f64 {
    let d = z.len() as f64;
    -0.5 * z.iter().map(|v| v * v).sum::<f64>() / (t * t) - d * t.ln() - 0.5 * d * (2.0 * std::f64::consts::PI).ln()
}

impl Bound<'_> {
    /// The same flow with base distribution N(0, t² I); `t` must be finite and > 0.
    pub fn with_temperature(mut self, t: f64) -> Self {
        debug_assert!(t.is_finite() && t > 0.0);
        self.temperature = t;
        self
    }

    /// Conditioner `t` in f64.
    fn wide(&self, t: usize) -> Conditioner<'_, f64> {
        Conditioner { layers: &self.flow.conditioners[t], ctx_bias: &self.ctx_bias[t], gates: &self.gates[t] }
    }

    /// Conditioner `t` in f32: the weights were trained in f32 (the copy is exact but for
    /// the folded bin scale) and only the sums round in f32, ~1e-7 relative.
    fn narrow(&self, t: usize) -> Conditioner<'_, f32> {
        let n = self.narrow.get_or_init(|| {
            let to32 = |v: &[f64]| -> Vec<f32> { v.iter().map(|&x| x as f32).collect() };
            Narrow {
                layers: (self.flow.conditioners.iter())
                    .map(|c| {
                        c.iter()
                            .map(|l| Dense {
                                w: Mat::from_fn(l.w.nrows(), l.w.ncols(), |r, k| l.w[(r, k)] as f32),
                                b: to32(&l.b),
                            })
                            .collect()
                    })
                    .collect(),
                ctx_bias: self.ctx_bias.iter().map(|c| to32(c)).collect(),
                gates: self.gates.iter().map(|g| g.iter().map(|v| to32(v)).collect()).collect(),
            }
        });
        Conditioner { layers: &n.layers[t], ctx_bias: &n.ctx_bias[t], gates: &n.gates[t] }
    }

    /// Raw spline parameters [P × n] of transform `t` (`transposed`: [n × P]) in f64,
    /// keeping the activations in `acts` (see [`Conditioner::raw`]).
    fn raw_keeping(
        &self,
        t: usize,
        a: &[f64],
        n: usize,
        acts: Option<&mut Vec<Vec<f64>>>,
        transposed: bool,
    ) -> Vec<f64> {
        self.wide(t).raw(self.flow.cfg.dim / 2, self.flow.cfg.blocks, a, n, acts, transposed)
    }

    /// The gradient of Σ_i g_raw_i · raw_i with respect to `a`, given the activations
    /// [`Self::raw_keeping`] kept: ReLU masks from the kept (post-ReLU or pre-ReLU) values.
    fn raw_backward(&self, t: usize, acts: &[Vec<f64>], g_raw: Vec<f64>, n: usize) -> Vec<f64> {
        let layers = &self.flow.conditioners[t];
        let dc = self.flow.cfg.dim / 2;
        let blocks = self.flow.cfg.blocks;
        let last = layers.len() - 1;
        let mask =
            |g: &mut [f64], by: &[f64]| g.iter_mut().zip(by).for_each(|(g, v)| *g = if *v > 0.0 { *g } else { 0.0 });
        let mut g = g_raw;
        if blocks > 0 {
            let width = layers[0].w.ncols();
            g = back(layers[last].w.as_ref(), &g, n);
            for k in (0..blocks).rev() {
                let (h, s) = (&acts[2 * k], &acts[2 * k + 1]);
                let mut gr = g.clone();
                for col in gr.chunks_exact_mut(width) {
                    col.iter_mut().zip(&self.gates[t][k]).for_each(|(v, gate)| *v *= gate);
                }
                let mut gs = back(layers[2 + 3 * k].w.as_ref(), &gr, n);
                mask(&mut gs, s);
                let mut gh = back(layers[1 + 3 * k].w.as_ref(), &gs, n);
                mask(&mut gh, h);
                g.iter_mut().zip(&gh).for_each(|(a, b)| *a += b);
            }
        } else {
            for l in (1..=last).rev() {
                g = back(layers[l].w.as_ref(), &g, n);
                mask(&mut g, &acts[l - 1]);
            }
        }
        back(layers[0].w.as_ref().subrows(0, dc), &g, n)
    }

    /// One coupling transform on u [d × n] (after its permutation), forward or inverse;
    /// adds each sample's log |f'| to `logdet`. The conditioner runs in f32 when sampling
    /// (`inverse`) unless `wide`.
    fn couple(&self, t: usize, u: &mut [f64], n: usize, inverse: bool, wide: bool, logdet: &mut [f64]) {
        let cfg = &self.flow.cfg;
        let d = cfg.dim;
        let dc = d / 2;
        let untouched = u.chunks_exact(d).flat_map(|c| c[..dc].iter().copied());
        let raw = if inverse && !wide {
            let a: Vec<f32> = untouched.map(|v| v as f32).collect();
            self.narrow(t).raw(dc, cfg.blocks, &a, n, None, true).into_iter().map(f64::from).collect()
        } else {
            self.raw_keeping(t, &untouched.collect::<Vec<_>>(), n, None, true)
        };
        lanes::splines(&Splines { d, dc, bins: cfg.bins, bound: cfg.bound, inverse }, u, &raw, n, logdet);
    }

    /// Standard-normal draws z (n rows of d, row-major) → points v (same layout) and
    /// log q(v), in one inverse pass.
    pub fn sample(&self, z: &[f64]) -> (Vec<f64>, Vec<f64>) {
        self.inverse(z, false)
    }

    /// As [`Self::sample`] with every conditioner in f64: slower, but the exact inverse of
    /// [`Self::base`] (to rounding), so that log q is the log-density of the map's own
    /// output, smooth in z (`npe::LatentMap` differentiates through it).
    pub fn sample_wide(&self, z: &[f64]) -> (Vec<f64>, Vec<f64>) {
        self.inverse(z, true)
    }

    fn inverse(&self, z: &[f64], wide: bool) -> (Vec<f64>, Vec<f64>) {
        let cfg = &self.flow.cfg;
        let d = cfg.dim;
        let n = z.len() / d;
        let mut logdet = vec![0.0; n];
        let tz: Vec<f64> = z.iter().map(|v| v * self.temperature).collect();
        let mut u = tz.clone();
        for t in (0..cfg.transforms).rev() {
            if let Some(a) = self.flow.lu.get(t) {
                a.apply(&mut u, true);
                logdet.iter_mut().for_each(|l| *l += a.logdet);
            }
            self.couple(t, &mut u, n, true, wide, &mut logdet);
            permute(&mut u, &cfg.permutations[t], true);
        }
        let lp = tz.chunks_exact(d).zip(&logdet).map(|(c, ld)| log_normal(c, self.temperature) + ld).collect();
        (u, lp)
    }

    /// log q(v) for points v (n rows of d, row-major; the flow's standardised space).
    pub fn log_prob(&self, v: &[f64]) -> Vec<f64> {
        self.base(v).1
    }

    /// Points v (n rows of d, row-major) → the standard-normal draws z that
    /// [`Self::sample`] maps to them (the inverse of the sampling map) and log q(v).
    pub fn base(&self, v: &[f64]) -> (Vec<f64>, Vec<f64>) {
        let cfg = &self.flow.cfg;
        let d = cfg.dim;
        let n = v.len() / d;
        let mut logdet = vec![0.0; n];
        let mut u = v.to_vec();
        for t in 0..cfg.transforms {
            permute(&mut u, &cfg.permutations[t], false);
            self.couple(t, &mut u, n, false, true, &mut logdet);
            if let Some(a) = self.flow.lu.get(t) {
                a.apply(&mut u, false);
                logdet.iter_mut().for_each(|l| *l += a.logdet);
            }
        }
        let lp = u.chunks_exact(d).zip(&logdet).map(|(c, ld)| log_normal(c, self.temperature) + ld).collect();
        (u.iter().map(|v| v / self.temperature).collect(), lp)
    }
}

impl Bound<'_> {
    /// log q(v) and its gradient ∂ log q / ∂v for points v (n rows of d, row-major), by
    /// one forward pass that keeps its activations and one backward pass (the MAP search;
    /// `tests::log_prob_grad_matches_finite_differences` checks it).
    pub fn log_prob_grad(&self, v: &[f64]) -> (Vec<f64>, Vec<f64>) {
        let cfg = &self.flow.cfg;
        let d = cfg.dim;
        let (dc, dt) = (d / 2, d - d / 2);
        let np = 3 * cfg.bins - 1;
        let n = v.len() / d;
        let mut logdet = vec![0.0; n];
        let mut u = v.to_vec();
        // Per transform: its input (after the permutation), activations and raw parameters.
        let mut tape = Vec::with_capacity(cfg.transforms);
        for t in 0..cfg.transforms {
            permute(&mut u, &cfg.permutations[t], false);
            let a: Vec<f64> = u.chunks_exact(d).flat_map(|c| c[..dc].iter().copied()).collect();
            let mut acts = Vec::new();
            let raw = self.raw_keeping(t, &a, n, Some(&mut acts), false);
            let before = u.clone();
            splines(&Splines { d, dc, bins: cfg.bins, bound: cfg.bound, inverse: false }, &mut u, &raw, &mut logdet);
            if let Some(a) = self.flow.lu.get(t) {
                a.apply(&mut u, false);
                logdet.iter_mut().for_each(|l| *l += a.logdet);
            }
            tape.push((before, acts, raw));
        }
        let t2 = self.temperature * self.temperature;
        let lp = u.chunks_exact(d).zip(&logdet).map(|(c, ld)| log_normal(c, self.temperature) + ld).collect();
        // g = ∂ log q / ∂u, from the base density back through every transform.
        let mut g: Vec<f64> = u.iter().map(|z| -z / t2).collect();
        let mut g_raw = vec![0.0; dt * np * n];
        for t in (0..cfg.transforms).rev() {
            let (before, acts, raw) = &tape[t];
            if let Some(a) = self.flow.lu.get(t) {
                a.back(&mut g);
            }
            spline_grads(
                &Splines { d, dc, bins: cfg.bins, bound: cfg.bound, inverse: false },
                &mut g,
                before,
                raw,
                &mut g_raw,
            );
            let g_a = self.raw_backward(t, acts, g_raw.clone(), n);
            for (gc, ga) in g.chunks_exact_mut(d).zip(g_a.chunks_exact(dc.max(1))) {
                gc[..dc].iter_mut().zip(ga).for_each(|(x, y)| *x += y);
            }
            permute(&mut g, &cfg.permutations[t], true);
        }
        (lp, g)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::flow::Flow;
    use burn::prelude::*;

    #[test]
    fn plain_path_matches_burn() {
        plain_path_matches_burn_for(FlowConfig::new(7, 12, true));
        plain_path_matches_burn_for(FlowConfig { blocks: 2, ..FlowConfig::new(7, 12, true) });
        plain_path_matches_burn_for(FlowConfig { lu: true, ..FlowConfig::new(7, 12, true) });
    }

    /// A flow whose LU layers are far from their identity start (as after training).
    fn with_random_lu(mut flow: Flow, d: usize, scale: f32) -> Flow {
        use burn::module::Param;
        let dev = Device::flex();
        let r = |n: usize, s: usize, size: f32| -> Vec<f32> {
            (0..n).map(|i| (((i + 13 * s) * 7919 % 101) as f32 / 101.0 - 0.5) * size * scale).collect()
        };
        for (k, lu) in flow.lu.iter_mut().enumerate() {
            let t2 = |v: Vec<f32>| Param::from_tensor(Tensor::<2>::from_data(TensorData::new(v, [d, d]), &dev));
            let t1 = |v: Vec<f32>| Param::from_tensor(Tensor::<1>::from_data(TensorData::new(v, [d]), &dev));
            lu.lower = t2(r(d * d, k, 0.8));
            lu.upper = t2(r(d * d, k + 1, 0.8));
            // Around softplus⁻¹(1 − min), the identity's diagonal: each layer scales by
            // 0.8–1.2, so that five of them keep the density on the tests' grids.
            let s0 = ((1.0 - crate::flow::LU_MIN_DIAG).exp() - 1.0).ln() as f32;
            lu.diag = t1(r(d, k + 2, 0.8).into_iter().map(|v| v + s0).collect());
            lu.bias = t1(r(d, k + 3, 1.0));
        }
        flow
    }

    fn plain_path_matches_burn_for(cfg: FlowConfig) {
        let dev = Device::flex();
        let flow = with_random_lu(Flow::seeded(&cfg, &dev, Some(1)), cfg.dim, 1.0);
        let plain = flow.plain(&cfg);
        let input: Vec<f32> = (0..12).map(|i| (i as f32 * 0.37).sin()).collect();
        let n = 64;
        let z: Vec<f32> = (0..n * 7).map(|i| ((i * 7919 % 113) as f32 / 113.0 - 0.5) * 5.0).collect();
        let ctx = flow.embed(Tensor::<2>::from_data(TensorData::new(input.clone(), [1, 12]), &dev)).repeat_dim(0, n);
        let v_burn: Vec<f32> = flow
            .sample_from(&cfg, Tensor::<2>::from_data(TensorData::new(z.clone(), [n, 7]), &dev), ctx.clone())
            .try_into_vec_as::<f32>()
            .unwrap();
        let lp_burn: Vec<f32> = flow
            .log_prob(&cfg, Tensor::<2>::from_data(TensorData::new(v_burn.clone(), [n, 7]), &dev), ctx)
            .try_into_vec_as::<f32>()
            .unwrap();
        let bound = plain.bind(&input.iter().map(|&v| v as f64).collect::<Vec<_>>());
        let (v, lp) = bound.sample(&z.iter().map(|&v| v as f64).collect::<Vec<_>>());
        for (a, b) in v.iter().zip(&v_burn) {
            assert!((a - *b as f64).abs() < 1e-4, "sample {a} vs {b}");
        }
        let lp2 = bound.log_prob(&v);
        for ((a, b), c) in lp.iter().zip(&lp_burn).zip(&lp2) {
            assert!((a - *b as f64).abs() < 1e-3 * (1.0 + a.abs()), "log q {a} vs burn {b}");
            // 1e-6, not 1e-9: the sampling pass's conditioners sum in f32.
            assert!((a - c).abs() < 1e-6 * (1.0 + a.abs()), "one-pass log q {a} vs forward {c}");
        }
    }

    /// Central differences (h = 1e-5) of the one-pass log-density against the analytic
    /// gradient, for an MLP and a residual conditioner, at points inside and beyond the
    /// splines' bound.
    #[test]
    fn log_prob_grad_matches_finite_differences() {
        for cfg in [
            FlowConfig::new(5, 4, true),
            FlowConfig { blocks: 2, ..FlowConfig::new(4, 4, true) },
            FlowConfig { lu: true, ..FlowConfig::new(5, 4, true) },
        ] {
            let dev = Device::flex();
            let plain = with_random_lu(Flow::seeded(&cfg, &dev, Some(2)), cfg.dim, 1.0).plain(&cfg);
            let bound = plain.bind(&[0.3, -0.2, 0.5, 1.1]).with_temperature(1.3);
            let d = cfg.dim;
            let v: Vec<f64> = (0..8 * d).map(|i| ((i * 7919 % 113) as f64 / 113.0 - 0.5) * 2.5 * cfg.bound).collect();
            let (lp, g) = bound.log_prob_grad(&v);
            let lp0 = bound.log_prob(&v);
            let h = 1e-5;
            for (i, gi) in g.iter().enumerate() {
                assert!((lp[i / d] - lp0[i / d]).abs() < 1e-12, "log q with and without the tape");
                let (mut up, mut dn) = (v.clone(), v.clone());
                up[i] += h;
                dn[i] -= h;
                let fd = (bound.log_prob(&up)[i / d] - bound.log_prob(&dn)[i / d]) / (2.0 * h);
                assert!(
                    (fd - gi).abs() < 1e-5 * (1.0 + fd.abs()),
                    "blocks {}, point {} dim {}: fd {fd} vs {gi}",
                    cfg.blocks,
                    i / d,
                    i % d
                );
            }
        }
    }

    #[test]
    fn sigmoids_match_std_and_their_tangent_lines_touch() {
        let xs: Vec<f32> = (-4000..=4000).map(|i| i as f32 * 0.0237).chain([-200.0, -90.0, 0.0, 90.0, 200.0]).collect();
        let n = xs.len();
        let (mut s, mut s2, mut k, mut c) = (vec![0.0; n], vec![0.0; n], vec![0.0; n], vec![0.0; n]);
        sigmoids(&xs, &mut s, None);
        sigmoids(&xs, &mut s2, Some((&mut k, &mut c)));
        for i in 0..n {
            let x = f64::from(xs[i]);
            let want = 1.0 / (1.0 + (-x).exp());
            assert_eq!(s[i], s2[i]);
            assert!((f64::from(s[i]) - want).abs() <= 1.2e-7 * want + 1e-37, "σ({x}) = {} vs {want}", s[i]);
            let slope = want * (1.0 - want);
            assert!((f64::from(k[i]) - slope).abs() <= 1e-6 * slope + 1e-37, "σ'({x}) = {} vs {slope}", k[i]);
            // The line's value at x is σ(x), as the training's forward pass takes it.
            let at = f64::from(k[i]) * x + f64::from(c[i]);
            assert!((at - want).abs() < 1e-6, "line at {x}: {at} vs {want}");
        }
    }

    #[test]
    fn exp_neg_matches_std_within_4_ulp() {
        for i in 0..=200_000 {
            let x = -708.0 * (i as f64 / 200_000.0).powi(3);
            let (a, b) = (exp_neg::<false>(x), x.exp());
            assert!((a - b).abs() <= 4.0 * f64::EPSILON * b, "e^{x}: {a} vs {b}");
        }
        assert!(exp_neg::<false>(f64::NAN).is_nan());
        assert!(exp_neg::<false>(-1e4) >= 0.0 && exp_neg::<false>(-1e4) < 1e-300);
    }

    #[test]
    fn ln_1p_unit_matches_std_within_1_ulp() {
        let mut worst = 0.0f64;
        for i in 0..=200_000 {
            // 1e-300 … 1, denser near 1 and across the √2 − 1 switch.
            let x = if i % 2 == 0 { 10f64.powf(-300.0 * (i as f64 / 200_000.0).powi(3)) } else { i as f64 / 200_000.0 };
            let (a, b) = (ln_1p_unit(x), x.ln_1p());
            let ulp = f64::EPSILON * b.abs().max(f64::MIN_POSITIVE);
            worst = worst.max((a - b).abs() / ulp);
        }
        assert!(worst <= 1.0, "worst {worst} ulp");
        assert!(ln_1p_unit(f64::NAN).is_nan());
        assert_eq!(ln_1p_unit(0.0), 0.0);
    }

    #[test]
    fn spline_inverse_undoes_forward_with_the_same_slope() {
        let bins = 8;
        let raw: Vec<f64> = (0..3 * bins - 1).map(|i| ((i * 7919 % 101) as f64 / 50.0 - 1.0) * 2.0).collect();
        for i in 0..40 {
            let x = -5.5 + 11.0 * i as f64 / 39.0;
            let (y, slope) = spline_forward::<false>(x, &raw, bins, 5.0);
            let (back, slope2) = spline_inverse::<false>(y, &raw, bins, 5.0);
            assert!((back - x).abs() < 1e-9, "{x} → {y} → {back}");
            let (ld, ld2) = (slope.ln(), slope2.ln());
            assert!((ld - ld2).abs() < 1e-7);
            let h = 1e-6;
            let f = |x: f64| spline_forward::<false>(x, &raw, bins, 5.0).0;
            let fd = (f(x + h) - f(x - h)) / (2.0 * h);
            assert!((fd.ln() - ld).abs() < 1e-5, "x = {x}: {} vs {ld}", fd.ln());
        }
    }

    #[test]
    fn tempered_flow_is_a_normalised_density_consistent_in_both_directions() {
        let dev = Device::flex();
        let cfg = FlowConfig { lu: true, ..FlowConfig::new(2, 3, true) };
        let plain = with_random_lu(Flow::seeded(&cfg, &dev, Some(3)), 2, 0.3).plain(&cfg);
        let bound = plain.bind(&[0.3, -0.2, 0.5]).with_temperature(1.7);
        let z: Vec<f64> = (0..64 * 2).map(|i| ((i * 7919 % 113) as f64 / 113.0 - 0.5) * 4.0).collect();
        let (v, lp) = bound.sample(&z);
        for (a, b) in lp.iter().zip(bound.log_prob(&v)) {
            assert!((a - b).abs() < 1e-6 * (1.0 + a.abs()), "one-pass log q {a} vs forward {b}");
        }
        // ∫ q_T dv = 1 on a grid wide enough for T = 1.7 (midpoint rule, 2-D).
        let (h, half) = (0.05, 16.0);
        let m = (2.0 * half / h) as usize;
        let pts: Vec<f64> =
            (0..m * m).flat_map(|k| [-half + h * (0.5 + (k / m) as f64), -half + h * (0.5 + (k % m) as f64)]).collect();
        let mass: f64 = bound.log_prob(&pts).iter().map(|l| l.exp()).sum::<f64>() * h * h;
        assert!((mass - 1.0).abs() < 2e-3, "tempered mass {mass}");
    }

    /// Above `SERIAL_ELEMENTS` the spline pass runs in rayon chunks: the same numbers as
    /// one serial pass over all elements.
    #[test]
    fn parallel_spline_pass_equals_the_serial_one() {
        let (bins, n) = (10, SERIAL_ELEMENTS + 1_000);
        let np = 3 * bins - 1;
        let raw: Vec<f32> = (0..n * np).map(|i| ((i * 7919 % 211) as f32 / 105.0 - 1.0) * 3.0).collect();
        let x: Vec<f32> = (0..n).map(|i| ((i * 104_729 % 97) as f32 / 96.0 - 0.5) * 7.0).collect();
        let run = |parallel: bool| {
            let (mut y, mut ld) = (vec![0.0; n], vec![0.0; n]);
            let (mut jy, mut jl) = (vec![0.0; n * (np + 1)], vec![0.0; n * (np + 1)]);
            let jac = Some((&mut jy[..], &mut jl[..]));
            if parallel {
                spline_jacobians(&x, &raw, bins, 3.0, (&mut y, &mut ld), jac);
            } else {
                lane_jacobians::chunk(&x, &raw, bins, 3.0, (&mut y, &mut ld), jac);
            }
            (y, ld, jy, jl)
        };
        assert!(run(true) == run(false));
    }
}
