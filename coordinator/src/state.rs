//! The coordinator's state: jobs, their chunks and leases, the exact merge, and persistence.
//!
//! Durability: an accepted partial is written to `jobs/{id}/partials/{chunk}.zst` (temporary
//! file, fsync, rename) before the upload is acknowledged; the merged image lives in memory and
//! in a checkpoint (`jobs/{id}/checkpoint`: the merged accumulation plus the set of chunks in
//! it), written atomically every `CHECKPOINT_EVERY` merges and at the end, after which the
//! partials it contains are deleted. After a crash, a job's image is its checkpoint plus every
//! partial not in it: nothing acknowledged is lost and nothing is merged twice. Jobs themselves
//! (spec, state, priority, idempotency key) are rows in SQLite (WAL). Leases live in memory:
//! after a restart every unfinished chunk is pending again, under epochs above all earlier ones.

use std::collections::{BTreeMap, HashMap, HashSet, VecDeque};
use std::io::Write;
use std::path::{Path, PathBuf};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use furnace_core::{Accum, Scene};
use furnace_proto::{
    chunk_plan, decode_partial, encode_partial, Bundle, ChunkSpec, JobSettings, JobSpec, JobState, JobStatus,
    Lease,
};

/// Merges between checkpoints (at least; see `Coordinator::checkpoint_interval`).
const CHECKPOINT_EVERY: usize = 256;
/// The database: jobs (spec, state, idempotency key) and the boot counter.
const SCHEMA: &str = "CREATE TABLE IF NOT EXISTS jobs (
        id TEXT PRIMARY KEY, spec TEXT NOT NULL, state TEXT NOT NULL,
        idempotency_key TEXT UNIQUE, created INTEGER NOT NULL);
    CREATE TABLE IF NOT EXISTS meta (key TEXT PRIMARY KEY, value INTEGER NOT NULL);";
/// Brings a database made by an earlier version up to date.
fn migrate(db: &rusqlite::Connection) -> Result<(), CoordError> {
    let has = |col: &str| -> Result<bool, CoordError> {
        let n: i64 =
            db.query_row("SELECT COUNT(*) FROM pragma_table_info('jobs') WHERE name = ?1", [col], |r| {
                r.get(0)
            })?;
        Ok(n > 0)
    };
    if !has("request_hash")? {
        // The hash of the spec an idempotency key was first used with.
        db.execute_batch("ALTER TABLE jobs ADD COLUMN request_hash TEXT")?;
    }
    Ok(())
}

/// The hash of a submitted spec, as submitted (before the scene fills in its defaults).
fn request_hash(spec: &JobSpec) -> String {
    blake3::hash(&serde_json::to_vec(spec).unwrap_or_default()).to_hex().to_string()
}

/// Failures of one worker on one job after which it gets no more of that job's chunks.
pub const MAX_FAILURES_PER_WORKER: u32 = 3;
/// Errors a job keeps for its status (the most recent), and the longest kept, in bytes.
pub const MAX_ERRORS: usize = 100;
pub const MAX_ERROR_BYTES: usize = 2048;
/// Workers a job's status lists (the most recent).
pub const MAX_JOB_WORKERS: usize = 1000;

#[derive(Debug, thiserror::Error)]
pub enum CoordError {
    #[error("{0}")]
    BadRequest(String),
    #[error("{0}")]
    NotFound(String),
    #[error("{0}")]
    Conflict(String),
    #[error("{0}")]
    Unprocessable(String),
    #[error("internal error: {0}")]
    Internal(String),
}

impl From<std::io::Error> for CoordError {
    fn from(e: std::io::Error) -> Self {
        CoordError::Internal(e.to_string())
    }
}
impl From<rusqlite::Error> for CoordError {
    fn from(e: rusqlite::Error) -> Self {
        CoordError::Internal(format!("database: {e}"))
    }
}

#[derive(Clone, Debug)]
enum ChunkState {
    Pending,
    Leased {
        epoch: u64,
        worker: String,
        deadline: Instant,
        /// When it was handed out, for the chunk duration metric.
        since: Instant,
    },
    Done,
    /// Not rendered: its tile reached the job's target error first.
    Skipped,
}

struct Job {
    id: String,
    spec: JobSpec,
    /// `spec.bundle.hash()`, computed once: every lease carries it.
    bundle_hash: String,
    state: JobState,
    plan: Vec<ChunkSpec>,
    chunks: Vec<ChunkState>,
    /// Pending chunks in hand-out order: requeued ones go to the front.
    queue: VecDeque<u32>,
    accum: Accum,
    /// Chunks whose partial is in `accum`.
    merged: HashSet<u32>,
    /// Chunks not to render: their tile reached the target error (noise-target jobs).
    skipped: HashSet<u32>,
    /// Each tile's latest error estimate (noise-target jobs; NaN until known).
    tile_est: Vec<f64>,
    /// The whole image's estimated relative MSE and the samples it was computed at: a pass over
    /// the full accumulation, so status polls reuse it for a second unless the job is complete.
    est_cache: std::cell::Cell<Option<(Instant, u64, f64)>>,
    /// Chunks in the last checkpoint.
    checkpointed: HashSet<u32>,
    since_checkpoint: usize,
    /// A checkpoint is being written (outside the lock).
    checkpointing: bool,
    /// When the last checkpoint failed (a full disk), for [`retry_checkpoints`].
    checkpoint_failed: Option<Instant>,
    last_checkpoint: Instant,
    /// Filter margin of the scene, for checking partial sizes.
    margin: u32,
    render_plan: String,
    failures: HashMap<String, u32>,
    errors: Vec<String>,
    /// The loaded scene, kept for workers in this process (`furnace render`, `--local-workers`).
    scene: Option<Arc<Scene>>,
    workers: BTreeMap<String, Instant>,
    /// (time, samples) of recent merges, for the rate.
    recent: VecDeque<(Instant, u64)>,
    samples_done: u64,
    created: u64,
    /// A finished job keeps only its final status (and its result on disk): the plan, the
    /// chunk states, the accumulation and the scene are released.
    final_status: Option<Box<JobStatus>>,
}

impl Job {
    fn dir(&self, data: &Path) -> PathBuf {
        data.join("jobs").join(&self.id)
    }

    /// A chunk's partial rectangle (x0, y0, width, height): its tile grown by the filter's
    /// margin, clipped to the image.
    fn window(&self, chunk: u32) -> (u32, u32, u32, u32) {
        let s = &self.spec.settings;
        let r = &self.plan[chunk as usize].region;
        let m = self.margin;
        let x0 = r.x0.saturating_sub(m);
        let y0 = r.y0.saturating_sub(m);
        (x0, y0, (r.x1 + m).min(s.width) - x0, (r.y1 + m).min(s.height) - y0)
    }

