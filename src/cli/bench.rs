//! `otofit bench ...`: speed figures measured on this machine (medians and ratios; the
//! README quotes them). Benchmarks, not tests: they never fail on a slow machine.

use crate::sim::batch::{self, Design};
use crate::sim::{Effects, Model, ModelConfig, Theta};
use anyhow::Result;
use clap::{Args, Subcommand};
use std::time::Instant;

/// `otofit bench`'s arguments: which benchmark.
#[derive(Args, Debug)]
pub struct BenchArgs {
    /// The benchmark to run.
    #[command(subcommand)]
    pub what: BenchWhat,
}

/// The benchmarks: each prints medians and ratios against its targets.
#[derive(Subcommand, Debug)]
pub enum BenchWhat {
    /// Simulator: one 50-frequency run on one core, and a parallel batch.
    Sim {
        /// Runs in the parallel batch.
        #[arg(long, default_value_t = 10_000)]
        runs: usize,
        /// The eardrum variant to time (the default model's drum unless given).
        #[command(flatten)]
        drum: super::drum::DrumOpts,
    },
    /// POST /infer latency: concurrent clients against an in-process server on loopback.
    Infer {
        /// Concurrent clients (closed loop: each sends its next request on the answer).
        #[arg(long, default_value_t = 16)]
        clients: usize,
        /// Requests per client.
        #[arg(long, default_value_t = 10)]
        requests: usize,
        /// Posterior samples per request.
        #[arg(long, default_value_t = 1000)]
        samples: usize,
        /// No server: `requests` inferences + fit checks of the same example in this
        /// process on one thread, by the flow the service answers it with, timed per phase
        /// (each phase's wall time is then its CPU time).
        #[arg(long)]
        direct: bool,
        /// The request's `posterior`: `exact` also samples the likelihood's posterior
        /// (short chains) in every request.
        #[arg(long, value_enum, default_value = "flow", conflicts_with = "direct")]
        posterior: super::infer::PosteriorArg,
        /// Instead of the example, six simulated seven-measure ears with findings (one
        /// side of the normal ranges, or both), one after another: per ear the request's
        /// latency and the differential's alternatives (`timing_ms.alternatives`).
        #[arg(long, conflicts_with_all = ["direct", "posterior"])]
        findings: bool,
    },
    /// POST /infer's exact posterior (short chains) on held-out simulated ears: 50 % and
    /// 90 % coverage, R-hat/ESS verdicts and wall time on every ear, and on the first
    /// `--reference` ears the C2ST against the long chain of `otofit infer --exact`.
    Exact(super::bench_exact::ExactArgs),
    /// NPE: training on a two-moons-like toy and on a middle-ear table, inference latency,
    /// held-out log-probability.
    Npe {
        /// A middle-ear dataset folder (e.g. from `otofit simulate --n 10000`); skipped if absent.
        #[arg(long)]
        data: Option<std::path::PathBuf>,
        /// A trained middle-ear model for the latency and held-out numbers.
        #[arg(long, default_value = "models/default.otofit")]
        model: std::path::PathBuf,
        /// Held-out middle-ear dataset folder.
        #[arg(long)]
        held: Option<std::path::PathBuf>,
        /// Seed of the middle-ear training (`otofit train --seed`).
        #[arg(long, default_value_t = 0)]
        seed: u64,
    },
    /// The trust layer: fit-check false alarms on the model's own ears, detection of
    /// strong hidden effects, readings of ears at the centre of the normal ranges.
    Fit {
        /// The model whose fit check is measured.
        #[arg(long, default_value = "models/default.otofit")]
        model: std::path::PathBuf,
        /// Cases per group (null, each effect, centre ears).
        #[arg(long, default_value_t = 100)]
        cases: usize,
        /// Seed of the cases and their noise.
        #[arg(long, default_value_t = 1)]
        seed: u64,
        /// Feature groups given, comma-separated (e.g. impedance,absorbance: WBT alone); all if empty.
        #[arg(long, default_value = "")]
        measures: String,
    },
    /// Posterior accuracy on standard SBI tasks: C2ST against reference posteriors and
    /// training time (JSON too).
    C2st(Box<super::bench_c2st::C2stArgs>),
    /// Ears from published middle-ear models otofit does not contain (Kringlebotn 1988,
    /// Hudde & Engel 1998), healthy and with three conditions, read by the model as
    /// `otofit infer` reads them: fit-check pass rate, right readings and confident wrong
    /// ones, per model × condition (table on stdout; crossmodel.md and crossmodel.json in
    /// --out).
    Crossmodel {
        /// Noisy ears per model × condition (otofit's 1× test–retest noise, one seed each).
        #[arg(long, default_value_t = 20)]
        ears: usize,
        /// Folder for crossmodel.md (the table) and crossmodel.json (every ear).
        #[arg(long)]
        out: std::path::PathBuf,
        /// The model that reads the ears.
        #[arg(long, default_value = "models/default.otofit")]
        model: std::path::PathBuf,
        /// Seed of the severities, the noise and the posterior draws.
        #[arg(long, default_value_t = 1)]
        seed: u64,
        /// Posterior samples per ear.
        #[arg(long, default_value_t = 1000)]
        samples: usize,
        /// Feature groups given, comma-separated (e.g. impedance,absorbance: WBT alone); all if empty.
        #[arg(long, default_value = "")]
        measures: String,
        /// Also diagnose every ear the fit check refuses (all measures given) with the
        /// discrepancy workflow, without retraining: misfits.md and misfits.json in --out.
        #[arg(long)]
        diagnose: bool,
        /// Also fit the differential's alternatives on the ears the fit check refuses
        /// (never shipped): what the constrained fits would name on an ear the model does
        /// not reproduce; a second table.
        #[arg(long)]
        alternatives_on_misfits: bool,
    },
    /// The shipped posterior (the flow) against the posterior under the model's own
    /// likelihood (least-squares fits, then a Metropolis chain, as `otofit infer --exact`)
    /// on held-out simulated ears, half prior draws and half near the model's
    /// degeneracies: coverage, interval widths, confident wrong readings, C2ST and wall
    /// time per ear (table on stdout; posterior.json in --out).
    Posterior {
        /// Held-out ears (1..=10000): the first half prior draws, the rest near degeneracies.
        #[arg(long)]
        ears: usize,
        /// Seed of the ears, their noise, the flow's draws, the chains and the C2STs.
        #[arg(long, default_value_t = 1)]
        seed: u64,
        /// Metropolis steps per ear (4000..=200000; fewer than the default 100000, the
        /// length measured calibrated, under-cover: for quick looks only).
        #[arg(long, default_value_t = crate::bench::posterior::DEFAULT_STEPS)]
        steps: usize,
        /// Feature groups given, comma-separated (e.g. impedance,absorbance: wideband
        /// tympanometry, answered by the masked flow and scored against the likelihood of
        /// those features alone); all if empty.
        #[arg(long, default_value = "")]
        measures: String,
        /// The lowest frequency given, in Hz (0..=500; 0: the whole grid), as a device
        /// that exports from 226 Hz: the features below it are left out.
        #[arg(long, default_value_t = 0.0)]
        from_hz: f64,
        /// Folder for posterior.json (every ear and the pooled scores); none if absent.
        #[arg(long)]
        out: Option<std::path::PathBuf>,
        /// The model whose flow is measured (its simulator and noise make the ears).
        #[arg(long, default_value = "models/default.otofit")]
        model: std::path::PathBuf,
    },
    /// The readings on the model's own simulated ears: for each tissue parameter and side
    /// of its normal range, ears with that one value outside the range (the rest inside),
    /// and healthy ears: how often the pathology is read on its side (sensitivity, also by
    /// distance beyond the limit) and how often a healthy value is read abnormal
    /// (specificity); table on stdout, readings.md and readings.json in --out.
    Readings {
        /// Noisy ears per group (healthy, and each parameter below or above its range).
        #[arg(long, default_value_t = 50)]
        ears: usize,
        /// Folder for readings.md (the table) and readings.json (every ear).
        #[arg(long)]
        out: std::path::PathBuf,
        /// The model that reads the ears (its simulator and noise make them).
        #[arg(long, default_value = "models/default.otofit")]
        model: std::path::PathBuf,
        /// Seed of the ears, their noise and the posterior draws.
        #[arg(long, default_value_t = 1)]
        seed: u64,
        /// Feature groups given, comma-separated (e.g. impedance,absorbance: WBT alone); all if empty.
        #[arg(long, default_value = "")]
        measures: String,
        /// Read the likelihood's own posterior (a Metropolis chain of this many steps per
        /// ear, 100000..=200000, about 9 s each) instead of the flow's.
        #[arg(long)]
        exact: Option<usize>,
    },
    /// Scaling with threads: dataset generation (CSV and .npy) and training epoch time at
    /// 1, 2, 4, … threads up to the cores, with speed-up and efficiency.
    Scale(super::bench_scale::ScaleArgs),
    /// Discrepancy naming on hidden-effect cases (simulator-only pipeline).
    Discrepancy {
        /// Hidden cases per effect.
        #[arg(long, default_value_t = 20)]
        cases: usize,
        /// Effect-free cases (false alarms).
        #[arg(long, default_value_t = 50)]
        clean: usize,
        /// Seed of the cases, the null and the fits.
        #[arg(long, default_value_t = 1)]
        seed: u64,
        /// `all` or a comma-separated list of the effects hidden in turn (every effect
        /// stays a candidate).
        #[arg(long, default_value = "all")]
        effects: String,
        /// Skip timing one full diagnosis with its retrain (about five minutes).
        #[arg(long)]
        no_full: bool,
        /// Folder for cases.json: every hidden case (its parameters, the effect's size and
        /// signature, the verdict, χ²ν before and after); none if absent.
        #[arg(long)]
        out: Option<std::path::PathBuf>,
    },
}

