//! What a fixation changes, in otofit's ear and in the two published networks of the
//! cross-model suite: each condition against its own model's healthy ear, per measure at
//! a few frequencies, noise-free. A stapes fixation of the networks is read by otofit's
//! least squares as a stiff joint or a fixed malleus (docs/results/crossmodel.md); the
//! table shows which of otofit's changes each network's fixation resembles.
//!
//! Columns: the change of the stapes and umbo velocity magnitudes and of the ear-canal
//! impedance magnitude (dB), and of the absorbance (in absorbance units).
//!
//! `cargo run --example fixation_signatures` (a second).

use otofit::bench::crossmodel::run::ModelKind;
use otofit::bench::crossmodel::{Condition, Geometry, features, training_air};
use otofit::sim::batch::{Design, run_rows};
use otofit::sim::params::Effects;
use otofit::sim::{Model, ModelConfig, PARAMS};

/// Frequencies reported (the nearest grid point to each).
const AT_HZ: [f64; 5] = [250.0, 500.0, 1000.0, 2000.0, 4000.0];

/// Measure blocks of the 350 features: |v_stapes|, |Z|, absorbance, |v_umbo|.
const STAPES: usize = 0;
const IMPEDANCE: usize = 2;
const ABSORBANCE: usize = 4;
const UMBO: usize = 5;

/// One row of the table: `x` against `base`, at the grid points `at`.
fn row(name: &str, base: &[f64], x: &[f64], nf: usize, at: &[usize]) {
    let db = |m: usize, i: usize| 20.0 * (x[m * nf + i] - base[m * nf + i]);
    let cells = |f: &dyn Fn(usize) -> f64| at.iter().map(|&i| format!("{:+.1}", f(i))).collect::<Vec<_>>().join(" ");
    println!(
        "| {name} | {} | {} | {} | {} |",
        cells(&|i| db(STAPES, i)),
        cells(&|i| db(UMBO, i)),
        cells(&|i| db(IMPEDANCE, i)),
        at.iter()
            .map(|&i| format!("{:+.2}", x[ABSORBANCE * nf + i] - base[ABSORBANCE * nf + i]))
            .collect::<Vec<_>>()
            .join(" ")
    );
}

fn main() -> Result<(), Box<dyn std::error::Error>> {
    let model = Model::new(ModelConfig::default())?;
    let freqs = model.frequencies().to_vec();
    let nf = freqs.len();
    let at: Vec<usize> = AT_HZ
        .iter()
        .map(|&f| (0..nf).min_by(|&a, &b| (freqs[a] / f).ln().abs().total_cmp(&(freqs[b] / f).ln().abs())).unwrap())
        .collect();
    let hz: Vec<String> = at.iter().map(|&i| format!("{:.0}", freqs[i])).collect();
    println!("Changes at {} Hz, each against its own model's healthy ear.\n", hz.join(", "));
    println!("| change | stapes velocity, dB | umbo velocity, dB | impedance, dB | absorbance |");
    println!("|---|---|---|---|---|");

    // otofit's FE ear: the nominal row with one tissue parameter scaled, or the fixed
    // malleus effect added.
    let nominal: Vec<f64> = PARAMS.iter().map(|p| p.nominal).collect();
    let run = |design: &Design, rows: &[Vec<f64>]| -> Result<Vec<Vec<f64>>, Box<dyn std::error::Error>> {
        run_rows(&model, design, rows, 0, None).into_iter().map(|r| r.map_err(|e| e.to_string().into())).collect()
    };
    let base = run(&Design::default(), std::slice::from_ref(&nominal))?.remove(0);
    let param = |name: &str| PARAMS.iter().position(|p| p.name == name).unwrap();
    for (name, factor) in [("E_sal", 10.0), ("E_sal", 30.0), ("E_joints", 10.0), ("E_joints", 100.0)] {
        let mut r = nominal.clone();
        let k = param(name);
        r[k] = (r[k] * factor).min(PARAMS[k].high);
        let x = run(&Design::default(), &[r])?.remove(0);
        row(&format!("otofit: {name} ×{factor}"), &base, &x, nf, &at);
    }
    let effect = Effects::index("malleus_fixation").ok_or("no malleus_fixation effect")?;
    let design = Design { varied: vec![effect], ..Design::default() };
    for k in [1e5, 1e6] {
        let r: Vec<f64> = nominal.iter().copied().chain([k]).collect();
        let x = run(&design, &[r])?.remove(0);
        row(&format!("otofit: malleus fixed, {k:.0e} N/m"), &base, &x, nf, &at);
    }

    // The networks, each condition against its own healthy ear; stapes fixation at the
    // ends and the middle of the suite's 10–100× range.
    let (geometry, air) = (Geometry::nominal(), training_air());
    for m in [ModelKind::Kringlebotn1988, ModelKind::HuddeEngel1998] {
        let (healthy, _) = m.ear(Condition::Healthy, 0.0);
        let base = features(healthy.as_ref(), &geometry, &air, &freqs);
        let mut cases = vec![];
        for s in [0.0, 0.5, 1.0] {
            cases.push((Condition::StapesFixation, s));
        }
        cases.push((Condition::MalleusFixation, 0.0));
        for (c, s) in cases {
            let (ear, severity) = m.ear(c, s);
            let x = features(ear.as_ref(), &geometry, &air, &freqs);
            let what = match c {
                Condition::StapesFixation => format!("annular ligament ×{severity:.0}"),
                _ => "malleus fixed".to_string(),
            };
            row(&format!("{}: {what}", m.name()), &base, &x, nf, &at);
        }
    }
    Ok(())
}
