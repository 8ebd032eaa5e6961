//! Where the coordinator keeps what must outlive it. [`Store`] is everything the job core asks
//! of storage; [`DiskStore`] keeps it in a data folder (SQLite rows, content-addressed files,
//! each job's partials, checkpoint, status and result); [`MemStore`] keeps job rows in memory
//! and nothing else, for `furnace render`, whose jobs live as long as the process.
//!
//! The coordinator calls no method under its lock: job rows are written in batches by
//! whichever request needs its change stored (see `state::sync_rows`), and files are read and
//! written by the requests that need them.
//!
//! Layout of a data folder:
//! - `furnace.db`: jobs (spec, state, idempotency key, request hash) and the boot counter;
//! - `files/{hash}`: bundle files by BLAKE3 hash; `bundles/{hash}.json` and `bundles/{hash}/`:
//!   a bundle's manifest and its files laid out under their paths;
//! - `jobs/{id}/partials/{chunk}.zst`, `checkpoint`, `status.json`, `result.exr`,
//!   `quarantine/`.

use std::collections::HashSet;
use std::io::Write;
use std::path::{Path, PathBuf};
use std::sync::Mutex;

use furnace_core::{Image, Scene};
use furnace_proto::{Bundle, JobSpec, JobState, JobStatus};

use crate::error::CoordError;

/// A job as stored: what a restart needs to rebuild it.
#[derive(Clone, Debug)]
pub struct JobRow {
    pub id: String,
    pub spec: JobSpec,
    pub state: JobState,
    pub created: u64,
}

/// One change to the job rows.
#[derive(Clone, Debug)]
pub enum RowOp {
    /// A new job, with the idempotency key it was submitted with and the hash of the
    /// request; its folder is made first (a row always has one).
    Insert { row: JobRow, key: Option<String>, request: String },
    /// A job's state and spec (its priority) as they are now.
    Update(JobRow),
    /// The job is gone; a row that is not there is no error.
    Delete(String),
}

/// What the coordinator stores, and where from it restarts.
pub trait Store: Send + Sync {
    /// Whether anything stored outlives the process. A store that keeps nothing gets no
    /// partials or checkpoints to write, and its finished jobs keep their image in memory.
    fn durable(&self) -> bool;
    /// Counts a start of the coordinator and returns its number (1 for the first): epochs
    /// handed out after a restart start above every epoch of earlier starts.
    fn boot(&self) -> Result<u64, CoordError>;

    // Job rows.
    /// Every stored job, oldest first; a row that cannot be read is returned as its id and
    /// the reason.
    fn jobs(&self) -> Result<Vec<Result<JobRow, (String, String)>>, CoordError>;
    /// Writes a batch of changes to the job rows at once, in order (a batch written in part
    /// is rolled back). Returns what to remove for the deleted jobs (with [`remove_paths`]): each one's
    /// folder, and its bundle and files when no job left uses them.
    /// Bundles and files whose hash is in `keep` stay, whatever the rows say (jobs not
    /// stored yet use them).
    fn write_rows(&self, ops: &[RowOp], keep: &HashSet<String>) -> Result<Vec<PathBuf>, CoordError>;
    /// Every stored idempotency key: the job it names and the hash of the request it was
    /// first used with (none for rows of earlier versions).
    fn keys(&self) -> Result<Vec<(String, String, Option<String>)>, CoordError>;

    // A job's files.
    /// Stores an accepted partial durably (before it is acknowledged).
    fn save_partial(&self, job: &str, chunk: u32, bytes: &[u8]) -> Result<(), CoordError>;
    /// Stores a checkpoint, written by `write` as it is stored (it replaces the previous one),
    /// then drops the partials it now holds (`merged`); with `result`, also the finished job's
    /// image. Returns the checkpoint's size in bytes.
    fn save_checkpoint(
        &self,
        job: &str,
        write: &dyn Fn(&mut dyn Write) -> std::io::Result<()>,
        merged: &[u32],
        result: Option<&Image>,
    ) -> Result<u64, CoordError>;
    /// The last checkpoint's bytes, if there is one.
    fn checkpoint(&self, job: &str) -> Option<Vec<u8>>;
    /// The chunks whose stored partials are not in the checkpoint, in order.
    fn partials(&self, job: &str) -> Vec<u32>;
    fn partial(&self, job: &str, chunk: u32) -> Result<Vec<u8>, String>;
    fn drop_partial(&self, job: &str, chunk: u32);
    /// Sets a stored file that cannot be used (`checkpoint`, or a chunk's partial) aside;
    /// returns its name.
    fn quarantine(&self, job: &str, chunk: Option<u32>) -> String;
    /// Stores the final status of a finished job (so that a restart need not load its scene).
    fn save_status(&self, job: &str, status: &JobStatus) -> Result<(), CoordError>;
    /// A finished job's final status, when it and its result are stored (a job cancelled
    /// before its first chunk has its status alone).
    fn final_status(&self, job: &str) -> Option<JobStatus>;
    /// Where a finished job's result is.
    fn result_path(&self, job: &str) -> PathBuf;

