//! The coupled middle-ear model: eardrum shell FE + rigid ossicles with connector
//! springs, one sparse complex system per frequency, driven by a unit volume velocity
//! into the eardrum; then the residual canal as a uniform viscothermal line whose length
//! and area are per-run parameters (the measurement geometry).
//!
//! Unknowns: the pressure on the eardrum; eardrum node DOFs (u_r, u_z, β) except the
//! clamped rim and the rigid umbo disc (condensed through the drum's modes by default);
//! ossicle DOFs [w_umbo, θ_malleus, x_incus, θ_incus, x_stapes, φ_stapes]; the
//! middle-ear cavity pressure. The disc's axial motion is the umbo's, which is the
//! malleus point at the umbo arm (w_umbo = x_malleus + l_u θ_m). z points medially;
//! positive canal pressure pushes the drum toward +z.
//!
//! Why the canal is a line and not FE (v2): the middle ear sees the canal only through
//! the pressure on the drum and the volume velocity into it, so one solve per frequency
//! gives Z_tm and every velocity per unit flow; the canal's exact transfer matrix
//! (cosh ΓL, Z_c sinh ΓL; …) then maps them to the impedance plane and the microphone for
//! any length and area at the cost of a few complex numbers. The FE canal
//! (`canal.rs`) converges to the same line (tests/it/physics.rs) and stays the
//! verification of it and the path to non-uniform canals.

use super::air::{self, Air};
use super::anatomical_drum::{self, AnatomicalCondensed, AnatomicalDrum};
use super::drum::{DrumCoefficients, DrumError, DrumModes};
use super::drum_mesh::{DrumGeometry, ManubriumModes};
use super::ear_effects;
use super::line_drum::{LineDrum, LineTuning, simpson};
use super::memo::{DrumMemo, Memo, Solved};
use super::params::{Effects, Theta};
use super::shell::{ShellElement, ShellMaterial, cone_nodes};
use super::system::{SolveError, System, SystemBuilder, Workspace};
use faer::c64;
use std::f64::consts::PI;

/// Geometry and fixed material data. Every number is from physics-notes §1 unless the
/// comment says it was chosen; `g_*` are the fixed geometric factors of k = E·g.
///
/// Baseline fit (docs/simulator.md): with a straight 80 µm cone the nominal drum was
/// 2–3× too stiff (|Z|₂₅₀ 1.6e8, vst −42 dB at 1 kHz). Within the published ranges we
/// chose a 0.3 mm lateral bulge of the generator (the curved radial fibres), 60 µm
/// thickness (range 40–120 µm), a 0.5 mm umbo disc (0.5–1 mm) and the 15 mm residual
/// canal (12–15 mm). tests/it/baseline.rs checks the result against tests/data.
/// The canal's length and area and the microphone distance are not here: they are
/// per-run parameters (`params::PARAMS`, nominal 12 mm, 44 mm², 2 mm).
#[derive(Clone, Debug)]
pub struct Geometry {
    /// Eardrum radius, m.
    pub tm_radius: f64,
    /// Eardrum cone depth, m.
    pub tm_depth: f64,
    /// Lateral bulge of the generator's midpoint from the straight cone, m.
    pub tm_bulge: f64,
    /// Eardrum thickness, m.
    pub tm_thickness: f64,
    /// Eardrum density, kg/m³.
    pub tm_rho: f64,
    /// Eardrum Poisson ratio.
    pub tm_nu: f64,
    /// How the eardrum dissipates (see [`DrumLoss`]).
    pub tm_loss: DrumLoss,
    /// Which eardrum FE (see [`DrumShape`]).
    pub tm_shape: DrumShape,
    /// Axisymmetric drum only: radius of the rigid disc tied to the umbo, m.
    pub disc_radius: f64,
    /// Axisymmetric drum only: shell elements from the disc to the rim.
    pub tm_elements: usize,
    /// Malleus mass, kg (notes §1.3).
    pub m_malleus: f64,
    /// Malleus inertia about the rotation axis, kg·m².
    pub i_malleus: f64,
    /// Incus mass, kg.
    pub m_incus: f64,
    /// Incus inertia about the rotation axis, kg·m².
    pub i_incus: f64,
    /// Stapes mass, kg.
    pub m_stapes: f64,
    /// Stapes inertia for rocking about the footplate centre, kg·m².
    pub i_stapes: f64,
    /// Umbo arm from the rotation axis, m.
    pub arm_umbo: f64,
    /// Lenticular process arm from the rotation axis, m.
    pub arm_lp: f64,
    /// IMJ arm from the rotation axis, m (negative = above the axis, on the heads).
    pub arm_imj: f64,
    /// Tensor tympani insertion arm from the rotation axis, m.
    pub arm_ttt: f64,
    /// Stapes head height above the footplate, m.
    pub stapes_height: f64,
    /// Tilt of the stapes axis to the lenticular process' motion, rad (chosen: it
    /// couples rocking to the drive).
    pub stapes_tilt: f64,
    /// Height above the footplate of the LDV spot for the rocking part, m.
    pub ldv_spot: f64,
    /// Footplate area, m².
    pub footplate_area: f64,
    /// Leak channel length, m (notes §4: ℓ = 5 mm).
    pub leak_length: f64,
    /// Geometric factors, m (springs) or m³ (rotational springs), k = E·g: anterior
    /// mallear ligament.
    pub g_aml: f64,
    /// Anterior mallear ligament in torsion.
    pub g_aml_rot: f64,
    /// Posterior incudal ligament.
    pub g_pil: f64,
    /// Posterior incudal ligament in torsion.
    pub g_pil_rot: f64,
    /// Tensor tympani tendon.
    pub g_ttt: f64,
    /// Stapedius tendon.
    pub g_stapedius: f64,
    /// Incudomallear joint.
    pub g_imj: f64,
    /// Incudomallear joint in rotation.
    pub g_imj_rot: f64,
    /// Incudostapedial joint along z.
    pub g_isj: f64,
    /// Incudostapedial joint in shear.
    pub g_isj_shear: f64,
    /// An experiment (docs/simulator.md, "The incus across the stapes
    /// axis"): the incus also translates across the stapes axis (in the rocking plane),
    /// held by the posterior incudal ligament and the incudomallear joint, so the ISJ
    /// shears between two moving bodies. `false` (every model so far): the ISJ's shear
    /// spring holds the stapes head to the ground.
    pub incus_lateral: bool,
    /// The posterior incudal ligament across the stapes axis. The footplate's long axis,
    /// the rocking plane's, runs antero-posteriorly like the ossicular axis the PIL lies
    /// on, so the ligament is loaded along its length: a/l, as along z.
    pub g_pil_lateral: f64,
    /// The incudomallear joint across the stapes axis: its faces slide (shear). The
    /// malleus has no lateral motion in this model, so the joint holds the incus to ground.
    pub g_imj_lateral: f64,
    /// Stapes annular ligament, piston.
    pub g_sal: f64,
    /// Stapes annular ligament, rocking.
    pub g_sal_rock: f64,
}

impl Default for Geometry {
    /// The v8 ear, [`Geometry::anatomical`]: the anatomical FE drum on the chain's cited
    /// masses and ligament geometry, nothing scaled to fit a norm.
    fn default() -> Self {
        Geometry::anatomical()
    }
}

impl Geometry {
    /// The v6–v7 ear (`--drum line`): the axisymmetric ear's chain with the
    /// transmission-line drum of [`LineTuning::v7`], whose loss factor and ossicle-mass
    /// factor were tuned to the norms (docs/simulator.md, "v6" and "v7"). Kept for
    /// comparison; its tuned tissue values are [`LineTuning::theta`].
    pub fn line() -> Geometry {
        let mut g = Geometry::axisymmetric();
        LineTuning::v7().apply(&mut g);
        g
    }

    /// The anatomical ear, the default since v8: [`AnatomicalDrum::default`] with its
    /// frequency-independent loss factor on the notes-based chain of
    /// [`Geometry::axisymmetric`] (masses and ligament geometry unscaled).
    pub fn anatomical() -> Geometry {
        Geometry {
            tm_shape: DrumShape::Anatomical(AnatomicalDrum::default()),
            tm_loss: DrumLoss::LossFactor(anatomical_drum::LOSS_FACTOR),
            ..Geometry::axisymmetric()
        }
    }

    /// Gives the chosen joints the bonded-layer stiffening of [`JointPad`] (an
    /// experiment, `--joint-pads`: docs/results/simulator.md, "Joint pads as
    /// incompressible layers"). Every ear so far uses the unconfined E·A/t.
    pub fn confine_joint_pads(&mut self, pads: JointPads) {
        if matches!(pads, JointPads::Confined | JointPads::ImjConfined) {
            self.g_imj *= IMJ_PAD.compression_factor();
            self.g_imj_rot *= IMJ_PAD.tilt_factor();
        }
        if pads == JointPads::Confined {
            self.g_isj *= ISJ_PAD.compression_factor();
        }
    }

