//! Identifiability of the seven tissue parameters at the typical ear: the Cramér–Rao
//! bound from the Fisher information of the features under the test–retest noise model,
//! with all fourteen parameters free (so the nuisances take their share), for all seven
//! measures and for wideband tympanometry alone (impedance and absorbance). Parameters
//! on a log scale are counted in decades. The numbers are in docs/results/simulator.md.

use faer::linalg::solvers::Solve;
use otofit_sim::output::{GROUPS, MEASURES, features, noise_std};
use otofit_sim::params::Scale;
use otofit_sim::{Effects, Model, ModelConfig, N_PARAMS, PARAMS, Theta};

/// Features of `theta` with parameter `i` moved by `step` on its sampling scale.
fn moved(model: &Model, theta: &Theta, i: usize, step: f64) -> Vec<f64> {
    let mut t = *theta;
    t.0[i] = match PARAMS[i].scale {
        Scale::Log10 => t.0[i] * 10f64.powf(step),
        Scale::Linear => t.0[i] + step * (PARAMS[i].high - PARAMS[i].low),
    };
    features(&model.runner().run(&t, &Effects::default()).unwrap())
}

/// ∂x/∂θ_i by central differences (a hundredth of a decade, or of the box), forward at
/// the lower end of a linear box (an elastic drum, a massless cochlea: nominal 0).
fn jacobian(model: &Model, theta: &Theta) -> Vec<Vec<f64>> {
    let h = 0.01;
    (0..N_PARAMS)
        .map(|i| {
            let at_floor = PARAMS[i].scale == Scale::Linear && theta.0[i] <= PARAMS[i].low;
            let (p, m, span) = if at_floor {
                (moved(model, theta, i, h), moved(model, theta, i, 0.0), h)
            } else {
                (moved(model, theta, i, h), moved(model, theta, i, -h), 2.0 * h)
            };
            p.iter().zip(&m).map(|(a, b)| (a - b) / span).collect()
        })
        .collect()
}

/// √diag(F⁻¹) for the features whose measure is in `measures`, over the parameters those
/// features see at all (`None`: a parameter that acts only on measures left out, such as
/// the microphone distance for wideband tympanometry).
fn bounds(jac: &[Vec<f64>], std: &[f64], keep: &[bool]) -> Vec<Option<f64>> {
    let info = |a: usize, b: usize| -> f64 {
        (0..std.len()).filter(|&k| keep[k]).map(|k| jac[a][k] * jac[b][k] / (std[k] * std[k])).sum()
    };
    let largest = (0..jac.len()).map(|i| info(i, i)).fold(0.0, f64::max);
    let seen: Vec<usize> = (0..jac.len()).filter(|&i| info(i, i) > 1e-12 * largest).collect();
    let n = seen.len();
    let f = faer::Mat::<f64>::from_fn(n, n, |a, b| info(seen[a], seen[b]));
    let inv = f.partial_piv_lu().solve(faer::Mat::<f64>::identity(n, n));
    let mut out = vec![None; jac.len()];
    for (a, &i) in seen.iter().enumerate() {
        out[i] = Some(inv[(a, a)].max(0.0).sqrt());
    }
    out
}

#[test]
#[ignore = "a measurement for the docs; --ignored --nocapture"]
fn measure_cramer_rao_bounds_at_the_typical_ear() {
    let model = Model::new(ModelConfig::default()).unwrap();
    let theta = Theta::nominal();
    let jac = jacobian(&model, &theta);
    let n_f = model.frequencies().len();
    let std = noise_std(model.frequencies());
    let in_groups = |groups: &[&str]| -> Vec<bool> {
        MEASURES
            .iter()
            .flat_map(|m| {
                let on = GROUPS.iter().any(|(g, ms)| groups.contains(g) && ms.contains(&m.name));
                std::iter::repeat_n(on, n_f)
            })
            .collect()
    };
    let all = bounds(&jac, &std, &in_groups(&["stapes_velocity", "impedance", "absorbance", "umbo_velocity"]));
    let wbt = bounds(&jac, &std, &in_groups(&["impedance", "absorbance"]));
    let show = |v: Option<f64>, unit: &str| v.map_or("not seen".to_string(), |v| format!("{v:.3}{unit}"));
    println!("| parameter | CRB, all measures | CRB, WBT only |");
    println!("|---|---|---|");
    for i in 0..N_PARAMS {
        let unit = if PARAMS[i].scale == Scale::Log10 { " dec" } else { " of the box" };
        println!("| {} | {} | {} |", PARAMS[i].name, show(all[i], unit), show(wbt[i], unit));
    }
}
