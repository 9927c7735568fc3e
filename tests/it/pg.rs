//! The job queue on both backends, against a real PostgreSQL: a throwaway cluster
//! (initdb into a temporary directory, a free loopback port, trust auth) started once
//! per test binary from the distribution's binaries (`initdb`, `postgres` on PATH or in
//! /usr/lib/postgresql/*/bin), one fresh database per test. PostgreSQL refuses to run as
//! root, so as root it runs as the `postgres` user. Without the binaries the PostgreSQL
//! tests skip with a loud message, except under CI (`CI` set) or with
//! `OTOFIT_REQUIRE_POSTGRES=1`, where they fail.

use otofit::jobs::{self, Ctx};
use otofit::store::{Database, Store};
use serde_json::json;
use std::path::{Path, PathBuf};
use std::process::{Command, Stdio};
use std::sync::{Arc, OnceLock};
use std::time::{Duration, Instant};

struct Cluster {
    port: u16,
}

fn pg_bin(name: &str) -> Option<PathBuf> {
    let on_path = std::env::var_os("PATH")
        .map(|p| std::env::split_paths(&p).map(|d| d.join(name)).find(|f| f.is_file()))
        .unwrap_or_default();
    on_path.or_else(|| {
        let mut found: Vec<PathBuf> = std::fs::read_dir("/usr/lib/postgresql")
            .into_iter()
            .flatten()
            .flatten()
            .map(|d| d.path().join("bin").join(name))
            .filter(|f| f.is_file())
            .collect();
        found.sort();
        found.pop()
    })
}

/// uid/gid to run PostgreSQL as: `postgres` when we are root, else ourselves.
fn run_as() -> Option<(u32, u32)> {
    // SAFETY: geteuid has no preconditions.
    if unsafe { libc::geteuid() } != 0 {
        return None;
    }
    let passwd = std::fs::read_to_string("/etc/passwd").ok()?;
    let line = passwd.lines().find(|l| l.starts_with("postgres:"))?;
    let f: Vec<&str> = line.split(':').collect();
    Some((f[2].parse().ok()?, f[3].parse().ok()?))
}

fn command(bin: &Path, ids: Option<(u32, u32)>) -> Command {
    use std::os::unix::process::CommandExt;
    let mut c = Command::new(bin);
    if let Some((uid, gid)) = ids {
        c.uid(uid).gid(gid);
    }
    c
}

/// Removes the cluster folders (`otofit-pg-<pid>`) of earlier test binaries that have
/// ended: a cluster lives as long as its binary, so its folder cannot go with a guard.
fn remove_dead_clusters() {
    let Ok(entries) = std::fs::read_dir(std::env::temp_dir()) else { return };
    for e in entries.flatten() {
        let name = e.file_name().to_string_lossy().into_owned();
        let Some(pid) = name.strip_prefix("otofit-pg-").and_then(|p| p.parse::<u32>().ok()) else { continue };
        if pid != std::process::id() && !Path::new(&format!("/proc/{pid}")).exists() {
            let _ = std::fs::remove_dir_all(e.path());
        }
    }
}

