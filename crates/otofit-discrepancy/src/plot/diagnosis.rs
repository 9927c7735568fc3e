//! The diagnosis drawn and written: its figures (spectra with the predictive band,
//! standardised residuals, before and after an effect is added), its HTML page (verdict,
//! statistics against their null thresholds, where the misfit lies, the candidates) and
//! [`write_report`], which writes them with report.json for the CLI and the service alike.

#![warn(missing_docs)]

use super::html::Page;
use super::{BAND, Band, DRAW, MAP, OBS, Series, residual_map, spectra};
use crate::dataset::FileError;
use crate::discrepancy::Verdict;
use crate::discrepancy::workflow::{Check, Report};
use crate::npe::NpeError;
use crate::sim::params::PARAMS;
use std::path::{Path, PathBuf};

/// The checks drawn: (label, check), before and (when the model was extended) after.
fn checks(r: &Report) -> Vec<(&'static str, &Check)> {
    let mut out = vec![("before", &r.before)];
    out.extend(r.after.as_ref().map(|a| ("after", a)));
    out
}

/// File names of the figures, in the order [`figures`] draws them.
pub fn figure_names(r: &Report) -> Vec<String> {
    checks(r).iter().flat_map(|(l, _)| [format!("spectra_{l}.svg"), format!("residuals_{l}.svg")]).collect()
}

/// The figures of one check: spectra (observation, MAP, draws, 90 % predictive band) and
/// the residual map.
fn check_figures(freqs: &[f64], label: &str, obs: &[f64], c: &Check) -> [(String, String); 2] {
    let mut series = vec![Series { x: obs, color: OBS, width: 2.0, opacity: 1.0, label: Some("observation") }];
    for d in &c.draws_x {
        series.push(Series { x: d, color: DRAW, width: 1.0, opacity: 0.35, label: None });
    }
    series.push(Series { x: &c.map_x, color: MAP, width: 1.5, opacity: 1.0, label: Some("MAP re-simulation") });
    [
        (
            format!("spectra_{label}.svg"),
            spectra(
                &format!("Spectra {label}: observation, MAP, draws, 90 % predictive band"),
                freqs,
                &[Band { lo: &c.lo, hi: &c.hi, color: BAND, label: "90 % predictive band" }],
                &series,
            ),
        ),
        (
            format!("residuals_{label}.svg"),
            residual_map(&format!("Standardised residuals {label} (observation − prediction)/σ"), freqs, &c.z),
        ),
    ]
}

/// The report's figures as (file name, SVG).
pub fn figures(r: &Report) -> Vec<(String, String)> {
    checks(r).iter().flat_map(|(l, c)| check_figures(&r.frequencies_hz, l, &r.observation, c)).collect()
}

/// Where [`write_report`] puts what is not in the report folder, and how report.json
/// links to it.
pub struct Links<'a> {
    /// A figure's link in report.json, from its file name.
    pub figure: &'a dyn Fn(&str) -> String,
    /// Where an extended model is saved, and its link in report.json.
    pub model: (PathBuf, String),
    /// The page's own link in report.json, if it has one (the service's).
    pub page: Option<String>,
}

