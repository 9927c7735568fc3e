//! Contract fuzzing, schemathesis-style. Every operation of openapi.yaml gets
//! `EXAMPLES` requests made by a seeded generator from the valid bodies the spec and the
//! other tests use: fields removed, wrong JSON types, null, huge, negative and
//! NaN-as-string numbers, long and unicode strings, deep nesting, unknown fields, arrays
//! of the wrong length, malformed JSON, wrong content types, bad query strings and path
//! ids (traversal, percent-encoding, very long), with a tenant's key, an admin's, another
//! tenant's, a wrong one or none, and on a keyless server with foreign Host headers. Every
//! answer must be below 500, and every 4xx an RFC 9457 problem (application/problem+json
//! whose `status` is the HTTP status); a 2xx must hold the keys its schema requires. On
//! SQLite and PostgreSQL (`pg::backends`). No dispatcher runs: posted jobs only queue.
//!
//! `OTOFIT_FUZZ_SEED` and `OTOFIT_FUZZ_EXAMPLES` change the seed and the count.

use crate::pg::{TempDir, backends, ctx_on, temp_dir};
use axum::Router;
use axum::body::Body;
use axum::http::{HeaderValue, Request, StatusCode, header};
use otofit::http::{AppState, router};
use otofit::jobs::Ctx;
use rand::seq::IndexedRandom;
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use serde_json::{Value, json};
use std::sync::Arc;
use std::time::{Duration, Instant};
use tower::ServiceExt;

const SPEC: &str = include_str!("../../openapi.yaml");
/// Requests per operation (the issue asks for at least 200).
const EXAMPLES: usize = 300;

/// An operation of the spec: method, path template, the parameters it documents
/// (name, `in`, enum values), the examples of its request body and the required keys of
/// its first 2xx answer's JSON schema (none when it documents no schema).
#[derive(Debug, Default)]
struct Op {
    method: String,
    path: String,
    params: Vec<(String, String, Vec<String>)>,
    examples: Vec<Value>,
    ok_required: Option<Vec<String>>,
}

/// The names of a one-line `required: [a, b]`.
fn required_list(line: &str) -> Vec<String> {
    let inner = line.trim().trim_start_matches("required: [").trim_end_matches(']');
    inner.split(", ").map(str::to_string).collect()
}

/// The required keys of a component schema (the first `required:` below its name).
fn component_required(schema: &str) -> Vec<String> {
    let at = SPEC.find(&format!("\n    {schema}:\n")).unwrap_or_else(|| panic!("no schema {schema}"));
    required_list(SPEC[at..].lines().find(|l| l.trim().starts_with("required: [")).unwrap())
}

/// The value of `key: ` in a one-line flow mapping such as `{ name: id, in: path, … }`.
fn flow_value<'a>(line: &'a str, key: &str) -> Option<&'a str> {
    let rest = line.split_once(&format!(" {key}: "))?.1;
    Some(rest.split([',', '}']).next()?.trim())
}

