//! The service through its router (no sockets): contract, validation, jobs, auth.

use crate::pg::{TempDir, temp_dir};
use axum::Router;
use axum::body::Body;
use axum::http::{Request, StatusCode, header};
use otofit::http::{AppState, ROUTES, router};
use otofit::jobs::{self, Ctx};
use serde_json::{Value, json};
use std::path::PathBuf;
use std::sync::Arc;
use tower::ServiceExt;

const SPEC: &str = include_str!("../../openapi.yaml");

pub(crate) fn default_model() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("models/default.otofit")
}

/// A router on a fresh data dir, removed when the returned guard is dropped (keep it for the
/// whole test).
pub(crate) async fn app(keys: Vec<[u8; 32]>, max_queue: i64, dispatch: bool) -> (Router, Arc<Ctx>, TempDir) {
    let dir = temp_dir("http");
    let ctx = otofit::cli::serve::open(&dir, &default_model(), max_queue).await.unwrap();
    if dispatch {
        tokio::spawn(jobs::dispatcher(ctx.clone()));
    }
    (router(AppState::new(ctx.clone(), keys)), ctx, dir)
}

pub(crate) async fn call(
    app: &Router,
    method: &str,
    uri: &str,
    body: Option<Value>,
) -> (StatusCode, axum::http::HeaderMap, Value) {
    let mut req = Request::builder().method(method).uri(uri);
    if body.is_some() {
        req = req.header(header::CONTENT_TYPE, "application/json");
    }
    let req = req.body(body.map_or(Body::empty(), |b| Body::from(b.to_string()))).unwrap();
    let res = app.clone().oneshot(req).await.unwrap();
    let (status, headers) = (res.status(), res.headers().clone());
    let bytes = axum::body::to_bytes(res.into_body(), usize::MAX).await.unwrap();
    (status, headers, serde_json::from_slice(&bytes).unwrap_or(Value::Null))
}

async fn raw(app: &Router, req: Request<Body>) -> (StatusCode, axum::http::HeaderMap, Value) {
    let res = app.clone().oneshot(req).await.unwrap();
    let (status, headers) = (res.status(), res.headers().clone());
    let bytes = axum::body::to_bytes(res.into_body(), usize::MAX).await.unwrap();
    (status, headers, serde_json::from_slice(&bytes).unwrap_or(Value::Null))
}

/// (method, path) of every operation in openapi.yaml (paths at 2 spaces, methods at 4).
fn spec_operations() -> Vec<(String, String)> {
    let mut ops = Vec::new();
    let (mut in_paths, mut path) = (false, String::new());
    for line in SPEC.lines() {
        if line.starts_with("paths:") {
            in_paths = true;
        } else if !line.starts_with(' ') && !line.is_empty() {
            in_paths = false;
        } else if in_paths && line.starts_with("  /") {
            path = line.trim().trim_end_matches(':').to_string();
        } else if in_paths && (line == "    get:" || line == "    post:") {
            ops.push((line.trim().trim_end_matches(':').to_string(), path.clone()));
        }
    }
    ops
}

/// Every `example:` of the spec (single-line JSON), with the path it sits under.
fn spec_examples() -> Vec<(String, Value)> {
    let mut out = Vec::new();
    let mut path = String::new();
    for line in SPEC.lines() {
        if line.starts_with("  /") {
            path = line.trim().trim_end_matches(':').to_string();
        }
        if let Some(ex) = line.trim().strip_prefix("example: ") {
            out.push((
                path.clone(),
                serde_json::from_str(ex).unwrap_or_else(|e| panic!("example under {path} is not JSON: {e}")),
            ));
        }
    }
    out
}

/// Required keys of a component schema (its `required: [...]` line).
fn required(schema: &str) -> Vec<String> {
    let start = SPEC.find(&format!("\n    {schema}:\n")).unwrap_or_else(|| panic!("no schema {schema}"));
    let line = SPEC[start..].lines().find(|l| l.trim().starts_with("required:")).unwrap();
    line.trim().trim_start_matches("required: [").trim_end_matches(']').split(", ").map(str::to_string).collect()
}

#[test]
fn openapi_lists_exactly_the_served_routes() {
    let mut spec = spec_operations();
    let mut served: Vec<(String, String)> = ROUTES.iter().map(|(m, p)| (m.to_string(), p.to_string())).collect();
    spec.sort();
    served.sort();
    assert_eq!(spec, served);
}

#[tokio::test]
async fn spec_examples_are_answered_as_documented() {
    let (app, _, _dir) = app(vec![], 8, false).await;
    let examples = spec_examples();
    let infer = &examples.iter().find(|(p, _)| p == "/infer").unwrap().1;
    let (status, _, body) = call(&app, "POST", "/infer", Some(infer.clone())).await;
    assert_eq!(status, StatusCode::OK, "{body}");
    for k in required("InferResponse") {
        assert!(body.get(&k).is_some(), "response lacks required '{k}'");
    }
    for k in required("ParamSummary") {
        assert!(body["parameters"][0].get(&k).is_some(), "parameter summary lacks '{k}'");
    }
    assert_eq!(body["samples"].as_array().unwrap().len(), 1000);
    assert_eq!(body["inputs"]["interpolated"], true);
    // The example is the typical ear (tissue at the centres of the normal ranges): its
    // posterior must cover the true E_sal. Not with its 90 % interval: the cavity sits on
    // its prior's upper bound and the E_sal posterior trades against it; the truth must
    // lie in the central 98 %.
    let true_sal = otofit::npe::normal::centre_row()[3];
    let sal: Vec<f64> = body["samples"].as_array().unwrap().iter().map(|r| r[3].as_f64().unwrap()).collect();
    let below = sal.iter().filter(|&&v| v < true_sal).count() as f64 / sal.len() as f64;
    // (The v7 model put it at the 99.1st percentile, a recorded miss; the v8 model at 0.947.)
    eprintln!("P(E_sal < truth) = {below}: {}", body["parameters"][3]);
    assert!((0.01..=0.99).contains(&below), "P(E_sal < truth) = {below}");
    let job = &examples.iter().find(|(p, _)| p == "/jobs").unwrap().1;
    let (status, headers, body) = call(&app, "POST", "/jobs", Some(job.clone())).await;
    assert_eq!(status, StatusCode::ACCEPTED, "{body}");
    assert!(headers[header::LOCATION].to_str().unwrap().starts_with("/jobs/"));
    for k in required("Job") {
        assert!(body.get(&k).is_some(), "job lacks '{k}'");
    }
    for (path, ex) in &examples {
        if path == "/health" {
            let (_, _, b) = call(&app, "GET", "/health", None).await;
            assert_eq!(
                b.as_object().unwrap().keys().collect::<Vec<_>>(),
                ex.as_object().unwrap().keys().collect::<Vec<_>>()
            );
        }
    }
    let (status, _, body) = call(&app, "GET", "/ready", None).await;
    assert_eq!((status, body["ready"].as_bool()), (StatusCode::OK, Some(true)));
}

#[tokio::test]
async fn bad_requests_get_problems_that_name_the_field() {
    let (app, _, _dir) = app(vec![], 8, false).await;
    let f = [200.0, 1000.0, 900.0, 8000.0];
    let body = json!({"measurements": {"absorbance": {"frequencies_hz": f, "values": [0.1, 0.5, 0.6, 0.3]}}});
    let (status, headers, p) = call(&app, "POST", "/infer", Some(body)).await;
    assert_eq!(status, StatusCode::UNPROCESSABLE_ENTITY);
    assert_eq!(headers[header::CONTENT_TYPE], "application/problem+json");
    assert_eq!(p["errors"][0]["field"], "measurements.absorbance.frequencies_hz[2]", "{p}");
    let narrow = json!({"measurements": {"absorbance": {"frequencies_hz": [500.0, 4000.0], "values": [0.1, 0.5]}}});
    let (_, _, p) = call(&app, "POST", "/infer", Some(narrow)).await;
    assert!(p["errors"][0]["message"].as_str().unwrap().contains("must reach"), "{p}");
    let nan =
        json!({"measurements": {"absorbance": {"frequencies_hz": [200.0, 8000.0], "values": [0.1]}}, "samples": 0});
    let (status, _, p) = call(&app, "POST", "/infer", Some(nan)).await;
    assert_eq!(status, StatusCode::UNPROCESSABLE_ENTITY, "{p}");
    let (status, _, p) = call(&app, "POST", "/infer", Some(json!({"measurements": {"wbt": {}}}))).await;
    assert_eq!(status, StatusCode::UNPROCESSABLE_ENTITY);
    assert!(p["errors"][0]["field"] == "measurements.wbt", "named by its JSON path: {p}");
    let req = Request::builder()
        .method("POST")
        .uri("/infer")
        .header(header::CONTENT_TYPE, "application/json")
        .body(Body::from("{not json"))
        .unwrap();
    assert_eq!(raw(&app, req).await.0, StatusCode::BAD_REQUEST);
    let req = Request::builder()
        .method("POST")
        .uri("/infer")
        .header(header::CONTENT_TYPE, "text/plain")
        .body(Body::from("{}"))
        .unwrap();
    assert_eq!(raw(&app, req).await.0, StatusCode::UNSUPPORTED_MEDIA_TYPE);
    let big = vec![b' '; otofit::http::MAX_BODY + 10];
    let req = Request::builder()
        .method("POST")
        .uri("/infer")
        .header(header::CONTENT_TYPE, "application/json")
        .body(Body::from(big))
        .unwrap();
    let (status, _, p) = raw(&app, req).await;
    assert_eq!(status, StatusCode::PAYLOAD_TOO_LARGE, "{p}");
    let (status, _, p) = call(
        &app,
        "POST",
        "/jobs",
        Some(json!({"kind": "simulate", "params": {"n": 5, "effects": {"probe_leak": 1.0}}})),
    )
    .await;
    assert_eq!(status, StatusCode::UNPROCESSABLE_ENTITY);
    assert_eq!(p["errors"][0]["field"], "params.effects.probe_leak", "{p}");
    let (status, _, p) =
        call(&app, "POST", "/jobs", Some(json!({"kind": "train", "params": {"dataset": "nope"}}))).await;
    assert_eq!((status, p["errors"][0]["field"].as_str()), (StatusCode::NOT_FOUND, Some("params.dataset")));
    assert_eq!(call(&app, "GET", "/jobs/nope", None).await.0, StatusCode::NOT_FOUND);
    assert_eq!(call(&app, "GET", "/jobs?state=done", None).await.0, StatusCode::UNPROCESSABLE_ENTITY);
    assert_eq!(call(&app, "GET", "/nowhere", None).await.0, StatusCode::NOT_FOUND);
}

