//! Checks that fail when the physics is wrong: the canal's viscothermal attenuation
//! against Kirchhoff's wide-tube formula (written here from the physics, with air
//! properties from the ideal-gas law and Sutherland's law rather than the simulator's
//! fits), and the nominal ear's power budget (probe → canal → drum → ossicles → cochlea).
//! The membrane closed form is in `src/sim/shell.rs` (`pressurised_sphere_...`), the
//! passivity checks of every effect in `sim.rs`.

use crate::baseline::norm;
use faer::c64;
use otofit::sim::canal::{Area, CanalMesh};
use otofit::sim::line_drum::LineDrum;
use otofit::sim::{DrumLoss, DrumShape, Effects, Model, ModelConfig, PARAMS, Preset, Theta};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use std::f64::consts::PI;

/// Air at `celsius` and 1 atm from first principles: ideal gas (R_s = 287.05 J/kg/K,
/// γ = 1.4 for a diatomic gas), Sutherland's viscosity law (μ_ref = 1.716e-5 Pa·s at
/// 273.15 K, S = 110.4 K; White, Viscous Fluid Flow, 3rd ed., Table 1-2) and Pr = 0.71.
/// Returns (ρ, c, ν = μ/ρ, γ, Pr).
fn textbook_air(celsius: f64) -> (f64, f64, f64, f64, f64) {
    let t = 273.15 + celsius;
    let (r_s, gamma) = (287.05, 1.4);
    let rho = 101_325.0 / (r_s * t);
    let mu = 1.716e-5 * (t / 273.15).powf(1.5) * (273.15 + 110.4) / (t + 110.4);
    (rho, (gamma * r_s * t).sqrt(), mu / rho, gamma, 0.71)
}

/// The FE canal's element size (v1's model canal: ≥ 80 elements per wavelength at 8 kHz).
const CANAL_H: f64 = 0.5e-3;

/// Attenuation Re Γ (Np/m) of the FE canal (the simulator's own mesh density) over a
/// uniform tube of radius `r` and length λ/4: the condensed two-port of a uniform line
/// is [U_in, −U_out] = Y·[p_0, p_L] with Y₁₁ = coth(ΓL)/Z_c and Y₁₂ = −1/(Z_c sinh ΓL),
/// so cosh ΓL = −Y₁₁/Y₁₂ whatever the loss model inside the elements.
fn fe_attenuation(preset: Preset, r: f64, f: f64) -> f64 {
    let air = preset.air();
    let l = air.c / (4.0 * f);
    let mesh = CanalMesh::new(l, &Area::Uniform(PI * r * r), CANAL_H, &[]);
    let y = mesh.condense(&air, 2.0 * PI * f, 0, mesh.n_nodes() - 1);
    let cosh: c64 = -y[0] / y[1];
    cosh.acosh().re / l
}

#[test]
fn canal_attenuation_matches_kirchhoff_wide_tube_formula() {
    // Kirchhoff (1868, Ann. Phys. 134:177) for plane waves in a circular tube of radius r
    // whose viscous and thermal boundary layers are thin (δ_v = √(2ν/ω) ≪ r):
    //   α = (1/(r c))·√(ων/2)·(1 + (γ − 1)/√Pr)   [Np/m],
    // the first term viscous, the second thermal. Its relative error is of order δ_v/r
    // (2.9 % at r = 2.5 mm, 1 kHz, 37 °C; 0.5 % at 5 mm, 8 kHz), so the tolerance is
    // δ_v/r + 0.5 %. Halving either loss (−34 % or −16 %), a wrong boundary-layer radius
    // (a missing √Pr: −5 %) or a viscosity off by 10 % (±5 %) fails.
    let mut worst: f64 = 0.0;
    for (preset, celsius) in [(Preset::TemporalBone, 22.0), (Preset::Live, 37.0)] {
        let (_, c, nu, gamma, pr) = textbook_air(celsius);
        for r in [2.5e-3, (44e-6 / PI).sqrt(), 5e-3] {
            for f in [1000.0, 2000.0, 4000.0, 8000.0] {
                let w = 2.0 * PI * f;
                let kirchhoff = (w * nu / 2.0).sqrt() / (r * c) * (1.0 + (gamma - 1.0) / pr.sqrt());
                let tol = (2.0 * nu / w).sqrt() / r + 0.005;
                let fe = fe_attenuation(preset, r, f);
                let dev = fe / kirchhoff - 1.0;
                eprintln!(
                    "{celsius} °C, r {:.2} mm, {f} Hz: α FE {fe:.4}, Kirchhoff {kirchhoff:.4} Np/m ({:+.2} %, tol {:.2} %)",
                    r * 1e3,
                    100.0 * dev,
                    100.0 * tol
                );
                worst = worst.max(dev.abs() / tol);
                assert!(dev.abs() < tol, "α at r = {r} m, {f} Hz, {celsius} °C: FE {fe} vs Kirchhoff {kirchhoff} Np/m");
            }
        }
    }
    eprintln!("worst |α_FE/α_Kirchhoff − 1| / tolerance = {worst:.2}");
}

