//! `otofit infer`: a model and observations (CSV, header = feature names) → posterior
//! samples (CSV) and one JSON summary per observation on stdout.

use crate::dataset::read_csv;
use crate::npe::{Npe, Obs};
use anyhow::{Context, Result, bail};
use clap::Args;
use std::io::Write;
use std::path::PathBuf;

#[derive(Args, Debug)]
pub struct InferArgs {
    #[arg(long)]
    pub model: PathBuf,
    /// CSV: header row naming features, one row per observation.
    #[arg(long)]
    pub obs: PathBuf,
    #[arg(long, default_value_t = 1000)]
    pub samples: usize,
    #[arg(long, default_value_t = 0)]
    pub seed: u64,
    /// Samples CSV (parameter names; plus `obs` when OBS has several rows).
    #[arg(long)]
    pub out: PathBuf,
}

/// Lines up an observation table's columns with the model's features.
pub fn align(model: &Npe, header: &[String], row: &[f64]) -> Result<(Vec<f64>, Vec<bool>)> {
    let names = &model.header.feature_names;
    for h in header {
        if !names.contains(h) {
            bail!("column '{h}' is not a feature of this model (features look like '{}')", names[0]);
        }
    }
    let mut x = vec![f64::NAN; names.len()];
    let mut present = vec![false; names.len()];
    for (h, v) in header.iter().zip(row) {
        let i = names.iter().position(|n| n == h).unwrap_or(0);
        x[i] = *v;
        present[i] = v.is_finite();
    }
    Ok((x, present))
}

pub fn run(args: InferArgs) -> Result<()> {
    if args.samples == 0 || args.samples > 1_000_000 {
        bail!("--samples must be between 1 and 1000000");
    }
    let model = Npe::load(&args.model)?;
    let table = read_csv(&args.obs)?;
    if table.rows.is_empty() {
        bail!("{}: no observation rows", args.obs.display());
    }
    let many = table.rows.len() > 1;
    let names: Vec<&str> = model.params().iter().map(|p| p.name.as_str()).collect();
    let mut out = String::new();
    out.push_str(&if many { format!("obs,{}\n", names.join(",")) } else { format!("{}\n", names.join(",")) });
    let stdout = std::io::stdout();
    for (r, row) in table.rows.iter().enumerate() {
        let (x, present) =
            align(&model, &table.header, row).with_context(|| format!("{}: row {}", args.obs.display(), r + 1))?;
        if crate::discrepancy::fitcheck::simulator_for(&model).is_ok()
            && let Some((_, i, v)) = crate::sim::output::implausible(&x, &present).first()
        {
            bail!(
                "{}: row {}: {} = {v} is outside the physical range of a human ear (phases in rad, magnitudes as log10 of m/s/Pa and Pa·s/m³)",
                args.obs.display(),
                r + 1,
                model.header.feature_names[*i]
            );
        }
        let inf = model
            .infer(&Obs { x: &x, present: Some(&present) }, args.samples, args.seed)
            .with_context(|| format!("observation {}", r + 1))?;
        for s in &inf.samples {
            let vals: Vec<String> = s.iter().map(|v| format!("{v:e}")).collect();
            if many {
                out.push_str(&format!("{r},"));
            }
            out.push_str(&vals.join(","));
            out.push('\n');
        }
        let mut differential = crate::npe::normal::read(model.params(), &inf.samples);
        let fit = match crate::discrepancy::fitcheck::fit_check(&model, &x, &present, &inf) {
            Ok(f) => {
                if f.ok == Some(false) {
                    crate::npe::normal::withdraw(&mut differential, f.reason.as_deref().unwrap_or_default());
                }
                serde_json::json!(f)
            }
            Err(e) => serde_json::json!({ "ok": null, "reason": e.to_string() }),
        };
        let json = serde_json::json!({ "observation": r, "fit": fit, "parameters": inf.summaries, "differential": differential, "timing_ms": { "sample": inf.sample_ms, "map": inf.map_ms } });
        writeln!(stdout.lock(), "{json}")?;
    }
    let tmp = args.out.with_extension("tmp");
    std::fs::write(&tmp, out).with_context(|| format!("cannot write {}", tmp.display()))?;
    std::fs::rename(&tmp, &args.out)?;
    Ok(())
}
