//! NPE against an analytic posterior, calibration, checkpoints and determinism.

use otofit::npe::{self, Dataset, Npe, Obs, Param, Scale, TrainSettings};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;

const A: [[f64; 2]; 3] = [[1.0, 0.5], [-0.3, 1.0], [0.8, 0.8]];
const SIGMA: f64 = 0.3;

/// x = Aθ (noise comes from the noise model during training), θ uniform on [−4, 4]².
fn linear_gaussian(n: usize, seed: u64) -> Dataset {
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    let params: Vec<Param> = ["a", "b"]
        .iter()
        .map(|n| Param { name: n.to_string(), unit: "1".into(), scale: Scale::Linear, low: -4.0, high: 4.0 })
        .collect();
    let theta: Vec<Vec<f64>> = (0..n).map(|_| vec![rng.random_range(-4.0..4.0), rng.random_range(-4.0..4.0)]).collect();
    let x = theta.iter().map(|t| A.iter().map(|r| r[0] * t[0] + r[1] * t[1]).collect()).collect();
    Dataset {
        params,
        feature_names: vec!["x0".into(), "x1".into(), "x2".into()],
        frequencies_hz: vec![],
        groups: vec![],
        noise_std: vec![SIGMA; 3],
        theta,
        x,
        skipped: 0,
    }
}

/// Exact posterior of θ for a flat prior (the box is wide): N((AᵀA)⁻¹Aᵀx, σ²(AᵀA)⁻¹).
fn exact(x: &[f64]) -> ([f64; 2], [f64; 2]) {
    let mut ata = [[0.0; 2]; 2];
    let mut atx = [0.0; 2];
    for (r, xi) in A.iter().zip(x) {
        for i in 0..2 {
            atx[i] += r[i] * xi;
            for j in 0..2 {
                ata[i][j] += r[i] * r[j];
            }
        }
    }
    let det = ata[0][0] * ata[1][1] - ata[0][1] * ata[1][0];
    let inv = [[ata[1][1] / det, -ata[0][1] / det], [-ata[1][0] / det, ata[0][0] / det]];
    let mean = [inv[0][0] * atx[0] + inv[0][1] * atx[1], inv[1][0] * atx[0] + inv[1][1] * atx[1]];
    (mean, [SIGMA * inv[0][0].sqrt(), SIGMA * inv[1][1].sqrt()])
}

fn trained() -> &'static Npe {
    static MODEL: std::sync::OnceLock<Npe> = std::sync::OnceLock::new();
    MODEL.get_or_init(|| {
        let ds = linear_gaussian(4000, 1);
        // sbi's NSF with the rate decayed by a half cosine over a fixed 300 epochs: the
        // stds come within 4.3 % here (seeds 4-8: 5.3-5.7 %, from 40,000 draws). Early
        // stopping at a constant rate left them 3-20 % too wide (docs/npe.md, "The
        // analytic check").
        let s = TrainSettings {
            max_epochs: 300,
            patience: 300,
            lr_cosine: true,
            seed: 3,
            ..otofit::bench::sbi_nsf_settings()
        };
        npe::train(&ds, &s, &mut |r| {
            eprintln!("epoch {} train {:.3} val {:.3}", r.epoch, r.train_loss, r.val_loss);
            true
        })
        .unwrap()
    })
}

/// (mean, std, MAP) of θ0 and θ1 for one observation.
type Summaries = [(f64, f64, f64); 2];

