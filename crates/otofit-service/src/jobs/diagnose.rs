//! `diagnose`: the discrepancy workflow on one observation against a registered model
//! (fit, check, name the missing effect, add it and retrain), with a report page, its
//! figures and the extended model.

use super::spec::{FieldError, effect_names, in_range, model_and_observation};
use super::{Ctx, JobContext, JobError, Reporter, Stopped, limits, registered_model};
use crate::sim::params::{EFFECTS, Effects};
use crate::sim::{Model, ModelConfig};
use serde::{Deserialize, Serialize};
use std::sync::atomic::Ordering;

/// The params of a diagnose job: find where model and observation disagree, name the effect.
#[derive(Clone, Debug, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct DiagnoseParams {
    /// Base model id; the default model if absent.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub model: Option<String>,
    /// The observation: the model's features in its order (see GET /models/{id}), `null`
    /// for a feature not measured (a whole measure, e.g. no umbo LDV: the base model must
    /// accept that subset). A patient's measurement: shown to its tenant only.
    pub x: Vec<Option<f64>>,
    /// Effect names; all if absent.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub candidates: Option<Vec<String>>,
    /// Add the named effect and retrain the model with it (default true).
    #[serde(default = "yes")]
    pub extend: bool,
    /// Size of the extended model's training set (default 10,000).
    #[serde(default = "rows")]
    pub train_rows: usize,
    /// Epochs at most of the extended model's training (default 1000; the default recipe
    /// ends sooner).
    #[serde(default = "super::train::epochs")]
    pub max_epochs: usize,
    /// Effect-free simulations for the null distribution of the statistics (default 40).
    #[serde(default = "nulls")]
    pub null_cases: usize,
    /// Seed of the null simulations, the fits' starts and the extended training.
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

impl DiagnoseParams {
    /// The checks that need no model (its existence and feature count are checked
    /// against the store when the job is posted).
    pub(super) fn validate(&self, errs: &mut Vec<FieldError>) {
        model_and_observation(self.model.as_deref(), &self.x, errs);
        for (i, c) in self.candidates.iter().flatten().enumerate() {
            if Effects::index(c).is_none() {
                errs.push((
                    format!("params.candidates[{i}]"),
                    format!("unknown effect '{c}' (known: {})", effect_names()),
                ));
            }
        }
        in_range("params.train_rows", &limits::TRAIN_ROWS, self.train_rows, errs);
        in_range("params.max_epochs", &limits::EPOCHS, self.max_epochs, errs);
        in_range("params.null_cases", &limits::NULL_CASES, self.null_cases, errs);
    }

    /// The base model's id (`default` when absent).
    pub fn model_id(&self) -> &str {
        self.model.as_deref().unwrap_or("default")
    }
}

pub(super) fn execute(
    ctx: &Ctx,
    job_id: &str,
    p: &DiagnoseParams,
    r: &Reporter,
) -> Result<serde_json::Value, JobError> {
    use crate::discrepancy::DiagnoseError;
    use crate::discrepancy::workflow::{Settings, diagnose};
    let id = p.model_id();
    let base = registered_model(ctx, id)?;
    if p.x.len() != base.header.feature_names.len() {
        let n = base.header.feature_names.len();
        return Err(JobError::client(format!("params.x has {} values; model '{id}' has {n} features", p.x.len())));
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
    let model = Model::new(ModelConfig::default()).internal("the simulator could not be set up")?;
    let x: Vec<f64> = p.x.iter().map(|v| v.unwrap_or(f64::NAN)).collect();
    let report = diagnose(&model, &base, &x, &s, &mut |m| {
        let k = crate::discrepancy::workflow::stage_of(m);
        let _ = r.report(k as f64 / crate::discrepancy::workflow::STAGES.len() as f64, m.to_string());
    })
    .map_err(|e| match e {
        DiagnoseError::Cancelled => Stopped.into(),
        DiagnoseError::Npe(e) => {
            JobError::npe(e, "the extended model's training data", "the posterior estimator failed")
        }
        // The observation or the base model does not fit the workflow.
        e if e.is_input() => JobError::client(e.to_string()),
        // A failed step (the MAP's simulation, the base fit): its message names the step,
        // its source says why.
        e => JobError::internal(e.to_string(), e),
    })?;
    // Fencing: a job cancelled or interrupted meanwhile writes no report and no model.
    if r.cancel.load(Ordering::Relaxed) {
        return Err(Stopped.into());
    }
    r.still_ours(ctx)?;
    let links = crate::plot::diagnosis::Links {
        figure: &|n| format!("/jobs/{job_id}/files/{n}"),
        model: (ctx.data_dir.join("models").join(format!("{job_id}.otofit")), format!("/models/{job_id}")),
        page: Some(format!("/jobs/{job_id}/files/report.html")),
    };
    crate::plot::diagnosis::write_report(&ctx.data_dir.join("reports").join(job_id), &report, &links)
        .internal("the report or the extended model could not be written")
}
