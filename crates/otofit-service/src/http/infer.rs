//! POST /infer: measurements as devices export them (own frequency grids, magnitude and
//! phase or absorbance) → interpolated in log-frequency onto the model grid → posterior.
//! The body is JSON (`InferRequest`) or a long-layout CSV table (`text/csv`, one row per
//! frequency, [`crate::formats::long`]) with the request's options as query parameters.

use super::{AppState, Problem, json_body};
use crate::discrepancy::alternatives::{self, Alternatives, AlternativesParams};
use crate::discrepancy::exact_fast::{self, FastExact};
use crate::discrepancy::fitcheck::{FitCheck, FitCheckError, MAX_REFINE_STEPS, Refined};
use crate::npe::normal::{Differential, Verdict};
use crate::npe::{Inference, Npe, NpeError, Obs, Summary};
use axum::Json;
use axum::body::Bytes;
use axum::extract::{Query, State};
use axum::http::{HeaderMap, StatusCode};
use serde::{Deserialize, Serialize};
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
    /// A figure in the response: `corner` (the posterior's corner plot, SVG).
    pub plot: Option<Plot>,
    /// Levenberg–Marquardt steps of a least-squares best fit from the MAP (0: none).
    pub refine: Option<usize>,
    /// `flow` (the default): the flow's posterior alone; `exact`: also the likelihood's
    /// posterior, sampled within the request (`discrepancy::exact_fast`), under `exact`.
    pub posterior: Option<PosteriorKind>,
}

/// Which posterior POST /infer answers with.
#[derive(Clone, Copy, Debug, Default, Deserialize, PartialEq, Eq)]
#[serde(rename_all = "lowercase")]
pub enum PosteriorKind {
    /// The flow's (amortized, calibrated, wider than the likelihood's).
    #[default]
    Flow,
    /// The flow's and, under `exact`, the likelihood's own from short chains started at
    /// the flow's draws, with their diagnostics.
    Exact,
}

impl std::str::FromStr for PosteriorKind {
    type Err = String;
    fn from_str(s: &str) -> Result<Self, String> {
        match s {
            "flow" => Ok(PosteriorKind::Flow),
            "exact" => Ok(PosteriorKind::Exact),
            _ => Err(format!("'{s}' is not a posterior (known: flow, exact)")),
        }
    }
}

/// Figures POST /infer can draw into its response.
#[derive(Clone, Copy, Debug, Deserialize, PartialEq, Eq)]
#[serde(rename_all = "lowercase")]
pub enum Plot {
    /// Pairwise histograms and marginals over the prior box, MAP marked, ticks in units.
    Corner,
}

impl std::str::FromStr for Plot {
    type Err = String;
    fn from_str(s: &str) -> Result<Self, String> {
        match s {
            "corner" => Ok(Plot::Corner),
            _ => Err(format!("'{s}' is not a figure (known: corner)")),
        }
    }
}

use crate::formats::Imported;
pub use crate::measurements::Measurements;
use crate::measurements::{MeasurementError, bands_used};

/// The feature vector of a request's measurements, errors as problems naming the field
/// (for a CSV body, the column it came from).
pub(super) fn features(
    npe: &Npe,
    m: &Measurements,
    csv: Option<&Imported>,
) -> Result<crate::measurements::Features, Problem> {
    crate::measurements::features(npe, m).map_err(|e| {
        let insufficient = e.insufficient_data();
        let mut p = match e {
            MeasurementError::NotOtofitModel => Problem::new(StatusCode::CONFLICT, e.to_string()),
            MeasurementError::Invalid(errs) => match csv {
                Some(imp) => Problem::invalid(errs.iter().map(|(f, m)| imp.column_of(f, m)).collect()),
                None => Problem::invalid(errs),
            },
        };
        if insufficient {
            p.code = Some("insufficient_data");
            p.detail = "too few measured points to read this ear: nothing is inferred from them".into();
        }
        p
    })
}

