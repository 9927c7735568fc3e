//! Artifacts in S3-compatible object storage, against a real S3 server: moto's
//! (`moto_server`, from PyPI's `moto[server]`; `.ci/run` installs it into a venv under
//! the cache folder when absent), started on a free loopback port for each test. Without
//! moto_server the S3 tests skip with a loud message, except under CI (`CI` set) or with
//! `OTOFIT_REQUIRE_S3=1`, where they fail.

use crate::pg::{Procs, fresh_database, temp_dir};
use serde_json::{Value, json};
use std::path::{Path, PathBuf};
use std::process::{Command, Stdio};
use std::time::{Duration, Instant};

/// moto_server: `OTOFIT_MOTO_SERVER`, else in the venv `.ci/run` makes, else on PATH.
fn moto_bin() -> Option<PathBuf> {
    if let Some(p) = std::env::var_os("OTOFIT_MOTO_SERVER") {
        return Some(PathBuf::from(p)).filter(|p| p.is_file());
    }
    let cache = std::env::var_os("XDG_CACHE_HOME")
        .map(PathBuf::from)
        .or_else(|| std::env::var_os("HOME").map(|h| PathBuf::from(h).join(".cache")));
    let venv = cache.map(|c| c.join("otofit/venv/bin/moto_server")).filter(|p| p.is_file());
    venv.or_else(|| {
        std::env::var_os("PATH")
            .and_then(|p| std::env::split_paths(&p).map(|d| d.join("moto_server")).find(|f| f.is_file()))
    })
}

fn free_port() -> u16 {
    std::net::TcpListener::bind("127.0.0.1:0").unwrap().local_addr().unwrap().port()
}

/// A running moto server (killed when dropped) and its port.
struct Moto {
    port: u16,
    _proc: Procs,
}

/// Starts moto_server on a free loopback port; `None` (after a loud message) when it is
/// not installed and not required.
fn start_moto() -> Option<Moto> {
    let required = std::env::var_os("CI").is_some() || std::env::var_os("OTOFIT_REQUIRE_S3").is_some();
    let Some(bin) = moto_bin() else {
        assert!(!required, "moto_server is required here (CI or OTOFIT_REQUIRE_S3) but not found");
        eprintln!(
            "\n!!!!! SKIPPING an S3 test: moto_server not found (pip install 'moto[server]==5.2.5'; .ci/run does) !!!!!\n"
        );
        return None;
    };
    let port = free_port();
    let child = Command::new(&bin)
        .args(["-H", "127.0.0.1", "-p", &port.to_string()])
        .stdout(Stdio::null())
        .stderr(Stdio::null())
        .spawn()
        .unwrap_or_else(|e| panic!("{}: {e}", bin.display()));
    let moto = Moto { port, _proc: Procs(vec![child]) };
    let t0 = Instant::now();
    while raw(port, "GET", "/", b"").is_none() {
        assert!(t0.elapsed() < Duration::from_secs(60), "moto_server did not answer on 127.0.0.1:{port} within 60 s");
        std::thread::sleep(Duration::from_millis(200));
    }
    Some(moto)
}

/// One HTTP request: (status, body bytes).
fn raw(port: u16, method: &str, path: &str, body: &[u8]) -> Option<(u16, Vec<u8>)> {
    use std::io::{Read, Write};
    let mut s = std::net::TcpStream::connect(("127.0.0.1", port)).ok()?;
    let head = format!(
        "{method} {path} HTTP/1.1\r\nHost: 127.0.0.1:{port}\r\nContent-Type: application/json\r\nContent-Length: {}\r\nConnection: close\r\n\r\n",
        body.len()
    );
    s.write_all(head.as_bytes()).ok()?;
    s.write_all(body).ok()?;
    let mut out = vec![];
    s.read_to_end(&mut out).ok()?;
    let split = out.windows(4).position(|w| w == b"\r\n\r\n")?;
    let head = String::from_utf8_lossy(&out[..split]).into_owned();
    let status = head.split(' ').nth(1)?.parse().ok()?;
    let mut body = out[split + 4..].to_vec();
    if head.to_ascii_lowercase().contains("transfer-encoding: chunked") {
        body = unchunk(&body);
    }
    Some((status, body))
}

