//! Unidirectional path tracing with next-event estimation and multiple importance sampling
//! (power heuristic, Veach 1997) and Russian roulette. Mitsuba 3's `path` integrator, from
//! `rr_depth` on, continues with probability min(max(throughput) * eta^2, 0.95). Here, from
//! the second bounce on, paths under `Techniques::early_roulette` throughput (measured as
//! Mitsuba does) go on with probability throughput / early_roulette; from `rr_depth` on, with
//! that probability but at most 0.95, so that every path still ends (Mitsuba's rule when
//! early_roulette is 0). Light samples under `Techniques::light_cutoff` go through roulette
//! before their shadow ray. All keep the expectation.
//!
//! Depth follows Mitsuba: the camera ray's hit is depth 0; emission is gathered at every depth;
//! a vertex at depth d scatters only if d + 1 < max_depth.

use glam::{Vec2, Vec3};

use super::Stats;
use crate::bsdf::Bsdf;
use crate::geometry::bvh::{Hit, SpawnedFrom};
use crate::geometry::{Ray, RayDifferentials};
use crate::light::Light;
use crate::math::{apart, apart2, mis_power, Rgb};
use crate::sampler::SampleStream;
use crate::scene::Scene;
use crate::texture::Texture;

/// Lights among which next-event estimation picks by reusing the light sample's first
/// number (4 of its 23 bits at most).
const REUSE_LIGHTS: usize = 16;

/// Hidden emitters a camera ray passes through at most (stacked coplanar lights would
/// otherwise keep it in place).
const MAX_PASSES: u32 = 64;

/// How [`li`] finds its ray's first hit.
#[derive(Clone, Copy)]
pub enum First {
    /// Through the whole tree.
    Trace,
    /// Already found (by [`Scene::intersect_among_packet`]): the hit, or none.
    Found(Option<Hit>),
}

