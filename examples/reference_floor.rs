//! How low can the reference ear's χ² go if the line drum's fixed structure is freed too?
//! `otofit study reference` fits the 14 inferred parameters by least squares inside their
//! prior boxes (χ²ν 7.76 on v7); the drum's structural constants — the line's delay τ,
//! characteristic impedance Z₀, coupling area S and shunt compliance C_s (at E_ref), the
//! drum's loss factor η, the ossicle-mass and annular-ligament-geometry factors — stay at
//! `LineTuning::v7()`. Here they are columns of the same Levenberg–Marquardt fit
//! (`discrepancy::fit::fit_columns`, the study's χ²: the reference ear's features, its
//! test–retest STD, the absent umbo features left out), each inside the box
//! `examples/tune_nominal.rs` searched (docs/simulator.md, "A transmission-line drum").
//!
//! Variants (docs/simulator.md, "Known gaps"): `params` the 14 parameters only (the
//! study's fit); `structure` the 14 and the seven structural constants; `normal` the same
//! with the six tissue values other than E_eardrum inside their normal ranges
//! (`npe::normal::NORMAL`); `wide` as `structure` with every structural box widened ×3 at
//! both ends (the shunt's floor to 1e-17 m³/Pa), to see whether a box binds; `loose` as `wide` with the prior's
//! boxes widened ×3 too (not ldv_angle's and n's), the model's form unbounded;
//! `loosen=NAME,…` as `structure` with only the named columns in `loose`'s boxes. With the line free E_eardrum is held at E_ref: it reaches the
//! ear only through the line (τ·√(E_ref/E), Z₀·√(E/E_ref), C_s·E_ref/E), so freeing both
//! is one degenerate direction and would void the line's boxes.
//!
//! Starts: the v7 nominal ear; the default model's MAP and four posterior draws (seed 0,
//! as the study); for the structural variants also the `params` fit's best row; and
//! `random` rows uniform in the free columns' boxes. Each start runs `iterations`
//! Levenberg–Marquardt steps, restarted from where it stopped while that gains > 0.1 %
//! (at most 8 times).
//!
//! `cargo run --example reference_floor -- [iterations] [random] [variant… | loosen=NAME,…] [explain]`
//! (defaults 200, 4, every variant; ~1 s per start); `explain` prints each variant's best
//! ear, and the nominal row on its structure, against the published norms (`otofit
//! simulate --explain`'s report).

use otofit::discrepancy::fit::{Fit, Observation, feature_residual, fit_columns, residuals};
use otofit::npe::normal::NORMAL;
use otofit::npe::{Npe, Obs};
use otofit::sim::batch::Design;
use otofit::sim::line_drum::{E_REF, LineDrum, LineTuning};
use otofit::sim::output::MEASURES;
use otofit::sim::params::{ParamSpec, Scale};
use otofit::sim::{Effects, Geometry, Model, ModelConfig, N_PARAMS, PARAMS, Theta, simulate};

type Error = Box<dyn std::error::Error>;

/// The drum's structural constants, the columns after the 14 parameters, in
/// `examples/tune_nominal.rs`'s boxes: τ 10–200 µs (the cat drum's ~36 µs, Puria & Allen
/// 1998; the human middle ear's whole group delay 60–150 µs), Z₀ 3e6–1e8 Pa·s/m³ (|Z_TM|
/// ≈ 2e7 near 1 kHz), S 20–60 mm² (Hudde's A₀ 38 mm² of 60 mm²), C_s 10^−13.5–10^−10.5
/// m³/Pa (0.005–4 cm³ of air), η 0.01–1 (physics-notes §2: 0.02–1, Homma 0.15–0.7),
/// ossicle masses and SAL geometry ×10^±0.3 and ×0.1–10 (the session-11 search's boxes;
/// the notes' malleus + incus 45–60 mg is ×0.85–1.13, v7's ×1.73 is already outside it).
/// Nominal: v7's.
fn structure_columns() -> Vec<ParamSpec> {
    let v7 = LineTuning::v7();
    let c = |name, unit, low, high, nominal| ParamSpec { name, unit, scale: Scale::Log10, low, high, nominal };
    vec![
        c("line_delay", "s", 10e-6, 200e-6, v7.line.delay),
        c("line_z0", "Pa·s/m³", 3e6, 1e8, v7.line.z0),
        c("line_area", "m²", 20e-6, 60e-6, v7.line.area),
        c("line_shunt", "m³/Pa", 10f64.powf(-13.5), 10f64.powf(-10.5), v7.line.shunt),
        c("drum_eta", "1", 0.01, 1.0, v7.eta),
        c("ossicle_mass", "×", 10f64.powf(-0.3), 10f64.powf(0.3), v7.ossicle_mass),
        c("sal_geometry", "×", 0.1, 10.0, v7.sal_geometry),
    ]
}