async fn wait(app: &Router, id: &str) -> Value {
    for _ in 0..600 {
        let (_, _, j) = call(app, "GET", &format!("/jobs/{id}"), None).await;
        if ["succeeded", "failed", "cancelled"].contains(&j["state"].as_str().unwrap_or("")) {
            return j;
        }
        tokio::time::sleep(std::time::Duration::from_millis(100)).await;
    }
    panic!("job {id} did not end");
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn simulate_train_and_infer_through_jobs() {
    let (app, _, _dir) = app(vec![], 8, true).await;
    let (_, _, j) =
        call(&app, "POST", "/jobs", Some(json!({"kind": "simulate", "params": {"n": 120, "seed": 3}}))).await;
    let id = j["id"].as_str().unwrap().to_string();
    let done = wait(&app, &id).await;
    assert_eq!(done["state"], "succeeded", "{done}");
    assert_eq!(done["progress"], 1.0);
    let (_, _, ds) = call(&app, "GET", &format!("/datasets/{id}"), None).await;
    assert_eq!(ds["rows"], 120);
    let res =
        app.clone().oneshot(Request::get(format!("/datasets/{id}/x.csv")).body(Body::empty()).unwrap()).await.unwrap();
    let csv = axum::body::to_bytes(res.into_body(), usize::MAX).await.unwrap();
    assert_eq!(String::from_utf8_lossy(&csv).lines().count(), 121);
    let (_, _, t) = call(
        &app,
        "POST",
        "/jobs",
        Some(json!({"kind": "train", "params": {"dataset": id, "max_epochs": 2, "ensemble": 2}})),
    )
    .await;
    let tid = t["id"].as_str().unwrap().to_string();
    let done = wait(&app, &tid).await;
    assert_eq!(done["state"], "succeeded", "{done}");
    let (status, _, m) = call(&app, "GET", &format!("/models/{tid}"), None).await;
    assert_eq!(
        (status, m["training"]["epochs"].as_u64(), m["members"].as_u64()),
        (StatusCode::OK, Some(4), Some(2)),
        "two members of two epochs: {m}"
    );
    let (_, _, r) = call(
        &app,
        "POST",
        "/jobs",
        Some(json!({"kind": "resimulate", "params": {"theta": [[2e7, 5e6, 2e6, 2e5, 6e6, 7.5e-5, 2.1e10]]}})),
    )
    .await;
    let done = wait(&app, r["id"].as_str().unwrap()).await;
    assert_eq!(done["result"]["x"][0].as_array().unwrap().len(), 350, "{done}");
    // With the observation: ρ per row and measure, a figure and a report page.
    let obs = done["result"]["x"][0].clone();
    let theta = json!([[2e7, 5e6, 2e6, 2e5, 6e6, 7.5e-5, 2.1e10], [2e7, 5e6, 2e6, 1e6, 6e6, 7.5e-5, 2.1e10]]);
    let (_, _, r) = call(
        &app,
        "POST",
        "/jobs",
        Some(json!({"kind": "resimulate", "params": {"theta": theta, "observation": obs}})),
    )
    .await;
    let done = wait(&app, r["id"].as_str().unwrap()).await;
    let rho = &done["result"]["rho"];
    assert!(
        rho[0].as_array().unwrap().iter().all(|v| (v.as_f64().unwrap() - 1.0).abs() < 1e-12),
        "same row, same spectra: {rho}"
    );
    assert!(rho[1][0].as_f64().unwrap() < 1.0, "a stiffer annular ligament changes vst: {rho}");
    let page = text(&app, done["result"]["report"].as_str().unwrap()).await;
    assert!(page.contains("<img src=\"spectra.svg\"") && page.contains("E_sal"));
    let (_, _, bad) = call(
        &app,
        "POST",
        "/jobs",
        Some(json!({"kind": "resimulate", "params": {"theta": theta, "observation": [1.0]}})),
    )
    .await;
    assert_eq!(bad["errors"][0]["field"], "params.observation", "{bad}");
}

/// GET a text/html resource.
async fn text(app: &Router, uri: &str) -> String {
    let res = app.clone().oneshot(Request::get(uri).body(Body::empty()).unwrap()).await.unwrap();
    assert_eq!(res.status(), StatusCode::OK, "{uri}");
    assert_eq!(res.headers()[header::CONTENT_TYPE], "text/html; charset=utf-8");
    String::from_utf8(axum::body::to_bytes(res.into_body(), usize::MAX).await.unwrap().to_vec()).unwrap()
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn cancel_recover_and_queue_limits() {
    let (app, ctx, _dir) = app(vec![], 2, true).await;
    let (_, _, j) =
        call(&app, "POST", "/jobs", Some(json!({"kind": "simulate", "params": {"n": 100000, "seed": 1}}))).await;
    let id = j["id"].as_str().unwrap().to_string();
    tokio::time::sleep(std::time::Duration::from_millis(400)).await;
    let (status, _, _) = call(&app, "POST", &format!("/jobs/{id}/cancel"), None).await;
    assert_eq!(status, StatusCode::ACCEPTED);
    let done = wait(&app, &id).await;
    assert_eq!(done["state"], "cancelled", "{done}");
    assert!(!ctx.dataset_dir(&id).join("x.csv").exists() && !ctx.dataset_dir(&id).join("x.csv.tmp").exists());
    assert_eq!(call(&app, "POST", &format!("/jobs/{id}/cancel"), None).await.0, StatusCode::CONFLICT);
    // Queue bound: two queued jobs fill a queue of 2 (no dispatcher claims them here).
    let (app2, ctx2, _dir2) = self::app(vec![], 2, false).await;
    for _ in 0..2 {
        assert_eq!(
            call(&app2, "POST", "/jobs", Some(json!({"kind": "simulate", "params": {"n": 10}}))).await.0,
            StatusCode::ACCEPTED
        );
    }
    assert_eq!(
        call(&app2, "POST", "/jobs", Some(json!({"kind": "simulate", "params": {"n": 10}}))).await.0,
        StatusCode::TOO_MANY_REQUESTS
    );
    // Crash recovery: a job left running is re-queued, or failed after its last attempt.
    let store = &ctx2.store;
    let lease = jobs::DEFAULT_LEASE;
    let first = store.claim("test", lease).await.unwrap().unwrap();
    let second = store.claim("test", lease).await.unwrap().unwrap();
    sqlx::query("UPDATE jobs SET attempts = max_attempts WHERE id = ?")
        .bind(&second.id)
        .execute(store.sqlite().unwrap())
        .await
        .unwrap();
    assert_eq!(store.recover().await.unwrap(), (1, 1));
    assert_eq!(store.job(&first.id).await.unwrap().unwrap().state, "queued");
    let failed = store.job(&second.id).await.unwrap().unwrap();
    assert_eq!(failed.state, "failed");
    assert!(failed.error.unwrap().contains("last attempt"));
}

#[tokio::test]
async fn api_keys_guard_every_route_but_health() {
    use sha2::Digest;
    let hash: [u8; 32] = sha2::Sha256::digest(b"s3cret").into();
    let (app, _, _dir) = app(vec![hash], 8, false).await;
    assert_eq!(call(&app, "GET", "/health", None).await.0, StatusCode::OK);
    assert_eq!(call(&app, "GET", "/models", None).await.0, StatusCode::UNAUTHORIZED);
    let with = |key: &str| {
        Request::get("/models").header(header::AUTHORIZATION, format!("Bearer {key}")).body(Body::empty()).unwrap()
    };
    assert_eq!(raw(&app, with("wrong")).await.0, StatusCode::UNAUTHORIZED);
    assert_eq!(raw(&app, with("s3cret")).await.0, StatusCode::OK);
    assert_eq!(otofit::cli::serve::parse_key_hashes(&[hex::encode(hash)]).unwrap(), vec![hash]);
    assert!(otofit::cli::serve::parse_key_hashes(&["zz".into()]).is_err());
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn diagnose_job_writes_a_report_with_figures() {
    let (app, _, _dir) = app(vec![], 8, true).await;
    let model = otofit::sim::Model::new(otofit::sim::ModelConfig::default()).unwrap();
    let mut fx = otofit::sim::Effects::default();
    fx.set("probe_leak", 3e-4).unwrap();
    let x = otofit::sim::simulate(&mut model.runner(), &otofit::sim::Theta::nominal(), &fx).unwrap();
    let params = json!({"x": x, "extend": false, "null_cases": 5, "candidates": ["probe_leak", "probe_offset"]});
    let (status, _, j) = call(&app, "POST", "/jobs", Some(json!({"kind": "diagnose", "params": params}))).await;
    assert_eq!(status, StatusCode::ACCEPTED, "{j}");
    let done = wait(&app, j["id"].as_str().unwrap()).await;
    assert_eq!(done["state"], "succeeded", "{done}");
    let r = &done["result"];
    assert!(["effect_named", "unexplained"].contains(&r["verdict"].as_str().unwrap()), "{r}");
    assert_eq!(r["candidates"][0]["effect"], "probe_leak");
    let fig = r["figures"][0].as_str().unwrap();
    let res = app.clone().oneshot(Request::get(fig).body(Body::empty()).unwrap()).await.unwrap();
    assert_eq!(res.headers()[header::CONTENT_TYPE], "image/svg+xml");
    // The report page links every figure relatively, so each resolves beside it.
    let page = text(&app, r["report"].as_str().unwrap()).await;
    assert!(page.contains("probe_leak"));
    for f in r["figures"].as_array().unwrap() {
        let name = f.as_str().unwrap().rsplit('/').next().unwrap();
        assert!(page.contains(&format!("<img src=\"{name}\"")), "{name} not on the page");
    }
    let (status, _, p) =
        call(&app, "POST", "/jobs", Some(json!({"kind": "diagnose", "params": {"x": [1.0], "candidates": ["wall"]}})))
            .await;
    assert_eq!(status, StatusCode::UNPROCESSABLE_ENTITY);
    assert_eq!(p["errors"][0]["field"], "params.candidates[0]", "{p}");
}

/// An exact job: the likelihood's posterior of the nominal ear without its umbo LDV
/// (`null` features), narrower than the flow's and centred on the ear's eardrum modulus;
/// its params are checked by name.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn exact_job_samples_the_likelihoods_posterior() {
    let (app, _, _dir) = app(vec![], 8, true).await;
    let model = otofit::sim::Model::new(otofit::sim::ModelConfig::default()).unwrap();
    let theta = otofit::sim::Theta::nominal();
    let x = otofit::sim::simulate(&mut model.runner(), &theta, &otofit::sim::Effects::default()).unwrap();
    let x: Vec<Option<f64>> = x.iter().enumerate().map(|(i, v)| (i < 250).then_some(*v)).collect();
    let (status, _, j) = call(&app, "POST", "/jobs", Some(json!({"kind": "exact", "params": {"x": x}}))).await;
    assert_eq!(status, StatusCode::ACCEPTED, "{j}");
    let done = wait(&app, j["id"].as_str().unwrap()).await;
    assert_eq!(done["state"], "succeeded", "{done}");
    assert_eq!(done["params"]["steps"], 100_000, "the default is written out");
    let r = &done["result"];
    let eardrum = |v: &Value| {
        let s = v.as_array().unwrap().iter().find(|s| s["name"] == "E_eardrum").unwrap().clone();
        (s["q05"].as_f64().unwrap(), s["q95"].as_f64().unwrap())
    };
    let (flow, exact) = (eardrum(&r["flow"]), eardrum(&r["exact"]["summaries"]));
    let truth = theta.e_eardrum();
    // Narrower than the flow's, which is calibrated over the prior and so wider (1.1–1.4
    // times on three-measure ears); by more than the few per cent that separate two
    // samples of one distribution, so the flow's own draws would not pass.
    assert!(exact.1 - exact.0 < 0.9 * (flow.1 - flow.0), "flow {flow:?}, likelihood {exact:?}");
    // Its median within 5 % of the truth, as the CLI's test of the same chain: on this
    // noise-free ear the truth can sit just outside a 90 % interval 3.5 % wide (seen:
    // 18.68–19.993 MPa for 20 MPa), the likelihood's ridge with the other parameters
    // skewing the marginal.
    let median =
        r["exact"]["summaries"].as_array().unwrap().iter().find(|s| s["name"] == "E_eardrum").unwrap()["median"]
            .as_f64()
            .unwrap();
    assert!((median / truth - 1.0).abs() < 0.05, "median {median:e}, 90 % {exact:?}");
    assert_eq!(r["differential"].as_array().unwrap().len(), 7, "{r}");
    assert_eq!(r["fit"]["ok"], true, "{r}");
    let bad = |params: Value, field: &'static str| {
        let app = app.clone();
        async move {
            let (status, _, p) = call(&app, "POST", "/jobs", Some(json!({"kind": "exact", "params": params}))).await;
            assert_eq!(status, StatusCode::UNPROCESSABLE_ENTITY, "{p}");
            assert_eq!(p["errors"][0]["field"], field, "{p}");
        }
    };
    bad(json!({"x": x, "steps": 1000}), "params.steps").await;
    bad(json!({"x": vec![Value::Null; 350]}), "params.x").await;
    bad(json!({"x": [1.0, 2.0]}), "params.x").await;
    let unknown = json!({"kind": "exact", "params": {"x": x, "model": "no-such-model"}});
    let (status, _, p) = call(&app, "POST", "/jobs", Some(unknown)).await;
    assert_eq!((status, p["errors"][0]["field"].as_str()), (StatusCode::NOT_FOUND, Some("params.model")), "{p}");
}

/// Blocking HTTP/1.1 over std (the real binary, on a socket).
pub(crate) fn http(port: u16, method: &str, path: &str, body: Option<&str>) -> Option<(u16, Value)> {
    use std::io::{Read, Write};
    let mut s = std::net::TcpStream::connect(("127.0.0.1", port)).ok()?;
    let b = body.unwrap_or("");
    let req = format!(
        "{method} {path} HTTP/1.1\r\nHost: localhost\r\nContent-Type: application/json\r\nContent-Length: {}\r\nConnection: close\r\n\r\n{b}",
        b.len()
    );
    s.write_all(req.as_bytes()).ok()?;
    let mut out = String::new();
    s.read_to_string(&mut out).ok()?;
    let status = out.split(' ').nth(1)?.parse().ok()?;
    let json = out.split("\r\n\r\n").nth(1).and_then(|b| serde_json::from_str(b).ok()).unwrap_or(Value::Null);
    Some((status, json))
}

fn start(port: u16, dir: &std::path::Path) -> std::process::Child {
    let child = std::process::Command::new(env!("CARGO_BIN_EXE_otofit"))
        .args([
            "serve",
            "--addr",
            &format!("127.0.0.1:{port}"),
            "--data-dir",
            dir.to_str().unwrap(),
            "--default-model",
            default_model().to_str().unwrap(),
        ])
        .stdout(std::process::Stdio::null())
        .stderr(std::process::Stdio::null())
        .spawn()
        .unwrap();
    for _ in 0..100 {
        if http(port, "GET", "/health", None).is_some() {
            break;
        }
        std::thread::sleep(std::time::Duration::from_millis(100));
    }
    child
}

#[test]
fn a_job_killed_with_sigkill_is_requeued_and_completes_after_restart() {
    let port = std::net::TcpListener::bind("127.0.0.1:0").unwrap().local_addr().unwrap().port();
    let dir = temp_dir("kill");
    let mut server = start(port, &dir);
    let (status, job) =
        http(port, "POST", "/jobs", Some(r#"{"kind":"simulate","params":{"n":40000,"seed":2}}"#)).unwrap();
    assert_eq!(status, 202, "{job}");
    let id = job["id"].as_str().unwrap().to_string();
    let path = format!("/jobs/{id}");
    for _ in 0..100 {
        if http(port, "GET", &path, None).unwrap().1["state"] == "running" {
            break;
        }
        std::thread::sleep(std::time::Duration::from_millis(50));
    }
    server.kill().unwrap(); // SIGKILL: no chance to clean up
    server.wait().unwrap();
    let mut server = start(port, &dir);
    let mut last = Value::Null;
    for _ in 0..600 {
        last = http(port, "GET", &path, None).unwrap().1;
        if last["state"] == "succeeded" || last["state"] == "failed" {
            break;
        }
        std::thread::sleep(std::time::Duration::from_millis(100));
    }
    server.kill().unwrap();
    server.wait().unwrap();
    assert_eq!(last["state"], "succeeded", "{last}");
    assert_eq!(last["attempts"], 2, "one attempt killed, one completed");
    let x = std::fs::read_to_string(dir.join("datasets").join(&id).join("x.csv")).unwrap();
    assert_eq!(x.lines().count(), 40_001, "the dataset is complete, not a mix of two runs");
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn poison_pill_theta_is_refused_and_extreme_allowed_rows_finish() {
    let (app, _ctx, _dir) = app(vec![], 8, true).await;
    // These values once looped the figure code forever, allocating without bound.
    let pill = json!({"kind": "resimulate", "params": {"theta": [vec![1e-308; 7]]}});
    let (status, _, body) = call(&app, "POST", "/jobs", Some(pill)).await;
    assert_eq!(status, StatusCode::UNPROCESSABLE_ENTITY, "{body}");
    assert!(body.to_string().contains("params.theta[0][0]"), "{body}");
    // Every bad value is named, not only the first, with ranges in short numbers.
    let pill = json!({"kind": "resimulate", "params": {"theta": [vec![1e-308; 14]]}});
    let (status, _, body) = call(&app, "POST", "/jobs", Some(pill)).await;
    assert_eq!(status, StatusCode::UNPROCESSABLE_ENTITY, "{body}");
    // Parameters whose range starts at zero (an elastic drum, no angle, no fluid mass) take it.
    let positive = otofit::sim::PARAMS.iter().filter(|p| p.low > 0.0).count();
    assert_eq!(body["errors"].as_array().unwrap().len(), positive, "{body}");
    assert!(!body.to_string().contains("0000000"), "{body}");
    // A geometry of zero runs nowhere: refused at posting, each value named.
    let mut zero = otofit::sim::Theta::nominal().0.to_vec();
    zero[7..10].fill(0.0);
    let (status, _, body) =
        call(&app, "POST", "/jobs", Some(json!({"kind": "resimulate", "params": {"theta": [zero]}}))).await;
    assert_eq!(status, StatusCode::UNPROCESSABLE_ENTITY, "{body}");
    let fields: Vec<&str> = body["errors"].as_array().unwrap().iter().map(|e| e["field"].as_str().unwrap()).collect();
    assert_eq!(fields, ["params.theta[0][7]", "params.theta[0][8]", "params.theta[0][9]"], "{body}");
    let pill = json!({"kind": "simulate", "params": {"theta": [[1e6, 5e6, 2e6, 2e5, 6e6, 7.5e-5, f64::MAX]]}});
    let (status, _, body) = call(&app, "POST", "/jobs", Some(pill)).await;
    assert_eq!(status, StatusCode::UNPROCESSABLE_ENTITY, "{body}");
    assert!(body.to_string().contains("params.theta[0][6]"), "{body}");
    // The most extreme rows still accepted (the prior box ± one decade) run to the end.
    let lows: Vec<f64> = otofit::sim::params::PARAMS
        .iter()
        .map(|p| if p.scale == otofit::sim::params::Scale::Log10 { p.low / 10.0 } else { p.low })
        .collect();
    let highs: Vec<f64> = otofit::sim::params::PARAMS
        .iter()
        .map(|p| if p.scale == otofit::sim::params::Scale::Log10 { p.high * 10.0 } else { p.high })
        .collect();
    let job = json!({"kind": "resimulate", "params": {"theta": [lows, highs]}});
    let (status, _, body) = call(&app, "POST", "/jobs", Some(job)).await;
    assert_eq!(status, StatusCode::ACCEPTED, "{body}");
    let done = tokio::time::timeout(std::time::Duration::from_secs(60), wait(&app, body["id"].as_str().unwrap()))
        .await
        .expect("the job finishes");
    assert_eq!(done["state"], "succeeded", "{done}");
    assert_eq!(done["result"]["failed_rows"], 0, "{done}");
}

/// The openapi.yaml /infer example (the typical ear, `npe::normal::centre_row`, noise-free,
/// SI units and radians).
pub(crate) fn nominal_request() -> Value {
    spec_examples().into_iter().find(|(p, _)| p == "/infer").unwrap().1
}

fn scaled(mut req: Value, measure: &str, key: &str, k: f64) -> Value {
    let v: Vec<f64> =
        req["measurements"][measure][key].as_array().unwrap().iter().map(|x| x.as_f64().unwrap() * k).collect();
    req["measurements"][measure][key] = json!(v);
    req
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn wrong_units_are_rejected_with_the_field_or_converted_when_declared() {
    let (app, _, _dir) = app(vec![], 8, false).await;
    let deg = 180.0 / std::f64::consts::PI;
    // Degrees sent as radians: rejected, the field named, the unit suggested.
    for measure in ["impedance", "stapes_velocity"] {
        let (status, _, p) = call(&app, "POST", "/infer", Some(scaled(nominal_request(), measure, "phase", deg))).await;
        assert_eq!(status, StatusCode::UNPROCESSABLE_ENTITY, "{p}");
        assert_eq!(p["errors"][0]["field"], format!("measurements.{measure}.phase"), "{p}");
        assert!(p["errors"][0]["message"].as_str().unwrap().contains("phase_unit"), "{p}");
    }
    // Impedance in MΩ, velocity in mm/s/Pa: rejected with a hint.
    let (status, _, p) =
        call(&app, "POST", "/infer", Some(scaled(nominal_request(), "impedance", "magnitude", 1e-6))).await;
    assert_eq!(
        (status, p["errors"][0]["field"].as_str()),
        (StatusCode::UNPROCESSABLE_ENTITY, Some("measurements.impedance.magnitude"))
    );
    assert!(p["errors"][0]["message"].as_str().unwrap().contains("MOhm"), "{p}");
    let (status, _, p) =
        call(&app, "POST", "/infer", Some(scaled(nominal_request(), "stapes_velocity", "magnitude", 1e3))).await;
    assert_eq!(status, StatusCode::UNPROCESSABLE_ENTITY, "{p}");
    assert!(p["errors"][0]["message"].as_str().unwrap().contains("mm/s/Pa"), "{p}");
    // 1e308, absorbance −0.3 and 1.2: rejected.
    let mut huge = nominal_request();
    huge["measurements"]["impedance"]["magnitude"][5] = json!(1e308);
    assert_eq!(call(&app, "POST", "/infer", Some(huge)).await.0, StatusCode::UNPROCESSABLE_ENTITY);
    for bad in [-0.3, 1.2] {
        let mut req = nominal_request();
        req["measurements"]["absorbance"]["values"][7] = json!(bad);
        let (status, _, p) = call(&app, "POST", "/infer", Some(req)).await;
        assert_eq!(status, StatusCode::UNPROCESSABLE_ENTITY, "{p}");
        assert_eq!(p["errors"][0]["field"], "measurements.absorbance.values[7]", "{p}");
    }
    // The same ear in degrees, MΩ and dB re 1 mm/s/Pa, declared: the same answer as in SI.
    let (_, _, si) = call(&app, "POST", "/infer", Some(nominal_request())).await;
    let mut req = scaled(scaled(nominal_request(), "impedance", "phase", deg), "impedance", "magnitude", 1e-6);
    req["measurements"]["impedance"]["phase_unit"] = json!("deg");
    req["measurements"]["impedance"]["magnitude_unit"] = json!("MOhm");
    let db: Vec<f64> = req["measurements"]["stapes_velocity"]["magnitude"]
        .as_array()
        .unwrap()
        .iter()
        .map(|v| 20.0 * (v.as_f64().unwrap() / 1e-3).log10())
        .collect();
    req["measurements"]["stapes_velocity"]["magnitude"] = json!(db);
    req["measurements"]["stapes_velocity"]["magnitude_unit"] = json!("dB re 1 mm/s/Pa");
    let (status, _, other) = call(&app, "POST", "/infer", Some(req.clone())).await;
    assert_eq!(status, StatusCode::OK, "{other}");
    for k in 0..7 {
        let (a, b) =
            (si["parameters"][k]["median"].as_f64().unwrap(), other["parameters"][k]["median"].as_f64().unwrap());
        assert!((a / b - 1.0).abs() < 1e-3, "parameter {k}: {a} vs {b}");
    }
    req["measurements"]["impedance"]["magnitude_unit"] = json!("furlongs");
    let (status, _, p) = call(&app, "POST", "/infer", Some(req)).await;
    assert_eq!(
        (status, p["errors"][0]["field"].as_str()),
        (StatusCode::UNPROCESSABLE_ENTITY, Some("measurements.impedance.magnitude_unit"))
    );
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn every_inference_carries_a_fit_check_and_withdraws_readings_when_the_model_does_not_fit() {
    let (app, _, _dir) = app(vec![], 8, false).await;
    // The typical ear: the model fits it, and no parameter is read as abnormal.
    let (status, _, body) = call(&app, "POST", "/infer", Some(nominal_request())).await;
    assert_eq!(status, StatusCode::OK, "{body}");
    let fit = &body["fit"];
    assert_eq!(fit["ok"], true, "{fit}");
    assert!(fit["reduced_chi2"].as_f64().unwrap() <= fit["threshold"].as_f64().unwrap(), "{fit}");
    for d in body["differential"].as_array().unwrap() {
        assert!(["within", "undetermined"].contains(&d["reading"].as_str().unwrap()), "{d}");
    }
    assert!(body.get("next").is_none());
    // The same ear behind a 0.5 mm probe leak, which the seven parameters cannot mimic.
    let model = otofit::sim::Model::new(otofit::sim::ModelConfig::default()).unwrap();
    let mut fx = otofit::sim::Effects::default();
    fx.set("probe_leak", 0.5e-3).unwrap();
    let x = otofit::sim::simulate(&mut model.runner(), &otofit::sim::Theta::nominal(), &fx).unwrap();
    let n = model.frequencies().len();
    let f = model.frequencies().to_vec();
    let mag = |b: usize| x[b * n..(b + 1) * n].iter().map(|v| 10f64.powf(*v)).collect::<Vec<f64>>();
    let req = json!({"measurements": {
        "stapes_velocity": {"frequencies_hz": f, "magnitude": mag(0), "phase": x[n..2 * n]},
        "impedance": {"frequencies_hz": f, "magnitude": mag(2), "phase": x[3 * n..4 * n]},
        "absorbance": {"frequencies_hz": f, "values": x[4 * n..5 * n]},
    }});
    let (status, _, body) = call(&app, "POST", "/infer", Some(req)).await;
    assert_eq!(status, StatusCode::OK, "{body}");
    assert_eq!(body["fit"]["ok"], false, "{}", body["fit"]);
    assert!(!body["fit"]["bands"].as_array().unwrap().is_empty(), "{}", body["fit"]);
    for d in body["differential"].as_array().unwrap() {
        assert_eq!(d["reading"], "unreliable", "{d}");
        assert!(d["associated_with"].is_null(), "{d}");
    }
    assert_eq!(body["next"]["body"]["kind"], "diagnose", "{}", body["next"]);
}

/// The queue limit holds under concurrent posts (the count and the insert
/// are one statement).
#[tokio::test(flavor = "multi_thread", worker_threads = 4)]
async fn concurrent_job_posts_never_exceed_the_queue_limit() {
    let (app, ctx, _dir) = app(vec![], 8, false).await;
    let job = json!({"kind": "simulate", "params": {"n": 10}});
    for _ in 0..7 {
        assert_eq!(call(&app, "POST", "/jobs", Some(job.clone())).await.0, StatusCode::ACCEPTED);
    }
    for round in 0..3 {
        let posts: Vec<_> = (0..40)
            .map(|_| {
                let (app, job) = (app.clone(), job.clone());
                tokio::spawn(async move { call(&app, "POST", "/jobs", Some(job)).await.0 })
            })
            .collect();
        let mut accepted = 0;
        for p in posts {
            match p.await.unwrap() {
                StatusCode::ACCEPTED => accepted += 1,
                StatusCode::TOO_MANY_REQUESTS => {}
                other => panic!("unexpected {other}"),
            }
        }
        let active: i64 = sqlx::query_scalar("SELECT COUNT(*) FROM jobs WHERE state IN ('queued', 'running')")
            .fetch_one(ctx.store.sqlite().unwrap())
            .await
            .unwrap();
        assert_eq!((round, accepted, active), (round, usize::from(round == 0), 8), "limit 8 with 7 active");
    }
}

/// A diagnose job's model is an id looked up in the store, never a path;
/// `default` is the registered default model; errors name the id, not server paths.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn diagnose_models_are_registered_ids_never_paths() {
    let (app, _, _dir) = app(vec![], 8, false).await;
    let diag =
        |model: Value, x: Value| json!({"kind": "diagnose", "params": {"model": model, "x": x, "extend": false}});
    for bad in ["../../../../etc/model", "/etc/passwd", "a/b", "", &"m".repeat(65)] {
        let (status, _, p) = call(&app, "POST", "/jobs", Some(diag(json!(bad), json!([1.0])))).await;
        assert_eq!(
            (status, p["errors"][0]["field"].as_str()),
            (StatusCode::UNPROCESSABLE_ENTITY, Some("params.model"))
        );
    }
    let (status, _, p) = call(&app, "POST", "/jobs", Some(diag(json!("ghost"), json!([1.0])))).await;
    assert_eq!(status, StatusCode::NOT_FOUND, "{p}");
    assert_eq!(p["errors"][0]["message"], "model 'ghost' is not registered", "{p}");
    // The default model answers by its id before any /infer has loaded it; a wrong-length x
    // is refused now, not when the job runs.
    let (status, _, p) = call(&app, "POST", "/jobs", Some(diag(json!("default"), json!([1.0])))).await;
    assert_eq!((status, p["errors"][0]["field"].as_str()), (StatusCode::UNPROCESSABLE_ENTITY, Some("params.x")));
    assert!(p["errors"][0]["message"].as_str().unwrap().contains("model 'default' takes 350"), "{p}");
    // Jobs queued without that check (an older server) fail naming the id, no path.
    let (_, ctx2, _dir2) = self::app(vec![], 8, false).await;
    let dir = ctx2.data_dir.display().to_string();
    let cases = [
        ("t1", "../../../../etc/model", "model '../../../../etc/model' is not registered"),
        ("t2", "ghost", "model 'ghost' is not registered"),
        ("t3", "default", "params.x has 1 values; model 'default' has 350 features"),
    ];
    for (id, model, _) in cases {
        let params = json!({"model": model, "x": [1.0]});
        assert!(ctx2.store.insert_job_within(id, "diagnose", &params, 1, 8).await.unwrap());
    }
    tokio::spawn(jobs::dispatcher(ctx2.clone()));
    for (id, _, want) in cases {
        let mut job = None;
        for _ in 0..100 {
            let j = ctx2.store.job(id).await.unwrap().unwrap();
            if j.state == "failed" {
                job = Some(j);
                break;
            }
            tokio::time::sleep(std::time::Duration::from_millis(50)).await;
        }
        let err = job.expect("the job fails").error.unwrap();
        assert_eq!(err, want);
        assert!(!err.contains(&dir) && !err.contains("/tmp") && !err.contains(".otofit"), "{err}");
    }
}

/// Everything logged from now on, by any thread of this process, as plain text.
fn capture_logs() -> Arc<std::sync::Mutex<Vec<u8>>> {
    #[derive(Clone)]
    struct Sink(Arc<std::sync::Mutex<Vec<u8>>>);
    impl std::io::Write for Sink {
        fn write(&mut self, b: &[u8]) -> std::io::Result<usize> {
            self.0.lock().unwrap().extend_from_slice(b);
            Ok(b.len())
        }
        fn flush(&mut self) -> std::io::Result<()> {
            Ok(())
        }
    }
    let buf = Arc::new(std::sync::Mutex::new(Vec::new()));
    let sink = Sink(buf.clone());
    let sub = tracing_subscriber::fmt().with_ansi(false).with_writer(move || sink.clone()).finish();
    tracing::subscriber::set_global_default(sub).expect("no other test of this process sets a global subscriber");
    buf
}

/// A job that fails for the server's own reason (its dataset's folder cannot be created:
/// a file is in the way) shows what failed and no path at all; the cause, with the path,
/// goes to the server log with the job's id.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_server_side_failure_names_no_path_and_its_cause_is_logged() {
    let logs = capture_logs();
    let (app, ctx, _dir) = app(vec![], 8, false).await;
    let dir = ctx.dataset_dir("blocked");
    std::fs::create_dir_all(&dir).unwrap();
    std::fs::write(dir.join("parts"), "in the way").unwrap();
    assert!(ctx.store.insert_job_within("blocked", "simulate", &json!({"n": 20}), 1, 8).await.unwrap());
    tokio::spawn(jobs::dispatcher(ctx.clone()));
    let mut job = Value::Null;
    for _ in 0..300 {
        job = call(&app, "GET", "/jobs/blocked", None).await.2;
        if job["state"] == "failed" {
            break;
        }
        tokio::time::sleep(std::time::Duration::from_millis(100)).await;
    }
    assert_eq!(job["state"], "failed", "{job}");
    let err = job["error"].as_str().unwrap();
    assert_eq!(err, "the dataset's folder could not be created", "{job}");
    assert!(!err.contains('/') && !err.contains("DATA_DIR") && !err.contains("parts"), "{err}");
    // The log line of the failure: the job's id, the public message and the cause.
    let line =
        |text: &str| text.lines().find(|l| l.contains("job failed") && l.contains("job=blocked")).map(str::to_string);
    let mut logged = None;
    for _ in 0..50 {
        logged = line(&String::from_utf8_lossy(&logs.lock().unwrap()));
        if logged.is_some() {
            break;
        }
        tokio::time::sleep(std::time::Duration::from_millis(20)).await;
    }
    let logged = logged.expect("the failure is logged with the job's id");
    let parts = dir.join("parts").display().to_string();
    assert!(logged.contains("ERROR") && logged.contains(err) && logged.contains(&parts), "{logged}");
}

/// A running diagnose stops within 30 s of its cancel, in whichever step it is
/// (the null runs, or simulating and training the extended model), and writes nothing after.
/// Alone it stops in ~1 s; a 5 s bound flaked on a loaded host, and a diagnose that ignores
/// the cancel runs on for minutes in every step.
#[test]
fn a_cancelled_diagnose_stops_within_30_s_and_writes_nothing() {
    // Its own runtime, dropped without waiting: a diagnose that ignores the cancel must fail
    // the test now, not when its blocking task ends.
    let rt = tokio::runtime::Builder::new_multi_thread().worker_threads(2).enable_all().build().unwrap();
    let res = rt.block_on(async { tokio::spawn(cancel_diagnoses()).await });
    rt.shutdown_background();
    if let Err(e) = res {
        std::panic::resume_unwind(e.into_panic());
    }
}

/// An ear's features without its umbo velocity (JSON nulls): the shipped model stores no
/// diagnose null for that set of measures, so a diagnose job measures one for the ear, a
/// long step a test can interrupt.
fn without_umbo(model: &otofit::sim::Model, x: &[f64]) -> Vec<Option<f64>> {
    let nf = model.frequencies().len();
    let umbo = otofit::sim::output::MEASURES.iter().position(|m| m.name == "vu_mag").unwrap() * nf;
    x.iter().enumerate().map(|(i, v)| (i < umbo).then_some(*v)).collect()
}

async fn cancel_diagnoses() {
    let (app, ctx, _dir) = app(vec![], 8, true).await;
    let model = otofit::sim::Model::new(otofit::sim::ModelConfig::default()).unwrap();
    let mut fx = otofit::sim::Effects::default();
    fx.set("probe_leak", 3e-4).unwrap();
    let x = otofit::sim::simulate(&mut model.runner(), &otofit::sim::Theta::nominal(), &fx).unwrap();
    // (step the cancel waits for, params): a long null, then a long extension.
    let cases = [
        ("null", json!({"x": without_umbo(&model, &x), "null_cases": 1000, "candidates": ["probe_leak"]})),
        (
            "add",
            json!({"x": x, "null_cases": 5, "candidates": ["probe_leak"], "train_rows": 100000, "max_epochs": 5000}),
        ),
        (
            "training the extended model",
            json!({"x": x, "null_cases": 5, "candidates": ["probe_leak"], "train_rows": 2000, "max_epochs": 5000}),
        ),
    ];
    for (step, params) in cases {
        let (status, _, j) = call(&app, "POST", "/jobs", Some(json!({"kind": "diagnose", "params": params}))).await;
        assert_eq!(status, StatusCode::ACCEPTED, "{j}");
        let id = j["id"].as_str().unwrap().to_string();
        let t0 = std::time::Instant::now();
        loop {
            let (_, _, j) = call(&app, "GET", &format!("/jobs/{id}"), None).await;
            if j["message"].as_str().unwrap_or("").contains(step) {
                break;
            }
            assert!(t0.elapsed().as_secs() < 300 && j["state"] != "succeeded", "never reached '{step}': {j}");
            tokio::time::sleep(std::time::Duration::from_millis(100)).await;
        }
        tokio::time::sleep(std::time::Duration::from_millis(500)).await;
        let (status, _, _) = call(&app, "POST", &format!("/jobs/{id}/cancel"), None).await;
        assert_eq!(status, StatusCode::ACCEPTED);
        let t1 = std::time::Instant::now();
        let done = tokio::time::timeout(std::time::Duration::from_secs(30), wait(&app, &id)).await;
        let done = done.unwrap_or_else(|_| panic!("diagnose still running 30 s after cancel (in '{step}')"));
        assert_eq!(done["state"], "cancelled", "{done}");
        eprintln!("diagnose cancelled in '{step}' after {:.2} s", t1.elapsed().as_secs_f64());
        tokio::time::sleep(std::time::Duration::from_millis(1500)).await;
        assert!(!ctx.data_dir.join("reports").join(&id).exists(), "a report after cancel");
        assert!(!ctx.data_dir.join("models").join(format!("{id}.otofit")).exists(), "a model after cancel");
        assert_eq!(call(&app, "GET", &format!("/models/{id}"), None).await.0, StatusCode::NOT_FOUND);
    }
}

/// A child process killed when the test ends, also when it fails.
struct Reap(std::process::Child);

impl Drop for Reap {
    fn drop(&mut self) {
        let _ = self.0.kill();
        let _ = self.0.wait();
    }
}

impl std::ops::Deref for Reap {
    type Target = std::process::Child;
    fn deref(&self) -> &Self::Target {
        &self.0
    }
}

impl std::ops::DerefMut for Reap {
    fn deref_mut(&mut self) -> &mut Self::Target {
        &mut self.0
    }
}

/// The child's exit status if it ends within `secs`; otherwise it is killed and `None`.
fn exit_within(child: &mut std::process::Child, secs: u64) -> Option<std::process::ExitStatus> {
    for _ in 0..secs * 10 {
        if let Some(status) = child.try_wait().unwrap() {
            return Some(status);
        }
        std::thread::sleep(std::time::Duration::from_millis(100));
    }
    child.kill().unwrap();
    child.wait().unwrap();
    None
}

/// One process per data directory; a second `otofit serve` on it refuses to
/// start and says why.
#[test]
fn a_second_server_on_the_same_data_dir_refuses_to_start() {
    let port = std::net::TcpListener::bind("127.0.0.1:0").unwrap().local_addr().unwrap().port();
    let dir = temp_dir("lock");
    let mut first = Reap(start(port, &dir));
    assert_eq!(http(port, "GET", "/health", None).unwrap().0, 200);
    let port2 = std::net::TcpListener::bind("127.0.0.1:0").unwrap().local_addr().unwrap().port();
    let mut second = std::process::Command::new(env!("CARGO_BIN_EXE_otofit"))
        .args(["serve", "--addr", &format!("127.0.0.1:{port2}"), "--data-dir", dir.to_str().unwrap()])
        .args(["--default-model", default_model().to_str().unwrap()])
        .stdout(std::process::Stdio::null())
        .stderr(std::process::Stdio::piped())
        .spawn()
        .unwrap();
    let status = exit_within(&mut second, 10);
    first.kill().unwrap();
    first.wait().unwrap();
    let mut err = String::new();
    std::io::Read::read_to_string(&mut second.stderr.take().unwrap(), &mut err).unwrap();
    assert!(status.is_some_and(|s| !s.success()), "the second server started");
    assert!(err.contains("is in use by another otofit process") && err.contains(&first.id().to_string()), "{err}");
    // In-process too; the lock goes with the process (killed above), so the dir is free again.
    let rt = tokio::runtime::Runtime::new().unwrap();
    let ctx = rt.block_on(otofit::cli::serve::open(&dir, &default_model(), 8)).unwrap();
    let again = rt.block_on(otofit::cli::serve::open(&dir, &default_model(), 8));
    assert!(again.err().unwrap().to_string().contains("in use"));
    drop(ctx);
    assert!(rt.block_on(otofit::cli::serve::open(&dir, &default_model(), 8)).is_ok());
}

/// The nominal ear's impedance and absorbance as a WBT device reports them: its own grid
/// (1/12 octave from `f0`), magnitude in `unit`, phase in degrees.
fn wbt_request(f0: f64, f1: f64) -> Value {
    let model = otofit::sim::Model::new(otofit::sim::ModelConfig::default()).unwrap();
    let x = otofit::sim::simulate(&mut model.runner(), &otofit::sim::Theta::nominal(), &Default::default()).unwrap();
    let grid = model.frequencies().to_vec();
    let n = grid.len();
    let mut device: Vec<f64> = (0..).map(|k| f0 * 2f64.powf(k as f64 / 12.0)).take_while(|f| *f < f1 * 0.99).collect();
    device.push(f1);
    let on = |b: usize| otofit::sim::output::interpolate_log_f(&grid, &x[b * n..(b + 1) * n], &device);
    json!({"measurements": {
        "impedance": {
            "frequencies_hz": device,
            "magnitude": on(2).iter().map(|v| 10f64.powf(*v) / 1e5).collect::<Vec<f64>>(),
            "magnitude_unit": "cgs",
            "phase": on(3).iter().map(|v| v.to_degrees()).collect::<Vec<f64>>(),
            "phase_unit": "deg",
        },
        "absorbance": {"frequencies_hz": device, "values": on(4)},
    }})
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn wideband_tympanometry_alone_on_a_sub_band_gets_a_posterior() {
    let (app, _, _dir) = app(vec![], 8, false).await;
    let (status, _, body) = call(&app, "POST", "/infer", Some(wbt_request(226.0, 8000.0))).await;
    assert_eq!(status, StatusCode::OK, "{body}");
    assert_eq!(body["inputs"]["used"], json!(["impedance", "absorbance"]));
    let band = body["inputs"]["band_hz"]["zec_mag"].as_array().unwrap();
    assert!(band[0].as_f64().unwrap() > 226.0 && band[1].as_f64().unwrap() == 8000.0, "{band:?}");
    assert!(body["inputs"]["band_hz"].get("vst_mag").is_none());
    assert_eq!(body["fit"]["ok"], true, "{}", body["fit"]);
    for d in body["differential"].as_array().unwrap() {
        assert!(["within", "undetermined"].contains(&d["reading"].as_str().unwrap()), "{d}");
    }
    // A WBT that stops at 6 kHz is still inside what the model was trained for.
    let (status, _, body) = call(&app, "POST", "/infer", Some(wbt_request(250.0, 6000.0))).await;
    assert_eq!(status, StatusCode::OK, "{body}");
    // 500–3000 Hz leaves out more than training did: refused, never extrapolated.
    let (status, _, p) = call(&app, "POST", "/infer", Some(wbt_request(500.0, 3000.0))).await;
    assert_eq!(status, StatusCode::UNPROCESSABLE_ENTITY, "{p}");
    assert_eq!(p["errors"][0]["field"], "measurements.impedance.frequencies_hz", "{p}");
}

/// A clinic's inputs: wideband tympanometry plus umbo LDV through the canal (in dB re
/// 1 mm/s/Pa and degrees, as vibrometer software shows them), from the nominal ear.
fn clinic_request() -> Value {
    let model = otofit::sim::Model::new(otofit::sim::ModelConfig::default()).unwrap();
    let x = otofit::sim::simulate(&mut model.runner(), &otofit::sim::Theta::nominal(), &Default::default()).unwrap();
    let n = model.frequencies().len();
    let mut req = wbt_request(226.0, 8000.0);
    req["measurements"]["umbo_velocity"] = json!({
        "frequencies_hz": model.frequencies(),
        "magnitude": x[5 * n..6 * n].iter().map(|v| 20.0 * (v + 3.0)).collect::<Vec<f64>>(),
        "magnitude_unit": "dB re 1 mm/s/Pa",
        "phase": x[6 * n..].iter().map(|v| v.to_degrees()).collect::<Vec<f64>>(),
        "phase_unit": "deg",
    });
    req
}

/// Every measure over the whole grid, SI units and radians, from the nominal ear.
fn full_request() -> Value {
    let model = otofit::sim::Model::new(otofit::sim::ModelConfig::default()).unwrap();
    let x = otofit::sim::simulate(&mut model.runner(), &otofit::sim::Theta::nominal(), &Default::default()).unwrap();
    let (f, n) = (model.frequencies(), model.frequencies().len());
    let block = |k: usize| x[k * n..(k + 1) * n].to_vec();
    let magnitude = |k: usize| block(k).iter().map(|v| 10f64.powf(*v)).collect::<Vec<f64>>();
    json!({"measurements": {
        "stapes_velocity": {"frequencies_hz": f, "magnitude": magnitude(0), "phase": block(1)},
        "impedance": {"frequencies_hz": f, "magnitude": magnitude(2), "phase": block(3)},
        "absorbance": {"frequencies_hz": f, "values": block(4)},
        "umbo_velocity": {"frequencies_hz": f, "magnitude": magnitude(5), "phase": block(6)},
    }})
}

/// The shipped model holds a full-measure flow and flows for the study's three measures,
/// for wideband tympanometry and for WBT with umbo LDV (each whole band, and part of it): an
/// ear with every measure over the whole band is answered by the first, an ear of one of
/// those sets by its set's flow, an ear of another set by the main (masked) flow, and
/// GET /models/{id} lists each with its own calibration.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn an_ear_with_every_measure_is_answered_by_the_full_measure_flow() {
    let (app, _, _dir) = app(vec![], 8, false).await;
    let full = full_request();
    let (status, _, a) = call(&app, "POST", "/infer", Some(full.clone())).await;
    assert_eq!(status, StatusCode::OK, "{a}");
    assert_eq!(a["inputs"]["flow"], "full-measure", "{}", a["inputs"]);
    assert_eq!(a["fit"]["ok"], true, "{}", a["fit"]);
    // /log_prob gives the density of the flow that answered.
    let draws = a["samples"].as_array().unwrap()[..3].to_vec();
    let mut lp_req = full.clone();
    lp_req["theta"] = json!(draws);
    let (status, _, lp) = call(&app, "POST", "/log_prob", Some(lp_req)).await;
    assert_eq!((status, lp["inputs"]["flow"].as_str()), (StatusCode::OK, Some("full-measure")), "{lp}");
    // Without umbo velocity: the study's three measures, answered by their own flow.
    let mut without_umbo = full;
    without_umbo["measurements"].as_object_mut().unwrap().remove("umbo_velocity");
    let (status, _, b) = call(&app, "POST", "/infer", Some(without_umbo.clone())).await;
    assert_eq!((status, b["inputs"]["flow"].as_str()), (StatusCode::OK, Some("measure-set")), "{}", b["inputs"]);
    assert_eq!(b["fit"]["ok"], true, "{}", b["fit"]);
    let mut wbt = without_umbo;
    wbt["measurements"].as_object_mut().unwrap().remove("stapes_velocity");
    let (status, _, c) = call(&app, "POST", "/infer", Some(wbt.clone())).await;
    assert_eq!((status, c["inputs"]["flow"].as_str()), (StatusCode::OK, Some("measure-set")), "{}", c["inputs"]);
    assert_eq!(c["fit"]["ok"], true, "{}", c["fit"]);
    // The same WBT ear above 300 Hz only, as a device exports it: the WBT flow trained
    // with band masks; WBT with umbo LDV from 226 Hz: its own band-masked flow; an ear of
    // another set of measures: the masked flow.
    let mut cut = wbt;
    for m in ["impedance", "absorbance"] {
        let block = cut["measurements"][m].as_object_mut().unwrap();
        let keep: Vec<usize> = (0..block["frequencies_hz"].as_array().unwrap().len())
            .filter(|&i| block["frequencies_hz"][i].as_f64().unwrap() >= 300.0)
            .collect();
        for (_, v) in block.iter_mut() {
            *v = json!(keep.iter().map(|&i| v[i].clone()).collect::<Vec<_>>());
        }
    }
    let (status, _, e) = call(&app, "POST", "/infer", Some(cut)).await;
    assert_eq!((status, e["inputs"]["flow"].as_str()), (StatusCode::OK, Some("measure-set")), "{}", e["inputs"]);
    assert_eq!(e["fit"]["ok"], true, "{}", e["fit"]);
    let (status, _, e) = call(&app, "POST", "/infer", Some(clinic_request())).await;
    assert_eq!((status, e["inputs"]["flow"].as_str()), (StatusCode::OK, Some("measure-set")), "{}", e["inputs"]);
    assert_eq!(e["fit"]["ok"], true, "{}", e["fit"]);
    let mut other = full_request();
    other["measurements"].as_object_mut().unwrap().remove("absorbance");
    let (status, _, e) = call(&app, "POST", "/infer", Some(other)).await;
    assert_eq!((status, e["inputs"]["flow"].as_str()), (StatusCode::OK, Some("main")), "{}", e["inputs"]);
    let (status, _, m) = call(&app, "GET", "/models/default", None).await;
    assert_eq!(status, StatusCode::OK, "{m}");
    let f = &m["full_measure_flow"];
    let t = f["temperature"].as_f64().unwrap_or(f64::NAN);
    assert!((0.5..=2.0).contains(&t) && f["fit_null"].is_object(), "{f}");
    assert_ne!(f["training"], m["training"], "the full-measure flow's own training, not the main flow's");
    let sets = m["measure_set_flows"].as_array().cloned().unwrap_or_default();
    assert_eq!(sets.len(), 6, "{m}");
    assert_eq!(sets[0]["measures"], json!(["stapes_velocity", "impedance", "absorbance"]));
    assert_eq!(sets[1]["measures"], json!(["impedance", "absorbance"]));
    assert_eq!(sets[2]["measures"], json!(["impedance", "absorbance"]));
    assert_eq!(sets[3]["measures"], json!(["impedance", "absorbance", "umbo_velocity"]));
    assert_eq!(sets[4]["measures"], json!(["impedance", "absorbance", "umbo_velocity"]));
    assert_eq!(sets[5]["measures"], json!(["impedance", "absorbance", "umbo_velocity"]));
    let partial: Vec<bool> = sets.iter().map(|s| s["accepts_partial_bands"].as_bool().unwrap()).collect();
    assert_eq!(partial, [false, false, true, true, false, true]);
    // The two band-masked flows of WBT with umbo velocity: cuts of up to a quarter of the
    // grid, and of up to two points (a device's export from 226 Hz).
    let grid: Vec<f64> = serde_json::from_value(m["frequencies_hz"].clone()).unwrap();
    let reach = |k: usize| json!([grid[k], grid[grid.len() - 1 - k]]);
    let reaches: Vec<_> = sets.iter().map(|s| s.get("band_must_reach_hz").cloned()).collect();
    let quarter = grid.len() / 4;
    assert_eq!(reaches, [None, None, Some(reach(quarter)), Some(reach(quarter)), None, Some(reach(2))], "{m}");
    for set in &sets {
        assert!(set["fit_null"].is_object() && set["training"] != f["training"], "{set}");
    }
    for pair in sets.windows(2) {
        assert_ne!(pair[0]["training"], pair[1]["training"]);
    }
}

/// Umbo velocity: WBT + umbo LDV is answered, the umbo narrows the
/// posterior of the tissue parameters on average, and its fields are checked by name.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn wideband_tympanometry_with_umbo_ldv_gets_a_narrower_posterior() {
    let (app, _, _dir) = app(vec![], 8, false).await;
    let (status, _, wbt) = call(&app, "POST", "/infer", Some(wbt_request(226.0, 8000.0))).await;
    assert_eq!(status, StatusCode::OK, "{wbt}");
    let (status, _, both) = call(&app, "POST", "/infer", Some(clinic_request())).await;
    assert_eq!(status, StatusCode::OK, "{both}");
    assert_eq!(both["inputs"]["used"], json!(["impedance", "umbo_velocity", "absorbance"]));
    assert_eq!(both["fit"]["ok"], true, "{}", both["fit"]);
    for d in both["differential"].as_array().unwrap() {
        assert!(["within", "undetermined"].contains(&d["reading"].as_str().unwrap()), "{d}");
    }
    // Information as the 90 % interval's width in decades (the CV of a posterior that
    // spans decades is ruled by its tail, not by its width).
    let width = |b: &Value| {
        let p = b["parameters"].as_array().unwrap();
        p[..7].iter().map(|s| (s["q95"].as_f64().unwrap() / s["q05"].as_f64().unwrap()).log10()).sum::<f64>() / 7.0
    };
    let (a, u) = (width(&wbt), width(&both));
    eprintln!("mean 90 % width of the tissue parameters, decades: WBT {a:.3}, WBT + umbo {u:.3}");
    assert!(u < a * 0.95, "the umbo adds no information: mean 90 % width {a:.3} → {u:.3} decades");
    // Phases sent as degrees but declared radians are refused, naming the umbo's field.
    let mut bad = clinic_request();
    bad["measurements"]["umbo_velocity"]["phase_unit"] = json!("rad");
    let (status, _, p) = call(&app, "POST", "/infer", Some(bad)).await;
    assert_eq!(status, StatusCode::UNPROCESSABLE_ENTITY, "{p}");
    assert_eq!(p["errors"][0]["field"], "measurements.umbo_velocity.phase", "{p}");
}

/// A router whose /infer has the given limits (its own data dir).
async fn limited_app(limits: otofit::http::InferLimits) -> (Router, TempDir) {
    let dir = temp_dir("limits");
    let ctx = otofit::cli::serve::open_with(&dir, &default_model(), 8, limits).await.unwrap();
    (router(AppState::new(ctx, vec![])), dir)
}

/// /infer runs at most `concurrency` at once with a short queue, answers 503 +
/// Retry-After (problem+json) beyond it, and 503 once past its deadline.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn infer_is_bounded_in_concurrency_and_time() {
    use otofit::http::InferLimits;
    let secs = std::time::Duration::from_secs;
    let mut req = nominal_request();
    req["samples"] = json!(20000);
    req["return_samples"] = json!(false);
    let (app, _dir) = limited_app(InferLimits { concurrency: 1, queue: 1, deadline: secs(60) }).await;
    let calls: Vec<_> = (0..8)
        .map(|_| {
            let (app, req) = (app.clone(), req.clone());
            tokio::spawn(async move { call(&app, "POST", "/infer", Some(req)).await })
        })
        .collect();
    let (mut ok, mut busy) = (0, 0);
    for c in calls {
        let (status, headers, body) = c.await.unwrap();
        match status {
            StatusCode::OK => ok += 1,
            StatusCode::SERVICE_UNAVAILABLE => {
                busy += 1;
                assert_eq!(headers[header::CONTENT_TYPE], "application/problem+json");
                assert_eq!(headers[header::RETRY_AFTER], "1");
                assert!(body["detail"].as_str().unwrap().contains("1 inferences running and 1 waiting"), "{body}");
            }
            other => panic!("{other}: {body}"),
        }
    }
    assert!(ok >= 2 && busy >= 1 && ok + busy == 8, "{ok} answered, {busy} turned away");
    // Past the deadline: 503 with Retry-After, not a connection held open.
    let (app, _dir2) =
        limited_app(InferLimits { concurrency: 1, queue: 1, deadline: std::time::Duration::from_millis(5) }).await;
    let (status, headers, body) = call(&app, "POST", "/infer", Some(req)).await;
    assert_eq!(status, StatusCode::SERVICE_UNAVAILABLE, "{body}");
    assert!(headers.contains_key(header::RETRY_AFTER));
    assert!(body["detail"].as_str().unwrap().contains("deadline"), "{body}");
}

/// `otofit serve` on a free loopback port with the default model and `extra` flags, its
/// stdout to `stdout`, once it answers /health; the data directory lives as long as the
/// returned guard.
fn serve_on_a_free_port(tag: &str, extra: &[&str], stdout: std::process::Stdio) -> (Reap, u16, TempDir) {
    let port = std::net::TcpListener::bind("127.0.0.1:0").unwrap().local_addr().unwrap().port();
    let dir = temp_dir(tag);
    let server = Reap(
        std::process::Command::new(env!("CARGO_BIN_EXE_otofit"))
            .args(["serve", "--addr", &format!("127.0.0.1:{port}"), "--data-dir", dir.to_str().unwrap()])
            .args(["--default-model", default_model().to_str().unwrap()])
            .args(extra)
            .stdout(stdout)
            .stderr(std::process::Stdio::null())
            .spawn()
            .unwrap(),
    );
    for _ in 0..100 {
        if http(port, "GET", "/health", None).is_some() {
            break;
        }
        std::thread::sleep(std::time::Duration::from_millis(100));
    }
    (server, port, dir)
}

/// `serve`'s log redirected to a file (a pipe here, as under systemd or a container
/// runtime) carries no ANSI colour codes: a collector reads plain text.
#[test]
fn a_redirected_server_log_is_plain_text() {
    use std::io::Read;
    let (mut server, port, _dir) = serve_on_a_free_port("ansi", &[], std::process::Stdio::piped());
    assert!(http(port, "GET", "/models", None).is_some(), "the server answers");
    std::process::Command::new("kill").args(["-TERM", &server.id().to_string()]).status().unwrap();
    assert!(exit_within(&mut server, 10).is_some(), "stopped after SIGTERM");
    let mut log = String::new();
    server.stdout.take().unwrap().read_to_string(&mut log).unwrap();
    assert!(log.contains("otofit serving"), "the start-up line was logged: {log:?}");
    assert!(!log.contains('\u{1b}'), "ANSI escape in a redirected log: {log:?}");
}

/// A connection that sends half a request is closed after the idle timeout, and
/// does not hold up a SIGTERM shutdown.
#[test]
fn half_sent_requests_are_dropped_and_do_not_delay_shutdown() {
    use std::io::{Read, Write};
    let (mut server, port, _dir) =
        serve_on_a_free_port("idle", &["--idle-timeout", "1", "--infer-deadline", "0.5"], std::process::Stdio::null());
    let half = |bytes: &str| {
        let mut s = std::net::TcpStream::connect(("127.0.0.1", port)).unwrap();
        s.set_read_timeout(Some(std::time::Duration::from_secs(10))).unwrap();
        s.write_all(bytes.as_bytes()).unwrap();
        s
    };
    // Half the headers; then full headers and half the body.
    for bytes in [
        "POST /jobs HTTP/1.1\r\nHost: localhost\r\nContent-Le",
        "POST /jobs HTTP/1.1\r\nHost: localhost\r\nContent-Type: application/json\r\nContent-Length: 100\r\n\r\n{\"kind\":",
    ] {
        let t0 = std::time::Instant::now();
        let mut s = half(bytes);
        let mut out = Vec::new();
        let _ = s.read_to_end(&mut out); // EOF (or a reset) once the server lets go
        let waited = t0.elapsed().as_secs_f64();
        assert!(waited < 5.0, "held {waited:.1} s: {}", String::from_utf8_lossy(&out));
    }
    // SIGTERM with a half-sent request open: the server still exits promptly.
    let _open = half("GET /models HTTP/1.1\r\nHo");
    std::thread::sleep(std::time::Duration::from_millis(200));
    let t0 = std::time::Instant::now();
    std::process::Command::new("kill").args(["-TERM", &server.id().to_string()]).status().unwrap();
    let exited = exit_within(&mut server, 10);
    assert!(exited.is_some_and(|s| s.success()), "not stopped 10 s after SIGTERM: {exited:?}");
    eprintln!("exited {:.2} s after SIGTERM", t0.elapsed().as_secs_f64());
}

/// Contract gaps. Every error is problem+json (405, extractor 400s naming the
/// parameter); list limits out of range are refused, not clamped; the Bearer scheme is
/// case-insensitive; a body is one JSON value of exactly application/json.
#[tokio::test]
async fn contract_gaps_are_closed() {
    use sha2::Digest;
    let (app, _, _dir) = app(vec![], 8, false).await;
    let problem = |h: &axum::http::HeaderMap| h[header::CONTENT_TYPE] == "application/problem+json";
    let (status, headers, p) = call(&app, "DELETE", "/jobs", None).await;
    assert_eq!(status, StatusCode::METHOD_NOT_ALLOWED);
    assert!(problem(&headers) && headers.contains_key(header::ALLOW), "{headers:?}");
    assert_eq!(p["status"], 405, "{p}");
    let allowed = p["detail"].as_str().unwrap().rsplit("allowed: ").next().unwrap().to_string();
    assert!(allowed == "GET, POST" || allowed == "POST, GET", "{p}");
    let (status, headers, p) = call(&app, "PUT", "/infer", None).await;
    assert_eq!(status, StatusCode::METHOD_NOT_ALLOWED);
    assert!(p["detail"].as_str().unwrap().ends_with("allowed: POST"), "{p}");
    assert_eq!(headers[header::ALLOW], "POST", "{headers:?}");
    let (status, headers, p) = call(&app, "GET", "/jobs?limit=abc", None).await;
    assert_eq!((status, problem(&headers)), (StatusCode::BAD_REQUEST, true), "{p}");
    assert_eq!(p["errors"][0]["field"], "limit", "{p}");
    for bad in ["0", "-5", "1001"] {
        let (status, headers, p) = call(&app, "GET", &format!("/jobs?limit={bad}"), None).await;
        assert_eq!((status, problem(&headers)), (StatusCode::UNPROCESSABLE_ENTITY, true), "limit={bad}: {p}");
        assert_eq!(p["errors"][0]["field"], "limit", "{p}");
    }
    assert_eq!(call(&app, "GET", "/jobs?limit=1000", None).await.0, StatusCode::OK);
    let post = |ct: &str, body: &str| {
        Request::post("/jobs").header(header::CONTENT_TYPE, ct).body(Body::from(body.to_string())).unwrap()
    };
    let job = r#"{"kind":"simulate","params":{"n":3}}"#;
    let (status, headers, p) = raw(&app, post("application/json", &format!("{job} trailing"))).await;
    assert_eq!((status, problem(&headers)), (StatusCode::BAD_REQUEST, true), "{p}");
    assert_eq!(raw(&app, post("application/json", &format!("{job}{job}"))).await.0, StatusCode::BAD_REQUEST);
    for ct in ["application/jsonx", "application/json-patch+json", "text/json"] {
        let (status, headers, _) = raw(&app, post(ct, job)).await;
        assert_eq!((status, problem(&headers)), (StatusCode::UNSUPPORTED_MEDIA_TYPE, true), "{ct}");
    }
    for ct in ["application/json; charset=utf-8", "Application/JSON"] {
        assert_eq!(raw(&app, post(ct, &format!("{job}\n"))).await.0, StatusCode::ACCEPTED, "{ct}");
    }
    let twice = json!({"kind": "simulate", "params": {"n": 3, "vary": ["probe_leak", "probe_leak"]}});
    let (status, _, p) = call(&app, "POST", "/jobs", Some(twice)).await;
    assert_eq!((status, p["errors"][0]["field"].as_str()), (StatusCode::UNPROCESSABLE_ENTITY, Some("params.vary[1]")));
    let null = json!({"kind": "diagnose", "params": {"model": null, "x": [1.0]}});
    let (status, _, p) = call(&app, "POST", "/jobs", Some(null)).await;
    assert_eq!((status, p["errors"][0]["field"].as_str()), (StatusCode::UNPROCESSABLE_ENTITY, Some("params.model")));
    let hash: [u8; 32] = sha2::Sha256::digest(b"s3cret").into();
    let (keyed, _, _dir2) = self::app(vec![hash], 8, false).await;
    for scheme in ["Bearer", "bearer", "BEARER"] {
        let req = Request::get("/models").header(header::AUTHORIZATION, format!("{scheme} s3cret"));
        assert_eq!(raw(&keyed, req.body(Body::empty()).unwrap()).await.0, StatusCode::OK, "{scheme}");
    }
    let req = Request::get("/models").header(header::AUTHORIZATION, "Basic s3cret").body(Body::empty()).unwrap();
    let (status, headers, _) = raw(&keyed, req).await;
    assert_eq!((status, problem(&headers)), (StatusCode::UNAUTHORIZED, true));
}

/// An over-long request target (414) or too many or too large header fields
/// (431) get problems, not hyper's empty bodies (which remain past hyper's own bounds).
#[tokio::test]
async fn long_targets_and_large_heads_get_problems() {
    let (app, _, _dir) = app(vec![], 8, false).await;
    let problem = |h: &axum::http::HeaderMap| h[header::CONTENT_TYPE] == "application/problem+json";
    let max = otofit::http::MAX_URI;
    let uri = |n: usize| format!("/jobs?state={}", "q".repeat(n - "/jobs?state=".len()));
    let (status, _, _) = raw(&app, Request::get(uri(max)).body(Body::empty()).unwrap()).await;
    assert_eq!(status, StatusCode::UNPROCESSABLE_ENTITY, "at the bound: answered (a bad state)");
    let (status, headers, p) = raw(&app, Request::get(uri(max + 1)).body(Body::empty()).unwrap()).await;
    assert_eq!((status, problem(&headers)), (StatusCode::URI_TOO_LONG, true), "{p}");
    let (fields, bytes) = otofit::http::MAX_HEADERS;
    let mut many = Request::get("/jobs");
    for i in 0..=fields {
        many = many.header(format!("x-h{i}"), "v");
    }
    let (status, headers, p) = raw(&app, many.body(Body::empty()).unwrap()).await;
    assert_eq!((status, problem(&headers)), (StatusCode::REQUEST_HEADER_FIELDS_TOO_LARGE, true), "{p}");
    let big = Request::get("/jobs").header("x-big", "b".repeat(bytes)).body(Body::empty()).unwrap();
    let (status, headers, p) = raw(&app, big).await;
    assert_eq!((status, problem(&headers)), (StatusCode::REQUEST_HEADER_FIELDS_TOO_LARGE, true), "{p}");
    let fine = Request::get("/jobs").header("x-big", "b".repeat(bytes / 2)).body(Body::empty()).unwrap();
    assert_eq!(raw(&app, fine).await.0, StatusCode::OK);
}

/// A simulate job that fails leaves no temporary files, and a restart removes
/// those of runs that were killed.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn failed_and_killed_simulate_jobs_leave_no_temporary_files() {
    let (_, ctx, _dir) = app(vec![], 8, false).await;
    // x.csv taken by a directory: the final rename fails after the rows were written.
    let dir = ctx.dataset_dir("blocked");
    std::fs::create_dir_all(dir.join("x.csv").join("in-the-way")).unwrap();
    assert!(ctx.store.insert_job_within("blocked", "simulate", &json!({"n": 20}), 1, 8).await.unwrap());
    tokio::spawn(jobs::dispatcher(ctx.clone()));
    let mut job = None;
    for _ in 0..300 {
        let j = ctx.store.job("blocked").await.unwrap().unwrap();
        if j.state == "failed" {
            job = Some(j);
            break;
        }
        tokio::time::sleep(std::time::Duration::from_millis(100)).await;
    }
    let job = job.expect("the job fails");
    let left: Vec<_> = std::fs::read_dir(&dir).unwrap().flatten().map(|e| e.file_name()).collect();
    assert!(!left.iter().any(|n| n.to_string_lossy().ends_with(".tmp")), "{left:?} after {:?}", job.error);
    // Leftovers of a killed run go at the next start.
    let data = temp_dir("tmp");
    std::fs::create_dir_all(data.join("datasets").join("killed")).unwrap();
    std::fs::write(data.join("datasets").join("killed").join("x.csv.tmp"), "1,2\n").unwrap();
    let staging = data.join("datasets").join("killed").join(".attempt-0123456789abcdef");
    std::fs::create_dir_all(&staging).unwrap();
    std::fs::write(staging.join("x.csv.tmp"), "1,2\n").unwrap();
    let _ctx = otofit::cli::serve::open(&data, &default_model(), 8).await.unwrap();
    assert!(!data.join("datasets").join("killed").join("x.csv.tmp").exists());
    assert!(!staging.exists(), "a killed attempt's staging folder goes too");
}

/// SIGTERM during a diagnose: the process exits within seconds (not after its
/// 60 s grace), the job goes back to the queue without counting the attempt, nothing written.
#[test]
fn sigterm_during_a_diagnose_exits_promptly_and_requeues_it() {
    let port = std::net::TcpListener::bind("127.0.0.1:0").unwrap().local_addr().unwrap().port();
    let dir = temp_dir("term");
    let mut server = Reap(start(port, &dir));
    let model = otofit::sim::Model::new(otofit::sim::ModelConfig::default()).unwrap();
    let x = otofit::sim::simulate(&mut model.runner(), &otofit::sim::Theta::nominal(), &Default::default()).unwrap();
    // One candidate, as the cancel test: a stop waits for the null ear in flight, and with
    // every candidate that ear's fits took over 15 s on two cores under the test suite's load.
    let params = json!({"x": without_umbo(&model, &x), "null_cases": 1000, "candidates": ["probe_leak"]});
    let body = json!({"kind": "diagnose", "params": params}).to_string();
    let (status, job) = http(port, "POST", "/jobs", Some(&body)).unwrap();
    assert_eq!(status, 202, "{job}");
    let path = format!("/jobs/{}", job["id"].as_str().unwrap());
    for _ in 0..300 {
        if http(port, "GET", &path, None).unwrap().1["message"].as_str().unwrap_or("").contains("null") {
            break;
        }
        std::thread::sleep(std::time::Duration::from_millis(100));
    }
    let t0 = std::time::Instant::now();
    std::process::Command::new("kill").args(["-TERM", &server.id().to_string()]).status().unwrap();
    let exited = exit_within(&mut server, 15);
    let secs = t0.elapsed().as_secs_f64();
    assert!(exited.is_some_and(|s| s.success()) && secs < 10.0, "{exited:?} after {secs:.1} s");
    let mut server = Reap(start(port, &dir));
    let (_, after) = http(port, "GET", &path, None).unwrap();
    server.kill().unwrap();
    server.wait().unwrap();
    assert!(["queued", "running"].contains(&after["state"].as_str().unwrap()), "{after}");
    assert!(after["attempts"].as_i64().unwrap() <= 1, "the interrupted attempt is not counted: {after}");
    assert!(!dir.join("reports").join(job["id"].as_str().unwrap()).exists());
    eprintln!("exited {secs:.2} s after SIGTERM");
}

/// A model that cannot be loaded is reported by its id; the file's path stays
/// in the server log.
#[tokio::test]
async fn unloadable_models_do_not_show_server_paths() {
    let (app, ctx, _dir) = app(vec![], 8, false).await;
    let path = ctx.data_dir.join("models").join("broken.otofit");
    std::fs::create_dir_all(path.parent().unwrap()).unwrap();
    std::fs::write(&path, b"not a checkpoint").unwrap();
    ctx.store.add_model("broken", &path.display().to_string(), false, None).await.unwrap();
    let (status, _, m) = call(&app, "GET", "/models/broken", None).await;
    assert_eq!(status, StatusCode::OK);
    assert_eq!(m["error"], "model 'broken' cannot be loaded (the server log says why)", "{m}");
    let (_, _, all) = call(&app, "GET", "/models", None).await;
    let dir = ctx.data_dir.display().to_string();
    assert!(!all.to_string().contains(&dir) && !all.to_string().contains("/tmp"), "{all}");
    let (status, _, p) =
        call(&app, "POST", "/jobs", Some(json!({"kind": "diagnose", "params": {"model": "broken", "x": [1.0]}}))).await;
    assert_eq!(status, StatusCode::UNPROCESSABLE_ENTITY);
    assert_eq!(p["errors"][0]["message"], "model 'broken' cannot be loaded (the server log says why)", "{p}");
}

/// Every operation documents its other errors (401, 405, 408, 500) as
/// problem+json, and those answers are problem+json.
#[tokio::test]
async fn every_operation_documents_its_errors_as_problems() {
    let ops = spec_operations().len();
    let defaults = SPEC.lines().filter(|l| *l == "        default: { $ref: \"#/components/responses/Error\" }").count();
    assert_eq!(defaults, ops, "one default (error) response per operation");
    use sha2::Digest;
    let (app, _, _dir) = app(vec![sha2::Sha256::digest(b"k").into()], 8, false).await;
    for (method, path) in ROUTES {
        let uri = path.replace("{id}", "x").replace("{name}", "report.html").replace("{file}", "x.csv");
        let (status, headers, p) = call(&app, &method.to_uppercase(), &uri, None).await;
        let want = if path == "/health" { StatusCode::OK } else { StatusCode::UNAUTHORIZED };
        assert_eq!(status, want, "{method} {path}");
        if status != StatusCode::OK {
            assert_eq!(headers[header::CONTENT_TYPE], "application/problem+json", "{method} {path}");
            assert_eq!(p["status"], 401);
        }
        let (status, headers, _) = call(&app, "PUT", &uri, None).await;
        assert!(headers[header::CONTENT_TYPE] == "application/problem+json", "PUT {path}: {status}");
    }
}

/// Fencing: A worker whose job was re-queued and claimed again (a restart)
/// can no longer end it; only the current claim's worker can.
#[tokio::test]
async fn only_the_current_attempt_can_end_a_job() {
    let (_, ctx, _dir) = app(vec![], 8, false).await;
    let store = &ctx.store;
    assert!(store.insert_job_within("j", "simulate", &json!({"n": 5}), 3, 8).await.unwrap());
    let first = store.claim("a", jobs::DEFAULT_LEASE).await.unwrap().unwrap();
    store.recover().await.unwrap();
    let second = store.claim("b", jobs::DEFAULT_LEASE).await.unwrap().unwrap();
    assert_eq!((first.attempts, second.attempts), (1, 2));
    let (t1, t2) = (first.lease_token.unwrap(), second.lease_token.unwrap());
    assert_ne!(t1, t2);
    assert!(
        !store.finish("j", &t1, otofit::store::JobState::Succeeded, None, Some(&json!({"late": true}))).await.unwrap()
    );
    assert!(!store.requeue("j", &t1).await.unwrap());
    assert!(!store.heartbeat("j", &t1, jobs::DEFAULT_LEASE).await.unwrap());
    let j = store.job("j").await.unwrap().unwrap();
    assert_eq!((j.state.as_str(), j.result), ("running", None), "the late worker changed nothing");
    assert!(store.heartbeat("j", &t2, jobs::DEFAULT_LEASE).await.unwrap());
    assert!(store.finish("j", &t2, otofit::store::JobState::Succeeded, None, Some(&json!({"rows": 5}))).await.unwrap());
    assert_eq!(store.job("j").await.unwrap().unwrap().state, "succeeded");
}

/// A job param of the wrong type, unknown or missing is named by its full
/// JSON path, not as `params`.
#[tokio::test]
async fn job_param_errors_carry_the_full_path() {
    let (app, _, _dir) = app(vec![], 8, false).await;
    let theta = json!([[2e7, 5e6, 2e6, 2e5, 6e6, 7.5e-5, 2.1e10], [2e7, "soft", 2e6, 2e5, 6e6, 7.5e-5, 2.1e10]]);
    for (kind, params, field) in [
        ("resimulate", json!({"theta": theta}), "params.theta[1][1]"),
        ("simulate", json!({"n": 5, "bogus": 1}), "params.bogus"),
        ("simulate", json!({"n": -5}), "params.n"),
        ("train", json!({"dataset": "d", "max_epochs": "many"}), "params.max_epochs"),
        ("diagnose", json!({"candidates": ["probe_leak"]}), "params.x"),
        ("diagnose", json!({"x": [1.0, "high"]}), "params.x[1]"),
        // null is a feature not measured; an observation of nothing is refused.
        ("diagnose", json!({"x": [null, null]}), "params.x"),
    ] {
        let (status, headers, p) = call(&app, "POST", "/jobs", Some(json!({"kind": kind, "params": params}))).await;
        assert_eq!(status, StatusCode::UNPROCESSABLE_ENTITY, "{p}");
        assert_eq!(headers[header::CONTENT_TYPE], "application/problem+json");
        assert_eq!(p["errors"][0]["field"], field, "{p}");
    }
}

/// The lines of component schema `name` in openapi.yaml (below its key, at four spaces;
/// empty for a one-line schema, whose line is the first).
fn component(name: &str) -> Vec<&'static str> {
    let at = [format!("\n    {name}:\n"), format!("\n    {name}: ")]
        .iter()
        .find_map(|k| SPEC.find(k.as_str()))
        .unwrap_or_else(|| panic!("openapi.yaml has no schema {name}"));
    let mut lines = SPEC[at + 1..].lines();
    let first = lines.next().unwrap();
    std::iter::once(first).chain(lines.take_while(|l| l.starts_with("      "))).collect()
}