    /// Checks that `acc` is a partial of `chunk`: its rectangle (the chunk's tile grown by the
    /// filter margin) and its sample count.
    fn fits(&self, chunk: u32, acc: &Accum) -> Result<(), String> {
        let r = &self.plan[chunk as usize].region;
        let want = self.window(chunk);
        let got = (acc.x0, acc.y0, acc.width, acc.height);
        if got != want {
            return Err(format!(
                "partial covers {}x{} at ({}, {}); chunk {chunk} needs {}x{} at ({}, {})",
                got.2, got.3, got.0, got.1, want.2, want.3, want.0, want.1
            ));
        }
        let expected = r.samples();
        if acc.sample_count() != expected {
            return Err(format!(
                "partial holds {} samples; chunk {chunk} has {expected}",
                acc.sample_count()
            ));
        }
        // Filters weigh samples by non-negative weights and radiance is non-negative: no sum
        // can be negative, and no pixel gets more than the chunk's samples per pixel.
        let spp = r.s1 - r.s0;
        let bad = acc
            .pixels
            .iter()
            .position(|p| p.weight < 0 || p.lum2 < 0 || p.rgb.iter().any(|&c| c < 0) || p.count > spp);
        if let Some(i) = bad {
            let (x, y) = (acc.x0 + i as u32 % acc.width, acc.y0 + i as u32 / acc.width);
            return Err(format!("partial pixel ({x}, {y}) holds a negative sum or more than {spp} samples"));
        }
        Ok(())
    }

    /// A finished job as a restart restores it: its final status, nothing else.
    fn finished(id: String, spec: JobSpec, created: u64, status: JobStatus) -> Job {
        let mut job = Job::new(id, spec, JobState::Done, created, Vec::new(), Accum::new(0, 0, 0, 0));
        job.render_plan = status.plan.clone();
        job.errors = status.errors.clone();
        job.samples_done = status.samples_done;
        job.accum.dropped = status.dropped_samples;
        job.release(status);
        job
    }

    /// A job with its plan and accumulation, every chunk pending, nothing queued yet.
    fn new(
        id: String,
        spec: JobSpec,
        state: JobState,
        created: u64,
        plan: Vec<ChunkSpec>,
        accum: Accum,
    ) -> Job {
        Job {
            bundle_hash: spec.bundle.hash(),
            id,
            spec,
            state,
            chunks: vec![ChunkState::Pending; plan.len()],
            plan,
            queue: VecDeque::new(),
            accum,
            merged: HashSet::new(),
            skipped: HashSet::new(),
            tile_est: Vec::new(),
            est_cache: std::cell::Cell::new(None),
            checkpointed: HashSet::new(),
            since_checkpoint: 0,
            checkpointing: false,
            checkpoint_failed: None,
            last_checkpoint: Instant::now(),
            margin: 0,
            render_plan: String::new(),
            failures: HashMap::new(),
            errors: Vec::new(),
            scene: None,
            workers: BTreeMap::new(),
            recent: VecDeque::new(),
            samples_done: 0,
            created,
            final_status: None,
        }
    }

    /// Keeps `status` as the job's final status and lets go of everything else.
    fn release(&mut self, status: JobStatus) {
        let dropped = self.accum.dropped;
        self.accum = Accum::new(0, 0, 0, 0);
        self.accum.dropped = dropped;
        self.plan = Vec::new();
        self.chunks = Vec::new();
        self.queue = VecDeque::new();
        self.merged = HashSet::new();
        self.skipped = HashSet::new();
        self.checkpointed = HashSet::new();
        self.tile_est = Vec::new();
        self.recent = VecDeque::new();
        self.failures = HashMap::new();
        self.workers = BTreeMap::new(); // the final status lists them
        self.scene = None;
        self.final_status = Some(Box::new(status));
    }

    /// Records an error for the job's status: at most [`MAX_ERROR_BYTES`] of it, and only the
    /// [`MAX_ERRORS`] most recent.
    fn record_error(&mut self, mut e: String) {
        if e.len() > MAX_ERROR_BYTES {
            let mut end = MAX_ERROR_BYTES;
            while !e.is_char_boundary(end) {
                end -= 1;
            }
            e.truncate(end);
            e.push_str(" [cut]");
        }
        if self.errors.len() == MAX_ERRORS {
            self.errors.remove(0);
        }
        self.errors.push(e);
    }

    /// Moves a stored file that cannot be used aside (into the job's `quarantine/`), logs it
    /// and records it in the job's errors: the chunks it held are rendered again.
    fn quarantine(&mut self, data: &Path, file: &Path, why: &str) {
        let dir = self.dir(data).join("quarantine");
        let name = file.file_name().map(|n| n.to_string_lossy().into_owned()).unwrap_or_default();
        let moved = std::fs::create_dir_all(&dir).and_then(|_| std::fs::rename(file, dir.join(&name)));
        let e = format!("stored {name} was unusable ({why}); moved to quarantine/, its chunks render again");
        tracing::error!(job = %self.id, "{e}");
        if let Err(m) = moved {
            tracing::error!(job = %self.id, "cannot move {} aside: {m}", file.display());
            std::fs::remove_file(file).ok();
        }
        self.record_error(e);
    }

    fn samples_total(&self) -> u64 {
        let s = &self.spec.settings;
        s.width as u64 * s.height as u64 * s.spp
    }

    /// A copy of the merge for a checkpoint, when one is due (after `CHECKPOINT_EVERY` merges
    /// and `interval`, and when the job is complete) and none is being written.
    fn snapshot(&mut self, data: &Path, interval: Duration) -> Option<Snapshot> {
        let finished = self.complete();
        let due = self.since_checkpoint >= CHECKPOINT_EVERY && self.last_checkpoint.elapsed() >= interval;
        if self.checkpointing || !(finished || due) {
            return None;
        }
        self.checkpointing = true;
        self.since_checkpoint = 0;
        self.last_checkpoint = Instant::now();
        let mut ids: Vec<u32> = self.merged.iter().copied().collect();
        ids.sort();
        let new = ids.iter().copied().filter(|id| !self.checkpointed.contains(id)).collect();
        let mut skipped: Vec<u32> = self.skipped.iter().copied().collect();
        skipped.sort();
        Some(Snapshot {
            job: self.id.clone(),
            dir: self.dir(data),
            ids,
            skipped,
            new,
            accum: self.accum.clone(),
            finished,
        })
    }

    /// Every chunk merged or skipped.
    fn complete(&self) -> bool {
        self.merged.len() + self.skipped.len() == self.plan.len()
    }

    /// After chunk `chunk` of a noise-target job is merged: estimate its tile's error from the
    /// chunk's own samples (its pass alone, so the decision depends only on deterministic
    /// partials, never on arrival order), then queue the tile's next pass or skip the rest.
    /// The pass's estimated relative MSE falls as 1/passes: after pass p it is est / (p + 1).
    fn follow_up(&mut self, chunk: u32, acc: &Accum) {
        let Some(target) = self.spec.settings.target_rel_error else { return };
        let n = self.spec.settings.tiles();
        let (tile, pass) = (chunk % n, chunk / n);
        let r = self.plan[chunk as usize].region;
        let mut own = Accum::new(r.x0, r.y0, r.x1 - r.x0, r.y1 - r.y0);
        own.merge(acc);
        let est = own.estimated_rel_mse() / (pass + 1) as f64;
        self.tile_est[tile as usize] = est;
        let next = chunk + n;
        if next as usize >= self.plan.len() {
            return;
        }
        if est <= target * target {
            for c in (next..self.plan.len() as u32).step_by(n as usize) {
                self.skipped.insert(c);
                self.chunks[c as usize] = ChunkState::Skipped;
            }
        } else {
            self.queue.push_back(next);
        }
    }

