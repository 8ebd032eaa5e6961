//! A job's core: its chunk plan, the state of every chunk (pending, leased under an epoch,
//! merged, skipped), the exact merge of their partials, and the noise-target control that
//! decides each tile's next pass. No I/O: the coordinator stores what this produces through its
//! [`Store`](crate::store::Store).

use std::collections::{BTreeMap, HashMap, HashSet, VecDeque};
use std::time::{Duration, Instant};

use std::sync::Arc;

use furnace_core::{Accum, Scene};
use furnace_proto::{ChunkSpec, JobSpec, JobState, JobStatus, RenderStats};

/// Merges between checkpoints (at least; see `Coordinator::checkpoint_interval`).
const CHECKPOINT_EVERY: usize = 256;
/// Errors a job keeps for its status (the most recent), and the longest kept, in bytes.
pub const MAX_ERRORS: usize = 100;
pub const MAX_ERROR_BYTES: usize = 2048;

/// A job's merge at one moment, to be checkpointed outside the lock.
pub(crate) struct Snapshot {
    pub(crate) job: String,
    /// Chunks in `accum`, sorted.
    pub(crate) ids: Vec<u32>,
    /// Chunks skipped (noise-target jobs), sorted.
    pub(crate) skipped: Vec<u32>,
    /// Each tile's sum of its merged passes' estimates ([`Job::tile_sum`]; noise-target jobs).
    pub(crate) tile_sums: Vec<f64>,
    /// Those not in the previous checkpoint: their stored partials go once this one is written.
    pub(crate) new: Vec<u32>,
    /// Shared with the job until it merges again (copy on write): a snapshot costs no copy.
    pub(crate) accum: Arc<Accum>,
    /// The render statistics of the chunks in `accum`.
    pub(crate) stats: RenderStats,
    /// The job ends (every chunk is in, or it is cancelled): its final status, to store with
    /// its result (the image so far, for a cancelled job).
    pub(crate) status: Option<JobStatus>,
}

#[derive(Clone, Debug)]
pub(crate) enum ChunkState {
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

pub(crate) struct Job {
    pub(crate) id: String,
    pub(crate) spec: JobSpec,
    /// `spec.bundle.hash()`, computed once: every lease carries it.
    pub(crate) bundle_hash: String,
    pub(crate) state: JobState,
    pub(crate) plan: Vec<ChunkSpec>,
    pub(crate) chunks: Vec<ChunkState>,
    /// Pending chunks in hand-out order: requeued ones go to the front.
    pub(crate) queue: VecDeque<u32>,
    /// Shared with a snapshot being written, if any; the next merge then copies it first.
    pub(crate) accum: Arc<Accum>,
    /// Chunks whose partial is in `accum`.
    pub(crate) merged: HashSet<u32>,
    /// Chunks not to render: their tile reached the target error (noise-target jobs).
    pub(crate) skipped: HashSet<u32>,
    /// Each tile's sum, over its merged passes in pass order, of each pass's own estimated
    /// relative MSE (noise-target jobs; see [`Job::follow_up`]). NaN where passes were merged
    /// whose estimates are not known (a checkpoint written before the sums were stored).
    pub(crate) tile_sum: Vec<f64>,
    /// The whole image's estimated relative MSE and the samples it was computed at: a pass over
    /// the full accumulation, so status polls reuse it for a second unless the job is complete.
    pub(crate) est_cache: std::cell::Cell<Option<(Instant, u64, f64)>>,
    /// Chunks in the last checkpoint.
    pub(crate) checkpointed: HashSet<u32>,
    pub(crate) since_checkpoint: usize,
    /// A checkpoint is being written (outside the lock).
    pub(crate) checkpointing: bool,
    /// When the last checkpoint failed (a full disk), for [`retry_checkpoints`].
    pub(crate) checkpoint_failed: Option<Instant>,
    pub(crate) last_checkpoint: Instant,
    /// Filter margin of the scene, for checking partial sizes.
    pub(crate) margin: u32,
    pub(crate) render_plan: String,
    pub(crate) failures: HashMap<String, u32>,
    pub(crate) errors: Vec<String>,
    /// The loaded scene, kept for workers in this process (`furnace render`, `--local-workers`).
    pub(crate) scene: Option<Arc<Scene>>,
    pub(crate) workers: BTreeMap<String, Instant>,
    /// (time, samples) of recent merges, for the rate.
    pub(crate) recent: VecDeque<(Instant, u64)>,
    pub(crate) samples_done: u64,
    /// What rendering the merged chunks took (their partials' statistics, summed).
    pub(crate) stats: RenderStats,
    pub(crate) created: u64,
    /// A job that ended (done or cancelled) keeps only its final status, its result stored; a
    /// job paused for long is set aside the same way, its checkpoint stored, until it is
    /// resumed or cancelled: the plan, the chunk states, the accumulation and the scene are
    /// released.
    pub(crate) released: Option<Box<JobStatus>>,
    /// Since when the job is paused.
    pub(crate) paused_since: Option<Instant>,
}

impl Job {
    /// A chunk's partial rectangle (x0, y0, width, height): its tile grown by the filter's
    /// margin, clipped to the image.
    pub(crate) fn window(&self, chunk: u32) -> (u32, u32, u32, u32) {
        let s = &self.spec.settings;
        let r = &self.plan[chunk as usize].region;
        let m = self.margin;
        let x0 = r.x0.saturating_sub(m);
        let y0 = r.y0.saturating_sub(m);
        (x0, y0, (r.x1 + m).min(s.width) - x0, (r.y1 + m).min(s.height) - y0)
    }