/// Mean within 0.25 σ, std within `std_tol` (relative) and MAP within `map_tol` σ of the
/// exact posterior on four observations; the first miss as an error.
fn matches_analytic(summaries: &dyn Fn(u64, &[f64]) -> Summaries, std_tol: f64, map_tol: f64) -> Result<(), String> {
    let mut rng = ChaCha8Rng::seed_from_u64(9);
    for case in 0..4 {
        let t = [rng.random_range(-2.0..2.0), rng.random_range(-2.0..2.0)];
        let x: Vec<f64> = A.iter().map(|r| r[0] * t[0] + r[1] * t[1] + SIGMA * rng.random_range(-1.0..1.0)).collect();
        let (mean, std) = exact(&x);
        for (k, (m, s, map)) in summaries(case, &x).into_iter().enumerate() {
            eprintln!(
                "case {case} θ{k}: mean {m:.3} (exact {:.3}), std {s:.3} (exact {:.3}), map {map:.3}",
                mean[k], std[k]
            );
            if (m - mean[k]).abs() >= 0.25 * std[k] {
                return Err(format!("case {case} θ{k}: mean {m} vs {}", mean[k]));
            }
            if (s / std[k] - 1.0).abs() >= std_tol {
                return Err(format!("case {case} θ{k}: std {s} vs {}", std[k]));
            }
            if (map - mean[k]).abs() >= map_tol * std[k] {
                return Err(format!("case {case} θ{k}: map {map} vs {}", mean[k]));
            }
        }
    }
    Ok(())
}

/// From 40,000 draws: the std's own sampling error is then 0.35 % (with 4,000, 1.1 %: at
/// seed 3 the worst of the eight stds read 7.4 % off from 4,000 draws, 4.3 % from 40,000).
fn flow_summaries(model: &Npe) -> impl Fn(u64, &[f64]) -> Summaries + '_ {
    move |case, x| {
        let inf = model.infer(&Obs { x, present: None }, 40_000, case).unwrap();
        [0, 1].map(|k| (inf.summaries[k].mean, inf.summaries[k].std, inf.summaries[k].map))
    }
}

/// The exact posterior's summaries with its std × `widen`.
fn exact_summaries(widen: f64) -> impl Fn(u64, &[f64]) -> Summaries {
    move |_, x| {
        let (mean, std) = exact(x);
        [0, 1].map(|k| (mean[k], std[k] * widen, mean[k]))
    }
}

/// The ±8 % std check, and its own sensitivity: the exact posterior
/// passes it and the exact posterior 18 % too wide fails it.
#[test]
fn the_8_percent_check_fails_a_posterior_18_percent_too_wide() {
    matches_analytic(&exact_summaries(1.0), 0.08, 0.3).unwrap();
    let err = matches_analytic(&exact_summaries(1.18), 0.08, 0.3).expect_err("18 % too wide passed");
    assert!(err.contains("std"), "{err}");
}

/// Means within 0.25 σ, stds within ±8 % and the MAP within 0.3 σ of the exact posterior,
/// which is 9× narrower than the prior.
#[test]
fn recovers_the_analytic_linear_gaussian_posterior() {
    matches_analytic(&flow_summaries(trained()), 0.08, 0.3).unwrap();
}

#[test]
#[cfg_attr(not(feature = "slow-tests"), ignore = "slow tier: `cargo test --features slow-tests`, run by .ci/run")]
fn coverage_on_held_out_simulations_is_not_overconfident() {
    let model = trained();
    let held = linear_gaussian(150, 77);
    let mut rng = ChaCha8Rng::seed_from_u64(5);
    let rows: Vec<(Vec<f64>, Vec<f64>)> = held
        .theta
        .iter()
        .zip(&held.x)
        .map(|(t, x)| {
            (t.clone(), x.iter().map(|v| v + SIGMA * rng.sample::<f64, _>(rand_distr::StandardNormal)).collect())
        })
        .collect();
    let cal = npe::calibrate::calibrate(model, &rows, 300, 1).unwrap();
    for (l, c) in cal.levels.iter().zip(&cal.coverage) {
        eprintln!("level {l:.2}: coverage {c:.3}");
        assert!(*c >= l - 0.1, "overconfident at {l}: {c}");
    }
}

