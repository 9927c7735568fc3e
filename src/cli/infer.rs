//! `otofit infer`: a model and observations (CSV, header = feature names) → posterior
//! samples (CSV) and one JSON summary per observation on stdout.

use crate::dataset::read_csv;
use crate::npe::{Npe, Obs};
use anyhow::{Context, Result, bail};
use clap::Args;
use std::io::Write;
use std::path::{Path, PathBuf};

/// Arguments of `otofit infer`.
#[derive(Args, Debug)]
pub struct InferArgs {
    /// Model file (.otofit), e.g. models/default.otofit.
    #[arg(long)]
    pub model: PathBuf,
    /// Observation(s): a CSV feature table (header = feature names such as
    /// absorbance@1000.0, one row per observation; absent columns = measures not given);
    /// one observation in the POST /infer format (.json, e.g. from `otofit import wai`); or
    /// one ear as a long-layout CSV (a Frequency column, one row per frequency: see
    /// `otofit import csv --help`).
    #[arg(long)]
    pub obs: PathBuf,
    /// How to read a long-layout --obs table.
    #[command(flatten)]
    pub long: super::import::LongArgs,
    /// Long-layout tables: the units of an export family for columns that declare
    /// none ("wai": Zmag in Pa·s/m³, Zang in cycles, as the WAI database stores them).
    #[arg(long)]
    pub preset: Option<crate::formats::long::Preset>,
    /// Posterior samples per observation (1..=1000000).
    #[arg(long, default_value_t = 1000)]
    pub samples: usize,
    /// Seed of the posterior draws (same seed, same samples).
    #[arg(long, default_value_t = 0)]
    pub seed: u64,
    /// Samples CSV (parameter names; plus `obs` when OBS has several rows).
    #[arg(long, required_unless_present = "log_prob")]
    pub out: Option<PathBuf>,
    /// Instead of sampling: log q(θ|x) of the given parameter sets (CSV, header = the
    /// model's parameter names, natural units), one JSON line per observation; θ outside
    /// the prior box has density 0 (null, listed in `outside_prior`).
    #[arg(long, conflicts_with_all = ["out", "plot"])]
    pub log_prob: Option<PathBuf>,
    /// Folder for one corner plot per observation (corner_<row>.svg: the posterior over the
    /// prior box, MAP marked, tick values in the parameters' units).
    #[arg(long)]
    pub plot: Option<PathBuf>,
    /// Also refine the MAP by least squares against the observation (Levenberg–Marquardt
    /// from the flow's MAP through the simulator, at most this many steps, 0..=200, e.g.
    /// 50; about 15 simulations per step) and report the best fit under `refined`: the
    /// parameter set whose spectra match the measurement most closely, beside the
    /// posterior's mode.
    #[arg(long, default_value_t = 0, conflicts_with = "log_prob")]
    pub refine: usize,
    /// Also sample the posterior under the model's own likelihood (Gaussian noise of the
    /// training, the prior boxes) by this many Metropolis steps, one simulation each, in
    /// four chains side by side (0 = off, else 100000..=200000: 100000, about 10 s on two
    /// cores, is the length measured calibrated), beside the best of sixteen
    /// least-squares fits; reported under `exact` with its own
    /// summaries and differential reading. Much narrower than the flow's posterior, and
    /// exact only when the model fits the ear (docs/npe.md, "The flow's posterior against
    /// the likelihood's").
    #[arg(long, default_value_t = 0, conflicts_with = "log_prob")]
    pub exact: usize,
    /// Which posterior: `flow` (the flow's alone) or `exact`: also the likelihood's
    /// posterior from four short Metropolis chains started at dispersed flow draws (about
    /// a second per observation, at most 3 s), reported under `exact` with R-hat and ESS;
    /// `exact: false` with the reason when the chains disagree, have too few effective
    /// draws or run out of time, or when the fit check fails.
    #[arg(long, value_enum, default_value = "flow", conflicts_with = "log_prob")]
    pub posterior: PosteriorArg,
}