/// The names under a component schema's `properties:`, sorted.
fn schema_properties(name: &str) -> Vec<String> {
    let (mut inside, mut names) = (false, vec![]);
    for l in component(name).into_iter().skip(1) {
        let indent = l.len() - l.trim_start().len();
        if indent == 6 {
            inside = l.trim() == "properties:";
        } else if inside && indent == 8 {
            names.push(l.trim().split(':').next().unwrap().to_string());
        }
    }
    names.sort();
    names
}

/// The names of a component schema's own `required: [...]` (none if it has none).
fn schema_required(name: &str) -> Vec<String> {
    component(name).into_iter().find(|l| l.starts_with("      required: [")).map_or(vec![], |l| {
        l.trim().trim_start_matches("required: [").trim_end_matches(']').split(", ").map(str::to_string).collect()
    })
}

/// The number after `key: ` in a one-line flow mapping.
fn flow_number(line: &str, key: &str) -> f64 {
    let rest = line.split_once(&format!("{key}: ")).unwrap_or_else(|| panic!("no {key} in {line}")).1;
    rest.split([',', ' ', '}']).next().unwrap().parse().unwrap_or_else(|e| panic!("{key} in {line}: {e}"))
}

/// The measurement units the contract enumerates are exactly those the server reads, so
/// a schema-valid unit is never refused and none the server reads is left out.
#[test]
fn measurement_units_in_the_contract_are_the_servers() {
    use otofit::measurements::{IMPEDANCE_UNITS, PHASE_UNITS, VELOCITY_UNITS};
    let names = |units: &[(&[&str], Option<f64>)]| -> Vec<String> {
        units.iter().flat_map(|(n, _)| n.iter().map(|s| s.to_string())).collect()
    };
    let enumerated = |schema: &str, field: &str| -> Vec<String> {
        let l = property_line(schema, field);
        let list = l.split_once("enum: [").unwrap_or_else(|| panic!("{schema}.{field} has no enum")).1;
        list.split(']').next().unwrap().split(", ").map(|s| s.trim_matches('"').to_string()).collect()
    };
    assert_eq!(enumerated("VelocityCurve", "magnitude_unit"), names(&VELOCITY_UNITS));
    assert_eq!(enumerated("ImpedanceCurve", "magnitude_unit"), names(&IMPEDANCE_UNITS));
    let phases: Vec<String> = PHASE_UNITS.iter().map(|(n, _)| n.to_string()).collect();
    for schema in ["VelocityCurve", "ImpedanceCurve"] {
        assert_eq!(enumerated(schema, "phase_unit"), phases, "{schema}");
    }
}

