//! The effects that act inside the middle ear, against their limiting forms and their
//! clinical signatures (params::EFFECTS).

use faer::c64;
use otofit_sim::model::perforation_impedance;
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

#[test]
fn a_perforation_in_a_rigid_drum_is_the_hole_in_series_with_the_cavity() {
    // Drum and chain made rigid (moduli 10⁷× the prior's top): the only way in is the
    // hole, so the impedance at the drum is Z_p + ρc²/(jωV), the hole's plug pushing on
    // the cavity air. Leaving the cavity row out of the perforation, or the hole out of
    // the flow row, fails here.
    let model = Model::new(ModelConfig::default()).unwrap();
    let mut theta = Theta::nominal();
    for i in 0..5 {
        theta.0[i] *= 1e7;
    }
    let a = 1e-3;
    let fx = with("perforation", a);
    let v = theta.cavity_volume();
    let mut r = model.runner();
    for f in [200.0, 1000.0, 4000.0] {
        r.solve_with(&theta, &fx, f).unwrap();
        let z = r.solution()[model.dofs.p_drum]; // unit flow in
        let w = 2.0 * std::f64::consts::PI * f;
        let want = perforation_impedance(&model.air, a, w) + c64::new(0.0, -model.air.bulk_modulus() / (v * w));
        assert!((z - want).norm() < 1e-3 * want.norm(), "{f} Hz: {z} against {want}");
    }
}

/// Below the resonance of the hole's air plug with the cavity's compliance (517 Hz for
/// a 1 mm hole into the nominal 20 cm³), the cavity pressure follows the canal's through
/// the hole and the pressure difference that drives the drum collapses to about
/// |Z_p/(Z_p + Z_cav)| of it: 0.18 (−15 dB) at 200 Hz. Voss et al. 2001 measured losses
/// of this kind, growing as the frequency falls and the hole grows.
#[test]
fn a_perforation_lowers_transmission_below_its_resonance_with_the_cavity() {
    let model = Model::new(ModelConfig::default()).unwrap();
    let (u0, s0) = levels(&model, &Effects::default(), &[200.0]);
    let mut last = (u0, s0);
    for a in [0.5e-3, 1e-3, 2e-3] {
        let (u1, s1) = levels(&model, &with("perforation", a), &[200.0]);
        eprintln!("perforation {:.1} mm: 200 Hz umbo {:+.2} dB, stapes {:+.2} dB", a * 1e3, u1 - u0, s1 - s0);
        assert!(u1 < last.0 && s1 < last.1, "a larger hole must lose more: {a} m");
        last = (u1, s1);
    }
    assert!(
        last.0 - u0 < -6.0 && last.1 - s0 < -6.0,
        "2 mm hole: umbo {:+.2}, stapes {:+.2} dB",
        last.0 - u0,
        last.1 - s0
    );
}