    /// Checks that `acc` is a partial of `chunk`: its rectangle (the chunk's tile grown by the
    /// filter margin) and its sample count.
    pub(crate) fn fits(&self, chunk: u32, acc: &Accum) -> Result<(), String> {
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

    /// An ended job (done or cancelled) as a restart restores it: its final status, nothing
    /// else.
    pub(crate) fn finished(id: String, spec: JobSpec, created: u64, status: JobStatus) -> Job {
        let state = status.state;
        let mut job = Job::new(id, spec, state, created, Vec::new(), Accum::new(0, 0, 0, 0));
        job.render_plan = status.plan.clone();
        job.errors = status.errors.clone();
        job.samples_done = status.samples_done;
        Arc::make_mut(&mut job.accum).dropped = status.dropped_samples;
        job.release(status);
        job
    }

    /// A job with its plan and accumulation, every chunk pending, nothing queued yet.
    pub(crate) fn new(
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
            accum: Arc::new(accum),
            merged: HashSet::new(),
            skipped: HashSet::new(),
            tile_sum: Vec::new(),
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
            stats: RenderStats::default(),
            created,
            released: None,
            paused_since: None,
        }
    }

    /// The accumulation to merge into, made the size of the image on first use: a job holds
    /// no image until its first chunk comes in (the frames of a frame-range job wait their
    /// turn without one).
    pub(crate) fn accum_mut(&mut self) -> &mut Accum {
        let (w, h) = (self.spec.settings.width, self.spec.settings.height);
        if self.accum.pixels.is_empty() && w as u64 * h as u64 > 0 {
            let mut full = Accum::new(0, 0, w, h);
            full.dropped = self.accum.dropped;
            self.accum = Arc::new(full);
        }
        Arc::make_mut(&mut self.accum)
    }

    /// Bytes the accumulation takes once made (96 a pixel).
    pub(crate) fn image_bytes(&self) -> usize {
        let s = &self.spec.settings;
        s.width as usize * s.height as usize * std::mem::size_of::<furnace_core::film::PixelSum>()
    }

    /// Keeps `status` as the job's final status and lets go of everything else.
    pub(crate) fn release(&mut self, status: JobStatus) {
        let mut empty = Accum::new(0, 0, 0, 0);
        empty.dropped = self.accum.dropped;
        self.accum = Arc::new(empty);
        self.plan = Vec::new();
        self.chunks = Vec::new();
        self.queue = VecDeque::new();
        self.merged = HashSet::new();
        self.skipped = HashSet::new();
        self.checkpointed = HashSet::new();
        self.tile_sum = Vec::new();
        self.recent = VecDeque::new();
        self.failures = HashMap::new();
        self.workers = BTreeMap::new(); // the final status lists them
        self.scene = None;
        self.released = Some(Box::new(status));
    }

    /// Records an error for the job's status: at most [`MAX_ERROR_BYTES`] of it, and only the
    /// [`MAX_ERRORS`] most recent.
    pub(crate) fn record_error(&mut self, mut e: String) {
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

    /// Records that a stored file (`name`) could not be used and was set aside: its chunks
    /// are rendered again.
    pub(crate) fn quarantined(&mut self, name: &str, why: &str) {
        let e = format!("stored {name} was unusable ({why}); moved to quarantine/, its chunks render again");
        tracing::error!(job = %self.id, "{e}");
        self.record_error(e);
    }

    pub(crate) fn samples_total(&self) -> u64 {
        let s = &self.spec.settings;
        s.width as u64 * s.height as u64 * s.spp
    }

    /// A copy of the merge for a checkpoint, when one is due (after `CHECKPOINT_EVERY` merges
    /// and `interval`, and when the job is complete) and none is being written.
    /// A cancelled job's snapshot is its last: it ends the job with the image so far.
    pub(crate) fn snapshot(&mut self, interval: Duration) -> Option<Snapshot> {
        let due = self.since_checkpoint >= CHECKPOINT_EVERY && self.last_checkpoint.elapsed() >= interval;
        self.snapshot_if(due)
    }

    /// A snapshot now, unless one is being written (or the job is released).
    pub(crate) fn snapshot_now(&mut self) -> Option<Snapshot> {
        self.snapshot_if(true)
    }

    fn snapshot_if(&mut self, due: bool) -> Option<Snapshot> {
        let end = match self.state {
            _ if self.released.is_some() => return None,
            JobState::Cancelled => Some(JobState::Cancelled),
            _ if self.complete() => Some(JobState::Done),
            _ => None,
        };
        if self.checkpointing || !(end.is_some() || due) {
            return None;
        }
        // A job that ends before its first chunk still stores an image of its size.
        self.accum_mut();
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
            ids,
            skipped,
            tile_sums: self.tile_sum.clone(),
            new,
            accum: self.accum.clone(),
            stats: self.stats.clone(),
            status: end.map(|state| JobStatus { state, ..self.status() }),
        })
    }