#[test]
fn canal_line_of_the_model_equals_the_fe_canal_for_any_geometry() {
    // The model maps the drum's impedance Z_tm to the impedance plane through the exact
    // transfer matrix of a uniform line (v2); the FE canal (an independent
    // discretisation of Webster's equation with its own element loss terms) terminated by
    // the same Z_tm must give the same Z_ec to the FE's second-order error. A wrong
    // transfer matrix (e.g. a swapped sinh term) or a wrong area fails by far more.
    let model = Model::new(ModelConfig::default()).unwrap();
    let mut runner = model.runner();
    let fx = Effects::default();
    let air = model.air;
    let mut worst: f64 = 0.0;
    for (l, s) in [(3e-3, 25e-6), (12e-3, 44e-6), (25e-3, 70e-6)] {
        let mut theta = Theta::nominal();
        theta.0[7] = l;
        theta.0[8] = s;
        let mesh = CanalMesh::new(l, &Area::Uniform(s), CANAL_H / 4.0, &[]);
        for f in [250.0, 1000.0, 4000.0, 8000.0] {
            let zec = runner.response_at(&theta, &fx, f).unwrap().zec;
            let z_tm = runner.solution()[model.dofs.p_drum];
            let y = mesh.condense(&air, 2.0 * PI * f, 0, mesh.n_nodes() - 1);
            // [U0, −U_L] = Y [p0, p_L] with U_L = p_L / Z_tm, for p0 = 1.
            let p_l = -y[2] / (y[3] + 1.0 / z_tm);
            let z_fe = 1.0 / (y[0] + y[1] * p_l);
            let dev = ((zec - z_fe) / z_fe).norm();
            worst = worst.max(dev);
            assert!(dev < 2e-3, "L {l} m, S {s} m², {f} Hz: line {zec}, FE {z_fe} (|Δ|/|Z| = {dev:.1e})");
        }
    }
    eprintln!("worst |Z_line − Z_FE| / |Z_FE| = {worst:.1e}");
}

