//! `otofit calibrate`: coverage and SBC ranks of a model on held-out simulations; with
//! `--tune`, also the post-hoc recalibration (base temperature) and the fit check's null,
//! written into the model; with `--null-only`, the fit check's null alone, for the model
//! and every flow it holds; with `--diagnose-null`, the diagnose workflow's null, written
//! into the model.

use crate::bench::posterior::check_from_hz;
use crate::npe::Obs;
use crate::npe::calibrate::{TUNE_LEVELS, calibrate_given, tune_temperature};
use crate::npe::{Dataset, Npe};
use anyhow::{Context, Result, bail};
use clap::Args;
use std::path::PathBuf;

/// Arguments of `otofit calibrate`.
#[derive(Args, Debug)]
pub struct CalibrateArgs {
    /// Model file (.otofit).
    #[arg(long)]
    pub model: PathBuf,
    /// Held-out dataset folder (not the training set).
    #[arg(long, required_unless_present_any = ["diagnose_null", "null_only"])]
    pub data: Option<PathBuf>,
    /// Rows used (the first N; at most the dataset's rows).
    #[arg(long, default_value_t = 200)]
    pub n: usize,
    /// Posterior samples per row (10..=100000).
    #[arg(long, default_value_t = 500)]
    pub samples: usize,
    /// Seed of the noise added to the held-out spectra and of the posterior draws.
    #[arg(long, default_value_t = 0)]
    pub seed: u64,
    /// Tune the base temperature on these rows (so joint HPD coverage reaches each level
    /// of 50/80/90/95 % less 0.01) and measure the fit check's null on fresh simulations;
    /// write both into the model (or into --out). Measure the result on other rows.
    #[arg(long)]
    pub tune: bool,
    /// Where --tune writes the model (default: over --model).
    #[arg(long)]
    pub out: Option<PathBuf>,
    /// Held-out simulations behind the fit check's null (with --tune or --null-only).
    #[arg(long, default_value_t = 500)]
    pub null_cases: usize,
    /// Folder for calibration.json and calibration.svg (coverage curve, SBC rank
    /// histograms), besides the table on stdout.
    #[arg(long)]
    pub report: Option<PathBuf>,
    /// Run the held-out coverage this many times (1..=20), with seeds --seed, --seed + 1,
    /// …: each level's mean, range and standard deviation over the runs (one run's
    /// coverage moves with its seed by about as much as its binomial error).
    #[arg(long, default_value_t = 1, conflicts_with_all = ["tune", "report", "json"])]
    pub seeds: usize,
    /// Print the full result as JSON (coverage per level, SBC ranks) instead of the table.
    #[arg(long, conflicts_with = "tune")]
    pub json: bool,
    /// Measure the diagnose workflow's null on this many effect-free simulations and
    /// write it into the model (or into --out), so that `otofit diagnose` and diagnose
    /// jobs skip their per-ear null. Needs no --data.
    #[arg(long, conflicts_with_all = ["tune", "report", "json"])]
    pub diagnose_null: Option<usize>,
    /// Measure the fit check's null again on --null-cases fresh simulations, for the model
    /// and every flow it holds (full-measure, measure-set), keeping their temperatures;
    /// write the result into the model (or into --out). Needs no --data.
    #[arg(long, conflicts_with_all = ["tune", "report", "json", "diagnose_null"])]
    pub null_only: bool,
    /// Feature groups given, per stored null (comma-separated group names, or `all`);
    /// repeat for several sets. An ear whose measures are not one of these sets gets its
    /// null measured per ear.
    #[arg(long, default_values_t = ["all".to_string(), "impedance,absorbance".to_string()])]
    pub diagnose_groups: Vec<String>,
    /// Give the held-out rows only these feature groups (comma-separated), as a clinic's
    /// subset of measures: each row is answered by the flow of the file that answers such
    /// ears (a measure-set flow of exactly these groups, else the main flow).
    #[arg(long, value_delimiter = ',', conflicts_with_all = ["tune", "null_only", "diagnose_null"])]
    pub measures: Vec<String>,
    /// Give the held-out rows from this frequency up (Hz, ≤ 500), as a device's export
    /// from 226 Hz: the features below it are left out and a band-masked flow answers.
    #[arg(long, conflicts_with_all = ["tune", "null_only", "diagnose_null"])]
    pub from_hz: Option<f64>,
}

/// How far below each level the tuned coverage may stay (held-out rows are noisy).
const TUNE_SLACK: f64 = 0.01;