/// The line of property `field` of component schema `schema`.
fn property_line(schema: &str, field: &str) -> &'static str {
    let key = format!("        {field}: ");
    component(schema).into_iter().find(|l| l.starts_with(&key)).unwrap_or_else(|| panic!("{schema} has no {field}"))
}

/// openapi.yaml's params schema of a job kind (`SimulateParams` for `simulate`).
fn params_schema(kind: &str) -> String {
    format!("{}{}Params", kind[..1].to_uppercase(), &kind[1..])
}

/// A job's params as the server stores them (every field it has a default for written
/// out), one per kind: together they give every field but `theta` of a simulate job.
fn full_params() -> Vec<(&'static str, Value)> {
    let x = vec![0.5; 350];
    let nominal: Vec<f64> = otofit::sim::params::PARAMS.iter().map(|p| p.nominal).collect();
    let given = [
        ("simulate", json!({"n": 5, "effects": {"probe_leak": 1e-4}, "vary": ["probe_offset"]})),
        ("train", json!({"dataset": "d1"})),
        ("resimulate", json!({"theta": [nominal], "observation": x})),
        ("diagnose", json!({"x": x, "model": "default", "candidates": ["probe_leak"]})),
        ("exact", json!({"x": x, "model": "default"})),
    ];
    given.into_iter().map(|(k, p)| (k, jobs::JobSpec::parse(k, &p).unwrap().params())).collect()
}

