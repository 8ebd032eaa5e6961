//! The farm's commands: `serve`, `worker`, `submit`, `status`.

use std::collections::{BTreeMap, HashMap};
use std::net::SocketAddr;
use std::path::PathBuf;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, Mutex};
use std::time::Duration;

use anyhow::{bail, Context, Result};
use clap::Args;
use furnace_core::Scene;
use furnace_proto::{ApiError, Bundle, FrameRange, JobSettings, JobSpec, JobState, JobStatus};

#[derive(Args)]
pub struct ServeArgs {
    /// Folder for the database, uploaded files and job results.
    #[arg(long, env = "FURNACE_DATA_DIR")]
    pub data_dir: PathBuf,
    /// Address to listen on.
    #[arg(long, env = "FURNACE_BIND", default_value = "127.0.0.1:8640")]
    pub bind: SocketAddr,
    /// Workers to run inside this process.
    #[arg(long, default_value_t = 0)]
    pub local_workers: usize,
    /// Threads per local worker (default: all cores shared); each keeps half its threads'
    /// worth of chunks in flight, 2 to 16.
    #[arg(long)]
    pub worker_threads: Option<usize>,
    /// Shared token for workers and clients; required unless binding to loopback.
    #[arg(long, env = "FURNACE_TOKEN")]
    pub token: Option<String>,
    /// Seconds a lease lasts without a heartbeat.
    #[arg(long, default_value_t = 30.0)]
    pub lease_seconds: f64,
    /// Connections served at once; more wait to be accepted.
    #[arg(long, default_value_t = furnace_coordinator::api::MAX_CONNECTIONS)]
    pub max_connections: usize,
    /// Seconds a client has to send a request's headers.
    #[arg(long, default_value_t = furnace_coordinator::api::HEADER_READ_TIMEOUT.as_secs_f64())]
    pub header_timeout: f64,
    /// Seconds a request may take, its body included.
    #[arg(long, default_value_t = furnace_coordinator::api::REQUEST_TIMEOUT.as_secs_f64())]
    pub request_timeout: f64,
    /// Hours (at least 1) a stored file that no job uses is kept (uploaded for a submission
    /// that never came); checked at start and every hour.
    #[arg(long, default_value_t = furnace_coordinator::api::UNUSED_FILES.as_secs_f64() / 3600.0)]
    pub unused_file_hours: f64,
    /// Megabytes of request bodies received at once, all requests together; a request waits
    /// for its share (up to half the request time limit, then 503). No body held in memory
    /// may be larger; file uploads stream to disk and hold at most 8 MB of it.
    #[arg(long, default_value_t = (furnace_coordinator::api::BODY_BUDGET >> 20) as u64)]
    pub body_budget_mb: u64,
    /// Megabytes of the largest file a submission may upload (streamed to disk).
    #[arg(long, default_value_t = furnace_coordinator::api::MAX_FILE >> 20)]
    pub max_file_mb: u64,
    /// Minutes after which a paused job with no chunk in flight is set aside: its checkpoint
    /// stored and its memory released until it is resumed or cancelled.
    #[arg(long, default_value_t = 10.0)]
    pub evict_paused_minutes: f64,
    /// Gigabytes the jobs in memory may hold together (96 bytes a pixel of each running job);
    /// a submission beyond it is refused with 503.
    #[arg(long, default_value_t = 8.0)]
    pub max_job_memory_gb: f64,
    /// Megabytes a submitted scene may take to load (textures, meshes, curves and what their
    /// loaders hold, estimated before each is read); a scene over it is refused (422). Workers
    /// have the same setting: keep theirs at least this.
    #[arg(long, default_value_t = furnace_core::FARM_SCENE_BYTES >> 20)]
    pub max_scene_memory_mb: u64,
}

