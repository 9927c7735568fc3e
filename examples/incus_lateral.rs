//! What the incus moving across the stapes axis (the ISJ shearing between
//! two moving bodies, `Geometry::incus_lateral`) changes. For the nominal ear and prior
//! draws: how far the features move, in test–retest STDs per measure; and how well the
//! features pin each parameter down, as the Cramér–Rao bound from the Fisher information
//! JᵀΣ⁻¹J (log10 units for log-scaled parameters, fractions of the range for the others),
//! with the joint held to the ground (every model so far) and with the incus free.
//!
//! `cargo run --example incus_lateral -- [draws]` (default 100; a few seconds).

use faer::Mat;
use faer::prelude::Solve;
use otofit::sim::batch::{Design, default_noise_std, run_rows};
use otofit::sim::output::MEASURES;
use otofit::sim::params::Scale;
use otofit::sim::{Model, ModelConfig, PARAMS};

/// A parameter's inference coordinate: log10 for log-scaled parameters, else the value
/// over its prior range.
fn coord(k: usize, v: f64) -> f64 {
    let p = &PARAMS[k];
    match p.scale {
        Scale::Log10 => v.log10(),
        Scale::Linear => v / (p.high - p.low),
    }
}

fn value(k: usize, u: f64) -> f64 {
    let p = &PARAMS[k];
    match p.scale {
        Scale::Log10 => 10f64.powf(u),
        Scale::Linear => u * (p.high - p.low),
    }
}

/// Features of `rows` (noise-free); `None` where a run failed.
fn features(model: &Model, rows: &[Vec<f64>]) -> Vec<Option<Vec<f64>>> {
    run_rows(model, &Design::default(), rows, 0, None).into_iter().map(Result::ok).collect()
}

/// Cramér–Rao standard deviations per parameter at `row` (central differences, one-sided
/// on a prior edge), in [`coord`] units; `None` if a run failed or F is singular.
fn crb(model: &Model, row: &[f64], sigma: &[f64]) -> Option<Vec<f64>> {
    let d = PARAMS.len();
    let h = 0.01;
    let mut cols = Vec::with_capacity(d);
    for k in 0..d {
        let u = coord(k, row[k]);
        let (lo, hi) = (coord(k, PARAMS[k].low), coord(k, PARAMS[k].high));
        let (a, b) = ((u - h).max(lo), (u + h).min(hi));
        let mut ra = row.to_vec();
        let mut rb = row.to_vec();
        ra[k] = value(k, a);
        rb[k] = value(k, b);
        let x = features(model, &[ra, rb]);
        let (xa, xb) = (x[0].as_ref()?, x[1].as_ref()?);
        cols.push(xa.iter().zip(xb).zip(sigma).map(|((p, q), s)| (q - p) / (b - a) / s).collect::<Vec<f64>>());
    }
    let f = Mat::<f64>::from_fn(d, d, |i, j| cols[i].iter().zip(&cols[j]).map(|(a, b)| a * b).sum());
    let inv = f.partial_piv_lu().solve(Mat::<f64>::identity(d, d));
    let out: Vec<f64> = (0..d).map(|i| inv[(i, i)].max(0.0).sqrt()).collect();
    out.iter().all(|v| v.is_finite()).then_some(out)
}

fn median(mut v: Vec<f64>) -> f64 {
    v.sort_by(f64::total_cmp);
    if v.is_empty() { f64::NAN } else { v[v.len() / 2] }
}

fn main() -> Result<(), Box<dyn std::error::Error>> {
    let draws: usize = std::env::args().nth(1).map_or(Ok(100), |s| s.parse())?;
    let held = Model::new(ModelConfig::default())?;
    let mut config = ModelConfig::default();
    config.geometry.incus_lateral = true;
    let free = Model::new(config)?;
    let sigma = default_noise_std(&held);
    let n = held.frequencies().len();
    let nominal: Vec<f64> = PARAMS.iter().map(|p| p.nominal).collect();
    let mut rows = vec![nominal.clone()];
    rows.extend(Design::default().draw(0x15A1, 0, draws));

    // How far the features move, per measure, in STDs.
    let (xh, xf) = (features(&held, &rows), features(&free, &rows));
    println!("features moved by the free incus (RMS over the band, in test–retest STDs):");
    println!("{:16} {:>8} {:>14} {:>12}", "measure", "nominal", "draws median", "draws max");
    for (m, meas) in MEASURES.iter().enumerate() {
        let rms = |a: &[f64], b: &[f64]| {
            ((m * n..(m + 1) * n).map(|i| ((a[i] - b[i]) / sigma[i]).powi(2)).sum::<f64>() / n as f64).sqrt()
        };
        let all: Vec<f64> = xh.iter().zip(&xf).filter_map(|(a, b)| Some(rms(a.as_ref()?, b.as_ref()?))).collect();
        let (worst, top) = all.iter().enumerate().skip(1).fold((0, 0.0), |b, (i, &v)| if v > b.1 { (i, v) } else { b });
        println!(
            "{:16} {:8.3} {:14.3} {:12.3}  (E_joints {:.1e}, E_ligaments {:.1e} there)",
            meas.name,
            all[0],
            median(all[1..].to_vec()),
            top,
            rows[worst][4],
            rows[worst][1]
        );
    }

    // The LDV beam's angle: is it a flat gain (cos θ) or a spectrum of its own? The
    // stapes magnitude at 45° over the one on the piston axis, across the band.
    println!("\nLDV beam at 45° over on-axis, stapes magnitude (dB): least … largest over the band");
    for (name, model) in [("held", &held), ("free", &free)] {
        let mut tilted = nominal.clone();
        tilted[12] = 45.0;
        let x = features(model, &[nominal.clone(), tilted]);
        let (a, b) = (x[0].as_ref().ok_or("run failed")?, x[1].as_ref().ok_or("run failed")?);
        let db: Vec<f64> = (0..n).map(|i| 20.0 * (b[i] - a[i])).collect();
        let lo = db.iter().copied().fold(f64::INFINITY, f64::min);
        let hi = db.iter().copied().fold(f64::NEG_INFINITY, f64::max);
        println!("{name}: {lo:.2} … {hi:.2} dB (cos 45° = {:.2} dB)", 20.0 * 45f64.to_radians().cos().log10());
    }

    // Cramér–Rao bounds, nominal and the draws' median.
    let mut table = Vec::new();
    for model in [&held, &free] {
        let at_nominal = crb(model, &nominal, &sigma);
        let per_draw: Vec<Vec<f64>> = rows[1..].iter().filter_map(|r| crb(model, r, &sigma)).collect();
        table.push((at_nominal, per_draw));
    }
    println!("\nCramér–Rao STD (log10 units; linear parameters in fractions of their range):");
    println!(
        "{:16} {:>12} {:>12} {:>14} {:>14}",
        "parameter", "nominal held", "nominal free", "draws held", "draws free"
    );
    for (k, p) in PARAMS.iter().enumerate() {
        let nom = |t: &Option<Vec<f64>>| t.as_ref().map_or(f64::NAN, |v| v[k]);
        let med = |t: &Vec<Vec<f64>>| median(t.iter().map(|v| v[k]).collect());
        println!(
            "{:16} {:12.3} {:12.3} {:14.3} {:14.3}",
            p.name,
            nom(&table[0].0),
            nom(&table[1].0),
            med(&table[0].1),
            med(&table[1].1)
        );
    }
    println!("(draws with a regular Fisher matrix: held {}, free {} of {draws})", table[0].1.len(), table[1].1.len());
    Ok(())
}