/// The simulator's geometry for structural values `s` (in `structure_columns` order).
fn geometry(s: &[f64]) -> Geometry {
    let mut g = Geometry::axisymmetric();
    let line = LineDrum { delay: s[0], z0: s[1], area: s[2], shunt: s[3] };
    LineTuning { line, eta: s[4], ossicle_mass: s[5], sal_geometry: s[6], ..LineTuning::v7() }.apply(&mut g);
    g
}

/// The reference ear and a one-model cache: a fit's Jacobian moves the structure in only
/// 7 of its columns, so most evaluations reuse the last model.
struct Ear {
    obs: Observation,
    cache: Option<(Vec<f64>, Model)>,
}

/// The model for structural values `s`, built unless it is the cached one.
fn cached<'a>(cache: &'a mut Option<(Vec<f64>, Model)>, structure: &[f64]) -> Option<&'a Model> {
    if cache.as_ref().is_none_or(|(s, _)| s != structure) {
        let config = ModelConfig { geometry: geometry(structure), ..ModelConfig::default() };
        *cache = Some((structure.to_vec(), Model::new(config).ok()?));
    }
    cache.as_ref().map(|c| &c.1)
}

impl Ear {
    /// The study's standardised residuals of a full row (14 parameters, 7 structural).
    fn residuals(&mut self, row: &[f64]) -> Option<Vec<f64>> {
        let model = cached(&mut self.cache, &row[N_PARAMS..])?;
        residuals(&mut model.runner(), &Design::default(), &row[..N_PARAMS], &self.obs)
    }

    fn features(&mut self, row: &[f64]) -> Option<Vec<f64>> {
        let model = cached(&mut self.cache, &row[N_PARAMS..])?;
        let theta = Theta(std::array::from_fn(|i| row[i]));
        simulate(&mut model.runner(), &theta, &Effects::default()).ok()
    }
}

/// Levenberg–Marquardt restarts after the first run, at most.
const ROUNDS: usize = 8;

/// Which columns of the full row a variant fits, and in which boxes.
struct Variant {
    name: &'static str,
    /// Indices into the full row (14 parameters, then the structure).
    free: Vec<usize>,
    /// One box per full-row column (the fixed ones unused).
    boxes: Vec<ParamSpec>,
}

