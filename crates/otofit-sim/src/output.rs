//! From complex responses to the 350 features: seven measures × the frequency grid, in
//! the order and units of simulator.md, and the test–retest noise model. Umbo velocity
//! comes last so that the first 250 features keep the order of five-measure models.

use super::model::Response;
use serde::Serialize;
use std::f64::consts::PI;

/// One measure (a block of the feature vector).
#[derive(Clone, Copy, Debug, Serialize)]
pub struct Measure {
    /// Feature-name prefix (`<name>_<frequency index>`), as in datasets and requests.
    pub name: &'static str,
    /// The unit of the features (magnitudes as log10 of the physical unit).
    pub unit: &'static str,
    /// Test–retest standard deviation at ≤ 2 kHz (simulator.md noise model).
    pub noise_std: f64,
    /// The physical envelope of the feature (its unit): values outside cannot come from a
    /// human ear measured in these units, whatever the pathology, and they hold every
    /// simulation of the prior box (v7, 20,000 draws: velocity 1.4e-11…1.6e-3 m/s/Pa, umbo
    /// up to 5.0e-2, phase −23.5…+2.6 rad, |Z| 1.4e5…1.0e9, Z phase ±1.56 rad). Velocity
    /// 1e-12 to 1e-2 m/s/Pa (umbo: below); impedance 10^4.5–1e10 Pa·s/m³ (the canal's own
    /// Z0 is ~1e7); a passive impedance's phase within ±90° (+20° for probe calibration
    /// error); unwrapped velocity phase −1620…+360° (the line drum's softest drums delay
    /// by up to ~300 µs); absorbance 0–1 with five test–retest STDs (0.15) either side: a
    /// measurement is the ear's value plus noise, so the model's own 1×-noise ears must
    /// pass (at ±0.05, 1.7 STD, 60 of 1,000 noisy prior ears failed, all below 600 Hz).
    pub envelope: (f64, f64),
}

/// The number of measures in a feature vector (five before umbo velocity joined).
pub const N_MEASURES: usize = 7;

/// The measures in feature-vector order, each a block of one value per frequency.
pub const MEASURES: [Measure; N_MEASURES] = [
    Measure { name: "vst_mag", unit: "log10(m/s/Pa)", noise_std: 0.075, envelope: (-12.0, -2.0) },
    Measure { name: "vst_phase", unit: "rad", noise_std: 0.10, envelope: (-9.0 * PI, 2.0 * PI) },
    Measure { name: "zec_mag", unit: "log10(Pa·s/m³)", noise_std: 0.05, envelope: (4.5, 10.0) },
    Measure { name: "zec_phase", unit: "rad", noise_std: 0.05, envelope: (-0.5 * PI - 0.35, 0.5 * PI + 0.35) },
    Measure { name: "absorbance", unit: "1", noise_std: 0.03, envelope: (-0.15, 1.15) },
    // Umbo LDV through the canal: the stapes LDV's test–retest STD (the design notes hold
    // no separate umbo figure). The umbo moves 2–10× the stapes, and the prior box's
    // floppiest ears reach 5.0e-2 m/s/Pa (v7, 20,000 draws), so its envelope ends at
    // 10^−0.8 (160 mm/s/Pa), still below a normal umbo curve sent in mm/s/Pa (peak ~0.3 → −0.5).
    Measure { name: "vu_mag", unit: "log10(m/s/Pa)", noise_std: 0.075, envelope: (-12.0, -0.8) },
    Measure { name: "vu_phase", unit: "rad", noise_std: 0.10, envelope: (-9.0 * PI, 2.0 * PI) },
];

/// The first feature of each measure outside its physical envelope, as (measure index,
/// feature index, value); absent features (`present[i]` false) are skipped.
pub fn implausible(x: &[f64], present: &[bool], n_freq: usize) -> Vec<(usize, usize, f64)> {
    let n = n_freq.max(1);
    MEASURES[..(x.len() / n).min(N_MEASURES)]
        .iter()
        .enumerate()
        .filter_map(|(m, ms)| {
            (m * n..(m + 1) * n)
                .find(|&i| present[i] && !(ms.envelope.0..=ms.envelope.1).contains(&x[i]))
                .map(|i| (m, i, x[i]))
        })
        .collect()
}

