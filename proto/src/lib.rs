//! What crosses the wire between Furnace's coordinator, workers and clients: serde types and
//! pure functions. Everything is versioned under [`API`].
//!
//! - [`JobSettings`] and [`chunk_plan`]: the plan is a pure function of the settings.
//! - [`Bundle`]: a scene and its assets by content hash; [`JobSpec`] what a client submits.
//! - [`Lease`], [`Heartbeat`], [`JobStatus`], [`ApiError`] and the rest: the JSON of every
//!   request and response of the HTTP API.
//! - [`Link`]: how a worker reaches a coordinator, over HTTP or in one process.
//! - [`encode_partial`] / [`decode_partial`]: a chunk's partial accumulation as an EXR with
//!   named integer channels and the tile position as the EXR data window, zstd on the wire.

use std::collections::BTreeMap;

use furnace_core::film::PixelSum;
pub use furnace_core::Region;
use serde::{Deserialize, Serialize};

pub mod fuzz;
mod link;
mod partial;
pub use link::{Link, Uploaded};
pub use partial::{
    decode_chunk, decode_partial, encode_chunk, encode_partial, partial_size_limit, write_chunk, PartialError,
};

/// The API's path prefix.
pub const API: &str = "/v1";

/// The render settings of a job. Left out (or 0), the size and the samples per pixel are the
/// scene's (its film and its sampler's `sample_count`); tiles are 64 pixels, chunks 64 spp.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct JobSettings {
    /// Image size; 0 x 0: the scene's film.
    pub width: u32,
    pub height: u32,
    /// Samples per pixel (0: the scene's); with `target_rel_error`, the most any pixel gets.
    pub spp: u64,
    pub tile_size: u32,
    pub spp_per_chunk: u64,
    pub seed: u64,
    pub priority: i32,
    /// Stop each tile once its estimated relative error (the root of its estimated relative
    /// MSE) is at most this; `None`: render every sample.
    pub target_rel_error: Option<f64>,
}

impl Default for JobSettings {
    fn default() -> Self {
        JobSettings {
            width: 0,
            height: 0,
            spp: 0,
            tile_size: 64,
            spp_per_chunk: 64,
            seed: 0,
            priority: 0,
            target_rel_error: None,
        }
    }
}

/// The most files a bundle may hold.
pub const MAX_BUNDLE_FILES: usize = 10_000;

/// The most chunks one job may have (its plan and chunk states take about 100 bytes each).
pub const MAX_CHUNKS: u64 = 1 << 20;
/// The most samples per pixel one job may ask for.
pub const MAX_SPP: u64 = 1 << 24;

impl JobSettings {
    /// Tiles in one pass of the plan: chunk `id` is tile `id % n` of pass `id / n`.
    pub fn tiles(&self) -> u32 {
        let t = self.tile_size.max(1);
        self.width.div_ceil(t).saturating_mul(self.height.div_ceil(t))
    }

    /// Checks the settings against the job limits (film size, [`MAX_SPP`], [`MAX_CHUNKS`])
    /// with checked arithmetic, before anything is planned or allocated; returns the number of
    /// chunks. The error names the limit.
    pub fn check_limits(&self) -> Result<u64, String> {
        let (w, h) = (self.width, self.height);
        furnace_core::scene::build::check_film_size(w, h)?;
        if self.tile_size == 0 || self.spp_per_chunk == 0 {
            return Err("tile_size and spp_per_chunk must be positive".into());
        }
        if self.spp > MAX_SPP {
            return Err(format!("spp {} is more than the limit of {MAX_SPP} samples per pixel", self.spp));
        }
        let t = self.tile_size as u64;
        let tiles = (w as u64).div_ceil(t) * (h as u64).div_ceil(t);
        let chunks = tiles * self.spp.div_ceil(self.spp_per_chunk);
        if chunks > MAX_CHUNKS {
            return Err(format!(
                "{w} x {h} pixels at {} spp in {t}-pixel tiles of {} spp makes {chunks} chunks, more than \
                 the limit of {MAX_CHUNKS}: use larger tiles or more samples per chunk",
                self.spp, self.spp_per_chunk
            ));
        }
        Ok(chunks)
    }
}

