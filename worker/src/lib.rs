//! Furnace's worker: pulls chunk leases from a coordinator, fetches the scene bundle (cached
//! on disk by hash), renders the chunk on all its threads, heartbeats while it renders, and
//! uploads the partial with retries. It waits out an unreachable coordinator, and when asked to
//! stop it finishes the chunks in hand, uploads them and exits. `furnace render` runs this same
//! worker against a coordinator in its own process (the `furnace` package's `LocalLink`).
//! The worker knows the coordinator only through [`Link`] and the wire types of
//! `furnace-proto`; it does not depend on the coordinator crate.

use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{mpsc, Arc, Mutex};
use std::time::Duration;

use furnace_core::{render_region, render_region_on, Accum, Scene, Stats};
use furnace_proto::{encode_chunk, ApiError, Bundle, ChunkSpec, FailureReport, Lease, LeaseRequest};
pub use furnace_proto::{Link, Uploaded};
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
    pub link: Arc<dyn Link>,
    /// Render threads (0: all cores).
    pub threads: usize,
    /// Chunks in flight at once, sharing the threads: while one chunk's last rows render or
    /// its result uploads, the others keep the threads busy. 0: [`auto_slots`] of the threads.
    pub slots: usize,
    pub name: String,
    /// Wait between polls when there is no work.
    pub poll: Duration,
    /// Set to stop after the chunk in hand.
    pub stop: Arc<AtomicBool>,
    /// Stop when the coordinator has no work (instead of polling on).
    pub exit_when_idle: bool,
}

/// Runs the worker until stopped (or idle, with `exit_when_idle`). Returns chunks rendered.
pub fn run(cfg: WorkerConfig) -> Result<u64, WorkerError> {
    let pool = rayon::ThreadPoolBuilder::new()
        .num_threads(cfg.threads)
        .thread_name(|i| format!("render-{i}"))
        .build()
        .map_err(|e| WorkerError::Pool(e.to_string()))?;
    let slots = match cfg.slots {
        0 => auto_slots(pool.current_num_threads()),
        n => n,
    };
    tracing::debug!("{} render threads, up to {slots} chunks in flight", pool.current_num_threads());
    let done = std::thread::scope(|s| {
        // A slot the system cannot start a thread for is left out (with a warning), as long
        // as one runs: fewer chunks in flight, the same results.
        let mut handles = Vec::with_capacity(slots);
        for k in 0..slots {
            match std::thread::Builder::new().name(format!("slot-{k}")).spawn_scoped(s, || slot(&cfg, &pool))
            {
                Ok(h) => handles.push(h),
                Err(e) => {
                    tracing::warn!("cannot start slot {} of {slots}: {e}; running with {k}", k + 1);
                    break;
                }
            }
        }
        if handles.is_empty() {
            return Err(WorkerError::Pool("cannot start a single slot thread".into()));
        }
        Ok(handles.into_iter().map(|h| h.join().unwrap_or(0)).sum())
    })?;
    Ok(done)
}

/// Chunks in flight for `threads` render threads: half the threads, at least 2 and at most
/// [`MAX_AUTO_SLOTS`]. A chunk is rendered in bands of two rows (32 for a 64-pixel tile) that
/// the pool's threads take in turn ([`render_region_on`]); with too few chunks in flight, the
/// threads that find no band left wait for a chunk's upload and the next lease. Measured on
/// 16 cores (docs/BENCHMARKS.md, "Multi-core scaling"), when a chunk's bands were a fork-join
/// on the pool: at 16 threads, 8 chunks render 16 to 31% more samples a second than 2, and 4
/// chunks about half that. Each chunk in flight holds its
/// accumulation (its tile's pixels) and, while idle, one lease request at the coordinator.
pub fn auto_slots(threads: usize) -> usize {
    (threads / 2).clamp(2, MAX_AUTO_SLOTS)
}

/// The most chunks [`auto_slots`] keeps in flight: 16 slots of 16 bands keep 64 threads
/// busy four times over.
pub const MAX_AUTO_SLOTS: usize = 16;

