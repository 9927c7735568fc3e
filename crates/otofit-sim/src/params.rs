//! The inferred parameters — seven tissue parameters (simulator.md table; sources in
//! physics-notes §2), three measurement-geometry nuisances and two properties every ear
//! has but the study fixed (its middle-ear air volume, its eardrum's viscoelasticity) —
//! and the optional effects (physics-notes §4), with names, units, scales and ranges.

use serde::{Deserialize, Serialize};

/// Sampling scale of a parameter (also read from prior and checkpoint files).
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Scale {
    /// Uniform in the value.
    Linear,
    /// Uniform in log10 of the value (moduli, loads: positive, over decades).
    Log10,
}

/// A named scalar with a unit, a prior box and a nominal value.
#[derive(Clone, Copy, Debug, Serialize)]
pub struct ParamSpec {
    /// Name, as in files, CLI arguments and the API.
    pub name: &'static str,
    /// Unit of the value.
    pub unit: &'static str,
    /// How the prior samples it.
    pub scale: Scale,
    /// Lower end of the prior box.
    pub low: f64,
    /// Upper end of the prior box.
    pub high: f64,
    /// Value of the nominal ear.
    pub nominal: f64,
}

impl ParamSpec {
    /// Maps u ∈ [0, 1] onto the prior box (log-uniform for `Log10`).
    pub fn from_unit(&self, u: f64) -> f64 {
        match self.scale {
            Scale::Linear => self.low + u * (self.high - self.low),
            Scale::Log10 => 10f64.powf(self.low.log10() + u * (self.high.log10() - self.low.log10())),
        }
    }

    /// Whether `v` lies in the prior box.
    pub fn contains(&self, v: f64) -> bool {
        v.is_finite() && v >= self.low && v <= self.high
    }
    /// Whether the simulator can run with `v`: finite and positive, or zero for a
    /// parameter whose prior starts at zero (an elastic eardrum, n = 0).
    pub fn physical(&self, v: f64) -> bool {
        v.is_finite() && (v > 0.0 || (v == 0.0 && self.low == 0.0))
    }
}

/// Number of inferred parameters: the tissue parameters, the geometry nuisances, the
/// ear's cavity and eardrum viscoelasticity, then the LDV beam angle and the cochlear
/// fluid mass.
pub const N_PARAMS: usize = 14;

/// Number of measurement-geometry nuisances (after the tissue parameters).
pub const N_GEOMETRY: usize = 3;

/// Number of tissue parameters (the first columns of theta.csv; the only ones read
/// against normal ranges).
pub const N_TISSUE: usize = 7;