#[derive(Args)]
pub struct WorkerArgs {
    /// Coordinator URL, e.g. http://127.0.0.1:8640.
    #[arg(long, env = "FURNACE_COORDINATOR")]
    pub coordinator: String,
    /// Render threads (default: all cores).
    #[arg(long)]
    pub threads: Option<usize>,
    /// Chunks rendered at once on those threads, so that chunk ends do not idle them, 1 to
    /// 256 (default: half the threads, 2 to 16). Each holds its tile's accumulation and, while
    /// idle, one lease request open at the coordinator.
    #[arg(long, value_parser = clap::value_parser!(u32).range(1..=256))]
    pub slots: Option<u32>,
    #[arg(long, env = "FURNACE_TOKEN")]
    pub token: Option<String>,
    /// Name shown in job status (default: host and process id, and in a container a random
    /// suffix).
    #[arg(long, env = "FURNACE_NAME")]
    pub name: Option<String>,
    /// Scene bundle cache, private to the user (default: $XDG_CACHE_HOME/furnace or
    /// ~/.cache/furnace).
    #[arg(long)]
    pub cache: Option<PathBuf>,
    /// Exit when the coordinator has no work instead of polling on.
    #[arg(long)]
    pub exit_when_idle: bool,
    /// Keep the Unix time of the coordinator's last answer in this file (for health checks:
    /// `furnace probe --file`).
    #[arg(long, env = "FURNACE_HEALTH_FILE")]
    pub health_file: Option<PathBuf>,
    /// Megabytes a job's scene may take to load (BVH included); a scene over it fails its
    /// chunks on this worker.
    #[arg(long, default_value_t = furnace_core::FARM_SCENE_BYTES >> 20)]
    pub max_scene_memory_mb: u64,
}

#[derive(Args)]
pub struct ProbeArgs {
    /// URL that must answer 2xx (e.g. http://127.0.0.1:8640/readyz).
    #[arg(required_unless_present = "file", conflicts_with = "file")]
    pub url: Option<String>,
    /// Instead: a worker's --health-file, which must be younger than --max-age.
    #[arg(long)]
    pub file: Option<PathBuf>,
    /// Seconds.
    #[arg(long, default_value_t = 120)]
    pub max_age: u64,
}

/// Exits 0 when the URL answers 2xx within 5 s, or the health file is fresh: for container
/// health checks, in images without curl.
pub fn probe(a: ProbeArgs) -> Result<()> {
    if let Some(file) = a.file {
        let text =
            std::fs::read_to_string(&file).with_context(|| format!("health file {}", file.display()))?;
        let at: u64 = text.trim().parse().with_context(|| format!("{}: not a Unix time", file.display()))?;
        let now = std::time::SystemTime::now().duration_since(std::time::UNIX_EPOCH)?.as_secs();
        let age = now.saturating_sub(at);
        if age > a.max_age {
            bail!("the coordinator last answered {age} s ago (more than {} s)", a.max_age);
        }
        return Ok(());
    }
    let url = a.url.unwrap_or_default();
    let http = reqwest::blocking::Client::builder().timeout(Duration::from_secs(5)).build()?;
    let r = http.get(&url).send().with_context(|| format!("GET {url}"))?;
    if !r.status().is_success() {
        bail!("GET {url}: {}", r.status());
    }
    Ok(())
}

