//! The service layer over otofit's numerical core: state in SQLite or PostgreSQL
//! (`store`), the job queue and its workers (`jobs`), artifacts on disk or in S3
//! (`artifacts`), bounded inference slots (`gate`), counters (`metrics`) and the HTTP
//! API (`http`).

pub mod artifacts;
pub mod gate;
pub mod http;
pub mod jobs;
pub mod metrics;
pub mod store;

// The layers below, under the names the modules use for them (`crate::sim::…`).
use otofit_discrepancy::{discrepancy, formats, measurements, plot};
use otofit_npe::{dataset, npe};
use otofit_sim as sim;