    // Content-addressed files and bundles.
    /// Stores a file under its hash, reading it from `body` and hashing it as it is written
    /// (nothing is held in memory); refused, and nothing kept, when it does not hash to `hash`.
    /// Returns false when a good copy was stored already (then `body` is not read).
    fn put_file_from(&self, hash: &str, body: &mut dyn std::io::Read) -> Result<bool, CoordError>;
    /// [`Store::put_file_from`] for bytes in memory.
    fn put_file(&self, hash: &str, mut bytes: &[u8]) -> Result<bool, CoordError> {
        self.put_file_from(hash, &mut bytes)
    }
    fn has_file(&self, hash: &str) -> bool;
    /// Marks a stored file as wanted now (a client checked it is there before submitting).
    fn touch_file(&self, hash: &str);
    fn file(&self, hash: &str) -> Option<Vec<u8>>;
    /// A stored file opened for reading, to stream it.
    fn open_file(&self, hash: &str) -> Option<std::fs::File>;
    fn bundle_manifest(&self, hash: &str) -> Option<Vec<u8>>;
    /// Lays the bundle's files out under their paths (once per bundle) and loads its scene from
    /// there with `load`; the layout and the manifest are kept only if `load` succeeds.
    fn load_bundle(
        &self,
        bundle: &Bundle,
        load: &dyn Fn(&Path) -> Result<Scene, CoordError>,
    ) -> Result<Scene, CoordError>;
    /// Removes stored files and laid-out bundles that no job uses and that were last stored
    /// longer than `unused_for` ago (files uploaded for a submission that never came, or that
    /// failed). Returns how many it removed.
    fn collect_garbage(&self, unused_for: std::time::Duration) -> Result<usize, CoordError>;
}

/// Removes files and folders, logging what cannot be removed (a path already gone is fine).
pub fn remove_paths(paths: &[PathBuf]) {
    for p in paths {
        let removed = if p.is_dir() { std::fs::remove_dir_all(p) } else { std::fs::remove_file(p) };
        if let Err(e) = removed {
            if e.kind() != std::io::ErrorKind::NotFound {
                tracing::warn!("removing {}: {e}", p.display());
            }
        }
    }
}

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

fn json<T: serde::Serialize>(v: &T) -> Result<String, CoordError> {
    serde_json::to_string(v).map_err(|e| CoordError::Internal(e.to_string()))
}

/// A data folder: SQLite rows and files.
pub struct DiskStore {
    data: PathBuf,
    db: Mutex<rusqlite::Connection>,
}

impl DiskStore {
    /// Opens (or creates) a data folder, removing temporary files of writes a crash
    /// interrupted.
    pub fn open(data: &Path) -> Result<DiskStore, CoordError> {
        for d in ["files", "jobs", "bundles"] {
            std::fs::create_dir_all(data.join(d))?;
        }
        let tmp = |e: &std::fs::DirEntry| e.file_name().to_string_lossy().ends_with(".tmp");
        // Bundle folders of submissions, and files of uploads, a crash interrupted.
        for e in std::fs::read_dir(data.join("bundles"))?.flatten().filter(tmp) {
            std::fs::remove_dir_all(e.path()).ok();
        }
        for e in std::fs::read_dir(data.join("files"))?.flatten().filter(tmp) {
            std::fs::remove_file(e.path()).ok();
        }
        for job in std::fs::read_dir(data.join("jobs"))?.flatten() {
            for d in [job.path(), job.path().join("partials")] {
                for e in std::fs::read_dir(d).into_iter().flatten().flatten().filter(tmp) {
                    std::fs::remove_file(e.path()).ok();
                }
            }
        }
        let db = rusqlite::Connection::open(data.join("furnace.db"))?;
        db.pragma_update(None, "journal_mode", "WAL")?;
        db.pragma_update(None, "synchronous", "FULL")?;
        db.execute_batch(SCHEMA)?;
        migrate(&db)?;
        Ok(DiskStore { data: data.to_path_buf(), db: Mutex::new(db) })
    }

    fn db(&self) -> std::sync::MutexGuard<'_, rusqlite::Connection> {
        self.db.lock().unwrap_or_else(|e| e.into_inner())
    }

    fn job_dir(&self, job: &str) -> PathBuf {
        self.data.join("jobs").join(job)
    }

    fn partial_path(&self, job: &str, chunk: u32) -> PathBuf {
        self.job_dir(job).join("partials").join(format!("{chunk}.zst"))
    }

    fn file_path(&self, hash: &str) -> PathBuf {
        self.data.join("files").join(hash)
    }

    fn bundle_dir(&self, hash: &str) -> PathBuf {
        self.data.join("bundles").join(hash)
    }

    fn manifest_path(&self, hash: &str) -> PathBuf {
        self.data.join("bundles").join(format!("{hash}.json"))
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
            made.map_err(|e| CoordError::Invalid(format!("bundle path '{path}' cannot be laid out: {e}")))?;
        }
        Ok(())
    }
}