/// Calibration reads its rows side by side, a few per thread at a time: every row's
/// draws come from the row's own seed, so one thread and two give the same coverage,
/// ranks and intervals.
#[test]
fn calibration_is_the_same_on_one_thread_and_on_two() {
    let model = trained();
    let held = linear_gaussian(21, 78);
    let mut rng = ChaCha8Rng::seed_from_u64(6);
    let noisy = |x: &Vec<f64>| x.iter().map(|v| v + SIGMA * rng.sample::<f64, _>(rand_distr::StandardNormal)).collect();
    let rows: Vec<(Vec<f64>, Vec<f64>)> = held.theta.iter().cloned().zip(held.x.iter().map(noisy)).collect();
    let on = |threads: usize| {
        let pool = rayon::ThreadPoolBuilder::new().num_threads(threads).build().unwrap();
        pool.install(|| npe::calibrate::calibrate(model, &rows, 50, 3).unwrap())
    };
    let (one, two) = (on(1), on(2));
    assert_eq!(one.coverage, two.coverage);
    assert_eq!(one.marginal_coverage90, two.marginal_coverage90);
    for (a, b) in one.sbc_ranks.iter().zip(&two.sbc_ranks) {
        assert_eq!(a.ranks, b.ranks, "{}", a.name);
    }
    assert_eq!(one.sbc_ranks[0].ranks.len(), rows.len());
}

/// A checkpoint with its JSON header rewritten by `edit` (the length field kept consistent).
fn with_header(bytes: &[u8], edit: impl Fn(String) -> String) -> Vec<u8> {
    let n = u64::from_le_bytes(bytes[11..19].try_into().unwrap()) as usize;
    let header = edit(String::from_utf8(bytes[19..19 + n].to_vec()).unwrap());
    let mut out = bytes[..11].to_vec();
    out.extend_from_slice(&(header.len() as u64).to_le_bytes());
    out.extend_from_slice(header.as_bytes());
    out.extend_from_slice(&bytes[19 + n..]);
    out
}