/// One chunk at a time: lease, render, upload.
fn slot(cfg: &WorkerConfig, pool: &rayon::ThreadPool) -> u64 {
    let mut done = 0;
    let mut backoff = Backoff::new();
    while !cfg.stop.load(Ordering::SeqCst) {
        match cfg.link.lease(&cfg.name) {
            Ok(Some(lease)) => {
                backoff.reset();
                if work(cfg, pool, &lease) {
                    done += 1;
                }
            }
            Ok(None) => {
                if cfg.exit_when_idle {
                    break;
                }
                sleep_unless_stopped(cfg.poll, &cfg.stop);
            }
            Err(e) => {
                let d = backoff.next();
                tracing::warn!("coordinator unreachable ({e}); retrying in {:.1} s", d.as_secs_f64());
                sleep_unless_stopped(d, &cfg.stop);
            }
        }
    }
    done
}

/// Renders and uploads one leased chunk. Returns whether the upload was accepted.
fn work(cfg: &WorkerConfig, pool: &rayon::ThreadPool, lease: &Lease) -> bool {
    let link = &*cfg.link;
    let scene = match link.scene(lease) {
        Ok(s) => s,
        Err(e) => {
            tracing::error!(job = %lease.job, chunk = lease.chunk.id, "{e}");
            link.fail(lease, &e);
            return false;
        }
    };
    let t = std::time::Instant::now();
    // Heartbeats while rendering and uploading, a third of the lease apart (an upload over a
    // slow link may take longer than a lease). A lease that is gone (revoked by a cancel or a
    // delete, or given to another worker) stops the render: its result would be refused.
    let (tx, rx) = mpsc::channel::<()>();
    let every = Duration::from_millis((lease.deadline_ms / 3).max(50));
    let lost = AtomicBool::new(false);
    std::thread::scope(|s| {
        let lost = &lost;
        let beats = std::thread::Builder::new().name("heartbeat".into()).spawn_scoped(s, move || {
            while let Err(mpsc::RecvTimeoutError::Timeout) = rx.recv_timeout(every) {
                if !link.heartbeat(lease) {
                    lost.store(true, Ordering::SeqCst);
                    break;
                }
            }
        });
        if let Err(e) = beats {
            // Rendered without heartbeats: a chunk longer than its lease is then given to
            // another worker and this upload refused, which loses time, not results.
            tracing::warn!(job = %lease.job, chunk = lease.chunk.id, "cannot start the heartbeat thread: {e}");
        }
        let done = render_and_upload(link, pool, &scene, lease, lost, t);
        drop(tx);
        done
    })
}