/// One unit of work: a [`Region`] (pixels `[x0, x1) x [y0, y1)`, samples `[s0, s1)`).
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, Serialize, Deserialize)]
pub struct ChunkSpec {
    /// Position in the plan; chunk ids are stable for given settings.
    pub id: u32,
    #[serde(flatten)]
    pub region: Region,
}

/// The chunk plan of a job, in hand-out order: all tiles of the first sample range before any
/// tile of the second, so that a preview improves evenly.
pub fn chunk_plan(s: &JobSettings) -> Vec<ChunkSpec> {
    furnace_core::plan_regions(s.width, s.height, s.spp, s.tile_size, s.spp_per_chunk)
        .into_iter()
        .enumerate()
        .map(|(id, region)| ChunkSpec { id: id as u32, region })
        .collect()
}

/// A scene bundle: the scene file's path and every file it needs (the scene too), by relative
/// path, each named by the BLAKE3 hash (hex) of its bytes.
#[derive(Clone, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Bundle {
    pub scene: String,
    pub files: BTreeMap<String, String>,
}

impl Bundle {
    /// The bundle of a loaded scene: its file and every asset it reads, by path relative to the
    /// scene's folder. Returns the bundle and, for each of its paths, the file on this machine.
    pub fn of_scene(
        scene_path: &std::path::Path,
        scene: &furnace_core::Scene,
    ) -> Result<(Bundle, Vec<(String, std::path::PathBuf)>), String> {
        Bundle::of_scene_hashing(scene_path, scene, &mut |p| hash_file(p))
    }

    /// [`Bundle::of_scene`] with the files hashed by `hash` (given each file's canonical path):
    /// the frames of a frame range hash the files they share once.
    pub fn of_scene_hashing(
        scene_path: &std::path::Path,
        scene: &furnace_core::Scene,
        hash: &mut dyn FnMut(&std::path::Path) -> std::io::Result<String>,
    ) -> Result<(Bundle, Vec<(String, std::path::PathBuf)>), String> {
        let canon = |p: &std::path::Path| p.canonicalize().map_err(|e| format!("{}: {e}", p.display()));
        let scene_file = canon(scene_path)?;
        let dir = scene_file.parent().ok_or("the scene file has no folder")?.to_path_buf();
        let mut paths = vec![scene_file];
        for a in &scene.assets {
            paths.push(canon(a)?);
        }
        let mut bundle = Bundle { scene: String::new(), files: BTreeMap::new() };
        let mut local = Vec::new();
        for (i, p) in paths.into_iter().enumerate() {
            let rel = p
                .strip_prefix(&dir)
                .map_err(|_| format!("{} is outside the scene's folder {}", p.display(), dir.display()))?
                .to_string_lossy()
                .replace('\\', "/");
            let hash = hash(&p).map_err(|e| format!("cannot read {}: {e}", p.display()))?;
            if i == 0 {
                bundle.scene = rel.clone();
            }
            bundle.files.insert(rel.clone(), hash);
            local.push((rel, p));
        }
        Ok((bundle, local))
    }

    /// The bundle's own hash: BLAKE3 of its canonical JSON (files sorted by path).
    pub fn hash(&self) -> String {
        let json = serde_json::to_vec(self).expect("a bundle serialises");
        blake3::hash(&json).to_hex().to_string()
    }

