//! The job queue: a tokio dispatcher claims queued jobs from the store (SQLite or
//! PostgreSQL) one at a time and runs the CPU work on the blocking pool (simulations fan
//! out on rayon inside it), so the async runtime never blocks. Progress goes to the
//! database as the work goes; cancellation and shutdown are checked between chunks.
//!
//! Every claim is a lease (see `store`): the dispatcher renews it every third of its
//! length while the job runs, and a job whose lease is lost (this worker stalled or was
//! cut off, and another took the job back) is stopped and writes nothing: results are
//! fenced by the lease token in the database, and files are written into an attempt's own
//! staging place and moved into place only after a fresh renewal.

use crate::dataset::{self, Rows};
use crate::npe::{self, Dataset, Npe, TrainSettings};
use crate::sim::batch::{Design, Noise, default_noise_std, run_rows};
use crate::sim::output::feature_names;
use crate::sim::params::{EFFECTS, Effects, N_PARAMS, N_TISSUE, PARAMS, with_nominal_geometry};

const N_GEOMETRY: usize = N_PARAMS - N_TISSUE;
use crate::sim::{Model, ModelConfig};
use crate::store::{JobRow, Store};
use anyhow::{Context, Result, anyhow, bail};
use serde::Deserialize;
use std::collections::{BTreeMap, HashMap};
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, RwLock};
use std::time::Duration;
use tokio::sync::Notify;

pub const KINDS: [&str; 4] = ["simulate", "train", "resimulate", "diagnose"];

/// Shared service state.
pub struct Ctx {
    pub store: Store,
    pub data_dir: PathBuf,
    pub notify: Notify,
    pub shutdown: AtomicBool,
    models: RwLock<HashMap<String, Arc<Npe>>>,
    pub max_queue: i64,
    /// The data directory's lock, held as long as this context lives (see `with_lock`).
    data_lock: Option<std::fs::File>,
    /// Slots and deadline of POST /infer.
    pub infer_gate: crate::http::InferGate,
    /// This process as a worker (`host:pid`), written into the jobs it claims.
    pub worker: String,
    /// Length of a claim's lease; renewed every third of it.
    pub lease: Duration,
    /// Counters and histograms of this process, for GET /metrics.
    pub metrics: crate::http::metrics::Metrics,
}

/// Default lease of a claimed job: a worker that stops renewing it for this long loses
/// the job to another.
pub const DEFAULT_LEASE: Duration = Duration::from_secs(30);

impl Ctx {
    pub fn new(store: Store, data_dir: PathBuf, max_queue: i64) -> Ctx {
        Ctx {
            store,
            data_dir,
            notify: Notify::new(),
            shutdown: AtomicBool::new(false),
            models: RwLock::new(HashMap::new()),
            max_queue,
            data_lock: None,
            infer_gate: crate::http::InferGate::new(crate::http::InferLimits::default()),
            worker: crate::store::worker_name(),
            lease: DEFAULT_LEASE,
            metrics: Default::default(),
        }
    }

    /// Claims jobs with leases of `lease` (renewed every third of it) instead of 30 s.
    pub fn with_lease(mut self, lease: Duration) -> Ctx {
        self.lease = lease;
        self
    }

    /// Bounds POST /infer by `limits` instead of the defaults.
    pub fn with_infer_limits(mut self, limits: crate::http::InferLimits) -> Ctx {
        self.infer_gate = crate::http::InferGate::new(limits);
        self
    }

    /// Keeps `lock` (the data directory's lock file, locked) for the life of the context.
    pub fn with_lock(mut self, lock: std::fs::File) -> Ctx {
        self.data_lock = Some(lock);
        self
    }

    /// A registered model, loaded once and shared.
    pub fn loaded(&self, id: &str, path: &Path) -> Result<Arc<Npe>> {
        if let Some(m) = self.models.read().map_err(|_| anyhow!("model cache poisoned"))?.get(id) {
            return Ok(m.clone());
        }
        let m = Arc::new(Npe::load(path)?);
        self.models.write().map_err(|_| anyhow!("model cache poisoned"))?.insert(id.to_string(), m.clone());
        Ok(m)
    }

