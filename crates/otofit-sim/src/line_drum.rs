//! The eardrum as a lossy transmission line between the ear canal and the umbo
//! (`DrumShape::Line`), after Puria & Allen 1998 (JASA 104:3463, cat) and O'Connor &
//! Puria 2008 (human middle-ear circuit): the drum carries a travelling wave from its
//! surface to the manubrium, so the malleus sees the canal pressure with a delay.
//!
//! Two-port. Port 1 is the canal side: the net pressure on the drum P₁ = p_drum − p_cav
//! and the volume velocity into it U₁. Port 2 is the manubrium: a pressure P₂ acting on
//! the coupling area S (force F = S·P₂ on the umbo, toward +z) and U₂ = S·v_umbo. The line
//! has unit length, series impedance z = jω·τ·Z₀ and shunt admittance y = jω·(τ/Z₀)/r per
//! length, so Γ = √(zy) and Z_c = √(z/y); lossless (r = 1) it delays by τ with
//! characteristic impedance Z₀. A shunt compliance C_s at port 1 is the part of the drum
//! that moves air but not the manubrium.
//!
//! E_eardrum. r = κ/E_ref, κ being the drum's complex modulus of `model.rs` (E with its
//! loss model and viscoelastic exponent; E_ref = the nominal E_eardrum, 20 MPa), scales
//! the stiffness of the line and of the shunt; their masses are fixed. A membrane's wave
//! speed is √(tension/surface density) and its tension ∝ E·h, so the delay goes as
//! √(E_ref/E), Z_c as √(E/E_ref) and the shunt compliance as E_ref/E. Loss enters only
//! through Im κ ≥ 0, so the drum is passive whenever κ is (Re y ≥ 0, Re z = 0).
//!
//! In the model the drum is a dense 3×3 block on (umbo, p_drum, p_cav): eliminating P₂
//! with the ABCD matrix [A B; C D] (AD − BC = 1) gives
//!   F  = (S/A)·P₁ − (S²B/A)·v,   U₁ = (C/A)·P₁ + (S/A)·v,
//! reciprocal (the same S/A both ways). τ, Z₀, S and C_s are geometry (knobs of
//! `examples/tune_nominal.rs`), not inferred parameters.
//!
//! Literature values, as far as they could be checked here: Puria & Allen's cat drum delay
//! is of the order of 30–40 µs; human middle-ear group delays are 60–150 µs over 2–8 kHz
//! (physics-notes §3.1), of which the drum carries a part. The effective area at low
//! frequency is 20–40 mm² (Hudde & Engel: A₀ = 38 mm² of 60 mm²). The exact circuit values
//! of either paper could not be retrieved (physics-notes §6: "Not found in public code"),
//! so [`LineDrum::NOMINAL`] is chosen inside these orders, not copied.

use super::model::{DrumLoss, DrumShape, Geometry};
use super::params::{PARAMS, Theta};
use faer::c64;

/// The modulus at which `delay`, `z0` and `shunt` hold: the nominal E_eardrum, Pa.
pub const E_REF: f64 = PARAMS[0].nominal;

/// The line drum's geometry, at E_eardrum = [`E_REF`] without loss.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct LineDrum {
    /// One-way delay τ of the lossless line, s.
    pub delay: f64,
    /// Characteristic impedance Z₀, Pa·s/m³.
    pub z0: f64,
    /// Coupling area S between the line's end and the umbo, m².
    pub area: f64,
    /// Shunt compliance C_s at the canal side (drum not coupled to the manubrium), m³/Pa.
    pub shunt: f64,
}

/// The line's state at both ports for a given P₁ and umbo velocity.
#[derive(Clone, Copy, Debug)]
pub struct Ports {
    /// Pressure at the manubrium end, Pa.
    pub p2: c64,
    /// Volume velocity at the manubrium end (S·v), m³/s.
    pub u2: c64,
    /// Volume velocity into the line at the canal end, m³/s.
    pub u1: c64,
    /// Volume velocity into the shunt, m³/s.
    pub u_shunt: c64,
}

impl LineDrum {
    /// A starting point (chosen, see the module doc): τ 40 µs, Z₀ 2e7 Pa·s/m³ (the order
    /// of |Z_TM| near 1 kHz), S 40 mm², a shunt of 0.1 cm³ equivalent air volume.
    pub const NOMINAL: LineDrum = LineDrum { delay: 40e-6, z0: 2e7, area: 40e-6, shunt: 7e-13 };

