//! POST /log_prob: log q(θ|x) of given parameter sets for one ear's measurements (the
//! same measurements as POST /infer), e.g. to compare candidate ears or to check a
//! posterior against a known truth.

use super::{AppState, JsonBody, Problem};
use crate::measurements::Measurements;
use crate::npe::Obs;
use axum::Json;
use axum::extract::State;
use serde::{Deserialize, Serialize};

/// Parameter sets per request: each costs one flow pass, far less than a sample.
pub const MAX_THETA: usize = 10_000;

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
pub struct LogProbRequest {
    pub model: Option<String>,
    pub measurements: Measurements,
    /// Rows in the model's parameter order (GET /models/{id}), natural units.
    pub theta: Vec<Vec<f64>>,
}

pub async fn log_prob(
    State(st): State<AppState>,
    axum::Extension(who): axum::Extension<super::Principal>,
    JsonBody(req): JsonBody<LogProbRequest>,
) -> Result<Json<LogProbResponse>, Problem> {
    if req.theta.is_empty() || req.theta.len() > MAX_THETA {
        return Err(Problem::invalid(vec![("theta".into(), format!("needs 1..={MAX_THETA} rows"))]));
    }
    let (row, npe) = super::infer::model_for(&st, &who, req.model.as_deref()).await?;
    let d = npe.params().len();
    let mut errs = Vec::new();
    for (i, t) in req.theta.iter().enumerate() {
        if t.len() != d {
            let names: Vec<&str> = npe.params().iter().map(|p| p.name.as_str()).collect();
            errs.push((
                format!("theta[{i}]"),
                format!("has {} values; the model takes {d} ({})", t.len(), names.join(", ")),
            ));
        } else if let Some(k) = t.iter().position(|v| !v.is_finite()) {
            errs.push((format!("theta[{i}][{k}]"), "must be a finite number".into()));
        }
    }
    if !errs.is_empty() {
        errs.truncate(10);
        return Err(Problem::invalid(errs));
    }
    let (x, present, used) = super::infer::features(&npe, &req.measurements, None)?;
    let theta = req.theta;
    // The density of the flow /infer samples for these measurements.
    let flow = npe.answering_name(&Obs { x: &x, present: Some(&present) });
    let npe2 = npe.clone();
    let lp = tokio::task::spawn_blocking(move || {
        let obs = Obs { x: &x, present: Some(&present) };
        npe2.answering(&obs).log_prob(&obs, &theta).map(|lp| (lp, theta))
    })
    .await
    .map_err(Problem::internal)?
    .map_err(super::infer::npe_problem)?;
    let (lp, theta) = lp;
    // Outside the prior box the posterior density is zero: null, and listed.
    let inside = |t: &[f64]| npe.params().iter().zip(t).all(|(p, v)| (p.low..=p.high).contains(v));
    let outside: Vec<usize> = (0..theta.len()).filter(|&i| !inside(&theta[i])).collect();
    let values: Vec<Option<f64>> =
        lp.iter().enumerate().map(|(i, v)| (!outside.contains(&i) && v.is_finite()).then_some(*v)).collect();
    Ok(Json(LogProbResponse {
        model: row.id,
        columns: npe.params().iter().map(|p| p.name.clone()).collect(),
        inputs: UsedInputs { used, flow },
        log_prob: values,
        outside_prior: outside,
    }))
}

/// The answer of POST /log_prob.
#[derive(Serialize)]
pub struct LogProbResponse {
    /// The model's id.
    pub model: String,
    /// The parameter of each column of `theta`.
    pub columns: Vec<String>,
    pub inputs: UsedInputs,
    /// Each row's log density; null outside the prior box (or not finite).
    pub log_prob: Vec<Option<f64>>,
    /// The rows outside the prior box.
    pub outside_prior: Vec<usize>,
}

/// The response's `inputs`: the feature blocks the measurements gave.
#[derive(Serialize)]
pub struct UsedInputs {
    pub used: Vec<&'static str>,
    /// The flow whose density this is (`full-measure`, `measure-set` or `main`, as POST /infer's).
    pub flow: &'static str,
}
