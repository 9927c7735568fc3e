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

/// The largest absolute difference between two feature vectors.
fn worst(a: &[f64], b: &[f64]) -> f64 {
    a.iter().zip(b).map(|(x, y)| (x - y).abs()).fold(0.0, f64::max)
}

fn features_of(model: &Model, theta: &Theta, fx: &Effects) -> Vec<f64> {
    features(&model.runner().run(theta, fx).unwrap())
}

/// Mean absorbance over `band`.
fn absorbance(model: &Model, fx: &Effects, band: &[f64]) -> f64 {
    let mut r = model.runner();
    band.iter().map(|&f| r.response_at(&Theta::nominal(), fx, f).unwrap().absorbance()).sum::<f64>() / band.len() as f64
}

/// Prints an effect's signature on the nominal ear: stapes and umbo level changes and the
/// absorbance change in three bands.
fn signature(model: &Model, fx: &Effects, label: &str) -> [(f64, f64, f64); 3] {
    let bands: [&[f64]; 3] =
        [&[200.0, 300.0, 400.0, 500.0], &[1000.0, 1500.0, 2000.0], &[4000.0, 5000.0, 6300.0, 8000.0]];
    let off = Effects::default();
    let out = bands.map(|b| {
        let ((u0, s0), (u1, s1)) = (levels(model, &off, b), levels(model, fx, b));
        (s1 - s0, u1 - u0, absorbance(model, fx, b) - absorbance(model, &off, b))
    });
    eprintln!(
        "{label}: stapes / umbo dB, ΔA at 0.2–0.5 kHz {:+.1} / {:+.1}, {:+.3}; 1–2 kHz {:+.1} / {:+.1}, {:+.3}; 4–8 kHz {:+.1} / {:+.1}, {:+.3}",
        out[0].0, out[0].1, out[0].2, out[1].0, out[1].1, out[1].2, out[2].0, out[2].1, out[2].2
    );
    out
}

/// Drum and chain made rigid (moduli 10⁷× the prior's top, as in the perforation test): a
/// hole of radius `a` is the only way in, so the impedance at the drum is the hole's plug
/// in series with whatever lies behind it.
fn rigid_with_hole(model: &Model, fx: &Effects, f: f64) -> c64 {
    let mut theta = Theta::nominal();
    for i in 0..5 {
        theta.0[i] *= 1e7;
    }
    let mut r = model.runner();
    r.solve_with(&theta, fx, f).unwrap();
    r.solution()[model.dofs.p_drum]
}

/// Asserts, at three frequencies, that the impedance behind a rigid drum with a hole of
/// radius `a` is the hole's plug in series with `behind(ω)`.
fn assert_hole_in_series_with(model: &Model, fx: &Effects, a: f64, behind: impl Fn(f64) -> c64) {
    for f in [200.0, 1500.0, 4000.0] {
        let w = 2.0 * std::f64::consts::PI * f;
        let want = perforation_impedance(&model.air, a, w) + behind(w);
        let z = rigid_with_hole(model, fx, f);
        assert!((z - want).norm() < 1e-3 * want.norm(), "{f} Hz: {z} against {want}");
    }
}

#[test]
fn an_effusion_is_a_fluid_mass_in_series_with_the_air_left() {
    // Behind a rigid drum with a 1 mm hole: Z = Z_p + jωM_f + ρc²/(jωV(1 − φ)), the fluid's
    // mass ρ·d·φ/A (d = 2 mm, A = 59.7 mm²) before the air that is left.
    let model = Model::new(ModelConfig::default()).unwrap();
    let (a, fill) = (1e-3, 0.6);
    let mut fx = with("perforation", a);
    fx.set("effusion", fill).unwrap();
    let v = Theta::nominal().cavity_volume() * (1.0 - fill);
    let m_f = 1000.0 * 2e-3 * fill / (std::f64::consts::PI * 4.0e-3 * 4.75e-3);
    assert_hole_in_series_with(&model, &fx, a, |w| c64::new(0.0, w * m_f - model.air.bulk_modulus() / (v * w)));
}

