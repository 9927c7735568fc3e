//! Where artifacts live: the files jobs leave behind (datasets, trained models, reports),
//! named by keys relative to a root — `datasets/<id>/x.csv`, `models/<id>.otofit`,
//! `reports/<id>/report.html` — the same layout as the data directory.
//!
//! Two backends behind one interface:
//! - **local** (the default, no configuration): the data directory *is* the store; a
//!   job's files are already in place when it ends, and reading a key reads the file.
//! - **object storage** (`--artifacts s3://BUCKET/PREFIX`, Apache Arrow's `object_store`;
//!   credentials, region and endpoint from the standard `AWS_*` variables): a worker
//!   uploads a job's files under `PREFIX/<key>` when the job succeeds (the data directory
//!   is its scratch space); any process fetches a key into its own data directory on
//!   first use (`fetch`: the local copy is the cache, keyed by the job id in its name), so
//!   a server on another machine loads a model that a worker trained elsewhere.
//!
//! The object store's requests run on a small runtime of their own, so that the same
//! calls work from async handlers, from blocking job threads and from tests.

use object_store::path::Path as ObjectPath;
use object_store::{ObjectStore, ObjectStoreExt};
use std::path::{Path, PathBuf};
use std::sync::Arc;

/// Why an artifact could not be stored or read.
#[derive(Debug, thiserror::Error)]
pub enum ArtifactError {
    /// `--artifacts` names no store this build can use.
    #[error("--artifacts: {0}")]
    Config(String),
    /// A key that is not a plain relative name (`..`, absolute, empty parts).
    #[error("'{0}' is not an artifact key")]
    BadKey(String),
    /// No such artifact (neither local nor in the store).
    #[error("artifact '{0}' not found")]
    NotFound(String),
    /// A model row names a store other than this process's (`--artifacts` differs).
    #[error("'{0}' is not in this process's artifact store ({1})")]
    ForeignUrl(String, String),
    /// The object store failed on `key`.
    #[error("{key}: {source}")]
    Store {
        /// The artifact's key.
        key: String,
        /// The store's error.
        source: object_store::Error,
    },
    /// Reading or writing the local copy at `path` failed.
    #[error("{path}: {source}")]
    Io {
        /// The local file.
        path: PathBuf,
        /// The I/O error.
        source: std::io::Error,
    },
    /// The object store's own runtime is gone (the process is shutting down).
    #[error("the artifact store's runtime stopped")]
    Runtime,
}

type Result<T> = std::result::Result<T, ArtifactError>;

fn io(path: &Path) -> impl FnOnce(std::io::Error) -> ArtifactError + '_ {
    move |source| ArtifactError::Io { path: path.to_path_buf(), source }
}

/// The artifact store of a process: its data directory, and an object store if one is
/// configured.
pub struct Artifacts {
    data_dir: PathBuf,
    remote: Option<Remote>,
}

struct Remote {
    store: Arc<dyn ObjectStore>,
    /// `PREFIX` without slashes at either end (may be empty).
    prefix: String,
    /// `s3://BUCKET[/PREFIX]`, as shown in logs and written into model rows.
    url: String,
    /// Runs the store's requests; shut down in the background when dropped.
    rt: Option<tokio::runtime::Runtime>,
}

impl Drop for Remote {
    fn drop(&mut self) {
        if let Some(rt) = self.rt.take() {
            rt.shutdown_background();
        }
    }
}

impl std::fmt::Debug for Artifacts {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "Artifacts({})", self.describe())
    }
}

/// A key is relative, made of plain names (ids, file names): never `..`, `.` or empty.
fn check_key(key: &str) -> Result<()> {
    let plain = |p: &str| !p.is_empty() && p != "." && p != ".." && !p.contains('\\') && !p.contains('\0');
    if key.split('/').all(plain) { Ok(()) } else { Err(ArtifactError::BadKey(key.to_string())) }
}

/// The key of a job's model file.
pub fn model_key(id: &str) -> String {
    format!("models/{id}.otofit")
}

/// The key of one file of a job's dataset.
pub fn dataset_key(id: &str, file: &str) -> String {
    format!("datasets/{id}/{file}")
}

/// The key of one file of a job's report.
pub fn report_key(id: &str, file: &str) -> String {
    format!("reports/{id}/{file}")
}

impl Artifacts {
    /// The default: artifacts are the files in `data_dir`.
    pub fn local(data_dir: &Path) -> Artifacts {
        Artifacts { data_dir: data_dir.to_path_buf(), remote: None }
    }

