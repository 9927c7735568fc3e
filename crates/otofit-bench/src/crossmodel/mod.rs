//! Cross-model suite: ears made by published middle-ear models that otofit does not
//! contain, read by otofit's shipped posterior exactly as `otofit infer` and `POST /infer`
//! read a measurement (posterior samples, MAP, fit check, normal-range differential).
//!
//! A posterior trained on one simulator can be confidently wrong on ears another model
//! makes, and the fit check is the only guard against it. This module measures how often
//! that guard holds: per model × condition, the fit check's pass rate, the rate of the
//! reading the condition should give, and the rate of confident (P ≥ 0.95) readings that
//! name another structure while the fit check passes.
//!
//! Parts:
//! - [`kringlebotn`]: Kringlebotn's (1988) network, the lumped model most later circuit
//!   models start from;
//! - [`hudde_engel`]: Hudde & Engel's (1998) acousto-mechanical model, fitted to their
//!   own measurements with a frequency-dependent effective eardrum area;
//! - [`canal`]: the residual canal between the probe and the drum (transfer matrix);
//! - [`run`]: noisy ears, inference, scores, table and JSON.
//!
//! Each model gives, per frequency, the impedance at the eardrum and the umbo and stapes
//! velocities per pascal at the drum ([`DrumResponse`]); [`features`] carries them through
//! the canal into otofit's 350-feature layout (`otofit_sim::output::features`: log10
//! magnitudes, phases unwrapped along frequency, absorbance as a fraction, velocities
//! over the pressure at the V/P microphone).

pub mod canal;
pub mod hudde_engel;
pub mod kringlebotn;
pub mod misfits;
pub mod run;

use faer::c64;
use otofit_sim::air::Air;
use otofit_sim::{PARAMS, Response};
use serde::Serialize;

/// What a middle-ear model gives at one frequency, referred to the pressure on the drum
/// (time convention e^{+jωt}, velocities positive medially).
#[derive(Clone, Copy, Debug)]
pub struct DrumResponse {
    /// Acoustic input impedance at the eardrum, Pa·s/m³.
    pub z_drum: c64,
    /// Stapes (piston) velocity over the pressure at the drum, m/s/Pa.
    pub v_stapes: c64,
    /// Umbo velocity over the pressure at the drum, m/s/Pa.
    pub v_umbo: c64,
}

/// A middle-ear model: the drum's impedance and the ossicles' velocities per frequency.
pub trait EarModel {
    /// The model at `freq_hz`.
    fn at(&self, freq_hz: f64) -> DrumResponse;
}

/// The ear conditions the suite makes. Effusion is not among them: neither model has
/// it (Sankowsky-Rothe et al. 2022 model fluid in their infant structure, and their code
/// refuses it for Hudde & Engel's: applied anyway, the empirical phase terms make the
/// drum active, absorbance below 0 near 3 kHz).
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize)]
#[serde(rename_all = "snake_case")]
pub enum Condition {
    /// The published model as it stands.
    Healthy,
    /// Otosclerosis: the annular ligament 10–100× stiffer.
    StapesFixation,
    /// Malleus fixation: the malleus suspension 100× stiffer.
    MalleusFixation,
    /// Incudostapedial joint broken: a soft-tissue remnant joins incus and stapes.
    Discontinuity,
}

/// Every condition, in table order.
pub const CONDITIONS: [Condition; 4] =
    [Condition::Healthy, Condition::StapesFixation, Condition::MalleusFixation, Condition::Discontinuity];

impl Condition {
    /// Name as in the table and the JSON.
    pub fn name(self) -> &'static str {
        match self {
            Condition::Healthy => "healthy",
            Condition::StapesFixation => "stapes_fixation",
            Condition::MalleusFixation => "malleus_fixation",
            Condition::Discontinuity => "discontinuity",
        }
    }

    /// The readings (tissue parameter, direction) that name this condition in otofit's
    /// differential (`otofit_npe::npe::normal::NORMAL`'s `below` / `above` texts): any one
    /// of them is the right answer, and no finding at all is the right answer for a
    /// healthy ear. Malleus fixation stiffens the malleus' suspension, which otofit splits
    /// into ligaments and tendons (tensor tympani), so either reads as right, as does the
    /// differential's effect hypothesis `malleus_fixation present` (the head fixed).
    pub fn expected(self) -> &'static [(&'static str, &'static str)] {
        match self {
            Condition::Healthy => &[],
            Condition::StapesFixation => &[("E_sal", "above")],
            Condition::MalleusFixation => {
                &[("E_ligaments", "above"), ("E_tendons", "above"), ("malleus_fixation", "present")]
            }
            Condition::Discontinuity => &[("E_joints", "below")],
        }
    }
}

