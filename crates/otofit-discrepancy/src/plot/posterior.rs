//! A posterior's corner plot over a model's prior box, for the CLI's figures and for
//! POST /infer's `plot=corner`.

use crate::npe::{Param, Scale};

/// Corner plot of posterior samples (rows of natural θ) over the prior box of `params`:
/// ticks in each parameter's unit, the MAP in red and, when known, the truth in green.
pub fn posterior_corner(
    params: &[Param],
    samples: &[Vec<f64>],
    truth: Option<&[f64]>,
    map: &[f64],
    title: &str,
) -> String {
    let dims: Vec<super::Dim<'_>> = params
        .iter()
        .enumerate()
        .map(|(k, p)| super::Dim {
            name: &p.name,
            unit: &p.unit,
            low: p.low,
            high: p.high,
            log: p.scale == Scale::Log10,
            truth: truth.map(|t| t[k]),
            map: Some(map[k]),
        })
        .collect();
    super::corner(title, &dims, samples)
}
