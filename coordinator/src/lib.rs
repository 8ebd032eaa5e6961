//! Furnace's coordinator: jobs, chunk leases, the exact merge of partial accumulations, and
//! their persistence, behind the HTTP API of `furnace serve`.

pub mod api;
pub mod state;

use std::collections::HashSet;

use furnace_core::Accum;
use furnace_proto::ChunkSpec;

pub use api::{router, run, AppState};
pub use state::{CoordError, Coordinator};

/// The merged image of one job, in memory (the rule the coordinator applies).
pub struct JobAccum {
    pub accum: Accum,
    merged: HashSet<u32>,
}

#[derive(Debug, PartialEq, Eq)]
pub enum MergeOutcome {
    Merged,
    /// This chunk was merged before; the partial was ignored.
    Duplicate,
}

impl JobAccum {
    pub fn new(width: u32, height: u32) -> JobAccum {
        JobAccum { accum: Accum::new(0, 0, width, height), merged: HashSet::new() }
    }

    /// Merges `partial`, the result of `chunk`, unless that chunk was merged already.
    /// Integer sums make the result independent of the order of arrival.
    pub fn merge(&mut self, chunk: &ChunkSpec, partial: &Accum) -> MergeOutcome {
        if !self.merged.insert(chunk.id) {
            return MergeOutcome::Duplicate;
        }
        self.accum.merge(partial);
        MergeOutcome::Merged
    }

    pub fn chunks_merged(&self) -> usize {
        self.merged.len()
    }
}
