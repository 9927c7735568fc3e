//! `simulate`: prior draws or given rows through the simulator into a dataset folder,
//! `datasets/<job id>/` (written by each attempt into its own staging folder, moved into
//! place after a fresh renewal of its lease).

use super::spec::{FieldError, effects_of, non_negative, theta_values, with_geometry};
use super::{Ctx, Reporter, Stopped, limits};
use crate::dataset::{self, Rows};
use crate::sim::batch::{Design, Noise, default_noise_std};
use crate::sim::params::{Effects, N_PARAMS, N_TISSUE};
use crate::sim::{Model, ModelConfig};
use anyhow::{Context, Result};
use serde::{Deserialize, Serialize};
use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

#[derive(Clone, Debug, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct SimulateParams {
    /// Prior draws (or `theta`).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub n: Option<usize>,
    #[serde(default)]
    pub seed: u64,
    /// Rows in the order of the 10 parameters (or the 7 tissue ones), then the `vary`
    /// effects.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub theta: Option<Vec<Vec<f64>>>,
    #[serde(default)]
    pub effects: BTreeMap<String, f64>,
    #[serde(default)]
    pub vary: Vec<String>,
    #[serde(default)]
    pub noise_scale: f64,
}

impl SimulateParams {
    pub(super) fn validate(&self, errs: &mut Vec<FieldError>) {
        effects_of(&self.effects, errs);
        for (i, v) in self.vary.iter().enumerate() {
            if Effects::index(v).is_none() {
                errs.push((format!("params.vary[{i}]"), format!("unknown effect '{v}'")));
            } else if self.vary[..i].contains(v) {
                errs.push((format!("params.vary[{i}]"), format!("'{v}' is already varied")));
            }
        }
        match (&self.n, &self.theta) {
            (Some(n), None) => super::spec::in_range("params.n", &limits::SIMULATE_ROWS, *n, errs),
            (None, Some(rows)) if !limits::SIMULATE_ROWS.contains(&rows.len()) => {
                errs.push(("params.theta".into(), format!("needs 1..={} rows", limits::SIMULATE_ROWS.end())))
            }
            (None, Some(rows)) => {
                // Full rows, or tissue-only rows that take the nominal other parameters.
                let (w, short) = (N_PARAMS + self.vary.len(), N_TISSUE + self.vary.len());
                if let Some(i) = rows.iter().position(|r| r.len() != w && r.len() != short) {
                    errs.push((
                        format!("params.theta[{i}]"),
                        format!(
                            "needs {w} values (the {N_PARAMS} parameters, then the varied effects) or {short} \
                             (the {N_TISSUE} tissue parameters with nominal geometry, then the varied effects)"
                        ),
                    ));
                } else {
                    theta_values(&with_geometry(rows, self.vary.len()), errs);
                }
            }
            (Some(_), Some(_)) => errs.push(("params".into(), "give either n or theta, not both".into())),
            (None, None) => errs.push(("params.n".into(), "give n (prior draws) or theta (rows)".into())),
        }
        non_negative("params.noise_scale", self.noise_scale, errs);
    }
}

/// Simulates the rows into this attempt's staging folder, then (the lease renewed) moves
/// the files into `datasets/<id>/`.
pub(super) fn execute(ctx: &Ctx, id: &str, p: &SimulateParams, r: &Reporter) -> Result<serde_json::Value> {
    let mut design = Design { fixed: effects_of(&p.effects, &mut vec![]), varied: vec![] };
    design.varied = p.vary.iter().filter_map(|v| Effects::index(v)).collect();
    let model = Model::new(ModelConfig::default())?;
    let noise = Noise { std: default_noise_std(&model), scale: p.noise_scale, seed: p.seed };
    let rows = match &p.theta {
        Some(t) => Rows::Given(with_geometry(t, design.varied.len())),
        None => Rows::Prior { n: p.n.unwrap_or(0), seed: p.seed },
    };
    let dir = ctx.dataset_dir(id);
    let staging = staging_dir(&dir, &r.claim.1);
    let mut last = 0;
    let meta =
        dataset::simulate_to_dir(&model, &design, &rows, &noise, model.config.preset, &staging, &mut |done, n| {
            ctx.metrics.simulated(done.saturating_sub(last) as u64);
            last = done;
            r.report(done as f64 / n as f64, format!("simulated {done}/{n}"))
        })
        .map_err(|e| match e {
            dataset::DatasetError::Cancelled(_) => Stopped.into(),
            e => anyhow::Error::from(e),
        })?;
    r.still_ours(ctx)?;
    publish_dataset(&staging, &dir)?;
    Ok(serde_json::json!({
        "dataset": format!("/datasets/{id}"),
        "rows": meta.n_rows,
        "failed": meta.failed.len(),
        "wall_seconds": meta.wall_seconds,
    }))
}

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
pub(super) fn staging_dir(dir: &Path, token: &str) -> PathBuf {
    dir.join(format!(".attempt-{}", &token[..token.len().min(16)]))
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
