//! Tenants. Keys belong to tenants; jobs, datasets and models belong to the
//! tenant that made them; another tenant's id answers 404 on every route that takes one,
//! lists show only one's own, an admin key sees all but not other tenants' measurements.
//! On SQLite and, when its binaries are installed, PostgreSQL.

use crate::pg::{backends, ctx_on};
use axum::Router;
use axum::body::Body;
use axum::http::{Request, StatusCode, header};
use otofit::http::{AppState, router};
use otofit::jobs::Ctx;
use serde_json::{Value, json};
use std::sync::Arc;
use std::time::Duration;
use tower::ServiceExt;

/// A request with `key` (if any) as its bearer key; (status, body).
async fn send(app: &Router, key: Option<&str>, method: &str, uri: &str, body: Option<Value>) -> (StatusCode, Value) {
    let mut req = Request::builder().method(method).uri(uri);
    if let Some(k) = key {
        req = req.header(header::AUTHORIZATION, format!("Bearer {k}"));
    }
    if body.is_some() {
        req = req.header(header::CONTENT_TYPE, "application/json");
    }
    let req = req.body(body.map_or(Body::empty(), |b| Body::from(b.to_string()))).unwrap();
    let res = app.clone().oneshot(req).await.unwrap();
    let status = res.status();
    let bytes = axum::body::to_bytes(res.into_body(), usize::MAX).await.unwrap();
    (status, serde_json::from_slice(&bytes).unwrap_or(Value::Null))
}

/// A text answer of GET `uri` with `key`.
async fn text(app: &Router, key: Option<&str>, uri: &str) -> String {
    let mut req = Request::builder().method("GET").uri(uri);
    if let Some(k) = key {
        req = req.header(header::AUTHORIZATION, format!("Bearer {k}"));
    }
    let res = app.clone().oneshot(req.body(Body::empty()).unwrap()).await.unwrap();
    assert_eq!(res.status(), StatusCode::OK, "GET {uri}");
    let bytes = axum::body::to_bytes(res.into_body(), usize::MAX).await.unwrap();
    String::from_utf8(bytes.to_vec()).unwrap()
}

