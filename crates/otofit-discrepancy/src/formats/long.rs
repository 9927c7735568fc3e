//! Long-layout tables: one row per frequency, one column per quantity, as the WAI
//! database and wideband-tympanometry devices export them —
//!
//! ```text
//! Subject,Ear,Frequency,Absorbance,Zmag [Pa*s/m^3],Zang [cycles]
//! S01,Left,226,0.038,8.36e7,-0.236
//! ```
//!
//! Admittance becomes the impedance (Z = 1/Y) and reflectance the absorbance (1 − |R|²)
//! and, with its phase and the canal area, the impedance ([`super::immittance`]).
//!
//! Columns are found by name (case, spaces and punctuation ignored; see [`COLUMNS`]);
//! other columns are kept only for `select`. A column's unit is written in its header
//! (`Zang [deg]`, `Frequency (kHz)`) or declared by the caller (`--unit Zang=deg`, a
//! `unit=Zang=deg` query parameter), or comes from a preset ([`Preset::Wai`]: Zmag in
//! Pa·s/m³, Zang in cycles, as the WAI database stores them). A magnitude or phase
//! without a unit is an error naming the column: units are never guessed. Frequency
//! defaults to Hz and absorbance to a fraction (0–1), the quantities' own units.
//!
//! A cell that is empty (or `NA`, `NaN`) means "not measured at this frequency": each
//! measure keeps the rows where it has values, on its own grid.

use super::{FormatError, Imported};
use crate::measurements::{IMPEDANCE_UNITS, MagPhase, Measurements, PHASE_UNITS, VELOCITY_UNITS, Values};

/// What a column holds.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Quantity {
    /// Frequency, Hz by default.
    Frequency,
    /// Absorbance, a fraction by default.
    Absorbance,
    /// |Z| of the ear-canal impedance.
    Zmag,
    /// ∠Z.
    Zang,
    /// |V_stapes/P_ec|.
    VstMag,
    /// ∠(V_stapes/P_ec).
    VstAng,
    /// |V_umbo/P_ec| (clinical LDV through the canal).
    VuMag,
    /// ∠(V_umbo/P_ec).
    VuAng,
    /// |Y| of the ear-canal admittance (1/Z).
    Ymag,
    /// ∠Y.
    Yang,
    /// |R| of the pressure reflectance.
    Rmag,
    /// ∠R.
    Rang,
    /// |R|², the power reflectance (1 − absorbance).
    PowerReflectance,
    /// The ear canal's cross-section at the probe (the WAI database's AreaCanal).
    Area,
}

/// Each quantity's canonical column name and the names it is found by (lower case,
/// letters and digits only: `|Z|` is `z`, `Zang_deg` would be `zangdeg`).
pub const COLUMNS: [(Quantity, &str, &[&str]); 14] = [
    (Quantity::Frequency, "Frequency", &["frequency", "freq", "f", "hz", "frequencyhz"]),
    (Quantity::Absorbance, "Absorbance", &["absorbance", "a", "powerabsorbance", "energyabsorbance"]),
    (Quantity::Zmag, "Zmag", &["zmag", "z", "zmagnitude", "impedancemagnitude", "impedancemag"]),
    (Quantity::Zang, "Zang", &["zang", "zangle", "zphase", "impedanceangle", "impedancephase"]),
    (Quantity::VstMag, "VstMag", &["vstmag", "vst", "stapesvelocity", "stapesvelocitymagnitude", "stapesvelocitymag"]),
    (Quantity::VstAng, "VstAng", &["vstang", "vstphase", "stapesvelocityphase", "stapesvelocityangle"]),
    (Quantity::VuMag, "VuMag", &["vumag", "vu", "umbovelocity", "umbovelocitymagnitude", "umbovelocitymag"]),
    (Quantity::VuAng, "VuAng", &["vuang", "vuphase", "umbovelocityphase", "umbovelocityangle"]),
    (Quantity::Ymag, "Ymag", &["ymag", "y", "ymagnitude", "admittancemagnitude", "admittancemag", "admittance"]),
    (Quantity::Yang, "Yang", &["yang", "yangle", "yphase", "admittanceangle", "admittancephase"]),
    (
        Quantity::Rmag,
        "Rmag",
        &["rmag", "r", "reflectancemagnitude", "reflectancemag", "pressurereflectance", "pressurereflectancemagnitude"],
    ),
    (
        Quantity::Rang,
        "Rang",
        &["rang", "rangle", "rphase", "reflectanceangle", "reflectancephase", "pressurereflectancephase"],
    ),
    (Quantity::PowerReflectance, "PowerReflectance", &["powerreflectance", "energyreflectance", "r2"]),
    (Quantity::Area, "AreaCanal", &["areacanal", "canalarea", "area"]),
];

/// Phase units: (accepted names, the name `measurements` knows).
const PHASE: [(&[&str], &str); 3] = [
    (&["rad", "radians", "radian"], "rad"),
    (&["deg", "degrees", "degree", "°"], "deg"),
    (&["cycles", "cycle", "cyc"], "cycles"),
];
/// Frequency units: (accepted names, factor to Hz).
const FREQUENCY: [(&[&str], f64); 2] = [(&["Hz"], 1.0), (&["kHz"], 1e3)];
/// Absorbance and reflectance units: (accepted names, factor to a fraction).
const FRACTION: [(&[&str], f64); 2] = [(&["1", "fraction"], 1.0), (&["%", "percent"], 0.01)];
/// Admittance units: (accepted names, factor to m³/(Pa·s)). The acoustic mho of
/// tympanometry is the CGS one, cm⁵/(dyn·s) = 1e-5 m³/(Pa·s); 1 mmho ≈ the admittance of
/// 1 cm³ of air at 226 Hz.
const ADMITTANCE: [(&[&str], f64); 4] = [
    (&["m^3/(Pa*s)", "m³/(Pa·s)", "SI"], 1.0),
    (&["mmho", "acoustic mmho"], 1e-8),
    (&["umho", "µmho"], 1e-11),
    (&["mho", "cgs", "cm^5/(dyn*s)"], 1e-5),
];
/// Canal cross-section units: (accepted names, factor to m²).
const AREA: [(&[&str], f64); 3] =
    [(&["mm2", "mm²", "mm^2"], 1e-6), (&["cm2", "cm²", "cm^2"], 1e-4), (&["m2", "m²", "m^2"], 1.0)];
