//! The splines of a coupling over a block of samples, four samples at a time: the
//! sampling path's hot loop (`POST /infer` spent about a third of its CPU in the scalar
//! kernel, [`super::splines`]).
//!
//! The scalar kernel walks one sample's knots at a time, so only the exponentials of one
//! softmax run side by side, and its branches (the bin search, the end derivatives, the
//! tails beyond the bound) are per sample. Here the conditioner's output comes transposed
//! ([n × P], one parameter of every sample contiguous: [`super::batch_forward_t`]) and
//! every step — softmaxes, the bin search, the knots, the two end derivatives, the
//! quadratic — runs on four samples in one AVX2 register, the branches as selects. Each
//! lane computes what the scalar kernel computes, operation for operation (FMAs only
//! where the scalar kernel has them, in the exponential's polynomial), so the two agree
//! bit for bit (`tests`). Without AVX2 each sample's parameters are gathered and the
//! scalar kernel runs on them.

use super::Splines;

/// Every transformed dim of every sample of u [d × n] (the row of a sample contiguous)
/// through its spline, parameters `raw` [n × P] column-major (parameter p of sample i at
/// `p·n + i`, P = dt·(3K−1)), adding log |f′| to `logdet`.
pub(super) fn splines(s: &Splines, u: &mut [f64], raw: &[f64], n: usize, logdet: &mut [f64]) {
    let np = 3 * s.bins - 1;
    let p = (s.d - s.dc) * np;
    assert!(raw.len() >= p * n && u.len() >= s.d * n && logdet.len() >= n, "spline block sizes");
    #[cfg(target_arch = "x86_64")]
    {
        use std::arch::is_x86_feature_detected as has;
        if has!("avx2") && has!("fma") && has!("avx512f") && has!("avx512vl") {
            // SAFETY: the CPU has the features `avx512vl::splines` is compiled for (just detected).
            return unsafe { avx512vl::splines(s, u, raw, n, logdet) };
        }
        if has!("avx2") && has!("fma") {
            // SAFETY: the CPU has the features `avx2::splines` is compiled for (just detected).
            return unsafe { avx2::splines(s, u, raw, n, logdet) };
        }
    }
    portable(s, u, raw, n, logdet);
}

/// The scalar kernel on each sample's gathered parameters.
fn portable(s: &Splines, u: &mut [f64], raw: &[f64], n: usize, logdet: &mut [f64]) {
    let p = (s.d - s.dc) * (3 * s.bins - 1);
    let mut col = vec![0.0; p];
    for i in 0..n {
        for (q, c) in col.iter_mut().enumerate() {
            *c = raw[q * n + i];
        }
        super::splines(s, &mut u[i * s.d..(i + 1) * s.d], &col, &mut logdet[i..=i]);
    }
}

