//! Command-line interface: one submodule per command, each a thin layer over the core.

use clap::{Parser, Subcommand};

pub mod attach;
pub mod bench;
mod bench_c2st;
mod bench_exact;
mod bench_fit;
mod bench_scale;
pub mod calibrate;
pub mod diagnose;
mod drum;
pub mod explain;
pub mod import;
pub mod infer;
pub mod keys;
mod progress;
pub mod serve;
pub mod simulate;
pub mod study;
pub mod train;
pub mod worker;

/// The command line: one subcommand.
#[derive(Parser, Debug)]
#[command(name = "otofit", version, about = "Middle-ear FE models tuned by neural posterior estimation")]
pub struct Cli {
    /// The subcommand to run.
    #[command(subcommand)]
    pub command: Command,
}

/// The subcommands of `otofit`.
#[derive(Subcommand, Debug)]
pub enum Command {
    /// Simulate parameter sets (prior draws or given rows) into a dataset folder.
    Simulate(simulate::SimulateArgs),
    /// Find where model and measurement disagree, name the missing effect, add it.
    Diagnose(diagnose::DiagnoseArgs),
    /// The seed study's analyses (validate, noise, size, reference): tables, JSON and SVG
    /// figures.
    Study(study::StudyArgs),
    /// Run the HTTP service (API + job queue).
    Serve(serve::ServeArgs),
    /// Run jobs from a shared job table (PostgreSQL), without HTTP.
    Worker(worker::WorkerArgs),
    /// API keys of the service: add (per tenant), list, revoke.
    Keys(keys::KeysArgs),
    /// Train a posterior estimator on a dataset folder.
    Train(train::TrainArgs),
    /// Posterior samples, MAP and summaries for observations.
    Infer(infer::InferArgs),
    /// Coverage and SBC ranks on held-out simulations (a table, or JSON; --report: JSON
    /// and an SVG figure).
    Calibrate(calibrate::CalibrateArgs),
    /// Measure speed (simulator, ...) on this machine.
    Bench(bench::BenchArgs),
    /// Store an unmasked model inside a masked one: it then answers the ears with every
    /// measure present (sharper there), the masked one every subset.
    Attach(attach::AttachArgs),
    /// Convert a device or database export into an observation (JSON, POST /infer format).
    Import(import::ImportArgs),
}

/// Runs the subcommand.
pub fn run(cli: Cli) -> anyhow::Result<()> {
    match cli.command {
        Command::Simulate(args) => simulate::run(args),
        Command::Bench(args) => bench::run(args),
        Command::Train(args) => train::run(args),
        Command::Serve(args) => serve::run(args),
        Command::Worker(args) => worker::run(args),
        Command::Keys(args) => keys::run(args),
        Command::Study(args) => study::run(args),
        Command::Diagnose(args) => diagnose::run(args),
        Command::Infer(args) => infer::run(args),
        Command::Calibrate(args) => calibrate::run(args),
        Command::Import(args) => import::run(args),
        Command::Attach(args) => attach::run(args),
    }
}
