//! The suite's runner: for each model × condition, noisy ears read by a posterior the way
//! `otofit infer` and `POST /infer` read one (samples and MAP, the fit check, the
//! normal-range differential, withdrawn when the fit fails), and the rates a clinic
//! would live with.
//!
//! Scores, per model × condition, over all its ears:
//! - `fit_ok`: the fit check passed;
//! - `correct`: the fit check passed and the answer shipped names the condition
//!   ([`Condition::expected`]); for a healthy ear, holds no finding at all;
//! - `confident_wrong`: the answer shipped holds a finding (P ≥ 0.95 below or above its
//!   normal range) on a parameter the condition does not name: a wrong structure
//!   named while the fit check passed;
//! - the same two before the fit check withdraws anything (`*_raw`): what the posterior
//!   alone says.
//!
//! Ears the CLI would refuse (a feature outside the physical envelope,
//! `otofit_sim::output::implausible`) are counted as refused and read as nothing.

use super::hudde_engel::HuddeEngel;
use super::kringlebotn::Kringlebotn;
use super::{CONDITIONS, Condition, EarModel, Geometry, features, training_air};
use anyhow::{Result, anyhow, bail};
use otofit_discrepancy::discrepancy::alternatives::{AlternativesParams, Hypothesis, alternatives};
use otofit_discrepancy::discrepancy::fitcheck::checked_reading;
use otofit_npe::npe::normal::{self, Differential};
use otofit_npe::npe::{Npe, Obs};
use otofit_sim::batch::Noise;
use otofit_sim::output;
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use rayon::prelude::*;
use serde::Serialize;
use std::collections::BTreeMap;

/// The published models of the suite.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize)]
pub enum ModelKind {
    /// Kringlebotn 1988's network ([`Kringlebotn`]).
    #[serde(rename = "kringlebotn_1988")]
    Kringlebotn1988,
    /// Hudde & Engel 1998's adult model ([`HuddeEngel`]).
    #[serde(rename = "hudde_engel_1998")]
    HuddeEngel1998,
}

/// Every model, in table order.
pub const MODELS: [ModelKind; 2] = [ModelKind::Kringlebotn1988, ModelKind::HuddeEngel1998];

/// Stapes fixation's range of annular-ligament stiffening, drawn log-uniformly per ear.
pub const STAPES_FIXATION: (f64, f64) = (10.0, 100.0);

impl ModelKind {
    /// Name as in the table and the JSON.
    pub fn name(self) -> &'static str {
        match self {
            ModelKind::Kringlebotn1988 => "kringlebotn_1988",
            ModelKind::HuddeEngel1998 => "hudde_engel_1998",
        }
    }

    /// One ear of this model with `condition`; `severity` in [0, 1] places it within the
    /// condition's range. Returns the ear and the severity in the condition's own unit
    /// (the stapes' stiffening factor, the malleus' 100; 1 where it has none).
    pub fn ear(self, condition: Condition, severity: f64) -> (Box<dyn EarModel + Send + Sync>, f64) {
        let stiffening = STAPES_FIXATION.0 * (STAPES_FIXATION.1 / STAPES_FIXATION.0).powf(severity);
        match self {
            ModelKind::Kringlebotn1988 => {
                let k = Kringlebotn::published();
                match condition {
                    Condition::Healthy => (Box::new(k), 1.0),
                    Condition::StapesFixation => (Box::new(k.stapes_fixed(stiffening)), stiffening),
                    Condition::MalleusFixation => (Box::new(k.malleus_fixed()), 100.0),
                    Condition::Discontinuity => (Box::new(k.disconnected()), 1.0),
                }
            }
            ModelKind::HuddeEngel1998 => {
                let h = HuddeEngel::published();
                match condition {
                    Condition::Healthy => (Box::new(h), 1.0),
                    Condition::StapesFixation => (Box::new(h.stapes_fixed(stiffening)), stiffening),
                    Condition::MalleusFixation => (Box::new(h.malleus_fixed()), 100.0),
                    Condition::Discontinuity => (Box::new(h.disconnected()), 1.0),
                }
            }
        }
    }
}

