//! openapi.yaml against the types of the JSON edge: each request struct reads exactly the
//! properties its schema lists, and each response struct writes exactly the properties
//! its schema lists, every required one always. The field names come from serde (what a
//! derive hands a deserializer or serializer), so a field renamed on either side fails.
//! openapi.yaml is read by indentation (the tree has no YAML parser): block keys, one
//! per line, and one-line flow lists for `required`, as the file writes them.

use super::infer::{Figure, Figures, InferRequest, InferResponse, Inputs, Timing};
use super::log_prob::{LogProbRequest, LogProbResponse, UsedInputs};
use super::resources::{JobDoc, JobLinks, JobList, NewJob};
use crate::jobs::{DiagnoseParams, ExactParams, JobSpec, ResimulateParams, SimulateParams, TrainParams};
use crate::measurements::{MagPhase, Measurements, Values};
use serde::de::{self, DeserializeOwned, Visitor};
use serde::ser::{self, Impossible, Serialize};
use std::collections::BTreeSet;

const SPEC: &str = include_str!("../../../../openapi.yaml");

type Names = BTreeSet<String>;

fn indent(line: &str) -> usize {
    line.len() - line.trim_start().len()
}

/// A key's name as YAML writes it, quoted or not.
fn key_of(line: &str) -> &str {
    line.trim().split(':').next().unwrap_or("").trim_matches('"')
}

/// A YAML node: its own line and the lines of its block.
type Node = (&'static str, Vec<&'static str>);

/// The node at `path` below the lines of `block`: each key a direct child of the one
/// before (the shallowest lines of its block).
fn find(mut block: Vec<&'static str>, path: &[&str]) -> Node {
    let mut head = "";
    for key in path {
        let depth = block.iter().map(|l| indent(l)).min().unwrap_or(0);
        let at = block
            .iter()
            .position(|l| indent(l) == depth && key_of(l) == *key)
            .unwrap_or_else(|| panic!("openapi.yaml has no {path:?} (no {key} below {head:?})"));
        head = block[at];
        block = block[at + 1..].iter().take_while(|l| indent(l) > depth).copied().collect();
    }
    (head, block)
}

/// The node at `path` in openapi.yaml.
fn node(path: &[&str]) -> Node {
    find(SPEC.lines().filter(|l| !l.trim().is_empty()).collect(), path)
}

/// The component a `{ $ref: "#/components/schemas/NAME" }` node names, else the node.
fn schema(path: &[&str]) -> Node {
    let (head, block) = node(path);
    match head.split_once("$ref: \"#/components/schemas/") {
        Some((_, name)) => node(&["components", "schemas", name.split('"').next().unwrap_or("")]),
        None => (head, block),
    }
}

/// The schema of `method path`'s JSON request body.
fn request_schema(route: &str, method: &str) -> Node {
    schema(&["paths", route, method, "requestBody", "content", "application/json", "schema"])
}

/// The schema of `method path`'s `status` JSON answer.
fn response_schema(route: &str, method: &str, status: &str) -> Node {
    schema(&["paths", route, method, "responses", status, "content", "application/json", "schema"])
}

/// The names under a schema's `properties`.
fn properties(schema: &Node) -> Names {
    let (_, block) = find(schema.1.clone(), &["properties"]);
    let depth = block.iter().map(|l| indent(l)).min().unwrap_or(0);
    block.iter().filter(|l| indent(l) == depth).map(|l| key_of(l).to_string()).collect()
}

/// The names of a schema's `required: [a, b]`.
fn required((_, block): &Node) -> Names {
    let depth = block.iter().map(|l| indent(l)).min().unwrap_or(0);
    let line = block.iter().find(|l| indent(l) == depth && key_of(l) == "required");
    let list = line.and_then(|l| l.split_once('[')).map_or("", |(_, r)| r.split(']').next().unwrap_or(""));
    list.split(',').map(str::trim).filter(|s| !s.is_empty()).map(str::to_string).collect()
}

/// The property `name` of a schema, as a schema.
fn property(schema: &Node, name: &str) -> Node {
    find(schema.1.clone(), &["properties", name])
}

/// The fields serde reads for struct `T`: its derive hands them to `deserialize_struct`.
fn fields<T: DeserializeOwned>() -> Names {
    struct FieldNames<'a>(&'a mut &'static [&'static str]);
    impl<'de> de::Deserializer<'de> for FieldNames<'_> {
        type Error = de::value::Error;
        fn deserialize_any<V: Visitor<'de>>(self, _: V) -> Result<V::Value, Self::Error> {
            Err(de::Error::custom("not a struct"))
        }
        fn deserialize_struct<V: Visitor<'de>>(
            self,
            _: &'static str,
            fields: &'static [&'static str],
            _: V,
        ) -> Result<V::Value, Self::Error> {
            *self.0 = fields;
            Err(de::Error::custom("fields read"))
        }
        serde::forward_to_deserialize_any! {
            bool i8 i16 i32 i64 i128 u8 u16 u32 u64 u128 f32 f64 char str string bytes byte_buf option
            unit unit_struct newtype_struct seq tuple tuple_struct map enum identifier ignored_any
        }
    }
    let mut names: &'static [&'static str] = &[];
    let _ = T::deserialize(FieldNames(&mut names));
    assert!(!names.is_empty(), "{} is not a struct", std::any::type_name::<T>());
    names.iter().map(|s| s.to_string()).collect()
}