    /// Checks that every path is relative, stays inside the bundle, and that the scene is one
    /// of the files; every hash is 64 hex digits.
    pub fn validate(&self) -> Result<(), String> {
        if !self.files.contains_key(&self.scene) {
            return Err(format!("the scene file '{}' is not among the bundle's files", self.scene));
        }
        if self.files.len() > MAX_BUNDLE_FILES {
            return Err(format!(
                "a bundle holds at most {MAX_BUNDLE_FILES} files, this one {}",
                self.files.len()
            ));
        }
        for (path, hash) in &self.files {
            if path.len() > 1024
                || path.split('/').any(|c| c.len() > 255)
                || path.chars().any(char::is_control)
            {
                return Err(format!(
                    "bundle path '{}' must be at most 1024 bytes, 255 a part, with no control characters",
                    path.escape_debug()
                ));
            }
            // A file at `a` and another at `a/b` cannot both be laid out.
            let mut prefix = path.clone();
            prefix.push('/');
            if self.files.range(prefix.clone()..).next().is_some_and(|(p, _)| p.starts_with(&prefix)) {
                return Err(format!("bundle path '{path}' is a file and a folder of another path"));
            }
            let bad = path.is_empty()
                || path.starts_with('/')
                || path.contains('\\')
                || path.contains(':')
                || path.split('/').any(|c| c.is_empty() || c == "." || c == "..");
            if bad {
                return Err(format!(
                    "bundle path '{path}' must be relative, with no '.', '..' or empty parts"
                ));
            }
            if !is_hash(hash) {
                return Err(format!("bundle file '{path}': '{hash}' is not a BLAKE3 hex hash"));
            }
        }
        Ok(())
    }
}

/// Whether `s` looks like a BLAKE3 hash in hex (64 lowercase hex digits).
pub fn is_hash(s: &str) -> bool {
    s.len() == 64 && s.bytes().all(|c| c.is_ascii_digit() || (b'a'..=b'f').contains(&c))
}

/// What a client submits: a bundle (its files uploaded first) and settings. Width, height and
/// spp of 0 take the scene's own.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct JobSpec {
    pub bundle: Bundle,
    #[serde(default)]
    pub settings: JobSettings,
    /// Scene parameters, as `furnace render -D name=value`: they override the scene's
    /// `<default>`s when it is loaded.
    #[serde(default, skip_serializing_if = "BTreeMap::is_empty")]
    pub defines: BTreeMap<String, String>,
    /// Render every frame of this range as one job: frame `n` is the bundle's scene with
    /// `frame` defined as `n` (`-D frame=n`), and with the last run of `#` in its path (if any)
    /// replaced by `n`, zero-padded to the run's length (`anim_####.xml`: `anim_0007.xml`).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub frames: Option<FrameRange>,
    /// Set by the coordinator on each frame of a frame-range job (a submission may not).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub frame_of: Option<FrameOf>,
}

impl JobSpec {
    /// A one-frame job of `bundle` with `settings`, no scene parameters.
    pub fn new(bundle: Bundle, settings: JobSettings) -> JobSpec {
        JobSpec { bundle, settings, defines: BTreeMap::new(), frames: None, frame_of: None }
    }
}

/// The most frames one job may have.
pub const MAX_FRAMES: u64 = 10_000;

/// Frames `first` to `last` (both included), every `step`-th.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct FrameRange {
    pub first: u32,
    pub last: u32,
    #[serde(default = "one")]
    pub step: u32,
}

fn one() -> u32 {
    1
}

impl FrameRange {
    /// Parses `A-B[:STEP]` (or a single frame `A`) and checks it.
    pub fn parse(s: &str) -> Result<FrameRange, String> {
        let bad =
            || format!("frames '{s}': expected FIRST-LAST[:STEP] with whole numbers, e.g. 1-250 or 1-250:10");
        let (range, step) = match s.split_once(':') {
            Some((r, st)) => (r, st.trim().parse().map_err(|_| bad())?),
            None => (s, 1),
        };
        let (first, last) = match range.split_once('-') {
            Some((a, b)) => (a.trim().parse().map_err(|_| bad())?, b.trim().parse().map_err(|_| bad())?),
            None => {
                let a = range.trim().parse().map_err(|_| bad())?;
                (a, a)
            }
        };
        let r = FrameRange { first, last, step };
        r.check()?;
        Ok(r)
    }

