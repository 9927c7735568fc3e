//! Exact condensation of the eardrum's interior DOFs.
//!
//! The drum's interior block is κ·K + s·M with two scalars per solve (κ = E·(1 + jωβ)·…,
//! s = −ω²) and fixed real K, M. With generalized eigenvectors normalised on K
//! (Φᵀ K Φ = I, Φᵀ M Φ = diag μ), its inverse is Φ (κI + s·diag μ)⁻¹ Φᵀ: diagonal in
//! modal coordinates. K rather than M normalises because the clamped K is well
//! conditioned, while M's rotary terms shrink with the element size. So
//! the interior can be eliminated exactly (all modes kept, nothing truncated) at
//! O(modes) per solve, leaving only the umbo and the two pressures it couples to. The
//! modes depend on the mesh only, not on E, and are computed once per model.

use faer::{Mat, Side, c64};

/// The interior of the drum, projected on its modes.
#[derive(Clone, Debug)]
pub struct DrumModes {
    /// Modal masses μ_k = φ_kᵀ M φ_k (modal stiffnesses are 1 at E = 1 Pa).
    pub mu: Vec<f64>,
    /// φ_kᵀ K_ib: stiffness coupling of mode k to the umbo.
    pub kb: Vec<f64>,
    /// φ_kᵀ M_ib: mass coupling of mode k to the umbo.
    pub mb: Vec<f64>,
    /// φ_kᵀ b_i: volume mode k sweeps (its coupling to the pressures).
    pub bb: Vec<f64>,
}

/// Why a drum's modes could not be computed: each variant names the matrix at fault.
#[derive(Clone, Debug, PartialEq, Eq, thiserror::Error)]
pub enum DrumError {
    /// The eigendecomposition of `matrix` ("stiffness", or "mass" for the mass matrix in
    /// the stiffness' metric) failed.
    #[error("{matrix} eigen: {detail}")]
    Eigen {
        /// Which matrix.
        matrix: &'static str,
        /// The solver's own message.
        detail: String,
    },
    /// `matrix` is not positive definite: the drum is not clamped, or its mesh or
    /// material is degenerate.
    #[error("drum {matrix} matrix is not positive definite{detail}")]
    NotPositiveDefinite {
        /// Which matrix.
        matrix: &'static str,
        /// The solver's own message, after ": ", when it gave one.
        detail: String,
    },
    /// The sparse `matrix` could not be built from its entries (an index overflow or no
    /// memory: the mesh is too large).
    #[error("drum {matrix} matrix could not be assembled: {detail}")]
    Assembly {
        /// Which matrix.
        matrix: &'static str,
        /// faer's own message.
        detail: String,
    },
}

impl DrumError {
    pub(crate) fn eigen(matrix: &'static str, e: impl std::fmt::Debug) -> DrumError {
        DrumError::Eigen { matrix, detail: format!("{e:?}") }
    }
}

/// Coefficients of one solve: stiffness factor κ, mass factor s = −ω², flow factor jω,
/// cavity stiffness ρc²/V (0 when the cavity is open).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct DrumCoefficients {
    /// Stiffness factor κ: E with its loss (complex for a lossy drum).
    pub kappa: c64,
    /// Mass factor s = −ω².
    pub s: f64,
    /// Flow factor jω (volume velocity from swept volume).
    pub jw: c64,
    /// Cavity stiffness ρc²/V, Pa/m³ (0 when the cavity is open).
    pub cavity: f64,
}

impl DrumModes {
    /// `k`, `m`: the interior blocks (n×n, symmetric, M positive definite); `k_ib`, `m_ib`:
    /// their coupling columns to the umbo; `b`: the interior swept-volume vector.
    pub fn new(k: &Mat<f64>, m: &Mat<f64>, k_ib: &[f64], m_ib: &[f64], b: &[f64]) -> Result<DrumModes, DrumError> {
        let n = k.nrows();
        // K^{-1/2} from K's own eigendecomposition (the clamped drum's K is SPD).
        let ek = k.self_adjoint_eigen(Side::Lower).map_err(|e| DrumError::eigen("stiffness", e))?;
        let (vm, dm) = (ek.U(), ek.S().column_vector());
        let mut half = Mat::<f64>::zeros(n, n);
        for j in 0..n {
            if dm[j] <= 0.0 {
                return Err(DrumError::NotPositiveDefinite { matrix: "stiffness", detail: String::new() });
            }
            let w = 1.0 / dm[j].sqrt();
            for i in 0..n {
                half[(i, j)] = vm[(i, j)] * w;
            }
        }
        let k_inv_half = &half * vm.transpose();
        let c = &k_inv_half * m * &k_inv_half;
        let c = Mat::<f64>::from_fn(n, n, |i, j| 0.5 * (c[(i, j)] + c[(j, i)]));
        let em = c.self_adjoint_eigen(Side::Lower).map_err(|e| DrumError::eigen("mass", e))?;
        let phi = &k_inv_half * em.U();
        let project = |v: &[f64]| -> Vec<f64> { (0..n).map(|kk| (0..n).map(|i| phi[(i, kk)] * v[i]).sum()).collect() };
        Ok(DrumModes {
            mu: (0..n).map(|i| em.S().column_vector()[i]).collect(),
            kb: project(k_ib),
            mb: project(m_ib),
            bb: project(b),
        })
    }