fn start_cluster() -> Result<Cluster, String> {
    let (initdb, postgres) = match (pg_bin("initdb"), pg_bin("postgres")) {
        (Some(i), Some(p)) => (i, p),
        _ => return Err("initdb/postgres not found on PATH or in /usr/lib/postgresql/*/bin".into()),
    };
    let ids = run_as();
    if unsafe { libc::geteuid() } == 0 && ids.is_none() {
        return Err("running as root and there is no `postgres` user to run PostgreSQL as".into());
    }
    remove_dead_clusters();
    let dir = std::env::temp_dir().join(format!("otofit-pg-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);
    std::fs::create_dir_all(&dir).map_err(|e| e.to_string())?;
    if let Some((uid, gid)) = ids {
        std::os::unix::fs::chown(&dir, Some(uid), Some(gid)).map_err(|e| e.to_string())?;
    }
    let data = dir.join("data");
    let out = command(&initdb, ids)
        .args(["-D", data.to_str().unwrap(), "-U", "postgres", "--auth=trust", "--no-sync", "-E", "UTF8"])
        .output()
        .map_err(|e| format!("initdb: {e}"))?;
    if !out.status.success() {
        return Err(format!("initdb failed: {}", String::from_utf8_lossy(&out.stderr)));
    }
    let port = std::net::TcpListener::bind("127.0.0.1:0").unwrap().local_addr().unwrap().port();
    // The server is the child of a thread that lives as long as the test binary, and
    // asks the kernel for SIGTERM when that thread (so the binary) ends: no server is
    // left running after the tests, however they end.
    let (tx, rx) = std::sync::mpsc::channel();
    let args: Vec<String> = [
        "-D",
        data.to_str().unwrap(),
        "-p",
        &port.to_string(),
        "-k",
        dir.to_str().unwrap(),
        "-c",
        "listen_addresses=127.0.0.1",
        "-c",
        "fsync=off",
        "-c",
        "max_connections=300",
    ]
    .iter()
    .map(|s| s.to_string())
    .collect();
    std::thread::spawn(move || {
        use std::os::unix::process::CommandExt;
        let mut c = command(&postgres, ids);
        c.args(&args).stdout(Stdio::null()).stderr(Stdio::null());
        // SAFETY: prctl is async-signal-safe; it runs after the uid change (which would
        // clear the setting).
        unsafe {
            c.pre_exec(|| {
                libc::prctl(libc::PR_SET_PDEATHSIG, libc::SIGTERM);
                Ok(())
            });
        }
        let child = c.spawn();
        let _ = tx.send(child.as_ref().map(|_| ()).map_err(|e| e.to_string()));
        if let Ok(mut child) = child {
            let _ = child.wait();
        }
        loop {
            std::thread::park();
        }
    });
    rx.recv().map_err(|e| e.to_string())?.map_err(|e| format!("postgres: {e}"))?;
    let t0 = Instant::now();
    while std::net::TcpStream::connect(("127.0.0.1", port)).is_err() {
        if t0.elapsed() > Duration::from_secs(30) {
            return Err(format!("postgres did not listen on 127.0.0.1:{port} within 30 s"));
        }
        std::thread::sleep(Duration::from_millis(100));
    }
    Ok(Cluster { port })
}

fn cluster() -> Option<&'static Cluster> {
    static CLUSTER: OnceLock<Result<Cluster, String>> = OnceLock::new();
    match CLUSTER.get_or_init(start_cluster) {
        Ok(c) => Some(c),
        Err(e) => {
            let required = std::env::var_os("CI").is_some() || std::env::var_os("OTOFIT_REQUIRE_POSTGRES").is_some();
            assert!(!required, "PostgreSQL is required here (CI or OTOFIT_REQUIRE_POSTGRES) but: {e}");
            eprintln!("\n!!!!! SKIPPING a PostgreSQL test: {e} (install postgresql; .ci/run does) !!!!!\n");
            None
        }
    }
}

/// A fresh database on the throwaway cluster: its URL.
pub(crate) async fn fresh_database() -> Option<String> {
    use sqlx::Connection;
    let c = cluster()?;
    static N: std::sync::atomic::AtomicUsize = std::sync::atomic::AtomicUsize::new(0);
    let name = format!("t{}_{}", std::process::id(), N.fetch_add(1, std::sync::atomic::Ordering::SeqCst));
    let admin = format!("postgres://postgres@127.0.0.1:{}/postgres", c.port);
    // A server that listens may still be starting up ("the database system is starting
    // up"): connections are retried for a while before that counts as a failure.
    let t0 = Instant::now();
    let mut conn = loop {
        match sqlx::PgConnection::connect(&admin).await {
            Ok(conn) => break conn,
            Err(_) if t0.elapsed() < Duration::from_secs(30) => {
                tokio::time::sleep(Duration::from_millis(100)).await;
            }
            Err(e) => panic!("connect to the test cluster: {e}"),
        }
    };
    sqlx::query(sqlx::AssertSqlSafe(format!("CREATE DATABASE {name}"))).execute(&mut conn).await.unwrap();
    Some(format!("postgres://postgres@127.0.0.1:{}/{name}", c.port))
}

/// A fresh folder `otofit-<tag>-…` under the system temp dir, removed with everything in it
/// when the guard is dropped (use it as a `&Path` through `Deref`).
pub(crate) struct TempDir(tempfile::TempDir);

impl std::ops::Deref for TempDir {
    type Target = Path;
    fn deref(&self) -> &Path {
        self.0.path()
    }
}

impl AsRef<Path> for TempDir {
    fn as_ref(&self) -> &Path {
        self.0.path()
    }
}

pub(crate) fn temp_dir(tag: &str) -> TempDir {
    TempDir(tempfile::Builder::new().prefix(&format!("otofit-{tag}-")).tempdir().unwrap())
}

/// The stores of [`backends`], iterated while the SQLite file's folder is kept.
pub(crate) struct Backends {
    list: std::vec::IntoIter<(String, Database)>,
    _dir: TempDir,
}

impl Iterator for Backends {
    type Item = (String, Database);
    fn next(&mut self) -> Option<Self::Item> {
        self.list.next()
    }
}

/// A store on each backend: SQLite in a temporary file and, when available, PostgreSQL.
pub(crate) async fn backends() -> Backends {
    let dir = temp_dir("sq");
    let mut v = vec![("sqlite".to_string(), Database::Sqlite(dir.join("otofit.db")))];
    if let Some(url) = fresh_database().await {
        v.push(("postgres".into(), Database::Postgres(url)));
    }
    Backends { list: v.into_iter(), _dir: dir }
}

const LEASE: Duration = Duration::from_secs(30);

/// A claim is exclusive: of many concurrent claimers of one job exactly one gets it.
#[tokio::test(flavor = "multi_thread", worker_threads = 4)]
async fn one_job_is_claimed_by_exactly_one_of_many_claimers() {
    for (name, db) in backends().await {
        let stores: Vec<Store> = {
            let mut v = vec![];
            for _ in 0..8 {
                v.push(Store::connect(&db).await.unwrap());
            }
            v
        };
        for round in 0..5 {
            let id = format!("j{round}");
            assert!(stores[0].insert_job_within(&id, "simulate", &json!({"n": 5}), 3, 100).await.unwrap());
            let claims: Vec<_> = stores
                .iter()
                .enumerate()
                .map(|(k, s)| {
                    let s = s.clone();
                    tokio::spawn(async move { s.claim(&format!("w{k}"), LEASE).await.unwrap() })
                })
                .collect();
            let mut got = vec![];
            for c in claims {
                got.extend(c.await.unwrap());
            }
            assert_eq!(got.len(), 1, "{name} round {round}: {} claimers got the job", got.len());
            assert_eq!(got[0].attempts, 1, "{name}");
        }
    }
}

/// A worker that stops renewing its lease (killed, stalled) loses the job: after the
/// lease another worker takes it back, and the first one's writes are all refused.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn an_expired_lease_is_taken_back_and_the_stale_worker_is_fenced_out() {
    for (name, db) in backends().await {
        let (a, b) = (Store::connect(&db).await.unwrap(), Store::connect(&db).await.unwrap());
        assert!(a.insert_job_within("j", "simulate", &json!({"n": 5}), 3, 8).await.unwrap());
        let short = Duration::from_millis(1000);
        let first = a.claim("a", short).await.unwrap().unwrap();
        let t1 = first.lease_token.clone().unwrap();
        // Within its lease the job is A's: nothing to take back, nothing to claim.
        assert_eq!(b.reap_expired().await.unwrap(), (0, 0), "{name}");
        assert!(b.claim("b", LEASE).await.unwrap().is_none(), "{name}");
        // A renews once, then goes silent.
        assert!(a.heartbeat("j", &t1, short).await.unwrap(), "{name}");
        tokio::time::sleep(Duration::from_millis(1300)).await;
        assert_eq!(b.reap_expired().await.unwrap(), (1, 0), "{name}: the expired job goes back to the queue");
        let second = b.claim("b", LEASE).await.unwrap().expect("B re-claims the job");
        let t2 = second.lease_token.clone().unwrap();
        assert_eq!((second.attempts, second.worker.as_deref()), (2, Some("b")), "{name}");
        // A wakes up: its renewal, progress, result and re-queue are all refused.
        assert!(!a.heartbeat("j", &t1, short).await.unwrap(), "{name}");
        a.progress("j", &t1, 0.9, "stale").await.unwrap();
        assert!(
            !a.finish("j", &t1, otofit::store::JobState::Succeeded, None, Some(&json!({"stale": true}))).await.unwrap(),
            "{name}"
        );
        assert!(!a.requeue("j", &t1).await.unwrap(), "{name}");
        let j = b.job("j").await.unwrap().unwrap();
        assert_eq!((j.state.as_str(), j.progress, j.result), ("running", 0.0, None), "{name}");
        assert!(
            b.finish("j", &t2, otofit::store::JobState::Succeeded, None, Some(&json!({"rows": 5}))).await.unwrap(),
            "{name}"
        );
        assert_eq!(b.job("j").await.unwrap().unwrap().state, "succeeded", "{name}");
        // On its last attempt an expired job fails instead of coming back forever.
        assert!(a.insert_job_within("k", "simulate", &json!({"n": 5}), 1, 8).await.unwrap());
        a.claim("a", short).await.unwrap().unwrap();
        tokio::time::sleep(Duration::from_millis(1300)).await;
        assert_eq!(b.reap_expired().await.unwrap(), (0, 1), "{name}");
        let k = b.job("k").await.unwrap().unwrap();
        assert_eq!(k.state, "failed", "{name}");
        assert!(k.error.unwrap().contains("lease"), "{name}");
    }
}