#[test]
fn an_effusion_lowers_velocities_most_at_high_frequency_and_vanishes_when_drained() {
    let model = Model::new(ModelConfig::default()).unwrap();
    let off = features_of(&model, &Theta::nominal(), &Effects::default());
    let trace = features_of(&model, &Theta::nominal(), &with("effusion", 1e-9));
    assert!(worst(&off, &trace) < 1e-6, "a drained ear: {:e}", worst(&off, &trace));
    let mut last = 0.0;
    for fill in [0.3, 0.6, 0.95] {
        let s = signature(&model, &with("effusion", fill), &format!("effusion {fill}"));
        // Ravicz et al. 2004: the loss grows with the fill, more at high frequency.
        assert!(s[2].1 < last && s[2].1 < s[0].1, "umbo 4–8 kHz {:+.1} dB, 0.2–0.5 kHz {:+.1} dB", s[2].1, s[0].1);
        last = s[2].1;
    }
    assert!(last < -10.0, "a nearly full ear loses {last:+.1} dB of umbo velocity at 4–8 kHz");
}

#[test]
fn a_static_pressure_without_tissue_loss_is_a_stiffer_drum_and_suspension() {
    // With every tissue loss off (drum loss factor 0, β → 0) the pre-stress stiffness
    // (2ΔP/TW)² is indistinguishable from moduli scaled by 1 + (2ΔP/TW)²; at half the
    // tympanometric width (37.5 daPa) the factor is exactly 2.
    let mut config = ModelConfig::default();
    config.geometry.tm_loss = otofit_sim::DrumLoss::LossFactor(0.0);
    let model = Model::new(config).unwrap();
    let mut theta = Theta::nominal();
    theta.0[5] = 1e-20; // damping_beta
    let mut stiff = theta;
    for i in [0, 1, 3] {
        stiff.0[i] *= 2.0; // E_eardrum, E_ligaments, E_sal
    }
    let mut fx = Effects::default();
    fx.0[Effects::index("pressure").unwrap()] = -375.0;
    let (a, b) = (features_of(&model, &theta, &fx), features_of(&model, &stiff, &Effects::default()));
    assert!(worst(&a, &b) < 1e-9, "{:e}", worst(&a, &b));
}

#[test]
fn a_static_pressure_lowers_low_frequency_absorbance_and_vanishes_at_zero() {
    let model = Model::new(ModelConfig::default()).unwrap();
    let off = features_of(&model, &Theta::nominal(), &Effects::default());
    let mut fx = Effects::default();
    fx.0[Effects::index("pressure").unwrap()] = -1e-3;
    assert!(worst(&off, &features_of(&model, &Theta::nominal(), &fx)) < 1e-6);
    for p in [-1000.0, -2000.0, -3000.0] {
        let s = signature(&model, &with("pressure", p), &format!("pressure {p} Pa"));
        // Voss et al. 2012: reflectance rises (absorbance falls) below 1–2 kHz.
        assert!(s[0].2 < 0.0 && s[0].0 < -3.0, "{p} Pa: 0.2–0.5 kHz ΔA {:+.3}, stapes {:+.1} dB", s[0].2, s[0].0);
    }
}

#[test]
fn a_mastoid_is_the_aditus_branch_in_parallel_with_the_tympanic_air() {
    // Behind a rigid drum with a hole: Z = Z_p + 1/(jωC_t + Y_m), C_t the tympanic air
    // (1 − f)V/ρc², Y_m the aditus (880 kg/m⁴, 1.7e6 Pa·s/m³) before the mastoid cells
    // fV/ρc² with their resonance at 3.5 kHz, Q 0.4: Hudde & Engel's network, written out
    // here apart from the code.
    let model = Model::new(ModelConfig::default()).unwrap();
    let (a, behind) = (1e-3, 0.9);
    let mut fx = with("perforation", a);
    fx.set("mastoid", behind).unwrap();
    let (v, k) = (Theta::nominal().cavity_volume(), model.air.bulk_modulus());
    assert_hole_in_series_with(&model, &fx, a, |w| {
        let jw = c64::new(0.0, w);
        let x = w / (2.0 * std::f64::consts::PI * 3500.0);
        let cells = jw * (behind * v / k) / c64::new(1.0 - x * x, x / 0.4);
        let branch = 1.0 / (c64::new(1.7e6, w * 880.0) + 1.0 / cells);
        1.0 / (jw * ((1.0 - behind) * v / k) + branch)
    });
}

