//! Clients that send their request body slowly hold no inference slot: a real /infer is
//! answered at its usual latency while 70 connections trickle bodies, and the trickling
//! clients themselves get 429 (too many from one address) or 408 (body too slow).

use crate::http::{default_model, nominal_request};
use crate::pg::temp_dir;
use otofit::http::conn::ClientAddr;
use otofit::http::{AppState, BODY_DEADLINE, InferLimits, UPLOADS_PER_ADDRESS, router};
use std::net::SocketAddr;
use std::time::{Duration, Instant};
use tokio::io::{AsyncReadExt, AsyncWriteExt};
use tokio::net::{TcpSocket, TcpStream};

/// One request over a fresh connection from 127.0.0.1: (status, seconds).
async fn post(addr: SocketAddr, body: &str) -> (u16, f64) {
    let t0 = Instant::now();
    let mut s = TcpStream::connect(addr).await.unwrap();
    let head = format!(
        "POST /infer HTTP/1.1\r\nHost: 127.0.0.1\r\nContent-Type: application/json\r\nContent-Length: {}\r\nConnection: close\r\n\r\n",
        body.len()
    );
    s.write_all(head.as_bytes()).await.unwrap();
    s.write_all(body.as_bytes()).await.unwrap();
    let mut out = Vec::new();
    s.read_to_end(&mut out).await.unwrap();
    (status_of(&out), t0.elapsed().as_secs_f64())
}

fn status_of(reply: &[u8]) -> u16 {
    let text = String::from_utf8_lossy(reply);
    text.split(' ').nth(1).and_then(|s| s.parse().ok()).unwrap_or(0)
}

/// A client at 127.0.0.2 that announces a 100 kB body and sends a byte every 100 ms until
/// it is answered (or 3 deadlines pass): the status it got.
async fn trickle(addr: SocketAddr) -> u16 {
    let sock = TcpSocket::new_v4().unwrap();
    sock.bind("127.0.0.2:0".parse().unwrap()).unwrap();
    let mut s = sock.connect(addr).await.unwrap();
    let head =
        "POST /infer HTTP/1.1\r\nHost: 127.0.0.1\r\nContent-Type: application/json\r\nContent-Length: 100000\r\n\r\n{";
    s.write_all(head.as_bytes()).await.unwrap();
    let (mut rd, mut wr) = s.into_split();
    let writer = tokio::spawn(async move {
        while wr.write_all(b" ").await.is_ok() {
            tokio::time::sleep(Duration::from_millis(100)).await;
        }
    });
    let mut out = vec![0u8; 512];
    let n = tokio::time::timeout(3 * BODY_DEADLINE, rd.read(&mut out)).await.ok().and_then(|r| r.ok()).unwrap_or(0);
    writer.abort();
    status_of(&out[..n])
}

fn median(mut v: Vec<f64>) -> f64 {
    v.sort_by(f64::total_cmp);
    v[v.len() / 2]
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn trickling_bodies_hold_no_inference_slot() {
    let dir = temp_dir("slow");
    let limits = InferLimits { concurrency: 4, ..InferLimits::default() };
    let ctx = otofit::cli::serve::open_with(&dir, &default_model(), 8, limits).await.unwrap();
    let app = router(AppState::new(ctx, vec![])).into_make_service_with_connect_info::<ClientAddr>();
    let listener = tokio::net::TcpListener::bind("127.0.0.1:0").await.unwrap();
    let addr = listener.local_addr().unwrap();
    tokio::spawn(async move { axum::serve(listener, app).await });
    let mut req = nominal_request();
    req["samples"] = serde_json::json!(200);
    req["return_samples"] = serde_json::json!(false);
    let body = req.to_string();
    post(addr, &body).await; // the model loads on first use
    let mut quiet = Vec::new();
    for _ in 0..7 {
        let (status, s) = post(addr, &body).await;
        assert_eq!(status, 200);
        quiet.push(s);
    }
    let slow: Vec<_> = (0..70).map(|_| tokio::spawn(trickle(addr))).collect();
    tokio::time::sleep(Duration::from_millis(500)).await;
    let mut loaded = Vec::new();
    for _ in 0..7 {
        let (status, s) = post(addr, &body).await;
        assert_eq!(status, 200, "a real /infer beside 70 trickling bodies");
        loaded.push(s);
    }
    let (q, l) = (median(quiet), median(loaded));
    eprintln!("/infer p50: {:.1} ms unloaded, {:.1} ms beside 70 trickling bodies ({:.2}×)", q * 1e3, l * 1e3, l / q);
    assert!(l <= 2.0 * q + 0.05, "p50 {l:.3} s beside slow clients vs {q:.3} s unloaded");
    let mut seen = std::collections::BTreeMap::new();
    for c in slow {
        *seen.entry(c.await.unwrap()).or_insert(0) += 1;
    }
    eprintln!("the trickling clients got {seen:?}");
    assert_eq!(seen.get(&429), Some(&(70 - UPLOADS_PER_ADDRESS)), "{seen:?}");
    assert_eq!(seen.get(&408), Some(&UPLOADS_PER_ADDRESS), "{seen:?}");
}