impl DiskStore {
    /// [`Store::write_rows`] once the new folders are made: one transaction.
    fn write_rows_in(&self, ops: &[RowOp], keep: &HashSet<String>) -> Result<Vec<PathBuf>, CoordError> {
        let mut db = self.db();
        let tx = db.transaction()?;
        let mut deleted = Vec::new();
        for op in ops {
            match op {
                RowOp::Insert { row, key, request } => {
                    tx.execute(
                        "INSERT INTO jobs (id, spec, state, idempotency_key, created, request_hash)
                         VALUES (?1, ?2, ?3, ?4, ?5, ?6)",
                        rusqlite::params![
                            row.id,
                            json(&row.spec)?,
                            row.state.name(),
                            key,
                            row.created as i64,
                            request
                        ],
                    )?;
                }
                RowOp::Update(row) => {
                    tx.execute(
                        "UPDATE jobs SET state = ?1, spec = ?2 WHERE id = ?3",
                        rusqlite::params![row.state.name(), json(&row.spec)?, row.id],
                    )?;
                }
                RowOp::Delete(id) => {
                    let spec: Option<String> =
                        tx.query_row("SELECT spec FROM jobs WHERE id = ?1", [id], |r| r.get(0)).ok();
                    if tx.execute("DELETE FROM jobs WHERE id = ?1", [id])? > 0 {
                        let bundle = spec.and_then(|s| serde_json::from_str::<JobSpec>(&s).ok());
                        deleted.push((id, bundle.map(|s| s.bundle)));
                    }
                }
            }
        }
        // What the deleted jobs used and no job left uses goes with them.
        let others: Vec<Bundle> = {
            let mut st = tx.prepare("SELECT spec FROM jobs")?;
            let specs = st.query_map([], |r| r.get::<_, String>(0))?;
            specs
                .flatten()
                .filter_map(|s| serde_json::from_str::<JobSpec>(&s).ok())
                .map(|s| s.bundle)
                .collect()
        };
        tx.commit()?;
        let mut gone = Vec::new();
        for (id, bundle) in deleted {
            gone.push(self.job_dir(id));
            let Some(bundle) = bundle else { continue };
            let hash = bundle.hash();
            if !keep.contains(&hash) && !others.iter().any(|b| b.hash() == hash) {
                gone.push(self.bundle_dir(&hash));
                gone.push(self.manifest_path(&hash));
            }
            for h in bundle.files.values() {
                if !keep.contains(h) && !others.iter().any(|b| b.files.values().any(|o| o == h)) {
                    gone.push(self.file_path(h));
                }
            }
        }
        // Jobs deleted together may share files.
        let mut seen = HashSet::new();
        gone.retain(|p| seen.insert(p.clone()));
        Ok(gone)
    }

    /// The bundles and files every stored job uses.
    fn in_use(&self) -> Result<(HashSet<String>, HashSet<String>), CoordError> {
        let db = self.db();
        let mut st = db.prepare("SELECT spec FROM jobs")?;
        let specs = st.query_map([], |r| r.get::<_, String>(0))?;
        let (mut bundles, mut files) = (HashSet::new(), HashSet::new());
        for spec in specs {
            // A row that cannot be read keeps everything: nothing is removed on a guess.
            let spec = serde_json::from_str::<JobSpec>(&spec?)
                .map_err(|e| CoordError::Internal(format!("stored spec unreadable: {e}")))?;
            bundles.insert(spec.bundle.hash());
            files.extend(spec.bundle.files.into_values());
        }
        Ok((bundles, files))
    }
}

impl Store for DiskStore {
    fn durable(&self) -> bool {
        true
    }

    fn boot(&self) -> Result<u64, CoordError> {
        let db = self.db();
        let boot: i64 =
            db.query_row("SELECT value FROM meta WHERE key = 'boot'", [], |r| r.get(0)).unwrap_or(0) + 1;
        db.execute("INSERT OR REPLACE INTO meta (key, value) VALUES ('boot', ?1)", [boot])?;
        Ok(boot as u64)
    }

    fn jobs(&self) -> Result<Vec<Result<JobRow, (String, String)>>, CoordError> {
        let db = self.db();
        let mut st = db.prepare("SELECT id, spec, state, created FROM jobs ORDER BY created, id")?;
        let rows = st.query_map([], |r| {
            Ok((r.get::<_, String>(0)?, r.get::<_, String>(1)?, r.get::<_, String>(2)?, r.get::<_, i64>(3)?))
        })?;
        let rows: Vec<_> = rows.collect::<Result<_, _>>()?;
        Ok(rows
            .into_iter()
            .map(|(id, spec, state, created)| {
                let spec = serde_json::from_str::<JobSpec>(&spec)
                    .map_err(|e| (id.clone(), format!("stored spec unreadable: {e}")))?;
                let state = serde_json::from_value::<JobState>(serde_json::Value::String(state))
                    .map_err(|e| (id.clone(), format!("stored state unreadable: {e}")))?;
                // A row whose folder is missing (made by an earlier version after the row, and
                // lost) gets it back: its files can be written again.
                std::fs::create_dir_all(self.job_dir(&id).join("partials")).ok();
                Ok(JobRow { id, spec, state, created: created.max(0) as u64 })
            })
            .collect())
    }

    fn write_rows(&self, ops: &[RowOp], keep: &HashSet<String>) -> Result<Vec<PathBuf>, CoordError> {
        // Folders first: a row always has one (a job's files are written only into it).
        let new: Vec<PathBuf> = ops
            .iter()
            .filter_map(|op| match op {
                RowOp::Insert { row, .. } => Some(self.job_dir(&row.id)),
                _ => None,
            })
            .collect();
        let written = new
            .iter()
            .try_for_each(|d| std::fs::create_dir_all(d.join("partials")))
            .map_err(CoordError::from)
            .and_then(|()| self.write_rows_in(ops, keep));
        if written.is_err() {
            for d in &new {
                std::fs::remove_dir_all(d).ok();
            }
        }
        written
    }