/// Runs the chosen benchmark.
pub fn run(args: BenchArgs) -> Result<()> {
    match args.what {
        BenchWhat::Sim { runs, drum } => sim(runs, &drum),
        BenchWhat::Npe { data, model, held, seed } => npe_bench(data, &model, held, seed),
        BenchWhat::Infer { requests, samples, direct: true, .. } => infer_direct(requests, samples),
        BenchWhat::Infer { clients, requests, samples, direct: false, findings: true, .. } => {
            infer_findings(clients, requests, samples)
        }
        BenchWhat::Infer { clients, requests, samples, direct: false, posterior, findings: false } => {
            infer(clients, requests, samples, posterior)
        }
        BenchWhat::Exact(a) => super::bench_exact::run(a),
        BenchWhat::Fit { model, cases, seed, measures } => super::bench_fit::run(&model, cases, seed, &measures),
        BenchWhat::Discrepancy { cases, clean, seed, effects, no_full, out } => {
            super::diagnose::bench(cases, clean, seed, &effects, !no_full, out.as_deref())
        }
        BenchWhat::Crossmodel { ears, out, model, seed, samples, measures, diagnose, alternatives_on_misfits } => {
            crossmodel(ears, &out, &model, seed, samples, &measures, alternatives_on_misfits)?;
            if diagnose { crossmodel_misfits(ears, &out, &model, seed, samples) } else { Ok(()) }
        }
        BenchWhat::C2st(a) => super::bench_c2st::run(*a),
        BenchWhat::Scale(a) => super::bench_scale::run(a),
        BenchWhat::Readings { ears, out, model, seed, measures, exact } => {
            readings(ears, &out, &model, seed, &measures, exact)
        }
        BenchWhat::Posterior { ears, seed, steps, measures, from_hz, out, model } => {
            let measures = groups(&measures);
            let p = crate::bench::posterior::PosteriorParams { ears, seed, steps, measures, from_hz };
            posterior(p, out.as_deref(), &model)
        }
    }
}