/// An inference error as a problem: what the observation lacks for this model is a 422
/// on `measurements` (the message names the feature or group); anything else is a bug,
/// logged and answered 500.
pub(super) fn npe_problem(e: NpeError) -> Problem {
    match e {
        NpeError::Observation(o) => Problem::invalid(vec![("measurements".into(), o.to_string())]),
        e => Problem::internal(e),
    }
}

/// The request of a JSON body, or of a long-layout CSV body and its query parameters
/// (with what reading the table did).
fn request(
    headers: &HeaderMap,
    query: &[(String, String)],
    body: &[u8],
) -> Result<(InferRequest, Option<Imported>), Problem> {
    let ct = headers.get(axum::http::header::CONTENT_TYPE).and_then(|v| v.to_str().ok()).unwrap_or("");
    let media = ct.split(';').next().unwrap_or("").trim();
    if media.eq_ignore_ascii_case("text/csv") {
        return csv_request(query, body);
    }
    // `plot` asks for a figure, whatever the body; every other option is the body's.
    let mut plot = None;
    for (k, v) in query {
        if k != "plot" {
            return Err(Problem::invalid(vec![(
                k.clone(),
                "query parameters other than plot apply to text/csv bodies; with JSON, put it in the body".into(),
            )]));
        }
        plot = Some(v.parse().map_err(|m| Problem::invalid(vec![("plot".into(), m)]))?);
    }
    let mut req: InferRequest = json_body(headers, body).map_err(|mut p| {
        if p.status == StatusCode::UNSUPPORTED_MEDIA_TYPE.as_u16() {
            p.detail = "send Content-Type: application/json (InferRequest) or text/csv (a long-layout table)".into();
        }
        p
    })?;
    req.plot = plot.or(req.plot);
    Ok((req, None))
}

/// A `text/csv` body: the table's measurements, the rest of the request from the query
/// (`model`, `samples`, `seed`, `return_samples`, `unit=COLUMN=UNIT`,
/// `select=COLUMN=VALUE`, `preset`, `plot`, `refine`, `posterior`).
fn csv_request(query: &[(String, String)], body: &[u8]) -> Result<(InferRequest, Option<Imported>), Problem> {
    use crate::formats::long::{self, LongOptions};
    let mut req = InferRequest {
        model: None,
        measurements: Measurements::default(),
        samples: None,
        seed: None,
        return_samples: None,
        plot: None,
        refine: None,
        posterior: None,
    };
    let mut opts = LongOptions::default();
    let bad = |k: &str, m: String| Problem::invalid(vec![(k.to_string(), m)]);
    for (k, v) in query {
        match k.as_str() {
            "model" => req.model = Some(v.clone()),
            "samples" => req.samples = Some(v.parse().map_err(|_| bad(k, format!("'{v}' is not a count")))?),
            "seed" => req.seed = Some(v.parse().map_err(|_| bad(k, format!("'{v}' is not a seed (0..2^64)")))?),
            "return_samples" => {
                req.return_samples = Some(v.parse().map_err(|_| bad(k, format!("'{v}' is not true or false")))?)
            }
            "unit" => opts.units.push(long::pair(v, "unit").map_err(|m| bad(k, m))?),
            "select" => opts.select.push(long::pair(v, "select").map_err(|m| bad(k, m))?),
            "preset" => opts.preset = Some(v.parse().map_err(|m| bad(k, m))?),
            "plot" => req.plot = Some(v.parse().map_err(|m| bad(k, m))?),
            "refine" => req.refine = Some(v.parse().map_err(|_| bad(k, format!("'{v}' is not a count of steps")))?),
            "posterior" => req.posterior = Some(v.parse().map_err(|m| bad(k, m))?),
            _ => {
                return Err(bad(
                    k,
                    "unknown query parameter (known: model, samples, seed, return_samples, unit, select, preset, \
                     plot, refine, posterior)"
                        .into(),
                ));
            }
        }
    }
    let text = std::str::from_utf8(body)
        .map_err(|e| Problem::new(StatusCode::BAD_REQUEST, format!("the CSV body is not UTF-8: {e}")))?;
    let mut imp = long::read(text, &opts).map_err(|e| bad(&e.field(), e.message()))?;
    req.measurements = std::mem::take(&mut imp.measurements);
    Ok((req, Some(imp)))
}

