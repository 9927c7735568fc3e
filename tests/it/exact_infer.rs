//! POST /infer's `posterior: exact`: the likelihood's posterior within the request, by
//! importance sampling or short chains, with their diagnostics; the field validated by
//! name.

use crate::http::{app, call, nominal_request};
use axum::body::Body;
use axum::http::{Request, StatusCode, header};
use serde_json::json;
use tower::ServiceExt;

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn infer_with_the_exact_posterior_reports_its_sampler_and_its_verdict() {
    let (app, _, _dir) = app(vec![], 8, false).await;
    let mut req = nominal_request();
    req["posterior"] = json!("exact");
    req["samples"] = json!(200);
    let (status, _, body) = call(&app, "POST", "/infer", Some(req)).await;
    assert_eq!(status, StatusCode::OK, "{body}");
    let e = &body["exact"];
    let exact = e["exact"].as_bool().unwrap_or_else(|| panic!("no exact.exact: {e}"));
    // Importance sampling always runs first; the chains only where its weights fail.
    let w = &e["importance"];
    assert!(w["ess"].is_number() && w["rounds"].as_u64().unwrap() >= 1, "{w}");
    let g = &e["diagnostics"];
    match e["method"].as_str() {
        Some("chains") => {
            assert_eq!(g["acceptance"].as_array().map(Vec::len), Some(4), "{g}");
            assert!(g["deadline_hit"].is_boolean(), "{g}");
        }
        Some("importance") => assert!(!exact || g.is_null(), "{e}"),
        m => panic!("method {m:?}: {e}"),
    }
    assert!(body["timing_ms"]["exact"].as_f64().unwrap() > 0.0, "{}", body["timing_ms"]);
    if exact {
        assert!(e.get("reason").is_none(), "{e}");
        if e["method"] == "importance" {
            let s = &e["settings"]["importance"];
            assert!(w["ess"].as_f64().unwrap() >= s["ess_min"].as_f64().unwrap(), "{w}");
            assert!(w["pareto_k"].as_f64().unwrap() <= s["k_max"].as_f64().unwrap(), "{w}");
        } else {
            assert!(g["rhat"].as_f64().unwrap() <= e["settings"]["rhat_max"].as_f64().unwrap(), "{g}");
        }
    } else {
        // Not exact: the reason says why, and no reading is offered from these draws.
        assert!(!e["reason"].as_str().unwrap().is_empty(), "{e}");
        for d in e["differential"].as_array().unwrap() {
            assert_eq!(d["reading"], "unreliable", "{d}");
        }
    }
    // The flow's answer is there as without the option.
    assert_eq!(body["fit"]["ok"], true, "{}", body["fit"]);
    assert_eq!(body["samples_count"], 200);
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn an_unknown_posterior_is_a_422_naming_the_field() {
    let (app, _, _dir) = app(vec![], 8, false).await;
    let mut req = nominal_request();
    req["posterior"] = json!("mcmc");
    let (status, _, p) = call(&app, "POST", "/infer", Some(req)).await;
    assert_eq!(status, StatusCode::UNPROCESSABLE_ENTITY, "{p}");
    assert_eq!(p["errors"][0]["field"], "posterior", "{p}");
    // A text/csv body takes it as a query parameter, validated the same way.
    let csv = Request::builder()
        .method("POST")
        .uri("/infer?posterior=mcmc")
        .header(header::CONTENT_TYPE, "text/csv")
        .body(Body::from("Frequency [Hz],Absorbance\n226,0.04\n"))
        .unwrap();
    let res = app.clone().oneshot(csv).await.unwrap();
    assert_eq!(res.status(), StatusCode::UNPROCESSABLE_ENTITY);
    let bytes = axum::body::to_bytes(res.into_body(), usize::MAX).await.unwrap();
    let p: serde_json::Value = serde_json::from_slice(&bytes).unwrap();
    assert_eq!(p["errors"][0]["field"], "posterior", "{p}");
    assert!(p["errors"][0]["message"].as_str().unwrap().contains("flow, exact"), "{p}");
}