#[test]
fn power_budget_of_the_nominal_ear() {
    // Per frequency: power in at the probe = canal walls + into the middle ear at the drum,
    // and into the drum = drum + ligaments + tendons + joints + SAL + cochlea, every part
    // ≥ 0. Prints the table of docs/simulator.md ("Power budget").
    let model = Model::new(ModelConfig::default()).unwrap();
    let budget = model.runner().power_budget(&Theta::nominal()).unwrap();
    eprintln!("     f Hz   canal%  drum-in%   drum%   lig+tend%  joints%   SAL%   cochlea%   (of probe | of drum-in)");
    for p in &budget {
        let parts = [p.drum, p.ligaments, p.tendons, p.joints, p.sal, p.cochlea];
        assert!(parts.iter().chain([&p.canal]).all(|&v| v >= 0.0), "{p:?}");
        let sum: f64 = parts.iter().sum();
        assert!((p.probe - p.canal - p.into_drum).abs() < 1e-9 * p.probe, "canal balance {p:?}");
        assert!((p.into_drum - sum).abs() < 1e-9 * p.probe, "middle-ear balance {p:?}");
        let (of_probe, of_me) = (|v: f64| 100.0 * v / p.probe, |v: f64| 100.0 * v / p.into_drum);
        eprintln!(
            "{:9.0} {:8.1} {:9.1} {:8.1} {:10.2} {:8.3} {:7.2} {:9.1}",
            p.freq_hz,
            of_probe(p.canal),
            of_probe(p.into_drum),
            of_me(p.drum),
            of_me(p.ligaments + p.tendons),
            of_me(p.joints),
            of_me(p.sal),
            of_me(p.cochlea)
        );
    }
    // The cochlea's share of the power entering the middle ear, against the issue's
    // target (≥ 30 % at 1–4 kHz); recorded as named known misses.
    for (f, name) in
        [(1000.0, "cochlear_share_1khz_pct"), (2000.0, "cochlear_share_2khz_pct"), (4000.0, "cochlear_share_4khz_pct")]
    {
        let share = 100.0 * share_at(&model, f);
        norm(name, share, share >= 30.0);
    }
}

fn share_at(model: &Model, f: f64) -> f64 {
    let mut runner = model.runner();
    runner.solve_at(&Theta::nominal(), f).unwrap();
    runner.power_balance(&Theta::nominal(), f).cochlear_share()
}

#[test]
#[ignore = "known miss: the cochlea receives 3.5 / 2.9 / 0.6 % of the middle-ear input at 1 / 2 / 4 kHz (tests/data/known_misses.json); at 2-4 kHz the target is out of reach of any ear that meets the norms (the_norms_cap_the_cochlear_share_...)"]
fn cochlea_receives_at_least_30_percent_at_1_to_4_khz() {
    let model = Model::new(ModelConfig::default()).unwrap();
    for f in [1000.0, 1500.0, 2000.0, 3000.0, 4000.0] {
        let share = share_at(&model, f);
        assert!(share >= 0.30, "cochlear share at {f} Hz: {:.1} %", 100.0 * share);
    }
}

/// The norms themselves cap the cochlear share above 2 kHz, far below the 30 % the
/// issue asked for. Between the impedance plane and the drum a uniform canal keeps |R|,
/// so the drum absorbs P = A·|p_i|²/(2Z₀) of an incident wave p_i, and the pressure on it
/// is |p_d| = |p_i||1 + R| ≤ |p_i|(1 + √(1 − A)). The cochlea takes ½Z_c·A_fp²·|V/P|²·|p_d|²,
/// so share ≤ Z_c·A_fp²·|V/P|²·Z₀·(1 + √(1 − A))²/A. At the most favourable end of every
/// datum — V/P 5 dB above Goode 1994 (the issue's own tolerance), Z_c at the top of its
/// normal range (Zwislocki 35 GΩ), A at the low end of the adult 10–90 % range, Z₀ of the
/// nominal 44 mm² canal — the bound is 15 % at 2 kHz and 3.3 % at 4 kHz (27 % and 5.7 %
/// with the narrowest canal of the prior, 25 mm²). Canal wall losses only lower it. So
/// no ear that meets the other targets can give the cochlea ≥ 30 % at 2–4 kHz; at 1 kHz
/// the bound (> 100 %) does not bind. The nominal model's 8.4 % and 4.2 % sit at or below
/// the bound (its V/P is 6–7 dB above Goode there). Fails if the norms, the Goode
/// conversion or the footplate area change enough to make the target reachable.
#[test]
fn the_norms_cap_the_cochlear_share_far_below_30_percent_at_2_and_4_khz() {
    use crate::baseline::floats;
    let n = crate::baseline::normative();
    // The value of table `t`'s column `col` at frequency `f` (a tabulated one).
    let at = |t: &str, col: &str, f: f64| {
        let fs = floats(&n[t]["frequency_hz"]);
        floats(&n[t][col])[fs.iter().position(|&x| x == f).unwrap()]
    };
    let goode = |f: f64| at("vst_goode1994", "value", f);
    let a_low = |f: f64| at("absorbance", "low", f);
    let z_c = otofit::npe::normal::NORMAL.iter().find(|r| r.name == "cochlear_load").unwrap().high;
    let a_fp = otofit::sim::Geometry::default().footplate_area;
    let air = Preset::TemporalBone.air();
    let bound = |f: f64, area: f64| {
        let v = 10f64.powf((goode(f) + 5.0) / 20.0) * 1e-3; // m/s/Pa
        let a = a_low(f);
        z_c * a_fp * a_fp * v * v * (air.rho * air.c / area) * (1.0 + (1.0 - a).sqrt()).powi(2) / a
    };
    let model = Model::new(ModelConfig::default()).unwrap();
    for (f, cap) in [(2000.0, 0.20), (4000.0, 0.05)] {
        let (b44, b25) = (bound(f, 44e-6), bound(f, 25e-6));
        let share = share_at(&model, f);
        eprintln!(
            "{f} Hz: cochlear share at most {:.1} % (44 mm²), {:.1} % (25 mm²); nominal model {:.1} %",
            100.0 * b44,
            100.0 * b25,
            100.0 * share
        );
        assert!(b44 < cap && b25 < 0.30, "{f} Hz: bound {b44:.3} / {b25:.3}");
    }
    assert!(bound(1000.0, 44e-6) > 1.0, "1 kHz: the bound binds");
}