    /// The samples still to render: for noise-target jobs, each unfinished tile's passes
    /// predicted from its latest estimate (all its remaining passes while it has none).
    fn samples_left(&self) -> u64 {
        let s = &self.spec.settings;
        let Some(target) = s.target_rel_error else { return self.samples_total() - self.samples_done };
        let n = s.tiles();
        let passes = (self.plan.len() as u32).div_ceil(n);
        let mut left = 0;
        for tile in 0..n {
            let todo: Vec<u32> = (tile..self.plan.len() as u32)
                .step_by(n as usize)
                .filter(|c| !self.merged.contains(c) && !self.skipped.contains(c))
                .collect();
            let Some(&first) = todo.first() else { continue };
            let done = first / n;
            let est = self.tile_est[tile as usize];
            let need = if est.is_finite() {
                ((est * done as f64 / (target * target)).ceil() as u32).clamp(done + 1, passes)
            } else {
                passes
            };
            left += todo
                .iter()
                .take((need - done) as usize)
                .map(|&c| self.plan[c as usize].region.samples())
                .sum::<u64>();
        }
        left
    }

    /// The merge's estimated relative MSE, recomputed at most once a second while the job
    /// runs (always exact once it is complete).
    fn estimated_rel_mse(&self) -> f64 {
        if let Some((at, samples, e)) = self.est_cache.get() {
            let fresh =
                samples == self.samples_done || (at.elapsed() < Duration::from_secs(1) && !self.complete());
            if fresh {
                return e;
            }
        }
        let e = self.accum.estimated_rel_mse();
        self.est_cache.set(Some((Instant::now(), self.samples_done, e)));
        e
    }

    fn counts(&self) -> (u64, u64, u64) {
        let (mut done, mut leased, mut pending) = (0, 0, 0);
        for c in &self.chunks {
            match c {
                ChunkState::Done | ChunkState::Skipped => done += 1,
                ChunkState::Leased { .. } => leased += 1,
                ChunkState::Pending => pending += 1,
            }
        }
        (done, leased, pending)
    }
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
    data: PathBuf,
    /// Whether jobs, partials and results are stored in `data` (false: in memory only).
    persist: bool,
    db: rusqlite::Connection,
    jobs: BTreeMap<String, Job>,
    next_epoch: u64,
    pub lease_duration: Duration,
    /// Largest decompressed partial accepted (bytes).
    pub max_partial: usize,
    /// Keep each job's loaded scene for workers in this process.
    pub keep_scenes: bool,
    /// Time between tries of a checkpoint that failed.
    pub checkpoint_retry: Duration,
    /// Least time between two checkpoints of a job. A checkpoint encodes the job's whole
    /// accumulation (about a second for 1920 x 1080 here); between them, a restart replays the
    /// stored partials.
    pub checkpoint_interval: Duration,
    workers: BTreeMap<String, WorkerSeen>,
}

fn now_secs() -> u64 {
    std::time::SystemTime::now().duration_since(std::time::UNIX_EPOCH).map(|d| d.as_secs()).unwrap_or(0)
}

/// Writes `bytes` to `path` atomically: temporary file, fsync, rename, fsync of the folder.
pub fn write_atomic(path: &Path, bytes: &[u8]) -> std::io::Result<()> {
    let dir = path.parent().unwrap_or(Path::new("."));
    std::fs::create_dir_all(dir)?;
    // Unique, so that concurrent writes of one path never share a temporary file.
    static N: std::sync::atomic::AtomicU64 = std::sync::atomic::AtomicU64::new(0);
    let n = N.fetch_add(1, std::sync::atomic::Ordering::Relaxed);
    let name = path.file_name().and_then(|n| n.to_str()).unwrap_or("file");
    let tmp = dir.join(format!(".{name}.{}.{n}.tmp", std::process::id()));
    let written = std::fs::File::create(&tmp)
        .and_then(|mut f| f.write_all(bytes).and_then(|_| f.sync_all()))
        .and_then(|_| std::fs::rename(&tmp, path));
    if let Err(e) = written {
        // A full disk or the like: no temporary file is left behind.
        std::fs::remove_file(&tmp).ok();
        return Err(e);
    }
    if let Ok(d) = std::fs::File::open(dir) {
        d.sync_all().ok();
    }
    Ok(())
}

/// A job's image: developed from its accumulation in memory, or a finished job's result file.
pub enum Picture {
    Developed(furnace_core::Image),
    File(PathBuf),
}

impl Picture {
    /// The image, reading the file if need be (call it without the coordinator's lock).
    pub fn image(self) -> Result<furnace_core::Image, CoordError> {
        match self {
            Picture::Developed(img) => Ok(img),
            Picture::File(path) => furnace_core::Image::read_exr(&path)
                .map_err(|e| CoordError::Internal(format!("{}: {e}", path.display()))),
        }
    }
}

/// What loading a job's scene needs of the coordinator, taken out of it so that scenes are
/// loaded, validated and planned without its lock.
struct Loader {
    data: PathBuf,
    keep_scenes: bool,
}

impl Loader {
    /// A new job for a submitted spec: its bundle laid out, its scene loaded and checked.
    fn submitted(&self, spec: JobSpec, key: Option<&str>) -> Result<Job, CoordError> {
        static SUBMISSIONS: std::sync::atomic::AtomicU64 = std::sync::atomic::AtomicU64::new(0);
        let created = now_secs();
        let n = SUBMISSIONS.fetch_add(1, std::sync::atomic::Ordering::Relaxed);
        let nanos = std::time::SystemTime::now().duration_since(std::time::UNIX_EPOCH).map(|d| d.as_nanos());
        let seed = format!("{}-{nanos:?}-{key:?}-{n}-{}", spec.bundle.hash(), std::process::id());
        let id = blake3::hash(seed.as_bytes()).to_hex()[..16].to_string();
        self.new_job(id, spec, JobState::Queued, created)
    }

    fn file_path(&self, hash: &str) -> PathBuf {
        self.data.join("files").join(hash)
    }

    fn bundle_dir(&self, bundle_hash: &str) -> PathBuf {
        self.data.join("bundles").join(bundle_hash)
    }

    /// Lays the bundle's files out under `bundles/{hash}/` (once) and loads its scene.
    fn load_bundle(&self, spec: &JobSpec) -> Result<(PathBuf, Scene), CoordError> {
        let b = &spec.bundle;
        b.validate().map_err(CoordError::BadRequest)?;
        let missing: Vec<&str> =
            b.files.iter().filter(|(_, h)| !self.file_path(h).exists()).map(|(p, _)| p.as_str()).collect();
        if !missing.is_empty() {
            return Err(CoordError::BadRequest(format!(
                "bundle files not uploaded yet: {} (PUT /v1/files/{{hash}} first)",
                missing.join(", ")
            )));
        }
        let hash = b.hash();
        let dir = self.bundle_dir(&hash);
        let manifest = self.data.join("bundles").join(format!("{hash}.json"));
        let scene = if dir.is_dir() {
            // Laid out by an earlier submission.
            self.load_scene(&dir, b)?
        } else {
            // Laid out in a folder of this submission's own, loaded from there, then moved into
            // place: concurrent submissions of one bundle never share a half-made folder, and
            // one that fails leaves nothing behind.
            static N: std::sync::atomic::AtomicU64 = std::sync::atomic::AtomicU64::new(0);
            let n = N.fetch_add(1, std::sync::atomic::Ordering::Relaxed);
            let tmp = self.data.join("bundles").join(format!(".{hash}.{}.{n}.tmp", std::process::id()));
            let loaded = self.lay_out(b, &tmp).and_then(|_| self.load_scene(&tmp, b));
            // Another submission may have put the same bundle in place meanwhile: keep that.
            if loaded.is_err() || std::fs::rename(&tmp, &dir).is_err() {
                std::fs::remove_dir_all(&tmp).ok();
            }
            loaded?
        };
        if !manifest.exists() {
            write_atomic(&manifest, &serde_json::to_vec(b).unwrap_or_default())?;
        }
        Ok((dir, scene))
    }

