//! The discrepancy workflow on the command line, and its benchmark.

use crate::discrepancy::workflow::{Settings, diagnose, null_thresholds, stored_thresholds};
use crate::discrepancy::{self, Verdict};
use crate::sim::batch::{Design, Noise, default_noise_std, run_rows};
use crate::sim::params::{EFFECTS, N_EFFECTS, N_PARAMS};
use crate::sim::{Model, ModelConfig};
use anyhow::{Context, Result, bail};
use clap::Args;
use std::path::{Path, PathBuf};
use std::time::Instant;

/// Arguments of `otofit diagnose`.
#[derive(Args, Debug)]
pub struct DiagnoseArgs {
    /// Base model (trained on otofit's simulator without effects).
    #[arg(long)]
    pub model: PathBuf,
    /// One observation: CSV with a header of all the model's feature names.
    #[arg(long)]
    pub obs: PathBuf,
    /// Report folder (created): report.html, report.json, the figures and, with an
    /// extension, the extended model.
    #[arg(long)]
    pub out: PathBuf,
    /// `all` or a comma-separated list of effects.
    #[arg(long, default_value = "all")]
    pub candidates: String,
    /// Name the effect but do not extend and retrain.
    #[arg(long)]
    pub no_extend: bool,
    /// Size of the extended model's training set, and its epochs.
    #[arg(long, default_value_t = 10_000)]
    pub train_rows: usize,
    /// Epochs of the extended model's training (1..=5000, as a diagnose job).
    #[arg(long, default_value_t = 1000)]
    pub max_epochs: usize,
    /// Effect-free simulations for the null distribution of the statistics, when it is
    /// measured for this ear (the model stores none for these measures, or --measure-null).
    #[arg(long, default_value_t = 40)]
    pub null_cases: usize,
    /// Measure the null for this ear even when the model stores one (slower).
    #[arg(long)]
    pub measure_null: bool,
    /// Seed of the null simulations, the fits' starts and the extended training.
    #[arg(long, default_value_t = 0)]
    pub seed: u64,
}

/// Runs `otofit diagnose`.
pub fn run(args: DiagnoseArgs) -> Result<()> {
    use crate::plot::diagnosis::{Links, write_report};
    // The diagnose job's limits (jobs::limits).
    use crate::jobs::limits::{EPOCHS, NULL_CASES, TRAIN_ROWS, check};
    check(&NULL_CASES, args.null_cases).map_err(|m| anyhow::anyhow!("--null-cases {m}"))?;
    check(&TRAIN_ROWS, args.train_rows).map_err(|m| anyhow::anyhow!("--train-rows {m}"))?;
    check(&EPOCHS, args.max_epochs).map_err(|m| anyhow::anyhow!("--max-epochs {m}"))?;
    let candidates = effect_list("--candidates", &args.candidates)?;
    let base = crate::npe::Npe::load(&args.model)?;
    let table = crate::dataset::read_csv(&args.obs)?;
    let Some(row) = table.rows.first() else { bail!("{}: no observation row", args.obs.display()) };
    // Absent columns are measures not taken (NaN): the base model must accept the subset.
    let (x, _) = super::infer::align(&base, &table.header, row)?;
    let model = Model::new(ModelConfig::default())?;
    let s = Settings {
        candidates,
        extend: !args.no_extend,
        train_rows: args.train_rows,
        max_epochs: args.max_epochs,
        null_cases: args.null_cases,
        measure_null: args.measure_null,
        seed: args.seed,
        ..Settings::default()
    };
    let stages = super::progress::Progress::stages("diagnose");
    let n = crate::discrepancy::workflow::STAGES.len();
    let report = diagnose(&model, &base, &x, &s, &mut |m| {
        stages.message(&format!("stage {} of {n}: {m}", crate::discrepancy::workflow::stage_of(m) + 1))
    })?;
    stages.finish();
    let model_path = args.out.join("extended.otofit");
    let links = Links {
        figure: &|name| name.to_string(),
        model: (model_path.clone(), model_path.display().to_string()),
        page: None,
    };
    write_report(&args.out, &report, &links)?;
    println!("verdict: {:?}{}", report.verdict, report.named.map(|n| format!(" ({n})")).unwrap_or_default());
    println!("alarm thresholds: {}", report.null.describe());
    for b in &report.before.bands {
        println!("  {}", b.describe());
    }
    if let (Some(a), Some(p)) = (&report.after, &report.effect_posterior) {
        println!(
            "reduced χ² {:.2} → {:.2}; {} median {:.3e} [{:.3e}, {:.3e}] {}",
            report.before.reduced_chi2, a.reduced_chi2, p.effect, p.median, p.q05, p.q95, p.unit
        );
    }
    Ok(())
}

