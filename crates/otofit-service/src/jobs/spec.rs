//! What a job is: [`JobSpec`], parsed and validated once when it is posted (every bad
//! field named by its JSON path), stored as its JSON (`kind` and `params` columns) and
//! executed from the typed value.

use super::diagnose::DiagnoseParams;
use super::exact::ExactParams;
use super::resimulate::ResimulateParams;
use super::simulate::SimulateParams;
use super::train::TrainParams;
use crate::sim::params::{EFFECTS, Effects, N_TISSUE, PARAMS, ParamSpec, Scale, with_nominal_geometry};
use crate::store::JobRow;
use serde::{Deserialize, Serialize};
use std::collections::BTreeMap;

/// The job kinds, as `kind` spells them.
pub const KINDS: [&str; 5] = ["simulate", "train", "resimulate", "diagnose", "exact"];

/// A job: its kind and its params (`{"kind": …, "params": {…}}`, the body of POST /jobs).
#[derive(Clone, Debug, Serialize, Deserialize)]
#[serde(tag = "kind", content = "params", rename_all = "lowercase")]
pub enum JobSpec {
    /// Simulate a dataset from the prior or given rows.
    Simulate(SimulateParams),
    /// Train a model on a simulated dataset.
    Train(TrainParams),
    /// Re-simulate given parameter rows (e.g. a posterior's) and draw them.
    Resimulate(ResimulateParams),
    /// Check an observation against a model, name the missing effect and retrain with it.
    Diagnose(DiagnoseParams),
    /// Sample an observation's posterior under the model's own likelihood.
    Exact(ExactParams),
}

/// A validation problem: the JSON path of the field and what is wrong with it.
pub type FieldError = (String, String);

impl JobSpec {
    /// A posted job, parsed and checked, or every problem found naming its field.
    pub fn parse(kind: &str, params: &serde_json::Value) -> Result<JobSpec, Vec<FieldError>> {
        let mut errs = Vec::new();
        let spec = match kind {
            "simulate" => JobSpec::Simulate(parse(params)?),
            "train" => JobSpec::Train(parse(params)?),
            "resimulate" => JobSpec::Resimulate(parse(params)?),
            "diagnose" => {
                let p: DiagnoseParams = parse(params)?;
                if p.model.is_none() && params.get("model").is_some() {
                    errs.push(("params.model".into(), "must be a model id, or left out for the default model".into()));
                }
                JobSpec::Diagnose(p)
            }
            "exact" => {
                let p: ExactParams = parse(params)?;
                if p.model.is_none() && params.get("model").is_some() {
                    errs.push(("params.model".into(), "must be a model id, or left out for the default model".into()));
                }
                JobSpec::Exact(p)
            }
            other => {
                let known = KINDS.join(", ");
                return Err(vec![("kind".into(), format!("unknown job kind '{other}' (known: {known})"))]);
            }
        };
        match &spec {
            JobSpec::Simulate(p) => p.validate(&mut errs),
            JobSpec::Train(p) => p.validate(&mut errs),
            JobSpec::Resimulate(p) => p.validate(&mut errs),
            JobSpec::Diagnose(p) => p.validate(&mut errs),
            JobSpec::Exact(p) => p.validate(&mut errs),
        }
        if errs.is_empty() { Ok(spec) } else { Err(errs) }
    }

    /// The spec of a stored job (checked when it was queued).
    pub fn of(job: &JobRow) -> Result<JobSpec, serde_json::Error> {
        serde_json::from_value(serde_json::json!({ "kind": job.kind, "params": job.params }))
    }

    /// The job's kind, as `kind` spells it.
    pub fn kind(&self) -> &'static str {
        match self {
            JobSpec::Simulate(_) => "simulate",
            JobSpec::Train(_) => "train",
            JobSpec::Resimulate(_) => "resimulate",
            JobSpec::Diagnose(_) => "diagnose",
            JobSpec::Exact(_) => "exact",
        }
    }

    /// The row of this job as queued, every other field set (for tests).
    #[cfg(test)]
    pub(crate) fn queued(&self) -> JobRow {
        JobRow {
            id: "j".into(),
            tenant: "t".into(),
            kind: self.kind().into(),
            state: crate::store::JobState::Queued,
            params: self.params(),
            progress: 0.0,
            message: String::new(),
            attempts: 0,
            max_attempts: 3,
            cancel_requested: false,
            error: None,
            result: None,
            created_at: String::new(),
            started_at: None,
            finished_at: None,
            retry_at: None,
            lease_token: None,
            worker: None,
        }
    }

    /// The params as stored: every default written out, so a job shows what it runs with.
    pub fn params(&self) -> serde_json::Value {
        let mut v = serde_json::to_value(self).unwrap_or_default();
        v["params"].take()
    }
}