/// The keys serde writes for `value`: those written, and those its derive skipped
/// (`skip_serializing_if`) and so may be left out. A flattened struct's keys count as
/// written (a map gets no skipped keys).
#[derive(Debug, Default)]
struct Keys {
    written: Names,
    skipped: Names,
}

fn keys<T: Serialize>(value: &T) -> Keys {
    let mut k = Keys::default();
    value.serialize(KeyNames(&mut k)).unwrap();
    k
}

struct KeyNames<'a>(&'a mut Keys);
type Error = de::value::Error;

macro_rules! not_an_object {
    ($($name:ident($($t:ty),*) -> $r:ty;)*) => {
        $(fn $name(self $(, _: $t)*) -> Result<$r, Error> {
            Err(ser::Error::custom("not an object"))
        })*
    };
}

impl<'a> ser::Serializer for KeyNames<'a> {
    type Ok = ();
    type Error = Error;
    type SerializeSeq = Impossible<(), Error>;
    type SerializeTuple = Impossible<(), Error>;
    type SerializeTupleStruct = Impossible<(), Error>;
    type SerializeTupleVariant = Impossible<(), Error>;
    type SerializeMap = Self;
    type SerializeStruct = Self;
    type SerializeStructVariant = Impossible<(), Error>;

    not_an_object! {
        serialize_bool(bool) -> (); serialize_i8(i8) -> (); serialize_i16(i16) -> ();
        serialize_i32(i32) -> (); serialize_i64(i64) -> (); serialize_u8(u8) -> ();
        serialize_u16(u16) -> (); serialize_u32(u32) -> (); serialize_u64(u64) -> ();
        serialize_f32(f32) -> (); serialize_f64(f64) -> (); serialize_char(char) -> ();
        serialize_str(&str) -> (); serialize_bytes(&[u8]) -> (); serialize_none() -> ();
        serialize_unit() -> (); serialize_unit_struct(&'static str) -> ();
        serialize_unit_variant(&'static str, u32, &'static str) -> ();
        serialize_seq(Option<usize>) -> Impossible<(), Error>;
        serialize_tuple(usize) -> Impossible<(), Error>;
        serialize_tuple_struct(&'static str, usize) -> Impossible<(), Error>;
        serialize_tuple_variant(&'static str, u32, &'static str, usize) -> Impossible<(), Error>;
        serialize_struct_variant(&'static str, u32, &'static str, usize) -> Impossible<(), Error>;
    }

    fn serialize_some<T: ?Sized + Serialize>(self, _: &T) -> Result<(), Error> {
        Err(ser::Error::custom("not an object"))
    }
    fn serialize_newtype_struct<T: ?Sized + Serialize>(self, _: &'static str, v: &T) -> Result<(), Error> {
        v.serialize(self)
    }
    fn serialize_newtype_variant<T: ?Sized + Serialize>(
        self,
        _: &'static str,
        _: u32,
        _: &'static str,
        _: &T,
    ) -> Result<(), Error> {
        Err(ser::Error::custom("not an object"))
    }
    fn serialize_map(self, _: Option<usize>) -> Result<Self, Error> {
        Ok(self)
    }
    fn serialize_struct(self, _: &'static str, _: usize) -> Result<Self, Error> {
        Ok(self)
    }
}

impl ser::SerializeStruct for KeyNames<'_> {
    type Ok = ();
    type Error = Error;
    fn serialize_field<T: ?Sized + Serialize>(&mut self, key: &'static str, _: &T) -> Result<(), Error> {
        self.0.written.insert(key.into());
        Ok(())
    }
    fn skip_field(&mut self, key: &'static str) -> Result<(), Error> {
        self.0.skipped.insert(key.into());
        Ok(())
    }
    fn end(self) -> Result<(), Error> {
        Ok(())
    }
}

impl ser::SerializeMap for KeyNames<'_> {
    type Ok = ();
    type Error = Error;
    fn serialize_key<T: ?Sized + Serialize>(&mut self, key: &T) -> Result<(), Error> {
        let key = serde_json::to_value(key).map_err(ser::Error::custom)?;
        self.0.written.insert(key.as_str().unwrap_or_default().into());
        Ok(())
    }
    fn serialize_value<T: ?Sized + Serialize>(&mut self, _: &T) -> Result<(), Error> {
        Ok(())
    }
    fn end(self) -> Result<(), Error> {
        Ok(())
    }
}

