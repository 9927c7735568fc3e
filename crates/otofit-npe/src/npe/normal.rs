//! Normal ranges of the seven parameters (the span of values reported for normal ears,
//! physics-notes §2) and differential reading of a posterior against them: the posterior
//! probability below, within and above, and the conditions a deviation is associated
//! with. Information for a clinician, not a diagnosis.

use super::Param;
use serde::Serialize;

/// A tissue parameter's normal range, with its source and what leaving it suggests.
pub struct NormalRange {
    /// The parameter.
    pub name: &'static str,
    /// Lower end of the normal range.
    pub low: f64,
    /// Upper end of the normal range.
    pub high: f64,
    /// Where the range comes from.
    pub source: &'static str,
    /// What a value below the range is associated with.
    pub below: &'static str,
    /// What a value above the range is associated with.
    pub above: &'static str,
}

/// The normal ranges of the seven tissue parameters.
pub const NORMAL: [NormalRange; 7] = [
    NormalRange {
        name: "E_eardrum",
        low: 2e6,
        high: 2e8,
        source: "Aernouts 2012 (2–3 MPa) … Gan 2016 (200 MPa)",
        below: "a flaccid or atrophic eardrum (healed perforation, atelectasis)",
        above: "a stiff, thickened eardrum (tympanosclerosis)",
    },
    NormalRange {
        name: "E_ligaments",
        low: 5e4,
        high: 2.1e7,
        source: "Sun 2002 superior ligament (0.049 MPa, clipped to the prior floor 0.05) … Gan 2004 AML (21 MPa)",
        below: "lax suspensory ligaments",
        above: "malleus fixation (anterior mallear ligament ossification)",
    },
    NormalRange {
        name: "E_tendons",
        low: 5.2e5,
        high: 5e6,
        source: "Gan 2004 stapedial tendon (0.52 MPa) … Homma 2010 TTT (5 MPa)",
        below: "slack middle-ear muscles",
        above: "contracted tensor tympani or stapedius (reflex, spasm)",
    },
    NormalRange {
        name: "E_sal",
        low: 1e5,
        high: 1.1e6,
        source: "Gan 2016 (0.1 MPa) … Kwacz 2015 (1.1 MPa)",
        below: "a lax annular ligament — or a missing effect bent into it (run diagnose)",
        above: "stapes fixation (otosclerosis)",
    },
    NormalRange {
        name: "E_joints",
        low: 4.4e5,
        high: 7e6,
        source: "Gan 2004 ISJ (0.44 MPa) … Homma 2010 IMJ (7 MPa)",
        below: "ossicular discontinuity or joint erosion (e.g. incudostapedial)",
        above: "joint ankylosis or fixation",
    },
    NormalRange {
        name: "damping_beta",
        low: 7.5e-5,
        high: 1.5e-4,
        source: "Gan-lab FE (7.5e-5 s soft tissue, 1e-4 s TM, 1.5e-4 s bone)",
        below: "unusually low losses",
        above: "middle-ear effusion or inflammation",
    },
    NormalRange {
        name: "cochlear_load",
        low: 2.1e10,
        high: 3.5e10,
        source: "Aibara 2001 (21 GΩ) … Zwislocki (35 GΩ)",
        below: "a third-window lesion (e.g. superior canal dehiscence)",
        above: "raised cochlear impedance (e.g. a round-window obstruction)",
    },
];

/// The typical ear: every tissue value at the geometric centre of its normal range, the
/// other parameters nominal (the openapi.yaml example, `bench fit`'s centre ear). Since v8
/// the simulator's nominal tissue values are these (to the 5 digits of `PARAMS`).
pub fn centre_row() -> Vec<f64> {
    crate::sim::PARAMS
        .iter()
        .map(|p| NORMAL.iter().find(|r| r.name == p.name).map_or(p.nominal, |r| (r.low * r.high).sqrt()))
        .collect()
}

