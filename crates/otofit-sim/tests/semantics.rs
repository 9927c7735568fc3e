//! Each tissue parameter acts on the default ear as its tissue does: the changes that
//! clinical and temporal-bone studies associate with each structure, tested on the
//! nominal ear with one parameter moved. (E_eardrum's own tests, compliance ∝ 1/E and
//! lower low-frequency transmission, are in `fe_drum.rs`.)
//!
//! Directions, from the literature: a fixed stapes (otosclerosis, stiff annular
//! ligament) lowers low-frequency stapes velocity by tens of dB while umbo velocity falls
//! by a few (Nakajima et al. 2005, Laryngoscope 115:147; Rosowski et al. 2008, Otol
//! Neurotol 29:1218); a fixed malleus lowers umbo and stapes velocity together (Nakajima
//! 2005); an interrupted incudostapedial joint raises umbo velocity and drops stapes
//! velocity (Rosowski 2008); the cochlear input impedance controls the stapes' motion
//! above its resonance (Merchant, Ravicz & Rosowski 1996, Hear Res 97:30); contracted
//! middle-ear muscles stiffen the chain, acting mostly below 1 kHz (Møller 1965); more
//! damping lowers and broadens the middle-ear resonance.

use otofit_sim::{Effects, JointPads, Model, ModelConfig, PARAMS, Theta};

fn set(theta: &mut Theta, name: &str, factor: f64) {
    theta.0[PARAMS.iter().position(|p| p.name == name).unwrap()] *= factor;
}

/// Mean 20·log10 |V/P| of umbo and stapes over the frequencies `band`.
fn levels(model: &Model, theta: &Theta, band: &[f64]) -> (f64, f64) {
    let mut r = model.runner();
    let (mut vu, mut vs) = (0.0, 0.0);
    for &f in band {
        let resp = r.response_at(theta, &Effects::default(), f).unwrap();
        vu += 20.0 * resp.vu_over_p.norm().log10() / band.len() as f64;
        vs += 20.0 * resp.vst_over_p.norm().log10() / band.len() as f64;
    }
    (vu, vs)
}

/// Change in dB (umbo, stapes) over `band` when `name` is multiplied by `factor`.
fn change(model: &Model, name: &str, factor: f64, band: &[f64]) -> (f64, f64) {
    let base = Theta::nominal();
    let mut moved = base;
    set(&mut moved, name, factor);
    let (u0, s0) = levels(model, &base, band);
    let (u1, s1) = levels(model, &moved, band);
    eprintln!("{name} ×{factor}: umbo {:+.2} dB, stapes {:+.2} dB over {band:?} Hz", u1 - u0, s1 - s0);
    (u1 - u0, s1 - s0)
}

fn ear() -> Model {
    Model::new(ModelConfig::default()).unwrap()
}

const LOW: [f64; 4] = [200.0, 300.0, 400.0, 500.0];
const HIGH: [f64; 4] = [4000.0, 5000.0, 6300.0, 8000.0];

#[test]
fn a_stiff_annular_ligament_lowers_stapes_velocity_far_more_than_umbo_velocity() {
    let (du, ds) = change(&ear(), "E_sal", 10.0, &LOW);
    assert!(ds < -6.0, "stapes {ds:.2} dB");
    assert!(du.abs() < 0.5 * ds.abs(), "umbo {du:.2} dB against stapes {ds:.2} dB");
}

#[test]
#[ignore = "known miss: E_ligaments ×30 moves the 200–500 Hz umbo velocity by −1.6 dB and the stapes by +1.0 dB; \
            the model's ligaments (anterior mallear, posterior incudal) lie on the rotation axis and the \
            off-axis superior and lateral mallear ligaments are absent (docs/results/simulator.md)"]
fn a_fixed_malleus_lowers_umbo_and_stapes_velocity_together() {
    let (du, ds) = change(&ear(), "E_ligaments", 30.0, &LOW);
    assert!(du < -3.0 && ds < -3.0, "umbo {du:.2} dB, stapes {ds:.2} dB");
    assert!(du < 0.5 * ds, "the umbo falls at least half as much as the stapes: {du:.2} against {ds:.2} dB");
}

#[test]
fn a_loose_incudostapedial_joint_raises_umbo_velocity_and_lowers_stapes_velocity() {
    let (du, ds) = change(&ear(), "E_joints", 0.01, &LOW);
    assert!(du > 0.0, "umbo {du:.2} dB");
    assert!(ds < -6.0, "stapes {ds:.2} dB");
}