/// The lane kernel as module `$name`, every function compiled for `$features`: AVX2 and
/// FMA, and the same 256-bit code with AVX-512VL enabled besides, which gives the
/// register allocator 32 vector registers instead of 16 (the exponentials' constants stay
/// in registers: the sampling path's CPU −5 %, `otofit bench infer --direct`).
macro_rules! lane_kernel {
    ($name:ident, $features:literal) => {
        #[cfg(target_arch = "x86_64")]
        pub(super) mod $name {
            use super::super::{
                EXP_SHIFT, INV_FACT, LG, LN2_HI, LN2_LO, MIN_DERIVATIVE, MIN_HEIGHT, MIN_WIDTH, Splines,
            };
            use std::arch::x86_64::*;

            pub(in super::super) type V = __m256d;

            #[target_feature(enable = $features)]
            pub(in super::super) fn set(x: f64) -> V {
                _mm256_set1_pd(x)
            }

            #[target_feature(enable = $features)]
            pub(in super::super) fn add(a: V, b: V) -> V {
                _mm256_add_pd(a, b)
            }

            #[target_feature(enable = $features)]
            pub(in super::super) fn sub(a: V, b: V) -> V {
                _mm256_sub_pd(a, b)
            }

            #[target_feature(enable = $features)]
            pub(in super::super) fn mul(a: V, b: V) -> V {
                _mm256_mul_pd(a, b)
            }

            /// b where `mask`, else a.
            #[target_feature(enable = $features)]
            pub(in super::super) fn blend(a: V, b: V, mask: V) -> V {
                _mm256_blendv_pd(a, b, mask)
            }

            #[target_feature(enable = $features)]
            pub(in super::super) fn eq(a: V, b: V) -> V {
                _mm256_cmp_pd::<_CMP_EQ_OQ>(a, b)
            }

            /// Four values from `src[at..at + 4]`.
            #[target_feature(enable = $features)]
            fn load(src: &[f64], at: usize) -> V {
                let c = &src[at..at + 4];
                // SAFETY: `c` holds four f64 (checked by the slice); loadu takes any alignment.
                unsafe { _mm256_loadu_pd(c.as_ptr()) }
            }

            #[target_feature(enable = $features)]
            pub(in super::super) fn store(v: V) -> [f64; 4] {
                let mut a = [0.0; 4];
                // SAFETY: `a` holds four f64; storeu takes any alignment.
                unsafe { _mm256_storeu_pd(a.as_mut_ptr(), v) };
                a
            }

            /// `super::super::exp_neg::<true>` in lanes (the same operations, NaN kept).
            #[target_feature(enable = $features)]
            pub(in super::super) fn exp_neg(x: V) -> V {
                // max(−708, x) returns x when x is NaN, as the scalar clamp does.
                let x = _mm256_max_pd(set(-708.0), x);
                let shifted = _mm256_add_pd(_mm256_mul_pd(x, set(std::f64::consts::LOG2_E)), set(EXP_SHIFT));
                let n = _mm256_sub_pd(shifted, set(EXP_SHIFT));
                let r = _mm256_sub_pd(_mm256_sub_pd(x, _mm256_mul_pd(n, set(LN2_HI))), _mm256_mul_pd(n, set(LN2_LO)));
                let mut p = set(INV_FACT[0]);
                for &c in &INV_FACT[1..] {
                    p = _mm256_fmadd_pd(p, r, set(c));
                }
                let k = _mm256_sub_epi64(_mm256_castpd_si256(shifted), _mm256_castpd_si256(set(EXP_SHIFT)));
                let two_n = _mm256_slli_epi64::<52>(_mm256_add_epi64(k, _mm256_set1_epi64x(1023)));
                _mm256_mul_pd(p, _mm256_castsi256_pd(two_n))
            }

            /// softplus(r) + MIN_DERIVATIVE, as `super::super::derivative`.
            #[target_feature(enable = $features)]
            pub(in super::super) fn softplus(r: V) -> V {
                // −|r|: the sign bit set.
                let l = ln_1p_unit(exp_neg(_mm256_or_pd(r, set(-0.0))));
                _mm256_add_pd(_mm256_add_pd(_mm256_max_pd(r, _mm256_setzero_pd()), l), set(MIN_DERIVATIVE))
            }

            /// `super::super::ln_1p_unit` in lanes (the same operations).
            #[target_feature(enable = $features)]
            fn ln_1p_unit(x: V) -> V {
                let u = add(set(1.0), x);
                let c = _mm256_div_pd(sub(x, sub(u, set(1.0))), u);
                let big = _mm256_cmp_pd::<_CMP_GT_OQ>(u, set(std::f64::consts::SQRT_2));
                let m = blend(u, mul(u, set(0.5)), big);
                let k = _mm256_and_pd(big, set(1.0));
                let f = sub(m, set(1.0));
                let s = _mm256_div_pd(f, add(set(2.0), f));
                let z = mul(s, s);
                let w = mul(z, z);
                let t1 = mul(w, add(set(LG[1]), mul(w, add(set(LG[3]), mul(w, set(LG[5]))))));
                let t2 = mul(z, add(set(LG[0]), mul(w, add(set(LG[2]), mul(w, add(set(LG[4]), mul(w, set(LG[6]))))))));
                let r = add(t2, t1);
                let hfsq = mul(mul(set(0.5), f), f);
                let inner = add(mul(s, add(hfsq, r)), add(mul(k, set(LN2_LO)), c));
                sub(mul(k, set(LN2_HI)), sub(sub(hfsq, inner), f))
            }

            /// The knot at cumulative weight c: c·2·bound − bound.
            #[target_feature(enable = $features)]
            pub(in super::super) fn knot(c: V, bound: V) -> V {
                _mm256_sub_pd(_mm256_mul_pd(_mm256_mul_pd(c, set(2.0)), bound), bound)
            }

            /// Softmax weights of one knot axis (K raw values, the lanes' j-th from `param(j)`),
            /// as `super::super::axis_weights`: e into `e`; (scale, Σ e) returned.
            #[target_feature(enable = $features)]
            pub(in super::super) fn axis(e: &mut [V; 32], param: impl Fn(usize) -> V, bins: usize, min: f64) -> (V, V) {
                let mut m = set(f64::NEG_INFINITY);
                for (j, ej) in e.iter_mut().enumerate().take(bins) {
                    *ej = param(j);
                    m = _mm256_max_pd(m, *ej);
                }
                let mut s = _mm256_setzero_pd();
                for ej in e.iter_mut().take(bins) {
                    *ej = exp_neg(_mm256_sub_pd(*ej, m));
                    s = _mm256_add_pd(s, *ej);
                }
                (_mm256_div_pd(set(1.0 - bins as f64 * min), s), s)
            }

            /// f′ at t in a bin of slope delta with end derivatives d0, d1 (`super::super::slope`).
            #[target_feature(enable = $features)]
            fn slope(delta: V, d0: V, d1: V, t: V) -> V {
                let one_t = sub(set(1.0), t);
                let t1 = mul(t, one_t);
                let den = add(delta, mul(sub(add(d0, d1), mul(set(2.0), delta)), t1));
                let n2 = add(add(mul(mul(d1, t), t), mul(mul(set(2.0), delta), t1)), mul(mul(d0, one_t), one_t));
                _mm256_div_pd(mul(mul(delta, delta), n2), mul(den, den))
            }

            /// `x` clamped to [0, 1] as f64::clamp does (NaN stays NaN).
            #[target_feature(enable = $features)]
            pub(in super::super) fn unit(x: V) -> V {
                let x = _mm256_blendv_pd(x, _mm256_setzero_pd(), _mm256_cmp_pd::<_CMP_LT_OQ>(x, _mm256_setzero_pd()));
                _mm256_blendv_pd(x, set(1.0), _mm256_cmp_pd::<_CMP_GT_OQ>(x, set(1.0)))
            }

            /// One dim's spline at `v` for four samples (forward: y = f(v); inverse: x = f⁻¹(v))
            /// and |f′| there; parameter j of the lanes at `src[(first + j)·stride + off..][..4]`.
            /// Lane by lane what `super::super::spline_forward` / `spline_inverse` give.
            #[target_feature(enable = $features)]
            fn spline(s: &Splines, v: V, src: &[f64], stride: usize, off: usize, first: usize) -> (V, V) {
                let bins = s.bins;
                let bound = set(s.bound);
                let (mut wx, mut wy) = ([_mm256_setzero_pd(); 32], [_mm256_setzero_pd(); 32]);
                let sx = axis(&mut wx, |j| load(src, (first + j) * stride + off), bins, MIN_WIDTH).0;
                let sy = axis(&mut wy, |j| load(src, (first + bins + j) * stride + off), bins, MIN_HEIGHT).0;
                let (search, scale, min) = if s.inverse { (&wy, sy, MIN_HEIGHT) } else { (&wx, sx, MIN_WIDTH) };
                // The active bin: the count of leading interior knots not above v (the scalar
                // search stops at the first knot above v; the knots rise, so the count is its
                // stop; a NaN v passes every knot there and here).
                let (mut k, mut acc) = (_mm256_setzero_pd(), _mm256_setzero_pd());
                for w in &search[..bins - 1] {
                    let next = add(add(acc, mul(*w, scale)), set(min));
                    let passed = _mm256_cmp_pd::<_CMP_NLT_UQ>(v, knot(next, bound));
                    k = add(k, _mm256_and_pd(passed, set(1.0)));
                    acc = next;
                }
                // The active bin's cumulative weights on both axes and the raw values of its two
                // interior end derivatives.
                let (mut ax, mut ay) = (_mm256_setzero_pd(), _mm256_setzero_pd());
                let [mut x0, mut x1, mut y0, mut y1, mut r0, mut r1] = [_mm256_setzero_pd(); 6];
                for j in 0..bins {
                    let at = eq(k, set(j as f64));
                    let nx = add(add(ax, mul(wx[j], sx)), set(MIN_WIDTH));
                    let ny = add(add(ay, mul(wy[j], sy)), set(MIN_HEIGHT));
                    (x0, x1, y0, y1) = (blend(x0, ax, at), blend(x1, nx, at), blend(y0, ay, at), blend(y1, ny, at));
                    if j + 1 < bins {
                        let rd = load(src, (first + 2 * bins + j) * stride + off);
                        r0 = blend(r0, rd, eq(k, set((j + 1) as f64)));
                        r1 = blend(r1, rd, at);
                    }
                    (ax, ay) = (nx, ny);
                }
                let last = eq(k, set((bins - 1) as f64));
                let (x0, y0) = (knot(x0, bound), knot(y0, bound));
                let w = sub(blend(knot(x1, bound), bound, last), x0);
                let h = sub(blend(knot(y1, bound), bound, last), y0);
                let d0 = blend(softplus(r0), set(1.0), eq(k, _mm256_setzero_pd()));
                let d1 = blend(softplus(r1), set(1.0), last);
                let delta = _mm256_div_pd(h, w);
                let two_delta = mul(set(2.0), delta);
                let (out, t) = if s.inverse {
                    let dy = sub(v, y0);
                    let s = sub(add(d0, d1), two_delta);
                    let a = add(mul(h, sub(delta, d0)), mul(dy, s));
                    let b = sub(mul(h, d0), mul(dy, s));
                    let c = mul(_mm256_xor_pd(delta, set(-0.0)), dy);
                    let disc = _mm256_max_pd(sub(mul(b, b), mul(mul(set(4.0), a), c)), _mm256_setzero_pd());
                    let neg_b = _mm256_xor_pd(b, set(-0.0));
                    let t = unit(_mm256_div_pd(mul(set(2.0), c), sub(neg_b, _mm256_sqrt_pd(disc))));
                    (add(mul(t, w), x0), t)
                } else {
                    let t = unit(_mm256_div_pd(sub(v, x0), w));
                    let t1 = mul(t, sub(set(1.0), t));
                    let num = mul(h, add(mul(mul(delta, t), t), mul(d0, t1)));
                    let den = add(delta, mul(sub(add(d0, d1), two_delta), t1));
                    (add(y0, _mm256_div_pd(num, den)), t)
                };
                let f = slope(delta, d0, d1, t);
                // Beyond the bound the spline is the identity.
                let abs = _mm256_andnot_pd(set(-0.0), v);
                let outside = _mm256_cmp_pd::<_CMP_GT_OQ>(abs, bound);
                (blend(out, v, outside), blend(f, set(1.0), outside))
            }

            /// Samples g..g + live (live ≤ 4) of u through their splines; the lanes' parameter p
            /// at `src[p·stride + off..][..4]`.
            #[allow(clippy::too_many_arguments)]
            #[target_feature(enable = $features)]
            fn group(
                s: &Splines,
                u: &mut [f64],
                src: &[f64],
                stride: usize,
                off: usize,
                g: usize,
                live: usize,
                ld: &mut [f64],
            ) {
                let (d, dc) = (s.d, s.dc);
                let np = 3 * s.bins - 1;
                let mut jac = [1.0; 4];
                for k in 0..d - dc {
                    let at = |l: usize| (g + l.min(live - 1)) * d + dc + k;
                    let v = _mm256_setr_pd(u[at(0)], u[at(1)], u[at(2)], u[at(3)]);
                    let (y, f) = spline(s, v, src, stride, off, k * np);
                    let (y, f) = (store(y), store(f));
                    for l in 0..live {
                        u[(g + l) * d + dc + k] = y[l];
                        jac[l] *= f[l];
                    }
                }
                for l in 0..live {
                    ld[g + l] += jac[l].ln();
                }
            }

            /// [`super::splines`] with AVX2 and FMA: whole groups of four read `raw` in place; a
            /// last, partial group reads a copy padded with its last sample.
            #[target_feature(enable = $features)]
            pub(super) fn splines(s: &Splines, u: &mut [f64], raw: &[f64], n: usize, logdet: &mut [f64]) {
                let full = n / 4 * 4;
                for g in (0..full).step_by(4) {
                    group(s, u, raw, n, g, g, 4, logdet);
                }
                if full < n {
                    let live = n - full;
                    let p = (s.d - s.dc) * (3 * s.bins - 1);
                    let pad: Vec<f64> = (0..p * 4).map(|q| raw[(q / 4) * n + full + (q % 4).min(live - 1)]).collect();
                    group(s, u, &pad, 4, 0, full, live, logdet);
                }
            }
        }
    };
}