    /// Series impedance and shunt admittance per (unit) length at angular frequency `w`
    /// for the drum's complex modulus `kappa`.
    pub fn zy(&self, kappa: c64, w: f64) -> (c64, c64) {
        let r = kappa / E_REF;
        let jw = c64::new(0.0, w);
        (jw * (self.delay * self.z0), jw * (self.delay / self.z0) / r)
    }

    /// Propagation constant Γ (over the whole line, Re Γ ≥ 0) and characteristic
    /// impedance Z_c (Re Z_c ≥ 0).
    pub fn constants(&self, kappa: c64, w: f64) -> (c64, c64) {
        let (z, y) = self.zy(kappa, w);
        ((z * y).sqrt(), (z / y).sqrt())
    }

    /// The ABCD matrix [A, B, C, D]: (P₁, U₁) = [A B; C D]·(P₂, U₂).
    pub fn abcd(&self, kappa: c64, w: f64) -> [c64; 4] {
        let (g, zc) = self.constants(kappa, w);
        let (ch, sh) = (g.cosh(), g.sinh());
        [ch, zc * sh, sh / zc, ch]
    }

    /// Admittance of the shunt compliance, m³/(s·Pa).
    pub fn shunt_admittance(&self, kappa: c64, w: f64) -> c64 {
        c64::new(0.0, w * self.shunt) * E_REF / kappa
    }

    /// Input impedance of the line alone (no shunt) terminated by `z_load` (acoustic,
    /// Pa·s/m³) at the manubrium end.
    pub fn input_impedance(&self, kappa: c64, w: f64, z_load: c64) -> c64 {
        let [a, b, c, d] = self.abcd(kappa, w);
        (a * z_load + b) / (c * z_load + d)
    }

    /// The block on (umbo, p_drum, p_cav) × (umbo, p_drum, p_cav), row-major, that the
    /// drum adds to the system: the umbo's force row (−F), the driven flow row (U₁ + U_s)
    /// and the cavity row ((ρc²/V)·(U₁ + U_s)/(jω); its −p_cav is the model's).
    pub fn block(&self, kappa: c64, w: f64, cavity: f64) -> [c64; 9] {
        let [a, b, c, _] = self.abcd(kappa, w);
        let jw = c64::new(0.0, w);
        let s = self.area;
        let t = s / a; // force per P₁, and volume velocity per umbo velocity
        let zb = s * s * b / a; // mechanical impedance at the umbo with P₁ = 0
        let yin = c / a + self.shunt_admittance(kappa, w); // flow per P₁, umbo held
        let k = c64::new(cavity, 0.0) / jw;
        [jw * zb, -t, t, jw * t, yin, -yin, k * jw * t, k * yin, -k * yin]
    }

    /// Both ports' state for net pressure `p1` on the drum and umbo velocity `v`.
    pub fn ports(&self, kappa: c64, w: f64, p1: c64, v: c64) -> Ports {
        let [a, b, c, d] = self.abcd(kappa, w);
        let u2 = v * self.area;
        let p2 = (p1 - b * u2) / a;
        Ports { p2, u2, u1: c * p2 + d * u2, u_shunt: self.shunt_admittance(kappa, w) * p1 }
    }

    /// Power dissipated in the drum, W: ½∫₀¹(Re z·|U(x)|² + Re y·|p(x)|²)dx along the line
    /// (Simpson, 256 intervals, from the manubrium-end state) plus ½·Re Y_s·|P₁|² in the
    /// shunt. Written from the distributed losses, independently of the port powers it
    /// must balance.
    pub fn loss(&self, kappa: c64, w: f64, p1: c64, v: c64) -> f64 {
        let ports = self.ports(kappa, w, p1, v);
        let (z, y) = self.zy(kappa, w);
        let (g, zc) = self.constants(kappa, w);
        let line = simpson(256, |x| {
            let (ch, sh) = ((g * x).cosh(), (g * x).sinh());
            let p = ch * ports.p2 + zc * sh * ports.u2;
            let u = sh / zc * ports.p2 + ch * ports.u2;
            z.re * u.norm_sqr() + y.re * p.norm_sqr()
        });
        0.5 * line + 0.5 * self.shunt_admittance(kappa, w).re * p1.norm_sqr()
    }
}

