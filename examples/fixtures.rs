//! Regenerates the device-export fixtures of tests/data from the current simulator's
//! nominal ear (temporal-bone preset, no effects): the WAI long layout (`wai_long.csv`,
//! 1/12 octave from 226 Hz and 8 kHz, Zang in cycles; the right ear's Zmag 5 % higher),
//! the same left ear as a WBT device's table (`wbt_device_long.csv`: semicolons, %,
//! CGS acoustic ohms, degrees, 226–5740 Hz), as pressure reflectance with a canal area
//! (`wai_reflectance.csv`, Z0 = ρc/S at 37 °C with the area that gives the simulator's Z0) and as admittance
//! (`admittance_long.csv`, mmho, degrees), and its umbo velocity on the model grid as an
//! LDV's UFF dataset 58 (`ldv_umbo.uff`, mm/s over Pa). From the typical ear
//! (`npe::normal::centre_row`, every tissue value at the centre of its normal range): the
//! stapes velocity as an LDV's dataset 58 (`ldv_stapes.uff`) and the request example of
//! POST /infer in `openapi.yaml` (the directory's `../../openapi.yaml`; the example line is
//! replaced). Run it when the simulator's nominal ear changes (docs/simulator.md):
//!
//! `cargo run --example fixtures -- tests/data`

use faer::c64;
use otofit::npe::normal::centre_row;
use otofit::sim::{Effects, Model, ModelConfig, N_PARAMS, Preset, Theta};
use std::fmt::Write as _;
use std::path::Path;

fn main() -> Result<(), String> {
    let dir = std::env::args().nth(1).ok_or("usage: fixtures DIR (tests/data)")?;
    let dir = Path::new(&dir);
    let model = Model::new(ModelConfig::default()).map_err(|e| e.to_string())?;
    let mut runner = model.runner();
    let (theta, fx) = (Theta::nominal(), Effects::default());
    let mut at = |f: f64| runner.response_at(&theta, &fx, f).map_err(|e| e.to_string());
    let wai_f: Vec<f64> = (0..62).map(|k| 226.0 * 2f64.powf(k as f64 / 12.0)).chain([8000.0]).collect();
    let rows: Vec<(f64, c64, f64)> =
        wai_f.iter().map(|&f| at(f).map(|r| (f, r.zec, r.absorbance()))).collect::<Result<_, _>>()?;

    let mut wai = String::from("Subject,Ear,Frequency,Absorbance,Zmag,Zang,AreaCanal\n");
    for (ear, k) in [("Left", 1.0), ("Right", 1.05)] {
        for (f, z, a) in &rows {
            let cycles = z.arg() / std::f64::consts::TAU;
            writeln!(wai, "S01,{ear},{f:.2},{a:.5},{},{cycles:.5},44.2", g6(k * z.norm())).unwrap();
        }
    }
    write(dir, "wai_long.csv", &wai)?;

    let mut dev = String::from("Frequency [Hz];Absorbance [%];Zmag [cgs];Zang [deg]\n");
    for (f, z, a) in rows.iter().filter(|r| r.0 < 5750.0) {
        writeln!(dev, "{f:.1};{:.2};{:.2};{:.2}", 100.0 * a, z.norm() / 1e5, z.arg().to_degrees()).unwrap();
    }
    write(dir, "wbt_device_long.csv", &dev)?;

    // The importer takes Z0 = ρc/S with air at 37 °C; this area gives the simulator's own
    // Z0 (22 °C, 44 mm²), so 1 − |R|² is the table's absorbance.
    let (live, bone) = (Preset::Live.air(), Preset::TemporalBone.air());
    let area_mm2 = (44.0 * live.rho * live.c / (bone.rho * bone.c) * 100.0).round() / 100.0;
    let z0 = live.z0(area_mm2 * 1e-6);
    let mut refl = String::from("Subject,Ear,Frequency,Rmag,Rang [deg],AreaCanal [mm2]\n");
    let mut adm = String::from("Frequency [Hz],Ymag [mmho],Yang [deg]\n");
    for (f, z, _) in &rows {
        let r = (z - z0) / (z + z0);
        writeln!(refl, "S01,Left,{f:.2},{:.6},{:.4},{area_mm2:.2}", r.norm(), r.arg().to_degrees()).unwrap();
        let y_mmho = 1e3 / (z.norm() / 1e5); // CGS acoustic millimho
        writeln!(adm, "{f:.2},{},{}", g5(y_mmho), g5(-z.arg().to_degrees())).unwrap();
    }
    write(dir, "wai_reflectance.csv", &refl)?;
    write(dir, "admittance_long.csv", &adm)?;

    let grid = model.frequencies().to_vec();
    let umbo: Vec<(f64, c64)> =
        grid.iter().map(|&f| at(f).map(|r| (f, r.vu_over_p * 1e3))).collect::<Result<_, _>>()?;
    write(
        dir,
        "ldv_umbo.uff",
        &uff58(&umbo, "umbo", "umbo velocity over ear-canal pressure, LDV through the canal; the nominal ear"),
    )?;

    let typical = Theta(<[f64; N_PARAMS]>::try_from(centre_row().as_slice()).map_err(|e| e.to_string())?);
    let on_grid: Vec<_> = grid
        .iter()
        .map(|&f| runner.response_at(&typical, &fx, f).map_err(|e| e.to_string()))
        .collect::<Result<_, _>>()?;

    // The request example: frequencies to 0.1 Hz, magnitudes to 5 significant digits,
    // phases in radians (unwrapped) to 4 decimals; the LDV file holds the same numbers.
    let sig5 = |v: f64| format!("{v:.4e}").parse::<f64>().expect("a number");
    let dec = |v: f64, d: i32| (v * 10f64.powi(d)).round() / 10f64.powi(d);
    let freqs: Vec<f64> = grid.iter().map(|&f| dec(f, 1)).collect();
    let rounded = |z: Vec<c64>| -> (Vec<f64>, Vec<f64>) {
        (z.iter().map(|v| sig5(v.norm())).collect(), unwrap(&z).into_iter().map(|p| dec(p, 4)).collect())
    };
    let (vst_mag, vst_phase) = rounded(on_grid.iter().map(|r| r.vst_over_p).collect());
    let (zec_mag, zec_phase) = rounded(on_grid.iter().map(|r| r.zec).collect());
    let absorbance: Vec<f64> = on_grid.iter().map(|r| dec(r.absorbance(), 5)).collect();
    let stapes: Vec<(f64, c64)> =
        (0..freqs.len()).map(|k| (freqs[k], c64::from_polar(vst_mag[k] * 1e3, vst_phase[k]))).collect();
    write(
        dir,
        "ldv_stapes.uff",
        &uff58(&stapes, "stapes", "stapes velocity over ear-canal pressure, LDV; the typical ear of openapi.yaml"),
    )?;
    let f = list(&freqs);
    let example = format!(
        "{{\"measurements\":{{\"stapes_velocity\":{{\"frequencies_hz\":{f},\"magnitude\":{},\"phase\":{}}},\
         \"impedance\":{{\"frequencies_hz\":{f},\"magnitude\":{},\"phase\":{}}},\
         \"absorbance\":{{\"frequencies_hz\":{f},\"values\":{}}}}},\"samples\":1000,\"seed\":7}}",
        list(&vst_mag),
        list(&vst_phase),
        list(&zec_mag),
        list(&zec_phase),
        list(&absorbance)
    );
    let spec = dir.join("../../openapi.yaml");
    let yaml = std::fs::read_to_string(&spec).map_err(|e| format!("{}: {e}", spec.display()))?;
    let marker = "example: {\"measurements\"";
    let mut hits = 0;
    let lines: Vec<String> = yaml
        .lines()
        .map(|l| match l.find(marker) {
            Some(at) => {
                hits += 1;
                format!("{}example: {example}", &l[..at])
            }
            None => l.to_string(),
        })
        .collect();
    if hits != 1 {
        return Err(format!("{}: {hits} request examples found, expected one", spec.display()));
    }
    write(dir, "../../openapi.yaml", &(lines.join("\n") + "\n"))?;
    Ok(())
}

