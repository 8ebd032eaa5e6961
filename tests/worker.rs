//! The worker loop against a scripted coordinator (a `Link` of the test's own).

mod common;

use std::sync::atomic::{AtomicBool, AtomicU32, Ordering};
use std::sync::Arc;
use std::time::{Duration, Instant};

use common::load;
use furnace_core::{Accum, Region, Scene, Stats};
use furnace_proto::{ChunkSpec, JobSettings, Lease, Link, Uploaded};
use furnace_worker::WorkerConfig;

/// The one lease of a scripted coordinator (none once `handed`): chunk 0 of job "j".
fn lease_once(handed: &AtomicBool, region: Region, deadline_ms: u64) -> Option<Lease> {
    if handed.swap(true, Ordering::SeqCst) {
        return None;
    }
    Some(Lease {
        job: "j".into(),
        chunk: ChunkSpec { id: 0, region },
        epoch: 1,
        settings: JobSettings::default(),
        bundle_hash: String::new(),
        defines: Default::default(),
        deadline_ms,
    })
}

/// A worker of one thread and one slot that stops when `link` has no more work.
fn one_thread(link: Arc<dyn Link>) -> WorkerConfig {
    WorkerConfig {
        link,
        threads: 1,
        slots: 1,
        name: "w".into(),
        poll: Duration::from_millis(10),
        stop: Arc::new(AtomicBool::new(false)),
        exit_when_idle: true,
    }
}

/// Hands out one long chunk whose lease is gone at the first heartbeat (its job cancelled).
struct Revoked {
    scene: Arc<Scene>,
    handed: AtomicBool,
    heartbeats: AtomicU32,
    uploads: AtomicU32,
    failures: AtomicU32,
}

impl Link for Revoked {
    fn lease(&self, _: &str) -> Result<Option<Lease>, String> {
        Ok(lease_once(&self.handed, Region { x0: 0, y0: 0, x1: 48, y1: 40, s0: 0, s1: 4096 }, 150))
    }
    fn heartbeat(&self, _: &Lease) -> bool {
        self.heartbeats.fetch_add(1, Ordering::SeqCst);
        false
    }
    fn scene(&self, _: &Lease) -> Result<Arc<Scene>, String> {
        Ok(self.scene.clone())
    }
    fn upload(&self, _: &Lease, _: &Accum, _: &Stats) -> Uploaded {
        self.uploads.fetch_add(1, Ordering::SeqCst);
        Uploaded::Accepted
    }
    fn fail(&self, _: &Lease, _: &str) {
        self.failures.fetch_add(1, Ordering::SeqCst);
    }
}

/// Issue 14: a worker rendered a chunk to its end after its lease was gone (its job cancelled
/// or deleted), then had the upload refused. Now the first refused heartbeat stops the render
/// within a band of rows, and nothing is uploaded or reported as failed.
#[test]
fn a_revoked_lease_stops_the_render_mid_chunk() {
    let scene = Arc::new(load("small.xml", &[]));
    // The whole chunk, 48 x 40 pixels x 4096 samples, for scale.
    let t = Instant::now();
    let region = Region { x0: 0, y0: 0, x1: 48, y1: 4, s0: 0, s1: 4096 };
    furnace_core::render_region(&scene, &region, 0);
    let whole = t.elapsed().as_secs_f64() * 10.0;
    let link = Arc::new(Revoked {
        scene,
        handed: AtomicBool::new(false),
        heartbeats: AtomicU32::new(0),
        uploads: AtomicU32::new(0),
        failures: AtomicU32::new(0),
    });
    let cfg = one_thread(link.clone());
    let t = Instant::now();
    assert_eq!(furnace_worker::run(cfg).unwrap(), 0, "no chunk counts as done");
    let took = t.elapsed().as_secs_f64();
    assert_eq!(link.heartbeats.load(Ordering::SeqCst), 1);
    assert_eq!((link.uploads.load(Ordering::SeqCst), link.failures.load(Ordering::SeqCst)), (0, 0));
    assert!(took < whole / 4.0, "stopped after {took:.2} s; the whole chunk takes about {whole:.2} s");
}

/// Hands out one small chunk whose upload crawls (a slow link): 1 s, 8 leases long.
struct SlowUpload {
    scene: Arc<Scene>,
    handed: AtomicBool,
    uploading: AtomicBool,
    beats_while_uploading: AtomicU32,
}

impl Link for SlowUpload {
    fn lease(&self, _: &str) -> Result<Option<Lease>, String> {
        Ok(lease_once(&self.handed, Region { x0: 0, y0: 0, x1: 4, y1: 4, s0: 0, s1: 1 }, 120))
    }
    fn heartbeat(&self, _: &Lease) -> bool {
        if self.uploading.load(Ordering::SeqCst) {
            self.beats_while_uploading.fetch_add(1, Ordering::SeqCst);
        }
        true
    }
    fn scene(&self, _: &Lease) -> Result<Arc<Scene>, String> {
        Ok(self.scene.clone())
    }
    fn upload(&self, _: &Lease, _: &Accum, _: &Stats) -> Uploaded {
        self.uploading.store(true, Ordering::SeqCst);
        std::thread::sleep(Duration::from_secs(1));
        self.uploading.store(false, Ordering::SeqCst);
        Uploaded::Accepted
    }
    fn fail(&self, _: &Lease, _: &str) {}
}

/// Found by the namespace test: heartbeats stopped when a chunk's render ended, so over a slow
/// link a lease expired during its upload and the chunk was refused and rendered again. The
/// lease is now kept alive while uploading.
#[test]
fn a_lease_is_kept_alive_while_its_upload_crawls() {
    let link = Arc::new(SlowUpload {
        scene: Arc::new(load("small.xml", &[])),
        handed: AtomicBool::new(false),
        uploading: AtomicBool::new(false),
        beats_while_uploading: AtomicU32::new(0),
    });
    let cfg = one_thread(link.clone());
    assert_eq!(furnace_worker::run(cfg).unwrap(), 1);
    // A heartbeat every 40 ms: about 25 in the second the upload takes.
    let beats = link.beats_while_uploading.load(Ordering::SeqCst);
    assert!(beats >= 10, "{beats} heartbeats while uploading");
}
