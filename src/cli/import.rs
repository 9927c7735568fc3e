//! `otofit import wai`: a wideband-acoustic-immittance table in long layout (one row per
//! frequency, as the WAI database and WBT devices export it) → an observation in the
//! `POST /infer` format, with its units declared rather than guessed.

use crate::measurements::{MagPhase, Measurements, Values};
use anyhow::{Context, Result, bail};
use clap::{Args, Subcommand};
use std::path::{Path, PathBuf};

#[derive(Args, Debug)]
pub struct ImportArgs {
    #[command(subcommand)]
    pub what: ImportWhat,
}

#[derive(Subcommand, Debug)]
pub enum ImportWhat {
    /// Long-layout WAI CSV: columns Frequency (or Freq, Hz), Absorbance, Zmag, Zang (names
    /// case-insensitive; other columns kept only for --select).
    Wai {
        /// The CSV file.
        #[arg(long = "in")]
        input: PathBuf,
        /// The observation to write (JSON, the POST /infer request format).
        #[arg(long)]
        out: PathBuf,
        /// Unit of Zmag: "Pa·s/m³" (SI acoustic ohm), "MOhm" or "cgs".
        #[arg(long, default_value = "Pa*s/m^3")]
        zmag_unit: String,
        /// Unit of Zang: cycles (the WAI database), deg or rad.
        #[arg(long, default_value = "cycles")]
        zang_unit: String,
        /// Keep only rows where COLUMN equals VALUE (repeatable), e.g. --select Ear=Left
        /// for a file with several ears.
        #[arg(long, value_name = "COLUMN=VALUE")]
        select: Vec<String>,
    },
}

pub fn run(args: ImportArgs) -> Result<()> {
    match args.what {
        ImportWhat::Wai { input, out, zmag_unit, zang_unit, select } => {
            let m = wai(&input, &zmag_unit, &zang_unit, &select)?;
            let doc = serde_json::json!({ "measurements": m });
            let tmp = out.with_extension("tmp");
            std::fs::write(&tmp, serde_json::to_vec_pretty(&doc)?)
                .with_context(|| format!("cannot write {}", tmp.display()))?;
            std::fs::rename(&tmp, &out)?;
            eprintln!("wrote {} ({} frequencies)", out.display(), m.absorbance.as_ref().map_or(0, |a| a.values.len()));
            Ok(())
        }
    }
}

/// The column of `header` with one of `names` (case-insensitive).
fn column(header: &[String], names: &[&str], path: &Path) -> Result<usize> {
    header.iter().position(|h| names.iter().any(|n| h.eq_ignore_ascii_case(n))).with_context(|| {
        format!("{}: no column {} (columns: {})", path.display(), names.join(" or "), header.join(", "))
    })
}

/// Reads a long-layout WAI table into measurements (impedance and absorbance).
pub fn wai(path: &Path, zmag_unit: &str, zang_unit: &str, select: &[String]) -> Result<Measurements> {
    let text = std::fs::read_to_string(path).with_context(|| format!("cannot read {}", path.display()))?;
    let mut lines = text.lines().filter(|l| !l.trim().is_empty());
    let cells = |l: &str| l.split(',').map(|c| c.trim().trim_matches('"').to_string()).collect::<Vec<String>>();
    let header = cells(lines.next().with_context(|| format!("{}: empty file", path.display()))?);
    if header.len() < 2 {
        bail!("{}: not a CSV with a header row (found '{}')", path.display(), header.join(""));
    }
    let (fc, ac) = (column(&header, &["Frequency", "Freq", "Hz"], path)?, column(&header, &["Absorbance"], path)?);
    let (mc, pc) = (column(&header, &["Zmag"], path)?, column(&header, &["Zang"], path)?);
    let mut filters = Vec::new();
    for s in select {
        let Some((c, v)) = s.split_once('=') else { bail!("--select '{s}': expected COLUMN=VALUE") };
        filters.push((column(&header, &[c.trim()], path).context("--select")?, v.trim().to_string()));
    }
    let (mut f, mut a, mut zm, mut za) = (vec![], vec![], vec![], vec![]);
    for (i, line) in lines.enumerate() {
        let row = cells(line);
        if row.len() != header.len() {
            bail!("{}: line {} has {} cells, the header {}", path.display(), i + 2, row.len(), header.len());
        }
        if filters.iter().any(|(c, v)| &row[*c] != v) {
            continue;
        }
        let num = |c: usize| {
            row[c].parse::<f64>().map_err(|_| {
                anyhow::anyhow!(
                    "{}: line {}, column '{}': '{}' is not a number",
                    path.display(),
                    i + 2,
                    header[c],
                    row[c]
                )
            })
        };
        f.push(num(fc)?);
        a.push(num(ac)?);
        zm.push(num(mc)?);
        za.push(num(pc)?);
    }
    if f.len() < 2 {
        bail!("{}: {} rows left after --select; need at least 2 frequencies", path.display(), f.len());
    }
    let several = f.windows(2).any(|w| w[1] <= w[0]);
    if several {
        bail!(
            "{}: frequencies do not increase: several ears or sessions? pick one with --select COLUMN=VALUE",
            path.display()
        );
    }
    Ok(Measurements {
        stapes_velocity: None,
        impedance: Some(MagPhase {
            frequencies_hz: f.clone(),
            magnitude: zm,
            phase: za,
            magnitude_unit: Some(zmag_unit.to_string()),
            phase_unit: Some(zang_unit.to_string()),
        }),
        absorbance: Some(Values { frequencies_hz: f, values: a }),
    })
}
