//! The HTTP API (axum): a thin layer over `npe`, `jobs` and `store`. Errors are RFC 9457
//! problem details; validation errors name the field. openapi.yaml is the contract and
//! `ROUTES` the list a test checks it against; the `contract` tests check the request and
//! response structs against its schemas.

pub mod auth;
pub use auth::{Principal, host_allowed};
pub mod conn;
mod extract;
pub use extract::{JsonBody, json_body};
mod infer;
mod log_prob;
pub use crate::gate::{BODY_DEADLINE, InferGate, InferLimits, UPLOADS_PER_ADDRESS};
pub use crate::metrics;
#[cfg(test)]
mod contract;
mod resources;

use crate::jobs::Ctx;
use axum::Router;
use axum::body::Body;
use axum::extract::{ConnectInfo, Request, State};
use axum::http::{HeaderValue, StatusCode, header};
use axum::middleware::{self, Next};
use axum::response::{IntoResponse, Response};
use axum::routing::{get, post};
use serde::Serialize;
use std::sync::Arc;
use std::sync::atomic::{AtomicBool, AtomicUsize, Ordering};
use std::time::Duration;

/// Every route the server answers: (method, path). openapi.yaml must list exactly these.
pub const ROUTES: [(&str, &str); 15] = [
    ("get", "/health"),
    ("get", "/ready"),
    ("get", "/openapi.yaml"),
    ("get", "/models"),
    ("get", "/models/{id}"),
    ("post", "/infer"),
    ("post", "/log_prob"),
    ("post", "/jobs"),
    ("get", "/jobs"),
    ("get", "/jobs/{id}"),
    ("post", "/jobs/{id}/cancel"),
    ("get", "/jobs/{id}/files/{name}"),
    ("get", "/datasets/{id}"),
    ("get", "/datasets/{id}/{file}"),
    ("get", "/metrics"),
];

/// Largest request body accepted (2 MiB); a larger one gets a 413 problem.
pub const MAX_BODY: usize = 2 * 1024 * 1024;

/// Counts a waiting request for as long as it waits (also when its client goes away).
struct Waiting<'a>(&'a AtomicUsize);

impl Drop for Waiting<'_> {
    fn drop(&mut self) {
        self.0.fetch_sub(1, Ordering::SeqCst);
    }
}

fn busy(detail: String, retry_after: u64) -> Response {
    let mut r = Problem::new(StatusCode::SERVICE_UNAVAILABLE, detail).into_response();
    r.headers_mut().insert(header::RETRY_AFTER, HeaderValue::from(retry_after));
    r
}

/// The /infer gate with its latency recorded for /metrics (status and seconds, waiting
/// for a slot included). The body is received in full before a slot is taken, so a
/// client that trickles its body holds no slot (408 after [`BODY_DEADLINE`]).
async fn infer_gate(State(st): State<AppState>, req: Request, next: Next) -> Response {
    let t0 = std::time::Instant::now();
    let r = match receive_body(&st, req).await {
        Ok(req) => infer_slot(State(st.clone()), req, next).await,
        Err(r) => r,
    };
    st.ctx.metrics.inferred(r.status().as_u16(), t0.elapsed().as_secs_f64());
    r
}

/// The request with its body received in full: within [`BODY_DEADLINE`] (408), at most
/// [`MAX_BODY`] bytes (413), at most [`UPLOADS_PER_ADDRESS`] at once from one client
/// address (429).
async fn receive_body(st: &AppState, req: Request) -> Result<Request, Response> {
    let addr = req.extensions().get::<ConnectInfo<conn::ClientAddr>>().map(|c| c.0.0.ip());
    let _upload = match addr {
        Some(ip) => match st.ctx.infer_gate.upload(ip) {
            Some(u) => Some(u),
            None => {
                let detail = format!(
                    "{UPLOADS_PER_ADDRESS} request bodies from this address are still arriving; retry when they are done"
                );
                let mut r = Problem::new(StatusCode::TOO_MANY_REQUESTS, detail).into_response();
                r.headers_mut().insert(header::RETRY_AFTER, HeaderValue::from(1));
                return Err(r);
            }
        },
        None => None,
    };
    let (parts, body) = req.into_parts();
    match tokio::time::timeout(BODY_DEADLINE, axum::body::to_bytes(body, MAX_BODY)).await {
        Ok(Ok(bytes)) => Ok(Request::from_parts(parts, Body::from(bytes))),
        Ok(Err(_)) => {
            Err(Problem::new(StatusCode::PAYLOAD_TOO_LARGE, format!("request body over {MAX_BODY} bytes"))
                .into_response())
        }
        Err(_) => {
            let detail = format!("the request body did not arrive within {} s", BODY_DEADLINE.as_secs());
            Err(Problem::new(StatusCode::REQUEST_TIMEOUT, detail).into_response())
        }
    }
}