    /// Loads the bundle's scene from where it is laid out; errors name files by their bundle
    /// paths, the client's own, not by this host's.
    fn load_scene(&self, dir: &Path, b: &Bundle) -> Result<Scene, CoordError> {
        Scene::load(&dir.join(&b.scene), &[]).map_err(|e| {
            let inside = format!("{}/", dir.display());
            CoordError::Unprocessable(format!(
                "the scene cannot be rendered: {}",
                e.to_string().replace(&inside, "")
            ))
        })
    }

    /// The bundle's files under their paths in a new folder `dir`: hard links to the stored
    /// files (copies where links cannot be made).
    fn lay_out(&self, b: &Bundle, dir: &Path) -> Result<(), CoordError> {
        for (path, h) in &b.files {
            let dst = dir.join(path);
            let made = dst.parent().map_or(Ok(()), std::fs::create_dir_all).and_then(|_| {
                std::fs::hard_link(self.file_path(h), &dst)
                    .or_else(|_| std::fs::copy(self.file_path(h), &dst).map(|_| ()))
            });
            made.map_err(|e| {
                CoordError::BadRequest(format!("bundle path '{path}' cannot be laid out: {e}"))
            })?;
        }
        Ok(())
    }

    fn new_job(&self, id: String, spec: JobSpec, state: JobState, created: u64) -> Result<Job, CoordError> {
        let (_, scene) = self.load_bundle(&spec)?;
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
            return Err(CoordError::Unprocessable(format!(
                "job size {}x{} differs from the scene's film {w}x{h}",
                s.width, s.height
            )));
        }
        if s.spp == 0 {
            s.spp = scene.spp as u64;
        }
        s.check_limits().map_err(CoordError::Unprocessable)?;
        if let Some(t) = s.target_rel_error {
            if !(t.is_finite() && t > 0.0) {
                return Err(CoordError::BadRequest(format!("target_rel_error must be positive, got {t}")));
            }
            if s.spp_per_chunk < 2 {
                return Err(CoordError::BadRequest(
                    "a noise-target job needs spp_per_chunk >= 2 (error is estimated from each chunk's samples)"
                        .into(),
                ));
            }
        }
        let plan = chunk_plan(s);
        let n = plan.len();
        // Noise-target jobs hand out a tile's next pass only once its last one is judged.
        let first = if s.target_rel_error.is_some() { (s.tiles() as usize).min(n) } else { n };
        let tiles = s.tiles() as usize;
        let mut job = Job::new(id, spec, state, created, plan, Accum::new(0, 0, w, h));
        job.queue = (0..first as u32).collect();
        job.tile_est = vec![f64::NAN; tiles];
        job.margin = scene.film.filter.margin();
        job.render_plan = scene.plan.to_string();
        job.scene = self.keep_scenes.then_some(scene);
        Ok(job)
    }
}

impl Coordinator {
    /// Opens (or creates) the data directory and resumes every unfinished job.
    pub fn open(data: &Path) -> Result<Coordinator, CoordError> {
        std::fs::create_dir_all(data.join("files"))?;
        std::fs::create_dir_all(data.join("jobs"))?;
        std::fs::create_dir_all(data.join("bundles"))?;
        // Bundle folders of submissions a crash interrupted.
        for e in std::fs::read_dir(data.join("bundles"))?.flatten() {
            if e.file_name().to_string_lossy().ends_with(".tmp") {
                std::fs::remove_dir_all(e.path()).ok();
            }
        }
        let db = rusqlite::Connection::open(data.join("furnace.db"))?;
        db.pragma_update(None, "journal_mode", "WAL")?;
        db.pragma_update(None, "synchronous", "FULL")?;
        db.execute_batch(SCHEMA)?;
        migrate(&db)?;
        // Epochs after a restart start above every epoch handed out before.
        let boot: i64 =
            db.query_row("SELECT value FROM meta WHERE key = 'boot'", [], |r| r.get(0)).unwrap_or(0) + 1;
        db.execute("INSERT OR REPLACE INTO meta (key, value) VALUES ('boot', ?1)", [boot])?;
        let mut c = Coordinator {
            data: data.to_path_buf(),
            persist: true,
            db,
            jobs: BTreeMap::new(),
            next_epoch: (boot as u64) << 32,
            lease_duration: Duration::from_secs(30),
            max_partial: 256 << 20,
            keep_scenes: false,
            checkpoint_retry: Duration::from_secs(5),
            checkpoint_interval: Duration::from_secs(10),
            workers: BTreeMap::new(),
        };
        let rows: Vec<(String, String, String, i64)> = {
            let mut st = c.db.prepare("SELECT id, spec, state, created FROM jobs ORDER BY created, id")?;
            let rows = st.query_map([], |r| Ok((r.get(0)?, r.get(1)?, r.get(2)?, r.get(3)?)))?;
            rows.collect::<Result<_, _>>()?
        };
        for (id, spec, state, created) in rows {
            // One job that cannot be restored is logged and left out; the others go on.
            let restored = serde_json::from_str::<JobSpec>(&spec)
                .map_err(|e| CoordError::Internal(format!("stored spec unreadable: {e}")))
                .and_then(|spec| {
                    let state: JobState = serde_json::from_value(serde_json::Value::String(state))
                        .map_err(|e| CoordError::Internal(format!("stored state unreadable: {e}")))?;
                    // A finished job with its final status on disk comes back without its scene.
                    let dir = c.data.join("jobs").join(&id);
                    let status = std::fs::read(dir.join("status.json")).ok();
                    let status = status.and_then(|b| serde_json::from_slice::<JobStatus>(&b).ok());
                    match status {
                        Some(st) if state == JobState::Done && dir.join("result.exr").exists() => {
                            Ok((Job::finished(id.clone(), spec, created as u64, st), state))
                        }
                        _ => Ok((c.restore_job(id.clone(), spec, state, created as u64)?, state)),
                    }
                });
            let (mut job, state) = match restored {
                Ok(r) => r,
                Err(e) => {
                    tracing::error!(job = %id, "cannot restore this job, left out until the next start: {e}");
                    continue;
                }
            };
            // Every chunk merged but the end not recorded (a crash or failure while writing
            // the final checkpoint): finish it now.
            let open = !matches!(state, JobState::Done | JobState::Cancelled);
            let snap = if open { job.snapshot(&c.data, c.checkpoint_interval) } else { None };
            let release = state == JobState::Done && job.final_status.is_none();
            c.jobs.insert(id.clone(), job);
            if release {
                if let Err(e) = c.evict(&id) {
                    tracing::error!(job = %id, "cannot release the finished job: {e}");
                }
            }
            if let Some(s) = snap {
                let result = s.write();
                c.checkpoint_written(&s, &result);
                if let Err(e) = result {
                    // The job stays open; its next merge or the next start writes it again.
                    tracing::error!(job = %s.job, "cannot write the final checkpoint: {e}");
                }
            }
        }
        Ok(c)
    }