    /// The v1–v5 ear: the axisymmetric FE drum with Rayleigh loss and the chain's
    /// notes-based masses and ligament geometry (`--drum axisymmetric`; the FE drum's
    /// closed-form tests use it).
    pub fn axisymmetric() -> Geometry {
        let nu = 0.485;
        let shear = 1.0 / (2.0 * (1.0 + nu)); // G/E
        // Ligament and tendon cross-sections and lengths: notes §1.4 mid-range values.
        let (a_aml, l_aml) = (0.45e-6, 1.25e-3);
        let (a_pil, l_pil) = (0.40e-6, 0.5e-3);
        let torsion = |a: f64, l: f64| shear * a * a / (2.0 * PI) / l; // G·J/L per E, J = A²/2π
        // Joints: k = E·A/t (the unconfined pad; `anatomical` adds the bonded layer's
        // shape factor), so the IMJ is 4× stiffer per unit E than the ISJ; rotation
        // E·I/t, I = A·R²/4.
        let (a_imj, t_imj) = (IMJ_PAD.area, IMJ_PAD.thickness);
        let r_imj = IMJ_PAD.radius();
        // SAL in piston shear k = G·P·d/w (notes §1.6), perimeter 7.2 mm, width 0.1 mm and
        // depth 0.155 mm chosen so E = 0.2 MPa gives 750 N/m (target 500–1000 N/m).
        let g_sal = shear * 7.2e-3 * 0.155e-3 / 0.1e-3;
        let half_fp = 1.5e-3; // footplate semi-axis; rocking k = k_sal·a²/3 (thin ellipse)
        Geometry {
            tm_radius: 4.4e-3,
            tm_depth: 2.0e-3,
            tm_bulge: 0.3e-3,
            tm_thickness: 60e-6,
            tm_rho: 1100.0,
            tm_nu: nu,
            tm_loss: DrumLoss::Rayleigh,
            tm_shape: DrumShape::Axisymmetric,
            disc_radius: 0.5e-3,
            tm_elements: 20,
            m_malleus: 25e-6,
            i_malleus: 70e-12,
            m_incus: 28e-6,
            i_incus: 80e-12,
            m_stapes: 3e-6,
            i_stapes: 2e-12,
            arm_umbo: 5.5e-3,
            arm_lp: 4.2e-3,
            arm_imj: -1.0e-3,
            arm_ttt: 2.0e-3,
            stapes_height: 3.3e-3,
            stapes_tilt: 0.2,
            ldv_spot: 1.0e-3,
            footplate_area: 3.2e-6,
            leak_length: 5e-3,
            g_aml: a_aml / l_aml,
            g_aml_rot: torsion(a_aml, l_aml),
            g_pil: a_pil / l_pil,
            g_pil_rot: torsion(a_pil, l_pil),
            g_ttt: 0.45e-6 / 2.5e-3,
            g_stapedius: 0.13e-6 / 1.75e-3,
            g_imj: a_imj / t_imj,
            g_imj_rot: a_imj * r_imj * r_imj / (4.0 * t_imj),
            g_isj: ISJ_PAD.area / ISJ_PAD.thickness,
            g_isj_shear: shear * ISJ_PAD.area / ISJ_PAD.thickness,
            incus_lateral: false,
            g_pil_lateral: a_pil / l_pil,
            g_imj_lateral: shear * a_imj / t_imj,
            g_sal,
            g_sal_rock: g_sal * half_fp * half_fp / 3.0,
        }
    }
}

/// The incudomallear joint's cartilage pad: 2.5 mm² of facet (notes §1.4: 2–3 mm²) and
/// 62.5 µm between the bones, the v1 ear's value, below the notes' 0.1–0.2 mm for gap
/// and cartilage together (at 0.1 mm the shape factor's gains are ×41 and ×14, not ×103
/// and ×35: docs/results/simulator.md, "Joint pads as incompressible layers").
pub const IMJ_PAD: JointPad = JointPad { area: 2.5e-6, thickness: 62.5e-6 };
/// The incudostapedial joint's pad: 0.6 mm², 60 µm (notes §1.4: 0.4–0.8 mm², 0.05–0.1 mm).
pub const ISJ_PAD: JointPad = JointPad { area: 0.6e-6, thickness: 60e-6 };

/// A joint as a thin circular layer of soft tissue between two bone faces.
///
/// Why the shape factor: at sound frequencies the cartilage has no time to drain, so it
/// deforms at constant volume (Poisson ratio 0.5; Mow et al. 1980, J Biomech Eng
/// 102:73). A thin layer of an incompressible solid held between two faces cannot
/// thin without flowing outwards against its faces, so it is far stiffer in compression
/// and tilting than E·A/t: E(1 + 2S²) in compression and E(1 + 2S²/3) in tilting, with
/// the shape factor S = R/(2t), the loaded area over the free edge area (Gent & Lindley
/// 1959, Proc Inst Mech Eng 173:111; Gent & Meinecke 1970, Polym Eng Sci 10:48). Shear is
/// at constant volume already and keeps G·A/t. The limit holds while the stiffened
/// modulus stays well below the tissue's bulk modulus (about 2.2 GPa, water's; Duck
/// 1990, Physical Properties of Tissue): E_joints up to about 20 MPa for the
/// incudomallear joint, whose pad is by then rigid against the chain's other springs.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct JointPad {
    /// Facet area, m².
    pub area: f64,
    /// Tissue thickness between the bones, m.
    pub thickness: f64,
}

impl JointPad {
    /// The radius of the circle of the pad's area, m.
    pub fn radius(&self) -> f64 {
        (self.area / PI).sqrt()
    }

    /// Loaded area over free edge area: πR² / (2πR·t).
    pub fn shape_factor(&self) -> f64 {
        self.radius() / (2.0 * self.thickness)
    }

    /// Compression stiffness over the unconfined E·A/t.
    pub fn compression_factor(&self) -> f64 {
        1.0 + 2.0 * self.shape_factor().powi(2)
    }

    /// Tilting stiffness over the unconfined E·I/t.
    pub fn tilt_factor(&self) -> f64 {
        1.0 + 2.0 / 3.0 * self.shape_factor().powi(2)
    }
}

/// Which joint pads carry [`JointPad`]'s stiffening.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum JointPads {
    /// E·A/t for both joints (every ear so far).
    Unconfined,
    /// Both joints confined.
    Confined,
    /// The incudomallear joint confined, the incudostapedial joint not.
    ImjConfined,
}

/// The eardrum's loss model.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum DrumLoss {
    /// The seed's: E·(1 + jωβ) with the ossicles' damping_beta (a loss growing with
    /// frequency, which overdamps the drum's modes above ~2 kHz).
    Rayleigh,
    /// A frequency-independent loss factor η: E·(1 + jη) (soft tissue's measured
    /// behaviour over the audio band); damping_beta then acts on the ossicles only.
    LossFactor(f64),
    /// A frequency-independent loss factor set by damping_beta: η = 2π·f_ref·β, the
    /// Rayleigh loss at f_ref (one damping parameter for the whole ear, as in the study,
    /// without a loss that grows with frequency in the drum).
    Hysteretic {
        /// The frequency whose Rayleigh loss sets η, Hz.
        f_ref_hz: f64,
    },
}

/// The eardrum's finite elements.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum DrumShape {
    /// v1: an axisymmetric conical shell tied to the malleus by a rigid disc at the umbo
    /// (`shell.rs`). It cannot decouple from the malleus at high frequency.
    Axisymmetric,
    /// v2: flat-shell triangles over the same cone with the manubrium attached along its
    /// length from the umbo to `manubrium_to_rim` (m) from the rim, `rings` rings from the
    /// umbo to the rim (`drum_mesh.rs`). Always condensed onto the malleus through its modes.
    Manubrium {
        /// Rings of triangles from the umbo to the rim (the mesh density).
        rings: usize,
        /// Gap between the manubrium's lateral end and the rim, m.
        manubrium_to_rim: f64,
    },
    /// v6–v7's default (an experiment when it was added, 2026-11): the drum as a lossy transmission line from the canal to
    /// the umbo (`line_drum.rs`, Puria & Allen 1998); no FE, no modes.
    Line(LineDrum),
    /// The anatomical FE drum (`anatomical_drum.rs`): elliptical outline, measured
    /// thickness, the manubrium as a strip of finite width, a compliant annulus. Always
    /// condensed onto the malleus.
    Anatomical(AnatomicalDrum),
}