/// The operations of openapi.yaml, read from its `paths:` section: path keys at two
/// spaces, methods at four, `parameters` items and `requestBody` examples below them.
fn operations() -> Vec<Op> {
    let paths = SPEC.split_once("\npaths:\n").unwrap().1.split_once("\ncomponents:\n").unwrap().0;
    let (mut ops, mut path, mut section, mut status) = (Vec::<Op>::new(), "", "", "");
    for line in paths.lines() {
        let indent = line.len() - line.trim_start().len();
        let key = line.trim().trim_end_matches(':');
        match indent {
            2 => path = key,
            4 => ops.push(Op { method: key.to_string(), path: path.to_string(), ..Op::default() }),
            6 => section = key.split(':').next().unwrap_or(""),
            8 if section == "responses" => status = key.split(':').next().unwrap_or("").trim_matches('"'),
            _ => {}
        }
        let Some(op) = ops.last_mut() else { continue };
        if section == "parameters"
            && let (Some(name), Some(place)) = (flow_value(line, "name"), flow_value(line, "in"))
        {
            let values = line
                .split_once("enum: [")
                .map_or(vec![], |(_, r)| r.split(']').next().unwrap_or("").split(", ").map(str::to_string).collect());
            op.params.push((name.to_string(), place.to_string(), values));
        }
        if section == "requestBody"
            && let Some(ex) = line.trim().strip_prefix("example: ")
        {
            op.examples.push(serde_json::from_str(ex).expect("a request example is JSON"));
        }
        if section == "responses" && status.starts_with('2') && op.ok_required.is_none() {
            if let Some((_, name)) = line.split_once("$ref: \"#/components/schemas/") {
                op.ok_required = Some(component_required(name.split('"').next().unwrap_or("")));
            } else if line.trim().starts_with("required: [") {
                op.ok_required = Some(required_list(line));
            }
        }
    }
    ops
}

/// Ids and keys the generator draws from: things that exist, for some principal.
struct World {
    apps: Vec<(String, Router, Vec<Option<String>>)>,
    job_ids: Vec<String>,
    model_ids: Vec<String>,
    x: Vec<f64>,
    theta: Vec<f64>,
}

/// A keyed server on `db`: tenants alpha and beta, an admin key and an `--api-key-hash`
/// key; alpha owns a succeeded simulate job (its dataset and report) and a model.
async fn keyed_app(
    name: &str,
    db: &otofit::store::Database,
) -> (Router, Arc<Ctx>, Vec<Option<String>>, String, TempDir) {
    let store = otofit::store::Store::connect(db).await.unwrap();
    let data = temp_dir(&format!("fuzz-{name}"));
    let path = std::fs::canonicalize(crate::http::default_model()).unwrap();
    store.add_model("default", &path.display().to_string(), true, None).await.unwrap();
    let mut ctx = Arc::into_inner(ctx_on(store, &data, "fuzz", Duration::from_secs(30))).unwrap();
    (ctx.max_queue, ctx.max_queue_per_tenant) = (1_000_000, 1_000_000);
    let ctx = Arc::new(ctx);
    let app = router(AppState::new(ctx.clone(), vec![otofit::store::key_hash("cli-key")]));
    let alpha = ctx.store.add_key("alpha", false).await.unwrap().key;
    let beta = ctx.store.add_key("beta", false).await.unwrap().key;
    let admin = ctx.store.add_key("ops", true).await.unwrap().key;
    let ja = crate::tenants::succeeded_simulate(&app, &ctx, &alpha).await;
    std::fs::write(ctx.dataset_dir(&ja).join("theta.csv"), "1\n").unwrap();
    ctx.store.add_model("ma", &path.display().to_string(), false, Some(&ja)).await.unwrap();
    let keys = [alpha.clone(), alpha, beta, admin, "cli-key".into()].map(Some);
    (app, ctx, keys.into(), ja, data)
}

/// A keyless server (the Host guard instead of keys) on SQLite, and its data dir's guard.
async fn keyless_app() -> (Router, TempDir) {
    let data = temp_dir("fuzz-keyless");
    let ctx = otofit::cli::serve::open(&data, &crate::http::default_model(), 1_000_000).await.unwrap();
    (router(AppState::new(ctx, vec![])), data)
}

/// One generated request, kept to be shown when its answer breaks the contract.
struct Case {
    method: String,
    uri: String,
    headers: Vec<(String, Vec<u8>)>,
    body: Vec<u8>,
}

impl std::fmt::Display for Case {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        let uri: String = self.uri.chars().take(300).collect();
        write!(f, "{} {uri}", self.method)?;
        for (k, v) in &self.headers {
            let v = String::from_utf8_lossy(v);
            let v =
                if k == "authorization" { format!("{}…", v.chars().take(10).collect::<String>()) } else { v.into() };
            write!(f, "\n  {k}: {v}")?;
        }
        let body = String::from_utf8_lossy(&self.body[..self.body.len().min(400)]).into_owned();
        write!(f, "\n  body ({} bytes): {body}", self.body.len())
    }
}

