//! POST /infer: measurements as devices export them (own frequency grids, magnitude and
//! phase or absorbance) → interpolated in log-frequency onto the model grid → posterior.

use super::{AppState, Problem, json_body};
use crate::npe::{Npe, Obs};
use axum::Json;
use axum::body::Bytes;
use axum::extract::State;
use axum::http::{HeaderMap, StatusCode};
use serde::Deserialize;
use serde_json::json;
use std::sync::Arc;

pub const MAX_SAMPLES: usize = 20_000;

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
pub struct InferRequest {
    pub model: Option<String>,
    pub measurements: Measurements,
    pub samples: Option<usize>,
    pub seed: Option<u64>,
    pub return_samples: Option<bool>,
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Measurements {
    /// |V_stapes/P_ec| in m/s/Pa and its phase in rad.
    pub stapes_velocity: Option<MagPhase>,
    /// Ear-canal impedance |Z| in Pa·s/m³ and its phase in rad.
    pub impedance: Option<MagPhase>,
    pub absorbance: Option<Values>,
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
pub struct MagPhase {
    pub frequencies_hz: Vec<f64>,
    pub magnitude: Vec<f64>,
    pub phase: Vec<f64>,
    /// Unit of `magnitude` (default SI: m/s/Pa or Pa·s/m³); see `magnitude_scale`.
    pub magnitude_unit: Option<String>,
    /// "rad" (default), "deg" or "cycles".
    pub phase_unit: Option<String>,
}

/// Velocity units: (accepted names, factor to m/s/Pa; `None`: decibels re 1 mm/s/Pa).
const VELOCITY_UNITS: [(&[&str], Option<f64>); 3] =
    [(&["m/s/Pa", "SI"], Some(1.0)), (&["mm/s/Pa"], Some(1e-3)), (&["dB re 1 mm/s/Pa", "dB"], None)];
/// Impedance units: SI acoustic ohms, MΩ of them, and CGS acoustic ohms (dyn·s/cm⁵).
const IMPEDANCE_UNITS: [(&[&str], Option<f64>); 3] = [
    (&["Pa·s/m³", "Pa*s/m^3", "Pa s/m3", "SI"], Some(1.0)),
    (&["MOhm", "MΩ"], Some(1e6)),
    (&["cgs", "dyn·s/cm⁵", "dyn*s/cm^5"], Some(1e5)),
];
const PHASE_UNITS: [(&str, f64); 3] =
    [("rad", 1.0), ("deg", std::f64::consts::PI / 180.0), ("cycles", std::f64::consts::TAU)];

/// Magnitudes in SI from `unit`; an unknown unit is an error naming `field`.
fn magnitude_si(
    field: &str,
    mp: &MagPhase,
    units: &[(&[&str], Option<f64>)],
    errs: &mut Vec<(String, String)>,
) -> Option<Vec<f64>> {
    let Some(unit) = &mp.magnitude_unit else { return Some(mp.magnitude.clone()) };
    match units.iter().find(|(names, _)| names.iter().any(|n| n.eq_ignore_ascii_case(unit))) {
        Some((_, Some(k))) => Some(mp.magnitude.iter().map(|v| v * k).collect()),
        Some((_, None)) => Some(mp.magnitude.iter().map(|db| 1e-3 * 10f64.powf(db / 20.0)).collect()),
        None => {
            let known: Vec<&str> = units.iter().map(|(n, _)| n[0]).collect();
            errs.push((
                format!("{field}.magnitude_unit"),
                format!("unknown unit '{unit}' (known: {})", known.join(", ")),
            ));
            None
        }
    }
}

fn phase_rad(field: &str, mp: &MagPhase, errs: &mut Vec<(String, String)>) -> Option<Vec<f64>> {
    let unit = mp.phase_unit.as_deref().unwrap_or("rad");
    match PHASE_UNITS.iter().find(|(n, _)| n.eq_ignore_ascii_case(unit)) {
        Some((_, k)) => Some(mp.phase.iter().map(|v| v * k).collect()),
        None => {
            errs.push((format!("{field}.phase_unit"), format!("unknown unit '{unit}' (known: rad, deg, cycles)")));
            None
        }
    }
}

/// A hint when a magnitude outside the physical envelope looks like another unit.
fn magnitude_hint(block: usize, v: f64) -> &'static str {
    match block {
        0 if v > 1e-2 && v <= 1e2 => "; it looks like mm/s/Pa: send \"magnitude_unit\": \"mm/s/Pa\"",
        2 if (1e-2..1e5).contains(&v) => {
            "; it looks like MΩ or CGS acoustic ohms: send \"magnitude_unit\": \"MOhm\" or \"cgs\""
        }
        _ => "",
    }
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Values {
    pub frequencies_hz: Vec<f64>,
    pub values: Vec<f64>,
}

/// Checks one measured curve and interpolates it in log-frequency onto `grid`. With
/// `cut = Some(k)` (a band-masked model) the curve may cover a sub-band that leaves out at
/// most `k` grid points at each end: grid points outside it are NaN (absent), never
/// extrapolated.
fn resample(
    field: &str,
    f: &[f64],
    v: &[f64],
    grid: &[f64],
    cut: Option<usize>,
    errs: &mut Vec<(String, String)>,
) -> Option<Vec<f64>> {
    let before = errs.len();
    if f.len() < 2 {
        errs.push((format!("{field}.frequencies_hz"), "needs at least 2 points".into()));
    }
    if v.len() != f.len() {
        errs.push((field.to_string(), format!("has {} values for {} frequencies", v.len(), f.len())));
    }
    if let Some(i) = f.iter().position(|x| !x.is_finite() || *x <= 0.0) {
        errs.push((format!("{field}.frequencies_hz[{i}]"), "must be a finite frequency > 0".into()));
    } else if let Some(i) = (1..f.len()).find(|&i| f[i] <= f[i - 1]) {
        errs.push((format!("{field}.frequencies_hz[{i}]"), "frequencies must increase strictly".into()));
    }
    if errs.len() > before {
        return None;
    }
    let inside = |g: f64| g >= f[0] * 0.995 && g <= f[f.len() - 1] * 1.005;
    if let Some(k) = cut {
        let lo = grid.iter().position(|&g| inside(g));
        let hi = grid.iter().rposition(|&g| inside(g));
        let n = grid.len();
        match lo.zip(hi) {
            Some((lo, hi)) if lo <= k && n - 1 - hi <= k => {
                let mut out = crate::sim::output::interpolate_log_f(f, v, grid);
                out.iter_mut().zip(grid).filter(|(_, g)| !inside(**g)).for_each(|(o, _)| *o = f64::NAN);
                return Some(out);
            }
            _ => {
                errs.push((
                    format!("{field}.frequencies_hz"),
                    format!(
                        "must reach from at most {:.0} Hz to at least {:.0} Hz (got {:.0}–{:.0}); this model was trained \
                         with up to {k} grid points missing at each end and never extrapolates",
                        grid[k],
                        grid[n - 1 - k],
                        f[0],
                        f[f.len() - 1]
                    ),
                ));
                return None;
            }
        }
    }
    if f[0] > grid[0] * 1.005 || f[f.len() - 1] < grid[grid.len() - 1] * 0.995 {
        errs.push((
            format!("{field}.frequencies_hz"),
            format!(
                "must cover the model band {:.0}–{:.0} Hz (got {:.0}–{:.0})",
                grid[0],
                grid[grid.len() - 1],
                f[0],
                f[f.len() - 1]
            ),
        ));
        return None;
    }
    Some(crate::sim::output::interpolate_log_f(f, v, grid))
}

fn check_values(field: &str, v: &[f64], positive: bool, errs: &mut Vec<(String, String)>) {
    if let Some(i) = v.iter().position(|x| !x.is_finite() || (positive && *x <= 0.0)) {
        errs.push((
            format!("{field}[{i}]"),
            if positive { "must be a finite number > 0".into() } else { "must be a finite number".into() },
        ));
    }
}

/// Rejects features outside the physical envelope of their measure, naming the request
/// field and the model-grid frequency, with a hint where the value looks like a unit slip.
fn plausible(x: &[f64], grid: &[f64], errs: &mut Vec<(String, String)>) {
    use crate::sim::output::{MEASURES, implausible};
    let n = grid.len();
    let present: Vec<bool> = x.iter().map(|v| v.is_finite()).collect();
    for (m, i, v) in implausible(x, &present) {
        let f = grid[i % n];
        let (field, shown, range, hint) = match m {
            0 | 2 => {
                let (lo, hi) = MEASURES[m].envelope;
                let field = if m == 0 { "stapes_velocity.magnitude" } else { "impedance.magnitude" };
                let unit = if m == 0 { "m/s/Pa" } else { "Pa·s/m³" };
                let shown = format!("{:.3e} {unit}", 10f64.powf(v));
                (
                    field,
                    shown,
                    format!("{:.0e}–{:.0e} {unit}", 10f64.powf(lo), 10f64.powf(hi)),
                    magnitude_hint(m, 10f64.powf(v)),
                )
            }
            1 | 3 => {
                let (lo, hi) = MEASURES[m].envelope;
                let field = if m == 1 { "stapes_velocity.phase" } else { "impedance.phase" };
                let hint = if v.abs() <= 1100.0 { "; phases in degrees need \"phase_unit\": \"deg\"" } else { "" };
                let range = format!("{:.2}…{:.2} rad (unwrapped)", lo, hi);
                (field, format!("{v:.2} rad"), range, hint)
            }
            _ => ("absorbance.values", format!("{v:.3}"), "0–1".into(), ""),
        };
        errs.push((
            format!("measurements.{field}"),
            format!("{shown} at {f:.0} Hz is outside the physical range {range} of a human ear{hint}"),
        ));
    }
}

/// The band of each measure given, as (first, last) model-grid frequency used.
fn bands_used(npe: &Npe, present: &[bool]) -> serde_json::Map<String, serde_json::Value> {
    let grid = &npe.header.frequencies_hz;
    let n = grid.len().max(1);
    crate::sim::output::MEASURES
        .iter()
        .enumerate()
        .filter_map(|(m, ms)| {
            let on: Vec<usize> = (0..n).filter(|&k| present.get(m * n + k).copied().unwrap_or(false)).collect();
            let (lo, hi) = (on.first()?, on.last()?);
            Some((ms.name.to_string(), json!([grid[*lo], grid[*hi]])))
        })
        .collect()
}

/// The model's feature vector and presence flags from the measurements.
/// Features on the model grid, which are present, and the measures used.
type Features = (Vec<f64>, Vec<bool>, Vec<&'static str>);

fn features(npe: &Npe, m: &Measurements) -> Result<Features, Problem> {
    let grid = &npe.header.frequencies_hz;
    let cut = npe.header.mask_bands.then_some(npe.header.band_cut_max);
    let n = grid.len();
    let mut errs = Vec::new();
    if n == 0 || npe.header.feature_names.len() != 5 * n {
        return Err(Problem::new(
            StatusCode::CONFLICT,
            "this model was not trained on otofit's five measures; use the CLI with a feature table",
        ));
    }
    let mut x = vec![f64::NAN; 5 * n];
    let mut used = Vec::new();
    let mut magphase =
        |field: &'static str, mp: &MagPhase, block: usize, x: &mut Vec<f64>, errs: &mut Vec<(String, String)>| {
            let fld = format!("measurements.{field}");
            let units: &[(&[&str], Option<f64>)] = if block == 0 { &VELOCITY_UNITS } else { &IMPEDANCE_UNITS };
            let (Some(mag), Some(phase)) = (magnitude_si(&fld, mp, units, errs), phase_rad(&fld, mp, errs)) else {
                return;
            };
            let decibels = mp.magnitude_unit.as_deref().is_some_and(|u| u.starts_with("dB"));
            if decibels {
                check_values(&format!("{fld}.magnitude"), &mp.magnitude, false, errs);
            } else if mp.magnitude.iter().any(|v| *v <= 0.0) && block == 0 {
                let i = mp.magnitude.iter().position(|v| *v <= 0.0).unwrap_or(0);
                errs.push((
                    format!("{fld}.magnitude[{i}]"),
                    "must be > 0 (for decibels send \"magnitude_unit\": \"dB re 1 mm/s/Pa\")".into(),
                ));
            } else {
                check_values(&format!("{fld}.magnitude"), &mp.magnitude, true, errs);
            }
            check_values(&format!("{fld}.phase"), &mp.phase, false, errs);
            let logmag: Vec<f64> = mag.iter().map(|v| v.log10()).collect();
            let phase = crate::sim::output::unwrap(phase.into_iter());
            if let (Some(a), Some(b)) = (
                resample(&fld, &mp.frequencies_hz, &logmag, grid, cut, errs),
                resample(&fld, &mp.frequencies_hz, &phase, grid, cut, errs),
            ) {
                x[block * n..(block + 1) * n].copy_from_slice(&a);
                x[(block + 1) * n..(block + 2) * n].copy_from_slice(&b);
                used.push(field);
            }
        };
    if let Some(mp) = &m.stapes_velocity {
        magphase("stapes_velocity", mp, 0, &mut x, &mut errs);
    }
    if let Some(mp) = &m.impedance {
        magphase("impedance", mp, 2, &mut x, &mut errs);
    }
    if let Some(a) = &m.absorbance {
        check_values("measurements.absorbance.values", &a.values, false, &mut errs);
        if let Some(i) = a.values.iter().position(|v| !(-0.05..=1.05).contains(v)) {
            errs.push((
                format!("measurements.absorbance.values[{i}]"),
                format!(
                    "{} is outside 0–1 (absorbance is a fraction of power; ±0.05 is allowed for calibration error)",
                    a.values[i]
                ),
            ));
        }
        if let Some(v) = resample("measurements.absorbance", &a.frequencies_hz, &a.values, grid, cut, &mut errs) {
            x[4 * n..].copy_from_slice(&v);
            used.push("absorbance");
        }
    }
    if errs.is_empty() {
        plausible(&x, grid, &mut errs);
    }
    if !errs.is_empty() {
        return Err(Problem::invalid(errs));
    }
    if used.is_empty() {
        return Err(Problem::invalid(vec![(
            "measurements".into(),
            "give at least one of stapes_velocity, impedance, absorbance".into(),
        )]));
    }
    let present: Vec<bool> = x.iter().map(|v| v.is_finite()).collect();
    if !npe.header.mask_groups && present.iter().any(|p| !p) {
        let missing: Vec<&str> =
            ["stapes_velocity", "impedance", "absorbance"].into_iter().filter(|f| !used.contains(f)).collect();
        return Err(Problem::invalid(vec![(
            "measurements".into(),
            format!("this model needs every measure; missing: {}", missing.join(", ")),
        )]));
    }
    Ok((x, present, used))
}

pub async fn infer(
    State(st): State<AppState>,
    headers: HeaderMap,
    body: Bytes,
) -> Result<Json<serde_json::Value>, Problem> {
    let t0 = std::time::Instant::now();
    let req: InferRequest = json_body(&headers, &body)?;
    let n = req.samples.unwrap_or(1000);
    if n == 0 || n > MAX_SAMPLES {
        return Err(Problem::invalid(vec![("samples".into(), format!("must be 1..={MAX_SAMPLES}"))]));
    }
    let row = match &req.model {
        Some(id) => st
            .ctx
            .store
            .model(id)
            .await
            .map_err(Problem::internal)?
            .ok_or_else(|| Problem::invalid(vec![("model".into(), format!("no model '{id}'"))]))?,
        None => st
            .ctx
            .store
            .default_model()
            .await
            .map_err(Problem::internal)?
            .ok_or_else(|| Problem::new(StatusCode::SERVICE_UNAVAILABLE, "no default model is registered"))?,
    };
    let ctx = st.ctx.clone();
    let (id, path) = (row.id.clone(), row.path.clone());
    let npe: Arc<Npe> = tokio::task::spawn_blocking(move || ctx.loaded(&id, std::path::Path::new(&path)))
        .await
        .map_err(Problem::internal)?
        .map_err(|e| {
            Problem::new(StatusCode::SERVICE_UNAVAILABLE, format!("model '{}' cannot be loaded: {e:#}", row.id))
        })?;
    let (x, present, used) = features(&npe, &req.measurements)?;
    let band_hz = bands_used(&npe, &present);
    let seed = req.seed.unwrap_or(0);
    let npe2 = npe.clone();
    let (inf, fit) = tokio::task::spawn_blocking(move || {
        let inf = npe2.infer(&Obs { x: &x, present: Some(&present) }, n, seed)?;
        let fit = crate::discrepancy::fitcheck::fit_check(&npe2, &x, &present, &inf);
        anyhow::Ok((inf, fit.map(|f| (f, x))))
    })
    .await
    .map_err(Problem::internal)?
    .map_err(|e| Problem::invalid(vec![("measurements".into(), format!("{e:#}"))]))?;
    tracing::info!(model = %row.id, samples = n, inputs = used.len(), ms = t0.elapsed().as_secs_f64() * 1e3, "inferred");
    let mut differential = crate::npe::normal::read(npe.params(), &inf.samples);
    let mut next = serde_json::Value::Null;
    let fit = match fit {
        Ok((f, x)) => {
            if f.ok == Some(false) {
                let why = f.reason.clone().unwrap_or_default();
                crate::npe::normal::withdraw(&mut differential, &why);
                let mut params = json!({ "x": x });
                if let Some(m) = &req.model {
                    params["model"] = json!(m);
                }
                next = json!({ "why": "look for the physical effect the model is missing", "method": "POST", "path": "/jobs" });
                if x.iter().all(|v| v.is_finite()) {
                    next["body"] = json!({ "kind": "diagnose", "params": params });
                }
            }
            json!(f)
        }
        Err(e) => json!({ "ok": null, "reason": e.to_string() }),
    };
    let mut doc = json!({
        "model": row.id,
        "fit": fit,
        "parameters": inf.summaries,
        "differential": differential,
        "differential_note": "per parameter: the posterior probability below / within / above the normal range; a reading only where the posterior is informative and puts ≥ 0.8 on one side, else undetermined; unreliable for every parameter when the fit check fails. Information, not a diagnosis",
        "map": inf.map,
        "inputs": {
            "used": used,
            "interpolated": true,
            "note": "each measure was interpolated linearly in log-frequency onto the model grid (magnitudes as log10, phases unwrapped)",
            "grid_hz": npe.header.frequencies_hz,
            "band_hz": band_hz,
        },
        "samples_count": n,
        "seed": seed,
        "timing_ms": { "sample": inf.sample_ms, "map": inf.map_ms, "total": t0.elapsed().as_secs_f64() * 1e3 },
    });
    if !next.is_null() {
        doc["next"] = next;
    }
    if req.return_samples.unwrap_or(true) {
        doc["samples"] = json!(inf.samples);
        doc["sample_columns"] = json!(npe.params().iter().map(|p| &p.name).collect::<Vec<_>>());
    }
    Ok(Json(doc))
}