/// The inferred parameters, in the column order of theta.csv.
///
/// The last three are nuisances of the measurement, not of the ear, inferred with the
/// tissue so that the tissue posterior is not bent to absorb them: the path
/// from the impedance plane to the eardrum (a WBT probe sits a few mm to ~20 mm from the
/// drum; the temporal-bone study's plane 12–15 mm), the canal cross-section (adult canals
/// 25–70 mm², physics-notes §1.1) and the distance of the V/P microphone from the drum
/// (the study's probe tube ≈ 2 mm lateral of the umbo). The last two were optional effects
/// until v3: a live ear always has a closed middle-ear air volume (tympanum and mastoid,
/// 0.5–20 cm³ behind the drum) and an eardrum whose modulus rises with frequency,
/// E·(jω/ω0)^n with n up to 0.3 (loss tangent tan(nπ/2)), and either, left out, was
/// absorbed by the tissue parameters without the fit check seeing it (docs/simulator.md,
/// "v3"). The LDV beam angle to the stapes piston axis and the cochlear fluid mass were
/// optional effects until v5, for the same reason: no fit check could see them, and
/// normal ears with either at the top of its range read a false finding 11 % and 15 % of
/// the time (`otofit bench fit`, docs/simulator.md "v5").
///
/// The nominal tissue values (v8) are the geometric centres of the published normal ranges
/// (`otofit_npe::npe::normal::NORMAL`, physics-notes §2; a test there keeps the two
/// equal): a typical ear from the literature, not a point fitted to the norms. The nominal
/// viscoelastic exponent is 0: the default drum's loss is its loss factor
/// (`anatomical_drum::LOSS_FACTOR`). The line drum's tuned values are
/// `line_drum::LineTuning::theta`.
pub const PARAMS: [ParamSpec; N_PARAMS] = [
    ParamSpec { name: "E_eardrum", unit: "Pa", scale: Scale::Log10, low: 1e6, high: 300e6, nominal: 20e6 },
    ParamSpec { name: "E_ligaments", unit: "Pa", scale: Scale::Log10, low: 5e4, high: 5e7, nominal: 1.0247e6 },
    ParamSpec { name: "E_tendons", unit: "Pa", scale: Scale::Log10, low: 5e4, high: 5e7, nominal: 1.6125e6 },
    ParamSpec { name: "E_sal", unit: "Pa", scale: Scale::Log10, low: 5e3, high: 1e7, nominal: 3.3166e5 },
    ParamSpec { name: "E_joints", unit: "Pa", scale: Scale::Log10, low: 1e5, high: 1e9, nominal: 1.7550e6 },
    ParamSpec { name: "damping_beta", unit: "s", scale: Scale::Log10, low: 7.5e-6, high: 7.5e-4, nominal: 1.0607e-4 },
    ParamSpec {
        name: "cochlear_load", unit: "Pa·s/m³", scale: Scale::Log10, low: 2e9, high: 2e11, nominal: 2.7111e10
    },
    ParamSpec { name: "canal_length", unit: "m", scale: Scale::Linear, low: 3e-3, high: 25e-3, nominal: 12e-3 },
    ParamSpec { name: "canal_area", unit: "m²", scale: Scale::Linear, low: 25e-6, high: 70e-6, nominal: 44e-6 },
    ParamSpec { name: "mic_distance", unit: "m", scale: Scale::Linear, low: 0.5e-3, high: 4e-3, nominal: 2e-3 },
    // Nominal: the largest volume, within 0.6 noise STD of an opened cavity (a temporal
    // bone, the study's and v2's default) on every feature of the nominal ear.
    ParamSpec { name: "cavity", unit: "m³", scale: Scale::Log10, low: 0.5e-6, high: 20e-6, nominal: 20e-6 },
    ParamSpec { name: "tm_viscoelastic", unit: "1", scale: Scale::Linear, low: 0.0, high: 0.3, nominal: 0.0 },
    // Nominal 0: the beam along the piston axis and a massless cochlear load, the v4 ear.
    ParamSpec { name: "ldv_angle", unit: "deg", scale: Scale::Linear, low: 0.0, high: 60.0, nominal: 0.0 },
    ParamSpec { name: "cochlear_mass", unit: "kg/m⁴", scale: Scale::Linear, low: 0.0, high: 1e6, nominal: 0.0 },
];

/// A row of the tissue values followed by anything (effect columns), with the nominal
/// geometry inserted after the tissue values: the full parameter row.
pub fn with_nominal_geometry(row: &[f64]) -> Vec<f64> {
    let mut full = row[..N_TISSUE].to_vec();
    full.extend(PARAMS[N_TISSUE..].iter().map(|p| p.nominal));
    full.extend_from_slice(&row[N_TISSUE..]);
    full
}

/// Whether a parameter name is one of the simulator's measurement-geometry nuisances.
pub fn is_geometry(name: &str) -> bool {
    PARAMS[N_TISSUE..N_TISSUE + N_GEOMETRY].iter().any(|p| p.name == name)
}

/// One parameter set, in the order of [`PARAMS`].
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Theta(pub [f64; N_PARAMS]);

