//! The physics of the optional effects that change the middle ear's own coefficients:
//! fluid in the middle ear, a static pressure across the drum, a mastoid air-cell network
//! behind the aditus, an interrupted incudostapedial joint, a fixed malleus
//! (`params::EFFECTS`). The
//! perforation and the third window live beside the terms they change in `model.rs`.
//!
//! The cavity row of the system reads c_row·(V_drum + U_hole/jω) − c_diag·p_cav = 0, so
//! p_cav = Z·U with jωZ = c_row/c_diag for whatever enters the air spaces. The condensed
//! drums take c_row as a real number (their swept volume's weight in that row), so every
//! effect that makes Z other than a compliance either keeps c_row real (fluid: a mass in
//! series with the air, jωZ = ρc²/V_air − ω²M_f) or leaves c_row = ρc²/V and puts the
//! rest into c_diag (the mastoid branch, a lossy admittance in parallel).

use super::air::Air;
use super::anatomical_drum::{RADIUS_X, RADIUS_Y};
use super::params::Effects;
use faer::c64;
use std::f64::consts::PI;

/// Density of a middle-ear effusion, kg/m³: serous effusion is mostly water, and Ravicz
/// et al. 2004 (Hear Res 195:103) used saline (1000–1010 kg/m³).
pub const FLUID_DENSITY: f64 = 1000.0;

/// Depth of fluid the drum moves, m: the air gap between the umbo and the promontory, about
/// 2 mm in adults (the mesotympanum's narrowest depth; Gulya & Schuknecht, Anatomy of the
/// Temporal Bone, 1995). The fluid behind the drum is confined there, so it moves with the
/// drum over that depth.
pub const FLUID_DEPTH: f64 = 2.0e-3;

/// Acoustic mass of the effusion entrained by the drum, kg/m⁴, for a middle ear whose air
/// space is filled to the fraction `fill`. Ravicz et al. 2004 found that above 1 kHz the
/// loss grows with the fraction of the drum's area the fluid touches ("an increase in TM
/// mass by entrained fluid"); taking that fraction equal to the fill (the fluid level
/// rises across the drum as the space fills), a layer of depth d over the contacted area
/// cA moving with the volume velocity cU stores the kinetic energy ½ρd(cU)²/(cA), the
/// energy of an acoustic mass ρ·d·c/A driven by the drum's whole flow U. A is the pars
/// tensa's projected area (the anatomical drum's ellipse).
pub fn effusion_mass(fill: f64) -> f64 {
    FLUID_DENSITY * FLUID_DEPTH * fill / (PI * RADIUS_X * RADIUS_Y)
}

/// Tympanometric width of normal adult ears, Pa: the pressure interval over which the
/// compensated 226 Hz admittance stays above half its peak, 51–114 daPa over the central
/// 90 % of adults (Margolis & Heller 1987, Audiology 26:197; ASHA 1990 interim norms). 75
/// daPa is inside that range, near its middle; it was not chosen to fit any measure here.
pub const TYMPANOMETRIC_WIDTH: f64 = 750.0;

/// Extra stiffness, as a multiple of the unloaded stiffness, of the drum and the chain's
/// suspension under a static pressure difference `dp` (Pa) across the drum. A tympanogram
/// is the ear's low-frequency admittance against that difference: a peak at zero whose
/// half-height width is the tympanometric width TW. The simplest even peak with that
/// width, 1/(1 + (2ΔP/TW)²), read as stiffness, multiplies it by 1 + (2ΔP/TW)²: ×5 at
/// ±75 daPa, ×65 at ±300 daPa, where tympanograms are flat. The added part is the
/// stiffness of the static pre-stress (the geometric stiffness of a loaded membrane), set
/// by the load and not by the tissue's loss modulus, so it is added without loss: the
/// drum's loss factor falls as it stiffens, which a stiffer E_eardrum cannot mimic.
/// Measured signature (Voss et al. 2012, Ear Hear 33:195, cadaver ears at ±300 daPa;
/// Margolis, Saly & Keefe 1999, JASA 106:265): reflectance rises below 1–2 kHz and falls
/// near its minimum.
pub fn pressure_stiffening(dp: f64) -> f64 {
    (2.0 * dp / TYMPANOMETRIC_WIDTH).powi(2)
}

/// Acoustic mass of the aditus ad antrum, kg/m⁴ (Hudde & Engel 1998, Acustica 84:720,
/// adult values as coded in Sankowsky-Rothe's middleEarCavitiesInfant.m; physics-notes §4).
pub const ADITUS_MASS: f64 = 880.0;
/// Resistance of the aditus, Pa·s/m³ (same source).
pub const ADITUS_RESISTANCE: f64 = 1.7e6;
/// Resonance of the mastoid air cells, Hz (same source): the cells are many small
/// cavities behind narrow necks, not one compliance.
pub const MASTOID_CELL_RESONANCE: f64 = 3500.0;
/// Quality factor of that resonance (same source).
pub const MASTOID_CELL_Q: f64 = 0.4;

