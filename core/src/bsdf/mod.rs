//! BSDFs in the local shading frame (z = shading normal). Directions point away from the
//! surface: `wo` towards the viewer, `wi` towards the light. `eval` includes the cosine
//! foreshortening |cos theta_i|, so a path's throughput is multiplied by `eval / pdf`.
//! Delta lobes have `eval` = `pdf` = 0 and are reached only by `sample`.

pub mod conductor;
pub mod dielectric;
pub mod diffuse;
pub mod hair;
pub mod microfacet;
pub mod plastic;

// Scene loading: `diffuse` and `twosided`, as the table in `scene::plugins` names them.
use crate::scene::build::{Builder, R};

/// `diffuse`: `reflectance` (0.5).
pub(crate) fn diffuse_from(b: &mut Builder, i: usize) -> R<Bsdf> {
    Ok(Bsdf::Diffuse { reflectance: b.color(i, "reflectance", Rgb::splat(0.5))? })
}

/// `twosided`: one nested BSDF for both sides, or a front and a back.
pub(crate) fn twosided_from(b: &mut Builder, i: usize) -> R<Bsdf> {
    let doc = b.doc;
    match doc.children(i, "bsdf").as_slice() {
        [(_, f, _)] => {
            let front = b.side(*f)?;
            Ok(Bsdf::TwoSided { front: front.clone(), back: front })
        }
        [(_, f, _), (_, bk, _)] => Ok(Bsdf::TwoSided { front: b.side(*f)?, back: b.side(*bk)? }),
        _ => Err(b.err(doc.obj(i).pos, "twosided needs one or two nested <bsdf>s")),
    }
}

#[cfg(test)]
mod tests;

use glam::{Vec2, Vec3};

use crate::math::Rgb;
use crate::texture::{TexCoord, Texture};

pub use conductor::{Conductor, Roughness};
pub use dielectric::Dielectric;
pub use microfacet::Distribution;
pub use plastic::{Plastic, RoughCoating};

/// What the integrator asks of a BSDF at every vertex ([`Bsdf::traits`]).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Traits {
    pub black: bool,
    pub smooth: bool,
    pub chooses_lobe: bool,
}

/// A sampled incident direction.
#[derive(Clone, Copy, Debug)]
pub struct BsdfSample {
    pub wi: Vec3,
    /// eval / pdf (for delta lobes, the lobe's weight / its selection probability).
    pub weight: Rgb,
    /// Solid-angle pdf (for delta lobes, the probability of choosing the lobe).
    pub pdf: f32,
    pub delta: bool,
    /// Relative index of refraction crossed (1 for reflection).
    pub eta: f32,
}

#[derive(Clone, Debug)]
pub enum Bsdf {
    /// Lambertian reflection (Mitsuba `diffuse`); black from the back.
    Diffuse { reflectance: Texture },
    /// Mitsuba `twosided`: `front` on the front side, `back` (mirrored) on the back side.
    TwoSided { front: Box<Bsdf>, back: Box<Bsdf> },
    /// `conductor` and `roughconductor`.
    Conductor(Conductor),
    /// `dielectric`, `roughdielectric` and `thindielectric`.
    Dielectric(Dielectric),
    /// `plastic`.
    Plastic(Plastic),
    /// `hair` (Chiang et al. 2016); the local x axis runs along the fibre.
    Hair(hair::Hair),
}

