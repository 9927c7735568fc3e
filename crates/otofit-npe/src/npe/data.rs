//! Training tables: theta.csv + x.csv (header rows) with meta.json (written by
//! `otofit simulate`) or prior.json (any simulator's table).

use super::prior::Param;
use super::{NpeError, Result};
use crate::dataset::{Format, read_csv, read_npy};
use serde::{Deserialize, Serialize};
use std::path::Path;

/// A feature group a model can be asked to do without (e.g. one modality).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Group {
    /// The group's name (a modality, e.g. `wbt`).
    pub name: String,
    /// Indices of its features.
    pub features: Vec<usize>,
}

/// A training table in memory: θ rows, x rows and their description.
pub struct Dataset {
    /// The prior box, one per θ column.
    pub params: Vec<Param>,
    /// One name per x column.
    pub feature_names: Vec<String>,
    /// The frequency grid of the features (empty for a table without one).
    pub frequencies_hz: Vec<f64>,
    /// Feature groups the model may be trained to do without.
    pub groups: Vec<Group>,
    /// 1× noise standard deviation per feature (zeros when the table has none).
    pub noise_std: Vec<f64>,
    /// θ rows (natural units, inside the prior box).
    pub theta: Vec<Vec<f64>>,
    /// x rows, aligned with `theta`, all finite.
    pub x: Vec<Vec<f64>>,
    /// Rows dropped for non-finite values or θ outside the prior box.
    pub skipped: usize,
}

/// Reads and parses a JSON file of the folder, naming what it should have been.
fn read_json<T: serde::de::DeserializeOwned>(path: &Path, expected: &str) -> Result<T> {
    let bytes = std::fs::read(path).map_err(crate::dataset::FileError::on("read", path))?;
    serde_json::from_slice(&bytes).map_err(|e| NpeError::table(path, format!("{expected}: {e}")))
}

#[derive(Deserialize)]
struct Meta {
    parameters: Vec<Param>,
    #[serde(default)]
    frequencies_hz: Vec<f64>,
    #[serde(default)]
    features: Vec<MetaFeature>,
    #[serde(default)]
    groups: Vec<MetaGroup>,
    #[serde(default)]
    noise: Option<MetaNoise>,
    /// Absent in datasets written before .npy tables: CSV.
    #[serde(default)]
    format: Format,
}

#[derive(Deserialize)]
struct MetaFeature {
    #[serde(default)]
    name: String,
    #[serde(default)]
    measure: String,
}

#[derive(Deserialize)]
struct MetaGroup {
    name: String,
    measures: Vec<String>,
}

#[derive(Deserialize)]
struct MetaNoise {
    std: Vec<f64>,
}

#[derive(Deserialize)]
struct PriorFile {
    parameters: Vec<Param>,
}

impl Dataset {
    /// Reads a dataset folder: theta.csv, x.csv and meta.json or prior.json.
    pub fn load(dir: &Path) -> Result<Dataset> {
        let meta_path = dir.join("meta.json");
        let prior_path = dir.join("prior.json");
        let (params, meta) = if meta_path.exists() {
            let m: Meta = read_json(&meta_path, "not a dataset meta.json")?;
            (m.parameters.clone(), Some(m))
        } else if prior_path.exists() {
            let p: PriorFile =
                read_json(&prior_path, r#"expected {"parameters":[{"name","low","high","scale","unit"}]}"#)?;
            (p.parameters, None)
        } else {
            return Err(NpeError::table(dir, "neither meta.json nor prior.json found"));
        };
        for p in &params {
            p.validate().map_err(|e| NpeError::table(dir, e.to_string()))?;
        }
        let format = meta.as_ref().map(|m| m.format).unwrap_or_default();
        let [theta_file, x_file, _] = format.files();
        let (tt, xt) = match (format, &meta) {
            (Format::Npy, Some(m)) => {
                let names = params.iter().map(|p| p.name.clone()).collect();
                let features = m.features.iter().map(|f| f.name.clone()).collect();
                (read_npy(&dir.join(theta_file), names)?, read_npy(&dir.join(x_file), features)?)
            }
            _ => (read_csv(&dir.join(theta_file))?, read_csv(&dir.join(x_file))?),
        };
        if tt.rows.len() != xt.rows.len() {
            let why = format!("{theta_file} has {} rows but {x_file} has {}", tt.rows.len(), xt.rows.len());
            return Err(NpeError::table(dir, why));
        }
        // theta.csv columns in prior order, by name.
        let cols: Vec<usize> = params
            .iter()
            .map(|p| {
                tt.header
                    .iter()
                    .position(|h| *h == p.name)
                    .ok_or_else(|| NpeError::table(dir, format!("{theta_file} has no column '{}'", p.name)))
            })
            .collect::<Result<_>>()?;
        let nf = xt.header.len();
        let (mut theta, mut x, mut skipped) = (Vec::new(), Vec::new(), 0);
        for (t, xr) in tt.rows.iter().zip(&xt.rows) {
            let row: Vec<f64> = cols.iter().map(|&c| t[c]).collect();
            if row.iter().zip(&params).all(|(v, p)| p.contains(*v)) && xr.iter().all(|v| v.is_finite()) {
                theta.push(row);
                x.push(xr.clone());
            } else {
                skipped += 1;
            }
        }
        let (mut frequencies_hz, mut groups, mut noise_std) = (vec![], vec![], vec![0.0; nf]);
        if let Some(m) = meta {
            frequencies_hz = m.frequencies_hz;
            if let Some(n) = m.noise {
                if n.std.len() != nf {
                    let why = format!("noise.std has {} values for {nf} features", n.std.len());
                    return Err(NpeError::table(&meta_path, why));
                }
                noise_std = n.std;
            }
            if m.features.len() == nf {
                for g in m.groups {
                    let features: Vec<usize> =
                        (0..nf).filter(|&i| g.measures.contains(&m.features[i].measure)).collect();
                    if !features.is_empty() {
                        groups.push(Group { name: g.name, features });
                    }
                }
            }
        }
        Ok(Dataset { params, feature_names: xt.header, frequencies_hz, groups, noise_std, theta, x, skipped })
    }
}