const UNICODE: [&str; 6] =
    ["ünïcødé", "🦀🦀🦀", "\u{202e}gnp.exe", "\u{0}\u{1}\u{7f}", "ｆｕｌｌｗｉｄｔｈ", "\u{fffd}\u{feff}\u{10ffff}"];

/// A value of a type the schema does not expect, or at its edges.
fn odd_value(rng: &mut ChaCha8Rng) -> Value {
    match rng.random_range(0..22) {
        0 => Value::Null,
        1 => json!(true),
        2 => json!(0),
        3 => json!(-1),
        4 => json!(-1e308),
        5 => json!(1e308),
        6 => json!(5e-324),
        7 => json!(u64::MAX),
        8 => json!(i64::MIN),
        9 => json!(9007199254740993u64),
        10 => json!(20001),
        11 => json!(0.5),
        12 => json!(["NaN", "Infinity", "-Infinity", "1e999", "-0", "0x10"][rng.random_range(0..6)]),
        13 => json!(""),
        14 => json!("x".repeat(rng.random_range(1_000..100_000))),
        15 => json!(UNICODE.choose(rng).unwrap()),
        16 => json!(["../../../../etc/passwd", "default", "%00", "null", "corner"][rng.random_range(0..5)]),
        17 => json!([]),
        18 => json!({}),
        19 => (0..rng.random_range(2..200)).fold(json!(1), |v, _| json!([v])),
        20 => json!({"a": {"b": [1, "2", null]}}),
        _ => json!(rng.random_range(-1e6..1e6)),
    }
}

/// The JSON pointer of a node reached by a random walk from the root (every depth
/// equally likely to be picked, not every node: the long arrays do not drown the rest).
fn random_pointer(v: &Value, rng: &mut ChaCha8Rng) -> String {
    let (mut node, mut ptr) = (v, String::new());
    loop {
        let children: Vec<(String, &Value)> = match node {
            Value::Object(m) => m.iter().map(|(k, v)| (k.replace('~', "~0").replace('/', "~1"), v)).collect(),
            Value::Array(a) => a.iter().enumerate().map(|(i, v)| (i.to_string(), v)).collect(),
            _ => vec![],
        };
        if children.is_empty() || rng.random_bool(0.25) {
            return ptr;
        }
        let (k, child) = children.choose(rng).unwrap();
        ptr = format!("{ptr}/{k}");
        node = child;
    }
}

/// One structural mutation of `v` at a random node.
fn mutate(v: &mut Value, rng: &mut ChaCha8Rng) {
    let ptr = random_pointer(v, rng);
    let other = v.pointer(&random_pointer(v, rng)).cloned().unwrap_or(Value::Null);
    let (parent, last) = ptr.rsplit_once('/').unwrap_or(("", ""));
    let kind = rng.random_range(0..7);
    if kind == 0 && !ptr.is_empty() {
        // Remove the node from its object or array.
        let key = last.replace("~1", "/").replace("~0", "~");
        match v.pointer_mut(parent) {
            Some(Value::Object(m)) => {
                m.remove(&key);
            }
            Some(Value::Array(a)) => {
                if let Some(i) = key.parse::<usize>().ok().filter(|&i| i < a.len()) {
                    a.remove(i);
                }
            }
            _ => {}
        }
        return;
    }
    let Some(node) = v.pointer_mut(&ptr) else { return };
    match (kind, node) {
        (1, Value::Array(a)) => {
            // The wrong length: empty, one short, one more, or repeated (bounded).
            match rng.random_range(0..4) {
                0 => a.clear(),
                1 => {
                    a.pop();
                }
                2 => a.push(a.last().cloned().unwrap_or(json!(1))),
                _ => {
                    let copy = a.clone();
                    a.extend(copy.into_iter().cycle().take(rng.random_range(1..64)));
                }
            }
        }
        (2, Value::Object(m)) => {
            m.insert(["bogus", "", "__proto__", "ünï"][rng.random_range(0..4)].into(), odd_value(rng));
        }
        (3, node) => *node = other,
        (4, node @ Value::Number(_)) => {
            let f = node.as_f64().unwrap_or(1.0);
            *node = [json!(-f), json!(f * 1e300), json!(f.to_string()), json!(f / 1e300), json!(f.round() as i64)]
                [rng.random_range(0..5)]
            .clone();
        }
        (_, node) => *node = odd_value(rng),
    }
}