impl Theta {
    /// Every parameter at its nominal value.
    pub fn nominal() -> Theta {
        Theta(PARAMS.map(|p| p.nominal))
    }
    /// Eardrum Young's modulus, Pa.
    pub fn e_eardrum(&self) -> f64 {
        self.0[0]
    }
    /// Ligaments' Young's modulus, Pa.
    pub fn e_ligaments(&self) -> f64 {
        self.0[1]
    }
    /// Tendons' Young's modulus, Pa.
    pub fn e_tendons(&self) -> f64 {
        self.0[2]
    }
    /// Stapes annular ligament's Young's modulus, Pa.
    pub fn e_sal(&self) -> f64 {
        self.0[3]
    }
    /// Joints' Young's modulus, Pa.
    pub fn e_joints(&self) -> f64 {
        self.0[4]
    }
    /// Rayleigh stiffness-proportional damping β, s.
    pub fn damping_beta(&self) -> f64 {
        self.0[5]
    }
    /// Cochlear input resistance R_c, Pa·s/m³.
    pub fn cochlear_load(&self) -> f64 {
        self.0[6]
    }
    /// Residual canal from the impedance plane to the eardrum, m.
    pub fn canal_length(&self) -> f64 {
        self.0[7]
    }
    /// Canal cross-section at the impedance plane, m².
    pub fn canal_area(&self) -> f64 {
        self.0[8]
    }
    /// V/P microphone, distance lateral of the eardrum, m.
    pub fn mic_distance(&self) -> f64 {
        self.0[9]
    }
    /// Volume of the closed middle-ear air space behind the drum, m³.
    pub fn cavity_volume(&self) -> f64 {
        self.0[10]
    }
    /// Exponent n of the eardrum's power-law viscoelasticity (0: elastic).
    pub fn tm_exponent(&self) -> f64 {
        self.0[11]
    }
    /// Angle of the LDV beam to the stapes piston axis, degrees: the measured stapes
    /// velocity is v_piston·cos θ + rocking·sin θ.
    pub fn ldv_angle_deg(&self) -> f64 {
        self.0[12]
    }
    /// Cochlear fluid mass M_c, kg/m⁴: Z_c = R_c + jωM_c.
    pub fn cochlear_mass(&self) -> f64 {
        self.0[13]
    }
    /// The tissue parameters with nominal geometry (`simulate --theta` with seven columns).
    pub fn from_tissue(tissue: &[f64; N_TISSUE]) -> Theta {
        let mut t = Theta::nominal();
        t.0[..N_TISSUE].copy_from_slice(tissue);
        t
    }
}

/// An optional physical effect: one parameter, an "off" value, and a range.
#[derive(Clone, Copy, Debug, Serialize)]
pub struct EffectSpec {
    /// Name, as in files, CLI arguments and the API.
    pub name: &'static str,
    /// Unit of the value.
    pub unit: &'static str,
    /// The value that switches the effect off.
    pub off: f64,
    /// Lower end of the range.
    pub low: f64,
    /// Upper end of the range.
    pub high: f64,
    /// How a prior that varies the effect samples it.
    pub scale: Scale,
    /// What the effect models.
    pub description: &'static str,
}

impl EffectSpec {
    /// Accepts the off value or a value inside [low, high].
    pub fn accepts(&self, v: f64) -> bool {
        v == self.off || (v.is_finite() && v >= self.low && v <= self.high)
    }
    /// The effect as a parameter whose prior box is its range (nominal: the middle).
    pub fn as_param(&self) -> ParamSpec {
        ParamSpec {
            name: self.name,
            unit: self.unit,
            scale: self.scale,
            low: self.low,
            high: self.high,
            nominal: self.from_unit(0.5),
        }
    }
    /// Maps u ∈ [0, 1] onto the range, as [`ParamSpec::from_unit`].
    pub fn from_unit(&self, u: f64) -> f64 {
        ParamSpec { name: self.name, unit: self.unit, scale: self.scale, low: self.low, high: self.high, nominal: 0.0 }
            .from_unit(u)
    }
}

/// Number of optional effects.
pub const N_EFFECTS: usize = 9;