/// The model a request names (one its tenant may see) or the default model, loaded off the
/// runtime threads. An id that names no model the client may see is a 404 naming the
/// field, as GET /models/{id} and a job's `params.model` answer.
pub(super) async fn model_for(
    st: &AppState,
    who: &super::Principal,
    model: Option<&str>,
) -> Result<(crate::store::ModelRow, Arc<Npe>), Problem> {
    let row = match model {
        Some(id) => super::resources::visible_model(st, who, id)
            .await?
            .ok_or_else(|| super::field_problem(StatusCode::NOT_FOUND, "model", format!("no model '{id}'")))?,
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
            // The cause names a server path: logged, not answered.
            tracing::error!(model = %row.id, error = %format!("{e:#}"), "model cannot be loaded");
            Problem::new(StatusCode::SERVICE_UNAVAILABLE, format!("model '{}' cannot be loaded (logged)", row.id))
        })?;
    Ok((row, npe))
}

/// POST /infer: the posterior of one ear's measurements, with its fit check, the
/// differential reading, and the next step when the fit fails.
pub async fn infer(
    State(st): State<AppState>,
    axum::Extension(who): axum::Extension<super::Principal>,
    Query(query): Query<Vec<(String, String)>>,
    headers: HeaderMap,
    body: Bytes,
) -> Result<Json<InferResponse>, Problem> {
    let t0 = std::time::Instant::now();
    let (req, csv) = request(&headers, &query, &body)?;
    let n = req.samples.unwrap_or(1000);
    if n == 0 || n > MAX_SAMPLES {
        return Err(Problem::invalid(vec![("samples".into(), format!("must be 1..={MAX_SAMPLES}"))]));
    }
    let refine = req.refine.unwrap_or(0);
    if refine > MAX_REFINE_STEPS {
        return Err(Problem::invalid(vec![("refine".into(), format!("must be 0..={MAX_REFINE_STEPS} steps"))]));
    }
    let (row, npe) = model_for(&st, &who, req.model.as_deref()).await?;
    let (x, present, used) = features(&npe, &req.measurements, csv.as_ref())?;
    let band_hz = bands_used(&npe, &present);
    // Which of the model's flows answers: its full-measure flow for an ear with every
    // measure over the whole band, a measure-set flow for an ear of exactly its groups,
    // when the model holds one.
    let flow = npe.answering_name(&Obs { x: &x, present: Some(&present) });
    let seed = req.seed.unwrap_or(0);
    let npe2 = npe.clone();
    let (plot, title) = (req.plot, format!("Posterior, model {}", row.id));
    let exact = (req.posterior == Some(PosteriorKind::Exact))
        .then(|| t0 + exact_fast::BUDGET.min(st.ctx.infer_gate.limits.deadline.mul_f64(0.8)));
    // Sampling, MAP and the fit check are CPU work: off the runtime threads.
    let answer =
        tokio::task::spawn_blocking(move || posterior(&npe2, x, present, (n, seed, refine), plot, &title, exact))
            .await
            .map_err(Problem::internal)?
            .map_err(npe_problem)?;
    tracing::info!(model = %row.id, samples = n, inputs = used.len(), ms = t0.elapsed().as_secs_f64() * 1e3, "inferred");
    let Answer { inf, fit, fit_ms, corner, refined, mut differential, alternatives, exact } = answer;
    let (fit, next) = fit_and_next(fit, req.model.as_deref(), &mut differential);
    // Read against the normal ranges, which every flow of a model shares.
    let exact = exact.map(|e| exact_doc(e, &npe, &fit));
    let verdict = crate::npe::normal::verdict(&differential, fit["ok"].as_bool());
    // The measurement-geometry nuisances are reported apart from the tissue parameters:
    // they describe the probe's placement, not the ear, and have no normal range.
    let (geometry, tissue): (Vec<_>, Vec<_>) =
        inf.summaries.into_iter().partition(|s| crate::sim::params::is_geometry(&s.name));
    let timing_ms = Timing {
        sample: inf.sample_ms,
        map: inf.map_ms,
        fit: fit_ms,
        alternatives: alternatives.as_ref().map_or(0.0, |a| a.ms),
        exact: exact.as_ref().map_or(0.0, |e| e["ms"].as_f64().unwrap_or(0.0)),
        total: t0.elapsed().as_secs_f64() * 1e3,
    };
    let samples = req.return_samples.unwrap_or(true).then_some(inf.samples);
    Ok(Json(InferResponse {
        verdict,
        model: row.id,
        fit,
        parameters: tissue,
        differential,
        differential_note: DIFFERENTIAL_NOTE,
        map: inf.map,
        inputs: Inputs {
            used,
            interpolated: true,
            note: INTERPOLATION_NOTE,
            grid_hz: npe.header.frequencies_hz.clone(),
            band_hz,
            format: if csv.is_some() { "csv" } else { "json" },
            flow,
            notes: csv.map(|imp| imp.notes),
        },
        samples_count: n,
        seed,
        timing_ms,
        exact,
        alternatives,
        next,
        refined: refined.map(|r| r.map_or_else(|e| RefinedDoc::Failed { reason: e.to_string() }, RefinedDoc::Fit)),
        geometry_note: (!geometry.is_empty()).then_some(GEOMETRY_NOTE),
        geometry,
        figures: corner.map(|svg| Figures { corner: Figure { media_type: "image/svg+xml", svg } }),
        sample_columns: samples.is_some().then(|| npe.params().iter().map(|p| p.name.clone()).collect()),
        samples,
    }))
}

