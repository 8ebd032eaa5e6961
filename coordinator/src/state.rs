//! The coordinator: its jobs (each a [`Job`] core), the scheduler that hands out their chunks,
//! the registry of workers, and the functions that take slow work (loading scenes, decoding,
//! storing) out of its lock.
//!
//! Durability, with a durable [`Store`]: an accepted partial is stored (temporary file, fsync,
//! rename) before the upload is acknowledged; the merged image lives in memory and in a
//! checkpoint (the merged accumulation plus the set of chunks in it), written every 256 merges
//! (and `checkpoint_interval`) and at the end, after which the partials it holds are dropped.
//! After a crash, a job's image is its checkpoint plus every partial not in it: nothing
//! acknowledged is lost and nothing is merged twice. Leases live in memory: after a restart
//! every unfinished chunk is pending again, under epochs above all earlier ones.

use std::collections::{BTreeMap, BTreeSet, HashMap, HashSet};
use std::path::{Path, PathBuf};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use furnace_core::{Accum, LoadLimits, Scene};
use furnace_proto::{
    chunk_plan, decode_chunk, encode_chunk, frame_path, Bundle, FrameOf, FrameStatus, JobSettings, JobSpec,
    JobState, JobStatus, Lease, RenderStats,
};

pub use crate::error::CoordError;
use crate::job::{ChunkState, Job, Snapshot};
pub use crate::job::{MAX_ERRORS, MAX_ERROR_BYTES};
use crate::store::{DiskStore, JobRow, MemStore, RowOp, Store};

/// The hash of a submitted spec, as submitted (before the scene fills in its defaults).
fn request_hash(spec: &JobSpec) -> String {
    blake3::hash(&serde_json::to_vec(spec).unwrap_or_default()).to_hex().to_string()
}

/// Failures of one worker on one job after which it gets no more of that job's chunks.
pub const MAX_FAILURES_PER_WORKER: u32 = 3;
/// Workers a job's status lists (the most recent).
pub const MAX_JOB_WORKERS: usize = 1000;
/// Most frames of one frame-range job started and not yet finished at once.
pub const MAX_OPEN_FRAMES: usize = 3;

/// Bytes the images of a frame range of `frames` frames, each of `image` bytes, hold at once.
fn open_images_bytes(image: usize, frames: usize) -> usize {
    image.saturating_mul(frames.min(MAX_OPEN_FRAMES))
}

/// What the coordinator remembers of a worker: it exists only in the requests it makes.
struct WorkerSeen {
    last_seen: Instant,
    chunks_done: u64,
    samples_done: u64,
}

/// A worker without leases is idle while it has been heard from within a lease duration plus
/// this (workers ask for work every few seconds), and lost after.
const WORKER_SLACK: Duration = Duration::from_secs(5);
/// Workers silent for this long are forgotten.
const FORGET_WORKER: Duration = Duration::from_secs(3600);

pub struct Coordinator {
    store: Arc<dyn Store>,
    jobs: BTreeMap<String, Job>,
    next_epoch: u64,
    pub lease_duration: Duration,
    /// Largest decompressed partial accepted (bytes).
    pub max_partial: usize,
    /// Keep each job's loaded scene for workers in this process.
    pub keep_scenes: bool,
    /// Time between tries of a checkpoint that failed.
    pub checkpoint_retry: Duration,
    /// A paused job is set aside (its checkpoint stored, its memory released) once paused this
    /// long with no lease in flight; resuming or cancelling it loads it again.
    pub evict_paused_after: Duration,
    /// Most bytes the jobs in memory may hold together (accumulations, plans, chunk states);
    /// a submission beyond it is refused (503). Jobs restored at start are not refused.
    pub max_job_bytes: usize,
    /// Least time between two checkpoints of a job. A checkpoint encodes the job's whole
    /// accumulation (about a second for 1920 x 1080 here); between them, a restart replays the
    /// stored partials.
    pub checkpoint_interval: Duration,
    /// Most memory a submitted scene may take to load (estimated as it loads; see
    /// [`LoadLimits`]); over it, the submission is refused (422).
    pub max_scene_bytes: u64,
    workers: BTreeMap<String, WorkerSeen>,
    /// When the registry was last swept of workers silent for [`FORGET_WORKER`].
    pruned: Option<Instant>,
    /// Idempotency keys: the job each names and the hash of the request it came with (kept
    /// here, so that a submission reads no database under the lock).
    keys: HashMap<String, (String, Option<String>)>,
    /// Jobs whose row changed since the store last wrote it ([`sync_rows`]).
    dirty: BTreeSet<String>,
    /// New jobs whose row is not stored yet: their idempotency key and request hash.
    unwritten: HashMap<String, (Option<String>, String)>,
    /// Jobs with a row that could not be restored at start (they can still be deleted).
    left_out: HashSet<String>,
    /// Held by whoever writes rows: one batch at a time, each taken when its writer starts.
    row_writer: Arc<Mutex<()>>,
    /// Bundles of submissions whose scenes are loading (by ticket): a job deleted meanwhile
    /// leaves their files.
    loading: BTreeMap<u64, Bundle>,
    tickets: u64,
    /// Frame-range jobs: each one's frames in order, as (frame number, the frame's own job).
    /// The frames are jobs like any other (stored, leased, merged, restored alike); their
    /// specs name the job they belong to, from which this is rebuilt at start.
    groups: BTreeMap<String, Vec<(u32, String)>>,
    /// Held while a job's scene is loaded for workers in this process ([`load_scene`]).
    scene_loads: Arc<Mutex<()>>,
}

fn now_secs() -> u64 {
    std::time::SystemTime::now().duration_since(std::time::UNIX_EPOCH).map(|d| d.as_secs()).unwrap_or(0)
}

/// A job's image: developed from its accumulation in memory, or a finished job's result file.
pub enum Picture {
    Developed(furnace_core::Image),
    File(PathBuf),
    /// A job set aside: its stored checkpoint, developed (black before any chunk is merged).
    Checkpoint {
        store: Arc<dyn Store>,
        job: String,
        width: u32,
        height: u32,
    },
}

impl Picture {
    /// The image, reading the file if need be (call it without the coordinator's lock).
    pub fn image(self) -> Result<furnace_core::Image, CoordError> {
        match self {
            Picture::Developed(img) => Ok(img),
            Picture::File(path) => furnace_core::Image::read_exr(&path)
                .map_err(|e| CoordError::Internal(format!("{}: {e}", path.display()))),
            Picture::Checkpoint { store, job, width, height } => match store.checkpoint(&job) {
                None => Ok(Accum::new(0, 0, width, height).develop()),
                Some(bytes) => decode_checkpoint(&bytes, furnace_proto::partial_size_limit(width, height))
                    .map(|(_, _, _, acc, _)| acc.develop())
                    .map_err(|e| CoordError::Internal(format!("checkpoint of job {job}: {e}"))),
            },
        }
    }
}

/// What loading a job's scene needs of the coordinator, taken out of it so that scenes are
/// loaded, validated and planned without its lock.
#[derive(Clone)]
struct Loader {
    store: Arc<dyn Store>,
    keep_scenes: bool,
    /// Most memory a scene may take to load.
    max_scene_bytes: u64,
    /// Largest decompressed partial accepted: no chunk may need more.
    max_partial: usize,
    /// Most memory the coordinator's jobs may hold (a frame range's frames are weighed before
    /// they are all made).
    max_job_bytes: usize,
    /// Files parsed by the loads before (the frames of one submission share theirs).
    assets: Option<Arc<furnace_core::scene::assets::AssetCache>>,
}

impl Loader {
    /// The jobs of a submitted spec (its id and one job, or a job per frame of a frame range):
    /// its bundle laid out, its scenes loaded and checked (given up at `deadline`).
    fn submitted(
        &self,
        spec: JobSpec,
        key: Option<&str>,
        deadline: Option<Instant>,
    ) -> Result<(String, Vec<Job>), CoordError> {
        static SUBMISSIONS: std::sync::atomic::AtomicU64 = std::sync::atomic::AtomicU64::new(0);
        let created = now_secs();
        let n = SUBMISSIONS.fetch_add(1, std::sync::atomic::Ordering::Relaxed);
        let nanos = std::time::SystemTime::now().duration_since(std::time::UNIX_EPOCH).map(|d| d.as_nanos());
        let seed = format!("{}-{nanos:?}-{key:?}-{n}-{}", spec.bundle.hash(), std::process::id());
        let id = blake3::hash(seed.as_bytes()).to_hex()[..16].to_string();
        if spec.frame_of.is_some() {
            return Err(CoordError::Invalid(
                "frame_of is the coordinator's: submit a frame range with \"frames\" instead".into(),
            ));
        }
        let Some(range) = spec.frames else {
            return Ok((id.clone(), vec![self.new_job(id, spec, JobState::Queued, created, deadline)?]));
        };
        range.check().map_err(CoordError::Invalid)?;
        // Every frame is loaded and checked now, each file the frames share parsed once; only
        // the first keeps its scene (workers in this process load the others when they reach
        // them) and its BVH.
        let assets = Some(Arc::new(furnace_core::scene::assets::AssetCache::new()));
        let first = Loader { assets: assets.clone(), ..self.clone() };
        let later = Loader { keep_scenes: false, assets, ..self.clone() };
        // With `####` in the scene's path, a frame's bundle holds its own scene file and what
        // the frames share, not the other frames' scene files.
        let scenes: HashSet<String> = range.numbers().map(|n| frame_path(&spec.bundle.scene, n)).collect();
        let mut jobs: Vec<Job> = Vec::new();
        for n in range.numbers() {
            let mut defines = spec.defines.clone();
            defines.insert("frame".into(), n.to_string());
            let scene = frame_path(&spec.bundle.scene, n);
            let files = spec
                .bundle
                .files
                .iter()
                .filter(|(p, _)| **p == scene || !scenes.contains(*p))
                .map(|(p, h)| (p.clone(), h.clone()))
                .collect();
            let bundle = Bundle { scene, files };
            let frame = JobSpec {
                bundle,
                settings: spec.settings.clone(),
                defines,
                frames: None,
                frame_of: Some(FrameOf { job: id.clone(), frame: n }),
            };
            let loader = if jobs.is_empty() { &first } else { &later };
            let within = |e: CoordError| e.within(&format!("frame {n}"));
            if deadline.is_some_and(|d| Instant::now() > d) {
                return Err(within(CoordError::TooLarge("the request's time ran out".into())));
            }
            let job = loader
                .new_job(format!("{id}-{n}"), frame, JobState::Queued, created, deadline)
                .map_err(within)?;
            if jobs.is_empty() {
                // Every frame holds what the first does (its chunk plan; at most
                // MAX_OPEN_FRAMES hold an image at once): a range too large is refused before the others are made.
                let frames = range.count() as usize;
                let need =
                    job.held_bytes().saturating_mul(frames) + open_images_bytes(job.image_bytes(), frames);
                if need > self.max_job_bytes {
                    return Err(CoordError::TooLarge(format!(
                        "the job's {} frames would hold {:.2} GB of chunk plans and images, more than the coordinator's limit of {:.2} GB (--max-job-memory-gb): fewer frames, more spp_per_chunk or a larger tile_size",
                        range.count(),
                        need as f64 / 1e9,
                        self.max_job_bytes as f64 / 1e9
                    )));
                }
            }
            if let Some(first) = jobs.first() {
                let (a, b) = (&first.spec.settings, &job.spec.settings);
                if (a.width, a.height, a.spp) != (b.width, b.height, b.spp) {
                    return Err(within(CoordError::Unrenderable(format!(
                        "its film is {}x{} at {} spp, frame {}'s {}x{} at {} spp: every frame of a job renders alike",
                        b.width, b.height, b.spp, range.first, a.width, a.height, a.spp
                    ))));
                }
            }
            jobs.push(job);
        }
        if let Some(assets) = &first.assets {
            let (hits, misses) = assets.counts();
            tracing::info!(job = %id, frames = jobs.len(), hits, misses, "frames loaded and checked (files parsed: misses; reused: hits)");
        }
        Ok((id, jobs))
    }

