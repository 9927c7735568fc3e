//! Ear canal: 1D finite elements of Webster's horn equation, −(S p′)′ − k² S p = 0,
//! with linear elements and viscothermal losses per element (physics-notes §5.1).
//!
//! Weak form, with nodal volume velocities U as the right-hand side:
//!   Σ_e [ (1 − F_v)/(jωρ) ∫ S N′N′ + jω(1 + (γ−1)F_t)/(ρc²) ∫ S N N ] p = U,
//! so each element carries two unit matrices (∫ S N′N′ and ∫ S N N) and two
//! frequency-dependent coefficients. U enters at the probe (x = 0) and leaves into the
//! eardrum at x = L.

use super::air::Air;
use faer::c64;

/// Cross-section along the canal.
#[derive(Clone, Debug, PartialEq)]
pub enum Area {
    /// Constant area, m².
    Uniform(f64),
    /// Radius varying linearly from `r0` at x = 0 to `r1` at x = L (a truncated cone).
    Cone {
        /// Radius at the probe end (x = 0), m.
        r0: f64,
        /// Radius at the eardrum end (x = L), m.
        r1: f64,
    },
}

impl Area {
    /// Cross-section at `x` along a canal of `length`, m².
    pub fn at(&self, x: f64, length: f64) -> f64 {
        match *self {
            Area::Uniform(s) => s,
            Area::Cone { r0, r1 } => {
                let r = r0 + (r1 - r0) * x / length;
                std::f64::consts::PI * r * r
            }
        }
    }
}

/// A 1D canal mesh with its unit element matrices.
#[derive(Clone, Debug)]
pub struct CanalMesh {
    /// Canal length from the probe to the eardrum, m.
    pub length: f64,
    /// Node positions from the probe (0) to the eardrum (`length`).
    pub x: Vec<f64>,
    /// Per element: ∫ S N′N′ dx (2×2, row-major).
    pub k: Vec<[f64; 4]>,
    /// Per element: ∫ S N N dx (2×2, row-major).
    pub m: Vec<[f64; 4]>,
    /// Per element: the area used for its loss functions (at the element's midpoint).
    pub loss_area: Vec<f64>,
}

// 3-point Gauss–Legendre on [0, 1]: exact for the quartic integrands of a cone.
const GAUSS3: [(f64, f64); 3] =
    [(0.112_701_665_379_258_3, 5.0 / 18.0), (0.5, 8.0 / 18.0), (0.887_298_334_620_741_7, 5.0 / 18.0)];

impl CanalMesh {
    /// Meshes [0, length] with elements no longer than `h_max`, putting nodes exactly at
    /// each of `stations` (e.g. the measurement planes).
    pub fn new(length: f64, area: &Area, h_max: f64, stations: &[f64]) -> CanalMesh {
        let mut cuts: Vec<f64> = vec![0.0, length];
        cuts.extend(stations.iter().copied().filter(|&s| s > 0.0 && s < length));
        cuts.sort_by(|a, b| a.total_cmp(b));
        cuts.dedup_by(|a, b| (*a - *b).abs() < 1e-12);
        let mut x = vec![0.0];
        for w in cuts.windows(2) {
            let n = ((w[1] - w[0]) / h_max).ceil().max(1.0) as usize;
            for i in 1..=n {
                x.push(w[0] + (w[1] - w[0]) * i as f64 / n as f64);
            }
        }
        let mut mesh = CanalMesh { length, x, k: vec![], m: vec![], loss_area: vec![] };
        for e in 0..mesh.x.len() - 1 {
            let (x0, x1) = (mesh.x[e], mesh.x[e + 1]);
            let h = x1 - x0;
            let (mut k, mut m) = ([0.0; 4], [0.0; 4]);
            for (xi, w) in GAUSS3 {
                let s = area.at(x0 + xi * h, length);
                let n = [1.0 - xi, xi];
                let dn = [-1.0 / h, 1.0 / h];
                for a in 0..2 {
                    for b in 0..2 {
                        k[2 * a + b] += w * h * s * dn[a] * dn[b];
                        m[2 * a + b] += w * h * s * n[a] * n[b];
                    }
                }
            }
            mesh.k.push(k);
            mesh.m.push(m);
            mesh.loss_area.push(area.at(x0 + 0.5 * h, length));
        }
        mesh
    }