/// The response's `differential_note`.
const DIFFERENTIAL_NOTE: &str = "per parameter: the posterior probability below / within / above the normal range; a reading only where the posterior is informative and puts ≥ 0.8 within or ≥ 0.95 below or above, else undetermined; unreliable for every parameter when the fit check fails. Information, not a diagnosis";
/// The response's `inputs.note`.
const INTERPOLATION_NOTE: &str = "each measure was interpolated linearly in log-frequency onto the model grid (magnitudes as log10, phases unwrapped)";
/// The response's `geometry_note`.
const GEOMETRY_NOTE: &str = "measurement geometry inferred with the tissue (path from the impedance plane to the eardrum, canal \
     cross-section, V/P microphone distance): nuisances that keep the tissue posterior unbiased, not findings";

/// The answer of POST /infer: openapi.yaml's InferResponse. The optional parts are
/// left out, not null, when absent.
#[derive(Serialize)]
pub struct InferResponse {
    /// The answer in one line.
    pub verdict: Verdict,
    /// The model's id.
    pub model: String,
    /// The fit check, or `ok` null and why it could not run.
    pub fit: serde_json::Value,
    /// Posterior summaries of the tissue parameters.
    pub parameters: Vec<Summary>,
    /// The normal-range reading of each tissue parameter.
    pub differential: Vec<Differential>,
    pub differential_note: &'static str,
    /// The MAP, natural units, in the model's parameter order.
    pub map: Vec<f64>,
    /// What the measurements gave and how they were read.
    pub inputs: Inputs,
    pub samples_count: usize,
    pub seed: u64,
    pub timing_ms: Timing,
    /// The likelihood's posterior (`posterior: exact`).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub exact: Option<serde_json::Value>,
    /// The competing explanations of the findings.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub alternatives: Option<Alternatives>,
    /// The job to post when the fit check fails.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub next: Option<NextStep>,
    /// The least-squares best fit from the MAP (`refine` > 0).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub refined: Option<RefinedDoc>,
    /// Posterior summaries of the measurement-geometry nuisances (models that have them).
    #[serde(skip_serializing_if = "Vec::is_empty")]
    pub geometry: Vec<Summary>,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub geometry_note: Option<&'static str>,
    /// The figures `plot` asked for.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub figures: Option<Figures>,
    /// The posterior draws, natural units (`return_samples`, the default).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub samples: Option<Vec<Vec<f64>>>,
    /// The parameter of each column of `samples`.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub sample_columns: Option<Vec<String>>,
}

