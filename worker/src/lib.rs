//! Furnace's worker: pulls chunk leases from a coordinator, fetches the scene bundle (cached
//! on disk by hash), renders the chunk on all its threads, heartbeats while it renders, and
//! uploads the partial with retries. It waits out an unreachable coordinator, and when asked to
//! stop it finishes the chunk in hand, uploads it and exits.

use std::collections::HashMap;
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{mpsc, Arc};
use std::time::Duration;

use furnace_core::{render_region, render_region_parallel, Accum, Scene, Stats};
use furnace_proto::{encode_partial, ApiError, Bundle, ChunkSpec, Lease, LeaseRequest};
use reqwest::blocking::{Client, RequestBuilder, Response};
use reqwest::StatusCode;

/// Renders one chunk: its tile plus the filter margin, its sample range (one thread).
pub fn render_chunk(scene: &Scene, chunk: &ChunkSpec, seed: u64) -> (Accum, Stats) {
    render_region(scene, &chunk.region, seed)
}

#[derive(Debug, thiserror::Error)]
pub enum WorkerError {
    #[error("cannot build the worker's thread pool: {0}")]
    Pool(String),
    #[error("HTTP client: {0}")]
    Client(String),
    #[error("cache folder {path}: {err}")]
    Cache { path: String, err: std::io::Error },
}

pub struct WorkerConfig {
    /// Base URL, e.g. `http://127.0.0.1:8640`.
    pub coordinator: String,
    pub token: Option<String>,
    pub threads: usize,
    pub name: String,
    /// Scene bundles, cached by hash.
    pub cache: PathBuf,
    /// Wait between polls when there is no work.
    pub poll: Duration,
    /// Set to stop after the chunk in hand.
    pub stop: Arc<AtomicBool>,
    /// Stop when the coordinator has no work (instead of polling on).
    pub exit_when_idle: bool,
}

struct Worker {
    cfg: WorkerConfig,
    http: Client,
    pool: rayon::ThreadPool,
    scenes: HashMap<String, Arc<Scene>>,
}

/// Runs the worker until stopped (or idle, with `exit_when_idle`). Returns chunks rendered.
pub fn run(cfg: WorkerConfig) -> Result<u64, WorkerError> {
    let pool = rayon::ThreadPoolBuilder::new()
        .num_threads(cfg.threads)
        .thread_name(|i| format!("render-{i}"))
        .build()
        .map_err(|e| WorkerError::Pool(e.to_string()))?;
    let http = Client::builder()
        .timeout(Duration::from_secs(120))
        .build()
        .map_err(|e| WorkerError::Client(e.to_string()))?;
    std::fs::create_dir_all(&cfg.cache)
        .map_err(|err| WorkerError::Cache { path: cfg.cache.display().to_string(), err })?;
    let mut w = Worker { cfg, http, pool, scenes: HashMap::new() };
    let mut done = 0;
    let mut backoff = Backoff::new();
    while !w.cfg.stop.load(Ordering::SeqCst) {
        match w.lease() {
            Ok(Some(lease)) => {
                backoff.reset();
                if w.work(&lease) {
                    done += 1;
                }
            }
            Ok(None) => {
                if w.cfg.exit_when_idle {
                    break;
                }
                sleep_unless_stopped(w.cfg.poll, &w.cfg.stop);
            }
            Err(e) => {
                let d = backoff.next();
                tracing::warn!("coordinator unreachable ({e}); retrying in {:.1} s", d.as_secs_f64());
                sleep_unless_stopped(d, &w.cfg.stop);
            }
        }
    }
    Ok(done)
}

fn sleep_unless_stopped(d: Duration, stop: &AtomicBool) {
    let end = std::time::Instant::now() + d;
    while std::time::Instant::now() < end && !stop.load(Ordering::SeqCst) {
        std::thread::sleep(Duration::from_millis(20).min(d));
    }
}

/// Exponential backoff from 100 ms to 5 s.
struct Backoff(Duration);
impl Backoff {
    fn new() -> Self {
        Backoff(Duration::from_millis(100))
    }
    fn reset(&mut self) {
        *self = Backoff::new();
    }
    fn next(&mut self) -> Duration {
        let d = self.0;
        self.0 = (self.0 * 2).min(Duration::from_secs(5));
        d
    }
}

fn error_text(r: Response) -> String {
    let status = r.status();
    match r.json::<ApiError>() {
        Ok(e) => format!("{status}: {}", e.error),
        Err(_) => status.to_string(),
    }
}

impl Worker {
    fn url(&self, path: &str) -> String {
        format!("{}{}", self.cfg.coordinator.trim_end_matches('/'), path)
    }

    fn auth(&self, r: RequestBuilder) -> RequestBuilder {
        match &self.cfg.token {
            Some(t) => r.bearer_auth(t),
            None => r,
        }
    }

    fn lease(&self) -> Result<Option<Lease>, String> {
        let r = self
            .auth(self.http.post(self.url("/v1/leases")))
            .json(&LeaseRequest { worker: self.cfg.name.clone() })
            .send()
            .map_err(|e| e.to_string())?;
        match r.status() {
            StatusCode::OK => r.json().map(Some).map_err(|e| e.to_string()),
            StatusCode::NO_CONTENT => Ok(None),
            _ => Err(error_text(r)),
        }
    }

