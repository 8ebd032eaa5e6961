//! A worker and a coordinator in one process.

use std::sync::{Arc, Mutex};

use furnace_coordinator::state::accept_partial;
use furnace_coordinator::{CoordError, Coordinator};
use furnace_core::{Accum, Scene, Stats};
use furnace_proto::{Lease, Link, Uploaded};

/// A coordinator in the same process: leases and partials go through the same
/// [`Coordinator`] calls as the HTTP API's, without encoding or sockets.
pub struct LocalLink {
    pub coord: Arc<Mutex<Coordinator>>,
    /// Render statistics of every accepted chunk.
    pub stats: Mutex<Stats>,
}

impl LocalLink {
    pub fn new(coord: Arc<Mutex<Coordinator>>) -> LocalLink {
        LocalLink { coord, stats: Mutex::new(Stats::default()) }
    }
    fn lock(&self) -> std::sync::MutexGuard<'_, Coordinator> {
        self.coord.lock().unwrap_or_else(|e| e.into_inner())
    }
}

impl Link for LocalLink {
    fn lease(&self, worker: &str) -> Result<Option<Lease>, String> {
        Ok(self.lock().lease(worker, std::time::Instant::now()))
    }
    fn heartbeat(&self, l: &Lease) -> bool {
        self.lock().heartbeat(&l.job, l.chunk.id, l.epoch, std::time::Instant::now()).is_ok()
    }
    fn scene(&self, l: &Lease) -> Result<Arc<Scene>, String> {
        furnace_coordinator::state::load_scene(&self.coord, &l.job).map_err(|e| e.to_string())
    }
    fn upload(&self, l: &Lease, acc: &Accum, stats: &Stats) -> Uploaded {
        match accept_partial(&self.coord, &l.job, l.chunk.id, l.epoch, acc, Some(stats), None) {
            Ok(()) => {
                self.stats.lock().unwrap_or_else(|e| e.into_inner()).merge(stats);
                Uploaded::Accepted
            }
            Err(CoordError::Internal(e)) => Uploaded::Retry(e),
            Err(e) => Uploaded::Refused(e.to_string()),
        }
    }
    fn fail(&self, l: &Lease, error: &str) {
        let _ = self.lock().fail(&l.job, l.chunk.id, l.epoch, error);
    }
}