impl ModelKind {
    /// The cochlear load of the model's healthy ear on otofit's scale, Pa·s/m³: its
    /// mechanical resistance at the footplate over otofit's footplate area squared (the
    /// load the stapes of both ears meets is then the same).
    pub fn cochlear_load(self) -> f64 {
        let r = match self {
            ModelKind::Kringlebotn1988 => Kringlebotn::published().cochlear_resistance(),
            ModelKind::HuddeEngel1998 => HuddeEngel::published().cochlear_resistance(),
        };
        r / otofit_sim::model::Geometry::default().footplate_area.powi(2)
    }

    /// The readings the model's own healthy tissue implies against otofit's normal
    /// ranges, where its elements map onto a tissue parameter one to one (the cochlear
    /// load); such a reading is right for every ear of the model. Its annular ligament
    /// lies inside E_sal's range in both models (tested); the other elements (drum,
    /// suspension, joints) have no one-to-one counterpart and imply nothing.
    pub fn inherent(self) -> Vec<String> {
        let range = normal::NORMAL.iter().find(|r| r.name == "cochlear_load").map(|r| (r.low, r.high));
        let load = self.cochlear_load();
        match range {
            Some((low, _)) if load < low => vec!["cochlear_load below".to_string()],
            Some((_, high)) if load > high => vec!["cochlear_load above".to_string()],
            _ => vec![],
        }
    }
}

/// How big a run is.
#[derive(Clone, Debug)]
pub struct CrossParams {
    /// Noisy ears per model × condition.
    pub ears: usize,
    /// Seed of the severities, the noise and the posterior draws.
    pub seed: u64,
    /// Posterior samples per ear (the CLI's and the service's default: 1000).
    pub samples: usize,
    /// Multiplies otofit's 1× test–retest noise (`otofit simulate --noise-scale`).
    pub noise_scale: f64,
    /// The feature groups given to the posterior and the fit check (e.g. `impedance`,
    /// `absorbance`: wideband tympanometry alone); all when empty.
    pub groups: Vec<String>,
    /// Also fit the differential's alternatives on ears whose fit check failed (never
    /// shipped): what the constrained fits would name on an ear the model does not
    /// reproduce.
    pub misfits: bool,
}

impl Default for CrossParams {
    fn default() -> Self {
        CrossParams { ears: 20, seed: 1, samples: 1000, noise_scale: 1.0, groups: vec![], misfits: false }
    }
}

/// One ear's reading.
#[derive(Clone, Debug, Serialize)]
pub struct EarOutcome {
    /// The condition's severity (its own unit, see [`ModelKind::ear`]).
    pub severity: f64,
    /// Why the CLI would refuse this ear (a feature outside the physical envelope).
    pub refused: Option<String>,
    /// The fit check's verdict (`None`: refused, or the check could not run).
    pub fit_ok: Option<bool>,
    /// The fit check's posterior-predictive reduced χ².
    pub reduced_chi2: Option<f64>,
    /// Why the fit check failed, in its words.
    pub fit_reason: Option<String>,
    /// Findings (`NAME below|above`) before the fit check withdraws anything.
    pub findings_raw: Vec<String>,
    /// Findings as shipped (empty when the fit failed).
    pub findings: Vec<String>,
    /// With the fit check passed: the explanations the differential with alternatives
    /// keeps (`NAME below|above`, or `none`), the best and those within its margin;
    /// with [`CrossParams::misfits`], also when it failed.
    pub alternatives: Vec<String>,
    /// The best-fitting explanation that is not on its normal limit, whenever the
    /// alternatives were fitted.
    pub best_explanation: Option<String>,
}

