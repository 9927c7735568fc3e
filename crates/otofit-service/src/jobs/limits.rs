//! Bounds on the work one job (or one CLI command) may ask for, defined once: the HTTP
//! validation (`JobSpec::parse`) and the CLI flags check the same ranges.

use std::fmt::Display;
use std::ops::RangeInclusive;

/// Rows held in memory at once: given θ rows of a simulate job, a chunk, a diagnose
/// job's extended training set.
pub const MAX_ROWS: usize = 100_000;
/// Prior draws of one simulate job (`params.n`). Chunked and streamed to disk, so memory
/// does not grow with n; disk does (~3.5 KB per row of x.csv: ~3.5 GB at the top).
pub const SIMULATE_ROWS: RangeInclusive<usize> = 1..=1_000_000;
/// Given θ rows of a simulate job (`params.theta`, in the request body).
pub const THETA_ROWS: RangeInclusive<usize> = 1..=MAX_ROWS;
/// Rows of a resimulate job.
pub const RESIMULATE_ROWS: RangeInclusive<usize> = 1..=1_000;
/// Training epochs (train; diagnose's extended model; `otofit train`/`diagnose`).
pub const EPOCHS: RangeInclusive<usize> = 1..=5_000;
/// Flows in a trained ensemble.
pub const ENSEMBLE: RangeInclusive<usize> = 1..=16;
/// Rows of a diagnose job's extended training set.
pub const TRAIN_ROWS: RangeInclusive<usize> = 100..=MAX_ROWS;
/// Effect-free simulations of a diagnose job's null distribution: fewer than 5 have no
/// 97.5 % quantile worth the name (0 once disabled every alarm).
pub const NULL_CASES: RangeInclusive<usize> = 5..=1_000;

/// Metropolis steps of an exact posterior (exact jobs, `otofit infer --exact`): from the
/// length measured calibrated to twice it.
pub const EXACT_STEPS: RangeInclusive<usize> =
    crate::discrepancy::exact::MIN_STEPS..=crate::discrepancy::exact::MAX_STEPS;

/// `Err("must be A..=B, got V")` when `v` is outside `range`.
pub fn check<T: PartialOrd + Display>(range: &RangeInclusive<T>, v: T) -> Result<(), String> {
    if range.contains(&v) { Ok(()) } else { Err(format!("must be {}..={}, got {v}", range.start(), range.end())) }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn check_names_the_range_and_the_value() {
        assert_eq!(check(&EPOCHS, 1), Ok(()));
        assert_eq!(check(&EPOCHS, 5000), Ok(()));
        assert_eq!(check(&EPOCHS, 0), Err("must be 1..=5000, got 0".into()));
        assert_eq!(check(&ENSEMBLE, 17), Err("must be 1..=16, got 17".into()));
    }
}