/// The /infer gate (a layer on that route): a slot or a short wait for one, then the
/// request runs in its own task holding the slot until its work is done, even when the
/// client has been answered 503 at the deadline: the bound is on work, not on replies.
async fn infer_slot(State(st): State<AppState>, req: Request, next: Next) -> Response {
    let gate = &st.ctx.infer_gate;
    let InferLimits { concurrency, queue, deadline } = gate.limits;
    let t0 = tokio::time::Instant::now();
    let slot = match gate.slots.clone().try_acquire_owned() {
        Ok(slot) => slot,
        Err(_) => {
            if gate.waiting.fetch_add(1, Ordering::SeqCst) >= queue {
                gate.waiting.fetch_sub(1, Ordering::SeqCst);
                return busy(format!("{concurrency} inferences running and {queue} waiting; retry shortly"), 1);
            }
            let _waiting = Waiting(&gate.waiting);
            match tokio::time::timeout(deadline, gate.slots.clone().acquire_owned()).await {
                Ok(Ok(slot)) => slot,
                _ => return busy(format!("no inference slot within the {} s deadline", deadline.as_secs_f64()), 1),
            }
        }
    };
    let work = tokio::spawn(async move {
        let _slot = slot;
        next.run(req).await
    });
    match tokio::time::timeout_at(t0 + deadline, work).await {
        Ok(Ok(r)) => r,
        Ok(Err(e)) => Problem::internal(e).into_response(),
        Err(_) => {
            tracing::warn!(ms = t0.elapsed().as_millis() as u64, "inference over its deadline");
            busy(
                format!(
                    "the inference took longer than its {} s deadline; retry, or ask for fewer samples",
                    deadline.as_secs_f64()
                ),
                2,
            )
        }
    }
}

/// What every handler gets: the job context and the server's authentication settings.
#[derive(Clone)]
pub struct AppState {
    /// The store, data dir, models and queue shared with the job runner.
    pub ctx: Arc<Ctx>,
    /// SHA-256 hashes of accepted API keys; empty = no authentication.
    pub key_hashes: Arc<Vec<[u8; 32]>>,
    /// Host names a keyless server answers besides loopback names and IP literals
    /// (lower case, without port).
    pub allowed_hosts: Arc<Vec<String>>,
    /// Whether the database was seen to hold API keys (then the server stays keyed).
    keyed: Arc<AtomicBool>,
}

impl AppState {
    /// The state of a server that accepts the keys with these SHA-256 hashes (none: no authentication).
    pub fn new(ctx: Arc<Ctx>, key_hashes: Vec<[u8; 32]>) -> AppState {
        AppState {
            ctx,
            key_hashes: Arc::new(key_hashes),
            allowed_hosts: Arc::new(vec![]),
            keyed: Arc::new(AtomicBool::new(false)),
        }
    }

    /// Also answers these host names when keyless (DNS-rebinding guard).
    pub fn with_allowed_hosts(mut self, hosts: Vec<String>) -> AppState {
        self.allowed_hosts = Arc::new(hosts.into_iter().map(|h| h.to_ascii_lowercase()).collect());
        self
    }
}

/// An RFC 9457 problem.
#[derive(Debug, Serialize)]
pub struct Problem {
    /// A URI naming the kind of problem.
    #[serde(rename = "type")]
    pub kind: String,
    /// The HTTP status's reason phrase.
    pub title: String,
    /// The HTTP status code.
    pub status: u16,
    /// What went wrong, for a person.
    pub detail: String,
    /// The request fields that were invalid, and why (422 only).
    #[serde(skip_serializing_if = "Vec::is_empty")]
    pub errors: Vec<FieldProblem>,
    /// A machine-readable reason where one status has several (e.g. `insufficient_data`).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub code: Option<&'static str>,
}