/// "within" is read when the posterior puts at least this much probability inside the
/// normal range.
pub const CONFIDENT: f64 = 0.8;
/// "below" / "above" (a finding a clinic acts on) need this much: a calibrated posterior
/// of an ear whose value sits on a limit of the normal range puts a roughly uniform
/// probability on either side, so a 0.8 rule would call it abnormal about 20 % of the
/// time per limit (the nominal ear sits on two: 22 and 17 of 40 noisy repeats read
/// E_joints "above" and damping "below" at 0.8, 0 and 1 of 40 at 0.95; docs/npe.md).
pub const ABNORMAL: f64 = 0.95;
/// A posterior informs a reading when its 90 % interval is narrower than the normal range
/// or than this fraction of the prior box (on the parameter's scale).
pub const INFORMATIVE_PRIOR_FRACTION: f64 = 0.5;
/// A posterior whose median lies within this fraction of the box from a bound is piled
/// against it: the model cannot represent the value, so no reading is made from it.
pub const BOUND_FRACTION: f64 = 0.025;

/// One parameter's posterior read against its normal range.
#[derive(Clone, Debug, Serialize)]
pub struct Differential {
    /// The parameter.
    pub name: String,
    /// Lower end of the normal range.
    pub normal_low: f64,
    /// Upper end of the normal range.
    pub normal_high: f64,
    /// Posterior probability below the range.
    pub p_below: f64,
    /// Posterior probability within the range.
    pub p_within: f64,
    /// Posterior probability above the range.
    pub p_above: f64,
    /// "within" (P ≥ `CONFIDENT`), "below" or "above" (P ≥ `ABNORMAL`) when the posterior
    /// is informative; "undetermined" when it does not; "unreliable" when the
    /// model does not fit the observation (then no reading is made at all).
    pub reading: &'static str,
    /// What a deviation in the read direction is associated with (below / above only).
    pub associated_with: Option<&'static str>,
    /// Why the reading is undetermined or unreliable.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub reason: Option<String>,
    /// "low" or "high" when the posterior is piled against that prior bound.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub at_prior_bound: Option<&'static str>,
    /// Where the range comes from.
    pub source: &'static str,
}

/// The nearest order statistic of `v` (the value [`crate::stats::quantile_nearest`] takes
/// from `v` sorted by `total_cmp`: a value some draw actually took), by selection; `v` is
/// reordered. NaN when empty.
fn nearest(v: &mut [f64], q: f64) -> f64 {
    let Some(n) = v.len().checked_sub(1) else { return f64::NAN };
    *v.select_nth_unstable_by((n as f64 * q).round() as usize, f64::total_cmp).1
}

/// Reads posterior samples (columns in `params` order) against the normal ranges;
/// parameters without a range are skipped.
pub fn read(params: &[Param], samples: &[Vec<f64>]) -> Vec<Differential> {
    if samples.is_empty() {
        return Vec::new();
    }
    let n = samples.len() as f64;
    params
        .iter()
        .enumerate()
        .filter_map(|(k, p)| {
            let r = NORMAL.iter().find(|r| r.name == p.name)?;
            let below = samples.iter().filter(|s| s[k] < r.low).count() as f64 / n;
            let above = samples.iter().filter(|s| s[k] > r.high).count() as f64 / n;
            let within = 1.0 - below - above;
            // The three order statistics of the positions that `quantile` would pick after a
            // sort, by selection, and only they mapped to positions (the map rises).
            let mut col: Vec<f64> = samples.iter().map(|s| s[k]).collect();
            let mut pick = |q: f64| p.position(nearest(&mut col, q));
            let (q05, median, q95) = (pick(0.05), pick(0.5), pick(0.95));
            let width90 = q95 - q05;
            let normal_width = p.position(r.high) - p.position(r.low);
            let at_prior_bound = if median < BOUND_FRACTION {
                Some("low")
            } else if median > 1.0 - BOUND_FRACTION {
                Some("high")
            } else {
                None
            };
            let informative = width90 < normal_width.max(INFORMATIVE_PRIOR_FRACTION);
            let (reading, associated_with, reason) = if let Some(side) = at_prior_bound {
                let why = format!(
                    "the posterior is piled against the prior's {side} bound: the model cannot represent this \
                     ear's value (run a diagnose job to look for a missing effect)"
                );
                ("undetermined", None, Some(why))
            } else if !informative {
                let why = format!(
                    "the data do not pin this parameter down: its 90 % interval spans {:.0} % of the prior box",
                    100.0 * width90
                );
                ("undetermined", None, Some(why))
            } else if within >= CONFIDENT {
                ("within", None, None)
            } else if below >= ABNORMAL {
                ("below", Some(r.below), None)
            } else if above >= ABNORMAL {
                ("above", Some(r.above), None)
            } else {
                let why = format!(
                    "neither within (P ≥ {CONFIDENT}) nor outside (P ≥ {ABNORMAL} below or above): the posterior \
                     straddles a limit of the normal range"
                );
                ("undetermined", None, Some(why))
            };
            Some(Differential {
                name: p.name.clone(),
                normal_low: r.low,
                normal_high: r.high,
                p_below: below,
                p_within: within,
                p_above: above,
                reading,
                associated_with,
                reason,
                at_prior_bound,
                source: r.source,
            })
        })
        .collect()
}

