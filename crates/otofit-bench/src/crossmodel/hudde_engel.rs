//! Hudde & Engel's acousto-mechanical middle-ear model (adult), fitted to their own
//! eardrum-impedance and transfer measurements: an acoustic eardrum shunt Y_ac beside a
//! frequency-dependent effective drum area A_D that drives the malleus, the
//! incudomalleolar joint as a slip shunt between malleus and incus, the stapes and the
//! cochlea as the load, and the middle-ear cavities in series:
//!
//! ```text
//! Z_drum = Z_cav + 1 / (Y_ac + A_D² / z_mech)
//! z_mech = ⅔ Z_dmi + 1 / (Y_mi + 1 / (⅓ Z_dmi + Z_load))
//! Z_dmi  = 1/(jω n_oss) + jω m_oss + (jω m_free + w_free) ∥ (1/(jω n_cpl) + w_cpl)
//! Y_mi   = 1 / (1/(jω n_mi) + w_mi)
//! Z_load = w_St + jω m_St + 1/(jω n_St) + w_C + jω m_C + 1/(jω n_C)
//! Y_ac   = e^{jφ_Y} / (W_ac + jω M_ac0 (1 + √(f/f_Ym)) + 1/(jω N_ac)),
//!          φ_Y = s_Yph · log10(1 + f/f_Yph)
//! A_D    = (A_0 + A_∞) / (1 − (f/f_A)² + j f/(f_A Q_A)) − A_∞, its phase above f_Aph
//!          continued as arg A_D(f_Aph) + s_Aph · log10(f/f_Aph)
//! Y_cav  = 1/(W_t + 1/(jω N_t)) + 1/(W_ada + jω M_ada + 1/(jω N_ant + Y_mac)),
//!          Y_mac = jω N_mac / (1 − (f/f_mac)² + j f/(f_mac Q_mac)),  N = V/(ρc²)
//! ```
//!
//! Sources: H. Hudde & A. Engel (1998), "Measuring and modeling basic properties of the
//! human middle ear and ear canal", Parts I–III, Acustica / Acta Acustica 84:720–738,
//! 894–913, 1091–1108 (structure and adult values). The values and the two empirical
//! phase terms are read from their restatement in T. Sankowsky-Rothe et al. (2022),
//! "Parametric model of young infants' eardrum and ear canal impedances…", Parts I–II,
//! Acta Acustica, whose published code keeps Hudde & Engel's adult model as an option
//! (`ModelStructure = 'Hudde_Engel_1998'`, `AgeGroup = 'adult'`).
//!
//! Velocities: the malleus (umbo) moves at v_M = A_D·p_net / z_mech, p_net the pressure
//! across the drum; the stapes at the incus' velocity (the model has no lever: the
//! incus and the stapes are one series branch), less what a broken incudostapedial
//! joint lets slip.

use super::{DrumResponse, EarModel, compliance, mass, parallel, resistance, series};
use faer::c64;
use otofit_sim::air::Air;
use std::f64::consts::PI;

/// Hudde & Engel's ossicular-chain suspension compliance, m/N (also the base of
/// Kringlebotn's malleus fixation, which has none).
pub const N_OSS: f64 = 3.0e-3;