/// A `--measures` value's feature groups: comma-separated, blanks dropped (none: all).
pub(super) fn groups(measures: &str) -> Vec<String> {
    measures.split(',').map(str::trim).filter(|m| !m.is_empty()).map(String::from).collect()
}

/// `otofit bench posterior`: the flow against the likelihood's posterior, the table on
/// stdout, every ear in `out`/posterior.json.
fn posterior(
    p: crate::bench::posterior::PosteriorParams,
    out: Option<&std::path::Path>,
    model: &std::path::Path,
) -> Result<()> {
    use crate::bench::posterior;
    use anyhow::Context;
    p.check()?;
    if let Some(out) = out {
        std::fs::create_dir_all(out).with_context(|| format!("--out {}: cannot create it", out.display()))?;
    }
    let npe = crate::npe::Npe::load(model).with_context(|| format!("--model {}", model.display()))?;
    let t = Instant::now();
    let report = posterior::run(&npe, &p, &mut |outcome| match outcome {
        Ok(e) => eprintln!(
            "ear {} ({}): flow {:.2} s, exact {:.1} s, C2ST {:.3}, acceptance {:.2}, chain's R-hat {:.3} ({:.0} s)",
            e.ear,
            e.kind,
            e.flow_seconds,
            e.exact_seconds,
            e.c2st,
            e.acceptance,
            e.chain_rhat,
            t.elapsed().as_secs_f64()
        ),
        Err(s) => eprintln!("ear {} ({}): skipped: {}", s.ear, s.kind, s.reason),
    })?;
    let seconds = t.elapsed().as_secs_f64();
    print!("{}", posterior::table(&report));
    println!("wall time {seconds:.0} s");
    if let Some(out) = out {
        let mut doc = serde_json::to_value(&report)?;
        doc["model"] = model.display().to_string().into();
        doc["seconds"] = seconds.into();
        std::fs::write(out.join("posterior.json"), serde_json::to_vec_pretty(&doc)?)?;
    }
    Ok(())
}

/// `otofit bench crossmodel`: the cross-model suite, its table on stdout and in
/// `out`/crossmodel.md, every ear in `out`/crossmodel.json.
fn crossmodel(
    ears: usize,
    out: &std::path::Path,
    model: &std::path::Path,
    seed: u64,
    samples: usize,
    measures: &str,
    misfits: bool,
) -> Result<()> {
    use crate::bench::crossmodel::run::{self, CrossParams};
    use anyhow::Context;
    if !(1..=10_000).contains(&ears) {
        anyhow::bail!("--ears must be 1..=10000 (got {ears})");
    }
    if samples == 0 || samples > 1_000_000 {
        anyhow::bail!("--samples must be between 1 and 1000000");
    }
    std::fs::create_dir_all(out).with_context(|| format!("--out {}: cannot create it", out.display()))?;
    let npe = crate::npe::Npe::load(model)?;
    let p = CrossParams { ears, seed, samples, groups: groups(measures), misfits, ..CrossParams::default() };
    let given = if measures.is_empty() { "all" } else { measures };
    let t = Instant::now();
    let results = run::run(&npe, &p, &mut |r| {
        eprintln!(
            "{} {}: fit ok {:.0} %, correct {:.0} %, confident wrong {:.0} % ({:.0} s)",
            r.model.name(),
            r.condition.name(),
            100.0 * r.fit_ok,
            100.0 * r.correct,
            100.0 * r.confident_wrong,
            t.elapsed().as_secs_f64()
        )
    })?;
    let mut table = run::table(&results);
    if misfits {
        let m = run::misfit_table(&results);
        table.push_str(&format!("\nThe alternatives on the ears the fit check refused (never shipped):\n\n{m}"));
    }
    println!("measures given: {given}");
    print!("{table}");
    std::fs::write(out.join("crossmodel.md"), format!("measures given: {given}\n\n{table}"))?;
    let doc = serde_json::json!({
        "model": model.display().to_string(),
        "ears": ears,
        "seed": seed,
        "samples": samples,
        "noise_scale": p.noise_scale,
        "measures": given,
        "seconds": t.elapsed().as_secs_f64(),
        "results": results,
    });
    std::fs::write(out.join("crossmodel.json"), serde_json::to_vec_pretty(&doc)?)?;
    Ok(())
}

