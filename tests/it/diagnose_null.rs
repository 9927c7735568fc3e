//! The diagnose workflow's null stored in the model: measured once per feature set,
//! kept through a save and a load, and used by a diagnosis only where it applies.

use otofit::discrepancy::Verdict;
use otofit::discrepancy::workflow::{NullSource, Settings, diagnose, groups_given, measure_null};
use otofit::npe::{DiagnoseNull, DiagnoseSubsetNull, Npe};
use otofit::sim::batch::{Design, Noise, default_noise_std, run_rows};
use otofit::sim::{Effects, Model, ModelConfig, Theta};

fn base() -> Npe {
    Npe::load(&std::path::PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("models/default.otofit")).unwrap()
}

/// The nominal ear with a probe leak the workflow names when its thresholds are the
/// measured ones (tests/it/discrepancy.rs), 1× noise.
fn leaky_ear(model: &Model) -> Vec<f64> {
    let mut fixed = Effects::default();
    fixed.set("probe_leak", 3e-4).unwrap();
    let noise = Noise { std: default_noise_std(model), scale: 1.0, seed: 5 };
    run_rows(model, &Design { fixed, varied: vec![] }, &[Theta::nominal().0.to_vec()], 0, Some(&noise))
        .remove(0)
        .unwrap()
}

fn probe_leak() -> usize {
    Effects::index("probe_leak").unwrap()
}

/// Few cases and one candidate: the point is which thresholds are used, not their size.
fn settings() -> Settings {
    Settings {
        candidates: vec![probe_leak()],
        draws: 100,
        null_cases: 5,
        extend: false,
        seed: 3,
        ..Settings::default()
    }
}

/// A stored null whose thresholds no ear can pass: a diagnosis that uses it says
/// `no_discrepancy` even for the leaky ear.
fn unreachable_null(groups: Vec<String>, candidates: Vec<String>) -> DiagnoseNull {
    DiagnoseNull {
        quantile: otofit::discrepancy::workflow::ALARM_QUANTILE,
        cases: 7,
        draws: 100,
        candidates,
        subsets: vec![DiagnoseSubsetNull { groups, base_reduced_chi2: 1e12, best_drop: 1e12 }],
        fit_version: otofit::discrepancy::CANDIDATE_FIT_VERSION,
    }
}

fn all_groups(npe: &Npe) -> Vec<String> {
    let mut g: Vec<String> = npe.header.groups.iter().map(|g| g.name.clone()).collect();
    g.sort();
    g
}

/// Runs the workflow and reports whether it measured a null (its progress says so).
fn run(model: &Model, npe: &Npe, x: &[f64], s: &Settings) -> (otofit::discrepancy::workflow::Report, bool) {
    let mut measured = false;
    let r = diagnose(model, npe, x, s, &mut |m| measured |= m.starts_with("null")).unwrap();
    (r, measured)
}

#[test]
fn feature_groups_given_whole_are_named_and_partial_ones_are_not() {
    let npe = base();
    let f = npe.header.feature_names.len();
    assert_eq!(groups_given(&npe, &vec![true; f]), Some(all_groups(&npe)));
    let group = |name: &str| npe.header.groups.iter().find(|g| g.name == name).unwrap().features.clone();
    let mut wbt = vec![false; f];
    group("impedance").into_iter().chain(group("absorbance")).for_each(|i| wbt[i] = true);
    assert_eq!(groups_given(&npe, &wbt), Some(vec!["absorbance".to_string(), "impedance".to_string()]));
    // One impedance frequency missing: a band-limited ear has no stored null.
    wbt[group("impedance")[0]] = false;
    assert_eq!(groups_given(&npe, &wbt), None);
}

