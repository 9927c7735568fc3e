//! Readings of one ear: measurements as devices export them (`measurements`, `formats`),
//! the normative reference ear (`reference`), the fit check and the discrepancy workflow
//! (`discrepancy`) and the figures that show them (`plot`). Synchronous, free of HTTP
//! and SQL.

pub mod discrepancy;
pub mod formats;
pub mod measurements;
pub mod plot;
pub mod reference;

// The layers below, under the names the modules use for them (`crate::sim::…`).
use otofit_npe::{dataset, npe, stats};
use otofit_sim as sim;