/// `--posterior`'s values.
#[derive(clap::ValueEnum, Clone, Copy, Debug, PartialEq, Eq)]
pub enum PosteriorArg {
    /// The flow's posterior alone.
    Flow,
    /// Also the likelihood's, from short chains.
    Exact,
}

/// Lines up an observation table's columns with the model's features.
pub fn align(model: &Npe, header: &[String], row: &[f64]) -> Result<(Vec<f64>, Vec<bool>)> {
    let names = &model.header.feature_names;
    for h in header {
        if !names.contains(h) {
            bail!(
                "column '{h}' is not a feature of this model (features look like '{}'; a long-layout table needs a \
                 Frequency column)",
                names[0]
            );
        }
    }
    let mut x = vec![f64::NAN; names.len()];
    let mut present = vec![false; names.len()];
    for (h, v) in header.iter().zip(row) {
        let i = names.iter().position(|n| n == h).unwrap_or(0);
        x[i] = *v;
        present[i] = v.is_finite();
    }
    Ok((x, present))
}

/// One ear's measurements as (features, present) on the model's grid, errors naming the
/// file and, for a table, the column each field came from.
fn measured(
    model: &Npe,
    path: &Path,
    m: &crate::measurements::Measurements,
    imported: Option<&crate::formats::Imported>,
) -> Result<(Vec<f64>, Vec<bool>)> {
    use crate::measurements::MeasurementError;
    match crate::measurements::features(model, m) {
        Ok((x, present, _)) => Ok((x, present)),
        Err(MeasurementError::Invalid(errs)) => {
            let named = |f: &str, m: &str| imported.map_or((f.to_string(), m.to_string()), |i| i.column_of(f, m));
            let lines: Vec<String> = errs.iter().map(|(f, m)| named(f, m)).map(|(f, m)| format!("{f}: {m}")).collect();
            bail!("{}: {}", path.display(), lines.join("; "))
        }
        Err(e) => Err(anyhow::Error::new(e).context(path.display().to_string())),
    }
}

/// The observations of `path`: a feature table (CSV, header = feature names, one row per
/// observation), one observation in the `POST /infer` format (`.json`: the request, or
/// just its `measurements`) or one ear as a long-layout table, as (features, present) on
/// the model's grid.
/// One observation of a table: its features and which are given, or why it was refused.
type Row = std::result::Result<(Vec<f64>, Vec<bool>), String>;

/// The observations in `path`. A single ear (JSON, long layout) is refused whole; a
/// feature table's rows one by one, so that one bad row costs only itself.
fn observations(model: &Npe, path: &Path, args: &InferArgs) -> Result<Vec<Row>> {
    if path.extension().is_some_and(|e| e.eq_ignore_ascii_case("json")) {
        let text = std::fs::read_to_string(path).with_context(|| format!("cannot read {}", path.display()))?;
        let mut doc: serde_json::Value =
            serde_json::from_str(&text).with_context(|| format!("{}: not JSON", path.display()))?;
        let m = doc.get_mut("measurements").map(serde_json::Value::take).unwrap_or(doc);
        let m: crate::measurements::Measurements = serde_json::from_value(m)
            .with_context(|| format!("{}: not an observation in the POST /infer format", path.display()))?;
        return Ok(vec![Ok(measured(model, path, &m, None)?)]);
    }
    let first = std::fs::read(path).with_context(|| format!("cannot read {}", path.display()))?;
    if first.iter().find(|b| !b.is_ascii_whitespace()) == Some(&b'{') {
        bail!(
            "{}: looks like JSON; name it .json (the POST /infer format) or give a CSV feature table",
            path.display()
        );
    }
    let head = String::from_utf8_lossy(&first);
    let head = head.lines().find(|l| !l.trim().is_empty() && !l.trim_start().starts_with('#')).unwrap_or("");
    if crate::formats::long::looks_long(head) {
        let opts = args.long.options(args.preset)?;
        let imp = super::import::read_table(path, &opts)?;
        for n in &imp.notes {
            eprintln!("note: {n}");
        }
        return Ok(vec![Ok(measured(model, path, &imp.measurements, Some(&imp))?)]);
    }
    if !args.long.is_empty() || args.preset.is_some() {
        bail!(
            "{}: --unit, --select and --preset apply to long-layout tables (with a Frequency column)",
            path.display()
        );
    }
    let table = read_csv(path)?;
    if table.rows.is_empty() {
        bail!("{}: no observation rows", path.display());
    }
    let otofit_model = crate::discrepancy::fitcheck::simulator_for(model).is_ok();
    let row = |row: &[f64]| -> Result<(Vec<f64>, Vec<bool>)> {
        let (x, present) = align(model, &table.header, row)?;
        // The JSON path checks this in measurements::features; a feature table here.
        if otofit_model
            && let Some((_, i, v)) =
                crate::sim::output::implausible(&x, &present, model.header.frequencies_hz.len()).first()
        {
            bail!(
                "{} = {v} is outside the physical range of a human ear (phases in rad, magnitudes as log10 of m/s/Pa \
                 and Pa·s/m³)",
                model.header.feature_names[*i]
            );
        }
        Ok((x, present))
    };
    let rows: Vec<Row> = table
        .rows
        .iter()
        .enumerate()
        .map(|(r, v)| row(v).map_err(|e| format!("{}: row {}: {e:#}", path.display(), r + 1)))
        .collect();
    // A table of one ear is that ear: refused whole, as before any work.
    if let [Err(why)] = rows.as_slice() {
        bail!("{why}");
    }
    Ok(rows)
}