impl DrumShape {
    /// The v2 drum at its measured mesh density (docs/simulator.md): 16 rings leave a
    /// discretisation error below the test–retest noise; 12 do not.
    pub const MANUBRIUM: DrumShape = DrumShape::Manubrium { rings: 16, manubrium_to_rim: 1.0e-3 };
}

/// Air temperature preset.
#[derive(Clone, Copy, Debug, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Preset {
    /// Temporal-bone laboratory, air at 22 °C (the default).
    TemporalBone,
    /// Living ear, air at 37 °C.
    Live,
}

impl Preset {
    /// The air at the preset's temperature.
    pub fn air(self) -> Air {
        match self {
            Preset::TemporalBone => Air::at_celsius(22.0),
            Preset::Live => Air::at_celsius(37.0),
        }
    }
}

/// Log-spaced frequency grid, Hz.
pub fn log_grid(f_lo: f64, f_hi: f64, n: usize) -> Vec<f64> {
    (0..n).map(|i| f_lo * (f_hi / f_lo).powf(i as f64 / (n - 1).max(1) as f64)).collect()
}

/// Everything needed to build a model.
#[derive(Clone, Debug)]
pub struct ModelConfig {
    /// Air temperature.
    pub preset: Preset,
    /// Geometry and fixed material data.
    pub geometry: Geometry,
    /// The frequencies simulated, Hz.
    pub frequencies: Vec<f64>,
    /// Eliminate the drum's interior exactly through its modes (`drum.rs`); `false`
    /// keeps every shell DOF in the sparse system (same answer, slower; for tests).
    pub reduce_drum: bool,
}

impl Default for ModelConfig {
    fn default() -> Self {
        ModelConfig {
            preset: Preset::TemporalBone,
            geometry: Geometry::default(),
            frequencies: log_grid(200.0, 8000.0, 50),
            reduce_drum: true,
        }
    }
}

/// Block ids of the system's coefficient terms.
#[derive(Clone, Copy, Debug)]
struct Blocks {
    tm: usize,
    ligaments: usize,
    tendons: usize,
    joints: usize,
    sal: usize,
    mass: usize,
    cochlea: usize,
    drum_load: usize,   // −b p_drum in the mechanics rows
    drum_flow: usize,   // jω bᵀq: the flow into the drum (the driven row)
    cavity_load: usize, // +b p_cav in the mechanics rows
    cavity_row: usize,  // (1/C_cav) bᵀq − p_cav = 0
    cavity_diag: usize,
    /// A perforation's flow from the canal into the cavity, Y_p(p_drum − p_cav): in the
    /// flow row, and as volume into the cavity row (`perforation` effect; 0 when closed).
    perforation_flow: usize,
    perforation_cavity: usize,
    /// The incudostapedial joint again (axial and shear), weighted (s − 1)·κ_joints so that
    /// the joint's total is s·κ_joints (`isj_discontinuity`; 0 when intact).
    isj: usize,
    /// The malleus head bound to the attic wall (`malleus_fixation`; 0 when off).
    malleus_fixation: usize,
    /// The condensed drum: n² blocks (row-major) on its n boundary unknowns, (umbo,
    /// p_drum, p_cavity) or, for the manubrium drum, (umbo, θ_m, p_drum, p_cavity).
    drum_schur: usize,
}

/// The eardrum's interior, eliminated exactly through its modes.
enum Condensed {
    /// On (umbo, p_drum, p_cavity); the umbo disc and its b entries are in the system.
    Axisymmetric(DrumModes),
    /// On (umbo, θ_m, p_drum, p_cavity); holds the manubrium's own terms too.
    Manubrium(std::sync::Arc<ManubriumModes>),
    /// The anatomical drum, on the same four unknowns.
    Anatomical(std::sync::Arc<AnatomicalCondensed>),
    /// On (umbo, p_drum, p_cavity): the line's two-port and its shunt.
    Line(LineDrum),
}

/// Indices of the named unknowns.
#[derive(Clone, Debug)]
pub struct Dofs {
    /// Pressure on the eardrum; its row is the flow balance the unit drive enters.
    pub p_drum: usize,
    /// Axial displacement of the umbo (the malleus at the umbo arm), m.
    pub umbo: usize,
    /// Malleus rotation, rad.
    pub theta_m: usize,
    /// Incus translation, m.
    pub x_incus: usize,
    /// Incus rotation, rad.
    pub theta_i: usize,
    /// Stapes piston displacement along its axis, m.
    pub x_stapes: usize,
    /// Stapes rocking about the footplate centre, rad.
    pub phi_stapes: usize,
    /// Incus translation across the stapes axis, m (only with `Geometry::incus_lateral`).
    pub y_incus: Option<usize>,
    /// Middle-ear cavity pressure; its row is the cavity's compliance.
    pub p_cavity: usize,
    /// Number of unknowns.
    pub n: usize,
}

/// A built model: mesh, blocks and the shared symbolic factorisation. Build once; run
/// any number of parameter sets on any number of threads (one [`Runner`] per thread).
pub struct Model {
    /// What the model was built from.
    pub config: ModelConfig,
    /// The air in the canal and the cavity.
    pub air: Air,
    /// Where each named unknown is.
    pub dofs: Dofs,
    system: System,
    blocks: Blocks,
    /// Volume swept per unit of each unknown (zero off the eardrum).
    b: Vec<f64>,
    drum: Option<Condensed>,
}

/// The complex responses at one frequency.
#[derive(Clone, Copy, Debug)]
pub struct Response {
    /// Frequency, Hz.
    pub freq_hz: f64,
    /// Measured stapes velocity over canal pressure at the microphone, m/s/Pa.
    pub vst_over_p: c64,
    /// Umbo velocity over the same pressure, m/s/Pa (clinical LDV through the canal).
    pub vu_over_p: c64,
    /// Ear-canal impedance at the measurement plane as the probe sees it, Pa·s/m³.
    pub zec: c64,
    /// Characteristic impedance ρc/S at the measurement plane.
    pub z0: f64,
}

impl Response {
    /// Absorbance 1 − |R|² at the measurement plane.
    pub fn absorbance(&self) -> f64 {
        air::absorbance(self.zec, self.z0)
    }
}

/// Why one parameter set could not be simulated.
#[derive(Debug, thiserror::Error)]
pub enum SimError {
    /// A parameter (or effect) the model cannot use: not finite, or not positive.
    #[error("parameter {name} = {value} must be finite and positive (tm_viscoelastic: ≥ 0)")]
    BadParameter {
        /// The parameter's name.
        name: &'static str,
        /// The value given.
        value: f64,
    },
    /// A row with fewer columns than the parameters (e.g. a model trained on an older
    /// simulator's parameter list).
    #[error(
        "a parameter row has {got} columns; this simulator needs {expected} (its parameters, then the varied effects)"
    )]
    RowWidth {
        /// Columns the design needs.
        expected: usize,
        /// Columns given.
        got: usize,
    },
    #[error(transparent)]
    /// The sparse solve failed.
    Solve(#[from] SolveError),
    /// The sparse pattern of the system could not be analysed (faer's symbolic LU: its
    /// indices overflow or memory ran out).
    #[error("model setup failed: symbolic LU of the {unknowns}-unknown system: {source:?}")]
    SymbolicLu {
        /// Unknowns of the system.
        unknowns: usize,
        /// faer's reason.
        source: faer::sparse::FaerError,
    },
    /// `ModelConfig::reduce_drum` is false for a drum that exists only condensed.
    #[error(
        "model setup failed: reduce_drum = false with tm_shape = {shape}: that drum is always condensed \
         (reduce_drum = false needs DrumShape::Axisymmetric)"
    )]
    DrumNotCondensed {
        /// The drum shape asked for.
        shape: &'static str,
    },
    /// The drum's modes could not be computed.
    #[error("model setup failed: {0}")]
    Drum(#[from] DrumError),
}

/// The residual canal as a uniform line: pressure and flow at distance `l` lateral of
/// the drum, for pressure `p_l` on the drum and a unit flow into it.
#[derive(Clone, Copy, Debug)]
struct Line {
    /// Series impedance and shunt admittance per length (for the wall losses).
    z: c64,
    y: c64,
    gamma: c64,
    zc: c64,
    p_l: c64,
}

impl Line {
    fn at(&self, l: f64) -> (c64, c64) {
        let (ch, sh) = ((self.gamma * l).cosh(), (self.gamma * l).sinh());
        (ch * self.p_l + self.zc * sh, sh * self.p_l / self.zc + ch)
    }
}