/// Contract and server agree on each job kind's params: openapi.yaml types `params`
/// per kind (NewJob: one schema per kind, picked by `kind`), with exactly the fields the
/// server reads, so one kind's params are refused under another by both, for the same
/// field. (Before, any object was schema-valid params for every kind: an `exact` job
/// with a simulate job's params passed the schema and got a 422.)
#[tokio::test]
async fn each_job_kind_has_its_own_params_in_the_contract_and_the_server() {
    let (app, _, _dir) = app(vec![], 8, false).await;
    let new_job = component("NewJob").join("\n");
    for kind in jobs::KINDS {
        let params = params_schema(kind);
        let job = component(&params.replace("Params", "Job")).join("\n");
        assert!(new_job.contains(&format!("{kind}: \"#/components/schemas/{}Job\"", &params[..params.len() - 6])));
        assert!(job.contains(&format!("kind: {{ type: string, const: {kind} }}")), "{job}");
        assert!(job.contains(&format!("params: {{ $ref: \"#/components/schemas/{params}\" }}")), "{job}");
        assert!(component(&params).contains(&"      additionalProperties: false"), "{params}");
        // The server's fields, as serde lists them for an unknown one.
        let body = json!({"kind": kind, "params": {"zz_unknown": 0}});
        let (status, _, p) = call(&app, "POST", "/jobs", Some(body)).await;
        assert_eq!(
            (status, p["errors"][0]["field"].as_str()),
            (StatusCode::UNPROCESSABLE_ENTITY, Some("params.zz_unknown"))
        );
        let message = p["errors"][0]["message"].as_str().unwrap();
        let mut fields: Vec<String> =
            message.split_once("expected").unwrap().1.split('`').skip(1).step_by(2).map(str::to_string).collect();
        fields.sort();
        assert_eq!(schema_properties(&params), fields, "{kind}: {message}");
    }
    let full = full_params();
    for (kind, params) in &full {
        let (status, _, p) = call(&app, "POST", "/jobs", Some(json!({"kind": kind, "params": params}))).await;
        // Valid for its own kind (train's dataset d1 does not exist: a 404).
        let want = if *kind == "train" { StatusCode::NOT_FOUND } else { StatusCode::ACCEPTED };
        assert_eq!(status, want, "{kind}: {p}");
        for (other, _) in full.iter().filter(|(k, _)| k != kind) {
            let schema = params_schema(other);
            let (props, required) = (schema_properties(&schema), schema_required(&schema));
            let given: Vec<&String> = params.as_object().unwrap().keys().collect();
            let unknown: Vec<&&String> = given.iter().filter(|k| !props.contains(k)).collect();
            let missing: Vec<&String> = required.iter().filter(|r| !given.contains(r)).collect();
            assert!(!unknown.is_empty() || !missing.is_empty(), "{schema} takes {kind}'s params {params}");
            let body = json!({"kind": other, "params": params});
            let (status, headers, p) = call(&app, "POST", "/jobs", Some(body)).await;
            assert_eq!(status, StatusCode::UNPROCESSABLE_ENTITY, "{other} with {kind}'s params: {p}");
            assert_eq!(headers[header::CONTENT_TYPE], "application/problem+json");
            let field = p["errors"][0]["field"].as_str().unwrap().strip_prefix("params.").unwrap().to_string();
            assert!(
                unknown.iter().any(|u| ***u == field) || missing.iter().any(|m| **m == field),
                "{other} with {kind}'s params: the server names {field}, the schema refuses {unknown:?} {missing:?}"
            );
        }
    }
    // The case schemathesis found: an exact job with a simulate job's params.
    let simulate = &full.iter().find(|(k, _)| *k == "simulate").unwrap().1;
    let (status, _, p) = call(&app, "POST", "/jobs", Some(json!({"kind": "exact", "params": simulate}))).await;
    let field = p["errors"][0]["field"].as_str().unwrap();
    assert_eq!(status, StatusCode::UNPROCESSABLE_ENTITY, "{p}");
    assert!(["params.effects", "params.n", "params.noise_scale", "params.vary"].contains(&field), "{p}");
}

