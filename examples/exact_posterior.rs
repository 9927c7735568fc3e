//! The flow's posterior against the likelihood's (`discrepancy::exact`) on simulated ears
//! of the default model's own simulator with its training noise: how wide each is (the
//! posterior standard deviation in log10 units for log-scaled parameters, in fractions
//! of the prior range for the others), how often each one's 90 % interval holds the
//! truth, and how well its draws re-simulate (χ² over the 350 features; ≈ 350 at the
//! truth).
//!
//! `cargo run --example exact_posterior -- [ears] [steps]` (defaults 40 and 100,000, the
//! length `otofit infer --exact` requires; about 9 s per ear and core, 3 min on two).
//! `OTOFIT_EARS=1` also prints each ear's χ² at the truth, at the best fit and the
//! chain's median.

use otofit::discrepancy::fitcheck::exact;
use otofit::npe::{Npe, Obs};
use otofit::sim::batch::{Design, Noise, run_rows};
use otofit::sim::params::Scale;
use otofit::sim::{Effects, Model, ModelConfig, PARAMS, Theta, simulate};
use rayon::prelude::*;

fn coord(k: usize, v: f64) -> f64 {
    let p = &PARAMS[k];
    match p.scale {
        Scale::Log10 => v.log10(),
        Scale::Linear => v / (p.high - p.low),
    }
}

fn sd(c: &[f64]) -> f64 {
    let m = c.iter().sum::<f64>() / c.len() as f64;
    (c.iter().map(|v| (v - m).powi(2)).sum::<f64>() / c.len() as f64).sqrt()
}

fn median(mut v: Vec<f64>) -> f64 {
    v.sort_by(f64::total_cmp);
    if v.is_empty() { f64::NAN } else { v[v.len() / 2] }
}

/// Whether the truth lies inside the draws' central 90 % interval of parameter k.
fn inside(draws: &[Vec<f64>], k: usize, truth: f64) -> bool {
    let mut c: Vec<f64> = draws.iter().map(|t| t[k]).collect();
    c.sort_by(f64::total_cmp);
    let q = |p: f64| c[((c.len() - 1) as f64 * p).round() as usize];
    (q(0.05)..=q(0.95)).contains(&truth)
}

/// Per ear: (per parameter: flow sd, exact sd, flow inside, exact inside), χ² medians of
/// the flow's and the chain's draws, χ² at the truth, the chain's acceptance, seconds.
type EarResult = (Vec<(f64, f64, bool, bool)>, f64, f64, f64, f64, f64);

fn main() -> Result<(), Box<dyn std::error::Error>> {
    let mut args = std::env::args().skip(1);
    let ears: usize = args.next().map_or(Ok(40), |s| s.parse())?;
    let steps: usize = args.next().map_or(Ok(100_000), |s| s.parse())?;
    let npe = Npe::load(&std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("models/default.otofit"))?;
    let model = Model::new(ModelConfig::default())?;
    let sigma = npe.header.noise_std.clone();
    let rows = Design::default().draw(0xE4AC, 0, ears);
    let noise = Noise { std: sigma.clone(), scale: 1.0, seed: 0xE5 };
    let xs = run_rows(&model, &Design::default(), &rows, 0, Some(&noise));
    let chi2 = |runner: &mut otofit::sim::Runner<'_>, t: &[f64], x: &[f64]| -> f64 {
        let theta = Theta(std::array::from_fn(|k| t[k]));
        let n = x.len() / otofit::sim::output::MEASURES.len();
        simulate(runner, &theta, &Effects::default()).map_or(f64::INFINITY, |f| {
            f.iter()
                .zip(x)
                .zip(&sigma)
                .enumerate()
                .map(|(i, ((s, o), sg))| (otofit::discrepancy::fit::feature_residual(i, n, *s, *o) / sg).powi(2))
                .sum()
        })
    };
    let out: Vec<EarResult> = rows
        .par_iter()
        .zip(&xs)
        .enumerate()
        .filter_map(|(e, (row, x))| {
            let x = x.as_ref().ok()?;
            let t0 = std::time::Instant::now();
            let present = vec![true; x.len()];
            let inf = npe.infer(&Obs { x, present: None }, 1000, e as u64).ok()?;
            let ex = exact(&npe, x, &present, &inf, steps, e as u64).ok()?;
            let secs = t0.elapsed().as_secs_f64();
            let mut runner = model.runner();
            let flow_chi2 = median(inf.samples.iter().take(200).map(|t| chi2(&mut runner, t, x)).collect());
            let truth_chi2 = chi2(&mut runner, row, x);
            if std::env::var("OTOFIT_EARS").is_ok() {
                eprintln!(
                    "ear {e}: χ² truth {truth_chi2:.1}, best fit {:.1}, chain median {:.1}",
                    ex.chain.chi2_start, ex.chain.chi2_median
                );
            }
            let per = (0..PARAMS.len())
                .map(|k| {
                    let f: Vec<f64> = inf.samples.iter().map(|t| coord(k, t[k])).collect();
                    let c: Vec<f64> = ex.chain.samples.iter().map(|t| coord(k, t[k])).collect();
                    (sd(&f), sd(&c), inside(&inf.samples, k, row[k]), inside(&ex.chain.samples, k, row[k]))
                })
                .collect();
            Some((per, flow_chi2, ex.chain.chi2_median, truth_chi2, ex.chain.acceptance, secs))
        })
        .collect();
    let n = out.len();
    println!("{n} of {ears} simulated ears (1× noise), {steps} chain steps each");
    println!(
        "{:16} {:>10} {:>10} {:>7} {:>12} {:>12}",
        "parameter", "flow sd", "exact sd", "ratio", "flow in 90%", "exact in 90%"
    );
    for (k, p) in PARAMS.iter().enumerate() {
        let f = median(out.iter().map(|o| o.0[k].0).collect());
        let c = median(out.iter().map(|o| o.0[k].1).collect());
        let fi = out.iter().filter(|o| o.0[k].2).count() as f64 / n as f64;
        let ci = out.iter().filter(|o| o.0[k].3).count() as f64 / n as f64;
        println!("{:16} {f:10.3} {c:10.3} {:7.1} {:11.0}% {:11.0}%", p.name, f / c, 100.0 * fi, 100.0 * ci);
    }
    let all = |i: usize| {
        out.iter().map(|o| o.0.iter().filter(|v| if i == 2 { v.2 } else { v.3 }).count()).sum::<usize>() as f64
            / (n * PARAMS.len()) as f64
    };
    println!(
        "truth inside the 90 % intervals, all parameters: flow {:.1}%, exact {:.1}%",
        100.0 * all(2),
        100.0 * all(3)
    );
    println!(
        "median χ² of the draws: flow {:.0}, exact {:.0}; at the truth {:.0} (350 features)",
        median(out.iter().map(|o| o.1).collect()),
        median(out.iter().map(|o| o.2).collect()),
        median(out.iter().map(|o| o.3).collect())
    );
    println!(
        "chain acceptance median {:.2}; seconds per ear median {:.1}",
        median(out.iter().map(|o| o.4).collect()),
        median(out.iter().map(|o| o.5).collect())
    );
    Ok(())
}
