//! Emitters: `area` (on any shape), `point`, `spot`, `directional`, `constant` and `envmap`.
//!
//! `sample` returns a direction towards the light from a reference point with its radiance and
//! its solid-angle pdf; `pdf_hit` gives the pdf with which `sample` would have produced a
//! surface point that a BSDF-sampled ray hit, so that both strategies can be weighted by MIS.

pub mod envmap;

pub use envmap::EnvMap;

use glam::{Vec2, Vec3};

use crate::geometry::{Geometry, Interaction, Shape, Sphere};
use crate::math::{square_to_uniform_sphere, Frame, Rgb, INV_FOUR_PI, PI};
use crate::texture::Texture;

/// Kinds of emitters, for the render plan and statistics.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, PartialOrd, Ord)]
pub enum LightKind {
    Area,
    Point,
    Spot,
    Directional,
    Constant,
    Envmap,
}

impl LightKind {
    pub const COUNT: usize = 6;
    pub const ALL: [LightKind; LightKind::COUNT] = [
        LightKind::Area,
        LightKind::Point,
        LightKind::Spot,
        LightKind::Directional,
        LightKind::Constant,
        LightKind::Envmap,
    ];

    /// Whether rays that BSDF sampling traces can find this kind of light (area lights and
    /// lights at infinity, not the delta ones): what MIS weighs against light sampling.
    pub fn is_hit_by_rays(self) -> bool {
        matches!(self, LightKind::Area | LightKind::Constant | LightKind::Envmap)
    }

    pub fn name(self) -> &'static str {
        match self {
            LightKind::Area => "area",
            LightKind::Point => "point",
            LightKind::Spot => "spot",
            LightKind::Directional => "directional",
            LightKind::Constant => "constant",
            LightKind::Envmap => "envmap",
        }
    }
}

#[derive(Clone, Debug)]
pub enum Light {
    Area {
        shape: u32,
        radiance: Texture,
        /// Normalised cumulative area of the shape's primitives (f64), length prims + 1.
        cdf: Vec<f64>,
        area: f64,
    },
    Point {
        position: Vec3,
        intensity: Rgb,
    },
    /// Mitsuba's `spot`: intensity at the axis (+z of `to_world`), full up to `beam_width`,
    /// falling linearly in angle to 0 at `cutoff`.
    Spot {
        position: Vec3,
        axis: Vec3,
        intensity: Rgb,
        cos_cutoff: f32,
        cos_beam: f32,
        cutoff: f32,
        beam: f32,
    },
    /// Light from one direction: `direction` is where the light travels.
    Directional {
        direction: Vec3,
        irradiance: Rgb,
    },
    /// `compensated`: MIS compensation (Karlik et al. 2019, as for an environment map): a
    /// constant is nowhere brighter than its mean, so light sampling leaves all of it to BSDF
    /// sampling, which weights what it finds by 1 (its light pdf is 0). Only beside BSDF
    /// sampling with MIS; light sampling alone samples the sphere uniformly.
    Constant {
        radiance: Rgb,
        compensated: bool,
    },
    Envmap(std::sync::Arc<EnvMap>),
}

/// A light sample as seen from a reference point.
#[derive(Clone, Copy, Debug)]
pub struct LightSample {
    /// Unit direction from the reference point towards the light.
    pub wi: Vec3,
    /// Incident radiance (the caller divides by `pdf`): [`LightSample::li`].
    li: Incident,
    /// Solid-angle pdf of `wi` (1 for delta lights).
    pub pdf: f32,
    pub delta: bool,
    /// The point on the light, offset off its surface, and its distance from the reference
    /// point (the length that `wi` was normalised by); `None` for lights at infinity.
    pub target: Option<(Vec3, f32)>,
}

/// A light sample's incident radiance, or the point of an environment map where it is to be
/// looked up: only once the shadow ray is clear (in fur many are blocked), as the lookup is a
/// bilinear fetch from a large image, unless a light-sample cutoff needs it before
/// (`Techniques::light_cutoff`).
#[derive(Clone, Copy, Debug)]
enum Incident {
    Known(Rgb),
    EnvMap(Vec2),
}