impl Model {
    /// Builds the model: the unknowns' layout, then the drum, the ossicles and the
    /// pressure coupling each add their terms to one sparse pattern, factorised
    /// symbolically once for every parameter set and frequency.
    pub fn new(config: ModelConfig) -> Result<Model, SimError> {
        let g = &config.geometry;
        let air = config.preset.air();
        let nodes = drum_nodes(&config)?;
        let dofs = Dofs::layout(config.reduce_drum, nodes.len(), g.incus_lateral);
        let mut sb = SystemBuilder::new(dofs.n);
        let blocks = Blocks::new(&mut sb, dofs.condensed(g.tm_shape).len());
        let mut b = vec![0.0; dofs.n];
        let drum = drum(&config, &nodes, &dofs, &blocks, &mut sb, &mut b)?;
        ossicles(g, &dofs, &blocks, &mut sb);
        couple_pressures(&b, &dofs, &blocks, &mut sb);
        let unknowns = dofs.n;
        let system = sb.build().map_err(|source| SimError::SymbolicLu { unknowns, source })?;
        Ok(Model { config, air, dofs, system, blocks, b, drum })
    }

    /// Non-zeros of the sparse system.
    pub fn nnz(&self) -> usize {
        self.system.nnz()
    }

    /// Unknowns of the sparse system.
    pub fn n_unknowns(&self) -> usize {
        self.system.n
    }

    /// The frequency grid, Hz.
    pub fn frequencies(&self) -> &[f64] {
        &self.config.frequencies
    }

    /// Per-thread solver state; one per thread, any number per model.
    pub fn runner(&self) -> Runner<'_> {
        Runner {
            model: self,
            ws: self.system.workspace(),
            coef: vec![c64::new(0.0, 0.0); self.system.n_blocks()],
            memo: None,
            drum_memo: Vec::new(),
        }
    }

    /// The system's block coefficients at angular frequency `w`; the condensed drum's block
    /// from `drum_memo` when it holds one for the same drum coefficients.
    fn fill_coefficients(
        &self,
        theta: &Theta,
        fx: &Effects,
        w: f64,
        coef: &mut [c64],
        mut drum_memo: Option<&mut DrumMemo>,
    ) {
        let bl = &self.blocks;
        let jw = c64::new(0.0, w);
        let rayleigh = c64::new(1.0, w * theta.damping_beta());
        let drum_loss = match self.config.geometry.tm_loss {
            DrumLoss::Rayleigh => rayleigh,
            DrumLoss::LossFactor(eta) => c64::new(1.0, eta),
            DrumLoss::Hysteretic { f_ref_hz } => c64::new(1.0, 2.0 * PI * f_ref_hz * theta.damping_beta()),
        };
        // Power-law viscoelastic eardrum, E·(jω/ω0)^n, ω0 = 2π·1 kHz.
        let n = theta.tm_exponent();
        let visco = if n == 0.0 {
            c64::new(1.0, 0.0)
        } else {
            c64::from_polar((w / (2.0 * PI * 1000.0)).powf(n), n * PI / 2.0)
        };
        coef[bl.tm] = drum_loss * visco * theta.e_eardrum();
        coef[bl.ligaments] = rayleigh * theta.e_ligaments();
        coef[bl.tendons] = rayleigh * theta.e_tendons();
        coef[bl.joints] = rayleigh * theta.e_joints();
        coef[bl.sal] = rayleigh * theta.e_sal();
        // A static pressure across the drum: lossless pre-stress stiffness on the drum and
        // the chain's suspension (`ear_effects::pressure_stiffening`).
        let stiffening = ear_effects::pressure_stiffening(fx.static_pressure());
        if stiffening > 0.0 {
            coef[bl.tm] += stiffening * theta.e_eardrum();
            coef[bl.ligaments] += stiffening * theta.e_ligaments();
            coef[bl.sal] += stiffening * theta.e_sal();
        }
        // An interrupted incudostapedial joint: its spring and dashpot scaled by s.
        coef[bl.isj] = coef[bl.joints] * (fx.isj_factor() - 1.0);
        // A fixed malleus: the head bound to the attic wall without loss (it stores energy
        // and dissipates none, so the power balance has no term for it).
        coef[bl.malleus_fixation] = c64::new(fx.malleus_fixation(), 0.0);
        coef[bl.mass] = c64::new(-w * w, 0.0);
        // The cochlear input impedance, shunted by a third window's acoustic mass when one
        // is open: the displaced fluid takes both paths (params::EFFECTS, third_window).
        let mut z_cochlea = c64::new(theta.cochlear_load(), w * theta.cochlear_mass());
        let m_tw = fx.third_window_mass();
        if m_tw > 0.0 {
            let z_tw = c64::new(0.0, w * m_tw);
            z_cochlea = z_cochlea * z_tw / (z_cochlea + z_tw);
        }
        coef[bl.cochlea] = jw * z_cochlea;
        coef[bl.drum_load] = c64::new(1.0, 0.0);
        coef[bl.drum_flow] = jw;
        coef[bl.cavity_load] = c64::new(1.0, 0.0);
        // The air behind the drum: a compliance, or with fluid and a mastoid the
        // impedance of `ear_effects::cavity_coefficients`.
        let (cavity_row, cavity_diag) = ear_effects::cavity_coefficients(&self.air, theta.cavity_volume(), fx, w);
        coef[bl.cavity_row] = c64::new(cavity_row, 0.0);
        coef[bl.cavity_diag] = cavity_diag;
        let y_p = match fx.perforation_radius() {
            a if a > 0.0 => 1.0 / perforation_impedance(&self.air, a, w),
            _ => c64::new(0.0, 0.0),
        };
        coef[bl.perforation_flow] = y_p;
        coef[bl.perforation_cavity] = y_p * cavity_row / jw;
        let c = self.drum_coefficients(coef, w);
        let at = bl.drum_schur;
        if let Some(block) = drum_memo.as_deref_mut().and_then(|m| m.get(&c)) {
            coef[at..at + block.len()].copy_from_slice(block);
            return;
        }
        let n = match &self.drum {
            Some(Condensed::Axisymmetric(modes)) => {
                coef[at..at + 9].copy_from_slice(&modes.schur(&c));
                9
            }
            Some(Condensed::Manubrium(modes)) => {
                for (i, row) in modes.block(&c).iter().enumerate() {
                    coef[at + 4 * i..at + 4 * i + 4].copy_from_slice(row);
                }
                16
            }
            Some(Condensed::Anatomical(drum)) => {
                for (i, row) in drum.block(&c).iter().enumerate() {
                    coef[at + 4 * i..at + 4 * i + 4].copy_from_slice(row);
                }
                16
            }
            Some(Condensed::Line(line)) => {
                let block = line.block(coef[bl.tm], w, coef[bl.cavity_row].re);
                coef[at..at + 9].copy_from_slice(&block);
                9
            }
            None => return,
        };
        if let Some(m) = drum_memo {
            m.insert(c, &coef[at..at + n]);
        }
    }

    fn drum_coefficients(&self, coef: &[c64], w: f64) -> DrumCoefficients {
        let bl = &self.blocks;
        DrumCoefficients { kappa: coef[bl.tm], s: -w * w, jw: c64::new(0.0, w), cavity: coef[bl.cavity_row].re }
    }
}

impl Dofs {
    /// The unknowns in order: p_drum, the drum's interior (only when it is kept whole,
    /// so that the tests can compare it with the condensed drum), the ossicles, p_cavity.
    fn layout(reduce_drum: bool, n_nodes: usize, incus_lateral: bool) -> Dofs {
        let n_interior = 3 * n_nodes.saturating_sub(2);
        let osc = 1 + if reduce_drum { 0 } else { n_interior };
        let lat = usize::from(incus_lateral);
        Dofs {
            p_drum: 0,
            umbo: osc,
            theta_m: osc + 1,
            x_incus: osc + 2,
            theta_i: osc + 3,
            x_stapes: osc + 4,
            phi_stapes: osc + 5,
            y_incus: incus_lateral.then_some(osc + 6),
            p_cavity: osc + 6 + lat,
            n: osc + 7 + lat,
        }
    }

    /// The unknowns a condensed drum couples to: the manubrium drum also turns with the
    /// malleus along its length, the axisymmetric one meets it at the umbo only.
    fn condensed(&self, shape: DrumShape) -> Vec<usize> {
        match shape {
            DrumShape::Axisymmetric | DrumShape::Line(_) => vec![self.umbo, self.p_drum, self.p_cavity],
            DrumShape::Manubrium { .. } | DrumShape::Anatomical(_) => {
                vec![self.umbo, self.theta_m, self.p_drum, self.p_cavity]
            }
        }
    }
}