    /// A coordinator that stores nothing: the one `furnace render` runs in its own process.
    /// Jobs are submitted with [`Coordinator::submit_scene`]; everything lives in memory.
    pub fn ephemeral() -> Result<Coordinator, CoordError> {
        let db = rusqlite::Connection::open_in_memory()?;
        db.execute_batch(SCHEMA)?;
        migrate(&db)?;
        Ok(Coordinator {
            data: PathBuf::new(),
            persist: false,
            db,
            jobs: BTreeMap::new(),
            next_epoch: 1 << 32,
            lease_duration: Duration::from_secs(30),
            max_partial: 256 << 20,
            keep_scenes: true,
            checkpoint_retry: Duration::from_secs(5),
            checkpoint_interval: Duration::from_secs(10),
            workers: BTreeMap::new(),
        })
    }

    pub fn data_dir(&self) -> &Path {
        &self.data
    }

    /// Path of a stored file by hash.
    pub fn file_path(&self, hash: &str) -> PathBuf {
        self.loader().file_path(hash)
    }

    fn bundle_dir(&self, hash: &str) -> PathBuf {
        self.loader().bundle_dir(hash)
    }

    fn loader(&self) -> Loader {
        Loader { data: self.data.clone(), keep_scenes: self.keep_scenes }
    }

    /// The job an idempotency key already names.
    /// A key used again with the same spec names the same job; with another spec, it is
    /// refused.
    fn idempotent(&self, key: Option<&str>, request: &str) -> Result<Option<String>, CoordError> {
        let Some(k) = key else { return Ok(None) };
        let found: Option<(String, Option<String>)> = self
            .db
            .query_row("SELECT id, request_hash FROM jobs WHERE idempotency_key = ?1", [k], |r| {
                Ok((r.get(0)?, r.get(1)?))
            })
            .ok();
        match found {
            Some((_, Some(h))) if h != request => {
                Err(CoordError::Conflict(format!("Idempotency-Key '{k}' was used for another job spec")))
            }
            other => Ok(other.map(|(id, _)| id)),
        }
    }

    /// Rebuilds a job after a restart: checkpoint plus every partial not in it.
    fn restore_job(
        &self,
        id: String,
        spec: JobSpec,
        state: JobState,
        created: u64,
    ) -> Result<Job, CoordError> {
        let mut job = self.loader().new_job(id, spec, state, created)?;
        let dir = job.dir(&self.data);
        // Temporary files of writes a crash interrupted.
        for d in [dir.clone(), dir.join("partials")] {
            for e in std::fs::read_dir(d).into_iter().flatten().flatten() {
                if e.file_name().to_string_lossy().ends_with(".tmp") {
                    std::fs::remove_file(e.path()).ok();
                }
            }
        }
        let checkpoint = dir.join("checkpoint");
        if let Ok(bytes) = std::fs::read(&checkpoint) {
            let n = job.plan.len();
            let limit = furnace_proto::partial_size_limit(job.accum.width, job.accum.height);
            let checked = decode_checkpoint(&bytes, limit).and_then(|(ids, skipped, acc)| {
                let a = &job.accum;
                if (acc.x0, acc.y0, acc.width, acc.height) != (a.x0, a.y0, a.width, a.height) {
                    return Err(format!(
                        "it covers {}x{}, the job {}x{}",
                        acc.width, acc.height, a.width, a.height
                    ));
                }
                if let Some(c) = ids.iter().chain(&skipped).find(|&&c| c as usize >= n) {
                    return Err(format!("it names chunk {c} of {n}"));
                }
                let merged: HashSet<u32> = ids.iter().copied().collect();
                match skipped.iter().find(|c| merged.contains(c)) {
                    Some(c) => Err(format!("it has chunk {c} both merged and skipped")),
                    None => Ok((ids, skipped, acc)),
                }
            });
            match checked {
                Ok((ids, skipped, acc)) => {
                    job.accum = acc;
                    job.merged = ids.iter().copied().collect();
                    job.skipped = skipped.into_iter().collect();
                    job.checkpointed = job.merged.clone();
                }
                Err(e) => job.quarantine(&self.data, &checkpoint, &e),
            }
        }
        if let Ok(entries) = std::fs::read_dir(dir.join("partials")) {
            let mut files: Vec<(u32, PathBuf)> = entries
                .flatten()
                .filter_map(|e| {
                    let name = e.file_name().into_string().ok()?;
                    let id = name.strip_suffix(".zst")?.parse().ok()?;
                    Some((id, e.path()))
                })
                .collect();
            files.sort();
            for (id, path) in files {
                if job.merged.contains(&id) || id as usize >= job.plan.len() {
                    std::fs::remove_file(&path).ok();
                    continue;
                }
                let acc = match std::fs::read(&path)
                    .map_err(|e| e.to_string())
                    .and_then(|bytes| decode_partial(&bytes, self.max_partial).map_err(|e| e.to_string()))
                    .and_then(|acc| job.fits(id, &acc).map(|_| acc))
                {
                    Ok(acc) => acc,
                    Err(e) => {
                        job.quarantine(&self.data, &path, &e);
                        continue;
                    }
                };
                job.accum.merge(&acc);
                job.merged.insert(id);
                job.follow_up(id, &acc);
            }
        }
        for &id in &job.merged {
            job.chunks[id as usize] = ChunkState::Done;
            job.samples_done += job.plan[id as usize].region.samples();
        }
        for &id in &job.skipped {
            job.chunks[id as usize] = ChunkState::Skipped;
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
            job.queue.retain(|id| !job.merged.contains(id));
        }
        Ok(job)
    }

    /// Submits a job; with an idempotency key already used, returns that job instead.
    pub fn submit(&mut self, spec: JobSpec, key: Option<&str>) -> Result<(String, bool), CoordError> {
        let request = request_hash(&spec);
        if let Some(id) = self.idempotent(key, &request)? {
            return Ok((id, false));
        }
        let job = self.loader().submitted(spec, key)?;
        self.insert_job(job, key, &request)
    }

    /// Submits a job for a scene already loaded in this process. Such a job has no bundle and
    /// is not stored: it lives as long as the process (`furnace render`).
    pub fn submit_scene(&mut self, scene: Arc<Scene>, settings: JobSettings) -> Result<String, CoordError> {
        let created = now_secs();
        let id = format!("local-{}", self.jobs.len());
        let spec = JobSpec { bundle: Bundle { scene: String::new(), files: BTreeMap::new() }, settings };
        let mut job =
            self.loader().job_from_scene(id.clone(), spec, JobState::Queued, created, scene.clone())?;
        job.scene = Some(scene);
        self.jobs.insert(id.clone(), job);
        Ok(id)
    }

    fn insert_job(
        &mut self,
        job: Job,
        key: Option<&str>,
        request: &str,
    ) -> Result<(String, bool), CoordError> {
        let (id, created) = (job.id.clone(), job.created);
        let spec_json = serde_json::to_string(&job.spec).map_err(|e| CoordError::Internal(e.to_string()))?;
        self.db.execute(
            "INSERT INTO jobs (id, spec, state, idempotency_key, created, request_hash)
             VALUES (?1, ?2, 'queued', ?3, ?4, ?5)",
            rusqlite::params![id, spec_json, key, created as i64, request],
        )?;
        if self.persist {
            std::fs::create_dir_all(job.dir(&self.data).join("partials"))?;
        }
        self.jobs.insert(id.clone(), job);
        Ok((id, true))
    }

    fn job_mut(&mut self, id: &str) -> Result<&mut Job, CoordError> {
        self.jobs.get_mut(id).ok_or_else(|| CoordError::NotFound(format!("no job '{id}'")))
    }