impl LightSample {
    /// Whether the incident radiance is certainly zero (an environment map's, not yet looked
    /// up, is taken as not: importance sampling picks only directions where it shines, up to
    /// underflow of a tiny `scale`, which then costs a shadow ray and adds zero).
    pub fn is_black(&self) -> bool {
        matches!(self.li, Incident::Known(c) if c == Rgb::ZERO)
    }

    /// The incident radiance, from `light`, the light that gave this sample.
    pub fn li(&self, light: &Light) -> Rgb {
        match (self.li, light) {
            (Incident::Known(c), _) => c,
            (Incident::EnvMap(uv), Light::Envmap(e)) => e.radiance_at(uv),
            (Incident::EnvMap(_), _) => unreachable!("an environment map's sample from another light"),
        }
    }
}

impl Light {
    pub fn kind(&self) -> LightKind {
        match self {
            Light::Area { .. } => LightKind::Area,
            Light::Point { .. } => LightKind::Point,
            Light::Spot { .. } => LightKind::Spot,
            Light::Directional { .. } => LightKind::Directional,
            Light::Constant { .. } => LightKind::Constant,
            Light::Envmap(_) => LightKind::Envmap,
        }
    }

    pub fn area(shape_idx: u32, shape: &Shape, radiance: Texture) -> Light {
        let n = shape.prim_count();
        let mut cdf = Vec::with_capacity(n + 1);
        let mut acc = 0.0f64;
        cdf.push(0.0);
        for i in 0..n {
            acc += shape.prim_area(i);
            cdf.push(acc);
        }
        for c in &mut cdf {
            *c /= acc;
        }
        Light::Area { shape: shape_idx, radiance, cdf, area: acc }
    }

    /// Whether light sampling picks this light: not a MIS-compensated constant, nor an
    /// environment map with nothing to sample (black, or constant and compensated), which it
    /// leaves to BSDF sampling.
    pub fn is_sampled(&self) -> bool {
        match self {
            Light::Constant { compensated, .. } => !compensated,
            Light::Envmap(e) => e.is_sampled(),
            _ => true,
        }
    }

    /// Turns MIS compensation of an environment map or a constant off (see each).
    pub fn disable_mis_compensation(&mut self) {
        match self {
            Light::Envmap(e) => *e = std::sync::Arc::new(e.with_compensation(false)),
            Light::Constant { compensated, .. } => *compensated = false,
            _ => {}
        }
    }

    /// Whether light sampling uses a MIS-compensated density (or, for a constant, leaves it
    /// all to BSDF sampling).
    pub fn is_compensated(&self) -> bool {
        match self {
            Light::Envmap(e) => e.compensated(),
            Light::Constant { compensated, .. } => *compensated,
            _ => false,
        }
    }

    /// Whether the light reads the uv of the points it emits from (an area light's radiance
    /// texture).
    pub fn reads_surface(&self) -> bool {
        matches!(self, Light::Area { radiance, .. } if !radiance.is_const())
    }

    /// Lights that escaped rays can hit (not the delta `directional`).
    pub fn is_infinite(&self) -> bool {
        matches!(self, Light::Constant { .. } | Light::Envmap(_))
    }