/// Ends a run whose table had refused rows: every other row was answered and written.
fn refused(rows: usize, why: &[String]) -> Result<()> {
    match why {
        [] => Ok(()),
        [first, ..] => bail!(
            "{} of {rows} observations refused (each has an `error` line on stdout; the others were answered): \
             first: {first}",
            why.len()
        ),
    }
}

/// The parameter sets of a `--log-prob` table, in the model's parameter order.
fn theta_rows(model: &Npe, path: &Path) -> Result<Vec<Vec<f64>>> {
    let table = read_csv(path).with_context(|| "--log-prob".to_string())?;
    let names: Vec<&str> = model.params().iter().map(|p| p.name.as_str()).collect();
    if let Some(h) = table.header.iter().find(|h| !names.contains(&h.as_str())) {
        bail!("--log-prob {}: column '{h}' is not a parameter of this model ({})", path.display(), names.join(", "));
    }
    let cols: Vec<usize> = names
        .iter()
        .map(|n| {
            table.header.iter().position(|h| h == n).with_context(|| {
                format!("--log-prob {}: column '{n}' missing (the table needs every parameter)", path.display())
            })
        })
        .collect::<Result<_>>()?;
    if table.rows.is_empty() {
        bail!("--log-prob {}: no parameter rows", path.display());
    }
    Ok(table.rows.iter().map(|r| cols.iter().map(|&c| r[c]).collect()).collect())
}

/// `--log-prob`: log q(θ|x) of every given θ for every observation, one JSON line each.
fn log_probs(model: &Npe, rows: &[Row], path: &Path) -> Result<()> {
    let thetas = theta_rows(model, path)?;
    let inside = |t: &[f64]| model.params().iter().zip(t).all(|(p, v)| v.is_finite() && (p.low..=p.high).contains(v));
    let mut stdout = std::io::stdout().lock();
    let mut why = Vec::new();
    for (r, row) in rows.iter().enumerate() {
        let lp = row.as_ref().map_err(String::clone).and_then(|(x, present)| {
            let obs = Obs { x, present: Some(present) };
            model.answering(&obs).log_prob(&obs, &thetas).map_err(|e| format!("observation {}: {e:#}", r + 1))
        });
        let lp = match lp {
            Ok(lp) => lp,
            Err(e) if rows.len() == 1 => bail!("{e}"),
            Err(e) => {
                writeln!(stdout, "{}", serde_json::json!({ "observation": r, "error": e }))?;
                why.push(e);
                continue;
            }
        };
        let outside: Vec<usize> = (0..thetas.len()).filter(|&i| !inside(&thetas[i])).collect();
        let lp: Vec<Option<f64>> =
            lp.iter().enumerate().map(|(i, v)| (!outside.contains(&i) && v.is_finite()).then_some(*v)).collect();
        let line = serde_json::json!({ "observation": r, "log_prob": lp, "outside_prior": outside });
        writeln!(stdout, "{line}")?;
    }
    refused(rows.len(), &why)
}

