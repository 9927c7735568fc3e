//! The training's spline pass with its Jacobians, four elements at a time.
//!
//! Profiled on the 10-D Gaussian task, the scalar pass ([`super::spline_jacobian`]) was
//! about 29 % of a training, one element's softmaxes and derivatives at a time. Here four
//! elements run in one AVX2 register, with the lane kernel's exponentials, bin search and
//! knots ([`super::lanes`]); each lane computes what the scalar pass computes, operation
//! for operation (the same FMAs, libm's `ln` and `exp` lane by lane where the scalar pass
//! calls them), so the two agree bit for bit (`tests`) and a seed trains the same flow
//! as before.

/// Elements per group.
const LANES: usize = 4;

/// [`super::jacobian_chunk_with`] on one chunk (layouts as there; without `jacobians`, y
/// and log f′ only: the validation pass): where the CPU has AVX2 and FMA, the whole groups
/// of four in lanes and the last 1–3 elements on the scalar pass compiled alike; else the
/// scalar pass throughout. The one place the features are detected.
pub(super) fn chunk(
    x: &[f32],
    raw: &[f32],
    bins: usize,
    bound: f64,
    out: (&mut [f32], &mut [f32]),
    jacobians: Option<(&mut [f32], &mut [f32])>,
) {
    #[cfg(target_arch = "x86_64")]
    {
        use std::arch::is_x86_feature_detected as has;
        if has!("avx2") && has!("fma") && has!("avx512f") && has!("avx512vl") {
            // SAFETY: the CPU has the features `avx512vl::chunk` is compiled for (just detected).
            return unsafe { avx512vl::chunk(x, raw, bins, bound, out, jacobians) };
        }
        if has!("avx2") && has!("fma") {
            // SAFETY: the CPU has the features `avx2::chunk` is compiled for (just detected).
            return unsafe { avx2::chunk(x, raw, bins, bound, out, jacobians) };
        }
    }
    super::jacobian_chunk_with::<false>(x, raw, bins, bound, out, jacobians);
}

