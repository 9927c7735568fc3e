//! `otofit study NAME`: the seed study's analyses on otofit's own simulator — validation
//! on unseen simulations (Fig. 2), robustness to training noise (Fig. 4) and the effect of
//! training-set size (Fig. 5). Each prints a table and writes JSON and SVG figures.

use crate::npe::{self, Dataset, Npe, Obs, TrainSettings};
use crate::plot::{self, html::Page};
use crate::sim::batch::{Design, Noise, default_noise_std, run_rows};
use crate::sim::output::{MEASURES, feature_names};
use crate::sim::{Model, ModelConfig, N_PARAMS, PARAMS};
use crate::stats;
use anyhow::{Context, Result, bail};
use clap::{Args, ValueEnum};
use serde_json::json;
use std::path::{Path, PathBuf};

/// Spearman ρ per measure between two feature vectors (measure-major).
fn rho(a: &[f64], b: &[f64]) -> Vec<f64> {
    stats::spearman_per_block(a, b, MEASURES.len())
}

/// The seed study's analyses.
#[derive(Clone, Copy, Debug, ValueEnum)]
// The values are explained in the flag's help: a doc comment on a value would become clap's
// help for it and switch --help to the long layout.
#[allow(missing_docs)]
pub enum StudyName {
    Validate,
    Noise,
    Size,
    Reference,
}

/// Arguments of `otofit study`.
#[derive(Args, Debug)]
pub struct StudyArgs {
    /// validate (coverage and recovery on unseen simulations), noise (training noise
    /// against test noise), size (training-set size), reference (the reference ear).
    pub name: StudyName,
    /// Output folder (created): tables, JSON and SVG figures.
    #[arg(long)]
    pub out: PathBuf,
    /// Model for `validate` and `reference`.
    #[arg(long, default_value = "models/default.otofit")]
    pub model: PathBuf,
    /// Unseen simulations for `validate`.
    #[arg(long, default_value_t = 200)]
    pub n: usize,
    /// Training-set size for `noise`; the largest size for `size` (then /10, /100).
    #[arg(long, default_value_t = 10_000)]
    pub train_rows: usize,
    /// Epochs at most for the models `noise` and `size` train.
    #[arg(long, default_value_t = 300)]
    pub max_epochs: usize,
    /// Seed of the simulations, the training and the posterior draws.
    #[arg(long, default_value_t = 0)]
    pub seed: u64,
    /// `reference` only: the simulator of the least-squares fit and the re-simulations
    /// (the posterior and its fit check still come from --model and its simulator).
    #[command(flatten)]
    pub drum: super::drum::DrumOpts,
    /// `validate` only: also refine each MAP by least squares against the observation
    /// (Levenberg–Marquardt from the flow's MAP, at most this many steps; 0 = off) and
    /// report the refined re-simulation beside the flow's.
    #[arg(long, default_value_t = 0)]
    pub refine: usize,
}

/// Posterior draws re-simulated, as figure series (the first one labelled).
fn draw_series(draws: &[Vec<f64>]) -> impl Iterator<Item = plot::Series<'_>> {
    draws.iter().enumerate().map(|(k, d)| plot::Series {
        x: d,
        color: plot::DRAW,
        width: 1.0,
        opacity: 0.5,
        label: (k == 0).then_some("posterior draws re-simulated"),
    })
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
        params: PARAMS.iter().map(npe::Param::from).collect(),
        feature_names: feature_names(model.frequencies()),
        frequencies_hz: model.frequencies().to_vec(),
        groups: vec![],
        noise_std: default_noise_std(model),
        theta: t,
        x,
        skipped: 0,
    }
}

fn write(out: &Path, name: &str, text: &str) -> Result<()> {
    std::fs::create_dir_all(out)?;
    std::fs::write(out.join(name), text)?;
    Ok(())
}

/// Corner plot of posterior samples over the model's prior box (MAP in red, truth in green).
pub(crate) fn corner(npe: &Npe, samples: &[Vec<f64>], truth: Option<&[f64]>, map: &[f64], title: &str) -> String {
    plot::posterior_corner(npe.params(), samples, truth, map, title)
}

/// Posterior summary of one observation: CV per parameter and ρ of the MAP re-simulation.
fn infer_one(
    model: &Model,
    npe: &Npe,
    x: &[f64],
    truth_x: &[f64],
    seed: u64,
) -> Result<(npe::Inference, Vec<f64>, Vec<f64>)> {
    let inf = npe.infer(&Obs { x, present: None }, 1000, seed)?;
    let map_x = run_rows(model, &Design::default(), std::slice::from_ref(&inf.map), 0, None).remove(0)?;
    let r = rho(&map_x, truth_x);
    Ok((inf, map_x, r))
}

