//! `train`: a posterior estimator on a succeeded simulate job's dataset, saved as
//! `models/<job id>.otofit` and registered under the job's id (by `super::run`).

use super::spec::{FieldError, in_range, non_negative, plain_id};
use super::{Ctx, Reporter, Stopped, limits};
use crate::npe::{self, Dataset, TrainSettings};
use anyhow::{Context, Result, bail};
use serde::{Deserialize, Serialize};
use std::sync::atomic::Ordering;

#[derive(Clone, Debug, Serialize, Deserialize)]
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
    /// Flows in the ensemble (`limits::ENSEMBLE`).
    #[serde(default = "one_member")]
    pub ensemble: usize,
}

fn one_member() -> usize {
    1
}
fn one() -> f64 {
    1.0
}
/// Default epochs of a training (train and diagnose jobs).
pub(super) fn epochs() -> usize {
    300
}

impl TrainParams {
    pub(super) fn validate(&self, errs: &mut Vec<FieldError>) {
        plain_id("params.dataset", &self.dataset, errs);
        in_range("params.max_epochs", &limits::EPOCHS, self.max_epochs, errs);
        non_negative("params.noise_scale", self.noise_scale, errs);
        in_range("params.ensemble", &limits::ENSEMBLE, self.ensemble, errs);
    }
}

pub(super) fn execute(ctx: &Ctx, id: &str, p: &TrainParams, r: &Reporter) -> Result<serde_json::Value> {
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
    model.save(&models.join(format!("{id}.otofit")))?;
    Ok(serde_json::json!({
        "model": format!("/models/{id}"),
        "epochs": model.header.training.epochs,
        "best_val_loss": model.header.training.best_val_loss,
        "cancelled_early": r.cancel.load(Ordering::Relaxed),
    }))
}