/// Where the probe and the microphone sit in the canal: otofit's nominal measurement
/// geometry (`otofit_sim::params::PARAMS`: canal_length, canal_area, mic_distance).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Geometry {
    /// Residual canal from the impedance plane to the drum, m.
    pub canal_length: f64,
    /// Canal cross-section, m².
    pub canal_area: f64,
    /// V/P microphone, distance lateral of the drum, m.
    pub mic_distance: f64,
}

impl Geometry {
    /// otofit's nominal geometry (12 mm, 44 mm², 2 mm).
    pub fn nominal() -> Geometry {
        let nominal = |name: &str| PARAMS.iter().find(|p| p.name == name).map_or(f64::NAN, |p| p.nominal);
        Geometry {
            canal_length: nominal("canal_length"),
            canal_area: nominal("canal_area"),
            mic_distance: nominal("mic_distance"),
        }
    }
}

/// The model's responses at the probe on `freqs`: the drum's impedance moved through the
/// residual canal to the impedance plane, and the velocities re-referred from the drum's
/// pressure to the microphone's, as otofit's simulator reports them
/// (`otofit_sim::Runner::response_at`).
pub fn responses(model: &dyn EarModel, geometry: &Geometry, air: &Air, freqs: &[f64]) -> Vec<Response> {
    freqs
        .iter()
        .map(|&f| {
            let d = model.at(f);
            let tube = canal::Tube::new(air, 2.0 * std::f64::consts::PI * f, geometry.canal_area);
            let zec = tube.input_impedance(geometry.canal_length, d.z_drum);
            let p_mic = tube.pressure_ratio(geometry.mic_distance, d.z_drum);
            Response {
                freq_hz: f,
                vst_over_p: d.v_stapes / p_mic,
                vu_over_p: d.v_umbo / p_mic,
                zec,
                z0: air.z0(geometry.canal_area),
            }
        })
        .collect()
}

/// The model's noise-free feature vector in otofit's layout on `freqs`.
pub fn features(model: &dyn EarModel, geometry: &Geometry, air: &Air, freqs: &[f64]) -> Vec<f64> {
    otofit_sim::output::features(&responses(model, geometry, air, freqs))
}

/// The impedance of elements in series.
pub(crate) fn series(z: &[c64]) -> c64 {
    z.iter().fold(c64::new(0.0, 0.0), |a, &b| a + b)
}

/// The impedance of elements in parallel.
pub(crate) fn parallel(z: &[c64]) -> c64 {
    let one = c64::new(1.0, 0.0);
    one / z.iter().fold(c64::new(0.0, 0.0), |a, &b| a + one / b)
}

/// Impedance of a mass (or inertance) `m` at angular frequency `w`.
pub(crate) fn mass(w: f64, m: f64) -> c64 {
    c64::new(0.0, w * m)
}

/// Impedance of a compliance `c` at angular frequency `w` (0 for an infinite compliance).
pub(crate) fn compliance(w: f64, c: f64) -> c64 {
    if c.is_infinite() { c64::new(0.0, 0.0) } else { c64::new(0.0, -1.0 / (w * c)) }
}

/// Impedance of a resistance `r`.
pub(crate) fn resistance(r: f64) -> c64 {
    c64::new(r, 0.0)
}

/// The air otofit's shipped model was trained with (the temporal-bone preset, 22 °C).
pub fn training_air() -> Air {
    otofit_sim::Preset::TemporalBone.air()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn nominal_geometry_is_otofits() {
        let g = Geometry::nominal();
        assert_eq!((g.canal_length, g.canal_area, g.mic_distance), (12e-3, 44e-6, 2e-3));
    }

    #[test]
    fn every_expected_reading_names_a_tissue_parameter_or_an_effect_hypothesis() {
        use otofit_discrepancy::discrepancy::alternatives::EFFECT_HYPOTHESES;
        let names: Vec<&str> = otofit_npe::npe::normal::NORMAL.iter().map(|r| r.name).collect();
        for c in CONDITIONS {
            for (p, dir) in c.expected() {
                let tissue = names.contains(p) && matches!(*dir, "below" | "above");
                let effect = EFFECT_HYPOTHESES.iter().any(|h| h.effect == *p) && *dir == "present";
                assert!(tissue || effect, "{}: {p} {dir}", c.name());
            }
        }
    }
}