/// Effects by a flag's value: `all`, or comma-separated names (an unknown one named).
fn effect_list(flag: &str, value: &str) -> Result<Vec<usize>> {
    if value == "all" {
        return Ok((0..N_EFFECTS).collect());
    }
    value
        .split(',')
        .map(|c| {
            crate::sim::Effects::index(c.trim())
                .with_context(|| format!("{flag}: unknown effect '{c}' (known: {})", crate::jobs::effect_names()))
        })
        .collect()
}

/// Rates of the workflow on hidden-effect cases with the default model as the base:
/// naming accuracy and 90 % coverage per effect (naming by the extended fit, no retrain
/// per case), false alarms on effect-free cases, and the wall time of one full diagnosis
/// with the retrain.
/// `effects` (`all` or names) are the effects hidden in turn; every effect stays a
/// candidate. `full`: also time one full diagnosis with its retrain. `out`: a folder for
/// cases.json, every hidden case.
pub fn bench(cases: usize, clean: usize, seed: u64, effects: &str, full: bool, out: Option<&Path>) -> Result<()> {
    let hidden = effect_list("--effects", effects)?;
    if let Some(dir) = out {
        std::fs::create_dir_all(dir).with_context(|| format!("--out {}: cannot create it", dir.display()))?;
    }
    let model = Model::new(ModelConfig::default())?;
    let base = crate::npe::Npe::load(std::path::Path::new("models/default.otofit"))?;
    let noise = Noise { std: default_noise_std(&model), scale: 1.0, seed };
    let t0 = Instant::now();
    let s = bench_settings(&model, &base, seed)?;
    let draw = Cases { model: &model, noise: &noise, seed };
    false_alarms(&draw, &base, &s, clean)?;
    println!("visible: the effect's noise-free signature Σ(Δx/σ)² > {VISIBLE}");
    println!(
        "{:<18} {:>5} {:>8} {:>7} {:>11} {:>10} {:>9} {:>9}  named % by fifth of the range (weakest first), detection limit, other verdicts, named or read (the differential's finding associated with the effect, when the ear's own tissue does not explain it)",
        "effect", "cases", "named %", "visible", "named vis %", "cover90 %", "χ²ν base", "χ²ν fit"
    );
    let mut records = vec![];
    for e in hidden {
        records.extend(effect_rates(&draw, &base, &s, e, cases)?);
    }
    if let Some(dir) = out {
        let names: Vec<&str> = crate::sim::PARAMS.iter().map(|p| p.name).collect();
        let doc = serde_json::json!({ "seed": seed, "params": names, "visible": VISIBLE, "cases": records });
        std::fs::write(dir.join("cases.json"), serde_json::to_vec_pretty(&doc)?)?;
    }
    if full {
        full_diagnosis(&draw, &base, seed)?;
    }
    println!("wall {:.0} s", t0.elapsed().as_secs_f64());
    Ok(())
}

/// The benchmarks' settings: no retrain per case, and alarm thresholds shared by every
/// case: the model's stored null when it was measured on at least as many effect-free
/// ears as the benchmark would use, else measured once here (1× noise).
pub(super) fn bench_settings(model: &Model, base: &crate::npe::Npe, seed: u64) -> Result<Settings> {
    let noise = Noise { std: default_noise_std(model), scale: 1.0, seed };
    let t0 = Instant::now();
    let mut s = Settings { extend: false, null_cases: NULL_CASES, seed, ..Settings::default() };
    let all = vec![true; base.header.feature_names.len()];
    let q = 100.0 * crate::discrepancy::workflow::ALARM_QUANTILE;
    let (t, whence) = match stored_thresholds(base, &all, &s).filter(|(_, cases)| *cases >= NULL_CASES) {
        Some((t, cases)) => (t, format!("the model's, {cases} effect-free cases")),
        None => {
            let (t, cases) = null_thresholds(model, base, &noise, &all, &s)?;
            (t, format!("{cases} effect-free cases, measured once"))
        }
    };
    s.thresholds = Some(t);
    println!(
        "null ({whence}): {q} % quantiles: posterior-predictive χ²ν {:.3}, best χ² drop {:.1} ({:.0} s)",
        t.base_reduced_chi2,
        t.best_drop,
        t0.elapsed().as_secs_f64()
    );
    Ok(s)
}