/// Runs `otofit study`.
pub fn run(a: StudyArgs) -> Result<()> {
    check_args(&a)?;
    let mut config = ModelConfig::default();
    a.drum.apply(&mut config)?;
    let model = Model::new(config)?;
    let noise = Noise { std: default_noise_std(&model), scale: 1.0, seed: a.seed ^ 0x0B5 };
    match a.name {
        StudyName::Validate => validate(&a, &model, &noise),
        StudyName::Reference => reference(&model, &a.model, &a.out, a.seed, &a.drum.starts()),
        StudyName::Noise | StudyName::Size => noise_or_size(&a, &model, &noise),
    }
}

/// Refuses arguments out of their ranges, naming the flag.
fn check_args(a: &StudyArgs) -> Result<()> {
    if !(1..=100_000).contains(&a.n) {
        bail!("--n must be 1..=100000 (got {})", a.n);
    }
    if !(100..=1_000_000).contains(&a.train_rows) {
        bail!("--train-rows must be 100..=1000000 (got {})", a.train_rows);
    }
    if !(1..=5000).contains(&a.max_epochs) {
        bail!("--max-epochs must be 1..=5000 (got {})", a.max_epochs);
    }
    if a.refine > 200 {
        bail!("--refine must be 0..=200 steps (got {})", a.refine);
    }
    if a.refine > 0 && !matches!(a.name, StudyName::Validate) {
        bail!("--refine only applies to `study validate`");
    }
    if a.drum.is_set() && !matches!(a.name, StudyName::Reference) {
        bail!("--drum, --drum-loss, --incus-lateral and --joint-pads only apply to `study reference`");
    }
    Ok(())
}

/// What `study validate` gathers over the unseen simulations.
struct Validation {
    /// ρ per measure, per simulation.
    rhos: Vec<Vec<f64>>,
    /// CV per parameter, per simulation.
    cvs: Vec<Vec<f64>>,
    /// Simulations with the truth inside the 90 % interval, per parameter.
    inside: Vec<usize>,
    /// RMS residual (MAP − truth)/σ per measure, per simulation.
    rms: Vec<Vec<f64>>,
    /// With `--refine`: ρ per measure and RMS residual per measure of the refined MAP.
    refined: Vec<(Vec<f64>, Vec<f64>)>,
}

/// The studies re-simulate the model's parameters: refuse a model trained on another
/// simulator's parameters or features (e.g. an older version's) with a message, not a
/// wrong answer.
fn same_simulator(npe: &Npe, path: &Path) -> Result<()> {
    crate::discrepancy::fitcheck::simulator_for(npe).map(|_| ()).with_context(|| {
        let names: Vec<&str> = npe.params().iter().map(|p| p.name.as_str()).collect();
        format!(
            "{}: its parameters ({}) are not this simulator's ({}); retrain it on `otofit simulate` data",
            path.display(),
            names.join(", "),
            crate::sim::PARAMS.iter().map(|p| p.name).collect::<Vec<_>>().join(", ")
        )
    })
}

/// `study validate`: unseen simulations with 1× noise, inferred and re-simulated.
fn validate(a: &StudyArgs, model: &Model, noise: &Noise) -> Result<()> {
    let npe = Npe::load(&a.model)?;
    same_simulator(&npe, &a.model)?;
    let held = simulated(model, a.n, a.seed ^ 0x7E57);
    let mut v = Validation {
        rhos: vec![],
        cvs: vec![vec![]; N_PARAMS],
        inside: vec![0usize; N_PARAMS],
        // ρ is blind to offsets (a MAP spectrum 20 dB low can rank-correlate perfectly),
        // so the RMS residual in noise units, per measure, goes beside it.
        rms: vec![vec![]; MEASURES.len()],
        refined: vec![],
    };
    for (i, (t, x0)) in held.theta.iter().zip(&held.x).enumerate() {
        let x = noise.apply(x0, i);
        let (inf, map_x, r) = infer_one(model, &npe, &x, x0, i as u64)?;
        for (k, s) in inf.summaries.iter().enumerate() {
            v.cvs[k].push(s.cv);
            v.inside[k] += usize::from(t[k] >= s.q05 && t[k] <= s.q95);
        }
        v.rhos.push(r);
        let rms = rms_per_measure(model, noise, &map_x, x0);
        for (out, e) in v.rms.iter_mut().zip(rms) {
            out.push(e);
        }
        if a.refine > 0 {
            let obs = crate::discrepancy::fit::Observation { x: x.clone(), sigma: noise.std.clone() };
            let design = Design::default();
            let best = crate::discrepancy::fit::fit(model, &design, std::slice::from_ref(&inf.map), &obs, a.refine)
                .map_or_else(|| inf.map.clone(), |f| f.row);
            let refined_x = run_rows(model, &design, std::slice::from_ref(&best), 0, None).remove(0)?;
            v.refined.push((rho(&refined_x, x0), rms_per_measure(model, noise, &refined_x, x0)));
        }
        if i < 5 {
            validate_figures(a, model, &npe, noise, i, (t, x0, &x), &inf, &map_x)?;
        }
    }
    validate_report(a, &v)
}