/// The scores of one model × condition.
#[derive(Clone, Debug, Serialize)]
pub struct CaseResult {
    /// The model.
    pub model: ModelKind,
    /// The condition.
    pub condition: Condition,
    /// The readings that name the condition (`NAME below|above`); none for healthy.
    pub expected: Vec<String>,
    /// Readings the model's own tissue implies ([`ModelKind::inherent`]): right, not wrong.
    pub inherent: Vec<String>,
    /// Ears read.
    pub ears: usize,
    /// Ears the CLI would refuse.
    pub refused: usize,
    /// Fraction of ears whose fit check passed.
    pub fit_ok: f64,
    /// Fraction whose fit check passed and whose answer names the condition (healthy: no
    /// finding).
    pub correct: f64,
    /// Fraction whose shipped answer holds a finding the condition does not name.
    pub confident_wrong: f64,
    /// `correct` before the fit check withdraws anything.
    pub correct_raw: f64,
    /// `confident_wrong` before the fit check withdraws anything.
    pub confident_wrong_raw: f64,
    /// Of the ears whose fit check passed, the fraction whose answer names the condition
    /// or keeps it among its alternatives (healthy: `none` kept among them); `None` with
    /// no such ear.
    pub among_alternatives: Option<f64>,
    /// Median reduced χ² of the fit check over the ears it ran on.
    pub median_chi2: Option<f64>,
    /// With [`CrossParams::misfits`], over the ears whose fit check failed: the share
    /// whose best explanation names the condition (healthy: `none` or the model's own
    /// tissue), the share that keep it within the margin, and the median number kept.
    pub misfit_alternatives: Option<MisfitScores>,
    /// How often each finding was shipped.
    pub findings: BTreeMap<String, usize>,
    /// How often each finding was read before the fit check.
    pub findings_raw: BTreeMap<String, usize>,
    /// Every ear.
    pub per_ear: Vec<EarOutcome>,
}

/// What the alternatives say of the ears whose fit check failed (never shipped).
#[derive(Clone, Debug, Serialize)]
pub struct MisfitScores {
    /// Ears whose fit check failed and whose alternatives were fitted.
    pub ears: usize,
    /// Share whose best explanation names the condition.
    pub best_names: f64,
    /// Share that keep the condition within the margin.
    pub among: f64,
    /// Median number of explanations kept.
    pub kept_median: usize,
}

/// `NAME below|above` for every confident finding of a differential.
fn findings(d: &[Differential]) -> Vec<String> {
    d.iter().filter(|r| matches!(r.reading, "below" | "above")).map(|r| format!("{} {}", r.name, r.reading)).collect()
}

/// Whether a set of findings names `condition` (healthy: holds none but the model's
/// `inherent` ones).
fn names_condition(found: &[String], expected: &[String], inherent: &[String]) -> bool {
    if expected.is_empty() {
        found.iter().all(|f| inherent.contains(f))
    } else {
        found.iter().any(|f| expected.contains(f))
    }
}

/// Whether one explanation of the alternatives (`NAME below|above|present`, or `none`)
/// is the condition's; for a healthy ear `none`, or a reading the model's own tissue
/// implies (`inherent`). An answer without a finding whose least squares prefer an
/// abnormal ear does not count as healthy.
fn explains(a: &str, expected: &[String], inherent: &[String]) -> bool {
    if expected.is_empty() { a == "none" || inherent.iter().any(|i| i == a) } else { expected.iter().any(|x| x == a) }
}

/// Whether a set of findings holds one that neither the condition nor the model's own
/// tissue (`inherent`) names.
fn names_another(found: &[String], expected: &[String], inherent: &[String]) -> bool {
    found.iter().any(|f| !expected.contains(f) && !inherent.contains(f))
}

