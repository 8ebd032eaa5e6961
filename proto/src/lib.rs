//! What crosses the wire between Furnace's coordinator and workers. Serde types plus pure
//! functions, no I/O.
//!
//! So far: job settings and the chunk plan, a pure function of the settings (every tile crossed
//! with every sample range, pass by pass). Leases, progress and the partial-accumulation
//! encoding join when the farm protocol does.

pub use furnace_core::Region;
use serde::{Deserialize, Serialize};

/// The render settings of a job (DESIGN.md defaults: 1920 x 1080 at 4096 spp, 64-pixel tiles,
/// 64 spp per chunk).
#[derive(Clone, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(default)]
pub struct JobSettings {
    pub width: u32,
    pub height: u32,
    pub spp: u64,
    pub tile_size: u32,
    pub spp_per_chunk: u64,
    pub seed: u64,
    pub priority: i32,
}

impl Default for JobSettings {
    fn default() -> Self {
        JobSettings {
            width: 1920,
            height: 1080,
            spp: 4096,
            tile_size: 64,
            spp_per_chunk: 64,
            seed: 0,
            priority: 0,
        }
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

#[cfg(test)]
mod tests {
    use super::*;

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
    fn settings_round_trip_with_defaults() {
        let s: JobSettings = serde_json_like("{}");
        assert_eq!(s, JobSettings::default());
    }

    // Minimal deserialisation of an empty object without pulling serde_json into proto's tests.
    fn serde_json_like(_: &str) -> JobSettings {
        use serde::de::value::{Error, MapDeserializer};
        let empty: MapDeserializer<std::iter::Empty<(String, u32)>, Error> =
            MapDeserializer::new(std::iter::empty());
        JobSettings::deserialize(empty).expect("defaults fill every field")
    }
}