/// Feature groups a model can be asked to work without (modalities).
pub const GROUPS: [(&str, &[&str]); 4] = [
    ("stapes_velocity", &["vst_mag", "vst_phase"]),
    ("impedance", &["zec_mag", "zec_phase"]),
    ("absorbance", &["absorbance"]),
    ("umbo_velocity", &["vu_mag", "vu_phase"]),
];

/// `measure@frequency` names, measure-major.
pub fn feature_names(freqs: &[f64]) -> Vec<String> {
    MEASURES.iter().flat_map(|m| freqs.iter().map(move |f| format!("{}@{:.1}", m.name, f))).collect()
}

/// The feature vector of one run (measure-major, phases unwrapped along frequency).
pub fn features(responses: &[Response]) -> Vec<f64> {
    let n = responses.len();
    let mut out = Vec::with_capacity(N_MEASURES * n);
    out.extend(responses.iter().map(|r| r.vst_over_p.norm().log10()));
    out.extend(unwrap(responses.iter().map(|r| r.vst_over_p.arg())));
    out.extend(responses.iter().map(|r| r.zec.norm().log10()));
    out.extend(unwrap(responses.iter().map(|r| r.zec.arg())));
    out.extend(responses.iter().map(|r| r.absorbance()));
    out.extend(responses.iter().map(|r| r.vu_over_p.norm().log10()));
    out.extend(unwrap(responses.iter().map(|r| r.vu_over_p.arg())));
    out
}

/// Unwraps phases so that consecutive values differ by less than π. The first value is
/// kept in (−π, π].
pub fn unwrap(phases: impl Iterator<Item = f64>) -> Vec<f64> {
    let mut out: Vec<f64> = Vec::new();
    for p in phases {
        let v = match out.last() {
            None => p,
            Some(&prev) => {
                let tau = std::f64::consts::TAU;
                p + tau * ((prev - p) / tau).round()
            }
        };
        out.push(v);
    }
    out
}

/// Test–retest standard deviation per feature: the measure's value, rising linearly in
/// log-frequency from 1× at ≤ 2 kHz to 2× at 8 kHz (and beyond, by the same slope).
pub fn noise_std(freqs: &[f64]) -> Vec<f64> {
    MEASURES
        .iter()
        .flat_map(|m| freqs.iter().map(move |&f| m.noise_std * (1.0 + ((f / 2000.0).max(1.0)).log(4.0))))
        .collect()
}

/// Linear interpolation in log-frequency of (f, v) at each grid frequency, held constant
/// beyond the end points. `f` must increase strictly and hold at least 2 points.
pub fn interpolate_log_f(f: &[f64], v: &[f64], grid: &[f64]) -> Vec<f64> {
    grid.iter()
        .map(|&g| {
            let i = f.partition_point(|&x| x < g).clamp(1, f.len() - 1);
            let t = ((g.ln() - f[i - 1].ln()) / (f[i].ln() - f[i - 1].ln())).clamp(0.0, 1.0);
            v[i - 1] * (1.0 - t) + v[i] * t
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn unwrap_removes_jumps() {
        let w = unwrap([3.0, -3.0, -2.5, 2.9].into_iter());
        assert!((w[1] - (-3.0 + std::f64::consts::TAU)).abs() < 1e-12);
        for p in w.windows(2) {
            assert!((p[1] - p[0]).abs() < std::f64::consts::PI);
        }
    }

    #[test]
    fn noise_rises_from_one_to_two_times() {
        let s = noise_std(&[200.0, 2000.0, 4000.0, 8000.0]);
        assert_eq!(s[0], 0.075);
        assert_eq!(s[1], 0.075);
        assert!((s[2] - 0.075 * 1.5).abs() < 1e-12);
        assert!((s[3] - 0.15).abs() < 1e-12);
        assert!((s[19] - 0.06).abs() < 1e-12);
    }

    #[test]
    fn names_follow_measure_at_frequency() {
        let n = feature_names(&[200.0, 1000.0]);
        assert_eq!(n[0], "vst_mag@200.0");
        assert_eq!(n[9], "absorbance@1000.0");
    }
}
