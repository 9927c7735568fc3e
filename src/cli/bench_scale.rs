//! `otofit bench scale`: dataset generation and training at 1, 2, 4, … threads up to the
//! machine's cores, with the speed-up and the efficiency (speed-up per thread) of each.
//! The training time is the median of the epochs' wall times (each with its validation
//! pass); with `--data` only the training on that dataset is timed. A benchmark, not a
//! test: run it on a quiet machine, its numbers are only as good.

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
    /// Training epochs timed at each thread count (the default recipe: batches of a
    /// tenth of the training rows, 64 to 1,000); the median epoch is reported.
    #[arg(long, default_value_t = 3)]
    pub epochs: usize,
    /// Time the training only, on this dataset folder (its first --train-rows rows),
    /// without simulating.
    #[arg(long)]
    pub data: Option<std::path::PathBuf>,
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

/// One thread count's times, seconds (simulation: `None` with `--data`).
struct Times {
    threads: usize,
    csv: Option<f64>,
    npy: Option<f64>,
    /// The median epoch.
    epoch: f64,
    /// Every epoch, in order.
    epochs: Vec<f64>,
}

/// The 1, 5 and 15 min load averages (empty where /proc has none).
fn load_average() -> String {
    let load = std::fs::read_to_string("/proc/loadavg").unwrap_or_default();
    load.split_whitespace().take(3).collect::<Vec<_>>().join(" ")
}

/// The median of `v` (the mean of the middle two for an even count).
fn median(v: &[f64]) -> f64 {
    let mut s = v.to_vec();
    s.sort_by(f64::total_cmp);
    let n = s.len();
    if n == 0 { f64::NAN } else { 0.5 * (s[(n - 1) / 2] + s[n / 2]) }
}

/// Trains on the first `rows` rows of `ds` for `epochs` epochs (no early stop) on the
/// current thread pool; each epoch's wall time.
fn train_epochs(mut ds: npe::Dataset, rows: usize, epochs: usize) -> Result<Vec<f64>> {
    if rows > ds.theta.len() {
        bail!("--train-rows {rows} is more than the dataset's {} usable rows", ds.theta.len());
    }
    ds.theta.truncate(rows);
    ds.x.truncate(rows);
    let settings = TrainSettings { max_epochs: epochs, patience: epochs + 1, ..TrainSettings::default() };
    let mut times = Vec::with_capacity(epochs);
    npe::train(&ds, &settings, &mut |r| {
        times.push(r.seconds);
        true
    })
    .context("training")?;
    Ok(times)
}

pub fn run(args: ScaleArgs) -> Result<()> {
    let cores = std::thread::available_parallelism().map_or(1, |n| n.get());
    let max = args.max_threads.unwrap_or(cores);
    if !(1..=1024).contains(&max) {
        bail!("--max-threads must be 1..=1024, got {max}");
    }
    let simulated = args.data.is_none();
    if args.rows == 0 || args.train_rows == 0 || (simulated && args.train_rows > args.rows) || args.epochs == 0 {
        bail!("--rows, --train-rows (≤ --rows) and --epochs must be positive");
    }
    let load = load_average();
    match &args.data {
        Some(_) => println!(
            "{cores} cores; load average {load}; training only, on {} rows for {} epochs",
            args.train_rows, args.epochs
        ),
        None => println!(
            "{cores} cores; load average {load}; {} rows simulated and written, training on {} rows for {} epochs",
            args.rows, args.train_rows, args.epochs
        ),
    }
    let config = ModelConfig::default();
    let preset = config.preset;
    let model = Model::new(config)?;
    let design = Design::default();
    let noise = Noise { std: batch::default_noise_std(&model), scale: 1.0, seed: 0 };
    let rows = Rows::Prior { n: args.rows, seed: 0 };
    let scratch = Scratch(std::env::temp_dir().join(format!("otofit-bench-scale-{}", std::process::id())));
    let mut table = Vec::new();
    for threads in thread_counts(max) {
        let pool = rayon::ThreadPoolBuilder::new().num_threads(threads).build()?;
        let t = pool.install(|| -> Result<Times> {
            if let Some(dir) = &args.data {
                let ds = npe::Dataset::load(dir).with_context(|| format!("reading {}", dir.display()))?;
                let epochs = train_epochs(ds, args.train_rows, args.epochs)?;
                return Ok(Times { threads, csv: None, npy: None, epoch: median(&epochs), epochs });
            }
            let mut secs = [0.0; 2];
            for (i, format) in [Format::Csv, Format::Npy].into_iter().enumerate() {
                let dir = scratch.0.join(format!("{threads}-{format:?}"));
                let run = DatasetRun { model: &model, design: &design, rows: &rows, noise: &noise, preset, format };
                let t0 = Instant::now();
                dataset::simulate_to_dir(&run, &dir, &mut |_, _| true)?;
                secs[i] = t0.elapsed().as_secs_f64();
            }
            let ds = npe::Dataset::load(&scratch.0.join(format!("{threads}-Npy")))?;
            let epochs = train_epochs(ds, args.train_rows, args.epochs)?;
            for f in ["Csv", "Npy"] {
                std::fs::remove_dir_all(scratch.0.join(format!("{threads}-{f}")))?;
            }
            Ok(Times { threads, csv: Some(secs[0]), npy: Some(secs[1]), epoch: median(&epochs), epochs })
        })?;
        let each: Vec<String> = t.epochs.iter().map(|e| format!("{e:.2}")).collect();
        let simulated = match (t.csv, t.npy) {
            (Some(c), Some(n)) => format!(
                "simulate+CSV {c:.2} s ({:.0} rows/s), simulate+npy {n:.2} s ({:.0} rows/s), ",
                args.rows as f64 / c,
                args.rows as f64 / n
            ),
            _ => String::new(),
        };
        println!(
            "{:>3} threads: {simulated}training {:.2} s/epoch (median; epochs {} s)",
            t.threads,
            t.epoch,
            each.join(", ")
        );
        table.push(t);
    }
    let one = &table[0];
    let ratio = |base: Option<f64>, now: Option<f64>, per: f64| match (base, now) {
        (Some(b), Some(n)) => format!("{:>5.2}× ({:>3.0} %)", b / n, 100.0 * b / n / per),
        _ => "    –".into(),
    };
    println!("\nthreads | simulate+CSV speed-up (efficiency) | simulate+npy | training epoch");
    for t in &table {
        let per = t.threads as f64;
        println!(
            "{:>7} | {} | {} | {}",
            t.threads,
            ratio(one.csv, t.csv, per),
            ratio(one.npy, t.npy, per),
            ratio(Some(one.epoch), Some(t.epoch), per)
        );
    }
    println!("load average at the end {}", load_average());
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

    #[test]
    fn the_median_epoch_is_the_middle_one() {
        assert_eq!(median(&[3.0, 1.0, 2.0]), 2.0);
        assert_eq!(median(&[4.0, 1.0, 3.0, 2.0]), 2.5);
        assert!(median(&[]).is_nan());
    }
}
