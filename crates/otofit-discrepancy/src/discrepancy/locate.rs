//! Where the misfit is: contiguous runs of large standardised residuals, reported as
//! measure × frequency band with a sign.

use crate::sim::output::MEASURES;
use serde::Serialize;

/// One run of misfit: a measure's frequency band where the observation leaves the model
/// on one side.
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct Band {
    /// The measure's name (as in `sim::output::MEASURES`).
    pub measure: &'static str,
    /// Lowest frequency of the run, Hz.
    pub f_lo_hz: f64,
    /// Highest frequency of the run, Hz.
    pub f_hi_hz: f64,
    /// +1: the measurement lies above the model; −1: below.
    pub sign: i8,
    /// Mean standardised residual over the run: how far out it lies, in noise units.
    pub mean_z: f64,
    /// Neighbouring features in the run.
    pub n_features: usize,
}

impl Band {
    /// The band in one sentence for reports ("zec_mag above the model from 800 to 2000
    /// Hz (mean z +3.1)").
    pub fn describe(&self) -> String {
        format!(
            "{} {} the model from {:.0} to {:.0} Hz (mean z {:+.1})",
            self.measure,
            if self.sign > 0 { "above" } else { "below" },
            self.f_lo_hz,
            self.f_hi_hz,
            self.mean_z
        )
    }
}

/// `z`: standardised residuals (observation − prediction)/σ, measure-major over `freqs`.
/// A band is a run of at least `min_len` neighbouring features of one sign with
/// |z| > `threshold`.
pub fn locate(z: &[f64], freqs: &[f64], threshold: f64, min_len: usize) -> Vec<Band> {
    let n = freqs.len();
    let mut bands = Vec::new();
    for (m, measure) in MEASURES.iter().enumerate().take(z.len() / n.max(1)) {
        let zs = &z[m * n..(m + 1) * n];
        let mut i = 0;
        while i < n {
            let s = zs[i].signum();
            if zs[i].abs() <= threshold {
                i += 1;
                continue;
            }
            let start = i;
            while i < n && zs[i].abs() > threshold && zs[i].signum() == s {
                i += 1;
            }
            if i - start >= min_len {
                bands.push(Band {
                    measure: measure.name,
                    f_lo_hz: freqs[start],
                    f_hi_hz: freqs[i - 1],
                    sign: s as i8,
                    mean_z: zs[start..i].iter().sum::<f64>() / (i - start) as f64,
                    n_features: i - start,
                });
            }
        }
    }
    bands
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn finds_runs_with_sign_and_ignores_isolated_spikes() {
        let freqs: Vec<f64> = (0..10).map(|i| 100.0 * (i + 1) as f64).collect();
        let mut z = vec![0.0; 50];
        z[2..6].copy_from_slice(&[-3.0, -4.0, -3.5, -3.1]); // vst_mag 300–600 Hz, low
        z[48] = 5.0; // one absorbance spike
        z[40 + 8] = 5.0;
        let b = locate(&z, &freqs, 2.5, 3);
        assert_eq!(b.len(), 1);
        assert_eq!(
            (b[0].measure, b[0].f_lo_hz, b[0].f_hi_hz, b[0].sign, b[0].n_features),
            ("vst_mag", 300.0, 600.0, -1, 4)
        );
        assert!(b[0].describe().contains("below the model from 300 to 600 Hz"));
    }
}