/// Admittance of the antrum and mastoid air cells as seen through the aditus, m³/(Pa·s):
/// the aditus' mass and resistance in series with the cells' compliance N = V/(ρc²) and
/// their own lossy resonance, Y_mac = jωN / (1 − (ω/ω_m)² + jω/(Q ω_m)) (Hudde & Engel's
/// form; the antrum's volume is folded into `volume`). Passive: every series term has a
/// non-negative real part.
pub fn mastoid_admittance(air: &Air, volume: f64, w: f64) -> c64 {
    let jw = c64::new(0.0, w);
    let wm = 2.0 * PI * MASTOID_CELL_RESONANCE;
    let x = w / wm;
    let y_cells = jw * (volume / air.bulk_modulus()) / c64::new(1.0 - x * x, x / MASTOID_CELL_Q);
    1.0 / (c64::new(ADITUS_RESISTANCE, w * ADITUS_MASS) + 1.0 / y_cells)
}

/// The cavity row's coefficients (c_row, c_diag) at angular frequency `w` for a middle-ear
/// air volume `v` (the inferred `cavity`) and the effects: (ρc²/v, 1) with none of them.
///
/// With fluid filling the fraction φ of the air space, the air left is v(1 − φ) and the
/// fluid's mass M_f sits between the drum and that air. With a mastoid, the fraction f of
/// the air lies behind the aditus: the tympanic air (1 − f)·v(1 − φ) in parallel with the
/// mastoid branch. The low-frequency compliance is the whole air's, so `cavity` keeps its
/// meaning; what the base cannot make is the aditus' resonance with the tympanic air.
pub fn cavity_coefficients(air: &Air, v: f64, fx: &Effects, w: f64) -> (f64, c64) {
    let k = air.bulk_modulus();
    let (fill, behind) = (fx.effusion_fill(), fx.mastoid_fraction());
    if fill == 0.0 && behind == 0.0 {
        return (k / v, c64::new(1.0, 0.0));
    }
    let v_air = v * (1.0 - fill);
    let m_f = effusion_mass(fill);
    if behind == 0.0 {
        return (k / v_air - w * w * m_f, c64::new(1.0, 0.0));
    }
    let jw = c64::new(0.0, w);
    let y_air = jw * ((1.0 - behind) * v_air / k) + mastoid_admittance(air, behind * v_air, w);
    let z = jw * m_f + 1.0 / y_air;
    (k / v, (k / v) / (jw * z))
}

/// Length of the adult malleus from the top of its head to the tip of the manubrium (the
/// umbo), m: 8.08 mm mean (Binvignat et al. 2015, Int J Morphol 33:914); other series give
/// 7.2–8.1 mm (Mudhol et al. 2022, J Anat Soc India 71:88; Noussios et al. 2016, J Clin
/// Med Res 8:76, a meta-analysis).
pub const MALLEUS_LENGTH: f64 = 8.0e-3;

/// Height of the malleus head along the bone, m: the head is about as tall as it is wide,
/// and its greatest width is 1.86–1.94 mm (Vedpathak et al. 2020, Int J Sci Res 9(7), CT of
/// 114 adults).
pub const MALLEUS_HEAD_HEIGHT: f64 = 1.9e-3;

/// Where a fixation of the malleus head holds the malleus, for an umbo `arm_umbo` below the
/// rotation axis: (the arm of the head's centre, m, negative above the axis as
/// `Geometry::arm_imj`; the torsion per unit stiffness, m²).
///
/// A fixation binds the head to the attic wall over the head (fibrous tissue, a bony bar
/// to the epitympanic wall, neo-osteogenesis around the head; Nakajima et al. 2005,
/// Laryngoscope 115:147). The head's top lies the malleus' length above the umbo, so
/// 8.0 − 5.5 = 2.5 mm above the axis for the default chain, and the head spans
/// [`MALLEUS_HEAD_HEIGHT`] below it. A stiffness k spread evenly over that span, each point
/// pulled back along z in proportion to its own displacement u + (l − l_u)·θ, stores
/// ½k·mean(u_l²) = ½k·u_c² + ½(k·h²/12)·θ²: a spring k at the head's centre and a torsion
/// spring k·h²/12. Held at one point only, the malleus would turn about the head as freely
/// as its ligaments let its axis move (a point spring of any stiffness lowers the nominal
/// ear's 250–500 Hz umbo velocity by under 3 dB); spread over the head, a stiff fixation
/// stops the malleus, as a bony fixation does.
pub fn malleus_head_fixation(arm_umbo: f64) -> (f64, f64) {
    let top = MALLEUS_LENGTH - arm_umbo;
    (-(top - MALLEUS_HEAD_HEIGHT / 2.0), MALLEUS_HEAD_HEIGHT * MALLEUS_HEAD_HEIGHT / 12.0)
}