/// One benchmark observation: the noisy features, the hidden effect's true value and the
/// strength of its noise-free signature.
struct Case {
    x: Vec<f64>,
    truth: Option<f64>,
    strength: f64,
    /// The ear's parameters (design column order).
    row: Vec<f64>,
}

/// Draws the benchmark's cases from the default model.
struct Cases<'a> {
    model: &'a Model,
    noise: &'a Noise,
    seed: u64,
}

impl Cases<'_> {
    /// Case `row`, with `hidden` switched on at a prior draw; `None` when a simulation
    /// fails. The parameters stay in the central 80 % of the prior so that a miss is the
    /// workflow's, not an edge of the prior's.
    fn draw(&self, row: usize, hidden: Option<usize>) -> Option<Case> {
        let (model, noise, seed) = (self.model, self.noise, self.seed);
        let mut design = Design::default();
        design.varied.extend(hidden);
        let mut r = design.draw(seed, row, 1).remove(0);
        let u = design.draw(seed ^ 0xC0FFEE, row, 1).remove(0);
        let cols = design.columns();
        for k in 0..N_PARAMS {
            r[k] = cols[k].from_unit(0.1 + 0.8 * unit_of(&cols[k], u[k])); // central 80 % of the prior
        }
        let x = run_rows(model, &design, &[r.clone()], row, Some(noise)).remove(0).ok()?;
        let strength = match hidden {
            Some(_) => {
                let on = run_rows(model, &design, &[r.clone()], row, None).remove(0).ok()?;
                let off = run_rows(model, &Design::default(), &[r[..N_PARAMS].to_vec()], row, None).remove(0).ok()?;
                (0..on.len())
                    .map(|i| (discrepancy::fit::feature_residual(i, 50, on[i], off[i]) / noise.std[i]).powi(2))
                    .sum()
            }
            None => 0.0,
        };
        Some(Case { x, truth: hidden.map(|_| r[N_PARAMS]), strength, row: r[..N_PARAMS].to_vec() })
    }
}

/// Effect-free cases that get any verdict but "no discrepancy".
fn false_alarms(draw: &Cases, base: &crate::npe::Npe, s: &Settings, clean: usize) -> Result<()> {
    let mut false_alarms = 0;
    let mut n_clean = 0;
    for i in 0..clean {
        let Some(c) = draw.draw(200_000 + i, None) else { continue };
        let r = diagnose(draw.model, base, &c.x, s, &mut |_| {})?;
        n_clean += 1;
        false_alarms += usize::from(r.verdict != Verdict::NoDiscrepancy);
    }
    println!(
        "false alarms: {false_alarms} of {n_clean} effect-free cases ({:.1} %; target ≤ 5 %)",
        100.0 * false_alarms as f64 / n_clean.max(1) as f64
    );
    Ok(())
}