/// A job's params as `T`; an error names the full JSON path of the field
/// (`params.theta[0][1]`, `params.bogus` for an unknown or missing one).
fn parse<T: serde::de::DeserializeOwned>(params: &serde_json::Value) -> Result<T, Vec<FieldError>> {
    let bytes = serde_json::to_vec(params).map_err(|e| vec![("params".to_string(), e.to_string())])?;
    // Read from text, as a posted body is: serde_json words a number it cannot take from
    // its text (`1e+300`), where a `Value` would write it out in full.
    serde_path_to_error::deserialize(&mut serde_json::Deserializer::from_slice(&bytes))
        .map_err(|e| vec![field_error("params", &e)])
}

/// (field, message) of a JSON error: the field's path under `root` (which may be empty)
/// from the segments serde was at, and serde's message without its position.
pub fn field_error(root: &str, e: &serde_path_to_error::Error<serde_json::Error>) -> FieldError {
    use serde_path_to_error::Segment;
    let mut field = root.to_string();
    // A key that is not a string has no name: a path of nothing else names no field.
    if !e.path().iter().all(|s| matches!(s, Segment::Unknown)) {
        for segment in e.path() {
            match segment {
                Segment::Seq { index } => field += &format!("[{index}]"),
                Segment::Map { key } | Segment::Enum { variant: key } => child(&mut field, key),
                Segment::Unknown => child(&mut field, "?"),
            }
        }
    }
    let inner = e.inner();
    let text = inner.to_string();
    let position = format!(" at line {} column {}", inner.line(), inner.column());
    let message = text.strip_suffix(&position).unwrap_or(&text).to_string();
    // An unknown field's path ends with its key; a missing one's is its parent, and serde
    // names the field only in its message (`missing field `x``).
    if let Some(name) = message.strip_prefix("missing field `").and_then(|r| r.strip_suffix('`')) {
        child(&mut field, name);
    }
    (field, message)
}

/// `field` made the path of its member `name`.
fn child(field: &mut String, name: &str) {
    if !field.is_empty() {
        field.push('.');
    }
    field.push_str(name);
}

/// `errs` gets `field`'s problem when `v` is outside `range` (see `limits`).
pub(super) fn in_range(field: &str, range: &std::ops::RangeInclusive<usize>, v: usize, errs: &mut Vec<FieldError>) {
    if let Err(m) = super::limits::check(range, v) {
        errs.push((field.into(), m));
    }
}

/// `errs` gets `field`'s problem unless `v` is a finite number ≥ 0.
pub(super) fn non_negative(field: &str, v: f64, errs: &mut Vec<FieldError>) {
    if !(v.is_finite() && v >= 0.0) {
        errs.push((field.into(), "must be a finite number ≥ 0".into()));
    }
}

/// Longest id a job may name (models, datasets).
pub const MAX_ID: usize = 64;

/// An id that names a row of the store: ASCII letters, digits, `_` and `-`, 1..=64 long.
/// Ids are looked up, never joined into a path, but a plain id keeps that true for
/// anything that might (`../../etc/model` is refused before it gets near the disk).
pub fn is_plain_id(id: &str) -> bool {
    (1..=MAX_ID).contains(&id.len()) && id.bytes().all(|b| b.is_ascii_alphanumeric() || b == b'_' || b == b'-')
}

/// The checks of a job on one observation (diagnose, exact) that need no model: the
/// model id is plain, every feature finite or null, at least one measured.
pub(super) fn model_and_observation(model: Option<&str>, x: &[Option<f64>], errs: &mut Vec<FieldError>) {
    if let Some(m) = model {
        plain_id("params.model", m, errs);
    }
    if let Some(i) = x.iter().position(|v| v.is_some_and(|v| !v.is_finite())) {
        errs.push((format!("params.x[{i}]"), "must be a finite number or null (not measured)".into()));
    }
    if !x.is_empty() && x.iter().all(Option::is_none) {
        errs.push(("params.x".into(), "holds no measured feature (every value is null)".into()));
    }
}

pub(super) fn plain_id(field: &str, id: &str, errs: &mut Vec<FieldError>) {
    if !is_plain_id(id) {
        errs.push((field.into(), format!("must be a plain id (1..={MAX_ID} of A-Z a-z 0-9 _ -)")));
    }
}

/// The fixed effects of `params.effects`; unknown names and bad values go to `errs`.
pub(super) fn effects_of(map: &BTreeMap<String, f64>, errs: &mut Vec<FieldError>) -> Effects {
    let mut fx = Effects::default();
    for (name, v) in map {
        if let Err(e) = fx.set(name, *v) {
            errs.push((format!("params.effects.{name}"), e.to_string()));
        }
    }
    fx
}

