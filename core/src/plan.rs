//! The render plan: which techniques this scene needs, derived once at load. The integrator and
//! camera run only the stages the plan switches on; an effect the scene does not use costs
//! nothing.
//!
//! Two parts: [`Techniques`], typed switches that the integrator reads where each acts, and
//! [`PlanDescription`], what the render does in words, for people (`furnace render --plan`,
//! the log, a job's status). Settings the scene states have one home elsewhere, which both
//! read: `max_depth`, `rr_depth` and `hide_emitters` in `Scene::integrator`, the lens in
//! `Camera::lens` (`None`: a pinhole), MIS compensation in each environment map and constant
//! (`Scene::sampled_lights` lists the lights light sampling picks among).

use std::fmt;

use serde::Serialize;

use crate::bsdf::Bsdf;
use crate::light::{Light, LightKind};
use crate::scene::Scene;
use crate::texture::{FilterType, Texture};

/// The techniques the path tracer runs for a scene.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct Techniques {
    /// Next-event estimation: some light is sampled (`Scene::sampled_lights`: not a
    /// MIS-compensated constant) and some BSDF is not purely specular.
    pub light_sampling: bool,
    /// MIS (power heuristic) between BSDF and light sampling: light sampling of lights that
    /// BSDF-sampled rays can also hit (area, constant and envmap lights). With light sampling
    /// but without MIS, emission that BSDF-sampled rays find is left to light sampling (only
    /// reachable as an ablation: derived plans have MIS whenever such lights are sampled).
    pub mis: bool,
    /// Rays that leave the scene look up lights at infinity.
    pub escaped_rays_lookup: bool,
    /// Camera rays carry differentials and first hits compute texture footprints (some
    /// texture is `trilinear` or `ewa`).
    pub footprints: bool,
    /// Light samples that would add less than this luminance to their pixel go through
    /// Russian roulette before their shadow ray: traced with probability (what they would
    /// add) / cutoff, and weighted up by its inverse when traced, so that each adds the
    /// cutoff or nothing. The expectation is unchanged; 0 (the default) traces every one.
    /// [`Scene::derive_techniques`] sets it to [`LIGHT_CUTOFF`] of the scene's brightness.
    pub light_cutoff: f32,
    /// The scene was loaded without its BVH (to be checked and planned, not rendered): the
    /// loads that render it derive the cutoff.
    pub light_cutoff_pending: bool,
    /// From the second bounce on, a path whose throughput (its largest channel, times eta^2,
    /// as Mitsuba's roulette measures it) has fallen under this goes through Russian roulette
    /// even before `rr_depth`: it goes on with probability throughput / this, weighted by the
    /// inverse. From `rr_depth` on every path does, with that probability but at most 0.95
    /// (Mitsuba's rule is throughput, at most 0.95: it ended half the paths of a closed room
    /// that still carried half their light). Before `rr_depth` the first bounce never does:
    /// what it finds is most of a dark pixel's value (textured.xml's dark squares lost 2.5% of
    /// relMSE to it for 2% of time). 0: Mitsuba's roulette alone, from `rr_depth`.
    /// [`Techniques::derive`] sets [`EARLY_ROULETTE`].
    pub early_roulette: f32,
}

/// [`Techniques::early_roulette`]: 30%. Fur absorbs: two or three bounces in, many of its
/// paths carry a few percent, and each bounce through fur costs a full ray (docs/BENCHMARKS.md,
/// "Issue 15, thirty-second step", which began at 5%, before rr_depth only). In a closed room
/// (cbox) paths off the coloured walls fall under a third of their throughput within a few
/// bounces, each bounce a full ray for little light, while those off the white walls keep
/// half of it past rr_depth, where Mitsuba's rule ended half of them. Efficiency
/// (1 / (relMSE x time), 3 seeds) against 5% before rr_depth and Mitsuba's rule after it:
/// cbox +9.5%, whimsical +5%, hair -2% (runs of one binary differ by 3-5% in time);
/// textured, envmap and thinlens the same (their paths leave the scene first); "Issue 15,
/// thirty-fourth step".
pub const EARLY_ROULETTE: f32 = 0.3;

/// The light-sample cutoff ([`Techniques::light_cutoff`]) as a share of the scene's
/// brightness ([`crate::render::preview`]): 3%. In fur, paths lose most of their throughput
/// to absorption within a few bounces, and many of their shadow rays would add under it
/// (docs/BENCHMARKS.md, "Issue 15, thirty-second step", which set 1%). Efficiency
/// (1 / (relMSE x time), 3 seeds) at 3% against 1%: hair +3.7%, whimsical +3.4%, envmap +2%,
/// the error within 0.1% and the time shorter; thinlens, which then gets a cutoff, -0.7%
/// (within the spread); cbox's preview leaves out 8.8% (under [`CUTOFF_SAVES`]: none, as
/// before, where a cutoff would cost it 2-4%); "Issue 15, thirty-fourth step".
pub const LIGHT_CUTOFF: f64 = 0.03;

