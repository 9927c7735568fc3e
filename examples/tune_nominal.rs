//! Searches the nominal ear for a point that meets the v4 normative targets at once:
//! stapes V/P within ±5 dB of Goode 1994, phase at 8 kHz in [−450°, −250°], group delay
//! 60–150 µs at 2–8 kHz, absorbance inside the adult 10–90 % range, cochlear share ≥ 30 %
//! at 1–4 kHz. The knobs (`KNOBS`) are the seven tissue values, bounded by their normal
//! ranges (src/npe/normal.rs), the drum's loss factor and viscoelastic exponent n, and two
//! structural factors (ossicle masses, SAL geometry); the cost is a sum of squared hinge distances to the targets
//! (each target counts 1 per its tolerance unit), minimised by Nelder–Mead from the
//! current nominal and from random starts. Exploration only: docs/simulator.md records
//! what it found.
//!
//! `cargo run --example tune_nominal -- [rings] [starts] [iterations]`, ~1 ms per
//! evaluation. Environment: `DRUM=axi` the default (axisymmetric, Rayleigh) drum instead
//! of the manubrium drum; `DRUM=line` the transmission-line drum (`sim::line_drum`, session
//! 12), whose delay, characteristic impedance, coupling area and shunt compliance are then
//! knobs 11–14 (held at `LineDrum::NOMINAL` for the other drums; `rings` is then unused),
//! with the loss factor η of knob 1 on its modulus; `FIX=7,9` holds those knobs at today's value; `W_SHARE=0` drops
//! the cochlear-share target; `W_ZEC=1` adds the live-adult |Z_ec| and phase ranges at
//! 250–2000 Hz (normative.json `zec`; off by default); `SHARE_MIN=a,b,c` sets its floors at 1, 2 and 4 kHz (default
//! 0.33 each; the norms cap the share at ~0.15 and ~0.03 at 2 and 4 kHz, docs/simulator.md); `THICK`, `DEPTH`, `GAP` comma lists of drum thickness,
//! depth and manubrium-to-rim gap (m) to search over; `VISCO` the drum's viscoelastic
//! exponent; `X0` a start point.

use otofit::npe::normal::NORMAL;
use otofit::sim::line_drum::LineDrum;
use otofit::sim::{DrumLoss, DrumShape, Effects, Geometry, Model, ModelConfig, PARAMS, Theta};
use serde_json::Value;
use std::f64::consts::PI;

/// The published norms the baseline tests use.
const NORMATIVE: &str = include_str!("../reference/normative.json");

/// Goode 1994's frequencies and values, and the adult absorbance range's frequencies,
/// low and high ends, from reference/normative.json.
struct Norms {
    goode_f: Vec<f64>,
    goode_v: Vec<f64>,
    abs_f: Vec<f64>,
    abs_lo: Vec<f64>,
    abs_hi: Vec<f64>,
    /// Live-adult |Z_ec| (Pa·s/m³) and phase (degrees) ranges at the measurement plane.
    zec_f: Vec<f64>,
    zec_mag: Vec<(f64, f64)>,
    zec_phase: Vec<(f64, f64)>,
}

impl Norms {
    fn load() -> Result<Norms, String> {
        let n: Value = serde_json::from_str(NORMATIVE).map_err(|e| format!("reference/normative.json: {e}"))?;
        let floats = |v: &Value| -> Vec<f64> { v.as_array().into_iter().flatten().filter_map(Value::as_f64).collect() };
        let (g, a, z) = (&n["vst_goode1994"], &n["absorbance"], &n["zec"]);
        let pairs =
            |lo: &str, hi: &str| -> Vec<(f64, f64)> { floats(&z[lo]).into_iter().zip(floats(&z[hi])).collect() };
        Ok(Norms {
            goode_f: floats(&g["frequency_hz"]),
            goode_v: floats(&g["value"]),
            abs_f: floats(&a["frequency_hz"]),
            abs_lo: floats(&a["low"]),
            abs_hi: floats(&a["high"]),
            zec_f: floats(&z["frequency_hz"]),
            zec_mag: pairs("mag_low", "mag_high"),
            zec_phase: pairs("phase_low_deg", "phase_high_deg"),
        })
    }
}

