//! The model-error term against its analytic posterior: a linear simulator whose inputs
//! carry noise and a smooth Gaussian discrepancy has a Gaussian likelihood with covariance
//! σ²(I + k²K); a flow trained with that term must recover that posterior, which is much
//! wider than the noise-only one.

use otofit::npe::{self, Dataset, ModelError, Npe, Obs, Param, Scale, TrainSettings};
use otofit_npe::spd;
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use rand_distr::{Distribution, StandardNormal};

const SIGMA: f64 = 0.2;
const N: usize = 8;
const ME: ModelError = ModelError { scale: 2.0, octaves: 1.0, varying: false };

fn grid() -> Vec<f64> {
    (0..N).map(|i| 250.0 * 32f64.powf(i as f64 / (N - 1) as f64)).collect()
}

/// The design: an offset and a slope in log frequency (what a smooth discrepancy mimics
/// best, so the term must widen both).
fn design() -> Vec<[f64; 2]> {
    grid().iter().map(|f| [1.0, (f / 250.0).log2() / 5.0 - 0.5]).collect()
}

fn dataset(n: usize, seed: u64) -> Dataset {
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    let params = ["offset", "slope"]
        .iter()
        .map(|n| Param { name: n.to_string(), unit: "1".into(), scale: Scale::Linear, low: -4.0, high: 4.0 })
        .collect();
    let a = design();
    let theta: Vec<Vec<f64>> = (0..n).map(|_| vec![rng.random_range(-4.0..4.0), rng.random_range(-4.0..4.0)]).collect();
    let x = theta.iter().map(|t| a.iter().map(|r| r[0] * t[0] + r[1] * t[1]).collect()).collect();
    Dataset {
        params,
        feature_names: (0..N).map(|k| format!("x{k}")).collect(),
        frequencies_hz: grid(),
        groups: vec![],
        noise_std: vec![SIGMA; N],
        theta,
        x,
        skipped: 0,
    }
}

/// The likelihood's covariance: σ²I plus the model error's σ²k²K (`with`), or noise only.
fn covariance(with: bool) -> Vec<Vec<f64>> {
    let l2: Vec<f64> = grid().iter().map(|f| f.log2()).collect();
    (0..N)
        .map(|i| {
            (0..N)
                .map(|j| {
                    let d = (l2[i] - l2[j]) / ME.octaves;
                    let me = if with { ME.scale * ME.scale * (-0.5 * d * d).exp() } else { 0.0 };
                    SIGMA * SIGMA * (me + if i == j { 1.0 } else { 0.0 })
                })
                .collect()
        })
        .collect()
}

/// Exact posterior (flat prior: the box is wide) of a linear Gaussian likelihood:
/// mean (AᵀΣ⁻¹A)⁻¹AᵀΣ⁻¹x and the marginal stds.
fn exact(x: &[f64], with: bool) -> ([f64; 2], [f64; 2]) {
    let si = spd::inverse(&covariance(with)).unwrap();
    let a = design();
    let mut p = [[0.0; 2]; 2];
    let mut b = [0.0; 2];
    for i in 0..N {
        for j in 0..N {
            for r in 0..2 {
                b[r] += a[i][r] * si[i][j] * x[j];
                for c in 0..2 {
                    p[r][c] += a[i][r] * si[i][j] * a[j][c];
                }
            }
        }
    }
    let cov = spd::inverse(&[p[0].to_vec(), p[1].to_vec()]).unwrap();
    let mean = [cov[0][0] * b[0] + cov[0][1] * b[1], cov[1][0] * b[0] + cov[1][1] * b[1]];
    (mean, [cov[0][0].sqrt(), cov[1][1].sqrt()])
}

fn trained() -> Npe {
    let s = TrainSettings {
        max_epochs: 300,
        patience: 300,
        lr_cosine: true,
        seed: 3,
        model_error: Some(ME),
        ..otofit::bench::sbi_nsf_settings()
    };
    npe::train(&dataset(4000, 1), &s, &mut |_| true).unwrap()
}