/// The effect library, in a fixed order (physics-notes §4 for forms and signatures).
pub const EFFECTS: [EffectSpec; N_EFFECTS] = [
    EffectSpec {
        name: "probe_offset",
        unit: "m",
        off: 0.0,
        low: -3e-3,
        high: 3e-3,
        scale: Scale::Linear,
        description: "impedance measurement plane moved toward the eardrum by Δx",
    },
    EffectSpec {
        name: "probe_leak",
        unit: "m",
        off: 0.0,
        low: 0.05e-3,
        high: 0.5e-3,
        scale: Scale::Log10,
        description: "leak of radius a (length 5 mm) shunting the probe",
    },
    // A third window (superior canal dehiscence): the perilymph the stapes displaces
    // escapes through the dehiscence as well as through the cochlear partition, an
    // acoustic mass in parallel with the cochlear load (the shunt of Songer & Rosowski
    // 2007, JASA 122:943; lossless here, its limiting form). The range is ρL/A for
    // perilymph (1000 kg/m³) through dehiscences of 0.5–5 mm² and 1–3 mm of canal lumen
    // (2e5–6e6 kg/m⁴). Signature: the cochlear input impedance falls at low frequency,
    // so low-frequency stapes and umbo velocity rise (Rosowski et al. 2004, Otol Neurotol
    // 25:323), with little change above 1–2 kHz.
    EffectSpec {
        name: "third_window",
        unit: "kg/m⁴",
        off: 0.0,
        low: 2e5,
        high: 6e6,
        scale: Scale::Log10,
        description: "a third window (superior canal dehiscence): an inner-ear shunt of acoustic mass M in parallel with the cochlear load",
    },
    // A perforation of the pars tensa: air flows from the canal through the hole into the
    // middle-ear cavity beside the drum, an acoustic mass and resistance in a path from
    // p_drum to p_cavity (Voss et al. 2001, JASA 110:1432; `model::perforation_impedance`).
    // Radii 0.25–2.5 mm: the 0.5–5 mm diameters of Voss et al.'s temporal bones.
    // Signature: the pressure difference across the drum falls at low frequency, so
    // low-frequency velocities fall and the low-frequency impedance drops, with the
    // perforation's mass resonating with the cavity's compliance.
    EffectSpec {
        name: "perforation",
        unit: "m",
        off: 0.0,
        low: 0.25e-3,
        high: 2.5e-3,
        scale: Scale::Log10,
        description: "a perforation of radius a in the pars tensa: a path from the canal into the middle-ear cavity",
    },
    // Fluid in the middle ear (otitis media with effusion): the fraction φ of the air space
    // filled, the air left v(1 − φ) and the fluid's mass on the drum
    // (`ear_effects::cavity_coefficients`). Ravicz, Rosowski & Merchant 2004 (Hear Res
    // 195:103) filled temporal bones from a few per cent to full: below 1 kHz the loss
    // (up to 25 dB in umbo velocity) follows the air left, above it (up to 35 dB) the
    // drum's area in contact with fluid. 0.05–0.95: a trace to all but a bubble (a full
    // ear has no air compliance left, a limit this lumped form does not reach).
    EffectSpec {
        name: "effusion",
        unit: "1",
        off: 0.0,
        low: 0.05,
        high: 0.95,
        scale: Scale::Linear,
        description: "fluid filling the fraction φ of the middle-ear air space: less air, and the fluid's mass on the drum; umbo and stapes velocity fall most above 1 kHz, absorbance falls",
    },
    // A static pressure in the middle ear below (or above) the canal's, e.g. from a blocked
    // Eustachian tube; the value is p_middle_ear − p_canal (a tympanogram's peak pressure
    // when the canal is at ambient pressure). The drum and the chain's suspension stiffen
    // by (2ΔP/TW)² without loss (`ear_effects::pressure_stiffening`); the model is even in
    // ΔP, so only underpressure, the clinical case, is in the range: −300 to −10 daPa
    // (Voss et al. 2012, Ear Hear 33:195, measured ±300 daPa).
    EffectSpec {
        name: "pressure",
        unit: "Pa",
        off: 0.0,
        low: -3000.0,
        high: -100.0,
        scale: Scale::Linear,
        description: "static middle-ear pressure relative to the canal (negative: underpressure): a stiffer drum and chain; absorbance and velocities fall below 1–2 kHz",
    },
    // A mastoid air-cell network behind the aditus ad antrum: the fraction f of the
    // middle-ear air volume lies behind the aditus' mass and resistance, the rest in the
    // tympanum (`ear_effects::mastoid_admittance`, Hudde & Engel 1998's adult network;
    // Stepp & Voss 2005, JASA 118:861). The total volume, and so the low-frequency
    // compliance, stays the inferred `cavity`; what the base cannot make is the aditus'
    // antiresonance with the tympanic air, a narrow notch in absorbance and velocity at
    // 1–3.5 kHz (Voss et al. 2000, Hear Res 150:43). 0.5–0.97: a tympanum of 0.5–1 cm³
    // beside mastoids of 1 to over 20 cm³ (Hudde & Engel: 0.5 and 8.8 cm³, f = 0.95).
    EffectSpec {
        name: "mastoid",
        unit: "1",
        off: 0.0,
        low: 0.5,
        high: 0.97,
        scale: Scale::Linear,
        description: "a mastoid air-cell network holding the fraction f of the middle-ear air behind the aditus: a notch in absorbance and velocities at the aditus' antiresonance (1–3.5 kHz)",
    },
    // An interrupted incudostapedial joint (an eroded lenticular process, a fibrous
    // union): the joint's spring and its Rayleigh dashpot scaled by s ≪ 1, the incudomallear
    // joint unchanged (physics-notes §4, the form of Nakajima et al. 2012, Ear Hear 33:35).
    // 1e-6 (a gap: no joint left) to 0.1 (a loose fibrous joint); off = 1.
    EffectSpec {
        name: "isj_discontinuity",
        unit: "1",
        off: 1.0,
        low: 1e-6,
        high: 0.1,
        scale: Scale::Log10,
        description: "incudostapedial joint stiffness scaled by s: stapes velocity falls across the band, the unloaded drum moves more (an absorbance peak near 0.5–1 kHz)",
    },
    // A fixed malleus: the head bound to the attic wall by fibrous tissue, a bony bar or
    // neo-osteogenesis (Nakajima et al. 2005, Laryngoscope 115:147), a lossless stiffness k
    // spread over the head, 0.6–2.5 mm above the rotation axis: a spring at the head's
    // centre and a torsion spring (`ear_effects::malleus_head_fixation`). The anterior
    // mallear and posterior incudal ligaments lie on the axis, so no value of E_ligaments
    // makes it. The range's low end, 1e3 N/m, is about three times the anterior mallear
    // ligament's own spring (370 N/m at the nominal E_ligaments) and costs about 1 dB; its
    // high end, 1e7 N/m, is the axial spring EA/L of a bar of bone (E ≈ 17 GPa; Reilly &
    // Burstein 1975, J Biomech 8:393) 0.6 mm² across and 1 mm long, and costs 39 dB. So
    // the range spans Nakajima et al.'s grades of stapes-velocity loss: fibrous tissue
    // around the head under 10 dB, a bony bar 10–30 dB, extensive neo-osteogenesis over
    // 35 dB. Signature: umbo and stapes velocity fall together below 2 kHz, where a stapes
    // fixation lowers the stapes' and leaves the umbo's (Nakajima et al. 2005, Hear Res
    // 204:60; Rosowski et al. 2003, Otol Neurotol 24:165).
    EffectSpec {
        name: "malleus_fixation",
        unit: "N/m",
        off: 0.0,
        low: 1e3,
        high: 1e7,
        scale: Scale::Log10,
        description: "the malleus head bound to the attic wall with stiffness k: umbo and stapes velocity fall together below 2 kHz, absorbance falls a little",
    },
];