/// Radiance arriving along `ray`. `diff`: the camera ray's differentials, when the plan asks
/// for texture footprints (used at the first hit). `first`: how to find the ray's first hit.
/// `light0`: the first vertex's light sample, where the camera's own 4-D set has two numbers
/// to spare (a camera without a lens).
///
/// The numbers a vertex takes (`s`: one 4-D Owen-scrambled Sobol set, or hashed numbers past
/// [`crate::sampler::SOBOL_SETS`], is one stratified point): vertex d's light sample is set
/// `1 + 2d`'s first two numbers, its BSDF sample the last two of the set after its choices'
/// set, the next vertex's (`1 + 2(d + 1)`). So each BSDF sample is stratified together with
/// the light sample at the vertex it leads to: the two numbers the path's next direct light
/// depends on jointly. Paired with the same vertex's light sample, as before, it stratified
/// two independent choices instead (light through glass: envmap's relMSE at 64 spp over 64
/// seeds, median 0.00635 -> 0.00590, 10%-trimmed mean 0.00676 -> 0.00584).
/// Where `light0` is given, the first vertex's light sample comes with the pixel position in
/// the camera's set, and set 1 is never computed. docs/BENCHMARKS.md, "Issue 15,
/// twenty-fourth step".
pub fn li(
    scene: &Scene,
    mut ray: Ray,
    diff: Option<&RayDifferentials>,
    mut first: First,
    light0: Option<[f32; 2]>,
    s: &mut SampleStream,
    st: &mut Stats,
) -> Rgb {
    let plan = scene.techniques;
    let settings = &scene.integrator;
    if settings.max_depth == 0 {
        return Rgb::ZERO; // Mitsuba: max_depth 0 renders nothing, not even emitters
    }
    // Light sampling picks among `sampled_lights`: a MIS-compensated constant (or constant
    // map) is left to BSDF sampling (its light pdf is 0, so what BSDF sampling finds of it
    // weighs 1), and a black map has nothing to sample.
    let n_lights = scene.sampled_lights.len();
    let sel_pdf = if n_lights > 0 { 1.0 / n_lights as f32 } else { 0.0 };
    // Whether light sampling picks a light. The light (of at most REUSE_LIGHTS), and an area
    // light's primitive (`Light::sample`), are picked by reusing the light sample's first
    // number, rescaled within each choice (as Mitsuba does): the choices and the point on the
    // light then come from one stratified 2-D sample. Each reuse spends log2(choices) of the
    // number's 23 bits; more lights are picked with a number of their own.
    let chooses_light = n_lights > 1;
    let reuses_for_light = n_lights <= REUSE_LIGHTS;

    let mut l = Rgb::ZERO;
    let mut beta = Rgb::ONE;
    let mut eta = 1.0f32;
    let mut depth: u32 = 0;
    // The previous scattering vertex, for MIS of emission found by BSDF sampling.
    let mut prev_p = ray.o;
    let mut prev_pdf = 0.0f32;
    let mut prev_delta = true;
    let mut passes = 0u32;
    // What the ray leaves behind, which its traversal does not test (`Accel::spawned_from`).
    let mut from = SpawnedFrom::NOTHING;
    // This vertex's set, where it is known already: computed by the vertex before (whose BSDF
    // sample took its last two numbers), or the camera's spare numbers at the first.
    let mut here: Option<[f32; 4]> = light0.map(|[u, v]| [u, v, 0.0, 0.0]);

    loop {
        st.rays += 1;
        let show_emitters = !(settings.hide_emitters && depth == 0);
        // Without light sampling at the previous vertex, emission found here is unweighted.
        let unweighted = depth == 0 || prev_delta || !plan.light_sampling;
        let hit = match std::mem::replace(&mut first, First::Trace) {
            First::Trace => scene.accel.closest(&scene.shapes, &ray, from),
            First::Found(hit) => hit,
        };
        let Some(hit) = hit else {
            if plan.escaped_rays_lookup && show_emitters {
                st.escaped_lookups += 1;
                for &k in &scene.infinite_lights {
                    let light = &scene.lights[k as usize];
                    let (le, w) = if unweighted || !light.is_sampled() {
                        (light.le_infinite(ray.d), 1.0)
                    } else if !plan.mis {
                        (Rgb::ZERO, 0.0)
                    } else {
                        let (le, pdf) = light.le_pdf_infinite(ray.d);
                        (le, mis_power(prev_pdf, sel_pdf * pdf))
                    };
                    // (Read a coordinate at a time: `math::apart`.)
                    l += beta * apart(le) * w;
                }
            }
            break;
        };
        // The next vertex's set (past this vertex's choices), whose last two numbers are this
        // vertex's BSDF sample, computed here and taken below (after the pass through hidden
        // emitters, which takes none); this vertex's own set came from the vertex before (or
        // the camera), and is computed here only at a lens camera's first vertex. Computed
        // ahead of the hit's interaction, their table reads and stores are done by the time
        // shading reads them (plain build: textured +15%, thinlens +3%, the others within
        // 2.5%; docs/BENCHMARKS.md, "Issue 15, twenty-first step").
        let set = here.unwrap_or_else(|| s.peek_4d());
        let next = if depth.saturating_add(1) < settings.max_depth { s.peek_4d_ahead(2) } else { [0.0; 4] };
        // (Made here, not inside the Option: see `Accel::closest`.)
        let it = scene.accel.hit_interaction(&scene.shapes, &ray, &hit);
        let shape = &scene.shapes[it.shape as usize];
        // As Mitsuba 3.9: with hide_emitters, camera rays pass through emitting surfaces
        // (whatever their BSDF) as if they were not there; passing is not a bounce.
        if !show_emitters && shape.light.is_some() && passes < MAX_PASSES {
            passes += 1;
            ray = it.spawn_ray(ray.d);
            from = scene.accel.spawned_from(&scene.shapes, &hit, &it, ray.d);
            continue;
        }
        let wo_world = -ray.d;
        if let (Some(k), true) = (shape.light, show_emitters) {
            let light = &scene.lights[k as usize];
            let le = light.le_surface(&it, wo_world);
            if le != Rgb::ZERO {
                let w = if unweighted {
                    1.0
                } else if !plan.mis {
                    0.0 // light sampling alone (an ablation): this light was sampled by NEE
                } else {
                    mis_power(prev_pdf, sel_pdf * light.pdf_hit(&scene.shapes, prev_p, ray.d, &it))
                };
                l += beta * le * w;
            }
        }
        if depth.saturating_add(1) >= settings.max_depth {
            break;
        }

        let bsdf = &scene.bsdfs[shape.bsdf as usize];
        let traits = scene.bsdf_traits[shape.bsdf as usize];
        if traits.black {
            break;
        }
        // (The frame and wo read a coordinate at a time: `math::apart`.)
        let frame = it.frame.apart();
        let wo = apart(frame.to_local(wo_world));
        let tc = match diff {
            Some(d) if depth == 0 => {
                st.footprints += 1;
                it.tex_coord(d)
            }
            // (Read a coordinate at a time: `math::apart`.)
            _ => apart2(it.uv).into(),
        };
        // A textured diffuse surface's reflectance, looked up once here instead of by light
        // sampling's eval and again by bsdf.sample (both read it at `tc`, front side only).
        // (A constant texture owns nothing: no drop needed.)
        let looked_up;
        let bsdf = match bsdf {
            Bsdf::Diffuse { reflectance } if !reflectance.is_const() && wo.z > 0.0 => {
                let reflectance = Texture::Const(reflectance.eval(tc));
                looked_up = std::mem::ManuallyDrop::new(Bsdf::Diffuse { reflectance });
                &*looked_up
            }
            _ => bsdf,
        };
        // What both of the vertex's samples share for this wo, computed once (hair's angles and
        // attenuations: `Bsdf::at`).
        let bsdf = bsdf.at(wo);
        s.skip_4d();
        let [lu, lv, _, _] = set;
        let [_, _, bu, bv] = next;
        here = Some(next);
        // The light's choice past REUSE_LIGHTS lights, lobe choice, roulette, and a spare
        // number for a light's primitive: computed only if used here.
        let mut choices = s.defer_4d();

        // Next-event estimation: one light, chosen uniformly (as Mitsuba does). Its light sample
        // is drawn first, then the BSDF sample, then the light sample is evaluated and its
        // shadow ray traced: the BSDF sample does not depend on the light sample, so the core
        // computes it while the light sample's chain of divisions and roots (an environment
        // map's warp) is still in flight, instead of after the shadow ray. The same numbers in
        // either order.
        // The light chosen, kept apart from its sample: a tuple of the two would be a copy of
        // the sample, read back wide while its fields are still being stored (`math::apart`).
        let mut nee_light = None;
        let nee = if plan.light_sampling && n_lights > 0 && traits.smooth {
            let (k, lu) = if !chooses_light {
                (0, lu)
            } else if reuses_for_light {
                let x = lu * n_lights as f32;
                let k = (x as usize).min(n_lights - 1);
                (k, (x - k as f32).clamp(0.0, 1.0 - f32::EPSILON / 2.0))
            } else {
                (((choices.get(s)[0] * n_lights as f32) as usize).min(n_lights - 1), lu)
            };
            let light = &scene.lights[scene.sampled_lights[k] as usize];
            st.light_samples[light.kind() as usize] += 1;
            let spare = || choices.get(s)[3];
            nee_light = Some(light);
            light.sample(&scene.shapes, &it, Vec2::new(lu, lv), spare)
        } else {
            None
        };

        // BSDF sampling (taken up after next-event estimation).
        st.bsdf_samples += 1;
        let bsel = if traits.chooses_lobe { choices.get(s)[1] } else { 0.0 };
        let bs = bsdf.sample(tc, wo, bsel, Vec2::new(bu, bv));

        if let (Some(light), Some(ls)) = (nee_light, &nee) {
            if ls.pdf > 0.0 && !ls.is_black() {
                // (Read a coordinate at a time: `math::apart`.)
                let ls_wi = apart(ls.wi);
                let wi = frame.to_local(ls_wi);
                let (f, bsdf_pdf) = bsdf.eval_pdf(tc, wo, wi);
                let light_pdf = ls.pdf * sel_pdf;
                let w = if ls.delta || !plan.mis { 1.0 } else { mis_power(light_pdf, bsdf_pdf) };
                // The light's radiance, looked up ahead of the shadow ray only where a cutoff
                // needs it (an environment map's lookup is a bilinear fetch, otherwise made
                // only for rays that are clear).
                let mut li = None;
                // Russian roulette below the cutoff (`Techniques::light_cutoff`) on the
                // path's roulette number, which nothing about this sample depends on. It is
                // a multiple of 2^-23 (Sobol sets; of 2^-24 past them), so q is rounded up to
                // one: the chance of u < q is then q exactly, and the expectation is kept.
                // (What the sample adds is measured in magnitude, so that a negative radiance
                // goes through the roulette too; a NaN is traced, as before, for the film to
                // count.)
                let mut keep = 1.0;
                if f != Rgb::ZERO && plan.light_cutoff > 0.0 {
                    let le = ls.li(light);
                    li = Some(le);
                    let c = crate::math::luminance((beta * f * le).abs()) * (w / light_pdf);
                    if c < plan.light_cutoff {
                        keep = roulette(c / plan.light_cutoff, choices.get(s)[2]);
                    }
                }
                if f != Rgb::ZERO && keep > 0.0 {
                    let shadow = match ls.target {
                        Some((t, dist)) => it.spawn_ray_to(ls_wi, apart(t), dist),
                        None => it.spawn_ray(ls_wi),
                    };
                    st.shadow_rays += 1;
                    let from = scene.accel.spawned_from(&scene.shapes, &hit, &it, ls_wi);
                    if !scene.occluded_from(&shadow, from) {
                        let le = li.unwrap_or_else(|| ls.li(light));
                        // (keep after the product: it is at most 2^23 where the product is
                        // under the cutoff, so their product stays finite.)
                        l += beta * f * le * (w / light_pdf) * keep;
                    }
                }
            }
        }

        let Some(bs) = bs else {
            break;
        };
        // (The sample's vectors read a coordinate at a time: `math::apart`.)
        let wi_world = frame.to_world(apart(bs.wi));
        beta *= apart(bs.weight);
        eta *= bs.eta;
        prev_p = it.p;
        prev_pdf = bs.pdf;
        prev_delta = bs.delta;
        ray = it.spawn_ray(wi_world);
        from = scene.accel.spawned_from(&scene.shapes, &hit, &it, wi_world);
        depth += 1;

        // Russian roulette (`Techniques::early_roulette`, threshold t): from the second bounce
        // on, a path under t of its throughput goes on with probability throughput / t; from
        // rr_depth on every path does, at most 0.95 (with t = 0, Mitsuba's rule: throughput,
        // at most 0.95). On the path's roulette number, which nothing this vertex has drawn
        // depends on; through `roulette`, which rounds q up to the numbers' grid, so that the
        // chance of going on is q exactly.
        let (m, t) = (beta.max_element() * eta * eta, plan.early_roulette);
        let q = if depth >= settings.rr_depth {
            (if t > 0.0 { m / t } else { m }).min(0.95)
        } else if t > 0.0 && depth >= 2 {
            (m / t).min(1.0)
        } else {
            1.0
        };
        if q < 1.0 {
            let keep = roulette(q, choices.get(s)[2]);
            if keep == 0.0 {
                break;
            }
            beta *= keep;
        }
        if !(beta.max_element() > 0.0) {
            break;
        }
    }
    l
}

