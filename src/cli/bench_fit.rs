//! `otofit bench fit`: how the trust layer of an inference behaves — the fit check's
//! false-alarm rate on the model's own simulated ears, its detection rate on ears with a
//! strong hidden effect, and the differential reading of ears at the centre of every
//! normal range. Numbers for the README, measured, not asserted.

use crate::discrepancy::fitcheck::fit_check;
use crate::npe::normal::{Differential, NORMAL, read};
use crate::npe::{Npe, Obs};
use crate::sim::batch::{Design, Noise, run_rows};
use crate::sim::{EFFECTS, Effects, PARAMS};
use anyhow::{Result, bail};
use serde_json::json;
use std::path::Path;

/// Each effect at the end of its range where it changes the spectra most (since v3 the
/// cavity and the eardrum's viscoelasticity are parameters of every model, not hidden).
const STRONG: [(&str, f64); 4] =
    [("probe_offset", 3e-3), ("probe_leak", 0.5e-3), ("ldv_angle", 60.0), ("cochlear_mass", 1e6)];

struct Outcome {
    ok: Option<bool>,
    chi2: f64,
    worst: f64,
    readings: Vec<Differential>,
}

fn infer_one(npe: &Npe, x: &[f64], present: &[bool], seed: u64) -> Result<Outcome> {
    let inf = npe.infer(&Obs { x, present: Some(present) }, 1000, seed)?;
    let fit = fit_check(npe, x, present, &inf)?;
    let worst = fit.worst_measure.as_ref().map_or(0.0, |w| w.1);
    Ok(Outcome { ok: fit.ok, chi2: fit.reduced_chi2, worst, readings: read(npe.params(), &inf.samples) })
}

fn median(v: &[Outcome], f: impl Fn(&Outcome) -> f64) -> f64 {
    crate::stats::median_upper(&crate::stats::sorted(v.iter().map(f).collect()))
}

fn rate(v: &[Outcome], f: impl Fn(&Outcome) -> bool) -> f64 {
    v.iter().filter(|o| f(o)).count() as f64 / v.len().max(1) as f64
}

fn simulate(npe: &Npe, design: &Design, rows: &[Vec<f64>], seed: u64) -> Result<Vec<Vec<f64>>> {
    let model = crate::discrepancy::fitcheck::simulator_for(npe)?;
    let noise = Noise { std: npe.header.noise_std.clone(), scale: 1.0, seed };
    Ok(run_rows(model, design, rows, 0, Some(&noise)).into_iter().filter_map(|r| r.ok()).collect())
}

