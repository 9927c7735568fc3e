//! Conversions from the immittance quantities devices report to the model's features
//! (ear-canal impedance magnitude and phase, absorbance). Time convention e^{+jωt}, as in
//! `sim`: a compliant ear has a negative impedance phase at low frequencies.
//!
//! Pressure reflectance R relates to the impedance Z at the same plane through the
//! canal's characteristic impedance Z0 = ρc/S: R = (Z − Z0)/(Z + Z0), so
//! Z = Z0 (1 + R)/(1 − R), and absorbance A = 1 − |R|² (Rosowski, Stenfelt & Lilly 2013,
//! Ear Hear 34 Suppl 1). Turning R into Z needs S, the canal's cross-section at the probe
//! (the WAI database's AreaCanal), and ρc of the air: here ρc at 37 °C. A device that
//! computed R with another ρc or area gives an impedance off by the ratio of the two Z0 —
//! a few per cent for the temperature, more for the area.

use crate::sim::air::Air;
use faer::c64;

/// ρc of air at 37 °C (in the ear canal), Pa·s/m (≈ 401).
pub fn rho_c() -> f64 {
    let air = Air::at_celsius(37.0);
    air.rho * air.c
}

/// The characteristic impedance ρc/S of a canal of cross-section `area` (m²), Pa·s/m³.
pub fn z0(area: f64) -> f64 {
    rho_c() / area
}

/// (|Z|, ∠Z in rad) from pressure reflectance (|R|, ∠R in rad) where the characteristic
/// impedance is `z0`; `None` at R = 1 (an infinite impedance).
pub fn impedance_from_reflectance(r_mag: f64, r_phase: f64, z0: f64) -> Option<(f64, f64)> {
    let r = c64::from_polar(r_mag, r_phase);
    let one = c64::new(1.0, 0.0);
    if (one - r).norm() < 1e-12 {
        return None;
    }
    let z = (one + r) / (one - r) * z0;
    Some((z.norm(), z.arg()))
}

/// (|R|, ∠R in rad) from an impedance (|Z|, ∠Z in rad) and `z0`.
pub fn reflectance_from_impedance(z_mag: f64, z_phase: f64, z0: f64) -> (f64, f64) {
    let z = c64::from_polar(z_mag, z_phase);
    let r = (z - z0) / (z + z0);
    (r.norm(), r.arg())
}

/// (|Z|, ∠Z) from an admittance (|Y|, ∠Y) in SI units: Z = 1/Y.
pub fn impedance_from_admittance(y_mag: f64, y_phase: f64) -> (f64, f64) {
    (1.0 / y_mag, -y_phase)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn reflectance_and_impedance_round_trip_and_give_the_simulators_absorbance() {
        let z0 = z0(44e-6);
        assert!((rho_c() - 401.4).abs() < 0.5, "{}", rho_c());
        for (zm, zp) in [(9.4e7, -1.49), (1.4e7, -0.57), (8.0e5, 0.85), (z0, 0.0)] {
            let (rm, rp) = reflectance_from_impedance(zm, zp, z0);
            let (zm2, zp2) = impedance_from_reflectance(rm, rp, z0).unwrap();
            assert!((zm2 / zm - 1.0).abs() < 1e-12 && (zp2 - zp).abs() < 1e-12, "{zm} {zp}: {zm2} {zp2}");
            let a = crate::sim::air::absorbance(c64::from_polar(zm, zp), z0);
            assert!((1.0 - rm * rm - a).abs() < 1e-12);
        }
        // A matched load reflects nothing; a rigid wall (Z → ∞) everything, in phase.
        assert!(reflectance_from_impedance(z0, 0.0, z0).0 < 1e-15);
        assert!(impedance_from_reflectance(1.0, 0.0, z0).is_none());
        // A compliance (Z phase −90°) reflects with |R| = 1 and a phase below 0.
        let (rm, rp) = reflectance_from_impedance(1e8, -std::f64::consts::FRAC_PI_2, z0);
        assert!((rm - 1.0).abs() < 1e-12 && rp < 0.0);
        let (m, p) = impedance_from_admittance(1e-8, 1.2);
        assert_eq!((m, p), (1e8, -1.2));
    }
}
