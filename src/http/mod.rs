//! The HTTP API (axum): a thin layer over `npe`, `jobs` and `store`. Errors are RFC 9457
//! problem details; validation errors name the field. openapi.yaml is the contract and
//! `ROUTES` the list a test checks it against.

mod infer;
mod resources;

use crate::jobs::Ctx;
use axum::Router;
use axum::extract::{Request, State};
use axum::http::{HeaderValue, StatusCode, header};
use axum::middleware::{self, Next};
use axum::response::{IntoResponse, Response};
use axum::routing::{get, post};
use serde::Serialize;
use std::sync::Arc;
use subtle::ConstantTimeEq;

/// Every route the server answers: (method, path). openapi.yaml must list exactly these.
pub const ROUTES: [(&str, &str); 13] = [
    ("get", "/health"),
    ("get", "/ready"),
    ("get", "/openapi.yaml"),
    ("get", "/models"),
    ("get", "/models/{id}"),
    ("post", "/infer"),
    ("post", "/jobs"),
    ("get", "/jobs"),
    ("get", "/jobs/{id}"),
    ("post", "/jobs/{id}/cancel"),
    ("get", "/jobs/{id}/files/{name}"),
    ("get", "/datasets/{id}"),
    ("get", "/datasets/{id}/{file}"),
];

pub const MAX_BODY: usize = 2 * 1024 * 1024;

#[derive(Clone)]
pub struct AppState {
    pub ctx: Arc<Ctx>,
    /// SHA-256 hashes of accepted API keys; empty = no authentication.
    pub key_hashes: Arc<Vec<[u8; 32]>>,
}

/// An RFC 9457 problem.
#[derive(Debug, Serialize)]
pub struct Problem {
    #[serde(rename = "type")]
    pub kind: String,
    pub title: String,
    pub status: u16,
    pub detail: String,
    #[serde(skip_serializing_if = "Vec::is_empty")]
    pub errors: Vec<FieldProblem>,
}

#[derive(Debug, Serialize)]
pub struct FieldProblem {
    pub field: String,
    pub message: String,
}

impl Problem {
    pub fn new(status: StatusCode, detail: impl Into<String>) -> Problem {
        let title = status.canonical_reason().unwrap_or("Error").to_string();
        let slug = title.to_lowercase().replace(' ', "-");
        Problem {
            kind: format!("https://otofit.dev/problems/{slug}"),
            title,
            status: status.as_u16(),
            detail: detail.into(),
            errors: vec![],
        }
    }

    pub fn invalid(errors: Vec<(String, String)>) -> Problem {
        let mut p = Problem::new(StatusCode::UNPROCESSABLE_ENTITY, "the request has invalid fields");
        p.errors = errors.into_iter().map(|(field, message)| FieldProblem { field, message }).collect();
        p
    }

    pub fn internal(e: impl std::fmt::Display) -> Problem {
        tracing::error!(error = %e, "internal error");
        Problem::new(StatusCode::INTERNAL_SERVER_ERROR, "internal error (logged)")
    }
}

impl IntoResponse for Problem {
    fn into_response(self) -> Response {
        let status = StatusCode::from_u16(self.status).unwrap_or(StatusCode::INTERNAL_SERVER_ERROR);
        let mut r = (status, serde_json::to_string(&self).unwrap_or_default()).into_response();
        r.headers_mut().insert(header::CONTENT_TYPE, HeaderValue::from_static("application/problem+json"));
        r
    }
}

/// Parses a JSON body, answering 415 for another content type and 400/422 for bad JSON.
pub fn json_body<T: serde::de::DeserializeOwned>(headers: &axum::http::HeaderMap, body: &[u8]) -> Result<T, Problem> {
    let ct = headers.get(header::CONTENT_TYPE).and_then(|v| v.to_str().ok()).unwrap_or("");
    if !ct.starts_with("application/json") {
        return Err(Problem::new(StatusCode::UNSUPPORTED_MEDIA_TYPE, "send Content-Type: application/json"));
    }
    let de = &mut serde_json::Deserializer::from_slice(body);
    serde_path_to_error(de)
}

/// serde_json with the path of the failing field in the error.
fn serde_path_to_error<'de, T: serde::de::DeserializeOwned>(
    de: &mut serde_json::Deserializer<serde_json::de::SliceRead<'de>>,
) -> Result<T, Problem> {
    T::deserialize(de).map_err(|e| {
        if e.is_syntax() || e.is_eof() {
            Problem::new(StatusCode::BAD_REQUEST, format!("malformed JSON: {e}"))
        } else {
            let field = field_of(&e.to_string());
            Problem::invalid(vec![(field, e.to_string())])
        }
    })
}

/// Best effort: the field name serde mentions ("missing field `x`", "unknown field `y`").
fn field_of(msg: &str) -> String {
    msg.split('`').nth(1).unwrap_or("body").to_string()
}

async fn auth(State(st): State<AppState>, req: Request, next: Next) -> Response {
    if st.key_hashes.is_empty() || req.uri().path() == "/health" {
        return next.run(req).await;
    }
    let key =
        req.headers().get(header::AUTHORIZATION).and_then(|v| v.to_str().ok()).and_then(|v| v.strip_prefix("Bearer "));
    let ok = key.is_some_and(|k| {
        use sha2::Digest;
        let h: [u8; 32] = sha2::Sha256::digest(k.as_bytes()).into();
        st.key_hashes.iter().fold(0u8, |acc, stored| acc | stored.ct_eq(&h).unwrap_u8()) == 1
    });
    if ok {
        next.run(req).await
    } else {
        let mut r = Problem::new(StatusCode::UNAUTHORIZED, "a valid API key is required (Authorization: Bearer <key>)")
            .into_response();
        r.headers_mut().insert(header::WWW_AUTHENTICATE, HeaderValue::from_static("Bearer"));
        r
    }
}

async fn too_large(req: Request, next: Next) -> Response {
    let r = next.run(req).await;
    if r.status() == StatusCode::PAYLOAD_TOO_LARGE {
        return Problem::new(StatusCode::PAYLOAD_TOO_LARGE, format!("request body over {MAX_BODY} bytes"))
            .into_response();
    }
    r
}

pub fn router(state: AppState) -> Router {
    use resources::*;
    Router::new()
        .route("/health", get(health))
        .route("/ready", get(ready))
        .route("/openapi.yaml", get(openapi))
        .route("/models", get(list_models))
        .route("/models/{id}", get(get_model))
        .route("/infer", post(infer::infer))
        .route("/jobs", post(create_job).get(list_jobs))
        .route("/jobs/{id}", get(get_job))
        .route("/jobs/{id}/cancel", post(cancel_job))
        .route("/jobs/{id}/files/{name}", get(get_job_file))
        .route("/datasets/{id}", get(get_dataset))
        .route("/datasets/{id}/{file}", get(get_dataset_file))
        .fallback(|| async { Problem::new(StatusCode::NOT_FOUND, "no such route") })
        .layer(middleware::from_fn_with_state(state.clone(), auth))
        .layer(tower_http::limit::RequestBodyLimitLayer::new(MAX_BODY))
        .layer(middleware::from_fn(too_large))
        .layer(tower_http::trace::TraceLayer::new_for_http())
        .with_state(state)
}