impl Blocks {
    /// One coefficient block per term, and n² for the condensed drum's dense block on its
    /// `n_condensed` boundary unknowns (each entry varies with frequency on its own).
    fn new(sb: &mut SystemBuilder, n_condensed: usize) -> Blocks {
        Blocks {
            tm: sb.block(),
            ligaments: sb.block(),
            tendons: sb.block(),
            joints: sb.block(),
            sal: sb.block(),
            mass: sb.block(),
            cochlea: sb.block(),
            drum_load: sb.block(),
            drum_flow: sb.block(),
            cavity_load: sb.block(),
            cavity_row: sb.block(),
            cavity_diag: sb.block(),
            perforation_flow: sb.block(),
            perforation_cavity: sb.block(),
            isj: sb.block(),
            malleus_fixation: sb.block(),
            drum_schur: {
                let first = sb.block();
                for _ in 1..n_condensed.pow(2) {
                    sb.block();
                }
                first
            },
        }
    }
}

/// The axisymmetric drum's nodes, from the disc edge (index 0) to the clamped rim; none
/// for the manubrium drum, which meshes itself and exists only condensed.
fn drum_nodes(config: &ModelConfig) -> Result<Vec<(f64, f64)>, SimError> {
    let g = &config.geometry;
    match g.tm_shape {
        DrumShape::Axisymmetric => Ok(cone_nodes(g.disc_radius, g.tm_radius, g.tm_depth, g.tm_bulge, g.tm_elements)),
        DrumShape::Manubrium { .. } if !config.reduce_drum => Err(SimError::DrumNotCondensed { shape: "Manubrium" }),
        DrumShape::Anatomical(_) if !config.reduce_drum => Err(SimError::DrumNotCondensed { shape: "Anatomical" }),
        DrumShape::Manubrium { .. } | DrumShape::Line(_) | DrumShape::Anatomical(_) => Ok(Vec::new()),
    }
}

/// The eardrum: assembled into the system, or condensed through its modes with only the
/// pattern of its dense block on the boundary unknowns in the system (the values come
/// per frequency from the modes).
fn drum(
    config: &ModelConfig,
    nodes: &[(f64, f64)],
    dofs: &Dofs,
    blocks: &Blocks,
    sb: &mut SystemBuilder,
    b: &mut [f64],
) -> Result<Option<Condensed>, SimError> {
    let g = &config.geometry;
    let drum = match g.tm_shape {
        DrumShape::Axisymmetric => {
            axisymmetric_drum(g, nodes, dofs, blocks, config.reduce_drum, sb, b)?.map(Condensed::Axisymmetric)
        }
        DrumShape::Manubrium { rings, manubrium_to_rim } => {
            let drum = DrumGeometry {
                radius_x: g.tm_radius,
                radius_y: g.tm_radius,
                depth: g.tm_depth,
                bulge: g.tm_bulge,
                manubrium_to_rim,
                material: ShellMaterial { h: g.tm_thickness, nu: g.tm_nu, rho: g.tm_rho },
                rings,
            };
            Some(Condensed::Manubrium(drum.modes_shared()?))
        }
        DrumShape::Line(line) => Some(Condensed::Line(line)),
        DrumShape::Anatomical(drum) => Some(Condensed::Anatomical(drum.condensed_shared()?)),
    };
    if drum.is_some() {
        let condensed_at = dofs.condensed(g.tm_shape);
        for (i, &r) in condensed_at.iter().enumerate() {
            for (j, &c) in condensed_at.iter().enumerate() {
                sb.add(blocks.drum_schur + condensed_at.len() * i + j, r, c, 1.0);
            }
        }
    }
    Ok(drum)
}

/// The ossicular chain: masses, ligaments, tendons, joints, the annular ligament and the
/// cochlear load, each in its own block so that its modulus scales it per run.
fn ossicles(g: &Geometry, d: &Dofs, blocks: &Blocks, sb: &mut SystemBuilder) {
    // Malleus in (w_umbo, θ_m): x_m = w_umbo − l_u θ_m, so a malleus point at arm l
    // moves by w_umbo + (l − l_u) θ_m along z.
    let lu = g.arm_umbo;
    let malleus_at = |l: f64| vec![(d.umbo, 1.0), (d.theta_m, l - lu)];
    let incus_at = |l: f64| vec![(d.x_incus, 1.0), (d.theta_i, l)];
    // Stapes: piston x_s along its axis, tilted by α from z; rocking φ about the
    // footplate centre moves the head by h·φ across the axis.
    let (ca, sa, hs) = (g.stapes_tilt.cos(), g.stapes_tilt.sin(), g.stapes_height);
    let head_z = [(d.x_stapes, ca), (d.phi_stapes, -hs * sa)];
    let head_y = [(d.x_stapes, sa), (d.phi_stapes, hs * ca)];

    // Masses (centres of mass on the rotation axis, at the footplate for rocking).
    sb.add_outer(blocks.mass, &malleus_at(0.0), g.m_malleus);
    sb.add(blocks.mass, d.theta_m, d.theta_m, g.i_malleus);
    sb.add(blocks.mass, d.x_incus, d.x_incus, g.m_incus);
    sb.add(blocks.mass, d.theta_i, d.theta_i, g.i_incus);
    sb.add(blocks.mass, d.x_stapes, d.x_stapes, g.m_stapes);
    sb.add(blocks.mass, d.phi_stapes, d.phi_stapes, g.i_stapes);

    // Ligaments on the axis: translation plus torsion.
    sb.add_outer(blocks.ligaments, &malleus_at(0.0), g.g_aml);
    sb.add(blocks.ligaments, d.theta_m, d.theta_m, g.g_aml_rot);
    sb.add_outer(blocks.ligaments, &incus_at(0.0), g.g_pil);
    sb.add(blocks.ligaments, d.theta_i, d.theta_i, g.g_pil_rot);
    // Tendons: tensor tympani on the malleus neck, stapedius across the stapes head.
    sb.add_outer(blocks.tendons, &malleus_at(g.arm_ttt), g.g_ttt);
    sb.add_outer(blocks.tendons, &head_y, g.g_stapedius);
    // Joints: IMJ (translation at its arm + rotation), ISJ (along z and shear).
    let mut imj = malleus_at(g.arm_imj);
    imj.extend(incus_at(g.arm_imj).into_iter().map(|(i, c)| (i, -c)));
    sb.add_outer(blocks.joints, &imj, g.g_imj);
    sb.add_outer(blocks.joints, &[(d.theta_m, 1.0), (d.theta_i, -1.0)], g.g_imj_rot);
    let mut isj = incus_at(g.arm_lp);
    isj.extend(head_z.iter().map(|&(i, c)| (i, -c)));
    sb.add_outer(blocks.joints, &isj, g.g_isj);
    sb.add_outer(blocks.isj, &isj, g.g_isj);
    match d.y_incus {
        // The lenticular process moves across the axis with the incus: the ISJ shears
        // between the two bodies; the PIL and the IMJ hold the incus.
        Some(yi) => {
            let mut shear = vec![(yi, 1.0)];
            shear.extend(head_y.iter().map(|&(i, c)| (i, -c)));
            sb.add_outer(blocks.joints, &shear, g.g_isj_shear);
            sb.add_outer(blocks.isj, &shear, g.g_isj_shear);
            sb.add(blocks.mass, yi, yi, g.m_incus);
            sb.add(blocks.ligaments, yi, yi, g.g_pil_lateral);
            sb.add(blocks.joints, yi, yi, g.g_imj_lateral);
        }
        None => {
            sb.add_outer(blocks.joints, &head_y, g.g_isj_shear);
            sb.add_outer(blocks.isj, &head_y, g.g_isj_shear);
        }
    }
    // A fixed malleus: the head bound to the attic wall, a spring at the head's centre and
    // a torsion spring (`ear_effects::malleus_head_fixation`; the block's coefficient is
    // the stiffness in N/m, 0 when off).
    let (head, torsion) = ear_effects::malleus_head_fixation(lu);
    sb.add_outer(blocks.malleus_fixation, &malleus_at(head), 1.0);
    sb.add(blocks.malleus_fixation, d.theta_m, d.theta_m, torsion);
    // Stapes annular ligament: piston and rocking.
    sb.add(blocks.sal, d.x_stapes, d.x_stapes, g.g_sal);
    sb.add(blocks.sal, d.phi_stapes, d.phi_stapes, g.g_sal_rock);
    // Cochlear load on the piston: force = Z_c·A_fp²·velocity.
    sb.add(blocks.cochlea, d.x_stapes, d.x_stapes, g.footplate_area * g.footplate_area);
}