/// The model's parameters (SI: acoustic elements in Pa·s/m³, kg/m⁴, m⁵/N; mechanical
/// ones in N·s/m, kg, m/N), named as in Hudde & Engel 1998 / Sankowsky-Rothe 2022.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct HuddeEngel {
    /// Eardrum acoustic losses W_ac (4e7 Pa·s/m³).
    pub w_ac: f64,
    /// Eardrum acoustic compliance N_ac (5e-12 m⁵/N).
    pub n_ac: f64,
    /// Eardrum acoustic mass at low frequency M_ac0 (2400 kg/m⁴).
    pub m_ac0: f64,
    /// Frequency at which the drum's acoustic mass has doubled, f_Ym (1900 Hz).
    pub f_ym: f64,
    /// Characteristic frequency of Y_ac's phase term, f_Yph (8000 Hz).
    pub f_yph: f64,
    /// Slope of Y_ac's phase term, s_Yph (1.4π).
    pub s_yph: f64,
    /// Effective drum area at low frequency, A_0 (38 mm², 0.633 of a 60 mm² drum).
    pub a_0: f64,
    /// Effective drum area at high frequency, A_∞ (2 mm²).
    pub a_inf: f64,
    /// Quality factor of the area function, Q_A (1.3).
    pub q_a: f64,
    /// Characteristic frequency of the area function, f_A (2200 Hz).
    pub f_a: f64,
    /// Frequency above which the area's phase follows the slope, f_Aph (1500 Hz).
    pub f_aph: f64,
    /// Slope of the area's phase above f_Aph, s_Aph (−1.2π).
    pub s_aph: f64,
    /// Ossicular-chain suspension compliance n_oss (3 mm/N).
    pub n_oss: f64,
    /// Ossicular-chain mass m_oss (7 mg).
    pub m_oss: f64,
    /// Drum–malleus coupling compliance n_cpl (0.5 mm/N).
    pub n_cpl: f64,
    /// Drum–malleus coupling losses w_cpl (0.08 N·s/m).
    pub w_cpl: f64,
    /// Freely vibrating drum's losses w_free (0.02 N·s/m).
    pub w_free: f64,
    /// Freely vibrating drum's mass m_free (12 mg).
    pub m_free: f64,
    /// Incudomalleolar joint compliance n_mi (0.04 mm/N).
    pub n_mi: f64,
    /// Incudomalleolar joint losses w_mi (1 N·s/m).
    pub w_mi: f64,
    /// Stapes losses w_St (18e-3 N·s/m).
    pub w_st: f64,
    /// Stapes mass m_St (3 mg).
    pub m_st: f64,
    /// Stapes (annular ligament) compliance n_St (1.2 mm/N).
    pub n_st: f64,
    /// Cochlear losses w_C (70e-3 N·s/m, at the footplate).
    pub w_c: f64,
    /// Cochlear fluid mass m_C (10 mg, at the footplate).
    pub m_c: f64,
    /// Cochlear compliance n_C (11 mm/N, at the footplate).
    pub n_c: f64,
    /// Incudostapedial slip compliance: 0 for the intact (rigid) joint of the model.
    pub n_isj: f64,
    /// Incudostapedial slip losses (with `n_isj`).
    pub w_isj: f64,
    /// Tympanic cavity losses W_t (2e6 Pa·s/m³).
    pub w_t: f64,
    /// Tympanic cavity volume V_t (0.5 cm³).
    pub v_t: f64,
    /// Aditus ad antrum losses W_ada (1.7e6 Pa·s/m³).
    pub w_ada: f64,
    /// Aditus ad antrum mass M_ada (880 kg/m⁴).
    pub m_ada: f64,
    /// Antrum volume V_ant (0.8 cm³).
    pub v_ant: f64,
    /// Mastoid air cells' volume V_mac (8 cm³).
    pub v_mac: f64,
    /// Mastoid air cells' characteristic frequency f_mac (3500 Hz).
    pub f_mac: f64,
    /// Mastoid air cells' quality factor Q_mac (0.4).
    pub q_mac: f64,
    /// ρc² of the middle-ear air, Pa (body temperature).
    pub bulk_modulus: f64,
}

impl HuddeEngel {
    /// The cochlea's mechanical resistance at the footplate, N·s/m (w_C).
    pub fn cochlear_resistance(&self) -> f64 {
        self.w_c
    }

    /// Hudde & Engel's adult values.
    pub fn published() -> HuddeEngel {
        HuddeEngel {
            w_ac: 4e7,
            n_ac: 5e-12,
            m_ac0: 2400.0,
            f_ym: 1900.0,
            f_yph: 8000.0,
            s_yph: 1.4 * PI,
            a_0: 38e-6,
            a_inf: 2e-6,
            q_a: 1.3,
            f_a: 2200.0,
            f_aph: 1500.0,
            s_aph: -1.2 * PI,
            n_oss: N_OSS,
            m_oss: 7e-6,
            n_cpl: 0.5e-3,
            w_cpl: 0.08,
            w_free: 0.02,
            m_free: 12e-6,
            n_mi: 0.04e-3,
            w_mi: 1.0,
            w_st: 18e-3,
            m_st: 3e-6,
            n_st: 1.2e-3,
            w_c: 70e-3,
            m_c: 10e-6,
            n_c: 11e-3,
            n_isj: 0.0,
            w_isj: 0.0,
            w_t: 2e6,
            v_t: 0.5e-6,
            w_ada: 1.7e6,
            m_ada: 880.0,
            v_ant: 0.8e-6,
            v_mac: 8e-6,
            f_mac: 3500.0,
            q_mac: 0.4,
            bulk_modulus: Air::at_celsius(37.0).bulk_modulus(),
        }
    }