    /// Samples the light from `it` with `u`. Its first number also chooses an area light's
    /// primitive ([`pick_reuse`]); `spare` is a further uniform number, asked for only when the
    /// chosen primitive's share is too small for that.
    pub fn sample(
        &self,
        shapes: &[Shape],
        it: &Interaction,
        u: Vec2,
        spare: impl FnOnce() -> f32,
    ) -> Option<LightSample> {
        match self {
            Light::Area { shape, radiance, cdf, area } => {
                let sh = &shapes[*shape as usize];
                if let Geometry::Sphere(s) = &sh.geometry {
                    if !sh.flip_normals {
                        if let Some(ls) = sample_sphere_cone(s, it.p, u, radiance) {
                            return Some(ls);
                        }
                    }
                }
                let sp = match sh.sample_whole(u) {
                    Some(sp) => sp,
                    None => {
                        let (prim, ux) = pick_reuse(cdf, u.x, spare);
                        sh.sample_prim(prim, Vec2::new(ux, u.y))
                    }
                };
                let v = sp.p - it.p;
                let dist2 = v.length_squared();
                if dist2 == 0.0 {
                    return None;
                }
                let dist = dist2.sqrt();
                let wi = v / dist;
                let cos_l = -sp.n.dot(wi);
                if cos_l <= 0.0 {
                    return None; // the sampled point faces away: emits nothing towards `it`
                }
                let pdf = dist2 / (cos_l * *area as f32);
                let li = radiance.eval(sp.uv.into());
                Some(LightSample {
                    wi,
                    li: Incident::Known(li),
                    pdf,
                    delta: false,
                    target: Some((crate::math::offset_ray_origin(sp.p, sp.p_err, sp.n, -wi), dist)),
                })
            }
            Light::Point { position, intensity } => {
                let v = *position - it.p;
                let dist2 = v.length_squared();
                if dist2 == 0.0 {
                    return None;
                }
                let dist = dist2.sqrt();
                Some(LightSample {
                    wi: v / dist,
                    li: Incident::Known(*intensity / dist2),
                    pdf: 1.0,
                    delta: true,
                    target: Some((*position, dist)),
                })
            }
            Light::Spot { position, axis, intensity, cos_cutoff, cos_beam, cutoff, beam } => {
                let v = *position - it.p;
                let dist2 = v.length_squared();
                if dist2 == 0.0 {
                    return None;
                }
                let dist = dist2.sqrt();
                let wi = v / dist;
                let cos = (-wi).dot(*axis);
                let falloff = if cos >= *cos_beam {
                    1.0
                } else if cos <= *cos_cutoff {
                    return None;
                } else {
                    ((cutoff - crate::math::safe_acos(cos)) / (cutoff - beam)).clamp(0.0, 1.0)
                };
                Some(LightSample {
                    wi,
                    li: Incident::Known(*intensity * (falloff / dist2)),
                    pdf: 1.0,
                    delta: true,
                    target: Some((*position, dist)),
                })
            }
            Light::Directional { direction, irradiance } => Some(LightSample {
                wi: -*direction,
                li: Incident::Known(*irradiance),
                pdf: 1.0,
                delta: true,
                target: None,
            }),
            Light::Constant { compensated: true, .. } => None,
            Light::Constant { radiance, compensated: false } => Some(LightSample {
                wi: square_to_uniform_sphere(u),
                li: Incident::Known(*radiance),
                pdf: INV_FOUR_PI,
                delta: false,
                target: None,
            }),
            Light::Envmap(e) => {
                let (wi, uv, pdf) = e.sample_direction(u)?;
                // Sampled by the map, a direction shines (its density follows the luminance);
                // sampled uniformly (the ablation), it may not: looked up now, as a black one
                // needs no shadow ray.
                let li = if e.uniform { Incident::Known(e.radiance_at(uv)) } else { Incident::EnvMap(uv) };
                Some(LightSample { wi, li, pdf, delta: false, target: None })
            }
        }
    }

    /// Solid-angle pdf with which [`Light::sample`] from `p_ref` yields the point `hit` on this
    /// (area) light, reached along unit direction `wi`.
    pub fn pdf_hit(&self, shapes: &[Shape], p_ref: Vec3, wi: Vec3, hit: &Interaction) -> f32 {
        match self {
            Light::Area { shape, area, .. } => {
                let sh = &shapes[*shape as usize];
                if let Geometry::Sphere(s) = &sh.geometry {
                    if !sh.flip_normals {
                        if let Some(one_minus_cos) = cone_extent(s.center, s.radius, p_ref) {
                            return 1.0 / (2.0 * PI * one_minus_cos);
                        }
                    }
                }
                let cos_l = hit.frame.n.dot(-wi).abs();
                if cos_l == 0.0 {
                    return 0.0;
                }
                let dist2 = (hit.p - p_ref).length_squared();
                dist2 / (cos_l * *area as f32)
            }
            _ => 0.0,
        }
    }

