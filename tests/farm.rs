//! The farm's merge rule: chunks rendered separately, merged in any order with duplicates,
//! give exactly the single-machine render.

mod common;

use common::*;
use furnace_coordinator::{JobAccum, MergeOutcome};
use furnace_proto::{chunk_plan, JobSettings};
use furnace_worker::render_chunk;

#[test]
fn chunks_merged_in_any_order_with_duplicates_equal_the_local_render() {
    let scene = load("small.xml", &[]);
    let settings = JobSettings {
        width: scene.film.crop_width,
        height: scene.film.crop_height,
        spp: 12,
        tile_size: 16,
        spp_per_chunk: 5,
        seed: 4,
        priority: 0,
    };
    let plan = chunk_plan(&settings);
    let partials: Vec<_> = plan.iter().map(|c| render_chunk(&scene, c, settings.seed).0).collect();
    let mut job = JobAccum::new(settings.width, settings.height);
    // Reverse order, every third chunk delivered twice.
    for (k, (c, p)) in plan.iter().zip(&partials).enumerate().rev() {
        assert_eq!(job.merge(c, p), MergeOutcome::Merged);
        if k % 3 == 0 {
            assert_eq!(job.merge(c, p), MergeOutcome::Duplicate);
        }
    }
    assert_eq!(job.chunks_merged(), plan.len());
    let local = render(&scene, settings.spp, settings.seed).0;
    assert!(job.accum == local, "farm merge differs from the local render");
}