/// For any number of servers: concurrent posts never exceed the queue limit
/// (on PostgreSQL the count and the insert run under an advisory lock).
#[tokio::test(flavor = "multi_thread", worker_threads = 4)]
async fn concurrent_inserts_from_many_servers_never_exceed_the_queue_limit() {
    for (name, db) in backends().await {
        let mut stores = vec![];
        for _ in 0..4 {
            stores.push(Store::connect(&db).await.unwrap());
        }
        for k in 0..7 {
            assert!(stores[0].insert_job_within(&format!("pre{k}"), "simulate", &json!({"n": 1}), 3, 8).await.unwrap());
        }
        let posts: Vec<_> = (0..40)
            .map(|k| {
                let s = stores[k % stores.len()].clone();
                tokio::spawn(
                    async move { s.insert_job_within(&format!("p{k}"), "simulate", &json!({"n": 1}), 3, 8).await },
                )
            })
            .collect();
        let mut accepted = 0;
        for p in posts {
            accepted += usize::from(p.await.unwrap().unwrap());
        }
        let active: i64 = stores[0].queue_counts(None).await.unwrap().iter().map(|c| c.count).sum();
        assert_eq!((accepted, active), (1, 8), "{name}: limit 8 with 7 active");
    }
}

pub(crate) fn ctx_on(store: Store, data: &Path, worker: &str, lease: Duration) -> Arc<Ctx> {
    let mut ctx = Ctx::new(store, data.to_path_buf(), 64).with_lease(lease);
    ctx.worker = worker.to_string();
    Arc::new(ctx)
}