    /// Loads the bundle's scene from where the store lays it out; errors name files by their
    /// bundle paths, the client's own, not by this host's.
    fn load_bundle(
        &self,
        b: &Bundle,
        defines: &BTreeMap<String, String>,
        deadline: Option<Instant>,
    ) -> Result<Scene, CoordError> {
        b.validate().map_err(CoordError::Invalid)?;
        // The BVH only for workers in this process: checking and planning need none.
        let limits = LoadLimits {
            max_bytes: self.max_scene_bytes,
            deadline,
            accel: self.keep_scenes,
            assets: self.assets.clone(),
        };
        let defines: Vec<(String, String)> = defines.iter().map(|(k, v)| (k.clone(), v.clone())).collect();
        self.store.load_bundle(b, &|dir: &Path| {
            Scene::load_with(&dir.join(&b.scene), &defines, &limits).map_err(|e| {
                let inside = format!("{}/", dir.display());
                CoordError::Unrenderable(format!(
                    "the scene cannot be rendered: {}",
                    e.to_string().replace(&inside, "")
                ))
            })
        })
    }

    fn new_job(
        &self,
        id: String,
        spec: JobSpec,
        state: JobState,
        created: u64,
        deadline: Option<Instant>,
    ) -> Result<Job, CoordError> {
        // What the load freed (the scene too, unless kept) goes back to the system: the
        // allocator would keep it (a PLY loader's many small blocks, across threads), and loads
        // one after another would add up.
        struct Trim;
        impl Drop for Trim {
            fn drop(&mut self) {
                #[cfg(all(target_os = "linux", target_env = "gnu"))]
                // SAFETY: malloc_trim only returns free memory to the system.
                unsafe {
                    libc::malloc_trim(0);
                }
            }
        }
        let _trim = Trim;
        let scene = self.load_bundle(&spec.bundle, &spec.defines, deadline)?;
        self.job_from_scene(id, spec, state, created, Arc::new(scene))
    }

    fn job_from_scene(
        &self,
        id: String,
        mut spec: JobSpec,
        state: JobState,
        created: u64,
        scene: Arc<Scene>,
    ) -> Result<Job, CoordError> {
        let s = &mut spec.settings;
        let (w, h) = (scene.film.crop_width, scene.film.crop_height);
        if s.width == 0 && s.height == 0 {
            (s.width, s.height) = (w, h);
        }
        if (s.width, s.height) != (w, h) {
            return Err(CoordError::Unrenderable(format!(
                "job size {}x{} differs from the scene's film {w}x{h}",
                s.width, s.height
            )));
        }
        if s.spp == 0 {
            s.spp = scene.spp as u64;
        }
        s.check_limits().map_err(CoordError::Unrenderable)?;
        if let Some(t) = s.target_rel_error {
            if !(t.is_finite() && t > 0.0) {
                return Err(CoordError::Invalid(format!("target_rel_error must be positive, got {t}")));
            }
            if s.spp_per_chunk < 2 {
                return Err(CoordError::Invalid(
                    "a noise-target job needs spp_per_chunk >= 2 (error is estimated from each chunk's samples)"
                        .into(),
                ));
            }
        }
        // A chunk's partial (its tile and the filter's margin) must fit in an upload.
        let margin = scene.film.filter.margin();
        let side = |n: u32| (s.tile_size.saturating_add(margin.saturating_mul(2))).min(n);
        let need = furnace_proto::partial_size_limit(side(s.width), side(s.height));
        if need > self.max_partial {
            return Err(CoordError::Unrenderable(format!(
                "a chunk's partial would take {need} bytes (tile_size {} plus the filter's margin of {margin} px), more than the {} an upload may hold: use a smaller tile_size",
                s.tile_size, self.max_partial
            )));
        }
        let plan = chunk_plan(s);
        let n = plan.len();
        // Noise-target jobs hand out a tile's next pass only once its last one is judged.
        let first = if s.target_rel_error.is_some() { (s.tiles() as usize).min(n) } else { n };
        // Each tile's sum of its passes' estimates, for noise-target jobs.
        let sums = if s.target_rel_error.is_some() { s.tiles() as usize } else { 0 };
        // The image is made on the first merge (see `Job::accum_mut`).
        let mut job = Job::new(id, spec, state, created, plan, Accum::new(0, 0, 0, 0));
        job.queue = (0..first as u32).collect();
        job.tile_sum = vec![0.0; sums];
        job.margin = scene.film.filter.margin();
        job.render_plan = scene.describe().to_string();
        job.scene = self.keep_scenes.then_some(scene);
        Ok(job)
    }

    /// Rebuilds a job from its stored checkpoint plus every stored partial not in it (after a
    /// restart, or when a job set aside is resumed); a
    /// stored file that cannot be used is set aside and its chunks render again.
    fn restore(&self, max_partial: usize, row: JobRow) -> Result<Job, CoordError> {
        // A job accepted once is not refused now for the memory its scene takes (the limit may
        // have been lowered since).
        // A frame of a frame-range job comes back without its scene: workers in this process
        // load it when they reach the frame (`load_scene`), so a restart does not hold every
        // frame's scene at once.
        let keep_scenes = self.keep_scenes && row.spec.frame_of.is_none();
        let unlimited = Loader { max_scene_bytes: u64::MAX, keep_scenes, ..self.clone() };
        let mut job = unlimited.new_job(row.id, row.spec, row.state, row.created, None)?;
        let id = job.id.clone();
        if let Some(bytes) = self.store.checkpoint(&id) {
            let n = job.plan.len();
            let (w, h) = (job.spec.settings.width, job.spec.settings.height);
            let limit = furnace_proto::partial_size_limit(w, h);
            let checked = decode_checkpoint(&bytes, limit).and_then(|(ids, skipped, sums, acc, stats)| {
                if (acc.x0, acc.y0, acc.width, acc.height) != (0, 0, w, h) {
                    return Err(format!("it covers {}x{}, the job {w}x{h}", acc.width, acc.height));
                }
                if let Some(c) = ids.iter().chain(&skipped).find(|&&c| c as usize >= n) {
                    return Err(format!("it names chunk {c} of {n}"));
                }
                let merged: HashSet<u32> = ids.iter().copied().collect();
                match skipped.iter().find(|c| merged.contains(c)) {
                    Some(c) => Err(format!("it has chunk {c} both merged and skipped")),
                    None => Ok((ids, skipped, sums, acc, stats)),
                }
            });
            match checked {
                Ok((ids, skipped, sums, acc, stats)) => {
                    // The tiles' sums of their checkpointed passes' estimates; a checkpoint
                    // without them (written before they were stored) leaves the tiles it has
                    // passes of unjudged (NaN: never skipped early, so never fewer samples).
                    let tiles = job.tile_sum.len();
                    if sums.len() == tiles {
                        job.tile_sum = sums.iter().map(|&b| f64::from_bits(b)).collect();
                    } else if tiles > 0 {
                        for &c in &ids {
                            job.tile_sum[c as usize % tiles] = f64::NAN;
                        }
                    }
                    job.accum = Arc::new(acc);
                    job.stats = stats.unwrap_or_default();
                    job.merged = ids.iter().copied().collect();
                    job.skipped = skipped.into_iter().collect();
                    job.checkpointed = job.merged.clone();
                }
                Err(e) => {
                    let name = self.store.quarantine(&id, None);
                    job.quarantined(&name, &e);
                }
            }
        }
        // A noise-target tile's passes are judged one after another (`Job::follow_up`): a pass
        // whose previous one is not merged (its stored partial was unusable) renders again
        // after it instead. (Stored partials come in chunk order, so a tile's in pass order.)
        let passes_of = job.spec.settings.target_rel_error.map(|_| job.spec.settings.tiles());
        for chunk in self.store.partials(&id) {
            let waits = passes_of.is_some_and(|n| chunk >= n && !job.merged.contains(&(chunk - n)));
            if job.merged.contains(&chunk) || chunk as usize >= job.plan.len() || waits {
                self.store.drop_partial(&id, chunk);
                continue;
            }
            let acc = match self
                .store
                .partial(&id, chunk)
                .and_then(|bytes| decode_chunk(&bytes, max_partial).map_err(|e| e.to_string()))
                .and_then(|(acc, stats)| job.fits(chunk, &acc).map(|_| (acc, stats)))
            {
                Ok((acc, stats)) => {
                    if let Some(s) = stats {
                        job.stats.merge(&s);
                    }
                    acc
                }
                Err(e) => {
                    let name = self.store.quarantine(&id, Some(chunk));
                    job.quarantined(&name, &e);
                    continue;
                }
            };
            job.accum_mut().merge(&acc);
            job.merged.insert(chunk);
            job.follow_up(chunk, &acc);
        }
        for &c in &job.merged {
            job.chunks[c as usize] = ChunkState::Done;
            job.samples_done += job.plan[c as usize].region.samples();
        }
        for &c in &job.skipped {
            job.chunks[c as usize] = ChunkState::Skipped;
        }
        if job.spec.settings.target_rel_error.is_some() {
            // Each tile's next pass, if its earlier passes are all merged and it is not skipped.
            let n = job.spec.settings.tiles();
            job.queue = (0..n.min(job.plan.len() as u32))
                .filter_map(|t| {
                    (t..job.plan.len() as u32).step_by(n as usize).find(|c| !job.merged.contains(c))
                })
                .filter(|c| !job.skipped.contains(c))
                .collect();
        } else {
            job.queue.retain(|c| !job.merged.contains(c));
        }
        Ok(job)
    }
}

impl Coordinator {
    /// Opens (or creates) the data directory and resumes every unfinished job.
    pub fn open(data: &Path) -> Result<Coordinator, CoordError> {
        Coordinator::open_with(data, false)
    }

    /// [`Coordinator::open`], keeping each job's scene (restored ones too) for workers in
    /// this process with `keep_scenes`.
    pub fn open_with(data: &Path, keep_scenes: bool) -> Result<Coordinator, CoordError> {
        Coordinator::restored(Arc::new(DiskStore::open(data)?), keep_scenes)
    }

    /// A coordinator that stores nothing: the one `furnace render` runs in its own process.
    /// Jobs are submitted with [`Coordinator::submit_scene`]; everything lives in memory.
    pub fn ephemeral() -> Result<Coordinator, CoordError> {
        let mut c = Coordinator::with_store(Arc::new(MemStore::new()))?;
        c.keep_scenes = true;
        Ok(c)
    }

    /// A coordinator over `store`, with every job the store holds restored: finished ones as
    /// their final status, the others from their checkpoint and stored partials.
    pub fn with_store(store: Arc<dyn Store>) -> Result<Coordinator, CoordError> {
        Coordinator::restored(store, false)
    }

    fn restored(store: Arc<dyn Store>, keep_scenes: bool) -> Result<Coordinator, CoordError> {
        // Epochs after a restart start above every epoch handed out before.
        let boot = store.boot()?;
        let mut c = Coordinator {
            store,
            jobs: BTreeMap::new(),
            next_epoch: boot << 32,
            lease_duration: Duration::from_secs(30),
            max_partial: 256 << 20,
            keep_scenes,
            checkpoint_retry: Duration::from_secs(5),
            checkpoint_interval: Duration::from_secs(10),
            evict_paused_after: Duration::from_secs(600),
            max_job_bytes: 8 << 30,
            max_scene_bytes: furnace_core::FARM_SCENE_BYTES,
            workers: BTreeMap::new(),
            pruned: None,
            keys: HashMap::new(),
            dirty: BTreeSet::new(),
            unwritten: HashMap::new(),
            left_out: HashSet::new(),
            row_writer: Arc::new(Mutex::new(())),
            loading: BTreeMap::new(),
            tickets: 0,
            groups: BTreeMap::new(),
            scene_loads: Arc::new(Mutex::new(())),
        };
        for (key, id, request) in c.store.keys()? {
            c.keys.insert(key, (id, request));
        }
        // The frames of a frame-range job share their parsed files while they are restored.
        let restorer =
            Loader { assets: Some(Arc::new(furnace_core::scene::assets::AssetCache::new())), ..c.loader() };
        for row in c.store.jobs()? {
            // One job that cannot be restored is logged and left out; the others go on.
            let restored = row.map_err(|(id, e)| (id, CoordError::Internal(e))).and_then(|row| {
                let (id, state) = (row.id.clone(), row.state);
                // A finished job with its final status stored comes back without its scene.
                // (Its stored status and its row agree on how it ended.)
                let job = match c.store.final_status(&id).filter(|st| st.state == state) {
                    Some(st) => Ok(Job::finished(row.id, row.spec, row.created, st)),
                    None => restorer.restore(c.max_partial, row),
                };
                job.map(|j| (j, state)).map_err(|e| (id, e))
            });
            let (mut job, state) = match restored {
                Ok(r) => r,
                Err((id, e)) => {
                    tracing::error!(job = %id, "cannot restore this job, left out until the next start: {e}");
                    c.left_out.insert(id);
                    continue;
                }
            };
            let id = job.id.clone();
            if state == JobState::Paused {
                // Set aside again once idle for the usual time.
                job.paused_since = Some(Instant::now());
            }
            // Every chunk merged but the end not recorded (a crash or failure while writing
            // the final checkpoint): finish it now.
            // So is a cancelled job whose last checkpoint was not written.
            let snap = if state != JobState::Done { job.snapshot(c.checkpoint_interval) } else { None };
            let release = state == JobState::Done && job.released.is_none();
            c.jobs.insert(id.clone(), job);
            if release {
                if let Err(e) = c.evict(&id, true) {
                    tracing::error!(job = %id, "cannot release the finished job: {e}");
                }
            }
            if let Some(s) = snap {
                let result = s.write(&*c.store);
                c.checkpoint_written(&s, &result);
                if let Err(e) = result {
                    // The job stays open; its next merge or the next start writes it again.
                    tracing::error!(job = %s.job, "cannot write the final checkpoint: {e}");
                }
            }
        }
        for j in c.jobs.values() {
            if let Some(f) = &j.spec.frame_of {
                c.groups.entry(f.job.clone()).or_default().push((f.frame, j.id.clone()));
            }
        }
        for frames in c.groups.values_mut() {
            frames.sort();
        }
        // A frame-range job's key is stored with its first frame's row, and names the job.
        for (id, _) in c.keys.values_mut() {
            if let Some(f) = c.jobs.get(id.as_str()).and_then(|j| j.spec.frame_of.as_ref()) {
                *id = f.job.clone();
            }
        }
        if let Err(e) = c.write_rows_now() {
            tracing::error!("cannot record the jobs finished at start: {e}");
        }
        Ok(c)
    }

