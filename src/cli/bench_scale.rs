//! `otofit bench scale`: dataset generation and training at 1, 2, 4, … threads up to the
//! machine's cores, with the speed-up and the efficiency (speed-up per thread) of each.
//! A benchmark, not a test: run it on a quiet machine, its numbers are only as good.

use crate::dataset::{self, DatasetRun, Format, Rows};
use crate::npe::{self, TrainSettings};
use crate::sim::batch::{self, Design, Noise};
use crate::sim::{Model, ModelConfig};
use anyhow::{Context, Result, bail};
use clap::Args;
use std::time::Instant;

/// Arguments of `otofit bench scale`.
#[derive(Args, Debug)]
pub struct ScaleArgs {
    /// Rows simulated and written at each thread count (CSV and .npy each).
    #[arg(long, default_value_t = 20_000)]
    pub rows: usize,
    /// Rows of the training table (the first rows of the simulated one).
    #[arg(long, default_value_t = 5_000)]
    pub train_rows: usize,
    /// Training epochs timed at each thread count (batch 200, the default recipe).
    #[arg(long, default_value_t = 3)]
    pub epochs: usize,
    /// The most threads tried (default: the machine's cores).
    #[arg(long)]
    pub max_threads: Option<usize>,
}

/// The thread counts tried: 1, 2, 4, … and the maximum itself.
fn thread_counts(max: usize) -> Vec<usize> {
    let mut v: Vec<usize> = std::iter::successors(Some(1usize), |t| Some(t * 2)).take_while(|&t| t < max).collect();
    v.push(max);
    v
}

/// A scratch folder, removed with everything in it when dropped.
struct Scratch(std::path::PathBuf);

impl Drop for Scratch {
    fn drop(&mut self) {
        let _ = std::fs::remove_dir_all(&self.0);
    }
}

/// One thread count's times, seconds.
struct Times {
    threads: usize,
    csv: f64,
    npy: f64,
    epoch: f64,
}

pub fn run(args: ScaleArgs) -> Result<()> {
    let cores = std::thread::available_parallelism().map_or(1, |n| n.get());
    let max = args.max_threads.unwrap_or(cores);
    if !(1..=1024).contains(&max) {
        bail!("--max-threads must be 1..=1024, got {max}");
    }
    if args.rows == 0 || args.train_rows == 0 || args.train_rows > args.rows || args.epochs == 0 {
        bail!("--rows, --train-rows (≤ --rows) and --epochs must be positive");
    }
    let config = ModelConfig::default();
    let preset = config.preset;
    let model = Model::new(config)?;
    let design = Design::default();
    let noise = Noise { std: batch::default_noise_std(&model), scale: 1.0, seed: 0 };
    let rows = Rows::Prior { n: args.rows, seed: 0 };
    let scratch = Scratch(std::env::temp_dir().join(format!("otofit-bench-scale-{}", std::process::id())));
    let load = std::fs::read_to_string("/proc/loadavg").unwrap_or_default();
    println!(
        "{cores} cores; load average {}; {} rows simulated and written, training on {} rows for {} epochs",
        load.split_whitespace().take(3).collect::<Vec<_>>().join(" "),
        args.rows,
        args.train_rows,
        args.epochs
    );
    let mut table = Vec::new();
    for threads in thread_counts(max) {
        let pool = rayon::ThreadPoolBuilder::new().num_threads(threads).build()?;
        let t = pool.install(|| -> Result<Times> {
            let mut secs = [0.0; 2];
            for (i, format) in [Format::Csv, Format::Npy].into_iter().enumerate() {
                let dir = scratch.0.join(format!("{threads}-{format:?}"));
                let run = DatasetRun { model: &model, design: &design, rows: &rows, noise: &noise, preset, format };
                let t0 = Instant::now();
                dataset::simulate_to_dir(&run, &dir, &mut |_, _| true)?;
                secs[i] = t0.elapsed().as_secs_f64();
            }
            let mut ds = npe::Dataset::load(&scratch.0.join(format!("{threads}-Npy")))?;
            ds.theta.truncate(args.train_rows);
            ds.x.truncate(args.train_rows);
            let settings =
                TrainSettings { max_epochs: args.epochs, patience: args.epochs + 1, ..TrainSettings::default() };
            let t0 = Instant::now();
            npe::train(&ds, &settings, &mut |_| true).context("training")?;
            let epoch = t0.elapsed().as_secs_f64() / args.epochs as f64;
            for f in ["Csv", "Npy"] {
                std::fs::remove_dir_all(scratch.0.join(format!("{threads}-{f}")))?;
            }
            Ok(Times { threads, csv: secs[0], npy: secs[1], epoch })
        })?;
        println!(
            "{:>3} threads: simulate+CSV {:.2} s ({:.0} rows/s), simulate+npy {:.2} s ({:.0} rows/s), training {:.2} s/epoch",
            t.threads,
            t.csv,
            args.rows as f64 / t.csv,
            t.npy,
            args.rows as f64 / t.npy,
            t.epoch
        );
        table.push(t);
    }
    let one = &table[0];
    println!("\nthreads | simulate+CSV speed-up (efficiency) | simulate+npy | training epoch");
    for t in &table {
        let ratio = |base: f64, now: f64| base / now;
        let (c, n, e) = (ratio(one.csv, t.csv), ratio(one.npy, t.npy), ratio(one.epoch, t.epoch));
        let per = t.threads as f64;
        println!(
            "{:>7} | {c:>5.2}× ({:>3.0} %) | {n:>5.2}× ({:>3.0} %) | {e:>5.2}× ({:>3.0} %)",
            t.threads,
            100.0 * c / per,
            100.0 * n / per,
            100.0 * e / per
        );
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn thread_counts_double_up_to_the_cores() {
        assert_eq!(thread_counts(1), [1]);
        assert_eq!(thread_counts(2), [1, 2]);
        assert_eq!(thread_counts(6), [1, 2, 4, 6]);
        assert_eq!(thread_counts(16), [1, 2, 4, 8, 16]);
    }
}