/// The Jacobian kernel as module `$name`, compiled for `$features` with the lane kernel
/// of the same name.
macro_rules! jacobian_kernel {
    ($name:ident, $features:literal) => {
        #[cfg(target_arch = "x86_64")]
        mod $name {
            use super::super::lanes::$name::{V, add, axis, blend, eq, knot, mul, set, softplus, store, sub, unit};
            use super::super::{MIN_HEIGHT, MIN_WIDTH, jacobian_chunk_with};
            use super::LANES;
            use std::arch::x86_64::*;

            #[target_feature(enable = $features)]
            fn div(a: V, b: V) -> V {
                _mm256_div_pd(a, b)
            }

            /// −a (the sign flipped, as Rust's unary minus).
            #[target_feature(enable = $features)]
            fn neg(a: V) -> V {
                _mm256_xor_pd(a, set(-0.0))
            }

            /// a < b lane by lane.
            #[target_feature(enable = $features)]
            fn less(a: V, b: V) -> V {
                _mm256_cmp_pd::<_CMP_LT_OQ>(a, b)
            }

            /// Four f32 widened to f64.
            #[target_feature(enable = $features)]
            fn widen(v: [f32; 4]) -> V {
                _mm256_cvtps_pd(_mm_setr_ps(v[0], v[1], v[2], v[3]))
            }

            /// `super::chunk` for a CPU with these features.
            #[target_feature(enable = $features)]
            pub(super) fn chunk(
                x: &[f32],
                raw: &[f32],
                bins: usize,
                bound: f64,
                (y, ld): (&mut [f32], &mut [f32]),
                mut jacobians: Option<(&mut [f32], &mut [f32])>,
            ) {
                let np = 3 * bins - 1;
                let lanes = jacobians.as_mut().map(|(jy, jl)| (&mut **jy, &mut **jl));
                let done = self::jacobians(x, raw, bins, bound, (&mut *y, &mut *ld), lanes);
                let rest = jacobians.map(|(jy, jl)| (&mut jy[done * (np + 1)..], &mut jl[done * (np + 1)..]));
                let (x, raw, y, ld) = (&x[done..], &raw[done * np..], &mut y[done..], &mut ld[done..]);
                jacobian_chunk_with::<true>(x, raw, bins, bound, (y, ld), rest);
            }

            /// The leading whole groups of four elements; returns how many elements it did.
            #[target_feature(enable = $features)]
            pub(super) fn jacobians(
                x: &[f32],
                raw: &[f32],
                bins: usize,
                bound: f64,
                (y, ld): (&mut [f32], &mut [f32]),
                mut jacobians: Option<(&mut [f32], &mut [f32])>,
            ) -> usize {
                let whole = x.len() / LANES * LANES;
                // The softmax weights' buffers, set anew for each group's first `bins`.
                let zero = _mm256_setzero_pd();
                let mut weights = ([zero; 32], [zero; 32]);
                for e in (0..whole).step_by(LANES) {
                    let jacobians = jacobians.as_mut().map(|(jy, jl)| (&mut **jy, &mut **jl));
                    group(x, raw, (bins, bound), e, &mut weights, (y, ld), jacobians);
                }
                whole
            }

            /// Elements e..e + 4: lane by lane `super::super::spline_jacobian::<true>` inside
            /// the bound and the identity beyond it, as `jacobian_chunk_with` writes them
            /// (without Jacobians, `spline_forward`'s y and log f′, the same terms).
            #[allow(clippy::too_many_arguments)]
            #[target_feature(enable = $features)]
            fn group(
                x: &[f32],
                raw: &[f32],
                (bins, bound): (usize, f64),
                e: usize,
                (wx, wy): &mut ([V; 32], [V; 32]),
                (y, ld): (&mut [f32], &mut [f32]),
                jacobians: Option<(&mut [f32], &mut [f32])>,
            ) {
                let np = 3 * bins - 1;
                let param = |j: usize| widen(std::array::from_fn(|l| raw[(e + l) * np + j]));
                let v = widen(std::array::from_fn(|l| x[e + l]));
                let b = set(bound);
                let zero = _mm256_setzero_pd();
                let (sx, tx) = axis(wx, |j| param(j), bins, MIN_WIDTH);
                let (sy, ty) = axis(wy, |j| param(bins + j), bins, MIN_HEIGHT);
                // The active bin on x, as the lane kernel's search.
                let (mut k, mut acc) = (zero, zero);
                for w in &wx[..bins - 1] {
                    let next = add(add(acc, mul(*w, sx)), set(MIN_WIDTH));
                    let passed = _mm256_cmp_pd::<_CMP_NLT_UQ>(v, knot(next, b));
                    k = add(k, _mm256_and_pd(passed, set(1.0)));
                    acc = next;
                }
                // The active bin's knots and interior derivatives' raw values.
                let (mut ax, mut ay) = (zero, zero);
                let [mut x0, mut x1, mut y0, mut y1, mut r0, mut r1] = [zero; 6];
                for j in 0..bins {
                    let at = eq(k, set(j as f64));
                    let nx = add(add(ax, mul(wx[j], sx)), set(MIN_WIDTH));
                    let ny = add(add(ay, mul(wy[j], sy)), set(MIN_HEIGHT));
                    (x0, x1, y0, y1) = (blend(x0, ax, at), blend(x1, nx, at), blend(y0, ay, at), blend(y1, ny, at));
                    if j + 1 < bins {
                        let rd = param(2 * bins + j);
                        r0 = blend(r0, rd, eq(k, set((j + 1) as f64)));
                        r1 = blend(r1, rd, at);
                    }
                    (ax, ay) = (nx, ny);
                }
                let last = eq(k, set((bins - 1) as f64));
                let (x0, y0) = (knot(x0, b), knot(y0, b));
                let w = sub(blend(knot(x1, b), b, last), x0);
                let h = sub(blend(knot(y1, b), b, last), y0);
                let d0 = blend(softplus(r0), set(1.0), eq(k, zero));
                let d1 = blend(softplus(r1), set(1.0), last);
                // `super::super::local`'s terms.
                let (one, two) = (set(1.0), set(2.0));
                let delta = div(h, w);
                let t = unit(div(sub(v, x0), w));
                let one_t = sub(one, t);
                let t1 = mul(t, one_t);
                let two_delta = mul(two, delta);
                let s = sub(add(d0, d1), two_delta);
                let den = add(delta, mul(s, t1));
                let a = add(mul(mul(delta, t), t), mul(d0, t1));
                let out_y = add(y0, div(mul(h, a), den));
                let n2 = add(add(mul(mul(d1, t), t), mul(two_delta, t1)), mul(mul(d0, one_t), one_t));
                let slope = div(mul(mul(delta, delta), n2), mul(den, den));
                let Some((jy, jl)) = jacobians else {
                    let [xs, out_y, slope] = [v, out_y, slope].map(|q| store(q));
                    for l in 0..LANES {
                        (y[e + l], ld[e + l]) = if xs[l].abs() > bound {
                            (xs[l] as f32, 0.0)
                        } else {
                            (out_y[l] as f32, slope[l].ln() as f32)
                        };
                    }
                    return;
                };
                let one_2t = sub(one, mul(two, t));
                let den_t = mul(s, one_2t);
                let den_delta = sub(one, mul(two, t1));
                let a_t = add(mul(two_delta, t), mul(d0, one_2t));
                let n2_t = sub(add(mul(mul(two, d1), t), mul(two_delta, one_2t)), mul(mul(two, d0), one_t));
                let den2 = mul(den, den);
                // `super::super::spline_jacobian`'s partials: of y, then of log f′.
                let yt = div(mul(h, sub(mul(a_t, den), mul(a, den_t))), den2);
                let ydelta = div(mul(h, sub(mul(mul(t, t), den), mul(a, den_delta))), den2);
                let yd0 = div(mul(mul(h, t1), sub(den, a)), den2);
                let yd1 = div(mul(mul(neg(h), a), t1), den2);
                let yh = add(div(a, den), div(ydelta, w));
                let two_t1_den = div(mul(two, t1), den);
                let lt = sub(div(n2_t, n2), div(mul(two, den_t), den));
                let ldelta = sub(add(div(two, delta), div(mul(two, t1), n2)), div(mul(two, den_delta), den));
                let ld0 = sub(div(mul(one_t, one_t), n2), two_t1_den);
                let ld1 = sub(div(mul(t, t), n2), two_t1_den);
                let lh = div(ldelta, w);
                let via = |gt: V, gdelta: V| {
                    (div(gt, w), div(neg(gt), w), sub(div(mul(neg(gt), t), w), div(mul(gdelta, delta), w)))
                };
                let ((yx, yx0, yw), (lx, lx0, lw)) = (via(yt, ydelta), via(lt, ldelta));
                let at = |l: usize| (e + l) * (np + 1);
                // Empty sums as Rust's (−0.0), for the shares below the active bin.
                let empty = set(std::iter::empty::<f64>().sum());
                for (axis, ew, total, min, (y_lo, y_len), (l_lo, l_len)) in [
                    (0, &mut *wx, tx, MIN_WIDTH, (yx0, yw), (lx0, lw)),
                    (1, &mut *wy, ty, MIN_HEIGHT, (one, yh), (zero, lh)),
                ] {
                    // Each bin's share of the axis (in place of its weight), the active
                    // bin's, and theirs below it summed in order.
                    let (mut below, mut share) = (empty, zero);
                    for (j, ej) in ew.iter_mut().enumerate().take(bins) {
                        *ej = div(*ej, total);
                        let (at, under) = (eq(k, set(j as f64)), less(set(j as f64), k));
                        (below, share) = (blend(below, add(below, *ej), under), blend(share, *ej, at));
                    }
                    let c = set(2.0 * bound * (1.0 - bins as f64 * min));
                    let (y_mean, l_mean) =
                        (add(mul(y_lo, below), mul(y_len, share)), add(mul(l_lo, below), mul(l_len, share)));
                    for (i, ei) in ew.iter().enumerate().take(bins) {
                        let si = mul(c, *ei);
                        let (is, under) = (eq(k, set(i as f64)), less(set(i as f64), k));
                        let gy = blend(blend(zero, y_len, is), y_lo, under);
                        let gl = blend(blend(zero, l_len, is), l_lo, under);
                        let (vy, vl) = (store(mul(si, sub(gy, y_mean))), store(mul(si, sub(gl, l_mean))));
                        for l in 0..LANES {
                            (jy[at(l) + axis * bins + i], jl[at(l) + axis * bins + i]) = (vy[l] as f32, vl[l] as f32);
                        }
                    }
                }
                let [ks, xs, out_y, slope, yx, lx, yd0, yd1, ld0, ld1] =
                    [k, v, out_y, slope, yx, lx, yd0, yd1, ld0, ld1].map(|q| store(q));
                for l in 0..LANES {
                    let (jy, jl) = (&mut jy[at(l)..at(l) + np + 1], &mut jl[at(l)..at(l) + np + 1]);
                    if xs[l].abs() > bound {
                        // The identity tail.
                        jy.iter_mut().chain(jl.iter_mut()).for_each(|v| *v = 0.0);
                        (y[e + l], ld[e + l], jy[np]) = (xs[l] as f32, 0.0, 1.0);
                        continue;
                    }
                    // Interior derivatives: softplus, ∂/∂r = σ(r), libm's exp as the scalar pass.
                    jy[2 * bins..np].iter_mut().chain(jl[2 * bins..np].iter_mut()).for_each(|v| *v = 0.0);
                    let kl = ks[l] as usize;
                    for (knot, gy, gl) in [(kl, yd0[l], ld0[l]), (kl + 1, yd1[l], ld1[l])] {
                        if knot > 0 && knot < bins {
                            let j = 2 * bins + knot - 1;
                            let sg = 1.0 / (1.0 + (-f64::from(raw[(e + l) * np + j])).exp());
                            (jy[j], jl[j]) = ((gy * sg) as f32, (gl * sg) as f32);
                        }
                    }
                    (y[e + l], ld[e + l], jy[np], jl[np]) =
                        (out_y[l] as f32, slope[l].ln() as f32, yx[l] as f32, lx[l] as f32);
                }
            }
        }
    };
}

