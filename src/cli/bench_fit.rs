//! `otofit bench fit`: how the trust layer of an inference behaves — the fit check's
//! false-alarm rate on the model's own simulated ears, its detection rate on ears with a
//! strong hidden effect, and the differential reading of ears at the centre of every
//! normal range, and how often normal ears with a hidden effect get a false finding while
//! the fit looks fine. Numbers for the README, measured, not asserted.

use crate::discrepancy::fitcheck::fit_check;
use crate::npe::normal::{Differential, NORMAL, read};
use crate::npe::{Npe, Obs};
use crate::sim::batch::{Design, Noise, run_rows};
use crate::sim::{EFFECTS, Effects, PARAMS};
use anyhow::{Result, anyhow, bail};
use serde_json::json;
use std::path::Path;

/// Each effect at the end of its range where it changes the spectra most. The cavity and
/// the eardrum's viscoelasticity (v3), the LDV beam angle and the cochlear fluid mass (v5)
/// became parameters: for a model that infers one, its ears get that value as a parameter
/// instead of a hidden effect, so the rows stay comparable across model versions.
const STRONG: [(&str, f64); 4] =
    [("probe_offset", 3e-3), ("probe_leak", 0.5e-3), ("ldv_angle", 60.0), ("cochlear_mass", 1e6)];

/// The design and rows that put `name` at `value`: an effect fixed for every row, or a
/// parameter column set in each row.
fn with_strong(name: &str, value: f64, rows: &[Vec<f64>]) -> Result<(Design, Vec<Vec<f64>>)> {
    let mut fixed = Effects::default();
    let mut rows = rows.to_vec();
    if let Some(k) = PARAMS.iter().position(|p| p.name == name) {
        rows.iter_mut().for_each(|r| r[k] = value);
    } else if name != "none" {
        fixed.set(name, value)?;
    }
    Ok((Design { fixed, varied: vec![] }, rows))
}

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

/// Infers each simulated ear, case `k` with seed `seed + k`.
fn infer_all(npe: &Npe, xs: &[Vec<f64>], present: &[bool], seed: u64) -> Result<Vec<Outcome>> {
    xs.iter().enumerate().map(|(k, x)| infer_one(npe, x, present, seed + k as u64)).collect()
}

/// Whether every parameter reads as within its normal range or undetermined: what a
/// normal ear should get.
fn benign(o: &Outcome) -> bool {
    o.readings.iter().all(|d| d.reading == "within" || d.reading == "undetermined")
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
    let present = present(&npe, measures)?;
    // Seeds the calibration never used; the same prior draws with and without effects.
    let rows = Design::default().draw(seed ^ 0xBE7C, 0, cases);
    let null_ok = null(&npe, &rows, &present, seed)?;
    let detect = hidden_effects(&npe, &rows, &present, seed)?;
    let centred_ok = centre(&npe, &present, cases, seed)?;
    let nom = nominal(&npe, &present, seed)?;
    let findings = false_findings(&npe, &present, cases, seed)?;
    let doc = json!({
        "model": model.display().to_string(),
        "cases": cases,
        "measures": if measures.is_empty() { "all" } else { measures },
        "null_fit_ok": null_ok,
        "hidden_effects": detect,
        "centre_benign": centred_ok,
        "nominal_fit_ok": nom.ok,
        "nominal_benign": benign(&nom),
        "normal_ears": findings,
    });
    println!("{doc}");
    Ok(())
}

/// Which features are given: those of the named groups, or all.
fn present(npe: &Npe, measures: &str) -> Result<Vec<bool>> {
    let names: Vec<&str> = measures.split(',').filter(|m| !m.is_empty()).collect();
    let present = npe.header.features_of_groups(&names).map_err(|e| anyhow!("--measures: {e}"))?;
    if !measures.is_empty() {
        println!("measures given: {measures}");
    }
    Ok(present)
}

/// (1) The null: prior draws, no effect, 1× noise. Returns the fit.ok rate.
fn null(npe: &Npe, rows: &[Vec<f64>], present: &[bool], seed: u64) -> Result<f64> {
    let null = infer_all(npe, &simulate(npe, &Design::default(), rows, seed)?, present, seed)?;
    let null_ok = rate(&null, |o| o.ok == Some(true));
    println!(
        "fit.ok on {} held-out simulations (null): {:.3} (median χ²ν {:.2}, worst measure {:.2})",
        null.len(),
        null_ok,
        median(&null, |o| o.chi2),
        median(&null, |o| o.worst)
    );
    Ok(null_ok)
}

/// (2) Each strong hidden effect on the null's draws: how often the fit check flags it.
fn hidden_effects(npe: &Npe, rows: &[Vec<f64>], present: &[bool], seed: u64) -> Result<Vec<serde_json::Value>> {
    let mut detect = Vec::new();
    for (name, value) in STRONG {
        let (design, rows) = with_strong(name, value, rows)?;
        let out = infer_all(npe, &simulate(npe, &design, &rows, seed ^ 0xEF)?, present, seed)?;
        let flagged = rate(&out, |o| o.ok == Some(false));
        let unit = EFFECTS.iter().map(|e| (e.name, e.unit)).chain(PARAMS.iter().map(|p| (p.name, p.unit)));
        let unit = unit.into_iter().find(|(n, _)| *n == name).map_or("", |(_, u)| u);
        println!(
            "fit.ok false with {name} = {value:e} {unit}: {flagged:.3} of {} (median χ²ν {:.2}, worst measure {:.2})",
            out.len(),
            median(&out, |o| o.chi2),
            median(&out, |o| o.worst)
        );
        detect.push(json!({ "effect": name, "value": value, "flagged": flagged, "cases": out.len() }));
    }
    Ok(detect)
}

