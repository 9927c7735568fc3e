//! Readers for the files clinics and laboratories export, each producing otofit's
//! [`Measurements`]: long-layout CSV tables (one row per frequency, as the WAI database
//! and wideband-tympanometry devices export them) and UFF dataset 58 (the frequency
//! response functions vibrometer software exports). Units are read from the column
//! headers or declared by the caller, never guessed; every error names the column, and
//! the line where one cell is at fault.
//!
//! The readers only parse and convert units; the physical checks and the interpolation
//! onto a model's grid stay in [`crate::measurements::features`], shared with JSON input.

use crate::measurements::Measurements;

pub mod immittance;
pub mod long;
pub mod uff58;

/// Why a file cannot be read as measurements.
#[derive(Debug, thiserror::Error)]
pub enum FormatError {
    /// The text is not a table of this format (no header row, a JSON document, ...).
    #[error("{0}")]
    NotThisFormat(String),
    /// A column is missing, repeated, or has an unknown or undeclared unit.
    #[error("column '{column}': {message}")]
    Column {
        /// The column, as the header names it.
        column: String,
        /// What is wrong with it.
        message: String,
    },
    /// One cell does not parse or is outside what the column can hold.
    #[error("line {line}, column '{column}': {message}")]
    Cell {
        /// The cell's line in the file, from 1.
        line: usize,
        /// The cell's column, as the header names it.
        column: String,
        /// What is wrong with it.
        message: String,
    },
    /// The table as a whole (no rows left, frequencies that do not increase, ...).
    #[error("{0}")]
    Table(String),
}

impl FormatError {
    /// The field an API problem names: the column (`Zang`, `Zang[line 7]`), or `body`.
    pub fn field(&self) -> String {
        match self {
            FormatError::Column { column, .. } => column.clone(),
            FormatError::Cell { line, column, .. } => format!("{column}[line {line}]"),
            FormatError::NotThisFormat(_) | FormatError::Table(_) => "body".into(),
        }
    }

    /// The message without the field it names (for an API problem's `message`).
    pub fn message(&self) -> String {
        match self {
            FormatError::Column { message, .. } | FormatError::Cell { message, .. } => message.clone(),
            FormatError::NotThisFormat(m) | FormatError::Table(m) => m.clone(),
        }
    }
}

/// Measurements read from a file, and what was done on the way.
#[derive(Debug)]
pub struct Imported {
    /// The measurements, in the units the table declared.
    pub measurements: Measurements,
    /// Conversions and choices made (rows kept, units converted, columns not used), in
    /// words, for the user to see.
    pub notes: Vec<String>,
    /// (field of the POST /infer format, column it came from), so that a later error
    /// about `measurements.impedance.phase` can name the column `Zang`.
    pub columns: Vec<(String, String)>,
}

impl Imported {
    /// A measurement error about `field` (a JSON path of the POST /infer format) as one
    /// about the column it came from: `measurements.impedance.phase` → `Zang
    /// (measurements.impedance.phase)`, and a hint to send a JSON unit field told as a
    /// table's header unit.
    pub fn column_of(&self, field: &str, message: &str) -> (String, String) {
        let Some((_, c)) = self.columns.iter().find(|(f, _)| field.starts_with(f.as_str())) else {
            return (field.to_string(), message.to_string());
        };
        let mut message = message.to_string();
        if message.contains("_unit\"") {
            message.push_str(&format!(
                " (in a table: the unit in the column header, '{c} [unit]', or declared with --unit {c}=unit or a \
                 unit={c}=unit query parameter)"
            ));
        }
        (format!("{c} ({field})"), message)
    }
}
