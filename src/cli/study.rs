//! `otofit study NAME`: the seed study's analyses on otofit's own simulator — validation
//! on unseen simulations (Fig. 2), robustness to training noise (Fig. 4) and the effect of
//! training-set size (Fig. 5). Each prints a table and writes JSON and SVG figures.

use crate::discrepancy::workflow::spearman;
use crate::npe::{self, Dataset, Npe, Obs, TrainSettings};
use crate::plot;
use crate::sim::batch::{Design, Noise, default_noise_std, run_rows};
use crate::sim::output::{MEASURES, feature_names};
use crate::sim::{Model, ModelConfig, PARAMS};
use anyhow::{Result, bail};
use clap::{Args, ValueEnum};
use serde_json::json;
use std::path::{Path, PathBuf};

#[derive(Clone, Copy, Debug, ValueEnum)]
pub enum StudyName {
    Validate,
    Noise,
    Size,
}

#[derive(Args, Debug)]
pub struct StudyArgs {
    pub name: StudyName,
    #[arg(long)]
    pub out: PathBuf,
    /// Model for `validate`.
    #[arg(long, default_value = "models/default.otofit")]
    pub model: PathBuf,
    /// Unseen simulations for `validate`.
    #[arg(long, default_value_t = 200)]
    pub n: usize,
    /// Training-set size for `noise`; the largest size for `size` (then /10, /100).
    #[arg(long, default_value_t = 10_000)]
    pub train_rows: usize,
    #[arg(long, default_value_t = 300)]
    pub max_epochs: usize,
    #[arg(long, default_value_t = 0)]
    pub seed: u64,
}

fn to_param(p: &crate::sim::params::ParamSpec) -> npe::Param {
    npe::Param { name: p.name.into(), unit: p.unit.into(), scale: npe::Scale::Log10, low: p.low, high: p.high }
}

/// Noise-free simulations of prior draws as an in-memory dataset.
fn simulated(model: &Model, rows: usize, seed: u64) -> Dataset {
    let d = Design::default();
    let theta = d.draw(seed, 0, rows);
    let out = run_rows(model, &d, &theta, 0, None);
    let (mut t, mut x) = (vec![], vec![]);
    for (row, r) in theta.into_iter().zip(out) {
        if let Ok(v) = r {
            t.push(row);
            x.push(v);
        }
    }
    Dataset {
        params: PARAMS.iter().map(to_param).collect(),
        feature_names: feature_names(model.frequencies()),
        frequencies_hz: model.frequencies().to_vec(),
        groups: vec![],
        noise_std: default_noise_std(model),
        theta: t,
        x,
        skipped: 0,
    }
}

/// Spearman ρ per measure between two spectra.
fn rho(a: &[f64], b: &[f64]) -> Vec<f64> {
    let n = a.len() / MEASURES.len();
    (0..MEASURES.len()).map(|m| spearman(&a[m * n..(m + 1) * n], &b[m * n..(m + 1) * n])).collect()
}

fn write(out: &Path, name: &str, text: &str) -> Result<()> {
    std::fs::create_dir_all(out)?;
    std::fs::write(out.join(name), text)?;
    Ok(())
}

fn corner(npe: &Npe, samples: &[Vec<f64>], truth: Option<&[f64]>, map: &[f64], title: &str) -> String {
    let dims: Vec<plot::Dim<'_>> = npe
        .params()
        .iter()
        .enumerate()
        .map(|(k, p)| plot::Dim { name: &p.name, unit: &p.unit, low: p.low, high: p.high, log: p.scale == npe::Scale::Log10, truth: truth.map(|t| t[k]), map: Some(map[k]) })
        .collect();
    plot::corner(title, &dims, samples)
}

/// Posterior summary of one observation: CV per parameter and ρ of the MAP re-simulation.
fn infer_one(model: &Model, npe: &Npe, x: &[f64], truth_x: &[f64], seed: u64) -> Result<(npe::Inference, Vec<f64>, Vec<f64>)> {
    let inf = npe.infer(&Obs { x, present: None }, 1000, seed)?;
    let map_x = run_rows(model, &Design::default(), &[inf.map.clone()], 0, None).remove(0)?;
    let r = rho(&map_x, truth_x);
    Ok((inf, map_x, r))
}