/// (3) Ears at the centre of every normal range (geometric centre), noise-free and with
/// `cases` noise draws: how often every reading is benign.
fn centre(npe: &Npe, present: &[bool], cases: usize, seed: u64) -> Result<f64> {
    let centre = crate::npe::normal::centre_row();
    let model_sim = crate::discrepancy::fitcheck::simulator_for(npe)?;
    let clean = run_rows(model_sim, &Design::default(), std::slice::from_ref(&centre), 0, None).remove(0)?;
    let noise = Noise { std: npe.header.noise_std.clone(), scale: 1.0, seed: seed ^ 0xCE };
    let mut centred = vec![infer_one(npe, &clean, present, seed)?];
    for k in 0..cases {
        centred.push(infer_one(npe, &noise.apply(&clean, k), present, seed + k as u64)?);
    }
    let centred_ok = rate(&centred, benign);
    println!(
        "ears at the centre of the normal ranges reading within/undetermined for every parameter: {centred_ok:.3} of {} \
         (noise-free, the openapi example: {})",
        centred.len(),
        benign(&centred[0])
    );
    for d in &centred[0].readings {
        println!("  noise-free centre ear {:<14} {:<12} p_within {:.2}", d.name, d.reading, d.p_within);
    }
    Ok(centred_ok)
}

/// (4) The simulator's nominal ear, noise-free: cochlear_load on its normal range's lower
/// limit (v1–v5: damping_beta too).
fn nominal(npe: &Npe, present: &[bool], seed: u64) -> Result<Outcome> {
    let model_sim = crate::discrepancy::fitcheck::simulator_for(npe)?;
    let nominal =
        run_rows(model_sim, &Design::default(), &[crate::sim::Theta::nominal().0.to_vec()], 0, None).remove(0)?;
    let nom = infer_one(npe, &nominal, present, seed)?;
    println!(
        "nominal ear (cochlear_load on its normal range's lower limit): fit.ok {:?}, benign readings {}",
        nom.ok,
        benign(&nom)
    );
    for d in &nom.readings {
        println!(
            "  nominal {:<14} {:<12} p_below {:.2} p_within {:.2} p_above {:.2}",
            d.name, d.reading, d.p_below, d.p_within, d.p_above
        );
    }
    Ok(nom)
}

/// (5) Normal ears — every tissue value drawn log-uniformly inside its normal range, the
/// nuisances from the prior — with no effect and with each strong hidden effect: how
/// often the fit check flags them, and how often the answer names a finding (below or
/// above) while `fit.ok` is true. Every such finding is false (the truth is within), and
/// it is the harm the fit check exists to prevent: a confident wrong reading.
fn false_findings(npe: &Npe, present: &[bool], cases: usize, seed: u64) -> Result<Vec<serde_json::Value>> {
    use rand::{Rng, SeedableRng};
    let mut rows = Design::default().draw(seed ^ 0x40F, 0, cases);
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(seed ^ 0x40F);
    for row in rows.iter_mut() {
        for (k, p) in PARAMS.iter().enumerate() {
            if let Some(r) = NORMAL.iter().find(|r| r.name == p.name) {
                let u: f64 = rng.random();
                row[k] = (r.low.ln() + u * (r.high / r.low).ln()).exp();
            }
        }
    }
    let mut out = Vec::new();
    for (name, value) in std::iter::once(("none", 0.0)).chain(STRONG) {
        let (design, rows) = with_strong(name, value, &rows)?;
        let res = infer_all(npe, &simulate(npe, &design, &rows, seed ^ 0xF1)?, present, seed)?;
        let flagged = rate(&res, |o| o.ok == Some(false));
        let false_finding = rate(&res, |o| o.ok == Some(true) && !benign(o));
        let mut which = std::collections::BTreeMap::<String, usize>::new();
        for o in res.iter().filter(|o| o.ok == Some(true)) {
            for d in o.readings.iter().filter(|d| d.reading == "below" || d.reading == "above") {
                *which.entry(format!("{} {}", d.name, d.reading)).or_default() += 1;
            }
        }
        let listed: Vec<String> = which.iter().map(|(k, v)| format!("{k} {v}")).collect();
        println!(
            "normal ears, effect {name}: fit.ok false {flagged:.3}, false finding with fit.ok true {false_finding:.3} of {} ({})",
            res.len(),
            if listed.is_empty() { "none".to_string() } else { listed.join(", ") }
        );
        out.push(json!({ "effect": name, "value": value, "flagged": flagged, "false_finding": false_finding,
            "findings": which, "cases": res.len() }));
    }
    Ok(out)
}