    /// The range is not empty, its step positive, and it has at most [`MAX_FRAMES`] frames.
    pub fn check(&self) -> Result<(), String> {
        if self.step == 0 {
            return Err("frames: the step must be at least 1".into());
        }
        if self.first > self.last {
            return Err(format!("frames {}-{}: the first frame is after the last", self.first, self.last));
        }
        if self.count() > MAX_FRAMES {
            return Err(format!(
                "frames {}-{}:{} make {} frames, more than the limit of {MAX_FRAMES} a job",
                self.first,
                self.last,
                self.step,
                self.count()
            ));
        }
        Ok(())
    }

    pub fn count(&self) -> u64 {
        (self.last - self.first) as u64 / self.step.max(1) as u64 + 1
    }

    /// The frame numbers, in order.
    pub fn numbers(&self) -> impl Iterator<Item = u32> {
        (self.first..=self.last).step_by(self.step.max(1) as usize)
    }
}

/// Which frame of which job a job is (see [`JobSpec::frames`]).
#[derive(Clone, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct FrameOf {
    pub job: String,
    pub frame: u32,
}

/// `path` with its last run of `#` replaced by `frame`, zero-padded to the run's length (a
/// longer number is written whole); `path` itself when it has no `#`.
pub fn frame_path(path: &str, frame: u32) -> String {
    let Some(end) = path.rfind('#') else { return path.to_string() };
    let start = path[..end].trim_end_matches('#').len();
    let width = end + 1 - start;
    format!("{}{frame:0width$}{}", &path[..start], &path[end + 1..])
}

/// A worker asking for work.
#[derive(Clone, Debug, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct LeaseRequest {
    pub worker: String,
    /// How long the coordinator may hold the request open waiting for work (long polling),
    /// in milliseconds; it answers 204 if none comes. At most `MAX_LEASE_WAIT_MS`.
    #[serde(default)]
    pub wait_ms: u64,
}

/// Longest a lease request is held open.
pub const MAX_LEASE_WAIT_MS: u64 = 30_000;

/// A chunk leased to a worker until `deadline_ms` (milliseconds from now when granted) unless
/// it heartbeats. Uploads and heartbeats carry the epoch; a requeued chunk gets a higher one.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Lease {
    pub job: String,
    pub chunk: ChunkSpec,
    pub epoch: u64,
    pub settings: JobSettings,
    pub bundle_hash: String,
    /// Scene parameters to load the bundle's scene with (`-D name=value`).
    #[serde(default, skip_serializing_if = "BTreeMap::is_empty")]
    pub defines: BTreeMap<String, String>,
    pub deadline_ms: u64,
}

#[derive(Clone, Debug, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Heartbeat {
    pub epoch: u64,
}

/// What rendering took, counted by stage (the renderer's own counters): a chunk's partial
/// carries its own (the `stats` attribute), a job's status their sum. Counts add up exactly,
/// whatever the order.
pub use furnace_core::Stats as RenderStats;

/// `POST /v1/jobs/{id}/chunks/{chunk}/heartbeat`: the lease's new deadline, in milliseconds
/// from now.
#[derive(Clone, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct HeartbeatReply {
    pub deadline_ms: u64,
}

/// `POST /v1/jobs/{id}/chunks/{chunk}/fail`: a worker could not render its leased chunk.
#[derive(Clone, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct FailureReport {
    pub epoch: u64,
    pub error: String,
}

/// `POST /v1/jobs`: the job's id (a new job, or the one its idempotency key names).
#[derive(Clone, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Submitted {
    pub id: String,
}

/// `PUT /v1/files/{hash}`: whether the file was new (201) or already stored (200).
#[derive(Clone, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Stored {
    pub stored: bool,
}