    /// Renders and uploads one leased chunk. Returns whether the upload was accepted.
    fn work(&mut self, lease: &Lease) -> bool {
        let scene = match self.scene(&lease.bundle_hash) {
            Ok(s) => s,
            Err(e) => {
                self.report_failure(lease, &e);
                return false;
            }
        };
        // Heartbeats while rendering, a third of the lease apart.
        let (tx, rx) = mpsc::channel::<()>();
        let hb = {
            let http = self.http.clone();
            let url = self.url(&format!("/v1/jobs/{}/chunks/{}/heartbeat", lease.job, lease.chunk.id));
            let token = self.cfg.token.clone();
            let epoch = lease.epoch;
            let every = Duration::from_millis((lease.deadline_ms / 3).max(50));
            std::thread::spawn(move || {
                while let Err(mpsc::RecvTimeoutError::Timeout) = rx.recv_timeout(every) {
                    let mut r = http.post(&url).json(&furnace_proto::Heartbeat { epoch });
                    if let Some(t) = &token {
                        r = r.bearer_auth(t);
                    }
                    match r.send() {
                        Ok(resp) if resp.status() == StatusCode::CONFLICT => break,
                        _ => {}
                    }
                }
            })
        };
        let t = std::time::Instant::now();
        let (acc, st) =
            self.pool.install(|| render_region_parallel(&scene, &lease.chunk.region, lease.settings.seed));
        drop(tx);
        hb.join().ok();
        tracing::info!(
            job = %lease.job,
            chunk = lease.chunk.id,
            samples = lease.chunk.region.samples(),
            dropped = st.dropped,
            "rendered in {:.2} s",
            t.elapsed().as_secs_f64()
        );
        let body = encode_partial(&acc);
        self.upload(lease, body)
    }

    fn upload(&self, lease: &Lease, body: Vec<u8>) -> bool {
        let url = self
            .url(&format!("/v1/jobs/{}/chunks/{}/result?epoch={}", lease.job, lease.chunk.id, lease.epoch));
        let mut backoff = Backoff::new();
        loop {
            match self.auth(self.http.put(&url)).body(body.clone()).send() {
                Ok(r) if r.status().is_success() => return true,
                Ok(r) if r.status().is_client_error() => {
                    tracing::warn!(job = %lease.job, chunk = lease.chunk.id, "upload refused: {}", error_text(r));
                    return false;
                }
                Ok(r) => tracing::warn!("upload failed ({}); retrying", r.status()),
                Err(e) => tracing::warn!("upload failed ({e}); retrying"),
            }
            std::thread::sleep(backoff.next());
        }
    }

    fn report_failure(&self, lease: &Lease, error: &str) {
        tracing::error!(job = %lease.job, chunk = lease.chunk.id, "{error}");
        let url = self.url(&format!("/v1/jobs/{}/chunks/{}/fail", lease.job, lease.chunk.id));
        let body = serde_json::json!({"epoch": lease.epoch, "error": error});
        let _ = self.auth(self.http.post(url)).json(&body).send();
    }

    fn get(&self, path: &str) -> Result<Vec<u8>, String> {
        let r = self.auth(self.http.get(self.url(path))).send().map_err(|e| e.to_string())?;
        if !r.status().is_success() {
            return Err(error_text(r));
        }
        r.bytes().map(|b| b.to_vec()).map_err(|e| e.to_string())
    }

    /// The bundle's scene, from memory, the disk cache, or the coordinator.
    fn scene(&mut self, bundle_hash: &str) -> Result<Arc<Scene>, String> {
        if let Some(s) = self.scenes.get(bundle_hash) {
            return Ok(s.clone());
        }
        if !furnace_proto::is_hash(bundle_hash) {
            return Err(format!("bad bundle hash '{bundle_hash}'"));
        }
        let manifest = self.get(&format!("/v1/bundles/{bundle_hash}"))?;
        let bundle: Bundle =
            serde_json::from_slice(&manifest).map_err(|e| format!("bundle manifest: {e}"))?;
        bundle.validate()?;
        if bundle.hash() != bundle_hash {
            return Err(format!("bundle manifest does not hash to {bundle_hash}"));
        }
        let dir = self.cfg.cache.join("bundles").join(bundle_hash);
        for (path, hash) in &bundle.files {
            let file = self.cfg.cache.join("files").join(hash);
            if !file.exists() {
                let bytes = self.get(&format!("/v1/files/{hash}"))?;
                if blake3::hash(&bytes).to_hex().as_str() != hash {
                    return Err(format!("file {path} does not hash to {hash}"));
                }
                write_file(&file, &bytes).map_err(|e| format!("cache {}: {e}", file.display()))?;
            }
            let dst = dir.join(path);
            if !dst.exists() {
                if let Some(p) = dst.parent() {
                    std::fs::create_dir_all(p).map_err(|e| e.to_string())?;
                }
                std::fs::copy(&file, &dst).map_err(|e| format!("cache {}: {e}", dst.display()))?;
            }
        }
        let scene = Scene::load(&dir.join(&bundle.scene), &[]).map_err(|e| e.to_string())?;
        let scene = Arc::new(scene);
        self.scenes.insert(bundle_hash.to_string(), scene.clone());
        Ok(scene)
    }
}

fn write_file(path: &Path, bytes: &[u8]) -> std::io::Result<()> {
    if let Some(p) = path.parent() {
        std::fs::create_dir_all(p)?;
    }
    let tmp = path.with_extension(format!("tmp{}", std::process::id()));
    std::fs::write(&tmp, bytes)?;
    std::fs::rename(tmp, path)
}