/// Malformed JSON, or a valid one of the wrong shape, from a serialized body.
fn mangle(body: &mut Vec<u8>, rng: &mut ChaCha8Rng) {
    match rng.random_range(0..8) {
        0 => body.truncate(rng.random_range(0..=body.len())),
        1 => {
            let at = rng.random_range(0..=body.len());
            let byte = [b'{', b'"', b'\\', 0xff, 0xc3, 0, b'\n', b','][rng.random_range(0..8)];
            body.insert(at, byte);
        }
        2 => body.extend_from_slice([&b" trailing"[..], b"}", b"{}", b"\0"][rng.random_range(0..4)]),
        3 => {
            // A number token as a JSON-invalid one.
            let text = String::from_utf8_lossy(body).into_owned();
            let starts: Vec<usize> = text.match_indices(':').map(|(i, _)| i + 1).collect();
            if let Some(&at) = starts.choose(rng) {
                let end = text[at..].find([',', '}', ']']).map_or(text.len(), |e| at + e);
                let bad = ["NaN", "Infinity", "-Infinity", "1e999", "-", "01", "1.", ".5", "+1", "0x1F"];
                *body = format!("{}{}{}", &text[..at], bad.choose(rng).unwrap(), &text[end..]).into_bytes();
            }
        }
        4 => body.clear(),
        5 => *body = [&[0xef, 0xbb, 0xbf][..], body].concat(),
        6 => *body = [&b"null"[..], b"[]", b"\"s\"", b"1", b"{", b"[[[[[[[[", b"true"][rng.random_range(0..7)].to_vec(),
        _ => *body = vec![b' '; otofit::http::MAX_BODY + 1],
    }
}

/// Percent-encodes everything but unreserved characters.
fn enc(s: &str) -> String {
    s.bytes()
        .map(|b| {
            if b.is_ascii_alphanumeric() || b"-._~".contains(&b) {
                (b as char).to_string()
            } else {
                format!("%{b:02X}")
            }
        })
        .collect()
}

/// A path segment: an id that exists (for someone), or a hostile one.
fn segment(rng: &mut ChaCha8Rng, real: &[String], values: &[String]) -> String {
    if rng.random_bool(0.45) {
        let pool = if values.is_empty() { real } else { values };
        // The first is the one with files (a dataset, a report): picked more often.
        if let Some(v) = if rng.random_bool(0.3) { pool.first() } else { pool.choose(rng) } {
            return v.clone();
        }
    }
    match rng.random_range(0..16) {
        0 => "..".into(),
        1 => "../../../../etc/passwd".into(),
        2 => "..%2F..%2Fotofit.db".into(),
        3 => "%2e%2e".into(),
        4 => "%00".into(),
        5 => "%FF%FE".into(),
        6 => enc(UNICODE.choose(rng).unwrap()),
        7 => "a".repeat(rng.random_range(65..6_000)),
        8 => "a".repeat(otofit::http::MAX_URI + 1),
        9 => enc("' OR 1=1 --"),
        10 => "report.html".into(),
        11 => "spectra.svg%00.html".into(),
        12 => "x.csv".into(),
        13 => "%".into(),
        14 => enc(&format!("{} ", real.choose(rng).map_or("x", |s| s.as_str()))),
        _ => rng.random_range(0..u64::MAX).to_string(),
    }
}