/// An observation: the truth through the design, plus noise and one draw of the model
/// error (the sampler the training uses, on a stream of its own).
fn observe(t: [f64; 2], rng: &mut ChaCha8Rng, case: usize) -> Vec<f64> {
    let mut x: Vec<f64> = design()
        .iter()
        .map(|r| {
            let e: f64 = StandardNormal.sample(rng);
            r[0] * t[0] + r[1] * t[1] + SIGMA * e
        })
        .collect();
    ME.sampler(&grid(), &[SIGMA; N]).unwrap().add_for_row(&mut x, 99, case);
    x
}

/// The analytic check is able to fail: the model error widens the exact posterior of
/// both parameters by far more than the ±10 % tolerance below.
#[test]
fn the_model_error_widens_the_exact_posterior() {
    let x = vec![0.0; N];
    let (_, with) = exact(&x, true);
    let (_, without) = exact(&x, false);
    for k in 0..2 {
        assert!(with[k] / without[k] > 1.5, "θ{k}: std {:.4} with, {:.4} without", with[k], without[k]);
    }
}

/// Means within 0.3 σ and stds within ±10 % of the exact posterior with the model error.
#[test]
#[cfg_attr(not(feature = "slow-tests"), ignore = "slow tier: `cargo test --features slow-tests`, run by .ci/run")]
fn training_with_a_model_error_recovers_its_analytic_posterior() {
    let model = trained();
    assert_eq!(model.header.model_error, Some(ME));
    let mut rng = ChaCha8Rng::seed_from_u64(9);
    for case in 0..4 {
        let t = [rng.random_range(-2.0..2.0), rng.random_range(-2.0..2.0)];
        let x = observe(t, &mut rng, case);
        let (mean, std) = exact(&x, true);
        let inf = model.infer(&Obs { x: &x, present: None }, 40_000, case as u64).unwrap();
        for k in 0..2 {
            let (m, s) = (inf.summaries[k].mean, inf.summaries[k].std);
            eprintln!("case {case} θ{k}: mean {m:.3} (exact {:.3}), std {s:.3} (exact {:.3})", mean[k], std[k]);
            assert!((m - mean[k]).abs() < 0.3 * std[k], "case {case} θ{k}: mean {m} vs {}", mean[k]);
            assert!((s / std[k] - 1.0).abs() < 0.10, "case {case} θ{k}: std {s} vs {}", std[k]);
        }
    }
}

/// The term travels with the model: saved, loaded and refused when unusable.
#[test]
fn the_model_error_is_kept_in_the_checkpoint_and_checked_on_load() {
    let s = TrainSettings { max_epochs: 2, model_error: Some(ME), ..TrainSettings::default() };
    let model = npe::train(&dataset(200, 2), &s, &mut |_| true).unwrap();
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("m.otofit");
    model.save(&path).unwrap();
    let back = Npe::load(&path).unwrap();
    assert_eq!(back.header.model_error, Some(ME));
    // Its training inputs' spread includes the term: √(spread² + σ² + (kσ)²).
    let clean = npe::train(&dataset(200, 2), &TrainSettings { model_error: None, ..s.clone() }, &mut |_| true).unwrap();
    for (w, c) in back.header.x_std.iter().zip(&clean.header.x_std) {
        let want = (c * c + (ME.scale * SIGMA).powi(2)).sqrt();
        assert!((w - want).abs() < 1e-9, "x_std {w} against {want}");
    }
    let mut bad = back.header.clone();
    bad.model_error = Some(ModelError { scale: -1.0, ..ME });
    let err = bad.validate().unwrap_err().to_string();
    assert!(err.contains("model_error"), "{err}");
    // A table without a frequency grid cannot take the term: named before training.
    let mut flat = dataset(200, 2);
    flat.frequencies_hz.clear();
    match npe::train(&flat, &s, &mut |_| true) {
        Err(npe::NpeError::Settings { field, .. }) => assert_eq!(field, "model-error"),
        Err(e) => panic!("another error: {e}"),
        Ok(_) => panic!("trained a model error without a frequency grid"),
    }
}