    /// Stapes fixation: the stapes' (annular ligament's) compliance divided by `factor`.
    pub fn stapes_fixed(mut self, factor: f64) -> HuddeEngel {
        self.n_st /= factor;
        self
    }

    /// Malleus fixation: the ossicular suspension 100× stiffer.
    pub fn malleus_fixed(mut self) -> HuddeEngel {
        self.n_oss /= 100.0;
        self
    }

    /// Incudostapedial discontinuity. The model's joint is rigid; a break lets the
    /// incus slip over the stapes through a soft-tissue remnant, a shunt with
    /// Rosowski's (1996) ISJ values (C_J = 4.9e-4 m/N, R_J = 3.6 N·s/m, as restated from
    /// Kringlebotn 1988) made 1000× more compliant and 1000× less lossy, as in
    /// [`super::kringlebotn::Kringlebotn::disconnected`].
    pub fn disconnected(mut self) -> HuddeEngel {
        self.n_isj = 4.9e-4 * 1000.0;
        self.w_isj = 3.6 / 1000.0;
        self
    }

    /// The drum's acoustic shunt admittance Y_ac at `f` Hz.
    pub fn y_ac(&self, f: f64) -> c64 {
        let w = 2.0 * PI * f;
        let m = self.m_ac0 * (1.0 + (f / self.f_ym).sqrt());
        let phase = self.s_yph * (1.0 + f / self.f_yph).log10();
        c64::from_polar(1.0, phase) / series(&[resistance(self.w_ac), mass(w, m), compliance(w, self.n_ac)])
    }

    /// The effective drum area A_D at `f` Hz, m² (complex).
    pub fn area(&self, f: f64) -> c64 {
        let second_order = |f: f64| {
            c64::new(self.a_0 + self.a_inf, 0.0) / c64::new(1.0 - (f / self.f_a).powi(2), f / (self.f_a * self.q_a))
                - self.a_inf
        };
        let a = second_order(f);
        if f > self.f_aph {
            let phase = second_order(self.f_aph).arg() + self.s_aph * (f / self.f_aph).log10();
            c64::from_polar(a.norm(), phase)
        } else {
            a
        }
    }

    /// The middle-ear cavities' impedance at `f` Hz.
    pub fn z_cavities(&self, f: f64) -> c64 {
        let w = 2.0 * PI * f;
        let n = |v: f64| v / self.bulk_modulus;
        let jw = c64::new(0.0, w);
        let y_mac = jw * n(self.v_mac) / c64::new(1.0 - (f / self.f_mac).powi(2), f / (self.f_mac * self.q_mac));
        let one = c64::new(1.0, 0.0);
        let antrum = one / (jw * n(self.v_ant) + y_mac);
        let y = one / series(&[resistance(self.w_t), compliance(w, n(self.v_t))])
            + one / series(&[resistance(self.w_ada), mass(w, self.m_ada), antrum]);
        one / y
    }
}