/// RMS residual (simulated − truth)/σ of each measure.
fn rms_per_measure(model: &Model, noise: &Noise, sim_x: &[f64], x0: &[f64]) -> Vec<f64> {
    let nf = model.frequencies().len();
    (0..MEASURES.len())
        .map(|m| {
            let ss: f64 = (m * nf..(m + 1) * nf)
                .map(|i| (crate::discrepancy::fit::feature_residual(i, nf, sim_x[i], x0[i]) / noise.std[i]).powi(2))
                .sum();
            (ss / nf as f64).sqrt()
        })
        .collect()
}

/// Figures of unseen simulation `i` (truth θ, noise-free x0, observed x): spectra with
/// five posterior draws re-simulated, and the corner plot.
#[allow(clippy::too_many_arguments)]
fn validate_figures(
    a: &StudyArgs,
    model: &Model,
    npe: &Npe,
    noise: &Noise,
    i: usize,
    (t, x0, x): (&[f64], &[f64], &[f64]),
    inf: &npe::Inference,
    map_x: &[f64],
) -> Result<()> {
    let f = model.frequencies();
    // Five posterior draws re-simulated, and the observation's noise band.
    let draws: Vec<Vec<f64>> = run_rows(model, &Design::default(), &inf.samples[..5.min(inf.samples.len())], 0, None)
        .into_iter()
        .filter_map(|r| r.ok())
        .collect();
    let (lo, hi) = plot::plus_minus(x, &noise.std);
    let mut series = vec![plot::Series {
        x,
        color: plot::OBS,
        width: 2.0,
        opacity: 1.0,
        label: Some("noisy simulation (observation)"),
    }];
    series.extend(draw_series(&draws));
    series.push(plot::Series { x: x0, color: plot::TRUTH, width: 1.5, opacity: 1.0, label: Some("ground truth") });
    series.push(plot::Series {
        x: map_x,
        color: plot::MAP,
        width: 1.5,
        opacity: 1.0,
        label: Some("MAP re-simulation"),
    });
    let band = [plot::Band { lo: &lo, hi: &hi, color: plot::NOISE, label: "observation ± test–retest STD" }];
    write(
        &a.out,
        &format!("validate_{i}_spectra.svg"),
        &plot::spectra(&format!("Unseen simulation {i}"), f, &band, &series),
    )?;
    write(
        &a.out,
        &format!("validate_{i}_corner.svg"),
        &corner(npe, &inf.samples, Some(t), &inf.map, &format!("Posterior, unseen simulation {i}")),
    )?;
    Ok(())
}

