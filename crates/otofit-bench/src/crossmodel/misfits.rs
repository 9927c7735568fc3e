//! The suite's misfit ears through the discrepancy workflow: every ear of a published
//! model that the fit check refuses is diagnosed as `otofit diagnose` does (without the
//! extension's retraining), and the answer is scored by what it does to the gap between
//! the base model's best fit and a fit at the noise (reduced χ² 1). A named effect should
//! close at least half of that gap; otherwise the honest answer is `unexplained`; and a
//! named effect must never leave the fit worse than the base model's.
//!
//! The gap is measured between two least-squares fits, the base model's and the
//! candidate's (residuals over the noise σ alone), not from the predictive check's reduced
//! χ², whose residuals are divided by the posterior's spread as well and so read smaller.

use super::CONDITIONS;
use super::run::{CrossParams, MODELS, ModelKind, noisy_ear};
use crate::crossmodel::Condition;
use anyhow::Result;
use otofit_discrepancy::discrepancy::Verdict;
use otofit_discrepancy::discrepancy::fitcheck::fit_check;
use otofit_discrepancy::discrepancy::workflow::{Settings, diagnose};
use otofit_npe::npe::{Npe, Obs};
use otofit_sim::{Model, output};
use serde::Serialize;
use std::collections::BTreeMap;

/// One misfit ear's diagnosis.
#[derive(Clone, Debug, Serialize)]
pub struct MisfitEar {
    /// The base model's reduced χ² (the workflow's predictive check).
    pub before: f64,
    /// The base model's best least-squares fit, reduced χ² (the statistic `best_after` is).
    pub base_fit: Option<f64>,
    /// The verdict.
    pub verdict: String,
    /// The effect named, if any.
    pub named: Option<&'static str>,
    /// The best candidate's reduced χ² with its effect fitted.
    pub best_after: Option<f64>,
    /// Share of the gap (base_fit − 1) the named effect closes; `None` when none is named.
    pub closed: Option<f64>,
}

/// The scores of one model × condition.
#[derive(Clone, Debug, Serialize)]
pub struct MisfitRow {
    /// The model.
    pub model: ModelKind,
    /// The condition.
    pub condition: Condition,
    /// Ears the fit check refused (the ones diagnosed).
    pub misfits: usize,
    /// Ears the fit check passed (not diagnosed).
    pub fit_ok: usize,
    /// Of the misfits, named an effect that closes ≥ 50 % of the gap.
    pub closed_half: usize,
    /// Of the misfits, said `unexplained`.
    pub unexplained: usize,
    /// Of the misfits, said there was no discrepancy after all.
    pub no_discrepancy: usize,
    /// Of the misfits, named an effect whose fit is worse than the base model's.
    pub worse: usize,
    /// How often each effect was named.
    pub named: BTreeMap<&'static str, usize>,
    /// Every misfit ear.
    pub per_ear: Vec<MisfitEar>,
}

impl MisfitRow {
    /// A row with nothing counted yet.
    fn new(model: ModelKind, condition: Condition) -> MisfitRow {
        MisfitRow {
            model,
            condition,
            misfits: 0,
            fit_ok: 0,
            closed_half: 0,
            unexplained: 0,
            no_discrepancy: 0,
            worse: 0,
            named: BTreeMap::new(),
            per_ear: vec![],
        }
    }

    /// Counts one misfit ear's diagnosis: the predictive check's reduced χ² `before`, and
    /// the reduced χ² of the base model's best fit and of the best candidate's.
    fn tally(&mut self, verdict: Verdict, named: Option<&'static str>, before: f64, fits: Option<(f64, f64)>) {
        let (base_fit, best_after) = fits.unzip();
        let closed = named.and(fits).map(|(b, a)| (b - a) / (b - 1.0).max(f64::EPSILON));
        match verdict {
            Verdict::Unexplained => self.unexplained += 1,
            Verdict::NoDiscrepancy => self.no_discrepancy += 1,
            Verdict::EffectNamed => {}
        }
        if let Some(name) = named {
            *self.named.entry(name).or_default() += 1;
            self.closed_half += usize::from(closed.is_some_and(|c| c >= 0.5));
            self.worse += usize::from(fits.is_some_and(|(b, a)| a > b));
        }
        self.per_ear.push(MisfitEar { before, base_fit, verdict: format!("{verdict:?}"), named, best_after, closed });
    }
}

