//! `--drum` and `--drum-loss`: the eardrum variants of docs/simulator.md ("The v2
//! eardrum", "A transmission-line drum"), for reports only (`simulate --explain`,
//! `study reference`, `bench sim`). Datasets and
//! models always use the default drum: a model trained on a variant would be fit-checked
//! against the default simulator.

use crate::sim::line_drum::LineTuning;
use crate::sim::{DrumLoss, DrumShape, ModelConfig};
use anyhow::{Result, bail};
use clap::{Args, ValueEnum};

#[derive(Args, Debug, Default)]
pub struct DrumOpts {
    /// Eardrum for the report: `axisymmetric` (the default model's), `manubrium`
    /// (flat-shell triangles attached along the manubrium; not the default,
    /// docs/simulator.md says why) or `line` (session 12's transmission-line drum with
    /// the structure of its tuned point (a): line geometry, loss factor η 0.46 unless
    /// --drum-loss is given, ossicle masses ×1.21, annular-ligament geometry ×0.95;
    /// `sim::line_drum::LineTuning::POINT_A`).
    #[arg(long, value_enum)]
    pub drum: Option<DrumArg>,
    /// Eardrum loss for the report: `rayleigh` (E·(1 + jωβ), the default model's),
    /// `hysteretic` (η = 2π·1 kHz·β) or a fixed loss factor η (a number in (0, 10]).
    #[arg(long)]
    pub drum_loss: Option<String>,
}

#[derive(Clone, Copy, Debug, ValueEnum)]
pub enum DrumArg {
    Axisymmetric,
    Manubrium,
    Line,
}

impl DrumOpts {
    pub fn is_set(&self) -> bool {
        self.drum.is_some() || self.drum_loss.is_some()
    }

    /// Extra least-squares starts for this drum (`study reference`): the line drum's tuned
    /// tissue values (point (a)), since the default model's posterior is drawn for the
    /// axisymmetric drum.
    pub fn starts(&self) -> Vec<Vec<f64>> {
        match self.drum {
            Some(DrumArg::Line) => vec![LineTuning::POINT_A.theta().0.to_vec()],
            _ => Vec::new(),
        }
    }

    /// Puts the chosen drum and loss into `config`.
    pub fn apply(&self, config: &mut ModelConfig) -> Result<()> {
        match self.drum {
            Some(DrumArg::Manubrium) => config.geometry.tm_shape = DrumShape::MANUBRIUM,
            Some(DrumArg::Axisymmetric) => config.geometry.tm_shape = DrumShape::Axisymmetric,
            // The structure and loss factor of the tuned point; --drum-loss below replaces η.
            Some(DrumArg::Line) => LineTuning::POINT_A.apply(&mut config.geometry),
            None => {}
        }
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