/// A simulate job posted by `key`, then run to success by hand (claimed and finished, its
/// dataset files and a report file written), without a dispatcher.
pub(crate) async fn succeeded_simulate(app: &Router, ctx: &Ctx, key: &str) -> String {
    let (status, j) =
        send(app, Some(key), "POST", "/jobs", Some(json!({"kind": "simulate", "params": {"n": 3}}))).await;
    assert_eq!(status, StatusCode::ACCEPTED, "{j}");
    let id = j["id"].as_str().unwrap().to_string();
    let claimed = ctx.store.claim("test", Duration::from_secs(30)).await.unwrap().unwrap();
    assert_eq!(claimed.id, id);
    let dir = ctx.dataset_dir(&id);
    std::fs::create_dir_all(&dir).unwrap();
    std::fs::write(dir.join("meta.json"), r#"{"n_rows": 3}"#).unwrap();
    std::fs::write(dir.join("x.csv"), "1\n").unwrap();
    let reports = ctx.data_dir.join("reports").join(&id);
    std::fs::create_dir_all(&reports).unwrap();
    std::fs::write(reports.join("report.html"), "<p>report</p>").unwrap();
    let token = claimed.lease_token.unwrap();
    assert!(
        ctx.store
            .finish(&id, &token, otofit::store::JobState::Succeeded, None, Some(&json!({"rows": 3})))
            .await
            .unwrap()
    );
    id
}

fn ids(list: &Value, key: &str) -> Vec<String> {
    list[key].as_array().unwrap().iter().map(|j| j["id"].as_str().unwrap().to_string()).collect()
}

/// Two tenants and an admin on one server (`app` over `ctx`, no `--api-key-hash`).
async fn two_tenants_cannot_see_each_other(app: &Router, ctx: &Arc<Ctx>, backend: &str) {
    // Keyless until a key is stored; from then on every route but /health needs one.
    assert_eq!(send(app, None, "GET", "/jobs", None).await.0, StatusCode::OK, "{backend}");
    let alpha = ctx.store.add_key("alpha", false).await.unwrap().key;
    let beta = ctx.store.add_key("beta", false).await.unwrap().key;
    let ops = ctx.store.add_key("ops", true).await.unwrap();
    assert_eq!(send(app, None, "GET", "/jobs", None).await.0, StatusCode::UNAUTHORIZED, "{backend}");
    assert_eq!(send(app, None, "GET", "/health", None).await.0, StatusCode::OK, "{backend}");
    let (a, b) = (Some(alpha.as_str()), Some(beta.as_str()));

    let ja = succeeded_simulate(app, ctx, &alpha).await;
    let jb = succeeded_simulate(app, ctx, &beta).await;
    // A model trained from alpha's job is alpha's; the default model is everyone's.
    let default = ctx.store.model("default").await.unwrap().unwrap();
    ctx.store.add_model("ma", &default.path, false, Some(&ja)).await.unwrap();
    assert_eq!(ctx.store.model("ma").await.unwrap().unwrap().tenant.as_deref(), Some("alpha"), "{backend}");
    // Alpha's resimulate job carries a measurement (the observation).
    let obs = vec![0.5; 350];
    let resim = json!({"kind": "resimulate", "params": {"theta": [[2e7, 5e6, 2e6, 2e5, 6e6, 7.5e-5, 2.1e10]], "observation": obs}});
    let (status, r) = send(app, a, "POST", "/jobs", Some(resim)).await;
    assert_eq!(status, StatusCode::ACCEPTED, "{backend}: {r}");
    let jr = r["id"].as_str().unwrap().to_string();
    assert_eq!(r["tenant"], "alpha", "{backend}: {r}");

    // Every route that takes an id: alpha's answer 404 to beta, 2xx to alpha.
    for uri in [
        format!("/jobs/{ja}"),
        format!("/jobs/{jr}"),
        format!("/jobs/{ja}/files/report.html"),
        format!("/datasets/{ja}"),
        format!("/datasets/{ja}/x.csv"),
        "/models/ma".to_string(),
    ] {
        let (status, p) = send(app, b, "GET", &uri, None).await;
        assert_eq!(status, StatusCode::NOT_FOUND, "{backend}: beta GET {uri}: {p}");
        assert_eq!(send(app, a, "GET", &uri, None).await.0, StatusCode::OK, "{backend}: alpha GET {uri}");
        assert_eq!(send(app, Some(&ops.key), "GET", &uri, None).await.0, StatusCode::OK, "{backend}: admin {uri}");
    }
    assert_eq!(send(app, b, "GET", &format!("/jobs/{jb}"), None).await.0, StatusCode::OK, "{backend}");
    assert_eq!(send(app, a, "GET", &format!("/jobs/{jb}"), None).await.0, StatusCode::NOT_FOUND, "{backend}");
    let (status, _) = send(app, b, "POST", &format!("/jobs/{jr}/cancel"), None).await;
    assert_eq!(status, StatusCode::NOT_FOUND, "{backend}: beta cancels alpha's job");
    assert_eq!(ctx.store.job(&jr).await.unwrap().unwrap().state, "queued", "{backend}: not cancelled");

    // Lists: one's own; the admin sees all.
    let (_, list) = send(app, b, "GET", "/jobs", None).await;
    assert_eq!(ids(&list, "jobs"), vec![jb.clone()], "{backend}");
    let (_, list) = send(app, a, "GET", "/jobs?limit=10", None).await;
    assert_eq!(ids(&list, "jobs").len(), 2, "{backend}: {list}");
    let (_, list) = send(app, Some(&ops.key), "GET", "/jobs", None).await;
    assert_eq!(ids(&list, "jobs").len(), 3, "{backend}");
    let (_, models) = send(app, b, "GET", "/models", None).await;
    assert_eq!(ids(&models, "models"), vec!["default"], "{backend}");
    let (_, models) = send(app, a, "GET", "/models", None).await;
    assert_eq!(ids(&models, "models"), vec!["default", "ma"], "{backend}");

    // Another tenant's dataset and model cannot be used either: 404 as if unknown.
    let train = json!({"kind": "train", "params": {"dataset": ja}});
    let (status, p) = send(app, b, "POST", "/jobs", Some(train)).await;
    assert_eq!((status, p["errors"][0]["field"].as_str()), (StatusCode::NOT_FOUND, Some("params.dataset")));
    let diagnose = json!({"kind": "diagnose", "params": {"model": "ma", "x": vec![0.5; 350]}});
    let (status, p) = send(app, b, "POST", "/jobs", Some(diagnose)).await;
    assert_eq!((status, p["errors"][0]["field"].as_str()), (StatusCode::NOT_FOUND, Some("params.model")));
    let mut infer = crate::http::nominal_request();
    infer["model"] = json!("ma");
    infer["samples"] = json!(10);
    let (status, p) = send(app, b, "POST", "/infer", Some(infer.clone())).await;
    assert_eq!((status, p["errors"][0]["field"].as_str()), (StatusCode::NOT_FOUND, Some("model")), "{p}");
    assert_eq!(send(app, a, "POST", "/infer", Some(infer)).await.0, StatusCode::OK, "{backend}");

    // The admin sees alpha's job, but not the measurement in its params.
    let (_, j) = send(app, Some(&ops.key), "GET", &format!("/jobs/{jr}"), None).await;
    assert!(j["params"].get("observation").is_none() && j["params"].get("theta").is_some(), "{backend}: {j}");
    assert_eq!(j["redacted"], json!(["params.observation"]), "{backend}");
    let (_, j) = send(app, a, "GET", &format!("/jobs/{jr}"), None).await;
    assert_eq!(j["params"]["observation"].as_array().map(Vec::len), Some(350), "{backend}: the owner sees it");
    // Its figures are drawn from the measurement: the same rule holds for them.
    let reports = ctx.data_dir.join("reports").join(&jr);
    std::fs::create_dir_all(&reports).unwrap();
    std::fs::write(reports.join("spectra.svg"), "<svg/>").unwrap();
    let figure = format!("/jobs/{jr}/files/spectra.svg");
    let (status, p) = send(app, Some(&ops.key), "GET", &figure, None).await;
    assert_eq!(status, StatusCode::NOT_FOUND, "{backend}: the admin reads the observation's figure: {p}");
    assert_eq!(send(app, a, "GET", &figure, None).await.0, StatusCode::OK, "{backend}: the owner's figure");

    // /metrics: a tenant's key counts its own jobs only, and no process counters.
    let beta_metrics = text(app, b, "/metrics").await;
    assert!(
        beta_metrics.contains("otofit_jobs{kind=\"simulate\",state=\"succeeded\"} 1\n"),
        "{backend}: {beta_metrics}"
    );
    assert!(
        beta_metrics.contains("otofit_jobs{kind=\"resimulate\",state=\"queued\"} 0\n"),
        "{backend}: {beta_metrics}"
    );
    assert!(!beta_metrics.contains("otofit_simulated_rows_total"), "{backend}: {beta_metrics}");
    let all = text(app, Some(&ops.key), "/metrics").await;
    assert!(all.contains("otofit_jobs{kind=\"simulate\",state=\"succeeded\"} 2\n"), "{backend}: {all}");
    assert!(all.contains("otofit_jobs{kind=\"resimulate\",state=\"queued\"} 1\n"), "{backend}: {all}");
    assert!(all.contains("otofit_simulated_rows_total"), "{backend}: {all}");

    // A revoked key is refused; the server stays keyed.
    let keys = ctx.store.keys().await.unwrap();
    let beta_id = keys.iter().find(|k| k.tenant == "beta").unwrap().id.clone();
    assert_eq!(ctx.store.revoke_key(&beta_id).await.unwrap(), Some(true), "{backend}");
    assert_eq!(ctx.store.revoke_key(&beta_id).await.unwrap(), Some(false), "{backend}");
    assert_eq!(ctx.store.revoke_key("nope").await.unwrap(), None, "{backend}");
    assert_eq!(send(app, b, "GET", "/jobs", None).await.0, StatusCode::UNAUTHORIZED, "{backend}");
    assert_eq!(send(app, a, "GET", "/jobs", None).await.0, StatusCode::OK, "{backend}");
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn two_tenants_cannot_see_each_others_jobs_datasets_and_models() {
    for (name, db) in backends().await {
        let store = otofit::store::Store::connect(&db).await.unwrap();
        let data = crate::pg::temp_dir(&format!("tenants-{name}"));
        let path = std::fs::canonicalize(crate::http::default_model()).unwrap();
        store.add_model("default", &path.display().to_string(), true, None).await.unwrap();
        let ctx = ctx_on(store, &data, "test", Duration::from_secs(30));
        let app = router(AppState::new(ctx.clone(), vec![]));
        two_tenants_cannot_see_each_other(&app, &ctx, &name).await;
    }
}

/// `--api-key-hash` keys (configuration from before tenants) still work: admin keys of
/// the `default` tenant, which see every tenant's jobs.
#[tokio::test]
async fn command_line_keys_are_admins_of_the_default_tenant() {
    let data = crate::pg::temp_dir("clikeys");
    let db = otofit::store::Database::Sqlite(data.join("otofit.db"));
    let store = otofit::store::Store::connect(&db).await.unwrap();
    let ctx = ctx_on(store, &data, "test", Duration::from_secs(30));
    let app = router(AppState::new(ctx.clone(), vec![otofit::store::key_hash("legacy")]));
    let alpha = ctx.store.add_key("alpha", false).await.unwrap().key;
    let (status, j) =
        send(&app, Some(&alpha), "POST", "/jobs", Some(json!({"kind": "simulate", "params": {"n": 3}}))).await;
    assert_eq!(status, StatusCode::ACCEPTED, "{j}");
    let (status, j2) =
        send(&app, Some("legacy"), "POST", "/jobs", Some(json!({"kind": "simulate", "params": {"n": 3}}))).await;
    assert_eq!((status, j2["tenant"].as_str()), (StatusCode::ACCEPTED, Some("default")), "{j2}");
    let (_, list) = send(&app, Some("legacy"), "GET", "/jobs", None).await;
    assert_eq!(ids(&list, "jobs").len(), 2, "{list}");
    let (_, list) = send(&app, Some(&alpha), "GET", "/jobs", None).await;
    assert_eq!(ids(&list, "jobs"), vec![j["id"].as_str().unwrap().to_string()]);
    assert_eq!(send(&app, None, "GET", "/jobs", None).await.0, StatusCode::UNAUTHORIZED);
}

/// `otofit keys add|list|revoke` on a data directory: the key is printed once and works
/// (its hash is in the database), `list` never shows it, `revoke` turns it off.
#[tokio::test]
async fn keys_are_added_listed_and_revoked_from_the_command_line() {
    let data = crate::pg::temp_dir("keys-cli");
    let keys = |args: &[&str]| {
        let out = std::process::Command::new(env!("CARGO_BIN_EXE_otofit"))
            .arg("keys")
            .args(args)
            .args(["--data-dir", data.to_str().unwrap()])
            .output()
            .unwrap();
        let text = |b: &[u8]| String::from_utf8_lossy(b).to_string();
        (out.status.success(), text(&out.stdout), text(&out.stderr))
    };
    let (ok, key, err) = keys(&["add", "--tenant", "clinic-a"]);
    assert!(ok, "{err}");
    let key = key.trim().to_string();
    assert!(key.starts_with("otofit_") && key.len() > 70, "{key}");
    let id = key.split('_').nth(1).unwrap().to_string();
    assert!(err.contains(&id) && err.contains("clinic-a"), "{err}");
    let (ok, _, err) = keys(&["add", "--tenant", "ops", "--admin"]);
    assert!(ok, "{err}");
    let (ok, list, _) = keys(&["list"]);
    assert!(ok && list.contains(&id) && list.contains("clinic-a") && list.contains("ops"), "{list}");
    assert!(!list.contains(&key[20..]), "list shows no key: {list}");
    let store = otofit::store::Store::open(&data.join("otofit.db")).await.unwrap();
    let owner = store.key_owner(&otofit::store::key_hash(&key)).await.unwrap();
    assert_eq!(owner, Some(otofit::store::KeyOwner { tenant: "clinic-a".into(), admin: false }));
    let (ok, _, err) = keys(&["revoke", &id]);
    assert!(ok, "{err}");
    assert_eq!(store.key_owner(&otofit::store::key_hash(&key)).await.unwrap(), None);
    let (_, list, _) = keys(&["list", "--json"]);
    let list: Value = serde_json::from_str(&list).unwrap();
    let revoked = list.as_array().unwrap().iter().find(|k| k["id"] == id.as_str()).unwrap();
    assert!(revoked["revoked_at"].is_string(), "{revoked}");
    let (ok, _, err) = keys(&["revoke", "nope"]);
    assert!(!ok && err.contains("no key 'nope'"), "{err}");
    let (ok, _, err) = keys(&["add", "--tenant", "../etc"]);
    assert!(!ok && err.contains("--tenant"), "{err}");
}

/// One tenant cannot fill the whole queue: at its own limit (`--max-queue-per-tenant`)
/// its posts get a 429 naming that limit while another tenant's still go in, up to the
/// queue's limit (`--max-queue`), named in its own 429. On both backends.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_tenant_cannot_fill_the_whole_queue() {
    for (name, db) in backends().await {
        let store = otofit::store::Store::connect(&db).await.unwrap();
        let data = crate::pg::temp_dir(&format!("tenant-queue-{name}"));
        let mut ctx = Arc::into_inner(ctx_on(store, &data, "test", Duration::from_secs(30))).unwrap();
        (ctx.max_queue, ctx.max_queue_per_tenant) = (3, 2);
        let ctx = Arc::new(ctx);
        let app = router(AppState::new(ctx.clone(), vec![]));
        let alpha = ctx.store.add_key("alpha", false).await.unwrap().key;
        let beta = ctx.store.add_key("beta", false).await.unwrap().key;
        let job = || Some(json!({"kind": "simulate", "params": {"n": 10}}));
        for _ in 0..2 {
            assert_eq!(send(&app, Some(&alpha), "POST", "/jobs", job()).await.0, StatusCode::ACCEPTED, "{name}");
        }
        let (status, p) = send(&app, Some(&alpha), "POST", "/jobs", job()).await;
        assert_eq!(status, StatusCode::TOO_MANY_REQUESTS, "{name}: {p}");
        let detail = p["detail"].as_str().unwrap();
        assert!(detail.contains("--max-queue-per-tenant") && detail.contains("'alpha'"), "{name}: {detail}");
        // Beta still gets in, until the queue as a whole is full.
        assert_eq!(send(&app, Some(&beta), "POST", "/jobs", job()).await.0, StatusCode::ACCEPTED, "{name}");
        let (status, p) = send(&app, Some(&beta), "POST", "/jobs", job()).await;
        assert_eq!(status, StatusCode::TOO_MANY_REQUESTS, "{name}: {p}");
        let detail = p["detail"].as_str().unwrap();
        assert!(detail.contains("(--max-queue)") && !detail.contains("per-tenant"), "{name}: {detail}");
        // A job of alpha's ends: alpha may post again.
        let claimed = ctx.store.claim("test", Duration::from_secs(30)).await.unwrap().unwrap();
        let token = claimed.lease_token.unwrap();
        assert!(ctx.store.finish(&claimed.id, &token, otofit::store::JobState::Succeeded, None, None).await.unwrap());
        assert_eq!(send(&app, Some(&alpha), "POST", "/jobs", job()).await.0, StatusCode::ACCEPTED, "{name}");
    }
}

/// The flags: --max-queue-per-tenant defaults to half of --max-queue and must lie in
/// 1..=--max-queue; an error names the flag.
#[test]
fn queue_flags_are_checked_naming_the_flag() {
    use otofit::cli::serve::queue_bounds;
    assert_eq!(queue_bounds(64, None).unwrap(), otofit::store::QueueBounds { queue: 64, per_tenant: 32 });
    assert_eq!(queue_bounds(1, None).unwrap().per_tenant, 1);
    assert!(queue_bounds(8, Some(9)).unwrap_err().to_string().contains("--max-queue-per-tenant"));
    assert!(queue_bounds(8, Some(0)).unwrap_err().to_string().contains("--max-queue-per-tenant"));
    assert!(queue_bounds(0, None).unwrap_err().to_string().contains("--max-queue"));
}

/// Unknown query parameters of the list routes are refused (400, problem+json, the
/// parameter named) instead of silently ignored; known ones still work.
#[tokio::test]
async fn unknown_query_parameters_of_list_routes_are_named() {
    let data = crate::pg::temp_dir("strict-query");
    let store = otofit::store::Store::open(&data.join("otofit.db")).await.unwrap();
    let ctx = ctx_on(store, &data, "test", Duration::from_secs(30));
    let app = router(AppState::new(ctx, vec![]));
    for (uri, name, takes) in [
        ("/jobs?limt=5", "limt", "takes state or limit"),
        ("/jobs?state=queued&tenant=beta", "tenant", "takes state or limit"),
        ("/models?limit=3", "limit", "takes none"),
    ] {
        let req = Request::get(uri).body(Body::empty()).unwrap();
        let res = app.clone().oneshot(req).await.unwrap();
        assert_eq!(res.status(), StatusCode::BAD_REQUEST, "{uri}");
        assert_eq!(res.headers()[header::CONTENT_TYPE], "application/problem+json", "{uri}");
        let bytes = axum::body::to_bytes(res.into_body(), usize::MAX).await.unwrap();
        let p: Value = serde_json::from_slice(&bytes).unwrap();
        assert_eq!(p["errors"][0]["field"], name, "{uri}: {p}");
        let detail = p["detail"].as_str().unwrap();
        assert!(detail.contains(&format!("'{name}'")) && detail.contains(takes), "{uri}: {detail}");
    }
    for uri in ["/jobs?state=queued&limit=5", "/jobs", "/models"] {
        assert_eq!(send(&app, None, "GET", uri, None).await.0, StatusCode::OK, "{uri}");
    }
}
