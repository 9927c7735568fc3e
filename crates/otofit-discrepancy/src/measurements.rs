//! Measurements as devices export them — each measure on its own frequency grid, in its
//! declared units — checked against a human ear's physical range and turned into a
//! model's feature vector (interpolated in log-frequency onto the model grid, never
//! extrapolated). Shared by `POST /infer` and `otofit infer --obs file.json`.

use crate::npe::Npe;
use crate::sim::output::N_MEASURES;
use serde::{Deserialize, Serialize};
use serde_json::json;

/// Why measurements cannot become a feature vector.
#[derive(Debug, thiserror::Error)]
pub enum MeasurementError {
    /// The model's features are not otofit's measures on a frequency grid.
    #[error("this model was not trained on otofit's measures; use a feature table")]
    NotOtofitModel,
    /// Bad fields: (JSON path, what is wrong).
    #[error("invalid measurements: {}", .0.iter().map(|(f, m)| format!("{f}: {m}")).collect::<Vec<_>>().join("; "))]
    Invalid(Vec<(String, String)>),
}

/// How an error about measured points too sparse to score begins.
pub const INSUFFICIENT_DATA: &str = "insufficient data:";

impl MeasurementError {
    /// Whether every problem is measured points too sparse for the band (the request
    /// is well formed but carries too little to read an ear from).
    pub fn insufficient_data(&self) -> bool {
        matches!(self, MeasurementError::Invalid(errs) if !errs.is_empty() && errs.iter().all(|(_, m)| m.starts_with(INSUFFICIENT_DATA)))
    }
}

/// One ear's measurements, each on its own frequency grid; any subset may be given.
#[derive(Debug, Default, Deserialize, Serialize)]
#[serde(deny_unknown_fields)]
pub struct Measurements {
    /// |V_stapes/P_ec| in m/s/Pa and its phase in rad.
    pub stapes_velocity: Option<MagPhase>,
    /// Ear-canal impedance |Z| in Pa·s/m³ and its phase in rad.
    pub impedance: Option<MagPhase>,
    /// Absorbance (1 − |R|², a fraction of power).
    pub absorbance: Option<Values>,
    /// |V_umbo/P_ec| in m/s/Pa (clinical LDV through the canal) and its phase in rad.
    pub umbo_velocity: Option<MagPhase>,
}

/// A complex measure as magnitude and phase over frequency.
#[derive(Debug, Deserialize, Serialize)]
#[serde(deny_unknown_fields)]
pub struct MagPhase {
    /// Frequencies, Hz.
    pub frequencies_hz: Vec<f64>,
    /// Magnitudes, in `magnitude_unit`.
    pub magnitude: Vec<f64>,
    /// Phases, in `phase_unit`.
    pub phase: Vec<f64>,
    /// Unit of `magnitude` (default SI: m/s/Pa or Pa·s/m³); see `magnitude_scale`.
    pub magnitude_unit: Option<String>,
    /// "rad" (default), "deg" or "cycles".
    pub phase_unit: Option<String>,
}

/// Velocity units: (accepted names, factor to m/s/Pa; `None`: decibels re 1 mm/s/Pa).
pub const VELOCITY_UNITS: [(&[&str], Option<f64>); 3] =
    [(&["m/s/Pa", "SI"], Some(1.0)), (&["mm/s/Pa"], Some(1e-3)), (&["dB re 1 mm/s/Pa", "dB"], None)];
/// Impedance units: SI acoustic ohms, MΩ of them, and CGS acoustic ohms (dyn·s/cm⁵).
pub const IMPEDANCE_UNITS: [(&[&str], Option<f64>); 3] = [
    (&["Pa·s/m³", "Pa*s/m^3", "Pa s/m3", "SI"], Some(1.0)),
    (&["MOhm", "MΩ"], Some(1e6)),
    (&["cgs", "dyn·s/cm⁵", "dyn*s/cm^5"], Some(1e5)),
];
/// Phase units: (name, factor to rad).
pub const PHASE_UNITS: [(&str, f64); 3] =
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
        0 | 5 if v > 1e-2 && v <= 1e2 => "; it looks like mm/s/Pa: send \"magnitude_unit\": \"mm/s/Pa\"",
        2 if (1e-2..1e5).contains(&v) => {
            "; it looks like MΩ or CGS acoustic ohms: send \"magnitude_unit\": \"MOhm\" or \"cgs\""
        }
        _ => "",
    }
}

