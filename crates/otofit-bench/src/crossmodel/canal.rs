//! The residual ear canal between the probe and the drum as a uniform tube, by its
//! transfer (ABCD) matrix: with x measured laterally from the drum,
//!
//! ```text
//! [p(x)]   [cosh Γx      Zc sinh Γx] [p_drum]
//! [U(x)] = [sinh Γx / Zc  cosh Γx  ] [U_drum],   U_drum = p_drum / Z_drum
//! ```
//!
//! (Γ the propagation constant, Zc the characteristic impedance; lossless, Γ = jω/c and
//! Zc = ρc/S, this is the textbook chain matrix [cos kx, jZ0 sin kx; j sin kx / Z0,
//! cos kx], e.g. Keefe 1984, JASA 75:58, eq. 2, and physics-notes §5.1). Γ and Zc come
//! from the same viscothermal air otofit's own canal uses (Zwikker–Kosten form in
//! `otofit_sim::air`), so that a cross-model ear differs from otofit's ears in its middle
//! ear only, not in how the canal is computed.

use faer::c64;
use otofit_sim::air::{self, Air};

/// A uniform tube at one frequency.
#[derive(Clone, Copy, Debug)]
pub struct Tube {
    /// Propagation constant Γ, 1/m.
    pub gamma: c64,
    /// Characteristic impedance Zc, Pa·s/m³.
    pub zc: c64,
}

impl Tube {
    /// The canal of cross-section `area` filled with `air`, at angular frequency `w`.
    pub fn new(air: &Air, w: f64, area: f64) -> Tube {
        let (z, y) = air.line_zy(w, area);
        let (gamma, zc) = air::line_constants(z, y);
        Tube { gamma, zc }
    }

    /// Pressure and volume velocity a distance `x` lateral of a load `z_load` for a unit
    /// flow into the load.
    fn state(&self, x: f64, z_load: c64) -> (c64, c64) {
        let (ch, sh) = ((self.gamma * x).cosh(), (self.gamma * x).sinh());
        (ch * z_load + self.zc * sh, sh * z_load / self.zc + ch)
    }

    /// Impedance a distance `l` lateral of a load `z_load`.
    pub fn input_impedance(&self, l: f64, z_load: c64) -> c64 {
        let (p, u) = self.state(l, z_load);
        p / u
    }

    /// Impedance a distance `l` from a rigid end: Zc·coth(Γl) (as cosh/sinh, finite at
    /// the lossless quarter-wave null where tanh is not).
    pub fn input_impedance_rigid(&self, l: f64) -> c64 {
        self.zc * (self.gamma * l).cosh() / (self.gamma * l).sinh()
    }

    /// Pressure a distance `x` lateral of a load `z_load` over the pressure on the load.
    pub fn pressure_ratio(&self, x: f64, z_load: c64) -> c64 {
        self.state(x, z_load).0 / z_load
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::f64::consts::PI;

    const AREA: f64 = 44e-6;
    const LENGTH: f64 = 12e-3;

    /// Lossless and rigidly closed: the quarter-wave null sits at c/(4L), the half-wave
    /// pole at c/(2L), and the absorbance is 0 at every frequency.
    #[test]
    fn rigid_lossless_tube_has_its_quarter_wave_null() {
        let air = Air::lossless(1.2, 343.0);
        let z0 = air.z0(AREA);
        let f_null = 343.0 / (4.0 * LENGTH);
        let at = |f: f64| Tube::new(&air, 2.0 * PI * f, AREA).input_impedance_rigid(LENGTH);
        assert!(at(f_null).norm() < 1e-9 * z0, "|Z| at c/4L = {}", at(f_null).norm());
        assert!(at(0.98 * f_null).norm() > 0.02 * z0 && at(1.02 * f_null).norm() > 0.02 * z0);
        assert!(at(2.0 * f_null * 0.999).norm() > 100.0 * z0, "no pole at c/2L");
        for f in [200.0, 1000.0, 5000.0, 8000.0] {
            let a = otofit_sim::air::absorbance(at(f), z0);
            assert!(a.abs() < 1e-12, "absorbance {a} at {f} Hz");
        }
    }

    /// At low frequency a closed tube is its air's compliance S·L/(ρc²).
    #[test]
    fn closed_tube_is_a_compliance_at_low_frequency() {
        let air = Air::lossless(1.2, 343.0);
        let w = 2.0 * PI * 5.0;
        let c = AREA * LENGTH / air.bulk_modulus();
        let z = Tube::new(&air, w, AREA).input_impedance_rigid(LENGTH);
        let expect = c64::new(0.0, -1.0 / (w * c));
        assert!((z - expect).norm() < 1e-4 * expect.norm(), "{z} vs {expect}");
    }

    /// A matched load sees no reflection: Z = Z0 anywhere, |p| unchanged along the tube.
    #[test]
    fn matched_load_is_seen_unchanged() {
        let air = Air::lossless(1.2, 343.0);
        let z0 = c64::new(air.z0(AREA), 0.0);
        let t = Tube::new(&air, 2.0 * PI * 3000.0, AREA);
        assert!((t.input_impedance(LENGTH, z0) - z0).norm() < 1e-9 * z0.norm());
        assert!((t.pressure_ratio(LENGTH, z0).norm() - 1.0).abs() < 1e-12);
    }

    /// With losses the chain matrix agrees with otofit's closed-form line impedance.
    #[test]
    fn lossy_tube_agrees_with_the_line_formula() {
        let air = Air::at_celsius(22.0);
        let load = c64::new(2e7, -3e7);
        for f in [200.0, 2000.0, 8000.0] {
            let w = 2.0 * PI * f;
            let t = Tube::new(&air, w, AREA);
            let ours = t.input_impedance(LENGTH, load);
            let line = otofit_sim::air::line_input_impedance(t.zc, t.gamma, LENGTH, Some(load));
            assert!((ours - line).norm() < 1e-9 * line.norm(), "{f} Hz: {ours} vs {line}");
        }
    }
}
