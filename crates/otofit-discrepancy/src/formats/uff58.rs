//! Universal File Format dataset 58 (ASCII): the function records vibrometer software
//! exports (frequency response functions of a laser-Doppler vibrometer, e.g. velocity
//! over ear-canal pressure). A file is a sequence of datasets, each between lines `-1`,
//! the second line of each naming its type; only type 58 is read:
//!
//! ```text
//! records 1–5   ID lines (free text)
//! record 6      function type (4 = frequency response function), ids, entities, nodes
//! record 7      ordinate type (2/4 real, 5/6 complex; single/double), point count,
//!               abscissa spacing (0 uneven, 1 even), minimum, increment, z value
//! records 8–11  abscissa, ordinate numerator, ordinate denominator, z axis:
//!               data type (18 frequency, 11 velocity, 15 pressure, ...), unit exponents,
//!               axis label (columns 27–46), units label (columns 48–67)
//! record 12     the values: (x,) re, im per point; spaces separate the fixed-width fields
//! ```
//!
//! The ordinate must be a complex velocity over a pressure (an FRF), the abscissa a
//! frequency in Hz; units come from the units labels (`m/s`, `mm/s`, `um/s` over `Pa`),
//! never guessed. Points at 0 Hz are dropped. The phase is the complex value's argument,
//! read with the e^{+jωt} convention of `sim` (as the velocity-over-pressure FRFs of
//! vibrometer software are: a mass-like response lags); a file written with e^{−jωt}
//! has its phases negated.

use super::{FormatError, Imported};
use crate::measurements::{MagPhase, Measurements};

/// One dataset 58 as read: its ID line, the frequencies (Hz) and the complex ordinate in
/// m/s/Pa as (re, im).
#[derive(Debug)]
pub struct Frf {
    /// The dataset's ID line (record 1).
    pub id: String,
    /// Frequencies, Hz.
    pub frequencies_hz: Vec<f64>,
    /// The FRF in m/s/Pa as (re, im).
    pub values: Vec<(f64, f64)>,
}

/// Velocity units of a numerator: (labels, factor to m/s).
const VELOCITY: [(&[&str], f64); 3] = [(&["m/s"], 1.0), (&["mm/s"], 1e-3), (&["um/s", "µm/s", "micron/s"], 1e-6)];
/// Pressure units of a denominator: (labels, factor to Pa).
const PRESSURE: [(&[&str], f64); 2] = [(&["Pa", "N/m^2", "N/m2"], 1.0), (&["mPa"], 1e-3)];

fn err(line: usize, record: &str, message: String) -> FormatError {
    FormatError::Cell { line, column: record.to_string(), message }
}

/// The characters `from..to` (1-based, inclusive, as the format's columns are counted)
/// of a fixed-width line, trimmed.
fn columns(line: &str, from: usize, to: usize) -> String {
    line.chars().skip(from - 1).take(to + 1 - from).collect::<String>().trim().to_string()
}

/// Data type and units label of records 8–10: (data type, units label).
fn characteristics(line: usize, text: &str, record: &str) -> Result<(i64, String), FormatError> {
    let kind = text
        .split_whitespace()
        .next()
        .and_then(|t| t.parse().ok())
        .ok_or_else(|| err(line, record, format!("'{}' does not start with a data type", text.trim())))?;
    Ok((kind, columns(text, 48, 67)))
}

fn factor(line: usize, record: &str, label: &str, known: &[(&[&str], f64)], what: &str) -> Result<f64, FormatError> {
    known.iter().find(|(names, _)| names.iter().any(|n| n.eq_ignore_ascii_case(label))).map(|(_, k)| *k).ok_or_else(
        || {
            let names: Vec<&str> = known.iter().map(|(n, _)| n[0]).collect();
            err(
                line,
                record,
                format!("units label '{label}': not a {what} unit otofit reads (known: {})", names.join(", ")),
            )
        },
    )
}

