//! `otofit calibrate`: coverage and SBC ranks of a model on held-out simulations.

use crate::npe::{Dataset, Npe, calibrate::calibrate};
use anyhow::{Result, bail};
use clap::Args;
use std::path::PathBuf;

#[derive(Args, Debug)]
pub struct CalibrateArgs {
    #[arg(long)]
    pub model: PathBuf,
    /// Held-out dataset folder (not the training set).
    #[arg(long)]
    pub data: PathBuf,
    /// Rows used (the first N).
    #[arg(long, default_value_t = 200)]
    pub n: usize,
    #[arg(long, default_value_t = 500)]
    pub samples: usize,
    #[arg(long, default_value_t = 0)]
    pub seed: u64,
}

pub fn run(args: CalibrateArgs) -> Result<()> {
    let model = Npe::load(&args.model)?;
    let ds = Dataset::load(&args.data)?;
    if ds.feature_names != model.header.feature_names {
        bail!("{}: its features differ from the model's", args.data.display());
    }
    // Held-out x are noise-free simulations: add the model's training noise once.
    let noise = crate::sim::batch::Noise {
        std: model.header.noise_std.clone(),
        scale: model.header.noise_scale,
        seed: args.seed,
    };
    let rows: Vec<(Vec<f64>, Vec<f64>)> =
        ds.theta.iter().zip(&ds.x).take(args.n).enumerate().map(|(i, (t, x))| (t.clone(), noise.apply(x, i))).collect();
    let cal = calibrate(&model, &rows, args.samples, args.seed)?;
    println!("{}", serde_json::to_string(&cal)?);
    Ok(())
}