/// The most runs `--seeds` asks for.
const MAX_SEEDS: usize = 20;

/// The first `n` held-out rows as (θ, x), x with the model's training noise drawn with
/// `seed` (held-out x are noise-free simulations) and the model error it was trained
/// with, if any: the inputs its training saw.
fn noisy_rows(model: &Npe, ds: &Dataset, n: usize, seed: u64) -> Result<Vec<(Vec<f64>, Vec<f64>)>> {
    let noise = crate::sim::batch::Noise { std: model.header.noise_std.clone(), scale: model.header.noise_scale, seed };
    let mut rows: Vec<(Vec<f64>, Vec<f64>)> =
        ds.theta.iter().zip(&ds.x).take(n).enumerate().map(|(i, (t, x))| (t.clone(), noise.apply(x, i))).collect();
    model.add_model_error(rows.iter_mut().map(|(_, x)| x), seed)?;
    Ok(rows)
}

/// The joint HPD coverage at `TUNE_LEVELS` of one calibration.
fn at_levels(cal: &crate::npe::calibrate::Calibration) -> Vec<f64> {
    let at = |l: f64| cal.levels.iter().position(|v| (v - l).abs() < 1e-9).map_or(f64::NAN, |k| cal.coverage[k]);
    TUNE_LEVELS.iter().map(|&l| at(l)).collect()
}

/// `--seeds K`: the held-out coverage K times, seeds --seed, --seed + 1, …; each run on
/// stderr, each level's mean, range and standard deviation on stdout.
fn over_seeds(model: &Npe, ds: &Dataset, args: &CalibrateArgs, present: Option<&[bool]>) -> Result<()> {
    let mut runs: Vec<Vec<f64>> = Vec::with_capacity(args.seeds);
    for r in 0..args.seeds {
        let seed = args.seed.wrapping_add(r as u64);
        let rows = noisy_rows(model, ds, args.n, seed)?;
        let cal = calibrate_given(model, &rows, args.samples, seed, present, &mut |_| {})?;
        let c = at_levels(&cal);
        let shown: Vec<String> = c.iter().map(|v| format!("{v:.3}")).collect();
        eprintln!("seed {seed}: joint HPD coverage at 50/80/90/95 % {}", shown.join(" "));
        runs.push(c);
    }
    println!(
        "joint HPD coverage on {} held-out rows ({} samples each, temperature {:.3}), {} seeds from {}: mean \
         (lowest–highest, standard deviation over the runs)",
        args.n.min(ds.theta.len()),
        args.samples,
        answering(model, present).header.temperature,
        args.seeds,
        args.seed
    );
    for (j, l) in TUNE_LEVELS.iter().enumerate() {
        let v: Vec<f64> = runs.iter().map(|c| c[j]).collect();
        let (mean, var) = crate::stats::mean_var_sample(&v);
        let sd = var.sqrt();
        let (lo, hi) = v.iter().fold((f64::INFINITY, f64::NEG_INFINITY), |(a, b), &x| (a.min(x), b.max(x)));
        println!("  {:>3.0} %  {mean:.3}  ({:+.3}; {lo:.3}–{hi:.3}, sd {sd:.3})", 100.0 * l, mean - l);
    }
    Ok(())
}