#[test]
#[cfg_attr(not(feature = "slow-tests"), ignore = "slow tier: `cargo test --features slow-tests`, run by .ci/run")]
fn checkpoints_round_trip_and_bad_files_are_refused() {
    let model = trained();
    let dir = std::env::temp_dir().join(format!("otofit-npe-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let path = dir.join("m.otofit");
    model.save(&path).unwrap();
    let loaded = Npe::load(&path).unwrap();
    let x = [0.3, -0.2, 0.9];
    let obs = Obs { x: &x, present: None };
    assert_eq!(model.sample(&obs, 50, 4).unwrap(), loaded.sample(&obs, 50, 4).unwrap());
    assert!(std::fs::metadata(&path).unwrap().len() < 1_000_000);
    let bytes = std::fs::read(&path).unwrap();
    let err = |b: &[u8]| Npe::from_bytes(b).err().map(|e| format!("{e:#}")).unwrap_or_default();
    assert!(err(b"hello").contains("bad magic"));
    assert!(err(&bytes[..bytes.len() / 2]).contains("weights") || err(&bytes[..bytes.len() / 2]).contains("truncated"));
    // The header rewritten with an unknown format (its length field kept consistent).
    let v9 = with_header(&bytes, |h| h.replace("\"format_version\":2", "\"format_version\":9"));
    assert!(err(&v9).contains("format 9"), "{}", err(&v9));
    // A header length near u64::MAX (once a slice panic) is a named error.
    let mut huge = bytes.clone();
    huge[11..19].copy_from_slice(&(u64::MAX - 3).to_le_bytes());
    assert!(err(&huge).contains("header length"), "{}", err(&huge));
    // Flow settings the code cannot build (bins ≥ 32 tripped an assert, 0 underflowed).
    for bad in ["\"bins\":40", "\"bins\":0"] {
        let b = with_header(&bytes, |h| h.replace("\"bins\":10", bad));
        assert!(err(&b).contains("bins must be 2..=31"), "{bad}: {}", err(&b));
    }
    let e = model.sample(&Obs { x: &x[..2], present: None }, 5, 0).unwrap_err();
    assert!(e.to_string().contains("expects 3"), "{e}");
    assert!(e.is_input(), "a short observation is the caller's fault: {e:?}");
    // Every header field is checked and named (once: NaN standardisation, a panic on a
    // zero member count or a short `present`).
    let first_x_std =
        |h: &str| h.split("\"x_std\":[").nth(1).and_then(|r| r.split([',', ']']).next()).unwrap().to_string();
    let h = String::from_utf8(bytes[19..19 + u64::from_le_bytes(bytes[11..19].try_into().unwrap()) as usize].to_vec());
    let x_std = first_x_std(&h.unwrap());
    for (edit, field) in [
        (("\"temperature\":1.0".to_string(), "\"temperature\":0.0".to_string()), "checkpoint temperature"),
        (("\"members\":1".to_string(), "\"members\":0".to_string()), "checkpoint members"),
        ((format!("\"x_std\":[{x_std}"), "\"x_std\":[0.0".to_string()), "checkpoint x_std"),
        (("\"high\":4.0".to_string(), "\"high\":-5.0".to_string()), "checkpoint params"),
    ] {
        let b = with_header(&bytes, |h| {
            assert!(h.contains(&edit.0), "{} not in the header", edit.0);
            h.replacen(&edit.0, &edit.1, 1)
        });
        assert!(err(&b).contains(field), "{}: {}", edit.1, err(&b));
    }
    let present = [true, true];
    let e = model.sample(&Obs { x: &x, present: Some(&present) }, 5, 0).unwrap_err();
    assert!(e.to_string().contains("expects 3"), "{e}");
    let e = model.log_prob(&obs, &[vec![0.0; 3]]).unwrap_err();
    assert!(e.to_string().contains("2 parameters"), "{e}");
    let _ = std::fs::remove_dir_all(&dir);
}

#[test]
#[cfg_attr(not(feature = "slow-tests"), ignore = "slow tier: `cargo test --features slow-tests`, run by .ci/run")]
fn bad_training_and_calibration_settings_are_named_errors() {
    let ds = linear_gaussian(100, 3);
    let s = TrainSettings { embedding: false, max_epochs: 1, ..Default::default() };
    let e = npe::train(&ds, &TrainSettings { lr: -1.0, ..s.clone() }, &mut |_| true).err().unwrap();
    assert!(matches!(e, npe::NpeError::Settings { field: "lr", .. }) && e.is_input(), "{e:?}");
    let e = npe::train(&ds, &TrainSettings { lr_anneal: f64::NAN, ..s.clone() }, &mut |_| true).err().unwrap();
    assert!(matches!(e, npe::NpeError::Settings { field: "lr-anneal", .. }), "{e:?}");
    let e = npe::train(&ds, &TrainSettings { val_fraction: 1.0, ..s.clone() }, &mut |_| true).err().unwrap();
    assert!(matches!(e, npe::NpeError::Settings { field: "val-fraction", .. }), "{e:?}");
    let e = npe::train(&linear_gaussian(10, 3), &s, &mut |_| true).err().unwrap();
    assert!(e.to_string().contains("too few to train"), "{e}");
    // One sample per row once underflowed the marginal interval's index.
    let rows = vec![(vec![0.0, 0.0], vec![0.0, 0.0, 0.0])];
    let e = npe::calibrate::calibrate(trained(), &rows, 1, 0).unwrap_err();
    assert!(matches!(e, npe::NpeError::Settings { field: "samples", .. }), "{e:?}");
    let rows = vec![(vec![0.0, 0.0], vec![0.0, 0.0, 0.0]), (vec![0.0], vec![0.0, 0.0, 0.0])];
    let e = npe::calibrate::calibrate(trained(), &rows, 10, 0).unwrap_err();
    assert!(matches!(e, npe::NpeError::Settings { field: "rows", .. }) && e.to_string().contains("row 1"), "{e:?}");
}

#[test]
fn ensembles_store_every_member_and_format_1_still_loads() {
    let ds = linear_gaussian(400, 2);
    // The logit map: every draw lands in the box, so blocks are not reshuffled by rejection.
    let s = TrainSettings {
        embedding: false,
        max_epochs: 3,
        seed: 5,
        ensemble: 2,
        theta_map: npe::ThetaMap::Logit,
        ..Default::default()
    };
    let model = npe::train(&ds, &s, &mut |_| true).unwrap();
    assert_eq!(model.header.members, 2);
    let single = npe::train(&ds, &TrainSettings { ensemble: 1, ..s.clone() }, &mut |_| true).unwrap();
    let x = [0.3, -0.2, 0.9];
    let obs = Obs { x: &x, present: None };
    let (a, b) = (model.sample(&obs, 300, 1).unwrap(), single.sample(&obs, 300, 1).unwrap());
    // Block 0 (rows 0..128) comes from member 0, which is the single model; block 1 from member 1.
    assert_eq!(a[..128], b[..128]);
    assert_ne!(a[128..256], b[128..256]);
    let dir = std::env::temp_dir().join(format!("otofit-ens-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    model.save(&dir.join("e.otofit")).unwrap();
    let loaded = Npe::load(&dir.join("e.otofit")).unwrap();
    assert_eq!(loaded.header.members, 2);
    assert_eq!(loaded.sample(&obs, 300, 1).unwrap(), a);
    let lp = loaded.log_prob(&obs, &a[..5]).unwrap();
    assert!(lp.iter().all(|v| v.is_finite()));
    // Format 1 (one record, no length prefix; files written before ensembles) keeps loading.
    single.save(&dir.join("s.otofit")).unwrap();
    let v2 = std::fs::read(dir.join("s.otofit")).unwrap();
    // Format 1: the same header with format 1, the one record without its length prefix.
    let mut v1 = with_header(&v2, |h| h.replace("\"format_version\":2", "\"format_version\":1"));
    let n1 = 19 + u64::from_le_bytes(v1[11..19].try_into().unwrap()) as usize;
    v1.drain(n1..n1 + 8);
    let old = Npe::from_bytes(&v1).unwrap();
    assert_eq!((old.header.format_version, old.header.members), (1, 1));
    assert_eq!(old.sample(&obs, 50, 1).unwrap(), single.sample(&obs, 50, 1).unwrap());
    let _ = std::fs::remove_dir_all(&dir);
}

#[test]
fn training_is_deterministic_for_a_seed() {
    let ds = linear_gaussian(400, 2);
    let s = TrainSettings { embedding: true, max_epochs: 3, seed: 11, ..Default::default() };
    let a = npe::train(&ds, &s, &mut |_| true).unwrap();
    let b = npe::train(&ds, &s, &mut |_| true).unwrap();
    assert_eq!(a.header.training.best_val_loss, b.header.training.best_val_loss);
    let x = [0.1, 0.2, 0.3];
    let obs = Obs { x: &x, present: None };
    assert_eq!(a.sample(&obs, 20, 1).unwrap(), b.sample(&obs, 20, 1).unwrap());
}

/// The cosine schedule starts at the full rate (epoch 1 is the constant rate's, bit for
/// bit) and then lowers it (epoch 2, at half the rate, is not).
#[test]
fn the_cosine_rate_starts_at_the_rate_and_then_falls() {
    let ds = linear_gaussian(400, 2);
    let losses = |lr_cosine| {
        let s =
            TrainSettings { embedding: false, max_epochs: 2, lr_plateau: 0, seed: 3, lr_cosine, ..Default::default() };
        let mut v = Vec::new();
        npe::train(&ds, &s, &mut |r| {
            v.push(r.val_loss);
            true
        })
        .unwrap();
        v
    };
    let (constant, cosine) = (losses(false), losses(true));
    assert_eq!(constant[0], cosine[0]);
    assert_ne!(constant[1], cosine[1]);
}

/// C2ST smoke test through the benchmark's table interface: a short training on the
/// Gaussian-mixture task scores well below the prior's own score against the reference
/// (a broken flow or sampler scores like the prior).
#[test]
fn c2st_smoke_gaussian_mixture() {
    use otofit::bench::{self, Task, c2st};
    let task = Task::GaussianMixture;
    let dir = std::env::temp_dir().join(format!("otofit-c2st-smoke-{}", std::process::id()));
    bench::write_table(task, 3000, 1, &dir).unwrap();
    let ds = Dataset::load(&dir).unwrap();
    let s = TrainSettings { embedding: false, max_epochs: 30, seed: 1, ..Default::default() };
    let model = npe::train(&ds, &s, &mut |_| true).unwrap();
    let x = bench::observation(task, 1);
    let mut rng = ChaCha8Rng::seed_from_u64(2);
    let reference = task.reference(&x, 1000, &mut rng);
    let prior: Vec<Vec<f64>> = (0..1000).map(|_| task.prior(&mut rng)).collect();
    let draws = model.sample(&Obs { x: &x, present: None }, 1000, 3).unwrap();
    let p = c2st::C2stParams { max_epochs: 100, ..Default::default() };
    let (flow, blind) = (c2st::c2st(&reference, &draws, &p), c2st::c2st(&reference, &prior, &p));
    eprintln!("C2ST: flow {flow:.3}, prior {blind:.3}");
    assert!(blind > 0.9, "the prior is told apart from the posterior: {blind}");
    assert!(flow < 0.7, "C2ST {flow}");
    let _ = std::fs::remove_dir_all(&dir);
}

/// `--hidden` and `--transforms` size the flow (conditioners, embedding, permutations),
/// and sizes it cannot build are refused by name before training.
#[test]
fn the_flow_is_sized_by_the_settings() {
    let ds = linear_gaussian(200, 4);
    let s = TrainSettings { max_epochs: 1, hidden: 16, transforms: 3, ..TrainSettings::default() };
    let m = npe::train(&ds, &s, &mut |_| true).unwrap();
    let f = &m.header.flow;
    assert_eq!((f.hidden, f.transforms, f.permutations.len()), (16, 3, 3));
    assert_eq!(f.embedding, vec![16, 16, 16]);
    for (field, bad) in [
        ("hidden", TrainSettings { hidden: 2, ..s.clone() }),
        ("transforms", TrainSettings { transforms: 0, ..s.clone() }),
    ] {
        match npe::train(&ds, &bad, &mut |_| true) {
            Err(npe::NpeError::Settings { field: got, .. }) => assert_eq!(got, field),
            Err(e) => panic!("{field}: another error: {e}"),
            Ok(_) => panic!("{field}: trained"),
        }
    }
}

/// At the patience limit the default recipe anneals instead of stopping: the training
/// goes on for max(patience, ½ × the epochs so far) epochs and ends there; without the
/// anneal it ends at the limit.
#[test]
fn the_anneal_runs_half_the_epochs_so_far_after_the_patience_limit() {
    let ds = linear_gaussian(400, 2);
    let run = |lr_anneal| {
        let s = TrainSettings { embedding: false, patience: 3, seed: 5, lr_anneal, ..Default::default() };
        let mut v = Vec::new();
        npe::train(&ds, &s, &mut |r| {
            v.push(r.val_loss);
            true
        })
        .unwrap();
        v
    };
    // The first epoch at which `patience` epochs have passed without a better loss.
    let limit = |v: &[f64]| {
        let (mut best, mut at) = (f64::INFINITY, 0);
        for (k, &l) in v.iter().enumerate() {
            if l < best {
                (best, at) = (l, k + 1);
            }
            if k + 1 - at >= 3 {
                return k + 1;
            }
        }
        panic!("the patience limit was never reached in {} epochs", v.len());
    };
    let (stopped, annealed) = (run(0.0), run(0.5));
    let t = limit(&stopped);
    assert_eq!(stopped.len(), t);
    assert_eq!(limit(&annealed), t, "the same epochs until the limit");
    assert_eq!(annealed.len(), t + 3usize.max(t.div_ceil(2)));
}

/// Calibration of the ears a clinic gives (some measures, from 226 Hz) is that of the flow
/// the file answers them with, not of its main flow: through the whole file and through
/// the band-masked flow for a device's band alone, the same ranks row for row.
#[test]
fn a_calibration_of_some_measures_on_part_of_the_band_is_the_answering_flows() {
    let m = Npe::load(&std::path::PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("models/default.otofit")).unwrap();
    let h = &m.header;
    let present = h.features_given(&["impedance", "absorbance", "umbo_velocity"], 226.0).unwrap();
    let mid = |p: &Param| match p.scale {
        Scale::Log10 => (p.low * p.high).sqrt(),
        _ => 0.5 * (p.low + p.high),
    };
    let mut rng = ChaCha8Rng::seed_from_u64(3);
    let rows: Vec<(Vec<f64>, Vec<f64>)> = (0..6)
        .map(|_| {
            let x = h.x_mean.iter().zip(&h.x_std).map(|(m, s)| m + 0.3 * s * rng.random_range(-1.0..1.0)).collect();
            (h.params.iter().map(mid).collect(), x)
        })
        .collect();
    let device = m.measure_sets().iter().find(|s| s.header.mask_bands && s.header.band_cut_max == 2).unwrap();
    let run = |npe: &Npe| npe::calibrate::calibrate_given(npe, &rows, 50, 4, Some(&present), &mut |_| {}).unwrap();
    let (whole_file, flow) = (run(&m), run(device));
    for (a, b) in whole_file.sbc_ranks.iter().zip(&flow.sbc_ranks) {
        assert_eq!(a.ranks, b.ranks, "{}", a.name);
    }
    assert_eq!(whole_file.coverage, flow.coverage);
    let wrong = vec![true; present.len() + 1];
    let e = npe::calibrate::calibrate_given(&m, &rows, 50, 4, Some(&wrong), &mut |_| {}).unwrap_err().to_string();
    assert!(e.contains("351 feature flags"), "{e}");
}

/// The shipped model holds, for wideband tympanometry with and without umbo velocity, a
/// flow trained without band masks and one trained with them: an ear of exactly those
/// measures over the whole band is answered by the first (the sharper), the same ear
/// without the grid's lowest points, as devices export from 226 Hz, by the second. For
/// WBT with umbo velocity it holds two band-masked flows: one trained on the cuts a
/// device makes (up to two points) answers ears from 226 Hz, the one trained on cuts of
/// up to a quarter of the grid those that stop shorter (from 300 Hz).
#[test]
fn the_shipped_model_answers_whole_band_ears_by_its_flows_without_band_masks() {
    let m = Npe::load(&std::path::PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("models/default.otofit")).unwrap();
    let h = &m.header;
    let (x, grid) = (h.x_mean.clone(), h.frequencies_hz.len());
    let first_from = |hz: f64| h.frequencies_hz.iter().position(|&f| f >= hz).unwrap();
    let (from_226, from_300) = (first_from(226.0), first_from(300.0));
    assert_eq!((from_226, from_300), (2, 6), "{:?}", h.frequencies_hz);
    let quarter = grid / 4;
    // (measures, grid points missing at the low end, band masks and cut limit wanted)
    let cases: [(&[&str], usize, (bool, usize)); 5] = [
        (&["impedance", "absorbance"], 0, (false, 0)),
        (&["impedance", "absorbance"], from_226, (true, quarter)),
        (&["impedance", "absorbance", "umbo_velocity"], 0, (false, 0)),
        (&["impedance", "absorbance", "umbo_velocity"], from_226, (true, 2)),
        (&["impedance", "absorbance", "umbo_velocity"], from_300, (true, quarter)),
    ];
    for (measures, missing, want_flow) in cases {
        let mut read: Vec<bool> = vec![false; x.len()];
        for g in h.groups.iter().filter(|g| measures.contains(&g.name.as_str())) {
            g.features.iter().for_each(|&i| read[i] = true);
        }
        assert!(read.iter().any(|&r| r), "{measures:?}: no such groups in {:?}", h.groups);
        let present: Vec<bool> = read.iter().enumerate().map(|(i, &r)| r && i % grid >= missing).collect();
        let a = m.answering(&Obs { x: &x, present: Some(&present) });
        let mut got = a.header.measures.clone();
        got.sort();
        let mut want: Vec<String> = measures.iter().map(|s| s.to_string()).collect();
        want.sort();
        let flow = (a.header.mask_bands, a.header.band_cut_max);
        assert_eq!((got, flow), (want, want_flow), "{measures:?}, {missing} points missing");
    }
}