/// Runs `otofit infer`.
pub fn run(args: InferArgs) -> Result<()> {
    if args.samples == 0 || args.samples > 1_000_000 {
        bail!("--samples must be between 1 and 1000000");
    }
    let max_steps = crate::discrepancy::fitcheck::MAX_REFINE_STEPS;
    if args.refine > max_steps {
        bail!("--refine must be 0..={max_steps} steps (got {})", args.refine);
    }
    let range = crate::jobs::limits::EXACT_STEPS;
    if args.exact != 0 && !range.contains(&args.exact) {
        bail!("--exact must be 0 (off) or {}..={} steps (got {})", range.start(), range.end(), args.exact);
    }
    if args.exact != 0 && args.posterior == PosteriorArg::Exact {
        bail!("--exact (one long chain) and --posterior exact (short chains) both answer under `exact`: choose one");
    }
    if let Some(theta) = &args.log_prob {
        let model = Npe::load(&args.model)?;
        let rows = observations(&model, &args.obs, &args)?;
        return log_probs(&model, &rows, theta);
    }
    let out_path = args.out.clone().context("--out is required")?;
    if let Some(dir) = out_path.parent().filter(|d| !d.as_os_str().is_empty())
        && !dir.is_dir()
    {
        bail!("--out {}: the folder {} does not exist", out_path.display(), dir.display());
    }
    if let Some(dir) = &args.plot {
        std::fs::create_dir_all(dir).with_context(|| format!("--plot {}: cannot create it", dir.display()))?;
    }
    let model = Npe::load(&args.model)?;
    let rows = observations(&model, &args.obs, &args)?;
    let many = rows.len() > 1;
    let names: Vec<&str> = model.params().iter().map(|p| p.name.as_str()).collect();
    let mut out = String::new();
    out.push_str(&if many { format!("obs,{}\n", names.join(",")) } else { format!("{}\n", names.join(",")) });
    // The summaries are printed after --out is written: a reader that stops early
    // (`| head -1`) must not cost the samples.
    let mut summaries = Vec::with_capacity(rows.len());
    let mut why = Vec::new();
    for (r, row) in rows.iter().enumerate() {
        // The full-measure flow answers an ear with every measure, a measure-set flow an
        // ear of exactly its groups, when the file holds them.
        let answered = row.as_ref().map_err(String::clone).and_then(|(x, present)| {
            let obs = Obs { x, present: Some(present) };
            let inf = model.answering(&obs).infer(&obs, args.samples, args.seed);
            inf.map(|inf| ((x.as_slice(), present.as_slice()), inf))
                .map_err(|e| format!("observation {}: {e:#}", r + 1))
        });
        let ((x, present), inf) = match answered {
            Ok(a) => a,
            Err(e) if !many => bail!("{e}"),
            Err(e) => {
                summaries.push(serde_json::json!({ "observation": r, "error": e }).to_string());
                why.push(e);
                continue;
            }
        };
        let obs = Obs { x, present: Some(present) };
        let flow = model.answering_name(&obs);
        let model = model.answering(&obs);
        for s in &inf.samples {
            let vals: Vec<String> = s.iter().map(|v| format!("{v:e}")).collect();
            if many {
                out.push_str(&format!("{r},"));
            }
            out.push_str(&vals.join(","));
            out.push('\n');
        }
        if let Some(dir) = &args.plot {
            let title = format!("Posterior, {} observation {}", args.obs.display(), r + 1);
            let svg = super::study::corner(model, &inf.samples, None, &inf.map, &title);
            std::fs::write(dir.join(format!("corner_{}.svg", r + 1)), svg)?;
        }
        let (differential, fit) = crate::discrepancy::fitcheck::checked_reading(model, x, present, &inf, &inf.samples);
        let withdrawn = fit.as_ref().ok().filter(|f| f.ok == Some(false)).map(|f| f.reason.clone().unwrap_or_default());
        let fit = match fit {
            Ok(f) => serde_json::json!(f),
            Err(e) => serde_json::json!({ "ok": null, "reason": e.to_string() }),
        };
        // The competing explanations of a shipped finding, as POST /infer gives them.
        let alternatives = crate::discrepancy::alternatives::alternatives(
            model,
            x,
            present,
            (&inf.map, &inf.samples),
            &differential,
            fit["ok"].as_bool(),
            &Default::default(),
        );
        let verdict = crate::npe::normal::verdict(&differential, fit["ok"].as_bool());
        let mut json = serde_json::json!({ "observation": r, "verdict": verdict, "fit": fit, "flow": flow, "parameters": inf.summaries, "differential": differential, "timing_ms": { "sample": inf.sample_ms, "map": inf.map_ms } });
        if let Some(a) = alternatives {
            json["timing_ms"]["alternatives"] = serde_json::json!(a.ms);
            json["alternatives"] = serde_json::json!(a);
        }
        if args.refine > 0 {
            let fit = crate::discrepancy::fitcheck::refine(model, x, present, &inf.map, args.refine)
                .with_context(|| format!("--refine, observation {}", r + 1))?;
            json["refined"] = serde_json::json!(fit);
        }
        if args.exact > 0 {
            let ex = crate::discrepancy::fitcheck::exact(model, x, present, &inf, args.exact, args.seed)
                .with_context(|| format!("--exact, observation {}", r + 1))?;
            let mut doc = serde_json::json!(ex);
            doc["differential"] = serde_json::json!(ex.reading(model, withdrawn.as_deref()));
            doc["note"] = serde_json::json!(crate::discrepancy::fitcheck::EXACT_NOTE);
            json["exact"] = doc;
        }
        if args.posterior == PosteriorArg::Exact {
            json["exact"] = exact_fast(model, (x, present), &inf, args.seed, withdrawn.as_deref());
        }
        summaries.push(json.to_string());
    }
    let tmp = out_path.with_extension("tmp");
    std::fs::write(&tmp, out).with_context(|| format!("cannot write {}", tmp.display()))?;
    std::fs::rename(&tmp, &out_path)?;
    let mut stdout = std::io::stdout().lock();
    for line in summaries {
        writeln!(stdout, "{line}")?;
    }
    refused(rows.len(), &why)
}

/// `--posterior exact`: the likelihood's posterior of one observation from short chains
/// (as POST /infer's `exact`), withdrawn when the fit check failed (`withdrawn` its reason).
/// A sampler that cannot run on this ear (no chain finds a start) answers `exact: false`
/// with why, as POST /infer does, rather than ending the whole command.
fn exact_fast(
    model: &Npe,
    (x, present): (&[f64], &[bool]),
    inf: &crate::npe::Inference,
    seed: u64,
    withdrawn: Option<&str>,
) -> serde_json::Value {
    use crate::discrepancy::exact_fast::{self, BUDGET, Settings};
    let settings = Settings { seed, ..Default::default() };
    let mut e = match exact_fast::sample(model, x, present, inf, &settings, std::time::Instant::now() + BUDGET) {
        Ok(e) => e,
        Err(why) => return serde_json::json!({ "exact": false, "reason": why.to_string(), "ms": 0.0 }),
    };
    if let Some(why) = withdrawn {
        e.withdraw(why);
    }
    let mut doc = serde_json::json!(e);
    doc["differential"] = serde_json::json!(e.reading(model));
    doc["note"] = serde_json::json!(exact_fast::NOTE);
    doc
}