/// `otofit bench readings`: the table on stdout and in `out`/readings.md, every ear in
/// `out`/readings.json.
fn readings(
    ears: usize,
    out: &std::path::Path,
    model: &std::path::Path,
    seed: u64,
    measures: &str,
    exact_steps: Option<usize>,
) -> Result<()> {
    use crate::bench::readings::{self, ReadingsParams};
    use anyhow::Context;
    let npe = crate::npe::Npe::load(model)?;
    let p = ReadingsParams { ears, seed, measures: groups(measures), exact_steps };
    let t = Instant::now();
    let results = readings::run(&npe, &p, &mut |r| {
        eprintln!("{}: {:.0} % ({:.0} s)", r.group, 100.0 * r.rate, t.elapsed().as_secs_f64())
    })?;
    std::fs::create_dir_all(out).with_context(|| format!("--out {}: cannot create it", out.display()))?;
    let given = if measures.is_empty() { "all" } else { measures };
    let table = readings::table(&results);
    let posterior = exact_steps.map_or("the flow's".to_string(), |s| format!("the likelihood's ({s}-step chains)"));
    println!("measures given: {given}; posterior: {posterior}");
    print!("{table}");
    std::fs::write(out.join("readings.md"), format!("measures given: {given}; posterior: {posterior}\n\n{table}"))?;
    let doc = serde_json::json!({
        "model": model.display().to_string(),
        "ears": ears,
        "seed": seed,
        "samples": readings::SAMPLES,
        "exact_steps": exact_steps,
        "measures": given,
        "seconds": t.elapsed().as_secs_f64(),
        "groups": results,
    });
    std::fs::write(out.join("readings.json"), serde_json::to_vec_pretty(&doc)?)?;
    Ok(())
}

/// `otofit bench crossmodel --diagnose`: the suite's misfit ears (all measures) through
/// the discrepancy workflow, its table on stdout and in `out`/misfits.md, every ear in
/// `out`/misfits.json.
fn crossmodel_misfits(
    ears: usize,
    out: &std::path::Path,
    model: &std::path::Path,
    seed: u64,
    samples: usize,
) -> Result<()> {
    use crate::bench::crossmodel::misfits;
    use crate::bench::crossmodel::run::CrossParams;
    let npe = crate::npe::Npe::load(model)?;
    let sim = Model::new(ModelConfig::default())?;
    let t = Instant::now();
    let s = super::diagnose::bench_settings(&sim, &npe, seed)?;
    let p = CrossParams { ears, seed, samples, ..CrossParams::default() };
    let rows = misfits::run(&npe, &sim, &p, &s)?;
    let table = misfits::table(&rows);
    println!("\nmisfit ears (all measures) through the discrepancy workflow, no retraining:");
    print!("{table}");
    std::fs::write(out.join("misfits.md"), &table)?;
    let doc = serde_json::json!({
        "model": model.display().to_string(),
        "ears": ears,
        "seed": seed,
        "seconds": t.elapsed().as_secs_f64(),
        "rows": rows,
    });
    std::fs::write(out.join("misfits.json"), serde_json::to_vec_pretty(&doc)?)?;
    println!("wall {:.0} s", t.elapsed().as_secs_f64());
    Ok(())
}

fn median(v: &mut [f64]) -> f64 {
    v.sort_by(f64::total_cmp);
    crate::stats::median_upper(v)
}

fn sim(runs: usize, drum: &super::drum::DrumOpts) -> Result<()> {
    let mut config = ModelConfig::default();
    drum.apply(&mut config)?;
    let model = Model::new(config)?;
    let design = Design::default();
    let rows = design.draw(1, 0, runs.max(200));
    let mut runner = model.runner();
    let (t0, fx) = (Theta::nominal(), Effects::default());
    for _ in 0..20 {
        crate::sim::simulate(&mut runner, &t0, &fx)?; // warm up
    }
    let mut times: Vec<f64> = rows[..200]
        .iter()
        .map(|r| {
            let (theta, fx) = design.split(r);
            let t = Instant::now();
            let _ = crate::sim::simulate(&mut runner, &theta, &fx);
            t.elapsed().as_secs_f64() * 1e3
        })
        .collect();
    let one = median(&mut times);
    let t = Instant::now();
    let mut failed = 0;
    for first in (0..runs).step_by(1024) {
        let chunk = &rows[first..(first + 1024).min(runs)];
        failed += batch::run_rows(&model, &design, chunk, first, None).iter().filter(|r| r.is_err()).count();
    }
    let wall = t.elapsed().as_secs_f64();
    let threads = rayon::current_num_threads();
    println!(
        "system: {} unknowns, {} non-zeros, {} frequencies",
        model.n_unknowns(),
        model.nnz(),
        model.frequencies().len()
    );
    println!(
        "one run, one core: median {one:.2} ms ({:.1} µs per frequency; target ≤ 2 ms)",
        one * 1e3 / model.frequencies().len() as f64
    );
    println!(
        "{runs} runs on {threads} threads: {wall:.2} s ({:.0} runs/s, {failed} failed; target ≤ 15 s for 10,000); speed-up over one core {:.2}×",
        runs as f64 / wall,
        runs as f64 / wall * one / 1e3
    );
    Ok(())
}