/// The table, JSON and page of `study validate`.
fn validate_report(a: &StudyArgs, v: &Validation) -> Result<()> {
    let (rhos, cvs, inside, rms) = (&v.rhos, &v.cvs, &v.inside, &v.rms);
    let names: Vec<&str> = PARAMS.iter().map(|p| p.name).collect();
    let n = rhos.len() as f64;
    let mean_rho: Vec<f64> = (0..MEASURES.len()).map(|m| rhos.iter().map(|r| r[m]).sum::<f64>() / n).collect();
    let all = mean_rho.iter().sum::<f64>() / MEASURES.len() as f64;
    let med = |v: Vec<f64>| stats::median_upper(&stats::sorted(v));
    println!(
        "validate: {} unseen simulations, 1× noise; mean Spearman ρ (MAP re-simulation vs truth) {all:.4} (study: 0.998)",
        rhos.len()
    );
    for (m, r) in MEASURES.iter().zip(&mean_rho) {
        println!(
            "  ρ {:<11} {r:.4}   median RMS (MAP − truth)/σ {:.2}",
            m.name,
            med(rms[MEASURES.iter().position(|x| x.name == m.name).unwrap_or(0)].clone())
        );
    }
    let refined = (!v.refined.is_empty()).then(|| {
        let k = v.refined.len() as f64;
        let rho: Vec<f64> = (0..MEASURES.len()).map(|m| v.refined.iter().map(|r| r.0[m]).sum::<f64>() / k).collect();
        let rms: Vec<f64> = (0..MEASURES.len()).map(|m| med(v.refined.iter().map(|r| r.1[m]).collect())).collect();
        let all = rho.iter().sum::<f64>() / MEASURES.len() as f64;
        println!("MAP refined by least squares (≤ {} Levenberg–Marquardt steps): mean ρ {all:.4}", a.refine);
        for ((m, r), e) in MEASURES.iter().zip(&rho).zip(&rms) {
            println!("  ρ {:<11} {r:.4}   median RMS (refined − truth)/σ {e:.2}", m.name);
        }
        json!({ "steps": a.refine, "mean_rho": all, "rho_per_measure": MEASURES.iter().map(|m| m.name).zip(&rho).collect::<Vec<_>>(),
            "median_rms_sigma": MEASURES.iter().map(|m| m.name).zip(&rms).collect::<Vec<_>>() })
    });
    println!("{:<14} {:>10} {:>14}", "parameter", "median CV", "in 90 % int.");
    for k in 0..N_PARAMS {
        println!("{:<14} {:>10.3} {:>13.1}%", names[k], med(cvs[k].clone()), 100.0 * inside[k] as f64 / n);
    }
    let rms_med: Vec<f64> = rms.iter().map(|v| med(v.clone())).collect();
    let doc = json!({ "n": rhos.len(), "mean_rho": all, "median_rms_sigma": MEASURES.iter().map(|m| m.name).zip(&rms_med).collect::<Vec<_>>(), "rho_per_measure": MEASURES.iter().map(|m| m.name).zip(&mean_rho).collect::<Vec<_>>(),
        "median_cv": names.iter().zip(cvs.iter().map(|c| med(c.clone()))).collect::<Vec<_>>(),
        "coverage90": names.iter().zip(inside.iter().map(|&c| c as f64 / n)).collect::<Vec<_>>(), "refined": refined });
    write(&a.out, "validate.json", &serde_json::to_string_pretty(&doc)?)?;
    let mut p = Page::new("otofit study validate: unseen simulations");
    p.text(&format!("{} unseen prior draws, simulated, 1× test–retest noise added, inferred with {}; MAP re-simulated and compared with the noise-free truth. Study (Motallebzadeh et al. 2025, Fig. 2): mean ρ 0.998.", rhos.len(), a.model.display()));
    p.heading("MAP re-simulation vs truth").table(
        &["measure", "mean Spearman ρ", "median RMS residual / σ"],
        MEASURES
            .iter()
            .zip(&mean_rho)
            .zip(&rms_med)
            .map(|((m, r), e)| vec![m.name.into(), format!("{r:.4}"), format!("{e:.2}")])
            .chain([vec!["all".into(), format!("{all:.4}"), String::new()]])
            .collect(),
    );
    p.heading("Parameters").table(
        &["parameter", "median CV", "truth inside 90 % interval"],
        (0..N_PARAMS)
            .map(|k| {
                vec![
                    names[k].into(),
                    format!("{:.3}", med(cvs[k].clone())),
                    format!("{:.1} %", 100.0 * inside[k] as f64 / n),
                ]
            })
            .collect(),
    );
    p.heading("Five unseen simulations");
    for i in 0..rhos.len().min(5) {
        p.figure(
            &format!("validate_{i}_spectra.svg"),
            &format!("simulation {i}: observation ± STD, five posterior draws, truth, MAP re-simulation"),
        );
        p.figure(&format!("validate_{i}_corner.svg"), &format!("simulation {i}: posterior, truth (green), MAP (red)"));
    }
    write(&a.out, "report.html", &p.render())?;
    Ok(())
}

/// One model of `study noise`/`size` and what it says about the observation.
struct SizeRun {
    row: serde_json::Value,
    table: Vec<String>,
    figure: (String, String),
    run: (String, Vec<[f64; 3]>),
}

