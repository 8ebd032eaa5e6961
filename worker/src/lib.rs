//! Furnace's worker: renders chunks of a job with the shared core renderer.
//!
//! So far a worker renders a [`ChunkSpec`] into its partial accumulation. Pulling leases,
//! fetching scene bundles by hash, heartbeats and uploads join with the farm protocol.

use furnace_core::{render_region, Accum, Scene, Stats};
use furnace_proto::ChunkSpec;

/// Renders one chunk: its tile plus the filter margin, its sample range.
pub fn render_chunk(scene: &Scene, chunk: &ChunkSpec, seed: u64) -> (Accum, Stats) {
    render_region(scene, &chunk.region, seed)
}