#[test]
fn a_mastoid_makes_a_notch_at_the_aditus_antiresonance_and_absorbs_power() {
    let model = Model::new(ModelConfig::default()).unwrap();
    let off = features_of(&model, &Theta::nominal(), &Effects::default());
    assert!(worst(&off, &features_of(&model, &Theta::nominal(), &with("mastoid", 1e-9))) < 1e-6);
    // The tympanic air (2 cm³ of 20) against the aditus and the 18 cm³ behind it: the
    // lossless antiresonance lies at √((C_t + C_m)/(M C_t C_m))/2π = 1.49 kHz.
    let fx = with("mastoid", 0.9);
    signature(&model, &fx, "mastoid 0.9");
    let mut r = model.runner();
    let (mut deepest, mut at) = (0.0, 0.0);
    for i in 0..=60 {
        let f = 500.0 * (4000.0f64 / 500.0).powf(i as f64 / 60.0);
        let base = r.response_at(&Theta::nominal(), &Effects::default(), f).unwrap();
        let with = r.response_at(&Theta::nominal(), &fx, f).unwrap();
        let p = r.power_balance(&Theta::nominal(), f);
        assert!(p.cavity >= 0.0 && (p.into_drum - p.mechanical).abs() < 1e-9 * p.probe, "{f} Hz: {p:?}");
        let d = 20.0 * (with.vu_over_p.norm() / base.vu_over_p.norm()).log10();
        if d < deepest {
            (deepest, at) = (d, f);
        }
    }
    eprintln!("mastoid 0.9: deepest umbo notch {deepest:+.1} dB at {at:.0} Hz");
    assert!((1000.0..2200.0).contains(&at) && deepest < -3.0, "notch {deepest:+.1} dB at {at:.0} Hz");
}

#[test]
fn an_interrupted_incudostapedial_joint_is_that_joint_alone_made_softer() {
    // Scaling E_joints by s while the incudomallear joint's geometry grows by 1/s leaves
    // that joint as it was and scales only the incudostapedial one: the effect's ear.
    let s = 1e-3;
    let model = Model::new(ModelConfig::default()).unwrap();
    let mut config = ModelConfig::default();
    for g in [&mut config.geometry.g_imj, &mut config.geometry.g_imj_rot, &mut config.geometry.g_imj_lateral] {
        *g /= s;
    }
    let scaled = Model::new(config).unwrap();
    let mut theta = Theta::nominal();
    theta.0[4] *= s;
    let a = features_of(&model, &Theta::nominal(), &with("isj_discontinuity", s));
    let b = features_of(&scaled, &theta, &Effects::default());
    assert!(worst(&a, &b) < 1e-9, "{:e}", worst(&a, &b));
}

#[test]
fn an_interrupted_incudostapedial_joint_loses_stapes_velocity_across_the_band() {
    let model = Model::new(ModelConfig::default()).unwrap();
    let s = signature(&model, &with("isj_discontinuity", 1e-6), "isj_discontinuity 1e-6");
    // Nakajima et al. 2012: stapes velocity 20–40 dB down across the band; the unloaded
    // drum moves more at low frequency.
    assert!(s.iter().all(|b| b.0 < -15.0), "stapes {:+.1} / {:+.1} / {:+.1} dB", s[0].0, s[1].0, s[2].0);
    assert!(s[0].1 > 0.0, "umbo 0.2–0.5 kHz {:+.1} dB", s[0].1);
}

/// The air spaces never give power back, and the balance closes, with the mastoid at
/// both ends of its range, alone and beside fluid and a perforation, at the prior's
/// corners and centre (the random-draw passivity test of tests/it/sim.rs sums this term
/// into the middle-ear balance but does not check its sign).
#[test]
fn the_air_spaces_absorb_power_and_never_return_it() {
    use otofit_sim::PARAMS;
    let model = Model::new(ModelConfig::default()).unwrap();
    let mut r = model.runner();
    let mut cases = Vec::new();
    for behind in [0.5, 0.97] {
        let m = with("mastoid", behind);
        let mut wet = m;
        wet.set("effusion", 0.5).unwrap();
        let mut holed = wet;
        holed.set("perforation", 1e-3).unwrap();
        cases.extend([m, wet, holed]);
    }
    for u in [0.0, 0.5, 1.0] {
        let theta = Theta(std::array::from_fn(|i| PARAMS[i].from_unit(u)));
        for fx in &cases {
            for &f in model.frequencies() {
                r.solve_with(&theta, fx, f).unwrap();
                let p = r.power_balance(&theta, f);
                assert!(p.cavity >= -1e-12 * p.probe, "{f} Hz, {fx:?}: {p:?}");
                assert!((p.into_drum - p.mechanical).abs() < 1e-6 * p.probe, "{f} Hz, {fx:?}: {p:?}");
            }
        }
    }
}

