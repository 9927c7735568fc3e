//! POST /infer: measurements as devices export them (own frequency grids, magnitude and
//! phase or absorbance) → interpolated in log-frequency onto the model grid → posterior.

use super::{AppState, Problem, json_body};
use crate::npe::{Npe, Obs};
use axum::Json;
use axum::body::Bytes;
use axum::extract::State;
use axum::http::{HeaderMap, StatusCode};
use serde::Deserialize;
use serde_json::json;
use std::sync::Arc;

pub const MAX_SAMPLES: usize = 20_000;

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
pub struct InferRequest {
    pub model: Option<String>,
    pub measurements: Measurements,
    pub samples: Option<usize>,
    pub seed: Option<u64>,
    pub return_samples: Option<bool>,
}

pub use crate::measurements::Measurements;
use crate::measurements::{MeasurementError, bands_used};

/// The feature vector of a request's measurements, errors as problems naming the field.
fn features(npe: &Npe, m: &Measurements) -> Result<crate::measurements::Features, Problem> {
    crate::measurements::features(npe, m).map_err(|e| match e {
        MeasurementError::NotOtofitModel => Problem::new(StatusCode::CONFLICT, e.to_string()),
        MeasurementError::Invalid(errs) => Problem::invalid(errs),
    })
}

pub async fn infer(
    State(st): State<AppState>,
    headers: HeaderMap,
    body: Bytes,
) -> Result<Json<serde_json::Value>, Problem> {
    let t0 = std::time::Instant::now();
    let req: InferRequest = json_body(&headers, &body)?;
    let n = req.samples.unwrap_or(1000);
    if n == 0 || n > MAX_SAMPLES {
        return Err(Problem::invalid(vec![("samples".into(), format!("must be 1..={MAX_SAMPLES}"))]));
    }
    let row = match &req.model {
        Some(id) => st
            .ctx
            .store
            .model(id)
            .await
            .map_err(Problem::internal)?
            .ok_or_else(|| Problem::invalid(vec![("model".into(), format!("no model '{id}'"))]))?,
        None => st
            .ctx
            .store
            .default_model()
            .await
            .map_err(Problem::internal)?
            .ok_or_else(|| Problem::new(StatusCode::SERVICE_UNAVAILABLE, "no default model is registered"))?,
    };
    let ctx = st.ctx.clone();
    let (id, path) = (row.id.clone(), row.path.clone());
    let npe: Arc<Npe> = tokio::task::spawn_blocking(move || ctx.loaded(&id, std::path::Path::new(&path)))
        .await
        .map_err(Problem::internal)?
        .map_err(|e| {
            Problem::new(StatusCode::SERVICE_UNAVAILABLE, format!("model '{}' cannot be loaded: {e:#}", row.id))
        })?;
    let (x, present, used) = features(&npe, &req.measurements)?;
    let band_hz = bands_used(&npe, &present);
    let seed = req.seed.unwrap_or(0);
    let npe2 = npe.clone();
    let (inf, fit) = tokio::task::spawn_blocking(move || {
        let inf = npe2.infer(&Obs { x: &x, present: Some(&present) }, n, seed)?;
        let fit = crate::discrepancy::fitcheck::fit_check(&npe2, &x, &present, &inf);
        anyhow::Ok((inf, fit.map(|f| (f, x))))
    })
    .await
    .map_err(Problem::internal)?
    .map_err(|e| Problem::invalid(vec![("measurements".into(), format!("{e:#}"))]))?;
    tracing::info!(model = %row.id, samples = n, inputs = used.len(), ms = t0.elapsed().as_secs_f64() * 1e3, "inferred");
    let mut differential = crate::npe::normal::read(npe.params(), &inf.samples);
    let mut next = serde_json::Value::Null;
    let fit = match fit {
        Ok((f, x)) => {
            if f.ok == Some(false) {
                let why = f.reason.clone().unwrap_or_default();
                crate::npe::normal::withdraw(&mut differential, &why);
                let mut params = json!({ "x": x });
                if let Some(m) = &req.model {
                    params["model"] = json!(m);
                }
                next = json!({ "why": "look for the physical effect the model is missing", "method": "POST", "path": "/jobs" });
                if x.iter().all(|v| v.is_finite()) {
                    next["body"] = json!({ "kind": "diagnose", "params": params });
                }
            }
            json!(f)
        }
        Err(e) => json!({ "ok": null, "reason": e.to_string() }),
    };
    // The measurement-geometry nuisances are reported apart from the tissue parameters:
    // they describe the probe's placement, not the ear, and have no normal range.
    let (geometry, tissue): (Vec<_>, Vec<_>) =
        inf.summaries.iter().partition(|s| crate::sim::params::is_geometry(&s.name));
    let mut doc = json!({
        "model": row.id,
        "fit": fit,
        "parameters": tissue,
        "differential": differential,
        "differential_note": "per parameter: the posterior probability below / within / above the normal range; a reading only where the posterior is informative and puts ≥ 0.8 within or ≥ 0.95 below or above, else undetermined; unreliable for every parameter when the fit check fails. Information, not a diagnosis",
        "map": inf.map,
        "inputs": {
            "used": used,
            "interpolated": true,
            "note": "each measure was interpolated linearly in log-frequency onto the model grid (magnitudes as log10, phases unwrapped)",
            "grid_hz": npe.header.frequencies_hz,
            "band_hz": band_hz,
        },
        "samples_count": n,
        "seed": seed,
        "timing_ms": { "sample": inf.sample_ms, "map": inf.map_ms, "total": t0.elapsed().as_secs_f64() * 1e3 },
    });
    if !next.is_null() {
        doc["next"] = next;
    }
    if !geometry.is_empty() {
        doc["geometry"] = json!(geometry);
        doc["geometry_note"] = json!(
            "measurement geometry inferred with the tissue (path from the impedance plane to the eardrum, canal \
             cross-section, V/P microphone distance): nuisances that keep the tissue posterior unbiased, not findings"
        );
    }
    if req.return_samples.unwrap_or(true) {
        doc["samples"] = json!(inf.samples);
        doc["sample_columns"] = json!(npe.params().iter().map(|p| &p.name).collect::<Vec<_>>());
    }
    Ok(Json(doc))
}