#[derive(Args)]
pub struct SubmitArgs {
    /// Scene file (Mitsuba 3 XML); it and every file it reads are uploaded.
    pub scene: PathBuf,
    #[arg(long, default_value = "http://127.0.0.1:8640")]
    pub coordinator: String,
    #[arg(long, env = "FURNACE_TOKEN")]
    pub token: Option<String>,
    /// Samples per pixel (default: the scene's).
    #[arg(long)]
    pub spp: Option<u64>,
    /// Sample seed (default: the scene's).
    #[arg(long)]
    pub seed: Option<u64>,
    #[arg(long, default_value_t = 64)]
    pub tile: u32,
    #[arg(long, default_value_t = 64)]
    pub spp_per_chunk: u64,
    #[arg(long, default_value_t = 0)]
    pub priority: i32,
    /// Stop each tile at this estimated relative error (then --spp is the cap).
    #[arg(long)]
    pub target_rel_error: Option<f64>,
    /// Set a scene parameter, as Mitsuba's -D: `-D spp=16`.
    #[arg(short = 'D', value_name = "NAME=VALUE")]
    pub define: Vec<String>,
    /// Render frames FIRST-LAST[:STEP] as one job: frame N is the scene with `-D frame=N`,
    /// and with `####` in the scene's file name replaced by N, zero-padded (anim_####.xml).
    #[arg(long, value_name = "FIRST-LAST[:STEP]")]
    pub frames: Option<String>,
    /// Follow progress and download the result.
    #[arg(long)]
    pub wait: bool,
    /// Where --wait writes the result (an EXR, and a PNG beside it); with --frames, `####` in
    /// it takes each frame's number (default: JOB_####.exr).
    #[arg(short, long)]
    pub output: Option<PathBuf>,
}

#[derive(Args)]
pub struct StatusArgs {
    /// Job id (default: every job).
    pub job: Option<String>,
    #[arg(long, default_value = "http://127.0.0.1:8640")]
    pub coordinator: String,
    #[arg(long, env = "FURNACE_TOKEN")]
    pub token: Option<String>,
}

/// Sets `flag` on SIGTERM or SIGINT.
fn stop_on_signal(flag: Arc<AtomicBool>) {
    std::thread::spawn(move || {
        let Ok(rt) = tokio::runtime::Builder::new_current_thread().enable_all().build() else { return };
        rt.block_on(async {
            let Ok(mut term) = tokio::signal::unix::signal(tokio::signal::unix::SignalKind::terminate())
            else {
                return;
            };
            tokio::select! {
                _ = term.recv() => {}
                _ = tokio::signal::ctrl_c() => {}
            }
        });
        tracing::info!("stopping after the chunk in hand");
        flag.store(true, Ordering::SeqCst);
    });
}

pub fn serve(a: ServeArgs) -> Result<()> {
    if a.token.as_deref().is_some_and(|t| t.trim().is_empty() || t.trim() != t) {
        bail!("the token must not be empty or have spaces around it (--token or FURNACE_TOKEN)");
    }
    if !a.bind.ip().is_loopback() && a.token.is_none() {
        bail!("binding to {} (not loopback) needs a shared token: --token or FURNACE_TOKEN", a.bind);
    }
    // Local workers take the scene the coordinator loaded to check the job (restored jobs'
    // too).
    let mut coord = furnace_coordinator::Coordinator::open_with(&a.data_dir, a.local_workers > 0)
        .with_context(|| format!("cannot open data folder {}", a.data_dir.display()))?;
    coord.lease_duration = Duration::from_secs_f64(a.lease_seconds.max(0.1));
    coord.evict_paused_after = Duration::from_secs_f64(a.evict_paused_minutes.clamp(0.0, 1e6) * 60.0);
    coord.max_job_bytes = (a.max_job_memory_gb.clamp(0.0, 1e6) * 1e9) as usize;
    coord.max_scene_bytes = a.max_scene_memory_mb.saturating_mul(1 << 20);
    let mut state = furnace_coordinator::AppState::new(Arc::new(Mutex::new(coord)), a.token.clone())
        .with_body_budget((a.body_budget_mb.min(1 << 30) << 20) as usize)
        .with_max_file(a.max_file_mb.min(1 << 40) << 20)
        .with_max_connections(a.max_connections.clamp(1, u32::MAX as usize));
    state.header_timeout = Duration::from_secs_f64(a.header_timeout.clamp(0.1, 3600.0));
    state.request_timeout = Duration::from_secs_f64(a.request_timeout.clamp(0.1, 86400.0));
    if a.unused_file_hours < 1.0 {
        bail!("--unused-file-hours must be at least 1 (a submission under way needs its files)");
    }
    state.unused_files = Duration::from_secs_f64(a.unused_file_hours.min(1e6) * 3600.0);
    let rt = tokio::runtime::Builder::new_multi_thread().enable_all().build()?;
    rt.block_on(async move {
        let listener = tokio::net::TcpListener::bind(a.bind)
            .await
            .with_context(|| format!("cannot listen on {}", a.bind))?;
        let addr = listener.local_addr()?;
        // The first line on stdout is the address, for scripts and tests that bind port 0.
        println!("listening on http://{addr}");
        tracing::info!("coordinator on http://{addr}, data in {}", a.data_dir.display());
        let stop = Arc::new(AtomicBool::new(false));
        let mut locals = Vec::new();
        let link = Arc::new(furnace::local::LocalLink::new(state.coord.clone()));
        for i in 0..a.local_workers {
            let cfg = furnace_worker::WorkerConfig {
                link: link.clone(),
                threads: a.worker_threads.unwrap_or(0),
                slots: 0,
                name: format!("local-{i}"),
                poll: Duration::from_millis(100),
                stop: stop.clone(),
                exit_when_idle: false,
            };
            locals.push(std::thread::spawn(move || furnace_worker::run(cfg)));
        }
        let shutdown = async {
            let mut term = tokio::signal::unix::signal(tokio::signal::unix::SignalKind::terminate())
                .expect("SIGTERM handler");
            tokio::select! {
                _ = term.recv() => {}
                _ = tokio::signal::ctrl_c() => {}
            }
        };
        furnace_coordinator::run(listener, state, shutdown).await?;
        stop.store(true, Ordering::SeqCst);
        Ok::<_, anyhow::Error>(())
    })
}