/// Adult ear-canal cross-sections, m²: outside, the unit is likely wrong.
const AREA_RANGE: (f64, f64) = (10e-6, 150e-6);

/// Units a family of exports always uses, for columns whose header declares none.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Preset {
    /// The WAI database: Zmag in SI acoustic ohms (Pa·s/m³), Zang in cycles.
    Wai,
}

impl std::str::FromStr for Preset {
    type Err = String;

    fn from_str(s: &str) -> Result<Preset, String> {
        match s.to_ascii_lowercase().as_str() {
            "wai" => Ok(Preset::Wai),
            _ => Err(format!("unknown preset '{s}' (known: wai)")),
        }
    }
}

impl Preset {
    fn unit(self, q: Quantity) -> Option<&'static str> {
        match (self, q) {
            (Preset::Wai, Quantity::Zmag) => Some("Pa·s/m³"),
            (Preset::Wai, Quantity::Zang) => Some("cycles"),
            _ => None,
        }
    }
}

/// How to read a table.
#[derive(Clone, Debug, Default)]
pub struct LongOptions {
    /// Units declared outside the header: (column as its header names it, unit).
    pub units: Vec<(String, String)>,
    /// Keep only the rows where a column holds a value (one ear, one session).
    pub select: Vec<(String, String)>,
    /// Units for the columns that declare none.
    pub preset: Option<Preset>,
}

/// Splits `COLUMN=VALUE` (a `--unit`, `--select` or query argument).
pub fn pair(arg: &str, what: &str) -> Result<(String, String), String> {
    match arg.split_once('=') {
        Some((c, v)) if !c.trim().is_empty() => Ok((c.trim().to_string(), v.trim().to_string())),
        _ => Err(format!("{what} '{arg}': expected COLUMN=VALUE")),
    }
}

struct Col {
    index: usize,
    quantity: Quantity,
    /// As the header names it, without its unit.
    name: String,
    unit: Option<String>,
}

fn normalise(name: &str) -> String {
    name.chars().filter(|c| c.is_alphanumeric()).flat_map(char::to_lowercase).collect()
}

/// A header cell's name and unit: `Zmag [cgs]` → (`Zmag`, `cgs`); `Ymag (m^3/(Pa*s))`
/// → (`Ymag`, `m^3/(Pa*s)`).
fn split_unit(cell: &str) -> (String, Option<String>) {
    let c = cell.trim();
    for (open, close) in [('[', ']'), ('(', ')')] {
        if !c.ends_with(close) {
            continue;
        }
        let mut depth = 0;
        for (i, ch) in c.char_indices().rev() {
            if ch == close {
                depth += 1;
            } else if ch == open {
                depth -= 1;
                if depth == 0 {
                    let unit = c[i + open.len_utf8()..c.len() - close.len_utf8()].trim();
                    return (c[..i].trim().to_string(), Some(unit.to_string()));
                }
            }
        }
    }
    (c.to_string(), None)
}

/// The delimiter of a header line: tab, semicolon (without commas) or comma.
fn delimiter(header: &str) -> char {
    // Only delimiters outside quoted fields count: a quoted "Smith, J" is one cell.
    let bare: String = header.split('"').step_by(2).collect();
    if bare.contains('\t') {
        '\t'
    } else if bare.contains(';') && !bare.contains(',') {
        ';'
    } else {
        ','
    }
}

/// The cells of one line (RFC 4180 quoting: a delimiter inside quotes is text, `""`
/// inside quotes is one quote), each trimmed.
fn cells(line: &str, d: char) -> Vec<String> {
    let (mut out, mut cell, mut quoted) = (Vec::new(), String::new(), false);
    let mut chars = line.chars().peekable();
    while let Some(c) = chars.next() {
        match c {
            '"' if quoted && chars.peek() == Some(&'"') => {
                cell.push('"');
                chars.next();
            }
            '"' => quoted = !quoted,
            c if c == d && !quoted => out.push(std::mem::take(&mut cell).trim().to_string()),
            c => cell.push(c),
        }
    }
    out.push(cell.trim().to_string());
    out
}

/// Whether a CSV header line is a long-layout table (it has a frequency column and no
/// `measure@frequency` feature names).
pub fn looks_long(header: &str) -> bool {
    let hs = cells(header, delimiter(header));
    !hs.iter().any(|h| h.contains('@')) && hs.iter().any(|h| quantity(&split_unit(h).0) == Some(Quantity::Frequency))
}

fn quantity(name: &str) -> Option<Quantity> {
    let n = normalise(name);
    COLUMNS.iter().find(|(_, _, names)| names.contains(&n.as_str())).map(|(q, _, _)| *q)
}

fn canonical(q: Quantity) -> &'static str {
    COLUMNS.iter().find(|(c, _, _)| *c == q).map_or("?", |(_, n, _)| n)
}