/// Coupling through b, the volume swept per unit of each unknown: the canal pressure
/// loads the drum; the drum's volume velocity is the flow into it (the row the unit
/// drive enters); the cavity pressure pushes back.
fn couple_pressures(b: &[f64], d: &Dofs, blocks: &Blocks, sb: &mut SystemBuilder) {
    let last = d.p_drum;
    for (i, &bi) in b.iter().enumerate().filter(|(_, bi)| **bi != 0.0) {
        sb.add(blocks.drum_load, i, last, -bi);
        sb.add(blocks.drum_flow, last, i, bi);
        sb.add(blocks.cavity_load, i, d.p_cavity, bi);
        sb.add(blocks.cavity_row, d.p_cavity, i, bi);
    }
    sb.add(blocks.cavity_diag, d.p_cavity, d.p_cavity, -1.0);
    // A perforation: flow Y_p(p_drum − p_cavity) leaves the flow row's balance and enters
    // the cavity as volume Y_p(p_drum − p_cavity)/(jω).
    for (block, row) in [(blocks.perforation_flow, last), (blocks.perforation_cavity, d.p_cavity)] {
        sb.add(block, row, last, 1.0);
        sb.add(block, row, d.p_cavity, -1.0);
    }
}

/// Acoustic impedance of a perforation of radius `a` through the pars tensa: the air plug
/// of a short tube (the membrane's thickness, [`anatomical_drum::THICKNESS_MIDDLE`]) with
/// an end correction of 0.85a on each side, its mass ρ(t + 1.7a)/(πa²) and its viscous
/// resistance 8μ(t + 1.7a)/(πa⁴) (Poiseuille over the same length, as for the probe
/// leak) — the acoustic mass and resistance path from the canal to the middle-ear cavity
/// of Voss et al. 2001 (JASA 110:1432). The drum keeps its area and stiffness: a hole of
/// a few mm² in a 60 mm² membrane.
pub fn perforation_impedance(air: &Air, a: f64, w: f64) -> c64 {
    let length = anatomical_drum::THICKNESS_MIDDLE + 1.7 * a;
    let mass = air.rho * length / (PI * a * a);
    let res = 8.0 * air.mu * length / (PI * a.powi(4));
    c64::new(res, w * mass)
}

/// The axisymmetric drum's stiffness (per unit E), mass and swept volume, assembled
/// densely over its local DOFs (interior, then the umbo last): the modes need the
/// interior block and its coupling column to the umbo apart.
fn axisymmetric_matrices(g: &Geometry, nodes: &[(f64, f64)]) -> (faer::Mat<f64>, faer::Mat<f64>, Vec<f64>) {
    let n_interior = 3 * (nodes.len() - 2);
    let nl = n_interior + 1;
    // Local eardrum DOF d of node i: interior index 0..n_interior, the umbo as
    // n_interior, None on the clamped rim.
    let tm_local = |i: usize, d: usize| -> Option<usize> {
        if i == 0 {
            (d == 1).then_some(n_interior) // disc: u_r = β = 0, u_z = umbo
        } else if i == nodes.len() - 1 {
            None // clamped annulus
        } else {
            Some(3 * (i - 1) + d)
        }
    };
    let mat = ShellMaterial { h: g.tm_thickness, nu: g.tm_nu, rho: g.tm_rho };
    let (mut kd, mut md, mut bd) = (faer::Mat::<f64>::zeros(nl, nl), faer::Mat::<f64>::zeros(nl, nl), vec![0.0; nl]);
    for el in 0..nodes.len() - 1 {
        let se = ShellElement::new(nodes[el], nodes[el + 1], &mat);
        let map: [Option<usize>; 6] = std::array::from_fn(|i| tm_local(el + i / 3, i % 3));
        for i in 0..6 {
            let Some(li) = map[i] else { continue };
            bd[li] += se.b[i];
            for (j, lj) in map.iter().enumerate() {
                let Some(lj) = *lj else { continue };
                kd[(li, lj)] += se.k_unit[i][j];
                md[(li, lj)] += se.m[i][j];
            }
        }
    }
    (kd, md, bd)
}

/// Assembles the axisymmetric drum and its umbo disc: into the system directly, or (when
/// `reduce`) condensed through its modes, leaving the umbo terms and `b` in the system.
fn axisymmetric_drum(
    g: &Geometry,
    nodes: &[(f64, f64)],
    dofs: &Dofs,
    blocks: &Blocks,
    reduce: bool,
    sb: &mut SystemBuilder,
    b: &mut [f64],
) -> Result<Option<DrumModes>, SimError> {
    let n_interior = 3 * (nodes.len() - 2);
    let nl = n_interior + 1;
    let (kd, md, bd) = axisymmetric_matrices(g, nodes);
    let modes = if reduce {
        let ni = n_interior;
        let col = |a: &faer::Mat<f64>| (0..ni).map(|i| a[(i, ni)]).collect::<Vec<f64>>();
        let modes = DrumModes::new(
            &kd.submatrix(0, 0, ni, ni).to_owned(),
            &md.submatrix(0, 0, ni, ni).to_owned(),
            &col(&kd),
            &col(&md),
            &bd[..ni],
        )?;
        sb.add(blocks.tm, dofs.umbo, dofs.umbo, kd[(ni, ni)]);
        sb.add(blocks.mass, dofs.umbo, dofs.umbo, md[(ni, ni)]);
        b[dofs.umbo] = bd[ni];
        Some(modes)
    } else {
        let global = |l: usize| if l == n_interior { dofs.umbo } else { 1 + l };
        for li in 0..nl {
            b[global(li)] += bd[li];
            for lj in 0..nl {
                if kd[(li, lj)] != 0.0 || md[(li, lj)] != 0.0 {
                    sb.add(blocks.tm, global(li), global(lj), kd[(li, lj)]);
                    sb.add(blocks.mass, global(li), global(lj), md[(li, lj)]);
                }
            }
        }
        None
    };
    // The rigid disc: its area moves with the umbo; its mass rides on the umbo.
    let disc_area = PI * g.disc_radius * g.disc_radius;
    b[dofs.umbo] += disc_area;
    sb.add(blocks.mass, dofs.umbo, dofs.umbo, g.tm_rho * g.tm_thickness * disc_area);
    Ok(modes)
}

/// Per-thread solver state for one model.
pub struct Runner<'m> {
    model: &'m Model,
    ws: Workspace,
    coef: Vec<c64>,
    /// Recent whole-grid solves, when asked for ([`Runner::remember`]).
    memo: Option<Memo>,
    /// Recent drum blocks per frequency of the grid, with `memo`.
    drum_memo: Vec<DrumMemo>,
}

/// Power balance of one solve (W, for a unit probe volume velocity): what enters at the
/// probe, what the canal walls dissipate, what enters the middle ear at the drum, and
/// where the middle ear dissipates it: probe = canal + into_drum and into_drum =
/// mechanical (a closed cavity stores, never dissipates; a mastoid's aditus and cells do).
/// The probe leak and the probe offset act on Z_ec after the solve and are not part of it.
#[derive(Clone, Copy, Debug)]
pub struct PowerBalance {
    /// Frequency, Hz.
    pub freq_hz: f64,
    /// Power entering at the probe.
    pub probe: f64,
    /// Power dissipated by the canal walls.
    pub canal: f64,
    /// Power entering the middle ear at the drum (through a perforation too).
    pub into_drum: f64,
    /// All middle-ear dissipation: the sum of the eight parts below.
    pub mechanical: f64,
    /// The eardrum's loss (Rayleigh and, when on, viscoelastic), interior and disc.
    pub drum: f64,
    /// Rayleigh loss in the ossicular soft tissue, per stiffness block.
    pub ligaments: f64,
    /// Rayleigh loss in the tendons.
    pub tendons: f64,
    /// Rayleigh loss in the joints.
    pub joints: f64,
    /// Rayleigh loss in the annular ligament.
    pub sal: f64,
    /// Power delivered to the cochlear load ½·Re(Z_c)·A_fp²·|v_piston|².
    pub cochlea: f64,
    /// Loss in a perforation's air plug, ½·Re(Z_p)·|U_hole|² (0 without one).
    pub perforation: f64,
    /// Power the air spaces behind the drum absorb, ½·Re(p̄_cav·U) for all the flow U into
    /// them: 0 for a closed compliance, with or without fluid; the aditus' and the mastoid
    /// cells' loss when a mastoid is on.
    pub cavity: f64,
}

impl PowerBalance {
    /// Fraction of the power entering the middle ear that reaches the cochlea.
    pub fn cochlear_share(&self) -> f64 {
        self.cochlea / self.into_drum
    }
}

