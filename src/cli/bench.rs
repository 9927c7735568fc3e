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
