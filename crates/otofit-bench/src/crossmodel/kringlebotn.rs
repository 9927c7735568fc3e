//! Kringlebotn's network model of the human middle ear: every element an acoustic
//! impedance referred to the eardrum,
//!
//! ```text
//! Z_drum = Z1 + Z2 ∥ (Z3 + Z4 ∥ Z5)
//! Z1 = [(La + Ca + Ra) ∥ Ct]  +  Ld  +  [(Ls + Cs + Rs) ∥ (Cr + Rr)]
//!       middle-ear cavities     drum    drum suspension / uncoupled drum
//! Z2 = Cm + Rm      eardrum–manubrium coupling (shunt)
//! Z3 = Lo + Ro (+ Co, infinite)  malleus and incus, their ligaments, tensor tympani
//! Z4 = Ci + Ri      incus–stapes coupling (shunt)
//! Z5 = Lc + Cc + Rc stapes, annular ligament, stapedius tendon, cochlea, windows
//! ```
//!
//! Source: M. Kringlebotn (1988), "Network model for the human middle ear", Scand.
//! Audiol. 17:75–85, Fig. 2 and its element table (CGS acoustic units: inertance
//! g/cm⁴ = 1e5 kg/m⁴, compliance cm⁵/dyn = 1e-5 m⁵/N, resistance dyn·s/cm⁵ = 1e5
//! Pa·s/m³). The original was not at hand; the values here are read from two
//! re-statements that agree element for element: Rosowski (1996), "Models of external-
//! and middle-ear function", in *Auditory Computation* (Springer), which restates
//! Kringlebotn's eardrum and cavity elements in SI and the ossicular ones as mechanical
//! elements behind transformers (as F. Perdigão's `rosowski.m` implements it), and the
//! SSMEP project's CGS table of Kringlebotn's network (`KringlebotnMiddleEar.py`).
//! Converting Rosowski's mechanical coupling elements back through his transformers
//! gives Kringlebotn's to within 4 % (C_TS·A_TM² = 3.96e-12 vs Cm = 3.8e-12 m⁵/N;
//! C_J·(A_TM·r_MI)² = 2.98e-12 vs Ci = 3.0e-12; R_J/(A_TM·r_MI)² = 5.9e8 vs Ri = 6.0e8).
//!
//! Velocities: the network is referred to the drum through an ideal transformer of area
//! A_TM = 60 mm² (drum to umbo) and a malleus–incus lever of 1.3 (Rosowski 1996, the
//! ratios his conversion uses), so the umbo moves at U3/A_TM and the stapes at
//! U5/(A_TM·1.3), U3 and U5 the volume velocities through Z3 and Z5.

use super::{DrumResponse, EarModel, compliance, mass, parallel, resistance, series};
use faer::c64;
use std::f64::consts::PI;

/// CGS acoustic inertance (g/cm⁴) in kg/m⁴.
const INERTANCE: f64 = 1e5;
/// CGS acoustic compliance (cm⁵/dyn) in m⁵/N.
const COMPLIANCE: f64 = 1e-5;
/// CGS acoustic resistance (dyn·s/cm⁵) in Pa·s/m³.
const RESISTANCE: f64 = 1e5;

/// Drum-to-umbo transformer area, m² (Rosowski 1996, A_TM).
pub const AREA_TM: f64 = 60e-6;
/// Malleus–incus lever ratio (Rosowski 1996, r_MI).
pub const LEVER: f64 = 1.3;