/// Umbo velocity is the malleus point under the umbo. Closed form: with the chain made
/// rigid (ligaments, tendons and joints at 50 GPa–100 TPa, ≥ 10⁴× their nominal: malleus and incus turn as one body
/// about the fixed axis, and the incudostapedial shear spring holds the stapes head on
/// its path) the stiffness-controlled ratio V_umbo/V_stapes at 200 Hz is the lever ratio
/// l_umbo/l_lenticular over cos α, α the stapes tilt (the head's axial motion is
/// x_s/cos α once its lateral motion is held at zero), in phase. With the nominal,
/// flexible chain the umbo moves more than that lever carries to the stapes.
#[test]
fn umbo_over_stapes_is_the_lever_ratio_when_the_chain_is_rigid() {
    let model = Model::new(ModelConfig::default()).unwrap();
    let g = &model.config.geometry;
    let lever = g.arm_umbo / (g.arm_lp * g.stapes_tilt.cos());
    let mut runner = model.runner();
    let mut ratio = |theta: &Theta| {
        let r = runner.response_at(theta, &Effects::default(), 200.0).unwrap();
        r.vu_over_p / r.vst_over_p
    };
    // How the rigidity is shared moves the ratio by about ±1 % (the suspension sets where
    // the axis sits): equal 100 GPa 1.3244, v1–v5's nominal ×10⁴ 1.3348, joints 10³×
    // stiffer than the suspension 1.3499, against the closed form's 1.3362.
    for (lig, tendons, joints) in [(1e11, 1e11, 1e11), (5e10, 2e10, 6e10), (1e11, 1e11, 1e14)] {
        let mut rigid = Theta::nominal();
        (rigid.0[1], rigid.0[2], rigid.0[4]) = (lig, tendons, joints);
        let q = ratio(&rigid);
        eprintln!("rigid chain: |Vu/Vst| {:.4} (closed form {lever:.4}), phase {:.3}°", q.norm(), q.arg().to_degrees());
        assert!((q.norm() / lever - 1.0).abs() < 0.015, "|Vu/Vst| {:.4} vs {lever:.4}", q.norm());
        assert!(q.arg().abs() < 1f64.to_radians(), "phase {:.2}°", q.arg().to_degrees());
    }
    let q = ratio(&Theta::nominal());
    eprintln!("nominal: |Vu/Vst| {:.4}", q.norm());
    assert!(q.norm() > lever * 1.1, "nominal |Vu/Vst| {:.4}", q.norm());
}