    pub fn dataset_dir(&self, id: &str) -> PathBuf {
        self.data_dir.join("datasets").join(id)
    }
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
pub struct SimulateParams {
    pub n: Option<usize>,
    #[serde(default)]
    pub seed: u64,
    /// Rows in the order of the 7 parameters, then the `vary` effects.
    pub theta: Option<Vec<Vec<f64>>>,
    #[serde(default)]
    pub effects: BTreeMap<String, f64>,
    #[serde(default)]
    pub vary: Vec<String>,
    #[serde(default)]
    pub noise_scale: f64,
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
pub struct TrainParams {
    /// Id of a succeeded simulate job.
    pub dataset: String,
    #[serde(default = "one")]
    pub noise_scale: f64,
    #[serde(default)]
    pub seed: u64,
    #[serde(default = "epochs")]
    pub max_epochs: usize,
    #[serde(default)]
    pub mask_groups: bool,
    /// Flows in the ensemble (1..=8).
    #[serde(default = "one_member")]
    pub ensemble: usize,
}

fn one_member() -> usize {
    1
}
fn one() -> f64 {
    1.0
}
fn epochs() -> usize {
    300
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ResimulateParams {
    /// Rows of the 7 parameters (natural units), e.g. a MAP and posterior draws.
    pub theta: Vec<Vec<f64>>,
    #[serde(default)]
    pub effects: BTreeMap<String, f64>,
    /// The observation the rows were inferred from (250 features): drawn in the figure
    /// and compared by Spearman ρ per measure.
    pub observation: Option<Vec<f64>>,
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
pub struct DiagnoseParams {
    /// Base model id; the default model if absent.
    pub model: Option<String>,
    /// The observation: 250 features in the model's order (see GET /models/{id}).
    pub x: Vec<f64>,
    /// Effect names; all if absent.
    pub candidates: Option<Vec<String>>,
    #[serde(default = "yes")]
    pub extend: bool,
    #[serde(default = "rows")]
    pub train_rows: usize,
    #[serde(default = "epochs")]
    pub max_epochs: usize,
    #[serde(default = "nulls")]
    pub null_cases: usize,
    #[serde(default)]
    pub seed: u64,
}

fn yes() -> bool {
    true
}
fn rows() -> usize {
    10_000
}
fn nulls() -> usize {
    40
}

pub const MAX_ROWS: usize = 100_000;
pub const MAX_RESIMULATE: usize = 1_000;

/// A validation problem: the JSON path of the field and what is wrong with it.
pub type FieldError = (String, String);

/// Longest id a job may name (models, datasets).
pub const MAX_ID: usize = 64;

/// An id that names a row of the store: ASCII letters, digits, `_` and `-`, 1..=64 long.
/// Ids are looked up, never joined into a path, but a plain id keeps that true for
/// anything that might (`../../etc/model` is refused before it gets near the disk).
pub fn is_plain_id(id: &str) -> bool {
    (1..=MAX_ID).contains(&id.len()) && id.bytes().all(|b| b.is_ascii_alphanumeric() || b == b'_' || b == b'-')
}

fn plain_id(field: &str, id: &str, errs: &mut Vec<FieldError>) {
    if !is_plain_id(id) {
        errs.push((field.into(), format!("must be a plain id (1..={MAX_ID} of A-Z a-z 0-9 _ -)")));
    }
}

fn effects_of(map: &BTreeMap<String, f64>, errs: &mut Vec<FieldError>) -> Effects {
    let mut fx = Effects::default();
    for (name, v) in map {
        if let Err(e) = fx.set(name, *v) {
            errs.push((format!("params.effects.{name}"), e));
        }
    }
    fx
}

/// How far outside its prior box a requested parameter may lie: one decade each way
/// (log parameters) is far enough for any what-if, and keeps values such as 1e-308,
/// which no ear has and which break the solver's and the figures' arithmetic, out.
const THETA_SLACK_DECADES: f64 = 1.0;

/// Rows of `params.theta` with the nominal geometry inserted after the tissue columns
/// where a row gives only those (and then `n_effects` effect columns).
fn with_geometry(rows: &[Vec<f64>], n_effects: usize) -> Vec<Vec<f64>> {
    rows.iter().map(|r| if r.len() == N_TISSUE + n_effects { with_nominal_geometry(r) } else { r.clone() }).collect()
}

/// Checks the parameter values of `params.theta` rows (effects columns are checked
/// by the simulator's own range guard).
fn theta_values(rows: &[Vec<f64>], errs: &mut Vec<FieldError>) {
    for (i, row) in rows.iter().enumerate() {
        for (k, (v, p)) in row.iter().zip(PARAMS.iter()).enumerate() {
            let slack = 10f64.powf(THETA_SLACK_DECADES);
            let (lo, hi) = match p.scale {
                crate::sim::params::Scale::Log10 => (p.low / slack, p.high * slack),
                crate::sim::params::Scale::Linear => (p.low - (p.high - p.low), p.high + (p.high - p.low)),
            };
            if !v.is_finite() || *v < lo || *v > hi {
                errs.push((
                    format!("params.theta[{i}][{k}]"),
                    format!(
                        "{} = {v:e} {} is outside {lo:e}..={hi:e} (the prior box ±{THETA_SLACK_DECADES} decade)",
                        p.name, p.unit
                    ),
                ));
                return;
            }
        }
    }
}

/// A job's params as `T`; an error names the full JSON path of the field
/// (`params.theta[0][1]`, `params.bogus` for an unknown or missing one).
fn parse<T: serde::de::DeserializeOwned>(params: &serde_json::Value) -> Result<T, Vec<FieldError>> {
    let bytes = serde_json::to_vec(params).map_err(|e| vec![("params".to_string(), e.to_string())])?;
    // axum's Json tracks the path (serde_path_to_error): "…target type: theta[0][1]: invalid type: …".
    axum::Json::<T>::from_bytes(&bytes).map(|j| j.0).map_err(|r| vec![field_error("params", &r.body_text())])
}

/// (field, message) from the text of an axum Json data rejection, the field's path under
/// `root` (which may be empty).
pub fn field_error(root: &str, text: &str) -> FieldError {
    let text = text.split_once(": ").map_or(text, |(_, rest)| rest);
    let (path, message) = match text.split_once(": ") {
        Some((p, m)) if !p.contains(' ') => (p, m),
        _ => ("", text),
    };
    let mut field = root.to_string();
    if !path.is_empty() && path != "." {
        field += if path.starts_with('[') || field.is_empty() { "" } else { "." };
        field += path;
    }
    let named = message.strip_prefix("unknown field `").or_else(|| message.strip_prefix("missing field `"));
    // An unknown field's path ends with it already; a missing one's is its parent.
    if let Some(name) = named.and_then(|r| r.split('`').next())
        && !field.ends_with(&format!(".{name}"))
        && field != name
    {
        field = format!("{field}.{name}");
    }
    // The position is in a re-serialised copy of params: no use to the client.
    let message = message.split(" at line ").next().unwrap_or(message);
    (field, message.to_string())
}

/// Checks a job's params before it is queued, naming each bad field.
pub fn validate(kind: &str, params: &serde_json::Value) -> Result<(), Vec<FieldError>> {
    let mut errs = Vec::new();
    match kind {
        "simulate" => {
            let p: SimulateParams = parse(params)?;
            effects_of(&p.effects, &mut errs);
            for (i, v) in p.vary.iter().enumerate() {
                if Effects::index(v).is_none() {
                    errs.push((format!("params.vary[{i}]"), format!("unknown effect '{v}'")));
                } else if p.vary[..i].contains(v) {
                    errs.push((format!("params.vary[{i}]"), format!("'{v}' is already varied")));
                }
            }
            match (&p.n, &p.theta) {
                (Some(n), None) if *n == 0 || *n > MAX_ROWS => {
                    errs.push(("params.n".into(), format!("must be 1..={MAX_ROWS}")))
                }
                (None, Some(rows)) if rows.is_empty() || rows.len() > MAX_ROWS => {
                    errs.push(("params.theta".into(), format!("needs 1..={MAX_ROWS} rows")))
                }
                (None, Some(rows)) => {
                    let w = N_PARAMS + p.vary.len();
                    if let Some(i) = rows.iter().position(|r| r.len() != w && r.len() != w - N_GEOMETRY) {
                        errs.push((
                            format!("params.theta[{i}]"),
                            format!(
                                "needs {w} values (the {N_PARAMS} parameters, then the varied effects) or {} \
                                 (the {N_TISSUE} tissue parameters with nominal geometry, then the varied effects)",
                                w - N_GEOMETRY
                            ),
                        ));
                    } else {
                        theta_values(&with_geometry(rows, p.vary.len()), &mut errs);
                    }
                }
                (Some(_), Some(_)) => errs.push(("params".into(), "give either n or theta, not both".into())),
                (None, None) => errs.push(("params.n".into(), "give n (prior draws) or theta (rows)".into())),
                _ => {}
            }
            if !(p.noise_scale.is_finite() && p.noise_scale >= 0.0) {
                errs.push(("params.noise_scale".into(), "must be a finite number ≥ 0".into()));
            }
        }
        "train" => {
            let p: TrainParams = parse(params)?;
            plain_id("params.dataset", &p.dataset, &mut errs);
            if p.max_epochs == 0 || p.max_epochs > 5000 {
                errs.push(("params.max_epochs".into(), "must be 1..=5000".into()));
            }
            if !(p.noise_scale.is_finite() && p.noise_scale >= 0.0) {
                errs.push(("params.noise_scale".into(), "must be a finite number ≥ 0".into()));
            }
            if !(1..=8).contains(&p.ensemble) {
                errs.push(("params.ensemble".into(), "must be 1..=8".into()));
            }
        }
        "resimulate" => {
            let p: ResimulateParams = parse(params)?;
            effects_of(&p.effects, &mut errs);
            if p.theta.is_empty() || p.theta.len() > MAX_RESIMULATE {
                errs.push(("params.theta".into(), format!("needs 1..={MAX_RESIMULATE} rows")));
            }
            if let Some(i) = p.theta.iter().position(|r| r.len() != N_PARAMS && r.len() != N_TISSUE) {
                errs.push((
                    format!("params.theta[{i}]"),
                    format!(
                        "needs {N_PARAMS} values ({}) or the first {N_TISSUE} (nominal geometry)",
                        PARAMS.map(|p| p.name).join(", ")
                    ),
                ));
            } else {
                theta_values(&with_geometry(&p.theta, 0), &mut errs);
            }
            if let Some(x) = &p.observation {
                let n = 5 * crate::sim::ModelConfig::default().frequencies.len();
                if x.len() != n {
                    errs.push((
                        "params.observation".into(),
                        format!("needs {n} features in the model's order, got {}", x.len()),
                    ));
                } else if let Some(i) = x.iter().position(|v| !v.is_finite()) {
                    errs.push((format!("params.observation[{i}]"), "must be a finite number".into()));
                }
            }
        }
        "diagnose" => {
            let p: DiagnoseParams = parse(params)?;
            if let Some(m) = &p.model {
                plain_id("params.model", m, &mut errs);
            } else if params.get("model").is_some() {
                errs.push(("params.model".into(), "must be a model id, or left out for the default model".into()));
            }
            if let Some(i) = p.x.iter().position(|v| !v.is_finite()) {
                errs.push((format!("params.x[{i}]"), "must be a finite number".into()));
            }
            for (i, c) in p.candidates.iter().flatten().enumerate() {
                if Effects::index(c).is_none() {
                    errs.push((
                        format!("params.candidates[{i}]"),
                        format!("unknown effect '{c}' (known: {})", effect_names()),
                    ));
                }
            }
            if p.train_rows < 100 || p.train_rows > MAX_ROWS {
                errs.push(("params.train_rows".into(), format!("must be 100..={MAX_ROWS}")));
            }
            if p.max_epochs == 0 || p.max_epochs > 5000 {
                errs.push(("params.max_epochs".into(), "must be 1..=5000".into()));
            }
            if p.null_cases < 5 || p.null_cases > 1000 {
                errs.push(("params.null_cases".into(), "must be 5..=1000".into()));
            }
        }
        other => errs.push(("kind".into(), format!("unknown job kind '{other}' (known: {})", KINDS.join(", ")))),
    }
    if errs.is_empty() { Ok(()) } else { Err(errs) }
}

/// Reports progress and tells the worker whether to stop.
pub struct Reporter {
    tx: tokio::sync::mpsc::UnboundedSender<(f64, String)>,
    cancel: Arc<AtomicBool>,
    /// The claim: (job id, lease token), for the renewal before results are written.
    claim: (String, String),
}

impl Reporter {
    fn report(&self, progress: f64, message: String) -> bool {
        let _ = self.tx.send((progress, message));
        !self.cancel.load(Ordering::Relaxed)
    }

    /// Renews the lease (blocking; called from the job's thread) right before results are
    /// written: `Err(LeaseLost)` if the job is no longer this worker's, so nothing is
    /// written. After a renewal no other worker can claim the job for a whole lease.
    fn still_ours(&self, ctx: &Ctx) -> Result<()> {
        let (id, token) = (&self.claim.0, &self.claim.1);
        let renewed = tokio::runtime::Handle::current().block_on(ctx.store.heartbeat(id, token, ctx.lease));
        match renewed {
            Ok(true) => Ok(()),
            Ok(false) => {
                self.cancel.store(true, Ordering::Relaxed);
                bail!(LeaseLost)
            }
            Err(e) => Err(anyhow!(e).context("renewing the lease before writing results")),
        }
    }
}

#[derive(Debug, thiserror::Error)]
#[error("stopped on request")]
struct Stopped;

/// The job's lease was lost: another worker may hold it now.
#[derive(Debug, thiserror::Error)]
#[error("the job's lease was lost; this worker's results are dropped")]
pub struct LeaseLost;

/// Moves a finished simulate attempt's files from its staging folder into `dir`.
fn publish_dataset(staging: &Path, dir: &Path) -> Result<()> {
    for name in dataset::FILES {
        std::fs::rename(staging.join(name), dir.join(name)).with_context(|| format!("moving {name} into place"))?;
    }
    let _ = std::fs::remove_dir(staging);
    Ok(())
}

/// The staging folder of one attempt of a simulate job: its own, so two attempts of the
/// same job (a stalled worker and the one that took over) never write the same files.
fn staging_dir(dir: &Path, token: &str) -> PathBuf {
    dir.join(format!(".attempt-{}", &token[..token.len().min(16)]))
}

/// Runs one job's CPU work (on a blocking thread). Returns the job's result document.
fn execute(ctx: &Ctx, job: &JobRow, r: &Reporter) -> Result<serde_json::Value> {
    match job.kind.as_str() {
        "simulate" => {
            let p: SimulateParams = serde_json::from_value(job.params.clone())?;
            let mut errs = Vec::new();
            let mut design = Design { fixed: effects_of(&p.effects, &mut errs), varied: vec![] };
            design.varied = p.vary.iter().filter_map(|v| Effects::index(v)).collect();
            let model = Model::new(ModelConfig::default())?;
            let noise = Noise { std: default_noise_std(&model), scale: p.noise_scale, seed: p.seed };
            let rows = match p.theta {
                Some(t) => Rows::Given(with_geometry(&t, design.varied.len())),
                None => Rows::Prior { n: p.n.unwrap_or(0), seed: p.seed },
            };
            let dir = ctx.dataset_dir(&job.id);
            let staging = staging_dir(&dir, &r.claim.1);
            let mut last = 0;
            let meta = dataset::simulate_to_dir(
                &model,
                &design,
                &rows,
                &noise,
                model.config.preset,
                &staging,
                &mut |done, n| {
                    ctx.metrics.simulated(done.saturating_sub(last) as u64);
                    last = done;
                    r.report(done as f64 / n as f64, format!("simulated {done}/{n}"))
                },
            )
            .map_err(|e| match e {
                dataset::DatasetError::Cancelled(_) => Stopped.into(),
                e => anyhow::Error::from(e),
            })?;
            r.still_ours(ctx)?;
            publish_dataset(&staging, &dir)?;
            Ok(serde_json::json!({
                "dataset": format!("/datasets/{}", job.id),
                "rows": meta.n_rows,
                "failed": meta.failed.len(),
                "wall_seconds": meta.wall_seconds,
            }))
        }
        "train" => {
            let p: TrainParams = serde_json::from_value(job.params.clone())?;
            let dir = ctx.dataset_dir(&p.dataset);
            let ds = Dataset::load(&dir).with_context(|| format!("dataset '{}'", p.dataset))?;
            let s = TrainSettings {
                noise_scale: p.noise_scale,
                seed: p.seed,
                max_epochs: p.max_epochs,
                mask_groups: p.mask_groups,
                ensemble: p.ensemble,
                ..TrainSettings::default()
            };
            // Progress over all members (each may stop early, so this is a lower bound).
            let max = (s.max_epochs * s.ensemble) as f64;
            let model = npe::train(&ds, &s, &mut |e| {
                r.report(
                    (e.member * s.max_epochs + e.epoch) as f64 / max,
                    format!("member {} epoch {} val loss {:.4}", e.member, e.epoch, e.val_loss),
                )
            })?;
            if ctx.shutdown.load(Ordering::Relaxed) {
                bail!(Stopped);
            }
            r.still_ours(ctx)?;
            let models = ctx.data_dir.join("models");
            std::fs::create_dir_all(&models)?;
            let path = models.join(format!("{}.otofit", job.id));
            model.save(&path)?;
            Ok(serde_json::json!({
                "model": format!("/models/{}", job.id),
                "epochs": model.header.training.epochs,
                "best_val_loss": model.header.training.best_val_loss,
                "cancelled_early": r.cancel.load(Ordering::Relaxed),
            }))
        }
        "resimulate" => {
            let p: ResimulateParams = serde_json::from_value(job.params.clone())?;
            let mut errs = Vec::new();
            let design = Design { fixed: effects_of(&p.effects, &mut errs), varied: vec![] };
            let model = Model::new(ModelConfig::default())?;
            let theta = with_geometry(&p.theta, 0);
            let out = run_rows(&model, &design, &theta, 0, None);
            let x: Vec<serde_json::Value> = out
                .iter()
                .map(|res| match res {
                    Ok(x) => serde_json::json!(x),
                    Err(e) => serde_json::json!({ "error": e.to_string() }),
                })
                .collect();
            r.report(1.0, format!("{} rows", p.theta.len()));
            let ok: Vec<&[f64]> = out.iter().filter_map(|o| o.as_deref().ok()).collect();
            let page = crate::plot::resimulation(model.frequencies(), &theta, &ok, p.observation.as_deref());
            r.still_ours(ctx)?;
            let dir = ctx.data_dir.join("reports").join(&job.id);
            std::fs::create_dir_all(&dir)?;
            std::fs::write(dir.join("spectra.svg"), &page.svg)?;
            std::fs::write(dir.join("report.html"), &page.html)?;
            let files = |n: &str| format!("/jobs/{}/files/{n}", job.id);
            Ok(
                serde_json::json!({ "features": feature_names(model.frequencies()), "x": x, "rho": page.rho, "figures": [files("spectra.svg")], "report": files("report.html") }),
            )
        }
        "diagnose" => {
            use crate::discrepancy::workflow::{Settings, diagnose};
            let p: DiagnoseParams = serde_json::from_value(job.params.clone())?;
            let id = p.model.as_deref().unwrap_or("default");
            let base = registered_model(ctx, id)?;
            if p.x.len() != base.header.feature_names.len() {
                bail!(
                    "params.x has {} values; model '{id}' has {} features",
                    p.x.len(),
                    base.header.feature_names.len()
                );
            }
            let candidates = match &p.candidates {
                Some(c) => c.iter().filter_map(|n| Effects::index(n)).collect(),
                None => (0..EFFECTS.len()).collect(),
            };
            let s = Settings {
                candidates,
                extend: p.extend,
                train_rows: p.train_rows,
                max_epochs: p.max_epochs,
                null_cases: p.null_cases,
                seed: p.seed,
                cancel: Some(r.cancel.clone()),
                ..Settings::default()
            };
            let model = Model::new(ModelConfig::default())?;
            let steps = ["fit", "check", "null", "name", "add", "training"];
            let report = diagnose(&model, &base, &p.x, &s, &mut |m| {
                let k = steps.iter().position(|s| m.contains(s)).unwrap_or(0);
                let _ = r.report(k as f64 / steps.len() as f64, m.to_string());
            })
            .map_err(|e| match e {
                crate::discrepancy::DiagnoseError::Cancelled => Stopped.into(),
                e => anyhow::Error::from(e),
            })?;
            // Fencing: a job cancelled or interrupted meanwhile writes no report and no model.
            if r.cancel.load(Ordering::Relaxed) {
                bail!(Stopped);
            }
            r.still_ours(ctx)?;
            let links = crate::plot::diagnosis::Links {
                figure: &|n| format!("/jobs/{}/files/{n}", job.id),
                model: (ctx.data_dir.join("models").join(format!("{}.otofit", job.id)), format!("/models/{}", job.id)),
                page: Some(format!("/jobs/{}/files/report.html", job.id)),
            };
            Ok(crate::plot::diagnosis::write_report(&ctx.data_dir.join("reports").join(&job.id), &report, &links)?)
        }
        other => bail!("unknown job kind '{other}'"),
    }
}

/// A model by its id, looked up in the store (never a path built from the id). Errors
/// name the id, not the file: job errors are shown to clients.
pub fn registered_model(ctx: &Ctx, id: &str) -> Result<Arc<Npe>> {
    let unknown = || anyhow!("model '{id}' is not registered");
    if !is_plain_id(id) {
        return Err(unknown());
    }
    let rt = tokio::runtime::Handle::current();
    let row = rt.block_on(ctx.store.model(id))?.ok_or_else(unknown)?;
    ctx.loaded(&row.id, Path::new(&row.path)).map_err(|e| {
        tracing::error!(model = %id, error = %format!("{e:#}"), "model cannot be loaded");
        anyhow!("model '{id}' cannot be loaded (the server log says why)")
    })
}

/// An error message for clients: the server's own directories replaced by names.
fn scrub(ctx: &Ctx, msg: &str) -> String {
    let mut out = msg.to_string();
    let mut dirs: Vec<(PathBuf, &str)> = vec![];
    if ctx.data_dir.is_absolute() {
        dirs.push((ctx.data_dir.clone(), "DATA_DIR"));
    }
    if let Ok(d) = std::fs::canonicalize(&ctx.data_dir) {
        dirs.push((d, "DATA_DIR"));
    }
    if let Ok(d) = std::env::current_dir() {
        dirs.push((d, "."));
    }
    dirs.sort_by_key(|(d, _)| std::cmp::Reverse(d.as_os_str().len()));
    for (d, name) in dirs {
        let d = d.display().to_string();
        if d.len() > 1 {
            out = out.replace(&d, name);
        }
    }
    out
}

/// The dispatcher: takes back jobs whose lease expired, claims and runs jobs until
/// shutdown. Any number of dispatchers, in any number of processes, may share a store.
pub async fn dispatcher(ctx: Arc<Ctx>) {
    loop {
        if ctx.shutdown.load(Ordering::Relaxed) {
            break;
        }
        match ctx.store.reap_expired().await {
            Ok((0, 0)) => {}
            Ok((requeued, failed)) => {
                ctx.metrics.reaped(requeued + failed);
                tracing::warn!(requeued, failed, "took back jobs whose lease expired")
            }
            Err(e) => tracing::error!(error = %e, "reaping expired leases failed"),
        }
        match ctx.store.claim(&ctx.worker, ctx.lease).await {
            Ok(Some(job)) => {
                ctx.metrics.claimed();
                run(ctx.clone(), job).await
            }
            Ok(None) => {
                tokio::select! {
                    _ = ctx.notify.notified() => {}
                    _ = tokio::time::sleep(Duration::from_secs(1)) => {}
                }
            }
            Err(e) => {
                tracing::error!(error = %e, "claiming a job failed");
                tokio::time::sleep(Duration::from_secs(1)).await;
            }
        }
    }
}

async fn run(ctx: Arc<Ctx>, job: JobRow) {
    let t0 = std::time::Instant::now();
    let token = job.lease_token.clone().unwrap_or_default();
    tracing::info!(job = %job.id, kind = %job.kind, attempt = job.attempts, worker = %ctx.worker, "job started");
    let cancel = Arc::new(AtomicBool::new(false));
    let (tx, mut rx) = tokio::sync::mpsc::unbounded_channel();
    let reporter = Reporter { tx, cancel: cancel.clone(), claim: (job.id.clone(), token.clone()) };
    let (c2, j2) = (ctx.clone(), job.clone());
    let mut handle = tokio::task::spawn_blocking(move || execute(&c2, &j2, &reporter));
    // Intervals, not sleeps inside select!: progress messages must not starve the checks.
    let mut check = tokio::time::interval(Duration::from_millis(300));
    let mut renew = tokio::time::interval(ctx.lease / 3);
    renew.reset();
    let mut lost = false;
    let result = loop {
        tokio::select! {
            Some((p, m)) = rx.recv() => {
                if let Err(e) = ctx.store.progress(&job.id, &token, p, &m).await {
                    tracing::warn!(job = %job.id, error = %e, "progress not saved");
                }
            }
            _ = check.tick() => {
                if ctx.shutdown.load(Ordering::Relaxed) || ctx.store.cancel_requested(&job.id).await {
                    cancel.store(true, Ordering::Relaxed);
                }
            }
            _ = renew.tick() => match ctx.store.heartbeat(&job.id, &token, ctx.lease).await {
                Ok(true) => {}
                Ok(false) => {
                    ctx.metrics.lease_lost();
                    tracing::warn!(job = %job.id, "lease lost: stopping the job; its results will be dropped");
                    lost = true;
                    cancel.store(true, Ordering::Relaxed);
                }
                // A database hiccup: the lease still has two thirds to run; retried next tick.
                Err(e) => tracing::warn!(job = %job.id, error = %e, "lease not renewed"),
            },
            res = &mut handle => break res,
        }
    };
    let shutting_down = ctx.shutdown.load(Ordering::Relaxed);
    let cancelled = cancel.load(Ordering::Relaxed);
    let store = &ctx.store;
    // Every end is fenced by the lease token this worker claimed (see `Store::finish`).
    let id = job.id.as_str();
    let (label, outcome) = match result {
        _ if lost => ("lease_lost", Ok(false)),
        Ok(Err(e)) if e.is::<LeaseLost>() => ("lease_lost", Ok(false)),
        Err(e) => ("failed", store.finish(id, &token, "failed", Some(&format!("worker panicked: {e}")), None).await),
        // Interrupted by shutdown: back to the queue, the attempt not counted.
        Ok(_) if cancelled && shutting_down => ("requeued", store.requeue(id, &token).await),
        // A cancelled training still returns its best weights: that is a result.
        Ok(Ok(doc)) => ("succeeded", store.finish(id, &token, "succeeded", None, Some(&doc)).await),
        Ok(Err(e)) if cancelled || e.is::<Stopped>() => {
            ("cancelled", store.finish(id, &token, "cancelled", None, None).await)
        }
        Ok(Err(e)) => ("failed", store.finish(id, &token, "failed", Some(&scrub(&ctx, &format!("{e:#}"))), None).await),
    };
    let label = match outcome {
        Ok(true) => label,
        Ok(false) => "lease_lost",
        Err(_) => "not_saved",
    };
    ctx.metrics.job_ended(&job.kind, label, t0.elapsed().as_secs_f64());
    if job.kind == "simulate" {
        // This attempt's staging folder: moved into place on success, else left over.
        let staging = staging_dir(&ctx.dataset_dir(&job.id), &token);
        if staging.exists() {
            let _ = std::fs::remove_dir_all(&staging);
        }
    }
    let owned = match outcome {
        Ok(owned) => owned,
        Err(e) => {
            tracing::error!(job = %job.id, error = %e, "job state not saved");
            false
        }
    };
    if !owned {
        // Another worker holds the job now: its files and its model are its own.
        tracing::warn!(job = %job.id, attempt = job.attempts, "the job is no longer this worker's; its outcome is dropped");
        return;
    }
    if job.kind == "simulate" {
        // The job has ended: leftovers of earlier attempts of it are garbage now.
        remove_temporary_files(&ctx.dataset_dir(&job.id));
    }
    if (job.kind == "train" || job.kind == "diagnose")
        && let Ok(Some(j)) = ctx.store.job(&job.id).await
    {
        let path = ctx.data_dir.join("models").join(format!("{}.otofit", job.id));
        // Absolute: every process sharing the store (and the data directory, mounted at
        // the same path) loads the model by this path, whatever its working directory.
        if j.state == "succeeded"
            && let Ok(path) = std::fs::canonicalize(&path)
        {
            let _ = ctx.store.add_model(&job.id, &path.display().to_string(), false, Some(&job.id)).await;
        }
    }
    tracing::info!(job = %job.id, seconds = t0.elapsed().as_secs_f64(), "job ended");
}

/// Removes the `*.tmp` files a simulate job writes before renaming them into place, and
/// the staging folders (`.attempt-*`) of its attempts: what a failed, cancelled,
/// interrupted or superseded run leaves behind. Returns how many went.
pub fn remove_temporary_files(dir: &Path) -> usize {
    let Ok(entries) = std::fs::read_dir(dir) else { return 0 };
    entries
        .flatten()
        .filter(|e| {
            let name = e.file_name().to_string_lossy().into_owned();
            if name.starts_with(".attempt-") {
                std::fs::remove_dir_all(e.path()).is_ok()
            } else {
                name.ends_with(".tmp") && std::fs::remove_file(e.path()).is_ok()
            }
        })
        .count()
}

/// A new job id: time-ordered, unguessable enough for a local service.
pub fn new_id() -> String {
    use rand::Rng;
    let ms = std::time::SystemTime::now().duration_since(std::time::UNIX_EPOCH).unwrap_or_default().as_millis();
    format!("{ms:012x}{:08x}", rand::rng().random::<u32>())
}

/// Known effect names, for error messages.
pub fn effect_names() -> String {
    EFFECTS.iter().map(|e| e.name).collect::<Vec<_>>().join(", ")
}