/// One knob: its name, its search box and its start (today's nominal ear).
struct Knob {
    name: &'static str,
    lo: f64,
    hi: f64,
    start: f64,
}

/// The knobs in order: log10 of the value for the tissue parameters (inside their normal
/// ranges) and the drum's loss factor, log10 of a factor for the structural constants,
/// the viscoelastic exponent as is. Each starts at today's nominal ear.
fn knobs() -> Vec<Knob> {
    let tissue = |name: &'static str| {
        let r = NORMAL.iter().find(|r| r.name == name).expect("a tissue parameter has a normal range");
        let p = PARAMS.iter().find(|p| p.name == name).expect("a tissue parameter");
        Knob { name, lo: r.low.log10(), hi: r.high.log10(), start: p.nominal.log10() }
    };
    vec![
        tissue("E_eardrum"),
        Knob { name: "drum eta", lo: -2.0, hi: 0.0, start: -1.0 },
        tissue("damping_beta"),
        tissue("cochlear_load"),
        tissue("E_sal"),
        tissue("E_ligaments"),
        tissue("E_joints"),
        Knob { name: "ossicle mass x", lo: -0.3, hi: 0.3, start: 0.0 },
        tissue("E_tendons"),
        Knob { name: "g_sal x", lo: -1.0, hi: 1.0, start: 0.0 },
        Knob { name: "tm_viscoelastic n", lo: 0.0, hi: 0.3, start: 0.0 },
        // The line drum (DRUM=line): delay 10–200 µs (the cat's drum ~36 µs, Puria & Allen
        // 1998; the human middle ear's whole group delay 60–150 µs), Z₀ 3e6–1e8 Pa·s/m³
        // around |Z_TM| ≈ 2e7 near 1 kHz, area 20–60 mm² (Hudde's A₀ 38 mm² of 60 mm²),
        // shunt compliance 3e-14–3e-11 m³/Pa (0.005–4 cm³ of air).
        Knob { name: "line delay s", lo: -5.0, hi: (200e-6f64).log10(), start: LineDrum::NOMINAL.delay.log10() },
        Knob { name: "line Z0", lo: (3e6f64).log10(), hi: 8.0, start: LineDrum::NOMINAL.z0.log10() },
        Knob {
            name: "line area m2",
            lo: (20e-6f64).log10(),
            hi: (60e-6f64).log10(),
            start: LineDrum::NOMINAL.area.log10(),
        },
        Knob { name: "line shunt m3/Pa", lo: -13.5, hi: -10.5, start: LineDrum::NOMINAL.shunt.log10() },
    ]
}

/// The line drum's knobs (delay, Z₀, area, shunt).
const LINE_KNOBS: [usize; 4] = [11, 12, 13, 14];

/// What the environment asks for, read once (module doc).
struct Settings {
    axisymmetric: bool,
    line: bool,
    fixed: Vec<usize>,
    w_share: f64,
    w_zec: f64,
    share_min: [f64; 3],
    visco: Option<f64>,
    x0: Option<Vec<f64>>,
    thick: Vec<f64>,
    depth: Vec<f64>,
    gap: Vec<f64>,
}

/// A comma list of numbers from environment variable `name`, or `default`.
fn env_list<T: std::str::FromStr>(name: &str, default: &str) -> Result<Vec<T>, String> {
    let text = std::env::var(name).unwrap_or_else(|_| default.to_string());
    text.split(',')
        .filter(|s| !s.trim().is_empty())
        .map(|s| s.trim().parse().map_err(|_| format!("{name}: '{}' is not a number", s.trim())))
        .collect()
}