/// The response's `inputs`: the features used and how the measurements were read.
#[derive(Serialize)]
pub struct Inputs {
    /// The feature blocks the measurements gave.
    pub used: Vec<&'static str>,
    pub interpolated: bool,
    pub note: &'static str,
    /// The model's frequency grid, Hz.
    pub grid_hz: Vec<f64>,
    /// Per feature block: the first and last model-grid frequency given.
    pub band_hz: serde_json::Map<String, serde_json::Value>,
    /// The body's format: `json` or `csv`.
    pub format: &'static str,
    /// The flow that answered: `full-measure` (the model's flow for ears with every
    /// measure), `measure-set` (its flow for ears of exactly one set of groups) or `main`.
    pub flow: &'static str,
    /// What reading a text/csv table did.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub notes: Option<Vec<String>>,
}

/// The response's `timing_ms`: each stage's milliseconds.
#[derive(Serialize)]
pub struct Timing {
    pub sample: f64,
    pub map: f64,
    pub fit: f64,
    pub alternatives: f64,
    pub exact: f64,
    pub total: f64,
}

/// The response's `next`: the request to make when the fit check fails.
#[derive(Serialize)]
pub struct NextStep {
    pub why: &'static str,
    pub method: &'static str,
    pub path: &'static str,
    /// The body to post (a diagnose job on these features).
    pub body: serde_json::Value,
}

/// The response's `refined`: the best fit, or why it could not run.
#[derive(Serialize)]
#[serde(untagged)]
pub enum RefinedDoc {
    Fit(Refined),
    Failed { reason: String },
}

/// The response's `figures`.
#[derive(Serialize)]
pub struct Figures {
    pub corner: Figure,
}

/// A figure and its media type.
#[derive(Serialize)]
pub struct Figure {
    pub media_type: &'static str,
    pub svg: String,
}

/// What the blocking part of POST /infer computes.
struct Answer {
    inf: Inference,
    /// The fit check and the features it was run on, or why it could not run.
    fit: Result<(FitCheck, Vec<f64>), FitCheckError>,
    fit_ms: f64,
    /// The corner plot (SVG), when asked for.
    corner: Option<String>,
    /// The least-squares best fit from the MAP, when asked for.
    refined: Option<Result<Refined, FitCheckError>>,
    /// The normal-range differential of the samples (before a failed fit withdraws it).
    differential: Vec<crate::npe::normal::Differential>,
    /// The competing explanations of its findings, when the fit check passed and there
    /// is a finding.
    alternatives: Option<Alternatives>,
    /// The likelihood's posterior, when asked for (or why it could not run).
    exact: Option<Result<FastExact, FitCheckError>>,
}

/// The posterior of features `x` (`present` marks those measured) from `n` samples of
/// `seed`, its fit check (timed apart), with `refine` > 0 the best fit from its MAP and,
/// with `plot`, its corner plot; the differential and, for a passed fit check with
/// findings, their alternatives; with an `exact` deadline, the likelihood's posterior
/// from short chains stopped by it.
fn posterior(
    npe: &Npe,
    x: Vec<f64>,
    present: Vec<bool>,
    (n, seed, refine): (usize, u64, usize),
    plot: Option<Plot>,
    title: &str,
    exact: Option<std::time::Instant>,
) -> Result<Answer, NpeError> {
    let npe = npe.answering(&Obs { x: &x, present: Some(&present) });
    let inf = npe.infer(&Obs { x: &x, present: Some(&present) }, n, seed)?;
    let refined = (refine > 0).then(|| crate::discrepancy::fitcheck::refine(npe, &x, &present, &inf.map, refine));
    let t = std::time::Instant::now();
    let fit = crate::discrepancy::fitcheck::fit_check(npe, &x, &present, &inf);
    let fit_ms = t.elapsed().as_secs_f64() * 1e3;
    let corner = (plot == Some(Plot::Corner))
        .then(|| crate::plot::posterior_corner(npe.params(), &inf.samples, None, &inf.map, title));
    let differential = crate::npe::normal::read(npe.params(), &inf.samples);
    let fit_ok = fit.as_ref().ok().and_then(|f| f.ok);
    let alternatives = alternatives::alternatives(
        npe,
        &x,
        &present,
        (&inf.map, &inf.samples),
        &differential,
        fit_ok,
        &AlternativesParams::default(),
    );
    let exact = exact.map(|deadline| {
        let settings = exact_fast::Settings { seed, ..Default::default() };
        exact_fast::sample(npe, &x, &present, &inf, &settings, deadline)
    });
    Ok(Answer { inf, fit: fit.map(|f| (f, x)), fit_ms, corner, refined, differential, alternatives, exact })
}

