//! Retries with backoff: a failed attempt of a job with attempts left goes
//! back to the queue and is not claimed before its backoff (doubling, capped) has passed;
//! GET /jobs/{id} shows when (`retry_at`) and why (`error`). On both backends.

use crate::pg::{backends, ctx_on, temp_dir};
use axum::body::Body;
use axum::http::{Request, StatusCode};
use otofit::http::{AppState, router};
use otofit::jobs::{self, Backoff};
use otofit::store::Store;
use serde_json::{Value, json};
use std::sync::Arc;
use std::time::{Duration, Instant};
use tower::ServiceExt;

const LEASE: Duration = Duration::from_secs(30);

#[test]
fn backoff_doubles_from_the_first_wait_up_to_its_cap() {
    let b = Backoff::default();
    let secs: Vec<u64> = [1, 2, 3, 6, 7, 8, 64, 1000].iter().map(|&k| b.after(k).as_secs()).collect();
    assert_eq!(secs, [10, 20, 40, 320, 600, 600, 600, 600]);
    let b = Backoff { first: Duration::from_millis(300), max: Duration::from_millis(500) };
    assert_eq!((b.after(1), b.after(2), b.after(3)), (b.first, b.max, b.max));
}

/// The store alone: a failed attempt waits out its backoff in the queue (not claimable
/// before), then is claimed as the next attempt; the last attempt fails for good; a stale
/// worker's failure changes nothing.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_failed_attempt_is_claimed_again_only_after_its_backoff() {
    for (name, db) in backends().await {
        let s = Store::connect(&db).await.unwrap();
        assert!(s.insert_job_within("r", "simulate", &json!({"n": 5}), 3, 8).await.unwrap());
        let wait = Duration::from_millis(800);
        for attempt in 1..=3 {
            let j = s.claim("w", LEASE).await.unwrap().expect("due: claimed");
            assert_eq!((j.id.as_str(), j.attempts), ("r", attempt), "{name}");
            let token = j.lease_token.unwrap();
            assert_eq!(s.fail_or_retry("r", "stale", "late", wait).await.unwrap(), None, "{name}: fenced");
            let state = s.fail_or_retry("r", &token, &format!("boom {attempt}"), wait).await.unwrap();
            let failed_at = Instant::now();
            let j = s.job("r").await.unwrap().unwrap();
            assert_eq!(j.error.as_deref(), Some(format!("boom {attempt}").as_str()), "{name}");
            if attempt == 3 {
                assert_eq!((state.as_deref(), j.state.as_str()), (Some("failed"), "failed"), "{name}");
                assert!(j.retry_at.is_none() && j.finished_at.is_some(), "{name}: {j:?}");
                break;
            }
            assert_eq!((state.as_deref(), j.state.as_str()), (Some("queued"), "queued"), "{name}");
            assert!(j.retry_at.is_some() && j.finished_at.is_none(), "{name}: {j:?}");
            // Queued, but not due: nobody claims it before the backoff has passed.
            let mut claimed = None;
            while claimed.is_none() {
                claimed = s.claim("w", LEASE).await.unwrap();
                if claimed.is_none() {
                    tokio::time::sleep(Duration::from_millis(20)).await;
                }
            }
            let after = failed_at.elapsed();
            assert!(after >= wait - Duration::from_millis(50), "{name}: claimed again {after:?} after the failure");
            // Put it back as it was (claimed by the loop above) for the next round.
            let t = claimed.unwrap().lease_token.unwrap();
            assert!(s.requeue("r", &t).await.unwrap(), "{name}");
        }
        // Another job queued behind a job in backoff is claimed meanwhile.
        assert!(s.insert_job_within("a", "simulate", &json!({"n": 5}), 3, 8).await.unwrap());
        assert!(s.insert_job_within("b", "simulate", &json!({"n": 5}), 3, 8).await.unwrap());
        let a = s.claim("w", LEASE).await.unwrap().unwrap();
        assert_eq!(a.id, "a");
        s.fail_or_retry("a", &a.lease_token.unwrap(), "boom", Duration::from_secs(60)).await.unwrap();
        assert_eq!(s.claim("w", LEASE).await.unwrap().map(|j| j.id).as_deref(), Some("b"), "{name}");
        assert!(s.claim("w", LEASE).await.unwrap().is_none(), "{name}: 'a' waits its 60 s");
    }
}