    /// Where this coordinator stores jobs and files.
    pub fn store(&self) -> Arc<dyn Store> {
        self.store.clone()
    }

    fn loader(&self) -> Loader {
        Loader {
            store: self.store.clone(),
            keep_scenes: self.keep_scenes,
            max_scene_bytes: self.max_scene_bytes,
            max_partial: self.max_partial,
            max_job_bytes: self.max_job_bytes,
            assets: None,
        }
    }

    /// The job an idempotency key already names.
    /// A key used again with the same spec names the same job; with another spec, it is
    /// refused.
    fn idempotent(&self, key: Option<&str>, request: &str) -> Result<Option<String>, CoordError> {
        let Some(k) = key else { return Ok(None) };
        match self.keys.get(k) {
            Some((_, Some(h))) if h != request => {
                Err(CoordError::Refused(format!("Idempotency-Key '{k}' was used for another job spec")))
            }
            other => Ok(other.map(|(id, _)| id.clone())),
        }
    }

    /// Submits a job for a scene already loaded in this process. Such a job has no bundle and
    /// is not stored: it lives as long as the process (`furnace render`).
    pub fn submit_scene(&mut self, scene: Arc<Scene>, settings: JobSettings) -> Result<String, CoordError> {
        let created = now_secs();
        let id = format!("local-{}", self.jobs.len());
        let spec = JobSpec::new(Bundle { scene: String::new(), files: BTreeMap::new() }, settings);
        let mut job =
            self.loader().job_from_scene(id.clone(), spec, JobState::Queued, created, scene.clone())?;
        job.scene = Some(scene);
        self.jobs.insert(id.clone(), job);
        Ok(id)
    }

    /// Adds a submission's jobs (one, or the frames of a frame-range job `id`), their rows to
    /// be stored.
    fn insert_jobs(
        &mut self,
        id: String,
        jobs: Vec<Job>,
        key: Option<&str>,
        request: &str,
    ) -> Result<String, CoordError> {
        let held: usize = self.jobs.values().map(Job::held_bytes).sum();
        // Frames are handed out in order: at most MAX_OPEN_FRAMES of them hold an image at once.
        let frames = jobs.iter().filter(|j| j.spec.frame_of.is_some()).count();
        let need = jobs.iter().map(Job::held_bytes).sum::<usize>()
            + open_images_bytes(jobs.first().map_or(0, Job::image_bytes), frames);
        if held.saturating_add(need) > self.max_job_bytes {
            return Err(CoordError::Busy(format!(
                "the coordinator holds {:.2} GB of jobs in memory and this one needs {:.2} GB, over its limit of {:.2} GB (--max-job-memory-gb): wait for jobs to end, or pause or cancel some",
                held as f64 / 1e9,
                need as f64 / 1e9,
                self.max_job_bytes as f64 / 1e9
            )));
        }
        if let Some(k) = key {
            self.keys.insert(k.to_string(), (id.clone(), Some(request.to_string())));
        }
        let mut frames = Vec::new();
        for (i, job) in jobs.into_iter().enumerate() {
            // The key is stored with the first row only (keys are unique).
            let key = if i == 0 { key.map(String::from) } else { None };
            self.unwritten.insert(job.id.clone(), (key, request.to_string()));
            self.dirty.insert(job.id.clone());
            if let Some(f) = &job.spec.frame_of {
                frames.push((f.frame, job.id.clone()));
            }
            self.jobs.insert(job.id.clone(), job);
        }
        if !frames.is_empty() {
            self.groups.insert(id.clone(), frames);
        }
        Ok(id)
    }

    /// The jobs `id` stands for: its frames for a frame-range job, else itself.
    fn members(&self, id: &str) -> Vec<String> {
        match self.groups.get(id) {
            Some(frames) => frames.iter().map(|(_, j)| j.clone()).collect(),
            None => vec![id.to_string()],
        }
    }

    /// Some row of `id`'s jobs is not stored yet.
    fn unstored(&self, id: &str) -> bool {
        self.members(id).iter().any(|j| self.unwritten.contains_key(j))
    }

    /// Takes back a submission whose rows could not be stored, unless they are stored now;
    /// returns whether it did (call it with no rows being written).
    fn unsubmit(&mut self, id: &str) -> bool {
        let mut taken = false;
        for j in self.members(id) {
            if self.unwritten.remove(&j).is_some() {
                self.jobs.remove(&j);
                self.dirty.remove(&j);
                taken = true;
            }
        }
        if taken {
            self.groups.remove(id);
            self.keys.retain(|_, (j, _)| j != id);
        }
        taken
    }

    /// The row changes not yet stored, as they are now, deletions first (a deleted job's
    /// idempotency key may name a new one); they count as stored from here (see
    /// [`Coordinator::rows_written`]).
    fn take_rows(&mut self) -> Vec<RowOp> {
        let mut ops = Vec::new();
        for id in std::mem::take(&mut self.dirty) {
            let Some(j) = self.jobs.get(&id) else {
                // Deleted; a job deleted before its row was stored has none to delete.
                if self.unwritten.remove(&id).is_none() {
                    ops.push(RowOp::Delete(id));
                }
                continue;
            };
            let row = JobRow { id: id.clone(), spec: j.spec.clone(), state: j.state, created: j.created };
            ops.push(match self.unwritten.get(&id) {
                Some((key, request)) => RowOp::Insert { row, key: key.clone(), request: request.clone() },
                None => RowOp::Update(row),
            });
        }
        ops.sort_by_key(|op| !matches!(op, RowOp::Delete(_)));
        ops
    }

    /// Records how a batch of [`Coordinator::take_rows`] ended: stored, or to be written again.
    fn rows_written(&mut self, ops: &[RowOp], result: &Result<Vec<PathBuf>, CoordError>) {
        for op in ops {
            match (op, result) {
                (RowOp::Insert { row, .. }, Ok(_)) => {
                    self.unwritten.remove(&row.id);
                }
                (_, Ok(_)) => {}
                (RowOp::Insert { row, .. } | RowOp::Update(row), Err(_)) => {
                    self.dirty.insert(row.id.clone());
                }
                (RowOp::Delete(id), Err(_)) => {
                    self.dirty.insert(id.clone());
                }
            }
        }
    }

    /// The hashes of the bundles and files that jobs in memory and loads under way use.
    fn in_use(&self) -> HashSet<String> {
        let bundles = self.jobs.values().map(|j| &j.spec.bundle).chain(self.loading.values());
        let mut used = HashSet::new();
        for b in bundles {
            used.insert(b.hash());
            used.extend(b.files.values().cloned());
        }
        used
    }

    /// Whether some job's row is to be stored.
    pub fn rows_due(&self) -> bool {
        !self.dirty.is_empty()
    }

    /// Stores the changed rows while holding the lock: at start, before anyone else can ask
    /// anything of the coordinator (everyone after goes through [`sync_rows`]). Returns what
    /// the deleted jobs leave to remove.
    fn write_rows_now(&mut self) -> Result<Vec<PathBuf>, CoordError> {
        let ops = self.take_rows();
        if ops.is_empty() {
            return Ok(Vec::new());
        }
        let result = self.store.write_rows(&ops, &self.in_use());
        self.rows_written(&ops, &result);
        result
    }

    fn job_mut(&mut self, id: &str) -> Result<&mut Job, CoordError> {
        self.jobs.get_mut(id).ok_or_else(|| CoordError::Unknown(format!("no job '{id}'")))
    }

    fn set_state(&mut self, id: &str, state: JobState) -> Result<(), CoordError> {
        let j = self.job_mut(id)?;
        if state == JobState::Paused && j.state != JobState::Paused {
            j.paused_since = Some(Instant::now());
        } else if state != JobState::Paused {
            j.paused_since = None;
        }
        j.state = state;
        self.dirty.insert(id.to_string());
        Ok(())
    }

    /// Cancel, pause or resume. A cancelled job's last checkpoint is due: with a durable
    /// store it is returned, to be written outside the lock (see [`control`]).
    fn control(&mut self, id: &str, action: &str) -> Result<Option<Snapshot>, CoordError> {
        let (state, complete) = {
            let j = self.job_mut(id)?;
            (j.state, j.released.is_none() && j.complete())
        };
        let next = match (action, state) {
            (_, JobState::Done) => return Err(CoordError::Refused(format!("job {id} is done"))),
            // Its final checkpoint is being written: it ends done, whatever is asked now.
            (_, s) if complete && s != JobState::Cancelled => {
                return Err(CoordError::Refused(format!("job {id} is finishing: every chunk is merged")))
            }
            ("cancel", _) => JobState::Cancelled,
            (_, JobState::Cancelled) => return Err(CoordError::Refused(format!("job {id} is cancelled"))),
            ("pause", _) => JobState::Paused,
            ("resume", JobState::Paused) => JobState::Queued,
            ("resume", s) => s,
            (a, _) => {
                return Err(CoordError::Invalid(format!("unknown action '{a}' (cancel, pause, resume)")))
            }
        };
        if next == JobState::Cancelled {
            // Revoked: uploads, heartbeats and failure reports of these leases are refused.
            let j = self.job_mut(id)?;
            for c in j.chunks.iter_mut().filter(|c| matches!(c, ChunkState::Leased { .. })) {
                *c = ChunkState::Pending;
            }
        }
        self.set_state(id, next)?;
        let store = self.store.durable() && next == JobState::Cancelled;
        let j = self.job_mut(id)?;
        if store && j.merged.is_empty() {
            // A job cancelled before its first chunk has no image to store (cancelling a range
            // of thousands of frames would otherwise make and write an image for each): its
            // final status is all that is kept (see `Store::final_status`). If it cannot be stored, the job is cancelled all the
            // same (a restart finds its row cancelled and finishes it then).
            if let Err(e) = self.evict(id, true) {
                tracing::error!(job = %id, "cannot store the cancelled job's status: {e}");
            }
            return Ok(None);
        }
        Ok(if store { j.snapshot(Duration::ZERO) } else { None })
    }

    fn reprioritise(&mut self, id: &str, priority: i32) -> Result<(), CoordError> {
        let job = self.job_mut(id)?;
        if matches!(job.state, JobState::Done | JobState::Cancelled) {
            return Err(CoordError::Refused(format!("job {id} is {}: it has no priority", job.state.name())));
        }
        job.spec.settings.priority = priority;
        self.dirty.insert(id.to_string());
        Ok(())
    }