/// Trains on the first `size` rows of `ds` with the noise model scaled by `level` and
/// infers the observation `x` (noise-free `x0`, parameters `truth`).
fn size_run(
    a: &StudyArgs,
    model: &Model,
    ds: &Dataset,
    (size, level): (usize, f64),
    (truth, x0, x): (&[f64], &[f64], &[f64]),
) -> Result<SizeRun> {
    let names: Vec<&str> = PARAMS.iter().map(|p| p.name).collect();
    let sub = Dataset { theta: ds.theta[..size].to_vec(), x: ds.x[..size].to_vec(), ..simulated(model, 0, 0) };
    let s = TrainSettings { noise_scale: level, seed: a.seed, max_epochs: a.max_epochs, ..TrainSettings::default() };
    let npe = npe::train(&sub, &s, &mut |_| true)?;
    let (inf, _, r) = infer_one(model, &npe, x, x0, 1)?;
    let label = format!("n{size}_noise{level}");
    write(
        &a.out,
        &format!("{label}_corner.svg"),
        &corner(&npe, &inf.samples, Some(truth), &inf.map, &format!("{size} simulations, {level}× noise")),
    )?;
    let mean_rho = r.iter().sum::<f64>() / r.len() as f64;
    let cv: Vec<f64> = inf.summaries.iter().map(|s| s.cv).collect();
    // Width in decades of the 90 % interval: robust where CV saturates
    // (log-uniform posteriors as wide as the prior have CV > 1).
    let width = inf.summaries.iter().map(|s| (s.q95 / s.q05).log10()).sum::<f64>() / N_PARAMS as f64;
    println!(
        "{size:>6} simulations, noise {level:>4}×: mean 90 % width {width:.3} decades, mean CV {:.3}, mean ρ {mean_rho:.3}, epochs {}  CV per parameter {:?}",
        cv.iter().sum::<f64>() / N_PARAMS as f64,
        npe.header.training.epochs,
        cv.iter().map(|c| (c * 1000.0).round() / 1000.0).collect::<Vec<_>>()
    );
    let run_label =
        if matches!(a.name, StudyName::Noise) { format!("{level}× noise") } else { format!("{size} simulations") };
    let run = (run_label, inf.summaries.iter().map(|s| [s.q05, s.median, s.q95]).collect::<Vec<_>>());
    let figure = (
        format!("{label}_corner.svg"),
        format!("{size} simulations, {level}× noise: posterior, truth (green), MAP (red)"),
    );
    let table = vec![
        size.to_string(),
        format!("{level}×"),
        format!("{width:.3}"),
        format!("{:.3}", cv.iter().sum::<f64>() / N_PARAMS as f64),
        format!("{mean_rho:.3}"),
        npe.header.training.epochs.to_string(),
    ];
    let row = json!({ "train_rows": size, "noise_scale": level, "cv": names.iter().zip(&cv).collect::<Vec<_>>(), "mean_cv": cv.iter().sum::<f64>() / N_PARAMS as f64, "mean_width_decades": width, "rho": r, "mean_rho": mean_rho, "epochs": npe.header.training.epochs });
    Ok(SizeRun { row, table, figure, run })
}

/// `study noise` (training noise 0.1×, 1×, 10×) and `study size` (100×, 10×, 1× fewer
/// simulations): one observation inferred by each model.
fn noise_or_size(a: &StudyArgs, model: &Model, noise: &Noise) -> Result<()> {
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
    let ds = simulated(model, *sizes.last().unwrap_or(&0), a.seed);
    // The same observation for every model: a mid-prior ear with 1× noise.
    let truth = Design::default().draw(a.seed ^ 0x0B5E, 0, 1).remove(0);
    let x0 = run_rows(model, &Design::default(), std::slice::from_ref(&truth), 0, None).remove(0)?;
    let x = noise.apply(&x0, 0);
    let (mut rows, mut table, mut figs, mut runs) = (vec![], vec![], vec![], vec![]);
    for &size in &sizes {
        for &level in &levels {
            let r = size_run(a, model, &ds, (size, level), (&truth, &x0, &x))?;
            rows.push(r.row);
            table.push(r.table);
            figs.push(r.figure);
            runs.push(r.run);
        }
    }
    let name = if matches!(a.name, StudyName::Noise) { "noise.json" } else { "size.json" };
    write(&a.out, name, &serde_json::to_string_pretty(&json!({ "truth": truth, "runs": rows }))?)?;
    let noise_study = matches!(a.name, StudyName::Noise);
    let stem = if noise_study { "noise" } else { "size" };
    let dims: Vec<plot::Dim<'_>> = PARAMS
        .iter()
        .zip(&truth)
        .map(|(p, &t)| plot::Dim {
            name: p.name,
            unit: p.unit,
            low: p.low,
            high: p.high,
            log: p.scale == crate::sim::params::Scale::Log10,
            truth: Some(t),
            map: None,
        })
        .collect();
    let run_refs: Vec<(&str, Vec<[f64; 3]>)> = runs.iter().map(|(l, q)| (l.as_str(), q.clone())).collect();
    write(
        &a.out,
        &format!("{stem}_intervals.svg"),
        &plot::intervals(&format!("Posterior 90 % intervals, one observation ({stem} study)"), &dims, &run_refs),
    )?;
    let mut p = Page::new(if noise_study {
        "otofit study noise: training noise 0.1×, 1×, 10×"
    } else {
        "otofit study size: 100×, 10×, 1× fewer simulations"
    });
    p.text(if noise_study {
        "One observation (a prior draw with 1× noise) inferred by models trained with the noise model scaled 0.1×, 1× and 10×. Study (Fig. 4): CV about 7× larger from 1× to 10×; ρ 0.96 → 0.94."
    } else {
        "One observation (a prior draw with 1× noise) inferred by models trained on nested subsets of one simulated set. Study (Fig. 5): posteriors narrow as the training set grows."
    });
    p.table(&["simulations", "noise", "mean 90 % width (decades)", "mean CV", "mean ρ", "epochs"], table);
    p.figure(&format!("{stem}_intervals.svg"), "90 % intervals and medians per parameter, one line per model");
    for (file, caption) in &figs {
        p.figure(file, caption);
    }
    write(&a.out, "report.html", &p.render())?;
    Ok(())
}