impl Runner<'_> {
    /// Solves one frequency for a unit volume velocity into the eardrum; the full
    /// solution is then in [`Self::solution`].
    pub fn solve_at(&mut self, theta: &Theta, freq_hz: f64) -> Result<(), SimError> {
        self.solve_with(theta, &Effects::default(), freq_hz)
    }

    /// [`Self::solve_at`] with the effects that act inside the middle ear (a third
    /// window, a perforation, fluid, a static pressure, a mastoid, an interrupted
    /// incudostapedial joint, a fixed malleus); those at the probe act on the responses
    /// after the solve.
    pub fn solve_with(&mut self, theta: &Theta, fx: &Effects, freq_hz: f64) -> Result<(), SimError> {
        self.solve_on_grid(theta, fx, freq_hz, None)
    }

    /// [`Self::solve_with`]; `grid`: the frequency's index in the model's grid, whose
    /// kept drum blocks the solve may use.
    fn solve_on_grid(
        &mut self,
        theta: &Theta,
        fx: &Effects,
        freq_hz: f64,
        grid: Option<usize>,
    ) -> Result<(), SimError> {
        check(theta)?;
        let w = 2.0 * PI * freq_hz;
        let drum_memo = grid.and_then(|k| self.drum_memo.get_mut(k));
        self.model.fill_coefficients(theta, fx, w, &mut self.coef, drum_memo);
        self.model.system.solve(&self.coef, &[(self.model.dofs.p_drum, c64::new(1.0, 0.0))], &mut self.ws, freq_hz)?;
        Ok(())
    }

    /// The unknowns of the last solve (unit volume velocity into the eardrum).
    pub fn solution(&self) -> &[c64] {
        &self.ws.x
    }

    /// The residual canal of `theta` at angular frequency `w`, loaded by the last solve.
    fn line(&self, theta: &Theta, w: f64) -> Line {
        line(&self.model.air, theta, w, self.ws.x[self.model.dofs.p_drum])
    }

    /// The unknowns a response is read from, of the last solve.
    fn solved(&self) -> Solved {
        let (d, x) = (&self.model.dofs, &self.ws.x);
        Solved { p_drum: x[d.p_drum], x_stapes: x[d.x_stapes], phi_stapes: x[d.phi_stapes], umbo: x[d.umbo] }
    }

    /// Keeps the last `capacity` distinct whole-grid solves of [`Self::run`], so a run
    /// that differs from one of them only after the solve (the canal, the microphone,
    /// the LDV angle, the probe's effects) costs no solve: a finite-difference Jacobian's
    /// columns for those. Each grid frequency also keeps its last four drum blocks, so a
    /// run that leaves the drum's stiffness and the cavity as they were skips the modal
    /// sum. The answers are the same bit for bit.
    pub fn remember(&mut self, capacity: usize) {
        self.memo = Some(Memo::new(capacity));
        // Four: a Jacobian's base, then at most the drum's stiffness, the cavity and
        // the viscoelasticity columns between columns that reuse the base's block.
        self.drum_memo = self.model.config.frequencies.iter().map(|_| DrumMemo::new(4)).collect();
    }

    /// [`Self::remember`] sized for finite-difference Jacobians of `columns` columns: the
    /// base row outlives its columns' runs, which reuse its solves and drum blocks.
    pub fn remember_jacobian(&mut self, columns: usize) {
        self.remember(columns + 1);
    }

    /// Runs answered from the kept solves so far (0 when none are kept).
    pub fn solves_reused(&self) -> usize {
        self.memo.as_ref().map_or(0, Memo::hits)
    }

    /// Drum blocks taken from the kept ones so far, over all frequencies.
    pub fn drum_blocks_reused(&self) -> usize {
        self.drum_memo.iter().map(DrumMemo::hits).sum()
    }

    /// Measured responses at one frequency, effects applied.
    pub fn response_at(&mut self, theta: &Theta, fx: &Effects, freq_hz: f64) -> Result<Response, SimError> {
        self.solve_with(theta, fx, freq_hz)?;
        Ok(respond(self.model, theta, fx, freq_hz, self.solved()))
    }

    /// All frequencies of the model's grid.
    pub fn run(&mut self, theta: &Theta, fx: &Effects) -> Result<Vec<Response>, SimError> {
        let freqs = self.model.config.frequencies.clone();
        let Some(mut memo) = self.memo.take() else {
            return freqs.iter().map(|&f| self.response_at(theta, fx, f)).collect();
        };
        let key = memo.key(theta, fx);
        let out = match memo.get(&key) {
            Some(solved) => {
                check(theta)?;
                Ok(freqs.iter().zip(solved).map(|(&f, &s)| respond(self.model, theta, fx, f, s)).collect())
            }
            None => {
                let mut solved = Vec::with_capacity(freqs.len());
                let out = freqs
                    .iter()
                    .enumerate()
                    .map(|(k, &f)| {
                        self.solve_on_grid(theta, fx, f, Some(k))?;
                        let s = self.solved();
                        solved.push(s);
                        Ok(respond(self.model, theta, fx, f, s))
                    })
                    .collect::<Result<Vec<Response>, SimError>>();
                if out.is_ok() {
                    memo.insert(key, solved);
                }
                out
            }
        };
        self.memo = Some(memo);
        out
    }

    /// Power balance of the last solve, per unit volume velocity at the impedance plane,
    /// each term from its own physical formula: probe ½Re(p̄₀U₀); canal walls
    /// ½∫(Re Z′|U|² + Re Y′|p|²)dx along the line (Simpson); drum ½Re(p̄_L·jω bᵀq);
    /// mechanical ½ω Σ Im(κ_b)·qᴴB_b q over the stiffness and dashpot blocks.
    pub fn power_balance(&self, theta: &Theta, freq_hz: f64) -> PowerBalance {
        let m = self.model;
        let x = &self.ws.x;
        let w = 2.0 * PI * freq_hz;
        let line = self.line(theta, w);
        let l = theta.canal_length();
        let (p0, u0) = line.at(l);
        let scale = 1.0 / u0.norm_sqr();
        let probe = 0.5 * (p0.conj() * u0).re * scale;
        let canal = simpson(512, |t| {
            let (p, u) = line.at(l * t);
            line.z.re * u.norm_sqr() + line.y.re * p.norm_sqr()
        }) * l
            * 0.5
            * scale;
        let mut vol: c64 = m.b.iter().zip(x).map(|(bi, xi)| *xi * *bi).sum();
        let bl = &m.blocks;
        let loss = |b: usize| 0.5 * w * self.coef[b].im * m.system.quadratic_form(b, &self.ws).re * scale;
        let mut drum = loss(bl.tm);
        // The condensed interior: recover its modal amplitudes for volume and losses.
        let c = m.drum_coefficients(&self.coef, w);
        let (u, d) = (x[m.dofs.umbo], &m.dofs);
        let (v_int, e_int) = match &m.drum {
            Some(Condensed::Axisymmetric(modes)) => {
                let eta = modes.interior(&c, [u, x[d.p_drum], x[d.p_cavity]]);
                let (v, e) = modes.volume_and_energy(&eta, u);
                (v, e.re)
            }
            Some(Condensed::Manubrium(modes)) => {
                let (t, p, pc) = (x[d.theta_m], x[d.p_drum], x[d.p_cavity]);
                let eta = modes.interior(&c, [u, t, p, pc]);
                (modes.volume(&eta, u, t), modes.unit_stiffness_energy(&eta, u, t))
            }
            Some(Condensed::Anatomical(drum)) => {
                drum.volume_and_energy(&c, [u, x[d.theta_m], x[d.p_drum], x[d.p_cavity]])
            }
            Some(Condensed::Line(line)) => {
                let (kappa, jw) = (self.coef[bl.tm], c64::new(0.0, w));
                let (p1, v) = (x[d.p_drum] - x[d.p_cavity], jw * u);
                let ports = line.ports(kappa, w, p1, v);
                drum += line.loss(kappa, w, p1, v) * scale;
                ((ports.u1 + ports.u_shunt) / jw, 0.0)
            }
            None => (c64::new(0.0, 0.0), 0.0),
        };
        vol += v_int;
        drum += 0.5 * w * self.coef[bl.tm].im * e_int * scale;
        // A perforation's flow joins the drum's at the canal side and loses ½Re(Z_p)|U_p|²
        // in the hole; the cavity takes both flows and, a pure compliance, no net power.
        let dp = x[m.dofs.p_drum] - x[m.dofs.p_cavity];
        let u_hole = self.coef[bl.perforation_flow] * dp;
        let flow_in = c64::new(0.0, w) * vol + u_hole;
        let into_drum = 0.5 * (x[m.dofs.p_drum].conj() * flow_in).re * scale;
        let perforation = 0.5 * (dp.conj() * u_hole).re * scale;
        let cavity = 0.5 * (x[m.dofs.p_cavity].conj() * (c64::new(0.0, w) * vol + u_hole)).re * scale;
        // The joints' block holds the whole incudostapedial joint; its `isj` copy carries
        // the (s − 1) of an interrupted one, so the two sum to the joint's true loss.
        let (ligaments, tendons, joints) = (loss(bl.ligaments), loss(bl.tendons), loss(bl.joints) + loss(bl.isj));
        let (sal, cochlea) = (loss(bl.sal), loss(bl.cochlea));
        let mechanical = drum + ligaments + tendons + joints + sal + cochlea + perforation + cavity;
        PowerBalance {
            freq_hz,
            probe,
            canal,
            into_drum,
            mechanical,
            drum,
            ligaments,
            tendons,
            joints,
            sal,
            cochlea,
            perforation,
            cavity,
        }
    }

    /// The power balance at every frequency of the model's grid (one solve each).
    pub fn power_budget(&mut self, theta: &Theta) -> Result<Vec<PowerBalance>, SimError> {
        let freqs = self.model.config.frequencies.clone();
        freqs
            .iter()
            .map(|&f| {
                self.solve_at(theta, f)?;
                Ok(self.power_balance(theta, f))
            })
            .collect()
    }
}

