//! The effects that act inside the middle ear, against their limiting forms and their
//! clinical signatures (params::EFFECTS).

use otofit_sim::output::features;
use otofit_sim::{Effects, Model, ModelConfig, Theta};

fn with(name: &str, value: f64) -> Effects {
    let mut fx = Effects::default();
    fx.0[Effects::index(name).unwrap()] = value;
    fx
}

/// Mean 20·log10 |V/P| of umbo and stapes over `band`.
fn levels(model: &Model, fx: &Effects, band: &[f64]) -> (f64, f64) {
    let mut r = model.runner();
    let (mut vu, mut vs) = (0.0, 0.0);
    for &f in band {
        let resp = r.response_at(&Theta::nominal(), fx, f).unwrap();
        vu += 20.0 * resp.vu_over_p.norm().log10() / band.len() as f64;
        vs += 20.0 * resp.vst_over_p.norm().log10() / band.len() as f64;
    }
    (vu, vs)
}

#[test]
fn a_third_window_of_vanishing_admittance_is_no_third_window() {
    // The shunt is in parallel with the cochlear load: as its mass grows without bound it
    // carries no flow and the ear is the ear without it (in series it would block the
    // stapes instead).
    let model = Model::new(ModelConfig::default()).unwrap();
    let run = |fx: &Effects| features(&model.runner().run(&Theta::nominal(), fx).unwrap());
    let (off, closed) = (run(&Effects::default()), run(&with("third_window", 1e16)));
    let worst = off.iter().zip(&closed).map(|(a, b)| (a - b).abs()).fold(0.0, f64::max);
    assert!(worst < 1e-4, "largest feature change {worst:e}");
    let open = run(&with("third_window", 1e6));
    let moved = off.iter().zip(&open).map(|(a, b)| (a - b).abs()).fold(0.0, f64::max);
    assert!(moved > 0.05, "an open third window changes the ear: {moved:e}");
}

#[test]
fn a_third_window_raises_low_frequency_stapes_velocity_more_than_high() {
    let model = Model::new(ModelConfig::default()).unwrap();
    let low = [200.0, 300.0, 400.0, 500.0];
    let high = [4000.0, 5000.0, 6300.0, 8000.0];
    let fx = with("third_window", 1e6);
    let (u0, s0) = levels(&model, &Effects::default(), &low);
    let (u1, s1) = levels(&model, &fx, &low);
    let (_, h0) = levels(&model, &Effects::default(), &high);
    let (_, h1) = levels(&model, &fx, &high);
    eprintln!(
        "third window 1e6 kg/m⁴: 200–500 Hz umbo {:+.2} dB, stapes {:+.2} dB; 4–8 kHz stapes {:+.2} dB",
        u1 - u0,
        s1 - s0,
        h1 - h0
    );
    assert!(s1 - s0 > 0.5, "low-frequency stapes {:+.2} dB", s1 - s0);
    assert!((h1 - h0).abs() < s1 - s0, "high {:+.2} dB against low {:+.2} dB", h1 - h0, s1 - s0);
}