/// The share of shadow rays the cutoff must leave out of the scene's preview for a render to
/// use it ([`crate::scene::Scene::derive_techniques`]). Its test costs about 30 instructions
/// a light sample (and, for an environment map, the radiance lookup of samples whose shadow
/// ray is blocked); the cheapest shadow ray about 300 (cbox's, callgrind), fur's thousands:
/// at 15% left out it pays in any scene. (The early roulette leaves fewer light samples for
/// the cutoff: whimsical's preview read 25% before it, 21% with it at 5%, 18% at 30%, with a
/// cutoff of 1%; 30% with the cutoff at 3%. cbox's reads 8.8%.)
pub const CUTOFF_SAVES: f64 = 0.15;

impl Techniques {
    pub fn derive(scene: &Scene) -> Techniques {
        let sampled = || scene.sampled_lights.iter().map(|&k| &scene.lights[k as usize]);
        let light_sampling = sampled().next().is_some() && scene.bsdfs.iter().any(Bsdf::is_smooth);
        let mis = light_sampling && sampled().any(|l| l.kind().is_hit_by_rays());
        Techniques {
            light_sampling,
            mis,
            escaped_rays_lookup: !scene.infinite_lights.is_empty(),
            footprints: scene.bsdfs.iter().flat_map(|b| b.textures()).any(|t| t.wants_footprint()),
            light_cutoff: 0.0,
            light_cutoff_pending: false,
            early_roulette: EARLY_ROULETTE,
        }
    }
}

/// Lights of one kind in a scene.
#[derive(Clone, Debug, PartialEq, Eq, Serialize)]
pub struct LightCount {
    pub kind: &'static str,
    pub count: usize,
}

/// What a scene's render does, in words: the scene's settings and the stages its
/// [`Techniques`] run, in order. `Display` writes the text `furnace render --plan` prints;
/// it serialises (`furnace render --plan --json`).
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct PlanDescription {
    pub camera: String,
    pub filter: String,
    pub sampler: String,
    /// Emitters by kind, in a fixed order.
    pub emitters: Vec<LightCount>,
    /// `None`: unlimited.
    pub max_depth: Option<u32>,
    pub rr_depth: u32,
    pub hide_emitters: bool,
    pub stages: Vec<String>,
}