/// The entry of `known` that `col`'s unit names; an error naming the column when it has
/// none (and `default` is `None`) or an unknown one.
fn unit<'a, T: Copy>(col: &Col, known: &'a [(&'a [&'a str], T)], default: Option<T>) -> Result<T, FormatError> {
    let listed = || known.iter().map(|(n, _)| n[0]).collect::<Vec<_>>().join(", ");
    let Some(u) = &col.unit else {
        return default.ok_or_else(|| FormatError::Column {
            column: col.name.clone(),
            message: format!(
                "no unit: write it in the header ('{0} [{1}]') or declare it (--unit {0}={1}, or unit={0}={1} in the query); \
                 known units: {2}",
                col.name,
                known[0].0[0],
                listed()
            ),
        });
    };
    known.iter().find(|(names, _)| names.iter().any(|n| n.eq_ignore_ascii_case(u))).map(|(_, v)| *v).ok_or_else(|| {
        FormatError::Column { column: col.name.clone(), message: format!("unknown unit '{u}' (known: {})", listed()) }
    })
}

fn empty(c: &str) -> bool {
    c.is_empty() || ["na", "nan", "n/a"].contains(&c.to_ascii_lowercase().as_str())
}

/// The header's cells: (name, unit).
type Header = Vec<(String, Option<String>)>;

/// The table's data rows after `select`: (line number, cells).
type Rows = Vec<(usize, Vec<String>)>;

/// The rows where every column of `cols` has a value: their frequencies and the values
/// of each column. A row with some of them but not all is an error naming the empty cell.
fn series(rows: &Rows, f: &[f64], cols: &[&Col]) -> Result<(Vec<f64>, Vec<Vec<f64>>), FormatError> {
    let mut freq = Vec::new();
    let mut vals = vec![Vec::new(); cols.len()];
    for ((line, r), fr) in rows.iter().zip(f) {
        let have: Vec<bool> = cols.iter().map(|c| !empty(&r[c.index])).collect();
        if !have.iter().any(|h| *h) {
            continue;
        }
        if let Some(k) = have.iter().position(|h| !h) {
            let given = cols.iter().find(|c| !empty(&r[c.index])).map_or("", |c| c.name.as_str());
            return Err(FormatError::Cell {
                line: *line,
                column: cols[k].name.clone(),
                message: format!("empty where '{given}' has a value: give both or neither"),
            });
        }
        for (c, v) in cols.iter().zip(vals.iter_mut()) {
            v.push(number(*line, c, &r[c.index])?);
        }
        freq.push(*fr);
    }
    Ok((freq, vals))
}

fn number(line: usize, col: &Col, cell: &str) -> Result<f64, FormatError> {
    let bad = |message: String| FormatError::Cell { line, column: col.name.clone(), message };
    let v: f64 = cell.parse().map_err(|_| {
        bad(if cell.contains(',') {
            format!("'{cell}' is not a number (decimal commas are not read: export with decimal points)")
        } else {
            format!("'{cell}' is not a number")
        })
    })?;
    if !v.is_finite() {
        return Err(bad(format!("'{cell}' is not a finite number")));
    }
    Ok(v)
}

/// Reads a long-layout table into measurements.
pub fn read(text: &str, opts: &LongOptions) -> Result<Imported, FormatError> {
    let mut lines = text
        .lines()
        .enumerate()
        .map(|(i, l)| (i + 1, l))
        .filter(|(_, l)| !l.trim().is_empty() && !l.trim_start().starts_with('#'));
    let Some((_, head)) = lines.next() else {
        return Err(FormatError::NotThisFormat("empty: expected a CSV table with a header row".into()));
    };
    let (d, header) = header(head)?;
    let names: Vec<&str> = header.iter().map(|(n, _)| n.as_str()).collect();
    let cols = columns(&header, opts)?;
    let find = |q: Quantity| cols.iter().find(|c| c.quantity == q);
    let Some(fcol) = find(Quantity::Frequency) else {
        return Err(FormatError::Column {
            column: "Frequency".into(),
            message: format!("no frequency column (Frequency, Freq, f or Hz); the columns are {}", names.join(", ")),
        });
    };
    let (rows, mut notes) = select(lines, d, &names, opts)?;
    let f = frequencies(&rows, fcol, &names)?;
    let t = Table { rows: &rows, f: &f };
    let (measurements, columns) = measures(&t, &find, fcol, &names, &mut notes)?;
    Ok(Imported { measurements, notes, columns })
}

/// The header line's delimiter and its cells as (name, unit). JSON is told apart here so
/// that a JSON body sent as CSV gets an error that says so rather than one about columns.
fn header(head: &str) -> Result<(char, Header), FormatError> {
    let head = head.trim_start_matches('\u{feff}');
    if head.trim_start().starts_with('{') || head.trim_start().starts_with('[') {
        return Err(FormatError::NotThisFormat(
            "looks like JSON, not a CSV table (send JSON as application/json, or name the file .json)".into(),
        ));
    }
    let d = delimiter(head);
    let header: Header = cells(head, d).iter().map(|c| split_unit(c)).collect();
    if header.len() < 2 {
        return Err(FormatError::NotThisFormat(format!(
            "not a CSV table with a header row (the first line is '{}')",
            head.chars().take(60).collect::<String>()
        )));
    }
    Ok((d, header))
}