pub fn worker(a: WorkerArgs) -> Result<()> {
    let stop = Arc::new(AtomicBool::new(false));
    stop_on_signal(stop.clone());
    let host = std::fs::read_to_string("/etc/hostname").map(|s| s.trim().to_string()).unwrap_or_default();
    let cache = a.cache.unwrap_or_else(furnace_worker::default_cache_dir);
    let mut link = furnace_worker::HttpLink::new(&a.coordinator, a.token, cache)?;
    link.health_file = a.health_file;
    link.max_scene_bytes = a.max_scene_memory_mb.saturating_mul(1 << 20);
    let cfg = furnace_worker::WorkerConfig {
        link: Arc::new(link),
        threads: a.threads.unwrap_or(0),
        slots: a.slots.unwrap_or(0) as usize,
        name: a.name.unwrap_or_else(|| default_worker_name(&host)),
        // Lease requests wait at the coordinator for work (long polling); this is the pause
        // between two of them.
        poll: Duration::from_millis(100),
        stop,
        exit_when_idle: a.exit_when_idle,
    };
    let n = furnace_worker::run(cfg)?;
    tracing::info!("worker stopped after {n} chunks");
    Ok(())
}

/// Host name and process id; in a container (process 1), where workers on the host's network
/// share the host's name, a few random hex digits too, so that two are never one worker to
/// the coordinator.
fn default_worker_name(host: &str) -> String {
    let pid = std::process::id();
    if pid != 1 {
        return format!("{host}-{pid}");
    }
    use std::hash::{BuildHasher, Hasher};
    // The standard library's randomly keyed hasher: a random number without a crate.
    let salt = std::collections::hash_map::RandomState::new().build_hasher().finish();
    format!("{host}-1-{:06x}", salt & 0xff_ffff)
}

struct Api {
    base: String,
    token: Option<String>,
    http: reqwest::blocking::Client,
}