pub(crate) async fn wait_state(store: &Store, id: &str, states: &[&str], secs: u64) -> otofit::store::JobRow {
    let t0 = Instant::now();
    loop {
        let j = store.job(id).await.unwrap().unwrap();
        if states.contains(&j.state.as_str()) || t0.elapsed() > Duration::from_secs(secs) {
            return j;
        }
        tokio::time::sleep(Duration::from_millis(50)).await;
    }
}

/// Several dispatchers (one per simulated worker process) on one PostgreSQL job table:
/// every job runs exactly once (one attempt each), and the work is spread.
#[tokio::test(flavor = "multi_thread", worker_threads = 4)]
async fn three_workers_share_the_jobs_and_run_each_exactly_once() {
    let Some(url) = fresh_database().await else { return };
    let db = Database::Postgres(url);
    let data = temp_dir("pgw");
    let server = Store::connect(&db).await.unwrap();
    let ids: Vec<String> = (0..12).map(|k| format!("sim{k:02}")).collect();
    for id in &ids {
        assert!(server.insert_job_within(id, "simulate", &json!({"n": 200, "seed": 1}), 3, 64).await.unwrap());
    }
    let mut ctxs = vec![];
    for w in 0..3 {
        let ctx = ctx_on(Store::connect(&db).await.unwrap(), &data, &format!("w{w}"), LEASE);
        tokio::spawn(jobs::dispatcher(ctx.clone()));
        ctxs.push(ctx);
    }
    let mut by_worker = std::collections::BTreeMap::new();
    for id in &ids {
        let j = wait_state(&server, id, &["succeeded", "failed", "cancelled"], 120).await;
        assert_eq!((j.state.as_str(), j.attempts), ("succeeded", 1), "{id}: {:?}", j.error);
        *by_worker.entry(j.worker.unwrap()).or_insert(0) += 1;
        let x = std::fs::read_to_string(data.join("datasets").join(id).join("x.csv")).unwrap();
        assert_eq!(x.lines().count(), 201, "{id}");
    }
    for c in &ctxs {
        c.shutdown.store(true, std::sync::atomic::Ordering::Relaxed);
    }
    assert!(by_worker.len() >= 2, "the jobs were spread over the workers: {by_worker:?}");
}

