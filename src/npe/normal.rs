//! Normal ranges of the seven parameters (the span of values reported for normal ears,
//! physics-notes §2) and differential reading of a posterior against them: the posterior
//! probability below, within and above, and the conditions a deviation is associated
//! with. Information for a clinician, not a diagnosis.

use serde::Serialize;

pub struct NormalRange {
    pub name: &'static str,
    pub low: f64,
    pub high: f64,
    pub source: &'static str,
    pub below: &'static str,
    pub above: &'static str,
}

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

#[derive(Clone, Debug, Serialize)]
pub struct Differential {
    pub name: String,
    pub normal_low: f64,
    pub normal_high: f64,
    pub p_below: f64,
    pub p_within: f64,
    pub p_above: f64,
    /// "below", "within" or "above": the most probable of the three.
    pub reading: &'static str,
    /// What a deviation in the most probable direction is associated with (if not within).
    pub associated_with: Option<&'static str>,
    pub source: &'static str,
}

/// Reads posterior samples (columns in `names` order) against the normal ranges; columns
/// without a range are skipped.
pub fn read(names: &[&str], samples: &[Vec<f64>]) -> Vec<Differential> {
    let n = samples.len().max(1) as f64;
    names
        .iter()
        .enumerate()
        .filter_map(|(k, name)| {
            let r = NORMAL.iter().find(|r| r.name == *name)?;
            let below = samples.iter().filter(|s| s[k] < r.low).count() as f64 / n;
            let above = samples.iter().filter(|s| s[k] > r.high).count() as f64 / n;
            let within = 1.0 - below - above;
            let (reading, associated_with) = if within >= below && within >= above {
                ("within", None)
            } else if below > above {
                ("below", Some(r.below))
            } else {
                ("above", Some(r.above))
            };
            Some(Differential {
                name: name.to_string(),
                normal_low: r.low,
                normal_high: r.high,
                p_below: below,
                p_within: within,
                p_above: above,
                reading,
                associated_with,
                source: r.source,
            })
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn ranges_lie_inside_the_prior_and_readings_follow_the_mass() {
        for (r, p) in NORMAL.iter().zip(crate::sim::PARAMS) {
            assert_eq!(r.name, p.name);
            assert!(p.low <= r.low && r.low < r.high && r.high <= p.high, "{}", r.name);
            assert!(r.low <= p.nominal && p.nominal <= r.high, "nominal {} outside its normal range", r.name);
        }
        let stiff: Vec<Vec<f64>> = (0..100).map(|i| vec![2e6 + 1e4 * i as f64]).collect();
        let d = read(&["E_sal"], &stiff);
        assert_eq!((d[0].reading, d[0].p_above), ("above", 1.0));
        assert!(d[0].associated_with.unwrap().contains("otosclerosis"));
        assert!(read(&["other"], &stiff).is_empty());
    }
}