    fn keys(&self) -> Result<Vec<(String, String, Option<String>)>, CoordError> {
        let db = self.db();
        let mut st = db.prepare(
            "SELECT idempotency_key, id, request_hash FROM jobs WHERE idempotency_key IS NOT NULL",
        )?;
        let keys = st.query_map([], |r| Ok((r.get(0)?, r.get(1)?, r.get(2)?)))?.collect::<Result<_, _>>()?;
        Ok(keys)
    }

    fn save_partial(&self, job: &str, chunk: u32, bytes: &[u8]) -> Result<(), CoordError> {
        Ok(write_into(&self.partial_path(job, chunk), bytes)?)
    }

    fn save_checkpoint(
        &self,
        job: &str,
        write: &dyn Fn(&mut dyn Write) -> std::io::Result<()>,
        merged: &[u32],
        result: Option<&Image>,
    ) -> Result<u64, CoordError> {
        let size = write_with(&self.job_dir(job).join("checkpoint"), |f| write(f))?;
        for &id in merged {
            std::fs::remove_file(self.partial_path(job, id)).ok();
        }
        if let Some(img) = result {
            // Written atomically and durably (temporary file, fsync, rename) before the final
            // status, which counts only beside a result.
            write_with(&self.result_path(job), |f| img.write_exr_to(f).map_err(std::io::Error::other))?;
        }
        Ok(size)
    }

    fn checkpoint(&self, job: &str) -> Option<Vec<u8>> {
        std::fs::read(self.job_dir(job).join("checkpoint")).ok()
    }

    fn partials(&self, job: &str) -> Vec<u32> {
        let Ok(entries) = std::fs::read_dir(self.job_dir(job).join("partials")) else { return Vec::new() };
        let mut ids: Vec<u32> = entries
            .flatten()
            .filter_map(|e| e.file_name().into_string().ok()?.strip_suffix(".zst")?.parse().ok())
            .collect();
        ids.sort();
        ids
    }

    fn partial(&self, job: &str, chunk: u32) -> Result<Vec<u8>, String> {
        std::fs::read(self.partial_path(job, chunk)).map_err(|e| e.to_string())
    }

    fn drop_partial(&self, job: &str, chunk: u32) {
        std::fs::remove_file(self.partial_path(job, chunk)).ok();
    }

    fn quarantine(&self, job: &str, chunk: Option<u32>) -> String {
        let file = match chunk {
            Some(c) => self.partial_path(job, c),
            None => self.job_dir(job).join("checkpoint"),
        };
        let dir = self.job_dir(job).join("quarantine");
        let name = file.file_name().map(|n| n.to_string_lossy().into_owned()).unwrap_or_default();
        let moved = std::fs::create_dir(&dir)
            .or_else(|e| if dir.is_dir() { Ok(()) } else { Err(e) })
            .and_then(|_| std::fs::rename(&file, dir.join(&name)));
        if let Err(m) = moved {
            tracing::error!(job, "cannot move {} aside: {m}", file.display());
            std::fs::remove_file(&file).ok();
        }
        name
    }

    fn save_status(&self, job: &str, status: &JobStatus) -> Result<(), CoordError> {
        let bytes = serde_json::to_vec(status).map_err(|e| CoordError::Internal(e.to_string()))?;
        Ok(write_into(&self.job_dir(job).join("status.json"), &bytes)?)
    }

    fn final_status(&self, job: &str) -> Option<JobStatus> {
        let bytes = std::fs::read(self.job_dir(job).join("status.json")).ok()?;
        let status = serde_json::from_slice::<JobStatus>(&bytes).ok()?;
        // A job cancelled before its first chunk ends with its status alone (no image).
        let imageless = status.state == JobState::Cancelled && status.chunks_done == 0;
        (imageless || self.result_path(job).exists()).then_some(status)
    }

    fn result_path(&self, job: &str) -> PathBuf {
        self.job_dir(job).join("result.exr")
    }

    fn put_file_from(&self, hash: &str, body: &mut dyn std::io::Read) -> Result<bool, CoordError> {
        // A stored file is kept only while it still hashes to its name; a damaged one is
        // replaced. Stored again, it counts as new for garbage collection.
        let path = self.file_path(hash);
        let good = std::fs::File::open(&path)
            .and_then(|f| blake3::Hasher::new().update_reader(f).map(|h| h.finalize()))
            .is_ok_and(|h| h.to_hex().as_str() == hash);
        if good {
            touch(&path);
            return Ok(false);
        }
        static N: std::sync::atomic::AtomicU64 = std::sync::atomic::AtomicU64::new(0);
        let n = N.fetch_add(1, std::sync::atomic::Ordering::Relaxed);
        let tmp = self.data.join("files").join(format!(".{hash}.{}.{n}.tmp", std::process::id()));
        let mut hasher = blake3::Hasher::new();
        let written = std::fs::File::create(&tmp).and_then(|f| {
            let mut out = std::io::BufWriter::new(f);
            let mut buf = vec![0u8; 1 << 16];
            loop {
                let k = body.read(&mut buf)?;
                if k == 0 {
                    break;
                }
                hasher.update(&buf[..k]);
                out.write_all(&buf[..k])?;
            }
            out.into_inner().map_err(|e| e.into_error())?.sync_all()
        });
        let actual = hasher.finalize().to_hex();
        let checked = match written {
            Err(e) => Err(CoordError::from(e)),
            Ok(()) if actual.as_str() != hash => {
                Err(CoordError::Invalid(format!("body hashes to {actual}, not {hash}")))
            }
            Ok(()) => std::fs::rename(&tmp, &path).map_err(CoordError::from),
        };
        if let Err(e) = checked {
            std::fs::remove_file(&tmp).ok();
            return Err(e);
        }
        if let Ok(d) = std::fs::File::open(self.data.join("files")) {
            d.sync_all().ok();
        }
        Ok(true)
    }