fn variants(loosen: &[&str]) -> Vec<Variant> {
    let full: Vec<ParamSpec> = PARAMS.iter().copied().chain(structure_columns()).collect();
    let normal: Vec<ParamSpec> = full
        .iter()
        .map(|p| match NORMAL.iter().find(|r| r.name == p.name) {
            Some(r) => ParamSpec { low: r.low, high: r.high, ..*p },
            None => *p,
        })
        .collect();
    // Past the plausible boxes: does any structural box bind? (The shunt's floor goes to
    // 1e-17 m³/Pa, practically no shunt.)
    let wide: Vec<ParamSpec> = full
        .iter()
        .enumerate()
        .map(|(i, p)| match i.checked_sub(N_PARAMS) {
            Some(3) => ParamSpec { low: 1e-17, high: 3.0 * p.high, ..*p },
            Some(_) => ParamSpec { low: p.low / 3.0, high: 3.0 * p.high, ..*p },
            None => *p,
        })
        .collect();
    // And past the prior's boxes too (not ldv_angle and tm_viscoelastic, whose ranges are
    // their physical ones): how far the model's form can go at all.
    let loose: Vec<ParamSpec> = wide
        .iter()
        .enumerate()
        .map(|(i, p)| match p.name {
            "ldv_angle" | "tm_viscoelastic" => *p,
            _ if i < N_PARAMS => ParamSpec { low: p.low / 3.0, high: 3.0 * p.high, ..*p },
            _ => *p,
        })
        .collect();
    let without_e: Vec<usize> = (1..full.len()).collect();
    vec![
        Variant { name: "params", free: (0..N_PARAMS).collect(), boxes: full.clone() },
        Variant { name: "structure", free: without_e.clone(), boxes: full.clone() },
        Variant { name: "normal", free: without_e.clone(), boxes: normal },
        Variant { name: "wide", free: without_e.clone(), boxes: wide },
        Variant { name: "loose", free: without_e.clone(), boxes: loose.clone() },
        // `loosen=a,b`: `structure` with only the named columns in `loose`'s boxes.
        Variant {
            name: "loosen",
            free: without_e,
            boxes: full.iter().zip(&loose).map(|(p, l)| if loosen.contains(&p.name) { *l } else { *p }).collect(),
        },
    ]
}

/// A full row with the free columns replaced by `u`'s values.
fn full_row(template: &[f64], free: &[usize], values: &[f64]) -> Vec<f64> {
    let mut row = template.to_vec();
    for (&i, &v) in free.iter().zip(values) {
        row[i] = v;
    }
    row
}

/// The best fit of one variant, with the starts' reduced χ².
struct Best {
    row: Vec<f64>,
    fit: Fit,
    by_start: Vec<(String, f64)>,
}

fn run_variant(ear: &mut Ear, v: &Variant, starts: &[(String, Vec<f64>)], iters: usize) -> Option<Best> {
    let cols: Vec<ParamSpec> = v.free.iter().map(|&i| v.boxes[i]).collect();
    let mut best: Option<Best> = None;
    let mut by_start = Vec::new();
    for (name, start) in starts {
        let clock = std::time::Instant::now();
        let mut fit_from = |row: &[f64]| {
            let x0: Vec<f64> = v.free.iter().map(|&i| row[i]).collect();
            fit_columns(&cols, &x0, iters, |u| ear.residuals(&full_row(row, &v.free, u)))
        };
        let Some(mut fit) = fit_from(start) else {
            by_start.push((name.clone(), f64::NAN));
            continue;
        };
        let mut row = full_row(start, &v.free, &fit.row);
        let mut steps = fit.iterations;
        // Restarted while a restart gains more than 0.1 % (a restart resets the damping).
        for _ in 0..ROUNDS {
            match fit_from(&row) {
                Some(again) if again.chi2 < fit.chi2 => {
                    let gain = fit.chi2 - again.chi2;
                    (row, fit) = (full_row(start, &v.free, &again.row), again);
                    steps += fit.iterations;
                    if gain < 1e-3 * fit.chi2 {
                        break;
                    }
                }
                _ => break,
            }
        }
        eprintln!(
            "  {}: from {name}: χ²ν {:.3} ({steps} steps, {} ms)",
            v.name,
            fit.reduced_chi2(),
            clock.elapsed().as_millis()
        );
        by_start.push((name.clone(), fit.reduced_chi2()));
        if best.as_ref().is_none_or(|b| fit.chi2 < b.fit.chi2) {
            best = Some(Best { row, fit, by_start: vec![] });
        }
    }
    best.map(|b| Best { by_start, ..b })
}