/// Why an effect could not be set: each variant names the effect.
#[derive(Clone, Debug, PartialEq, thiserror::Error)]
pub enum EffectError {
    /// No effect has this name.
    #[error("unknown effect '{name}' (known: {known})")]
    Unknown {
        /// The name given.
        name: String,
        /// The effects' names, comma-separated.
        known: String,
    },
    /// The value is outside the effect's range (or not a number).
    #[error("effect '{name}' = {value} is outside its range [{low}, {high}] {unit} (off = {off})")]
    OutOfRange {
        /// The effect.
        name: &'static str,
        /// The value given.
        value: f64,
        /// The range's lower end.
        low: f64,
        /// The range's upper end.
        high: f64,
        /// The effect's unit.
        unit: &'static str,
        /// The value that switches the effect off.
        off: f64,
    },
}

/// Values of the optional effects, in the order of [`EFFECTS`]; all off by default.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Effects(pub [f64; N_EFFECTS]);

impl Default for Effects {
    fn default() -> Self {
        Effects(EFFECTS.map(|e| e.off))
    }
}

impl Effects {
    /// Index of the effect called `name` in [`EFFECTS`].
    pub fn index(name: &str) -> Option<usize> {
        EFFECTS.iter().position(|e| e.name == name)
    }
    /// Sets one effect by name, checking the value against its range.
    pub fn set(&mut self, name: &str, value: f64) -> Result<(), EffectError> {
        let i = Self::index(name).ok_or_else(|| {
            let known: Vec<_> = EFFECTS.iter().map(|e| e.name).collect();
            EffectError::Unknown { name: name.to_string(), known: known.join(", ") }
        })?;
        let spec = &EFFECTS[i];
        if !spec.accepts(value) {
            return Err(EffectError::OutOfRange {
                name: spec.name,
                value,
                low: spec.low,
                high: spec.high,
                unit: spec.unit,
                off: spec.off,
            });
        }
        self.0[i] = value;
        Ok(())
    }
    /// How far the impedance plane moves toward the eardrum, m.
    pub fn probe_offset(&self) -> f64 {
        self.0[0]
    }
    /// Radius of a leak shunting the probe, m.
    pub fn leak_radius(&self) -> f64 {
        self.0[1]
    }
    /// Acoustic mass of a third-window shunt beside the cochlea, kg/m⁴ (0: none).
    pub fn third_window_mass(&self) -> f64 {
        self.0[2]
    }
    /// Radius of a perforation of the pars tensa, m (0: none).
    pub fn perforation_radius(&self) -> f64 {
        self.0[3]
    }
    /// Fraction of the middle-ear air space filled with fluid (0: none).
    pub fn effusion_fill(&self) -> f64 {
        self.0[4]
    }
    /// Static pressure of the middle ear relative to the canal, Pa (0: none).
    pub fn static_pressure(&self) -> f64 {
        self.0[5]
    }
    /// Fraction of the middle-ear air behind the aditus, in the mastoid (0: no mastoid).
    pub fn mastoid_fraction(&self) -> f64 {
        self.0[6]
    }
    /// Factor on the incudostapedial joint's stiffness (1: intact).
    pub fn isj_factor(&self) -> f64 {
        self.0[7]
    }
    /// Stiffness of the malleus head's fixation to the attic wall, N/m (0: none).
    pub fn malleus_fixation(&self) -> f64 {
        self.0[8]
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn nominal_inside_prior_and_bounds_ordered() {
        for p in PARAMS {
            assert!(p.low < p.high && p.contains(p.nominal), "{}", p.name);
            assert!((p.from_unit(0.0) - p.low).abs() <= 1e-9 * p.low);
            assert!((p.from_unit(1.0) - p.high).abs() <= 1e-9 * p.high);
        }
    }

    #[test]
    fn effects_reject_out_of_range_and_unknown() {
        let mut e = Effects::default();
        assert!(e.set("probe_leak", 0.2e-3).is_ok());
        assert!(e.set("probe_leak", 0.0).is_ok());
        assert!(e.set("probe_leak", 1.0).unwrap_err().to_string().contains("outside its range"));
        assert!(e.set("cavity", 2e-6).unwrap_err().to_string().contains("unknown effect 'cavity'"));
        assert!(e.set("probe_offset", f64::NAN).is_err());
        assert!(e.set("ldv_angle", 10.0).unwrap_err().to_string().contains("unknown effect 'ldv_angle'"));
        assert!(e.set("wax", 1.0).unwrap_err().to_string().contains("unknown effect 'wax'"));
    }

    #[test]
    fn effect_errors_name_the_effect() {
        let mut e = Effects::default();
        let unknown = e.set("wax", 1.0).unwrap_err();
        assert!(matches!(&unknown, EffectError::Unknown { name, .. } if name == "wax"), "{unknown:?}");
        assert!(unknown.to_string().contains("'wax'") && unknown.to_string().contains("probe_leak"), "{unknown}");
        let range = e.set("probe_leak", 1.0).unwrap_err();
        assert!(matches!(range, EffectError::OutOfRange { name: "probe_leak", value: 1.0, .. }), "{range:?}");
        assert!(range.to_string().contains("'probe_leak' = 1"), "{range}");
    }
}