    /// Returns expired leases to the front of their job's queue; returns how many.
    pub fn expire_leases(&mut self, now: Instant) -> usize {
        let mut n = 0;
        for job in self.jobs.values_mut() {
            for (i, c) in job.chunks.iter_mut().enumerate() {
                if let ChunkState::Leased { deadline, worker, .. } = c {
                    if *deadline <= now {
                        tracing::info!(job = %job.id, chunk = i, worker = %worker, "lease expired; chunk requeued");
                        *c = ChunkState::Pending;
                        job.queue.push_front(i as u32);
                        n += 1;
                        metrics::counter!("furnace_lease_expirations_total").increment(1);
                        metrics::counter!("furnace_chunk_retries_total", "reason" => "expired").increment(1);
                    }
                }
            }
        }
        n
    }

    /// Hands out the next chunk: highest priority first, then oldest job; pass by pass.
    pub fn lease(&mut self, worker: &str, now: Instant) -> Option<Lease> {
        self.expire_leases(now);
        self.seen(worker, now);
        // A frame-range job has at most MAX_OPEN_FRAMES open (started, not finished): a frame whose
        // queue waits on its passes being judged (a noise target) lets the next ones start, not
        // every frame after it, each of which would hold an image.
        // A frame that every worker known has failed too often (it gets no more of them) holds
        // no slot: three broken frames would otherwise stop the rest of the range.
        let given_up = |j: &Job| {
            !j.failures.is_empty()
                && self
                    .workers
                    .keys()
                    .all(|w| j.failures.get(w).copied().unwrap_or(0) >= MAX_FAILURES_PER_WORKER)
        };
        let mut open: HashMap<&str, usize> = HashMap::new();
        // (Only a coordinator holding frame ranges pays for this pass.)
        if !self.groups.is_empty() {
            for j in self.jobs.values().filter(|j| j.state == JobState::Running && !given_up(j)) {
                if let Some(f) = &j.spec.frame_of {
                    *open.entry(f.job.as_str()).or_default() += 1;
                }
            }
        }
        let may_start = |j: &Job| match (&j.spec.frame_of, j.state) {
            (Some(f), JobState::Queued) => open.get(f.job.as_str()).copied().unwrap_or(0) < MAX_OPEN_FRAMES,
            _ => true,
        };
        // The frames of a frame-range job go in frame order. One pass (no sort): a frame-range
        // job of thousands of frames is thousands of jobs here.
        let id = self
            .jobs
            .values()
            .filter(|j| matches!(j.state, JobState::Queued | JobState::Running))
            .filter(|j| may_start(j))
            // Not before its row (and its folder, where its partials go) is stored.
            .filter(|j| !self.unwritten.contains_key(&j.id))
            .filter(|j| j.failures.get(worker).copied().unwrap_or(0) < MAX_FAILURES_PER_WORKER)
            .filter(|j| !j.queue.is_empty())
            .min_by_key(|j| {
                let (group, frame) =
                    j.spec.frame_of.as_ref().map_or((j.id.as_str(), 0), |f| (f.job.as_str(), f.frame));
                (std::cmp::Reverse(j.spec.settings.priority), j.created, group, frame, j.id.as_str())
            })?
            .id
            .clone();
        let epoch = self.next_epoch;
        self.next_epoch += 1;
        let deadline = now + self.lease_duration;
        let ms = self.lease_duration.as_millis() as u64;
        let job = self.jobs.get_mut(&id)?;
        // Only a pending chunk is handed out (a queue entry may be stale: a chunk merged
        // meanwhile, or queued twice after a restart).
        let chunk = loop {
            let c = job.queue.pop_front()?;
            if matches!(job.chunks[c as usize], ChunkState::Pending) {
                break c;
            }
        };
        job.chunks[chunk as usize] =
            ChunkState::Leased { epoch, worker: worker.to_string(), deadline, since: now };
        if job.workers.len() >= MAX_JOB_WORKERS && !job.workers.contains_key(worker) {
            // The longest silent one makes room: a status lists a bounded number of workers.
            let oldest = job.workers.iter().min_by_key(|(_, t)| **t).map(|(w, _)| w.clone());
            oldest.map(|w| job.workers.remove(&w));
        }
        job.workers.insert(worker.to_string(), now);
        if job.state == JobState::Queued {
            // Stored by the next sync of rows (a restart treats queued and running alike).
            job.state = JobState::Running;
            self.dirty.insert(id.clone());
        }
        let job = &self.jobs[&id];
        Some(Lease {
            job: id.clone(),
            chunk: job.plan[chunk as usize],
            epoch,
            settings: job.spec.settings.clone(),
            bundle_hash: job.bundle_hash.clone(),
            defines: job.spec.defines.clone(),
            deadline_ms: ms,
        })
    }

    fn leased(&mut self, job: &str, chunk: u32, epoch: u64) -> Result<&mut Job, CoordError> {
        let j = self.job_mut(job)?;
        if j.state == JobState::Cancelled {
            return Err(CoordError::Refused(format!("job {job} is cancelled: its leases are revoked")));
        }
        if j.released.is_some() && j.state == JobState::Paused {
            return Err(CoordError::Refused(format!(
                "stale lease: job {job} is paused, chunk {chunk} not leased"
            )));
        }
        if j.released.is_some() {
            return Err(CoordError::Refused(format!(
                "chunk {chunk} of job {job} is already merged: the job is done"
            )));
        }
        let c = j
            .chunks
            .get(chunk as usize)
            .ok_or_else(|| CoordError::Unknown(format!("job {job} has no chunk {chunk}")))?;
        match c {
            ChunkState::Leased { epoch: e, .. } if *e == epoch => Ok(j),
            ChunkState::Done => {
                Err(CoordError::Refused(format!("chunk {chunk} of job {job} is already merged")))
            }
            _ => Err(CoordError::Refused(format!(
                "stale lease: chunk {chunk} of job {job} is not leased under epoch {epoch}"
            ))),
        }
    }

    pub fn heartbeat(&mut self, job: &str, chunk: u32, epoch: u64, now: Instant) -> Result<u64, CoordError> {
        let d = self.lease_duration;
        let j = self.leased(job, chunk, epoch)?;
        let ChunkState::Leased { deadline, worker, .. } = &mut j.chunks[chunk as usize] else {
            unreachable!("checked by leased()")
        };
        *deadline = now + d;
        let worker = worker.clone();
        j.workers.insert(worker.clone(), now);
        self.seen(&worker, now);
        Ok(d.as_millis() as u64)
    }

    /// A worker reports that it could not render its chunk.
    pub fn fail(&mut self, job: &str, chunk: u32, epoch: u64, error: &str) -> Result<(), CoordError> {
        let j = self.leased(job, chunk, epoch)?;
        let worker = match &j.chunks[chunk as usize] {
            ChunkState::Leased { worker, .. } => worker.clone(),
            _ => unreachable!("checked by leased()"),
        };
        let n = j.failures.entry(worker.clone()).or_insert(0);
        *n += 1;
        let n = *n;
        j.record_error(format!("worker {worker}, chunk {chunk}: {error}"));
        if n == MAX_FAILURES_PER_WORKER {
            j.record_error(format!("worker {worker} failed {n} times and gets no more of this job"));
        }
        j.chunks[chunk as usize] = ChunkState::Pending;
        j.queue.push_front(chunk);
        metrics::counter!("furnace_chunk_failures_total").increment(1);
        metrics::counter!("furnace_chunk_retries_total", "reason" => "failed").increment(1);
        Ok(())
    }

    /// Checks a partial against its lease and its chunk's rectangle and sample count. Returns
    /// the store to keep it in first, when this coordinator's store is durable. Changes nothing.
    pub fn check_partial(
        &mut self,
        job: &str,
        chunk: u32,
        epoch: u64,
        acc: &Accum,
    ) -> Result<Option<Arc<dyn Store>>, CoordError> {
        let store = self.store.clone();
        let j = self.leased(job, chunk, epoch)?;
        j.fits(chunk, acc).map_err(CoordError::Invalid)?;
        Ok(store.durable().then_some(store))
    }

    /// Merges a checked (and, when this coordinator stores partials, stored) partial; at most
    /// once per chunk. Returns a checkpoint to write, when one is due.
    fn merge_partial(
        &mut self,
        job: &str,
        chunk: u32,
        epoch: u64,
        acc: &Accum,
        stats: Option<&RenderStats>,
        now: Instant,
    ) -> Result<Option<Snapshot>, CoordError> {
        let t0 = Instant::now();
        let (worker, since) = match &self.leased(job, chunk, epoch)?.chunks[chunk as usize] {
            ChunkState::Leased { worker, since, .. } => (worker.clone(), *since),
            _ => unreachable!("checked by leased()"),
        };
        let (durable, interval) = (self.store.durable(), self.checkpoint_interval);
        let j = self.job_mut(job)?;
        if acc.dropped.total() > 0 {
            tracing::warn!(job, chunk, worker = %worker, "chunk dropped samples: {}", acc.dropped);
        }
        // Copies the accumulation only if a checkpoint of it is still being written.
        j.accum_mut().merge(acc);
        if let Some(s) = stats {
            j.stats.merge(s);
        }
        j.merged.insert(chunk);
        j.chunks[chunk as usize] = ChunkState::Done;
        j.follow_up(chunk, acc);
        let samples = j.plan[chunk as usize].region.samples();
        metrics::histogram!("furnace_chunk_duration_seconds").record(now.duration_since(since).as_secs_f64());
        metrics::counter!("furnace_samples_rendered_total").increment(samples);
        metrics::counter!("furnace_merged_bytes_total")
            .increment(std::mem::size_of_val(acc.pixels.as_slice()) as u64);
        j.samples_done += samples;
        j.recent.push_back((now, samples));
        while j.recent.len() > 1 && now.duration_since(j.recent[0].0) > Duration::from_secs(30) {
            j.recent.pop_front();
        }
        j.since_checkpoint += 1;
        let finished = j.complete();
        let snap = if durable { j.snapshot(interval) } else { None };
        self.seen(&worker, now);
        if let Some(w) = self.workers.get_mut(&worker) {
            w.chunks_done += 1;
            w.samples_done += samples;
        }
        metrics::histogram!("furnace_merge_duration_seconds").record(t0.elapsed().as_secs_f64());
        if !durable && finished {
            self.set_state(job, JobState::Done)?;
        }
        Ok(snap)
    }

    /// Notes that `worker` was heard from.
    pub fn seen(&mut self, worker: &str, now: Instant) {
        match self.workers.get_mut(worker) {
            Some(w) => w.last_seen = now,
            None => {
                // Forgetting sweeps the whole registry: at most once a minute, not per new name.
                if self.pruned.is_none_or(|t| now.saturating_duration_since(t) >= Duration::from_secs(60)) {
                    self.workers.retain(|_, w| now.saturating_duration_since(w.last_seen) < FORGET_WORKER);
                    self.pruned = Some(now);
                }
                let w = WorkerSeen { last_seen: now, chunks_done: 0, samples_done: 0 };
                self.workers.insert(worker.to_string(), w);
            }
        }
    }

    /// Every worker seen in the last hour, with its state.
    pub fn workers(&self, now: Instant) -> Vec<furnace_proto::WorkerStatus> {
        let mut leases: HashMap<&str, u64> = HashMap::new();
        for j in self.jobs.values() {
            for c in &j.chunks {
                if let ChunkState::Leased { worker, .. } = c {
                    *leases.entry(worker.as_str()).or_default() += 1;
                }
            }
        }
        self.workers
            .iter()
            .filter(|(_, w)| now.saturating_duration_since(w.last_seen) < FORGET_WORKER)
            .map(|(name, w)| {
                let held = leases.get(name.as_str()).copied().unwrap_or(0);
                let silent = now.saturating_duration_since(w.last_seen);
                let state = if held > 0 {
                    "busy"
                } else if silent <= self.lease_duration + WORKER_SLACK {
                    "idle"
                } else {
                    "lost"
                };
                furnace_proto::WorkerStatus {
                    name: name.clone(),
                    state: state.into(),
                    leases: held,
                    chunks_done: w.chunks_done,
                    samples_done: w.samples_done,
                    last_seen_seconds: silent.as_secs_f64(),
                }
            })
            .collect()
    }