/// Diagnoses every ear of every model × condition that the fit check refuses, with all
/// measures given, `p.ears` ears each (the same ears as [`super::run::run`]'s).
pub fn run(npe: &Npe, sim: &Model, p: &CrossParams, s: &Settings) -> Result<Vec<MisfitRow>> {
    let freqs = npe.header.frequencies_hz.clone();
    let present = vec![true; freqs.len() * output::N_MEASURES];
    let mut rows = vec![];
    let cases = MODELS.iter().flat_map(|&m| CONDITIONS.iter().map(move |&c| (m, c)));
    for (case, (model, condition)) in cases.enumerate() {
        let mut row = MisfitRow::new(model, condition);
        for k in 0..p.ears {
            let ear = case * 1_000_000 + k;
            let (x, _) = noisy_ear(model, condition, p, ear, &freqs);
            if !output::implausible(&x, &present, freqs.len()).is_empty() {
                continue; // the CLI refuses it before any reading
            }
            // The service's fit check: the full-measure flow's when the model holds one.
            let answering = npe.answering(&Obs { x: &x, present: Some(&present) });
            let inf =
                answering.infer(&Obs { x: &x, present: Some(&present) }, p.samples, p.seed.wrapping_add(ear as u64))?;
            if fit_check(answering, &x, &present, &inf).is_ok_and(|f| f.ok != Some(false)) {
                row.fit_ok += 1;
                continue;
            }
            row.misfits += 1;
            let r = diagnose(sim, npe, &x, s, &mut |_| {})?;
            row.tally(r.verdict, r.named, r.before.reduced_chi2, r.candidates.first().map(fits));
        }
        rows.push(row);
    }
    Ok(rows)
}

/// The reduced χ² of the base model's best fit and of candidate `c`'s (whose score is
/// the base fit's χ² less its own, less the penalty; its fit has one column more).
fn fits(c: &otofit_discrepancy::discrepancy::Candidate) -> (f64, f64) {
    let base_chi2 = c.chi2 + c.chi2_drop();
    let base_dof = c.fit.n_features - (c.fit.row.len() - 1);
    (base_chi2 / base_dof as f64, c.reduced_chi2)
}

/// The rows as a Markdown table.
pub fn table(rows: &[MisfitRow]) -> String {
    let mut s = String::from(
        "| model | condition | misfits diagnosed | named, closes ≥ 50 % of the gap | named, closes less | unexplained | no discrepancy | named but worse | effects named | median share of the gap closed (named) | median χ²ν: check / base fit / best candidate |\n|---|---|---|---|---|---|---|---|---|---|---|\n",
    );
    for r in rows {
        // The lower median over the ears that have the value; "–" when none has.
        let mid = |f: &dyn Fn(&MisfitEar) -> Option<f64>, show: &dyn Fn(f64) -> String| {
            let mut v: Vec<f64> = r.per_ear.iter().filter_map(f).collect();
            v.sort_by(f64::total_cmp);
            v.get(v.len().saturating_sub(1) / 2).map_or("–".into(), |&m| show(m))
        };
        let median = mid(&|e| e.closed, &|c| format!("{:.0} %", 100.0 * c));
        let one = |m: f64| format!("{m:.1}");
        let chi2 = format!(
            "{} / {} / {}",
            mid(&|e| Some(e.before), &one),
            mid(&|e| e.base_fit, &one),
            mid(&|e| e.best_after, &one)
        );
        let named_total: usize = r.named.values().sum();
        let names: Vec<String> = r.named.iter().map(|(n, k)| format!("{n} {k}")).collect();
        s.push_str(&format!(
            "| {} | {} | {} | {} | {} | {} | {} | {} | {} | {median} | {chi2} |\n",
            r.model.name(),
            r.condition.name(),
            r.misfits,
            r.closed_half,
            named_total - r.closed_half,
            r.unexplained,
            r.no_discrepancy,
            r.worse,
            if names.is_empty() { "–".into() } else { names.join(", ") },
        ));
    }
    s
}

#[cfg(test)]
mod tests {
    use super::*;

    fn row() -> MisfitRow {
        MisfitRow { misfits: 3, ..MisfitRow::new(ModelKind::Kringlebotn1988, Condition::Healthy) }
    }

    #[test]
    fn a_named_effect_is_scored_by_the_share_of_the_gap_it_closes() {
        let mut r = row();
        // The gap is the base fit's (5), not the predictive check's (3 or 9).
        r.tally(Verdict::EffectNamed, Some("mastoid"), 3.0, Some((5.0, 2.0))); // closes 3 of 4
        r.tally(Verdict::EffectNamed, Some("mastoid"), 9.0, Some((5.0, 4.0))); // closes 1 of 4
        r.tally(Verdict::EffectNamed, Some("effusion"), 9.0, Some((5.0, 6.0))); // worse
        r.tally(Verdict::Unexplained, None, 9.0, Some((9.0, 8.5)));
        assert_eq!((r.closed_half, r.worse, r.unexplained), (1, 1, 1));
        assert_eq!(r.named["mastoid"], 2);
        assert_eq!(r.per_ear[0].closed, Some(0.75));
        assert_eq!(r.per_ear[3].closed, None, "nothing named, nothing closed");
        let t = table(&[r]);
        assert!(
            t.contains("| kringlebotn_1988 | healthy | 3 | 1 | 2 | 1 | 0 | 1 | effusion 1, mastoid 2 | 25 % | 9.0 / 5.0 / 4.0 |"),
            "{t}"
        );
    }
}