/// CPU seconds this process has used so far (user + system, all threads).
fn cpu_seconds() -> f64 {
    #[cfg(unix)]
    {
        // SAFETY: getrusage writes into the zeroed struct we own; RUSAGE_SELF is valid.
        let mut u: libc::rusage = unsafe { std::mem::zeroed() };
        if unsafe { libc::getrusage(libc::RUSAGE_SELF, &mut u) } == 0 {
            let s = |t: libc::timeval| t.tv_sec as f64 + t.tv_usec as f64 * 1e-6;
            return s(u.ru_utime) + s(u.ru_stime);
        }
    }
    f64::NAN
}

/// CPU seconds the calling thread has used so far.
fn thread_cpu_seconds() -> f64 {
    #[cfg(unix)]
    {
        // SAFETY: clock_gettime writes into the zeroed struct we own.
        let mut t: libc::timespec = unsafe { std::mem::zeroed() };
        if unsafe { libc::clock_gettime(libc::CLOCK_THREAD_CPUTIME_ID, &mut t) } == 0 {
            return t.tv_sec as f64 + t.tv_nsec as f64 * 1e-9;
        }
    }
    f64::NAN
}

/// The 1-minute load average (NaN where /proc is absent).
fn load_average() -> f64 {
    std::fs::read_to_string("/proc/loadavg")
        .ok()
        .and_then(|s| s.split_whitespace().next().and_then(|v| v.parse().ok()))
        .unwrap_or(f64::NAN)
}

/// The `POST /infer` example of openapi.yaml.
fn infer_example() -> Result<serde_json::Value> {
    let spec = include_str!("../../openapi.yaml");
    let example = spec
        .lines()
        .map(str::trim)
        .find_map(|l| l.strip_prefix("example: ").filter(|e| e.starts_with("{\"measurements\"")))
        .ok_or_else(|| anyhow::anyhow!("no /infer example in openapi.yaml"))?;
    Ok(serde_json::from_str(example)?)
}

/// What one `POST /infer` computes (features, samples + MAP, fit check), without the
/// server, on one thread: per-phase medians are CPU times.
fn infer_direct(requests: usize, samples: usize) -> Result<()> {
    use crate::npe::{Npe, Obs};
    let npe = Npe::load(std::path::Path::new("models/default.otofit"))?;
    let m: crate::measurements::Measurements = serde_json::from_value(infer_example()?["measurements"].clone())?;
    let (x, present, _) = crate::measurements::features(&npe, &m)?;
    let pool = rayon::ThreadPoolBuilder::new().num_threads(1).build()?;
    let obs = Obs { x: &x, present: Some(&present) };
    // The flow the service answers this ear with (for the example, the three-measure one).
    let npe = npe.answering(&obs);
    let load0 = load_average();
    let (mut sample, mut map, mut fit, mut total) = (vec![], vec![], vec![], vec![]);
    let (mut cpu_inf, mut cpu_fit) = (vec![], vec![]);
    pool.install(|| -> Result<()> {
        for k in 0..=requests {
            let (t, c) = (Instant::now(), thread_cpu_seconds());
            let inf = npe.infer(&obs, samples, 0)?;
            let (tf, cf) = (Instant::now(), thread_cpu_seconds());
            crate::discrepancy::fitcheck::fit_check(npe, &x, &present, &inf)?;
            if k > 0 {
                // the first is a warm-up (the simulator is built then)
                cpu_inf.push((cf - c) * 1e3);
                cpu_fit.push((thread_cpu_seconds() - cf) * 1e3);
                fit.push(tf.elapsed().as_secs_f64() * 1e3);
                total.push(t.elapsed().as_secs_f64() * 1e3);
                sample.push(inf.sample_ms);
                map.push(inf.map_ms);
            }
        }
        Ok(())
    })?;
    println!(
        "POST /infer's work in-process, one thread, {samples} samples, {requests} runs: thread CPU median {:.1} ms for samples + MAP, {:.1} ms for the fit check; wall medians {:.1} ms (sample {:.1}, MAP {:.1}, fit check {:.1}); load average {load0:.2} → {:.2}",
        median(&mut cpu_inf),
        median(&mut cpu_fit),
        median(&mut total),
        median(&mut sample),
        median(&mut map),
        median(&mut fit),
        load_average()
    );
    Ok(())
}

