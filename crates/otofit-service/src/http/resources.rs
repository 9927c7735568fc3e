//! Health, models, jobs and datasets.

use super::{AppState, JsonBody, Principal, Problem};
use crate::jobs::{self, JobSpec};
use crate::store::{Admission, JobRow, JobState, QueueBounds};
use axum::extract::{Path, Query, State};
use axum::http::{HeaderValue, StatusCode, header};
use axum::response::{IntoResponse, Response};
use axum::{Extension, Json};
use serde::{Deserialize, Serialize};
use serde_json::json;

pub async fn health() -> Json<serde_json::Value> {
    Json(json!({ "status": "ok", "version": env!("CARGO_PKG_VERSION") }))
}

pub async fn ready(State(st): State<AppState>) -> Response {
    let db = st.ctx.store.ping().await;
    let model = match st.ctx.store.default_model().await {
        Ok(Some(m)) => st.ctx.loaded(&m.id, std::path::Path::new(&m.path)).is_ok(),
        _ => false,
    };
    if db && model {
        return Json(json!({ "ready": true, "database": true, "default_model": true })).into_response();
    }
    let what = |ok: bool| if ok { "ok" } else { "unavailable" };
    let detail = format!("not ready: database {}, default model {}", what(db), what(model));
    let mut p = Problem::new(StatusCode::SERVICE_UNAVAILABLE, detail);
    p.code = Some("not_ready");
    p.into_response()
}

/// Prometheus text format: the job table by kind and state, this process's counters and
/// histograms (see `http::metrics`). A tenant's key sees its own jobs only and none of
/// the process counters, which count every tenant's work; admins and a worker's metrics
/// port (no keys, no principal) see everything.
pub async fn metrics(State(st): State<AppState>, who: Option<Extension<Principal>>) -> Result<Response, Problem> {
    let scope = who.as_ref().and_then(|w| w.scope());
    let queue = st.ctx.store.queue_counts(scope).await.map_err(Problem::internal)?;
    let mut r = st.ctx.metrics.render(&crate::jobs::KINDS, &queue, scope.is_none()).into_response();
    r.headers_mut().insert(header::CONTENT_TYPE, HeaderValue::from_static("text/plain; version=0.0.4; charset=utf-8"));
    Ok(r)
}

pub async fn openapi() -> Response {
    let mut r = include_str!("../../../../openapi.yaml").into_response();
    r.headers_mut().insert(header::CONTENT_TYPE, HeaderValue::from_static("application/yaml"));
    r
}

/// [highest allowed first frequency, lowest allowed last frequency] of a band-masked flow.
fn band_must_reach_hz(h: &otofit_npe::npe::Header) -> Option<[f64; 2]> {
    let n = h.frequencies_hz.len();
    (h.mask_bands && h.band_cut_max < n)
        .then(|| [h.frequencies_hz[h.band_cut_max], h.frequencies_hz[n - 1 - h.band_cut_max]])
}

fn model_doc(st: &AppState, m: &crate::store::ModelRow) -> serde_json::Value {
    let base = json!({
        "id": m.id, "default": m.is_default, "created_at": m.created_at, "source_job": m.source_job, "tenant": m.tenant,
    });
    match st.ctx.loaded(&m.id, std::path::Path::new(&m.path)) {
        Ok(npe) => {
            let h = &npe.header;
            let mut d = base;
            d["parameters"] = json!(h.params);
            d["frequencies_hz"] = json!(h.frequencies_hz);
            d["features"] = json!(h.feature_names.len());
            d["groups"] = json!(h.groups.iter().map(|g| &g.name).collect::<Vec<_>>());
            d["accepts_subsets"] = json!(h.mask_groups);
            // The narrowest band each measure may cover (band-masked models), never extrapolated.
            d["accepts_partial_bands"] = json!(h.mask_bands);
            if let Some(reach) = band_must_reach_hz(h) {
                d["band_must_reach_hz"] = json!(reach);
            }
            d["training"] = json!(h.training);
            d["members"] = json!(h.members);
            // The flow that answers ears with every measure, when the model holds one.
            if let Some(full) = npe.full_measure() {
                let f = &full.header;
                d["full_measure_flow"] = json!({
                    "training": f.training,
                    "temperature": f.temperature,
                    "fit_null": f.fit_null,
                });
            }
            // The flows that answer ears of exactly one set of feature groups.
            let sets: Vec<_> = npe
                .measure_sets()
                .iter()
                .map(|s| {
                    let f = &s.header;
                    let mut set = json!({
                        "measures": f.measures, "accepts_partial_bands": f.mask_bands, "training": f.training,
                        "temperature": f.temperature, "fit_null": f.fit_null,
                    });
                    // Two band-masked flows of the same measures differ in how far a band may stop short.
                    if let Some(reach) = band_must_reach_hz(f) {
                        set["band_must_reach_hz"] = json!(reach);
                    }
                    // A flow of one device's band answers ears given exactly from there.
                    if f.from_hz > 0.0 {
                        set["from_hz"] = json!(f.from_hz);
                    }
                    set
                })
                .collect();
            if !sets.is_empty() {
                d["measure_set_flows"] = json!(sets);
            }
            d["calibration"] = json!({
                "temperature": h.temperature,
                "fit_null": h.fit_null,
                "note": "temperature: standard deviation of the flow's base distribution, tuned on held-out simulations so that joint credible regions hold the truth at their level; fit_null: thresholds of the fit check, set on held-out simulations so that the check as a whole fails 1 - quantile of them (joint: true; false in files calibrated before), null when uncalibrated",
            });
            d
        }
        Err(e) => {
            // The cause names server files: it goes to the log, the client gets the id.
            tracing::error!(model = %m.id, error = %format!("{e:#}"), "model cannot be loaded");
            let mut d = base;
            d["error"] = json!(format!("model '{}' cannot be loaded (the server log says why)", m.id));
            d
        }
    }
}