/// The stapes head's displacement across its axis (the rocking plane), from the solve.
fn head_lateral(model: &Model, x: &[c64]) -> c64 {
    let g = &model.config.geometry;
    let d = &model.dofs;
    x[d.x_stapes] * g.stapes_tilt.sin() + x[d.phi_stapes] * (g.stapes_height * g.stapes_tilt.cos())
}

#[test]
fn the_incus_across_the_stapes_axis_obeys_its_own_equation_of_motion() {
    // `Geometry::incus_lateral`: the incus's lateral unknown couples to
    // the rest only through the ISJ's shear spring, so its row is a closed form: the joint
    // spring κ_j·g_isj against the incus held by the PIL (ligaments' modulus) and the IMJ
    // (joints') and its mass, y_i = κ_j g_isj·y_head / (κ_j g_isj + κ_l g_pil + κ_j g_imj
    // − ω² m_i), κ = E(1 + jωβ). Unequal moduli catch a spring in the wrong block.
    let mut config = ModelConfig::default();
    config.geometry.incus_lateral = true;
    let model = Model::new(config).unwrap();
    let g = &model.config.geometry;
    let yi = model.dofs.y_incus.expect("the lateral unknown exists");
    let mut runner = model.runner();
    let mut theta = Theta::nominal();
    (theta.0[1], theta.0[4]) = (2e6, 3e7); // E_ligaments, E_joints
    for f in [200.0, 1000.0, 3000.0, 8000.0] {
        runner.solve_at(&theta, f).unwrap();
        let x = runner.solution();
        let w = 2.0 * PI * f;
        let ray = c64::new(1.0, w * theta.damping_beta());
        let (kj, kl) = (ray * theta.e_joints(), ray * theta.e_ligaments());
        let isj = kj * g.g_isj_shear;
        let want =
            isj * head_lateral(&model, x) / (isj + kl * g.g_pil_lateral + kj * g.g_imj_lateral - w * w * g.m_incus);
        assert!((x[yi] - want).norm() < 1e-9 * want.norm(), "{f} Hz: y_incus {} vs closed form {want}", x[yi]);
    }
}

#[test]
fn holding_the_incus_across_the_axis_gives_the_grounded_joint() {
    // With its lateral holds 10⁸× stiffer the incus stands still across the axis, and the
    // model must be every earlier model (the ISJ's shear spring to the ground), feature
    // for feature; with the holds as built the features move by much less than the noise
    // (docs/simulator.md, "The incus across the stapes axis").
    let grounded = Model::new(ModelConfig::default()).unwrap();
    let mut config = ModelConfig::default();
    config.geometry.incus_lateral = true;
    config.geometry.g_pil_lateral *= 1e8;
    config.geometry.g_imj_lateral *= 1e8;
    let held = Model::new(config).unwrap();
    assert_eq!(held.n_unknowns(), grounded.n_unknowns() + 1);
    let mut rng = ChaCha8Rng::seed_from_u64(3);
    for _ in 0..5 {
        let mut theta = Theta(std::array::from_fn(|i| PARAMS[i].from_unit(rng.random())));
        theta.0[12] = 45.0; // the LDV beam sees the rocking
        let a = otofit::sim::simulate(&mut grounded.runner(), &theta, &Effects::default()).unwrap();
        let b = otofit::sim::simulate(&mut held.runner(), &theta, &Effects::default()).unwrap();
        let worst = a.iter().zip(&b).map(|(p, q)| (p - q).abs()).fold(0.0, f64::max);
        assert!(worst < 1e-6, "held incus vs grounded joint: worst feature difference {worst:.2e} at {theta:?}");
    }
}

/// A line drum for the tests (`sim::line_drum`), inside the knobs' ranges of
/// examples/tune_nominal.rs.
const LINE: LineDrum = LineDrum { delay: 60e-6, z0: 1.5e7, area: 40e-6, shunt: 7e-13 };

