//! `otofit simulate --explain`: one ear's responses against the published norms the
//! baseline tests use (reference/normative.json) and its power budget, as a table.

use crate::sim::output::interpolate_log_f;
use crate::sim::{Effects, Model, ModelConfig, Runner, Theta};
use anyhow::{Context, Result};
use serde_json::Value;
use std::f64::consts::PI;

const NORMATIVE: &str = include_str!("../../reference/normative.json");

fn floats(v: &Value) -> Vec<f64> {
    v.as_array().map(|a| a.iter().filter_map(Value::as_f64).collect()).unwrap_or_default()
}

fn mark(inside: bool) -> &'static str {
    if inside { "" } else { "  ← outside" }
}

/// One simulated ear: its features on the model's grid, and the runner for responses
/// off that grid (group delays, the power budget).
struct Ear<'a> {
    runner: Runner<'a>,
    theta: &'a Theta,
    fx: &'a Effects,
    freqs: Vec<f64>,
    x: Vec<f64>,
}

impl Ear<'_> {
    /// Feature `k` (in the simulator's measure order) at `f`, interpolated in log f.
    fn measure(&self, k: usize, f: f64) -> f64 {
        let n = self.freqs.len();
        interpolate_log_f(&self.freqs, &self.x[k * n..(k + 1) * n], &[f])[0]
    }

    /// A log10(m/s/Pa) feature in dB re 1 mm/s/Pa, the unit of the published norms.
    fn db(&self, k: usize, f: f64) -> f64 {
        20.0 * (self.measure(k, f) + 3.0)
    }
}

/// Prints the report for one parameter set.
pub fn report(config: ModelConfig, theta: &Theta, fx: &Effects) -> Result<()> {
    let norms: Value = serde_json::from_str(NORMATIVE).context("reference/normative.json")?;
    let model = Model::new(config)?;
    let mut runner = model.runner();
    let freqs = model.frequencies().to_vec();
    let x = crate::sim::simulate(&mut runner, theta, fx)?;
    let mut ear = Ear { runner, theta, fx, freqs, x };
    stapes_velocity(&ear, &norms["vst_goode1994"]);
    stapes_phase(&mut ear, &norms["vst_phase"])?;
    absorbance(&ear, &norms["absorbance"]);
    impedance(&ear, &norms["zec"]);
    umbo_velocity(&mut ear)?;
    power_budget(&mut ear)
}

fn stapes_velocity(ear: &Ear, g: &Value) {
    println!("stapes velocity V/P, dB re 1 mm/s/Pa, against Goode et al. 1994 (target ±5 dB)");
    let mut diffs = Vec::new();
    for (f, v) in floats(&g["frequency_hz"]).into_iter().zip(floats(&g["value"])) {
        let d = ear.db(0, f) - v;
        diffs.push(d);
        println!("  {f:6.0} Hz  {:7.1}  Goode {v:6.1}  {d:+5.1}{}", ear.db(0, f), mark(d.abs() <= 5.0));
    }
    let rms = (diffs.iter().map(|d| d * d).sum::<f64>() / diffs.len() as f64).sqrt();
    println!("  rms {rms:.2} dB, worst {:.2} dB", diffs.iter().fold(0.0f64, |m, d| m.max(d.abs())));
}

/// The phase at the grid's ends and the group delay, by a central difference over ±0.5 %
/// of the frequency (the grid is too coarse for a delay at 8 kHz).
fn stapes_phase(ear: &mut Ear, p: &Value) -> Result<()> {
    let (x, n) = (&ear.x, ear.freqs.len());
    let ph8 = x[2 * n - 1].to_degrees();
    let r8 = floats(&p["at_8khz_deg"]);
    println!(
        "stapes velocity phase: {:.0}° at 200 Hz, {ph8:.0}° at 8 kHz (target {r8:?}){}",
        x[n].to_degrees(),
        mark(ph8 >= r8[0] && ph8 <= r8[1])
    );
    let gd = floats(&p["group_delay_us"]["range"]);
    for f in [1000.0, 2000.0, 4000.0, 8000.0] {
        let mut v = |f: f64| ear.runner.response_at(ear.theta, ear.fx, f).map(|r| r.vst_over_p);
        let d = -(v(1.005 * f)? / v(0.995 * f)?).arg() / (2.0 * PI * 0.01 * f) * 1e6;
        println!("  group delay at {f:5.0} Hz: {d:6.1} µs (target {gd:?}){}", mark(d >= gd[0] && d <= gd[1]));
    }
    Ok(())
}

