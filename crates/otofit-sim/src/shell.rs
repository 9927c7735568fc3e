//! Axisymmetric (n = 0) conical shell frustum element with membrane and bending action
//! (Kirchhoff–Love, after Grafton & Strome 1963).
//!
//! Node DOFs in global axes: (u_r radial, u_z axial, β rotation of the meridian).
//! Along the element the meridional displacement u_s is linear and the normal
//! displacement w_n is a Hermite cubic with β = dw_n/ds. Strains:
//!   ε_s = du_s/ds, ε_θ = (c·u_s − s·w_n)/r, κ_s = −d²w_n/ds², κ_θ = −c·(dw_n/ds)/r,
//! with (c, s) = (dr/ds, dz/ds) and the normal n = (−s, c). Matrices are integrated
//! with 4-point Gauss over the meridian, weight 2πr ds, so no r = 0 singularity arises
//! at Gauss points (a node at r = 0 must have u_r = β = 0).

use std::f64::consts::PI;

/// Material and thickness of a shell part.
#[derive(Clone, Copy, Debug)]
pub struct ShellMaterial {
    /// Thickness, m.
    pub h: f64,
    /// Poisson ratio.
    pub nu: f64,
    /// Density, kg/m³.
    pub rho: f64,
}

/// One element's matrices in global DOFs [u_r1, u_z1, β1, u_r2, u_z2, β2].
#[derive(Clone, Debug)]
pub struct ShellElement {
    /// Stiffness for E = 1 Pa (stiffness is linear in E).
    pub k_unit: [[f64; 6]; 6],
    /// Consistent mass.
    pub m: [[f64; 6]; 6],
    /// ∫ N_wᵀ dA: the load of a unit pressure along n, and the volume swept per DOF.
    pub b: [f64; 6],
}

const GAUSS4: [(f64, f64); 4] = [
    (0.069_431_844_202_973_71, 0.173_927_422_568_726_93),
    (0.330_009_478_207_571_87, 0.326_072_577_431_273_07),
    (0.669_990_521_792_428_1, 0.326_072_577_431_273_07),
    (0.930_568_155_797_026_3, 0.173_927_422_568_726_93),
];

/// Hermite cubics on [0, 1] and their first and second derivatives in ξ.
fn hermite(xi: f64) -> ([f64; 4], [f64; 4], [f64; 4]) {
    let (x2, x3) = (xi * xi, xi * xi * xi);
    (
        [1.0 - 3.0 * x2 + 2.0 * x3, xi - 2.0 * x2 + x3, 3.0 * x2 - 2.0 * x3, -x2 + x3],
        [-6.0 * xi + 6.0 * x2, 1.0 - 4.0 * xi + 3.0 * x2, 6.0 * xi - 6.0 * x2, -2.0 * xi + 3.0 * x2],
        [-6.0 + 12.0 * xi, -4.0 + 6.0 * xi, 6.0 - 12.0 * xi, -2.0 + 6.0 * xi],
    )
}