    fn has_file(&self, hash: &str) -> bool {
        self.file_path(hash).is_file()
    }

    fn touch_file(&self, hash: &str) {
        touch(&self.file_path(hash));
    }

    fn file(&self, hash: &str) -> Option<Vec<u8>> {
        std::fs::read(self.file_path(hash)).ok()
    }

    fn open_file(&self, hash: &str) -> Option<std::fs::File> {
        std::fs::File::open(self.file_path(hash)).ok()
    }

    fn bundle_manifest(&self, hash: &str) -> Option<Vec<u8>> {
        std::fs::read(self.manifest_path(hash)).ok()
    }

    fn load_bundle(
        &self,
        b: &Bundle,
        load: &dyn Fn(&Path) -> Result<Scene, CoordError>,
    ) -> Result<Scene, CoordError> {
        let missing: Vec<&str> =
            b.files.iter().filter(|(_, h)| !self.has_file(h)).map(|(p, _)| p.as_str()).collect();
        if !missing.is_empty() {
            return Err(CoordError::Invalid(format!(
                "bundle files not uploaded yet: {} (PUT /v1/files/{{hash}} first)",
                missing.join(", ")
            )));
        }
        // Fresh again for garbage collection, which leaves a submission's files alone (it takes
        // only what was unused for at least an hour).
        for h in b.files.values() {
            touch(&self.file_path(h));
        }
        let hash = b.hash();
        let dir = self.bundle_dir(&hash);
        touch(&dir);
        touch(&self.manifest_path(&hash));
        let scene = if dir.is_dir() {
            // Laid out by an earlier submission.
            load(&dir)?
        } else {
            // Laid out in a folder of this submission's own, loaded from there, then moved into
            // place: concurrent submissions of one bundle never share a half-made folder, and
            // one that fails leaves nothing behind.
            static N: std::sync::atomic::AtomicU64 = std::sync::atomic::AtomicU64::new(0);
            let n = N.fetch_add(1, std::sync::atomic::Ordering::Relaxed);
            let tmp = self.data.join("bundles").join(format!(".{hash}.{}.{n}.tmp", std::process::id()));
            let loaded = self.lay_out(b, &tmp).and_then(|_| load(&tmp));
            // Another submission may have put the same bundle in place meanwhile: keep that.
            if loaded.is_err() || std::fs::rename(&tmp, &dir).is_err() {
                std::fs::remove_dir_all(&tmp).ok();
            }
            loaded?
        };
        let manifest = self.manifest_path(&hash);
        if !manifest.exists() {
            write_atomic(&manifest, json(b)?.as_bytes())?;
        }
        Ok(scene)
    }

    fn collect_garbage(&self, unused_for: std::time::Duration) -> Result<usize, CoordError> {
        let (bundles, files) = self.in_use()?;
        let old = |e: &std::fs::DirEntry| {
            let age = e.metadata().ok().and_then(|m| m.modified().ok()).and_then(|t| t.elapsed().ok());
            age.is_some_and(|a| a >= unused_for)
        };
        let mut gone = Vec::new();
        for e in std::fs::read_dir(self.data.join("files"))?.flatten() {
            let name = e.file_name().to_string_lossy().into_owned();
            // Temporary files are uploads under way (a crash's are removed by their age).
            if !files.contains(&name) && old(&e) {
                gone.push(e.path());
            }
        }
        // Job folders without a row: a deletion whose removal failed (a write raced it).
        let rows: HashSet<String> =
            self.db().prepare("SELECT id FROM jobs")?.query_map([], |r| r.get(0))?.flatten().collect();
        for e in std::fs::read_dir(self.data.join("jobs"))?.flatten() {
            if !rows.contains(&*e.file_name().to_string_lossy()) && old(&e) {
                gone.push(e.path());
            }
        }
        for e in std::fs::read_dir(self.data.join("bundles"))?.flatten() {
            let name = e.file_name().to_string_lossy().into_owned();
            let hash = name.strip_suffix(".json").unwrap_or(&name);
            // Temporary layouts belong to submissions under way (a crash's go at start).
            if !name.ends_with(".tmp") && !bundles.contains(hash) && old(&e) {
                gone.push(e.path());
            }
        }
        remove_paths(&gone);
        if !gone.is_empty() {
            tracing::info!("removed {} stored files and bundles that no job uses", gone.len());
        }
        Ok(gone.len())
    }
}

/// Job rows in memory, and no files: jobs live as long as the process.
#[derive(Default)]
pub struct MemStore {
    /// Rows by id, in order of insertion, with their idempotency key and request hash.
    rows: Mutex<Vec<(JobRow, Option<String>, String)>>,
}

impl MemStore {
    pub fn new() -> MemStore {
        MemStore::default()
    }

    fn rows(&self) -> std::sync::MutexGuard<'_, Vec<(JobRow, Option<String>, String)>> {
        self.rows.lock().unwrap_or_else(|e| e.into_inner())
    }
}

