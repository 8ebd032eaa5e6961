//! Scenes: Mitsuba 3 XML files loaded into everything the renderer needs.

pub mod assets;
pub mod build;
pub mod plugins;
pub mod xml;

use std::path::{Path, PathBuf};

use crate::bsdf::Bsdf;
use crate::camera::Camera;
use crate::film::Filter;
use crate::geometry::{Accel, Interaction, Ray, Shape};
use crate::light::Light;
use crate::plan::{PlanDescription, Techniques};

pub use xml::Pos;

/// A scene that cannot be loaded: the file, the line and column (0 when the whole file is at
/// fault), and what was expected.
#[derive(Debug, Clone, thiserror::Error)]
#[error("{}{}: {message}", file.display(), if line > &0 { format!(":{line}:{col}") } else { String::new() })]
pub struct SceneError {
    pub file: PathBuf,
    pub line: u32,
    pub col: u32,
    pub message: String,
}

impl SceneError {
    pub fn at(file: &Path, pos: Pos, message: impl Into<String>) -> SceneError {
        SceneError { file: file.to_path_buf(), line: pos.line, col: pos.col, message: message.into() }
    }

    pub fn file(file: &Path, message: impl Into<String>) -> SceneError {
        SceneError { file: file.to_path_buf(), line: 0, col: 0, message: message.into() }
    }
}

/// The output image: full film size, the cropped window we render, and the pixel filter.
#[derive(Clone, Debug, PartialEq)]
pub struct FilmSettings {
    pub width: u32,
    pub height: u32,
    pub crop_x: u32,
    pub crop_y: u32,
    pub crop_width: u32,
    pub crop_height: u32,
    pub filter: Filter,
}

/// Mitsuba's `path` integrator settings.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct PathSettings {
    /// Longest path, in vertices after the camera (`u32::MAX` for Mitsuba's -1).
    pub max_depth: u32,
    /// Depth from which every path goes through Russian roulette, as in Mitsuba (on Furnace's
    /// scale, and for low-throughput paths before it too: `Techniques::early_roulette`).
    pub rr_depth: u32,
    /// Hide directly visible emitters.
    pub hide_emitters: bool,
}

/// What loading one scene may take.
#[derive(Clone, Debug)]
pub struct LoadLimits {
    /// Most memory the load may hold, estimated before each part is read: what each texture,
    /// mesh and curve file keeps, what its loader holds while reading it, and the BVH's build
    /// (the estimates are in `scene::build`, measured in docs/DESIGN.md).
    pub max_bytes: u64,
    /// The load stops with an error once this instant is past.
    pub deadline: Option<std::time::Instant>,
    /// Build the BVH. Without it a scene can be checked and planned but not rendered (the
    /// coordinator's case); its cost counts all the same, so that a scene loaded within a
    /// budget loads within the same budget where it is rendered.
    pub accel: bool,
    /// Files earlier loads parsed, to use again (see [`assets`]); `None`: every file is read.
    pub assets: Option<std::sync::Arc<assets::AssetCache>>,
}

/// The memory a farm's coordinator and workers let one scene take to load, unless told
/// otherwise (`--max-scene-memory-mb`).
pub const FARM_SCENE_BYTES: u64 = 8 << 30;

impl Default for LoadLimits {
    /// No limit on memory or time; the BVH built.
    fn default() -> LoadLimits {
        LoadLimits { max_bytes: u64::MAX, deadline: None, accel: true, assets: None }
    }
}

/// A loaded scene.
pub struct Scene {
    pub file: PathBuf,
    pub camera: Camera,
    pub film: FilmSettings,
    pub integrator: PathSettings,
    /// Samples per pixel the scene asks for (`sample_count`).
    pub spp: u32,
    /// Sampler seed from the scene (`seed`, default 0).
    pub seed: u64,
    /// The sampler plugin the scene named (Furnace always uses Owen-scrambled Sobol).
    pub sampler_type: String,
    pub shapes: Vec<Shape>,
    pub bsdfs: Vec<Bsdf>,
    /// `bsdfs[k].traits()` for each BSDF, kept with them.
    pub bsdf_traits: Vec<crate::bsdf::Traits>,
    pub lights: Vec<Light>,
    /// Indices into `lights` of lights at infinity (seen by escaping rays).
    pub infinite_lights: Vec<u32>,
    /// Indices into `lights` of the lights light sampling picks among ([`Light::is_sampled`]).
    pub sampled_lights: Vec<u32>,
    pub accel: Accel,
    /// What the integrator runs (see `plan`).
    pub techniques: Techniques,
    /// Every file the scene reads besides itself (for scene bundles).
    pub assets: Vec<PathBuf>,
    /// The most memory its load was estimated to hold at once (see [`LoadLimits`]): a load
    /// with `max_bytes` below it is refused.
    pub load_estimate: u64,
}