/// What the reference study computes: the posterior, its predictive check, the
/// least-squares fit and the readings.
struct ReferenceFit {
    r: crate::reference::Reference,
    inf: npe::Inference,
    c: crate::discrepancy::workflow::Check,
    draws_rho: Vec<Vec<f64>>,
    best: crate::discrepancy::Fit,
    /// The least-squares fit's reduced χ² from each set of starts (the posterior's, and
    /// the drum's tuned point when it has one).
    starts_chi2: Vec<(String, f64)>,
    best_x: Vec<f64>,
    best_rho: Vec<f64>,
    map_rho: Vec<f64>,
    /// The measures the reference ear holds (`MEASURES` indices; no umbo velocity).
    measured: Vec<usize>,
    mean_abs: f64,
    best_abs: f64,
    differential: Vec<npe::normal::Differential>,
    fit: Result<crate::discrepancy::fitcheck::FitCheck, crate::discrepancy::fitcheck::FitCheckError>,
}

/// Inference on the measured-like reference ear: MAP and five posterior draws
/// re-simulated, ρ per measure, predictive check and the differential reading.
fn reference(model: &Model, path: &Path, out: &Path, seed: u64, extra: &[Vec<f64>]) -> Result<()> {
    let npe = &Npe::load(path)?;
    same_simulator(npe, path)?;
    let r = crate::reference::build(model.frequencies())?;
    write(out, "reference_obs.csv", &crate::reference::csv(&r.feature_names, &r.x))?;
    write(out, "reference_std.csv", &crate::reference::csv(&r.feature_names, &r.std))?;
    let e = reference_fit(model, npe, r, seed, extra)?;
    reference_figures(model, npe, out, &e)?;
    reference_print(path, &e)?;
    reference_report(out, &e)
}

/// The posterior of the reference ear, checked and compared with a least-squares fit.
fn reference_fit(
    model: &Model,
    npe: &Npe,
    r: crate::reference::Reference,
    seed: u64,
    extra: &[Vec<f64>],
) -> Result<ReferenceFit> {
    use crate::discrepancy::fit::Observation;
    use crate::discrepancy::workflow::check;
    let inf = npe.infer(&Obs { x: &r.x, present: None }, 1000, seed)?;
    let obs = Observation { x: r.x.clone(), sigma: r.std.clone() };
    let c = check(model, &Design::default(), &inf.samples[..200], &inf.map, &obs)?;
    let draws_rho: Vec<Vec<f64>> = c.draws_x.iter().map(|d| rho(d, &r.x)).collect();
    // The best the simulator can do (least squares from the MAP and four draws) separates
    // a model that cannot fit this ear from an estimator that extrapolates badly.
    let mut starts = vec![inf.map.clone()];
    starts.extend(inf.samples.iter().step_by(inf.samples.len() / 4).take(4).cloned());
    let lsq = |starts: &[Vec<f64>]| crate::discrepancy::fit::fit(model, &Design::default(), starts, &obs, 40);
    // `extra` (e.g. the line drum's tuned point) is fitted on its own too, so the report
    // says which starts found the best fit.
    let by_starts: Vec<(&str, Option<crate::discrepancy::Fit>)> = std::iter::once(("MAP + 4 draws", lsq(&starts)))
        .chain((!extra.is_empty()).then(|| ("the drum's tuned point", lsq(extra))))
        .collect();
    let starts_chi2: Vec<(String, f64)> = by_starts
        .iter()
        .map(|(name, f)| (name.to_string(), f.as_ref().map_or(f64::NAN, |f| f.reduced_chi2())))
        .collect();
    let best = by_starts
        .into_iter()
        .filter_map(|(_, f)| f)
        .min_by(|a, b| a.chi2.total_cmp(&b.chi2))
        .ok_or_else(|| anyhow::anyhow!("least-squares fit failed to simulate"))?;
    let best_x = run_rows(model, &Design::default(), std::slice::from_ref(&best.row), 0, None).remove(0)?;
    let best_rho = rho(&best_x, &r.x);
    let n = model.frequencies().len();
    let measured: Vec<usize> =
        (0..MEASURES.len()).filter(|m| r.x[m * n..(m + 1) * n].iter().all(|v| v.is_finite())).collect();
    let map_rho: Vec<f64> = MEASURES
        .iter()
        .map(|ms| c.spearman.iter().find(|(name, _)| name == ms.name).map_or(f64::NAN, |(_, v)| *v))
        .collect();
    let mean_over = |v: &[f64]| measured.iter().map(|&m| v[m].abs()).sum::<f64>() / measured.len().max(1) as f64;
    let (mean_abs, best_abs) = (mean_over(&map_rho), mean_over(&best_rho));
    // The fit check every inference carries (with the model's training noise, as a
    // request would get it; the check above uses the ear's own test-retest STD).
    let (differential, fit) =
        crate::discrepancy::fitcheck::checked_reading(npe, &r.x, &vec![true; r.x.len()], &inf, &inf.samples);
    Ok(ReferenceFit {
        r,
        inf,
        c,
        draws_rho,
        best,
        starts_chi2,
        best_x,
        best_rho,
        map_rho,
        measured,
        mean_abs,
        best_abs,
        differential,
        fit,
    })
}