#[test]
fn the_cochlear_load_sets_the_high_frequency_stapes_velocity_not_the_low() {
    let m = ear();
    let (_, high) = change(&m, "cochlear_load", 3.0, &HIGH);
    let (_, low) = change(&m, "cochlear_load", 3.0, &[200.0, 250.0]);
    assert!(high < -3.0, "4–8 kHz stapes {high:.2} dB");
    assert!(low.abs() < 0.5 * high.abs(), "200–250 Hz stapes {low:.2} dB against {high:.2} dB above 4 kHz");
}

#[test]
fn contracted_tendons_lower_low_frequency_transmission() {
    let (du, ds) = change(&ear(), "E_tendons", 10.0, &LOW);
    assert!(du < -1.0 && ds < -1.0, "umbo {du:.2} dB, stapes {ds:.2} dB");
}

#[test]
#[ignore = "known miss: E_tendons ×10 lowers the stapes velocity by 1.5 dB at 200–500 Hz but 3.0 dB at \
            4–8 kHz (docs/results/simulator.md)"]
fn contracted_tendons_stiffen_the_chain_below_one_kilohertz() {
    let m = ear();
    let (_, low) = change(&m, "E_tendons", 10.0, &LOW);
    let (_, high) = change(&m, "E_tendons", 10.0, &HIGH);
    assert!(low < -1.0, "200–500 Hz stapes {low:.2} dB");
    assert!(high.abs() < 0.5 * low.abs(), "4–8 kHz stapes {high:.2} dB against {low:.2} dB");
}

#[test]
fn more_damping_lowers_the_stapes_resonance_and_spares_the_low_frequencies() {
    let m = ear();
    let grid = m.frequencies().to_vec();
    let peak = |theta: &Theta| {
        let mut r = m.runner();
        grid.iter()
            .map(|&f| 20.0 * r.response_at(theta, &Effects::default(), f).unwrap().vst_over_p.norm().log10())
            .fold(f64::NEG_INFINITY, f64::max)
    };
    let base = Theta::nominal();
    let mut damped = base;
    set(&mut damped, "damping_beta", 4.0);
    let drop = peak(&damped) - peak(&base);
    let (_, low) = change(&m, "damping_beta", 4.0, &[200.0]);
    eprintln!("damping_beta ×4: stapes peak {drop:+.2} dB");
    assert!(drop < -1.0, "peak {drop:.2} dB");
    assert!(low.abs() < 0.5 * drop.abs(), "200 Hz {low:.2} dB against the peak's {drop:.2} dB");
}

/// The default ear with the joint pads of `pads` (`--joint-pads`).
fn ear_with(pads: JointPads) -> Model {
    let mut config = ModelConfig::default();
    config.geometry.confine_joint_pads(pads);
    Model::new(config).unwrap()
}

/// Umbo over stapes velocity, dB, averaged over 400–1000 Hz: the lever's 2.3 dB if the
/// malleus and incus turn as one body, more if the incudomallear joint slips.
fn slip(model: &Model) -> f64 {
    let (vu, vs) = levels(model, &Theta::nominal(), &[400.0, 500.0, 630.0, 800.0, 1000.0]);
    vu - vs
}

#[test]
fn confined_joint_pads_turn_the_malleus_and_incus_as_one_body() {
    // A confined pad is 35× stiffer in tilting (S = 7.1): the incus follows the malleus and
    // only the lever separates umbo and stapes; E·A/t lets the joint slip.
    let geometry = ModelConfig::default().geometry;
    let lever = 20.0 * (geometry.arm_umbo / geometry.arm_lp).log10();
    let (confined, unconfined) = (slip(&ear_with(JointPads::ImjConfined)), slip(&ear()));
    eprintln!(
        "umbo − stapes at 400–1000 Hz: lever {lever:.2} dB, confined {confined:.2} dB, unconfined {unconfined:.2} dB"
    );
    assert!((confined - lever).abs() < 3.0, "confined {confined:.2} dB against the lever's {lever:.2} dB");
    assert!(unconfined - confined > 6.0, "unconfined {unconfined:.2} dB, confined {confined:.2} dB");
}

/// What confining the pads costs and gains (`--ignored --nocapture`; the numbers of
/// docs/results/simulator.md, "Joint pads as incompressible layers").
#[test]
#[ignore = "a report"]
fn joint_pads_report() {
    for pads in [JointPads::Unconfined, JointPads::ImjConfined, JointPads::Confined] {
        let model = ear_with(pads);
        eprintln!("{pads:?}: umbo − stapes at 400–1000 Hz {:.2} dB", slip(&model));
        change(&model, "E_sal", 10.0, &LOW);
        change(&model, "E_joints", 0.01, &LOW);
    }
}