impl Store for MemStore {
    fn durable(&self) -> bool {
        false
    }
    fn boot(&self) -> Result<u64, CoordError> {
        Ok(1)
    }
    fn jobs(&self) -> Result<Vec<Result<JobRow, (String, String)>>, CoordError> {
        Ok(self.rows().iter().map(|r| Ok(r.0.clone())).collect())
    }
    fn write_rows(&self, ops: &[RowOp], _: &HashSet<String>) -> Result<Vec<PathBuf>, CoordError> {
        let mut held = self.rows();
        // All or nothing, as a transaction.
        let mut rows = held.clone();
        for op in ops {
            match op {
                RowOp::Insert { row, key, request } => {
                    if key.is_some() && rows.iter().any(|r| r.1 == *key) {
                        return Err(CoordError::Internal("idempotency key stored twice".into()));
                    }
                    rows.push((row.clone(), key.clone(), request.clone()));
                }
                RowOp::Update(row) => {
                    if let Some(r) = rows.iter_mut().find(|r| r.0.id == row.id) {
                        r.0 = row.clone();
                    }
                }
                RowOp::Delete(id) => rows.retain(|r| r.0.id != *id),
            }
        }
        *held = rows;
        Ok(Vec::new())
    }
    fn keys(&self) -> Result<Vec<(String, String, Option<String>)>, CoordError> {
        let rows = self.rows();
        Ok(rows.iter().filter_map(|r| Some((r.1.clone()?, r.0.id.clone(), Some(r.2.clone())))).collect())
    }
    // Not durable: the coordinator stores no partials or checkpoints here.
    fn save_partial(&self, _: &str, _: u32, _: &[u8]) -> Result<(), CoordError> {
        Ok(())
    }
    fn save_checkpoint(
        &self,
        _: &str,
        _: &dyn Fn(&mut dyn Write) -> std::io::Result<()>,
        _: &[u32],
        _: Option<&Image>,
    ) -> Result<u64, CoordError> {
        Ok(0)
    }
    fn checkpoint(&self, _: &str) -> Option<Vec<u8>> {
        None
    }
    fn partials(&self, _: &str) -> Vec<u32> {
        Vec::new()
    }
    fn partial(&self, job: &str, chunk: u32) -> Result<Vec<u8>, String> {
        Err(format!("no stored partial {chunk} of job {job} in memory"))
    }
    fn drop_partial(&self, _: &str, _: u32) {}
    fn quarantine(&self, _: &str, chunk: Option<u32>) -> String {
        chunk.map_or("checkpoint".into(), |c| format!("{c}.zst"))
    }
    fn save_status(&self, _: &str, _: &JobStatus) -> Result<(), CoordError> {
        Ok(())
    }
    fn final_status(&self, _: &str) -> Option<JobStatus> {
        None
    }
    fn result_path(&self, job: &str) -> PathBuf {
        PathBuf::from(format!("{job}.exr"))
    }
    fn put_file_from(&self, _: &str, _: &mut dyn std::io::Read) -> Result<bool, CoordError> {
        Err(CoordError::Invalid("this coordinator stores no files".into()))
    }
    fn has_file(&self, _: &str) -> bool {
        false
    }
    fn touch_file(&self, _: &str) {}
    fn file(&self, _: &str) -> Option<Vec<u8>> {
        None
    }
    fn open_file(&self, _: &str) -> Option<std::fs::File> {
        None
    }
    fn bundle_manifest(&self, _: &str) -> Option<Vec<u8>> {
        None
    }
    fn load_bundle(
        &self,
        _: &Bundle,
        _: &dyn Fn(&Path) -> Result<Scene, CoordError>,
    ) -> Result<Scene, CoordError> {
        Err(CoordError::Invalid("this coordinator stores no files: submit a loaded scene".into()))
    }
    fn collect_garbage(&self, _: std::time::Duration) -> Result<usize, CoordError> {
        Ok(0)
    }
}

/// Sets a file's or folder's modification time to now (if it exists), unless it was set in
/// the last ten minutes: garbage collection takes only what was unused for an hour, and a file
/// left as it is keeps its identity for the asset cache (`scene::assets`, which knows a file by
/// its modification time among others), so the frames of one submission parse it once.
fn touch(path: &Path) {
    let now = std::time::SystemTime::now();
    let recent = std::fs::metadata(path)
        .and_then(|m| m.modified())
        .is_ok_and(|t| now.duration_since(t).is_ok_and(|d| d < std::time::Duration::from_secs(600)));
    if recent {
        return;
    }
    let f = if path.is_dir() {
        std::fs::File::open(path)
    } else {
        std::fs::File::options().append(true).open(path)
    };
    f.and_then(|f| f.set_modified(now)).ok();
}

/// Writes `bytes` to `path` atomically: temporary file, fsync, rename, fsync of the folder
/// (made if need be).
pub fn write_atomic(path: &Path, bytes: &[u8]) -> std::io::Result<()> {
    std::fs::create_dir_all(path.parent().unwrap_or(Path::new(".")))?;
    write_into(path, bytes)
}

/// [`write_atomic`] into a folder that must exist: a job's files are written only while its
/// folder is there, so a write that races the job's deletion fails instead of bringing the
/// folder back.
fn write_into(path: &Path, bytes: &[u8]) -> std::io::Result<()> {
    write_with(path, |f| f.write_all(bytes)).map(drop)
}