    /// Jobs, chunks and workers by state.
    pub fn stats(&self, now: Instant) -> furnace_proto::FarmStats {
        let mut jobs: BTreeMap<String, u64> =
            JobState::ALL.iter().map(|s| (s.name().to_string(), 0)).collect();
        let mut chunks: BTreeMap<String, u64> =
            ["pending", "leased", "done", "skipped"].iter().map(|s| (s.to_string(), 0)).collect();
        let mut pending_chunks = 0;
        // A frame-range job counts once, in its state.
        for id in self.groups.keys() {
            if let Ok(st) = self.status(id) {
                *jobs.entry(st.state.name().into()).or_default() += 1;
            }
        }
        for j in self.jobs.values() {
            if j.spec.frame_of.is_none() {
                *jobs.entry(j.state.name().into()).or_default() += 1;
            }
            if let Some(st) = &j.released {
                *chunks.entry("done".into()).or_default() += st.chunks_done.saturating_sub(st.chunks_skipped);
                *chunks.entry("skipped".into()).or_default() += st.chunks_skipped;
                *chunks.entry("pending".into()).or_default() += st.chunks_pending;
            }
            for c in &j.chunks {
                let name = match c {
                    ChunkState::Pending => "pending",
                    ChunkState::Leased { .. } => "leased",
                    ChunkState::Done => "done",
                    ChunkState::Skipped => "skipped",
                };
                *chunks.entry(name.into()).or_default() += 1;
            }
            if matches!(j.state, JobState::Queued | JobState::Running) {
                pending_chunks += j.queue.len() as u64;
            }
        }
        let mut workers: BTreeMap<String, u64> =
            ["busy", "idle", "lost"].iter().map(|s| (s.to_string(), 0)).collect();
        for w in self.workers(now) {
            *workers.entry(w.state).or_default() += 1;
        }
        furnace_proto::FarmStats { jobs, chunks, pending_chunks, workers }
    }

    /// Records a written checkpoint (or its failure); a job finished meanwhile gets its final
    /// checkpoint next.
    fn checkpoint_written(&mut self, snap: &Snapshot, result: &Result<(), CoordError>) -> Option<Snapshot> {
        let interval = self.checkpoint_interval;
        let j = self.jobs.get_mut(&snap.job)?;
        j.checkpointing = false;
        if let Err(e) = result {
            j.record_error(format!("checkpoint failed: {e}"));
            j.checkpoint_failed = Some(Instant::now());
            return None;
        }
        j.checkpoint_failed = None;
        j.checkpointed.extend(&snap.ids);
        if snap.status.is_none() && j.idle(self.evict_paused_after) && j.checkpoint_current() {
            self.set_aside(&snap.job);
            return None;
        }
        if let Some(st) = &snap.status {
            if st.state == JobState::Done {
                if let Err(e) = self.set_state(&snap.job, JobState::Done) {
                    tracing::error!(job = %snap.job, "cannot record the job as done: {e}");
                }
            }
            tracing::info!(job = %snap.job, "job {}", st.state.name());
            // A stored job's result and final status are stored: its memory goes
            // (`furnace render`'s stays).
            if self.store.durable() {
                if let Err(e) = self.evict(&snap.job, false) {
                    tracing::error!(job = %snap.job, "cannot release the finished job: {e}");
                }
            }
            return None;
        }
        j.snapshot(interval)
    }

    /// The scene of a job, when this coordinator keeps scenes.
    pub fn job_scene(&self, id: &str) -> Option<Arc<Scene>> {
        self.jobs.get(id)?.scene.clone()
    }

    /// A job's status; a frame-range job's sums its frames' and lists each.
    pub fn status(&self, id: &str) -> Result<JobStatus, CoordError> {
        if let Some(frames) = self.groups.get(id) {
            return self.group_status(id, frames);
        }
        Ok(self.jobs.get(id).ok_or_else(|| CoordError::Unknown(format!("no job '{id}'")))?.status())
    }

    /// A job's (or frame range's) samples done and in all, as `status` gives them, without
    /// its error estimate or the rest: for progress bars that poll often.
    pub fn progress(&self, id: &str) -> Result<(u64, u64), CoordError> {
        let unknown = || CoordError::Unknown(format!("no job '{id}'"));
        if let Some(frames) = self.groups.get(id) {
            let jobs: Vec<&Job> = frames.iter().filter_map(|(_, j)| self.jobs.get(j)).collect();
            if jobs.is_empty() {
                return Err(unknown());
            }
            return Ok(jobs.iter().map(|j| j.progress()).fold((0, 0), |(d, t), (a, b)| (d + a, t + b)));
        }
        Ok(self.jobs.get(id).ok_or_else(unknown)?.progress())
    }

    fn group_status(&self, id: &str, frames: &[(u32, String)]) -> Result<JobStatus, CoordError> {
        let all: Vec<(u32, JobStatus)> =
            frames.iter().filter_map(|(n, j)| Some((*n, self.jobs.get(j)?.status()))).collect();
        let Some((_, first)) = all.first() else {
            return Err(CoordError::Unknown(format!("no job '{id}' (none of its frames could be restored)")));
        };
        let mut st = JobStatus {
            id: id.to_string(),
            chunks_total: 0,
            chunks_done: 0,
            chunks_leased: 0,
            chunks_pending: 0,
            chunks_skipped: 0,
            samples_done: 0,
            samples_total: 0,
            samples_per_second: 0.0,
            eta_seconds: None,
            estimated_rel_mse: None,
            dropped_samples: Default::default(),
            render_stats: RenderStats::default(),
            workers: Vec::new(),
            errors: Vec::new(),
            frames: Vec::new(),
            ..first.clone()
        };
        let mut workers = BTreeSet::new();
        for (n, f) in &all {
            st.chunks_total += f.chunks_total;
            st.chunks_done += f.chunks_done;
            st.chunks_leased += f.chunks_leased;
            st.chunks_pending += f.chunks_pending;
            st.chunks_skipped += f.chunks_skipped;
            st.samples_done += f.samples_done;
            st.samples_total += f.samples_total;
            st.samples_per_second += f.samples_per_second;
            // The worst frame's.
            st.estimated_rel_mse = match (st.estimated_rel_mse, f.estimated_rel_mse) {
                (Some(a), Some(b)) => Some(a.max(b)),
                (a, b) => a.or(b),
            };
            st.dropped_samples.add(&f.dropped_samples);
            st.render_stats.merge(&f.render_stats);
            workers.extend(f.workers.iter().cloned());
            st.errors.extend(f.errors.iter().map(|e| format!("frame {n}: {e}")));
            st.frames.push(FrameStatus {
                frame: *n,
                state: f.state,
                chunks_total: f.chunks_total,
                chunks_done: f.chunks_done,
                samples_done: f.samples_done,
                samples_total: f.samples_total,
                samples_per_second: f.samples_per_second,
                eta_seconds: f.eta_seconds,
                estimated_rel_mse: f.estimated_rel_mse,
            });
        }
        st.errors.drain(..st.errors.len().saturating_sub(MAX_ERRORS));
        st.workers = workers.into_iter().take(MAX_JOB_WORKERS).collect();
        let left = st.samples_total - st.samples_done;
        st.eta_seconds = (st.samples_per_second > 0.0).then(|| left as f64 / st.samples_per_second);
        let states: Vec<JobState> = all.iter().map(|(_, f)| f.state).collect();
        let any = |s: JobState| states.contains(&s);
        // A frame cancelled on its own (through its frame job's id) leaves the others going:
        // the job is cancelled once none is left to render.
        let ended = |s: JobState| matches!(s, JobState::Done | JobState::Cancelled);
        st.state = if states.iter().all(|&s| s == JobState::Done) {
            JobState::Done
        } else if states.iter().all(|&s| ended(s)) {
            JobState::Cancelled
        } else if states.iter().all(|&s| ended(s) || s == JobState::Paused) {
            JobState::Paused
        } else if any(JobState::Running) || any(JobState::Done) {
            JobState::Running
        } else {
            JobState::Queued
        };
        Ok(st)
    }

    /// The job of frame `frame` of the frame-range job `id`.
    pub fn frame_job(&self, id: &str, frame: u32) -> Result<String, CoordError> {
        let frames = self.groups.get(id).ok_or_else(|| {
            let what = if self.jobs.contains_key(id) { "has no frame range" } else { "does not exist" };
            CoordError::Unknown(format!("job '{id}' {what}"))
        })?;
        frames
            .iter()
            .find(|(n, _)| *n == frame)
            .map(|(_, j)| j.clone())
            .ok_or_else(|| CoordError::Unknown(format!("job '{id}' has no frame {frame}")))
    }

    /// Every job's id (a frame-range job's, not its frames').
    pub fn job_ids(&self) -> Vec<String> {
        self.job_ids_after(None, usize::MAX)
    }

    /// At most `limit` job ids in order, those after `after` if given (a frame-range job's,
    /// not its frames').
    pub fn job_ids_after(&self, after: Option<&str>, limit: usize) -> Vec<String> {
        use std::ops::Bound::{Excluded, Unbounded};
        let from = || after.map_or(Unbounded, |a| Excluded(a.to_string()));
        let jobs =
            self.jobs.range((from(), Unbounded)).filter(|(_, j)| j.spec.frame_of.is_none()).map(|(id, _)| id);
        let groups = self.groups.range((from(), Unbounded)).map(|(id, _)| id);
        let mut ids: Vec<String> = jobs.take(limit).chain(groups.take(limit)).cloned().collect();
        ids.sort();
        ids.truncate(limit);
        ids
    }

    /// The job's image: developed from the accumulation, or (a finished job's) its result file.
    /// A frame-range job's is the frame being rendered (the first unfinished one with chunks
    /// merged), else the last finished one, else its first.
    pub fn picture(&self, id: &str) -> Result<Picture, CoordError> {
        if let Some(frames) = self.groups.get(id) {
            let job = |(_, j): &&(u32, String)| self.jobs.get(j);
            let rendering = frames
                .iter()
                .find(|f| job(f).is_some_and(|j| j.state != JobState::Done && j.samples_done > 0));
            let done = frames.iter().rev().find(|f| job(f).is_some_and(|j| j.state == JobState::Done));
            let (_, frame) = rendering
                .or(done)
                .or(frames.first())
                .ok_or_else(|| CoordError::Unknown(format!("no job '{id}'")))?;
            return self.picture(frame);
        }
        let j = self.jobs.get(id).ok_or_else(|| CoordError::Unknown(format!("no job '{id}'")))?;
        let black =
            || Picture::Developed(Accum::new(0, 0, j.spec.settings.width, j.spec.settings.height).develop());
        Ok(match j.released {
            Some(_) if j.state == JobState::Paused => Picture::Checkpoint {
                store: self.store.clone(),
                job: id.to_string(),
                width: j.spec.settings.width,
                height: j.spec.settings.height,
            },
            // A job cancelled before its first chunk stored no image.
            Some(_) if j.state == JobState::Cancelled && !self.store.result_path(id).exists() => black(),
            Some(_) => Picture::File(self.store.result_path(id)),
            // Black until its first chunk.
            None if j.accum.pixels.is_empty() => black(),
            None => Picture::Developed(j.accum.develop()),
        })
    }

    pub fn image(&self, id: &str) -> Result<furnace_core::Image, CoordError> {
        self.picture(id)?.image()
    }

    /// Bytes the job's plan, chunk states and accumulation hold in memory (the larger part
    /// of what a job costs: 96 bytes a pixel).
    pub fn held_bytes(&self, id: &str) -> Result<usize, CoordError> {
        Ok(self.jobs.get(id).ok_or_else(|| CoordError::Unknown(format!("no job '{id}'")))?.held_bytes())
    }

    /// Records that an upload of `chunk` was refused as malformed (the worker drops it and the
    /// lease expires): the job's status says why its chunk is rendered again.
    pub fn note_refused_upload(&mut self, id: &str, chunk: u32, why: &str) {
        if let Some(j) = self.jobs.get_mut(id).filter(|j| j.released.is_none()) {
            j.record_error(format!("upload of chunk {chunk} refused: {why}"));
        }
    }

    /// Forgets a job, its row to be deleted: leases of it are refused from now on.
    fn forget(&mut self, id: &str) -> Result<(), CoordError> {
        // A job left out at the last start (its scene files gone) has a row but no state.
        if self.jobs.remove(id).is_none() && !self.left_out.remove(id) {
            return Err(CoordError::Unknown(format!("no job '{id}'")));
        }
        self.keys.retain(|_, (j, _)| j != id);
        self.dirty.insert(id.to_string());
        tracing::info!(job = %id, "job deleted");
        Ok(())
    }

