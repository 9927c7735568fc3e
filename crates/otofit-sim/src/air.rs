//! Air properties, viscothermal tube losses and the closed-form tube formulas the
//! canal FE is verified against (physics-notes §0 and §5.1).
//!
//! Time convention e^{+jωt} throughout `sim`.

use faer::c64;

/// Properties of air at one temperature.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Air {
    /// Density, kg/m³.
    pub rho: f64,
    /// Speed of sound, m/s.
    pub c: f64,
    /// Dynamic viscosity, Pa·s.
    pub mu: f64,
    /// Ratio of specific heats.
    pub gamma: f64,
    /// Square root of the Prandtl number.
    pub sqrt_pr: f64,
}

impl Air {
    /// Benade 1968 / Keefe 1984 fits (as tabulated in physics-notes §0), valid near room
    /// and body temperature.
    pub fn at_celsius(t: f64) -> Air {
        let dt = t - 26.85;
        Air {
            rho: 1.1769 * (1.0 - 0.00335 * dt),
            c: 347.23 * (1.0 + 0.00166 * dt),
            mu: 1.846e-5 * (1.0 + 0.0025 * dt),
            gamma: 1.4017 * (1.0 - 0.00002 * dt),
            sqrt_pr: 0.8410 * (1.0 - 0.0002 * dt),
        }
    }

    /// Air without viscous or thermal losses (for lossless verification cases).
    pub fn lossless(rho: f64, c: f64) -> Air {
        Air { rho, c, mu: 0.0, gamma: 1.4, sqrt_pr: 0.84 }
    }

    /// ρc², the adiabatic bulk modulus, Pa.
    pub fn bulk_modulus(&self) -> f64 {
        self.rho * self.c * self.c
    }

    /// Characteristic impedance of a tube of area `s`, Pa·s/m³.
    pub fn z0(&self, s: f64) -> f64 {
        self.rho * self.c / s
    }

    /// Series impedance per length Z and shunt admittance per length Y of a circular
    /// tube of cross-section `s` (Zwikker–Kosten / Benade form):
    /// Z = (jωρ/S)/(1 − F(r_v)), Y = (jωS/ρc²)(1 + (γ−1)F(r_t)).
    pub fn line_zy(&self, omega: f64, s: f64) -> (c64, c64) {
        let jw = c64::new(0.0, omega);
        let (fv, ft) = self.loss_functions(omega, s);
        let z = jw * self.rho / s / (c64::new(1.0, 0.0) - fv);
        let y = jw * s / self.bulk_modulus() * (c64::new(1.0, 0.0) + (self.gamma - 1.0) * ft);
        (z, y)
    }

    /// The viscous and thermal loss functions F(r_v), F(r_t) of a tube of area `s`.
    pub fn loss_functions(&self, omega: f64, s: f64) -> (c64, c64) {
        if self.mu == 0.0 {
            return (c64::new(0.0, 0.0), c64::new(0.0, 0.0));
        }
        let a = (s / std::f64::consts::PI).sqrt();
        let rv = a * (omega * self.rho / self.mu).sqrt();
        (loss_f(rv), loss_f(self.sqrt_pr * rv))
    }
}

/// F(r) = 2 J1(r√−j) / (r√−j J0(r√−j)) by its large-r expansion, from the Hankel
/// asymptotics of J1/J0: F ≈ √2(1−j)/r + j/r² + (1+j)/(4√2 r³).
/// The ear canal has r_v ≥ 30 above 100 Hz, where the r⁻⁴ remainder is below 1e-6;
/// the expansion is not used below r = 5 (there the exact Bessel form would be needed).
pub fn loss_f(r: f64) -> c64 {
    debug_assert!(r > 5.0, "viscothermal expansion used outside its range (r = {r})");
    let s2 = std::f64::consts::SQRT_2;
    let r2 = r * r;
    c64::new(s2 / r, -s2 / r) + c64::new(0.0, 1.0 / r2) + c64::new(1.0, 1.0) * (1.0 / (4.0 * s2) / (r2 * r))
}

/// Input impedance of a uniform line (characteristic impedance `zc`, propagation
/// constant `gamma`, length `l`) terminated by `zl` (`None` = rigid end).
pub fn line_input_impedance(zc: c64, gamma: c64, l: f64, zl: Option<c64>) -> c64 {
    let t = (gamma * l).tanh();
    match zl {
        None => zc / t,
        Some(zl) => zc * (zl + zc * t) / (zc + zl * t),
    }
}