/// The malleus head as the fixation holds it, written out apart from the code: its top
/// 8.0 − 5.5 = 2.5 mm above the rotation axis (the malleus' length from head to umbo,
/// Binvignat et al. 2015, less the chain's umbo arm), 1.9 mm tall (Vedpathak et al. 2020).
const HEAD_TOP: f64 = 8.0e-3 - 5.5e-3;
const HEAD_HEIGHT: f64 = 1.9e-3;

fn fixed_malleus(k: f64) -> Effects {
    with("malleus_fixation", k)
}

#[test]
fn a_malleus_fixation_of_vanishing_stiffness_is_no_fixation() {
    let model = Model::new(ModelConfig::default()).unwrap();
    let off = features_of(&model, &Theta::nominal(), &Effects::default());
    let slack = features_of(&model, &Theta::nominal(), &fixed_malleus(1e-6));
    assert!(worst(&off, &slack) < 1e-6, "a spring of 1 µN/m: {:e}", worst(&off, &slack));
    let mild = features_of(&model, &Theta::nominal(), &fixed_malleus(1e3));
    assert!(worst(&off, &mild) > 1e-3, "the range's low end changes the ear: {:e}", worst(&off, &mild));
}

/// A stiffness k spread evenly over the head, from its top down 1.9 mm, is a spring k at the
/// head's centre and a torsion spring k·h²/12 (the second moment of the span about its
/// centre). Written with the chain's own connectors: the tensor tympani tendon moved to the
/// head's centre with stiffness k, and k·h²/12 added to the anterior mallear ligament's
/// torsion, on an ear without tissue loss (the fixation is lossless) and without the
/// tendon in the effect's ear. A fixation held at one point (no torsion), at the head's
/// top, or with the torsion of a span twice as tall fails here.
#[test]
fn a_malleus_fixation_is_a_stiffness_spread_over_the_head() {
    let k = 1e5;
    let mut theta = Theta::nominal();
    theta.0[5] = 1e-20; // damping_beta
    let mut config = ModelConfig::default();
    config.geometry.g_ttt = 0.0;
    let fixed = Model::new(config.clone()).unwrap();
    config.geometry.g_ttt = k / theta.e_tendons();
    config.geometry.arm_ttt = -(HEAD_TOP - HEAD_HEIGHT / 2.0);
    config.geometry.g_aml_rot += k * HEAD_HEIGHT * HEAD_HEIGHT / 12.0 / theta.e_ligaments();
    let springs = Model::new(config).unwrap();
    let (a, b) = (features_of(&fixed, &theta, &fixed_malleus(k)), features_of(&springs, &theta, &Effects::default()));
    assert!(worst(&a, &b) < 1e-9, "{:e}", worst(&a, &b));
}

/// As k → ∞ the malleus is clamped: held at a point and in torsion, both its unknowns fall
/// as 1/k (the fixation's force k·u converges to the clamped ear's reaction), and the
/// stapes, driven through the malleus, stops with it. A point fixation would leave the
/// malleus turning about the head (its umbo would not fall as 1/k).
#[test]
fn a_stiff_malleus_fixation_clamps_the_malleus() {
    let model = Model::new(ModelConfig::default()).unwrap();
    let mut r = model.runner();
    let mut solve = |k: f64, f: f64| {
        r.solve_with(&Theta::nominal(), &fixed_malleus(k), f).unwrap();
        let x = r.solution();
        (x[model.dofs.umbo], x[model.dofs.theta_m], x[model.dofs.x_stapes])
    };
    for f in [250.0, 1000.0, 4000.0] {
        let (u0, _, s0) = solve(0.0, f);
        let (u1, t1, s1) = solve(1e10, f);
        let (u2, t2, s2) = solve(1e11, f);
        for (name, a, b) in [("umbo", u1, u2), ("rotation", t1, t2), ("stapes", s1, s2)] {
            assert!((a - b * 10.0).norm() < 1e-3 * a.norm(), "{f} Hz: {name} {a} at 1e10, {b} at 1e11 N/m");
        }
        let db = |a: c64, b: c64| 20.0 * (a.norm() / b.norm()).log10();
        eprintln!("{f} Hz, k 1e10 N/m: umbo {:+.1} dB, stapes {:+.1} dB", db(u1, u0), db(s1, s0));
        assert!(
            db(u1, u0) < -80.0 && db(s1, s0) < -80.0,
            "{f} Hz: umbo {:+.1}, stapes {:+.1} dB",
            db(u1, u0),
            db(s1, s0)
        );
    }
}