/// Reads one ear as `otofit infer` does.
fn read_ear(npe: &Npe, x: &[f64], present: &[bool], p: &CrossParams, seed: u64) -> Result<EarOutcome> {
    let mut ear = EarOutcome {
        severity: 1.0,
        refused: None,
        fit_ok: None,
        reduced_chi2: None,
        fit_reason: None,
        findings_raw: vec![],
        findings: vec![],
        alternatives: vec![],
        best_explanation: None,
    };
    if let Some((m, i, v)) = output::implausible(x, present, npe.header.frequencies_hz.len()).first() {
        ear.refused = Some(format!(
            "{} = {v} outside the envelope of {}",
            npe.header.feature_names[*i],
            output::MEASURES[*m].name
        ));
        return Ok(ear);
    }
    // As the service answers: the full-measure flow for an ear with every measure.
    let npe = npe.answering(&Obs { x, present: Some(present) });
    let inf = npe.infer(&Obs { x, present: Some(present) }, p.samples, seed)?;
    // What the draws say before a failed fit check withdraws it.
    ear.findings_raw = findings(&normal::read(npe.params(), &inf.samples));
    let (differential, fit) = checked_reading(npe, x, present, &inf, &inf.samples);
    match fit {
        Ok(f) => {
            ear.fit_ok = f.ok;
            ear.reduced_chi2 = Some(f.reduced_chi2);
            if f.ok == Some(false) {
                ear.fit_reason = f.reason;
            }
        }
        Err(e) => ear.fit_reason = Some(e.to_string()),
    }
    ear.findings = findings(&differential);
    // The competing explanations, also when nothing is read: is the condition among them?
    let ap = AlternativesParams { when_no_finding: true, when_misfit: p.misfits, ..Default::default() };
    if let Some(a) = alternatives(npe, x, present, (&inf.map, &inf.samples), &differential, ear.fit_ok, &ap) {
        let name = |h: &Hypothesis| h.parameter.map_or("none".to_string(), |n| format!("{n} {}", h.direction));
        let distinct = a.hypotheses.iter().filter(|h| !h.at_normal_limit);
        ear.alternatives = distinct.clone().filter(|h| h.delta_chi2 < a.margin).map(name).collect();
        ear.best_explanation = distinct.map(name).next();
    } else if ear.fit_ok == Some(true) && ear.findings.is_empty() {
        // Nothing abnormal fits within the margin of a normal ear.
        ear.alternatives = vec!["none".into()];
    }
    Ok(ear)
}

/// Ear `row` of `model` with `condition`: its features on `freqs` with otofit's noise
/// (scaled by `p.noise_scale`, seeded by `p.seed` and the row) and its severity.
pub fn noisy_ear(
    model: ModelKind,
    condition: Condition,
    p: &CrossParams,
    row: usize,
    freqs: &[f64],
) -> (Vec<f64>, f64) {
    let mut rng = ChaCha8Rng::seed_from_u64(p.seed);
    rng.set_stream(row as u64);
    let (ear, severity) = model.ear(condition, rng.random::<f64>());
    let clean = features(ear.as_ref(), &Geometry::nominal(), &training_air(), freqs);
    let noise = Noise { std: output::noise_std(freqs), scale: p.noise_scale, seed: p.seed };
    let x = if p.noise_scale > 0.0 { noise.apply(&clean, row) } else { clean };
    (x, severity)
}