/// Every dataset 58 of a file (other dataset types are skipped).
pub fn read_all(text: &str) -> Result<Vec<Frf>, FormatError> {
    let lines: Vec<&str> = text.lines().collect();
    let delimiter = |l: &str| l.trim() == "-1";
    let mut out = Vec::new();
    let mut i = 0;
    let mut datasets = 0;
    while i < lines.len() {
        if !delimiter(lines[i]) {
            if lines[i].trim().is_empty() {
                i += 1;
                continue;
            }
            return Err(FormatError::NotThisFormat(format!(
                "line {}: expected '-1' opening a dataset (a Universal File Format file), found '{}'",
                i + 1,
                lines[i].chars().take(40).collect::<String>()
            )));
        }
        let end = (i + 1..lines.len())
            .find(|&k| delimiter(lines[k]))
            .ok_or_else(|| FormatError::Table(format!("the dataset opened at line {} has no closing '-1'", i + 1)))?;
        datasets += 1;
        if lines.get(i + 1).map(|l| l.trim()) == Some("58") {
            out.push(dataset(&lines, i + 2, end)?);
        }
        i = end + 1;
    }
    if out.is_empty() {
        return Err(FormatError::NotThisFormat(format!(
            "no dataset 58 (function at nodal DOF) among the file's {datasets} datasets"
        )));
    }
    Ok(out)
}

/// Dataset 58 from its first record (line index `start`) up to the closing delimiter.
fn dataset(lines: &[&str], start: usize, end: usize) -> Result<Frf, FormatError> {
    if end < start + 11 {
        return Err(FormatError::Table(format!(
            "the dataset 58 at line {} has {} records before its values; the format has 11",
            start,
            end.saturating_sub(start)
        )));
    }
    let id = lines[start].trim().to_string();
    let layout = layout(lines, start)?;
    let k = scale(lines, start)?;
    values(id, lines, start, end, &layout, k)
}

/// How record 12 lays out the values (record 7): `n` points, evenly spaced from `x0` by
/// `dx`, or each with its own abscissa.
struct Layout {
    n: usize,
    even: bool,
    x0: f64,
    dx: f64,
}

/// Records 6 and 7: an FRF (function type 4) with complex values, since the phase is
/// half of what the measure says.
fn layout(lines: &[&str], start: usize) -> Result<Layout, FormatError> {
    let ln = |k: usize| start + k; // 1-based line number of record k+1
    let function: i64 = lines[start + 5].split_whitespace().next().and_then(|t| t.parse().ok()).unwrap_or(-1);
    if function != 4 {
        return Err(err(
            ln(6),
            "record 6",
            format!("function type {function}: otofit reads frequency response functions (type 4)"),
        ));
    }
    let r7: Vec<f64> =
        lines[start + 6].split_whitespace().filter_map(|t| t.replace(['D', 'd'], "E").parse().ok()).collect();
    if r7.len() < 5 {
        return Err(err(
            ln(7),
            "record 7",
            format!("'{}': expected 3 integers and 3 numbers", lines[start + 6].trim()),
        ));
    }
    let (ordinate, n, even, x0, dx) = (r7[0] as i64, r7[1] as usize, r7[2] as i64 == 1, r7[3], r7[4]);
    if !matches!(ordinate, 5 | 6) {
        return Err(err(
            ln(7),
            "record 7",
            format!("ordinate data type {ordinate}: an FRF needs complex values (5 or 6), for the phase"),
        ));
    }
    Ok(Layout { n, even, x0, dx })
}

/// Records 8–10: the factor from the file's units to m/s/Pa. The data types are checked
/// first so that a wrong kind of spectrum is named as such, not as a unit problem.
fn scale(lines: &[&str], start: usize) -> Result<f64, FormatError> {
    let ln = |k: usize| start + k; // 1-based line number of record k+1
    let (x_kind, x_units) = characteristics(ln(8), lines[start + 7], "record 8")?;
    let (num_kind, num_units) = characteristics(ln(9), lines[start + 8], "record 9")?;
    let (den_kind, den_units) = characteristics(ln(10), lines[start + 9], "record 10")?;
    if x_kind != 18 || !(x_units.is_empty() || x_units.eq_ignore_ascii_case("Hz")) {
        return Err(err(
            ln(8),
            "record 8",
            format!("abscissa data type {x_kind} in '{x_units}': otofit reads spectra over frequency (18) in Hz"),
        ));
    }
    if num_kind != 11 {
        return Err(err(
            ln(9),
            "record 9",
            format!("ordinate numerator data type {num_kind}: otofit reads velocity (11)"),
        ));
    }
    if den_kind != 15 {
        return Err(err(
            ln(10),
            "record 10",
            format!("ordinate denominator data type {den_kind}: otofit reads velocity over pressure (15)"),
        ));
    }
    Ok(factor(ln(9), "record 9", &num_units, &VELOCITY, "velocity")?
        / factor(ln(10), "record 10", &den_units, &PRESSURE, "pressure")?)
}