fn absorbance(ear: &Ear, a: &Value) {
    println!("absorbance against the adult 10–90 % range");
    let (lo, hi, mean) = (floats(&a["low"]), floats(&a["high"]), floats(&a["mean"]));
    for (k, f) in floats(&a["frequency_hz"]).into_iter().enumerate() {
        let v = ear.measure(4, f);
        println!(
            "  {f:6.0} Hz  {v:5.2}  [{:.2}, {:.2}] mean {:.2}{}",
            lo[k],
            hi[k],
            mean[k],
            mark(v >= lo[k] && v <= hi[k])
        );
    }
}

/// The impedance against the live bands, and above them (4 and 8 kHz) unmarked.
fn impedance(ear: &Ear, z: &Value) {
    println!("ear-canal impedance at the measurement plane (live adults)");
    let (ml, mh, pl, ph) =
        (floats(&z["mag_low"]), floats(&z["mag_high"]), floats(&z["phase_low_deg"]), floats(&z["phase_high_deg"]));
    for (k, f) in floats(&z["frequency_hz"]).into_iter().enumerate() {
        let (m, phase) = (10f64.powf(ear.measure(2, f)), ear.measure(3, f).to_degrees());
        let ok = m >= ml[k] && m <= mh[k] && phase >= pl[k] && phase <= ph[k];
        println!(
            "  {f:6.0} Hz  {m:.2e} Pa·s/m³ {phase:5.0}°  [{:.1e}, {:.1e}] [{}, {}]°{}",
            ml[k],
            mh[k],
            pl[k],
            ph[k],
            mark(ok)
        );
    }
    for f in [4000.0, 8000.0] {
        println!("  {f:6.0} Hz  {:.2e} Pa·s/m³ {:5.0}°", 10f64.powf(ear.measure(2, f)), ear.measure(3, f).to_degrees());
    }
}

fn umbo_velocity(ear: &mut Ear) -> Result<()> {
    let mut umbo = Vec::new();
    for f in [250.0, 500.0, 1000.0, 2000.0, 4000.0, 8000.0] {
        let v = ear.runner.response_at(ear.theta, ear.fx, f)?.vu_over_p;
        umbo.push(format!("{:.1} @ {f:.0} Hz", 20.0 * (v.norm().log10() + 3.0)));
    }
    println!("umbo velocity V/P (vu_mag), dB re 1 mm/s/Pa: {}", umbo.join(", "));
    Ok(())
}

/// Where the power goes, every 7th grid frequency, and the cochlea's share where the
/// target is set.
fn power_budget(ear: &mut Ear) -> Result<()> {
    println!("power budget, % of the power entering the middle ear (canal: % of the probe's)");
    println!("    f Hz  canal  drum  lig+tend  joints   SAL  cochlea");
    for p in ear.runner.power_budget(ear.theta)?.iter().step_by(7) {
        let me = |v: f64| 100.0 * v / p.into_drum;
        println!(
            "  {:6.0} {:5.1} {:5.1} {:8.2} {:7.3} {:5.2} {:7.1}",
            p.freq_hz,
            100.0 * p.canal / p.probe,
            me(p.drum),
            me(p.ligaments + p.tendons),
            me(p.joints),
            me(p.sal),
            me(p.cochlea)
        );
    }
    for f in [1000.0, 2000.0, 4000.0] {
        ear.runner.solve_at(ear.theta, f)?;
        let share = ear.runner.power_balance(ear.theta, f).cochlear_share();
        println!("  cochlear share at {f:.0} Hz: {:.1} % (target ≥ 30 %){}", 100.0 * share, mark(share >= 0.3));
    }
    Ok(())
}
