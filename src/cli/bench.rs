//! `otofit bench ...`: speed figures measured on this machine (medians and ratios; the
//! README quotes them). Benchmarks, not tests: they never fail on a slow machine.

use crate::sim::batch::{self, Design};
use crate::sim::{Effects, Model, ModelConfig, Theta};
use anyhow::Result;
use clap::{Args, Subcommand};
use std::time::Instant;

#[derive(Args, Debug)]
pub struct BenchArgs {
    #[command(subcommand)]
    pub what: BenchWhat,
}

#[derive(Subcommand, Debug)]
pub enum BenchWhat {
    /// Simulator: one 50-frequency run on one core, and a parallel batch.
    Sim {
        /// Runs in the parallel batch.
        #[arg(long, default_value_t = 10_000)]
        runs: usize,
    },
    /// POST /infer latency: concurrent clients against an in-process server on loopback.
    Infer {
        #[arg(long, default_value_t = 16)]
        clients: usize,
        /// Requests per client.
        #[arg(long, default_value_t = 10)]
        requests: usize,
        #[arg(long, default_value_t = 1000)]
        samples: usize,
    },
    /// Discrepancy naming on hidden-effect cases (simulator-only pipeline).
    Discrepancy {
        /// Hidden cases per effect.
        #[arg(long, default_value_t = 20)]
        cases: usize,
        /// Effect-free cases (false alarms).
        #[arg(long, default_value_t = 50)]
        clean: usize,
        #[arg(long, default_value_t = 1)]
        seed: u64,
    },
}

pub fn run(args: BenchArgs) -> Result<()> {
    match args.what {
        BenchWhat::Sim { runs } => sim(runs),
        BenchWhat::Infer { clients, requests, samples } => infer(clients, requests, samples),
        BenchWhat::Discrepancy { cases, clean, seed } => super::diagnose::bench(cases, clean, seed),
    }
}

fn median(v: &mut [f64]) -> f64 {
    v.sort_by(f64::total_cmp);
    v[v.len() / 2]
}

fn sim(runs: usize) -> Result<()> {
    let model = Model::new(ModelConfig::default())?;
    let design = Design::default();
    let rows = design.draw(1, 0, runs.max(200));
    let mut runner = model.runner();
    let (t0, fx) = (Theta::nominal(), Effects::default());
    for _ in 0..20 {
        crate::sim::simulate(&mut runner, &t0, &fx)?; // warm up
    }
    let mut times: Vec<f64> = rows[..200]
        .iter()
        .map(|r| {
            let (theta, fx) = design.split(r);
            let t = Instant::now();
            let _ = crate::sim::simulate(&mut runner, &theta, &fx);
            t.elapsed().as_secs_f64() * 1e3
        })
        .collect();
    let one = median(&mut times);
    let t = Instant::now();
    let mut failed = 0;
    for first in (0..runs).step_by(1024) {
        let chunk = &rows[first..(first + 1024).min(runs)];
        failed += batch::run_rows(&model, &design, chunk, first, None).iter().filter(|r| r.is_err()).count();
    }
    let wall = t.elapsed().as_secs_f64();
    let threads = rayon::current_num_threads();
    println!("system: {} unknowns, {} non-zeros, {} frequencies", model.n_unknowns(), model.nnz(), model.frequencies().len());
    println!("one run, one core: median {one:.2} ms ({:.1} µs per frequency; target ≤ 2 ms)", one * 1e3 / model.frequencies().len() as f64);
    println!(
        "{runs} runs on {threads} threads: {wall:.2} s ({:.0} runs/s, {failed} failed; target ≤ 15 s for 10,000); speed-up over one core {:.2}×",
        runs as f64 / wall,
        runs as f64 / wall * one / 1e3
    );
    Ok(())
}

/// One HTTP/1.1 request over a fresh connection; returns (status line, milliseconds).
async fn post(addr: std::net::SocketAddr, body: &str) -> Result<(String, f64)> {
    use tokio::io::{AsyncReadExt, AsyncWriteExt};
    let t = Instant::now();
    let mut s = tokio::net::TcpStream::connect(addr).await?;
    let req = format!("POST /infer HTTP/1.1\r\nHost: bench\r\nContent-Type: application/json\r\nContent-Length: {}\r\nConnection: close\r\n\r\n{body}", body.len());
    s.write_all(req.as_bytes()).await?;
    let mut buf = Vec::new();
    s.read_to_end(&mut buf).await?;
    let status = String::from_utf8_lossy(&buf).lines().next().unwrap_or("").to_string();
    Ok((status, t.elapsed().as_secs_f64() * 1e3))
}

fn infer(clients: usize, requests: usize, samples: usize) -> Result<()> {
    let spec = include_str!("../../openapi.yaml");
    let example = spec.lines().map(str::trim).find_map(|l| l.strip_prefix("example: ").filter(|e| e.starts_with("{\"measurements\"")))
        .ok_or_else(|| anyhow::anyhow!("no /infer example in openapi.yaml"))?;
    let mut body: serde_json::Value = serde_json::from_str(example)?;
    body["samples"] = samples.into();
    body["return_samples"] = false.into();
    let body = body.to_string();
    let rt = tokio::runtime::Builder::new_multi_thread().enable_all().build()?;
    rt.block_on(async move {
        let dir = std::env::temp_dir().join(format!("otofit-bench-{}", std::process::id()));
        let ctx = super::serve::open(&dir, std::path::Path::new("models/default.otofit"), 8).await?;
        let app = crate::http::router(crate::http::AppState { ctx, key_hashes: std::sync::Arc::new(vec![]) });
        let listener = tokio::net::TcpListener::bind("127.0.0.1:0").await?;
        let addr = listener.local_addr()?;
        tokio::spawn(async move { axum::serve(listener, app).await });
        post(addr, &body).await?; // load the model once
        let t = Instant::now();
        let mut tasks = Vec::new();
        for _ in 0..clients {
            let body = body.clone();
            tasks.push(tokio::spawn(async move {
                let mut out = Vec::new();
                for _ in 0..requests {
                    out.push(post(addr, &body).await);
                }
                out
            }));
        }
        let mut lat = Vec::new();
        let mut bad = 0;
        for task in tasks {
            for r in task.await? {
                match r {
                    Ok((status, ms)) if status.contains(" 200 ") => lat.push(ms),
                    _ => bad += 1,
                }
            }
        }
        let wall = t.elapsed().as_secs_f64();
        lat.sort_by(f64::total_cmp);
        let q = |p: f64| lat[((lat.len() - 1) as f64 * p).round() as usize];
        println!("POST /infer, {samples} samples + MAP, {clients} concurrent clients × {requests} requests: p50 {:.0} ms, p90 {:.0} ms, p99 {:.0} ms, max {:.0} ms; {:.1} req/s; {bad} failed (targets p50 ≤ 100 ms, p99 ≤ 300 ms)", q(0.5), q(0.9), q(0.99), lat[lat.len() - 1], lat.len() as f64 / wall);
        let _ = std::fs::remove_dir_all(&dir);
        anyhow::Ok(())
    })
}