/// `measures`: the feature groups given (e.g. "impedance,absorbance"); all when empty.
pub fn run(model: &Path, cases: usize, seed: u64, measures: &str) -> Result<()> {
    if !(5..=10_000).contains(&cases) {
        bail!("--cases must be 5..=10000 (got {cases})");
    }
    let npe = Npe::load(model)?;
    if npe.header.fit_null.is_none() {
        bail!("{} has no fit-check null: run `otofit calibrate --tune` first", model.display());
    }
    let f = npe.header.feature_names.len();
    let mut present = vec![measures.is_empty(); f];
    for name in measures.split(',').filter(|m| !m.is_empty()) {
        let Some(g) = npe.header.groups.iter().find(|g| g.name == name.trim()) else {
            let known: Vec<&str> = npe.header.groups.iter().map(|g| g.name.as_str()).collect();
            bail!("--measures: unknown group '{name}' (known: {})", known.join(", "));
        };
        g.features.iter().for_each(|&i| present[i] = true);
    }
    if !measures.is_empty() {
        println!("measures given: {measures}");
    }
    let base = Design::default();
    // 1. The null: prior draws, no effect, 1× noise (seeds the calibration never used).
    let rows = base.draw(seed ^ 0xBE7C, 0, cases);
    let null: Vec<Outcome> = simulate(&npe, &base, &rows, seed)?
        .iter()
        .enumerate()
        .map(|(k, x)| infer_one(&npe, x, &present, seed + k as u64))
        .collect::<Result<_>>()?;
    let null_ok = rate(&null, |o| o.ok == Some(true));
    println!(
        "fit.ok on {} held-out simulations (null): {:.3} (median χ²ν {:.2}, worst measure {:.2})",
        null.len(),
        null_ok,
        median(&null, |o| o.chi2),
        median(&null, |o| o.worst)
    );
    // 2. Strong hidden effects.
    let mut detect = Vec::new();
    for (name, value) in STRONG {
        let mut fixed = Effects::default();
        fixed.set(name, value).map_err(anyhow::Error::msg)?;
        let design = Design { fixed, varied: vec![] };
        let out: Vec<Outcome> = simulate(&npe, &design, &rows, seed ^ 0xEF)?
            .iter()
            .enumerate()
            .map(|(k, x)| infer_one(&npe, x, &present, seed + k as u64))
            .collect::<Result<_>>()?;
        let flagged = rate(&out, |o| o.ok == Some(false));
        let unit = EFFECTS.iter().find(|e| e.name == name).map_or("", |e| e.unit);
        println!(
            "fit.ok false with {name} = {value:e} {unit}: {flagged:.3} of {} (median χ²ν {:.2}, worst measure {:.2})",
            out.len(),
            median(&out, |o| o.chi2),
            median(&out, |o| o.worst)
        );
        detect.push(json!({ "effect": name, "value": value, "flagged": flagged, "cases": out.len() }));
    }
    // 3. Ears at the centre of every normal range (geometric centre), noisy and noise-free.
    let centre: Vec<f64> = PARAMS
        .iter()
        .map(|p| NORMAL.iter().find(|r| r.name == p.name).map_or(p.nominal, |r| (r.low * r.high).sqrt()))
        .collect();
    let model_sim = crate::discrepancy::fitcheck::simulator_for(&npe)?;
    let clean = run_rows(model_sim, &base, std::slice::from_ref(&centre), 0, None).remove(0)?;
    let noise = Noise { std: npe.header.noise_std.clone(), scale: 1.0, seed: seed ^ 0xCE };
    let mut centred = vec![infer_one(&npe, &clean, &present, seed)?];
    for k in 0..cases {
        centred.push(infer_one(&npe, &noise.apply(&clean, k), &present, seed + k as u64)?);
    }
    let benign = |o: &Outcome| o.readings.iter().all(|d| d.reading == "within" || d.reading == "undetermined");
    let centred_ok = rate(&centred, benign);
    println!(
        "ears at the centre of the normal ranges reading within/undetermined for every parameter: {centred_ok:.3} of {} \
         (noise-free: {})",
        centred.len(),
        benign(&centred[0])
    );
    for d in &centred[0].readings {
        println!("  noise-free centre ear {:<14} {:<12} p_within {:.2}", d.name, d.reading, d.p_within);
    }
    // 4. The nominal ear, noise-free (the openapi.yaml example).
    let nominal = run_rows(model_sim, &base, &[crate::sim::Theta::nominal().0.to_vec()], 0, None).remove(0)?;
    let nom = infer_one(&npe, &nominal, &present, seed)?;
    println!("nominal ear (openapi example): fit.ok {:?}, benign readings {}", nom.ok, benign(&nom));
    for d in &nom.readings {
        println!(
            "  nominal {:<14} {:<12} p_below {:.2} p_within {:.2} p_above {:.2}",
            d.name, d.reading, d.p_below, d.p_within, d.p_above
        );
    }
    let doc = json!({
        "model": model.display().to_string(),
        "cases": cases,
        "measures": if measures.is_empty() { "all" } else { measures },
        "null_fit_ok": null_ok,
        "hidden_effects": detect,
        "centre_benign": centred_ok,
        "nominal_fit_ok": nom.ok,
        "nominal_benign": benign(&nom),
    });
    println!("{doc}");
    Ok(())
}