impl Bsdf {
    /// Plugin name, for the render plan.
    pub fn name(&self) -> &'static str {
        match self {
            Bsdf::Diffuse { .. } => "diffuse",
            Bsdf::TwoSided { .. } => "twosided",
            Bsdf::Conductor(c) if c.rough.is_some() => "roughconductor",
            Bsdf::Conductor(_) => "conductor",
            Bsdf::Dielectric(d) if d.thin => "thindielectric",
            Bsdf::Dielectric(d) if d.rough.is_some() => "roughdielectric",
            Bsdf::Dielectric(_) => "dielectric",
            Bsdf::Plastic(p) if p.rough.is_some() => "roughplastic",
            Bsdf::Plastic(_) => "plastic",
            Bsdf::Hair(_) => "hair",
        }
    }

    /// Whether `pred` holds for this BSDF or, for a two-sided one, either side.
    pub fn any(&self, pred: &dyn Fn(&Bsdf) -> bool) -> bool {
        pred(self) || matches!(self, Bsdf::TwoSided { front, back } if front.any(pred) || back.any(pred))
    }

    /// [`Bsdf::is_black`], [`Bsdf::is_smooth`] and [`Bsdf::chooses_lobe`] at once, for the
    /// scene to keep beside its BSDFs (the integrator asks at every vertex; a two-sided BSDF
    /// answers by recursion).
    pub fn traits(&self) -> Traits {
        Traits { black: self.is_black(), smooth: self.is_smooth(), chooses_lobe: self.chooses_lobe() }
    }

    /// Whether the BSDF has a non-delta component, so that light sampling can help.
    pub fn is_smooth(&self) -> bool {
        match self {
            Bsdf::Diffuse { .. } | Bsdf::Plastic(_) | Bsdf::Hair(_) => true,
            Bsdf::TwoSided { front, back } => front.is_smooth() || back.is_smooth(),
            Bsdf::Conductor(c) => c.rough.is_some(),
            Bsdf::Dielectric(d) => d.rough.is_some() && !d.thin,
        }
    }

    /// Whether `sample` uses its `u1` (to choose a lobe).
    pub fn chooses_lobe(&self) -> bool {
        match self {
            Bsdf::Diffuse { .. } | Bsdf::Conductor(_) => false,
            Bsdf::Dielectric(_) | Bsdf::Plastic(_) | Bsdf::Hair(_) => true,
            Bsdf::TwoSided { front, back } => front.chooses_lobe() || back.chooses_lobe(),
        }
    }

    /// Whether the BSDF reflects nothing at all (paths end there).
    pub fn is_black(&self) -> bool {
        match self {
            Bsdf::Diffuse { reflectance } => reflectance.is_black(),
            Bsdf::TwoSided { front, back } => front.is_black() && back.is_black(),
            _ => false,
        }
    }

    /// Whether the BSDF's value at a hit depends on more than the normal: a texture that is not
    /// constant (read at the hit's uv), or the tangent (anisotropic roughness; hair, whose x
    /// axis runs along the fibre). A sphere whose BSDF and emitter do not computes no uv or
    /// tangents ([`crate::geometry::Sphere::tangents`]).
    pub fn reads_surface(&self) -> bool {
        let anisotropic = |r: Option<&Roughness>| {
            r.is_some_and(|r| match (&r.alpha_u, &r.alpha_v) {
                (Texture::Const(a), Texture::Const(b)) => a != b,
                _ => true,
            })
        };
        self.textures().iter().any(|t| !t.is_const())
            || match self {
                Bsdf::Hair(_) => true,
                Bsdf::TwoSided { front, back } => front.reads_surface() || back.reads_surface(),
                Bsdf::Conductor(c) => anisotropic(c.rough.as_ref()),
                Bsdf::Dielectric(d) => anisotropic(d.rough.as_ref()),
                Bsdf::Plastic(p) => anisotropic(p.rough.as_ref().map(|r| &r.roughness)),
                Bsdf::Diffuse { .. } => false,
            }
    }

    /// Every texture the BSDF reads.
    pub fn textures(&self) -> Vec<&Texture> {
        match self {
            Bsdf::Diffuse { reflectance } => vec![reflectance],
            Bsdf::TwoSided { front, back } => {
                let mut t = front.textures();
                t.extend(back.textures());
                t
            }
            Bsdf::Conductor(c) => {
                let mut t = vec![&c.specular_reflectance];
                t.extend(rough_textures(&c.rough));
                t
            }
            Bsdf::Dielectric(d) => {
                let mut t = vec![&d.specular_reflectance, &d.specular_transmittance];
                t.extend(rough_textures(&d.rough));
                t
            }
            Bsdf::Plastic(p) => {
                let mut t = vec![&p.diffuse_reflectance, &p.specular_reflectance];
                if let Some(r) = &p.rough {
                    t.extend([&r.roughness.alpha_u, &r.roughness.alpha_v]);
                }
                t
            }
            Bsdf::Hair(_) => Vec::new(),
        }
    }

    /// The value (f |cos theta_i|) for `wi` given `wo`: [`Bsdf::eval_pdf`]'s first half.
    #[inline]
    pub fn eval(&self, uv: TexCoord, wo: Vec3, wi: Vec3) -> Rgb {
        self.eval_pdf(uv, wo, wi).0
    }

    /// The solid-angle density with which [`Bsdf::sample`] picks `wi` given `wo`:
    /// [`Bsdf::eval_pdf`]'s second half.
    #[inline]
    pub fn pdf(&self, uv: TexCoord, wo: Vec3, wi: Vec3) -> f32 {
        self.eval_pdf(uv, wo, wi).1
    }

    /// The value and the pdf of `wi` together: light sampling needs both (the pdf for MIS),
    /// and each BSDF computes the terms they share (half vector, Fresnel, D, G1, texture
    /// lookups) once.
    /// (Not inlined: in the integrator's loop, where it is called once a vertex, it crowded
    /// out the sampler's inlining.)
    #[inline(never)]
    pub fn eval_pdf(&self, uv: TexCoord, wo: Vec3, wi: Vec3) -> (Rgb, f32) {
        match self {
            Bsdf::Diffuse { reflectance } => (diffuse::eval(reflectance, uv, wo, wi), diffuse::pdf(wo, wi)),
            Bsdf::TwoSided { front, back } => {
                if wo.z >= 0.0 {
                    front.eval_pdf(uv, wo, wi)
                } else {
                    back.eval_pdf(uv, flip(wo), flip(wi))
                }
            }
            Bsdf::Conductor(c) => c.eval_pdf(uv, wo, wi),
            Bsdf::Dielectric(d) => d.eval_pdf(uv, wo, wi),
            Bsdf::Plastic(p) => p.eval_pdf(uv, wo, wi),
            Bsdf::Hair(h) => h.eval_pdf(wo, wi, hair::Hair::h_from(wo)),
        }
    }

    /// This BSDF seen from `wo` at one vertex ([`BsdfAt`]).
    #[inline]
    pub fn at(&self, wo: Vec3) -> BsdfAt<'_> {
        match self {
            Bsdf::Hair(h) => BsdfAt::Hair(h.at(wo, hair::Hair::h_from(wo))),
            b => BsdfAt::Other(b),
        }
    }

    /// Samples `wi` given `wo`; `u1` picks a lobe, `u2` the direction within it.
    #[inline]
    pub fn sample(&self, uv: TexCoord, wo: Vec3, u1: f32, u2: Vec2) -> Option<BsdfSample> {
        match self {
            Bsdf::Diffuse { reflectance } => diffuse::sample(reflectance, uv, wo, u2),
            Bsdf::TwoSided { front, back } => {
                if wo.z >= 0.0 {
                    front.sample(uv, wo, u1, u2)
                } else {
                    back.sample(uv, flip(wo), u1, u2).map(|s| BsdfSample { wi: flip(s.wi), ..s })
                }
            }
            Bsdf::Conductor(c) => c.sample(uv, wo, u2),
            Bsdf::Dielectric(d) => d.sample(uv, wo, u1, u2),
            Bsdf::Plastic(p) => p.sample(uv, wo, u1, u2),
            Bsdf::Hair(h) => h.sample(wo, hair::Hair::h_from(wo), u1, u2),
        }
    }
}