impl ShellElement {
    /// Element from node 1 at (r1, z1) to node 2 at (r2, z2).
    pub fn new(p1: (f64, f64), p2: (f64, f64), mat: &ShellMaterial) -> ShellElement {
        let (dr, dz) = (p2.0 - p1.0, p2.1 - p1.1);
        let len = (dr * dr + dz * dz).sqrt();
        let (c, s) = (dr / len, dz / len);
        let a_mem = mat.h / (1.0 - mat.nu * mat.nu); // × E
        let d_ben = mat.h.powi(3) / (12.0 * (1.0 - mat.nu * mat.nu)); // × E
        let mut k = [[0.0; 6]; 6];
        let mut m = [[0.0; 6]; 6];
        let mut b = [0.0; 6];
        // Local DOFs: [u_s1, w1, β1, u_s2, w2, β2].
        for (xi, w) in GAUSS4 {
            let r = p1.0 + c * xi * len;
            let da = w * 2.0 * PI * r * len;
            let (h, dh, ddh) = hermite(xi);
            let nw = [0.0, h[0], len * h[1], 0.0, h[2], len * h[3]];
            let nu_s = [1.0 - xi, 0.0, 0.0, xi, 0.0, 0.0];
            let eps_s = [-1.0 / len, 0.0, 0.0, 1.0 / len, 0.0, 0.0];
            let eps_t: [f64; 6] = std::array::from_fn(|i| (c * nu_s[i] - s * nw[i]) / r);
            let kap_s = [0.0, -ddh[0], -len * ddh[1], 0.0, -ddh[2], -len * ddh[3]].map(|v| v / (len * len));
            let kap_t = [0.0, dh[0], len * dh[1], 0.0, dh[2], len * dh[3]].map(|v| -c * v / (r * len));
            for i in 0..6 {
                for j in 0..6 {
                    let mem = eps_s[i] * eps_s[j]
                        + eps_t[i] * eps_t[j]
                        + mat.nu * (eps_s[i] * eps_t[j] + eps_t[i] * eps_s[j]);
                    let ben = kap_s[i] * kap_s[j]
                        + kap_t[i] * kap_t[j]
                        + mat.nu * (kap_s[i] * kap_t[j] + kap_t[i] * kap_s[j]);
                    k[i][j] += da * (a_mem * mem + d_ben * ben);
                    m[i][j] += da * mat.rho * mat.h * (nu_s[i] * nu_s[j] + nw[i] * nw[j]);
                }
                b[i] += da * nw[i];
            }
        }
        // Local → global: u_s = c u_r + s u_z, w_n = −s u_r + c u_z, β unchanged.
        let mut t = [[0.0; 6]; 6];
        for n in 0..2 {
            let o = 3 * n;
            t[o][o] = c;
            t[o][o + 1] = s;
            t[o + 1][o] = -s;
            t[o + 1][o + 1] = c;
            t[o + 2][o + 2] = 1.0;
        }
        ShellElement { k_unit: congruence(&t, &k), m: congruence(&t, &m), b: transpose_apply(&t, &b) }
    }
}

/// Tᵀ A T for 6×6 matrices.
fn congruence(t: &[[f64; 6]; 6], a: &[[f64; 6]; 6]) -> [[f64; 6]; 6] {
    let mut at = [[0.0; 6]; 6];
    for i in 0..6 {
        for j in 0..6 {
            at[i][j] = (0..6).map(|k| a[i][k] * t[k][j]).sum();
        }
    }
    let mut out = [[0.0; 6]; 6];
    for i in 0..6 {
        for j in 0..6 {
            out[i][j] = (0..6).map(|k| t[k][i] * at[k][j]).sum();
        }
    }
    out
}

fn transpose_apply(t: &[[f64; 6]; 6], v: &[f64; 6]) -> [f64; 6] {
    std::array::from_fn(|i| (0..6).map(|k| t[k][i] * v[k]).sum())
}

/// Nodes of a conical generator from the inner radius `r_in` to the clamped rim `a`, for
/// a cone of `depth` whose apex lies on the axis: z(r) = depth·(1 − r/a) − bulge·4t(1−t),
/// t = (r − r_in)/(a − r_in), z pointing medially (from the canal into the middle ear).
/// `bulge` > 0 curves the generator laterally, like the eardrum's radial fibres.
pub fn cone_nodes(r_in: f64, a: f64, depth: f64, bulge: f64, n_el: usize) -> Vec<(f64, f64)> {
    (0..=n_el)
        .map(|i| {
            let t = i as f64 / n_el as f64;
            let r = r_in + (a - r_in) * t;
            (r, depth * (1.0 - r / a) - bulge * 4.0 * t * (1.0 - t))
        })
        .collect()
}

#[cfg(test)]
pub(crate) mod tests {
    use super::*;
    use faer::Mat;
    use faer::prelude::Solve;

    /// A dense assembled shell for tests: nodes along a generator, per-node constraint
    /// flags, returning (K for E, M, b) over the free DOFs.
    pub(crate) fn assemble_dense(
        nodes: &[(f64, f64)],
        mat: &ShellMaterial,
        e: f64,
        fixed: impl Fn(usize, usize) -> bool,
    ) -> (Mat<f64>, Mat<f64>, Vec<f64>) {
        let mut map = vec![None; 3 * nodes.len()];
        let mut n = 0;
        for node in 0..nodes.len() {
            for d in 0..3 {
                if !fixed(node, d) {
                    map[3 * node + d] = Some(n);
                    n += 1;
                }
            }
        }
        let (mut k, mut m, mut b) = (Mat::<f64>::zeros(n, n), Mat::<f64>::zeros(n, n), vec![0.0; n]);
        for el in 0..nodes.len() - 1 {
            let se = ShellElement::new(nodes[el], nodes[el + 1], mat);
            for i in 0..6 {
                let Some(gi) = map[3 * el + i] else { continue };
                b[gi] += se.b[i];
                for j in 0..6 {
                    let Some(gj) = map[3 * el + j] else { continue };
                    k[(gi, gj)] += e * se.k_unit[i][j];
                    m[(gi, gj)] += se.m[i][j];
                }
            }
        }
        (k, m, b)
    }