/// Russian roulette with probability `q` (in [0, 1]) on `u`: the weight of what goes on, 1 /
/// q, or 0 for what stops. `u` is a multiple of 2^-23 (Sobol sets; of 2^-24 past them), so q
/// is first rounded up to one: the chance that u < q is then q exactly, and the expectation
/// is kept.
#[inline]
fn roulette(q: f32, u: f32) -> f32 {
    const GRID: f32 = (1u32 << 23) as f32;
    let q = (q * GRID).ceil() / GRID;
    if u < q {
        1.0 / q
    } else {
        0.0
    }
}

/// What [`li`] returns for camera rays that hit nothing (their directions `d`, at most eight),
/// into `out`, bit for bit, and its counts: each infinite light's radiance along each, an
/// environment map's eight at once ([`crate::light::envmap::EnvMap::eval_many`]). False, with
/// nothing done, where [`li`] would not simply look them up (`max_depth` 0, hidden emitters,
/// the lookup ablated).
pub fn li_escaped(scene: &Scene, d: &[Vec3], out: &mut [Rgb], st: &mut Stats) -> bool {
    if !looks_up_escaped(scene) {
        return false;
    }
    let n = d.len();
    out[..n].fill(Rgb::ZERO);
    let mut le = [Rgb::ZERO; 8];
    for &k in &scene.infinite_lights {
        match &scene.lights[k as usize] {
            Light::Envmap(e) => e.eval_many(d, &mut le[..n]),
            light => {
                for (le, d) in le.iter_mut().zip(d) {
                    *le = light.le_infinite(*d);
                }
            }
        }
        // As li adds a light found by a camera ray: beta 1, weight 1.
        for (l, le) in out.iter_mut().zip(&le[..n]) {
            *l += Rgb::ONE * *le * 1.0;
        }
    }
    st.rays += n as u64;
    st.escaped_lookups += n as u64;
    true
}