/// A BSDF at one path vertex, seen from one `wo` ([`Bsdf::at`]): where a BSDF's evaluations
/// for a given wo share work, it is done once for the vertex's light sample and its BSDF
/// sample. Only hair has such work (wo's angles, the lobes' attenuations, their tilts and
/// azimuthal centres); every other BSDF is evaluated as [`Bsdf::eval_pdf`] and
/// [`Bsdf::sample`] do, the same values.
#[derive(Clone, Copy)]
pub enum BsdfAt<'a> {
    Hair(hair::HairAt<'a>),
    Other(&'a Bsdf),
}

impl BsdfAt<'_> {
    /// [`Bsdf::eval_pdf`] for this vertex's wo (the one it was made for: `wo` is passed
    /// again, rather than kept in the enum, so that no copy of it is read back wide while its
    /// coordinates are still being stored: `math::apart`).
    #[inline]
    pub fn eval_pdf(&self, uv: TexCoord, wo: Vec3, wi: Vec3) -> (Rgb, f32) {
        match self {
            BsdfAt::Hair(h) => h.eval_pdf(wi),
            BsdfAt::Other(b) => b.eval_pdf(uv, wo, wi),
        }
    }

    /// [`Bsdf::sample`] for this vertex's wo (passed again, as to [`BsdfAt::eval_pdf`]).
    #[inline]
    pub fn sample(&self, uv: TexCoord, wo: Vec3, u1: f32, u2: Vec2) -> Option<BsdfSample> {
        match self {
            BsdfAt::Hair(h) => h.sample(u1, u2),
            BsdfAt::Other(b) => b.sample(uv, wo, u1, u2),
        }
    }
}

fn rough_textures(r: &Option<Roughness>) -> Vec<&Texture> {
    r.as_ref().map(|r| vec![&r.alpha_u, &r.alpha_v]).unwrap_or_default()
}

#[inline]
fn flip(v: Vec3) -> Vec3 {
    Vec3::new(v.x, v.y, -v.z)
}
