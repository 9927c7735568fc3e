//! Neural posterior estimation for otofit: simulation tables on disk (`dataset`), the
//! conditional spline flow (`flow`), training, sampling and calibration (`npe`), and the
//! small statistics every layer shares (`stats`). Synchronous, no I/O beyond its files.

pub mod dataset;
pub mod flow;
pub mod npe;
pub mod npy;
pub mod spd;
pub mod stats;

// The layer below, under the name the modules use for it (`crate::sim::…`).
use otofit_sim as sim;