impl Settings {
    fn from_env(n_knobs: usize) -> Result<Settings, String> {
        let one = |name: &str| -> Result<Option<f64>, String> { Ok(env_list::<f64>(name, "")?.first().copied()) };
        let mut fixed: Vec<usize> = env_list("FIX", "")?;
        let line = std::env::var("DRUM").as_deref() == Ok("line");
        if !line {
            fixed.extend(LINE_KNOBS);
        }
        if let Some(k) = fixed.iter().find(|&&k| k >= n_knobs) {
            return Err(format!("FIX: knob {k} does not exist (0..{n_knobs})"));
        }
        let x0 = std::env::var("X0").is_ok().then(|| env_list::<f64>("X0", "")).transpose()?;
        if let Some(x) = x0.as_ref().filter(|x| x.len() != n_knobs) {
            return Err(format!("X0: {} values, need {n_knobs}", x.len()));
        }
        Ok(Settings {
            axisymmetric: std::env::var("DRUM").as_deref() == Ok("axi"),
            line,
            fixed,
            w_share: one("W_SHARE")?.unwrap_or(1.0),
            w_zec: one("W_ZEC")?.unwrap_or(0.0),
            share_min: match env_list::<f64>("SHARE_MIN", "0.33,0.33,0.33")?[..] {
                [a, b, c] => [a, b, c],
                _ => return Err("SHARE_MIN: three values, at 1, 2 and 4 kHz".into()),
            },
            visco: one("VISCO")?,
            x0,
            thick: env_list("THICK", "60e-6")?,
            depth: env_list("DEPTH", "2e-3")?,
            gap: env_list("GAP", "1e-3")?,
        })
    }
}

struct Metrics {
    goode: Vec<f64>,
    phase8: f64,
    delay: [f64; 4],
    /// Least and largest group delay over 25 log-spaced frequencies from 2 to 8 kHz, µs.
    delay_band: (f64, f64),
    absorb: Vec<f64>,
    share: [f64; 3],
    split: Vec<[f64; 5]>,
    /// |Z_ec| and its phase (degrees) at the normative impedance frequencies.
    zec: Vec<(f64, f64)>,
}

fn hinge(v: f64, lo: f64, hi: f64) -> f64 {
    if v < lo {
        lo - v
    } else if v > hi {
        v - hi
    } else {
        0.0
    }
}

impl Metrics {
    fn cost(&self, norms: &Norms, w_share: f64, share_min: [f64; 3], w_zec: f64) -> f64 {
        let mut c = 0.0;
        for d in &self.goode {
            c += hinge(*d, -4.0, 4.0).powi(2) + 0.02 * d * d;
        }
        c += (hinge(self.phase8, -430.0, -270.0) / 20.0).powi(2);
        for d in self.delay {
            c += (hinge(d, 65.0, 140.0) / 15.0).powi(2);
        }
        for (k, a) in self.absorb.iter().enumerate() {
            c += (hinge(*a, norms.abs_lo[k] + 0.02, norms.abs_hi[k] - 0.02) / 0.05).powi(2);
        }
        for (s, lo) in self.share.iter().zip(share_min) {
            c += w_share * (hinge(*s, lo, 1.0) / 0.05).powi(2);
        }
        // |Z_ec| in dB outside its range per dB, the phase per 5°.
        for ((m, p), ((mlo, mhi), (plo, phi))) in self.zec.iter().zip(norms.zec_mag.iter().zip(&norms.zec_phase)) {
            let db = |v: f64| 20.0 * v.log10();
            c += w_zec * (hinge(db(*m), db(*mlo), db(*mhi)).powi(2) + (hinge(*p, *plo, *phi) / 5.0).powi(2));
        }
        c
    }
    fn print(&self) {
        let f = |v: &[f64], p: usize| v.iter().map(|x| format!("{x:.p$}")).collect::<Vec<_>>().join(" ");
        println!("  goode diff dB: {}", f(&self.goode, 1));
        println!("  phase 8k {:.0}, delay 2/3/4/8k {} us", self.phase8, f(&self.delay, 0));
        println!("  group delay over 2-8 kHz: {:.0} to {:.0} us", self.delay_band.0, self.delay_band.1);
        println!("  absorbance: {}", f(&self.absorb, 2));
        println!("  cochlear share 1/2/4k: {}", f(&self.share, 2));
        for (z, hz) in self.zec.iter().zip([250, 500, 1000, 2000]) {
            println!("  zec {hz} Hz: {:.3e} Pa·s/m³ {:.0}°", z.0, z.1);
        }
        for s in &self.split {
            println!("  split drum/lig+tend/joints/sal/cochlea: {}", f(s, 3));
        }
    }
}