/// A query string: the operation's parameters with good and bad values, unknown ones,
/// and malformed encodings.
fn query(rng: &mut ChaCha8Rng, op: &Op) -> String {
    let known: Vec<&(String, String, Vec<String>)> = op.params.iter().filter(|p| p.1 == "query").collect();
    let mut parts = vec![];
    for _ in 0..rng.random_range(1..4) {
        let name = match known.choose(rng) {
            Some(p) if rng.random_bool(0.7) => p.0.clone(),
            _ => ["limt", "state", "limit", "", "plot", "a[b]", "%ZZ", "%FF"][rng.random_range(0..8)].to_string(),
        };
        let enum_value = known.iter().find(|p| p.0 == name).and_then(|p| p.2.choose(rng)).cloned();
        let value = match rng.random_range(0..12) {
            0..3 if enum_value.is_some() => enum_value.unwrap(),
            0 => "1".into(),
            1 => "-5".into(),
            2 => "1e3".into(),
            3 => "99999999999999999999999".into(),
            4 => "abc".into(),
            5 => String::new(),
            6 => "%00".into(),
            7 => "%FF".into(),
            8 => enc(UNICODE.choose(rng).unwrap()),
            9 => "Zang=deg".into(),
            10 => "Ear=Left".into(),
            _ => "x".repeat(rng.random_range(1..3_000)),
        };
        parts.push(if rng.random_bool(0.1) { name } else { format!("{name}={value}") });
    }
    if rng.random_bool(0.1) {
        parts.push(String::new());
    }
    parts.join("&")
}

/// Valid bodies of the operation (the spec's examples and those of the other tests).
fn seeds(op: &Op, w: &World) -> Vec<(Value, &'static str)> {
    let mut out: Vec<(Value, &str)> =
        op.examples.iter().map(|e| (e.clone(), if e.is_string() { "text/csv" } else { "application/json" })).collect();
    let theta = json!([w.theta, w.theta.iter().map(|v| v * 1.5).collect::<Vec<_>>()]);
    let nominal = crate::http::nominal_request();
    let measurements = nominal["measurements"].clone();
    let json = |v: Value| (v, "application/json");
    match (op.method.as_str(), op.path.as_str()) {
        ("post", "/infer") => {
            let mut small = nominal.clone();
            small["samples"] = json!(200);
            small["return_samples"] = json!(false);
            let mut wbt = small.clone();
            wbt["measurements"].as_object_mut().unwrap().remove("stapes_velocity");
            wbt["plot"] = json!("corner");
            wbt["model"] = json!("default");
            out.extend([json(small), json(wbt), json(json!({"measurements": {}}))]);
        }
        ("post", "/log_prob") => {
            out.push(json(json!({"measurements": measurements, "theta": theta})));
            out.push(json(json!({"model": "ma", "measurements": measurements, "theta": [w.theta]})));
        }
        ("post", "/jobs") => {
            let ds = &w.job_ids[0];
            out.extend(
                [
                    json!({"kind": "simulate", "params": {"n": 3, "seed": 1, "effects": {"probe_leak": 1e-4}, "vary": ["probe_offset"]}}),
                    json!({"kind": "simulate", "params": {"theta": theta, "noise_scale": 0.5}}),
                    json!({"kind": "train", "params": {"dataset": ds, "max_epochs": 2, "ensemble": 2, "mask_groups": true}}),
                    json!({"kind": "resimulate", "params": {"theta": theta, "observation": w.x}}),
                    json!({"kind": "diagnose", "params": {"x": w.x, "model": "default", "candidates": ["probe_leak"], "extend": false, "null_cases": 5}}),
                ]
                .map(json),
            );
        }
        _ => {}
    }
    out
}