impl PlanDescription {
    pub fn of(scene: &Scene) -> PlanDescription {
        let t = &scene.techniques;
        let camera = match scene.camera.lens {
            None => "pinhole (no lens samples)".to_string(),
            Some(l) => format!(
                "thin lens, aperture radius {}, focus distance {}",
                l.aperture_radius, l.focus_distance
            ),
        };
        let emitters: Vec<LightCount> = LightKind::ALL
            .iter()
            .map(|&k| LightCount {
                kind: k.name(),
                count: scene.lights.iter().filter(|l| l.kind() == k).count(),
            })
            .filter(|c| c.count > 0)
            .collect();
        let mut stages = vec![
            format!(
                "camera rays ({})",
                if scene.camera.lens.is_some() {
                    "thin lens: 2 lens dimensions per sample"
                } else {
                    "pinhole"
                }
            ),
            "intersect (8-wide BVH)".to_string(),
        ];
        let (mut spheres, mut read) = (0, 0);
        for s in &scene.shapes {
            if let crate::geometry::Geometry::Sphere(b) = &s.geometry {
                spheres += 1;
                read += usize::from(b.tangents);
            }
        }
        if spheres > 0 {
            stages.push(format!(
                "spheres: uv and tangents at hits for {read} of {spheres} (where a texture, anisotropy, hair or an emitter's texture reads them)"
            ));
        }
        if t.light_sampling {
            let kinds: Vec<&str> = LightKind::ALL
                .into_iter()
                .filter(|&k| scene.sampled_lights.iter().any(|&i| scene.lights[i as usize].kind() == k))
                .map(LightKind::name)
                .collect();
            stages.push(format!("light sampling: {}", kinds.join(", ")));
        }
        if scene.lights.iter().any(|l| matches!(l, Light::Constant { compensated: true, .. })) {
            stages.push("constant emitter: left to BSDF sampling (MIS-compensated)".into());
        }
        if t.mis {
            stages.push("MIS (power heuristic): BSDF sampling x light sampling".into());
        }
        if t.light_sampling && t.light_cutoff > 0.0 {
            stages.push(format!(
                "light samples adding under {:.3e} ({}% of the scene's brightness) to a pixel: Russian roulette before the shadow ray",
                t.light_cutoff,
                LIGHT_CUTOFF * 100.0
            ));
        }
        if t.light_sampling && t.light_cutoff_pending {
            stages.push(
                "light-sample cutoff: derived from a preview where the scene is rendered (this load built no BVH)"
                    .into(),
            );
        }
        let mut bsdfs: Vec<&'static str> = Vec::new();
        for b in &scene.bsdfs {
            collect_bsdf_names(b, &mut bsdfs);
        }
        stages.push(format!("BSDF sampling: {}", bsdfs.join(", ")));
        let emitter_textures = scene.lights.iter().filter_map(|l| match l {
            Light::Area { radiance, .. } => Some(radiance),
            _ => None,
        });
        for tex in scene.bsdfs.iter().flat_map(|b| b.textures()).chain(emitter_textures) {
            let line = match tex {
                Texture::Bitmap(bt) => {
                    let (w, h) = (bt.bitmap.width, bt.bitmap.height);
                    match bt.filter {
                        FilterType::Nearest => {
                            format!("texture: bitmap {w}x{h} nearest lookup, no footprint")
                        }
                        FilterType::Bilinear => {
                            format!("texture: bitmap {w}x{h} bilinear lookup, no footprint")
                        }
                        FilterType::Trilinear => format!(
                            "texture: bitmap {w}x{h} mip-mapped trilinear, footprint from ray differentials"
                        ),
                        FilterType::Ewa => {
                            format!(
                                "texture: bitmap {w}x{h} mip-mapped EWA, footprint from ray differentials"
                            )
                        }
                    }
                }
                Texture::Bytes(bt) => {
                    let (w, h, filter) = (bt.bitmap.width, bt.bitmap.height, bt.filter.name());
                    match bt.filter {
                        FilterType::Trilinear | FilterType::Ewa => format!(
                            "texture: bitmap {w}x{h} mip-mapped {}, footprint from ray differentials, 8-bit texels",
                            if bt.filter == FilterType::Ewa { "EWA" } else { "trilinear" }
                        ),
                        _ => format!("texture: bitmap {w}x{h} {filter} lookup, no footprint, 8-bit texels"),
                    }
                }
                Texture::Checkerboard(_) => "texture: checkerboard".to_string(),
                Texture::Const(_) => continue,
            };
            if !stages.contains(&line) {
                stages.push(line);
            }
        }
        if t.escaped_rays_lookup {
            stages.push("escaped rays: infinite lights".into());
        }
        let envmaps =
            || scene.lights.iter().filter_map(|l| if let Light::Envmap(e) = l { Some(e) } else { None });
        if envmaps().any(|e| e.is_sampled()) {
            stages.push(format!(
                "environment importance sampling (piecewise-bilinear luminance x solid angle, hierarchical warp{})",
                if t.mis && envmaps().any(|e| e.is_sampled() && e.compensated()) { ", MIS-compensated" } else { "" }
            ));
        }
        if envmaps().any(|e| !e.is_sampled()) {
            stages.push(
                "environment map: left to BSDF sampling (black, or constant and MIS-compensated)".into(),
            );
        }
        let i = &scene.integrator;
        if t.early_roulette > 0.0 {
            stages.push(format!(
                "Russian roulette from the second bounce for paths under {}% throughput, and from depth {} for all (at most 95% go on)",
                // (To a tenth of a percent: 0.3 in f32 times 100 prints 30.000002.)
                (t.early_roulette * 1000.0).round() / 10.0,
                i.rr_depth
            ));
        } else {
            stages.push(format!("Russian roulette from depth {}", i.rr_depth));
        }
        PlanDescription {
            camera,
            filter: scene.film.filter.name(),
            sampler: format!("owen-scrambled sobol (scene names '{}')", scene.sampler_type),
            emitters,
            max_depth: (i.max_depth != u32::MAX).then_some(i.max_depth),
            rr_depth: i.rr_depth,
            hide_emitters: i.hide_emitters,
            stages,
        }
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

impl fmt::Display for PlanDescription {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        writeln!(f, "camera      {}", self.camera)?;
        writeln!(f, "pixel       {} filter; sampler {}", self.filter, self.sampler)?;
        let lights: Vec<String> = self.emitters.iter().map(|c| format!("{} x{}", c.kind, c.count)).collect();
        writeln!(f, "emitters    {}", if lights.is_empty() { "none".into() } else { lights.join(", ") })?;
        writeln!(
            f,
            "integrator  path, max_depth {}, rr_depth {}{}",
            self.max_depth.map_or("unlimited".to_string(), |d| d.to_string()),
            self.rr_depth,
            if self.hide_emitters { ", emitters hidden" } else { "" }
        )?;
        writeln!(f, "stages:")?;
        for s in &self.stages {
            writeln!(f, "  - {s}")?;
        }
        Ok(())
    }
}
