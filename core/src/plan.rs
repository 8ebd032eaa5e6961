//! The render plan: which effects this scene needs, derived once at load. The integrator and
//! camera run only the stages the plan lists; an effect the scene does not use costs nothing.

use std::fmt;

use crate::bsdf::Bsdf;
use crate::light::LightKind;
use crate::scene::Scene;
use crate::texture::{FilterType, Texture};

#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub enum CameraModel {
    #[default]
    Pinhole,
    /// Thin lens with a non-zero aperture (an aperture of 0 is planned as a pinhole).
    ThinLens { aperture_radius: f32, focus_distance: f32 },
}

#[derive(Clone, Debug, Default, PartialEq)]
pub struct RenderPlan {
    pub camera: CameraModel,
    /// Emitters by kind, with their counts, in a fixed order.
    pub lights: Vec<(LightKind, usize)>,
    /// Next-event estimation: some light can be sampled and some BSDF is not purely specular.
    pub light_sampling: bool,
    /// MIS (power heuristic) between BSDF and light sampling: light sampling of lights that
    /// BSDF-sampled rays can also hit (area, constant and envmap lights). With light sampling
    /// but without MIS, emission that BSDF-sampled rays find is left to light sampling (only
    /// reachable as an ablation: derived plans have MIS whenever such lights exist).
    pub mis: bool,
    /// Light sampling of an environment map leaves directions no brighter than its mean to
    /// BSDF sampling (MIS compensation; see `light::envmap`).
    pub mis_compensation: bool,
    /// Rays that leave the scene look up lights at infinity.
    pub escaped_rays_lookup: bool,
    /// BSDF plugins in use.
    pub bsdfs: Vec<&'static str>,
    /// One line per texture lookup kind in use.
    pub textures: Vec<String>,
    /// Camera rays carry differentials and first hits compute texture footprints (some
    /// texture is `trilinear` or `ewa`).
    pub footprints: bool,
    pub filter: String,
    pub max_depth: u32,
    pub rr_depth: u32,
    pub hide_emitters: bool,
    pub sampler: String,
}

impl RenderPlan {
    pub fn derive(scene: &Scene) -> RenderPlan {
        let camera = match scene.camera.lens {
            Some(l) if l.aperture_radius > 0.0 => {
                CameraModel::ThinLens { aperture_radius: l.aperture_radius, focus_distance: l.focus_distance }
            }
            _ => CameraModel::Pinhole,
        };
        let mut lights: Vec<(LightKind, usize)> = LightKind::ALL
            .iter()
            .map(|&k| (k, scene.lights.iter().filter(|l| l.kind() == k).count()))
            .collect();
        lights.retain(|&(_, n)| n > 0);
        let any_smooth = scene.bsdfs.iter().any(Bsdf::is_smooth);
        let light_sampling = !scene.lights.is_empty() && any_smooth;
        let mis = light_sampling
            && scene
                .lights
                .iter()
                .any(|l| matches!(l.kind(), LightKind::Area | LightKind::Constant | LightKind::Envmap));
        let mut bsdfs: Vec<&'static str> = Vec::new();
        for b in &scene.bsdfs {
            collect_bsdf_names(b, &mut bsdfs);
        }
        let mut textures = Vec::new();
        let emitter_textures = scene.lights.iter().filter_map(|l| match l {
            crate::light::Light::Area { radiance, .. } => Some(radiance),
            _ => None,
        });
        for t in scene.bsdfs.iter().flat_map(|b| b.textures()).chain(emitter_textures) {
            let line = match t {
                Texture::Bitmap(bt) => {
                    let (w, h) = (bt.bitmap.width, bt.bitmap.height);
                    match bt.filter {
                        FilterType::Nearest => format!("bitmap {w}x{h} nearest lookup, no footprint"),
                        FilterType::Bilinear => format!("bitmap {w}x{h} bilinear lookup, no footprint"),
                        FilterType::Trilinear => {
                            format!("bitmap {w}x{h} mip-mapped trilinear, footprint from ray differentials")
                        }
                        FilterType::Ewa => {
                            format!("bitmap {w}x{h} mip-mapped EWA, footprint from ray differentials")
                        }
                    }
                }
                Texture::Checkerboard(_) => "checkerboard".to_string(),
                Texture::Const(_) => continue,
            };
            if !textures.contains(&line) {
                textures.push(line);
            }
        }
        let footprints = scene.bsdfs.iter().flat_map(|b| b.textures()).any(|t| t.wants_footprint());
        RenderPlan {
            footprints,
            camera,
            lights,
            light_sampling,
            mis,
            mis_compensation: mis
                && scene
                    .lights
                    .iter()
                    .any(|l| matches!(l, crate::light::Light::Envmap(e) if e.compensated())),
            escaped_rays_lookup: !scene.infinite_lights.is_empty(),
            bsdfs,
            textures,
            filter: scene.film.filter.name(),
            max_depth: scene.integrator.max_depth,
            rr_depth: scene.integrator.rr_depth,
            hide_emitters: scene.integrator.hide_emitters,
            sampler: format!("owen-scrambled sobol (scene names '{}')", scene.sampler_type),
        }
    }