/// A request for `op` made from one of its `seeds`, and the index of the app to send it to.
fn generate(rng: &mut ChaCha8Rng, op: &Op, seeds: &[(Value, &str)], w: &World) -> (usize, Case) {
    let mut method = op.method.to_uppercase();
    if rng.random_bool(0.04) {
        method = ["GET", "POST", "PUT", "DELETE", "PATCH", "OPTIONS", "HEAD"].choose(rng).unwrap().to_string();
    }
    let mut uri = op.path.clone();
    for (name, place, values) in &op.params {
        if place == "path" {
            let real = if op.path.starts_with("/models") { &w.model_ids } else { &w.job_ids };
            let real: Vec<String> = if name == "name" { vec!["report.html".into()] } else { real.clone() };
            uri = uri.replace(&format!("{{{name}}}"), &segment(rng, &real, values));
        }
    }
    if rng.random_bool(0.35) {
        uri = format!("{uri}?{}", query(rng, op));
    }
    let mut headers: Vec<(String, Vec<u8>)> = vec![];
    let mut body = vec![];
    let wants_body = op.method == "post" && !seeds.is_empty();
    if wants_body || rng.random_bool(0.1) {
        let (mut v, mut ct) = seeds.choose(rng).cloned().unwrap_or((json!({"a": 1}), "application/json"));
        for _ in 0..rng.random_range(0..4) {
            mutate(&mut v, rng);
        }
        body = match &v {
            Value::String(s) if ct == "text/csv" && rng.random_bool(0.7) => s.clone().into_bytes(),
            _ => {
                ct = "application/json";
                v.to_string().into_bytes()
            }
        };
        if rng.random_bool(0.2) {
            mangle(&mut body, rng);
        }
        let ct: &[u8] = match rng.random_range(0..20) {
            0 => b"",
            1 => b"text/plain",
            2 => b"application/json; charset=utf-8",
            3 => b"APPLICATION/JSON",
            4 => b"application/jsonx",
            5 => b"application/problem+json",
            6 => b"text/csv",
            7 => b"multipart/form-data; boundary=x",
            8 => b";;;",
            9 => b"application/json\xff",
            _ => ct.as_bytes(),
        };
        if !ct.is_empty() {
            headers.push(("content-type".into(), ct.to_vec()));
        }
    }
    if rng.random_bool(0.03) {
        headers.push(("content-length".into(), b"99999999999".to_vec()));
    }
    let app = if w.apps.len() > 1 && rng.random_bool(0.2) { 1 } else { 0 };
    let keys = &w.apps[app].2;
    match keys.choose(rng).cloned().flatten() {
        Some(key) if rng.random_bool(0.9) => {
            headers.push(("authorization".into(), format!("Bearer {key}").into_bytes()))
        }
        _ => {
            let bad: [&[u8]; 6] =
                [b"", b"Bearer", b"Bearer wrong", b"Basic YTpi", b"bearer  \xff\xfe", b"Bearer a b c"];
            let b = bad.choose(rng).unwrap();
            if !b.is_empty() {
                headers.push(("authorization".into(), b.to_vec()));
            }
        }
    }
    if app == 1 || rng.random_bool(0.1) {
        let hosts: [&[u8]; 9] =
            [b"localhost", b"127.0.0.1:8080", b"[::1]:80", b"evil.example", b"", b"a:b:c", b"[::1", b"h\xc3\xa9", b"."];
        headers.push(("host".into(), hosts.choose(rng).unwrap().to_vec()));
    }
    (app, Case { method, uri, headers, body })
}

