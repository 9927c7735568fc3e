//! `--drum`, `--drum-loss`, `--incus-lateral` and `--joint-pads`: the eardrum and chain
//! variants of docs/simulator.md ("The v2 eardrum", "A transmission-line drum", "The
//! incus across the stapes axis", "Joint pads as incompressible layers"), for reports only (`simulate --explain`,
//! `study reference`, `bench sim`). Datasets and
//! models always use the default drum (v8: the anatomical FE drum): a model trained on a
//! variant would be fit-checked against the default simulator.

use crate::sim::line_drum::LineTuning;
use crate::sim::{DrumLoss, DrumShape, Geometry, JointPads, ModelConfig, PARAMS, Theta};
use anyhow::{Result, bail};
use clap::{Args, ValueEnum};

#[derive(Args, Debug, Default)]
pub struct DrumOpts {
    /// Eardrum for the report: `anatomical` (the default since v8: the anatomical FE drum
    /// of `sim::anatomical_drum` on the chain's cited masses: elliptical outline, measured
    /// thickness, a manubrium strip, a compliant annulus, loss factor 0.2;
    /// docs/results/fe-drum.md), `line` (v6–v7's transmission-line drum of
    /// `sim::line_drum::LineTuning::v7`, tuned to the norms: loss factor η 0.77 unless
    /// --drum-loss is given, ossicle masses ×1.73; the nominal ear is its tuned one),
    /// `axisymmetric` (the v1–v5 ear: FE cone, Rayleigh loss, unscaled chain) or
    /// `manubrium` (v5's chain with flat-shell triangles attached along the manubrium;
    /// docs/simulator.md says why it was never the default).
    #[arg(long, value_enum)]
    pub drum: Option<DrumArg>,
    /// Eardrum loss for the report: `rayleigh` (E·(1 + jωβ), the default model's),
    /// `hysteretic` (η = 2π·1 kHz·β) or a fixed loss factor η (a number in (0, 10]).
    #[arg(long)]
    pub drum_loss: Option<String>,
    /// The incus also moves across the stapes axis, so the incudostapedial joint shears
    /// between two moving bodies (an experiment: docs/simulator.md "The
    /// incus across the stapes axis"); without it the joint's shear holds the stapes head
    /// to the ground, as in every model so far.
    #[arg(long)]
    pub incus_lateral: bool,
    /// The joints' cartilage as thin incompressible layers between bone faces, stiffer in
    /// compression and tilting than E·A/t by the bonded-layer shape factor (an
    /// experiment: docs/results/simulator.md, "Joint pads as incompressible layers"):
    /// `confined` (both joints), `imj` (the incudomallear joint only) or `unconfined`
    /// (E·A/t, every ear so far).
    #[arg(long, value_enum)]
    pub joint_pads: Option<JointPadsArg>,
}

#[derive(Clone, Copy, Debug, ValueEnum)]
pub enum JointPadsArg {
    Unconfined,
    Confined,
    Imj,
}

#[derive(Clone, Copy, Debug, ValueEnum)]
pub enum DrumArg {
    Axisymmetric,
    Manubrium,
    Line,
    Anatomical,
}

impl DrumOpts {
    pub fn is_set(&self) -> bool {
        self.drum.is_some() || self.drum_loss.is_some() || self.incus_lateral || self.joint_pads.is_some()
    }

    /// Extra least-squares starts for this drum (`study reference`): the drum's own
    /// nominal row, since the default model's posterior is drawn for the default ear.
    pub fn starts(&self) -> Vec<Vec<f64>> {
        match self.drum {
            Some(DrumArg::Axisymmetric | DrumArg::Manubrium | DrumArg::Line) => vec![self.nominal().0.to_vec()],
            _ => Vec::new(),
        }
    }

    /// The nominal ear of this drum (`simulate --explain` without --theta): the line's
    /// tuned tissue values, the v1–v5 values for the older FE drums, else the prior's.
    pub fn nominal(&self) -> Theta {
        match self.drum {
            Some(DrumArg::Line) => LineTuning::v7().theta(),
            Some(DrumArg::Axisymmetric | DrumArg::Manubrium) => {
                let row = v5_nominal();
                Theta(std::array::from_fn(|i| row[i]))
            }
            Some(DrumArg::Anatomical) | None => Theta::nominal(),
        }
    }

    /// Puts the chosen drum and loss into `config`.
    pub fn apply(&self, config: &mut ModelConfig) -> Result<()> {
        match self.drum {
            Some(DrumArg::Manubrium) => {
                config.geometry = Geometry { tm_shape: DrumShape::MANUBRIUM, ..Geometry::axisymmetric() }
            }
            Some(DrumArg::Axisymmetric) => config.geometry = Geometry::axisymmetric(),
            Some(DrumArg::Line) => config.geometry = Geometry::line(),
            // The default; --drum-loss below replaces η.
            Some(DrumArg::Anatomical) | None => {}
        }
        config.geometry.incus_lateral = self.incus_lateral;
        config.geometry.confine_joint_pads(match self.joint_pads {
            None | Some(JointPadsArg::Unconfined) => JointPads::Unconfined,
            Some(JointPadsArg::Confined) => JointPads::Confined,
            Some(JointPadsArg::Imj) => JointPads::ImjConfined,
        });
        if let Some(text) = &self.drum_loss {
            config.geometry.tm_loss = match text.as_str() {
                "rayleigh" => DrumLoss::Rayleigh,
                "hysteretic" => DrumLoss::Hysteretic { f_ref_hz: 1000.0 },
                _ => match text.parse::<f64>() {
                    Ok(eta) if eta > 0.0 && eta <= 10.0 => DrumLoss::LossFactor(eta),
                    _ => bail!("--drum-loss '{text}': expected rayleigh, hysteretic or a loss factor in (0, 10]"),
                },
            };
        }
        Ok(())
    }
}

/// The v1–v5 nominal row (tissue values of the axisymmetric ear, the rest the prior's
/// nominal).
fn v5_nominal() -> Vec<f64> {
    const V5: [(&str, f64); 7] = [
        ("E_ligaments", 5e6),
        ("E_tendons", 2e6),
        ("E_sal", 2e5),
        ("E_joints", 6e6),
        ("damping_beta", 7.5e-5),
        ("cochlear_load", 2.1e10),
        ("tm_viscoelastic", 0.0),
    ];
    PARAMS.iter().map(|p| V5.iter().find(|(n, _)| *n == p.name).map_or(p.nominal, |(_, v)| *v)).collect()
}