/// The columns otofit reads, each with its unit: from the header, else declared by the
/// caller, else from the preset. A header and a declaration that disagree is an error
/// rather than a silent choice, since either could be the wrong one.
fn columns(header: &Header, opts: &LongOptions) -> Result<Vec<Col>, FormatError> {
    let mut cols: Vec<Col> = Vec::new();
    for (index, (name, u)) in header.iter().enumerate() {
        let Some(q) = quantity(name) else { continue };
        if let Some(prev) = cols.iter().find(|c| c.quantity == q) {
            return Err(FormatError::Column {
                column: name.clone(),
                message: format!("holds {} as column '{}' does: keep one", canonical(q), prev.name),
            });
        }
        cols.push(Col { index, quantity: q, name: name.clone(), unit: u.clone() });
    }
    for (c, u) in &opts.units {
        let Some(col) = cols.iter_mut().find(|col| col.name.eq_ignore_ascii_case(c)) else {
            let read: Vec<&str> = cols.iter().map(|c| c.name.as_str()).collect();
            return Err(FormatError::Column {
                column: c.clone(),
                message: format!(
                    "a unit is declared for it, but no column of that name is read (read: {})",
                    read.join(", ")
                ),
            });
        };
        match &col.unit {
            Some(h) if !h.eq_ignore_ascii_case(u) => {
                return Err(FormatError::Column {
                    column: col.name.clone(),
                    message: format!("the header says '{h}' and the declared unit is '{u}': keep one"),
                });
            }
            _ => col.unit = Some(u.clone()),
        }
    }
    for col in &mut cols {
        if col.unit.is_none() {
            col.unit = opts.preset.and_then(|p| p.unit(col.quantity)).map(str::to_string);
        }
    }
    Ok(cols)
}

/// The data rows that pass `select`, and a note of how many were kept (a wrong select
/// that keeps too few rows should be visible in the result, not only as an error).
fn select<'l>(
    lines: impl Iterator<Item = (usize, &'l str)>,
    d: char,
    names: &[&str],
    opts: &LongOptions,
) -> Result<(Rows, Vec<String>), FormatError> {
    let mut filters = Vec::new();
    for (c, v) in &opts.select {
        let Some(i) = names.iter().position(|n| n.eq_ignore_ascii_case(c)) else {
            return Err(FormatError::Column {
                column: c.clone(),
                message: format!("select names no column of the table (columns: {})", names.join(", ")),
            });
        };
        filters.push((i, v.clone()));
    }
    let mut rows: Rows = Vec::new();
    let mut total = 0;
    for (line, l) in lines {
        let r = cells(l, d);
        if r.len() != names.len() {
            return Err(FormatError::Table(format!(
                "line {line} has {} cells, the header {} (delimiter '{}')",
                r.len(),
                names.len(),
                d.escape_default()
            )));
        }
        total += 1;
        if filters.iter().all(|(i, v)| &r[*i] == v) {
            rows.push((line, r));
        }
    }
    let mut notes = Vec::new();
    if !filters.is_empty() {
        let s: Vec<String> = opts.select.iter().map(|(c, v)| format!("{c}={v}")).collect();
        notes.push(format!("kept {} of {total} rows ({})", rows.len(), s.join(", ")));
    }
    if rows.len() < 2 {
        return Err(FormatError::Table(format!(
            "{} data rows{}; need at least 2 frequencies",
            rows.len(),
            if filters.is_empty() { "" } else { " left after select" }
        )));
    }
    Ok((rows, notes))
}

/// The rows' frequencies in Hz. They must increase: a table that repeats them most often
/// holds several ears or sessions, and the error says how to pick one.
fn frequencies(rows: &Rows, fcol: &Col, names: &[&str]) -> Result<Vec<f64>, FormatError> {
    let hz = unit(fcol, &FREQUENCY, Some(1.0))?;
    let mut f = Vec::with_capacity(rows.len());
    for (line, r) in rows {
        let v = number(*line, fcol, &r[fcol.index])? * hz;
        if v <= 0.0 {
            return Err(FormatError::Cell { line: *line, column: fcol.name.clone(), message: "must be > 0".into() });
        }
        f.push(v);
    }
    if let Some(k) = (1..f.len()).find(|&k| f[k] <= f[k - 1]) {
        let others: Vec<&str> = names.iter().copied().filter(|n| quantity(n).is_none()).collect();
        return Err(FormatError::Table(format!(
            "frequencies do not increase at line {} ({} Hz after {} Hz): several ears or sessions in one table? pick \
             one with --select COLUMN=VALUE (over HTTP a select=COLUMN=VALUE query parameter){}",
            rows[k].0,
            f[k],
            f[k - 1],
            if others.is_empty() { String::new() } else { format!(" (other columns: {})", others.join(", ")) }
        )));
    }
    Ok(f)
}

/// Every measure the columns give, and which column each measurement field came from (so
/// that a later validation error names the table's column, not a JSON path).
fn measures<'c>(
    t: &Table,
    find: &impl Fn(Quantity) -> Option<&'c Col>,
    fcol: &Col,
    names: &[&str],
    notes: &mut Vec<String>,
) -> Result<(Measurements, Vec<(String, String)>), FormatError> {
    let mut m = Measurements::default();
    let mut columns = Vec::new();
    m.absorbance = absorbance(t, find, &mut columns, notes)?;
    m.impedance = impedance(t, find, &mut columns, notes)?;
    m.stapes_velocity =
        mag_phase(t, find(Quantity::VstMag), find(Quantity::VstAng), &VELOCITY_UNITS, "stapes_velocity", &mut columns)?;
    m.umbo_velocity =
        mag_phase(t, find(Quantity::VuMag), find(Quantity::VuAng), &VELOCITY_UNITS, "umbo_velocity", &mut columns)?;
    // An error about a measure's frequencies is one about the frequency column.
    let given = [
        ("impedance", m.impedance.is_some()),
        ("absorbance", m.absorbance.is_some()),
        ("stapes_velocity", m.stapes_velocity.is_some()),
        ("umbo_velocity", m.umbo_velocity.is_some()),
    ];
    for (field, _) in given.into_iter().filter(|(_, on)| *on) {
        columns.insert(0, (format!("measurements.{field}.frequencies_hz"), fcol.name.clone()));
    }
    if m.absorbance.is_none() && m.impedance.is_none() && m.stapes_velocity.is_none() && m.umbo_velocity.is_none() {
        let known: Vec<&str> = COLUMNS.iter().skip(1).map(|(_, n, _)| *n).collect();
        return Err(FormatError::Table(format!(
            "no measure found: the columns are {}; otofit reads {}",
            names.join(", "),
            known.join(", ")
        )));
    }
    Ok((m, columns))
}