    /// Paused for at least `after`, with no lease in flight: it can be set aside.
    pub(crate) fn idle(&self, after: Duration) -> bool {
        self.state == JobState::Paused
            && self.released.is_none()
            && !self.checkpointing
            && self.paused_since.is_some_and(|t| t.elapsed() >= after)
            && !self.chunks.iter().any(|c| matches!(c, ChunkState::Leased { .. }))
    }

    /// Bytes the job's plan, chunk states and accumulation hold in memory (the larger part of
    /// what a job costs: 96 bytes a pixel).
    /// A job's image counts from submission (it is made on the first merge); a frame of a
    /// frame-range job counts only once made (the submission counts the frames that can run
    /// at once).
    pub(crate) fn held_bytes(&self) -> usize {
        let made = self.accum.pixels.capacity() * std::mem::size_of::<furnace_core::film::PixelSum>();
        let image = match self.spec.frame_of {
            None if self.released.is_none() => made.max(self.image_bytes()),
            _ => made,
        };
        image
            + self.plan.capacity() * std::mem::size_of::<ChunkSpec>()
            + self.chunks.capacity() * std::mem::size_of::<ChunkState>()
            + self.tile_sum.capacity() * 8
    }

    /// Every merged chunk is in the stored checkpoint.
    pub(crate) fn checkpoint_current(&self) -> bool {
        self.merged.iter().all(|c| self.checkpointed.contains(c))
    }

    /// Every chunk merged or skipped.
    pub(crate) fn complete(&self) -> bool {
        self.merged.len() + self.skipped.len() == self.plan.len()
    }

    /// After chunk `chunk` of a noise-target job is merged: estimate its tile's error, then
    /// queue the tile's next pass or skip the rest.
    ///
    /// Each pass's estimate `e_k` comes from that chunk's own samples (its pass alone, so that
    /// the decision depends only on deterministic partials, never on arrival order); the
    /// tile's passes are merged one after another, so their sum is added in pass order. After
    /// pass p the tile's estimated relative MSE is `(e_0 + ... + e_p) / (p + 1)^2`: the mean
    /// pass's error over p + 1 passes. A firefly in an early pass keeps its weight in that sum
    /// (its share of the tile's error falls as 1/(p + 1)^2, as the image's does); judged by the
    /// last pass alone (`e_p / (p + 1)`, before 2026-11-27), a clean pass after one stopped the
    /// tile with the firefly in it.
    pub(crate) fn follow_up(&mut self, chunk: u32, acc: &Accum) {
        let Some(target) = self.spec.settings.target_rel_error else { return };
        let n = self.spec.settings.tiles();
        let (tile, pass) = (chunk % n, chunk / n);
        let r = self.plan[chunk as usize].region;
        let mut own = Accum::new(r.x0, r.y0, r.x1 - r.x0, r.y1 - r.y0);
        own.merge(acc);
        let sum = self.tile_sum[tile as usize] + own.estimated_rel_mse_for_stopping();
        self.tile_sum[tile as usize] = sum;
        let passes = (pass + 1) as f64;
        let est = sum / (passes * passes);
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
    /// predicted from its mean pass estimate so far (all its remaining passes while it has
    /// none): `need` passes bring the estimate to `mean / need`.
    pub(crate) fn samples_left(&self) -> u64 {
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
            let mean = self.tile_sum[tile as usize] / done as f64;
            let need = if done > 0 && mean.is_finite() {
                ((mean / (target * target)).ceil() as u32).clamp(done + 1, passes)
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
    pub(crate) fn estimated_rel_mse(&self) -> f64 {
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

    pub(crate) fn counts(&self) -> (u64, u64, u64) {
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

    /// Samples done, and done plus left (`status`'s `samples_done` and `samples_total`):
    /// what a progress bar shows, without the error estimate (a pass over every pixel) or
    /// anything else `status` builds.
    pub(crate) fn progress(&self) -> (u64, u64) {
        match &self.released {
            Some(st) => (st.samples_done, st.samples_total),
            None => (self.samples_done, self.samples_done + self.samples_left()),
        }
    }

    /// The job's status: counts, rate, ETA and error estimate, or its final status.
    pub(crate) fn status(&self) -> JobStatus {
        let j = self;
        if let Some(st) = &j.released {
            return JobStatus {
                state: j.state,
                settings: j.spec.settings.clone(),
                errors: j.errors.clone(),
                ..(**st).clone()
            };
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
        JobStatus {
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
            render_stats: j.stats.clone(),
            workers: j.workers.keys().cloned().collect(),
            errors: j.errors.clone(),
            plan: j.render_plan.clone(),
            frames: Vec::new(),
        }
    }
}