/// Whether an answer keeps the contract: below 500; a 4xx is a problem whose `status` is
/// the HTTP status; a JSON 2xx parses. An answer to HEAD has no body: its headers only.
fn verdict(status: StatusCode, content_type: Option<&HeaderValue>, body: &[u8], head: bool) -> Result<(), String> {
    if status.is_server_error() {
        return Err(format!("{status}"));
    }
    let json: Option<Value> = serde_json::from_slice(body).ok();
    if status.is_client_error() {
        if content_type.is_none_or(|c| c != "application/problem+json") {
            return Err(format!("{status} with content-type {content_type:?}"));
        }
        if head && body.is_empty() {
            return Ok(());
        }
        let p = json.ok_or_else(|| format!("{status} whose body is not JSON"))?;
        if p["status"].as_u64() != Some(status.as_u16().into()) {
            return Err(format!("{status} whose problem says status {}", p["status"]));
        }
        if !["type", "title", "detail"].iter().all(|k| p[k].is_string()) {
            return Err(format!("{status}: a problem without type, title and detail"));
        }
        let fields_ok = p.get("errors").is_none_or(|e| {
            e.as_array().is_some_and(|e| e.iter().all(|f| f["field"].is_string() && f["message"].is_string()))
        });
        if !fields_ok {
            return Err(format!("{status}: errors are not [{{field, message}}]"));
        }
    } else if content_type.is_some_and(|c| c.as_bytes().starts_with(b"application/json")) && json.is_none() && !head {
        return Err(format!("{status}: application/json that does not parse"));
    }
    Ok(())
}

/// Whether a 2xx JSON answer of `op` has the keys its documented schema requires.
fn conforms(op: &Op, body: &[u8]) -> Result<(), String> {
    let (Some(required), Ok(v)) = (&op.ok_required, serde_json::from_slice::<Value>(body)) else { return Ok(()) };
    match required.iter().find(|k| v.get(k.as_str()).is_none()) {
        Some(k) => Err(format!("a {} {} answer without the required '{k}'", op.method, op.path)),
        None => Ok(()),
    }
}

/// Sends `case` to `app`: the answer's status, content type and body.
async fn send(app: &Router, case: &Case) -> (StatusCode, Option<HeaderValue>, Vec<u8>) {
    let mut req = Request::builder().method(case.method.as_str()).uri(case.uri.as_str());
    for (k, v) in &case.headers {
        req = req.header(k.as_str(), HeaderValue::from_bytes(v).unwrap());
    }
    let res = app.clone().oneshot(req.body(Body::from(case.body.clone())).unwrap()).await.unwrap();
    let (status, ct) = (res.status(), res.headers().get(header::CONTENT_TYPE).cloned());
    (status, ct, axum::body::to_bytes(res.into_body(), usize::MAX).await.unwrap().to_vec())
}

