//! Lambertian reflection: f = R / pi on the front side, sampled by the cosine-weighted hemisphere.

use glam::{Vec2, Vec3};

use super::BsdfSample;
use crate::math::{square_to_cosine_hemisphere, Rgb, INV_PI};
use crate::texture::{TexCoord, Texture};

#[inline]
pub fn eval(r: &Texture, uv: TexCoord, wo: Vec3, wi: Vec3) -> Rgb {
    if wo.z <= 0.0 || wi.z <= 0.0 {
        return Rgb::ZERO;
    }
    r.eval(uv) * (INV_PI * wi.z)
}

#[inline]
pub fn pdf(wo: Vec3, wi: Vec3) -> f32 {
    if wo.z <= 0.0 || wi.z <= 0.0 {
        0.0
    } else {
        wi.z * INV_PI
    }
}

#[inline]
pub fn sample(r: &Texture, uv: TexCoord, wo: Vec3, u: Vec2) -> Option<BsdfSample> {
    if wo.z <= 0.0 {
        return None;
    }
    let wi = square_to_cosine_hemisphere(u);
    let pdf = wi.z * INV_PI;
    if pdf <= 0.0 {
        return None;
    }
    Some(BsdfSample { wi, weight: r.eval(uv), pdf, delta: false, eta: 1.0 })
}