    /// Nodes of the mesh (one pressure unknown each).
    pub fn n_nodes(&self) -> usize {
        self.x.len()
    }

    /// Index of the node at `x` (it must be a station given to `new`).
    pub fn node_at(&self, x: f64) -> Option<usize> {
        self.x.iter().position(|&xn| (xn - x).abs() < 1e-9)
    }

    /// The two frequency-dependent coefficients of element `e`: (on ∫SN′N′, on ∫SNN).
    pub fn coefficients(&self, air: &Air, omega: f64, e: usize) -> (c64, c64) {
        let (fv, ft) = air.loss_functions(omega, self.loss_area[e]);
        let one = c64::new(1.0, 0.0);
        let ck = (one - fv) / c64::new(0.0, omega * air.rho);
        let cm = c64::new(0.0, omega / air.bulk_modulus()) * (one + (air.gamma - 1.0) * ft);
        (ck, cm)
    }

    /// Element matrix of `e` at one frequency (2×2, row-major).
    pub fn element(&self, air: &Air, omega: f64, e: usize) -> [c64; 4] {
        let (ck, cm) = self.coefficients(air, omega, e);
        std::array::from_fn(|i| ck * self.k[e][i] + cm * self.m[e][i])
    }

    /// Volume velocity through the plane at node `i` toward the eardrum: the consistent
    /// flux of the elements right of `i` (more accurate than differentiating p).
    pub fn flux_at_node(&self, air: &Air, omega: f64, p: &[c64], i: usize) -> c64 {
        let a = self.element(air, omega, i);
        a[0] * p[i] + a[1] * p[i + 1]
    }
}

impl CanalMesh {
    /// The exact two-port of the elements between nodes `from` < `to`: the Schur
    /// complement S (2×2, row-major) with [U_in, −U_out] = S·[p_from, p_to], where U_in
    /// enters at `from` toward the eardrum. Interior nodes are eliminated one by one
    /// (the chain is tridiagonal), O(to − from).
    pub fn condense(&self, air: &Air, omega: f64, from: usize, to: usize) -> [c64; 4] {
        let mut s = self.element(air, omega, from);
        for e in from + 1..to {
            let b = self.element(air, omega, e);
            let d = s[3] + b[0];
            s = [s[0] - s[1] * s[2] / d, -s[1] * b[1] / d, -b[2] * s[2] / d, b[3] - b[2] * b[1] / d];
        }
        s
    }
}

/// Termination of a stand-alone canal (for verification against closed forms).
#[derive(Clone, Copy, Debug)]
pub enum Load {
    /// No flow through the end (a closed tube).
    Rigid,
    /// p = 0 at the end.
    Open,
    /// p = Z·U at the end, Z in Pa·s/m³.
    Impedance(c64),
}

/// Solves a stand-alone canal driven by U = 1 at x = 0 and returns the nodal pressures.
/// Used by tests and by the verification of the coupled model's canal part.
pub fn solve_driven(mesh: &CanalMesh, air: &Air, omega: f64, load: Load) -> Vec<c64> {
    let n = mesh.n_nodes();
    let zero = c64::new(0.0, 0.0);
    let (mut lo, mut di, mut up) = (vec![zero; n], vec![zero; n], vec![zero; n]);
    for e in 0..n - 1 {
        let a = mesh.element(air, omega, e);
        di[e] += a[0];
        up[e] += a[1];
        lo[e + 1] += a[2];
        di[e + 1] += a[3];
    }
    let mut rhs = vec![zero; n];
    rhs[0] = c64::new(1.0, 0.0);
    match load {
        Load::Rigid => {}
        Load::Impedance(z) => di[n - 1] += c64::new(1.0, 0.0) / z,
        Load::Open => {
            // Dirichlet p = 0: replace the last equation.
            lo[n - 1] = zero;
            di[n - 1] = c64::new(1.0, 0.0);
        }
    }
    thomas(&lo, &di, &up, &mut rhs);
    rhs
}

