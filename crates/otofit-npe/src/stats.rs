//! Small statistics shared by every layer: quantiles of sorted samples, means and
//! standard deviations, and Spearman's rank correlation. Pure functions on slices, no
//! dependencies, so that any module can use them without importing another layer.
//!
//! Three quantile definitions are in use, each kept where results were measured with it
//! (changing one would move published numbers):
//! - [`quantile_linear`] interpolates between order statistics (posterior summaries:
//!   smooth in the samples);
//! - [`quantile_nearest`] takes the nearest order statistic (null thresholds and reading
//!   against normal ranges: a value that was actually observed);
//! - [`quantile_floor`] rounds the rank down (predictive bands and marginal coverage:
//!   never the outermost sample for a 90 % band of few draws).

#![warn(missing_docs)]

/// `q` quantile of ascending `sorted` by linear interpolation between order statistics
/// at position q·(n − 1). Panics on an empty slice.
pub fn quantile_linear(sorted: &[f64], q: f64) -> f64 {
    let pos = q * (sorted.len() - 1) as f64;
    let (i, frac) = (pos.floor() as usize, pos - pos.floor());
    if i + 1 < sorted.len() { sorted[i] * (1.0 - frac) + sorted[i + 1] * frac } else { sorted[i] }
}

/// `q` quantile of ascending `sorted`: the order statistic nearest to rank q·(n − 1);
/// `None` for an empty slice.
pub fn quantile_nearest(sorted: &[f64], q: f64) -> Option<f64> {
    let n = sorted.len().checked_sub(1)?;
    sorted.get((n as f64 * q).round() as usize).copied()
}

/// `q` quantile of ascending `sorted`: the order statistic at rank ⌊q·(n − 1)⌋. Panics on
/// an empty slice.
pub fn quantile_floor(sorted: &[f64], q: f64) -> f64 {
    sorted[(q * (sorted.len() - 1) as f64) as usize]
}

/// The upper median of ascending `sorted` (the order statistic at n/2); NaN when empty.
pub fn median_upper(sorted: &[f64]) -> f64 {
    sorted.get(sorted.len() / 2).copied().unwrap_or(f64::NAN)
}

/// Sorts `v` ascending (NaN last, by `total_cmp`) and returns it. Unstable (faster): values
/// equal under `total_cmp` have the same bits, so the order is the stable sort's.
pub fn sorted(mut v: Vec<f64>) -> Vec<f64> {
    v.sort_unstable_by(f64::total_cmp);
    v
}

/// Arithmetic mean; NaN when empty.
pub fn mean(v: impl IntoIterator<Item = f64>) -> f64 {
    let (sum, n) = v.into_iter().fold((0.0, 0usize), |(s, n), x| (s + x, n + 1));
    sum / n as f64
}

/// Mean and population standard deviation (divided by n).
pub fn mean_std_population(v: &[f64]) -> (f64, f64) {
    let n = v.len() as f64;
    let m = v.iter().sum::<f64>() / n;
    let var = v.iter().map(|x| (x - m).powi(2)).sum::<f64>() / n;
    (m, var.sqrt())
}

/// Mean and sample variance (divided by n − 1, at least 1).
pub fn mean_var_sample(v: &[f64]) -> (f64, f64) {
    let n = v.len() as f64;
    let m = v.iter().sum::<f64>() / n;
    let var = v.iter().map(|x| (x - m).powi(2)).sum::<f64>() / (n - 1.0).max(1.0);
    (m, var)
}

/// Ranks 0..n of `v` (ties in input order).
pub fn ranks(v: &[f64]) -> Vec<f64> {
    let mut idx: Vec<usize> = (0..v.len()).collect();
    idx.sort_by(|&a, &b| v[a].total_cmp(&v[b]));
    let mut r = vec![0.0; v.len()];
    for (k, &i) in idx.iter().enumerate() {
        r[i] = k as f64;
    }
    r
}

/// Spearman rank correlation (no tie correction; spectra rarely tie).
pub fn spearman(a: &[f64], b: &[f64]) -> f64 {
    let (ra, rb) = (ranks(a), ranks(b));
    let n = a.len() as f64;
    let m = (n - 1.0) / 2.0;
    let cov: f64 = ra.iter().zip(&rb).map(|(x, y)| (x - m) * (y - m)).sum();
    let var: f64 = ra.iter().map(|x| (x - m).powi(2)).sum();
    cov / var
}

/// Spearman ρ per block of `a` and `b` cut into `blocks` equal blocks (one per measure
/// of a measure-major feature vector).
pub fn spearman_per_block(a: &[f64], b: &[f64], blocks: usize) -> Vec<f64> {
    let n = a.len() / blocks.max(1);
    (0..blocks).map(|m| spearman(&a[m * n..(m + 1) * n], &b[m * n..(m + 1) * n])).collect()
}