/// Per measure: χ² and Spearman ρ, over the measures the reference ear holds.
fn split(ear: &mut Ear, row: &[f64]) -> Option<Vec<(&'static str, f64, f64)>> {
    let x = ear.features(row)?;
    let obs = &ear.obs;
    let n = x.len() / MEASURES.len();
    let rho = otofit::stats::spearman_per_block(&x, &obs.x, MEASURES.len());
    Some(
        (0..MEASURES.len())
            .filter(|m| obs.x[m * n..(m + 1) * n].iter().all(|v| v.is_finite()))
            .map(|m| {
                let chi2 = (m * n..(m + 1) * n)
                    .map(|i| (feature_residual(i, n, x[i], obs.x[i]) / obs.sigma[i]).powi(2))
                    .sum::<f64>();
                (MEASURES[m].name, chi2, rho[m])
            })
            .collect(),
    )
}

fn report(ear: &mut Ear, v: &Variant, b: &Best) -> Result<(), Error> {
    let f = &b.fit;
    let study_dof = f.n_features - N_PARAMS;
    println!(
        "\n== {}: χ² {:.1} over {} features, {} free: χ²ν {:.3} (over the study's {study_dof} dof: {:.3})",
        v.name,
        f.chi2,
        f.n_features,
        v.free.len(),
        f.reduced_chi2(),
        f.chi2 / study_dof as f64
    );
    let named: Vec<String> =
        b.by_start.iter().filter(|(s, _)| !s.starts_with("random")).map(|(s, c)| format!("{s} {c:.3}")).collect();
    println!("  by start: {}", named.join(", "));
    let mut random: Vec<f64> = b.by_start.iter().filter(|(s, _)| s.starts_with("random")).map(|s| s.1).collect();
    random.sort_by(f64::total_cmp);
    if !random.is_empty() {
        let least: Vec<String> = random.iter().take(6).map(|c| format!("{c:.3}")).collect();
        println!("  {} random starts: least {}; median {:.3}", random.len(), least.join(" "), random[random.len() / 2]);
    }
    let parts = split(ear, &b.row).ok_or("the best row failed to simulate")?;
    let mean_rho = parts.iter().map(|p| p.2.abs()).sum::<f64>() / parts.len() as f64;
    println!("  {:<11} {:>9} {:>7}", "measure", "χ²", "ρ");
    for (name, chi2, rho) in &parts {
        println!("  {name:<11} {chi2:>9.1} {rho:>7.3}");
    }
    println!("  mean |ρ| {mean_rho:.3}");
    for (i, p) in v.boxes.iter().enumerate() {
        let value = b.row[i];
        let note = if !v.free.contains(&i) {
            "fixed".to_string()
        } else {
            // Position in the box on its sampling scale.
            let q = match p.scale {
                Scale::Linear => (value - p.low) / (p.high - p.low),
                Scale::Log10 => (value / p.low).log10() / (p.high / p.low).log10(),
            };
            let edge = if q <= 0.01 {
                "  ON LOWER EDGE"
            } else if q >= 0.99 {
                "  ON UPPER EDGE"
            } else {
                ""
            };
            format!("box [{:.4e}, {:.4e}] at {q:.3}{edge}", p.low, p.high)
        };
        println!("  {:<16} {value:>12.5e} {:<8} {note}", p.name, p.unit);
    }
    Ok(())
}

