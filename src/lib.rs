//! otofit: subject-specific middle-ear finite-element models tuned by neural posterior
//! estimation.
//!
//! The workspace's crates are its layers, lowest first: `otofit-sim` (the simulator),
//! `otofit-npe` (tables, the flow, training), `otofit-discrepancy` (measurements, the fit
//! check, the discrepancy workflow, figures), `otofit-service` (store, jobs, HTTP) and
//! `otofit-bench` (the SBI benchmark tasks). Cargo enforces the order: a crate depends
//! only on those below it. This crate is the command-line program (`cli`) and re-exports
//! each layer's modules under one name, so `otofit::sim::…` reads the same everywhere.

pub mod cli;

pub use otofit_bench as bench;
pub use otofit_discrepancy::{discrepancy, formats, measurements, plot, reference};
pub use otofit_npe::{dataset, flow, npe, stats};
pub use otofit_service::{artifacts, gate, http, jobs, metrics, store};
pub use otofit_sim as sim;