/// One invalid field of a request.
#[derive(Debug, Serialize)]
pub struct FieldProblem {
    /// The field's path in the request body (e.g. `measurements.umbo_velocity.phase`).
    pub field: String,
    /// What is wrong with it.
    pub message: String,
}

impl Problem {
    /// A problem with `status`, its reason as title and `detail`.
    pub fn new(status: StatusCode, detail: impl Into<String>) -> Problem {
        let title = status.canonical_reason().unwrap_or("Error").to_string();
        let slug = title.to_lowercase().replace(' ', "-");
        Problem {
            kind: format!("https://otofit.dev/problems/{slug}"),
            title,
            status: status.as_u16(),
            detail: detail.into(),
            errors: vec![],
            code: None,
        }
    }

    /// A 422 naming each invalid field and why.
    pub fn invalid(errors: Vec<(String, String)>) -> Problem {
        let mut p = Problem::new(StatusCode::UNPROCESSABLE_ENTITY, "the request has invalid fields");
        p.errors = errors.into_iter().map(|(field, message)| FieldProblem { field, message }).collect();
        p
    }

    /// A 500 that logs the error and tells the client no more than that it was logged.
    pub fn internal(e: impl std::fmt::Display) -> Problem {
        tracing::error!(error = %e, "internal error");
        Problem::new(StatusCode::INTERNAL_SERVER_ERROR, "internal error (logged)")
    }
}

/// A problem with `status` about one field of the request, named in `errors`.
pub(crate) fn field_problem(status: StatusCode, field: &str, message: String) -> Problem {
    let mut p = Problem::new(status, format!("{field}: {message}"));
    p.errors = vec![FieldProblem { field: field.into(), message }];
    p
}

impl IntoResponse for Problem {
    fn into_response(self) -> Response {
        let status = StatusCode::from_u16(self.status).unwrap_or(StatusCode::INTERNAL_SERVER_ERROR);
        let mut r = (status, serde_json::to_string(&self).unwrap_or_default()).into_response();
        r.headers_mut().insert(header::CONTENT_TYPE, HeaderValue::from_static("application/problem+json"));
        r
    }
}

/// Longest request target (path and query) answered; longer ones get a 414 problem.
pub const MAX_URI: usize = 8 * 1024;
/// Most header fields, and most bytes of header names and values, in one request; more
/// gets a 431 problem.
pub const MAX_HEADERS: (usize, usize) = (64, 32 * 1024);

/// 414 and 431 as problems, below hyper's own bounds (a 64 KiB target, 100 fields, a
/// ~400 KB head), past which hyper answers them itself with an empty body before any
/// middleware runs.
async fn head_limits(req: Request, next: Next) -> Response {
    let target = req.uri().path_and_query().map_or(0, |pq| pq.as_str().len());
    if target > MAX_URI {
        let detail = format!("the request target has {target} bytes; at most {MAX_URI} are answered");
        return Problem::new(StatusCode::URI_TOO_LONG, detail).into_response();
    }
    let fields = req.headers().len();
    let bytes: usize = req.headers().iter().map(|(k, v)| k.as_str().len() + v.len()).sum();
    if fields > MAX_HEADERS.0 || bytes > MAX_HEADERS.1 {
        let (n, b) = MAX_HEADERS;
        let detail = format!("{fields} header fields of {bytes} bytes; at most {n} fields and {b} bytes are answered");
        return Problem::new(StatusCode::REQUEST_HEADER_FIELDS_TOO_LARGE, detail).into_response();
    }
    next.run(req).await
}

