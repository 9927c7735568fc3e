//! `train`: a posterior estimator on a succeeded simulate job's dataset, saved as
//! `models/<job id>.otofit` and registered under the job's id (by `super::run`).
//!
//! The training keeps a checkpoint, `checkpoints/<job id>.ckpt`, across attempts: an
//! attempt that takes the job up again (after a kill, a lost lease, a restart) resumes
//! from it, and the model is the same as an uninterrupted run's. It goes when the job
//! ends (succeeded, cancelled, failed on its last attempt).

use super::spec::{FieldError, in_range, non_negative, plain_id};
use super::{Ctx, JobContext, JobError, LeaseLost, Reporter, Stopped, limits};
use crate::npe::{self, Checkpointing, Dataset, TrainSettings};
use anyhow::Context;
use serde::{Deserialize, Serialize};
use std::path::{Path, PathBuf};
use std::sync::atomic::Ordering;

/// The params of a train job: fit a model to a simulated dataset.
#[derive(Clone, Debug, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct TrainParams {
    /// Id of a succeeded simulate job.
    pub dataset: String,
    /// Multiple of the dataset's 1× noise model added to x during training (default 1).
    #[serde(default = "one")]
    pub noise_scale: f64,
    /// Seed of the initial weights and the batch order.
    #[serde(default)]
    pub seed: u64,
    /// Most epochs to train (default 1000; the default recipe ends sooner).
    #[serde(default = "epochs")]
    pub max_epochs: usize,
    /// Train with group masks so that the model accepts any subset of measure groups.
    #[serde(default)]
    pub mask_groups: bool,
    /// Flows in the ensemble (`limits::ENSEMBLE`); absent: from the table's size, as
    /// `otofit train` (`TrainSettings::members_for`).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub ensemble: Option<usize>,
}
fn one() -> f64 {
    1.0
}
/// Default epochs of a training (train and diagnose jobs).
pub(super) fn epochs() -> usize {
    1000
}

impl TrainParams {
    pub(super) fn validate(&self, errs: &mut Vec<FieldError>) {
        plain_id("params.dataset", &self.dataset, errs);
        in_range("params.max_epochs", &limits::EPOCHS, self.max_epochs, errs);
        non_negative("params.noise_scale", self.noise_scale, errs);
        if let Some(k) = self.ensemble {
            in_range("params.ensemble", &limits::ENSEMBLE, k, errs);
        }
    }
}

/// The folder of the train jobs' checkpoints in the data directory.
const CHECKPOINTS: &str = "checkpoints";

/// The checkpoint of train job `id`.
fn checkpoint_path(data_dir: &Path, id: &str) -> PathBuf {
    data_dir.join(CHECKPOINTS).join(format!("{id}.ckpt"))
}

pub(super) fn execute(ctx: &Ctx, id: &str, p: &TrainParams, r: &Reporter) -> Result<serde_json::Value, JobError> {
    let rt = tokio::runtime::Handle::current();
    let removed = remove_ended_checkpoints(ctx);
    if removed > 0 {
        tracing::info!(files = removed, "removed checkpoints of train jobs that ended");
    }
    let res = train(ctx, id, p, r);
    // A failure on the last attempt ends the job: its checkpoint goes. Stopped (shutdown)
    // or taken over (lease lost): the job runs again and resumes from it.
    if let Err(e) = &res
        && !(e.is::<Stopped>() || e.is::<LeaseLost>())
        && rt.block_on(ctx.store.job(id)).ok().flatten().is_some_and(|j| j.attempts >= j.max_attempts)
    {
        npe::remove_checkpoint(&checkpoint_path(&ctx.data_dir, id));
    }
    res
}

fn train(ctx: &Ctx, id: &str, p: &TrainParams, r: &Reporter) -> Result<serde_json::Value, JobError> {
    let dir = ctx.dataset_dir(&p.dataset);
    let subject = format!("dataset '{}'", p.dataset);
    let ds = Dataset::load(&dir).map_err(|e| JobError::npe(e, &subject, format!("{subject} could not be read")))?;
    let s = TrainSettings {
        noise_scale: p.noise_scale,
        seed: p.seed,
        max_epochs: p.max_epochs,
        mask_groups: p.mask_groups,
        ensemble: p.ensemble.unwrap_or(0),
        ..TrainSettings::default()
    };
    // At least every 30 s: the most training time a killed job loses.
    let checkpoint = Checkpointing::new(checkpoint_path(&ctx.data_dir, id), &r.claim.1[..r.claim.1.len().min(16)]);
    let folder = ctx.data_dir.join(CHECKPOINTS);
    std::fs::create_dir_all(&folder)
        .with_context(|| format!("creating {}", folder.display()))
        .internal("the checkpoint folder could not be created")?;
    // Progress: the epochs done over every member's epoch budget (each may stop early, so
    // this is a lower bound). The members may train side by side, their reports
    // interleaved: each report is one epoch more, on top of the checkpoint's.
    let max = (s.max_epochs * s.members_for_table(ds.theta.len())) as f64;
    let mut done = npe::checkpoint_epochs(&checkpoint.path).unwrap_or(0);
    let trained = npe::train_checkpointed(&ds, &s, Some(&checkpoint), &mut |e| {
        done += 1;
        r.report(
            (done as f64 / max).min(1.0),
            format!("member {} epoch {} val loss {:.4}", e.member, e.epoch, e.val_loss),
        )
    })
    .map_err(|e| JobError::npe(e, &subject, format!("training on {subject} failed")))?;
    if trained.resumed_from_epoch > 0 {
        tracing::info!(job = %id, epochs = trained.resumed_from_epoch, "training resumed from its checkpoint");
    }
    if ctx.shutdown.load(Ordering::Relaxed) {
        return Err(Stopped.into());
    }
    r.still_ours(ctx)?;
    let models = ctx.data_dir.join("models");
    std::fs::create_dir_all(&models)
        .with_context(|| format!("creating {}", models.display()))
        .internal("the models folder could not be created")?;
    let model = trained.model;
    model.save(&models.join(format!("{id}.otofit"))).internal("the trained model could not be saved")?;
    // The model is written: the job ends now (succeeded), its checkpoint is garbage.
    npe::remove_checkpoint(&checkpoint.path);
    Ok(serde_json::json!({
        "model": format!("/models/{id}"),
        "epochs": model.header.training.epochs,
        "best_val_loss": model.header.training.best_val_loss,
        "cancelled_early": r.cancel.load(Ordering::Relaxed),
        "resumed_from_epoch": trained.resumed_from_epoch,
    }))
}

/// Removes the checkpoints (and their temporary files) of train jobs that are no longer
/// queued or running: those whose worker died on the job's last attempt, or that were
/// ended by hand. Returns how many files went.
fn remove_ended_checkpoints(ctx: &Ctx) -> usize {
    let rt = tokio::runtime::Handle::current();
    let dir = ctx.data_dir.join(CHECKPOINTS);
    let mut ids: Vec<String> = std::fs::read_dir(&dir)
        .into_iter()
        .flatten()
        .flatten()
        .filter_map(|e| e.file_name().to_string_lossy().split_once(".ckpt").map(|(id, _)| id.to_string()))
        .collect();
    ids.sort();
    ids.dedup();
    ids.iter()
        .filter(|id| match rt.block_on(ctx.store.job(id)) {
            Ok(Some(j)) => !j.state.is_active(),
            Ok(None) => true,
            Err(_) => false,
        })
        .map(|id| npe::remove_checkpoint(&checkpoint_path(&ctx.data_dir, id)))
        .sum()
}