/// The part of [`work`] under heartbeats.
fn render_and_upload(
    link: &dyn Link,
    pool: &rayon::ThreadPool,
    scene: &Scene,
    lease: &Lease,
    lost: &AtomicBool,
    t: std::time::Instant,
) -> bool {
    // A panic while rendering is this chunk's failure, reported with its message; the worker
    // lives on.
    let rendered = std::panic::catch_unwind(std::panic::AssertUnwindSafe(|| {
        render_region_on(pool, scene, &lease.chunk.region, lease.settings.seed, lost)
    }));
    let (acc, st) = match rendered {
        Ok(Some(r)) => r,
        Ok(None) => {
            // Work thrown away: worth a warning.
            tracing::warn!(job = %lease.job, chunk = lease.chunk.id, "lease lost while rendering: chunk dropped");
            return false;
        }
        Err(panic) => {
            let e = format!("render panicked: {}", furnace_core::scene::panic_message(&*panic));
            tracing::error!(job = %lease.job, chunk = lease.chunk.id, "{e}");
            link.fail(lease, &e);
            return false;
        }
    };
    tracing::debug!(
        job = %lease.job,
        chunk = lease.chunk.id,
        samples = lease.chunk.region.samples(),
        dropped = acc.dropped.total(),
        "rendered in {:.2} s",
        t.elapsed().as_secs_f64()
    );
    let mut backoff = Backoff::new();
    loop {
        match link.upload(lease, &acc, &st) {
            Uploaded::Accepted => return true,
            Uploaded::Refused(e) => {
                tracing::warn!(job = %lease.job, chunk = lease.chunk.id, "upload refused: {e}");
                return false;
            }
            Uploaded::Retry(e) => tracing::warn!("upload failed ({e}); retrying"),
        }
        // A lease lost meanwhile: the upload would be refused.
        if lost.load(Ordering::SeqCst) {
            tracing::warn!(job = %lease.job, chunk = lease.chunk.id, "lease lost while uploading: chunk dropped");
            return false;
        }
        std::thread::sleep(backoff.next());
    }
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

/// Loaded scenes a worker keeps for the leases to come: the frame it renders and the next.
pub const SCENES_KEPT: usize = 2;

/// A coordinator over HTTP. Scene bundles are cached on disk by hash and in memory once loaded.
pub struct HttpLink {
    base: String,
    token: Option<String>,
    http: Client,
    /// The cache folder, through the descriptor the file holds open (see `private_dir`).
    cache: Mutex<(PathBuf, std::fs::File)>,
    /// Its name, for messages (and to make it again if it is removed).
    cache_name: PathBuf,
    /// The scenes loaded last, by bundle hash and scene parameters, the newest last (at most
    /// [`SCENES_KEPT`]: the frames of a frame-range job would otherwise pile up).
    scenes: Mutex<Vec<(String, Arc<Scene>)>>,
    /// Files the loads before parsed: a frame reads again only what differs from the last.
    assets: Arc<furnace_core::scene::assets::AssetCache>,
    /// How long a lease request may wait at the coordinator for work.
    pub wait: Duration,
    /// A file that holds the Unix time of the last answer from the coordinator (rewritten at
    /// most every 5 s), for container health checks (`furnace probe --file`).
    pub health_file: Option<PathBuf>,
    /// Most memory a job's scene may take to load (see `furnace_core::LoadLimits`).
    pub max_scene_bytes: u64,
    health_written: Mutex<Option<std::time::Instant>>,
}

impl HttpLink {
    /// `base` is e.g. `http://127.0.0.1:8640`; `cache` holds scene bundles by hash.
    pub fn new(base: &str, token: Option<String>, cache: PathBuf) -> Result<HttpLink, WorkerError> {
        let http = Client::builder()
            .timeout(Duration::from_secs(120))
            .build()
            .map_err(|e| WorkerError::Client(e.to_string()))?;
        let cache_name = cache;
        let (cache, cache_dir) = private_dir(&cache_name)
            .map_err(|err| WorkerError::Cache { path: cache_name.display().to_string(), err })?;
        let base = base.trim_end_matches('/').to_string();
        let scenes = Mutex::new(Vec::new());
        let health_written = Mutex::new(None);
        Ok(HttpLink {
            base,
            token,
            http,
            cache: Mutex::new((cache, cache_dir)),
            cache_name,
            scenes,
            assets: Arc::new(furnace_core::scene::assets::AssetCache::new()),
            wait: Duration::from_secs(2),
            health_file: None,
            max_scene_bytes: furnace_core::FARM_SCENE_BYTES,
            health_written,
        })
    }

    /// The cache folder; made again (and checked again) if it was removed (a cleaner of
    /// `/tmp`, say): the folder held open would take no new files.
    fn cache_dir(&self) -> std::io::Result<PathBuf> {
        use std::os::unix::fs::MetadataExt;
        let mut cache = self.cache.lock().unwrap_or_else(|e| e.into_inner());
        if cache.1.metadata()?.nlink() == 0 {
            tracing::warn!("the cache folder {} was removed: making it again", self.cache_name.display());
            *cache = private_dir(&self.cache_name)?;
        }
        Ok(cache.0.clone())
    }

    /// Notes an answer from the coordinator in the health file.
    fn answered(&self) {
        let Some(path) = &self.health_file else { return };
        let mut last = self.health_written.lock().unwrap_or_else(|e| e.into_inner());
        if last.is_some_and(|t| t.elapsed() < Duration::from_secs(5)) {
            return;
        }
        *last = Some(std::time::Instant::now());
        let now = std::time::SystemTime::now().duration_since(std::time::UNIX_EPOCH).unwrap_or_default();
        if let Err(e) = write_file(path, now.as_secs().to_string().as_bytes()) {
            tracing::warn!("health file {}: {e}", path.display());
        }
    }

    fn url(&self, path: &str) -> String {
        format!("{}{}", self.base, path)
    }

    fn auth(&self, r: RequestBuilder) -> RequestBuilder {
        match &self.token {
            Some(t) => r.bearer_auth(t),
            None => r,
        }
    }

    fn get(&self, path: &str) -> Result<Vec<u8>, String> {
        let r = self.auth(self.http.get(self.url(path))).send().map_err(|e| e.to_string())?;
        if !r.status().is_success() {
            return Err(error_text(r));
        }
        r.bytes().map(|b| b.to_vec()).map_err(|e| e.to_string())
    }

    /// Streams `GET path` into the cache's `file` while hashing it (never whole in memory);
    /// stored only if it hashes to `hash`. `name` is the file's path in the bundle.
    fn download(
        &self,
        path: &str,
        file: &Path,
        hash: &str,
        name: &str,
        cache_err: &dyn Fn(&Path, std::io::Error) -> String,
    ) -> Result<(), String> {
        use std::io::{Read, Write};
        let mut r = self.auth(self.http.get(self.url(path))).send().map_err(|e| e.to_string())?;
        if !r.status().is_success() {
            return Err(error_text(r));
        }
        let tmp = temp_beside(file).map_err(|e| cache_err(file, e))?;
        let mut out = std::fs::File::create(&tmp).map_err(|e| cache_err(&tmp, e))?;
        let mut hasher = blake3::Hasher::new();
        let mut buf = vec![0u8; 1 << 16];
        let copied = loop {
            let n = match r.read(&mut buf) {
                Ok(0) => break Ok(()),
                Ok(n) => n,
                Err(e) => break Err(e.to_string()),
            };
            hasher.update(&buf[..n]);
            if let Err(e) = out.write_all(&buf[..n]) {
                break Err(cache_err(&tmp, e));
            }
        };
        drop(out);
        let done = copied.and_then(|()| {
            if hasher.finalize().to_hex().as_str() != hash {
                return Err(format!("file {name} does not hash to {hash}"));
            }
            std::fs::rename(&tmp, file).map_err(|e| cache_err(file, e))
        });
        if done.is_err() {
            std::fs::remove_file(&tmp).ok();
        }
        done
    }

    /// Fetches the bundle's files (those not cached yet) and loads its scene.
    fn load(&self, bundle_hash: &str, defines: &[(String, String)]) -> Result<Scene, String> {
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
        // Nothing on disk is trusted: a cached file is used only if it is a plain file that
        // still hashes to its name, and the bundle is laid out from those bytes in a folder of
        // this load's own (no other load or worker process sharing the cache touches it; new
        // files are renamed into place, which replaces a link instead of writing through it),
        // then removed once the scene is in memory.
        static LOADS: std::sync::atomic::AtomicU64 = std::sync::atomic::AtomicU64::new(0);
        let n = LOADS.fetch_add(1, std::sync::atomic::Ordering::Relaxed);
        let cache = self.cache_dir().map_err(|e| format!("cache {}: {e}", self.cache_name.display()))?;
        let dir = cache.join("bundles").join(format!("{bundle_hash}.{}.{n}", std::process::id()));
        let cache_err = |p: &Path, e: std::io::Error| {
            let shown = p.strip_prefix(&cache).map(|rel| self.cache_name.join(rel));
            format!("cache {}: {e}", shown.as_deref().unwrap_or(p).display())
        };
        match std::fs::symlink_metadata(&dir) {
            Ok(m) if m.is_dir() => std::fs::remove_dir_all(&dir),
            Ok(_) => std::fs::remove_file(&dir),
            Err(_) => Ok(()),
        }
        .map_err(|e| cache_err(&dir, e))?;
        for (path, hash) in &bundle.files {
            let file = cache.join("files").join(hash);
            if !cached(&file, hash) {
                self.download(&format!("/v1/files/{hash}"), &file, hash, path, &cache_err)?;
            }
            let dst = dir.join(path);
            link_or_copy(&file, &dst).map_err(|e| cache_err(&dst, e))?;
        }
        let limits = furnace_core::LoadLimits {
            max_bytes: self.max_scene_bytes,
            assets: Some(self.assets.clone()),
            ..Default::default()
        };
        // Errors name files by their paths in the bundle.
        let inside = format!("{}/", dir.display());
        let scene = Scene::load_with(&dir.join(&bundle.scene), defines, &limits).map_err(|e| {
            let e = e.to_string().replace(&inside, "");
            // The limit named is this worker's own.
            e.replace("(--max-scene-memory-mb)", "(this worker's --max-scene-memory-mb)")
        });
        std::fs::remove_dir_all(&dir).ok();
        scene
    }
}

impl Link for HttpLink {
    fn lease(&self, worker: &str) -> Result<Option<Lease>, String> {
        let r = self
            .auth(self.http.post(self.url("/v1/leases")))
            .json(&LeaseRequest { worker: worker.to_string(), wait_ms: self.wait.as_millis() as u64 })
            .send()
            .map_err(|e| e.to_string())?;
        match r.status() {
            StatusCode::OK => {
                self.answered();
                r.json().map(Some).map_err(|e| e.to_string())
            }
            StatusCode::NO_CONTENT => {
                self.answered();
                Ok(None)
            }
            _ => Err(error_text(r)),
        }
    }

    fn heartbeat(&self, l: &Lease) -> bool {
        let url = self.url(&format!("/v1/jobs/{}/chunks/{}/heartbeat", l.job, l.chunk.id));
        let r = self.auth(self.http.post(url)).json(&furnace_proto::Heartbeat { epoch: l.epoch }).send();
        if matches!(&r, Ok(resp) if resp.status().is_success()) {
            // A worker busy with long chunks asks for no lease for minutes: its heartbeats
            // keep its health file fresh.
            self.answered();
        }
        // The lease is gone (revoked, taken over, or its job deleted): stop heartbeating.
        !matches!(r, Ok(resp) if matches!(resp.status(), StatusCode::CONFLICT | StatusCode::NOT_FOUND))
    }

    fn scene(&self, l: &Lease) -> Result<Arc<Scene>, String> {
        // Held while loading, so that two slots do not load the same scene twice.
        let mut scenes = self.scenes.lock().unwrap_or_else(|e| e.into_inner());
        let defines: Vec<(String, String)> = l.defines.iter().map(|(k, v)| (k.clone(), v.clone())).collect();
        let key = format!("{}{defines:?}", l.bundle_hash);
        if let Some(i) = scenes.iter().position(|(k, _)| *k == key) {
            let hit = scenes.remove(i);
            scenes.push(hit.clone());
            return Ok(hit.1);
        }
        let scene = Arc::new(self.load(&l.bundle_hash, &defines)?);
        if scenes.len() >= SCENES_KEPT {
            scenes.remove(0);
        }
        scenes.push((key, scene.clone()));
        Ok(scene)
    }

    fn upload(&self, l: &Lease, acc: &Accum, stats: &Stats) -> Uploaded {
        let url = self.url(&format!("/v1/jobs/{}/chunks/{}/result?epoch={}", l.job, l.chunk.id, l.epoch));
        match self.auth(self.http.put(&url)).body(encode_chunk(acc, Some(stats))).send() {
            Ok(r) if r.status().is_success() => {
                self.answered();
                Uploaded::Accepted
            }
            Ok(r) if r.status().is_client_error() => Uploaded::Refused(error_text(r)),
            Ok(r) => Uploaded::Retry(r.status().to_string()),
            Err(e) => Uploaded::Retry(e.to_string()),
        }
    }

    fn fail(&self, l: &Lease, error: &str) {
        let url = self.url(&format!("/v1/jobs/{}/chunks/{}/fail", l.job, l.chunk.id));
        let body = FailureReport { epoch: l.epoch, error: error.to_string() };
        let _ = self.auth(self.http.post(url)).json(&body).send();
    }
}

/// Whether the cache holds `file` as a plain file (not a link) that hashes to `hash` (read
/// in pieces).
fn cached(file: &Path, hash: &str) -> bool {
    std::fs::symlink_metadata(file).is_ok_and(|m| m.is_file())
        && furnace_proto::hash_file(file).is_ok_and(|h| h == hash)
}

/// Puts the cached `file` at `dst` in a bundle's folder: a hard link (no copy of a large
/// file), or a copy where links cannot be made.
fn link_or_copy(file: &Path, dst: &Path) -> std::io::Result<()> {
    if let Some(p) = dst.parent() {
        std::fs::create_dir_all(p)?;
    }
    std::fs::hard_link(file, dst).or_else(|_| std::fs::copy(file, dst).map(|_| ()))
}

/// The worker's default cache: `$XDG_CACHE_HOME/furnace`, else `~/.cache/furnace`, else
/// `furnace-cache-$USER` in the temporary folder (made private by [`HttpLink::new`]).
pub fn default_cache_dir() -> PathBuf {
    let env = |k: &str| std::env::var_os(k).filter(|v| !v.is_empty()).map(PathBuf::from);
    env("XDG_CACHE_HOME")
        .or_else(|| env("HOME").map(|h| h.join(".cache")))
        .map(|c| c.join("furnace"))
        .unwrap_or_else(|| {
            let user = std::env::var("USER").unwrap_or_else(|_| "user".into());
            std::env::temp_dir().join(format!("furnace-cache-{user}"))
        })
}

/// The cache folder to use for `dir`: `dir` itself when it is a folder (not a link) of this
/// process's user, made private (mode 0700); in a folder of another user (a shared `/tmp`,
/// a Kubernetes emptyDir), a private `furnace-UID` inside it.
///
/// The folder is checked through a descriptor opened without following links, and used from
/// then on through that descriptor (`/proc/self/fd/N`, kept open with the returned file): a
/// folder renamed and replaced by a link afterwards (possible in a parent other users may
/// write) is never followed.
fn private_dir(dir: &Path) -> std::io::Result<(PathBuf, std::fs::File)> {
    use std::os::unix::fs::{DirBuilderExt, MetadataExt, OpenOptionsExt, PermissionsExt};
    use std::os::unix::io::AsRawFd;
    // On Linux /proc/self belongs to this process's user.
    let me = std::fs::metadata("/proc/self").map(|p| p.uid()).ok();
    let mut dir = dir.to_path_buf();
    for last in [false, true] {
        std::fs::DirBuilder::new().recursive(true).mode(0o700).create(&dir)?;
        let opened = std::fs::OpenOptions::new()
            .read(true)
            .custom_flags(libc::O_NOFOLLOW | libc::O_DIRECTORY | libc::O_CLOEXEC)
            .open(&dir);
        let refused =
            || std::io::Error::other(format!("{} is not a folder (a link is refused)", dir.display()));
        let fd = match opened {
            Ok(f) => f,
            Err(e) if matches!(e.raw_os_error(), Some(libc::ELOOP | libc::ENOTDIR)) => return Err(refused()),
            Err(e) => return Err(e),
        };
        let m = fd.metadata()?;
        if !m.is_dir() {
            return Err(refused());
        }
        match me {
            Some(uid) if m.uid() != uid && last => {
                return Err(std::io::Error::other(format!("{} belongs to another user", dir.display())))
            }
            Some(uid) if m.uid() != uid => dir = dir.join(format!("furnace-{uid}")),
            _ => {
                if m.mode() & 0o077 != 0 {
                    fd.set_permissions(std::fs::Permissions::from_mode(0o700))?;
                }
                // A parent others may write into (not sticky) can rename the folder: harmless
                // here (it is used through its descriptor), but worth saying.
                if let Some(p) = dir.parent().and_then(|p| std::fs::metadata(p).ok()) {
                    if p.mode() & 0o002 != 0 && p.mode() & 0o1000 == 0 {
                        tracing::warn!(
                            "{}: its folder may be written by anyone and is not sticky",
                            dir.display()
                        );
                    }
                }
                let by_fd = PathBuf::from(format!("/proc/self/fd/{}", fd.as_raw_fd()));
                let path = if by_fd.is_dir() {
                    by_fd
                } else {
                    tracing::warn!("no /proc/self/fd here: the cache folder is used by its name");
                    dir
                };
                return Ok((path, fd));
            }
        }
    }
    unreachable!("the second pass returns")
}

fn write_file(path: &Path, bytes: &[u8]) -> std::io::Result<()> {
    let tmp = temp_beside(path)?;
    std::fs::write(&tmp, bytes)?;
    std::fs::rename(tmp, path)
}

/// A fresh temporary name beside `path` (its folder made), to write and then rename.
fn temp_beside(path: &Path) -> std::io::Result<PathBuf> {
    if let Some(p) = path.parent() {
        std::fs::create_dir_all(p)?;
    }
    static N: std::sync::atomic::AtomicU64 = std::sync::atomic::AtomicU64::new(0);
    let n = N.fetch_add(1, std::sync::atomic::Ordering::Relaxed);
    Ok(path.with_extension(format!("tmp{}.{n}", std::process::id())))
}

#[cfg(test)]
mod cache_tests {
    use super::*;
    use std::os::unix::fs::{MetadataExt, PermissionsExt};

    /// The cache is a private folder: made 0700 when ours; a private `furnace-UID` inside a
    /// folder of another user; a link is refused.
    #[test]
    fn the_cache_folder_is_private_to_its_user() {
        let root = std::env::temp_dir().join(format!("furnace-cache-test-{}", std::process::id()));
        std::fs::remove_dir_all(&root).ok();
        let ours = root.join("ours");
        std::fs::create_dir_all(&ours).unwrap();
        std::fs::set_permissions(&ours, std::fs::Permissions::from_mode(0o777)).unwrap();
        let (dir, _held) = private_dir(&ours).unwrap();
        assert_eq!(std::fs::canonicalize(&dir).unwrap(), std::fs::canonicalize(&ours).unwrap());
        assert_eq!(std::fs::metadata(&ours).unwrap().mode() & 0o777, 0o700);
        let link = root.join("link");
        std::os::unix::fs::symlink(&ours, &link).unwrap();
        assert!(private_dir(&link).unwrap_err().to_string().contains("link is refused"));
        let me = std::fs::metadata("/proc/self").unwrap().uid();
        let theirs = root.join("theirs");
        std::fs::create_dir_all(&theirs).unwrap();
        if std::os::unix::fs::chown(&theirs, Some(me + 1), None).is_ok() {
            let (dir, _held) = private_dir(&theirs).unwrap();
            let inside = theirs.join(format!("furnace-{me}"));
            assert_eq!(std::fs::canonicalize(&dir).unwrap(), std::fs::canonicalize(&inside).unwrap());
            assert_eq!(std::fs::metadata(&inside).unwrap().mode() & 0o777, 0o700);
        }
        std::fs::remove_dir_all(&root).ok();
    }

    /// Downloads stream into the cache while hashed: a body that hashes right is stored
    /// whole; one that does not is refused and leaves nothing, temporary or not.
    #[test]
    fn downloads_are_stored_only_when_they_hash_right() {
        use std::io::{Read, Write};
        let root = std::env::temp_dir().join(format!("furnace-cache-dl-{}", std::process::id()));
        std::fs::remove_dir_all(&root).ok();
        let body: Vec<u8> = (0..300_000u32).map(|i| (i * 7 % 251) as u8).collect();
        let listener = std::net::TcpListener::bind("127.0.0.1:0").unwrap();
        let url = format!("http://{}", listener.local_addr().unwrap());
        let served = body.clone();
        std::thread::spawn(move || {
            for stream in listener.incoming().take(2) {
                let mut s = stream.unwrap();
                let mut head = [0u8; 1024];
                let _ = s.read(&mut head);
                let _ = write!(
                    s,
                    "HTTP/1.1 200 OK\r\nContent-Length: {}\r\nConnection: close\r\n\r\n",
                    served.len()
                );
                let _ = s.write_all(&served);
            }
        });
        let link = HttpLink::new(&url, None, root.join("cache")).unwrap();
        let dir = link.cache_dir().unwrap();
        let err = |p: &Path, e: std::io::Error| format!("{}: {e}", p.display());
        let good = blake3::hash(&body).to_hex().to_string();
        let file = dir.join("files").join(&good);
        link.download("/v1/files/x", &file, &good, "fur.txt", &err).unwrap();
        assert_eq!(std::fs::read(&file).unwrap(), body);
        assert!(cached(&file, &good));
        let wrong = "0".repeat(64);
        let bad = dir.join("files").join(&wrong);
        let e = link.download("/v1/files/y", &bad, &wrong, "fur.txt", &err).unwrap_err();
        assert!(e.contains("fur.txt does not hash to"), "{e}");
        let left: Vec<_> =
            std::fs::read_dir(dir.join("files")).unwrap().map(|e| e.unwrap().file_name()).collect();
        assert_eq!(left, [std::ffi::OsString::from(&good)], "only the good file is kept");
        std::fs::remove_dir_all(&root).ok();
    }

    /// Review of issue 14: a cache folder removed under a running worker (a cleaner of /tmp)
    /// left it unable to load any scene until restarted: the folder it held open takes no
    /// new files. It is made again.
    #[test]
    fn a_removed_cache_folder_is_made_again() {
        let root = std::env::temp_dir().join(format!("furnace-cache-gone-{}", std::process::id()));
        std::fs::remove_dir_all(&root).ok();
        let link = HttpLink::new("http://127.0.0.1:9", None, root.join("cache")).unwrap();
        std::fs::remove_dir_all(&root).unwrap();
        let dir = link.cache_dir().unwrap();
        write_file(&dir.join("files").join("f"), b"cached").unwrap();
        assert_eq!(std::fs::read(root.join("cache/files/f")).unwrap(), b"cached");
        std::fs::remove_dir_all(&root).ok();
    }

    /// Issue 14: the cache folder was checked once and then used by its name, so in a parent
    /// other users may write (not sticky) it could be renamed and replaced by a link to
    /// another folder after the check. It is now used through the descriptor that was
    /// checked: what is written goes into the folder that was checked, wherever it is now.
    #[test]
    fn the_checked_cache_folder_is_used_even_if_its_name_is_swapped_for_a_link() {
        let root = std::env::temp_dir().join(format!("furnace-cache-swap-{}", std::process::id()));
        std::fs::remove_dir_all(&root).ok();
        let (cache, victim) = (root.join("cache"), root.join("victim"));
        std::fs::create_dir_all(&victim).unwrap();
        let (dir, _held) = private_dir(&cache).unwrap();
        std::fs::rename(&cache, root.join("moved")).unwrap();
        std::os::unix::fs::symlink(&victim, &cache).unwrap();
        write_file(&dir.join("files").join("f"), b"cached").unwrap();
        assert_eq!(std::fs::read(root.join("moved/files/f")).unwrap(), b"cached");
        assert_eq!(std::fs::read_dir(&victim).unwrap().count(), 0, "written through the link");
        std::fs::remove_dir_all(&root).ok();
    }
}