/// Runs `otofit calibrate`.
pub fn run(args: CalibrateArgs) -> Result<()> {
    if !(10..=100_000).contains(&args.samples) {
        bail!("--samples must be 10..=100000 (got {})", args.samples);
    }
    if args.n == 0 {
        bail!("--n must be at least 1");
    }
    if !(1..=MAX_SEEDS).contains(&args.seeds) {
        bail!("--seeds must be 1..={MAX_SEEDS} (got {})", args.seeds);
    }
    if (args.tune || args.null_only) && !(20..=100_000).contains(&args.null_cases) {
        bail!("--null-cases must be 20..=100000 (got {})", args.null_cases);
    }
    let mut model = Npe::load(&args.model)?;
    if let Some(cases) = args.diagnose_null {
        return diagnose_null(model, &args, cases);
    }
    if args.null_only {
        return fit_null_only(model, &args);
    }
    let data = args.data.as_ref().context("--data is required")?;
    let ds = Dataset::load(data)?;
    if ds.feature_names != model.header.feature_names {
        bail!("{}: its features differ from the model's", data.display());
    }
    if args.n > ds.theta.len() {
        bail!("--n {} exceeds the {} rows of {}", args.n, ds.theta.len(), data.display());
    }
    let present = given(&model, &args)?;
    let present = present.as_deref();
    if args.seeds > 1 {
        return over_seeds(&model, &ds, &args, present);
    }
    let rows = noisy_rows(&model, &ds, args.n, args.seed)?;
    if args.tune {
        let tuning = tune_temperature(&mut model, &rows, args.samples, args.seed, TUNE_SLACK)?;
        eprintln!(
            "temperature {:.3}: joint HPD coverage at {:?} on the tuning rows {:?} -> {:?}",
            tuning.temperature, TUNE_LEVELS, tuning.coverage_before, tuning.coverage_after
        );
        if !tuning.reached {
            eprintln!(
                "warning: no temperature in 1..4 brings the coverage to every level less {TUNE_SLACK}; \
                 kept {:.3}, which came closest. The flow is overconfident in a way a temperature \
                 cannot mend: train it longer or on more rows",
                tuning.temperature
            );
        }
        let null = crate::discrepancy::fitcheck::null(&model, args.null_cases, args.seed)
            .context("the fit check's null (only models of otofit's simulator have one)")?;
        eprintln!(
            "fit check null on {} simulations: reduced χ² threshold {:.3}, input score threshold {:.3} (quantile {})",
            null.cases, null.reduced_chi2, null.input_score, null.quantile
        );
        model.header.fit_null = Some(null);
        let out = args.out.as_ref().unwrap_or(&args.model);
        model.save(out)?;
        eprintln!("wrote {}", out.display());
        println!("{}", serde_json::to_string_pretty(&tuning)?);
        return Ok(());
    }
    if let Some(dir) = &args.report {
        std::fs::create_dir_all(dir).with_context(|| format!("--report {}: cannot create it", dir.display()))?;
    }
    let mut bar = super::progress::Progress::new("calibrated", "held-out rows", rows.len() as u64);
    let cal = calibrate_given(&model, &rows, args.samples, args.seed, present, &mut |done| bar.set(done as u64))?;
    bar.finish();
    if let Some(dir) = &args.report {
        let ranks: Vec<(&str, Vec<usize>)> = cal.sbc_ranks.iter().map(|r| (r.name.as_str(), r.ranks.clone())).collect();
        let title = format!("Calibration of {} on {} held-out simulations", args.model.display(), cal.rows);
        let svg = crate::plot::calibration(&title, &cal.levels, &cal.coverage, &ranks, cal.samples_per_row);
        std::fs::write(dir.join("calibration.svg"), svg)?;
        std::fs::write(dir.join("calibration.json"), serde_json::to_vec(&cal)?)?;
        eprintln!("wrote {0}/calibration.json and {0}/calibration.svg", dir.display());
    }
    if args.json {
        println!("{}", serde_json::to_string(&cal)?);
        return Ok(());
    }
    if let Some(p) = present {
        let flow = model.answering_name(&Obs { x: &vec![0.0; p.len()], present: Some(p) });
        println!(
            "rows given {} of {} features, answered by the {flow} flow",
            p.iter().filter(|&&g| g).count(),
            p.len()
        );
    }
    println!(
        "joint HPD coverage on {} held-out rows ({} samples each, temperature {:.3}):",
        cal.rows,
        cal.samples_per_row,
        answering(&model, present).header.temperature
    );
    for (l, c) in TUNE_LEVELS.iter().zip(at_levels(&cal)) {
        println!("  {:>3.0} %  {c:.3}  ({:+.3})", 100.0 * l, c - l);
    }
    println!(
        "per parameter: marginal 50 % coverage (from the SBC ranks), 90 %, SBC rank χ² (10 bins, 9 dof; 99 % \
         quantile 21.7)"
    );
    for (r, m) in cal.sbc_ranks.iter().zip(&cal.marginal_coverage90) {
        let (chi2, _) = r.chi2(cal.samples_per_row, 10);
        let half = central_share(&r.ranks, cal.samples_per_row, 0.5);
        let flag = if chi2 > 21.7 { "  (not uniform)" } else { "" };
        println!("  {:<16} {half:.3}  {m:.3}  {chi2:6.1}{flag}", r.name);
    }
    Ok(())
}

/// The features `--measures` and `--from-hz` give (None: every feature, as before).
fn given(model: &Npe, args: &CalibrateArgs) -> Result<Option<Vec<bool>>> {
    if args.measures.is_empty() && args.from_hz.is_none() {
        return Ok(None);
    }
    let from_hz = args.from_hz.unwrap_or(0.0);
    check_from_hz(from_hz)?;
    let present =
        model.header.features_given(&args.measures, from_hz).map_err(|e| anyhow::anyhow!("--measures: {e}"))?;
    Ok(Some(present))
}