/// Withdraws every reading: the model does not fit the observation, so no parameter value
/// it infers can be read against a normal range.
pub fn withdraw(readings: &mut [Differential], why: &str) {
    for d in readings {
        d.reading = "unreliable";
        d.associated_with = None;
        d.reason = Some(why.to_string());
    }
}

/// The answer in one line: what a clinician reads first.
#[derive(Clone, Debug, serde::Serialize, PartialEq)]
pub struct Verdict {
    /// `reliable_no_finding`, `reliable_findings`, `unreliable_model_misfit` or
    /// `unchecked` (the model was never calibrated, so its fit cannot be judged).
    pub code: &'static str,
    /// One sentence for a person.
    pub sentence: String,
    /// The parameters read below or above their normal range, as `NAME below|above`.
    pub findings: Vec<String>,
}

/// The verdict of a differential whose fit check said `fit_ok` (`None`: no check).
pub fn verdict(readings: &[Differential], fit_ok: Option<bool>) -> Verdict {
    let findings: Vec<String> = readings
        .iter()
        .filter(|d| matches!(d.reading, "below" | "above"))
        .map(|d| format!("{} {}", d.name, d.reading))
        .collect();
    let undetermined = readings.iter().filter(|d| d.reading == "undetermined").count();
    let (code, sentence) = match fit_ok {
        Some(false) => (
            "unreliable_model_misfit",
            "The model does not reproduce these measurements, so no parameter is read; look for the missing effect (see next).".to_string(),
        ),
        None => ("unchecked", "The model is not calibrated, so its fit cannot be judged; read the parameters with care.".to_string()),
        Some(true) if findings.is_empty() => (
            "reliable_no_finding",
            format!(
                "The model fits; no parameter is outside its normal range ({undetermined} of {} undetermined).",
                readings.len()
            ),
        ),
        Some(true) => ("reliable_findings", format!("The model fits; outside the normal range: {}.", findings.join(", "))),
    };
    Verdict { code, sentence, findings }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_simulators_nominal_tissue_is_the_centre_of_the_normal_ranges() {
        let centre = centre_row();
        for (p, c) in crate::sim::PARAMS.iter().zip(&centre).take(crate::sim::N_TISSUE) {
            assert!((p.nominal / c - 1.0).abs() < 1e-4, "{}: nominal {} against the centre {c}", p.name, p.nominal);
        }
    }

    #[test]
    fn nearest_by_selection_is_the_sorted_order_statistic() {
        for n in [1, 2, 7, 1000] {
            let v: Vec<f64> = (0..n).map(|i| ((i * 7919 % 1009) as f64 - 500.0) * 1e-3).collect();
            let sorted = crate::stats::sorted(v.clone());
            for q in [0.0, 0.05, 0.5, 0.95, 1.0] {
                assert_eq!(nearest(&mut v.clone(), q), crate::stats::quantile_nearest(&sorted, q).unwrap());
            }
        }
        assert!(nearest(&mut [], 0.5).is_nan());
    }

    #[test]
    fn ranges_lie_inside_the_prior_and_readings_follow_the_mass() {
        for (r, p) in NORMAL.iter().zip(crate::sim::PARAMS) {
            assert_eq!(r.name, p.name);
            assert!(p.low <= r.low && r.low < r.high && r.high <= p.high, "{}", r.name);
            assert!(r.low <= p.nominal && p.nominal <= r.high, "nominal {} outside its normal range", r.name);
        }
        let params: Vec<Param> = crate::sim::PARAMS.iter().map(Param::from).collect();
        let sal = std::slice::from_ref(&params[3]);
        let stiff: Vec<Vec<f64>> = (0..100).map(|i| vec![2e6 + 1e4 * i as f64]).collect();
        let d = read(sal, &stiff);
        assert_eq!((d[0].reading, d[0].p_above), ("above", 1.0));
        assert!(d[0].associated_with.unwrap().contains("otosclerosis"));
        let other = Param { name: "other".into(), ..params[3].clone() };
        assert!(read(&[other], &stiff).is_empty());
    }

    fn draws(p: &Param, lo: f64, hi: f64) -> Vec<Vec<f64>> {
        // Evenly spread over [lo, hi] on the parameter's scale.
        (0..200).map(|i| vec![lerp(p, lo, hi, i as f64 / 199.0)]).collect()
    }

    fn lerp(p: &Param, lo: f64, hi: f64, q: f64) -> f64 {
        match p.scale {
            crate::npe::Scale::Log10 => 10f64.powf(lo.log10() + q * (hi.log10() - lo.log10())),
            crate::npe::Scale::Linear => lo + q * (hi - lo),
        }
    }

    #[test]
    fn uninformative_straddling_and_bound_hugging_posteriors_are_not_read() {
        let params: Vec<Param> = crate::sim::PARAMS.iter().map(Param::from).collect();
        let tendons = std::slice::from_ref(&params[2]);
        // The prior itself: mostly "within" by mass, but it says nothing.
        let prior = draws(&params[2], params[2].low, params[2].high);
        let d = &read(tendons, &prior)[0];
        assert_eq!(d.reading, "undetermined", "{d:?}");
        assert!(d.reason.as_ref().unwrap().contains("pin"), "{d:?}");
        // Narrow, but half above and half within (the openapi example's E_tendons).
        let straddle = draws(&params[2], 3e6, 8e6);
        assert_eq!(read(tendons, &straddle)[0].reading, "undetermined");
        // Narrow and inside: within.
        assert_eq!(read(tendons, &draws(&params[2], 1e6, 3e6))[0].reading, "within");
        // 90 % above the normal range (5 MPa) is not enough for "above"; 100 % is.
        let mostly = draws(&params[2], 5e6 / 10f64.powf(0.05), 5e6 * 10f64.powf(0.45));
        let d = &read(tendons, &mostly)[0];
        assert!((d.p_above - 0.9).abs() < 0.02 && d.reading == "undetermined", "{d:?}");
        assert_eq!(read(tendons, &draws(&params[2], 6e6, 2e7))[0].reading, "above");
        // Piled against the upper bound: never a P = 1 reading.
        let hug = draws(&params[2], params[2].high * 0.97, params[2].high);
        let d = &read(tendons, &hug)[0];
        assert_eq!((d.reading, d.at_prior_bound, d.p_above), ("undetermined", Some("high"), 1.0), "{d:?}");
        let mut all = read(&params, &vec![params.iter().map(|p| lerp(p, p.low, p.high, 0.5)).collect(); 10]);
        withdraw(&mut all, "model does not fit");
        assert!(all.iter().all(|d| d.reading == "unreliable" && d.associated_with.is_none()));
    }
}
