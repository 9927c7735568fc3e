//! The diagnosis as one HTML page: verdict, statistics against their null thresholds,
//! where the misfit lies, the candidates, and the figures before and after.

use super::Verdict;
use super::workflow::{Check, Report};
use crate::plot::html::Page;
use crate::sim::params::PARAMS;

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

impl Report {
    /// The page; figures are linked by the names in `self.figures`.
    pub fn html(&self) -> String {
        let mut p = Page::new("otofit diagnosis");
        let verdict = match self.verdict {
            Verdict::NoDiscrepancy => {
                "no discrepancy: the base model explains the observation within its noise".to_string()
            }
            Verdict::EffectNamed => format!("effect named: {}", self.named.unwrap_or("?")),
            Verdict::Unexplained => {
                "unexplained: model and observation disagree, and no candidate effect explains it".to_string()
            }
        };
        p.heading("Verdict").text(&verdict);
        let t = &self.thresholds;
        p.heading("Statistics").table(
            &["statistic", "value", "threshold (97.5 % quantile of effect-free data)"],
            vec![
                vec![
                    "reduced χ², base posterior-predictive".into(),
                    format!("{:.2}", self.before.reduced_chi2),
                    format!("{:.2}", t.base_reduced_chi2),
                ],
                vec![
                    "best candidate's χ² drop".into(),
                    self.candidates.first().map_or("—".into(), |c| format!("{:.1} ({})", c.chi2_drop(), c.effect)),
                    format!("{:.1}", t.best_drop),
                ],
                vec!["reduced χ² that counts as explained".into(), "".into(), format!("≤ {:.2}", t.explained)],
            ],
        );
        if let (Some(a), Some(e)) = (&self.after, &self.effect_posterior) {
            p.text(&format!("After adding {} and retraining: reduced χ² {:.2} → {:.2}; {} median {:.3e} {} (90 % interval {:.3e} … {:.3e}).", e.effect, self.before.reduced_chi2, a.reduced_chi2, e.effect, e.median, e.unit, e.q05, e.q95));
        }
        p.heading("Where the misfit lies");
        if self.before.bands.is_empty() {
            p.text("No band of three or more neighbouring frequencies with |z| > 2.5.");
        } else {
            p.table(&["band"], self.before.bands.iter().map(|b| vec![b.describe()]).collect());
        }
        p.heading("Candidate effects (best first)").table(
            &["effect", "fitted value", "90 % interval", "reduced χ²", "score (χ² drop − BIC)"],
            self.candidates
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
            .table(&["measure", "before", "after"], rho_rows(&self.before, self.after.as_ref()));
        p.heading("MAP parameters").table(
            &["parameter", "before", "after"],
            PARAMS
                .iter()
                .enumerate()
                .map(|(k, ps)| {
                    vec![
                        format!("{} ({})", ps.name, ps.unit),
                        format!("{:.3e}", self.map_before[k]),
                        self.map_after.as_ref().map_or("—".into(), |m| format!("{:.3e}", m[k])),
                    ]
                })
                .collect(),
        );
        p.heading("Figures");
        for (name, _) in &self.figures {
            let what = if name.starts_with("spectra") {
                "observation, MAP and posterior draws re-simulated, 90 % predictive band"
            } else {
                "standardised residuals per measure and frequency"
            };
            let when = if name.contains("after") { "after adding the effect" } else { "base model" };
            p.figure(name, &format!("{what} ({when})"));
        }
        p.text(&format!("Run time {:.1} s.", self.seconds));
        p.render()
    }
}