/// [`write_into`], the file written by `write` through a buffer (nothing else held in memory);
/// returns its size.
fn write_with(
    path: &Path,
    write: impl FnOnce(&mut std::io::BufWriter<std::fs::File>) -> std::io::Result<()>,
) -> std::io::Result<u64> {
    let dir = path.parent().unwrap_or(Path::new("."));
    // Unique, so that concurrent writes of one path never share a temporary file.
    static N: std::sync::atomic::AtomicU64 = std::sync::atomic::AtomicU64::new(0);
    let n = N.fetch_add(1, std::sync::atomic::Ordering::Relaxed);
    let name = path.file_name().and_then(|n| n.to_str()).unwrap_or("file");
    let tmp = dir.join(format!(".{name}.{}.{n}.tmp", std::process::id()));
    let written = std::fs::File::create(&tmp).and_then(|f| {
        let mut out = std::io::BufWriter::with_capacity(1 << 16, f);
        write(&mut out)?;
        let f = out.into_inner().map_err(|e| e.into_error())?;
        f.sync_all()?;
        let size = f.metadata()?.len();
        std::fs::rename(&tmp, path)?;
        Ok(size)
    });
    if written.is_err() {
        // A full disk or the like: no temporary file is left behind.
        std::fs::remove_file(&tmp).ok();
    }
    if let Ok(d) = std::fs::File::open(dir) {
        d.sync_all().ok();
    }
    written
}

#[cfg(test)]
mod tests {
    use super::*;
    use furnace_proto::JobSettings;

    fn row(id: &str, created: u64) -> JobRow {
        let bundle = Bundle { scene: "s.xml".into(), files: Default::default() };
        JobRow {
            id: id.into(),
            spec: JobSpec::new(bundle, JobSettings::default()),
            state: JobState::Queued,
            created,
        }
    }

    /// What the coordinator relies on of any store's job rows: order, updates, keys, deletion.
    fn rows_contract(store: &dyn Store) {
        let insert = |id, created, key: Option<&str>, request: &str| RowOp::Insert {
            row: row(id, created),
            key: key.map(String::from),
            request: request.into(),
        };
        store
            .write_rows(&[insert("b", 2, Some("key"), "h1"), insert("a", 1, None, "h2")], &HashSet::new())
            .unwrap();
        let mut b = row("b", 2);
        b.state = JobState::Running;
        b.spec.settings.priority = -7;
        store.write_rows(&[RowOp::Update(b)], &HashSet::new()).unwrap();
        // A batch that fails in part changes nothing.
        let twice = [RowOp::Delete("a".into()), insert("c", 3, Some("key"), "h3")];
        assert!(store.write_rows(&twice, &HashSet::new()).is_err(), "a key stored twice");
        let jobs: Vec<JobRow> = store.jobs().unwrap().into_iter().map(Result::unwrap).collect();
        let ids: Vec<&str> = jobs.iter().map(|r| r.id.as_str()).collect();
        if store.durable() {
            assert_eq!(ids, ["a", "b"], "oldest first");
        } else {
            assert_eq!(ids, ["b", "a"], "in order of submission");
        }
        let b = jobs.iter().find(|r| r.id == "b").unwrap();
        assert_eq!((b.state, b.spec.settings.priority), (JobState::Running, -7));
        assert_eq!(store.keys().unwrap(), [("key".into(), "b".into(), Some("h1".into()))]);
        store.write_rows(&[RowOp::Delete("b".into()), RowOp::Delete("b".into())], &HashSet::new()).unwrap();
        assert_eq!(store.keys().unwrap(), []);
        assert_eq!(store.jobs().unwrap().len(), 1);
    }

    fn scratch(name: &str) -> PathBuf {
        let d = std::env::temp_dir().join(format!("furnace-store-{name}-{}", std::process::id()));
        std::fs::remove_dir_all(&d).ok();
        d
    }

    /// A checkpoint writer of fixed bytes.
    fn bytes(b: &'static [u8]) -> impl Fn(&mut dyn Write) -> std::io::Result<()> {
        move |out| out.write_all(b)
    }