    fn plate(n_el: usize) -> (Mat<f64>, Mat<f64>, Vec<f64>, f64, f64) {
        let (a, e) = (4.4e-3, 20e6);
        let mat = ShellMaterial { h: 80e-6, nu: 0.3, rho: 1100.0 };
        let nodes: Vec<(f64, f64)> = (0..=n_el).map(|i| (a * i as f64 / n_el as f64, 0.0)).collect();
        let last = nodes.len() - 1;
        // Centre: u_r = β = 0 by symmetry; rim: clamped.
        let (k, m, b) = assemble_dense(&nodes, &mat, e, |node, d| (node == 0 && d != 1) || node == last);
        let d = e * mat.h.powi(3) / (12.0 * (1.0 - mat.nu * mat.nu));
        (k, m, b, d, a)
    }

    fn solve(k: &Mat<f64>, rhs: &[f64]) -> Vec<f64> {
        let r = Mat::from_fn(rhs.len(), 1, |i, _| rhs[i]);
        let x = k.partial_piv_lu().solve(&r);
        (0..rhs.len()).map(|i| x[(i, 0)]).collect()
    }

    /// Lowest eigenvalue of K x = λ M x by inverse iteration.
    pub(crate) fn lowest_omega(k: &Mat<f64>, m: &Mat<f64>) -> f64 {
        let n = k.nrows();
        let lu = k.partial_piv_lu();
        let mut x = Mat::<f64>::from_fn(n, 1, |i, _| 1.0 + (i % 3) as f64 * 0.1);
        let mut lambda = 0.0;
        for _ in 0..200 {
            let y = lu.solve(m * &x);
            let num = (x.transpose() * k * &x)[(0, 0)];
            let den = (x.transpose() * m * &x)[(0, 0)];
            lambda = num / den;
            let norm = y.norm_l2();
            x = y * (1.0 / norm);
        }
        lambda.sqrt()
    }

    #[test]
    fn flat_limit_matches_clamped_plate_statics() {
        let (k, _, b, d, a) = plate(40);
        let q = 1.0;
        let u = solve(&k, &b.iter().map(|v| v * q).collect::<Vec<_>>());
        // DOF 0 is the centre's w (u_r and β fixed there).
        let w0 = u[0];
        let w0_exact = q * a.powi(4) / (64.0 * d);
        assert!((w0 / w0_exact - 1.0).abs() < 1e-4, "centre deflection {w0:e} vs {w0_exact:e}");
        let vol: f64 = b.iter().zip(&u).map(|(bi, ui)| bi * ui).sum();
        let c_exact = PI * a.powi(6) / (192.0 * d);
        assert!((vol / c_exact - 1.0).abs() < 1e-4, "volume compliance {vol:e} vs {c_exact:e}");
    }

    #[test]
    fn flat_limit_matches_clamped_plate_first_frequency_and_converges_from_above() {
        let mut prev = f64::INFINITY;
        let rho_h = 1100.0 * 80e-6;
        for n in [5, 10, 20, 40] {
            let (k, m, _, d, a) = plate(n);
            let f = lowest_omega(&k, &m) / (2.0 * PI);
            let exact = 10.2158 / (2.0 * PI * a * a) * (d / rho_h).sqrt();
            assert!(f >= exact * (1.0 - 1e-6), "consistent mass must bound from above: {f} < {exact}");
            assert!(f <= prev, "not monotone: {f} after {prev}");
            prev = f;
            if n == 40 {
                assert!((f / exact - 1.0).abs() < 1e-4, "f01 {f} vs {exact} (notes: 274 Hz)");
                assert!((exact - 274.0).abs() < 1.0);
            }
        }
    }