/// How far outside its prior box a requested parameter may lie: one decade each way
/// (log parameters) is far enough for any what-if, and keeps values such as 1e-308,
/// which no ear has and which break the solver's and the figures' arithmetic, out.
const THETA_SLACK_DECADES: f64 = 1.0;

/// Rows of `params.theta` with the nominal geometry inserted after the tissue columns
/// where a row gives only those (and then `n_effects` effect columns).
pub(super) fn with_geometry(rows: &[Vec<f64>], n_effects: usize) -> Vec<Vec<f64>> {
    rows.iter().map(|r| if r.len() == N_TISSUE + n_effects { with_nominal_geometry(r) } else { r.clone() }).collect()
}

/// The values a job's `params.theta` may give parameter `p` (inclusive): its prior box
/// widened each way. openapi.yaml's ThetaRow states the same bounds. Each end is the
/// nearest double to a decimal of 12 significant digits (0.000115, not the sum's
/// 0.00011499999999999999): one the contract can write and a JSON parser reads back as
/// the same number, so a client that sends the stated bound gets it taken.
pub fn theta_box(p: &ParamSpec) -> (f64, f64) {
    let slack = 10f64.powf(THETA_SLACK_DECADES);
    let (lo, hi) = match p.scale {
        Scale::Log10 => (p.low / slack, p.high * slack),
        // A box's width below its low end, or a decade where that would reach zero.
        Scale::Linear => {
            let below = p.low - (p.high - p.low);
            (if below > 0.0 || p.low == 0.0 { below.max(0.0) } else { p.low / slack }, p.high + (p.high - p.low))
        }
    };
    let tidy = |v: f64| format!("{v:.11e}").parse().unwrap_or(v);
    (tidy(lo), tidy(hi))
}

/// Checks the parameter values of `params.theta` rows (effects columns are checked
/// by the simulator's own range guard): every value the simulator cannot run with, or
/// that lies beyond the prior box's slack, is named.
pub(super) fn theta_values(rows: &[Vec<f64>], errs: &mut Vec<FieldError>) {
    for (i, row) in rows.iter().enumerate() {
        for (k, (v, p)) in row.iter().zip(PARAMS.iter()).enumerate() {
            let (lo, hi) = theta_box(p);
            if !p.physical(*v) || *v < lo || *v > hi {
                let why = if p.physical(*v) { "the prior box widened each way" } else { "must be > 0" };
                errs.push((
                    format!("params.theta[{i}][{k}]"),
                    format!("{} = {} {} is outside {}..={} ({why})", p.name, short(*v), p.unit, short(lo), short(hi)),
                ));
            }
        }
    }
}

/// A number with at most four significant digits: `-0.019`, `2.5e-5`, `1e-308`.
fn short(v: f64) -> String {
    if v == 0.0 || (1e-3..1e4).contains(&v.abs()) {
        let s = format!("{v:.4}");
        let s = s.trim_end_matches('0').trim_end_matches('.');
        return if s == "-0" { "0".into() } else { s.into() };
    }
    let s = format!("{v:.3e}");
    let (m, e) = s.split_once('e').unwrap_or((&s, "0"));
    format!("{}e{e}", m.trim_end_matches('0').trim_end_matches('.'))
}

/// Known effect names, for error messages.
pub fn effect_names() -> String {
    EFFECTS.iter().map(|e| e.name).collect::<Vec<_>>().join(", ")
}

#[cfg(test)]
mod tests {
    use super::*;
    use serde_json::json;

    #[test]
    fn a_job_is_stored_with_its_defaults_and_read_back_as_the_same_spec() {
        let spec = JobSpec::parse("train", &json!({"dataset": "d1"})).unwrap();
        let params = spec.params();
        assert_eq!(
            params,
            json!({"dataset": "d1", "noise_scale": 1.0, "seed": 0, "max_epochs": 1000, "mask_groups": false})
        );
        let back = JobSpec::of(&spec.queued()).unwrap();
        assert_eq!((back.kind(), back.params()), ("train", params));
        // Absent options stay absent (no `"ensemble": null`, no `"model": null`, no
        // `"theta": null`).
        let d = JobSpec::parse("diagnose", &json!({"x": [1.0, 2.0]})).unwrap().params();
        assert!(d.get("model").is_none() && d.get("candidates").is_none(), "{d}");
        assert_eq!(d["null_cases"], 40);
        let s = JobSpec::parse("simulate", &json!({"n": 5})).unwrap().params();
        assert!(s.get("theta").is_none() && s["n"] == 5, "{s}");
        let back = JobSpec::of(&JobSpec::parse("simulate", &json!({"n": 5})).unwrap().queued()).unwrap();
        assert!(matches!(back, JobSpec::Simulate(SimulateParams { n: Some(5), .. })));
    }

