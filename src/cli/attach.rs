//! `otofit attach`: store flows inside a masked model that answer some ears more sharply:
//! a full-measure flow (ears with every measure) and measure-set flows (ears with exactly
//! the groups a flow was trained on).

use std::path::{Path, PathBuf};

use anyhow::{Context, Result, bail};
use clap::Args;

use crate::npe::Npe;

/// Arguments of `otofit attach`.
#[derive(Args, Debug)]
pub struct AttachArgs {
    /// The model that answers every subset of measures (trained with masks); rewritten in
    /// place unless --out is given.
    #[arg(long)]
    pub model: PathBuf,
    /// The model that answers observations with every measure present: trained without
    /// masks on the same simulator, parameters and grid, and calibrated on its own
    /// (`otofit calibrate --tune`), since it brings its temperature and fit-check null.
    #[arg(long)]
    pub full: Option<PathBuf>,
    /// A model trained on some feature groups alone (`otofit train --measures`), calibrated
    /// on its own: it answers ears that give exactly those groups. May be repeated.
    #[arg(long)]
    pub measure_set: Vec<PathBuf>,
    /// Where to write the combined model (default: --model).
    #[arg(long)]
    pub out: Option<PathBuf>,
}

/// A flow to attach, refused unless calibrated: it answers with its own fit check.
fn calibrated(path: &Path, option: &str) -> Result<Npe> {
    let flow = Npe::load(path)?;
    if flow.header.fit_null.is_none() {
        bail!(
            "{option} {}: not calibrated (run `otofit calibrate --model {} --data D --tune` first: it answers with its own fit check)",
            path.display(),
            path.display()
        );
    }
    Ok(flow)
}

/// Runs `otofit attach`.
pub fn run(args: AttachArgs) -> Result<()> {
    if args.full.is_none() && args.measure_set.is_empty() {
        bail!("give --full or --measure-set (the flows to store in --model)");
    }
    let mut model = Npe::load(&args.model)?;
    if let Some(path) = &args.full {
        let full = calibrated(path, "--full")?;
        model.attach_full_measure(full).with_context(|| format!("--full {}", path.display()))?;
    }
    for path in &args.measure_set {
        let set = calibrated(path, "--measure-set")?;
        model.attach_measure_set(set).with_context(|| format!("--measure-set {}", path.display()))?;
    }
    let out = args.out.as_ref().unwrap_or(&args.model);
    model.save(out)?;
    if let Some(path) = &args.full {
        println!("{}: full-measure flow from {} attached", out.display(), path.display());
    }
    for path in &args.measure_set {
        println!("{}: measure-set flow from {} attached", out.display(), path.display());
    }
    Ok(())
}