fn unchunk(mut b: &[u8]) -> Vec<u8> {
    let mut out = vec![];
    while let Some(eol) = b.windows(2).position(|w| w == b"\r\n") {
        let n = usize::from_str_radix(String::from_utf8_lossy(&b[..eol]).trim(), 16).unwrap_or(0);
        if n == 0 {
            break;
        }
        out.extend_from_slice(&b[eol + 2..eol + 2 + n]);
        b = &b[eol + 2 + n + 2..];
    }
    out
}

fn json_of(port: u16, method: &str, path: &str, body: Option<&Value>) -> (u16, Value) {
    let b = body.map(|b| b.to_string()).unwrap_or_default();
    let (status, bytes) = raw(port, method, path, b.as_bytes()).expect("the server answers");
    (status, serde_json::from_slice(&bytes).unwrap_or(Value::Null))
}

/// `otofit serve`/`worker` with the S3 store of `moto` under `s3://otofit-test/lab`.
fn otofit(moto: &Moto, args: &[&str]) -> Command {
    let mut c = Command::new(env!("CARGO_BIN_EXE_otofit"));
    c.args(args).args(["--artifacts", "s3://otofit-test/lab"]);
    for (k, _) in std::env::vars_os() {
        if k.to_string_lossy().starts_with("AWS_") {
            c.env_remove(k);
        }
    }
    c.env("AWS_ENDPOINT", format!("http://127.0.0.1:{}", moto.port))
        .env("AWS_ALLOW_HTTP", "true")
        .env("AWS_ACCESS_KEY_ID", "testing")
        .env("AWS_SECRET_ACCESS_KEY", "testing")
        .env("AWS_DEFAULT_REGION", "us-east-1")
        .stdout(Stdio::null())
        .stderr(Stdio::null());
    c
}

/// The bucket's listing (ListObjectsV2 XML) under `lab/`.
fn bucket_listing(moto: &Moto) -> String {
    let (status, body) = raw(moto.port, "GET", "/otofit-test?list-type=2&prefix=lab/", b"").unwrap();
    assert_eq!(status, 200);
    String::from_utf8_lossy(&body).into_owned()
}

fn wait_job(port: u16, id: &str, secs: u64) -> Value {
    let t0 = Instant::now();
    loop {
        let (_, j) = json_of(port, "GET", &format!("/jobs/{id}"), None);
        if !matches!(j["state"].as_str(), Some("queued" | "running")) || t0.elapsed() > Duration::from_secs(secs) {
            return j;
        }
        std::thread::sleep(Duration::from_millis(200));
    }
}

fn files_under(dir: &Path) -> Vec<String> {
    let mut out = vec![];
    for e in std::fs::read_dir(dir).into_iter().flatten().flatten() {
        let p = e.path();
        if p.is_dir() {
            out.extend(files_under(&p).into_iter().map(|f| format!("{}/{f}", e.file_name().to_string_lossy())));
        } else {
            out.push(e.file_name().to_string_lossy().into_owned());
        }
    }
    out
}