/// Everything one evaluation needs: the norms, the knobs, the settings.
struct Search {
    norms: Norms,
    knobs: Vec<Knob>,
    settings: Settings,
}

impl Search {
    /// The ear at knob values `x` (inside the knobs' boxes).
    fn apply(&self, x: &[f64], base_g: &Geometry, shape: DrumShape) -> (Geometry, Theta) {
        let mut g = base_g.clone();
        let mut t = Theta::nominal();
        let m = |i: usize| 10f64.powf(x[i]);
        for (k, knob) in self.knobs.iter().enumerate() {
            if let Some(i) = PARAMS.iter().position(|p| p.name == knob.name) {
                t.0[i] = m(k);
            }
        }
        g.tm_loss = DrumLoss::LossFactor(m(1));
        for v in [&mut g.m_malleus, &mut g.i_malleus, &mut g.m_incus, &mut g.i_incus] {
            *v *= m(7);
        }
        t.0[11] = self.settings.visco.unwrap_or(x[10]);
        g.g_sal *= m(9);
        g.g_sal_rock *= m(9);
        g.tm_shape = shape;
        if self.settings.line {
            g.tm_shape = DrumShape::Line(LineDrum { delay: m(11), z0: m(12), area: m(13), shunt: m(14) });
        }
        if self.settings.axisymmetric {
            g.tm_shape = DrumShape::Axisymmetric;
            g.tm_loss = DrumLoss::Rayleigh;
        }
        (g, t)
    }

    fn metrics(&self, g: Geometry, t: &Theta) -> Option<Metrics> {
        let config = ModelConfig { geometry: g, ..ModelConfig::default() };
        let model = Model::new(config).ok()?;
        let mut r = model.runner();
        let fx = Effects::default();
        let mut resp = |f: f64| r.response_at(t, &fx, f).ok();
        let n = &self.norms;
        let mut goode = Vec::with_capacity(n.goode_f.len());
        for (f, v) in n.goode_f.iter().zip(&n.goode_v) {
            goode.push(20.0 * (resp(*f)?.vst_over_p.norm().log10() + 3.0) - v);
        }
        // Unwrapped phase at 8 kHz: follow the grid.
        let mut prev = resp(200.0)?.vst_over_p;
        let mut phase = prev.arg();
        for f in otofit::sim::model::log_grid(200.0, 8000.0, 200).into_iter().skip(1) {
            let v = resp(f)?.vst_over_p;
            phase += (v / prev).arg();
            prev = v;
        }
        let mut group_delay = |f: f64| -> Option<f64> {
            let d = (resp(1.005 * f)?.vst_over_p / resp(0.995 * f)?.vst_over_p).arg();
            Some(-d / (2.0 * PI * 0.01 * f) * 1e6)
        };
        let mut delay = [0.0; 4];
        for (k, f) in [2000.0, 3000.0, 4000.0, 8000.0].iter().enumerate() {
            delay[k] = group_delay(*f)?;
        }
        let mut delay_band = (f64::INFINITY, f64::NEG_INFINITY);
        for f in otofit::sim::model::log_grid(2000.0, 8000.0, 25) {
            let d = group_delay(f)?;
            delay_band = (delay_band.0.min(d), delay_band.1.max(d));
        }
        let mut absorb = Vec::with_capacity(n.abs_f.len());
        for f in &n.abs_f {
            absorb.push(resp(*f)?.absorbance());
        }
        let mut zec = Vec::with_capacity(n.zec_f.len());
        for f in &n.zec_f {
            let z = resp(*f)?.zec;
            zec.push((z.norm(), z.arg().to_degrees()));
        }
        let mut share = [0.0; 3];
        let mut split = Vec::new();
        for (k, f) in [1000.0, 2000.0, 4000.0].iter().enumerate() {
            r.solve_at(t, *f).ok()?;
            let p = r.power_balance(t, *f);
            share[k] = p.cochlear_share();
            let d = p.into_drum;
            split.push([p.drum / d, (p.ligaments + p.tendons) / d, p.joints / d, p.sal / d, p.cochlea / d]);
        }
        Some(Metrics { goode, phase8: phase.to_degrees(), delay, delay_band, absorb, share, split, zec })
    }