impl Api {
    fn new(base: &str, token: Option<String>) -> Result<Api> {
        let http = reqwest::blocking::Client::builder().timeout(Duration::from_secs(300)).build()?;
        Ok(Api { base: base.trim_end_matches('/').to_string(), token, http })
    }
    fn req(&self, method: reqwest::Method, path: &str) -> reqwest::blocking::RequestBuilder {
        let r = self.http.request(method, format!("{}{path}", self.base));
        match &self.token {
            Some(t) => r.bearer_auth(t),
            None => r,
        }
    }
    fn check(r: reqwest::blocking::Response) -> Result<reqwest::blocking::Response> {
        if r.status().is_success() {
            return Ok(r);
        }
        let status = r.status();
        let msg = r.json::<ApiError>().map(|e| e.error).unwrap_or_default();
        bail!("coordinator answered {status}: {msg}")
    }
    fn status(&self, id: &str) -> Result<JobStatus> {
        let r = self.req(reqwest::Method::GET, &format!("/v1/jobs/{id}")).send()?;
        Ok(Self::check(r)?.json()?)
    }
}

/// The bundle of a submission: the scene's, or for a frame range the union of every frame's
/// (each frame's scene loaded with `frame` defined, its `####` file name filled in), with the
/// scene's path as given (`####` and all). Returns the bundle, its files on this machine,
/// and the first frame's scene.
fn bundle_of(
    scene: &std::path::Path,
    defines: &[(String, String)],
    frames: Option<FrameRange>,
) -> Result<(Bundle, BTreeMap<String, PathBuf>, Scene)> {
    // Loaded to check it and to find its files: no BVH (the workers build their own).
    let assets = Some(Arc::new(furnace_core::scene::assets::AssetCache::new()));
    let limits = furnace_core::LoadLimits { accel: false, assets, ..Default::default() };
    let Some(range) = frames else {
        let loaded = Scene::load_with(scene, defines, &limits)?;
        let (bundle, files) = Bundle::of_scene(scene, &loaded).map_err(anyhow::Error::msg)?;
        return Ok((bundle, files.into_iter().collect(), loaded));
    };
    let pattern = scene.to_string_lossy().to_string();
    let name = scene.file_name().map(|n| n.to_string_lossy().to_string()).unwrap_or_default();
    if scene.parent().is_some_and(|d| d.to_string_lossy().contains('#')) {
        bail!(
            "{pattern}: '#' may stand for the frame number in the scene's file name only, not in its folder"
        );
    }
    let mut union = Bundle { scene: String::new(), files: BTreeMap::new() };
    let mut local = BTreeMap::new();
    let mut first = None;
    // A file the frames share is hashed once (known by its path, length and modification time:
    // one changed meanwhile is hashed again, and refused below).
    let mut hashed: HashMap<(PathBuf, u64, Option<std::time::SystemTime>), String> = HashMap::new();
    let mut hash = |p: &std::path::Path| -> std::io::Result<String> {
        let m = std::fs::metadata(p)?;
        let key = (p.to_path_buf(), m.len(), m.modified().ok());
        if let Some(h) = hashed.get(&key) {
            return Ok(h.clone());
        }
        let h = furnace_proto::hash_file(p)?;
        hashed.insert(key, h.clone());
        Ok(h)
    };
    let bar = indicatif::ProgressBar::new(range.count());
    bar.set_style(
        indicatif::ProgressStyle::with_template("checking frames {bar:40} {pos}/{len}")
            .expect("static progress template"),
    );
    for n in range.numbers() {
        let path = PathBuf::from(furnace_proto::frame_path(&pattern, n));
        let mut defs = defines.to_vec();
        defs.retain(|(k, _)| k != "frame");
        defs.push(("frame".into(), n.to_string()));
        let loaded = Scene::load_with(&path, &defs, &limits).with_context(|| format!("frame {n}"))?;
        let (bundle, files) =
            Bundle::of_scene_hashing(&path, &loaded, &mut hash).map_err(anyhow::Error::msg)?;
        for (rel, file) in files {
            let hash = &bundle.files[&rel];
            if union.files.insert(rel.clone(), hash.clone()).is_some_and(|h| h != *hash) {
                bail!("{}: the file changed while the frames were read", file.display());
            }
            local.insert(rel, file);
        }
        if first.is_none() {
            // The scene's path in the bundle, with its pattern.
            let dir = bundle.scene.rsplit_once('/').map(|(d, _)| format!("{d}/")).unwrap_or_default();
            union.scene = format!("{dir}{name}");
            first = Some(loaded);
        }
        bar.inc(1);
    }
    bar.finish_and_clear();
    Ok((union, local, first.expect("a frame range has a frame")))
}