pub async fn list_models(
    State(st): State<AppState>,
    Extension(who): Extension<Principal>,
    _: StrictQuery<NoQuery>,
) -> Result<Json<serde_json::Value>, Problem> {
    let rows = st.ctx.store.models(who.scope()).await.map_err(Problem::internal)?;
    Ok(Json(json!({ "models": rows.iter().map(|m| model_doc(&st, m)).collect::<Vec<_>>() })))
}

/// Whether `id` can name a stored job or model. None holds a NUL, which PostgreSQL text
/// cannot even hold as a query parameter (an error, once a 500): such an id is unknown.
fn may_be_stored(id: &str) -> bool {
    !id.contains('\0')
}

/// The model `id` if `who` may use it (another tenant's model does not exist for it).
pub async fn visible_model(
    st: &AppState,
    who: &Principal,
    id: &str,
) -> Result<Option<crate::store::ModelRow>, Problem> {
    if !may_be_stored(id) {
        return Ok(None);
    }
    let m = st.ctx.store.model(id).await.map_err(Problem::internal)?;
    Ok(m.filter(|m| who.sees_model(m)))
}

pub async fn get_model(
    State(st): State<AppState>,
    Extension(who): Extension<Principal>,
    Path(id): Path<String>,
) -> Result<Json<serde_json::Value>, Problem> {
    match visible_model(&st, &who, &id).await? {
        Some(m) => Ok(Json(model_doc(&st, &m))),
        None => Err(Problem::new(StatusCode::NOT_FOUND, format!("no model '{id}'"))),
    }
}