/// A worker with data directory A stores a simulate job's dataset in S3
/// (moto); a worker with data directory C fetches it to train a model and stores the
/// model and a resimulate job's report; a `serve` with data directory B (the same
/// PostgreSQL job table, no shared files) serves the dataset and the report from the
/// store and answers /infer with the trained model, fetched into B.
#[test]
fn a_server_with_another_data_directory_serves_what_a_worker_stored_in_s3() {
    let Some(moto) = start_moto() else { return };
    let rt = tokio::runtime::Runtime::new().unwrap();
    let Some(url) = rt.block_on(fresh_database()) else { return };
    let (status, body) = raw(moto.port, "PUT", "/otofit-test", b"").unwrap();
    assert_eq!(status, 200, "creating the bucket: {}", String::from_utf8_lossy(&body));
    let (a, b) = (temp_dir("s3w"), temp_dir("s3s"));
    let port = free_port();
    let model = crate::http::default_model();
    let serve = otofit(&moto, &["serve", "--database", &url, "--data-dir", b.to_str().unwrap(), "--workers", "0"])
        .args(["--addr", &format!("127.0.0.1:{port}"), "--default-model", model.to_str().unwrap()])
        .spawn()
        .unwrap();
    let worker = otofit(&moto, &["worker", "--database", &url, "--data-dir", a.to_str().unwrap(), "--threads", "1"])
        .spawn()
        .unwrap();
    let mut procs = Procs(vec![serve, worker]);
    let t0 = Instant::now();
    while raw(port, "GET", "/health", b"").is_none() {
        assert!(t0.elapsed() < Duration::from_secs(30), "serve did not start");
        std::thread::sleep(Duration::from_millis(100));
    }

    // A dataset, made by the worker, served by the server from the store.
    let (status, j) =
        json_of(port, "POST", "/jobs", Some(&json!({"kind": "simulate", "params": {"n": 120, "seed": 3}})));
    assert_eq!(status, 202, "{j}");
    let sim = j["id"].as_str().unwrap().to_string();
    let done = wait_job(port, &sim, 120);
    assert_eq!(done["state"], "succeeded", "{done}");
    let (status, x) = raw(port, "GET", &format!("/datasets/{sim}/x.csv"), b"").unwrap();
    assert_eq!(status, 200, "{}", String::from_utf8_lossy(&x));
    assert_eq!(String::from_utf8_lossy(&x).lines().count(), 121);
    assert_eq!(x, std::fs::read(a.join(format!("datasets/{sim}/x.csv"))).unwrap(), "the worker's bytes");
    let listed = bucket_listing(&moto);
    let entry = format!("<Key>lab/datasets/{sim}/x.csv</Key>");
    let at = listed.find(&entry).unwrap_or_else(|| panic!("no {entry} in the bucket: {listed}"));
    let size = listed[at..].split("<Size>").nth(1).and_then(|s| s.split('<').next()).unwrap();
    assert_eq!(size, x.len().to_string(), "the object in the bucket has the dataset's size");
    let (status, ds) = json_of(port, "GET", &format!("/datasets/{sim}"), None);
    assert_eq!((status, ds["rows"].as_u64()), (200, Some(120)), "{ds}");
    assert!(!b.join("datasets").exists(), "the server has no dataset files of its own");

    // Worker A stops; worker C (its own data directory) trains on A's dataset, fetched
    // from the store.
    procs.0[1].kill().unwrap();
    procs.0[1].wait().unwrap();
    let c = temp_dir("s3c");
    let other = ["worker", "--database", &url, "--data-dir", c.to_str().unwrap(), "--threads", "1"];
    procs.0.push(otofit(&moto, &other).spawn().unwrap());

    // A model trained by a worker, loaded by the server from the store.
    let train =
        json!({"kind": "train", "params": {"dataset": sim, "max_epochs": 2, "ensemble": 1, "mask_groups": true}});
    let (status, j) = json_of(port, "POST", "/jobs", Some(&train));
    assert_eq!(status, 202, "{j}");
    let tid = j["id"].as_str().unwrap().to_string();
    let done = wait_job(port, &tid, 300);
    assert_eq!(done["state"], "succeeded", "{done}");
    let (status, m) = json_of(port, "GET", &format!("/models/{tid}"), None);
    assert_eq!((status, m["error"].is_null()), (200, true), "{m}");
    let mut req = crate::http::nominal_request();
    req["model"] = json!(tid);
    let (status, inferred) = json_of(port, "POST", "/infer", Some(&req));
    assert_eq!(status, 200, "{inferred}");
    assert_eq!(inferred["model"], json!(tid), "{inferred}");
    let cached = b.join(format!("models/{tid}.otofit"));
    assert!(bucket_listing(&moto).contains(&format!("<Key>lab/models/{tid}.otofit</Key>")));
    assert_eq!(
        std::fs::read(&cached).unwrap(),
        std::fs::read(c.join(format!("models/{tid}.otofit"))).unwrap(),
        "the server's cached copy is the worker's model"
    );
    assert_eq!(
        std::fs::read(c.join(format!("datasets/{sim}/x.csv"))).unwrap(),
        x,
        "worker C trained on A's dataset, fetched from the store"
    );

    // A report (resimulate with an observation), served from the store.
    let theta = json!([[2e7, 5e6, 2e6, 2e5, 6e6, 7.5e-5, 2.1e10]]);
    let (_, r) =
        json_of(port, "POST", "/jobs", Some(&json!({"kind": "resimulate", "params": {"theta": theta.clone()}})));
    let obs = wait_job(port, r["id"].as_str().unwrap(), 60)["result"]["x"][0].clone();
    let (_, r) = json_of(
        port,
        "POST",
        "/jobs",
        Some(&json!({"kind": "resimulate", "params": {"theta": theta, "observation": obs}})),
    );
    let rid = r["id"].as_str().unwrap().to_string();
    let done = wait_job(port, &rid, 60);
    assert_eq!(done["state"], "succeeded", "{done}");
    let (status, page) = raw(port, "GET", &format!("/jobs/{rid}/files/report.html"), b"").unwrap();
    assert_eq!(status, 200, "{}", String::from_utf8_lossy(&page));
    assert!(String::from_utf8_lossy(&page).contains("spectra.svg"));
    // The server's data directory: its database lock aside, only the fetched model.
    let mut own = files_under(&b);
    own.retain(|f| !f.starts_with("otofit."));
    assert_eq!(own, [format!("models/{tid}.otofit")], "{own:?}");
    drop(procs);
    let _ = (std::fs::remove_dir_all(&a), std::fs::remove_dir_all(&b), std::fs::remove_dir_all(&c));
}