pub fn submit(a: SubmitArgs) -> Result<()> {
    let api = Api::new(&a.coordinator, a.token.clone())?;
    let defines = crate::parse_defines(&a.define)?;
    let frames = a.frames.as_deref().map(FrameRange::parse).transpose().map_err(anyhow::Error::msg)?;
    if let (Some(range), Some(out)) = (frames, &a.output) {
        // Checked before anything is uploaded: a bad name found after the render loses it.
        check_frame_output(out, range.count())?;
    }
    let (bundle, files, scene) = bundle_of(&a.scene, &defines, frames)?;
    for (rel, path) in &files {
        let hash = &bundle.files[rel];
        let head = api.req(reqwest::Method::HEAD, &format!("/v1/files/{hash}")).send()?;
        if head.status().is_success() {
            continue;
        }
        // Streamed from the file, never whole in memory.
        let file = std::fs::File::open(path).with_context(|| format!("cannot read {}", path.display()))?;
        let len = file.metadata().with_context(|| format!("cannot read {}", path.display()))?.len();
        let body = reqwest::blocking::Body::sized(file, len);
        Api::check(api.req(reqwest::Method::PUT, &format!("/v1/files/{hash}")).body(body).send()?)
            .with_context(|| format!("uploading {rel}"))?;
    }
    let settings = JobSettings {
        width: 0,
        height: 0,
        spp: a.spp.unwrap_or(scene.spp as u64),
        tile_size: a.tile,
        spp_per_chunk: a.spp_per_chunk,
        seed: a.seed.unwrap_or(scene.seed),
        priority: a.priority,
        target_rel_error: a.target_rel_error,
    };
    let spec = JobSpec { defines: defines.into_iter().collect(), frames, ..JobSpec::new(bundle, settings) };
    let key = blake3::hash(serde_json::to_string(&spec)?.as_bytes()).to_hex()[..32].to_string();
    let key = format!("{key}-{}", std::process::id());
    let r = api.req(reqwest::Method::POST, "/v1/jobs").header("Idempotency-Key", key).json(&spec).send()?;
    let id = Api::check(r)?.json::<furnace_proto::Submitted>()?.id;
    println!("{id}");
    if !a.wait {
        return Ok(());
    }
    let bar = indicatif::ProgressBar::new(1);
    bar.set_style(
        indicatif::ProgressStyle::with_template(
            "{bar:40} {percent:>3}%  {human_pos}/{human_len} samples  {msg}",
        )
        .expect("static progress template"),
    );
    loop {
        let st = api.status(&id)?;
        bar.set_length(st.samples_total);
        bar.set_position(st.samples_done);
        let mut error = st.estimated_rel_mse.map(|e| format!(", error {:.3}", e.sqrt())).unwrap_or_default();
        if !st.frames.is_empty() {
            let done = st.frames.iter().filter(|f| f.state == JobState::Done).count();
            error = format!(", {done}/{} frames{error}", st.frames.len());
        }
        bar.set_message(match st.eta_seconds {
            Some(e) => format!("{:.0} samples/s, ETA {e:.0}s{error}", st.samples_per_second),
            None => error,
        });
        // Often near the end, rarely in a long job: a twentieth of the time left, 0.1 to 2 s.
        let pause = st.eta_seconds.map_or(0.25, |e| (e / 20.0).clamp(0.1, 2.0));
        match st.state {
            JobState::Done => break,
            JobState::Cancelled => bail!("job {id} was cancelled"),
            _ => std::thread::sleep(Duration::from_secs_f64(pause)),
        }
    }
    bar.finish_and_clear();
    let Some(range) = frames else {
        let out = a.output.unwrap_or_else(|| PathBuf::from(format!("{id}.exr")));
        return download(&api, &format!("/v1/jobs/{id}/result.exr"), &out);
    };
    let out = a.output.unwrap_or_else(|| PathBuf::from(format!("{id}_####.exr")));
    let pattern = out.to_string_lossy().to_string();
    for n in range.numbers() {
        let out = PathBuf::from(furnace_proto::frame_path(&pattern, n));
        download(&api, &format!("/v1/jobs/{id}/frames/{n}/result.exr"), &out)?;
    }
    Ok(())
}