/// Propagation constant Γ = √(ZY) and characteristic impedance Zc = √(Z/Y) of a line.
pub fn line_constants(z: c64, y: c64) -> (c64, c64) {
    let gamma = (z * y).sqrt();
    let zc = (z / y).sqrt();
    // Choose the decaying branch: Re Γ ≥ 0 and Re Zc ≥ 0.
    let gamma = if gamma.re < 0.0 || (gamma.re == 0.0 && gamma.im < 0.0) { -gamma } else { gamma };
    let zc = if zc.re < 0.0 { -zc } else { zc };
    (gamma, zc)
}

/// Moves an impedance `z` measured at one plane a distance `dx` toward the load along a
/// uniform line (negative `dx` moves away from it).
pub fn shift_impedance(z: c64, zc: c64, gamma: c64, dx: f64) -> c64 {
    let t = (gamma * dx).tanh();
    zc * (z - zc * t) / (zc - z * t)
}

/// Absorbance 1 − |R|², R = (Z − Z0)/(Z + Z0).
pub fn absorbance(z: c64, z0: f64) -> f64 {
    let r = (z - z0) / (z + z0);
    1.0 - r.norm_sqr()
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The range guard is live in tests (the test profile turns the workspace's own debug
    /// assertions on), so a caller outside the expansion's range fails a test.
    #[test]
    #[should_panic(expected = "outside its range")]
    fn the_expansions_range_guard_runs_in_tests() {
        loss_f(2.0);
    }

    #[test]
    fn air_fits_match_the_notes() {
        let a = Air::at_celsius(37.0);
        assert!((a.rho - 1.14).abs() < 0.005, "rho {}", a.rho);
        assert!((a.c - 353.0).abs() < 0.5, "c {}", a.c);
        let b = Air::at_celsius(22.0);
        assert!((b.rho - 1.19).abs() < 0.01 && (b.c - 344.4).abs() < 0.5);
    }

    #[test]
    fn loss_expansion_is_dissipative_and_shrinks() {
        // Both Z and Y must have positive real parts (energy is lost, never made).
        let air = Air::at_celsius(22.0);
        for f in [100.0, 1000.0, 8000.0] {
            let (z, y) = air.line_zy(2.0 * std::f64::consts::PI * f, 44e-6);
            assert!(z.re > 0.0 && y.re > 0.0);
        }
        assert!(loss_f(1000.0).norm() < loss_f(30.0).norm());
    }

    /// J_n(z) by its power series (exact enough for |z| ≤ 40 in f64 because J grows
    /// like e^{|Im z|} there while the terms grow slower).
    fn bessel_j(n: u32, z: c64) -> c64 {
        let half = z * 0.5;
        let mut term = c64::new(1.0, 0.0);
        for k in 1..=n {
            term = term * half / k as f64;
        }
        let q = half * half;
        let mut sum = term;
        for k in 1..200u32 {
            term = -term * q / ((k * (k + n)) as f64);
            sum += term;
            if term.norm() < 1e-18 * sum.norm() {
                break;
            }
        }
        sum
    }

    #[test]
    fn loss_expansion_matches_the_bessel_form() {
        let sqrt_mj = c64::new(0.5f64.sqrt(), -(0.5f64.sqrt()));
        for r in [8.0, 15.0, 30.0] {
            let z = sqrt_mj * r;
            let exact = bessel_j(1, z) * 2.0 / (z * bessel_j(0, z));
            let err = (exact - loss_f(r)).norm();
            assert!(err < 2.0 / r.powi(4), "r = {r}: |ΔF| = {err:e}");
        }
    }

    #[test]
    fn lossless_rigid_tube_absorbs_nothing() {
        let air = Air::lossless(1.19, 344.0);
        let s = 44e-6;
        for f in [200.0, 1234.5, 8000.0] {
            let (z, y) = air.line_zy(2.0 * std::f64::consts::PI * f, s);
            let (g, zc) = line_constants(z, y);
            let zin = line_input_impedance(zc, g, 0.012, None);
            assert!(absorbance(zin, air.z0(s)).abs() < 1e-12);
        }
    }
}