/// A JSON array as Python writes it (the example was first written so): the shortest
/// decimal, in exponent form below 1e-4 with a two-digit exponent.
fn list(v: &[f64]) -> String {
    let item = |x: f64| {
        if x != 0.0 && x.abs() < 1e-4 {
            let s = format!("{x:e}");
            let (m, e) = s.split_once("e-").expect("a negative exponent");
            format!("{m}e-{e:0>2}")
        } else {
            serde_json::to_string(&x).expect("a finite number")
        }
    };
    format!("[{}]", v.iter().map(|&x| item(x)).collect::<Vec<_>>().join(","))
}

/// Phases along frequency without 2π jumps.
fn unwrap(z: &[c64]) -> Vec<f64> {
    let mut out: Vec<f64> = Vec::with_capacity(z.len());
    for v in z {
        let p = v.arg();
        out.push(match out.last() {
            Some(&prev) => p + std::f64::consts::TAU * ((prev - p) / std::f64::consts::TAU).round(),
            None => p,
        });
    }
    out
}

fn write(dir: &Path, name: &str, text: &str) -> Result<(), String> {
    std::fs::write(dir.join(name), text).map_err(|e| format!("{name}: {e}"))?;
    eprintln!("wrote {}", dir.join(name).display());
    Ok(())
}

/// Six significant digits, as C's %g: plain below 1e6, else d.ddddde+XX.
fn g6(v: f64) -> String {
    if v < 1e6 { format!("{}", (v + 0.5).floor()) } else { exp(v, 5) }
}

/// Five significant digits (the admittance table's values are 0.1–1000).
fn g5(v: f64) -> String {
    let digits = (4 - v.abs().log10().floor() as i32).max(0) as usize;
    format!("{v:.digits$}")
}

/// d.ddddde+XX with `p` decimals.
fn exp(v: f64, p: usize) -> String {
    let s = format!("{v:.p$e}");
    let (m, e) = s.split_once('e').expect("exponent");
    let e: i32 = e.parse().expect("integer exponent");
    format!("{m}e{}{:02}", if e < 0 { '-' } else { '+' }, e.abs())
}

/// One UFF dataset 58 of complex single values, the velocity at `node` over the
/// reference microphone.
fn uff58(points: &[(f64, c64)], node: &str, title: &str) -> String {
    let e = |v: f64| {
        let s = exp(v, 5).to_uppercase();
        format!("{s:>13}")
    };
    let mut s = String::from("    -1\n    58\n");
    s += &format!("{title} (otofit test fixture)\n");
    s += "NONE\n2026-11-23\npoint 1 / reference mic\nNONE\n";
    s += &format!("    4         1    1         0 {node:<10}          1   3 mic                 1   0\n");
    writeln!(s, "         5{:>10}         0  0.00000E+00  0.00000E+00  0.00000E+00", points.len()).unwrap();
    s += "        18    0    0    0 Frequency            Hz                  \n";
    s += "        11    1    0    0 Velocity             mm/s                \n";
    s += "        15   -2    1    0 Pressure             Pa                  \n";
    s += "         0    0    0    0 NONE                 NONE                \n";
    for pair in points.chunks(2) {
        for (f, v) in pair {
            s += &format!("{}{}{}", e(*f), e(v.re), e(v.im));
        }
        s += "\n";
    }
    s += "    -1\n";
    s
}