    /// Solid-angle pdf with which [`Light::sample`] yields direction `d` of a light at infinity.
    pub fn pdf_infinite(&self, d: Vec3) -> f32 {
        match self {
            Light::Constant { compensated: true, .. } => 0.0,
            Light::Constant { .. } => INV_FOUR_PI,
            Light::Envmap(e) => e.pdf(d),
            _ => 0.0,
        }
    }

    /// Radiance leaving an area light's surface point `hit` towards `wo` (unit, world).
    pub fn le_surface(&self, hit: &Interaction, wo: Vec3) -> Rgb {
        match self {
            Light::Area { radiance, .. } if hit.frame.n.dot(wo) > 0.0 => radiance.eval(hit.uv.into()),
            _ => Rgb::ZERO,
        }
    }

    /// Radiance arriving from infinity along direction `-d` (a ray travelling along `d` escaped).
    pub fn le_infinite(&self, d: Vec3) -> Rgb {
        match self {
            Light::Constant { radiance, .. } => *radiance,
            Light::Envmap(e) => e.eval(d),
            _ => Rgb::ZERO,
        }
    }

    /// [`Light::le_infinite`] and [`Light::pdf_infinite`] at once.
    pub fn le_pdf_infinite(&self, d: Vec3) -> (Rgb, f32) {
        match self {
            Light::Envmap(e) => e.eval_pdf(d),
            _ => (self.le_infinite(d), self.pdf_infinite(d)),
        }
    }
}

/// Index `i` with cdf[i] <= u < cdf[i + 1].
fn pick(cdf: &[f64], u: f32) -> usize {
    let n = cdf.len() - 1;
    let u = u as f64;
    cdf.partition_point(|&c| c <= u).saturating_sub(1).min(n - 1)
}

/// A choice's share of [0, 1) below which [`pick_reuse`] does not reuse the number: rescaling
/// by a share p leaves log2(1 / p) fewer of its 23 bits, and a mesh emitter of a million
/// triangles would otherwise put every sample on a few lines across each triangle.
const REUSE_MIN_SHARE: f64 = 1.0 / 64.0;

/// [`pick`], and a uniform number for the chosen primitive: `u` rescaled to [0, 1) within the
/// chosen interval, to be used again (as Mitsuba does for a mesh emitter's triangle), so that
/// a primitive and the point on it come from one stratified 2-D sample and the points
/// stratify over the whole light; or, where the interval is narrower than
/// [`REUSE_MIN_SHARE`], `spare()`. A single primitive (cdf [0, 1]) leaves `u` exactly as it was.
fn pick_reuse(cdf: &[f64], u: f32, spare: impl FnOnce() -> f32) -> (usize, f32) {
    let i = pick(cdf, u);
    let (lo, hi) = (cdf[i], cdf[i + 1]);
    let v = if hi - lo >= REUSE_MIN_SHARE { ((u as f64 - lo) / (hi - lo)) as f32 } else { spare() };
    (i, v.clamp(0.0, 1.0 - f32::EPSILON / 2.0))
}

/// 1 - cos(theta_max) of the cone a sphere subtends from `p`, or `None` when `p` is inside it.
/// Computed as sin^2 / (1 + cos) to stay accurate for tiny, distant spheres.
fn cone_extent(center: Vec3, radius: f32, p: Vec3) -> Option<f32> {
    let d2 = (center - p).length_squared();
    let r2 = radius * radius;
    if d2 <= r2 * 1.0001 {
        return None;
    }
    let sin2 = r2 / d2;
    let cos = (1.0 - sin2).max(0.0).sqrt();
    Some(sin2 / (1.0 + cos))
}