fn infer(clients: usize, requests: usize, samples: usize, posterior: super::infer::PosteriorArg) -> Result<()> {
    let exact = posterior == super::infer::PosteriorArg::Exact;
    let mut body = infer_example()?;
    if exact {
        body["posterior"] = "exact".into();
    }
    body["samples"] = samples.into();
    body["return_samples"] = false.into();
    let body = body.to_string();
    let rt = tokio::runtime::Builder::new_multi_thread().enable_all().build()?;
    rt.block_on(async move {
        let dir = std::env::temp_dir().join(format!("otofit-bench-{}", std::process::id()));
        let addr = serve_default_model(&dir).await?;
        post(addr, &body).await?; // load the model once
        let (t, cpu0, load0) = (Instant::now(), cpu_seconds(), load_average());
        let mut lat = Vec::new();
        let mut phases: [Vec<f64>; 5] = Default::default();
        let mut bad = 0;
        for r in closed_loop(addr, &body, clients, requests).await? {
            match r {
                Ok((status, ms, answer)) if status.contains(" 200 ") => {
                    lat.push(ms);
                    for (v, k) in phases.iter_mut().zip(["sample", "map", "fit", "exact", "total"]) {
                        v.extend(answer["timing_ms"][k].as_f64());
                    }
                }
                _ => bad += 1,
            }
        }
        let wall = t.elapsed().as_secs_f64();
        let cpu = cpu_seconds() - cpu0;
        lat.sort_by(f64::total_cmp);
        let q = |p: f64| crate::stats::quantile_nearest(&lat, p).unwrap_or(f64::NAN);
        let Some(&max) = lat.last() else {
            anyhow::bail!("every POST /infer failed ({bad} requests): no latency to report");
        };
        let (what, targets) = if exact {
            (" + exact posterior", "targets: one client p50 ≤ 1000 ms, p99 ≤ 2000 ms")
        } else {
            ("", "targets: one client p50 ≤ 20 ms; 16 clients p50 ≤ 100 ms, p99 ≤ 300 ms")
        };
        println!("POST /infer, {samples} samples + MAP + fit check{what}, {clients} concurrent clients × {requests} requests: p50 {:.0} ms, p90 {:.0} ms, p99 {:.0} ms, max {:.0} ms; {:.1} req/s; {bad} failed ({targets})", q(0.5), q(0.9), q(0.99), max, lat.len() as f64 / wall);
        let [s, m, f, e, tot] = phases.map(|mut v| if v.is_empty() { f64::NAN } else { median(&mut v) });
        println!(
            "CPU {:.1} ms per request (process user + system over {} requests, {} threads); server-side medians: sample {s:.1} ms, MAP {m:.1} ms, fit check {f:.1} ms, exact {e:.1} ms, handler total {tot:.1} ms; load average {load0:.2} → {:.2}",
            cpu * 1e3 / (lat.len() + bad).max(1) as f64,
            lat.len() + bad,
            rayon::current_num_threads(),
            load_average()
        );
        let _ = std::fs::remove_dir_all(&dir);
        anyhow::Ok(())
    })
}

/// The ears of `bench infer --findings`: tissue at the centre of every normal range but
/// for these values (name, value), and what the change is.
const FINDING_EARS: [(&str, &[(&str, f64)]); 6] = [
    ("stapes fixation", &[("E_sal", 4e6)]),
    ("joint erosion", &[("E_joints", 1e5)]),
    ("contracted muscles", &[("E_tendons", 2e7)]),
    ("stapes fixation, low losses", &[("E_sal", 3e6), ("damping_beta", 2.5e-5)]),
    ("stapes fixation, low cochlear load", &[("E_sal", 3e6), ("cochlear_load", 6e9)]),
    ("contracted muscles, flaccid drum", &[("E_tendons", 2e7), ("E_eardrum", 1.5e6)]),
];

/// A POST /infer body of every measure of a simulated ear: `FINDING_EARS[k]` with 1×
/// noise of seed 3.
fn finding_body(model: &crate::sim::Model, k: usize, samples: usize) -> Result<serde_json::Value> {
    use crate::sim::batch::{Design, Noise, default_noise_std, run_rows};
    use crate::sim::params::{N_TISSUE, PARAMS};
    // The ear's canal, cavity, drum viscoelasticity, LDV angle and cochlear mass from the
    // prior (seed 5, row k); its tissue at the centre of the normal ranges.
    let mut row = Design::default().draw(5, k, 1).remove(0);
    row[..N_TISSUE].copy_from_slice(&crate::npe::normal::centre_row()[..N_TISSUE]);
    for &(name, v) in FINDING_EARS[k].1 {
        let i = PARAMS.iter().position(|p| p.name == name).ok_or_else(|| anyhow::anyhow!("no parameter {name}"))?;
        row[i] = v;
    }
    let noise = Noise { std: default_noise_std(model), scale: 1.0, seed: 3 };
    let x = run_rows(model, &Design::default(), &[row], 0, Some(&noise)).remove(0)?;
    let f = model.frequencies().to_vec();
    let n = f.len();
    let block = |b: usize| x[b * n..(b + 1) * n].to_vec();
    let mag = |b: usize| block(b).into_iter().map(|v| 10f64.powf(v)).collect::<Vec<f64>>();
    Ok(serde_json::json!({
        "measurements": {
            "stapes_velocity": {"frequencies_hz": f, "magnitude": mag(0), "phase": block(1)},
            "impedance": {"frequencies_hz": f, "magnitude": mag(2), "phase": block(3)},
            "absorbance": {"frequencies_hz": f, "values": block(4)},
            "umbo_velocity": {"frequencies_hz": f, "magnitude": mag(5), "phase": block(6)},
        },
        "samples": samples,
        "return_samples": false,
    }))
}