/// The reference study's spectra, corner and residual figures.
fn reference_figures(model: &Model, npe: &Npe, out: &Path, e: &ReferenceFit) -> Result<()> {
    let f = model.frequencies();
    let (lo_obs, hi_obs) = plot::plus_minus(&e.r.x, &e.r.std);
    let mut series = vec![plot::Series {
        x: &e.r.x,
        color: plot::OBS,
        width: 2.0,
        opacity: 1.0,
        label: Some("reference ear (normative means)"),
    }];
    series.extend(draw_series(&e.c.draws_x));
    series.push(plot::Series {
        x: &e.c.map_x,
        color: plot::MAP,
        width: 1.5,
        opacity: 1.0,
        label: Some("MAP re-simulation"),
    });
    series.push(plot::Series {
        x: &e.best_x,
        color: plot::TRUTH,
        width: 1.5,
        opacity: 1.0,
        label: Some("least-squares fit"),
    });
    let bands = [
        plot::Band { lo: &lo_obs, hi: &hi_obs, color: plot::NOISE, label: "reference ± test–retest STD" },
        plot::Band { lo: &e.c.lo, hi: &e.c.hi, color: plot::BAND, label: "90 % posterior-predictive band" },
    ];
    write(
        out,
        "reference_spectra.svg",
        &plot::spectra("Reference ear: normative means, MAP and posterior draws re-simulated", f, &bands, &series),
    )?;
    write(out, "reference_corner.svg", &corner(npe, &e.inf.samples, None, &e.inf.map, "Posterior, reference ear"))?;
    write(
        out,
        "reference_residuals.svg",
        &plot::residual_map("Reference ear: standardised residuals (reference − predictive mean) / σ", f, &e.c.z),
    )?;
    Ok(())
}

/// The reference study's table on stdout.
fn reference_print(path: &Path, e: &ReferenceFit) -> Result<()> {
    let mean_abs = e.mean_abs;
    println!("reference: measured-like ear (reference/ear.json), model {}", path.display());
    println!("{:<11} {:>9} {:>19} {:>19}", "measure", "ρ (MAP)", "ρ (5 draws, mean)", "ρ (least squares)");
    for &m in &e.measured {
        let d = e.draws_rho.iter().map(|r| r[m]).sum::<f64>() / e.draws_rho.len().max(1) as f64;
        println!("{:<11} {:>9.3} {:>19.3} {:>19.3}", MEASURES[m].name, e.map_rho[m], d, e.best_rho[m]);
    }
    let best_abs = e.best_abs;
    println!(
        "mean |ρ|: MAP re-simulation {mean_abs:.3}, least-squares fit {best_abs:.3} (study, one temporal bone: 0.964)"
    );
    println!(
        "reduced χ²: posterior-predictive {:.2}, least-squares fit {:.2}",
        e.c.reduced_chi2,
        e.best.reduced_chi2()
    );
    if e.starts_chi2.len() > 1 {
        let by: Vec<String> = e.starts_chi2.iter().map(|(name, c)| format!("from {name} {c:.2}")).collect();
        println!("least-squares reduced χ² by starts: {}", by.join(", "));
    }
    match &e.fit {
        Ok(f) => println!(
            "fit check: ok {:?} (reduced χ² {:.2}, threshold {:.2}){}",
            f.ok,
            f.reduced_chi2,
            f.threshold.unwrap_or(f64::NAN),
            if f.ok == Some(false) { ": every reading withdrawn (unreliable)" } else { "" }
        ),
        Err(e) => println!("fit check: not available ({e})"),
    }
    for b in &e.c.bands {
        println!("  misfit: {}", b.describe());
    }
    println!("{:<14} {:>11} {:>11} {:>11} {:>7}", "parameter", "MAP", "q05", "q95", "CV");
    for s in &e.inf.summaries {
        println!("{:<14} {:>11.3e} {:>11.3e} {:>11.3e} {:>7.3}", s.name, s.map, s.q05, s.q95, s.cv);
    }
    println!("{}", serde_json::to_string_pretty(&e.differential)?);
    Ok(())
}