pub fn run(a: StudyArgs) -> Result<()> {
    let model = Model::new(ModelConfig::default())?;
    let noise = Noise { std: default_noise_std(&model), scale: 1.0, seed: a.seed ^ 0x0B5 };
    let names: Vec<&str> = PARAMS.iter().map(|p| p.name).collect();
    match a.name {
        StudyName::Validate => {
            let npe = Npe::load(&a.model)?;
            let held = simulated(&model, a.n, a.seed ^ 0x7E57);
            let (mut rhos, mut cvs, mut inside) = (vec![], vec![vec![]; 7], vec![0usize; 7]);
            for (i, (t, x0)) in held.theta.iter().zip(&held.x).enumerate() {
                let x = noise.apply(x0, i);
                let (inf, map_x, r) = infer_one(&model, &npe, &x, x0, i as u64)?;
                for (k, s) in inf.summaries.iter().enumerate() {
                    cvs[k].push(s.cv);
                    inside[k] += usize::from(t[k] >= s.q05 && t[k] <= s.q95);
                }
                rhos.push(r);
                if i < 5 {
                    let f = model.frequencies();
                    let series = [
                        plot::Series { x: &x, color: plot::OBS, width: 2.0, opacity: 1.0, label: Some("noisy simulation (observation)") },
                        plot::Series { x: x0, color: plot::TRUTH, width: 1.5, opacity: 1.0, label: Some("ground truth") },
                        plot::Series { x: &map_x, color: plot::MAP, width: 1.5, opacity: 1.0, label: Some("MAP re-simulation") },
                    ];
                    write(&a.out, &format!("validate_{i}_spectra.svg"), &plot::spectra(&format!("Unseen simulation {i}"), f, &[], &series))?;
                    write(&a.out, &format!("validate_{i}_corner.svg"), &corner(&npe, &inf.samples, Some(t), &inf.map, &format!("Posterior, unseen simulation {i}")))?;
                }
            }
            let n = rhos.len() as f64;
            let mean_rho: Vec<f64> = (0..MEASURES.len()).map(|m| rhos.iter().map(|r| r[m]).sum::<f64>() / n).collect();
            let all = mean_rho.iter().sum::<f64>() / MEASURES.len() as f64;
            let med = |mut v: Vec<f64>| {
                v.sort_by(f64::total_cmp);
                v[v.len() / 2]
            };
            println!("validate: {} unseen simulations, 1× noise; mean Spearman ρ (MAP re-simulation vs truth) {all:.4} (study: 0.998)", rhos.len());
            for (m, r) in MEASURES.iter().zip(&mean_rho) {
                println!("  ρ {:<11} {r:.4}", m.name);
            }
            println!("{:<14} {:>10} {:>14}", "parameter", "median CV", "in 90 % int.");
            for k in 0..7 {
                println!("{:<14} {:>10.3} {:>13.1}%", names[k], med(cvs[k].clone()), 100.0 * inside[k] as f64 / n);
            }
            let doc = json!({ "n": rhos.len(), "mean_rho": all, "rho_per_measure": MEASURES.iter().map(|m| m.name).zip(&mean_rho).collect::<Vec<_>>(),
                "median_cv": names.iter().zip(cvs.iter().map(|c| med(c.clone()))).collect::<Vec<_>>(),
                "coverage90": names.iter().zip(inside.iter().map(|&c| c as f64 / n)).collect::<Vec<_>>() });
            write(&a.out, "validate.json", &serde_json::to_string_pretty(&doc)?)?;
        }
        StudyName::Noise | StudyName::Size => {
            let sizes: Vec<usize> = match a.name {
                StudyName::Size => vec![a.train_rows / 100, a.train_rows / 10, a.train_rows],
                _ => vec![a.train_rows],
            };
            if sizes[0] < 20 {
                bail!("--train-rows too small for this study (smallest set {} < 20)", sizes[0]);
            }
            let levels: Vec<f64> = match a.name {
                StudyName::Noise => vec![0.1, 1.0, 10.0],
                _ => vec![1.0],
            };
            let ds = simulated(&model, *sizes.last().unwrap(), a.seed);
            // The same observation for every model: a mid-prior ear with 1× noise.
            let truth = Design::default().draw(a.seed ^ 0x0B5E, 0, 1).remove(0);
            let x0 = run_rows(&model, &Design::default(), &[truth.clone()], 0, None).remove(0)?;
            let x = noise.apply(&x0, 0);
            let mut rows = vec![];
            for &size in &sizes {
                for &level in &levels {
                    let sub = Dataset { theta: ds.theta[..size].to_vec(), x: ds.x[..size].to_vec(), ..simulated(&model, 0, 0) };
                    let s = TrainSettings { noise_scale: level, seed: a.seed, max_epochs: a.max_epochs, ..TrainSettings::default() };
                    let npe = npe::train(&sub, &s, &mut |_| true)?;
                    let (inf, _, r) = infer_one(&model, &npe, &x, &x0, 1)?;
                    let label = format!("n{size}_noise{level}");
                    write(&a.out, &format!("{label}_corner.svg"), &corner(&npe, &inf.samples, Some(&truth), &inf.map, &format!("{size} simulations, {level}× noise")))?;
                    let mean_rho = r.iter().sum::<f64>() / r.len() as f64;
                    let cv: Vec<f64> = inf.summaries.iter().map(|s| s.cv).collect();
                    // Width in decades of the 90 % interval: robust where CV saturates
                    // (log-uniform posteriors as wide as the prior have CV > 1).
                    let width = inf.summaries.iter().map(|s| (s.q95 / s.q05).log10()).sum::<f64>() / 7.0;
                    println!("{size:>6} simulations, noise {level:>4}×: mean 90 % width {width:.3} decades, mean CV {:.3}, mean ρ {mean_rho:.3}, epochs {}  CV per parameter {:?}", cv.iter().sum::<f64>() / 7.0, npe.header.training.epochs, cv.iter().map(|c| (c * 1000.0).round() / 1000.0).collect::<Vec<_>>());
                    rows.push(json!({ "train_rows": size, "noise_scale": level, "cv": names.iter().zip(&cv).collect::<Vec<_>>(), "mean_cv": cv.iter().sum::<f64>() / 7.0, "mean_width_decades": width, "rho": r, "mean_rho": mean_rho, "epochs": npe.header.training.epochs }));
                }
            }
            let name = if matches!(a.name, StudyName::Noise) { "noise.json" } else { "size.json" };
            write(&a.out, name, &serde_json::to_string_pretty(&json!({ "truth": truth, "runs": rows }))?)?;
        }
    }
    Ok(())
}
