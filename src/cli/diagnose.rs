//! The discrepancy workflow on the command line, and its benchmark.

use crate::discrepancy::{self, Observation, Thresholds, Verdict};
use crate::sim::batch::{Design, Noise, default_noise_std, run_rows};
use crate::sim::params::{EFFECTS, N_EFFECTS};
use crate::sim::{Model, ModelConfig};
use anyhow::{Context, Result, bail};
use clap::Args;
use std::path::PathBuf;
use std::time::Instant;

#[derive(Args, Debug)]
pub struct DiagnoseArgs {
    /// Base model (trained on otofit's simulator without effects).
    #[arg(long)]
    pub model: PathBuf,
    /// One observation: CSV with a header of all 250 feature names.
    #[arg(long)]
    pub obs: PathBuf,
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
    #[arg(long, default_value_t = 300)]
    pub max_epochs: usize,
    /// Effect-free simulations for the null distribution of the statistics.
    #[arg(long, default_value_t = 40)]
    pub null_cases: usize,
    #[arg(long, default_value_t = 0)]
    pub seed: u64,
}

pub fn run(args: DiagnoseArgs) -> Result<()> {
    use crate::discrepancy::workflow::{Settings, diagnose};
    let candidates: Vec<usize> = if args.candidates == "all" {
        (0..N_EFFECTS).collect()
    } else {
        args.candidates
            .split(',')
            .map(|c| crate::sim::Effects::index(c.trim()).with_context(|| format!("--candidates: unknown effect '{c}' (known: {})", crate::jobs::effect_names())))
            .collect::<Result<_>>()?
    };
    let base = crate::npe::Npe::load(&args.model)?;
    let table = crate::dataset::read_csv(&args.obs)?;
    let Some(row) = table.rows.first() else { bail!("{}: no observation row", args.obs.display()) };
    let (x, present) = super::infer::align(&base, &table.header, row)?;
    if let Some(i) = present.iter().position(|p| !p) {
        bail!("{}: feature '{}' is missing (diagnose needs all 250)", args.obs.display(), base.header.feature_names[i]);
    }
    let model = Model::new(ModelConfig::default())?;
    let s = Settings { candidates, extend: !args.no_extend, train_rows: args.train_rows, max_epochs: args.max_epochs, null_cases: args.null_cases, seed: args.seed, ..Settings::default() };
    let report = diagnose(&model, &base, &x, &s, &mut |m| eprintln!("{m}"))?;
    std::fs::create_dir_all(&args.out)?;
    for (name, svg) in &report.figures {
        std::fs::write(args.out.join(name), svg)?;
    }
    let mut doc = serde_json::to_value(&report)?;
    if let Some(m) = &report.extended_model {
        let path = args.out.join("extended.otofit");
        m.save(&path)?;
        doc["extended_model"] = path.display().to_string().into();
    }
    doc["figures"] = report.figures.iter().map(|(n, _)| n.clone()).collect::<Vec<_>>().into();
    let tmp = args.out.join("report.json.tmp");
    std::fs::write(&tmp, serde_json::to_vec_pretty(&doc)?)?;
    std::fs::rename(&tmp, args.out.join("report.json"))?;
    println!("verdict: {:?}{}", report.verdict, report.named.map(|n| format!(" ({n})")).unwrap_or_default());
    for b in &report.before.bands {
        println!("  {}", b.describe());
    }
    if let (Some(a), Some(p)) = (&report.after, &report.effect_posterior) {
        println!("reduced χ² {:.2} → {:.2}; {} median {:.3e} [{:.3e}, {:.3e}] {}", report.before.reduced_chi2, a.reduced_chi2, p.effect, p.median, p.q05, p.q95, p.unit);
    }
    Ok(())
}

/// Base starts without NPE: the nominal row and a few prior draws.
fn base_starts(seed: u64) -> Vec<Vec<f64>> {
    let mut starts = vec![crate::sim::Theta::nominal().0.to_vec()];
    starts.extend(Design::default().draw(seed ^ 0xBA5E, 0, 3));
    starts
}

struct Case {
    truth: Option<(usize, f64)>,
    verdict: Verdict,
    named: Option<&'static str>,
    covered: bool,
    base_rchi2: f64,
    after_rchi2: f64,
    best_drop: f64,
    /// Σ((x_on − x_off)/σ)² at the true parameters without noise: how visible the
    /// hidden effect is at all.
    strength: f64,
}