    /// Sets a paused, idle job aside: its status is kept, everything else released (its stored
    /// checkpoint holds every merged chunk).
    fn set_aside(&mut self, id: &str) {
        let Some(j) = self.jobs.get_mut(id) else { return };
        let st = j.status();
        j.release(st);
        tracing::info!(job = %id, "paused job set aside: its memory is released until it is resumed");
    }

    /// Releases a finished job's memory, keeping its final status (stored too, with `store`,
    /// so that a restart need not load its scene; the final checkpoint has stored it already).
    fn evict(&mut self, id: &str, store: bool) -> Result<(), CoordError> {
        let st = self.status(id)?;
        if store {
            self.store.save_status(id, &st)?;
        }
        self.job_mut(id)?.release(st);
        Ok(())
    }

    pub fn result_path(&self, id: &str) -> Result<PathBuf, CoordError> {
        if let Some(frames) = self.groups.get(id) {
            let (a, b) = (frames.first().map_or(0, |f| f.0), frames.last().map_or(0, |f| f.0));
            return Err(CoordError::Refused(format!(
                "job {id} renders frames {a} to {b}: each has its result at /v1/jobs/{id}/frames/{{n}}/result.exr"
            )));
        }
        let j = self.jobs.get(id).ok_or_else(|| CoordError::Unknown(format!("no job '{id}'")))?;
        if j.state != JobState::Done {
            return Err(CoordError::Refused(format!("job {id} is not done ({:?})", j.state)));
        }
        Ok(self.store.result_path(id))
    }

    pub fn bundle_manifest(&self, hash: &str) -> Result<Vec<u8>, CoordError> {
        if !furnace_proto::is_hash(hash) {
            return Err(CoordError::Invalid(format!("'{hash}' is not a bundle hash")));
        }
        self.store.bundle_manifest(hash).ok_or_else(|| CoordError::Unknown(format!("no bundle {hash}")))
    }
}

/// Accepts a partial for a leased chunk: checks it, stores it durably (when the coordinator
/// stores partials) without holding the lock, then merges it. `encoded` is the partial as
/// uploaded, if it came over the wire. Every worker, remote or in this process, goes through here.
pub fn accept_partial(
    coord: &Mutex<Coordinator>,
    job: &str,
    chunk: u32,
    epoch: u64,
    acc: &Accum,
    stats: Option<&RenderStats>,
    encoded: Option<&[u8]>,
) -> Result<(), CoordError> {
    let lock = || coord.lock().unwrap_or_else(|e| e.into_inner());
    // Each guard is dropped before a refusal is counted: count_duplicate locks again.
    let checked = lock().check_partial(job, chunk, epoch, acc);
    let store = checked.inspect_err(|_| count_duplicate(coord, job, chunk))?;
    if let Some(store) = store {
        // Chunks are deterministic: a partial stored by a lease that loses the race below holds
        // the same bytes as the one merged, and a restart merges each chunk at most once.
        match encoded {
            Some(bytes) => store.save_partial(job, chunk, bytes)?,
            None => store.save_partial(job, chunk, &encode_chunk(acc, stats))?,
        }
    }
    let merged = lock().merge_partial(job, chunk, epoch, acc, stats, Instant::now());
    let snap = merged.inspect_err(|_| count_duplicate(coord, job, chunk))?;
    write_checkpoints(coord, snap)
}

/// Writes a checkpoint and those due after it, without the lock: leases and uploads go on
/// meanwhile.
fn write_checkpoints(coord: &Mutex<Coordinator>, mut snap: Option<Snapshot>) -> Result<(), CoordError> {
    // Most merges make no checkpoint: no second lock for them.
    if snap.is_none() {
        return Ok(());
    }
    let store = coord.lock().unwrap_or_else(|e| e.into_inner()).store();
    while let Some(s) = snap {
        let result = s.write(&*store);
        snap = coord.lock().unwrap_or_else(|e| e.into_inner()).checkpoint_written(&s, &result);
        result?;
    }
    // A finished job's state; if it cannot be stored now, the server's timer tries again (the
    // merge that led here succeeded: its upload is not failed for it).
    if let Err(e) = sync_rows(coord) {
        tracing::warn!("cannot store the jobs' rows yet: {e}");
    }
    Ok(())
}

/// Stores the job rows changed since the last time (submissions, states, priorities,
/// deletions) without the coordinator's lock, and removes what deleted jobs leave. One writer
/// at a time, each writing the rows as they are when it starts: the store always ends with
/// the latest. A request whose change must be stored before it is answered calls this after
/// making the change; the server's timer calls it for the others (a job leased, so running).
pub fn sync_rows(coord: &Mutex<Coordinator>) -> Result<(), CoordError> {
    let lock = || coord.lock().unwrap_or_else(|e| e.into_inner());
    let writer = lock().row_writer.clone();
    let _turn = writer.lock().unwrap_or_else(|e| e.into_inner());
    let (store, ops, keep) = {
        let mut c = lock();
        let ops = c.take_rows();
        let keep =
            if ops.iter().any(|op| matches!(op, RowOp::Delete(_))) { c.in_use() } else { HashSet::new() };
        (c.store.clone(), ops, keep)
    };
    if ops.is_empty() {
        return Ok(());
    }
    let result = store.write_rows(&ops, &keep);
    lock().rows_written(&ops, &result);
    crate::store::remove_paths(&result?);
    Ok(())
}

/// Writes again, at most every `checkpoint_retry`, the final checkpoint of every job whose
/// last one failed (a full disk): such a job would otherwise stay running at 100% until a
/// restart. Called by the server's timer.
pub fn retry_checkpoints(coord: &Mutex<Coordinator>) {
    let snaps: Vec<Snapshot> = {
        let mut c = coord.lock().unwrap_or_else(|e| e.into_inner());
        let retry = c.checkpoint_retry;
        c.jobs
            .values_mut()
            .filter(|j| !j.checkpointing && j.checkpoint_failed.is_some_and(|t| t.elapsed() >= retry))
            .filter(|j| j.released.is_none())
            .filter_map(|j| {
                j.checkpoint_failed = None;
                j.snapshot(Duration::ZERO)
            })
            .collect()
    };
    for s in snaps {
        let job = s.job.clone();
        if let Err(e) = write_checkpoints(coord, Some(s)) {
            tracing::warn!(job = %job, "checkpoint retry failed: {e}");
        }
    }
}

/// Sets aside every paused job idle for `evict_paused_after`: one whose checkpoint is current
/// at once, the others once a checkpoint is written (here, outside the lock). Called by the
/// server's timer; does nothing for a store that is not durable.
pub fn set_aside_idle(coord: &Mutex<Coordinator>) {
    let snaps: Vec<Snapshot> = {
        let mut c = coord.lock().unwrap_or_else(|e| e.into_inner());
        if !c.store.durable() {
            return;
        }
        let after = c.evict_paused_after;
        let idle: Vec<String> = c.jobs.values().filter(|j| j.idle(after)).map(|j| j.id.clone()).collect();
        let mut snaps = Vec::new();
        for id in idle {
            if c.jobs[&id].checkpoint_current() {
                c.set_aside(&id);
            } else if let Some(s) = c.jobs.get_mut(&id).and_then(|j| j.snapshot_now()) {
                snaps.push(s);
            }
        }
        snaps
    };
    for s in snaps {
        let job = s.job.clone();
        if let Err(e) = write_checkpoints(coord, Some(s)) {
            tracing::warn!(job = %job, "checkpoint of an idle job failed: {e}");
        }
    }
}

/// The scene of a job for workers in this process: kept since submission, or loaded now
/// (outside the lock; the later frames of a frame-range job) and kept until the job ends.
pub fn load_scene(coord: &Mutex<Coordinator>, id: &str) -> Result<Arc<Scene>, CoordError> {
    let lock = || coord.lock().unwrap_or_else(|e| e.into_inner());
    if let Some(s) = lock().job_scene(id) {
        return Ok(s);
    }
    let turn = lock().scene_loads.clone();
    // One load at a time: the slots of a worker asking for the same new frame load it once.
    let _turn = turn.lock().unwrap_or_else(|e| e.into_inner());
    let (loader, spec) = {
        let c = lock();
        let j = c.jobs.get(id).ok_or_else(|| CoordError::Unknown(format!("no job '{id}'")))?;
        if let Some(s) = &j.scene {
            return Ok(s.clone());
        }
        if j.spec.bundle.files.is_empty() {
            return Err(CoordError::Unknown(format!("job {id} has no scene in this process")));
        }
        (c.loader(), j.spec.clone())
    };
    let scene = Arc::new(loader.load_bundle(&spec.bundle, &spec.defines, None)?);
    if let Some(j) = lock().jobs.get_mut(id).filter(|j| j.released.is_none()) {
        j.scene = Some(scene.clone());
    }
    Ok(scene)
}

/// Loads a job that was set aside again (outside the lock), so that it can be resumed or
/// cancelled.
fn bring_back(coord: &Mutex<Coordinator>, id: &str) -> Result<(), CoordError> {
    let lock = || coord.lock().unwrap_or_else(|e| e.into_inner());
    let (loader, max, row) = {
        let c = lock();
        let Some(j) = c.jobs.get(id) else { return Ok(()) };
        if j.released.is_none() || j.state != JobState::Paused {
            return Ok(());
        }
        let row = JobRow { id: id.to_string(), spec: j.spec.clone(), state: j.state, created: j.created };
        (c.loader(), c.max_partial, row)
    };
    let mut job = loader.restore(max, row)?;
    let mut c = lock();
    match c.jobs.get(id) {
        Some(old) if old.released.is_some() && old.state == JobState::Paused => {
            let mut errors = old.errors.clone();
            errors.extend(job.errors.drain(..));
            errors.drain(..errors.len().saturating_sub(MAX_ERRORS));
            job.errors = errors;
            job.spec.settings.priority = old.spec.settings.priority;
            job.paused_since = old.paused_since;
            c.jobs.insert(id.to_string(), job);
            tracing::info!(job = %id, "job brought back");
        }
        _ => {} // deleted, or brought back by another request meanwhile
    }
    Ok(())
}

/// Cancels, pauses or resumes a job. A cancelled job ends like a finished one: its image so
/// far, its checkpoint and its final status are stored (outside the lock) and its memory
/// released; its preview stays. A job set aside is loaded again first.
/// Returns the job's status as the change left it (a request racing it, a delete say, does not
/// change the answer).
/// A frame-range job's frames are changed one by one, those finished left as they are.
pub fn control(coord: &Mutex<Coordinator>, id: &str, action: &str) -> Result<JobStatus, CoordError> {
    let lock = || coord.lock().unwrap_or_else(|e| e.into_inner());
    let (members, group) = {
        let c = lock();
        (c.members(id), c.groups.contains_key(id))
    };
    let mut changed = 0;
    let mut refused = None;
    for job in &members {
        match control_one(coord, job, action) {
            Ok(()) => changed += 1,
            // A finished frame stays finished.
            Err(CoordError::Refused(e)) if group => refused = Some(e),
            Err(e) => return Err(e),
        }
    }
    if changed == 0 {
        if let Some(e) = refused {
            let st = lock().status(id)?;
            return Err(CoordError::Refused(format!("job {id} is {}: {e}", st.state.name())));
        }
    }
    let status = lock().status(id)?;
    sync_rows(coord).map(|()| status)
}

fn control_one(coord: &Mutex<Coordinator>, id: &str, action: &str) -> Result<(), CoordError> {
    if matches!(action, "resume" | "cancel") {
        bring_back(coord, id)?;
    }
    let snap = coord.lock().unwrap_or_else(|e| e.into_inner()).control(id, action)?;
    if let Err(e) = write_checkpoints(coord, snap) {
        // The job stays cancelled; its memory goes at the next retry or start (unless it was
        // deleted meanwhile, which is why its folder is gone).
        if coord.lock().unwrap_or_else(|e| e.into_inner()).jobs.contains_key(id) {
            tracing::error!(job = %id, "cannot store the cancelled job: {e}");
        }
    }
    Ok(())
}

/// Sets a job's priority and stores it, without the lock; returns the job's status as the
/// change left it.
pub fn set_priority(coord: &Mutex<Coordinator>, id: &str, priority: i32) -> Result<JobStatus, CoordError> {
    let status = {
        let mut c = coord.lock().unwrap_or_else(|e| e.into_inner());
        if c.groups.contains_key(id) {
            // Its unfinished frames; refused only when none is left.
            let results: Vec<_> = c.members(id).iter().map(|j| c.reprioritise(j, priority)).collect();
            if !results.iter().any(Result::is_ok) {
                let st = c.status(id)?;
                return Err(CoordError::Refused(format!(
                    "job {id} is {}: it has no priority",
                    st.state.name()
                )));
            }
        } else {
            c.reprioritise(id, priority)?;
        }
        c.status(id)?
    };
    sync_rows(coord).map(|()| status)
}