    pub fn has_light(&self, kind: LightKind) -> bool {
        self.lights.iter().any(|&(k, _)| k == kind)
    }
}

fn collect_bsdf_names(b: &Bsdf, out: &mut Vec<&'static str>) {
    if let Bsdf::TwoSided { front, back } = b {
        collect_bsdf_names(front, out);
        collect_bsdf_names(back, out);
    }
    if !out.contains(&b.name()) {
        out.push(b.name());
    }
}

impl fmt::Display for RenderPlan {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self.camera {
            CameraModel::Pinhole => writeln!(f, "camera      pinhole (no lens samples)")?,
            CameraModel::ThinLens { aperture_radius, focus_distance } => writeln!(
                f,
                "camera      thin lens, aperture radius {aperture_radius}, focus distance {focus_distance}"
            )?,
        }
        writeln!(f, "pixel       {} filter; sampler {}", self.filter, self.sampler)?;
        let lights: Vec<String> = self.lights.iter().map(|(k, n)| format!("{} x{n}", k.name())).collect();
        writeln!(f, "emitters    {}", if lights.is_empty() { "none".into() } else { lights.join(", ") })?;
        writeln!(
            f,
            "integrator  path, max_depth {}, rr_depth {}{}",
            if self.max_depth == u32::MAX { "unlimited".to_string() } else { self.max_depth.to_string() },
            self.rr_depth,
            if self.hide_emitters { ", emitters hidden" } else { "" }
        )?;
        writeln!(f, "stages:")?;
        writeln!(
            f,
            "  - camera rays ({})",
            match self.camera {
                CameraModel::Pinhole => "pinhole",
                CameraModel::ThinLens { .. } => "thin lens: 2 lens dimensions per sample",
            }
        )?;
        writeln!(f, "  - intersect (8-wide BVH)")?;
        if self.light_sampling {
            let kinds: Vec<&str> = self.lights.iter().map(|(k, _)| k.name()).collect();
            writeln!(f, "  - light sampling: {}", kinds.join(", "))?;
        }
        if self.mis {
            writeln!(f, "  - MIS (power heuristic): BSDF sampling x light sampling")?;
        }
        writeln!(f, "  - BSDF sampling: {}", self.bsdfs.join(", "))?;
        for t in &self.textures {
            writeln!(f, "  - texture: {t}")?;
        }
        if self.escaped_rays_lookup {
            writeln!(f, "  - escaped rays: infinite lights")?;
        }
        if self.has_light(LightKind::Envmap) {
            writeln!(
                f,
                "  - environment importance sampling (piecewise-bilinear luminance x solid angle, hierarchical warp{})",
                if self.mis_compensation { ", MIS-compensated" } else { "" }
            )?;
        }
        writeln!(f, "  - Russian roulette from depth {}", self.rr_depth)
    }
}
