//! The measured-like reference ear: normative mean spectra with citations
//! (`reference/ear.json`), interpolated onto a model's frequency grid as an observation
//! (350 features) with a test–retest STD per feature. The table holds no umbo velocity
//! (the design notes cite no normative umbo curve): those features are NaN, absent; their
//! STD is the noise model's, so that std.csv stays a complete noise table.

use crate::sim::output::{MEASURES, feature_names, interpolate_log_f, noise_std};
use serde::Deserialize;
use std::collections::BTreeMap;

/// The compiled-in anchor table is not usable: always an internal error (the table ships
/// with the binary; no caller input reaches it).
#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum ReferenceError {
    /// The table is not the expected JSON.
    #[error("reference/ear.json")]
    Json(#[source] serde_json::Error),
    /// A curve cannot be interpolated.
    #[error("reference/ear.json: '{0}' needs ≥ 2 strictly increasing positive frequencies, one value each")]
    Curve(&'static str),
    /// A measure's STD level is missing.
    #[error("reference/ear.json: std.{0} missing")]
    MissingStd(&'static str),
}

type Result<T> = std::result::Result<T, ReferenceError>;

/// The anchor table, compiled into the binary so that the service and the Docker image
/// need no data folder.
pub const EAR_JSON: &str = include_str!("../../../reference/ear.json");

#[derive(Deserialize)]
struct Curve {
    frequency_hz: Vec<f64>,
    value: Vec<f64>,
    citation: String,
}

#[derive(Deserialize)]
struct Table {
    vst_mag_db: Curve,
    vst_phase_deg: Curve,
    zec_mag: Curve,
    zec_phase_deg: Curve,
    absorbance: Curve,
    std: BTreeMap<String, serde_json::Value>,
}

/// The reference ear on one frequency grid, in feature units.
pub struct Reference {
    /// One name per feature (the model grid's).
    pub feature_names: Vec<String>,
    /// The reference ear's features.
    pub x: Vec<f64>,
    /// Test–retest STD per feature.
    pub std: Vec<f64>,
    /// One citation per measure, in `MEASURES` order.
    pub citations: Vec<String>,
}

/// Linear interpolation in log-frequency, constant beyond the end anchors.
fn interpolate(c: &Curve, name: &'static str, grid: &[f64]) -> Result<Vec<f64>> {
    let f = &c.frequency_hz;
    if f.len() < 2 || f.len() != c.value.len() || f.windows(2).any(|w| w[1] <= w[0]) || f[0] <= 0.0 {
        return Err(ReferenceError::Curve(name));
    }
    Ok(interpolate_log_f(f, &c.value, grid))
}

/// Builds the reference ear on `freqs` (the model grid).
pub fn build(freqs: &[f64]) -> Result<Reference> {
    let t: Table = serde_json::from_str(EAR_JSON).map_err(ReferenceError::Json)?;
    let mut x = Vec::with_capacity(MEASURES.len() * freqs.len());
    // vst in feature units: log10(m/s/Pa) from dB re 1 mm/s/Pa; phases in rad.
    x.extend(interpolate(&t.vst_mag_db, "vst_mag_db", freqs)?.iter().map(|db| db / 20.0 - 3.0));
    x.extend(interpolate(&t.vst_phase_deg, "vst_phase_deg", freqs)?.iter().map(|d| d.to_radians()));
    x.extend(interpolate(&log10(&t.zec_mag), "zec_mag", freqs)?);
    x.extend(interpolate(&t.zec_phase_deg, "zec_phase_deg", freqs)?.iter().map(|d| d.to_radians()));
    x.extend(interpolate(&t.absorbance, "absorbance", freqs)?);
    x.resize(MEASURES.len() * freqs.len(), f64::NAN);
    // STD: the noise model's shape in frequency, at the table's level per measure.
    let mut std = noise_std(freqs);
    for (m, measure) in MEASURES.iter().enumerate().take(5) {
        let level = t.std.get(measure.name).and_then(|v| v.as_f64()).ok_or(ReferenceError::MissingStd(measure.name))?;
        for s in &mut std[m * freqs.len()..(m + 1) * freqs.len()] {
            *s *= level / measure.noise_std;
        }
    }
    let mut citations: Vec<String> = [&t.vst_mag_db, &t.vst_phase_deg, &t.zec_mag, &t.zec_phase_deg, &t.absorbance]
        .iter()
        .map(|c| c.citation.clone())
        .collect();
    citations.resize(MEASURES.len(), "none: no normative umbo velocity in the design notes; absent".into());
    Ok(Reference { feature_names: feature_names(freqs), x, std, citations })
}

fn log10(c: &Curve) -> Curve {
    Curve {
        frequency_hz: c.frequency_hz.clone(),
        value: c.value.iter().map(|v| v.log10()).collect(),
        citation: String::new(),
    }
}

/// One-row CSV with a header of feature names (the OBS format of `otofit infer`);
/// absent (non-finite) features are left out, as `otofit infer` reads absent columns.
pub fn csv(names: &[String], row: &[f64]) -> String {
    let on: Vec<usize> = (0..row.len()).filter(|&i| row[i].is_finite()).collect();
    let head: Vec<&str> = on.iter().map(|&i| names[i].as_str()).collect();
    let cells: Vec<String> = on.iter().map(|&i| format!("{:.6e}", row[i])).collect();
    format!("{}\n{}\n", head.join(","), cells.join(","))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::sim::{Model, ModelConfig};

    #[test]
    fn anchors_are_reproduced_on_the_grid() {
        let freqs = [200.0, 1000.0, 2000.0, 8000.0];
        let r = build(&freqs).unwrap();
        let n = freqs.len();
        // Goode 1994 at 1 kHz: −19.5 dB re 1 mm/s/Pa.
        assert!((r.x[1] - (-19.5 / 20.0 - 3.0)).abs() < 1e-12);
        assert!((r.x[n + 2] - (-90f64).to_radians()).abs() < 1e-12);
        assert!((r.x[4 * n + 2] - 0.70).abs() < 1e-12);
        // Absorbance is held below its first anchor (250 Hz).
        assert!((r.x[4 * n] - 0.12).abs() < 1e-12);
        // The STD doubles from 2 to 8 kHz.
        assert!((r.std[4 * n + 3] / r.std[4 * n + 2] - 2.0).abs() < 1e-12);
    }

    #[test]
    fn shipped_csvs_match_the_table() {
        let model = Model::new(ModelConfig::default()).unwrap();
        let r = build(model.frequencies()).unwrap();
        let root = concat!(env!("CARGO_MANIFEST_DIR"), "/../..");
        let obs = std::fs::read_to_string(format!("{root}/reference/obs.csv")).unwrap();
        let std = std::fs::read_to_string(format!("{root}/reference/std.csv")).unwrap();
        assert_eq!(
            obs,
            csv(&r.feature_names, &r.x),
            "reference/obs.csv is stale: run `otofit study reference --out DIR` and copy DIR/reference_obs.csv"
        );
        assert_eq!(std, csv(&r.feature_names, &r.std), "reference/std.csv is stale");
    }
}