    /// From `--artifacts`: `None` (or `local`) for the data directory, `s3://BUCKET[/PREFIX]`
    /// for S3-compatible storage configured by the `AWS_*` variables (`AWS_ENDPOINT` and
    /// `AWS_ALLOW_HTTP=true` for a local server).
    pub fn open(spec: Option<&str>, data_dir: &Path) -> Result<Artifacts> {
        let spec = spec.map(str::trim).filter(|s| !s.is_empty() && *s != "local");
        let Some(url) = spec else { return Ok(Artifacts::local(data_dir)) };
        let Some(rest) = url.strip_prefix("s3://") else {
            let scheme = url.split_once("://").map_or(url, |(s, _)| s);
            return Err(ArtifactError::Config(format!(
                "unsupported store '{scheme}' (give s3://BUCKET/PREFIX, or nothing for the data directory)"
            )));
        };
        let (bucket, prefix) = rest.split_once('/').unwrap_or((rest, ""));
        let prefix = prefix.trim_matches('/').to_string();
        if bucket.is_empty() || (!prefix.is_empty() && check_key(&prefix).is_err()) {
            return Err(ArtifactError::Config(format!("'{url}' is not s3://BUCKET or s3://BUCKET/PREFIX")));
        }
        // reqwest's TLS (for https endpoints) uses the process's rustls provider: ring.
        let _ = rustls::crypto::ring::default_provider().install_default();
        let store = object_store::aws::AmazonS3Builder::from_env()
            .with_bucket_name(bucket)
            .build()
            .map_err(|e| ArtifactError::Config(format!("{url}: {e}")))?;
        let url = if prefix.is_empty() { format!("s3://{bucket}") } else { format!("s3://{bucket}/{prefix}") };
        Ok(Artifacts::with_store(data_dir, Arc::new(store), &prefix, &url))
    }

    /// Artifacts in `store` under `prefix` (named `url`), cached in `data_dir`.
    pub fn with_store(data_dir: &Path, store: Arc<dyn ObjectStore>, prefix: &str, url: &str) -> Artifacts {
        let rt = tokio::runtime::Builder::new_multi_thread()
            .worker_threads(1)
            .thread_name("otofit-artifacts")
            .enable_all()
            .build()
            .expect("a tokio runtime for the artifact store");
        let remote = Remote { store, prefix: prefix.trim_matches('/').to_string(), url: url.to_string(), rt: Some(rt) };
        Artifacts { data_dir: data_dir.to_path_buf(), remote: Some(remote) }
    }

    /// `local (DATA_DIR)` or the store's URL, for logs.
    pub fn describe(&self) -> String {
        match &self.remote {
            None => format!("local ({})", self.data_dir.display()),
            Some(r) => r.url.clone(),
        }
    }

    /// Whether artifacts go to an object store (else they are the data directory's files).
    pub fn is_remote(&self) -> bool {
        self.remote.is_some()
    }

    /// The local file of `key`: where a job writes it, and where a fetched copy is cached.
    pub fn local_path(&self, key: &str) -> PathBuf {
        self.data_dir.join(key)
    }

    /// What a model row records for the model file of job `id`: its absolute path for
    /// local artifacts (every process sharing the data directory loads it there), else its
    /// URL in the store.
    pub fn model_ref(&self, id: &str) -> Result<String> {
        let key = model_key(id);
        match &self.remote {
            None => {
                let path = self.local_path(&key);
                Ok(std::fs::canonicalize(&path).map_err(io(&path))?.display().to_string())
            }
            Some(r) => Ok(format!("{}/{key}", r.url)),
        }
    }

    /// The local file of a model row's `path`: a path as it is; a URL of this store
    /// fetched into the data directory first (once; later calls find the copy).
    /// Blocking: call it from a blocking thread or where a short wait is acceptable.
    pub fn model_file(&self, path: &str) -> Result<PathBuf> {
        if !path.contains("://") {
            return Ok(PathBuf::from(path));
        }
        let foreign = || ArtifactError::ForeignUrl(path.to_string(), self.describe());
        let r = self.remote.as_ref().ok_or_else(foreign)?;
        let key = path.strip_prefix(r.url.as_str()).and_then(|k| k.strip_prefix('/')).ok_or_else(foreign)?;
        self.fetch_blocking(key)
    }

    fn object_path(r: &Remote, key: &str) -> ObjectPath {
        if r.prefix.is_empty() { ObjectPath::from(key) } else { ObjectPath::from(format!("{}/{key}", r.prefix)) }
    }