/// Upper thresholds, one per statistic (`stats[j][i]`: statistic j of case i), such that
/// at most a fraction `1 − level` of the cases exceed any of them: a check that fails when
/// any statistic exceeds its threshold then keeps the false-alarm rate `level` promises,
/// where each statistic held to its own `level` quantile would fail up to m times as many
/// cases. Each threshold is its statistic's (k + 1)-th largest value, the same k for all,
/// k as large as that budget allows. Statistics of unequal length are cut to the shortest;
/// no cases: infinite thresholds.
pub fn joint_upper_thresholds(stats: &[Vec<f64>], level: f64) -> Vec<f64> {
    let n = stats.iter().map(Vec::len).min().unwrap_or(0);
    if n == 0 {
        return vec![f64::INFINITY; stats.len()];
    }
    let budget = ((1.0 - level) * n as f64 + 1e-9).floor() as usize;
    let ordered: Vec<Vec<f64>> = stats.iter().map(|s| sorted(s[..n].to_vec())).collect();
    let at = |k: usize| -> Vec<f64> { ordered.iter().map(|s| s[n - 1 - k.min(n - 1)]).collect() };
    let failing = |t: &[f64]| (0..n).filter(|&i| stats.iter().zip(t).any(|(s, &t)| s[i] > t)).count();
    // The union's failures grow with k: walk up while they stay within the budget.
    let mut k = 0;
    while k + 1 < n && failing(&at(k + 1)) <= budget {
        k += 1;
    }
    at(k)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn spearman_of_monotone_maps_is_one() {
        let a = [1.0, 2.0, 3.0, 10.0];
        assert!((spearman(&a, &[0.1, 0.2, 0.5, 0.9]) - 1.0).abs() < 1e-12);
        assert!((spearman(&a, &[4.0, 3.0, 2.0, 1.0]) + 1.0).abs() < 1e-12);
    }

    #[test]
    fn the_three_quantiles_differ_as_documented() {
        let v = [0.0, 1.0, 2.0, 3.0];
        // Rank q·(n − 1) = 1.8 for q = 0.6.
        assert!((quantile_linear(&v, 0.6) - 1.8).abs() < 1e-12);
        assert_eq!(quantile_nearest(&v, 0.6), Some(2.0));
        assert_eq!(quantile_floor(&v, 0.6), 1.0);
        assert_eq!(quantile_nearest(&[], 0.5), None);
        assert_eq!(median_upper(&v), 2.0);
        assert!(median_upper(&[]).is_nan());
    }

    #[test]
    fn moments() {
        let (m, s) = mean_std_population(&[1.0, 3.0]);
        assert_eq!((m, s), (2.0, 1.0));
        let (m, v) = mean_var_sample(&[1.0, 3.0]);
        assert_eq!((m, v), (2.0, 2.0));
        assert_eq!(mean([1.0, 2.0, 6.0]), 3.0);
    }

    #[test]
    fn joint_thresholds_fail_the_promised_share_of_cases_however_the_statistics_relate() {
        // Three independent statistics (a fixed pseudo-random sequence): each at its own
        // 99 % quantile would fail up to 3 % of the cases together.
        let n = 3000;
        let mut state = 0x2545_F491_4F6C_DD1Du64;
        let mut next = || {
            state ^= state << 13;
            state ^= state >> 7;
            state ^= state << 17;
            (state >> 11) as f64 / (1u64 << 53) as f64
        };
        let independent: Vec<Vec<f64>> = (0..3).map(|_| (0..n).map(|_| next()).collect()).collect();
        let union_failing =
            |stats: &[Vec<f64>], t: &[f64]| (0..n).filter(|&i| stats.iter().zip(t).any(|(s, &t)| s[i] > t)).count();
        let t = joint_upper_thresholds(&independent, 0.99);
        let failing = union_failing(&independent, &t);
        assert!((25..=30).contains(&failing), "{failing} of {n} fail (budget 30)");
        let alone: Vec<f64> = independent.iter().map(|s| quantile_nearest(&sorted(s.clone()), 0.99).unwrap()).collect();
        assert!(union_failing(&independent, &alone) > 60, "each at its own 99 % fails more together");
        // The same statistic three times: the joint thresholds are its own 99 % quantile.
        let same = vec![independent[0].clone(); 3];
        let t = joint_upper_thresholds(&same, 0.99);
        assert_eq!(union_failing(&same, &t), 30);
        assert!(t.iter().all(|&v| v == t[0]));
        assert_eq!(joint_upper_thresholds(&[vec![], vec![1.0]], 0.99), vec![f64::INFINITY; 2]);
        // Too few cases for the budget: the largest value of each, nothing fails.
        assert_eq!(joint_upper_thresholds(&[vec![1.0, 3.0, 2.0]], 0.99), vec![3.0]);
    }
}