/// `bench infer --findings`: each ear of [`FINDING_EARS`] posted by `clients` closed-loop
/// clients, `requests` each after one of warm-up; medians of the latency and of the
/// answer's `timing_ms.alternatives` per ear.
fn infer_findings(clients: usize, requests: usize, samples: usize) -> Result<()> {
    let model = crate::sim::Model::new(crate::sim::ModelConfig::default())?;
    let bodies = (0..FINDING_EARS.len()).map(|k| finding_body(&model, k, samples)).collect::<Result<Vec<_>>>()?;
    let rt = tokio::runtime::Builder::new_multi_thread().enable_all().build()?;
    rt.block_on(async move {
        let dir = std::env::temp_dir().join(format!("otofit-bench-{}", std::process::id()));
        let addr = serve_default_model(&dir).await?;
        println!("POST /infer with the differential's alternatives, {samples} samples, {clients} concurrent clients × {requests} requests per ear (target: one client p50 ≤ 100 ms)");
        for ((what, change), body) in FINDING_EARS.iter().zip(&bodies) {
            let body = body.to_string();
            let (_, _, first) = post(addr, &body).await?; // warm-up
            let load0 = load_average();
            let (mut lat, mut alt, mut bad) = (vec![], vec![], 0);
            for r in closed_loop(addr, &body, clients, requests).await? {
                match r {
                    Ok((status, ms, answer)) if status.contains(" 200 ") => {
                        lat.push(ms);
                        alt.push(answer["timing_ms"]["alternatives"].as_f64().unwrap_or(0.0));
                    }
                    _ => bad += 1,
                }
            }
            if lat.is_empty() {
                anyhow::bail!("every POST /infer of the {what} ear failed ({bad} requests)");
            }
            let change: Vec<String> = change.iter().map(|(n, v)| format!("{n} {v:e}")).collect();
            let hypotheses = first["alternatives"]["hypotheses"].as_array().map_or(0, Vec::len);
            println!(
                "{what} ({}): verdict {}, {hypotheses} hypotheses; p50 {:.1} ms, max {:.1} ms; alternatives p50 {:.1} ms; {bad} failed; load average {load0:.2} → {:.2}",
                change.join(", "),
                first["verdict"]["code"].as_str().unwrap_or("none"),
                median(&mut lat),
                lat.iter().copied().fold(0.0, f64::max),
                median(&mut alt),
                load_average()
            );
        }
        let _ = std::fs::remove_dir_all(&dir);
        anyhow::Ok(())
    })
}

/// An in-process server of the default model on a loopback port, its state in `dir`.
async fn serve_default_model(dir: &std::path::Path) -> Result<std::net::SocketAddr> {
    let ctx = super::serve::open(dir, std::path::Path::new("models/default.otofit"), 8).await?;
    let app = crate::http::router(crate::http::AppState::new(ctx, vec![]));
    let listener = tokio::net::TcpListener::bind("127.0.0.1:0").await?;
    let addr = listener.local_addr()?;
    tokio::spawn(async move { axum::serve(listener, app).await });
    Ok(addr)
}

/// `clients` closed-loop clients posting `body` `requests` times each; every answer of
/// [`post`].
async fn closed_loop(
    addr: std::net::SocketAddr,
    body: &str,
    clients: usize,
    requests: usize,
) -> Result<Vec<Result<(String, f64, serde_json::Value)>>> {
    let tasks: Vec<_> = (0..clients)
        .map(|_| {
            let body = body.to_string();
            tokio::spawn(async move {
                let mut out = Vec::new();
                for _ in 0..requests {
                    out.push(post(addr, &body).await);
                }
                out
            })
        })
        .collect();
    let mut out = Vec::new();
    for task in tasks {
        out.extend(task.await?);
    }
    Ok(out)
}

/// One HTTP/1.1 request over a fresh connection; returns (status line, milliseconds,
/// the answer's JSON, null when it is none).
async fn post(addr: std::net::SocketAddr, body: &str) -> Result<(String, f64, serde_json::Value)> {
    use tokio::io::{AsyncReadExt, AsyncWriteExt};
    let t = Instant::now();
    let mut s = tokio::net::TcpStream::connect(addr).await?;
    let req = format!(
        "POST /infer HTTP/1.1\r\nHost: localhost\r\nContent-Type: application/json\r\nContent-Length: {}\r\nConnection: close\r\n\r\n{body}",
        body.len()
    );
    s.write_all(req.as_bytes()).await?;
    let mut buf = Vec::new();
    s.read_to_end(&mut buf).await?;
    let ms = t.elapsed().as_secs_f64() * 1e3;
    let text = String::from_utf8_lossy(&buf);
    let status = text.lines().next().unwrap_or("").to_string();
    let answer = text
        .split_once("\r\n\r\n")
        .and_then(|(_, b)| serde_json::from_str::<serde_json::Value>(b).ok())
        .unwrap_or_default();
    Ok((status, ms, answer))
}