/// The response's `exact`: the chains' summaries (tissue and geometry apart, as the
/// flow's), their diagnostics, and their normal-range reading, withdrawn when the fit
/// check failed (then `exact` is false: the likelihood is that of a model that does not
/// describe the ear) or when the diagnostics failed.
fn exact_doc(e: Result<FastExact, FitCheckError>, npe: &Npe, fit: &serde_json::Value) -> serde_json::Value {
    let mut e = match e {
        Ok(e) => e,
        Err(err) => return json!({ "exact": false, "reason": err.to_string(), "ms": 0.0 }),
    };
    if fit["ok"].as_bool() == Some(false) {
        e.withdraw(fit["reason"].as_str().unwrap_or("the model does not fit these measurements"));
    }
    let reading = e.reading(npe);
    let (geometry, tissue): (Vec<_>, Vec<_>) =
        e.summaries.iter().partition(|s| crate::sim::params::is_geometry(&s.name));
    let mut doc = json!(e);
    doc["parameters"] = json!(tissue);
    doc["geometry"] = json!(geometry);
    doc.as_object_mut().map(|o| o.remove("summaries"));
    doc["differential"] = json!(reading);
    doc["note"] = json!(exact_fast::NOTE);
    doc
}

/// The response's `fit` and, when the fit check fails, its `next` step (a diagnose job
/// on these features, for the model the request named); a failed fit withdraws every
/// reading of the differential.
fn fit_and_next(
    fit: Result<(FitCheck, Vec<f64>), FitCheckError>,
    model: Option<&str>,
    differential: &mut [crate::npe::normal::Differential],
) -> (serde_json::Value, Option<NextStep>) {
    let mut next = None;
    let fit = match fit {
        Ok((f, x)) => {
            if f.ok == Some(false) {
                let why = f.reason.clone().unwrap_or_default();
                crate::npe::normal::withdraw(differential, &why);
                // Features not measured are null: the diagnose job leaves them out.
                let mut params = json!({ "x": x });
                if let Some(m) = model {
                    params["model"] = json!(m);
                }
                next = Some(NextStep {
                    why: "look for the physical effect the model is missing",
                    method: "POST",
                    path: "/jobs",
                    body: json!({ "kind": "diagnose", "params": params }),
                });
            }
            json!(f)
        }
        Err(e) => json!({ "ok": null, "reason": e.to_string() }),
    };
    (fit, next)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::npe::ObservationError;

    #[test]
    fn observation_errors_are_422_on_measurements_and_internal_ones_500() {
        let p = npe_problem(NpeError::Observation(ObservationError::Missing { feature: "zec_mag_7".into() }));
        assert_eq!(p.status, 422);
        assert_eq!(p.errors[0].field, "measurements");
        assert!(p.errors[0].message.contains("zec_mag_7"), "{}", p.errors[0].message);
        let p = npe_problem(NpeError::NoFiniteLoss { member: 0 });
        assert_eq!(p.status, 500);
        assert!(p.errors.is_empty() && !p.detail.contains("finite"), "{}", p.detail);
    }
}