/// The residual canal of `theta` at angular frequency `w`, loaded by drum pressure `p_l`
/// per unit flow into the drum.
fn line(air: &Air, theta: &Theta, w: f64, p_l: c64) -> Line {
    let (z, y) = air.line_zy(w, theta.canal_area());
    let (gamma, zc) = air::line_constants(z, y);
    Line { z, y, gamma, zc, p_l }
}

fn check(theta: &Theta) -> Result<(), SimError> {
    for (v, p) in theta.0.iter().zip(super::params::PARAMS.iter()) {
        if !p.physical(*v) {
            return Err(SimError::BadParameter { name: p.name, value: *v });
        }
    }
    Ok(())
}

/// Measured responses at one frequency from one solve, effects at the probe applied.
fn respond(m: &Model, theta: &Theta, fx: &Effects, freq_hz: f64, s: Solved) -> Response {
    let g = &m.config.geometry;
    let w = 2.0 * PI * freq_hz;
    let jw = c64::new(0.0, w);
    let line = line(&m.air, theta, w, s.p_drum);
    let (p_mic, _) = line.at(theta.mic_distance());
    // Stapes velocity as the LDV sees it: piston·cos θ + rocking at the spot·sin θ.
    let theta_ldv = theta.ldv_angle_deg().to_radians();
    let v_piston = jw * s.x_stapes;
    let v_rock = jw * s.phi_stapes * g.ldv_spot;
    let v_meas = v_piston * theta_ldv.cos() + v_rock * theta_ldv.sin();
    // Impedance at the plane, then moved by the probe offset along the same line,
    // then shunted by the leak.
    let (p0, u0) = line.at(theta.canal_length());
    let mut zec = p0 / u0;
    let dx = fx.probe_offset();
    if dx != 0.0 {
        zec = air::shift_impedance(zec, line.zc, line.gamma, dx);
    }
    let a = fx.leak_radius();
    if a > 0.0 {
        let l = g.leak_length;
        let mass = m.air.rho * (l + 1.7 * a) / (PI * a * a);
        let res = 8.0 * m.air.mu * l / (PI * a.powi(4));
        let z_leak = c64::new(res, w * mass);
        zec = zec * z_leak / (zec + z_leak);
    }
    Response {
        freq_hz,
        vst_over_p: v_meas / p_mic,
        vu_over_p: jw * s.umbo / p_mic,
        zec,
        z0: m.air.z0(theta.canal_area()),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn an_uncondensed_manubrium_drum_is_refused_naming_the_setting() {
        let mut config = ModelConfig { reduce_drum: false, ..ModelConfig::default() };
        config.geometry.tm_shape = DrumShape::MANUBRIUM;
        let Err(e) = Model::new(config) else { panic!("reduce_drum = false with the manubrium drum is refused") };
        assert!(matches!(e, SimError::DrumNotCondensed { shape: "Manubrium" }), "{e:?}");
        let msg = e.to_string();
        assert!(msg.contains("reduce_drum = false") && msg.contains("Manubrium"), "{msg}");
    }

    #[test]
    fn kept_solves_answer_only_runs_that_differ_after_the_solve_and_answer_them_exactly() {
        let model = Model::new(ModelConfig::default()).unwrap();
        let fresh = |theta: &Theta, fx: &Effects| model.runner().run(theta, fx).unwrap();
        let mut kept = model.runner();
        kept.remember(3);
        let base = Theta::nominal();
        let with = |name: &str, value: f64| {
            let mut t = base;
            t.0[super::super::params::PARAMS.iter().position(|p| p.name == name).unwrap()] = value;
            t
        };
        let effect = |name: &str, value: f64| {
            let mut fx = Effects::default();
            fx.set(name, value).unwrap();
            fx
        };
        // (run, effects, reused so far): every after-solve change reuses the base's
        // solves; anything inside the middle ear does not.
        let runs = [
            (base, Effects::default(), 0),
            (with("canal_length", 15e-3), Effects::default(), 1),
            (with("canal_area", 40e-6), Effects::default(), 2),
            (with("mic_distance", 3e-3), Effects::default(), 3),
            (with("ldv_angle", 20.0), Effects::default(), 4),
            (base, effect("probe_leak", 1e-4), 5),
            (with("cavity", 5e-6), Effects::default(), 5),
            (with("E_sal", 4e5), Effects::default(), 5),
            (with("cochlear_mass", 1e5), Effects::default(), 5),
            (base, effect("third_window", 1e6), 5),
            // The base is the oldest of the three kept now: gone.
            (base, Effects::default(), 5),
            (with("canal_length", 9e-3), Effects::default(), 6),
        ];
        for (k, (theta, fx, reused)) in runs.iter().enumerate() {
            let got = kept.run(theta, fx).unwrap();
            let want = fresh(theta, fx);
            for (a, b) in got.iter().zip(&want) {
                assert!(
                    a.vst_over_p == b.vst_over_p && a.vu_over_p == b.vu_over_p && a.zec == b.zec && a.z0 == b.z0,
                    "run {k} differs from a fresh runner's at {} Hz",
                    a.freq_hz
                );
            }
            assert_eq!(kept.solves_reused(), *reused, "runs answered from kept solves after run {k}");
        }
        // An unphysical row is refused even when its solve is kept.
        let mut bad = base;
        bad.0[8] = -1.0;
        assert!(matches!(kept.run(&bad, &Effects::default()), Err(SimError::BadParameter { name: "canal_area", .. })));
    }

    #[test]
    fn kept_drum_blocks_serve_only_runs_that_leave_the_drum_as_it_was() {
        // The default drum's loss is its own loss factor, so the Rayleigh damping of the
        // chain leaves the drum's block as it was; its stiffness and the cavity do not.
        let model = Model::new(ModelConfig::default()).unwrap();
        assert!(matches!(model.config.geometry.tm_loss, DrumLoss::LossFactor(_)));
        let nf = model.frequencies().len();
        let mut kept = model.runner();
        kept.remember(1);
        let base = Theta::nominal();
        let with = |name: &str, factor: f64| {
            let mut t = base;
            let i = super::super::params::PARAMS.iter().position(|p| p.name == name).unwrap();
            t.0[i] *= factor;
            t
        };
        let runs = [
            (base, 0),
            (with("E_sal", 1.2), nf),
            (with("E_ligaments", 0.8), nf),
            (with("E_tendons", 1.1), nf),
            (with("E_joints", 2.0), nf),
            (with("damping_beta", 1.5), nf),
            (with("cochlear_load", 0.7), nf),
            (with("E_eardrum", 1.1), 0),
            (with("cavity", 0.5), 0),
        ];
        for (k, (theta, reused)) in runs.iter().enumerate() {
            let before = kept.drum_blocks_reused();
            let got = kept.run(theta, &Effects::default()).unwrap();
            let want = model.runner().run(theta, &Effects::default()).unwrap();
            for (a, b) in got.iter().zip(&want) {
                assert!(
                    a.vst_over_p == b.vst_over_p && a.vu_over_p == b.vu_over_p && a.zec == b.zec,
                    "run {k} differs from a fresh runner's at {} Hz",
                    a.freq_hz
                );
            }
            assert_eq!(kept.drum_blocks_reused() - before, *reused, "drum blocks reused by run {k}");
        }
        // A single solve outside a whole-grid run keeps nothing and reuses nothing.
        let mut plain = model.runner();
        plain.run(&base, &Effects::default()).unwrap();
        plain.run(&with("E_sal", 1.2), &Effects::default()).unwrap();
        assert_eq!(plain.drum_blocks_reused(), 0);
    }

    #[test]
    fn a_failed_symbolic_factorisation_names_the_system_and_faer_reason() {
        let e = SimError::SymbolicLu { unknowns: 42, source: faer::sparse::FaerError::OutOfMemory };
        assert_eq!(e.to_string(), "model setup failed: symbolic LU of the 42-unknown system: OutOfMemory");
        assert!(std::error::Error::source(&e).is_some(), "faer's error is the source");
    }
}
