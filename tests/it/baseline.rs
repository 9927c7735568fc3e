//! The nominal model against the normative data in tests/data/normative.json
//! (physics-notes §3, citations in the file).

use otofit::sim::{self, Effects, Model, ModelConfig, Theta};
use serde_json::Value;

fn normative() -> Value {
    let text = std::fs::read_to_string(concat!(env!("CARGO_MANIFEST_DIR"), "/tests/data/normative.json")).unwrap();
    serde_json::from_str(&text).unwrap()
}

fn floats(v: &Value) -> Vec<f64> {
    v.as_array().unwrap().iter().map(|x| x.as_f64().unwrap()).collect()
}

/// Linear interpolation in log-frequency of one measure's 50 values.
fn at(freqs: &[f64], values: &[f64], f: f64) -> f64 {
    let i = freqs.iter().position(|&g| g >= f).unwrap().max(1);
    let t = (f.ln() - freqs[i - 1].ln()) / (freqs[i].ln() - freqs[i - 1].ln());
    values[i - 1] * (1.0 - t) + values[i] * t
}

struct Baseline {
    freqs: Vec<f64>,
    x: Vec<f64>,
}

impl Baseline {
    fn new() -> Baseline {
        let model = Model::new(ModelConfig::default()).unwrap();
        let x = sim::simulate(&mut model.runner(), &Theta::nominal(), &Effects::default()).unwrap();
        Baseline { freqs: model.frequencies().to_vec(), x }
    }
    /// Measure k (0..5) at frequency f.
    fn get(&self, k: usize, f: f64) -> f64 {
        at(&self.freqs, &self.x[50 * k..50 * (k + 1)], f)
    }
    fn vst_db(&self, f: f64) -> f64 {
        20.0 * (self.get(0, f) + 3.0) // log10(m/s/Pa) → dB re 1 mm/s/Pa
    }
}

#[test]
fn stapes_velocity_inside_the_astm_soft_gate() {
    let (b, n) = (Baseline::new(), normative());
    let g = &n["vst_gate"];
    let (fs, lo, hi) = (floats(&g["frequency_hz"]), floats(&g["lower"]), floats(&g["upper"]));
    for k in 0..fs.len() {
        let v = b.vst_db(fs[k]);
        eprintln!("vst {} Hz: {v:.1} dB", fs[k]);
        assert!(v >= lo[k] && v <= hi[k], "vst at {} Hz = {v:.1} dB outside [{}, {}]", fs[k], lo[k], hi[k]);
    }
    // Goode 1994 as a cross-check: the model runs 6–11 dB above it at 2–4 kHz (too little
    // high-frequency loss in an axisymmetric drum; README), so bound the RMS and the worst.
    let gd = &n["vst_goode1994"];
    let d: Vec<f64> =
        floats(&gd["frequency_hz"]).into_iter().zip(floats(&gd["value"])).map(|(f, v)| b.vst_db(f) - v).collect();
    let rms = (d.iter().map(|x| x * x).sum::<f64>() / d.len() as f64).sqrt();
    let worst = d.iter().fold(0.0f64, |m, x| m.max(x.abs()));
    eprintln!("vst vs Goode 1994: rms {rms:.1} dB, worst {worst:.1} dB");
    assert!(rms <= 8.0 && worst <= 12.0, "vst vs Goode: rms {rms:.1} dB, worst {worst:.1} dB ({d:.1?})");
}

#[test]
fn stapes_velocity_phase_is_stiffness_then_mass_controlled() {
    let (b, n) = (Baseline::new(), normative());
    let p = &n["vst_phase"];
    let (lo, hi) = (floats(&p["at_200hz_deg"])[0], floats(&p["at_200hz_deg"])[1]);
    let ph200 = b.x[50].to_degrees();
    assert!(ph200 >= lo && ph200 <= hi, "phase at 200 Hz = {ph200:.0}°");
    let zero = b.freqs.iter().zip(&b.x[50..100]).find(|(_, ph)| **ph < 0.0).map(|(f, _)| *f).unwrap();
    let z = floats(&p["zero_crossing_hz"]);
    assert!(zero >= z[0] && zero <= z[1], "phase crosses 0 at {zero:.0} Hz");
    // Monotone lag above the crossing; beyond −90° by 3 kHz.
    assert!(b.x[51..100].windows(2).all(|w| w[1] <= w[0] + 1e-9), "phase not monotone");
    assert!(b.get(1, 3000.0).to_degrees() < -90.0);
}

#[test]
fn absorbance_inside_the_normative_range() {
    let (b, n) = (Baseline::new(), normative());
    let a = &n["absorbance"];
    let (fs, lo, hi) = (floats(&a["frequency_hz"]), floats(&a["low"]), floats(&a["high"]));
    for k in 0..fs.len() {
        let v = b.get(4, fs[k]);
        eprintln!("absorbance {} Hz: {v:.2}", fs[k]);
        assert!(v >= lo[k] && v <= hi[k], "A at {} Hz = {v:.2} outside [{}, {}]", fs[k], lo[k], hi[k]);
    }
    // Shape: a broad maximum of 0.6–0.9 between 1.5 and 4 kHz.
    let (i_max, a_max) = b.x[200..250].iter().enumerate().fold((0, 0.0), |m, (i, &v)| if v > m.1 { (i, v) } else { m });
    assert!((0.6..=0.9).contains(&a_max), "max A {a_max:.2}");
    assert!((1500.0..=4000.0).contains(&b.freqs[i_max]), "max A at {:.0} Hz", b.freqs[i_max]);
}

#[test]
fn ear_canal_impedance_inside_the_normative_range() {
    let (b, n) = (Baseline::new(), normative());
    let z = &n["zec"];
    let fs = floats(&z["frequency_hz"]);
    let (mlo, mhi) = (floats(&z["mag_low"]), floats(&z["mag_high"]));
    let (plo, phi) = (floats(&z["phase_low_deg"]), floats(&z["phase_high_deg"]));
    let miss = floats(&z["phase_known_miss_deg"]);
    for k in 0..fs.len() {
        let m = 10f64.powf(b.get(2, fs[k]));
        let p = b.get(3, fs[k]).to_degrees();
        eprintln!("zec {} Hz: {m:.2e} {p:.0}°", fs[k]);
        assert!(m >= mlo[k] && m <= mhi[k], "|Zec| at {} Hz = {m:.2e}", fs[k]);
        assert!(p >= plo[k] - miss[k] && p <= phi[k] + miss[k], "Zec phase at {} Hz = {p:.0}°", fs[k]);
    }
    // The quarter-wave minimum of the path from the measurement plane to the drum.
    let g = otofit::sim::Geometry::default();
    let f_qw = 344.0 / (4.0 * (g.canal_length - g.zec_plane));
    let (i_min, _) =
        b.x[100..150].iter().enumerate().skip(25).fold((0, f64::MAX), |m, (i, &v)| if v < m.1 { (i, v) } else { m });
    let f_min = b.freqs[i_min];
    assert!(f_min > 0.8 * f_qw && f_min < 1.25 * f_qw, "|Zec| minimum at {f_min:.0} Hz, quarter wave {f_qw:.0} Hz");
}