/// Whether [`li_escaped`] looks up what camera rays that hit nothing bring (else it does
/// nothing and returns false).
#[inline]
pub fn looks_up_escaped(scene: &Scene) -> bool {
    let settings = &scene.integrator;
    settings.max_depth != 0 && !settings.hide_emitters && scene.techniques.escaped_rays_lookup
}

/// Scene loading: `path` (`max_depth` -1 = unlimited, `rr_depth` 5, `hide_emitters`).
pub(crate) fn from_scene(
    b: &mut crate::scene::build::Builder,
    i: usize,
) -> crate::scene::build::R<crate::scene::PathSettings> {
    let doc = b.doc;
    let max_depth = doc.int_or(i, "max_depth", -1)?;
    if max_depth < -1 {
        return Err(b.err(doc.pos_of(i, "max_depth"), "max_depth must be -1 (unlimited) or >= 0"));
    }
    let rr_depth = doc.int_or(i, "rr_depth", 5)?;
    if rr_depth <= 0 {
        return Err(b.err(doc.pos_of(i, "rr_depth"), "rr_depth must be > 0"));
    }
    Ok(crate::scene::PathSettings {
        max_depth: if max_depth < 0 { u32::MAX } else { max_depth.min(u32::MAX as i64) as u32 },
        rr_depth: rr_depth.min(u32::MAX as i64) as u32,
        hide_emitters: doc.boolean_or(i, "hide_emitters", false)?,
    })
}
