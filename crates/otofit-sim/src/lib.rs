//! The FE middle-ear simulator: θ (7 tissue parameters, 3 measurement-geometry nuisances,
//! the cavity volume and the drum's viscoelasticity) + optional effects → 350 features
//! (seven measures on a log-frequency grid).
//!
//! Parts: the residual canal as an exact viscothermal line (`air`; its FE twin `canal`,
//! a 1D Webster-horn FE, verifies it), `shell` (axisymmetric
//! conical shell FE of the eardrum), ossicles as rigid bodies with connector springs,
//! coupled in `model` and solved by `system` (faer sparse LU, symbolic factorisation
//! shared by all frequencies and parameter sets). `batch` runs many sets on rayon.
//! No I/O here: the CLI and the service do that.

pub mod air;
pub mod anatomical_drum;
pub mod batch;
pub mod canal;
pub mod drum;
pub mod drum_mesh;
pub mod ear_effects;
pub mod line_drum;
pub mod memo;
pub mod mode_cache;
pub mod model;
pub mod output;
pub mod params;
pub mod shell;
pub mod system;
pub mod tri_shell;

pub use model::{
    DrumLoss, DrumShape, Geometry, JointPad, JointPads, Model, ModelConfig, PowerBalance, Preset, Response, Runner,
    SimError, log_grid,
};
pub use params::{EFFECTS, Effects, N_EFFECTS, N_PARAMS, N_TISSUE, PARAMS, Theta};

/// Simulates one parameter set into its feature vector.
pub fn simulate(runner: &mut Runner<'_>, theta: &Theta, effects: &Effects) -> Result<Vec<f64>, SimError> {
    Ok(output::features(&runner.run(theta, effects)?))
}