    /// `theta_box` is what posting checks, both ends included (openapi.yaml's ThetaRow
    /// states it as minimum and maximum). Just outside: 1e-12 relative, as JSON text
    /// (serde_json's parse of a number may land an ulp off the value written).
    #[test]
    fn theta_values_on_the_box_edges_are_taken_and_just_outside_refused() {
        let nominal: Vec<f64> = PARAMS.iter().map(|p| p.nominal).collect();
        for (k, p) in PARAMS.iter().enumerate() {
            let (lo, hi) = theta_box(p);
            let (below, above) = (lo - (lo * 1e-12).max(1e-300), hi * (1.0 + 1e-12));
            for (v, ok) in [(lo, true), (hi, true), (below, false), (above, false)] {
                let mut row = nominal.clone();
                row[k] = v;
                let res = JobSpec::parse("resimulate", &json!({ "theta": [row] }));
                match res {
                    Ok(_) => assert!(ok, "{} = {v} taken", p.name),
                    Err(e) => assert!(!ok && e[0].0 == format!("params.theta[0][{k}]"), "{} = {v}: {e:?}", p.name),
                }
            }
        }
    }

    /// A bad param is named by the path serde was at, under `params`; a missing one by
    /// its parent's path and its name. Keys and values are the client's text, whatever
    /// they hold.
    #[test]
    fn params_that_do_not_parse_are_named_by_their_json_path() {
        for (kind, params, field, message) in [
            ("train", json!({}), "params.dataset", "missing field `dataset`"),
            ("train", json!(null), "params", "invalid type: null, expected struct TrainParams"),
            (
                "simulate",
                json!({"theta": [[1.0, "a"]]}),
                "params.theta[0][1]",
                "invalid type: string \"a\", expected f64",
            ),
            (
                "simulate",
                json!({"effects": {"a: b": "x"}}),
                "params.effects.a: b",
                "invalid type: string \"x\", expected f64",
            ),
            ("exact", json!([[1.0]]), "params[0]", "invalid type: sequence, expected a string"),
            // A number serde_json cannot take is worded from its text, as in a posted body.
            (
                "train",
                json!({"dataset": "d", "ensemble": 1e300}),
                "params.ensemble",
                "invalid type: floating point `1e+300`, expected usize",
            ),
            (
                "train",
                json!({"dataset": "d", "seed": "x at line 3"}),
                "params.seed",
                "invalid type: string \"x at line 3\", expected u64",
            ),
        ] {
            let e = JobSpec::parse(kind, &params).unwrap_err();
            assert_eq!(e, [(field.to_string(), message.to_string())], "{kind} {params}");
        }
        let e = JobSpec::parse("simulate", &json!({"n": 1, "n ": 2})).unwrap_err();
        assert_eq!(e[0].0, "params.n ");
        assert!(e[0].1.starts_with("unknown field `n `, expected one of `n`, `seed`"), "{e:?}");
    }

    #[test]
    fn unknown_kinds_and_out_of_range_limits_name_the_field() {
        let e = JobSpec::parse("compile", &json!({})).unwrap_err();
        assert_eq!(e[0].0, "kind");
        assert!(e[0].1.contains("simulate, train, resimulate, diagnose"), "{e:?}");
        // One set of limits for every kind (and the CLI): 16 flows, 5000 epochs.
        assert!(JobSpec::parse("train", &json!({"dataset": "d", "ensemble": 16, "max_epochs": 5000})).is_ok());
        let e = JobSpec::parse("train", &json!({"dataset": "d", "ensemble": 17, "max_epochs": 5001})).unwrap_err();
        let fields: Vec<&str> = e.iter().map(|(f, _)| f.as_str()).collect();
        assert_eq!(fields, ["params.max_epochs", "params.ensemble"], "{e:?}");
        assert_eq!(e[1].1, "must be 1..=16, got 17");
        let e = JobSpec::parse("diagnose", &json!({"x": [1.0], "max_epochs": 5001, "null_cases": 4})).unwrap_err();
        let fields: Vec<&str> = e.iter().map(|(f, _)| f.as_str()).collect();
        assert_eq!(fields, ["params.max_epochs", "params.null_cases"], "{e:?}");
        let e = JobSpec::parse("simulate", &json!({"n": 1_000_001})).unwrap_err();
        assert_eq!(e[0], ("params.n".into(), "must be 1..=1000000, got 1000001".into()));
        assert!(JobSpec::parse("simulate", &json!({"n": 200_000})).is_ok(), "a 200,000-row job (chunked)");
    }
}