fn env_or<T: std::str::FromStr>(name: &str, default: T) -> T {
    std::env::var(name).ok().and_then(|v| v.parse().ok()).unwrap_or(default)
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn contract_fuzzing_finds_no_5xx_and_only_problem_errors() {
    let t0 = Instant::now();
    let (examples, seed) = (env_or("OTOFIT_FUZZ_EXAMPLES", EXAMPLES), env_or("OTOFIT_FUZZ_SEED", 13u64));
    let ops = operations();
    let mut served: Vec<(String, String)> =
        otofit::http::ROUTES.iter().map(|(m, p)| (m.to_string(), p.to_string())).collect();
    let mut listed: Vec<(String, String)> = ops.iter().map(|o| (o.method.clone(), o.path.clone())).collect();
    served.sort();
    listed.sort();
    assert_eq!(listed, served, "the fuzzer reads every operation of openapi.yaml");
    let with_schema = ops.iter().filter(|o| o.ok_required.is_some()).count();
    assert_eq!(
        with_schema,
        11,
        "2xx schemas read: {:?}",
        ops.iter().map(|o| (&o.path, &o.ok_required)).collect::<Vec<_>>()
    );
    let mut failures = vec![];
    for (backend, db) in backends().await {
        let (app, _ctx, keys, ja, _data) = keyed_app(&backend, &db).await;
        let mut apps = vec![(backend.clone(), app, keys)];
        let mut _keyless_data = None;
        if backend == "sqlite" {
            let (keyless, data) = keyless_app().await;
            apps.push(("sqlite keyless".into(), keyless, vec![None]));
            _keyless_data = Some(data);
        }
        let theta: Vec<f64> = otofit::sim::params::PARAMS.iter().map(|p| p.nominal).collect();
        let mut w =
            World { apps, job_ids: vec![ja], model_ids: vec!["default".into(), "ma".into()], x: vec![0.5; 350], theta };
        for (i, op) in ops.iter().enumerate() {
            let mut rng = ChaCha8Rng::seed_from_u64(seed ^ ((i as u64) << 32));
            let seeds = seeds(op, &w);
            let (t, mut tally) = (Instant::now(), std::collections::BTreeMap::<u16, usize>::new());
            for k in 0..examples {
                let (app, case) = generate(&mut rng, op, &seeds, &w);
                let (status, ct, body) = send(&w.apps[app].1, &case).await;
                *tally.entry(status.as_u16()).or_default() += 1;
                if status == StatusCode::ACCEPTED
                    && let Some(id) =
                        serde_json::from_slice::<Value>(&body).ok().and_then(|j| j["id"].as_str().map(String::from))
                {
                    w.job_ids.push(id);
                }
                let mut checked = verdict(status, ct.as_ref(), &body, case.method == "HEAD");
                if status.is_success() && case.method == op.method.to_uppercase() {
                    checked = checked.and(conforms(op, &body));
                }
                if let Err(why) = checked {
                    let answer = String::from_utf8_lossy(&body[..body.len().min(300)]).into_owned();
                    let on = &w.apps[app].0;
                    failures.push(format!(
                        "[{on}, seed {seed}, {} {} #{k}] {why}\n  {case}\n  → {answer}",
                        op.method, op.path
                    ));
                }
            }
            eprintln!(
                "fuzz {backend}: {} {} {examples} requests in {:.1} s: {tally:?}",
                op.method,
                op.path,
                t.elapsed().as_secs_f64()
            );
        }
    }
    eprintln!("fuzz: {:.1} s in all", t0.elapsed().as_secs_f64());
    for f in failures.iter().take(20) {
        eprintln!("{f}\n");
    }
    assert!(failures.is_empty(), "{} requests broke the contract (the first are printed above)", failures.len());
}

/// The check itself: it passes a problem and flags a 5xx, a plain-text or empty 4xx, a
/// problem whose status is not the answer's, and a JSON 2xx that does not parse.
#[test]
fn the_contract_check_flags_what_it_must() {
    let (problem, text) =
        (HeaderValue::from_static("application/problem+json"), HeaderValue::from_static("text/plain"));
    let p = |status: u16| json!({"type": "t", "title": "x", "status": status, "detail": "d"}).to_string().into_bytes();
    assert_eq!(verdict(StatusCode::BAD_REQUEST, Some(&problem), &p(400), false), Ok(()));
    assert_eq!(verdict(StatusCode::OK, Some(&HeaderValue::from_static("application/json")), b"{}", false), Ok(()));
    for (status, ct, body) in [
        (StatusCode::INTERNAL_SERVER_ERROR, Some(&problem), p(500)),
        (StatusCode::SERVICE_UNAVAILABLE, Some(&problem), p(503)),
        (StatusCode::BAD_REQUEST, Some(&text), b"bad request".to_vec()),
        (StatusCode::METHOD_NOT_ALLOWED, None, vec![]),
        (StatusCode::NOT_FOUND, Some(&problem), p(400)),
        (StatusCode::NOT_FOUND, Some(&problem), br#"{"status": 404}"#.to_vec()),
        (StatusCode::OK, Some(&HeaderValue::from_static("application/json")), b"{".to_vec()),
    ] {
        assert!(verdict(status, ct, &body, false).is_err(), "{status} {ct:?} passed");
    }
}