/// Point (a) of the first line-drum search (v6) (docs/simulator.md, "A transmission-line drum"): the
/// nominal ear meets Goode ±5 dB (worst 0.8 dB), the 8 kHz phase (−272°), group delay
/// 65–87 µs over 2–8 kHz and the adult absorbance range with every tissue value inside its
/// normal range. Found by `DRUM=line W_SHARE=0 cargo run --example tune_nominal -- 12 6
/// 1500` (Nelder–Mead, 6 starts × 2 × 1,500 iterations; the values below are its printed
/// best point, re-run on commit 593a883). `--drum line` (`otofit simulate --explain`,
/// `otofit study reference`) uses the structural part ([`LineTuning::apply`]); the tissue
/// part ([`LineTuning::theta`]) is a parameter row, given with `--theta` or used as a
/// least-squares start.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct LineTuning {
    /// The line's geometry at [`E_REF`].
    pub line: LineDrum,
    /// The drum's loss factor η (`DrumLoss::LossFactor`).
    pub eta: f64,
    /// Factor on the malleus' and incus' masses and inertias.
    pub ossicle_mass: f64,
    /// Factor on the annular ligament's geometric factors (piston and rocking).
    pub sal_geometry: f64,
    /// The tissue values by name (`params::PARAMS`), and the drum's viscoelastic exponent.
    pub tissue: [(&'static str, f64); 8],
}

impl LineTuning {
    /// The first search's point (a) (see the type's doc for the search and its command).
    pub const POINT_A: LineTuning = LineTuning {
        line: LineDrum { delay: 165.23e-6, z0: 3.0873e7, area: 25.591e-6, shunt: 7.3853e-12 },
        eta: 0.46349,
        ossicle_mass: 1.2129,
        sal_geometry: 0.94811,
        tissue: [
            ("E_eardrum", 122.41e6),
            ("E_ligaments", 15.058e6),
            ("E_tendons", 0.66833e6),
            ("E_sal", 0.35212e6),
            ("E_joints", 0.81313e6),
            ("damping_beta", 1.2257e-4),
            ("cochlear_load", 2.1e10),
            ("tm_viscoelastic", 0.172),
        ],
    };

    /// The v7 search's point (d): the same search with the live-adult impedance ranges in the
    /// cost and the annular-ligament geometry held (`DRUM=line W_SHARE=0 W_ZEC=1 FIX=9
    /// cargo run --example tune_nominal -- 12 6 1500`, cost 0.023; the values below are its
    /// printed best point). Without the hold the same search puts that geometry on its
    /// box's floor (×0.1, docs/simulator.md "v7").
    pub const POINT_D: LineTuning = LineTuning {
        line: LineDrum {
            delay: 5.130081180826794e-5,
            z0: 99999988.0865087,
            area: 2.4700914905277485e-5,
            shunt: 4.177414784461698e-12,
        },
        eta: 0.77299,
        ossicle_mass: 1.7337,
        sal_geometry: 1.0,
        tissue: [
            ("E_eardrum", 14.638e6),
            ("E_ligaments", 3.1868e6),
            ("E_tendons", 2.4842e6),
            ("E_sal", 0.29611e6),
            ("E_joints", 1.4704e6),
            ("damping_beta", 8.4233e-5),
            ("cochlear_load", 2.1079e10),
            ("tm_viscoelastic", 0.017),
        ],
    };

    /// The v7 default ear (docs/simulator.md, "v7"): point (d) restated at E_eardrum =
    /// [`E_REF`], as v6 restated point (a).
    pub fn v7() -> LineTuning {
        LineTuning::POINT_D.at_modulus(E_REF)
    }

    /// The same ear with E_eardrum = `e` and the line rescaled so that every output is
    /// unchanged. The line's E-scaling makes (E, τ, Z₀, C_s) degenerate: only τ·√(E_ref/E),
    /// Z₀·√(E/E_ref) and C_s·E_ref/E reach the ear (docs/simulator.md, "v6").
    pub fn at_modulus(&self, e: f64) -> LineTuning {
        let mut t = *self;
        let slot = t.tissue.iter_mut().find(|(n, _)| *n == "E_eardrum").expect("E_eardrum is a tuned value");
        let r = e / slot.1; // new over old modulus
        slot.1 = e;
        t.line.delay *= r.sqrt();
        t.line.z0 /= r.sqrt();
        t.line.shunt *= r;
        t
    }

    /// Puts the line, its loss factor and the two structural factors into `g` (the
    /// example's `Search::apply`, structural part).
    pub fn apply(&self, g: &mut Geometry) {
        g.tm_shape = DrumShape::Line(self.line);
        g.tm_loss = DrumLoss::LossFactor(self.eta);
        for v in [&mut g.m_malleus, &mut g.i_malleus, &mut g.m_incus, &mut g.i_incus] {
            *v *= self.ossicle_mass;
        }
        g.g_sal *= self.sal_geometry;
        g.g_sal_rock *= self.sal_geometry;
    }

    /// The tissue values and viscoelastic exponent of the tuned point, every other
    /// parameter nominal.
    pub fn theta(&self) -> Theta {
        let mut t = Theta::nominal();
        for (name, v) in self.tissue {
            let i = PARAMS.iter().position(|p| p.name == name).expect("a parameter of PARAMS");
            t.0[i] = v;
        }
        t
    }
}

/// ∫₀¹ f by Simpson's rule on `n` (even) intervals.
pub fn simpson(n: usize, f: impl Fn(f64) -> f64) -> f64 {
    let weight = |k: usize| {
        if k == 0 || k == n {
            1.0
        } else if k % 2 == 1 {
            4.0
        } else {
            2.0
        }
    };
    (0..=n).map(|k| weight(k) * f(k as f64 / n as f64)).sum::<f64>() / (3.0 * n as f64)
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::f64::consts::PI;

    const D: LineDrum = LineDrum { delay: 60e-6, z0: 1.5e7, area: 45e-6, shunt: 0.0 };
    const LOSSLESS: c64 = c64 { re: E_REF, im: 0.0 };

    #[test]
    fn v6_is_point_a_at_the_reference_modulus() {
        let (a, v6) = (LineTuning::POINT_A, LineTuning::POINT_A.at_modulus(E_REF));
        let e = |t: &LineTuning| t.tissue[0].1;
        assert_eq!(e(&v6), E_REF);
        let tuned = LineTuning::v7().theta();
        assert!(tuned.0.iter().zip(&PARAMS).all(|(v, p)| p.contains(*v)), "v7's tuned ear is inside the prior box");
        // The same ear: every block entry agrees at each modulus (lossy, frequency-varying).
        for (f, eta) in [(300.0, 0.46), (2000.0, 0.1), (7500.0, 1.0)] {
            let w = 2.0 * PI * f;
            let k = |e: f64| c64::new(e, e * eta);
            let (x, y) = (a.line.block(k(e(&a)), w, 1e12), v6.line.block(k(e(&v6)), w, 1e12));
            for (p, q) in x.iter().zip(&y) {
                assert!((p - q).norm() <= 1e-9 * p.norm().max(1e-30), "{f} Hz: {p} vs {q}");
            }
        }
    }

    #[test]
    fn lossless_line_input_impedance_is_the_textbook_formula() {
        // Z_in = Z₀(Z_L + jZ₀ tan ωτ)/(Z₀ + jZ_L tan ωτ), written here from the textbook.
        for f in [300.0, 1000.0, 2500.0, 4166.0, 7000.0] {
            let w = 2.0 * PI * f;
            for zl in [c64::new(3e6, -2e7), c64::new(4e7, 1e7), c64::new(0.0, 5e6)] {
                let t = c64::new(0.0, (w * D.delay).tan());
                let want = D.z0 * (zl + t * D.z0) / (D.z0 + t * zl);
                let got = D.input_impedance(LOSSLESS, w, zl);
                assert!((got - want).norm() < 1e-9 * want.norm(), "{f} Hz, Z_L {zl}: {got} vs {want}");
            }
        }
    }

    #[test]
    fn matched_line_has_z0_input_and_delays_by_tau() {
        for f in [500.0, 2000.0, 6000.0] {
            let w = 2.0 * PI * f;
            let zin = D.input_impedance(LOSSLESS, w, c64::new(D.z0, 0.0));
            assert!((zin - D.z0).norm() < 1e-9 * D.z0, "{f} Hz: {zin}");
            // Matched: P₂/P₁ = e^{−jωτ}; its group delay −dφ/dω is τ.
            let ratio = |w: f64| {
                let [a, b, _, _] = D.abcd(LOSSLESS, w);
                1.0 / (a + b / D.z0)
            };
            let dw = 1e-3 * w;
            let gd = -(ratio(w + dw) / ratio(w - dw)).arg() / (2.0 * dw);
            assert!((gd - D.delay).abs() < 1e-9, "{f} Hz: group delay {gd} s");
            assert!((ratio(w).norm() - 1.0).abs() < 1e-12);
        }
    }

    #[test]
    fn a_stiffer_drum_carries_a_faster_wave_with_a_higher_impedance() {
        // E = 4·E_ref: the delay halves and Z_c doubles (wave speed ∝ √E, mass fixed).
        let w = 2.0 * PI * 3000.0;
        let (g1, z1) = D.constants(LOSSLESS, w);
        let (g4, z4) = D.constants(LOSSLESS * 4.0, w);
        assert!((g1.im - w * D.delay).abs() < 1e-12 && (g4.im - 0.5 * w * D.delay).abs() < 1e-12, "{g1} {g4}");
        assert!((z1.re - D.z0).abs() < 1e-6 && (z4.re - 2.0 * D.z0).abs() < 1e-6, "{z1} {z4}");
    }

    #[test]
    fn the_two_port_is_reciprocal_and_its_block_says_so() {
        // AD − BC = 1, and the force per unit P₁ with the umbo held equals the volume
        // velocity per unit umbo velocity with P₁ = 0, for lossy moduli too.
        let drum = LineDrum { shunt: 5e-13, ..D };
        for (f, kappa) in [(800.0, c64::new(5e6, 2e6)), (3000.0, c64::new(2e7, 6e6)), (7500.0, c64::new(1e8, 0.0))] {
            let w = 2.0 * PI * f;
            let [a, b, c, d] = drum.abcd(kappa, w);
            assert!((a * d - b * c - 1.0).norm() < 1e-9, "{f} Hz: det {}", a * d - b * c);
            let blk = drum.block(kappa, w, 0.0);
            let force_per_p = -blk[1]; // umbo row, p_drum column: −F
            let flow_per_v = blk[3] / c64::new(0.0, w); // flow row, umbo column (×jω)
            assert!((force_per_p - flow_per_v).norm() < 1e-12 * force_per_p.norm(), "{f} Hz");
            let p = drum.ports(kappa, w, c64::new(1.0, 0.3), c64::new(-2e-9, 1e-9));
            assert!(
                (p.u1 + p.u_shunt - (blk[3] / c64::new(0.0, w) * c64::new(-2e-9, 1e-9) + blk[4] * c64::new(1.0, 0.3)))
                    .norm()
                    < 1e-9 * p.u1.norm()
            );
        }
    }

    #[test]
    fn distributed_loss_equals_port_power_difference_and_is_not_negative() {
        // ½Re(P̄₁(U₁ + U_s)) − ½Re(P̄₂U₂) = the Simpson integral of the distributed loss,
        // ≥ 0 for Im κ ≥ 0, 0 for a lossless drum.
        let drum = LineDrum { shunt: 5e-13, ..D };
        for (f, kappa) in [(800.0, c64::new(5e6, 2e6)), (3000.0, c64::new(2e7, 6e6)), (7500.0, LOSSLESS)] {
            let w = 2.0 * PI * f;
            let (p1, v) = (c64::new(1.0, 0.3), c64::new(-2e-9, 1e-9));
            let ports = drum.ports(kappa, w, p1, v);
            let port = 0.5 * (p1.conj() * (ports.u1 + ports.u_shunt)).re - 0.5 * (ports.p2.conj() * ports.u2).re;
            let loss = drum.loss(kappa, w, p1, v);
            let scale = 0.5 * (p1.norm() * (ports.u1 + ports.u_shunt).norm() + ports.p2.norm() * ports.u2.norm());
            assert!(loss >= -1e-15 * scale, "{f} Hz: loss {loss}");
            assert!((port - loss).abs() < 1e-6 * scale, "{f} Hz: ports {port} vs distributed {loss}");
        }
    }
}