#[test]
fn line_drum_with_the_umbo_held_is_the_rigid_ended_line_beside_its_shunt_and_behind_the_cavity() {
    // With the malleus 10¹⁰× heavier the umbo stands still (U₂ = 0), so the model's drum
    // impedance (p_drum per unit flow) must be the textbook rigid-ended lossless line
    // −jZ₀·cot ωτ, in parallel with the shunt compliance, in series with the cavity
    // ρc²/(jωV). Checks how the two-port is wired into the system (flow row, cavity row).
    let mut config = ModelConfig::default();
    config.geometry.tm_shape = DrumShape::Line(LINE);
    config.geometry.tm_loss = DrumLoss::LossFactor(0.0);
    config.geometry.m_malleus *= 1e10;
    config.geometry.i_malleus *= 1e10;
    let model = Model::new(config).unwrap();
    let mut runner = model.runner();
    let mut theta = Theta::nominal();
    theta.0[11] = 0.0; // an elastic drum: the closed form is the lossless line
    for f in [250.0, 1000.0, 3000.0, 5000.0, 8000.0] {
        runner.solve_at(&theta, f).unwrap();
        let x = runner.solution();
        let w = 2.0 * PI * f;
        let z_line = c64::new(0.0, -LINE.z0 / (w * LINE.delay).tan());
        let y_shunt = c64::new(0.0, w * LINE.shunt);
        let z_cav = c64::new(0.0, -model.air.bulk_modulus() / (w * theta.cavity_volume()));
        let want = 1.0 / (1.0 / z_line + y_shunt) + z_cav;
        let got = x[model.dofs.p_drum];
        assert!((got - want).norm() < 1e-6 * want.norm(), "{f} Hz: model {got}, closed form {want}");
        assert!(x[model.dofs.umbo].norm() * w * LINE.area < 1e-6, "{f} Hz: the umbo moves");
    }
}

#[test]
fn line_drum_ear_is_passive_and_balances_its_power_at_random_draws() {
    // Random θ over the prior, random line geometry and drum loss model, every other ear
    // with the incus free across the stapes axis: every loss ≥ 0
    // (the drum's from its distributed losses along the line), probe = canal + into the
    // drum, into the drum = the middle-ear losses, Re Z_ec ≥ 0, 0 ≤ A ≤ 1.
    let mut rng = ChaCha8Rng::seed_from_u64(12);
    let log_uniform = |rng: &mut ChaCha8Rng, lo: f64, hi: f64| lo * (hi / lo).powf(rng.random::<f64>());
    let mut least_drum = f64::INFINITY;
    for draw in 0..40 {
        let line = LineDrum {
            delay: log_uniform(&mut rng, 10e-6, 150e-6),
            z0: log_uniform(&mut rng, 3e6, 1e8),
            area: log_uniform(&mut rng, 20e-6, 60e-6),
            shunt: if draw % 4 == 0 { 0.0 } else { log_uniform(&mut rng, 1e-13, 1e-11) },
        };
        let mut config = ModelConfig::default();
        config.geometry.tm_shape = DrumShape::Line(line);
        config.geometry.tm_loss = match draw % 3 {
            0 => DrumLoss::Rayleigh,
            1 => DrumLoss::LossFactor(rng.random::<f64>()),
            _ => DrumLoss::Hysteretic { f_ref_hz: 1000.0 },
        };
        config.geometry.incus_lateral = draw % 2 == 1;
        let model = Model::new(config).unwrap();
        let mut runner = model.runner();
        let theta = Theta(std::array::from_fn(|i| PARAMS[i].from_unit(rng.random())));
        for &f in model.frequencies() {
            let r = runner.response_at(&theta, &Effects::default(), f).unwrap();
            let p = runner.power_balance(&theta, f);
            let parts = [p.canal, p.drum, p.ligaments, p.tendons, p.joints, p.sal, p.cochlea];
            assert!(p.probe > 0.0 && parts.iter().all(|&v| v >= -1e-12 * p.probe), "{p:?} {line:?} {theta:?}");
            least_drum = least_drum.min(p.drum / p.into_drum);
            let tol = 1e-6 * p.probe;
            assert!((p.probe - p.canal - p.into_drum).abs() < tol, "canal balance {p:?} {line:?}");
            assert!((p.into_drum - p.mechanical).abs() < tol, "middle-ear balance {p:?} {line:?}");
            let a = r.absorbance();
            assert!(r.zec.re >= 0.0 && (-1e-12..=1.0 + 1e-12).contains(&a), "Z_ec {} A {a} at {f} Hz", r.zec);
        }
    }
    eprintln!("40 line drums × 50 frequencies; least drum loss / drum input {least_drum:.2e}");
}