/// The selected rows and their frequencies (Hz).
struct Table<'a> {
    rows: &'a Rows,
    f: &'a [f64],
}

/// Absorbance from an Absorbance column, else from power reflectance (1 − |R|²), else
/// from |R| (1 − |R|²).
fn absorbance<'c>(
    t: &Table,
    find: &impl Fn(Quantity) -> Option<&'c Col>,
    columns: &mut Vec<(String, String)>,
    notes: &mut Vec<String>,
) -> Result<Option<Values>, FormatError> {
    let (a, pr) = (find(Quantity::Absorbance), find(Quantity::PowerReflectance));
    if let (Some(a), Some(pr)) = (a, pr) {
        return Err(FormatError::Column {
            column: pr.name.clone(),
            message: format!("gives the absorbance (1 − power reflectance) that column '{}' gives: keep one", a.name),
        });
    }
    let Some((c, from_r)) =
        a.map(|c| (c, None)).or(pr.map(|c| (c, Some(1)))).or(find(Quantity::Rmag).map(|c| (c, Some(2))))
    else {
        return Ok(None);
    };
    let k = unit(c, &FRACTION, Some(1.0))?;
    let (fa, v) = series(t.rows, t.f, &[c])?;
    let top = if from_r == Some(2) { 1.03 } else { 1.05 };
    if let Some(i) = v[0].iter().position(|a| *a < 0.0 || *a * k > top) {
        let percent = if c.unit.is_none() && v[0][i] > 1.0 {
            format!("; in percent? write '{} [%]' in the header", c.name)
        } else {
            String::new()
        };
        return Err(FormatError::Column {
            column: c.name.clone(),
            message: format!("{} is outside 0–1 (a fraction of power or pressure){percent}", v[0][i]),
        });
    }
    if fa.is_empty() {
        return Ok(None);
    }
    let values: Vec<f64> = match from_r {
        None => v[0].iter().map(|a| a * k).collect(),
        Some(1) => v[0].iter().map(|r2| 1.0 - r2 * k).collect(),
        _ => v[0].iter().map(|r| 1.0 - (r * k).powi(2)).collect(),
    };
    if from_r.is_some() {
        notes.push(format!("absorbance from {}: A = 1 − |R|²", c.name));
    }
    columns.push(("measurements.absorbance".to_string(), c.name.clone()));
    Ok(Some(Values { frequencies_hz: fa, values }))
}

/// The impedance from Zmag + Zang, else from an admittance (Z = 1/Y), else from pressure
/// reflectance and the canal area (Z = Z0 (1 + R)/(1 − R), Z0 = ρc/S).
fn impedance<'c>(
    t: &Table,
    find: &impl Fn(Quantity) -> Option<&'c Col>,
    columns: &mut Vec<(String, String)>,
    notes: &mut Vec<String>,
) -> Result<Option<MagPhase>, FormatError> {
    let (zm, za) = (find(Quantity::Zmag), find(Quantity::Zang));
    let (ym, ya) = (find(Quantity::Ymag), find(Quantity::Yang));
    let (rm, ra, area) = (find(Quantity::Rmag), find(Quantity::Rang), find(Quantity::Area));
    let unused = |notes: &mut Vec<String>, why: &str| {
        let cols: Vec<&str> = [ra, area].into_iter().flatten().map(|c| c.name.as_str()).collect();
        if !cols.is_empty() {
            notes.push(format!("{} not used: {why}", cols.join(", ")));
        }
    };
    if zm.is_some() || za.is_some() {
        if let Some(y) = ym.or(ya) {
            return Err(FormatError::Column {
                column: y.name.clone(),
                message: "the table gives the impedance (Zmag, Zang) too: keep one".into(),
            });
        }
        unused(notes, "the impedance was given as measured (the model infers the canal area with the tissue)");
        return mag_phase(t, zm, za, &IMPEDANCE_UNITS, "impedance", columns);
    }
    if let Some((ym, ya)) = both(ym, ya)? {
        let z = from_admittance(t, ym, ya, columns, notes)?;
        if z.is_some() {
            unused(notes, "the impedance came from the admittance");
        }
        return Ok(z);
    }
    let (Some(rm), Some(ra)) = (rm, ra) else {
        unused(notes, "no impedance, admittance or reflectance phase to use it with");
        return Ok(None);
    };
    let Some(area) = area else {
        notes.push(format!(
            "{} not used: an impedance from reflectance needs the canal area (an AreaCanal column); absorbance only",
            ra.name
        ));
        return Ok(None);
    };
    from_reflectance(t, [rm, ra, area], columns, notes)
}