    /// Modal amplitudes of mode k's coupling: row entries (umbo, flow, cavity rows) and
    /// column entries (umbo, canal-pressure, cavity-pressure columns).
    fn coupling(&self, k: usize, c: &DrumCoefficients) -> ([c64; 3], [c64; 3]) {
        let a = c.kappa * self.kb[k] + c.s * self.mb[k];
        let b = self.bb[k];
        ([a, c.jw * b, c64::new(c.cavity * b, 0.0)], [a, c64::new(-b, 0.0), c64::new(b, 0.0)])
    }

    /// The Schur complement the interior adds to the 3×3 block of (umbo, canal pressure
    /// at the drum, cavity pressure), row-major.
    pub fn schur(&self, c: &DrumCoefficients) -> [c64; 9] {
        let mut out = [c64::new(0.0, 0.0); 9];
        for k in 0..self.mu.len() {
            let (r, col) = self.coupling(k, c);
            let d = c.kappa + c.s * self.mu[k];
            for i in 0..3 {
                let ri = r[i] / d;
                for j in 0..3 {
                    out[3 * i + j] -= ri * col[j];
                }
            }
        }
        out
    }

    /// Modal amplitudes η of the interior for boundary values x_b = (umbo, p_drum, p_cav).
    pub fn interior(&self, c: &DrumCoefficients, xb: [c64; 3]) -> Vec<c64> {
        (0..self.mu.len())
            .map(|k| {
                let (_, col) = self.coupling(k, c);
                -(col[0] * xb[0] + col[1] * xb[1] + col[2] * xb[2]) / (c.kappa + c.s * self.mu[k])
            })
            .collect()
    }

    /// Interior swept volume Σ bb_k η_k and the interior part of the unit-stiffness
    /// quadratic form qᴴ K q (interior–interior plus both cross terms) for umbo value u.
    pub fn volume_and_energy(&self, eta: &[c64], u: c64) -> (c64, c64) {
        let mut vol = c64::new(0.0, 0.0);
        let mut energy = c64::new(0.0, 0.0);
        for ((e, bb), kb) in eta.iter().zip(&self.bb).zip(&self.kb) {
            vol += e * bb;
            energy += e.conj() * e + (e.conj() * u + u.conj() * e) * kb;
        }
        (vol, energy)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_stiffness_that_is_not_positive_definite_is_named() {
        let k = Mat::<f64>::from_fn(2, 2, |i, j| if i == j { -1.0 } else { 0.0 });
        let m = Mat::<f64>::identity(2, 2);
        let Err(e) = DrumModes::new(&k, &m, &[0.0; 2], &[0.0; 2], &[1.0; 2]) else { panic!("K = −I is refused") };
        assert_eq!(e, DrumError::NotPositiveDefinite { matrix: "stiffness", detail: String::new() });
        assert_eq!(e.to_string(), "drum stiffness matrix is not positive definite");
    }

    #[test]
    fn a_failed_eigendecomposition_names_its_matrix() {
        #[derive(Debug)]
        struct NoConvergence;
        let e = DrumError::eigen("mass", NoConvergence);
        assert_eq!(e, DrumError::Eigen { matrix: "mass", detail: "NoConvergence".into() });
        assert_eq!(e.to_string(), "mass eigen: NoConvergence");
    }

    #[test]
    fn a_failed_assembly_names_its_matrix() {
        let e = DrumError::Assembly { matrix: "stiffness", detail: "IndexOverflow".into() };
        assert_eq!(e.to_string(), "drum stiffness matrix could not be assembled: IndexOverflow");
    }
}
