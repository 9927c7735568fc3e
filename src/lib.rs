//! otofit: subject-specific middle-ear finite-element models tuned by neural posterior
//! estimation.
//!
//! The numerical core (`sim`, `flow`, `npe`) is synchronous, takes plain data plus a
//! config, and knows nothing of HTTP or SQL. `cli` holds the command-line glue.

pub mod bench;
pub mod cli;
pub mod dataset;
pub mod discrepancy;
pub mod flow;
pub mod formats;
pub mod http;
pub mod jobs;
pub mod measurements;
pub mod npe;
pub mod plot;
pub mod reference;
pub mod sim;
pub mod stats;
pub mod store;