    /// Runs `f` on the store's runtime and waits for it (from any thread or runtime).
    async fn on_store<T: Send + 'static>(&self, f: impl Future<Output = Result<T>> + Send + 'static) -> Result<T> {
        let r = self.remote.as_ref().expect("on_store without a store");
        let rt = r.rt.as_ref().ok_or(ArtifactError::Runtime)?;
        rt.spawn(f).await.map_err(|_| ArtifactError::Runtime)?
    }

    /// `on_store`, blocking the calling thread (never a runtime's only thread's work:
    /// the store's runtime has its own thread).
    fn on_store_blocking<T: Send + 'static>(&self, f: impl Future<Output = Result<T>> + Send + 'static) -> Result<T> {
        let r = self.remote.as_ref().expect("on_store without a store");
        let rt = r.rt.as_ref().ok_or(ArtifactError::Runtime)?;
        let (tx, rx) = std::sync::mpsc::channel();
        rt.spawn(async move {
            let _ = tx.send(f.await);
        });
        rx.recv().map_err(|_| ArtifactError::Runtime)?
    }

    /// Stores the local file of `key` (written by a job) as the artifact `key`. Local
    /// backend: the file is already the artifact (checked to exist).
    pub async fn put(&self, key: &str) -> Result<()> {
        check_key(key)?;
        let path = self.local_path(key);
        let Some(r) = &self.remote else {
            return tokio::fs::metadata(&path).await.map(|_| ()).map_err(io(&path));
        };
        let (store, location, k) = (r.store.clone(), Self::object_path(r, key), key.to_string());
        self.on_store(async move {
            use tokio::io::AsyncWriteExt;
            let mut file = tokio::fs::File::open(&path).await.map_err(io(&path))?;
            // One PUT for small files, a multipart upload for large ones (datasets).
            let mut up = object_store::buffered::BufWriter::with_capacity(store, location, 16 << 20);
            let copied = tokio::io::copy(&mut file, &mut up).await;
            let closed = match copied {
                Ok(_) => up.shutdown().await,
                Err(e) => {
                    let _ = up.abort().await;
                    Err(e)
                }
            };
            closed.map_err(|e| match e.downcast::<object_store::Error>() {
                Ok(source) => ArtifactError::Store { key: k.clone(), source },
                Err(e) => ArtifactError::Io { path: path.clone(), source: e },
            })
        })
        .await
    }

    /// Stores every file a job `id` left in the data directory: its dataset
    /// (`datasets/<id>/*`, not its part or staging folders), its model
    /// (`models/<id>.otofit`) and its report (`reports/<id>/*`). The keys stored, in order
    /// (a dataset's meta.json last: a dataset is complete once its meta.json is there).
    pub async fn put_job(&self, id: &str) -> Result<Vec<String>> {
        check_key(id)?;
        let mut keys = vec![];
        for dir in ["datasets", "reports"] {
            let Ok(mut entries) = tokio::fs::read_dir(self.data_dir.join(dir).join(id)).await else { continue };
            let mut names = vec![];
            while let Ok(Some(e)) = entries.next_entry().await {
                let name = e.file_name().to_string_lossy().into_owned();
                let file = e.file_type().await.is_ok_and(|t| t.is_file());
                if file && !name.starts_with('.') && !name.ends_with(".tmp") {
                    names.push(name);
                }
            }
            names.sort_by_key(|n| (n == "meta.json", n.clone()));
            keys.extend(names.into_iter().map(|n| format!("{dir}/{id}/{n}")));
        }
        let model = model_key(id);
        if tokio::fs::try_exists(self.local_path(&model)).await.unwrap_or(false) {
            keys.push(model);
        }
        for k in &keys {
            self.put(k).await?;
        }
        Ok(keys)
    }

    /// The local file of artifact `key`: the data directory's file if there, else (object
    /// store) downloaded into it first, under a temporary name renamed when complete.
    pub async fn fetch(&self, key: &str) -> Result<PathBuf> {
        check_key(key)?;
        let path = self.local_path(key);
        if tokio::fs::try_exists(&path).await.unwrap_or(false) {
            return Ok(path);
        }
        let Some(r) = &self.remote else { return Err(ArtifactError::NotFound(key.to_string())) };
        self.on_store(download(r.store.clone(), Self::object_path(r, key), key.to_string(), path)).await
    }

    /// `fetch` for blocking threads (a job's work, model loading).
    pub fn fetch_blocking(&self, key: &str) -> Result<PathBuf> {
        check_key(key)?;
        let path = self.local_path(key);
        if path.exists() {
            return Ok(path);
        }
        let Some(r) = &self.remote else { return Err(ArtifactError::NotFound(key.to_string())) };
        self.on_store_blocking(download(r.store.clone(), Self::object_path(r, key), key.to_string(), path))
    }

    /// The bytes of artifact `key`: the local file if there, else read from the store
    /// (not cached: datasets are served once, and large).
    pub async fn read(&self, key: &str) -> Result<Vec<u8>> {
        check_key(key)?;
        let path = self.local_path(key);
        match tokio::fs::read(&path).await {
            Ok(b) => return Ok(b),
            Err(e) if e.kind() != std::io::ErrorKind::NotFound => return Err(io(&path)(e)),
            Err(_) => {}
        }
        let Some(r) = &self.remote else { return Err(ArtifactError::NotFound(key.to_string())) };
        let (store, location, k) = (r.store.clone(), Self::object_path(r, key), key.to_string());
        self.on_store(async move {
            let got = store.get(&location).await.map_err(|e| store_error(&k, e))?;
            Ok(got.bytes().await.map_err(|e| store_error(&k, e))?.to_vec())
        })
        .await
    }
}