jacobian_kernel!(avx2, "avx2,fma");
jacobian_kernel!(avx512vl, "avx2,fma,avx512f,avx512vl");

/// The lanes exist on x86-64 only.
#[cfg(all(test, target_arch = "x86_64"))]
mod tests {
    use super::super::jacobian_chunk_with;

    /// The lane kernels give the scalar pass's values, Jacobians and log-slopes bit for
    /// bit (and its values and log-slopes alone where no Jacobian is asked for), on points
    /// inside and beyond the bound and bin counts from 2 to 31, with a partial group left
    /// to the scalar pass. (A reordered operation in f64 seldom shows after rounding to
    /// f32; the trainings compared end to end in docs/results/npe.md are what show the
    /// same flows.)
    #[test]
    fn lanes_match_the_scalar_jacobians_exactly() {
        if !(std::arch::is_x86_feature_detected!("avx2") && std::arch::is_x86_feature_detected!("fma")) {
            return;
        }
        // Uniform on (−1, 1) from a xorshift stream.
        let mut state = 0x2545_f491_4f6c_dd1d_u64;
        let mut uniform = move || {
            state ^= state << 13;
            state ^= state >> 7;
            state ^= state << 17;
            (state >> 40) as f32 / (1u64 << 23) as f32 - 1.0
        };
        for (bins, n) in [(8, 4001), (10, 1037), (4, 1009), (2, 1005), (31, 502)] {
            let np = 3 * bins - 1;
            let bound = 3.0;
            let raw: Vec<f32> = (0..np * n).map(|_| uniform() * 3.0).collect();
            let x: Vec<f32> = (0..n).map(|_| uniform() * 3.5).collect();
            let run = |lanes: bool, with_jacobians: bool| {
                let (mut y, mut ld) = (vec![9.0f32; n], vec![9.0f32; n]);
                let (mut jy, mut jl) = (vec![9.0f32; n * (np + 1)], vec![9.0f32; n * (np + 1)]);
                let mut js = with_jacobians.then_some((&mut jy[..], &mut jl[..]));
                let done = if lanes {
                    let js = js.as_mut().map(|(a, b)| (&mut **a, &mut **b));
                    // SAFETY: the CPU has AVX2 and FMA (checked above).
                    unsafe { super::avx2::jacobians(&x, &raw, bins, bound, (&mut y, &mut ld), js) }
                } else {
                    0
                };
                let (ys, lds) = (&mut y[done..], &mut ld[done..]);
                let js = js.map(|(a, b)| (&mut a[done * (np + 1)..], &mut b[done * (np + 1)..]));
                // Outside an AVX2 function `FMA = true` calls libm's fma: the same rounding.
                jacobian_chunk_with::<true>(&x[done..], &raw[done * np..], bins, bound, (ys, lds), js);
                (done, [y, ld, jy, jl].map(|v| v.iter().map(|f| f.to_bits()).collect::<Vec<_>>()))
            };
            for with_jacobians in [true, false] {
                let ((done, lanes), (_, scalar)) = (run(true, with_jacobians), run(false, with_jacobians));
                assert_eq!(done, n / 4 * 4, "bins {bins}, n {n}: whole groups");
                for (what, (a, b)) in ["y", "log f′", "∂y", "∂ log f′"].iter().zip(lanes.iter().zip(&scalar)) {
                    assert_eq!(a, b, "bins {bins}, n {n}, Jacobians {with_jacobians}: {what}");
                }
            }
            let scalar = run(false, true).1;
            // Points on both sides of the bound, and Jacobians that are not all zero.
            assert!(x.iter().any(|v| v.abs() > 3.0) && x.iter().any(|v| v.abs() < 3.0));
            assert!(scalar[2].iter().filter(|&&b| f32::from_bits(b) != 0.0).count() > n * bins);
        }
    }
}