    fn s_status() -> JobStatus {
        serde_json::from_str(&format!(
            r#"{{"id":"j","state":"done","settings":{},"chunks_total":1,"chunks_done":1,
               "chunks_leased":0,"chunks_pending":0,"samples_done":1,"samples_total":1,
               "samples_per_second":0,"eta_seconds":null,"workers":[],"errors":[],"plan":""}}"#,
            serde_json::to_string(&JobSettings::default()).unwrap()
        ))
        .unwrap()
    }

    /// Issue 14: files uploaded for a submission that never came (or failed) stayed forever.
    #[test]
    fn files_no_job_uses_are_collected_once_old_enough() {
        let dir = scratch("gc");
        let s = DiskStore::open(&dir).unwrap();
        let hash = |b: &[u8]| blake3::hash(b).to_hex().to_string();
        let (used, unused) = (hash(b"scene"), hash(b"orphan"));
        let e = s.put_file(&used, b"not the scene").unwrap_err();
        assert!(matches!(&e, CoordError::Invalid(m) if m.contains("hashes to")), "{e:?}");
        assert_eq!(std::fs::read_dir(dir.join("files")).unwrap().count(), 0, "a refused file was kept");
        s.put_file(&used, b"scene").unwrap();
        s.put_file(&unused, b"orphan").unwrap();
        std::fs::write(dir.join("files/not-a-hash"), b"?").unwrap();
        std::fs::create_dir_all(dir.join("bundles/abandoned")).unwrap();
        std::fs::create_dir_all(dir.join("jobs/orphan/partials")).unwrap();
        let mut job = row("j", 1);
        job.spec.bundle.files.insert("s.xml".into(), used.clone());
        s.write_rows(&[RowOp::Insert { row: job, key: None, request: "h".into() }], &HashSet::new()).unwrap();
        let hour = std::time::Duration::from_secs(3600);
        assert_eq!(s.collect_garbage(hour).unwrap(), 0, "recent files are kept");
        assert_eq!(s.collect_garbage(std::time::Duration::ZERO).unwrap(), 4);
        assert!(!dir.join("jobs/orphan").exists() && dir.join("jobs/j").is_dir());
        assert!(s.has_file(&used) && !s.has_file(&unused));
        assert!(!dir.join("files/not-a-hash").exists() && !dir.join("bundles/abandoned").exists());
        // Once its job is deleted, its files go too.
        remove_paths(&s.write_rows(&[RowOp::Delete("j".into())], &HashSet::new()).unwrap());
        assert!(!s.has_file(&used));
        std::fs::remove_dir_all(&dir).ok();
    }

    #[test]
    fn both_stores_keep_job_rows_alike() {
        rows_contract(&MemStore::new());
        let dir = scratch("rows");
        rows_contract(&DiskStore::open(&dir).unwrap());
        // Rows outlive the store that wrote them; the boot counter counts starts.
        let again = DiskStore::open(&dir).unwrap();
        assert_eq!(again.jobs().unwrap().len(), 1);
        assert_eq!((again.boot().unwrap(), again.boot().unwrap()), (1, 2));
        std::fs::remove_dir_all(&dir).ok();
    }

    /// A checkpoint drops the partials it holds; a file set aside leaves the partials; a
    /// final status counts only with its result; temporary files go at the next open.
    #[test]
    fn the_disk_store_keeps_a_jobs_files_consistent() {
        let dir = scratch("files");
        let s = DiskStore::open(&dir).unwrap();
        s.write_rows(&[RowOp::Insert { row: row("j", 1), key: None, request: "h".into() }], &HashSet::new())
            .unwrap();
        for c in [3, 1, 2] {
            s.save_partial("j", c, &[c as u8]).unwrap();
        }
        assert_eq!(s.partials("j"), [1, 2, 3]);
        assert_eq!(s.save_checkpoint("j", &bytes(b"cp"), &[1, 3], None).unwrap(), 2);
        assert_eq!((s.partials("j"), s.checkpoint("j")), (vec![2], Some(b"cp".to_vec())));
        assert_eq!(s.partial("j", 2).unwrap(), [2]);
        assert_eq!(s.quarantine("j", Some(2)), "2.zst");
        assert!(s.partials("j").is_empty());
        assert!(dir.join("jobs/j/quarantine/2.zst").is_file());
        let status = s_status();
        s.save_status("j", &status).unwrap();
        assert!(s.final_status("j").is_none(), "no result yet");
        s.save_checkpoint(
            "j",
            &bytes(b"cp2"),
            &[],
            Some(&Image { width: 1, height: 1, data: vec![Default::default()] }),
        )
        .unwrap();
        assert_eq!(s.final_status("j"), Some(status));
        std::fs::write(dir.join("jobs/j/partials/.7.zst.1.1.tmp"), b"half").unwrap();
        std::fs::write(dir.join(format!("files/.{}.1.1.tmp", "a".repeat(64))), b"half an upload").unwrap();
        drop(s);
        DiskStore::open(&dir).unwrap();
        assert!(!dir.join("jobs/j/partials/.7.zst.1.1.tmp").exists());
        assert_eq!(
            std::fs::read_dir(dir.join("files")).unwrap().count(),
            0,
            "an interrupted upload was kept"
        );
        // A write racing the job's deletion fails; it does not bring the folder back.
        let s = DiskStore::open(&dir).unwrap();
        let gone = s.write_rows(&[RowOp::Delete("j".into())], &HashSet::new()).unwrap();
        remove_paths(&gone);
        assert!(s.save_partial("j", 4, b"late").is_err());
        assert!(s.save_checkpoint("j", &bytes(b"late"), &[], None).is_err());
        assert!(s.save_status("j", &s_status()).is_err());
        assert!(!dir.join("jobs/j").exists());
        std::fs::remove_dir_all(&dir).ok();
    }

    /// A file touched in the last ten minutes keeps its modification time: the frames of one
    /// submission find it unchanged in the asset cache (the time is part of a file's identity
    /// there). An older one is brought up to now, for garbage collection.
    #[test]
    fn touch_freshens_old_files_and_leaves_recent_ones() {
        let dir = scratch("touch");
        std::fs::create_dir_all(&dir).unwrap();
        let path = dir.join("f");
        std::fs::write(&path, b"x").unwrap();
        let mtime = || std::fs::metadata(&path).unwrap().modified().unwrap();
        let set = |t: std::time::SystemTime| {
            std::fs::File::options().append(true).open(&path).unwrap().set_modified(t).unwrap()
        };
        let now = std::time::SystemTime::now();
        let recent = now - std::time::Duration::from_secs(60);
        set(recent);
        touch(&path);
        assert_eq!(mtime(), recent, "a recent file's time changed");
        set(now - std::time::Duration::from_secs(7200));
        touch(&path);
        assert!(mtime() >= now, "an old file was not freshened");
        std::fs::remove_dir_all(&dir).ok();
    }
}
