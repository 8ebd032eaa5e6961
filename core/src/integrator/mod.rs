//! Integrators and the per-render statistics they keep.

pub mod path;

use crate::light::LightKind;

/// Counters of the work a render did, by stage. Cheap (thread-local sums merged per chunk);
/// they let tests prove that a stage the plan leaves out never runs. They travel with the
/// farm's partials (as `furnace_proto::RenderStats`).
#[derive(Clone, Debug, Default, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct Stats {
    /// Camera samples traced.
    pub samples: u64,
    /// Samples that drew a point on the lens.
    pub lens_samples: u64,
    /// Closest-hit queries.
    pub rays: u64,
    /// Shadow (any-hit) queries.
    pub shadow_rays: u64,
    /// Light samples drawn, by [`LightKind`] (index `kind as usize`).
    pub light_samples: [u64; LightKind::COUNT],
    /// BSDF samples drawn.
    pub bsdf_samples: u64,
    /// Escaped rays that looked up lights at infinity.
    pub escaped_lookups: u64,
    /// Texture footprints computed from ray differentials.
    pub footprints: u64,
}

impl Stats {
    pub fn merge(&mut self, o: &Stats) {
        self.samples += o.samples;
        self.lens_samples += o.lens_samples;
        self.rays += o.rays;
        self.shadow_rays += o.shadow_rays;
        for k in 0..LightKind::COUNT {
            self.light_samples[k] += o.light_samples[k];
        }
        self.bsdf_samples += o.bsdf_samples;
        self.escaped_lookups += o.escaped_lookups;
        self.footprints += o.footprints;
    }

    pub fn light_samples_of(&self, kind: LightKind) -> u64 {
        self.light_samples[kind as usize]
    }
}