/// The network's elements in SI acoustic units (inertance kg/m⁴, compliance m⁵/N,
/// resistance Pa·s/m³), named as in Kringlebotn 1988.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Kringlebotn {
    /// Aditus, antrum and mastoid inertance (1e-3 g/cm⁴).
    pub la: f64,
    /// Antrum and mastoid air compliance (3.9e-6 cm⁵/dyn).
    pub ca: f64,
    /// Aditus resistance (60 dyn·s/cm⁵).
    pub ra: f64,
    /// Tympanic cavity air compliance (0.4e-6 cm⁵/dyn).
    pub ct: f64,
    /// Eardrum inertance (7.5e-3 g/cm⁴).
    pub ld: f64,
    /// Eardrum suspension inertance (66e-3 g/cm⁴).
    pub ls: f64,
    /// Eardrum suspension compliance (0.3e-6 cm⁵/dyn).
    pub cs: f64,
    /// Eardrum suspension resistance (20 dyn·s/cm⁵).
    pub rs: f64,
    /// Eardrum (uncoupled part) compliance (1.3e-6 cm⁵/dyn).
    pub cr: f64,
    /// Eardrum (uncoupled part) resistance (120 dyn·s/cm⁵).
    pub rr: f64,
    /// Eardrum–manubrium coupling compliance (0.38e-6 cm⁵/dyn).
    pub cm: f64,
    /// Eardrum–manubrium coupling resistance (120 dyn·s/cm⁵).
    pub rm: f64,
    /// Malleus and incus inertance (22e-3 g/cm⁴).
    pub lo: f64,
    /// Malleus–incus suspension resistance (20 dyn·s/cm⁵).
    pub ro: f64,
    /// Malleus–incus suspension compliance: infinite in Kringlebotn 1988 (the ligaments'
    /// stiffness is negligible in the network); finite only for a fixed malleus.
    pub co: f64,
    /// Incus–stapes coupling compliance (0.3e-6 cm⁵/dyn).
    pub ci: f64,
    /// Incus–stapes coupling resistance (6000 dyn·s/cm⁵).
    pub ri: f64,
    /// Stapes and cochlea inertance (46e-3 g/cm⁴).
    pub lc: f64,
    /// Stapes and cochlea compliance, the annular ligament's (0.56e-6 cm⁵/dyn).
    pub cc: f64,
    /// Stapes and cochlea resistance (330 dyn·s/cm⁵).
    pub rc: f64,
}

impl Kringlebotn {
    /// The mechanical resistance the stapes meets, N·s/m: R_c through the transformer and
    /// the lever, R_c·(A_TM·r_MI)². An upper bound of the cochlea's own: Kringlebotn's R_c
    /// also holds the stapes' and annular ligament's losses.
    pub fn cochlear_resistance(&self) -> f64 {
        self.rc * (AREA_TM * LEVER).powi(2)
    }

    /// Kringlebotn 1988's published values.
    pub fn published() -> Kringlebotn {
        Kringlebotn {
            la: 1e-3 * INERTANCE,
            ca: 3.9e-6 * COMPLIANCE,
            ra: 60.0 * RESISTANCE,
            ct: 0.4e-6 * COMPLIANCE,
            ld: 7.5e-3 * INERTANCE,
            ls: 66e-3 * INERTANCE,
            cs: 0.3e-6 * COMPLIANCE,
            rs: 20.0 * RESISTANCE,
            cr: 1.3e-6 * COMPLIANCE,
            rr: 120.0 * RESISTANCE,
            cm: 0.38e-6 * COMPLIANCE,
            rm: 120.0 * RESISTANCE,
            lo: 22e-3 * INERTANCE,
            ro: 20.0 * RESISTANCE,
            co: f64::INFINITY,
            ci: 0.3e-6 * COMPLIANCE,
            ri: 6000.0 * RESISTANCE,
            lc: 46e-3 * INERTANCE,
            cc: 0.56e-6 * COMPLIANCE,
            rc: 330.0 * RESISTANCE,
        }
    }

    /// Stapes fixation: the stapes–cochlea branch's compliance (the annular ligament's)
    /// divided by `factor` (10–100).
    pub fn stapes_fixed(mut self, factor: f64) -> Kringlebotn {
        self.cc /= factor;
        self
    }

    /// Malleus fixation. The published network has no suspension stiffness (Co = ∞), so
    /// "100× stiffer" needs a finite base: Hudde & Engel's (1998) ossicular suspension,
    /// n_oss = 3 mm/N, referred to the drum through A_TM (3e-3 · A_TM² = 1.08e-11 m⁵/N),
    /// made 100× stiffer: Co = 1.08e-13 m⁵/N.
    pub fn malleus_fixed(mut self) -> Kringlebotn {
        self.co = super::hudde_engel::N_OSS * AREA_TM * AREA_TM / 100.0;
        self
    }

    /// Incudostapedial discontinuity: the joint's coupling shunt left as a soft-tissue
    /// remnant, 1000× more compliant and with 1/1000 of its resistance.
    pub fn disconnected(mut self) -> Kringlebotn {
        self.ci *= 1000.0;
        self.ri /= 1000.0;
        self
    }