#[test]
fn a_diagnosis_uses_the_models_null_only_where_it_applies() {
    let model = Model::new(ModelConfig::default()).unwrap();
    let x = leaky_ear(&model);
    let mut npe = base();
    let names = vec!["probe_leak".to_string()];
    npe.header.diagnose_null = Some(unreachable_null(all_groups(&npe), names.clone()));

    // Every measure given, the candidate covered: the stored thresholds, no null run.
    let (r, measured) = run(&model, &npe, &x, &settings());
    assert_eq!((r.null, measured), (NullSource::Model { cases: 7 }, false));
    assert_eq!(r.verdict, Verdict::NoDiscrepancy, "the stored thresholds were not the ones used");

    // Asked to measure: the ear's own null, which alarms on the leak.
    let (r, measured) = run(&model, &npe, &x, &Settings { measure_null: true, ..settings() });
    assert_eq!((r.null, measured), (NullSource::Measured { cases: 5 }, true));
    assert_ne!(r.verdict, Verdict::NoDiscrepancy);

    // A candidate the stored null did not rank: measured.
    let s = Settings { candidates: vec![probe_leak(), Effects::index("effusion").unwrap()], ..settings() };
    assert_eq!(run(&model, &npe, &x, &s).0.null, NullSource::Measured { cases: 5 });

    // Other draws per case: a different statistic, measured.
    assert_eq!(run(&model, &npe, &x, &Settings { draws: 60, ..settings() }).0.null, NullSource::Measured { cases: 5 });

    // Thresholds of another candidate fit, or of one not recorded: measured.
    for v in [0, otofit::discrepancy::CANDIDATE_FIT_VERSION - 1] {
        let mut old = base();
        old.header.diagnose_null =
            Some(DiagnoseNull { fit_version: v, ..unreachable_null(all_groups(&npe), names.clone()) });
        assert_eq!(run(&model, &old, &x, &settings()).0.null, NullSource::Measured { cases: 5 }, "fit version {v}");
    }

    // WBT alone while the model stores only the full set: measured.
    let mut wbt = x.clone();
    for g in npe.header.groups.iter().filter(|g| g.name == "stapes_velocity" || g.name == "umbo_velocity") {
        g.features.iter().for_each(|&i| wbt[i] = f64::NAN);
    }
    assert_eq!(run(&model, &npe, &wbt, &settings()).0.null, NullSource::Measured { cases: 5 });
}

#[test]
fn a_measured_null_is_stored_per_feature_set_and_survives_a_save() {
    let model = Model::new(ModelConfig::default()).unwrap();
    let mut npe = base();
    let f = npe.header.feature_names.len();
    let mut wbt = vec![false; f];
    for g in npe.header.groups.iter().filter(|g| g.name == "impedance" || g.name == "absorbance") {
        g.features.iter().for_each(|&i| wbt[i] = true);
    }
    let s = settings();
    let noise = Noise { std: npe.header.noise_std.clone(), scale: 1.0, seed: s.seed };
    let null = measure_null(&model, &npe, &noise, &[vec![true; f], wbt], &s, &mut |_, _| {}).unwrap();
    assert_eq!(null.cases, 5);
    assert_eq!(null.candidates, ["probe_leak"]);
    let groups: Vec<_> = null.subsets.iter().map(|t| t.groups.join("+")).collect();
    assert_eq!(groups, ["absorbance+impedance+stapes_velocity+umbo_velocity", "absorbance+impedance"]);
    for t in &null.subsets {
        assert!(t.base_reduced_chi2.is_finite() && t.base_reduced_chi2 > 0.0, "{t:?}");
        assert!(t.best_drop.is_finite(), "{t:?}");
    }
    // A partial group cannot be stored.
    let mut partial = vec![false; f];
    partial[0] = true;
    assert!(measure_null(&model, &npe, &noise, &[partial], &s, &mut |_, _| {}).is_err());

    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("m.otofit");
    npe.header.diagnose_null = Some(null.clone());
    npe.save(&path).unwrap();
    let loaded = Npe::load(&path).unwrap();
    let kept = loaded.header.diagnose_null.as_ref().unwrap();
    assert_eq!(kept.subsets[1].best_drop, null.subsets[1].best_drop);

    // The stored thresholds are the ones a later diagnosis of the same features uses.
    let x = leaky_ear(&model);
    let (r, measured) = run(&model, &loaded, &x, &s);
    assert_eq!((r.null, measured), (NullSource::Model { cases: 5 }, false));
    assert_eq!(r.thresholds.best_drop, null.subsets[0].best_drop);
}

/// A damaged stored null is refused at load, naming the field.
#[test]
fn a_stored_null_with_a_negative_threshold_is_refused_at_load() {
    let mut npe = base();
    let mut null = unreachable_null(all_groups(&npe), vec!["probe_leak".into()]);
    null.subsets[0].base_reduced_chi2 = -1.0;
    npe.header.diagnose_null = Some(null);
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("m.otofit");
    npe.save(&path).unwrap();
    let Err(e) = Npe::load(&path) else { panic!("a negative threshold was loaded") };
    let e = anyhow::Error::from(e);
    assert!(format!("{e:#}").contains("diagnose_null"), "{e:#}");
}