/// Runs every model × condition with `p.ears` noisy ears each; `progress`
/// hears each case as it ends.
pub fn run(npe: &Npe, p: &CrossParams, progress: &mut dyn FnMut(&CaseResult)) -> Result<Vec<CaseResult>> {
    let freqs = npe.header.frequencies_hz.clone();
    if npe.header.feature_names != output::feature_names(&freqs) {
        bail!("the model's features are not otofit's seven measures on its grid: no cross-model ears for it");
    }
    let present = npe.header.features_of_groups(&p.groups).map_err(|e| anyhow!("--measures: {e}"))?;
    let mut out = vec![];
    let cases = MODELS.iter().flat_map(|&m| CONDITIONS.iter().map(move |&c| (m, c)));
    for (case, (model, condition)) in cases.enumerate() {
        let expected: Vec<String> = condition.expected().iter().map(|(n, d)| format!("{n} {d}")).collect();
        let inherent = model.inherent();
        let per_ear: Vec<EarOutcome> = (0..p.ears)
            .into_par_iter()
            .map(|k| {
                let row = case * 1_000_000 + k;
                let (x, severity) = noisy_ear(model, condition, p, row, &freqs);
                let mut o = read_ear(npe, &x, &present, p, p.seed.wrapping_add(row as u64))?;
                o.severity = severity;
                Ok(o)
            })
            .collect::<Result<_>>()?;
        let n = per_ear.len().max(1) as f64;
        let rate = |f: &dyn Fn(&EarOutcome) -> bool| per_ear.iter().filter(|e| f(e)).count() as f64 / n;
        let count = |get: &dyn Fn(&EarOutcome) -> &Vec<String>| {
            let mut m = BTreeMap::new();
            for e in &per_ear {
                for f in get(e) {
                    *m.entry(f.clone()).or_insert(0) += 1;
                }
            }
            m
        };
        let mut chi2: Vec<f64> = per_ear.iter().filter_map(|e| e.reduced_chi2).collect();
        chi2.sort_by(f64::total_cmp);
        // A shipped answer is right only with the fit check passed: a withdrawn reading
        // says nothing about the ear, healthy or not.
        let scored = |found: &dyn Fn(&EarOutcome) -> &Vec<String>, right: bool, shipped: bool| {
            rate(&|e| {
                e.refused.is_none()
                    && if right {
                        (!shipped || e.fit_ok == Some(true)) && names_condition(found(e), &expected, &inherent)
                    } else {
                        names_another(found(e), &expected, &inherent)
                    }
            })
        };
        let result = CaseResult {
            model,
            condition,
            ears: per_ear.len(),
            refused: per_ear.iter().filter(|e| e.refused.is_some()).count(),
            fit_ok: rate(&|e| e.fit_ok == Some(true)),
            correct: scored(&|e| &e.findings, true, true),
            confident_wrong: scored(&|e| &e.findings, false, true),
            correct_raw: scored(&|e| &e.findings_raw, true, false),
            confident_wrong_raw: scored(&|e| &e.findings_raw, false, false),
            median_chi2: (!chi2.is_empty()).then(|| chi2[(chi2.len() - 1) / 2]),
            among_alternatives: {
                let ok: Vec<&EarOutcome> = per_ear.iter().filter(|e| e.fit_ok == Some(true)).collect();
                let kept = |e: &&EarOutcome| {
                    (!expected.is_empty() && names_condition(&e.findings, &expected, &inherent))
                        || e.alternatives.iter().any(|a| explains(a, &expected, &inherent))
                };
                (!ok.is_empty()).then(|| ok.iter().filter(|e| kept(e)).count() as f64 / ok.len() as f64)
            },
            misfit_alternatives: {
                let bad: Vec<&EarOutcome> =
                    per_ear.iter().filter(|e| e.fit_ok == Some(false) && e.best_explanation.is_some()).collect();
                let share =
                    |f: &dyn Fn(&EarOutcome) -> bool| bad.iter().filter(|e| f(e)).count() as f64 / bad.len() as f64;
                let mut kept: Vec<usize> = bad.iter().map(|e| e.alternatives.len()).collect();
                kept.sort_unstable();
                (!bad.is_empty()).then(|| MisfitScores {
                    ears: bad.len(),
                    best_names: share(&|e| {
                        e.best_explanation.as_deref().is_some_and(|b| explains(b, &expected, &inherent))
                    }),
                    among: share(&|e| e.alternatives.iter().any(|a| explains(a, &expected, &inherent))),
                    kept_median: kept[(kept.len() - 1) / 2],
                })
            },
            findings: count(&|e| &e.findings),
            findings_raw: count(&|e| &e.findings_raw),
            expected,
            inherent,
            per_ear,
        };
        progress(&result);
        out.push(result);
    }
    Ok(out)
}

/// What a case should read, in words: its expected readings, or no finding.
fn should_read(r: &CaseResult) -> String {
    if r.expected.is_empty() { "no finding".to_string() } else { r.expected.join(" or ") }
}

