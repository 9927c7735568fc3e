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

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Measurements {
    /// |V_stapes/P_ec| in m/s/Pa and its phase in rad.
    pub stapes_velocity: Option<MagPhase>,
    /// Ear-canal impedance |Z| in Pa·s/m³ and its phase in rad.
    pub impedance: Option<MagPhase>,
    pub absorbance: Option<Values>,
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
pub struct MagPhase {
    pub frequencies_hz: Vec<f64>,
    pub magnitude: Vec<f64>,
    pub phase: Vec<f64>,
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Values {
    pub frequencies_hz: Vec<f64>,
    pub values: Vec<f64>,
}

/// Checks one measured curve and interpolates it in log-frequency onto `grid`.
fn resample(field: &str, f: &[f64], v: &[f64], grid: &[f64], errs: &mut Vec<(String, String)>) -> Option<Vec<f64>> {
    let before = errs.len();
    if f.len() < 2 {
        errs.push((format!("{field}.frequencies_hz"), "needs at least 2 points".into()));
    }
    if v.len() != f.len() {
        errs.push((field.to_string(), format!("has {} values for {} frequencies", v.len(), f.len())));
    }
    if let Some(i) = f.iter().position(|x| !x.is_finite() || *x <= 0.0) {
        errs.push((format!("{field}.frequencies_hz[{i}]"), "must be a finite frequency > 0".into()));
    } else if let Some(i) = (1..f.len()).find(|&i| f[i] <= f[i - 1]) {
        errs.push((format!("{field}.frequencies_hz[{i}]"), "frequencies must increase strictly".into()));
    }
    if errs.len() > before {
        return None;
    }
    if f[0] > grid[0] * 1.005 || f[f.len() - 1] < grid[grid.len() - 1] * 0.995 {
        errs.push((
            format!("{field}.frequencies_hz"),
            format!(
                "must cover the model band {:.0}–{:.0} Hz (got {:.0}–{:.0})",
                grid[0],
                grid[grid.len() - 1],
                f[0],
                f[f.len() - 1]
            ),
        ));
        return None;
    }
    Some(crate::sim::output::interpolate_log_f(f, v, grid))
}

fn check_values(field: &str, v: &[f64], positive: bool, errs: &mut Vec<(String, String)>) {
    if let Some(i) = v.iter().position(|x| !x.is_finite() || (positive && *x <= 0.0)) {
        errs.push((
            format!("{field}[{i}]"),
            if positive { "must be a finite number > 0".into() } else { "must be a finite number".into() },
        ));
    }
}

/// The model's feature vector and presence flags from the measurements.
fn features(npe: &Npe, m: &Measurements) -> Result<(Vec<f64>, Vec<bool>, Vec<&'static str>), Problem> {
    let grid = &npe.header.frequencies_hz;
    let n = grid.len();
    let mut errs = Vec::new();
    if n == 0 || npe.header.feature_names.len() != 5 * n {
        return Err(Problem::new(
            StatusCode::CONFLICT,
            "this model was not trained on otofit's five measures; use the CLI with a feature table",
        ));
    }
    let mut x = vec![f64::NAN; 5 * n];
    let mut used = Vec::new();
    let mut magphase =
        |field: &'static str, mp: &MagPhase, block: usize, x: &mut Vec<f64>, errs: &mut Vec<(String, String)>| {
            check_values(&format!("measurements.{field}.magnitude"), &mp.magnitude, true, errs);
            check_values(&format!("measurements.{field}.phase"), &mp.phase, false, errs);
            let logmag: Vec<f64> = mp.magnitude.iter().map(|v| v.log10()).collect();
            let phase = crate::sim::output::unwrap(mp.phase.iter().copied());
            let fld = format!("measurements.{field}");
            if let (Some(a), Some(b)) = (
                resample(&fld, &mp.frequencies_hz, &logmag, grid, errs),
                resample(&fld, &mp.frequencies_hz, &phase, grid, errs),
            ) {
                x[block * n..(block + 1) * n].copy_from_slice(&a);
                x[(block + 1) * n..(block + 2) * n].copy_from_slice(&b);
                used.push(field);
            }
        };
    if let Some(mp) = &m.stapes_velocity {
        magphase("stapes_velocity", mp, 0, &mut x, &mut errs);
    }
    if let Some(mp) = &m.impedance {
        magphase("impedance", mp, 2, &mut x, &mut errs);
    }
    if let Some(a) = &m.absorbance {
        check_values("measurements.absorbance.values", &a.values, false, &mut errs);
        if let Some(i) = a.values.iter().position(|v| !(-0.5..=1.5).contains(v)) {
            errs.push((format!("measurements.absorbance.values[{i}]"), "absorbance must lie near 0–1".into()));
        }
        if let Some(v) = resample("measurements.absorbance", &a.frequencies_hz, &a.values, grid, &mut errs) {
            x[4 * n..].copy_from_slice(&v);
            used.push("absorbance");
        }
    }
    if !errs.is_empty() {
        return Err(Problem::invalid(errs));
    }
    if used.is_empty() {
        return Err(Problem::invalid(vec![(
            "measurements".into(),
            "give at least one of stapes_velocity, impedance, absorbance".into(),
        )]));
    }
    let present: Vec<bool> = x.iter().map(|v| v.is_finite()).collect();
    if !npe.header.mask_groups && present.iter().any(|p| !p) {
        let missing: Vec<&str> =
            ["stapes_velocity", "impedance", "absorbance"].into_iter().filter(|f| !used.contains(f)).collect();
        return Err(Problem::invalid(vec![(
            "measurements".into(),
            format!("this model needs every measure; missing: {}", missing.join(", ")),
        )]));
    }
    Ok((x, present, used))
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
    let seed = req.seed.unwrap_or(0);
    let npe2 = npe.clone();
    let inf = tokio::task::spawn_blocking(move || npe2.infer(&Obs { x: &x, present: Some(&present) }, n, seed))
        .await
        .map_err(Problem::internal)?
        .map_err(|e| Problem::invalid(vec![("measurements".into(), format!("{e:#}"))]))?;
    tracing::info!(model = %row.id, samples = n, inputs = used.len(), ms = t0.elapsed().as_secs_f64() * 1e3, "inferred");
    let names: Vec<&str> = npe.params().iter().map(|p| p.name.as_str()).collect();
    let mut doc = json!({
        "model": row.id,
        "parameters": inf.summaries,
        "differential": crate::npe::normal::read(&names, &inf.samples),
        "differential_note": "posterior probability below / within / above the normal range reported for each parameter, and what a deviation is associated with: information, not a diagnosis",
        "map": inf.map,
        "inputs": {
            "used": used,
            "interpolated": true,
            "note": "each measure was interpolated linearly in log-frequency onto the model grid (magnitudes as log10, phases unwrapped)",
            "grid_hz": npe.header.frequencies_hz,
        },
        "samples_count": n,
        "seed": seed,
        "timing_ms": { "sample": inf.sample_ms, "map": inf.map_ms, "total": t0.elapsed().as_secs_f64() * 1e3 },
    });
    if req.return_samples.unwrap_or(true) {
        doc["samples"] = json!(inf.samples);
        doc["sample_columns"] = json!(npe.params().iter().map(|p| &p.name).collect::<Vec<_>>());
    }
    Ok(Json(doc))
}