/// Deletes a job: forgotten under the lock (its leases refused from then on), its row, folder
/// and the files no other job uses removed without it.
pub fn delete(coord: &Mutex<Coordinator>, id: &str) -> Result<(), CoordError> {
    {
        let mut c = coord.lock().unwrap_or_else(|e| e.into_inner());
        // A delete whose row is still to be removed (an earlier try failed to store it) is
        // tried again, not refused as unknown.
        if let Some(frames) = c.groups.remove(id) {
            for (_, j) in frames {
                c.forget(&j).ok();
            }
            c.keys.retain(|_, (j, _)| j != id);
        } else if !c.dirty.contains(id) || c.jobs.contains_key(id) {
            c.forget(id)?;
        }
    }
    sync_rows(coord)
}

/// Submits a job, locking the coordinator only to look up the idempotency key and to insert
/// the job: the bundle is laid out and the scene loaded, validated and planned without the
/// lock, so leases, uploads and status go on meanwhile. A load that ends after `deadline` (the
/// request's time limit, when its client has been answered already) submits nothing.
pub fn submit(
    coord: &Mutex<Coordinator>,
    spec: JobSpec,
    key: Option<&str>,
    deadline: Option<Instant>,
) -> Result<(String, bool), CoordError> {
    let started = Instant::now();
    let lock = || coord.lock().unwrap_or_else(|e| e.into_inner());
    let request = request_hash(&spec);
    if let Some(id) = keyed(coord, key, &request)? {
        return Ok((id, false));
    }
    // Its bundle's files stay while it loads, whatever job is deleted meanwhile.
    let (loader, ticket) = {
        let mut c = lock();
        c.tickets += 1;
        let ticket = c.tickets;
        c.loading.insert(ticket, spec.bundle.clone());
        (c.loader(), ticket)
    };
    struct Loading<'a>(&'a Mutex<Coordinator>, u64);
    impl Drop for Loading<'_> {
        fn drop(&mut self) {
            self.0.lock().unwrap_or_else(|e| e.into_inner()).loading.remove(&self.1);
        }
    }
    let _loading = Loading(coord, ticket);
    // A load past the deadline stops there (its error says so): either way, nothing is submitted.
    let frames = spec.frames.map(|r| r.count());
    let job = loader.submitted(spec, key, deadline);
    if deadline.is_some_and(|d| Instant::now() > d) {
        let took = started.elapsed().as_secs_f64();
        return Err(CoordError::TooLarge(match frames {
            // Where it stopped: the frame whose load ran out of time.
            Some(n) => format!(
                "loading and checking the {n} frames took {took:.1} s, longer than the request may take{}; nothing was submitted",
                job.as_ref().err().map(|e| format!(" ({e})")).unwrap_or_default()
            ),
            None => format!(
                "the scene took {took:.1} s to load, longer than the request may take; nothing was submitted"
            ),
        }));
    }
    let (id, jobs) = job?;
    let id = loop {
        // A submission with the same key that finished meanwhile wins, once its row is stored.
        if let Some(id) = keyed(coord, key, &request)? {
            return Ok((id, false));
        }
        let mut c = lock();
        if c.idempotent(key, &request)?.is_none() {
            break c.insert_jobs(id, jobs, key, &request)?;
        }
    };
    // Answered only once its row is stored; if it cannot be, the job is taken back (no
    // writer may be storing it meanwhile).
    if let Err(e) = sync_rows(coord) {
        let writer = lock().row_writer.clone();
        let _turn = writer.lock().unwrap_or_else(|e| e.into_inner());
        if lock().unsubmit(&id) {
            return Err(e);
        }
    }
    Ok((id, true))
}

/// The job an idempotency key names, once its row is stored: a job whose row is still being
/// written (or fails, and is taken back) is not answered for.
fn keyed(coord: &Mutex<Coordinator>, key: Option<&str>, request: &str) -> Result<Option<String>, CoordError> {
    loop {
        let found = {
            let c = coord.lock().unwrap_or_else(|e| e.into_inner());
            c.idempotent(key, request)?.map(|id| {
                let pending = c.unstored(&id);
                (id, pending)
            })
        };
        match found {
            Some((_, true)) => sync_rows(coord)?,
            other => return Ok(other.map(|(id, _)| id)),
        }
    }
}

/// The first check of an upload, before its body is decoded: the chunk must be leased under
/// `epoch`. Returns the most bytes its partial may decompress to.
pub fn check_upload(
    coord: &Mutex<Coordinator>,
    job: &str,
    chunk: u32,
    epoch: u64,
) -> Result<usize, CoordError> {
    let mut c = coord.lock().unwrap_or_else(|e| e.into_inner());
    let max = c.max_partial;
    let checked = c.leased(job, chunk, epoch).map(|j| j.window(chunk));
    drop(c);
    let (_, _, w, h) = checked.inspect_err(|_| count_duplicate(coord, job, chunk))?;
    // No more than this chunk's partial can hold, however well the body compresses.
    Ok(furnace_proto::partial_size_limit(w, h).min(max))
}

/// Counts a refused upload of a chunk that is already merged (a lease that expired while its
/// worker was still rendering, or a retried upload whose first attempt got through).
fn count_duplicate(coord: &Mutex<Coordinator>, job: &str, chunk: u32) {
    let c = coord.lock().unwrap_or_else(|e| e.into_inner());
    let merged = |j: &Job| {
        !matches!(j.state, JobState::Cancelled | JobState::Paused)
            && (j.released.is_some() || matches!(j.chunks.get(chunk as usize), Some(ChunkState::Done)))
    };
    if c.jobs.get(job).is_some_and(merged) {
        metrics::counter!("furnace_duplicate_uploads_total").increment(1);
    }
}

impl Snapshot {
    /// Stores the checkpoint (merged chunk ids and accumulation), which drops the partials in
    /// it; for a finished job, also its result and final status.
    fn write(&self, store: &dyn Store) -> Result<(), CoordError> {
        let t = Instant::now();
        let header = serde_json::to_vec(&CheckpointHeader {
            merged: self.ids.clone(),
            skipped: self.skipped.clone(),
            tile_sums: self.tile_sums.iter().map(|s| s.to_bits()).collect(),
        })
        .map_err(|e| CoordError::Internal(e.to_string()))?;
        // Encoded as it is written: no copy of the accumulation is made.
        let write = |out: &mut dyn std::io::Write| {
            out.write_all(&(header.len() as u64).to_le_bytes())?;
            out.write_all(&header)?;
            furnace_proto::write_chunk(&self.accum, Some(&self.stats), out)
        };
        let result = self.status.as_ref().map(|_| self.accum.develop());
        let size = store.save_checkpoint(&self.job, &write, &self.new, result.as_ref())?;
        if let Some(st) = &self.status {
            store.save_status(&self.job, st)?;
        }
        metrics::histogram!("furnace_checkpoint_duration_seconds").record(t.elapsed().as_secs_f64());
        metrics::counter!("furnace_checkpoint_bytes_total").increment(size);
        tracing::info!(job = %self.job, bytes = size, "checkpoint written in {:.3} s", t.elapsed().as_secs_f64());
        Ok(())
    }
}

/// The chunks a checkpoint holds, and those its job skips.
#[derive(serde::Serialize, serde::Deserialize)]
struct CheckpointHeader {
    merged: Vec<u32>,
    #[serde(default)]
    skipped: Vec<u32>,
    /// Noise-target jobs: each tile's sum of its merged passes' estimates (`Job::tile_sum`),
    /// as f64 bits (exact through JSON); absent for other jobs.
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    tile_sums: Vec<u64>,
}

fn decode_checkpoint(bytes: &[u8], max: usize) -> Result<CheckpointParts, String> {
    let n =
        u64::from_le_bytes(bytes.get(..8).ok_or("truncated")?.try_into().map_err(|_| "truncated")?) as usize;
    let end = n.checked_add(8).filter(|&e| e <= bytes.len()).ok_or("truncated header")?;
    let h: CheckpointHeader = serde_json::from_slice(&bytes[8..end]).map_err(|e| e.to_string())?;
    let (acc, stats) = decode_chunk(&bytes[end..], max).map_err(|e| e.to_string())?;
    Ok((h.merged, h.skipped, h.tile_sums, acc, stats))
}

/// What a checkpoint holds: merged chunks, skipped chunks, the tiles' sums (f64 bits), the
/// accumulation and its statistics.
type CheckpointParts = (Vec<u32>, Vec<u32>, Vec<u64>, Accum, Option<RenderStats>);

#[cfg(test)]
mod tests {
    use super::*;

    fn tiny_scene() -> Arc<Scene> {
        let xml = r#"<scene version="3.0.0"><sensor type="perspective"><float name="fov" value="40"/>
            <transform name="to_world"><lookat origin="0, 0, 5" target="0, 0, 0" up="0, 1, 0"/></transform>
            <film type="hdrfilm"><integer name="width" value="4"/><integer name="height" value="4"/></film>
            </sensor><emitter type="constant"/></scene>"#;
        Arc::new(Scene::load_str(xml, Path::new("tiny.xml"), &[]).unwrap())
    }

    fn submit(c: &mut Coordinator, priority: i32) -> String {
        let settings = JobSettings {
            width: 0,
            height: 0,
            spp: 4,
            tile_size: 4,
            spp_per_chunk: 1,
            priority,
            ..Default::default()
        };
        c.submit_scene(tiny_scene(), settings).unwrap()
    }

    /// A noise-target tile of eight passes whose first holds a firefly: the firefly's error
    /// (the first pass's estimate, about 0.21) is judged with every pass after it, its share
    /// falling as 1/passes^2, so the tile stops after five passes (0.21 / 25 < 0.1^2). Judged
    /// by the last pass alone the second, clean pass stopped it; a sum over the passes rather
    /// than their square, or none at all, would render all eight. A tile clean from the start
    /// stops after its first pass.
    #[test]
    fn a_firefly_keeps_its_tile_sampling() {
        let run = |firefly: bool| {
            let coord = Mutex::new(Coordinator::ephemeral().unwrap());
            let settings = JobSettings {
                spp: 16,
                tile_size: 4,
                spp_per_chunk: 2,
                target_rel_error: Some(0.1),
                ..Default::default()
            };
            let job = coord.lock().unwrap().submit_scene(tiny_scene(), settings).unwrap();
            let mut leased = Vec::new();
            loop {
                // (Its own statement: the guard must not live through the loop's body.)
                let lease = coord.lock().unwrap().lease("w", Instant::now());
                let Some(l) = lease else { break };
                let pass = l.chunk.id; // one tile: chunk k is pass k
                leased.push(pass);
                let r = l.chunk.region;
                let mut acc = Accum::new(r.x0, r.y0, r.x1 - r.x0, r.y1 - r.y0);
                for y in r.y0..r.y1 {
                    for x in r.x0..r.x1 {
                        for k in 0..(r.s1 - r.s0) as u32 {
                            let v = if firefly && pass == 0 && (x, y, k) == (1, 2, 0) {
                                200.0
                            } else {
                                0.5 + 0.01 * ((x + 3 * y + k) % 3) as f32
                            };
                            let l = furnace_core::math::Rgb::splat(v);
                            acc.count_sample(x, y, l);
                            acc.splat(x, y, 1.0, l);
                        }
                    }
                }
                accept_partial(&coord, &l.job, l.chunk.id, l.epoch, &acc, None, None).unwrap();
            }
            assert_eq!(coord.lock().unwrap().status(&job).unwrap().state, JobState::Done);
            leased
        };
        assert_eq!(run(false), vec![0]);
        assert_eq!(run(true), vec![0, 1, 2, 3, 4]);
    }