/// The results as a Markdown table: one row per model × condition.
pub fn table(results: &[CaseResult]) -> String {
    let mut s = String::from(
        "| model | condition | should read | ears | refused | fit ok | correct | confident wrong | correct, before fit check | confident wrong, before fit check | named or among the alternatives (of fit ok) | median χ² | most frequent wrong finding (ears, before fit check) |\n|---|---|---|---|---|---|---|---|---|---|---|---|---|\n",
    );
    let pct = |v: f64| format!("{:.0} %", 100.0 * v);
    for r in results {
        let wrong = r
            .findings_raw
            .iter()
            .filter(|(f, _)| !r.expected.contains(f) && !r.inherent.contains(f))
            .max_by_key(|(_, n)| **n)
            .map_or("—".to_string(), |(f, n)| format!("{f} ({n})"));
        let mut should = should_read(r);
        if !r.inherent.is_empty() {
            should.push_str(&format!(" (its own tissue: {})", r.inherent.join(", ")));
        }
        s.push_str(&format!(
            "| {} | {} | {} | {} | {} | {} | {} | {} | {} | {} | {} | {} | {} |\n",
            r.model.name(),
            r.condition.name(),
            should,
            r.ears,
            r.refused,
            pct(r.fit_ok),
            pct(r.correct),
            pct(r.confident_wrong),
            pct(r.correct_raw),
            pct(r.confident_wrong_raw),
            r.among_alternatives.map_or("—".to_string(), pct),
            r.median_chi2.map_or("—".to_string(), |c| format!("{c:.1}")),
            wrong
        ));
    }
    s
}