/// Indices of the lights that light sampling picks among ([`Light::is_sampled`]).
pub(crate) fn sampled_lights(lights: &[Light]) -> Vec<u32> {
    (0..lights.len() as u32).filter(|&i| lights[i as usize].is_sampled()).collect()
}

impl Scene {
    /// Loads a scene file; `defines` override `<default>` parameters (`-D name=value`).
    pub fn load(path: &Path, defines: &[(String, String)]) -> Result<Scene, SceneError> {
        Scene::load_with(path, defines, &LoadLimits::default())
    }

    /// [`Scene::load`] within `limits`: memory, time, and whether to build the BVH.
    pub fn load_with(
        path: &Path,
        defines: &[(String, String)],
        limits: &LoadLimits,
    ) -> Result<Scene, SceneError> {
        guarded(path, || {
            let mut budget = build::Budget::new(limits);
            let size = std::fs::metadata(path).map(|m| m.len()).unwrap_or(0);
            let xml = size.saturating_mul(build::XML_PER_BYTE);
            budget.charge("the scene file", xml, xml).map_err(|e| SceneError::file(path, e))?;
            build::build_within(&xml::parse_file(path, defines)?, budget)
        })
    }

    /// Loads a scene file, letting `edit` change the parsed document before it is built.
    pub fn load_edited(
        path: &Path,
        defines: &[(String, String)],
        edit: &dyn Fn(&mut xml::Doc),
    ) -> Result<Scene, SceneError> {
        guarded(path, || {
            let mut doc = xml::parse_file(path, defines)?;
            edit(&mut doc);
            build::build(&doc, &LoadLimits::default())
        })
    }

    /// Loads scene XML held in memory; relative asset paths resolve against `path`'s folder.
    pub fn load_str(text: &str, path: &Path, defines: &[(String, String)]) -> Result<Scene, SceneError> {
        guarded(path, || build::build(&xml::parse_str(text, path, defines)?, &LoadLimits::default()))
    }

    /// What rendering this scene does, in words (the render plan's description).
    pub fn describe(&self) -> PlanDescription {
        PlanDescription::of(self)
    }

    /// Turns MIS compensation off in every environment map and constant (`furnace report`'s
    /// ablations), and derives again what depends on it: the lights light sampling picks
    /// among and the techniques.
    pub fn disable_mis_compensation(&mut self) {
        for l in &mut self.lights {
            l.disable_mis_compensation();
        }
        self.sampled_lights = sampled_lights(&self.lights);
        // (The light-sample cutoff stays as derived for the scene as loaded: the ablation
        // changes compensation alone.)
        let (cutoff, pending) = (self.techniques.light_cutoff, self.techniques.light_cutoff_pending);
        self.techniques = Techniques::derive(self);
        (self.techniques.light_cutoff, self.techniques.light_cutoff_pending) = (cutoff, pending);
    }