/// A real measure over frequency.
#[derive(Debug, Deserialize, Serialize)]
#[serde(deny_unknown_fields)]
pub struct Values {
    /// Frequencies, Hz.
    pub frequencies_hz: Vec<f64>,
    /// The values, one per frequency.
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
    // The model band is 0.2–8 kHz: a curve that ends at 20 "Hz" is in kHz.
    if f[f.len() - 1] <= 20.0 && grid[0] > 20.0 {
        errs.push((
            format!("{field}.frequencies_hz"),
            format!("they end at {} Hz, below the model band: they look like kHz; send Hz (× 1000)", f[f.len() - 1]),
        ));
        return None;
    }
    let inside = |g: f64| g >= f[0] * 0.995 && g <= f[f.len() - 1] * 1.005;
    if let Some(k) = cut {
        let lo = grid.iter().position(|&g| inside(g));
        let hi = grid.iter().rposition(|&g| inside(g));
        let n = grid.len();
        match lo.zip(hi) {
            Some((lo, hi)) if lo <= k && n - 1 - hi <= k => {
                if let Some(message) = sparse(f, grid) {
                    errs.push((format!("{field}.frequencies_hz"), message));
                    return None;
                }
                let mut out = crate::sim::output::interpolate_log_f(f, v, grid);
                out.iter_mut().zip(grid).filter(|(_, g)| !inside(**g)).for_each(|(o, _)| *o = f64::NAN);
                return Some(out);
            }
            _ => {
                let (a, b, lo, hi) = (f[0], f[f.len() - 1], grid[k], grid[n - 1 - k]);
                let gaps: Vec<String> = [(lo, a.min(hi)), (b.max(lo), hi)]
                    .into_iter()
                    .filter(|(x, y)| y > &(x * 1.005))
                    .map(|(x, y)| format!("{x:.0}–{y:.0} Hz"))
                    .collect();
                errs.push((
                    format!("{field}.frequencies_hz"),
                    format!(
                        "must reach from at most {lo:.0} Hz to at least {hi:.0} Hz (got {a:.0}–{b:.0}): {} not covered; \
                         this model was trained with up to {k} grid points missing at each end and never extrapolates",
                        gaps.join(" and ")
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
    if let Some(message) = sparse(f, grid) {
        errs.push((format!("{field}.frequencies_hz"), message));
        return None;
    }
    Some(crate::sim::output::interpolate_log_f(f, v, grid))
}

/// Widest gap between two measured frequencies inside the model band, in octaves. The
/// grid is interpolated from the points given, and the fit check scores every grid
/// point: a curve with wider gaps would be scored as if measured where it was not.
/// Half an octave admits every device layout in use (1/3 to 1/24 octave).
pub const MAX_GAP_OCTAVES: f64 = 0.5;

/// Why the measured points are too sparse for the model band, if they are.
fn sparse(f: &[f64], grid: &[f64]) -> Option<String> {
    let (g0, g1) = (grid[0], grid[grid.len() - 1]);
    let (lo, hi, octaves) = f
        .windows(2)
        .map(|w| (w[0].max(g0), w[1].min(g1)))
        .filter(|(a, b)| b > a)
        .map(|(a, b)| (a, b, (b / a).log2()))
        .max_by(|x, y| x.2.total_cmp(&y.2))?;
    (octaves > MAX_GAP_OCTAVES).then(|| {
        format!(
            "{INSUFFICIENT_DATA} no measured point between {lo:.0} and {hi:.0} Hz ({octaves:.2} octaves); \
             measure at least every {MAX_GAP_OCTAVES} octave over the band, as devices do"
        )
    })
}

fn check_values(field: &str, v: &[f64], positive: bool, errs: &mut Vec<(String, String)>) {
    if let Some(i) = v.iter().position(|x| !x.is_finite() || (positive && *x <= 0.0)) {
        errs.push((
            format!("{field}[{i}]"),
            if positive { "must be a finite number > 0".into() } else { "must be a finite number".into() },
        ));
    }
}

/// The request field of each measure (`MEASURES` order).
const FIELDS: [&str; N_MEASURES] =
    ["stapes_velocity", "stapes_velocity", "impedance", "impedance", "absorbance", "umbo_velocity", "umbo_velocity"];

/// Rejects features outside the physical envelope of their measure, naming the request
/// field and the model-grid frequency, with a hint where the value looks like a unit slip.
fn plausible(x: &[f64], grid: &[f64], errs: &mut Vec<(String, String)>) {
    use crate::sim::output::{MEASURES, implausible};
    let n = grid.len();
    let present: Vec<bool> = x.iter().map(|v| v.is_finite()).collect();
    for (m, i, v) in implausible(x, &present, n) {
        let f = grid[i % n];
        let (lo, hi) = MEASURES[m].envelope;
        let (part, shown, range, hint) = match MEASURES[m].name {
            "absorbance" => ("values", format!("{v:.3}"), "0–1".into(), ""),
            name if name.ends_with("_phase") => {
                let hint = if v.abs() <= 1100.0 { "; phases in degrees need \"phase_unit\": \"deg\"" } else { "" };
                ("phase", format!("{v:.2} rad"), format!("{lo:.2}…{hi:.2} rad (unwrapped)"), hint)
            }
            _ => {
                let unit = if m == 2 { "Pa·s/m³" } else { "m/s/Pa" };
                let range = format!("{:.0e}–{:.0e} {unit}", 10f64.powf(lo), 10f64.powf(hi));
                ("magnitude", format!("{:.3e} {unit}", 10f64.powf(v)), range, magnitude_hint(m, 10f64.powf(v)))
            }
        };
        errs.push((
            format!("measurements.{}.{part}", FIELDS[m]),
            format!("{shown} at {f:.0} Hz is outside the physical range {range} of a human ear{hint}"),
        ));
    }
}

/// The band of each measure given, as (first, last) model-grid frequency used.
pub fn bands_used(npe: &Npe, present: &[bool]) -> serde_json::Map<String, serde_json::Value> {
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

/// How many of otofit's measures the model takes (5: without umbo velocity, as models
/// before v4; 7: all), from its feature names; `None` when they are not otofit's.
pub fn model_measures(npe: &Npe) -> Option<usize> {
    let names = &npe.header.feature_names;
    let n = npe.header.frequencies_hz.len();
    let measures = names.len().checked_div(n).unwrap_or(0);
    let ours = |m: usize| names[m * n].split('@').next() == Some(crate::sim::output::MEASURES[m].name);
    ([5, N_MEASURES].contains(&measures) && names.len() == measures * n && (0..measures).all(ours)).then_some(measures)
}

/// Features on the model grid, which are present, and the measures used.
pub type Features = (Vec<f64>, Vec<bool>, Vec<&'static str>);

/// The model's feature vector and presence flags from the measurements. Every problem
/// is collected before returning, so that one reply names all the fields to fix.
pub fn features(npe: &Npe, m: &Measurements) -> Result<Features, MeasurementError> {
    let measures = model_measures(npe).ok_or(MeasurementError::NotOtofitModel)?;
    let t = Target {
        grid: &npe.header.frequencies_hz,
        cut: npe.header.mask_bands.then_some(npe.header.band_cut_max),
        measures,
    };
    let n = t.grid.len();
    let mut errs = Vec::new();
    let mut x = vec![f64::NAN; measures * n];
    let mut used = Vec::new();
    let blocks = [
        ("stapes_velocity", &m.stapes_velocity, 0),
        ("impedance", &m.impedance, 2),
        ("umbo_velocity", &m.umbo_velocity, 5),
    ];
    for (field, mp, block) in blocks {
        if let Some(mp) = mp
            && mag_phase(field, mp, block, &t, &mut x, &mut errs)
        {
            used.push(field);
        }
    }
    if let Some(a) = &m.absorbance
        && absorbance(a, &t, &mut x, &mut errs)
    {
        used.push("absorbance");
    }
    if errs.is_empty() {
        plausible(&x, t.grid, &mut errs);
    }
    if errs.is_empty() {
        unit_slips(m, &x, t.grid, &mut errs);
    }
    if !errs.is_empty() {
        return Err(MeasurementError::Invalid(errs));
    }
    let present = complete(npe, &x, &used, measures)?;
    Ok((x, present, used))
}

/// Slips of a declared unit that still land inside the physical envelope: phases in
/// cycles declared as radians, and an impedance off by a factor of ten (MΩ for CGS
/// acoustic ohms) that its own absorbance contradicts.
fn unit_slips(m: &Measurements, x: &[f64], grid: &[f64], errs: &mut Vec<(String, String)>) {
    let n = grid.len();
    let blocks = [
        ("stapes_velocity", &m.stapes_velocity, 1),
        ("impedance", &m.impedance, 3),
        ("umbo_velocity", &m.umbo_velocity, 6),
    ];
    for (field, mp, block) in blocks {
        let Some(mp) = mp else { continue };
        let radians = mp.phase_unit.as_deref().is_none_or(|u| u.eq_ignore_ascii_case("rad"));
        let phase: Vec<f64> = x[block * n..(block + 1) * n].iter().copied().filter(|v| v.is_finite()).collect();
        if radians && cycles_as_radians(&phase) {
            errs.push((
                format!("measurements.{field}.phase_unit"),
                format!(
                    "every phase lies within ±{CYCLES_BOUND} rad, which no ear shows over its band (the phase \
                     turns by radians); they look like cycles: send \"phase_unit\": \"cycles\""
                ),
            ));
        }
    }
    if m.impedance.is_some() && m.absorbance.is_some() {
        let mag: Vec<f64> = x[2 * n..3 * n].iter().map(|v| 10f64.powf(*v)).collect();
        if let Some(k) = impedance_scale_slip(&mag, &x[3 * n..4 * n], &x[4 * n..5 * n]) {
            let looks = if k > 1.0 {
                "a larger unit than declared (e.g. MΩ declared as \"cgs\": send \"MOhm\")"
            } else {
                "a smaller unit than declared (e.g. CGS acoustic ohms declared as \"MOhm\": send \"cgs\")"
            };
            errs.push((
                "measurements.impedance.magnitude_unit".into(),
                format!(
                    "the impedance and the absorbance disagree unless the impedance is {k}× what its unit says: \
                     it looks like {looks}"
                ),
            ));
        }
    }
}

/// The largest |phase| (rad) of a curve that is taken for cycles declared as radians.
/// A real ear's impedance phase sits near −1.2 rad at 200 Hz (a compliance), and its
/// velocities' phases fall by several radians of group delay towards 8 kHz.
const CYCLES_BOUND: f64 = 0.5;

/// Whether `phase` (rad, on the model grid) looks like cycles: every value within
/// ±[`CYCLES_BOUND`] over at least 10 grid points.
fn cycles_as_radians(phase: &[f64]) -> bool {
    phase.len() >= 10 && phase.iter().all(|v| v.abs() <= CYCLES_BOUND)
}

/// ρc of air (Pa·s/m) at 22–37 °C, 402–413: its spread is far below the canal area's.
const RHO_C: f64 = 410.0;

/// The factor (10 or 0.1) by which the impedance (|Z| in Pa·s/m³ and its phase in rad,
/// on the grid) must be scaled to agree with the absorbance `a`, when it disagrees as
/// given. Absorbance is 1 − |R|² with R = (Z − Z₀)/(Z + Z₀) at the probe, Z₀ = ρc/A for a
/// canal area A anywhere in the prior's 25–70 mm² (the best one is taken): a factor of
/// ten in |Z| is far outside what the area can explain.
fn impedance_scale_slip(mag: &[f64], phase: &[f64], a: &[f64]) -> Option<f64> {
    let mismatch = |k: f64| {
        (0..=45)
            .map(|i| RHO_C / ((25.0 + i as f64) * 1e-6))
            .map(|z0| {
                let (mut sum, mut count) = (0.0, 0usize);
                for ((m, p), a) in mag.iter().zip(phase).zip(a) {
                    if !(m.is_finite() && p.is_finite() && a.is_finite()) {
                        continue;
                    }
                    let (re, im) = (k * m * p.cos() / z0, k * m * p.sin() / z0);
                    let r2 = ((re - 1.0).powi(2) + im * im) / ((re + 1.0).powi(2) + im * im);
                    sum += (a - (1.0 - r2)).abs();
                    count += 1;
                }
                sum / count.max(1) as f64
            })
            .fold(f64::INFINITY, f64::min)
    };
    let given = mismatch(1.0);
    [10.0, 0.1].into_iter().find(|&k| given > 0.1 && mismatch(k) < 0.5 * given.min(0.1))
}

/// The model's frequency grid, its band cut and how many measures it takes: where the
/// measurements are resampled to.
struct Target<'a> {
    grid: &'a [f64],
    cut: Option<usize>,
    measures: usize,
}

/// A magnitude/phase measure into features `block` (log10 |·|) and `block + 1` (the
/// unwrapped phase); whether it was used.
fn mag_phase(
    field: &'static str,
    mp: &MagPhase,
    block: usize,
    t: &Target,
    x: &mut [f64],
    errs: &mut Vec<(String, String)>,
) -> bool {
    let (grid, n, measures) = (t.grid, t.grid.len(), t.measures);
    let fld = format!("measurements.{field}");
    if block >= measures {
        errs.push((fld, format!("this model was trained on {measures} measures, without {field}")));
        return false;
    }
    let velocity = block != 2;
    let units: &[(&[&str], Option<f64>)] = if velocity { &VELOCITY_UNITS } else { &IMPEDANCE_UNITS };
    let (Some(mag), Some(phase)) = (magnitude_si(&fld, mp, units, errs), phase_rad(&fld, mp, errs)) else {
        return false;
    };
    check_magnitude(&fld, mp, velocity, errs);
    check_values(&format!("{fld}.phase"), &mp.phase, false, errs);
    let logmag: Vec<f64> = mag.iter().map(|v| v.log10()).collect();
    let phase = crate::sim::output::unwrap(phase.into_iter());
    let (Some(a), Some(b)) = (
        resample(&fld, &mp.frequencies_hz, &logmag, grid, t.cut, errs),
        // The same frequencies: their errors are the magnitude's, named once.
        resample(&fld, &mp.frequencies_hz, &phase, grid, t.cut, &mut Vec::new()),
    ) else {
        return false;
    };
    x[block * n..(block + 1) * n].copy_from_slice(&a);
    x[(block + 1) * n..(block + 2) * n].copy_from_slice(&b);
    true
}

/// Magnitudes in decibels may be ≤ 0; linear ones must be > 0, and a velocity that is
/// not gets a hint, since a dB column sent without its unit is the usual cause.
fn check_magnitude(fld: &str, mp: &MagPhase, velocity: bool, errs: &mut Vec<(String, String)>) {
    let decibels = mp.magnitude_unit.as_deref().is_some_and(|u| u.starts_with("dB"));
    if decibels {
        check_values(&format!("{fld}.magnitude"), &mp.magnitude, false, errs);
    } else if mp.magnitude.iter().any(|v| *v <= 0.0) && velocity {
        let i = mp.magnitude.iter().position(|v| *v <= 0.0).unwrap_or(0);
        errs.push((
            format!("{fld}.magnitude[{i}]"),
            "must be > 0 (for decibels send \"magnitude_unit\": \"dB re 1 mm/s/Pa\")".into(),
        ));
    } else {
        check_values(&format!("{fld}.magnitude"), &mp.magnitude, true, errs);
    }
}

/// The absorbance into feature block 4; whether it was used. The envelope (0–1 with five
/// test–retest STDs either side) is the simulator's, `sim::output::MEASURES`.
fn absorbance(a: &Values, t: &Target, x: &mut [f64], errs: &mut Vec<(String, String)>) -> bool {
    let n = t.grid.len();
    check_values("measurements.absorbance.values", &a.values, false, errs);
    let (lo, hi) = crate::sim::output::MEASURES[4].envelope;
    if let Some(i) = a.values.iter().position(|v| !(lo..=hi).contains(v)) {
        errs.push((
            format!("measurements.absorbance.values[{i}]"),
            format!(
                "{} is outside 0–1 (absorbance is a fraction of power; {} either side is allowed for measurement \
                 noise)",
                a.values[i], -lo
            ),
        ));
    }
    let Some(v) = resample("measurements.absorbance", &a.frequencies_hz, &a.values, t.grid, t.cut, errs) else {
        return false;
    };
    x[4 * n..5 * n].copy_from_slice(&v);
    true
}

/// The presence flags, once at least one measure is given and, for a model trained
/// without masking, every one of them.
fn complete(npe: &Npe, x: &[f64], used: &[&str], measures: usize) -> Result<Vec<bool>, MeasurementError> {
    if used.is_empty() {
        return Err(MeasurementError::Invalid(vec![(
            "measurements".into(),
            "give at least one of stapes_velocity, impedance, absorbance, umbo_velocity".into(),
        )]));
    }
    let present: Vec<bool> = x.iter().map(|v| v.is_finite()).collect();
    if !npe.header.mask_groups && present.iter().any(|p| !p) {
        let mut missing: Vec<&str> = FIELDS[..measures].iter().copied().filter(|f| !used.contains(f)).collect();
        missing.dedup();
        return Err(MeasurementError::Invalid(vec![(
            "measurements".into(),
            format!("this model needs every measure; missing: {}", missing.join(", ")),
        )]));
    }
    Ok(present)
}