/// Uniform sampling of the cone of directions subtended by a sphere (pbrt 3rd ed., 14.2.2).
fn sample_sphere_cone(s: &Sphere, p: Vec3, u: Vec2, radiance: &Texture) -> Option<LightSample> {
    let (center, radius) = (s.center, s.radius);
    let one_minus_cos_max = cone_extent(center, radius, p)?;
    let to_c = center - p;
    let dc = to_c.length();
    let axis = to_c / dc;
    // cos theta = 1 - u (1 - cos theta_max), kept in "1 - cos" form for accuracy.
    let one_minus_cos = u.y * one_minus_cos_max;
    let cos_t = 1.0 - one_minus_cos;
    let sin2_t = (one_minus_cos * (2.0 - one_minus_cos)).max(0.0);
    let sin_t = sin2_t.sqrt();
    let (sp, cp) = crate::math::sin_cos_2pi(u.x);
    let frame = Frame::from_normal(axis);
    let wi = frame.to_world(Vec3::new(sin_t * cp, sin_t * sp, cos_t)).normalize();
    // Distance to the near intersection with the sphere along wi.
    let ds = dc * cos_t - (radius * radius - dc * dc * sin2_t).max(0.0).sqrt();
    let hit = p + wi * ds;
    let n = (hit - center).normalize();
    let p_on = center + n * radius;
    let p_err = (center.abs() + (n * radius).abs()) * crate::math::gamma(6);
    Some(LightSample {
        wi,
        li: Incident::Known(radiance.eval(s.uv(n).into())),
        pdf: 1.0 / (2.0 * PI * one_minus_cos_max),
        delta: false,
        target: Some((crate::math::offset_ray_origin(p_on, p_err, n, -wi), ds)),
    })
}

// Scene loading: the emitters that stand alone, and `area`'s radiance (the shape it is nested
// in makes the light).
use crate::scene::build::{Builder, R};
use crate::scene::xml::Pos;

/// `point`: `intensity`, `position` or `to_world`.
pub(crate) fn point_from(b: &mut Builder, i: usize, pos: Pos) -> R<Light> {
    let doc = b.doc;
    let intensity = b.const_color(i, "intensity", Rgb::ONE)?;
    let position = match (doc.transform(i, "to_world")?, doc.point(i, "position")?) {
        (Some(_), Some(_)) => {
            return Err(b.err(pos, "point emitter: give 'position' or 'to_world', not both"))
        }
        (Some(m), None) => m.transform_point3(Vec3::ZERO),
        (None, Some(p)) => p,
        (None, None) => Vec3::ZERO,
    };
    Ok(Light::Point { position, intensity })
}

/// `constant`: `radiance`. MIS-compensated, as an environment map is by default (Mitsuba's
/// `constant` has no switch for it; `furnace report` measures it off).
pub(crate) fn constant_from(b: &mut Builder, i: usize, _: Pos) -> R<Light> {
    Ok(Light::Constant { radiance: b.const_color(i, "radiance", Rgb::ONE)?, compensated: true })
}

/// `directional`: `irradiance`, `direction` or `to_world`.
pub(crate) fn directional_from(b: &mut Builder, i: usize, pos: Pos) -> R<Light> {
    let doc = b.doc;
    let irradiance = b.const_color(i, "irradiance", Rgb::ONE)?;
    let direction = match (doc.point(i, "direction")?, doc.transform(i, "to_world")?) {
        (Some(_), Some(_)) => return Err(b.err(pos, "directional: give 'direction' or 'to_world', not both")),
        (Some(d), None) => d,
        (None, Some(m)) => m.transform_vector3(Vec3::Z),
        (None, None) => Vec3::Z,
    };
    if direction.length_squared() == 0.0 || !direction.is_finite() {
        return Err(b.err(pos, "directional: the direction must be a non-zero vector"));
    }
    Ok(Light::Directional { direction: direction.normalize(), irradiance })
}

/// `spot`: `intensity`, `cutoff_angle` (20), `beam_width` (3/4 of the cutoff), `to_world`.
pub(crate) fn spot_from(b: &mut Builder, i: usize, pos: Pos) -> R<Light> {
    let doc = b.doc;
    let intensity = b.const_color(i, "intensity", Rgb::ONE)?;
    let cutoff = doc.float_or(i, "cutoff_angle", 20.0)?;
    let beam = doc.float_or(i, "beam_width", cutoff * 0.75)?;
    if !(cutoff > 0.0 && cutoff <= 180.0 && beam > 0.0 && beam <= cutoff) {
        return Err(
            b.err(pos, format!("spot: need 0 < beam_width ({beam}) <= cutoff_angle ({cutoff}) <= 180"))
        );
    }
    let m = doc.transform(i, "to_world")?.unwrap_or(glam::Mat4::IDENTITY);
    let (cutoff, beam) = (cutoff.to_radians(), beam.to_radians());
    Ok(Light::Spot {
        position: m.transform_point3(Vec3::ZERO),
        axis: m.transform_vector3(Vec3::Z).normalize(),
        intensity,
        cos_cutoff: cutoff.cos(),
        cos_beam: beam.cos(),
        cutoff,
        beam,
    })
}