/// The job `id` if `who` may see it (another tenant's job does not exist for it).
async fn visible_job(st: &AppState, who: &Principal, id: &str) -> Result<Option<crate::store::JobRow>, Problem> {
    if !may_be_stored(id) {
        return Ok(None);
    }
    let j = st.ctx.store.job(id).await.map_err(Problem::internal)?;
    Ok(j.filter(|j| who.sees_job(j)))
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
pub struct NewJob {
    kind: String,
    #[serde(default)]
    params: serde_json::Value,
}

/// Job params that hold a patient's measurements: shown to the job's own tenant only
/// (an admin of another tenant sees the job without them, listed under `redacted`).
const MEASUREMENT_PARAMS: [&str; 2] = ["x", "observation"];

/// A job as served (openapi.yaml's Job): the stored row, without another tenant's
/// measurements, and its links.
#[derive(Serialize)]
pub struct JobDoc {
    /// The job as stored (its fields at the top level).
    #[serde(flatten)]
    pub job: JobRow,
    /// The params removed because they hold another tenant's measurements.
    #[serde(skip_serializing_if = "Vec::is_empty")]
    pub redacted: Vec<String>,
    pub links: JobLinks,
}

/// A job's `links`.
#[derive(Serialize)]
pub struct JobLinks {
    /// The job itself.
    #[serde(rename = "self")]
    pub this: String,
    /// Where to post to cancel it.
    pub cancel: String,
}

/// The answer of GET /jobs.
#[derive(Serialize)]
pub struct JobList {
    pub jobs: Vec<JobDoc>,
}

/// `job` as `who` sees it.
fn job_doc(mut job: JobRow, who: &Principal) -> JobDoc {
    let mut redacted = vec![];
    if job.tenant != who.tenant
        && let Some(params) = job.params.as_object_mut()
    {
        redacted =
            MEASUREMENT_PARAMS.iter().filter(|k| params.remove(**k).is_some()).map(|k| format!("params.{k}")).collect();
    }
    let links = JobLinks { this: format!("/jobs/{}", job.id), cancel: format!("/jobs/{}/cancel", job.id) };
    JobDoc { job, redacted, links }
}

pub async fn create_job(
    State(st): State<AppState>,
    Extension(who): Extension<Principal>,
    JsonBody(req): JsonBody<NewJob>,
) -> Result<Response, Problem> {
    let spec = JobSpec::parse(&req.kind, &req.params).map_err(Problem::invalid)?;
    match &spec {
        // As GET /datasets/{id}: no such dataset (for this client) is a 404, one whose
        // simulate job has not succeeded a 409; both name the field.
        JobSpec::Train(p) => match visible_job(&st, &who, &p.dataset).await? {
            Some(j) if j.kind == "simulate" && j.state == "succeeded" => {}
            Some(j) if j.kind == "simulate" => {
                let message = format!("dataset '{}' is not ready (job {})", p.dataset, j.state);
                return Err(super::field_problem(StatusCode::CONFLICT, "params.dataset", message));
            }
            _ => {
                let message = format!("no dataset '{}' (a succeeded simulate job's id)", p.dataset);
                return Err(super::field_problem(StatusCode::NOT_FOUND, "params.dataset", message));
            }
        },
        JobSpec::Diagnose(p) => model_takes(&st, &who, p.model.as_deref(), p.x.len()).await?,
        JobSpec::Exact(p) => model_takes(&st, &who, p.model.as_deref(), p.x.len()).await?,
        JobSpec::Simulate(_) | JobSpec::Resimulate(_) => {}
    }
    let id = jobs::new_id();
    let bounds = QueueBounds { queue: st.ctx.max_queue, per_tenant: st.ctx.max_queue_per_tenant };
    let admitted = st
        .ctx
        .store
        .insert_tenant_job_within(&id, &who.tenant, spec.kind(), &spec.params(), 3, bounds)
        .await
        .map_err(Problem::internal)?;
    let full = |detail: String| {
        let mut r = Problem::new(StatusCode::TOO_MANY_REQUESTS, detail).into_response();
        r.headers_mut().insert(header::RETRY_AFTER, HeaderValue::from(10));
        Ok(r)
    };
    match admitted {
        Admission::Queued => {}
        Admission::QueueFull => {
            return full(format!(
                "the queue is full: {} active (queued or running) jobs, the limit (--max-queue); retry later",
                bounds.queue
            ));
        }
        Admission::TenantFull => {
            return full(format!(
                "tenant '{}' has {} active (queued or running) jobs, its limit (--max-queue-per-tenant); \
                 retry when one ends",
                who.tenant, bounds.per_tenant
            ));
        }
    }
    st.ctx.notify.notify_one();
    tracing::info!(job = %id, kind = spec.kind(), tenant = %who.tenant, "job queued");
    let job =
        st.ctx.store.job(&id).await.map_err(Problem::internal)?.ok_or_else(|| Problem::internal("job vanished"))?;
    let mut r = (StatusCode::ACCEPTED, Json(job_doc(job, &who))).into_response();
    r.headers_mut().insert(header::LOCATION, HeaderValue::from_str(&format!("/jobs/{id}")).map_err(Problem::internal)?);
    Ok(r)
}

/// A diagnose or exact job's model (`params.model`, else the default) must be registered
/// (else a 404) and take as many features as `params.x` has (else a 422): both answered
/// now, not when the job runs.
async fn model_takes(st: &AppState, who: &Principal, model: Option<&str>, n: usize) -> Result<(), Problem> {
    let id = model.unwrap_or("default").to_string();
    let field = if model.is_some() { "params.model" } else { "params" };
    // An id that names no model (for this client) is a 404, as GET /models/{id} answers.
    if visible_model(st, who, &id).await?.is_none() {
        return Err(super::field_problem(StatusCode::NOT_FOUND, field, format!("model '{id}' is not registered")));
    }
    let ctx = st.ctx.clone();
    let id2 = id.clone();
    let npe = tokio::task::spawn_blocking(move || jobs::registered_model(&ctx, &id2))
        .await
        .map_err(Problem::internal)?
        .map_err(|e| {
            if let Some(cause) = e.cause() {
                tracing::error!(model = %id, error = %format!("{cause:#}"), "model cannot be loaded");
            }
            Problem::invalid(vec![(field.into(), e.to_string())])
        })?;
    let want = npe.header.feature_names.len();
    if n != want {
        return Err(Problem::invalid(vec![(
            "params.x".into(),
            format!("has {n} values; model '{id}' takes {want} features (GET /models/{id} lists them)"),
        )]));
    }
    Ok(())
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
pub struct JobQuery {
    state: Option<String>,
    limit: Option<i64>,
}

/// The query of a route that takes none.
#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
pub struct NoQuery {}

/// A query string read into `T` (`deny_unknown_fields`): a parameter the route does not
/// take is a 400 naming it, not silently ignored (a misspelt `limt=5` would otherwise
/// answer 100 rows as if it had been heard).
pub struct StrictQuery<T>(pub T);

impl<S: Send + Sync, T: serde::de::DeserializeOwned> axum::extract::FromRequestParts<S> for StrictQuery<T> {
    type Rejection = Response;

    async fn from_request_parts(parts: &mut axum::http::request::Parts, state: &S) -> Result<Self, Response> {
        match Query::<T>::from_request_parts(parts, state).await {
            Ok(Query(q)) => Ok(StrictQuery(q)),
            Err(e) => {
                let text = e.body_text();
                let Some(name) = text.split_once("unknown field `").and_then(|(_, r)| r.split_once('`')).map(|x| x.0)
                else {
                    // A bad value: the `problems` layer names its parameter.
                    return Err(e.into_response());
                };
                let takes = match text.split_once(", expected ") {
                    Some((_, names)) => format!("this route takes {}", names.replace('`', "")),
                    None => "this route takes none".into(),
                };
                let mut p =
                    Problem::new(StatusCode::BAD_REQUEST, format!("unknown query parameter '{name}' ({takes})"));
                p.errors = vec![super::FieldProblem {
                    field: name.into(),
                    message: format!("unknown query parameter; {takes}"),
                }];
                Err(p.into_response())
            }
        }
    }
}

pub async fn list_jobs(
    State(st): State<AppState>,
    Extension(who): Extension<Principal>,
    StrictQuery(q): StrictQuery<JobQuery>,
) -> Result<Json<JobList>, Problem> {
    if let Some(s) = &q.state
        && JobState::parse(s).is_none()
    {
        let names: Vec<&str> = JobState::ALL.iter().map(|s| s.as_str()).collect();
        return Err(Problem::invalid(vec![("state".into(), format!("must be one of {}", names.join(", ")))]));
    }
    let limit = q.limit.unwrap_or(100);
    if !(1..=1000).contains(&limit) {
        return Err(Problem::invalid(vec![("limit".into(), format!("must be 1..=1000, got {limit}"))]));
    }
    let rows = st.ctx.store.jobs(q.state.as_deref(), limit, who.scope()).await.map_err(Problem::internal)?;
    Ok(Json(JobList { jobs: rows.into_iter().map(|j| job_doc(j, &who)).collect() }))
}

pub async fn get_job(
    State(st): State<AppState>,
    Extension(who): Extension<Principal>,
    Path(id): Path<String>,
) -> Result<Json<JobDoc>, Problem> {
    match visible_job(&st, &who, &id).await? {
        Some(mut j) => {
            // A running simulate job's chunks finish on any worker; its own worker writes
            // progress only between its own chunks, so the chunk table is ahead.
            if j.kind == "simulate" && j.state == "running" {
                let chunks = st.ctx.store.chunks(&id).await.unwrap_or_default();
                if let Some((p, message)) = crate::jobs::progress_from_chunks(&chunks)
                    && p > j.progress
                {
                    (j.progress, j.message) = (p, message);
                }
            }
            Ok(Json(job_doc(j, &who)))
        }
        None => Err(Problem::new(StatusCode::NOT_FOUND, format!("no job '{id}'"))),
    }
}

pub async fn cancel_job(
    State(st): State<AppState>,
    Extension(who): Extension<Principal>,
    Path(id): Path<String>,
) -> Result<Response, Problem> {
    match visible_job(&st, &who, &id).await? {
        None => Err(Problem::new(StatusCode::NOT_FOUND, format!("no job '{id}'"))),
        Some(j) if !j.state.is_active() => {
            Err(Problem::new(StatusCode::CONFLICT, format!("job '{id}' already ended ({})", j.state)))
        }
        Some(_) => {
            let j = st
                .ctx
                .store
                .cancel(&id)
                .await
                .map_err(Problem::internal)?
                .ok_or_else(|| Problem::internal("job vanished"))?;
            Ok((StatusCode::ACCEPTED, Json(job_doc(j, &who))).into_response())
        }
    }
}

async fn dataset_job(st: &AppState, who: &Principal, id: &str) -> Result<(), Problem> {
    match visible_job(st, who, id).await? {
        Some(j) if j.kind == "simulate" && j.state == "succeeded" => Ok(()),
        Some(j) if j.kind == "simulate" => {
            Err(Problem::new(StatusCode::CONFLICT, format!("dataset '{id}' is not ready (job {})", j.state)))
        }
        _ => Err(Problem::new(StatusCode::NOT_FOUND, format!("no dataset '{id}'"))),
    }
}

pub async fn get_dataset(
    State(st): State<AppState>,
    Extension(who): Extension<Principal>,
    Path(id): Path<String>,
) -> Result<Json<serde_json::Value>, Problem> {
    dataset_job(&st, &who, &id).await?;
    let meta =
        st.ctx.artifacts.read(&crate::artifacts::dataset_key(&id, "meta.json")).await.map_err(Problem::internal)?;
    let meta: serde_json::Value = serde_json::from_slice(&meta).map_err(Problem::internal)?;
    Ok(Json(json!({
        "id": id,
        "rows": meta["n_rows"],
        "meta": meta,
        "files": { "theta": format!("/datasets/{id}/theta.csv"), "x": format!("/datasets/{id}/x.csv"), "meta": format!("/datasets/{id}/meta.json") },
    })))
}

pub async fn get_dataset_file(
    State(st): State<AppState>,
    Extension(who): Extension<Principal>,
    Path((id, file)): Path<(String, String)>,
) -> Result<Response, Problem> {
    let ct = match file.as_str() {
        "theta.csv" | "x.csv" => "text/csv",
        "meta.json" => "application/json",
        _ => {
            return Err(Problem::new(StatusCode::NOT_FOUND, format!("no file '{file}' (theta.csv, x.csv, meta.json)")));
        }
    };
    dataset_job(&st, &who, &id).await?;
    let bytes = st.ctx.artifacts.read(&crate::artifacts::dataset_key(&id, &file)).await.map_err(Problem::internal)?;
    let mut r = bytes.into_response();
    r.headers_mut().insert(header::CONTENT_TYPE, HeaderValue::from_static(ct));
    Ok(r)
}

/// A file a job wrote: its report page (report.html), report.json or SVG figures.
pub async fn get_job_file(
    State(st): State<AppState>,
    Extension(who): Extension<Principal>,
    Path((id, name)): Path<(String, String)>,
) -> Result<Response, Problem> {
    let ct = match name.rsplit('.').next() {
        Some("svg") => "image/svg+xml",
        Some("html") => "text/html; charset=utf-8",
        Some("json") => "application/json",
        _ => "",
    };
    if ct.is_empty() || name.contains('/') || name.contains("..") {
        return Err(Problem::new(StatusCode::NOT_FOUND, format!("no file '{name}'")));
    }
    let Some(job) = visible_job(&st, &who, &id).await? else {
        return Err(Problem::new(StatusCode::NOT_FOUND, format!("no job '{id}'")));
    };
    // A job's files are drawn from its measurements: they follow the params' rule.
    if job.tenant != who.tenant && MEASUREMENT_PARAMS.iter().any(|k| job.params.get(k).is_some()) {
        let detail = format!("job '{id}' holds another tenant's measurements: its files are that tenant's only");
        return Err(Problem::new(StatusCode::NOT_FOUND, detail));
    }
    let bytes = st
        .ctx
        .artifacts
        .read(&crate::artifacts::report_key(&id, &name))
        .await
        .map_err(|_| Problem::new(StatusCode::NOT_FOUND, format!("job '{id}' has no file '{name}'")))?;
    let mut r = bytes.into_response();
    r.headers_mut().insert(header::CONTENT_TYPE, HeaderValue::from_static(ct));
    Ok(r)
}