/// Record 12: the frequencies and (re, im) values scaled by `k`, as dataset `id`. Points
/// at or below 0 Hz are dropped (a DC bin has no phase and no place on a log-frequency
/// grid).
fn values(id: String, lines: &[&str], start: usize, end: usize, layout: &Layout, k: f64) -> Result<Frf, FormatError> {
    let &Layout { n, even, x0, dx } = layout;
    let mut numbers = Vec::new();
    for (j, l) in lines[start + 11..end].iter().enumerate() {
        for t in l.split_whitespace() {
            let v: f64 = t
                .replace(['D', 'd'], "E")
                .parse()
                .map_err(|_| err(start + 12 + j, "record 12", format!("'{t}' is not a number")))?;
            numbers.push(v);
        }
    }
    let per = if even { 2 } else { 3 };
    if numbers.len() != n * per {
        return Err(err(
            start + 12,
            "record 12",
            format!(
                "{} numbers for {n} {} points (record 7)",
                numbers.len(),
                if even { "complex" } else { "(x, complex)" }
            ),
        ));
    }
    let (mut f, mut values) = (Vec::with_capacity(n), Vec::with_capacity(n));
    for (p, c) in numbers.chunks(per).enumerate() {
        let x = if even { x0 + dx * p as f64 } else { c[0] };
        if x <= 0.0 {
            continue;
        }
        f.push(x);
        values.push((c[per - 2] * k, c[per - 1] * k));
    }
    Ok(Frf { id, frequencies_hz: f, values })
}

/// The measure a dataset 58 holds (the file does not say which point the laser saw).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Measure {
    /// The stapes, as an LDV on a temporal bone sees it.
    StapesVelocity,
    /// The umbo, as clinical LDV through the ear canal sees it.
    UmboVelocity,
}

impl std::str::FromStr for Measure {
    type Err = String;

    fn from_str(s: &str) -> Result<Measure, String> {
        match s {
            "stapes_velocity" => Ok(Measure::StapesVelocity),
            "umbo_velocity" => Ok(Measure::UmboVelocity),
            _ => Err(format!("unknown measure '{s}' (known: stapes_velocity, umbo_velocity)")),
        }
    }
}