    fn set_state(&mut self, id: &str, state: JobState) -> Result<(), CoordError> {
        let name =
            serde_json::to_value(state).ok().and_then(|v| v.as_str().map(String::from)).unwrap_or_default();
        self.db.execute("UPDATE jobs SET state = ?1 WHERE id = ?2", rusqlite::params![name, id])?;
        self.job_mut(id)?.state = state;
        Ok(())
    }

    /// Cancel, pause or resume.
    pub fn control(&mut self, id: &str, action: &str) -> Result<(), CoordError> {
        let state = self.job_mut(id)?.state;
        let next = match (action, state) {
            (_, JobState::Done) => return Err(CoordError::Conflict(format!("job {id} is done"))),
            ("cancel", _) => JobState::Cancelled,
            (_, JobState::Cancelled) => return Err(CoordError::Conflict(format!("job {id} is cancelled"))),
            ("pause", _) => JobState::Paused,
            ("resume", JobState::Paused) => JobState::Queued,
            ("resume", s) => s,
            (a, _) => {
                return Err(CoordError::BadRequest(format!("unknown action '{a}' (cancel, pause, resume)")))
            }
        };
        if next == JobState::Cancelled {
            // Revoked: uploads, heartbeats and failure reports of these leases are refused.
            let j = self.job_mut(id)?;
            for c in j.chunks.iter_mut().filter(|c| matches!(c, ChunkState::Leased { .. })) {
                *c = ChunkState::Pending;
            }
        }
        self.set_state(id, next)
    }

