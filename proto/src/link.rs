//! The worker's side of the contract: what it asks of a coordinator, wherever that runs.

use std::sync::Arc;

use furnace_core::{Accum, Scene, Stats};

use crate::Lease;

/// Where a worker gets its chunks and sends its results: a coordinator over HTTP (the
/// worker's `HttpLink`) or one in the same process (`furnace::local::LocalLink`). The
/// worker's loop is the same for both.
pub trait Link: Send + Sync {
    /// The next chunk, `None` when there is no work; `Err` when the coordinator is unreachable.
    fn lease(&self, worker: &str) -> Result<Option<Lease>, String>;
    /// Extends the lease; false when it is no longer this worker's.
    fn heartbeat(&self, lease: &Lease) -> bool;
    /// The lease's scene, loaded.
    fn scene(&self, lease: &Lease) -> Result<Arc<Scene>, String>;
    /// Delivers a rendered chunk: its accumulation and its render statistics.
    fn upload(&self, lease: &Lease, acc: &Accum, stats: &Stats) -> Uploaded;
    /// Reports that the chunk could not be rendered.
    fn fail(&self, lease: &Lease, error: &str);
}

/// What became of an upload.
#[derive(Clone, Debug, PartialEq, Eq)]
pub enum Uploaded {
    Accepted,
    /// Refused for good (stale lease, duplicate, bad partial): drop it.
    Refused(String),
    /// Not delivered (coordinator unreachable or failing): try again.
    Retry(String),
}