    /// The network's branches at angular frequency `w`: (Z1, Z2, Z3, Z4, Z5).
    fn branches(&self, w: f64) -> [c64; 5] {
        let cavities = parallel(&[
            series(&[mass(w, self.la), compliance(w, self.ca), resistance(self.ra)]),
            compliance(w, self.ct),
        ]);
        let suspension = parallel(&[
            series(&[mass(w, self.ls), compliance(w, self.cs), resistance(self.rs)]),
            series(&[compliance(w, self.cr), resistance(self.rr)]),
        ]);
        [
            series(&[cavities, mass(w, self.ld), suspension]),
            series(&[compliance(w, self.cm), resistance(self.rm)]),
            series(&[mass(w, self.lo), resistance(self.ro), compliance(w, self.co)]),
            series(&[compliance(w, self.ci), resistance(self.ri)]),
            series(&[mass(w, self.lc), compliance(w, self.cc), resistance(self.rc)]),
        ]
    }
}

impl EarModel for Kringlebotn {
    fn at(&self, freq_hz: f64) -> DrumResponse {
        let w = 2.0 * PI * freq_hz;
        let [z1, z2, z3, z4, z5] = self.branches(w);
        let z45 = parallel(&[z4, z5]);
        let z345 = z3 + z45;
        let z2345 = parallel(&[z2, z345]);
        let z_drum = z1 + z2345;
        // A unit pressure on the drum: the flow into it, then its share through the
        // ossicular branch (Z3) and through the stapes (Z5).
        let u_drum = c64::new(1.0, 0.0) / z_drum;
        let u3 = u_drum * z2345 / z345;
        let u5 = u3 * z45 / z5;
        DrumResponse { z_drum, v_umbo: u3 / AREA_TM, v_stapes: u5 / (AREA_TM * LEVER) }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Below every resonance the network is its compliances: the cavities' (Ct + Ca), the
    /// drum's (Cs + Cr) and the ossicles' three shunts (Cm + Ci + Cc) in series.
    #[test]
    fn low_frequency_impedance_is_the_networks_compliance() {
        let k = Kringlebotn::published();
        // At 0.1 Hz the largest resistance, Ri, is 1e-3 of its compliance's reactance.
        let f = 0.1;
        let w = 2.0 * PI * f;
        let c = 1.0 / (1.0 / (k.ct + k.ca) + 1.0 / (k.cs + k.cr) + 1.0 / (k.cm + k.ci + k.cc));
        let z = k.at(f).z_drum;
        let expect = c64::new(0.0, -1.0 / (w * c));
        assert!((z - expect).norm() < 3e-3 * expect.norm(), "{z} vs {expect}");
        assert!((z.arg().to_degrees() + 90.0).abs() < 0.2, "phase {}", z.arg().to_degrees());
        // As an equivalent air volume (ρc² = 1.42e5 Pa), 0.85 cm³: inside the adult
        // range of static admittance at 226 Hz, 0.3–1.7 cm³ (Margolis & Heller 1987).
        let volume_cm3 = c * 1.42e5 * 1e6;
        assert!((0.3..1.7).contains(&volume_cm3), "equivalent volume {volume_cm3} cm³");
    }

    /// The healthy network's stapes velocity at 1 kHz lies inside the temporal-bone
    /// acceptance range of ASTM F2504-05 (Rosowski, Chien, Ravicz & Merchant 2007, Audiol.
    /// Neurootol. 12:265; physics-notes §3.1): −30 to −9 dB re 1 mm/s/Pa.
    #[test]
    fn healthy_stapes_velocity_at_1khz_is_in_the_astm_range() {
        let v = Kringlebotn::published().at(1000.0).v_stapes.norm();
        let db = 20.0 * (v / 1e-3).log10();
        assert!((-30.0..=-9.0).contains(&db), "|Vs/P| at 1 kHz = {db:.1} dB re 1 mm/s/Pa");
    }

    /// Each condition moves the velocities the way the clinical and temporal-bone
    /// literature reports (physics-notes §4): fixations lower the stapes' low-frequency
    /// motion, a broken incudostapedial joint lowers it most while the umbo moves more.
    #[test]
    fn conditions_move_velocities_in_the_reported_directions() {
        let healthy = Kringlebotn::published().at(400.0);
        let db = |a: c64, b: c64| 20.0 * (a.norm() / b.norm()).log10();
        let stapes = Kringlebotn::published().stapes_fixed(30.0).at(400.0);
        assert!(db(stapes.v_stapes, healthy.v_stapes) < -10.0);
        let malleus = Kringlebotn::published().malleus_fixed().at(400.0);
        assert!(db(malleus.v_umbo, healthy.v_umbo) < -10.0);
        let broken = Kringlebotn::published().disconnected().at(400.0);
        assert!(db(broken.v_stapes, healthy.v_stapes) < -20.0);
        assert!(db(broken.v_umbo, healthy.v_umbo) > 0.0);
    }
}