/// The impedance from an admittance column pair: |Z| = 1/|Y|, ∠Z = −∠Y, in the phase's
/// own unit (negating an angle needs no conversion).
fn from_admittance(
    t: &Table,
    ym: &Col,
    ya: &Col,
    columns: &mut Vec<(String, String)>,
    notes: &mut Vec<String>,
) -> Result<Option<MagPhase>, FormatError> {
    use super::immittance;
    let k = unit(ym, &ADMITTANCE, None)?;
    let phase_unit = unit(ya, &PHASE, None)?;
    let (fy, v) = series(t.rows, t.f, &[ym, ya])?;
    if fy.is_empty() {
        return Ok(None);
    }
    let mut z = MagPhase {
        frequencies_hz: fy,
        magnitude: Vec::new(),
        phase: Vec::new(),
        magnitude_unit: Some("Pa·s/m³".into()),
        phase_unit: Some(phase_unit.into()),
    };
    for (y, p) in v[0].iter().zip(&v[1]) {
        if *y <= 0.0 {
            return Err(FormatError::Column {
                column: ym.name.clone(),
                message: format!("{y}: an admittance magnitude must be > 0"),
            });
        }
        let (m, p) = immittance::impedance_from_admittance(y * k, *p);
        z.magnitude.push(m);
        z.phase.push(p);
    }
    notes.push(format!("impedance from the admittance {}, {}: |Z| = 1/|Y|, ∠Z = −∠Y", ym.name, ya.name));
    columns.push(("measurements.impedance.magnitude".into(), ym.name.clone()));
    columns.push(("measurements.impedance.phase".into(), ya.name.clone()));
    Ok(Some(z))
}

/// The impedance from pressure reflectance and the canal area, Z = Z0 (1 + R)/(1 − R)
/// with Z0 = ρc/S. The area is checked against an adult canal's because a wrong unit
/// there scales |Z| by orders of magnitude without any other sign.
fn from_reflectance(
    t: &Table,
    [rm, ra, area]: [&Col; 3],
    columns: &mut Vec<(String, String)>,
    notes: &mut Vec<String>,
) -> Result<Option<MagPhase>, FormatError> {
    use super::immittance;
    let s = unit(area, &AREA, None)?;
    let pu = unit(ra, &PHASE, None)?;
    let ph = PHASE_UNITS.iter().find(|(n, _)| *n == pu).map_or(1.0, |(_, k)| *k);
    let k = unit(rm, &FRACTION, Some(1.0))?;
    let (fr, v) = series(t.rows, t.f, &[rm, ra, area])?;
    if fr.is_empty() {
        return Ok(None);
    }
    let (mut mag, mut phase, mut z0s) = (Vec::new(), Vec::new(), Vec::new());
    for (i, fz) in fr.iter().enumerate() {
        let line = t.rows[t.f.iter().position(|x| x == fz).unwrap_or(0)].0;
        let sa = v[2][i] * s;
        if !(AREA_RANGE.0..=AREA_RANGE.1).contains(&sa) {
            return Err(FormatError::Cell {
                line,
                column: area.name.clone(),
                message: format!(
                    "{} m² is outside 10–150 mm², an adult ear canal's cross-section: is the unit right?",
                    sa
                ),
            });
        }
        let z0 = immittance::z0(sa);
        let (zm, zp) = immittance::impedance_from_reflectance(v[0][i] * k, v[1][i] * ph, z0).ok_or_else(|| {
            FormatError::Cell { line, column: rm.name.clone(), message: "R = 1: an infinite impedance".into() }
        })?;
        mag.push(zm);
        phase.push(zp);
        z0s.push(z0);
    }
    notes.push(format!(
        "impedance from {}, {} and {}: Z = Z0 (1 + R)/(1 − R), Z0 = ρc/S = {:.3e} Pa·s/m³ (ρc = {:.1} Pa·s/m, air at \
         37 °C; S from {}); a device that assumed another ρc or area gives |Z| off by that ratio",
        rm.name,
        ra.name,
        area.name,
        z0s[0],
        immittance::rho_c(),
        area.name
    ));
    for field in ["measurements.impedance.magnitude", "measurements.impedance.phase"] {
        columns.push((field.into(), format!("{}/{}", rm.name, ra.name)));
    }
    Ok(Some(MagPhase {
        frequencies_hz: fr,
        magnitude: mag,
        phase,
        magnitude_unit: Some("Pa·s/m³".into()),
        phase_unit: Some("rad".into()),
    }))
}

/// A magnitude column and its phase column, both or neither.
fn both<'c>(mag: Option<&'c Col>, ang: Option<&'c Col>) -> Result<Option<(&'c Col, &'c Col)>, FormatError> {
    match (mag, ang) {
        (None, None) => Ok(None),
        (Some(m), Some(a)) => Ok(Some((m, a))),
        (Some(c), None) | (None, Some(c)) => Err(FormatError::Column {
            column: c.name.clone(),
            message: "a magnitude needs its phase column and a phase its magnitude column".into(),
        }),
    }
}

/// A magnitude/phase pair of columns as a measure in its declared units; both columns or
/// neither.
fn mag_phase(
    t: &Table,
    mag: Option<&Col>,
    ang: Option<&Col>,
    units: &[(&[&str], Option<f64>)],
    field: &str,
    columns: &mut Vec<(String, String)>,
) -> Result<Option<MagPhase>, FormatError> {
    let Some((mag, ang)) = both(mag, ang)? else { return Ok(None) };
    let names: Vec<(&[&str], &str)> = units.iter().map(|(n, _)| (*n, n[0])).collect();
    let mag_unit = unit(mag, &names, None)?;
    let phase_unit = unit(ang, &PHASE, None)?;
    let (fm, v) = series(t.rows, t.f, &[mag, ang])?;
    if fm.is_empty() {
        return Ok(None);
    }
    columns.push((format!("measurements.{field}.magnitude"), mag.name.clone()));
    columns.push((format!("measurements.{field}.phase"), ang.name.clone()));
    let [m, p]: [Vec<f64>; 2] = v.try_into().unwrap_or_default();
    Ok(Some(MagPhase {
        frequencies_hz: fm,
        magnitude: m,
        phase: p,
        magnitude_unit: Some(mag_unit.to_string()),
        phase_unit: Some(phase_unit.to_string()),
    }))
}