/// Why the report could not be written.
#[derive(Debug, thiserror::Error)]
pub enum WriteError {
    /// A file or folder could not be written.
    #[error(transparent)]
    Io(#[from] FileError),
    /// The extended model could not be saved.
    #[error(transparent)]
    Model(#[from] NpeError),
    /// report.json could not be encoded.
    #[error("cannot encode report.json")]
    Json(#[from] serde_json::Error),
}

/// Writes the report folder `dir` (created): the figures, report.html, report.json
/// (temp-then-rename) and the extended model where `links` says. Returns report.json's
/// document: the report with links to its figures, model and page.
pub fn write_report(dir: &Path, r: &Report, links: &Links<'_>) -> Result<serde_json::Value, WriteError> {
    let io = |path: &Path| FileError::on("write", path);
    std::fs::create_dir_all(dir).map_err(io(dir))?;
    let figs = figures(r);
    for (name, svg) in &figs {
        std::fs::write(dir.join(name), svg).map_err(io(&dir.join(name)))?;
    }
    let mut doc = serde_json::to_value(r)?;
    if let Some(m) = &r.extended_model {
        let (path, link) = &links.model;
        if let Some(parent) = path.parent() {
            std::fs::create_dir_all(parent).map_err(io(parent))?;
        }
        m.save(path)?;
        doc["extended_model"] = link.clone().into();
    }
    doc["figures"] = figs.iter().map(|(n, _)| (links.figure)(n)).collect::<Vec<_>>().into();
    if let Some(page) = &links.page {
        doc["report"] = page.clone().into();
    }
    std::fs::write(dir.join("report.html"), html(r)).map_err(io(&dir.join("report.html")))?;
    let tmp = dir.join("report.json.tmp");
    std::fs::write(&tmp, serde_json::to_vec_pretty(&doc)?).map_err(io(&tmp))?;
    std::fs::rename(&tmp, dir.join("report.json")).map_err(io(&dir.join("report.json")))?;
    Ok(doc)
}

fn rho_rows(before: &Check, after: Option<&Check>) -> Vec<Vec<String>> {
    before
        .spearman
        .iter()
        .enumerate()
        .map(|(m, (name, r))| {
            vec![name.clone(), format!("{r:.3}"), after.map_or("—".into(), |a| format!("{:.3}", a.spearman[m].1))]
        })
        .collect()
}

/// The diagnosis page; figures are linked by the names [`figures`] gives them.
pub fn html(this: &Report) -> String {
    let mut p = Page::new("otofit diagnosis");
    p.heading("Verdict").text(&verdict(this));
    statistics(&mut p, this);
    p.heading("Where the misfit lies");
    if this.before.bands.is_empty() {
        p.text("No band of three or more neighbouring frequencies with |z| > 2.5.");
    } else {
        p.table(&["band"], this.before.bands.iter().map(|b| vec![b.describe()]).collect());
    }
    p.heading("Candidate effects (best first)").table(
        &["effect", "fitted value", "90 % interval", "reduced χ²", "score (χ² drop − BIC)"],
        this.candidates
            .iter()
            .map(|c| {
                vec![
                    c.effect.into(),
                    format!("{:.3e} {}", c.value, c.unit),
                    format!("{:.3e} … {:.3e}", c.interval90[0], c.interval90[1]),
                    format!("{:.2}", c.reduced_chi2),
                    format!("{:.1}", c.score),
                ]
            })
            .collect(),
    );
    p.heading("Spearman ρ, MAP re-simulation vs observation")
        .table(&["measure", "before", "after"], rho_rows(&this.before, this.after.as_ref()));
    p.heading("MAP parameters").table(&["parameter", "before", "after"], map_rows(this));
    figure_list(&mut p, this);
    p.text(&format!("Run time {:.1} s.", this.seconds));
    p.render()
}

fn verdict(this: &Report) -> String {
    match this.verdict {
        Verdict::NoDiscrepancy => {
            "no discrepancy: the base model explains the observation within its noise".to_string()
        }
        Verdict::EffectNamed => format!("effect named: {}", this.named.unwrap_or("?")),
        Verdict::Unexplained => {
            "unexplained: model and observation disagree, and no candidate effect explains it".to_string()
        }
    }
}

/// The two alarm statistics beside their thresholds, so that a reader sees by how much
/// the verdict was reached; then the extended model's outcome, when there is one.
fn statistics(p: &mut Page, this: &Report) {
    let t = &this.thresholds;
    p.heading("Statistics").table(
        &["statistic", "value", "threshold (97.5 % quantile of effect-free data)"],
        vec![
            vec![
                "reduced χ², base posterior-predictive".into(),
                format!("{:.2}", this.before.reduced_chi2),
                format!("{:.2}", t.base_reduced_chi2),
            ],
            vec![
                "best candidate's χ² drop".into(),
                this.candidates.first().map_or("—".into(), |c| format!("{:.1} ({})", c.chi2_drop(), c.effect)),
                format!("{:.1}", t.best_drop),
            ],
            vec!["reduced χ² that counts as explained".into(), "".into(), format!("≤ {:.2}", t.explained)],
        ],
    );
    p.text(&format!("Thresholds: {}.", this.null.describe()));
    if let (Some(a), Some(e)) = (&this.after, &this.effect_posterior) {
        p.text(&format!("After adding {} and retraining: reduced χ² {:.2} → {:.2}; {} median {:.3e} {} (90 % interval {:.3e} … {:.3e}).", e.effect, this.before.reduced_chi2, a.reduced_chi2, e.effect, e.median, e.unit, e.q05, e.q95));
    }
}

/// The MAP of each base parameter before and after the extension (the effect's own
/// value is in the extended model's posterior, not here).
fn map_rows(this: &Report) -> Vec<Vec<String>> {
    PARAMS
        .iter()
        .enumerate()
        .map(|(k, ps)| {
            vec![
                format!("{} ({})", ps.name, ps.unit),
                format!("{:.3e}", this.map_before[k]),
                this.map_after.as_ref().map_or("—".into(), |m| format!("{:.3e}", m[k])),
            ]
        })
        .collect()
}

fn figure_list(p: &mut Page, this: &Report) {
    p.heading("Figures");
    for name in figure_names(this) {
        let what = if name.starts_with("spectra") {
            "observation, MAP and posterior draws re-simulated, 90 % predictive band"
        } else {
            "standardised residuals per measure and frequency"
        };
        let when = if name.contains("after") { "after adding the effect" } else { "base model" };
        p.figure(&name, &format!("{what} ({when})"));
    }
}