/// The bounds openapi.yaml states for job params are the server's: theta's values (its
/// prior boxes widened), the effects' ranges and names, one width of simulate rows per
/// count of varied effects, and the job limits.
#[test]
fn job_params_schema_states_the_servers_bounds() {
    use otofit::jobs::limits;
    use otofit::sim::params::{EFFECTS, N_EFFECTS, PARAMS};
    let columns: Vec<&str> = component("ThetaRow").into_iter().filter(|l| l.trim_start().starts_with("- &t")).collect();
    assert_eq!(columns.len(), PARAMS.len());
    for (l, p) in columns.iter().zip(PARAMS.iter()) {
        assert!(l.contains(&format!("description: \"{}, {}\"", p.name, p.unit)), "{l}");
        let (lo, hi) = jobs::theta_box(p);
        assert_eq!((flow_number(l, "minimum"), flow_number(l, "maximum")), (lo, hi), "{}", p.name);
    }
    let names: Vec<&str> = EFFECTS.iter().map(|e| e.name).collect();
    assert_eq!(component("EffectName")[0], format!("    EffectName: {{ type: string, enum: [{}] }}", names.join(", ")));
    let mut sorted = names.clone();
    sorted.sort();
    assert_eq!(schema_properties("Effects"), sorted);
    for e in EFFECTS {
        let l = property_line("Effects", e.name);
        assert_eq!((flow_number(l, "minimum"), flow_number(l, "maximum")), (e.low, e.high), "{}", e.name);
        if !(e.low..=e.high).contains(&e.off) {
            assert_eq!(flow_number(l, "const"), e.off, "{}", e.name);
        }
    }
    let rows = component("SimulateRows").join("\n");
    for k in 1..=N_EFFECTS + 1 {
        let branch = rows.contains(&format!("vary: {{ minItems: {k}, maxItems: {k} }}"));
        assert_eq!(branch, k <= N_EFFECTS, "simulate rows with {k} varied effects");
    }
    for (schema, field, range) in [
        ("SimulateParams", "n", limits::SIMULATE_ROWS),
        ("TrainParams", "max_epochs", limits::EPOCHS),
        ("TrainParams", "ensemble", limits::ENSEMBLE),
        ("DiagnoseParams", "train_rows", limits::TRAIN_ROWS),
        ("DiagnoseParams", "max_epochs", limits::EPOCHS),
        ("DiagnoseParams", "null_cases", limits::NULL_CASES),
        ("ExactParams", "steps", limits::EXACT_STEPS),
    ] {
        let l = property_line(schema, field);
        assert_eq!(
            (flow_number(l, "minimum"), flow_number(l, "maximum")),
            (*range.start() as f64, *range.end() as f64),
            "{schema}.{field}"
        );
    }
    for (schema, range) in [("SimulateParams", limits::THETA_ROWS), ("ResimulateParams", limits::RESIMULATE_ROWS)] {
        let l = property_line(schema, "theta");
        assert_eq!(
            (flow_number(l, "minItems"), flow_number(l, "maxItems")),
            (*range.start() as f64, *range.end() as f64),
            "{schema}.theta"
        );
    }
    let features = (otofit::sim::output::N_MEASURES * otofit::sim::ModelConfig::default().frequencies.len()) as f64;
    let l = property_line("ResimulateParams", "observation");
    assert_eq!((flow_number(l, "minItems"), flow_number(l, "maxItems")), (features, features));
}