    /// `x` with the fixed knobs at today's value.
    fn with_fixed(&self, x: &[f64]) -> Vec<f64> {
        let mut x = x.to_vec();
        for &k in &self.settings.fixed {
            x[k] = self.knobs[k].start;
        }
        x
    }

    /// `x` clamped into the knobs' boxes.
    fn clamped(&self, x: &[f64]) -> Vec<f64> {
        x.iter().zip(&self.knobs).map(|(v, k)| v.clamp(k.lo, k.hi)).collect()
    }

    fn cost(&self, x: &[f64], g: &Geometry, shape: DrumShape) -> f64 {
        let x = self.with_fixed(x);
        let out: f64 = x.iter().zip(&self.knobs).map(|(v, k)| hinge(*v, k.lo, k.hi)).sum();
        let (g2, t) = self.apply(&self.clamped(&x), g, shape);
        self.metrics(g2, &t)
            .map(|m| m.cost(&self.norms, self.settings.w_share, self.settings.share_min, self.settings.w_zec))
            .unwrap_or(1e9)
            + 100.0 * out
    }
}

fn nelder_mead(f: &dyn Fn(&[f64]) -> f64, x0: Vec<f64>, step: f64, iters: usize) -> (Vec<f64>, f64) {
    let n = x0.len();
    let mut pts: Vec<(Vec<f64>, f64)> = Vec::new();
    pts.push((x0.clone(), f(&x0)));
    for i in 0..n {
        let mut x = x0.clone();
        x[i] += step;
        let v = f(&x);
        pts.push((x, v));
    }
    for _ in 0..iters {
        pts.sort_by(|a, b| a.1.total_cmp(&b.1));
        let centroid: Vec<f64> = (0..n).map(|j| pts[..n].iter().map(|p| p.0[j]).sum::<f64>() / n as f64).collect();
        let worst = pts[n].clone();
        let along = |t: f64| -> Vec<f64> { (0..n).map(|j| centroid[j] + t * (worst.0[j] - centroid[j])).collect() };
        let xr = along(-1.0);
        let fr = f(&xr);
        if fr < pts[0].1 {
            let xe = along(-2.0);
            let fe = f(&xe);
            pts[n] = if fe < fr { (xe, fe) } else { (xr, fr) };
        } else if fr < pts[n - 1].1 {
            pts[n] = (xr, fr);
        } else {
            let xc = along(0.5);
            let fc = f(&xc);
            if fc < worst.1 {
                pts[n] = (xc, fc);
            } else {
                let best = pts[0].0.clone();
                for p in pts.iter_mut().skip(1) {
                    let x: Vec<f64> = (0..n).map(|j| best[j] + 0.5 * (p.0[j] - best[j])).collect();
                    *p = (x.clone(), f(&x));
                }
            }
        }
    }
    pts.sort_by(|a, b| a.1.total_cmp(&b.1));
    pts.swap_remove(0)
}

