//! Symmetric positive definite matrices, through faer's Cholesky factorisation: the
//! exact chain's proposal covariances, the SBI tasks' Gaussian priors and Laplace
//! approximations. Row-major nested rows in and out, the layout those callers build.

#![warn(missing_docs)]

use faer::linalg::solvers::Solve;
use faer::{Mat, Side};

fn to_mat(a: &[Vec<f64>]) -> Option<Mat<f64>> {
    let d = a.len();
    if a.iter().any(|r| r.len() != d || r.iter().any(|v| !v.is_finite())) {
        return None;
    }
    Some(Mat::from_fn(d, d, |i, j| a[i][j]))
}

fn to_rows(m: &Mat<f64>) -> Vec<Vec<f64>> {
    (0..m.nrows()).map(|i| (0..m.ncols()).map(|j| m[(i, j)]).collect()).collect()
}

/// Lower Cholesky factor L (L Lᵀ = a) of a symmetric positive definite matrix, read from
/// its lower triangle; `None` when it is not square, not finite or not positive definite.
pub fn cholesky(a: &[Vec<f64>]) -> Option<Vec<Vec<f64>>> {
    let llt = to_mat(a)?.llt(Side::Lower).ok()?;
    Some(to_rows(&llt.L().to_owned()))
}

/// The inverse of a symmetric positive definite matrix; `None` as for [`cholesky`].
pub fn inverse(a: &[Vec<f64>]) -> Option<Vec<Vec<f64>>> {
    let llt = to_mat(a)?.llt(Side::Lower).ok()?;
    Some(to_rows(&llt.solve(Mat::<f64>::identity(a.len(), a.len()))))
}

#[cfg(test)]
mod tests {
    use super::*;

    fn product(a: &[Vec<f64>], b: &[Vec<f64>]) -> Vec<Vec<f64>> {
        let d = a.len();
        (0..d).map(|i| (0..d).map(|j| (0..d).map(|k| a[i][k] * b[k][j]).sum()).collect()).collect()
    }

    #[test]
    fn the_factor_and_the_inverse_reproduce_the_matrix() {
        let a = vec![vec![4.0, 2.0, 0.6], vec![2.0, 5.0, 1.0], vec![0.6, 1.0, 3.0]];
        let l = cholesky(&a).unwrap();
        let lt: Vec<Vec<f64>> = (0..3).map(|i| (0..3).map(|j| l[j][i]).collect()).collect();
        assert!((0..3).all(|i| (i + 1..3).all(|j| l[i][j] == 0.0)), "lower triangular: {l:?}");
        let inv = inverse(&a).unwrap();
        for (x, y) in [
            (product(&l, &lt), a.clone()),
            (product(&a, &inv), vec![vec![1.0, 0.0, 0.0], vec![0.0, 1.0, 0.0], vec![0.0, 0.0, 1.0]]),
        ] {
            for (r, s) in x.iter().zip(&y) {
                for (p, q) in r.iter().zip(s) {
                    assert!((p - q).abs() < 1e-12, "{x:?} vs {y:?}");
                }
            }
        }
    }

    #[test]
    fn indefinite_non_finite_and_ragged_matrices_are_refused() {
        assert!(cholesky(&[vec![1.0, 2.0], vec![2.0, 1.0]]).is_none(), "indefinite");
        assert!(inverse(&[vec![1.0, f64::NAN], vec![f64::NAN, 1.0]]).is_none(), "not finite");
        assert!(cholesky(&[vec![1.0, 0.0], vec![0.0]]).is_none(), "ragged");
    }
}