fn run_case(model: &Model, noise: &Noise, seed: u64, row_id: usize, hidden: Option<usize>, t: &Thresholds, candidates: &[usize]) -> Option<Case> {
    let mut design = Design::default();
    if let Some(e) = hidden {
        design.varied.push(e);
    }
    // Base parameters from the middle 80 % of the prior (unit-box), effect from its range.
    let mut row = design.draw(seed, row_id, 1).remove(0);
    let cols = design.columns();
    let mut rng_u = design.draw(seed ^ 0xC0FFEE, row_id, 1).remove(0);
    for (k, c) in cols.iter().enumerate().take(7) {
        let q = 0.1 + 0.8 * unit_of(c, rng_u[k]);
        row[k] = c.from_unit(q);
    }
    rng_u.clear();
    let x = run_rows(model, &design, &[row.clone()], row_id, Some(noise)).remove(0).ok()?;
    let strength = match hidden {
        Some(_) => {
            let on = run_rows(model, &design, &[row.clone()], row_id, None).remove(0).ok()?;
            let off = run_rows(model, &Design::default(), &[row[..7].to_vec()], row_id, None).remove(0).ok()?;
            let nf = on.len() / 5;
            (0..on.len()).map(|i| (discrepancy::fit::feature_residual(i, nf, on[i], off[i]) / noise.std[i]).powi(2)).sum()
        }
        None => 0.0,
    };
    let obs = Observation { x, sigma: noise.std.clone() };
    let (base, ranked) = discrepancy::fit_and_rank(model, &obs, &base_starts(seed + row_id as u64), candidates)?;
    let v = discrepancy::verdict(base.reduced_chi2(), &ranked, base.chi2, t);
    let best_drop = ranked.first().map_or(0.0, |c| base.chi2 - c.chi2);
    let named = (v == Verdict::EffectNamed).then(|| ranked[0].effect);
    let covered = match (hidden, named) {
        (Some(e), Some(n)) if EFFECTS[e].name == n => {
            let t = row[7];
            t >= ranked[0].interval90[0] && t <= ranked[0].interval90[1]
        }
        _ => false,
    };
    let after = if v == Verdict::EffectNamed { ranked[0].reduced_chi2 } else { base.reduced_chi2() };
    Some(Case { truth: hidden.map(|e| (e, row[7])), verdict: v, named, covered, base_rchi2: base.reduced_chi2(), after_rchi2: after, best_drop, strength })
}

fn unit_of(c: &crate::sim::params::ParamSpec, v: f64) -> f64 {
    let t = |v: f64| if c.scale == crate::sim::params::Scale::Log10 { v.log10() } else { v };
    (t(v) - t(c.low)) / (t(c.high) - t(c.low))
}

/// Signature strength above which a hidden effect counts as visible at 1× noise.
const VISIBLE: f64 = 50.0;

pub fn bench(cases: usize, clean: usize, seed: u64) -> Result<()> {
    let model = Model::new(ModelConfig::default())?;
    let noise = Noise { std: default_noise_std(&model), scale: 1.0, seed };
    let all: Vec<usize> = (0..N_EFFECTS).collect();
    let t0 = Instant::now();
    // Null calibration: the base fit's reduced χ² on effect-free data (separate rows).
    let never = Thresholds { base_reduced_chi2: f64::INFINITY, best_drop: f64::INFINITY, explained: 0.0 };
    let null: Vec<Case> = (0..clean).filter_map(|i| run_case(&model, &noise, seed, 100_000 + i, None, &never, &all)).collect();
    let q95 = |mut v: Vec<f64>| {
        v.sort_by(f64::total_cmp);
        v[(0.95 * (v.len() - 1) as f64).round() as usize]
    };
    let t = Thresholds {
        base_reduced_chi2: q95(null.iter().map(|c| c.base_rchi2).collect()),
        best_drop: q95(null.iter().map(|c| c.best_drop).collect()),
        explained: 1.3,
    };
    println!("null ({} cases): 95 % quantiles: base reduced χ² {:.3}, best χ² drop {:.1}", null.len(), t.base_reduced_chi2, t.best_drop);
    let false_alarms = (0..clean).filter_map(|i| run_case(&model, &noise, seed, 200_000 + i, None, &t, &all)).filter(|c| c.verdict != Verdict::NoDiscrepancy).count();
    println!("false alarms on {clean} fresh effect-free cases: {false_alarms} ({:.1} %)", 100.0 * false_alarms as f64 / clean as f64);
    println!("visible: the hidden effect's noise-free signature Σ(Δx/σ)² exceeds {VISIBLE}");
    println!("{:<16} {:>6} {:>8} {:>8} {:>10} {:>9} {:>10} {:>10}  confusions", "effect", "cases", "named %", "visible", "named vis %", "cover90 %", "χ²ν before", "χ²ν after");
    for e in 0..N_EFFECTS {
        let rows: Vec<Case> = (0..cases).filter_map(|i| run_case(&model, &noise, seed, e * 1000 + i, Some(e), &t, &all)).collect();
        let n = rows.len() as f64;
        let named = rows.iter().filter(|c| c.named == Some(EFFECTS[e].name)).count() as f64;
        let visible: Vec<&Case> = rows.iter().filter(|c| c.strength > VISIBLE).collect();
        let named_visible = visible.iter().filter(|c| c.named == Some(EFFECTS[e].name)).count() as f64;
        let covered = rows.iter().filter(|c| c.covered).count() as f64;
        let med = |mut v: Vec<f64>| {
            v.sort_by(f64::total_cmp);
            v[v.len() / 2]
        };
        let mut conf: std::collections::BTreeMap<String, usize> = Default::default();
        for c in rows.iter().filter(|c| c.named != Some(EFFECTS[e].name)) {
            let key = match c.verdict {
                Verdict::EffectNamed => c.named.unwrap().to_string(),
                v => format!("{v:?}"),
            };
            *conf.entry(key).or_default() += 1;
            let _ = c.truth;
        }
        println!(
            "{:<16} {:>6} {:>8.0} {:>8} {:>10.0} {:>9.0} {:>10.2} {:>10.2}  {:?}",
            EFFECTS[e].name,
            rows.len(),
            100.0 * named / n,
            visible.len(),
            100.0 * named_visible / (visible.len() as f64).max(1.0),
            100.0 * covered / named.max(1.0),
            med(rows.iter().map(|c| c.base_rchi2).collect()),
            med(rows.iter().map(|c| c.after_rchi2).collect()),
            conf
        );
    }
    println!("wall {:.1} s", t0.elapsed().as_secs_f64());
    Ok(())
}