/// `area`'s radiance (a colour or a texture); the light is made with its shape.
pub(crate) fn area_radiance_from(b: &mut Builder, i: usize) -> R<Texture> {
    b.color(i, "radiance", Rgb::ONE)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Shadow rays towards an area light and a point light never find the light's own surface
    /// (nor the surface a point light sits on): floors far from the origin with the light
    /// close above, where a surface's offset is large beside the light's distance. (A shadow
    /// ray that kept the light sample's direction from the unoffset point, shifted by the
    /// floor's offset, ended past the light's surface in most of these samples.)
    #[test]
    fn shadow_rays_stop_short_of_the_light_they_aim_at() {
        use crate::geometry::{Accel, Geometry, Mesh, Ray};
        use glam::{Mat4, Quat};
        let mut checked = 0;
        for (y, height, half) in
            [(0.75f32, 1e-3f32, 0.5f32), (5.0, 0.02, 1.0), (1000.0, 1.0, 3.0), (1e4, 2.0, 5.0)]
        {
            let place = |at: f32, size: f32, facing_down: bool| {
                let turn = Quat::from_rotation_x(if facing_down { 90f32 } else { -90f32 }.to_radians());
                Mat4::from_scale_rotation_translation(Vec3::splat(size), turn, Vec3::new(0.3, at, -0.2))
            };
            let shape = |m: Mat4, name: &str| Shape {
                geometry: Geometry::Mesh(Mesh::placed_rectangle(&m)),
                bsdf: 0,
                light: None,
                flip_normals: false,
                name: name.into(),
            };
            let shapes = vec![
                shape(place(y, half, false), "floor"),
                shape(place(y + height, 0.2 * half, true), "light"),
            ];
            let accel = Accel::build(&shapes);
            let area = Light::area(1, &shapes[1], Texture::Const(Rgb::ONE));
            // A point light on the light's plane, as one screwed into a ceiling.
            let point = Light::Point { position: Vec3::new(0.3, y + height, -0.2), intensity: Rgb::ONE };
            for i in 0..400 {
                let f = |k: u32| ((i * 7 + k * 131) % 400) as f32 / 400.0;
                let at = Vec3::new(
                    0.3 + half * 0.9 * (2.0 * f(1) - 1.0),
                    y + 0.5 * height,
                    -0.2 + half * 0.9 * (2.0 * f(2) - 1.0),
                );
                let it = accel.intersect(&shapes, &Ray::new(at, -Vec3::Y)).expect("the floor is below");
                assert_eq!(it.shape, 0);
                for light in [&area, &point] {
                    let Some(ls) = light.sample(&shapes, &it, Vec2::new(f(3), f(4)), || 0.5) else {
                        continue;
                    };
                    let (target, dist) = ls.target.expect("a light at a point");
                    let ray = it.spawn_ray_to(ls.wi, target, dist);
                    assert!(
                        !accel.occluded(&shapes, &ray),
                        "y {y} height {height}: {ray:?} hits the light's own plane"
                    );
                    checked += 1;
                }
            }
        }
        assert!(checked > 2000, "{checked}");
    }

    /// An environment map's samples: by importance, the radiance is looked up later, never
    /// taken as black, and is the white half's; by the uniform ablation, a black direction is
    /// known black at once (no shadow ray) and the radiance is the map's in that direction.
    #[test]
    fn environment_samples_defer_only_what_shines() {
        use crate::texture::{Bitmap, FilterType};
        // The upper half of the sky white, the lower black.
        let texels = (0..8 * 4).map(|k| if k < 16 { Rgb::ONE } else { Rgb::ZERO }).collect();
        let bmp = std::sync::Arc::new(Bitmap { width: 8, height: 4, texels });
        let it = Interaction {
            p: Vec3::ZERO,
            p_err: Vec3::ZERO,
            t: 1.0,
            ng: Vec3::Y,
            frame: crate::math::Frame::from_normal(Vec3::Y),
            uv: Vec2::ZERO,
            dpdu: Vec3::X,
            dpdv: Vec3::Z,
            shape: 0,
            prim: 0,
            piece: None,
            instance: None,
        };
        for uniform in [false, true] {
            let mut env = EnvMap::new(bmp.clone(), 1.0, glam::Mat3::IDENTITY, FilterType::Nearest, false);
            env.uniform = uniform;
            let light = Light::Envmap(std::sync::Arc::new(env));
            let (mut black, mut none, n) = (0, 0, 1000);
            for i in 0..n {
                let u = Vec2::new((i as f32 + 0.5) / n as f32, (i as f32 * 0.618_034).fract());
                // (None only where a sample's pdf rounds to 0, at a pole.)
                let Some(ls) = light.sample(&[], &it, u, || 0.5) else {
                    none += 1;
                    continue;
                };
                black += ls.is_black() as usize;
                if uniform {
                    let Light::Envmap(e) = &light else { unreachable!() };
                    assert_eq!(ls.li(&light), e.eval(ls.wi), "{i}");
                } else {
                    assert!(matches!(ls.li, Incident::EnvMap(_)) && ls.li(&light) == Rgb::ONE, "{i}");
                }
            }
            // Uniformly, about half the sphere is black; by importance, none of it.
            assert!(if uniform { (400..600).contains(&black) } else { black == 0 }, "{uniform}: {black}");
            assert!(none < 10, "{uniform}: {none} samples without a direction");
        }
    }

    /// The reused number covers [0, 1) again within each primitive, in order, and a single
    /// primitive's is the number itself.
    #[test]
    fn pick_reuse_rescales_within_the_choice() {
        let none = || -> f32 { panic!("the spare number was asked for") };
        let cdf = [0.0, 0.25, 0.25, 1.0];
        assert_eq!(pick_reuse(&cdf, 0.0, none), (0, 0.0));
        assert_eq!(pick_reuse(&cdf, 0.125, none), (0, 0.5));
        assert_eq!(pick_reuse(&cdf, 0.25, none), (2, 0.0));
        assert_eq!(pick_reuse(&cdf, 0.625, none), (2, 0.5));
        let (k, v) = pick_reuse(&cdf, 1.0 - f32::EPSILON / 2.0, none);
        assert!(k == 2 && v < 1.0);
        for i in 0..1000 {
            let u = i as f32 / 1000.0;
            assert_eq!(pick_reuse(&[0.0, 1.0], u, none), (0, u));
        }
        // A narrow share takes the spare number instead of a few bits of `u`.
        let narrow = [0.0, 0.001, 1.0];
        assert_eq!(pick_reuse(&narrow, 0.0005, || 0.75), (0, 0.75));
        assert_eq!(pick_reuse(&narrow, 0.5, || 0.75).0, 1);
    }

    #[test]
    fn pick_follows_the_cdf() {
        let cdf = [0.0, 0.25, 0.25, 1.0];
        assert_eq!(pick(&cdf, 0.0), 0);
        assert_eq!(pick(&cdf, 0.2), 0);
        assert_eq!(pick(&cdf, 0.25), 2);
        assert_eq!(pick(&cdf, 0.999_999), 2);
    }

    #[test]
    fn cone_of_a_tiny_far_sphere_keeps_its_precision() {
        // A sun of 0.002 sr: 1 - cos = omega / (2 pi).
        let omega = 0.002f32;
        let one_minus_cos = omega / (2.0 * PI);
        let sin2 = one_minus_cos * (2.0 - one_minus_cos);
        let d = 1.0e4f32;
        let r = d * sin2.sqrt();
        let e = cone_extent(Vec3::new(0.0, 0.0, d), r, Vec3::ZERO).unwrap();
        assert!((e - one_minus_cos).abs() / one_minus_cos < 1e-4, "{e} vs {one_minus_cos}");
    }
}
