//! BSDFs in the local shading frame (z = shading normal). Directions point away from the
//! surface: `wo` towards the viewer, `wi` towards the light. `eval` includes the cosine
//! foreshortening |cos theta_i|, so a path's throughput is multiplied by `eval / pdf`.

pub mod diffuse;

use glam::{Vec2, Vec3};

use crate::math::Rgb;
use crate::texture::Texture;

/// A sampled incident direction.
#[derive(Clone, Copy, Debug)]
pub struct BsdfSample {
    pub wi: Vec3,
    /// eval / pdf (for delta lobes, the lobe's weight).
    pub weight: Rgb,
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
}

impl Bsdf {
    /// Whether the BSDF has a non-delta component, so that light sampling can help.
    pub fn is_smooth(&self) -> bool {
        match self {
            Bsdf::Diffuse { .. } => true,
            Bsdf::TwoSided { front, back } => front.is_smooth() || back.is_smooth(),
        }
    }

    /// Whether the BSDF reflects nothing at all (paths end there).
    pub fn is_black(&self) -> bool {
        match self {
            Bsdf::Diffuse { reflectance } => reflectance.is_black(),
            Bsdf::TwoSided { front, back } => front.is_black() && back.is_black(),
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
        }
    }

    #[inline]
    pub fn eval(&self, uv: Vec2, wo: Vec3, wi: Vec3) -> Rgb {
        match self {
            Bsdf::Diffuse { reflectance } => diffuse::eval(reflectance, uv, wo, wi),
            Bsdf::TwoSided { front, back } => {
                if wo.z >= 0.0 {
                    front.eval(uv, wo, wi)
                } else {
                    back.eval(uv, flip(wo), flip(wi))
                }
            }
        }
    }

    #[inline]
    #[allow(clippy::only_used_in_recursion)] // textured lobes will read uv
    pub fn pdf(&self, uv: Vec2, wo: Vec3, wi: Vec3) -> f32 {
        match self {
            Bsdf::Diffuse { .. } => diffuse::pdf(wo, wi),
            Bsdf::TwoSided { front, back } => {
                if wo.z >= 0.0 {
                    front.pdf(uv, wo, wi)
                } else {
                    back.pdf(uv, flip(wo), flip(wi))
                }
            }
        }
    }

    /// Samples `wi` given `wo`; `u1` picks a lobe, `u2` the direction within it.
    #[inline]
    #[allow(clippy::only_used_in_recursion)] // u1 picks lobes of multi-lobe BSDFs
    pub fn sample(&self, uv: Vec2, wo: Vec3, u1: f32, u2: Vec2) -> Option<BsdfSample> {
        match self {
            Bsdf::Diffuse { reflectance } => diffuse::sample(reflectance, uv, wo, u2),
            Bsdf::TwoSided { front, back } => {
                if wo.z >= 0.0 {
                    front.sample(uv, wo, u1, u2)
                } else {
                    back.sample(uv, flip(wo), u1, u2).map(|s| BsdfSample { wi: flip(s.wi), ..s })
                }
            }
        }
    }
}

#[inline]
fn flip(v: Vec3) -> Vec3 {
    Vec3::new(v.x, v.y, -v.z)
}