    pub fn set_priority(&mut self, id: &str, priority: i32) -> Result<(), CoordError> {
        let job = self.job_mut(id)?;
        job.spec.settings.priority = priority;
        let spec = serde_json::to_string(&job.spec).map_err(|e| CoordError::Internal(e.to_string()))?;
        self.db.execute("UPDATE jobs SET spec = ?1 WHERE id = ?2", rusqlite::params![spec, id])?;
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
        let mut order: Vec<(std::cmp::Reverse<i32>, u64, String)> = self
            .jobs
            .values()
            .filter(|j| matches!(j.state, JobState::Queued | JobState::Running))
            .filter(|j| j.failures.get(worker).copied().unwrap_or(0) < MAX_FAILURES_PER_WORKER)
            .filter(|j| !j.queue.is_empty())
            .map(|j| (std::cmp::Reverse(j.spec.settings.priority), j.created, j.id.clone()))
            .collect();
        order.sort();
        let (_, _, id) = order.into_iter().next()?;
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
            job.state = JobState::Running;
            let _ = self.db.execute("UPDATE jobs SET state = 'running' WHERE id = ?1", [&id]);
        }
        let job = &self.jobs[&id];
        Some(Lease {
            job: id.clone(),
            chunk: job.plan[chunk as usize],
            epoch,
            settings: job.spec.settings.clone(),
            bundle_hash: job.bundle_hash.clone(),
            deadline_ms: ms,
        })
    }

    fn leased(&mut self, job: &str, chunk: u32, epoch: u64) -> Result<&mut Job, CoordError> {
        let j = self.job_mut(job)?;
        if j.final_status.is_some() {
            return Err(CoordError::Conflict(format!(
                "chunk {chunk} of job {job} is already merged: the job is done"
            )));
        }
        if j.state == JobState::Cancelled {
            return Err(CoordError::Conflict(format!("job {job} is cancelled: its leases are revoked")));
        }
        let c = j
            .chunks
            .get(chunk as usize)
            .ok_or_else(|| CoordError::NotFound(format!("job {job} has no chunk {chunk}")))?;
        match c {
            ChunkState::Leased { epoch: e, .. } if *e == epoch => Ok(j),
            ChunkState::Done => {
                Err(CoordError::Conflict(format!("chunk {chunk} of job {job} is already merged")))
            }
            _ => Err(CoordError::Conflict(format!(
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
    /// where to store it first, when this coordinator stores partials. Changes nothing.
    pub fn check_partial(
        &mut self,
        job: &str,
        chunk: u32,
        epoch: u64,
        acc: &Accum,
    ) -> Result<Option<PathBuf>, CoordError> {
        let (data, persist) = (self.data.clone(), self.persist);
        let j = self.leased(job, chunk, epoch)?;
        j.fits(chunk, acc).map_err(CoordError::BadRequest)?;
        Ok(persist.then(|| j.dir(&data).join("partials").join(format!("{chunk}.zst"))))
    }

    /// Merges a checked (and, when this coordinator stores partials, stored) partial; at most
    /// once per chunk. Returns a checkpoint to write, when one is due.
    fn merge_partial(
        &mut self,
        job: &str,
        chunk: u32,
        epoch: u64,
        acc: &Accum,
        now: Instant,
    ) -> Result<Option<Snapshot>, CoordError> {
        let t0 = Instant::now();
        let (worker, since) = match &self.leased(job, chunk, epoch)?.chunks[chunk as usize] {
            ChunkState::Leased { worker, since, .. } => (worker.clone(), *since),
            _ => unreachable!("checked by leased()"),
        };
        let (data, persist, interval) = (self.data.clone(), self.persist, self.checkpoint_interval);
        let j = self.job_mut(job)?;
        if acc.dropped.total() > 0 {
            tracing::warn!(job, chunk, worker = %worker, "chunk dropped samples: {}", acc.dropped);
        }
        j.accum.merge(acc);
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
        let snap = if persist { j.snapshot(&data, interval) } else { None };
        self.seen(&worker, now);
        if let Some(w) = self.workers.get_mut(&worker) {
            w.chunks_done += 1;
            w.samples_done += samples;
        }
        metrics::histogram!("furnace_merge_duration_seconds").record(t0.elapsed().as_secs_f64());
        if !persist && finished {
            self.set_state(job, JobState::Done)?;
        }
        Ok(snap)
    }

    /// Notes that `worker` was heard from.
    pub fn seen(&mut self, worker: &str, now: Instant) {
        match self.workers.get_mut(worker) {
            Some(w) => w.last_seen = now,
            None => {
                self.workers.retain(|_, w| now.duration_since(w.last_seen) < FORGET_WORKER);
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
        for j in self.jobs.values() {
            *jobs.entry(j.state.name().into()).or_default() += 1;
            if let Some(st) = &j.final_status {
                *chunks.entry("done".into()).or_default() += st.chunks_done.saturating_sub(st.chunks_skipped);
                *chunks.entry("skipped".into()).or_default() += st.chunks_skipped;
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
        let (data, interval) = (self.data.clone(), self.checkpoint_interval);
        let j = self.jobs.get_mut(&snap.job)?;
        j.checkpointing = false;
        if let Err(e) = result {
            j.record_error(format!("checkpoint failed: {e}"));
            j.checkpoint_failed = Some(Instant::now());
            return None;
        }
        j.checkpoint_failed = None;
        j.checkpointed.extend(&snap.ids);
        if snap.finished {
            if let Err(e) = self.set_state(&snap.job, JobState::Done) {
                tracing::error!(job = %snap.job, "cannot record the job as done: {e}");
            }
            tracing::info!(job = %snap.job, "job done");
            // A stored job's result is on disk: its memory goes (`furnace render`'s stays).
            if self.persist {
                if let Err(e) = self.evict(&snap.job) {
                    tracing::error!(job = %snap.job, "cannot release the finished job: {e}");
                }
            }
            return None;
        }
        j.snapshot(&data, interval)
    }

    /// The scene of a job, when this coordinator keeps scenes.
    pub fn job_scene(&self, id: &str) -> Option<Arc<Scene>> {
        self.jobs.get(id)?.scene.clone()
    }

    pub fn status(&self, id: &str) -> Result<JobStatus, CoordError> {
        let j = self.jobs.get(id).ok_or_else(|| CoordError::NotFound(format!("no job '{id}'")))?;
        if let Some(st) = &j.final_status {
            return Ok(JobStatus {
                settings: j.spec.settings.clone(),
                errors: j.errors.clone(),
                ..(**st).clone()
            });
        }
        let (done, leased, pending) = j.counts();
        let rate = match (j.recent.front(), j.recent.back()) {
            (Some(a), Some(b)) if b.0 > a.0 => {
                let s: u64 = j.recent.iter().skip(1).map(|x| x.1).sum();
                s as f64 / b.0.duration_since(a.0).as_secs_f64()
            }
            _ => 0.0,
        };
        let left = j.samples_left();
        Ok(JobStatus {
            id: j.id.clone(),
            state: j.state,
            settings: j.spec.settings.clone(),
            chunks_total: j.plan.len() as u64,
            chunks_done: done,
            chunks_leased: leased,
            chunks_pending: pending,
            chunks_skipped: j.skipped.len() as u64,
            samples_done: j.samples_done,
            samples_total: j.samples_done + left,
            samples_per_second: rate,
            eta_seconds: (rate > 0.0).then(|| left as f64 / rate),
            estimated_rel_mse: Some(j.estimated_rel_mse()).filter(|e| e.is_finite()),
            dropped_samples: j.accum.dropped,
            workers: j.workers.keys().cloned().collect(),
            errors: j.errors.clone(),
            plan: j.render_plan.clone(),
        })
    }

    pub fn job_ids(&self) -> Vec<String> {
        self.jobs.keys().cloned().collect()
    }

    /// The merged image so far.
    /// The job's image: developed from the accumulation, or (a finished job's) its result file.
    pub fn picture(&self, id: &str) -> Result<Picture, CoordError> {
        let j = self.jobs.get(id).ok_or_else(|| CoordError::NotFound(format!("no job '{id}'")))?;
        Ok(match j.final_status {
            Some(_) => Picture::File(j.dir(&self.data).join("result.exr")),
            None => Picture::Developed(j.accum.develop()),
        })
    }

    pub fn image(&self, id: &str) -> Result<furnace_core::Image, CoordError> {
        self.picture(id)?.image()
    }

    /// Bytes the job's plan, chunk states and accumulation hold in memory (the larger part
    /// of what a job costs: 96 bytes a pixel).
    pub fn held_bytes(&self, id: &str) -> Result<usize, CoordError> {
        let j = self.jobs.get(id).ok_or_else(|| CoordError::NotFound(format!("no job '{id}'")))?;
        Ok(j.accum.pixels.capacity() * std::mem::size_of::<furnace_core::film::PixelSum>()
            + j.plan.capacity() * std::mem::size_of::<ChunkSpec>()
            + j.chunks.capacity() * std::mem::size_of::<ChunkState>()
            + j.tile_est.capacity() * 8)
    }

    /// Forgets a job: its row, its state in memory; returns its folder and the bundle and
    /// stored files no other job uses, for the caller to remove outside the lock. Leases of it
    /// are refused from now on.
    pub fn delete(&mut self, id: &str) -> Result<Vec<PathBuf>, CoordError> {
        if id.is_empty() || !id.chars().all(|c| c.is_ascii_alphanumeric() || c == '-') {
            return Err(CoordError::NotFound(format!("no job '{id}'")));
        }
        // A job left out at the last start (its scene files gone) has a row but no state.
        let spec: Option<String> =
            self.db.query_row("SELECT spec FROM jobs WHERE id = ?1", [id], |r| r.get(0)).ok();
        let rows = self.db.execute("DELETE FROM jobs WHERE id = ?1", [id])?;
        if rows == 0 && !self.jobs.contains_key(id) {
            return Err(CoordError::NotFound(format!("no job '{id}'")));
        }
        self.jobs.remove(id);
        let mut gone = vec![self.data.join("jobs").join(id)];
        // Its bundle and stored files too, unless another job uses them.
        if let Some(bundle) = spec.and_then(|s| serde_json::from_str::<JobSpec>(&s).ok()).map(|s| s.bundle) {
            let others: Vec<Bundle> = {
                let mut st = self.db.prepare("SELECT spec FROM jobs")?;
                let specs = st.query_map([], |r| r.get::<_, String>(0))?;
                specs
                    .flatten()
                    .filter_map(|s| serde_json::from_str::<JobSpec>(&s).ok())
                    .map(|s| s.bundle)
                    .collect()
            };
            let hash = bundle.hash();
            if !others.iter().any(|b| b.hash() == hash) {
                gone.push(self.bundle_dir(&hash));
                gone.push(self.data.join("bundles").join(format!("{hash}.json")));
            }
            for h in bundle.files.values() {
                if !others.iter().any(|b| b.files.values().any(|o| o == h)) {
                    gone.push(self.file_path(h));
                }
            }
        }
        tracing::info!(job = %id, "job deleted");
        Ok(gone)
    }

    /// Releases a finished job's memory, keeping its final status (also written to
    /// `status.json`, so that a restart need not load its scene).
    fn evict(&mut self, id: &str) -> Result<(), CoordError> {
        let st = self.status(id)?;
        let (data, persist) = (self.data.clone(), self.persist);
        let j = self.job_mut(id)?;
        if persist {
            let json = serde_json::to_vec(&st).map_err(|e| CoordError::Internal(e.to_string()))?;
            write_atomic(&j.dir(&data).join("status.json"), &json)?;
        }
        j.release(st);
        Ok(())
    }

    pub fn result_path(&self, id: &str) -> Result<PathBuf, CoordError> {
        let j = self.jobs.get(id).ok_or_else(|| CoordError::NotFound(format!("no job '{id}'")))?;
        if j.state != JobState::Done {
            return Err(CoordError::Conflict(format!("job {id} is not done ({:?})", j.state)));
        }
        Ok(j.dir(&self.data).join("result.exr"))
    }

    pub fn bundle_manifest(&self, hash: &str) -> Result<Vec<u8>, CoordError> {
        if !furnace_proto::is_hash(hash) {
            return Err(CoordError::BadRequest(format!("'{hash}' is not a bundle hash")));
        }
        std::fs::read(self.data.join("bundles").join(format!("{hash}.json")))
            .map_err(|_| CoordError::NotFound(format!("no bundle {hash}")))
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
    encoded: Option<&[u8]>,
) -> Result<(), CoordError> {
    let lock = || coord.lock().unwrap_or_else(|e| e.into_inner());
    // Each guard is dropped before a refusal is counted: count_duplicate locks again.
    let checked = lock().check_partial(job, chunk, epoch, acc);
    let path = checked.inspect_err(|_| count_duplicate(coord, job, chunk))?;
    if let Some(path) = path {
        // Chunks are deterministic: a partial stored by a lease that loses the race below holds
        // the same bytes as the one merged, and a restart merges each chunk at most once.
        match encoded {
            Some(bytes) => write_atomic(&path, bytes)?,
            None => write_atomic(&path, &encode_partial(acc))?,
        }
    }
    let merged = lock().merge_partial(job, chunk, epoch, acc, Instant::now());
    let snap = merged.inspect_err(|_| count_duplicate(coord, job, chunk))?;
    write_checkpoints(coord, snap)
}

/// Writes a checkpoint and those due after it, without the lock: leases and uploads go on
/// meanwhile.
fn write_checkpoints(coord: &Mutex<Coordinator>, mut snap: Option<Snapshot>) -> Result<(), CoordError> {
    while let Some(s) = snap {
        let result = s.write();
        snap = coord.lock().unwrap_or_else(|e| e.into_inner()).checkpoint_written(&s, &result);
        result?;
    }
    Ok(())
}

/// Writes again, at most every `checkpoint_retry`, the final checkpoint of every job whose
/// last one failed (a full disk): such a job would otherwise stay running at 100% until a
/// restart. Called by the server's timer.
pub fn retry_checkpoints(coord: &Mutex<Coordinator>) {
    let snaps: Vec<Snapshot> = {
        let mut c = coord.lock().unwrap_or_else(|e| e.into_inner());
        let (data, retry) = (c.data.clone(), c.checkpoint_retry);
        c.jobs
            .values_mut()
            .filter(|j| !j.checkpointing && j.checkpoint_failed.is_some_and(|t| t.elapsed() >= retry))
            .filter(|j| !matches!(j.state, JobState::Done | JobState::Cancelled))
            .filter_map(|j| {
                j.checkpoint_failed = None;
                j.snapshot(&data, Duration::ZERO)
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

/// Submits a job, locking the coordinator only to look up the idempotency key and to insert
/// the job: the bundle is laid out and the scene loaded, validated and planned without the
/// lock, so leases, uploads and status go on meanwhile.
pub fn submit(
    coord: &Mutex<Coordinator>,
    spec: JobSpec,
    key: Option<&str>,
) -> Result<(String, bool), CoordError> {
    let lock = || coord.lock().unwrap_or_else(|e| e.into_inner());
    let request = request_hash(&spec);
    let loader = {
        let c = lock();
        if let Some(id) = c.idempotent(key, &request)? {
            return Ok((id, false));
        }
        c.loader()
    };
    let job = loader.submitted(spec, key)?;
    let mut c = lock();
    // A submission with the same key that finished meanwhile wins.
    match c.idempotent(key, &request)? {
        Some(id) => Ok((id, false)),
        None => c.insert_job(job, key, &request),
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
    let merged =
        |j: &Job| j.final_status.is_some() || matches!(j.chunks.get(chunk as usize), Some(ChunkState::Done));
    if c.jobs.get(job).is_some_and(merged) {
        metrics::counter!("furnace_duplicate_uploads_total").increment(1);
    }
}

/// A job's merge at one moment, to be checkpointed outside the lock.
struct Snapshot {
    job: String,
    dir: PathBuf,
    /// Chunks in `accum`, sorted.
    ids: Vec<u32>,
    /// Chunks skipped (noise-target jobs), sorted.
    skipped: Vec<u32>,
    /// Those not in the previous checkpoint: their partial files go once this one is written.
    new: Vec<u32>,
    accum: Accum,
    /// Every chunk is in: write `result.exr` too.
    finished: bool,
}

impl Snapshot {
    /// Writes the checkpoint (merged chunk ids and accumulation) atomically, then drops the
    /// partials in it; for a finished job, also `result.exr`.
    fn write(&self) -> Result<(), CoordError> {
        let t = Instant::now();
        let header =
            serde_json::to_vec(&CheckpointHeader { merged: self.ids.clone(), skipped: self.skipped.clone() })
                .map_err(|e| CoordError::Internal(e.to_string()))?;
        let mut bytes = (header.len() as u64).to_le_bytes().to_vec();
        bytes.extend_from_slice(&header);
        bytes.extend_from_slice(&encode_partial(&self.accum));
        write_atomic(&self.dir.join("checkpoint"), &bytes)?;
        for id in &self.new {
            std::fs::remove_file(self.dir.join("partials").join(format!("{id}.zst"))).ok();
        }
        if self.finished {
            // Written atomically (temporary file, rename) before the job is marked done.
            let result = self.dir.join("result.exr");
            self.accum.develop().write_exr(&result).map_err(|e| CoordError::Internal(e.to_string()))?;
        }
        metrics::histogram!("furnace_checkpoint_duration_seconds").record(t.elapsed().as_secs_f64());
        metrics::counter!("furnace_checkpoint_bytes_total").increment(bytes.len() as u64);
        tracing::info!(job = %self.job, bytes = bytes.len(), "checkpoint written in {:.3} s", t.elapsed().as_secs_f64());
        Ok(())
    }
}

/// The chunks a checkpoint holds, and those its job skips.
#[derive(serde::Serialize, serde::Deserialize)]
struct CheckpointHeader {
    merged: Vec<u32>,
    #[serde(default)]
    skipped: Vec<u32>,
}

fn decode_checkpoint(bytes: &[u8], max: usize) -> Result<(Vec<u32>, Vec<u32>, Accum), String> {
    let n =
        u64::from_le_bytes(bytes.get(..8).ok_or("truncated")?.try_into().map_err(|_| "truncated")?) as usize;
    let end = n.checked_add(8).filter(|&e| e <= bytes.len()).ok_or("truncated header")?;
    let h: CheckpointHeader = serde_json::from_slice(&bytes[8..end]).map_err(|e| e.to_string())?;
    let acc = decode_partial(&bytes[end..], max).map_err(|e| e.to_string())?;
    Ok((h.merged, h.skipped, acc))
}

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

    /// Issue 14: the priority was negated to sort, so i32::MIN overflowed and went first.
    #[test]
    fn the_highest_priority_goes_first_at_the_extremes() {
        let mut c = Coordinator::ephemeral().unwrap();
        let low = submit(&mut c, i32::MIN);
        let high = submit(&mut c, i32::MAX);
        let now = Instant::now();
        assert_eq!(c.lease("w", now).unwrap().job, high);
        c.set_priority(&high, i32::MIN + 1).unwrap();
        assert_eq!(c.lease("w", now).unwrap().job, high);
        c.set_priority(&low, 0).unwrap();
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
        accept_partial(&coord, &job, first.chunk.id, first.epoch, &acc, None).unwrap();
        let mut c = coord.into_inner().unwrap();
        c.jobs.get_mut(&job).unwrap().queue.push_front(first.chunk.id);
        let leased: Vec<u32> =
            std::iter::from_fn(|| c.lease("w", Instant::now())).map(|l| l.chunk.id).collect();
        assert_eq!(leased.len(), 3, "{leased:?}");
        assert!(!leased.contains(&first.chunk.id));
    }

    /// Issue 14: an upload in flight when a job was cancelled turned it into done.
    #[test]
    fn cancel_revokes_the_leases_in_flight() {
        let mut c = Coordinator::ephemeral().unwrap();
        let job = submit(&mut c, 0);
        let leases: Vec<_> = std::iter::from_fn(|| c.lease("w", Instant::now())).collect();
        assert_eq!(leases.len(), 4);
        c.control(&job, "cancel").unwrap();
        assert_eq!(c.status(&job).unwrap().chunks_leased, 0);
        let coord = Mutex::new(c);
        let scene = tiny_scene();
        for l in &leases {
            let acc = furnace_core::render_region(&scene, &l.chunk.region, 0).0;
            let e = accept_partial(&coord, &job, l.chunk.id, l.epoch, &acc, None).unwrap_err();
            assert!(matches!(&e, CoordError::Conflict(m) if m.contains("cancelled")), "{e:?}");
        }
        let c = coord.lock().unwrap();
        assert_eq!(c.status(&job).unwrap().state, JobState::Cancelled);
        assert_eq!(c.status(&job).unwrap().chunks_done, 0);
    }
}