/// An id in job params that names nothing is a 404 naming the field, as GET /models/{id}
/// and GET /datasets/{id} answer; a dataset whose simulate job has not succeeded a 409.
/// (They were 422s: a schema-valid body refused for the store's state, not its content.)
#[tokio::test]
async fn job_params_naming_no_model_or_dataset_are_404_and_an_unready_dataset_409() {
    let (app, _, _dir) = app(vec![], 8, false).await;
    let x = vec![0.5; 350];
    let post = |kind: &str, params: Value| call(&app, "POST", "/jobs", Some(json!({"kind": kind, "params": params})));
    let (status, _, queued) = post("simulate", json!({"n": 5})).await;
    assert_eq!(status, StatusCode::ACCEPTED);
    let (status, _, exact) = post("exact", json!({"x": x})).await;
    assert_eq!(status, StatusCode::ACCEPTED);
    for (kind, params, want, field) in [
        ("train", json!({"dataset": "nope"}), StatusCode::NOT_FOUND, "params.dataset"),
        ("train", json!({"dataset": exact["id"]}), StatusCode::NOT_FOUND, "params.dataset"),
        ("train", json!({"dataset": queued["id"]}), StatusCode::CONFLICT, "params.dataset"),
        ("diagnose", json!({"model": "ghost", "x": x}), StatusCode::NOT_FOUND, "params.model"),
        ("exact", json!({"model": "ghost", "x": x}), StatusCode::NOT_FOUND, "params.model"),
    ] {
        let (status, headers, p) = post(kind, params.clone()).await;
        assert_eq!((status, p["errors"][0]["field"].as_str()), (want, Some(field)), "{kind} {params}: {p}");
        assert_eq!(headers[header::CONTENT_TYPE], "application/problem+json");
        assert_eq!(p["status"], want.as_u16());
    }
    let (_, _, p) = post("train", json!({"dataset": queued["id"]})).await;
    assert!(p["errors"][0]["message"].as_str().unwrap().ends_with("is not ready (job queued)"), "{p}");
}

/// A body field of the wrong type is named by its JSON path, not `body` or its
/// value.
#[tokio::test]
async fn body_type_errors_carry_the_full_path() {
    let (app, _, _dir) = app(vec![], 8, false).await;
    let mut bad = nominal_request();
    bad["measurements"]["absorbance"]["values"][3] = json!("high");
    let mut negative = nominal_request();
    negative["samples"] = json!(-5);
    for (uri, body, field) in [
        ("/infer", bad, "measurements.absorbance.values[3]"),
        ("/infer", negative, "samples"),
        ("/jobs", json!({"kind": 5, "params": {}}), "kind"),
    ] {
        let (status, _, p) = call(&app, "POST", uri, Some(body)).await;
        assert_eq!((status, p["errors"][0]["field"].as_str()), (StatusCode::UNPROCESSABLE_ENTITY, Some(field)), "{p}");
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn keyless_server_answers_only_loopback_names_ip_literals_and_allowed_hosts() {
    // DNS rebinding: a page on evil.example resolves its own name to 127.0.0.1 and
    // drives a keyless local server; its requests carry Host: evil.example.
    let (app, ctx, _dir) = app(vec![], 8, false).await;
    let get = |app: Router, host: &'static str| async move {
        let req = Request::builder().uri("/models").header(header::HOST, host).body(Body::empty()).unwrap();
        let r = app.oneshot(req).await.unwrap();
        let status = r.status();
        let body = axum::body::to_bytes(r.into_body(), 1 << 20).await.unwrap();
        (status, String::from_utf8_lossy(&body).to_string())
    };
    for host in ["localhost:8080", "127.0.0.1:8080", "[::1]:8080", "10.1.2.3", "LOCALHOST", "app.localhost:80"] {
        assert_eq!(get(app.clone(), host).await.0, StatusCode::OK, "{host}");
    }
    let (status, body) = get(app.clone(), "evil.example:8080").await;
    assert_eq!(status, StatusCode::MISDIRECTED_REQUEST, "{body}");
    assert!(body.contains("--allowed-host evil.example") && body.contains("\"status\":421"), "{body}");
    // Named with --allowed-host: answered.
    let allowed = router(AppState::new(ctx.clone(), vec![]).with_allowed_hosts(vec!["Otofit.Lab".into()]));
    assert_eq!(get(allowed.clone(), "otofit.lab:8080").await.0, StatusCode::OK);
    assert_eq!(get(allowed, "evil.example").await.0, StatusCode::MISDIRECTED_REQUEST);
    // With API keys the key check guards instead: any host, but a key is needed.
    let keyed = router(AppState::new(ctx, vec![[7u8; 32]]));
    assert_eq!(get(keyed, "evil.example").await.0, StatusCode::UNAUTHORIZED);
}

/// One ear as a long-layout table (`text/csv`), the request's options in the
/// query; errors name the column.
#[tokio::test]
async fn a_long_layout_csv_body_is_inferred_and_its_errors_name_the_column() {
    let (app, _, _dir) = app(vec![], 8, false).await;
    let csv = |uri: &str, body: String| {
        Request::builder()
            .method("POST")
            .uri(uri)
            .header(header::CONTENT_TYPE, "text/csv")
            .body(Body::from(body))
            .unwrap()
    };
    let data = PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("tests/data");
    let device = std::fs::read_to_string(data.join("wbt_device_long.csv")).unwrap();
    let (status, _, r) = raw(&app, csv("/infer?samples=300&seed=2", device.clone())).await;
    assert_eq!(status, StatusCode::OK, "{r}");
    assert_eq!(r["inputs"]["format"], "csv");
    assert_eq!(r["inputs"]["used"], json!(["impedance", "absorbance"]));
    let band = |r: &Value, m: &str| -> Vec<i64> {
        r["inputs"]["band_hz"][m].as_array().unwrap().iter().map(|v| v.as_f64().unwrap().round() as i64).collect()
    };
    assert_eq!(band(&r, "zec_mag"), [232, 5491], "{}", r["inputs"]);
    assert_eq!(r["samples"].as_array().unwrap().len(), 300);
    assert_eq!(r["fit"]["ok"], true, "{}", r["fit"]);
    // The WAI database's table, several ears: the preset and the ear in the query.
    let wai = std::fs::read_to_string(data.join("wai_long.csv")).unwrap();
    let (status, _, r) = raw(&app, csv("/infer?preset=wai&select=Ear=Left&return_samples=false", wai.clone())).await;
    assert_eq!(status, StatusCode::OK, "{r}");
    assert!(r["inputs"]["notes"][0].as_str().unwrap().contains("kept 63 of 126 rows"), "{}", r["inputs"]);
    assert!(r.get("samples").is_none());
    let first_absorbance = device.lines().nth(1).and_then(|l| l.split(';').nth(1)).unwrap().to_string();
    for (uri, body, field) in [
        ("/infer?select=Ear=Left", wai.clone(), "Zmag"),
        ("/infer?preset=wai", wai.clone(), "body"),
        ("/infer?sample=3", device.clone(), "sample"),
        ("/infer?unit=Zang", device.clone(), "unit"),
        ("/infer", device.replace("Zmag [cgs]", "Zmag [Pa*s/m^3]"), "Zmag (measurements.impedance.magnitude)"),
        ("/infer", device.replacen(&format!(";{first_absorbance};"), ";3.7x;", 1), "Absorbance[line 2]"),
    ] {
        let (status, _, p) = raw(&app, csv(uri, body)).await;
        assert_eq!((status, p["errors"][0]["field"].as_str()), (StatusCode::UNPROCESSABLE_ENTITY, Some(field)), "{p}");
    }
    // Query parameters belong to CSV bodies; JSON carries its own.
    let (status, _, p) = call(&app, "POST", "/infer?samples=3", Some(json!({"measurements": {}}))).await;
    assert_eq!((status, p["errors"][0]["field"].as_str()), (StatusCode::UNPROCESSABLE_ENTITY, Some("samples")), "{p}");
    // The spec's text/csv example is answered.
    let example =
        spec_examples().into_iter().filter(|(p, _)| p == "/infer").find_map(|(_, v)| v.as_str().map(String::from));
    let (status, _, r) = raw(&app, csv("/infer?return_samples=false", example.expect("a text/csv example"))).await;
    assert_eq!(status, StatusCode::OK, "{r}");
    assert_eq!(band(&r, "absorbance"), [232, 8000], "{}", r["inputs"]);
}

/// GET /metrics in the Prometheus text format: the job table by kind and state,
/// this process's claims, simulated rows, job durations and /infer latencies.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn metrics_count_jobs_rows_and_inferences() {
    let (app, _, _dir) = app(vec![], 8, true).await;
    let (_, _, j) = call(&app, "POST", "/jobs", Some(json!({"kind": "simulate", "params": {"n": 20}}))).await;
    let id = j["id"].as_str().unwrap().to_string();
    assert_eq!(wait(&app, &id).await["state"], "succeeded");
    assert_eq!(call(&app, "POST", "/infer", Some(nominal_request())).await.0, StatusCode::OK);
    assert_eq!(
        call(&app, "POST", "/infer", Some(json!({"measurements": {}}))).await.0,
        StatusCode::UNPROCESSABLE_ENTITY
    );
    let res = app.clone().oneshot(Request::get("/metrics").body(Body::empty()).unwrap()).await.unwrap();
    assert_eq!(res.status(), StatusCode::OK);
    assert_eq!(res.headers()[header::CONTENT_TYPE], "text/plain; version=0.0.4; charset=utf-8");
    let text = String::from_utf8(axum::body::to_bytes(res.into_body(), usize::MAX).await.unwrap().to_vec()).unwrap();
    for line in [
        "otofit_jobs{kind=\"simulate\",state=\"succeeded\"} 1",
        "otofit_jobs{kind=\"train\",state=\"queued\"} 0",
        "otofit_job_claims_total 1",
        "otofit_simulated_rows_total 20",
        "otofit_job_duration_seconds_count{kind=\"simulate\",outcome=\"succeeded\"} 1",
        "otofit_infer_duration_seconds_count{code=\"200\"} 1",
        "otofit_infer_duration_seconds_count{code=\"422\"} 1",
    ] {
        assert!(text.lines().any(|l| l == line), "no '{line}' in\n{text}");
    }
}

