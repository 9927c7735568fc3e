//! `otofit attach`: store an unmasked model inside a masked one as its full-measure flow.

use std::path::PathBuf;

use anyhow::{Context, Result};
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
    pub full: PathBuf,
    /// Where to write the combined model (default: --model).
    #[arg(long)]
    pub out: Option<PathBuf>,
}

/// Runs `otofit attach`.
pub fn run(args: AttachArgs) -> Result<()> {
    let mut model = Npe::load(&args.model)?;
    let full = Npe::load(&args.full)?;
    if full.header.fit_null.is_none() {
        anyhow::bail!(
            "--full {}: not calibrated (run `otofit calibrate --model {} --data D --tune` first: it answers with its own fit check)",
            args.full.display(),
            args.full.display()
        );
    }
    model.attach_full_measure(full).with_context(|| format!("--full {}", args.full.display()))?;
    let out = args.out.as_ref().unwrap_or(&args.model);
    model.save(out)?;
    println!("{}: full-measure flow from {} attached", out.display(), args.full.display());
    Ok(())
}
