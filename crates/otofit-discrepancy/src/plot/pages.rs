//! Report pages composed from figures and tables, shared by the CLI and the service.

use super::html::Page;
use super::{DRAW, MAP, OBS, Series, spectra};
use crate::sim::PARAMS;
use crate::sim::output::MEASURES;
use crate::stats::spearman_per_block;

/// A re-simulation's figure and page, and ρ per row and measure against the observation.
pub struct Resimulation {
    /// The figure: spectra of the re-simulated rows over the observation.
    pub svg: String,
    /// The page showing the figure.
    pub html: String,
    /// Spearman ρ per row and measure against the observation; `None` without an observation.
    pub rho: Option<Vec<Vec<f64>>>,
}

/// Rows re-simulated (the first drawn as the MAP), over the observation when given.
pub fn resimulation(freqs: &[f64], theta: &[Vec<f64>], x: &[&[f64]], obs: Option<&[f64]>) -> Resimulation {
    let mut series = Vec::new();
    if let Some(o) = obs {
        series.push(Series { x: o, color: OBS, width: 2.0, opacity: 1.0, label: Some("observation") });
    }
    for (k, row) in x.iter().enumerate().skip(1).take(20) {
        series.push(Series {
            x: row,
            color: DRAW,
            width: 1.0,
            opacity: 0.5,
            label: (k == 1).then_some("other rows (e.g. posterior draws)"),
        });
    }
    if let Some(first) = x.first() {
        series.push(Series { x: first, color: MAP, width: 1.5, opacity: 1.0, label: Some("first row (e.g. the MAP)") });
    }
    let svg = spectra("Re-simulated spectra", freqs, &[], &series);
    let rho = obs.map(|o| x.iter().map(|row| spearman_per_block(row, o, MEASURES.len())).collect::<Vec<_>>());
    let mut p = Page::new("otofit re-simulation");
    p.text(&format!("{} rows re-simulated, {} succeeded.", theta.len(), x.len()));
    let mut head = vec!["row"];
    head.extend(PARAMS.iter().map(|p| p.name));
    p.heading("Parameter rows").table(
        &head,
        theta
            .iter()
            .enumerate()
            .map(|(i, r)| std::iter::once(i.to_string()).chain(r.iter().map(|v| format!("{v:.3e}"))).collect())
            .collect(),
    );
    if let Some(rho) = &rho {
        let mut head = vec!["row"];
        head.extend(MEASURES.iter().map(|m| m.name));
        head.push("mean");
        p.heading("Spearman ρ against the observation").table(
            &head,
            rho.iter()
                .enumerate()
                .map(|(i, r)| {
                    std::iter::once(i.to_string())
                        .chain(r.iter().map(|v| format!("{v:.3}")))
                        .chain(std::iter::once(format!("{:.3}", r.iter().sum::<f64>() / r.len() as f64)))
                        .collect()
                })
                .collect(),
        );
    }
    p.figure("spectra.svg", "re-simulated spectra (first row red, others blue), observation black");
    Resimulation { svg, html: p.render(), rho }
}