/// A running worker whose lease is taken from it (it stalled past its lease, and another
/// worker took the job) stops and writes nothing; the job completes once, by the other.
#[tokio::test(flavor = "multi_thread", worker_threads = 4)]
async fn a_worker_that_lost_its_lease_stops_and_writes_nothing() {
    let Some(url) = fresh_database().await else { return };
    let db = Database::Postgres(url);
    let data = temp_dir("pgl");
    let server = Store::connect(&db).await.unwrap();
    assert!(server.insert_job_within("big", "simulate", &json!({"n": 30000, "seed": 3}), 3, 64).await.unwrap());
    let a = ctx_on(Store::connect(&db).await.unwrap(), &data, "a", Duration::from_secs(3));
    tokio::spawn(jobs::dispatcher(a.clone()));
    let j = wait_state(&server, "big", &["running"], 30).await;
    assert_eq!(j.worker.as_deref(), Some("a"));
    // A is writing a chunk into a part file under a name of its own (`*.<its tag>.tmp`).
    let parts = data.join("datasets").join("big").join("parts");
    let a_files = || -> Vec<String> {
        let names = std::fs::read_dir(&parts).into_iter().flatten().flatten();
        names.map(|e| e.file_name().to_string_lossy().into_owned()).filter(|n| n.ends_with(".tmp")).collect()
    };
    let t0 = Instant::now();
    while a_files().is_empty() && t0.elapsed() < Duration::from_secs(30) {
        tokio::time::sleep(Duration::from_millis(20)).await;
    }
    let a_tmp = a_files();
    assert!(!a_tmp.is_empty(), "A writes a part into {}", parts.display());
    // A stall, as seen from the database: A's lease ran out and a reaper took the job
    // back (what `Store::reap_expired` does, here at once so that A cannot renew first).
    let pool = match &server.pool {
        otofit::store::Pool::Postgres(p) => p.clone(),
        _ => unreachable!(),
    };
    sqlx::query("UPDATE jobs SET state = 'queued', lease_token = NULL WHERE id = 'big'").execute(&pool).await.unwrap();
    let b = ctx_on(Store::connect(&db).await.unwrap(), &data, "b", Duration::from_secs(3));
    tokio::spawn(jobs::dispatcher(b.clone()));
    let t0 = Instant::now();
    while server.job("big").await.unwrap().unwrap().attempts < 2 && t0.elapsed() < Duration::from_secs(30) {
        tokio::time::sleep(Duration::from_millis(20)).await;
    }
    // A notices at its next renewal (a third of its lease), stops within 1,024 rows and
    // removes its temporary files, while B is still at work.
    let t0 = Instant::now();
    while a_files().iter().any(|f| a_tmp.contains(f)) && t0.elapsed() < Duration::from_secs(4) {
        tokio::time::sleep(Duration::from_millis(50)).await;
    }
    assert!(!a_files().iter().any(|f| a_tmp.contains(f)), "A still at work {:?} after losing its lease", t0.elapsed());
    let now = server.job("big").await.unwrap().unwrap();
    assert_eq!((now.state.as_str(), now.worker.as_deref()), ("running", Some("b")), "B is still at work");
    let done = wait_state(&server, "big", &["succeeded", "failed", "cancelled"], 120).await;
    assert_eq!((done.state.as_str(), done.attempts, done.worker.as_deref()), ("succeeded", 2, Some("b")), "{done:?}");
    let x = std::fs::read_to_string(data.join("datasets").join("big").join("x.csv")).unwrap();
    assert_eq!(x.lines().count(), 30_001, "one complete dataset, not a mix of two attempts");
    // A stopped; nothing but the dataset is left (no staging folder, parts or *.tmp).
    tokio::time::sleep(Duration::from_secs(2)).await;
    let mut left: Vec<_> = std::fs::read_dir(data.join("datasets").join("big"))
        .unwrap()
        .flatten()
        .map(|e| e.file_name().to_string_lossy().into_owned())
        .collect();
    left.sort();
    assert_eq!(left, ["meta.json", "theta.csv", "x.csv"]);
    a.shutdown.store(true, std::sync::atomic::Ordering::Relaxed);
    b.shutdown.store(true, std::sync::atomic::Ordering::Relaxed);
}

fn spawn_worker(url: &str, data: &Path, lease: &str) -> std::process::Child {
    Command::new(env!("CARGO_BIN_EXE_otofit"))
        .args(["worker", "--database", url, "--data-dir", data.to_str().unwrap(), "--lease-seconds", lease])
        .args(["--threads", "1"])
        .stdout(Stdio::null())
        .stderr(Stdio::null())
        .spawn()
        .unwrap()
}

/// `otofit worker` processes: one is killed with SIGKILL mid-job; after its lease
/// expires another worker re-claims the job and completes it.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_killed_worker_process_loses_its_job_to_another_after_the_lease() {
    let Some(url) = fresh_database().await else { return };
    let db = Database::Postgres(url.clone());
    let data = temp_dir("pgk");
    let server = Store::connect(&db).await.unwrap();
    assert!(server.insert_job_within("k", "simulate", &json!({"n": 30000, "seed": 4}), 3, 64).await.unwrap());
    let mut procs = Procs(vec![spawn_worker(&url, &data, "2")]);
    let j = wait_state(&server, "k", &["running"], 60).await;
    assert_eq!(j.state, "running", "the first worker claimed the job");
    tokio::time::sleep(Duration::from_millis(500)).await;
    procs.0[0].kill().unwrap(); // SIGKILL: no chance to re-queue
    procs.0[0].wait().unwrap();
    let t_kill = Instant::now();
    // The lease the dead worker left behind, against the database clock now.
    let pool = match &server.pool {
        otofit::store::Pool::Postgres(p) => p.clone(),
        _ => unreachable!(),
    };
    let now_ms: i64 = sqlx::query_scalar("SELECT CAST(EXTRACT(EPOCH FROM clock_timestamp()) * 1000 AS BIGINT)")
        .fetch_one(&pool)
        .await
        .unwrap();
    let left_ms = server.lease_expires_ms("k").await.unwrap().unwrap() - now_ms;
    assert!(left_ms > 0, "the lease was still running at the kill ({left_ms} ms)");
    procs.0.push(spawn_worker(&url, &data, "2"));
    let t0 = Instant::now();
    while server.job("k").await.unwrap().unwrap().attempts < 2 && t0.elapsed() < Duration::from_secs(60) {
        tokio::time::sleep(Duration::from_millis(20)).await;
    }
    let reclaimed_after = t_kill.elapsed();
    let done = wait_state(&server, "k", &["succeeded", "failed", "cancelled"], 180).await;
    drop(procs);
    assert_eq!((done.state.as_str(), done.attempts), ("succeeded", 2), "{done:?}");
    assert!(
        reclaimed_after >= Duration::from_millis(left_ms as u64),
        "re-claimed {reclaimed_after:?} after the kill, before the lease expired ({left_ms} ms left)"
    );
    assert_ne!(done.worker, j.worker, "the second worker finished it");
    let x = std::fs::read_to_string(data.join("datasets").join("k").join("x.csv")).unwrap();
    assert_eq!(x.lines().count(), 30_001);
}