fn store_error(key: &str, e: object_store::Error) -> ArtifactError {
    match e {
        object_store::Error::NotFound { .. } => ArtifactError::NotFound(key.to_string()),
        source => ArtifactError::Store { key: key.to_string(), source },
    }
}

/// Downloads `location` to `path` (through `path.<random>.tmp`, renamed when complete).
async fn download(store: Arc<dyn ObjectStore>, location: ObjectPath, key: String, path: PathBuf) -> Result<PathBuf> {
    use tokio::io::AsyncWriteExt;
    let got = store.get(&location).await.map_err(|e| store_error(&key, e))?;
    if let Some(dir) = path.parent() {
        tokio::fs::create_dir_all(dir).await.map_err(io(dir))?;
    }
    let tmp = path.with_extension(format!("{:08x}.tmp", rand::random::<u32>()));
    let written = async {
        let mut file = tokio::fs::File::create(&tmp).await.map_err(io(&tmp))?;
        let mut stream = got.into_stream();
        while let Some(chunk) = futures_next(&mut stream).await {
            file.write_all(&chunk.map_err(|e| store_error(&key, e))?).await.map_err(io(&tmp))?;
        }
        file.sync_all().await.map_err(io(&tmp))?;
        tokio::fs::rename(&tmp, &path).await.map_err(io(&path))
    }
    .await;
    if written.is_err() {
        let _ = tokio::fs::remove_file(&tmp).await;
    }
    written.map(|_| path)
}

/// The next item of a stream (futures-core's trait alone, no combinator crate).
async fn futures_next<S: futures_core::Stream + Unpin>(s: &mut S) -> Option<S::Item> {
    std::future::poll_fn(|cx| futures_core::Stream::poll_next(std::pin::Pin::new(&mut *s), cx)).await
}

#[cfg(test)]
mod tests {
    use super::*;

    fn temp(tag: &str) -> PathBuf {
        let d = std::env::temp_dir().join(format!("otofit-artifacts-{tag}-{}", std::process::id()));
        let _ = std::fs::remove_dir_all(&d);
        std::fs::create_dir_all(&d).unwrap();
        d
    }

    fn write(dir: &Path, key: &str, text: &str) {
        let p = dir.join(key);
        std::fs::create_dir_all(p.parent().unwrap()).unwrap();
        std::fs::write(p, text).unwrap();
    }

    /// The default backend is the data directory itself: a job's files are its artifacts
    /// where they were written, models are recorded by absolute path, reads read files.
    #[tokio::test]
    async fn the_local_backend_is_the_data_directory() {
        let dir = temp("local");
        let a = Artifacts::open(None, &dir).unwrap();
        assert!(!a.is_remote());
        write(&dir, "datasets/j1/x.csv", "x\n1\n");
        write(&dir, "datasets/j1/meta.json", "{}");
        write(&dir, "datasets/j1/parts/part-00000.json", "{}");
        write(&dir, "models/j1.otofit", "model");
        let keys = a.put_job("j1").await.unwrap();
        assert_eq!(keys, ["datasets/j1/x.csv", "datasets/j1/meta.json", "models/j1.otofit"]);
        assert_eq!(a.read("datasets/j1/x.csv").await.unwrap(), b"x\n1\n");
        assert!(matches!(a.read("datasets/j2/x.csv").await, Err(ArtifactError::NotFound(_))));
        assert_eq!(a.fetch("models/j1.otofit").await.unwrap(), dir.join("models/j1.otofit"));
        assert!(matches!(a.fetch_blocking("models/j2.otofit"), Err(ArtifactError::NotFound(_))));
        let r = a.model_ref("j1").unwrap();
        assert_eq!(PathBuf::from(&r), std::fs::canonicalize(dir.join("models/j1.otofit")).unwrap());
        assert_eq!(a.model_file(&r).unwrap(), PathBuf::from(&r));
        assert!(matches!(a.model_file("s3://b/models/j1.otofit"), Err(ArtifactError::ForeignUrl(..))));
        assert!(matches!(a.put("models/j2.otofit").await, Err(ArtifactError::Io { .. })));
        for bad in ["../x", "/etc/passwd", "a//b", "datasets/./x", ""] {
            assert!(matches!(a.read(bad).await, Err(ArtifactError::BadKey(_))), "{bad}");
        }
        assert!(Artifacts::open(Some("local"), &dir).is_ok_and(|a| !a.is_remote()));
        for bad in ["gs://b/p", "s3://", "s3:///p", "s3://b/../p", "/srv/artifacts"] {
            assert!(matches!(Artifacts::open(Some(bad), &dir), Err(ArtifactError::Config(_))), "{bad}");
        }
        let _ = std::fs::remove_dir_all(&dir);
    }

