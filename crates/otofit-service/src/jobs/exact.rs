//! `exact`: the posterior of one observation under the model's own likelihood
//! (`discrepancy::exact`, `otofit infer --exact`): ten seconds or more of a core per
//! observation, so it runs on the job queue, not in POST /infer.

use super::spec::{FieldError, in_range, model_and_observation};
use super::{Ctx, JobError, Reporter, limits, registered_model};
use crate::npe::Obs;
use serde::{Deserialize, Serialize};

/// The params of an exact job.
#[derive(Clone, Debug, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ExactParams {
    /// Model id; the default model if absent.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub model: Option<String>,
    /// The observation: the model's features in its order (see GET /models/{id}), `null`
    /// for a feature not measured. A patient's measurement: shown to its tenant only.
    pub x: Vec<Option<f64>>,
    /// Metropolis steps of the four chains together, one simulation each (default 100,000, the length measured
    /// calibrated).
    #[serde(default = "steps")]
    pub steps: usize,
    /// Seed of the flow's draws (the fits' starts) and of the chain.
    #[serde(default)]
    pub seed: u64,
}

fn steps() -> usize {
    crate::discrepancy::exact::MIN_STEPS
}

impl ExactParams {
    /// The checks that need no model (its existence and feature count are checked
    /// against the store when the job is posted).
    pub(super) fn validate(&self, errs: &mut Vec<FieldError>) {
        model_and_observation(self.model.as_deref(), &self.x, errs);
        in_range("params.steps", &limits::EXACT_STEPS, self.steps, errs);
    }

    /// The model's id (`default` when absent).
    pub fn model_id(&self) -> &str {
        self.model.as_deref().unwrap_or("default")
    }
}

pub(super) fn execute(ctx: &Ctx, p: &ExactParams, r: &Reporter) -> Result<serde_json::Value, JobError> {
    use crate::discrepancy::fitcheck::FitCheckError;
    let id = p.model_id();
    let npe = registered_model(ctx, id)?;
    if p.x.len() != npe.header.feature_names.len() {
        let n = npe.header.feature_names.len();
        return Err(JobError::client(format!("params.x has {} values; model '{id}' has {n} features", p.x.len())));
    }
    let x: Vec<f64> = p.x.iter().map(|v| v.unwrap_or(f64::NAN)).collect();
    let present: Vec<bool> = p.x.iter().map(Option::is_some).collect();
    // The full-measure flow answers an ear with every measure, when the model holds one.
    let npe = npe.answering(&Obs { x: &x, present: Some(&present) });
    r.report(0.0, "the flow's posterior and the fit check".into());
    let inf = npe
        .infer(&Obs { x: &x, present: Some(&present) }, 1000, p.seed)
        .map_err(|e| JobError::npe(e, &format!("model '{id}'"), "the flow's posterior could not be computed"))?;
    let fit = crate::discrepancy::fitcheck::fit_check(npe, &x, &present, &inf);
    r.report(0.05, format!("least-squares fits, then {} chain steps", p.steps));
    let ex = crate::discrepancy::fitcheck::exact(npe, &x, &present, &inf, p.steps, p.seed).map_err(|e| match e {
        FitCheckError::Simulator(_) => JobError::internal("the simulator could not be built", e),
        // Not otofit's model, or a chain that cannot start on this observation.
        e => JobError::client(e.to_string()),
    })?;
    let withdrawn = match &fit {
        Ok(f) if f.ok == Some(false) => Some(f.reason.clone().unwrap_or_default()),
        _ => None,
    };
    let fit = fit.map_or_else(|e| serde_json::json!({ "ok": null, "reason": e.to_string() }), |f| serde_json::json!(f));
    let diagnostics = across_chains(&ex.chain.samples, ex.chain.chains);
    r.still_ours(ctx)?;
    Ok(serde_json::json!({
        "model": id,
        "fit": fit,
        "flow": inf.summaries,
        "differential": ex.reading(npe, withdrawn.as_deref()),
        "exact": ex,
        "diagnostics": diagnostics,
        "note": crate::discrepancy::fitcheck::EXACT_NOTE,
    }))
}

/// The chains' diagnostic: their kept draws (chain after chain) cut into `chains`
/// segments, one per chain, read by `exact_fast::by_segments` (rank-normalised split
/// R-hat, bulk and tail ESS, the worst over the parameters).
fn across_chains(draws: &[Vec<f64>], chains: usize) -> serde_json::Value {
    let (rhat, ess_bulk, ess_tail, n) = crate::discrepancy::exact_fast::by_segments(draws, chains);
    serde_json::json!({ "rhat": rhat, "ess_bulk": ess_bulk, "ess_tail": ess_tail, "chains": chains, "draws": n })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn chains_that_disagree_are_flagged() {
        // Draws alternating ±1 (one coordinate) around a level that climbs from 0 to 6
        // over four chains of 1,000: the chains disagree. Four chains of the same values
        // do not.
        let drift: Vec<Vec<f64>> =
            (0..4000).map(|t| vec![6.0 * t as f64 / 4000.0 + if t % 2 == 0 { 1.0 } else { -1.0 }]).collect();
        let d = across_chains(&drift, 4);
        assert!(d["rhat"].as_f64().unwrap() > 1.5, "{d}");
        assert_eq!((d["chains"].as_u64(), d["draws"].as_u64()), (Some(4), Some(4000)), "{d}");
        let flat: Vec<Vec<f64>> = (0..4000).map(|t| vec![((t * 7919) % 1000) as f64]).collect();
        let d = across_chains(&flat, 4);
        assert!(d["rhat"].as_f64().unwrap() < 1.05, "{d}");
    }
}