/// Every error answer as problem+json: those of axum itself (405, extractor rejections),
/// of tower-http (413, 408) and of handlers that are not problems yet. The headers that go
/// with a status (Allow, Retry-After, WWW-Authenticate) are kept.
async fn problems(req: Request, next: Next) -> Response {
    let path = req.uri().path().to_string();
    let r = next.run(req).await;
    let status = r.status();
    let is_problem = r.headers().get(header::CONTENT_TYPE).is_some_and(|v| v == "application/problem+json");
    if !(status.is_client_error() || status.is_server_error()) || is_problem {
        return r;
    }
    let (parts, body) = r.into_parts();
    let text = axum::body::to_bytes(body, 4096).await.unwrap_or_default();
    let text = String::from_utf8_lossy(&text).trim().to_string();
    let mut allow = parts.headers.get(header::ALLOW).and_then(|v| v.to_str().ok()).unwrap_or("").to_string();
    if status == StatusCode::METHOD_NOT_ALLOWED && allow.is_empty() {
        allow = allowed_methods(&path);
    }
    let mut p = match status {
        StatusCode::PAYLOAD_TOO_LARGE => Problem::new(status, format!("request body over {MAX_BODY} bytes")),
        StatusCode::METHOD_NOT_ALLOWED => Problem::new(status, format!("method not allowed here; allowed: {allow}")),
        StatusCode::REQUEST_TIMEOUT => Problem::new(status, "the request was not received and answered in time"),
        _ if text.is_empty() => Problem::new(status, status.canonical_reason().unwrap_or("error")),
        _ => Problem::new(status, text.clone()),
    };
    // Query/path rejections name the parameter: "Failed to deserialize query string: limit: …".
    if status == StatusCode::BAD_REQUEST
        && let Some(rest) = text.split_once("query string: ").or_else(|| text.split_once("path parameter")).map(|x| x.1)
        && let Some((field, message)) = rest.split_once(": ")
    {
        p.errors = vec![FieldProblem { field: field.trim().trim_matches('`').to_string(), message: message.into() }];
    }
    let mut out = p.into_response();
    for h in [header::ALLOW, header::RETRY_AFTER, header::WWW_AUTHENTICATE] {
        if let Some(v) = parts.headers.get(&h) {
            out.headers_mut().insert(h, v.clone());
        }
    }
    if status == StatusCode::METHOD_NOT_ALLOWED
        && let Ok(v) = HeaderValue::from_str(&allow)
    {
        out.headers_mut().insert(header::ALLOW, v);
    }
    out
}

/// The methods [`ROUTES`] answers on `path` (`{…}` segments match any), as an Allow value.
fn allowed_methods(path: &str) -> String {
    let segments: Vec<&str> = path.trim_matches('/').split('/').collect();
    let matches = |route: &str| {
        let r: Vec<&str> = route.trim_matches('/').split('/').collect();
        r.len() == segments.len() && r.iter().zip(&segments).all(|(a, b)| a.starts_with('{') || a == b)
    };
    let mut methods: Vec<String> =
        ROUTES.iter().filter(|(_, route)| matches(route)).map(|(m, _)| m.to_ascii_uppercase()).collect();
    methods.dedup();
    methods.join(", ")
}

/// Bounds every request's total time, body included: 408 after `timeout`.
pub fn with_request_timeout(app: Router, timeout: Duration) -> Router {
    app.layer(tower_http::timeout::TimeoutLayer::with_status_code(StatusCode::REQUEST_TIMEOUT, timeout))
        .layer(middleware::from_fn(problems))
}

/// GET /metrics alone, for a worker's `--metrics-addr` (a process without the API).
pub fn metrics_router(ctx: Arc<Ctx>) -> Router {
    Router::new().route("/metrics", get(resources::metrics)).with_state(AppState::new(ctx, vec![]))
}

/// The service's routes, authentication and body limit on `state`.
pub fn router(state: AppState) -> Router {
    use resources::*;
    Router::new()
        .route("/health", get(health))
        .route("/ready", get(ready))
        .route("/openapi.yaml", get(openapi))
        .route("/models", get(list_models))
        .route("/models/{id}", get(get_model))
        .route("/infer", post(infer::infer).layer(middleware::from_fn_with_state(state.clone(), infer_gate)))
        .route("/log_prob", post(log_prob::log_prob).layer(middleware::from_fn_with_state(state.clone(), infer_gate)))
        .route("/jobs", post(create_job).get(list_jobs))
        .route("/jobs/{id}", get(get_job))
        .route("/jobs/{id}/cancel", post(cancel_job))
        .route("/jobs/{id}/files/{name}", get(get_job_file))
        .route("/datasets/{id}", get(get_dataset))
        .route("/datasets/{id}/{file}", get(get_dataset_file))
        .route("/metrics", get(metrics))
        .fallback(|| async { Problem::new(StatusCode::NOT_FOUND, "no such route") })
        .layer(middleware::from_fn_with_state(state.clone(), auth::guard))
        .layer(tower_http::limit::RequestBodyLimitLayer::new(MAX_BODY))
        .layer(middleware::from_fn(head_limits))
        .layer(middleware::from_fn(problems))
        .layer(tower_http::trace::TraceLayer::new_for_http())
        .with_state(state)
}