/// `keys` of a response against its schema: every property written or skippable and
/// no other, every required one always written.
fn check_response(what: &str, k: &Keys, schema: &Node) {
    let all: Names = k.written.union(&k.skipped).cloned().collect();
    assert_eq!(all, properties(schema), "{what}: the fields written (left) and the schema's properties (right)");
    let missing: Names = required(schema).difference(&k.written).cloned().collect();
    assert!(missing.is_empty(), "{what}: required by the schema but not always written: {missing:?}");
}

#[test]
fn request_structs_read_exactly_their_schemas_properties() {
    let infer = request_schema("/infer", "post");
    assert_eq!(fields::<InferRequest>(), properties(&infer), "InferRequest");
    let measurements = property(&infer, "measurements");
    assert_eq!(fields::<Measurements>(), properties(&measurements), "measurements");
    for curve in ["VelocityCurve", "ImpedanceCurve"] {
        assert_eq!(fields::<MagPhase>(), properties(&node(&["components", "schemas", curve])), "{curve}");
    }
    assert_eq!(fields::<Values>(), properties(&node(&["components", "schemas", "Values"])), "Values");
    let log_prob = request_schema("/log_prob", "post");
    assert_eq!(fields::<LogProbRequest>(), properties(&log_prob), "LogProbRequest");
    // NewJob is one schema per kind, each of `kind` and that kind's params.
    let params = [
        ("Simulate", fields::<SimulateParams>()),
        ("Train", fields::<TrainParams>()),
        ("Resimulate", fields::<ResimulateParams>()),
        ("Diagnose", fields::<DiagnoseParams>()),
        ("Exact", fields::<ExactParams>()),
    ];
    assert!(request_schema("/jobs", "post").0.contains("NewJob"));
    for (kind, fields_of_params) in params {
        let job = node(&["components", "schemas", &format!("{kind}Job")]);
        assert_eq!(fields::<NewJob>(), properties(&job), "{kind}Job");
        assert_eq!(fields_of_params, properties(&node(&["components", "schemas", &format!("{kind}Params")])), "{kind}");
    }
}

#[test]
fn response_structs_write_exactly_their_schemas_properties() {
    let inputs = Inputs {
        used: vec![],
        interpolated: true,
        note: "",
        grid_hz: vec![],
        band_hz: Default::default(),
        format: "json",
        flow: "main",
        notes: None,
    };
    let timing_ms = Timing { sample: 0.0, map: 0.0, fit: 0.0, alternatives: 0.0, exact: 0.0, total: 0.0 };
    let infer = InferResponse {
        verdict: crate::npe::normal::verdict(&[], None),
        model: String::new(),
        fit: serde_json::Value::Null,
        parameters: vec![],
        differential: vec![],
        differential_note: "",
        map: vec![],
        inputs,
        samples_count: 0,
        seed: 0,
        timing_ms,
        exact: None,
        alternatives: None,
        next: None,
        refined: None,
        geometry: vec![],
        geometry_note: None,
        figures: None,
        samples: None,
        sample_columns: None,
    };
    let schema = response_schema("/infer", "post", "200");
    check_response("InferResponse", &keys(&infer), &schema);
    check_response("inputs", &keys(&infer.inputs), &property(&schema, "inputs"));
    check_response("timing_ms", &keys(&infer.timing_ms), &property(&schema, "timing_ms"));
    let figures = Figures { corner: Figure { media_type: "image/svg+xml", svg: String::new() } };
    let figures_schema = property(&schema, "figures");
    check_response("figures", &keys(&figures), &figures_schema);
    check_response("figures.corner", &keys(&figures.corner), &property(&figures_schema, "corner"));

    let log_prob = LogProbResponse {
        model: String::new(),
        columns: vec![],
        inputs: UsedInputs { used: vec![], flow: "main" },
        log_prob: vec![],
        outside_prior: vec![],
    };
    let schema = response_schema("/log_prob", "post", "200");
    check_response("LogProbResponse", &keys(&log_prob), &schema);

    // `redacted` given, so that the flattened row's map lists it too.
    let job = JobDoc {
        job: JobSpec::parse("train", &serde_json::json!({"dataset": "d"})).unwrap().queued(),
        redacted: vec!["params.x".into()],
        links: JobLinks { this: String::new(), cancel: String::new() },
    };
    for (route, method, status) in
        [("/jobs", "post", "202"), ("/jobs/{id}", "get", "200"), ("/jobs/{id}/cancel", "post", "202")]
    {
        check_response(&format!("{method} {route}"), &keys(&job), &response_schema(route, method, status));
    }
    let unredacted = JobDoc { redacted: vec![], ..job };
    let written = keys(&unredacted).written;
    let job_schema = node(&["components", "schemas", "Job"]);
    assert!(required(&job_schema).is_subset(&written), "Job: {written:?}");
    let list = JobList { jobs: vec![] };
    check_response("JobList", &keys(&list), &response_schema("/jobs", "get", "200"));
}
