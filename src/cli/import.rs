//! `otofit import`: a clinic's or database's export → an observation in the `POST /infer`
//! format (JSON), with its units declared rather than guessed. `wai` and `csv` read
//! long-layout tables (one row per frequency, [`crate::formats::long`]).

use crate::formats::long::{self, LongOptions, Preset};
use anyhow::{Context, Result};
use clap::{Args, Subcommand};
use std::path::{Path, PathBuf};

/// Arguments of `otofit import`.
#[derive(Args, Debug)]
pub struct ImportArgs {
    /// The export format to read.
    #[command(subcommand)]
    pub what: ImportWhat,
}

/// The export formats `otofit import` reads.
#[derive(Subcommand, Debug)]
pub enum ImportWhat {
    /// The WAI database's long layout: Frequency, Absorbance, Zmag (Pa·s/m³ unless its
    /// header or --zmag-unit says otherwise), Zang (cycles unless declared), one row per
    /// frequency; other columns (Subject, Ear, ...) serve --select.
    Wai {
        /// The input and output files and how to read the table.
        #[command(flatten)]
        table: TableArgs,
        /// Unit of Zmag: "Pa*s/m^3" (SI acoustic ohm; the default), "MOhm" or "cgs".
        #[arg(long)]
        zmag_unit: Option<String>,
        /// Unit of Zang: cycles (the default, as the WAI database stores it), deg or rad.
        #[arg(long)]
        zang_unit: Option<String>,
    },
    /// Any long-layout CSV (comma, semicolon or tab separated; one row per frequency):
    /// Frequency, and any of Absorbance, Zmag + Zang, Ymag + Yang (admittance), Rmag
    /// (+ Rang) or PowerReflectance, AreaCanal, VstMag + VstAng, VuMag + VuAng (umbo
    /// velocity); each magnitude, phase and area with its unit in the header (`Zmag
    /// [cgs]`, `Zang [deg]`, `Ymag [mmho]`, `AreaCanal [mm2]`) or from --unit. Reflectance with its phase and the canal area
    /// becomes the impedance Z = Z0 (1 + R)/(1 − R), Z0 = ρc/S (air at 37 °C).
    Csv {
        /// The input and output files and how to read the table.
        #[command(flatten)]
        table: TableArgs,
    },
    /// A Universal File Format file (ASCII) with a dataset 58: a laser-Doppler
    /// vibrometer's frequency response function, complex velocity over pressure (m/s,
    /// mm/s or um/s over Pa, from the units labels of records 9 and 10) over frequency.
    Uff58 {
        /// The .uff/.unv file.
        #[arg(long = "in")]
        input: PathBuf,
        /// The observation to write (JSON, the POST /infer request format).
        #[arg(long)]
        out: PathBuf,
        /// Which measure the FRF is (the file does not say where the laser pointed):
        /// stapes_velocity or umbo_velocity (clinical LDV through the canal).
        #[arg(long)]
        measure: crate::formats::uff58::Measure,
        /// Which dataset 58 of the file (1-based), when it holds several.
        #[arg(long)]
        dataset: Option<usize>,
    },
}

/// The arguments every long-layout import takes.
#[derive(Args, Debug)]
pub struct TableArgs {
    /// The CSV file.
    #[arg(long = "in")]
    pub input: PathBuf,
    /// The observation to write (JSON, the POST /infer request format).
    #[arg(long)]
    pub out: PathBuf,
    /// How to read the table.
    #[command(flatten)]
    pub long: LongArgs,
}

/// How to read a long-layout table (`import` and `infer --obs`).
#[derive(Args, Debug, Default)]
pub struct LongArgs {
    /// Long-layout tables: the unit of a column whose header gives none, e.g. --unit
    /// Zang=deg (repeatable).
    #[arg(long, value_name = "COLUMN=UNIT")]
    pub unit: Vec<String>,
    /// Long-layout tables: keep only rows where COLUMN equals VALUE (repeatable), e.g.
    /// --select Ear=Left for a file with several ears.
    #[arg(long, value_name = "COLUMN=VALUE")]
    pub select: Vec<String>,
}

impl LongArgs {
    /// Whether no --unit or --select was given.
    pub fn is_empty(&self) -> bool {
        self.unit.is_empty() && self.select.is_empty()
    }

    /// Reading options from the arguments, with a preset's units.
    pub fn options(&self, preset: Option<Preset>) -> Result<LongOptions> {
        let pairs = |v: &[String], what: &str| -> Result<Vec<(String, String)>> {
            v.iter().map(|a| long::pair(a, what).map_err(anyhow::Error::msg)).collect()
        };
        Ok(LongOptions { units: pairs(&self.unit, "--unit")?, select: pairs(&self.select, "--select")?, preset })
    }
}

/// Reads a long-layout table file, its errors naming the file.
pub fn read_table(path: &Path, opts: &LongOptions) -> Result<crate::formats::Imported> {
    let text =
        std::fs::read_to_string(path).with_context(|| format!("cannot read {} (a UTF-8 CSV)", path.display()))?;
    long::read(&text, opts).with_context(|| format!("{}", path.display()))
}

/// Writes an observation in the POST /infer format, with what it holds on stderr.
fn write(out: &Path, imp: &crate::formats::Imported) -> Result<()> {
    if let Some(dir) = out.parent().filter(|d| !d.as_os_str().is_empty())
        && !dir.is_dir()
    {
        anyhow::bail!("--out {}: the folder {} does not exist", out.display(), dir.display());
    }
    for n in &imp.notes {
        eprintln!("note: {n}");
    }
    let m = &imp.measurements;
    let doc = serde_json::json!({ "measurements": m });
    let tmp = out.with_extension("tmp");
    std::fs::write(&tmp, serde_json::to_vec_pretty(&doc)?)
        .with_context(|| format!("cannot write {}", tmp.display()))?;
    std::fs::rename(&tmp, out)?;
    let count = |n: Option<usize>, name: &str| n.map(|n| format!("{name} at {n} frequencies"));
    let what: Vec<String> = [
        count(m.impedance.as_ref().map(|z| z.frequencies_hz.len()), "impedance"),
        count(m.absorbance.as_ref().map(|a| a.frequencies_hz.len()), "absorbance"),
        count(m.stapes_velocity.as_ref().map(|v| v.frequencies_hz.len()), "stapes velocity"),
    ]
    .into_iter()
    .flatten()
    .collect();
    eprintln!("wrote {} ({})", out.display(), what.join(", "));
    Ok(())
}

/// Runs `otofit import`.
pub fn run(args: ImportArgs) -> Result<()> {
    let (table, opts) = match args.what {
        ImportWhat::Wai { mut table, zmag_unit, zang_unit } => {
            table.long.unit.extend(zmag_unit.map(|u| format!("Zmag={u}")));
            table.long.unit.extend(zang_unit.map(|u| format!("Zang={u}")));
            let opts = table.long.options(Some(Preset::Wai))?;
            (table, opts)
        }
        ImportWhat::Csv { table } => {
            let opts = table.long.options(None)?;
            (table, opts)
        }
        ImportWhat::Uff58 { input, out, measure, dataset } => {
            let text = std::fs::read_to_string(&input)
                .with_context(|| format!("cannot read {} (an ASCII Universal File Format file)", input.display()))?;
            let imp =
                crate::formats::uff58::read(&text, dataset, measure).with_context(|| format!("{}", input.display()))?;
            return write(&out, &imp);
        }
    };
    let imp = read_table(&table.input, &opts)?;
    write(&table.out, &imp)
}