/// `POST /v1/jobs/{id}/priority`.
#[derive(Clone, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Priority {
    pub priority: i32,
}

/// `GET /readyz`: the coordinator's state answers, and how many jobs it holds.
#[derive(Clone, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Ready {
    pub ready: bool,
    pub jobs: u64,
}

/// Every refusal: a 4xx with this body.
#[derive(Clone, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub struct ApiError {
    pub error: String,
}

/// Job states.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum JobState {
    Queued,
    Running,
    Paused,
    Done,
    Cancelled,
}

impl JobState {
    pub const ALL: [JobState; 5] =
        [JobState::Queued, JobState::Running, JobState::Paused, JobState::Done, JobState::Cancelled];

    /// The state's name on the wire.
    pub fn name(self) -> &'static str {
        match self {
            JobState::Queued => "queued",
            JobState::Running => "running",
            JobState::Paused => "paused",
            JobState::Done => "done",
            JobState::Cancelled => "cancelled",
        }
    }
}

/// `GET /v1/jobs/{id}`.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct JobStatus {
    pub id: String,
    pub state: JobState,
    pub settings: JobSettings,
    pub chunks_total: u64,
    pub chunks_done: u64,
    pub chunks_leased: u64,
    pub chunks_pending: u64,
    /// Chunks not rendered because their tile reached the target error.
    #[serde(default)]
    pub chunks_skipped: u64,
    pub samples_done: u64,
    pub samples_total: u64,
    pub samples_per_second: f64,
    pub eta_seconds: Option<f64>,
    /// Relative MSE of the merge so far, estimated from its own sums (see
    /// `Accum::estimated_rel_mse`); absent before pixels have 2 samples.
    #[serde(default)]
    pub estimated_rel_mse: Option<f64>,
    /// Samples rendered but left out of the image (NaN, infinite, radiance above 2^40), by
    /// reason; they count in `samples_done`.
    #[serde(default)]
    pub dropped_samples: furnace_core::Dropped,
    /// What rendering the merged chunks took, by stage (the sum of their partials' counts).
    #[serde(default)]
    pub render_stats: RenderStats,
    pub workers: Vec<String>,
    pub errors: Vec<String>,
    pub plan: String,
    /// A frame-range job's frames, in order (absent for a one-frame job); the counts above
    /// are their sums.
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub frames: Vec<FrameStatus>,
}

/// One frame of a frame-range job (`GET /v1/jobs/{id}`'s `frames`).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct FrameStatus {
    pub frame: u32,
    pub state: JobState,
    pub chunks_total: u64,
    pub chunks_done: u64,
    pub samples_done: u64,
    pub samples_total: u64,
    pub samples_per_second: f64,
    pub eta_seconds: Option<f64>,
    #[serde(default)]
    pub estimated_rel_mse: Option<f64>,
}

/// A worker as the coordinator sees it (`GET /v1/workers`).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct WorkerStatus {
    pub name: String,
    /// `busy` (holds leases), `idle` (heard from within a lease duration plus 5 s) or `lost`
    /// (silent for longer; its leases expire and go to others).
    pub state: String,
    pub leases: u64,
    pub chunks_done: u64,
    pub samples_done: u64,
    pub last_seen_seconds: f64,
}

/// The whole farm in counts (`GET /v1/stats`): what `/metrics` exports and what autoscalers
/// read. Maps are keyed by state name and list every state, zeros included.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct FarmStats {
    pub jobs: std::collections::BTreeMap<String, u64>,
    pub chunks: std::collections::BTreeMap<String, u64>,
    /// Pending chunks of queued and running jobs: work a worker could take now.
    pub pending_chunks: u64,
    pub workers: std::collections::BTreeMap<String, u64>,
}

/// The words of a pixel's sums, in channel order: R, G, B, weight, lum2 as four 32-bit words
/// each (two's complement, least significant first), then the count as two.
pub(crate) const WORDS: usize = 5 * 4 + 2;