/// Dataset number `pick` (1-based; `None`: the only one) of a file as `measure`.
pub fn read(text: &str, pick: Option<usize>, measure: Measure) -> Result<Imported, FormatError> {
    let all = read_all(text)?;
    let frf = match pick {
        Some(k) if (1..=all.len()).contains(&k) => &all[k - 1],
        None if all.len() == 1 => &all[0],
        _ => {
            let list: Vec<String> = all.iter().enumerate().map(|(k, d)| format!("{}: {}", k + 1, d.id)).collect();
            return Err(FormatError::Table(format!(
                "the file holds {} datasets 58; pick one with --dataset N ({})",
                all.len(),
                list.join("; ")
            )));
        }
    };
    let mag: Vec<f64> = frf.values.iter().map(|(re, im)| re.hypot(*im)).collect();
    let phase: Vec<f64> = frf.values.iter().map(|(re, im)| im.atan2(*re)).collect();
    let mp = MagPhase {
        frequencies_hz: frf.frequencies_hz.clone(),
        magnitude: mag,
        phase,
        magnitude_unit: Some("m/s/Pa".into()),
        phase_unit: Some("rad".into()),
    };
    let mut m = Measurements::default();
    let field = match measure {
        Measure::StapesVelocity => {
            m.stapes_velocity = Some(mp);
            "measurements.stapes_velocity"
        }
        Measure::UmboVelocity => {
            m.umbo_velocity = Some(mp);
            "measurements.umbo_velocity"
        }
    };
    let notes = vec![format!(
        "dataset 58 '{}': {} points, {:.0}–{:.0} Hz, as {field}",
        frf.id,
        frf.frequencies_hz.len(),
        frf.frequencies_hz.first().copied().unwrap_or(0.0),
        frf.frequencies_hz.last().copied().unwrap_or(0.0)
    )];
    Ok(Imported { measurements: m, notes, columns: vec![(field.into(), "record 12".into())] })
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A dataset 58 with `values` (re, im) at even spacing from `x0` by `dx`.
    fn even(x0: f64, dx: f64, values: &[(f64, f64)], num: &str, den: &str) -> String {
        let mut s = String::from("    -1\n    58\nLDV umbo\nNONE\nNONE\nNONE\nNONE\n");
        s += "    4         1    1         0 NONE               1   3 NONE               1   3\n";
        s += &format!("         6{:10}         1{:13.5E}{:13.5E}  0.00000E+00\n", values.len(), x0, dx);
        s += "        18    0    0    0 Frequency            Hz                  \n";
        s += &format!("        11    1    0    0 Velocity             {num:<20}\n");
        s += &format!("        15   -2    1    0 Pressure             {den:<20}\n");
        s += "         0    0    0    0 NONE                 NONE                \n";
        for c in values.chunks(2) {
            s += &c.iter().map(|(r, i)| format!("{r:20.12E}{i:20.12E}")).collect::<String>();
            s += "\n";
        }
        s + "    -1\n"
    }

    #[test]
    fn an_even_complex_double_frf_in_mm_per_s_per_pa() {
        let v = [(0.0, 0.0), (1e-2, 2e-2), (-3e-2, 1e-2)];
        let text = format!("    -1\n   151\nheader\n    -1\n{}", even(0.0, 500.0, &v, "mm/s", "Pa"));
        let imp = read(&text, None, Measure::StapesVelocity).unwrap();
        let s = imp.measurements.stapes_velocity.as_ref().unwrap();
        assert_eq!(s.frequencies_hz, [500.0, 1000.0], "the 0 Hz point is dropped");
        assert!((s.magnitude[0] - 1e-3 * 5f64.sqrt() * 1e-2).abs() < 1e-15, "{:?}", s.magnitude);
        assert!((s.phase[1] - 1f64.atan2(-3.0)).abs() < 1e-12);
        assert!(imp.notes[0].contains("LDV umbo"), "{:?}", imp.notes);
    }

    #[test]
    fn errors_name_the_record() {
        let v = [(1e-2, 2e-2), (-3e-2, 1e-2)];
        let e = read(&even(200.0, 500.0, &v, "in/s", "Pa"), None, Measure::StapesVelocity).unwrap_err();
        assert!(e.field() == "record 9[line 11]" && e.message().contains("'in/s'"), "{e}");
        let e = read(&even(200.0, 500.0, &v, "m/s", "psi"), None, Measure::StapesVelocity).unwrap_err();
        assert_eq!(e.field(), "record 10[line 12]", "{e}");
        let two = even(200.0, 500.0, &v, "m/s", "Pa") + &even(200.0, 500.0, &v, "m/s", "Pa");
        let e = read(&two, None, Measure::StapesVelocity).unwrap_err();
        assert!(e.message().contains("--dataset N (1: LDV umbo; 2: LDV umbo)"), "{e}");
        assert!(read(&two, Some(2), Measure::StapesVelocity).is_ok());
        let umbo = read(&two, Some(1), Measure::UmboVelocity).unwrap();
        assert!(umbo.measurements.umbo_velocity.is_some() && umbo.measurements.stapes_velocity.is_none());
        assert_eq!(umbo.columns[0].0, "measurements.umbo_velocity");
        assert!("umbo".parse::<Measure>().unwrap_err().contains("umbo_velocity"));
        let short = even(200.0, 500.0, &v, "m/s", "Pa").replacen("         2         1", "         3         1", 1);
        let e = read(&short, None, Measure::StapesVelocity).unwrap_err();
        assert!(e.field().starts_with("record 12") && e.message().contains("4 numbers for 3"), "{e}");
        let e = read("Frequency,Absorbance\n", None, Measure::StapesVelocity).unwrap_err();
        assert!(matches!(e, FormatError::NotThisFormat(_)), "{e}");
    }
}