/// Child processes killed when the test ends, also when it fails half-way.
pub(crate) struct Procs(pub Vec<std::process::Child>);

impl Drop for Procs {
    fn drop(&mut self) {
        for p in &mut self.0 {
            let _ = p.kill();
            let _ = p.wait();
        }
    }
}

fn free_port() -> u16 {
    std::net::TcpListener::bind("127.0.0.1:0").unwrap().local_addr().unwrap().port()
}

/// An HTTP-only `serve` (`--workers 0`) on `url`; waits until it answers /health.
fn spawn_serve(url: &str, data: &Path, port: u16) -> std::process::Child {
    let model = crate::http::default_model();
    let child = Command::new(env!("CARGO_BIN_EXE_otofit"))
        .args(["serve", "--database", url, "--data-dir", data.to_str().unwrap(), "--workers", "0"])
        .args(["--addr", &format!("127.0.0.1:{port}"), "--default-model", model.to_str().unwrap()])
        .stdout(Stdio::null())
        .stderr(Stdio::null())
        .spawn()
        .unwrap();
    let t0 = Instant::now();
    while crate::http::http(port, "GET", "/health", None).is_none() && t0.elapsed() < Duration::from_secs(30) {
        std::thread::sleep(Duration::from_millis(100));
    }
    child
}