    /// The object-store path through `object_store`'s in-memory store: a job's files go
    /// up under the prefix; another data directory fetches (and then keeps) them; a model
    /// row's URL resolves only against the same store.
    #[test]
    fn an_object_store_backend_puts_and_fetches_through_another_data_directory() {
        let (a_dir, b_dir) = (temp("worker"), temp("server"));
        let mem: Arc<dyn ObjectStore> = Arc::new(object_store::memory::InMemory::new());
        let worker = Artifacts::with_store(&a_dir, mem.clone(), "/lab/", "s3://bkt/lab");
        let server = Artifacts::with_store(&b_dir, mem.clone(), "lab", "s3://bkt/lab");
        write(&a_dir, "datasets/j1/x.csv", "x\n1\n");
        write(&a_dir, "datasets/j1/meta.json", "{}");
        write(&a_dir, "datasets/j1/.attempt-1/x.csv", "staging");
        write(&a_dir, "reports/j1/report.html", "<p>");
        write(&a_dir, "models/j1.otofit", "model bytes");
        // Called from a plain thread: the store's runtime does the work.
        let rt = tokio::runtime::Builder::new_current_thread().enable_all().build().unwrap();
        let keys = rt.block_on(worker.put_job("j1")).unwrap();
        assert_eq!(keys, ["datasets/j1/x.csv", "datasets/j1/meta.json", "reports/j1/report.html", "models/j1.otofit"]);
        let listed: Vec<String> = rt.block_on(async {
            let mut v = vec![];
            let mut s = mem.list(None);
            while let Some(m) = futures_next(&mut s).await {
                v.push(m.unwrap().location.to_string());
            }
            v.sort();
            v
        });
        assert_eq!(
            listed,
            [
                "lab/datasets/j1/meta.json",
                "lab/datasets/j1/x.csv",
                "lab/models/j1.otofit",
                "lab/reports/j1/report.html"
            ]
        );
        assert_eq!(rt.block_on(server.read("datasets/j1/x.csv")).unwrap(), b"x\n1\n");
        assert!(!b_dir.join("datasets/j1/x.csv").exists(), "reads are not cached");
        let r = worker.model_ref("j1").unwrap();
        assert_eq!(r, "s3://bkt/lab/models/j1.otofit");
        // Blocking fetch from inside a current-thread runtime (as an async handler would).
        let got = rt.block_on(async { server.model_file(&r) }).unwrap();
        assert_eq!(got, b_dir.join("models/j1.otofit"));
        assert_eq!(std::fs::read_to_string(&got).unwrap(), "model bytes");
        // Cached: found locally even after the object is gone.
        rt.block_on(mem.delete(&ObjectPath::from("lab/models/j1.otofit"))).unwrap();
        assert_eq!(server.fetch_blocking("models/j1.otofit").unwrap(), got);
        assert!(matches!(rt.block_on(server.fetch("models/j9.otofit")), Err(ArtifactError::NotFound(_))));
        assert!(matches!(server.model_file("s3://other/models/j1.otofit"), Err(ArtifactError::ForeignUrl(..))));
        // No temporary download left behind.
        let left: Vec<_> = std::fs::read_dir(b_dir.join("models")).unwrap().flatten().map(|e| e.file_name()).collect();
        assert_eq!(left.len(), 1, "{left:?}");
        drop(rt);
        let _ = (std::fs::remove_dir_all(&a_dir), std::fs::remove_dir_all(&b_dir));
    }
}