fn main() -> Result<(), Error> {
    let args: Vec<String> = std::env::args().skip(1).collect();
    let numbers: Vec<usize> = args.iter().filter_map(|a| a.parse().ok()).collect();
    let (iters, random) = (numbers.first().copied().unwrap_or(200), numbers.get(1).copied().unwrap_or(4));
    let explain = args.iter().any(|a| a == "explain");
    let loosen: Vec<&str> = args.iter().filter_map(|a| a.strip_prefix("loosen=")).flat_map(|a| a.split(',')).collect();
    let wanted: Vec<&str> = args
        .iter()
        .map(|a| if a.starts_with("loosen=") { "loosen" } else { a.as_str() })
        .filter(|a| a.parse::<usize>().is_err())
        .collect();
    let chosen: Vec<Variant> = variants(&loosen)
        .into_iter()
        .filter(|v| (wanted.iter().all(|w| *w == "explain") && v.name != "loosen") || wanted.contains(&v.name))
        .collect();

    let freqs = ModelConfig::default().frequencies;
    let r = otofit::reference::build(&freqs)?;
    let mut ear = Ear { obs: Observation { x: r.x.clone(), sigma: r.std.clone() }, cache: None };
    let v7: Vec<f64> = structure_columns().iter().map(|p| p.nominal).collect();
    let with_v7 = |theta: &[f64]| -> Vec<f64> { theta.iter().copied().chain(v7.iter().copied()).collect() };
    // The structure columns at v7's values are the default simulator.
    let default = Model::new(ModelConfig::default())?;
    let nominal = simulate(&mut default.runner(), &Theta::nominal(), &Effects::default())?;
    let here = ear.features(&with_v7(&Theta::nominal().0)).ok_or("v7 failed to simulate")?;
    assert!(nominal.iter().zip(&here).all(|(a, b)| (a - b).abs() <= 1e-12 * a.abs().max(1.0)), "not v7's ear");

    // The study's starts: the default model's MAP and four posterior draws, seed 0.
    let npe = Npe::load(&std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("models/default.otofit"))?;
    let inf = npe.infer(&Obs { x: &r.x, present: None }, 1000, 0)?;
    let mut starts = vec![("v7 nominal".to_string(), with_v7(&Theta::nominal().0)), ("MAP".into(), with_v7(&inf.map))];
    for (k, d) in inf.samples.iter().step_by(inf.samples.len() / 4).take(4).enumerate() {
        starts.push((format!("draw {k}"), with_v7(d)));
    }
    let mut params_best: Option<Vec<f64>> = None;
    for v in &chosen {
        // Each variant draws the same random starts, whichever others run.
        let mut seed = 12345u64;
        let mut rnd = move || {
            seed ^= seed << 13;
            seed ^= seed >> 7;
            seed ^= seed << 17;
            (seed >> 11) as f64 / (1u64 << 53) as f64
        };
        let mut these = starts.clone();
        if v.free.len() > N_PARAMS {
            // The line's degeneracy: the structural variants hold E_eardrum at E_ref, so a
            // start's own modulus is moved into its line first (`LineTuning::at_modulus`).
            for (_, row) in these.iter_mut() {
                *row = at_reference_modulus(row);
            }
            if let Some(row) = &params_best {
                these.push(("params fit".into(), at_reference_modulus(row)));
            }
        }
        for k in 0..random {
            let mut row = with_v7(&Theta::nominal().0);
            for &i in &v.free {
                row[i] = v.boxes[i].from_unit(rnd());
            }
            these.push((format!("random {k}"), row));
        }
        let b = run_variant(&mut ear, v, &these, iters).ok_or("no start simulated")?;
        report(&mut ear, v, &b)?;
        if v.name == "params" {
            params_best = Some(b.row.clone());
        }
        if explain {
            // The fitted ear, then the prior's nominal row (v7's tissue, nominal canal and
            // microphone) on the fitted structure.
            for (which, theta) in
                [("fitted row", Theta(std::array::from_fn(|i| b.row[i]))), ("nominal row", Theta::nominal())]
            {
                println!("\n  -- {}: {which} against the norms (otofit simulate --explain's report)", v.name);
                let config = ModelConfig { geometry: geometry(&b.row[N_PARAMS..]), ..ModelConfig::default() };
                otofit::cli::explain::report(config, &theta, &Effects::default())?;
            }
        }
    }
    Ok(())
}

/// The same ear with E_eardrum = E_ref, its line rescaled (`LineTuning::at_modulus`).
fn at_reference_modulus(row: &[f64]) -> Vec<f64> {
    let s = &row[N_PARAMS..];
    let line = LineDrum { delay: s[0], z0: s[1], area: s[2], shunt: s[3] };
    let mut tuning = LineTuning { line, ..LineTuning::v7() };
    tuning.tissue[0].1 = row[0];
    let t = tuning.at_modulus(E_REF);
    let mut out = row.to_vec();
    out[0] = E_REF;
    out[N_PARAMS..N_PARAMS + 4].copy_from_slice(&[t.line.delay, t.line.z0, t.line.area, t.line.shunt]);
    out
}