pub(crate) fn pixel_words(p: &PixelSum) -> [u32; WORDS] {
    let mut w = [0u32; WORDS];
    for (q, v) in [p.rgb[0], p.rgb[1], p.rgb[2], p.weight, p.lum2].into_iter().enumerate() {
        let u = v as u128;
        for k in 0..4 {
            w[q * 4 + k] = (u >> (32 * k)) as u32;
        }
    }
    w[20] = p.count as u32;
    w[21] = (p.count >> 32) as u32;
    w
}

pub(crate) fn pixel_from_words(w: &[u32; WORDS]) -> PixelSum {
    let q = |i: usize| -> i128 {
        let mut u = 0u128;
        for k in 0..4 {
            u |= (w[i * 4 + k] as u128) << (32 * k);
        }
        u as i128
    };
    PixelSum { rgb: [q(0), q(1), q(2)], weight: q(3), lum2: q(4), count: w[20] as u64 | (w[21] as u64) << 32 }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Every small message of the API reads back what was written and refuses a field it
    /// does not know (a misspelt field is an error, not a silent default).
    #[test]
    fn wire_messages_round_trip_and_refuse_unknown_fields() {
        fn check<T: Serialize + for<'de> Deserialize<'de> + PartialEq + std::fmt::Debug>(v: T) {
            let mut json = serde_json::to_value(&v).unwrap();
            assert_eq!(serde_json::from_value::<T>(json.clone()).unwrap(), v);
            json.as_object_mut().unwrap().insert("typo".into(), 1.into());
            let e = serde_json::from_value::<T>(json).unwrap_err().to_string();
            assert!(e.contains("unknown field `typo`"), "{e}");
        }
        check(HeartbeatReply { deadline_ms: 30_000 });
        check(FailureReport { epoch: 1 << 32, error: "out of memory".into() });
        check(Submitted { id: "0123456789abcdef".into() });
        check(Stored { stored: true });
        check(Priority { priority: i32::MIN });
        check(Ready { ready: true, jobs: 3 });
        check(JobSettings::default());
    }

    #[test]
    fn plan_covers_every_pixel_sample_once_pass_by_pass() {
        let s = JobSettings {
            width: 130,
            height: 70,
            spp: 150,
            tile_size: 64,
            spp_per_chunk: 64,
            ..Default::default()
        };
        let plan = chunk_plan(&s);
        let mut covered = vec![0u32; (s.width * s.height) as usize * s.spp as usize];
        for c in plan.iter().map(|c| c.region) {
            for y in c.y0..c.y1 {
                for x in c.x0..c.x1 {
                    for i in c.s0..c.s1 {
                        covered[((y * s.width + x) as u64 * s.spp + i) as usize] += 1;
                    }
                }
            }
        }
        assert!(covered.iter().all(|&n| n == 1));
        // 3 x 2 tiles, sample ranges [0,64) [64,128) [128,150), pass by pass.
        assert_eq!(plan.len(), 18);
        assert!(plan.windows(2).all(|w| w[0].region.s0 <= w[1].region.s0));
        assert_eq!(plan.iter().map(|c| c.id).collect::<Vec<_>>(), (0..18).collect::<Vec<_>>());
    }

    #[test]
    fn frame_ranges_parse_and_name_their_files() {
        let r = FrameRange::parse("1-10:3").unwrap();
        assert_eq!(r.numbers().collect::<Vec<_>>(), [1, 4, 7, 10]);
        assert_eq!(r.count(), 4);
        assert_eq!(FrameRange::parse("5").unwrap().numbers().collect::<Vec<_>>(), [5]);
        assert_eq!(FrameRange::parse("0-2").unwrap().numbers().collect::<Vec<_>>(), [0, 1, 2]);
        for (s, fragment) in [
            ("3-1", "after the last"),
            ("1-5:0", "at least 1"),
            ("a-b", "expected FIRST-LAST"),
            ("-1-5", "expected FIRST-LAST"),
            ("0-4294967295", "more than the limit of 10000"),
        ] {
            let e = FrameRange::parse(s).unwrap_err();
            assert!(e.contains(fragment), "{s}: {e}");
        }
        assert_eq!(frame_path("anim_####.xml", 7), "anim_0007.xml");
        assert_eq!(frame_path("a#/b_##.xml", 123), "a#/b_123.xml");
        assert_eq!(frame_path("scene.xml", 3), "scene.xml");
        assert_eq!(frame_path("#", 42), "42");
    }

    #[test]
    fn settings_round_trip_with_defaults() {
        let s: JobSettings = serde_json_like("{}");
        assert_eq!(s, JobSettings::default());
    }

    #[test]
    fn bundle_paths_that_cannot_be_laid_out_are_refused() {
        let hash = "0".repeat(64);
        let bundle = |paths: &[&str]| Bundle {
            scene: paths[0].to_string(),
            files: paths.iter().map(|p| (p.to_string(), hash.clone())).collect(),
        };
        assert!(bundle(&["s.xml", "tex/a.png", "tex/b.png"]).validate().is_ok());
        for (paths, fragment) in [
            (&["s.xml", "a", "a/b"][..], "is a file and a folder"),
            (&["s.xml", "nul\0.png"][..], "no control characters"),
            (&["s.xml", &"x".repeat(300)][..], "255 a part"),
            (&["../s.xml"][..], "must be relative"),
        ] {
            let e = bundle(paths).validate().unwrap_err();
            assert!(e.contains(fragment), "{paths:?}: {e}");
        }
    }

    #[test]
    fn job_limits_are_checked_without_overflow() {
        let ok = JobSettings { width: 1920, height: 1080, spp: 4096, ..JobSettings::default() };
        assert_eq!(ok.check_limits(), Ok(510 * 64));
        let refused = |s: JobSettings, fragment: &str| {
            let e = s.check_limits().unwrap_err();
            assert!(e.contains(fragment), "{e}");
        };
        refused(JobSettings { spp: u64::MAX, ..ok.clone() }, "limit of 16777216 samples");
        // The careless submit of issue 14: cbox (256 x 256) at 4096 spp in 1-pixel, 1-spp chunks.
        let careless = JobSettings { width: 256, height: 256, tile_size: 1, spp_per_chunk: 1, ..ok.clone() };
        refused(careless, "268435456 chunks, more than the limit of 1048576");
        refused(JobSettings { width: 65536, height: 65536, ..ok.clone() }, "at most 65535 pixels a side");
        refused(JobSettings { width: u32::MAX, height: 1, ..ok.clone() }, "at most 65535 pixels a side");
        refused(JobSettings { width: 65535, height: 65535, ..ok.clone() }, "33554432 (2^25) in all");
        refused(JobSettings { tile_size: 0, ..ok.clone() }, "must be positive");
        let huge_tiles = JobSettings { tile_size: u32::MAX, spp_per_chunk: u64::MAX, spp: 16, ..ok.clone() };
        assert_eq!(huge_tiles.check_limits(), Ok(1));
        assert_eq!(chunk_plan(&huge_tiles).len(), 1);
    }

    // Minimal deserialisation of an empty object without pulling serde_json into proto's tests.
    fn serde_json_like(_: &str) -> JobSettings {
        use serde::de::value::{Error, MapDeserializer};
        let empty: MapDeserializer<std::iter::Empty<(String, u32)>, Error> =
            MapDeserializer::new(std::iter::empty());
        JobSettings::deserialize(empty).expect("defaults fill every field")
    }
}

/// BLAKE3 of a file, read in pieces (never whole in memory), as hex.
pub fn hash_file(path: &std::path::Path) -> std::io::Result<String> {
    let mut h = blake3::Hasher::new();
    h.update_reader(std::fs::File::open(path)?)?;
    Ok(h.finalize().to_hex().to_string())
}