#[cfg(test)]
mod tests {
    use super::*;

    fn opts(units: &[(&str, &str)], select: &[(&str, &str)], preset: Option<Preset>) -> LongOptions {
        let own = |v: &[(&str, &str)]| v.iter().map(|(a, b)| (a.to_string(), b.to_string())).collect();
        LongOptions { units: own(units), select: own(select), preset }
    }

    const WAI: &str = "Subject,Ear,Frequency,Absorbance,Zmag,Zang,AreaCanal\n\
        S1,Left,226,0.04,8.4e7,-0.236,44\n\
        S1,Left,1000,0.5,2e7,-0.18,44\n\
        S1,Right,226,0.05,8.0e7,-0.235,45\n\
        S1,Right,1000,0.55,1.9e7,-0.17,45\n";

    #[test]
    fn quoted_fields_keep_their_delimiters_and_quotes() {
        assert_eq!(cells(r#""Smith, J",226,"say ""hi""""#, ','), ["Smith, J", "226", r#"say "hi""#]);
        assert_eq!(cells(" a ; \"b;c\" ;", ';'), ["a", "b;c", ""]);
        assert_eq!(delimiter(r#""Name, full";Frequency [Hz];Absorbance"#), ';');
        // A device export whose patient column holds the delimiter, quoted.
        let text = "Patient,Frequency [Hz],Absorbance\n\"Smith, J\",226,0.05\n\"Smith, J\",1000,0.5\n\
                    \"Smith, J\",4000,0.4\n";
        let imp = read(text, &opts(&[], &[("Patient", "Smith, J")], None)).unwrap();
        let a = imp.measurements.absorbance.as_ref().unwrap();
        assert_eq!(
            (a.frequencies_hz.as_slice(), a.values.as_slice()),
            ([226.0, 1000.0, 4000.0].as_slice(), [0.05, 0.5, 0.4].as_slice())
        );
    }

    #[test]
    fn header_units_and_their_names() {
        assert_eq!(split_unit("Zmag [cgs]"), ("Zmag".into(), Some("cgs".into())));
        assert_eq!(split_unit(" Frequency (kHz) "), ("Frequency".into(), Some("kHz".into())));
        assert_eq!(split_unit("Ymag (m^3/(Pa*s))"), ("Ymag".into(), Some("m^3/(Pa*s)".into())));
        assert_eq!(split_unit("Zang"), ("Zang".into(), None));
        assert_eq!(quantity("|Z|"), Some(Quantity::Zmag));
        assert_eq!(quantity("Impedance phase"), Some(Quantity::Zang));
        assert!(looks_long("Freq;Absorbance") && !looks_long("absorbance@200.0,absorbance@215.6"));
    }

    #[test]
    fn the_wai_preset_reads_one_selected_ear() {
        let imp = read(WAI, &opts(&[], &[("Ear", "Right")], Some(Preset::Wai))).unwrap();
        let z = imp.measurements.impedance.as_ref().unwrap();
        assert_eq!(z.frequencies_hz, [226.0, 1000.0]);
        assert_eq!(z.magnitude, [8.0e7, 1.9e7]);
        assert_eq!((z.magnitude_unit.as_deref(), z.phase_unit.as_deref()), (Some("Pa·s/m³"), Some("cycles")));
        assert_eq!(imp.measurements.absorbance.as_ref().unwrap().values, [0.05, 0.55]);
        assert!(imp.notes[0].contains("kept 2 of 4 rows"), "{:?}", imp.notes);
        let (field, message) = imp.column_of("measurements.impedance.phase", "need \"phase_unit\": \"deg\"");
        assert_eq!(field, "Zang (measurements.impedance.phase)");
        assert!(message.contains("'Zang [unit]'"), "{message}");
    }

    #[test]
    fn units_are_declared_never_guessed_and_errors_name_the_column() {
        let err = |text: &str, o: LongOptions| read(text, &o).unwrap_err();
        // Without the preset the phase has no unit.
        let e = err(WAI, opts(&[("Zmag", "SI")], &[("Ear", "Left")], None));
        assert_eq!((e.field(), e.message().contains("no unit")), ("Zang".into(), true), "{e}");
        let e = err(WAI, opts(&[("Zmag", "furlongs"), ("Zang", "deg")], &[("Ear", "Left")], None));
        assert!(e.field() == "Zmag" && e.message().contains("unknown unit 'furlongs'"), "{e}");
        let e = err("f [Hz],Zmag [cgs],Zang [deg]\n200,800,-80\n", opts(&[("Zang", "rad")], &[], None));
        assert!(e.field() == "Zang" && e.message().contains("keep one"), "{e}");
        let e = err(WAI, opts(&[], &[], Some(Preset::Wai)));
        assert!(e.to_string().contains("several ears"), "{e}");
        let e = err(WAI, opts(&[], &[("Side", "Left")], Some(Preset::Wai)));
        assert_eq!(e.field(), "Side");
        let e = err("Frequency,Absorbance\n200,38\n400,55\n", LongOptions::default());
        assert!(e.field() == "Absorbance" && e.message().contains("[%]"), "{e}");
        let e = err("Frequency,Absorbance\n200,0.3\n400,0,5\n", LongOptions::default());
        assert!(e.to_string().contains("line 3 has 3 cells"), "{e}");
        let e = err("Frequency;Absorbance\n200;0,3\n400;0,5\n", LongOptions::default());
        assert!(e.field() == "Absorbance[line 2]" && e.message().contains("decimal commas"), "{e}");
        let e = err("{\"measurements\":{}}", LongOptions::default());
        assert!(matches!(e, FormatError::NotThisFormat(_)), "{e}");
        let e = err("Frequency,Zmag [cgs],Zang [deg]\n200,800,-80\n400,,-70\n", LongOptions::default());
        assert_eq!(e.field(), "Zmag[line 3]", "{e}");
        let e = err("Frequency,Pressure\n200,1\n400,2\n", LongOptions::default());
        assert!(e.to_string().contains("no measure found"), "{e}");
    }

    #[test]
    fn declared_units_reach_the_measurement_and_empty_cells_shorten_a_measure() {
        let text = "Frequency (kHz)\tAbsorbance [%]\t|Z| [cgs]\tZ phase [deg]\n0.2\t3\t900\t-85\n0.25\t4\tNA\tNA\n\
                    0.5\t15\t380\t-80\n";
        let imp = read(text, &LongOptions::default()).unwrap();
        let a = imp.measurements.absorbance.as_ref().unwrap();
        assert_eq!(a.frequencies_hz, [200.0, 250.0, 500.0]);
        assert!((a.values[1] - 0.04).abs() < 1e-12);
        let z = imp.measurements.impedance.as_ref().unwrap();
        assert_eq!(z.frequencies_hz, [200.0, 500.0]);
        assert_eq!((z.magnitude_unit.as_deref(), z.phase_unit.as_deref()), (Some("cgs"), Some("deg")));
    }

    #[test]
    fn reflectance_and_admittance_become_impedance_and_absorbance() {
        use crate::formats::immittance::{reflectance_from_impedance, z0};
        let z = [(226.0, 8.4e7, -1.48), (1000.0, 1.9e7, -1.17), (4000.0, 1.14e7, -1.25)];
        let mut r = String::from("Frequency,Rmag,Rang [rad],AreaCanal [mm2]\n");
        let mut y = String::from("Frequency,Ymag [mmho],Yang [deg]\n");
        for (f, m, p) in z {
            let (rm, rp) = reflectance_from_impedance(m, p, z0(44.2e-6));
            r.push_str(&format!("{f},{rm:e},{rp:e},44.2\n"));
            y.push_str(&format!("{f},{:e},{:e}\n", 1.0 / m / 1e-8, -p.to_degrees()));
        }
        let imp = read(&r, &LongOptions::default()).unwrap();
        let zr = imp.measurements.impedance.as_ref().unwrap();
        let a = imp.measurements.absorbance.as_ref().unwrap();
        for (k, (_, m, p)) in z.iter().enumerate() {
            assert!((zr.magnitude[k] / m - 1.0).abs() < 1e-9 && (zr.phase[k] - p).abs() < 1e-9, "{zr:?}");
            let want = crate::sim::air::absorbance(faer::c64::from_polar(*m, *p), z0(44.2e-6));
            assert!((a.values[k] - want).abs() < 1e-9, "{a:?}");
        }
        assert!(imp.notes.iter().any(|n| n.contains("Z0 = ρc/S")), "{:?}", imp.notes);
        let imp = read(&y, &LongOptions::default()).unwrap();
        let zy = imp.measurements.impedance.as_ref().unwrap();
        assert_eq!(zy.phase_unit.as_deref(), Some("deg"));
        for (k, (_, m, p)) in z.iter().enumerate() {
            assert!((zy.magnitude[k] / m - 1.0).abs() < 1e-9 && (zy.phase[k] - p.to_degrees()).abs() < 1e-9, "{zy:?}");
        }
        assert!(imp.measurements.absorbance.is_none());
        // Without the area, reflectance gives the absorbance only, and says so.
        let no_area = r.replace(",AreaCanal [mm2]", "").replace(",44.2\n", "\n");
        let imp = read(&no_area, &LongOptions::default()).unwrap();
        assert!(imp.measurements.impedance.is_none() && imp.measurements.absorbance.is_some());
        assert!(imp.notes.iter().any(|n| n.contains("needs the canal area")), "{:?}", imp.notes);
        let err = |text: String| read(&text, &LongOptions::default()).unwrap_err();
        let e = err(r.replace("AreaCanal [mm2]", "AreaCanal"));
        assert!(e.field() == "AreaCanal" && e.message().contains("no unit"), "{e}");
        let e = err(r.replace("AreaCanal [mm2]", "AreaCanal [m2]"));
        assert!(e.field() == "AreaCanal[line 2]" && e.message().contains("is the unit right"), "{e}");
        let e =
            err("Frequency,Ymag [mmho],Yang [deg],Zmag [cgs],Zang [deg]\n200,1,80,800,-80\n400,2,70,700,-70\n".into());
        assert!(e.field() == "Ymag" && e.message().contains("keep one"), "{e}");
        let e = err("Frequency,Absorbance,PowerReflectance\n200,0.1,0.9\n400,0.2,0.8\n".into());
        assert_eq!(e.field(), "PowerReflectance", "{e}");
        let e = err("Frequency,Ymag [ohm],Yang [deg]\n200,1,80\n400,2,70\n".into());
        assert!(e.field() == "Ymag" && e.message().contains("mmho"), "{e}");
    }
}