    /// Derives the techniques from the scene ([`Techniques::derive`]), and then the
    /// light-sample cutoff: [`crate::plan::LIGHT_CUTOFF`] of the scene's brightness as those
    /// techniques render it ([`crate::render::preview`] of the whole film, whatever the crop
    /// window), kept where it leaves out at least [`crate::plan::CUTOFF_SAVES`] of the
    /// preview's shadow rays (elsewhere its test would cost more than it saves).
    /// Deterministic: every load of the scene with its BVH derives the same cutoff on the same
    /// CPU target. Without the BVH (`built` false: the coordinator's loads, which plan but do
    /// not render) the cutoff is left to the loads that render
    /// ([`Techniques::light_cutoff_pending`]).
    pub fn derive_techniques(&mut self, built: bool) {
        self.techniques = Techniques::derive(self);
        if !self.techniques.light_sampling {
            return;
        }
        if !built {
            self.techniques.light_cutoff_pending = true;
            return;
        }
        // The whole film, so that a crop window renders its pixels as the whole image does.
        let film = self.film.clone();
        (self.film.crop_x, self.film.crop_y) = (0, 0);
        (self.film.crop_width, self.film.crop_height) = (film.width, film.height);
        let (brightness, all) = crate::render::preview(self);
        let cutoff = (brightness * crate::plan::LIGHT_CUTOFF) as f32;
        if cutoff > 0.0 && cutoff.is_finite() {
            self.techniques.light_cutoff = cutoff;
            let (_, traced) = crate::render::preview(self);
            let saves = 1.0 - traced as f64 / all as f64;
            tracing::debug!(brightness, cutoff, saves, "light-sample cutoff");
            if !(saves >= crate::plan::CUTOFF_SAVES) {
                self.techniques.light_cutoff = 0.0;
            }
        }
        self.film = film;
    }

    /// Whether the scene has a light of this kind.
    pub fn has_light(&self, kind: crate::light::LightKind) -> bool {
        self.lights.iter().any(|l| l.kind() == kind)
    }

    #[inline]
    pub fn intersect(&self, ray: &Ray) -> Option<Interaction> {
        self.accel.intersect(&self.shapes, ray)
    }

    /// [`Scene::intersect`] for a ray of the bundle that `cands` was gathered for
    /// ([`crate::geometry::Accel::gather`]). The packets' reference in tests.
    #[cfg(test)]
    pub(crate) fn intersect_among(
        &self,
        ray: &Ray,
        cands: &crate::geometry::bvh::Candidates,
    ) -> Option<Interaction> {
        self.accel.intersect_among(&self.shapes, ray, cands)
    }

    /// [`Scene::intersect_among`] for up to [`crate::geometry::bvh::PACKET`] rays of one
    /// bundle at once, into `out` (as long as `rays`).
    pub(crate) fn intersect_among_packet(
        &self,
        rays: &[Ray],
        cands: &crate::geometry::bvh::Candidates,
        out: &mut [Option<crate::geometry::bvh::Hit>],
    ) {
        self.accel.intersect_among_packet(&self.shapes, rays, cands, out)
    }

    #[inline]
    pub fn occluded(&self, ray: &Ray) -> bool {
        self.accel.occluded(&self.shapes, ray)
    }

    /// [`Scene::occluded`] for a ray spawned from `from`
    /// ([`crate::geometry::bvh::Accel::spawned_from`]).
    #[inline]
    pub fn occluded_from(&self, ray: &Ray, from: crate::geometry::bvh::SpawnedFrom) -> bool {
        self.accel.occluded_from(&self.shapes, ray, from)
    }
}

/// Runs a scene load, turning a panic (a bug: every input should get a proper error) into the
/// load's error, so that no scene can take down a worker or the coordinator.
fn guarded(path: &Path, load: impl FnOnce() -> Result<Scene, SceneError>) -> Result<Scene, SceneError> {
    std::panic::catch_unwind(std::panic::AssertUnwindSafe(load)).unwrap_or_else(|panic| {
        Err(SceneError::file(
            path,
            format!(
                "internal error while loading the scene (a bug; please report it): {}",
                panic_message(&*panic)
            ),
        ))
    })
}

/// The text of a caught panic.
pub fn panic_message(panic: &(dyn std::any::Any + Send)) -> String {
    match (panic.downcast_ref::<&str>(), panic.downcast_ref::<String>()) {
        (Some(s), _) => s.to_string(),
        (_, Some(s)) => s.clone(),
        _ => "panic without a message".into(),
    }
}

impl std::fmt::Debug for Scene {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Scene")
            .field("file", &self.file)
            .field("film", &self.film)
            .field("shapes", &self.shapes.len())
            .field("lights", &self.lights.len())
            .field("techniques", &self.techniques)
            .finish_non_exhaustive()
    }
}