/// One row of the table: how often effect `e`, hidden, is named (overall, when its
/// signature is visible above the noise, and in each fifth of its range by size), its
/// detection limit, how often its 90 % interval covers the truth, and what the other
/// cases were called instead. Returns one record per case.
fn effect_rates(
    draw: &Cases,
    base: &crate::npe::Npe,
    s: &Settings,
    e: usize,
    cases: usize,
) -> Result<Vec<serde_json::Value>> {
    let effect = &EFFECTS[e];
    let (mut n, mut named, mut vis, mut named_vis, mut covered, mut named_or_read) = (0, 0, 0, 0, 0, 0);
    let (mut before, mut after) = (Vec::new(), Vec::new());
    let mut bins = [(0usize, 0usize); SIZE_BINS];
    let mut other: std::collections::BTreeMap<String, usize> = Default::default();
    let spec = effect.as_param();
    let mut records = vec![];
    for i in 0..cases {
        let Some(Case { x, truth, strength, row }) = draw.draw(e * 1000 + i, Some(e)) else { continue };
        let r = diagnose(draw.model, base, &x, s, &mut |_| {})?;
        let findings = shipped_findings(base, &x, draw.seed.wrapping_add(i as u64))?;
        let read_as = associated_finding(effect.name)
            .is_some_and(|f| findings.iter().any(|g| g == &f) && !tissue_reads(&row, &f));
        named_or_read += usize::from(r.named == Some(effect.name) || read_as);
        records.push(serde_json::json!({
            "effect": effect.name,
            "case": i,
            "size": truth,
            "signature": strength,
            "params": row,
            "verdict": format!("{:?}", r.verdict),
            "named": r.named,
            "reduced_chi2_before": r.before.reduced_chi2,
            "reduced_chi2_after": r.candidates.first().map(|c| c.reduced_chi2),
            "best_candidate": r.candidates.first().map(|c| c.effect),
            "best_candidate_fit": r.candidates.first().map(|c| &c.fit.row),
            "findings": findings,
        }));
        n += 1;
        let visible = strength > VISIBLE;
        vis += usize::from(visible);
        before.push(r.before.reduced_chi2);
        let t = truth.unwrap_or(f64::NAN);
        // Bins run from the weakest fifth to the strongest: an effect whose off value lies
        // above its range (a joint factor below 1, an underpressure) grows toward `low`.
        let u = unit_of(&spec, t);
        let strength = if grows_downward(effect) { 1.0 - u } else { u };
        let bin = ((strength * SIZE_BINS as f64) as usize).min(SIZE_BINS - 1);
        bins[bin].0 += 1;
        if r.named == Some(effect.name) {
            named += 1;
            bins[bin].1 += 1;
            named_vis += usize::from(visible);
            let c = &r.candidates[0];
            after.push(c.reduced_chi2);
            covered += usize::from(t >= c.interval90[0] && t <= c.interval90[1]);
        } else {
            let key = r.named.map_or_else(|| format!("{:?}", r.verdict), str::to_string);
            *other.entry(key).or_default() += 1;
        }
    }
    let med = |v: Vec<f64>| crate::stats::median_upper(&crate::stats::sorted(v));
    let per_bin: Vec<String> = bins
        .iter()
        .map(|&(k, m)| if k == 0 { "–".into() } else { format!("{:.0}", 100.0 * m as f64 / k as f64) })
        .collect();
    // The readings benchmark's rule: every larger size bin named in ≥ 90 % of its cases.
    let limit = match otofit_bench::readings::detectable_from(&bins) {
        Some(b) => {
            let edge = b as f64 / SIZE_BINS as f64;
            let u = if grows_downward(effect) { 1.0 - edge } else { edge };
            format!("{:.3e} {}", spec.from_unit(u), effect.unit)
        }
        None => "none".into(),
    };
    let or_read = match associated_finding(effect.name) {
        Some(f) => format!("{:.0} % ({f})", 100.0 * named_or_read as f64 / n.max(1) as f64),
        None => "—".into(),
    };
    println!(
        "{:<18} {:>5} {:>8.0} {:>7} {:>11.0} {:>10.0} {:>9.2} {:>9.2}  by size {:<22} limit {limit}  {:?}  named or read: {or_read}",
        effect.name,
        n,
        100.0 * named as f64 / n.max(1) as f64,
        vis,
        100.0 * named_vis as f64 / vis.max(1) as f64,
        100.0 * covered as f64 / named.max(1) as f64,
        med(before),
        med(after),
        per_bin.join("/"),
        other
    );
    Ok(records)
}

/// The reading that names an effect's condition when the base model absorbs the effect
/// into a tissue parameter (`npe::normal::NORMAL`'s associations): the answer's
/// differential then names it even when the diagnose workflow has nothing to add.
fn associated_finding(effect: &str) -> Option<String> {
    let (name, side) = match effect {
        "third_window" => ("cochlear_load", "below"),
        "malleus_fixation" => ("E_ligaments", "above"),
        "isj_discontinuity" => ("E_joints", "below"),
        "effusion" => ("damping_beta", "above"),
        _ => return None,
    };
    Some(format!("{name} {side}"))
}

/// Whether `finding` (`NAME below|above`) is true of the ear's own tissue in `row`: then
/// reading it says nothing about a hidden effect, and the bench does not count it.
fn tissue_reads(row: &[f64], finding: &str) -> bool {
    let Some((name, side)) = finding.split_once(' ') else { return false };
    let Some(k) = crate::sim::PARAMS.iter().position(|p| p.name == name) else { return false };
    let Some(r) = crate::npe::normal::NORMAL.iter().find(|r| r.name == name) else { return false };
    match side {
        "below" => row[k] < r.low,
        "above" => row[k] > r.high,
        _ => false,
    }
}