/// Two `serve` processes on one PostgreSQL and one data directory (no lock between them):
/// both answer /infer, a job posted to one is seen through the other, a worker process
/// runs it, and its dataset is served by either.
#[test]
fn two_servers_share_one_job_table_and_both_answer_infer() {
    let rt = tokio::runtime::Runtime::new().unwrap();
    let Some(url) = rt.block_on(fresh_database()) else { return };
    let data = temp_dir("pg2s");
    let (a, b) = (free_port(), free_port());
    let mut procs = Procs(vec![spawn_serve(&url, &data, a), spawn_serve(&url, &data, b)]);
    let infer = crate::http::nominal_request().to_string();
    let req = |port, method, path: &str, body: Option<&str>| crate::http::http(port, method, path, body).unwrap();
    for port in [a, b] {
        let (status, body) = req(port, "POST", "/infer", Some(&infer));
        assert_eq!(status, 200, "server on {port}: {body}");
    }
    let (status, job) = req(a, "POST", "/jobs", Some(r#"{"kind":"simulate","params":{"n":50,"seed":5}}"#));
    assert_eq!(status, 202, "{job}");
    let id = job["id"].as_str().unwrap().to_string();
    let (status, seen) = req(b, "GET", &format!("/jobs/{id}"), None);
    assert_eq!((status, seen["state"].as_str()), (200, Some("queued")), "no dispatcher runs it yet: {seen}");
    let metrics_port = free_port();
    let mut worker = Command::new(env!("CARGO_BIN_EXE_otofit"));
    worker.args(["worker", "--database", &url, "--data-dir", data.to_str().unwrap()]);
    worker.args(["--metrics-addr", &format!("127.0.0.1:{metrics_port}")]);
    procs.0.push(worker.stdout(Stdio::null()).stderr(Stdio::null()).spawn().unwrap());
    let t0 = Instant::now();
    let mut last = serde_json::Value::Null;
    while t0.elapsed() < Duration::from_secs(60) {
        last = req(b, "GET", &format!("/jobs/{id}"), None).1;
        if last["state"] != "queued" && last["state"] != "running" {
            break;
        }
        std::thread::sleep(Duration::from_millis(100));
    }
    let (status, ds) = req(a, "GET", &format!("/datasets/{id}"), None);
    // The worker's own /metrics: its claim and its rows (the servers ran no job).
    let worker_metrics = metrics_text(metrics_port);
    let server_metrics = metrics_text(a);
    drop(procs);
    assert_eq!(last["state"], "succeeded", "{last}");
    assert_eq!((status, ds["rows"].as_u64()), (200, Some(50)), "{ds}");
    for line in ["otofit_job_claims_total 1", "otofit_simulated_rows_total 50"] {
        assert!(worker_metrics.lines().any(|l| l == line), "worker: no '{line}' in\n{worker_metrics}");
    }
    assert!(server_metrics.lines().any(|l| l == "otofit_jobs{kind=\"simulate\",state=\"succeeded\"} 1"));
    assert!(server_metrics.lines().any(|l| l == "otofit_simulated_rows_total 0"), "{server_metrics}");
}

/// The body of GET /metrics on `port` (plain text).
fn metrics_text(port: u16) -> String {
    use std::io::{Read, Write};
    let mut s = std::net::TcpStream::connect(("127.0.0.1", port)).unwrap();
    s.write_all(b"GET /metrics HTTP/1.1\r\nHost: localhost\r\nConnection: close\r\n\r\n").unwrap();
    let mut out = String::new();
    s.read_to_string(&mut out).unwrap();
    assert!(out.starts_with("HTTP/1.1 200"), "{out}");
    out.split("\r\n\r\n").nth(1).unwrap_or("").to_string()
}

/// The scale-out flags are checked before anything starts, each error naming its flag.
#[test]
fn scale_out_flags_are_validated_naming_the_flag() {
    let cases: [(&[&str], &str); 9] = [
        (&["worker", "--chunk-rows", "99"], "--chunk-rows"),
        (&["serve", "--retry-backoff-seconds=-1"], "--retry-backoff-seconds"),
        (
            &["worker", "--retry-backoff-seconds", "20", "--retry-backoff-max-seconds", "10"],
            "--retry-backoff-max-seconds",
        ),
        (&["worker", "--database", "mysql://db/otofit"], "--database"),
        (&["worker", "--lease-seconds", "0"], "--lease-seconds"),
        (&["worker", "--concurrency", "0"], "--concurrency"),
        (&["worker", "--threads", "0"], "--threads"),
        (&["serve", "--workers", "65"], "--workers"),
        (&["serve", "--database", "sqlite://"], "--database"),
    ];
    for (args, flag) in cases {
        let out = Command::new(env!("CARGO_BIN_EXE_otofit")).args(args).output().unwrap();
        let err = String::from_utf8_lossy(&out.stderr);
        assert!(!out.status.success() && err.contains(flag), "{args:?}: {err}");
    }
}

/// A PostgreSQL database migrated before the chunks migration's comment was reworded
/// (its first released checksum put back) still opens, with the new checksum stored.
#[tokio::test]
async fn a_postgres_database_migrated_with_the_old_wording_still_opens() {
    let Some(url) = fresh_database().await else { return };
    let old: Vec<u8> = (0..48)
        .map(|i| {
            let hex =
                "00697cc548db7905e80717a0a46c9276848e34266ed456173b7d5081cd31548ccd9521d86ee6a9b305387fa31245eb79";
            u8::from_str_radix(&hex[2 * i..2 * i + 2], 16).unwrap()
        })
        .collect();
    let checksum = |pool: &sqlx::PgPool| {
        let pool = pool.clone();
        async move {
            let (sum,): (Vec<u8>,) = sqlx::query_as("SELECT checksum FROM _sqlx_migrations WHERE version = 3")
                .fetch_one(&pool)
                .await
                .unwrap();
            sum
        }
    };
    let store = Store::connect(&Database::Postgres(url.clone())).await.unwrap();
    let otofit::store::Pool::Postgres(pool) = &store.pool else { unreachable!() };
    let new = checksum(pool).await;
    sqlx::query("UPDATE _sqlx_migrations SET checksum = $1 WHERE version = 3").bind(&old).execute(pool).await.unwrap();
    pool.close().await;
    let store = Store::connect(&Database::Postgres(url)).await.expect("the old wording's database opens");
    let otofit::store::Pool::Postgres(pool) = &store.pool else { unreachable!() };
    assert_eq!(checksum(pool).await, new);
    assert_ne!(old, new);
}

/// One column as both databases describe it: name, type (SQLite's name for it), NOT NULL,
/// and the default without PostgreSQL's casts.
type Column = (String, String, bool, Option<String>);

async fn sqlite_schema(pool: &sqlx::SqlitePool) -> (Vec<(String, Vec<Column>)>, Vec<String>) {
    let tables: Vec<(String,)> = sqlx::query_as(
        "SELECT name FROM sqlite_master WHERE type = 'table' \
         AND name NOT LIKE 'sqlite_%' AND name NOT LIKE '_sqlx%' ORDER BY name",
    )
    .fetch_all(pool)
    .await
    .unwrap();
    let mut schema = Vec::new();
    for (table,) in tables {
        let rows: Vec<(i64, String, String, i64, Option<String>, i64)> =
            sqlx::query_as(sqlx::AssertSqlSafe(format!("PRAGMA table_info({table})"))).fetch_all(pool).await.unwrap();
        // SQLite lets a TEXT primary key hold NULL (a legacy quirk); the code never writes one.
        let columns = rows.into_iter().map(|(_, name, ty, notnull, dflt, pk)| (name, ty, notnull == 1 || pk > 0, dflt));
        schema.push((table, columns.collect()));
    }
    let indexes: Vec<(String,)> =
        sqlx::query_as("SELECT name FROM sqlite_master WHERE type = 'index' AND sql IS NOT NULL ORDER BY name")
            .fetch_all(pool)
            .await
            .unwrap();
    (schema, indexes.into_iter().map(|(n,)| n).collect())
}

async fn postgres_schema(pool: &sqlx::PgPool) -> (Vec<(String, Vec<Column>)>, Vec<String>) {
    let rows: Vec<(String, String, String, String, Option<String>)> = sqlx::query_as(
        "SELECT table_name::text, column_name::text, data_type::text, is_nullable::text, column_default::text \
         FROM information_schema.columns WHERE table_schema = 'public' AND table_name NOT LIKE '_sqlx%' \
         ORDER BY table_name, ordinal_position",
    )
    .fetch_all(pool)
    .await
    .unwrap();
    let mut schema: Vec<(String, Vec<Column>)> = Vec::new();
    for (table, name, ty, nullable, dflt) in rows {
        let ty = match ty.as_str() {
            "text" => "TEXT",
            "bigint" => "INTEGER",
            "double precision" => "REAL",
            other => panic!("{table}.{name}: no SQLite type for PostgreSQL's {other}"),
        };
        let dflt = dflt.map(|d| d.split("::").next().unwrap().to_string());
        let column = (name, ty.to_string(), nullable == "NO", dflt);
        match schema.last_mut() {
            Some((t, columns)) if *t == table => columns.push(column),
            _ => schema.push((table, vec![column])),
        }
    }
    // Constraint indexes (primary keys, UNIQUE) are made by the tables themselves.
    let indexes: Vec<(String,)> = sqlx::query_as(
        "SELECT indexname::text FROM pg_indexes WHERE schemaname = 'public' \
         AND indexname NOT LIKE '%_pkey' AND indexname NOT LIKE '%_key' ORDER BY indexname",
    )
    .fetch_all(pool)
    .await
    .unwrap();
    (schema, indexes.into_iter().map(|(n,)| n).collect())
}

/// The two migration trees (migrations/ for SQLite, migrations/postgres/ for PostgreSQL,
/// each numbered by its own history) end in the same schema: the same tables, columns in
/// the same order with the same types, NOT NULL and defaults, and the same indexes. The
/// one difference allowed is PostgreSQL's CHECK on jobs.state, which SQLite cannot add
/// to an existing table (the code writes the state only through `JobState`).
#[tokio::test]
async fn both_migration_trees_end_in_the_same_schema() {
    let Some(url) = fresh_database().await else { return };
    let dir = temp_dir("schema");
    let sqlite = Store::connect(&Database::Sqlite(dir.join("otofit.db"))).await.unwrap();
    let postgres = Store::connect(&Database::Postgres(url)).await.unwrap();
    let otofit::store::Pool::Postgres(pg) = &postgres.pool else { unreachable!() };
    let (lite_tables, lite_indexes) = sqlite_schema(sqlite.sqlite().unwrap()).await;
    let (pg_tables, pg_indexes) = postgres_schema(pg).await;
    let names = |s: &[(String, Vec<Column>)]| s.iter().map(|(t, _)| t.clone()).collect::<Vec<_>>();
    assert_eq!(names(&lite_tables), names(&pg_tables), "tables");
    for ((table, lite), (_, pg)) in lite_tables.iter().zip(&pg_tables) {
        assert_eq!(lite, pg, "columns of {table} (SQLite left, PostgreSQL right)");
    }
    assert_eq!(lite_indexes, pg_indexes, "indexes");
}

/// A job queued through one store, or chunks planned, wakes the listening dispatchers of
/// another process at once (PostgreSQL NOTIFY), instead of at their next poll.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn queued_work_wakes_the_listeners_of_other_processes() {
    let Some(url) = fresh_database().await else { return };
    let here = Store::connect(&Database::Postgres(url.clone())).await.unwrap();
    let there = Store::connect(&Database::Postgres(url)).await.unwrap();
    let (tx, mut rx) = tokio::sync::mpsc::unbounded_channel();
    let listener = tokio::spawn(async move { there.listen_for_work(move || tx.send(()).unwrap()).await });
    // The listener is up once an announcement gets through.
    let t0 = Instant::now();
    while !matches!(rx.try_recv(), Ok(())) {
        assert!(t0.elapsed() < Duration::from_secs(10), "no announcement got through");
        here.announce_work().await.unwrap();
        tokio::time::sleep(Duration::from_millis(50)).await;
    }
    tokio::time::sleep(Duration::from_millis(200)).await;
    while rx.try_recv().is_ok() {}
    assert!(here.insert_job_within("j1", "simulate", &json!({"n": 10}), 3, 100).await.unwrap());
    let wait = Duration::from_secs(10);
    assert!(tokio::time::timeout(wait, rx.recv()).await.is_ok(), "a queued job woke nobody");
    here.plan_chunks("j1", &[(0, 5), (5, 5)]).await.unwrap();
    assert!(tokio::time::timeout(wait, rx.recv()).await.is_ok(), "planned chunks woke nobody");
    listener.abort();
}