/// POST /log_prob gives log q(θ|x) of given rows for one ear's measurements:
/// on the typical ear its own θ beats an eardrum 10× softer, a row outside the prior
/// box is null and listed, and a row of the wrong width is a 422 naming it.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn log_prob_ranks_the_truth_and_names_bad_rows() {
    use otofit::sim::params::PARAMS;
    let (app, _, _dir) = app(vec![], 8, false).await;
    let nominal = otofit::npe::normal::centre_row();
    let mut soft = nominal.clone();
    soft[0] /= 10.0;
    let mut outside = nominal.clone();
    outside[0] = PARAMS[0].high * 2.0;
    let mut req = nominal_request();
    let measurements = req["measurements"].take();
    let body = json!({"measurements": measurements, "theta": [nominal, soft, outside]});
    let (status, _, r) = call(&app, "POST", "/log_prob", Some(body.clone())).await;
    assert_eq!(status, StatusCode::OK, "{r}");
    let lp = r["log_prob"].as_array().unwrap();
    let (truth, wrong) = (lp[0].as_f64().unwrap(), lp[1].as_f64().unwrap());
    assert!(truth > wrong + 5.0, "log q nominal {truth} vs soft eardrum {wrong}");
    assert!(lp[2].is_null() && r["outside_prior"] == json!([2]), "{r}");
    assert_eq!(r["columns"][0], "E_eardrum");
    let mut bad = body;
    bad["theta"] = json!([[1.0, 2.0]]);
    let (status, _, p) = call(&app, "POST", "/log_prob", Some(bad)).await;
    assert_eq!((status, p["errors"][0]["field"].as_str()), (StatusCode::UNPROCESSABLE_ENTITY, Some("theta[0]")), "{p}");
}

/// POST /infer draws the posterior's corner plot on request (`plot=corner` as a
/// query parameter or a body field), an SVG with tick values, and names a figure it does
/// not know.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn infer_draws_a_corner_plot_on_request() {
    let (app, _, _dir) = app(vec![], 8, false).await;
    let mut req = nominal_request();
    req["return_samples"] = json!(false);
    let (status, _, r) = call(&app, "POST", "/infer", Some(req.clone())).await;
    assert_eq!(status, StatusCode::OK, "{r}");
    assert!(r.get("figures").is_none(), "no figure unless asked");
    let (status, _, by_query) = call(&app, "POST", "/infer?plot=corner", Some(req.clone())).await;
    assert_eq!(status, StatusCode::OK, "{by_query}");
    req["plot"] = json!("corner");
    let (status, _, by_body) = call(&app, "POST", "/infer", Some(req.clone())).await;
    assert_eq!(status, StatusCode::OK, "{by_body}");
    for r in [&by_query, &by_body] {
        let fig = &r["figures"]["corner"];
        assert_eq!(fig["media_type"], "image/svg+xml");
        let svg = fig["svg"].as_str().unwrap();
        assert!(svg.starts_with("<svg") && svg.trim_end().ends_with("</svg>"), "{}", &svg[..80.min(svg.len())]);
        // One marginal per parameter, labelled with its name and unit.
        for p in r["parameters"].as_array().unwrap().iter().chain(r["geometry"].as_array().unwrap()) {
            assert!(svg.contains(p["name"].as_str().unwrap()), "{} not in the plot", p["name"]);
        }
    }
    assert_eq!(by_query["figures"], by_body["figures"], "same seed, same figure");
    let (status, _, p) = call(&app, "POST", "/infer?plot=pairs", Some(nominal_request())).await;
    assert_eq!((status, p["errors"][0]["field"].as_str()), (StatusCode::UNPROCESSABLE_ENTITY, Some("plot")), "{p}");
    req["plot"] = json!("pairs");
    let (status, _, p) = call(&app, "POST", "/infer", Some(req)).await;
    assert_eq!(status, StatusCode::UNPROCESSABLE_ENTITY, "{p}");
    assert!(p.to_string().contains("plot"), "{p}");
}

/// POST /infer's `refine`: the least-squares best fit from the MAP fits the openapi
/// example (the typical ear, noise-free) far closer than the MAP, and a step count past
/// the cap is a 422 naming `refine`.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn infer_refines_the_map_on_request() {
    let (app, _, _dir) = app(vec![], 8, false).await;
    let mut req = nominal_request();
    req["return_samples"] = json!(false);
    let (status, _, r) = call(&app, "POST", "/infer", Some(req.clone())).await;
    assert_eq!(status, StatusCode::OK, "{r}");
    assert!(r.get("refined").is_none(), "no fit unless asked");
    req["refine"] = json!(50);
    let (status, _, r) = call(&app, "POST", "/infer", Some(req.clone())).await;
    assert_eq!(status, StatusCode::OK, "{r}");
    let fit = &r["refined"];
    let (map, best) = (fit["map_reduced_chi2"].as_f64().unwrap(), fit["reduced_chi2"].as_f64().unwrap());
    // Far within the noise: a tenth of the χ²ν that noise alone gives (v8: 0.038 from 2.55;
    // the noise-free ear's exact optimum is 0, but the suspension springs leave a flat valley).
    assert!(best < 0.1 && best < map / 10.0, "{fit}");
    assert_eq!(fit["parameters"].as_object().unwrap().len(), r["map"].as_array().unwrap().len(), "{fit}");
    req["refine"] = json!(201);
    let (status, _, p) = call(&app, "POST", "/infer", Some(req)).await;
    assert_eq!((status, p["errors"][0]["field"].as_str()), (StatusCode::UNPROCESSABLE_ENTITY, Some("refine")), "{p}");
}

/// Sparse curves are refused, never scored as if measured: two points can never give a
/// finding. Every answer opens with a verdict; a model that cannot be loaded is named
/// without its server path; a missing field is named by its JSON path.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn sparse_inputs_are_insufficient_and_answers_carry_a_verdict() {
    let (app, ctx, _dir) = app(vec![], 8, false).await;
    let two = json!({"measurements": {"absorbance": {"frequencies_hz": [200, 8000], "values": [0.02, 0.1]}}});
    let (status, _, p) = call(&app, "POST", "/infer", Some(two)).await;
    assert_eq!(status, StatusCode::UNPROCESSABLE_ENTITY, "{p}");
    assert_eq!(p["code"], "insufficient_data", "{p}");
    assert_eq!(p["errors"][0]["field"], "measurements.absorbance.frequencies_hz", "{p}");
    assert!(p["errors"][0]["message"].as_str().unwrap().contains("5.32 octaves"), "{p}");
    // A WBT at 1/3 octave is dense enough; one at whole octaves is not.
    let wbt = |step: f64| {
        let f: Vec<f64> =
            (0..).map(|k| 200.0 * 2f64.powf(k as f64 * step)).take_while(|f| *f < 7999.0).chain([8000.0]).collect();
        let v: Vec<f64> = f.iter().map(|_| 0.5).collect();
        json!({"measurements": {"absorbance": {"frequencies_hz": f, "values": v}}, "samples": 50, "return_samples": false})
    };
    let (status, _, p) = call(&app, "POST", "/infer", Some(wbt(1.0))).await;
    assert_eq!((status, p["code"].as_str()), (StatusCode::UNPROCESSABLE_ENTITY, Some("insufficient_data")), "{p}");
    let (status, _, body) = call(&app, "POST", "/infer", Some(wbt(1.0 / 3.0))).await;
    assert_eq!(status, StatusCode::OK, "{body}");
    let code = body["verdict"]["code"].as_str().unwrap();
    assert!(["reliable_no_finding", "reliable_findings", "unreliable_model_misfit"].contains(&code), "{body}");
    assert!(!body["verdict"]["sentence"].as_str().unwrap().is_empty());
    // The nominal ear: it fits, and nothing is outside its range.
    let (status, _, body) = call(&app, "POST", "/infer", Some(nominal_request())).await;
    assert_eq!(status, StatusCode::OK, "{body}");
    assert_eq!(body["verdict"]["code"], "reliable_no_finding", "{}", body["verdict"]);
    // A missing phase is named by its path.
    let mut req = nominal_request();
    req["measurements"]["impedance"].as_object_mut().unwrap().remove("phase");
    let (status, _, p) = call(&app, "POST", "/infer", Some(req)).await;
    assert_eq!(status, StatusCode::UNPROCESSABLE_ENTITY, "{p}");
    assert_eq!(p["errors"][0]["field"], "measurements.impedance.phase", "{p}");
    // A registered model whose file is gone: 503 naming the model, not the path.
    let gone = ctx.data_dir.join("models/gone.otofit");
    ctx.store.add_model("gone", &gone.display().to_string(), false, None).await.unwrap();
    let mut req = nominal_request();
    req["model"] = json!("gone");
    let (status, _, p) = call(&app, "POST", "/infer", Some(req)).await;
    assert_eq!(status, StatusCode::SERVICE_UNAVAILABLE, "{p}");
    let detail = p["detail"].as_str().unwrap();
    assert!(detail.contains("'gone'") && !detail.contains(&*ctx.data_dir.display().to_string()), "{p}");
    assert!(!p.to_string().contains("/models/gone.otofit"), "{p}");
}

/// Unit slips that land inside the physical envelope are named with the unit they look
/// like: CGS ohms declared as MΩ (10× off, which the absorbance contradicts), phases in
/// cycles declared as radians, kHz sent as Hz.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn unit_slips_inside_the_envelope_are_named() {
    let (app, _, _dir) = app(vec![], 8, false).await;
    let field_and_message = |p: &Value| {
        let e = &p["errors"][0];
        (e["field"].as_str().unwrap_or("").to_string(), e["message"].as_str().unwrap_or("").to_string())
    };
    // CGS acoustic ohms (SI / 1e5) declared as MΩ: ten times too large.
    let mut req = scaled(nominal_request(), "impedance", "magnitude", 1e-5);
    req["measurements"]["impedance"]["magnitude_unit"] = json!("MOhm");
    let (status, _, p) = call(&app, "POST", "/infer", Some(req)).await;
    assert_eq!(status, StatusCode::UNPROCESSABLE_ENTITY, "{p}");
    let (field, message) = field_and_message(&p);
    assert_eq!(field, "measurements.impedance.magnitude_unit", "{p}");
    assert!(message.contains("send \"cgs\""), "{p}");
    // And the other way: MΩ values declared as CGS.
    let mut req = scaled(nominal_request(), "impedance", "magnitude", 1e-6);
    req["measurements"]["impedance"]["magnitude_unit"] = json!("cgs");
    let (_, _, p) = call(&app, "POST", "/infer", Some(req)).await;
    assert!(field_and_message(&p).1.contains("send \"MOhm\""), "{p}");
    // Impedance phases in cycles, declared (by default) as radians.
    let req = scaled(nominal_request(), "impedance", "phase", 1.0 / std::f64::consts::TAU);
    let (status, _, p) = call(&app, "POST", "/infer", Some(req)).await;
    assert_eq!(status, StatusCode::UNPROCESSABLE_ENTITY, "{p}");
    let (field, message) = field_and_message(&p);
    assert_eq!(field, "measurements.impedance.phase_unit", "{p}");
    assert!(message.contains("cycles"), "{p}");
    // Frequencies in kHz: named once, with the hint.
    let mut req = nominal_request();
    for m in ["stapes_velocity", "impedance", "absorbance"] {
        req = scaled(req, m, "frequencies_hz", 1e-3);
    }
    let (status, _, p) = call(&app, "POST", "/infer", Some(req)).await;
    assert_eq!(status, StatusCode::UNPROCESSABLE_ENTITY, "{p}");
    let errors = p["errors"].as_array().unwrap();
    assert_eq!(errors.len(), 3, "one error per measure: {p}");
    assert!(errors.iter().all(|e| e["message"].as_str().unwrap().contains("look like kHz")), "{p}");
    // The same ear declared correctly is answered.
    let mut req = scaled(nominal_request(), "impedance", "magnitude", 1e-5);
    req["measurements"]["impedance"]["magnitude_unit"] = json!("cgs");
    assert_eq!(call(&app, "POST", "/infer", Some(req)).await.0, StatusCode::OK);
}

/// Not ready is a problem like every other error: 503, problem+json, the missing part named.
#[tokio::test]
async fn not_ready_is_a_problem_naming_the_missing_part() {
    let dir = temp_dir("not-ready");
    let ctx = otofit::cli::serve::open(&dir, std::path::Path::new("/nonexistent.otofit"), 8).await.unwrap();
    let app = router(AppState::new(ctx, vec![]));
    let (status, headers, p) = call(&app, "GET", "/ready", None).await;
    assert_eq!(status, StatusCode::SERVICE_UNAVAILABLE, "{p}");
    assert_eq!(headers[header::CONTENT_TYPE], "application/problem+json");
    assert_eq!(
        (p["code"].as_str(), p["detail"].as_str()),
        (Some("not_ready"), Some("not ready: database ok, default model unavailable")),
        "{p}"
    );
}

/// The README's example answer is what the server answers for the example it sends: a
/// stale example (a retrained model, a changed reading) fails here. Every number the
/// README states is compared to its rounding; timings are not.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_readme_example_answer_is_what_the_server_answers() {
    let readme = std::fs::read_to_string(PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("README.md")).unwrap();
    let block = readme.split("## Read the answer").nth(1).and_then(|s| s.split("```json\n").nth(1)).unwrap();
    let stated: Value = serde_json::from_str(block.split("```").next().unwrap()).expect("the README's answer is JSON");
    let (app, _, _dir) = app(vec![], 8, false).await;
    let (status, _, got) = call(&app, "POST", "/infer", Some(nominal_request())).await;
    assert_eq!(status, StatusCode::OK, "{got}");
    // Equal to the README's rounding: three significant digits (≤ 0.51 % for values ≥ 1),
    // two or three decimals for fractions (≤ 0.0051).
    let close = |printed: &Value, actual: &Value, what: &str| {
        let (p, a) = (printed.as_f64().unwrap(), actual.as_f64().unwrap());
        let tolerance = if p.abs() >= 1.0 { 0.0051 * p.abs() } else { 0.0051 };
        assert!((p - a).abs() <= tolerance, "README {what}: {p} printed, {a} answered");
    };
    assert_eq!(stated["verdict"], got["verdict"], "README verdict");
    assert_eq!(stated["fit"]["ok"], got["fit"]["ok"]);
    for k in ["reduced_chi2", "threshold"] {
        close(&stated["fit"][k], &got["fit"][k], &format!("fit.{k}"));
    }
    assert_eq!(stated["fit"]["worst_measure"][0], got["fit"]["worst_measure"][0]);
    close(&stated["fit"]["worst_measure"][1], &got["fit"]["worst_measure"][1], "fit.worst_measure");
    let find =
        |list: &Value, name: &Value| list.as_array().unwrap().iter().find(|d| d["name"] == *name).cloned().unwrap();
    for (section, keys) in
        [("differential", &["p_below", "p_within", "p_above"][..]), ("parameters", &["map", "q05", "q95", "cv"][..])]
    {
        for s in stated[section].as_array().unwrap() {
            let g = find(&got[section], &s["name"]);
            if section == "differential" {
                assert_eq!(s["reading"], g["reading"], "README reading of {}", s["name"]);
            }
            for k in keys {
                close(&s[*k], &g[*k], &format!("{section} {} {k}", s["name"]));
            }
        }
    }
}