/// The flow that answers rows of `present` (the main flow when every feature is given).
fn answering<'a>(model: &'a Npe, present: Option<&[bool]>) -> &'a Npe {
    match present {
        Some(p) => model.answering(&Obs { x: &vec![0.0; p.len()], present: Some(p) }),
        None => model,
    }
}

/// Share of rows whose truth lies inside the central `level` interval of its draws, read
/// off its SBC rank (the truth's rank among `samples` draws).
fn central_share(ranks: &[usize], samples: usize, level: f64) -> f64 {
    let (lo, hi) = ((1.0 - level) / 2.0 * samples as f64, (1.0 + level) / 2.0 * samples as f64);
    let inside = ranks.iter().filter(|&&r| (lo..=hi).contains(&(r as f64))).count();
    inside as f64 / ranks.len().max(1) as f64
}

/// Measures the fit check's null of the model and of each flow it holds, and writes them
/// into the model.
fn fit_null_only(mut model: Npe, args: &CalibrateArgs) -> Result<()> {
    use crate::discrepancy::fitcheck::null;
    let what = "the fit check's null (only models of otofit's simulator have one)";
    let report = |name: &str, n: &crate::npe::FitNull| {
        eprintln!(
            "{name}: fit check null on {} simulations: reduced χ² threshold {:.3}, worst measure {:.3}, input score \
             {:.3} (the check fails {:.1} % of them)",
            n.cases,
            n.reduced_chi2,
            n.measure_chi2,
            n.input_score,
            100.0 * (1.0 - n.quantile)
        )
    };
    let main = null(&model, args.null_cases, args.seed).context(what)?;
    report("main flow", &main);
    model.header.fit_null = Some(main);
    for flow in model.attached_mut() {
        let n = null(flow, args.null_cases, args.seed).context(what)?;
        let h = &flow.header;
        let name = if h.measures.is_empty() {
            "full-measure flow".to_string()
        } else {
            format!("measure-set flow {}{}", h.measures.join(","), if h.mask_bands { " (band masks)" } else { "" })
        };
        report(&name, &n);
        flow.header.fit_null = Some(n);
    }
    let out = args.out.as_ref().unwrap_or(&args.model);
    model.save(out)?;
    eprintln!("wrote {}", out.display());
    Ok(())
}

/// Measures the diagnose workflow's null for each `--diagnose-groups` set and writes it
/// into the model.
fn diagnose_null(mut model: Npe, args: &CalibrateArgs, cases: usize) -> Result<()> {
    use crate::discrepancy::workflow::{Settings, measure_null};
    use crate::jobs::limits::{NULL_CASES, check};
    check(&NULL_CASES, cases).map_err(|m| anyhow::anyhow!("--diagnose-null {m}"))?;
    let sets = args
        .diagnose_groups
        .iter()
        .map(|g| given_set(&model, g).with_context(|| format!("--diagnose-groups '{g}'")))
        .collect::<Result<Vec<_>>>()?;
    let sim = crate::sim::Model::new(crate::sim::ModelConfig::default())?;
    let noise = crate::sim::batch::Noise { std: model.header.noise_std.clone(), scale: 1.0, seed: args.seed };
    let s = Settings { null_cases: cases, seed: args.seed, extend: false, ..Settings::default() };
    let bar = super::progress::Progress::stages("diagnose null");
    let null = measure_null(&sim, &model, &noise, &sets, &s, &mut |k, n| {
        bar.message(&format!("feature set {} of {n}", (k + 1).min(n)))
    })?;
    bar.finish();
    for t in &null.subsets {
        eprintln!(
            "diagnose null on {} ears, {}: base reduced χ² threshold {:.3}, best-drop threshold {:.1}",
            null.cases,
            t.groups.join("+"),
            t.base_reduced_chi2,
            t.best_drop
        );
    }
    model.header.diagnose_null = Some(null);
    let out = args.out.as_ref().unwrap_or(&args.model);
    model.save(out)?;
    eprintln!("wrote {}", out.display());
    Ok(())
}

/// The features given when the named groups are (`all`: every feature).
fn given_set(model: &Npe, groups: &str) -> Result<Vec<bool>> {
    let f = model.header.feature_names.len();
    if groups.trim() == "all" {
        return Ok(vec![true; f]);
    }
    let names: Vec<&str> = groups.split(',').collect();
    Ok(model.header.features_of_groups(&names)?)
}