/// `-o` for a frame range of `count` frames: `#`s in the file name, before its extension (the
/// PNG beside each EXR takes the same name), none in its folder.
fn check_frame_output(out: &std::path::Path, count: u64) -> Result<()> {
    let shown = out.display();
    if out.parent().is_some_and(|d| d.to_string_lossy().contains('#')) {
        bail!("-o {shown}: '#' may stand for the frame number in the file name only, not in its folder");
    }
    let stem = out.file_stem().map(|s| s.to_string_lossy().to_string()).unwrap_or_default();
    let name = out.file_name().map(|s| s.to_string_lossy().to_string()).unwrap_or_default();
    if name.contains('#') && !stem.contains('#') {
        bail!("-o {shown}: the frame number's '#'s must come before the extension (out_####.exr)");
    }
    if count > 1 && !stem.contains('#') {
        bail!("-o {shown}: a frame range needs '#'s in the output name for the frame number (out_####.exr)");
    }
    Ok(())
}

/// Writes the EXR at `path` to `out`, and its PNG (exposure 0) beside it, as `furnace render`
/// does.
fn download(api: &Api, path: &str, out: &std::path::Path) -> Result<()> {
    let bytes = Api::check(api.req(reqwest::Method::GET, path).send()?)?.bytes()?;
    std::fs::write(out, &bytes).with_context(|| format!("cannot write {}", out.display()))?;
    let png = out.with_extension("png");
    let image =
        furnace_core::Image::read_exr(out).with_context(|| format!("cannot read {}", out.display()))?;
    image.write_png(&png, 0.0).with_context(|| format!("cannot write {}", png.display()))?;
    eprintln!("wrote {} and {}", out.display(), png.display());
    Ok(())
}

pub fn status(a: StatusArgs) -> Result<()> {
    let api = Api::new(&a.coordinator, a.token)?;
    let all: Vec<JobStatus> = match &a.job {
        Some(id) => vec![api.status(id)?],
        None => {
            // A page at a time.
            let mut all: Vec<JobStatus> = Vec::new();
            loop {
                let after = all.last().map(|s| format!("&after={}", s.id)).unwrap_or_default();
                let path = format!("/v1/jobs?limit={}{after}", furnace_coordinator::api::MAX_LIST);
                let page: Vec<JobStatus> =
                    Api::check(api.req(reqwest::Method::GET, &path).send()?)?.json()?;
                let last = page.len() < furnace_coordinator::api::MAX_LIST;
                all.extend(page);
                if last {
                    break all;
                }
            }
        }
    };
    for s in all {
        println!(
            "{}  {:?}  {}/{} chunks, {}/{} samples, {:.0} samples/s{}{}",
            s.id,
            s.state,
            s.chunks_done,
            s.chunks_total,
            s.samples_done,
            s.samples_total,
            s.samples_per_second,
            s.eta_seconds.map(|e| format!(", ETA {e:.0}s")).unwrap_or_default(),
            if s.errors.is_empty() { String::new() } else { format!(", {} errors", s.errors.len()) }
        );
    }
    Ok(())
}
