//! Can any fit check see an effect the parameters can absorb? For each optional effect at
//! the end of its range, noisy simulations (prior draws, the model's training noise) are
//! fitted by least squares *without* the effect, from the truth and the nominal point.
//! That best fit bounds every posterior-predictive check from below: where its reduced
//! χ² stays under the model's null threshold, no fit check can flag the case, and the
//! printed tissue-parameter errors say what the absorbed effect costs.
//!
//! `cargo run --example identifiability_floor -- [cases]` (default 40; ~1 s per case).

use otofit::discrepancy::fit::{Observation, fit, residuals};
use otofit::npe::Npe;
use otofit::sim::batch::{Design, Noise, run_rows};
use otofit::sim::{Effects, Model, ModelConfig, N_TISSUE, PARAMS};
use rayon::prelude::*;

/// The optional effects at the end of their range (since v5 the LDV beam angle and the
/// cochlear fluid mass are parameters, inferred with every ear: docs/simulator.md "v5").
const STRONG: [(&str, f64); 3] = [("none", 0.0), ("probe_offset", 3e-3), ("probe_leak", 0.5e-3)];

fn median(mut v: Vec<f64>) -> f64 {
    v.sort_by(f64::total_cmp);
    v[v.len() / 2]
}

fn main() -> Result<(), Box<dyn std::error::Error>> {
    let cases: usize = std::env::args().nth(1).map_or(Ok(40), |s| s.parse())?;
    let npe = Npe::load(&std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("models/default.otofit"))?;
    let threshold = npe.header.fit_null.as_ref().map_or(f64::INFINITY, |n| n.reduced_chi2);
    let std = npe.header.noise_std.clone();
    let model = Model::new(ModelConfig::default())?;
    let base = Design::default();
    let rows = base.draw(0xBE7C, 0, cases.max(1));
    let nominal: Vec<f64> = PARAMS.iter().map(|p| p.nominal).collect();
    println!("null threshold (model's fit check, all measures): reduced χ² {threshold:.2}");
    for (name, value) in STRONG {
        let mut fixed = Effects::default();
        if name != "none" {
            fixed.set(name, value)?;
        }
        let noise = Noise { std: std.clone(), scale: 1.0, seed: 0xEF };
        let xs = run_rows(&model, &Design { fixed, varied: vec![] }, &rows, 0, Some(&noise));
        let out: Vec<(f64, Vec<f64>)> = xs
            .par_iter()
            .zip(&rows)
            .filter_map(|(x, row)| {
                let obs = Observation { x: x.as_ref().ok()?.clone(), sigma: std.clone() };
                let best = fit(&model, &base, &[row.clone(), nominal.clone()], &obs, 60)?;
                residuals(&mut model.runner(), &base, &best.row, &obs)?;
                let err = (0..N_TISSUE).map(|i| (best.row[i].log10() - row[i].log10()).abs()).collect();
                Some((best.reduced_chi2(), err))
            })
            .collect();
        let flagged = out.iter().filter(|o| o.0 > threshold).count() as f64 / out.len().max(1) as f64;
        let errs: Vec<String> =
            (0..N_TISSUE).map(|i| format!("{:.2}", median(out.iter().map(|o| o.1[i]).collect()))).collect();
        println!(
            "{name:14} {value:8.1e}: best-fit χ²ν median {:.2}, above the threshold in {flagged:.2} of {}; \
             median |Δlog10| of the tissue parameters {}",
            median(out.iter().map(|o| o.0).collect()),
            out.len(),
            errs.join(" ")
        );
    }
    Ok(())
}