/// Two-moons-like toy (Greenberg et al. 2019): θ ∈ [−1, 1]², x ∈ R².
fn two_moons(n: usize, seed: u64) -> crate::npe::Dataset {
    use rand::{Rng, SeedableRng};
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(seed);
    let params = ["t0", "t1"]
        .iter()
        .map(|n| crate::npe::Param {
            name: n.to_string(),
            unit: "1".into(),
            scale: crate::npe::Scale::Linear,
            low: -1.0,
            high: 1.0,
        })
        .collect();
    let (mut theta, mut x) = (Vec::new(), Vec::new());
    for _ in 0..n {
        let t: [f64; 2] = [rng.random_range(-1.0..1.0), rng.random_range(-1.0..1.0)];
        let a: f64 = rng.random_range(-std::f64::consts::FRAC_PI_2..std::f64::consts::FRAC_PI_2);
        let r = 0.1 + 0.01 * rng.sample::<f64, _>(rand_distr::StandardNormal);
        let p = [r * a.cos() + 0.25, r * a.sin()];
        let s = std::f64::consts::FRAC_1_SQRT_2;
        x.push(vec![p[0] - (t[0] + t[1]).abs() * s, p[1] + (-t[0] + t[1]) * s]);
        theta.push(t.to_vec());
    }
    crate::npe::Dataset {
        params,
        feature_names: vec!["x0".into(), "x1".into()],
        frequencies_hz: vec![],
        groups: vec![],
        noise_std: vec![0.0; 2],
        theta,
        x,
        skipped: 0,
    }
}

fn npe_bench(
    data: Option<std::path::PathBuf>,
    model: &std::path::Path,
    held: Option<std::path::PathBuf>,
    seed: u64,
) -> Result<()> {
    use crate::npe::{self, Npe, Obs, TrainSettings};
    let held = held.map(|dir| npe::Dataset::load(&dir)).transpose()?;
    let toy = two_moons(10_000, 1);
    let t = Instant::now();
    let m =
        npe::train(&toy, &TrainSettings { embedding: false, noise_scale: 0.0, ..Default::default() }, &mut |_| true)?;
    let test = two_moons(1000, 2);
    let lp: f64 = test
        .theta
        .iter()
        .zip(&test.x)
        .map(|(th, x)| {
            m.log_prob(&Obs { x, present: None }, std::slice::from_ref(th)).map(|v| v[0]).unwrap_or(f64::NAN)
        })
        .sum::<f64>()
        / 1000.0;
    println!(
        "two-moons toy, 10,000 simulations: {:.1} s, {} epochs (best {}), held-out mean log q(θ|x) {lp:.3} (sbi 0.27 here: ~208 s, 155 epochs)",
        t.elapsed().as_secs_f64(),
        m.header.training.epochs,
        m.header.training.best_epoch
    );
    if let Some(dir) = data {
        let ds = npe::Dataset::load(&dir)?;
        let t = Instant::now();
        let m = npe::train(&ds, &TrainSettings { seed, ..TrainSettings::default() }, &mut |_| true)?;
        println!(
            "middle ear, {} simulations × {} features, 3×50 embedding: {:.1} s, {} epochs (best {}, val loss {:.3}) (sbi 0.27 here: ~290 s, 190 epochs; target ≤ 150 s)",
            ds.theta.len(),
            ds.feature_names.len(),
            t.elapsed().as_secs_f64(),
            m.header.training.epochs,
            m.header.training.best_epoch,
            m.header.training.best_val_loss
        );
        if let Some(ds) = &held {
            let (lp, n) = held_out_log_q(&m, ds);
            println!(
                "held-out mean log q(θ|x) of this training (seed {seed}) on {n} simulations (natural units): {lp:.2}"
            );
        }
    }
    let m = Npe::load(model)?;
    let x0 = crate::sim::simulate(
        &mut Model::new(ModelConfig::default())?.runner(),
        &Theta::nominal(),
        &Effects::default(),
    )?;
    let obs = Obs { x: &x0, present: None };
    m.infer(&obs, 1000, 0)?; // warm up
    let (mut times, mut sample, mut map) = (vec![], vec![], vec![]);
    for k in 0..5 {
        let t = Instant::now();
        let inf = m.infer(&obs, 10_000, k)?;
        times.push(t.elapsed().as_secs_f64() * 1e3);
        sample.push(inf.sample_ms);
        map.push(inf.map_ms);
    }
    println!(
        "infer after load, 10,000 samples + MAP + CV, one observation: median {:.0} ms of 5 (sampling {:.0} ms, MAP {:.0} ms; target ≤ 100 ms)",
        median(&mut times),
        median(&mut sample),
        median(&mut map)
    );
    if let Some(ds) = &held {
        let (lp, n) = held_out_log_q(&m, ds);
        println!("held-out mean log q(θ|x) of {} on {n} simulations (natural units): {lp:.2}", model.display());
    }
    Ok(())
}

/// Mean log q(θ|x) of `m` on the first (at most) 500 rows of `ds`, x with one noise draw
/// of the model's noise model (seed 9), and the row count.
fn held_out_log_q(m: &crate::npe::Npe, ds: &crate::npe::Dataset) -> (f64, usize) {
    use crate::npe::Obs;
    let noise = crate::sim::batch::Noise { std: m.header.noise_std.clone(), scale: m.header.noise_scale, seed: 9 };
    let n = ds.theta.len().min(500);
    let lp = (0..n)
        .map(|i| {
            let x = noise.apply(&ds.x[i], i);
            m.log_prob(&Obs { x: &x, present: None }, std::slice::from_ref(&ds.theta[i]))
                .map(|v| v[0])
                .unwrap_or(f64::NAN)
        })
        .sum::<f64>()
        / n as f64;
    (lp, n)
}
