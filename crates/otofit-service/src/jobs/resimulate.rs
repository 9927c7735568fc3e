//! `resimulate`: given parameter rows (a MAP, posterior draws) through the simulator,
//! with a figure and a report page; with the observation they were inferred from, ρ per
//! row and measure.

use super::spec::{FieldError, effects_of, theta_values, with_geometry};
use super::{Ctx, JobContext, JobError, Reporter, limits};
use crate::sim::batch::{Design, run_rows};
use crate::sim::output::feature_names;
use crate::sim::params::{N_PARAMS, N_TISSUE, PARAMS};
use crate::sim::{Model, ModelConfig};
use anyhow::Context;
use serde::{Deserialize, Serialize};
use std::collections::BTreeMap;

/// The params of a resimulate job: spectra of given parameter rows, drawn over an observation.
#[derive(Clone, Debug, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ResimulateParams {
    /// Rows of the 10 parameters or the 7 tissue ones (natural units), e.g. a MAP and
    /// posterior draws.
    pub theta: Vec<Vec<f64>>,
    /// Modelling effects set to a fixed value, by name.
    #[serde(default)]
    pub effects: BTreeMap<String, f64>,
    /// The observation the rows were inferred from (the model's features): drawn in the figure
    /// and compared by Spearman ρ per measure. A patient's measurement: shown to its
    /// tenant only.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub observation: Option<Vec<f64>>,
}

impl ResimulateParams {
    pub(super) fn validate(&self, errs: &mut Vec<FieldError>) {
        effects_of(&self.effects, errs);
        if !limits::RESIMULATE_ROWS.contains(&self.theta.len()) {
            errs.push(("params.theta".into(), format!("needs 1..={} rows", limits::RESIMULATE_ROWS.end())));
        }
        if let Some(i) = self.theta.iter().position(|r| r.len() != N_PARAMS && r.len() != N_TISSUE) {
            errs.push((
                format!("params.theta[{i}]"),
                format!(
                    "needs {N_PARAMS} values ({}) or the first {N_TISSUE} (nominal geometry)",
                    PARAMS.map(|p| p.name).join(", ")
                ),
            ));
        } else {
            theta_values(&with_geometry(&self.theta, 0), errs);
        }
        if let Some(x) = &self.observation {
            let n = crate::sim::output::N_MEASURES * ModelConfig::default().frequencies.len();
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
}

pub(super) fn execute(ctx: &Ctx, id: &str, p: &ResimulateParams, r: &Reporter) -> Result<serde_json::Value, JobError> {
    let design = Design { fixed: effects_of(&p.effects, &mut vec![]), varied: vec![] };
    let model = Model::new(ModelConfig::default()).internal("the simulator could not be set up")?;
    let theta = with_geometry(&p.theta, 0);
    let out = run_rows(&model, &design, &theta, 0, None);
    let x: Vec<serde_json::Value> = out
        .iter()
        .map(|res| match res {
            Ok(x) => serde_json::json!(x),
            Err(e) => serde_json::json!({ "error": e.to_string() }),
        })
        .collect();
    // A row the simulator refused is in `x` as its error; the job says how many.
    let failed = out.iter().filter(|o| o.is_err()).count();
    r.report(1.0, format!("{} rows, {failed} failed", p.theta.len()));
    let ok: Vec<&[f64]> = out.iter().filter_map(|o| o.as_deref().ok()).collect();
    let page = crate::plot::resimulation(model.frequencies(), &theta, &ok, p.observation.as_deref());
    r.still_ours(ctx)?;
    let dir = ctx.data_dir.join("reports").join(id);
    let written = std::fs::create_dir_all(&dir)
        .and_then(|()| std::fs::write(dir.join("spectra.svg"), &page.svg))
        .and_then(|()| std::fs::write(dir.join("report.html"), &page.html));
    written.with_context(|| format!("writing {}", dir.display())).internal("the report could not be written")?;
    let files = |n: &str| format!("/jobs/{id}/files/{n}");
    Ok(serde_json::json!({
        "features": feature_names(model.frequencies()),
        "x": x,
        "failed_rows": failed,
        "rho": page.rho,
        "figures": [files("spectra.svg")],
        "report": files("report.html"),
    }))
}
