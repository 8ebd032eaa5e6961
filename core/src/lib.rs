#![allow(clippy::neg_cmp_op_on_partial_ord)] // `!(a > b)` is how NaN is rejected on purpose
//! Furnace's renderer: Mitsuba 3 scenes in, exact partial accumulations and images out.
//!
//! No networking and no async: the farm crates drive this library.

pub mod bsdf;
pub mod camera;
pub mod cpu;
pub mod film;
pub mod geometry;
pub mod image_io;
pub mod integrator;
pub mod light;
pub mod math;
pub mod plan;
pub mod render;
pub mod sampler;
pub mod scene;
pub mod simd;
pub mod testing;
pub mod texture;

pub use film::{Accum, Dropped};
pub use image_io::Image;
pub use integrator::Stats;
pub use plan::{PlanDescription, Techniques};
pub use render::{accum_rect, plan_regions, render_image, render_region, render_region_on, Region};
pub use scene::{LoadLimits, Scene, SceneError, FARM_SCENE_BYTES};