impl EarModel for HuddeEngel {
    fn at(&self, freq_hz: f64) -> DrumResponse {
        let w = 2.0 * PI * freq_hz;
        let one = c64::new(1.0, 0.0);
        let z_dmi = series(&[
            compliance(w, self.n_oss),
            mass(w, self.m_oss),
            parallel(&[
                series(&[mass(w, self.m_free), resistance(self.w_free)]),
                series(&[compliance(w, self.n_cpl), resistance(self.w_cpl)]),
            ]),
        ]);
        let y_mi = one / series(&[compliance(w, self.n_mi), resistance(self.w_mi)]);
        let z_load = series(&[
            resistance(self.w_st + self.w_c),
            mass(w, self.m_st + self.m_c),
            compliance(w, self.n_st),
            compliance(w, self.n_c),
        ]);
        // A broken incudostapedial joint: a slip shunt across the load.
        let z_stapes = if self.n_isj > 0.0 {
            parallel(&[z_load, series(&[compliance(w, self.n_isj), resistance(self.w_isj)])])
        } else {
            z_load
        };
        let z_incus = z_dmi / 3.0 + z_stapes;
        let z_after_malleus = one / (y_mi + one / z_incus);
        let z_mech = z_dmi * (2.0 / 3.0) + z_after_malleus;
        let a_d = self.area(freq_hz);
        let z_cav = self.z_cavities(freq_hz);
        let z_drum = z_cav + one / (self.y_ac(freq_hz) + a_d * a_d / z_mech);
        // A unit pressure on the drum: the pressure across it, the malleus' velocity,
        // the force at the incudomalleolar joint, the incus' and the stapes' velocities.
        let p_net = one - z_cav / z_drum;
        let v_malleus = a_d * p_net / z_mech;
        let v_incus = v_malleus * z_after_malleus / z_incus;
        let v_stapes = v_incus * z_stapes / z_load;
        DrumResponse { z_drum, v_umbo: v_malleus, v_stapes }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Sankowsky-Rothe et al. (2022, Part I) set their infant drum's tension from the
    /// imaginary part of Hudde & Engel's Y_ac at 160 Hz, 4.9363e-9 m⁵/(N·s): equal to
    /// its five digits.
    #[test]
    fn drum_shunt_at_160_hz_is_the_published_value() {
        let y = HuddeEngel::published().y_ac(160.0);
        assert!((y.im - 4.9363e-9).abs() < 2e-5 * 4.9363e-9, "Im Y_ac(160 Hz) = {:e}", y.im);
    }

    /// Below every resonance the model is its compliances: the drum's shunt N_ac beside
    /// the ossicles' (n_oss split ⅔ / ⅓ around the joint n_mi, then n_St and n_C in
    /// series) seen through A_0², in series with the cavities' three air volumes.
    #[test]
    fn low_frequency_impedance_is_the_models_compliance() {
        let m = HuddeEngel::published();
        let f = 1.0;
        let w = 2.0 * PI * f;
        let n_incus = 1.0 / (1.0 / (3.0 * m.n_oss) + 1.0 / m.n_st + 1.0 / m.n_c);
        let n_mech = 1.0 / (1.0 / (1.5 * m.n_oss) + 1.0 / (m.n_mi + n_incus));
        let c_drum = m.n_ac + m.a_0 * m.a_0 * n_mech;
        let c_cav = (m.v_t + m.v_ant + m.v_mac) / m.bulk_modulus;
        let c = 1.0 / (1.0 / c_drum + 1.0 / c_cav);
        let z = m.at(f).z_drum;
        let expect = c64::new(0.0, -1.0 / (w * c));
        assert!((z - expect).norm() < 0.01 * expect.norm(), "{z} vs {expect}");
    }

    /// The healthy model's stapes velocity at 1 kHz lies inside ASTM F2504-05's
    /// temporal-bone range (Rosowski et al. 2007): −30 to −9 dB re 1 mm/s/Pa.
    #[test]
    fn healthy_stapes_velocity_at_1khz_is_in_the_astm_range() {
        let v = HuddeEngel::published().at(1000.0).v_stapes.norm();
        let db = 20.0 * (v / 1e-3).log10();
        assert!((-30.0..=-9.0).contains(&db), "|Vs/P| at 1 kHz = {db:.1} dB re 1 mm/s/Pa");
    }

    /// Conditions move the velocities as reported (physics-notes §4).
    #[test]
    fn conditions_move_velocities_in_the_reported_directions() {
        let f = 400.0;
        let healthy = HuddeEngel::published().at(f);
        let db = |a: c64, b: c64| 20.0 * (a.norm() / b.norm()).log10();
        let stapes = HuddeEngel::published().stapes_fixed(30.0).at(f);
        assert!(db(stapes.v_stapes, healthy.v_stapes) < -10.0);
        let malleus = HuddeEngel::published().malleus_fixed().at(f);
        assert!(db(malleus.v_umbo, healthy.v_umbo) < -10.0);
        let broken = HuddeEngel::published().disconnected().at(f);
        assert!(db(broken.v_stapes, healthy.v_stapes) < -20.0);
        assert!(db(broken.v_umbo, healthy.v_umbo) > 0.0);
    }
}