    #[test]
    fn element_matrices_are_symmetric_and_have_rigid_axial_translation() {
        let mat = ShellMaterial { h: 80e-6, nu: 0.485, rho: 1100.0 };
        let se = ShellElement::new((1.0e-3, 1.5e-3), (1.3e-3, 1.36e-3), &mat);
        for i in 0..6 {
            for j in 0..6 {
                assert!((se.k_unit[i][j] - se.k_unit[j][i]).abs() <= 1e-9 * se.k_unit[i][i].abs().max(1e-30));
                assert!((se.m[i][j] - se.m[j][i]).abs() <= 1e-12 * se.m[i][i].abs().max(1e-30));
            }
        }
        // A rigid axial translation (u_z = 1 at both nodes, no rotation) costs no energy.
        let t = [0.0, 1.0, 0.0, 0.0, 1.0, 0.0];
        let ku: Vec<f64> = (0..6).map(|i| (0..6).map(|j| se.k_unit[i][j] * t[j]).sum()).collect();
        let scale = se.k_unit[1][1].abs();
        assert!(ku.iter().all(|v| v.abs() < 1e-9 * scale), "{ku:?}");
        // Its volume sweep equals the projected annulus area π(r2² − r1²).
        let vol: f64 = (0..6).map(|i| se.b[i] * t[i]).sum();
        let area = PI * (1.3e-3f64.powi(2) - 1.0e-3f64.powi(2));
        assert!((vol / area - 1.0).abs() < 1e-12, "{vol} vs {area}");
    }

    #[test]
    fn pressurised_sphere_matches_membrane_theory() {
        // Independent closed form for the membrane part (the plate tests above see bending
        // only). A thin spherical shell of radius R under internal pressure q carries it by
        // membrane action alone: equilibrium of a hemisphere gives N_φ = N_θ = qR/2, biaxial
        // plane stress gives ε = (1 − ν)N/(Eh), so the normal displacement is uniform,
        // w = εR = qR²(1 − ν)/(2Eh), and no curvature changes (Timoshenko & Woinowsky-Krieger,
        // Theory of Plates and Shells, 2nd ed. 1959, membrane theory of shells of revolution;
        // Roark's Formulas for Stress and Strain, thin-walled spherical vessel:
        // ΔR = qR²(1 − ν)/(2Et)). The upper hemisphere then sweeps ΔV = 2πR²·w =
        // πqR⁴(1 − ν)/(Eh): inversely proportional to the membrane stiffness Eh/(1 − ν²).
        // Meridian from the pole (u_r = β = 0) to the equator (u_z = β = 0 by the mirror
        // symmetry of the whole sphere), drum-like R, h, E and ν.
        let (radius, e): (f64, f64) = (4.4e-3, 20e6);
        let mat = ShellMaterial { h: 60e-6, nu: 0.485, rho: 1100.0 };
        let exact = PI * radius.powi(4) * (1.0 - mat.nu) / (e * mat.h);
        let mut errs = vec![];
        for n_el in [20, 40, 80] {
            let nodes: Vec<(f64, f64)> = (0..=n_el)
                .map(|i| {
                    let phi = 0.5 * PI * i as f64 / n_el as f64;
                    (radius * phi.sin(), radius * phi.cos())
                })
                .collect();
            let last = nodes.len() - 1;
            let (k, _, b) = assemble_dense(&nodes, &mat, e, |n, d| (n == 0 && d != 1) || (n == last && d != 0));
            let u = solve(&k, &b);
            let vol: f64 = b.iter().zip(&u).map(|(x, y)| x * y).sum();
            errs.push(vol / exact - 1.0);
        }
        eprintln!("sphere volume compliance, relative error at 20/40/80 elements: {errs:?}");
        assert!(errs[2].abs() < 5e-4, "ΔV off by {errs:?} (exact {exact:e} m³/Pa)");
        assert!(errs[1].abs() > 3.0 * errs[2].abs(), "no convergence: {errs:?}");
    }

    #[test]
    fn curvature_stiffens_the_membrane() {
        // A cone of growing depth is stiffer than the flat plate (membrane action).
        let mat = ShellMaterial { h: 80e-6, nu: 0.485, rho: 1100.0 };
        let compliance = |depth: f64| {
            let nodes = cone_nodes(0.0, 4.4e-3, depth, 0.0, 40);
            let last = nodes.len() - 1;
            let (k, _, b) = assemble_dense(&nodes, &mat, 20e6, |n, d| (n == 0 && d != 1) || n == last);
            let u = solve(&k, &b);
            b.iter().zip(&u).map(|(x, y)| x * y).sum::<f64>()
        };
        let c: Vec<f64> = [0.0, 0.5e-3, 1.0e-3, 2.0e-3].iter().map(|&d| compliance(d)).collect();
        for w in c.windows(2) {
            assert!(w[1] < 0.7 * w[0], "{c:?}");
        }
    }
}