lane_kernel!(avx2, "avx2,fma");
lane_kernel!(avx512vl, "avx2,fma,avx512f,avx512vl");

#[cfg(test)]
mod tests {
    use super::super::{Splines, splines as scalar};
    use super::{portable, splines};

    /// The lane kernels (AVX-512VL, AVX2, portable) give the scalar kernel's values bit
    /// for bit, both ways, on block sizes that leave partial groups, with points inside and
    /// beyond the bound.
    #[test]
    fn lanes_match_the_scalar_kernel_exactly() {
        for (bins, n) in [(10, 128), (10, 37), (4, 3), (2, 1), (31, 9)] {
            let (d, dc) = (7, 3);
            let np = 3 * bins - 1;
            let p = (d - dc) * np;
            // raw [P × n] (scalar layout) and its transpose [n × P].
            let raw: Vec<f64> = (0..p * n).map(|i| ((i * 7919 % 211) as f64 / 105.0 - 1.0) * 3.0).collect();
            let raw_t: Vec<f64> = (0..p * n).map(|k| raw[(k % n) * p + k / n]).collect();
            let u0: Vec<f64> = (0..d * n).map(|i| ((i * 104_729 % 223) as f64 / 111.0 - 1.0) * 3.5).collect();
            for inverse in [false, true] {
                let s = Splines { d, dc, bins, bound: 3.0, inverse };
                let (mut u1, mut u2, mut u3) = (u0.clone(), u0.clone(), u0.clone());
                let (mut l1, mut l2, mut l3) = (vec![0.5; n], vec![0.5; n], vec![0.5; n]);
                scalar(&s, &mut u1, &raw, &mut l1);
                splines(&s, &mut u2, &raw_t, n, &mut l2);
                portable(&s, &mut u3, &raw_t, n, &mut l3);
                let bits = |v: &[f64]| v.iter().map(|x| x.to_bits()).collect::<Vec<_>>();
                let what = format!("bins {bins}, n {n}, inverse {inverse}");
                assert_eq!(bits(&u1), bits(&u2), "{what}: points");
                assert_eq!(bits(&l1), bits(&l2), "{what}: log-determinants");
                assert_eq!((bits(&u1), bits(&l1)), (bits(&u3), bits(&l3)), "{what}: portable");
                // The AVX2-only kernel too, where the dispatch chose the AVX-512VL one.
                #[cfg(target_arch = "x86_64")]
                if std::arch::is_x86_feature_detected!("avx2") && std::arch::is_x86_feature_detected!("fma") {
                    let (mut u4, mut l4) = (u0.clone(), vec![0.5; n]);
                    // SAFETY: the CPU has AVX2 and FMA (just detected).
                    unsafe { super::avx2::splines(&s, &mut u4, &raw_t, n, &mut l4) };
                    assert_eq!((bits(&u1), bits(&l1)), (bits(&u4), bits(&l4)), "{what}: AVX2");
                }
                assert!(u0.iter().zip(&u1).any(|(a, b)| a != b) && l1.iter().all(|v| v.is_finite()));
            }
        }
    }
}