/// The reference ear is a composite: its impedance and its absorbance are means of
/// different studies. In this model (in any model that reports absorbance from its own
/// Z_ec) A = 1 − |(Z − Z₀)/(Z + Z₀)|², Z₀ = ρc/S with S the canal area, a parameter
/// bounded by the prior. So the reference ear's five impedance and absorbance features at
/// each frequency cannot all be fitted: the least χ² over every complex Z at every
/// frequency (any model at all, smooth or not), for a given S, is a floor on
/// `study reference`'s reduced χ² (its 250 features, the stapes ones fitted exactly).
#[test]
fn the_reference_ears_impedance_and_absorbance_set_a_floor_on_its_reduced_chi2() {
    let model = Model::new(ModelConfig::default()).unwrap();
    let freqs = model.frequencies();
    let n = freqs.len();
    let r = otofit::reference::build(freqs).unwrap();
    let feature = |m: usize, k: usize| (r.x[m * n + k], r.std[m * n + k]);
    let floor = |area: f64| {
        let z0 = model.air.z0(area);
        (0..n)
            .map(|k| {
                let ((lt, s1), (pt, s2), (at, s3)) = (feature(2, k), feature(3, k), feature(4, k));
                let cost = |l: f64, p: f64| {
                    let z = c64::from_polar(10f64.powf(l), p);
                    let a = 1.0 - ((z - z0) / (z + z0)).norm_sqr();
                    ((l - lt) / s1).powi(2) + ((p - pt) / s2).powi(2) + ((a - at) / s3).powi(2)
                };
                // A grid over ±12 STDs of each, then a pattern search from its best point.
                let (mut best, mut l, mut p) = (f64::INFINITY, lt, pt);
                for i in -60..=60 {
                    for j in -60..=60 {
                        let (li, pj) = (lt + 0.2 * i as f64 * s1, pt + 0.2 * j as f64 * s2);
                        let c = cost(li, pj);
                        if c < best {
                            (best, l, p) = (c, li, pj);
                        }
                    }
                }
                let mut step = 0.1;
                while step > 1e-6 {
                    let moves = [(step * s1, 0.0), (-step * s1, 0.0), (0.0, step * s2), (0.0, -step * s2)];
                    match moves.iter().map(|&(dl, dp)| (cost(l + dl, p + dp), dl, dp)).find(|m| m.0 < best) {
                        Some((c, dl, dp)) => (best, l, p) = (c, l + dl, p + dp),
                        None => step /= 2.0,
                    }
                }
                best
            })
            .sum::<f64>()
            / (5 * n) as f64
    };
    let areas = [25e-6, 35.6e-6, 44e-6, 60e-6, 70e-6];
    let floors: Vec<f64> = areas.iter().map(|&s| floor(s)).collect();
    for (s, f) in areas.iter().zip(&floors) {
        eprintln!("canal area {:.1} mm²: reduced χ² ≥ {f:.3}", s * 1e6);
    }
    // The floor falls as the canal widens; the values docs/simulator.md quotes (at the
    // prior's widest canal, of the χ²ν ≤ 3 target at most 1.11 is left for the rest).
    assert!(floors.windows(2).all(|w| w[1] < w[0]), "{floors:?}");
    for (got, quoted) in floors.iter().zip([3.679, 3.093, 2.659, 2.102, 1.889]) {
        assert!((got - quoted).abs() < 0.002, "{floors:?}");
    }
}