async fn get(app: &axum::Router, uri: &str) -> Value {
    let res = app.clone().oneshot(Request::get(uri).body(Body::empty()).unwrap()).await.unwrap();
    assert_eq!(res.status(), StatusCode::OK);
    serde_json::from_slice(&axum::body::to_bytes(res.into_body(), usize::MAX).await.unwrap()).unwrap()
}

/// Through the dispatcher: a simulate job that fails on every attempt (its dataset's
/// x.csv is taken by a folder) is retried after 0.6 s and then 1 s (capped), each time
/// visible in GET /jobs/{id} as queued with `retry_at` and the attempt's `error`, and
/// fails for good after its third attempt.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_failing_job_is_retried_with_backoff_visible_in_get_job() {
    for (name, db) in backends().await {
        let data = temp_dir(&format!("retry-{name}"));
        let store = Store::connect(&db).await.unwrap();
        std::fs::create_dir_all(data.join("datasets/blocked/x.csv/in-the-way")).unwrap();
        assert!(store.insert_job_within("blocked", "simulate", &json!({"n": 20}), 3, 8).await.unwrap());
        let ctx = Arc::into_inner(ctx_on(store.clone(), &data, "w", LEASE)).unwrap();
        let retry = Backoff { first: Duration::from_millis(600), max: Duration::from_millis(1000) };
        let ctx = Arc::new(ctx.with_settings(jobs::JobSettings { lease: LEASE, chunk_rows: 10_000, retry }));
        let app = router(AppState::new(ctx.clone(), vec![]));
        tokio::spawn(jobs::dispatcher(ctx.clone()));
        let mut seen = vec![]; // (attempts, retry_at, error) while waiting for a retry
        let t0 = Instant::now();
        let last = loop {
            let j = get(&app, "/jobs/blocked").await;
            if j["state"] == "failed" || t0.elapsed() > Duration::from_secs(60) {
                break j;
            }
            if j["state"] == "queued" && j["attempts"].as_i64() > Some(0) {
                let key = (j["attempts"].as_i64().unwrap(), j["retry_at"].clone(), j["error"].clone());
                if !seen.contains(&key) {
                    seen.push(key);
                }
            }
            tokio::time::sleep(Duration::from_millis(20)).await;
        };
        ctx.shutdown.store(true, std::sync::atomic::Ordering::Relaxed);
        assert_eq!((last["state"].as_str(), last["attempts"].as_i64()), (Some("failed"), Some(3)), "{name}: {last}");
        assert!(last["retry_at"].is_null() && last["error"].as_str().unwrap().contains("x.csv"), "{name}: {last}");
        assert_eq!(seen.iter().map(|s| s.0).collect::<Vec<_>>(), [1, 2], "{name}: {seen:?}");
        for (attempts, retry_at, error) in &seen {
            assert!(retry_at.is_string() && error.as_str().unwrap().contains("x.csv"), "{name} {attempts}: {seen:?}");
        }
        // Each retry's attempt started at its retry_at or later (both RFC 3339, UTC, ms).
        let hist = store.job("blocked").await.unwrap().unwrap();
        assert!(hist.started_at.as_deref().unwrap() >= seen[1].1.as_str().unwrap(), "{name}: {hist:?} {seen:?}");
        // No leftovers of the three attempts (removed right after the job's end is saved).
        let left = || -> Vec<String> {
            let names = std::fs::read_dir(data.join("datasets/blocked")).unwrap().flatten();
            names.map(|e| e.file_name().to_string_lossy().into_owned()).collect()
        };
        let t0 = Instant::now();
        while left() != ["x.csv"] && t0.elapsed() < Duration::from_secs(5) {
            tokio::time::sleep(Duration::from_millis(20)).await;
        }
        assert_eq!(left(), ["x.csv"], "{name}");
    }
}