fn main() -> Result<(), String> {
    let args: Vec<String> = std::env::args().collect();
    let arg = |i: usize, name: &str, default: usize| -> Result<usize, String> {
        args.get(i).map_or(Ok(default), |s| s.parse().map_err(|_| format!("{name}: '{s}' is not a count")))
    };
    let (rings, starts, iters) = (arg(1, "rings", 12)?, arg(2, "starts", 4)?, arg(3, "iterations", 600)?);
    let knobs = knobs();
    let settings = Settings::from_env(knobs.len())?;
    let search = Search { norms: Norms::load()?, knobs, settings };
    let start: Vec<f64> = search.settings.x0.clone().unwrap_or_else(|| search.knobs.iter().map(|k| k.start).collect());
    let mut overall: Option<(f64, Vec<f64>, Geometry, DrumShape)> = None;
    for &h in &search.settings.thick {
        for &depth in &search.settings.depth {
            for &gap in &search.settings.gap {
                let g = Geometry { tm_thickness: h, tm_depth: depth, ..Geometry::axisymmetric() };
                let shape = DrumShape::Manubrium { rings, manubrium_to_rim: gap };
                let f = |x: &[f64]| search.cost(x, &g, shape);
                let mut seed = 12345u64;
                let mut rnd = || {
                    seed ^= seed << 13;
                    seed ^= seed >> 7;
                    seed ^= seed << 17;
                    (seed >> 11) as f64 / (1u64 << 53) as f64
                };
                let mut best: Option<(Vec<f64>, f64)> = None;
                for s in 0..starts {
                    let x0: Vec<f64> = if s == 0 {
                        start.clone()
                    } else {
                        search.knobs.iter().map(|k| k.lo + (k.hi - k.lo) * rnd()).collect()
                    };
                    let (mut x, mut v) = nelder_mead(&f, x0, 0.3, iters);
                    let (x2, v2) = nelder_mead(&f, x.clone(), 0.1, iters);
                    if v2 < v {
                        (x, v) = (x2, v2);
                    }
                    if best.as_ref().is_none_or(|b| v < b.1) {
                        best = Some((x, v));
                    }
                }
                let Some((x, v)) = best else { return Err("starts: must be at least 1".into()) };
                println!(
                    "h {:.0} um, depth {:.2} mm, gap {:.2} mm: cost {v:.2}  knobs {}",
                    h * 1e6,
                    depth * 1e3,
                    gap * 1e3,
                    x.iter().map(|v| format!("{v:.2}")).collect::<Vec<_>>().join(" ")
                );
                if overall.as_ref().is_none_or(|o| v < o.0) {
                    overall = Some((v, x, g.clone(), shape));
                }
            }
        }
    }
    let Some((v, x, g, shape)) = overall else { return Err("THICK, DEPTH, GAP: each needs a value".into()) };
    let x = search.with_fixed(&x);
    let shape = if search.settings.line { search.apply(&search.clamped(&x), &g, shape).0.tm_shape } else { shape };
    println!("best cost {v:.3}: thickness {:.0} um, depth {:.2} mm, {shape:?}", g.tm_thickness * 1e6, g.tm_depth * 1e3);
    for (k, knob) in search.knobs.iter().enumerate() {
        let (name, lo, hi) = (knob.name, knob.lo, knob.hi);
        if k == 10 {
            println!("  {name:16} {:.3}  [{lo:.3}, {hi:.3}]", x[k]);
        } else {
            println!("  {name:16} log10 {:+.3}  ({:.4e})  [{lo:.3}, {hi:.3}]", x[k], 10f64.powf(x[k]));
        }
    }
    let (g2, t) = search.apply(&search.clamped(&x), &g, shape);
    if let Some(m) = search.metrics(g2.clone(), &t) {
        m.print();
    }
    // Cost per simulation at the best point: 1000 runs of the 50-frequency grid, one core.
    let model = Model::new(ModelConfig { geometry: g2, ..ModelConfig::default() }).map_err(|e| e.to_string())?;
    let mut runner = model.runner();
    let clock = std::time::Instant::now();
    for _ in 0..1000 {
        otofit::sim::simulate(&mut runner, &t, &Effects::default()).map_err(|e| e.to_string())?;
    }
    println!("  cost per 50-frequency run: {:.3} ms (1000 runs)", clock.elapsed().as_secs_f64());
    Ok(())
}