/// reference.json and the reference study's page.
fn reference_report(out: &Path, e: &ReferenceFit) -> Result<()> {
    let (mean_abs, best_abs) = (e.mean_abs, e.best_abs);
    let doc = json!({
        "mean_abs_rho": mean_abs,
        "rho_map": e.c.spearman,
        "rho_draws": e.draws_rho,
        "reduced_chi2": e.c.reduced_chi2,
        "least_squares": { "row": e.best.row, "rho": e.best_rho, "mean_abs_rho": best_abs, "reduced_chi2": e.best.reduced_chi2(), "reduced_chi2_by_starts": e.starts_chi2 },
        "misfit_bands": e.c.bands,
        "parameters": e.inf.summaries,
        "differential": e.differential,
        "fit": e.fit.as_ref().ok(),
        "citations": MEASURES.iter().map(|m| m.name).zip(&e.r.citations).collect::<Vec<_>>(),
    });
    write(out, "reference.json", &serde_json::to_string_pretty(&doc)?)?;
    let mut p = Page::new("otofit study reference: a measured-like ear");
    p.text("Normative mean spectra (reference/ear.json, citations below) inferred as one observation, MAP and five posterior draws re-simulated; a least-squares fit shows the best the simulator can do. Study (one temporal bone, Fig. 3): mean |ρ| 0.964.");
    p.heading("Spearman ρ against the reference").table(
        &["measure", "MAP", "5 draws (mean)", "least squares"],
        e.measured
            .iter()
            .map(|&m| {
                vec![
                    MEASURES[m].name.into(),
                    format!("{:.3}", e.map_rho[m]),
                    format!("{:.3}", e.draws_rho.iter().map(|r| r[m]).sum::<f64>() / e.draws_rho.len().max(1) as f64),
                    format!("{:.3}", e.best_rho[m]),
                ]
            })
            .collect(),
    );
    p.text(&format!("Mean |ρ|: MAP {mean_abs:.3}, least squares {best_abs:.3}. Reduced χ²: posterior-predictive {:.2}, least squares {:.2}.", e.c.reduced_chi2, e.best.reduced_chi2()));
    p.heading("Posterior and normal ranges (information, not a diagnosis)").table(
        &["parameter", "MAP", "90 % interval", "CV", "P(below)", "P(within)", "P(above)", "reading", "associated with"],
        e.inf
            .summaries
            .iter()
            .zip(&e.differential)
            .map(|(s, d)| {
                vec![
                    format!("{} ({})", s.name, s.unit),
                    format!("{:.3e}", s.map),
                    format!("{:.3e} … {:.3e}", s.q05, s.q95),
                    format!("{:.3}", s.cv),
                    format!("{:.2}", d.p_below),
                    format!("{:.2}", d.p_within),
                    format!("{:.2}", d.p_above),
                    d.reading.to_string(),
                    d.associated_with.unwrap_or("").to_string(),
                ]
            })
            .collect(),
    );
    if !e.c.bands.is_empty() {
        p.heading("Where the reference and the model disagree")
            .table(&["band"], e.c.bands.iter().map(|b| vec![b.describe()]).collect());
    }
    p.figure("reference_spectra.svg", "reference ± STD, MAP, five draws, least-squares fit, 90 % predictive band");
    p.figure("reference_residuals.svg", "standardised residuals per measure and frequency");
    p.figure("reference_corner.svg", "posterior (MAP red)");
    p.heading("Sources");
    for (m, cite) in MEASURES.iter().zip(&e.r.citations) {
        p.text(&format!("{}: {cite}", m.name));
    }
    write(out, "report.html", &p.render())?;
    Ok(())
}