    /// A coordinator over a data folder with one stored job `j` (key `k`) of the tiny scene.
    fn stored(name: &str) -> (PathBuf, Arc<Mutex<Coordinator>>) {
        let dir = std::env::temp_dir().join(format!("furnace-state-{name}-{}", std::process::id()));
        std::fs::remove_dir_all(&dir).ok();
        let mut c = Coordinator::open(&dir).unwrap();
        let bundle = Bundle { scene: "tiny.xml".into(), files: BTreeMap::new() };
        let settings = JobSettings { spp: 4, tile_size: 4, spp_per_chunk: 1, ..Default::default() };
        let spec = JobSpec::new(bundle, settings);
        let job = c.loader().job_from_scene("j".into(), spec, JobState::Queued, 1, tiny_scene()).unwrap();
        c.insert_jobs(job.id.clone(), vec![job], Some("k"), "h").unwrap();
        c.write_rows_now().unwrap();
        (dir, Arc::new(Mutex::new(c)))
    }

    fn stored_row(dir: &Path, id: &str) -> Option<(i32, String)> {
        let db = rusqlite::Connection::open(dir.join("furnace.db")).unwrap();
        db.query_row("SELECT spec, state FROM jobs WHERE id = ?1", [id], |r| {
            let spec: JobSpec = serde_json::from_str(&r.get::<_, String>(0)?).unwrap();
            Ok((spec.settings.priority, r.get(1)?))
        })
        .ok()
    }

    /// Issue 14: job rows were written to SQLite (and synced) under the coordinator's lock, so
    /// one slow write held every lease, upload and status. Now the lock is free meanwhile, and
    /// the store still ends with the latest row.
    #[test]
    fn job_rows_are_stored_without_the_lock() {
        let (dir, coord) = stored("unlocked");
        // Another connection holds the database: the next row write waits for it.
        let mut db = rusqlite::Connection::open(dir.join("furnace.db")).unwrap();
        let held = db.transaction_with_behavior(rusqlite::TransactionBehavior::Exclusive).unwrap();
        let c2 = coord.clone();
        let writer = std::thread::spawn(move || set_priority(&c2, "j", 7));
        std::thread::sleep(Duration::from_millis(300));
        assert!(!writer.is_finished(), "the write did not wait for the database");
        let t = Instant::now();
        let lease = coord.try_lock().expect("the lock is held while the row is written").lease("w", t);
        assert!(lease.is_some() && t.elapsed() < Duration::from_millis(100));
        assert_eq!(coord.lock().unwrap().status("j").unwrap().settings.priority, 7);
        held.rollback().unwrap();
        writer.join().unwrap().unwrap();
        assert_eq!(stored_row(&dir, "j"), Some((7, "queued".into())));
        // The lease's change (running) is stored by the next sync, the server's timer's.
        assert!(coord.lock().unwrap().rows_due());
        sync_rows(&coord).unwrap();
        assert_eq!(stored_row(&dir, "j"), Some((7, "running".into())));
        delete(&coord, "j").unwrap();
        assert_eq!(stored_row(&dir, "j"), None);
        assert!(!dir.join("jobs/j").exists());
        std::fs::remove_dir_all(&dir).ok();
    }

    /// A submission whose row cannot be stored is taken back whole (its key too), and no later
    /// write stores it.
    #[test]
    fn a_submission_whose_row_fails_is_taken_back() {
        let (dir, coord) = stored("unstored");
        let mut c = coord.lock().unwrap();
        // The key is forgotten in memory only: storing it again breaks the row's UNIQUE key.
        c.keys.clear();
        let spec = c.jobs["j"].spec.clone();
        let job = c.loader().job_from_scene("j2".into(), spec, JobState::Queued, 2, tiny_scene()).unwrap();
        c.insert_jobs(job.id.clone(), vec![job], Some("k"), "h").unwrap();
        c.reprioritise("j", 3).unwrap();
        c.write_rows_now().unwrap_err();
        assert!(c.unsubmit("j2"));
        assert!(c.status("j2").is_err() && c.idempotent(Some("k"), "h").unwrap().is_none());
        c.write_rows_now().unwrap();
        drop(c);
        assert_eq!((stored_row(&dir, "j"), stored_row(&dir, "j2")), (Some((3, "queued".into())), None));
        std::fs::remove_dir_all(&dir).ok();
    }

    /// Review of issue 14: between a job's last merge and its final checkpoint (written
    /// without the lock), a cancel would race the checkpoint that makes it done. It is refused
    /// in that window; the job ends done.
    #[test]
    fn a_cancel_between_the_last_merge_and_done_is_refused() {
        let (dir, coord) = stored("finishing");
        let mut c = coord.lock().unwrap();
        let scene = tiny_scene();
        let mut last = None;
        while let Some(l) = c.lease("w", Instant::now()) {
            let acc = furnace_core::render_region(&scene, &l.chunk.region, 0).0;
            last = c.merge_partial("j", l.chunk.id, l.epoch, &acc, None, Instant::now()).unwrap();
        }
        let snap = last.expect("the last merge makes the final checkpoint");
        assert_eq!(snap.status.as_ref().map(|s| s.state), Some(JobState::Done));
        let e = c.control("j", "cancel").err().expect("refused");
        assert!(matches!(&e, CoordError::Refused(m) if m.contains("finishing")), "{e:?}");
        let store = c.store();
        let written = snap.write(&*store);
        assert!(c.checkpoint_written(&snap, &written).is_none());
        assert_eq!(c.status("j").unwrap().state, JobState::Done);
        let e = c.control("j", "cancel").err().expect("refused");
        assert!(matches!(&e, CoordError::Refused(m) if m.contains("is done")), "{e:?}");
        drop(c);
        std::fs::remove_dir_all(&dir).ok();
    }

    /// Review of issue 14: a job was leased, and a repeated submission answered with it,
    /// before its row (and its folder, where its partials go) was stored. Both now wait for
    /// the row.
    #[test]
    fn a_job_is_leased_and_named_by_its_key_only_once_its_row_is_stored() {
        let (dir, coord) = stored("pending");
        let mut c = coord.lock().unwrap();
        while c.lease("w", Instant::now()).is_some() {}
        let spec = c.jobs["j"].spec.clone();
        let job = c.loader().job_from_scene("j2".into(), spec, JobState::Queued, 2, tiny_scene()).unwrap();
        c.insert_jobs(job.id.clone(), vec![job], Some("k2"), "h2").unwrap();
        assert!(c.lease("w", Instant::now()).is_none(), "leased before its row is stored");
        assert!(!dir.join("jobs/j2").exists());
        drop(c);
        assert_eq!(keyed(&coord, Some("k2"), "h2").unwrap().as_deref(), Some("j2"));
        assert_eq!(stored_row(&dir, "j2"), Some((0, "queued".into())), "answered before its row was stored");
        assert_eq!(coord.lock().unwrap().lease("w", Instant::now()).map(|l| l.job).as_deref(), Some("j2"));
        std::fs::remove_dir_all(&dir).ok();
    }

    /// Review of issue 14: deleting a job removed the bundle and files no stored row used,
    /// though a submission loading the same bundle (not stored yet) needed them.
    #[test]
    fn a_delete_leaves_the_files_of_a_submission_still_loading() {
        let (dir, coord) = stored("loading");
        let bundle = coord.lock().unwrap().jobs["j"].spec.bundle.clone();
        let laid_out = dir.join("bundles").join(bundle.hash());
        std::fs::create_dir_all(&laid_out).unwrap();
        coord.lock().unwrap().loading.insert(1, bundle.clone());
        delete(&coord, "j").unwrap();
        assert!(!dir.join("jobs/j").exists());
        assert!(laid_out.is_dir(), "the bundle of a submission under way was removed");
        std::fs::remove_dir_all(&dir).ok();
    }

    /// Issue 14: the priority was negated to sort, so i32::MIN overflowed and went first.
    #[test]
    fn the_highest_priority_goes_first_at_the_extremes() {
        let mut c = Coordinator::ephemeral().unwrap();
        let low = submit(&mut c, i32::MIN);
        let high = submit(&mut c, i32::MAX);
        let now = Instant::now();
        assert_eq!(c.lease("w", now).unwrap().job, high);
        c.reprioritise(&high, i32::MIN + 1).unwrap();
        assert_eq!(c.lease("w", now).unwrap().job, high);
        c.reprioritise(&low, 0).unwrap();
        assert_eq!(c.lease("w", now).unwrap().job, low);
    }

    /// Issue 14: six 20 MiB failure messages made every status response 120 MiB. (2 MiB here.)
    #[test]
    fn failure_messages_are_cut_and_only_the_latest_kept() {
        let mut c = Coordinator::ephemeral().unwrap();
        let job = submit(&mut c, 0);
        let huge = "é".repeat(1 << 20);
        for k in 0..MAX_ERRORS + 20 {
            let l = c.lease(&format!("w{k}"), Instant::now()).unwrap();
            c.fail(&job, l.chunk.id, l.epoch, &huge).unwrap();
        }
        let s = c.status(&job).unwrap();
        assert_eq!(s.errors.len(), MAX_ERRORS);
        assert!(s.errors.iter().all(|e| e.len() <= MAX_ERROR_BYTES + 6 && e.ends_with("[cut]")));
        assert!(s.errors[MAX_ERRORS - 1].starts_with(&format!("worker w{}", MAX_ERRORS + 19)));
    }

    /// Review of issue 14: a queue entry for a chunk merged meanwhile (after a quarantine, a
    /// noise-target job's next pass could be queued twice) was leased again and merged twice.
    #[test]
    fn only_pending_chunks_are_leased() {
        let mut c = Coordinator::ephemeral().unwrap();
        let job = submit(&mut c, 0);
        let first = c.lease("w", Instant::now()).unwrap();
        let coord = Mutex::new(c);
        let acc = furnace_core::render_region(&tiny_scene(), &first.chunk.region, 0).0;
        accept_partial(&coord, &job, first.chunk.id, first.epoch, &acc, None, None).unwrap();
        let mut c = coord.into_inner().unwrap();
        c.jobs.get_mut(&job).unwrap().queue.push_front(first.chunk.id);
        let leased: Vec<u32> =
            std::iter::from_fn(|| c.lease("w", Instant::now())).map(|l| l.chunk.id).collect();
        assert_eq!(leased.len(), 3, "{leased:?}");
        assert!(!leased.contains(&first.chunk.id));
    }

    /// Probe of issue 14: every new worker name swept the whole registry under the lock. Now
    /// it is swept at most once a minute, and the list never shows a worker silent for an hour.
    #[test]
    fn workers_silent_for_an_hour_are_forgotten_without_a_sweep_per_name() {
        let mut c = Coordinator::ephemeral().unwrap();
        let t0 = Instant::now();
        for k in 0..100 {
            c.seen(&format!("old-{k}"), t0);
        }
        let later = t0 + FORGET_WORKER + Duration::from_secs(1);
        c.seen("new-0", later);
        assert_eq!(c.workers.len(), 1, "the first new name after an hour sweeps");
        for k in 0..100 {
            c.seen(&format!("old-{k}"), later);
        }
        let much_later = later + FORGET_WORKER + Duration::from_secs(1);
        c.seen("new-1", much_later);
        c.seen("new-2", much_later + Duration::from_secs(1));
        // Swept once more at new-1; new-2 within the minute does not sweep again.
        assert_eq!(c.workers.len(), 2);
        let listed: Vec<String> =
            c.workers(much_later + Duration::from_secs(1)).into_iter().map(|w| w.name).collect();
        assert_eq!(listed, ["new-1", "new-2"]);
    }

    /// Issue 14: an upload in flight when a job was cancelled turned it into done.
    #[test]
    fn cancel_revokes_the_leases_in_flight() {
        let mut c = Coordinator::ephemeral().unwrap();
        let job = submit(&mut c, 0);
        let leases: Vec<_> = std::iter::from_fn(|| c.lease("w", Instant::now())).collect();
        assert_eq!(leases.len(), 4);
        assert!(c.control(&job, "cancel").unwrap().is_none(), "nothing to store in memory");
        assert_eq!(c.status(&job).unwrap().chunks_leased, 0);
        let coord = Mutex::new(c);
        let scene = tiny_scene();
        for l in &leases {
            let acc = furnace_core::render_region(&scene, &l.chunk.region, 0).0;
            let e = accept_partial(&coord, &job, l.chunk.id, l.epoch, &acc, None, None).unwrap_err();
            assert!(matches!(&e, CoordError::Refused(m) if m.contains("cancelled")), "{e:?}");
        }
        let c = coord.lock().unwrap();
        assert_eq!(c.status(&job).unwrap().state, JobState::Cancelled);
        assert_eq!(c.status(&job).unwrap().chunks_done, 0);
    }
}