/// The alternatives on the ears whose fit check failed (`CrossParams::misfits`), as a
/// Markdown table: one row per model × condition with such ears.
pub fn misfit_table(results: &[CaseResult]) -> String {
    let mut s = String::from(
        "| model | condition | should read | misfit ears | best explanation names it | named within the margin | explanations kept (median) | most frequent best explanation (ears) |\n|---|---|---|---|---|---|---|---|\n",
    );
    let pct = |v: f64| format!("{:.0} %", 100.0 * v);
    for r in results {
        let Some(m) = &r.misfit_alternatives else { continue };
        let mut best = BTreeMap::new();
        for e in r.per_ear.iter().filter(|e| e.fit_ok == Some(false)) {
            if let Some(b) = &e.best_explanation {
                *best.entry(b.as_str()).or_insert(0) += 1;
            }
        }
        let most = best.iter().max_by_key(|(_, n)| **n).map_or("—".to_string(), |(b, n)| format!("{b} ({n})"));
        let should = should_read(r);
        s.push_str(&format!(
            "| {} | {} | {} | {} | {} | {} | {} | {} |\n",
            r.model.name(),
            r.condition.name(),
            should,
            m.ears,
            pct(m.best_names),
            pct(m.among),
            m.kept_median,
            most
        ));
    }
    s
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn scoring_follows_the_condition() {
        let e = |v: &[&str]| v.iter().map(|s| s.to_string()).collect::<Vec<_>>();
        let sal = e(&["E_sal above"]);
        assert!(names_condition(&e(&["E_sal above", "E_eardrum below"]), &sal, &[]));
        assert!(names_another(&e(&["E_sal above", "E_eardrum below"]), &sal, &[]));
        assert!(!names_another(&e(&["E_sal above"]), &sal, &[]));
        assert!(names_condition(&[], &[], &[]) && !names_condition(&e(&["E_joints below"]), &[], &[]));
        assert!(names_another(&e(&["E_joints below"]), &[], &[]));
        // A reading the model's own tissue implies is neither wrong nor a finding too many.
        let own = e(&["cochlear_load below"]);
        assert!(names_condition(&own, &[], &own) && !names_another(&own, &sal, &own));
        assert!(names_another(&e(&["cochlear_load above"]), &sal, &own));
        // An explanation of the alternatives: the condition's, or for a healthy ear none
        // or the model's own tissue.
        assert!(explains("E_sal above", &sal, &own) && !explains("E_joints above", &sal, &own));
        assert!(!explains("none", &sal, &own) && explains("none", &[], &own));
        assert!(explains("cochlear_load below", &[], &own) && !explains("E_sal above", &[], &own));
    }

    /// The models' cochlear loads on otofit's scale, from their published elements:
    /// Hudde & Engel's w_C = 70e-3 N·s/m over (3.2 mm²)² = 6.8e9 Pa·s/m³, Kringlebotn's
    /// 330 dyn·s/cm⁵ through (60 mm²·1.3)² = 1.96e10 — both below otofit's normal range
    /// (2.1e10–3.5e10), so a healthy ear of either reads `cochlear_load below` rightly.
    /// Their annular ligaments (H&E 1/1.2 mm/N = 833 N/m; Kringlebotn (A_TM·r_MI)²/C_c =
    /// 1086 N/m) lie inside E_sal's normal range through otofit's ligament
    /// (375–4125 N/m), so no E_sal reading is inherent.
    #[test]
    fn the_models_own_cochlear_loads_lie_below_the_normal_range() {
        let he = ModelKind::HuddeEngel1998.cochlear_load();
        let kr = ModelKind::Kringlebotn1988.cochlear_load();
        assert!((he / 6.836e9 - 1.0).abs() < 1e-3, "Hudde & Engel {he:e}");
        assert!((kr / 1.961e10 - 1.0).abs() < 1e-3, "Kringlebotn {kr:e}");
        for m in MODELS {
            assert_eq!(m.inherent(), vec!["cochlear_load below".to_string()], "{}", m.name());
        }
        let sal = normal::NORMAL.iter().find(|r| r.name == "E_sal").unwrap();
        let k_per_e = otofit_sim::model::Geometry::default().g_sal;
        let he_k = 1.0 / HuddeEngel::published().n_st;
        let kr = Kringlebotn::published();
        let kr_k = (super::super::kringlebotn::AREA_TM * super::super::kringlebotn::LEVER).powi(2) / kr.cc;
        for k in [he_k, kr_k] {
            assert!((sal.low * k_per_e..=sal.high * k_per_e).contains(&k), "{k} N/m");
        }
    }

    /// Why otofit reads these networks' stapes fixations as a fixed malleus or a stiff
    /// joint: in both, an annular ligament only 10× stiffer already lowers the umbo's
    /// velocity below 1 kHz by more than 10 dB and by over half as much as the stapes'
    /// — the signature Nakajima et al. (2005, Hear Res 204:60) measured for malleus
    /// fixations in temporal bones, where stapes fixations lowered the umbo's by less
    /// than 10 dB (their joints flex, as otofit's FE chain does:
    /// otofit-sim/tests/semantics.rs). `cargo run --example fixation_signatures` tables it.
    #[test]
    fn the_networks_stapes_fixations_lower_the_umbo_as_a_fixed_malleus_does() {
        let freqs = [250.0, 500.0, 1000.0];
        let umbo_stapes_db = |ear: &dyn EarModel| {
            let x = features(ear, &Geometry::nominal(), &training_air(), &freqs);
            // |v_stapes| is the first block, |v_umbo| the sixth (log10 m/s/Pa).
            let mean = |m: usize| 20.0 * x[m * 3..m * 3 + 3].iter().sum::<f64>() / 3.0;
            (mean(5), mean(0))
        };
        for m in MODELS {
            let (healthy, _) = m.ear(Condition::Healthy, 0.0);
            let (fixed, factor) = m.ear(Condition::StapesFixation, 0.0);
            assert_eq!(factor, STAPES_FIXATION.0);
            let (u0, s0) = umbo_stapes_db(healthy.as_ref());
            let (u1, s1) = umbo_stapes_db(fixed.as_ref());
            let (du, ds) = (u1 - u0, s1 - s0);
            assert!(du < -10.0 && du < 0.5 * ds, "{}: umbo {du:.1} dB, stapes {ds:.1} dB", m.name());
        }
    }

    /// Every model is passive (absorbance in [0, 1] at the probe, the drum's resistance
    /// not negative) and gives finite features inside otofit's physical envelope for
    /// every condition, at both ends of the condition's range.
    #[test]
    fn every_ear_is_a_plausible_measurement() {
        let freqs = otofit_sim::log_grid(200.0, 8000.0, 50);
        let present = vec![true; 350];
        for m in MODELS {
            for c in CONDITIONS {
                for s in [0.0, 1.0] {
                    let (ear, _) = m.ear(c, s);
                    assert!(freqs.iter().all(|&f| ear.at(f).z_drum.re >= 0.0), "{} {}", m.name(), c.name());
                    let x = features(ear.as_ref(), &Geometry::nominal(), &training_air(), &freqs);
                    let absorbance = &x[200..250];
                    assert!(absorbance.iter().all(|a| (0.0..=1.0).contains(a)), "{} {}", m.name(), c.name());
                    assert!(x.iter().all(|v| v.is_finite()), "{} {}", m.name(), c.name());
                    let bad = output::implausible(&x, &present, freqs.len());
                    assert!(bad.is_empty(), "{} {} severity {s}: {bad:?}", m.name(), c.name());
                }
            }
        }
    }

    /// The runner on two ears per case with the shipped model: every case scored, no ear
    /// refused, rates in [0, 1], the same numbers twice, the groups given respected.
    #[test]
    fn runner_reads_a_couple_of_ears() {
        let path = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("../../models/default.otofit");
        let npe = Npe::load(&path).unwrap();
        let p = CrossParams { ears: 2, samples: 200, ..CrossParams::default() };
        let t = std::time::Instant::now();
        let a = run(&npe, &p, &mut |_| {}).unwrap();
        assert!(t.elapsed().as_secs_f64() < 30.0, "{:.1} s", t.elapsed().as_secs_f64());
        assert_eq!(a.len(), 8);
        for r in &a {
            assert_eq!((r.ears, r.refused), (2, 0), "{} {}", r.model.name(), r.condition.name());
            for v in [r.fit_ok, r.correct, r.confident_wrong, r.correct_raw, r.confident_wrong_raw] {
                assert!((0.0..=1.0).contains(&v), "{v}");
            }
        }
        let b = run(&npe, &p, &mut |_| {}).unwrap();
        let key = |v: &[CaseResult]| serde_json::to_string(&v.iter().map(|r| &r.per_ear).collect::<Vec<_>>()).unwrap();
        assert_eq!(key(&a), key(&b));
        let wbt = CrossParams { groups: vec!["impedance".into(), "absorbance".into()], ..p.clone() };
        assert_ne!(key(&run(&npe, &wbt, &mut |_| {}).unwrap()), key(&a));
        let bad = CrossParams { groups: vec!["tympanogram".into()], ..p.clone() };
        assert!(run(&npe, &bad, &mut |_| {}).unwrap_err().to_string().contains("unknown feature group"));
        assert_eq!(table(&a).lines().count(), 10);
    }

    /// The alternatives of ears the fit check refuses are fitted only when asked, and
    /// then on every such ear; the shipped answer is the same either way.
    #[test]
    fn misfit_ears_get_alternatives_only_when_asked() {
        let path = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("../../models/default.otofit");
        let npe = Npe::load(&path).unwrap();
        let p = CrossParams { ears: 1, samples: 200, ..CrossParams::default() };
        let off = run(&npe, &p, &mut |_| {}).unwrap();
        let on = run(&npe, &CrossParams { misfits: true, ..p.clone() }, &mut |_| {}).unwrap();
        let mut misfits = 0;
        for (a, b) in off.iter().zip(&on) {
            assert!(a.misfit_alternatives.is_none(), "{} {}", a.model.name(), a.condition.name());
            let refused = b.per_ear.iter().filter(|e| e.fit_ok == Some(false)).count();
            misfits += refused;
            assert_eq!(b.misfit_alternatives.as_ref().map_or(0, |m| m.ears), refused);
            for (ea, eb) in a.per_ear.iter().zip(&b.per_ear) {
                assert_eq!((&ea.findings, ea.fit_ok), (&eb.findings, eb.fit_ok));
                if eb.fit_ok == Some(false) {
                    assert!(ea.best_explanation.is_none() && ea.alternatives.is_empty());
                    assert!(eb.best_explanation.is_some() && !eb.alternatives.is_empty());
                }
            }
        }
        // Every ear of both models fails the check with all seven measures.
        assert!(misfits >= 6, "{misfits} misfit ears");
        assert_eq!(
            misfit_table(&on).lines().count(),
            2 + on.iter().filter(|r| r.misfit_alternatives.is_some()).count()
        );
    }
}