/// The findings (`NAME below|above`) of the answer `otofit infer` gives for `x` with every
/// measure: none when the fit check withdraws the readings.
fn shipped_findings(base: &crate::npe::Npe, x: &[f64], seed: u64) -> Result<Vec<String>> {
    let present = vec![true; x.len()];
    let inf = base.infer(&crate::npe::Obs { x, present: Some(&present) }, 1000, seed)?;
    let (d, fit) = crate::discrepancy::fitcheck::checked_reading(base, x, &present, &inf, &inf.samples);
    Ok(crate::npe::normal::verdict(&d, fit?.ok).findings)
}

/// Whether `effect` grows toward the low end of its range (its off value lies above it).
fn grows_downward(effect: &crate::sim::params::EffectSpec) -> bool {
    effect.off >= effect.high
}

/// Fifths of an effect's range (in its scale: log for log-scaled effects), weakest
/// first, that the naming rate is reported by.
const SIZE_BINS: usize = 5;

/// One full diagnosis, retrain included, at full size: the wall time a user waits.
fn full_diagnosis(draw: &Cases, base: &crate::npe::Npe, seed: u64) -> Result<()> {
    let leak = crate::sim::Effects::index("probe_leak").context("probe_leak is in the library")?;
    let x = draw.draw(999_999, Some(leak)).ok_or_else(|| anyhow::anyhow!("simulation failed"))?.x;
    let full = Settings { seed, ..Settings::default() };
    let t1 = Instant::now();
    let r = diagnose(draw.model, base, &x, &full, &mut |_| {})?;
    println!(
        "one full diagnosis (hidden probe_leak; null of 40 cases, 10,000-row retrain): {:.0} s, verdict {:?} {:?}, χ²ν {:.2} → {:.2} (target ≤ 300 s)",
        t1.elapsed().as_secs_f64(),
        r.verdict,
        r.named,
        r.before.reduced_chi2,
        r.after.as_ref().map_or(f64::NAN, |a| a.reduced_chi2)
    );
    Ok(())
}

fn unit_of(c: &crate::sim::params::ParamSpec, v: f64) -> f64 {
    crate::npe::prior::space::position(c.scale, c.low, c.high, v)
}

/// Effect-free cases behind the benchmark's thresholds (a 97.5 % quantile needs more
/// than the 40 a single diagnosis uses to be stable).
const NULL_CASES: usize = 120;

/// Signature strength above which a hidden effect counts as visible at 1× noise.
const VISIBLE: f64 = 50.0;

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn effects_whose_off_value_lies_above_their_range_grow_downward() {
        let named = |n: &str| &EFFECTS[crate::sim::Effects::index(n).unwrap()];
        assert!(grows_downward(named("isj_discontinuity")) && grows_downward(named("pressure")));
        assert!(!grows_downward(named("perforation")) && !grows_downward(named("effusion")));
    }

    /// Each association is one the normal-range table itself states for that reading.
    #[test]
    fn an_associated_finding_is_the_one_the_normal_ranges_name_the_condition_by() {
        let words = [
            ("third_window", "third-window"),
            ("malleus_fixation", "malleus fixation"),
            ("isj_discontinuity", "discontinuity"),
            ("effusion", "effusion"),
        ];
        for (effect, word) in words {
            let f = associated_finding(effect).unwrap();
            let (name, side) = f.split_once(' ').unwrap();
            let r = crate::npe::normal::NORMAL.iter().find(|r| r.name == name).unwrap();
            let text = if side == "below" { r.below } else { r.above };
            assert!(text.contains(word), "{effect}: {f} is associated with '{text}'");
        }
        assert!(associated_finding("probe_leak").is_none() && associated_finding("mastoid").is_none());
        // A reading the ear's own tissue explains does not count for the effect.
        let mut row = crate::npe::normal::centre_row();
        assert!(!tissue_reads(&row, "cochlear_load below"));
        row[6] = 1e10;
        assert!(tissue_reads(&row, "cochlear_load below") && !tissue_reads(&row, "cochlear_load above"));
    }
}