/// Tridiagonal solve (no pivoting: the canal matrix is diagonally dominant enough at
/// the element sizes used here; tests compare against closed forms).
fn thomas(lo: &[c64], di: &[c64], up: &[c64], rhs: &mut [c64]) {
    let n = di.len();
    let mut c = vec![c64::new(0.0, 0.0); n];
    let mut b = di[0];
    c[0] = up[0] / b;
    rhs[0] /= b;
    for i in 1..n {
        b = di[i] - lo[i] * c[i - 1];
        c[i] = up[i] / b;
        rhs[i] = (rhs[i] - lo[i] * rhs[i - 1]) / b;
    }
    for i in (0..n - 1).rev() {
        let next = rhs[i + 1];
        rhs[i] -= c[i] * next;
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::air::{absorbance, line_constants, line_input_impedance};
    use std::f64::consts::PI;

    const L: f64 = 0.012;
    const S: f64 = 44e-6;

    fn fe_zin(n_el: usize, air: &Air, f: f64, load: Load) -> c64 {
        let mesh = CanalMesh::new(L, &Area::Uniform(S), L / n_el as f64, &[]);
        solve_driven(&mesh, air, 2.0 * PI * f, load)[0]
    }

    fn exact_zin(air: &Air, f: f64, load: Load) -> c64 {
        let (z, y) = air.line_zy(2.0 * PI * f, S);
        let (g, zc) = line_constants(z, y);
        match load {
            Load::Rigid => line_input_impedance(zc, g, L, None),
            Load::Open => line_input_impedance(zc, g, L, Some(c64::new(0.0, 0.0))),
            Load::Impedance(zl) => line_input_impedance(zc, g, L, Some(zl)),
        }
    }

    fn rel(a: c64, b: c64) -> f64 {
        (a - b).norm() / b.norm()
    }

    #[test]
    fn condensed_two_port_reproduces_the_full_canal() {
        let air = Air::at_celsius(22.0);
        let mesh = CanalMesh::new(15e-3, &Area::Cone { r0: 4e-3, r1: 3e-3 }, 0.5e-3, &[3e-3]);
        let n = mesh.n_nodes();
        let mid = mesh.node_at(3e-3).unwrap();
        for f in [200.0, 3000.0, 8000.0] {
            let w = 2.0 * std::f64::consts::PI * f;
            let zl = c64::new(2e7, -3e7);
            let p = solve_driven(&mesh, &air, w, Load::Impedance(zl));
            // Whole canal: U_in = 1 and U_out = p_L / Z_L.
            let s = mesh.condense(&air, w, 0, n - 1);
            let u_in = s[0] * p[0] + s[1] * p[n - 1];
            let u_out = -(s[2] * p[0] + s[3] * p[n - 1]);
            assert!((u_in - 1.0).norm() < 1e-9, "{u_in}");
            assert!((u_out - p[n - 1] / zl).norm() < 1e-9 * u_out.norm());
            // Flux through an interior station equals the consistent element flux.
            let right = mesh.condense(&air, w, mid, n - 1);
            let flux = right[0] * p[mid] + right[1] * p[n - 1];
            let reference = mesh.flux_at_node(&air, w, &p, mid);
            assert!((flux - reference).norm() < 1e-6 * reference.norm(), "{flux} vs {reference}");
        }
    }

    #[test]
    fn uniform_tube_matches_transmission_line_lossless_and_lossy() {
        let load_z = c64::new(2.0e7, -3.0e7);
        for air in [Air::lossless(1.19, 344.0), Air::at_celsius(22.0)] {
            for load in [Load::Rigid, Load::Open, Load::Impedance(load_z)] {
                for f in [200.0, 1000.0, 4000.0, 8000.0] {
                    let e = rel(fe_zin(96, &air, f, load), exact_zin(&air, f, load));
                    assert!(e < 2e-3, "{load:?} at {f} Hz (mu = {}): rel. error {e:e}", air.mu);
                }
            }
        }
    }

    #[test]
    fn rigid_tube_quarter_wave_and_low_frequency_compliance() {
        let air = Air::lossless(1.19, 344.0);
        // Low-frequency limit 1/(jωC), C = SL/(ρc²).
        let f = 20.0;
        let c = S * L / air.bulk_modulus();
        let z = fe_zin(48, &air, f, Load::Rigid);
        let expect = c64::new(0.0, -1.0 / (2.0 * PI * f * c));
        assert!(rel(z, expect) < 1e-3, "{z} vs {expect}");
        // Impedance zero at c/(4L): |Z| there is tiny compared with Z0.
        let fq = air.c / (4.0 * L);
        let zq = fe_zin(192, &air, fq, Load::Rigid);
        assert!(zq.norm() < 1e-3 * air.z0(S), "|Z({fq:.0} Hz)| = {:e}", zq.norm());
        // Absorbance of a lossless rigid tube is zero at all frequencies.
        for f in [200.0, 3000.0, 8000.0] {
            assert!(absorbance(fe_zin(24, &air, f, Load::Rigid), air.z0(S)).abs() < 1e-12);
        }
        // A matched load absorbs everything.
        let zm = fe_zin(192, &air, 3000.0, Load::Impedance(c64::new(air.z0(S), 0.0)));
        assert!((absorbance(zm, air.z0(S)) - 1.0).abs() < 1e-4);
    }

    #[test]
    fn linear_elements_converge_at_second_order() {
        let air = Air::at_celsius(22.0);
        let load = Load::Impedance(c64::new(1.0e7, -2.0e7));
        let exact = exact_zin(&air, 8000.0, load);
        let errs: Vec<f64> = [4, 8, 16, 32].iter().map(|&n| rel(fe_zin(n, &air, 8000.0, load), exact)).collect();
        for w in errs.windows(2) {
            let order = (w[0] / w[1]).log2();
            assert!((order - 2.0).abs() < 0.25, "observed order {order:.2} from {errs:?}");
        }
    }

    #[test]
    fn conical_horn_matches_the_exact_spherical_wave_solution() {
        // Radius 3.0 mm at the probe to 4.0 mm at the end, rigid-ish load Z_L.
        let air = Air::lossless(1.19, 344.0);
        let (r0, r1) = (3.0e-3, 4.0e-3);
        let area = Area::Cone { r0, r1 };
        let zl = c64::new(3.0e7, -5.0e7);
        // Apex distance: S ∝ x², radius grows linearly, so x1 = r0 L/(r1 − r0).
        let x1 = r0 * L / (r1 - r0);
        let x2 = x1 + L;
        for f in [500.0, 3000.0, 8000.0] {
            let w = 2.0 * PI * f;
            let k = w / air.c;
            let j = c64::new(0.0, 1.0);
            let s_of = |x: f64| PI * (r0 * x / x1).powi(2);
            // Basis p = e^{∓jkx}/x, U = −S/(jωρ) ∂p/∂x.
            let p = |x: f64, sgn: f64| (j * (-sgn * k * x)).exp() / x;
            let dp = |x: f64, sgn: f64| (j * (-sgn * k * x)).exp() * (j * (-sgn * k * x) - 1.0) / (x * x);
            let u = |x: f64, sgn: f64| -s_of(x) / (j * w * air.rho) * dp(x, sgn);
            // Conditions at x2: U = 1 and p = Z_L U.
            let (a11, a12) = (u(x2, 1.0), u(x2, -1.0));
            let (a21, a22) = (p(x2, 1.0) - zl * u(x2, 1.0), p(x2, -1.0) - zl * u(x2, -1.0));
            let det = a11 * a22 - a12 * a21;
            let (ca, cb) = (a22 / det, -a21 / det);
            let exact = (ca * p(x1, 1.0) + cb * p(x1, -1.0)) / (ca * u(x1, 1.0) + cb * u(x1, -1.0));
            let mesh = CanalMesh::new(L, &area, L / 192.0, &[]);
            let fe = solve_driven(&mesh, &air, w, Load::Impedance(zl))[0];
            assert!(rel(fe, exact) < 2e-3, "{f} Hz: FE {fe} vs exact {exact}");
        }
    }

    #[test]
    fn consistent_flux_recovers_the_plane_impedance() {
        // Z at an interior node equals the input impedance of the remaining tube.
        let air = Air::at_celsius(22.0);
        let zl = c64::new(2.0e7, -1.0e7);
        let mesh = CanalMesh::new(L, &Area::Uniform(S), 0.25e-3, &[0.003]);
        let i = mesh.node_at(0.003).unwrap();
        let w = 2.0 * PI * 6000.0;
        let p = solve_driven(&mesh, &air, w, Load::Impedance(zl));
        let z_plane = p[i] / mesh.flux_at_node(&air, w, &p, i);
        let (z, y) = air.line_zy(w, S);
        let (g, zc) = line_constants(z, y);
        let exact = line_input_impedance(zc, g, L - 0.003, Some(zl));
        assert!(rel(z_plane, exact) < 1e-3, "{z_plane} vs {exact}");
    }
}