/// The object store refuses a succeeded job's files (the bucket does not exist): the job
/// fails telling what failed and no path, key or URL of the store; `serve`'s log holds the
/// cause, with the object's key, under the job's id.
#[test]
fn an_object_store_failure_names_no_key_and_its_cause_is_logged() {
    let Some(moto) = start_moto() else { return };
    let (data, logs) = (temp_dir("s3fail"), temp_dir("s3log"));
    let log = logs.join("serve.log");
    let port = free_port();
    let model = crate::http::default_model();
    let serve = otofit(&moto, &["serve", "--data-dir", data.to_str().unwrap(), "--workers", "1", "--log-json"])
        .args(["--addr", &format!("127.0.0.1:{port}"), "--default-model", model.to_str().unwrap()])
        .stdout(std::fs::File::create(&log).unwrap())
        .spawn()
        .unwrap();
    let _procs = Procs(vec![serve]);
    let t0 = Instant::now();
    while raw(port, "GET", "/health", b"").is_none() {
        assert!(t0.elapsed() < Duration::from_secs(30), "serve did not start");
        std::thread::sleep(Duration::from_millis(100));
    }
    let (status, j) = json_of(port, "POST", "/jobs", Some(&json!({"kind": "simulate", "params": {"n": 20}})));
    assert_eq!(status, 202, "{j}");
    let id = j["id"].as_str().unwrap().to_string();
    // The first attempt's error shows while the job waits for its retry (10 s).
    let t0 = Instant::now();
    let job = loop {
        let (_, j) = json_of(port, "GET", &format!("/jobs/{id}"), None);
        if j["error"].is_string() || t0.elapsed() > Duration::from_secs(60) {
            break j;
        }
        std::thread::sleep(Duration::from_millis(100));
    };
    let err = job["error"].as_str().unwrap_or_else(|| panic!("the job fails: {job}"));
    assert_eq!(err, "the job's files could not be stored in the artifact store", "{job}");
    assert!(!err.contains('/') && !err.contains("otofit-test") && !err.contains("127.0.0.1"), "{err}");
    // serve's log (JSON lines): the failure under the job's id, with the store's cause.
    let t0 = Instant::now();
    let line = loop {
        let text = std::fs::read_to_string(&log).unwrap();
        let found = text
            .lines()
            .filter_map(|l| serde_json::from_str::<Value>(l).ok())
            .find(|l| l["fields"]["message"] == "job failed" && l["fields"]["job"] == json!(id));
        if found.is_some() || t0.elapsed() > Duration::from_secs(10) {
            break found.unwrap_or_else(|| panic!("no failure of {id} in the log:\n{text}"));
        }
        std::thread::sleep(Duration::from_millis(100));
    };
    let cause = line["fields"]["cause"].as_str().unwrap_or_default();
    assert_eq!((line["level"].as_str(), line["fields"]["error"].as_str()), (Some("ERROR"), Some(err)), "{line}");
    assert!(cause.contains(&format!("datasets/{id}/")), "the cause names the object's key: {line}");
}