/// Umbo and stapes level changes (dB) and the absorbance change at `f` of (`theta`, `fx`)
/// against the nominal ear without effects.
fn change_at(model: &Model, theta: &Theta, fx: &Effects, f: f64) -> (f64, f64, f64) {
    let mut r = model.runner();
    let base = r.response_at(&Theta::nominal(), &Effects::default(), f).unwrap();
    let with = r.response_at(theta, fx, f).unwrap();
    let db = |a: c64, b: c64| 20.0 * (a.norm() / b.norm()).log10();
    (db(with.vu_over_p, base.vu_over_p), db(with.vst_over_p, base.vst_over_p), with.absorbance() - base.absorbance())
}

/// Umbo and stapes loss over 250–1000 Hz, mean dB (positive: a loss).
fn low_frequency_loss(model: &Model, theta: &Theta, fx: &Effects) -> (f64, f64) {
    let band = [250.0, 500.0, 1000.0];
    let (mut u, mut s) = (0.0, 0.0);
    for f in band {
        let (du, ds, _) = change_at(model, theta, fx, f);
        (u, s) = (u - du / band.len() as f64, s - ds / band.len() as f64);
    }
    (u, s)
}

/// The umbo velocity tells a fixed malleus from a fixed stapes (Nakajima et al. 2005, Hear
/// Res 204:60 and Laryngoscope 115:147; Rosowski et al. 2003, Otol Neurotol 24:165): a
/// malleus fixation lowers umbo and stapes velocity alike, a stapes fixation lowers the
/// stapes' and leaves the umbo's nearly as it was. Here a bony-bar fixation (1e6 N/m)
/// against an annular ligament 10× stiffer, at 250–1000 Hz.
#[test]
fn umbo_velocity_separates_a_fixed_malleus_from_a_fixed_stapes() {
    let model = Model::new(ModelConfig::default()).unwrap();
    let (um, sm) = low_frequency_loss(&model, &Theta::nominal(), &fixed_malleus(1e6));
    let mut stiff_sal = Theta::nominal();
    stiff_sal.0[3] *= 10.0;
    let (us, ss) = low_frequency_loss(&model, &stiff_sal, &Effects::default());
    eprintln!(
        "250–1000 Hz loss, umbo / stapes: malleus fixation 1e6 N/m {um:.1} / {sm:.1} dB; E_sal ×10 {us:.1} / {ss:.1} dB"
    );
    // Nakajima et al. 2005: a bony bar to the head costs 10–30 dB of stapes velocity.
    assert!((10.0..30.0).contains(&sm), "malleus fixation: stapes {sm:.1} dB");
    assert!(
        um / sm > 0.8 && us / ss < 0.2,
        "umbo / stapes loss: malleus {:.2}, stapes fixation {:.2}",
        um / sm,
        us / ss
    );
}

/// The effect's signature across its range, printed for the record (umbo and stapes dB,
/// absorbance change at 250, 500, 1000 and 4000 Hz): the loss grows with the stiffness and
/// spans Nakajima et al.'s (2005, Laryngoscope 115:147) grades of stapes-velocity loss,
/// from under 10 dB (fibrous tissue around the head) to over 35 dB (extensive
/// neo-osteogenesis), with the umbo's loss the stapes' to within 1 dB.
#[test]
fn a_malleus_fixation_lowers_umbo_and_stapes_together_across_its_range() {
    let model = Model::new(ModelConfig::default()).unwrap();
    let mut last = 0.0;
    for k in [1e3, 1e5, 1e7] {
        let row: Vec<String> = [250.0, 500.0, 1000.0, 4000.0]
            .iter()
            .map(|&f| {
                let (u, s, a) = change_at(&model, &Theta::nominal(), &fixed_malleus(k), f);
                format!("{f} Hz umbo {u:+.1} stapes {s:+.1} dB, ΔA {a:+.3}")
            })
            .collect();
        eprintln!("malleus_fixation {k:e} N/m: {}", row.join("; "));
        let (u, s) = low_frequency_loss(&model, &Theta::nominal(), &fixed_malleus(k));
        assert!(s > last && (u - s).abs() < 1.0, "{k:e} N/m: 250–1000 Hz umbo {u:.1}, stapes {s:.1} dB");
        last = s;
    }
    let (mild, _) = low_frequency_loss(&model, &Theta::nominal(), &fixed_malleus(1e3));
    assert!(mild < 10.0 && last > 35.0, "250–1000 Hz stapes loss {mild:.1} dB at 1e3 N/m, {last:.1} dB at 1e7 N/m");
}
